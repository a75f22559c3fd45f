"""Benchmark: fluo_jung against Mitsuba's native diffuse, measured side by side.

Renders the same scene (a sphere and a floor under an area light, path tracer,
depth 6) with three materials in one process, interleaving the runs and keeping each
method's fastest of ``--repeats`` timings, then prints the time ratios:

* fluo_jung(c = 0) / diffuse   (target <= 1.10 in scalar_spectral: the c = 0 shim
  skips the Rust call and must cost what diffuse costs)
* fluo_jung(c = 0.5) / diffuse (the cost of one FFI call per interaction)

Usage: python benches/bench_jung.py [--spp 32] [--res 128] [--repeats 3] [--json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import mitsuba as mi

SCENE = """<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="6"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 1.5, 4" target="0, 0.2, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/></film>
    </sensor>
    <shape type="sphere"><float name="radius" value="0.7"/><point name="center" x="0" y="0.3" z="0"/>{bsdf}</shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="5"/><translate y="-0.4"/></transform>{bsdf}
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="90"/><translate y="3"/></transform>
        <emitter type="area"><rgb name="radiance" value="6"/></emitter>
    </shape>
    <emitter type="constant"><rgb name="radiance" value="0.2"/></emitter>
</scene>"""

REFLECTANCE = '<spectrum name="reflectance" value="360:0.1, 430:0.2, 480:0.7, 550:0.8, 600:0.3, 700:0.6, 830:0.5"/>'
METHODS = {
    "diffuse": f'<bsdf type="diffuse">{REFLECTANCE}</bsdf>',
    "fluo_jung_c0": f'<bsdf type="fluo_jung">{REFLECTANCE}<float name="concentration" value="0"/></bsdf>',
    "fluo_jung_c0.5": f'<bsdf type="fluo_jung">{REFLECTANCE}<float name="concentration" value="0.5"/></bsdf>',
}


def bench(variant: str, spp: int, res: int, repeats: int) -> dict:
    mi.set_variant(variant)
    import fluo  # noqa: F401  (registers the plugins)

    scenes = {k: mi.load_string(SCENE.format(res=res, bsdf=v)) for k, v in METHODS.items()}
    for s in scenes.values():  # warm-up (thread pool, caches)
        mi.render(s, spp=1)
    best = {k: float("inf") for k in scenes}
    for _ in range(repeats):
        for k, s in scenes.items():
            t0 = time.perf_counter()
            mi.render(s, spp=spp, seed=1)
            best[k] = min(best[k], time.perf_counter() - t0)
    return {
        "variant": variant,
        "seconds": best,
        "ratio_c0_over_diffuse": best["fluo_jung_c0"] / best["diffuse"],
        "ratio_c05_over_diffuse": best["fluo_jung_c0.5"] / best["diffuse"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    results = [bench(v, a.spp, a.res, a.repeats) for v in ("scalar_spectral", "scalar_rgb")]
    if a.json:
        print(json.dumps({"machine": platform.processor() or platform.machine(), "results": results}))
        return
    print(f"fluo_jung vs diffuse, {a.res}x{a.res}, {a.spp} spp, best of {a.repeats} ({platform.machine()})")
    for r in results:
        s = r["seconds"]
        print(f"  {r['variant']:16s} diffuse {s['diffuse']:.3f}s  fluo_jung(c=0) {s['fluo_jung_c0']:.3f}s  "
              f"fluo_jung(c=0.5) {s['fluo_jung_c0.5']:.3f}s  ratio c=0/diffuse {r['ratio_c0_over_diffuse']:.3f}  "
              f"c=0.5/diffuse {r['ratio_c05_over_diffuse']:.3f}")


if __name__ == "__main__":
    main()
