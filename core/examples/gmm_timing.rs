//! Timing of `fluo_gmm` against `fluo_matrix` on the same measured material, through the
//! [`Bispectral`] methods a wavelength-shifting path tracer calls at a fluorescent vertex.
//!
//! ```text
//! cargo run --release -p fluo --example gmm_timing [-- ROUNDS]
//! cargo run --release -p fluo --example gmm_timing -- --dump > values.txt
//! ```
//!
//! Each round times every method on the mixture and then on the matrix (paired,
//! interleaved, so that a shared machine's load hits both alike); the medians over the
//! rounds are printed in ns/call with the gmm/matrix ratio. `--dump` prints the mixture's
//! values on a fixed grid instead, for comparing two builds to the last digit.
//!
//! The light range is that of a visible-light scene, [360, 830] nm; wi is the normal.

use std::hint::black_box;
use std::path::Path;
use std::time::Instant;

use fluo::models::gmm::GmmModel;
use fluo::models::matrix::MatrixModel;
use fluo::Bispectral;

/// Excitation range of the scene's light, nm.
const LIGHT_RANGE_NM: (f64, f64) = (360.0, 830.0);
/// Calls per method per model per round.
const CALLS: usize = 20_000;
/// Default number of rounds (the median is taken over them).
const DEFAULT_ROUNDS: usize = 9;
const NORMAL: [f64; 3] = [0.0, 0.0, 1.0];

/// Wavelengths over [380, 780] nm and uniforms in [0, 1), from a fixed LCG.
fn inputs(n: usize) -> Vec<(f64, f64, f64)> {
    let mut s: u64 = 0x853c_49e6_748f_ea9b;
    let mut next = || {
        s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n).map(|_| (380.0 + 400.0 * next(), 380.0 + 400.0 * next(), next())).collect()
}

/// (λo, λi, ξ) per call.
type Inputs = [(f64, f64, f64)];
/// Calls one method once per input and sums the results.
type Method = fn(&dyn Bispectral, &Inputs) -> f64;
type Bench = (&'static str, Method);

/// The timed methods; each returns a sum so that nothing is optimised away.
const BENCHES: [Bench; 6] = [
    ("shift_albedo", |m, xs| xs.iter().map(|&(lo, _, _)| m.shift_albedo(NORMAL, lo, LIGHT_RANGE_NM)).sum()),
    ("sample_excitation", |m, xs| {
        xs.iter().filter_map(|&(lo, _, u)| m.sample_excitation(NORMAL, lo, u, LIGHT_RANGE_NM)).map(|s| s.0 + s.1).sum()
    }),
    ("excitation_pdf", |m, xs| {
        xs.iter().map(|&(lo, li, _)| m.excitation_pdf(NORMAL, lo, li.min(lo), LIGHT_RANGE_NM)).sum()
    }),
    ("sample_emission", |m, xs| {
        xs.iter().filter_map(|&(_, li, u)| m.sample_emission(NORMAL, li - 60.0, u)).map(|s| s.0 + s.1).sum()
    }),
    ("emission_pdf", |m, xs| xs.iter().map(|&(lo, li, _)| m.emission_pdf(NORMAL, li.min(lo) - 60.0, lo)).sum()),
    ("reradiation", |m, xs| xs.iter().map(|&(lo, li, _)| m.reradiation(NORMAL, NORMAL, li.min(lo) - 60.0, lo)).sum()),
];

fn time(f: Method, m: &dyn Bispectral, xs: &Inputs) -> f64 {
    let t = Instant::now();
    black_box(f(black_box(m), black_box(xs)));
    t.elapsed().as_nanos() as f64 / xs.len() as f64
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn dump(m: &dyn Bispectral) {
    for i in 0..=400 {
        let lo = 380.0 + i as f64;
        println!("shift_albedo {lo} {:e}", m.shift_albedo(NORMAL, lo, LIGHT_RANGE_NM));
        for u in [0.0, 0.1, 0.37, 0.5, 0.83, 0.999] {
            let s = m.sample_excitation(NORMAL, lo, u, LIGHT_RANGE_NM).unwrap_or((f64::NAN, f64::NAN));
            println!("sample_excitation {lo} {u} {:e} {:e}", s.0, s.1);
            let e = m.sample_emission(NORMAL, lo - 80.0, u).unwrap_or((f64::NAN, f64::NAN));
            println!("sample_emission {} {u} {:e} {:e}", lo - 80.0, e.0, e.1);
        }
        for li in [300.0, 370.0, 420.0, 500.0, 650.0, 779.0] {
            println!("excitation_pdf {lo} {li} {:e}", m.excitation_pdf(NORMAL, lo, li, LIGHT_RANGE_NM));
            println!("emission_pdf {li} {lo} {:e}", m.emission_pdf(NORMAL, li, lo));
        }
    }
}

fn main() -> fluo::Result<()> {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/matrices");
    let gmm = GmmModel::from_file(data.join("jung_orange.gmm.json"))?;
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().is_some_and(|a| a == "--dump") {
        dump(&gmm);
        return Ok(());
    }
    let rounds = args.first().and_then(|a| a.parse().ok()).unwrap_or(DEFAULT_ROUNDS).max(1);
    let matrix = MatrixModel::from_file(data.join("jung_orange.csv"))?;
    let xs = inputs(CALLS);
    let mut ns = vec![(Vec::new(), Vec::new()); BENCHES.len()];
    for _ in 0..rounds {
        for ((_, f), (g, m)) in BENCHES.iter().zip(ns.iter_mut()) {
            g.push(time(*f, &gmm, &xs));
            m.push(time(*f, &matrix, &xs));
        }
    }
    println!("{:<18} {:>10} {:>10} {:>8}   (median of {rounds} rounds, ns/call)", "method", "gmm", "matrix", "ratio");
    for ((name, _), (g, m)) in BENCHES.iter().zip(ns) {
        let (g, m) = (median(g), median(m));
        println!("{name:<18} {g:>10.1} {m:>10.1} {:>8.2}", g / m);
    }
    Ok(())
}
