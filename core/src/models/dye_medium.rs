//! A fluorescent dye dissolved in a participating medium ([`DyeMedium`], `fluo_dye_medium`):
//! Jung et al.'s spectra (b-spline emission e(λ), its mirrored absorption a(λ), eqs. 3-6 of
//! Jung et al. 2019, as [`JungFluorescence`]) as volume coefficients.
//!
//! ```text
//! μa(λ) = σa · a(λ)                         (1/m; a ∈ [0, 1], peak 1 at λe − s)
//! f(λi → λo) = Q · e(λo) · [λi < λo]        (re-emitted per nm of λo per unit absorbed)
//! μf(λo | R) = Q e(λo) σa ∫_{R.lo}^{min(R.hi, λo)} a(λi) dλi
//! ```
//!
//! ∫ e = 1, and absorption and emission supports never overlap (the mirror construction),
//! so every absorbed photon re-emits with probability exactly Q. Excitation sampling is
//! the exact inverse CDF of a(λ) over the interval ([`JungFluorescence::sample_absorption`]),
//! so p = μa f / μf and a shift weighs μf (the bispectral medium contract).
//!
//! | name            | unit | valid range                    | default |
//! |-----------------|------|--------------------------------|---------|
//! | `emission_peak` | nm   | [200, 1200]                    | 520     |
//! | `stokes_shift`  | nm   | (0, max_stokes_shift(λe)]      | 60      |
//! | `quantum_yield` | 1    | [0, 1]                         | 0.9     |
//! | `sigma_a`       | 1/m  | [0, 1e9] (peak absorption)     | 100     |

use std::fmt;

use super::jung::{JungFluorescence, JungParams};
use crate::error::check_range;
use crate::Result;

/// Valid range of `sigma_a`, 1/m.
pub const SIGMA_A_RANGE_PER_M: (f64, f64) = (0.0, 1e9);

/// User parameters of a dye medium (see the module table).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DyeMediumParams {
    /// Emission peak λe, nm.
    pub emission_peak_nm: f64,
    /// Stokes shift s, nm.
    pub stokes_shift_nm: f64,
    /// Quantum yield Q.
    pub quantum_yield: f64,
    /// Peak absorption coefficient σa, 1/m.
    pub sigma_a_per_m: f64,
}

impl Default for DyeMediumParams {
    fn default() -> Self {
        Self { emission_peak_nm: 520.0, stokes_shift_nm: 60.0, quantum_yield: 0.9, sigma_a_per_m: 100.0 }
    }
}

/// A validated dye medium.
#[derive(Debug, Clone)]
pub struct DyeMedium {
    params: DyeMediumParams,
    dye: JungFluorescence,
}

impl DyeMedium {
    /// Validate (errors name the parameter, its value and the valid range).
    pub fn new(params: DyeMediumParams) -> Result<Self> {
        check_range("sigma_a", params.sigma_a_per_m, SIGMA_A_RANGE_PER_M.0, SIGMA_A_RANGE_PER_M.1)?;
        let dye = JungFluorescence::new(JungParams {
            emission_peak: params.emission_peak_nm,
            stokes_shift: params.stokes_shift_nm,
            concentration: 1.0,
            quantum_yield: params.quantum_yield,
        })?;
        Ok(Self { params, dye })
    }

    /// Whether anything is ever re-emitted.
    pub fn is_fluorescent(&self) -> bool {
        self.params.quantum_yield > 0.0 && self.params.sigma_a_per_m > 0.0
    }

    /// [absorption support's start, emission support's end], nm.
    pub fn lambda_range(&self) -> (f64, f64) {
        (self.dye.absorption_support().0, self.dye.emission_support().1)
    }

    /// μa(λ), 1/m.
    pub fn absorption_per_m(&self, lambda_nm: f64) -> f64 {
        self.params.sigma_a_per_m * self.dye.absorption(lambda_nm)
    }

    /// Q e(λo), per nm per unit absorbed.
    pub fn emission_per_nm(&self, lambda_o_nm: f64) -> f64 {
        self.params.quantum_yield * self.dye.emission(lambda_o_nm)
    }

    /// f(λi → λo), per nm of λo per unit absorbed at λi.
    pub fn reradiation_per_nm(&self, lambda_i_nm: f64, lambda_o_nm: f64) -> f64 {
        if lambda_i_nm < lambda_o_nm {
            self.emission_per_nm(lambda_o_nm)
        } else {
            0.0
        }
    }

    /// μf(λo | R), 1/m.
    pub fn shift_coefficient_per_m(&self, lambda_o_nm: f64, range: (f64, f64)) -> f64 {
        let e = self.emission_per_nm(lambda_o_nm);
        if !(e > 0.0) {
            return 0.0;
        }
        let hi = range.1.min(lambda_o_nm);
        e * self.params.sigma_a_per_m * self.dye.absorption_integral_range(range.0, hi)
    }

    /// λi ∝ a(λi) over [R.lo, min(R.hi, λo)]: (λi, pdf per nm), or None.
    pub fn sample_excitation(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> Option<(f64, f64)> {
        if !(self.emission_per_nm(lambda_o_nm) > 0.0) {
            return None;
        }
        self.dye.sample_absorption(xi, range.0, range.1.min(lambda_o_nm))
    }
}

impl fmt::Display for DyeMedium {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let p = &self.params;
        write!(
            f,
            "DyeMedium[emission_peak = {} nm, stokes_shift = {} nm, quantum_yield = {}, sigma_a = {} 1/m]",
            p.emission_peak_nm, p.stokes_shift_nm, p.quantum_yield, p.sigma_a_per_m
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dye_medium_keeps_the_contract() {
        let m = DyeMedium::new(DyeMediumParams::default()).unwrap();
        let range = (300.0, 830.0);
        for lo in [480.0, 520.0, 560.0] {
            let mu_f = m.shift_coefficient_per_m(lo, range);
            // μf by midpoint quadrature of μa f.
            let n = 200_000;
            let h = (lo - 300.0) / n as f64;
            let q: f64 = (0..n)
                .map(|i| {
                    let l = 300.0 + (i as f64 + 0.5) * h;
                    m.absorption_per_m(l) * m.reradiation_per_nm(l, lo) * h
                })
                .sum();
            assert!((mu_f - q).abs() <= 1e-6 * q.max(1e-12), "{lo}: {mu_f} vs {q}");
            if mu_f > 0.0 {
                let (l, pdf) = m.sample_excitation(lo, range, 0.37).unwrap();
                let want = m.absorption_per_m(l) * m.reradiation_per_nm(l, lo) / mu_f;
                assert!((pdf - want).abs() <= 1e-9 * want, "{pdf} vs {want}");
            }
        }
        assert!(DyeMedium::new(DyeMediumParams { sigma_a_per_m: -1.0, ..Default::default() })
            .unwrap_err()
            .to_string()
            .contains("sigma_a"));
        assert!(DyeMedium::new(DyeMediumParams { quantum_yield: 2.0, ..Default::default() })
            .unwrap_err()
            .to_string()
            .contains("quantum_yield"));
    }
}
