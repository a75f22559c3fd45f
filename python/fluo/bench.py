"""``fluo bench``: what accuracy costs in time, measured side by side in one run.

Every scene in ``scenes/bench/*.xml`` is rendered with every method that applies to it,
on the same machine in one process:

* a converged spectral reference (``fluo_path`` in ``scalar_spectral`` at
  ``ref_spp``), cached in ``out/cache/bench/`` with its settings (a changed scene or
  setting makes a new one);
* each method at a ladder of sample counts; at every rung the render time and the
  per-pixel CIEDE2000 against the reference (linear sRGB → XYZ → L*a*b*, white: D65 at
  the reference's peak luminance) are measured.

Columns (all measured):

* ``time``: render time at the top rung (fixed spp);
* ``mean_de``, ``p95_de``: mean and 95th-percentile per-pixel ΔE00 at that rung;
* ``equal_error_time``: time to reach mean ΔE00 ≤ ``target_de``, interpolated in
  (log time, ΔE) between rungs; a method whose error never gets there (its bias floor
  lies above the target) reports ``unreachable`` with that floor;
* ``material_floats``: floats the renderer stores per fluorescent material for the
  method (the representation's memory).

Methods are declared in :data:`METHODS`: how to turn a bench scene into the method's
scene (variant, integrator, material rewrite). The table goes to stdout (Markdown),
``results.json`` and ``accuracy_vs_time.png`` to the output folder.
"""

from __future__ import annotations

import hashlib
import json
import platform
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from . import repo_root
from .colour import delta_e_map

BENCH_DIR = repo_root() / "scenes" / "bench"


def _strip_reduced_params(text: str) -> str:
    return re.sub(r'\s*<string name="(basis|method)" value="[^"]*"/>', "", text)


def _to_path(text: str) -> str:
    return _strip_reduced_params(text.replace('<integrator type="fluo_path">', '<integrator type="path">'))


def _remove_dyes(text: str) -> str:
    """The same materials without fluorescent dye (concentration 0)."""
    return re.sub(r'<float name="concentration" value="[^"]*"/>', '<float name="concentration" value="0"/>', text)


def _jung_to_diffuse(text: str) -> str:
    """Replace each fluo_jung by Mitsuba's diffuse with the same reflectance (bench
    scenes give fluo_jung reflectances as <rgb>)."""
    def repl(m: re.Match) -> str:
        body = m.group(1)
        refl = re.search(r'<rgb name="reflectance" value="[^"]*"/>', body)
        return '<bsdf type="diffuse">' + (refl.group(0) if refl else "") + "</bsdf>"
    return re.sub(r'<bsdf type="fluo_jung">(.*?)</bsdf>', repl, text, flags=re.S)


def _reduced(basis: str, method: str) -> Callable[[str], str]:
    def rewrite(text: str) -> str:
        text = re.sub(r'<string name="basis" value="[^"]*"/>', f'<string name="basis" value="{basis}"/>', text)
        return re.sub(r'<string name="method" value="[^"]*"/>', f'<string name="method" value="{method}"/>', text)
    return rewrite


@dataclass
class Method:
    """One way of rendering a bench scene."""

    name: str
    variant: str
    rewrite: Callable[[str], str]
    #: floats stored per fluorescent material (None: not fluorescence-aware)
    floats: Callable[[str], int]
    note: str = ""


def _jung_floats(_: str) -> int:
    return 4  # λe, s, c, Q (plus the reflectance every method stores)


METHODS: list[Method] = [
    Method("spectral analytic (fluo_path)", "scalar_spectral", lambda t: t, _jung_floats),
    *[Method(f"rgb {m}-{b} (fluo_path)", "scalar_rgb", _reduced(b, m),
             (lambda k: (lambda _: k * k))({"rgb": 3, "xyzu": 4, "x7": 7}[b]))
      for m in ("ours", "naive") for b in ("rgb", "xyzu", "x7")],
    Method("rgb plain, no fluorescence (path)", "scalar_rgb", lambda t: _remove_dyes(_to_path(t)),
           lambda _: 0, "what a user gets today"),
    Method("spectral native path, nearest diffuse", "scalar_spectral",
           lambda t: _jung_to_diffuse(_to_path(t)), lambda _: 0, "the cost floor"),
]


@dataclass
class Row:
    scene: str
    method: str
    spp: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    mean_de: list[float] = field(default_factory=list)
    p95_de: list[float] = field(default_factory=list)
    equal_error_time: float | None = None
    floor_de: float = 0.0
    material_floats: int = 0


def _render_text(text: str, variant: str, res: int, spp: int, seed: int, cache: Path) -> tuple[np.ndarray, float]:
    import mitsuba as mi

    mi.set_variant(variant)
    import fluo  # noqa: F401  (plugins)

    digest = hashlib.sha1(text.encode()).hexdigest()[:12]
    path = cache / f"scene_{digest}.xml"
    path.write_text(text)
    scene = mi.load_file(str(path), res=res, spp=spp)
    t0 = time.perf_counter()
    img = np.array(mi.render(scene, seed=seed), dtype=np.float64)[..., :3]
    return img, time.perf_counter() - t0


def _absolutise_includes(text: str, scene_dir: Path) -> str:
    return re.sub(r'<include filename="([^"/][^"]*)"/>',
                  lambda m: f'<include filename="{(scene_dir / m.group(1)).resolve()}"/>', text)


def equal_error_time(seconds: list[float], errors: list[float], target: float) -> float | None:
    """Time at which the error ladder first reaches ``target`` (log-time interpolation)."""
    for i, (t, e) in enumerate(zip(seconds, errors)):
        if e <= target:
            if i == 0:
                return t * e / target if e > 0 else t  # reached on the first rung: scale down
            t0, e0 = seconds[i - 1], errors[i - 1]
            w = (e0 - target) / (e0 - e) if e0 != e else 1.0
            return float(np.exp(np.log(t0) + w * (np.log(t) - np.log(t0))))
    return None


def run(quick: bool = True, out: Path | None = None, scenes: list[Path] | None = None,
        target_de: float = 1.5, log=print) -> dict:
    """Run the benchmark; returns the results dict (also written to ``out``)."""
    out = Path(out or repo_root() / "out" / "bench")
    cache = repo_root() / "out" / "cache" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    res = 48 if quick else 96
    ladder = [4, 16, 64, 256, 1024]
    ref_spp = 4096 if quick else 16384
    rows: list[Row] = []
    scenes = scenes or sorted(BENCH_DIR.glob("*.xml"))
    for scene_path in scenes:
        base = _absolutise_includes(scene_path.read_text(), scene_path.parent)
        key = hashlib.sha1(f"{base}|{res}|{ref_spp}".encode()).hexdigest()[:12]
        ref_file = cache / f"{scene_path.stem}_ref_{key}.npy"
        if ref_file.exists():
            ref = np.load(ref_file)
            log(f"[bench] {scene_path.name}: cached reference {ref_file.name}")
        else:
            log(f"[bench] {scene_path.name}: spectral reference, {ref_spp} spp at {res}x{res} ...")
            ref, t = _render_text(base, "scalar_spectral", res, ref_spp, 12345, cache)
            np.save(ref_file, ref)
            ref_file.with_suffix(".json").write_text(json.dumps(
                {"scene": scene_path.name, "res": res, "spp": ref_spp, "seconds": t}))
        n_materials = len(re.findall(r'<bsdf type="fluo_(?!illuminant)', base))
        for m in METHODS:
            text = m.rewrite(base)
            row = Row(scene_path.stem, m.name, material_floats=m.floats(text) if n_materials else 0)
            for spp in ladder:
                img, t = _render_text(text, m.variant, res, spp, 1, cache)
                de = delta_e_map(np.maximum(img, 0), np.maximum(ref, 0))
                row.spp.append(spp)
                row.seconds.append(t)
                row.mean_de.append(float(de.mean()))
                row.p95_de.append(float(np.percentile(de, 95)))
            row.equal_error_time = equal_error_time(row.seconds, row.mean_de, target_de)
            row.floor_de = min(row.mean_de)
            rows.append(row)
            log(f"[bench]   {m.name:42s} {row.seconds[-1]:7.2f}s  ΔE00 {row.mean_de[-1]:.2f}")
    result = {
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {platform.processor() or 'unknown cpu'}, "
                   f"{__import__('os').cpu_count()} cores",
        "quick": quick, "res": res, "ladder_spp": ladder, "ref_spp": ref_spp, "target_de": target_de,
        "rows": [r.__dict__ for r in rows],
    }
    (out / "results.json").write_text(json.dumps(result, indent=1))
    (out / "results.md").write_text(table(result))
    plot(result, out / "accuracy_vs_time.png")
    return result


def table(result: dict) -> str:
    lines = [f"fluo bench ({'quick' if result['quick'] else 'full'}), {result['date']}, {result['machine']}; "
             f"{result['res']}x{result['res']}, time and ΔE00 at {result['ladder_spp'][-1]} spp, "
             f"reference {result['ref_spp']} spp, equal-error target mean ΔE00 ≤ {result['target_de']}",
             "",
             "| scene | method | time (s) | mean ΔE00 | p95 ΔE00 | equal-error time (s) | floats/material |",
             "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        eet = (f"{r['equal_error_time']:.3f}" if r["equal_error_time"] is not None
               else f"unreachable (floor {r['floor_de']:.2f})")
        lines.append(f"| {r['scene']} | {r['method']} | {r['seconds'][-1]:.3f} | {r['mean_de'][-1]:.2f} | "
                     f"{r['p95_de'][-1]:.2f} | {eet} | {r['material_floats']} |")
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({r["scene"] for r in result["rows"]})
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 4.5), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for r in (r for r in result["rows"] if r["scene"] == scene):
            ax.plot(r["seconds"], r["mean_de"], marker="o", label=r["method"])
        ax.axhline(result["target_de"], color="grey", ls="--", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("render time (s)")
        ax.set_ylabel("mean ΔE00 vs spectral reference")
        ax.set_title(scene)
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"fluo bench, {result['date']}, {result['machine']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
