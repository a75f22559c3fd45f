//! The `fluo-rs` command line: a real argument parser (clap) rejects what it does not
//! know, validates numbers before any work starts, and reports errors in one line.

use std::process::Command;

fn run(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_fluo-rs")).args(args).output().expect("run fluo-rs");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn misspelt_and_unknown_flags_are_usage_errors() {
    // Before: exit 0 with the default emission peak (520 nm).
    let (code, stdout, stderr) = run(&["jung", "--emision-peak", "700", "--json"]);
    assert_eq!(code, 2, "{stdout}{stderr}");
    assert!(stderr.contains("--emision-peak") && stderr.contains("Usage"), "{stderr}");
    assert!(stderr.contains("--emission-peak"), "suggests the right flag: {stderr}");
    let (code, _, stderr) = run(&["patch", "--material", "{}", "--frobnicate", "1"]);
    assert_eq!(code, 2, "{stderr}");
    let (code, _, stderr) = run(&["jung", "stray-positional"]);
    assert_eq!(code, 2, "{stderr}");
    let (code, _, stderr) = run(&["no-such-subcommand"]);
    assert_eq!(code, 2, "{stderr}");
}

#[test]
fn numbers_are_validated_before_running() {
    // Before: `--threads 1e30` panicked.
    for (args, flag) in [
        (vec!["upsample-cube", "--space", "srgb", "--threads", "1e30", "-o", "/tmp/x.cube"], "--threads"),
        (vec!["upsample-cube", "--space", "srgb", "--threads", "0", "-o", "/tmp/x.cube"], "--threads"),
        (vec!["jung", "--concentration", "nan"], "--concentration"),
        (vec!["jung", "--emission-peak", "abc"], "--emission-peak"),
        (vec!["qd", "--radius", "inf"], "--radius"),
        (vec!["fit-gmm", "x.bfc", "--components=-3", "-o", "/tmp/x.json"], "--components"),
        (vec!["fit-gmm", "x.bfc", "--components", "0", "-o", "/tmp/x.json"], "--components"),
    ] {
        let (code, _, stderr) = run(&args);
        assert_eq!(code, 2, "{args:?}: {stderr}");
        assert!(stderr.contains(flag) && !stderr.contains("panicked"), "{args:?}: {stderr}");
    }
}

#[test]
fn version_help_and_valid_calls() {
    let (code, stdout, _) = run(&["--version"]);
    assert_eq!(code, 0);
    assert_eq!(stdout.trim(), format!("fluo-rs {}", env!("CARGO_PKG_VERSION")));
    let (code, stdout, _) = run(&["patch", "--help"]);
    assert_eq!(code, 0);
    assert!(stdout.contains("--illuminant") && stdout.contains("--material"));
    let (code, stdout, stderr) = run(&["jung", "--emission-peak", "700", "--stokes-shift", "50", "--json"]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("700"), "{stdout}");
}

#[test]
fn library_errors_are_one_line_with_status_1() {
    let (code, _, stderr) = run(&["jung", "--concentration", "2"]);
    assert_eq!(code, 1);
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(stderr.starts_with("fluo-rs: error:") && stderr.contains("concentration"), "{stderr}");
    let (code, _, stderr) = run(&["patch", "--material", "/dev/zero.bfc", "--illuminant", "D65"]);
    assert_eq!(code, 1, "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
}

#[test]
fn negative_numbers_reach_the_model_and_are_refused_by_name() {
    // Before: `--emission-peak -5` was "unexpected argument '-5'" (a usage error that
    // never named the parameter's range).
    let (code, _, stderr) = run(&["jung", "--emission-peak", "-5"]);
    assert_eq!(code, 1, "{stderr}");
    assert!(stderr.contains("\"emission_peak\" = -5") && stderr.contains("[200, 1200]"), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
}

#[test]
fn saturated_report_compares_every_basis() {
    let (code, stdout, stderr) = run(&["saturated-report", "--json"]);
    assert_eq!(code, 0, "{stderr}");
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let rows = v["saturated"].as_array().unwrap();
    for basis in ["rgb", "xyzu", "x7"] {
        assert!(rows.iter().any(|r| r["basis"] == basis), "{basis}");
    }
    assert!(rows.iter().all(|r| r["delta_e"].as_f64().unwrap().is_finite()));
}

/// An empty `FLUO_CUBE_DIR` counts as unset: the shipped cubes are found from any working
/// directory (before: the empty path resolved against the working directory, and found none).
#[test]
fn empty_cube_dir_means_unset() {
    let out = Command::new(env!("CARGO_BIN_EXE_fluo-rs"))
        .args(["upsample-report", "--card", "2"])
        .env("FLUO_CUBE_DIR", "")
        .current_dir(std::env::temp_dir())
        .output()
        .expect("run fluo-rs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(String::from_utf8_lossy(&out.stdout).contains("acescg"), "{stderr}");
}

/// `gmm-report --components 1,2,...` (the README's command) takes a list; it exited 1
/// with "not a whole number" when the fit options read the same option as one count.
#[test]
fn gmm_report_takes_a_list_of_component_counts() {
    let yellow = concat!(env!("CARGO_MANIFEST_DIR"), "/../data/matrices/jung_yellow.csv");
    let (code, out, err) = run(&["gmm-report", yellow, "--components", "1,2", "--json"]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).expect("one JSON object");
    let text = v.to_string();
    assert!(text.contains("\"components\":1") && text.contains("\"components\":2"), "{text}");
    let (code, _, err) = run(&["gmm-report", yellow, "--components", "1,x"]);
    assert_ne!(code, 0);
    assert!(err.contains("expected e.g. 1,2,4,8,16"), "{err}");
}
