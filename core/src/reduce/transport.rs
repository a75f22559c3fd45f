//! Reduced transport for a renderer whose working space is Mitsuba's linear sRGB: the
//! basis, its RGB maps and per-material reduced matrices (what `fluo_path` carries in
//! `scalar_rgb`).

use nalgebra::{DMatrix, DVector};

use super::{reduce, Basis, BasisKind, Method, Operator};
use crate::spectrum::{cmf, Observer};
use crate::{Error, Result};

/// A transport basis prepared for a renderer whose working space is Mitsuba's linear
/// sRGB (CIE 1931 based): coefficients are normalised like Mitsuba's spectrum → RGB
/// conversion (c = Sᵀ W L / ∫ȳ), and the maps between RGB and coefficients are
/// precomputed.
#[derive(Debug, Clone)]
pub struct Transport {
    /// `rgb`, `xyzu` or `x7` (`rgb` transports sRGB itself with the XYZ reduction
    /// converted by eq. 16).
    pub name: &'static str,
    /// The basis (CIE 1931 bands).
    pub basis: Basis,
    /// Method of the reductions.
    pub method: Method,
    /// 3×K: linear sRGB = output · c.
    pub output: Vec<f64>,
    /// K×3: coefficients of light given as linear sRGB (upsampled with the dual XYZ basis).
    pub from_rgb: Vec<f64>,
    /// K×3 and the white response, for turning an RGB albedo into a per-band one:
    /// a_k = (from_rgb · a)_k / (from_rgb · 1)_k.
    pub white: Vec<f64>,
}

impl Transport {
    /// Prepare `rgb`, `xyzu`, `x7` or `auto` transport (`auto` without lights: the bands of
    /// `x7`; [`Transport::adaptive`] builds it for a scene's lights).
    pub fn new(name: &str, method: Method) -> Result<Self> {
        let kind = match name.to_ascii_lowercase().as_str() {
            "rgb" | "xyz" => BasisKind::Xyz,
            "xyzu" => BasisKind::Xyzu,
            "x7" => BasisKind::X7,
            "auto" => BasisKind::Adaptive,
            _ => return Err(Error::param("basis", format!("\"{name}\""), "one of rgb, xyzu, x7, auto")),
        };
        let label =
            if name.eq_ignore_ascii_case("rgb") || name.eq_ignore_ascii_case("xyz") { "rgb" } else { kind.name() };
        Self::with_basis(label, Basis::new(kind, Observer::Cie1931)?, method)
    }

    /// The scene-adaptive transport (`auto`, [`Basis::adaptive`]) for the lights' spectra
    /// `lights`, each sampled on the reduction grid ([`super::grid`]).
    pub fn adaptive(lights: &[Vec<f64>], method: Method) -> Result<Self> {
        Self::with_basis("auto", Basis::adaptive(Observer::Cie1931, lights)?, method)
    }

    fn with_basis(label: &'static str, basis: Basis, method: Method) -> Result<Self> {
        if label == "auto" && method == Method::Naive {
            // the naive reduction divides by each band's area: the light band has none to speak of
            return Err(Error::param("method", "\"naive\"", "\"ours\" with basis \"auto\""));
        }
        let m = nalgebra::Matrix3::from_fn(|r, c| crate::colour::mitsuba::XYZ_TO_SRGB[r][c]);
        let minv = m.try_inverse().ok_or_else(|| Error::data("XYZ→sRGB matrix is singular"))?;
        // XYZ basis (for upsampling RGB light) in the same normalisation.
        let xyz = Basis::new(BasisKind::Xyz, Observer::Cie1931)?;
        // K×3 map: c_K = Sᵀ W S̃_xyz · xyz, xyz = M⁻¹ rgb   (coefficients of a spectrum are
        // scaled by 1/∫ȳ on both sides, so the map is scale-free)
        let proj = basis.gram(&xyz.dual); // K×3 (Sᵀ W S̃_xyz)
        let mut from_rgb_m = &proj * DMatrix::from_fn(3, 3, |r, c| minv[(r, c)]);
        // RGB light lies in span(x̄, ȳ, z̄), W-orthogonal to the light bands: their rows are
        // zero (what the product leaves is rounding, which band albedos would divide)
        for band in basis.len() - basis.light_bands()..basis.len() {
            for c in 0..3 {
                from_rgb_m[(band, c)] = 0.0;
            }
        }
        let t = &basis.t;
        let out_m = DMatrix::from_fn(3, 3, |r, c| m[(r, c)]) * t; // 3×K
        let (output, from_rgb) = if label == "rgb" {
            (DMatrix::<f64>::identity(3, 3), DMatrix::<f64>::identity(3, 3))
        } else {
            (out_m, from_rgb_m)
        };
        let white = &from_rgb * DVector::from_element(3, 1.0);
        Ok(Self {
            name: label,
            method,
            output: output.transpose().iter().copied().collect(),
            from_rgb: from_rgb.transpose().iter().copied().collect(),
            white: white.iter().copied().collect(),
            basis,
        })
    }

    /// Number of transported channels K.
    pub fn len(&self) -> usize {
        if self.name == "rgb" {
            3
        } else {
            self.basis.len()
        }
    }

    /// Always false.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The reduced reradiation (or full operator) of a material for this transport,
    /// K×K row major. `rgb` uses the XYZ reduction converted with eq. 16.
    pub fn reduce(&self, material: &Operator) -> Vec<f64> {
        let r = reduce(material, &self.basis, self.method);
        let k = self.basis.len();
        self.finish(DMatrix::from_fn(k, k, |i, j| r.matrix[i][j]))
    }

    /// [`Transport::reduce`]'s derivative with respect to each node value of a bilinear
    /// reradiation table on the grids `lambda_i`, `lambda_o` ([`super::bilinear_jacobian`]):
    /// one K×K matrix (row major) per node, node j·n_i + k, one after the other.
    pub fn reduce_jacobian_bilinear(&self, lambda_i: &[f64], lambda_o: &[f64]) -> Vec<f64> {
        super::bilinear_jacobian(&self.basis, self.method, lambda_i, lambda_o)
            .into_iter()
            .flat_map(|m| self.finish(m))
            .collect()
    }

    /// A reduced matrix in this transport's channels (`rgb`: eq. 16 from XYZ), row major.
    fn finish(&self, mx: DMatrix<f64>) -> Vec<f64> {
        let out = if self.name == "rgb" {
            let m = DMatrix::from_fn(3, 3, |i, j| crate::colour::mitsuba::XYZ_TO_SRGB[i][j]);
            let minv = m.clone().try_inverse().unwrap_or_else(|| DMatrix::identity(3, 3));
            m * mx * minv
        } else {
            mx
        };
        out.transpose().iter().copied().collect()
    }

    /// Coefficients of a light spectrum in this transport (Mitsuba's normalisation:
    /// a unit spectrum has Y = 1; `rgb` gives its linear sRGB).
    pub fn coefficients(&self, f: &dyn Fn(f64) -> f64) -> Vec<f64> {
        let ybar = cmf(Observer::Cie1931).y().integrate();
        let c: Vec<f64> = self.basis.down(f).into_iter().map(|v| v / ybar).collect();
        if self.name == "rgb" {
            let xyz = self.basis.to_xyz(&c);
            crate::colour::mitsuba::XYZ_TO_SRGB
                .iter()
                .map(|row| row[0] * xyz[0] + row[1] * xyz[1] + row[2] * xyz[2])
                .collect()
        } else {
            c
        }
    }
}

#[cfg(test)]
mod transport_tests {
    use super::*;

    #[test]
    fn bilinear_jacobian_times_the_table_is_the_reduction() {
        // the reduction is linear in the table: Σ_node ∂M/∂p·p must be the reduction of the
        // model's reradiation (evaluated by the model itself), in every basis and method
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/matrices/jung_orange.csv");
        let model = crate::models::matrix::MatrixModel::from_file(&path).unwrap();
        let (p, _) = model.row_tables();
        let rerad = Operator::new(|_| 0.0, |li, lo| model.reradiation(li, lo));
        for (name, method) in [("x7", Method::Ours), ("rgb", Method::Ours), ("xyzu", Method::Naive)] {
            let t = Transport::new(name, method).unwrap();
            let kk = t.len() * t.len();
            let jac = t.reduce_jacobian_bilinear(model.lambda_i(), model.lambda_o());
            assert_eq!(jac.len(), kk * p.len());
            let want = t.reduce(&rerad);
            let scale = want.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
            assert!(scale > 1e-3, "{name}: nothing reduced");
            for e in 0..kk {
                let got: f64 = p.iter().enumerate().map(|(n, v)| v * jac[n * kk + e]).sum();
                assert!((got - want[e]).abs() <= 1e-9 * scale, "{name} entry {e}: {got} vs {want:?}");
            }
        }
        // an updated table is validated
        let mut q = p.to_vec();
        q[3] = -1.0;
        let err = model.with_reradiation(&q).unwrap_err().to_string();
        assert!(err.contains("reradiation") && err.contains("-1"), "{err}");
        assert!(model.with_reradiation(&q[1..]).is_err());
        q[3] = 1e30; // beyond a file's bound: renders in f32 would overflow
        assert!(model.with_reradiation(&q).unwrap_err().to_string().contains("reradiation"));
        q[3] = 0.0;
        assert!(model.with_reradiation(&q).is_ok());
    }

    #[test]
    fn rgb_transport_maps_white_to_white_and_matches_mitsuba_conversion() {
        for name in ["rgb", "xyzu", "x7"] {
            let t = Transport::new(name, Method::Ours).unwrap();
            let k = t.len();
            // light given in RGB, through from_rgb then output, comes back unchanged
            let rgb = [0.3, 0.5, 0.9];
            let c: Vec<f64> = (0..k).map(|i| (0..3).map(|j| t.from_rgb[i * 3 + j] * rgb[j]).sum()).collect();
            let back: Vec<f64> = (0..3).map(|r| (0..k).map(|i| t.output[r * k + i] * c[i]).sum()).collect();
            for j in 0..3 {
                assert!((back[j] - rgb[j]).abs() < 1e-9, "{name}: {back:?}");
            }
            // a spectrum's coefficients give Mitsuba's sRGB of it
            let f = |l: f64| 0.5 + 0.4 * ((l - 400.0) / 80.0).sin();
            let c = t.coefficients(&f);
            let out: Vec<f64> = (0..3).map(|r| (0..k).map(|i| t.output[r * k + i] * c[i]).sum()).collect();
            let want = crate::colour::mitsuba::spectrum_to_srgb(f);
            for j in 0..3 {
                // the grids' trapezoid end weights differ at 360 nm
                assert!((out[j] - want[j]).abs() < 1e-5, "{name}: {out:?} vs {want:?}");
            }
            // identity material -> identity matrix
            let m = t.reduce(&Operator::new(|_| 1.0, |_, _| 0.0));
            for i in 0..k {
                for j in 0..k {
                    assert!((m[i * k + j] - if i == j { 1.0 } else { 0.0 }).abs() < 1e-9);
                }
            }
        }
    }
}
