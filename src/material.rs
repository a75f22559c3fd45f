//! Material descriptions for the command line (`fluo patch --material M`).
//!
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
//! (`*.bfc`, `*.csv`, `*.exr`: the tabulated model of `fluo_matrix`, [`crate::matrix`])
//! or a Gaussian-mixture fit (`*.gmm.json`: `fluo_gmm`, [`crate::gmm`]).

use serde_json::Value;

use crate::bispectral::PatchMaterial;
use crate::jung::{JungMaterial, JungParams, Reflectance};
use crate::reduce::Reradiating;
use crate::sigmoid::SigmoidPolynomial;
use crate::{Error, Result};

/// What the command line needs of a material: patch colorimetry and the reradiation
/// operator (for reductions).
pub trait Material: PatchMaterial + Reradiating {}
impl<T: PatchMaterial + Reradiating> Material for T {}

/// Read a material argument: inline JSON (starting with `{`) or a path to a JSON file.
pub fn load_material(arg: &str) -> Result<Box<dyn Material>> {
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
fn load_measured(arg: &str) -> Option<Result<Box<dyn Material>>> {
    let lower = arg.trim().to_ascii_lowercase();
    if lower.ends_with(".gmm.json") {
        return Some(crate::gmm::GmmModel::from_file(arg.trim()).map(|m| Box::new(m) as Box<dyn Material>));
    }
    if [".bfc", ".csv", ".exr"].iter().any(|e| lower.ends_with(e)) {
        return Some(crate::matrix::MatrixModel::from_file(arg.trim()).map(|m| Box::new(m) as Box<dyn Material>));
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
pub fn material_from_json(v: &Value) -> Result<Box<dyn Material>> {
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
        assert_eq!(m.elastic_albedo(500.0), 0.25);
        let m = load_material(r#"{"model":"jung","reflectance":{"coefficients":[0,0,0]}}"#).unwrap();
        assert_eq!(m.elastic_albedo(700.0), 0.5);
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
