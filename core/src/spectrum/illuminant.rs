//! CIE standard illuminants, the CIE daylight (D-series) generator and Planck's law.
//!
//! # Illuminants ([`illuminant`])
//! | name | source | domain |
//! |---|---|---|
//! | `A` | defining formula, CIE 015:2018: `S_A(λ) = 100 (560/λ)^5 · (e^{c₂/(2848·560)} − 1) / (e^{c₂/(2848 λ)} − 1)`, `c₂ = 1.435·10⁷ nm·K` | 300–830 nm, 1 nm |
//! | `D65` | CIE 15:2004 table (as shipped by colour-science), continued above 780 nm by [`daylight`] at its CCT | 300–830 nm, 5 nm |
//! | `D50`, `D55`, `D60`, `D75` | [`daylight`] at `T = N·100 · 1.4388/1.4380` K | 300–830 nm, 5 nm |
//! | `E` | equal energy, 1.0 everywhere | 300–830 nm, 5 nm |
//! | `FL1`–`FL12`, `HP1`–`HP5` | CIE 15:2004 tables (as shipped by colour-science) | 380–780 nm, 5 nm |
//!
//! All are relative spectral power distributions in the CIE's scaling (100 at 560 nm
//! for A and the D series; the CIE's own arbitrary scale for FL and HP), except E,
//! which is 1.0.
//!
//! # Daylight ([`daylight`]), CIE 015:2018
//! For a correlated colour temperature `T` in 4000–25000 K:
//!
//! ```text
//! x_D = −4.6070·10⁹/T³ + 2.9678·10⁶/T² + 0.09911·10³/T + 0.244063     (4000 K ≤ T ≤ 7000 K)
//! x_D = −2.0064·10⁹/T³ + 1.9018·10⁶/T² + 0.24748·10³/T + 0.237040     (7000 K < T ≤ 25000 K)
//! y_D = −3.000 x_D² + 2.870 x_D − 0.275
//! M   = 0.0241 + 0.2562 x_D − 0.7341 y_D
//! M₁  = (−1.3515 − 1.7703 x_D + 5.9114 y_D) / M
//! M₂  = (0.0300 − 31.4424 x_D + 30.0717 y_D) / M
//! S(λ) = S₀(λ) + M₁ S₁(λ) + M₂ S₂(λ)
//! ```
//!
//! `M₁` and `M₂` are rounded to three decimals, as CIE 015 prescribes (and as
//! colour-science's `sd_CIE_illuminant_D_series` does by default); `x_D`, `y_D` are not
//! rounded. With that choice the generator reproduces the CIE tables of D50, D55, D65
//! and D75 to within their printed rounding (≤ 10⁻³). The named D illuminants use the
//! nominal temperature rescaled from the old second radiation constant,
//! `T = T_nominal · 1.4388/1.4380` (so D65 is at ≈ 6504 K); [`daylight`] itself takes
//! the actual CCT. The basis S₀, S₁, S₂ is tabulated at 5 nm, 300–830 nm, and is linearly
//! interpolated between samples, as CIE 015 recommends.
//!
//! # Planck's law ([`blackbody`])
//! ```text
//! L_λ(λ, T) = 2 h c² / λ⁵ · 1 / (exp(h c / (λ k_B T)) − 1)
//! ```
//! with the exact SI 2019 constants, returned in W·sr⁻¹·m⁻²·nm⁻¹ (spectral radiance
//! per nanometre of wavelength). `exp_m1` keeps the denominator accurate at long
//! wavelengths (Rayleigh–Jeans regime).

use std::sync::OnceLock;

use super::{csv, RegularSpectrum, Spectral};
use crate::error::check_range;
use crate::{Error, Result};

/// Every name [`illuminant`] accepts (case-insensitively).
pub const ILLUMINANT_NAMES: &[&str] = &[
    "A", "D50", "D55", "D60", "D65", "D75", "E", "FL1", "FL2", "FL3", "FL4", "FL5", "FL6", "FL7", "FL8", "FL9", "FL10",
    "FL11", "FL12", "HP1", "HP2", "HP3", "HP4", "HP5",
];

/// Valid correlated colour temperatures of the CIE daylight model, K.
const DAYLIGHT_CCT_RANGE_K: (f64, f64) = (4000.0, 25000.0);
/// Where the CIE daylight locus switches from its low-CCT to its high-CCT cubic, K.
const DAYLIGHT_CCT_SPLIT_K: f64 = 7000.0;
/// `1.4388 / 1.4380`: rescales the nominal CCT of D50…D75 (defined with the old
/// second radiation constant) to the current temperature scale.
const D_SERIES_CCT_RESCALE: f64 = 1.4388 / 1.4380;

/// CIE illuminant A's distribution temperature, K (CIE 015:2018).
const CIE_A_TEMPERATURE_K: f64 = 2848.0;
/// The second radiation constant used in the definition of illuminant A, nm·K.
const CIE_A_C2_NM_K: f64 = 1.435e7;
/// Domain and step on which illuminants A, E and the D series are generated, nm.
const GENERATED_DOMAIN_NM: (f64, f64) = (300.0, 830.0);
/// Step of illuminant A (its defining formula is tabulated at 1 nm by the CIE), nm.
const CIE_A_STEP_NM: f64 = 1.0;
/// Step of illuminant E, nm (matches the daylight basis).
const E_STEP_NM: f64 = 5.0;

/// Planck constant, J·s (SI 2019, exact).
const PLANCK_H: f64 = 6.626_070_15e-34;
/// Speed of light in vacuum, m/s (exact).
const SPEED_OF_LIGHT: f64 = 299_792_458.0;
/// Boltzmann constant, J/K (SI 2019, exact).
const BOLTZMANN_K: f64 = 1.380_649e-23;
/// Highest temperature accepted by [`blackbody_spectrum`], K.
const MAX_BLACKBODY_TEMPERATURE_K: f64 = 1e6;

/// Largest accepted value of a light's spectrum (after any scaling). Lamp spectra
/// with `normalize = false` carry physical units; the bound keeps radiance × BSDF ×
/// sampling weights finite in the renderer's float32 with a wide margin.
pub const MAX_LAMP_VALUE: f64 = 1e12;

/// Check that a spectrum can light a scene: every value in `[0, MAX_LAMP_VALUE]`.
/// `label` (a file or illuminant name) and the wavelength of the first bad value are
/// named in the error. `fluo_illuminant` and `fluo patch` both validate through it.
pub fn check_lamp(label: &str, wavelengths_nm: &[f64], values: &[f64]) -> Result<()> {
    match values.iter().position(|v| !(*v >= 0.0 && *v <= MAX_LAMP_VALUE)) {
        None => Ok(()),
        Some(i) => Err(Error::data(format!(
            "{label}: spectral value {} at {} nm: valid range is [0, {}] (no negative light)",
            crate::num(values[i]),
            crate::num(wavelengths_nm[i]),
            crate::num(MAX_LAMP_VALUE)
        ))),
    }
}

/// A CIE standard illuminant by name (case-insensitive; see [`ILLUMINANT_NAMES`] and the
/// module table for sources and domains). Unknown names give an error listing the valid
/// ones.
pub fn illuminant(name: &str) -> Result<RegularSpectrum> {
    let key = name.trim().to_ascii_uppercase();
    match key.as_str() {
        "A" => Ok(cie_a()),
        "E" => {
            let (lo, hi) = GENERATED_DOMAIN_NM;
            (|_: f64| 1.0).resample(lo, hi, E_STEP_NM)
        }
        "D65" => d65_extended(),
        "D50" | "D55" | "D60" | "D75" => {
            let nominal: f64 = key[1..].parse::<f64>().map_err(|e| Error::data(e.to_string()))? * 100.0;
            daylight(nominal * D_SERIES_CCT_RESCALE)
        }
        _ => tabulated().iter().find(|(n, _)| *n == key).map(|(_, s)| s.clone()).ok_or_else(|| {
            Error::param("illuminant", format!("\"{name}\""), format!("one of {}", ILLUMINANT_NAMES.join(", ")))
        }),
    }
}

/// Tabulated D65 (300–780 nm) continued to 830 nm with the daylight generator at the
/// same CCT (the CIE table was produced by that generator, so the two agree to the
/// table's rounding where they overlap), so that renders sampling up to 830 nm see it.
fn d65_extended() -> Result<RegularSpectrum> {
    let table = tabulated()
        .iter()
        .find(|(n, _)| *n == "D65")
        .map(|(_, s)| s.clone())
        .ok_or_else(|| Error::data("embedded D65 table missing"))?;
    let (_, hi) = GENERATED_DOMAIN_NM;
    if table.end_nm() >= hi {
        return Ok(table);
    }
    let generated = daylight(6500.0 * D_SERIES_CCT_RESCALE)?;
    let step = table.step_nm();
    let n = ((hi - table.start_nm()) / step).round() as usize;
    let values = (0..=n)
        .map(|i| {
            let l = table.start_nm() + i as f64 * step;
            if l <= table.end_nm() {
                table.eval(l)
            } else {
                generated.eval(l)
            }
        })
        .collect();
    RegularSpectrum::new(table.start_nm(), step, values)
}

/// CIE illuminant A from its defining formula, 300–830 nm at 1 nm.
fn cie_a() -> RegularSpectrum {
    static A: OnceLock<RegularSpectrum> = OnceLock::new();
    A.get_or_init(|| {
        let (lo, hi) = GENERATED_DOMAIN_NM;
        let num = (CIE_A_C2_NM_K / (CIE_A_TEMPERATURE_K * 560.0)).exp_m1();
        let a = move |l: f64| 100.0 * (560.0 / l).powi(5) * num / (CIE_A_C2_NM_K / (CIE_A_TEMPERATURE_K * l)).exp_m1();
        a.resample(lo, hi, CIE_A_STEP_NM).unwrap_or_else(|e| panic!("illuminant A grid: {e}"))
    })
    .clone()
}

/// The tabulated illuminants (D65, FL1–FL12, HP1–HP5), parsed once from the embedded
/// `data/spectra/illuminants.csv`.
fn tabulated() -> &'static [(String, RegularSpectrum)] {
    static TABLE: OnceLock<Vec<(String, RegularSpectrum)>> = OnceLock::new();
    TABLE.get_or_init(|| {
        let parse = || -> Result<Vec<(String, RegularSpectrum)>> {
            csv::named_groups(include_str!("../../../data/spectra/illuminants.csv"))?
                .into_iter()
                .map(|(name, w, v)| Ok((name, RegularSpectrum::from_evenly_spaced(&w, v)?)))
                .collect()
        };
        // Compiled-in data, checked by the tests: failure means a corrupted build.
        parse().unwrap_or_else(|e| panic!("embedded data/spectra/illuminants.csv: {e}"))
    })
}

/// The CIE daylight basis `[S0, S1, S2]`, parsed once from the embedded
/// `data/spectra/daylight_basis.csv`.
fn daylight_basis() -> &'static [RegularSpectrum; 3] {
    static BASIS: OnceLock<[RegularSpectrum; 3]> = OnceLock::new();
    BASIS.get_or_init(|| {
        let parse = || -> Result<[RegularSpectrum; 3]> {
            let cols = csv::columns(include_str!("../../../data/spectra/daylight_basis.csv"), 4)?;
            let s = |k: usize| RegularSpectrum::from_evenly_spaced(&cols[0], cols[k].clone());
            Ok([s(1)?, s(2)?, s(3)?])
        };
        parse().unwrap_or_else(|e| panic!("embedded data/spectra/daylight_basis.csv: {e}"))
    })
}

/// Chromaticity `(x_D, y_D)` of CIE daylight at correlated colour temperature `t` (K).
fn daylight_xy(t: f64) -> (f64, f64) {
    let (t2, t3) = (t * t, t * t * t);
    let x = if t <= DAYLIGHT_CCT_SPLIT_K {
        -4.6070e9 / t3 + 2.9678e6 / t2 + 0.09911e3 / t + 0.244063
    } else {
        -2.0064e9 / t3 + 1.9018e6 / t2 + 0.24748e3 / t + 0.237040
    };
    (x, -3.000 * x * x + 2.870 * x - 0.275)
}

/// Round to three decimals, as CIE 015 prescribes for `M₁`, `M₂`.
fn round3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// CIE daylight (D-series) relative spectral power at correlated colour temperature
/// `cct_k` (K, actual temperature; D65 is ≈ 6504 K), 300–830 nm at 5 nm, normalised by
/// construction to ≈ 100 at 560 nm. Valid for `cct_k` in `[4000, 25000]`.
pub fn daylight(cct_k: f64) -> Result<RegularSpectrum> {
    let (lo, hi) = DAYLIGHT_CCT_RANGE_K;
    let t = check_range("cct_k", cct_k, lo, hi)?;
    let (x, y) = daylight_xy(t);
    let m = 0.0241 + 0.2562 * x - 0.7341 * y;
    let m1 = round3((-1.3515 - 1.7703 * x + 5.9114 * y) / m);
    let m2 = round3((0.0300 - 31.4424 * x + 30.0717 * y) / m);
    let [s0, s1, s2] = daylight_basis();
    let values = (0..s0.values().len())
        .map(|i| m2.mul_add(s2.values()[i], m1.mul_add(s1.values()[i], s0.values()[i])))
        .collect();
    RegularSpectrum::new(s0.start_nm(), s0.step_nm(), values)
}

/// Planck's law: blackbody spectral radiance at wavelength `lambda_nm` (nm) and
/// temperature `temperature_k` (K), in W·sr⁻¹·m⁻²·nm⁻¹.
///
/// Returns 0 when either argument is not finite and positive (and where the
/// exponential overflows, i.e. where the true value underflows anyway).
pub fn blackbody(lambda_nm: f64, temperature_k: f64) -> f64 {
    if !(lambda_nm.is_finite() && lambda_nm > 0.0 && temperature_k.is_finite() && temperature_k > 0.0) {
        return 0.0;
    }
    let lambda_m = lambda_nm * 1e-9;
    let x = PLANCK_H * SPEED_OF_LIGHT / (lambda_m * BOLTZMANN_K * temperature_k);
    let denom = x.exp_m1();
    if !denom.is_finite() {
        return 0.0;
    }
    // W·sr⁻¹·m⁻²·m⁻¹ → per nm.
    2.0 * PLANCK_H * SPEED_OF_LIGHT * SPEED_OF_LIGHT / lambda_m.powi(5) / denom * 1e-9
}

/// [`blackbody`] at `temperature_k` sampled on the grid `start_nm, start_nm + step_nm, …,
/// end_nm` (absolute radiance, W·sr⁻¹·m⁻²·nm⁻¹; normalise as needed). Errors unless
/// `temperature_k` is in `(0, 1e6]` K and the grid is valid (as for
/// [`Spectral::resample`]) with `start_nm > 0`.
pub fn blackbody_spectrum(temperature_k: f64, start_nm: f64, end_nm: f64, step_nm: f64) -> Result<RegularSpectrum> {
    if !(temperature_k.is_finite() && temperature_k > 0.0 && temperature_k <= MAX_BLACKBODY_TEMPERATURE_K) {
        return Err(Error::param("temperature_k", temperature_k, format!("(0, {MAX_BLACKBODY_TEMPERATURE_K}] K")));
    }
    if !(start_nm.is_finite() && start_nm > 0.0) {
        return Err(Error::param("start_nm", start_nm, "(0, inf) nm"));
    }
    (move |l: f64| blackbody(l, temperature_k)).resample(start_nm, end_nm, step_nm)
}

#[cfg(test)]
mod tests {
    use super::super::{cmf, IrregularSpectrum, Observer};
    use super::*;
    use std::path::Path;

    /// The CIE D65 table is rounded to 4 decimals and was computed by the CIE with its
    /// own rounding of x_D and interpolation; the generator (M₁, M₂ rounded) lands within
    /// 10⁻³ of it at every 5 nm sample (colour-science 0.4.7 finds 8.5·10⁻⁴).
    const D65_GENERATOR_TOLERANCE: f64 = 1e-3;
    /// Values in the shared reference CSVs (colour-science, 6 significant digits);
    /// relative tolerance.
    const REFERENCE_REL_TOLERANCE: f64 = 1e-5;
    /// Absolute floor for the reference comparison (values printed to 4 decimals).
    const REFERENCE_ABS_TOLERANCE: f64 = 1e-4;

    fn shared(file: &str) -> Option<IrregularSpectrum> {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/illuminants").join(file);
        if !path.exists() {
            eprintln!("skipping comparison with {}: not found", path.display());
            return None;
        }
        Some(IrregularSpectrum::from_csv_file(&path).unwrap())
    }

    #[test]
    fn every_name_is_available_case_insensitively() {
        for name in ILLUMINANT_NAMES {
            let s = illuminant(&name.to_lowercase()).unwrap();
            assert!(s.values().iter().all(|v| v.is_finite()), "{name}");
            assert!(s.start_nm() <= 380.0 && s.end_nm() >= 780.0, "{name}");
        }
        assert_eq!(illuminant("E").unwrap().eval(555.5), 1.0);
        assert_eq!(illuminant("FL2").unwrap().eval(380.0), 1.18);
        assert_eq!(illuminant("hp5").unwrap().eval(385.0), 7.11);
    }

    #[test]
    fn unknown_illuminant_lists_the_valid_names() {
        let e = illuminant("D66").unwrap_err().to_string();
        assert!(e.contains("\"D66\"") && e.contains("FL12") && e.contains("HP5"), "{e}");
    }

    #[test]
    fn illuminant_a_matches_the_cie_table() {
        let a = illuminant("A").unwrap();
        // CIE 15:2004 table values (colour-science 0.4.7).
        for (l, v) in [(300.0, 0.930483), (455.0, 35.4068), (560.0, 100.0), (780.0, 241.675)] {
            assert!((a.eval(l) - v).abs() <= REFERENCE_REL_TOLERANCE * v, "A({l}) = {}", a.eval(l));
        }
        // A is a 2848 K Planckian with the old c₂ (1.435e-2 m·K); with the current c₂
        // (1.4388e-2) the same shape is a blackbody at 2848 · 1.4388/1.435 = 2856 K.
        let t = CIE_A_TEMPERATURE_K * 1.4388 / 1.435;
        let ratio = |l: f64| a.eval(l) / blackbody(l, t);
        assert!((ratio(400.0) / ratio(700.0) - 1.0).abs() < 1e-3);
    }

    #[test]
    fn daylight_generator_reproduces_tabulated_d65() {
        let table = illuminant("D65").unwrap();
        let generated = daylight(6500.0 * D_SERIES_CCT_RESCALE).unwrap();
        for i in 0..table.values().len() {
            let l = table.wavelength_nm(i);
            let (g, t) = (generated.eval(l), table.values()[i]);
            assert!((g - t).abs() < D65_GENERATOR_TOLERANCE, "{l} nm: {g} vs {t}");
        }
        assert!((generated.eval(560.0) - 100.0).abs() < D65_GENERATOR_TOLERANCE);
    }

    #[test]
    fn daylight_locus_and_range() {
        // CIE 015:2018 tabulates D65 at (x, y) = (0.31272, 0.32903).
        let (x, y) = daylight_xy(6500.0 * D_SERIES_CCT_RESCALE);
        assert!((x - 0.31272).abs() < 1e-5 && (y - 0.32903).abs() < 1e-4, "({x}, {y})");
        let e = daylight(3000.0).unwrap_err().to_string();
        assert!(e.contains("cct_k") && e.contains("4000"), "{e}");
        assert!(daylight(f64::NAN).is_err());
        // Both branches of x_D meet continuously at 7000 K.
        let below = daylight(DAYLIGHT_CCT_SPLIT_K).unwrap();
        let above = daylight(DAYLIGHT_CCT_SPLIT_K + 1e-6).unwrap();
        assert!((below.eval(450.0) - above.eval(450.0)).abs() < 0.05);
    }

    #[test]
    fn blackbody_physics() {
        // Wien's displacement law: peak at b / T, b = 2.897771955e-3 m·K.
        let t = 5000.0;
        let peak = (2000..10000).map(|i| i as f64 * 0.1).fold((0.0, 0.0), |best, l| {
            let v = blackbody(l, t);
            if v > best.1 {
                (l, v)
            } else {
                best
            }
        });
        assert!((peak.0 - 2.897_771_955e6 / t).abs() < 0.2, "peak at {} nm", peak.0);
        // Stefan–Boltzmann: π ∫ L dλ = σ T⁴ (σ = 5.670374419e-8 W m⁻² K⁻⁴).
        let s = blackbody_spectrum(t, 10.0, 200_000.0, 1.0).unwrap();
        let exitance = std::f64::consts::PI * s.integrate();
        assert!((exitance / (5.670_374_419e-8 * t.powi(4)) - 1.0).abs() < 1e-3, "{exitance}");
        assert_eq!(blackbody(-1.0, t), 0.0);
        assert_eq!(blackbody(500.0, 0.0), 0.0);
        assert_eq!(blackbody(1.0, 300.0), 0.0);
        assert!(blackbody_spectrum(-5.0, 380.0, 780.0, 5.0).unwrap_err().to_string().contains("temperature_k"));
    }

    #[test]
    fn matches_shared_reference_files_when_present() {
        let check = |name: &str, ours: &RegularSpectrum| {
            let Some(reference) = shared(&format!("{name}.csv")) else { return };
            for (l, v) in reference.wavelengths_nm().iter().zip(reference.values()) {
                let o = ours.eval(*l);
                let tol = REFERENCE_ABS_TOLERANCE.max(REFERENCE_REL_TOLERANCE * v.abs());
                assert!((o - v).abs() <= tol, "{name} at {l} nm: ours {o}, reference {v}");
            }
        };
        for name in ["A", "D65", "FL1", "FL2", "HP5", "D60"] {
            check(name, &illuminant(name).unwrap());
        }
        // E is 100 in the reference (CIE scaling) and 1.0 here.
        if let Some(e) = shared("E.csv") {
            assert!(e.values().iter().all(|&v| v == 100.0));
        }
        // A sanity use of the CMFs with a generated illuminant: D60's chromaticity is
        // close to the ACES white (0.32168, 0.33767).
        let [x, y, z] = cmf(Observer::Cie1931).xyz_of(&illuminant("D60").unwrap());
        let (cx, cy) = (x / (x + y + z), y / (x + y + z));
        assert!((cx - 0.32168).abs() < 5e-4 && (cy - 0.33767).abs() < 5e-4, "({cx}, {cy})");
    }
}
