"""Shared fixtures for the Python/Mitsuba tests.

Nothing is skipped: if ``libfluo.so`` is missing or fails to load, every test errors
with the loader's message (run ``bash scripts/setup.sh``).

Fixtures:

``render``
    ``render(scene, variant, spp, seed=0, **params) -> np.ndarray`` (H, W, C) float32;
    ``scene`` is a scene dict (``mi.load_dict``) or an XML path (``mi.load_file``,
    ``params`` substituted for ``$name``). Sets the variant; the fluo plugins are
    registered for both scalar variants, so tests may switch variants freely.
``fluo_cli``
    The ``fluo`` console script installed in this interpreter's environment.
``scene_xml``
    ``scene_xml(tmp_path, bsdf_xml, ...) -> Path``: a small XML test scene (a sphere
    with the given BSDF under a constant environment) written to a file; ``extra``
    goes first in ``<scene>`` (``<default>`` parameters, comments).
``mitsuba_log``
    The list of lines Mitsuba's logger writes while the test runs (warnings included).
"""

from __future__ import annotations

import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

#: Variants the fluo plugins are registered for.
VARIANTS = ("scalar_spectral", "scalar_rgb")


@pytest.fixture(scope="session", autouse=True)
def fluo_module():
    """Import ``fluo`` (loading libfluo.so) once; fail loudly if that is impossible."""
    try:
        import fluo
    except ImportError as err:
        pytest.fail(f"cannot import fluo: {err}", pytrace=False)
    return fluo


def _render(scene, variant: str, spp: int, seed: int = 0, **params) -> np.ndarray:
    mi.set_variant(variant)
    if isinstance(scene, dict):
        if params:
            raise TypeError("params are only substituted into XML scenes")
        loaded = mi.load_dict(scene)
    else:
        loaded = mi.load_file(str(scene), **params)
    image = np.array(mi.render(loaded, spp=spp, seed=seed), dtype=np.float32)
    return image


@pytest.fixture
def render():
    """``render(scene_dict_or_path, variant, spp, seed=0, **params)`` -> numpy image."""
    return _render


@pytest.fixture(scope="session")
def fluo_cli() -> Path:
    script = Path(sys.executable).parent / "fluo"
    if not script.is_file():
        pytest.fail(f"console script {script} missing; run bash scripts/setup.sh "
                    "(pip install -e . into the venv)", pytrace=False)
    return script


SCENE_TEMPLATE = """<scene version="3.0.0">
    {extra}
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world">
            <lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="{width}"/>
            <integer name="height" value="{height}"/>
        </film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
    <shape type="sphere">
        {bsdf}
    </shape>
</scene>
"""


def _scene_xml(directory: Path, bsdf: str, *, width: int = 16, height: int = 12,
               extra: str = "", name: str = "scene.xml") -> Path:
    path = Path(directory) / name
    path.write_text(SCENE_TEMPLATE.format(bsdf=bsdf, width=width, height=height,
                                          extra=extra), encoding="utf-8")
    return path


@pytest.fixture
def scene_xml():
    """``scene_xml(directory, bsdf_xml, width=16, height=12, extra="", name=...)``."""
    return _scene_xml


class _LogLines(mi.Appender):
    """A Mitsuba log appender that keeps the lines."""

    def __init__(self):
        super().__init__()
        self.lines: list[str] = []

    def append(self, level, text):
        self.lines.append(text)

    def log_progress(self, *args):
        pass


@pytest.fixture
def mitsuba_log():
    catch = _LogLines()
    mi.logger().add_appender(catch)
    try:
        yield catch.lines
    finally:
        mi.logger().remove_appender(catch)
