"""Tests of the fluo_jung plugin (Jung et al. 2019, eq. 1) in both scalar variants.

References used here are independent of the Rust core: the model's equations 2-6
re-implemented in numpy straight from the paper, Mitsuba's own spectrum -> sRGB
conversion, and Mitsuba's native ``diffuse`` BSDF (the c = 0 limit).
"""

from __future__ import annotations

import math
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS, scene_text, textured_plane, mean_rgb, checkerboard

REPO = Path(__file__).resolve().parents[2]


# ---------------------------------------------------------------- reference model
def bspline(x):
    """Jung et al. 2019, eq. 3."""
    x = np.abs(np.asarray(x, dtype=np.float64))
    return np.where(x <= 1, 1 - x**2 / 3, np.where(x < 3, (3 - x) ** 2 / 6, 0.0))


def ref_alpha(le, s):
    return le * s / (2 * le - s)  # eq. 4


def ref_emission(lam, le, s):
    a = ref_alpha(le, s)
    return bspline(3 / a * (np.asarray(lam, float) - le)) * 9 / (8 * a)  # eq. 5


def ref_absorption(lam, le, s):
    """Eq. 6 as printed: b(3/α ((2/(λe−α) − 1/λ)⁻¹ − λe)), zero where the mirror is undefined."""
    a = ref_alpha(le, s)
    lam = np.asarray(lam, float)
    denom = 2 / (le - a) - 1 / lam
    mirrored = np.where(denom > 0, 1 / np.where(denom > 0, denom, 1), np.inf)
    out = bspline(3 / a * (mirrored - le))
    # the mirror maps the emission's long half onto λ > λe − α; absorption lives below it
    return np.where(lam < le - a, out, 0.0)


def ref_sigmoid(lam, c):
    x = c[0] * np.asarray(lam, float) ** 2 + c[1] * lam + c[2]
    return 0.5 + x / (2 * np.sqrt(1 + x * x))  # eq. 2


def surface_interaction(wavelengths=(400.0, 450.0, 500.0, 600.0), wi=(0, 0, 1)):
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(*wi)
    si.n = mi.Vector3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    if dr.size_v(mi.Spectrum) == 4:
        si.wavelengths = mi.Spectrum(*wavelengths)
    return si


def jung(**kw):
    return mi.load_dict({"type": "fluo_jung", **kw})


# ------------------------------------------------------------------------- tests
@pytest.mark.parametrize("variant", VARIANTS)
def test01_create(variant):
    mi.set_variant(variant)
    b = jung()
    assert b is not None
    text = str(b)
    for part in ("emission_peak = 520", "stokes_shift = 60", "concentration = 0.5"):
        assert part in text, text
    assert b.flags() & mi.BSDFFlags.DiffuseReflection
    params = mi.traverse(b)
    for key in ("emission_peak", "stokes_shift", "concentration", "quantum_yield"):
        assert key in params


@pytest.mark.parametrize("variant", VARIANTS)
def test02_load_demo_scene(variant):
    mi.set_variant(variant)
    scene = mi.load_file(str(REPO / "scenes" / "jung_spheres.xml"), res=16, spp=1)
    names = [s.bsdf().class_name() for s in scene.shapes()]
    assert names.count("FluoJung") == 3, names


@pytest.mark.parametrize("params", [
    dict(emission_peak=520.0, stokes_shift=60.0, concentration=0.7, quantum_yield=0.9),
    dict(emission_peak=420.0, stokes_shift=100.0, concentration=1.0, quantum_yield=1.0),
    dict(emission_peak=650.0, stokes_shift=30.0, concentration=0.25, quantum_yield=0.5),
])
def test03_eval_spectral_matches_paper_equations(params):
    mi.set_variant("scalar_spectral")
    coeffs = (-2e-4, 0.22, -55.0)
    b = jung(coefficients=", ".join(map(str, coeffs)), **params)
    le, s, c = params["emission_peak"], params["stokes_shift"], params["concentration"]
    rng = np.random.default_rng(3)
    ctx = mi.BSDFContext()
    for _ in range(20):
        lam = np.sort(rng.uniform(360, 830, 4))
        lam[0] = le - s  # include the absorption peak
        si = surface_interaction(tuple(lam))
        cos_o = rng.uniform(0.05, 1)
        wo = mi.Vector3f(math.sqrt(1 - cos_o**2), 0, cos_o)
        got = np.array(b.eval(ctx, si, wo))
        want = (1 - c * ref_absorption(lam, le, s)) * ref_sigmoid(lam, coeffs) / math.pi * cos_o
        np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-7)
        pdf = b.pdf(ctx, si, wo)
        assert abs(pdf - cos_o / math.pi) < 1e-6


def test04_rgb_albedo_matches_mitsuba_conversion():
    """RGB variant: albedo = Mitsuba's sRGB of R(λ) = r(1 − c a) + c Q e ∫₃₆₀⁸³⁰ a (under E),
    the reradiated part scaled by the largest k ≤ 1 keeping every channel ≤ 1."""
    mi.set_variant("scalar_rgb")
    coeffs = (-2e-4, 0.22, -55.0)
    le, s, c, q = 540.0, 70.0, 0.8, 0.9
    b = jung(coefficients=", ".join(map(str, coeffs)), emission_peak=le, stokes_shift=s,
             concentration=c, quantum_yield=q)
    lam = np.linspace(360.0, 830.0, 4701)
    excite = np.trapezoid(ref_absorption(lam, le, s), lam)
    elastic_rgb = np.clip(np.array(mi.spectrum_list_to_srgb(
        list(lam), list(ref_sigmoid(lam, coeffs) * (1 - c * ref_absorption(lam, le, s))), bounded=False)), 0, 1)
    glow_rgb = np.maximum(np.array(mi.spectrum_list_to_srgb(
        list(lam), list(c * q * excite * ref_emission(lam, le, s)), bounded=False)), 0.0)
    k = min([1.0] + [(1 - e) / f for e, f in zip(elastic_rgb, glow_rgb) if f > 0])
    want = elastic_rgb + k * glow_rgb
    assert k < 1.0 and want.max() == pytest.approx(1.0, abs=1e-4)  # this green needs the bound
    got = np.array(b.eval_diffuse_reflectance(surface_interaction()))
    # Mitsuba integrates a 5 nm CIE table with 1000 Riemann steps, we a 1 nm one.
    np.testing.assert_allclose(got, want, rtol=5e-3)
    # fluorescence makes it brighter than the elastic part alone
    elastic = ref_sigmoid(lam, coeffs) * (1 - c * ref_absorption(lam, le, s))
    no_fl = np.clip(np.array(mi.spectrum_list_to_srgb(list(lam), list(elastic), bounded=False)), 0, 1)
    assert got[1] > no_fl[1] + 0.05  # the green glow


def _rel_diff(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).mean() / np.abs(b).mean())


#: The cross-validation scene: a sphere on a floor of the same BSDF, lit from above.
CROSS = dict(max_depth=4, origin="0, 1.5, 4", target="0, 0.2, 0", spp=8, width=48, height=32,
             light='<rgb name="radiance" value="0.2"/>', size=0.7, center="0, 0.3, 0")

SPECTRUM = '<spectrum name="reflectance" value="360:0.1, 430:0.2, 480:0.7, 550:0.8, 600:0.3, 700:0.6, 830:0.5"/>'


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("reflectance", [SPECTRUM, '<rgb name="reflectance" value="0.7, 0.3, 0.2"/>'])
def test05_zero_concentration_matches_native_diffuse(variant, reflectance, tmp_path, render, scene_xml):
    """Cross-validation: c = 0 is Mitsuba's diffuse (same seed, same spp)."""
    jung_c0 = f'<bsdf type="fluo_jung">{reflectance}<float name="concentration" value="0"/></bsdf>'
    diffuse = f'<bsdf type="diffuse">{reflectance}</bsdf>'
    ours = scene_xml(tmp_path, jung_c0, ground=jung_c0, name="ours.xml", **CROSS)
    native = scene_xml(tmp_path, diffuse, ground=diffuse, name="native.xml", **CROSS)
    a = render(ours, variant, spp=8, seed=5)
    b = render(native, variant, spp=8, seed=5)
    assert np.isfinite(a).all() and b.mean() > 0
    assert _rel_diff(a, b) < 5e-3


def test06_sigmoid_reflectance_matches_tabulated_diffuse(tmp_path, render, scene_xml):
    """Spectral: the sigmoid branch (coefficients) equals diffuse with that spectrum tabulated."""
    coeffs = (-2e-4, 0.22, -55.0)
    lam = np.arange(360.0, 831.0, 2.0)
    values = ", ".join(f"{l:g}:{v:.6f}" for l, v in zip(lam, ref_sigmoid(lam, coeffs)))
    sigmoid = ('<bsdf type="fluo_jung"><string name="coefficients" value="%s"/>'
               '<float name="concentration" value="0"/></bsdf>' % ", ".join(map(str, coeffs)))
    tabulated = f'<bsdf type="diffuse"><spectrum name="reflectance" value="{values}"/></bsdf>'
    ours = scene_xml(tmp_path, sigmoid, ground=sigmoid, name="ours.xml", **CROSS)
    native = scene_xml(tmp_path, tabulated, ground=tabulated, name="native.xml", **CROSS)
    a = render(ours, "scalar_spectral", spp=8, seed=2)
    b = render(native, "scalar_spectral", spp=8, seed=2)
    assert _rel_diff(a, b) < 5e-3


@pytest.mark.parametrize("variant", VARIANTS)
def test07_direction_sampling_chi2(variant, chi2_directions):
    """Pearson chi-square of sampled directions against the pdf (conftest)."""
    mi.set_variant(variant)
    b = jung(concentration=0.4)
    si = surface_interaction(wi=(0.3, 0.0, math.sqrt(1 - 0.09)))
    stat, critical, dof = chi2_directions(b, si, n=40_000, bins_u=10, bins_phi=12, seed=11)
    assert dof > 50
    assert stat < critical, (stat, critical, dof)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("props, needle", [
    (dict(quantum_yield=1.5), 'quantum_yield" = 1.5'),
    (dict(concentration=-0.1), 'concentration" = -0.1'),
    (dict(concentration=float("nan")), "concentration"),
    (dict(stokes_shift=1040.0), 'stokes_shift" = 1040'),
    (dict(stokes_shift=-5.0), "stokes_shift"),
    (dict(emission_peak=50.0), "emission_peak"),
    (dict(coefficients="1, 2"), "coefficients"),
    (dict(coefficients="1, x, 3"), "coefficients"),
    (dict(coefficients="0, 0, 0", reflectance=0.5), "not both"),
])
def test08_bad_input_raises_clear_error(variant, props, needle):
    mi.set_variant(variant)
    with pytest.raises(Exception) as err:
        jung(**props)
    assert needle in str(err.value), str(err.value)


@pytest.mark.parametrize("variant", VARIANTS)
def test09_traverse_update_revalidates(variant):
    mi.set_variant(variant)
    b = jung(concentration=1.0, emission_peak=520.0, stokes_shift=60.0, reflectance=0.8)
    si = surface_interaction((460.0, 500.0, 600.0, 700.0))
    before = np.array(b.eval_diffuse_reflectance(si))
    params = mi.traverse(b)
    params["concentration"] = 0.0
    params.update()
    after = np.array(b.eval_diffuse_reflectance(si))
    if "spectral" in variant:
        assert before[0] < 0.8 * 0.9 and abs(after[0] - 0.8) < 1e-6  # a(460) > 0.1 removed light
    else:
        assert not np.allclose(before, after)
    params["quantum_yield"] = 2.0
    with pytest.raises(Exception, match="quantum_yield"):
        params.update()


def test10_hard_cases_are_finite():
    """Sweep the parameter box and its edges at the ends of 300-830 nm."""
    mi.set_variant("scalar_spectral")
    ctx = mi.BSDFContext()
    for le in (200.0, 300.0, 520.0, 830.0, 1200.0):
        s_max = 2 * le * (le - 1) / (2 * le - 1)
        for s in (1e-3, 1.0, 0.5 * s_max, 0.999 * s_max):
            for c in (0.0, 1.0):
                for q in (0.0, 1.0):
                    b = jung(emission_peak=le, stokes_shift=s, concentration=c, quantum_yield=q)
                    for lam in ((300.0, 301.0, 829.0, 830.0), (le - s, le, le + 1, 360.0)):
                        for cos_o in (1.0, 1e-6):
                            wo = mi.Vector3f(math.sqrt(1 - cos_o**2), 0, cos_o)
                            v = np.array(b.eval(ctx, surface_interaction(lam, wi=(0.99999, 0, 0.004472)), wo))
                            assert np.isfinite(v).all() and (v >= 0).all(), (le, s, c, q, lam, v)


# ------------------------------------------------------- wide-gamut upsampling (`color`)
import json
import subprocess
import sys

import fluo
from fluo import upsample_demo

COLOR_SCENE = (REPO / "scenes" / "upsample_acescg.xml").read_text()


def _color_scene(color_xml: str, fluorescence: str = "true", width: int = 32, height: int = 8) -> str:
    """The demo scene (D65 sky, white Y = 1, direct light, head-on) with `color` replaced."""
    import re
    s = re.sub(r'<texture type="bitmap".*?</texture>', color_xml, COLOR_SCENE, flags=re.S)
    s = s.replace('value="256"', f'value="{width}"').replace('value="64"/>\n            <rfilter',
                                                            f'value="{height}"/>\n            <rfilter')
    return s.replace("$fluorescence", fluorescence).replace("$spp", "32")


def _cube_prediction_srgb(rgb, fluorescence=True):
    """fluo-rs upsample-lookup: the colour the cube's coefficients reproduce (ACEScg,
    Bradford-adapted from D65), converted to the linear sRGB a Mitsuba film shows."""
    out = fluo.run_tool(["upsample-lookup", "--space", "acescg", "--rgb", ",".join(map(str, rgb)),
                         "--fluorescence", "true" if fluorescence else "false", "--json"])
    got = np.array(out["reproduced_rgb"])
    d = upsample_demo
    xyz = got @ d.ACESCG_TO_XYZ.T @ d.bradford(d.ACES_WHITE, d.D65_WHITE).T
    return xyz @ np.linalg.inv(d.SRGB_TO_XYZ).T, out


@pytest.mark.parametrize("rgb", [(1.0, 0.0, 0.0), (0.9, 0.0, 0.9), (1.0, 0.375, 0.0), (0.5, 0.5, 0.5)])
def test11_color_render_matches_cube_prediction(rgb):
    """A constant ACEScg colour renders (fluo_path, spectral) to the colour the cube's
    Rust evaluator predicts: the shim, the lookup and fluo_path agree with eq. 7."""
    mi.set_variant("scalar_spectral")
    scene = mi.load_string(_color_scene('<rgb name="color" value="%g, %g, %g"/>' % rgb))
    img = np.array(mi.render(scene, spp=32, seed=1))[..., :3].reshape(-1, 3).mean(0)
    want, out = _cube_prediction_srgb(rgb)
    # Monte Carlo noise (32 spp x 256 px) and Mitsuba's own 5 nm CIE table: ~1 %.
    assert (np.abs(img - want) < 0.025 * np.maximum(np.abs(want), 1.0)).all(), (img, want, out)
    if out["coefficients"]["concentration"] > 0:
        # and fluorescence matters: without it the render is measurably different
        scene = mi.load_string(_color_scene('<rgb name="color" value="%g, %g, %g"/>' % rgb, "false"))
        nofl = np.array(mi.render(scene, spp=32, seed=1))[..., :3].reshape(-1, 3).mean(0)
        assert np.abs(nofl - img).max() > 0.05


def test12_texture_demo_de2000_map(tmp_path):
    """The demo: saturated ACEScg card -> per-pixel CIEDE2000 map; fluorescence lowers it."""
    res = {}
    for flag in ([], ["--no-fluorescence"]):
        out = subprocess.run([sys.executable, "-m", "fluo.upsample_demo", "--spp", "16", "--out", str(tmp_path)] + flag,
                             capture_output=True, text=True, check=True, cwd=REPO,
                             env={**__import__("os").environ, "PYTHONPATH": str(REPO / "python")})
        res[bool(flag)] = json.loads(out.stdout.strip().splitlines()[-1])
        assert Path(res[bool(flag)]["de2000_map"]).is_file()
        assert Path(res[bool(flag)]["de2000_map"].replace(".exr", ".png")).is_file()
    # per texel (noise averaged out): fluorescence brings the saturated card closer
    assert res[False]["de2000_texel_mean"] < 3.0, res
    assert res[False]["de2000_texel_mean"] < 0.7 * res[True]["de2000_texel_mean"], res


def _write_exr(path, data):
    mi.set_variant("scalar_rgb")
    mi.Bitmap(np.asarray(data, dtype=np.float32)).write(str(path))
    return path


def _textured(path, extra=""):
    return ('<bsdf version="3.0.0" type="fluo_jung"><texture type="bitmap" name="color">'
            f'<string name="filename" value="{path}"/><boolean name="raw" value="true"/></texture>{extra}</bsdf>')


@pytest.mark.parametrize("variant", VARIANTS)
def test14_texture_coefficients_precomputed_per_texel(variant, tmp_path):
    """Coefficients are computed once per texel at load (distinct sets reported), and
    the albedo at a texel is that of its own colour (spectral: elastic part)."""
    tex = _write_exr(tmp_path / "t.exr", [[[0.9, 0, 0.9], [0.5, 0.5, 0.5]], [[0.5, 0.5, 0.5], [0.2, 0.6, 0.1]]])
    mi.set_variant(variant)
    b = mi.load_string(_textured(tex))
    assert "texture 2 x 2 acescg, 3 distinct coefficient sets" in str(b), str(b)
    grey = mi.load_string('<bsdf version="3.0.0" type="fluo_jung"><rgb name="color" value="0.5, 0.5, 0.5"/></bsdf>')
    si = surface_interaction((400.0, 480.0, 560.0, 640.0))
    si.uv = mi.Point2f(0.75, 0.25)  # texel (1, 0): grey
    np.testing.assert_allclose(np.array(b.eval_diffuse_reflectance(si)),
                               np.array(grey.eval_diffuse_reflectance(si)), rtol=1e-6)


@pytest.mark.parametrize("variant", VARIANTS)
def test15_color_bad_input_raises_clear_errors(variant, tmp_path):
    nan_tex = _write_exr(tmp_path / "nan.exr", [[[0.5, 0.5, 0.5], [0.1, float("nan"), 0.2]]] * 2)
    big_tex = _write_exr(tmp_path / "big.exr", [[[0.5, 0.5, 0.5], [0.1, 1.5, 0.2]]] * 2)
    bad_cube = tmp_path / "bad.cube"
    bad_cube.write_bytes(b"FLUOCUBE" + b"\0" * 20)
    srgb_cube = REPO / "data" / "cubes" / "srgb_d65_tinf_r33.cube"
    mi.set_variant(variant)
    cases = [
        ('<rgb name="color" value="1.2, 0, 0.5"/>', 'invalid parameter "color"', "[0, 1]"),
        ('<rgb name="color" value="0.5, -0.1, 0.5"/>', 'invalid parameter "color"', "[0, 1]"),
        ('<rgb name="color" value="0.5, 0.5, 0.5"/><string name="color_space" value="p3"/>',
         'invalid parameter "color_space" = "p3"', "acescg"),
        ('<rgb name="color" value="0.5, 0.5, 0.5"/><string name="lookup" value="cubic"/>', '"lookup"', "nearest"),
        ('<rgb name="color" value="0.5, 0.5, 0.5"/><float name="concentration" value="0.3"/>',
         'do not also specify "concentration"', ""),
        ('<rgb name="color" value="0.5, 0.5, 0.5"/><string name="cube" value="%s"/>' % bad_cube,
         "not a valid coefficient cube", "bad.cube"),
        ('<rgb name="color" value="0.5, 0.5, 0.5"/><string name="cube" value="%s"/>' % srgb_cube,
         'a cube generated for color_space "acescg"', "srgb"),
    ]
    for xml, needle, needle2 in cases:
        with pytest.raises(Exception) as err:
            mi.load_string(f'<bsdf version="3.0.0" type="fluo_jung">{xml}</bsdf>')
        assert needle in str(err.value) and needle2 in str(err.value), str(err.value)
    for tex, needle in ((nan_tex, "NaN"), (big_tex, "texel (x = 1, y = 0)")):
        with pytest.raises(Exception) as err:
            mi.load_string(_textured(tex))
        assert needle in str(err.value) and '"color" = texel (x =' in str(err.value), str(err.value)
    if "spectral" in variant:
        with pytest.raises(Exception) as err:  # not raw: Mitsuba already turned it into spectra
            mi.load_string(_textured(nan_tex).replace('<boolean name="raw" value="true"/>', ""))
        assert "raw" in str(err.value), str(err.value)


# ------------------------------------------------- textured numeric parameters (issue 17)
#: Two values per texturable parameter, far enough apart that the two uniform
#: materials differ by many times the tolerance of test16.
TEXTURE_PAIRS = {
    "concentration": (0.1, 0.9),
    "quantum_yield": (0.2, 1.0),
    "emission_peak": (480.0, 620.0),
    "stokes_shift": (20.0, 120.0),
}
TEXTURED_BASE = {"type": "fluo_jung", "reflectance": 0.3, "emission_peak": 520.0, "stokes_shift": 60.0,
                 "concentration": 0.8, "quantum_yield": 0.9}


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("param", sorted(TEXTURE_PAIRS))
def test16_checkerboard_parameter_renders_as_average_of_uniforms(variant, param):
    """A checkerboard of two values of one parameter renders as the mean of the two
    uniform materials: spectral (fluo_path's wavelength shifting, per-hit dye) and
    scalar_rgb (reduced transport, per-hit reduced matrix)."""
    a, b = TEXTURE_PAIRS[param]
    ua = mean_rgb(textured_plane(variant, dict(TEXTURED_BASE, **{param: a})))
    ub = mean_rgb(textured_plane(variant, dict(TEXTURED_BASE, **{param: b})))
    got = mean_rgb(textured_plane(variant, dict(TEXTURED_BASE, **{param: checkerboard(a, b)})))
    want = (ua + ub) / 2
    # spectral: Monte Carlo noise of different materials (measured ≤ 0.4 %); reduced RGB
    # is deterministic here (one bounce, no wavelength sampling)
    rtol = 0.012 if "spectral" in variant else 1e-4
    np.testing.assert_allclose(got, want, rtol=rtol)
    # the test can fail: the two uniform materials differ by far more than the tolerance
    assert np.abs(ua - ub).max() > 8 * rtol * want.max(), (ua, ub)
    # and a material that ignored the texture (one value everywhere) would miss
    assert min(np.abs(got - ua).max(), np.abs(got - ub).max()) > 4 * rtol * want.max()


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("param", sorted(TEXTURE_PAIRS))
def test17_textured_parameter_is_the_uniform_material_at_each_hit(variant, param):
    """Per hit, eval and the albedo served to Mitsuba's own integrators equal those of
    the uniform material with that hit's value (sigmoid base reflectance: the elastic
    part r(1 − c a) per hit). The hit's value is the texture's eval_1, as Mitsuba's own
    plugins read float textures (Mitsuba 3.8's checkerboard.eval_1 returns color1 where
    its eval returns color0 and vice versa; the value sets are the same)."""
    a, b = TEXTURE_PAIRS[param]
    base = dict(TEXTURED_BASE)
    del base["reflectance"]
    base["coefficients"] = "1e-5, -0.01, 1.5"  # r(λ) ≈ 0.1-0.6
    mi.set_variant(variant)
    board = checkerboard(a, b, cells=2)
    tex = mi.load_dict(dict(base, **{param: board}))
    board = mi.load_dict(board)
    ctx = mi.BSDFContext()
    wo = mi.Vector3f(0.3, 0.2, math.sqrt(1 - 0.13))
    seen = set()
    for uv in ((0.1, 0.1), (0.35, 0.1), (0.35, 0.35)):  # squares of 0.5 in uv·2
        si = surface_interaction((410.0, 450.0, 475.0, 540.0))  # in the absorption bands
        si.uv = mi.Point2f(*uv)
        value = float(np.array(board.eval_1(si)).ravel()[0])
        seen.add(value)
        uniform = mi.load_dict(dict(base, **{param: value}))
        np.testing.assert_allclose(np.array(tex.eval(ctx, si, wo)), np.array(uniform.eval(ctx, si, wo)),
                                   rtol=2e-5, atol=1e-7)
        np.testing.assert_allclose(np.array(tex.eval_diffuse_reflectance(si)),
                                   np.array(uniform.eval_diffuse_reflectance(si)), rtol=2e-5, atol=1e-7)
    assert len(seen) == 2
    # the other value differs there (spectral eval serves the elastic part alone, which
    # Q does not touch: test16 covers Q's reradiation)
    if not ("spectral" in variant and param == "quantum_yield"):
        other = mi.load_dict(dict(base, **{param: sum(TEXTURE_PAIRS[param]) - value}))
        assert np.abs(np.array(other.eval(ctx, si, wo)) - np.array(tex.eval(ctx, si, wo))).max() > 1e-3
    assert "dye shapes" in str(tex) and "dye shapes" not in str(uniform)  # uniform: the float fast path


def _float_bitmap(values, filter_type="nearest"):
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.array(values, dtype=np.float32)), "raw": True,
            "filter_type": filter_type}


@pytest.mark.parametrize("variant", VARIANTS)
def test18_textured_parameters_validated_per_texel(variant):
    """Every texel (bitmaps) or constituent value (a checkerboard's colours) is checked
    at load; the error names the parameter, the value, its texel and the valid range."""
    mi.set_variant(variant)
    nan = float("nan")
    cases = [
        ("concentration", _float_bitmap([[0.1, 0.2, 0.3], [0.4, 1.5, 0.6]]),
         'invalid parameter "concentration" = 1.5 at texel (x = 1, y = 1)', "[0, 1]"),
        ("quantum_yield", _float_bitmap([[0.1, nan], [0.4, 0.5]]),
         'invalid parameter "quantum_yield" = NaN at texel (x = 1, y = 0)', "[0, 1]"),
        ("emission_peak", _float_bitmap([[500.0, 520.0], [1500.0, 520.0]]),
         'invalid parameter "emission_peak" = 1500 at texel (x = 0, y = 1)', "[200, 1200]"),
        ("stokes_shift", _float_bitmap([[-3.0, 50.0], [50.0, 50.0]]),
         'invalid parameter "stokes_shift" = -3 at texel (x = 0, y = 0)', "[0.001,"),
        ("concentration", checkerboard(0.5, -0.2),
         'invalid parameter "concentration" = -0.2 (value 1 of its texture)', "[0, 1]"),
        # each (λe, s) pair the textures combine must be a valid dye: s < s_max(300 nm)
        ("emission_peak", checkerboard(300.0, 700.0),
         'the pair emission_peak = 300, stokes_shift = 500', "for emission_peak = 300 nm"),
    ]
    for param, tex, needle, needle2 in cases:
        props = dict(TEXTURED_BASE, **{param: tex})
        if needle.startswith("the pair"):
            props["stokes_shift"] = checkerboard(20.0, 500.0)
        with pytest.raises(Exception) as err:
            mi.load_dict(props)
        assert needle in str(err.value) and needle2 in str(err.value), str(err.value)
    with pytest.raises(Exception, match="one channel"):
        mi.load_dict(dict(TEXTURED_BASE, concentration=_float_bitmap(np.full((2, 2, 3), 0.5))))
    with pytest.raises(Exception, match='do not also specify "concentration"'):
        mi.load_dict({"type": "fluo_jung", "color": {"type": "rgb", "value": [0.5, 0.5, 0.5]},
                      "concentration": checkerboard(0.1, 0.2)})


@pytest.mark.parametrize("variant", VARIANTS)
def test19_bitmap_parameter_renders_as_texel_average(variant):
    """A 2×2 bitmap of concentrations (nearest texels, tiled over the plane) renders as
    the mean of the four uniform materials; a bilinear bitmap interpolates c, which
    enters the model linearly, so it renders the same mean."""
    values = [[0.0, 0.3], [0.6, 1.0]]
    uniform = [mean_rgb(textured_plane(variant, dict(TEXTURED_BASE, concentration=v), spp=32))
               for row in values for v in row]
    want = np.mean(uniform, axis=0)
    rtol = 0.012 if "spectral" in variant else 1e-4
    for filter_type in ("nearest", "bilinear"):
        tex = dict(_float_bitmap(values, filter_type), to_uv=mi.ScalarTransform4f().scale([50, 50, 1]))
        got = mean_rgb(textured_plane(variant, dict(TEXTURED_BASE, concentration=tex), spp=32))
        # bilinear: the pixel samples see a continuum of c, an estimate of its mean
        np.testing.assert_allclose(got, want, rtol=rtol if filter_type == "nearest" else max(rtol, 2e-3),
                                   err_msg=filter_type)
    assert np.abs(uniform[0] - uniform[3]).max() > 8 * rtol * want.max()


def test20_traverse_shows_and_updates_parameter_textures():
    mi.set_variant("scalar_rgb")
    b = mi.load_dict(dict(TEXTURED_BASE, concentration=_float_bitmap([[0.2, 0.4], [0.2, 0.4]])))
    params = mi.traverse(b)
    assert "concentration.data" in params and "emission_peak" in params
    si = surface_interaction()
    si.uv = mi.Point2f(0.25, 0.5)
    before = np.array(b.eval_diffuse_reflectance(si))
    params["concentration.data"] = mi.TensorXf(np.array([[[0.9], [0.4]], [[0.9], [0.4]]], dtype=np.float32))
    params.update()
    after = np.array(b.eval_diffuse_reflectance(si))
    want = np.array(mi.load_dict(dict(TEXTURED_BASE, concentration=0.9)).eval_diffuse_reflectance(si))
    np.testing.assert_allclose(after, want, rtol=1e-5)
    assert np.abs(after - before).max() > 0.01
    with pytest.raises(Exception, match=r'"concentration" = 2 at texel \(x = 0, y = 0\)'):
        params["concentration.data"] = mi.TensorXf(np.array([[[2.0], [0.4]], [[0.9], [0.4]]], dtype=np.float32))
        params.update()


@pytest.mark.parametrize("variant", VARIANTS)
def test21_bilinear_texels_interpolate_reradiation(variant, tmp_path, capsys):
    """Jung et al. 2019, Fig. 12: with texel_interpolation = bilinear a magnified colour
    texture renders as the bilinear interpolation of its texels' renders (the BBRRDFs
    are mixed, so the light is), where nearest texels give a step. Two columns of
    colours needing fluorescence, seen whole by an orthographic camera (32 pixel
    columns; the texel centres at u = 1/4, 3/4 fall on pixel edges)."""
    a, b = [0.9, 0.0, 0.9], [0.05, 0.8, 0.05]
    tex = _write_exr(tmp_path / "two.exr", [[a, b], [a, b]])
    uniform_tex = {k: _write_exr(tmp_path / f"{k}.exr", [[c, c], [c, c]]) for k, c in (("a", a), ("b", b))}

    def render_columns(bsdf_xml):
        mi.set_variant(variant)
        scene = mi.load_string(scene_text(
            bsdf_xml.replace('<bsdf version="3.0.0" ', "<bsdf "), integrator="fluo_path", max_depth=2,
            camera="orthographic", origin="0, 0, 5", spp=4096, width=32, height=2, rfilter="box",
            emitter="directional",
            light='<spectrum type="fluo_illuminant" name="irradiance"><string name="illuminant" value="D65"/></spectrum>',
            shape="rectangle", size=1))
        return np.array(mi.render(scene, seed=3), dtype=np.float64).mean(axis=0)  # (32, 3)

    bil = '<string name="texel_interpolation" value="bilinear"/>'
    ua = render_columns(_textured(uniform_tex["a"])).mean(axis=0)
    ub = render_columns(_textured(uniform_tex["b"])).mean(axis=0)
    u = (np.arange(32) + 0.5) / 32
    wb = np.interp(u, [-0.25, 0.25, 0.75, 1.25], [1.0, 0.0, 1.0, 0.0])  # texel b's weight, repeat wrap
    want = (1 - wb)[:, None] * ua + wb[:, None] * ub
    scale = want.mean()
    errors = {}
    for name, extra in (("nearest", ""), ("bilinear", bil)):
        got = render_columns(_textured(tex, extra))
        errors[name] = float(np.sqrt(np.mean((got - want) ** 2)) / scale)
    with capsys.disabled():
        print(f"\n[{variant}] relative RMSE against the interpolated texels: {errors}")
    # spectral: Monte Carlo noise only (0.030, 0.023, 0.011 at 256, 1024, 4096 spp: 1/√spp);
    # RGB: 8e-4; nearest: 0.83 spectral, 0.58 RGB
    assert errors["bilinear"] < 0.02, errors
    assert errors["nearest"] > 4 * errors["bilinear"], errors
    with pytest.raises(Exception, match='"texel_interpolation" = "cubic"'):
        mi.load_string(_textured(tex, '<string name="texel_interpolation" value="cubic"/>'))


@pytest.mark.parametrize("variant", VARIANTS)
def test22_differentiable_flags_say_where_gradients_flow(variant):
    """Issue 32 finding 14, issue 35: the four dye parameters of a uniform fluo_jung are
    differentiable in every variant: in RGB, λe and s, baked into the reduced matrices,
    carry gradients through the matrices' derivatives (jit_reduced_derivatives; test_fluo_prb
    test05 compares them with central differences). Textured, all four are differentiable
    per texel (test_fluo_prb test04 and test04b): c and Q scale the hit's dye shape, and the
    shape's closed forms (spectral) or reduced matrices and RGB parts (RGB) carry λe and s."""
    mi.set_variant(variant)
    params = mi.traverse(mi.load_dict({"type": "fluo_jung"}))
    for key in ("emission_peak", "stokes_shift", "concentration", "quantum_yield"):
        flags = params.flags(key)
        assert not flags & mi.ParamFlags.NonDifferentiable, (variant, key, flags)
    for name, values in (("emission_peak", (520.0, 560.0)), ("stokes_shift", (60.0, 80.0)),
                         ("concentration", (0.2, 0.6)), ("quantum_yield", (0.5, 0.9))):
        textured = mi.traverse(mi.load_dict({"type": "fluo_jung", name: {
            "type": "checkerboard", "color0": values[0], "color1": values[1]}}))
        keys = [k for k in textured.keys() if k.startswith(name) and k.endswith(".value")]  # (not to_uv)
        assert keys, (variant, name, list(textured.keys()))
        for key in keys:
            assert not textured.flags(key) & mi.ParamFlags.NonDifferentiable, (variant, key)