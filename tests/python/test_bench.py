"""The bench machinery (python/fluo/bench.py): interpolation and scene rewrites.

Timing itself is not tested (benchmarks print measured ratios); these tests check
that every method turns every bench scene into a scene Mitsuba loads, with the
intended integrator and materials.
"""

import mitsuba as mi
import pytest

from fluo import bench


def test01_equal_error_time_interpolates_in_log_time():
    secs, errs = [1.0, 4.0, 16.0], [4.0, 2.0, 1.0]
    assert bench.equal_error_time(secs, errs, 2.0) == pytest.approx(4.0)
    assert bench.equal_error_time(secs, errs, 1.5) == pytest.approx(8.0)  # halfway in log time
    assert bench.equal_error_time(secs, errs, 0.5) is None               # never reached
    assert bench.equal_error_time(secs, errs, 8.0) == pytest.approx(0.5)  # below the first rung


@pytest.mark.parametrize("scene", sorted(bench.BENCH_DIR.glob("*.xml")), ids=lambda p: p.stem)
@pytest.mark.parametrize("method", bench.METHODS, ids=lambda m: m.name)
def test02_every_method_loads_every_bench_scene(scene, method, tmp_path):
    text = method.rewrite(bench._absolutise_includes(scene.read_text(), scene.parent))
    path = tmp_path / "s.xml"
    path.write_text(text)
    mi.set_variant(method.variant)
    s = mi.load_file(str(path), res=8, spp=1)
    integrator = s.integrator().class_name()
    names = [sh.bsdf().class_name() for sh in s.shapes()]
    if "path" in method.name and "fluo_path" not in method.name:
        assert integrator != "FluoPath"
    if "nearest diffuse" in method.name:
        assert "FluoJung" not in names
    if "fluo_path" in method.name:
        assert integrator == "FluoPath"
