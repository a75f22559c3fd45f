//! Jung et al.'s diffuse fluorescent BBRRDF with parametric absorption and emission.
//!
//! # Model
//! Jung, Hanika, Dachsbacher 2018 (MAM), as used in Jung et al. 2019, eq. 1:
//!
//! ```text
//! f(λi, ωi, ωo, λo) = [ δ(λi − λo)·(1 − c·a(λi))·r(λi)  +  c·a(λi)·Q·e(λo) ] / π
//! ```
//!
//! The first summand is ordinary (elastic) diffuse reflection, the second the
//! fluorescent reradiation `P(λi, λo) = c·a(λi)·Q·e(λo)` (per nm of λo).
//!
//! Emission and absorption (Jung et al. 2019, eqs. 3–6), with the quadratic b-spline
//! `b(x)` of eq. 3 (support (−3, 3), peak b(0) = 1, ∫b = 8/3):
//!
//! ```text
//! α    = λe·s / (2λe − s)                                   (eq. 4)
//! e(λo) = b(3(λo − λe)/α) · 9/(8α)                          (eq. 5, ∫e = 1)
//! a(λi) = b(3/α · ((2/(λe − α) − 1/λi)⁻¹ − λe))             (eq. 6, max a = 1)
//! ```
//!
//! Reading of eq. 6 (checked against the physics, see shared/papers/README.md):
//! absorption is the emission mirrored over *wavenumber* about the emission's short
//! edge λe − α, i.e. 1/λ' = 2/(λe − α) − 1/λi. Its peak is then at
//! λa = λe(λe − α)/(λe + α) = λe − s, which is exactly eq. 4 solved for s, and its
//! support is ((λe−α)(λe+α)/(λe+3α), λe − α): absorption and emission touch but do
//! not overlap, so reradiation only shifts to longer wavelengths.
//!
//! # Parameters
//! | name            | symbol | unit | valid range                          | default |
//! |-----------------|--------|------|--------------------------------------|---------|
//! | `emission_peak` | λe     | nm   | [200, 1200]                          | 520     |
//! | `stokes_shift`  | s      | nm   | [0.001, s_max(λe)), see below        | 60      |
//! | `concentration` | c      | 1    | [0, 1]                               | 0.5     |
//! | `quantum_yield` | Q      | 1    | [0, 1]                               | 0.96    |
//!
//! `s_max(λe)` keeps 2λe − s > 0 (α > 0) and the absorption support positive with a
//! margin: λe − α ≥ [`MIN_ABSORPTION_EDGE_NM`].
//!
//! # Sampling
//! * Emission (λo given λi, light paths): exact inverse CDF of the b-spline, one
//!   uniform number; equivalent to eq. 8 (sum of three uniforms), pdf = e(λo).
//! * Absorption (λi given λo, camera paths): exact, pdf ∝ a(λi) (not the paper's
//!   triangular approximation). The CDF has a closed form: with v = u + 3 ∈ [0, 6]
//!   (u the b-spline argument), dλi = (α/3)/(1 + βv)² dv, β = 2α/(3(λe − α)), so
//!   ∫a dλi is a sum of moments ∫vⁿ/(1+βv)² dv of the three quadratic pieces (the
//!   masses of whole pieces are baked, so one evaluation costs one piece's moments). It
//!   is inverted by safeguarded Newton iteration (bounded: [`MAX_NEWTON_ITERATIONS`]),
//!   optionally restricted to an excitation range [lo, hi] (e.g. where lights emit),
//!   started from a baked inverse CDF: λ at [`INVERSE_CDF_INTERVALS`] + 1 equally
//!   spaced levels of the CDF with the slopes dλ/dF = ∫a / a(λ), read by cubic Hermite
//!   interpolation (cube-root in the two end intervals, where the mass is cubic in the
//!   distance to the support's end). The start only saves iterations: the root, its
//!   tolerance and the pdf a(λi)/∫a are those of the exact CDF, as without the table.
//!
//! # Numerical notes
//! * Tiny Stokes shifts make β → 0: the moments then use their power series (no
//!   cancellation); otherwise the closed forms with `ln_1p`.
//! * Near s_max, λe − α → 0 and the absorption band stretches towards 0 nm; the
//!   margin [`MIN_ABSORPTION_EDGE_NM`] keeps every expression finite.
//! * Every function returns an exact 0 outside its support.
//!
//! # References
//! A. Jung, J. Hanika, C. Dachsbacher, "A Simple Diffuse Fluorescent BBRRDF Model",
//! MAM 2018. A. Jung, A. Wilkie, J. Hanika, W. Jakob, C. Dachsbacher, "Wide Gamut
//! Spectral Upsampling with Fluorescence", CGF 38(4), 2019.

use std::f64::consts::FRAC_1_PI;
use std::fmt;

use crate::error::check_range;
use crate::interface::Bispectral;
use crate::sigmoid::SigmoidPolynomial;
use crate::{Error, Result};

/// Smallest accepted short edge λe − α of the emission band (= long edge of the
/// absorption band), nm. Keeps the absorption support positive with a margin.
pub const MIN_ABSORPTION_EDGE_NM: f64 = 1.0;
/// Smallest accepted Stokes shift, nm (the model degenerates to a delta at s = 0).
pub const MIN_STOKES_SHIFT_NM: f64 = 1e-3;
/// Valid emission peak range, nm.
pub const EMISSION_PEAK_RANGE_NM: (f64, f64) = (200.0, 1200.0);
/// Iteration bound of the safeguarded Newton inversion of the absorption CDF.
pub const MAX_NEWTON_ITERATIONS: usize = 64;
/// Relative tolerance (of the support width) at which the CDF inversion stops.
const NEWTON_TOLERANCE: f64 = 1e-13;
/// Newton steps below this fraction of the support width end the inversion when the
/// quadratic error estimate after them is below the tolerance (the cubic term is then
/// ~1e-15 of the width).
const NEWTON_POLISH_STEP: f64 = 1e-5;
/// Intervals of the baked inverse absorption CDF that starts the Newton iteration
/// (equally spaced in the CDF; 33 nodes, 528 bytes per dye).
pub const INVERSE_CDF_INTERVALS: usize = 32;
/// b(v − 3) on the pieces [0, 2], [2, 4], [4, 6] of v as c0 + c1 v + c2 v².
const PIECES: [(f64, f64, [f64; 3]); 3] =
    [(0.0, 2.0, [0.0, 0.0, 1.0 / 6.0]), (2.0, 4.0, [-2.0, 2.0, -1.0 / 3.0]), (4.0, 6.0, [6.0, -2.0, 1.0 / 6.0])];
/// Below this β·v the absorption-CDF moments use their power series. The closed forms
/// cancel to order x³ (g₂ ≈ x³/3), leaving a relative error near 3ε/x² ≈ 7e-12 at the
/// switch; the series needs ~8 terms there. (At 0.25 the series took ~30 terms and
/// dominated the cost of fluorescent vertices.)
const SERIES_MAX_X: f64 = 0.01;
/// Hard bound on power-series terms (0.25^80 is far below f64 resolution).
const SERIES_MAX_TERMS: usize = 80;

/// Quadratic b-spline of Jung et al. eq. 3: support (−3, 3), b(0) = 1.
pub fn bspline(x: f64) -> f64 {
    let ax = x.abs();
    if ax <= 1.0 {
        1.0 - x * x / 3.0
    } else if ax < 3.0 {
        let d = 3.0 - ax;
        d * d / 6.0
    } else {
        0.0
    }
}

/// User-facing parameters of the fluorescent part (see the module table).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JungParams {
    /// Emission peak λe, nm.
    pub emission_peak: f64,
    /// Stokes shift s (emission peak − absorption peak), nm.
    pub stokes_shift: f64,
    /// Concentration (mixing factor) c ∈ [0, 1].
    pub concentration: f64,
    /// Quantum yield Q ∈ [0, 1].
    pub quantum_yield: f64,
}

impl Default for JungParams {
    fn default() -> Self {
        Self { emission_peak: 520.0, stokes_shift: 60.0, concentration: 0.5, quantum_yield: 0.96 }
    }
}

/// Largest valid Stokes shift for a given emission peak: the s at which
/// λe − α(s) = [`MIN_ABSORPTION_EDGE_NM`] (α = λe s/(2λe − s) is increasing in s).
pub fn max_stokes_shift(emission_peak: f64) -> f64 {
    let alpha = emission_peak - MIN_ABSORPTION_EDGE_NM;
    2.0 * emission_peak * alpha / (emission_peak + alpha)
}

/// The `fluo_jung` parameters that take a texture ([`check_param_value`]).
pub const TEXTURABLE_PARAMS: [&str; 4] = ["emission_peak", "stokes_shift", "concentration", "quantum_yield"];

/// Check one value of a `fluo_jung` parameter on its own, as every texel (or constituent
/// value) of a parameter texture is checked at load: `concentration` and `quantum_yield`
/// in [0, 1], `emission_peak` in [`EMISSION_PEAK_RANGE_NM`], `stokes_shift` finite in
/// [[`MIN_STOKES_SHIFT_NM`], s_max(1200 nm)). A Stokes shift's full bound depends on the
/// emission peak: [`JungFluorescence::new`] checks each (λe, s) pair that can meet.
pub fn check_param_value(name: &str, value: f64) -> Result<()> {
    match name {
        "concentration" | "quantum_yield" => check_range(name, value, 0.0, 1.0).map(|_| ()),
        "emission_peak" => check_range(name, value, EMISSION_PEAK_RANGE_NM.0, EMISSION_PEAK_RANGE_NM.1).map(|_| ()),
        "stokes_shift" => {
            let hi = max_stokes_shift(EMISSION_PEAK_RANGE_NM.1);
            if value.is_finite() && value >= MIN_STOKES_SHIFT_NM && value < hi {
                Ok(())
            } else {
                Err(Error::param(
                    name,
                    value,
                    format!("[{MIN_STOKES_SHIFT_NM}, {hi:.4}) nm (and below s_max of every emission_peak it meets)"),
                ))
            }
        }
        _ => Err(Error::param("parameter", format!("\"{name}\""), TEXTURABLE_PARAMS.join(", "))),
    }
}

/// The fluorescent part of the model with its derived ("baked") quantities.
#[derive(Debug, Clone, PartialEq)]
pub struct JungFluorescence {
    params: JungParams,
    /// Emission half-width α (eq. 4), nm.
    alpha: f64,
    /// Mirror constant k = 2/(λe − α), nm⁻¹.
    k: f64,
    /// β = 2α / (3(λe − α)), the slope of the Jacobian denominator in v.
    beta: f64,
    /// Absorption support [min, max], nm.
    absorption_support: (f64, f64),
    /// ∫ a(λ) dλ over the whole support, nm.
    absorption_integral: f64,
    /// ∫ b(v − 3)/(1 + βv)² dv over the pieces above piece p (v ≥ 2(p + 1)).
    tails_above: [f64; 3],
    /// Inverse CDF at F = i / [`INVERSE_CDF_INTERVALS`]: (λ, dλ/dF); the end slopes are unused.
    inverse_cdf: Vec<(f64, f64)>,
}

impl JungFluorescence {
    /// Validate the parameters and bake the derived data.
    pub fn new(params: JungParams) -> Result<Self> {
        let (lo, hi) = EMISSION_PEAK_RANGE_NM;
        let le = check_range("emission_peak", params.emission_peak, lo, hi)?;
        let s_max = max_stokes_shift(le);
        let s = params.stokes_shift;
        if !(s.is_finite() && s >= MIN_STOKES_SHIFT_NM && s < s_max) {
            return Err(Error::param(
                "stokes_shift",
                s,
                format!(
                    "[{MIN_STOKES_SHIFT_NM}, {s_max:.4}) nm for emission_peak = {le} nm \
                     (2·emission_peak − stokes_shift > 0 and the absorption band must stay above \
                     {MIN_ABSORPTION_EDGE_NM} nm)"
                ),
            ));
        }
        check_range("concentration", params.concentration, 0.0, 1.0)?;
        check_range("quantum_yield", params.quantum_yield, 0.0, 1.0)?;

        let alpha = le * s / (2.0 * le - s);
        let edge = le - alpha; // > MIN_ABSORPTION_EDGE_NM by the check above
        let k = 2.0 / edge;
        let beta = 2.0 * alpha / (3.0 * edge);
        let support = (edge * (le + alpha) / (le + 3.0 * alpha), edge);
        let mut model = Self {
            params,
            alpha,
            k,
            beta,
            absorption_support: support,
            absorption_integral: 0.0,
            tails_above: [0.0; 3],
            inverse_cdf: Vec::new(),
        };
        let piece = |p: usize| {
            let (a, b, c) = PIECES[p];
            let m = moments(a, b, beta);
            c[0] * m[0] + c[1] * m[1] + c[2] * m[2]
        };
        model.tails_above = [piece(1) + piece(2), piece(2), 0.0];
        model.absorption_integral = model.absorption_tail(0.0);
        model.inverse_cdf = model.bake_inverse_cdf();
        Ok(model)
    }

    /// The parameters this model was built from.
    pub fn params(&self) -> &JungParams {
        &self.params
    }

    /// Emission half-width α (eq. 4), nm: e is supported on (λe − α, λe + α).
    pub fn alpha(&self) -> f64 {
        self.alpha
    }

    /// Emission support (λe − α, λe + α), nm.
    pub fn emission_support(&self) -> (f64, f64) {
        (self.params.emission_peak - self.alpha, self.params.emission_peak + self.alpha)
    }

    /// Absorption support, nm.
    pub fn absorption_support(&self) -> (f64, f64) {
        self.absorption_support
    }

    /// Absorption peak wavelength λe − s, nm (where a = 1).
    pub fn absorption_peak(&self) -> f64 {
        self.params.emission_peak - self.params.stokes_shift
    }

    /// Whether the material re-emits at all (c > 0 and Q > 0).
    pub fn is_fluorescent(&self) -> bool {
        self.params.concentration > 0.0 && self.params.quantum_yield > 0.0
    }

    /// Emission spectrum e(λo), nm⁻¹, unit integral (eq. 5).
    pub fn emission(&self, lambda_o: f64) -> f64 {
        bspline(3.0 * (lambda_o - self.params.emission_peak) / self.alpha) * (9.0 / (8.0 * self.alpha))
    }

    /// Map λi to v = u + 3 ∈ (0, 6) of the absorption b-spline, or `None` outside
    /// the support. v = 3(λ' − (λe − α))/α with λ' the mirrored wavelength; written
    /// as 3(2 − kλi) / (αk(kλi − 1)) to avoid cancellation.
    fn absorption_v(&self, lambda_i: f64) -> Option<f64> {
        let (lo, hi) = self.absorption_support;
        if !(lambda_i > lo && lambda_i < hi) {
            return None;
        }
        let kl = self.k * lambda_i; // in (1, 2) on the support
        Some(3.0 * (2.0 - kl) / (self.alpha * self.k * (kl - 1.0)))
    }

    /// Absorption spectrum a(λi) ∈ [0, 1], peak 1 at λe − s (eq. 6).
    pub fn absorption(&self, lambda_i: f64) -> f64 {
        self.absorption_v(lambda_i).map_or(0.0, |v| bspline(v - 3.0))
    }

    /// ∫ a(λ) dλ over the whole support, nm.
    pub fn absorption_integral(&self) -> f64 {
        self.absorption_integral
    }

    /// ∫_{lo}^{hi} a(λ) dλ, nm (0 if the ranges do not overlap).
    pub fn absorption_integral_range(&self, lo: f64, hi: f64) -> f64 {
        (self.absorption_cdf(hi) - self.absorption_cdf(lo)).max(0.0)
    }

    /// Unnormalised CDF: ∫_{−∞}^{λ} a(t) dt.
    pub fn absorption_cdf(&self, lambda: f64) -> f64 {
        let (lo, hi) = self.absorption_support;
        if !(lambda > lo) {
            0.0
        } else if lambda >= hi {
            self.absorption_integral
        } else {
            // λ in the support: the mass below λ is the mass at v' ∈ [v(λ), 6].
            self.absorption_v(lambda).map_or(0.0, |v| self.absorption_tail(v))
        }
    }

    /// (α/3) ∫_{v}^{6} b(v' − 3) / (1 + βv')² dv'  — mass of λi below λ(v): the part
    /// of v's piece above v plus the baked masses of the pieces above it.
    fn absorption_tail(&self, v: f64) -> f64 {
        let v = v.clamp(0.0, 6.0);
        let p = ((0.5 * v) as usize).min(2);
        let (_, b, c) = PIECES[p];
        let part = if v < b {
            let m = moments(v, b, self.beta);
            c[0] * m[0] + c[1] * m[1] + c[2] * m[2]
        } else {
            0.0
        };
        (self.alpha / 3.0) * (part + self.tails_above[p]).max(0.0)
    }

    /// λ at the CDF levels i / [`INVERSE_CDF_INTERVALS`] (by the exact inversion) with
    /// the slopes dλ/dF = ∫a / a(λ).
    fn bake_inverse_cdf(&self) -> Vec<(f64, f64)> {
        let (slo, shi) = self.absorption_support;
        let n = INVERSE_CDF_INTERVALS;
        (0..=n)
            .map(|i| {
                let x = match i {
                    0 => slo,
                    _ if i == n => shi,
                    _ => self.invert_cdf(i as f64 / n as f64 * self.absorption_integral, slo, shi, slo, shi, None),
                };
                let a = self.absorption(x);
                (x, if a > 0.0 { self.absorption_integral / a } else { 0.0 })
            })
            .collect()
    }

    /// Start of the inversion of cdf(λ) = `target` from the baked inverse CDF: cubic
    /// Hermite inside, linear in the end intervals.
    fn inverse_cdf_guess(&self, target: f64) -> Option<f64> {
        let n = INVERSE_CDF_INTERVALS;
        let f = target / self.absorption_integral * n as f64;
        if !(f >= 0.0 && f <= n as f64) || self.inverse_cdf.len() != n + 1 {
            return None;
        }
        let i = (f as usize).min(n - 1);
        let t = f - i as f64;
        let ((x0, s0), (x1, s1)) = (self.inverse_cdf[i], self.inverse_cdf[i + 1]);
        // The b-spline's ends make the mass cubic in the distance to the support's ends.
        if i == 0 {
            return Some(x0 + (x1 - x0) * t.cbrt());
        }
        if i == n - 1 {
            return Some(x1 - (x1 - x0) * (1.0 - t).cbrt());
        }
        let h = 1.0 / n as f64;
        let (t2, t3) = (t * t, t * t * t);
        let x = (2.0 * t3 - 3.0 * t2 + 1.0) * x0
            + (t3 - 2.0 * t2 + t) * h * s0
            + (-2.0 * t3 + 3.0 * t2) * x1
            + (t3 - t2) * h * s1;
        Some(x)
    }

    /// a(λi) and its derivative da/dλi (zero outside the support).
    fn absorption_and_slope(&self, lambda_i: f64) -> (f64, f64) {
        let Some(v) = self.absorption_v(lambda_i) else { return (0.0, 0.0) };
        let u = v - 3.0;
        let db = if u.abs() <= 1.0 { -2.0 * u / 3.0 } else { -u.signum() * (3.0 - u.abs()) / 3.0 };
        let kl = self.k * lambda_i - 1.0;
        (bspline(u), db * -3.0 / (self.alpha * kl * kl)) // dv/dλ = −3 / (α (kλ − 1)²)
    }

    /// Safeguarded Newton on F(λ) = cdf(λ) − `target` over [lo, hi] ⊂ the support
    /// [slo, shi], F increasing with F' = a(λ), from `start` (the midpoint if `None` or
    /// outside). Stops when the step is below the tolerance, or when it is small and
    /// Newton's error estimate after it, |a'/(2a)|·step², is.
    fn invert_cdf(&self, target: f64, lo: f64, hi: f64, slo: f64, shi: f64, start: Option<f64>) -> f64 {
        let (mut a, mut b) = (lo, hi);
        let mut x = start.filter(|x| *x > a && *x < b).unwrap_or(0.5 * (a + b));
        let tol = NEWTON_TOLERANCE * (shi - slo);
        let polish = NEWTON_POLISH_STEP * (shi - slo);
        for _ in 0..MAX_NEWTON_ITERATIONS {
            let f = self.absorption_cdf(x) - target;
            if f > 0.0 {
                b = x;
            } else {
                a = x;
            }
            let (d, slope) = self.absorption_and_slope(x);
            let newton = if d > 0.0 { x - f / d } else { f64::NAN };
            if newton > a && newton < b {
                let step = newton - x;
                if step.abs() <= tol || (step.abs() <= polish && 0.5 * (slope / d).abs() * step * step <= tol) {
                    return newton;
                }
                x = newton;
            } else {
                let mid = 0.5 * (a + b);
                if (mid - x).abs() <= tol || b - a <= tol {
                    return mid;
                }
                x = mid;
            }
        }
        x
    }

    /// Sample λo ∝ e(λo) from one uniform number (exact inverse CDF of the b-spline;
    /// the same distribution as eq. 8). Returns (λo, pdf = e(λo)).
    pub fn sample_emission(&self, xi: f64) -> (f64, f64) {
        let t = irwin_hall3_inverse_cdf(xi.clamp(0.0, 1.0));
        let lambda_o = self.params.emission_peak + self.alpha * (2.0 * t / 3.0 - 1.0);
        (lambda_o, self.emission(lambda_o))
    }

    /// pdf of [`Self::sample_emission`], nm⁻¹.
    pub fn emission_pdf(&self, lambda_o: f64) -> f64 {
        self.emission(lambda_o)
    }

    /// Sample λi ∝ a(λi) restricted to [lo, hi] (use the whole support with
    /// `(0, f64::INFINITY)`). Returns `None` when no absorption lies in the range.
    /// Returns (λi, pdf) with pdf = a(λi) / ∫_{lo}^{hi} a.
    pub fn sample_absorption(&self, xi: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
        let (slo, shi) = self.absorption_support;
        let (lo, hi) = (lo.max(slo), hi.min(shi));
        if !(hi > lo) {
            return None;
        }
        let (c_lo, c_hi) = (self.absorption_cdf(lo), self.absorption_cdf(hi));
        let mass = c_hi - c_lo;
        if !(mass > 0.0) {
            return None;
        }
        let target = c_lo + xi.clamp(0.0, 1.0) * mass;
        let x = self.invert_cdf(target, lo, hi, slo, shi, self.inverse_cdf_guess(target));
        let pdf = self.absorption(x) / mass;
        if pdf > 0.0 && pdf.is_finite() {
            Some((x, pdf))
        } else {
            None
        }
    }

    /// pdf of [`Self::sample_absorption`] with the same range.
    pub fn absorption_pdf(&self, lambda_i: f64, lo: f64, hi: f64) -> f64 {
        if !(lambda_i >= lo && lambda_i <= hi) {
            return 0.0;
        }
        let mass = self.absorption_integral_range(lo, hi);
        if mass > 0.0 {
            self.absorption(lambda_i) / mass
        } else {
            0.0
        }
    }

    /// Elastic factor 1 − c·a(λ) multiplying the reflectance at λ.
    pub fn elastic_factor(&self, lambda: f64) -> f64 {
        1.0 - self.params.concentration * self.absorption(lambda)
    }

    /// Reradiation P(λi, λo) = c·a(λi)·Q·e(λo), nm⁻¹ (the BBRRDF's fluorescent
    /// summand times π).
    pub fn reradiation(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        if !(lambda_o > lambda_i) {
            return 0.0; // absorption and emission never overlap: no anti-Stokes term
        }
        self.params.concentration * self.params.quantum_yield * self.absorption(lambda_i) * self.emission(lambda_o)
    }
}

impl fmt::Display for JungFluorescence {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let p = &self.params;
        let (alo, ahi) = self.absorption_support;
        write!(
            f,
            "JungFluorescence[emission_peak = {} nm, stokes_shift = {} nm, concentration = {}, \
             quantum_yield = {}, alpha = {:.4} nm, absorption = ({alo:.2}, {ahi:.2}) nm, \
             ∫a = {:.4} nm]",
            p.emission_peak, p.stokes_shift, p.concentration, p.quantum_yield, self.alpha, self.absorption_integral
        )
    }
}

/// Moments ∫_{v1}^{v2} vⁿ / (1 + βv)² dv for n = 0, 1, 2 (0 ≤ v1 ≤ v2, β ≥ 0).
fn moments(v1: f64, v2: f64, beta: f64) -> [f64; 3] {
    if beta * v2 <= SERIES_MAX_X {
        // 1/(1+x)² = Σ (−1)^m (m+1) x^m, integrated term by term.
        let mut out = [0.0; 3];
        for (n, o) in out.iter_mut().enumerate() {
            let p1 = v1.powi(n as i32 + 1);
            let p2 = v2.powi(n as i32 + 1);
            let (x1, x2) = (beta * v1, beta * v2);
            let (mut q1, mut q2) = (1.0, 1.0); // x^m
            let mut sum = 0.0;
            for m in 0..SERIES_MAX_TERMS {
                let sign = if m % 2 == 0 { 1.0 } else { -1.0 };
                let term = sign * (m as f64 + 1.0) / ((n + m + 1) as f64) * (p2 * q2 - p1 * q1);
                sum += term;
                if term.abs() <= f64::EPSILON * 1e-3 * sum.abs() {
                    break;
                }
                q1 *= x1;
                q2 *= x2;
            }
            *o = sum;
        }
        out
    } else {
        // g0 = x/(1+x), g1 = ln(1+x) − x/(1+x), g2 = x − 2 ln(1+x) + x/(1+x)
        let g = |x: f64| {
            let r = x / (1.0 + x);
            let l = x.ln_1p();
            [r, l - r, x - 2.0 * l + r]
        };
        let (a, b) = (g(beta * v1), g(beta * v2));
        [(b[0] - a[0]) / beta, (b[1] - a[1]) / (beta * beta), (b[2] - a[2]) / (beta * beta * beta)]
    }
}

/// Inverse CDF of the sum of three uniforms (Irwin–Hall, n = 3) on [0, 3].
fn irwin_hall3_inverse_cdf(u: f64) -> f64 {
    const ONE_SIXTH: f64 = 1.0 / 6.0;
    if u <= ONE_SIXTH {
        (6.0 * u).cbrt()
    } else if u >= 1.0 - ONE_SIXTH {
        3.0 - (6.0 * (1.0 - u)).cbrt()
    } else {
        // Middle piece, y = t − 3/2: F = 1/2 + 3y/4 − y³/3, i.e. y³ − (9/4)y + 3(F − 1/2) = 0.
        // Trigonometric root of the depressed cubic lying in [−1/2, 1/2].
        let q = 3.0 * (u - 0.5);
        let arg = (-4.0 * q / (3.0 * 3f64.sqrt())).clamp(-1.0, 1.0);
        let y = 3f64.sqrt() * ((arg.acos() - 2.0 * std::f64::consts::PI) / 3.0).cos();
        1.5 + y
    }
}

/// Reflectance of the elastic part.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Reflectance {
    /// A constant reflectance in [0, 1].
    Constant(f64),
    /// Jakob–Hanika sigmoid polynomial (eq. 2).
    Sigmoid(SigmoidPolynomial),
}

impl Reflectance {
    /// r(λ).
    pub fn eval(&self, lambda_nm: f64) -> f64 {
        match self {
            Reflectance::Constant(r) => *r,
            Reflectance::Sigmoid(s) => s.eval(lambda_nm),
        }
    }

    /// Validate (constant in [0, 1], finite coefficients).
    pub fn validate(&self) -> Result<()> {
        match self {
            Reflectance::Constant(r) => check_range("reflectance", *r, 0.0, 1.0).map(|_| ()),
            Reflectance::Sigmoid(s) => SigmoidPolynomial::new(s.coefficients).map(|_| ()),
        }
    }
}

/// The complete Jung material: reflectance plus fluorescence (eq. 1).
#[derive(Debug, Clone, PartialEq)]
pub struct JungMaterial {
    /// Elastic reflectance r(λ).
    pub reflectance: Reflectance,
    /// Fluorescent part.
    pub fluorescence: JungFluorescence,
}

impl JungMaterial {
    /// Build and validate.
    pub fn new(reflectance: Reflectance, params: JungParams) -> Result<Self> {
        reflectance.validate()?;
        Ok(Self { reflectance, fluorescence: JungFluorescence::new(params)? })
    }

    /// Elastic (diagonal) albedo (1 − c·a(λ))·r(λ).
    pub fn elastic_albedo(&self, lambda: f64) -> f64 {
        self.fluorescence.elastic_factor(lambda) * self.reflectance.eval(lambda)
    }

    /// Spectrum reflected towards any direction by a flat patch lit by `illum(λ)`
    /// (per unit of radiance and π): R(λ) = r(λ)(1 − c a(λ)) I(λ) + Q c e(λ) ∫ a I
    /// (Jung et al. 2019, eq. 7). `illum_range` bounds ∫ a I and `grid_step` its
    /// trapezoid grid, nm.
    pub fn reflected(&self, illum: &dyn Fn(f64) -> f64, illum_range: (f64, f64), grid_step: f64, lambda: f64) -> f64 {
        let p = self.fluorescence.params();
        let excitation = absorbed_power(&self.fluorescence, illum, illum_range, grid_step);
        self.elastic_albedo(lambda) * illum(lambda)
            + p.quantum_yield * p.concentration * self.fluorescence.emission(lambda) * excitation
    }
}

/// ∫ a(λ) I(λ) dλ over `range` with the trapezoid rule on a `step` grid; the absorption
/// band's own support bounds the integration so narrow bands are not missed.
pub fn absorbed_power(f: &JungFluorescence, illum: &dyn Fn(f64) -> f64, range: (f64, f64), step: f64) -> f64 {
    let (slo, shi) = f.absorption_support();
    let (lo, hi) = (range.0.max(slo), range.1.min(shi));
    if !(hi > lo) || !(step > 0.0) {
        return 0.0;
    }
    // At least 256 intervals across the band, so tiny widths integrate accurately.
    let n = (((hi - lo) / step).ceil() as usize).max(256);
    let h = (hi - lo) / n as f64;
    let mut sum = 0.0;
    for i in 0..=n {
        let l = lo + i as f64 * h;
        let w = if i == 0 || i == n { 0.5 } else { 1.0 };
        sum += w * f.absorption(l) * illum(l);
    }
    sum * h
}

// ---------------------------------------------------------------- the interface

impl Bispectral for JungFluorescence {
    fn excitation_range(&self) -> Option<(f64, f64)> {
        self.is_fluorescent().then(|| self.absorption_support())
    }
    fn emission_range(&self) -> Option<(f64, f64)> {
        self.is_fluorescent().then(|| self.emission_support())
    }
    /// The elastic factor 1 − c·a(λ): the albedo of the dye over a white base (the
    /// plugin multiplies it by the base reflectance, a Mitsuba texture, per hit).
    fn elastic_albedo(&self, _cos_i: f64, lambda: f64) -> f64 {
        self.elastic_factor(lambda)
    }
    fn density(&self, _cos_i: f64, lambda_i: f64, lambda_o: f64) -> f64 {
        JungFluorescence::reradiation(self, lambda_i, lambda_o)
    }
    /// P = (c·Q·a(λi))·e(λo) for λi < λo.
    fn density_factors(&self, _cos_i: f64, lambdas: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
        let cq = self.params.concentration * self.params.quantum_yield;
        Some((
            lambdas.iter().map(|&l| cq * self.absorption(l)).collect(),
            lambdas.iter().map(|&l| self.emission(l)).collect(),
        ))
    }
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
        let p = self.params();
        if !self.is_fluorescent() || !(self.emission(lambda_o) > 0.0) {
            return 0.0;
        }
        // Only excitation below λo reaches it (no anti-Stokes term); the absorption
        // band's own grid, so that narrow bands are not missed.
        let hi = domain.1.min(lambda_o);
        p.concentration * p.quantum_yield * self.emission(lambda_o) * absorbed_power(self, illum, (domain.0, hi), 1.0)
    }
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        if !(wi[2] > 0.0 && wo[2] > 0.0) {
            return 0.0;
        }
        JungFluorescence::reradiation(self, lambda_i, lambda_o) * FRAC_1_PI * wo[2]
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

/// The complete material: the dye's interface with the elastic part r(λ)·(1 − c·a(λ)).
impl Bispectral for JungMaterial {
    fn excitation_range(&self) -> Option<(f64, f64)> {
        self.fluorescence.excitation_range()
    }
    fn emission_range(&self) -> Option<(f64, f64)> {
        self.fluorescence.emission_range()
    }
    fn elastic_albedo(&self, _cos_i: f64, lambda: f64) -> f64 {
        JungMaterial::elastic_albedo(self, lambda)
    }
    fn density(&self, cos_i: f64, lambda_i: f64, lambda_o: f64) -> f64 {
        self.fluorescence.density(cos_i, lambda_i, lambda_o)
    }
    fn density_factors(&self, cos_i: f64, lambdas: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
        self.fluorescence.density_factors(cos_i, lambdas)
    }
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
        self.fluorescence.reradiated(illum, domain, lambda_o)
    }
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        Bispectral::reradiation(&self.fluorescence, wi, wo, lambda_i, lambda_o)
    }
    fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64 {
        self.fluorescence.shift_albedo(wi, lambda_o, range)
    }
    fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        self.fluorescence.sample_excitation(wi, lambda_o, xi, range)
    }
    fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64 {
        self.fluorescence.excitation_pdf(wi, lambda_o, lambda_i, range)
    }
    fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        Bispectral::sample_emission(&self.fluorescence, wi, lambda_i, xi)
    }
    fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        Bispectral::emission_pdf(&self.fluorescence, wi, lambda_i, lambda_o)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_values_are_checked_one_by_one() {
        assert!(check_param_value("concentration", 0.0).is_ok() && check_param_value("concentration", 1.0).is_ok());
        assert!(check_param_value("quantum_yield", 0.5).is_ok());
        for (name, bad) in [
            ("concentration", 1.5),
            ("concentration", f64::NAN),
            ("quantum_yield", -0.1),
            ("emission_peak", 150.0),
            ("emission_peak", f64::INFINITY),
            ("stokes_shift", 0.0),
            ("stokes_shift", 5000.0),
        ] {
            let e = check_param_value(name, bad).unwrap_err().to_string();
            assert!(e.contains(name), "{e}");
        }
        assert!(check_param_value("radius", 1.0).is_err());
        // the loose per-value bound admits every shift some peak allows
        let s = max_stokes_shift(EMISSION_PEAK_RANGE_NM.1) * 0.999;
        assert!(check_param_value("stokes_shift", s).is_ok());
        assert!(JungFluorescence::new(JungParams { emission_peak: 1200.0, stokes_shift: s, ..JungParams::default() })
            .is_ok());
    }
    use crate::testutil::{chi2, chi2_critical, simpson, uniforms};

    const UP: [f64; 3] = [0.0, 0.0, 1.0];

    fn jung() -> JungFluorescence {
        crate::testutil::green_dye()
    }

    #[test]
    fn shift_albedo_is_the_integral_of_reradiation() {
        let m: &dyn Bispectral = &jung();
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
        let m: &dyn Bispectral = &jung();
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

    fn model(le: f64, s: f64) -> JungFluorescence {
        JungFluorescence::new(JungParams {
            emission_peak: le,
            stokes_shift: s,
            concentration: 0.7,
            quantum_yield: 0.96,
        })
        .unwrap()
    }

    #[test]
    fn bspline_integral_and_peak() {
        assert_eq!(bspline(0.0), 1.0);
        assert_eq!(bspline(3.0), 0.0);
        let i = simpson(bspline, -3.0, 3.0, 6000);
        assert!((i - 8.0 / 3.0).abs() < 1e-9, "{i}");
    }

    #[test]
    fn emission_integrates_to_one() {
        for (le, s) in [(520.0, 60.0), (400.0, 60.0), (650.0, 5.0), (450.0, 200.0), (300.0, 0.01)] {
            let m = model(le, s);
            let (lo, hi) = m.emission_support();
            let i = simpson(|l| m.emission(l), lo, hi, 60_000);
            assert!((i - 1.0).abs() < 1e-6, "λe={le} s={s}: ∫e = {i}");
        }
    }

    #[test]
    fn absorption_peaks_at_one_at_stokes_distance() {
        // Paper's Fig. 4 example: λe = 400 nm, s = 60 nm -> absorption peak at 340 nm.
        for (le, s) in [(400.0, 60.0), (520.0, 60.0), (600.0, 150.0), (700.0, 3.0)] {
            let m = model(le, s);
            let peak = le - s;
            assert!((m.absorption(peak) - 1.0).abs() < 1e-12, "a(peak) = {}", m.absorption(peak));
            assert!((m.absorption_peak() - peak).abs() < 1e-12);
            // and it is the maximum: a grid search finds nothing higher
            let (lo, hi) = m.absorption_support();
            let mut best = (0.0, 0.0);
            let n = 200_000;
            for i in 0..=n {
                let l = lo + (hi - lo) * i as f64 / n as f64;
                let a = m.absorption(l);
                if a > best.1 {
                    best = (l, a);
                }
            }
            assert!(best.1 <= 1.0 + 1e-12);
            assert!((best.0 - peak).abs() < 2.0 * (hi - lo) / n as f64 + 1e-9, "argmax {} vs {peak}", best.0);
            // touches, does not overlap, the emission band
            assert!((hi - m.emission_support().0).abs() < 1e-9);
        }
    }

    #[test]
    fn absorption_integral_matches_quadrature() {
        for (le, s) in [(520.0, 60.0), (400.0, 60.0), (300.0, 0.05), (800.0, 600.0), (450.0, 440.0), (500.0, 2.0)] {
            let m = model(le, s);
            let (lo, hi) = m.absorption_support();
            // split at the b-spline knots (in λ) for Simpson's accuracy
            let to_l = |v: f64| {
                let lp = 2.0 / m.k + m.alpha * v / 3.0;
                lp / (m.k * lp - 1.0)
            };
            let knots = [hi, to_l(2.0), to_l(4.0), lo];
            let mut q = 0.0;
            for w in knots.windows(2) {
                q += simpson(|l| m.absorption(l), w[1], w[0], 20_000);
            }
            let rel = (m.absorption_integral() - q).abs() / q;
            assert!(rel < 1e-7, "λe={le} s={s}: closed {} vs quadrature {q}", m.absorption_integral());
            // partial CDF at the peak, too
            let peak = m.absorption_peak();
            let q_peak = simpson(|l| m.absorption(l), lo, to_l(4.0), 20_000)
                + simpson(|l| m.absorption(l), to_l(4.0), peak, 20_000);
            assert!((m.absorption_cdf(peak) - q_peak).abs() / q_peak < 1e-7);
        }
    }

    #[test]
    fn moments_series_and_closed_form_agree() {
        for (v1, v2) in [(0.0, 2.0), (2.0, 4.0), (4.0, 6.0), (1.3, 5.9)] {
            let beta = SERIES_MAX_X / v2; // at the switch point
            let s = moments(v1, v2, beta * (1.0 - 1e-9));
            let c = moments(v1, v2, beta * (1.0 + 1e-9));
            for n in 0..3 {
                assert!((s[n] - c[n]).abs() <= 1e-8 * c[n].abs().max(1e-12), "n={n}: {} vs {}", s[n], c[n]);
            }
        }
    }

    #[test]
    fn irwin_hall_inverse_is_inverse() {
        let cdf = |t: f64| {
            if t <= 1.0 {
                t * t * t / 6.0
            } else if t <= 2.0 {
                (-2.0 * t * t * t + 9.0 * t * t - 9.0 * t + 3.0) / 6.0
            } else {
                1.0 - (3.0 - t).powi(3) / 6.0
            }
        };
        for i in 0..=1000 {
            let u = i as f64 / 1000.0;
            let t = irwin_hall3_inverse_cdf(u);
            assert!((0.0..=3.0).contains(&t));
            assert!((cdf(t) - u).abs() < 1e-12, "u={u} t={t} F={}", cdf(t));
        }
    }

    #[test]
    fn emission_sampling_matches_pdf_chi2() {
        let m = model(520.0, 60.0);
        let xs: Vec<f64> = uniforms(200_000, 1).into_iter().map(|u| m.sample_emission(u).0).collect();
        let (lo, hi) = m.emission_support();
        let (stat, dof) = chi2(&xs, lo, hi, 100, |l| m.emission_pdf(l));
        assert!(stat < chi2_critical(dof), "chi2 {stat} dof {dof}");
        for &x in &xs {
            assert!(x >= lo && x <= hi);
        }
    }

    #[test]
    fn absorption_sampling_matches_pdf_chi2() {
        for (le, s, range) in [
            (520.0, 60.0, (0.0_f64, f64::INFINITY)),
            (400.0, 120.0, (0.0, f64::INFINITY)),
            (450.0, 80.0, (360.0, 830.0)),  // truncated by the camera range
            (420.0, 100.0, (300.0, 330.0)), // a narrow UV lamp band
        ] {
            let m = model(le, s);
            let (slo, shi) = m.absorption_support();
            let (lo, hi) = (range.0.max(slo), range.1.min(shi));
            let xs: Vec<f64> = uniforms(100_000, 7)
                .into_iter()
                .map(|u| {
                    let (l, pdf) = m.sample_absorption(u, range.0, range.1).unwrap();
                    assert!((pdf - m.absorption_pdf(l, range.0, range.1)).abs() <= 1e-9 * pdf);
                    l
                })
                .collect();
            let (stat, dof) = chi2(&xs, lo, hi, 100, |l| m.absorption_pdf(l, range.0, range.1));
            assert!(stat < chi2_critical(dof), "λe={le} s={s} {range:?}: chi2 {stat} dof {dof}");
        }
    }

    #[test]
    fn inverse_cdf_start_is_close_and_the_root_exact() {
        // The baked start lies within 0.1 of the support width of the root in the end
        // intervals (measured: 5e-2 at s = 700 nm, 4e-3 otherwise) and 1e-3 inside them
        // (measured: 4e-4); the Newton polish then lands on the root of the exact CDF (a
        // 200-step bisection) to the inversion's rounding level, as the start at the
        // midpoint did (measured: 1.5e-9 of the width at s = 5 nm, 1e-11 otherwise).
        for (le, s) in [(520.0, 60.0), (400.0, 120.0), (450.0, 80.0), (600.0, 5.0), (800.0, 700.0)] {
            let m = model(le, s);
            let (slo, shi) = m.absorption_support();
            let w = shi - slo;
            let n = INVERSE_CDF_INTERVALS as f64;
            for u in uniforms(2_000, 9) {
                let target = u * m.absorption_integral();
                let guess = m.inverse_cdf_guess(target).unwrap();
                let (x, _) = m.sample_absorption(u, 0.0, f64::INFINITY).unwrap();
                let (mut a, mut b) = (slo, shi);
                for _ in 0..200 {
                    let mid = 0.5 * (a + b);
                    if m.absorption_cdf(mid) > target {
                        b = mid;
                    } else {
                        a = mid;
                    }
                }
                let root = 0.5 * (a + b);
                let inner = u * n >= 1.0 && u * n <= n - 1.0;
                assert!((guess - root).abs() <= if inner { 1e-3 } else { 0.1 } * w, "λe={le} s={s} u={u}");
                assert!((x - root).abs() <= 2e-9 * w, "λe={le} s={s} u={u}: {x} vs {root}");
            }
        }
    }

    #[test]
    fn absorption_sampling_outside_support_is_none() {
        let m = model(520.0, 60.0);
        assert!(m.sample_absorption(0.5, 600.0, 830.0).is_none());
        assert_eq!(m.absorption_pdf(700.0, 300.0, 830.0), 0.0);
    }

    #[test]
    fn validation_errors_name_parameter_and_range() {
        let bad = |p: JungParams| JungFluorescence::new(p).unwrap_err().to_string();
        let d = JungParams::default();
        let e = bad(JungParams { stokes_shift: 1100.0, ..d });
        assert!(e.contains("stokes_shift") && e.contains("1100") && e.contains("2·emission_peak"), "{e}");
        let e = bad(JungParams { stokes_shift: d.emission_peak * 2.0 - 1e-9, ..d });
        assert!(e.contains("stokes_shift"), "{e}");
        assert!(bad(JungParams { concentration: 1.5, ..d }).contains("concentration"));
        assert!(bad(JungParams { quantum_yield: -0.1, ..d }).contains("quantum_yield"));
        assert!(bad(JungParams { quantum_yield: f64::NAN, ..d }).contains("quantum_yield"));
        assert!(bad(JungParams { emission_peak: 50.0, ..d }).contains("emission_peak"));
        assert!(bad(JungParams { stokes_shift: 0.0, ..d }).contains("stokes_shift"));
    }

    #[test]
    fn energy_reradiated_never_exceeds_absorbed() {
        // ∫ P(λi, λo) dλo = c Q a(λi) ≤ c a(λi): with the elastic part, total ≤ r ≤ 1.
        let m = model(520.0, 60.0);
        for li in [400.0, 440.0, 455.0, 470.0] {
            let (lo, hi) = m.emission_support();
            let rerad = simpson(|lo_| m.reradiation(li, lo_), lo, hi, 20_000);
            let expected = 0.7 * 0.96 * m.absorption(li);
            assert!((rerad - expected).abs() < 1e-6);
            assert!(m.elastic_factor(li) + rerad <= 1.0 + 1e-9);
        }
    }
}

// ------------------------------------------------------------------ the dye medium

/// Valid range of `sigma_a`, 1/m.
pub const SIGMA_A_RANGE_PER_M: (f64, f64) = (0.0, 1e9);

/// User parameters of a dye medium (see [`DyeMedium`]'s table).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DyeMediumParams {
    /// Emission peak λe, nm.
    pub emission_peak_nm: f64,
    /// Stokes shift s, nm.
    pub stokes_shift_nm: f64,
    /// Quantum yield Q.
    pub quantum_yield: f64,
    /// Peak absorption coefficient σa, 1/m.
    pub sigma_a_per_m: f64,
}

impl Default for DyeMediumParams {
    fn default() -> Self {
        Self { emission_peak_nm: 520.0, stokes_shift_nm: 60.0, quantum_yield: 0.9, sigma_a_per_m: 100.0 }
    }
}

/// Cells of a dye medium's μa table in the vectorised variants ([`DyeMedium::absorption_nodes`]):
/// the b-spline's linear interpolation at support/4096 (≈ 0.01-0.05 nm) is within 1e-5 of
/// its peak (test `jit_tables_follow_the_media` in model.rs).
pub const DYE_JIT_CELLS: usize = 4096;

/// A fluorescent dye dissolved in a participating medium ([`DyeMedium`], `fluo_dye_medium`):
/// Jung et al.'s spectra (b-spline emission e(λ), its mirrored absorption a(λ), eqs. 3-6 of
/// Jung et al. 2019, as [`JungFluorescence`]) as volume coefficients.
///
/// ```text
/// μa(λ) = σa · a(λ)                         (1/m; a ∈ [0, 1], peak 1 at λe − s)
/// f(λi → λo) = Q · e(λo) · [λi < λo]        (re-emitted per nm of λo per unit absorbed)
/// μf(λo | R) = Q e(λo) σa ∫_{R.lo}^{min(R.hi, λo)} a(λi) dλi
/// ```
///
/// ∫ e = 1, and absorption and emission supports never overlap (the mirror construction),
/// so every absorbed photon re-emits with probability exactly Q. Excitation sampling is
/// the exact inverse CDF of a(λ) over the interval ([`JungFluorescence::sample_absorption`]),
/// so p = μa f / μf and a shift weighs μf (the bispectral medium contract).
///
/// | name            | unit | valid range                    | default |
/// |-----------------|------|--------------------------------|---------|
/// | `emission_peak` | nm   | [200, 1200]                    | 520     |
/// | `stokes_shift`  | nm   | (0, max_stokes_shift(λe)]      | 60      |
/// | `quantum_yield` | 1    | [0, 1]                         | 0.9     |
/// | `sigma_a`       | 1/m  | [0, 1e9] (peak absorption)     | 100     |
///
/// A validated dye medium (`fluo_dye_medium`).
#[derive(Debug, Clone)]
pub struct DyeMedium {
    params: DyeMediumParams,
    dye: JungFluorescence,
}

impl DyeMedium {
    /// Validate (errors name the parameter, its value and the valid range).
    pub fn new(params: DyeMediumParams) -> Result<Self> {
        check_range("sigma_a", params.sigma_a_per_m, SIGMA_A_RANGE_PER_M.0, SIGMA_A_RANGE_PER_M.1)?;
        let dye = JungFluorescence::new(JungParams {
            emission_peak: params.emission_peak_nm,
            stokes_shift: params.stokes_shift_nm,
            concentration: 1.0,
            quantum_yield: params.quantum_yield,
        })?;
        Ok(Self { params, dye })
    }

    /// Whether anything is ever re-emitted.
    pub fn is_fluorescent(&self) -> bool {
        self.params.quantum_yield > 0.0 && self.params.sigma_a_per_m > 0.0
    }

    /// [absorption support's start, emission support's end], nm.
    pub fn lambda_range(&self) -> (f64, f64) {
        (self.dye.absorption_support().0, self.dye.emission_support().1)
    }

    /// μa(λ), 1/m.
    pub fn absorption_per_m(&self, lambda_nm: f64) -> f64 {
        self.params.sigma_a_per_m * self.dye.absorption(lambda_nm)
    }

    /// Q e(λo), per nm per unit absorbed.
    pub fn emission_per_nm(&self, lambda_o_nm: f64) -> f64 {
        self.params.quantum_yield * self.dye.emission(lambda_o_nm)
    }

    /// f(λi → λo), per nm of λo per unit absorbed at λi.
    pub fn reradiation_per_nm(&self, lambda_i_nm: f64, lambda_o_nm: f64) -> f64 {
        if lambda_i_nm < lambda_o_nm {
            self.emission_per_nm(lambda_o_nm)
        } else {
            0.0
        }
    }

    /// The emission peak λe, nm.
    pub fn emission_peak_nm(&self) -> f64 {
        self.params.emission_peak_nm
    }

    /// Nodes for a piecewise-linear table of μa (the vectorised variants'):
    /// [`DYE_JIT_CELLS`] equal cells over the absorption support (zero outside it).
    pub fn absorption_nodes(&self) -> Vec<f64> {
        let (lo, hi) = self.dye.absorption_support();
        (0..=DYE_JIT_CELLS).map(|i| lo + (hi - lo) * i as f64 / DYE_JIT_CELLS as f64).collect()
    }

    /// μf(λo | R), 1/m.
    pub fn shift_coefficient_per_m(&self, lambda_o_nm: f64, range: (f64, f64)) -> f64 {
        let e = self.emission_per_nm(lambda_o_nm);
        if !(e > 0.0) {
            return 0.0;
        }
        let hi = range.1.min(lambda_o_nm);
        e * self.params.sigma_a_per_m * self.dye.absorption_integral_range(range.0, hi)
    }

    /// λi ∝ a(λi) over [R.lo, min(R.hi, λo)]: (λi, pdf per nm), or None.
    pub fn sample_excitation(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> Option<(f64, f64)> {
        if !(self.emission_per_nm(lambda_o_nm) > 0.0) {
            return None;
        }
        self.dye.sample_absorption(xi, range.0, range.1.min(lambda_o_nm))
    }

    /// μf(λo | R) and [`DyeMedium::sample_excitation`] with `xi`.
    pub fn shift_and_sample(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> (f64, Option<(f64, f64)>) {
        (self.shift_coefficient_per_m(lambda_o_nm, range), self.sample_excitation(lambda_o_nm, range, xi))
    }
}

impl fmt::Display for DyeMedium {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let p = &self.params;
        write!(
            f,
            "DyeMedium[emission_peak = {} nm, stokes_shift = {} nm, quantum_yield = {}, sigma_a = {} 1/m]",
            p.emission_peak_nm, p.stokes_shift_nm, p.quantum_yield, p.sigma_a_per_m
        )
    }
}

#[cfg(test)]
mod dye_medium_tests {
    use super::*;

    #[test]
    fn dye_medium_keeps_the_contract() {
        let m = DyeMedium::new(DyeMediumParams::default()).unwrap();
        let range = (300.0, 830.0);
        for lo in [480.0, 520.0, 560.0] {
            let mu_f = m.shift_coefficient_per_m(lo, range);
            // μf by midpoint quadrature of μa f.
            let n = 200_000;
            let h = (lo - 300.0) / n as f64;
            let q: f64 = (0..n)
                .map(|i| {
                    let l = 300.0 + (i as f64 + 0.5) * h;
                    m.absorption_per_m(l) * m.reradiation_per_nm(l, lo) * h
                })
                .sum();
            assert!((mu_f - q).abs() <= 1e-6 * q.max(1e-12), "{lo}: {mu_f} vs {q}");
            if mu_f > 0.0 {
                let (l, pdf) = m.sample_excitation(lo, range, 0.37).unwrap();
                let want = m.absorption_per_m(l) * m.reradiation_per_nm(l, lo) / mu_f;
                assert!((pdf - want).abs() <= 1e-9 * want, "{pdf} vs {want}");
            }
        }
        assert!(DyeMedium::new(DyeMediumParams { sigma_a_per_m: -1.0, ..Default::default() })
            .unwrap_err()
            .to_string()
            .contains("sigma_a"));
        assert!(DyeMedium::new(DyeMediumParams { quantum_yield: 2.0, ..Default::default() })
            .unwrap_err()
            .to_string()
            .contains("quantum_yield"));
    }
}
