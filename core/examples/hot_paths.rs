//! Timing of the per-vertex methods a wavelength-shifting render calls, ns/call.
//!
//! `cargo run --release -p fluo --example hot_paths [rounds]` prints, per method, the
//! median over `rounds` (default 7) of the mean time per call over a fixed batch of
//! pseudo-random inputs. To compare two builds on a shared machine, run their binaries
//! alternately and take the median of the medians.

use std::hint::black_box;
use std::time::Instant;

use fluo::interface::Bispectral;
use fluo::models::jung::{JungFluorescence, JungParams};
use fluo::models::matrix::{shared_bispectral_files, MatrixModel};
use fluo::models::qd::{QdIndex, QdModel, QdParams, Substrate};
use fluo::spectrum::{illuminant, IrregularSpectrum, Spectral};

/// Inputs per batch.
const BATCH: usize = 20_000;

/// Deterministic uniform numbers in [0, 1) (splitmix64).
fn uniforms(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            (z >> 11) as f64 / (1u64 << 53) as f64
        })
        .collect()
}

/// A direction in the upper hemisphere from two uniforms (cos θ uniform in (0, 1]).
fn dir(u: f64, v: f64) -> [f64; 3] {
    let c = 1.0 - u;
    let s = (1.0 - c * c).max(0.0).sqrt();
    let p = 2.0 * std::f64::consts::PI * v;
    [s * p.cos(), s * p.sin(), c]
}

/// Median over `rounds` of the mean ns per call of `f` over `0..BATCH`.
fn time(rounds: usize, mut f: impl FnMut(usize) -> f64) -> f64 {
    let mut v: Vec<f64> = (0..rounds)
        .map(|_| {
            let t = Instant::now();
            let mut acc = 0.0;
            for i in 0..BATCH {
                acc += f(i);
            }
            black_box(acc);
            t.elapsed().as_nanos() as f64 / BATCH as f64
        })
        .collect();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let rounds = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(7usize).max(1);
    let u = [uniforms(BATCH, 1), uniforms(BATCH, 2), uniforms(BATCH, 3), uniforms(BATCH, 4), uniforms(BATCH, 5)];
    let wi: Vec<[f64; 3]> = (0..BATCH).map(|i| dir(u[0][i], u[1][i])).collect();
    let wo: Vec<[f64; 3]> = (0..BATCH).map(|i| dir(u[2][i], u[3][i])).collect();
    let range = (360.0, 830.0);
    let visible = |i: usize, k: usize| 360.0 + 470.0 * u[k][i];
    let mut rows: Vec<(&str, f64)> = Vec::new();

    // fluo_qd: default coating over gold
    let qd = QdModel::new(QdParams::default(), QdIndex::CdSe, Substrate::Constant { eta: 0.27, k: 2.9 }).unwrap();
    let (xlo, xhi) = qd.excitation_range().unwrap();
    let peak = qd.band().emission_peak_nm;
    let li = |i: usize| xlo.max(360.0) + (xhi - xlo.max(360.0)) * u[4][i];
    let lo = |i: usize| peak - 60.0 + 120.0 * u[2][i];
    rows.push(("qd reradiation", time(rounds, |i| qd.reradiation(wi[i], wo[i], li(i), lo(i)))));
    rows.push(("qd shift_albedo", time(rounds, |i| qd.shift_albedo(wi[i], lo(i), range))));
    rows.push((
        "qd sample_excitation",
        time(rounds, |i| qd.sample_excitation(wi[i], lo(i), u[3][i], range).map_or(0.0, |s| s.0)),
    ));
    rows.push(("qd excitation_pdf", time(rounds, |i| qd.excitation_pdf(wi[i], lo(i), li(i), range))));
    rows.push(("qd sample_emission", time(rounds, |i| qd.sample_emission(wi[i], li(i), u[3][i]).map_or(0.0, |s| s.0))));
    rows.push(("qd elastic_albedo (r_tot)", time(rounds, |i| qd.elastic_albedo(wi[i][2], visible(i, 4)))));
    rows.push((
        "qd coating (elastic coefficients)",
        time(rounds, |i| {
            let c = qd.coating(wi[i][2], visible(i, 4));
            let t = c.t_spe * (1.0 - c.a_tf);
            c.r_spe + t * t
        }),
    ));

    // fluo_jung: default dye
    let jung = JungFluorescence::new(JungParams::default()).unwrap();
    let (elo, ehi) = jung.emission_support();
    let jo = |i: usize| elo + (ehi - elo) * u[2][i];
    rows.push((
        "jung sample_excitation",
        time(rounds, |i| jung.sample_excitation(wi[i], jo(i), u[3][i], range).map_or(0.0, |s| s.0)),
    ));
    rows.push(("jung excitation_pdf", time(rounds, |i| jung.excitation_pdf(wi[i], jo(i), visible(i, 4), range))));
    rows.push(("jung shift_albedo", time(rounds, |i| jung.shift_albedo(wi[i], jo(i), range))));

    // fluo_matrix: the first shared measurement (10 nm BFC grids)
    if let Some(path) = shared_bispectral_files().into_iter().find(|p| p.to_string_lossy().ends_with(".BFC")) {
        let m = MatrixModel::from_file(&path).unwrap();
        let (ml, mh) = m.emission_support().unwrap();
        let mo = |i: usize| ml + (mh - ml) * u[2][i];
        rows.push(("matrix reradiation", time(rounds, |i| m.reradiation(visible(i, 4), mo(i)))));
        rows.push((
            "matrix sample_excitation",
            time(rounds, |i| m.sample_excitation(mo(i), u[3][i], 300.0, 830.0).map_or(0.0, |s| s.0)),
        ));
        rows.push(("matrix excitation_pdf", time(rounds, |i| m.excitation_pdf(mo(i), visible(i, 4), 300.0, 830.0))));
        rows.push(("matrix reflectance", time(rounds, |i| m.reflectance(visible(i, 4)))));
    } else {
        eprintln!("no shared BFC file: matrix rows skipped");
    }

    // spectra: D65 as the plugin holds it (irregular form of the 5 nm table)
    let d65 = IrregularSpectrum::from(illuminant("D65").unwrap());
    rows.push(("spectrum D65 eval (irregular form)", time(rounds, |i| d65.eval(visible(i, 4)))));
    let fl2 = illuminant("FL2").unwrap();
    rows.push(("spectrum FL2 eval (regular form)", time(rounds, |i| fl2.eval(visible(i, 4)))));

    for (name, ns) in rows {
        println!("{name:<36} {ns:>9.1}");
    }
}
