//! Fuzzing every file loader with random bytes and mutations of real files.
//!
//! Loaders: Labsphere BFC and CSV reradiation matrices, bispectral OpenEXR, Gaussian-
//! mixture fits (JSON), lamp/spectrum CSVs, coefficient cubes. Seeds are the files
//! the project ships (and the shared measured data when present); mutations replace
//! numeric tokens with hostile values (huge grid sizes, 1e300, NaN, negative, 3e38),
//! flip bytes, truncate and splice. Every input must come back as `Ok` or a clean
//! `Err`: a panic fails the case, and the global allocator below refuses any single
//! allocation over [`MAX_ALLOCATION`] bytes, which aborts the test binary — so a
//! loader that lets a header drive an allocation fails this test instead of passing
//! by luck of overcommit. The case counts keep the whole file to a few seconds.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};

use fluo::models::gmm::{GmmFile, GmmModel};
use fluo::models::matrix::{parse_bfc, parse_csv, read_exr, write_exr, Donaldson};
use fluo::spectrum::{check_lamp, IrregularSpectrum};
use fluo::upsample::Cube;
use proptest::prelude::*;

/// Largest single allocation a loader may make on any input (the largest legitimate
/// one is a 129³ cube, ~85 MB of f64).
const MAX_ALLOCATION: usize = 512 << 20;

struct Capped;

// SAFETY: forwards to the system allocator; refusing (null) is allowed by the contract.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Capped {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() > MAX_ALLOCATION {
            return std::ptr::null_mut();
        }
        System.alloc(layout)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > MAX_ALLOCATION {
            return std::ptr::null_mut();
        }
        System.realloc(ptr, layout, new_size)
    }
}

#[global_allocator]
static ALLOCATOR: Capped = Capped;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn text_seeds(dir: &Path, ext: &str) -> Vec<String> {
    let mut out = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.to_string_lossy().to_ascii_lowercase().ends_with(ext) {
                if let Ok(t) = std::fs::read_to_string(&p) {
                    out.push(t);
                }
            }
        }
    }
    out.sort();
    out
}

/// Values a hostile header or data field may hold.
const HOSTILE: [&str; 14] = [
    "100000",
    "99999999999",
    "1e300",
    "-1e300",
    "3e38",
    "NaN",
    "inf",
    "-1",
    "0",
    "1e-300",
    "4294967297",
    "",
    "18446744073709551616",
    "2.5",
];

/// Replace numeric-looking tokens of `text` (chosen by `picks`) with hostile values.
fn mutate_tokens(text: &str, picks: &[(usize, usize)]) -> String {
    let mut tokens: Vec<String> = Vec::new();
    let mut cur = String::new();
    for ch in text.chars() {
        let part = ch.is_ascii_alphanumeric() || ch == '.' || ch == '-' || ch == '+';
        if part {
            cur.push(ch);
        } else {
            if !cur.is_empty() {
                tokens.push(std::mem::take(&mut cur));
            }
            tokens.push(ch.to_string());
        }
    }
    if !cur.is_empty() {
        tokens.push(cur);
    }
    let numeric: Vec<usize> = (0..tokens.len()).filter(|&i| tokens[i].parse::<f64>().is_ok()).collect();
    if !numeric.is_empty() {
        for &(at, what) in picks {
            // Bias toward the first numbers (headers, sizes) half of the time.
            let idx = if at % 2 == 0 { numeric[(at / 2) % numeric.len().min(40)] } else { numeric[at % numeric.len()] };
            tokens[idx] = HOSTILE[what % HOSTILE.len()].to_string();
        }
    }
    tokens.concat()
}

fn mutate_bytes(bytes: &[u8], flips: &[(usize, u8)], cut: Option<usize>) -> Vec<u8> {
    let mut b = bytes.to_vec();
    if !b.is_empty() {
        for &(at, v) in flips {
            // Half of the flips land in the first 96 bytes (headers).
            let i = if at % 2 == 0 { (at / 2) % b.len().min(96) } else { at % b.len() };
            b[i] = v;
        }
    }
    if let Some(c) = cut {
        b.truncate(c % (b.len() + 1));
    }
    b
}

fn picks() -> impl Strategy<Value = Vec<(usize, usize)>> {
    prop::collection::vec((0usize..10_000, 0usize..HOSTILE.len()), 1..4)
}

fn flips() -> impl Strategy<Value = Vec<(usize, u8)>> {
    prop::collection::vec((0usize..1_000_000, any::<u8>()), 0..12)
}

fn matrix_seeds(ext: &str) -> Vec<String> {
    let mut s = text_seeds(&repo().join("data/matrices"), ext);
    s.extend(text_seeds(&repo().join("../shared/data/bispectral"), ext));
    assert!(!s.is_empty(), "no {ext} seed files");
    s
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1000))]

    #[test]
    fn bfc_never_panics(seed in 0usize..64, p in picks(), cut in prop::option::of(0usize..100_000)) {
        let seeds = {
            let mut s = text_seeds(&repo().join("../shared/data/bispectral"), ".bfc");
            s.push(fluo_tiny_bfc());
            s
        };
        let mut text = mutate_tokens(&seeds[seed % seeds.len()], &p);
        if let Some(c) = cut {
            let c = c % (text.len() + 1);
            if text.is_char_boundary(c) { text.truncate(c); }
        }
        let _ = parse_bfc(&text, "fuzz.bfc");
    }

    #[test]
    fn csv_matrix_never_panics(seed in 0usize..64, p in picks()) {
        let seeds = matrix_seeds(".csv");
        let _ = parse_csv(&mutate_tokens(&seeds[seed % seeds.len()], &p), "fuzz.csv");
    }

    #[test]
    fn gmm_json_never_panics(seed in 0usize..8, p in picks()) {
        let seeds = text_seeds(&repo().join("data/matrices"), ".gmm.json");
        prop_assert!(!seeds.is_empty());
        let text = mutate_tokens(&seeds[seed % seeds.len()], &p);
        if let Ok(file) = serde_json::from_str::<GmmFile>(&text) {
            if let Ok(model) = GmmModel::new(file) {
                // Accepted fits must evaluate finitely.
                for (li, lo) in [(350.0, 450.0), (400.0, 600.0), (500.0, 700.0)] {
                    prop_assert!(model.reradiation(li, lo).is_finite());
                }
            }
        }
    }

    #[test]
    fn lamp_csv_never_panics(seed in 0usize..8, p in picks()) {
        let seeds = ["300,0.5\n365,10\n400,1\n830,0\n".to_string(),
                     std::fs::read_to_string(repo().join("scenes/spectra/uv_lamp_365.csv")).unwrap()];
        let text = mutate_tokens(&seeds[seed % seeds.len()], &p);
        if let Ok(s) = IrregularSpectrum::from_csv_str(&text) {
            if check_lamp("fuzz.csv", s.wavelengths_nm(), s.values()).is_ok() {
                prop_assert!(s.values().iter().all(|v| (*v as f32).is_finite()));
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn cube_never_panics(f in flips(), cut in prop::option::of(0usize..2_000_000)) {
        let bytes = std::fs::read(repo().join("data/cubes/srgb_d65_tinf_r33.cube")).unwrap();
        let _ = Cube::from_bytes(&mutate_bytes(&bytes, &f, cut), "fuzz.cube");
    }

    #[test]
    fn exr_never_panics(f in flips(), cut in prop::option::of(0usize..20_000)) {
        let dir = std::env::temp_dir().join(format!("fluo-fuzz-exr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let src = dir.join("seed.exr");
        if !src.exists() {
            let d = Donaldson::new("seed", vec![400.0, 450.0, 500.0], vec![400.0, 450.0, 500.0],
                                   vec![0.5, 0.0, 0.0, 0.1, 0.6, 0.0, 0.05, 0.1, 0.7]).unwrap();
            write_exr(&d, &src).unwrap();
        }
        let bytes = std::fs::read(&src).unwrap();
        let case = dir.join(format!("case-{}.exr", std::thread::current().name().unwrap_or("t").len()));
        std::fs::write(&case, mutate_bytes(&bytes, &f, cut)).unwrap();
        let _ = read_exr(&case);
    }
}

fn fluo_tiny_bfc() -> String {
    let mut s = String::from("Labsphere\nBFC-450 Matrix File\n");
    for _ in 0..8 {
        s.push_str("; comment\n");
    }
    s.push_str("340 380 20 3 340 20\nr:c: 340 360 380\n340 0.5 0 0\n360 0.1 0.6 0\n380 0.05 0.1 0.7\nEOD\n");
    s
}
