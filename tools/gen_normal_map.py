"""Generate the normal map of ``scenes/fluo_normalmap.xml`` (run once; the PNG is committed).

A 128×128 hammered-metal pattern: a 6×6 grid of shallow spherical dimples (each
cap's slope at most ~35 degrees), jittered by a fixed seed, as a tangent-space normal map
(8-bit RGB, n = 2·rgb − 1, read with ``raw`` true by Mitsuba's ``normalmap``).

    .venv/bin/python tools/gen_normal_map.py
"""

from pathlib import Path

import mitsuba as mi
import numpy as np

N, CELLS, SLOPE = 128, 6, 0.7


def main():
    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:N, 0:N] / N  # image rows top-down
    nx, ny = np.zeros((N, N)), np.zeros((N, N))
    cell = 1.0 / CELLS
    for i in range(CELLS):
        for j in range(CELLS):
            cx, cy = (i + 0.5 + rng.uniform(-0.15, 0.15)) * cell, (j + 0.5 + rng.uniform(-0.15, 0.15)) * cell
            r = cell * rng.uniform(0.35, 0.5)
            dx, dy = x - cx, y - cy
            inside = dx * dx + dy * dy < r * r
            # a dimple's slope grows linearly from its centre to its rim (a spherical cap)
            nx[inside] = -SLOPE * dx[inside] / r
            ny[inside] = SLOPE * dy[inside] / r  # +v points up the image
    n = np.stack([nx, ny, np.ones_like(nx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    rgb = np.round((0.5 * n + 0.5) * 255).astype(np.uint8)
    out = Path(__file__).resolve().parents[1] / "scenes" / "textures" / "hammered_normal.png"
    mi.Bitmap(rgb, mi.Bitmap.PixelFormat.RGB).write(str(out))
    print(out)


if __name__ == "__main__":
    main()
