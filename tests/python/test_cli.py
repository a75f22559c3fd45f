"""The ``fluo`` package and command line: loader, help, render, demo, forwarding.

Rendering tests use Mitsuba's native ``diffuse`` BSDF, so they test the CLI, not our
plugins (those have their own test_<plugin>.py).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANTS

DIFFUSE = '<bsdf type="diffuse"><rgb name="reflectance" value="$reflectance"/></bsdf>'
DEFAULT_REFLECTANCE = '<default name="reflectance" value="0.5"/>'


def run(cmd, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True,
                          check=False, **kwargs)


def read_image(path: Path) -> np.ndarray:
    mi.set_variant("scalar_rgb")
    return np.array(mi.Bitmap(str(path)))


def stub_tool(tmp_path: Path, body: str) -> dict:
    """An executable stand-in for fluo-rs; returns an environment pointing FLUO_TOOL at it."""
    tool = tmp_path / "fluo-rs-stub"
    tool.write_text(f"#!{sys.executable}\n" + textwrap.dedent(body), encoding="utf-8")
    tool.chmod(0o755)
    return {**os.environ, "FLUO_TOOL": str(tool)}


def test01_help(fluo_cli):
    proc = run([fluo_cli, "--help"])
    assert proc.returncode == 0, proc.stderr
    for word in ("render", "demo", "forwarded", "fluo-rs"):
        assert word in proc.stdout


def test02_module_help():
    proc = run([sys.executable, "-m", "fluo", "--help"])
    assert proc.returncode == 0, proc.stderr
    assert "render" in proc.stdout and "demo" in proc.stdout


@pytest.mark.parametrize("variant", VARIANTS)
def test03_render_writes_exr_and_png(fluo_cli, tmp_path, scene_xml, variant):
    scene = scene_xml(tmp_path, DIFFUSE, extra=DEFAULT_REFLECTANCE)
    out = tmp_path / "out" / "image.exr"
    proc = run([fluo_cli, "render", scene, "--variant", variant, "--spp", 4, "-o", out])
    assert proc.returncode == 0, proc.stderr
    png = out.with_suffix(".png")
    assert proc.stdout.split() == [str(out), str(png)]

    exr = read_image(out)
    assert exr.shape == (12, 16, 3) and exr.dtype == np.float32
    assert np.all(np.isfinite(exr)) and exr.mean() > 0
    ldr = read_image(png)
    assert ldr.shape == (12, 16, 3) and ldr.dtype == np.uint8 and ldr.mean() > 0


def test04_render_params_and_seed(fluo_cli, tmp_path, scene_xml):
    scene = scene_xml(tmp_path, DIFFUSE, extra=DEFAULT_REFLECTANCE)
    means = {}
    for reflectance in (0.1, 0.9):
        out = tmp_path / f"r{reflectance}.exr"
        proc = run([fluo_cli, "render", scene, "--variant", "scalar_rgb", "--spp", 4,
                    "--seed", 7, "--param", f"reflectance={reflectance}", "-o", out, "-q"])
        assert proc.returncode == 0, proc.stderr
        means[reflectance] = read_image(out).mean()
    assert means[0.9] > means[0.1] > 0


def test05_render_reports_errors(fluo_cli, tmp_path, scene_xml):
    scene = scene_xml(tmp_path, '<bsdf type="no_such_plugin"/>')
    proc = run([fluo_cli, "render", scene, "--variant", "scalar_rgb", "--spp", 1,
                "-o", tmp_path / "x.exr"])
    assert proc.returncode == 1
    assert "no_such_plugin" in proc.stderr and "Traceback" not in proc.stderr
    proc = run([fluo_cli, "render", scene, "--variant", "scalar_rgb", "--spp", 0,
                "-o", tmp_path / "x.exr"])
    assert proc.returncode == 2 and "positive" in proc.stderr


def test05b_render_serves_the_vectorised_variants_and_refuses_huge_films(fluo_cli, tmp_path, scene_xml):
    """`fluo render --variant` offers every variant the library serves (an llvm render
    through the CLI, a fluorescent material in it); a film too large for Dr.Jit's arrays is
    refused before it allocates anything (a 100000² film took 5.3 GB before failing)."""
    proc = run([fluo_cli, "render", "--help"])
    for variant in ("llvm_ad_spectral", "llvm_ad_rgb", "cuda_ad_spectral", "cuda_ad_rgb"):
        assert variant in proc.stdout
    scene = scene_xml(tmp_path, '<bsdf type="fluo_jung"/>', integrator="fluo_path")
    out = tmp_path / "llvm.exr"
    proc = run([fluo_cli, "render", scene, "--variant", "llvm_ad_rgb", "--spp", 4, "-o", out, "-q"])
    assert proc.returncode == 0, proc.stderr
    exr = read_image(out)
    assert exr.shape == (12, 16, 3) and np.all(np.isfinite(exr)) and exr.mean() > 0
    huge = scene_xml(tmp_path, DIFFUSE, extra=DEFAULT_REFLECTANCE, width=100000, height=100000, name="huge.xml")
    proc = run([fluo_cli, "render", huge, "--variant", "scalar_rgb", "--spp", 1, "-o", tmp_path / "h.exr"])
    assert proc.returncode == 1 and "100000 x 100000" in proc.stderr and "2^30" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr


def test05c_empty_cube_dir_means_unset(tmp_path):
    """FLUO_CUBE_DIR='' is unset (before: the cube resolved against the working
    directory): a `color` material loads from any directory."""
    code = ("import mitsuba as mi; mi.set_variant('scalar_rgb'); import fluo; "
            "mi.load_dict({'type': 'fluo_jung', 'color': {'type': 'rgb', 'value': [0.2, 0.8, 0.3]}}); print('ok')")
    proc = run([sys.executable, "-c", code], env={**os.environ, "FLUO_CUBE_DIR": ""}, cwd=tmp_path)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-2000:]


def test06_demo_respects_variant_comment(fluo_cli, tmp_path, scene_xml):
    scenes = tmp_path / "scenes"
    (scenes / "sub").mkdir(parents=True)
    scene_xml(scenes, DIFFUSE, extra=DEFAULT_REFLECTANCE, name="both.xml")
    scene_xml(scenes, DIFFUSE, extra=DEFAULT_REFLECTANCE + "<!-- fluo: variants=scalar_spectral -->",
              name="spectral_only.xml")
    scene_xml(scenes / "sub", DIFFUSE, name="ignored.xml")
    out = tmp_path / "out"
    proc = run([fluo_cli, "demo", "--scenes", scenes, "--out", out, "--spp", 1])
    assert proc.returncode == 0, proc.stderr
    renders = {f"{stem}_{variant}{ext}"
               for stem, variants in (("both", VARIANTS), ("spectral_only", ("scalar_spectral",)))
               for variant in variants + ("no_fluorescence",) for ext in (".exr", ".png")}
    expected = renders | {"both_de00.png", "spectral_only_de00.png",
                          "gallery.png", "index.html", "gallery.json"}
    assert {p.name for p in out.iterdir()} == expected
    for name in expected:
        assert str(out / name) in proc.stdout
    assert f"Gallery: {out / 'gallery.png'}" in proc.stdout
    # the restricted scene's reduced-RGB panel says why it is missing
    assert "the scene allows scalar_spectral" in (out / "index.html").read_text()


def test07_unknown_subcommand_is_forwarded(fluo_cli, tmp_path):
    env = stub_tool(tmp_path, """
        import sys
        print("args:", " ".join(sys.argv[1:]))
        print("to stderr", file=sys.stderr)
        sys.exit(3)
    """)
    proc = run([fluo_cli, "patch", "--x", "1", "qd"], env=env)
    assert proc.returncode == 3
    assert proc.stdout.strip() == "args: patch --x 1 qd"
    assert proc.stderr.strip() == "to stderr"


def test08_forwarding_without_tool_fails_clearly(fluo_cli, tmp_path):
    env = {**os.environ, "FLUO_TOOL": str(tmp_path / "missing")}
    proc = run([fluo_cli, "fit-gmm"], env=env)
    assert proc.returncode == 127 and "fluo-rs" in proc.stderr


def test09_run_tool_json(fluo_module, tmp_path, monkeypatch):
    env = stub_tool(tmp_path, """
        import json, sys
        if "fail" in sys.argv:
            print("bad parameter: sigma = -1", file=sys.stderr)
            sys.exit(2)
        print(json.dumps({"args": sys.argv[1:]}))
    """)
    monkeypatch.setenv("FLUO_TOOL", env["FLUO_TOOL"])
    assert fluo_module.run_tool(["qd", "--n", "3"]) == {"args": ["qd", "--n", "3", "--json"]}
    with pytest.raises(RuntimeError, match="sigma = -1"):
        fluo_module.run_tool(["fail"])


@pytest.mark.parametrize("variant_first", [True, False], ids=["variant_first", "import_first"])
def test10_plugins_registered_in_any_import_order(variant_first):
    """Every plugin in fluo.PLUGINS is known in both scalar variants, whichever of
    ``mi.set_variant`` and ``import fluo`` comes first (fresh process each)."""
    script = textwrap.dedent(f"""
        import mitsuba as mi
        if {variant_first}:
            mi.set_variant("scalar_rgb")
        import fluo
        for variant in {VARIANTS!r}:
            mi.set_variant(variant)
            for name in fluo.PLUGINS:
                try:
                    mi.load_dict({{"type": name}})
                except RuntimeError as err:  # a parameter error still means "registered"
                    if "not found" in str(err):
                        raise SystemExit(f"{{name}} not registered for {{variant}}: {{err}}")
        print("ok")
    """)
    proc = run([sys.executable, "-c", script])
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stdout + proc.stderr


def test11_plugin_list_comes_from_the_library(fluo_module):
    """fluo.PLUGINS and the fluorescent BSDFs are what the shims registered, once each."""
    from fluo.scenes import FLUORESCENT_BSDFS

    assert fluo_module.PLUGIN_KINDS == {
        "fluo_gmm": "bsdf", "fluo_illuminant": "texture", "fluo_jung": "bsdf", "fluo_matrix": "bsdf",
        "fluo_path": "integrator", "fluo_prb": "integrator", "fluo_prbvolpath": "integrator", "fluo_qd": "bsdf",
        "fluo_qd_medium": "medium", "fluo_volpath": "integrator",
        "fluo_dye_medium": "medium"}
    assert fluo_module.PLUGINS == tuple(sorted(fluo_module.PLUGIN_KINDS))
    assert set(FLUORESCENT_BSDFS) == {"fluo_gmm", "fluo_jung", "fluo_matrix", "fluo_qd"}


# ------------------------------------------------------------- user errors: one line


def _one_line_error(proc, code=None):
    assert proc.returncode != 0 if code is None else proc.returncode == code, proc
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [l for l in proc.stderr.strip().splitlines() if "error" in l]
    assert len(lines) >= 1, proc.stderr
    return proc.stderr


@pytest.mark.parametrize("output, needle", [
    ("not_a_dir.txt/out.exr", "is not a directory"),
    (".", "is a directory"),
    ("out.tiff", "unsupported extension"),
])
def test_render_checks_the_output_path_before_rendering(fluo_cli, tmp_path, scene_xml, output, needle):
    (tmp_path / "not_a_dir.txt").write_text("x")
    scene = scene_xml(tmp_path, '<bsdf type="diffuse"/>')
    proc = subprocess.run([str(fluo_cli), "render", str(scene), "--variant", "scalar_rgb", "--spp", "1",
                           "-o", str(tmp_path / output)], capture_output=True, text=True, timeout=120)
    err = _one_line_error(proc, 1)
    assert needle in err and "fluo render: error:" in err, err


@pytest.mark.parametrize("seed", ["-1", "abc", str(2**32), "1.5"])
def test_render_rejects_bad_seeds(fluo_cli, tmp_path, scene_xml, seed):
    scene = scene_xml(tmp_path, '<bsdf type="diffuse"/>')
    proc = subprocess.run([str(fluo_cli), "render", str(scene), "--variant", "scalar_rgb", "--spp", "1",
                           "-o", str(tmp_path / "x.exr"), "--seed", seed], capture_output=True, text=True, timeout=120)
    err = _one_line_error(proc, 2)
    assert "--seed" in err, err


def test_bench_rejects_an_unusable_output_directory(fluo_cli, tmp_path):
    (tmp_path / "file").write_text("x")
    proc = subprocess.run([str(fluo_cli), "bench", "--quick", "--out", str(tmp_path / "file")],
                          capture_output=True, text=True, timeout=120)
    assert "not a directory" in _one_line_error(proc, 1)


def test_a_non_executable_tool_is_a_one_line_error(fluo_cli, tmp_path):
    fake = tmp_path / "fluo-rs"
    fake.write_text("not a program\n")
    fake.chmod(0o644)
    env = {**os.environ, "FLUO_TOOL": str(fake)}
    proc = subprocess.run([str(fluo_cli), "patch", "--material", "{}", "--illuminant", "D65"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert "cannot run fluo-rs" in _one_line_error(proc, 126)
