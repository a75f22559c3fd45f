#!/usr/bin/env bash
# Run all tests: set up (scripts/setup.sh), the format check, clippy and the docs' links
# (warnings are errors), pure-Rust tests (cargo test --release),
# the Python/Mitsuba tests (pytest tests/python; extra args are passed to pytest), then
# the user path: build the wheel and use it from a fresh venv (scripts/wheel_smoke.sh).
# Every suite runs; the exit status is non-zero if any failed, or if pytest collected
# no tests (its status 5).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

bash scripts/setup.sh
# Same environment as the setup build, so cargo does not rerun build.rs needlessly.
export FLUO_PYTHON="$PWD/.venv/bin/python"

failed=()

# Cheap checks first: formatting (rustfmt.toml), then lints as errors.
echo "[test] cargo fmt --all --check"
cargo fmt --all --check || failed+=("cargo fmt --all --check")
echo "[test] cargo clippy --workspace --all-targets -- -D warnings"
cargo clippy --release --workspace --all-targets -- -D warnings || failed+=("cargo clippy")
# Doc links resolve (fluo-mitsuba's docs are for maintainers and link its private items).
echo "[test] cargo doc --workspace --no-deps (warnings are errors)"
RUSTDOCFLAGS="-D warnings -A rustdoc::private_intra_doc_links" cargo doc --release --workspace --no-deps \
    || failed+=("cargo doc")

echo "[test] cargo test --release --workspace"
cargo test --release --workspace || failed+=("cargo test")

echo "[test] pytest tests/python"
status=0
.venv/bin/python -m pytest tests/python -q "$@" || status=$?
if (( status == 5 )); then
    echo "[test] pytest collected no tests" >&2
fi
(( status == 0 )) || failed+=("pytest (exit status $status)")

echo "[test] wheel smoke test (scripts/wheel_smoke.sh)"
bash scripts/wheel_smoke.sh || failed+=("wheel smoke test")

if (( ${#failed[@]} )); then
    echo "[test] FAILED: ${failed[*]}" >&2
    exit 1
fi
echo "[test] all passed"
