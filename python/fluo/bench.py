"""``fluo bench``: what accuracy costs in time, measured side by side in one run.

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
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from . import data_dir, out_dir, run_tool, scenes_dir
from .colour import delta_e_map
from .scenes import diffuse_bsdf, inline_includes

BENCH_DIR = scenes_dir() / "bench"


def _strip_reduced_params(text: str) -> str:
    return re.sub(r'\s*<string name="(basis|method)" value="[^"]*"/>', "", text)


def _to_path(text: str) -> str:
    """Mitsuba's own integrator: path for fluo_path, volpath for fluo_volpath."""
    text = text.replace('<integrator type="fluo_path">', '<integrator type="path">')
    return _strip_reduced_params(text.replace('<integrator type="fluo_volpath">', '<integrator type="volpath">'))


MEDIUM = re.compile(r'(<medium type="fluo_(?:qd|dye)_medium"[^>]*>)(.*?)(</medium>)', flags=re.S)


def _media_without_fluorescence(text: str) -> str:
    """Fluorescent media at quantum_yield 0: the same absorption, no re-emission (their
    non-fluorescent limit, a plain absorbing medium under any integrator)."""
    def repl(m: re.Match) -> str:
        body = re.sub(r'\s*<float name="quantum_yield" value="[^"]*"/>', "", m.group(2))
        return m.group(1) + '<float name="quantum_yield" value="0"/>' + body + m.group(3)
    return MEDIUM.sub(repl, text)


def _outside_media(text: str, rewrite: Callable[[str], str]) -> str:
    """Apply ``rewrite`` to everything but the fluorescent media's definitions."""
    out, last = [], 0
    for m in MEDIUM.finditer(text):
        out += [rewrite(text[last:m.start()]), m.group(0)]
        last = m.end()
    return "".join(out + [rewrite(text[last:])])


def _matrix_to_diffuse(text: str) -> str:
    """fluo_matrix -> diffuse with the matrix's diagonal (its elastic reflectance)."""

    def repl(m: re.Match) -> str:
        d = run_tool(["diagonal", "--material", m.group(1)])
        return diffuse_bsdf(d["wavelengths_nm"], d["values"])
    return re.sub(r'<bsdf type="fluo_matrix"><string name="filename" value="([^"]*)"/></bsdf>', repl, text)


def _remove_dyes(text: str) -> str:
    """The same materials without their fluorescent dye (concentration or density 0; a
    ``color`` through the cube takes the cube's reflectance-only solution; a measured
    matrix keeps its diagonal); fluorescent media keep their absorption at yield 0."""
    def surfaces(t: str) -> str:
        t = re.sub(r'<float name="concentration" value="[^"]*"/>', '<float name="concentration" value="0"/>', t)
        t = re.sub(r'(<rgb name="color" value="[^"]*"/>)', r'\1<boolean name="fluorescence" value="false"/>', t)
        return re.sub(r'<float name="density" value="[^"]*"/>', '<float name="density" value="0"/>', t)
    return _matrix_to_diffuse(_media_without_fluorescence(_outside_media(text, surfaces)))


#: Linear ACEScg (AP1) to linear sRGB / Rec. 709 (Bradford D60 → D65), for the nearest
#: native material of a ``color`` given in ACEScg.
ACESCG_TO_SRGB = np.array([[1.70505, -0.62179, -0.08326],
                           [-0.13026, 1.14080, -0.01055],
                           [-0.02400, -0.12897, 1.15297]])


def _to_native(text: str) -> str:
    """Mitsuba's nearest native materials: diffuse for fluo_jung (same reflectance) and
    fluo_matrix (its diagonal), roughconductor for fluo_qd (same substrate and roughness)."""
    def jung(m: re.Match) -> str:
        refl = re.search(r'<rgb name="reflectance" value="[^"]*"/>', m.group(2))
        color = re.search(r'<rgb name="color" value="([^"]*)"/>', m.group(2))
        if color and not refl:
            space = re.search(r'<string name="color_space" value="([^"]*)"/>', m.group(2))
            rgb = np.array([float(v) for v in color.group(1).split(",")])
            if (space.group(1) if space else "acescg").lower() == "acescg":
                rgb = ACESCG_TO_SRGB @ rgb
            values = ", ".join(f"{v:.4f}" for v in np.clip(rgb, 0.0, 1.0))
            return f'<bsdf type="diffuse"{m.group(1) or ""}><rgb name="reflectance" value="{values}"/></bsdf>'
        return f'<bsdf type="diffuse"{m.group(1) or ""}>' + (refl.group(0) if refl else "") + "</bsdf>"

    def qd(m: re.Match) -> str:
        keep = re.findall(r'<(?:string|float) name="(?:material|alpha|distribution)" value="[^"]*"/>', m.group(2))
        return f'<bsdf type="roughconductor"{m.group(1) or ""}>' + "".join(keep) + "</bsdf>"
    text = re.sub(r'<bsdf type="fluo_jung"( id="[^"]*")?>(.*?)</bsdf>', jung, text, flags=re.S)
    text = re.sub(r'<bsdf type="fluo_qd"( id="[^"]*")?>(.*?)</bsdf>', qd, text, flags=re.S)
    return _media_without_fluorescence(_matrix_to_diffuse(text))


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


def _qd_knob(name: str, value: str) -> Callable[[str], str]:
    """Every fluo_qd with ``name`` (an excitation-table knob) set to ``value``."""
    kind = "integer" if name == "table_cos_nodes" else "float"

    def rewrite(text: str) -> str:
        return re.sub(r'(<bsdf type="fluo_qd"[^>]*>)', rf'\1<{kind} name="{name}" value="{value}"/>', text)
    return rewrite


def cube_path(res: int, space: str = "acescg") -> Path:
    """A coefficient cube of resolution ``res``: the shipped one for 33, else generated
    once (threshold ∞, like the shipped ones) into ``out/cache/cubes/``."""
    shipped = data_dir("cubes") / f"{space}_d65_tinf_r{res}.cube"
    if shipped.exists():
        return shipped
    path = out_dir() / "cache" / "cubes" / f"{space}_d65_tinf_r{res}.cube"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        run_tool(["upsample-cube", "--space", space, "--res", res, "--threshold", "inf", "-o", path])
    return path


def _cube_knob(res: int, lookup: str = "nearest") -> Callable[[str], str]:
    """Every fluo_jung ``color`` through the cube of resolution ``res`` with ``lookup``."""
    def rewrite(text: str) -> str:
        cube = cube_path(res)
        return re.sub(r'(<rgb name="color" value="[^"]*"/>)',
                      rf'\1<string name="cube" value="{cube}"/><string name="lookup" value="{lookup}"/>', text)
    return rewrite


def _reduced(basis: str, method: str) -> Callable[[str], str]:
    def rewrite(text: str) -> str:
        text = re.sub(r'<string name="basis" value="[^"]*"/>', f'<string name="basis" value="{basis}"/>', text)
        return re.sub(r'<string name="method" value="[^"]*"/>', f'<string name="method" value="{method}"/>', text)
    return rewrite


def _material_kinds(text: str) -> set[str]:
    """Fluorescent material kinds of a scene; ``cube`` when a fluo_jung takes a ``color``;
    ``medium`` for fluorescent participating media."""
    kinds = set(re.findall(r'<bsdf type="fluo_(jung|matrix|gmm|qd)"', text))
    if MEDIUM.search(text):
        kinds.add("medium")
    if re.search(r'<bsdf type="fluo_jung"[^>]*>(?:(?!</bsdf>).)*name="color"', text, flags=re.S):
        kinds.add("cube")
    return kinds


def _material_bytes(text: str) -> float:
    """Mean bytes at render time of the scene's fluorescent materials (model and tables)."""
    from . import run_tool

    sizes = []
    for m in re.finditer(r'<bsdf type="fluo_(jung|matrix|gmm|qd)"(?: id="[^"]*")?>(.*?)</bsdf>', text, flags=re.S):
        kind, body = m.group(1), m.group(2)
        if kind in ("matrix", "gmm"):
            f = re.search(r'name="filename" value="([^"]*)"', body).group(1)
            sizes.append(run_tool(["memory", "--material", f])["bytes"])
        elif kind == "qd":
            r = re.search(r'<float name="radius" value="([^"]*)"/>', body)
            args = ["qd", "--radius", r.group(1) if r else "2.2"]
            for name in ("table_cos_nodes", "table_step"):
                k = re.search(rf'name="{name}" value="([^"]*)"', body)
                if k:
                    args += [f"--{name.replace('_', '-')}", k.group(1)]
            sizes.append(run_tool(args)["tables"]["bytes"])
        elif "name=\"color\"" in body:
            # the model plus the coefficient cube it looks colours up in (shared by all
            # materials of a colour space; counted whole, once per material)
            cube = re.search(r'<string name="cube" value="([^"]*)"/>', body)
            path = Path(cube.group(1)) if cube else data_dir("cubes") / "acescg_d65_tinf_r33.cube"
            sizes.append(run_tool(["memory", "--material", '{"model":"jung"}'])["bytes"] + path.stat().st_size)
        else:
            sizes.append(run_tool(["memory", "--material", '{"model":"jung"}'])["bytes"])
    for m in MEDIUM.finditer(text):
        if 'fluo_qd_medium' in m.group(1):
            args = ["qd-medium"]
            for name in ("radius", "width", "concentration"):
                v = re.search(rf'<float name="{name}" value="([^"]*)"/>', m.group(2))
                if v:
                    args += [f"--{name}", v.group(1)]
            sizes.append(run_tool(args)["bytes"])
    return float(np.mean(sizes)) if sizes else 0.0


def _reduced_bytes(k: int) -> Callable[[str], float]:
    def size(text: str) -> float:
        kinds = _material_kinds(text)
        # a K×K matrix of f64 per material; angle-dependent coatings keep 17 of them,
        # media two (absorption and reradiation)
        per = {"qd": 17, "medium": 2}.get(next(iter(kinds)), 1) if len(kinds) == 1 else 1
        return float(8 * k * k * per) if kinds else 0.0
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
    #: the accuracy/cost knob the row varies ("" for the methods themselves)
    knob: str = ""
    #: scene stems the method is restricted to; None: every scene it applies to
    scenes: set[str] | None = None
    #: material kinds the method can render at all (the vectorised variants serve fewer
    #: plugins): a scene with any other kind is skipped; None: every kind
    serves: set[str] | None = None

    def applies(self, scene: str, kinds: set[str]) -> bool:
        return ((self.kinds is None or bool(self.kinds & kinds))
                and (self.scenes is None or scene in self.scenes)
                and (self.serves is None or kinds <= self.serves))


def methods(cache: Path) -> list[Method]:
    """Every method the project offers, in table order."""
    ms = [Method("spectral, scene's own model (fluo_path)", "scalar_spectral", lambda t: t, _material_bytes)]
    ms += [Method(f"spectral GMM-{k} (fluo_path)", "scalar_spectral", _gmm(k, cache), _material_bytes, {"matrix"},
                  knob="GMM components")
           for k in (2, 4, 8)]
    # excitation tables of fluo_qd (defaults: 33 rows in cos θ, 1 nm base step), on the
    # blacklight scene, where the coatings are excited hardest
    ms += [Method(f"spectral, fluo_qd {name}={value} (fluo_path)", "scalar_spectral", _qd_knob(name, value),
                  _material_bytes, {"qd"}, knob="QD tables", scenes={"blacklight_box"})
           for name, value in (("table_cos_nodes", "2"), ("table_cos_nodes", "5"), ("table_cos_nodes", "129"),
                               ("table_step", "10"), ("table_step", "0.25"))]
    # coefficient cube of fluo_jung's `color` (shipped: 33³, nearest)
    ms += [Method(f"spectral, color cube {res}³ {lookup} (fluo_path)", "scalar_spectral", _cube_knob(res, lookup),
                  _material_bytes, {"cube"}, knob="cube resolution")
           for res, lookup in ((9, "nearest"), (17, "nearest"), (33, "trilinear"))]
    ms += [Method(f"rgb {m}-{b} (fluo_path)", "scalar_rgb", _reduced(b, m), _reduced_bytes({"rgb": 3, "xyzu": 4, "x7": 7}[b]))
           for m in ("ours", "naive") for b in ("rgb", "xyzu", "x7")]
    ms += [Method("rgb plain, no fluorescence (path)", "scalar_rgb", lambda t: _remove_dyes(_to_path(t)),
                  lambda _: 0.0, note="what a user gets today"),
           Method("spectral native path, nearest material", "scalar_spectral", lambda t: _to_native(_to_path(t)),
                  lambda _: 0.0, note="the cost floor")]
    # The vectorised variants, on the scenes whose materials they serve (each in its own
    # process, timed after a first render that compiles the kernels).
    ms += [Method(f"llvm {SPECTRAL}", "llvm_ad_spectral", lambda t: t, _material_bytes, serves=JIT_KINDS),
           Method("llvm spectral GMM-8 (fluo_path)", "llvm_ad_spectral", _gmm(8, cache), _material_bytes,
                  {"matrix"}, serves=JIT_KINDS),
           Method("llvm rgb ours-x7 (fluo_path)", "llvm_ad_rgb", _reduced("x7", "ours"), _reduced_bytes(7),
                  serves=JIT_KINDS),
           Method("llvm spectral native path, nearest material", "llvm_ad_spectral",
                  lambda t: _to_native(_to_path(t)), lambda _: 0.0, serves=JIT_KINDS, note="llvm's cost floor")]
    # The same shims on Dr.Jit's CUDA backend, where this machine has a GPU (CI has none).
    if _cuda_available():
        ms += [Method(f"cuda {SPECTRAL}", "cuda_ad_spectral", lambda t: t, _material_bytes, serves=JIT_KINDS),
               Method("cuda rgb ours-x7 (fluo_path)", "cuda_ad_rgb", _reduced("x7", "ours"), _reduced_bytes(7),
                      serves=JIT_KINDS),
               Method("cuda spectral native path, nearest material", "cuda_ad_spectral",
                      lambda t: _to_native(_to_path(t)), lambda _: 0.0, serves=JIT_KINDS, note="cuda's cost floor")]
    return ms


def _cuda_available() -> bool:
    """Whether Dr.Jit finds a CUDA device here (the "cuda ..." methods run only then)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # noqa: BLE001  (no CUDA driver: no cuda rows)
        return False


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
JIT_KINDS = {"jung", "cube", "matrix", "gmm", "qd", "medium"}


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


def _absolutise_includes(text: str, scene_dir: Path) -> str:
    """Inline includes and substitute file-valued defaults (``$name``) with
    absolute paths, using a ``<!-- fluo: fallback name=path -->`` when the file is missing."""
    # inlined, so that rewrites reach the included integrator and materials
    text = inline_includes(text, scene_dir)
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


SPECTRAL = "spectral, scene's own model (fluo_path)"
NO_FLUORESCENCE = "rgb plain, no fluorescence (path)"
README_BEGIN = "<!-- bench:begin (generated by scripts/bench_readme.py from docs/bench/results.json; do not edit) -->"
README_END = "<!-- bench:end -->"


def _eet(r: dict) -> str:
    if r["equal_error_time"] is None:
        return f"∞: bias floor {r['floor_de']:.2f} > target"
    lo, hi = r.get("equal_error_range", [None, None])
    spread = (f" [{lo:.3f}–{hi:.3f}]" if lo is not None and hi is not None else "")
    return f"{r['equal_error_time']:.3f}{spread}"


def _time(r: dict) -> str:
    lo, hi = r.get("seconds_min"), r.get("seconds_max")
    return f"{r['seconds'][-1]:.3f}" + (f" [{lo[-1]:.3f}–{hi[-1]:.3f}]" if lo and hi else "")


def header(result: dict) -> str:
    return (f"fluo bench ({'quick' if result['quick'] else 'full'}), {result['date']}, {result['machine']}; "
            f"{result['res']}x{result['res']}, time and ΔE00 at {result['ladder_spp'][-1]} spp, "
            f"reference {result['ref_spp']} spp, equal-error target mean ΔE00 ≤ {result['target_de']}; "
            f"times: median [min–max] of {result.get('repeats', 1)} renders per rung, ΔE00 of their "
            f"(identical, same seed) image")


def _volumetric(scene: str) -> bool:
    """Whether the bench scene renders with fluo_volpath (fluorescent media)."""
    path = BENCH_DIR / f"{scene}.xml"
    return path.is_file() and 'type="fluo_volpath"' in path.read_text()


def display_method(r: dict) -> str:
    """A row's method as tables show it: the integrator it really rendered with
    (``fluo_volpath``/``volpath`` on the scenes with media, where a method's name says
    ``fluo_path``/``path``)."""
    name = r["method"]
    if _volumetric(r["scene"]):
        name = name.replace("(fluo_path)", "(fluo_volpath)").replace("(path)", "(volpath)")
        name = name.replace("native path,", "native volpath,")
    return name


def rows_table(rows: list[dict], knob: bool = False) -> str:
    """Markdown table of bench rows (``knob``: with the knob's name as first column)."""
    head = ("| knob | " if knob else "| ") + ("scene | method | time (s) | mean ΔE00 | p95 ΔE00 | "
                                              "equal-error time (s) | bytes/material |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(("| " + r.get("knob", "") + " " if knob else "") +
                     f"| {r['scene']} | {display_method(r)} | {_time(r)} | {r['mean_de'][-1]:.2f} | "
                     f"{r['p95_de'][-1]:.2f} | {_eet(r)} | {r['material_bytes']:.0f} |")
    return "\n".join(lines) + "\n"


def _split(result: dict) -> tuple[list[dict], list[dict]]:
    """(method rows, knob rows); the GMM rows are both a method and a knob: kept with the
    methods and not repeated."""
    rows = result["rows"]
    knobs = [r for r in rows if r.get("knob") and not r["method"].startswith("spectral GMM")]
    return [r for r in rows if r not in knobs], knobs


def table(result: dict) -> str:
    methods_rows, knob_rows = _split(result)
    text = header(result) + "\n\n" + rows_table(methods_rows)
    if knob_rows:
        text += "\nAccuracy/cost knobs (same reference; compare with the scene's own-model row above):\n\n"
        text += rows_table(knob_rows, knob=True)
    return text + saturated_table(result.get("saturated", []))


def _range(values: list[float], fmt: str = "{:.1f}", unit: str = "") -> str:
    lo, hi = fmt.format(min(values)), fmt.format(max(values))
    return f"{lo}{unit}" if lo == hi else f"{lo}–{hi}{unit}"


def claims(result: dict) -> dict:
    """Every number the README's reading states, computed from ``result``."""
    methods_rows, knob_rows = _split(result)
    scenes = list(dict.fromkeys(r["scene"] for r in result["rows"]))
    spectral = {r["scene"]: r for r in methods_rows if r["method"] == SPECTRAL}
    ours = [r for r in methods_rows if r["method"].startswith("rgb ours-")]
    ratios, ratio_cases, ours_missing = [], [], []
    for r in ours:
        s = spectral.get(r["scene"])
        if r["equal_error_time"] is None:
            ours_missing.append((r["method"], r["scene"]))
        elif s is not None and s["equal_error_time"] is not None:
            ratios.append(s["equal_error_time"] / r["equal_error_time"])
            ratio_cases.append(f"{r['method'].split()[1]} on {r['scene']}")
    # scenes where spectral rendering itself stays above the target: compare at the top rung
    unconverged = {sc: {"spectral": s["mean_de"][-1],
                        "ours": [r["mean_de"][-1] for r in ours if r["scene"] == sc]}
                   for sc, s in spectral.items() if s["equal_error_time"] is None}
    others = [r for r in methods_rows if r["method"].startswith("rgb naive-") or
              r["method"] in (NO_FLUORESCENCE, "spectral native path, nearest material")]
    never = [r for r in others if r["equal_error_time"] is None]
    reach = [r for r in others if r["equal_error_time"] is not None]
    no_fluo = {r["scene"]: r["mean_de"][-1] for r in methods_rows if r["method"] == NO_FLUORESCENCE}
    gmm_time, gmm_mem = [], []
    for r in methods_rows:
        s = spectral.get(r["scene"])
        if r["method"].startswith("spectral GMM") and s and r["material_bytes"] > 0:
            gmm_time.append(r["seconds"][-1] / s["seconds"][-1])
            gmm_mem.append(s["material_bytes"] / r["material_bytes"])
    spreads = [(r["seconds_max"][-1] - r["seconds_min"][-1]) / r["seconds"][-1]
               for r in result["rows"] if r.get("seconds_max") and r["seconds"][-1] > 0]
    knobs = []
    for r in knob_rows:
        s = spectral.get(r["scene"])
        knobs.append({"knob": r["knob"], "scene": r["scene"], "method": r["method"],
                      "mean_de": r["mean_de"][-1], "own_mean_de": s["mean_de"][-1] if s else None,
                      "time_ratio": r["seconds"][-1] / s["seconds"][-1] if s else None,
                      "bytes": r["material_bytes"], "own_bytes": s["material_bytes"] if s else None,
                      "reaches": r["equal_error_time"] is not None})
    # the vectorised variants against the scalar ones, same method, same scene
    llvm = []
    for jit_name, scalar_name in ((f"llvm {SPECTRAL}", SPECTRAL), ("llvm rgb ours-x7 (fluo_path)",
                                                                   "rgb ours-x7 (fluo_path)")):
        scalar_rows = {r["scene"]: r for r in methods_rows if r["method"] == scalar_name}
        for r in methods_rows:
            s = scalar_rows.get(r["scene"])
            if r["method"] == jit_name and s is not None:
                a, b = s["equal_error_time"], r["equal_error_time"]
                llvm.append({"method": jit_name, "scene": r["scene"],
                             "eet_ratio": a / b if a is not None and b is not None else None,
                             "time_ratio": s["seconds"][-1] / r["seconds"][-1],
                             "compile_s": r.get("compile_s")})
    return {"scenes": scenes, "target": result["target_de"], "repeats": result.get("repeats", 1), "llvm": llvm,
            "ratios": ratios, "ratio_cases": ratio_cases, "ours_cases": len(ours), "ours_missing": ours_missing,
            "unconverged": unconverged,
            "ours_floors": [r["floor_de"] for r in ours],
            "never": [(r["method"], r["scene"], r["floor_de"]) for r in never],
            "reach": [(r["method"], r["scene"], r["equal_error_time"]) for r in reach],
            "no_fluorescence": no_fluo, "gmm_time": gmm_time, "gmm_mem": gmm_mem,
            "spreads": spreads, "knobs": knobs}


def _short(method: str) -> str:
    return {NO_FLUORESCENCE: "plain RGB", "spectral native path, nearest material": "native"}.get(
        method, method.replace(" (fluo_path)", "").replace("rgb ", ""))


def _by_scene(items: list[tuple[str, str]]) -> str:
    """"a, b on s1; c on s2" from (method, scene) pairs, scenes in first-seen order."""
    groups: dict[str, list[str]] = {}
    for method, scene in items:
        groups.setdefault(scene, []).append(_short(method))
    return "; ".join(f"{', '.join(ms)} on {sc}" for sc, ms in groups.items())


def reading(result: dict) -> str:
    """The README's one-paragraph reading of ``result``: every number from :func:`claims`."""
    c = claims(result)
    t = c["target"]
    out = ["Reading it (generated from the results above by `scripts/bench_readme.py`):"]
    if c["ratios"]:
        n = len(c["ratios"])
        faster = [x for x in c["ratios"] if x > 1.0]
        slower = [(x, case) for x, case in zip(c["ratios"], c["ratio_cases"]) if x <= 1.0]
        sent = (f"where both reach the target (mean ΔE00 ≤ {t:g}), reduced RGB transport with the dual "
                f"basis (`ours`) gets there sooner than spectral rendering in {len(faster)} of {n} "
                f"scene × basis cases")
        if faster:
            sent += f" ({_range(faster)}× sooner)"
        if slower:
            sent += ", not sooner in " + ", ".join(f"{case} ({x:.2f}×)" for x, case in slower)
        out.append(sent + f"; spectral / ours equal-error time ranges over {_range(c['ratios'])}×.")
    if c["unconverged"]:
        out.append("Spectral rendering itself stays above the target within the ladder on "
                   + "; ".join(f"{sc} (mean ΔE00 {u['spectral']:.2f} at the top rung, `ours` "
                               f"{_range(u['ours'], '{:.2f}')})" for sc, u in c["unconverged"].items())
                   + ".")
    if c["ours_missing"]:
        out.append(f"`ours` never reaches the target for {_by_scene(c['ours_missing'])}.")
    if c["ours_floors"]:
        out.append(f"`ours` floors (lowest mean ΔE00 along the ladder): {_range(c['ours_floors'], '{:.2f}')}.")
    if c["never"]:
        out.append(f"{len(c['never'])} rows of the naive reduction, plain RGB and the native materials never "
                   f"reach the target within the ladder (floors {_range([f for *_, f in c['never']], '{:.2f}')}: "
                   + _by_scene([(m, s) for m, s, _ in c["never"]]) + ")"
                   + (f"; {len(c['reach'])} do reach it: "
                      + ", ".join(f"{_short(m)} on {s} ({e:.2f} s)" for m, s, e in c["reach"])
                      if c["reach"] else "") + ".")
    elif c["reach"]:
        out.append("Every row of the naive reduction, plain RGB and the native materials reaches the target.")
    if c["no_fluorescence"]:
        out.append("Removing the dyes (plain RGB, what a user gets today) costs a mean ΔE00 of "
                   + ", ".join(f"{v:.2f} on {s}" for s, v in c["no_fluorescence"].items()) + ".")
    if c["gmm_time"]:
        out.append(f"GMM fits take {_range(c['gmm_time'], '{:.2f}')}× the tabulated matrix's time for "
                   f"{_range(c['gmm_mem'], '{:.0f}')}× less memory.")
    by_knob: dict[str, list[dict]] = {}
    for k in c["knobs"]:
        by_knob.setdefault(k["knob"], []).append(k)
    for name, ks in by_knob.items():
        own = ks[0]["own_mean_de"]
        change = max(abs(k["mean_de"] - own) for k in ks)
        out.append(f"Knob {name} on {', '.join(dict.fromkeys(k['scene'] for k in ks))} (own model: "
                   f"mean ΔE00 {own:.2f}; largest change {change:.2f}): "
                   + "; ".join(f"{_short(k['method']).replace('spectral, ', '')}: ΔE00 {k['mean_de']:.2f}, "
                               f"{k['time_ratio']:.2f}× the time, {k['bytes']:.0f} B"
                               for k in ks) + ".")
    if c["llvm"]:
        for name, variant in ((f"llvm {SPECTRAL}", "llvm_ad_spectral"), ("llvm rgb ours-x7 (fluo_path)",
                                                                          "llvm_ad_rgb")):
            ls = [x for x in c["llvm"] if x["method"] == name]
            if not ls:
                continue
            eet = [x["eet_ratio"] for x in ls if x["eet_ratio"] is not None]
            out.append(f"In `{variant}` {_short(name.replace('llvm ', '')).replace('spectral, ', '')} renders the "
                       f"top rung {_range([x['time_ratio'] for x in ls], '{:.2f}')}× as fast as the scalar "
                       f"variant on {', '.join(x['scene'] for x in ls)}"
                       + (f" (equal-error time {_range(eet, '{:.2f}')}× shorter)" if eet else "")
                       + "; kernel compilation, excluded from those times, takes "
                       + _range([x["compile_s"] or 0.0 for x in ls], "{:.1f}", " s") + ".")
    if c["spreads"]:
        sp = sorted(c["spreads"])
        out.append(f"Times are medians of {c['repeats']} renders; at the top rung the spread (max − min) / "
                   f"median is {100 * sp[len(sp) // 2]:.0f} % in the median row and up to "
                   f"{100 * sp[-1]:.0f} % (a shared machine).")
    return " ".join(out) + "\n"


def readme_region(result: dict, image: str = "docs/bench/accuracy_vs_time.png") -> str:
    """The README's generated region (markers included): header, tables, plot, reading."""
    methods_rows, knob_rows = _split(result)
    parts = [README_BEGIN, "", header(result), "", rows_table(methods_rows).rstrip()]
    if knob_rows:
        parts += ["", "Accuracy/cost knobs (same reference; compare with the scene's own-model row above):", "",
                  rows_table(knob_rows, knob=True).rstrip()]
    parts += ["", f"![accuracy against time]({image})", "", reading(result).rstrip(), "", README_END]
    return "\n".join(parts) + "\n"


def replace_region(readme: str, region: str) -> str:
    """``readme`` with the text between the bench markers replaced by ``region``."""
    start = readme.find("<!-- bench:begin")
    end = readme.find(README_END)
    if start < 0 or end < 0 or end < start:
        raise ValueError("README has no <!-- bench:begin ... --> … <!-- bench:end --> region")
    rest = readme[end + len(README_END):]
    return readme[:start] + region + (rest[1:] if rest.startswith("\n") else rest)


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

    rows, _ = _split(result)  # knob rows: in the tables only
    scenes = sorted({r["scene"] for r in rows})
    names = list(dict.fromkeys(r["method"] for r in rows))
    cmap = plt.get_cmap("tab20")
    style = {n: (cmap(i % 20), "osD^v<>"[i % 7]) for i, n in enumerate(names)}
    ncols = min(3, len(scenes))
    nrows = -(-len(scenes) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6.0 * ncols, 4.6 * nrows + 1.0), squeeze=False)
    for ax in axes.flat[len(scenes):]:
        ax.set_visible(False)
    for ax, scene in zip(axes.flat, scenes):
        for r in (r for r in rows if r["scene"] == scene):
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
    fig.tight_layout(rect=(0, 0.9 / (4.6 * nrows + 1.0) + 0.05, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":  # the vectorised variants' render process (_render_ladder_jit)
    import sys

    _jit_worker(sys.argv[1])
