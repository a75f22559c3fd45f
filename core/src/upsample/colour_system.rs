//! The colour of a set of upsampling coefficients under one illuminant in one RGB space
//! (eq. 7 of Jung et al. 2019, see the [module docs](super)): the forward model that the
//! cube's test-card reports and the optimiser both evaluate.
//!
//! # Numerics
//! The reflectance integral uses a [`GRID_STEP_NM`] grid with weights that integrate
//! hat functions against the 1 nm CMF × illuminant table; the absorption and emission
//! integrals use 8-point Gauss–Legendre rules on each polynomial piece of the b-spline
//! (in the absorption's mirrored variable v, whose Jacobian is exact), so narrow bands
//! are integrated as accurately as wide ones.

use super::{params_of, poly, Coefficients, Params, LAMBDA_MAX_NM, LAMBDA_MIN_NM, QUANTUM_YIELD, T_SPAN};
use crate::colour::{mat_inv, mat_mul, mat_vec, Mat3, RgbSpace};
use crate::models::jung::bspline;
use crate::sigmoid::sigmoid;
use crate::spectrum::{cmf, illuminant, Observer, Spectral};
use crate::{Error, Result};

/// Knot spacing of the reflectance quadrature grid, nm.
pub const GRID_STEP_NM: f64 = 2.0;

/// 8-point Gauss–Legendre nodes (positive half) and weights on [−1, 1].
const GL8: [(f64, f64); 4] = [
    (0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_5),
    (0.960_289_856_497_536_3, 0.101_228_536_290_376_3),
];

/// Bradford cone response matrix (Lam 1985).
const BRADFORD: Mat3 = [[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]];

/// Bradford adaptation matrix taking XYZ seen under `from` white to `to` white.
fn bradford(from: [f64; 3], to: [f64; 3]) -> Mat3 {
    let (s, d) = (mat_vec(&BRADFORD, from), mat_vec(&BRADFORD, to));
    let scale = [[d[0] / s[0], 0.0, 0.0], [0.0, d[1] / s[1], 0.0], [0.0, 0.0, d[2] / s[2]]];
    let inverse = mat_inv(&BRADFORD).expect("the Bradford matrix is invertible (det ≈ 2.9)");
    mat_mul(&inverse, &mat_mul(&scale, &BRADFORD))
}

/// The colour of coefficients in one RGB space under one illuminant (eq. 7), with
/// everything that depends only on the space and illuminant precomputed.
#[derive(Debug, Clone)]
pub struct ColourSystem {
    space: RgbSpace,
    pub(super) illuminant: String,
    /// Adapted, normalised RGB colour matching functions at 1 nm, 360..=830 nm.
    pub(super) cmf_rgb: Vec<[f64; 3]>,
    /// Illuminant at 1 nm, 360..=830 nm.
    pub(super) illum: Vec<f64>,
    /// Normalised wavelength of each reflectance grid knot.
    grid_t: Vec<f64>,
    /// RGB weight of each knot: ∫ hat_k(λ) I(λ) cmf_rgb(λ) dλ.
    grid_w: Vec<[f64; 3]>,
}

/// Linear interpolation in a 1 nm table starting at [`LAMBDA_MIN_NM`]; 0 outside.
#[inline]
pub(super) fn table<T: Copy + Into<[f64; 3]>>(tab: &[T], lambda: f64) -> [f64; 3] {
    let x = lambda - LAMBDA_MIN_NM;
    if !(x >= 0.0 && x <= (tab.len() - 1) as f64) {
        return [0.0; 3];
    }
    let i = (x as usize).min(tab.len() - 2);
    let f = x - i as f64;
    let (a, b): ([f64; 3], [f64; 3]) = (tab[i].into(), tab[i + 1].into());
    [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2])]
}

#[inline]
pub(super) fn table1(tab: &[f64], lambda: f64) -> f64 {
    let x = lambda - LAMBDA_MIN_NM;
    if !(x >= 0.0 && x <= (tab.len() - 1) as f64) {
        return 0.0;
    }
    let i = (x as usize).min(tab.len() - 2);
    let f = x - i as f64;
    tab[i] + f * (tab[i + 1] - tab[i])
}

/// Derived quantities of the fluorescent part for one (λe, s).
pub(super) struct Fluo {
    alpha: f64,
    /// Short edge of the emission band λe − α (= long edge of the absorption band).
    edge: f64,
    beta: f64,
    lambda_e: f64,
}

impl Fluo {
    pub(super) fn new(lambda_e: f64, s: f64) -> Option<Self> {
        let den = 2.0 * lambda_e - s;
        if !(lambda_e > 0.0 && s > 0.0 && den > 0.0) {
            return None;
        }
        let alpha = lambda_e * s / den;
        let edge = lambda_e - alpha;
        if !(edge > crate::models::jung::MIN_ABSORPTION_EDGE_NM && alpha > 0.0) {
            return None;
        }
        Some(Self { alpha, edge, beta: 2.0 * alpha / (3.0 * edge), lambda_e })
    }

    /// Absorption quadrature nodes: (λ, a(λ)·|dλ/dv|·w) so that ∫ f a dλ ≈ Σ f(λ)·wt.
    pub(super) fn absorption_nodes(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        let k = 2.0 / self.edge;
        (0..3).flat_map(move |piece| {
            let centre = 2.0 * piece as f64 + 1.0; // pieces [0,2], [2,4], [4,6] of v
            GL8.iter().flat_map(move |&(x, w)| {
                [centre - x, centre + x].map(move |v| {
                    let lp = self.edge + self.alpha * v / 3.0;
                    let lambda = lp / (k * lp - 1.0);
                    let jac = (self.alpha / 3.0) / (1.0 + self.beta * v).powi(2);
                    (lambda, bspline(v - 3.0) * jac * w)
                })
            })
        })
    }

    /// Emission quadrature nodes: (λ, e(λ)·w) so that ∫ f e dλ ≈ Σ f(λ)·wt.
    pub(super) fn emission_nodes(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        // e = 9/(8α) b(3(λ − λe)/α), dλ = α/3 dx: ∫ f e = 3/8 ∫ b(x) f(λe + αx/3) dx.
        [-2.0, 0.0, 2.0].into_iter().flat_map(move |centre: f64| {
            GL8.iter().flat_map(move |&(x, w)| {
                [centre - x, centre + x].map(move |u| (self.lambda_e + self.alpha * u / 3.0, 0.375 * bspline(u) * w))
            })
        })
    }
}

impl ColourSystem {
    /// Colour system for `space` under the CIE illuminant `illuminant_name`.
    pub fn new(space: RgbSpace, illuminant_name: &str) -> Result<Self> {
        let spd = illuminant(illuminant_name)?;
        let c = cmf(Observer::Cie1931);
        let n = (LAMBDA_MAX_NM - LAMBDA_MIN_NM) as usize + 1;
        let lambdas: Vec<f64> = (0..n).map(|i| LAMBDA_MIN_NM + i as f64).collect();
        let illum: Vec<f64> = lambdas.iter().map(|&l| spd.eval(l)).collect();
        let xyz: Vec<[f64; 3]> = lambdas.iter().map(|&l| [c.x().eval(l), c.y().eval(l), c.z().eval(l)]).collect();
        let trap = |i: usize| if i == 0 || i + 1 == n { 0.5 } else { 1.0 };
        let mut white = [0.0; 3];
        for i in 0..n {
            for k in 0..3 {
                white[k] += trap(i) * illum[i] * xyz[i][k];
            }
        }
        let y_i = white[1];
        if !(y_i > 0.0) {
            return Err(Error::param(
                "illuminant",
                format!("\"{illuminant_name}\""),
                "an illuminant with visible energy in 360-830 nm",
            ));
        }
        let white = white.map(|w| w / y_i);
        let adapt = bradford(white, space.white_xyz());
        let cmf_rgb: Vec<[f64; 3]> = xyz.iter().map(|v| space.to_rgb(mat_vec(&adapt, *v)).map(|x| x / y_i)).collect();
        let knots = ((LAMBDA_MAX_NM - LAMBDA_MIN_NM) / GRID_STEP_NM).round() as usize + 1;
        let grid_lambda: Vec<f64> = (0..knots).map(|k| LAMBDA_MIN_NM + k as f64 * GRID_STEP_NM).collect();
        let mut grid_w = vec![[0.0; 3]; knots];
        for i in 0..n {
            let l = lambdas[i];
            let pos = (l - LAMBDA_MIN_NM) / GRID_STEP_NM;
            let k = (pos.floor() as usize).min(knots - 2);
            let f = pos - k as f64;
            let base = trap(i) * illum[i];
            for ch in 0..3 {
                grid_w[k][ch] += (1.0 - f) * base * cmf_rgb[i][ch];
                grid_w[k + 1][ch] += f * base * cmf_rgb[i][ch];
            }
        }
        let grid_t = grid_lambda.iter().map(|l| (l - LAMBDA_MIN_NM) / T_SPAN).collect();
        Ok(Self { space, illuminant: illuminant_name.trim().to_ascii_uppercase(), cmf_rgb, illum, grid_t, grid_w })
    }

    /// The RGB space.
    pub fn space(&self) -> RgbSpace {
        self.space
    }

    /// The illuminant's name.
    pub fn illuminant(&self) -> &str {
        &self.illuminant
    }

    /// RGB of coefficients (eq. 7, see the module docs).
    pub fn rgb(&self, c: &Coefficients) -> [f64; 3] {
        self.rgb_params(&params_of(c))
    }

    pub(super) fn rgb_params(&self, p: &Params) -> [f64; 3] {
        let mut rgb = [0.0; 3];
        for (t, w) in self.grid_t.iter().zip(&self.grid_w) {
            let r = sigmoid(poly(p, *t));
            rgb[0] += r * w[0];
            rgb[1] += r * w[1];
            rgb[2] += r * w[2];
        }
        let conc = p[4];
        if conc > 0.0 {
            if let Some(f) = Fluo::new(100.0 * p[3], 100.0 * p[5]) {
                let (mut absorbed, mut lost) = (0.0, [0.0; 3]);
                for (lambda, wt) in f.absorption_nodes() {
                    let i = table1(&self.illum, lambda);
                    if i == 0.0 {
                        continue;
                    }
                    absorbed += wt * i;
                    let r = sigmoid(poly(p, (lambda - LAMBDA_MIN_NM) / T_SPAN));
                    let cm = table(&self.cmf_rgb, lambda);
                    for ch in 0..3 {
                        lost[ch] += r * wt * i * cm[ch];
                    }
                }
                let mut emitted = [0.0; 3];
                if absorbed > 0.0 {
                    for (lambda, wt) in f.emission_nodes() {
                        let cm = table(&self.cmf_rgb, lambda);
                        for ch in 0..3 {
                            emitted[ch] += wt * cm[ch];
                        }
                    }
                }
                for ch in 0..3 {
                    rgb[ch] += conc * (QUANTUM_YIELD * absorbed * emitted[ch] - lost[ch]);
                }
            }
        }
        rgb
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::jung::{JungMaterial, JungParams, Reflectance};
    use crate::sigmoid::SigmoidPolynomial;

    /// Independent reference: eq. 7 on a 0.1 nm grid with the crate's Jung model,
    /// the CIE 1931 table and the same adaptation.
    fn reference_rgb(sys: &ColourSystem, c: &Coefficients) -> [f64; 3] {
        let spd = illuminant(&sys.illuminant).unwrap();
        let illum = |l: f64| if (LAMBDA_MIN_NM..=LAMBDA_MAX_NM).contains(&l) { spd.eval(l) } else { 0.0 };
        let m = JungMaterial::new(
            Reflectance::Sigmoid(SigmoidPolynomial::new(c.reflectance).unwrap()),
            JungParams {
                emission_peak: c.emission_peak,
                stokes_shift: c.stokes_shift,
                concentration: c.concentration,
                quantum_yield: QUANTUM_YIELD,
            },
        )
        .unwrap();
        let cm = cmf(Observer::Cie1931);
        let (mut xyz, mut white) = ([0.0; 3], [0.0; 3]);
        let step = 0.1;
        let n = ((LAMBDA_MAX_NM - LAMBDA_MIN_NM) / step) as usize;
        let excitation =
            crate::models::jung::absorbed_power(&m.fluorescence, &illum, (LAMBDA_MIN_NM, LAMBDA_MAX_NM), 0.1);
        let p = m.fluorescence.params();
        for i in 0..=n {
            let l = LAMBDA_MIN_NM + i as f64 * step;
            let w = if i == 0 || i == n { 0.5 } else { 1.0 } * step;
            let refl = m.elastic_albedo(l) * illum(l)
                + p.quantum_yield * p.concentration * m.fluorescence.emission(l) * excitation;
            let bar = [cm.x().eval(l), cm.y().eval(l), cm.z().eval(l)];
            for k in 0..3 {
                xyz[k] += w * refl * bar[k];
                white[k] += w * illum(l) * bar[k];
            }
        }
        let y = white[1];
        let adapt = bradford(white.map(|v| v / y), sys.space.white_xyz());
        sys.space.to_rgb(mat_vec(&adapt, xyz.map(|v| v / y)))
    }

    #[test]
    fn white_reflector_maps_to_rgb_one() {
        for space in [RgbSpace::Srgb, RgbSpace::Rec2020, RgbSpace::AcesCg] {
            let sys = ColourSystem::new(space, "D65").unwrap();
            // r = S(1e4) ≈ 1 − 2.5e-9
            let rgb = sys.rgb(&Coefficients::reflectance_only([0.0, 0.0, 1e4]));
            assert!(rgb.iter().all(|v| (v - 1.0).abs() < 1e-4), "{space:?}: {rgb:?}");
        }
    }

    #[test]
    fn colour_matches_independent_fine_quadrature() {
        let sys = ColourSystem::new(RgbSpace::AcesCg, "D65").unwrap();
        let cases = [
            Coefficients::reflectance_only([-2e-4, 0.22, -55.0]),
            Coefficients {
                reflectance: [1e-4, -0.1, 20.0],
                emission_peak: 530.0,
                concentration: 0.8,
                stokes_shift: 60.0,
            },
            Coefficients {
                reflectance: [0.0, 0.01, -5.0],
                emission_peak: 610.0,
                concentration: 1.0,
                stokes_shift: 95.0,
            },
            // a narrow band: s = 5 nm (α ≈ 2.5 nm)
            Coefficients { reflectance: [0.0, 0.0, 0.0], emission_peak: 460.0, concentration: 1.0, stokes_shift: 5.0 },
        ];
        for c in cases {
            let got = sys.rgb(&c);
            let want = reference_rgb(&sys, &c);
            for k in 0..3 {
                assert!((got[k] - want[k]).abs() < 2e-3, "{c:?}: {got:?} vs {want:?}");
            }
        }
    }
}
