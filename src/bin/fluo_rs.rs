//! `fluo-rs`: the physics half of the `fluo` command line.
//!
//! The Python `fluo` command forwards every subcommand it does not handle itself
//! (`render`, `demo`) to this tool. Each subcommand prints exactly one JSON object on
//! stdout with `--json` (a readable summary otherwise); errors go to stderr with a
//! non-zero exit status.

use std::collections::BTreeMap;
use std::process::ExitCode;

use fluo::jung::{JungFluorescence, JungParams};
use serde_json::{json, Value};

const HELP: &str = "\
fluo-rs: physics subcommands of the fluo command line

USAGE:
    fluo-rs <SUBCOMMAND> [OPTIONS] [--json]

SUBCOMMANDS:
    jung     Derived quantities of a fluo_jung material
             --emission-peak NM --stokes-shift NM --concentration C --quantum-yield Q

OPTIONS:
    --json   print one JSON object on stdout
    --help   this text
";

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
