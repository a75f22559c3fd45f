//! Conventions shared with Mitsuba 3 (pure Rust; nothing here links Mitsuba).
//!
//! * The camera samples wavelengths in [`CIE_MIN_NM`, `CIE_MAX_NM`] = [360, 830] nm
//!   and Mitsuba's RGB upsampling is zero outside it (`include/mitsuba/core/spectrum.h`).
//! * In RGB variants Mitsuba turns a reflectance spectrum v(λ) into linear sRGB as
//!   `xyz_to_srgb(∫ v(λ)·cmf₁₉₃₁(λ) dλ / ∫ ȳ(λ) dλ)` over that range, i.e. under an
//!   equal-energy light and *without* dividing by the RGB of the light
//!   (`spectrum_list_to_srgb` in `src/core/spectrum.cpp`). [`spectrum_to_srgb`]
//!   reproduces it (on a 1 nm grid of the CIE 1931 table; Mitsuba uses a 5 nm table,
//!   which differs by < 0.1 %).

use crate::spectrum::{cmf, Observer, Spectral};

/// Shortest wavelength Mitsuba's camera samples, nm (`MI_CIE_MIN`).
pub const CIE_MIN_NM: f64 = 360.0;
/// Longest wavelength Mitsuba's camera samples, nm (`MI_CIE_MAX`).
pub const CIE_MAX_NM: f64 = 830.0;

/// Mitsuba's `xyz_to_srgb` matrix (row major), linear sRGB / Rec. 709 primaries.
pub const XYZ_TO_SRGB: crate::colour::Mat3 =
    [[3.240479, -1.537150, -0.498535], [-0.969256, 1.875991, 0.041556], [0.055648, -0.204043, 1.057311]];

/// Linear sRGB of a reflectance spectrum as Mitsuba's RGB variants compute it.
pub fn spectrum_to_srgb(v: impl Fn(f64) -> f64) -> [f64; 3] {
    let c = cmf(Observer::Cie1931);
    let (mut xyz, mut ysum) = ([0.0; 3], 0.0);
    let n = (CIE_MAX_NM - CIE_MIN_NM) as usize;
    for i in 0..=n {
        let l = CIE_MIN_NM + i as f64;
        let w = if i == 0 || i == n { 0.5 } else { 1.0 };
        let (x, y, z) = (c.x().eval(l), c.y().eval(l), c.z().eval(l));
        let val = v(l);
        xyz[0] += w * x * val;
        xyz[1] += w * y * val;
        xyz[2] += w * z * val;
        ysum += w * y;
    }
    let xyz = xyz.map(|t| t / ysum);
    XYZ_TO_SRGB.map(|row| row[0] * xyz[0] + row[1] * xyz[1] + row[2] * xyz[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_spectrum_is_mitsubas_equal_energy_white() {
        // XYZ of E normalised to Y = 1 is ≈ (1, 1, 1) (CIE 1931: 1.0000/1/0.9999...),
        // so Mitsuba's sRGB of a white reflectance is the row sums of the matrix.
        let rgb = spectrum_to_srgb(|_| 1.0);
        let rows: Vec<f64> = XYZ_TO_SRGB.iter().map(|r| r.iter().sum()).collect();
        for k in 0..3 {
            assert!((rgb[k] - rows[k]).abs() < 2e-3, "{rgb:?} vs {rows:?}");
        }
    }
}
