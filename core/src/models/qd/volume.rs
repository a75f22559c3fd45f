//! Absorption and emission cross sections of dots dispersed in a medium
//! ([`QdVolume`], sec. 4.1 of Benamira & Pattanaik 2023, eqs. 9–15), for a
//! fluorescent participating medium.

use super::band::{
    check_lambda_range, cut_gaussian, lambda_grid, logistic, logistic_cdf, trapezoid, QdBand, TABLE_STEP_NM,
};
use super::index::{rayleigh_absorption_cross_section_nm2, rayleigh_scattering_cross_section_nm2, QdIndex};
use crate::error::check_range;
use crate::Result;

/// Absorption and emission cross sections of dots dispersed in a medium (sec. 4.1),
/// ready for a fluorescent participating medium.
#[derive(Debug, Clone, PartialEq)]
pub struct QdVolume {
    band: QdBand,
    index: QdIndex,
    n_env: f64,
    quantum_yield: f64,
    lambda_range: (f64, f64),
    /// β = σ_abs^Ray(λQD), nm² (eq. 9).
    beta: f64,
    /// γ of eq. 15, nm³.
    gamma: f64,
}

impl QdVolume {
    /// Dots of `band` and index `index` in a medium of index `n_env`; γ normalises the
    /// emission over [λmin, λmax] (eq. 15).
    pub fn new(band: QdBand, index: QdIndex, n_env: f64, quantum_yield: f64, lambda_range: (f64, f64)) -> Result<Self> {
        check_range("ext_ior", n_env, 1.0, 3.0)?;
        check_range("quantum_yield", quantum_yield, 0.0, 1.0)?;
        check_lambda_range(lambda_range)?;
        index.validate()?;
        let beta = rayleigh_absorption_cross_section_nm2(
            band.radius_nm,
            band.lambda_qd_nm,
            index.eval(band.lambda_qd_nm),
            n_env,
        );
        let mut v = Self { band, index, n_env, quantum_yield, lambda_range, beta, gamma: 0.0 };
        let grid = lambda_grid(lambda_range, &band, TABLE_STEP_NM);
        let total = trapezoid(&grid, |l| v.absorption_cross_section_nm2(l));
        let i = v.emission_normalisation();
        v.gamma = if i > 0.0 { quantum_yield / i * total } else { 0.0 };
        Ok(v)
    }

    /// The band (λQD, Stokes shift, emission peak).
    pub fn band(&self) -> &QdBand {
        &self.band
    }

    /// I = Λ(λmax) − Λ(λmin) (eq. 13).
    pub fn emission_normalisation(&self) -> f64 {
        let mu = self.band.emission_peak_nm;
        let s = 0.5 * self.band.width_nm;
        logistic_cdf(self.lambda_range.1, mu, s) - logistic_cdf(self.lambda_range.0, mu, s)
    }

    /// σ_abs(λ), nm² (eq. 9): Rayleigh bulk absorption below λQD plus the Gaussian
    /// quantum absorption, continuous at λQD.
    pub fn absorption_cross_section_nm2(&self, lambda_nm: f64) -> f64 {
        let b = &self.band;
        let g = cut_gaussian(lambda_nm, b.lambda_qd_nm, b.width_nm);
        if lambda_nm <= b.lambda_qd_nm {
            rayleigh_absorption_cross_section_nm2(b.radius_nm, lambda_nm, self.index.eval(lambda_nm), self.n_env)
                + 0.5 * self.beta * g
        } else {
            1.5 * self.beta * g
        }
    }

    /// σ_em(λ) = γ L(λ, λQD + Sλ, δλ/2), nm² (eq. 10), zero outside [λmin, λmax].
    pub fn emission_cross_section_nm2(&self, lambda_nm: f64) -> f64 {
        if !(lambda_nm >= self.lambda_range.0 && lambda_nm <= self.lambda_range.1) {
            return 0.0;
        }
        self.gamma * logistic(lambda_nm, self.band.emission_peak_nm, 0.5 * self.band.width_nm)
    }

    /// Rayleigh scattering cross section at λ, nm² (neglected by the model).
    pub fn scattering_cross_section_nm2(&self, lambda_nm: f64) -> f64 {
        rayleigh_scattering_cross_section_nm2(self.band.radius_nm, lambda_nm, self.index.eval(lambda_nm), self.n_env)
    }

    /// γ of eq. 15, nm³.
    pub fn gamma(&self) -> f64 {
        self.gamma
    }

    /// Quantum yield Q.
    pub fn quantum_yield(&self) -> f64 {
        self.quantum_yield
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::qd::band::QdConstants;

    #[test]
    fn volume_cross_sections_follow_figs_5_and_6() {
        let c = QdConstants::default();
        let vol = |r: f64, d: f64| {
            QdVolume::new(QdBand::new(&c, r, d).unwrap(), QdIndex::CdSe, 1.446, 0.8, (300.0, 830.0)).unwrap()
        };
        // Emission peak (argmax of σ_em) grows with R.
        let argmax = |v: &QdVolume| {
            (0..=5300).map(|i| 300.0 + 0.1 * i as f64).fold((0.0, 0.0), |b, l| {
                let s = v.emission_cross_section_nm2(l);
                if s > b.1 {
                    (l, s)
                } else {
                    b
                }
            })
        };
        let mut prev = 0.0;
        for r in [1.5, 2.0, 2.7, 3.3, 4.5] {
            let v = vol(r, 15.0);
            let (peak, _) = argmax(&v);
            assert!(peak > prev, "R = {r}: peak {peak}");
            assert!((peak - v.band().emission_peak_nm).abs() < 0.11);
            prev = peak;
            // σ_abs continuous at λQD, and ∫σ_em = Q ∫σ_abs (eq. 15).
            let lq = v.band().lambda_qd_nm;
            let (a, b) = (v.absorption_cross_section_nm2(lq - 1e-9), v.absorption_cross_section_nm2(lq + 1e-9));
            assert!((a - b).abs() < 1e-6 * a, "{a} vs {b}");
            let grid: Vec<f64> = (0..=530_000).map(|i| 300.0 + 0.001 * i as f64).collect();
            let em = trapezoid(&grid, |l| v.emission_cross_section_nm2(l));
            let ab = trapezoid(&grid, |l| v.absorption_cross_section_nm2(l));
            assert!((em - 0.8 * ab).abs() < 1e-4 * ab, "{em} vs {}", 0.8 * ab);
            // Scattering is negligible next to absorption in the UV (the paper's claim).
            assert!(v.scattering_cross_section_nm2(350.0) < 1e-2 * v.absorption_cross_section_nm2(350.0));
        }
        // Fig. 6: wider bands lower the emission maximum.
        let mut prev = f64::INFINITY;
        for d in [10.0, 15.0, 20.0, 25.0, 30.0] {
            let (_, m) = argmax(&vol(1.8, d));
            assert!(m < prev);
            prev = m;
        }
    }
}
