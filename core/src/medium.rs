//! The fluorescent participating media ([`MediumModel`]): a closed set with static
//! dispatch, seen by `fluo_volpath` through one bispectral medium contract:
//!
//! * μa(λ), 1/m: absorption (all of it attenuates);
//! * f(λi → λo): re-emitted power per nm of λo per unit power absorbed at λi, isotropic,
//!   ∫ f dλo ≤ quantum yield;
//! * μf(λo | R) = ∫_R μa(λi) f(λi → λo) dλi, 1/m;
//! * excitation sampling with density exactly μa f / μf over R (so a shift weighs μf).
//!
//! Models: [`QdMedium`] (`fluo_qd_medium`, Benamira & Pattanaik 2023) and [`DyeMedium`]
//! (`fluo_dye_medium`, Jung et al.'s dye spectra). Adding one: its module under
//! `models/`, one arm per method here, its bridge constructor and shim.

use std::fmt;

use crate::models::dye_medium::DyeMedium;
use crate::models::qd::QdMedium;

/// A fluorescent participating medium.
#[derive(Debug, Clone)]
pub enum MediumModel {
    /// Quantum dots in a host (boxed: its baked tables' header is large).
    Qd(Box<QdMedium>),
    /// A Jung-style dye in solution.
    Dye(DyeMedium),
}

macro_rules! dispatch {
    ($self:ident, $m:ident => $e:expr) => {
        match $self {
            MediumModel::Qd($m) => $e,
            MediumModel::Dye($m) => $e,
        }
    };
}

impl MediumModel {
    /// Whether anything is ever re-emitted.
    pub fn is_fluorescent(&self) -> bool {
        dispatch!(self, m => m.is_fluorescent())
    }

    /// [λmin, λmax], nm: where absorption re-emits and where emission lands.
    pub fn lambda_range(&self) -> (f64, f64) {
        dispatch!(self, m => m.lambda_range())
    }

    /// μa(λ), 1/m.
    pub fn absorption_per_m(&self, lambda_nm: f64) -> f64 {
        dispatch!(self, m => m.absorption_per_m(lambda_nm))
    }

    /// f(λi → λo), per nm of λo per unit absorbed at λi.
    pub fn reradiation_per_nm(&self, lambda_i_nm: f64, lambda_o_nm: f64) -> f64 {
        dispatch!(self, m => m.reradiation_per_nm(lambda_i_nm, lambda_o_nm))
    }

    /// μf(λo | R), 1/m.
    pub fn shift_coefficient_per_m(&self, lambda_o_nm: f64, range: (f64, f64)) -> f64 {
        dispatch!(self, m => m.shift_coefficient_per_m(lambda_o_nm, range))
    }

    /// λi with density μa f / μf over R: (λi, pdf per nm), or None where μf = 0.
    pub fn sample_excitation(&self, lambda_o_nm: f64, range: (f64, f64), xi: f64) -> Option<(f64, f64)> {
        dispatch!(self, m => m.sample_excitation(lambda_o_nm, range, xi))
    }
}

impl fmt::Display for MediumModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        dispatch!(self, m => m.fmt(f))
    }
}
