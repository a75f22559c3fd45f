#!/usr/bin/env python3
"""Generate the small spectral tables embedded in the `fluo` crate (`data/spectra/`).

Run once, by hand, in a throwaway virtual environment:

    python3 -m venv /tmp/cs && /tmp/cs/bin/pip install colour-science
    /tmp/cs/bin/python tools/gen_spectral_data.py

Every file starts with `#` comment lines naming the colour-science version and the
dataset key it came from, then one header line, then comma-separated rows. Numbers
are written with Python's shortest round-trip `repr`, i.e. exactly the values
colour-science ships (the CIE tables' own digits), with no rounding added here.

Files written (all on their native CIE grids, wavelengths in nm):
- cie1931_2deg.csv   CIE 1931 2 degree XYZ CMFs, 360-830 nm, 1 nm      (nm,x,y,z)
- cie2006_2deg.csv   CIE 2006 ("2015" in colour) 2 degree XYZ CMFs, 390-830 nm, 1 nm (nm,x,y,z)
- daylight_basis.csv CIE daylight basis S0, S1, S2, 300-830 nm, 5 nm  (nm,s0,s1,s2)
- illuminants.csv    tabulated CIE illuminants, long format            (name,nm,value)
                     D65 300-780 nm at 5 nm (the CIE 15:2004 table that colour ships),
                     FL1..FL12 and HP1..HP5 380-780 nm at 5 nm.
Illuminant A (from its defining formula), E (constant) and the D series other than
D65 (from the daylight basis) are computed in Rust and are not written here.
"""

import os
import warnings

warnings.filterwarnings("ignore")

import colour  # noqa: E402
from colour.colorimetry.datasets.illuminants.sds_d_illuminant_series import (  # noqa: E402
    SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES,
)

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "data", "spectra")
VERSION = colour.__version__


def fmt(v):
    """Shortest exact decimal form of a float; integers keep no trailing '.0'."""
    v = float(v)
    if v == int(v) and abs(v) < 1e9:
        return str(int(v))
    return repr(v)


def write(name, comments, header, rows):
    path = os.path.join(OUT, name)
    with open(path, "w", newline="\n") as f:
        for c in comments:
            f.write(f"# {c}\n")
        f.write(header + "\n")
        for row in rows:
            f.write(",".join(fmt(v) if not isinstance(v, str) else v for v in row) + "\n")
    print(f"wrote {path} ({os.path.getsize(path)} bytes)")


def write_cmfs(name, key, title):
    cmfs = colour.MSDS_CMFS[key]
    rows = [[w, *vals] for w, vals in zip(cmfs.wavelengths, cmfs.values)]
    write(
        name,
        [title, f"source: colour-science {VERSION}, colour.MSDS_CMFS[\"{key}\"]",
         f"grid: {cmfs.shape.start:g}-{cmfs.shape.end:g} nm, step {cmfs.shape.interval:g} nm"],
        "nm,x,y,z",
        rows,
    )


def main():
    os.makedirs(OUT, exist_ok=True)
    write_cmfs("cie1931_2deg.csv", "CIE 1931 2 Degree Standard Observer",
               "CIE 1931 2 degree standard observer, XYZ colour matching functions")
    write_cmfs("cie2006_2deg.csv", "CIE 2015 2 Degree Standard Observer",
               "CIE 2006 (CIE 170-2:2015) 2 degree XYZ colour matching functions")

    basis = SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES
    s0, s1, s2 = basis["S0"], basis["S1"], basis["S2"]
    assert list(s0.wavelengths) == list(s1.wavelengths) == list(s2.wavelengths)
    write(
        "daylight_basis.csv",
        ["CIE daylight basis functions S0, S1, S2 (CIE 015:2018)",
         f"source: colour-science {VERSION}, "
         "colour.colorimetry.datasets.illuminants.sds_d_illuminant_series."
         "SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES[\"S0\", \"S1\", \"S2\"]",
         f"grid: {s0.shape.start:g}-{s0.shape.end:g} nm, step {s0.shape.interval:g} nm"],
        "nm,s0,s1,s2",
        [[w, a, b, c] for w, a, b, c in zip(s0.wavelengths, s0.values, s1.values, s2.values)],
    )

    names = ["D65"] + [f"FL{i}" for i in range(1, 13)] + [f"HP{i}" for i in range(1, 6)]
    rows = []
    for n in names:
        sd = colour.SDS_ILLUMINANTS[n]
        rows += [[n, w, v] for w, v in zip(sd.wavelengths, sd.values)]
    write(
        "illuminants.csv",
        ["Tabulated CIE standard illuminants, relative spectral power distributions as tabulated by the CIE",
         f"source: colour-science {VERSION}, colour.SDS_ILLUMINANTS[name] for name in "
         + ", ".join(names),
         "grids: D65 300-780 nm, FL*/HP* 380-780 nm, all at 5 nm (CIE 15:2004 tables)",
         "long format: one row per (illuminant, wavelength); rows of one illuminant are contiguous"],
        "name,nm,value",
        rows,
    )


if __name__ == "__main__":
    main()
