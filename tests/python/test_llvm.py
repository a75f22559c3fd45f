"""fluo's plugins in the vectorised variants (llvm_ad_rgb, llvm_ad_spectral): rendering,
gradients, updates and refusals that need an llvm process.

Every plugin is one class serving every variant, so the image comparisons here (llvm image
means within Z standard errors of the scalar variants' images, the per-pixel variance from
the scalar images) check the variant plumbing (dispatch, loops, registration), not a second
implementation; each plugin's own references run in llvm through test_variants.py.
The llvm renders run in a fresh process (``llvm_worker.py``: Mitsuba 3.8 cannot load an
llvm scene after a scalar render in one process).
"""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

import fluo
from llvm_worker import eval_bsdf

REPO = Path(__file__).resolve().parents[2]
SCENES = REPO / "scenes"
WORKER = Path(__file__).with_name("llvm_worker.py")
#: Largest accepted |z| per channel. Path-traced pixels are heavy-tailed, so the variance
#: estimate from a few images is itself noisy; 4.5 keeps false alarms rare while a 1 % bias
#: of a box's mean (about 6 standard errors at 512 spp, 24²) still fails.
Z = 4.5
#: Differences below this fraction of the image mean pass whatever their z (the variance
#: estimate can be small by chance); a missing or doubled glow is far larger.
REL_FLOOR = 0.0075
#: Scalar renders per comparison (their spread estimates the per-pixel variance).
SCALAR_SEEDS = 3
#: The plugins served in the vectorised variants (fluo_common.h, jit_plugin(), as the
#: library reports them; test11 holds it against what actually loads and the README).
JIT_PLUGINS = fluo.JIT_PLUGINS
MATRICES = REPO / "data" / "matrices"


def run_llvm(jobs: list[dict], timeout: int = 600) -> list[dict]:
    """Run render jobs in a fresh process (llvm_worker.py documents the job format)."""
    proc = subprocess.run([sys.executable, str(WORKER), json.dumps(jobs)], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)
    lines = [line[line.index("RESULT ") + 7:] for line in proc.stdout.splitlines() if "RESULT " in line]
    assert proc.returncode == 0 and lines, f"llvm worker failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return json.loads(lines[-1])


def scalar_images(variant: str, job: dict) -> tuple[np.ndarray, np.ndarray]:
    mi.set_variant(variant)
    params = job.get("params", {})
    scene = mi.load_string(job["xml"], **params) if "xml" in job else mi.load_file(job["file"], **params)
    kwargs = {}
    if "integrator" in job:
        kwargs["integrator"] = mi.load_dict({"type": job["integrator"], "max_depth": job.get("max_depth", 6)})
    return np.stack([np.array(mi.render(scene, spp=job["spp"], seed=s, **kwargs), dtype=np.float64)
                     for s in range(SCALAR_SEEDS)])


def z_scores(scalar: np.ndarray, mean_llvm) -> np.ndarray:
    """z of the llvm image mean against the mean of the scalar images (same settings)."""
    m, n = scalar.shape[0], scalar.shape[1] * scalar.shape[2]
    var = np.mean(np.var(scalar, axis=0, ddof=1), axis=(0, 1))  # per-pixel MC variance, per channel
    se = np.sqrt(var / n * (1.0 + 1.0 / m))  # llvm mean (1 image) vs scalar mean (m images)
    return (np.asarray(mean_llvm) - scalar.mean(axis=(0, 1, 2))) / np.maximum(se, 1e-12)


def scene_job(file: Path, variant: str, spp: int, res: int = 24, **params) -> dict:
    params = {"res": str(res), "spp": str(spp), **{k: str(v) for k, v in params.items()}}
    return {"variant": variant, "file": str(file), "params": params, "spp": spp, "seed": 7}


# (scene, llvm variant, extra params): the Jung bench box under D65 from 300 nm (every RGB
# basis), the demo objects under a UV-only lamp and under D65, sigmoid coefficients,
# `color` (the cube), textured concentration and emission peak (the label).
CASES = [
    ("bench/jung_box.xml", "llvm_ad_spectral", {}),
    ("bench/jung_box.xml", "llvm_ad_rgb", {"basis": "rgb"}),
    ("bench/jung_box.xml", "llvm_ad_rgb", {"basis": "xyzu"}),
    ("bench/jung_box.xml", "llvm_ad_rgb", {"basis": "x7"}),
    ("fluo_path_uv.xml", "llvm_ad_spectral", {}),
    ("fluo_path_uv.xml", "llvm_ad_rgb", {"basis": "x7"}),
    ("jung_spheres.xml", "llvm_ad_spectral", {}),
    ("jung_spheres.xml", "llvm_ad_rgb", {}),
    ("bench/highlighter_box.xml", "llvm_ad_spectral", {}),
    ("bench/highlighter_box.xml", "llvm_ad_rgb", {"basis": "x7"}),
    ("fluo_path_d65.xml", "llvm_ad_spectral", {}),
    ("fluo_path_d65.xml", "llvm_ad_rgb", {}),
    ("label_textured.xml", "llvm_ad_spectral", {}),
    ("label_textured.xml", "llvm_ad_rgb", {}),
]


def test01_llvm_images_equal_scalar_within_noise():
    """Image means of llvm renders lie within Z standard errors of the scalar ones, in
    both variants, every basis, UV-only light, coefficients and `color`."""
    jobs = [scene_job(SCENES / s, v, spp=512, **p) for s, v, p in CASES]
    results = run_llvm(jobs)
    report, bad = [], []
    for (s, v, p), job, res in zip(CASES, jobs, results):
        assert "error" not in res, f"{s} {v} {p}: {res['error']}"
        assert res["finite"], f"{s} {v}: non-finite pixels"
        scalar = scalar_images(v.replace("llvm_ad_", "scalar_"), job)
        assert scalar.mean() > 1e-3, f"{s}: the scalar image is black, the comparison would be empty"
        z = z_scores(scalar, res["mean"])
        line = (f"{s} {v} {p}: llvm {np.round(res['mean'], 4)} scalar "
                f"{np.round(scalar.mean(axis=(0, 1, 2)), 4)} z {np.round(z, 2)}")
        report.append(line)
        rel = np.abs(np.asarray(res["mean"]) - scalar.mean(axis=(0, 1, 2))) / scalar.mean()
        if np.any((np.abs(z) > Z) & (rel > REL_FLOOR)):
            bad.append(line)
    print("\n".join(report))
    assert not bad, "llvm differs from scalar beyond noise:\n" + "\n".join(bad)


def test02_without_fluorescence_fluo_path_is_path():
    """Without fluorescent materials (every dye at concentration 0) llvm fluo_path renders
    what llvm path renders (within noise), in both variants."""
    xml = (SCENES / "bench" / "jung_box.xml").read_text().replace('name="concentration" value="0.9"',
                                                                  'name="concentration" value="0"')
    xml = xml.replace('name="concentration" value="1.0"', 'name="concentration" value="0"')
    xml = xml.replace('filename="include/', f'filename="{SCENES / "bench" / "include"}/')
    jobs = []
    for v in ("llvm_ad_spectral", "llvm_ad_rgb"):
        for integ, seed in (("fluo_path", 1), ("path", 2), ("path", 3), ("path", 4)):
            jobs.append({"variant": v, "xml": xml, "params": {"res": "24", "spp": "256", "basis": "x7",
                                                              "method": "ours"},
                         "spp": 256, "seed": seed, "integrator": integ, "image": True})
    results = run_llvm(jobs)
    for i in range(0, len(jobs), 4):
        assert all("error" not in r for r in results[i:i + 4]), results[i:i + 4]
        fl, *paths = (np.array(r["image"]) for r in results[i:i + 4])
        z = z_scores(np.stack(paths), fl.mean(axis=(0, 1)))
        assert np.all(np.abs(z) < Z), f"{jobs[i]['variant']}: fluo_path vs path z = {z}"


def test03_other_plugins_and_unsupported_inputs_raise_clear_errors():
    """In llvm: plugins not yet ported raise "not available"; invalid inputs raise errors that
    name the parameter instead of rendering without it; fluo_jung's textured parameters are
    validated as in the scalar variants (every (λe, s) pair the textures combine). Bilinear
    colour texels render (finite, lit)."""
    base = """<scene version="3.0.0"><integrator type="fluo_path"/>
        <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="4"/>
        <integer name="height" value="4"/></film></sensor>
        <emitter type="constant"><spectrum type="fluo_illuminant" name="radiance">
        <string name="illuminant" value="D65"/></spectrum></emitter>
        <shape type="sphere">{bsdf}</shape></scene>"""
    cases = {
        "qd_bad_radius": ('<bsdf type="fluo_qd"><float name="radius" value="9"/></bsdf>', 'radius'),
        "textured_pair": ('<bsdf type="fluo_jung"><texture type="checkerboard" name="emission_peak"><float '
                          'name="color0" value="300"/><float name="color1" value="700"/></texture><texture '
                          'type="checkerboard" name="stokes_shift"><float name="color0" value="20"/><float '
                          'name="color1" value="500"/></texture></bsdf>',
                          'the pair emission_peak = 300, stokes_shift = 500'),
        "bad_yield": ('<bsdf type="fluo_jung"><float name="quantum_yield" value="1.5"/></bsdf>',
                      'quantum_yield'),
        "matrix_index": ('<bsdf type="fluo_matrix"><string name="filename0" value="a.csv"/></bsdf>',
                         'invalid parameter "filename0" = "a.csv": file not found'),
        "matrix_missing": ('<bsdf type="fluo_matrix"><string name="filename" value="no_such.csv"/></bsdf>',
                           'file not found'),
        "gmm_malformed": (f'<bsdf type="fluo_gmm"><string name="filename" value="{MATRICES / "jung_orange.csv"}"/>'
                          '</bsdf>', 'fluo_gmm'),
    }
    jobs = [{"variant": "llvm_ad_spectral", "xml": base.format(bsdf=b), "spp": 1} for b, _ in cases.values()]
    for name in fluo.PLUGIN_KINDS:
        if name in JIT_PLUGINS:
            continue
        kind = fluo.PLUGIN_KINDS[name]
        if kind == "bsdf":
            jobs.append({"variant": "llvm_ad_rgb", "xml": base.format(bsdf=f'<bsdf type="{name}"/>'), "spp": 1})
    bilinear = ('<bsdf type="fluo_jung"><texture type="bitmap" name="color"><string name="filename" '
                f'value="{SCENES / "textures" / "acescg_card.exr"}"/><boolean name="raw" value="true"/>'
                '</texture><string name="texel_interpolation" value="bilinear"/></bsdf>')
    seen = base.replace('<shape type="sphere">', '<shape type="sphere"><point name="center" x="0" y="0" z="4"/>')
    renders = [{"variant": v, "xml": seen.format(bsdf=bilinear), "spp": 4} for v in ("llvm_ad_rgb", "llvm_ad_spectral")]
    results = run_llvm(jobs + renders)
    for (name, (_, expected)), res in zip(cases.items(), results):
        assert "error" in res and expected in res["error"], f"{name}: {res}"
    for res in results[len(cases):len(jobs)]:
        assert "error" in res and "not available in variant" in res["error"], res
    for res in results[len(jobs):]:
        assert "mean" in res and all(np.isfinite(res["mean"])) and max(res["mean"]) > 0, res


def test04_bsdf_values_equal_the_rust_reference():
    """fluo_jung's per-lane closed forms (absorption mirrored over wavenumber, the sigmoid,
    the RGB variant's bounded albedo) give the values the scalar variants get from Rust, at
    random directions and wavelengths (float rounding: rtol 1e-4)."""
    rng = np.random.default_rng(5)
    points = []
    for _ in range(40):
        wi, wo = rng.normal(size=3), rng.normal(size=3)
        wi[2], wo[2] = abs(wi[2]) + 0.05, abs(wo[2]) + 0.05
        lam = rng.uniform(300.0, 830.0, size=4)
        lam[:2] = rng.uniform(440.0, 520.0, size=2)  # inside the dye's absorption band
        points.append([list(wi / np.linalg.norm(wi)), list(wo / np.linalg.norm(wo)), list(lam)])
    bsdfs = [
        {"type": "fluo_jung", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.3]}, "emission_peak": 540.0,
         "stokes_shift": 70.0, "concentration": 0.8},
        {"type": "fluo_jung", "coefficients": "0.0, 0.02, -11.5", "emission_peak": 610.0, "stokes_shift": 90.0,
         "concentration": 1.0, "quantum_yield": 0.7},
        {"type": "fluo_jung", "color": {"type": "rgb", "value": [0.9, 0.1, 0.8]}},
    ]
    jobs = [{"variant": v, "bsdf": b, "points": points} for v in ("llvm_ad_spectral", "llvm_ad_rgb") for b in bsdfs]
    results = run_llvm(jobs)
    for job, res in zip(jobs, results):
        assert "error" not in res, res
        mi.set_variant(job["variant"].replace("llvm_ad_", "scalar_"))
        ref = np.array(eval_bsdf(mi.load_dict(job["bsdf"]), points))
        got = np.array(res["values"])
        assert np.abs(ref).max() > 1e-3
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-6, err_msg=f"{job['variant']} {job['bsdf']}")



def test05_color_texture_per_texel():
    """A `color` texture (upsample_acescg.xml: a wide-gamut chart lit directly, each pixel
    one texel's reflected colour) renders in llvm pixel by pixel as in the scalar variants:
    the per-texel dyes and RGB albedos land on the same texels (a permutation would move
    whole patches) and the spectral shift of each texel's dye is unbiased."""
    for v in ("llvm_ad_spectral", "llvm_ad_rgb"):
        job = {"variant": v, "file": str(SCENES / "upsample_acescg.xml"), "params": {"spp": "64"}, "spp": 256,
               "seed": 7, "image": True}
        res = run_llvm([job])[0]
        assert "error" not in res, res
        gpu = np.array(res["image"])
        scalar = scalar_images(v.replace("llvm_ad_", "scalar_"), job)
        # 8×8-pixel blocks (about one chart patch): per-block z against the scalar mean,
        # with the per-pixel variance estimated from the scalar images.
        b = 8
        def blocks(x):
            h, w = x.shape[-3] // b * b, x.shape[-2] // b * b
            x = x[..., :h, :w, :]
            return x.reshape(*x.shape[:-3], h // b, b, w // b, b, 3).mean(axis=(-4, -2))
        var = np.var(scalar, axis=0, ddof=1)
        ref = blocks(scalar).mean(axis=0)
        se = np.sqrt(blocks(var) / (b * b) * (1 + 1 / scalar.shape[0]))
        se = np.maximum(se, 2e-3 * np.abs(ref) + 1e-4)  # float rounding where there is no noise (RGB)
        zb = (blocks(gpu) - ref) / se
        z = z_scores(scalar, gpu.mean(axis=(0, 1)))
        print(v, "image z", z, "block |z| p99", np.percentile(np.abs(zb), 99), "max", np.abs(zb).max())
        assert np.percentile(np.abs(zb), 99) < 4.5 and np.abs(zb).max() < 8, f"{v}: patches differ from scalar"
        assert np.all(np.abs(z) < Z), f"{v}: mean differs from scalar beyond noise, z = {z}"


GRAD_SCENE = """<scene version="3.0.0">
    <integrator type="fluo_path"><integer name="max_depth" value="3"/>{basis}</integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>
    <emitter type="constant"><spectrum type="fluo_illuminant" name="radiance">
        <string name="illuminant" value="D65"/></spectrum></emitter>
    <bsdf type="fluo_jung" id="dye">
        <float name="reflectance" value="0.5"/>
        <float name="emission_peak" value="540"/><float name="stokes_shift" value="70"/>
        <float name="concentration" value="0.6"/><float name="quantum_yield" value="0.9"/>
    </bsdf>
    <shape type="sphere"><ref id="dye"/></shape>
</scene>"""


def test06_gradients_match_finite_differences():
    """d(mean image)/d(parameter) by automatic differentiation through the llvm kernels equals
    central finite differences with the same seed: within 10 % for concentration, quantum
    yield and the reflectance (measured: under 2 %), within 25 % for emission peak and Stokes
    shift (measured: 1 % and 13 %; changing the dye's shape re-bakes its sampling table, so
    the two finite-difference renders share fewer random numbers) in llvm_ad_spectral; the same
    five in llvm_ad_rgb, where the dye's shape reaches the image through the reduced matrices
    and RGB parts baked from it, differentiated through their derivatives along λe and s
    (fluo_jung's jit_reduced_derivatives)."""
    steps = {"dye.concentration": 0.05, "dye.quantum_yield": 0.05, "dye.emission_peak": 4.0,
             "dye.stokes_shift": 2.0, "dye.reflectance.value": 0.05}
    jobs = [{"variant": "llvm_ad_spectral", "xml": GRAD_SCENE.format(basis=""), "spp": 512, "seed": 3,
             "gradients": steps},
            {"variant": "llvm_ad_rgb", "xml": GRAD_SCENE.format(basis='<string name="basis" value="x7"/>'),
             "spp": 512, "seed": 3,
             "gradients": steps}]
    results = run_llvm(jobs)
    for job, res in zip(jobs, results):
        assert "error" not in res, res
        for key, (ad, fd) in res["gradients"].items():
            print(job["variant"], key, "ad", ad, "fd", fd)
            assert abs(fd) > 1e-5, f"{key}: the image does not depend on it, the check would be empty"
            tol = 0.25 if key in ("dye.emission_peak", "dye.stokes_shift") else 0.1
            assert abs(ad - fd) <= tol * abs(fd), f"{job['variant']} {key}: AD {ad} vs finite differences {fd}"


#: GRAD_SCENE's dye, replaced by a quantum-dot coating in test06b.
QD_DYE_OLD = """<bsdf type="fluo_jung" id="dye">
        <float name="reflectance" value="0.5"/>
        <float name="emission_peak" value="540"/><float name="stokes_shift" value="70"/>
        <float name="concentration" value="0.6"/><float name="quantum_yield" value="0.9"/>
    </bsdf>"""


def test06b_gradients_at_zero_concentration_and_yield():
    """Issue 32 finding 6: at concentration 0 (or quantum yield 0) the elastic/shift choice
    never drew the shift, so AD lost the reradiation's derivative (AD -0.0436 against
    -0.0230 by differences). The sphere under a constant sky has no inter-reflection, so the
    image is linear in c and Q and the forward difference from 0 is exact up to noise (a
    long step: the render at 0 draws fewer random numbers, so the two share no noise).
    fluo_qd at quantum_yield 0 (density 0.8): its coating was not fluorescent at Q = 0, so dQ was
    0 against 0.083 by differences; it now bakes its tables at Q = 1 (nothing in them depends
    on Q) and weights by Q per lane, in both AD variants (measured: spectral 0.0851 against
    0.0831, RGB 0.0838 against 0.0886: RGB's image is slightly non-linear in Q, its central
    difference at Q = 0.3 equals AD to 0.1 %).
    llvm_ad_rgb fluo_jung at c = 0: a reflectance texture's factor clip(1 − c·s, 0, 1) rounded
    to 1 below c ≈ 1e-5 and the clip's tie dropped d/dc (AD 0.0118 against 0.0086); now 0.00858
    against 0.00858. At Q = 0 in RGB the render at exactly 0 takes the plain BSDF's path (its
    RGB albedo) and the one above it the reduced transport, whose elastic part differs by the
    basis' projection: the forward difference is taken from Q = 1e-3 (measured: AD at 0
    0.02682, differences from 1e-3 0.02684, from 0 0.0353)."""
    base = GRAD_SCENE.format(basis="")
    assert QD_DYE_OLD in base
    qd = base.replace(QD_DYE_OLD, '<bsdf type="fluo_qd" id="dye"><float name="quantum_yield" value="0"/>'
                                  '<float name="density" value="0.8"/></bsdf>')
    jobs = [*({"variant": v, "spp": 2048, "seed": 4, "forward": True, "xml": qd,
               "gradients": {"dye.quantum_yield": 0.2}} for v in ("llvm_ad_spectral", "llvm_ad_rgb")),
            {"variant": "llvm_ad_spectral", "spp": 4096, "seed": 4, "forward": True,
             "xml": base.replace('<float name="concentration" value="0.6"/>', '<float name="concentration" value="0"/>'),
             "gradients": {"dye.concentration": 0.4}},
            {"variant": "llvm_ad_rgb", "spp": 1024, "seed": 4, "forward": True,
             "xml": base.replace('<float name="concentration" value="0.6"/>', '<float name="concentration" value="0"/>'),
             "gradients": {"dye.concentration": 0.05}},
            {"variant": "llvm_ad_spectral", "spp": 4096, "seed": 4, "forward": True,
             "xml": base.replace('<float name="quantum_yield" value="0.9"/>', '<float name="quantum_yield" value="0"/>'),
             "gradients": {"dye.quantum_yield": 0.4}}]
    rgb_q = [{"variant": "llvm_ad_rgb", "spp": 1024, "seed": 4, "forward": True, "gradients": {"dye.quantum_yield": 0.05},
              "xml": base.replace('<float name="quantum_yield" value="0.9"/>', f'<float name="quantum_yield" value="{q}"/>')}
             for q in ("0", "0.001")]
    results = run_llvm(jobs + rgb_q)
    (ad0, _), (_, fd_above) = (r["gradients"]["dye.quantum_yield"] for r in results[len(jobs):])
    print("llvm_ad_rgb quantum_yield at 0: ad", ad0, "forward difference from 1e-3", fd_above)
    assert abs(ad0 - fd_above) <= 0.1 * abs(fd_above), (ad0, fd_above)
    for job, res in zip(jobs, results):
        assert "error" not in res, res
        for key, (ad, fd) in res["gradients"].items():
            print(job["variant"], key, "at 0: ad", ad, "forward difference", fd)
            assert abs(fd) > 1e-4, f"{key}: the image does not depend on it, the check would be empty"
            assert abs(ad - fd) <= 0.1 * abs(fd), f"{key} at 0: AD {ad} vs forward difference {fd}"


def test07_invalid_update_is_refused_and_the_material_keeps_working():
    """An update through mi.traverse that breaks a parameter's range raises an error naming
    it, and the material renders as before afterwards."""
    code = GRAD_SCENE.format(basis="")
    script = f'''
import json, mitsuba as mi, numpy as np
mi.set_variant("llvm_ad_spectral")
import fluo
scene = mi.load_string({code!r})
p = mi.traverse(scene)
before = np.array(mi.render(scene, spp=16, seed=1)).mean()
errors = []
for key, value in (("dye.concentration", 1.5), ("dye.stokes_shift", 2000.0), ("dye.quantum_yield", float("nan"))):
    p[key] = mi.Float(value)
    try:
        p.update()
        errors.append(None)
    except Exception as e:
        errors.append(str(e))
    p = mi.traverse(scene)
after = np.array(mi.render(scene, spp=16, seed=1)).mean()
print("RESULT " + json.dumps({{"errors": errors, "before": float(before), "after": float(after),
      "conc": float(p["dye.concentration"][0])}}))
'''
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, cwd=REPO)
    lines = [ln[ln.index("RESULT ") + 7:] for ln in proc.stdout.splitlines() if "RESULT " in ln]
    assert lines, proc.stderr[-3000:]
    res = json.loads(lines[-1])
    for name, err in zip(("concentration", "stokes_shift", "quantum_yield"), res["errors"]):
        assert err is not None and name in err, (name, err)
    assert res["conc"] == pytest.approx(0.6)
    assert res["after"] == pytest.approx(res["before"], rel=1e-6)


def test08_inverse_rendering_example_recovers_the_dye():
    """examples/inverse_jung.py recovers concentration and emission peak from a target image
    within its tolerances (it exits non-zero otherwise), starting 0.4 and 40 nm away."""
    proc = subprocess.run([sys.executable, str(REPO / "examples" / "inverse_jung.py")], capture_output=True,
                          text=True, timeout=900, cwd=REPO)
    print(proc.stdout[-1500:])
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "MISSED" not in proc.stdout and proc.stdout.count(" ok (tolerance") == 2


D65 = '<string name="illuminant" value="D65"/>'
UV_FLAT = f'<string name="filename" value="{SCENES / "spectra" / "uv_flat_300_380.csv"}"/>'
CLOSEUP = """<scene version="3.0.0">
    <integrator type="fluo_path"><integer name="max_depth" value="3"/>{basis}
        <boolean name="hide_emitters" value="true"/></integrator>
    <sensor type="perspective"><float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/></film>
    </sensor>
    <emitter type="constant"><spectrum type="fluo_illuminant" name="radiance">{light}</spectrum></emitter>
    {bsdf}
    <shape type="sphere"><ref id="{id}"/></shape>
</scene>"""


def closeup(bsdf: str, light: str, basis: str = "", res: int = 24) -> str:
    """A sphere filling the view with material `bsdf` (an XML element whose id it reads) under
    a constant `light` (a fluo_illuminant's parameters), fluo_path with optional `basis`."""
    return CLOSEUP.format(bsdf=bsdf, id=re.search(r'id="([^"]+)"', bsdf).group(1), light=light, basis=basis,
                          res=res)


def lit_variants():
    """(light, its label, llvm variant, basis) for D65 in both variants (RGB: x7) and the
    300-380 nm lamp in the spectral one (UV-only light in RGB is the reduced transport's
    known limit, warned)."""
    for light, label in ((D65, "d65"), (UV_FLAT, "uv")):
        for v, basis in (("llvm_ad_spectral", ""), ("llvm_ad_rgb", '<string name="basis" value="x7"/>')):
            if light is UV_FLAT and v == "llvm_ad_rgb":
                continue
            yield light, label, v, basis


def resampled_matrix(path: Path, source: str, keep) -> Path:
    """data/matrices/`source` on the wavelengths (both axes) where keep(nm) holds."""
    rows = [r for r in csv.reader((MATRICES / source).open()) if r and not r[0].startswith("#")]
    cols = [0] + [i for i in range(1, len(rows[0])) if keep(float(rows[0][i]))]
    with path.open("w", newline="") as f:
        out = csv.writer(f)
        out.writerow([rows[0][i] for i in cols])
        for r in rows[1:]:
            if keep(float(r[0])):
                out.writerow([r[i] for i in cols])
    return path


def irregular_matrix(path: Path) -> Path:
    """jung_yellow.csv on an irregular grid (steps of 10 and 20 nm on both axes), so that
    cells are found by binary search rather than by the uniform grids' multiplication."""
    return resampled_matrix(path, "jung_yellow.csv", lambda w: int(w) // 10 % 3 != 1)


def test09_measured_materials_equal_scalar_within_noise(tmp_path):
    """fluo_matrix (tabulated rows: binary search and the cell's quadratic root per lane) and
    fluo_gmm (truncated conditional normals with float erfc/Φ⁻¹) render in llvm what the
    scalar variants render: close-ups filling the view under D65 from 300 nm and under a
    flat 300-380 nm lamp (the glow alone) in both variants (also a matrix on an irregular
    grid: binary searches instead of the uniform grids' index), the measured demo scenes
    and the measured bench box.
    The glow's estimator is heavy-tailed (a per-pixel variance from a few images
    underestimates the variance of the image mean), so the test compares image means with
    the spread of the means themselves: 4 llvm and 6 scalar seeds, a pooled two-sample z."""
    cases = []
    irregular = irregular_matrix(tmp_path / "irregular.csv")
    for plugin, file in (("fluo_matrix", "jung_yellow.csv"), ("fluo_matrix", "jung_brightener.csv"),
                         ("fluo_gmm", "jung_orange.gmm.json"), ("fluo_matrix", irregular)):
        for light, label, v, basis in lit_variants():
            xml = closeup(f'<bsdf type="{plugin}" id="m"><string name="filename" value="{MATRICES / file}"/>'
                          '</bsdf>', light, basis)
            cases.append((f"{plugin} {Path(file).name} {label}", v, {"variant": v, "xml": xml, "spp": 256}))
    for scene in ("fluo_measured.xml", "fluo_measured_uv.xml", "bench/measured_box.xml"):
        for v in ("llvm_ad_spectral", "llvm_ad_rgb"):
            params = {"matrix_a": MATRICES / "jung_yellow.csv", "matrix_b": MATRICES / "jung_brightener.csv"}
            if scene.startswith("bench/"):
                params["basis"] = "x7"
            cases.append((scene, v, scene_job(SCENES / scene, v, spp=256, **params)))
    assert_means_equal(cases)


def assert_means_equal(cases: list, llvm_seeds: int = 4, scalar_seeds: int = 6) -> None:
    """Each (name, llvm variant, job) renders in llvm with `llvm_seeds` seeds and in the
    matching scalar variant with `scalar_seeds`; the image means must agree by a pooled
    two-sample z (or within REL_FLOOR of the image mean)."""
    results = run_llvm([{**job, "seed": 11 + s} for _, _, job in cases for s in range(llvm_seeds)])
    report, bad = [], []
    for c, (name, v, job) in enumerate(cases):
        runs = results[c * llvm_seeds:(c + 1) * llvm_seeds]
        assert all("error" not in r for r in runs), f"{name} {v}: {runs[0].get('error')}"
        assert all(r["finite"] for r in runs), f"{name} {v}: non-finite pixels"
        a = np.array([r["mean"] for r in runs])
        mi.set_variant(v.replace("llvm_ad_", "scalar_"))
        params = job.get("params", {})
        scene = mi.load_string(job["xml"]) if "xml" in job else mi.load_file(job["file"], **params)
        kwargs = {}
        if "integrator" in job:  # as llvm_worker.py
            kwargs["integrator"] = mi.load_dict({"type": job["integrator"], "max_depth": job.get("max_depth", 6)})
        b = np.array([np.array(mi.render(scene, spp=job["spp"], seed=s, **kwargs)).mean(axis=(0, 1))
                      for s in range(scalar_seeds)])
        assert np.abs(b.mean()) > 1e-3, f"{name}: the scalar image is black, the comparison would be empty"
        pooled = (np.var(a, axis=0, ddof=1) * (llvm_seeds - 1) + np.var(b, axis=0, ddof=1) * (scalar_seeds - 1)) / (
            llvm_seeds + scalar_seeds - 2)
        z = (a.mean(axis=0) - b.mean(axis=0)) / np.sqrt(pooled * (1 / llvm_seeds + 1 / scalar_seeds) + 1e-20)
        line = f"{name} {v}: llvm {np.round(a.mean(axis=0), 4)} scalar {np.round(b.mean(axis=0), 4)} z {np.round(z, 2)}"
        report.append(line)
        rel = np.abs(a.mean(axis=0) - b.mean(axis=0)) / np.abs(b.mean())
        if np.any((np.abs(z) > Z) & (rel > REL_FLOOR)):
            bad.append(line)
    print("\n".join(report))
    assert not bad, "llvm differs from scalar beyond noise:\n" + "\n".join(bad)


def test10_measured_bsdf_values_equal_the_rust_reference(tmp_path):
    """The diagonal ρ(λ) per lane (spectral) and the RGB albedos equal the scalar variants'
    Rust values at random directions and wavelengths, including beyond the diagonal's ends."""
    rng = np.random.default_rng(9)
    points = []
    for _ in range(40):
        wi, wo = rng.normal(size=3), rng.normal(size=3)
        wi[2], wo[2] = abs(wi[2]) + 0.05, abs(wo[2]) + 0.05
        points.append([list(wi / np.linalg.norm(wi)), list(wo / np.linalg.norm(wo)),
                       list(rng.uniform(250.0, 900.0, size=4))])
    bsdfs = [{"type": "fluo_matrix", "filename": str(MATRICES / "jung_yellow.csv")},
             {"type": "fluo_matrix", "filename": str(irregular_matrix(tmp_path / "irregular.csv"))},
             {"type": "fluo_gmm", "filename": str(MATRICES / "jung_orange.gmm.json")}]
    assert_bsdf_values_equal(bsdfs, points, rtol=1e-4, atol=1e-6, peak=1e-3)


def assert_bsdf_values_equal(bsdfs: list, points: list, rtol: float, atol: float, peak: float) -> None:
    """Each BSDF's eval at `points` in both llvm variants equals the matching scalar
    variant's, whose largest value must exceed `peak` (else the check would be empty)."""
    jobs = [{"variant": v, "bsdf": b, "points": points} for v in ("llvm_ad_spectral", "llvm_ad_rgb") for b in bsdfs]
    for job, res in zip(jobs, run_llvm(jobs)):
        assert "error" not in res, res
        mi.set_variant(job["variant"].replace("llvm_ad_", "scalar_"))
        ref = np.array(eval_bsdf(mi.load_dict(job["bsdf"]), points))
        assert np.abs(ref).max() > peak
        np.testing.assert_allclose(np.array(res["values"]), ref, rtol=rtol, atol=atol,
                                   err_msg=f"{job['variant']} {job['bsdf']}")


def test11_readme_variants_column_is_true():
    """The README's plugin table says, per plugin, which variants serve it: every plugin
    marked "llvm" instantiates in llvm_ad_rgb and llvm_ad_spectral (or fails for a reason of
    its own, e.g. a missing file), every other one raises "not available in variant"."""
    table = {}
    for line in (REPO / "README.md").read_text(encoding="utf-8").splitlines():
        m = re.match(r"\| `(fluo_\w+)`\s*\| \w+\s*\| ([^|]+)\|", line)
        if m:
            table[m.group(1)] = "llvm" in m.group(2)
    assert set(table) == set(fluo.PLUGIN_KINDS), f"README table {sorted(table)} vs plugins {sorted(fluo.PLUGIN_KINDS)}"
    assert {name for name, llvm in table.items() if llvm} == set(JIT_PLUGINS)
    jobs = [{"variant": v, "load": {"type": name}} for name in table for v in ("llvm_ad_rgb", "llvm_ad_spectral")]
    for job, res in zip(jobs, run_llvm(jobs)):
        name = job["load"]["type"]
        unavailable = "error" in res and "not available in variant" in res["error"]
        assert unavailable != table[name], f"{name} in {job['variant']}: README says llvm={table[name]}, got {res}"


def rejected_update(xml: str, key: str, change: str) -> dict:
    """In a fresh llvm_ad_spectral process: render `xml`, set parameter `key` to what the
    Python statement `change` leaves in `value` (it starts as the current value), update,
    render again. Returns the update's error message (None if accepted) and both means."""
    script = f'''
import json, mitsuba as mi, numpy as np
mi.set_variant("llvm_ad_spectral")
import fluo
scene = mi.load_string({xml!r})
p = mi.traverse(scene)
before = np.array(mi.render(scene, spp=16, seed=1)).mean()
value = p[{key!r}]
{change}
p[{key!r}] = value
try:
    p.update()
    err = None
except Exception as e:
    err = str(e)
after = np.array(mi.render(scene, spp=16, seed=1)).mean()
print("RESULT " + json.dumps({{"error": err, "before": float(before), "after": float(after)}}))
'''
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, cwd=REPO)
    lines = [ln[ln.index("RESULT ") + 7:] for ln in proc.stdout.splitlines() if "RESULT " in ln]
    assert lines, proc.stderr[-3000:]
    return json.loads(lines[-1])


def test12_gmm_gradients_and_updates():
    """fluo_gmm's mixture weights (renormalised) and means are differentiable in
    llvm_ad_spectral and llvm_ad_rgb: d(mean image)/d(parameter) by AD equals central finite differences,
    each averaged over three seeds (moving a weight or a mean also moves where λi is
    sampled, so the two difference renders share fewer random numbers: single seeds scatter
    by ~10 % for the weights; measured means agree within 5 %), within 12 %; an update Rust
    rejects (a negative weight) raises an error naming it and the material renders as
    before."""
    gmm = MATRICES / "jung_orange.gmm.json"
    xml = closeup(f'<bsdf type="fluo_gmm" id="gmm"><string name="filename" value="{gmm}"/></bsdf>', D65, res=16)
    steps = {"gmm.weights": 0.004, "gmm.means_excitation": 3.0, "gmm.means_emission": 3.0}
    runs = run_llvm([{"variant": "llvm_ad_spectral", "xml": xml, "spp": 4096, "seed": s, "gradients": steps}
                     for s in (3, 4, 5)])
    assert all("error" not in r for r in runs), runs
    for key in steps:
        ad, fd = (float(np.mean([r["gradients"][key][i] for r in runs])) for i in (0, 1))
        print(key, "ad", ad, "fd", fd)
        assert abs(fd) > 1e-5, f"{key}: the image does not depend on it, the check would be empty"
        assert abs(ad - fd) <= 0.12 * abs(fd), f"{key}: AD {ad} vs finite differences {fd}"
    # llvm_ad_rgb (default basis, auto): the mixture reaches the image through the reduced
    # matrix; its derivatives (each component's operator, central differences along the
    # means) against central differences of renders with the same seed (no wavelength is
    # sampled in RGB: the differences are smooth)
    rgb = run_llvm([{"variant": "llvm_ad_rgb", "xml": xml, "spp": 256, "seed": 3, "gradients": steps}])[0]
    assert "error" not in rgb, rgb
    for key in steps:
        ad, fd = rgb["gradients"][key]
        print("llvm_ad_rgb", key, "ad", ad, "fd", fd)
        assert abs(fd) > 1e-5, f"{key}: the image does not depend on it, the check would be empty"
        assert abs(ad - fd) <= 0.10 * abs(fd), f"llvm_ad_rgb {key}: AD {ad} vs finite differences {fd}"
    out = rejected_update(xml, "gmm.weights", "w = np.array(value); w[0] = -0.5; value = mi.Float(w)")
    assert out["error"] is not None and "weights" in out["error"], out
    assert out["after"] == pytest.approx(out["before"], rel=1e-6)


def test12b_matrix_reradiation_gradients_and_updates():
    """fluo_matrix's reradiation P (its nodes, ``reradiation`` in ``mi.traverse``) is
    differentiable in both AD variants: spectral through the shift's value (the sampling
    and its mass detached), RGB through the reduced operator's derivative (linear in P:
    Rust's Jacobian of the reduction, ``cargo test`` checks it against the reduction). AD
    equals central differences along P itself (P·(1 + t): every node scaled, zeros stay
    zero) within 10 %; an update Rust refuses (a negative entry) names it and the material
    renders as before."""
    m = MATRICES / "jung_orange.csv"
    xml = closeup(f'<bsdf type="fluo_matrix" id="mat"><string name="filename" value="{m}"/></bsdf>', D65, res=16)
    steps = {"mat.reradiation": 0.05}
    runs = run_llvm([{"variant": v, "xml": xml, "spp": spp, "seed": 3, "gradients": steps, "relative": True}
                     for v, spp in (("llvm_ad_spectral", 4096), ("llvm_ad_rgb", 256))])
    for v, r in zip(("llvm_ad_spectral", "llvm_ad_rgb"), runs):
        assert "error" not in r, r
        ad, fd = r["gradients"]["mat.reradiation"]
        print(v, "ad", ad, "fd", fd)
        assert abs(fd) > 1e-3, f"{v}: the image does not depend on P, the check would be empty"
        assert abs(ad - fd) <= 0.10 * abs(fd), f"{v}: AD {ad} vs finite differences {fd}"
    out = rejected_update(xml, "mat.reradiation", "q = np.array(value); q[5] = -1.0; value = mi.Float(q)")
    assert out["error"] is not None and "reradiation" in out["error"], out
    assert out["after"] == pytest.approx(out["before"], rel=1e-6)


def test12c_matrix_reradiation_gradients_with_several_files(tmp_path):
    """Two files selected by an ``index`` bitmap (the second on a quarter of the texels):
    ``reradiation`` holds both matrices' nodes in file order and is differentiable per file in
    both AD variants. AD equals central differences along all of P (P·(1 + t)) and along the
    second file's nodes alone within 10 % (lanes reading the other file's change would see
    it on three quarters of the sphere instead of one); an update of the wrong size, or one
    Rust refuses in the second file, names it and leaves both."""
    files = [MATRICES / "jung_orange.csv", MATRICES / "jung_yellow.csv"]
    mi.set_variant("scalar_spectral")
    n0, n1 = (len(np.array(mi.traverse(mi.load_dict({"type": "fluo_matrix", "filename": str(f)}))["reradiation"]))
              for f in files)
    index = tmp_path / "index.exr"
    mi.Bitmap(np.array([[0, 0], [0, 1]], dtype=np.float32)).write(str(index))
    bsdf = (f'<bsdf type="fluo_matrix" id="mat"><string name="filename0" value="{files[0]}"/>'
            f'<string name="filename1" value="{files[1]}"/>' + bitmap_xml("index", index, 6, "nearest") + '</bsdf>')
    xml = closeup(bsdf, D65, res=16)
    cases = [(v, spp, span) for v, spp in (("llvm_ad_spectral", 4096), ("llvm_ad_rgb", 256))
             for span in ([0, n0 + n1], [n0, n0 + n1])]
    runs = run_llvm([{"variant": v, "xml": xml, "spp": spp, "seed": 3, "gradients": {"mat.reradiation": 0.05},
                      "relative": True, "span": span} for v, spp, span in cases])
    for (v, _, span), r in zip(cases, runs):
        assert "error" not in r, r
        ad, fd = r["gradients"]["mat.reradiation"]
        print(v, span, "ad", ad, "fd", fd)
        assert abs(fd) > 1e-3, f"{v} {span}: the image does not depend on these nodes, the check would be empty"
        assert abs(ad - fd) <= 0.10 * abs(fd), f"{v} {span}: AD {ad} vs finite differences {fd}"
    out = rejected_update(xml, "mat.reradiation", f"q = np.array(value); q[{n0 + 5}] = -1.0; value = mi.Float(q)")
    assert out["error"] is not None and "reradiation" in out["error"], out
    assert out["after"] == pytest.approx(out["before"], rel=1e-6)
    out = rejected_update(xml, "mat.reradiation", "value = mi.Float(np.array(value)[:-1])")
    assert out["error"] is not None and f"must keep its {n0 + n1} entries" in out["error"], out
    assert out["after"] == pytest.approx(out["before"], rel=1e-6)


def test12d_gmm_mixture_gradients_with_several_files(tmp_path):
    """Issue 35: two fits of the orange dye (8 and 4 components) selected by an ``index``
    bitmap (the second on a quarter of the texels): ``weights`` and the means hold both
    mixtures, [file][component] with the second padded to 8, and are differentiable per file
    in both AD variants. AD equals central differences along entries of the second file alone
    (a derivative applied to the other file's lanes would show on three quarters of the
    sphere instead of one; spectral: three seeds as test12, within 12 %; measured 0.00750
    against 0.00731 for its first weight, the differences scattering by ~10 % per seed at
    a 0.004 step) and, in RGB, of each file (its own derivative tables, within 10 %;
    measured within 1.5 %). An
    update setting a padded entry, or one Rust refuses in the second file, names it and
    leaves both; the padding has no gradient."""
    mi.set_variant("scalar_rgb")
    fit = tmp_path / "orange4.gmm.json"
    fluo.run_tool(["fit-gmm", str(MATRICES / "jung_orange.csv"), "--components", "4", "-o", str(fit)])
    index = tmp_path / "index.exr"
    mi.Bitmap(np.array([[0, 0], [0, 1]], dtype=np.float32)).write(str(index))
    bsdf = (f'<bsdf type="fluo_gmm" id="gmm"><string name="filename0" value="{MATRICES / "jung_orange.gmm.json"}"/>'
            f'<string name="filename1" value="{fit}"/>' + bitmap_xml("index", index, 6, "nearest") + '</bsdf>')
    xml = closeup(bsdf, D65, res=16)
    weights, means = {"gmm.weights": 0.01}, {"gmm.means_excitation": 3.0, "gmm.means_emission": 3.0}
    # (a file's weights moved together change nothing once renormalised: one weight each)
    cases = [("llvm_ad_spectral", weights, [8, 9]), ("llvm_ad_spectral", means, [8, 12]),
             ("llvm_ad_rgb", weights, [0, 1]), ("llvm_ad_rgb", weights, [8, 9]),
             ("llvm_ad_rgb", means, [0, 8]), ("llvm_ad_rgb", means, [8, 12])]
    jobs = [{"variant": v, "xml": xml, "spp": 4096 if v == "llvm_ad_spectral" else 256, "seed": seed,
             "gradients": steps, "span": span}
            for v, steps, span in cases for seed in ((3, 4, 5) if v == "llvm_ad_spectral" else (3,))]
    runs = run_llvm(jobs)
    assert all("error" not in r for r in runs), runs
    for v, steps, span in cases:
        mine = [r for job, r in zip(jobs, runs) if job["variant"] == v and job["span"] == span
                and job["gradients"] == steps]
        for key in steps:
            ad, fd = (float(np.mean([r["gradients"][key][i] for r in mine])) for i in (0, 1))
            print(v, span, key, "ad", ad, "fd", fd)
            assert abs(fd) > 1e-5, f"{v} {span} {key}: the image does not depend on it, the check would be empty"
            tol = 0.12 if v == "llvm_ad_spectral" else 0.10
            assert abs(ad - fd) <= tol * abs(fd), f"{v} {span} {key}: AD {ad} vs finite differences {fd}"
    # the second file's padding (entries 12-15) has no gradient, so an optimiser's step keeps
    # it at 0, which an update requires
    pads = run_llvm([{"variant": v, "xml": xml, "spp": 64, "seed": 3, "gradients": {"gmm.weights": 0.01},
                      "span": [12, 16], "ad_only": True} for v in ("llvm_ad_spectral", "llvm_ad_rgb")])
    for r in pads:
        assert "error" not in r and r["gradients"]["gmm.weights"][0] == 0.0, r
    out = rejected_update(xml, "gmm.weights", "w = np.array(value); w[13] = 0.2; value = mi.Float(w)")
    assert out["error"] is not None and "entry 13 pads" in out["error"], out
    assert out["after"] == pytest.approx(out["before"], rel=1e-6)
    out = rejected_update(xml, "gmm.weights", "w = np.array(value); w[9] = -0.5; value = mi.Float(w)")
    assert out["error"] is not None and "weight" in out["error"], out
    assert out["after"] == pytest.approx(out["before"], rel=1e-6)


#: fluo_qd coatings: on aluminium (GGX, orange dots), on glass (Beckmann, blue-green dots,
#: mostly reradiation: the substrate reflects 4 %), and on gold with a thin coating.
QD_MATERIALS = {
    "al": '<string name="material" value="Al"/><string name="distribution" value="ggx"/>'
          '<float name="alpha" value="0.15"/><float name="radius" value="3.3"/><float name="density" value="0.8"/>',
    "glass": '<float name="int_ior" value="1.5"/><float name="alpha" value="0.3"/><float name="radius" value="1.8"/>'
             '<float name="quantum_yield" value="0.9"/>',
    "au": '<string name="material" value="Au"/><float name="alpha" value="0.05"/><float name="radius" value="2.2"/>'
          '<float name="density" value="0.2"/>',
}


def test13_qd_equals_scalar_within_noise():
    """fluo_qd (tables of A_tot, R_spe and pass interpolated per lane, the microfacet lobe per
    direction, exact excitation sampling from the nearest A_tot row; in RGB the reduced
    matrices at the microfacet cosines) renders in llvm what the scalar variants render:
    close-ups of three coatings under D65 and (spectral) a 300-380 nm lamp, the two demo
    scenes and the two bench scenes with quantum dots (the blacklight room also holds
    fluo_jung: Lambertian and microfacet lobes in one kernel)."""
    cases = []
    for name, bsdf in QD_MATERIALS.items():
        for light, label, v, basis in lit_variants():
            xml = closeup(f'<bsdf type="fluo_qd" id="qd">{bsdf}</bsdf>', light, basis)
            cases.append((f"fluo_qd {name} {label}", v, {"variant": v, "xml": xml, "spp": 256}))
    for scene in ("fluo_qd_spheres.xml", "fluo_qd_spheres_uv.xml", "bench/qd_box.xml", "bench/blacklight_box.xml"):
        for v in ("llvm_ad_spectral", "llvm_ad_rgb"):
            params = {"basis": "x7"} if scene.startswith("bench/") else {}
            cases.append((scene, v, scene_job(SCENES / scene, v, spp=128, **params)))
    assert_means_equal(cases)


def glossy_points(seed: int, n: int) -> list:
    """n random (wi, wo, 4 wavelengths) points above the surface for a glossy lobe, every
    other one near the specular direction (where the lobe is large)."""
    rng = np.random.default_rng(seed)
    points = []
    for _ in range(n):
        wi, wo = rng.normal(size=3), rng.normal(size=3)
        wi[2], wo[2] = abs(wi[2]) + 0.05, abs(wo[2]) + 0.05
        if len(points) % 2:
            wo = np.array([-wi[0], -wi[1], wi[2]]) + 0.1 * rng.normal(size=3)
            wo[2] = abs(wo[2]) + 0.05
        points.append([list(wi / np.linalg.norm(wi)), list(wo / np.linalg.norm(wo)),
                       list(rng.uniform(360.0, 830.0, size=4))])
    return points


def test14_qd_bsdf_values_equal_the_rust_reference():
    """fluo_qd's elastic lobe per lane (Mitsuba's microfacet distribution and the substrate's
    Fresnel factor under the coating, R_spe and pass interpolated from Rust's tables) equals
    the scalar variants' (which ask Rust per call) at random directions and wavelengths.
    The tables hold R_spe and pass within 1.3e-4 (Rust test jit_tables_interpolate_the_model),
    which is 0.3 % of a glass substrate's 4 % reflectance: hence rtol 5e-3."""
    points = glossy_points(seed=5, n=60)
    bsdfs = [{"type": "fluo_qd", "material": "Al", "distribution": "ggx", "alpha": 0.15, "radius": 3.3,
              "density": 0.8},
             {"type": "fluo_qd", "int_ior": 1.5, "alpha": 0.3, "radius": 1.8},
             {"type": "fluo_qd", "material": "Au", "alpha": 0.05, "density": 0.0}]
    assert_bsdf_values_equal(bsdfs, points, rtol=5e-3, atol=1e-5, peak=1e-2)


def test15_qd_yield_gradient_and_updates(tmp_path):
    """fluo_qd's quantum_yield is differentiable in llvm: under a lamp below the camera's
    360 nm the image is reradiation alone, linear in Q, so d(mean)/dQ = mean/Q, which AD and
    central differences must give. The derivative is not mean/Q sample by sample (the
    gradient render's estimate differs from the plain render's of the same seed: measured
    for fluo_jung's Q too), so the match is within noise: 3 % at 4096 spp (measured 0.3 %).
    In llvm_ad_rgb under D65 AD equals central differences. An update Rust rejects (Q = 1.5)
    raises an error naming it and the material renders as before."""
    lamp = tmp_path / "uv_300_350.csv"
    lamp.write_text("nm,value\n299,0\n300,1\n350,1\n351,0\n")
    light = f'<string name="filename" value="{lamp}"/><boolean name="normalize" value="false"/>'
    glass = f'<bsdf type="fluo_qd" id="qd">{QD_MATERIALS["glass"]}</bsdf>'
    uv = closeup(glass, light, res=16)
    rgb = closeup(glass, D65, '<string name="basis" value="x7"/>', res=16)
    steps = {"qd.quantum_yield": 0.05}
    jobs = [{"variant": "llvm_ad_spectral", "xml": uv, "spp": 4096, "seed": 3, "gradients": steps},
            {"variant": "llvm_ad_spectral", "xml": uv, "spp": 4096, "seed": 3},
            {"variant": "llvm_ad_rgb", "xml": rgb, "spp": 1024, "seed": 3, "gradients": steps}]
    (grad_uv, mean_uv, grad_rgb) = run_llvm(jobs)
    assert all("error" not in r for r in (grad_uv, mean_uv, grad_rgb)), (grad_uv, mean_uv, grad_rgb)
    ad, fd = grad_uv["gradients"]["qd.quantum_yield"]
    exact = float(np.mean(mean_uv["mean"])) / 0.9
    print("uv: ad", ad, "fd", fd, "mean/Q", exact)
    assert abs(exact) > 1e-3
    assert ad == pytest.approx(exact, rel=0.03) and fd == pytest.approx(exact, rel=0.03)
    ad, fd = grad_rgb["gradients"]["qd.quantum_yield"]
    print("rgb: ad", ad, "fd", fd)
    assert abs(fd) > 1e-4 and ad == pytest.approx(fd, rel=0.02)
    out = rejected_update(uv, "qd.quantum_yield", "value = 1.5")
    assert out["error"] is not None and "quantum_yield" in out["error"], out
    assert out["after"] == pytest.approx(out["before"], rel=1e-6)


# A dielectric sphere of a UV-absorbing dye (fluo_dye_medium, blue emission) with host
# scattering, on a fluo_jung floor, under D65 from 300 nm: fluorescent media and surfaces
# in one kernel, refraction into the medium.
DYE_SPHERE = """<scene version="3.0.0">
    <default name="spp" value="64"/>
    <integrator type="fluo_volpath"><integer name="max_depth" value="12"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="0, 1.5, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="20"/><integer name="height" value="20"/></film>
    </sensor>
    <emitter type="constant">
        <spectrum type="fluo_illuminant" name="radiance"><string name="illuminant" value="D65"/></spectrum>
    </emitter>
    <medium type="fluo_dye_medium" id="dye">
        <float name="emission_peak" value="430"/>
        <float name="stokes_shift" value="50"/>
        <float name="sigma_a" value="100"/>
        <float name="scale" value="0.01"/>
        <float name="sigma_s" value="10"/>
    </medium>
    <shape type="sphere">
        <bsdf type="dielectric"/>
        <ref name="interior" id="dye"/>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/><translate y="-1"/></transform>
        <bsdf type="fluo_jung"/>
    </shape>
</scene>"""


def test16_media_equal_scalar_within_noise():
    """fluo_qd_medium and fluo_dye_medium in llvm (μa and the emission interpolated from
    Rust's tables, exact excitation sampling by the running integral of μa) with fluo_volpath
    in llvm_ad_spectral (spectral tracking, the fluorescent source's collision floor, shifts
    at real collisions; fluorescent BSDFs at surfaces) render what scalar_spectral renders,
    and in llvm_ad_rgb (the reduced transport: the media's K×K operators in band tracking, at
    real collisions and along shadow rays; fluorescent BSDFs' reduced matrices at surfaces)
    what scalar_rgb renders: both cuvette demos, the media bench scene (every basis in RGB)
    and a dye sphere on a fluo_jung floor, in RGB also on a fluo_qd floor (a
    direction-dependent lobe through media). Under Mitsuba's own volpath the media absorb
    without re-emitting (their Q = 0 limit), as in the scalar variants, in both llvm variants."""
    cases = [(scene, v, scene_job(SCENES / scene, v, spp=256))
             for scene in ("fluo_qd_cuvettes_uv.xml", "fluo_qd_cuvettes_d65.xml", "bench/qd_cuvette.xml")
             for v in ("llvm_ad_spectral", "llvm_ad_rgb")]
    for basis in ("rgb", "xyzu"):
        cases.append((f"bench/qd_cuvette.xml {basis}", "llvm_ad_rgb",
                      scene_job(SCENES / "bench" / "qd_cuvette.xml", "llvm_ad_rgb", spp=256, basis=basis)))
    for v in ("llvm_ad_spectral", "llvm_ad_rgb"):
        cases.append(("dye sphere", v, {"variant": v, "xml": DYE_SPHERE, "spp": 256}))
    qd_floor = DYE_SPHERE.replace('<bsdf type="fluo_jung"/>', '<bsdf type="fluo_qd"/>')
    assert qd_floor != DYE_SPHERE
    cases.append(("dye sphere on fluo_qd", "llvm_ad_rgb", {"variant": "llvm_ad_rgb", "xml": qd_floor, "spp": 256}))
    # a native medium on a fluorescent floor: the matrix throughput through volpath's own
    # tracking (an extinction per channel, distances sampled by a random channel, as volpath)
    native = re.sub(r'<medium type="fluo_dye_medium" id="dye">.*?</medium>',
                    '<medium type="homogeneous" id="dye"><rgb name="albedo" value="0.9, 0.5, 0.2"/>'
                    '<rgb name="sigma_t" value="0.1, 0.6, 1"/><float name="scale" value="3"/></medium>', DYE_SPHERE, flags=re.S)
    assert "fluo_dye_medium" not in native
    cases.append(("native medium on fluo_jung", "llvm_ad_rgb", {"variant": "llvm_ad_rgb", "xml": native, "spp": 256}))
    for v in ("llvm_ad_spectral", "llvm_ad_rgb"):
        job = scene_job(SCENES / "fluo_qd_cuvettes_d65.xml", v, spp=64)
        cases.append(("cuvettes under volpath", v, {**job, "integrator": "volpath", "max_depth": 12}))
    assert_means_equal(cases)


def test17_volpath_variants_and_errors():
    """Without fluorescence llvm fluo_volpath is Mitsuba's volpath (the same image, seed for
    seed: it hands the render over), in both variants; an invalid basis is refused with the
    scalar variant's error; a medium's invalid parameter raises Rust's error, naming it, in
    llvm as in scalar."""
    no_glow = (SCENES / "bench" / "qd_cuvette.xml").read_text().replace(
        '<float name="quantum_yield" value="0.8"/>', '<float name="quantum_yield" value="0"/>')
    assert no_glow != (SCENES / "bench" / "qd_cuvette.xml").read_text()
    no_glow = no_glow.replace('<include filename="', f'<include filename="{SCENES / "bench"}/')
    jobs = []
    for v in ("llvm_ad_rgb", "llvm_ad_spectral"):
        base = {"variant": v, "xml": no_glow, "params": {"res": "16"}, "spp": 16, "seed": 5}
        jobs += [{**base, "integrator": "fluo_volpath", "max_depth": 8}, {**base, "integrator": "volpath", "max_depth": 8}]
    jobs.append(scene_job(SCENES / "bench" / "qd_cuvette.xml", "llvm_ad_rgb", spp=4, basis="x9"))
    for bad in ({"type": "fluo_qd_medium", "quantum_yield": 1.5}, {"type": "fluo_dye_medium", "sigma_a": -1.0},
                {"type": "fluo_qd_medium", "scale": 0.0}):
        jobs.append({"variant": "llvm_ad_spectral", "load": bad})
    res = run_llvm(jobs)
    for a, b in (res[0:2], res[2:4]):
        assert "error" not in a and "error" not in b, (a, b)
        assert np.mean(a["mean"]) > 1e-3 and a["mean"] == b["mean"], (a, b)
    err = res[4].get("error", "")
    assert "fluo_volpath" in err and "x9" in err, res[4]
    for name, r in zip(("quantum_yield", "sigma_a", "scale"), res[5:]):
        assert name in r.get("error", ""), r


# A plane seen from above (a textured material: {bsdf}) under a constant light ({light}: a
# fluo_illuminant's parameters), fluo_path with optional {basis}.
TEXTURED_PLANE = """<scene version="3.0.0">
    <integrator type="fluo_path"><integer name="max_depth" value="4"/>{basis}</integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="{origin}, 3, 0.01" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"/>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>
    <emitter type="constant"><spectrum type="fluo_illuminant" name="radiance">{light}</spectrum></emitter>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/></transform>
{bsdf}    </shape>
</scene>"""

# A fluo_jung plane whose Stokes shift and yield are checkerboards (four dye shapes' worth
# of texels: 2 shifts, 2 yields) under D65 from 300 nm.
CHECKER_JUNG = TEXTURED_PLANE.format(origin=0, light=D65, basis="", bsdf="""        <bsdf type="fluo_jung">
            <float name="emission_peak" value="560"/>
            <float name="concentration" value="0.8"/>
            <texture type="checkerboard" name="stokes_shift">
                <float name="color0" value="40"/><float name="color1" value="90"/>
                <transform name="to_uv"><scale value="3"/></transform>
            </texture>
            <texture type="checkerboard" name="quantum_yield">
                <float name="color0" value="0.3"/><float name="color1" value="1.0"/>
                <transform name="to_uv"><scale value="2"/></transform>
            </texture>
            <string name="coefficients" value="0.0, 0.0, 1.0"/>
        </bsdf>
""")


def test18_textured_jung_in_llvm(tmp_path):
    """fluo_jung's textured numeric parameters in both llvm variants (per lane: λe and s the
    nearest of the texture's validated levels, c and Q the texture's value; RGB: each dye
    shape's reduced matrix, gathered per lane): checkerboard shift and yield render what the
    scalar variants render (the label demo is in test01's CASES), and a bad texel raises the
    scalar variants' error naming the parameter, the value and its texel."""
    cases = [("checkerboard shift and yield", v, {"variant": v, "xml": CHECKER_JUNG, "spp": 256})
             for v in ("llvm_ad_spectral", "llvm_ad_rgb")]
    assert_means_equal(cases)
    mi.set_variant("scalar_rgb")
    bad = tmp_path / "bad.exr"
    mi.Bitmap(np.array([[0.1, 0.2, 0.3], [0.4, 1.5, 0.6]], dtype=np.float32)).write(str(bad))
    tex = {"type": "bitmap", "filename": str(bad), "raw": True, "filter_type": "nearest"}
    jobs = [{"variant": v, "load": {"type": "fluo_jung", "concentration": tex}}
            for v in ("llvm_ad_spectral", "llvm_ad_rgb")]
    for res in run_llvm(jobs):
        err = res.get("error", "")
        assert 'invalid parameter "concentration" = 1.5 at texel (x = 1, y = 1)' in err and "[0, 1]" in err, res


INDEX_TEXTURE = """<texture type="bitmap" name="index"><string name="filename" value="{file}"/>
    <boolean name="raw" value="true"/><string name="filter_type" value="nearest"/>
    <transform name="to_uv"><scale value="4"/></transform></texture>"""


def test19_material_index_in_llvm(tmp_path):
    """fluo_matrix and fluo_gmm with several files selected per hit by a material-index bitmap
    in both llvm variants (per lane: the file's grids, tables or padded components; RGB: each
    file's reduced matrix, gathered per lane) render what the scalar variants render: three
    matrices on different grids (10 nm, an irregular one: binary search over the longest grid,
    20 nm to 700 nm) and three fits of 8, 4 and 8 components; a texel out of range raises the
    scalar variants' error naming it, and mi.traverse lists the index texture and the
    mixtures' arrays."""
    mi.set_variant("scalar_rgb")
    index = tmp_path / "index.exr"
    mi.Bitmap(np.array([[0, 1, 2], [2, 0, 1]], dtype=np.float32)).write(str(index))
    bad = tmp_path / "bad.exr"
    mi.Bitmap(np.array([[0, 1], [3, 2]], dtype=np.float32)).write(str(bad))
    fit = tmp_path / "brightener.gmm.json"
    fluo.run_tool(["fit-gmm", str(MATRICES / "jung_brightener.csv"), "--components", "4", "-o", str(fit)])
    files = {
        "fluo_matrix": [MATRICES / "jung_orange.csv", irregular_matrix(tmp_path / "irregular.csv"),
                        resampled_matrix(tmp_path / "coarse.csv", "jung_brightener.csv",
                                         lambda w: w <= 700 and int(w) % 20 == 0)],
        "fluo_gmm": [MATRICES / "jung_orange.gmm.json", fit, MATRICES / "jung_orange.gmm.json"],
    }

    def bsdf(plugin: str, texture: Path) -> str:
        names = "".join(f'<string name="filename{i}" value="{f}"/>' for i, f in enumerate(files[plugin]))
        return f'<bsdf type="{plugin}" id="m">{names}{INDEX_TEXTURE.format(file=texture)}</bsdf>'

    cases = []
    for plugin in files:
        for light, label, v, basis in lit_variants():
            cases.append((f"{plugin} index {label}", v,
                          {"variant": v, "xml": closeup(bsdf(plugin, index), light, basis), "spp": 256}))
    assert_means_equal(cases)
    jobs = [{"variant": v, "xml": closeup(bsdf(plugin, bad), D65), "spp": 1}
            for plugin in files for v in ("llvm_ad_spectral", "llvm_ad_rgb")]
    names = {f"filename{i}": str(f) for i, f in enumerate(files["fluo_gmm"])}
    tex = {"type": "bitmap", "filename": str(index), "raw": True, "filter_type": "nearest"}
    jobs.append({"variant": "llvm_ad_spectral", "traverse": {"type": "fluo_gmm", **names, "index": tex}})
    *errors, keys = run_llvm(jobs)
    for res in errors:
        err = res.get("error", "")
        assert '"index" = 3 at texel (x = 0, y = 1)' in err and "whole numbers 0 to 2" in err, res
    # (the mixtures' arrays too, [file][component]: test12d)
    assert any(k.endswith("index.data") for k in keys["keys"]) and "weights" in keys["keys"], keys


def textured_qd_plane(qd: str, light: str, basis: str) -> str:
    """A fluo_qd plane (aluminium substrate) whose parameters are textures (`qd`)."""
    return TEXTURED_PLANE.format(origin=0.4, light=light, basis=basis,
                                 bsdf=f'        <bsdf type="fluo_qd"><string name="material" value="Al"/>{qd}</bsdf>\n')


def checker_xml(name: str, a: float, b: float, scale: float) -> str:
    return (f'<texture type="checkerboard" name="{name}"><float name="color0" value="{a}"/><float name="color1" '
            f'value="{b}"/><transform name="to_uv"><scale value="{scale}"/></transform></texture>')


def bitmap_xml(name: str, file: Path, scale: float, filter_type: str = "bilinear") -> str:
    return (f'<texture type="bitmap" name="{name}"><string name="filename" value="{file}"/><boolean name="raw" '
            f'value="true"/><string name="filter_type" value="{filter_type}"/><transform name="to_uv"><scale '
            f'value="{scale}"/></transform></texture>')


def test20_textured_qd_in_llvm(tmp_path):
    """fluo_qd's textured radius, density, quantum_yield and alpha in both llvm variants (per
    lane: the hit's (radius, density) models at its nearest roughness level, bilinear weights,
    each with its own λ grid and tables; the reradiation of one picked per vertex with its
    weight as probability, where scalar_rgb sums them) render what the scalar variants
    render: radius and density checkerboards (four coatings), a bilinear density bitmap (hits
    between levels mix models) with yield and alpha checkerboards, a bilinear radius bitmap
    (models on different λ grids mixed), under D65 and a UV lamp;
    the elastic lobe's values at hits between levels (of density; of radius: two λ grids)
    equal the scalar ones; a bad texel
    raises the scalar variants' error naming it."""
    mi.set_variant("scalar_rgb")
    density = tmp_path / "density.exr"
    mi.Bitmap(np.array([[0.2, 0.8], [0.5, 0.3]], dtype=np.float32)).write(str(density))
    bad = tmp_path / "bad.exr"
    mi.Bitmap(np.array([[2.0, 2.5], [7.0, 2.0]], dtype=np.float32)).write(str(bad))
    radii = tmp_path / "radii.exr"
    mi.Bitmap(np.array([[1.8, 3.4], [2.6, 1.8]], dtype=np.float32)).write(str(radii))
    materials = {
        "radius, density": checker_xml("radius", 2.2, 3.0, 3) + checker_xml("density", 0.8, 0.4, 2),
        "density bitmap, yield, alpha": ('<float name="radius" value="2.6"/>' + bitmap_xml("density", density, 3)
                                         + checker_xml("quantum_yield", 0.3, 1.0, 2)
                                         + checker_xml("alpha", 0.1, 0.3, 5)),
        # hits between radii: models on different λ grids mixed (and picked)
        "radius bitmap": bitmap_xml("radius", radii, 3) + '<float name="density" value="0.8"/>',
    }
    cases = []
    for name, qd in materials.items():
        for light, label, v, basis in lit_variants():
            if light is UV_FLAT and name == "radius bitmap":
                # the glow of three radii under the lamp is too heavy-tailed for 4 seeds (12
                # llvm and 8 scalar seeds agree: 49600 ± 530 and 49580 ± 200 in red)
                continue
            cases.append((f"textured fluo_qd {name} {label}", v,
                          {"variant": v, "xml": textured_qd_plane(qd, light, basis), "spp": 256}))
    assert_means_equal(cases)
    # eval at uv = 0.5: the bitmap's four texels averaged (density 0.45, between levels 0.3 and 0.5)
    points = glossy_points(seed=9, n=30)
    radius = tmp_path / "radius.exr"
    mi.Bitmap(np.array([[2.0, 3.0], [2.5, 2.0]], dtype=np.float32)).write(str(radius))
    tex = {"type": "bitmap", "filename": str(density), "raw": True, "filter_type": "bilinear"}
    # (radius 2.375 at uv = 0.5: models on two radii's λ grids mixed)
    bsdfs = [{"type": "fluo_qd", "material": "Al", "alpha": 0.2, "radius": 3.0, "density": tex},
             {"type": "fluo_qd", "int_ior": 1.5, "alpha": 0.3, "radius": tex | {"filename": str(radius)},
              "density": 0.6}]
    assert_bsdf_values_equal(bsdfs, points, rtol=5e-3, atol=1e-5, peak=1e-2)
    jobs = [{"variant": v, "xml": textured_qd_plane(bitmap_xml("radius", bad, 1, "nearest"), D65, ""), "spp": 1}
            for v in ("llvm_ad_spectral", "llvm_ad_rgb")]
    # a texel made invalid through mi.traverse: the error names it, and the material keeps its
    # baked models (it renders, the texture's values clamped to them)
    xml = textured_qd_plane(bitmap_xml("radius", radii, 3), D65, "").replace('<shape type="rectangle">',
                                                                          '<shape type="rectangle" id="plane">')
    out = rejected_update(xml, "plane.bsdf.radius.data",
                          "value = type(value)(np.full(value.shape, 7.0, dtype=np.float32))")
    assert out["error"] is not None and '"radius" = 7' in out["error"], out
    assert np.isfinite(out["after"]) and out["after"] > 0.1 * out["before"], out
    # a texture that does not vary is read once as its float
    constant = {"type": "fluo_qd", "radius": {"type": "uniform", "value": 2.2}}
    loads = run_llvm([{"variant": v, "load": constant} for v in ("llvm_ad_spectral", "llvm_ad_rgb")])
    assert all(r.get("loaded") for r in loads), loads
    for v in ("scalar_spectral", "scalar_rgb"):
        mi.set_variant(v)
        assert "baked models" not in str(mi.load_dict(constant))
    for res in run_llvm(jobs):
        err = res.get("error", "")
        assert 'invalid parameter "radius" = 7 at texel (x = 0, y = 1)' in err and "[1, 5]" in err, res


def test21_qd_radius_and_density_gradients(tmp_path):
    """fluo_qd's radius and density are differentiable in both AD variants (a uniform
    material: the tables' derivatives, central differences of Rust's tables at ± 1e-3 on the
    model's λ grid, carried per lane with sampling detached): AD equals central differences
    of the image mean on the aluminium coating under D65 (the elastic lobe and the glow) and
    the gold one under a 300-350 nm lamp (the glow alone); in llvm_ad_rgb (the aluminium
    coating) through the reduced operator's derivative at its cosine nodes and the RGB
    tables' tangents; a textured material lists them as not differentiable.
    alpha (the lobe, evaluated per lane) is differentiable in both AD variants: AD against
    central differences on the aluminium coating under D65."""
    lamp = tmp_path / "uv_300_350.csv"
    lamp.write_text("nm,value\n299,0\n300,1\n350,1\n351,0\n")
    uv_light = f'<string name="filename" value="{lamp}"/><boolean name="normalize" value="false"/>'
    steps = {"qd.radius": 0.05, "qd.density": 0.05}
    scenes = {"al d65": closeup(f'<bsdf type="fluo_qd" id="qd">{QD_MATERIALS["al"]}</bsdf>', D65, res=16),
              "au uv": closeup(f'<bsdf type="fluo_qd" id="qd">{QD_MATERIALS["au"]}</bsdf>', uv_light, res=16)}
    # The central differences re-bake the tables, so their renders sample other paths: under
    # the lamp d/dradius from them scatters ~4 % at 8192 spp (measured AD/FD 0.02205/0.02161,
    # 0.02166/0.02091 over two seeds), under D65 0.1 %.
    tolerance = {"al d65": 0.02, "au uv": 0.08, "textured density, Q": 0.05}
    jobs = [{"variant": "llvm_ad_spectral", "xml": xml, "spp": 2048 if name == "al d65" else 8192, "seed": 3,
             "gradients": steps} for name, xml in scenes.items()]
    # Q's gradient where another parameter is a texture (the hit's Q is then the float's)
    textured_xml = closeup('<bsdf type="fluo_qd" id="qd"><string name="material" value="Au"/><float name="radius" '
                           'value="2.2"/>' + checker_xml("density", 0.2, 0.6, 4) + '</bsdf>', uv_light, res=16)
    jobs.append({"variant": "llvm_ad_spectral", "xml": textured_xml, "spp": 2048, "seed": 3,
                 "gradients": {"qd.quantum_yield": 0.05}})
    # alpha (both AD variants, uniform material): the lobe per lane, no table
    alpha_xml = scenes["al d65"]
    jobs += [{"variant": v, "xml": alpha_xml, "spp": 2048, "seed": 3, "gradients": {"qd.alpha": 0.01}}
             for v in ("llvm_ad_spectral", "llvm_ad_rgb")]
    # the same through Mitsuba's roughconductor (no fluorescence): fluo_path's sampled
    # direction moved with alpha and gave +0.53 where central differences give -0.38
    rough = re.sub(r'<bsdf type="fluo_qd" id="qd">.*?</bsdf>',
                   '<bsdf type="roughconductor" id="qd"><string name="material" value="Al"/>'
                   '<string name="distribution" value="ggx"/><float name="alpha" value="0.15"/></bsdf>',
                   alpha_xml, flags=re.S)
    jobs.append({"variant": "llvm_ad_spectral", "xml": rough, "spp": 2048, "seed": 3,
                 "gradients": {"qd.alpha.value": 0.01}})
    # fluo_qd's alpha through fluo_volpath, whose surface vertices sample the same way (a scene
    # without fluorescence is Mitsuba's volpath, which crashes on roughconductor's alpha gradient;
    # measured AD/differences: -0.368/-0.351 seed 3, -0.349/-0.354 seed 4, -0.359/-0.355 seed 5)
    jobs.append({"variant": "llvm_ad_spectral", "xml": alpha_xml.replace('type="fluo_path"', 'type="fluo_volpath"'),
                 "spp": 2048, "seed": 3, "gradients": {"qd.alpha": 0.01}})
    # radius and density in RGB: the reduced operator's derivative at the cosine nodes and the
    # RGB tables' tangents (the same seed: no wavelength is sampled, the differences are smooth)
    jobs.append({"variant": "llvm_ad_rgb", "xml": scenes["al d65"], "spp": 512, "seed": 3, "gradients": steps})
    jobs += [{"variant": v, "traverse": {"type": "fluo_qd", "density": d}}
             for v, d in (("llvm_ad_spectral", 0.8), ("llvm_ad_rgb", 0.8),
                          ("llvm_ad_spectral", {"type": "checkerboard", "color0": 0.2, "color1": 0.8}))]
    tolerance.update({"alpha spectral": 0.05, "alpha rgb": 0.05, "roughconductor alpha": 0.05,
                      "alpha, fluo_volpath": 0.10, "al d65 rgb": 0.05})
    *grads, spectral, rgb, textured = run_llvm(jobs)
    names = list(scenes) + ["textured density, Q", "alpha spectral", "alpha rgb", "roughconductor alpha",
                            "alpha, fluo_volpath", "al d65 rgb"]
    for name, res in zip(names, grads):
        assert "error" not in res, res
        for key, (ad, fd) in res["gradients"].items():
            print(name, key, "ad", ad, "fd", fd)
            assert abs(fd) > 1e-3 and ad == pytest.approx(fd, rel=tolerance[name]), (name, key, ad, fd)
    assert {"radius", "density", "quantum_yield"} <= set(spectral["differentiable"]), spectral
    assert "radius" in rgb["differentiable"] and "density" in rgb["differentiable"], rgb
    assert "quantum_yield" in rgb["differentiable"] and "alpha" in rgb["differentiable"], rgb
    assert "alpha" in spectral["differentiable"], spectral
    assert "radius" not in textured["differentiable"] and "alpha" not in textured["differentiable"], textured


def test22_distinct_materials_share_one_callable():
    """Issue 32 finding 15: 200 distinct fluo_qd spheres took 40 s to compile in
    llvm_ad_spectral (roughconductor: 0.6 s), 200 distinct dyes 60 s: each material's values
    were literals of the kernel, so Dr.Jit compiled one callable per instance. They are kernel
    inputs now (dr::make_opaque, as Mitsuba's plugins do; in RGB the reduced operators' entries
    too, once a scene holds more than 8 fluorescent materials): ten materials differing in
    concentration, emission peak, radius, roughness or yield assemble into one callable per
    call site, as ten native ones do (Dr.Jit's log: "to 1/10 functions"), in both llvm
    variants. The cost rows llvm_many_* measure the first render and memory of 200."""
    bsdfs = {
        "diffuse": lambda t: {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2 + 0.6 * t, 0.5, 0.5]}},
        "jung": lambda t: {"type": "fluo_jung", "concentration": 0.1 + 0.8 * t, "emission_peak": 500 + 60 * t},
        "qd": lambda t: {"type": "fluo_qd", "radius": 2.0 + 2.0 * t, "alpha": 0.05 + 0.2 * t},
        "qd_yield": lambda t: {"type": "fluo_qd", "quantum_yield": 0.2 + 0.6 * t},
    }
    script = '''
import json, sys, mitsuba as mi, drjit as dr
mi.set_variant(sys.argv[1])
import fluo
bsdfs = json.loads(sys.argv[2])
scene = {"type": "scene", "integrator": {"type": sys.argv[3], "max_depth": 3},
         "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at([0, 0, 30], [0, 0, 0], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 8, "height": 8}},
         "emitter": {"type": "constant", "radiance": {"type": "fluo_illuminant", "illuminant": "D65"}}}
for i, b in enumerate(bsdfs):
    scene[f"s{i}"] = {"type": "sphere", "center": [2 * i - 9, 0, 0], "radius": 0.8, "bsdf": b}
s = mi.load_dict(scene)
dr.set_log_level(dr.LogLevel.Debug)
dr.eval(mi.render(s, spp=1))
'''
    for variant in ("llvm_ad_spectral", "llvm_ad_rgb"):
        for name, make in bsdfs.items():
            materials = [make(i / 9) for i in range(10)]
            integrator = "path" if name == "diffuse" else "fluo_path"
            proc = subprocess.run([sys.executable, "-c", script, variant, json.dumps(materials), integrator],
                                  capture_output=True, text=True, timeout=600, cwd=REPO)
            assert proc.returncode == 0, proc.stderr[-3000:]
            log = proc.stdout + proc.stderr
            calls = re.findall(r'call \("(BSDF::eval_pdf_sample\(\)|drjit::dispatch\(\))"\) to (\d+)/(\d+) functions',
                               log)
            for site, unique, total in calls:
                assert (int(unique), int(total)) == (1, 10), (variant, name, site, unique, total)
            if not name.startswith("qd"):
                assert calls, (variant, name, log[-2000:])
            if name == "jung":  # its operator (RGB) or choice (spectral) is read per lane: no call of ours
                assert "drjit::dispatch()" not in [site for site, _, _ in calls], (variant, calls)
            if name.startswith("qd"):
                # choice and lobe (spectral), reduced lobe (RGB), and the coatings' own BSDF (their
                # microfacet lobe and coating: Bispectral::jit_eval_pdf_sample_joined) joined: no
                # call is assembled; the one over the scene's BSDFs finds nothing to do in any of
                # the ten (optimized away)
                assert not calls, (variant, name, calls)
                over_bsdfs = re.findall(r'call \("drjit::dispatch\(\)"\) with 10 instances.*', log)
                assert over_bsdfs and all("optimized away" in c for c in over_bsdfs), (variant, name, over_bsdfs)
                assert 'call ("BSDF::eval_pdf_sample()")' not in log, (variant, name)


TILES = """<scene version="3.0.0">
    <integrator type="fluo_path"><integer name="max_depth" value="3"/>{basis}
        <boolean name="hide_emitters" value="true"/></integrator>
    <sensor type="perspective"><float name="fov" value="90"/><string name="fov_axis" value="x"/>
        <transform name="to_world"><lookat origin="0, 0, 2" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="48"/></film>
    </sensor>
    <emitter type="constant"><spectrum type="fluo_illuminant" name="radiance">{light}</spectrum></emitter>
    {tiles}
</scene>"""


def tiles_xml(bsdfs: list[str], light: str, basis: str = "") -> str:
    """A 4×3 wall of unit squares filling the 64×48 view (16×16 pixels each, row-major from
    the top left), square i with the BSDF element bsdfs[i]."""
    tiles = "".join(
        f'<shape type="rectangle"><transform name="to_world"><scale value="0.5"/>'
        f'<translate value="{-1.5 + i % 4}, {1 - i // 4}, 0"/></transform>{b}</shape>' for i, b in enumerate(bsdfs))
    return TILES.format(basis=basis, light=light, tiles=tiles)


def tile_means(img: np.ndarray) -> np.ndarray:
    """Per square of tiles_xml, the mean of its inner 12×12 pixels: [12, channels]."""
    return np.stack([img[16 * (i // 4) + 2:16 * (i // 4) + 14, 16 * (i % 4) + 2:16 * (i % 4) + 14].mean(axis=(0, 1))
                     for i in range(12)])


def test23_many_materials_read_per_lane_equal_scalar(tmp_path):
    """Issue 32, the many-materials cost: with more than 8 fluorescent materials, the
    uniform ones (no texture, no gradient) are no longer reached through a call traced per
    material: in RGB their reduced operators are formed once per render into one table read
    per lane by the BSDF's registry id (fluo_reduced.h, gather_operators), in spectral
    variants fluo_jung's choice reads each dye's numbers and reflectance nodes from one table
    (Bispectral::jit_join). Every square of a wall of twelve, each its own material
    (ten distinct dyes and reflectances; one fluo_jung with a checkerboard reflectance, still
    reached through the call, and in the second scene a fluo_qd, a class of its own; one diffuse),
    renders in llvm what the scalar variants render (no table there), square by square (a
    row read for the wrong material shows on two squares), by a pooled z over seeds."""
    dyes = [f'<bsdf type="fluo_jung"><float name="concentration" value="{0.15 + 0.08 * i}"/>'
            f'<float name="emission_peak" value="{470 + 14 * i}"/><float name="stokes_shift" value="{30 + 8 * (i % 3)}"/>'
            f'<float name="quantum_yield" value="{0.5 + 0.05 * i}"/>'
            f'<rgb name="reflectance" value="{0.2 + 0.07 * i}, {0.8 - 0.06 * i}, {0.3 + 0.04 * (i % 5)}"/></bsdf>'
            for i in range(10)]
    checker = ('<bsdf type="fluo_jung"><float name="concentration" value="0.5"/>'
               '<texture type="checkerboard" name="reflectance"><rgb name="color0" value="0.1, 0.2, 0.6"/>'
               '<rgb name="color1" value="0.7, 0.6, 0.1"/></texture></bsdf>')
    diffuse = '<bsdf type="diffuse"><rgb name="reflectance" value="0.4, 0.5, 0.6"/></bsdf>'
    qd = '<bsdf type="fluo_qd"><float name="radius" value="2.5"/><float name="alpha" value="0.3"/></bsdf>'
    cases = []
    for last in (diffuse, qd):
        for v, basis in (("llvm_ad_spectral", ""), ("llvm_ad_rgb", '<string name="basis" value="x7"/>')):
            cases.append((f"d65 {'qd' if last is qd else 'diffuse'}", v,
                          {"variant": v, "xml": tiles_xml(dyes + [checker, last], D65, basis), "spp": 64,
                           "image": True}))
    llvm_seeds, scalar_seeds = 4, 6
    # (a job list per scene: all of them in one argument would pass the kernel's limit)
    results = [run_llvm([{**job, "seed": 11 + s} for s in range(llvm_seeds)]) for _, _, job in cases]
    report, bad = [], []
    for (name, v, job), runs in zip(cases, results):
        assert all("error" not in r for r in runs), f"{name} {v}: {runs[0].get('error')}"
        a = np.stack([tile_means(np.array(r["image"])) for r in runs])
        mi.set_variant(v.replace("llvm_ad_", "scalar_"))
        scene = mi.load_string(job["xml"])
        b = np.stack([tile_means(np.array(mi.render(scene, spp=job["spp"], seed=s), dtype=np.float64))
                      for s in range(scalar_seeds)])
        assert np.all(b.mean(axis=(0, 2)) > 1e-3), f"{name} {v}: a black square, the comparison would be empty"
        pooled = (np.var(a, axis=0, ddof=1) * (llvm_seeds - 1) + np.var(b, axis=0, ddof=1) * (scalar_seeds - 1)) / (
            llvm_seeds + scalar_seeds - 2)
        z = (a.mean(axis=0) - b.mean(axis=0)) / np.sqrt(pooled * (1 / llvm_seeds + 1 / scalar_seeds) + 1e-20)
        rel = np.abs(a.mean(axis=0) - b.mean(axis=0)) / np.abs(b.mean(axis=(0, 2)))[:, None]
        report.append(f"{name} {v}: max |z| {np.abs(z).max():.2f}, max rel {rel.max():.4f}")
        for i in np.nonzero(np.any((np.abs(z) > Z) & (rel > REL_FLOOR), axis=1))[0]:
            bad.append(f"{name} {v} square {i}: llvm {a.mean(axis=0)[i]} scalar {b.mean(axis=0)[i]} z {z[i]}")
    print("\n".join(report))
    assert not bad, "llvm differs from scalar beyond noise:\n" + "\n".join(bad)
    # A material with gradients keeps its call among the others read per lane: AD equals
    # central differences (same seed) for its concentration and emission peak.
    steps = {"dye0.concentration": 0.05, "dye0.emission_peak": 4.0}
    xml = tiles_xml(['<ref id="dye0"/>'] + dyes[1:] + [checker, diffuse], D65).replace(
        "<shape", dyes[0].replace('type="fluo_jung"', 'type="fluo_jung" id="dye0"') + "<shape", 1)
    jobs = [{"variant": "llvm_ad_spectral", "xml": xml, "spp": 256, "seed": 3, "gradients": steps},
            {"variant": "llvm_ad_rgb", "xml": xml.replace("<boolean", '<string name="basis" value="x7"/><boolean'),
             "spp": 256, "seed": 3, "gradients": steps}]
    for job, res in zip(jobs, run_llvm(jobs)):
        assert "error" not in res, res
        for key, (ad, fd) in res["gradients"].items():
            print(job["variant"], key, "ad", ad, "fd", fd)
            assert abs(fd) > 1e-5, f"{key}: the image does not depend on it, the check would be empty"
            assert abs(ad - fd) <= 0.25 * abs(fd), f"{job['variant']} {key}: AD {ad} vs finite differences {fd}"


def test24_many_coatings_joined_equal_scalar(tmp_path):
    """Issue 32, the many-materials cost of fluo_qd: with more than 8 fluorescent materials,
    the uniform coatings without gradients are joined (Bispectral::jit_join): in spectral
    variants one of them makes the choice and evaluates the direction-dependent reradiation
    of every coating's lanes from their tables joined as one set; in RGB the reduced
    transport reads each coating's node weights and terms' matrices from one table and asks
    the class for the lobe at the lane's roughness (fluo_reduced.h, joined_products); the
    lane's coating is read by its BSDF's registry id, instead of a callable traced per
    coating. A wall of twelve squares, each its own material: nine distinct coatings
    (radius, density, quantum yield, roughness, Beckmann/GGX, gold or the default substrate:
    each table and number of the joined set is read for the right lane or a square shows
    it), a coating with a checkerboard radius (not joinable: its own call), fluo_jung with
    its default reflectance (its own class) and diffuse. The coatings' own BSDF (microfacet
    lobe, coating, substrate) is evaluated joined too (jit_eval_pdf_sample_joined; one class
    per distribution and substrate), by fluo_path and fluo_volpath. llvm (both integrators)
    equals the scalar variant (no joining there) square by square, by a pooled z over seeds,
    in both llvm variants; then a coating with a gradient on its quantum yield among joined
    ones: AD equals central differences."""
    def coating(i: int) -> str:
        substrate = '<string name="material" value="Au"/>' if i % 3 == 2 else ""
        return (f'<bsdf type="fluo_qd"><float name="radius" value="{2.0 + 0.22 * i}"/>'
                f'<float name="density" value="{0.35 + 0.07 * i}"/><float name="quantum_yield" value="{0.4 + 0.06 * i}"/>'
                f'<float name="alpha" value="{0.12 + 0.04 * i}"/>'
                f'<string name="distribution" value="{"ggx" if i % 2 else "beckmann"}"/>{substrate}</bsdf>')
    coatings = [coating(i) for i in range(9)]
    checker = ('<bsdf type="fluo_qd"><texture type="checkerboard" name="radius"><float name="color0" value="2.2"/>'
               '<float name="color1" value="3.3"/></texture></bsdf>')
    jung = '<bsdf type="fluo_jung"><float name="concentration" value="0.5"/></bsdf>'
    diffuse = '<bsdf type="diffuse"><rgb name="reflectance" value="0.4, 0.5, 0.6"/></bsdf>'
    llvm_seeds, scalar_seeds = 4, 6
    bad = []
    for v, basis in (("llvm_ad_spectral", ""), ("llvm_ad_rgb", '<string name="basis" value="x7"/>')):
        xml = tiles_xml(coatings + [checker, jung, diffuse], D65, basis)
        mi.set_variant(v.replace("llvm_ad_", "scalar_"))
        scene = mi.load_string(xml)
        b = np.stack([tile_means(np.array(mi.render(scene, spp=64, seed=s), dtype=np.float64))
                      for s in range(scalar_seeds)])
        assert np.all(b.mean(axis=(0, 2)) > 1e-3), f"{v}: a black square, the comparison would be empty"
        for integrator in ("fluo_path", "fluo_volpath"):
            job = {"variant": v, "xml": xml.replace('"fluo_path"', f'"{integrator}"'), "spp": 64, "image": True}
            runs = run_llvm([{**job, "seed": 11 + s} for s in range(llvm_seeds)])
            assert all("error" not in r for r in runs), runs[0].get("error")
            a = np.stack([tile_means(np.array(r["image"])) for r in runs])
            pooled = (np.var(a, axis=0, ddof=1) * (llvm_seeds - 1) +
                      np.var(b, axis=0, ddof=1) * (scalar_seeds - 1)) / (llvm_seeds + scalar_seeds - 2)
            z = (a.mean(axis=0) - b.mean(axis=0)) / np.sqrt(pooled * (1 / llvm_seeds + 1 / scalar_seeds) + 1e-20)
            rel = np.abs(a.mean(axis=0) - b.mean(axis=0)) / np.abs(b.mean(axis=(0, 2)))[:, None]
            print(f"{v} {integrator}: max |z| {np.abs(z).max():.2f}, max rel {rel.max():.4f}")
            bad += [f"{v} {integrator} square {i}: llvm {a.mean(axis=0)[i]} scalar {b.mean(axis=0)[i]} z {z[i]}"
                    for i in np.nonzero(np.any((np.abs(z) > Z) & (rel > REL_FLOOR), axis=1))[0]]
        # the squares differ: a joined set read at one member for every lane would not
        assert np.ptp(b.mean(axis=0)[:9, 1]) > 0.05 * b.mean(axis=0)[:9, 1].max(), v
    assert not bad, "llvm differs from scalar beyond noise:\n" + "\n".join(bad)
    # A coating with a gradient keeps its call among joined ones.
    steps = {"qd0.quantum_yield": 0.05}
    for v, basis in (("llvm_ad_spectral", ""), ("llvm_ad_rgb", '<string name="basis" value="x7"/>')):
        xml_grad = tiles_xml(['<ref id="qd0"/>'] + coatings[1:] + [checker, jung, diffuse], D65, basis).replace(
            "<shape", coatings[0].replace('type="fluo_qd"', 'type="fluo_qd" id="qd0"') + "<shape", 1)
        res = run_llvm([{"variant": v, "xml": xml_grad, "spp": 256, "seed": 3, "gradients": steps}])[0]
        assert "error" not in res, res
        for key, (ad, fd) in res["gradients"].items():
            print(v, key, "ad", ad, "fd", fd)
            assert abs(fd) > 1e-5, f"{v} {key}: the image does not depend on it, the check would be empty"
            assert abs(ad - fd) <= 0.25 * abs(fd), f"{v} {key}: AD {ad} vs finite differences {fd}"


def test24b_nested_renders_follow_updates():
    """Nested in `moment` or `stokes` (whose render() calls only the nested sample(); `aov`
    calls the nested render()), fluo_path prepares a scene at its first sample, not per
    render: it kept that preparation after a parameter update, and a joined coating (twelve
    coatings: one class reads them all from joined tables) updated between two nested renders
    rendered as before the update (measured: identical to it, 0.22 off a fresh load). An
    update of a fluo plugin now prepares the scene again (fluo_detail::update_generation):
    the updated scene renders as a fresh load of it with the same seed (both llvm variants,
    fluo_path and fluo_volpath; `stokes` in llvm_ad_spectral_polarized), and differs from the
    render before the update."""
    script = '''
import sys, numpy as np, mitsuba as mi, drjit as dr
mi.set_variant(sys.argv[1])
import fluo
def scene(r0):
    d = {"type": "scene", "integrator": {"type": sys.argv[3], "integrator": {"type": sys.argv[2], "max_depth": 3}},
         "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at([0, 0, 30], [0, 0, 0], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 24, "height": 8}},
         "emitter": {"type": "constant", "radiance": {"type": "fluo_illuminant", "illuminant": "D65"}}}
    for i in range(12):
        d[f"s{i}"] = {"type": "sphere", "center": [2 * i - 11, 0, 0], "radius": 0.9,
                      "bsdf": {"type": "fluo_qd", "radius": r0 if i == 0 else 2.0 + 0.15 * i, "density": 0.8,
                               "alpha": 0.2}}
    return mi.load_dict(d)
def render(s):
    return np.array(mi.render(s, spp=64, seed=5))[..., :3]  # (the colour: the first moment, or S0)
s = scene(2.0)
before = render(s)
p = mi.traverse(s)
key = next(k for k in p.keys() if k.startswith("s0.") and k.endswith("radius"))
p[key] = 3.4
p.update()
after = render(s)
fresh = render(scene(3.4))
print("RESULT", float(np.abs(after - fresh).max()), float(np.abs(fresh - before).max()), float(np.abs(fresh).max()))
'''
    cases = [(v, i, "moment") for v in ("llvm_ad_spectral", "llvm_ad_rgb") for i in ("fluo_path", "fluo_volpath")]
    for variant, integrator, outer in cases + [("llvm_ad_spectral_polarized", "fluo_path", "stokes")]:
        proc = subprocess.run([sys.executable, "-c", script, variant, integrator, outer], capture_output=True,
                              text=True, timeout=600, cwd=REPO)
        assert proc.returncode == 0, proc.stderr[-3000:]
        line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")][-1]
        to_fresh, to_before, scale = map(float, line.split()[1:])
        print(variant, integrator, "after vs fresh", to_fresh, "fresh vs before", to_before, "scale", scale)
        assert to_before > 0.02 * scale, (variant, integrator, "the update does not show: the check is empty")
        assert to_fresh <= 1e-3 * scale, (variant, integrator, to_fresh, scale)


def test25_coating_updates_reuse_their_table_memory():
    """Every coating's spectral tables are one block of one array per variant
    (fluo_detail::TableStore: Dr.Jit rounds each allocation up to a power of two, and a joined
    class reads its members' blocks in place). An update frees its coating's block and the next
    one reuses the space: 200 radius updates of one coating among twelve (each block about
    0.7 MB: 140 MB if none were reused) grow the process by less than 20 MB, in llvm and in
    the scalar variant, which shares the class. test24 and test_updates check the values read."""
    script = '''
import sys, mitsuba as mi, drjit as dr
mi.set_variant(sys.argv[1])
import fluo
scene = {"type": "scene", "integrator": {"type": "fluo_path", "max_depth": 3},
         "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at([0, 0, 30], [0, 0, 0], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 8, "height": 8}},
         "emitter": {"type": "constant", "radiance": {"type": "fluo_illuminant", "illuminant": "D65"}}}
for i in range(12):
    scene[f"s{i}"] = {"type": "sphere", "center": [2 * i - 11, 0, 0], "radius": 0.8,
                      "bsdf": {"type": "fluo_qd", "radius": 2.0 + 0.15 * i}}
s = mi.load_dict(scene)
p = mi.traverse(s)
key = next(k for k in p.keys() if k.endswith("radius"))
def cycle(n):
    for i in range(n):
        p[key] = 2.0 + 0.05 * (i % 40)  # (grids of several lengths: blocks of several sizes)
        p.update()
        if i % 25 == 0:
            dr.eval(mi.render(s, spp=1))
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
cycle(50)
before = rss()
cycle(200)
print("RESULT", rss() - before)
'''
    for variant in ("llvm_ad_spectral", "scalar_spectral"):
        proc = subprocess.run([sys.executable, "-c", script, variant], capture_output=True, text=True, timeout=600,
                              cwd=REPO)
        assert proc.returncode == 0, proc.stderr[-3000:]
        grown = float(proc.stdout.split("RESULT")[-1])
        print(variant, f"grew {grown:.1f} MB")
        assert grown < 20.0, f"{variant}: 200 updates grew the process by {grown:.1f} MB"
