//! Stability suite: every model's whole parameter box plus its edges.
//!
//! For each model: construction either succeeds or returns an error naming the
//! parameter; evaluation is finite and non-negative; sampled values lie inside the
//! support and their pdfs agree with the pdf functions; energy is conserved per
//! excitation wavelength. Bugs found here get pinned regression cases below.

use fluo::models::jung::{max_stokes_shift, JungFluorescence, JungParams, EMISSION_PEAK_RANGE_NM};
use proptest::prelude::*;

/// Wavelengths worth probing: the ends of 300–830 nm plus a sweep.
fn probe_wavelengths(m: &JungFluorescence) -> Vec<f64> {
    let (alo, ahi) = m.absorption_support();
    let (elo, ehi) = m.emission_support();
    let mut v = vec![300.0, 360.0, 829.999, 830.0, alo, ahi, elo, ehi, m.absorption_peak(), m.params().emission_peak];
    v.extend((0..=53).map(|i| 300.0 + 10.0 * i as f64));
    v
}

fn check_jung(p: JungParams) -> Result<(), TestCaseError> {
    let m = match JungFluorescence::new(p) {
        Ok(m) => m,
        Err(e) => {
            let msg = e.to_string();
            prop_assert!(
                ["emission_peak", "stokes_shift", "concentration", "quantum_yield"].iter().any(|n| msg.contains(n)),
                "error does not name a parameter: {msg}"
            );
            return Ok(());
        }
    };
    prop_assert!(m.absorption_integral().is_finite() && m.absorption_integral() > 0.0);
    for l in probe_wavelengths(&m) {
        let (a, e, k) = (m.absorption(l), m.emission(l), m.elastic_factor(l));
        prop_assert!(a.is_finite() && (0.0..=1.0 + 1e-12).contains(&a), "a({l}) = {a}");
        prop_assert!(e.is_finite() && e >= 0.0, "e({l}) = {e}");
        prop_assert!(k.is_finite() && (0.0..=1.0).contains(&k), "1 - c a({l}) = {k}");
        for lo in [300.0, 500.0, 830.0] {
            let r = m.reradiation(l, lo);
            prop_assert!(r.is_finite() && r >= 0.0);
        }
        let cdf = m.absorption_cdf(l);
        prop_assert!(cdf.is_finite() && cdf >= 0.0 && cdf <= m.absorption_integral() * (1.0 + 1e-12));
    }
    // Energy per excitation wavelength: elastic + reradiated = 1 − c a + c Q a ≤ 1.
    for l in probe_wavelengths(&m) {
        let total = m.elastic_factor(l) + p.concentration * p.quantum_yield * m.absorption(l);
        prop_assert!(total <= 1.0 + 1e-12);
    }
    for xi in [0.0, 1e-9, 0.25, 0.5, 0.75, 1.0 - 1e-9, 1.0] {
        let (lo, pdf) = m.sample_emission(xi);
        let (elo, ehi) = m.emission_support();
        prop_assert!(lo >= elo - 1e-9 && lo <= ehi + 1e-9 && pdf.is_finite() && pdf >= 0.0);
        for (rlo, rhi) in [(0.0, f64::INFINITY), (300.0, 830.0), (360.0, 830.0)] {
            if let Some((li, pdf)) = m.sample_absorption(xi, rlo, rhi) {
                let (slo, shi) = m.absorption_support();
                prop_assert!(li >= slo.max(rlo) && li <= shi.min(rhi), "λi {li} outside");
                prop_assert!(pdf.is_finite() && pdf > 0.0);
                let want = m.absorption_pdf(li, rlo, rhi);
                prop_assert!((pdf - want).abs() <= 1e-9 * want, "pdf {pdf} vs {want}");
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    /// The valid box: emission peak, Stokes shift as a fraction of its maximum, c, Q.
    #[test]
    fn jung_valid_box(le in EMISSION_PEAK_RANGE_NM.0..=EMISSION_PEAK_RANGE_NM.1,
                      frac in 1e-6f64..0.999_999,
                      c in 0.0f64..=1.0, q in 0.0f64..=1.0) {
        let s = (frac * max_stokes_shift(le)).max(1e-3);
        check_jung(JungParams { emission_peak: le, stokes_shift: s, concentration: c, quantum_yield: q })?;
    }

    /// Anything at all: must construct cleanly or fail with a named parameter.
    #[test]
    fn jung_any_input(le in prop::num::f64::ANY, s in prop::num::f64::ANY,
                      c in prop::num::f64::ANY, q in prop::num::f64::ANY) {
        check_jung(JungParams { emission_peak: le, stokes_shift: s, concentration: c, quantum_yield: q })?;
    }
}

/// Edges of the box, enumerated.
#[test]
fn jung_edges() {
    let (lo, hi) = EMISSION_PEAK_RANGE_NM;
    for le in [lo, 300.0, 520.0, 830.0, hi] {
        let smax = max_stokes_shift(le);
        for s in [1e-3, 1e-2, 1.0, 0.5 * smax, smax * (1.0 - 1e-12), smax, 2.0 * le - 1e-9, 2.0 * le] {
            for c in [0.0, 1.0] {
                for q in [0.0, 1.0] {
                    check_jung(JungParams { emission_peak: le, stokes_shift: s, concentration: c, quantum_yield: q })
                        .unwrap_or_else(|e| panic!("λe={le} s={s} c={c} q={q}: {e}"));
                }
            }
        }
    }
}

// ------------------------------------------------------------------------ fluo_qd

mod qd {
    use fluo::models::qd::{Distribution, QdIndex, QdModel, QdParams, Substrate};
    use fluo::Bispectral;
    use proptest::prelude::*;

    const PARAM_NAMES: [&str; 7] = ["radius", "width", "quantum_yield", "density", "alpha", "lambda_m", "gap_energy"];

    fn dir(cos: f64, phi: f64) -> [f64; 3] {
        let s = (1.0 - cos * cos).max(0.0).sqrt();
        [s * phi.cos(), s * phi.sin(), cos]
    }

    /// Finite, non-negative values; sampled wavelengths inside their ranges with pdfs
    /// equal to the pdf functions; R_tot + Q A_tot ≤ 1 for every θ and λi (the
    /// Fresnel-level energy bound that, with ∫ D G1 ≤ 1, bounds the white furnace).
    pub fn check(p: QdParams, substrate: Substrate) -> Result<(), TestCaseError> {
        let m = match QdModel::new(p, QdIndex::CdSe, substrate) {
            Ok(m) => m,
            Err(e) => {
                let msg = e.to_string();
                prop_assert!(
                    PARAM_NAMES.iter().any(|n| msg.contains(n)) || msg.contains("eta") || msg.contains("ext_ior"),
                    "error does not name a parameter: {msg}"
                );
                return Ok(());
            }
        };
        let lq = m.band().lambda_qd_nm;
        let mut lambdas = vec![300.0, 830.0, lq, lq - 1e-9, lq + 1e-9, m.band().emission_peak_nm];
        lambdas.extend((0..=27).map(|i| 300.0 + 20.0 * i as f64));
        let cosines = [0.0, 1e-9, 1e-4, 0.01, 0.3, 0.7, 0.999_999, 1.0];
        for &c in &cosines {
            for &l in &lambdas {
                let (r, a) = (m.r_tot(c, l), m.a_tot(c, l));
                prop_assert!(
                    r.is_finite() && r >= 0.0 && a.is_finite() && a >= 0.0,
                    "R_tot {r} A_tot {a} at cos {c} λ {l}"
                );
                prop_assert!(
                    r + p.quantum_yield * a <= 1.0 + 1e-12,
                    "energy at cos {c} λ {l}: {}",
                    r + p.quantum_yield * a
                );
            }
        }
        let range = (300.0, 830.0);
        for &c in &cosines[1..] {
            let wi = dir(c, 0.3);
            for &co in &cosines[1..] {
                let wo = dir(co, 2.9);
                for &l in &lambdas {
                    let e = m.elastic(wi, wo, l);
                    prop_assert!(e.is_finite() && e >= 0.0, "elastic {e}");
                    let f = m.reradiation(wi, wo, 350.0, l);
                    prop_assert!(f.is_finite() && f >= 0.0, "reradiation {f}");
                }
            }
            for xi in [0.0, 1e-9, 0.5, 1.0 - 1e-9, 1.0] {
                for &lo in &lambdas {
                    if let Some((li, pdf)) = m.sample_excitation(wi, lo, xi, range) {
                        prop_assert!(
                            li >= 300.0 && li <= lo.min(830.0) && pdf.is_finite() && pdf > 0.0,
                            "λi {li} pdf {pdf}"
                        );
                        let want = m.excitation_pdf(wi, lo, li, range);
                        prop_assert!((pdf - want).abs() <= 1e-9 * want, "pdf {pdf} vs {want}");
                    }
                    let s = m.shift_albedo(wi, lo, range);
                    prop_assert!(s.is_finite() && s >= 0.0);
                }
                for &li in &[300.0, 400.0, lq] {
                    if let Some((lo, pdf)) = m.sample_emission(wi, li, xi) {
                        prop_assert!(lo > li && lo <= 830.0 && pdf.is_finite() && pdf > 0.0, "λo {lo} pdf {pdf}");
                        let want = m.emission_pdf(wi, li, lo);
                        prop_assert!((pdf - want).abs() <= 1e-9 * want, "pdf {pdf} vs {want}");
                    }
                }
            }
        }
        Ok(())
    }

    fn substrate(k: f64) -> Substrate {
        Substrate::Constant { eta: 0.2, k }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

        /// The valid box (radius, width, Q, ρ, α, distribution, substrate).
        #[test]
        fn qd_valid_box(r in 1.0f64..=5.0, w in 0.01f64..=100.0, q in 0.0f64..=1.0, rho in 0.0f64..=1.0,
                        alpha in 0.0f64..=1.0, ggx in any::<bool>(), k in 0.0f64..1e3) {
            let p = QdParams { radius_nm: r, width_nm: w, quantum_yield: q, density: rho, alpha,
                               distribution: if ggx { Distribution::Ggx } else { Distribution::Beckmann },
                               ..QdParams::default() };
            check(p, substrate(k))?;
        }

        /// Anything at all: must construct cleanly or fail with a named parameter.
        #[test]
        fn qd_any_input(r in prop::num::f64::ANY, w in prop::num::f64::ANY, q in prop::num::f64::ANY,
                        rho in prop::num::f64::ANY, alpha in prop::num::f64::ANY) {
            let p = QdParams { radius_nm: r, width_nm: w, quantum_yield: q, density: rho, alpha, ..QdParams::default() };
            check(p, substrate(2.0))?;
        }
    }

    /// Edges of the box: R at 1 and 5 nm, δλ tiny and large, Q = ρ = 1, α → 0 and 1,
    /// perfect mirror and dielectric substrates.
    #[test]
    fn qd_edges() {
        for r in [1.0, 5.0] {
            for w in [0.01, 15.0, 100.0] {
                for (q, rho) in [(0.0, 0.0), (1.0, 1.0), (0.0, 1.0)] {
                    for alpha in [0.0, 1e-4, 1.0] {
                        for s in [Substrate::Constant { eta: 1e-3, k: 1e3 }, Substrate::Constant { eta: 1.5, k: 0.0 }] {
                            let p = QdParams {
                                radius_nm: r,
                                width_nm: w,
                                quantum_yield: q,
                                density: rho,
                                alpha,
                                ..QdParams::default()
                            };
                            check(p, s).unwrap_or_else(|e| panic!("R={r} δ={w} Q={q} ρ={rho} α={alpha}: {e}"));
                        }
                    }
                }
            }
        }
    }
}

// ------------------------------------------------------------- upsampling

mod upsample {
    use super::*;
    use fluo::upsample::{Cube, Lookup};
    use std::sync::OnceLock;

    fn cube() -> &'static Cube {
        static CUBE: OnceLock<Cube> = OnceLock::new();
        CUBE.get_or_init(|| {
            Cube::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/cubes/acescg_d65_tinf_r33.cube"))
                .expect("shipped ACEScg cube")
        })
    }

    /// Whatever colour comes in: a valid Jung material (every lookup mode, with and
    /// without fluorescence) inside [0, 1]³, an error naming `color` outside.
    fn check_lookup(rgb: [f64; 3]) -> Result<(), TestCaseError> {
        let inside = rgb.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v));
        for mode in [Lookup::Nearest, Lookup::Trilinear] {
            for fl in [true, false] {
                match cube().lookup(rgb, mode, fl) {
                    Ok(c) => {
                        prop_assert!(inside, "{rgb:?} accepted");
                        prop_assert!(c.reflectance.iter().all(|x| x.is_finite()));
                        let p = JungParams {
                            emission_peak: c.emission_peak,
                            stokes_shift: c.stokes_shift,
                            concentration: c.concentration,
                            quantum_yield: fluo::upsample::QUANTUM_YIELD,
                        };
                        prop_assert!(JungFluorescence::new(p).is_ok(), "{rgb:?} -> {p:?}");
                        check_jung(p)?;
                    }
                    Err(e) => {
                        prop_assert!(!inside, "{rgb:?}: {e}");
                        prop_assert!(e.to_string().contains("\"color\""), "{e}");
                    }
                }
            }
        }
        Ok(())
    }

    /// Regression: trilinear weights summed to 1 + 2⁻⁵² and gave concentration > 1.
    #[test]
    fn lookup_blend_keeps_concentration_in_range() {
        check_lookup([0.9704927459488814, 0.05562379772230015, 0.005569884935046937]).unwrap();
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

        #[test]
        fn lookup_unit_cube(r in 0.0f64..=1.0, g in 0.0f64..=1.0, b in 0.0f64..=1.0) {
            check_lookup([r, g, b])?;
        }

        #[test]
        fn lookup_any_input(r in prop::num::f64::ANY, g in -0.5f64..1.5, b in prop::num::f64::ANY) {
            check_lookup([r, g, b])?;
        }
    }

    #[test]
    fn lookup_edges() {
        for v in [[0.0; 3], [1.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1e-12], [0.5, 1.0, 0.0]] {
            check_lookup(v).unwrap();
        }
    }
}

// ------------------------------------------------------------------ measured models
// fluo_matrix (core/src/models/matrix.rs) and fluo_gmm (core/src/models/gmm.rs): random matrices on the BFC-like
// grid (λo ⊂ λi) with noise (negatives, below-diagonal values, zero columns) and random
// mixtures (any weights, means far outside the domain, near-singular covariances).

mod measured {
    use super::*;
    use fluo::models::gmm::{Component, Diagonal, FitInfo, GmmFile, GmmModel, Scaling, FORMAT};
    use fluo::models::matrix::{Donaldson, Filtered, MatrixModel};

    /// λ worth probing: grid ends, just inside/outside, between nodes, Mitsuba's range ends.
    fn probes(lo: f64, hi: f64) -> Vec<f64> {
        let mut v = vec![lo, hi, lo - 1e-9, hi + 1e-9, lo + 1e-9, hi - 1e-9, 299.0, 360.0, 830.0];
        v.extend((0..=20).map(|i| lo + (hi - lo) * i as f64 / 20.0 + 0.37));
        v
    }

    /// A random matrix: λi = start + 10k (n_i), λo = the last n_o of them; column sums ≤ 1.
    fn matrix(n_i: usize, n_o: usize, raw: &[f64]) -> Donaldson {
        let li: Vec<f64> = (0..n_i).map(|k| 300.0 + 10.0 * k as f64).collect();
        let lo: Vec<f64> = li[n_i - n_o..].to_vec();
        let mut v = vec![0.0; n_i * n_o];
        for (idx, x) in v.iter_mut().enumerate() {
            *x = raw[idx % raw.len()];
        }
        // Normalise the non-negative part of each column to at most 1 (energy).
        for k in 0..n_i {
            let s: f64 = (0..n_o).map(|j| v[j * n_i + k].max(0.0)).sum();
            if s > 1.0 {
                for j in 0..n_o {
                    v[j * n_i + k] /= s;
                }
            }
        }
        Donaldson::new("random", li, lo, v).unwrap()
    }

    fn check_matrix(d: &Donaldson) -> Result<(), TestCaseError> {
        let f = Filtered::new(d).unwrap();
        let m = MatrixModel::new(&f).unwrap();
        let (lo_i, hi_i) = (d.lambda_i[0], d.lambda_i[d.lambda_i.len() - 1]);
        let (lo_o, hi_o) = (d.lambda_o[0], d.lambda_o[d.lambda_o.len() - 1]);
        for li in probes(lo_i, hi_i) {
            let total = m.reradiated_albedo(li);
            prop_assert!(total.is_finite() && total >= 0.0);
            // energy: reflectance + reradiated ≤ 1 at excitation wavelengths on the λo grid
            if li >= lo_o && li <= hi_o {
                prop_assert!(m.reflectance(li) + total <= 1.0 + 1e-9, "λi {li}: {}", m.reflectance(li) + total);
            }
            for lo in probes(lo_o, hi_o) {
                let p = m.reradiation(li, lo);
                prop_assert!(p.is_finite() && p >= 0.0);
                if li > lo {
                    prop_assert!(p == 0.0);
                }
            }
            for xi in [0.0, 1e-12, 0.5, 1.0 - 1e-12, 1.0] {
                if let Some((lo, pdf)) = m.sample_emission(li, xi) {
                    prop_assert!(lo >= li.max(lo_o) && lo <= hi_o && pdf.is_finite() && pdf > 0.0);
                    let want = m.emission_pdf(li, lo);
                    prop_assert!((pdf - want).abs() <= 1e-9 * want, "pdf {pdf} vs {want}");
                }
            }
        }
        for lo in probes(lo_o, hi_o) {
            for (a, b) in [(0.0, f64::INFINITY), (300.0, 830.0), (355.0, 375.0)] {
                let mass = m.absorbed_into(lo, a, b);
                prop_assert!(mass.is_finite() && mass >= 0.0);
                for xi in [0.0, 0.3, 1.0] {
                    if let Some((li, pdf)) = m.sample_excitation(lo, xi, a, b) {
                        prop_assert!(li >= a && li <= b.min(lo) && pdf.is_finite() && pdf > 0.0);
                        let want = m.excitation_pdf(lo, li, a, b);
                        prop_assert!((pdf - want).abs() <= 1e-9 * want);
                    }
                }
            }
        }
        Ok(())
    }

    fn gmm(parts: &[(f64, f64, f64, f64, f64, f64)], scale: f64) -> Option<GmmModel> {
        let total: f64 = parts.iter().map(|p| p.0).sum();
        if !(total > 0.0) {
            return None;
        }
        let components = parts
            .iter()
            .map(|&(w, ma, mb, sa, sb, rho)| Component {
                weight: w / total,
                mean: [ma, mb],
                covariance: [[sa * sa, rho * sa * sb], [rho * sa * sb, sb * sb]],
            })
            .collect();
        let file = GmmFile {
            format: FORMAT.into(),
            version: 1,
            source: "random".into(),
            lambda_i_range_nm: [300.0, 780.0],
            lambda_o_range_nm: [380.0, 780.0],
            diagonal: Diagonal { wavelengths_nm: vec![380.0, 780.0], values: vec![0.1, 0.9] },
            scaling: Scaling::IntegralRatio,
            scale,
            scale_integral_ratio: scale,
            scale_error_minimisation: scale,
            components,
            fit: FitInfo {
                method: "weighted_em".into(),
                iterations: 0,
                converged: true,
                log_likelihood: 0.0,
                seed: 0,
                restarts: 0,
                regularisation_nm2: [0.0, 0.0],
            },
        };
        match GmmModel::new(file) {
            Ok(m) => Some(m),
            Err(e) => {
                assert!(e.to_string().contains("components["), "{e}");
                None
            }
        }
    }

    fn check_gmm(m: &GmmModel) -> Result<(), TestCaseError> {
        for li in probes(300.0, 780.0) {
            let a = m.reradiated_albedo(li);
            prop_assert!(a.is_finite() && a >= 0.0);
            for lo in probes(380.0, 780.0) {
                let p = m.reradiation(li, lo);
                prop_assert!(p.is_finite() && p >= 0.0);
            }
            for xi in [0.0, 1e-12, 0.5, 1.0 - 1e-12, 1.0] {
                if let Some((lo, pdf)) = m.sample_emission(li, xi) {
                    prop_assert!(lo >= li.max(380.0) && lo <= 780.0 && pdf.is_finite() && pdf > 0.0, "{li} -> {lo}");
                    let want = m.emission_pdf(li, lo);
                    prop_assert!((pdf - want).abs() <= 1e-9 * want, "pdf {pdf} vs {want}");
                }
            }
        }
        for lo in probes(380.0, 780.0) {
            for (a, b) in [(300.0, 830.0), (355.0, 375.0)] {
                prop_assert!(m.absorbed_into(lo, a, b).is_finite());
                for xi in [0.0, 0.5, 1.0] {
                    if let Some((li, pdf)) = m.sample_excitation(lo, xi, a, b) {
                        prop_assert!(li >= a && li <= b.min(lo) && pdf.is_finite() && pdf > 0.0);
                        let want = m.excitation_pdf(lo, li, a, b);
                        prop_assert!((pdf - want).abs() <= 1e-9 * want);
                    }
                }
            }
        }
        Ok(())
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

        #[test]
        fn matrix_random(n_i in 2usize..12, frac in 0.0f64..=1.0,
                         raw in prop::collection::vec(-0.05f64..0.3, 1..64)) {
            let n_o = ((n_i as f64 * frac).round() as usize).clamp(2, n_i);
            check_matrix(&matrix(n_i, n_o, &raw))?;
        }

        #[test]
        fn gmm_random(parts in prop::collection::vec(
                          (0.0f64..1.0, 0.0f64..1200.0, 0.0f64..1200.0, 0.5f64..300.0, 0.5f64..300.0, -0.999f64..0.999),
                          1..6),
                      scale in 0.0f64..1000.0) {
            if let Some(m) = gmm(&parts, scale) {
                check_gmm(&m)?;
            }
        }
    }

    /// Edges: all-zero and pure-diagonal matrices, a single narrow component at the top
    /// corner, components far outside the domain, near-singular covariances.
    #[test]
    fn measured_edges() {
        check_matrix(&matrix(3, 2, &[0.0])).unwrap();
        check_matrix(&matrix(49, 41, &[-0.01, 0.0])).unwrap();
        check_matrix(&matrix(49, 41, &[1.0])).unwrap();
        for parts in [
            vec![(1.0, 779.0, 779.9, 0.5, 0.5, 0.0)],
            vec![(1.0, -5000.0, 9000.0, 1.0, 1.0, 0.0)],
            vec![(1.0, 500.0, 600.0, 300.0, 0.5, 0.999)],
            vec![(0.5, 400.0, 500.0, 10.0, 10.0, -0.999), (0.5, 770.0, 300.0, 5.0, 5.0, 0.5)],
        ] {
            if let Some(m) = gmm(&parts, 50.0) {
                check_gmm(&m).unwrap();
            }
        }
    }
}
