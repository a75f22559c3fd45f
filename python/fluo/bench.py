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
  (log time, ΔE) between rungs; a method whose error never gets there within the ladder
  (its bias floor lies above the target) reports ∞ with that measured floor;
* ``material_bytes``: bytes the renderer holds per fluorescent material for the method
  at render time (model, tables, reduced matrices: the representation's memory).

A second table, from ``fluo-rs saturated-report`` (Rust, ``src/reduce.rs``), reports
saturated fluorescence through reduced RGB transport per basis (``rgb``, ``xyzu``,
``x7``): a pure green and a pure red emitter and a UV optical brightener under D65, A
and FL2, as the luminance ratio reduced/spectral of the patch and of its reradiated
light alone, and the patch's ΔE00. It is where the bases differ most, and what the
``basis`` advice in ``fluo_path``'s documentation rests on.

Methods are declared in :func:`methods`: how to turn a bench scene into the method's
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

from . import repo_root, run_tool
from .colour import delta_e_map

BENCH_DIR = repo_root() / "scenes" / "bench"


def _strip_reduced_params(text: str) -> str:
    return re.sub(r'\s*<string name="(basis|method)" value="[^"]*"/>', "", text)


def _to_path(text: str) -> str:
    return _strip_reduced_params(text.replace('<integrator type="fluo_path">', '<integrator type="path">'))


def _matrix_to_diffuse(text: str) -> str:
    """fluo_matrix -> diffuse with the matrix's diagonal (its elastic reflectance)."""
    from . import run_tool

    def repl(m: re.Match) -> str:
        d = run_tool(["diagonal", "--material", m.group(1)])
        values = ", ".join(f"{l:g}:{min(max(v, 0.0), 1.0):.5f}" for l, v in zip(d["wavelengths_nm"], d["values"]))
        return f'<bsdf type="diffuse"><spectrum name="reflectance" value="{values}"/></bsdf>'
    return re.sub(r'<bsdf type="fluo_matrix"><string name="filename" value="([^"]*)"/></bsdf>', repl, text)


def _remove_dyes(text: str) -> str:
    """The same materials without their fluorescent dye (concentration or density 0;
    a measured matrix keeps its diagonal)."""
    text = re.sub(r'<float name="concentration" value="[^"]*"/>', '<float name="concentration" value="0"/>', text)
    text = re.sub(r'<float name="density" value="[^"]*"/>', '<float name="density" value="0"/>', text)
    return _matrix_to_diffuse(text)


def _to_native(text: str) -> str:
    """Mitsuba's nearest native materials: diffuse for fluo_jung (same reflectance) and
    fluo_matrix (its diagonal), roughconductor for fluo_qd (same substrate and roughness)."""
    def jung(m: re.Match) -> str:
        refl = re.search(r'<rgb name="reflectance" value="[^"]*"/>', m.group(1))
        return '<bsdf type="diffuse">' + (refl.group(0) if refl else "") + "</bsdf>"

    def qd(m: re.Match) -> str:
        keep = re.findall(r'<(?:string|float) name="(?:material|alpha|distribution)" value="[^"]*"/>', m.group(1))
        return '<bsdf type="roughconductor">' + "".join(keep) + "</bsdf>"
    text = re.sub(r'<bsdf type="fluo_jung">(.*?)</bsdf>', jung, text, flags=re.S)
    text = re.sub(r'<bsdf type="fluo_qd">(.*?)</bsdf>', qd, text, flags=re.S)
    return _matrix_to_diffuse(text)


def _gmm(components: int, cache: Path) -> Callable[[str], str]:
    """fluo_matrix -> fluo_gmm of a `components`-Gaussian fit (fitted once, cached)."""
    from . import run_tool

    def rewrite(text: str) -> str:
        def repl(m: re.Match) -> str:
            src = Path(m.group(1))
            key = hashlib.sha1(f"{src.resolve()}|{src.stat().st_mtime}|{components}".encode()).hexdigest()[:10]
            fit = cache / f"{src.stem}_{components}_{key}.gmm.json"
            if not fit.exists():
                run_tool(["fit-gmm", str(src), "--components", str(components), "-o", str(fit)])
            return f'<bsdf type="fluo_gmm"><string name="filename" value="{fit}"/></bsdf>'
        return re.sub(r'<bsdf type="fluo_matrix"><string name="filename" value="([^"]*)"/></bsdf>', repl, text)
    return rewrite


def _reduced(basis: str, method: str) -> Callable[[str], str]:
    def rewrite(text: str) -> str:
        text = re.sub(r'<string name="basis" value="[^"]*"/>', f'<string name="basis" value="{basis}"/>', text)
        return re.sub(r'<string name="method" value="[^"]*"/>', f'<string name="method" value="{method}"/>', text)
    return rewrite


def _material_kinds(text: str) -> set[str]:
    return set(re.findall(r'<bsdf type="fluo_(jung|matrix|gmm|qd)"', text))


def _material_bytes(text: str) -> float:
    """Mean bytes at render time of the scene's fluorescent materials (model and tables)."""
    from . import run_tool

    sizes = []
    for m in re.finditer(r'<bsdf type="fluo_(jung|matrix|gmm|qd)">(.*?)</bsdf>', text, flags=re.S):
        kind, body = m.group(1), m.group(2)
        if kind in ("matrix", "gmm"):
            f = re.search(r'name="filename" value="([^"]*)"', body).group(1)
            sizes.append(run_tool(["memory", "--material", f])["bytes"])
        elif kind == "qd":
            r = re.search(r'<float name="radius" value="([^"]*)"/>', body)
            sizes.append(run_tool(["qd", "--radius", r.group(1) if r else "2.2"])["tables"]["bytes"])
        else:
            sizes.append(run_tool(["memory", "--material", '{"model":"jung"}'])["bytes"])
    return float(np.mean(sizes)) if sizes else 0.0


def _reduced_bytes(k: int) -> Callable[[str], float]:
    def size(text: str) -> float:
        kinds = _material_kinds(text)
        # a K×K matrix of f64 per material; angle-dependent coatings keep 17 of them
        return float(8 * k * k * (17 if kinds == {"qd"} else 1)) if kinds else 0.0
    return size


@dataclass
class Method:
    """One way of rendering a bench scene."""

    name: str
    variant: str
    rewrite: Callable[[str], str]
    #: bytes per fluorescent material at render time, given the rewritten scene
    bytes: Callable[[str], float]
    #: material kinds (before rewriting) the method applies to; None: all
    kinds: set[str] | None = None
    note: str = ""


def methods(cache: Path) -> list[Method]:
    """Every method the project offers, in table order."""
    ms = [Method("spectral, scene's own model (fluo_path)", "scalar_spectral", lambda t: t, _material_bytes)]
    ms += [Method(f"spectral GMM-{k} (fluo_path)", "scalar_spectral", _gmm(k, cache), _material_bytes, {"matrix"})
           for k in (2, 4, 8)]
    ms += [Method(f"rgb {m}-{b} (fluo_path)", "scalar_rgb", _reduced(b, m), _reduced_bytes({"rgb": 3, "xyzu": 4, "x7": 7}[b]))
           for m in ("ours", "naive") for b in ("rgb", "xyzu", "x7")]
    ms += [Method("rgb plain, no fluorescence (path)", "scalar_rgb", lambda t: _remove_dyes(_to_path(t)),
                  lambda _: 0.0, note="what a user gets today"),
           Method("spectral native path, nearest material", "scalar_spectral", lambda t: _to_native(_to_path(t)),
                  lambda _: 0.0, note="the cost floor")]
    return ms


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
    material_bytes: float = 0.0


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
    """Inline includes and substitute file-valued defaults (``$name``) with
    absolute paths, using a ``<!-- fluo: fallback name=path -->`` when the file is missing."""
    def inline(m: re.Match) -> str:
        inc = (scene_dir / m.group(1)).resolve()
        body = inc.read_text()
        body = body[body.index(">", body.index("<scene")) + 1:body.rindex("</scene>")]
        return _absolutise_includes(body, inc.parent)
    # inlined, so that rewrites reach the included integrator and materials
    text = re.sub(r'<include filename="([^"]*)"/>', inline, text)
    fallbacks = dict(re.findall(r"<!--\s*fluo:\s*fallback\s+(\w+)=(\S+)\s*-->", text))
    for name, value in re.findall(r'<default name="(\w+)" value="([^"]*[./][^"]*)"/>', text):
        path = (scene_dir / value).resolve()
        if not path.exists() and name in fallbacks:
            path = (scene_dir / fallbacks[name]).resolve()
        text = re.sub(rf'\s*<default name="{name}" value="[^"]*"/>', "", text)
        text = text.replace(f"${name}", str(path))
    return text


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
        kinds = _material_kinds(base)
        for m in methods(cache):
            if m.kinds is not None and not (m.kinds & kinds):
                continue
            text = m.rewrite(base)
            row = Row(scene_path.stem, m.name, material_bytes=m.bytes(text))
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
        "machine": _machine(),
        "quick": quick, "res": res, "ladder_spp": ladder, "ref_spp": ref_spp, "target_de": target_de,
        "rows": [r.__dict__ for r in rows],
        "saturated": run_tool(["saturated-report"])["saturated"],
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
             "| scene | method | time (s) | mean ΔE00 | p95 ΔE00 | equal-error time (s) | bytes/material |",
             "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        eet = (f"{r['equal_error_time']:.3f}" if r["equal_error_time"] is not None
               else f"∞: bias floor {r['floor_de']:.2f} > target")
        lines.append(f"| {r['scene']} | {r['method']} | {r['seconds'][-1]:.3f} | {r['mean_de'][-1]:.2f} | "
                     f"{r['p95_de'][-1]:.2f} | {eet} | {r['material_bytes']:.0f} |")
    return "\n".join(lines) + "\n" + saturated_table(result.get("saturated", []))


def saturated_table(rows: list[dict]) -> str:
    """Markdown table of ``fluo-rs saturated-report`` rows: per material and light, for
    each basis, luminance ratio of the patch / of its reradiated light, and ΔE00."""
    if not rows:
        return ""
    bases = list(dict.fromkeys(r["basis"] for r in rows))
    lines = ["", "Saturated fluorescence through reduced RGB transport (patch facing the light; "
             "luminance reduced/spectral of the patch and of its reradiated light alone, 1 is exact; ΔE00):",
             "", "| material | light | " + " | ".join(bases) + " |", "|---|---|" + "---|" * len(bases)]
    for case, light in dict.fromkeys((r["case"], r["illuminant"]) for r in rows):
        cells = []
        for b in bases:
            r = next(x for x in rows if x["case"] == case and x["illuminant"] == light and x["basis"] == b)
            ratio = lambda v: "–" if v is None else f"{v:.2f}"  # None: the spectral patch is black
            cells.append(f"{ratio(r['luminance_ratio'])} / {ratio(r['fluorescence_ratio'])} / {r['delta_e']:.1f}")
        lines.append(f"| {case} | {light} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    """Mean ΔE00 against render time along the spp ladder, one panel per scene; each
    method keeps its colour and marker across panels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({r["scene"] for r in result["rows"]})
    names = list(dict.fromkeys(r["method"] for r in result["rows"]))
    cmap = plt.get_cmap("tab20")
    style = {n: (cmap(i % 20), "osD^v<>"[i % 7]) for i, n in enumerate(names)}
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.0 * len(scenes), 4.6), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for r in (r for r in result["rows"] if r["scene"] == scene):
            colour, marker = style[r["method"]]
            ax.plot(r["seconds"], r["mean_de"], marker=marker, ms=4, color=colour, label=r["method"])
        ax.axhline(result["target_de"], color="grey", ls="--", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("render time (s)")
        ax.set_ylabel("mean ΔE00 vs spectral reference")
        ax.set_title(scene)
        ax.grid(alpha=0.3, which="both")
    handles = [plt.Line2D([], [], color=style[n][0], marker=style[n][1], label=n) for n in names]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"fluo bench, {result['date']}, {result['machine']} (spp ladder "
                 f"{result['ladder_spp'][0]}…{result['ladder_spp'][-1]}; dashed: equal-error target)", fontsize=9)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
