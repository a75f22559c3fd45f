"""The demo scenes and the demo gallery (``fluo demo``; python/fluo/gallery.py, scenes.py).

* Every ``scenes/*.xml`` uses ``fluo_path`` and is allowed in both scalar variants, or
  (fluorescent media) ``fluo_volpath`` in ``scalar_spectral`` only, which ``scalar_rgb``
  refuses with a clear error; it renders (1 spp, tiny film) to finite pixels in each
  allowed variant, with and without fluorescence.
* The gallery of two scenes, rendered small into ``tmp_path``, writes its files; the
  figure has one row per scene and one column per panel; ``index.html`` names every
  scene; and each scene's "without fluorescence" panel differs from its spectral panel
  by more than Monte Carlo noise alone explains (threshold below).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS

import fluo
from fluo import gallery, scenes
from fluo.scenes import scene_fallback_params, scene_variants

SCENES = sorted((fluo.repo_root() / "scenes").glob("*.xml"))
#: The gallery test's scenes: the newcomer's first scene (daylight, fluorescence a
#: colour shift on three of four spheres) and the UV-lamp scene (fluorescence is
#: nearly all the light).
GALLERY_SCENES = ("jung_spheres.xml", "fluo_path_uv.xml")
#: Film and samples for the gallery test: small, but enough samples that the noise
#: floor (mean ΔE00 between two spectral renders) is well under the signal (measured:
#: 0.4-0.7 at 24 px and 1024 spp, against about 2 for daylight fluorescence).
GALLERY_RES, GALLERY_SPP = 20, 1024
#: How far, in mean ΔE00 over the whole frame, "without fluorescence" must differ from
#: spectral beyond the noise floor: 1 is about one just-noticeable difference (CIEDE2000
#: was scaled so that 1 is near the threshold of perception). It is a mean over every
#: pixel, the floor and background included, where fluorescence changes little; the
#: fluorescent spheres themselves differ by 10 and more (the maps' p95).
MIN_DE_ABOVE_NOISE = 1.0


def test01_scenes_exist():
    assert len(SCENES) >= 7, SCENES


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.name)
def test02_scene_uses_fluo_path_in_both_variants(scene):
    text = scenes.resolve(scene, scene_fallback_params(scene))
    integrators = re.findall(r'<integrator\s+type="([^"]+)"', text)
    materials = scenes.fluorescent_materials(text)
    assert materials, "a demo scene should show fluorescence"
    if any(m in scenes.FLUORESCENT_MEDIA for m in materials):
        # Fluorescent media: fluo_volpath (wavelength shifting in scalar_spectral, reduced
        # transport in scalar_rgb).
        assert integrators == ["fluo_volpath"], integrators
    else:
        assert integrators == ["fluo_path"], integrators
    assert scene_variants(scene) == VARIANTS


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.name)
def test03_scene_renders_in_both_variants(scene, variant):
    params = {**scene_fallback_params(scene), "res": 8, "spp": 1}
    text = scenes.resolve(scene, params)
    mi.set_variant(variant)
    if variant not in scene_variants(scene):
        # Refused with a clear error, never rendered without its fluorescence.
        with pytest.raises(RuntimeError, match="scalar_rgb"):
            mi.render(scenes.load(text, scene.parent), spp=1, seed=0)
        return
    for version in (text, scenes.without_fluorescence(text, scene.parent)):
        image = np.array(mi.render(scenes.load(version, scene.parent), spp=1, seed=0))
        assert image.ndim == 3 and image.shape[2] >= 3
        assert np.all(np.isfinite(image))


def test04_without_fluorescence_rewrites():
    text = ('<bsdf type="fluo_jung"><float name="concentration" value="1"/></bsdf>'
            '<bsdf type="fluo_qd"><float name="quantum_yield" value="0.9"/></bsdf>'
            '<bsdf type="fluo_jung"><texture type="checkerboard" name="quantum_yield">'
            '<float name="color0" value="0.2"/><float name="color1" value="0.9"/></texture></bsdf>'
            '<bsdf type="fluo_jung"><rgb name="color" value="0.1, 0.9, 0.1"/>'
            '<boolean name="fluorescence" value="true"/></bsdf>'
            '<bsdf type="fluo_gmm"><string name="filename" value="../data/matrices/jung_orange.gmm.json"/></bsdf>'
            '<bsdf type="fluo_matrix"><string name="filename" value="../data/matrices/jung_yellow.csv"/></bsdf>')
    out = scenes.without_fluorescence(text, fluo.repo_root() / "scenes")
    assert out.count('<float name="quantum_yield" value="0"/>') == 3 and "checkerboard" not in out
    assert '<boolean name="fluorescence" value="false"/>' in out
    assert scenes.fluorescent_materials(out) == ["fluo_jung", "fluo_qd", "fluo_jung", "fluo_jung"]
    assert out.count('<bsdf type="diffuse"><spectrum name="reflectance"') == 2
    medium = ('<medium type="fluo_qd_medium" id="dots"><float name="radius" value="2"/></medium>'
              '<medium type="fluo_qd_medium"><float name="quantum_yield" value="0.8"/></medium>')
    out = scenes.without_fluorescence(medium, fluo.repo_root() / "scenes")
    assert scenes.fluorescent_materials(medium) == ["fluo_qd_medium", "fluo_qd_medium"]
    assert out.count('<float name="quantum_yield" value="0"/>') == 2 and 'value="0.8"' not in out
    assert '<medium type="fluo_qd_medium" id="dots">' in out
    # several files behind an index texture: a clear error (the gallery notes it in the panel)
    several = ('<bsdf type="fluo_matrix"><string name="filename0" value="a.csv"/>'
               '<string name="filename1" value="b.csv"/></bsdf>')
    with pytest.raises(RuntimeError, match="filename0..N"):
        scenes.without_fluorescence(several, fluo.repo_root() / "scenes")


@pytest.fixture(scope="module")
def gallery_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("gallery")
    paths = [fluo.repo_root() / "scenes" / name for name in GALLERY_SCENES]
    readme = out / "docs" / "gallery.png"
    rows = gallery.run(paths, out, GALLERY_SPP, res=GALLERY_RES, readme=readme, log=print)
    return out, rows, readme


def test05_gallery_writes_its_files(gallery_run):
    out, rows, readme = gallery_run
    assert [r.scene for r in rows] == list(GALLERY_SCENES)
    for name in ("gallery.png", "index.html", "gallery.json"):
        assert (out / name).is_file(), name
    assert readme.is_file()
    for scene in GALLERY_SCENES:
        stem = Path(scene).stem
        for key in ("scalar_spectral", "scalar_rgb", "no_fluorescence"):
            for ext in (".exr", ".png"):
                assert (out / f"{stem}_{key}{ext}").is_file(), f"{stem}_{key}{ext}"
        assert (out / f"{stem}_de00.png").is_file()
    for row in rows:
        assert not row.failed, row.panels
        for key in ("scalar_spectral", "scalar_rgb", "no_fluorescence"):
            panel = row.panels[key]
            assert panel.seconds is not None and panel.seconds > 0
            assert panel.image.shape == (GALLERY_RES, GALLERY_RES, 3)
            assert np.all(np.isfinite(panel.image))


def test06_gallery_png_has_a_row_per_scene_and_a_column_per_panel(gallery_run):
    out, rows, readme = gallery_run
    mi.set_variant("scalar_rgb")
    image = np.array(mi.Bitmap(str(out / "gallery.png")))
    height, width = gallery.gallery_size(len(rows))
    assert image.shape[:2] == (height, width)
    assert width == len(gallery.PANELS) * round(gallery.CELL_IN * gallery.DPI)
    small = np.array(mi.Bitmap(str(readme)))
    assert small.shape[1] == gallery.README_WIDTH_PX
    assert small.shape[0] == round(height * gallery.README_WIDTH_PX / width)


def test07_index_html_references_every_scene(gallery_run):
    out, rows, _ = gallery_run
    page = (out / "index.html").read_text(encoding="utf-8")
    assert 'src="gallery.png"' in page
    for scene in GALLERY_SCENES:
        stem = Path(scene).stem
        assert scene in page
        for key in ("scalar_spectral", "scalar_rgb", "no_fluorescence", "de00"):
            assert f'src="{stem}_{key}.png"' in page
    summary = json.loads((out / "gallery.json").read_text(encoding="utf-8"))
    assert [s["scene"] for s in summary["scenes"]] == list(GALLERY_SCENES)


def test08_fluorescence_is_visible_above_noise(gallery_run):
    _, rows, _ = gallery_run
    for row in rows:
        assert row.fluorescent
        assert row.noise_de is not None and row.mean_de is not None
        assert row.mean_de > row.noise_de + MIN_DE_ABOVE_NOISE, (
            f"{row.scene}: mean ΔE00 {row.mean_de:.2f} vs noise floor {row.noise_de:.2f}")


def test09_progress_bar(tmp_path):
    path = tmp_path / "bar.txt"
    with path.open("w") as stream:
        bar = gallery.Progress(4, stream)
        bar.show("start")
        for i in range(4):
            bar.step(f"step {i}")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("[" + "-" * gallery.Progress.WIDTH + "] 0/4")
    assert lines[-1].startswith("[" + "#" * gallery.Progress.WIDTH + "] 4/4 step 3")


#: For every other scene: how far the map's 95th percentile must exceed the noise
#: floor's (two just-noticeable differences on at least a twentieth of the frame beyond
#: what noise reaches). A frame mean would miss upsample_acescg, where only the
#: out-of-gamut patches fluoresce (measured at 20 px, 1024 spp: p95 4.9 against a noise
#: p95 of 1.9; the spheres' scenes 10-50 against 1.5-4).
MIN_P95_ABOVE_NOISE = 2.0


@pytest.mark.parametrize("name", sorted(p.name for p in (fluo.repo_root() / "scenes").glob("*.xml")
                                        if p.name not in GALLERY_SCENES))
def test10_every_scene_shows_its_fluorescence(name, tmp_path):
    rows = gallery.run([fluo.repo_root() / "scenes" / name], tmp_path, GALLERY_SPP, res=GALLERY_RES,
                       log=lambda m: None, progress_stream=open(os.devnull, "w"))
    (row,) = rows
    assert row.fluorescent and not row.failed, row.panels
    assert row.p95_de > row.noise_p95 + MIN_P95_ABOVE_NOISE, (
        f"{name}: p95 ΔE00 {row.p95_de:.2f} vs noise floor p95 {row.noise_p95:.2f}")
