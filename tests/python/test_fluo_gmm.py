"""Tests of fluo_gmm (Gaussian-mixture reradiation, Hua et al. 2022).

References: the fit file's own diagonal (what the BSDF must serve), and the
single-bounce patch integral of ``fluo patch`` of the same fit file (direct
integration in Rust) that ``fluo_path`` renders must converge to within 1 %. The
wavelength sampling's chi-square tests against its pdf (several λi and λo, λi near the
top of the range) are Rust unit tests (``core/src/models/gmm.rs``), where the sampler is exposed.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS, scene_text

import fluo

REPO = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("FLUO_SHARED_DATA", REPO.parent / "shared" / "data"))
OWN_FIT = REPO / "data" / "matrices" / "jung_orange.gmm.json"


def plane_xyz(bsdf: str, illuminant: str, spp=192):
    """π·mean XYZ of a plane seen from above under a distant light of unit luminance."""
    mi.set_variant("scalar_spectral")
    light = f'<spectrum type="fluo_illuminant" name="irradiance"><string name="illuminant" value="{illuminant}"/></spectrum>'
    scene = mi.load_string(scene_text(
        bsdf, integrator="fluo_path", max_depth=2, camera="orthographic", origin="0, 0, 5",
        spp=spp, width=32, height=32, pixel_format="xyz", rfilter="box", emitter="directional",
        light=light, shape="rectangle", size=10))
    img = np.array(mi.render(scene, seed=1), dtype=np.float64)
    return img.reshape(-1, img.shape[-1])[:, :3].mean(axis=0) * math.pi


def check_converges(fit_path: Path, illuminant: str):
    xyz = plane_xyz(f'<bsdf type="fluo_gmm"><string name="filename" value="{fit_path}"/></bsdf>', illuminant)
    ref = fluo.run_tool(["patch", "--material", str(fit_path), "--illuminant", illuminant,
                         "--cmf", "cie1931"])
    want, elastic = np.array(ref["xyz"]), np.array(ref["elastic_xyz"])
    np.testing.assert_allclose(xyz, want, rtol=0.01)
    assert want[1] - elastic[1] > 0.03, (want, elastic)  # fluorescence ≥ 3 × the tolerance


@pytest.mark.parametrize("variant", VARIANTS)
def test01_create_and_errors(variant, tmp_path):
    mi.set_variant(variant)
    b = mi.load_dict({"type": "fluo_gmm", "filename": str(OWN_FIT)})
    assert "FluoGmm" in str(b) and "components = 8" in str(b)
    fit = json.loads(OWN_FIT.read_text())
    bad_cov = json.loads(OWN_FIT.read_text())
    bad_cov["components"][2]["covariance"] = [[1.0, 5.0], [5.0, 1.0]]
    bad_w = json.loads(OWN_FIT.read_text())
    bad_w["components"][0]["weight"] += 0.5
    for name, text, needle in [
        ("cov.gmm.json", json.dumps(bad_cov), r"components\[2\]\.covariance"),
        ("w.gmm.json", json.dumps(bad_w), "weight"),
        ("trunc.gmm.json", json.dumps(fit)[:200], "fit file"),
        ("nan.gmm.json", json.dumps(fit).replace('"scale": ', '"scale": NaN, "x": ', 1), "fit file"),
    ]:
        f = tmp_path / name
        f.write_text(text)
        with pytest.raises(Exception, match=needle):
            mi.load_dict({"type": "fluo_gmm", "filename": str(f)})


def test02_eval_serves_the_stored_diagonal():
    mi.set_variant("scalar_spectral")
    import drjit as dr
    fit = json.loads(OWN_FIT.read_text())
    lam, rho = np.array(fit["diagonal"]["wavelengths_nm"]), np.array(fit["diagonal"]["values"])
    b = mi.load_dict({"type": "fluo_gmm", "filename": str(OWN_FIT)})
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    wl = (400.0, 505.0, 610.0, 777.0)
    si.wavelengths = mi.Spectrum(*wl)
    got = np.array(b.eval(mi.BSDFContext(), si, mi.Vector3f(0, 0, 1)))
    np.testing.assert_allclose(got, np.interp(wl, lam, rho) / math.pi, rtol=1e-5)


@pytest.mark.parametrize("illuminant", ["D65", "A"])
def test03_plane_converges_to_patch_of_its_fit(illuminant):
    check_converges(OWN_FIT, illuminant)


@pytest.mark.skipif(not (SHARED / "bispectral" / "TEXTYELL.BFC").is_file(),
                    reason=f"shared data not found at {SHARED} (set FLUO_SHARED_DATA)")
def test04_measured_fit_converges_to_patch_of_its_fit(tmp_path):
    out = tmp_path / "TEXTYELL.gmm.json"
    fluo.run_tool(["fit-gmm", str(SHARED / "bispectral" / "TEXTYELL.BFC"), "--components", "8",
                   "-o", str(out)])
    check_converges(out, "D65")


@pytest.mark.parametrize("variant", VARIANTS)
def test05_tiny_weights_normalise_and_differentiate(variant):
    """Issue 32 finding 9: the mixture's weights are normalised, so scaling them all by
    1e-30 changes nothing, and in the AD variants their gradients stay finite (1/Σw² of
    such weights overflowed float: every gradient was NaN), in RGB too, where they reach
    the weights through the reduced matrix's derivatives."""
    import drjit as dr

    mi.set_variant(variant)
    scene = mi.load_string(scene_text(
        f'<bsdf type="fluo_gmm"><string name="filename" value="{OWN_FIT}"/></bsdf>', integrator="fluo_path",
        max_depth=2, spp=16, width=8, height=8, emitter="directional",
        light='<spectrum type="fluo_illuminant" name="irradiance"><string name="illuminant" value="D65"/></spectrum>',
        shape="rectangle", size=10))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("weights"))
    ref = np.array(mi.render(scene, seed=2))
    params[key] = params[key] * 1e-30
    params.update()
    tiny = np.array(mi.render(scene, seed=2))
    np.testing.assert_allclose(tiny, ref, rtol=1e-4, atol=1e-6)
    assert not params.flags(key) & mi.ParamFlags.NonDifferentiable
    if dr.is_diff_v(mi.Float):
        dr.enable_grad(params[key])
        params.update()
        dr.backward(dr.mean(mi.render(scene, params, seed=2)))
        g = np.array(dr.grad(params[key]))
        assert np.isfinite(g).all() and np.abs(g).max() > 0, g
