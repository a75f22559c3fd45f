//! Material descriptions for the command line, and the closed set of fluorescent media
//! ([`MediumModel`]). The closed set of surface models, [`crate::models::Model`], sits beside
//! their modules.
//!
//! # Command-line materials (`fluo patch --material M`)
//! `M` is a JSON object, given inline or as a path to a `.json` file:
//!
//! ```json
//! {"model": "jung", "emission_peak": 520, "stokes_shift": 60,
//!  "concentration": 0.8, "quantum_yield": 0.96,
//!  "reflectance": 0.5}                       // or {"coefficients": [c0, c1, c2]}
//! ```
//!
//! Omitted fields take the plugin defaults (those of `fluo_jung`). Unknown models and
//! fields are errors.
//!
//! Measured materials are given by their file instead: a reradiation matrix
//! (`*.bfc`, `*.csv`, `*.exr`: the tabulated model of `fluo_matrix`,
//! [`crate::models::matrix`]) or a Gaussian-mixture fit (`*.gmm.json`: `fluo_gmm`,
//! [`crate::models::gmm`]).

use std::fmt;

use serde_json::Value;

use crate::interface::Bispectral;
use crate::models::gmm::GmmModel;
use crate::models::jung::{DyeMedium, JungMaterial, JungParams, Reflectance};
use crate::models::matrix::MatrixModel;
use crate::models::qd::QdMedium;
use crate::sigmoid::SigmoidPolynomial;
use crate::{Error, Result};

/// Read a material argument: inline JSON (starting with `{`) or a path to a JSON file.
pub fn load_material(arg: &str) -> Result<Box<dyn Bispectral>> {
    if let Some(measured) = load_measured(arg) {
        return measured;
    }
    let text = if arg.trim_start().starts_with('{') {
        arg.to_string()
    } else {
        crate::fileio::read_text(std::path::Path::new(arg), crate::fileio::MAX_SMALL_FILE_BYTES, "material JSON")?
    };
    let v: Value = serde_json::from_str(&text).map_err(|e| Error::data(format!("material JSON: {e}")))?;
    material_from_json(&v)
}

/// A measured material file by extension (`.bfc`, `.csv`, `.exr`, `.gmm.json`), or `None`.
fn load_measured(arg: &str) -> Option<Result<Box<dyn Bispectral>>> {
    let lower = arg.trim().to_ascii_lowercase();
    if lower.ends_with(".gmm.json") {
        return Some(GmmModel::from_file(arg.trim()).map(|m| Box::new(m) as Box<dyn Bispectral>));
    }
    if [".bfc", ".csv", ".exr"].iter().any(|e| lower.ends_with(e)) {
        return Some(MatrixModel::from_file(arg.trim()).map(|m| Box::new(m) as Box<dyn Bispectral>));
    }
    None
}

fn number(v: &Value, key: &str, default: f64) -> Result<f64> {
    match v.get(key) {
        None => Ok(default),
        Some(x) => x.as_f64().ok_or_else(|| Error::param(key, x, "a number")),
    }
}

/// Build a material from its JSON description.
pub fn material_from_json(v: &Value) -> Result<Box<dyn Bispectral>> {
    let obj = v.as_object().ok_or_else(|| Error::data("material must be a JSON object"))?;
    let model = obj.get("model").and_then(Value::as_str).unwrap_or("");
    match model {
        "jung" => {
            const KEYS: [&str; 6] =
                ["model", "emission_peak", "stokes_shift", "concentration", "quantum_yield", "reflectance"];
            if let Some(k) = obj.keys().find(|k| !KEYS.contains(&k.as_str())) {
                return Err(Error::param(k, "(present)", format!("one of the jung fields {}", KEYS.join(", "))));
            }
            let d = JungParams::default();
            let params = JungParams {
                emission_peak: number(v, "emission_peak", d.emission_peak)?,
                stokes_shift: number(v, "stokes_shift", d.stokes_shift)?,
                concentration: number(v, "concentration", d.concentration)?,
                quantum_yield: number(v, "quantum_yield", d.quantum_yield)?,
            };
            let reflectance = match v.get("reflectance") {
                None => Reflectance::Constant(0.5),
                Some(Value::Number(n)) => Reflectance::Constant(n.as_f64().unwrap_or(f64::NAN)),
                Some(r) => {
                    let c = r
                        .get("coefficients")
                        .and_then(Value::as_array)
                        .filter(|a| a.len() == 3)
                        .and_then(|a| a.iter().map(Value::as_f64).collect::<Option<Vec<f64>>>())
                        .ok_or_else(|| {
                            Error::param("reflectance", r, "a number or {\"coefficients\": [c0, c1, c2]}")
                        })?;
                    Reflectance::Sigmoid(SigmoidPolynomial::new([c[0], c[1], c[2]])?)
                }
            };
            Ok(Box::new(JungMaterial::new(reflectance, params)?))
        }
        other => Err(Error::param("model", format!("\"{other}\""), "one of: jung")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_validates() {
        let m = load_material(r#"{"model":"jung","concentration":0,"reflectance":0.25}"#).unwrap();
        assert_eq!(m.elastic_albedo(1.0, 500.0), 0.25);
        let m = load_material(r#"{"model":"jung","reflectance":{"coefficients":[0,0,0]}}"#).unwrap();
        assert_eq!(m.elastic_albedo(1.0, 700.0), 0.5);
        for (bad, needle) in [
            (r#"{"model":"qd"}"#, "model"),
            (r#"{"model":"jung","quantum_yield":2}"#, "quantum_yield"),
            (r#"{"model":"jung","colour":1}"#, "colour"),
            (r#"{"model":"jung","reflectance":{"coefficients":[1,2]}}"#, "reflectance"),
            (r#"{"model":"jung","reflectance":1.5}"#, "reflectance"),
            (r#"{"model":"jung""#, "JSON"),
            ("/no/such/file.json", "I/O"),
            ("/no/such/file.BFC", "/no/such/file.BFC"),
            ("/no/such/fit.gmm.json", "/no/such/fit.gmm.json"),
        ] {
            let e = load_material(bad).err().unwrap().to_string();
            assert!(e.contains(needle), "{bad}: {e}");
        }
    }

    /// The vectorised variants' medium tables (MediumJitTables) against the models: μa,
    /// μf(λo | R) and the excitation sample at the same ξ, evaluated as the shim does.
    #[test]
    fn jit_tables_follow_the_media() {
        use crate::models::jung::DyeMediumParams;
        use crate::models::qd::QdMediumParams;
        let media = [
            MediumModel::Qd(Box::new(QdMedium::new(QdMediumParams::default()).unwrap())),
            MediumModel::Qd(Box::new(
                QdMedium::new(QdMediumParams { radius_nm: 1.5, width_nm: 2.0, ..QdMediumParams::default() }).unwrap(),
            )),
            MediumModel::Qd(Box::new(
                QdMedium::new(QdMediumParams { radius_nm: 3.0, width_nm: 0.05, ..QdMediumParams::default() }).unwrap(),
            )),
            MediumModel::Dye(DyeMedium::new(DyeMediumParams::default()).unwrap()),
            MediumModel::Dye(
                DyeMedium::new(DyeMediumParams {
                    emission_peak_nm: 640.0,
                    stokes_shift_nm: 25.0,
                    ..Default::default()
                })
                .unwrap(),
            ),
        ];
        for m in &media {
            let t = m.jit_tables();
            assert!(t.lambda.windows(2).all(|w| w[0] < w[1]));
            assert_eq!((t.lambda[0], *t.lambda.last().unwrap()), MEDIUM_JIT_DOMAIN_NM);
            let cell = |l: f64| t.lambda.partition_point(|&x| x <= l).clamp(1, t.lambda.len() - 1) - 1;
            let mu_a = |l: f64| {
                let k = cell(l);
                let f = (l - t.lambda[k]) / (t.lambda[k + 1] - t.lambda[k]);
                t.mu_a[k] + f * (t.mu_a[k + 1] - t.mu_a[k])
            };
            let c = |l: f64| {
                let k = cell(l);
                t.cum[k] + 0.5 * (l - t.lambda[k]) * (t.mu_a[k] + mu_a(l))
            };
            let e = |l: f64| {
                let x = &t.emission_lambda;
                if !(l >= x[0] && l <= *x.last().unwrap()) {
                    return 0.0;
                }
                let k = x.partition_point(|&v| v <= l).clamp(1, x.len() - 1) - 1;
                t.emission[k] + (l - x[k]) / (x[k + 1] - x[k]) * (t.emission[k + 1] - t.emission[k])
            };
            let peak = t.mu_a.iter().cloned().fold(0.0, f64::max);
            let (lo, hi) = m.lambda_range();
            let mut worst_a: f64 = 0.0;
            for i in 0..=20000 {
                let l = 200.0 + 1000.0 * i as f64 / 20000.0;
                worst_a = worst_a.max((mu_a(l) - m.absorption_per_m(l)).abs() / peak);
            }
            assert!(worst_a < 2e-4, "{m}: μa off by {worst_a:e} of its peak");
            let (mut worst_f, mut worst_l): (f64, f64) = (0.0, 0.0);
            for r in [(lo, hi), (300.0_f64.max(lo), 380.0_f64.min(hi)), (lo + 0.3 * (hi - lo), hi)] {
                let f_max = (0..=2000)
                    .map(|i| m.shift_coefficient_per_m(360.0 + 470.0 * i as f64 / 2000.0, r))
                    .fold(0.0, f64::max);
                if f_max == 0.0 {
                    continue;
                }
                for i in 0..=2000 {
                    let lo_nm = 360.0 + 470.0 * i as f64 / 2000.0;
                    let top = lo_nm.min(r.1);
                    let mu_f = e(lo_nm) * (c(top) - c(r.0)).max(0.0);
                    let want = m.shift_coefficient_per_m(lo_nm, r);
                    assert!((mu_f - want).abs() <= 2e-4 * f_max, "{m} {r:?} λo {lo_nm}: μf {mu_f} vs {want}");
                    worst_f = worst_f.max((mu_f - want).abs() / f_max);
                    if want > 1e-3 * f_max {
                        for xi in [0.03, 0.5, 0.97] {
                            let (ca, cb) = (c(r.0), c(top));
                            let target = ca + xi * (cb - ca);
                            let k = t.cum.partition_point(|&v| v <= target).clamp(1, t.lambda.len() - 1) - 1;
                            let (f0, f1, h) = (t.mu_a[k], t.mu_a[k + 1], t.lambda[k + 1] - t.lambda[k]);
                            let s = target - t.cum[k];
                            let u = 2.0 * s / (f0 + (f0 * f0 + 2.0 * (f1 - f0) * s / h).max(0.0).sqrt());
                            let li = t.lambda[k] + u;
                            let (want_li, _) = m.sample_excitation(lo_nm, r, xi).unwrap();
                            assert!((li - want_li).abs() < 0.05, "{m} λo {lo_nm} ξ {xi}: λi {li} vs {want_li}");
                            worst_l = worst_l.max((li - want_li).abs());
                        }
                    }
                }
            }
            println!(
                "{m}: {} μa nodes, {} emission nodes; μa within {worst_a:.1e} of its peak, μf within {worst_f:.1e} \
                 of its max, λi within {worst_l:.1e} nm",
                t.lambda.len(),
                t.emission_lambda.len()
            );
        }
    }
}

// ------------------------------------------------------- participating media
// The fluorescent participating media ([`MediumModel`]): a closed set with static
// dispatch, seen by `fluo_volpath` through one bispectral medium contract:
//
// * μa(λ), 1/m: absorption (all of it attenuates);
// * f(λi → λo): re-emitted power per nm of λo per unit power absorbed at λi, isotropic,
//   ∫ f dλo ≤ quantum yield;
// * μf(λo | R) = ∫_R μa(λi) f(λi → λo) dλi, 1/m;
// * excitation sampling with density exactly μa f / μf over R (so a shift weighs μf).
//
// Models: [`QdMedium`] (`fluo_qd_medium`, Benamira & Pattanaik 2023) and [`DyeMedium`]
// (`fluo_dye_medium`, Jung et al.'s dye spectra, in `models/jung.rs`). Adding one: its
// type in its model's module, one arm per method here, its bridge constructor and shim.

/// A fluorescent participating medium.
#[derive(Debug, Clone)]
pub enum MediumModel {
    /// Quantum dots in a host (boxed: its baked tables' header is large).
    Qd(Box<QdMedium>),
    /// A Jung-style dye in solution.
    Dye(DyeMedium),
}

macro_rules! dispatch {
    ($self:ident, $m:ident => $e:expr) => {
        match $self {
            MediumModel::Qd($m) => $e,
            MediumModel::Dye($m) => $e,
        }
    };
}

impl MediumModel {
    /// Whether anything is ever re-emitted.
    pub fn is_fluorescent(&self) -> bool {
        dispatch!(self, m => m.is_fluorescent())
    }

    /// [λmin, λmax], nm: where absorption re-emits and where emission lands.
    pub fn lambda_range(&self) -> (f64, f64) {
        dispatch!(self, m => m.lambda_range())
    }

    /// μa(λ), 1/m.
    pub fn absorption_per_m(&self, lambda_nm: f64) -> f64 {
        dispatch!(self, m => m.absorption_per_m(lambda_nm))
    }

    /// f(λi → λo), per nm of λo per unit absorbed at λi.
    pub fn reradiation_per_nm(&self, lambda_i_nm: f64, lambda_o_nm: f64) -> f64 {
        dispatch!(self, m => m.reradiation_per_nm(lambda_i_nm, lambda_o_nm))
    }

    /// μf(λo | R), 1/m.
    pub fn shift_coefficient_per_m(&self, lambda_o_nm: f64, range: (f64, f64)) -> f64 {
        dispatch!(self, m => m.shift_coefficient_per_m(lambda_o_nm, range))
    }

    /// λi with density μa f / μf over R: (λi, pdf per nm), or None where μf = 0.
    pub fn sample_excitation(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> Option<(f64, f64)> {
        dispatch!(self, m => m.sample_excitation(lambda_o_nm, range, xi))
    }

    /// μf(λo | R) and `sample_excitation(λo, R, xi)` together (what a fluorescent
    /// collision asks of each wavelength; one call sharing the integrals).
    pub fn shift_and_sample(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> (f64, Option<(f64, f64)>) {
        dispatch!(self, m => m.shift_and_sample(lambda_o_nm, range, xi))
    }
}

/// Wavelengths the vectorised variants' medium tables cover, nm (any wavelength a path
/// can carry: excitation from 200 nm, emission up to the models' 1200 nm limit).
pub const MEDIUM_JIT_DOMAIN_NM: (f64, f64) = (200.0, 1200.0);
/// Node spacing of a medium's μa table outside the model's own nodes, nm.
pub const MEDIUM_JIT_OUTER_STEP_NM: f64 = 0.5;
/// Tolerance of a medium's emission table: linear interpolation within this fraction of
/// the emission's peak everywhere (cells are halved until it holds: narrow lines get fine
/// cells where they are, the flat tails coarse ones).
pub const MEDIUM_JIT_EMISSION_TOL: f64 = 1e-5;
/// Largest cell of the emission table, nm.
pub const MEDIUM_JIT_EMISSION_STEP_NM: f64 = 1.0;

/// A fluorescent medium as the vectorised variants evaluate it per lane (both models
/// re-emit f(λi → λo) = e(λo)·`[λi < λo]` for λi in their range, so two tables hold the
/// whole contract):
///
/// ```text
/// μa(λ)        linear between the nodes `lambda` (values `mu_a`, 1/m), exact at the
///              models' own nodes (the QD medium's table is linear between them too)
/// C(λ)         ∫ μa from lambda[0] (`cum` at the nodes, nm/m; exact for the linear μa)
/// e(λo)        linear between the nodes `emission_lambda` over the model's λ range
///              (`emission`, per nm per unit absorbed, yield included; within
///              MEDIUM_JIT_EMISSION_TOL of its peak), 0 outside
/// μf(λo | R)   e(λo)·(C(min(λo, R.hi)) − C(R.lo))⁺, R within the model's range
/// λi | λo      ∝ μa on [R.lo, min(λo, R.hi)] (the inverse of C)
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct MediumJitTables {
    /// μa's nodes, nm, increasing, over [`MEDIUM_JIT_DOMAIN_NM`].
    pub lambda: Vec<f64>,
    /// μa at the nodes, 1/m.
    pub mu_a: Vec<f64>,
    /// Running integral of μa at the nodes, nm/m.
    pub cum: Vec<f64>,
    /// The emission's nodes, nm, increasing, over the model's λ range.
    pub emission_lambda: Vec<f64>,
    /// e(λo) at the nodes, per nm.
    pub emission: Vec<f64>,
}

impl MediumModel {
    /// The tables of [`MediumJitTables`].
    pub fn jit_tables(&self) -> MediumJitTables {
        let own: Vec<f64> = match self {
            MediumModel::Qd(m) => m.absorption_nodes().to_vec(),
            MediumModel::Dye(m) => m.absorption_nodes(),
        };
        let (d0, d1) = MEDIUM_JIT_DOMAIN_NM;
        let (first, last) = (own.first().copied().unwrap_or(d1), own.last().copied().unwrap_or(d0));
        let mut lambda = Vec::with_capacity(own.len() + 2100);
        let mut l = d0;
        while l < first {
            lambda.push(l);
            l += MEDIUM_JIT_OUTER_STEP_NM;
        }
        lambda.extend(own.iter().copied().filter(|&x| x >= d0 && x <= d1));
        let mut l = last + MEDIUM_JIT_OUTER_STEP_NM;
        while l < d1 {
            lambda.push(l);
            l += MEDIUM_JIT_OUTER_STEP_NM;
        }
        if lambda.last().is_none_or(|&x| x < d1) {
            lambda.push(d1);
        }
        lambda.dedup_by(|a, b| *a <= *b);
        let (lo, hi) = self.lambda_range();
        let e = |l: f64| dispatch!(self, m => m.emission_per_nm(l));
        let peak = match self {
            MediumModel::Qd(m) => m.band().emission_peak_nm,
            MediumModel::Dye(m) => m.emission_peak_nm(),
        };
        let mut base: Vec<f64> = (0..=((hi - lo) / MEDIUM_JIT_EMISSION_STEP_NM).ceil() as usize)
            .map(|i| (lo + i as f64 * MEDIUM_JIT_EMISSION_STEP_NM).min(hi))
            .collect();
        if peak > lo && peak < hi {
            base.push(peak);
        }
        base.sort_by(f64::total_cmp);
        base.dedup();
        let tol = MEDIUM_JIT_EMISSION_TOL * base.iter().map(|&l| e(l)).fold(0.0, f64::max);
        let emission_lambda = refine_linear(&e, &base, tol);
        self.jit_tables_on(lambda, emission_lambda)
    }

    /// The tables of [`MediumJitTables`] on given nodes (`lambda` increasing over
    /// [`MEDIUM_JIT_DOMAIN_NM`], `emission_lambda` increasing): a parameter's derivative
    /// tables are differences of tables on one model's nodes.
    pub fn jit_tables_on(&self, lambda: Vec<f64>, emission_lambda: Vec<f64>) -> MediumJitTables {
        let mu_a: Vec<f64> = lambda.iter().map(|&l| self.absorption_per_m(l)).collect();
        let cum = crate::spectrum::running_trapezoid(&lambda, &mu_a);
        let emission = emission_lambda.iter().map(|&l| dispatch!(self, m => m.emission_per_nm(l))).collect();
        MediumJitTables { lambda, mu_a, cum, emission_lambda, emission }
    }
}

/// Nodes between which linear interpolation of `f` stays within `tol` (absolute): each
/// cell of `base` halved while f at its midpoint or quarter points misses the chord by
/// more than `tol` (at most 2^-30 of the cell).
fn refine_linear(f: &dyn Fn(f64) -> f64, base: &[f64], tol: f64) -> Vec<f64> {
    /// The cell [a, b] with f(a), f(b): its nodes after a, into `out`.
    fn split(
        f: &dyn Fn(f64) -> f64,
        (a, fa): (f64, f64),
        (b, fb): (f64, f64),
        tol: f64,
        depth: u32,
        out: &mut Vec<f64>,
    ) {
        let m = 0.5 * (a + b);
        let fm = f(m);
        let (q1, q3) = (f(0.5 * (a + m)), f(0.5 * (m + b)));
        let off = (fm - 0.5 * (fa + fb))
            .abs()
            .max((q1 - 0.75 * fa - 0.25 * fb).abs())
            .max((q3 - 0.25 * fa - 0.75 * fb).abs());
        if depth < 30 && off > tol {
            split(f, (a, fa), (m, fm), tol, depth + 1, out);
            split(f, (m, fm), (b, fb), tol, depth + 1, out);
        } else {
            out.push(b);
        }
    }
    let mut out = vec![base[0]];
    for w in base.windows(2) {
        split(f, (w[0], f(w[0])), (w[1], f(w[1])), tol, 0, &mut out);
    }
    out
}

impl fmt::Display for MediumModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        dispatch!(self, m => m.fmt(f))
    }
}
