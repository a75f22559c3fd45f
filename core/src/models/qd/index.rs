//! Complex refractive index of the dots: the Ninomiya–Adachi dielectric function of
//! cubic CdSe (tabulated once per process), user-supplied n + ik ([`QdIndex`]), and the
//! optics of one small sphere in a medium (local field factor, Rayleigh cross sections,
//! eqs. 7–8 of Benamira & Pattanaik 2023).

use std::f64::consts::PI;
use std::sync::OnceLock;

use crate::spectrum::{IrregularSpectrum, Spectral};
use crate::{Error, Result};

/// A complex number n + ik or ε₁ + iε₂ (num-complex's, re-exported by nalgebra).
pub type Complex = nalgebra::Complex<f64>;

/// h·c in eV·nm, as in the refractiveindex.info script of Ninomiya & Adachi.
pub const HC_EV_NM: f64 = 413.566_733 * 2.997_924_58;
/// Wavelengths over which the CdSe model is tabulated, nm (fitted over 207–827 nm).
pub const CDSE_TABLE_RANGE_NM: (f64, f64) = (200.0, 1200.0);
const CDSE_TABLE_STEP_NM: f64 = 0.5;
/// Terms of the discrete exciton series of the CdSe model (as the published script).
const EXCITON_TERMS: usize = 999;

/// Principal square root (branch cut on the negative real axis; Re ≥ 0) by the
/// half-angle formulas √((|z| ± Re z)/2), without the atan2/sin/cos of num-complex's
/// polar `sqrt` (which moves the CdSe index by up to ~4e−13 relative).
fn sqrt(z: Complex) -> Complex {
    let r = z.norm_sqr().sqrt();
    let re = (0.5 * (r + z.re)).max(0.0).sqrt();
    let im = (0.5 * (r - z.re)).max(0.0).sqrt();
    Complex::new(re, if z.im < 0.0 { -im } else { im })
}

/// Dielectric function ε(E) of cubic CdSe, Ninomiya & Adachi (1995), Table III.
pub fn cdse_dielectric_function(energy_ev: f64) -> Complex {
    const E0: f64 = 1.74;
    const E0_D0: f64 = 2.15; // E0 + Δ0
    const G0: f64 = 0.015; // exciton binding energy
    const A0: f64 = 4.7; // eV^1.5
    const A0X: f64 = 0.01;
    const GAMMA0: f64 = 0.03;
    const E1: f64 = 4.28;
    const E1_D1: f64 = 4.48; // E1 + Δ1
    const B1: f64 = 3.0;
    const B1D: f64 = 1.5;
    const GAMMA1: f64 = 0.50;
    const GAMMA1D: f64 = 0.90;
    const E2: f64 = 6.08;
    const C: f64 = 1.4;
    const GAMMA2: f64 = 0.21;
    const EPS_INF: f64 = 1.40;

    let one = Complex::new(1.0, 0.0);
    let w = Complex::new(energy_ev, GAMMA0);
    // E0 / E0+Δ0 three-dimensional M0 critical points: f(χ) = χ⁻²(2 − √(1+χ) − √(1−χ)).
    let f = |chi: Complex| (Complex::new(2.0, 0.0) - sqrt(one + chi) - sqrt(one - chi)) / (chi * chi);
    let chi0 = w.scale(1.0 / E0);
    let chi_s0 = w.scale(1.0 / E0_D0);
    let eps_a = (f(chi0).scale(2.0) + f(chi_s0).scale((E0 / E0_D0).powf(1.5))).scale(A0 * E0.powf(-1.5));
    // Discrete exciton series at E0 and E0 + Δ0.
    let mut eps_x = Complex::new(0.0, 0.0);
    for n in 1..=EXCITON_TERMS {
        let n2 = (n * n) as f64;
        let a = A0X / (n2 * n as f64);
        let d1 = Complex::new(E0 - G0 / n2 - energy_ev, -GAMMA0);
        let d2 = Complex::new(E0_D0 - G0 / n2 - energy_ev, -GAMMA0);
        eps_x += (Complex::new(2.0, 0.0) / d1 + one / d2).scale(a);
    }
    // E1, E1 + Δ1 damped oscillators.
    let eps_b = Complex::new(B1, 0.0) / Complex::new(E1 - energy_ev, -GAMMA1)
        + Complex::new(B1D, 0.0) / Complex::new(E1_D1 - energy_ev, -GAMMA1D);
    // E2 damped harmonic oscillator.
    let chi2 = energy_ev / E2;
    let eps_c = Complex::new(C, 0.0) / Complex::new(1.0 - chi2 * chi2, -chi2 * GAMMA2);
    eps_a + eps_x + eps_b + eps_c + Complex::new(EPS_INF, 0.0)
}

fn cdse_table() -> &'static Vec<Complex> {
    static TABLE: OnceLock<Vec<Complex>> = OnceLock::new();
    TABLE.get_or_init(|| {
        let (lo, hi) = CDSE_TABLE_RANGE_NM;
        let n = ((hi - lo) / CDSE_TABLE_STEP_NM).round() as usize;
        (0..=n).map(|i| sqrt(cdse_dielectric_function(HC_EV_NM / (lo + i as f64 * CDSE_TABLE_STEP_NM)))).collect()
    })
}

/// Complex refractive index n + ik of cubic CdSe at λ (nm), from the tabulated
/// Ninomiya–Adachi model (linear interpolation, clamped to [`CDSE_TABLE_RANGE_NM`]).
pub fn cdse_refractive_index(lambda_nm: f64) -> Complex {
    let t = cdse_table();
    let (lo, hi) = CDSE_TABLE_RANGE_NM;
    let x = (lambda_nm.clamp(lo, hi) - lo) / CDSE_TABLE_STEP_NM;
    let x = if x.is_finite() { x } else { 0.0 };
    let i = (x.floor() as usize).min(t.len() - 2);
    let f = x - i as f64;
    match (t.get(i), t.get(i + 1)) {
        (Some(a), Some(b)) => a.scale(1.0 - f) + b.scale(f),
        _ => Complex::new(1.0, 0.0),
    }
}

/// Linear interpolation clamped to the end values (not zero outside).
pub(super) fn eval_clamped(s: &IrregularSpectrum, lambda: f64) -> f64 {
    let w = s.wavelengths_nm();
    let v = s.values();
    match (w.first(), w.last(), v.first(), v.last()) {
        (Some(&w0), Some(&w1), Some(&v0), Some(&v1)) => {
            if lambda <= w0 {
                v0
            } else if lambda >= w1 {
                v1
            } else {
                s.eval(lambda)
            }
        }
        _ => 0.0,
    }
}

/// Complex refractive index of the dot material.
#[derive(Debug, Clone, PartialEq)]
pub enum QdIndex {
    /// Cubic CdSe, Ninomiya & Adachi (1995) model (the default).
    CdSe,
    /// User-supplied n(λ) and k(λ) (linear interpolation, constant beyond the ends).
    Tabulated {
        /// Real part n.
        n: IrregularSpectrum,
        /// Imaginary part k ≥ 0.
        k: IrregularSpectrum,
    },
}

impl QdIndex {
    /// m_QD(λ) = n + ik.
    pub fn eval(&self, lambda_nm: f64) -> Complex {
        match self {
            QdIndex::CdSe => cdse_refractive_index(lambda_nm),
            QdIndex::Tabulated { n, k } => Complex::new(eval_clamped(n, lambda_nm), eval_clamped(k, lambda_nm)),
        }
    }

    pub(super) fn validate(&self) -> Result<()> {
        if let QdIndex::Tabulated { n, k } = self {
            if let Some(v) = n.values().iter().find(|v| !(**v > 0.0)) {
                return Err(Error::param("qd_eta", v, "(0, ∞) at every wavelength"));
            }
            if let Some(v) = k.values().iter().find(|v| !(**v >= 0.0)) {
                return Err(Error::param("qd_k", v, "[0, ∞) at every wavelength"));
            }
        }
        Ok(())
    }
}

/// Local field factor f = 3 m_env² / (m_QD² + 2 m_env²) (eq. 8).
pub fn local_field_factor(m_qd: Complex, n_env: f64) -> Complex {
    let e = n_env * n_env;
    Complex::new(3.0 * e, 0.0) / (m_qd * m_qd + Complex::new(2.0 * e, 0.0))
}

/// Rayleigh scattering cross section, nm² (eq. 7). **Reading:** Rayleigh scattering
/// goes with the *squared* modulus of the polarisability factor and, in a medium,
/// with k⁴ = (2π n_env/λ)⁴ (Bohren & Huffman 5.8): 24π³V² n_env⁴/λ⁴ |(m²−n²)/(m²+2n²)|².
pub fn rayleigh_scattering_cross_section_nm2(radius_nm: f64, lambda_nm: f64, m_qd: Complex, n_env: f64) -> f64 {
    let v = 4.0 / 3.0 * PI * radius_nm.powi(3);
    let e = Complex::new(n_env * n_env, 0.0);
    let m2 = m_qd * m_qd;
    let ratio = ((m2 - e) / (m2 + e.scale(2.0))).norm_sqr();
    24.0 * PI.powi(3) * v * v * n_env.powi(4) / lambda_nm.powi(4) * ratio
}

/// Rayleigh (dipole) absorption cross section, nm² (eq. 7). **Reading:** Leatherdale
/// et al. (2002), whom the paper cites, and the dipole limit of Bohren & Huffman give
/// σ = (2π/λ) (1/n_env) |f|² ε₂ V with ε₂ = 2 n_QD k_QD, i.e. 4π n_QD k_QD |f|² V /
/// (n_env λ); the paper's print has n_env in the numerator and no n_QD.
pub fn rayleigh_absorption_cross_section_nm2(radius_nm: f64, lambda_nm: f64, m_qd: Complex, n_env: f64) -> f64 {
    let v = 4.0 / 3.0 * PI * radius_nm.powi(3);
    let f2 = local_field_factor(m_qd, n_env).norm_sqr();
    (4.0 * PI * m_qd.re * m_qd.im * f2 * v / (n_env * lambda_nm)).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rayleigh_absorption_is_the_dipole_limit() {
        // Independent: σ = k Im(α), k = 2π n/λ, α = 4π a³ (ε − εm)/(ε + 2εm) / ... with
        // ε relative to the medium: α = 4πa³ (m_r² − 1)/(m_r² + 2), m_r = m/n.
        for (lam, n_env) in [(350.0, 1.0), (450.0, 1.446), (600.0, 1.33)] {
            let m = cdse_refractive_index(lam);
            let a = 2.5;
            let mr = m.scale(1.0 / n_env);
            let one = Complex::new(1.0, 0.0);
            let pol = ((mr * mr - one) / (mr * mr + one.scale(2.0))).scale(4.0 * PI * a * a * a);
            let want = 2.0 * PI * n_env / lam * pol.im;
            let got = rayleigh_absorption_cross_section_nm2(a, lam, m, n_env);
            assert!((got - want).abs() < 1e-9 * want, "{got} vs {want}");
        }
    }

    /// `<repo>/../shared/data`, or `$FLUO_SHARED_DATA`.
    fn shared_data() -> std::path::PathBuf {
        std::env::var_os("FLUO_SHARED_DATA")
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"))
    }

    /// Rows `wavelength_um n k` of a refractiveindex.info `tabulated nk` YAML file.
    fn read_nk_yml(path: &std::path::Path) -> Vec<(f64, f64, f64)> {
        let text = std::fs::read_to_string(path).unwrap();
        text.lines()
            .filter_map(|l| {
                let v: Vec<f64> = l.split_whitespace().map(str::parse).collect::<std::result::Result<_, _>>().ok()?;
                (v.len() == 3).then(|| (v[0] * 1e3, v[1], v[2]))
            })
            .collect()
    }

    #[test]
    fn cdse_default_matches_the_tabulated_data() {
        let dir = shared_data().join("ior");
        let cubic = dir.join("CdSe_Ninomiya-cubic.yml");
        if !cubic.is_file() {
            eprintln!(
                "SKIP cdse_default_matches_the_tabulated_data: {} absent (shared data not beside the repo)",
                cubic.display()
            );
            return;
        }
        // Cubic CdSe: the table was generated from the same published model (Table III),
        // so the built-in model must reproduce it to the table's 5 digits.
        let rows = read_nk_yml(&cubic);
        assert!(rows.len() > 400, "{} rows", rows.len());
        let mut worst = 0.0f64;
        for &(l, n, k) in &rows {
            let m = cdse_refractive_index(l);
            worst = worst.max(((m.re - n) / n).abs()).max((m.im - k).abs() / k.max(0.05));
        }
        eprintln!("cubic CdSe vs {}: worst relative deviation {worst:.2e} over {} rows", cubic.display(), rows.len());
        assert!(worst < 2e-3, "cubic CdSe: worst relative deviation {worst}");
        // Wurtzite (ordinary ray): a different crystal phase; the cubic model stays within
        // 10 % in n over the visible (a plausibility check of the default, not a fit).
        let hex = read_nk_yml(&dir.join("CdSe_Ninomiya-o.yml"));
        for &(l, n, _) in hex.iter().filter(|r| r.0 >= 400.0 && r.0 <= 800.0) {
            let m = cdse_refractive_index(l);
            assert!(((m.re - n) / n).abs() < 0.1, "λ={l}: {} vs {n}", m.re);
        }
    }
}
