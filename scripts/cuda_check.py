"""Check fluo's vectorised plugins on a GPU: cuda_ad_* against the scalar reference.

    python scripts/cuda_check.py [--out report.json] [--spp 256] [--res 48]

For each scene (the Jung bench box under D65 from 300 nm, the demo objects under a UV
lamp, sigmoid coefficients, the measured materials: matrices and a Gaussian mixture, the
quantum-dot bench box and cuvette, the textured label) it
renders the scalar variant and the cuda variant, each in
its own process (Mitsuba 3.8 cannot start a JIT variant in a process that has rendered
in a scalar one), with two seeds each, and prints per-channel means with a z-score
against the scalar mean (per-pixel variance from the two scalar images), the render
times, and an AD-vs-finite-difference check of d(mean image)/d(concentration) in both
cuda variants through fluo_path and fluo_prb. Needs an NVIDIA GPU; CI has none (tests/python/test_llvm.py covers
the same code on the LLVM backend).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MATRICES = REPO / "data" / "matrices"
SCENES = [("bench/jung_box.xml", {"basis": "auto"}), ("fluo_path_uv.xml", {"basis": "auto"}),
          ("jung_spheres.xml", {}),
          ("fluo_measured.xml", {"matrix_a": str(MATRICES / "jung_yellow.csv"),
                                 "matrix_b": str(MATRICES / "jung_brightener.csv")}),
          ("bench/qd_box.xml", {"basis": "auto"}), ("bench/qd_cuvette.xml", {"basis": "x7"}),
          ("label_textured.xml", {})]


def worker(variant: str, spp: int, res: int) -> dict:
    import mitsuba as mi
    import numpy as np

    mi.set_variant(variant)
    import fluo  # noqa: F401

    out = {}
    for scene, params in SCENES:
        kw = {"res": str(res), "spp": str(spp),
              **{k: v for k, v in params.items() if k != "basis" or "rgb" in variant}}
        s = mi.load_file(str(REPO / "scenes" / scene), **kw)
        images, times = [], []
        for seed in (0, 1, 2):
            t = time.perf_counter()
            images.append(np.array(mi.render(s, spp=spp, seed=seed), dtype=np.float64))
            times.append(time.perf_counter() - t)
        out[scene] = {"images": [im.tolist() for im in images[1:]], "first_s": times[0],
                      "render_s": min(times[1:])}
    if not variant.startswith("scalar"):
        out["gradients"] = gradients(variant, res, GRADIENT_SPP_FACTOR * spp)
    return out


#: The gradient check renders this many times --spp (one seed; the finite difference reuses it).
GRADIENT_SPP_FACTOR = 16


def gradients(variant: str, res: int, spp: int) -> list:
    """d(image mean)/d(concentration) of the Jung box's first sphere by AD through fluo_path
    (the recorded loop) and fluo_prb (path replay; in RGB with fluorescence each vertex's
    future from continuations of its path), against central differences on the same seed."""
    import drjit as dr
    import mitsuba as mi

    rows = []
    for integrator in ("fluo_path", "fluo_prb"):
        kw = {"basis": "auto"} if "rgb" in variant else {}
        s = mi.load_file(str(REPO / "scenes" / "bench" / "jung_box.xml"), res=str(res), spp=str(spp), **kw)
        integ = mi.load_dict({"type": integrator, "max_depth": 6, **kw})
        p = mi.traverse(s)
        key = next(k for k in p.keys() if k.endswith("bsdf.concentration"))
        x0 = float(p[key][0])
        p[key] = mi.Float(x0)
        dr.enable_grad(p[key])
        p.update()
        t = time.perf_counter()
        loss = dr.mean(mi.render(s, params=p, integrator=integ, spp=spp, seed=5), axis=None)
        dr.backward(loss)
        grad = float(dr.grad(p[key])[0])
        ad_s = time.perf_counter() - t
        h = 0.05
        vals = []
        for d in (-h, h):
            p[key] = mi.Float(x0 + d)
            p.update()
            vals.append(float(dr.mean(mi.render(s, params=p, integrator=integ, spp=spp, seed=5),
                                      axis=None).array[0]))
        rows.append({"integrator": integrator, "parameter": key, "spp": spp, "ad": grad,
                     "fd": (vals[1] - vals[0]) / (2 * h), "ad_s": round(ad_s, 3)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--res", type=int, default=48)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--backend", choices=("cuda", "llvm"), default="cuda",
                    help="JIT backend compared with scalar (llvm: a dry run of this script without a GPU)")
    ap.add_argument("--worker")
    a = ap.parse_args()
    if a.worker:
        print("RESULT " + json.dumps(worker(a.worker, a.spp, a.res)))
        return
    import numpy as np

    results = {}
    jit = f"{a.backend}_ad"
    for variant in ("scalar_spectral", f"{jit}_spectral", "scalar_rgb", f"{jit}_rgb"):
        proc = subprocess.run([sys.executable, __file__, "--worker", variant, "--spp", str(a.spp), "--res",
                               str(a.res)], capture_output=True, text=True)
        lines = [ln[ln.index("RESULT ") + 7:] for ln in proc.stdout.splitlines() if "RESULT " in ln]
        if proc.returncode != 0 or not lines:
            print(f"{variant}: failed\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
            results[variant] = {"error": proc.stderr[-4000:]}
            continue
        results[variant] = json.loads(lines[-1])
    report = {"spp": a.spp, "res": a.res, "scenes": {}}
    for family in ("spectral", "rgb"):
        ref, gpu = results.get(f"scalar_{family}", {}), results.get(f"{jit}_{family}", {})
        if "error" in ref or "error" in gpu:
            continue
        for scene, _ in SCENES:
            if scene not in ref or scene not in gpu:
                continue
            r = np.array(ref[scene]["images"])
            g = np.array(gpu[scene]["images"])
            n = r.shape[1] * r.shape[2]
            var = np.mean(np.var(r, axis=0, ddof=1), axis=(0, 1))
            se = np.sqrt(var / n * (1 / 2 + 1 / 2))
            z = (g.mean(axis=(0, 1, 2)) - r.mean(axis=(0, 1, 2))) / np.maximum(se, 1e-12)
            row = {"scalar_mean": r.mean(axis=(0, 1, 2)).round(5).tolist(),
                   "cuda_mean": g.mean(axis=(0, 1, 2)).round(5).tolist(), "z": z.round(2).tolist(),
                   "scalar_s": round(ref[scene]["render_s"], 3), "cuda_s": round(gpu[scene]["render_s"], 3),
                   "cuda_first_s": round(gpu[scene]["first_s"], 3)}
            report["scenes"][f"{scene} {family}"] = row
            print(f"{scene:28s} {family:8s} scalar {row['scalar_mean']} cuda {row['cuda_mean']} z {row['z']} "
                  f"time scalar {row['scalar_s']} s, cuda {row['cuda_s']} s (first {row['cuda_first_s']} s)")
    for variant in (f"{jit}_spectral", f"{jit}_rgb"):
        for g in results.get(variant, {}).get("gradients", []):
            report.setdefault("gradients", []).append({"variant": variant, **g})
            print(f"gradient {variant} {g['integrator']}: AD {g['ad']:.5g} FD {g['fd']:.5g} "
                  f"(ratio {g['ad'] / g['fd'] if g['fd'] else float('nan'):.3f}, {g['spp']} spp, "
                  f"backward pass {g['ad_s']} s)")
    if a.out:
        a.out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
