"""Benchmark: what fluorescence in participating media costs, side by side in one run.

Rows (A / B, median of interleaved paired rounds with their spread, as
benches/bench_costs.py measures; target <= 1.5 for the fluorescent rows):

=========================================================  ===========================================
row                                                        A / B
=========================================================  ===========================================
``volpath_plain``: no fluorescence (homogeneous medium)    ``fluo_volpath`` / ``volpath``
``volpath_qd``: quantum-dot cuvette, ``scalar_spectral``   ``fluo_volpath`` (Q = 0.8) / ``volpath`` (Q = 0)
``volpath_qd_grid``: the same with a density grid          ``fluo_volpath`` (Q = 0.8) / ``volpath`` (Q = 0)
=========================================================  ===========================================

The scene: a 1 cm cuvette (thin glass) of ``fluo_qd_medium`` (R = 2.7 nm, 0.4 µmol/L,
μa(340 nm) ≈ 3/cm) on a grey floor, lit by a D65 area light from 300 nm
(``fluo_illuminant``). B renders the same medium made non-fluorescent (``quantum_yield``
0: the same absorption, the same tracking majorant) with Mitsuba's ``volpath``.

Usage: python benches/bench_volpath.py [--spp 16] [--res 64] [--rounds 7] [--json]
(written to be merged into benches/bench_costs.py's ROWS when docs/bench/costs.json is
regenerated).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_spectral")
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_costs import paired  # noqa: E402  (the same paired-rounds timer)

T = mi.ScalarTransform4f()


def scene(res: int, integrator: str, medium: dict) -> dict:
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": 12},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": T.look_at(origin=[0, 2.5, 6], target=[0, 0.6, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res},
                   "sampler": {"type": "independent"}},
        "light": {"type": "rectangle", "to_world": T.translate([0, 5, 2]) @ T.rotate([1, 0, 0], 90) @ T.scale(2),
                  "emitter": {"type": "area",
                              "radiance": {"type": "fluo_illuminant", "illuminant": "D65", "scale": 10.0}}},
        "floor": {"type": "rectangle", "to_world": T.rotate([1, 0, 0], -90) @ T.scale(5),
                  "bsdf": {"type": "diffuse", "reflectance": 0.3}},
        "cuvette": {"type": "cube", "to_world": T.translate([0, 0.8, 0]) @ T.scale([0.5, 0.8, 0.5]),
                    "bsdf": {"type": "thindielectric", "int_ior": 1.5}, "interior": medium},
    }


def grid(path: Path) -> dict:
    x = np.linspace(0.0, 1.0, 16)
    g = 0.5 + 0.5 * np.sin(6.0 * x)[:, None, None] * np.cos(4.0 * x)[None, :, None] * np.ones(16)[None, None, :]
    mi.VolumeGrid(np.asarray(g, dtype=np.float32)[..., None]).write(str(path))
    return {"type": "gridvolume", "filename": str(path),
            "to_world": T.translate([-0.5, 0.0, -0.5]) @ T.scale([1.0, 1.6, 1.0])}


def qd(q: float, density: dict | None = None) -> dict:
    m = {"type": "fluo_qd_medium", "radius": 2.7, "quantum_yield": q, "concentration": 0.4, "scale": 0.01}
    if density is not None:
        m["density"] = density
    return m


def run_pair(a: argparse.Namespace, da: dict, db: dict) -> dict:
    import fluo  # noqa: F401  (registers the plugins)

    sa, sb = mi.load_dict(da), mi.load_dict(db)
    return paired(lambda: mi.render(sa, spp=a.spp, seed=1), lambda: mi.render(sb, spp=a.spp, seed=1), a.rounds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    if a.rounds < 5:
        ap.error("--rounds must be at least 5 (median of paired rounds)")
    vol = Path("/tmp") / "fluo_bench_volpath_density.vol"
    homogeneous = {"type": "homogeneous", "sigma_t": 2.0, "albedo": 0.8}
    rows = {
        "volpath_plain": ("no fluorescence: fluo_volpath / volpath, homogeneous medium", 1.05,
                          scene(a.res, "fluo_volpath", homogeneous), scene(a.res, "volpath", homogeneous)),
        "volpath_qd": ("QD cuvette: fluo_volpath (Q 0.8) / volpath (Q 0), spectral", 1.5,
                       scene(a.res, "fluo_volpath", qd(0.8)), scene(a.res, "volpath", qd(0.0))),
        "volpath_qd_grid": ("QD cuvette, density grid: fluo_volpath / volpath (Q 0)", 1.5,
                            scene(a.res, "fluo_volpath", qd(0.8, grid(vol))), scene(a.res, "volpath", qd(0.0, grid(vol)))),
    }
    results = []
    for key, (label, target, da, db) in rows.items():
        r = run_pair(a, da, db)
        results.append({"row": key, "label": label, "target": target, **r})
        if not a.json:
            print(f"{label:64s} {r['ratio']:.2f} [{r['min']:.2f}-{r['max']:.2f}] (target <= {target:.2f}; "
                  f"{r['a_s']:.2f} s / {r['b_s']:.2f} s)", flush=True)
    if a.json:
        print(json.dumps({"machine": platform.machine(), "spp": a.spp, "res": a.res, "rounds": a.rounds,
                          "results": results}))


if __name__ == "__main__":
    main()
