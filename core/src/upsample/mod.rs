//! Wide-gamut RGB → (reflectance + fluorescence) spectral upsampling (Jung et al. 2019).
//!
//! # Model (Jung et al. 2019, sec. 3)
//! Every RGB colour of a working space maps to six coefficients: the sigmoid-polynomial
//! reflectance c^r = (c0, c1, c2) of eq. 2 and the fluorescence c^f = (λe, c, s) of the
//! parametric model of eqs. 3–6 ([`crate::models::jung`]) with the quantum yield fixed at
//! Q = [`QUANTUM_YIELD`]. The colour of a set of coefficients is the colour of the
//! light a flat patch reflects under the cube's illuminant I (eq. 7):
//!
//! ```text
//! R(λ) = r(λ)(1 − c a(λ)) I(λ) + Q e(λ) ∫ c a(λ') I(λ') dλ'              (eq. 7)
//! RGB  = M_space · B(I → white_space) · ∫ R(λ) x̄ȳz̄(λ) dλ / ∫ I(λ) ȳ(λ) dλ
//! ```
//!
//! with CIE 1931 CMFs over [`LAMBDA_MIN_NM`, `LAMBDA_MAX_NM`] (Mitsuba's camera range;
//! the illuminant is zero outside it, i.e. the paper's "no UV" setting), M_space the
//! space's XYZ → RGB matrix ([`RgbSpace`](crate::colour::RgbSpace)) and B a Bradford
//! adaptation from the illuminant's white to the space's white, so that the perfect
//! white reflector maps to RGB (1, 1, 1) in every space (for ACEScg under D65 without B
//! it would land at ≈ (1.05, 0.99, 0.92) and white itself would be out of reach).
//!
//! # Modules
//! Rendering needs only the runtime; the offline optimiser writes the cubes it reads:
//! - `colour_system`: the colour of a set of coefficients (eq. 7), [`ColourSystem`];
//! - `cube` (runtime): the cube file ([`Cube`]: loading, validation, writing), the
//!   lookup of a colour's coefficients ([`Lookup`]) and the HSV test card
//!   ([`Reconstruction`]);
//! - `optimise` (offline): cube generation ([`generate_cube`], [`CubeSettings`]), the
//!   objective and fitting strategy of sec. 3.2–3.4.
//!
//! `optimise` uses `cube` and `colour_system`; neither of them uses `optimise`.
//!
//! # Coefficient domains
//! Reflectance coefficients are optimised for the normalised wavelength
//! t = (λ − 360)/470 ∈ [0, 1] (JH19's conditioning) and stored for λ in nm, the form
//! [`SigmoidPolynomial`](crate::sigmoid::SigmoidPolynomial) and the `fluo_jung` shim
//! take. λe and s are optimised in units of 100 nm.
//!
//! # Lookup (sec. 4, "Cube interpolation")
//! Nearest entry, or trilinear interpolation of coefficients where c is interpolated
//! with the ordinary weights and λe, s only over the corners with c > 0 (their
//! weights renormalised), since λe and s of non-fluorescent corners are meaningless.
//!
//! # Cube file (little endian)
//! | bytes | content |
//! |---|---|
//! | 8 | magic `FLUOCUBE` |
//! | 4 | u32 format version (1) |
//! | 4 | u32 colour space: 0 srgb, 1 rec2020, 2 acescg |
//! | 16 | illuminant name, ASCII, zero padded |
//! | 4 | u32 resolution n (entries per axis, grid k/(n−1)) |
//! | 4 | f32 threshold τ (nm⁻¹; +∞ allowed) |
//! | 4 | u32 floats per entry (11) |
//! | n³·11·4 | entries, index (r·n + g)·n + b, each `a b c λe c s err ra rb rc rerr` (f32) |
//!
//! `a b c` / `ra rb rc` are the sigmoid coefficients of the fluorescent solution and of
//! the reflectance-only (stage 1) solution for the normalised wavelength
//! t = (λ − 360 nm)/470 nm (P(t) = a t² + b t + c), which f32 holds without the
//! cancellation the nm form (c0 λ² + c1 λ + c2, terms ~10⁴ for box-like spectra) would
//! suffer; readers convert to the nm form in f64. `err` / `rerr` are their RGB distances
//! to the entry (without penalty), evaluated with the f32-rounded coefficients.
//!
//! # References
//! A. Jung, A. Wilkie, J. Hanika, W. Jakob, C. Dachsbacher, "Wide Gamut Spectral
//! Upsampling with Fluorescence", CGF 38(4), 2019. W. Jakob, J. Hanika, "A
//! Low-Dimensional Function Space for Efficient Spectral Upsampling", CGF 38(2), 2019.
//! Bradford: Lam (1985), as tabulated by Lindbloom and CIE 159:2004.

mod colour_system;
mod cube;
mod optimise;

pub use colour_system::{ColourSystem, GRID_STEP_NM};
pub use cube::{
    check_colour, hsv_card, hsv_to_rgb, shipped_cube_dir, space_name, Cube, CubeHeader, Entry, Lookup, Reconstruction,
    MAX_RESOLUTION,
};
pub use optimise::{
    generate_cube, max_slope, CubeSettings, GenerationStats, EMISSION_PEAK_BOUNDS_NM, FLUORESCENCE_TRIGGER,
    PENALTY_WEIGHT, REFLECTANCE_COEFF_LIMIT, REMAINING_ERROR, SMOOTH_THRESHOLD_PER_NM, STAGE1_SWEEPS,
    STOKES_SHIFT_BOUNDS_NM,
};

/// Shortest wavelength of the colour integrals, nm (Mitsuba's `MI_CIE_MIN`).
pub const LAMBDA_MIN_NM: f64 = 360.0;
/// Longest wavelength of the colour integrals, nm (Mitsuba's `MI_CIE_MAX`).
pub const LAMBDA_MAX_NM: f64 = 830.0;
/// Quantum yield of every cube entry (Jung et al. 2019, sec. 3.3).
pub const QUANTUM_YIELD: f64 = 0.96;

/// The six coefficients of one colour: reflectance (nm domain) and fluorescence.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Coefficients {
    /// Sigmoid-polynomial coefficients `[c0, c1, c2]` for λ in nm (eq. 2).
    pub reflectance: [f64; 3],
    /// Emission peak λe, nm (meaningless when `concentration == 0`).
    pub emission_peak: f64,
    /// Mixing factor c ∈ [0, 1].
    pub concentration: f64,
    /// Stokes shift s, nm (meaningless when `concentration == 0`).
    pub stokes_shift: f64,
}

impl Coefficients {
    /// Plain reflectance, no fluorescence.
    pub fn reflectance_only(reflectance: [f64; 3]) -> Self {
        Self { reflectance, emission_peak: 500.0, concentration: 0.0, stokes_shift: 50.0 }
    }
}

/// Span of the normalised wavelength t = (λ − 360)/470.
const T_SPAN: f64 = LAMBDA_MAX_NM - LAMBDA_MIN_NM;

/// Optimiser parameters: `[a, b, c, λe/100, conc, s/100]` with P(t) = a t² + b t + c.
type Params = [f64; 6];

/// Normalised-t coefficients → nm coefficients (P(λ) = c0 λ² + c1 λ + c2).
fn to_nm(p: &Params) -> [f64; 3] {
    let (a, b, c) = (p[0], p[1], p[2]);
    let (l0, l) = (LAMBDA_MIN_NM, T_SPAN);
    [a / (l * l), b / l - 2.0 * a * l0 / (l * l), a * l0 * l0 / (l * l) - b * l0 / l + c]
}

/// nm coefficients → normalised-t coefficients.
fn from_nm(c: &[f64; 3]) -> [f64; 3] {
    let (l0, l) = (LAMBDA_MIN_NM, T_SPAN);
    // P(λ) with λ = l0 + l t: c0 (l0 + l t)² + c1 (l0 + l t) + c2
    [c[0] * l * l, 2.0 * c[0] * l0 * l + c[1] * l, c[0] * l0 * l0 + c[1] * l0 + c[2]]
}

/// Coefficients (reflectance in the nm domain) → optimiser parameters.
fn params_of(c: &Coefficients) -> Params {
    let t = from_nm(&c.reflectance);
    [t[0], t[1], t[2], c.emission_peak / 100.0, c.concentration, c.stokes_shift / 100.0]
}

/// P(t) for normalised coefficients.
#[inline]
fn poly(p: &Params, t: f64) -> f64 {
    p[0].mul_add(t, p[1]).mul_add(t, p[2])
}

#[cfg(test)]
mod tests {
    //! Input validation across the public API, and the coefficient domains.
    use super::*;
    use crate::colour::RgbSpace;
    use crate::sigmoid::SigmoidPolynomial;

    #[test]
    fn coefficient_domains_round_trip() {
        let p = [3.0, -2.0, 0.5, 5.0, 0.0, 0.5];
        let nm = to_nm(&p);
        let s = SigmoidPolynomial::new(nm).unwrap();
        for l in [360.0, 500.0, 830.0] {
            let t = (l - 360.0) / 470.0;
            assert!((s.polynomial(l) - poly(&p, t)).abs() < 1e-9);
        }
        let back = from_nm(&nm);
        assert!((0..3).all(|k| (back[k] - p[k]).abs() < 1e-9));
    }

    #[test]
    fn bad_input_is_rejected_with_clear_errors() {
        let cube = Cube {
            header: CubeHeader { space: RgbSpace::Srgb, illuminant: "D65".into(), resolution: 2, threshold: 1.0 },
            entries: vec![
                Entry {
                    coefficients: Coefficients::reflectance_only([0.0; 3]),
                    error: 0.0,
                    reflectance_only: [0.0; 3],
                    reflectance_only_error: 0.0
                };
                8
            ],
        };
        for bad in [[1.2, 0.0, 0.0], [0.0, -0.1, 0.0], [0.0, 0.0, f64::NAN]] {
            let e = cube.lookup(bad, Lookup::Nearest, true).unwrap_err().to_string();
            assert!(e.contains("\"color\"") && e.contains("[0, 1]"), "{e}");
        }
        let bytes = cube.to_bytes();
        assert!(Cube::from_bytes(&bytes, "x").is_ok());
        let e = Cube::from_bytes(&bytes[..bytes.len() - 4], "x.cube").unwrap_err().to_string();
        assert!(e.contains("x.cube") && e.contains("bytes"), "{e}");
        let e = Cube::from_bytes(b"not a cube at all, really not", "y").unwrap_err().to_string();
        assert!(e.contains("FLUOCUBE"), "{e}");
        let mut nan = bytes.clone();
        nan[48..52].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(Cube::from_bytes(&nan, "z").unwrap_err().to_string().contains("non-finite"));
        let e = Lookup::from_name("cubic").unwrap_err().to_string();
        assert!(e.contains("lookup") && e.contains("nearest"), "{e}");
        assert!(CubeSettings {
            space: RgbSpace::Srgb,
            illuminant: "D65".into(),
            resolution: 1,
            threshold: f64::INFINITY,
            rounds: 1,
            threads: 1
        }
        .validate()
        .unwrap_err()
        .to_string()
        .contains("resolution"));
        assert!(ColourSystem::new(RgbSpace::Srgb, "D93").unwrap_err().to_string().contains("illuminant"));
    }
}
