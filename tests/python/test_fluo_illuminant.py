"""Tests of fluo_illuminant, the spectrally defined light (a CIE illuminant or a
``nm,value`` CSV) that reaches below the camera's 360 nm and, in scalar_rgb, feeds
fluo_path's reduced transport.

References: the CSV file's own values, Mitsuba's CIE 1931 ȳ (the luminance
normalisation), and Mitsuba's own spectrum → sRGB conversion of the same values.
"""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS

REPO = Path(__file__).resolve().parents[2]
UV_LAMP = REPO / "scenes" / "spectra" / "uv_lamp_365.csv"
#: The spectral variants of the run (conftest.VARIANTS: scalar here, llvm in test_variants.py).
SPECTRAL = [v for v in VARIANTS if "spectral" in v]


def _eval(tex, wavelengths):
    """The texture at the given wavelengths (four at a time, Mitsuba's spectrum size)."""
    out = []
    wl = list(wavelengths)
    for i in range(0, len(wl), 4):
        chunk = (wl[i:i + 4] + [wl[i]] * 4)[:4]
        si = mi.SurfaceInteraction3f()
        si.wavelengths = mi.Spectrum(*[float(x) for x in chunk])
        out.extend(np.array(tex.eval(si)).ravel()[:len(wl[i:i + 4])])
    return np.array(out)


@pytest.mark.parametrize("variant", SPECTRAL)
def test01_cie_illuminant_is_luminance_normalised(variant):
    mi.set_variant(variant)
    tex = mi.load_dict({"type": "fluo_illuminant", "illuminant": "d65", "scale": 2.0})
    lo, hi = tex.wavelength_range()
    assert (lo, hi) == (300, 830)
    lam = np.arange(360.0, 831.0, 1.0)
    values = _eval(tex, lam)
    ybar = np.array([mi.cie1931_y(float(x)) for x in lam], dtype=np.float64).ravel()
    # ∫ I ȳ / ∫ ȳ over the camera's range = scale (the normalisation fluo_illuminant promises)
    assert np.sum(values * ybar) / np.sum(ybar) == pytest.approx(2.0, rel=2e-3)
    assert np.all(_eval(tex, [300.0, 320.0]) > 0)  # the UV end is there for fluorescence


@pytest.mark.parametrize("variant", SPECTRAL)
def test02_file_lamp_follows_its_csv(variant):
    mi.set_variant(variant)
    tex = mi.load_dict({"type": "fluo_illuminant", "filename": str(UV_LAMP), "normalize": False})
    data = np.loadtxt(UV_LAMP, delimiter=",", comments="#", skiprows=3)
    lam, want = data[:, 0], data[:, 1]
    np.testing.assert_allclose(_eval(tex, lam), want, rtol=1e-5)
    mid = 0.5 * (lam[:-1] + lam[1:])
    np.testing.assert_allclose(_eval(tex, mid), 0.5 * (want[:-1] + want[1:]), rtol=1e-5)
    assert np.all(_eval(tex, [400.0, 600.0]) == 0)  # nothing outside the file's range


def test03_rgb_value_is_mitsubas_conversion_clipped():
    # In scalar_rgb the light is its linear sRGB (Mitsuba's conversion of the same
    # spectrum); the violet lamp's negative green is clipped to 0.
    mi.set_variant("scalar_spectral")
    spectral = mi.load_dict({"type": "fluo_illuminant", "illuminant": "A"})
    lam = np.arange(360.0, 831.0, 1.0)
    values = _eval(spectral, lam)
    want = np.array(mi.spectrum_list_to_srgb(list(lam), list(values), bounded=False))
    mi.set_variant("scalar_rgb")
    rgb = np.array(mi.load_dict({"type": "fluo_illuminant", "illuminant": "A"}).eval(mi.SurfaceInteraction3f()))
    np.testing.assert_allclose(rgb, want, rtol=5e-3)
    uv = np.array(mi.load_dict({"type": "fluo_illuminant", "filename": str(UV_LAMP), "normalize": False})
                  .eval(mi.SurfaceInteraction3f()))
    assert np.all(uv >= 0) and uv[2] > 0


@pytest.mark.parametrize("bad, needle", [
    ({"illuminant": "D99"}, "illuminant"),
    ({"illuminant": "A", "scale": -1.0}, "scale"),
    ({}, "exactly one"),
    ({"filename": "/no/such.csv"}, "no/such.csv"),
])
def test04_bad_input_names_the_parameter(bad, needle):
    mi.set_variant("scalar_spectral")
    with pytest.raises(Exception, match=needle):
        mi.load_dict({"type": "fluo_illuminant", **bad})


@pytest.mark.parametrize("grid", ["uniform", "irregular"])
@pytest.mark.parametrize("variant", SPECTRAL)
def test05_spectral_evaluation_is_the_tabulated_spectrum(tmp_path, grid, variant):
    """In scalar_spectral the light is evaluated per sample by Mitsuba's own regular or
    irregular spectrum built from the Rust nodes: the file's values at its nodes, the
    linear interpolant between them, zero outside, on either kind of grid."""
    mi.set_variant(variant)
    lam = np.linspace(320.0, 700.0, 39) if grid == "uniform" else np.array([320.0, 321.5, 340.0, 410.25, 555.0, 700.0])
    val = 1.0 + np.sin(lam / 37.0) ** 2
    f = tmp_path / "lamp.csv"
    f.write_text("nm,value\n" + "\n".join(f"{float(a)!r},{float(b)!r}" for a, b in zip(lam, val)))
    tex = mi.load_dict({"type": "fluo_illuminant", "filename": str(f), "normalize": False, "scale": 3.0})
    np.testing.assert_allclose(_eval(tex, lam), 3.0 * val, rtol=1e-6)
    mid = 0.5 * (lam[:-1] + lam[1:])
    np.testing.assert_allclose(_eval(tex, mid), 1.5 * (val[:-1] + val[1:]), rtol=1e-6)
    assert np.all(_eval(tex, [319.9, 700.1, 830.0]) == 0)
