"""Generate the textures of ``scenes/label_textured.xml`` (run once; the PNGs are committed).

A 96×48 label: a dye-concentration map (grayscale, raw values: c = pixel/255) with the
letters FLUO in a dense dye on a lightly dyed ground and an undyed border, and an
emission-peak map (a one-channel float EXR, in nm: an 8-bit image's raw values are
read as pixel/255) that is green (520 nm) on the left two letters and
orange (600 nm) on the right two.

    .venv/bin/python tools/gen_label_textures.py
"""

from pathlib import Path

import mitsuba as mi
import numpy as np

FONT = {  # 5×7 blocks
    "F": ["#####", "#....", "#....", "####.", "#....", "#....", "#...."],
    "L": ["#....", "#....", "#....", "#....", "#....", "#....", "#####"],
    "U": ["#...#", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."],
    "O": [".###.", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."],
}
W, H, SCALE = 96, 48, 3


def main():
    mi.set_variant("scalar_rgb")
    conc = np.full((H, W), 0.15)
    conc[:3, :] = conc[-3:, :] = conc[:, :3] = conc[:, -3:] = 0.0  # undyed border
    peak = np.full((H, W), 520.0)
    peak[:, W // 2:] = 600.0
    x0, y0 = (W - 23 * SCALE) // 2, (H - 7 * SCALE) // 2
    for i, ch in enumerate("FLUO"):
        for r, row in enumerate(FONT[ch]):
            for c, cell in enumerate(row):
                if cell == "#":
                    x, y = x0 + (i * 6 + c) * SCALE, y0 + r * SCALE
                    conc[y:y + SCALE, x:x + SCALE] = 1.0
    out = Path(__file__).resolve().parents[1] / "scenes" / "textures"
    png = mi.Bitmap(np.round(conc * 255).astype(np.uint8)[..., None], mi.Bitmap.PixelFormat.Y)
    png.write(str(out / "label_concentration.png"))
    exr = mi.Bitmap(peak.astype(np.float32)[..., None], mi.Bitmap.PixelFormat.Y)
    exr.write(str(out / "label_emission_peak.exr"))
    print(out / "label_concentration.png", out / "label_emission_peak.exr")


if __name__ == "__main__":
    main()
