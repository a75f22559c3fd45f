//! fluo_qd_medium, fluo_dye_medium: fluorescent participating media and their tables.

use super::*;

/// Opaque fluorescent medium handed to C++ (either plugin).
pub struct FluoMedium {
    pub(crate) model: MediumModel,
}

impl From<&QdMediumConfig> for qd::QdMediumParams {
    fn from(c: &QdMediumConfig) -> Self {
        qd::QdMediumParams {
            radius_nm: c.radius,
            width_nm: c.width,
            quantum_yield: c.quantum_yield,
            concentration_um: c.concentration,
            ext_ior: c.ext_ior,
            lambda_min_nm: c.lambda_min,
            lambda_max_nm: c.lambda_max,
            constants: (&c.constants).into(),
            table_step_nm: c.table_step,
        }
    }
}

pub(crate) fn qd_medium_new(config: &QdMediumConfig) -> Result<Box<FluoMedium>, String> {
    guarded(|| Ok(Box::new(FluoMedium { model: MediumModel::Qd(Box::new(qd::QdMedium::new(config.into())?)) })))
}

pub(crate) fn qd_medium_default_config() -> QdMediumConfig {
    let p = qd::QdMediumParams::default();
    QdMediumConfig {
        radius: p.radius_nm,
        width: p.width_nm,
        quantum_yield: p.quantum_yield,
        concentration: p.concentration_um,
        ext_ior: p.ext_ior,
        lambda_min: p.lambda_min_nm,
        lambda_max: p.lambda_max_nm,
        constants: (&p.constants).into(),
        table_step: p.table_step_nm,
    }
}

pub(crate) fn dye_medium_new(c: &DyeMediumConfig) -> Result<Box<FluoMedium>, String> {
    guarded(|| {
        let p = DyeMediumParams {
            emission_peak_nm: c.emission_peak,
            stokes_shift_nm: c.stokes_shift,
            quantum_yield: c.quantum_yield,
            sigma_a_per_m: c.sigma_a,
        };
        Ok(Box::new(FluoMedium { model: MediumModel::Dye(DyeMedium::new(p)?) }))
    })
}

pub(crate) fn dye_medium_default_config() -> DyeMediumConfig {
    let p = DyeMediumParams::default();
    DyeMediumConfig {
        emission_peak: p.emission_peak_nm,
        stokes_shift: p.stokes_shift_nm,
        quantum_yield: p.quantum_yield,
        sigma_a: p.sigma_a_per_m,
    }
}

pub(crate) fn medium_is_fluorescent(model: &FluoMedium) -> bool {
    model.model.is_fluorescent()
}

pub(crate) fn medium_absorption_rgb(model: &FluoMedium) -> Rgb {
    let c = spectrum_to_srgb(|l| model.model.absorption_per_m(l));
    rgb([c[0].max(0.0), c[1].max(0.0), c[2].max(0.0)])
}

pub(crate) fn medium_lambda_range(model: &FluoMedium) -> Range {
    range_of(Some(model.model.lambda_range()))
}

pub(crate) fn medium_jit_tables(model: &FluoMedium) -> MediumJitTables {
    bridged(model.model.jit_tables())
}

pub(crate) fn medium_jit_tables_on(model: &FluoMedium, lambda: &[f64], emission_lambda: &[f64]) -> MediumJitTables {
    bridged(model.model.jit_tables_on(lambda.to_vec(), emission_lambda.to_vec()))
}

fn bridged(t: fluo::model::MediumJitTables) -> MediumJitTables {
    MediumJitTables {
        lambda: t.lambda,
        mu_a: t.mu_a,
        cum: t.cum,
        emission_lambda: t.emission_lambda,
        emission: t.emission,
    }
}

pub(crate) fn medium_to_string(model: &FluoMedium) -> String {
    model.model.to_string()
}
