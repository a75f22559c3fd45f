"""The bench machinery (python/fluo/bench.py): interpolation and scene rewrites.

Timing itself is not tested (benchmarks print measured ratios); these tests check
that every method turns every bench scene into a scene Mitsuba loads, with the
intended integrator and materials.
"""

from pathlib import Path

import mitsuba as mi
import pytest

from fluo import bench, bench_methods


def test01_equal_error_time_interpolates_in_log_time():
    secs, errs = [1.0, 4.0, 16.0], [4.0, 2.0, 1.0]
    assert bench.equal_error_time(secs, errs, 2.0) == pytest.approx(4.0)
    assert bench.equal_error_time(secs, errs, 1.5) == pytest.approx(8.0)  # halfway in log time
    assert bench.equal_error_time(secs, errs, 0.5) is None               # never reached
    assert bench.equal_error_time(secs, errs, 8.0) == pytest.approx(0.5)  # below the first rung


def _pairs():
    """(scene, method index) for every method that applies to the scene's materials."""
    out = []
    for scene in sorted(bench.BENCH_DIR.glob("*.xml")):
        kinds = bench._material_kinds(bench._absolutise_includes(scene.read_text(), scene.parent))
        for i, m in enumerate(bench.methods(Path("."))):
            if m.applies(scene.stem, kinds):
                out.append(pytest.param(scene, i, id=f"{scene.stem}-{m.name}"))
    return out


def _shipped_cube(space):
    import fluo
    return fluo.repo_root() / "data" / "cubes" / f"{space}_d65_tinf_r33.cube"


@pytest.mark.parametrize("scene, index", _pairs())
def test02_every_method_loads_every_bench_scene(scene, index, tmp_path, monkeypatch):
    # cubes other than the shipped 33³ take minutes to generate: load with the shipped one
    monkeypatch.setattr(bench_methods, "cube_path", lambda res, space="acescg": _shipped_cube(space))
    method = bench.methods(tmp_path)[index]
    text = method.rewrite(bench._absolutise_includes(scene.read_text(), scene.parent))
    path = tmp_path / "s.xml"
    path.write_text(text)
    # (the vectorised variants' rows load here in the matching scalar variant, which checks
    # the rewrite; test02b renders them in their own variant, in a fresh process)
    mi.set_variant(method.variant.replace("llvm_ad_", "scalar_"))
    s = mi.load_file(str(path), res=8, spp=1)
    integrator = s.integrator().class_name()
    names = [sh.bsdf().class_name() for sh in s.shapes()]
    media = "fluo_qd_medium" in text
    if "path" in method.name and "fluo_path" not in method.name:
        assert not integrator.startswith("Fluo"), integrator
        # without fluorescence the media keep their absorption at yield 0
        assert not media or ('name="quantum_yield" value="0"' in text and 'value="0.8"' not in text)
    if "nearest material" in method.name:
        assert not any(n.startswith("Fluo") for n in names), names
    if "GMM" in method.name:
        assert "FluoGmm" in names and "FluoMatrix" not in names
    assert method.bytes(text) >= 0
    if "fluo_path" in method.name:  # the scene's own integrator: fluo_volpath for media
        assert integrator == ("FluoVolpath" if media else "FluoPath"), integrator
    # the tables name the integrator that rendered the row
    shown = bench.display_method({"method": method.name, "scene": scene.stem})
    expected = {"FluoVolpath": "(fluo_volpath)", "FluoPath": "(fluo_path)", "VolumetricPathIntegrator": "(volpath)",
                "PathIntegrator": "(path)"}.get(integrator)
    if "(" in method.name and expected is not None and "nearest material" not in method.name:
        assert shown.endswith(expected), (shown, integrator)


def test02b_vectorised_methods_render_their_bench_scenes(tmp_path):
    """Every "llvm" method renders every bench scene it applies to in its own variant (one
    sample, 8x8: no error, finite pixels), and applies to no scene with a material the
    vectorised variants do not serve."""
    import sys
    sys.path.insert(0, str(Path(__file__).parent))
    from test_llvm import run_llvm

    jobs, names = [], []
    for scene in sorted(bench.BENCH_DIR.glob("*.xml")):
        base = bench._absolutise_includes(scene.read_text(), scene.parent)
        kinds = bench._material_kinds(base)
        for m in bench.methods(tmp_path):
            if not m.variant.startswith("llvm_") or not m.applies(scene.stem, kinds):
                continue
            assert kinds <= bench.JIT_KINDS, (scene.stem, m.name, kinds)
            jobs.append({"variant": m.variant, "xml": m.rewrite(base), "params": {"res": "8", "spp": "1"}, "spp": 1})
            names.append(f"{scene.stem}: {m.name}")
    assert len(jobs) >= 16, names  # jung_box, highlighter_box, measured_box, qd_box, blacklight_box, qd_cuvette
    for name, res in zip(names, run_llvm(jobs)):
        assert "error" not in res and res["finite"], f"{name}: {res}"


def test03_bench_reports_saturated_fluorescence_per_basis():
    # fluo bench's second table: saturated emitters and a UV brightener per basis.
    import fluo
    rows = fluo.run_tool(["saturated-report"])["saturated"]
    text = bench.saturated_table(rows)
    assert "| material | light | rgb | xyzu | x7 |" in text
    for case in ["green emitter", "red emitter", "UV brightener"]:
        assert sum(line.startswith(f"| {case} |") for line in text.splitlines()) == 4  # D65, A, FL2, UV365
    uv = next(r for r in rows if r["case"] == "UV brightener" and r["illuminant"] == "D65" and r["basis"] == "rgb")
    assert uv["fluorescence_ratio"] < 0.05  # rgb has no UV band


# ---------------------------------------------------------------- README generation

def _row(scene, method, eet, floor, seconds=1.0, knob="", nbytes=100.0):
    return {"scene": scene, "method": method, "spp": [4, 16], "seconds": [seconds / 4, seconds],
            "seconds_min": [seconds / 5, 0.9 * seconds], "seconds_max": [seconds / 3, 1.2 * seconds],
            "seconds_all": [[seconds / 4] * 3, [seconds] * 3],
            "mean_de": [floor + 1.0, floor], "p95_de": [floor + 3.0, floor + 2.0],
            "equal_error_time": eet, "equal_error_range": [eet, eet] if eet else [None, None],
            "floor_de": floor, "material_bytes": nbytes, "knob": knob}


def _synthetic():
    """Two scenes; `ours` 2x and 5x sooner on one, never on the other; plain RGB reaches the
    target on scene b only; a knob row."""
    rows = [
        _row("a", bench.SPECTRAL, 4.0, 0.5, 10.0),
        _row("a", "rgb ours-xyzu (fluo_path)", 2.0, 0.6, 8.0),
        _row("a", "rgb ours-x7 (fluo_path)", 0.8, 0.9, 8.5),
        _row("a", "rgb naive-xyzu (fluo_path)", None, 3.3, 8.0),
        _row("a", bench.NO_FLUORESCENCE, None, 7.25, 6.0, nbytes=0.0),
        _row("b", bench.SPECTRAL, None, 1.9, 20.0),
        _row("b", "rgb ours-xyzu (fluo_path)", 3.0, 1.2, 15.0),
        _row("b", bench.NO_FLUORESCENCE, 1.1, 1.2, 9.0, nbytes=0.0),
        _row("b", "spectral, fluo_qd table_cos_nodes=5 (fluo_path)", None, 2.4, 19.0, knob="QD tables"),
    ]
    return {"date": "2026-01-01", "machine": "test", "quick": True, "res": 8, "ladder_spp": [4, 16],
            "ref_spp": 64, "target_de": 1.5, "repeats": 3, "rows": rows, "saturated": []}


def test04_reading_claims_follow_the_numbers():
    result = _synthetic()
    c = bench.claims(result)
    assert sorted(c["ratios"]) == pytest.approx([2.0, 5.0])  # spectral 4.0 s / 2.0 s and / 0.8 s
    text = bench.reading(result)
    assert "sooner than spectral rendering in 2 of 2 scene × basis cases (2.0–5.0× sooner)" in text
    assert "ranges over 2.0–5.0×" in text
    # b's spectral never reaches: no ratio there, compared at the top rung instead
    assert "stays above the target within the ladder on b (mean ΔE00 1.90 at the top rung, `ours` 1.20)" in text
    assert "floors (lowest mean ΔE00 along the ladder): 0.60–1.20" in text
    # rows that reach the target are not among those said never to reach it
    never = text[text.index("never reach the target"):text.index("do reach it")]
    assert "naive-xyzu, plain RGB on a" in never
    assert "on b" not in never
    assert "1 do reach it: plain RGB on b (1.10 s)" in text
    assert "floors 3.30–7.25" in text
    assert "costs a mean ΔE00 of 7.25 on a, 1.20 on b" in text
    assert "Knob QD tables on b (own model: mean ΔE00 1.90; largest change 0.50)" in text
    assert "0.95× the time" in text
    # timing spread at the top rung: (1.2 - 0.9) / 1 = 30 % everywhere
    assert "Times are medians of 3 renders" in text and "is 30 % in the median row and up to 30 %" in text
    # the knob row goes to its own table, not the methods' one
    region = bench.readme_region(result)
    methods_table, knob_table = region.split("Accuracy/cost knobs")
    assert "table_cos_nodes=5" in knob_table and "table_cos_nodes=5" not in methods_table
    assert "| 10.000 [9.000–12.000] |" in methods_table


def test05_reading_never_overstates():
    # none of the others reaches: no "do reach it" clause
    result = _synthetic()
    result["rows"] = [r for r in result["rows"] if r["scene"] == "a"]
    text = bench.reading(result)
    assert "do reach it" not in text and "stays above the target" not in text
    # a case where ours is slower is not counted as sooner, and is named with its ratio
    result["rows"][2]["equal_error_time"] = 8.0   # ours-x7: spectral 4.0 / 8.0 = 0.5
    text = bench.reading(result)
    assert "in 1 of 2 scene × basis cases (2.0× sooner), not sooner in ours-x7 on a (0.50×)" in text
    assert "ranges over 0.5–2.0×" in text
    c = bench.claims(result)
    assert min(c["ratios"]) == pytest.approx(0.5) and max(c["ratios"]) == pytest.approx(2.0)


def test06_replace_region_keeps_the_rest():
    readme = "intro\n<!-- bench:begin -->\nold\n<!-- bench:end -->\noutro\n"
    region = bench.readme_region(_synthetic())
    out = bench.replace_region(readme, region)
    assert out.startswith("intro\n" + bench.README_BEGIN) and out.endswith(bench.README_END + "\noutro\n")
    assert bench.replace_region(out, region) == out
    with pytest.raises(ValueError):
        bench.replace_region("no markers", region)


def test07_readme_region_is_generated_from_committed_results():
    import importlib.util
    import fluo
    root = fluo.repo_root()
    spec = importlib.util.spec_from_file_location("bench_readme", root / "scripts" / "bench_readme.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    readme = root / "README.md"
    assert mod.generate(root / "docs" / "bench" / "results.json", readme) == readme.read_text(), \
        "README's bench region is stale: run scripts/bench_readme.py"


def test08_strong_scenes_and_knob_rows_apply():
    kinds = {s.stem: bench._material_kinds(bench._absolutise_includes(s.read_text(), s.parent))
             for s in bench.BENCH_DIR.glob("*.xml")}
    assert kinds["highlighter_box"] == {"jung", "cube"} and kinds["blacklight_box"] == {"jung", "qd"}
    applied = {(m.knob, scene) for m in bench.methods(Path(".")) if m.knob
               for scene, k in kinds.items() if m.applies(scene, k)}
    assert applied == {("GMM components", "measured_box"), ("QD tables", "blacklight_box"),
                       ("cube resolution", "highlighter_box")}


@pytest.mark.parametrize("name, value", [("table_cos_nodes", "1"), ("table_cos_nodes", "2000"),
                                         ("table_step", "0"), ("table_step", "100")])
def test09_qd_table_knobs_are_validated(name, value, tmp_path):
    mi.set_variant("scalar_spectral")
    kind = "integer" if name == "table_cos_nodes" else "float"
    with pytest.raises(Exception, match=name):
        mi.load_dict({"type": "fluo_qd", name: int(value) if kind == "integer" else float(value)})
    ok = mi.load_dict({"type": "fluo_qd", "table_cos_nodes": 5, "table_step": 4.0})
    assert "FluoQd" in ok.class_name()


def test10_readme_costs_table_is_the_saved_cost_benchmark():
    """README's cost table is benches/bench_costs.py's output for docs/bench/costs.json."""
    import importlib.util
    import json
    import fluo
    root = fluo.repo_root()
    spec = importlib.util.spec_from_file_location("bench_costs", root / "benches" / "bench_costs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    saved = root / "docs" / "bench" / "costs.json"
    run = json.loads(saved.read_text())
    assert {r["row"] for r in run["results"]} == set(mod.ROWS) and run["rounds"] >= 5
    region = mod.readme_region(run, "docs/bench/costs.json")
    assert region in (root / "README.md").read_text(), \
        "README's costs table is stale: run benches/bench_costs.py --readme docs/bench/costs.json"
