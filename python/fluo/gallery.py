"""The demo gallery: what fluorescence adds to each demo scene, side by side.

``fluo demo`` (and ``scripts/demo.sh``) calls :func:`run`. Every ``scenes/*.xml`` is
rendered three times from one resolved text (:func:`fluo.scenes.resolve`), in this
process, with the scene's own integrator (``fluo_path``):

============================= ======================================================
panel                         what
============================= ======================================================
spectral                      ``scalar_spectral``: wavelength shifting, the reference
reduced RGB                   ``scalar_rgb``: reduced transport (Fichet et al. 2024)
without fluorescence          ``scalar_spectral``, every material's reradiation
                              removed (:func:`fluo.scenes.without_fluorescence`)
ΔE00 map                      per-pixel CIEDE2000 of "without fluorescence" against
                              "spectral" (:func:`fluo.colour.delta_e_map`; white: the
                              spectral image's brightest luminance on D65)
============================= ======================================================

Written to the output folder:

* ``<scene>_scalar_spectral.exr/.png`` and ``<scene>_scalar_rgb.exr/.png`` (as
  ``fluo render`` writes them), ``<scene>_no_fluorescence.exr/.png``,
  ``<scene>_de00.png`` (the map, :data:`DE_MAX` = white);
* ``gallery.png``: one row per scene, one column per panel, each labelled with its
  render time (``mi.render`` only, scene loading excluded);
* ``index.html``: the same table with the full-size images and the numbers;
* ``gallery.json``: the numbers (per scene and panel: seconds; per scene: mean and
  95th-percentile ΔE00 of the map, and its noise floor).

The ΔE00 map holds Monte Carlo noise as well as fluorescence. Each scene is therefore
rendered spectrally a second time with another seed (no file written), and the mean
ΔE00 between the two spectral renders is reported as the *noise floor*: what the map's
mean would be if fluorescence changed nothing (an upper bound, since "without
fluorescence" shares the spectral render's seed). Fluorescence is visible where the
map's mean exceeds its noise floor.

A scene restricted by ``<!-- fluo: variants=scalar_spectral -->`` gets a reduced-RGB
panel saying so. Nothing is skipped silently: a render that fails leaves a panel with
the error and makes :func:`run` report the scene as failed.
"""

from __future__ import annotations

import html
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from . import scenes as scene_text
from .colour import delta_e_map

#: The panels of a row, in column order: (key, column title).
PANELS = (("scalar_spectral", "spectral (scalar_spectral)"),
          ("scalar_rgb", "reduced RGB (scalar_rgb)"),
          ("no_fluorescence", "without fluorescence"),
          ("de00", "ΔE00 spectral vs without"))
#: ΔE00 shown as the top of the map's colour scale (larger values saturate).
#: 10 is a clearly visible difference for side-by-side colours; the map's scale bar
#: shows the value.
DE_MAX = 10.0
#: Size of one panel in the gallery figure, inches; with :data:`DPI` 300 x 300 pixels.
CELL_IN = 3.0
#: Height of the figure's title band, inches.
HEADER_IN = 0.5
#: Resolution of ``gallery.png``, dots per inch.
DPI = 100
#: Width of the README copy (``docs/gallery.png``), pixels: 180 per panel.
README_WIDTH_PX = 720


@dataclass
class Panel:
    """One rendered image of a gallery row."""

    key: str
    image: np.ndarray | None = None  # linear sRGB (H, W, 3); None if not rendered
    seconds: float | None = None  # mi.render only
    files: list[str] = field(default_factory=list)
    note: str = ""  # why there is no image (restricted variant, error)


@dataclass
class Row:
    """One scene of the gallery."""

    scene: str
    materials: list[str]
    panels: dict[str, Panel] = field(default_factory=dict)
    de_map: np.ndarray | None = None
    mean_de: float | None = None
    p95_de: float | None = None
    noise_de: float | None = None  # mean ΔE00 between two spectral renders (seeds differ)
    noise_p95: float | None = None  # their 95th percentile

    @property
    def fluorescent(self) -> bool:
        """Whether the scene claims fluorescence (has a fluorescent material)."""
        return bool(self.materials)

    @property
    def failed(self) -> bool:
        return any(p.note.startswith("error") for p in self.panels.values())


def gallery_size(rows: int, dpi: float = DPI) -> tuple[int, int]:
    """(height, width) in pixels of ``gallery.png`` with ``rows`` scenes."""
    return (round((rows * CELL_IN + HEADER_IN) * dpi), round(len(PANELS) * CELL_IN * dpi))


# ---------------------------------------------------------------------------- rendering


def _render(text: str, scene_dir: Path, variant: str, spp: int, seed: int, exr: Path):
    """Render a resolved scene text; write ``exr`` and a PNG beside it (unless ``exr``
    is None).

    Returns (linear sRGB image, seconds in mi.render, written paths)."""
    import mitsuba as mi

    mi.set_variant(variant)
    import fluo  # noqa: F401  (registers the plugins)

    scene = scene_text.load(text, scene_dir)
    t0 = time.perf_counter()
    image = mi.render(scene, spp=spp, seed=seed)
    seconds = time.perf_counter() - t0
    files = []
    if exr is not None:
        scene.sensors()[0].film().bitmap().write(str(exr))
        png = exr.with_suffix(".png")
        mi.util.write_bitmap(str(png), image[..., :3], write_async=False)
        files = [str(exr), str(png)]
    rgb = np.array(image, dtype=np.float64)[..., :3]
    if not np.all(np.isfinite(rgb)):
        raise RuntimeError(f"{variant}: {int(np.sum(~np.isfinite(rgb)))} non-finite pixel values")
    return rgb, seconds, files


def display(rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB -> 8-bit-ready display sRGB in [0, 1] (clipped, sRGB transfer curve)."""
    x = np.clip(rgb, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


class Progress:
    """A text progress bar on stderr: redrawn in place on a terminal, one line per
    step otherwise (logs, pytest)."""

    WIDTH = 30

    def __init__(self, total: int, stream=None):
        self.total, self.done = max(total, 1), 0
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def show(self, label: str) -> None:
        filled = self.WIDTH * self.done // self.total
        bar = "#" * filled + "-" * (self.WIDTH - filled)
        line = f"[{bar}] {self.done}/{self.total} {label}"
        if self.tty:
            self.stream.write("\r\033[K" + line + ("\n" if self.done == self.total else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def step(self, label: str) -> None:
        self.done += 1
        self.show(label)


def run(scenes: list[Path], out: Path, spp: int, res: int | None = None, seed: int = 0,
        readme: Path | None = None, log: Callable[[str], None] | None = None,
        progress_stream=None) -> list[Row]:
    """Render the gallery of ``scenes`` into ``out``; return its rows.

    ``res`` replaces each scene's ``$res`` (film width and height) where it has one;
    ``readme``: also write a :data:`README_WIDTH_PX`-wide copy of ``gallery.png`` there.
    """
    from .scenes import VARIANTS, scene_fallback_params, scene_variants

    log = log or (lambda m: print(m, file=sys.stderr, flush=True))
    out.mkdir(parents=True, exist_ok=True)
    rows: list[Row] = []
    bar = Progress(len(scenes) * 4, progress_stream)
    bar.show("starting")
    for scene in scenes:
        params: dict = {"spp": spp}
        if res is not None:
            params["res"] = res
        fallback = scene_fallback_params(scene)
        for key, value in fallback.items():
            log(f"fluo demo: {scene.name}: data for ${key} not found, using {value}")
        params.update(fallback)
        text = scene_text.resolve(scene, params)
        row = Row(scene.name, scene_text.fluorescent_materials(text))
        rows.append(row)
        allowed = scene_variants(scene)
        try:
            plain = scene_text.without_fluorescence(text, scene.parent)
        except (OSError, RuntimeError, KeyError) as err:
            plain = None
            row.panels["no_fluorescence"] = Panel("no_fluorescence", note=f"error: {err}")
        jobs = [(v, text, v) for v in VARIANTS] + [("no_fluorescence", plain, "scalar_spectral")]
        for key, job_text, variant in jobs:
            label = f"{scene.name}: {key}"
            if key in VARIANTS and key not in allowed:
                row.panels[key] = Panel(key, note=f"not rendered: the scene allows {', '.join(allowed)}")
            elif job_text is not None:
                try:
                    img, seconds, files = _render(job_text, scene.parent, variant, spp, seed,
                                                  out / f"{scene.stem}_{key}.exr")
                    row.panels[key] = Panel(key, img, seconds, files)
                except RuntimeError as err:  # Mitsuba's errors: plugin parameters, I/O
                    row.panels[key] = Panel(key, note=f"error: {err}")
                    log(f"fluo demo: FAILED {label}: {err}")
            bar.step(label)
        spectral, without = row.panels["scalar_spectral"].image, row.panels["no_fluorescence"].image
        if spectral is not None and without is not None:
            row.de_map = delta_e_map(np.maximum(without, 0), np.maximum(spectral, 0))
            row.mean_de = float(row.de_map.mean())
            row.p95_de = float(np.percentile(row.de_map, 95))
            de_png = out / f"{scene.stem}_de00.png"
            _save_de_png(row.de_map, de_png)
            row.panels["de00"] = Panel("de00", files=[str(de_png)])
            try:
                other_seed = (seed + 1) % 2**32  # Mitsuba's seeds are unsigned 32-bit
                noise, _, _ = _render(text, scene.parent, "scalar_spectral", spp, other_seed, None)
                noise_map = delta_e_map(np.maximum(noise, 0), np.maximum(spectral, 0))
                row.noise_de = float(noise_map.mean())
                row.noise_p95 = float(np.percentile(noise_map, 95))
            except RuntimeError as err:
                log(f"fluo demo: {scene.name}: noise-floor render failed: {err}")
        else:
            row.panels["de00"] = Panel("de00", note="needs the spectral and the without-fluorescence images")
        bar.step(f"{scene.name}: noise floor")
    write_figure(rows, out / "gallery.png", spp)
    if readme is not None:
        write_readme_copy(rows, readme, spp)
    write_html(rows, out, spp)
    (out / "gallery.json").write_text(json.dumps(summary(rows, spp, res), indent=1), encoding="utf-8")
    return rows


def summary(rows: list[Row], spp: int, res: int | None) -> dict:
    """The gallery's numbers as a JSON-ready dict."""
    return {
        "spp": spp, "res": res,
        "scenes": [{
            "scene": r.scene, "fluorescent_materials": r.materials,
            "mean_de00_spectral_vs_without": r.mean_de, "p95_de00_spectral_vs_without": r.p95_de,
            "mean_de00_noise_floor": r.noise_de, "p95_de00_noise_floor": r.noise_p95,
            "seconds": {k: p.seconds for k, p in r.panels.items() if p.seconds is not None},
            "notes": {k: p.note for k, p in r.panels.items() if p.note},
        } for r in rows],
    }


# ---------------------------------------------------------------------------- output


def _save_de_png(de: np.ndarray, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(str(path), np.clip(de, 0, DE_MAX), cmap="magma", vmin=0, vmax=DE_MAX)


def _num(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def _panel_title(title: str, panel: Panel) -> str:
    return f"{title}\n{panel.seconds:.2f} s" if panel.seconds is not None else title


def write_figure(rows: list[Row], path: Path, spp: int, dpi: float = DPI) -> None:
    """The gallery figure: one row per scene, one labelled column per panel;
    :func:`gallery_size` pixels at ``dpi``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(rows), 1)
    width, height = len(PANELS) * CELL_IN, n * CELL_IN + HEADER_IN
    fig = plt.figure(figsize=(width, height), dpi=dpi)
    fig.suptitle(f"fluo demo gallery, {spp} spp: fluo_path spectral | reduced RGB | "
                 f"without fluorescence | ΔE00 (0-{DE_MAX:g})", fontsize=8,
                 y=1 - 0.18 * HEADER_IN / height)
    pad = 0.1  # inches around each image inside its cell
    title_in = 0.75  # inches above each image for the row's scene name and its title
    for i, row in enumerate(rows):
        top = ((n - i) * CELL_IN - 0.06) / height
        fig.text(pad / width, top, f"{row.scene}: {_materials_label(row.materials)}",
                 fontsize=7, fontweight="bold", va="top")
        for j, (key, title) in enumerate(PANELS):
            left = (j * CELL_IN + pad) / width
            bottom = ((n - 1 - i) * CELL_IN + pad) / height
            ax = fig.add_axes((left, bottom, (CELL_IN - 2 * pad) / width,
                               (CELL_IN - 2 * pad - title_in) / height))
            ax.set_xticks([])
            ax.set_yticks([])
            panel = row.panels.get(key, Panel(key))
            label = _panel_title(title, panel)
            if key == "de00" and row.de_map is not None:
                im = ax.imshow(row.de_map, cmap="magma", vmin=0, vmax=DE_MAX)
                label = f"{title}\nmean {row.mean_de:.2f} (noise {_num(row.noise_de)}), p95 {row.p95_de:.2f}"
                bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
                bar.ax.tick_params(labelsize=5)
            elif panel.image is not None:
                ax.imshow(display(panel.image))
            else:
                ax.text(0.5, 0.5, panel.note or "not rendered", ha="center", va="center",
                        wrap=True, fontsize=6, transform=ax.transAxes)
            ax.set_title(label, fontsize=6.5)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def write_readme_copy(rows: list[Row], path: Path, spp: int) -> None:
    """The gallery figure :data:`README_WIDTH_PX` wide (kept in full RGB: a 256-colour
    palette, a third of the size, bands the shaded spheres)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_figure(rows, path, spp, dpi=README_WIDTH_PX / (len(PANELS) * CELL_IN))


def _materials_label(materials: list[str]) -> str:
    """``["fluo_qd", "fluo_qd", "fluo_jung"]`` -> ``"fluo_qd x2, fluo_jung"``."""
    if not materials:
        return "no fluorescent material"
    counts = {m: materials.count(m) for m in dict.fromkeys(materials)}
    return ", ".join(m if n == 1 else f"{m} x{n}" for m, n in counts.items())


def write_html(rows: list[Row], out: Path, spp: int) -> None:
    """``out/index.html``: the gallery figure, then per scene its panels at full size
    with render times and the ΔE00 numbers (links relative to ``out``)."""
    def cell(row: Row, key: str) -> str:
        panel = row.panels.get(key, Panel(key))
        pngs = [Path(f).name for f in panel.files if f.endswith(".png")]
        if not pngs:
            return f"<td>{html.escape(panel.note or 'not rendered')}</td>"
        caption = f"{panel.seconds:.2f} s" if panel.seconds is not None else ""
        if key == "de00":
            caption = (f"mean {row.mean_de:.2f} (noise floor {_num(row.noise_de)}), "
                       f"p95 {row.p95_de:.2f}; scale 0-{DE_MAX:g}")
        exrs = [Path(f).name for f in panel.files if f.endswith(".exr")]
        link = f' (<a href="{html.escape(exrs[0])}">EXR</a>)' if exrs else ""
        return (f'<td><a href="{html.escape(pngs[0])}"><img src="{html.escape(pngs[0])}" '
                f'alt="{html.escape(row.scene)} {key}"></a><br>{caption}{link}</td>')

    head = "".join(f"<th>{html.escape(t)}</th>" for _, t in PANELS)
    body = "\n".join(
        f"<tr><th>{html.escape(r.scene)}<br><small>{html.escape(_materials_label(r.materials))}"
        f"</small></th>" + "".join(cell(r, k) for k, _ in PANELS) + "</tr>" for r in rows)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>fluo demo gallery</title>
<style>body{{font-family:sans-serif}} td,th{{padding:4px;text-align:center;vertical-align:top}}
img{{width:256px;image-rendering:pixelated}}</style></head>
<body>
<h1>fluo demo gallery</h1>
<p>Every <code>scenes/*.xml</code> rendered with <code>fluo_path</code> at {spp} spp:
spectral (<code>scalar_spectral</code>, wavelength shifting), reduced RGB
(<code>scalar_rgb</code>), the same scene without fluorescence (reradiation removed,
elastic part kept; <code>scalar_spectral</code>), and the per-pixel CIEDE2000 between
spectral and without fluorescence, with its noise floor (the same between two spectral
renders with different seeds). Times are <code>mi.render</code> only.</p>
<p><img src="gallery.png" alt="gallery" style="width:100%;max-width:1200px"></p>
<table>
<tr><th>scene</th>{head}</tr>
{body}
</table>
</body></html>
"""
    (out / "index.html").write_text(page, encoding="utf-8")
