"""What pyproject.toml cannot say: the compiled parts of the wheel and its data.

``pip wheel .`` (or ``python -m build``) builds a platform wheel with setuptools-rust, tagged
``py3-none-<platform>`` (``AnyPythonWheel``: one file for every CPython >= 3.10):

* ``fluo/libfluo_mitsuba.so`` — the Mitsuba plugin library (the ``fluo-mitsuba`` crate in
  ``mitsuba/``: Rust core + bridge + C++ shims), built with cargo against the ``mitsuba``/``drjit``/``nanobind`` wheels of
  the isolated build environment (``FLUO_PYTHON`` = that environment's Python, see
  build.rs), with run paths relative to the installed package (``FLUO_RPATH=relative``:
  ``$ORIGIN/../mitsuba`` and ``$ORIGIN/../drjit``);
* ``fluo-rs`` — the physics tool (the ``fluo`` crate in ``core/``), installed into the environment's ``bin/``;
* ``fluo/data/{cubes,matrices,scenes}`` — the coefficient cubes, the example matrices and
  the demo scenes, found at run time through ``importlib.resources`` (``fluo.data_dir``).

The developer path (scripts/setup.sh) installs this package editable with
``FLUO_SKIP_RUST=1`` and builds the library with cargo itself (target/release).
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.bdist_wheel import bdist_wheel
from setuptools.command.build_py import build_py
from setuptools_rust import Binding, RustBin, RustExtension
from setuptools_rust.build import build_rust

ROOT = Path(__file__).resolve().parent
#: Package data: fluo/data/<name> <- <repository>/<source>.
DATA = {"cubes": "data/cubes", "matrices": "data/matrices", "scenes": "scenes"}


class BuildPyWithData(build_py):
    """build_py that also copies the repository's data folders into fluo/data/."""

    def run(self) -> None:
        super().run()
        for name, source in DATA.items():
            target = Path(self.build_lib) / "fluo" / "data" / name
            shutil.copytree(ROOT / source, target, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("*.md", "__pycache__"))


class AnyPythonWheel(bdist_wheel):
    """A platform wheel for every CPython: tagged ``py3-none-<platform>``. Nothing in it
    links Python (the plugin library links Mitsuba's and Dr.Jit's libraries, found through
    relative run paths in the installed ``mitsuba``/``drjit`` packages; ``fluo-rs`` is a
    plain executable), so one file serves every Python that Mitsuba 3.8 has wheels for."""

    def get_tag(self):
        _, _, platform = super().get_tag()
        return "py3", "none", platform


class BuildRustPlainName(build_rust):
    """The plugin library keeps its own name in the wheel, ``fluo/libfluo_mitsuba.so``:
    it is not a Python extension module (nothing in it links Python), so it takes no
    interpreter's suffix (setuptools-rust would name it ``*.cpython-311-*.so`` after the
    Python that built the wheel, misleading in a py3-none wheel)."""

    def get_dylib_ext_path(self, ext: RustExtension, target_fname: str) -> str:
        path = Path(super().get_dylib_ext_path(ext, target_fname))
        if ext.binding == Binding.NoBinding and path.name.startswith("libfluo_mitsuba."):
            return str(path.with_name("libfluo_mitsuba.so"))
        return str(path)


def rust_targets() -> list:
    if os.environ.get("FLUO_SKIP_RUST"):
        return []
    # setuptools-rust runs cargo (and rustc -V) with exactly this environment.
    env = dict(os.environ, FLUO_PYTHON=sys.executable, FLUO_RPATH="relative")
    # A target folder of its own: the wheel's library has relative run paths and must
    # not replace the developer build in target/release.
    env.setdefault("CARGO_TARGET_DIR", str(ROOT / "target" / "wheel"))
    return [
        RustExtension("fluo.libfluo_mitsuba", path="mitsuba/Cargo.toml", binding=Binding.NoBinding, env=env,
                      py_limited_api=False),
        RustBin("fluo-rs", path="core/Cargo.toml", env=env),
    ]


setup(rust_extensions=rust_targets(),
      cmdclass={"build_py": BuildPyWithData, "bdist_wheel": AnyPythonWheel, "build_rust": BuildRustPlainName},
      zip_safe=False)
