"""Scene files as text: resolve them to one self-contained XML and rewrite materials.

The demo gallery (:mod:`fluo.gallery`) renders each ``scenes/*.xml`` three ways from
one resolved text, so that every panel sees exactly the same objects:

* :func:`resolve` inlines ``<include>`` files (so that rewrites reach the included
  materials and integrator) and substitutes the scene's ``$name`` parameters (the
  caller's values over the ``<default>`` tags, which are then dropped). Relative file
  names stay relative to the scene's folder: load the text with :func:`load`, which puts
  that folder first on Mitsuba's file resolver.
* :func:`without_fluorescence` keeps every material's elastic (non-fluorescent) part
  and drops its reradiation, model by model:

  ================ ========================================================================
  material         without fluorescence
  ================ ========================================================================
  ``fluo_jung``    ``quantum_yield`` 0 (replacing a float or a texture): the dye still
                   absorbs, (1 − c a(λ)) r(λ), but re-emits nothing (Jung et al. 2018,
                   eq. 1 without its second term)
  ``fluo_jung`` +  ``fluorescence`` false: the coefficient cube's reflectance-only
  ``color``        solution for the same colour (the cube sets Q, so it cannot be zeroed)
  ``fluo_qd``      ``quantum_yield`` 0: the coating still absorbs and reflects (R_tot),
                   the dots emit nothing (Benamira & Pattanaik 2023, eq. 28, Q = 0)
  ``fluo_matrix``  ``diffuse`` with the matrix's diagonal ρ(λ) (``fluo-rs diagonal``)
  ``fluo_gmm``     ``diffuse`` with the fit file's stored measured diagonal ρ(λ)
  ``fluo_qd_medium`` ``quantum_yield`` 0: the dots (dye) still absorb and the host
  ``fluo_dye_medium`` scatters, nothing is re-emitted (participating media, ``<medium>``)
  ================ ========================================================================

  The result has no fluorescent material left that re-emits, so ``fluo_path`` runs
  Mitsuba's plain ``path`` code on it; the difference to the original is exactly the
  reradiated light.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from . import PLUGIN_KINDS

#: Variants ``fluo demo`` renders every scene in (the gallery's columns).
VARIANTS = ("scalar_spectral", "scalar_rgb")

_VARIANTS_COMMENT = re.compile(r"<!--\s*fluo:\s*variants\s*=\s*([^>]*?)\s*-->")
_FALLBACK_COMMENT = re.compile(r"<!--\s*fluo:\s*fallback\s+([A-Za-z_][\w]*)\s*=\s*([^>]*?)\s*-->")
_DEFAULT_TAG = re.compile(r'<default\s+name="([^"]+)"\s+value="([^"]*)"\s*/>')


def scene_variants(scene: Path) -> tuple[str, ...]:
    """Variants ``demo`` renders ``scene`` in: all of :data:`VARIANTS`, unless a
    ``<!-- fluo: variants=a,b -->`` comment restricts them."""
    match = _VARIANTS_COMMENT.search(scene.read_text(encoding="utf-8"))
    if match is None:
        return VARIANTS
    wanted = {name.strip() for name in match.group(1).split(",") if name.strip()}
    unknown = wanted - set(VARIANTS)
    if unknown:
        print(f"fluo demo: {scene.name}: ignoring unknown variants {sorted(unknown)}",
              file=sys.stderr)
    return tuple(v for v in VARIANTS if v in wanted)


def scene_fallback_params(scene: Path, force: bool = False) -> dict[str, str]:
    """Parameters replacing a scene's missing data files (``<!-- fluo: fallback K=PATH -->``).

    For each fallback whose ``<default name="K">`` file (relative to the scene) does not
    exist, or for every fallback with ``force``: ``K`` -> ``PATH`` resolved against the
    scene's directory.
    """
    text = scene.read_text(encoding="utf-8")
    defaults = dict(_DEFAULT_TAG.findall(text))
    params: dict[str, str] = {}
    for key, path in _FALLBACK_COMMENT.findall(text):
        default = defaults.get(key)
        if force or default is None or not (scene.parent / default).exists():
            params[key] = str((scene.parent / path).resolve())
    return params

#: Names of fluo's fluorescent BSDF plugins (``type="..."`` in XML): every BSDF the
#: plugin library registers.
FLUORESCENT_BSDFS = tuple(name for name, kind in PLUGIN_KINDS.items() if kind == "bsdf")
#: Names of fluo's fluorescent participating media (``<medium type="...">``).
FLUORESCENT_MEDIA = tuple(name for name, kind in PLUGIN_KINDS.items() if kind == "medium")

_INCLUDE = re.compile(r'<include\s+filename="([^"]*)"\s*/>')
_DEFAULT = re.compile(r'\s*<default\s+name="([^"]+)"\s+value="([^"]*)"\s*/>')
_PARAM = re.compile(r"\$([A-Za-z_]\w*)")
_BSDF = re.compile(r'<bsdf\s+type="(' + "|".join(FLUORESCENT_BSDFS) + r')"\s*>(.*?)</bsdf>', re.S)
_MEDIUM = re.compile(r'<medium\s+type="(' + "|".join(FLUORESCENT_MEDIA or ("(?!)",)) + r')"([^>]*)>(.*?)</medium>',
                     re.S)
_FILENAME = re.compile(r'<string\s+name="filename"\s+value="([^"]*)"\s*/>')
#: A float ``quantum_yield`` or a textured one (a texture without nested textures).
_QUANTUM_YIELD = re.compile(r'<float\s+name="quantum_yield"\s+value="[^"]*"\s*/>'
                            r'|<texture\s+type="[^"]*"\s+name="quantum_yield"\s*>(?:(?!<texture).)*?</texture>', re.S)
_FLUORESCENCE = re.compile(r'<boolean\s+name="fluorescence"\s+value="[^"]*"\s*/>')
_COLOR = re.compile(r'name="color"')


def _scene_body(text: str) -> str:
    """What lies between ``<scene ...>`` and ``</scene>`` (an included file's content)."""
    start = text.index(">", text.index("<scene")) + 1
    return text[start:text.rindex("</scene>")]


def inline_includes(text: str, scene_dir: Path) -> str:
    """``text`` with every ``<include filename="F"/>`` replaced by F's scene body,
    recursively (F relative to ``scene_dir``, as Mitsuba resolves it)."""
    def inline(m: re.Match) -> str:
        path = (scene_dir / m.group(1)).resolve()
        return inline_includes(_scene_body(path.read_text(encoding="utf-8")), path.parent)
    return _INCLUDE.sub(inline, text)


def resolve(scene: Path, params: dict | None = None) -> str:
    """The scene as one XML text: includes inlined, ``$name`` substituted.

    ``params`` override the scene's ``<default>`` values; a parameter the scene does
    not use is ignored (unlike ``mi.load_file``, which refuses it), so one ``res`` can
    be passed to every scene. A ``$name`` with neither a value nor a default is left
    for Mitsuba to report."""
    text = inline_includes(scene.read_text(encoding="utf-8"), scene.parent)
    values = {name: value for name, value in _DEFAULT.findall(text)}
    values.update({k: str(v) for k, v in (params or {}).items()})
    text = _DEFAULT.sub("", text)
    return _PARAM.sub(lambda m: values.get(m.group(1), m.group(0)), text)


def fluorescent_materials(text: str) -> list[str]:
    """Plugin names of the fluorescent BSDFs and then media in ``text``, each in order
    of appearance."""
    return [m.group(1) for m in _BSDF.finditer(text)] + [m.group(1) for m in _MEDIUM.finditer(text)]


def diffuse_bsdf(wavelengths, values) -> str:
    """A ``diffuse`` BSDF with a tabulated reflectance, clamped to [0, 1]."""
    pairs = ", ".join(f"{l:g}:{min(max(float(v), 0.0), 1.0):.5f}" for l, v in zip(wavelengths, values))
    return f'<bsdf type="diffuse"><spectrum name="reflectance" value="{pairs}"/></bsdf>'


def _set_float(body: str, pattern: re.Pattern, tag: str) -> str:
    """``body`` with ``tag`` replacing the element ``pattern`` matches, or added first."""
    return pattern.sub(tag, body) if pattern.search(body) else tag + body


def without_fluorescence(text: str, scene_dir: Path) -> str:
    """``text`` (a :func:`resolve`\\ d scene) with every fluorescent material's
    reradiation removed and its elastic part kept (table in the module docs).

    ``scene_dir`` resolves relative matrix file names. Raises ``OSError`` or
    ``RuntimeError`` when a matrix's diagonal cannot be read."""
    from . import run_tool

    def rewrite(m: re.Match) -> str:
        kind, body = m.group(1), m.group(2)
        if kind in ("fluo_matrix", "fluo_gmm"):
            found = _FILENAME.search(body)
            if found is None:  # filename0..N selected by an index texture
                raise RuntimeError(f"{kind} with several files (filename0..N and an index texture): removing "
                                   "its fluorescence is supported for one file per material only")
            name = found.group(1)
            path = Path(name) if Path(name).is_absolute() else (scene_dir / name).resolve()
            if kind == "fluo_gmm":
                diagonal = json.loads(path.read_text(encoding="utf-8"))["diagonal"]
            else:
                diagonal = run_tool(["diagonal", "--material", str(path)])
            return diffuse_bsdf(diagonal["wavelengths_nm"], diagonal["values"])
        if kind == "fluo_jung" and _COLOR.search(body):
            body = _set_float(body, _FLUORESCENCE, '<boolean name="fluorescence" value="false"/>')
        else:
            body = _set_float(body, _QUANTUM_YIELD, '<float name="quantum_yield" value="0"/>')
        return f'<bsdf type="{kind}">{body}</bsdf>'

    def rewrite_medium(m: re.Match) -> str:
        kind, attributes, body = m.group(1), m.group(2), m.group(3)
        body = _set_float(body, _QUANTUM_YIELD, '<float name="quantum_yield" value="0"/>')
        return f'<medium type="{kind}"{attributes}>{body}</medium>'

    return _MEDIUM.sub(rewrite_medium, _BSDF.sub(rewrite, text))


def load(text: str, scene_dir: Path):
    """``mi.load_string(text)`` with ``scene_dir`` first on the file resolver (relative
    file names in a resolved scene stay relative to its file); the resolver is restored
    afterwards. The Mitsuba variant must be set."""
    import mitsuba as mi

    previous = mi.file_resolver()
    resolver = mi.FileResolver(previous)
    resolver.prepend(str(scene_dir))
    mi.set_file_resolver(resolver)
    try:
        return mi.load_string(text)
    finally:
        mi.set_file_resolver(previous)
