//! The shift albedo tabulated over λo, for a wavelength-shifting integrator that asks
//! for it at every fluorescent vertex.
//!
//! A path tracer chooses between the elastic and the shifted event at a vertex with
//! probabilities proportional to the elastic albedo and to
//! [`Bispectral::shift_albedo`] (λo the path's wavelength, the excitation range R fixed
//! per scene). The choice stays unbiased for *any* weight that is positive wherever the
//! true shift albedo is: where the weight is positive but the true value is zero, the
//! shifted event samples nothing and the elastic event is weighted up by exactly the
//! probability it lost. So the weight may be approximate, but must never be zero where
//! fluorescence reaches λo.
//!
//! [`ShiftTable`] stores the exact value at the nodes of a uniform λo grid for one R
//! (built once, when a scene is prepared) and interpolates linearly inside a cell
//! whose two nodes are positive (positive there, whatever the true value in between);
//! outside the material's emission range it is zero (nothing is re-emitted there, so
//! the true value is zero); any other cell, and λo outside the grid, calls the
//! material's exact `shift_albedo`. Only materials whose shift albedo does not depend on ωi
//! ([`Bispectral::shift_albedo_is_isotropic`]) are tabulated.

use crate::interface::Bispectral;

/// λo step of [`ShiftTable`], nm.
pub const SHIFT_TABLE_STEP_NM: f64 = 1.0;

const UP: [f64; 3] = [0.0, 0.0, 1.0];

/// A material's shift albedo for one excitation range, tabulated over λo (see the
/// module docs for why this is unbiased).
#[derive(Debug, Clone)]
pub struct ShiftTable {
    range: (f64, f64),
    lo: f64,
    values: Vec<f64>,
    /// The material's emission range: outside it the shift albedo is exactly zero.
    emission: Option<(f64, f64)>,
}

impl ShiftTable {
    /// Tabulate `material`'s shift albedo for excitation over `range`, at λo over
    /// `lambda_o` (nm) every [`SHIFT_TABLE_STEP_NM`]; `None` when it depends on ωi or
    /// the interval is empty.
    pub fn new(material: &dyn Bispectral, range: (f64, f64), lambda_o: (f64, f64)) -> Option<Self> {
        if !material.shift_albedo_is_isotropic() || !(lambda_o.1 > lambda_o.0) || !lambda_o.0.is_finite() {
            return None;
        }
        let n = ((lambda_o.1 - lambda_o.0) / SHIFT_TABLE_STEP_NM).ceil().min(1e6) as usize + 1;
        let values = (0..n)
            .map(|k| {
                let v = material.shift_albedo(UP, lambda_o.0 + k as f64 * SHIFT_TABLE_STEP_NM, range);
                if v.is_finite() {
                    v.max(0.0)
                } else {
                    0.0
                }
            })
            .collect();
        Some(Self { range, lo: lambda_o.0, values, emission: material.emission_range() })
    }

    /// The excitation range the table was built for.
    pub fn range(&self) -> (f64, f64) {
        self.range
    }

    /// The shift albedo at λo for light arriving from `wi`: interpolated in cells
    /// whose nodes are both positive, exact (`material.shift_albedo`) elsewhere.
    /// `material` must be the one the table was built from.
    pub fn eval(&self, material: &dyn Bispectral, wi: [f64; 3], lambda_o: f64) -> f64 {
        if !(wi[2] > 0.0) {
            return 0.0;
        }
        // Nothing re-emitted at λo (the interface's emission range): zero, exactly,
        // without asking the material.
        match self.emission {
            Some((a, b)) if lambda_o >= a && lambda_o <= b => {}
            _ => return 0.0,
        }
        let x = (lambda_o - self.lo) / SHIFT_TABLE_STEP_NM;
        if x >= 0.0 {
            let k = x as usize;
            if let (Some(&a), Some(&b)) = (self.values.get(k), self.values.get(k + 1)) {
                if a > 0.0 && b > 0.0 {
                    let t = x - k as f64;
                    return a + t * (b - a);
                }
            }
        }
        material.shift_albedo(wi, lambda_o, self.range)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::matrix::MatrixModel;

    use crate::testutil::green_dye as dye;

    /// The table is positive wherever the exact value is (never zero where fluorescence
    /// reaches λo); returns its largest error relative to the largest value, on a fine
    /// λo grid (only the variance of the estimator depends on it).
    fn check(m: &dyn Bispectral, range: (f64, f64)) -> f64 {
        let t = ShiftTable::new(m, range, (300.0, 830.0)).unwrap();
        let peak = t.values.iter().fold(0.0f64, |a, &b| a.max(b));
        let mut worst: f64 = 0.0;
        for i in 0..=53_000 {
            let l = 299.0 + i as f64 * 0.01;
            let (exact, got) = (m.shift_albedo(UP, l, range), t.eval(m, UP, l));
            if exact > 0.0 {
                assert!(got > 0.0, "λo = {l}: table {got}, exact {exact}");
                worst = worst.max((got - exact).abs() / peak);
            } else {
                assert!(got >= 0.0, "λo = {l}: {got}");
            }
            assert_eq!(t.eval(m, [0.0, 0.0, -1.0], l), 0.0);
        }
        worst
    }

    #[test]
    fn jung_table_is_positive_where_the_integral_is_and_close() {
        let worst = check(&dye(), (360.0, 830.0));
        assert!(worst < 2e-3, "{worst}");
    }

    #[test]
    fn measured_table_is_positive_where_the_integral_is_and_close() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/matrices/jung_orange.csv");
        let m = MatrixModel::from_file(&path).unwrap();
        let worst = check(&m, (380.0, 830.0));
        assert!(worst < 0.05, "{worst}");
    }

    #[test]
    fn measured_tables_are_zero_only_where_the_integral_is() {
        // Every shipped matrix and Gaussian-mixture fit: the table (with its zero outside
        // the emission range) is positive wherever the exact value is.
        use crate::models::gmm::GmmModel;
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/matrices");
        for name in ["jung_brightener.csv", "jung_yellow.csv", "jung_orange.csv"] {
            let m = MatrixModel::from_file(dir.join(name)).unwrap();
            check(&m, (300.0, 830.0));
        }
        let g = GmmModel::from_file(dir.join("jung_orange.gmm.json")).unwrap();
        check(&g, (300.0, 830.0));
        check(&g, (380.0, 830.0));
    }

    #[test]
    fn direction_dependent_models_are_not_tabulated() {
        use crate::models::qd::{QdIndex, QdModel, QdParams, Substrate};
        let qd = QdModel::new(QdParams::default(), QdIndex::CdSe, Substrate::Constant { eta: 1.5, k: 0.0 }).unwrap();
        assert!(ShiftTable::new(&qd, (360.0, 830.0), (300.0, 830.0)).is_none());
        assert!(ShiftTable::new(&dye(), (360.0, 830.0), (830.0, 300.0)).is_none());
    }
}
