"""Shared fixtures for the Python/Mitsuba tests.

Nothing is skipped: if ``libfluo_mitsuba.so`` is missing or fails to load, every test errors
with the loader's message (run ``bash scripts/setup.sh``).

Fixtures:

``render``
    ``render(scene, variant, spp, seed=0, **params) -> np.ndarray`` (H, W, C) float32;
    ``scene`` is a scene dict (``mi.load_dict``) or an XML path (``mi.load_file``,
    ``params`` substituted for ``$name``). Sets the variant; the fluo plugins are
    registered for both scalar variants, so tests may switch variants freely.
``fluo_cli``
    The ``fluo`` console script installed in this interpreter's environment.
``scene_xml``
    ``scene_xml(tmp_path, bsdf_xml, name="scene.xml", **options) -> Path``: the one
    test scene (``SCENE_TEMPLATE``: by default a sphere with the given BSDF under a
    constant environment) written to a file. ``scene_text(bsdf_xml, **options)`` (import
    it from conftest) gives the same XML as text for ``mi.load_string``; its options
    choose the integrator, camera, film, filter, emitter, shape and an optional lit
    floor. ``extra`` goes first in ``<scene>`` (``<default>`` parameters, comments).
``textured_plane`` / ``mean_rgb`` (import them from conftest)
    ``textured_plane(variant, bsdf, spp=64, light="directional")``: an orthographic
    camera straight above a plane (one bounce: ``fluo_path`` with max_depth 2) under a
    D65 light from 300 nm (``fluo_illuminant``; a distant light, or ``"constant"`` for a
    constant sky); it sees uv [0.45, 0.55]², i.e. 10×10 squares of a 100-per-uv
    checkerboard (``checkerboard(a, b)``): exactly half of each value. ``mean_rgb(scene)``:
    its mean RGB.
``mitsuba_log``
    The list of lines Mitsuba's logger writes while the test runs (warnings included).
``chi2_directions``
    ``chi2_directions(bsdf, si, n, bins_u, bins_phi, seed) -> (stat, critical, dof)``:
    Pearson chi-square of ``bsdf.sample``'s directions in (cos θo, φo) bins against
    ``bsdf.pdf`` integrated over each bin, with the critical value at p = 1e-4; checks
    on the way that each sample's pdf equals ``pdf()`` and its weight ``eval()/pdf()``.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

#: The variants the plugin test files run in: the scalar pair by default;
#: ``FLUO_TEST_VARIANTS=llvm_ad_spectral,llvm_ad_rgb`` runs the same tests in the llvm
#: variants (in a fresh process: Mitsuba 3.8 cannot start an llvm variant after a scalar
#: render; test_variants.py does this for every plugin's test file).
VARIANTS = tuple(v for v in os.environ.get("FLUO_TEST_VARIANTS", "scalar_spectral,scalar_rgb").split(",") if v)


@pytest.fixture(scope="session", autouse=True)
def fluo_module():
    """Import ``fluo`` (loading libfluo_mitsuba.so) once; fail loudly if that is impossible."""
    try:
        import fluo
    except ImportError as err:
        pytest.fail(f"cannot import fluo: {err}", pytrace=False)
    return fluo


def _render(scene, variant: str, spp: int, seed: int = 0, **params) -> np.ndarray:
    mi.set_variant(variant)
    if isinstance(scene, dict):
        if params:
            raise TypeError("params are only substituted into XML scenes")
        loaded = mi.load_dict(scene)
    else:
        loaded = mi.load_file(str(scene), **params)
    image = np.array(mi.render(loaded, spp=spp, seed=seed), dtype=np.float32)
    return image


@pytest.fixture
def render():
    """``render(scene_dict_or_path, variant, spp, seed=0, **params)`` -> numpy image."""
    return _render


@pytest.fixture(scope="session")
def fluo_cli() -> Path:
    script = Path(sys.executable).parent / "fluo"
    if not script.is_file():
        pytest.fail(f"console script {script} missing; run bash scripts/setup.sh "
                    "(pip install -e . into the venv)", pytrace=False)
    return script


SCENE_TEMPLATE = """<scene version="3.0.0">
    {extra}
    <integrator type="{integrator}"><integer name="max_depth" value="{max_depth}"/></integrator>
    <sensor type="{camera}">
        {fov}
        <transform name="to_world">
            <lookat origin="{origin}" target="{target}" up="0, 1, 0"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="{width}"/>
            <integer name="height" value="{height}"/>
            <string name="pixel_format" value="{pixel_format}"/>
            <rfilter type="{rfilter}"/>
        </film>
    </sensor>
    <emitter type="{emitter}">{direction}{light}</emitter>
    <shape type="{shape}">
        <transform name="to_world"><scale value="{size}"/><translate value="{center}"/></transform>
        {bsdf}
    </shape>
    {ground}
</scene>
"""

#: The template's optional ``{ground}``: a floor under the shape (with its own BSDF) and
#: an area light above it.
GROUND = """<shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="5"/><translate y="-0.4"/></transform>
        {bsdf}
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="90"/><translate y="3"/></transform>
        <emitter type="area"><rgb name="radiance" value="6"/></emitter>
    </shape>"""


def scene_text(bsdf: str, *, extra: str = "", integrator: str = "path", max_depth: int = 3,
               camera: str = "perspective", fov: float = 40.0, origin: str = "0, 0, 4",
               target: str = "0, 0, 0", spp: int = 4, width: int = 16, height: int = 12,
               pixel_format: str = "rgb", rfilter: str = "gaussian", emitter: str = "constant",
               light: str = '<rgb name="radiance" value="1.0"/>', shape: str = "sphere",
               size: float = 1.0, center: str = "0, 0, 0", ground: str | None = None) -> str:
    """The test scene (``SCENE_TEMPLATE``) as XML text; the defaults are Mitsuba's own
    (independent sampler, rgb film, gaussian filter) where the template names them.

    ``camera`` is ``perspective`` (with ``fov``) or ``orthographic`` (the [-1, 1]² square
    around ``target``); ``emitter`` is ``constant`` (``light`` names ``radiance``) or
    ``directional`` (straight down -z; ``light`` names ``irradiance``); the ``shape``
    (``sphere`` or ``rectangle``) is scaled by ``size`` and moved to ``center``;
    ``ground``, a BSDF, adds a floor and an area light above (``GROUND``).
    """
    return SCENE_TEMPLATE.format(
        extra=extra, integrator=integrator, max_depth=max_depth, camera=camera,
        fov=f'<float name="fov" value="{fov:g}"/>' if camera == "perspective" else "",
        origin=origin, target=target, spp=spp, width=width, height=height,
        pixel_format=pixel_format, rfilter=rfilter, emitter=emitter,
        direction='<vector name="direction" value="0, 0, -1"/>' if emitter == "directional" else "",
        light=light, shape=shape, size=f"{size:g}", center=center, bsdf=bsdf,
        ground=GROUND.format(bsdf=ground) if ground is not None else "")


def _scene_xml(directory: Path, bsdf: str, *, name: str = "scene.xml", **options) -> Path:
    path = Path(directory) / name
    path.write_text(scene_text(bsdf, **options), encoding="utf-8")
    return path


@pytest.fixture
def scene_xml():
    """``scene_xml(directory, bsdf_xml, name="scene.xml", **options)`` -> the written path."""
    return _scene_xml


def textured_plane(variant: str, bsdf: dict, spp: int = 64, light: str = "directional"):
    """The checkerboard test scene (see the module docs), loaded in `variant`."""
    mi.set_variant(variant)
    d65 = {"type": "fluo_illuminant", "illuminant": "D65"}
    emitter = ({"type": "directional", "direction": [0, 0, -1], "irradiance": d65} if light == "directional"
               else {"type": "constant", "radiance": d65})
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "fluo_path", "max_depth": 2},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 20, "height": 20, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(10), "bsdf": bsdf},
        "light": emitter,
    })


def checkerboard(a, b, cells: int = 100) -> dict:
    """Mitsuba's checkerboard with `cells`×`cells` squares per unit of uv (color0 = a)."""
    return {"type": "checkerboard", "color0": a, "color1": b,
            "to_uv": mi.ScalarTransform4f().scale([cells, cells, 1])}


def mean_rgb(scene) -> np.ndarray:
    """Mean RGB of a render of `scene` (seed 1)."""
    return np.array(mi.render(scene, seed=1), dtype=np.float64).reshape(-1, 3).mean(0)


class _LogLines(mi.Appender):
    """A Mitsuba log appender that keeps the lines."""

    def __init__(self):
        super().__init__()
        self.lines: list[str] = []

    def append(self, level, text):
        self.lines.append(text)

    def log_progress(self, *args):
        pass


@pytest.fixture
def mitsuba_log():
    catch = _LogLines()
    mi.logger().add_appender(catch)
    try:
        yield catch.lines
    finally:
        mi.logger().remove_appender(catch)


def _chi2_directions(b, si, n=30_000, bins_u=16, bins_phi=16, seed=3):
    if mi.variant().startswith(("llvm", "cuda")):
        return _chi2_directions_wide(b, si, n, bins_u, bins_phi, seed)
    ctx = mi.BSDFContext()
    rng = np.random.default_rng(seed)
    counts = np.zeros((bins_u, bins_phi))
    for s1, s2, s3 in rng.random((n, 3)):
        bs, weight = b.sample(ctx, si, float(s1), mi.Point2f(float(s2), float(s3)))
        if not bs.pdf > 0 or not np.any(np.array(weight) > 0):
            continue  # a lost sample (reflected below the horizon): no mass in any bin
        wo = bs.wo
        pdf = b.pdf(ctx, si, wo)
        assert abs(bs.pdf - pdf) <= 1e-4 * max(pdf, 1.0), (bs.pdf, pdf)
        value = np.array(b.eval(ctx, si, wo))
        assert np.allclose(np.array(weight), value / pdf, rtol=2e-4, atol=1e-7)
        phi = (math.atan2(wo.y, wo.x) + 2 * math.pi) % (2 * math.pi)
        counts[min(int(wo.z * bins_u), bins_u - 1), min(int(phi / (2 * math.pi) * bins_phi), bins_phi - 1)] += 1
    # expected: midpoint rule on an 8x8 sub-grid of each bin, dω = d(cos θ) dφ
    sub = 8
    expected = np.zeros_like(counts)
    du, dphi = 1 / (bins_u * sub), 2 * math.pi / (bins_phi * sub)
    for i in range(bins_u * sub):
        u = (i + 0.5) * du
        st = math.sqrt(max(0.0, 1 - u * u))
        for k in range(bins_phi * sub):
            p = (k + 0.5) * dphi
            pdf = b.pdf(ctx, si, mi.Vector3f(st * math.cos(p), st * math.sin(p), u))
            expected[i // sub, k // sub] += pdf * du * dphi
    return _chi2_statistic(counts, expected * n)


def _chi2_directions_wide(b, si, n, bins_u, bins_phi, seed):
    """_chi2_directions in a JIT variant: every sample, and every pdf of the expected
    counts' sub-grid, in one vectorised call each."""
    ctx = mi.BSDFContext()
    u = np.random.default_rng(seed).random((n, 3))
    bs, weight = b.sample(ctx, si, mi.Float(u[:, 0]), mi.Point2f(mi.Float(u[:, 1]), mi.Float(u[:, 2])))
    pdf, value = b.pdf(ctx, si, bs.wo), b.eval(ctx, si, bs.wo)
    bs_pdf, pdf, wo = np.array(bs.pdf).ravel(), np.array(pdf).ravel(), np.array(bs.wo)
    weight, value = np.atleast_2d(np.array(weight)), np.atleast_2d(np.array(value))
    kept = (bs_pdf > 0) & np.any(weight > 0, axis=0)  # lost samples (below the horizon): no mass in any bin
    assert np.all(np.abs(bs_pdf - pdf)[kept] <= 1e-4 * np.maximum(pdf, 1.0)[kept])
    assert np.allclose(weight[:, kept], value[:, kept] / pdf[kept], rtol=2e-4, atol=1e-7)
    phi = (np.arctan2(wo[1], wo[0]) + 2 * math.pi) % (2 * math.pi)
    iu = np.minimum((wo[2] * bins_u).astype(int), bins_u - 1)
    ip = np.minimum((phi / (2 * math.pi) * bins_phi).astype(int), bins_phi - 1)
    counts = np.zeros((bins_u, bins_phi))
    np.add.at(counts, (iu[kept], ip[kept]), 1)
    sub = 8
    du, dphi = 1 / (bins_u * sub), 2 * math.pi / (bins_phi * sub)
    uu, pp = np.meshgrid((np.arange(bins_u * sub) + 0.5) * du, (np.arange(bins_phi * sub) + 0.5) * dphi, indexing="ij")
    st = np.sqrt(np.maximum(0.0, 1 - uu * uu))
    d = mi.Vector3f(mi.Float((st * np.cos(pp)).ravel()), mi.Float((st * np.sin(pp)).ravel()), mi.Float(uu.ravel()))
    grid = np.array(b.pdf(ctx, si, d)).reshape(uu.shape) * du * dphi
    expected = grid.reshape(bins_u, sub, bins_phi, sub).sum(axis=(1, 3))
    return _chi2_statistic(counts, expected * n)


def _chi2_statistic(counts, expected):
    """Pearson's statistic of `counts` against `expected`, its degrees of freedom and the
    critical value at p = 1e-4."""
    # pool bins with expected < 5 (Mitsuba's chi2 does the same)
    order = np.argsort(expected, axis=None)
    e_flat, c_flat = expected.flatten()[order], counts.flatten()[order]
    stat, dof, pe, pc = 0.0, 0, 0.0, 0.0
    for e, c in zip(e_flat, c_flat):
        pe += e
        pc += c
        if pe >= 5:
            stat += (pc - pe) ** 2 / pe
            dof += 1
            pe = pc = 0.0
    dof -= 1
    critical = dof * (1 - 2 / (9 * dof) + 3.719 * math.sqrt(2 / (9 * dof))) ** 3  # p = 1e-4 (Wilson-Hilferty)
    return stat, critical, dof


@pytest.fixture
def chi2_directions():
    return _chi2_directions
