//! The C++ bridge: the one `#[cxx::bridge]` module, and the only code that sees cxx.
//!
//! Direction: C++ (the Mitsuba plugin shims in `plugins/`) calls Rust; Rust never
//! calls C++. Models cross as opaque `Box`es. Construction returns `Result`, which cxx
//! turns into a C++ exception carrying the Rust message; the shims rethrow it through
//! Mitsuba's `Throw`. No panic may cross: constructors run under `catch_unwind`, and
//! hot-path functions are written without panicking operations (iterators, no indexing).
//! Spectra cross as slices of `f32` wavelengths (nm) and values, one entry per hero
//! wavelength.

use std::panic::{catch_unwind, AssertUnwindSafe};

use crate::jung::{JungFluorescence, JungParams, Reflectance};
use crate::mitsuba::{spectrum_to_srgb, CIE_MAX_NM, CIE_MIN_NM};
use crate::sigmoid::SigmoidPolynomial;

#[cxx::bridge(namespace = "fluo")]
mod bridge {
    /// `fluo_jung` parameters as parsed from Mitsuba `Properties` by the shim.
    struct JungConfig {
        emission_peak: f64,
        stokes_shift: f64,
        concentration: f64,
        quantum_yield: f64,
        /// True when the reflectance is given as sigmoid `coefficients`
        /// (otherwise the shim evaluates a Mitsuba texture itself).
        has_coefficients: bool,
        c0: f64,
        c1: f64,
        c2: f64,
    }

    /// A linear sRGB triple (Mitsuba's RGB variants' working space).
    struct Rgb {
        r: f64,
        g: f64,
        b: f64,
    }

    extern "Rust" {
        /// A validated, baked `fluo_jung` material.
        type JungModel;

        fn jung_new(config: &JungConfig) -> Result<Box<JungModel>>;
        fn jung_is_fluorescent(model: &JungModel) -> bool;
        /// out[j] = 1 − c·a(λ_j).
        fn jung_elastic_factor(model: &JungModel, lambdas: &[f32], out: &mut [f32]);
        /// out[j] = r(λ_j)·(1 − c·a(λ_j)) for sigmoid reflectance (0 without coefficients).
        fn jung_elastic_albedo(model: &JungModel, lambdas: &[f32], out: &mut [f32]);
        /// RGB variant, sigmoid reflectance: sRGB of the spectrum reflected under E.
        fn jung_rgb_albedo(model: &JungModel) -> Rgb;
        /// RGB variant, texture reflectance: per-channel elastic scale sRGB(1 − c a)/sRGB(1).
        fn jung_rgb_elastic_scale(model: &JungModel) -> Rgb;
        /// RGB variant: sRGB of the reradiated spectrum under E, c Q e(λ) ∫ a.
        fn jung_rgb_fluorescence(model: &JungModel) -> Rgb;
        fn jung_to_string(model: &JungModel) -> String;
    }
}

pub use bridge::{JungConfig, Rgb};

/// Opaque `fluo_jung` model handed to C++.
pub struct JungModel {
    fluorescence: JungFluorescence,
    reflectance: Option<Reflectance>,
}

fn guarded<T>(f: impl FnOnce() -> crate::Result<T>) -> Result<T, String> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(e.to_string()),
        Err(_) => Err("internal error (a panic was caught at the FFI boundary)".to_string()),
    }
}

fn jung_new(config: &JungConfig) -> Result<Box<JungModel>, String> {
    guarded(|| {
        let params = JungParams {
            emission_peak: config.emission_peak,
            stokes_shift: config.stokes_shift,
            concentration: config.concentration,
            quantum_yield: config.quantum_yield,
        };
        let fluorescence = JungFluorescence::new(params)?;
        let reflectance = if config.has_coefficients {
            Some(Reflectance::Sigmoid(SigmoidPolynomial::new([config.c0, config.c1, config.c2])?))
        } else {
            None
        };
        Ok(Box::new(JungModel { fluorescence, reflectance }))
    })
}

fn jung_is_fluorescent(model: &JungModel) -> bool {
    model.fluorescence.is_fluorescent()
}

fn jung_elastic_factor(model: &JungModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.fluorescence.elastic_factor(f64::from(l)) as f32;
    }
}

fn jung_elastic_albedo(model: &JungModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        let l = f64::from(l);
        let r = model.reflectance.as_ref().map_or(0.0, |r| r.eval(l));
        *o = (r * model.fluorescence.elastic_factor(l)) as f32;
    }
}

fn rgb(v: [f64; 3]) -> Rgb {
    Rgb { r: v[0], g: v[1], b: v[2] }
}

/// c·Q·∫_{360}^{830} a(λ) dλ: reradiated energy per unit equal-energy irradiance.
fn fluorescent_weight(model: &JungModel) -> f64 {
    let p = model.fluorescence.params();
    p.concentration * p.quantum_yield * model.fluorescence.absorption_integral_range(CIE_MIN_NM, CIE_MAX_NM)
}

fn jung_rgb_fluorescence(model: &JungModel) -> Rgb {
    let w = fluorescent_weight(model);
    if w <= 0.0 {
        return rgb([0.0; 3]);
    }
    rgb(spectrum_to_srgb(|l| w * model.fluorescence.emission(l)))
}

fn jung_rgb_albedo(model: &JungModel) -> Rgb {
    let elastic = spectrum_to_srgb(|l| {
        model.reflectance.as_ref().map_or(0.0, |r| r.eval(l)) * model.fluorescence.elastic_factor(l)
    });
    let f = jung_rgb_fluorescence(model);
    rgb([elastic[0] + f.r, elastic[1] + f.g, elastic[2] + f.b])
}

fn jung_rgb_elastic_scale(model: &JungModel) -> Rgb {
    let num = spectrum_to_srgb(|l| model.fluorescence.elastic_factor(l));
    let den = spectrum_to_srgb(|_| 1.0);
    let ratio = |k: usize| if den[k].abs() > 0.0 { (num[k] / den[k]).clamp(0.0, 1.0) } else { 1.0 };
    rgb([ratio(0), ratio(1), ratio(2)])
}

fn jung_to_string(model: &JungModel) -> String {
    match &model.reflectance {
        Some(Reflectance::Sigmoid(s)) => format!("{} with sigmoid reflectance {:?}", model.fluorescence, s.coefficients),
        _ => model.fluorescence.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> JungConfig {
        JungConfig {
            emission_peak: 520.0,
            stokes_shift: 60.0,
            concentration: 0.0,
            quantum_yield: 0.96,
            has_coefficients: true,
            c0: 0.0,
            c1: 0.0,
            c2: 0.0,
        }
    }

    #[test]
    fn errors_cross_as_messages() {
        let e = jung_new(&JungConfig { quantum_yield: 1.5, ..config() }).err().unwrap();
        assert!(e.contains("quantum_yield") && e.contains("1.5") && e.contains("[0, 1]"), "{e}");
        let e = jung_new(&JungConfig { c1: f64::NAN, ..config() }).err().unwrap();
        assert!(e.contains("coefficients[1]"), "{e}");
    }

    #[test]
    fn zero_concentration_is_plain_reflectance() {
        // coefficients (0,0,0) -> r = S(0) = 0.5 everywhere
        let m = jung_new(&config()).unwrap();
        let l = [300.0f32, 400.0, 555.0, 830.0];
        let mut out = [0.0f32; 4];
        jung_elastic_albedo(&m, &l, &mut out);
        assert_eq!(out, [0.5; 4]);
        let a = jung_rgb_albedo(&m);
        let white = spectrum_to_srgb(|_| 1.0);
        assert!((a.r - 0.5 * white[0]).abs() < 1e-12 && (a.b - 0.5 * white[2]).abs() < 1e-12);
        let f = jung_rgb_fluorescence(&m);
        assert_eq!((f.r, f.g, f.b), (0.0, 0.0, 0.0));
    }

    #[test]
    fn slices_of_different_length_do_not_panic() {
        let m = jung_new(&config()).unwrap();
        let mut out = [0.0f32; 2];
        jung_elastic_factor(&m, &[500.0, 510.0, 520.0], &mut out);
        jung_elastic_factor(&m, &[], &mut out);
    }
}
