//! CIE colour matching functions (CMFs) and tristimulus integration.
//!
//! For a spectrum `S(λ)` the CIE tristimulus values are (CIE 015:2018, without the
//! normalising factor `k`)
//!
//! ```text
//! X = ∫ S(λ) x̄(λ) dλ,   Y = ∫ S(λ) ȳ(λ) dλ,   Z = ∫ S(λ) z̄(λ) dλ
//! ```
//!
//! evaluated by the trapezoid rule on the CMF's own 1 nm grid (a spectrum coarser than
//! that is linearly interpolated onto it; outside its domain it is zero). Callers
//! normalise, e.g. `100 / Y_illuminant` for object colours.
//!
//! | observer | table | domain |
//! |---|---|---|
//! | [`Observer::Cie1931`] | CIE 1931 2° standard observer (CIE 015:2018) | 360–830 nm, 1 nm |
//! | [`Observer::Cie2006`] | CIE 2006 2° XYZ CMFs (CIE 170-2:2015; "CIE 2015 2 Degree Standard Observer" in colour-science) | 390–830 nm, 1 nm |

use std::sync::OnceLock;

use super::{csv, RegularSpectrum, Spectral};
use crate::{Error, Result};

/// A CIE standard colorimetric observer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Observer {
    /// CIE 1931 2° standard observer, 360–830 nm.
    #[default]
    Cie1931,
    /// CIE 2006 2° observer (CIE 170-2:2015 XYZ CMFs), 390–830 nm.
    Cie2006,
}

impl Observer {
    /// Parse a name, case-insensitively: `"cie1931"` (or `"1931"`) or `"cie2006"` (or
    /// `"2006"`, `"cie2015"`).
    pub fn from_name(name: &str) -> Result<Self> {
        match name.trim().to_ascii_lowercase().as_str() {
            "cie1931" | "1931" => Ok(Observer::Cie1931),
            "cie2006" | "2006" | "cie2015" => Ok(Observer::Cie2006),
            _ => Err(Error::param("observer", format!("\"{name}\""), "one of \"cie1931\", \"cie2006\"")),
        }
    }
}

/// The x̄, ȳ, z̄ colour matching functions of one observer, on a common 1 nm grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Cmf {
    x: RegularSpectrum,
    y: RegularSpectrum,
    z: RegularSpectrum,
}

impl Cmf {
    /// x̄(λ).
    pub fn x(&self) -> &RegularSpectrum {
        &self.x
    }

    /// ȳ(λ) (the photopic luminous efficiency function V(λ) for CIE 1931).
    pub fn y(&self) -> &RegularSpectrum {
        &self.y
    }

    /// z̄(λ).
    pub fn z(&self) -> &RegularSpectrum {
        &self.z
    }

    /// Unnormalised tristimulus values `[X, Y, Z] = ∫ S(λ)·[x̄, ȳ, z̄](λ) dλ` (λ in nm),
    /// by the trapezoid rule on the CMF's own grid. `s` is any [`Spectral`], e.g. a
    /// closure `&|lambda_nm: f64| ...`.
    pub fn xyz_of<S: Spectral + ?Sized>(&self, s: &S) -> [f64; 3] {
        let n = self.x.values().len();
        let (xs, ys, zs) = (self.x.values(), self.y.values(), self.z.values());
        let mut xyz = [0.0; 3];
        for i in 0..n {
            let w = if i == 0 || i + 1 == n { 0.5 } else { 1.0 };
            let sw = w * s.eval(self.x.wavelength_nm(i));
            xyz[0] += sw * xs[i];
            xyz[1] += sw * ys[i];
            xyz[2] += sw * zs[i];
        }
        xyz.map(|c| c * self.x.step_nm())
    }

    /// Parse an embedded `nm,x,y,z` table.
    fn parse(text: &str) -> Result<Self> {
        let mut cols = csv::columns(text, 4)?;
        let z = cols.pop().unwrap_or_default();
        let y = cols.pop().unwrap_or_default();
        let x = cols.pop().unwrap_or_default();
        let nm = cols.pop().unwrap_or_default();
        Ok(Self {
            x: RegularSpectrum::from_evenly_spaced(&nm, x)?,
            y: RegularSpectrum::from_evenly_spaced(&nm, y)?,
            z: RegularSpectrum::from_evenly_spaced(&nm, z)?,
        })
    }
}

/// The colour matching functions of `observer`, parsed on first use from the tables
/// embedded from `data/spectra/`.
pub fn cmf(observer: Observer) -> &'static Cmf {
    static CIE1931: OnceLock<Cmf> = OnceLock::new();
    static CIE2006: OnceLock<Cmf> = OnceLock::new();
    let (cell, text, file) = match observer {
        Observer::Cie1931 => (&CIE1931, include_str!("../../../data/spectra/cie1931_2deg.csv"), "cie1931_2deg.csv"),
        Observer::Cie2006 => (&CIE2006, include_str!("../../../data/spectra/cie2006_2deg.csv"), "cie2006_2deg.csv"),
    };
    // The tables are compiled in and checked by the tests below, so this cannot fail at
    // run time unless the crate was built from corrupted data.
    cell.get_or_init(|| Cmf::parse(text).unwrap_or_else(|e| panic!("embedded data/spectra/{file}: {e}")))
}

#[cfg(test)]
mod tests {
    use super::super::illuminant;
    use super::*;
    use std::path::Path;

    /// ∫ȳ dλ of the CIE 1931 table, trapezoid at 1 nm over 360–830 nm (colour-science
    /// 0.4.7 `np.trapezoid` on the same table gives 106.856914917).
    const CIE1931_Y_INTEGRAL: f64 = 106.856_914_917;
    /// CIE 2006 tables agree with CVRL's to their printed 7 significant digits.
    const CMF_TABLE_TOLERANCE: f64 = 1e-5;
    /// The CIE 015:2018 D65 white is (95.047, 100, 108.883); allow for the 5 nm table
    /// and the integration rule.
    const WHITE_TOLERANCE: f64 = 0.05;

    #[test]
    fn tables_parse_with_the_expected_grids() {
        let c = cmf(Observer::Cie1931);
        assert_eq!((c.x().start_nm(), c.x().end_nm(), c.x().step_nm()), (360.0, 830.0, 1.0));
        let c = cmf(Observer::Cie2006);
        assert_eq!((c.y().start_nm(), c.y().end_nm(), c.y().step_nm()), (390.0, 830.0, 1.0));
        // ȳ peaks at 1 at 555 nm (CIE 1931).
        assert_eq!(cmf(Observer::Cie1931).y().eval(555.0), 1.0);
        assert_eq!(Observer::from_name(" CIE2006 ").unwrap(), Observer::Cie2006);
        assert!(Observer::from_name("cie1964").unwrap_err().to_string().contains("cie1931"));
    }

    #[test]
    fn y_bar_integral() {
        let c = cmf(Observer::Cie1931);
        assert!((c.y().integrate() - CIE1931_Y_INTEGRAL).abs() < 1e-9);
        // xyz_of a constant 1 is the same integral.
        let [_, y, _] = c.xyz_of(&|_: f64| 1.0);
        assert!((y - CIE1931_Y_INTEGRAL).abs() < 1e-9);
    }

    #[test]
    fn d65_white_point() {
        let d65 = illuminant("D65").unwrap();
        let [x, y, z] = cmf(Observer::Cie1931).xyz_of(&d65);
        let (x, z) = (100.0 * x / y, 100.0 * z / y);
        assert!((x - 95.04).abs() < WHITE_TOLERANCE, "X = {x}");
        assert!((z - 108.88).abs() < WHITE_TOLERANCE, "Z = {z}");
    }

    #[test]
    fn cie2006_matches_cvrl_table_when_present() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/cmf/ciexyz06_2deg.csv");
        let Ok(text) = std::fs::read_to_string(&path) else {
            eprintln!("skipping CIE 2006 CMF comparison: {} not found", path.display());
            return;
        };
        let c = cmf(Observer::Cie2006);
        let mut rows = 0;
        for line in text.lines().filter(|l| !l.trim().is_empty()) {
            let f: Vec<f64> = line.split(',').map(|s| s.trim().parse().unwrap()).collect();
            let ours = [c.x().eval(f[0]), c.y().eval(f[0]), c.z().eval(f[0])];
            for k in 0..3 {
                assert!((ours[k] - f[k + 1]).abs() < CMF_TABLE_TOLERANCE, "{} nm, column {k}", f[0]);
            }
            rows += 1;
        }
        assert!(rows > 400, "only {rows} rows in {}", path.display());
    }
}
