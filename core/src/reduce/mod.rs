//! Reduced reradiation matrices (Fichet, Belcour & Barla 2024) for non-spectral
//! rendering of fluorescence.
//!
//! # Model
//! Transport carries K basis coefficients instead of a spectrum: a radiance spectrum
//! L(λ) is *downsampled* to `c_k = ∫ L(λ) s_k(λ) dλ` (eq. 8–9), where the s_k are the
//! columns of the N×K basis matrix S (CMFs, plus optional extra bands). A K-vector is
//! *upsampled* with the dual basis, `up[c] = S̃ c` (eq. 10–11). A material's
//! reradiation operator 𝒫 (diagonal ρ plus reradiation density P(λi, λo)) then acts on
//! K-vectors through the reduced matrix (eq. 15):
//!
//! ```text
//! P_ours = Sᵀ W 𝒫 S̃,   S̃ = S (Sᵀ W S)⁻¹,   (𝒫 f)(λo) = ρ(λo) f(λo) + ∫ P(λi, λo) f(λi) dλi
//! ```
//!
//! with W = diag(Δλ) the quadrature weights of the wavelength grid.
//! Reading of eq. 11 (see shared/papers/README.md): the extraction prints
//! S̃ = (S Sᵀ)⁻¹ S, which is N×N-singular for K < N; the dual basis of an N×K matrix is
//! S (Sᵀ W S)⁻¹, so that Sᵀ W S̃ = I_K and an identity 𝒫 reduces to I_K (tested).
//!
//! The naive reduction (eq. 6–7, Hullin et al. 2010) reconstructs the incoming
//! spectrum from the area-normalised basis s̄_k = s_k / ∫ s_k dλ and downsamples the
//! outgoing one with the plain basis: `P_naive = Sᵀ W 𝒫 S̄` (our reading of eq. 7, which
//! reproduces the paper's naive rows of Table 1, see
//! [`crate::reports::reduction::TABLE1_XYZ_NAIVE`]). It is kept for comparison only; it does
//! not map identity to identity.
//!
//! **What the matrices act on.** Reduced matrices act on *basis coefficients*
//! (downsampled radiance, c = Sᵀ W L), not on tristimulus values of another space.
//! The final colour is XYZ = T c, with T the 3×K transfer matrix (eq. 22 and sec. 4.2):
//! for the bases here, whose bands sum to the CMFs, T just adds the split bands back.
//! For an RGB working space, eq. 16 converts an XYZ-basis matrix to
//! `P_rgb = M P_xyz M⁻¹` with M = XYZ→RGB.
//!
//! # Bases ([`BasisKind`])
//! | name   | K | bands |
//! |--------|---|-------|
//! | `xyz`  | 3 | x̄, ȳ, z̄ |
//! | `xyzu` | 4 | x̄, ȳ, z̄, U (UV band) |
//! | `x7`   | 7 | x̄₁, x̄₂, x̄₃, ȳ₁, ȳ₂, z̄, U (appendix A, eqs. 17–22) |
//!
//! U is the first element of the paper's quadratic B-spline partition of unity over
//! 300–800 nm. The paper's basis file (`shared/data/cmf/xyzu_fichet2024.csv`) shows it
//! to be exactly `U(λ) = U₀ ((λ₁ − λ)/(λ₁ − 300))²` for λ ≤ λ₁ with U₀ = 1.34573 and
//! λ₁ = 550.5 nm (√U is linear to 1e-6); we construct it that way, and a test checks it
//! against the file when present.
//!
//! The split of appendix A uses the smoothstep S(λ; μ, σ) = 3t² − 2t³,
//! t = clamp((λ − μ)/(2σ) + 1/2, 0, 1), with μ_y = 570, σ_y = 60; x̄ split at 500 nm
//! (σ = 2) and at μ_x = 590, σ_x = 60. Since y₁ = ȳ·S (eq. 17) is the part *above* μ_y,
//! we order bands as (x̄₁, x̄₂, x̄₃, ȳ₁, ȳ₂, z̄, U) and T sums them as in eq. 22.
//!
//! # Numerical notes
//! The wavelength grid is 300–830 nm at 1 nm; Sᵀ W S is K×K, symmetric positive
//! definite for linearly independent bands, inverted with a Cholesky factorisation;
//! narrow splits make it ill-conditioned, which [`Basis::condition_number`] reports.
//! Reduced matrices have negative entries (the dual basis has negative lobes), and so
//! can reduced colours: renderers must allow negative channel values in transport and
//! clamp only for display.
//!
//! # References
//! A. Fichet, L. Belcour, P. Barla, "Non-Orthogonal Reduction for Rendering Fluorescent
//! Materials in Non-Spectral Engines", CGF 43(4), 2024.

use nalgebra::{DMatrix, DVector, SymmetricEigen, SVD};

use crate::interface::Bispectral;
use crate::patch::normalise_patch;
use crate::spectrum::{cmf, Observer, Spectral};
use crate::{Error, Result};

mod transport;

pub use transport::Transport;

/// Wavelength grid of the reduction, nm.
pub const GRID_START_NM: f64 = 300.0;
/// End of the reduction grid, nm.
pub const GRID_END_NM: f64 = 830.0;
/// Grid step, nm.
pub const GRID_STEP_NM: f64 = 1.0;
/// Peak value of the U band at 300 nm (paper's basis file).
pub const U_PEAK: f64 = 1.345_730_457_558_612_4;
/// Wavelength where the U band reaches zero, nm (paper's basis file).
pub const U_END_NM: f64 = 550.5;

/// Which transport basis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BasisKind {
    /// CIE x̄, ȳ, z̄.
    Xyz,
    /// x̄, ȳ, z̄ and the UV band.
    Xyzu,
    /// The seven-band split of appendix A (with U).
    X7,
    /// The six visible bands of `x7` and a band built from the scene's light spectra
    /// ([`Basis::adaptive`]): the part of their sum outside the visible bands' span, so
    /// that the light (UV included) is reconstructed exactly.
    Adaptive,
}

impl BasisKind {
    /// Parse `xyz`, `xyzu` or `x7`.
    pub fn from_name(name: &str) -> Result<Self> {
        match name.to_ascii_lowercase().as_str() {
            "xyz" => Ok(Self::Xyz),
            "xyzu" => Ok(Self::Xyzu),
            "x7" => Ok(Self::X7),
            "auto" => Ok(Self::Adaptive),
            _ => Err(Error::param("basis", format!("\"{name}\""), "one of xyz, xyzu, x7, auto")),
        }
    }

    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Xyz => "xyz",
            Self::Xyzu => "xyzu",
            Self::X7 => "x7",
            Self::Adaptive => "auto",
        }
    }
}

/// Reduction method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Dual-basis reduction, eq. 15.
    Ours,
    /// Normalised-basis reduction, eq. 7 (for comparison only).
    Naive,
}

impl Method {
    /// Parse `ours` or `naive`.
    pub fn from_name(name: &str) -> Result<Self> {
        match name.to_ascii_lowercase().as_str() {
            "ours" => Ok(Self::Ours),
            "naive" => Ok(Self::Naive),
            _ => Err(Error::param("method", format!("\"{name}\""), "one of ours, naive")),
        }
    }

    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ours => "ours",
            Self::Naive => "naive",
        }
    }
}

/// The paper's smoothstep S(λ; μ, σ) (appendix A).
pub fn smoothstep(lambda: f64, mu: f64, sigma: f64) -> f64 {
    let t = ((lambda - mu) / (2.0 * sigma) + 0.5).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// The UV band U(λ) (see the module docs).
pub fn u_band(lambda: f64) -> f64 {
    if !(lambda < U_END_NM) {
        return 0.0;
    }
    let t = (U_END_NM - lambda) / (U_END_NM - GRID_START_NM);
    U_PEAK * t * t
}

/// A transport basis sampled on the reduction grid.
#[derive(Debug, Clone)]
pub struct Basis {
    kind: BasisKind,
    observer: Observer,
    /// N×K band values (column k = band k).
    s: DMatrix<f64>,
    /// Quadrature weights (trapezoid), length N.
    w: DVector<f64>,
    /// N×K dual basis S (Sᵀ W S)⁻¹.
    dual: DMatrix<f64>,
    /// 3×K transfer matrix to XYZ.
    t: DMatrix<f64>,
    /// Condition number of the Gram matrix Sᵀ W S.
    condition: f64,
    /// `auto`: how many of its last bands are lights' residuals (0: x7's U).
    light_bands: usize,
}

/// The most light bands [`Basis::adaptive`] builds (K = 6 + this at most).
pub const MAX_LIGHT_BANDS: usize = 2;

/// Wavelengths of the reduction grid.
pub fn grid() -> Vec<f64> {
    let n = ((GRID_END_NM - GRID_START_NM) / GRID_STEP_NM).round() as usize;
    (0..=n).map(|i| GRID_START_NM + i as f64 * GRID_STEP_NM).collect()
}

/// The six visible bands of `x7` on the grid (appendix A): x̄ split at 500 nm and around
/// 590 nm, ȳ around 570 nm, z̄.
fn visible_x7(observer: Observer) -> Vec<Vec<f64>> {
    let c = cmf(observer);
    let (x, y, z) = (c.x(), c.y(), c.z());
    let split = |l: f64| smoothstep(l, 500.0, 2.0);
    let bands: [&dyn Fn(f64) -> f64; 6] = [
        &|l| x.eval(l) * (1.0 - split(l)),
        &|l| x.eval(l) * split(l) * smoothstep(l, 590.0, 60.0),
        &|l| x.eval(l) * split(l) * (1.0 - smoothstep(l, 590.0, 60.0)),
        &|l| y.eval(l) * smoothstep(l, 570.0, 60.0),
        &|l| y.eval(l) * (1.0 - smoothstep(l, 570.0, 60.0)),
        &|l| z.eval(l),
    ];
    let lambdas = grid();
    bands.iter().map(|f| lambdas.iter().map(|&l| f(l)).collect()).collect()
}

impl Basis {
    /// Build a basis from the CMFs of `observer` (the paper uses CIE 2006). `Adaptive`
    /// without lights: the bands of `x7`.
    pub fn new(kind: BasisKind, observer: Observer) -> Result<Self> {
        if kind == BasisKind::Adaptive {
            return Self::adaptive(observer, &[]);
        }
        let c = cmf(observer);
        let lambdas = grid();
        let (x, y, z) = (c.x(), c.y(), c.z());
        let mut bands: Vec<Vec<f64>> = match kind {
            BasisKind::X7 | BasisKind::Adaptive => visible_x7(observer),
            _ => vec![
                lambdas.iter().map(|&l| x.eval(l)).collect(),
                lambdas.iter().map(|&l| y.eval(l)).collect(),
                lambdas.iter().map(|&l| z.eval(l)).collect(),
            ],
        };
        if kind != BasisKind::Xyz {
            bands.push(lambdas.iter().map(|&l| u_band(l)).collect());
        }
        Self::from_bands(kind, observer, &bands)
    }

    /// The scene-adaptive basis: the six visible bands of `x7` (x̄₁, x̄₂, x̄₃, ȳ₁, ȳ₂, z̄)
    /// and up to [`MAX_LIGHT_BANDS`] light bands, each the part of a light spectrum (sampled
    /// on the reduction grid) outside the span of the bands before it (W-orthogonal
    /// residual): first the light whose residual is largest, then the sum of the others. A
    /// light in the span is reconstructed exactly by the dual basis, so a material lit
    /// directly by it reduces exactly (Sᵀ W 𝒫 L: every band's integral of the light it
    /// re-emits), its UV part included, whatever the lamp's shape: one or two distinct
    /// lights each exactly on its own (K = 7 or 8), more: the first exactly and the rest
    /// exactly together. Without lights, or with lights inside the visible span (residual
    /// below 1e-6 of their norm), the band is x7's U (the basis is x7); a second band is
    /// added only where it holds more than 1e-3 of its lights (below that it would cost
    /// K = 8 for nothing visible).
    pub fn adaptive(observer: Observer, lights: &[Vec<f64>]) -> Result<Self> {
        let lambdas = grid();
        let n = lambdas.len();
        for light in lights {
            if light.len() != n {
                return Err(Error::data(format!("adaptive basis: a light has {} samples, {n} expected", light.len())));
            }
            if light.iter().any(|v| !v.is_finite()) {
                return Err(Error::data("adaptive basis: a light spectrum is not finite"));
            }
        }
        let mut bands = visible_x7(observer);
        let mut remaining: Vec<Vec<f64>> = lights.to_vec();
        let mut light_bands = 0;
        while light_bands < MAX_LIGHT_BANDS && !remaining.is_empty() {
            let span = Self::from_bands(BasisKind::Adaptive, observer, &bands)?;
            let norm = |v: &[f64]| v.iter().zip(span.w.iter()).map(|(a, b)| a * a * b).sum::<f64>().sqrt();
            // r = L − S̃ Sᵀ W L (the dual basis reconstructs the projection onto the span)
            let residual = |l: &[f64]| -> Vec<f64> {
                let projection = span.up(&span.down_sampled(l));
                l.iter().zip(&projection).map(|(l, p)| l - p).collect()
            };
            let light = if light_bands + 1 == MAX_LIGHT_BANDS || remaining.len() == 1 {
                // the last band: the remaining lights together
                let total = (0..n).map(|i| remaining.iter().map(|l| l[i]).sum()).collect();
                remaining.clear();
                total
            } else {
                let outside: Vec<f64> = remaining.iter().map(|l| norm(&residual(l))).collect();
                let largest = (0..outside.len()).max_by(|&a, &b| outside[a].total_cmp(&outside[b])).unwrap_or(0);
                remaining.remove(largest)
            };
            let r = residual(&light);
            let threshold = if light_bands == 0 { 1e-6 } else { 1e-3 };
            if norm(&light) > 0.0 && norm(&r) > threshold * norm(&light) {
                // scaled to U's peak: coefficients of comparable size
                let peak = r.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
                bands.push(r.iter().map(|v| v * U_PEAK / peak).collect());
                light_bands += 1;
            }
        }
        if light_bands == 0 {
            bands.push(lambdas.iter().map(|&l| u_band(l)).collect());
        }
        Ok(Self { light_bands, ..Self::from_bands(BasisKind::Adaptive, observer, &bands)? })
    }

    /// How many of the last bands are built from lights ([`Basis::adaptive`]; 0: none).
    pub fn light_bands(&self) -> usize {
        self.light_bands
    }

    /// A basis from its bands sampled on the grid (x̄, ȳ, z̄ or the six split visible bands
    /// first, then bands outside the CMFs), its dual and its transfer to XYZ.
    fn from_bands(kind: BasisKind, observer: Observer, bands: &[Vec<f64>]) -> Result<Self> {
        let n = grid().len();
        let k = bands.len();
        let s = DMatrix::from_fn(n, k, |i, j| bands[j][i]);
        let w = DVector::from_fn(n, |i, _| if i == 0 || i == n - 1 { 0.5 * GRID_STEP_NM } else { GRID_STEP_NM });
        // band -> X, Y or Z (the visible bands sum to the CMFs; the others add nothing)
        let owner: &[usize] =
            if kind == BasisKind::X7 || kind == BasisKind::Adaptive { &[0, 0, 0, 1, 1, 2] } else { &[0, 1, 2] };
        let t = DMatrix::from_fn(3, k, |r, c| if c < owner.len() && owner[c] == r { 1.0 } else { 0.0 });
        let mut b =
            Self { kind, observer, s, w, dual: DMatrix::zeros(0, 0), t, condition: f64::INFINITY, light_bands: 0 };
        let gram = b.gram(&b.s);
        let eig = SymmetricEigen::try_new(gram.clone(), f64::EPSILON, max_iterations(k)).ok_or_else(|| {
            Error::data(format!("basis {}: the Gram matrix's eigenvalues did not converge", kind.name()))
        })?;
        let (mut lo, mut hi) = (f64::INFINITY, 0.0_f64);
        for e in eig.eigenvalues.iter() {
            lo = lo.min(*e);
            hi = hi.max(*e);
        }
        b.condition = if lo > 0.0 { hi / lo } else { f64::INFINITY };
        let inv = gram
            .cholesky()
            .ok_or_else(|| Error::data(format!("basis {}: bands are linearly dependent", kind.name())))?
            .inverse();
        b.dual = &b.s * inv;
        Ok(b)
    }

    /// Aᵀ W B for N-row matrices.
    fn gram(&self, a: &DMatrix<f64>) -> DMatrix<f64> {
        let wa = DMatrix::from_fn(a.nrows(), a.ncols(), |i, j| a[(i, j)] * self.w[i]);
        self.s.transpose() * wa
    }

    /// The basis kind.
    pub fn kind(&self) -> BasisKind {
        self.kind
    }

    /// The observer whose CMFs the bands come from.
    pub fn observer(&self) -> Observer {
        self.observer
    }

    /// Number of bands K.
    pub fn len(&self) -> usize {
        self.s.ncols()
    }

    /// Always false (a basis has at least three bands).
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Condition number of the Gram matrix Sᵀ W S.
    pub fn condition_number(&self) -> f64 {
        self.condition
    }

    /// The 3×K transfer matrix T (row major).
    pub fn transfer(&self) -> Vec<[f64; 3]> {
        (0..self.len()).map(|c| [self.t[(0, c)], self.t[(1, c)], self.t[(2, c)]]).collect()
    }

    /// Band values at the grid wavelengths (N×K, for tests and plots).
    pub fn band(&self, k: usize, lambda: f64) -> f64 {
        let i = ((lambda - GRID_START_NM) / GRID_STEP_NM).round();
        if i < 0.0 || i as usize >= self.s.nrows() || k >= self.len() {
            return 0.0;
        }
        self.s[(i as usize, k)]
    }

    /// Downsample a spectrum: c_k = ∫ f s_k dλ (eq. 8).
    pub fn down(&self, f: &dyn Fn(f64) -> f64) -> Vec<f64> {
        let lambdas = grid();
        let fw = DVector::from_fn(lambdas.len(), |i, _| f(lambdas[i]) * self.w[i]);
        (self.s.transpose() * fw).iter().copied().collect()
    }

    /// Downsample a spectrum sampled on the grid.
    pub fn down_sampled(&self, f: &[f64]) -> Vec<f64> {
        let fw = DVector::from_fn(f.len(), |i, _| f[i] * self.w[i]);
        (self.s.transpose() * fw).iter().copied().collect()
    }

    /// Upsample coefficients with the dual basis (eq. 10–11), evaluated on the grid.
    pub fn up(&self, c: &[f64]) -> Vec<f64> {
        let cv = DVector::from_column_slice(c);
        (&self.dual * cv).iter().copied().collect()
    }

    /// XYZ = T c.
    pub fn to_xyz(&self, c: &[f64]) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (r, o) in out.iter_mut().enumerate() {
            *o = (0..self.len()).map(|k| self.t[(r, k)] * c[k]).sum();
        }
        out
    }
}

/// What a reduction acts on: a material's spectral operator 𝒫 for light arriving at one
/// incidence, elastic albedo ρ(λ) on the diagonal plus reradiation density P(λi, λo),
/// nm⁻¹ (diffuse normalisation, the patch convention of [`crate::patch`]).
///
/// A value, not a trait: it is read off a [`Bispectral`] material ([`Operator::of`],
/// [`Operator::at`]) and may drop or replace the elastic part (transports that take it
/// from the renderer's own albedo). Fichet et al. reduce Lambertian materials only; an
/// angle-dependent model (quantum dots) is reduced per incidence cosine into a table.
pub struct Operator<'a> {
    elastic: Box<dyn Fn(f64) -> f64 + 'a>,
    density: Box<dyn Fn(f64, f64) -> f64 + 'a>,
    /// The density's factors on a grid, where it has them (Bispectral::density_factors).
    factors: Option<DensityFactors<'a>>,
}

type DensityFactors<'a> = Box<dyn Fn(&[f64]) -> Option<(Vec<f64>, Vec<f64>)> + 'a>;

impl<'a> Operator<'a> {
    /// An operator from its two parts.
    pub fn new(elastic: impl Fn(f64) -> f64 + 'a, density: impl Fn(f64, f64) -> f64 + 'a) -> Self {
        Operator { elastic: Box::new(elastic), density: Box::new(density), factors: None }
    }
    /// An operator without reradiation: the diagonal ρ(λ) alone.
    pub fn diagonal(elastic: impl Fn(f64) -> f64 + 'a) -> Self {
        let zeros = |l: &[f64]| Some((vec![0.0; l.len()], vec![0.0; l.len()]));
        Operator { factors: Some(Box::new(zeros)), ..Self::new(elastic, |_, _| 0.0) }
    }
    /// An operator whose density factors, P(λi, λo) = a(λi)·b(λo) for λi < λo and 0
    /// elsewhere (Bispectral::density_factors): reduced in O(N·K).
    pub fn factored(
        elastic: impl Fn(f64) -> f64 + 'a,
        a: impl Fn(f64) -> f64 + 'a,
        b: impl Fn(f64) -> f64 + 'a,
    ) -> Self {
        let (a, b) = (std::rc::Rc::new(a), std::rc::Rc::new(b));
        let (fa, fb) = (a.clone(), b.clone());
        let factors = move |l: &[f64]| Some((l.iter().map(|&x| fa(x)).collect(), l.iter().map(|&x| fb(x)).collect()));
        Operator {
            factors: Some(Box::new(factors)),
            ..Self::new(elastic, move |li, lo| if lo > li { a(li) * b(lo) } else { 0.0 })
        }
    }
    /// A material's operator for light along the normal.
    pub fn of<M: Bispectral + ?Sized>(material: &'a M) -> Self {
        Self::at(material, 1.0)
    }
    /// A material's operator for light arriving at incidence cosine `cos_i`.
    pub fn at<M: Bispectral + ?Sized>(material: &'a M, cos_i: f64) -> Self {
        Operator {
            factors: Some(Box::new(move |lambdas| material.density_factors(cos_i, lambdas))),
            ..Self::new(move |l| material.elastic_albedo(cos_i, l), move |li, lo| material.density(cos_i, li, lo))
        }
    }
    /// The reradiation alone (no diagonal).
    pub fn reradiation_only(self) -> Self {
        self.with_elastic(|_| 0.0)
    }
    /// The same reradiation with the diagonal `elastic`.
    pub fn with_elastic(self, elastic: impl Fn(f64) -> f64 + 'a) -> Self {
        Operator { elastic: Box::new(elastic), ..self }
    }
    /// Diagonal (elastic) albedo ρ(λ).
    pub fn elastic(&self, lambda: f64) -> f64 {
        (self.elastic)(lambda)
    }
    /// Reradiation density P(λi, λo), nm⁻¹.
    pub fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        (self.density)(lambda_i, lambda_o)
    }
    /// The density's factors on `lambdas` (Bispectral::density_factors), checked in size.
    fn grid_factors(&self, lambdas: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
        let n = lambdas.len();
        self.factors.as_ref().and_then(|f| f(lambdas)).filter(|(a, b)| a.len() == n && b.len() == n)
    }
    /// P(λi, λo) for every pair of `lambdas` into `out[i·n + o]`: from the factors where the
    /// density has them (a(λi)·b(λo), each evaluated once per wavelength), else per entry.
    fn density_grid(&self, lambdas: &[f64], out: &mut [f64]) {
        let n = lambdas.len();
        let factors = self.grid_factors(lambdas);
        for (i, column) in out.chunks_exact_mut(n).enumerate() {
            for (o, p) in column.iter_mut().enumerate() {
                *p = match &factors {
                    Some((a, b)) => {
                        if lambdas[o] > lambdas[i] {
                            a[i] * b[o]
                        } else {
                            0.0
                        }
                    }
                    None => self.density(lambdas[i], lambdas[o]),
                };
            }
        }
    }
}

/// A reduced K×K reradiation matrix.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Reduced {
    /// Basis name.
    pub basis: &'static str,
    /// Method name.
    pub method: &'static str,
    /// Rows of the matrix (acts on basis coefficients: c_o = M c_i).
    pub matrix: Vec<Vec<f64>>,
}

impl Reduced {
    /// c_o = M c_i.
    pub fn apply(&self, c: &[f64]) -> Vec<f64> {
        self.matrix.iter().map(|row| row.iter().zip(c).map(|(a, b)| a * b).sum()).collect()
    }
}

/// Discretise the operator 𝒫 on the grid as an N×N matrix acting on sampled spectra
/// (row λo, column λi; the diagonal holds ρ/Δλ-free values, the reradiation is weighted
/// by the λi quadrature weight).
fn operator(material: &Operator, basis: &Basis) -> DMatrix<f64> {
    let lambdas = grid();
    let n = lambdas.len();
    let mut m = DMatrix::zeros(n, n);
    // (column-major: entry (λo, λi) sits at i·n + o, as density_grid writes it)
    material.density_grid(&lambdas, m.as_mut_slice());
    for (i, mut column) in m.column_iter_mut().enumerate() {
        column *= basis.w[i];
        column[i] += material.elastic(lambdas[i]);
    }
    m
}

/// 𝒫·R (N×K) for a reduction's right factor R: with the density's factors (P = a(λi)·b(λo)
/// on λi < λo) as a running sum along the increasing grid, O(N·K); else through operator(),
/// O(N²·K) (200 distinct quantum-dot coatings spent most of their RGB load time there).
fn operator_times(material: &Operator, basis: &Basis, r: &DMatrix<f64>) -> DMatrix<f64> {
    let lambdas = grid();
    let Some((a, b)) = material.grid_factors(&lambdas) else {
        return &operator(material, basis) * r;
    };
    let (n, k) = r.shape();
    let mut out = DMatrix::zeros(n, k);
    let mut run = vec![0.0; k]; // Σ_{i < o} a_i·w_i·R[i, l]
    for o in 0..n {
        let e = material.elastic(lambdas[o]);
        for (l, s) in run.iter_mut().enumerate() {
            out[(o, l)] = e * r[(o, l)] + b[o] * *s;
            *s += a[o] * basis.w[o] * r[(o, l)];
        }
    }
    out
}

/// Reduce a material's reradiation to a K×K matrix in the given basis.
pub fn reduce(material: &Operator, basis: &Basis, method: Method) -> Reduced {
    let m = basis.gram(&operator_times(material, basis, &right(basis, method)));
    Reduced {
        basis: basis.kind.name(),
        method: method.name(),
        matrix: (0..m.nrows()).map(|r| (0..m.ncols()).map(|c| m[(r, c)]).collect()).collect(),
    }
}

/// The reduction's derivative with respect to each node value of a bilinear reradiation
/// table: for P(λi, λo) = Σ p_jk·h_j(λo)·h_k(λi) on λi ≤ λo (h the piecewise-linear hat
/// of a node on `lambda_o`, `lambda_i`, zero outside the grids; [`reduce`] is linear in
/// P), ∂M/∂p_jk = Sᵀ W 𝒫_jk R with 𝒫_jk that hat product's operator (no elastic part).
/// One K×K matrix per node, index j·n_i + k (λo row j, λi column k).
pub fn bilinear_jacobian(basis: &Basis, method: Method, lambda_i: &[f64], lambda_o: &[f64]) -> Vec<DMatrix<f64>> {
    let lambdas = grid();
    let r = right(basis, method);
    let k_len = basis.len();
    // each node's hat on the reduction grid: (first grid index, values)
    let hats = |g: &[f64]| -> Vec<(usize, Vec<f64>)> {
        (0..g.len())
            .map(|j| {
                let lo = if j > 0 { g[j - 1] } else { g[j] };
                let hi = if j + 1 < g.len() { g[j + 1] } else { g[j] };
                let first = lambdas.partition_point(|&l| l < lo);
                let values = lambdas[first..]
                    .iter()
                    .take_while(|&&l| l <= hi)
                    .map(|&l| match l.partial_cmp(&g[j]) {
                        Some(std::cmp::Ordering::Less) => (l - lo) / (g[j] - lo),
                        Some(std::cmp::Ordering::Greater) => (hi - l) / (hi - g[j]),
                        _ => 1.0,
                    })
                    .collect();
                (first, values)
            })
            .collect()
    };
    let (h_i, h_o) = (hats(lambda_i), hats(lambda_o));
    let mut out = vec![DMatrix::zeros(k_len, k_len); lambda_i.len() * lambda_o.len()];
    for (j, (o0, ho)) in h_o.iter().enumerate() {
        for (k, (i0, hi)) in h_i.iter().enumerate() {
            let m = &mut out[j * lambda_i.len() + k];
            for (di, &hk) in hi.iter().enumerate() {
                let i = i0 + di;
                if hk == 0.0 {
                    continue;
                }
                // 𝒫[o, i] = P(λi, λo)·w_i (operator()), row o weighted by W in the gram
                let wi = hk * basis.w[i];
                for (dj, &hj) in ho.iter().enumerate() {
                    let o = o0 + dj;
                    if o < i || hj == 0.0 {
                        continue;
                    }
                    let c = hj * wi * basis.w[o];
                    for a in 0..k_len {
                        let sa = basis.s[(o, a)] * c;
                        if sa != 0.0 {
                            for b in 0..k_len {
                                m[(a, b)] += sa * r[(i, b)];
                            }
                        }
                    }
                }
            }
        }
    }
    out
}

/// The right-hand factor R of a reduction Sᵀ W 𝒫 R: the dual basis S̃ (`ours`), or the
/// area-normalised bands (`naive`).
fn right(basis: &Basis, method: Method) -> DMatrix<f64> {
    match method {
        Method::Ours => basis.dual.clone(),
        Method::Naive => {
            // Our reading of eq. 6–7 (the extraction's S̄ᵀ 𝒫 S̄ cannot be meant literally:
            // with s̄ on the outgoing side c_o would not be a colour in the units of c_i).
            // The incoming side turns coefficients back into a spectrum, Σ_k c_k s̄_k with
            // s̄_k = s_k / ∫ s_k dλ (area norm); the outgoing side is the plain downsampling
            // of eq. 8. This reproduces the paper's naive rows of Table 1 (tested, ~0.2
            // ΔE00 off on average); an L² norm on both sides gives 15–19 ΔE00 where Table 1
            // has 10–15, and the area norm on both sides ~75.
            let norms: Vec<f64> = (0..basis.len())
                .map(|k| (0..basis.s.nrows()).map(|i| basis.s[(i, k)] * basis.w[i]).sum::<f64>())
                .collect();
            DMatrix::from_fn(basis.s.nrows(), basis.len(), |i, k| {
                if norms[k] > 0.0 {
                    basis.s[(i, k)] / norms[k]
                } else {
                    0.0
                }
            })
        }
    }
}

/// Colour of a lit patch through the reduced pipeline: `c_o = M down[I]`, `XYZ = T c_o`,
/// normalised so that the illuminant's own XYZ (`T down[I]`) has Y = 1. Returns
/// (xyz, white_xyz).
pub fn reduced_patch_xyz(reduced: &Reduced, basis: &Basis, illum: &dyn Spectral) -> Result<([f64; 3], [f64; 3])> {
    let c = basis.down(&|l| illum.eval(l));
    let white = basis.to_xyz(&c);
    let out = basis.to_xyz(&reduced.apply(&c));
    let (k, white, _) = normalise_patch(white, equal_energy_white(basis, illum))?;
    Ok((out.map(|v| v * k), white))
}

/// XYZ (basis CMFs, reduction grid) of a white diffuser under an equal-energy light
/// with `illum`'s radiant power over the grid: the reference of the radiant
/// normalisation ([`normalise_patch`]).
fn equal_energy_white(basis: &Basis, illum: &dyn Spectral) -> [f64; 3] {
    let lambdas = grid();
    let power: f64 = lambdas.iter().zip(basis.w.iter()).map(|(&l, w)| illum.eval(l) * w).sum();
    let width: f64 = basis.w.iter().sum();
    let c = cmf(basis.observer);
    let mut white = [0.0; 3];
    for (&l, w) in lambdas.iter().zip(basis.w.iter()) {
        let bar = [c.x().eval(l), c.y().eval(l), c.z().eval(l)];
        for r in 0..3 {
            white[r] += bar[r] * w * power / width;
        }
    }
    white
}

/// Colour of the same patch by spectral integration on the reduction grid with the
/// basis's own CMFs (the reference the reduction approximates), same normalisation.
pub fn spectral_patch_xyz(material: &Operator, basis: &Basis, illum: &dyn Spectral) -> Result<([f64; 3], [f64; 3])> {
    let lambdas = grid();
    let op = operator(material, basis);
    let i = DVector::from_fn(lambdas.len(), |k, _| illum.eval(lambdas[k]));
    let lo = &op * &i;
    let c = cmf(basis.observer);
    let (mut xyz, mut white) = ([0.0; 3], [0.0; 3]);
    for (k, &l) in lambdas.iter().enumerate() {
        let bar = [c.x().eval(l), c.y().eval(l), c.z().eval(l)];
        for r in 0..3 {
            xyz[r] += bar[r] * lo[k] * basis.w[k];
            white[r] += bar[r] * i[k] * basis.w[k];
        }
    }
    let (k, white, _) = normalise_patch(white, equal_energy_white(basis, illum))?;
    Ok((xyz.map(|v| v * k), white))
}

/// A family of matrices M_j (flattened, all of one length) written as
/// `M_j = Σ_t w[j][t]·B_t` with few terms: the truncated singular value decomposition of the
/// rows M_j. A direction-dependent reduced operator tabulated at cosines (fluo_qd's
/// microfacet lobe) is then, between nodes, Σ_t w_t(cos θ)·B_t with w_t linear between
/// the nodes' weights: per lane a few weights instead of whole matrices.
#[derive(Debug, Clone, PartialEq)]
pub struct LowRank {
    /// B_t, each as long as an M_j.
    pub basis: Vec<Vec<f64>>,
    /// `w[j][t]`, per node j.
    pub weights: Vec<Vec<f64>>,
    /// max_j max_i `|M_j,i − Σ_t w[j][t] B_t,i|` / max |M|: the error of the truncation.
    pub error: f64,
}

impl LowRank {
    /// The fewest terms (at most `max_rank`) whose relative error is ≤ `tolerance`, or, if
    /// none, `max_rank` terms (the caller reads `error`). An all-zero family has no terms.
    pub fn new(rows: &[Vec<f64>], max_rank: usize, tolerance: f64) -> Self {
        let (n, len) = (rows.len(), rows.first().map_or(0, Vec::len));
        let scale = rows.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
        if n == 0 || len == 0 || !(scale > 0.0) || rows.iter().any(|r| r.len() != len) {
            return Self { basis: Vec::new(), weights: vec![Vec::new(); n], error: 0.0 };
        }
        let x = DMatrix::from_fn(n, len, |j, i| rows[j][i]);
        let svd = SVD::try_new(x.clone(), true, true, f64::EPSILON, max_iterations(n.max(len)));
        let Some(SVD { u: Some(u), v_t: Some(v_t), singular_values }) = svd else {
            return Self { basis: Vec::new(), weights: vec![Vec::new(); n], error: f64::INFINITY };
        };
        let sigma = &singular_values;
        let mut order: Vec<usize> = (0..sigma.len()).collect();
        order.sort_by(|&a, &b| sigma[b].total_cmp(&sigma[a]));
        let mut best = None;
        for rank in 1..=max_rank.min(order.len()) {
            let terms = &order[..rank];
            let basis: Vec<Vec<f64>> =
                terms.iter().map(|&t| (0..len).map(|i| sigma[t] * v_t[(t, i)]).collect()).collect();
            let weights: Vec<Vec<f64>> = (0..n).map(|j| terms.iter().map(|&t| u[(j, t)]).collect()).collect();
            let mut error = 0.0f64;
            for j in 0..n {
                for i in 0..len {
                    let approx: f64 = (0..rank).map(|t| weights[j][t] * basis[t][i]).sum();
                    error = error.max((approx - x[(j, i)]).abs() / scale);
                }
            }
            let done = error <= tolerance;
            best = Some(Self { basis, weights, error });
            if done {
                break;
            }
        }
        best.unwrap_or(Self { basis: Vec::new(), weights: vec![Vec::new(); n], error: f64::INFINITY })
    }
}

/// Iteration cap of nalgebra's iterative decompositions (SVD, symmetric eigenvalues) for
/// an n×n problem: theirs is unbounded by default, and an iteration without exceptional
/// shifts can cycle forever on some matrices (a Schur decomposition once hung a render at
/// start). Converging problems take a few iterations per eigenvalue; past the cap the
/// caller takes its documented fallback.
fn max_iterations(n: usize) -> usize {
    100 * n.max(1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::{ciede2000, xyz_to_lab};
    use crate::models::jung::{JungMaterial, JungParams, Reflectance};
    use crate::spectrum::illuminant;

    fn identity() -> Operator<'static> {
        Operator::new(|_| 1.0, |_, _| 0.0)
    }

    #[test]
    fn factored_density_reduces_as_the_whole_operator() {
        // quantum dots' P = a(λi)·b(λo) on λi < λo: the running sum against 𝒫·R formed in full
        use crate::models::qd::{QdIndex, QdModel, QdParams, Substrate};
        let m = QdModel::new(
            QdParams { density: 0.8, ..QdParams::default() },
            QdIndex::CdSe,
            Substrate::Constant { eta: 0.27, k: 2.9 },
        )
        .unwrap();
        for b in all_bases() {
            for (cos, method) in [(1.0, Method::Ours), (0.3, Method::Ours), (0.7, Method::Naive)] {
                let op = Operator::at(&m, cos);
                let r = right(&b, method);
                let full = &operator(&op, &b) * &r;
                let fast = operator_times(&op, &b, &r);
                let scale = full.amax();
                assert!(scale > 0.0);
                assert!((&fast - &full).amax() <= 1e-12 * scale, "{} {cos}", b.kind.name());
                let reradiation = operator_times(&Operator::at(&m, cos).reradiation_only(), &b, &r);
                assert!(reradiation.amax() > 1e-3 * scale, "the reradiation is what is compared");
            }
        }
    }

    #[test]
    fn factored_operators_reduce_as_their_densities() {
        // a dye's P = c·Q·a(λi)·e(λo) (Operator::of, Operator::factored) and a diagonal alone,
        // against the same operators given by their density only (Operator::new: formed in full)
        let m = JungMaterial::new(
            Reflectance::Constant(0.6),
            JungParams { emission_peak: 540.0, stokes_shift: 90.0, concentration: 0.9, quantum_yield: 0.9 },
        )
        .unwrap();
        let f = &m.fluorescence;
        let plain = |l: f64| 0.3 + l * 1e-4;
        for b in all_bases() {
            for method in [Method::Ours, Method::Naive] {
                let r = right(&b, method);
                let pairs = [
                    (
                        Operator::of(&m),
                        Operator::new(|l| Bispectral::elastic_albedo(&m, 1.0, l), |li, lo| m.density(1.0, li, lo)),
                    ),
                    (
                        Operator::factored(plain, |l| f.absorption(l), |l| f.emission(l)),
                        Operator::new(plain, |li, lo| if lo > li { f.absorption(li) * f.emission(lo) } else { 0.0 }),
                    ),
                    (Operator::diagonal(plain), Operator::new(plain, |_, _| 0.0)),
                ];
                for (fast, full) in &pairs {
                    assert!(fast.grid_factors(&grid()).is_some() && full.grid_factors(&grid()).is_none());
                    let (x, y) = (operator_times(fast, &b, &r), operator_times(full, &b, &r));
                    assert!((&x - &y).amax() <= 1e-12 * y.amax(), "{}", b.kind.name());
                }
            }
        }
    }

    fn all_bases() -> Vec<Basis> {
        [BasisKind::Xyz, BasisKind::Xyzu, BasisKind::X7]
            .into_iter()
            .map(|k| Basis::new(k, Observer::Cie2006).unwrap())
            .collect()
    }

    #[test]
    fn identity_reduces_to_identity_with_ours_not_naive() {
        for b in all_bases() {
            let r = reduce(&identity(), &b, Method::Ours);
            for (i, row) in r.matrix.iter().enumerate() {
                for (j, v) in row.iter().enumerate() {
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((v - want).abs() < 1e-9, "{} [{i}][{j}] = {v}", b.kind().name());
                }
            }
            let n = reduce(&identity(), &b, Method::Naive);
            let off: f64 = (0..b.len())
                .flat_map(|i| (0..b.len()).map(move |j| (i, j)))
                .filter(|(i, j)| i != j)
                .map(|(i, j)| n.matrix[i][j].abs())
                .sum();
            assert!(off > 0.1, "naive should inject energy off the diagonal ({off})");
        }
    }

    #[test]
    fn dual_basis_is_biorthogonal() {
        for b in all_bases() {
            let g = b.gram(&b.dual);
            for i in 0..b.len() {
                for j in 0..b.len() {
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((g[(i, j)] - want).abs() < 1e-9);
                }
            }
            assert!(b.condition_number().is_finite());
        }
    }

    /// XYZ of the light a material re-emits under `light` (grid samples): exact, and
    /// through the basis (T · M · Sᵀ W L).
    fn single_bounce_xyz(op: &Operator, basis: &Basis, light: &[f64]) -> ([f64; 3], [f64; 3]) {
        let m = operator(op, basis);
        let out = &m * DVector::from_column_slice(light);
        let exact = basis.to_xyz(&basis.down_sampled(out.as_slice()));
        let r = reduce(op, basis, Method::Ours);
        let reduced = basis.to_xyz(&r.apply(&basis.down_sampled(light)));
        (exact, reduced)
    }

    #[test]
    fn adaptive_basis_reduces_direct_light_exactly() {
        let lambdas = grid();
        let gauss = |mu: f64, s: f64| lambdas.iter().map(move |&l| (-0.5 * ((l - mu) / s).powi(2)).exp());
        // a narrow 365 nm lamp, and the same with a dim D65 fill
        let lamp: Vec<f64> = gauss(365.0, 5.0).collect();
        let d65 = illuminant("D65").unwrap();
        let fill: Vec<f64> = lambdas.iter().map(|&l| 0.002 * d65.eval(l)).collect();
        // a brightener: absorbs 330-400 nm, re-emits around 440 nm; grey elastic part
        let brightener = Operator::new(
            |_| 0.5,
            |li: f64, lo: f64| {
                let a = (-0.5 * ((li - 360.0) / 20.0).powi(2)).exp();
                0.8 * a * (-0.5 * ((lo - 440.0) / 20.0).powi(2)).exp() / (20.0 * (2.0 * std::f64::consts::PI).sqrt())
            },
        );
        let x7 = Basis::new(BasisKind::X7, Observer::Cie1931).unwrap();
        let lab = |xyz: [f64; 3], white: f64| xyz_to_lab(xyz.map(|v| v / white), [0.95047, 1.0, 1.08883]);
        // a bright D65 sky with the lamp: two light bands, each light exact on its own
        let sky: Vec<f64> = lambdas.iter().map(|&l| 0.05 * d65.eval(l)).collect();
        let cases = [
            (vec![lamp.clone()], "lamp", 7),
            (vec![lamp.clone(), fill.clone()], "lamp + fill", 8),
            (vec![sky.clone(), lamp.clone()], "sky + lamp", 8),
            (vec![lamp.clone(), lamp.iter().map(|v| 3.0 * v).collect()], "lamp twice", 7),
        ];
        for (lights, name, k) in cases {
            let auto = Basis::adaptive(Observer::Cie1931, &lights).unwrap();
            assert_eq!((auto.len(), auto.kind(), auto.light_bands()), (k, BasisKind::Adaptive, k - 6), "{name}");
            let total: Vec<f64> = (0..lambdas.len()).map(|i| lights.iter().map(|l| l[i]).sum()).collect();
            for (i, light) in lights.iter().chain(std::iter::once(&total)).enumerate() {
                // each light (and their sum) is in the span: reconstructed exactly
                let back = auto.up(&auto.down_sampled(light));
                let peak = light.iter().fold(0.0_f64, |m, v| m.max(*v));
                assert!(back.iter().zip(light).all(|(a, b)| (a - b).abs() < 1e-9 * peak), "{name} light {i}");
                let (exact, reduced) = single_bounce_xyz(&brightener, &auto, light);
                let white = exact[1].max(1e-30) * 2.0;
                let de = ciede2000(lab(exact, white), lab(reduced, white));
                assert!(de < 1e-6, "{name} light {i}: auto ΔE00 {de}");
            }
            // x7's fixed U band misjudges the lamp's absorption
            let (exact, reduced) = single_bounce_xyz(&brightener, &x7, &total);
            let white = exact[1].max(1e-30) * 2.0;
            let de_x7 = ciede2000(lab(exact, white), lab(reduced, white));
            assert!(de_x7 > 1.0, "{name}: x7 ΔE00 {de_x7}");
        }
        // without lights (or with lights in the visible span) the basis is x7
        let plain = Basis::adaptive(Observer::Cie1931, &[]).unwrap();
        assert!((plain.s.clone() - x7.s.clone()).abs().max() < 1e-12);
        let visible: Vec<f64> = (0..lambdas.len()).map(|i| x7.s[(i, 3)] + 0.5 * x7.s[(i, 5)]).collect();
        let inside = Basis::adaptive(Observer::Cie1931, &[visible]).unwrap();
        assert!((inside.s.clone() - x7.s.clone()).abs().max() < 1e-12);
        assert!(Basis::adaptive(Observer::Cie1931, &[vec![1.0; 3]]).is_err());
        // RGB light has no light-band coefficient (exactly: band albedos divide by it)
        let d65_grid: Vec<f64> = lambdas.iter().map(|&l| d65.eval(l)).collect();
        let t = Transport::adaptive(&[lamp, d65_grid], Method::Ours).unwrap();
        assert!(t.white[6] == 0.0 && t.from_rgb[18..21].iter().all(|v| *v == 0.0), "{:?}", t.white);
    }

    #[test]
    fn bands_sum_to_the_cmfs() {
        let x7 = Basis::new(BasisKind::X7, Observer::Cie2006).unwrap();
        let c = cmf(Observer::Cie2006);
        for l in [400.0, 480.0, 499.0, 501.0, 560.0, 590.0, 650.0, 700.0] {
            let x = x7.band(0, l) + x7.band(1, l) + x7.band(2, l);
            let y = x7.band(3, l) + x7.band(4, l);
            assert!((x - c.x().eval(l)).abs() < 1e-12 && (y - c.y().eval(l)).abs() < 1e-12);
        }
    }

    #[test]
    fn u_band_matches_the_papers_file_when_present() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/cmf/xyzu_fichet2024.csv");
        let Ok(text) = std::fs::read_to_string(&path) else {
            eprintln!("skipping: {} not found", path.display());
            return;
        };
        let mut worst: f64 = 0.0;
        for line in text.lines() {
            let v: Vec<f64> = line.split(',').filter_map(|t| t.trim().parse().ok()).collect();
            if v.len() == 5 {
                worst = worst.max((u_band(v[0]) - v[4]).abs());
            }
        }
        assert!(worst < 1e-4, "U band differs from the paper's by {worst}");
    }

    #[test]
    fn non_fluorescent_material_is_exact_under_ours_for_smooth_light() {
        // A constant-albedo material is a multiple of the identity: exact in any basis.
        let m =
            JungMaterial::new(Reflectance::Constant(0.4), JungParams { concentration: 0.0, ..JungParams::default() })
                .unwrap();
        let d65 = illuminant("D65").unwrap();
        for b in all_bases() {
            let r = reduce(&Operator::of(&m), &b, Method::Ours);
            let (xyz, white) = reduced_patch_xyz(&r, &b, &d65).unwrap();
            let (sxyz, _) = spectral_patch_xyz(&Operator::of(&m), &b, &d65).unwrap();
            for k in 0..3 {
                assert!((xyz[k] - sxyz[k]).abs() < 1e-9, "{:?} vs {:?}", xyz, sxyz);
            }
            assert!((white[1] - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn ours_beats_naive_on_a_fluorescent_material() {
        let m = JungMaterial::new(
            Reflectance::Constant(0.3),
            JungParams { emission_peak: 540.0, stokes_shift: 90.0, concentration: 0.9, quantum_yield: 0.9 },
        )
        .unwrap();
        for name in ["D65", "A", "FL2"] {
            let light = illuminant(name).unwrap();
            for b in all_bases() {
                let (ref_xyz, white) = spectral_patch_xyz(&Operator::of(&m), &b, &light).unwrap();
                let lab_ref = xyz_to_lab(ref_xyz, white);
                let de = |method| {
                    let r = reduce(&Operator::of(&m), &b, method);
                    let (xyz, w) = reduced_patch_xyz(&r, &b, &light).unwrap();
                    ciede2000(xyz_to_lab(xyz, w), lab_ref)
                };
                let (ours, naive) = (de(Method::Ours), de(Method::Naive));
                assert!(ours < naive, "{name} {}: ours {ours} naive {naive}", b.kind().name());
                assert!(ours.is_finite() && ours < 6.0, "{name} {}: ours {ours}", b.kind().name());
            }
        }
    }

    #[test]
    fn low_rank_reconstructs_a_family_of_matrices() {
        // Rank 2 exactly: M_j = a_j·P + b_j·Q.
        let (p, q) = ([1.0, 2.0, 0.0, -1.0], [0.5, 0.0, 3.0, 1.0]);
        let rows: Vec<Vec<f64>> = (0..5)
            .map(|j| {
                let (a, b) = (1.0 + j as f64, (j as f64 * 0.7).sin());
                p.iter().zip(q).map(|(x, y)| a * x + b * y).collect()
            })
            .collect();
        let lr = LowRank::new(&rows, 3, 1e-12);
        assert_eq!(lr.basis.len(), 2);
        assert!(lr.error < 1e-12, "{}", lr.error);
        for (j, row) in rows.iter().enumerate() {
            for (i, v) in row.iter().enumerate() {
                let approx: f64 = (0..2).map(|t| lr.weights[j][t] * lr.basis[t][i]).sum();
                assert!((approx - v).abs() < 1e-12);
            }
        }
        // One term cannot hold it: the error of the best rank-1 truncation is reported.
        let one = LowRank::new(&rows, 1, 1e-12);
        assert_eq!(one.basis.len(), 1);
        assert!(one.error > 1e-3);
        // All zero: no terms.
        assert!(LowRank::new(&vec![vec![0.0; 4]; 3], 3, 1e-6).basis.is_empty());
    }
}
