//! `fluo-rs`: the physics half of the `fluo` command line.
//!
//! The Python `fluo` command forwards every subcommand it does not handle itself
//! (`render`, `demo`) to this tool. Each subcommand prints exactly one JSON object on
//! stdout with `--json` (a readable summary otherwise); errors go to stderr with a
//! non-zero exit status.

use std::collections::BTreeMap;
use std::process::ExitCode;

use fluo::bispectral::patch_xyz;
use fluo::gmm::{fit, FitOptions, Scaling};
use fluo::gmm_report::{report, ACCEPTANCE_COMPONENTS, ACCEPTANCE_DELTA_E, COMPONENT_COUNTS};
use fluo::matrix::{load_matrix, shared_bispectral_files, Filtered};
use fluo::jung::{JungFluorescence, JungMaterial, JungParams, Reflectance};
use fluo::material::load_material;
use fluo::spectrum::{cmf, illuminant, IrregularSpectrum, Observer};
use serde_json::{json, Value};

const HELP: &str = r#"
fluo-rs: physics subcommands of the fluo command line

USAGE:
    fluo-rs <SUBCOMMAND> [OPTIONS] [--json]

SUBCOMMANDS:
    jung     Derived quantities of a fluo_jung material
             --emission-peak NM --stokes-shift NM --concentration C --quantum-yield Q

    patch    XYZ of a flat patch under a light, by direct single-bounce integration
             --material M     material JSON (inline or a .json file), e.g.
                              '{"model":"jung","emission_peak":520,"concentration":0.8}'
             --illuminant I   CIE name (A, D50..D75, E, FL1..FL12, HP1..HP5) or a
                              nm,value CSV file
             --method spectral   (default; the only method so far)
             --cmf cie2006|cie1931   observer (default cie2006)
             Conventions: λo over the observer's 1 nm grid, λi over the
             illuminant's domain; light from the normal, viewed from the normal;
             normalised so that the perfect white diffuser has Y = 1.

    fit-gmm  Fit a Gaussian mixture to a measured reradiation matrix (Hua et al. 2022)
             fit-gmm X.BFC --components 8 -o X.gmm.json
             X: a .bfc, .csv or .exr matrix; --components K (1..64, default 8);
             --scaling integral_ratio|error_minimisation (S, eqs. 5/4; default
             integral_ratio); --seed N (default 1); --restarts N (default 4);
             --max-iterations N (default 500). Weighted EM, deterministic.

    gmm-report  ΔE2000 of fits against their tabulated matrices, memory, fit time
             gmm-report [FILES...] [--components 1,2,4,8,16]
             Default FILES: every matrix in $FLUO_SHARED_DATA/bispectral (else
             <repo>/../shared/data/bispectral). Lights: the CIE illuminants (patch
             colorimetry, white = the illuminant) and monochromatic 300-780 nm in
             10 nm steps; CIE 1931 observer. Exit status 1 if the 8-component mean
             under the CIE illuminants exceeds 0.3 (the paper's figure).

    export-matrix  Write a fluo_jung material as a reradiation matrix CSV (our own
             demo/test data, data/matrices/): diagonal (1 − c a) r, above it
             c Q a(λi) e(λo) Δλo, on λi 300..780 and λo 380..780 nm (10 nm)
             --emission-peak NM --stokes-shift NM --concentration C
             --quantum-yield Q --reflectance R -o FILE.csv

OPTIONS:
    -o FILE  output file (fit-gmm)
    --json   print one JSON object on stdout
    --help   this text
"#;

/// Parsed `--key value` options, flags and positional arguments.
struct Args {
    values: BTreeMap<String, String>,
    json: bool,
    positional: Vec<String>,
}

fn parse_args(args: &[String]) -> Result<Args, String> {
    let mut values = BTreeMap::new();
    let mut json = false;
    let mut positional = Vec::new();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        if a == "--json" {
            json = true;
        } else if let Some(key) = a.strip_prefix("--").or(if a == "-o" { Some("output") } else { None }) {
            let v = it.next().ok_or_else(|| format!("option --{key} needs a value"))?;
            values.insert(key.to_string(), v.clone());
        } else {
            positional.push(a.clone());
        }
    }
    Ok(Args { values, json, positional })
}

impl Args {
    fn f64_or(&self, key: &str, default: f64) -> Result<f64, String> {
        match self.values.get(key) {
            None => Ok(default),
            Some(v) => v.parse::<f64>().map_err(|_| format!("option --{key} = \"{v}\" is not a number")),
        }
    }
}

fn cmd_jung(args: &Args) -> Result<Value, String> {
    let d = JungParams::default();
    let p = JungParams {
        emission_peak: args.f64_or("emission-peak", d.emission_peak)?,
        stokes_shift: args.f64_or("stokes-shift", d.stokes_shift)?,
        concentration: args.f64_or("concentration", d.concentration)?,
        quantum_yield: args.f64_or("quantum-yield", d.quantum_yield)?,
    };
    let m = JungFluorescence::new(p).map_err(|e| e.to_string())?;
    Ok(json!({
        "params": p,
        "alpha_nm": m.alpha(),
        "absorption_peak_nm": m.absorption_peak(),
        "absorption_support_nm": [m.absorption_support().0, m.absorption_support().1],
        "emission_support_nm": [m.emission_support().0, m.emission_support().1],
        "absorption_integral_nm": m.absorption_integral(),
    }))
}

fn cmd_patch(args: &Args) -> Result<Value, String> {
    let material_arg = args.values.get("material").ok_or("patch needs --material")?;
    let illum_arg = args.values.get("illuminant").ok_or("patch needs --illuminant")?;
    let method = args.values.get("method").map_or("spectral", String::as_str);
    if method != "spectral" {
        return Err(format!("--method \"{method}\": valid methods are: spectral"));
    }
    let cmf_name = args.values.get("cmf").map_or("cie2006", String::as_str);
    let observer = match cmf_name {
        "cie2006" => Observer::Cie2006,
        "cie1931" => Observer::Cie1931,
        other => return Err(format!("--cmf \"{other}\": valid values are cie2006, cie1931")),
    };
    let material = load_material(material_arg).map_err(|e| e.to_string())?;
    let spectrum: IrregularSpectrum = if std::path::Path::new(illum_arg).is_file() {
        IrregularSpectrum::from_csv_file(illum_arg).map_err(|e| e.to_string())?
    } else {
        illuminant(illum_arg).map_err(|e| e.to_string())?.into()
    };
    let w = spectrum.wavelengths_nm();
    let domain = (w[0], w[w.len() - 1]);
    let p = patch_xyz(material.as_ref(), &spectrum, domain, cmf(observer));
    Ok(json!({
        "method": method,
        "cmf": cmf_name,
        "illuminant": illum_arg,
        "illuminant_domain_nm": [domain.0, domain.1],
        "xyz": p.xyz,
        "white_xyz": p.white_xyz,
        "elastic_xyz": p.elastic_xyz,
        "normalisation": "white Y = 1: XYZ = Σ cmf(λo) [ρ(λo) I(λo) + Σ P(λi,λo) I(λi)] / Σ I ȳ",
    }))
}

// ------------------------------------------------------------ measured matrices (issue 5)

fn usize_or(args: &Args, key: &str, default: usize) -> Result<usize, String> {
    match args.values.get(key) {
        None => Ok(default),
        Some(v) => v.parse::<usize>().map_err(|_| format!("option --{key} = \"{v}\" is not a whole number")),
    }
}

fn fit_options(args: &Args) -> Result<FitOptions, String> {
    let d = FitOptions::default();
    Ok(FitOptions {
        components: usize_or(args, "components", d.components)?,
        max_iterations: usize_or(args, "max-iterations", d.max_iterations)?,
        restarts: usize_or(args, "restarts", d.restarts)?,
        seed: usize_or(args, "seed", d.seed as usize)? as u64,
        scaling: match args.values.get("scaling") {
            None => d.scaling,
            Some(s) => Scaling::from_name(s).map_err(|e| e.to_string())?,
        },
        ..d
    })
}

fn cmd_fit_gmm(args: &Args) -> Result<Value, String> {
    let [input] = args.positional.as_slice() else {
        return Err("fit-gmm needs exactly one matrix file: fit-gmm X.BFC --components 8 -o X.gmm.json".into());
    };
    let output = args.values.get("output").ok_or("fit-gmm needs -o OUTPUT.gmm.json")?;
    let opts = fit_options(args)?;
    let filtered = Filtered::new(&load_matrix(input).map_err(|e| e.to_string())?).map_err(|e| e.to_string())?;
    let t0 = std::time::Instant::now();
    let file = fit(&filtered, &opts).map_err(|e| e.to_string())?;
    let seconds = t0.elapsed().as_secs_f64();
    file.save(output).map_err(|e| e.to_string())?;
    Ok(json!({
        "input": input,
        "output": output,
        "components": file.components.len(),
        "scaling": file.scaling,
        "scale": file.scale,
        "scale_integral_ratio": file.scale_integral_ratio,
        "scale_error_minimisation": file.scale_error_minimisation,
        "iterations": file.fit.iterations,
        "converged": file.fit.converged,
        "log_likelihood": file.fit.log_likelihood,
        "floats_stored": file.floats_stored(),
        "fit_seconds": seconds,
    }))
}

fn cmd_gmm_report(args: &Args) -> Result<Value, String> {
    let files: Vec<std::path::PathBuf> = if args.positional.is_empty() {
        let f = shared_bispectral_files();
        if f.is_empty() {
            return Err("gmm-report: no files given and no shared data found (set FLUO_SHARED_DATA)".into());
        }
        f
    } else {
        args.positional.iter().map(std::path::PathBuf::from).collect()
    };
    let counts: Vec<usize> = match args.values.get("components") {
        None => COMPONENT_COUNTS.to_vec(),
        Some(list) => list
            .split(',')
            .map(|x| x.trim().parse::<usize>().map_err(|_| format!("--components \"{list}\": expected e.g. 1,2,4,8,16")))
            .collect::<Result<_, _>>()?,
    };
    let r = report(&files, &counts, &fit_options(args)?).map_err(|e| e.to_string())?;
    let acceptance = r.summary.iter().find(|s| s.components == ACCEPTANCE_COMPONENTS).map(|s| {
        json!({"components": ACCEPTANCE_COMPONENTS, "mean_delta_e_cie": s.mean_delta_e_cie,
               "threshold": ACCEPTANCE_DELTA_E, "pass": s.mean_delta_e_cie <= ACCEPTANCE_DELTA_E})
    });
    if !args.json {
        eprintln!("{:<18} {:>3} {:>10} {:>9} {:>10} {:>9} {:>8} {:>7} {:>10}", "material", "K", "ΔE CIE", "max", "ΔE mono", "max", "fit s", "floats", "bytes");
        for m in &r.materials {
            for f in &m.fits {
                eprintln!(
                    "{:<18} {:>3} {:>10.4} {:>9.4} {:>10.4} {:>9.4} {:>8.3} {:>7} {:>10}",
                    m.file, f.components, f.delta_e_cie.mean, f.delta_e_cie.max, f.delta_e_mono.mean,
                    f.delta_e_mono.max, f.fit_seconds, f.floats_stored, f.bytes_at_render_time
                );
            }
            eprintln!("{:<18} matrix: {} floats stored, {} bytes at render time (with CDF tables)", m.file, m.matrix_floats_stored, m.matrix_bytes_at_render_time);
        }
        for s in &r.summary {
            eprintln!("mean K = {:>2}: ΔE CIE {:.4}, ΔE mono {:.4}, fit {:.3} s, {:.0} bytes (matrix {:.0})",
                s.components, s.mean_delta_e_cie, s.mean_delta_e_mono, s.mean_fit_seconds, s.mean_bytes_at_render_time, s.matrix_bytes_at_render_time);
        }
    }
    let mut out = serde_json::to_value(&r).map_err(|e| e.to_string())?;
    out["acceptance"] = acceptance.clone().unwrap_or(Value::Null);
    if let Some(a) = acceptance {
        if a["pass"] == json!(false) {
            println!("{out}");
            return Err(format!(
                "mean ΔE2000 with {ACCEPTANCE_COMPONENTS} components under the CIE illuminants is {} > {ACCEPTANCE_DELTA_E}",
                a["mean_delta_e_cie"]
            ));
        }
    }
    Ok(out)
}

fn cmd_export_matrix(args: &Args) -> Result<Value, String> {
    let output = args.values.get("output").ok_or("export-matrix needs -o FILE.csv")?;
    let d = JungParams::default();
    let p = JungParams {
        emission_peak: args.f64_or("emission-peak", d.emission_peak)?,
        stokes_shift: args.f64_or("stokes-shift", d.stokes_shift)?,
        concentration: args.f64_or("concentration", d.concentration)?,
        quantum_yield: args.f64_or("quantum-yield", d.quantum_yield)?,
    };
    let r = args.f64_or("reflectance", 0.5)?;
    let m = JungMaterial::new(Reflectance::Constant(r), p).map_err(|e| e.to_string())?;
    let (step, li, lo): (f64, Vec<f64>, Vec<f64>) =
        (10.0, (0..49).map(|k| 300.0 + 10.0 * k as f64).collect(), (0..41).map(|j| 380.0 + 10.0 * j as f64).collect());
    let mut text = format!(
        "# fluo_jung as a reradiation matrix (fluo-rs export-matrix): {}, reflectance {r}\nlambda_o\\lambda_i",
        serde_json::to_string(&p).map_err(|e| e.to_string())?
    );
    for x in &li {
        text.push_str(&format!(",{x}"));
    }
    text.push('\n');
    for &o in &lo {
        text.push_str(&format!("{o}"));
        for &i in &li {
            let v = if (i - o).abs() < 1e-9 {
                m.elastic_albedo(o)
            } else {
                m.fluorescence.reradiation(i, o) * step
            };
            text.push_str(&format!(",{v:.6e}"));
        }
        text.push('\n');
    }
    std::fs::write(output, text).map_err(|e| format!("{output}: {e}"))?;
    Ok(json!({"output": output, "params": p, "reflectance": r, "lambda_i_nm": [300, 780], "lambda_o_nm": [380, 780], "step_nm": step}))
}

fn run(argv: &[String]) -> Result<(), String> {
    let Some(cmd) = argv.first() else {
        print!("{HELP}");
        return Ok(());
    };
    if cmd == "--help" || cmd == "-h" || cmd == "help" {
        print!("{HELP}");
        return Ok(());
    }
    let args = parse_args(&argv[1..])?;
    if let (false, Some(a)) = (matches!(cmd.as_str(), "fit-gmm" | "gmm-report"), args.positional.first()) {
        return Err(format!("unexpected argument \"{a}\""));
    }
    let out = match cmd.as_str() {
        "fit-gmm" => cmd_fit_gmm(&args)?,
        "gmm-report" => cmd_gmm_report(&args)?,
        "export-matrix" => cmd_export_matrix(&args)?,
        "jung" => cmd_jung(&args)?,
        "patch" => cmd_patch(&args)?,
        other => return Err(format!("unknown subcommand \"{other}\" (see fluo-rs --help)")),
    };
    if args.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out).map_err(|e| e.to_string())?);
    }
    Ok(())
}

fn main() -> ExitCode {
    let argv: Vec<String> = std::env::args().skip(1).collect();
    match run(&argv) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fluo-rs: error: {e}");
            ExitCode::FAILURE
        }
    }
}
