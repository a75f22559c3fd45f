//! fluo_matrix, fluo_gmm: measured reradiation matrices and their Gaussian mixtures.

use super::*;

/// Opaque measured material (`fluo_matrix`, `fluo_gmm`) handed to C++: everything it
/// serves goes through the bispectral interface, so the generic handle is its only
/// field, with the measured diagonal as the model's elastic albedo.
pub struct MeasuredModel(Fluorescence);

impl MeasuredModel {
    fn new(model: Model) -> Box<Self> {
        Box::new(MeasuredModel(Fluorescence { model, elastic: Some(Reflectance::Constant(1.0)) }))
    }

    fn elastic_albedo(&self, lambda: f64) -> f64 {
        self.0.model.elastic_albedo(1.0, lambda)
    }
}

pub(crate) fn matrix_new(filename: &str) -> Result<Box<MeasuredModel>, String> {
    guarded(|| Ok(MeasuredModel::new(Model::Matrix(Arc::new(fluo::models::matrix::MatrixModel::from_file(filename)?)))))
}

pub(crate) fn gmm_new(filename: &str) -> Result<Box<MeasuredModel>, String> {
    guarded(|| Ok(MeasuredModel::new(Model::Gmm(Arc::new(fluo::models::gmm::GmmModel::from_file(filename)?)))))
}

pub(crate) fn measured_is_fluorescent(model: &MeasuredModel) -> bool {
    model.0.model.excitation_range().is_some()
}

pub(crate) fn measured_rgb_albedo(model: &MeasuredModel) -> Rgb {
    const UP: [f64; 3] = [0.0, 0.0, 1.0];
    let shifted = |l: f64| model.0.model.shift_albedo(UP, l, (CIE_MIN_NM, CIE_MAX_NM));
    rgb(bounded_rgb_albedo(spectrum_to_srgb(|l| model.elastic_albedo(l)), spectrum_to_srgb(shifted)))
}

pub(crate) fn measured_rgb_elastic(model: &MeasuredModel) -> Rgb {
    rgb(spectrum_to_srgb(|l| model.elastic_albedo(l)))
}

pub(crate) fn measured_to_string(model: &MeasuredModel) -> String {
    model.0.model.to_string()
}

pub(crate) fn measured_check_index(values: &[f32], width: usize, count: usize) -> Result<(), String> {
    check_texture_values("index", values, width, |_, v| fluo::models::check_material_index(v, count))
}

pub(crate) fn measured_tables(model: &MeasuredModel) -> MeasuredTables {
    let mut t = MeasuredTables {
        kind: String::new(),
        diagonal_nm: Vec::new(),
        diagonal: Vec::new(),
        lambda_i: Vec::new(),
        lambda_o: Vec::new(),
        p: Vec::new(),
        row_cdf: Vec::new(),
        scale: 0.0,
        rect: Vec::new(),
        components: Vec::new(),
    };
    match &model.0.model {
        Model::Matrix(m) => {
            let (nm, d) = m.diagonal();
            let (p, row_cdf) = m.row_tables();
            t = MeasuredTables {
                kind: "matrix".into(),
                diagonal_nm: nm.to_vec(),
                diagonal: d.to_vec(),
                lambda_i: m.lambda_i().to_vec(),
                lambda_o: m.lambda_o().to_vec(),
                p: p.to_vec(),
                row_cdf: row_cdf.to_vec(),
                ..t
            };
        }
        Model::Gmm(g) => {
            let f = g.file();
            t.kind = "gmm".into();
            t.diagonal_nm.clone_from(&f.diagonal.wavelengths_nm);
            t.diagonal.clone_from(&f.diagonal.values);
            t.scale = f.scale;
            t.rect =
                vec![f.lambda_i_range_nm[0], f.lambda_i_range_nm[1], f.lambda_o_range_nm[0], f.lambda_o_range_nm[1]];
            for c in &f.components {
                let [[aa, ab], [ba, bb]] = c.covariance;
                t.components.extend([c.weight, c.mean[0], c.mean[1], aa, 0.5 * (ab + ba), bb]);
            }
        }
        _ => {}
    }
    t
}

pub(crate) fn gmm_updated(
    model: &MeasuredModel,
    weights: &[f64],
    means_excitation: &[f64],
    means_emission: &[f64],
) -> Result<Box<MeasuredModel>, String> {
    guarded(|| {
        let Model::Gmm(g) = &model.0.model else {
            return Err(fluo::Error::data("not a Gaussian-mixture material".to_string()));
        };
        let mut file = g.file().clone();
        let n = file.components.len();
        if weights.len() != n || means_excitation.len() != n || means_emission.len() != n {
            return Err(fluo::Error::param("weights", weights.len(), format!("{n} entries (one per component)")));
        }
        let total: f64 = weights.iter().sum();
        if let Some(w) = weights.iter().find(|w| !(w.is_finite() && **w >= 0.0)) {
            return Err(fluo::Error::param("weights", w, "[0, ∞) (renormalised to sum 1)"));
        }
        if !(total > 0.0 && total.is_finite()) {
            return Err(fluo::Error::param("weights", format!("sum {total}"), "a positive sum"));
        }
        for (k, c) in file.components.iter_mut().enumerate() {
            c.weight = weights[k] / total;
            c.mean = [means_excitation[k], means_emission[k]];
        }
        Ok(MeasuredModel::new(Model::Gmm(Arc::new(fluo::models::gmm::GmmModel::new(file)?))))
    })
}

pub(crate) fn matrix_updated(model: &MeasuredModel, reradiation: &[f64]) -> Result<Box<MeasuredModel>, String> {
    guarded(|| {
        let Model::Matrix(m) = &model.0.model else {
            return Err(fluo::Error::data("not a reradiation matrix".to_string()));
        };
        Ok(MeasuredModel::new(Model::Matrix(Arc::new(m.with_reradiation(reradiation)?))))
    })
}

pub(crate) fn measured_fluorescence(model: &MeasuredModel) -> &Fluorescence {
    &model.0
}
