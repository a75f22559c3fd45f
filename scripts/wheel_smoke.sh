#!/usr/bin/env bash
# The user path, checked end to end: build the platform wheel (`pip wheel .`; then
# `auditwheel repair` for the manylinux tag), install
# it (one py3-none wheel) into a fresh virtual environment under every CPython 3.10-3.13 this
# machine has (pyenv's), outside the checkout, and from /tmp, with neither
# cargo nor rustc on PATH, render fluo_path with fluo_jung in both variants (and the polarized one), use the
# shipped cubes and scenes, and run fluo-rs. Called by scripts/test.sh (so by CI).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
say() { printf '[wheel] %s\n' "$*"; }

wheels=out/wheel
rm -f "$wheels"/fluo-*.whl
# setuptools' build/ folder outlives builds: a stale library left there would be packaged.
rm -rf build
say "pip wheel . (setuptools-rust; cargo target folder target/wheel)"
.venv/bin/python -m pip wheel . -w "$wheels" --no-deps --quiet --disable-pip-version-check
raw=$(ls "$wheels"/fluo-*.whl)
say "built $raw ($(du -h "$raw" | cut -f1))"
# The manylinux tag: auditwheel checks the symbol versions the library needs (glibc 2.35,
# GLIBCXX 3.4.29 here) and bundles nothing: Mitsuba's and Dr.Jit's libraries come from
# their own wheels (the run paths point there), the rest is the system's.
say "auditwheel repair (Mitsuba's and Dr.Jit's libraries excluded)"
PATH="$PWD/.venv/bin:$PATH" .venv/bin/auditwheel repair --plat "${FLUO_MANYLINUX:-manylinux_2_35_x86_64}" \
    --exclude libmitsuba.so --exclude libdrjit-core.so --exclude libdrjit-extra.so -w "$wheels" "$raw" >/dev/null
rm -f "$raw"
wheel=$(ls "$wheels"/fluo-*manylinux*.whl)
say "repaired: $wheel"
.venv/bin/python - "$wheel" <<'PY'
import sys, zipfile
libs = [n for n in zipfile.ZipFile(sys.argv[1]).namelist() if n.startswith("fluo/lib") and n.endswith(".so")]
assert libs == ["fluo/libfluo_mitsuba.so"], f"the wheel's plugin libraries: {libs}"
PY

work=$(mktemp -d /tmp/fluo-wheel-XXXXXX)
trap 'rm -rf "$work"' EXIT
cat > "$work/smoke.py" <<'PY'
import shutil, subprocess
for tool in ("cargo", "rustc"):
    assert shutil.which(tool) is None, f"{tool} is on PATH"

import mitsuba as mi
import numpy as np
import fluo

assert not fluo.in_checkout(), fluo.library_path()
assert fluo.library_path().parent.name == "fluo" and "site-packages" in str(fluo.library_path())
print("[wheel] library", fluo.library_path(), "built for", fluo.BUILT_FOR)

def render(variant, concentration, bsdf=None):
    mi.set_variant(variant)
    bsdf = bsdf or {"type": "fluo_jung", "emission_peak": 520.0, "concentration": concentration}
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "fluo_path", "max_depth": 3},
        "sensor": {"type": "perspective",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "light": {"type": "constant", "radiance": {"type": "fluo_illuminant", "illuminant": "D65"}},
        "ball": {"type": "sphere", "bsdf": bsdf}})
    return np.array(mi.render(scene, spp=32, seed=1))

for variant in ("scalar_spectral", "scalar_rgb"):
    dyed, plain = render(variant, 0.9), render(variant, 0.0)
    assert np.isfinite(dyed).all() and dyed.mean() > 0.01, (variant, dyed.mean())
    # The dye moves blue light to green: the centre's green/blue ratio rises.
    c = lambda img: img[6:10, 6:10].reshape(-1, 3).mean(0)
    assert c(dyed)[1] / c(dyed)[2] > 1.2 * c(plain)[1] / c(plain)[2], (variant, c(dyed), c(plain))
    print(f"[wheel] {variant}: fluo_path + fluo_jung renders, centre rgb {c(dyed).round(3)} vs undyed {c(plain).round(3)}")

# The polarized variant: the same scene, intensity equal to the unpolarized render.
pol = render("scalar_spectral_polarized", 0.9)
assert np.allclose(pol, render("scalar_spectral", 0.9), rtol=1e-3, atol=1e-5), "polarized != unpolarized"
print("[wheel] scalar_spectral_polarized: fluo_path + fluo_jung renders as scalar_spectral")

# The shipped cube (package data) through fluo_jung's colour upsampling.
img = render("scalar_rgb", 0.0, {"type": "fluo_jung", "color": {"type": "rgb", "value": [0.9, 0.8, 0.1]}})
assert np.isfinite(img).all() and img.mean() > 0.01
print("[wheel] fluo_jung color upsampling finds", fluo.data_dir("cubes"))

# The physics tool and the shipped scenes through the command line.
out = subprocess.run(["fluo-rs", "--version"], capture_output=True, text=True, check=True).stdout
print("[wheel]", out.strip())
res = fluo.run_tool(["patch", "--material", '{"model":"jung","emission_peak":520,"concentration":0.8}',
                     "--illuminant", "D65"])
assert 0 < res["xyz"][1] < 2, res
scene = fluo.scenes_dir() / "fluo_path_d65.xml"
subprocess.run(["fluo", "render", str(scene), "--variant", "scalar_rgb", "--spp", "4", "-o", "smoke.exr"],
               check=True, capture_output=True)
print("[wheel] fluo render of the shipped", scene.name, "ok")
PY

# One wheel (py3-none-<platform>) for every CPython that Mitsuba 3.8 has wheels for:
# the developer venv's Python and every other 3.10-3.13 this machine has (pyenv's).
base=$(.venv/bin/python -c 'import sys; print(sys._base_executable)')
pythons=("$base")
for v in 3.10 3.12 3.13; do
    found=$(ls -d "${PYENV_ROOT:-$HOME/.pyenv}"/versions/$v.*/bin/python$v 2>/dev/null | sort -V | tail -1 || true)
    [[ -z $found ]] && found=$(command -v "python$v" || true)
    if [[ -n $found && -x $found ]]; then pythons+=("$found"); else say "no Python $v on this machine: skipped"; fi
done
case "$(basename "$wheel")" in
    *-py3-none-manylinux_*) ;;
    *) say "error: $wheel is not tagged py3-none-manylinux (one wheel for every Python)" >&2; exit 1 ;;
esac
for python in "${pythons[@]}"; do
    version=$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
    venv="$work/venv$version"
    "$python" -m venv "$venv"
    say "Python $version: installing $(basename "$wheel") into a fresh venv (dependencies from the package index)"
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "$PWD/$wheel"
    say "Python $version: smoke test from $work without a toolchain on PATH"
    (cd "$work" && env -i HOME="$HOME" PATH="$venv/bin:/usr/bin:/bin" "$venv/bin/python" "$work/smoke.py")
done
say "ok (Pythons: ${#pythons[@]})"
