"""The bench machinery (python/fluo/bench.py): interpolation and scene rewrites.

Timing itself is not tested (benchmarks print measured ratios); these tests check
that every method turns every bench scene into a scene Mitsuba loads, with the
intended integrator and materials.
"""

from pathlib import Path

import mitsuba as mi
import pytest

from fluo import bench


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
            if m.kinds is None or m.kinds & kinds:
                out.append(pytest.param(scene, i, id=f"{scene.stem}-{m.name}"))
    return out


@pytest.mark.parametrize("scene, index", _pairs())
def test02_every_method_loads_every_bench_scene(scene, index, tmp_path):
    method = bench.methods(tmp_path)[index]
    text = method.rewrite(bench._absolutise_includes(scene.read_text(), scene.parent))
    path = tmp_path / "s.xml"
    path.write_text(text)
    mi.set_variant(method.variant)
    s = mi.load_file(str(path), res=8, spp=1)
    integrator = s.integrator().class_name()
    names = [sh.bsdf().class_name() for sh in s.shapes()]
    if "path" in method.name and "fluo_path" not in method.name:
        assert integrator != "FluoPath"
    if "nearest material" in method.name:
        assert not any(n.startswith("Fluo") for n in names), names
    if "GMM" in method.name:
        assert "FluoGmm" in names and "FluoMatrix" not in names
    assert method.bytes(text) >= 0
    if "fluo_path" in method.name:
        assert integrator == "FluoPath"


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
