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
//! reproduces the paper's naive rows of Table 1, see [`TABLE1_XYZ_NAIVE`]). It is kept for
//! comparison only; it does not map identity to identity.
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

use nalgebra::{DMatrix, DVector};

use crate::bispectral::normalise_patch;
use crate::spectrum::{cmf, Observer, Spectral};
use crate::{Error, Result};

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
}

impl BasisKind {
    /// Parse `xyz`, `xyzu` or `x7`.
    pub fn from_name(name: &str) -> Result<Self> {
        match name.to_ascii_lowercase().as_str() {
            "xyz" => Ok(Self::Xyz),
            "xyzu" => Ok(Self::Xyzu),
            "x7" => Ok(Self::X7),
            _ => Err(Error::param("basis", format!("\"{name}\""), "one of xyz, xyzu, x7")),
        }
    }

    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Xyz => "xyz",
            Self::Xyzu => "xyzu",
            Self::X7 => "x7",
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
}

/// Wavelengths of the reduction grid.
pub fn grid() -> Vec<f64> {
    let n = ((GRID_END_NM - GRID_START_NM) / GRID_STEP_NM).round() as usize;
    (0..=n).map(|i| GRID_START_NM + i as f64 * GRID_STEP_NM).collect()
}

impl Basis {
    /// Build a basis from the CMFs of `observer` (the paper uses CIE 2006).
    pub fn new(kind: BasisKind, observer: Observer) -> Result<Self> {
        let c = cmf(observer);
        let lambdas = grid();
        let n = lambdas.len();
        let bands: Vec<Box<dyn Fn(f64) -> f64>> = {
            let (x, y, z) = (c.x().clone(), c.y().clone(), c.z().clone());
            let (x1, x2, x3) = (x.clone(), x.clone(), x.clone());
            let (y1, y2) = (y.clone(), y.clone());
            let z2 = z.clone();
            match kind {
                BasisKind::Xyz | BasisKind::Xyzu => {
                    let mut v: Vec<Box<dyn Fn(f64) -> f64>> =
                        vec![Box::new(move |l| x.eval(l)), Box::new(move |l| y.eval(l)), Box::new(move |l| z.eval(l))];
                    if kind == BasisKind::Xyzu {
                        v.push(Box::new(u_band));
                    }
                    v
                }
                BasisKind::X7 => vec![
                    Box::new(move |l| x1.eval(l) * (1.0 - smoothstep(l, 500.0, 2.0))),
                    Box::new(move |l| x2.eval(l) * smoothstep(l, 500.0, 2.0) * smoothstep(l, 590.0, 60.0)),
                    Box::new(move |l| x3.eval(l) * smoothstep(l, 500.0, 2.0) * (1.0 - smoothstep(l, 590.0, 60.0))),
                    Box::new(move |l| y1.eval(l) * smoothstep(l, 570.0, 60.0)),
                    Box::new(move |l| y2.eval(l) * (1.0 - smoothstep(l, 570.0, 60.0))),
                    Box::new(move |l| z2.eval(l)),
                    Box::new(u_band),
                ],
            }
        };
        let k = bands.len();
        let s = DMatrix::from_fn(n, k, |i, j| bands[j](lambdas[i]));
        let w = DVector::from_fn(n, |i, _| if i == 0 || i == n - 1 { 0.5 * GRID_STEP_NM } else { GRID_STEP_NM });
        let t = match kind {
            BasisKind::Xyz => DMatrix::identity(3, 3),
            BasisKind::Xyzu => DMatrix::from_fn(3, 4, |r, c| if r == c { 1.0 } else { 0.0 }),
            BasisKind::X7 => {
                let owner = [0usize, 0, 0, 1, 1, 2]; // band -> X, Y or Z (U -> none)
                DMatrix::from_fn(3, 7, |r, c| if c < 6 && owner[c] == r { 1.0 } else { 0.0 })
            }
        };
        let mut b = Self { kind, observer, s, w, dual: DMatrix::zeros(0, 0), t, condition: f64::INFINITY };
        let gram = b.gram(&b.s);
        let eig = gram.clone().symmetric_eigen();
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

/// A material seen as a reradiation operator on spectra (diffuse normalisation, i.e.
/// the patch convention of [`crate::bispectral`]).
pub trait Reradiating {
    /// Diagonal (elastic) albedo ρ(λ).
    fn diagonal(&self, lambda: f64) -> f64;
    /// Reradiation density P(λi, λo), nm⁻¹ (zero for λo ≤ λi when there is no anti-Stokes part).
    fn density(&self, lambda_i: f64, lambda_o: f64) -> f64;
}

impl Reradiating for crate::jung::JungMaterial {
    fn diagonal(&self, lambda: f64) -> f64 {
        self.elastic_albedo(lambda)
    }
    fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        self.fluorescence.reradiation(lambda_i, lambda_o)
    }
}

impl Reradiating for crate::jung::JungFluorescence {
    fn diagonal(&self, lambda: f64) -> f64 {
        self.elastic_factor(lambda)
    }
    fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        self.reradiation(lambda_i, lambda_o)
    }
}

/// The quantum-dot coating's spectral operator at one microfacet incidence cosine:
/// diagonal R_tot(θ, λ), reradiation P(θ, λi, λo) (Benamira & Pattanaik eqs. 23, 27).
/// Fichet et al. reduce Lambertian materials only; an angle-dependent model is reduced
/// per incidence angle into a table (see [`crate::ffi`]'s reduced models).
pub struct QdAtAngle<'a>(pub &'a crate::qd::QdModel, pub f64);

impl Reradiating for QdAtAngle<'_> {
    fn diagonal(&self, lambda: f64) -> f64 {
        self.0.r_tot(self.1, lambda)
    }
    fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        self.0.reradiation_fresnel(self.1, lambda_i, lambda_o)
    }
}

/// For patch colorimetry and single reductions, angle-dependent models are taken at
/// normal incidence.
impl Reradiating for crate::bispectral::Model {
    fn diagonal(&self, lambda: f64) -> f64 {
        match self {
            crate::bispectral::Model::Jung(m) => m.diagonal(lambda),
            crate::bispectral::Model::Qd(m) => QdAtAngle(m, 1.0).diagonal(lambda),
            crate::bispectral::Model::Matrix(m) => Reradiating::diagonal(m, lambda),
            crate::bispectral::Model::Gmm(m) => Reradiating::diagonal(m, lambda),
        }
    }
    fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        match self {
            crate::bispectral::Model::Jung(m) => m.density(lambda_i, lambda_o),
            crate::bispectral::Model::Qd(m) => QdAtAngle(m, 1.0).density(lambda_i, lambda_o),
            crate::bispectral::Model::Matrix(m) => Reradiating::density(m, lambda_i, lambda_o),
            crate::bispectral::Model::Gmm(m) => Reradiating::density(m, lambda_i, lambda_o),
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
fn operator(material: &dyn Reradiating, basis: &Basis) -> DMatrix<f64> {
    let lambdas = grid();
    let n = lambdas.len();
    DMatrix::from_fn(n, n, |o, i| {
        let p = material.density(lambdas[i], lambdas[o]) * basis.w[i];
        if o == i {
            p + material.diagonal(lambdas[o])
        } else {
            p
        }
    })
}

/// Reduce a material's reradiation to a K×K matrix in the given basis.
pub fn reduce(material: &dyn Reradiating, basis: &Basis, method: Method) -> Reduced {
    let op = operator(material, basis);
    let m = match method {
        Method::Ours => {
            // Sᵀ W 𝒫 S̃
            let ps = &op * &basis.dual;
            basis.gram(&ps)
        }
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
            let sbar = DMatrix::from_fn(basis.s.nrows(), basis.len(), |i, k| {
                if norms[k] > 0.0 {
                    basis.s[(i, k)] / norms[k]
                } else {
                    0.0
                }
            });
            basis.gram(&(&op * &sbar))
        }
    };
    Reduced {
        basis: basis.kind.name(),
        method: method.name(),
        matrix: (0..m.nrows()).map(|r| (0..m.ncols()).map(|c| m[(r, c)]).collect()).collect(),
    }
}

/// Colour of a lit patch through the reduced pipeline: c_o = M down[I], XYZ = T c_o,
/// normalised so that the illuminant's own XYZ (T down[I]) has Y = 1. Returns
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
pub fn spectral_patch_xyz(
    material: &dyn Reradiating,
    basis: &Basis,
    illum: &dyn Spectral,
) -> Result<([f64; 3], [f64; 3])> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::{ciede2000, xyz_to_lab};
    use crate::jung::{JungMaterial, JungParams, Reflectance};
    use crate::spectrum::illuminant;

    struct Identity;
    impl Reradiating for Identity {
        fn diagonal(&self, _: f64) -> f64 {
            1.0
        }
        fn density(&self, _: f64, _: f64) -> f64 {
            0.0
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
            let r = reduce(&Identity, &b, Method::Ours);
            for (i, row) in r.matrix.iter().enumerate() {
                for (j, v) in row.iter().enumerate() {
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((v - want).abs() < 1e-9, "{} [{i}][{j}] = {v}", b.kind().name());
                }
            }
            let n = reduce(&Identity, &b, Method::Naive);
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
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/cmf/xyzu_fichet2024.csv");
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
            let r = reduce(&m, &b, Method::Ours);
            let (xyz, white) = reduced_patch_xyz(&r, &b, &d65).unwrap();
            let (sxyz, _) = spectral_patch_xyz(&m, &b, &d65).unwrap();
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
                let (ref_xyz, white) = spectral_patch_xyz(&m, &b, &light).unwrap();
                let lab_ref = xyz_to_lab(ref_xyz, white);
                let de = |method| {
                    let r = reduce(&m, &b, method);
                    let (xyz, w) = reduced_patch_xyz(&r, &b, &light).unwrap();
                    ciede2000(xyz_to_lab(xyz, w), lab_ref)
                };
                let (ours, naive) = (de(Method::Ours), de(Method::Naive));
                assert!(ours < naive, "{name} {}: ours {ours} naive {naive}", b.kind().name());
                assert!(ours.is_finite() && ours < 6.0, "{name} {}: ours {ours}", b.kind().name());
            }
        }
    }
}

/// A transport basis prepared for a renderer whose working space is Mitsuba's linear
/// sRGB (CIE 1931 based): coefficients are normalised like Mitsuba's spectrum → RGB
/// conversion (c = Sᵀ W L / ∫ȳ), and the maps between RGB and coefficients are
/// precomputed.
#[derive(Debug, Clone)]
pub struct Transport {
    /// `rgb`, `xyzu` or `x7` (`rgb` transports sRGB itself with the XYZ reduction
    /// converted by eq. 16).
    pub name: &'static str,
    /// The basis (CIE 1931 bands).
    pub basis: Basis,
    /// Method of the reductions.
    pub method: Method,
    /// 3×K: linear sRGB = output · c.
    pub output: Vec<f64>,
    /// K×3: coefficients of light given as linear sRGB (upsampled with the dual XYZ basis).
    pub from_rgb: Vec<f64>,
    /// K×3 and the white response, for turning an RGB albedo into a per-band one:
    /// a_k = (from_rgb · a)_k / (from_rgb · 1)_k.
    pub white: Vec<f64>,
}

impl Transport {
    /// Prepare `rgb`, `xyzu` or `x7` transport.
    pub fn new(name: &str, method: Method) -> Result<Self> {
        let kind = match name.to_ascii_lowercase().as_str() {
            "rgb" | "xyz" => BasisKind::Xyz,
            "xyzu" => BasisKind::Xyzu,
            "x7" => BasisKind::X7,
            _ => return Err(Error::param("basis", format!("\"{name}\""), "one of rgb, xyzu, x7")),
        };
        let label =
            if name.eq_ignore_ascii_case("rgb") || name.eq_ignore_ascii_case("xyz") { "rgb" } else { kind.name() };
        let basis = Basis::new(kind, Observer::Cie1931)?;
        let m = nalgebra::Matrix3::from_fn(|r, c| crate::mitsuba::XYZ_TO_SRGB[r][c]);
        let minv = m.try_inverse().ok_or_else(|| Error::data("XYZ→sRGB matrix is singular"))?;
        // XYZ basis (for upsampling RGB light) in the same normalisation.
        let xyz = Basis::new(BasisKind::Xyz, Observer::Cie1931)?;
        // K×3 map: c_K = Sᵀ W S̃_xyz · xyz, xyz = M⁻¹ rgb   (coefficients of a spectrum are
        // scaled by 1/∫ȳ on both sides, so the map is scale-free)
        let proj = basis.gram(&xyz.dual); // K×3 (Sᵀ W S̃_xyz)
        let from_rgb_m = &proj * DMatrix::from_fn(3, 3, |r, c| minv[(r, c)]);
        let t = &basis.t;
        let out_m = DMatrix::from_fn(3, 3, |r, c| m[(r, c)]) * t; // 3×K
        let (output, from_rgb) = if label == "rgb" {
            (DMatrix::<f64>::identity(3, 3), DMatrix::<f64>::identity(3, 3))
        } else {
            (out_m, from_rgb_m)
        };
        let white = &from_rgb * DVector::from_element(3, 1.0);
        Ok(Self {
            name: label,
            method,
            output: output.transpose().iter().copied().collect(),
            from_rgb: from_rgb.transpose().iter().copied().collect(),
            white: white.iter().copied().collect(),
            basis,
        })
    }

    /// Number of transported channels K.
    pub fn len(&self) -> usize {
        if self.name == "rgb" {
            3
        } else {
            self.basis.len()
        }
    }

    /// Always false.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The reduced reradiation (or full operator) of a material for this transport,
    /// K×K row major. `rgb` uses the XYZ reduction converted with eq. 16.
    pub fn reduce(&self, material: &dyn Reradiating) -> Vec<f64> {
        let r = reduce(material, &self.basis, self.method);
        let k = self.basis.len();
        let mx = DMatrix::from_fn(k, k, |i, j| r.matrix[i][j]);
        let out = if self.name == "rgb" {
            let m = DMatrix::from_fn(3, 3, |i, j| crate::mitsuba::XYZ_TO_SRGB[i][j]);
            let minv = m.clone().try_inverse().unwrap_or_else(|| DMatrix::identity(3, 3));
            m * mx * minv
        } else {
            mx
        };
        out.transpose().iter().copied().collect()
    }

    /// Coefficients of a light spectrum in this transport (Mitsuba's normalisation:
    /// a unit spectrum has Y = 1; `rgb` gives its linear sRGB).
    pub fn coefficients(&self, f: &dyn Fn(f64) -> f64) -> Vec<f64> {
        let ybar = cmf(Observer::Cie1931).y().integrate();
        let c: Vec<f64> = self.basis.down(f).into_iter().map(|v| v / ybar).collect();
        if self.name == "rgb" {
            let xyz = self.basis.to_xyz(&c);
            crate::mitsuba::XYZ_TO_SRGB.iter().map(|row| row[0] * xyz[0] + row[1] * xyz[1] + row[2] * xyz[2]).collect()
        } else {
            c
        }
    }
}

/// Only the reradiation of a material (its diagonal removed), for transports that
/// take the elastic part from the renderer's own RGB albedo.
pub struct ReradiationOnly<'a>(pub &'a dyn Reradiating);

impl Reradiating for ReradiationOnly<'_> {
    fn diagonal(&self, _: f64) -> f64 {
        0.0
    }
    fn density(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        self.0.density(lambda_i, lambda_o)
    }
}

#[cfg(test)]
mod transport_tests {
    use super::*;

    #[test]
    fn rgb_transport_maps_white_to_white_and_matches_mitsuba_conversion() {
        for name in ["rgb", "xyzu", "x7"] {
            let t = Transport::new(name, Method::Ours).unwrap();
            let k = t.len();
            // light given in RGB, through from_rgb then output, comes back unchanged
            let rgb = [0.3, 0.5, 0.9];
            let c: Vec<f64> = (0..k).map(|i| (0..3).map(|j| t.from_rgb[i * 3 + j] * rgb[j]).sum()).collect();
            let back: Vec<f64> = (0..3).map(|r| (0..k).map(|i| t.output[r * k + i] * c[i]).sum()).collect();
            for j in 0..3 {
                assert!((back[j] - rgb[j]).abs() < 1e-9, "{name}: {back:?}");
            }
            // a spectrum's coefficients give Mitsuba's sRGB of it
            let f = |l: f64| 0.5 + 0.4 * ((l - 400.0) / 80.0).sin();
            let c = t.coefficients(&f);
            let out: Vec<f64> = (0..3).map(|r| (0..k).map(|i| t.output[r * k + i] * c[i]).sum()).collect();
            let want = crate::mitsuba::spectrum_to_srgb(f);
            for j in 0..3 {
                // the grids' trapezoid end weights differ at 360 nm
                assert!((out[j] - want[j]).abs() < 1e-5, "{name}: {out:?} vs {want:?}");
            }
            // identity material -> identity matrix
            struct Id;
            impl Reradiating for Id {
                fn diagonal(&self, _: f64) -> f64 {
                    1.0
                }
                fn density(&self, _: f64, _: f64) -> f64 {
                    0.0
                }
            }
            let m = t.reduce(&Id);
            for i in 0..k {
                for j in 0..k {
                    assert!((m[i * k + j] - if i == j { 1.0 } else { 0.0 }).abs() < 1e-9);
                }
            }
        }
    }
}

/// Illuminants of Fichet et al.'s Table 1, in its column order.
pub const TABLE1_ILLUMINANTS: [&str; 7] = ["A", "E", "D60", "D65", "FL1", "FL2", "HP5"];
/// The paper's Table 1 row "XYZU Ours" (average ΔE2000 over their database).
pub const TABLE1_XYZU_OURS: [f64; 7] = [3.86, 3.23, 3.36, 3.33, 1.04, 0.52, 2.43];
/// The paper's Table 1 row "XYZ Ours".
pub const TABLE1_XYZ_OURS: [f64; 7] = [3.92, 5.02, 3.88, 3.96, 1.14, 0.62, 2.48];
/// The paper's Table 1 row "XYZ Naive".
pub const TABLE1_XYZ_NAIVE: [f64; 7] = [10.11, 9.73, 12.77, 12.88, 14.92, 10.88, 10.57];
/// The paper's Table 1 row "XYZU Naive".
pub const TABLE1_XYZU_NAIVE: [f64; 7] = [10.56, 11.20, 13.43, 13.40, 15.18, 11.51, 11.22];

/// One row of [`table1`]: a method and basis, ΔE2000 per illuminant averaged over the
/// materials, and per material.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Table1Row {
    /// `ours` or `naive`.
    pub method: &'static str,
    /// `xyz`, `xyzu` or `x7`.
    pub basis: &'static str,
    /// Mean over materials, per illuminant (in [`TABLE1_ILLUMINANTS`] order).
    pub mean: Vec<f64>,
    /// Mean over the seven illuminants.
    pub overall: f64,
    /// Per material (same order as the input), per illuminant.
    pub per_material: Vec<Vec<f64>>,
}

/// Fichet et al.'s Table 1 for the given materials: ΔE2000 (CIE 2006 observer,
/// reference white: the illuminant) between each reduced patch colour and the spectral
/// one, for naive/ours × XYZ/XYZU/x7 under A, E, D60, D65, FL1, FL2, HP5.
pub fn table1(materials: &[&dyn Reradiating]) -> Result<Vec<Table1Row>> {
    use crate::colour::{ciede2000, xyz_to_lab};
    let lights: Vec<crate::spectrum::RegularSpectrum> =
        TABLE1_ILLUMINANTS.iter().map(|n| crate::spectrum::illuminant(n)).collect::<Result<_>>()?;
    let mut rows = Vec::new();
    for method in [Method::Naive, Method::Ours] {
        for kind in [BasisKind::Xyz, BasisKind::Xyzu, BasisKind::X7] {
            let basis = Basis::new(kind, Observer::Cie2006)?;
            let mut per_material = Vec::new();
            for m in materials {
                let r = reduce(*m, &basis, method);
                let des = lights
                    .iter()
                    .map(|light| {
                        let (xyz, w) = reduced_patch_xyz(&r, &basis, light)?;
                        let (sxyz, sw) = spectral_patch_xyz(*m, &basis, light)?;
                        Ok(ciede2000(xyz_to_lab(xyz, w), xyz_to_lab(sxyz, sw)))
                    })
                    .collect::<Result<Vec<f64>>>()?;
                per_material.push(des);
            }
            let n = per_material.len().max(1) as f64;
            let mean: Vec<f64> =
                (0..lights.len()).map(|j| per_material.iter().map(|d| d[j]).sum::<f64>() / n).collect();
            let overall = mean.iter().sum::<f64>() / mean.len() as f64;
            rows.push(Table1Row { method: method.name(), basis: kind.name(), mean, overall, per_material });
        }
    }
    Ok(rows)
}

/// One row of [`saturated_report`]: a saturated fluorescent material under one light,
/// through one transport basis.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SaturatedRow {
    /// The material (see [`SATURATED_CASES`]).
    pub case: &'static str,
    /// Transport basis (`rgb`, `xyzu`, `x7`).
    pub basis: &'static str,
    /// CIE illuminant.
    pub illuminant: &'static str,
    /// Luminance of the reduced patch over the spectral one (1 is exact); None where the
    /// spectral patch is black (below [`SATURATED_MIN_Y`] of the white).
    pub luminance_ratio: Option<f64>,
    /// The same for the reradiated light alone (elastic part removed on both sides).
    pub fluorescence_ratio: Option<f64>,
    /// ΔE2000 between the two (reference white: the illuminant).
    pub delta_e: f64,
}

/// The saturated materials of [`saturated_report`]: name, constant reflectance and the
/// `fluo_jung` dye. A pure green and a pure red emitter (black base, every absorbed
/// photon re-emitted) and a UV optical brightener on white paper (absorbs at ~370 nm,
/// emits blue), the cases where a 3- or 4-band transport is least faithful.
pub const SATURATED_CASES: [(&str, f64, crate::jung::JungParams); 3] = [
    (
        "green emitter",
        0.0,
        crate::jung::JungParams { emission_peak: 520.0, stokes_shift: 40.0, concentration: 1.0, quantum_yield: 1.0 },
    ),
    (
        "red emitter",
        0.0,
        crate::jung::JungParams { emission_peak: 610.0, stokes_shift: 60.0, concentration: 1.0, quantum_yield: 1.0 },
    ),
    (
        "UV brightener",
        0.8,
        crate::jung::JungParams { emission_peak: 440.0, stokes_shift: 80.0, concentration: 0.5, quantum_yield: 0.9 },
    ),
];

/// Illuminants of [`saturated_report`]: daylight, incandescent, a fluorescent lamp and
/// [`UV_LAMP`], a narrow 365 nm "blacklight".
pub const SATURATED_ILLUMINANTS: [&str; 4] = ["D65", "A", "FL2", UV_LAMP];

/// Luminance (relative to the white) below which a patch counts as black in
/// [`saturated_report`], and no ratio is formed.
pub const SATURATED_MIN_Y: f64 = 1e-4;

/// Name of the narrow UV lamp of [`saturated_report`]: a Gaussian at 365 nm, σ = 5 nm.
pub const UV_LAMP: &str = "UV365";

/// A light of [`saturated_report`] by name (a CIE illuminant or [`UV_LAMP`]).
fn saturated_light(name: &str) -> Result<crate::spectrum::RegularSpectrum> {
    if name == UV_LAMP {
        let values = grid().iter().map(|&l| (-0.5 * ((l - 365.0) / 5.0).powi(2)).exp()).collect();
        return crate::spectrum::RegularSpectrum::new(GRID_START_NM, GRID_STEP_NM, values);
    }
    crate::spectrum::illuminant(name)
}

/// Saturated fluorescence through reduced RGB transport, as `fluo_path` renders it in
/// `scalar_rgb` (a patch facing a spectrally defined light: c = coefficients of the
/// light, linear sRGB = O · M · c), against the spectral patch colour (Mitsuba's own
/// spectrum → sRGB conversion of the reradiated spectrum), for every transport basis
/// with the `ours` reduction.
pub fn saturated_report() -> Result<Vec<SaturatedRow>> {
    saturated_rows(&SATURATED_CASES, &SATURATED_ILLUMINANTS)
}

/// [`saturated_report`] for given materials (name, constant reflectance, dye) and lights.
pub fn saturated_rows(
    cases: &[(&'static str, f64, crate::jung::JungParams)],
    illuminants: &[&'static str],
) -> Result<Vec<SaturatedRow>> {
    use crate::colour::{ciede2000, xyz_to_lab};
    use crate::mitsuba::{spectrum_to_srgb, XYZ_TO_SRGB};
    let minv = crate::colour::mat_inv(&XYZ_TO_SRGB).ok_or_else(|| Error::data("XYZ→sRGB matrix is singular"))?;
    let to_xyz = |rgb: [f64; 3]| crate::colour::mat_vec(&minv, rgb);
    let lambdas = grid();
    let weights: Vec<f64> = (0..lambdas.len())
        .map(|k| if k == 0 || k + 1 == lambdas.len() { 0.5 * GRID_STEP_NM } else { GRID_STEP_NM })
        .collect();
    let transports =
        ["rgb", "xyzu", "x7"].iter().map(|b| Transport::new(b, Method::Ours)).collect::<Result<Vec<_>>>()?;
    let ratio = |got: f64, want: f64| (want.abs() >= SATURATED_MIN_Y).then(|| got / want);
    let mut rows = Vec::new();
    for &(case, reflectance, params) in cases {
        let material = crate::jung::JungMaterial::new(crate::jung::Reflectance::Constant(reflectance), params)?;
        for &name in illuminants {
            let light = saturated_light(name)?;
            let i: Vec<f64> = lambdas.iter().map(|&l| light.eval(l)).collect();
            let shifted = |lo: f64| -> f64 {
                lambdas.iter().zip(&i).zip(&weights).map(|((&li, &v), &w)| material.density(li, lo) * v * w).sum()
            };
            // Reference white: the light itself, or for the UV lamp (which the observer
            // hardly sees) an equal-energy light of the same radiant power.
            let white = if name == UV_LAMP {
                let power: f64 = i.iter().zip(&weights).map(|(v, w)| v * w).sum();
                let span = GRID_END_NM - GRID_START_NM;
                to_xyz(spectrum_to_srgb(|_| power / span))
            } else {
                to_xyz(spectrum_to_srgb(|l| light.eval(l)))
            };
            let scale = 1.0 / white[1];
            let white = white.map(|v| v * scale);
            let fluorescent = to_xyz(spectrum_to_srgb(shifted)).map(|v| v * scale);
            let elastic = to_xyz(spectrum_to_srgb(|l| material.diagonal(l) * light.eval(l))).map(|v| v * scale);
            let reference = [0, 1, 2].map(|r| elastic[r] + fluorescent[r]);
            for t in &transports {
                let k = t.len();
                let c = t.coefficients(&|l| light.eval(l));
                let patch = |mm: &[f64]| {
                    let co: Vec<f64> = (0..k).map(|r| (0..k).map(|j| mm[r * k + j] * c[j]).sum()).collect();
                    let rgb: Vec<f64> = (0..3).map(|r| (0..k).map(|j| t.output[r * k + j] * co[j]).sum()).collect();
                    to_xyz([rgb[0], rgb[1], rgb[2]]).map(|v| v * scale)
                };
                let got = patch(&t.reduce(&material));
                let got_fluorescent = patch(&t.reduce(&ReradiationOnly(&material)));
                rows.push(SaturatedRow {
                    case,
                    basis: t.name,
                    illuminant: name,
                    luminance_ratio: ratio(got[1], reference[1]),
                    fluorescence_ratio: ratio(got_fluorescent[1], fluorescent[1]),
                    delta_e: ciede2000(xyz_to_lab(got, white), xyz_to_lab(reference, white)),
                });
            }
        }
    }
    Ok(rows)
}

#[cfg(test)]
mod saturated_tests {
    use super::*;

    fn row<'a>(rows: &'a [SaturatedRow], case: &str, light: &str, basis: &str) -> &'a SaturatedRow {
        rows.iter().find(|r| r.case == case && r.illuminant == light && r.basis == basis).unwrap()
    }

    #[test]
    fn a_material_without_fluorescence_is_exact_in_every_basis() {
        // Concentration 0: no dye, the elastic part alone (a grey 0.6): every basis must
        // reproduce the spectral patch (the reference path is Mitsuba's spectrum → sRGB).
        let grey = crate::jung::JungParams { concentration: 0.0, ..Default::default() };
        let rows = saturated_rows(&[("grey", 0.6, grey)], &["D65", "A", "FL2"]).unwrap();
        assert_eq!(rows.len(), 9);
        for r in &rows {
            assert!((r.luminance_ratio.unwrap() - 1.0).abs() < 2e-3 && r.delta_e < 0.05, "{r:?}");
        }
    }

    #[test]
    fn the_report_shows_what_each_basis_can_carry() {
        let rows = saturated_report().unwrap();
        assert_eq!(rows.len(), SATURATED_CASES.len() * SATURATED_ILLUMINANTS.len() * 3);
        assert!(rows.iter().all(|r| r.luminance_ratio.is_none_or(f64::is_finite) && r.delta_e.is_finite()));
        // rgb has no UV band: a brightener's reradiation under daylight all but vanishes,
        // while the UV bases carry most of it.
        assert!(row(&rows, "UV brightener", "D65", "rgb").fluorescence_ratio.unwrap() < 0.05);
        for b in ["xyzu", "x7"] {
            assert!(row(&rows, "UV brightener", "D65", b).fluorescence_ratio.unwrap() > 0.5, "{b}");
            // Under a narrow 365 nm lamp one UV band averages the brightener's absorption
            // over 300-400 nm: its glow comes out ~5x too dark (what fluo_path warns of).
            let uv = row(&rows, "UV brightener", UV_LAMP, b).fluorescence_ratio.unwrap();
            assert!(uv > 0.1 && uv < 0.35, "{b}: {uv}");
        }
        // Emitters that do not absorb at 365 nm are black under the lamp: no ratio.
        assert!(row(&rows, "green emitter", UV_LAMP, "x7").luminance_ratio.is_none());
        // x7 splits the visible range finely enough for a narrow green emitter under
        // daylight and incandescent light (within 20 %), where 3-4 bands lose a third.
        for light in ["D65", "A"] {
            let x7 = row(&rows, "green emitter", light, "x7").luminance_ratio.unwrap();
            let rgb = row(&rows, "green emitter", light, "rgb").luminance_ratio.unwrap();
            assert!((x7 - 1.0).abs() < 0.2 && (x7 - 1.0).abs() < (rgb - 1.0).abs(), "{light}: x7 {x7} rgb {rgb}");
        }
    }
}
