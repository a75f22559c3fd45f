"""fluo_dye_medium: a Jung-style dye in solution, through the same bispectral medium
interface and fluo_volpath estimator as fluo_qd_medium.

* test01: creation in both variants, parameter errors named.
* test02: a slab of dye over a large flat lamp against the 1-D quadrature reference of
  test_fluo_volpath.py (fed with ``fluo-rs dye-medium``'s spectra).
* test03: Q = 0 under fluo_volpath is native volpath's image.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS

import fluo
from test_fluo_volpath import cube_scene, render, slab_reference, slab_scene

DYE = {"emission_peak": 515.0, "stokes_shift": 25.0, "quantum_yield": 0.9, "sigma_a": 150.0}
#: Inside the dye's absorption and emission support (479-528 nm for these parameters).
BANDS = [(480, 490), (490, 505), (505, 515), (515, 527)]


@pytest.mark.parametrize("variant", VARIANTS)
def test01_create_and_validate(variant):
    mi.set_variant(variant)
    m = mi.load_dict({"type": "fluo_dye_medium", **DYE, "scale": 0.01})
    assert "FluoDyeMedium" in str(m) and "emission_peak = 515 nm" in str(m)
    for name, value in (("quantum_yield", 1.5), ("sigma_a", -1.0), ("emission_peak", 100.0),
                        ("stokes_shift", 0.0), ("scale", -1.0)):
        with pytest.raises(RuntimeError, match=rf"fluo_dye_medium.*{name}"):
            mi.load_dict({"type": "fluo_dye_medium", name: value})


def test02_slab_matches_a_1d_reference():
    mi.set_variant("scalar_spectral")
    tool = fluo.run_tool(["dye-medium", "--json", "--emission-peak", "515", "--stokes-shift", "25",
                          "--quantum-yield", "0.9", "--sigma-a", "150", "--step", "0.1"])
    lamp = {"type": "regular", "wavelength_min": 300, "wavelength_max": 830, "values": "1, 1"}
    medium = {"type": "fluo_dye_medium", **DYE, "scale": 0.01}
    img = render(slab_scene(4096, 2, medium, lamp, bands=BANDS), seed=5)
    got = img.reshape(-1, img.shape[-1]).mean(axis=0)
    want, reemitted = slab_reference(tool, 0.01, 1.0, lambda l: np.ones_like(l), bands=BANDS)
    assert reemitted[2] > 0.1 * want[2] and reemitted[0] == 0.0, (reemitted, want)  # glow around 515 nm
    np.testing.assert_allclose(got, want, rtol=0.03)


def test03_yield_zero_is_volpath():
    mi.set_variant("scalar_spectral")
    plain = {"type": "fluo_dye_medium", **DYE, "quantum_yield": 0.0, "scale": 0.01, "sigma_s": 20.0}
    np.testing.assert_allclose(render(cube_scene("fluo_volpath", plain, res=8, spp=8), seed=3),
                               render(cube_scene("volpath", plain, res=8, spp=8), seed=3), rtol=1e-4, atol=1e-5)
