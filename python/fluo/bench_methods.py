"""``fluo bench``'s methods: how each turns a bench scene into the scene it renders
(variant, integrator, material rewrite), which scenes it applies to, and the bytes per
material it holds (see :mod:`fluo.bench` for the benchmark itself)."""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import data_dir, out_dir, run_tool, scenes_dir
from .scenes import diffuse_bsdf, inline_includes

BENCH_DIR = scenes_dir() / "bench"
#: The method every other one is measured against, and the one a user gets today.
SPECTRAL = "spectral, scene's own model (fluo_path)"
NO_FLUORESCENCE = "rgb plain, no fluorescence (path)"


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
    ms += [Method(f"rgb {m}-{b} (fluo_path)", "scalar_rgb", _reduced(b, m),
                  _reduced_bytes({"rgb": 3, "xyzu": 4, "x7": 7, "auto": 7}[b]))
           for m in ("ours", "naive") for b in ("rgb", "xyzu", "x7", "auto") if (m, b) != ("naive", "auto")]
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
           Method("llvm rgb ours-auto (fluo_path)", "llvm_ad_rgb", _reduced("auto", "ours"), _reduced_bytes(7),
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


JIT_KINDS = {"jung", "cube", "matrix", "gmm", "qd", "medium"}


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
