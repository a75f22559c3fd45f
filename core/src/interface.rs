//! The one interface every fluorescent (bispectral) material implements.
//!
//! A bispectral BBRRDF splits into an elastic part (wavelength-preserving, served by
//! the model's ordinary BSDF) and reradiation f_fl(λi, ωi, ωo, λo) (sr⁻¹ nm⁻¹): light
//! absorbed at λi and re-emitted at λo > λi. [`Bispectral`] exposes both views of it:
//!
//! **Spectral operator** (patch colorimetry, reductions, RGB fallbacks), for light
//! arriving at incidence cosine `cos_i` and the diffuse normalisation (f = P/π):
//!
//! * `elastic_albedo`: the diagonal ρ(λ), the fraction kept at the same wavelength;
//! * `density`: P(λi, λo), nm⁻¹, reradiated per unit excitation and per nm of emission;
//! * `reradiated`: ∫ P(λi, λo) I(λi) dλi for an illuminant I (a provided method; a
//!   model with a sharper quadrature of its own overrides it).
//!
//! Diffuse models ignore `cos_i`; the quantum-dot coating depends on it. Patch
//! colorimetry and single reductions take light along the normal (`cos_i = 1`).
//!
//! **Directional sampling** (the wavelength-shifting path tracer), local frame, unit
//! directions, ωi given:
//!
//! * `reradiation`: f_fl · cos θo (Mitsuba's convention: BSDF values include the
//!   outgoing cosine);
//! * `sample_excitation` / `excitation_pdf`: λi given λo (camera paths), restricted
//!   to a range where light exists;
//! * `sample_emission` / `emission_pdf`: λo given λi (light paths);
//! * `shift_albedo`: ∫_R ∫_Ω f_fl cos θo dωo dλi, the reradiated albedo reaching
//!   λo from unit excitation over R: used only to choose between the elastic and the
//!   shifted event, so any value that is positive exactly where the integral is
//!   positive keeps the estimator unbiased;
//! * `excitation_range` / `emission_range`: where the material fluoresces.
//!
//! This module imports no model: the models (`crate::models`) implement it, and
//! `crate::models::Model` dispatches over the closed set of them.

/// λi step of the trapezoid in the provided [`Bispectral::reradiated`], nm.
pub const RERADIATED_STEP_NM: f64 = 0.5;

/// A fluorescent material: its spectral operator and what a wavelength-shifting path
/// tracer needs of its reradiation (see the module docs for conventions).
pub trait Bispectral {
    /// Excitation wavelengths (λi) at which the material re-emits, nm; `None` if it never does.
    fn excitation_range(&self) -> Option<(f64, f64)>;
    /// Wavelengths (λo) at which it re-emits, nm; `None` if it never does.
    fn emission_range(&self) -> Option<(f64, f64)>;

    /// Elastic albedo ρ(λ) for light arriving at incidence cosine `cos_i`.
    fn elastic_albedo(&self, cos_i: f64, lambda: f64) -> f64;
    /// Reradiation density P(λi, λo), nm⁻¹, for light arriving at incidence cosine
    /// `cos_i` (diffuse normalisation; zero for λo ≤ λi when there is no anti-Stokes part).
    fn density(&self, cos_i: f64, lambda_i: f64, lambda_o: f64) -> f64;
    /// Where the density factors as P(λi, λo) = a(λi)·b(λo) for λi < λo and 0 for λi ≥ λo
    /// (Stokes-only and separable: quantum dots, Jung's dye), a and b on `lambdas`; `None`
    /// (the default) otherwise. A reduction then sums over λi < λo as it runs along λo:
    /// O(N·K) instead of the O(N²·K) of the whole operator, whose N² entries it would
    /// otherwise evaluate one by one.
    fn density_factors(&self, cos_i: f64, lambdas: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
        let _ = (cos_i, lambdas);
        None
    }
    /// Reradiated radiance factor at λo for light along the normal:
    /// ∫ P(λi, λo) I(λi) dλi over `domain` (only excitation below λo reaches it),
    /// trapezoid on a ≤ [`RERADIATED_STEP_NM`] grid.
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
        let (lo, hi) = (domain.0, domain.1.min(lambda_o));
        if !(hi > lo) {
            return 0.0;
        }
        let n = ((hi - lo) / RERADIATED_STEP_NM).ceil().max(1.0) as usize;
        let h = (hi - lo) / n as f64;
        let mut sum = 0.0;
        for i in 0..=n {
            let l = if i == n { hi } else { lo + i as f64 * h };
            let w = if i == 0 || i == n { 0.5 } else { 1.0 };
            sum += w * self.density(1.0, l, lambda_o) * illum(l);
        }
        sum * h
    }

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
