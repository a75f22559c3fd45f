//! The closed set of fluorescent models ([`Model`], dispatched statically with `match`)
//! and material descriptions for the command line: the only file that names every
//! model.
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
use std::sync::Arc;

use serde_json::Value;

use crate::interface::Bispectral;
use crate::models::gmm::GmmModel;
use crate::models::jung::{DyeMedium, JungFluorescence, JungMaterial, JungParams, Reflectance};
use crate::models::matrix::MatrixModel;
use crate::models::qd::{QdMedium, QdModel};
use crate::sigmoid::SigmoidPolynomial;
use crate::{Error, Result};

/// The closed set of fluorescent models.
///
/// Each variant holds its model behind an [`Arc`], so that a handle that needs the
/// concrete model (a plugin's) and this generic one share a single copy; cloning a
/// `Model` is cheap.
#[derive(Debug, Clone)]
pub enum Model {
    /// Jung et al.'s diffuse parametric model (the dye; the base reflectance is the
    /// plugin's texture).
    Jung(Arc<JungFluorescence>),
    /// Benamira & Pattanaik's quantum-dot coated microfacet model.
    Qd(Arc<QdModel>),
    /// A measured reradiation matrix, tabulated (`fluo_matrix`).
    Matrix(Arc<MatrixModel>),
    /// A Gaussian-mixture fit of a measured matrix (`fluo_gmm`).
    Gmm(Arc<GmmModel>),
}

impl Model {
    /// The model's display name.
    pub fn name(&self) -> &'static str {
        match self {
            Model::Jung(_) => "jung",
            Model::Qd(_) => "qd",
            Model::Matrix(_) => "matrix",
            Model::Gmm(_) => "gmm",
        }
    }
}

impl fmt::Display for Model {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Model::Jung(m) => fmt::Display::fmt(&**m, f),
            Model::Qd(m) => fmt::Display::fmt(&**m, f),
            Model::Matrix(m) => fmt::Display::fmt(&**m, f),
            Model::Gmm(m) => fmt::Display::fmt(&**m, f),
        }
    }
}

impl Bispectral for Model {
    fn excitation_range(&self) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => m.excitation_range(),
            Model::Qd(m) => m.excitation_range(),
            Model::Matrix(m) => Bispectral::excitation_range(&**m),
            Model::Gmm(m) => Bispectral::excitation_range(&**m),
        }
    }
    fn emission_range(&self) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => m.emission_range(),
            Model::Qd(m) => m.emission_range(),
            Model::Matrix(m) => Bispectral::emission_range(&**m),
            Model::Gmm(m) => Bispectral::emission_range(&**m),
        }
    }
    fn elastic_albedo(&self, cos_i: f64, lambda: f64) -> f64 {
        match self {
            Model::Jung(m) => m.elastic_albedo(cos_i, lambda),
            Model::Qd(m) => m.elastic_albedo(cos_i, lambda),
            Model::Matrix(m) => Bispectral::elastic_albedo(&**m, cos_i, lambda),
            Model::Gmm(m) => Bispectral::elastic_albedo(&**m, cos_i, lambda),
        }
    }
    fn density(&self, cos_i: f64, lambda_i: f64, lambda_o: f64) -> f64 {
        match self {
            Model::Jung(m) => m.density(cos_i, lambda_i, lambda_o),
            Model::Qd(m) => m.density(cos_i, lambda_i, lambda_o),
            Model::Matrix(m) => Bispectral::density(&**m, cos_i, lambda_i, lambda_o),
            Model::Gmm(m) => Bispectral::density(&**m, cos_i, lambda_i, lambda_o),
        }
    }
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
        match self {
            Model::Jung(m) => m.reradiated(illum, domain, lambda_o),
            Model::Qd(m) => m.reradiated(illum, domain, lambda_o),
            Model::Matrix(m) => m.reradiated(illum, domain, lambda_o),
            Model::Gmm(m) => m.reradiated(illum, domain, lambda_o),
        }
    }
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        match self {
            Model::Jung(m) => Bispectral::reradiation(&**m, wi, wo, lambda_i, lambda_o),
            Model::Qd(m) => m.reradiation(wi, wo, lambda_i, lambda_o),
            Model::Matrix(m) => Bispectral::reradiation(&**m, wi, wo, lambda_i, lambda_o),
            Model::Gmm(m) => Bispectral::reradiation(&**m, wi, wo, lambda_i, lambda_o),
        }
    }
    fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64 {
        match self {
            Model::Jung(m) => m.shift_albedo(wi, lambda_o, range),
            Model::Qd(m) => m.shift_albedo(wi, lambda_o, range),
            Model::Matrix(m) => Bispectral::shift_albedo(&**m, wi, lambda_o, range),
            Model::Gmm(m) => Bispectral::shift_albedo(&**m, wi, lambda_o, range),
        }
    }
    fn shift_albedo_is_isotropic(&self) -> bool {
        match self {
            Model::Jung(m) => m.shift_albedo_is_isotropic(),
            Model::Qd(m) => m.shift_albedo_is_isotropic(),
            Model::Matrix(m) => m.shift_albedo_is_isotropic(),
            Model::Gmm(m) => m.shift_albedo_is_isotropic(),
        }
    }
    fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => m.sample_excitation(wi, lambda_o, xi, range),
            Model::Qd(m) => m.sample_excitation(wi, lambda_o, xi, range),
            Model::Matrix(m) => Bispectral::sample_excitation(&**m, wi, lambda_o, xi, range),
            Model::Gmm(m) => Bispectral::sample_excitation(&**m, wi, lambda_o, xi, range),
        }
    }
    fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64 {
        match self {
            Model::Jung(m) => m.excitation_pdf(wi, lambda_o, lambda_i, range),
            Model::Qd(m) => m.excitation_pdf(wi, lambda_o, lambda_i, range),
            Model::Matrix(m) => Bispectral::excitation_pdf(&**m, wi, lambda_o, lambda_i, range),
            Model::Gmm(m) => Bispectral::excitation_pdf(&**m, wi, lambda_o, lambda_i, range),
        }
    }
    fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => Bispectral::sample_emission(&**m, wi, lambda_i, xi),
            Model::Qd(m) => m.sample_emission(wi, lambda_i, xi),
            Model::Matrix(m) => Bispectral::sample_emission(&**m, wi, lambda_i, xi),
            Model::Gmm(m) => Bispectral::sample_emission(&**m, wi, lambda_i, xi),
        }
    }
    fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        match self {
            Model::Jung(m) => Bispectral::emission_pdf(&**m, wi, lambda_i, lambda_o),
            Model::Qd(m) => m.emission_pdf(wi, lambda_i, lambda_o),
            Model::Matrix(m) => Bispectral::emission_pdf(&**m, wi, lambda_i, lambda_o),
            Model::Gmm(m) => Bispectral::emission_pdf(&**m, wi, lambda_i, lambda_o),
        }
    }
}

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

impl fmt::Display for MediumModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        dispatch!(self, m => m.fmt(f))
    }
}
