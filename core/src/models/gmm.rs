//! Gaussian-mixture compression of reradiation matrices (Hua et al. 2022), behind
//! `fluo_gmm` and `fluo fit-gmm`.
//!
//! # Model
//! The reradiation of a filtered matrix ([`crate::models::matrix`]) is represented by a 2-D
//! Gaussian mixture in x = (λi, λo) (eqs. 1–2), scaled by S (eq. 3):
//!
//! ```text
//! p(λi, λo) = Σ_k π_k N(x | μ_k, Σ_k)                                   (eqs. 1, 2)
//! P(λi, λo) = S · p(λi, λo)   on Λ = [λi_min, λi_max] × [λo_min, λo_max], λi ≤ λo; else 0
//! f(λi, ωi, ωo, λo) = [ δ(λi − λo) ρ(λi) + P(λi, λo) ] / π             (diffuse)
//! ```
//!
//! The diagonal ρ is stored as measured (interpolated as in [`crate::models::matrix`]); Λ is the
//! measured rectangle. The file keeps the diagonal, S and 7 numbers per component
//! (π, μ, the 2×2 Σ): 1 + 7K numbers for the fluorescence (sec. 7.6).
//!
//! # Fitting (sec. 5)
//! Weighted EM \[GAPFH16\] on the matrix entries above the diagonal: every node
//! (λi_k, λo_j) with P > 0 is an observation of weight P(λi_k, λo_j). Responsibilities
//! are computed with log-sum-exp; every covariance gets `diag(hi²/6, ho²/6)` added in
//! the M-step: the variance of the tent (linear-interpolation) kernel that the
//! continuous matrix model puts around each node (hi, ho: grid steps), so the mixture
//! fits the interpolated matrix, and no component can collapse onto one node.
//! Initialisation is a weighted k-means++ from a fixed SplitMix64 seed, with several
//! restarts (best final likelihood wins); iterations are bounded. A dead component is
//! re-seeded at the worst-explained observation. Variational Bayes is not implemented.
//!
//! Scaling S (sec. 5.3): the integral ratio (eq. 5, the default, as in the paper)
//! S = ∬_Λ P_matrix / ∬_Λ p, both over λi ≤ λo, so the reradiated albedo is kept; or
//! error minimisation (eq. 4) with the L2 norm over the grid nodes,
//! S = Σ P_matrix·p / Σ p² (closed form). Both are stored; `scaling` names the one used.
//!
//! # Conditional sampling (sec. 6.1, with the slips corrected)
//! Write Σ_k = [[σaa, σab], [σab, σbb]] (a = λi, b = λo). For a given λi, component k
//! factors as N(λi | μa, σaa) · N(λo | μ_{b|a}, v_{b|a}) with
//!
//! ```text
//! μ_{b|a} = μb + σab/σaa · (λi − μa)  (= eq. 9),   v_{b|a} = σbb − σab²/σaa = 1/τbb
//! ```
//!
//! `v_{b|a}` is a variance (eq. 12 calls it σ); the mixing weights use the marginal of
//! λi, N(λi | μa, σaa) (eq. 11 writes λo where λi is meant). The distribution actually
//! rendered is P restricted to T = [max(λi, λo_min), λo_max], so the exact conditional
//! is the mixture of *truncated* normals with weights
//!
//! ```text
//! w_k ∝ π_k N(λi | μa, σaa) · M_k,   M_k = ∫_T N(λo | μ_{b|a}, v_{b|a}) dλo
//! pdf(λo | λi) = Σ_k π_k N(λi | μa, σaa) N(λo | μ_{b|a}, v_{b|a}) / Σ_k π_k N(λi | μa, σaa) M_k
//!              = P(λi, λo) / ∫_T P(λi, λo') dλo'
//! ```
//!
//! Sampling picks k by w_k (Algorithm 1's loop with the comparison the right way round:
//! stop at the first k with ξ < Σ_{≤k} w), reuses the rescaled uniform, and inverts the
//! truncated normal's CDF on T exactly — no rejection loop. λi | λo is the same with a
//! and b exchanged, on [max(lo, λi_min), min(hi, λo, λi_max)].
//!
//! # Numerical notes
//! Weights and masses are scaled in logarithms: when λi is near the top of the range
//! and almost no mass of any component lies above it (M_k ≈ 1e-40 or far smaller), the
//! conditional is still normalised exactly. Each π_k N M_k is e^{l_k} f_k with l_k the
//! log of the nearer tail and f_k ∈ [0, 1] (by expm1), so the weights cost one exp each
//! and no log. The truncated-normal CDF uses log Q(z) (Q the upper tail), computed from
//! erfc by its series below [`ERF_SERIES_MAX`] and from the continued fraction of the
//! scaled erfcx above (relative accuracy ~1e-11 at all z), tabulated on the hot path; its
//! inversion (central intervals too, in the smaller tail) is a safeguarded Newton
//! iteration from Acklam's quantile approximation, bounded by [`MAX_NEWTON_ITERATIONS`].
//! A conditional lives in fixed-size arrays ([`MAX_COMPONENTS`]): nothing is allocated
//! at render time. A conditional mass whose value underflows is reported as
//! [`f64::MIN_POSITIVE`] where the interval is not empty, so that it is positive exactly
//! where the integral is (what a path tracer choosing the shifted event needs).
//!
//! # References
//! Q. Hua, V. Tázlar, A. Fichet, A. Wilkie, "Efficient Storage and Importance Sampling
//! for Fluorescent Reflectance", CGF 2022. \[GAPFH16\] I. D. Gebru et al., "EM algorithms
//! for weighted-data clustering", IEEE TPAMI 38(12), 2016.

use std::fmt;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::models::matrix::{
    interp_indexed, Filtered, MatrixModel, MAX_MATRIX_VALUE, MAX_WAVELENGTH_NM, WAVELENGTH_TOLERANCE_NM,
};
use crate::spectrum::GridIndex;
use crate::{Error, Result};

/// Below this |x| erf uses its Taylor series; above, erfcx its continued fraction.
pub const ERF_SERIES_MAX: f64 = 2.5;
/// Bound on the erfcx continued fraction's terms (it converges in ~40 at [`ERF_SERIES_MAX`]).
const ERFCX_CF_DEPTH: usize = 200;
/// The continued fraction stops when a term changes it by less than this (relative).
const CF_TOLERANCE: f64 = 1e-16;
/// Hard bound on erf series terms.
const ERF_SERIES_MAX_TERMS: usize = 200;
/// Iteration bound of the safeguarded Newton inversions of the truncated normal.
pub const MAX_NEWTON_ITERATIONS: usize = 100;
/// Relative stopping tolerance of those inversions.
const NEWTON_TOLERANCE: f64 = 1e-13;
/// Default bound on EM iterations.
pub const DEFAULT_MAX_ITERATIONS: usize = 500;
/// EM stops when the weighted mean log-likelihood improves by less than this.
pub const DEFAULT_TOLERANCE: f64 = 1e-9;
/// Default number of k-means++ restarts.
pub const DEFAULT_RESTARTS: usize = 4;
/// A component whose responsibility mass falls below this is re-seeded.
const DEAD_COMPONENT_MASS: f64 = 1e-10;
/// Largest accepted component count.
pub const MAX_COMPONENTS: usize = 64;
/// λi step of the quadrature of ∬ p in the integral-ratio scaling, nm.
const SCALE_QUADRATURE_STEP_NM: f64 = 0.5;
/// Tolerance on Σπ = 1 and on the symmetry of Σ when reading a fit file.
const FILE_TOLERANCE: f64 = 1e-6;
/// Half-width of the tabulated range of [`log_q`].
pub const LOG_Q_TABLE_MAX: f64 = 10.0;
/// Step of that table (cubic Hermite error ∝ step⁴).
const LOG_Q_TABLE_STEP: f64 = 1.0 / 64.0;
/// Normal tails below e^−this (relative) are dropped from interval masses (< f64 ε).
const TAIL_NEGLIGIBLE: f64 = 40.0;
/// Components whose conditional weight is below e^−this of the largest are skipped.
const LN_NEGLIGIBLE: f64 = 45.0;
/// Smallest conditional mass reported where the exact one is positive (where the
/// interval is not empty): a path tracer needs shift_albedo > 0 exactly there.
const MIN_POSITIVE_MASS: f64 = f64::MIN_POSITIVE;
/// `format` field of a fit file.
pub const FORMAT: &str = "fluo-gmm";

/// Largest accepted magnitude of a covariance entry, nm² (a standard deviation of
/// 10 000 nm): larger ones overflow the determinant.
pub const MAX_COVARIANCE_NM2: f64 = 1e8;

const LN_SQRT_2PI: f64 = 0.918_938_533_204_672_8;
const FRAC_2_SQRT_PI: f64 = std::f64::consts::FRAC_2_SQRT_PI;

// ------------------------------------------------------------------ special functions

/// erf(x) by its Taylor series (|x| ≤ [`ERF_SERIES_MAX`]).
fn erf_series(x: f64) -> f64 {
    let x2 = x * x;
    let (mut term, mut sum) = (x, x);
    for n in 0..ERF_SERIES_MAX_TERMS {
        term *= -x2 / (n as f64 + 1.0);
        let add = term / (2.0 * n as f64 + 3.0);
        sum += add;
        if add.abs() <= 1e-17 * sum.abs() {
            break;
        }
    }
    FRAC_2_SQRT_PI * sum
}

/// erfcx(x) = exp(x²) erfc(x) for x ≥ [`ERF_SERIES_MAX`], by the Laplace continued
/// fraction erfc(x) = e^{−x²}/√π · 1/(x + (1/2)/(x + 1/(x + (3/2)/(x + …)))), evaluated
/// forwards (modified Lentz) until it converges (≈ 40 terms at x = 2.5, 10 at x = 10),
/// bounded by [`ERFCX_CF_DEPTH`].
fn erfcx_cf(x: f64) -> f64 {
    let (mut f, mut c, mut d) = (x, x, 0.0);
    for n in 1..=ERFCX_CF_DEPTH {
        let a = n as f64 * 0.5;
        d = 1.0 / (x + a * d);
        c = x + a / c;
        let delta = c * d;
        f *= delta;
        if (delta - 1.0).abs() <= CF_TOLERANCE {
            break;
        }
    }
    1.0 / (std::f64::consts::PI.sqrt() * f)
}

/// erfc(x).
pub fn erfc(x: f64) -> f64 {
    if x.is_nan() {
        return f64::NAN;
    }
    if x < -ERF_SERIES_MAX {
        2.0 - erfc(-x)
    } else if x <= ERF_SERIES_MAX {
        1.0 - erf_series(x)
    } else {
        (-x * x).exp() * erfcx_cf(x)
    }
}

/// ln Q(z), Q(z) = P(Z > z) the standard normal upper tail; finite for every finite z.
///
/// On |z| < [`LOG_Q_TABLE_MAX`] (the hot path of sampling) it is read from a table of
/// ln Q and its derivative −φ/Q with cubic Hermite interpolation (absolute error in
/// ln Q below 1e-10, the accuracy of erfc itself; a test checks it); elsewhere directly
/// ([`log_q_direct`]). CDF inversion and pdf use this same function.
pub fn log_q(z: f64) -> f64 {
    if !(z.abs() < LOG_Q_TABLE_MAX) {
        return log_q_direct(z);
    }
    let t = log_q_table();
    let u = (z + LOG_Q_TABLE_MAX) / LOG_Q_TABLE_STEP; // > 0: truncation is floor
    let i = (u as usize).min(t.len() - 2);
    let s = u - i as f64;
    let (y0, d0) = t[i];
    let (y1, d1) = t[i + 1];
    let h = LOG_Q_TABLE_STEP;
    let (s2, s3) = (s * s, s * s * s);
    (2.0 * s3 - 3.0 * s2 + 1.0) * y0 + (s3 - 2.0 * s2 + s) * h * d0 + (-2.0 * s3 + 3.0 * s2) * y1 + (s3 - s2) * h * d1
}

/// (ln Q, d ln Q/dz) at z = −[`LOG_Q_TABLE_MAX`] + i·[`LOG_Q_TABLE_STEP`], built once.
fn log_q_table() -> &'static [(f64, f64)] {
    static TABLE: std::sync::OnceLock<Vec<(f64, f64)>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let n = (2.0 * LOG_Q_TABLE_MAX / LOG_Q_TABLE_STEP).round() as usize;
        (0..=n)
            .map(|i| {
                let z = -LOG_Q_TABLE_MAX + i as f64 * LOG_Q_TABLE_STEP;
                let lq = log_q_direct(z);
                (lq, -(log_phi(z) - lq).exp())
            })
            .collect()
    })
}

/// ln Q(z) from erfc / erfcx (see [`log_q`]).
pub fn log_q_direct(z: f64) -> f64 {
    let x = z * std::f64::consts::FRAC_1_SQRT_2;
    if x < 0.0 {
        (-0.5 * erfc(-x)).ln_1p()
    } else if x <= ERF_SERIES_MAX {
        (0.5 * erfc(x)).ln()
    } else {
        -x * x + (0.5 * erfcx_cf(x)).ln()
    }
}

/// ln φ(z).
fn log_phi(z: f64) -> f64 {
    -0.5 * z * z - LN_SQRT_2PI
}

/// ln ∫_a^b φ (a < b); −∞ when empty.
pub fn log_std_mass(a: f64, b: f64) -> f64 {
    if !(b > a) {
        return f64::NEG_INFINITY;
    }
    let (ln_tail, fraction) = std_mass_parts(a, b);
    ln_tail + fraction.ln()
}

/// ∫_a^b φ = e^l · f for a < b, as (l, f) with f ∈ [0, 1]: l = ln Q(a) and
/// f = 1 − Q(b)/Q(a) (by expm1, accurate for short intervals) when 0 ≤ a, mirrored when
/// b ≤ 0, and l = 0, f = 1 − Q(b) − Q(−a) for a central interval. Kept apart so that a
/// mixture can weight its components with one exp each and without a log.
fn std_mass_parts(a: f64, b: f64) -> (f64, f64) {
    // Tails beyond e^−TAIL_NEGLIGIBLE are below f64 resolution and need no erfc:
    // Q(b)/Q(a) ≤ e^{−(b²−a²)/2} for 0 ≤ a < b (erfcx decreases), Q(z) ≤ e^{−z²/2}/2.
    let far = |e: f64| e > TAIL_NEGLIGIBLE;
    if a >= 0.0 {
        let la = log_q(a);
        if far(0.5 * (b - a) * (b + a)) {
            return (la, 1.0);
        }
        (la, -(log_q(b) - la).exp_m1())
    } else if b <= 0.0 {
        std_mass_parts(-b, -a)
    } else {
        // 1 − Q(b) − Q(−a), both tails < 1/2.
        let tail = |z: f64| if far(0.5 * z * z) { 0.0 } else { log_q(z).exp() };
        (0.0, 1.0 - (tail(b) + tail(-a)))
    }
}

/// Inverse-CDF sample of the standard normal truncated to [a, b] (a < b), u ∈ [0, 1].
pub fn sample_std_truncated(a: f64, b: f64, u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    if a >= 0.0 {
        sample_upper_tail(a, b, u)
    } else if b <= 0.0 {
        -sample_upper_tail(-b, -a, 1.0 - u)
    } else {
        // Central interval: Φ(x) = Φ(a) + u m with m = 1 − Q(−a) − Q(b) (both tails < 1/2,
        // no cancellation). Solved in the smaller tail: Q(−x) = Φ(x) when x ≤ 0, else
        // Q(x) = Q(b) + (1 − u) m, with the same ln Q as the tails and the masses.
        let (qa, qb) = (log_q(-a).exp(), log_q(b).exp());
        let m = 1.0 - qa - qb;
        let (below, above) = (qa + u * m, qb + (1.0 - u) * m);
        if below <= above {
            -solve_log_q(0.0, -a, below.ln())
        } else {
            solve_log_q(0.0, b, above.ln())
        }
    }
}

/// Sample on [a, b] ⊂ [0, ∞) by solving ln Q(x) = ln[Q(a) − u (Q(a) − Q(b))] in logs.
fn sample_upper_tail(a: f64, b: f64, u: f64) -> f64 {
    let (la, lb) = (log_q(a), log_q(b));
    // Q(b)/Q(a) − 1 = expm1(lb − la) ∈ (−1, 0]
    solve_log_q(a, b, la + (u * (lb - la).exp_m1()).ln_1p())
}

/// The x in [a, b] ⊂ [0, ∞) with ln Q(x) = `target` (clamped to [a, b] when outside).
fn solve_log_q(a: f64, b: f64, target: f64) -> f64 {
    // g(x) = target − ln Q(x), increasing; g' = φ(x)/Q(x).
    newton_bracketed(a, b, upper_quantile_guess(target), |x| {
        let lq = log_q(x);
        (target - lq, (log_phi(x) - lq).exp())
    })
}

/// x with Q(x) ≈ e^`ln_p`, by P. J. Acklam's rational approximation of the normal
/// quantile (relative error below 1.2e-9): the start of Newton's iteration, which then
/// needs about two steps.
fn upper_quantile_guess(ln_p: f64) -> f64 {
    const A: [f64; 6] = [
        -39.696_830_286_653_76,
        220.946_098_424_520_5,
        -275.928_510_446_968_7,
        138.357_751_867_269,
        -30.664_798_066_147_16,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -54.476_098_798_224_06,
        161.585_836_858_040_9,
        -155.698_979_859_886_6,
        66.801_311_887_719_72,
        -13.280_681_552_885_72,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -0.322_396_458_041_136_5,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] =
        [7.784_695_709_041_462e-3, 0.322_467_129_070_039_8, 2.445_134_137_142_996, 3.754_408_661_907_416];
    /// Below this p the tail form is used.
    const P_LOW: f64 = 0.024_25;
    let poly = |c: &[f64], x: f64| c.iter().fold(0.0, |acc, &k| acc * x + k);
    if ln_p < P_LOW.ln() {
        let q = (-2.0 * ln_p).sqrt();
        -poly(&C, q) / (poly(&D, q) * q + 1.0)
    } else {
        let q = ln_p.exp() - 0.5;
        let r = q * q;
        -poly(&A, r) * q / (poly(&B, r) * r + 1.0)
    }
}

/// Safeguarded Newton for an increasing f on [a, b] with f(a) ≤ 0 ≤ f(b), from `start`
/// (the midpoint when it is not in [a, b]); `fd` returns (f(x), f'(x)). Bounded by
/// [`MAX_NEWTON_ITERATIONS`]; falls back to bisection.
fn newton_bracketed(a: f64, b: f64, start: f64, fd: impl Fn(f64) -> (f64, f64)) -> f64 {
    let (mut lo, mut hi) = (a, b);
    let mut x = if start >= a && start <= b { start } else { 0.5 * (a + b) };
    for _ in 0..MAX_NEWTON_ITERATIONS {
        let (f, d) = fd(x);
        if f > 0.0 {
            hi = x;
        } else {
            lo = x;
        }
        let newton = if d > 0.0 && d.is_finite() { x - f / d } else { f64::NAN };
        let next = if newton > lo && newton < hi { newton } else { 0.5 * (lo + hi) };
        let tol = NEWTON_TOLERANCE * (1.0 + x.abs());
        if (next - x).abs() <= tol || hi - lo <= tol {
            return next.clamp(a, b);
        }
        x = next;
    }
    x.clamp(a, b)
}

/// ln Σ exp(v).
fn log_sum_exp(v: impl Iterator<Item = f64> + Clone) -> f64 {
    let m = v.clone().fold(f64::NEG_INFINITY, f64::max);
    if m == f64::NEG_INFINITY {
        return m;
    }
    m + v.map(|x| (x - m).exp()).sum::<f64>().ln()
}

// ------------------------------------------------------------------ file format

/// One mixture component: the 7 numbers of sec. 7.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Component {
    /// Mixing weight π_k.
    pub weight: f64,
    /// Mean (λi, λo), nm.
    pub mean: [f64; 2],
    /// Covariance [[σaa, σab], [σba, σbb]], nm² (a = λi, b = λo).
    pub covariance: [[f64; 2]; 2],
}

/// The stored diagonal (reflectance).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Diagonal {
    /// Wavelengths, nm.
    pub wavelengths_nm: Vec<f64>,
    /// ρ at those wavelengths.
    pub values: Vec<f64>,
}

/// How S was chosen (eqs. 4–5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scaling {
    /// Eq. 5: ∬ P_matrix / ∬ p (keeps the albedo; the paper's choice).
    IntegralRatio,
    /// Eq. 4 with the L2 norm over the grid nodes.
    ErrorMinimisation,
}

impl Scaling {
    /// Parse `integral_ratio` / `error_minimisation`.
    pub fn from_name(name: &str) -> Result<Self> {
        match name {
            "integral_ratio" | "integral" => Ok(Scaling::IntegralRatio),
            "error_minimisation" | "error" => Ok(Scaling::ErrorMinimisation),
            other => Err(Error::param("scaling", format!("\"{other}\""), "integral_ratio or error_minimisation")),
        }
    }
}

/// How the fit went (informative; not needed to render).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitInfo {
    /// `"weighted_em"`.
    pub method: String,
    /// EM iterations of the retained restart.
    pub iterations: usize,
    /// Whether it met the tolerance before the iteration bound.
    pub converged: bool,
    /// Weighted mean log-likelihood of the node data (weights sum to 1).
    pub log_likelihood: f64,
    /// Seed of the k-means++ initialisation.
    pub seed: u64,
    /// Restarts tried.
    pub restarts: usize,
    /// Covariance regularisation added to (σaa, σbb), nm².
    pub regularisation_nm2: [f64; 2],
}

/// A fit file (`*.gmm.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GmmFile {
    /// Always [`FORMAT`].
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// The matrix it was fitted to.
    pub source: String,
    /// Measured excitation range [λi_min, λi_max], nm.
    pub lambda_i_range_nm: [f64; 2],
    /// Measured emission range [λo_min, λo_max], nm.
    pub lambda_o_range_nm: [f64; 2],
    /// The diagonal, as measured (after filtering).
    pub diagonal: Diagonal,
    /// The scaling used for S.
    pub scaling: Scaling,
    /// S (eq. 3), nm.
    pub scale: f64,
    /// S by the integral ratio (eq. 5).
    pub scale_integral_ratio: f64,
    /// S by error minimisation (eq. 4, L2).
    pub scale_error_minimisation: f64,
    /// The mixture.
    pub components: Vec<Component>,
    /// Fitting details.
    pub fit: FitInfo,
}

impl GmmFile {
    /// Numbers stored: diagonal (wavelengths and values), S, and 7 per component.
    pub fn floats_stored(&self) -> usize {
        2 * self.diagonal.values.len() + 1 + 7 * self.components.len()
    }

    /// Write as pretty JSON.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let p = path.as_ref();
        let text = serde_json::to_string_pretty(self).map_err(|e| Error::data(e.to_string()))?;
        std::fs::write(p, text + "\n").map_err(|e| Error::Io(format!("{}: {e}", p.display())))
    }

    /// Read and parse (validated when baked by [`GmmModel::new`]).
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let p = path.as_ref();
        let text = crate::fileio::read_text(p, crate::fileio::MAX_SMALL_FILE_BYTES, "Gaussian-mixture fit")?;
        serde_json::from_str(&text).map_err(|e| Error::data(format!("{}: fit file: {e}", p.display())))
    }
}

// ------------------------------------------------------------------ the model

/// A component with its derived ("baked") conditional parameters. Pairs are indexed by
/// the given axis g (0: λi given, 1: λo given); f is the other one.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Baked {
    ln_w: f64,
    mu: [f64; 2],
    /// ln π − ½ ln σgg − ln √(2π): ln π N(x | μg, σgg) = this − ½ (x − μg)²/σgg.
    ln_marginal: [f64; 2],
    /// 1/σgg.
    inv_var: [f64; 2],
    /// σab/σgg: the conditional mean is μf + slope (x − μg) (eq. 9).
    slope: [f64; 2],
    /// √v_{f|g}, the conditional's standard deviation.
    cond_sd: [f64; 2],
    /// 1/√v_{f|g}.
    inv_cond_sd: [f64; 2],
    /// −ln √v_{f|g} − ln √(2π), the conditional's log normaliser.
    ln_cond_norm: [f64; 2],
    /// ln of the 2-D normaliser: −ln(2π √det).
    ln_norm2: f64,
    /// Σ⁻¹ entries (τaa, τab, τbb).
    inv: [f64; 3],
}

/// The conditional mixture at one value x of the given wavelength, on an interval
/// [a, b] of the other, in fixed-size arrays (no allocation): per component k its
/// ln π_k N(x | μg, σgg), conditional mean, and weight w_k = π_k N(x | μg, σgg) M_k
/// relative to a common scale near the largest (so that they do not underflow together).
struct Slice {
    n: usize,
    ln_marginal: [f64; MAX_COMPONENTS],
    mean: [f64; MAX_COMPONENTS],
    w: [f64; MAX_COMPONENTS],
    /// Σ_k w_k.
    sum: f64,
    /// ln Σ_k π_k N(x | μg, σgg) M_k; −∞ when no mass is left.
    ln_total: f64,
}

/// The baked `fluo_gmm` model (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct GmmModel {
    file: GmmFile,
    comps: Vec<Baked>,
    range: [[f64; 2]; 2],
    /// Cell lookup on the diagonal's wavelengths (direct where uniform).
    diagonal_index: GridIndex,
}

/// Conditioning axis: 0 = given λi (sample λo), 1 = given λo (sample λi).
#[derive(Clone, Copy)]
enum Given {
    LambdaI = 0,
    LambdaO = 1,
}

impl GmmModel {
    /// Validate a fit file and bake the conditionals.
    pub fn new(file: GmmFile) -> Result<Self> {
        if file.format != FORMAT {
            return Err(Error::param("format", format!("\"{}\"", file.format), format!("\"{FORMAT}\"")));
        }
        if file.version != 1 {
            return Err(Error::param("version", file.version, "1"));
        }
        for (name, r) in [("lambda_i_range_nm", file.lambda_i_range_nm), ("lambda_o_range_nm", file.lambda_o_range_nm)]
        {
            if !(r[0].is_finite() && r[1].is_finite() && r[0] > 0.0 && r[1] > r[0] && r[1] <= MAX_WAVELENGTH_NM) {
                return Err(Error::param(
                    name,
                    format!("[{}, {}]", crate::num(r[0]), crate::num(r[1])),
                    format!("[lo, hi] with 0 < lo < hi ≤ {MAX_WAVELENGTH_NM} nm"),
                ));
            }
        }
        let d = &file.diagonal;
        if d.wavelengths_nm.len() < 2 || d.values.len() != d.wavelengths_nm.len() {
            return Err(Error::param(
                "diagonal",
                format!("{} wavelengths, {} values", d.wavelengths_nm.len(), d.values.len()),
                "at least 2 wavelengths and as many values",
            ));
        }
        if d.wavelengths_nm.windows(2).any(|w| !(w[1] > w[0]))
            || d.wavelengths_nm.iter().any(|x| !(x.is_finite() && *x <= MAX_WAVELENGTH_NM))
        {
            return Err(Error::param(
                "diagonal.wavelengths_nm",
                "(not increasing)",
                "strictly increasing finite wavelengths",
            ));
        }
        if let Some(v) = d.values.iter().find(|v| !(**v >= 0.0 && **v <= MAX_MATRIX_VALUE)) {
            return Err(Error::param("diagonal.values", v, format!("[0, {MAX_MATRIX_VALUE}]")));
        }
        if !(file.scale.is_finite() && file.scale >= 0.0) {
            return Err(Error::param("scale", file.scale, "[0, ∞)"));
        }
        if file.components.is_empty() || file.components.len() > MAX_COMPONENTS {
            return Err(Error::param("components", file.components.len(), format!("[1, {MAX_COMPONENTS}] components")));
        }
        let total: f64 = file.components.iter().map(|c| c.weight).sum();
        if !((total - 1.0).abs() <= FILE_TOLERANCE) {
            return Err(Error::param("components[].weight", format!("sum {total}"), "weights ≥ 0 summing to 1"));
        }
        let mut comps = Vec::with_capacity(file.components.len());
        for (i, c) in file.components.iter().enumerate() {
            let name = |f: &str| format!("components[{i}].{f}");
            if !(c.weight.is_finite() && c.weight >= 0.0) {
                return Err(Error::param(&name("weight"), c.weight, "[0, 1]"));
            }
            if !c.mean.iter().all(|m| m.abs() <= MAX_WAVELENGTH_NM) {
                return Err(Error::param(
                    &name("mean"),
                    format!("[{}, {}]", crate::num(c.mean[0]), crate::num(c.mean[1])),
                    format!("finite wavelengths in [-{MAX_WAVELENGTH_NM}, {MAX_WAVELENGTH_NM}] nm"),
                ));
            }
            let [[aa, ab], [ba, bb]] = c.covariance;
            if !c.covariance.iter().flatten().all(|v| v.abs() <= MAX_COVARIANCE_NM2) {
                return Err(Error::param(
                    &name("covariance"),
                    format!("{:?}", c.covariance.map(|r| r.map(crate::num))),
                    format!("entries in [-{MAX_COVARIANCE_NM2}, {MAX_COVARIANCE_NM2}] nm²"),
                ));
            }
            let det = aa * bb - ab * ba;
            let sym = (ab - ba).abs() <= FILE_TOLERANCE * (aa.abs() + bb.abs());
            if !(aa.is_finite() && bb.is_finite() && ab.is_finite() && sym && aa > 0.0 && bb > 0.0 && det > 0.0) {
                return Err(Error::param(
                    &name("covariance"),
                    format!("{:?}", c.covariance),
                    "symmetric positive definite",
                ));
            }
            let ab = 0.5 * (ab + ba);
            let det = aa * bb - ab * ab;
            if !(det > 0.0) {
                return Err(Error::param(
                    &name("covariance"),
                    format!("{:?}", c.covariance),
                    "symmetric positive definite",
                ));
            }
            let ln_w = if c.weight > 0.0 { c.weight.ln() } else { f64::NEG_INFINITY };
            let cond_sd = [(det / aa).sqrt(), (det / bb).sqrt()];
            comps.push(Baked {
                ln_w,
                mu: c.mean,
                ln_marginal: [aa, bb].map(|v| ln_w - 0.5 * v.ln() - LN_SQRT_2PI),
                inv_var: [1.0 / aa, 1.0 / bb],
                slope: [ab / aa, ab / bb],
                cond_sd,
                inv_cond_sd: cond_sd.map(|sd| 1.0 / sd),
                ln_cond_norm: cond_sd.map(|sd| -sd.ln() - LN_SQRT_2PI),
                ln_norm2: -(2.0 * LN_SQRT_2PI) - 0.5 * det.ln(),
                inv: [bb / det, -ab / det, aa / det],
            });
        }
        // The reradiation's peak is at most S·Σ w_k·N_k(μ_k) = S·Σ w_k / (2π √det Σ_k):
        // held to the bound of a measured matrix entry, so that renders stay finite in f32.
        let peak: f64 = file.scale * comps.iter().map(|b| (b.ln_w + b.ln_norm2).exp()).sum::<f64>();
        if !(peak <= MAX_MATRIX_VALUE) {
            return Err(Error::param(
                "scale",
                file.scale,
                format!(
                    "a scale whose mixture peaks at most at {MAX_MATRIX_VALUE} per nm (this one peaks near {})",
                    crate::num(peak)
                ),
            ));
        }
        let range = [file.lambda_i_range_nm, file.lambda_o_range_nm];
        let diagonal_index = GridIndex::new(&file.diagonal.wavelengths_nm);
        Ok(Self { file, comps, range, diagonal_index })
    }

    /// Load and validate a `*.gmm.json` file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self> {
        let p = path.as_ref();
        Self::new(GmmFile::load(p)?).map_err(|e| Error::data(format!("{}: {e}", p.display())))
    }

    /// The fit file this model was built from.
    pub fn file(&self) -> &GmmFile {
        &self.file
    }

    /// Elastic albedo ρ(λ) (the stored diagonal, interpolated, constant beyond its ends).
    pub fn reflectance(&self, lambda: f64) -> f64 {
        interp_indexed(&self.file.diagonal.wavelengths_nm, self.diagonal_index, &self.file.diagonal.values, lambda)
    }

    /// Whether anything is reradiated.
    pub fn is_fluorescent(&self) -> bool {
        self.file.scale > 0.0
    }

    /// The measured excitation range, nm.
    pub fn excitation_support(&self) -> Option<(f64, f64)> {
        self.is_fluorescent().then_some((self.range[0][0], self.range[0][1]))
    }

    /// The measured emission range, nm.
    pub fn emission_support(&self) -> Option<(f64, f64)> {
        self.is_fluorescent().then_some((self.range[1][0], self.range[1][1]))
    }

    /// The mixture density p(λi, λo) (eq. 1), untruncated, nm⁻².
    pub fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        let mut ln_p = [f64::NEG_INFINITY; MAX_COMPONENTS];
        for (l, c) in ln_p.iter_mut().zip(&self.comps) {
            let (da, db) = (lambda_i - c.mu[0], lambda_o - c.mu[1]);
            let q = c.inv[0] * da * da + 2.0 * c.inv[1] * da * db + c.inv[2] * db * db;
            *l = c.ln_w + c.ln_norm2 - 0.5 * q;
        }
        log_sum_exp(ln_p[..self.comps.len()].iter().copied()).exp()
    }

    fn in_domain(&self, lambda_i: f64, lambda_o: f64) -> bool {
        lambda_i >= self.range[0][0]
            && lambda_i <= self.range[0][1]
            && lambda_o >= self.range[1][0]
            && lambda_o <= self.range[1][1]
            && lambda_i <= lambda_o
    }

    /// P(λi, λo) = S·p on the domain (zero for λi > λo and outside Λ), nm⁻¹.
    pub fn reradiation(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        if !self.in_domain(lambda_i, lambda_o) || !self.is_fluorescent() {
            return 0.0;
        }
        self.file.scale * self.density(lambda_i, lambda_o)
    }

    /// The interval of the free wavelength given the other (see the module docs).
    fn interval(&self, given: Given, x: f64, lo: f64, hi: f64) -> (f64, f64) {
        match given {
            Given::LambdaI => (x.max(self.range[1][0]).max(lo), self.range[1][1].min(hi)),
            Given::LambdaO => (lo.max(self.range[0][0]), hi.min(x).min(self.range[0][1])),
        }
    }

    /// The conditional mixture given x on [a, b] (see [`Slice`]).
    ///
    /// M_k needs two ln Q evaluations, so it is computed first for the component of
    /// largest ln π N(x | μg, σgg), and skipped for any other (its weight set to 0) when
    /// ln π N < ln(π N M of that first one) − [`LN_NEGLIGIBLE`]: since M_k ≤ 1, such a
    /// component changes the total by less than e^−45 relative, below f64 resolution.
    /// The weights then cost one exp each: w_k = f_k e^{ln π N + l_k − scale}, with
    /// (l_k, f_k) from `std_mass_parts` and scale the largest ln π N + l_k.
    fn slice(&self, given: Given, x: f64, a: f64, b: f64) -> Slice {
        let (g, f) = (given as usize, 1 - given as usize);
        let n = self.comps.len();
        let mut s = Slice {
            n,
            ln_marginal: [0.0; MAX_COMPONENTS],
            mean: [0.0; MAX_COMPONENTS],
            w: [0.0; MAX_COMPONENTS],
            sum: 0.0,
            ln_total: f64::NEG_INFINITY,
        };
        let mut top = 0;
        for (k, c) in self.comps.iter().enumerate() {
            let d = x - c.mu[g];
            s.ln_marginal[k] = c.ln_marginal[g] - 0.5 * d * d * c.inv_var[g];
            s.mean[k] = c.mu[f] + c.slope[g] * d;
            if s.ln_marginal[k] > s.ln_marginal[top] {
                top = k;
            }
        }
        // π N M = e^{ln π N + l} f (see `std_mass_parts`).
        let mut ln_part = [f64::NEG_INFINITY; MAX_COMPONENTS];
        let parts = |k: usize| {
            let (m, r) = (s.mean[k], self.comps[k].inv_cond_sd[g]);
            let (l, fraction) = std_mass_parts((a - m) * r, (b - m) * r);
            (s.ln_marginal[k] + l, fraction)
        };
        let mut fraction = [0.0; MAX_COMPONENTS];
        (ln_part[top], fraction[top]) = parts(top);
        let best = ln_part[top] + fraction[top].ln();
        for k in (0..n).filter(|&k| k != top) {
            if s.ln_marginal[k] >= best - LN_NEGLIGIBLE {
                (ln_part[k], fraction[k]) = parts(k);
            }
        }
        let scale = ln_part[..n].iter().fold(f64::NEG_INFINITY, |m, &l| m.max(l));
        if !scale.is_finite() {
            return s;
        }
        for ((w, l), f) in s.w[..n].iter_mut().zip(&ln_part).zip(&fraction) {
            *w = f * (l - scale).exp();
            s.sum += *w;
        }
        s.ln_total = scale + s.sum.ln();
        s
    }

    fn given_ok(&self, given: Given, x: f64) -> bool {
        let r = self.range[given as usize];
        self.is_fluorescent() && x >= r[0] && x <= r[1]
    }

    /// ∫ P over the free wavelength in [lo, hi] ∩ its domain; at least
    /// [`MIN_POSITIVE_MASS`] wherever that interval is not empty (where the exact
    /// integral is positive), even when the value itself underflows.
    fn conditional_mass(&self, given: Given, x: f64, lo: f64, hi: f64) -> f64 {
        if !self.given_ok(given, x) {
            return 0.0;
        }
        let (a, b) = self.interval(given, x, lo, hi);
        if !(b > a) {
            return 0.0;
        }
        let ln_total = self.slice(given, x, a, b).ln_total;
        if !ln_total.is_finite() {
            return 0.0;
        }
        (self.file.scale * ln_total.exp()).max(MIN_POSITIVE_MASS)
    }

    fn sample(&self, given: Given, x: f64, xi: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
        if !self.given_ok(given, x) {
            return None;
        }
        let (a, b) = self.interval(given, x, lo, hi);
        if !(b > a) {
            return None;
        }
        let s = self.slice(given, x, a, b);
        if !s.ln_total.is_finite() {
            return None;
        }
        // Component choice (Algorithm 1, corrected): first k with ξ < Σ_{≤k} w.
        let g = given as usize;
        let xi = xi.clamp(0.0, 1.0);
        let inv_sum = 1.0 / s.sum;
        let mut acc = 0.0;
        let mut pick = None;
        for (k, &w) in s.w[..s.n].iter().enumerate() {
            let w = w * inv_sum;
            if w > 0.0 && (xi < acc + w || k == s.n - 1) {
                pick = Some((k, ((xi - acc) / w).clamp(0.0, 1.0)));
                break;
            }
            acc += w;
        }
        let (k, u) = match pick {
            Some(p) => p,
            // Rounding left ξ above the last positive weight: take that component.
            None => (s.w[..s.n].iter().rposition(|&w| w > 0.0)?, 1.0),
        };
        let (m, c) = (s.mean[k], &self.comps[k]);
        let z = sample_std_truncated((a - m) * c.inv_cond_sd[g], (b - m) * c.inv_cond_sd[g], u);
        let v = (m + c.cond_sd[g] * z).clamp(a, b);
        let pdf = self.slice_pdf(given, &s, v);
        (pdf > 0.0 && pdf.is_finite()).then_some((v, pdf))
    }

    /// pdf(v | x) = Σ_k π_k N(x | μg, σgg) N(v | mean_k, v_{f|g}) / Σ_k π_k N(x | μg, σgg) M_k.
    fn slice_pdf(&self, given: Given, s: &Slice, v: f64) -> f64 {
        let g = given as usize;
        self.comps
            .iter()
            .zip(&s.ln_marginal[..s.n])
            .zip(&s.mean[..s.n])
            .map(|((c, lm), m)| {
                let z = (v - m) * c.inv_cond_sd[g];
                (lm + c.ln_cond_norm[g] - 0.5 * z * z - s.ln_total).exp()
            })
            .sum()
    }

    fn pdf(&self, given: Given, x: f64, v: f64, lo: f64, hi: f64) -> f64 {
        if !self.given_ok(given, x) {
            return 0.0;
        }
        let (a, b) = self.interval(given, x, lo, hi);
        if !(b > a && v >= a && v <= b) {
            return 0.0;
        }
        let s = self.slice(given, x, a, b);
        if !s.ln_total.is_finite() {
            return 0.0;
        }
        self.slice_pdf(given, &s, v)
    }

    /// ∫ P(λi, λo) dλo over the domain: the reradiated albedo at λi.
    pub fn reradiated_albedo(&self, lambda_i: f64) -> f64 {
        self.conditional_mass(Given::LambdaI, lambda_i, f64::NEG_INFINITY, f64::INFINITY)
    }

    /// ∫_{lo}^{min(hi, λo)} P(λi, λo) dλi.
    pub fn absorbed_into(&self, lambda_o: f64, lo: f64, hi: f64) -> f64 {
        self.conditional_mass(Given::LambdaO, lambda_o, lo, hi)
    }

    /// Sample λo | λi from the truncated conditional mixture: (λo, pdf per nm).
    pub fn sample_emission(&self, lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        self.sample(Given::LambdaI, lambda_i, xi, f64::NEG_INFINITY, f64::INFINITY)
    }

    /// pdf of [`Self::sample_emission`].
    pub fn emission_pdf(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        self.pdf(Given::LambdaI, lambda_i, lambda_o, f64::NEG_INFINITY, f64::INFINITY)
    }

    /// Sample λi | λo on [lo, min(hi, λo)]: (λi, pdf per nm).
    pub fn sample_excitation(&self, lambda_o: f64, xi: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
        self.sample(Given::LambdaO, lambda_o, xi, lo, hi)
    }

    /// pdf of [`Self::sample_excitation`].
    pub fn excitation_pdf(&self, lambda_o: f64, lambda_i: f64, lo: f64, hi: f64) -> f64 {
        self.pdf(Given::LambdaO, lambda_o, lambda_i, lo, hi)
    }

    /// ∬ p over the domain (λi ≤ λo), for unit S.
    fn domain_mass(&self) -> f64 {
        integrate_split(self.range[0][0], self.range[0][1], self.range[1][0], |li| {
            let (a, b) = self.interval(Given::LambdaI, li, f64::NEG_INFINITY, f64::INFINITY);
            if !(b > a) {
                return 0.0;
            }
            self.slice(Given::LambdaI, li, a, b).ln_total.exp()
        })
    }

    /// Floats held at render time: the diagonal, S, the domain, and per component the
    /// 7 stored numbers plus the baked conditionals.
    pub fn floats_at_render_time(&self) -> usize {
        // Baked: ln w, μ (2), and per axis ln marginal, 1/var, slope, sd, 1/sd, ln norm
        // (2 each), ln norm, inverse (3) = 19.
        2 * self.file.diagonal.values.len() + 1 + 4 + 19 * self.comps.len()
    }
}

/// Composite Simpson of f over [a, b], split at `knot` (where f has a kink), with
/// steps of about [`SCALE_QUADRATURE_STEP_NM`].
fn integrate_split(a: f64, b: f64, knot: f64, f: impl Fn(f64) -> f64) -> f64 {
    let simpson = |lo: f64, hi: f64| {
        if !(hi > lo) {
            return 0.0;
        }
        let n = (((hi - lo) / SCALE_QUADRATURE_STEP_NM).ceil() as usize).max(2).next_multiple_of(2);
        let h = (hi - lo) / n as f64;
        let mut s = f(lo) + f(hi);
        for i in 1..n {
            s += if i % 2 == 1 { 4.0 } else { 2.0 } * f(lo + i as f64 * h);
        }
        s * h / 3.0
    };
    let k = knot.clamp(a, b);
    simpson(a, k) + simpson(k, b)
}

impl fmt::Display for GmmModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "GmmModel[source = \"{}\", components = {}, S = {:.6} nm ({:?}), lambda_i = {:?} nm, lambda_o = {:?} nm]",
            self.file.source,
            self.comps.len(),
            self.file.scale,
            self.file.scaling,
            self.range[0],
            self.range[1]
        )
    }
}

// ------------------------------------------------------------------ fitting

/// Options of [`fit`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitOptions {
    /// Number of Gaussians K, [1, [`MAX_COMPONENTS`]].
    pub components: usize,
    /// EM iteration bound per restart.
    pub max_iterations: usize,
    /// Convergence tolerance on the weighted mean log-likelihood.
    pub tolerance: f64,
    /// Seed of the k-means++ initialisation.
    pub seed: u64,
    /// Restarts (k-means++ draws); the best final likelihood is kept.
    pub restarts: usize,
    /// Which S to render with.
    pub scaling: Scaling,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            components: 8,
            max_iterations: DEFAULT_MAX_ITERATIONS,
            tolerance: DEFAULT_TOLERANCE,
            seed: 1,
            restarts: DEFAULT_RESTARTS,
            scaling: Scaling::IntegralRatio,
        }
    }
}

/// SplitMix64: a tiny deterministic generator for the initialisation.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_f64(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Index drawn ∝ weights (all ≥ 0, positive sum).
    fn pick(&mut self, w: &[f64]) -> usize {
        let total: f64 = w.iter().sum();
        let mut t = self.next_f64() * total;
        for (i, &x) in w.iter().enumerate() {
            if t < x {
                return i;
            }
            t -= x;
        }
        w.iter().rposition(|&x| x > 0.0).unwrap_or(0)
    }
}

#[derive(Clone, Copy)]
struct Gauss {
    w: f64,
    mu: [f64; 2],
    cov: [f64; 3], // aa, ab, bb
}

impl Gauss {
    fn log_pdf(&self, x: [f64; 2]) -> f64 {
        let [aa, ab, bb] = self.cov;
        let det = aa * bb - ab * ab;
        let (da, db) = (x[0] - self.mu[0], x[1] - self.mu[1]);
        let q = (bb * da * da - 2.0 * ab * da * db + aa * db * db) / det;
        -0.5 * q - 0.5 * det.ln() - 2.0 * LN_SQRT_2PI
    }
}

/// Weighted EM from one initialisation; returns (mixture, log-likelihood, iterations, converged).
fn em(x: &[[f64; 2]], w: &[f64], init: Vec<Gauss>, reg: [f64; 2], opts: &FitOptions) -> (Vec<Gauss>, f64, usize, bool) {
    let k = init.len();
    let mut g = init;
    let mut resp = vec![0.0; x.len() * k];
    let mut lse = vec![0.0; x.len()];
    let mut prev = f64::NEG_INFINITY;
    let mut ll = prev;
    for it in 0..opts.max_iterations {
        // E-step, in logs.
        ll = 0.0;
        for (n, xn) in x.iter().enumerate() {
            let r = &mut resp[n * k..(n + 1) * k];
            for (rk, gk) in r.iter_mut().zip(&g) {
                *rk = if gk.w > 0.0 { gk.w.ln() + gk.log_pdf(*xn) } else { f64::NEG_INFINITY };
            }
            let l = log_sum_exp(r.iter().copied());
            for rk in r.iter_mut() {
                *rk = (*rk - l).exp();
            }
            lse[n] = l;
            ll += w[n] * l;
        }
        if (ll - prev).abs() <= opts.tolerance * (1.0 + ll.abs()) {
            return (g, ll, it, true);
        }
        prev = ll;
        // M-step.
        for (c, gk) in g.iter_mut().enumerate() {
            let nk: f64 = (0..x.len()).map(|n| w[n] * resp[n * k + c]).sum();
            if !(nk > DEAD_COMPONENT_MASS) {
                // Re-seed at the observation the mixture explains worst.
                let worst = (0..x.len()).max_by(|&a, &b| (-w[a] * lse[a]).total_cmp(&(-w[b] * lse[b]))).unwrap_or(0);
                *gk = Gauss { w: DEAD_COMPONENT_MASS, mu: x[worst], cov: [4.0 * reg[0], 0.0, 4.0 * reg[1]] };
                continue;
            }
            let mut mu = [0.0; 2];
            for n in 0..x.len() {
                let r = w[n] * resp[n * k + c];
                mu[0] += r * x[n][0];
                mu[1] += r * x[n][1];
            }
            mu = [mu[0] / nk, mu[1] / nk];
            let mut cov = [0.0; 3];
            for n in 0..x.len() {
                let r = w[n] * resp[n * k + c];
                let (da, db) = (x[n][0] - mu[0], x[n][1] - mu[1]);
                cov[0] += r * da * da;
                cov[1] += r * da * db;
                cov[2] += r * db * db;
            }
            *gk = Gauss { w: nk, mu, cov: [cov[0] / nk + reg[0], cov[1] / nk, cov[2] / nk + reg[1]] };
        }
        let total: f64 = g.iter().map(|c| c.w).sum();
        for c in g.iter_mut() {
            c.w /= total;
        }
    }
    (g, ll, opts.max_iterations, false)
}

/// Weighted k-means++ initialisation (deterministic for a seed).
fn kmeans_pp(x: &[[f64; 2]], w: &[f64], k: usize, reg: [f64; 2], rng: &mut SplitMix64) -> Vec<Gauss> {
    let d2 = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
    let mut centres = vec![x[rng.pick(w)]];
    let mut dist: Vec<f64> = x.iter().map(|&p| d2(p, centres[0])).collect();
    while centres.len() < k {
        let score: Vec<f64> = w.iter().zip(&dist).map(|(a, b)| a * b).collect();
        let c = if score.iter().sum::<f64>() > 0.0 { x[rng.pick(&score)] } else { x[rng.pick(w)] };
        centres.push(c);
        for (d, &p) in dist.iter_mut().zip(x) {
            *d = d.min(d2(p, c));
        }
    }
    // Hard assignment -> weights, means, covariances.
    let mut acc = vec![(0.0, [0.0; 2], [0.0; 3]); k];
    let nearest = |p: [f64; 2]| (0..k).min_by(|&a, &b| d2(p, centres[a]).total_cmp(&d2(p, centres[b]))).unwrap_or(0);
    for (&p, &wn) in x.iter().zip(w) {
        let a = &mut acc[nearest(p)];
        a.0 += wn;
        a.1[0] += wn * p[0];
        a.1[1] += wn * p[1];
    }
    let means: Vec<[f64; 2]> =
        acc.iter().zip(&centres).map(|(a, c)| if a.0 > 0.0 { [a.1[0] / a.0, a.1[1] / a.0] } else { *c }).collect();
    for (&p, &wn) in x.iter().zip(w) {
        let c = nearest(p);
        let (da, db) = (p[0] - means[c][0], p[1] - means[c][1]);
        let a = &mut acc[c];
        a.2[0] += wn * da * da;
        a.2[1] += wn * da * db;
        a.2[2] += wn * db * db;
    }
    let total: f64 = w.iter().sum();
    acc.iter()
        .zip(&means)
        .map(|(a, &mu)| {
            let cov = if a.0 > 0.0 {
                [a.2[0] / a.0 + reg[0], a.2[1] / a.0, a.2[2] / a.0 + reg[1]]
            } else {
                [4.0 * reg[0], 0.0, 4.0 * reg[1]]
            };
            Gauss { w: (a.0 / total).max(DEAD_COMPONENT_MASS), mu, cov }
        })
        .collect()
}

/// Fit a mixture to a filtered matrix (weighted EM, see the module docs) and compute S.
pub fn fit(matrix: &Filtered, opts: &FitOptions) -> Result<GmmFile> {
    if !(1..=MAX_COMPONENTS).contains(&opts.components) {
        return Err(Error::param("components", opts.components, format!("[1, {MAX_COMPONENTS}]")));
    }
    if opts.max_iterations == 0 || opts.restarts == 0 {
        return Err(Error::param("max_iterations/restarts", "0", "≥ 1"));
    }
    let model = MatrixModel::new(matrix)?;
    let source =
        Path::new(&matrix.source).file_name().map_or(matrix.source.clone(), |n| n.to_string_lossy().into_owned());
    let (li, lo) = (&matrix.lambda_i, &matrix.lambda_o);
    let ni = li.len();
    let (mut x, mut w) = (Vec::new(), Vec::new());
    for (j, &o) in lo.iter().enumerate() {
        for (k, &i) in li.iter().enumerate() {
            let v = matrix.off[j * ni + k] / matrix.band_nm[j];
            if v > 0.0 {
                x.push([i, o]);
                w.push(v);
            }
        }
    }
    let first_step = |g: &[f64]| g.windows(2).map(|p| p[1] - p[0]).fold(f64::INFINITY, f64::min);
    let reg = [first_step(li).powi(2) / 6.0, first_step(lo).powi(2) / 6.0];
    let li_range = [li[0], li[ni - 1]];
    let lo_range = [lo[0], lo[lo.len() - 1]];
    let diagonal = Diagonal { wavelengths_nm: matrix.diagonal_nm.clone(), values: matrix.diagonal.clone() };

    if x.is_empty() {
        // Nothing fluoresces: one placeholder component, S = 0.
        let file = GmmFile {
            format: FORMAT.into(),
            version: 1,
            source: source.clone(),
            lambda_i_range_nm: li_range,
            lambda_o_range_nm: lo_range,
            diagonal,
            scaling: opts.scaling,
            scale: 0.0,
            scale_integral_ratio: 0.0,
            scale_error_minimisation: 0.0,
            components: vec![Component {
                weight: 1.0,
                mean: [0.5 * (li_range[0] + li_range[1]), 0.5 * (lo_range[0] + lo_range[1])],
                covariance: [[reg[0], 0.0], [0.0, reg[1]]],
            }],
            fit: FitInfo {
                method: "weighted_em".into(),
                iterations: 0,
                converged: true,
                log_likelihood: 0.0,
                seed: opts.seed,
                restarts: 0,
                regularisation_nm2: reg,
            },
        };
        return Ok(file);
    }
    let total: f64 = w.iter().sum();
    for v in w.iter_mut() {
        *v /= total;
    }

    let mut best: Option<(Vec<Gauss>, f64, usize, bool)> = None;
    for r in 0..opts.restarts {
        let mut rng = SplitMix64(opts.seed.wrapping_mul(0x2545_F491_4F6C_DD1D).wrapping_add(r as u64));
        let init = kmeans_pp(&x, &w, opts.components.min(x.len()), reg, &mut rng);
        let out = em(&x, &w, init, reg, opts);
        if best.as_ref().is_none_or(|b| out.1 > b.1) {
            best = Some(out);
        }
    }
    let (g, ll, iterations, converged) = best.ok_or_else(|| Error::data("EM produced no fit"))?;
    let components: Vec<Component> = g
        .iter()
        .map(|c| Component { weight: c.w, mean: c.mu, covariance: [[c.cov[0], c.cov[1]], [c.cov[1], c.cov[2]]] })
        .collect();
    let mut file = GmmFile {
        format: FORMAT.into(),
        version: 1,
        source: source.clone(),
        lambda_i_range_nm: li_range,
        lambda_o_range_nm: lo_range,
        diagonal,
        scaling: opts.scaling,
        scale: 1.0,
        scale_integral_ratio: 1.0,
        scale_error_minimisation: 1.0,
        components,
        fit: FitInfo {
            method: "weighted_em".into(),
            iterations,
            converged,
            log_likelihood: ll,
            seed: opts.seed,
            restarts: opts.restarts,
            regularisation_nm2: reg,
        },
    };
    // Scalings (eqs. 4, 5) with the unit-S model.
    let unit = GmmModel::new(file.clone())?;
    let mass = unit.domain_mass();
    let s_ratio = if mass > 0.0 { model.total_reradiation() / mass } else { 0.0 };
    let (mut num, mut den) = (0.0, 0.0);
    for (j, &o) in lo.iter().enumerate() {
        for (k, &i) in li.iter().enumerate() {
            if i < o - WAVELENGTH_TOLERANCE_NM {
                let p = unit.density(i, o);
                num += matrix.off[j * ni + k] / matrix.band_nm[j] * p;
                den += p * p;
            }
        }
    }
    let s_err = if den > 0.0 { num / den } else { 0.0 };
    file.scale_integral_ratio = s_ratio;
    file.scale_error_minimisation = s_err;
    file.scale = match opts.scaling {
        Scaling::IntegralRatio => s_ratio,
        Scaling::ErrorMinimisation => s_err,
    };
    Ok(file)
}

lambertian_measured!(GmmModel);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::matrix::{load_matrix, shared_bispectral_files};
    use crate::testutil::{chi2, chi2_critical, simpson, uniforms};

    #[test]
    fn erfc_matches_reference_values() {
        // Reference values (Abramowitz & Stegun / high-precision tables).
        for (x, want) in [
            (0.0, 1.0),
            (0.5, 0.479_500_122_186_953_5),
            (1.0, 0.157_299_207_050_285_13),
            (2.0, 4.677_734_981_047_266e-3),
            (2.5, 4.069_520_174_449_59e-4),
            (3.0, 2.209_049_699_858_544e-5),
            (5.0, 1.537_459_794_428_035e-12),
            (10.0, 2.088_487_583_762_545e-45),
            (-1.0, 1.842_700_792_949_715),
        ] {
            let got = erfc(x);
            assert!((got - want).abs() <= 2e-11 * want, "erfc({x}) = {got}, want {want}");
        }
        // continuity across the switch point
        let (a, b) = (erfc(ERF_SERIES_MAX - 1e-12), erfc(ERF_SERIES_MAX + 1e-12));
        assert!((a - b).abs() < 2e-11 * a);
        // ln Q far in the tail: Q(40) ≈ φ(40)/40 (1 − 1/40² + 3/40⁴)
        let z = 40.0;
        let approx = log_phi(z) - z.ln() + (1.0 - 1.0 / (z * z) + 3.0 / z.powi(4)).ln();
        assert!((log_q(z) - approx).abs() < 1e-8, "{} vs {approx}", log_q(z));
        assert!((log_q(-3.0) - (1.0 - 0.5 * erfc(3.0 / 2f64.sqrt())).ln()).abs() < 1e-15);
    }

    #[test]
    fn tabulated_log_q_matches_direct_evaluation() {
        let mut worst: f64 = 0.0;
        for i in 0..=200_000 {
            let z = -10.5 + 21.0 * i as f64 / 200_000.0;
            worst = worst.max((log_q(z) - log_q_direct(z)).abs());
        }
        assert!(worst < 1e-10, "max |Δ ln Q| = {worst}");
    }

    #[test]
    fn truncated_normal_inverts_its_cdf() {
        for (a, b) in [(-1.0, 2.0), (0.5, 3.0), (5.0, 5.5), (30.0, 31.0), (-40.0, -39.0), (-0.1, 0.2), (100.0, 300.0)] {
            let lm = log_std_mass(a, b);
            assert!(lm.is_finite(), "{a} {b}");
            for u in [0.0, 0.01, 0.3, 0.5, 0.77, 0.999, 1.0] {
                let z = sample_std_truncated(a, b, u);
                assert!(z >= a && z <= b, "{z} not in [{a}, {b}]");
                // CDF of the truncated normal at z, in logs
                let c = (log_std_mass(a, z) - lm).exp();
                let c = if z <= a { 0.0 } else { c };
                assert!((c - u).abs() < 1e-9, "[{a}, {b}] u {u}: z {z} cdf {c}");
            }
        }
    }

    fn synthetic_file() -> GmmFile {
        GmmFile {
            format: FORMAT.into(),
            version: 1,
            source: "synthetic".into(),
            lambda_i_range_nm: [300.0, 780.0],
            lambda_o_range_nm: [380.0, 780.0],
            diagonal: Diagonal { wavelengths_nm: vec![380.0, 780.0], values: vec![0.2, 0.8] },
            scaling: Scaling::IntegralRatio,
            scale: 2.0,
            scale_integral_ratio: 2.0,
            scale_error_minimisation: 2.0,
            components: vec![
                Component { weight: 0.6, mean: [380.0, 450.0], covariance: [[900.0, 200.0], [200.0, 400.0]] },
                Component { weight: 0.3, mean: [470.0, 540.0], covariance: [[300.0, -50.0], [-50.0, 250.0]] },
                Component { weight: 0.1, mean: [600.0, 640.0], covariance: [[100.0, 0.0], [0.0, 64.0]] },
            ],
            fit: FitInfo {
                method: "weighted_em".into(),
                iterations: 0,
                converged: true,
                log_likelihood: 0.0,
                seed: 0,
                restarts: 0,
                regularisation_nm2: [0.0, 0.0],
            },
        }
    }

    #[test]
    fn conditional_masses_are_integrals_of_the_reradiation() {
        let m = GmmModel::new(synthetic_file()).unwrap();
        for li in [300.0_f64, 380.0, 455.0, 700.0, 779.0] {
            let q = simpson(|lo| m.reradiation(li, lo), li.max(380.0), 780.0, 20_000);
            let a = m.reradiated_albedo(li);
            assert!((a - q).abs() <= 1e-8 * q.max(1e-30) + 1e-300, "λi {li}: {a} vs {q}");
        }
        for (lo, r) in [(450.0, (300.0, 830.0_f64)), (600.0, (350.0, 500.0)), (381.0, (300.0, 830.0))] {
            let q = simpson(|li| m.reradiation(li, lo), r.0, r.1.min(lo), 20_000);
            let a = m.absorbed_into(lo, r.0, r.1);
            assert!((a - q).abs() <= 1e-8 * q, "λo {lo}: {a} vs {q}");
        }
        // the density is a normalised mixture
        let total = simpson(|li| simpson(|lo| m.density(li, lo), 0.0, 1200.0, 600), 0.0, 1200.0, 600);
        assert!((total - 1.0).abs() < 1e-6, "{total}");
    }

    #[test]
    fn conditional_sampling_matches_pdf_chi2() {
        let m = GmmModel::new(synthetic_file()).unwrap();
        // λo | λi, including λi near the top where almost no mass lies above it
        for li in [300.0_f64, 420.0, 560.0, 700.0, 770.0, 779.5] {
            let xs: Vec<f64> = uniforms(20_000, 3)
                .into_iter()
                .map(|u| {
                    let (x, pdf) = m.sample_emission(li, u).expect("sample");
                    assert!((pdf - m.emission_pdf(li, x)).abs() <= 1e-9 * pdf, "pdf mismatch at {x}");
                    x
                })
                .collect();
            let lo = li.max(380.0);
            let total = simpson(|x| m.emission_pdf(li, x), lo, 780.0, 4_000);
            assert!((total - 1.0).abs() < 1e-6, "λi {li}: ∫pdf = {total}");
            let (stat, dof) = chi2(&xs, lo, 780.0, 60, |x| m.emission_pdf(li, x));
            assert!(stat < chi2_critical(dof), "λi {li}: chi2 {stat} dof {dof}");
        }
        // λi | λo with ranges
        for (lo, r) in
            [(450.0, (300.0, 830.0_f64)), (700.0, (300.0, 830.0)), (600.0, (350.0, 420.0)), (381.0, (300.0, 830.0))]
        {
            let hi = r.1.min(lo);
            let xs: Vec<f64> = uniforms(20_000, 5)
                .into_iter()
                .map(|u| {
                    let (x, pdf) = m.sample_excitation(lo, u, r.0, r.1).expect("sample");
                    assert!(x >= r.0 && x <= hi);
                    assert!((pdf - m.excitation_pdf(lo, x, r.0, r.1)).abs() <= 1e-9 * pdf);
                    x
                })
                .collect();
            let (stat, dof) = chi2(&xs, r.0, hi, 60, |x| m.excitation_pdf(lo, x, r.0, r.1));
            assert!(stat < chi2_critical(dof), "λo {lo}: chi2 {stat} dof {dof}");
        }
        assert!(m.sample_emission(790.0, 0.5).is_none());
        assert!(m.sample_excitation(370.0, 0.5, 300.0, 830.0).is_none());
        assert_eq!(m.emission_pdf(500.0, 490.0), 0.0);
    }

    #[test]
    fn measured_fit_sampling_matches_pdf_chi2() {
        // 8-component fit of a measured matrix (shared data) or, without it, of our own.
        let path = shared_bispectral_files()
            .into_iter()
            .find(|p| p.to_string_lossy().contains("TEXTYELL"))
            .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/matrices/jung_yellow.csv"));
        let f = Filtered::new(&load_matrix(&path).unwrap()).unwrap();
        let m = GmmModel::new(fit(&f, &FitOptions::default()).unwrap()).unwrap();
        // λi near the top: almost no mass of any component lies above it.
        for li in [330.0_f64, 450.0, 600.0, 760.0, 778.0] {
            let mass = m.reradiated_albedo(li);
            assert!(mass.is_finite() && mass >= 0.0);
            let lo = li.max(380.0);
            let xs: Vec<f64> = uniforms(20_000, 9)
                .into_iter()
                .map(|u| {
                    let (x, pdf) = m.sample_emission(li, u).expect("sample");
                    assert!(x >= lo && x <= 780.0 && (pdf - m.emission_pdf(li, x)).abs() <= 1e-9 * pdf);
                    x
                })
                .collect();
            let (stat, dof) = chi2(&xs, lo, 780.0, 50, |x| m.emission_pdf(li, x));
            assert!(stat < chi2_critical(dof), "{}: λi {li}: chi2 {stat} dof {dof}", path.display());
        }
        for lo in [400.0_f64, 520.0, 650.0, 779.0] {
            let xs: Vec<f64> = uniforms(20_000, 11)
                .into_iter()
                .map(|u| m.sample_excitation(lo, u, 300.0, 830.0).expect("sample").0)
                .collect();
            let (stat, dof) = chi2(&xs, 300.0, lo, 50, |x| m.excitation_pdf(lo, x, 300.0, 830.0));
            assert!(stat < chi2_critical(dof), "{}: λo {lo}: chi2 {stat} dof {dof}", path.display());
        }
    }

    #[test]
    fn sampling_far_in_the_tail_is_exact_and_bounded() {
        // One narrow component far below λi: the conditional mass above λi is ~e^-1000.
        let mut f = synthetic_file();
        f.components = vec![Component { weight: 1.0, mean: [400.0, 450.0], covariance: [[100.0, 0.0], [0.0, 100.0]] }];
        let m = GmmModel::new(f).unwrap();
        let li = 775.0;
        assert_eq!(m.reradiation(li, 778.0), 0.0); // underflows in linear terms
        for u in [0.0, 0.25, 0.5, 0.9, 1.0] {
            let (x, pdf) = m.sample_emission(li, u).unwrap();
            assert!((li..=780.0).contains(&x) && pdf.is_finite() && pdf > 0.0, "{x} {pdf}");
            assert!((pdf - m.emission_pdf(li, x)).abs() <= 1e-9 * pdf);
        }
        // Truncated exponential-like: mass concentrated just above λi. The conditional
        // is N(450, 100) on [775, 780]: its density ratio across 1 nm is exp(-(z·dz)).
        let (x_med, _) = m.sample_emission(li, 0.5).unwrap();
        let rate = (li - 450.0) / 100.0; // per nm
        let want = li + (2.0f64).ln() / rate;
        assert!((x_med - want).abs() < 1e-3, "{x_med} vs {want}");
        // λi | λo on [770, 780]: ~e^-1200, below f64, yet positive, and it samples.
        let mass = m.absorbed_into(780.0, 770.0, 830.0);
        assert!(mass > 0.0 && mass <= f64::MIN_POSITIVE, "{mass}");
        assert!(m.sample_excitation(780.0, 0.5, 770.0, 830.0).is_some());
        assert_eq!(m.absorbed_into(780.0, 785.0, 830.0), 0.0);
    }

    #[test]
    fn file_validation_names_the_field() {
        let bad = |f: GmmFile| GmmModel::new(f).unwrap_err().to_string();
        let mut f = synthetic_file();
        f.components[0].covariance = [[100.0, 200.0], [200.0, 100.0]];
        assert!(bad(f).contains("components[0].covariance"));
        let mut f = synthetic_file();
        f.components[1].weight = 0.5;
        assert!(bad(f).contains("weight"));
        let mut f = synthetic_file();
        f.scale = f64::NAN;
        assert!(bad(f).contains("scale"));
        let mut f = synthetic_file();
        f.format = "x".into();
        assert!(bad(f).contains("format"));
        let mut f = synthetic_file();
        f.components[2].mean[0] = f64::INFINITY;
        assert!(bad(f).contains("components[2].mean"));
        let e = serde_json::from_str::<GmmFile>("{\"format\": \"fluo-gmm\"}").unwrap_err().to_string();
        assert!(e.contains("missing field"), "{e}");
    }

    #[test]
    fn fit_recovers_a_single_gaussian_and_scales() {
        // A matrix sampled from one Gaussian of known parameters (plus the tent
        // regularisation, which the fit adds back).
        let li: Vec<f64> = (0..49).map(|i| 300.0 + 10.0 * i as f64).collect();
        let lo: Vec<f64> = (0..41).map(|j| 380.0 + 10.0 * j as f64).collect();
        let (mu, cov) = ([420.0, 520.0], [900.0, 300.0, 600.0]);
        let g = Gauss { w: 1.0, mu, cov };
        let mut values = vec![0.0; li.len() * lo.len()];
        for (j, &o) in lo.iter().enumerate() {
            for (k, &i) in li.iter().enumerate() {
                values[j * li.len() + k] =
                    if (i - o).abs() < 1e-9 { 0.5 } else { 10.0 * 0.05 * g.log_pdf([i, o]).exp() * 100.0 };
            }
        }
        let d = crate::models::matrix::Donaldson::new("gauss", li, lo, values).unwrap();
        let f = Filtered::new(&d).unwrap();
        let opts = FitOptions { components: 1, ..FitOptions::default() };
        let file = fit(&f, &opts).unwrap();
        let c = file.components[0];
        // Truncation at the diagonal and the grid edges shifts the moments a little.
        assert!((c.mean[0] - mu[0]).abs() < 6.0 && (c.mean[1] - mu[1]).abs() < 6.0, "{:?}", c.mean);
        assert!((c.covariance[0][0] / (cov[0] + 100.0 / 6.0) - 1.0).abs() < 0.15, "{:?}", c.covariance);
        // integral ratio keeps the albedo
        let m = GmmModel::new(file.clone()).unwrap();
        let mm = MatrixModel::new(&f).unwrap();
        let total = integrate_split(300.0, 780.0, 380.0, |x| m.reradiated_albedo(x));
        assert!((total / mm.total_reradiation() - 1.0).abs() < 1e-3, "{total} vs {}", mm.total_reradiation());
        // determinism: same seed, same file
        assert_eq!(fit(&f, &opts).unwrap(), file);
    }

    #[test]
    fn shared_files_fit_with_every_component_count() {
        let files = shared_bispectral_files();
        if files.is_empty() {
            eprintln!("skipping: shared data not found (set FLUO_SHARED_DATA or place shared/ beside the repo)");
            return;
        }
        for path in files.iter().take(2) {
            let f = Filtered::new(&load_matrix(path).unwrap()).unwrap();
            for k in [1, 4, 16] {
                let file = fit(&f, &FitOptions { components: k, ..FitOptions::default() }).unwrap();
                assert_eq!(file.components.len(), k);
                assert_eq!(file.floats_stored(), 2 * 41 + 1 + 7 * k);
                let m = GmmModel::new(file).unwrap();
                assert!(m.is_fluorescent() && m.file().scale.is_finite());
                for li in [300.0, 400.0, 500.0, 779.0] {
                    let a = m.reradiated_albedo(li);
                    assert!(a.is_finite() && a >= 0.0);
                }
            }
        }
    }
}
