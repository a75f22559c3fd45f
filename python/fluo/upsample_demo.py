"""Wide-gamut upsampling demo: render an ACEScg test card and map its CIEDE2000 error.

``python -m fluo.upsample_demo [--spp N] [--out DIR]`` (from the repo, with
``PYTHONPATH=python``):

1. writes the saturated ACEScg test card ``scenes/textures/acescg_card.exr`` if missing
   (:func:`card_colours`: 16 hues x 4 rows of saturation/value, linear ACEScg);
2. renders ``scenes/upsample_acescg.xml`` (``fluo_jung`` with ``color`` = that texture,
   a D65 environment normalised to white Y = 1, ``fluo_path``, direct light only) in
   ``scalar_spectral``;
3. compares every pixel with its texel's input colour: input ACEScg -> XYZ (ACES white)
   -> Bradford to D65 (the cube's convention, ``core/src/upsample/``) -> L*a*b* (D65),
   against the rendered linear sRGB -> XYZ -> L*a*b*; writes the per-pixel ΔE2000 map
   beside the image (``<image>_de2000.exr`` and a ``.png`` with ΔE 10 = white) and
   prints mean / median / 95th percentile as JSON, plus the mean and max ΔE of each
   texel's average rendered colour (free of most Monte Carlo noise).

``--no-fluorescence`` renders with the cube's reflectance-only solutions instead.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from . import out_dir, scenes_dir
from .colour import SRGB_TO_XYZ, ciede2000, xyz_to_lab

SCENE = scenes_dir() / "upsample_acescg.xml"
CARD = scenes_dir() / "textures" / "acescg_card.exr"
#: Card layout: hues along x, these (saturation, value) rows along y (top first).
CARD_ROWS = ((1.0, 1.0), (1.0, 0.9), (0.7, 1.0), (1.0, 0.5))
CARD_HUES = 16

ACESCG_TO_XYZ = np.array([
    [0.6624541811085055, 0.13400420645643313, 0.15618768700490773],
    [0.2722287167809146, 0.6740817658111483, 0.05368951740793703],
    [-0.005574649490394109, 0.004060733528982825, 1.010339100312997]])
BRADFORD = np.array([[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]])
ACES_WHITE = np.array([0.32168 / 0.33767, 1.0, (1 - 0.32168 - 0.33767) / 0.33767])
D65_WHITE = np.array([0.3127 / 0.3290, 1.0, (1 - 0.3127 - 0.3290) / 0.3290])


def hsv_to_rgb(h, s, v):
    h6 = (h % 1.0) * 6.0
    i = int(np.floor(h6)) % 6
    f = h6 - np.floor(h6)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


def card_colours() -> np.ndarray:
    """(rows, hues, 3) linear ACEScg colours of the test card."""
    return np.array([[hsv_to_rgb(i / CARD_HUES, s, v) for i in range(CARD_HUES)] for s, v in CARD_ROWS])


def bradford(src_white, dst_white):
    s, d = BRADFORD @ src_white, BRADFORD @ dst_white
    return np.linalg.inv(BRADFORD) @ np.diag(d / s) @ BRADFORD


def write_card(path: Path = CARD) -> Path:
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    path.parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(card_colours().astype(np.float32)).write(str(path))
    return path


def reference_lab(shape) -> np.ndarray:
    """L*a*b* (D65) of the input colour under each pixel of an image of `shape` (h, w)."""
    h, w = shape
    card = card_colours()
    rows = (np.arange(h) + 0.5) / h * card.shape[0]
    cols = (np.arange(w) + 0.5) / w * card.shape[1]
    # The rectangle's v (texture rows from the top of the EXR) grows upwards on screen.
    rgb = card[::-1][rows.astype(int)][:, cols.astype(int)]
    xyz = rgb @ ACESCG_TO_XYZ.T @ bradford(ACES_WHITE, D65_WHITE).T
    return xyz_to_lab(xyz, D65_WHITE)


def de2000_map(image_srgb: np.ndarray) -> np.ndarray:
    xyz = image_srgb[..., :3] @ SRGB_TO_XYZ.T
    return ciede2000(reference_lab(image_srgb.shape[:2]), xyz_to_lab(xyz, D65_WHITE))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fluo.upsample_demo", description=__doc__.split("\n")[0])
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--out", type=Path, default=out_dir())
    parser.add_argument("--no-fluorescence", action="store_true")
    args = parser.parse_args(argv)
    import mitsuba as mi
    mi.set_variant("scalar_spectral")
    import fluo  # noqa: F401  (registers the plugins)
    if not CARD.exists():
        write_card()
    fl = "false" if args.no_fluorescence else "true"
    scene = mi.load_file(str(SCENE), spp=args.spp, fluorescence=fl)
    image = np.array(mi.render(scene, spp=args.spp, seed=0))[..., :3]
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / ("upsample_acescg_scalar_spectral" + ("_nofl" if args.no_fluorescence else ""))
    mi.util.write_bitmap(str(stem) + ".exr", image, write_async=False)
    mi.util.write_bitmap(str(stem) + ".png", image, write_async=False)
    de = de2000_map(image)
    mi.util.write_bitmap(str(stem) + "_de2000.exr", de[..., None].astype(np.float32), write_async=False)
    grey = np.clip(de / 10.0, 0, 1)
    mi.Bitmap((np.stack([grey] * 3, -1) * 255).astype(np.uint8)).write(str(stem) + "_de2000.png")
    # Noise-robust summary: ΔE of each texel's mean rendered colour.
    rows, cols = card_colours().shape[:2]
    h, w = image.shape[:2]
    blocks = image[: h // rows * rows, : w // cols * cols].reshape(rows, h // rows, cols, w // cols, 3).mean((1, 3))
    de_texel = de2000_map(np.repeat(np.repeat(blocks, 2, 0), 2, 1))
    print(json.dumps({"image": str(stem) + ".exr", "de2000_map": str(stem) + "_de2000.exr",
                      "fluorescence": not args.no_fluorescence,
                      "de2000_texel_mean": float(de_texel.mean()), "de2000_texel_max": float(de_texel.max()),
                      "de2000_mean": float(de.mean()), "de2000_median": float(np.median(de)),
                      "de2000_p95": float(np.percentile(de, 95)), "de2000_max": float(de.max())}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
