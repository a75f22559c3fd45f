//! `fluo-rs`: the physics half of the `fluo` command line.
//!
//! The Python `fluo` command forwards every subcommand it does not handle itself
//! (`render`, `demo`) to this tool. Each subcommand prints exactly one JSON object on
//! stdout with `--json` (a readable summary otherwise); errors go to stderr with a
//! non-zero exit status.

use std::collections::BTreeMap;
use std::process::ExitCode;

use fluo::colour::RgbSpace;
use fluo::colour::{ciede2000, xyz_to_lab};
use fluo::model::load_material;
use fluo::models::gmm::{fit, FitOptions, Scaling};
use fluo::models::jung::{JungFluorescence, JungMaterial, JungParams, Reflectance};
use fluo::models::matrix::{load_matrix, shared_bispectral_files, Filtered};
use fluo::patch::patch_xyz;
use fluo::reduce::{reduce, reduced_patch_xyz, spectral_patch_xyz, Basis, BasisKind, Method, Operator};
use fluo::reports::gmm::{report, ACCEPTANCE_COMPONENTS, ACCEPTANCE_DELTA_E, COMPONENT_COUNTS};
use fluo::spectrum::{cmf, illuminant, IrregularSpectrum, Observer, Spectral};
use fluo::upsample::{generate_cube, space_name, Cube, CubeSettings, Lookup, Reconstruction, REMAINING_ERROR};
use fluo::Bispectral;
use serde_json::{json, Value};

const HELP: &str = r#"
fluo-rs: physics subcommands of the fluo command line

USAGE:
    fluo-rs <SUBCOMMAND> [OPTIONS] [--json]

SUBCOMMANDS:
    jung     Derived quantities of a fluo_jung material
             --emission-peak NM --stokes-shift NM --concentration C --quantum-yield Q

    qd       Quantum-dot band of a fluo_qd coating (Brus equation, Stokes shift)
             --radius NM --width NM, and optionally any Table 1 constant in SI units:
             --gap-energy --elementary-charge --planck --light-speed --boltzmann
             --electron-mass --hole-mass --vacuum-permittivity
             --relative-permittivity --temperature
             Keys: lambda_qd_nm, stokes_shift_nm, emission_peak_nm, and the size and
             build time of the material's precomputed tables.

    qd-medium  Absorption and emission of a fluo_qd_medium (dots in a host)
             --radius NM --width NM --quantum-yield Q --concentration UMOL_PER_L
             --ext-ior N --step NM (output grid over [300, 830] nm, default 1)
             Keys: wavelengths_nm, absorption_per_m (μa, 1/m), emission_per_nm
             (re-emitted per nm per unit absorbed power, before the no-anti-Stokes
             cut), lambda_qd_nm, emission_peak_nm, lambda_min_nm, lambda_max_nm.

    dye-medium Absorption and emission of a fluo_dye_medium (Jung et al.'s dye spectra)
             --emission-peak NM --stokes-shift NM --quantum-yield Q --sigma-a PER_M
             --step NM; keys as qd-medium (over the dye's absorption and emission support).

    patch    XYZ of a flat patch under a light, by direct single-bounce integration
             --material M     material JSON (inline or a .json file), e.g.
                              '{"model":"jung","emission_peak":520,"concentration":0.8}'
             --illuminant I   CIE name (A, D50..D75, E, FL1..FL12, HP1..HP5) or a
                              nm,value CSV file
             --method spectral (default) | ours-xyz | ours-xyzu | ours-x7 |
                      naive-xyz | naive-xyzu | naive-x7
                      reduced methods (Fichet et al. 2024) also print delta_e2000
                      against the spectral result on the reduction grid
                      (300-830 nm, 1 nm; reference white: the illuminant)
             --cmf cie2006|cie1931   observer (default cie2006)
             Conventions: λo over the observer's 1 nm grid, λi over the
             illuminant's domain; light from the normal, viewed from the normal;
             normalised so that the perfect white diffuser has Y = 1.

    memory   Bytes a material occupies at render time: --material M (JSON, matrix, fit)
    diagonal The elastic reflectance (diagonal) of a matrix file: --material FILE
    reduce-report  Fichet et al.'s Table 1 on measured matrices (default: all of
             ../shared/data/bispectral): mean ΔE2000 per illuminant (A, E, D60, D65,
             FL1, FL2, HP5) for naive/ours x xyz/xyzu/x7 with the paper's rows
             beside ours, then the saturated-report table.
    saturated-report  Saturated fluorescence (pure green and red emitters, a UV
             brightener) under D65, A and FL2 through reduced RGB transport as
             fluo_path renders it in scalar_rgb, per basis (rgb, xyzu, x7): the
             luminance ratio to the spectral patch and ΔE2000.
    reduce   The K x K reduced reradiation matrix of a material
             --material M (as for patch)  --basis xyz|xyzu|x7  --method ours|naive
             --cmf cie2006|cie1931 (default cie2006)
             The matrix acts on basis coefficients c_k = ∫ L s_k dλ: c_o = M c_i;
             XYZ = T c (T printed too).
    upsample-cube    Generate an RGB -> (reflectance + fluorescence) coefficient cube
             (Jung et al. 2019, sec. 3.4)
             --space srgb|rec2020|acescg   --res N (default 33)
             --threshold inf|T   smoothness threshold, nm^-1 (paper: inf or 0.016)
             --illuminant NAME   (default D65)   --rounds R (default 12)
             --threads N (default: all cores; the cube does not depend on it)
             -o FILE             output (binary, header documented in core/src/upsample/)

    upsample-lookup  Coefficients of one colour and the colour they reproduce
             --rgb R,G,B   --cube FILE | --space S (the shipped cube)
             --lookup nearest|trilinear (default nearest)  --fluorescence true|false

    upsample-report  HSV test card (hue x saturation at value 1) through cubes
             --cube FILE   (repeatable; default: the shipped data/cubes/*.cube)
             --card N      card size N x N (default 64)
             RMSE of the reconstructed RGB with and without fluorescence, for
             nearest / trilinear-coefficient / spectral (reflectivity) interpolation,
             and the fraction of entries with remaining error > 1e-3.
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
    /// Values of the repeatable `--cube` option, in order.
    multi: Vec<String>,
    json: bool,
    positional: Vec<String>,
}

/// What an option takes; clap validates it before any subcommand runs.
#[derive(Clone, Copy)]
enum Kind {
    /// A finite number.
    Num,
    /// A whole number in [1, MAX_COUNT].
    Count,
    /// Text (a name, a file, a list), checked by the subcommand.
    Text,
}

/// Largest value of a whole-number option (`--threads`, `--res`, `--components`, ...):
/// each subcommand applies its own, smaller, range on top.
const MAX_COUNT: u64 = 1 << 20;

const QD_CONSTANTS: [&str; 10] = [
    "gap-energy",
    "elementary-charge",
    "planck",
    "light-speed",
    "boltzmann",
    "electron-mass",
    "hole-mass",
    "vacuum-permittivity",
    "relative-permittivity",
    "temperature",
];

/// Every subcommand: name, summary, options (long name, kind), and the name of its
/// positional file arguments (none: positionals are refused).
/// One subcommand: name, summary, options, positional files' name.
type Subcommand = (&'static str, &'static str, Vec<(&'static str, Kind)>, Option<&'static str>);

fn subcommands() -> Vec<Subcommand> {
    use Kind::*;
    let jung = vec![("emission-peak", Num), ("stokes-shift", Num), ("concentration", Num), ("quantum-yield", Num)];
    let mut qd = vec![("radius", Num), ("width", Num), ("table-cos-nodes", Count), ("table-step", Num)];
    qd.extend(QD_CONSTANTS.iter().map(|k| (*k, Num)));
    let mut export = jung.clone();
    export.extend([("reflectance", Num), ("output", Text)]);
    vec![
        ("jung", "Derived quantities of a fluo_jung material", jung, None),
        ("qd", "Quantum-dot band of a fluo_qd coating (Brus equation, Stokes shift)", qd, None),
        (
            "dye-medium",
            "Absorption and emission of a fluo_dye_medium (Jung et al.'s dye spectra)",
            vec![
                ("emission-peak", Num),
                ("stokes-shift", Num),
                ("quantum-yield", Num),
                ("sigma-a", Num),
                ("step", Num),
            ],
            None,
        ),
        (
            "qd-medium",
            "Absorption and emission of a fluo_qd_medium (dots in a host)",
            vec![
                ("radius", Num),
                ("width", Num),
                ("quantum-yield", Num),
                ("concentration", Num),
                ("ext-ior", Num),
                ("step", Num),
            ],
            None,
        ),
        (
            "patch",
            "XYZ of a flat patch under a light, by direct single-bounce integration",
            vec![("material", Text), ("illuminant", Text), ("method", Text), ("cmf", Text)],
            None,
        ),
        ("memory", "Bytes a material occupies at render time", vec![("material", Text)], None),
        ("diagonal", "The elastic reflectance (diagonal) of a matrix file", vec![("material", Text)], None),
        ("reduce-report", "Fichet et al.'s Table 1 on measured matrices", vec![], Some("FILES")),
        ("saturated-report", "Saturated fluorescence through reduced RGB transport, per basis", vec![], None),
        (
            "reduce",
            "The K x K reduced reradiation matrix of a material",
            vec![("material", Text), ("matrix", Text), ("basis", Text), ("method", Text), ("cmf", Text)],
            None,
        ),
        (
            "upsample-cube",
            "Generate an RGB -> (reflectance + fluorescence) coefficient cube",
            vec![
                ("space", Text),
                ("res", Count),
                ("threshold", Text),
                ("illuminant", Text),
                ("rounds", Count),
                ("threads", Count),
                ("output", Text),
            ],
            None,
        ),
        (
            "upsample-lookup",
            "Coefficients of one colour and the colour they reproduce",
            vec![("rgb", Text), ("cube", Text), ("space", Text), ("lookup", Text), ("fluorescence", Text)],
            None,
        ),
        ("upsample-report", "HSV test card through coefficient cubes", vec![("cube", Text), ("card", Count)], None),
        (
            "fit-gmm",
            "Fit a Gaussian mixture to a measured reradiation matrix (Hua et al. 2022)",
            vec![
                ("components", Count),
                ("scaling", Text),
                ("seed", Text),
                ("restarts", Count),
                ("max-iterations", Count),
                ("output", Text),
            ],
            Some("MATRIX"),
        ),
        ("gmm-report", "ΔE2000 of fits against their tabulated matrices", vec![("components", Text)], Some("FILES")),
        ("export-matrix", "Write a fluo_jung material as a reradiation matrix CSV", export, None),
    ]
}

/// The clap command line: every subcommand with exactly its options, `--json`,
/// `--help` and `--version`; unknown options, missing values and malformed numbers
/// are usage errors (exit status 2) before anything runs.
fn command() -> clap::Command {
    use clap::{value_parser, Arg, ArgAction, Command};
    let mut root = Command::new("fluo-rs")
        .version(env!("CARGO_PKG_VERSION"))
        .about("Physics subcommands of the fluo command line")
        .after_long_help(HELP)
        .subcommand_required(true)
        .arg_required_else_help(true);
    for (name, about, options, positional) in subcommands() {
        let mut sub = Command::new(name)
            .about(about)
            .args_override_self(true)
            .arg(Arg::new("json").long("json").action(ArgAction::SetTrue).help("print one JSON object on stdout"));
        for (long, kind) in options {
            let value_name: &'static str = Box::leak(long.to_uppercase().into_boxed_str());
            let mut arg = Arg::new(long).long(long).value_name(value_name);
            if long == "output" {
                arg = arg.short('o');
            }
            arg = match kind {
                // Negative numbers are values (then refused by the model naming the
                // parameter and its valid range), not unknown flags.
                Kind::Num => arg.allow_negative_numbers(true).value_parser(|s: &str| -> Result<f64, String> {
                    match s.trim().parse::<f64>() {
                        Ok(v) if v.is_finite() => Ok(v),
                        _ => Err(format!("\"{}\" is not a finite number", fluo::shown(&s))),
                    }
                }),
                Kind::Count => arg.value_parser(value_parser!(u64).range(1..=MAX_COUNT)),
                Kind::Text => arg,
            };
            if long == "cube" {
                arg = arg.action(ArgAction::Append);
            }
            sub = sub.arg(arg);
        }
        if let Some(p) = positional {
            sub = sub.arg(Arg::new("positional").value_name(p).num_args(0..).action(ArgAction::Append));
        }
        root = root.subcommand(sub);
    }
    root
}

/// Parse the command line (clap exits with usage on errors, `--help`, `--version`).
fn parse_args(argv: &[String]) -> (String, Args) {
    let matches = command().get_matches_from(std::iter::once("fluo-rs".to_string()).chain(argv.iter().cloned()));
    let (name, sub) = matches.subcommand().expect("subcommand_required");
    let mut values = BTreeMap::new();
    let mut multi = Vec::new();
    for id in sub.ids() {
        let key = id.as_str();
        if key == "json" || key == "positional" {
            continue;
        }
        if let Ok(Some(v)) = sub.try_get_one::<f64>(key) {
            values.insert(key.to_string(), v.to_string());
        } else if let Ok(Some(v)) = sub.try_get_one::<u64>(key) {
            values.insert(key.to_string(), v.to_string());
        } else if let Ok(Some(all)) = sub.try_get_many::<String>(key) {
            let all: Vec<String> = all.cloned().collect();
            if key == "cube" {
                multi.extend(all.iter().cloned());
            }
            if let Some(last) = all.last() {
                values.insert(key.to_string(), last.clone());
            }
        }
    }
    let positional = sub.get_many::<String>("positional").map(|v| v.cloned().collect()).unwrap_or_default();
    (name.to_string(), Args { values, multi, json: sub.get_flag("json"), positional })
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

fn cmd_qd(args: &Args) -> Result<Value, String> {
    use fluo::models::qd::{QdBand, QdConstants, QdIndex, QdModel, QdParams, Substrate};
    let d = QdParams::default();
    let mut c = QdConstants::default();
    let fields: [(&str, &mut f64); 10] = [
        ("gap-energy", &mut c.gap_energy),
        ("elementary-charge", &mut c.elementary_charge),
        ("planck", &mut c.planck),
        ("light-speed", &mut c.light_speed),
        ("boltzmann", &mut c.boltzmann),
        ("electron-mass", &mut c.electron_mass),
        ("hole-mass", &mut c.hole_mass),
        ("vacuum-permittivity", &mut c.vacuum_permittivity),
        ("relative-permittivity", &mut c.relative_permittivity),
        ("temperature", &mut c.temperature),
    ];
    for (key, field) in fields {
        *field = args.f64_or(key, *field)?;
    }
    let radius = args.f64_or("radius", d.radius_nm)?;
    let width = args.f64_or("width", d.width_nm)?;
    let cos_nodes = usize_or(args, "table-cos-nodes", d.cos_nodes)?;
    let table_step_nm = args.f64_or("table-step", d.table_step_nm)?;
    let band = QdBand::new(&c, radius, width).map_err(|e| e.to_string())?;
    // Cost of the per-material precomputation (a constant dielectric substrate).
    let t0 = std::time::Instant::now();
    let model = QdModel::new(
        QdParams { radius_nm: radius, width_nm: width, constants: c, cos_nodes, table_step_nm, ..d },
        QdIndex::CdSe,
        Substrate::Constant { eta: 1.5, k: 0.0 },
    )
    .map_err(|e| e.to_string())?;
    let build_ms = t0.elapsed().as_secs_f64() * 1e3;
    Ok(json!({
        "radius_nm": band.radius_nm,
        "width_nm": band.width_nm,
        "absorption_energy_j": band.absorption_energy_j,
        "lambda_qd_nm": band.lambda_qd_nm,
        "stokes_shift_nm": band.stokes_shift_nm,
        "emission_peak_nm": band.emission_peak_nm,
        "constants": c,
        "tables": {
            "rows_cos_theta": cos_nodes,
            "lambda_nodes": model.table_nodes(),
            "bytes": model.table_bytes(),
            "build_ms": build_ms,
        },
    }))
}

fn cmd_qd_medium(args: &Args) -> Result<Value, String> {
    use fluo::models::qd::{QdMedium, QdMediumParams};
    let d = QdMediumParams::default();
    let params = QdMediumParams {
        radius_nm: args.f64_or("radius", d.radius_nm)?,
        width_nm: args.f64_or("width", d.width_nm)?,
        quantum_yield: args.f64_or("quantum-yield", d.quantum_yield)?,
        concentration_um: args.f64_or("concentration", d.concentration_um)?,
        ext_ior: args.f64_or("ext-ior", d.ext_ior)?,
        ..d
    };
    let step = args.f64_or("step", 1.0)?;
    if !(0.01..=100.0).contains(&step) {
        return Err(format!("invalid parameter \"step\" = {step}: valid range is [0.01, 100] nm"));
    }
    let m = QdMedium::new(params).map_err(|e| e.to_string())?;
    let (lo, hi) = m.lambda_range();
    let n = ((hi - lo) / step).round() as usize;
    let grid: Vec<f64> = (0..=n).map(|i| lo + (hi - lo) * i as f64 / n as f64).collect();
    Ok(json!({
        "lambda_qd_nm": m.band().lambda_qd_nm,
        "emission_peak_nm": m.band().emission_peak_nm,
        "lambda_min_nm": lo,
        "lambda_max_nm": hi,
        "wavelengths_nm": grid,
        "absorption_per_m": grid.iter().map(|&l| m.absorption_per_m(l)).collect::<Vec<_>>(),
        "emission_per_nm": grid.iter().map(|&l| m.emission_per_nm(l)).collect::<Vec<_>>(),
        "bytes": m.bytes_at_render_time(),
    }))
}

fn cmd_dye_medium(args: &Args) -> Result<Value, String> {
    use fluo::models::jung::{DyeMedium, DyeMediumParams};
    let d = DyeMediumParams::default();
    let params = DyeMediumParams {
        emission_peak_nm: args.f64_or("emission-peak", d.emission_peak_nm)?,
        stokes_shift_nm: args.f64_or("stokes-shift", d.stokes_shift_nm)?,
        quantum_yield: args.f64_or("quantum-yield", d.quantum_yield)?,
        sigma_a_per_m: args.f64_or("sigma-a", d.sigma_a_per_m)?,
    };
    let step = args.f64_or("step", 1.0)?;
    if !(0.01..=100.0).contains(&step) {
        return Err(format!("invalid parameter \"step\" = {step}: valid range is [0.01, 100] nm"));
    }
    let m = DyeMedium::new(params).map_err(|e| e.to_string())?;
    let (lo, hi) = m.lambda_range();
    let n = ((hi - lo) / step).round().max(1.0) as usize;
    let grid: Vec<f64> = (0..=n).map(|i| lo + (hi - lo) * i as f64 / n as f64).collect();
    Ok(json!({
        "lambda_min_nm": lo,
        "lambda_max_nm": hi,
        "wavelengths_nm": grid,
        "absorption_per_m": grid.iter().map(|&l| m.absorption_per_m(l)).collect::<Vec<_>>(),
        "emission_per_nm": grid.iter().map(|&l| m.emission_per_nm(l)).collect::<Vec<_>>(),
    }))
}

/// `--cmf cie2006|cie1931` (default cie2006): the name and the observer.
fn observer_arg(args: &Args) -> Result<(&str, Observer), String> {
    match args.values.get("cmf").map_or("cie2006", String::as_str) {
        "cie2006" => Ok(("cie2006", Observer::Cie2006)),
        "cie1931" => Ok(("cie1931", Observer::Cie1931)),
        other => Err(format!("--cmf \"{other}\": valid values are cie2006, cie1931")),
    }
}

/// Matrix files named on the command line, or every shared measured file.
fn report_files(args: &Args, command: &str) -> Result<Vec<std::path::PathBuf>, String> {
    if !args.positional.is_empty() {
        return Ok(args.positional.iter().map(std::path::PathBuf::from).collect());
    }
    let files = shared_bispectral_files();
    if files.is_empty() {
        return Err(format!("{command}: no files given and no shared data found (set FLUO_SHARED_DATA)"));
    }
    Ok(files)
}

fn cmd_patch(args: &Args) -> Result<Value, String> {
    let material_arg = args.values.get("material").ok_or("patch needs --material")?;
    let illum_arg = args.values.get("illuminant").ok_or("patch needs --illuminant")?;
    let method = args.values.get("method").map_or("spectral", String::as_str);
    const METHODS: &str = "spectral, ours-xyz, ours-xyzu, ours-x7, naive-xyz, naive-xyzu, naive-x7";
    let reduced = if method == "spectral" {
        None
    } else {
        let (m, b) = method.split_once('-').ok_or(format!("--method \"{method}\": valid methods are {METHODS}"))?;
        let m = Method::from_name(m).map_err(|_| format!("--method \"{method}\": valid methods are {METHODS}"))?;
        let b = BasisKind::from_name(b).map_err(|_| format!("--method \"{method}\": valid methods are {METHODS}"))?;
        Some((m, b))
    };
    let (cmf_name, observer) = observer_arg(args)?;
    let material = load_material(material_arg).map_err(|e| e.to_string())?;
    let spectrum: IrregularSpectrum = if std::path::Path::new(illum_arg).is_file() {
        IrregularSpectrum::from_csv_file(illum_arg).map_err(|e| e.to_string())?
    } else {
        illuminant(illum_arg).map_err(|e| e.to_string())?.into()
    };
    fluo::spectrum::check_lamp(illum_arg, spectrum.wavelengths_nm(), spectrum.values()).map_err(|e| e.to_string())?;
    let w = spectrum.wavelengths_nm();
    let domain = (w[0], w[w.len() - 1]);
    let p = patch_xyz(material.as_ref(), &spectrum, domain, cmf(observer)).map_err(|e| e.to_string())?;
    if let Some((m, kind)) = reduced {
        let basis = Basis::new(kind, observer).map_err(|e| e.to_string())?;
        let illum = |l: f64| if l >= domain.0 && l <= domain.1 { spectrum.eval(l) } else { 0.0 };
        let r = reduce(&Operator::of(material.as_ref()), &basis, m);
        let (xyz, white) = reduced_patch_xyz(&r, &basis, &illum).map_err(|e| e.to_string())?;
        let (sxyz, swhite) =
            spectral_patch_xyz(&Operator::of(material.as_ref()), &basis, &illum).map_err(|e| e.to_string())?;
        let de = ciede2000(xyz_to_lab(xyz, white), xyz_to_lab(sxyz, swhite));
        return Ok(json!({
            "method": method,
            "cmf": cmf_name,
            "illuminant": illum_arg,
            "xyz": xyz,
            "white_xyz": white,
            "spectral_xyz": sxyz,
            "delta_e2000": de,
            "normalisation": p.normalisation.describe(),
            "reduced": "XYZ = T M down[I], normalised as the spectral patch",
        }));
    }
    Ok(json!({
        "method": method,
        "cmf": cmf_name,
        "illuminant": illum_arg,
        "illuminant_domain_nm": [domain.0, domain.1],
        "xyz": p.xyz,
        "white_xyz": p.white_xyz,
        "elastic_xyz": p.elastic_xyz,
        "normalisation": p.normalisation.describe(),
    }))
}

fn cmd_reduce(args: &Args) -> Result<Value, String> {
    let material_arg = args.values.get("material").or(args.values.get("matrix")).ok_or("reduce needs --material")?;
    let kind =
        BasisKind::from_name(args.values.get("basis").map_or("xyzu", String::as_str)).map_err(|e| e.to_string())?;
    let method =
        Method::from_name(args.values.get("method").map_or("ours", String::as_str)).map_err(|e| e.to_string())?;
    let (_, observer) = observer_arg(args)?;
    let material = load_material(material_arg).map_err(|e| e.to_string())?;
    let basis = Basis::new(kind, observer).map_err(|e| e.to_string())?;
    let r = reduce(&Operator::of(material.as_ref()), &basis, method);
    Ok(json!({
        "basis": r.basis,
        "method": r.method,
        "k": basis.len(),
        "matrix": r.matrix,
        "transfer": basis.transfer(),
        "gram_condition_number": basis.condition_number(),
        "acts_on": "basis coefficients c_k = ∫ L(λ) s_k(λ) dλ; c_out = matrix · c_in; XYZ = transferᵀ-columns · c",
    }))
}

/// Bytes a material occupies at render time (model plus sampling tables).
fn cmd_memory(args: &Args) -> Result<Value, String> {
    let m = args.values.get("material").ok_or("memory needs --material")?;
    let lower = m.trim().to_ascii_lowercase();
    let (model, bytes) = if lower.ends_with(".gmm.json") {
        let g = fluo::models::gmm::GmmModel::from_file(m.trim()).map_err(|e| e.to_string())?;
        ("gmm", 8 * g.floats_at_render_time())
    } else if [".bfc", ".csv", ".exr"].iter().any(|e| lower.ends_with(e)) {
        let t = fluo::models::matrix::MatrixModel::from_file(m.trim()).map_err(|e| e.to_string())?;
        ("matrix", 8 * t.floats_at_render_time())
    } else {
        load_material(m).map_err(|e| e.to_string())?;
        // parameters and baked constants of JungFluorescence, plus 3 reflectance coefficients
        ("jung", std::mem::size_of::<JungFluorescence>() + 3 * 8)
    };
    Ok(json!({"model": model, "bytes": bytes}))
}

/// The elastic reflectance (diagonal) of a measured matrix, for non-fluorescent stand-ins.
fn cmd_diagonal(args: &Args) -> Result<Value, String> {
    let m = args.values.get("material").ok_or("diagonal needs --material FILE")?;
    let t = fluo::models::matrix::MatrixModel::from_file(m.trim()).map_err(|e| e.to_string())?;
    let (nm, values) = t.diagonal();
    Ok(json!({"wavelengths_nm": nm, "values": values}))
}

fn cmd_reduce_report(args: &Args) -> Result<Value, String> {
    use fluo::reports::reduction::{
        table1, TABLE1_ILLUMINANTS, TABLE1_XYZU_NAIVE, TABLE1_XYZU_OURS, TABLE1_XYZ_NAIVE, TABLE1_XYZ_OURS,
    };
    let files = report_files(args, "reduce-report")?;
    let models = files
        .iter()
        .map(|f| fluo::models::matrix::MatrixModel::from_file(f).map_err(|e| e.to_string()))
        .collect::<Result<Vec<_>, _>>()?;
    let refs: Vec<&dyn Bispectral> = models.iter().map(|m| m as &dyn Bispectral).collect();
    let rows = table1(&refs).map_err(|e| e.to_string())?;
    let paper = [
        ("naive", "xyz", TABLE1_XYZ_NAIVE),
        ("naive", "xyzu", TABLE1_XYZU_NAIVE),
        ("ours", "xyz", TABLE1_XYZ_OURS),
        ("ours", "xyzu", TABLE1_XYZU_OURS),
    ];
    let saturated = fluo::reports::reduction::saturated_report().map_err(|e| e.to_string())?;
    if !args.json {
        eprintln!(
            "Fichet et al. Table 1 (mean ΔE2000 over {} materials, CIE 2006, white = illuminant; \
             paper: their database)",
            files.len()
        );
        eprintln!("{:<18} {}  {:>6}", "method", TABLE1_ILLUMINANTS.map(|n| format!("{n:>6}")).join(" "), "mean");
        let line = |label: String, values: &[f64]| {
            let cells: Vec<String> = values.iter().map(|v| format!("{v:>6.2}")).collect();
            let mean = values.iter().sum::<f64>() / values.len().max(1) as f64;
            eprintln!("{label:<18} {}  {mean:>6.2}", cells.join(" "));
        };
        for r in &rows {
            line(format!("{}-{}", r.method, r.basis), &r.mean);
            if let Some((_, _, p)) = paper.iter().find(|(m, b, _)| *m == r.method && *b == r.basis) {
                line(format!("  paper {}-{}", r.method, r.basis), p);
            }
        }
        eprintln!();
        print_saturated(&saturated);
    }
    Ok(json!({
        "files": files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>(),
        "illuminants": TABLE1_ILLUMINANTS,
        "rows": rows,
        "paper": paper.iter().map(|(m, b, p)| json!({"method": m, "basis": b, "mean": p})).collect::<Vec<_>>(),
        "saturated": saturated,
    }))
}

fn print_saturated(rows: &[fluo::reports::reduction::SaturatedRow]) {
    eprintln!("Saturated fluorescence through reduced RGB transport (fluo_path, scalar_rgb, method ours):");
    eprintln!(
        "per basis: luminance reduced/spectral of the patch, of its reradiated light alone (1 is exact), \
         and ΔE2000 of the patch (white = illuminant; UV365: equal-energy light of its power); \
         - where the spectral patch is black"
    );
    eprintln!("{:<15} {:<5} {:>15} {:>15} {:>15} {:>15}", "material", "light", "rgb", "xyzu", "x7", "auto");
    let mut seen: Vec<(&str, &str)> = Vec::new();
    for r in rows {
        if seen.contains(&(r.case, r.illuminant)) {
            continue;
        }
        seen.push((r.case, r.illuminant));
        let cell = |b: &str| {
            rows.iter()
                .find(|x| x.case == r.case && x.illuminant == r.illuminant && x.basis == b)
                .map(|x| {
                    let r = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2}"));
                    format!("{} {} {:.1}", r(x.luminance_ratio), r(x.fluorescence_ratio), x.delta_e)
                })
                .unwrap_or_default()
        };
        eprintln!(
            "{:<15} {:<5} {:>15} {:>15} {:>15} {:>15}",
            r.case,
            r.illuminant,
            cell("rgb"),
            cell("xyzu"),
            cell("x7"),
            cell("auto")
        );
    }
}

fn cmd_saturated_report(args: &Args) -> Result<Value, String> {
    let rows = fluo::reports::reduction::saturated_report().map_err(|e| e.to_string())?;
    if !args.json {
        print_saturated(&rows);
    }
    Ok(json!({ "saturated": rows }))
}

// ------------------------------------------------------------------ upsampling

fn parse_threshold(text: &str) -> Result<f64, String> {
    match text.trim().to_ascii_lowercase().as_str() {
        "inf" | "infinity" | "∞" => Ok(f64::INFINITY),
        t => t.parse::<f64>().map_err(|_| format!("--threshold \"{text}\" is not a number or \"inf\"")),
    }
}

fn cmd_upsample_cube(args: &Args) -> Result<Value, String> {
    let space = RgbSpace::from_name(args.values.get("space").ok_or("upsample-cube needs --space")?)
        .map_err(|e| e.to_string())?;
    let output = args.values.get("output").ok_or("upsample-cube needs -o FILE")?;
    let res = args.f64_or("res", 33.0)?;
    if !(res.fract() == 0.0 && res >= 2.0) {
        return Err(format!("--res {res}: must be a whole number >= 2"));
    }
    let threads_default = std::thread::available_parallelism().map_or(1, |n| n.get()) as f64;
    let settings = CubeSettings {
        space,
        illuminant: args.values.get("illuminant").cloned().unwrap_or_else(|| "D65".into()),
        resolution: res as usize,
        threshold: parse_threshold(args.values.get("threshold").map_or("inf", String::as_str))?,
        rounds: args.f64_or("rounds", 12.0)? as usize,
        threads: args.f64_or("threads", threads_default)?.max(1.0) as usize,
    };
    let start = std::time::Instant::now();
    let (cube, stats) =
        generate_cube(&settings, &mut |line| eprintln!("upsample-cube: {line}")).map_err(|e| e.to_string())?;
    let seconds = start.elapsed().as_secs_f64();
    cube.save(std::path::Path::new(output)).map_err(|e| e.to_string())?;
    Ok(json!({
        "output": output,
        "header": cube.header.to_string(),
        "entries": cube.entries().len(),
        "seconds": seconds,
        "threads": settings.threads,
        "stats": stats,
    }))
}

fn shipped_cubes() -> Vec<std::path::PathBuf> {
    let dir = fluo::upsample::shipped_cube_dir();
    let mut v: Vec<_> =
        std::fs::read_dir(dir).map(|rd| rd.filter_map(|e| e.ok().map(|e| e.path())).collect()).unwrap_or_default();
    v.retain(|p: &std::path::PathBuf| p.extension().is_some_and(|e| e == "cube"));
    v.sort();
    v
}

fn cmd_upsample_report(args: &Args) -> Result<Value, String> {
    let mut files: Vec<std::path::PathBuf> = args.multi.iter().map(std::path::PathBuf::from).collect();
    if files.is_empty() {
        files = shipped_cubes();
    }
    if files.is_empty() {
        return Err("upsample-report: no --cube given and no data/cubes/*.cube found".into());
    }
    let size = args.f64_or("card", 64.0)?;
    if !(size.fract() == 0.0 && (2.0..=4096.0).contains(&size)) {
        return Err(format!("--card {size}: must be a whole number in [2, 4096]"));
    }
    let size = size as usize;
    let mut reports = Vec::new();
    for f in &files {
        let cube = Cube::load(f).map_err(|e| e.to_string())?;
        let sys = cube.colour_system().map_err(|e| e.to_string())?;
        let mut rmse = serde_json::Map::new();
        for (name, how) in [
            ("nearest", Reconstruction::Coefficients(Lookup::Nearest)),
            ("trilinear", Reconstruction::Coefficients(Lookup::Trilinear)),
            ("spectral", Reconstruction::Spectra),
        ] {
            let with = cube.card_rmse(&sys, size, how, true).map_err(|e| e.to_string())?;
            let without = cube.card_rmse(&sys, size, how, false).map_err(|e| e.to_string())?;
            rmse.insert(
                name.into(),
                json!({"fluorescence": with, "reflectance_only": without, "ratio": without / with}),
            );
        }
        let n = cube.entries().len() as f64;
        let remaining = cube.entries().iter().filter(|e| e.error > REMAINING_ERROR).count();
        let remaining_refl = cube.entries().iter().filter(|e| e.reflectance_only_error > REMAINING_ERROR).count();
        let fluorescent = cube.entries().iter().filter(|e| e.coefficients.concentration > 0.0).count();
        reports.push(json!({
            "cube": f.display().to_string(),
            "space": space_name(cube.header.space),
            "illuminant": cube.header.illuminant,
            "resolution": cube.header.resolution,
            "threshold": if cube.header.threshold.is_finite() { json!(cube.header.threshold) } else { json!("inf") },
            "card": format!("{size}x{size} HSV (hue x saturation, value 1)"),
            "rmse": rmse,
            "fluorescent_entries": fluorescent,
            "fraction_remaining_error": remaining as f64 / n,
            "fraction_remaining_error_reflectance_only": remaining_refl as f64 / n,
            "remaining_error_threshold": REMAINING_ERROR,
        }));
    }
    Ok(json!({ "reports": reports }))
}

fn cmd_upsample_lookup(args: &Args) -> Result<Value, String> {
    let path = match (args.values.get("cube"), args.values.get("space")) {
        (Some(c), _) => std::path::PathBuf::from(c),
        (None, Some(sp)) => {
            let space = RgbSpace::from_name(sp).map_err(|e| e.to_string())?;
            fluo::upsample::shipped_cube_dir().join(format!("{}_d65_tinf_r33.cube", space_name(space)))
        }
        _ => return Err("upsample-lookup needs --cube FILE or --space S".into()),
    };
    let cube = Cube::load(&path).map_err(|e| e.to_string())?;
    let text = args.values.get("rgb").ok_or("upsample-lookup needs --rgb R,G,B")?;
    let v: Vec<f64> = text
        .split(',')
        .map(|t| t.trim().parse::<f64>().map_err(|_| format!("--rgb \"{text}\": not three numbers")))
        .collect::<Result<_, _>>()?;
    let rgb: [f64; 3] = v.try_into().map_err(|_| format!("--rgb \"{text}\": not three numbers"))?;
    let mode =
        Lookup::from_name(args.values.get("lookup").map_or("nearest", String::as_str)).map_err(|e| e.to_string())?;
    let fl = args.values.get("fluorescence").map_or("true", String::as_str) != "false";
    let c = cube.lookup(rgb, mode, fl).map_err(|e| e.to_string())?;
    let sys = cube.colour_system().map_err(|e| e.to_string())?;
    let got = sys.rgb(&c);
    Ok(json!({
        "cube": path.display().to_string(),
        "rgb": rgb,
        "coefficients": c,
        "reproduced_rgb": got,
        "error": ((0..3).map(|k| (got[k] - rgb[k]).powi(2)).sum::<f64>()).sqrt(),
    }))
}

// ------------------------------------------------------------ measured matrices

fn usize_or(args: &Args, key: &str, default: usize) -> Result<usize, String> {
    match args.values.get(key) {
        None => Ok(default),
        Some(v) => v.parse::<usize>().map_err(|_| format!("option --{key} = \"{v}\" is not a whole number")),
    }
}

/// The fit's options from the command line; `components` from `--components` when
/// `single_count` (fit-gmm), else the default (gmm-report's `--components` is a list, read
/// by the report itself: `gmm-report --components 1,2,4,8,16` exited 1 here before).
fn fit_options(args: &Args, single_count: bool) -> Result<FitOptions, String> {
    let d = FitOptions::default();
    Ok(FitOptions {
        components: if single_count { usize_or(args, "components", d.components)? } else { d.components },
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
    let opts = fit_options(args, true)?;
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
    let files = report_files(args, "gmm-report")?;
    let counts: Vec<usize> = match args.values.get("components") {
        None => COMPONENT_COUNTS.to_vec(),
        Some(list) => list
            .split(',')
            .map(|x| {
                x.trim().parse::<usize>().map_err(|_| format!("--components \"{list}\": expected e.g. 1,2,4,8,16"))
            })
            .collect::<Result<_, _>>()?,
    };
    let r = report(&files, &counts, &fit_options(args, false)?).map_err(|e| e.to_string())?;
    let acceptance = r.summary.iter().find(|s| s.components == ACCEPTANCE_COMPONENTS).map(|s| {
        json!({"components": ACCEPTANCE_COMPONENTS, "mean_delta_e_cie": s.mean_delta_e_cie,
               "threshold": ACCEPTANCE_DELTA_E, "pass": s.mean_delta_e_cie <= ACCEPTANCE_DELTA_E})
    });
    if !args.json {
        eprintln!(
            "{:<18} {:>3} {:>10} {:>9} {:>10} {:>9} {:>8} {:>7} {:>10}",
            "material", "K", "ΔE CIE", "max", "ΔE mono", "max", "fit s", "floats", "bytes"
        );
        for m in &r.materials {
            for f in &m.fits {
                eprintln!(
                    "{:<18} {:>3} {:>10.4} {:>9.4} {:>10.4} {:>9.4} {:>8.3} {:>7} {:>10}",
                    m.file,
                    f.components,
                    f.delta_e_cie.mean,
                    f.delta_e_cie.max,
                    f.delta_e_mono.mean,
                    f.delta_e_mono.max,
                    f.fit_seconds,
                    f.floats_stored,
                    f.bytes_at_render_time
                );
            }
            eprintln!(
                "{:<18} matrix: {} floats stored, {} bytes at render time (with CDF tables)",
                m.file, m.matrix_floats_stored, m.matrix_bytes_at_render_time
            );
        }
        for s in &r.summary {
            eprintln!(
                "mean K = {:>2}: ΔE CIE {:.4}, ΔE mono {:.4}, fit {:.3} s, {:.0} bytes (matrix {:.0})",
                s.components,
                s.mean_delta_e_cie,
                s.mean_delta_e_mono,
                s.mean_fit_seconds,
                s.mean_bytes_at_render_time,
                s.matrix_bytes_at_render_time
            );
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
            let v = if (i - o).abs() < 1e-9 { m.elastic_albedo(o) } else { m.fluorescence.reradiation(i, o) * step };
            text.push_str(&format!(",{v:.6e}"));
        }
        text.push('\n');
    }
    std::fs::write(output, text).map_err(|e| format!("{output}: {e}"))?;
    Ok(
        json!({"output": output, "params": p, "reflectance": r, "lambda_i_nm": [300, 780], "lambda_o_nm": [380, 780], "step_nm": step}),
    )
}

fn run(argv: &[String]) -> Result<(), String> {
    let (cmd, args) = parse_args(argv);
    let out = match cmd.as_str() {
        "fit-gmm" => cmd_fit_gmm(&args)?,
        "gmm-report" => cmd_gmm_report(&args)?,
        "export-matrix" => cmd_export_matrix(&args)?,
        "jung" => cmd_jung(&args)?,
        "patch" => cmd_patch(&args)?,
        "reduce" => cmd_reduce(&args)?,
        "reduce-report" => cmd_reduce_report(&args)?,
        "saturated-report" => cmd_saturated_report(&args)?,
        "memory" => cmd_memory(&args)?,
        "diagonal" => cmd_diagonal(&args)?,
        "qd" => cmd_qd(&args)?,
        "qd-medium" => cmd_qd_medium(&args)?,
        "dye-medium" => cmd_dye_medium(&args)?,
        "upsample-cube" => cmd_upsample_cube(&args)?,
        "upsample-report" => cmd_upsample_report(&args)?,
        "upsample-lookup" => cmd_upsample_lookup(&args)?,
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
    // A panic is a bug; still, the user gets one line, not a backtrace.
    std::panic::set_hook(Box::new(|info| {
        eprintln!("fluo-rs: internal error: {info} (please report this)");
    }));
    let argv: Vec<String> = std::env::args().skip(1).collect();
    match run(&argv) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fluo-rs: error: {e}");
            ExitCode::FAILURE
        }
    }
}
