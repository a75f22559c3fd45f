"""Benchmark: fluorescence in RGB (reduced transport) against the spectral reference.

Renders scenes/fluo_path_d65.xml (three fluo_jung spheres and a plain one under an area
light emitting D65 from 300 nm) in one run:

* the converged spectral reference (fluo_path, scalar_spectral, --ref-spp), cached in
  out/cache/ with its settings (delete it or change settings to recompute);
* scalar_rgb with fluo_path for every basis (rgb, xyzu, x7) and method (ours, naive),
  and plain RGB without fluorescence (Mitsuba's path with the dyes removed,
  concentration 0: what a user gets today), each at --spp;

and prints, per method, the render time and the mean and 95th-percentile per-pixel
CIEDE2000 against the reference (linear sRGB -> XYZ -> L*a*b*, white = D65 at the
reference's peak luminance), plus the time of the spectral render at the same spp.

Usage: python benches/bench_reduced.py [--res 128] [--spp 256] [--ref-spp 4096] [--json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

REPO = Path(__file__).resolve().parents[1]
SCENE = REPO / "scenes" / "fluo_path_d65.xml"


def render(variant: str, res: int, spp: int, seed: int = 1, **params) -> tuple[np.ndarray, float]:
    mi.set_variant(variant)
    import fluo  # noqa: F401

    scene = mi.load_file(str(SCENE), res=res, spp=spp, **params)
    t0 = time.perf_counter()
    img = np.array(mi.render(scene, seed=seed), dtype=np.float64)[..., :3]
    return img, time.perf_counter() - t0


def reference(res: int, spp: int) -> np.ndarray:
    key = hashlib.sha1(f"{SCENE.read_bytes()!r}{res}{spp}".encode()).hexdigest()[:12]
    cache = REPO / "out" / "cache" / f"bench_reduced_ref_{key}.npy"
    if cache.exists():
        return np.load(cache)
    img, t = render("scalar_spectral", res, spp, seed=7)
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.save(cache, img)
    cache.with_suffix(".json").write_text(json.dumps({"scene": str(SCENE), "res": res, "spp": spp,
                                                      "seconds": t}))
    return img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    from fluo.colour import delta_e_map

    ref = reference(a.res, a.ref_spp)
    rows = []

    def add(name, img, seconds):
        de = delta_e_map(np.maximum(img, 0), np.maximum(ref, 0))
        rows.append({"method": name, "seconds": seconds, "mean_de2000": float(de.mean()),
                     "p95_de2000": float(np.percentile(de, 95))})

    img, t = render("scalar_spectral", a.res, a.spp)
    add("spectral fluo_path", img, t)
    for basis in ("rgb", "xyzu", "x7"):
        for method in ("ours", "naive"):
            img, t = render("scalar_rgb", a.res, a.spp, basis=basis, method=method)
            add(f"rgb fluo_path {method}-{basis}", img, t)
    # plain RGB without fluorescence: the same scene under Mitsuba's path
    mi.set_variant("scalar_rgb")
    text = (REPO / "scenes" / "include" / "fluo_objects.xml").read_text()
    plain = REPO / "out" / "cache" / "fluo_objects_plain.xml"
    plain.parent.mkdir(parents=True, exist_ok=True)
    import re
    text = re.sub(r'<float name="concentration" value="[0-9.]+"/>', '<float name="concentration" value="0"/>', text)
    plain.write_text(text.replace('<integrator type="fluo_path">', '<integrator type="path">')
                     .replace('<string name="basis" value="$basis"/>', "")
                     .replace('<string name="method" value="$method"/>', ""))
    scene_text = SCENE.read_text().replace("include/fluo_objects.xml", str(plain))
    tmp = REPO / "out" / "cache" / "bench_reduced_plain.xml"
    tmp.write_text(scene_text)
    scene = mi.load_file(str(tmp), res=a.res, spp=a.spp)
    t0 = time.perf_counter()
    img = np.array(mi.render(scene, seed=1), dtype=np.float64)[..., :3]
    add("rgb path (no fluorescence)", img, time.perf_counter() - t0)

    if a.json:
        print(json.dumps({"machine": platform.machine(), "res": a.res, "spp": a.spp,
                          "ref_spp": a.ref_spp, "rows": rows}))
        return
    print(f"{SCENE.name}: {a.res}x{a.res}, {a.spp} spp vs spectral reference at {a.ref_spp} spp "
          f"({platform.machine()})")
    print(f"  {'method':32s} {'time':>8s} {'mean ΔE00':>10s} {'p95 ΔE00':>9s}")
    for r in rows:
        print(f"  {r['method']:32s} {r['seconds']:7.2f}s {r['mean_de2000']:10.2f} {r['p95_de2000']:9.2f}")


if __name__ == "__main__":
    main()
