"""Benchmark: fluo_path against Mitsuba's native path, measured side by side.

In one process, interleaved, best of ``--repeats``:

* Cornell box without fluorescence: fluo_path / path (target <= 1.05: the scene scan
  finds nothing to shift, and the plain path code runs), in both scalar variants;
* Cornell box whose walls and boxes are fluo_jung (c = 0.8), lit by D65 from 300 nm:
  fluo_path (shifting) / path (same materials, absorption without re-emission) —
  what the wavelength shifting itself costs.

Usage: python benches/bench_fluo_path.py [--spp 16] [--res 128] [--repeats 3] [--json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import mitsuba as mi


def cornell(integrator: str, res: int, fluorescent: bool) -> dict:
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = res
    d["integrator"] = {"type": integrator, "max_depth": 8}
    if fluorescent:
        for key in ("white", "red", "green"):
            refl = d[key]["reflectance"]
            d[key] = {"type": "fluo_jung", "reflectance": refl, "emission_peak": 560.0,
                      "stokes_shift": 90.0, "concentration": 0.8}
        d["light"]["emitter"]["radiance"] = {"type": "fluo_illuminant", "illuminant": "D65", "scale": 15.0}
    return d


def timed(scene, spp: int) -> float:
    t0 = time.perf_counter()
    mi.render(scene, spp=spp, seed=1)
    return time.perf_counter() - t0


def bench(variant: str, fluorescent: bool, spp: int, res: int, repeats: int) -> dict:
    mi.set_variant(variant)
    import fluo  # noqa: F401

    scenes = {k: mi.load_dict(cornell(k, res, fluorescent)) for k in ("path", "fluo_path")}
    for s in scenes.values():
        mi.render(s, spp=1)
    best = {k: float("inf") for k in scenes}
    for _ in range(repeats):
        for k, s in scenes.items():
            best[k] = min(best[k], timed(s, spp))
    return {"variant": variant, "fluorescent": fluorescent, "seconds": best,
            "ratio": best["fluo_path"] / best["path"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    runs = [bench("scalar_spectral", False, a.spp, a.res, a.repeats),
            bench("scalar_rgb", False, a.spp, a.res, a.repeats),
            bench("scalar_spectral", True, a.spp, a.res, a.repeats)]
    if a.json:
        print(json.dumps({"machine": platform.machine(), "results": runs}))
        return
    print(f"fluo_path vs path, Cornell box {a.res}x{a.res}, {a.spp} spp, best of {a.repeats} ({platform.machine()})")
    for r in runs:
        label = "fluorescent walls" if r["fluorescent"] else "no fluorescence"
        s = r["seconds"]
        print(f"  {r['variant']:16s} {label:18s} path {s['path']:.3f}s  fluo_path {s['fluo_path']:.3f}s  "
              f"ratio {r['ratio']:.3f}")


if __name__ == "__main__":
    main()
