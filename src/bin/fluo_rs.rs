//! `fluo-rs`: the physics half of the `fluo` command line.
//!
//! The Python `fluo` command forwards every subcommand it does not handle itself
//! (`render`, `demo`) to this tool. Each subcommand prints exactly one JSON object on
//! stdout with `--json` (a readable summary otherwise); errors go to stderr with a
//! non-zero exit status.

use std::collections::BTreeMap;
use std::process::ExitCode;

use fluo::bispectral::patch_xyz;
use fluo::colour::{ciede2000, xyz_to_lab};
use fluo::reduce::{reduce, reduced_patch_xyz, spectral_patch_xyz, Basis, BasisKind, Method};
use fluo::jung::{JungFluorescence, JungParams};
use fluo::material::load_material;
use fluo::spectrum::{cmf, illuminant, IrregularSpectrum, Observer, Spectral};
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

    reduce   The K x K reduced reradiation matrix of a material
             --material M (as for patch)  --basis xyz|xyzu|x7  --method ours|naive
             --cmf cie2006|cie1931 (default cie2006)
             The matrix acts on basis coefficients c_k = ∫ L s_k dλ: c_o = M c_i;
             XYZ = T c (T printed too).

OPTIONS:
    --json   print one JSON object on stdout
    --help   this text
"#;

/// Parsed `--key value` options and flags.
struct Args {
    values: BTreeMap<String, String>,
    json: bool,
}

fn parse_args(args: &[String]) -> Result<Args, String> {
    let mut values = BTreeMap::new();
    let mut json = false;
    let mut it = args.iter();
    while let Some(a) = it.next() {
        if a == "--json" {
            json = true;
        } else if let Some(key) = a.strip_prefix("--") {
            let v = it.next().ok_or_else(|| format!("option --{key} needs a value"))?;
            values.insert(key.to_string(), v.clone());
        } else {
            return Err(format!("unexpected argument \"{a}\""));
        }
    }
    Ok(Args { values, json })
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
    use fluo::qd::{QdBand, QdConstants, QdIndex, QdModel, QdParams, Substrate, COS_NODES};
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
    let band = QdBand::new(&c, radius, width).map_err(|e| e.to_string())?;
    // Cost of the per-material precomputation (a constant dielectric substrate).
    let t0 = std::time::Instant::now();
    let model = QdModel::new(
        QdParams { radius_nm: radius, width_nm: width, constants: c, ..d },
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
            "rows_cos_theta": COS_NODES,
            "lambda_nodes": model.table_nodes(),
            "bytes": model.table_bytes(),
            "build_ms": build_ms,
        },
    }))
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
    if let Some((m, kind)) = reduced {
        let basis = Basis::new(kind, observer).map_err(|e| e.to_string())?;
        let illum = |l: f64| if l >= domain.0 && l <= domain.1 { spectrum.eval(l) } else { 0.0 };
        let r = reduce(material.as_ref(), &basis, m);
        let (xyz, white) = reduced_patch_xyz(&r, &basis, &illum);
        let (sxyz, swhite) = spectral_patch_xyz(material.as_ref(), &basis, &illum);
        let de = ciede2000(xyz_to_lab(xyz, white), xyz_to_lab(sxyz, swhite));
        return Ok(json!({
            "method": method,
            "cmf": cmf_name,
            "illuminant": illum_arg,
            "xyz": xyz,
            "white_xyz": white,
            "spectral_xyz": sxyz,
            "delta_e2000": de,
            "normalisation": "white Y = 1; reduced: XYZ = T M down[I] / (T down[I])_Y",
        }));
    }
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

fn cmd_reduce(args: &Args) -> Result<Value, String> {
    let material_arg = args.values.get("material").or(args.values.get("matrix")).ok_or("reduce needs --material")?;
    let kind = BasisKind::from_name(args.values.get("basis").map_or("xyzu", String::as_str)).map_err(|e| e.to_string())?;
    let method = Method::from_name(args.values.get("method").map_or("ours", String::as_str)).map_err(|e| e.to_string())?;
    let observer = match args.values.get("cmf").map_or("cie2006", String::as_str) {
        "cie2006" => Observer::Cie2006,
        "cie1931" => Observer::Cie1931,
        other => return Err(format!("--cmf \"{other}\": valid values are cie2006, cie1931")),
    };
    let material = load_material(material_arg).map_err(|e| e.to_string())?;
    let basis = Basis::new(kind, observer).map_err(|e| e.to_string())?;
    let r = reduce(material.as_ref(), &basis, method);
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
    let out = match cmd.as_str() {
        "jung" => cmd_jung(&args)?,
        "patch" => cmd_patch(&args)?,
        "reduce" => cmd_reduce(&args)?,
        "qd" => cmd_qd(&args)?,
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
