"""Tests of the fluo_path integrator (wavelength shifting); fluo_illuminant's own are in
test_fluo_illuminant.py.

References: Mitsuba's native ``path`` (non-fluorescent scenes), the single-bounce
patch integral printed by ``fluo patch`` (computed by direct integration in Rust,
independently of the renderer), exact energy balance in a closed furnace, and
physical facts (a UV-only light reflects nothing visible from a plain surface).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS, scene_text

import fluo

REPO = Path(__file__).resolve().parents[2]


def transform():
    return mi.ScalarTransform4f()


def ortho_down(width=32, height=32, spp=64, pixel_format="xyz"):
    return {
        "type": "orthographic",
        "to_world": transform().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": pixel_format,
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": spp},
    }


def jung_xml(m):
    floats = "".join(f'<float name="{k}" value="{m[k]}"/>' for k in
                     ("reflectance", "emission_peak", "stokes_shift", "concentration", "quantum_yield"))
    return f'<bsdf type="fluo_jung">{floats}</bsdf>'


def plane_from_above(bsdf: str, irradiance: str, width=32, height=32, spp=192):
    """A plane seen straight from above (orthographic, XYZ film) under a distant light."""
    return mi.load_string(scene_text(
        bsdf, integrator="fluo_path", max_depth=2, camera="orthographic", origin="0, 0, 5",
        spp=spp, width=width, height=height, pixel_format="xyz", rfilter="box",
        emitter="directional", light=irradiance, shape="rectangle", size=10))


def render(scene, seed=1):
    return np.array(mi.render(scene, seed=seed), dtype=np.float64)


@pytest.mark.parametrize("variant", VARIANTS)
def test01_create(variant):
    mi.set_variant(variant)
    integrator = mi.load_dict({"type": "fluo_path", "max_depth": 5, "rr_depth": 3})
    assert "FluoPath" in str(integrator) and "max_depth = 5" in str(integrator)
    with pytest.raises(Exception, match=r'lambda_min" = 100'):
        mi.load_dict({"type": "fluo_path", "lambda_min": 100.0})


@pytest.mark.parametrize("variant", VARIANTS)
def test02_non_fluorescent_scene_matches_native_path(variant):
    """Cornell box, same seed and spp: the same code and random numbers as `path`."""
    mi.set_variant(variant)
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 48
    images = {}
    for integrator in ("path", "fluo_path"):
        d["integrator"] = {"type": integrator, "max_depth": 8}
        images[integrator] = render(mi.load_dict(d), seed=4)
    a, b = images["path"], images["fluo_path"]
    assert a.mean() > 0.05
    assert np.abs(a - b).max() <= 1e-5 * max(1.0, np.abs(a).max()), np.abs(a - b).max()


MATERIAL = {"model": "jung", "emission_peak": 520.0, "stokes_shift": 60.0, "concentration": 0.8,
            "quantum_yield": 0.9, "reflectance": 0.3}


def patch(material, illuminant, cmf="cie1931"):
    return fluo.run_tool(["patch", "--material", json.dumps(material), "--illuminant", illuminant,
                          "--cmf", cmf])


@pytest.mark.parametrize("illuminant, material", [
    ("D65", MATERIAL),
    ("A", MATERIAL),
    ("D65", dict(MATERIAL, emission_peak=610.0, stokes_shift=150.0, concentration=1.0,
                 quantum_yield=1.0, reflectance=0.0)),  # all colour from fluorescence
])
def test03_plane_converges_to_patch_integral(illuminant, material):
    """Camera straight above a fluorescent plane under a distant light: π·XYZ/E = patch XYZ."""
    mi.set_variant("scalar_spectral")
    # luminance-normalised irradiance: ∫E ȳ/∫ȳ = 1, so π·XYZ is the white-normalised colour
    scene = plane_from_above(jung_xml(material), '<spectrum type="fluo_illuminant" name="irradiance">'
                             f'<string name="illuminant" value="{illuminant}"/></spectrum>')
    img = render(scene)
    xyz = img.reshape(-1, img.shape[-1])[:, :3].mean(axis=0) * math.pi
    ref = patch(material, illuminant)
    want = np.array(ref["xyz"])
    np.testing.assert_allclose(xyz, want, rtol=0.01)
    # the test can fail: fluorescence must be present in the render
    elastic = np.array(ref["elastic_xyz"])
    assert want[1] - elastic[1] > 0.03  # ≥ 3 × the tolerance
    assert abs(xyz[1] - elastic[1]) > 0.5 * (want[1] - elastic[1])


def test04_uv_only_light_shows_emission_colour_and_black_neighbour():
    mi.set_variant("scalar_spectral")
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "fluo_path", "max_depth": 4},
        "sensor": ortho_down(width=32, height=16, spp=64, pixel_format="rgb"),
        "left": {"type": "rectangle", "to_world": transform().translate([-1, 0, 0]),
                 "bsdf": {"type": "fluo_jung", "reflectance": 0.8, "emission_peak": 520.0,
                          "stokes_shift": 185.0, "concentration": 1.0}},
        "right": {"type": "rectangle", "to_world": transform().translate([1, 0, 0]),
                  "bsdf": {"type": "diffuse", "reflectance": 0.8}},
        # no energy above 350 nm (below the camera's 360 nm)
        "lamp": {"type": "directional", "direction": [0, 0, -1],
                 "irradiance": {"type": "irregular", "wavelengths": "320, 330, 335, 340, 350",
                                "values": "0, 5, 10, 5, 0"}},
    })
    img = render(scene)
    left, right = img[:, :16].reshape(-1, 3).mean(0), img[:, 16:].reshape(-1, 3).mean(0)
    assert np.all(right == 0.0), right
    # green emission at 520 nm: green dominates
    assert left[1] > 0.1 and left[1] > 3 * max(left[0], left[2]), left
    # with the native path tracer the fluorescent plane is black too
    scene_native = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 4},
        "sensor": ortho_down(width=8, height=8, spp=16, pixel_format="rgb"),
        "left": {"type": "rectangle", "bsdf": {"type": "fluo_jung", "emission_peak": 520.0,
                                               "stokes_shift": 185.0, "concentration": 1.0}},
        "lamp": {"type": "directional", "direction": [0, 0, -1],
                 "irradiance": {"type": "irregular", "wavelengths": "320, 335, 350", "values": "0, 10, 0"}},
    })
    assert np.all(render(scene_native) == 0.0)


def furnace_energy(bsdf, depth, spp=48):
    """∫ L dλ over 300-830 nm seen from inside a closed emitting sphere (specfilm, flat band)."""
    flat = {"type": "regular", "wavelength_min": 300, "wavelength_max": 830, "values": "1, 1"}
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "fluo_path", "max_depth": depth, "rr_depth": 1000},
        "sensor": {"type": "perspective", "fov": 60,
                   "film": {"type": "specfilm", "width": 8, "height": 8, "energy": flat},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "walls": {"type": "sphere", "flip_normals": True, "radius": 5, "bsdf": bsdf,
                  "emitter": {"type": "area", "radiance": flat}},
    })
    return float(render(scene, seed=2).mean())


def test05_closed_furnace_never_gains_energy():
    """Walls emit 1 per nm over 530 nm; each bounce returns at most what it received."""
    mi.set_variant("scalar_spectral")
    emitted = 530.0
    white = {"type": "diffuse", "reflectance": 1.0}
    for depth in (2, 4):
        lossless = furnace_energy(white, depth)
        assert abs(lossless - depth * emitted) < 1e-3 * depth * emitted
        for q in (1.0, 0.5):
            fl = furnace_energy({"type": "fluo_jung", "reflectance": 1.0, "concentration": 1.0,
                                 "quantum_yield": q, "emission_peak": 560.0, "stokes_shift": 100.0},
                                depth)
            # Q = 1 conserves energy exactly (up to noise), Q < 1 loses some
            assert fl <= depth * emitted * 1.01, (depth, q, fl)
            if q == 1.0:
                assert fl >= depth * emitted * 0.99
            else:
                assert fl < depth * emitted * 0.99


@pytest.mark.parametrize("case", ["excitation_misses_lights", "monochromatic", "q1_c1_depth1",
                                  "q1_c1_depth100"])
def test06_hard_cases_are_finite_and_non_negative(case):
    mi.set_variant("scalar_spectral")
    bsdf = {"type": "fluo_jung", "reflectance": 0.5, "emission_peak": 520.0, "stokes_shift": 60.0,
            "concentration": 1.0, "quantum_yield": 1.0}
    light = {"type": "fluo_illuminant", "illuminant": "D65"}
    depth = 8
    if case == "excitation_misses_lights":
        bsdf.update(emission_peak=420.0, stokes_shift=80.0)  # absorbs 300-380 nm
        light = {"type": "irregular", "wavelengths": "500, 600", "values": "1, 1"}
    elif case == "monochromatic":
        light = {"type": "irregular", "wavelengths": "459.5, 460, 460.5", "values": "0, 20, 0"}
    elif case == "q1_c1_depth1":
        depth = 1
    else:
        depth = 100
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "fluo_path", "max_depth": depth, "rr_depth": 50},
        "sensor": {"type": "perspective", "fov": 70, "film": {"type": "hdrfilm", "width": 16, "height": 16,
                                                               "pixel_format": "xyz"},
                   "sampler": {"type": "independent", "sample_count": 16}},
        "walls": {"type": "sphere", "flip_normals": True, "radius": 5, "bsdf": bsdf},
        "ball": {"type": "sphere", "radius": 0.5, "to_world": transform().translate([0, 0, 2]),
                 "emitter": {"type": "area", "radiance": light}},
    })
    img = render(scene)
    assert np.isfinite(img).all() and (img >= 0).all()
    text = str(scene.integrator())
    if case == "excitation_misses_lights":
        assert "fluorescent_bsdfs = 0" in text, text
    elif case == "monochromatic":
        assert "fluorescent_bsdfs = 1" in text, text
        assert img[..., 1].mean() > 0  # 460 nm excites the 520 nm emission


def test07_patch_cli_conventions(tmp_path):
    out = patch(MATERIAL, "D65", cmf="cie2006")
    for key in ("xyz", "white_xyz", "cmf", "elastic_xyz"):
        assert key in out
    assert out["cmf"] == "cie2006"
    assert abs(out["white_xyz"][1] - 1.0) < 1e-12
    # default observer is CIE 2006
    default = fluo.run_tool(["patch", "--material", json.dumps(MATERIAL), "--illuminant", "D65"])
    assert default["cmf"] == "cie2006" and default["xyz"] == out["xyz"]
    # a CSV illuminant file equal to E gives the E result
    csv = tmp_path / "flat.csv"
    csv.write_text("# equal energy\nnm,value\n300,1\n830,1\n")
    from_file = patch(MATERIAL, str(csv))
    from_name = patch(MATERIAL, "E")
    np.testing.assert_allclose(from_file["xyz"], from_name["xyz"], rtol=1e-9)
    # D65 white point in CIE 1931 (x, y) = (0.3127, 0.3290)
    w = np.array(patch(MATERIAL, "D65")["white_xyz"])
    assert abs(w[0] / w.sum() - 0.3127) < 5e-4 and abs(w[1] / w.sum() - 0.3290) < 5e-4
    with pytest.raises(RuntimeError, match="illuminant"):
        fluo.run_tool(["patch", "--material", json.dumps(MATERIAL), "--illuminant", "NOPE"])
    with pytest.raises(RuntimeError, match="quantum_yield"):
        fluo.run_tool(["patch", "--material", json.dumps(dict(MATERIAL, quantum_yield=3)),
                       "--illuminant", "D65"])
    # through the Python CLI (forwarded to fluo-rs)
    cli = subprocess.run([sys.executable, "-m", "fluo", "patch", "--material", json.dumps(MATERIAL),
                          "--illuminant", "D65", "--json"], capture_output=True, text=True, check=True)
    assert json.loads(cli.stdout)["xyz"] == out["xyz"]


@pytest.mark.parametrize("name", ["fluo_path_d65.xml", "fluo_path_uv.xml"])
def test08_demo_scenes_render(name):
    mi.set_variant("scalar_spectral")
    scene = mi.load_file(str(REPO / "scenes" / name), spp=2, res=24)
    img = render(scene)
    assert np.isfinite(img).all() and img.mean() > 0
    assert "fluorescent_bsdfs = 3" in str(scene.integrator())


def test10_blackbody_defined_from_300nm_excites_uv_absorber():
    """Mitsuba's blackbody reaches the UV band only when its range starts below 360 nm."""
    mi.set_variant("scalar_spectral")

    def green(wavelength_min):
        scene = plane_from_above(
            '<bsdf type="fluo_jung"><float name="reflectance" value="0"/>'  # absorbs ~310-390 nm
            '<float name="emission_peak" value="450"/><float name="stokes_shift" value="110"/>'
            '<float name="concentration" value="1"/></bsdf>',
            '<spectrum type="blackbody" name="irradiance"><float name="temperature" value="6000"/>'
            f'<float name="wavelength_min" value="{wavelength_min}"/></spectrum>', width=8, height=8, spp=64)
        y = render(scene)[..., 1].mean()  # the integrator scans the scene when rendering
        assert f"excitation_range = [{wavelength_min:g}," in str(scene.integrator())
        return y

    uv, visible_only = green(300.0), green(360.0)
    assert visible_only > 0 and uv > 1.3 * visible_only, (uv, visible_only)
