//! Build script.
//!
//! Generate and compile the C++ side of the cxx bridge (`src/bridge.rs`), then compile
//! the Mitsuba plugin shims (`plugins/*.cpp`, headers in `include/fluo/`) against the
//! headers shipped in the `mitsuba==3.8.0` / `drjit==1.3.1` wheels and link them,
//! whole-archive, into `libfluo_mitsuba.so` (the cdylib only).
//! The wheels are found through a Python interpreter: `$FLUO_PYTHON`, else the
//! project's `.venv/bin/python` (one folder above this crate). Shims are compiled with `-msse4.2`, the wheel's ABI:
//! without it `Spectrum`/`Color` layouts differ and renders come out black; and with
//! [`CXX_FLAGS`] (no strict aliasing, hidden visibility).

use std::env;
use std::path::{Path, PathBuf};
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=src/bridge.rs");
    println!("cargo:rerun-if-env-changed=FLUO_PYTHON");
    println!("cargo:rerun-if-env-changed=FLUO_RPATH");

    cxx_build::bridge("src/bridge.rs")
        .std("c++17")
        .flag_if_supported("-msse4.2")
        .flags(CXX_FLAGS)
        .compile("fluo_bridge");

    build_plugins();
}

/// Flags every C++ translation unit gets besides `-msse4.2`: Dr.Jit's own build
/// requires `-fno-strict-aliasing` (without it a g++ -O2 build crashed inside
/// `ContinuousDistribution` in `scalar_spectral`), and hidden visibility keeps the
/// library's exports to its registration symbols (otherwise ~900 weak template
/// instantiations leak into the dynamic symbol table).
const CXX_FLAGS: [&str; 3] = ["-fno-strict-aliasing", "-fvisibility=hidden", "-fvisibility-inlines-hidden"];

/// Include and library directories of the Mitsuba/Dr.Jit/nanobind wheels.
struct Wheels {
    mitsuba: PathBuf,
    drjit: PathBuf,
    nanobind: PathBuf,
}

fn find_wheels(manifest: &Path) -> Wheels {
    let python = env::var_os("FLUO_PYTHON").map(PathBuf::from).unwrap_or_else(|| manifest.join("../.venv/bin/python"));
    let script = "import importlib.util as u\n\
                  for m in ('mitsuba', 'drjit', 'nanobind'):\n\
                  \x20   s = u.find_spec(m)\n\
                  \x20   print(list(s.submodule_search_locations)[0] if s else '')\n";
    let out = Command::new(&python).arg("-c").arg(script).output().unwrap_or_else(|e| {
        panic!(
            "fluo-mitsuba: cannot run Python at {} ({e}); set FLUO_PYTHON to a Python with \
             mitsuba==3.8.0, drjit==1.3.1 and nanobind installed (scripts/setup.sh does this)",
            python.display()
        )
    });
    let text = String::from_utf8_lossy(&out.stdout);
    let dirs: Vec<PathBuf> = text.lines().map(PathBuf::from).collect();
    if !out.status.success() || dirs.len() != 3 || dirs.iter().any(|d| d.as_os_str().is_empty()) {
        panic!(
            "fluo-mitsuba: {} lacks one of mitsuba, drjit, nanobind (found {:?}; stderr: {})",
            python.display(),
            dirs,
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Wheels { mitsuba: dirs[0].clone(), drjit: dirs[1].clone(), nanobind: dirs[2].clone() }
}

/// Every file's path and content under `dir`, sorted, appended to `out` (the plugin cache key).
fn hash_tree(dir: &Path, out: &mut Vec<u8>) {
    let mut entries: Vec<PathBuf> =
        std::fs::read_dir(dir).map(|rd| rd.filter_map(|e| e.ok().map(|e| e.path())).collect()).unwrap_or_default();
    entries.sort();
    for p in entries {
        let link = std::fs::symlink_metadata(&p).map(|m| m.file_type().is_symlink()).unwrap_or(true);
        if link {
            continue; // cxxbridge/crate/<crate> links back to this crate: its sources are keyed per file
        } else if p.is_dir() {
            hash_tree(&p, out);
        } else if let Ok(bytes) = std::fs::read(&p) {
            out.extend(p.to_string_lossy().bytes());
            out.extend(bytes);
        }
    }
}

fn cpp_sources(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> =
        std::fs::read_dir(dir).map(|rd| rd.filter_map(|e| e.ok().map(|e| e.path())).collect()).unwrap_or_default();
    files.retain(|p| p.extension().is_some_and(|e| e == "cpp"));
    files.sort();
    files
}

fn build_plugins() {
    let manifest = PathBuf::from(env::var("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let out_dir = PathBuf::from(env::var("OUT_DIR").expect("OUT_DIR"));
    let w = find_wheels(&manifest);
    // The wheels may live in a temporary build environment (pip's isolated build puts
    // them on PYTHONPATH): rerun when that changes or the libraries are gone.
    println!("cargo:rerun-if-env-changed=PYTHONPATH");
    println!("cargo:rerun-if-changed={}", w.mitsuba.join("libmitsuba.so").display());
    println!("cargo:rerun-if-changed={}", w.drjit.join("libdrjit-core.so").display());
    for d in ["plugins", "include/fluo"] {
        println!("cargo:rerun-if-changed={d}");
    }

    let sources = cpp_sources(&manifest.join("plugins"));
    for s in &sources {
        println!("cargo:rerun-if-changed={}", s.display());
    }

    let include = [
        manifest.join("include/fluo"),
        out_dir.join("cxxbridge/include"),
        out_dir.join("cxxbridge/crate"),
        w.mitsuba.join("include"),
        w.drjit.join("include"),
        w.nanobind.join("include"),
        w.nanobind.join("ext/robin_map/include"),
    ];
    let build = || {
        let mut b = cc::Build::new();
        b.cpp(true).std("c++17").includes(&include);
        b.flag("-msse4.2").flags(CXX_FLAGS).flag("-fPIC").flag_if_supported("-fno-math-errno");
        b.warnings(false).cargo_metadata(false);
        b
    };
    // Each translation unit's object is cached under a hash of everything it can see (its
    // source, every header of include/fluo and the bridge's generated ones, the include
    // paths): editing one plugin recompiles that one, a header all of them.
    let mut common = Vec::new();
    for dir in [manifest.join("include/fluo"), out_dir.join("cxxbridge")] {
        hash_tree(&dir, &mut common);
    }
    common.extend(format!("{include:?}{CXX_FLAGS:?}").bytes());
    let cache = out_dir.join("plugin-objects");
    std::fs::create_dir_all(&cache).expect("plugin object cache");
    let objects: Vec<PathBuf> = sources
        .iter()
        .map(|s| {
            let mut h = std::collections::hash_map::DefaultHasher::new();
            std::hash::Hash::hash(&common, &mut h);
            std::hash::Hash::hash(&std::fs::read(s).expect("plugin source"), &mut h);
            let stem = s.file_stem().unwrap().to_string_lossy();
            cache.join(format!("{stem}-{:016x}.o", std::hash::Hasher::finish(&h)))
        })
        .collect();
    if let Ok(rd) = std::fs::read_dir(&cache) {
        for old in rd.filter_map(|e| e.ok().map(|e| e.path())) {
            if !objects.contains(&old) {
                let _ = std::fs::remove_file(old); // an earlier version's object
            }
        }
    }
    // The stale ones, largest first, shared out to NUM_JOBS threads as they free up.
    let mut stale: Vec<(&PathBuf, &PathBuf)> = sources.iter().zip(&objects).filter(|(_, o)| !o.exists()).collect();
    stale.sort_by_key(|(s, _)| std::cmp::Reverse(std::fs::metadata(s).map(|m| m.len()).unwrap_or(0)));
    let jobs: usize = env::var("NUM_JOBS").ok().and_then(|j| j.parse().ok()).unwrap_or(2).max(1);
    let next = std::sync::atomic::AtomicUsize::new(0);
    std::thread::scope(|scope| {
        for _ in 0..jobs.min(stale.len()) {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some((src, obj)) = stale.get(i) else { break };
                let built = build().file(src).compile_intermediates();
                std::fs::copy(&built[0], obj).expect("cache a plugin object");
            });
        }
    });
    build().objects(&objects).compile("fluo_plugins");

    // Only the cdylib gets the shims and Mitsuba; the rlib, the tests and the fluo-rs
    // tool stay pure Rust. The bridge and cxx runtime libraries are listed again after
    // the whole-archive shims so their symbols resolve; -z defs turns any missing
    // symbol into a link error instead of a dlopen failure.
    let (m, d) = (w.mitsuba.display(), w.drjit.display());
    for arg in [
        "-Wl,--whole-archive".to_string(),
        out_dir.join("libfluo_plugins.a").display().to_string(),
        "-Wl,--no-whole-archive".to_string(),
        format!("-L{}", out_dir.display()),
        "-lfluo_bridge".to_string(),
        "-lcxxbridge1".to_string(),
        format!("-L{m}"),
        format!("-L{d}"),
        "-lmitsuba".to_string(),
        "-ldrjit-core".to_string(),
        "-ldrjit-extra".to_string(),
        "-lnanothread".to_string(),
        "-lstdc++".to_string(),
        "-Wl,-z,defs".to_string(),
    ] {
        println!("cargo:rustc-link-arg-cdylib={arg}");
    }
    for dir in run_paths(&w) {
        println!("cargo:rustc-link-arg-cdylib=-Wl,-rpath,{dir}");
    }
}

/// Where the installed library finds libmitsuba/libdrjit-*: next to it in a wheel
/// (`site-packages/fluo/libfluo_mitsuba*.so` → `$ORIGIN/../mitsuba`, `$ORIGIN/../drjit`), and,
/// unless `FLUO_RPATH=relative` (the wheel build, whose build environment is temporary),
/// the wheels it was compiled against (the developer build in target/release).
fn run_paths(w: &Wheels) -> Vec<String> {
    let mut dirs = vec!["$ORIGIN/../mitsuba".to_string(), "$ORIGIN/../drjit".to_string()];
    if env::var("FLUO_RPATH").as_deref() != Ok("relative") {
        dirs.push(w.mitsuba.display().to_string());
        dirs.push(w.drjit.display().to_string());
    }
    dirs
}
