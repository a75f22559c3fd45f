"""Colour conversions for image comparisons (numpy, vectorised).

The same definitions as the Rust core (``core/src/colour/``, ``core/src/colour/mitsuba.rs``):
linear sRGB uses Mitsuba's ``xyz_to_srgb`` matrix (CIE 1931 based), CIELAB the CIE
1976 formulae with the linear segment below (6/29)³, and CIEDE2000 Sharma, Wu & Dalal
(2005) with kL = kC = kH = 1 (tests/python/test_colour.py checks all 34 of their pairs).
"""

from __future__ import annotations

import numpy as np

#: Mitsuba's XYZ -> linear sRGB matrix (include/mitsuba/core/spectrum.h).
XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535],
                        [-0.969256, 1.875991, 0.041556],
                        [0.055648, -0.204043, 1.057311]])
SRGB_TO_XYZ = np.linalg.inv(XYZ_TO_SRGB)


def srgb_to_xyz(rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB (..., 3) -> XYZ (..., 3)."""
    return np.asarray(rgb, dtype=np.float64) @ SRGB_TO_XYZ.T


def xyz_to_srgb(xyz: np.ndarray) -> np.ndarray:
    """XYZ (..., 3) -> linear sRGB (..., 3)."""
    return np.asarray(xyz, dtype=np.float64) @ XYZ_TO_SRGB.T


def xyz_to_lab(xyz: np.ndarray, white: np.ndarray) -> np.ndarray:
    """CIE 1976 L*a*b* of XYZ (..., 3) relative to a white XYZ (3,)."""
    t = np.asarray(xyz, dtype=np.float64) / np.asarray(white, dtype=np.float64)
    d = 6.0 / 29.0
    f = np.where(t > d**3, np.cbrt(np.maximum(t, 0.0)), t / (3 * d * d) + 4.0 / 29.0)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


def ciede2000(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """CIEDE2000 colour difference of L*a*b* arrays (..., 3)."""
    lab1, lab2 = np.asarray(lab1, np.float64), np.asarray(lab2, np.float64)
    L1, a1, b1 = lab1[..., 0], lab1[..., 1], lab1[..., 2]
    L2, a2, b2 = lab2[..., 0], lab2[..., 1], lab2[..., 2]
    c1, c2 = np.hypot(a1, b1), np.hypot(a2, b2)
    cbar7 = ((c1 + c2) / 2) ** 7
    g = 0.5 * (1 - np.sqrt(cbar7 / (cbar7 + 25.0**7)))
    a1p, a2p = (1 + g) * a1, (1 + g) * a2
    c1p, c2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.where((a1p == 0) & (b1 == 0), 0.0, np.degrees(np.arctan2(b1, a1p)) % 360)
    h2p = np.where((a2p == 0) & (b2 == 0), 0.0, np.degrees(np.arctan2(b2, a2p)) % 360)
    dL, dC = L2 - L1, c2p - c1p
    dh = h2p - h1p
    dh = np.where(dh > 180, dh - 360, np.where(dh < -180, dh + 360, dh))
    dh = np.where(c1p * c2p == 0, 0.0, dh)
    dH = 2 * np.sqrt(c1p * c2p) * np.sin(np.radians(dh / 2))
    Lbar, Cbar = (L1 + L2) / 2, (c1p + c2p) / 2
    hsum = h1p + h2p
    hbar = np.where(c1p * c2p == 0, hsum,
                    np.where(np.abs(h1p - h2p) <= 180, hsum / 2,
                             np.where(hsum < 360, (hsum + 360) / 2, (hsum - 360) / 2)))
    t = (1 - 0.17 * np.cos(np.radians(hbar - 30)) + 0.24 * np.cos(np.radians(2 * hbar))
         + 0.32 * np.cos(np.radians(3 * hbar + 6)) - 0.20 * np.cos(np.radians(4 * hbar - 63)))
    dtheta = 30 * np.exp(-(((hbar - 275) / 25) ** 2))
    rc = 2 * np.sqrt(Cbar**7 / (Cbar**7 + 25.0**7))
    sl = 1 + 0.015 * (Lbar - 50) ** 2 / np.sqrt(20 + (Lbar - 50) ** 2)
    sc = 1 + 0.045 * Cbar
    sh = 1 + 0.015 * Cbar * t
    rt = -np.sin(np.radians(2 * dtheta)) * rc
    return np.sqrt((dL / sl) ** 2 + (dC / sc) ** 2 + (dH / sh) ** 2 + rt * (dC / sc) * (dH / sh))


def delta_e_map(rgb: np.ndarray, reference_rgb: np.ndarray, white_xyz=None) -> np.ndarray:
    """Per-pixel CIEDE2000 between two linear sRGB images (H, W, 3).

    The reference white defaults to the XYZ of the reference image's brightest pixel
    luminance on the D65 white point, Y = max(Y_ref) (a display-referred choice; pass
    ``white_xyz`` to use the illuminant instead)."""
    xyz, ref = srgb_to_xyz(rgb), srgb_to_xyz(reference_rgb)
    if white_xyz is None:
        y = max(float(ref[..., 1].max()), 1e-12)
        white_xyz = np.array([0.95047, 1.0, 1.08883]) * y
    return ciede2000(xyz_to_lab(xyz, white_xyz), xyz_to_lab(ref, white_xyz))
