"""The package's view of where things are, and its version guard.

The end-to-end user path (wheel built, installed into a fresh venv, used from /tmp
without a toolchain) is scripts/wheel_smoke.sh, run by scripts/test.sh.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import fluo

REPO = Path(__file__).resolve().parents[2]


def test01_pins_come_from_the_package_metadata():
    text = (REPO / "pyproject.toml").read_text()
    for name in ("mitsuba", "drjit"):
        pinned = re.search(rf'"{name}==([\w.]+)"', text.split("[project]")[1]).group(1)
        assert fluo.BUILT_FOR[name] == pinned


def test02_another_mitsuba_is_refused_naming_both_versions(monkeypatch):
    import mitsuba

    monkeypatch.setattr(fluo, "BUILT_FOR", {"mitsuba": "9.9.9", "drjit": fluo.BUILT_FOR["drjit"]})
    with pytest.raises(ImportError) as err:
        fluo._check_versions()
    text = str(err.value)
    assert "mitsuba==9.9.9" in text and f"mitsuba {mitsuba.__version__}" in text


def test03_a_checkout_finds_its_own_build_and_data():
    assert fluo.in_checkout()
    assert fluo.library_path() == REPO / "target" / "release" / "libfluo_mitsuba.so"
    assert fluo.tool_path() == REPO / "target" / "release" / "fluo-rs"
    assert fluo.data_dir("cubes") == REPO / "data" / "cubes"
    assert fluo.scenes_dir() == REPO / "scenes"
    assert fluo.out_dir() == REPO / "out"
    with pytest.raises(ValueError, match="unknown data folder"):
        fluo.data_dir("nope")


def test04_the_wheel_carries_every_data_folder_the_package_looks_up():
    # setup.py's DATA must name exactly the folders data_dir() serves, from sources
    # that exist (a renamed folder would ship a wheel without it).
    source = (REPO / "setup.py").read_text()
    data = dict(re.findall(r'"(\w+)": "([\w/]+)"', source.split("DATA =")[1].split("\n")[0]))
    assert set(data) == {"cubes", "matrices", "scenes"}
    for name, folder in data.items():
        assert (REPO / folder).is_dir() and (REPO / folder) == fluo.data_dir(name)
    assert any((REPO / data["cubes"]).glob("*_d65_tinf_r33.cube"))


@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_mono_polarized"])
def test05_other_variants_name_the_plugin_and_the_variant(variant):
    """Every plugin in a variant it does not serve (the mono ones) raises an error naming
    itself, the variant and the variants it runs in (not Mitsuba's 'plugin not found')."""
    import mitsuba as mi

    if variant not in mi.variants():
        pytest.fail(f"the mitsuba wheel lacks variant {variant}")
    mi.set_variant(variant)
    try:
        for name, kind in fluo.PLUGIN_KINDS.items():
            scene = {"type": name} if kind != "texture" else {"type": "diffuse", "reflectance": {"type": name}}
            with pytest.raises(Exception) as err:
                mi.load_dict(scene)
            msg = str(err.value)
            assert f'{name}: not available in variant "{variant}"' in msg, msg
            assert "scalar_rgb" in msg and "scalar_spectral_polarized" in msg
    finally:
        mi.set_variant("scalar_spectral")
