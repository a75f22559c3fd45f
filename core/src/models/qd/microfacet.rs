//! The surface under the quantum-dot film: the isotropic microfacet distribution
//! ([`Microfacet`], Mitsuba's Beckmann and GGX D with Smith G1) and the substrate's
//! Fresnel reflectance ([`Substrate`], Mitsuba's `fresnel_conductor`).

use std::f64::consts::PI;

use super::index::eval_clamped;
use crate::spectrum::IrregularSpectrum;
use crate::{Error, Result};

/// Smallest microfacet roughness (Mitsuba clamps α = 0 to the same value).
pub const MIN_ALPHA: f64 = 1e-4;
/// Mitsuba's guard on D(m)·cos θm below which D is zero.
const D_CUTOFF: f64 = 1e-20;

/// Microfacet distribution type (Mitsuba's `distribution`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Distribution {
    /// Beckmann (Mitsuba's default for rough conductors).
    Beckmann,
    /// GGX / Trowbridge–Reitz.
    Ggx,
}

/// Isotropic microfacet distribution with Mitsuba's D and Smith G1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Microfacet {
    /// Type.
    pub kind: Distribution,
    /// Roughness α.
    pub alpha: f64,
}

/// a · b.
pub(super) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Normalised ωi + ωo, or `None` if degenerate.
pub(super) fn half_vector(wi: [f64; 3], wo: [f64; 3]) -> Option<[f64; 3]> {
    let h = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
    let n = dot(h, h).sqrt();
    (n > 0.0 && n.is_finite()).then(|| [h[0] / n, h[1] / n, h[2] / n])
}

impl Microfacet {
    /// D(m), sr⁻¹ (zero where Mitsuba's guard D·cos θm > 1e−20 fails).
    pub fn d(&self, m: [f64; 3]) -> f64 {
        let a2 = self.alpha * self.alpha;
        let c2 = m[2] * m[2];
        let xy = m[0] * m[0] + m[1] * m[1];
        let r = match self.kind {
            Distribution::Beckmann => {
                if !(c2 > 0.0) {
                    return 0.0;
                }
                (-(xy / a2) / c2).exp() / (PI * a2 * c2 * c2)
            }
            Distribution::Ggx => {
                let t = xy / a2 + c2;
                1.0 / (PI * a2 * t * t)
            }
        };
        if r * m[2] > D_CUTOFF && r.is_finite() {
            r
        } else {
            0.0
        }
    }

    /// Smith's G1(v, m), as Mitsuba (Beckmann: its rational approximation).
    pub fn smith_g1(&self, v: [f64; 3], m: [f64; 3]) -> f64 {
        if dot(v, m) * v[2] <= 0.0 {
            return 0.0;
        }
        let xy = self.alpha * self.alpha * (v[0] * v[0] + v[1] * v[1]);
        if xy == 0.0 {
            return 1.0;
        }
        let t = xy / (v[2] * v[2]);
        match self.kind {
            Distribution::Beckmann => {
                let a = 1.0 / t.sqrt();
                if a >= 1.6 {
                    1.0
                } else {
                    (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
                }
            }
            Distribution::Ggx => 2.0 / (1.0 + (1.0 + t).sqrt()),
        }
    }

    /// pdf of Mitsuba's visible-normal sampling of ωo = reflect(ωi, m), per sr of ωo:
    /// D(m) G1(ωi, m) / (4 cos θi).
    pub fn pdf_reflect(&self, wi: [f64; 3], wo: [f64; 3]) -> f64 {
        if !(wi[2] > 0.0 && wo[2] > 0.0) {
            return 0.0;
        }
        match half_vector(wi, wo) {
            Some(m) if dot(wi, m) > 0.0 && dot(wo, m) > 0.0 => self.d(m) * self.smith_g1(wi, m) / (4.0 * wi[2]),
            _ => 0.0,
        }
    }

    /// D G / (4 cos θi) and cos θ = ωi·h, or `None` where Mitsuba's eval returns 0.
    pub fn lobe(&self, wi: [f64; 3], wo: [f64; 3]) -> Option<(f64, f64)> {
        if !(wi[2] > 0.0 && wo[2] > 0.0) {
            return None;
        }
        let h = half_vector(wi, wo)?;
        let d = self.d(h);
        if d == 0.0 {
            return None;
        }
        let g = self.smith_g1(wi, h) * self.smith_g1(wo, h);
        let c = dot(wi, h);
        (g > 0.0 && c > 0.0).then(|| (d * g / (4.0 * wi[2]), c.min(1.0)))
    }
}

/// Unpolarised Fresnel reflectance of a conductor (Mitsuba's `fresnel_conductor`, in
/// f64); with k = 0 and η > 1 it is the dielectric reflectance.
pub fn fresnel_conductor(cos_theta_i: f64, eta: f64, k: f64) -> f64 {
    let c2 = cos_theta_i * cos_theta_i;
    let s2 = 1.0 - c2;
    let s4 = s2 * s2;
    let t1 = eta * eta - k * k - s2;
    let a2pb2 = (t1 * t1 + 4.0 * k * k * eta * eta).max(0.0).sqrt();
    let a = (0.5 * (a2pb2 + t1)).max(0.0).sqrt();
    let term1 = a2pb2 + c2;
    let term2 = 2.0 * cos_theta_i * a;
    let rs = (term1 - term2) / (term1 + term2);
    let term3 = a2pb2 * c2 + s4;
    let term4 = term2 * s2;
    let rp = rs * (term3 - term4) / (term3 + term4);
    let r = 0.5 * (rs + rp);
    if r.is_finite() {
        r.clamp(0.0, 1.0)
    } else {
        1.0
    }
}

/// The surface under the coating, relative to the environment (η = n/n_env).
#[derive(Debug, Clone, PartialEq)]
pub enum Substrate {
    /// Constant complex index η + ik (k = 0: a dielectric, reflection only).
    Constant {
        /// Real part.
        eta: f64,
        /// Imaginary part.
        k: f64,
    },
    /// Spectral η(λ), k(λ) (e.g. sampled from Mitsuba's `material` data).
    Tabulated {
        /// Real part.
        eta: IrregularSpectrum,
        /// Imaginary part.
        k: IrregularSpectrum,
    },
}

impl Substrate {
    /// Fresnel reflectance R(θ, λ).
    pub fn reflectance(&self, cos_theta: f64, lambda_nm: f64) -> f64 {
        let (eta, k) = self.eta_k(lambda_nm);
        fresnel_conductor(cos_theta, eta, k)
    }

    /// (η, k) at λ (tabulated: clamped to the table's ends).
    pub fn eta_k(&self, lambda_nm: f64) -> (f64, f64) {
        match self {
            Substrate::Constant { eta, k } => (*eta, *k),
            Substrate::Tabulated { eta, k } => (eval_clamped(eta, lambda_nm), eval_clamped(k, lambda_nm)),
        }
    }

    pub(super) fn validate(&self) -> Result<()> {
        // η = 0 is valid Mitsuba input (roughconductor's default η = 0, k = 1).
        let ok_eta = |v: f64| v.is_finite() && v >= 0.0;
        let ok_k = |v: f64| v.is_finite() && v >= 0.0;
        match self {
            Substrate::Constant { eta, k } => {
                if !ok_eta(*eta) {
                    return Err(Error::param("eta", eta, "[0, ∞)"));
                }
                if !ok_k(*k) {
                    return Err(Error::param("k", k, "[0, ∞)"));
                }
            }
            Substrate::Tabulated { eta, k } => {
                if let Some(v) = eta.values().iter().find(|v| !ok_eta(**v)) {
                    return Err(Error::param("eta", v, "[0, ∞) at every wavelength"));
                }
                if let Some(v) = k.values().iter().find(|v| !ok_k(**v)) {
                    return Err(Error::param("k", v, "[0, ∞) at every wavelength"));
                }
            }
        }
        Ok(())
    }
}
