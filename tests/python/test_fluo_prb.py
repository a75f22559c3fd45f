"""fluo_prb: fluo_path with path replay for reverse-mode gradients (fluo_path.cpp's docs).

References: its primal is fluo_path's (the same loop and random numbers: equal images in
every variant); its gradients are compared with central finite differences of the image
mean (same seed, fluo_path renders) per parameter, in a box whose walls inter-reflect so
that paths have several vertices (the replay's remaining radiance matters). The AD
variants run in a fresh process (llvm_worker.py: Mitsuba 3.8 cannot start an llvm
variant after a scalar render). Memory is a benchmark row (benches/bench_costs.py
``llvm_backward_memory``), not a test.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
from conftest import VARIANTS

HERE = Path(__file__).resolve().parent
WORKER = HERE / "llvm_worker.py"
LAMP = HERE.parents[1] / "scenes" / "spectra" / "uv_lamp_365.csv"

#: A sphere of `dye` in an open box of grey diffuse walls (three sides and a floor) under a
#: D65 sky and a 365 nm lamp (UV: fluorescence is excited directly and after wall bounces).
_BOX = """<scene version="3.0.0">
    <integrator type="{integrator}"><integer name="max_depth" value="5"/><integer name="rr_depth" value="3"/></integrator>
    <sensor type="perspective"><float name="fov" value="55"/>
        <transform name="to_world"><lookat origin="0, 0.3, 3.2" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"/>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
            <rfilter type="gaussian"/></film>
    </sensor>
    <emitter type="constant" id="sky"><spectrum type="fluo_illuminant" name="radiance">
        <string name="illuminant" value="D65"/><float name="scale" value="0.5"/></spectrum></emitter>
    <emitter type="point" id="lamp"><point name="position" x="0.8" y="1.5" z="1.5"/>
        <spectrum type="fluo_illuminant" name="intensity"><string name="filename" value="{lamp}"/>
            <boolean name="normalize" value="false"/><float name="scale" value="2"/></spectrum></emitter>
    {dye}
    <bsdf type="diffuse" id="wall"><rgb name="reflectance" value="0.6, 0.6, 0.6"/></bsdf>
    <shape type="sphere"><float name="radius" value="0.7"/><ref id="dye"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="2"/><translate z="-1.5"/></transform><ref id="wall"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate y="1" angle="90"/><translate x="-1.5"/></transform><ref id="wall"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate y="1" angle="-90"/><translate x="1.5"/></transform><ref id="wall"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/><translate y="-0.7"/></transform><ref id="wall"/></shape>
</scene>"""


def box(integrator: str, dye: str) -> str:
    return _BOX.format(integrator=integrator, dye=dye, lamp=LAMP)


JUNG = """<bsdf type="fluo_jung" id="dye"><float name="reflectance" value="0.5"/>
        <float name="emission_peak" value="520"/><float name="stokes_shift" value="110"/>
        <float name="concentration" value="0.6"/><float name="quantum_yield" value="0.9"/></bsdf>"""
QD = """<bsdf type="fluo_qd" id="dye"><float name="density" value="0.8"/><float name="quantum_yield" value="0.8"/>
        <float name="radius" value="2.5"/></bsdf>"""
TEXTURED = """<bsdf type="fluo_jung" id="dye"><float name="reflectance" value="0.5"/>
        <float name="emission_peak" value="520"/><float name="stokes_shift" value="110"/>
        <float name="quantum_yield" value="0.9"/>
        <texture type="bitmap" name="concentration"><string name="filename" value="{bitmap}"/>
            <boolean name="raw" value="true"/><string name="filter_type" value="nearest"/></texture></bsdf>"""


#: Roulette off (rr_depth past max_depth), for the RGB derivatives (test05).
NO_RR = ('<integer name="rr_depth" value="3"/>', '<integer name="rr_depth" value="9"/>')


def run_worker(jobs: list[dict]) -> tuple[list[dict], str]:
    """The jobs' results and what the worker printed (Mitsuba's log)."""
    # (test_fluo_volpath's test08 sends its 8 media jobs in one call: 9.6 min on one 2-core
    # machine, over 20 on another of the same kind, its kernels cold)
    proc = subprocess.run([sys.executable, str(WORKER), json.dumps(jobs)], capture_output=True, text=True,
                          timeout=2400, cwd=HERE)
    lines = [line[line.index("RESULT ") + 7:] for line in proc.stdout.splitlines() if "RESULT " in line]
    assert proc.returncode == 0 and lines, f"llvm worker failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return json.loads(lines[-1]), proc.stdout + proc.stderr


def check(results: list[dict], jobs: list[dict], tol: float = 0.1) -> None:
    for job, res in zip(jobs, results):
        assert "error" not in res, res
        for key, (ad, fd) in res["gradients"].items():
            print(job["variant"], key, "AD", ad, "central differences", fd)
            assert abs(fd) > 1e-5, f"{key}: the image does not depend on it, the check would be empty"
            assert abs(ad - fd) <= tol * abs(fd), f"{job['variant']} {key}: AD {ad} vs differences {fd}"


@pytest.mark.parametrize("variant", VARIANTS)
def test01_primal_is_fluo_path(variant):
    """fluo_prb renders what fluo_path renders, bit for bit up to the scalar variants' block
    order: the same loop with the same random numbers (fluorescent dye and coating)."""
    mi.set_variant(variant)
    for dye in (JUNG, QD):
        images = [np.array(mi.render(mi.load_string(box(i, dye)), spp=8, seed=5))
                  for i in ("fluo_prb", "fluo_path")]
        assert images[0].mean() > 0.01
        np.testing.assert_allclose(images[0], images[1], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("variant", VARIANTS)
def test02_polarized_variants_refuse_it(variant):
    """Path replay divides the throughput per wavelength, which a Mueller matrix does not
    allow: the polarized variant (of this family) refuses fluo_prb with a message naming
    fluo_path; fluo_path itself loads there."""
    polarized = variant.replace("_rgb", "_spectral") + "_polarized"
    mi.set_variant(polarized)
    mi.load_dict({"type": "fluo_path"})
    with pytest.raises(Exception, match=r"fluo_prb: path replay is not available in the polarized.*fluo_path"):
        mi.load_dict({"type": "fluo_prb"})


def test03_gradients_match_finite_differences_spectral():
    """llvm_ad_spectral, fluo_prb (path replay): AD of the image mean within 10 % of
    central differences for the continuous parameters of fluo_jung and fluo_qd's density
    and yield (its radius: test06), at 4096 spp and at 16384 for the concentration and the coating: a parameter that moves the elastic/shift
    probabilities or re-bakes a sampling table decorrelates the two difference renders (at
    512 spp the differences of concentration scatter by 25 %; at 16384, two seeds: AD
    0.001058 and 0.001058, differences 0.00112 and 0.00111). AD through fluo_path's
    recorded loop gives the same values to 1e-6."""
    jobs = [
        {"variant": "llvm_ad_spectral", "xml": box("fluo_prb", JUNG), "spp": 4096, "seed": 3,
         "gradients": {"dye.quantum_yield": 0.05, "dye.reflectance.value": 0.05,
                       "dye.emission_peak": 4.0, "dye.stokes_shift": 4.0}},
        {"variant": "llvm_ad_spectral", "xml": box("fluo_prb", JUNG), "spp": 16384, "seed": 7,
         "gradients": {"dye.concentration": 0.1}},
        {"variant": "llvm_ad_spectral", "xml": box("fluo_prb", QD), "spp": 16384, "seed": 3,
         "gradients": {"dye.density": 0.1, "dye.quantum_yield": 0.1}},
    ]
    check(run_worker(jobs)[0], jobs)


def test04_textured_concentration_gradient(tmp_path):
    """A 4×4 bitmap of concentrations: the derivative of the image mean along all texels
    together, fluo_prb in llvm_ad_spectral, within 10 % of central differences (16384 spp,
    as test03's concentration), and in llvm_ad_rgb (the replay's continuations, roulette off
    as test05's: each hit's shape matrix times its c·Q)."""
    bitmap = tmp_path / "c.exr"
    mi.set_variant("scalar_rgb")
    mi.Bitmap(np.linspace(0.2, 0.8, 16, dtype=np.float32).reshape(4, 4, 1)).write(str(bitmap))
    xml = box("fluo_prb", TEXTURED.format(bitmap=bitmap))
    jobs = [{"variant": "llvm_ad_spectral", "spp": 16384, "seed": 3, "xml": xml,
             "gradients": {"dye.concentration.data": 0.1}},
            {"variant": "llvm_ad_rgb", "spp": 512, "seed": 3, "xml": xml.replace(*NO_RR),
             "gradients": {"dye.concentration.data": 0.05}}]
    check(run_worker(jobs)[0], jobs)


def test04b_textured_dye_shape_gradients(tmp_path):
    """Issue 35: bitmaps of emission peaks (500–540 nm) and Stokes shifts (90–120 nm), 4×4
    texels each, nearest lookups: d(mean image) along all texels of each within 10 % of
    central differences, in llvm_ad_spectral (the closed forms' derivative at each hit's
    level; measured at 4096 spp: AD −6.30e-5 against −6.24e-5 for λe, 7.17e-5 against
    7.14e-5 for s) and in llvm_ad_rgb (each dye shape's reduced matrix and RGB parts
    differentiated along λe and s; roulette off as test05). The levels are the texels'
    values, so the differences move the hits' dye shapes as the derivatives do."""
    mi.set_variant("scalar_rgb")
    paths = {}
    for name, (lo, hi) in (("emission_peak", (500.0, 540.0)), ("stokes_shift", (90.0, 120.0))):
        paths[name] = tmp_path / f"{name}.exr"
        mi.Bitmap(np.linspace(lo, hi, 16, dtype=np.float32).reshape(4, 4, 1)).write(str(paths[name]))
    textures = "".join(f'''<texture type="bitmap" name="{name}"><string name="filename" value="{path}"/>
            <boolean name="raw" value="true"/><string name="filter_type" value="nearest"/></texture>'''
                       for name, path in paths.items())
    dye = f'''<bsdf type="fluo_jung" id="dye"><float name="reflectance" value="0.5"/>
        <float name="concentration" value="0.6"/><float name="quantum_yield" value="0.9"/>{textures}</bsdf>'''
    steps = {"dye.emission_peak.data": 4.0, "dye.stokes_shift.data": 4.0}
    # and a float λe beside the s texture (RGB: the shapes' derivative tables serve it too)
    mixed = dye.replace(textures, textures[textures.index('<texture type="bitmap" name="stokes_shift"'):]).replace(
        '<float name="concentration"', '<float name="emission_peak" value="520"/><float name="concentration"')
    jobs = [{"variant": "llvm_ad_spectral", "spp": 8192, "seed": 3, "xml": box("fluo_prb", dye), "gradients": steps},
            {"variant": "llvm_ad_rgb", "spp": 512, "seed": 3, "xml": box("fluo_prb", dye).replace(*NO_RR),
             "gradients": steps},
            {"variant": "llvm_ad_rgb", "spp": 512, "seed": 3, "xml": box("fluo_prb", mixed).replace(*NO_RR),
             "gradients": {"dye.emission_peak": 4.0, "dye.stokes_shift.data": 4.0}}]
    check(run_worker(jobs)[0], jobs)


def test05_rgb_with_fluorescence_replays():
    """llvm_ad_rgb: the reduced transport's matrix throughput is replayed (each vertex's
    radiance still to come as K coefficients, from continuations of its path), without the
    recorded loop's fallback or its warning, and the gradients match central differences,
    the dye's shape (emission peak, Stokes shift) included through the derivatives of the
    reduced matrices and RGB parts (fluo_jung's jit_reduced_derivatives); a scene without
    fluorescent materials (the dye replaced by a diffuse BSDF) replays as well."""
    plain = box("fluo_prb", '<bsdf type="diffuse" id="dye"><rgb name="reflectance" '
                                                  'value="0.5"/></bsdf>')
    # without roulette: in RGB the differences are otherwise smooth (no wavelength is
    # sampled), but roulette decides on the matrix throughput, which the step moves, and
    # its different decisions scattered the yield's differences by ~30 % at 512 spp
    no_rr = box("fluo_prb", JUNG).replace(*NO_RR)
    jobs = [{"variant": "llvm_ad_rgb", "xml": no_rr, "spp": 512, "seed": 3,
             "gradients": {"dye.concentration": 0.05, "dye.quantum_yield": 0.05, "dye.reflectance.value": 0.05,
                           "dye.emission_peak": 4.0, "dye.stokes_shift": 4.0}},
            {"variant": "llvm_ad_rgb", "xml": plain, "spp": 512, "seed": 3,
             "gradients": {"dye.reflectance.value": 0.05, "wall.reflectance.value": 0.05}}]
    results, log = run_worker(jobs)
    check(results, jobs)
    assert "fluo_prb" not in log and "recorded loop" not in log, log[-3000:]


def compare_replay(jobs: list[dict], rel: float, differ: bool = False) -> None:
    """Run jobs in (fluo_prb, fluo_path) pairs: each replayed derivative within `rel` of the
    recorded loop's (`differ`: and not equal to the last bit)."""
    results, _ = run_worker(jobs)
    for replay, recorded in zip(results[0::2], results[1::2]):
        assert "error" not in replay and "error" not in recorded, (replay, recorded)
        for key, (ad, _) in replay["gradients"].items():
            ref = recorded["gradients"][key][0]
            print(key, "replay", ad, "recorded loop", ref)
            assert abs(ref) > 1e-6 and ad == pytest.approx(ref, rel=rel), (key, ad, ref)
            assert not differ or ad != ref, (key, ad, ref)


def test06_replay_equals_the_recorded_loop():
    """The same derivatives two ways, in llvm_ad_spectral and (roulette off) llvm_ad_rgb: path
    replay (fluo_prb) and AD through fluo_path's recorded loop, for a parameter of the dye's
    amount and of its shape in fluo_jung and fluo_qd, and the walls' reflectance in RGB
    (measured once for all eight spectral ones: equal to 2e-6; RGB: to 7e-7; fluo_qd's
    radius included: in this box under the 365 nm lamp its central
    differences do not settle, 0.1 nm steps give -0.0078 and 0.02 nm +0.0061 at 4096 spp,
    while both ADs give 0.01247; test_llvm.py test21 checks radius against differences where
    they settle). Equal to 1e-4 relative: the replay revisits the same vertices with the same
    random numbers and differentiates each vertex's weight instead of the whole loop; in RGB
    each vertex's continuations follow the path's own vertices where roulette is off (with
    it, their own roulette draws other, equally valid, paths)."""
    keys = {JUNG: {"dye.concentration": 0, "dye.emission_peak": 0}, QD: {"dye.density": 0, "dye.radius": 0}}
    rgb = {JUNG: {"dye.quantum_yield": 0, "dye.stokes_shift": 0, "wall.reflectance.value": 0},
           QD: {"dye.density": 0, "dye.radius": 0}}
    jobs = [{"variant": "llvm_ad_spectral", "xml": box(integrator, dye), "spp": 256, "seed": 9,
             "gradients": steps, "ad_only": True}
            for dye, steps in keys.items() for integrator in ("fluo_prb", "fluo_path")]
    jobs += [{"variant": "llvm_ad_rgb", "xml": box(integrator, dye).replace(*NO_RR), "spp": 64, "seed": 9,
              "gradients": steps, "ad_only": True}
             for dye, steps in rgb.items() for integrator in ("fluo_prb", "fluo_path")]
    compare_replay(jobs, rel=1e-4)


def test06b_rgb_replay_with_roulette():
    """llvm_ad_rgb with roulette (rr_depth 3, max_depth 5): each vertex's continuations draw
    their own roulette decisions on their own throughput, so replay and recorded loop are two
    estimates of one derivative: within 5 % of each other at 1024 spp (measured: 0.03–1.9 %),
    and not equal to the last bit (the replay, not the recorded loop, ran)."""
    keys = {JUNG: {"dye.concentration": 0, "dye.emission_peak": 0, "wall.reflectance.value": 0},
            QD: {"dye.density": 0, "dye.radius": 0}}
    jobs = [{"variant": "llvm_ad_rgb", "xml": box(integrator, dye), "spp": 1024, "seed": 9,
             "gradients": steps, "ad_only": True}
            for dye, steps in keys.items() for integrator in ("fluo_prb", "fluo_path")]
    compare_replay(jobs, rel=0.05, differ=True)


@pytest.mark.parametrize("variant", ["llvm_ad_spectral", "llvm_ad_rgb"], ids=["spectral", "rgb"])
def test07_inverse_example_recovers_the_map(variant):
    """examples/inverse_map.py recovers its hidden 32×32 concentration map to RMSE ≤ 0.05
    in 200 iterations through fluo_prb, and spectrally the emission peak within 5 nm from
    30 nm away (it exits non-zero otherwise). Measured (2 cores): spectral RMSE 0.170 -> 0.037,
    peak 560.09 nm, 13.5 s; RGB (basis auto, replayed) 0.170 -> 0.013, 17.8 s."""
    proc = subprocess.run([sys.executable, str(HERE.parents[1] / "examples" / "inverse_map.py"), "--variant", variant],
                          capture_output=True, text=True, timeout=900, cwd=HERE)
    print(proc.stdout[-800:])
    assert proc.returncode == 0 and "recovered" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]
