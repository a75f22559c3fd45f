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
