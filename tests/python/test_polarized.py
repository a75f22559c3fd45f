"""The polarized spectral variants: every plugin, fluo_path and fluo_volpath carry Mueller
matrices as Mitsuba's ``path``/``volpath`` do; reradiated light leaves unpolarized.

The tests run in ``scalar_spectral_polarized`` here and, through test_variants.py, in
``llvm_ad_spectral_polarized`` in a fresh process (each against its unpolarized twin,
``scalar_spectral`` / ``llvm_ad_spectral``). References: the unpolarized spectral render of
the same scene (a fluorescent scene's intensity S0 does not depend on polarization when
light leaves every fluorescent vertex unpolarized and the elastic lobes are Mitsuba's own
Mueller matrices or depolarizers), Mitsuba's ``path``/``volpath`` in the same variant
(native scenes, all four Stokes components), and Stokes s1..s3 = 0 for light that only
reradiation brings to the camera (where the same scene under visible light is polarized).
"""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS

REPO = Path(__file__).resolve().parents[2]
MATRICES = REPO / "data" / "matrices"
UV_LAMP = REPO / "scenes" / "spectra" / "uv_lamp_365.csv"

#: The polarized variant of each spectral variant under test, with that twin.
POLARIZED = tuple(v + "_polarized" for v in VARIANTS if v.endswith("_spectral"))

D65 = {"type": "fluo_illuminant", "illuminant": "D65"}
UV = {"type": "fluo_illuminant", "filename": str(UV_LAMP), "normalize": False}
BSDFS = {
    "jung": {"type": "fluo_jung", "emission_peak": 520.0, "concentration": 0.9},
    "matrix": {"type": "fluo_matrix", "filename": str(MATRICES / "jung_orange.csv")},
    "gmm": {"type": "fluo_gmm", "filename": str(MATRICES / "jung_orange.gmm.json")},
    "qd": {"type": "fluo_qd", "material": "Al", "alpha": 0.3, "radius": 2.2, "density": 0.8},
}
#: A dye absorbing at 316-376 nm (peak 340 nm), emitting around 420 nm.
JUNG_UV = {"type": "fluo_jung", "emission_peak": 420.0, "stokes_shift": 80.0, "concentration": 0.9}
#: Quantum dots on a dielectric substrate: its reflection at 45° is strongly polarized.
QD_GLASS = {"type": "fluo_qd", "int_ior": 1.5, "alpha": 0.3, "radius": 2.2, "density": 0.8}


def _twin(variant: str) -> str:
    return variant.removesuffix("_polarized")


def _plane(variant: str, bsdf: dict, light: dict, integrator: dict, *, res: int = 12,
           direction=(0.0, -1.0, -1.0)) -> mi.Scene:
    """A plane (z = 0) under a sun from +y+z (`light`'s spectrum), seen along the mirror
    direction from -y+z: the elastic lobes' polarizing reflection reaches the camera."""
    mi.set_variant(variant)
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 20,
                   "to_world": T().look_at(origin=[0, -3, 3], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "sun": {"type": "directional", "direction": list(direction), "irradiance": light},
        "sky": {"type": "constant", "radiance": {**light, "scale": 0.05}},
        "plane": {"type": "rectangle", "to_world": T().scale(2.0), "bsdf": bsdf}})


def _stokes(scene: mi.Scene, spp: int, seed: int = 0) -> np.ndarray:
    """(4, H, W, 3): the Stokes components' sRGB images of a scene whose integrator is
    `stokes` (Mitsuba's: its channels are the image, then S0..S3)."""
    img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)
    assert img.shape[-1] == 15, img.shape
    return np.stack([img[..., 3 + 3 * i: 6 + 3 * i] for i in range(4)])


@pytest.mark.parametrize("variant", POLARIZED)
def test01_every_plugin_loads_and_renders_finite(variant):
    mi.set_variant(variant)
    import fluo  # noqa: F401
    for name, bsdf in BSDFS.items():
        for integ in ("fluo_path", "fluo_volpath"):
            img = np.array(mi.render(_plane(variant, bsdf, D65, {"type": integ, "max_depth": 3}), spp=4))
            assert np.isfinite(img).all() and img.mean() > 0, (name, integ)
    # media (both), the illuminant as an area light
    for medium in ({"type": "fluo_dye_medium"}, {"type": "fluo_qd_medium", "scale": 0.01}):
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "fluo_volpath", "max_depth": 8},
            "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at(
                origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": 8, "height": 8}},
            "light": {"type": "sphere", "center": [0, 3, 3], "radius": 0.5,
                      "emitter": {"type": "area", "radiance": D65}},
            "ball": {"type": "sphere", "bsdf": {"type": "null"}, "interior": medium}})
        img = np.array(mi.render(scene, spp=8))
        assert np.isfinite(img).all() and img.mean() > 0, medium["type"]


#: (material, lamp) of test02: every material under D65 from 300 nm, the UV absorbers
#: under the 365 nm lamp (where nearly all the light they return is reradiated).
CASES = [(name, "d65") for name in sorted(BSDFS)] + [("jung_uv", "uv"), ("qd", "uv")]


@pytest.mark.parametrize("variant", POLARIZED)
@pytest.mark.parametrize("name,lamp", CASES)
def test02_fluorescent_intensity_equals_the_unpolarized_render(variant, name, lamp):
    """S0 of fluo_path in the polarized variant == the unpolarized spectral render (one
    bounce and inter-reflection-free: a plane under a sun and a dim sky)."""
    light = UV if lamp == "uv" else D65
    bsdf = JUNG_UV if name == "jung_uv" else BSDFS[name]
    integ = {"type": "fluo_path", "max_depth": 3}
    means = {}
    for v in (variant, _twin(variant)):
        img = np.array(mi.render(_plane(v, bsdf, light, integ), spp=256, seed=2), dtype=np.float64)
        assert np.isfinite(img).all()
        means[v] = img.mean(axis=(0, 1))
    print(variant, name, lamp, means)
    assert means[variant].mean() > 1e-2
    np.testing.assert_allclose(means[variant], means[_twin(variant)], rtol=0.03)


@pytest.mark.parametrize("variant", POLARIZED)
@pytest.mark.parametrize("case", ["conductor", "pplastic", "volpath"])
def test03_native_scenes_equal_mitsuba_in_every_stokes_component(variant, case):
    """Without fluorescence fluo_path == path and fluo_volpath == volpath, s0..s3 (a gold
    microfacet and Mitsuba's polarized plastic polarize what they reflect)."""
    bsdf = ({"type": "roughconductor", "material": "Au", "alpha": 0.2} if case != "pplastic"
            else {"type": "pplastic", "alpha": 0.1})
    ours_t, ref_t = ("fluo_volpath", "volpath") if case == "volpath" else ("fluo_path", "path")
    out = {}
    for t in (ours_t, ref_t):
        scene = _plane(variant, bsdf, D65, {"type": "stokes", "integrator": {"type": t, "max_depth": 4}})
        out[t] = _stokes(scene, spp=128, seed=5).mean(axis=(1, 2))  # (4, 3)
    print(variant, case, out)
    assert np.abs(out[ref_t][1]).mean() > 0.02 * out[ref_t][0].mean()  # the reference is polarized
    np.testing.assert_allclose(out[ours_t], out[ref_t], rtol=0.02, atol=2e-3 * out[ref_t][0].mean())


@pytest.mark.parametrize("variant", POLARIZED)
@pytest.mark.parametrize("name", ["qd", "jung"])
def test04_reradiated_light_is_unpolarized(variant, name, tmp_path):
    """A lamp below the camera's 360 nm: only reradiated light reaches it, and its Stokes
    s1..s3 vanish; the same fluo_qd under D65 reflects strongly polarized light (so the
    test can fail: a reradiation lobe that kept the substrate's Mueller matrix would show)."""
    lamp = tmp_path / "uv_300_350.csv"
    lamp.write_text("nm,value\n299,0\n300,1\n350,1\n351,0\n", encoding="utf-8")
    uv = {"type": "fluo_illuminant", "filename": str(lamp), "normalize": False}
    integ = {"type": "stokes", "integrator": {"type": "fluo_path", "max_depth": 2}}
    bsdf = QD_GLASS if name == "qd" else JUNG_UV
    s = _stokes(_plane(variant, bsdf, uv, integ), spp=64).mean(axis=(1, 2))
    print(variant, name, "UV only", s)
    assert s[0].mean() > 1e-4
    assert np.abs(s[1:]).max() <= 1e-6 * s[0].mean()
    if name == "qd":
        visible = _stokes(_plane(variant, bsdf, D65, integ), spp=64).mean(axis=(1, 2))
        print(variant, name, "D65", visible)
        assert np.abs(visible[1]).mean() > 0.1 * visible[0].mean()
