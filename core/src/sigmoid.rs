//! Jakob & Hanika's sigmoid-polynomial reflectance spectra.
//!
//! Jung et al. 2019, eq. 2 (after Jakob & Hanika 2019):
//!
//! ```text
//! r(λ) = S(P(λ)),   P(λ) = c0·λ² + c1·λ + c2,   S(x) = 1/2 + x / (2·sqrt(1 + x²))
//! ```
//!
//! with λ in nm. `S` maps ℝ onto (0, 1), so every coefficient triple is an
//! energy-conserving reflectance.
//!
//! Numerical notes: `x / sqrt(1 + x²)` overflows for |x| > 1e154; it is computed as
//! `x / hypot(1, x)`, which is exact to rounding for every finite x. Infinite `x`
//! (from huge coefficients) saturates to 0 or 1.
//!
//! References: W. Jakob, J. Hanika, "A Low-Dimensional Function Space for Efficient
//! Spectral Upsampling", CGF 38(2), 2019.

use crate::{Error, Result};

/// A sigmoid-polynomial reflectance spectrum `r(λ) = S(c0 λ² + c1 λ + c2)`, λ in nm.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SigmoidPolynomial {
    /// Polynomial coefficients `[c0, c1, c2]` (units nm⁻², nm⁻¹, 1).
    pub coefficients: [f64; 3],
}

/// The sigmoid `S(x) = 1/2 + x / (2 sqrt(1 + x²))`, saturating for infinite `x`.
pub fn sigmoid(x: f64) -> f64 {
    if x.is_nan() {
        return 0.5;
    }
    if x.is_infinite() {
        return if x > 0.0 { 1.0 } else { 0.0 };
    }
    0.5 + 0.5 * x / 1.0_f64.hypot(x)
}

/// Derivative `S'(x) = 1 / (2 (1 + x²)^{3/2})`.
pub fn sigmoid_derivative(x: f64) -> f64 {
    if !x.is_finite() {
        return 0.0;
    }
    let h = 1.0_f64.hypot(x);
    0.5 / (h * h * h)
}

impl SigmoidPolynomial {
    /// Build from coefficients; they must be finite.
    pub fn new(coefficients: [f64; 3]) -> Result<Self> {
        for (i, c) in coefficients.iter().enumerate() {
            if !c.is_finite() {
                return Err(Error::param(&format!("coefficients[{i}]"), c, "a finite number"));
            }
        }
        Ok(Self { coefficients })
    }

    /// The polynomial `P(λ)`, evaluated with fused multiply-adds (Horner).
    pub fn polynomial(&self, lambda_nm: f64) -> f64 {
        let [c0, c1, c2] = self.coefficients;
        c0.mul_add(lambda_nm, c1).mul_add(lambda_nm, c2)
    }

    /// Reflectance `r(λ) ∈ [0, 1]`.
    pub fn eval(&self, lambda_nm: f64) -> f64 {
        sigmoid(self.polynomial(lambda_nm))
    }

    /// Derivative `dr/dλ` (per nm), used by the smoothness penalty of Jung et al. sec. 3.2.
    pub fn derivative(&self, lambda_nm: f64) -> f64 {
        let [c0, c1, _] = self.coefficients;
        sigmoid_derivative(self.polynomial(lambda_nm)) * (2.0 * c0).mul_add(lambda_nm, c1)
    }
}

impl crate::spectrum::Spectral for SigmoidPolynomial {
    fn eval(&self, lambda_nm: f64) -> f64 {
        SigmoidPolynomial::eval(self, lambda_nm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sigmoid_limits_and_midpoint() {
        assert_eq!(sigmoid(0.0), 0.5);
        assert_eq!(sigmoid(f64::INFINITY), 1.0);
        assert_eq!(sigmoid(f64::NEG_INFINITY), 0.0);
        assert!((sigmoid(1e300) - 1.0).abs() < 1e-15);
        assert!(sigmoid(-1e300).abs() < 1e-15);
        // S(1) = 1/2 + 1/(2 sqrt 2)
        assert!((sigmoid(1.0) - (0.5 + 0.5 / 2f64.sqrt())).abs() < 1e-15);
    }

    #[test]
    fn derivative_matches_finite_difference() {
        let s = SigmoidPolynomial::new([1e-4, -0.1, 20.0]).unwrap();
        for lambda in [360.0, 450.0, 500.0, 620.0, 830.0] {
            let h = 1e-4;
            let fd = (s.eval(lambda + h) - s.eval(lambda - h)) / (2.0 * h);
            assert!((fd - s.derivative(lambda)).abs() < 1e-7, "λ={lambda}: {fd} vs {}", s.derivative(lambda));
        }
    }

    #[test]
    fn rejects_non_finite() {
        let e = SigmoidPolynomial::new([0.0, f64::NAN, 0.0]).unwrap_err();
        assert!(e.to_string().contains("coefficients[1]"), "{e}");
    }
}
