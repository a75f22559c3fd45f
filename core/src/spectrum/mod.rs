//! Sampled spectra, colour matching functions and CIE illuminants.
//!
//! A spectrum is a real function of wavelength `λ` in nm. Two sampled forms exist:
//!
//! - [`RegularSpectrum`]: samples `v_i` at `λ_i = start_nm + i·step_nm`, `i = 0..n`;
//! - [`IrregularSpectrum`]: samples `v_i` at strictly increasing `λ_i`.
//!
//! Both are evaluated by piecewise-linear interpolation and are exactly zero outside
//! `[λ_0, λ_{n-1}]`:
//!
//! ```text
//! S(λ) = (1 − t)·v_i + t·v_{i+1},   t = (λ − λ_i) / (λ_{i+1} − λ_i),   λ_i ≤ λ ≤ λ_{i+1}
//! ```
//!
//! An irregular spectrum whose wavelengths are in fact evenly spaced (a CIE table
//! converted for a renderer) is detected as such once and indexed directly.
//!
//! Integrals use the trapezoid rule, which is exact for such piecewise-linear data
//! on its own samples:
//!
//! ```text
//! ∫ S dλ ≈ Σ_i (λ_{i+1} − λ_i)·(v_i + v_{i+1}) / 2
//! ```
//!
//! Products of two spectra (e.g. an illuminant times a colour matching function) are
//! integrated the same way on a caller-given regular grid
//! ([`Spectral::integrate_product`]); [`Cmf::xyz_of`] uses the CMF's own 1 nm grid, as
//! CIE 015:2018 recommends.
//!
//! Anything that implements [`Spectral`] (both sampled types, and any closure
//! `Fn(f64) -> f64` of the wavelength in nm) can be evaluated, resampled and
//! integrated, so models can take either.
//!
//! # Data
//! The tables under `data/spectra/` (CIE 1931 and CIE 2006 2° CMFs, the daylight basis
//! S0/S1/S2, and the tabulated CIE D65, FL1–FL12, HP1–HP5) are embedded with
//! `include_str!` and parsed once, on first use. They were written by
//! `tools/gen_spectral_data.py` from colour-science; each file's header names the
//! version and dataset key. Illuminants A (its defining formula), E and the D series
//! other than D65 ([`daylight`]) are computed.
//!
//! # References
//! - CIE 015:2018, *Colorimetry*, 4th edition.
//! - CIE 170-2:2015, *Fundamental chromaticity diagram with physiological axes — Part 2*.
//! - Wyszecki & Stiles (1982), *Color Science*, 2nd edition (daylight).

mod cmf;
mod csv;
mod illuminant;

pub use cmf::{cmf, Cmf, Observer};
pub use illuminant::{
    blackbody, blackbody_spectrum, check_lamp, daylight, illuminant, ILLUMINANT_NAMES, MAX_LAMP_VALUE,
};

use crate::{Error, Result};

/// Relative tolerance, in units of the grid step, for a wavelength to count as lying on
/// a regular grid (a tabulated nm column, or `end_nm` of a requested grid).
const GRID_TOLERANCE: f64 = 1e-9;

/// Largest number of samples a resampling or integration grid may have; it guards
/// against a tiny `step_nm` exhausting memory or time (1 pm steps over 10 µm).
pub const MAX_GRID_SAMPLES: usize = 10_000_000;

/// The running trapezoid integral of the piecewise-linear function with values `y` at the
/// nodes `x` (the same length): ∫ from `x[0]` to each node, exact for that function.
pub fn running_trapezoid(x: &[f64], y: &[f64]) -> Vec<f64> {
    let mut cum = Vec::with_capacity(x.len());
    let mut acc = 0.0;
    cum.push(0.0);
    for (w, m) in x.windows(2).zip(y.windows(2)) {
        acc += 0.5 * (w[1] - w[0]) * (m[0] + m[1]);
        cum.push(acc);
    }
    cum
}

/// A function of wavelength: anything that can be evaluated at `lambda_nm`.
///
/// Implemented by [`RegularSpectrum`], [`IrregularSpectrum`] and every closure
/// `Fn(f64) -> f64`, so `cmf.xyz_of(&|lambda_nm: f64| 1.0)` works.
pub trait Spectral {
    /// The value at wavelength `lambda_nm` (nm).
    fn eval(&self, lambda_nm: f64) -> f64;

    /// Sample `self` on the regular grid `start_nm, start_nm + step_nm, …, end_nm`.
    ///
    /// `end_nm − start_nm` must be a positive whole multiple of `step_nm`.
    fn resample(&self, start_nm: f64, end_nm: f64, step_nm: f64) -> Result<RegularSpectrum> {
        let n = grid_len(start_nm, end_nm, step_nm)?;
        let values = (0..n).map(|i| self.eval(step_nm.mul_add(i as f64, start_nm))).collect();
        RegularSpectrum::new(start_nm, step_nm, values)
    }

    /// `∫ self(λ)·other(λ) dλ` by the trapezoid rule on the regular grid
    /// `start_nm, start_nm + step_nm, …, end_nm` (same rules as [`Spectral::resample`]).
    fn integrate_product(&self, other: &dyn Spectral, start_nm: f64, end_nm: f64, step_nm: f64) -> Result<f64> {
        let n = grid_len(start_nm, end_nm, step_nm)?;
        let mut sum = 0.0;
        for i in 0..n {
            let lambda = step_nm.mul_add(i as f64, start_nm);
            let w = if i == 0 || i + 1 == n { 0.5 } else { 1.0 };
            sum += w * self.eval(lambda) * other.eval(lambda);
        }
        Ok(sum * step_nm)
    }
}

impl<F: Fn(f64) -> f64> Spectral for F {
    fn eval(&self, lambda_nm: f64) -> f64 {
        self(lambda_nm)
    }
}

/// Number of samples of the grid `start_nm..=end_nm` by `step_nm`, after validation.
fn grid_len(start_nm: f64, end_nm: f64, step_nm: f64) -> Result<usize> {
    if !start_nm.is_finite() {
        return Err(Error::param("start_nm", start_nm, "a finite wavelength in nm"));
    }
    if !(end_nm.is_finite() && end_nm > start_nm) {
        return Err(Error::param("end_nm", end_nm, format!("a finite wavelength > start_nm = {start_nm}")));
    }
    if !(step_nm.is_finite() && step_nm > 0.0) {
        return Err(Error::param("step_nm", step_nm, "(0, inf) nm"));
    }
    let intervals = (end_nm - start_nm) / step_nm;
    if intervals > (MAX_GRID_SAMPLES - 1) as f64 {
        return Err(Error::param(
            "step_nm",
            step_nm,
            format!(
                "at least (end_nm - start_nm) / {} = {} nm",
                MAX_GRID_SAMPLES - 1,
                (end_nm - start_nm) / (MAX_GRID_SAMPLES - 1) as f64
            ),
        ));
    }
    let rounded = intervals.round();
    if (intervals - rounded).abs() > GRID_TOLERANCE * intervals.max(1.0) {
        return Err(Error::param(
            "end_nm",
            end_nm,
            format!("start_nm + k * step_nm for a whole k (start_nm = {start_nm}, step_nm = {step_nm})"),
        ));
    }
    Ok(rounded as usize + 1)
}

/// Largest deviation of a node from its ideal position, in steps, for a grid to count
/// as uniform in [`GridIndex::new`]: the direct index is then off by at most one cell
/// and one comparison with the neighbouring node corrects it.
const UNIFORM_GRID_TOLERANCE: f64 = 1e-6;

/// Cell lookup on a strictly increasing grid: direct indexing where the grid is uniform
/// (detected once, at load), bisection otherwise. Both give the same cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct GridIndex {
    /// (first node, 1 / step) of a uniform grid; `None` for an irregular one.
    uniform: Option<(f64, f64)>,
}

impl GridIndex {
    /// Bisection always (a grid not checked for uniformity).
    pub(crate) const IRREGULAR: Self = Self { uniform: None };

    /// Detect whether `grid` (strictly increasing) is uniform within
    /// [`UNIFORM_GRID_TOLERANCE`] of a step.
    pub(crate) fn new(grid: &[f64]) -> Self {
        let n = grid.len();
        let uniform = match (grid.first(), grid.last()) {
            (Some(&a), Some(&b)) if n >= 2 && b > a => {
                let step = (b - a) / (n - 1) as f64;
                let on_grid = grid
                    .iter()
                    .enumerate()
                    .all(|(i, &x)| (x - step.mul_add(i as f64, a)).abs() <= UNIFORM_GRID_TOLERANCE * step);
                (on_grid && step.is_finite()).then_some((a, 1.0 / step))
            }
            _ => None,
        };
        Self { uniform }
    }

    /// Whether the grid was found uniform.
    #[cfg(test)]
    pub(crate) fn is_uniform(&self) -> bool {
        self.uniform.is_some()
    }

    /// The cell i ∈ [0, n − 2] with grid[i] ≤ x < grid[i + 1] (i = 0 below the grid,
    /// n − 2 at or above its last node): exactly the bisection
    /// `partition_point(|g| g <= x).clamp(1, n − 1) − 1`. `grid` has ≥ 2 nodes and is the
    /// grid this index was built for; x is not NaN.
    #[inline]
    pub(crate) fn cell(&self, grid: &[f64], x: f64) -> usize {
        let last = grid.len() - 2;
        match self.uniform {
            Some((start, inv_step)) => {
                // Off by at most one cell (see UNIFORM_GRID_TOLERANCE); `as` saturates and,
                // on the non-negative value, truncates like floor (without a libm call).
                let i = (((x - start) * inv_step).max(0.0) as usize).min(last);
                if i > 0 && grid[i] > x {
                    i - 1
                } else if i < last && grid[i + 1] <= x {
                    i + 1
                } else {
                    i
                }
            }
            None => grid.partition_point(|&g| g <= x).clamp(1, last + 1) - 1,
        }
    }
}

/// Check sample values: at least two, all finite.
fn check_values(values: &[f64]) -> Result<()> {
    if values.len() < 2 {
        return Err(Error::param("values", format!("{} sample(s)", values.len()), "at least 2 samples"));
    }
    if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(Error::param(&format!("values[{i}]"), v, "a finite number"));
    }
    Ok(())
}

/// A spectrum sampled on a regular wavelength grid, linearly interpolated, zero outside.
///
/// Samples sit at `λ_i = start_nm + i·step_nm`, `i = 0..values.len()`.
#[derive(Debug, Clone, PartialEq)]
pub struct RegularSpectrum {
    start_nm: f64,
    step_nm: f64,
    values: Vec<f64>,
}

impl RegularSpectrum {
    /// A spectrum with `values[i]` at `start_nm + i·step_nm`.
    ///
    /// Errors unless `start_nm` is finite, `step_nm` is finite and positive, and there
    /// are at least 2 values, all finite.
    pub fn new(start_nm: f64, step_nm: f64, values: Vec<f64>) -> Result<Self> {
        if !start_nm.is_finite() {
            return Err(Error::param("start_nm", start_nm, "a finite wavelength in nm"));
        }
        if !(step_nm.is_finite() && step_nm > 0.0) {
            return Err(Error::param("step_nm", step_nm, "(0, inf) nm"));
        }
        check_values(&values)?;
        Ok(Self { start_nm, step_nm, values })
    }

    /// A regular spectrum from tabulated `(wavelength, value)` columns whose wavelengths
    /// must be evenly spaced (within [`GRID_TOLERANCE`] of a step).
    pub(crate) fn from_evenly_spaced(wavelengths_nm: &[f64], values: Vec<f64>) -> Result<Self> {
        let irregular = IrregularSpectrum::new(wavelengths_nm.to_vec(), values)?;
        let start = wavelengths_nm[0];
        let step = wavelengths_nm[1] - start;
        for (i, &w) in wavelengths_nm.iter().enumerate() {
            if (w - step.mul_add(i as f64, start)).abs() > GRID_TOLERANCE * step {
                return Err(Error::data(format!(
                    "wavelength {w} nm (row {i}) is not on the regular grid {start} + k * {step} nm"
                )));
            }
        }
        Self::new(start, step, irregular.values)
    }

    /// First sample's wavelength (nm).
    pub fn start_nm(&self) -> f64 {
        self.start_nm
    }

    /// Last sample's wavelength (nm).
    pub fn end_nm(&self) -> f64 {
        self.wavelength_nm(self.values.len() - 1)
    }

    /// Spacing of the samples (nm).
    pub fn step_nm(&self) -> f64 {
        self.step_nm
    }

    /// The sample values, in wavelength order.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// Wavelength (nm) of sample `i` (`start_nm + i·step_nm`; not bounds-checked).
    pub fn wavelength_nm(&self, i: usize) -> f64 {
        self.step_nm.mul_add(i as f64, self.start_nm)
    }

    /// `∫ S(λ) dλ` over the samples by the trapezoid rule (exact for this
    /// piecewise-linear spectrum).
    pub fn integrate(&self) -> f64 {
        let v = &self.values;
        let interior: f64 = v.iter().sum::<f64>() - 0.5 * (v[0] + v[v.len() - 1]);
        interior * self.step_nm
    }
}

impl Spectral for RegularSpectrum {
    fn eval(&self, lambda_nm: f64) -> f64 {
        let last = self.values.len() - 1;
        let t = (lambda_nm - self.start_nm) / self.step_nm;
        // Also rejects NaN.
        if !(t >= 0.0 && t <= last as f64) {
            return 0.0;
        }
        let i = (t as usize).min(last - 1); // t ≥ 0: truncation is floor
        let f = t - i as f64;
        (1.0 - f) * self.values[i] + f * self.values[i + 1]
    }
}

/// A spectrum sampled at strictly increasing wavelengths, linearly interpolated, zero
/// outside `[wavelengths_nm[0], wavelengths_nm[n-1]]`.
#[derive(Debug, Clone, PartialEq)]
pub struct IrregularSpectrum {
    wavelengths_nm: Vec<f64>,
    values: Vec<f64>,
    /// Direct indexing when the wavelengths happen to be evenly spaced.
    index: GridIndex,
}

impl IrregularSpectrum {
    /// A spectrum with `values[i]` at `wavelengths_nm[i]`.
    ///
    /// Errors unless both have the same length ≥ 2, all entries are finite and the
    /// wavelengths strictly increase.
    pub fn new(wavelengths_nm: Vec<f64>, values: Vec<f64>) -> Result<Self> {
        if wavelengths_nm.len() != values.len() {
            return Err(Error::param(
                "values",
                format!("{} values", values.len()),
                format!("one value per wavelength ({} wavelengths)", wavelengths_nm.len()),
            ));
        }
        check_values(&values)?;
        if let Some((i, w)) = wavelengths_nm.iter().enumerate().find(|(_, w)| !w.is_finite()) {
            return Err(Error::param(&format!("wavelengths_nm[{i}]"), w, "a finite wavelength in nm"));
        }
        if let Some(i) = (1..wavelengths_nm.len()).find(|&i| wavelengths_nm[i] <= wavelengths_nm[i - 1]) {
            return Err(Error::param(
                &format!("wavelengths_nm[{i}]"),
                wavelengths_nm[i],
                format!("strictly increasing wavelengths (> wavelengths_nm[{}] = {})", i - 1, wavelengths_nm[i - 1]),
            ));
        }
        let index = GridIndex::new(&wavelengths_nm);
        Ok(Self { wavelengths_nm, values, index })
    }

    /// Parse two-column CSV text: `nm,value` per line.
    ///
    /// Blank lines and lines starting with `#` are skipped, as is a first line with no
    /// numeric field (a header). Fields may be separated by a comma, a semicolon or whitespace.
    /// Errors name the line number and the offending field.
    pub fn from_csv_str(text: &str) -> Result<Self> {
        let (wavelengths, values) = csv::two_columns(text)?;
        Self::new(wavelengths, values)
    }

    /// Read and parse a two-column CSV file; see [`IrregularSpectrum::from_csv_str`].
    pub fn from_csv_file(path: impl AsRef<std::path::Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = crate::fileio::read_text(path, crate::fileio::MAX_SMALL_FILE_BYTES, "spectrum CSV")?;
        Self::from_csv_str(&text).map_err(|e| match e {
            Error::Data(msg) => Error::data(format!("{}: {msg}", path.display())),
            other => Error::data(format!("{}: {other}", path.display())),
        })
    }

    /// The sample wavelengths (nm), strictly increasing.
    pub fn wavelengths_nm(&self) -> &[f64] {
        &self.wavelengths_nm
    }

    /// The sample values, in wavelength order.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// `∫ S(λ) dλ` over the samples by the trapezoid rule (exact for this
    /// piecewise-linear spectrum).
    pub fn integrate(&self) -> f64 {
        let (w, v) = (&self.wavelengths_nm, &self.values);
        (1..w.len()).map(|i| 0.5 * (w[i] - w[i - 1]) * (v[i] + v[i - 1])).sum()
    }
}

impl Spectral for IrregularSpectrum {
    fn eval(&self, lambda_nm: f64) -> f64 {
        let w = &self.wavelengths_nm;
        let last = w.len() - 1;
        // Also rejects NaN.
        if !(lambda_nm >= w[0] && lambda_nm <= w[last]) {
            return 0.0;
        }
        // w[i] <= lambda < w[i+1] (i = last - 1 at the last node).
        let i = self.index.cell(w, lambda_nm);
        let f = (lambda_nm - w[i]) / (w[i + 1] - w[i]);
        (1.0 - f) * self.values[i] + f * self.values[i + 1]
    }
}

impl From<RegularSpectrum> for IrregularSpectrum {
    fn from(s: RegularSpectrum) -> Self {
        let wavelengths_nm: Vec<f64> = (0..s.values.len()).map(|i| s.wavelength_nm(i)).collect();
        let index = GridIndex::new(&wavelengths_nm);
        Self { wavelengths_nm, values: s.values, index }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Tolerance for results that are exact up to floating-point rounding.
    const EXACT: f64 = 1e-12;

    fn irregular() -> IrregularSpectrum {
        IrregularSpectrum::new(vec![400.0, 410.0, 450.0, 700.0], vec![1.0, 3.0, -2.0, 5.0]).unwrap()
    }

    #[test]
    fn interpolation_is_exact_at_samples_and_zero_outside() {
        let r = RegularSpectrum::new(380.0, 5.0, vec![1.0, 2.0, 4.0, 8.0]).unwrap();
        for (i, &v) in r.values().iter().enumerate() {
            assert_eq!(r.eval(r.wavelength_nm(i)), v);
        }
        assert_eq!(r.end_nm(), 395.0);
        assert!((r.eval(382.5) - 1.5).abs() < EXACT);
        assert!((r.eval(391.0) - 4.8).abs() < EXACT);
        for x in [379.999, 395.001, -1.0, 1e9, f64::NAN, f64::INFINITY] {
            assert_eq!(r.eval(x), 0.0, "at {x}");
        }

        let s = irregular();
        for (w, v) in s.wavelengths_nm().iter().zip(s.values()) {
            assert_eq!(s.eval(*w), *v);
        }
        assert!((s.eval(430.0) - 0.5).abs() < EXACT);
        assert!((s.eval(575.0) - 1.5).abs() < EXACT);
        for x in [399.0, 700.5, f64::NAN, f64::NEG_INFINITY] {
            assert_eq!(s.eval(x), 0.0, "at {x}");
        }
    }

    #[test]
    fn direct_index_is_the_bisection() {
        let bisect = |g: &[f64], x: f64| g.partition_point(|&v| v <= x).clamp(1, g.len() - 1) - 1;
        // 10 nm, 5 nm, accumulated 0.1 nm steps (rounding in every node), and irregular grids.
        let mut acc = vec![380.0];
        for _ in 0..4500 {
            acc.push(acc[acc.len() - 1] + 0.1);
        }
        let grids: [Vec<f64>; 4] = [
            (0..=53).map(|i| 300.0 + 10.0 * i as f64).collect(),
            (0..=106).map(|i| 300.0 + 5.0 * i as f64).collect(),
            acc,
            vec![400.0, 410.0, 450.0, 700.0],
        ];
        for (g, uniform) in grids.iter().zip([true, true, true, false]) {
            let index = GridIndex::new(g);
            assert_eq!(index.is_uniform(), uniform);
            let (a, b) = (g[0], g[g.len() - 1]);
            let mut xs = vec![a - 1.0, b + 1.0, f64::INFINITY, f64::NEG_INFINITY];
            for &x in g {
                // the neighbouring floats (positive grids)
                xs.extend([x, f64::from_bits(x.to_bits() - 1), f64::from_bits(x.to_bits() + 1)]);
            }
            xs.extend(uniforms_in(10_000, a, b));
            for x in xs {
                assert_eq!(index.cell(g, x), bisect(g, x), "x = {x}");
            }
        }
    }

    fn uniforms_in(n: usize, a: f64, b: f64) -> Vec<f64> {
        crate::testutil::uniforms(n, 11).into_iter().map(|u| a + (b - a) * u).collect()
    }

    #[test]
    fn trapezoid_is_exact_for_linear_functions() {
        let line = |x: f64| 2.0 * x - 300.0;
        // ∫_{400}^{700} (2x − 300) dx = [x² − 300x]_{400}^{700} = 280000 − 40000 = 240000.
        let exact = 240_000.0;
        let r = line.resample(400.0, 700.0, 10.0).unwrap();
        assert!((r.integrate() - exact).abs() < EXACT * exact);
        let w = vec![400.0, 401.5, 470.0, 555.0, 700.0];
        let v = w.iter().map(|&x| line(x)).collect();
        let s = IrregularSpectrum::new(w, v).unwrap();
        assert!((s.integrate() - exact).abs() < EXACT * exact);
        let one = |_: f64| 1.0;
        let p = s.integrate_product(&one, 400.0, 700.0, 0.5).unwrap();
        assert!((p - exact).abs() < EXACT * exact);
        // The closure forms of both arguments agree.
        let p2 = one.integrate_product(&line, 400.0, 700.0, 3.0).unwrap();
        assert!((p2 - exact).abs() < EXACT * exact);
    }

    #[test]
    fn resample_and_conversion_round_trip() {
        let s = irregular();
        let r = s.resample(400.0, 700.0, 2.0).unwrap();
        assert_eq!(r.values().len(), 151);
        assert_eq!(r.eval(410.0), 3.0);
        let back = IrregularSpectrum::from(r.clone());
        for x in [400.0, 401.0, 555.5, 700.0] {
            assert!((back.eval(x) - r.eval(x)).abs() < EXACT);
        }
        let even = RegularSpectrum::from_evenly_spaced(&[1.0, 2.0, 3.0], vec![0.0, 1.0, 0.0]).unwrap();
        assert_eq!(even.step_nm(), 1.0);
        assert!(RegularSpectrum::from_evenly_spaced(&[1.0, 2.0, 3.5], vec![0.0, 1.0, 0.0]).is_err());
    }

    #[test]
    fn bad_input_is_rejected_with_a_message_naming_it() {
        let e = IrregularSpectrum::new(vec![400.0, 500.0, 600.0], vec![1.0, f64::NAN, 2.0]).unwrap_err();
        assert!(e.to_string().contains("values[1]") && e.to_string().contains("NaN"), "{e}");
        let e = IrregularSpectrum::new(vec![400.0, 500.0, 450.0], vec![1.0, 2.0, 3.0]).unwrap_err();
        assert!(e.to_string().contains("wavelengths_nm[2]") && e.to_string().contains("increasing"), "{e}");
        let e = IrregularSpectrum::new(vec![400.0, 400.0], vec![1.0, 2.0]).unwrap_err();
        assert!(e.to_string().contains("increasing"), "{e}");
        let e = IrregularSpectrum::new(vec![400.0], vec![1.0]).unwrap_err();
        assert!(e.to_string().contains("at least 2"), "{e}");
        let e = IrregularSpectrum::new(vec![400.0, 500.0], vec![1.0]).unwrap_err();
        assert!(e.to_string().contains("one value per wavelength"), "{e}");
        let e = RegularSpectrum::new(400.0, 0.0, vec![1.0, 2.0]).unwrap_err();
        assert!(e.to_string().contains("step_nm"), "{e}");
        let e = RegularSpectrum::new(f64::NAN, 1.0, vec![1.0, 2.0]).unwrap_err();
        assert!(e.to_string().contains("start_nm"), "{e}");
        let e = irregular().resample(400.0, 700.0, 7.0).unwrap_err();
        assert!(e.to_string().contains("end_nm"), "{e}");
        assert!(irregular().resample(700.0, 400.0, 1.0).is_err());
        assert!(irregular().resample(400.0, 700.0, 1e-9).is_err());
    }
}
