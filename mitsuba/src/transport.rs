//! fluo_path, fluo_volpath: the generic fluorescence handle and the reduced RGB transport.

use super::*;

/// Opaque fluorescent model handed to C++ (see [`fluo::interface`]).
///
/// `elastic` is the elastic reflectance when Rust knows it spectrally (sigmoid
/// coefficients; measured diagonals), so that reductions can cover the whole operator
/// ρ(λ)·diag + P as in Fichet et al.; `None` when it comes from a Mitsuba texture.
pub struct Fluorescence {
    pub(crate) model: Model,
    pub(crate) elastic: Option<Reflectance>,
}

pub(crate) fn fluo_excitation_range(f: &Fluorescence) -> Range {
    range_of(f.model.excitation_range())
}
pub(crate) fn fluo_emission_range(f: &Fluorescence) -> Range {
    range_of(f.model.emission_range())
}

/// Opaque reduced transport.
pub struct TransportBasis(Transport);

pub(crate) fn transport_new(basis: &str, method: &str) -> Result<Box<TransportBasis>, String> {
    guarded(|| Ok(Box::new(TransportBasis(Transport::new(basis, Method::from_name(method)?)?))))
}
pub(crate) fn transport_adaptive(lights: &[f64], method: &str) -> Result<Box<TransportBasis>, String> {
    guarded(|| {
        let n = fluo::reduce::grid().len();
        let lights: Vec<Vec<f64>> = lights.chunks(n).map(<[f64]>::to_vec).collect();
        Ok(Box::new(TransportBasis(Transport::adaptive(&lights, Method::from_name(method)?)?)))
    })
}
pub(crate) fn transport_size(t: &TransportBasis) -> usize {
    t.0.len()
}
pub(crate) fn transport_output(t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.output, out);
}
pub(crate) fn transport_from_rgb(t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.from_rgb, out);
}
pub(crate) fn transport_white(t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.white, out);
}
pub(crate) fn transport_name(t: &TransportBasis) -> &'static str {
    t.0.name
}
pub(crate) fn transport_label(t: &TransportBasis) -> String {
    let b = &t.0.basis;
    if b.kind() != fluo::reduce::BasisKind::Adaptive {
        return format!("{}/{:?}", t.0.name, t.0.method);
    }
    // FNV-1a over every band after the six visible ones (the light bands, or x7's U)
    let digest = (6..b.len()).fold(0xcbf2_9ce4_8422_2325_u64, |h, k| {
        fluo::reduce::grid().iter().fold(h, |h, &l| (h ^ b.band(k, l).to_bits()).wrapping_mul(0x0100_0000_01b3))
    });
    format!("{}/{:?}/K{}/{digest:016x}", t.0.name, t.0.method, b.len())
}

pub(crate) fn medium_grid_absorption_max(model: &FluoMedium) -> f64 {
    fluo::reduce::grid().into_iter().map(|l| model.model.absorption_per_m(l)).fold(0.0, f64::max)
}

pub(crate) fn medium_reduced(model: &FluoMedium, t: &TransportBasis, absorption: &mut [f64], reradiation: &mut [f64]) {
    let m = &model.model;
    copy_into(&t.0.reduce(&Operator::diagonal(|l| m.absorption_per_m(l))), absorption);
    copy_into(
        &t.0.reduce(&Operator::new(|_| 0.0, |li, lo| m.absorption_per_m(li) * m.reradiation_per_nm(li, lo))),
        reradiation,
    );
}

/// Incidence-cosine nodes of angle-dependent reduced tables (uniform in cos θ,
/// linearly interpolated; the coating's own tables use the same kind of grid).
pub(crate) const REDUCED_COS_NODES: usize = 17;

/// Opaque reduced operator of one material, with its directional factor.
pub struct ReducedModel {
    directional: Directional,
    full: bool,
}

pub(crate) enum Directional {
    /// f = M/π (Lambertian): one K×K matrix.
    Lambertian(Vec<f64>),
    /// f = D G M(cos θ) / (4 cos θi cos θo), M tabulated at [`REDUCED_COS_NODES`]
    /// incidence cosines on the microfacet (cos θ = ωi·h).
    Microfacet { tables: Vec<Vec<f64>> },
}

pub(crate) fn reduced_new(f: &Fluorescence, t: &TransportBasis) -> Result<Box<ReducedModel>, String> {
    guarded(|| {
        Ok(Box::new(match (&f.model, &f.elastic) {
            (Model::Qd(m), _) => {
                let tables = (0..REDUCED_COS_NODES)
                    .map(|j| {
                        let c = j as f64 / (REDUCED_COS_NODES - 1) as f64;
                        t.0.reduce(&Operator::at(m.as_ref(), c.max(1e-3)).reradiation_only())
                    })
                    .collect();
                // Reradiation only: the plugin serves the elastic part per hit and per RGB
                // channel from the substrate's own eta/k (a gold substrate stays gold).
                ReducedModel { directional: Directional::Microfacet { tables }, full: false }
            }
            (_, Some(r)) => ReducedModel {
                directional: Directional::Lambertian(
                    t.0.reduce(&Operator::of(&f.model).with_elastic(|l| r.eval(l) * f.model.elastic_albedo(1.0, l))),
                ),
                full: true,
            },
            (_, None) => ReducedModel {
                directional: Directional::Lambertian(t.0.reduce(&Operator::of(&f.model).reradiation_only())),
                full: false,
            },
        }))
    })
}

pub(crate) fn jung_reduced_parts(
    model: &JungModel,
    t: &TransportBasis,
    reflectance: &mut [f64],
    absorbed: &mut [f64],
    reradiation: &mut [f64],
) -> bool {
    let copy = |m: Vec<f64>, out: &mut [f64]| {
        for (o, v) in out.iter_mut().zip(m.iter().chain(std::iter::repeat(&0.0))) {
            *o = *v;
        }
    };
    let dye = &model.dye;
    copy(t.0.reduce(&Operator::factored(|_| 0.0, |li| dye.absorption(li), |lo| dye.emission(lo))), reradiation);
    let has_reflectance = model.generic.elastic.is_some();
    if has_reflectance {
        copy(t.0.reduce(&Operator::diagonal(|l| model.reflectance(l))), reflectance);
        copy(t.0.reduce(&Operator::diagonal(|l| model.reflectance(l) * dye.absorption(l))), absorbed);
    } else {
        reflectance.fill(0.0);
        absorbed.fill(0.0);
    }
    has_reflectance
}

pub(crate) fn reduced_includes_elastic(r: &ReducedModel) -> bool {
    r.full
}
pub(crate) fn reduced_lambertian(r: &ReducedModel, out: &mut [f64]) -> bool {
    match &r.directional {
        Directional::Lambertian(m) if out.len() == m.len() => {
            out.copy_from_slice(m);
            true
        }
        _ => false,
    }
}
pub(crate) fn reduced_microfacet_nodes() -> usize {
    REDUCED_COS_NODES
}
/// Relative error (of the largest entry) within which `reduced_microfacet_low_rank` looks
/// for the fewest terms; measured ≤ 8.7e-6 with at most 3 terms for coatings of radius
/// 1.5-4.5 nm, density 0.1-0.8, on gold, glass and a strong conductor, in every basis
/// (test `qd_reduced_operators_are_low_rank`). The vectorised `fluo_path` warns beyond it.
pub(crate) const REDUCED_LOW_RANK_TOLERANCE: f64 = 1e-5;
pub(crate) fn reduced_microfacet_low_rank(
    r: &ReducedModel,
    max_terms: usize,
    basis: &mut [f64],
    weights: &mut [f64],
) -> f64 {
    let Directional::Microfacet { tables, .. } = &r.directional else { return -1.0 };
    let len = tables.first().map_or(0, Vec::len);
    if basis.len() != max_terms * len || weights.len() != tables.len() * max_terms {
        return f64::INFINITY;
    }
    let lr = fluo::reduce::LowRank::new(tables, max_terms, REDUCED_LOW_RANK_TOLERANCE);
    basis.iter_mut().for_each(|v| *v = 0.0);
    weights.iter_mut().for_each(|v| *v = 0.0);
    for (t, b) in lr.basis.iter().enumerate() {
        basis[t * len..(t + 1) * len].copy_from_slice(b);
    }
    for (j, w) in lr.weights.iter().enumerate() {
        weights[j * max_terms..j * max_terms + w.len()].copy_from_slice(w);
    }
    lr.error
}
pub(crate) fn illuminant_coefficients(s: &Illuminant, t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.coefficients(&|l| s.spectrum.eval(l)), out);
}

pub(crate) fn illuminant_on_grid(s: &Illuminant, out: &mut Vec<f64>) {
    out.extend(fluo::reduce::grid().into_iter().map(|l| s.spectrum.eval(l)));
}

/// Marks the plugin library: `import fluo` checks for it, so that `FLUO_LIBRARY` naming
/// another shared library fails with an explanation instead of "plugin not found".
#[no_mangle]
pub extern "C" fn fluo_plugins_built() -> u32 {
    1
}

pub(crate) fn matrix_reduced_jacobian(model: &MeasuredModel, t: &TransportBasis) -> Result<Vec<f64>, String> {
    guarded(|| match &measured_fluorescence(model).model {
        Model::Matrix(m) => Ok(t.0.reduce_jacobian_bilinear(m.lambda_i(), m.lambda_o())),
        _ => Err(fluo::Error::data("not a reradiation matrix".to_string())),
    })
}
