//! fluo_qd: Benamira & Pattanaik's quantum-dot coating and its tables.

use super::*;

/// Opaque `fluo_qd` material handed to C++: the coating, shared with the generic handle.
pub struct QdModel {
    pub(crate) coating: Arc<qd::QdModel>,
    generic: Fluorescence,
}

/// `From` both ways between a bridge struct and its core twin with the same fields,
/// each field named once.
macro_rules! mirror {
    ($bridge:ty, $core:ty { $($field:ident),* $(,)? }) => {
        impl From<&$core> for $bridge {
            fn from(c: &$core) -> Self {
                Self { $($field: c.$field),* }
            }
        }
        impl From<&$bridge> for $core {
            fn from(b: &$bridge) -> Self {
                Self { $($field: b.$field),* }
            }
        }
    };
}

mirror!(
    QdConstants,
    qd::QdConstants {
        gap_energy,
        elementary_charge,
        planck,
        light_speed,
        boltzmann,
        electron_mass,
        hole_mass,
        vacuum_permittivity,
        relative_permittivity,
        temperature,
    }
);

impl From<&QdConfig> for qd::QdParams {
    fn from(c: &QdConfig) -> Self {
        qd::QdParams {
            radius_nm: c.radius,
            width_nm: c.width,
            quantum_yield: c.quantum_yield,
            density: c.density,
            ext_ior: c.ext_ior,
            lambda_min_nm: c.lambda_min,
            lambda_max_nm: c.lambda_max,
            distribution: if c.ggx { qd::Distribution::Ggx } else { qd::Distribution::Beckmann },
            alpha: c.alpha,
            constants: (&c.constants).into(),
            cos_nodes: c.table_cos_nodes,
            table_step_nm: c.table_step,
        }
    }
}

impl From<&qd::QdParams> for QdConfig {
    fn from(p: &qd::QdParams) -> Self {
        QdConfig {
            radius: p.radius_nm,
            width: p.width_nm,
            quantum_yield: p.quantum_yield,
            density: p.density,
            ext_ior: p.ext_ior,
            lambda_min: p.lambda_min_nm,
            lambda_max: p.lambda_max_nm,
            ggx: p.distribution == qd::Distribution::Ggx,
            alpha: p.alpha,
            constants: (&p.constants).into(),
            table_cos_nodes: p.cos_nodes,
            table_step: p.table_step_nm,
        }
    }
}

/// A spectrum from shim samples: one value is a constant, several a table.
pub(crate) fn spectrum_of(name: &str, s: &SampledSpectrum) -> fluo::Result<IrregularSpectrum> {
    match s.values {
        [v] => IrregularSpectrum::new(vec![0.0, 1e4], vec![*v, *v]),
        _ => IrregularSpectrum::new(s.wavelengths.to_vec(), s.values.to_vec())
            .map_err(|e| fluo::Error::data(format!("{name}: {e}"))),
    }
}

pub(crate) fn qd_new(
    config: &QdConfig,
    eta: &SampledSpectrum,
    k: &SampledSpectrum,
    qd_eta: &SampledSpectrum,
    qd_k: &SampledSpectrum,
) -> Result<Box<QdModel>, String> {
    guarded(|| {
        let substrate = match (eta.values, k.values) {
            ([eta], [k]) => qd::Substrate::Constant { eta: *eta, k: *k },
            _ => qd::Substrate::Tabulated { eta: spectrum_of("eta", eta)?, k: spectrum_of("k", k)? },
        };
        let index = if qd_eta.values.is_empty() && qd_k.values.is_empty() {
            qd::QdIndex::CdSe
        } else {
            qd::QdIndex::Tabulated { n: spectrum_of("qd_eta", qd_eta)?, k: spectrum_of("qd_k", qd_k)? }
        };
        let coating = Arc::new(qd::QdModel::new(config.into(), index, substrate)?);
        // The coating's elastic reflectance R_tot(θ, λ) lives in the Rust model (the
        // substrate's eta/k are passed in), so reductions cover the whole operator.
        let generic =
            Fluorescence { model: Model::Qd(Arc::clone(&coating)), elastic: Some(Reflectance::Constant(1.0)) };
        Ok(Box::new(QdModel { coating, generic }))
    })
}

pub(crate) fn qd_default_config() -> QdConfig {
    (&qd::QdParams::default()).into()
}

pub(crate) fn qd_is_fluorescent(model: &QdModel) -> bool {
    model.coating.is_fluorescent()
}

pub(crate) fn qd_jit_tables(
    model: &QdModel,
    rows: usize,
    lambda: &[f64],
    extra_nm: &[f64],
    spectral: bool,
) -> QdJitTables {
    let m = &model.coating;
    let t = if !spectral {
        // (the RGB variants read the channels' coefficients alone: the λ tables were most of
        // an RGB coating's load)
        let mut t = m.jit_tables_on(rows, &[], extra_nm);
        t.lambda = m.table_lambda().to_vec();
        t
    } else if lambda.is_empty() {
        m.jit_tables(rows, extra_nm)
    } else {
        m.jit_tables_on(rows, lambda, extra_nm)
    };
    let p = m.params();
    let (excitation_lo, excitation_hi) = t.excitation.unwrap_or((0.0, 0.0));
    QdJitTables {
        lambda: t.lambda,
        rows: t.rows,
        a_tot: t.a_tot,
        cdf: t.cdf,
        r_spe: t.r_spe,
        pass: t.pass,
        r_tot: t.r_tot,
        extra_r_spe: t.extra_r_spe,
        extra_pass: t.extra_pass,
        emission_peak_nm: t.emission_peak_nm,
        emission_scale_nm: t.emission_scale_nm,
        emission_norm: t.emission_norm,
        lambda_min: p.lambda_min_nm,
        lambda_max: p.lambda_max_nm,
        excitation_lo,
        excitation_hi,
    }
}

pub(crate) fn qd_to_string(model: &QdModel) -> String {
    model.coating.to_string()
}

pub(crate) fn qd_fluorescence(model: &QdModel) -> &Fluorescence {
    &model.generic
}

pub(crate) fn qd_check_values(name: &str, values: &[f32], width: usize) -> Result<(), String> {
    check_texture_values(name, values, width, qd::check_param_value)
}

pub(crate) fn qd_texture_grid_nodes() -> usize {
    qd::TEXTURE_GRID_NODES
}

pub(crate) fn qd_texture_max_radii() -> usize {
    qd::TEXTURE_MAX_RADII
}

pub(crate) fn qd_texture_max_alphas() -> usize {
    qd::TEXTURE_MAX_ALPHAS
}
