"""The numpy colour helpers (python/fluo/colour.py) against published data."""

from pathlib import Path

import numpy as np

from fluo.colour import SRGB_TO_XYZ, ciede2000, xyz_to_lab, xyz_to_srgb

# Sharma, Wu & Dalal (2005), Table 1: L1, a1, b1, L2, a2, b2, ΔE00 (the file names its
# source; core/src/colour/ reads the same file).
SHARMA_2005 = np.loadtxt(Path(__file__).resolve().parents[1] / "data" / "ciede2000_sharma2005.csv",
                         delimiter=",", comments="#", skiprows=5)


def test01_ciede2000_all_34_sharma_pairs():
    got = ciede2000(SHARMA_2005[:, 0:3], SHARMA_2005[:, 3:6])
    np.testing.assert_allclose(got, SHARMA_2005[:, 6], atol=5e-5)
    # symmetric
    np.testing.assert_allclose(ciede2000(SHARMA_2005[:, 3:6], SHARMA_2005[:, 0:3]), got, atol=1e-9)


def test02_lab_white_and_round_trip():
    white = np.array([0.95047, 1.0, 1.08883])
    np.testing.assert_allclose(xyz_to_lab(white, white), [100, 0, 0], atol=1e-9)
    rgb = np.array([0.2, 0.5, 0.9])
    np.testing.assert_allclose(xyz_to_srgb(SRGB_TO_XYZ @ rgb), rgb, atol=1e-12)
