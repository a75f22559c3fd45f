"""Fluorescent materials inside BSDF wrappers, and under integrators other than fluo_path.

Every wrapper test runs in the scalar variants in this process and, through
test_variants.py, in ``llvm_ad_rgb`` and ``llvm_ad_spectral`` in a fresh one: the same
assertions, the same code path per lane.

Before: ``twosided``/``blendbsdf``/``mask`` around ``fluo_jung`` rendered without any
fluorescence under ``fluo_path`` (black under a UV-only lamp), and Mitsuba's ``path``
dropped fluorescence without a word; ``normalmap``/``bumpmap`` were refused.
"""

from __future__ import annotations

import gc
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
UV_LAMP = REPO / "scenes" / "spectra" / "uv_lamp_365.csv"
from conftest import VARIANTS  # noqa: E402
JUNG = {"type": "fluo_jung", "emission_peak": 520.0, "concentration": 0.9}
JUNG_RED = {"type": "fluo_jung", "emission_peak": 610.0, "concentration": 0.9}


def _render(bsdf: dict, variant: str, lamp: str, *, back: bool = False, spp: int = 64,
            integrator: str = "fluo_path") -> np.ndarray:
    mi.set_variant(variant)
    light = ({"type": "fluo_illuminant", "filename": str(UV_LAMP), "normalize": False}
             if lamp == "uv" else {"type": "fluo_illuminant", "illuminant": "D65"})
    # The rectangle faces +z; seen from behind, the camera sits at -z.
    origin = [0, 0, -4] if back else [0, 0, 4]
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 3},
        "sensor": {"type": "perspective",
                   "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 12, "height": 12, "rfilter": {"type": "box"}}},
        "emitter": {"type": "constant", "radiance": light},
        "shape": {"type": "rectangle", "bsdf": bsdf}})
    return np.array(mi.render(scene, spp=spp, seed=3), dtype=np.float64)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("lamp", ["uv", "d65"])
def test01_twosided_front_is_the_unwrapped_material(variant, lamp):
    plain = _render(JUNG, variant, lamp)
    wrapped = _render({"type": "twosided", "bsdf": JUNG}, variant, lamp)
    np.testing.assert_allclose(wrapped, plain, rtol=1e-5, atol=1e-9)
    if lamp == "uv":  # only fluorescence is visible: not black
        assert np.abs(wrapped).mean() > 1e-4


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("lamp", ["uv", "d65"])
def test02_twosided_back_fluoresces_like_the_front(variant, lamp):
    # (512 spp: at 64 the UV lamp's fluorescence scatters the image mean by ~2.5 %)
    front = _render(JUNG, variant, lamp, spp=512)
    back = _render({"type": "twosided", "bsdf": JUNG}, variant, lamp, back=True, spp=512)
    np.testing.assert_allclose(back.mean((0, 1)), front.mean((0, 1)), rtol=2e-2, atol=2e-5)
    # Two children: each side shows its own.
    two = {"type": "twosided", "front": JUNG, "back": JUNG_RED}
    red = _render(JUNG_RED, variant, lamp, spp=512)
    np.testing.assert_allclose(_render(two, variant, lamp, spp=512), front, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(_render(two, variant, lamp, back=True, spp=512).mean((0, 1)), red.mean((0, 1)),
                               rtol=2e-2, atol=2e-5)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("lamp", ["uv", "d65"])
def test03_blendbsdf_is_the_weighted_mean_of_its_children(variant, lamp):
    w = 0.3

    def blend(weight):
        return {"type": "blendbsdf", "weight": weight, "a": {"type": "diffuse"}, "b": JUNG}

    # Weights 0 and 1 select one child at every hit (the same scene otherwise).
    ends = [_render(blend(x), variant, lamp, spp=512).mean((0, 1)) for x in (0.0, 1.0)]
    np.testing.assert_allclose(ends[1], _render(JUNG, variant, lamp, spp=512).mean((0, 1)), rtol=2e-2, atol=2e-5)
    want = (1 - w) * ends[0] + w * ends[1]
    got = _render(blend(w), variant, lamp, spp=512).mean((0, 1))
    np.testing.assert_allclose(got, want, rtol=3e-2, atol=3e-5)
    # Nested: twosided(blendbsdf(...)) seen from behind.
    nested = _render({"type": "twosided", "bsdf": blend(w)}, variant, lamp, back=True, spp=512).mean((0, 1))
    np.testing.assert_allclose(nested, want, rtol=3e-2, atol=3e-5)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("lamp", ["uv", "d65"])
def test03b_mask_is_opacity_times_the_material_plus_pass_through(variant, lamp):
    # mask(α): the nested material with probability α, else the environment behind
    # the rectangle seen straight through (a null interaction). Before: refused.
    def mask(alpha):
        return _render({"type": "mask", "opacity": alpha, "bsdf": JUNG}, variant, lamp, spp=512).mean((0, 1))

    plain = _render(JUNG, variant, lamp, spp=512).mean((0, 1))
    np.testing.assert_allclose(mask(1.0), plain, rtol=2e-2, atol=2e-5)
    clear = mask(0.0)
    assert np.abs(clear - plain).max() > 0.05 * np.abs(plain).max()  # the two ends differ
    np.testing.assert_allclose(mask(0.4), 0.4 * plain + 0.6 * clear, rtol=3e-2, atol=3e-5)


def _map_file(tmp_path: Path, name: str, values) -> str:
    """A 2x2 raw bitmap of constant `values` (RGB for a normal map, one channel for a height)."""
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    data = np.tile(np.asarray(values, dtype=np.float32).reshape(1, 1, -1), (2, 2, 1))
    path = tmp_path / name
    mi.Bitmap(data).write(str(path))
    return str(path)


def _normal_map(tmp_path: Path, n) -> dict:
    n = np.asarray(n, dtype=np.float64) / np.linalg.norm(n)
    return {"type": "bitmap", "raw": True, "filename": _map_file(tmp_path, "n.exr", 0.5 * n + 0.5)}


def _sun(bsdf: dict, variant: str, lamp: str, tilt_deg: float = 0.0, seeds=(3,), spp: int = 64) -> np.ndarray:
    """A rectangle (turned by tilt_deg about y) seen straight down by an orthographic
    camera that it fills, lit by a directional light low from +x: direct light only
    (max_depth 2), so a Lambertian vertex shows E·cos(light, shading normal). One image
    per seed."""
    mi.set_variant(variant)
    spectrum = ({"type": "fluo_illuminant", "filename": str(UV_LAMP), "normalize": False}
                if lamp == "uv" else {"type": "fluo_illuminant", "illuminant": "D65"})
    T = mi.ScalarTransform4f()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "fluo_path", "max_depth": 2},
        "sensor": {"type": "orthographic", "to_world": T.look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        "sun": {"type": "directional", "direction": [-1.0, 0.1, -0.6], "irradiance": spectrum},
        "shape": {"type": "rectangle", "to_world": T.rotate([0, 1, 0], tilt_deg) @ T.scale(4), "bsdf": bsdf}})
    return np.stack([np.array(mi.render(scene, spp=spp, seed=s), dtype=np.float64) for s in seeds])


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("lamp", ["uv", "d65"])
def test04_flat_normal_and_zero_bump_maps_render_as_the_bare_material(variant, lamp, tmp_path):
    """normalmap with the unperturbed normal and bumpmap with a constant height around each
    fluorescent BSDF (fluo_jung, fluo_qd, fluo_matrix, fluo_gmm): the bare material's image
    (before: fluo_path refused both)."""
    flat = {"type": "normalmap", "normalmap": _normal_map(tmp_path, [0, 0, 1])}
    height = {"type": "bitmap", "raw": True, "filename": _map_file(tmp_path, "h.exr", [0.3])}
    bump = {"type": "bumpmap", "height": height, "scale": 2.0}
    matrices = REPO / "data" / "matrices"
    for bsdf in (JUNG, {"type": "fluo_qd", "density": 0.8},
                 {"type": "fluo_matrix", "filename": str(matrices / "jung_orange.csv")},
                 {"type": "fluo_gmm", "filename": str(matrices / "jung_orange.gmm.json")}):
        plain = _render(bsdf, variant, lamp)
        assert np.abs(plain).mean() > 1e-4
        for wrapper in (flat, bump):
            np.testing.assert_allclose(_render({**wrapper, "bsdf": bsdf}, variant, lamp), plain,
                                       rtol=1e-4, atol=1e-7, err_msg=wrapper["type"])


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("lamp", ["uv", "d65"])
def test04b_tilted_normal_map_renders_as_a_tilted_plane(variant, lamp, tmp_path):
    """A normal map tilting the shading normal about y, towards the light (+30 degrees:
    1.7x the flat plane's irradiance) or away (-15: 0.53x): under a directional light
    (direct only) the image mean equals the material on a plane tilted so, elastic and
    fluorescent light alike, within noise (4 seeds; a UV lamp's fluorescence in
    scalar_spectral is the noisy case)."""
    seeds = (1, 2, 3, 4)
    flat = _sun(JUNG, variant, lamp, seeds=seeds, spp=128).mean(axis=(1, 2, 3))
    for tilt in (30.0, -15.0):
        n = [np.sin(np.radians(tilt)), 0.0, np.cos(np.radians(tilt))]
        plane = _sun(JUNG, variant, lamp, tilt_deg=tilt, seeds=seeds, spp=128).mean(axis=(1, 2, 3))
        mapped = _sun({"type": "normalmap", "normalmap": _normal_map(tmp_path, n), "bsdf": JUNG}, variant, lamp,
                      seeds=seeds, spp=128).mean(axis=(1, 2, 3))
        se = np.sqrt((plane.var(ddof=1) + mapped.var(ddof=1)) / len(seeds))
        print(lamp, variant, tilt, "flat", flat.mean(), "tilted plane", plane.mean(), "normal map", mapped.mean())
        assert abs(plane.mean() / flat.mean() - (1.7 if tilt > 0 else 0.53)) < 0.15  # the tilt shows
        assert abs(mapped.mean() - plane.mean()) <= 4 * se + 2e-3 * abs(plane.mean()), (tilt, plane, mapped)


@pytest.mark.parametrize("variant", VARIANTS)
def test05_other_integrators_warn_once_per_scene(variant, mitsuba_log):
    def scene(integrator):
        shapes = {f"s{i}": {"type": "sphere", "center": [2.5 * i, 0, 0],
                            "bsdf": {"type": "twosided", "bsdf": {**JUNG, "emission_peak": 500.0 + 10 * i}}}
                  for i in range(3)}
        return mi.load_dict({"type": "scene", "integrator": {"type": integrator},
                             "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
                             "emitter": {"type": "constant"}, **shapes})

    mi.set_variant(variant)
    count = lambda: sum("fluo_path" in t and "once per scene" in t for t in mitsuba_log)  # noqa: E731
    s = scene("path")
    mi.render(s, spp=2)
    mi.render(s, spp=2)
    assert count() == 1  # three materials, two renders: one warning
    # (the vectorised variants trace every live instance of a BSDF class in a render's
    # dr::dispatch, the first scene's unmanaged materials too: release it first)
    del s
    gc.collect()
    mi.render(scene("fluo_path"), spp=2)
    assert count() == 1  # fluo_path transports fluorescence: no warning
    mi.render(scene("direct"), spp=2)
    assert count() == 2  # a new scene under another integrator warns again
