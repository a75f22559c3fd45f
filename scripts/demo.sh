#!/usr/bin/env bash
# Set up everything (scripts/setup.sh), then render every scenes/*.xml with fluo_path in
# scalar_spectral and scalar_rgb, and without fluorescence, into out/ (EXR + PNG), and
# write the gallery: out/gallery.png (one row per scene: spectral | reduced RGB |
# without fluorescence | CIEDE2000 map, with render times) and out/index.html.
# Extra args go to `fluo demo` (e.g. --spp 16 --res 128; --readme also refreshes
# docs/gallery.png, the copy README.md shows).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

bash scripts/setup.sh
.venv/bin/fluo demo --out "$PWD/out" "$@"
echo "[demo] gallery: $PWD/out/gallery.png (open $PWD/out/index.html for the full-size images)"
echo "[demo] per-render images: $PWD/out/<scene>_<variant>.exr and .png"
