//! Fichet et al. 2024, Table 1, on the measured matrices in ../shared/data/bispectral:
//! ours-XYZU averaged over the materials must be within 0.5 ΔE2000 of the paper's row
//! for every illuminant and at or below its mean over the seven (2.54); the 7-band
//! basis must improve on XYZU; ours must beat naive everywhere.

use fluo::models::matrix::{shared_bispectral_files, MatrixModel};
use fluo::reports::reduction::{table1, Table1Row, TABLE1_ILLUMINANTS, TABLE1_XYZU_OURS};
use fluo::Bispectral;

/// Table 1 over the shared measured matrices (None, said on stderr, without them).
fn shared_rows() -> Option<Vec<Table1Row>> {
    let files = shared_bispectral_files();
    if files.is_empty() {
        eprintln!("skipping: ../shared/data/bispectral not found (set FLUO_SHARED_DATA)");
        return None;
    }
    let models: Vec<MatrixModel> = files.iter().map(|f| MatrixModel::from_file(f).unwrap()).collect();
    let refs: Vec<&dyn Bispectral> = models.iter().map(|m| m as &dyn Bispectral).collect();
    Some(table1(&refs).unwrap())
}

/// The tolerance per illuminant.
const PER_ILLUMINANT_TOLERANCE: f64 = 0.5;

#[test]
fn table1_matches_the_paper_on_the_measured_materials() {
    let Some(rows) = shared_rows() else {
        return;
    };
    let row = |m: &str, b: &str| rows.iter().find(|r| r.method == m && r.basis == b).unwrap();
    let ours = row("ours", "xyzu");
    for (j, name) in TABLE1_ILLUMINANTS.iter().enumerate() {
        let (got, paper) = (ours.mean[j], TABLE1_XYZU_OURS[j]);
        assert!((got - paper).abs() <= PER_ILLUMINANT_TOLERANCE, "{name}: ours-xyzu {got:.3} vs paper {paper}");
    }
    let paper_mean = TABLE1_XYZU_OURS.iter().sum::<f64>() / 7.0;
    assert!(ours.overall <= paper_mean + 5e-3, "mean {:.3} vs paper {paper_mean:.3}", ours.overall);
    assert!(row("ours", "x7").overall < ours.overall, "x7 {} vs xyzu {}", row("ours", "x7").overall, ours.overall);
    for b in ["xyz", "xyzu", "x7"] {
        for (j, light) in TABLE1_ILLUMINANTS.iter().enumerate() {
            assert!(row("ours", b).mean[j] < row("naive", b).mean[j], "{b} {light}");
        }
    }
}

/// How close the naive rows' mean over the seven illuminants must come to the paper's:
/// the paper averages over its whole database, we over the shared materials, so single
/// illuminants differ by up to ~4.5 ΔE00 (A) while the means agree to ~0.2–1.2
/// (naive-xyz 11.54 vs 11.69, naive-xyzu 11.89 vs 12.36). The L² norm on both sides
/// (before) gave 15–19, the area norm on both sides ~75.
const NAIVE_TOLERANCE: f64 = 1.0;

#[test]
fn naive_rows_follow_eq_7_as_the_paper_computed_them() {
    use fluo::reports::reduction::{TABLE1_XYZU_NAIVE, TABLE1_XYZ_NAIVE};
    let Some(rows) = shared_rows() else {
        return;
    };
    for (basis, paper) in [("xyz", TABLE1_XYZ_NAIVE), ("xyzu", TABLE1_XYZU_NAIVE)] {
        let got = &rows.iter().find(|r| r.method == "naive" && r.basis == basis).unwrap().mean;
        eprintln!("naive-{basis}: ours {got:.2?} paper {paper:?}");
        let mean_got = got.iter().sum::<f64>() / 7.0;
        let mean_paper = paper.iter().sum::<f64>() / 7.0;
        assert!(
            (mean_got - mean_paper).abs() <= NAIVE_TOLERANCE,
            "naive-{basis}: mean {mean_got:.2} vs {mean_paper:.2}"
        );
    }
}
