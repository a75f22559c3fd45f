//! The fluorescent models, one module each, with their implementations of
//! [`crate::interface::Bispectral`]. A model imports the interface and shared numerics,
//! never `crate::model`, `crate::patch` or `crate::reduce`.
//!
//! [`Model`], the closed set of them, sits beside their module list, so that adding a model
//! touches this file once (its `pub mod` line and its arm in `Model`'s three matches) besides
//! its own module, its plugin's bridge section and module (`mitsuba/src/bridge.rs`,
//! `mitsuba/src/<name>.rs`), its shim (`mitsuba/plugins/fluo_<name>.cpp`) and its test file
//! (`tests/python/test_fluo_<name>.py`): six files.

use std::fmt;
use std::sync::Arc;

use crate::interface::Bispectral;

/// The interface of a measured model (`fluo_matrix`, `fluo_gmm`): diffuse in direction,
/// f_fl = P(λi, λo)/π, elastic albedo the matrix diagonal, on the wavelength methods
/// both models share (`reflectance`, `reradiation`, `absorbed_into`, the supports and
/// the samplers).
macro_rules! lambertian_measured {
    ($ty:ty) => {
        impl $crate::interface::Bispectral for $ty {
            fn excitation_range(&self) -> Option<(f64, f64)> {
                self.excitation_support()
            }
            fn emission_range(&self) -> Option<(f64, f64)> {
                self.emission_support()
            }
            fn elastic_albedo(&self, _cos_i: f64, lambda: f64) -> f64 {
                self.reflectance(lambda)
            }
            fn density(&self, _cos_i: f64, lambda_i: f64, lambda_o: f64) -> f64 {
                <$ty>::reradiation(self, lambda_i, lambda_o)
            }
            fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
                if !(wi[2] > 0.0 && wo[2] > 0.0) {
                    return 0.0;
                }
                <$ty>::reradiation(self, lambda_i, lambda_o) * std::f64::consts::FRAC_1_PI * wo[2]
            }
            fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64 {
                if !(wi[2] > 0.0) {
                    return 0.0;
                }
                self.absorbed_into(lambda_o, range.0, range.1) // Lambertian: ∫ cos/π dω = 1
            }
            fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)> {
                if !(wi[2] > 0.0) {
                    return None;
                }
                <$ty>::sample_excitation(self, lambda_o, xi, range.0, range.1)
            }
            fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64 {
                if !(wi[2] > 0.0) {
                    return 0.0;
                }
                <$ty>::excitation_pdf(self, lambda_o, lambda_i, range.0, range.1)
            }
            fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
                if !(wi[2] > 0.0) {
                    return None;
                }
                <$ty>::sample_emission(self, lambda_i, xi)
            }
            fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
                if !(wi[2] > 0.0) {
                    return 0.0;
                }
                <$ty>::emission_pdf(self, lambda_i, lambda_o)
            }
        }
    };
}

pub mod gmm;
pub mod jung;
pub mod matrix;
pub mod qd;

use gmm::GmmModel;
use jung::JungFluorescence;
use matrix::MatrixModel;
use qd::QdModel;

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

impl Model {
    /// The model behind the handle, as the interface every model implements.
    pub fn as_dyn(&self) -> &dyn Bispectral {
        match self {
            Model::Jung(m) => &**m,
            Model::Qd(m) => &**m,
            Model::Matrix(m) => &**m,
            Model::Gmm(m) => &**m,
        }
    }
}

/// Every method forwards to the model behind the handle ([`Model::as_dyn`]).
impl Bispectral for Model {
    fn excitation_range(&self) -> Option<(f64, f64)> {
        self.as_dyn().excitation_range()
    }
    fn emission_range(&self) -> Option<(f64, f64)> {
        self.as_dyn().emission_range()
    }
    fn elastic_albedo(&self, cos_i: f64, lambda: f64) -> f64 {
        self.as_dyn().elastic_albedo(cos_i, lambda)
    }
    fn density(&self, cos_i: f64, lambda_i: f64, lambda_o: f64) -> f64 {
        self.as_dyn().density(cos_i, lambda_i, lambda_o)
    }
    fn density_factors(&self, cos_i: f64, lambdas: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
        self.as_dyn().density_factors(cos_i, lambdas)
    }
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
        self.as_dyn().reradiated(illum, domain, lambda_o)
    }
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        self.as_dyn().reradiation(wi, wo, lambda_i, lambda_o)
    }
    fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64 {
        self.as_dyn().shift_albedo(wi, lambda_o, range)
    }
    fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        self.as_dyn().sample_excitation(wi, lambda_o, xi, range)
    }
    fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64 {
        self.as_dyn().excitation_pdf(wi, lambda_o, lambda_i, range)
    }
    fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        self.as_dyn().sample_emission(wi, lambda_i, xi)
    }
    fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        self.as_dyn().emission_pdf(wi, lambda_i, lambda_o)
    }
}

/// Largest distance of a material-index texel from an integer (an index map's value
/// stored as a float; an 8-bit image's raw values are exact).
pub const MATERIAL_INDEX_TOLERANCE: f64 = 1e-3;

/// Check one value of a material-index texture (`fluo_matrix`/`fluo_gmm` `index`): a
/// whole number (within [`MATERIAL_INDEX_TOLERANCE`]) in [0, `count` − 1].
pub fn check_material_index(value: f64, count: usize) -> crate::Result<()> {
    let hi = count.saturating_sub(1) as f64;
    if value.is_finite()
        && value >= -MATERIAL_INDEX_TOLERANCE
        && value <= hi + MATERIAL_INDEX_TOLERANCE
        && (value - value.round()).abs() <= MATERIAL_INDEX_TOLERANCE
    {
        Ok(())
    } else {
        Err(crate::Error::param(
            "index",
            value,
            format!("whole numbers 0 to {} (one per filename0..filename{})", crate::num(hi), crate::num(hi)),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn material_indices_are_whole_and_in_range() {
        assert!(check_material_index(0.0, 3).is_ok() && check_material_index(2.0, 3).is_ok());
        assert!(check_material_index(1.0004, 3).is_ok());
        for bad in [-1.0, 3.0, 0.5, f64::NAN] {
            assert!(check_material_index(bad, 3).unwrap_err().to_string().contains("\"index\""));
        }
    }
}
