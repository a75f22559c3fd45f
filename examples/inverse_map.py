"""Inverse rendering of a dye map: recover a 32×32 concentration texture (and, in the
spectral variant, the dye's emission peak) from a target image, by gradient descent
through fluo_prb (path replay: memory independent of path depth).

    .venv/bin/python examples/inverse_map.py [--variant llvm_ad_spectral|llvm_ad_rgb|cuda_ad_*]
        [--iterations 200] [--spp 16]

A plate painted with fluo_jung whose concentration is a 32×32 bitmap (one value per texel,
nearest lookup) lies under a D65 sky from 300 nm and a 365 nm lamp, seen straight from
above by an orthographic camera (2×2 pixels per texel). The target is rendered at hidden
values (a smooth map in [0.15, 0.85], emission peak 560 nm); the optimisation starts from
a uniform 0.5 and 530 nm and minimises the mean squared image difference with Adam,
clamping to the valid ranges after each step (the map's step quartered for the last 40 %
of the iterations). It prints, per iteration, the loss, the
map's RMSE against the hidden map and the emission peak, and exits with status 1 when the
final RMSE exceeds 0.05 (or the peak misses by more than 5 nm). In llvm_ad_rgb the peak is
baked into the reduced matrices; its gradient exists (their derivatives, baked when a
render starts) but each update of it recompiles the render kernel (~1.7 s here), so the RGB
run recovers the map at the true peak.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

LAMP = Path(__file__).resolve().parents[1] / "scenes" / "spectra" / "uv_lamp_365.csv"
TEXELS = 32
TRUE_PEAK, START_PEAK = 560.0, 530.0
RMSE_TOLERANCE, PEAK_TOLERANCE = 0.05, 5.0
LEARNING_RATE = {"map": 0.04, "peak": 2.0}


def hidden_map() -> np.ndarray:
    """A smooth map in [0.15, 0.85]: two blobs and a ramp."""
    y, x = np.mgrid[0:TEXELS, 0:TEXELS] / (TEXELS - 1)
    m = 0.15 + 0.4 * x + 0.3 * np.exp(-((x - 0.3) ** 2 + (y - 0.7) ** 2) / 0.03) \
        + 0.25 * np.exp(-((x - 0.75) ** 2 + (y - 0.25) ** 2) / 0.02)
    return np.clip(m, 0.15, 0.85).astype(np.float32)


def scene_dict(concentration: np.ndarray, peak: float, res: int) -> dict:
    return {
        "type": "scene",
        # RGB: the basis built from the scene's lights (the UV lamp reduced exactly)
        "integrator": {"type": "fluo_prb", "max_depth": 2, **({} if mi.is_spectral else {"basis": "auto"})},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "sky": {"type": "constant", "radiance": {"type": "fluo_illuminant", "illuminant": "D65", "scale": 0.7}},
        "lamp": {"type": "directional", "direction": [0.3, 0.2, -1.0],
                 "irradiance": {"type": "fluo_illuminant", "filename": str(LAMP), "normalize": False, "scale": 1.5}},
        "plate": {"type": "rectangle",
                  "bsdf": {"type": "fluo_jung", "id": "dye", "reflectance": 0.7, "quantum_yield": 0.9,
                           "emission_peak": peak, "stokes_shift": 80.0,
                           "concentration": {"type": "bitmap", "bitmap": mi.Bitmap(concentration[..., None]),
                                             "raw": True, "filter_type": "nearest"}}},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", default="llvm_ad_spectral",
                    choices=("llvm_ad_spectral", "llvm_ad_rgb", "cuda_ad_spectral", "cuda_ad_rgb"))
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--spp", type=int, default=16)
    a = ap.parse_args()

    mi.set_variant(a.variant)
    import fluo  # noqa: F401  (registers the plugins)

    res = 2 * TEXELS
    truth = hidden_map()
    spectral = a.variant.endswith("spectral")
    t0 = time.perf_counter()
    target = mi.render(mi.load_dict(scene_dict(truth, TRUE_PEAK, res)), spp=16 * a.spp, seed=12345)
    start = np.full_like(truth, 0.5)
    scene = mi.load_dict(scene_dict(start, START_PEAK if spectral else TRUE_PEAK, res))
    params = mi.traverse(scene)
    key_map = next(k for k in params.keys() if k.endswith("concentration.data"))
    key_peak = next(k for k in params.keys() if k.endswith("emission_peak"))
    opt = mi.ad.Adam(lr=LEARNING_RATE["map"])
    opt[key_map] = params[key_map]
    if spectral:
        opt[key_peak] = params[key_peak]
        opt.set_learning_rate({key_peak: LEARNING_RATE["peak"]})
    params.update(opt)

    def rmse() -> float:
        return float(np.sqrt(np.mean((np.array(params[key_map])[..., 0] - truth) ** 2)))

    rmse_start = rmse()
    for it in range(a.iterations):
        if it == int(0.6 * a.iterations):  # smaller steps once near: the noise's jitter shrinks
            opt.set_learning_rate({key_map: LEARNING_RATE["map"] / 4})
        image = mi.render(scene, params, spp=a.spp, seed=it)
        loss = dr.mean(dr.square(image - target), axis=None)
        dr.backward(loss)
        opt.step()
        opt[key_map] = dr.clip(opt[key_map], 0.0, 1.0)
        if spectral:
            opt[key_peak] = dr.clip(opt[key_peak], 200.0, 1200.0)
        params.update(opt)
        print(f"iteration {it:3d}  loss {float(loss.array[0]):.3e}  map RMSE {rmse():.4f}  "
              f"emission_peak {float(params[key_peak][0]):7.2f}", flush=True)

    seconds = time.perf_counter() - t0
    final, peak = rmse(), float(params[key_peak][0])
    ok = final <= RMSE_TOLERANCE and (not spectral or abs(peak - TRUE_PEAK) <= PEAK_TOLERANCE)
    print(f"\n{a.variant}: {a.iterations} iterations in {seconds:.1f} s: map RMSE {rmse_start:.4f} -> {final:.4f} "
          f"(tolerance {RMSE_TOLERANCE}), emission peak {peak:.2f} nm (truth {TRUE_PEAK}"
          f"{', start ' + str(START_PEAK) if spectral else ', fixed in RGB'}): "
          f"{'recovered' if ok else 'MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
