#!/usr/bin/env bash
# Set up everything (scripts/setup.sh), then render every scenes/*.xml in
# scalar_spectral and scalar_rgb into out/ (EXR + PNG). Extra args go to `fluo demo`
# (e.g. --spp 16).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

bash scripts/setup.sh
.venv/bin/fluo demo --out "$PWD/out" "$@"
echo "[demo] images are in $PWD/out/ (<scene>_<variant>.exr and .png)"
