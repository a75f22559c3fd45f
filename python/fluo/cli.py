"""The ``fluo`` command line.

Python subcommands:

``render``
    Render one scene file in any variant the library serves, write an EXR (or whatever the ``-o``
    extension says) plus an sRGB PNG beside it, and print the written paths.
``demo``
    Render every ``scenes/*.xml`` in every scalar variant it allows, and without
    fluorescence, into ``out/``, and write the gallery (``out/gallery.png``,
    ``out/index.html``; :mod:`fluo.gallery`).

Every other subcommand (``patch``, ``qd``, ``fit-gmm``, ``reduce``, ...) is forwarded
verbatim to the ``fluo-rs`` physics tool, whose stdout, stderr and exit status pass
through unchanged.

A scene restricts the variants ``demo`` renders it in with an XML comment::

    <!-- fluo: variants=scalar_spectral -->

A scene whose data may be missing (the measured matrices in ``../shared/data`` beside
the repository) names a fallback for a ``<default>`` parameter::

    <!-- fluo: fallback matrix_a=../data/matrices/jung_yellow.csv -->

``demo`` passes ``matrix_a=<fallback>`` (paths relative to the scene) when the file the
default names does not exist, and says so.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import mitsuba as mi

from . import out_dir, repo_root, scenes_dir, tool_path
from .scenes import VARIANTS

#: Subcommands implemented here; anything else goes to fluo-rs.
PYTHON_COMMANDS = ("render", "demo", "bench")
#: Every variant the plugin library serves (``fluo render --variant``); the cuda ones need
#: an NVIDIA GPU.
RENDER_VARIANTS = VARIANTS + ("llvm_ad_spectral", "llvm_ad_rgb", "cuda_ad_spectral", "cuda_ad_rgb",
                                "scalar_spectral_polarized", "llvm_ad_spectral_polarized",
                                "cuda_ad_spectral_polarized")
#: Largest film ``fluo render`` accepts, in pixels: Dr.Jit arrays hold at most 2^32 entries,
#: and a film stores at least four channels per pixel.
MAX_FILM_PIXELS = 2**30
#: Examples of subcommands that fluo-rs implements (shown in ``--help``).
FORWARDED_EXAMPLES = ("patch", "qd", "fit-gmm", "reduce")
#: Seconds to wait for ``fluo-rs --help`` while printing ``fluo --help``.
TOOL_HELP_TIMEOUT_S = 10.0

_LDR_SUFFIXES = (".png", ".jpg", ".jpeg")


# ---------------------------------------------------------------------------- parser


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fluo",
        description="Fluorescent materials for Mitsuba 3: render scenes, run the physics tool.",
        epilog=(
            f"Any other subcommand (e.g. {', '.join(FORWARDED_EXAMPLES)}) is forwarded "
            f"verbatim to fluo-rs ({tool_path()}); its commands are listed below."
        ),
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    render = sub.add_parser(
        "render",
        help="render one scene (EXR + PNG)",
        description="Render SCENE with mi.render and write PATH plus a PNG beside it.",
    )
    render.add_argument("scene", type=Path, metavar="SCENE", help="scene XML file")
    render.add_argument("--variant", choices=RENDER_VARIANTS, required=True)
    render.add_argument("--spp", type=_positive_int, required=True, metavar="N",
                        help="samples per pixel")
    render.add_argument("-o", "--output", type=Path, required=True, metavar="PATH",
                        help="output image; EXR if it ends in .exr (a PNG is written beside it)")
    render.add_argument("--seed", type=_seed, default=0, metavar="S",
                        help="sampler seed (default: 0)")
    render.add_argument("--param", action="append", default=[], type=_parse_param,
                        metavar="KEY=VALUE",
                        help="scene parameter ($KEY in the XML); repeatable")
    render.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bar or Mitsuba info messages")
    render.set_defaults(run=_cmd_render)

    demo = sub.add_parser(
        "demo",
        help="render every scenes/*.xml in both scalar variants and write a gallery",
        description=(
            "Render every SCENES/*.xml (not subfolders) in scalar_spectral and scalar_rgb "
            "into OUT/<scene>_<variant>.exr and .png, plus the same scene without "
            "fluorescence (OUT/<scene>_no_fluorescence.exr/.png) and the per-pixel CIEDE2000 "
            "between spectral and without (OUT/<scene>_de00.png), and put them side by side "
            "in OUT/gallery.png and OUT/index.html (numbers in OUT/gallery.json). A comment "
            "'<!-- fluo: variants=scalar_spectral -->' in a scene restricts its variants."
        ),
    )
    demo.add_argument("--spp", type=_positive_int, default=64, metavar="N",
                      help="samples per pixel (default: 64)")
    demo.add_argument("--out", type=Path, default=out_dir(), metavar="DIR",
                      help="output directory (default: <repo>/out in a checkout, else ./out)")
    demo.add_argument("--scenes", type=Path, default=scenes_dir(), metavar="DIR",
                      help="scene directory (default: the shipped scenes, <repo>/scenes in a checkout)")
    demo.add_argument("--res", type=_positive_int, default=None, metavar="N",
                      help="film width and height for scenes with a $res parameter "
                           "(default: each scene's own)")
    demo.add_argument("--seed", type=_seed, default=0, metavar="S",
                      help="sampler seed (default: 0)")
    demo.add_argument("--readme", action="store_true",
                      help="also write a small copy of the gallery to <repo>/docs/gallery.png "
                           "(the image README.md shows)")
    demo.set_defaults(run=_cmd_demo)

    bench = sub.add_parser(
        "bench",
        help="accuracy against time of every method on scenes/bench/*.xml",
        description=(
            "Render every scenes/bench/*.xml with every method (spectral, RGB reduced "
            "naive/ours x rgb/xyzu/x7, plain RGB, native path) in one run; print a table "
            "(time, mean/p95 CIEDE2000 against a cached converged spectral reference, "
            "equal-error time, floats per material) and write results.json, results.md "
            "and accuracy_vs_time.png to OUT."
        ),
    )
    bench.add_argument("--quick", action="store_true",
                       help="48x48 instead of 96x96, spp ladder 4..256 instead of 4..1024, and a 4096-spp "
                            "reference instead of 16384")
    bench.add_argument("--out", type=Path, default=out_dir() / "bench", metavar="DIR",
                       help="output directory (default: <repo>/out/bench in a checkout, else ./out/bench)")
    bench.add_argument("--target", type=float, default=1.5, metavar="DE",
                       help="equal-error target, mean CIEDE2000 (default: 1.5)")
    bench.add_argument("--repeats", type=_positive_int, default=3, metavar="N",
                       help="renders timed per rung; tables give the median and min-max (default: 3)")
    bench.set_defaults(run=_cmd_bench)
    return parser


def _cmd_bench(args: argparse.Namespace) -> int:
    from . import bench

    problem = check_output_path(args.out, directory=True)
    if problem:
        print(f"fluo bench: error: {problem}", file=sys.stderr)
        return 1
    _log_to_stderr(mi.LogLevel.Warn) if hasattr(mi, "LogLevel") else None
    result = bench.run(quick=args.quick, out=args.out, target_de=args.target, repeats=args.repeats,
                       log=lambda m: print(m, file=sys.stderr, flush=True))
    print(bench.table(result))
    print(f"wrote {args.out / 'results.json'}, {args.out / 'results.md'}, "
          f"{args.out / 'accuracy_vs_time.png'}")
    return 0


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


#: Largest sampler seed Mitsuba takes (an unsigned 32-bit integer).
MAX_SEED = 2**32 - 1


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number in [0, {MAX_SEED}], got {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be a whole number in [0, {MAX_SEED}], got {text}")
    return value


#: Image formats ``render`` writes (EXR through the film, the others as 8-bit sRGB).
OUTPUT_SUFFIXES = (".exr",) + _LDR_SUFFIXES


def check_output_path(path: Path, *, directory: bool = False) -> str | None:
    """Why ``path`` cannot be written (checked before rendering), or ``None``.

    ``directory``: ``path`` is an output directory (created if missing)."""
    if directory:
        target = path
        if target.exists() and not target.is_dir():
            return f"output directory {path} exists and is not a directory"
    else:
        if path.is_dir():
            return f"output path {path} is a directory"
        if path.suffix.lower() not in OUTPUT_SUFFIXES:
            return f"output path {path}: unsupported extension {path.suffix!r} (use one of {', '.join(OUTPUT_SUFFIXES)})"
        target = path.parent
    existing = target
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if not existing.is_dir():
        return f"cannot create {target}: {existing} is not a directory"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"cannot write to {target}: {existing} is not writable"
    return None


def _parse_param(text: str) -> tuple[str, int | float | str]:
    """``key=value`` -> ``(key, value)`` with value an int, else a float, else a string."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    for convert in (int, float):
        try:
            return key, convert(raw)
        except ValueError:
            pass
    return key, raw


def _print_help(parser: argparse.ArgumentParser) -> None:
    parser.print_help()
    print("\nfluo-rs commands (forwarded):")
    tool = tool_path()
    if not tool.is_file():
        print(f"  (fluo-rs is not built at {tool}; run bash scripts/setup.sh)")
        return
    try:
        proc = subprocess.run([str(tool), "--help"], capture_output=True, text=True,
                              timeout=TOOL_HELP_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired) as err:
        print(f"  (could not run {tool} --help: {err})")
        return
    text = (proc.stdout or proc.stderr).rstrip()
    print("\n".join("  " + line for line in text.splitlines()) or "  (no output)")


# ---------------------------------------------------------------------------- render


class _StderrAppender(mi.Appender):
    """Sends Mitsuba's log and progress bar to stderr (stdout is for output paths)."""

    def append(self, level, text):
        sys.stderr.write(text.rstrip("\n") + "\n")
        sys.stderr.flush()

    def log_progress(self, progress, name, formatted, eta, ptr=None):
        # `formatted` is a full bar; redraw it in place on one line.
        sys.stderr.write("\r" + formatted.strip("\r\n"))
        if progress >= 1.0:
            sys.stderr.write("\n")
        sys.stderr.flush()


_APPENDER: _StderrAppender | None = None  # kept alive for the logger


def _log_to_stderr(level) -> None:
    global _APPENDER
    logger = mi.logger() if hasattr(mi, "logger") else mi.Thread.thread().logger()
    _APPENDER = _StderrAppender()
    logger.clear_appenders()
    logger.add_appender(_APPENDER)
    logger.set_log_level(level)


def render_to_files(scene_path: Path, variant: str, spp: int, output: Path,
                    seed: int = 0, params: dict | None = None) -> list[Path]:
    """Render ``scene_path`` and write ``output`` plus a PNG beside it; return the paths.

    Sets the Mitsuba variant, so call it once per process (as ``fluo render`` does).
    """
    mi.set_variant(variant)
    import fluo  # noqa: F401  (loads libfluo_mitsuba.so: registers the fluo_* plugins)

    scene = mi.load_file(str(scene_path), **(params or {}))
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    if width * height > MAX_FILM_PIXELS:
        # Before: a 100000² film took 5.3 GB before Dr.Jit failed on it.
        raise RuntimeError(f"the film's crop is {width} x {height} = {width * height} pixels, more than the "
                           f"{MAX_FILM_PIXELS} (2^30) a render can hold (Dr.Jit arrays: 2^32 entries, 4 channels)")
    image = mi.render(scene, spp=spp, seed=seed)

    output.parent.mkdir(parents=True, exist_ok=True)
    written = []
    if output.suffix.lower() in _LDR_SUFFIXES:
        mi.util.write_bitmap(str(output), image[..., :3], write_async=False)
    else:
        # The film's own bitmap keeps channel names (AOVs) in the EXR.
        scene.sensors()[0].film().bitmap().write(str(output))
    written.append(output)

    png = output.with_suffix(".png")
    if png != output:
        # sRGB gamma, clamped, 8 bit; the first three channels are the image.
        mi.util.write_bitmap(str(png), image[..., :3], write_async=False)
        written.append(png)
    return written


def _cmd_render(args: argparse.Namespace) -> int:
    _log_to_stderr(mi.LogLevel.Warn if args.quiet else mi.LogLevel.Info)
    if not args.scene.is_file():
        print(f"fluo render: error: no scene file {args.scene}", file=sys.stderr)
        return 1
    problem = check_output_path(args.output)
    if problem:
        print(f"fluo render: error: {problem}", file=sys.stderr)
        return 1
    try:
        paths = render_to_files(args.scene, args.variant, args.spp, args.output,
                                seed=args.seed, params=dict(args.param))
    except RuntimeError as err:  # Mitsuba's errors: XML, plugin parameters, I/O
        print(f"fluo render: error: {err}", file=sys.stderr)
        return 1
    for path in paths:
        print(path)
    return 0


# ---------------------------------------------------------------------------- demo


def _cmd_demo(args: argparse.Namespace) -> int:
    from . import gallery

    args.out = args.out.resolve()
    problem = check_output_path(args.out, directory=True)
    if problem:
        print(f"fluo demo: error: {problem}", file=sys.stderr)
        return 1
    scenes = sorted(args.scenes.glob("*.xml"))
    if not scenes:
        print(f"fluo demo: no scenes in {args.scenes}", file=sys.stderr)
        return 1
    # Warnings and errors only: the gallery's own bar shows the progress.
    _log_to_stderr(mi.LogLevel.Warn)
    readme = (repo_root() / "docs" / "gallery.png") if args.readme else None
    rows = gallery.run(scenes, args.out, args.spp, res=args.res, seed=args.seed, readme=readme)
    written = [f for row in rows for panel in row.panels.values() for f in panel.files]
    written += [str(args.out / name) for name in ("gallery.png", "index.html", "gallery.json")]
    if readme is not None:
        written.append(str(readme))
    print("Written:")
    for path in written:
        print(f"  {path}")
    for row in rows:
        if row.mean_de is not None:
            times = ", ".join(f"{k} {p.seconds:.2f} s" for k, p in row.panels.items()
                              if p.seconds is not None)
            noise = "n/a" if row.noise_de is None else f"{row.noise_de:.2f}"
            print(f"  {row.scene}: mean ΔE00 spectral vs without fluorescence "
                  f"{row.mean_de:.2f} (noise floor {noise}, p95 {row.p95_de:.2f}); {times}")
    print(f"Gallery: {args.out / 'gallery.png'} and {args.out / 'index.html'}")
    failed = [row.scene for row in rows if row.failed]
    if failed:
        print(f"Failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------------------- main


def _forward(argv: list[str]) -> int:
    """Run ``fluo-rs argv...`` with inherited stdio and return its exit status."""
    tool = tool_path()
    if not tool.is_file():
        print(f"fluo: '{argv[0]}' is not a Python subcommand and fluo-rs is not built "
              f"at {tool}; run bash scripts/setup.sh", file=sys.stderr)
        return 127
    try:
        return subprocess.run([str(tool), *argv], check=False).returncode
    except KeyboardInterrupt:
        return 130
    except OSError as err:  # not executable, not a program, ...
        print(f"fluo: error: cannot run fluo-rs at {tool} ({err.strerror or err})", file=sys.stderr)
        return 126


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``fluo`` console script and ``python -m fluo``."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and not argv[0].startswith("-") and argv[0] not in PYTHON_COMMANDS:
        return _forward(argv)
    parser = _parser()
    if not argv or argv[0] in ("-h", "--help"):
        _print_help(parser)
        return 0 if argv else 2
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except KeyboardInterrupt:
        return 130
    except (OSError, RuntimeError) as err:  # I/O and Mitsuba errors: one line, no traceback
        print(f"fluo {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
