//! The bispectral interface every fluorescent model implements, and the
//! single-bounce "patch" colorimetry used to check renders.
//!
//! # Interface
//! A bispectral BBRRDF splits into an elastic part (wavelength-preserving, served by
//! the model's ordinary BSDF) and reradiation f_fl(λi, ωi, ωo, λo) (sr⁻¹ nm⁻¹):
//! light absorbed at λi and re-emitted at λo > λi. [`Bispectral`] exposes what a
//! wavelength-shifting path tracer needs of the second part:
//!
//! * `reradiation`: f_fl · cos θo (Mitsuba's convention: BSDF values include the
//!   outgoing cosine), local frame, unit directions, ωi given;
//! * `sample_excitation` / `excitation_pdf`: λi given λo (camera paths), restricted
//!   to a range where light exists;
//! * `sample_emission` / `emission_pdf`: λo given λi (light paths);
//! * `shift_albedo`: ∫_R ∫_Ω f_fl cos θo dωo dλi, the reradiated albedo reaching
//!   λo from unit excitation over R — used only to choose between the elastic and the
//!   shifted event, so any value that is positive exactly where the integral is
//!   positive keeps the estimator unbiased;
//! * `excitation_range` / `emission_range`: where the material fluoresces.
//!
//! Models form a closed set ([`Model`]), dispatched statically with `match`.
//!
//! # Patch colorimetry (Hua et al. 2022, sec. 7.3, eq. 15)
//! A flat patch lit by a distant light of spectral irradiance I(λ) and seen from the
//! normal: with the diffuse convention (f = P/π), its colour is
//!
//! ```text
//! XYZ = k Σ_λo cmf(λo) [ ρ(λo) I(λo) + Σ_λi P(λi, λo) I(λi) Δλi ] Δλo,   k = 1 / Σ I(λ) ȳ(λ) Δλ
//! ```
//!
//! with ρ the elastic albedo (the reradiation matrix diagonal). Conventions, fixed
//! here and documented for `fluo patch`: λo runs over the observer's CMF domain at
//! 1 nm (trapezoid); λi over the illuminant's domain at 1 nm (a finer grid across a
//! narrow absorption band, see [`crate::jung::absorbed_power`]); I is normalised so
//! that the perfect white diffuser has Y = 1 (`white_xyz`).

use crate::gmm::GmmModel;
use crate::jung::{absorbed_power, JungFluorescence};
use crate::matrix::MatrixModel;
use crate::spectrum::{Cmf, Spectral};
use crate::Result;

/// Operations a wavelength-shifting integrator needs from a fluorescent model.
pub trait Bispectral {
    /// Excitation wavelengths (λi) at which the model re-emits, nm; `None` if it never does.
    fn excitation_range(&self) -> Option<(f64, f64)>;
    /// Wavelengths (λo) at which it re-emits, nm; `None` if it never does.
    fn emission_range(&self) -> Option<(f64, f64)>;
    /// f_fl(λi, ωi, ωo, λo) · cos θo, sr⁻¹ nm⁻¹ (local frame, z up).
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64;
    /// ∫_{range} ∫_Ω f_fl · cos θo dωo dλi: albedo reaching λo from unit excitation over `range`.
    fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64;
    /// Sample λi given λo inside `range`: (λi, pdf per nm), or `None`.
    fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)>;
    /// pdf of [`Bispectral::sample_excitation`].
    fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64;
    /// Sample λo given λi: (λo, pdf per nm), or `None` when λi is not absorbed.
    fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)>;
    /// pdf of [`Bispectral::sample_emission`].
    fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64;
}

/// The closed set of fluorescent models.
#[derive(Debug, Clone)]
pub enum Model {
    /// Jung et al.'s diffuse parametric model.
    Jung(JungFluorescence),
    /// Benamira & Pattanaik's quantum-dot coated microfacet model (boxed: it carries tables).
    Qd(Box<crate::qd::QdModel>),
    /// A measured reradiation matrix, tabulated (`fluo_matrix`).
    Matrix(MatrixModel),
    /// A Gaussian-mixture fit of a measured matrix (`fluo_gmm`).
    Gmm(GmmModel),
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

const INV_PI: f64 = std::f64::consts::FRAC_1_PI;

impl Bispectral for JungFluorescence {
    fn excitation_range(&self) -> Option<(f64, f64)> {
        self.is_fluorescent().then(|| self.absorption_support())
    }
    fn emission_range(&self) -> Option<(f64, f64)> {
        self.is_fluorescent().then(|| self.emission_support())
    }
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        if !(wi[2] > 0.0 && wo[2] > 0.0) {
            return 0.0;
        }
        JungFluorescence::reradiation(self, lambda_i, lambda_o) * INV_PI * wo[2]
    }
    fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64 {
        if !(wi[2] > 0.0) || !self.is_fluorescent() {
            return 0.0;
        }
        // Lambertian: ∫ cos/π dω = 1. Only excitations below λo shift up to it.
        // Most camera wavelengths lie outside the narrow emission band: return before
        // integrating the absorption band.
        let e = self.emission(lambda_o);
        if !(e > 0.0) {
            return 0.0;
        }
        let p = self.params();
        let hi = range.1.min(lambda_o);
        p.concentration * p.quantum_yield * e * self.absorption_integral_range(range.0, hi)
    }
    fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        if !(wi[2] > 0.0) || !(self.emission(lambda_o) > 0.0) {
            return None;
        }
        self.sample_absorption(xi, range.0, range.1.min(lambda_o))
    }
    fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64 {
        if !(wi[2] > 0.0) || !(self.emission(lambda_o) > 0.0) {
            return 0.0;
        }
        self.absorption_pdf(lambda_i, range.0, range.1.min(lambda_o))
    }
    fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        if !(wi[2] > 0.0) || !(self.absorption(lambda_i) > 0.0) {
            return None;
        }
        Some(JungFluorescence::sample_emission(self, xi))
    }
    fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        if !(wi[2] > 0.0) || !(self.absorption(lambda_i) > 0.0) {
            return 0.0;
        }
        JungFluorescence::emission_pdf(self, lambda_o)
    }
}

impl Bispectral for Model {
    fn excitation_range(&self) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => m.excitation_range(),
            Model::Qd(m) => m.excitation_range(),
            Model::Matrix(m) => Bispectral::excitation_range(m),
            Model::Gmm(m) => Bispectral::excitation_range(m),
        }
    }
    fn emission_range(&self) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => m.emission_range(),
            Model::Qd(m) => m.emission_range(),
            Model::Matrix(m) => Bispectral::emission_range(m),
            Model::Gmm(m) => Bispectral::emission_range(m),
        }
    }
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        match self {
            Model::Jung(m) => Bispectral::reradiation(m, wi, wo, lambda_i, lambda_o),
            Model::Qd(m) => m.reradiation(wi, wo, lambda_i, lambda_o),
            Model::Matrix(m) => Bispectral::reradiation(m, wi, wo, lambda_i, lambda_o),
            Model::Gmm(m) => Bispectral::reradiation(m, wi, wo, lambda_i, lambda_o),
        }
    }
    fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64 {
        match self {
            Model::Jung(m) => m.shift_albedo(wi, lambda_o, range),
            Model::Qd(m) => m.shift_albedo(wi, lambda_o, range),
            Model::Matrix(m) => Bispectral::shift_albedo(m, wi, lambda_o, range),
            Model::Gmm(m) => Bispectral::shift_albedo(m, wi, lambda_o, range),
        }
    }
    fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => m.sample_excitation(wi, lambda_o, xi, range),
            Model::Qd(m) => m.sample_excitation(wi, lambda_o, xi, range),
            Model::Matrix(m) => Bispectral::sample_excitation(m, wi, lambda_o, xi, range),
            Model::Gmm(m) => Bispectral::sample_excitation(m, wi, lambda_o, xi, range),
        }
    }
    fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64 {
        match self {
            Model::Jung(m) => m.excitation_pdf(wi, lambda_o, lambda_i, range),
            Model::Qd(m) => m.excitation_pdf(wi, lambda_o, lambda_i, range),
            Model::Matrix(m) => Bispectral::excitation_pdf(m, wi, lambda_o, lambda_i, range),
            Model::Gmm(m) => Bispectral::excitation_pdf(m, wi, lambda_o, lambda_i, range),
        }
    }
    fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        match self {
            Model::Jung(m) => Bispectral::sample_emission(m, wi, lambda_i, xi),
            Model::Qd(m) => m.sample_emission(wi, lambda_i, xi),
            Model::Matrix(m) => Bispectral::sample_emission(m, wi, lambda_i, xi),
            Model::Gmm(m) => Bispectral::sample_emission(m, wi, lambda_i, xi),
        }
    }
    fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        match self {
            Model::Jung(m) => Bispectral::emission_pdf(m, wi, lambda_i, lambda_o),
            Model::Qd(m) => m.emission_pdf(wi, lambda_i, lambda_o),
            Model::Matrix(m) => Bispectral::emission_pdf(m, wi, lambda_i, lambda_o),
            Model::Gmm(m) => Bispectral::emission_pdf(m, wi, lambda_i, lambda_o),
        }
    }
}

/// What a flat patch does to light, for the patch colorimetry: the elastic albedo
/// ρ(λ) and the reradiated spectrum for a given illuminant.
pub trait PatchMaterial {
    /// Elastic albedo ρ(λ) (the diagonal), for light arriving along the normal.
    fn elastic_albedo(&self, lambda: f64) -> f64;
    /// Reradiated radiance factor at λo: ∫ P(λi, λo) I(λi) dλi (diffuse normalisation),
    /// for an illuminant defined on `domain`.
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64;
}

impl PatchMaterial for crate::jung::JungMaterial {
    fn elastic_albedo(&self, lambda: f64) -> f64 {
        crate::jung::JungMaterial::elastic_albedo(self, lambda)
    }
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
        let f = &self.fluorescence;
        let p = f.params();
        if !f.is_fluorescent() || !(f.emission(lambda_o) > 0.0) {
            return 0.0;
        }
        // Only excitation below λo reaches it (no anti-Stokes term).
        let hi = domain.1.min(lambda_o);
        p.concentration * p.quantum_yield * f.emission(lambda_o) * absorbed_power(f, illum, (domain.0, hi), 1.0)
    }
}

// ---------------------------------------------------------------- measured models
// `fluo_matrix` (src/matrix.rs) and `fluo_gmm` (src/gmm.rs): diffuse in direction,
// f_fl = P(λi, λo)/π, with the same wavelength interface on both.

/// λi step of the trapezoid in the measured models' [`PatchMaterial::reradiated`], nm.
const MEASURED_PATCH_STEP_NM: f64 = 0.5;

/// ∫_{lo}^{hi} p(λi) I(λi) dλi by the trapezoid rule on a ≤ [`MEASURED_PATCH_STEP_NM`] grid.
fn integrate_excitation(p: impl Fn(f64) -> f64, illum: &dyn Fn(f64) -> f64, lo: f64, hi: f64) -> f64 {
    if !(hi > lo) {
        return 0.0;
    }
    let n = ((hi - lo) / MEASURED_PATCH_STEP_NM).ceil().max(1.0) as usize;
    let h = (hi - lo) / n as f64;
    let mut sum = 0.0;
    for i in 0..=n {
        let l = if i == n { hi } else { lo + i as f64 * h };
        let w = if i == 0 || i == n { 0.5 } else { 1.0 };
        sum += w * p(l) * illum(l);
    }
    sum * h
}

macro_rules! measured_bispectral {
    ($ty:ty) => {
        impl Bispectral for $ty {
            fn excitation_range(&self) -> Option<(f64, f64)> {
                self.excitation_support()
            }
            fn emission_range(&self) -> Option<(f64, f64)> {
                self.emission_support()
            }
            fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
                if !(wi[2] > 0.0 && wo[2] > 0.0) {
                    return 0.0;
                }
                <$ty>::reradiation(self, lambda_i, lambda_o) * INV_PI * wo[2]
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

        impl crate::reduce::Reradiating for $ty {
            fn diagonal(&self, lambda: f64) -> f64 {
                self.reflectance(lambda)
            }
            fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
                <$ty>::reradiation(self, lambda_i, lambda_o)
            }
        }

        impl PatchMaterial for $ty {
            fn elastic_albedo(&self, lambda: f64) -> f64 {
                self.reflectance(lambda)
            }
            fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
                // Only excitation below λo reaches it; P(λo, λo) is the limit from below.
                integrate_excitation(
                    |li| <$ty>::reradiation(self, li, lambda_o),
                    illum,
                    domain.0,
                    domain.1.min(lambda_o),
                )
            }
        }
    };
}

measured_bispectral!(MatrixModel);
measured_bispectral!(GmmModel);

/// Result of [`patch_xyz`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatchColour {
    /// XYZ of the patch, normalised as [`Self::normalisation`] says.
    pub xyz: [f64; 3],
    /// XYZ of the reference white: a perfect white diffuser under the same light, or
    /// (radiant normalisation) under an equal-energy light of the same power.
    pub white_xyz: [f64; 3],
    /// XYZ of the elastic part alone.
    pub elastic_xyz: [f64; 3],
    /// How the colours are normalised.
    pub normalisation: Normalisation,
}

/// A lamp whose white patch has less luminance than this fraction of what an
/// equal-energy light of the same radiant power gives (a UV lamp: the eye sees almost
/// none of it) is normalised by its radiant power instead ([`Normalisation::Radiant`]):
/// dividing by a white Y near zero would blow the patch's colour up by that ratio.
pub const MIN_LUMINOUS_FRACTION: f64 = 1e-3;

/// How patch colours are normalised.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Normalisation {
    /// The white diffuser under the same light has Y = 1 (lamps the eye sees).
    WhiteY,
    /// A white diffuser under an equal-energy light (over the CMF range) of the same
    /// radiant power has Y = 1, and it is the reference white (UV lamps).
    Radiant,
}

impl Normalisation {
    /// The rule in words, as the `fluo patch` JSON reports it.
    pub fn describe(self) -> &'static str {
        match self {
            Normalisation::WhiteY => "white Y = 1: XYZ = Σ cmf(λo) [ρ(λo) I(λo) + Σ P(λi,λo) I(λi)] / Σ I ȳ",
            Normalisation::Radiant => {
                "radiant (the lamp is nearly invisible): XYZ = Σ cmf(λo) [ρ(λo) I(λo) + Σ P(λi,λo) I(λi)] / (Σ ȳ · ∫I dλ / (λmax − λmin)); \
                 the white is a white diffuser under an equal-energy light of the same power"
            }
        }
    }
}

/// Normalise raw patch sums: `xyz` (the patch), `white` (a white diffuser under the
/// lamp) and `equal_energy_white` (a white diffuser under an equal-energy light of the
/// lamp's radiant power), all in the same units. Returns the scale factor, the
/// reference white and the rule; an error for a lamp without power.
pub fn normalise_patch(white: [f64; 3], equal_energy_white: [f64; 3]) -> Result<(f64, [f64; 3], Normalisation)> {
    if white[1] > 0.0 && white[1] >= MIN_LUMINOUS_FRACTION * equal_energy_white[1] {
        Ok((1.0 / white[1], white.map(|v| v / white[1]), Normalisation::WhiteY))
    } else if equal_energy_white[1] > 0.0 {
        let k = 1.0 / equal_energy_white[1];
        Ok((k, equal_energy_white.map(|v| v * k), Normalisation::Radiant))
    } else {
        Err(crate::Error::data("the lamp has no power over the colour-matching range and its excitation range"))
    }
}

/// Single-bounce XYZ of a flat patch under an illuminant (see the module docs).
pub fn patch_xyz(
    material: &dyn PatchMaterial,
    illum: &dyn Spectral,
    illum_domain: (f64, f64),
    cmf: &Cmf,
) -> Result<PatchColour> {
    let (lo, hi) = (cmf.x().start_nm(), cmf.x().end_nm());
    let n = (hi - lo).round() as usize;
    let eval_i = |l: f64| if l >= illum_domain.0 && l <= illum_domain.1 { illum.eval(l) } else { 0.0 };
    let (mut xyz, mut white, mut elastic, mut cmf_sum) = ([0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3]);
    // Radiant power over the lamp's whole domain (UV included), 1 nm trapezoids.
    let steps = (illum_domain.1 - illum_domain.0).ceil().max(1.0) as usize;
    let h = (illum_domain.1 - illum_domain.0) / steps as f64;
    let power: f64 = (0..=steps)
        .map(|i| if i == 0 || i == steps { 0.5 } else { 1.0 } * h * eval_i(illum_domain.0 + h * i as f64))
        .sum();
    for i in 0..=n {
        let l = lo + (hi - lo) * i as f64 / n as f64;
        let w = if i == 0 || i == n { 0.5 } else { 1.0 };
        let bar = [cmf.x().eval(l), cmf.y().eval(l), cmf.z().eval(l)];
        let il = eval_i(l);
        let el = material.elastic_albedo(l) * il;
        let total = el + material.reradiated(&eval_i, illum_domain, l);
        for k in 0..3 {
            xyz[k] += w * bar[k] * total;
            white[k] += w * bar[k] * il;
            elastic[k] += w * bar[k] * el;
            cmf_sum[k] += w * bar[k];
        }
    }
    let equal_energy = cmf_sum.map(|v| v * power / (hi - lo));
    let (k, white_xyz, normalisation) = normalise_patch(white, equal_energy)?;
    Ok(PatchColour { xyz: xyz.map(|v| v * k), white_xyz, elastic_xyz: elastic.map(|v| v * k), normalisation })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jung::{JungMaterial, JungParams, Reflectance};
    use crate::spectrum::{cmf, Observer};

    const UP: [f64; 3] = [0.0, 0.0, 1.0];

    fn jung() -> JungFluorescence {
        JungFluorescence::new(JungParams {
            emission_peak: 520.0,
            stokes_shift: 60.0,
            concentration: 0.8,
            quantum_yield: 0.9,
        })
        .unwrap()
    }

    #[test]
    fn shift_albedo_is_the_integral_of_reradiation() {
        let m = Model::Jung(jung());
        let lambda_o = 530.0;
        let range = (300.0, 830.0);
        // ∫ dλi ∫ dω f_fl cos: diffuse ⇒ ∫dω cos/π = 1, so integrate P over λi only.
        let (lo, hi) = m.excitation_range().unwrap();
        let n = 20_000;
        let h = (hi - lo) / n as f64;
        let mut s = 0.0;
        for i in 0..n {
            let li = lo + (i as f64 + 0.5) * h;
            s += m.reradiation(UP, UP, li, lambda_o) * std::f64::consts::PI; // undo cos/π at normal
        }
        s *= h;
        let a = m.shift_albedo(UP, lambda_o, range);
        assert!((s - a).abs() < 1e-6 * a, "{s} vs {a}");
    }

    #[test]
    fn excitation_sampling_respects_range_and_pdf() {
        let m = Model::Jung(jung());
        for xi in [0.01, 0.3, 0.77, 0.99] {
            let (li, pdf) = m.sample_excitation(UP, 530.0, xi, (455.0, 830.0)).unwrap();
            assert!((455.0..=488.2).contains(&li), "{li}");
            assert!((pdf - m.excitation_pdf(UP, 530.0, li, (455.0, 830.0))).abs() < 1e-12);
        }
        // no emission at 400 nm: nothing to sample
        assert!(m.sample_excitation(UP, 400.0, 0.5, (300.0, 830.0)).is_none());
        // below the horizon: nothing
        assert!(m.sample_excitation([0.0, 0.0, -1.0], 530.0, 0.5, (300.0, 830.0)).is_none());
        let (lo, pdf) = m.sample_emission(UP, 460.0, 0.5).unwrap();
        assert!((lo - 520.0).abs() < 1e-9 && pdf > 0.0);
        assert!(m.sample_emission(UP, 600.0, 0.5).is_none());
    }

    #[test]
    fn patch_of_white_is_white_and_fluorescence_adds_light() {
        let c = cmf(Observer::Cie2006);
        let e = |_: f64| 1.0;
        let white =
            JungMaterial::new(Reflectance::Constant(1.0), JungParams { concentration: 0.0, ..JungParams::default() })
                .unwrap();
        let p = patch_xyz(&white, &e, (300.0, 830.0), c).unwrap();
        for k in 0..3 {
            assert!((p.xyz[k] - p.white_xyz[k]).abs() < 1e-12);
        }
        assert!((p.white_xyz[1] - 1.0).abs() < 1e-12);
        // fluorescent green on black: all light is reradiated, Y > 0, elastic = 0
        let green = JungMaterial::new(
            Reflectance::Constant(0.0),
            JungParams { emission_peak: 520.0, stokes_shift: 60.0, concentration: 1.0, quantum_yield: 1.0 },
        )
        .unwrap();
        let p = patch_xyz(&green, &e, (300.0, 830.0), c).unwrap();
        assert_eq!(p.elastic_xyz, [0.0; 3]);
        // Under E, absorbed energy ∫a (nm) is re-emitted with unit-integral e: Y = ∫a·∫e ȳ / ∫ȳ.
        let m = &green.fluorescence;
        let ybar_e: f64 = (0..=4400).map(|i| 390.0 + i as f64 * 0.1).map(|l| m.emission(l) * c.y().eval(l) * 0.1).sum();
        let want = m.absorption_integral() * ybar_e / c.y().integrate();
        assert!((p.xyz[1] - want).abs() < 2e-3 * want, "{} vs {want}", p.xyz[1]);
    }
}
