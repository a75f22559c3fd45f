//! A fluorescent participating medium of quantum dots in a host ([`QdMedium`]):
//! absorption coefficient, reradiation per unit absorption and excitation sampling
//! for `fluo_qd_medium` and the `fluo_volpath` integrator (Benamira & Pattanaik 2023,
//! secs. 4.1 and 6.2).
//!
//! # Model
//! N dots per m³ with cross sections σ_abs(λ), σ_em(λ) of [`QdVolume`] (eqs. 7–15, eq. 7
//! read as in `index.rs`):
//!
//! ```text
//! μa(λ) = N σ_abs(λ),   N = c · N_A · 10⁻³   (c in µmol/L, N in 1/m³)
//! μa [1/m] = c [µmol/L] · σ_abs [nm²] · N_A · 10⁻²¹            (PER_M_PER_UM_NM2)
//! ```
//!
//! An absorbed photon at λi is re-emitted isotropically with probability Q, at
//! λo distributed as the logistic emission line L(λo; λQD + Sλ, δλ/2) normalised over
//! [λmin, λmax] (eqs. 10, 13, 15: ∫σ_em = Q ∫σ_abs over the range, i.e. per absorbed
//! photon Q·L/I):
//!
//! ```text
//! f(λi → λo) = Q · L(λo) / I · [λi < λo] · [λi, λo ∈ [λmin, λmax]]      (per nm of λo)
//! ```
//!
//! No anti-Stokes emission (sec. 3.1): the part of L below λi is not emitted and not
//! renormalised, so ∫ f dλo ≤ Q for every λi (re-emitted ≤ Q · absorbed, the energy
//! bound `fluo_volpath` is tested against). Absorption outside [λmin, λmax] is not
//! re-emitted (the paper normalises the emission over that range only). Q is an energy
//! yield, as for the surface model.
//!
//! A camera path at λo meeting the medium sees the source coefficient
//!
//! ```text
//! μf(λo) = ∫_R μa(λi) f(λi → λo) dλi = Q L(λo)/I · ∫_{max(R.lo, λmin)}^{min(R.hi, λo, λmax)} μa dλi
//! ```
//!
//! ([`QdMedium::shift_coefficient_per_m`]) next to the elastic scattering coefficient,
//! and samples λi ∝ μa(λi) over that interval ([`QdMedium::sample_excitation`], exact
//! inverse CDF), which makes the shift's weight μf exactly.
//!
//! # Parameters
//! | name            | unit    | valid range              | default |
//! |-----------------|---------|--------------------------|---------|
//! | `radius`        | nm      | [1, 5]                   | 2.2     |
//! | `width`         | nm      | [0.01, 100]              | 15      |
//! | `quantum_yield` | 1       | [0, 1]                   | 0.8     |
//! | `concentration` | µmol/L  | [0, 1e6]                 | 1       |
//! | `ext_ior`       | 1       | [1, 3] (host index)      | 1.446 (chloroform) |
//! | `lambda_min/max`| nm      | 200 ≤ min < max ≤ 1200   | 300/830 |
//! | `table_step`    | nm      | [0.05, 50]               | 1       |
//!
//! # Numerical notes
//! μa is tabulated on the λ grid of the surface model (`table_step`, refined to δλ/8
//! around λQD) over [λmin, λmax] and interpolated linearly there; this piecewise-linear
//! μa *is* the medium's absorption (extinction, excitation pdf and μf all use it, so
//! the estimator stays exact). Outside the range the formula is used. Measured against
//! the formula: within 0.5 % of max(μa(λ), μa(λQD)) at the defaults (cells of δλ/8 on
//! the Gaussian) (test
//! `table_matches_the_cross_section`). The inverse CDF solves the quadratic of a
//! linear piece in its cancellation-free form.
//!
//! # References
//! A. Benamira, S. Pattanaik, EGSR 2023, secs. 4.1, 6.2 and Figs. 5, 6, 11, 12.

use std::fmt;

use super::band::{
    check_lambda_range, lambda_grid, LambdaIndex, QdBand, QdConstants, TABLE_STEP_NM, TABLE_STEP_RANGE_NM,
};
use super::index::QdIndex;
use super::volume::QdVolume;
use crate::error::check_range;
use crate::Result;

/// Avogadro's number × 10⁻²¹: μ [1/m] = c [µmol/L] · σ `[nm²]` · this (1 µmol/L =
/// 10⁻³ mol/m³; 1 nm² = 10⁻¹⁸ m²).
pub const PER_M_PER_UM_NM2: f64 = 6.022_140_76e23 * 1e-21;
/// Valid range of `concentration`, µmol/L.
pub const CONCENTRATION_RANGE_UM: (f64, f64) = (0.0, 1e6);
/// Valid range of the host index `ext_ior`.
pub const HOST_IOR_RANGE: (f64, f64) = (1.0, 3.0);
/// Refractive index of chloroform at 589 nm, the paper's host (sec. 6.2).
pub const CHLOROFORM_IOR: f64 = 1.446;

/// User parameters of a QD medium (see the module table).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QdMediumParams {
    /// Dot radius R, nm.
    pub radius_nm: f64,
    /// Band width δλ, nm.
    pub width_nm: f64,
    /// Quantum yield Q.
    pub quantum_yield: f64,
    /// Molar concentration of dots, µmol/L.
    pub concentration_um: f64,
    /// Host index n_env.
    pub ext_ior: f64,
    /// Emission normalisation range, nm.
    pub lambda_min_nm: f64,
    /// Upper end, nm.
    pub lambda_max_nm: f64,
    /// Brus/Stokes constants (Table 1).
    pub constants: QdConstants,
    /// Base λ step of the absorption table, nm.
    pub table_step_nm: f64,
}

impl Default for QdMediumParams {
    fn default() -> Self {
        Self {
            radius_nm: 2.2,
            width_nm: 15.0,
            quantum_yield: 0.8,
            concentration_um: 1.0,
            ext_ior: CHLOROFORM_IOR,
            lambda_min_nm: 300.0,
            lambda_max_nm: 830.0,
            constants: QdConstants::default(),
            table_step_nm: TABLE_STEP_NM,
        }
    }
}

/// The excitation of one λo (QdMedium::excitation).
struct Excitation {
    e: f64,
    a: f64,
    b: f64,
    ca: f64,
    cb: f64,
}

impl Excitation {
    /// μf = e(λo) ∫_a^b μa, 1/m.
    fn mu_f(&self) -> f64 {
        self.e * (self.cb - self.ca).max(0.0)
    }
}

/// A validated, baked QD medium.
#[derive(Debug, Clone)]
pub struct QdMedium {
    params: QdMediumParams,
    volume: QdVolume,
    grid: Vec<f64>,
    index: LambdaIndex,
    /// μa at the grid nodes, 1/m.
    mu_a: Vec<f64>,
    /// ∫ μa from grid[0] to each node (piecewise linear, exact), nm/m.
    cum: Vec<f64>,
    /// Cell lookup in `cum` (inverting the excitation CDF).
    cum_index: LambdaIndex,
    /// I of eq. 13.
    emission_norm: f64,
}

impl QdMedium {
    /// Bytes the medium occupies at render time: the struct and its tables (λ grid, μa,
    /// its running integral, the grid's index).
    pub fn bytes_at_render_time(&self) -> usize {
        std::mem::size_of::<Self>()
            + 8 * (self.grid.len() + self.mu_a.len() + self.cum.len())
            + self.index.heap_bytes()
            + self.cum_index.heap_bytes()
    }

    /// Validate and bake (errors name the parameter, its value and the valid range).
    pub fn new(params: QdMediumParams) -> Result<Self> {
        check_range("concentration", params.concentration_um, CONCENTRATION_RANGE_UM.0, CONCENTRATION_RANGE_UM.1)?;
        check_range("ext_ior", params.ext_ior, HOST_IOR_RANGE.0, HOST_IOR_RANGE.1)?;
        check_range("table_step", params.table_step_nm, TABLE_STEP_RANGE_NM.0, TABLE_STEP_RANGE_NM.1)?;
        let range = (params.lambda_min_nm, params.lambda_max_nm);
        check_lambda_range(range)?;
        let band = QdBand::new(&params.constants, params.radius_nm, params.width_nm)?;
        let volume = QdVolume::new(band, QdIndex::CdSe, params.ext_ior, params.quantum_yield, range)?;
        let grid = lambda_grid(range, &band, params.table_step_nm);
        let k = params.concentration_um * PER_M_PER_UM_NM2;
        let mu_a: Vec<f64> = grid.iter().map(|&l| k * volume.absorption_cross_section_nm2(l)).collect();
        let cum = crate::spectrum::running_trapezoid(&grid, &mu_a);
        let index = LambdaIndex::new(&grid);
        let cum_index = LambdaIndex::new(&cum);
        let emission_norm = volume.emission_normalisation();
        Ok(Self { params, volume, grid, index, mu_a, cum, cum_index, emission_norm })
    }

    /// The parameters it was built from.
    pub fn params(&self) -> &QdMediumParams {
        &self.params
    }

    /// The dots' band (λQD, Stokes shift, emission peak).
    pub fn band(&self) -> &QdBand {
        self.volume.band()
    }

    /// Whether anything is ever re-emitted (Q > 0, c > 0, a non-empty emission line).
    pub fn is_fluorescent(&self) -> bool {
        self.params.quantum_yield > 0.0
            && self.params.concentration_um > 0.0
            && self.emission_norm > 0.0
            && self.cum.last().is_some_and(|&c| c > 0.0)
    }

    /// [λmin, λmax], nm: where absorption can re-emit, and where it re-emits to.
    pub fn lambda_range(&self) -> (f64, f64) {
        (self.params.lambda_min_nm, self.params.lambda_max_nm)
    }

    /// The cell of λ inside the table and its linear weight.
    fn locate(&self, lambda_nm: f64) -> Option<(usize, f64)> {
        let (lo, hi) = self.lambda_range();
        if !(lambda_nm >= lo && lambda_nm <= hi) {
            return None;
        }
        let i = self.index.cell(&self.grid, lambda_nm);
        let (x0, x1) = (self.grid[i], self.grid[i + 1]);
        Some((i, ((lambda_nm - x0) / (x1 - x0)).clamp(0.0, 1.0)))
    }

    /// Absorption coefficient μa(λ), 1/m (the table inside [λmin, λmax], the formula
    /// outside).
    pub fn absorption_per_m(&self, lambda_nm: f64) -> f64 {
        match self.locate(lambda_nm) {
            Some((i, t)) => self.mu_a_at(i, t),
            None if lambda_nm.is_finite() && lambda_nm > 0.0 => {
                self.params.concentration_um * PER_M_PER_UM_NM2 * self.volume.absorption_cross_section_nm2(lambda_nm)
            }
            None => 0.0,
        }
    }

    /// The nodes of the μa table (the model's own grid over [λmin, λmax]; μa is linear
    /// between them there).
    pub fn absorption_nodes(&self) -> &[f64] {
        &self.grid
    }

    /// μa in cell i at fraction t of it (the table's linear interpolation), 1/m.
    #[inline]
    fn mu_a_at(&self, i: usize, t: f64) -> f64 {
        self.mu_a[i] + t * (self.mu_a[i + 1] - self.mu_a[i])
    }

    /// ∫ μa from λmin to λ (λ clamped to the range), nm/m.
    fn cumulative(&self, lambda_nm: f64) -> f64 {
        let (lo, hi) = self.lambda_range();
        let l = lambda_nm.clamp(lo, hi);
        if l == lo {
            return 0.0;
        }
        match self.locate(l) {
            // one cell lookup: μa(l) from the same cell
            Some((i, t)) => self.cum[i] + 0.5 * (l - self.grid[i]) * (self.mu_a[i] + self.mu_a_at(i, t)),
            None => 0.0,
        }
    }

    /// Emission per unit absorbed power per nm of λo, Q L(λo)/I on [λmin, λmax]
    /// (before the no-anti-Stokes cut).
    pub fn emission_per_nm(&self, lambda_o_nm: f64) -> f64 {
        let (lo, hi) = self.lambda_range();
        if !(lambda_o_nm >= lo && lambda_o_nm <= hi && self.emission_norm > 0.0) {
            return 0.0;
        }
        let b = self.volume.band();
        self.params.quantum_yield * super::band::logistic(lambda_o_nm, b.emission_peak_nm, 0.5 * b.width_nm)
            / self.emission_norm
    }

    /// f(λi → λo): re-emitted power per nm of λo per unit power absorbed at λi.
    pub fn reradiation_per_nm(&self, lambda_i_nm: f64, lambda_o_nm: f64) -> f64 {
        let (lo, hi) = self.lambda_range();
        if !(lambda_i_nm < lambda_o_nm && lambda_i_nm >= lo && lambda_i_nm <= hi) {
            return 0.0;
        }
        self.emission_per_nm(lambda_o_nm)
    }

    /// The excitation interval for λo within the light's range R, or None when empty.
    fn excitation_interval(&self, lambda_o_nm: f64, range: (f64, f64)) -> Option<(f64, f64)> {
        let (lo, hi) = self.lambda_range();
        let a = range.0.max(lo);
        let b = range.1.min(hi).min(lambda_o_nm);
        (a < b).then_some((a, b))
    }

    /// μf(λo) = ∫_R μa(λi) f(λi → λo) dλi, 1/m: the source coefficient a camera path
    /// at λo sees from excitations in R (nm).
    pub fn shift_coefficient_per_m(&self, lambda_o_nm: f64, range: (f64, f64)) -> f64 {
        self.excitation(lambda_o_nm, range).map_or(0.0, |x| x.mu_f())
    }

    /// What λo re-emits from R: its emission e(λo) and the excitation interval [a, b] with
    /// the running integrals of μa at its ends; None where nothing is re-emitted.
    fn excitation(&self, lambda_o_nm: f64, range: (f64, f64)) -> Option<Excitation> {
        let e = self.emission_per_nm(lambda_o_nm);
        if !(e > 0.0) {
            return None;
        }
        let (a, b) = self.excitation_interval(lambda_o_nm, range)?;
        Some(Excitation { e, a, b, ca: self.cumulative(a), cb: self.cumulative(b) })
    }

    /// Sample λi ∝ μa(λi) over the excitation interval of λo in R (exact inverse CDF
    /// of the piecewise-linear μa); (λi, pdf per nm), or None where μf(λo) = 0.
    pub fn sample_excitation(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> Option<(f64, f64)> {
        let (a, b) = self.excitation_interval(lambda_o_nm, range)?;
        self.sample_between(a, b, self.cumulative(a), self.cumulative(b), xi)
    }

    /// μf(λo | R) and a λi sampled as [`QdMedium::sample_excitation`] with `xi`, sharing
    /// the integrals (one call per shifted wavelength at a fluorescent collision).
    pub fn shift_and_sample(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> (f64, Option<(f64, f64)>) {
        match self.excitation(lambda_o_nm, range) {
            Some(x) => (x.mu_f(), self.sample_between(x.a, x.b, x.ca, x.cb, xi)),
            None => (0.0, None),
        }
    }

    /// λi ∝ μa on [a, b], whose running integrals are ca and cb (exact inverse CDF).
    fn sample_between(&self, a: f64, b: f64, ca: f64, cb: f64, xi: f64) -> Option<(f64, f64)> {
        let total = cb - ca;
        if !(total > 0.0 && total.is_finite()) {
            return None;
        }
        let target = ca + xi.clamp(0.0, 1.0) * total;
        // The cell holding `target` (the last i with cum[i] ≤ target: cum is non-decreasing).
        let i = self.cum_index.cell(&self.cum, target);
        let (x0, x1) = (self.grid[i], self.grid[i + 1]);
        let (f0, f1) = (self.mu_a[i], self.mu_a[i + 1]);
        let s = (target - self.cum[i]).max(0.0);
        let h = x1 - x0;
        // ∫_0^u (f0 + (f1 − f0) t/h) dt = s  ⇒  u = 2s / (f0 + sqrt(f0² + 2(f1 − f0)s/h)).
        let disc = (f0 * f0 + 2.0 * (f1 - f0) * s / h).max(0.0);
        let denom = f0 + disc.sqrt();
        let u = if denom > 0.0 { (2.0 * s / denom).min(h) } else { 0.0 };
        let lambda_i = (x0 + u).clamp(a, b);
        // μa(λi) from the cell just found (a lookup only if the clamp left it)
        let mu = if lambda_i >= x0 && lambda_i <= x1 {
            self.mu_a_at(i, ((lambda_i - x0) / h).clamp(0.0, 1.0))
        } else {
            self.absorption_per_m(lambda_i)
        };
        let pdf = mu / total;
        (pdf > 0.0 && pdf.is_finite()).then_some((lambda_i, pdf))
    }

    /// The density of [`QdMedium::sample_excitation`] at λi, per nm.
    pub fn excitation_pdf(&self, lambda_o_nm: f64, range: (f64, f64), lambda_i_nm: f64) -> f64 {
        let Some((a, b)) = self.excitation_interval(lambda_o_nm, range) else {
            return 0.0;
        };
        if !(lambda_i_nm >= a && lambda_i_nm <= b) {
            return 0.0;
        }
        let total = self.cumulative(b) - self.cumulative(a);
        if total > 0.0 {
            self.absorption_per_m(lambda_i_nm) / total
        } else {
            0.0
        }
    }
}

impl fmt::Display for QdMedium {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let p = &self.params;
        let b = self.volume.band();
        write!(
            f,
            "QdMedium[radius = {} nm, width = {} nm, quantum_yield = {}, concentration = {} µmol/L, ext_ior = {}, \
             λQD = {:.1} nm, emission peak = {:.1} nm, μa(350 nm) = {:.4e} 1/m, range = [{}, {}] nm]",
            p.radius_nm,
            p.width_nm,
            p.quantum_yield,
            p.concentration_um,
            p.ext_ior,
            b.lambda_qd_nm,
            b.emission_peak_nm,
            self.absorption_per_m(350.0),
            p.lambda_min_nm,
            p.lambda_max_nm
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn medium(r: f64, q: f64) -> QdMedium {
        QdMedium::new(QdMediumParams { radius_nm: r, quantum_yield: q, ..Default::default() }).unwrap()
    }

    /// ∫ g over [a, b] by composite Simpson with n (even) intervals.
    fn simpson(a: f64, b: f64, n: usize, g: impl Fn(f64) -> f64) -> f64 {
        let h = (b - a) / n as f64;
        let mut s = g(a) + g(b);
        for i in 1..n {
            s += if i % 2 == 1 { 4.0 } else { 2.0 } * g(a + i as f64 * h);
        }
        s * h / 3.0
    }

    #[test]
    fn table_matches_the_cross_section() {
        let m = medium(2.2, 0.8);
        let v = &m.volume;
        for i in 0..5300 {
            let l = 300.0 + 0.1 * i as f64 + 0.037;
            let exact = PER_M_PER_UM_NM2 * v.absorption_cross_section_nm2(l);
            let t = m.absorption_per_m(l);
            let peak = PER_M_PER_UM_NM2 * v.absorption_cross_section_nm2(v.band().lambda_qd_nm);
            assert!((t - exact).abs() <= 5e-3 * exact.max(peak), "λ = {l}: {t} vs {exact}");
        }
        // Outside the range: the formula.
        let l = 250.0;
        assert_eq!(m.absorption_per_m(l), PER_M_PER_UM_NM2 * v.absorption_cross_section_nm2(l));
    }

    #[test]
    fn shift_coefficient_and_sampling_agree_with_quadrature() {
        let m = medium(2.7, 0.8);
        let range = (300.0, 830.0);
        for lo in [480.0, 560.0, 600.0, 700.0] {
            let mu_f = m.shift_coefficient_per_m(lo, range);
            let q = simpson(300.0, lo, 20000, |l| m.absorption_per_m(l) * m.reradiation_per_nm(l, lo));
            // Simpson across the table's kinks: 1e-4.
            assert!((mu_f - q).abs() <= 1e-4 * q, "λo = {lo}: {mu_f} vs {q}");
            // The sampler's density integrates to one and matches its histogram.
            if mu_f > 0.0 {
                let n = 200_000;
                let bins = 20;
                let mut hist = vec![0usize; bins];
                for k in 0..n {
                    let xi = (k as f64 + 0.5) / n as f64;
                    let (l, pdf) = m.sample_excitation(lo, range, xi).unwrap();
                    assert!((pdf - m.excitation_pdf(lo, range, l)).abs() <= 1e-9 * pdf);
                    let b = (((l - 300.0) / (lo - 300.0)) * bins as f64) as usize;
                    hist[b.min(bins - 1)] += 1;
                }
                for (b, &h) in hist.iter().enumerate() {
                    let (a, c) = (
                        300.0 + (lo - 300.0) * b as f64 / bins as f64,
                        300.0 + (lo - 300.0) * (b + 1) as f64 / bins as f64,
                    );
                    let p = simpson(a, c, 2000, |l| m.excitation_pdf(lo, range, l));
                    assert!((h as f64 / n as f64 - p).abs() < 2e-4, "bin {b}: {} vs {p}", h as f64 / n as f64);
                }
            }
        }
    }

    #[test]
    fn reemission_never_exceeds_the_yield() {
        for r in [1.0, 1.5, 2.2, 3.3, 5.0] {
            for q in [0.0, 0.5, 1.0] {
                let m = medium(r, q);
                for li in [300.0, 350.0, 420.0, 500.0, 650.0, 800.0] {
                    let out = simpson(li, 830.0, 20000, |lo| m.reradiation_per_nm(li, lo));
                    assert!(out <= q + 1e-9 && out >= 0.0, "R = {r}, Q = {q}, λi = {li}: {out}");
                }
                assert_eq!(m.is_fluorescent(), q > 0.0);
                // Everything finite over the whole range.
                for i in 0..=1000 {
                    let l = 200.0 + i as f64;
                    assert!(m.absorption_per_m(l).is_finite() && m.absorption_per_m(l) >= 0.0);
                    assert!(m.shift_coefficient_per_m(l, (300.0, 830.0)).is_finite());
                }
            }
        }
        // Q = 1 and the whole line above λi: exactly the yield (to quadrature accuracy).
        let m = medium(2.2, 1.0);
        let out = simpson(300.0, 830.0, 40000, |lo| m.reradiation_per_nm(300.0, lo));
        assert!((out - 1.0).abs() < 1e-6, "{out}");
    }

    #[test]
    fn a_lamp_outside_the_band_excites_nothing() {
        let m = medium(2.2, 1.0);
        let peak = m.band().emission_peak_nm;
        // Light only above the emission: nothing reaches λo from below.
        assert_eq!(m.shift_coefficient_per_m(peak, (peak + 1.0, 830.0)), 0.0);
        assert!(m.sample_excitation(peak, (peak + 1.0, 830.0), 0.5).is_none());
        // Light only below λmin: nothing.
        assert_eq!(m.shift_coefficient_per_m(peak, (200.0, 299.0)), 0.0);
    }

    #[test]
    fn bad_parameters_name_themselves() {
        for (p, name) in [
            (QdMediumParams { radius_nm: 0.5, ..Default::default() }, "radius"),
            (QdMediumParams { radius_nm: f64::NAN, ..Default::default() }, "radius"),
            (QdMediumParams { quantum_yield: 1.5, ..Default::default() }, "quantum_yield"),
            (QdMediumParams { concentration_um: -1.0, ..Default::default() }, "concentration"),
            (QdMediumParams { ext_ior: 0.5, ..Default::default() }, "ext_ior"),
            (QdMediumParams { lambda_max_nm: 250.0, ..Default::default() }, "lambda_max"),
            (QdMediumParams { width_nm: 0.0, ..Default::default() }, "width"),
        ] {
            let e = QdMedium::new(p).unwrap_err().to_string();
            assert!(e.contains(name), "{name}: {e}");
        }
    }
}
