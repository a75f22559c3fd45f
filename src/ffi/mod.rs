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

use crate::bispectral::{Bispectral, Model, PatchMaterial};
use crate::jung::{JungFluorescence, JungParams, Reflectance};
use crate::mitsuba::{spectrum_to_srgb, CIE_MAX_NM, CIE_MIN_NM};
use crate::sigmoid::SigmoidPolynomial;
use crate::spectrum::{cmf, illuminant, IrregularSpectrum, Observer, Spectral};

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

    /// A closed wavelength interval, nm; empty when `lo >= hi`.
    struct Range {
        lo: f64,
        hi: f64,
    }

    /// A sampled wavelength with its pdf (per nm); `pdf == 0` means no sample.
    struct Sample {
        value: f64,
        pdf: f64,
    }

    /// A unit direction in the local shading frame (z = normal).
    struct Vec3 {
        x: f64,
        y: f64,
        z: f64,
    }

    extern "Rust" {
        /// Any fluorescent model, seen through the bispectral interface
        /// (`src/bispectral.rs`) that the `fluo_path` integrator uses.
        type Fluorescence;

        fn fluo_name(f: &Fluorescence) -> &'static str;
        /// Excitation wavelengths at which the model re-emits (empty if never).
        fn fluo_excitation_range(f: &Fluorescence) -> Range;
        /// Wavelengths at which it re-emits (empty if never).
        fn fluo_emission_range(f: &Fluorescence) -> Range;
        /// f_fl(λi, ωi, ωo, λo)·cos θo, sr⁻¹ nm⁻¹.
        fn fluo_reradiation(f: &Fluorescence, wi: &Vec3, wo: &Vec3, lambda_i: f64, lambda_o: f64) -> f64;
        /// ∫_range ∫ f_fl cos θo dωo dλi (chooses elastic vs shifted events).
        fn fluo_shift_albedo(f: &Fluorescence, wi: &Vec3, lambda_o: f64, range: &Range) -> f64;
        /// λi given λo within `range` (camera paths).
        fn fluo_sample_excitation(f: &Fluorescence, wi: &Vec3, lambda_o: f64, xi: f64, range: &Range) -> Sample;
        fn fluo_excitation_pdf(f: &Fluorescence, wi: &Vec3, lambda_o: f64, lambda_i: f64, range: &Range) -> f64;
        /// λo given λi (light paths).
        fn fluo_sample_emission(f: &Fluorescence, wi: &Vec3, lambda_i: f64, xi: f64) -> Sample;
        fn fluo_emission_pdf(f: &Fluorescence, wi: &Vec3, lambda_i: f64, lambda_o: f64) -> f64;

        /// An emission spectrum for `fluo_illuminant`: a CIE illuminant or a CSV file.
        type Illuminant;

        /// `name` (a CIE illuminant) or `filename` (a `nm,value` CSV), exactly one
        /// non-empty; scaled so that its luminance ∫ I ȳ / ∫ ȳ (CIE 1931) is `scale`.
        fn illuminant_new(name: &str, filename: &str, scale: f64) -> Result<Box<Illuminant>>;
        fn illuminant_eval(s: &Illuminant, lambdas: &[f32], out: &mut [f32]);
        /// The wavelengths where it is defined, nm.
        fn illuminant_range(s: &Illuminant) -> Range;
        /// Mean value over Mitsuba's 360–830 nm.
        fn illuminant_mean(s: &Illuminant) -> f64;
        /// Linear sRGB (Mitsuba's convention) for the RGB variant.
        fn illuminant_srgb(s: &Illuminant) -> Rgb;
        fn illuminant_to_string(s: &Illuminant) -> String;

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
        /// The model's fluorescent part, for the integrator.
        fn jung_fluorescence(model: &JungModel) -> &Fluorescence;

        /// A measured material (`fluo_matrix`, `fluo_gmm`): the diagonal (reflectance)
        /// plus reradiation, diffuse in direction.
        type MeasuredModel;

        /// `fluo_matrix`: a reradiation matrix file (.bfc, .csv, .exr), tabulated.
        fn matrix_new(filename: &str) -> Result<Box<MeasuredModel>>;
        /// `fluo_gmm`: a Gaussian-mixture fit file (.gmm.json, written by `fluo fit-gmm`).
        fn gmm_new(filename: &str) -> Result<Box<MeasuredModel>>;
        fn measured_is_fluorescent(model: &MeasuredModel) -> bool;
        /// out[j] = ρ(λ_j), the diagonal (elastic albedo).
        fn measured_elastic_albedo(model: &MeasuredModel, lambdas: &[f32], out: &mut [f32]);
        /// RGB variant: sRGB of ρ(λ) + ∫ P(λi, λ) dλi under equal-energy light (360–830 nm).
        fn measured_rgb_albedo(model: &MeasuredModel) -> Rgb;
        fn measured_to_string(model: &MeasuredModel) -> String;
        /// The model's fluorescent part, for the integrator.
        fn measured_fluorescence(model: &MeasuredModel) -> &Fluorescence;
    }
}

pub use bridge::{JungConfig, Range, Rgb, Sample, Vec3};

/// Opaque fluorescent model handed to C++ (see [`crate::bispectral`]).
pub struct Fluorescence(Model);

/// Opaque `fluo_jung` model handed to C++.
pub struct JungModel {
    fluorescence: JungFluorescence,
    reflectance: Option<Reflectance>,
    generic: Fluorescence,
}

fn range_of(r: Option<(f64, f64)>) -> Range {
    r.map_or(Range { lo: 0.0, hi: 0.0 }, |(lo, hi)| Range { lo, hi })
}

fn dir(v: &Vec3) -> [f64; 3] {
    [v.x, v.y, v.z]
}

fn sample_of(s: Option<(f64, f64)>) -> Sample {
    match s {
        Some((value, pdf)) if pdf > 0.0 && pdf.is_finite() && value.is_finite() => Sample { value, pdf },
        _ => Sample { value: 0.0, pdf: 0.0 },
    }
}

fn fluo_name(f: &Fluorescence) -> &'static str {
    f.0.name()
}
fn fluo_excitation_range(f: &Fluorescence) -> Range {
    range_of(f.0.excitation_range())
}
fn fluo_emission_range(f: &Fluorescence) -> Range {
    range_of(f.0.emission_range())
}
fn fluo_reradiation(f: &Fluorescence, wi: &Vec3, wo: &Vec3, lambda_i: f64, lambda_o: f64) -> f64 {
    f.0.reradiation(dir(wi), dir(wo), lambda_i, lambda_o)
}
fn fluo_shift_albedo(f: &Fluorescence, wi: &Vec3, lambda_o: f64, range: &Range) -> f64 {
    f.0.shift_albedo(dir(wi), lambda_o, (range.lo, range.hi))
}
fn fluo_sample_excitation(f: &Fluorescence, wi: &Vec3, lambda_o: f64, xi: f64, range: &Range) -> Sample {
    sample_of(f.0.sample_excitation(dir(wi), lambda_o, xi, (range.lo, range.hi)))
}
fn fluo_excitation_pdf(f: &Fluorescence, wi: &Vec3, lambda_o: f64, lambda_i: f64, range: &Range) -> f64 {
    f.0.excitation_pdf(dir(wi), lambda_o, lambda_i, (range.lo, range.hi))
}
fn fluo_sample_emission(f: &Fluorescence, wi: &Vec3, lambda_i: f64, xi: f64) -> Sample {
    sample_of(f.0.sample_emission(dir(wi), lambda_i, xi))
}
fn fluo_emission_pdf(f: &Fluorescence, wi: &Vec3, lambda_i: f64, lambda_o: f64) -> f64 {
    f.0.emission_pdf(dir(wi), lambda_i, lambda_o)
}

/// Opaque emission spectrum for `fluo_illuminant`.
pub struct Illuminant {
    label: String,
    spectrum: IrregularSpectrum,
}

fn illuminant_new(name: &str, filename: &str, scale: f64) -> Result<Box<Illuminant>, String> {
    guarded(|| {
        let (label, spectrum) = match (name.is_empty(), filename.is_empty()) {
            (false, true) => (name.to_string(), IrregularSpectrum::from(illuminant(name)?)),
            (true, false) => (filename.to_string(), IrregularSpectrum::from_csv_file(filename)?),
            _ => {
                return Err(crate::Error::param(
                    "illuminant",
                    format!("name \"{name}\", filename \"{filename}\""),
                    "exactly one of \"illuminant\" (a CIE name) and \"filename\" (a CSV spectrum)",
                ))
            }
        };
        if !(scale.is_finite() && scale >= 0.0) {
            return Err(crate::Error::param("scale", scale, "[0, ∞)"));
        }
        if spectrum.values().iter().any(|v| *v < 0.0) {
            return Err(crate::Error::data(format!("{label}: negative spectral values")));
        }
        let c = cmf(Observer::Cie1931);
        let y = c.y();
        let lum = spectrum.integrate_product(y, CIE_MIN_NM, CIE_MAX_NM, 1.0)?
            / y.integrate_product(&|_: f64| 1.0, CIE_MIN_NM, CIE_MAX_NM, 1.0)?;
        if !(lum > 0.0) {
            return Err(crate::Error::data(format!("{label}: no visible energy (zero luminance), cannot normalise")));
        }
        let k = scale / lum;
        let scaled = IrregularSpectrum::new(
            spectrum.wavelengths_nm().to_vec(),
            spectrum.values().iter().map(|v| v * k).collect(),
        )?;
        Ok(Box::new(Illuminant { label, spectrum: scaled }))
    })
}

fn illuminant_eval(s: &Illuminant, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = s.spectrum.eval(f64::from(l)) as f32;
    }
}

fn illuminant_range(s: &Illuminant) -> Range {
    let w = s.spectrum.wavelengths_nm();
    Range { lo: w.first().copied().unwrap_or(0.0), hi: w.last().copied().unwrap_or(0.0) }
}

fn illuminant_mean(s: &Illuminant) -> f64 {
    s.spectrum.integrate_product(&|_: f64| 1.0, CIE_MIN_NM, CIE_MAX_NM, 1.0).unwrap_or(0.0) / (CIE_MAX_NM - CIE_MIN_NM)
}

fn illuminant_srgb(s: &Illuminant) -> Rgb {
    rgb(spectrum_to_srgb(|l| s.spectrum.eval(l)))
}

fn illuminant_to_string(s: &Illuminant) -> String {
    let r = illuminant_range(s);
    format!("{} ({}-{} nm, luminance-normalised)", s.label, r.lo, r.hi)
}

fn jung_fluorescence(model: &JungModel) -> &Fluorescence {
    &model.generic
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
        let generic = Fluorescence(Model::Jung(fluorescence.clone()));
        Ok(Box::new(JungModel { fluorescence, reflectance, generic }))
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

// ---------------------------------------------------------------- fluo_matrix, fluo_gmm

/// Opaque measured material (`fluo_matrix`, `fluo_gmm`) handed to C++.
pub struct MeasuredModel {
    generic: Fluorescence,
}

impl MeasuredModel {
    /// The colorimetric view of the model (always present: only `matrix_new` and
    /// `gmm_new` build a `MeasuredModel`).
    fn patch(&self) -> Option<&dyn PatchMaterial> {
        match &self.generic.0 {
            Model::Matrix(m) => Some(m),
            Model::Gmm(m) => Some(m),
            Model::Jung(_) => None,
        }
    }

    fn elastic_albedo(&self, lambda: f64) -> f64 {
        self.patch().map_or(0.0, |p| p.elastic_albedo(lambda))
    }
}

fn matrix_new(filename: &str) -> Result<Box<MeasuredModel>, String> {
    guarded(|| {
        let m = crate::matrix::MatrixModel::from_file(filename)?;
        Ok(Box::new(MeasuredModel { generic: Fluorescence(Model::Matrix(m)) }))
    })
}

fn gmm_new(filename: &str) -> Result<Box<MeasuredModel>, String> {
    guarded(|| {
        let m = crate::gmm::GmmModel::from_file(filename)?;
        Ok(Box::new(MeasuredModel { generic: Fluorescence(Model::Gmm(m)) }))
    })
}

fn measured_is_fluorescent(model: &MeasuredModel) -> bool {
    model.generic.0.excitation_range().is_some()
}

fn measured_elastic_albedo(model: &MeasuredModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.elastic_albedo(f64::from(l)) as f32;
    }
}

fn measured_rgb_albedo(model: &MeasuredModel) -> Rgb {
    const UP: [f64; 3] = [0.0, 0.0, 1.0];
    let shifted = |l: f64| model.generic.0.shift_albedo(UP, l, (CIE_MIN_NM, CIE_MAX_NM));
    rgb(spectrum_to_srgb(|l| model.elastic_albedo(l) + shifted(l)))
}

fn measured_to_string(model: &MeasuredModel) -> String {
    match &model.generic.0 {
        Model::Matrix(m) => m.to_string(),
        Model::Gmm(m) => m.to_string(),
        Model::Jung(m) => m.to_string(),
    }
}

fn measured_fluorescence(model: &MeasuredModel) -> &Fluorescence {
    &model.generic
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
