#!/usr/bin/env bash
# Set up everything on a fresh machine; safe to re-run (each step is skipped or
# incremental when already done):
#   1. .venv with Python >= 3.11,
#   2. the pinned Python dependencies + pytest + this project (editable) into it,
#   3. cargo build --release (the workspace) -> target/release/libfluo_mitsuba.so, fluo-rs,
#   4. LLVM 19 for Dr.Jit's llvm variants (Debian's libllvm19, installed when missing).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

say() { printf '[setup] %s\n' "$*"; }

# 1. Virtual environment.
if [[ ! -x .venv/bin/python ]]; then
    python=${PYTHON:-}
    if [[ -z $python ]]; then
        if command -v python3.11 >/dev/null 2>&1; then python=python3.11; else python=python3; fi
    fi
    if ! "$python" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
        say "error: $python is $("$python" --version 2>&1); Python >= 3.11 is required" >&2
        exit 1
    fi
    say "creating .venv with $("$python" --version 2>&1)"
    "$python" -m venv .venv
fi

# 2. Python packages; the stamp names the pyproject.toml they were installed for.
hash=$(cat pyproject.toml setup.py | sha256sum | cut -c1-16)
stamp=".venv/.fluo-deps-$hash"
if [[ -e $stamp ]]; then
    say "python packages up to date ($stamp)"
else
    say "installing mitsuba==3.8.0, drjit==1.3.1, nanobind, numpy, pytest and fluo (editable) into .venv"
    # FLUO_SKIP_RUST: the editable install carries no compiled parts; step 3 builds them.
    FLUO_SKIP_RUST=1 .venv/bin/python -m pip install --quiet --disable-pip-version-check -e '.[test,build]'
    rm -f .venv/.fluo-deps-*
    touch "$stamp"
fi

# 3. Rust core, C++ shims, plugin library and tool (build.rs finds the wheel's headers
#    through FLUO_PYTHON).
say "cargo build --release"
FLUO_PYTHON="$PWD/.venv/bin/python" cargo build --release

for artefact in target/release/libfluo_mitsuba.so target/release/fluo-rs; do
    if [[ ! -e $artefact ]]; then
        say "error: the build did not produce $artefact" >&2
        exit 1
    fi
done
# 4. Dr.Jit's llvm variants (llvm_ad_rgb, llvm_ad_spectral) load libLLVM at run time.
if [[ -n ${DRJIT_LIBLLVM_PATH:-} ]] || ldconfig -p 2>/dev/null | grep -q 'libLLVM-19\.so\|libLLVM\.so\.19'; then
    say "libLLVM 19 present"
else
    say "installing libllvm19 (apt-get) for the llvm variants"
    sudo_=""
    if (( EUID != 0 )) && command -v sudo >/dev/null 2>&1; then sudo_="sudo"; fi
    if ! { $sudo_ apt-get install -y -q libllvm19 >/dev/null 2>&1 ||
           { $sudo_ apt-get update -q >/dev/null 2>&1 && $sudo_ apt-get install -y -q libllvm19 >/dev/null 2>&1; }; }; then
        say "warning: could not install libllvm19; the llvm variants (and their tests) will fail to start." >&2
        say "         Install LLVM >= 11 and set DRJIT_LIBLLVM_PATH to its libLLVM.so." >&2
    fi
fi
if ! .venv/bin/python -c 'import mitsuba as mi; mi.set_variant("llvm_ad_rgb"); import drjit as dr; dr.eval(dr.arange(mi.Float, 4))' 2>/dev/null; then
    say "warning: Mitsuba's llvm_ad_rgb variant does not start (no usable libLLVM)" >&2
fi

say "ready: $PWD/target/release/libfluo_mitsuba.so, $PWD/target/release/fluo-rs, $PWD/.venv/bin/fluo"
