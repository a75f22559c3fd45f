//! Malformed and hostile input files: each case asserts the exact outcome (a clean
//! error naming the file and the value, or a finite answer), never an abort, a hang
//! or an unbounded allocation. Cases reproduce reported defects; the random
//! counterpart is `tests/fuzz_loaders.rs`.

use std::path::{Path, PathBuf};

use fluo::models::gmm::{GmmFile, GmmModel};
use fluo::models::jung::{JungMaterial, JungParams, Reflectance};
use fluo::models::matrix::{load_matrix, read_exr, write_exr, Donaldson};
use fluo::patch::{patch_xyz, Normalisation};
use fluo::spectrum::{check_lamp, cmf, IrregularSpectrum, Observer};
use fluo::upsample::Cube;

struct Scratch(PathBuf);

impl Scratch {
    fn new(tag: &str) -> Self {
        let d = std::env::temp_dir().join(format!("fluo-bad-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        Scratch(d)
    }
    fn file(&self, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
        let p = self.0.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn bfc(grid_line: &str, rc_line: &str, rows: &str) -> String {
    let mut s = String::from("Labsphere\nBFC-450 Matrix File\n");
    for _ in 0..8 {
        s.push_str("; comment\n");
    }
    format!("{s}{grid_line}\n{rc_line}\n{rows}EOD\n")
}

fn err(r: Result<impl std::fmt::Debug, fluo::Error>) -> String {
    r.expect_err("must be rejected").to_string()
}

#[test]
fn bfc_header_claiming_a_huge_grid_is_refused_before_allocating() {
    // 100000 excitation wavelengths on line 12 (a ~690 kB file), 100000 emission rows
    // claimed: the old parser reserved 80 GB and aborted the process.
    let rc: String = std::iter::once("r:c:".to_string())
        .chain((0..100_000).map(|i| format!("{}", 300 + i)))
        .collect::<Vec<_>>()
        .join(" ");
    let s = Scratch::new("bfc");
    let p = s.file("huge.bfc", bfc("300 100299 1 100000 300 1", &rc, "300 0.5\n"));
    let e = err(load_matrix(&p));
    assert!(e.contains("huge.bfc") && e.contains("100000 × 100000") && e.contains("cannot hold"), "{e}");
}

#[test]
fn exr_data_window_claiming_a_huge_image_is_refused() {
    let s = Scratch::new("exr");
    let good = s.0.join("good.exr");
    let d = Donaldson::new("t", vec![400.0, 500.0], vec![400.0, 500.0], vec![0.5, 0.0, 0.1, 0.6]).unwrap();
    write_exr(&d, &good).unwrap();
    let mut bytes = std::fs::read(&good).unwrap();
    let key = b"dataWindow\0box2i\0";
    let at = bytes.windows(key.len()).position(|w| w == key).expect("dataWindow attribute") + key.len() + 4;
    for (k, v) in [(8, 99_999i32), (12, 99_999i32)] {
        bytes[at + k..at + k + 4].copy_from_slice(&v.to_le_bytes());
    }
    let p = s.file("huge.exr", &bytes);
    let e = err(read_exr(&p));
    assert!(e.contains("huge.exr") && e.contains("claims"), "{e}");
    assert!(read_exr(&good).is_ok());
}

#[cfg(unix)]
#[test]
fn fifos_and_devices_are_refused_by_every_loader_without_blocking() {
    let s = Scratch::new("fifo");
    for name in ["m.bfc", "m.csv", "m.exr", "fit.gmm.json", "lamp.csv", "c.cube"] {
        let p = s.0.join(name);
        assert!(std::process::Command::new("mkfifo").arg(&p).status().unwrap().success());
    }
    for e in [
        err(load_matrix(s.0.join("m.bfc"))),
        err(load_matrix(s.0.join("m.csv"))),
        err(load_matrix(s.0.join("m.exr"))),
        err(GmmFile::load(s.0.join("fit.gmm.json"))),
        err(IrregularSpectrum::from_csv_file(s.0.join("lamp.csv"))),
        err(Cube::load(&s.0.join("c.cube"))),
        err(IrregularSpectrum::from_csv_file("/dev/zero")),
        err(Cube::load(Path::new("/dev/zero"))),
        err(GmmFile::load("/dev/zero")),
    ] {
        assert!(e.contains("not a regular file"), "{e}");
    }
}

#[test]
fn absurd_values_are_refused_with_file_and_value() {
    let s = Scratch::new("values");
    let p = s.file("big.bfc", bfc("400 500 100 2 400 100", "r:c: 400 500", "400 1e300 0\n500 0.1 0.6\n"));
    let e = err(load_matrix(&p));
    assert!(e.contains("big.bfc") && e.contains("1e300") && e.contains("400 nm"), "{e}");
    let p = s.file("big.csv", "lambda_o\\lambda_i,400,500\n400,0.5,0\n500,1e300,0.6\n");
    let e = err(load_matrix(&p));
    assert!(e.contains("big.csv") && e.contains("1e300"), "{e}");
    // 3e38 is a finite float32: accepted before, it overflowed in the render.
    let d = Donaldson {
        source: "t".into(),
        lambda_i: vec![400.0, 500.0],
        lambda_o: vec![400.0, 500.0],
        values: vec![0.5, 0.0, 3e38, 0.6],
    };
    write_exr(&d, &s.0.join("big.exr")).unwrap();
    let e = err(read_exr(&s.0.join("big.exr")));
    assert!(e.contains("big.exr") && e.contains("3e38"), "{e}");
    // A line of 50 MB is not echoed.
    let p = s.file("long.csv", format!("lambda_o\\lambda_i,400,500\n400,0.5,{}\n", "7".repeat(50 << 20)));
    let e = err(load_matrix(&p));
    assert!(e.len() < 2000 && e.contains("long.csv"), "{} characters", e.len());
}

fn gmm_with(edit: impl Fn(&mut serde_json::Value)) -> Result<GmmModel, fluo::Error> {
    let text =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/matrices/jung_orange.gmm.json"))
            .unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    edit(&mut v);
    GmmModel::new(serde_json::from_value::<GmmFile>(v).unwrap())
}

#[test]
fn gmm_scale_and_covariance_that_overflow_float32_are_refused() {
    assert!(gmm_with(|_| {}).is_ok());
    let e = err(gmm_with(|v| v["scale"] = serde_json::json!(1e300)));
    assert!(e.contains("\"scale\" = 1e300"), "{e}");
    let e = err(gmm_with(|v| v["components"][0]["covariance"] = serde_json::json!([[1e300, 0.0], [0.0, 1e300]])));
    assert!(e.contains("components[0].covariance") && e.contains("1e300"), "{e}");
    let e = err(gmm_with(|v| v["components"][0]["mean"] = serde_json::json!([1e300, 500.0])));
    assert!(e.contains("components[0].mean"), "{e}");
}

#[test]
fn lamps_with_absurd_or_negative_values_are_refused() {
    let e = err(check_lamp("lamp.csv", &[300.0, 400.0], &[1.0, 1e300]));
    assert!(e.contains("lamp.csv") && e.contains("1e300") && e.contains("400 nm"), "{e}");
    let e = err(check_lamp("lamp.csv", &[300.0, 400.0], &[-0.5, 1.0]));
    assert!(e.contains("-0.5") && e.contains("300 nm"), "{e}");
    assert!(check_lamp("lamp.csv", &[300.0, 400.0], &[0.0, 1e6]).is_ok());
}

#[test]
fn patch_under_uv_lamps_is_normalised_by_radiant_power_and_never_negative() {
    let m = JungMaterial::new(
        Reflectance::Constant(0.5),
        JungParams { emission_peak: 450.0, stokes_shift: 80.0, concentration: 0.9, quantum_yield: 1.0 },
    )
    .unwrap();
    let c = cmf(Observer::Cie2006);
    let uv = |hi: f64| IrregularSpectrum::new(vec![300.0, hi], vec![1.0, 1.0]).unwrap();
    // 300–395 nm: was Y = 414 (normalised by the nearly invisible white); 300–370 nm:
    // was [0, 0, 0] (normalised by zero). Now both are per unit radiant power.
    let a = patch_xyz(&m, &uv(395.0), (300.0, 395.0), c).unwrap();
    let b = patch_xyz(&m, &uv(370.0), (300.0, 370.0), c).unwrap();
    for p in [a, b] {
        assert_eq!(p.normalisation, Normalisation::Radiant);
        assert!(p.xyz.iter().all(|v| v.is_finite() && *v >= 0.0), "{:?}", p.xyz);
        assert!(p.xyz[2] > 0.1 && p.xyz[2] < 2.0, "a blue glow of the order of the lamp's power: {:?}", p.xyz);
        assert!((p.white_xyz[1] - 1.0).abs() < 1e-12);
    }
    // Less lamp power below 370 nm, less excitation: the glow scales with the light.
    assert!(b.xyz[2] < a.xyz[2]);
    // A lamp the eye sees keeps the white-Y normalisation.
    let e = IrregularSpectrum::new(vec![300.0, 830.0], vec![1.0, 1.0]).unwrap();
    let p = patch_xyz(&m, &e, (300.0, 830.0), c).unwrap();
    assert_eq!(p.normalisation, Normalisation::WhiteY);
    assert!((p.white_xyz[1] - 1.0).abs() < 1e-12);
    // No power at all: an error, not zeros.
    let dark = IrregularSpectrum::new(vec![300.0, 400.0], vec![0.0, 0.0]).unwrap();
    assert!(err(patch_xyz(&m, &dark, (300.0, 400.0), c)).contains("no power"));
}
