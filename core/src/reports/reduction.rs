//! Reports on reduced transport: Fichet et al.'s Table 1 ([`table1`]) and saturated
//! emitters per basis ([`saturated_report`]).

use crate::interface::Bispectral;
use crate::models::jung::{JungMaterial, JungParams, Reflectance};
use crate::reduce::{
    grid, reduce, reduced_patch_xyz, spectral_patch_xyz, Basis, BasisKind, Method, Operator, Transport, GRID_END_NM,
    GRID_START_NM, GRID_STEP_NM,
};
use crate::spectrum::{Observer, Spectral};
use crate::{Error, Result};

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
    /// `xyz`, `xyzu`, `x7` or `auto` (built for each illuminant).
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
pub fn table1(materials: &[&dyn Bispectral]) -> Result<Vec<Table1Row>> {
    use crate::colour::{ciede2000, xyz_to_lab};
    let lights: Vec<crate::spectrum::RegularSpectrum> =
        TABLE1_ILLUMINANTS.iter().map(|n| crate::spectrum::illuminant(n)).collect::<Result<_>>()?;
    // `auto` (ours only: the naive reduction's area-normalised bands need positive ones) is
    // built per illuminant, for that light alone: what a patch lit by it sees.
    let adaptive: Vec<Basis> = lights
        .iter()
        .map(|light| Basis::adaptive(Observer::Cie2006, &[grid().iter().map(|&l| light.eval(l)).collect()]))
        .collect::<Result<_>>()?;
    let mut rows = Vec::new();
    for method in [Method::Naive, Method::Ours] {
        for kind in [BasisKind::Xyz, BasisKind::Xyzu, BasisKind::X7, BasisKind::Adaptive] {
            if kind == BasisKind::Adaptive && method == Method::Naive {
                continue;
            }
            let fixed = Basis::new(kind, Observer::Cie2006)?;
            let mut per_material = Vec::new();
            for m in materials {
                let r = reduce(&Operator::of(*m), &fixed, method);
                let des = lights
                    .iter()
                    .zip(&adaptive)
                    .map(|(light, own)| {
                        let (basis, r) = if kind == BasisKind::Adaptive {
                            (own, reduce(&Operator::of(*m), own, method))
                        } else {
                            (&fixed, r.clone())
                        };
                        let (xyz, w) = reduced_patch_xyz(&r, basis, light)?;
                        let (sxyz, sw) = spectral_patch_xyz(&Operator::of(*m), basis, light)?;
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
    /// Transport basis (`rgb`, `xyzu`, `x7`, `auto` built for the row's light).
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
pub const SATURATED_CASES: [(&str, f64, JungParams); 3] = [
    (
        "green emitter",
        0.0,
        JungParams { emission_peak: 520.0, stokes_shift: 40.0, concentration: 1.0, quantum_yield: 1.0 },
    ),
    (
        "red emitter",
        0.0,
        JungParams { emission_peak: 610.0, stokes_shift: 60.0, concentration: 1.0, quantum_yield: 1.0 },
    ),
    (
        "UV brightener",
        0.8,
        JungParams { emission_peak: 440.0, stokes_shift: 80.0, concentration: 0.5, quantum_yield: 0.9 },
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
    cases: &[(&'static str, f64, JungParams)],
    illuminants: &[&'static str],
) -> Result<Vec<SaturatedRow>> {
    use crate::colour::mitsuba::{spectrum_to_srgb, XYZ_TO_SRGB};
    use crate::colour::{ciede2000, xyz_to_lab};
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
        let material = JungMaterial::new(Reflectance::Constant(reflectance), params)?;
        for &name in illuminants {
            let light = saturated_light(name)?;
            let i: Vec<f64> = lambdas.iter().map(|&l| light.eval(l)).collect();
            let shifted = |lo: f64| -> f64 {
                lambdas
                    .iter()
                    .zip(&i)
                    .zip(&weights)
                    .map(|((&li, &v), &w)| material.fluorescence.reradiation(li, lo) * v * w)
                    .sum()
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
            let elastic = to_xyz(spectrum_to_srgb(|l| material.elastic_albedo(l) * light.eval(l))).map(|v| v * scale);
            let reference = [0, 1, 2].map(|r| elastic[r] + fluorescent[r]);
            // `auto` built for this light alone: exact for the patch it lights
            let own = Transport::adaptive(std::slice::from_ref(&i), Method::Ours)?;
            for t in transports.iter().chain(std::iter::once(&own)) {
                let k = t.len();
                let c = t.coefficients(&|l| light.eval(l));
                let patch = |mm: &[f64]| {
                    let co: Vec<f64> = (0..k).map(|r| (0..k).map(|j| mm[r * k + j] * c[j]).sum()).collect();
                    let rgb: Vec<f64> = (0..3).map(|r| (0..k).map(|j| t.output[r * k + j] * co[j]).sum()).collect();
                    to_xyz([rgb[0], rgb[1], rgb[2]]).map(|v| v * scale)
                };
                let got = patch(&t.reduce(&Operator::of(&material)));
                let got_fluorescent = patch(&t.reduce(&Operator::of(&material).reradiation_only()));
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
        let grey = JungParams { concentration: 0.0, ..Default::default() };
        let rows = saturated_rows(&[("grey", 0.6, grey)], &["D65", "A", "FL2"]).unwrap();
        assert_eq!(rows.len(), 12);
        for r in &rows {
            assert!((r.luminance_ratio.unwrap() - 1.0).abs() < 2e-3 && r.delta_e < 0.05, "{r:?}");
        }
    }

    #[test]
    fn the_report_shows_what_each_basis_can_carry() {
        let rows = saturated_report().unwrap();
        assert_eq!(rows.len(), SATURATED_CASES.len() * SATURATED_ILLUMINANTS.len() * 4);
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
        // `auto`, built for each light, reduces every patch it lights exactly (the
        // spectral patch integrates on Mitsuba's 360-830 nm, the basis on 300-830 nm).
        for r in rows.iter().filter(|r| r.basis == "auto") {
            assert!(r.delta_e < 0.1 && r.luminance_ratio.is_none_or(|v| (v - 1.0).abs() < 5e-3), "{r:?}");
            assert!(r.fluorescence_ratio.is_none_or(|v| (v - 1.0).abs() < 5e-3), "{r:?}");
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
