"""Fluorescent materials inside BSDF wrappers, and under integrators other than fluo_path.

Before: ``twosided``/``blendbsdf``/``mask`` around ``fluo_jung`` rendered without any
fluorescence under ``fluo_path`` (black under a UV-only lamp), and Mitsuba's ``path``
dropped fluorescence without a word.
"""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
UV_LAMP = REPO / "scenes" / "spectra" / "uv_lamp_365.csv"
VARIANTS = ("scalar_spectral", "scalar_rgb")
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
    front = _render(JUNG, variant, lamp)
    back = _render({"type": "twosided", "bsdf": JUNG}, variant, lamp, back=True)
    np.testing.assert_allclose(back.mean((0, 1)), front.mean((0, 1)), rtol=2e-2, atol=2e-5)
    # Two children: each side shows its own.
    two = {"type": "twosided", "front": JUNG, "back": JUNG_RED}
    red = _render(JUNG_RED, variant, lamp)
    np.testing.assert_allclose(_render(two, variant, lamp), front, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(_render(two, variant, lamp, back=True).mean((0, 1)), red.mean((0, 1)),
                               rtol=2e-2, atol=2e-5)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("lamp", ["uv", "d65"])
def test03_blendbsdf_is_the_weighted_mean_of_its_children(variant, lamp):
    w = 0.3

    def blend(weight):
        return {"type": "blendbsdf", "weight": weight, "a": {"type": "diffuse"}, "b": JUNG}

    # Weights 0 and 1 select one child at every hit (the same scene otherwise).
    ends = [_render(blend(x), variant, lamp, spp=512).mean((0, 1)) for x in (0.0, 1.0)]
    np.testing.assert_allclose(ends[1], _render(JUNG, variant, lamp).mean((0, 1)), rtol=2e-2, atol=2e-5)
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


@pytest.mark.parametrize("wrapper", [
    {"type": "bumpmap", "arbitrary": {"type": "checkerboard"}},
    {"type": "normalmap", "normalmap": {"type": "bitmap", "raw": True,
                                        "filename": str(REPO / "scenes" / "textures" / "acescg_card.exr")}},
])
@pytest.mark.parametrize("variant", VARIANTS)
def test04_unsupported_wrappers_are_refused(wrapper, variant):
    with pytest.raises(RuntimeError, match=r"fluo_path: a fluorescent material is wrapped in a .*cannot see through"):
        _render({**wrapper, "bsdf": JUNG}, variant, "d65", spp=1)


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
    mi.render(scene("fluo_path"), spp=2)
    assert count() == 1  # fluo_path transports fluorescence: no warning
    mi.render(scene("direct"), spp=2)
    assert count() == 2  # a new scene under another integrator warns again
