"""Benchmark: fluo_gmm against fluo_matrix (and fluo_matrix against diffuse), side by side.

In one process, interleaved, best of ``--repeats``, Cornell box with the walls and
boxes made of one material, lit by D65 from 300 nm, ``fluo_path``, ``scalar_spectral``:

* ``fluo_matrix`` (tabulated matrix, exact CDF sampling) / ``diffuse`` (same scene,
  plain reflectance): what measured fluorescence costs;
* ``fluo_gmm`` (8 Gaussians, truncated conditional sampling) / ``fluo_matrix``: the
  price of the compact representation at render time.

The material is a measured matrix from the shared data when present
(``$FLUO_SHARED_DATA/bispectral/TEXTYELL.BFC``), else ``data/matrices/jung_yellow.csv``.

Usage: python benches/bench_measured.py [--spp 16] [--res 128] [--repeats 3] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import mitsuba as mi

REPO = Path(__file__).resolve().parents[1]


def matrix_file() -> Path:
    shared = Path(os.environ.get("FLUO_SHARED_DATA", REPO.parent / "shared" / "data"))
    measured = shared / "bispectral" / "TEXTYELL.BFC"
    return measured if measured.is_file() else REPO / "data" / "matrices" / "jung_yellow.csv"


def cornell(bsdf: dict, res: int) -> dict:
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = res
    d["integrator"] = {"type": "fluo_path", "max_depth": 8}
    for key in ("white", "red", "green"):
        d[key] = dict(bsdf)
    d["light"]["emitter"]["radiance"] = {"type": "fluo_illuminant", "illuminant": "D65", "scale": 15.0}
    return d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    mi.set_variant("scalar_spectral")
    import fluo

    src = matrix_file()
    with tempfile.TemporaryDirectory() as tmp:
        fit = Path(tmp) / "fit.gmm.json"
        fluo.run_tool(["fit-gmm", str(src), "--components", "8", "-o", str(fit)])
        bsdfs = {
            "diffuse": {"type": "diffuse", "reflectance": 0.6},
            "fluo_matrix": {"type": "fluo_matrix", "filename": str(src)},
            "fluo_gmm": {"type": "fluo_gmm", "filename": str(fit)},
        }
        scenes = {k: mi.load_dict(cornell(b, a.res)) for k, b in bsdfs.items()}
        for s in scenes.values():
            mi.render(s, spp=1)
        best = {k: float("inf") for k in scenes}
        for _ in range(a.repeats):
            for k, s in scenes.items():
                t0 = time.perf_counter()
                mi.render(s, spp=a.spp, seed=1)
                best[k] = min(best[k], time.perf_counter() - t0)
    ratios = {"fluo_matrix/diffuse": best["fluo_matrix"] / best["diffuse"],
              "fluo_gmm/fluo_matrix": best["fluo_gmm"] / best["fluo_matrix"]}
    if a.json:
        print(json.dumps({"machine": platform.machine(), "material": src.name, "seconds": best, "ratios": ratios}))
        return
    print(f"measured materials, Cornell box {a.res}x{a.res}, {a.spp} spp, D65, fluo_path, best of {a.repeats} "
          f"({platform.machine()}, {src.name})")
    for k, v in best.items():
        print(f"  {k:12s} {v:.3f}s")
    for k, v in ratios.items():
        print(f"  ratio {k}: {v:.2f}")


if __name__ == "__main__":
    main()
