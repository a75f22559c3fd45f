#!/usr/bin/env python3
"""Regenerate README.md's `fluo bench` region from a results.json.

    PYTHONPATH=python .venv/bin/python scripts/bench_readme.py [docs/bench/results.json]
        [--readme README.md] [--check]

Rewrites the text between ``<!-- bench:begin ... -->`` and ``<!-- bench:end -->``: the
run's header line, the method and knob tables, the plot and the one-paragraph reading,
every number of which is computed from the results (``fluo.bench.claims``), so the
prose cannot drift from the table. ``--check`` rewrites nothing and exits 1 when the
README's region differs from what the results give.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "python"))

from fluo import bench  # noqa: E402


def generate(results: Path, readme: Path) -> str:
    """README text with its bench region regenerated from ``results``."""
    result = json.loads(results.read_text())
    try:
        rel = results.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        rel = str(results)
    image = (Path(rel).parent / "accuracy_vs_time.png").as_posix()
    return bench.replace_region(readme.read_text(), bench.readme_region(result, image))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="?", type=Path, default=ROOT / "docs" / "bench" / "results.json")
    ap.add_argument("--readme", type=Path, default=ROOT / "README.md")
    ap.add_argument("--check", action="store_true", help="exit 1 if the README's region is out of date")
    args = ap.parse_args(argv)
    text = generate(args.results, args.readme)
    if args.check:
        if text != args.readme.read_text():
            print(f"{args.readme}: bench region differs from {args.results}; run scripts/bench_readme.py",
                  file=sys.stderr)
            return 1
        return 0
    args.readme.write_text(text)
    print(f"rewrote the bench region of {args.readme} from {args.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
