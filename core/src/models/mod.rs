//! The fluorescent models, one module each, with their implementations of
//! [`crate::interface::Bispectral`]. A model imports the interface and shared numerics,
//! never `crate::model`, `crate::patch` or `crate::reduce`.
//!
//! Adding a model: its module here, one arm per method in `crate::model`, its section
//! of the bridge (`mitsuba/src/bridge.rs`), its shim (`mitsuba/plugins/fluo_<name>.cpp`)
//! and its test file (`tests/python/test_fluo_<name>.py`).

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
            fn shift_albedo_is_isotropic(&self) -> bool {
                true
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
