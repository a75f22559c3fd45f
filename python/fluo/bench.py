"""``fluo bench``: what accuracy costs in time, measured side by side in one run.

This module runs the benchmark (references, ladders, timing, the vectorised variants'
worker process); :mod:`fluo.bench_methods` says what each method renders (scene
rewrites, material bytes) and :mod:`fluo.bench_report` turns results into tables, the
README region and the plot. Their public names are re-exported here.

Every scene in ``scenes/bench/*.xml`` is rendered with every method that applies to it,
on the same machine in one process:

* a converged spectral reference (``fluo_path`` in ``scalar_spectral`` at
  ``ref_spp``), cached in ``out/cache/bench/`` with its settings (a changed scene or
  setting makes a new one);
* each method at a ladder of sample counts; at every rung the render is timed
  ``repeats`` times (default 3; the scene is loaded once, the same seed each time, so
  the images are identical and only the time varies) and the per-pixel CIEDE2000 of
  that image against the reference (linear sRGB → XYZ → L*a*b*, white: D65 at the
  reference's peak luminance) is measured.

Columns (all measured):

* ``time``: median render time at the top rung (fixed spp), with the min–max of the
  repeats (``seconds``: medians per rung; ``seconds_min``, ``seconds_max``,
  ``seconds_all``: the spread);
* ``mean_de``, ``p95_de``: mean and 95th-percentile per-pixel ΔE00 at that rung (of the
  one image all repeats produce);
* ``equal_error_time``: time to reach mean ΔE00 ≤ ``target_de``, interpolated in
  (log time, ΔE) between rungs on the median times (``equal_error_range``: the same on
  the fastest and the slowest repeat of every rung); a method whose error never gets
  there within the ladder (its bias floor lies above the target) reports ∞ with that
  measured floor;
* ``material_bytes``: bytes the renderer holds per fluorescent material for the method
  at render time (model, tables, reduced matrices: the representation's memory).

A second table, from ``fluo-rs saturated-report`` (Rust, ``core/src/reduce/``), reports
saturated fluorescence through reduced RGB transport per basis (``rgb``, ``xyzu``,
``x7``): a pure green and a pure red emitter and a UV optical brightener under D65, A
and FL2, as the luminance ratio reduced/spectral of the patch and of its reradiated
light alone, and the patch's ΔE00. It is where the bases differ most, and what the
``basis`` advice in ``fluo_path``'s documentation rests on.

Knob rows (``Method.knob``) vary one accuracy/cost setting of a model against the same
reference: ``fluo_qd``'s excitation tables (``table_cos_nodes``, ``table_step``), the
coefficient cube of ``fluo_jung``'s ``color`` (resolution 9 and 17, generated into
``out/cache/cubes/`` on first use, and ``trilinear`` lookup), and the GMM component count
of measured matrices (2/4/8).

Methods are declared in :func:`methods`: how to turn a bench scene into the method's
scene (variant, integrator, material rewrite). A method named "(fluo_path)" renders with
the scene's own fluo integrator: ``fluo_volpath`` in the scene with fluorescent media
(``qd_cuvette``), whose rows without fluorescence set the media's ``quantum_yield`` to 0
(the same absorption) under Mitsuba's ``volpath``. Rows named "llvm ..." render in the
vectorised variants (``llvm_ad_spectral``, ``llvm_ad_rgb``) on the scenes whose materials
those serve (:data:`JIT_KINDS`), and rows named "cuda ..." the same on a machine with a
CUDA GPU (Dr.Jit finds one; left out elsewhere), each method in a fresh process; their times exclude the
first render of each rung, which traces and compiles the kernels (``compile_s``: its
extra time at the lowest rung). ``scripts/bench_readme.py`` turns a
``results.json`` into the README's table and its reading (:func:`readme_region`). The table goes to stdout (Markdown),
``results.json`` and ``accuracy_vs_time.png`` to the output folder.
"""


from __future__ import annotations

import hashlib
import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import out_dir, run_tool
# The benchmark's parts, re-exported: methods (scene rewrites) and reports (tables, README).
from .bench_methods import (BENCH_DIR, JIT_KINDS, NO_FLUORESCENCE, SPECTRAL, Method,  # noqa: F401
                            _absolutise_includes, _material_kinds, cube_path, methods)
from .bench_report import (README_BEGIN, README_END, claims, display_method, plot, reading,  # noqa: F401
                           readme_region, replace_region, rows_table, saturated_table, table)
from .colour import delta_e_map

@dataclass
class Row:
    scene: str
    method: str
    spp: list[int] = field(default_factory=list)
    #: median render time per rung over the repeats, and its spread
    seconds: list[float] = field(default_factory=list)
    seconds_min: list[float] = field(default_factory=list)
    seconds_max: list[float] = field(default_factory=list)
    seconds_all: list[list[float]] = field(default_factory=list)
    mean_de: list[float] = field(default_factory=list)
    p95_de: list[float] = field(default_factory=list)
    equal_error_time: float | None = None
    #: equal-error time on the fastest and on the slowest repeat of every rung
    equal_error_range: list[float | None] = field(default_factory=lambda: [None, None])
    floor_de: float = 0.0
    material_bytes: float = 0.0
    knob: str = ""
    #: vectorised variants: the first render's time beyond a timed one (tracing and
    #: kernel compilation, excluded from ``seconds``), at the lowest rung
    compile_s: float | None = None


def _render_text(text: str, variant: str, res: int, spp: int, seed: int, cache: Path,
                 repeats: int = 1) -> tuple[np.ndarray, list[float]]:
    """Load once, render ``repeats`` times with the same seed; the first image and the
    render time of every repeat."""
    import mitsuba as mi

    mi.set_variant(variant)
    import fluo  # noqa: F401  (plugins)

    digest = hashlib.sha1(text.encode()).hexdigest()[:12]
    path = cache / f"scene_{digest}.xml"
    path.write_text(text)
    scene = mi.load_file(str(path), res=res, spp=spp)
    img, seconds = None, []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = mi.render(scene, seed=seed)
        seconds.append(time.perf_counter() - t0)
        if img is None:
            img = np.array(out, dtype=np.float64)[..., :3]
    return img, seconds


#: Material kinds (:func:`_material_kinds`) the vectorised variants serve
#: (``fluo.JIT_PLUGINS``: fluo_jung with its ``color``, fluo_matrix, fluo_gmm, fluo_qd, and
#: the fluorescent media under fluo_volpath), in llvm_ad_spectral and llvm_ad_rgb.


def _render_ladder_jit(text: str, variant: str, res: int, ladder: list[int], seed: int, cache: Path,
                       repeats: int) -> tuple[list[np.ndarray], list[list[float]], float]:
    """:func:`_render_text` at every rung of ``ladder`` in a vectorised variant, in a fresh
    process (Mitsuba 3.8 cannot start a JIT variant after a scalar render in one process):
    per rung the image and the times of ``repeats`` renders after a first one that
    compiles (evaluated and waited for inside the timing); and that first render's extra
    time at the lowest rung."""
    import subprocess
    import sys

    digest = hashlib.sha1(f"{text}|{variant}|{res}|{ladder}|{repeats}".encode()).hexdigest()[:12]
    scene = cache / f"scene_{digest}.xml"
    scene.write_text(text)
    job = cache / f"jit_{digest}.json"
    job.write_text(json.dumps({"scene": str(scene), "variant": variant, "res": res, "ladder": ladder,
                               "seed": seed, "repeats": repeats, "out": str(cache / f"jit_{digest}.npz")}))
    proc = subprocess.run([sys.executable, "-m", "fluo.bench", str(job)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"fluo bench: {variant} render failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
    done = json.loads(job.with_suffix(".done.json").read_text())
    data = np.load(done["out"])
    return [data[f"rung{i}"] for i in range(len(ladder))], done["seconds"], done["compile_s"]


def _jit_worker(job_file: str) -> None:
    """The fresh process of :func:`_render_ladder_jit`."""
    import drjit as dr
    import mitsuba as mi

    job = json.loads(Path(job_file).read_text())
    mi.set_variant(job["variant"])
    import fluo  # noqa: F401  (plugins)

    scene = mi.load_file(job["scene"], res=job["res"], spp=job["ladder"][0])

    def render(spp: int) -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        img = mi.render(scene, spp=spp, seed=job["seed"])
        dr.eval(img)
        dr.sync_thread()
        return img, time.perf_counter() - t0

    images, seconds, compile_s = {}, [], 0.0
    for i, spp in enumerate(job["ladder"]):
        first = render(spp)[1]
        times = []
        for _ in range(max(1, job["repeats"])):
            img, t = render(spp)
            times.append(t)
        images[f"rung{i}"] = np.array(img, dtype=np.float64)[..., :3]
        seconds.append(times)
        if i == 0:
            compile_s = max(0.0, first - float(np.median(times)))
    np.savez(job["out"], **images)
    Path(job_file).with_suffix(".done.json").write_text(json.dumps(
        {"out": job["out"], "seconds": seconds, "compile_s": compile_s}))


def _machine() -> str:
    """CPU model and core count (Linux /proc/cpuinfo; platform otherwise)."""
    import os
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores"


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
        target_de: float = 1.5, repeats: int = 3, log=print, *, res: int | None = None,
        ladder: list[int] | None = None, ref_spp: int | None = None) -> dict:
    """Run the benchmark; returns the results dict (also written to ``out``).

    ``quick``: 48x48, spp ladder 4…256, reference 4096 spp; full: 96x96, ladder 4…1024,
    reference 16384 spp (``res``, ``ladder``, ``ref_spp`` override either).
    """
    out = Path(out or out_dir() / "bench")
    cache = out_dir() / "cache" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    res = res or (48 if quick else 96)
    ladder = ladder or ([4, 16, 64, 256] if quick else [4, 16, 64, 256, 1024])
    ref_spp = ref_spp or (4096 if quick else 16384)
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
                {"scene": scene_path.name, "res": res, "spp": ref_spp, "seconds": t[0]}))
        kinds = _material_kinds(base)
        for m in methods(cache):
            if not m.applies(scene_path.stem, kinds):
                continue
            text = m.rewrite(base)
            row = Row(scene_path.stem, m.name, material_bytes=m.bytes(text), knob=m.knob)
            if m.variant.startswith("scalar_"):
                rendered = (_render_text(text, m.variant, res, spp, 1, cache, repeats) for spp in ladder)
            else:
                images, times, row.compile_s = _render_ladder_jit(text, m.variant, res, ladder, 1, cache, repeats)
                rendered = zip(images, times)
            for spp, (img, ts) in zip(ladder, rendered):
                de = delta_e_map(np.maximum(img, 0), np.maximum(ref, 0))
                row.spp.append(spp)
                row.seconds.append(float(np.median(ts)))
                row.seconds_min.append(min(ts))
                row.seconds_max.append(max(ts))
                row.seconds_all.append(ts)
                row.mean_de.append(float(de.mean()))
                row.p95_de.append(float(np.percentile(de, 95)))
            row.equal_error_time = equal_error_time(row.seconds, row.mean_de, target_de)
            row.equal_error_range = [equal_error_time(row.seconds_min, row.mean_de, target_de),
                                     equal_error_time(row.seconds_max, row.mean_de, target_de)]
            row.floor_de = min(row.mean_de)
            rows.append(row)
            log(f"[bench]   {m.name:48s} {row.seconds[-1]:7.2f}s "
                f"[{row.seconds_min[-1]:.2f}-{row.seconds_max[-1]:.2f}]  ΔE00 {row.mean_de[-1]:.2f}")
    result = {
        "date": time.strftime("%Y-%m-%d"),
        "machine": _machine(),
        "quick": quick, "res": res, "ladder_spp": ladder, "ref_spp": ref_spp, "target_de": target_de,
        "repeats": repeats,
        "rows": [r.__dict__ for r in rows],
        "saturated": run_tool(["saturated-report"])["saturated"],
    }
    (out / "results.json").write_text(json.dumps(result, indent=1))
    (out / "results.md").write_text(table(result))
    plot(result, out / "accuracy_vs_time.png")
    return result


if __name__ == "__main__":  # the vectorised variants' render process (_render_ladder_jit)
    import sys

    _jit_worker(sys.argv[1])
