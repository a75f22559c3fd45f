"""Fluorescent (bispectral) materials for Mitsuba 3.

Importing this package loads the plugin library ``libfluo_mitsuba.so`` (Rust physics
plus the C++ Mitsuba shims). Its static initialiser registers every plugin in :data:`PLUGINS`
with Mitsuba's plugin manager for both ``scalar_rgb`` and ``scalar_spectral``, so
``mi.set_variant(...)`` may be called before or after ``import fluo``::

    import mitsuba as mi
    import fluo

    mi.set_variant("scalar_spectral")
    scene = mi.load_file("scenes/jung_spheres.xml")

Where things are found (environment variables win), from a wheel (``pip install``)
and from a checkout (the editable developer install of scripts/setup.sh):

============== ================== ============================ ==============================================
what           variable           wheel                        checkout
============== ================== ============================ ==============================================
plugin library ``FLUO_LIBRARY``   ``fluo/libfluo_mitsuba*.so`` ``<repo>/target/release/libfluo_mitsuba.so``
physics tool   ``FLUO_TOOL``      ``<env>/bin/fluo-rs``        ``<repo>/target/release/fluo-rs``
cubes          ``FLUO_CUBE_DIR``  ``fluo/data/cubes``          ``<repo>/data/cubes``
scenes                            ``fluo/data/scenes``         ``<repo>/scenes``
============== ================== ============================ ==============================================

Importing against another Mitsuba than the one the library was built for raises an
``ImportError`` naming both versions (``BUILT_FOR``).
"""

from __future__ import annotations

# Must come first: libfluo_mitsuba.so resolves its Mitsuba symbols against the libmitsuba.so
# that the wheel loads on import.
import mitsuba  # noqa: F401  (imported for its side effect)

import ctypes
import importlib.metadata
import importlib.resources
import json
import os
import re
import subprocess
import sysconfig
from pathlib import Path

__all__ = [
    "BUILT_FOR",
    "JIT_PLUGINS",
    "PLUGINS",
    "PLUGIN_KINDS",
    "data_dir",
    "in_checkout",
    "library_path",
    "out_dir",
    "repo_root",
    "run_tool",
    "scenes_dir",
    "tool_path",
]

#: Environment variable overriding the plugin library location.
LIBRARY_ENV = "FLUO_LIBRARY"
#: Environment variable overriding the ``fluo-rs`` tool location.
TOOL_ENV = "FLUO_TOOL"

_PACKAGE = Path(__file__).resolve().parent


def _pins() -> dict[str, str]:
    """The exact ``mitsuba``/``drjit`` versions this package requires (pyproject.toml,
    read back from the installed metadata: the one place the pins are written)."""
    pins = {}
    try:
        requires = importlib.metadata.requires("fluo") or []
    except importlib.metadata.PackageNotFoundError:
        requires = []
    for req in requires:
        m = re.fullmatch(r"\s*(mitsuba|drjit)\s*==\s*([\w.]+)\s*", req)
        if m:
            pins[m.group(1)] = m.group(2)
    return pins


#: The Mitsuba and Dr.Jit versions the plugin library is built for (``libfluo_mitsuba.so`` is
#: compiled against exactly these wheels' headers and ABI).
BUILT_FOR: dict[str, str] = _pins()


def in_checkout() -> bool:
    """Whether this package runs from a source checkout (editable developer install)
    rather than from an installed wheel."""
    return (_PACKAGE.parents[1] / "Cargo.toml").is_file() and not any(_PACKAGE.glob("libfluo_mitsuba*.so"))


def repo_root() -> Path:
    """The repository root of a checkout (``python/fluo/__init__.py`` is two levels
    below it). From a wheel there is none: use :func:`data_dir`, :func:`scenes_dir`
    and :func:`out_dir` for what a checkout would provide."""
    return _PACKAGE.parents[1]


_SETUP_HINT = ("run the setup command in README.md (bash scripts/setup.sh)" if in_checkout()
               else "reinstall the fluo wheel")


def data_dir(name: str) -> Path:
    """A data folder shipped with fluo: ``cubes``, ``matrices`` or ``scenes``
    (``fluo/data/<name>`` in a wheel; ``data/<name>``, or ``scenes``, in a checkout)."""
    if name not in ("cubes", "matrices", "scenes"):
        raise ValueError(f"unknown data folder {name!r}: one of cubes, matrices, scenes")
    packaged = Path(str(importlib.resources.files("fluo") / "data" / name))
    if packaged.is_dir():
        return packaged
    return repo_root() / ("scenes" if name == "scenes" else f"data/{name}")


def scenes_dir() -> Path:
    """The demo scenes (:func:`data_dir` ``("scenes")``)."""
    return data_dir("scenes")


def out_dir() -> Path:
    """Where ``fluo demo``/``bench`` write by default: ``<repo>/out`` in a checkout, else
    ``./out`` (the working directory)."""
    return repo_root() / "out" if in_checkout() else Path.cwd() / "out"


def library_path() -> Path:
    """Path of the plugin library: ``$FLUO_LIBRARY``, the wheel's ``fluo/libfluo_mitsuba*.so``, or
    ``<repo>/target/release/libfluo_mitsuba.so``."""
    override = os.environ.get(LIBRARY_ENV)
    if override:
        return Path(override).expanduser().resolve()
    packaged = sorted(_PACKAGE.glob("libfluo_mitsuba*.so"))
    if packaged:
        return packaged[0]
    return repo_root() / "target" / "release" / "libfluo_mitsuba.so"


def tool_path() -> Path:
    """Path of the ``fluo-rs`` physics tool: ``$FLUO_TOOL``, the environment's
    ``bin/fluo-rs`` (installed with the wheel), or ``<repo>/target/release/fluo-rs``."""
    override = os.environ.get(TOOL_ENV)
    if override:
        return Path(override).expanduser().resolve()
    if not in_checkout():
        return Path(sysconfig.get_path("scripts")) / "fluo-rs"
    return repo_root() / "target" / "release" / "fluo-rs"


def _check_versions() -> None:
    """Refuse a Mitsuba/Dr.Jit other than the pinned ones before loading the library
    (a mismatched libmitsuba.so fails to load, or worse, loads and renders wrongly)."""
    import drjit

    have = {"mitsuba": mitsuba.__version__, "drjit": drjit.__version__}
    wrong = {k: v for k, v in have.items() if k in BUILT_FOR and BUILT_FOR[k] != v}
    if wrong:
        built = ", ".join(f"{k}=={BUILT_FOR[k]}" for k in sorted(BUILT_FOR))
        found = ", ".join(f"{k} {v}" for k, v in sorted(wrong.items()))
        raise ImportError(
            f"fluo's plugin library is built for {built}, but this Python has {found}: "
            f"install those exact versions (pip install {built.replace(', ', ' ')})"
        )


def run_tool(args: list[str]) -> dict:
    """Run ``fluo-rs <args> --json`` and return its stdout parsed as one JSON object.

    Raises ``FileNotFoundError`` if the tool is not built, and ``RuntimeError``
    (carrying the tool's stderr) if it exits non-zero or prints something that is
    not a JSON object.
    """
    tool = tool_path()
    if not tool.is_file():
        raise FileNotFoundError(f"fluo-rs not found at {tool}; {_SETUP_HINT}")
    cmd = [str(tool), *map(str, args), "--json"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    except OSError as err:  # not executable, not a program
        raise RuntimeError(f"cannot run fluo-rs at {tool}: {err.strerror or err}") from err
    if proc.returncode != 0:
        raise RuntimeError(
            f"{' '.join(cmd)} exited with status {proc.returncode}:\n{proc.stderr.strip()}"
        )
    try:
        result = json.loads(proc.stdout)
    except json.JSONDecodeError as err:
        raise RuntimeError(
            f"{' '.join(cmd)} printed invalid JSON ({err}); stdout starts with "
            f"{proc.stdout[:200]!r}; stderr:\n{proc.stderr.strip()}"
        ) from err
    if not isinstance(result, dict):
        raise RuntimeError(
            f"{' '.join(cmd)} printed JSON {type(result).__name__}, expected an object"
        )
    return result


def _load_library() -> ctypes.CDLL:
    """Load ``libfluo_mitsuba.so`` globally; a second call (or a module reload) is a no-op."""
    handle = globals().get("_LIBRARY")
    if handle is not None:
        return handle
    _check_versions()
    # The Rust side finds the shipped cubes through FLUO_CUBE_DIR (wheel: package data).
    # An empty value means unset (it would resolve against the working directory).
    if not os.environ.get("FLUO_CUBE_DIR"):
        os.environ["FLUO_CUBE_DIR"] = str(data_dir("cubes"))
    path = library_path()
    if not path.is_file():
        raise ImportError(
            f"fluo plugin library not found at {path} "
            f"(set {LIBRARY_ENV} to override); {_SETUP_HINT}",
            path=str(path),
        )
    try:
        # RTLD_GLOBAL: the plugins' symbols (and the Rust core's) stay visible to
        # Mitsuba once registered, like a plugin Mitsuba loaded itself.
        lib = ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    except OSError as err:
        raise ImportError(
            f"failed to load the fluo plugin library {path}: {err}; it must be built "
            f"against mitsuba=={mitsuba.__version__}; {_SETUP_HINT}",
            path=str(path),
        ) from err
    if not hasattr(lib, "fluo_plugins_built"):
        raise ImportError(
            f"{path} is not the fluo plugin library (no fluo_plugins_built symbol); "
            f"{_SETUP_HINT}",
            path=str(path),
        )
    return lib


# Survives importlib.reload(): the module dict is reused, so the handle is kept.
_LIBRARY: ctypes.CDLL | None = globals().get("_LIBRARY")
_LIBRARY = _load_library()


def _registered() -> list[tuple[str, str, str]]:
    """(name, kind, variants) of every plugin the library registered, as its shims recorded
    them when it was loaded: kind ``bsdf``, ``integrator``, ``texture`` or ``medium``;
    variants ``scalar`` or ``scalar,jit``."""
    listing = _LIBRARY.fluo_plugin_list
    listing.restype = ctypes.c_char_p
    return sorted(tuple(line.split(":", 2)) for line in (listing() or b"").decode().split())


#: Kind of each Mitsuba plugin ``libfluo_mitsuba.so`` registers, by ``type="..."`` name.
_REGISTERED = _registered()
PLUGIN_KINDS: dict[str, str] = {name: kind for name, kind, _ in _REGISTERED}
#: The plugins also served in the vectorised variants (llvm_ad_*, cuda_ad_*).
JIT_PLUGINS: tuple[str, ...] = tuple(name for name, _, variants in _REGISTERED if "jit" in variants.split(","))
#: Names of the Mitsuba plugins ``libfluo_mitsuba.so`` registers (``type="..."`` in XML).
PLUGINS: tuple[str, ...] = tuple(PLUGIN_KINDS)
