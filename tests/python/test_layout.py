"""The crate layout rules of README's "Layout": the physics crate has no C++ side, its
modules import each other one way, and the interface names no model."""

from __future__ import annotations

import importlib.util
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("module_graph", REPO / "tools" / "module_graph.py")
module_graph = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(module_graph)

EDGES = module_graph.graph(REPO / "core" / "src")
MODELS = {m for m in EDGES if m.startswith("models::")}


def test_no_import_cycle():
    assert module_graph.cycles(EDGES) == []


def test_graph_sees_every_model_and_the_error_module():
    # guards the parser itself: these edges exist in the code
    assert MODELS == {"models::jung", "models::qd", "models::matrix", "models::gmm"}
    assert "error" in EDGES["fileio"] and "interface" in EDGES["models::jung"]


def test_interface_imports_no_model_and_models_import_no_consumer():
    assert not EDGES["interface"] & (MODELS | {"model"}), EDGES["interface"]
    for m in MODELS:
        assert not EDGES[m] & {"model", "patch", "reduce", "reports", "upsample"}, (m, EDGES[m])


def test_only_model_and_reports_name_several_models():
    for node, deps in EDGES.items():
        if len(deps & MODELS) > 1:
            assert node in ("model", "reports") or node.startswith("models::"), (node, deps & MODELS)
    assert EDGES["model"] >= MODELS


def test_physics_crate_has_no_cxx():
    tree = subprocess.run(["cargo", "tree", "-p", "fluo", "-e", "normal,build", "--offline"], cwd=REPO,
                          capture_output=True, text=True, check=True).stdout
    assert tree.startswith("fluo v") and "cxx" not in tree, tree
    assert not (REPO / "core" / "build.rs").exists()


def python_package_graph() -> dict[str, set[str]]:
    """The fluo package's modules and the sibling modules each imports (at module level or
    inside a function: a lazy import is still a dependency), from the source text."""
    import re

    pkg = REPO / "python" / "fluo"
    names = {p.stem for p in pkg.glob("*.py")}
    edges: dict[str, set[str]] = {}
    for path in pkg.glob("*.py"):
        deps = set()
        for line in path.read_text(encoding="utf-8").splitlines():
            m = re.match(r"\s*from \.(\w*) import (.+)", line)
            if not m:
                continue
            if m.group(1):
                deps.add(m.group(1))
            else:  # from . import a, b  (package attributes that are modules)
                deps |= {n.strip().split(" as ")[0] for n in m.group(2).split("#")[0].split(",")} & names
        edges[path.stem] = deps - {path.stem}
    return edges


def test_python_package_has_no_import_cycle():
    """cli.py and gallery.py imported each other (the demo's scene helpers lived in cli.py);
    they now live in scenes.py, and the package's import graph is acyclic."""
    edges = python_package_graph()
    assert "cli" not in edges["gallery"] and "gallery" in edges["cli"]
    assert module_graph.cycles(edges) == []
