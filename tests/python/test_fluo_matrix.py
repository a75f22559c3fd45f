"""Tests of fluo_matrix (measured reradiation matrices) and the fit-gmm / gmm-report CLI.

References: the measured files themselves, parsed here independently with numpy (the
diagonal the BSDF serves), the single-bounce patch integral of ``fluo patch`` (direct
integration in Rust) that ``fluo_path`` renders must converge to, and the paper's
ΔE2000 figure for 8 Gaussians. Tests that need the shared data skip, with a message,
only when it is absent (``$FLUO_SHARED_DATA`` or ``<repo>/../shared/data``).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS, scene_text, textured_plane, mean_rgb

import fluo

REPO = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("FLUO_SHARED_DATA", REPO.parent / "shared" / "data"))
BISPECTRAL = SHARED / "bispectral"
FILES = sorted(p for p in BISPECTRAL.glob("*") if p.suffix.lower() in (".bfc", ".csv")) \
    if BISPECTRAL.is_dir() else []
needs_shared = pytest.mark.skipif(not FILES, reason=f"shared data not found at {SHARED} "
                                  "(set FLUO_SHARED_DATA)")
#: Our own matrices (generated from fluo_jung materials, see data/matrices/README.md).
OWN = sorted((REPO / "data" / "matrices").glob("*.csv"))
#: The strongest of them (absorbs blue-violet, emits at 610 nm).
ORANGE = REPO / "data" / "matrices" / "jung_orange.csv"


def read_matrix(path: Path):
    """Independent parser: (lambda_i, lambda_o, D[o, i]) from a BFC or CSV file."""
    lines = path.read_text().splitlines()
    if path.suffix.lower() == ".bfc":
        lam_i = np.array(lines[11].split()[1:], float)
        rows = [l.split() for l in lines[12:] if l.strip() and l.strip() != "EOD"]
    else:
        h = next(i for i, l in enumerate(lines) if l.lstrip("# ").lower().startswith("lambda"))
        lam_i = np.array(lines[h].lstrip("# ").split(",")[1:], float)
        rows = [l.split(",") for l in lines[h + 1:] if l.strip() and not l.startswith("#")]
    data = np.array(rows, float)
    return lam_i, data[:, 0], data[:, 1:]


def diagonal(path: Path):
    lam_i, lam_o, d = read_matrix(path)
    lam = [l for l in lam_o if l in lam_i]
    return np.array(lam), np.array([max(d[list(lam_o).index(l), list(lam_i).index(l)], 0.0) for l in lam])


def surface_interaction(wavelengths):
    import drjit as dr
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(0, 0, 1)
    si.n = mi.Vector3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    si.wavelengths = mi.Spectrum(*wavelengths)
    return si


def illuminant_xml(name: str, key: str = "irradiance") -> str:
    return f'<spectrum type="fluo_illuminant" name="{key}"><string name="illuminant" value="{name}"/></spectrum>'


def matrix_xml(path: Path) -> str:
    return f'<bsdf type="fluo_matrix"><string name="filename" value="{path}"/></bsdf>'


def plane_xyz(bsdf: str, illuminant: str, spp=192, seed=1):
    """π·mean XYZ of a plane seen from above under a distant light of unit luminance."""
    mi.set_variant("scalar_spectral")
    scene = mi.load_string(scene_text(
        bsdf, integrator="fluo_path", max_depth=2, camera="orthographic", origin="0, 0, 5",
        spp=spp, width=32, height=32, pixel_format="xyz", rfilter="box", emitter="directional",
        light=illuminant_xml(illuminant), shape="rectangle", size=10))
    img = np.array(mi.render(scene, seed=seed), dtype=np.float64)
    return img.reshape(-1, img.shape[-1])[:, :3].mean(axis=0) * math.pi, scene


def patch(material: Path, illuminant: str):
    return fluo.run_tool(["patch", "--material", str(material), "--illuminant", illuminant,
                          "--cmf", "cie1931"])


# ------------------------------------------------------------------------- tests
@pytest.mark.parametrize("variant", VARIANTS)
def test01_create_and_errors(variant, tmp_path):
    mi.set_variant(variant)
    path = OWN[0]
    b = mi.load_dict({"type": "fluo_matrix", "filename": str(path)})
    assert "FluoMatrix" in str(b) and path.name in str(b)
    assert b.flags() & mi.BSDFFlags.DiffuseReflection
    good = path.read_text().splitlines()
    cases = {
        "truncated.csv": ("\n".join(good[:10]) + "\n3", "truncated"),
        "nan.csv": ("\n".join([good[0], good[1].replace(",", ",nan,", 1)] + good[2:]), "not a finite"),
        "header.csv": ("\n".join(["wavelength,1,2"] + good[1:]), "wrong header"),
        "bad.BFC": ("VEC_01\nnot a BFC file\n", "wrong header"),
    }
    for name, (text, needle) in cases.items():
        f = tmp_path / name
        f.write_text(text)
        with pytest.raises(Exception, match=needle):
            mi.load_dict({"type": "fluo_matrix", "filename": str(f)})
    with pytest.raises(Exception, match="file not found"):
        mi.load_dict({"type": "fluo_matrix", "filename": str(tmp_path / "missing.BFC")})
    with pytest.raises(Exception, match='"filename" is required'):
        mi.load_dict({"type": "fluo_matrix"})


def test02_eval_serves_the_measured_diagonal():
    """Spectral eval = ρ(λ)/π·cos θo with ρ the diagonal, interpolated (numpy reference)."""
    mi.set_variant("scalar_spectral")
    files = (FILES or []) + OWN
    for path in files:
        lam, rho = diagonal(path)
        b = mi.load_dict({"type": "fluo_matrix", "filename": str(path)})
        wl = (385.0, 452.5, 555.0, 731.0)
        si = surface_interaction(wl)
        wo = mi.Vector3f(0.6, 0.0, 0.8)
        got = np.array(b.eval(mi.BSDFContext(), si, wo))
        want = np.interp(wl, lam, rho) / math.pi * 0.8
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7, err_msg=path.name)
        assert b.pdf(mi.BSDFContext(), si, wo) == pytest.approx(0.8 / math.pi, rel=1e-5)


def test03_chi2_directional_sampling(chi2_directions):
    """Pearson chi-square of sampled directions against the pdf (conftest)."""
    mi.set_variant("scalar_spectral")
    b = mi.load_dict({"type": "fluo_matrix", "filename": str(ORANGE)})
    si = surface_interaction((400.0, 500.0, 600.0, 700.0))
    si.wi = mi.Vector3f(0.3, 0.0, math.sqrt(1 - 0.09))
    stat, critical, dof = chi2_directions(b, si, n=20_000, bins_u=8, bins_phi=10, seed=5)
    assert dof > 40
    assert stat < critical, (stat, critical, dof)


@pytest.mark.parametrize("illuminant", ["D65", "A"])
def test04_plane_converges_to_patch_integral(illuminant):
    """fluo_path on a plane of our own matrix = fluo patch of the same file, within 1 %."""
    path = ORANGE
    xyz, _ = plane_xyz(matrix_xml(path), illuminant)
    ref = patch(path, illuminant)
    want, elastic = np.array(ref["xyz"]), np.array(ref["elastic_xyz"])
    np.testing.assert_allclose(xyz, want, rtol=0.01)
    assert want[1] - elastic[1] > 0.03  # fluorescence is ≥ 3 × the tolerance


@needs_shared
@pytest.mark.parametrize("name", ["TEXTYELL.BFC", "postit_yellow.csv"])
def test05_measured_plane_converges_to_patch_integral(name):
    path = BISPECTRAL / name
    xyz, scene = plane_xyz(matrix_xml(path), "D65")
    assert "fluorescent_bsdfs = 1" in str(scene.integrator())
    ref = patch(path, "D65")
    want, elastic = np.array(ref["xyz"]), np.array(ref["elastic_xyz"])
    np.testing.assert_allclose(xyz, want, rtol=0.01)
    assert want[1] - elastic[1] > 0.03, (want, elastic)


@needs_shared
def test06_every_measured_file_loads_fits_and_renders(tmp_path):
    assert len(FILES) == 6, FILES
    for path in FILES:
        out = tmp_path / (path.stem + ".gmm.json")
        info = fluo.run_tool(["fit-gmm", str(path), "--components", "4", "-o", str(out)])
        assert info["components"] == 4 and out.is_file() and info["scale"] > 0
        fit = json.loads(out.read_text())
        assert len(fit["components"]) == 4 and all(len(c["mean"]) == 2 for c in fit["components"])
        for bsdf in (matrix_xml(path),
                     f'<bsdf type="fluo_gmm"><string name="filename" value="{out}"/></bsdf>'):
            mi.set_variant("scalar_spectral")
            scene = mi.load_string(scene_text(bsdf, integrator="fluo_path", fov=60, width=8, height=8,
                                              light=illuminant_xml("D65", "radiance")))
            img = np.array(mi.render(scene), dtype=np.float64)
            assert np.isfinite(img).all() and img.mean() > 0, (path.name, bsdf)


@needs_shared
def test07_gmm_report_meets_the_papers_figure():
    """8 Gaussians: mean ΔE2000 over the measured files under the CIE illuminants ≤ 0.3."""
    r = fluo.run_tool(["gmm-report", "--components", "8"])
    acc = r["acceptance"]
    assert acc["components"] == 8 and acc["threshold"] == 0.3
    assert acc["pass"] and acc["mean_delta_e_cie"] <= 0.3, acc
    assert len(r["materials"]) == 6 and len(r["illuminants"]) >= 20
    for m in r["materials"]:
        f = m["fits"][0]
        assert f["floats_stored"] == 2 * 41 + 1 + 7 * 8
        assert f["bytes_at_render_time"] < m["matrix_bytes_at_render_time"] / 10
        assert f["delta_e_mono"]["mean"] > 0 and len(f["delta_e_per_illuminant"]) == len(r["illuminants"])


def test08_cli_errors():
    with pytest.raises(RuntimeError, match="exactly one matrix file"):
        fluo.run_tool(["fit-gmm", "-o", "/tmp/x.gmm.json"])
    with pytest.raises(RuntimeError, match="components"):
        fluo.run_tool(["fit-gmm", str(OWN[0]), "--components", "0", "-o", "/tmp/x.gmm.json"])
    with pytest.raises(RuntimeError, match="no/such.BFC"):
        fluo.run_tool(["fit-gmm", "/no/such.BFC", "-o", "/tmp/x.gmm.json"])

def test08b_fit_gmm_through_the_python_cli(tmp_path):
    """`fluo fit-gmm X --components K -o Y` (forwarded to fluo-rs) writes a valid fit file."""
    out = tmp_path / "orange.gmm.json"
    proc = subprocess.run([sys.executable, "-m", "fluo", "fit-gmm", str(ORANGE), "--components", "3",
                           "-o", str(out), "--json"], capture_output=True, text=True, check=True)
    info = json.loads(proc.stdout)
    fit = json.loads(out.read_text())
    assert info["components"] == 3 and fit["format"] == "fluo-gmm" and len(fit["components"]) == 3
    assert abs(sum(c["weight"] for c in fit["components"]) - 1) < 1e-9
    assert fit["scale"] == info["scale"] > 0 and fit["source"] == ORANGE.name
    lam, rho = diagonal(ORANGE)
    np.testing.assert_allclose(fit["diagonal"]["values"], rho, rtol=1e-6)


@pytest.mark.parametrize("name", ["fluo_measured.xml", "fluo_measured_uv.xml"])
def test09_demo_scenes_render(name):
    """With the measured materials when the shared data exists, and with our fallbacks."""
    mi.set_variant("scalar_spectral")
    from fluo.scenes import scene_fallback_params
    scene_path = REPO / "scenes" / name
    fallback = scene_fallback_params(scene_path, force=True)
    assert set(fallback) == {"matrix_a", "matrix_b"} and all(Path(p).is_file() for p in fallback.values())
    runs = [fallback]
    if FILES:
        runs.append({"matrix_a": str(BISPECTRAL / "TEXTYELL.BFC"), "matrix_b": str(BISPECTRAL / "CIBA12.BFC")})
    for params in runs:
        scene = mi.load_file(str(scene_path), spp=2, res=24, **params)
        img = np.array(mi.render(scene), dtype=np.float64)
        assert np.isfinite(img).all() and img.mean() > 0
        assert "fluorescent_bsdfs = 3" in str(scene.integrator())


def test10_demo_uses_fallbacks_only_for_missing_data(tmp_path, scene_xml):
    from fluo.scenes import scene_fallback_params
    (tmp_path / "here.csv").write_text("x")
    scene = scene_xml(tmp_path, matrix_xml("$a"), name="s.xml", extra=(
        '<!-- fluo: fallback a=fa.csv -->\n<!-- fluo: fallback b=fb.csv -->\n'
        '<default name="a" value="here.csv"/><default name="b" value="missing.csv"/>'))
    assert scene_fallback_params(scene) == {"b": str(tmp_path / "fb.csv")}


# ----------------------------------------- material-index texture (issue 17), both plugins
MATRICES = REPO / "data" / "matrices"


def index_files(plugin, tmp_path):
    if plugin == "fluo_matrix":
        return [str(MATRICES / "jung_orange.csv"), str(MATRICES / "jung_brightener.csv")]
    second = tmp_path / "brightener.gmm.json"
    fluo.run_tool(["fit-gmm", str(MATRICES / "jung_brightener.csv"), "--components", "4", "-o", str(second)])
    return [str(MATRICES / "jung_orange.gmm.json"), str(second)]


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("plugin", ["fluo_matrix", "fluo_gmm"])
def test11_material_index_checkerboard_renders_as_average(plugin, variant, tmp_path):
    """filename0/filename1 selected by a checkerboard index render as the mean of the two
    single-file materials (spectral shifting; reduced RGB with each file's matrix)."""
    files = index_files(plugin, tmp_path)
    ua = mean_rgb(textured_plane(variant, {"type": plugin, "filename": files[0]}))
    ub = mean_rgb(textured_plane(variant, {"type": plugin, "filename": files[1]}))
    board = {"type": "checkerboard", "color0": 0.0, "color1": 1.0,
             "to_uv": mi.ScalarTransform4f().scale([100, 100, 1])}
    got = mean_rgb(textured_plane(variant, {"type": plugin, "filename0": files[0], "filename1": files[1],
                                           "index": board}))
    want = (ua + ub) / 2
    rtol = 0.012 if "spectral" in variant else 1e-4  # measured 0.14 % / 0
    np.testing.assert_allclose(got, want, rtol=rtol)
    assert np.abs(ua - ub).max() > 8 * rtol * want.max(), (ua, ub)


@pytest.mark.parametrize("variant", VARIANTS)
def test12_material_index_validated_per_texel(variant):
    mi.set_variant(variant)
    files = {"filename0": str(MATRICES / "jung_orange.csv"), "filename1": str(MATRICES / "jung_yellow.csv"),
             "filename2": str(MATRICES / "jung_brightener.csv")}

    def bitmap(values):
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.array(values, dtype=np.float32)), "raw": True,
                "filter_type": "nearest"}

    for values, needle in (([[0, 1], [2, 3]], '"index" = 3 at texel (x = 1, y = 1)'),
                           ([[0, 0.5], [2, 1]], '"index" = 0.5 at texel (x = 1, y = 0)'),
                           ([[float("nan"), 0], [2, 1]], '"index" = NaN at texel (x = 0, y = 0)')):
        with pytest.raises(Exception) as err:
            mi.load_dict({"type": "fluo_matrix", **files, "index": bitmap(values)})
        assert needle in str(err.value) and "whole numbers 0 to 2" in str(err.value), str(err.value)
    ok = mi.load_dict({"type": "fluo_matrix", **files, "index": bitmap([[0, 1], [2, 1]])})
    assert "filename2" in str(ok) and "index" in str(ok)
    with pytest.raises(Exception, match="need a material-index texture"):
        mi.load_dict({"type": "fluo_matrix", **files})
    with pytest.raises(Exception, match="not both"):
        mi.load_dict({"type": "fluo_matrix", "filename": files["filename0"], **files, "index": 0.0})
    with pytest.raises(Exception, match='"filename1" = .*file not found'):
        mi.load_dict({"type": "fluo_matrix", "filename0": files["filename0"], "filename1": "missing.csv",
                      "index": 0.0})
