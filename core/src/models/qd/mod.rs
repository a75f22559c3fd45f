//! Quantum-dot coated microfacet BBRRDF (Benamira & Pattanaik 2023), plus the QD
//! absorption/emission cross sections for volumes (their sec. 4.1).
//!
//! # Quantum-dot band (paper sec. 3)
//! Brus equation (eqs. 1–3), with R the dot radius and Table 1 constants:
//!
//! ```text
//! E_abs = E_gap + E_coul + E_conf                                   (eq. 1)
//! E_coul = −1.8 e² / (4π ε0 εr R),  E_conf = h² (me + mh) / (8 R² me mh)   (eq. 2)
//! λQD = h c / E_abs                                                 (eq. 3)
//! Sλ  = (h c / (kB T)) · δλ² / λQD²                                 (eq. 6)
//! ```
//!
//! The emission peak is λQD + Sλ (eq. 5 and eq. 10; eq. 25 prints λQD − Sλ, a slip:
//! the Stokes shift moves emission to longer wavelengths, see shared/papers/README.md).
//!
//! # Thin-film QD coating (sec. 4.2), with our reading of each equation
//! At a microfacet with cos θ = ω·m (light and view make the same angle with m):
//!
//! ```text
//! α(θ,λ)  = ρ λ² / (2π² R² n_env² cos θ)                             (eq. 17)
//! S0      = −i (2π R n_env/λ)³ (m² − n_env²)/(m² + 2 n_env²),  Ss = S0,
//! Sp      = S0 cos(π − 2θ)                                          (eq. 18)
//! r_s,p   = −α S_s,p / (1 + α)                                       (eq. 16)
//! R_spe   = ½(|r_s|² + |r_p|²),  T_spe = 1 − R_spe                   (eq. 19)
//! ```
//!
//! α/(1 + α) is evaluated as ρλ²/(ρλ² + 2π²R²n²cos θ), finite at grazing incidence
//! (α → ∞ gives r → −S) and exactly 0 for ρ = 0.
//!
//! Absorption of one pass through the film (eqs. 20–21). **Reading:** eq. 20 prints
//! the Beer–Lambert *transmittance* exp(−4πk l/λ) as the absorption; with ρ = 0 (l = 0)
//! that would absorb everything. We use the absorbed fraction 1 − exp(−4πk l/λ):
//!
//! ```text
//! l = 2Rρ / cos θt,  sin θt = n_env sin θ / n_QD(λ)
//! A_bulk(λ) = 1 − exp(−4π k_QD(λ) l / λ)
//! A_tf(λ)   = A_bulk(λ) + β G(λ, λQD, δλ)   if λ ≤ λQD,   2β G(λ, λQD, δλ) otherwise,
//! β = A_bulk(λQD)                    (continuity at λQD), clamped to ≤ 1
//! ```
//!
//! Multiple scattering between film and substrate of Fresnel reflectance R(θ, λ)
//! (eqs. 22–24): R_tot = R_spe + T²(1−A)²R / (1 − R R_spe),
//! A_tot = T A + T A R T (1−A) / (1 − R R_spe). These are an exact energy balance
//! (R_tot + A_tot + substrate absorption = 1), so R_tot + A_tot ≤ 1.
//!
//! Emission (eqs. 25–27). **Reading:** taken literally, F = R_tot + A_tot(λi) E_tot(λo)
//! with γ(θ) = (Q/I) ∫A_tot dλ (eq. 26) re-emits Q·A_tot(λi)·∫A_tot dλ per unit
//! excitation, which exceeds A_tot(λi) as soon as ∫A_tot dλ > 1 nm: energy would be
//! created. E_tot(θ, λo) = γ(θ) L(λo) is the *spectrum emitted under equal-energy
//! light*; the bispectral matrix consistent with it divides by the absorbed total:
//!
//! ```text
//! P(θ, λi, λo) = A_tot(θ,λi) · E_tot(θ,λo) / ∫A_tot(θ,λ)dλ = Q · A_tot(θ,λi) · L(λo) / I
//! L = logistic(λo; λQD + Sλ, δλ/2) (eq. 30),  I = Λ(λmax) − Λ(λmin) (eqs. 13, 31)
//! F(θ, λi, λo) = δ(λi − λo) R_tot(θ, λi) + P(θ, λi, λo) · [λo > λi]          (eq. 27)
//! ```
//!
//! so ∫ E_tot dλo = Q ∫A_tot dλi (eq. 26's energy balance) and, per excitation
//! wavelength, re-emitted ≤ Q A_tot. No anti-Stokes emission (hypothesis of sec. 3.1):
//! the part of the logistic below λi is not emitted (not renormalised), which keeps
//! ∫P dλo ≤ Q A_tot. Q is read as an energy yield (the photon-energy factor λi/λo ≤ 1
//! is not applied, as in `fluo_jung`).
//!
//! Microfacet BBRRDF (eq. 28) with Mitsuba's conventions (values include cos θo):
//! f·cos θo = D(h) G(ωi, ωo) F(ωi·h, λi, λo) / (4 cos θi), D and Smith G exactly as
//! Mitsuba's `MicrofacetDistribution` (Beckmann with its rational G1, or GGX).
//!
//! # Parameters
//! | name            | symbol | unit | valid range             | default |
//! |-----------------|--------|------|-------------------------|---------|
//! | `radius`        | R      | nm   | [1, 5]                  | 2.2     |
//! | `width`         | δλ     | nm   | [0.01, 100]             | 15      |
//! | `quantum_yield` | Q      | 1    | [0, 1]                  | 0.8     |
//! | `density`       | ρ      | 1    | [0, 1]                  | 0.5     |
//! | `ext_ior`       | n_env  | 1    | [1, 3]                  | 1.000277|
//! | `lambda_min/max`| λmin/max | nm | 200 ≤ min < max ≤ 1200 | 300/830 |
//! | `alpha`         | α      | 1    | [0, 4] (0 → 1e-4)       | 0.1     |
//! | `distribution`  |        |      | beckmann, ggx           | beckmann|
//! | `table_cos_nodes` | rows of the tables | 1 | [2, 1025]       | 33      |
//! | `table_step`    | base λ step of the tables | nm | [0.05, 50] | 1       |
//! | Table 1 constants (`gap_energy` … `temperature`) | | SI | finite, > 0 | CdSe |
//!
//! `alpha` = 0 is clamped to [`MIN_ALPHA`] as Mitsuba does. The substrate is a
//! [`Substrate`] (conductor η + ik relative to the environment, η ≥ 0, k ≥ 0; a
//! dielectric is k = 0), the dot index a [`QdIndex`].
//!
//! # Complex index of CdSe
//! Default m_QD(λ): the model dielectric function of Ninomiya & Adachi, "Optical
//! properties of cubic and hexagonal CdSe", J. Appl. Phys. 78, 4681 (1995), cubic
//! CdSe, parameters of their Table III (E0, E0+Δ0 edges with a discrete exciton
//! series, E1/E1+Δ1 damped oscillators, E2 damped harmonic oscillator, ε∞).
//! Tabulated once at 0.5 nm over [`CDSE_TABLE_RANGE_NM`]; a test compares it with the
//! refractiveindex.info table of the same paper in `../shared/data/ior/`.
//!
//! # Precomputation (per material)
//! A_tot(θ_j, λ_k) on [`COS_NODES`] rows uniform in cos θ and a λ grid of steps ≤ 1 nm
//! over [λmin, λmax] (defaults: `table_cos_nodes` and `table_step` set both per material),
//! ≤ δλ/8 within ±[`GAUSS_CUTOFF`]·δλ of λQD, uniform between those ends and λQD (at most
//! four uniform segments: the renderer finds a cell by arithmetic), with its running
//! integral: this gives γ(θ), the shift albedo and an exact inverse-CDF sampler of
//! λi | λo (piecewise-linear density of the row nearest cos θi). Memory, with the
//! coating terms below: (3 · rows + 2) · nodes · 8 B + rows · 8 B + 8 · nodes B:
//! 33 × 532 nodes, 434 KB with the defaults ([`QdModel::table_bytes`]; more nodes only
//! for δλ < 8 nm). Time: about 2–5 ms per material on one core, plus
//! about 10 ms once per process for the CdSe table (`fluo qd` prints both).
//!
//! Wavelength sampling needs λi before the direction is known (fluo_path picks
//! wavelengths first), so the proposal uses θ = θi: exact for smooth surfaces, an
//! unbiased proposal otherwise (its support does not depend on θ).
//!
//! The coating terms are baked on the same grid: |S0|²(λ_k) (R_spe's λ factor),
//! A_bulk(θ_j, λ_k) (the `expm1` of eq. 20) and β(θ_j). Per call, [`QdModel::coating`]
//! interpolates them (linear in λ, and in cos θ between rows) and evaluates the rest
//! exactly: R_spe's cos θ factors, the Gaussian of A_tf, the substrate's Fresnel
//! reflectance; outside [λmin, λmax] it uses the formulas ([`QdModel::coating_exact`]).
//! Measured against them at four points of the parameter box (CdSe; test
//! `baked_coating_matches_the_formulas`): |ΔR_tot|, |ΔA_tot| ≤ 9e-5 (R = 5 nm, ρ = 1;
//! 1.1e-5 by default), R_spe within 1e-4 of its value, from the CdSe index's 0.5 nm
//! kinks between 1 nm nodes. The λ cell is found from equal buckets over the grid (two
//! per node), bisecting only inside the few buckets that the refinement near λQD crowds.
//!
//! # Numerical notes
//! * The Gaussian quantum-absorption peak is cut at ±[`GAUSS_CUTOFF`]·δλ
//!   (exp(−100) ≈ 4e−44), so the absorption support is exact and tabulated.
//! * R_spe is clamped to [0, 1] (near a plasmon resonance of user-supplied spectra
//!   |m²−n²|/|m²+2n²| is unbounded); A_tf to [0, 1]; 1 − R R_spe ≥ [`MIN_DENOMINATOR`].
//! * cos θt: if n_QD < n_env total internal reflection makes l infinite: the film
//!   then absorbs fully where k > 0 (guarded, no division by zero).
//!
//! # Layout
//! `band` (Table 1 constants, Brus equation, line shapes, λ grid), `index` (CdSe and
//! tabulated dot indices, Rayleigh cross sections), `volume` ([`QdVolume`]) and
//! `microfacet` ([`Microfacet`], [`Substrate`]); this file holds the coating itself
//! ([`QdModel`]). Every public item is re-exported here.
//!
//! # References
//! A. Benamira, S. Pattanaik, "A Microfacet Model for Specular Fluorescent Surfaces
//! and Fluorescent Volume Rendering using Quantum Dots", EGSR 2023.
//! C. A. Leatherdale et al., J. Phys. Chem. B 106, 7619 (2002) (eq. 7).
//! C. F. Bohren, D. R. Huffman, "Absorption and Scattering of Light by Small
//! Particles", Wiley 1983/2008 (eqs. 7, 18).
//! S. Ninomiya, S. Adachi, J. Appl. Phys. 78, 4681 (1995) (CdSe index).

mod band;
mod index;
mod medium;
mod microfacet;
mod volume;

use std::f64::consts::PI;
use std::fmt;
use std::sync::OnceLock;

use crate::error::check_range;
use crate::Result;

use band::{check_lambda_range, cut_gaussian, lambda_grid, logistic_survival, LambdaIndex};
pub use band::{
    gaussian, logistic, logistic_cdf, QdBand, QdConstants, BAND_RANGE_NM, GAUSS_CUTOFF, LAMBDA_RANGE_NM,
    MAX_STOKES_SHIFT_NM, RADIUS_RANGE_NM, TABLE_REFINE, TABLE_STEP_NM, TABLE_STEP_RANGE_NM, WIDTH_RANGE_NM,
};
pub use index::{
    cdse_dielectric_function, cdse_refractive_index, local_field_factor, rayleigh_absorption_cross_section_nm2,
    rayleigh_scattering_cross_section_nm2, Complex, QdIndex, CDSE_TABLE_RANGE_NM, HC_EV_NM,
};
pub use medium::{QdMedium, QdMediumParams, CHLOROFORM_IOR, CONCENTRATION_RANGE_UM, HOST_IOR_RANGE, PER_M_PER_UM_NM2};
pub use microfacet::{fresnel_conductor, Distribution, Microfacet, Substrate, MIN_ALPHA};
pub use volume::QdVolume;

/// Rows of the A_tot table, uniform in cos θ over [0, 1] (default of `table_cos_nodes`).
pub const COS_NODES: usize = 33;
/// Valid range of `table_cos_nodes`.
pub const COS_NODES_RANGE: (usize, usize) = (2, 1025);
/// Smallest accepted 1 − R·R_spe (only reached with R = R_spe = 1).
pub const MIN_DENOMINATOR: f64 = 1e-12;

/// User parameters of the coating (see the module table).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QdParams {
    /// Dot radius R, nm.
    pub radius_nm: f64,
    /// Width δλ of the absorption/emission bands, nm.
    pub width_nm: f64,
    /// Quantum yield Q.
    pub quantum_yield: f64,
    /// Coating density ρ.
    pub density: f64,
    /// Index of the environment n_env.
    pub ext_ior: f64,
    /// Lower end of the emission normalisation/integration range, nm.
    pub lambda_min_nm: f64,
    /// Upper end, nm.
    pub lambda_max_nm: f64,
    /// Microfacet distribution.
    pub distribution: Distribution,
    /// Roughness α.
    pub alpha: f64,
    /// Table 1 constants.
    pub constants: QdConstants,
    /// Rows of the A_tot tables, uniform in cos θ (accuracy/memory knob).
    pub cos_nodes: usize,
    /// Base λ step of the tables, nm (accuracy/memory knob; refined near λQD regardless).
    pub table_step_nm: f64,
}

impl Default for QdParams {
    fn default() -> Self {
        Self {
            radius_nm: 2.2,
            width_nm: 15.0,
            quantum_yield: 0.8,
            density: 0.5,
            ext_ior: 1.000_277,
            lambda_min_nm: 300.0,
            lambda_max_nm: 830.0,
            distribution: Distribution::Beckmann,
            alpha: 0.1,
            constants: QdConstants::default(),
            cos_nodes: COS_NODES,
            table_step_nm: TABLE_STEP_NM,
        }
    }
}

/// Coating quantities at one (θ, λ) (eqs. 16–21).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coating {
    /// Specular reflectance of the film, R_spe.
    pub r_spe: f64,
    /// Its transmittance, T_spe = 1 − R_spe.
    pub t_spe: f64,
    /// Absorption of one pass, A_tf.
    pub a_tf: f64,
}

impl Coating {
    /// R_tot (eq. 23) over a substrate of reflectance `r`.
    pub fn r_tot(&self, r: f64) -> f64 {
        let den = (1.0 - r * self.r_spe).max(MIN_DENOMINATOR);
        let pass = self.t_spe * (1.0 - self.a_tf);
        self.r_spe + pass * pass * r / den
    }
    /// A_tot (eq. 24) over a substrate of reflectance `r`.
    pub fn a_tot(&self, r: f64) -> f64 {
        let den = (1.0 - r * self.r_spe).max(MIN_DENOMINATOR);
        let ta = self.t_spe * self.a_tf;
        ta + ta * r * self.t_spe * (1.0 - self.a_tf) / den
    }
}

/// Precomputed A_tot(θ_j, λ_k) and its running integral along λ, and the coating terms
/// on the same grid.
#[derive(Debug, Clone, PartialEq)]
struct Tables {
    /// Cell lookup on the model's λ nodes.
    index: LambdaIndex,
    /// Row-major [COS_NODES][lambda.len()].
    a_tot: Vec<f64>,
    cdf: Vec<f64>,
    /// |S0|² = x⁶ |(m² − n²)/(m² + 2n²)|² at the λ nodes (eq. 18).
    s0_sq: Vec<f64>,
    /// A_bulk(θ_j, λ_k), same layout as `a_tot` (eq. 20).
    a_bulk: Vec<f64>,
    /// β(θ_j) = A_bulk(θ_j, λQD) (eq. 21).
    beta: Vec<f64>,
}

/// A QD-coated microfacet material (validated; its tables baked when first read).
#[derive(Debug, Clone, PartialEq)]
pub struct QdModel {
    params: QdParams,
    band: QdBand,
    index: QdIndex,
    substrate: Substrate,
    microfacet: Microfacet,
    /// Logistic scale δλ / 2.
    scale: f64,
    /// I = Λ(λmax) − Λ(λmin).
    norm: f64,
    /// The tables' λ nodes, nm.
    lambda: Vec<f64>,
    /// The tables of the Rust evaluation, baked when first read: a renderer that reads
    /// [`Self::jit_tables`] alone never needs them (0.4 MB a coating; 200 coatings' load).
    tables: OnceLock<Tables>,
    /// Excitation support, or `None` if the coating never re-emits: from the tables, or
    /// from [`Self::jit_tables`] where its rows hold the tables' ones.
    excitation: OnceLock<Option<(f64, f64)>>,
}

/// The tables the vectorised variants interpolate ([`QdModel::jit_tables`]).
#[derive(Debug, Clone, PartialEq)]
pub struct JitTables {
    /// λ nodes, nm (strictly increasing).
    pub lambda: Vec<f64>,
    /// Rows, at cos θ = j/(rows − 1).
    pub rows: usize,
    /// A_tot, row major `[rows][lambda]`.
    pub a_tot: Vec<f64>,
    /// Its running integral along λ, nm.
    pub cdf: Vec<f64>,
    /// The coating's R_spe, `[rows][lambda]`.
    pub r_spe: Vec<f64>,
    /// (T_spe (1 − A_tf))², `[rows][lambda]`.
    pub pass: Vec<f64>,
    /// The smooth surface's R_tot over this model's substrate ([`QdModel::r_tot`]),
    /// `[rows][lambda]`.
    pub r_tot: Vec<f64>,
    /// R_spe at the requested extra wavelengths, `[rows][extra]`.
    pub extra_r_spe: Vec<f64>,
    /// pass at the requested extra wavelengths, `[rows][extra]`.
    pub extra_pass: Vec<f64>,
    /// The emission e(λo | λi) = logistic(λo; peak, scale)/norm for λo > λi within
    /// [λmin, λmax] ([`QdModel::emission_given`], with [`band::logistic`]): its peak, nm...
    pub emission_peak_nm: f64,
    /// ... its scale, nm...
    pub emission_scale_nm: f64,
    /// ... and I = Λ(λmax) − Λ(λmin).
    pub emission_norm: f64,
    /// Excitation support, or `None` if the coating never re-emits.
    pub excitation: Option<(f64, f64)>,
}

/// The `fluo_qd` parameters that take a texture ([`check_param_value`]). A textured
/// `alpha` bakes one model per distinct roughness (at most [`TEXTURE_MAX_ALPHAS`]).
pub const TEXTURABLE_PARAMS: [&str; 4] = ["radius", "density", "quantum_yield", "alpha"];

/// Valid range of the microfacet roughness `alpha` (0 is clamped to 1e-4 by the shim).
pub const ALPHA_RANGE: (f64, f64) = (0.0, 4.0);

/// Nodes of the density grid on which a textured `fluo_qd` bakes its models when the
/// `density` texture has more distinct values than this (otherwise the models are baked
/// at the texture's own values, exact at every texel). A hit between two nodes mixes the
/// two models with linear weights. Measured against the exact model at the cell centres
/// (test `texture_grid_interpolation_error`, R = 2.2 nm, CdSe on gold, reradiated XYZ at
/// normal incidence under equal-energy light, relative to the exact Y): ≤
/// [`TEXTURE_GRID_MAX_ERROR`] with 9 nodes (0.18 % with 33, 0.09 % with 65).
///
/// The radius has no grid: mixing the models of two radii moves the emission band's
/// weight between their peaks rather than moving the peak, 50 % / 13 % / 5.8 % off in
/// XYZ at the cell centres of 9 / 33 / 65 nodes over R ∈ [1.5, 4] nm (same test). A
/// radius texture is baked at its own values, at most [`TEXTURE_MAX_RADII`] of them; a
/// filtered lookup between two texels of different radii mixes their two models, as
/// two inks side by side reradiate.
pub const TEXTURE_GRID_NODES: usize = 9;

/// Bound on the measured density-grid error of [`TEXTURE_GRID_NODES`] (measured 0.0073).
pub const TEXTURE_GRID_MAX_ERROR: f64 = 0.008;

/// Most distinct radii a `radius` texture may hold (each radius bakes one model per
/// density node: about 0.44 MB with the default tables).
pub const TEXTURE_MAX_RADII: usize = 16;

/// Most distinct roughnesses an `alpha` texture may hold. The reradiation's microfacet
/// lobe is baked into each model, so every roughness multiplies the (radius, density)
/// grid; a hit's reradiation takes the model of the nearest roughness level (its elastic
/// lobe uses the hit's exact roughness).
pub const TEXTURE_MAX_ALPHAS: usize = 4;

/// Check one value of a textured `fluo_qd` parameter on its own, as every texel (or
/// constituent value) of a parameter texture is checked at load: `radius` in
/// [`RADIUS_RANGE_NM`], `density` and `quantum_yield` in [0, 1], `alpha` in [`ALPHA_RANGE`].
pub fn check_param_value(name: &str, value: f64) -> Result<()> {
    match name {
        "radius" => check_range(name, value, RADIUS_RANGE_NM.0, RADIUS_RANGE_NM.1).map(|_| ()),
        "density" | "quantum_yield" => check_range(name, value, 0.0, 1.0).map(|_| ()),
        "alpha" => check_range(name, value, ALPHA_RANGE.0, ALPHA_RANGE.1).map(|_| ()),
        _ => Err(crate::Error::param("parameter", format!("\"{name}\""), TEXTURABLE_PARAMS.join(", "))),
    }
}

/// The running integral along λ (trapezoids) at node `k` of the table row being pushed into
/// `values` (row major, earlier rows complete) and `cdf`, whose value there is `v`.
fn running(lambda: &[f64], k: usize, values: &[f64], cdf: &[f64], v: f64) -> f64 {
    match (k, values.last(), cdf.last()) {
        (1.., Some(&prev), Some(&acc)) => acc + 0.5 * (lambda[k] - lambda[k - 1]) * (v + prev),
        _ => 0.0,
    }
}

impl QdModel {
    /// Validate and bake.
    pub fn new(params: QdParams, index: QdIndex, substrate: Substrate) -> Result<Self> {
        let band = QdBand::new(&params.constants, params.radius_nm, params.width_nm)?;
        check_range("quantum_yield", params.quantum_yield, 0.0, 1.0)?;
        check_range("density", params.density, 0.0, 1.0)?;
        check_range("ext_ior", params.ext_ior, 1.0, 3.0)?;
        check_lambda_range((params.lambda_min_nm, params.lambda_max_nm))?;
        check_range("alpha", params.alpha, ALPHA_RANGE.0, ALPHA_RANGE.1)?;
        check_range("table_cos_nodes", params.cos_nodes as f64, COS_NODES_RANGE.0 as f64, COS_NODES_RANGE.1 as f64)?;
        check_range("table_step", params.table_step_nm, TABLE_STEP_RANGE_NM.0, TABLE_STEP_RANGE_NM.1)?;
        index.validate()?;
        substrate.validate()?;
        let microfacet = Microfacet { kind: params.distribution, alpha: params.alpha.max(MIN_ALPHA) };
        let scale = 0.5 * params.width_nm;
        let norm = logistic_cdf(params.lambda_max_nm, band.emission_peak_nm, scale)
            - logistic_cdf(params.lambda_min_nm, band.emission_peak_nm, scale);
        let lambda = lambda_grid((params.lambda_min_nm, params.lambda_max_nm), &band, params.table_step_nm);
        Ok(Self {
            params,
            band,
            index,
            substrate,
            microfacet,
            scale,
            norm,
            lambda,
            tables: OnceLock::new(),
            excitation: OnceLock::new(),
        })
    }

    /// Every node (cos θ_j = j/(rows − 1), λ_k) of a table, row by row: `node(j, k, coating,
    /// substrate reflectance, A_bulk)` by the formulas ([`Self::coating_exact`],
    /// [`Self::substrate_reflectance`], [`Self::bulk_absorption`]), what depends on λ alone
    /// (the dot's index, |S0|², the substrate's η, k) evaluated once per node; returns |S0|²
    /// at the nodes and β(θ_j) = A_bulk(θ_j, λQD).
    fn for_nodes(
        &self,
        rows: usize,
        lambda: &[f64],
        mut node: impl FnMut(usize, usize, &Coating, f64, f64),
    ) -> (Vec<f64>, Vec<f64>) {
        let cos = |j: usize| j as f64 / (rows - 1) as f64;
        let m_l: Vec<Complex> = lambda.iter().map(|&l| self.index.eval(l)).collect();
        let s0_sq: Vec<f64> = lambda.iter().zip(&m_l).map(|(&l, &m)| self.s0_sq_with(l, m)).collect();
        let eta_k: Vec<(f64, f64)> = lambda.iter().map(|&l| self.substrate.eta_k(l)).collect();
        let beta: Vec<f64> = (0..rows).map(|j| self.bulk_absorption(cos(j), self.band.lambda_qd_nm)).collect();
        for (j, &beta_j) in beta.iter().enumerate() {
            let c = cos(j);
            for (k, &l) in lambda.iter().enumerate() {
                let bulk = self.bulk_absorption_with(c, l, m_l[k]);
                let co = self.coating_with(c, l, || s0_sq[k], || self.film_absorption_with(l, || beta_j, bulk));
                node(j, k, &co, fresnel_conductor(c.clamp(0.0, 1.0), eta_k[k].0, eta_k[k].1), bulk);
            }
        }
        (s0_sq, beta)
    }

    /// The excitation support, `None` for a coating that never re-emits, else from A_tot
    /// tables ([rows][λ] on the model's grid, read only then) whose rows `step`·j are the
    /// tables' rows j: the nodes where any row absorbs, widened to the neighbouring nodes.
    fn support<'a>(&'a self, a_tot: impl FnOnce() -> &'a [f64], step: usize) -> Option<(f64, f64)> {
        if !(self.is_fluorescent_params() && self.norm > 0.0) {
            return None;
        }
        let (a_tot, n, lambda) = (a_tot(), self.lambda.len(), &self.lambda);
        let any = |k: usize| (0..self.params.cos_nodes).any(|j| a_tot[j * step * n + k] > 0.0);
        let first = (0..n).find(|&k| any(k))?;
        let last = (0..n).rev().find(|&k| any(k))?;
        Some((lambda[first.saturating_sub(1)], lambda[(last + 1).min(n - 1)]))
    }

    /// The tables, baked at the first call.
    fn tables(&self) -> &Tables {
        self.tables.get_or_init(|| self.bake())
    }

    /// Excitation support, or `None` if the coating never re-emits.
    fn excitation(&self) -> Option<(f64, f64)> {
        *self.excitation.get_or_init(|| self.support(|| &self.tables().a_tot, 1))
    }

    fn bake(&self) -> Tables {
        let lambda = &self.lambda;
        let n = lambda.len();
        let rows = self.params.cos_nodes;
        let mut a_bulk = Vec::with_capacity(rows * n);
        let mut a_tot: Vec<f64> = Vec::with_capacity(rows * n);
        let mut cdf = Vec::with_capacity(rows * n);
        let (s0_sq, beta) = self.for_nodes(rows, lambda, |_, k, co, r, bulk| {
            a_bulk.push(bulk);
            let a = co.a_tot(r);
            cdf.push(running(lambda, k, &a_tot, &cdf, a));
            a_tot.push(a);
        });
        Tables { index: LambdaIndex::new(lambda), a_tot, cdf, s0_sq, a_bulk, beta }
    }

    fn is_fluorescent_params(&self) -> bool {
        self.params.density > 0.0 && self.params.quantum_yield > 0.0
    }

    /// The parameters.
    pub fn params(&self) -> &QdParams {
        &self.params
    }
    /// λQD, Stokes shift, emission peak.
    pub fn band(&self) -> &QdBand {
        &self.band
    }
    /// The microfacet distribution (α clamped to [`MIN_ALPHA`]).
    pub fn microfacet(&self) -> &Microfacet {
        &self.microfacet
    }
    /// Whether the coating re-emits at all.
    pub fn is_fluorescent(&self) -> bool {
        self.excitation().is_some()
    }
    /// Memory held by the precomputed tables, bytes.
    pub fn table_bytes(&self) -> usize {
        let t = self.tables();
        8 * (self.lambda.len() + t.a_tot.len() + t.cdf.len() + t.s0_sq.len() + t.a_bulk.len() + t.beta.len())
            + 4 * t.index.len()
    }
    /// Number of λ nodes of the tables.
    pub fn table_nodes(&self) -> usize {
        self.lambda.len()
    }
    /// The λ nodes of the tables, nm.
    pub fn table_lambda(&self) -> &[f64] {
        &self.lambda
    }

    /// m_QD(λ).
    pub fn qd_index(&self, lambda_nm: f64) -> Complex {
        self.index.eval(lambda_nm)
    }

    /// Substrate Fresnel reflectance R(θ, λ).
    pub fn substrate_reflectance(&self, cos_theta: f64, lambda_nm: f64) -> f64 {
        self.substrate.reflectance(cos_theta.clamp(0.0, 1.0), lambda_nm)
    }

    /// Film quantities at (θ, λ) (eqs. 16–21, see the module docs for the reading),
    /// from the baked tables inside [λmin, λmax]: |S0|²(λ) and A_bulk(θ, λ) interpolated,
    /// the θ factors of R_spe and the Gaussian of A_tf exact. [`Self::coating_exact`]
    /// outside.
    pub fn coating(&self, cos_theta: f64, lambda_nm: f64) -> Coating {
        let p = &self.params;
        if !(p.density > 0.0) || !lambda_nm.is_finite() {
            return Coating { r_spe: 0.0, t_spe: 1.0, a_tf: 0.0 };
        }
        let t = self.tables();
        let n = self.lambda.len();
        if !(lambda_nm >= self.lambda[0] && lambda_nm <= self.lambda[n - 1]) || t.s0_sq.len() != n {
            return self.coating_exact(cos_theta, lambda_nm);
        }
        let c = cos_theta.clamp(0.0, 1.0);
        let k = t.index.cell(&self.lambda, lambda_nm);
        let fl = (lambda_nm - self.lambda[k]) / (self.lambda[k + 1] - self.lambda[k]);
        let s0_sq = t.s0_sq[k] + fl * (t.s0_sq[k + 1] - t.s0_sq[k]);
        let r_spe = self.film_reflectance(c, lambda_nm, s0_sq);
        let b = &self.band;
        let g = cut_gaussian(lambda_nm, b.lambda_qd_nm, b.width_nm);
        let rows = p.cos_nodes;
        let x = c * (rows - 1) as f64;
        let j = (x as usize).min(rows - 2);
        let fc = x - j as f64;
        let beta = if g > 0.0 { t.beta[j] + fc * (t.beta[j + 1] - t.beta[j]) } else { 0.0 };
        let a = if lambda_nm <= b.lambda_qd_nm {
            let at = |j: usize| {
                let (a0, a1) = (t.a_bulk[j * n + k], t.a_bulk[j * n + k + 1]);
                a0 + fl * (a1 - a0)
            };
            let (a0, a1) = (at(j), at(j + 1));
            a0 + fc * (a1 - a0) + beta * g
        } else {
            2.0 * beta * g
        };
        let a_tf = if a.is_finite() { a.clamp(0.0, 1.0) } else { 0.0 };
        Coating { r_spe, t_spe: 1.0 - r_spe, a_tf }
    }

    /// [`Self::coating`] by the formulas, without the tables.
    pub fn coating_exact(&self, cos_theta: f64, lambda_nm: f64) -> Coating {
        let c = cos_theta.clamp(0.0, 1.0);
        self.coating_with(c, lambda_nm, || self.s0_sq(lambda_nm), || self.film_absorption(c, lambda_nm))
    }

    /// [`Self::coating_exact`] from |S0|²(λ) and A_tf(θ, λ), evaluated only where the film
    /// is there: the bake's one evaluation per node, from its per-λ quantities.
    fn coating_with(
        &self,
        cos_theta: f64,
        lambda_nm: f64,
        s0_sq: impl FnOnce() -> f64,
        a_tf: impl FnOnce() -> f64,
    ) -> Coating {
        if !(self.params.density > 0.0) || !lambda_nm.is_finite() {
            return Coating { r_spe: 0.0, t_spe: 1.0, a_tf: 0.0 };
        }
        let c = cos_theta.clamp(0.0, 1.0);
        let r_spe = self.film_reflectance(c, lambda_nm, s0_sq());
        let a_tf = a_tf();
        Coating { r_spe, t_spe: 1.0 - r_spe, a_tf }
    }

    /// |S0|² = x⁶ |(m² − n²)/(m² + 2n²)|², x = 2πR n_env/λ (eq. 18).
    fn s0_sq(&self, lambda_nm: f64) -> f64 {
        self.s0_sq_with(lambda_nm, self.index.eval(lambda_nm))
    }
    /// [`Self::s0_sq`] given the dot's index m at λ.
    fn s0_sq_with(&self, lambda_nm: f64, m: Complex) -> f64 {
        let n_env = self.params.ext_ior;
        let e = Complex::new(n_env * n_env, 0.0);
        let m2 = m * m;
        let ratio = (m2 - e) / (m2 + e.scale(2.0));
        let x = 2.0 * PI * self.params.radius_nm * n_env / lambda_nm;
        x.powi(6) * ratio.norm_sqr()
    }

    /// R_spe = ½ q² |S0|² (1 + cos²(π − 2θ)) with q = α/(1 + α) (eqs. 16–19), clamped to [0, 1].
    fn film_reflectance(&self, c: f64, lambda_nm: f64, s0_sq: f64) -> f64 {
        let p = &self.params;
        let (rho, r, n_env) = (p.density, p.radius_nm, p.ext_ior);
        // α/(1+α) = ρλ²/(ρλ² + 2π²R²n²cosθ), finite for cos θ → 0.
        let num = rho * lambda_nm * lambda_nm;
        let q = num / (num + 2.0 * PI * PI * r * r * n_env * n_env * c);
        let cos_scat = -(2.0 * c * c - 1.0); // cos(π − 2θ)
        let r_spe = 0.5 * q * q * s0_sq * (1.0 + cos_scat * cos_scat);
        if r_spe.is_finite() {
            r_spe.clamp(0.0, 1.0)
        } else {
            1.0
        }
    }

    /// 1 − exp(−4πk l/λ) with l = 2Rρ/cos θt (eq. 20, read as an absorbed fraction).
    fn bulk_absorption(&self, cos_theta: f64, lambda_nm: f64) -> f64 {
        self.bulk_absorption_with(cos_theta, lambda_nm, self.index.eval(lambda_nm))
    }
    /// [`Self::bulk_absorption`] given the dot's index m at λ.
    fn bulk_absorption_with(&self, cos_theta: f64, lambda_nm: f64, m: Complex) -> f64 {
        let p = &self.params;
        if !(m.im > 0.0) {
            return 0.0;
        }
        let s = p.ext_ior * (1.0 - cos_theta * cos_theta).max(0.0).sqrt() / m.re;
        let cos_t2 = 1.0 - s * s;
        if !(cos_t2 > 0.0) {
            return 1.0; // total internal reflection in the film: l → ∞
        }
        let l = 2.0 * p.radius_nm * p.density / cos_t2.sqrt();
        -(-4.0 * PI * m.im * l / lambda_nm).exp_m1()
    }

    /// A_tf(θ, λ) (eq. 21), clamped to [0, 1].
    pub fn film_absorption(&self, cos_theta: f64, lambda_nm: f64) -> f64 {
        if !(self.params.density > 0.0) {
            return 0.0;
        }
        let lqd = self.band.lambda_qd_nm;
        let bulk = if lambda_nm <= lqd { self.bulk_absorption(cos_theta, lambda_nm) } else { 0.0 };
        self.film_absorption_with(lambda_nm, || self.bulk_absorption(cos_theta, lqd), bulk)
    }
    /// [`Self::film_absorption`] from A_bulk(θ, λQD) (`beta`, evaluated where the band's
    /// Gaussian reaches λ) and A_bulk(θ, λ) (`bulk`, read where λ ≤ λQD).
    fn film_absorption_with(&self, lambda_nm: f64, beta: impl FnOnce() -> f64, bulk: f64) -> f64 {
        if !(self.params.density > 0.0) {
            return 0.0;
        }
        let b = &self.band;
        let g = cut_gaussian(lambda_nm, b.lambda_qd_nm, b.width_nm);
        let beta = if g > 0.0 { beta() } else { 0.0 };
        let a = if lambda_nm <= b.lambda_qd_nm { bulk + beta * g } else { 2.0 * beta * g };
        if a.is_finite() {
            a.clamp(0.0, 1.0)
        } else {
            0.0
        }
    }

    /// R_tot(θ, λ) (eq. 23) over this substrate.
    pub fn r_tot(&self, cos_theta: f64, lambda_nm: f64) -> f64 {
        self.coating(cos_theta, lambda_nm).r_tot(self.substrate_reflectance(cos_theta, lambda_nm))
    }

    /// A_tot(θ, λ) (eq. 24) over this substrate.
    pub fn a_tot(&self, cos_theta: f64, lambda_nm: f64) -> f64 {
        self.coating(cos_theta, lambda_nm).a_tot(self.substrate_reflectance(cos_theta, lambda_nm))
    }

    /// Normalised emission shape e(λo | λi) = L(λo)/I for λo ∈ (λi, λmax] ∩ [λmin, λmax],
    /// nm⁻¹ (its integral over λo is ≤ 1).
    pub fn emission_given(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        let p = &self.params;
        if !(lambda_o > lambda_i && lambda_o >= p.lambda_min_nm && lambda_o <= p.lambda_max_nm && self.norm > 0.0) {
            return 0.0;
        }
        logistic(lambda_o, self.band.emission_peak_nm, self.scale) / self.norm
    }

    /// Bispectral reradiation P(θ, λi, λo) = Q A_tot(θ, λi) L(λo)/I, λo > λi (eq. 27).
    pub fn reradiation_fresnel(&self, cos_theta: f64, lambda_i: f64, lambda_o: f64) -> f64 {
        let e = self.emission_given(lambda_i, lambda_o);
        if e == 0.0 || !(self.params.quantum_yield > 0.0) {
            return 0.0;
        }
        self.params.quantum_yield * self.a_tot(cos_theta, lambda_i) * e
    }

    /// γ(θ) = (Q/I) ∫ A_tot(θ, λ) dλ over [λmin, λmax] (eq. 26), from the tables
    /// (linear in cos θ between rows), nm.
    pub fn gamma(&self, cos_theta: f64) -> f64 {
        if !(self.norm > 0.0) {
            return 0.0;
        }
        let n = self.lambda.len();
        let rows = self.params.cos_nodes;
        let x = cos_theta.clamp(0.0, 1.0) * (rows - 1) as f64;
        let j = (x.floor() as usize).min(rows - 2);
        let f = x - j as f64;
        let total = |j: usize| self.tables().cdf.get(j * n + n - 1).copied().unwrap_or(0.0);
        self.params.quantum_yield / self.norm * ((1.0 - f) * total(j) + f * total(j + 1))
    }

    /// Emission spectrum under equal-energy light E_tot(θ, λo) = γ(θ) L(λo) (eq. 25, with
    /// the centre λQD + Sλ), nm⁻¹·nm.
    pub fn emission_white(&self, cos_theta: f64, lambda_o: f64) -> f64 {
        let p = &self.params;
        if !(lambda_o >= p.lambda_min_nm && lambda_o <= p.lambda_max_nm) {
            return 0.0;
        }
        self.gamma(cos_theta) * logistic(lambda_o, self.band.emission_peak_nm, self.scale)
    }

    /// Elastic BSDF value times cos θo (D G R_tot / (4 cos θi)).
    pub fn elastic(&self, wi: [f64; 3], wo: [f64; 3], lambda: f64) -> f64 {
        match self.microfacet.lobe(wi, wo) {
            Some((lobe, c)) => lobe * self.r_tot(c, lambda),
            None => 0.0,
        }
    }

    /// What the renderer evaluates per lane instead of calling the model (`fluo_qd` in every
    /// variant; Dr.Jit cannot trace calls into Rust). On the model's λ grid and at `rows`
    /// cosines uniform over [0, 1], by the formulas at every node ([`Self::coating_exact`]:
    /// not from the Rust evaluation's own tables, which are then never baked): A_tot (the
    /// reradiation's absorption) and its running integral along λ (trapezoids: exact for the
    /// bilinear interpolant), and the coating's R_spe and pass = (T_spe (1 − A_tf))², from which the
    /// renderer forms the elastic R_tot = R_spe + pass·R/(1 − R·R_spe) over its own
    /// substrate Fresnel factor R; and R_spe, pass at the wavelengths `extra_nm` (the RGB
    /// channels'), row major `[rows][extra]`. Bilinear interpolation in (cos θ, λ) is the
    /// vectorised model: test `jit_tables_interpolate_the_model` measures its error.
    pub fn jit_tables(&self, rows: usize, extra_nm: &[f64]) -> JitTables {
        self.jit_tables_on(rows, &self.lambda, extra_nm)
    }

    /// [`Self::jit_tables`] on the λ grid `lambda` (strictly increasing) instead of the
    /// model's own: another model's, so that the tables of nearby parameters can be
    /// differenced node by node (the vectorised variants' derivatives in radius and density).
    pub fn jit_tables_on(&self, rows: usize, lambda: &[f64], extra_nm: &[f64]) -> JitTables {
        let rows = rows.max(2);
        let lambda = lambda.to_vec();
        let n = lambda.len();
        let mut t = JitTables {
            rows,
            a_tot: Vec::with_capacity(rows * n),
            cdf: Vec::with_capacity(rows * n),
            r_spe: Vec::with_capacity(rows * n),
            pass: Vec::with_capacity(rows * n),
            r_tot: Vec::with_capacity(rows * n),
            extra_r_spe: Vec::with_capacity(rows * extra_nm.len()),
            extra_pass: Vec::with_capacity(rows * extra_nm.len()),
            emission_peak_nm: self.band.emission_peak_nm,
            emission_scale_nm: self.scale,
            emission_norm: self.norm,
            excitation: None,
            lambda: Vec::new(),
        };
        // R_spe and pass = (T_spe (1 − A_tf))² of the coating.
        let elastic = |co: &Coating| (co.r_spe, (co.t_spe * (1.0 - co.a_tf)).powi(2));
        self.for_nodes(rows, &lambda, |_, k, co, r, _| {
            let a = co.a_tot(r);
            t.cdf.push(running(&lambda, k, &t.a_tot, &t.cdf, a));
            t.a_tot.push(a);
            let (rs, p) = elastic(co);
            t.r_spe.push(rs);
            t.pass.push(p);
            t.r_tot.push(co.r_tot(r));
        });
        for j in 0..rows {
            let c = j as f64 / (rows - 1) as f64;
            for &l in extra_nm {
                let (rs, p) = elastic(&self.coating_exact(c, l));
                t.extra_r_spe.push(rs);
                t.extra_pass.push(p);
            }
        }
        // The support from these rows where they hold the tables' ones (the same nodes by
        // the same formulas): the tables are then never baked for it.
        let tables_rows = self.params.cos_nodes - 1;
        if lambda == self.lambda && (rows - 1) % tables_rows == 0 && self.excitation.get().is_none() {
            let _ = self.excitation.set(self.support(|| &t.a_tot, (rows - 1) / tables_rows));
        }
        t.excitation = self.excitation();
        t.lambda = lambda;
        t
    }

    // ---- excitation tables

    fn row(&self, cos_theta: f64) -> usize {
        let rows = self.params.cos_nodes;
        ((cos_theta.clamp(0.0, 1.0) * (rows - 1) as f64).round() as usize).min(rows - 1)
    }

    /// Interpolated table value and running integral at λ on row j.
    fn table_at(&self, j: usize, lambda: f64) -> (f64, f64) {
        let t = self.tables();
        let n = self.lambda.len();
        let (Some(&l0), Some(&l1)) = (self.lambda.first(), self.lambda.last()) else { return (0.0, 0.0) };
        if !(lambda > l0) {
            return (t.a_tot.get(j * n).copied().unwrap_or(0.0), 0.0);
        }
        if lambda >= l1 {
            return (
                t.a_tot.get(j * n + n - 1).copied().unwrap_or(0.0),
                t.cdf.get(j * n + n - 1).copied().unwrap_or(0.0),
            );
        }
        let k = t.index.cell(&self.lambda, lambda);
        let (xa, xb) = (self.lambda[k], self.lambda[k + 1]);
        let (a, b) = (t.a_tot[j * n + k], t.a_tot[j * n + k + 1]);
        let f = (lambda - xa) / (xb - xa);
        let v = a + f * (b - a);
        (v, t.cdf[j * n + k] + 0.5 * (lambda - xa) * (a + v))
    }

    /// The λi interval [lo, hi] of excitations that can reach λo inside `range`.
    fn excitation_interval(&self, lambda_o: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        let (slo, shi) = self.excitation()?;
        let lo = range.0.max(slo);
        let hi = range.1.min(shi).min(lambda_o);
        (hi > lo).then_some((lo, hi))
    }

    /// Sample λi on [lo, hi] ∝ the piecewise-linear A_tot row j: (λi, pdf).
    fn sample_row(&self, j: usize, lo: f64, hi: f64, xi: f64) -> Option<(f64, f64)> {
        let (_, c_lo) = self.table_at(j, lo);
        let (_, c_hi) = self.table_at(j, hi);
        let mass = c_hi - c_lo;
        if !(mass > 0.0) {
            return None;
        }
        let target = c_lo + xi.clamp(0.0, 1.0) * mass;
        let t = self.tables();
        let n = self.lambda.len();
        let cdf = &t.cdf[j * n..(j + 1) * n];
        // Bin k with cdf[k] ≤ target < cdf[k+1].
        let k = cdf.partition_point(|&c| c <= target).clamp(1, n - 1) - 1;
        let (xa, xb) = (self.lambda[k], self.lambda[k + 1]);
        let (a, b) = (t.a_tot[j * n + k], t.a_tot[j * n + k + 1]);
        let bin = cdf[k + 1] - cdf[k];
        let u = if bin > 0.0 { ((target - cdf[k]) / bin).clamp(0.0, 1.0) } else { 0.5 };
        // Inverse CDF of the linear density on the bin (pbrt's SampleLinear form).
        let denom = a + (a * a + u * (b * b - a * a)).max(0.0).sqrt();
        let s = if denom > 0.0 { u * (a + b) / denom } else { u };
        let x = (xa + s.clamp(0.0, 1.0) * (xb - xa)).clamp(lo, hi);
        let (v, _) = self.table_at(j, x);
        let pdf = v / mass;
        (pdf > 0.0 && pdf.is_finite()).then_some((x, pdf))
    }

    fn row_pdf(&self, j: usize, lo: f64, hi: f64, lambda: f64) -> f64 {
        if !(lambda >= lo && lambda <= hi) {
            return 0.0;
        }
        let mass = self.table_at(j, hi).1 - self.table_at(j, lo).1;
        if mass > 0.0 {
            self.table_at(j, lambda).0 / mass
        } else {
            0.0
        }
    }

    /// Emission interval (max(λi, λmin), λmax] and its logistic mass.
    fn emission_interval(&self, lambda_i: f64) -> Option<(f64, f64, f64)> {
        let p = &self.params;
        let a = lambda_i.max(p.lambda_min_nm);
        let b = p.lambda_max_nm;
        if !(b > a) {
            return None;
        }
        let mu = self.band.emission_peak_nm;
        let mass = if a >= mu {
            logistic_survival(a, mu, self.scale) - logistic_survival(b, mu, self.scale)
        } else {
            logistic_cdf(b, mu, self.scale) - logistic_cdf(a, mu, self.scale)
        };
        (mass > 0.0 && mass.is_finite()).then_some((a, b, mass))
    }

    fn absorbs(&self, cos_theta: f64, lambda_i: f64) -> bool {
        let p = &self.params;
        lambda_i >= p.lambda_min_nm && lambda_i <= p.lambda_max_nm && self.a_tot(cos_theta, lambda_i) > 0.0
    }
}

impl fmt::Display for QdModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let p = &self.params;
        let b = &self.band;
        write!(
            f,
            "QdModel[radius = {} nm, width = {} nm, quantum_yield = {}, density = {}, distribution = {:?}, \
             alpha = {}, lambda_qd = {:.2} nm, stokes_shift = {:.2} nm, emission_peak = {:.2} nm, \
             range = [{}, {}] nm, tables = {} x {} ({} bytes)]",
            p.radius_nm,
            p.width_nm,
            p.quantum_yield,
            p.density,
            p.distribution,
            p.alpha,
            b.lambda_qd_nm,
            b.stokes_shift_nm,
            b.emission_peak_nm,
            p.lambda_min_nm,
            p.lambda_max_nm,
            self.params.cos_nodes,
            self.lambda.len(),
            self.table_bytes()
        )
    }
}

/// The coating over its substrate. The spectral operator is the coating's at one
/// microfacet incidence cosine: diagonal R_tot(θ, λ), reradiation P(θ, λi, λo)
/// (eqs. 23, 27); reduced tables are built from it per cosine.
impl crate::interface::Bispectral for QdModel {
    fn excitation_range(&self) -> Option<(f64, f64)> {
        self.excitation()
    }
    fn emission_range(&self) -> Option<(f64, f64)> {
        self.excitation().map(|_| (self.params.lambda_min_nm, self.params.lambda_max_nm))
    }
    fn elastic_albedo(&self, cos_i: f64, lambda: f64) -> f64 {
        self.r_tot(cos_i, lambda)
    }
    fn density(&self, cos_i: f64, lambda_i: f64, lambda_o: f64) -> f64 {
        self.reradiation_fresnel(cos_i, lambda_i, lambda_o)
    }
    /// P = (Q·A_tot(θ, λi))·(L(λo)/I) for λi < λo (reradiation_fresnel's factors).
    fn density_factors(&self, cos_i: f64, lambdas: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
        let q = self.params.quantum_yield;
        let a = lambdas.iter().map(|&l| if q > 0.0 { q * self.a_tot(cos_i, l) } else { 0.0 }).collect();
        // (every λo is above -∞: the line alone)
        let b = lambdas.iter().map(|&l| self.emission_given(f64::NEG_INFINITY, l)).collect();
        Some((a, b))
    }
    fn reradiation(&self, wi: [f64; 3], wo: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        if self.excitation().is_none() {
            return 0.0;
        }
        let e = self.emission_given(lambda_i, lambda_o);
        if e == 0.0 {
            return 0.0;
        }
        match self.microfacet.lobe(wi, wo) {
            Some((lobe, c)) => lobe * self.params.quantum_yield * self.a_tot(c, lambda_i) * e,
            None => 0.0,
        }
    }
    fn shift_albedo(&self, wi: [f64; 3], lambda_o: f64, range: (f64, f64)) -> f64 {
        // Smooth-surface value Q e(λo) ∫ A_tot(θi, λi) dλi (the microfacet albedo ≤ 1
        // is left out): positive exactly where the true integral is.
        if !(wi[2] > 0.0) {
            return 0.0;
        }
        let Some((lo, hi)) = self.excitation_interval(lambda_o, range) else { return 0.0 };
        let e = self.emission_given(lo, lambda_o);
        let j = self.row(wi[2]);
        self.params.quantum_yield * e * (self.table_at(j, hi).1 - self.table_at(j, lo).1).max(0.0)
    }
    fn sample_excitation(&self, wi: [f64; 3], lambda_o: f64, xi: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        if !(wi[2] > 0.0) {
            return None;
        }
        let (lo, hi) = self.excitation_interval(lambda_o, range)?;
        if self.emission_given(lo, lambda_o) == 0.0 {
            return None;
        }
        self.sample_row(self.row(wi[2]), lo, hi, xi)
    }
    fn excitation_pdf(&self, wi: [f64; 3], lambda_o: f64, lambda_i: f64, range: (f64, f64)) -> f64 {
        if !(wi[2] > 0.0) {
            return 0.0;
        }
        let Some((lo, hi)) = self.excitation_interval(lambda_o, range) else { return 0.0 };
        if self.emission_given(lo, lambda_o) == 0.0 {
            return 0.0;
        }
        self.row_pdf(self.row(wi[2]), lo, hi, lambda_i)
    }
    fn sample_emission(&self, wi: [f64; 3], lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        if !(wi[2] > 0.0) || self.excitation().is_none() || !self.absorbs(wi[2], lambda_i) {
            return None;
        }
        let (a, b, mass) = self.emission_interval(lambda_i)?;
        let mu = self.band.emission_peak_nm;
        let xi = xi.clamp(0.0, 1.0);
        let x = if a >= mu {
            let sa = logistic_survival(a, mu, self.scale);
            let sv = (sa - xi * mass).clamp(f64::MIN_POSITIVE, 1.0);
            mu + self.scale * ((1.0 - sv) / sv).ln()
        } else {
            let ca = logistic_cdf(a, mu, self.scale);
            let cv = (ca + xi * mass).clamp(f64::MIN_POSITIVE, 1.0 - f64::EPSILON);
            mu + self.scale * (cv / (1.0 - cv)).ln()
        };
        let x = x.clamp(a, b);
        let pdf = logistic(x, mu, self.scale) / mass;
        (pdf > 0.0 && pdf.is_finite() && x > lambda_i).then_some((x, pdf))
    }
    fn emission_pdf(&self, wi: [f64; 3], lambda_i: f64, lambda_o: f64) -> f64 {
        if !(wi[2] > 0.0) || self.excitation().is_none() || !self.absorbs(wi[2], lambda_i) {
            return 0.0;
        }
        match self.emission_interval(lambda_i) {
            Some((a, b, mass)) if lambda_o > a && lambda_o <= b => {
                logistic(lambda_o, self.band.emission_peak_nm, self.scale) / mass
            }
            _ => 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::band::trapezoid;
    use super::microfacet::{dot, half_vector};
    use super::*;

    /// The reradiated XYZ at normal incidence under equal-energy light (per unit Q).
    fn reradiated_xyz(m: &QdModel) -> [f64; 3] {
        use crate::spectrum::Spectral;
        let c = crate::spectrum::cmf(crate::spectrum::Observer::Cie1931);
        let (mut xyz, step) = ([0.0; 3], 2.0);
        let mut lo = 360.0;
        while lo <= 830.0 {
            let e = m.reradiated(&|_| 1.0, (300.0, 830.0), lo);
            for (k, cmf) in [c.x(), c.y(), c.z()].into_iter().enumerate() {
                xyz[k] += e * cmf.eval(lo) * step;
            }
            lo += step;
        }
        xyz
    }

    /// The vectorised variants' model: bilinear interpolation of [`QdModel::jit_tables`] in
    /// (cos θ, λ) against the model itself, at cell centres (the worst place for a linear
    /// interpolant), over the whole table, on gold and glass. Measured: A_tot within 6.9e-4
    /// of its peak (R = 1.5 nm; 2.6e-4 at 3.3 nm), R_spe and pass within 1.3e-4.
    #[test]
    /// [`QdModel::jit_tables_on`] on the model's own grid is [`QdModel::jit_tables`], and on
    /// a neighbour's grid the tables of two radii 0.01 nm apart differ by a small step.
    fn jit_tables_on_another_grid() {
        let at = |r: f64| model(QdParams { radius_nm: r, density: 0.8, ..QdParams::default() });
        let (a, b) = (at(2.2), at(2.21));
        let own = a.jit_tables(9, &[611.0]);
        let same = a.jit_tables_on(9, &own.lambda, &[611.0]);
        assert_eq!(own.a_tot, same.a_tot);
        assert_eq!(own.r_tot, same.r_tot);
        let next = b.jit_tables_on(9, &own.lambda, &[611.0]);
        assert_eq!(next.lambda, own.lambda);
        let peak = own.a_tot.iter().fold(0.0f64, |m, v| m.max(*v));
        let step = own.a_tot.iter().zip(&next.a_tot).fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        assert!(peak > 0.0 && step > 0.0 && step < 0.05 * peak, "{step} of {peak}");
    }

    #[test]
    fn jit_tables_leave_the_tables_unbaked() {
        // the support read from the vectorised tables' rows is the tables' own (gold and a
        // dielectric, thin and dense films, a coating that never re-emits)
        for substrate in [GOLD, Substrate::Constant { eta: 1.5, k: 0.0 }] {
            for (radius, density, q) in [(1.8, 0.2, 0.5), (3.1, 0.9, 1.0), (2.5, 0.5, 0.0)] {
                let p = QdParams { radius_nm: radius, density, quantum_yield: q, ..QdParams::default() };
                let a = QdModel::new(p, QdIndex::CdSe, substrate.clone()).unwrap();
                let b = QdModel::new(p, QdIndex::CdSe, substrate.clone()).unwrap();
                let t = a.jit_tables(65, &[611.0]);
                assert!(a.tables.get().is_none(), "jit_tables baked the tables");
                assert_eq!(t.excitation, b.excitation());
                // (a coating that never re-emits has no support to read from them)
                assert_eq!(b.tables.get().is_some(), q > 0.0);
                assert_eq!(t.excitation.is_some(), q > 0.0);
                // rows that do not hold the tables' ones: the tables' support
                let c = QdModel::new(a.params, QdIndex::CdSe, substrate.clone()).unwrap();
                assert_eq!(c.jit_tables(50, &[]).excitation, t.excitation);
            }
        }
    }

    #[test]
    fn jit_tables_interpolate_the_model() {
        const ROWS: usize = 65; // fluo_qd.cpp's JitCosNodes
        for substrate in [GOLD, Substrate::Constant { eta: 1.5, k: 0.0 }] {
            for radius in [1.5, 2.2, 3.3] {
                let m = QdModel::new(
                    QdParams { radius_nm: radius, ..QdParams::default() },
                    QdIndex::CdSe,
                    substrate.clone(),
                )
                .unwrap();
                let t = m.jit_tables(ROWS, &[611.0, 549.0, 464.0]);
                let n = t.lambda.len();
                assert_eq!((t.a_tot.len(), t.extra_pass.len()), (ROWS * n, ROWS * 3));
                let peak = t.a_tot.iter().cloned().fold(0.0, f64::max);
                let (mut worst_a, mut worst_r) = (0.0f64, 0.0f64);
                for j in 0..ROWS - 1 {
                    for k in 0..n - 1 {
                        let (c, l) = ((j as f64 + 0.5) / (ROWS - 1) as f64, 0.5 * (t.lambda[k] + t.lambda[k + 1]));
                        let at = |v: &[f64]| {
                            0.25 * (v[j * n + k] + v[j * n + k + 1] + v[(j + 1) * n + k] + v[(j + 1) * n + k + 1])
                        };
                        worst_a = worst_a.max((at(&t.a_tot) - m.a_tot(c, l)).abs() / peak);
                        let co = m.coating(c, l);
                        let p = (co.t_spe * (1.0 - co.a_tf)).powi(2);
                        worst_r = worst_r.max((at(&t.r_spe) - co.r_spe).abs()).max((at(&t.pass) - p).abs());
                    }
                }
                // A_tot relative to its peak; R_spe and pass are fractions of one.
                assert!(worst_a < 1e-3, "A_tot off by {worst_a:e} of its peak (R = {radius})");
                assert!(worst_r < 3e-4, "R_spe/pass off by {worst_r:e} (R = {radius})");
                // the running integral is the trapezoid rule of the same nodes
                let last = t.cdf[n - 1];
                assert!((last - trapezoid(&t.lambda, |l| m.a_tot(0.0, l))).abs() <= 1e-9 * last.max(1.0));
            }
        }
    }

    #[test]
    fn check_param_value_ranges() {
        for name in TEXTURABLE_PARAMS {
            assert!(check_param_value(name, f64::NAN).is_err(), "{name}");
        }
        assert!(check_param_value("alpha", ALPHA_RANGE.0).is_ok() && check_param_value("alpha", ALPHA_RANGE.1).is_ok());
        let e = check_param_value("alpha", 4.5).unwrap_err().to_string();
        assert!(e.contains("\"alpha\"") && e.contains("4.5"), "{e}");
        assert!(check_param_value("width", 10.0).is_err());
    }

    #[test]
    fn texture_grid_interpolation_error() {
        let at = |r: f64, rho: f64| {
            reradiated_xyz(&model(QdParams { radius_nm: r, density: rho, quantum_yield: 1.0, ..QdParams::default() }))
        };
        // worst relative XYZ error of the two-node mixture at the cell centres of n nodes
        let worst = |n: usize, lo: f64, hi: f64, f: &dyn Fn(f64) -> [f64; 3]| {
            let node = |i: usize| lo + (hi - lo) * i as f64 / (n - 1) as f64;
            let mut w: f64 = 0.0;
            for i in 0..n - 1 {
                let (a, b, exact) = (f(node(i)), f(node(i + 1)), f(0.5 * (node(i) + node(i + 1))));
                for k in 0..3 {
                    w = w.max((0.5 * (a[k] + b[k]) - exact[k]).abs() / exact[1]);
                }
            }
            w
        };
        let density = worst(TEXTURE_GRID_NODES, 0.0, 1.0, &|rho| at(2.2, rho));
        eprintln!("density grid, {TEXTURE_GRID_NODES} nodes: {density:.4}");
        assert!(density <= TEXTURE_GRID_MAX_ERROR, "{density}");
        // the documented figures (finer density grids, and why the radius has none)
        assert!(worst(33, 0.0, 1.0, &|rho| at(2.2, rho)) <= 0.002);
        for (n, lo, hi) in [(9, 0.45, 0.55), (33, 0.12, 0.14), (65, 0.05, 0.06)] {
            let radius = worst(n, 1.5, 4.0, &|r| at(r, 0.5));
            eprintln!("radius grid, {n} nodes: {radius:.4}");
            assert!(radius > lo && radius <= hi, "{n}: {radius}");
        }
    }
    use crate::interface::Bispectral;
    use crate::testutil::{chi2, chi2_critical, uniforms};

    const GOLD: Substrate = Substrate::Constant { eta: 0.27, k: 2.9 };

    fn model(p: QdParams) -> QdModel {
        QdModel::new(p, QdIndex::CdSe, GOLD).unwrap()
    }

    #[test]
    fn baked_tables_equal_the_formulas() {
        // the bake evaluates what depends on λ once per node: every entry is still the
        // per-call formula's, to the bit (gold and a dielectric substrate, thin and dense films)
        for substrate in [GOLD, Substrate::Constant { eta: 1.5, k: 0.0 }] {
            for (radius, density) in [(1.8, 0.2), (3.1, 0.9)] {
                let m = QdModel::new(
                    QdParams { radius_nm: radius, density, ..QdParams::default() },
                    QdIndex::CdSe,
                    substrate.clone(),
                )
                .unwrap();
                let t = m.tables();
                let (n, rows) = (m.lambda.len(), m.params.cos_nodes);
                for j in 0..rows {
                    let c = j as f64 / (rows - 1) as f64;
                    for (k, &l) in m.lambda.iter().enumerate() {
                        let a = m.coating_exact(c, l).a_tot(m.substrate_reflectance(c, l));
                        assert_eq!(t.a_tot[j * n + k].to_bits(), a.to_bits(), "A_tot at ({c}, {l})");
                        assert_eq!(t.a_bulk[j * n + k].to_bits(), m.bulk_absorption(c, l).to_bits());
                    }
                }
            }
        }
    }

    #[test]
    fn density_factors_equal_the_density() {
        // a(λi)·b(λo) on λi < λo, 0 elsewhere: the density entry by entry, to the bit
        let m = model(QdParams { density: 0.8, ..QdParams::default() });
        let lambdas: Vec<f64> = (0..=106).map(|i| 300.0 + 5.0 * i as f64).collect();
        let mut positive = 0;
        for cos_i in [0.05, 0.5, 1.0] {
            let (a, b) = m.density_factors(cos_i, &lambdas).unwrap();
            for (i, &li) in lambdas.iter().enumerate() {
                for (o, &lo) in lambdas.iter().enumerate() {
                    let got = if lo > li { a[i] * b[o] } else { 0.0 };
                    assert_eq!(got.to_bits(), m.density(cos_i, li, lo).to_bits(), "cos {cos_i} {li} -> {lo}");
                    positive += usize::from(got > 0.0);
                }
            }
        }
        assert!(positive > 1000, "{positive}");
    }

    fn dir(theta_deg: f64) -> [f64; 3] {
        let t = theta_deg.to_radians();
        [t.sin(), 0.0, t.cos()]
    }

    #[test]
    fn table_knobs_are_validated_and_converge() {
        for (rows, step) in [(1, 1.0), (2000, 1.0), (33, 0.0), (33, f64::NAN), (33, 100.0)] {
            let p = QdParams { cos_nodes: rows, table_step_nm: step, ..QdParams::default() };
            let Err(e) = QdModel::new(p, QdIndex::CdSe, GOLD) else { panic!("out of range") };
            assert!(e.to_string().contains(if rows == 33 { "table_step" } else { "table_cos_nodes" }), "{e}");
        }
        let fine = model(QdParams { cos_nodes: 129, table_step_nm: 0.25, ..QdParams::default() });
        let base = model(QdParams::default());
        let coarse = model(QdParams { cos_nodes: 5, table_step_nm: 8.0, ..QdParams::default() });
        assert!(coarse.table_bytes() < base.table_bytes() && base.table_bytes() < fine.table_bytes());
        let err = |m: &QdModel| {
            (0..=20).map(|i| (m.gamma(i as f64 / 20.0) - fine.gamma(i as f64 / 20.0)).abs()).fold(0.0, f64::max)
        };
        assert!(err(&base) <= err(&coarse) + 1e-12, "{} vs {}", err(&base), err(&coarse));
        assert!(err(&base) < 1e-2 * fine.gamma(1.0), "{}", err(&base));
    }

    #[test]
    fn baked_coating_matches_the_formulas() {
        // Largest |baked − exact| over a dense (cos θ, λ) sweep: absolute (all terms are
        // fractions in [0, 1]), far below the 2e-3 of the balance tests.
        for p in [
            QdParams::default(),
            QdParams { radius_nm: 5.0, density: 1.0, quantum_yield: 1.0, ..QdParams::default() },
            QdParams { radius_nm: 3.3, width_nm: 0.05, ..QdParams::default() },
            QdParams { radius_nm: 1.5, width_nm: 100.0, ext_ior: 1.5, ..QdParams::default() },
        ] {
            let m = model(p);
            let mut err = [0.0_f64; 4];
            let mut max = [0.0_f64; 4];
            for i in 0..=100 {
                let c = i as f64 / 100.0;
                for l in (0..=53_000).map(|k| 300.0 + 0.01 * k as f64).chain([m.band().lambda_qd_nm]) {
                    let (b, e) = (m.coating(c, l), m.coating_exact(c, l));
                    let r = m.substrate_reflectance(c, l);
                    let pairs =
                        [(b.r_spe, e.r_spe), (b.a_tf, e.a_tf), (b.r_tot(r), e.r_tot(r)), (b.a_tot(r), e.a_tot(r))];
                    for (t, (x, y)) in pairs.into_iter().enumerate() {
                        err[t] = err[t].max((x - y).abs());
                        max[t] = max[t].max(y.abs());
                    }
                }
            }
            // Measured: R_spe ≤ 1e-4 of its largest value, A_tf ≤ 5e-5, R_tot and A_tot
            // ≤ 9e-5 (R = 5 nm, ρ = 1), from the CdSe index's 0.5 nm kinks between the 1 nm nodes.
            let msg = format!("R={} δ={}: |Δ| {err:?} of {max:?}", p.radius_nm, p.width_nm);
            assert!(err[0] <= 2e-4 * max[0] && err[1] <= 1e-4 && err[2] <= 2e-4 && err[3] <= 2e-4, "{msg}");
        }
    }

    #[test]
    fn zero_density_is_the_substrate() {
        let m = model(QdParams { density: 0.0, ..QdParams::default() });
        for c in [0.0, 0.3, 1.0] {
            for l in [300.0, 450.0, 830.0] {
                assert_eq!(m.r_tot(c, l), m.substrate_reflectance(c, l));
                assert_eq!(m.a_tot(c, l), 0.0);
            }
        }
        assert!(!m.is_fluorescent());
    }

    #[test]
    fn fresnel_level_energy_balance() {
        // R_tot + A_tot + substrate absorption = 1 (eqs. 22-24 are an exact series).
        for p in
            [QdParams { density: 1.0, quantum_yield: 1.0, radius_nm: 5.0, ..QdParams::default() }, QdParams::default()]
        {
            let m = model(p);
            for c in [0.0, 1e-6, 0.1, 0.5, 1.0] {
                for l in [300.0, 350.0, 420.0, m.band().lambda_qd_nm, 600.0, 830.0] {
                    let co = m.coating(c, l);
                    let r = m.substrate_reflectance(c, l);
                    // Sum the series of eq. 22 and the matching absorption series directly.
                    let (mut rt, mut at, mut up) = (co.r_spe, co.t_spe * co.a_tf, co.t_spe * (1.0 - co.a_tf) * r);
                    for _ in 0..200 {
                        rt += co.t_spe * (1.0 - co.a_tf) * up;
                        at += co.t_spe * co.a_tf * up;
                        up *= co.r_spe * r;
                    }
                    assert!((rt - co.r_tot(r)).abs() < 1e-12 && (at - co.a_tot(r)).abs() < 1e-12);
                    assert!(co.r_tot(r) + co.a_tot(r) <= 1.0 + 1e-12);
                }
            }
        }
    }

    #[test]
    fn absorption_grows_with_density_and_peaks_near_lambda_qd() {
        let lo = model(QdParams { density: 0.2, ..QdParams::default() });
        let hi = model(QdParams { density: 0.8, ..QdParams::default() });
        let lq = hi.band().lambda_qd_nm;
        for l in [320.0, 400.0, lq] {
            assert!(hi.film_absorption(1.0, l) > lo.film_absorption(1.0, l));
        }
        // Gaussian shoulder above λQD, nothing far above it
        assert!(hi.film_absorption(1.0, lq + 15.0) > 0.0);
        assert_eq!(hi.film_absorption(1.0, lq + 200.0), 0.0);
        // continuity at λQD
        let (a, b) = (hi.film_absorption(1.0, lq - 1e-7), hi.film_absorption(1.0, lq + 1e-7));
        assert!((a - b).abs() < 1e-6, "{a} {b}");
    }

    #[test]
    fn gamma_is_the_white_light_balance() {
        // ∫ E_tot dλo = Q ∫ A_tot dλi (eq. 26) and the bispectral matrix integrates to it.
        let m = model(QdParams::default());
        let grid: Vec<f64> = (0..=53_000).map(|i| 300.0 + 0.01 * i as f64).collect();
        for c in [0.0, 0.5, 1.0] {
            let a = trapezoid(&grid, |l| m.a_tot(c, l));
            let e = trapezoid(&grid, |l| m.emission_white(c, l));
            assert!((e - 0.8 * a).abs() < 2e-3 * a, "cos {c}: {e} vs {}", 0.8 * a);
        }
    }

    /// Midpoint quadrature of ∫ g(ωo) dωo over reflected directions, in the half-vector
    /// parametrisation θh = atan(α tan(πu/2)) (dωo = 4 (ωi·h) dωh), adapted to α.
    fn integrate_reflected(m: &QdModel, wi: [f64; 3], g: impl Fn([f64; 3]) -> f64) -> f64 {
        integrate_reflected_n(m, wi, g, 300, 48)
    }

    fn integrate_reflected_n(m: &QdModel, wi: [f64; 3], g: impl Fn([f64; 3]) -> f64, nu: usize, nphi: usize) -> f64 {
        let a = m.microfacet().alpha;
        let mut sum = 0.0;
        for i in 0..nu {
            let u = (i as f64 + 0.5) / nu as f64;
            let t = (0.5 * PI * u).tan();
            let th = (a * t).atan();
            let dth = a * 0.5 * PI * (1.0 + t * t) / (1.0 + a * a * t * t) / nu as f64;
            for k in 0..nphi {
                let ph = 2.0 * PI * (k as f64 + 0.5) / nphi as f64;
                let h = [th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()];
                let c = dot(wi, h);
                if c <= 0.0 {
                    continue;
                }
                let wo = [2.0 * c * h[0] - wi[0], 2.0 * c * h[1] - wi[1], 2.0 * c * h[2] - wi[2]];
                let dw = 4.0 * c * th.sin() * dth * (2.0 * PI / nphi as f64);
                sum += g(wo) * dw;
            }
        }
        sum
    }

    #[test]
    fn white_furnace_per_excitation_wavelength() {
        // For every θ and λi: ∫dωo [elastic + ∫dλo reradiation] ≤ 1, Q = ρ = 1 included,
        // using the BSDF evaluation itself. Reradiation is separable in λo, so its λo
        // integral is ∫ e(λo|λi) dλo (trapezoid) times the value at one λo.
        let grid: Vec<f64> = (0..=5_300).map(|i| 300.0 + 0.1 * i as f64).collect();
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            for alpha in [1e-3, 0.2, 1.0] {
                for (rho, q, r) in [(1.0, 1.0, 5.0), (1.0, 1.0, 1.0), (0.5, 0.8, 2.2)] {
                    let m = QdModel::new(
                        QdParams {
                            density: rho,
                            quantum_yield: q,
                            radius_nm: r,
                            alpha,
                            distribution: dist,
                            ..QdParams::default()
                        },
                        QdIndex::CdSe,
                        Substrate::Constant { eta: 1e-3, k: 1e3 }, // a near-perfect mirror: worst case
                    )
                    .unwrap();
                    for theta in [0.0, 60.0, 89.9] {
                        let wi = dir(theta);
                        for li in [300.0, m.band().lambda_qd_nm - 3.0, m.band().lambda_qd_nm + 5.0, 600.0, 830.0] {
                            let lo_ref = (m.band().emission_peak_nm).max(li + 1.0).min(830.0);
                            let e_ref = m.emission_given(li, lo_ref);
                            let e_int = trapezoid(&grid, |l| m.emission_given(li, l));
                            assert!(e_int <= 1.0 + 1e-6, "∫e = {e_int}");
                            let total = integrate_reflected(&m, wi, |wo| {
                                let rer =
                                    if e_ref > 0.0 { m.reradiation(wi, wo, li, lo_ref) / e_ref * e_int } else { 0.0 };
                                m.elastic(wi, wo, li) + rer
                            });
                            assert!(total.is_finite() && total >= 0.0);
                            assert!(
                                total <= 1.0 + 2e-3,
                                "{dist:?} α={alpha} ρ={rho} Q={q} R={r} θ={theta} λi={li}: {total}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn quadrature_normalises_the_visible_normals() {
        // ∫ D(h) G1(ωi,h) (ωi·h)/cos θi dωh = 1 checks the quadrature of the furnace test
        // (including the reflected directions below the horizon, which the BSDF drops).
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            for alpha in [1e-3, 0.2, 1.0] {
                let m = model(QdParams { alpha, distribution: dist, ..QdParams::default() });
                for theta in [0.0, 60.0, 85.0] {
                    let wi = dir(theta);
                    let mf = *m.microfacet();
                    let v = integrate_reflected(&m, wi, |wo| match half_vector(wi, wo) {
                        Some(h) => mf.d(h) * mf.smith_g1(wi, h) / (4.0 * wi[2]),
                        None => 0.0,
                    });
                    // Beckmann's rational G1 is within 0.35 % of the exact one.
                    assert!((v - 1.0).abs() < 6e-3, "{dist:?} α={alpha} θ={theta}: {v}");
                }
            }
        }
    }

    // ---- wavelength sampling

    #[test]
    fn wavelength_sampling_chi2_including_hard_cases() {
        for (r, width, theta) in
            [(2.2, 15.0, 0.0), (1.0, 15.0, 60.0), (5.0, 15.0, 89.9), (3.3, 0.05, 30.0), (1.5, 100.0, 0.0)]
        {
            let m = model(QdParams {
                radius_nm: r,
                width_nm: width,
                density: 1.0,
                quantum_yield: 1.0,
                ..QdParams::default()
            });
            let wi = dir(theta);
            // λi | λo (camera paths), over the scene range [300, 830]
            let lo_nm = m.band().emission_peak_nm.min(829.0);
            let range = (300.0, 830.0);
            let (lo, hi) = (300.0_f64.max(m.excitation_range().unwrap().0), lo_nm.min(m.excitation_range().unwrap().1));
            let xs: Vec<f64> = uniforms(100_000, 3)
                .into_iter()
                .filter_map(|u| {
                    let (l, pdf) = m.sample_excitation(wi, lo_nm, u, range)?;
                    let want = m.excitation_pdf(wi, lo_nm, l, range);
                    assert!((pdf - want).abs() <= 1e-9 * want, "pdf {pdf} vs {want}");
                    Some(l)
                })
                .collect();
            assert!(xs.len() > 99_000, "λi|λo R={r} δ={width}: {} samples", xs.len());
            let (stat, dof) = chi2(&xs, lo, hi, 200, |l| m.excitation_pdf(wi, lo_nm, l, range));
            assert!(stat < chi2_critical(dof), "λi|λo R={r} δ={width}: chi2 {stat} dof {dof}");
            // λo | λi (light paths)
            for li in [300.0, (m.band().lambda_qd_nm - 1.0).max(300.0)] {
                let xs: Vec<f64> = uniforms(100_000, 5)
                    .into_iter()
                    .filter_map(|u| {
                        let (l, pdf) = m.sample_emission(wi, li, u)?;
                        let want = m.emission_pdf(wi, li, l);
                        assert!((pdf - want).abs() <= 1e-9 * want, "pdf {pdf} vs {want}");
                        Some(l)
                    })
                    .collect();
                assert!(xs.len() > 99_000, "λo|λi R={r} δ={width} λi={li}: {} samples", xs.len());
                // bins over the emission band (±30 logistic scales: the tails beyond hold < 1e-12)
                let (mu, sc) = (m.band().emission_peak_nm, 0.5 * width);
                let band_lo = li.max(300.0).max(mu - 30.0 * sc);
                let blo = if band_lo < 829.0 { band_lo } else { li.max(300.0) };
                let bhi = (mu + 30.0 * sc).min(830.0).max(blo + 1.0);
                let (stat, dof) = chi2(&xs, blo, bhi, 400, |l| m.emission_pdf(wi, li, l));
                assert!(dof > 50, "dof {dof}");
                assert!(stat < chi2_critical(dof), "λo|λi R={r} δ={width} λi={li}: chi2 {stat} dof {dof}");
            }
        }
    }

    #[test]
    fn excitation_pdf_integrates_to_one_and_follows_a_tot_at_normal_incidence() {
        let m = model(QdParams { density: 1.0, ..QdParams::default() });
        let range = (300.0, 830.0);
        let lo_nm = m.band().emission_peak_nm;
        let grid: Vec<f64> = (0..=530_000).map(|i| 300.0 + 0.001 * i as f64).collect();
        let total = trapezoid(&grid, |l| m.excitation_pdf([0.0, 0.0, 1.0], lo_nm, l, range));
        assert!((total - 1.0).abs() < 1e-4, "{total}");
        // shift albedo = Q e(λo) ∫ A_tot(θi) dλi below λo (smooth limit)
        let want =
            0.8 * m.emission_given(300.0, lo_nm) * trapezoid(&grid, |l| if l < lo_nm { m.a_tot(1.0, l) } else { 0.0 });
        let got = m.shift_albedo([0.0, 0.0, 1.0], lo_nm, range);
        assert!((got - want).abs() < 2e-3 * want, "{got} vs {want}");
    }

    #[test]
    fn errors_name_parameter_value_and_range() {
        let bad = |p: QdParams| QdModel::new(p, QdIndex::CdSe, GOLD).unwrap_err().to_string();
        let d = QdParams::default();
        let e = bad(QdParams { radius_nm: 0.5, ..d });
        assert!(e.contains("radius") && e.contains("0.5") && e.contains("[1, 5]"), "{e}");
        assert!(bad(QdParams { quantum_yield: 1.5, ..d }).contains("quantum_yield"));
        assert!(bad(QdParams { density: f64::NAN, ..d }).contains("density"));
        assert!(bad(QdParams { width_nm: 0.0, ..d }).contains("width"));
        assert!(bad(QdParams { alpha: -0.1, ..d }).contains("alpha"));
        assert!(bad(QdParams { lambda_max_nm: 250.0, ..d }).contains("lambda_max"));
        let e = bad(QdParams { constants: QdConstants { planck: -1.0, ..QdConstants::default() }, ..d });
        assert!(e.contains("planck"), "{e}");
        let heavy = QdConstants { gap_energy: 1e-21, electron_mass: 1e-20, hole_mass: 1e-20, ..QdConstants::default() };
        let e = bad(QdParams { constants: heavy, radius_nm: 5.0, ..d });
        assert!(e.contains("gap_energy"), "{e}");
        let e = QdModel::new(d, QdIndex::CdSe, Substrate::Constant { eta: -1.0, k: 0.0 }).unwrap_err().to_string();
        assert!(e.contains("eta"), "{e}");
    }
}
