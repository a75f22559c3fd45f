//! Single-bounce "patch" colorimetry of any material, used to check renders and by
//! the reports (Hua et al. 2022, sec. 7.3, eq. 15).
//!
//! A flat patch lit by a distant light of spectral irradiance I(λ) and seen from the
//! normal: with the diffuse convention (f = P/π), its colour is
//!
//! ```text
//! XYZ = k Σ_λo cmf(λo) [ ρ(λo) I(λo) + Σ_λi P(λi, λo) I(λi) Δλi ] Δλo,   k = 1 / Σ I(λ) ȳ(λ) Δλ
//! ```
//!
//! with ρ the elastic albedo (the reradiation matrix diagonal). Conventions, fixed
//! here and documented for `fluo patch`: λo runs over the observer's CMF domain at
//! 1 nm (trapezoid); λi over the illuminant's domain at 1 nm (a finer grid across a
//! narrow absorption band, see [`crate::models::jung::absorbed_power`]); I is normalised so
//! that the perfect white diffuser has Y = 1 (`white_xyz`).

use crate::interface::Bispectral;
use crate::spectrum::{Cmf, Spectral};
use crate::Result;

/// Result of [`patch_xyz`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatchColour {
    /// XYZ of the patch, normalised as [`Self::normalisation`] says.
    pub xyz: [f64; 3],
    /// XYZ of the reference white: a perfect white diffuser under the same light, or
    /// (radiant normalisation) under an equal-energy light of the same power.
    pub white_xyz: [f64; 3],
    /// XYZ of the elastic part alone.
    pub elastic_xyz: [f64; 3],
    /// How the colours are normalised.
    pub normalisation: Normalisation,
}

/// A lamp whose white patch has less luminance than this fraction of what an
/// equal-energy light of the same radiant power gives (a UV lamp: the eye sees almost
/// none of it) is normalised by its radiant power instead ([`Normalisation::Radiant`]):
/// dividing by a white Y near zero would blow the patch's colour up by that ratio.
pub const MIN_LUMINOUS_FRACTION: f64 = 1e-3;

/// How patch colours are normalised.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Normalisation {
    /// The white diffuser under the same light has Y = 1 (lamps the eye sees).
    WhiteY,
    /// A white diffuser under an equal-energy light (over the CMF range) of the same
    /// radiant power has Y = 1, and it is the reference white (UV lamps).
    Radiant,
}

impl Normalisation {
    /// The rule in words, as the `fluo patch` JSON reports it.
    pub fn describe(self) -> &'static str {
        match self {
            Normalisation::WhiteY => "white Y = 1: XYZ = Σ cmf(λo) [ρ(λo) I(λo) + Σ P(λi,λo) I(λi)] / Σ I ȳ",
            Normalisation::Radiant => {
                "radiant (the lamp is nearly invisible): XYZ = Σ cmf(λo) [ρ(λo) I(λo) + Σ P(λi,λo) I(λi)] / (Σ ȳ · ∫I dλ / (λmax − λmin)); \
                 the white is a white diffuser under an equal-energy light of the same power"
            }
        }
    }
}

/// Normalise raw patch sums: `xyz` (the patch), `white` (a white diffuser under the
/// lamp) and `equal_energy_white` (a white diffuser under an equal-energy light of the
/// lamp's radiant power), all in the same units. Returns the scale factor, the
/// reference white and the rule; an error for a lamp without power.
pub fn normalise_patch(white: [f64; 3], equal_energy_white: [f64; 3]) -> Result<(f64, [f64; 3], Normalisation)> {
    if white[1] > 0.0 && white[1] >= MIN_LUMINOUS_FRACTION * equal_energy_white[1] {
        Ok((1.0 / white[1], white.map(|v| v / white[1]), Normalisation::WhiteY))
    } else if equal_energy_white[1] > 0.0 {
        let k = 1.0 / equal_energy_white[1];
        Ok((k, equal_energy_white.map(|v| v * k), Normalisation::Radiant))
    } else {
        Err(crate::Error::data("the lamp has no power over the colour-matching range and its excitation range"))
    }
}

/// Single-bounce XYZ of a flat patch under an illuminant (see the module docs).
pub fn patch_xyz(
    material: &dyn Bispectral,
    illum: &dyn Spectral,
    illum_domain: (f64, f64),
    cmf: &Cmf,
) -> Result<PatchColour> {
    patch_xyz_of(
        &|l| material.elastic_albedo(1.0, l),
        &|i, d, l| material.reradiated(i, d, l),
        illum,
        illum_domain,
        cmf,
    )
}

/// The elastic albedo ρ(λ) of a patch.
pub type ElasticFn<'a> = &'a dyn Fn(f64) -> f64;
/// ∫ P(λi, λo) I(λi) dλi of a patch: (illuminant, its domain, λo).
pub type ReradiatedFn<'a> = &'a dyn Fn(&dyn Fn(f64) -> f64, (f64, f64), f64) -> f64;

/// [`patch_xyz`] of a patch given by its two parts, for representations that are not
/// materials (the dense 1 nm grids of [`crate::reports::gmm`]).
pub fn patch_xyz_of(
    elastic_albedo: ElasticFn,
    reradiated: ReradiatedFn,
    illum: &dyn Spectral,
    illum_domain: (f64, f64),
    cmf: &Cmf,
) -> Result<PatchColour> {
    let (lo, hi) = (cmf.x().start_nm(), cmf.x().end_nm());
    let n = (hi - lo).round() as usize;
    let eval_i = |l: f64| if l >= illum_domain.0 && l <= illum_domain.1 { illum.eval(l) } else { 0.0 };
    let (mut xyz, mut white, mut elastic, mut cmf_sum) = ([0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3]);
    // Radiant power over the lamp's whole domain (UV included), 1 nm trapezoids.
    let steps = (illum_domain.1 - illum_domain.0).ceil().max(1.0) as usize;
    let h = (illum_domain.1 - illum_domain.0) / steps as f64;
    let power: f64 = (0..=steps)
        .map(|i| if i == 0 || i == steps { 0.5 } else { 1.0 } * h * eval_i(illum_domain.0 + h * i as f64))
        .sum();
    for i in 0..=n {
        let l = lo + (hi - lo) * i as f64 / n as f64;
        let w = if i == 0 || i == n { 0.5 } else { 1.0 };
        let bar = [cmf.x().eval(l), cmf.y().eval(l), cmf.z().eval(l)];
        let il = eval_i(l);
        let el = elastic_albedo(l) * il;
        let total = el + reradiated(&eval_i, illum_domain, l);
        for k in 0..3 {
            xyz[k] += w * bar[k] * total;
            white[k] += w * bar[k] * il;
            elastic[k] += w * bar[k] * el;
            cmf_sum[k] += w * bar[k];
        }
    }
    let equal_energy = cmf_sum.map(|v| v * power / (hi - lo));
    let (k, white_xyz, normalisation) = normalise_patch(white, equal_energy)?;
    Ok(PatchColour { xyz: xyz.map(|v| v * k), white_xyz, elastic_xyz: elastic.map(|v| v * k), normalisation })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::jung::{JungMaterial, JungParams, Reflectance};
    use crate::spectrum::{cmf, Observer};

    #[test]
    fn patch_of_white_is_white_and_fluorescence_adds_light() {
        let c = cmf(Observer::Cie2006);
        let e = |_: f64| 1.0;
        let white =
            JungMaterial::new(Reflectance::Constant(1.0), JungParams { concentration: 0.0, ..JungParams::default() })
                .unwrap();
        let p = patch_xyz(&white, &e, (300.0, 830.0), c).unwrap();
        for k in 0..3 {
            assert!((p.xyz[k] - p.white_xyz[k]).abs() < 1e-12);
        }
        assert!((p.white_xyz[1] - 1.0).abs() < 1e-12);
        // fluorescent green on black: all light is reradiated, Y > 0, elastic = 0
        let green = JungMaterial::new(
            Reflectance::Constant(0.0),
            JungParams { emission_peak: 520.0, stokes_shift: 60.0, concentration: 1.0, quantum_yield: 1.0 },
        )
        .unwrap();
        let p = patch_xyz(&green, &e, (300.0, 830.0), c).unwrap();
        assert_eq!(p.elastic_xyz, [0.0; 3]);
        // Under E, absorbed energy ∫a (nm) is re-emitted with unit-integral e: Y = ∫a·∫e ȳ / ∫ȳ.
        let m = &green.fluorescence;
        let ybar_e: f64 = (0..=4400).map(|i| 390.0 + i as f64 * 0.1).map(|l| m.emission(l) * c.y().eval(l) * 0.1).sum();
        let want = m.absorption_integral() * ybar_e / c.y().integrate();
        assert!((p.xyz[1] - want).abs() < 2e-3 * want, "{} vs {want}", p.xyz[1]);
    }
}
