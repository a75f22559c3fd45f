"""The module dependency graph of the physics crate (core/src), without test code.

``python tools/module_graph.py`` prints each module's imports and any cycle;
tests/python/test_layout.py asserts the layout rules with it: no cycle, the interface
imports no model, only ``model`` and what sits above it name several models.

A module is a top-level file or folder of core/src, except that each model under
``models/`` is its own node (``models::jung``). Edges are ``crate::<module>`` paths
in code before the first ``#[cfg(test)]`` of a file; comments are ignored.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

#: Items re-exported at the crate root, and the module that defines them.
ROOT_ITEMS = {"Error": "error", "Result": "error", "num": "error", "shown": "error",
              "Bispectral": "interface", "Model": "model"}


def module_of(path: Path, src: Path) -> str | None:
    """The graph node of a source file (None for the crate root and binaries)."""
    parts = [p for p in path.relative_to(src).with_suffix("").parts if p != "mod"]
    if not parts or parts[0] in ("lib", "bin"):
        return None
    if parts[0] == "models" and len(parts) >= 2:
        return "models::" + parts[1]
    return parts[0]


def graph(src: Path) -> dict[str, set[str]]:
    """module -> the modules its non-test code uses."""
    edges: dict[str, set[str]] = {}
    for path in sorted(src.rglob("*.rs")):
        node = module_of(path, src)
        if node is None:
            continue
        text = path.read_text(encoding="utf-8")
        cut = text.find("#[cfg(test)]")
        code = re.sub(r"//.*", "", text if cut < 0 else text[:cut])
        deps = edges.setdefault(node, set())
        names = re.findall(r"crate::(models::\w+|\w+)", code)
        for group in re.findall(r"crate::\{([^}]*)\}", code):  # use crate::{a, b::c};
            names += [re.match(r"\s*(models::\w+|\w+)", g).group(1) for g in group.split(",") if g.strip()]
        for target in names:
            target = ROOT_ITEMS.get(target, target)
            if target not in ("models", node):
                deps.add(target)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Every elementary cycle found by depth-first search (each reported once)."""
    found: list[list[str]] = []
    seen: set[frozenset[str]] = set()

    def walk(start: str, node: str, path: list[str]) -> None:
        for nxt in sorted(edges.get(node, ())):
            if nxt == start:
                key = frozenset(path)
                if key not in seen:
                    seen.add(key)
                    found.append(path + [start])
            elif nxt not in path and nxt > start:
                walk(start, nxt, path + [nxt])

    for start in sorted(edges):
        walk(start, start, [start])
    return found


def main() -> int:
    src = Path(__file__).resolve().parents[1] / "core" / "src"
    edges = graph(src)
    for node in sorted(edges):
        print(f"{node:16} -> {', '.join(sorted(edges[node])) or '-'}")
    found = cycles(edges)
    print("cycles:", "; ".join(" -> ".join(c) for c in found) if found else "none")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
