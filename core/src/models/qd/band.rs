//! The quantum-dot band (sec. 3 of Benamira & Pattanaik 2023): Table 1 constants,
//! the Brus equation and Stokes shift ([`QdBand`], eqs. 1–3 and 6), the Gaussian and
//! logistic line shapes (eqs. 29–31), and the λ grid the tables and integrals use.

use std::f64::consts::PI;

use crate::error::check_range;
use crate::{Error, Result};

/// Base step of the λ grid of the tables, nm (default of `table_step`).
pub const TABLE_STEP_NM: f64 = 1.0;
/// Valid range of `table_step`, nm.
pub const TABLE_STEP_RANGE_NM: (f64, f64) = (0.05, 50.0);
/// Refinement of the λ grid near λQD: nodes every δλ / this.
pub const TABLE_REFINE: f64 = 8.0;
/// The quantum-absorption Gaussian is zero beyond this many δλ from λQD.
pub const GAUSS_CUTOFF: f64 = 10.0;
/// Valid range of the dot radius, nm.
pub const RADIUS_RANGE_NM: (f64, f64) = (1.0, 5.0);
/// Valid range of the Gaussian width δλ, nm.
pub const WIDTH_RANGE_NM: (f64, f64) = (0.01, 100.0);
/// Valid range of the integration limits λmin, λmax, nm.
pub const LAMBDA_RANGE_NM: (f64, f64) = (200.0, 1200.0);
/// Band edges λQD the constants may give, nm: wide around the visible (CdSe dots of
/// 1–5 nm sit at 400–690 nm), so that only absurd constants are refused.
pub const BAND_RANGE_NM: (f64, f64) = (100.0, 5000.0);
/// Largest Stokes shift the constants may give, nm: far above the largest of the valid
/// parameter box with the paper's constants (8.1e3 nm at radius 1 nm, width 100 nm).
pub const MAX_STOKES_SHIFT_NM: f64 = 1e6;

/// Physical constants of the Brus equation and Stokes shift (SI units), Table 1
/// values (CdSe) by default. Each may be overridden.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct QdConstants {
    /// Bulk band gap E_gap, J.
    pub gap_energy: f64,
    /// Elementary charge e, C.
    pub elementary_charge: f64,
    /// Planck constant h, J·s.
    pub planck: f64,
    /// Speed of light c, m/s.
    pub light_speed: f64,
    /// Boltzmann constant kB, J/K.
    pub boltzmann: f64,
    /// Effective electron mass me, kg.
    pub electron_mass: f64,
    /// Effective hole mass mh, kg.
    pub hole_mass: f64,
    /// Vacuum permittivity ε0, F/m.
    pub vacuum_permittivity: f64,
    /// Relative permittivity εr of the dot material.
    pub relative_permittivity: f64,
    /// Temperature T, K.
    pub temperature: f64,
}

impl Default for QdConstants {
    /// Table 1 of the paper (CdSe).
    fn default() -> Self {
        Self {
            gap_energy: 2.8e-19,
            elementary_charge: 1.6e-19,
            planck: 6.63e-34,
            light_speed: 3.0e8,
            boltzmann: 1.38e-23,
            electron_mass: 1.18e-31,
            hole_mass: 4.09e-31,
            vacuum_permittivity: 8.85e-12,
            relative_permittivity: 5.8,
            temperature: 293.0,
        }
    }
}

impl QdConstants {
    /// The constants with their parameter names, for validation and display.
    pub fn named(&self) -> [(&'static str, f64); 10] {
        [
            ("gap_energy", self.gap_energy),
            ("elementary_charge", self.elementary_charge),
            ("planck", self.planck),
            ("light_speed", self.light_speed),
            ("boltzmann", self.boltzmann),
            ("electron_mass", self.electron_mass),
            ("hole_mass", self.hole_mass),
            ("vacuum_permittivity", self.vacuum_permittivity),
            ("relative_permittivity", self.relative_permittivity),
            ("temperature", self.temperature),
        ]
    }

    /// `name = value` of those of `involved` that differ from the defaults (the ones
    /// the user set), or of all of `involved` when none does: what an error blames.
    fn blame(&self, involved: &[&str]) -> String {
        let defaults = Self::default().named();
        let pick = |changed_only: bool| -> Vec<String> {
            self.named()
                .iter()
                .zip(defaults.iter())
                .filter(|((n, v), (_, d))| involved.contains(n) && (!changed_only || v != d))
                .map(|((n, v), _)| format!("\"{n}\" = {}", crate::num(*v)))
                .collect()
        };
        let changed = pick(true);
        if changed.is_empty() { pick(false) } else { changed }.join(", ")
    }

    /// Every constant must be finite and positive.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in self.named() {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::param(name, v, "(0, ∞), finite"));
            }
        }
        Ok(())
    }

    /// Coulomb energy −1.8 e² / (4π ε0 εr R), J (eq. 2).
    pub fn coulomb_energy(&self, radius_nm: f64) -> f64 {
        let r = radius_nm * 1e-9;
        -1.8 * self.elementary_charge * self.elementary_charge
            / (4.0 * PI * self.vacuum_permittivity * self.relative_permittivity * r)
    }

    /// Confinement energy h² (me + mh) / (8 R² me mh), J (eq. 2).
    pub fn confinement_energy(&self, radius_nm: f64) -> f64 {
        let r = radius_nm * 1e-9;
        self.planck * self.planck * (self.electron_mass + self.hole_mass)
            / (8.0 * r * r * self.electron_mass * self.hole_mass)
    }
}

/// Absorption threshold and emission peak of one dot size (sec. 3).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct QdBand {
    /// Radius R, nm.
    pub radius_nm: f64,
    /// Gaussian width δλ, nm.
    pub width_nm: f64,
    /// E_abs = E_gap + E_coul + E_conf, J (eq. 1).
    pub absorption_energy_j: f64,
    /// Threshold wavelength λQD = hc / E_abs, nm (eq. 3).
    pub lambda_qd_nm: f64,
    /// Stokes shift Sλ, nm (eq. 6).
    pub stokes_shift_nm: f64,
    /// Emission peak λQD + Sλ, nm.
    pub emission_peak_nm: f64,
}

impl QdBand {
    /// Evaluate eqs. 1–3 and 6; errors name the offending parameter.
    pub fn new(constants: &QdConstants, radius_nm: f64, width_nm: f64) -> Result<Self> {
        constants.validate()?;
        check_range("radius", radius_nm, RADIUS_RANGE_NM.0, RADIUS_RANGE_NM.1)?;
        check_range("width", width_nm, WIDTH_RANGE_NM.0, WIDTH_RANGE_NM.1)?;
        let e = constants.gap_energy + constants.coulomb_energy(radius_nm) + constants.confinement_energy(radius_nm);
        if !(e.is_finite() && e > 0.0) {
            return Err(Error::param(
                "gap_energy",
                constants.gap_energy,
                format!("a value making E_abs = E_gap + E_coul + E_conf > 0 at radius {radius_nm} nm (got {e:e} J)"),
            ));
        }
        let hc = constants.planck * constants.light_speed;
        let lambda_qd_nm = hc / e * 1e9;
        if !(lambda_qd_nm >= BAND_RANGE_NM.0 && lambda_qd_nm <= BAND_RANGE_NM.1) {
            return Err(Error::data(format!(
                "invalid constants {}: the band edge λQD = h c / E_abs = {} nm at radius {} nm; valid range is [{}, {}] nm",
                constants.blame(&[
                    "planck",
                    "light_speed",
                    "gap_energy",
                    "elementary_charge",
                    "electron_mass",
                    "hole_mass",
                    "vacuum_permittivity",
                    "relative_permittivity"
                ]),
                crate::num(lambda_qd_nm),
                crate::num(radius_nm),
                BAND_RANGE_NM.0,
                BAND_RANGE_NM.1
            )));
        }
        let thermal_nm = hc / (constants.boltzmann * constants.temperature) * 1e9;
        let stokes_shift_nm = thermal_nm * width_nm * width_nm / (lambda_qd_nm * lambda_qd_nm);
        if !(stokes_shift_nm <= MAX_STOKES_SHIFT_NM) {
            return Err(Error::data(format!(
                "invalid constants {}: Stokes shift h c w² / (k T λQD²) = {} nm at λQD = {} nm; valid is at most {} nm",
                constants.blame(&["boltzmann", "temperature", "planck", "light_speed"]),
                crate::num(stokes_shift_nm),
                crate::num(lambda_qd_nm),
                crate::num(MAX_STOKES_SHIFT_NM)
            )));
        }
        Ok(Self {
            radius_nm,
            width_nm,
            absorption_energy_j: e,
            lambda_qd_nm,
            stokes_shift_nm,
            emission_peak_nm: lambda_qd_nm + stokes_shift_nm,
        })
    }
}

/// G(λ, λm, δ) = exp(−(λ − λm)²/δ²) (eq. 29).
pub fn gaussian(lambda: f64, mean: f64, delta: f64) -> f64 {
    let x = (lambda - mean) / delta;
    (-x * x).exp()
}

/// Logistic density L(λ, λm, s) (eq. 30), unit integral over ℝ; evaluated as
/// e^{−|u|} / (s (1 + e^{−|u|})²) so that no exponential overflows.
pub fn logistic(lambda: f64, mean: f64, scale: f64) -> f64 {
    let e = (-((lambda - mean) / scale).abs()).exp();
    e / (scale * (1.0 + e) * (1.0 + e))
}

/// Logistic CDF Λ(λ, λm, s) = 1 / (1 + exp(−(λ − λm)/s)) (eq. 31).
pub fn logistic_cdf(lambda: f64, mean: f64, scale: f64) -> f64 {
    let u = (lambda - mean) / scale;
    if u >= 0.0 {
        1.0 / (1.0 + (-u).exp())
    } else {
        let e = u.exp();
        e / (1.0 + e)
    }
}

/// 1 − Λ, accurate in the upper tail.
pub(super) fn logistic_survival(lambda: f64, mean: f64, scale: f64) -> f64 {
    logistic_cdf(-lambda, -mean, scale)
}

/// G(λ, λm, δ) cut to zero beyond ±[`GAUSS_CUTOFF`]·δ of λm.
pub(super) fn cut_gaussian(lambda: f64, mean: f64, delta: f64) -> f64 {
    if (lambda - mean).abs() > GAUSS_CUTOFF * delta {
        0.0
    } else {
        gaussian(lambda, mean, delta)
    }
}

/// λmin and λmax inside [`LAMBDA_RANGE_NM`], λmin < λmax.
pub(super) fn check_lambda_range(r: (f64, f64)) -> Result<()> {
    check_range("lambda_min", r.0, LAMBDA_RANGE_NM.0, LAMBDA_RANGE_NM.1)?;
    check_range("lambda_max", r.1, LAMBDA_RANGE_NM.0, LAMBDA_RANGE_NM.1)?;
    if !(r.1 > r.0) {
        return Err(Error::param("lambda_max", r.1, format!("(lambda_min = {}, {}]", r.0, LAMBDA_RANGE_NM.1)));
    }
    Ok(())
}

/// The λ grid of the tables: uniform segments between the range's ends and the cut points
/// λQD and λQD ± GAUSS_CUTOFF·δλ (the band's centre and the cut Gaussian's ends, where
/// the tabulated functions bend), each with the largest step ≤ `base_step` that divides
/// it, and ≤ δλ/TABLE_REFINE inside the band. Piecewise uniform (at most four segments),
/// so that the renderer finds a cell by arithmetic (fluo_qd's LaneGrid segments); a cut
/// point within `MIN_SEGMENT_NM` of another end is dropped.
pub(super) fn lambda_grid(range: (f64, f64), band: &QdBand, base_step: f64) -> Vec<f64> {
    const MIN_SEGMENT_NM: f64 = 1e-2;
    let (lo, hi) = range;
    let (c, d) = (band.lambda_qd_nm, band.width_nm);
    let fine = base_step.min(d / TABLE_REFINE);
    let mut ends = vec![lo];
    for cut in [c - GAUSS_CUTOFF * d, c, c + GAUSS_CUTOFF * d] {
        if cut > ends[ends.len() - 1] + MIN_SEGMENT_NM && cut < hi - MIN_SEGMENT_NM {
            ends.push(cut);
        }
    }
    ends.push(hi);
    let mut g = Vec::new();
    for w in ends.windows(2) {
        let (s, e) = (w[0], w[1]);
        // (segments end at the cut points, or within MIN_SEGMENT_NM of a dropped one)
        let mid = 0.5 * (s + e);
        let inside = mid > c - GAUSS_CUTOFF * d && mid < c + GAUSS_CUTOFF * d;
        let step = if inside { fine } else { base_step };
        let n = ((e - s) / step).ceil().max(1.0) as usize;
        g.extend((0..n).map(|i| s + (e - s) * i as f64 / n as f64));
    }
    g.push(hi);
    g
}

/// Buckets per node of a [`LambdaIndex`].
const BUCKETS_PER_NODE: usize = 2;

/// Cell lookup on the (piecewise-uniform, not uniform) λ grid of the tables: equal
/// buckets over the grid, each holding the cells it overlaps, so that a lookup is one
/// division and, in the rare bucket spanning several nodes (the refinement near λQD
/// for δλ < 8 nm), a bisection over those few. The result is the plain bisection's.
/// It also indexes the running integral of μa (non-decreasing, flat where μa = 0), which
/// inverts the excitation CDF: the buckets are then equal in probability.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct LambdaIndex {
    start: f64,
    /// Buckets per nm.
    inv_width: f64,
    /// Cell at the start of bucket b, for b = 0..=buckets.
    first: Vec<u32>,
}

impl LambdaIndex {
    /// Heap bytes of the index.
    pub(super) fn heap_bytes(&self) -> usize {
        self.first.len() * std::mem::size_of::<u32>()
    }

    /// Index `grid` (non-decreasing, ≥ 2 nodes; an empty span leaves every lookup to the
    /// bisection).
    pub(super) fn new(grid: &[f64]) -> Self {
        let n = grid.len();
        let (start, end) = (grid[0], grid[n - 1]);
        let buckets = BUCKETS_PER_NODE * n;
        let inv_width = if end > start { buckets as f64 / (end - start) } else { 0.0 };
        let first =
            (0..=buckets).map(|b| bisect(grid, start + (end - start) * (b as f64 / buckets as f64)) as u32).collect();
        Self { start, inv_width, first }
    }

    /// Number of bucket entries held.
    pub(super) fn len(&self) -> usize {
        self.first.len()
    }

    /// The cell i ∈ [0, n − 2] with grid[i] ≤ x < grid[i + 1] (clamped at the ends),
    /// as `bisect`; x is not NaN.
    #[inline]
    pub(super) fn cell(&self, grid: &[f64], x: f64) -> usize {
        let buckets = self.first.len() - 1;
        let b = (((x - self.start) * self.inv_width).max(0.0) as usize).min(buckets - 1);
        let (lo, hi) = (self.first[b] as usize, self.first[b + 1] as usize);
        let i = lo + grid[lo + 1..=hi].partition_point(|&g| g <= x);
        // Guard against a bucket edge rounded across a node: then bisect the whole grid.
        let last = grid.len() - 2;
        let ok = (i == 0 || grid[i] <= x) && (i == last || x < grid[i + 1]);
        if ok {
            i
        } else {
            bisect(grid, x)
        }
    }
}

/// Bisection: the last cell i ≤ n − 2 with grid[i] ≤ x (0 below the grid).
pub(super) fn bisect(grid: &[f64], x: f64) -> usize {
    grid.partition_point(|&g| g <= x).clamp(1, grid.len() - 1) - 1
}

/// Trapezoidal ∫ f over the nodes of `grid`.
pub(super) fn trapezoid(grid: &[f64], f: impl Fn(f64) -> f64) -> f64 {
    grid.windows(2).map(|w| 0.5 * (w[1] - w[0]) * (f(w[0]) + f(w[1]))).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lambda_grid_is_piecewise_uniform() {
        // the renderer's LaneGrid finds cells by arithmetic over at most four uniform runs
        for (radius, width, step) in [(2.2, 15.0, 1.0), (3.3, 0.05, 1.0), (1.5, 2.0, 0.05), (5.0, 100.0, 50.0)] {
            let band = QdBand::new(&QdConstants::default(), radius, width).unwrap();
            let g = lambda_grid((300.0, 830.0), &band, step);
            assert_eq!((g[0], g[g.len() - 1]), (300.0, 830.0));
            let (a, b) =
                (band.lambda_qd_nm - GAUSS_CUTOFF * band.width_nm, band.lambda_qd_nm + GAUSS_CUTOFF * band.width_nm);
            let fine = step.min(band.width_nm / TABLE_REFINE);
            let mut runs = 1;
            for k in 0..g.len() - 1 {
                let h = g[k + 1] - g[k];
                let mid = 0.5 * (g[k] + g[k + 1]);
                assert!(h > 0.0 && h <= (if mid > a && mid < b { fine } else { step }) * (1.0 + 1e-9), "{k}: {h}");
                if k > 0 && (h - (g[k] - g[k - 1])).abs() > 1e-6 * h {
                    runs += 1;
                }
            }
            assert!(runs <= 4, "{runs} runs (R = {radius}, δλ = {width})");
        }
    }

    #[test]
    fn lambda_index_is_the_bisection() {
        for (radius, width, step) in [(2.2, 15.0, 1.0), (3.3, 0.05, 1.0), (1.5, 2.0, 0.05), (5.0, 100.0, 50.0)] {
            let band = QdBand::new(&QdConstants::default(), radius, width).unwrap();
            let grid = lambda_grid((300.0, 830.0), &band, step);
            let index = LambdaIndex::new(&grid);
            let mut xs: Vec<f64> = (0..=200_000).map(|i| 290.0 + 550.0 * i as f64 / 200_000.0).collect();
            for &g in &grid {
                xs.extend([g, f64::from_bits(g.to_bits() - 1), f64::from_bits(g.to_bits() + 1)]);
            }
            for x in xs {
                assert_eq!(index.cell(&grid, x), bisect(&grid, x), "x = {x}");
            }
        }
    }

    #[test]
    fn lambda_index_of_a_running_integral_is_the_bisection() {
        // Non-decreasing tables with flat runs (a running integral of a function that is 0
        // over whole cells, at the start, inside and at the end), and an empty span.
        let f = |i: usize| {
            if (40..90).contains(&i) || !(5..=170).contains(&i) {
                0.0
            } else {
                (i as f64 * 0.37).sin().abs()
            }
        };
        let mut cum = vec![0.0];
        for i in 0..200 {
            cum.push(cum[i] + 0.5 * (f(i) + f(i + 1)));
        }
        for table in [cum, vec![0.0; 7], vec![1.0, 1.0, 2.0, 2.0, 2.0, 3.0]] {
            let index = LambdaIndex::new(&table);
            let (lo, hi) = (table[0], table[table.len() - 1]);
            let mut xs: Vec<f64> = (0..=20_000).map(|i| lo - 1.0 + (hi - lo + 2.0) * i as f64 / 20_000.0).collect();
            for &g in &table {
                xs.extend([g, g - 1e-12, g + 1e-12]);
            }
            for x in xs {
                assert_eq!(index.cell(&table, x), bisect(&table, x), "x = {x}");
            }
        }
    }

    #[test]
    fn brus_equation_by_hand() {
        // R = 1.5 nm, Table 1 constants, evaluated by hand (see the module docs).
        let c = QdConstants::default();
        let r = 1.5e-9;
        let conf = 6.63e-34f64.powi(2) * (1.18e-31 + 4.09e-31) / (8.0 * r * r * 1.18e-31 * 4.09e-31);
        let coul = -1.8 * 1.6e-19f64.powi(2) / (4.0 * PI * 8.85e-12 * 5.8 * r);
        let lam = 6.63e-34 * 3e8 / (2.8e-19 + conf + coul) * 1e9;
        let b = QdBand::new(&c, 1.5, 15.0).unwrap();
        assert!((b.lambda_qd_nm - lam).abs() < 1e-9, "{} vs {lam}", b.lambda_qd_nm);
        assert!((b.lambda_qd_nm - 398.6).abs() < 0.5, "{}", b.lambda_qd_nm);
        let s = 6.63e-34 * 3e8 / (1.38e-23 * 293.0) * 225e-18 / (lam * 1e-9).powi(2) * 1e9;
        assert!((b.stokes_shift_nm - s).abs() < 1e-9);
        assert!((b.emission_peak_nm - (lam + s)).abs() < 1e-9);
    }

    #[test]
    fn band_grows_with_radius_and_shift_with_width() {
        // Fig. 5: λQD and the emission peak grow with R; Fig. 6: Sλ grows with δλ.
        let c = QdConstants::default();
        let mut prev = (0.0, 0.0);
        for r in [1.0, 1.5, 2.2, 3.3, 4.5, 5.0] {
            let b = QdBand::new(&c, r, 15.0).unwrap();
            assert!(b.lambda_qd_nm > prev.0 && b.emission_peak_nm > prev.1, "R = {r}");
            prev = (b.lambda_qd_nm, b.emission_peak_nm);
        }
        let mut prev = 0.0;
        for d in [10.0, 15.0, 20.0, 25.0, 30.0] {
            let b = QdBand::new(&c, 1.8, d).unwrap();
            assert!(b.stokes_shift_nm > prev);
            prev = b.stokes_shift_nm;
        }
    }
}
