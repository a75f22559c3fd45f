"""Benchmark: fluo_qd against fluo_jung and Mitsuba's native roughconductor, side by side.

Two measurements, each interleaving the methods in one process and keeping each
method's fastest of ``--repeats`` timings, then printing time ratios:

1. Time per BSDF evaluation (``bsdf.eval`` from Python on a fixed set of directions,
   ``scalar_spectral``): the Python call overhead is common to all methods, so the
   ratios understate the differences; the absolute µs are printed too.
2. Time per render (a sphere and a floor under an area light with a D65 spectrum from
   300 nm, depth 6, ``scalar_spectral``) with ``path`` and with ``fluo_path``
   (wavelength shifting active for the fluorescent materials).

Methods: roughconductor (Au, GGX α = 0.2); fluo_qd with ρ = 0 (takes roughconductor's
code path); fluo_qd with ρ = 0.8 (one Rust call per Fresnel evaluation plus the
reradiation under fluo_path); fluo_jung (c = 0.5, diffuse).

Usage: python benches/bench_qd.py [--spp 16] [--res 96] [--repeats 3] [--evals 20000] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time

import drjit as dr
import mitsuba as mi

SCENE = """<scene version="3.0.0">
    <integrator type="{integrator}"><integer name="max_depth" value="6"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 1.5, 4" target="0, 0.2, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/></film>
    </sensor>
    <shape type="sphere"><float name="radius" value="0.7"/><point name="center" x="0" y="0.3" z="0"/>{bsdf}</shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="5"/><translate y="-0.4"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="90"/><translate y="3"/></transform>
        <emitter type="area"><spectrum type="fluo_illuminant" name="radiance">
            <string name="illuminant" value="D65"/><float name="scale" value="6"/></spectrum></emitter>
    </shape>
</scene>"""

ROUGH = '<string name="material" value="Au"/><string name="distribution" value="ggx"/><float name="alpha" value="0.2"/>'
METHODS = {
    "roughconductor": {"xml": f'<bsdf type="roughconductor">{ROUGH}</bsdf>',
                       "dict": {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.2}},
    "fluo_qd_rho0": {"xml": f'<bsdf type="fluo_qd">{ROUGH}<float name="density" value="0"/></bsdf>',
                     "dict": {"type": "fluo_qd", "material": "Au", "distribution": "ggx", "alpha": 0.2, "density": 0.0}},
    "fluo_qd_rho0.8": {"xml": f'<bsdf type="fluo_qd">{ROUGH}<float name="density" value="0.8"/></bsdf>',
                       "dict": {"type": "fluo_qd", "material": "Au", "distribution": "ggx", "alpha": 0.2,
                                "density": 0.8}},
    "fluo_jung": {"xml": '<bsdf type="fluo_jung"><float name="concentration" value="0.5"/></bsdf>',
                  "dict": {"type": "fluo_jung", "concentration": 0.5}},
}


def bench_eval(n: int, repeats: int) -> dict:
    mi.set_variant("scalar_spectral")
    import fluo  # noqa: F401  (registers the plugins)

    bsdfs = {k: mi.load_dict(v["dict"]) for k, v in METHODS.items()}
    ctx = mi.BSDFContext()
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(0.3, 0.0, math.sqrt(0.91))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wavelengths = mi.Spectrum(380.0, 480.0, 580.0, 680.0)
    dirs = []
    for i in range(64):
        t, p = 0.05 + 0.6 * i / 64, 2.4 * i
        dirs.append(mi.Vector3f(math.sin(t) * math.cos(p) - 0.3, math.sin(t) * math.sin(p), math.cos(t)))
    dirs = [dr.normalize(d) for d in dirs]
    best = {k: float("inf") for k in bsdfs}
    for _ in range(repeats):
        for k, b in bsdfs.items():
            t0 = time.perf_counter()
            for j in range(n):
                b.eval(ctx, si, dirs[j & 63])
            best[k] = min(best[k], (time.perf_counter() - t0) / n)
    return {"us_per_eval": {k: v * 1e6 for k, v in best.items()},
            "ratio_qd_rho0_over_roughconductor": best["fluo_qd_rho0"] / best["roughconductor"],
            "ratio_qd_over_roughconductor": best["fluo_qd_rho0.8"] / best["roughconductor"],
            "ratio_qd_over_jung": best["fluo_qd_rho0.8"] / best["fluo_jung"]}


def bench_render(integrator: str, spp: int, res: int, repeats: int) -> dict:
    mi.set_variant("scalar_spectral")
    import fluo  # noqa: F401

    scenes = {k: mi.load_string(SCENE.format(integrator=integrator, res=res, bsdf=v["xml"]))
              for k, v in METHODS.items()}
    for s in scenes.values():  # warm-up
        mi.render(s, spp=1)
    best = {k: float("inf") for k in scenes}
    for _ in range(repeats):
        for k, s in scenes.items():
            t0 = time.perf_counter()
            mi.render(s, spp=spp, seed=1)
            best[k] = min(best[k], time.perf_counter() - t0)
    return {"integrator": integrator, "seconds": best,
            "ratio_qd_rho0_over_roughconductor": best["fluo_qd_rho0"] / best["roughconductor"],
            "ratio_qd_over_roughconductor": best["fluo_qd_rho0.8"] / best["roughconductor"],
            "ratio_qd_over_jung": best["fluo_qd_rho0.8"] / best["fluo_jung"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--evals", type=int, default=20000)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    ev = bench_eval(a.evals, a.repeats)
    renders = [bench_render(i, a.spp, a.res, a.repeats) for i in ("path", "fluo_path")]
    if a.json:
        print(json.dumps({"machine": platform.processor() or platform.machine(), "eval": ev, "render": renders}))
        return
    print(f"fluo_qd vs roughconductor and fluo_jung, scalar_spectral, best of {a.repeats} ({platform.machine()})")
    us = ev["us_per_eval"]
    print("  per BSDF eval (from Python): " + "  ".join(f"{k} {v:.2f}us" for k, v in us.items()))
    print(f"    ratio qd(rho=0)/roughconductor {ev['ratio_qd_rho0_over_roughconductor']:.3f}  "
          f"qd(rho=0.8)/roughconductor {ev['ratio_qd_over_roughconductor']:.3f}  "
          f"qd(rho=0.8)/jung {ev['ratio_qd_over_jung']:.3f}")
    for r in renders:
        s = r["seconds"]
        print(f"  render {a.res}x{a.res} {a.spp} spp, {r['integrator']:9s}: "
              + "  ".join(f"{k} {v:.3f}s" for k, v in s.items()))
        print(f"    ratio qd(rho=0)/roughconductor {r['ratio_qd_rho0_over_roughconductor']:.3f}  "
              f"qd(rho=0.8)/roughconductor {r['ratio_qd_over_roughconductor']:.3f}  "
              f"qd(rho=0.8)/jung {r['ratio_qd_over_jung']:.3f}")


if __name__ == "__main__":
    main()
