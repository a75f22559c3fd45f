"""Fluorescent (bispectral) materials for Mitsuba 3.

Importing this package loads the plugin library ``libfluo.so`` (Rust physics plus the
C++ Mitsuba shims). Its static initialiser registers every plugin in :data:`PLUGINS`
with Mitsuba's plugin manager for both ``scalar_rgb`` and ``scalar_spectral``, so
``mi.set_variant(...)`` may be called before or after ``import fluo``::

    import mitsuba as mi
    import fluo

    mi.set_variant("scalar_spectral")
    scene = mi.load_file("scenes/jung_spheres.xml")

Where things are found (environment variables win):

============== ================ ==================================
what           variable         default
============== ================ ==================================
plugin library ``FLUO_LIBRARY`` ``<repo>/target/release/libfluo.so``
physics tool   ``FLUO_TOOL``    ``<repo>/target/release/fluo-rs``
============== ================ ==================================

``<repo>`` is the checkout this package was installed from (editable install).
"""

from __future__ import annotations

# Must come first: libfluo.so resolves its Mitsuba symbols against the libmitsuba.so
# that the wheel loads on import.
import mitsuba  # noqa: F401  (imported for its side effect)

import ctypes
import json
import os
import subprocess
from pathlib import Path

__all__ = [
    "PLUGINS",
    "library_path",
    "repo_root",
    "run_tool",
    "tool_path",
]

#: Names of the Mitsuba plugins that ``libfluo.so`` registers (``type="..."`` in XML).
PLUGINS: tuple[str, ...] = ("fluo_jung", "fluo_path", "fluo_illuminant", "fluo_qd", "fluo_matrix", "fluo_gmm")

#: Environment variable overriding the plugin library location.
LIBRARY_ENV = "FLUO_LIBRARY"
#: Environment variable overriding the ``fluo-rs`` tool location.
TOOL_ENV = "FLUO_TOOL"

_SETUP_HINT = "run the setup command in README.md (bash scripts/setup.sh)"


def repo_root() -> Path:
    """The repository root: ``python/fluo/__init__.py`` is two levels below it."""
    return Path(__file__).resolve().parents[2]


def library_path() -> Path:
    """Path of the plugin library: ``$FLUO_LIBRARY`` or ``<repo>/target/release/libfluo.so``."""
    override = os.environ.get(LIBRARY_ENV)
    if override:
        return Path(override).expanduser().resolve()
    return repo_root() / "target" / "release" / "libfluo.so"


def tool_path() -> Path:
    """Path of the ``fluo-rs`` physics tool: ``$FLUO_TOOL`` or ``<repo>/target/release/fluo-rs``."""
    override = os.environ.get(TOOL_ENV)
    if override:
        return Path(override).expanduser().resolve()
    return repo_root() / "target" / "release" / "fluo-rs"


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
    """Load ``libfluo.so`` globally; a second call (or a module reload) is a no-op."""
    handle = globals().get("_LIBRARY")
    if handle is not None:
        return handle
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
            f"{path} contains no Mitsuba plugins: it was built without "
            "`--features mitsuba` (a plain `cargo build --release` replaces it); "
            f"{_SETUP_HINT}",
            path=str(path),
        )
    return lib


# Survives importlib.reload(): the module dict is reused, so the handle is kept.
_LIBRARY: ctypes.CDLL | None = globals().get("_LIBRARY")
_LIBRARY = _load_library()
