//! How well Gaussian mixtures reproduce measured matrices: the evaluation of Hua et
//! al. 2022, sec. 7, behind `fluo gmm-report`.
//!
//! For each material and component count K, the tabulated matrix model
//! ([`crate::models::matrix::MatrixModel`]) and its fit ([`crate::models::gmm::GmmModel`]) are compared
//! by CIEDE2000 (k_L = k_C = k_H = 1) under two sets of lights (sec. 7.2):
//!
//! * **CIE illuminants**: every illuminant of [`crate::spectrum::ILLUMINANT_NAMES`],
//!   through [`crate::patch::patch_xyz`] (single bounce, light and view along the normal,
//!   eq. 15; white Y = 1); L\*a\*b\* relative to the illuminant's own white.
//! * **Monochromatic light** at λ0 = 300, 310, …, 780 nm, of radiant power ∫ȳ dλ, so a
//!   light at a wavelength where ȳ = 1 has the luminance of the unit white:
//!   `XYZ = ρ(λ0)·cmf(λ0) + ∫ cmf(λo) P(λ0, λo) dλo`; L\*a\*b\* relative to the
//!   equal-energy white (Y = 1).
//!
//! Observer: CIE 1931 2° (360–830 nm, 1 nm). Both models are evaluated on the same
//! 1 nm grid ([`Dense`]: P at integer λi × λo, trapezoid in λi), so differences are the
//! model's, not the quadrature's; a test checks the grid against `fluo patch`'s direct
//! integration.
//!
//! Memory (sec. 7.6): floats stored in the file and bytes held at render time (f64),
//! for the tabulated matrix with its two cumulative tables, and for the mixture with
//! its baked conditionals (plus, once per process and shared by every mixture, the
//! 20 kB ln Q table of [`crate::models::gmm::log_q`]).

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::colour::{ciede2000, xyz_to_lab};
use crate::models::gmm::{fit, FitOptions, GmmModel};
use crate::models::matrix::{load_matrix, Filtered, MatrixModel};
use crate::patch::{patch_xyz_of, PatchColour};
use crate::spectrum::{cmf, illuminant, Cmf, Observer, Spectral, ILLUMINANT_NAMES};
use crate::{Error, Result};

/// Component counts of the report (the paper's).
pub const COMPONENT_COUNTS: [usize; 5] = [1, 2, 4, 8, 16];
/// Monochromatic lights: first, last, step, nm.
pub const MONOCHROMATIC_NM: (u32, u32, u32) = (300, 780, 10);
/// The paper's figure for 8 components under the CIE illuminants (sec. 7.5).
pub const ACCEPTANCE_DELTA_E: f64 = 0.3;
/// Component count the acceptance figure is for.
pub const ACCEPTANCE_COMPONENTS: usize = 8;

/// A bispectral material sampled at integer wavelengths: P(λi, λo) for λi in
/// `lambda_i0` + i nm and λo on the observer's 1 nm grid, and ρ on that grid.
pub struct Dense {
    lambda_i0: f64,
    n_i: usize,
    lambda_o0: f64,
    n_o: usize,
    /// `p[o * n_i + i]`.
    p: Vec<f64>,
    rho: Vec<f64>,
}

impl Dense {
    /// Tabulate `p(λi, λo)` (zero for λi > λo) and `rho(λ)`.
    pub fn new(lambda_i: (f64, f64), cmf: &Cmf, p: impl Fn(f64, f64) -> f64, rho: impl Fn(f64) -> f64) -> Self {
        let lambda_i0 = lambda_i.0.ceil();
        let n_i = (lambda_i.1.floor() - lambda_i0) as usize + 1;
        let lambda_o0 = cmf.x().start_nm().round();
        let n_o = (cmf.x().end_nm().round() - lambda_o0) as usize + 1;
        let mut table = vec![0.0; n_i * n_o];
        for o in 0..n_o {
            let lo = lambda_o0 + o as f64;
            for i in 0..n_i {
                let li = lambda_i0 + i as f64;
                if li <= lo {
                    table[o * n_i + i] = p(li, lo);
                }
            }
        }
        let rho = (0..n_o).map(|o| rho(lambda_o0 + o as f64)).collect();
        Self { lambda_i0, n_i, lambda_o0, n_o, p: table, rho }
    }

    fn row(&self, lambda_o: f64) -> Option<&[f64]> {
        let o = lambda_o - self.lambda_o0;
        if !(o >= 0.0 && o.fract() == 0.0 && (o as usize) < self.n_o) {
            return None;
        }
        let o = o as usize;
        Some(&self.p[o * self.n_i..(o + 1) * self.n_i])
    }

    /// XYZ under monochromatic light at integer λ0 (see the module docs).
    pub fn monochromatic_xyz(&self, lambda0: f64, cmf: &Cmf) -> [f64; 3] {
        let bar = |l: f64| [cmf.x().eval(l), cmf.y().eval(l), cmf.z().eval(l)];
        let i = lambda0 - self.lambda_i0;
        let mut xyz = [0.0; 3];
        let b0 = bar(lambda0);
        let rho0 = crate::models::matrix::interp_clamped(
            &(0..self.n_o).map(|o| self.lambda_o0 + o as f64).collect::<Vec<_>>(),
            &self.rho,
            lambda0,
        );
        if lambda0 >= self.lambda_o0 {
            for k in 0..3 {
                xyz[k] = rho0 * b0[k];
            }
        }
        if i >= 0.0 && (i as usize) < self.n_i {
            let i = i as usize;
            for o in 0..self.n_o {
                let w = if o == 0 || o == self.n_o - 1 { 0.5 } else { 1.0 };
                let v = self.p[o * self.n_i + i];
                if v != 0.0 {
                    let b = bar(self.lambda_o0 + o as f64);
                    for k in 0..3 {
                        xyz[k] += w * v * b[k];
                    }
                }
            }
        }
        xyz
    }
}

impl Dense {
    /// Its patch colour ([`patch_xyz`] on the dense grids).
    fn patch(&self, illum: &dyn Spectral, domain: (f64, f64), c: &Cmf) -> Result<PatchColour> {
        patch_xyz_of(&|l| self.elastic_albedo(l), &|i, d, l| self.reradiated(i, d, l), illum, domain, c)
    }

    fn elastic_albedo(&self, lambda: f64) -> f64 {
        let o = (lambda - self.lambda_o0).round();
        if o >= 0.0 && (o as usize) < self.n_o {
            self.rho[o as usize]
        } else {
            0.0
        }
    }
    fn reradiated(&self, illum: &dyn Fn(f64) -> f64, domain: (f64, f64), lambda_o: f64) -> f64 {
        let Some(row) = self.row(lambda_o) else { return 0.0 };
        let lo = domain.0.max(self.lambda_i0).ceil();
        let hi = domain.1.min(lambda_o).min(self.lambda_i0 + (self.n_i - 1) as f64).floor();
        if !(hi > lo) {
            return 0.0;
        }
        let (a, b) = ((lo - self.lambda_i0) as usize, (hi - self.lambda_i0) as usize);
        let mut sum = 0.0;
        for (i, v) in row.iter().enumerate().take(b + 1).skip(a) {
            let w = if i == a || i == b { 0.5 } else { 1.0 };
            sum += w * v * illum(self.lambda_i0 + i as f64);
        }
        sum
    }
}

/// Colours of one material under every light of the report.
struct Colours {
    cie: Vec<([f64; 3], [f64; 3])>, // (xyz, white)
    mono: Vec<[f64; 3]>,
}

fn mono_wavelengths() -> Vec<f64> {
    let (a, b, s) = MONOCHROMATIC_NM;
    (a..=b).step_by(s as usize).map(f64::from).collect()
}

fn colours(d: &Dense, lights: &[(String, crate::spectrum::RegularSpectrum)], c: &Cmf) -> Result<Colours> {
    let cie = lights
        .iter()
        .map(|(_, s)| d.patch(s, (s.start_nm(), s.end_nm()), c).map(|p| (p.xyz, p.white_xyz)))
        .collect::<Result<_>>()?;
    let mono = mono_wavelengths().into_iter().map(|l| d.monochromatic_xyz(l, c)).collect();
    Ok(Colours { cie, mono })
}

/// Equal-energy white, Y = 1.
fn e_white(c: &Cmf) -> [f64; 3] {
    let y = c.y().integrate();
    [c.x().integrate() / y, 1.0, c.z().integrate() / y]
}

/// Mean and max of a list.
#[derive(Debug, Clone, Serialize)]
pub struct Stats {
    /// Mean.
    pub mean: f64,
    /// Maximum.
    pub max: f64,
}

fn stats(v: &[f64]) -> Stats {
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    Stats { mean, max: v.iter().copied().fold(0.0, f64::max) }
}

/// One fit of one material.
#[derive(Debug, Clone, Serialize)]
pub struct FitReport {
    /// K.
    pub components: usize,
    /// Wall-clock fitting time (EM restarts and S), s.
    pub fit_seconds: f64,
    /// EM iterations of the retained restart.
    pub iterations: usize,
    /// Whether EM met its tolerance.
    pub converged: bool,
    /// ΔE2000 under the CIE illuminants.
    pub delta_e_cie: Stats,
    /// ΔE2000 per CIE illuminant, in [`Report::illuminants`] order.
    pub delta_e_per_illuminant: Vec<f64>,
    /// ΔE2000 under the monochromatic lights.
    pub delta_e_mono: Stats,
    /// Floats in the fit file (diagonal, S, 7 per component).
    pub floats_stored: usize,
    /// Bytes the baked model holds at render time.
    pub bytes_at_render_time: usize,
}

/// One material.
#[derive(Debug, Clone, Serialize)]
pub struct MaterialReport {
    /// File.
    pub file: String,
    /// Floats in the measured matrix (values and grids).
    pub matrix_floats_stored: usize,
    /// Bytes of the tabulated model at render time (matrix, both CDF tables, grids, diagonal).
    pub matrix_bytes_at_render_time: usize,
    /// Fits, one per component count.
    pub fits: Vec<FitReport>,
}

/// Means over the materials for one component count.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// K.
    pub components: usize,
    /// Mean over materials and CIE illuminants.
    pub mean_delta_e_cie: f64,
    /// Mean over materials and monochromatic lights.
    pub mean_delta_e_mono: f64,
    /// Mean fitting time, s.
    pub mean_fit_seconds: f64,
    /// Mean bytes at render time of the fits.
    pub mean_bytes_at_render_time: f64,
    /// Mean bytes at render time of the tabulated matrices.
    pub matrix_bytes_at_render_time: f64,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Observer.
    pub observer: &'static str,
    /// CIE illuminants, in order.
    pub illuminants: Vec<String>,
    /// Monochromatic wavelengths, nm.
    pub monochromatic_nm: Vec<f64>,
    /// Per material.
    pub materials: Vec<MaterialReport>,
    /// Per component count.
    pub summary: Vec<Summary>,
}

/// Evaluate `files` for `counts` components (see the module docs).
pub fn report(files: &[impl AsRef<Path>], counts: &[usize], base: &FitOptions) -> Result<Report> {
    if files.is_empty() {
        return Err(Error::data("gmm-report: no material files"));
    }
    let c = cmf(Observer::Cie1931);
    let lights: Vec<(String, crate::spectrum::RegularSpectrum)> =
        ILLUMINANT_NAMES.iter().map(|n| illuminant(n).map(|s| (n.to_string(), s))).collect::<Result<_>>()?;
    let white_e = e_white(c);
    let mut materials = Vec::new();
    for path in files {
        let path = path.as_ref();
        let filtered = Filtered::new(&load_matrix(path)?)?;
        let matrix = MatrixModel::new(&filtered)?;
        let li = (filtered.lambda_i[0], filtered.lambda_i[filtered.lambda_i.len() - 1]);
        let dense_ref = Dense::new(li, c, |a, b| matrix.reradiation(a, b), |l| matrix.reflectance(l));
        let reference = colours(&dense_ref, &lights, c)?;
        let mut fits = Vec::new();
        for &k in counts {
            let t0 = Instant::now();
            let file = fit(&filtered, &FitOptions { components: k, ..*base })?;
            let fit_seconds = t0.elapsed().as_secs_f64();
            let (iterations, converged, floats_stored) =
                (file.fit.iterations, file.fit.converged, file.floats_stored());
            let model = GmmModel::new(file)?;
            let dense = Dense::new(li, c, |a, b| model.reradiation(a, b), |l| model.reflectance(l));
            let got = colours(&dense, &lights, c)?;
            let de_cie: Vec<f64> = reference
                .cie
                .iter()
                .zip(&got.cie)
                .map(|((x, w), (y, _))| ciede2000(xyz_to_lab(*x, *w), xyz_to_lab(*y, *w)))
                .collect();
            let de_mono: Vec<f64> = reference
                .mono
                .iter()
                .zip(&got.mono)
                .map(|(x, y)| ciede2000(xyz_to_lab(*x, white_e), xyz_to_lab(*y, white_e)))
                .collect();
            fits.push(FitReport {
                components: k,
                fit_seconds,
                iterations,
                converged,
                delta_e_cie: stats(&de_cie),
                delta_e_per_illuminant: de_cie,
                delta_e_mono: stats(&de_mono),
                floats_stored,
                bytes_at_render_time: 8 * model.floats_at_render_time(),
            });
        }
        materials.push(MaterialReport {
            file: path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned()),
            matrix_floats_stored: filtered.off.len() + filtered.lambda_i.len() + filtered.lambda_o.len(),
            matrix_bytes_at_render_time: 8 * matrix.floats_at_render_time(),
            fits,
        });
    }
    let n = materials.len() as f64;
    let summary = counts
        .iter()
        .enumerate()
        .map(|(i, &k)| Summary {
            components: k,
            mean_delta_e_cie: materials.iter().map(|m| m.fits[i].delta_e_cie.mean).sum::<f64>() / n,
            mean_delta_e_mono: materials.iter().map(|m| m.fits[i].delta_e_mono.mean).sum::<f64>() / n,
            mean_fit_seconds: materials.iter().map(|m| m.fits[i].fit_seconds).sum::<f64>() / n,
            mean_bytes_at_render_time: materials.iter().map(|m| m.fits[i].bytes_at_render_time as f64).sum::<f64>() / n,
            matrix_bytes_at_render_time: materials.iter().map(|m| m.matrix_bytes_at_render_time as f64).sum::<f64>()
                / n,
        })
        .collect();
    Ok(Report {
        observer: "cie1931",
        illuminants: lights.into_iter().map(|l| l.0).collect(),
        monochromatic_nm: mono_wavelengths(),
        materials,
        summary,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::matrix::shared_bispectral_files;
    use crate::patch::patch_xyz;

    #[test]
    fn dense_grid_matches_direct_patch_integration() {
        let files = shared_bispectral_files();
        let Some(path) = files.iter().find(|p| p.to_string_lossy().contains("TEXTYELL")) else {
            eprintln!("skipping: shared data not found (set FLUO_SHARED_DATA or place shared/ beside the repo)");
            return;
        };
        let c = cmf(Observer::Cie1931);
        let m = MatrixModel::from_file(path).unwrap();
        let d = Dense::new((300.0, 780.0), c, |a, b| m.reradiation(a, b), |l| m.reflectance(l));
        for name in ["D65", "A", "FL2"] {
            let s = illuminant(name).unwrap();
            let dom = (s.start_nm(), s.end_nm());
            let (a, b) = (patch_xyz(&m, &s, dom, c).unwrap(), d.patch(&s, dom, c).unwrap());
            for k in 0..3 {
                assert!(
                    (a.xyz[k] - b.xyz[k]).abs() < 2e-4 * a.xyz[k].abs().max(1e-3),
                    "{name}: {:?} vs {:?}",
                    a.xyz,
                    b.xyz
                );
            }
            assert!(a.xyz[1] - a.elastic_xyz[1] > 0.01, "{name}: fluorescence present");
        }
        // Monochromatic at 360 nm: only reradiation is visible; compare with quadrature.
        let xyz = d.monochromatic_xyz(360.0, c);
        let direct: f64 = (380..=780).map(|lo| m.reradiation(360.0, lo as f64) * c.y().eval(lo as f64)).sum();
        assert!((xyz[1] - direct).abs() < 1e-3 * direct, "{} vs {direct}", xyz[1]);
    }

    #[test]
    fn eight_components_meet_the_papers_figure() {
        let files = shared_bispectral_files();
        if files.is_empty() {
            eprintln!("skipping: shared data not found (set FLUO_SHARED_DATA or place shared/ beside the repo)");
            return;
        }
        let r = report(&files, &[ACCEPTANCE_COMPONENTS], &FitOptions::default()).unwrap();
        let s = &r.summary[0];
        assert_eq!(r.materials.len(), 6);
        assert!(s.mean_delta_e_cie <= ACCEPTANCE_DELTA_E, "mean ΔE2000 = {}", s.mean_delta_e_cie);
        assert!(s.mean_bytes_at_render_time < s.matrix_bytes_at_render_time / 10.0);
    }
}
