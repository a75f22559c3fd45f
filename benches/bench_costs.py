"""Benchmark: what each fluorescent feature costs over its native counterpart, every
row measured side by side in one run.

Each row renders (or loads) two scenes A and B in the same process, interleaved in
paired rounds (A then B, then B then A, ...), and reports the median of the per-round
ratios A/B with their spread (min-max): on a shared 2-core machine a paired ratio is
stable where absolute times are not. Rows and targets:

================================================  ===========================================  ======
row                                               A / B                                        target
================================================  ===========================================  ======
Cornell box without fluorescence (both variants)  ``fluo_path`` / ``path``                     1.05
fluorescent Cornell box, ``scalar_spectral``      ``fluo_path`` / ``path`` (``fluo_jung``)     1.10
measured material, same box                       ``fluo_matrix`` / ``diffuse``                1.25
Gaussian mixture (8)                              ``fluo_gmm`` / ``fluo_matrix``               1.15
quantum-dot coating (density 0.8)                 ``fluo_qd`` / ``roughconductor``             1.15
reduced RGB ``x7``, ``scalar_rgb``                ``fluo_path`` / ``path`` (dyes removed)      1.20
spectral light on a plain box                     ``fluo_illuminant`` D65 / native ``d65``     1.01
plain box + 1000 hidden fluorescent spheres       ``fluo_path`` (N = 1000) / ``path`` (N = 0)  1.15
load of K coloured ``fluo_jung`` (``color``)      ms and MB per material (B: ``diffuse``)      0.2 ms
textured ``fluo_jung`` (both variants)            textured / uniform ``fluo_jung``             1.30
textured ``fluo_qd``, ``scalar_spectral``         textured / uniform ``fluo_qd``               1.30
medium without fluorescence                       ``fluo_volpath`` / ``volpath``               1.05
quantum-dot cuvette (homogeneous, density grid)   ``fluo_volpath`` Q 0.8 / ``volpath`` Q 0     1.50
quantum-dot cuvette, reduced RGB ``x7``          ``fluo_volpath`` Q 0.8 / ``volpath`` Q 0     1.50
llvm: box without fluorescence (both variants)    llvm ``fluo_path`` / llvm ``path``           1.05
llvm: fluorescent box, ``llvm_ad_spectral``       ``fluo_path`` / ``path`` (dyes removed)      1.50
llvm: reduced RGB ``x7``, ``llvm_ad_rgb``         ``fluo_path`` / ``path`` (dyes removed)      1.50
llvm: measured matrix / mixture box (spectral)    ``fluo_matrix``, ``fluo_gmm`` / ``diffuse``  1.50
llvm: measured matrix box, reduced ``x7``         ``fluo_matrix`` / ``diffuse``                1.50
llvm: quantum-dot coating (both variants)         ``fluo_qd`` / ``roughconductor``             1.50
llvm: textured ``fluo_jung``, spectral            textured / uniform ``fluo_jung``             1.30
llvm: textured ``fluo_qd`` (both variants)        textured / uniform ``fluo_qd``               1.50
llvm: medium without fluorescence (spectral)      ``fluo_volpath`` / ``volpath``               1.05
llvm: quantum-dot cuvette, ``llvm_ad_spectral``   ``fluo_volpath`` Q 0.8 / ``volpath`` Q 0     report
llvm speed-up, same fluorescent box (both)        scalar ``fluo_path`` / llvm ``fluo_path``    report
per vertex, closed box (4 models × 4 variants)    fluorescent walls / native walls             1.25
llvm: 200 distinct materials (jung, qd; both)     first render, peak memory / native ones      2.0
llvm: one backward pass, peak memory (spectral)   ``fluo_prb`` / AD through ``fluo_path``      0.5
llvm: one backward pass, peak memory (RGB)        ``fluo_prb`` / AD through ``fluo_path``      0.5
llvm: one backward pass, QD cuvette (spectral)    ``fluo_prbvolpath`` / AD, ``fluo_volpath``   0.5
llvm: one backward pass, QD cuvette (RGB)         ``fluo_prbvolpath`` / AD, ``fluo_volpath``   0.5
================================================  ===========================================  ======

The materials of the box rows replace the box's walls and blocks; the light is the
box's area light with a D65 spectrum from 300 nm (``fluo_illuminant``), except in the
rows without fluorescence (Mitsuba's own light) and the ``fluo_illuminant`` row. The measured material is ``data/matrices/jung_orange.csv`` and its
8-component fit ``jung_orange.gmm.json``. Hidden spheres sit behind the back wall, each
with its own dye (Mitsuba merges equal definitions), so no ray reaches them but
``fluo_path`` knows 1000 fluorescent BSDFs. The medium rows render a 1 cm cuvette (thin
glass) of ``fluo_qd_medium`` (R = 2.7 nm, 0.4 µmol/L, μa(340 nm) ≈ 3/cm), homogeneous or
with a density grid, on a grey floor under a D65 area light from 300 nm; B is the same
medium made non-fluorescent (``quantum_yield`` 0: the same absorption and tracking
majorant) under Mitsuba's ``volpath``, in ``scalar_spectral`` and (the reduced row)
``scalar_rgb``. The textured rows give the material
checkerboards (``TEXTURED_JUNG``: concentration and emission peak, two dye shapes;
``TEXTURED_QD``: radius and density, four baked coatings) against the uniform material
with the first value of each; both render with ``fluo_path``. In llvm the textured
``fluo_qd`` rows are held to the llvm rows' 1.5, not the scalar rows' 1.30: against the lean
vectorised baseline each hit's four models (their λ cells, the elastic part's mixture of four
R_tot) weigh more than in the scalar variant, whose per-call overheads dilute them.

The per-vertex rows render a closed cube whose six walls are one material (``fluo_jung``,
``fluo_matrix``, ``fluo_gmm`` against ``diffuse``; ``fluo_qd`` against ``roughconductor``), lit
by a small spherical D65 light inside and seen from inside, with ``fluo_path`` (reduced x7 in
RGB) against Mitsuba's ``path``, ``max_depth`` 8 and ``rr_depth`` 108: no path escapes and
none is rouletted, so both sides trace the same vertices and the ratio is the cost of a
fluorescent vertex over a native one, in all four variants (llvm ones in a worker).

The many-materials rows put 200 spheres in the box, each its own material (``fluo_jung``: a
distinct concentration and emission peak; ``fluo_qd``: a distinct radius) against 200 distinct
``diffuse`` or ``roughconductor`` ones under ``path``, and time the load and first render (tracing
and compiling every kernel, each side in a fresh process with an empty kernel cache) and its
peak memory: a JIT variant compiles one callable per distinct instance unless the instances'
values are kernel inputs rather than literals (issue 32, finding 15: 60 s for 200 dyes), and
traces one per instance unless their data is read per lane (fluo_path's docs: operators
gathered in RGB, each class's data joined in spectral variants).

The medium rows render ``MEDIA_SPP_FACTOR`` (4) times the samples of the others (a 16-spp
cuvette render is too short to time on a shared machine), the scalar basis row
``BASIS_SPP_FACTOR`` (4) times (its two sides differ by a few multiplies per vertex). The llvm rows render
``LLVM_SPP_FACTOR`` (8) times the samples of the others and run in
a fresh process each (Mitsuba 3.8 cannot start an llvm variant in a
process that has rendered in a scalar one): A and B are interleaved there as everywhere
else; their first render, which traces and compiles the kernels, is reported as
``compile_s`` (kernel compile time) and not timed. The speed-up row times the same
fluorescent box in a scalar process and an llvm process, started alternately, each
round's ratio of the two render times (after their first, compiling, render).

The llvm cuvette row is a report, not a target: measured with parts of fluo_volpath's
vectorised loop switched off, its tracking (spectral tracking, the source-rate floor, the
flight's rates) costs nothing over volpath (0.92 with shifts disabled) and the excitation
sample little (1.75 with a constant λi instead of 1.82): the rest is the re-emitted light
itself, paths that go on where volpath's absorbed light stops, which the lean llvm volpath
baseline does not dilute as the scalar one does (its row: 1.41). (Those numbers predate
2026-11-28, when the majorant fluo's media give Mitsuba's volpath was doubled to end a bias:
the native baseline of every cuvette row changed then; llvm row 1.94 -> 1.47, scalar 1.66 -> 1.50.)

``--backend cuda`` runs the JIT rows (``llvm_*`` and the per-vertex ``vertex_*_llvm_*``) in
the cuda variants instead (``cuda_ad_spectral``, ``cuda_ad_rgb``, same scenes, same pairs),
on a machine with an NVIDIA GPU; their labels then say "cuda". The speed-up rows compare
scalar with cuda. Memory there is the peak of Dr.Jit's device allocations
(``malloc_watermark``), not the process's resident set.

Usage: python benches/bench_costs.py [--spp 16] [--res 96] [--rounds 7] [--rows a,b] [--json]
       python benches/bench_costs.py --backend cuda --rows llvm_jung,llvm_qd --json   # on a GPU
       python benches/bench_costs.py --json > docs/bench/costs.json
       python benches/bench_costs.py --readme docs/bench/costs.json   # README's costs region
       python benches/bench_costs.py --rows llvm_jung --merge docs/bench/costs.json  # update rows in place

``--readme`` measures nothing: it rewrites README.md's region between
``<!-- costs:begin -->`` and ``<!-- costs:end -->`` from a saved ``--json`` run, so the
README's table is the benchmark's output, never typed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

# One BLAS thread: numpy's idle OpenBLAS threads spin on the renders' cores (~6 % of
# a 2-core machine's time, on both sides of every ratio).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("scalar_spectral")  # the scene dictionaries need a variant's types

REPO = Path(__file__).resolve().parents[1]
MATRICES = REPO / "data" / "matrices"
D65 = {"type": "fluo_illuminant", "illuminant": "D65", "scale": 15.0}
DYE = {"emission_peak": 560.0, "stokes_shift": 90.0, "concentration": 0.8}
ROUGH = {"material": "Au", "distribution": "ggx", "alpha": 0.2}
HIDDEN = 1000
HOMOGENEOUS = {"type": "homogeneous", "sigma_t": 2.0, "albedo": 0.8}
GRID = Path("/tmp") / "fluo_bench_volpath_density.vol"
COLOURED = 100


def checker(a: float, b: float) -> dict:
    return {"type": "checkerboard", "color0": a, "color1": b,
            "to_uv": mi.ScalarTransform4f().scale([8, 8, 1])}


#: The textured rows' materials: (textured, uniform) parameters.
TEXTURED_JUNG = ({"concentration": checker(0.8, 0.4), "emission_peak": checker(560.0, 610.0)},
                 {"concentration": 0.8, "emission_peak": 560.0})
TEXTURED_QD = ({"radius": checker(2.2, 3.0), "density": checker(0.8, 0.4)}, {"radius": 2.2, "density": 0.8})


def box(res: int, integrator: str = "fluo_path", bsdf=None, light=D65, **integrator_props) -> dict:
    """Mitsuba's Cornell box; ``bsdf(reflectance)`` gives the walls' and blocks' BSDF."""
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = res
    d["sensor"]["film"]["rfilter"] = {"type": "box"}
    d["integrator"] = {"type": integrator, "max_depth": 8, **integrator_props}
    if bsdf is not None:
        for key in ("white", "red", "green"):
            d[key] = bsdf(d[key]["reflectance"])
    if light is not None:
        d["light"]["emitter"]["radiance"] = light
    return d


def jung(refl: dict) -> dict:
    return {"type": "fluo_jung", "reflectance": refl, **DYE}


def measured(plugin: str):
    """Walls and blocks of a measured material (jung_orange: its matrix, or its 8-Gaussian fit)."""
    file = MATRICES / ("jung_orange.csv" if plugin == "fluo_matrix" else "jung_orange.gmm.json")
    return lambda refl: {"type": plugin, "filename": str(file)}


def diffuse(refl: dict) -> dict:
    return {"type": "diffuse", "reflectance": refl}


def with_hidden_spheres(d: dict, n: int) -> dict:
    for i in range(n):
        d[f"hidden_{i}"] = {
            "type": "sphere", "center": [-0.9 + 1.8 * (i % 32) / 31, -0.9 + 1.8 * (i // 32) / 31, -3.0],
            "radius": 0.01,
            "bsdf": {"type": "fluo_jung", "emission_peak": 500.0 + 0.1 * i, "concentration": 0.5}}
    return d


T = mi.ScalarTransform4f()


def cuvette(res: int, integrator: str, medium: dict) -> dict:
    """A 1 cm cuvette (thin glass) of `medium` on a grey floor under a D65 area light from 300 nm."""
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": 12},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": T.look_at(origin=[0, 2.5, 6], target=[0, 0.6, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res},
                   "sampler": {"type": "independent"}},
        "light": {"type": "rectangle", "to_world": T.translate([0, 5, 2]) @ T.rotate([1, 0, 0], 90) @ T.scale(2),
                  "emitter": {"type": "area",
                              "radiance": {"type": "fluo_illuminant", "illuminant": "D65", "scale": 10.0}}},
        "floor": {"type": "rectangle", "to_world": T.rotate([1, 0, 0], -90) @ T.scale(5),
                  "bsdf": {"type": "diffuse", "reflectance": 0.3}},
        "cuvette": {"type": "cube", "to_world": T.translate([0, 0.8, 0]) @ T.scale([0.5, 0.8, 0.5]),
                    "bsdf": {"type": "thindielectric", "int_ior": 1.5}, "interior": medium},
    }


def density_grid(path: Path) -> dict:
    """A smooth 16³ density grid written to `path`."""
    x = np.linspace(0.0, 1.0, 16)
    g = 0.5 + 0.5 * np.sin(6.0 * x)[:, None, None] * np.cos(4.0 * x)[None, :, None] * np.ones(16)[None, None, :]
    mi.VolumeGrid(np.asarray(g, dtype=np.float32)[..., None]).write(str(path))
    return {"type": "gridvolume", "filename": str(path),
            "to_world": T.translate([-0.5, 0.0, -0.5]) @ T.scale([1.0, 1.6, 1.0])}


def qd_medium(q: float, density: dict | None = None) -> dict:
    """fluo_qd_medium: R = 2.7 nm, 0.4 µmol/L (μa(340 nm) ≈ 3/cm), yield q."""
    m = {"type": "fluo_qd_medium", "radius": 2.7, "quantum_yield": q, "concentration": 0.4, "scale": 0.01}
    if density is not None:
        m["density"] = density
    return m


#: Per-vertex rows: a closed box whose six walls are one material (fluorescent, or its
#: native counterpart), lit by a small spherical light inside, seen from inside: every path
#: meets VERTEX_DEPTH - 1 surfaces, none escapes, and roulette is off (rr_depth > max_depth),
#: so both sides trace the same number of vertices and the ratio is the per-vertex cost.
VERTEX_DEPTH = 8

#: (fluorescent, native) wall materials of the per-vertex rows.
VERTEX_MATERIALS = {
    "jung": ({"type": "fluo_jung", "reflectance": 0.5, **DYE}, {"type": "diffuse", "reflectance": 0.5}),
    "matrix": ({"type": "fluo_matrix", "filename": str(MATRICES / "jung_orange.csv")},
               {"type": "diffuse", "reflectance": 0.5}),
    "gmm": ({"type": "fluo_gmm", "filename": str(MATRICES / "jung_orange.gmm.json")},
            {"type": "diffuse", "reflectance": 0.5}),
    "qd": ({"type": "fluo_qd", "density": 0.8, **ROUGH}, {"type": "roughconductor", **ROUGH}),
}


def closed_box(res: int, integrator: str, bsdf: dict, basis: str = "x7") -> dict:
    """The per-vertex rows' scene (VERTEX_DEPTH; reduced RGB in `basis`)."""
    props = {"basis": basis} if integrator == "fluo_path" else {}
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": VERTEX_DEPTH, "rr_depth": VERTEX_DEPTH + 100, **props},
        "sensor": {"type": "perspective", "fov": 70,
                   "to_world": T.look_at(origin=[0, 0, 0.8], target=[0, 0, -1], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "walls": {"type": "cube", "flip_normals": True, "bsdf": bsdf},
        "light": {"type": "sphere", "center": [0.3, 0.5, -0.3], "radius": 0.1,
                  "emitter": {"type": "area", "radiance": D65}},
    }


def vertex_row(variant: str, model: str, res: int, spp: int, rounds: int) -> dict:
    fl, native = VERTEX_MATERIALS[model]
    pair = render_pair_jit if variant.startswith("llvm_") else render_pair
    return pair(variant, closed_box(res, "fluo_path", fl), closed_box(res, "path", native), spp, rounds)


def basis_row(variant: str, res: int, spp: int, rounds: int) -> dict:
    """Per-vertex cost of the adaptive basis over x7 (fluo_jung walls under the D65
    fluo_illuminant: auto builds its light band from it)."""
    fl, _ = VERTEX_MATERIALS["jung"]
    pair = render_pair_jit if variant.startswith("llvm_") else render_pair
    return pair(variant, closed_box(res, "fluo_path", fl, "auto"), closed_box(res, "fluo_path", fl, "x7"), spp, rounds)


def paired(a, b, rounds: int) -> dict:
    """Median and spread of t(a)/t(b) over interleaved rounds (a, b: callables)."""
    a(), b()  # warm up (scene preparation, caches)
    ratios, ta, tb = [], [], []
    for r in range(rounds):
        order = (a, b) if r % 2 == 0 else (b, a)
        times = {}
        for f in order:
            t0 = time.perf_counter()
            f()
            times[f] = time.perf_counter() - t0
        ta.append(times[a])
        tb.append(times[b])
        ratios.append(times[a] / times[b])
    return {"ratio": statistics.median(ratios), "min": min(ratios), "max": max(ratios),
            "a_s": statistics.median(ta), "b_s": statistics.median(tb)}


def render_pair(variant: str, da: dict, db: dict, spp: int, rounds: int) -> dict:
    mi.set_variant(variant)
    import fluo  # noqa: F401  (registers the plugins)

    sa, sb = mi.load_dict(da), mi.load_dict(db)
    return paired(lambda: mi.render(sa, spp=spp, seed=1), lambda: mi.render(sb, spp=spp, seed=1), rounds)


def rss_mb() -> float:
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * 4096 / 2**20


def load_row(res: int, rounds: int) -> dict:
    """Per coloured fluo_jung: load time and resident memory over a box without them."""
    mi.set_variant("scalar_spectral")
    import fluo  # noqa: F401

    def scene(fluorescent: bool) -> dict:
        d = box(res, bsdf=diffuse)
        for i in range(COLOURED):  # distinct colours: one material each
            rgb = {"type": "rgb", "value": [0.2 + 0.6 * i / COLOURED, 0.6, 0.3]}
            bsdf = {"type": "fluo_jung", "color": rgb} if fluorescent else {"type": "diffuse", "reflectance": rgb}
            d[f"ball_{i}"] = {"type": "sphere", "center": [0.0, 0.0, -5.0 - i], "radius": 0.1, "bsdf": bsdf}
        return d

    dk, d0 = scene(True), scene(False)
    r = paired(lambda: mi.load_dict(dk), lambda: mi.load_dict(d0), rounds)
    plain = mi.load_dict(d0)
    before = rss_mb()
    kept = mi.load_dict(dk)
    grown = rss_mb() - before
    del kept, plain
    per_ms = (r["a_s"] - r["b_s"]) * 1e3 / COLOURED
    return {**r, "per_material_ms": per_ms, "per_material_mb": grown / COLOURED}


#: The medium rows render this many times the samples of the others: at 16 spp a cuvette
#: render takes ~0.1 s, where the scheduling of 9 image blocks on a shared 2-core machine
#: moved single paired ratios by ±0.2 (the no-fluorescence row, the very code path of
#: volpath, came out 0.90-1.21).
MEDIA_SPP_FACTOR = 4

#: The basis rows compare two renders of one scene that differ by a few multiplies per
#: vertex (auto and x7 both carry K = 7 bands): at 16 spp (0.6 s a render on the 2-core
#: machine) single ratios of the scalar row spread 0.87-1.31 from block scheduling alone, so
#: the scalar row renders this many times the samples (the llvm row has LLVM_SPP_FACTOR).
BASIS_SPP_FACTOR = 4

#: The llvm rows render this many times the samples of the others: a vectorised render of
#: a 96² image at 16 spp takes milliseconds, where kernel launches and thread start-up
#: would be what is timed.
LLVM_SPP_FACTOR = 8


#: The JIT backend of the rows named llvm_* (``--backend``): "llvm", or "cuda" on a GPU.
JIT_BACKEND = "llvm"


def jit_variant(variant: str) -> str:
    """`variant` (an llvm_ad_* name) in the backend the llvm rows run on."""
    return variant.replace("llvm_", f"{JIT_BACKEND}_", 1) if variant.startswith("llvm_") else variant


def peak_mb() -> float:
    """Peak memory of this process so far, in MB: its resident set on the CPU backends; on
    the GPU (``--backend cuda``) the peak of Dr.Jit's device allocations (the renders'
    arrays, Mitsuba's scene and the recorded AD graph all live there)."""
    import resource

    if JIT_BACKEND == "cuda":
        import drjit as dr

        return dr.detail.malloc_watermark(dr.detail.AllocType.Device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def in_worker(row: str, a) -> dict:
    """Run one row (or one side of one) in a fresh process; its JSON result."""
    cmd = [sys.executable, __file__, "--worker", row, "--spp", str(a.spp * LLVM_SPP_FACTOR), "--res", str(a.res),
           "--rounds", str(a.rounds), "--backend", JIT_BACKEND]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    lines = [ln[ln.index("RESULT ") + 7:] for ln in proc.stdout.splitlines() if "RESULT " in ln]
    if proc.returncode != 0 or not lines:
        raise SystemExit(f"bench worker {row} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1])


def render_pair_jit(variant: str, da: dict, db: dict, spp: int, rounds: int) -> dict:
    """render_pair in a JIT variant: renders are evaluated (and waited for) inside the timing;
    the first render of each scene (tracing, kernel compilation) is timed apart."""
    import drjit as dr

    mi.set_variant(jit_variant(variant))
    import fluo  # noqa: F401

    sa, sb = mi.load_dict(da), mi.load_dict(db)

    def run(scene):
        img = mi.render(scene, spp=spp, seed=1)
        dr.eval(img)
        dr.sync_thread()

    compile_s = []
    for scene in (sa, sb):
        t0 = time.perf_counter()
        run(scene)
        compile_s.append(time.perf_counter() - t0)
    r = paired(lambda: run(sa), lambda: run(sb), rounds)
    return {**r, "compile_s": compile_s[0] - r["a_s"], "compile_b_s": compile_s[1] - r["b_s"]}


def render_times(variant: str, d: dict, spp: int, rounds: int) -> dict:
    """One scene's render times in this process: the first (compiling) and `rounds` more."""
    import drjit as dr

    mi.set_variant(jit_variant(variant))
    import fluo  # noqa: F401

    scene = mi.load_dict(d)
    times = []
    for _ in range(rounds + 1):
        t0 = time.perf_counter()
        img = mi.render(scene, spp=spp, seed=1)
        if dr.is_jit_v(type(img)):
            dr.eval(img)
            dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return {"first_s": times[0], "times": times[1:]}


def speedup_row(a, family: str) -> dict:
    """scalar / llvm render time of the fluorescent box, processes started alternately."""
    ratios, ts, tl, compile_s = [], [], [], 0.0
    for r in range(a.rounds):
        order = ("scalar", "llvm") if r % 2 == 0 else ("llvm", "scalar")
        got = {side: in_worker(f"speedup_{side}_{family}", argparse.Namespace(spp=a.spp, res=a.res, rounds=5))
               for side in order}
        s, l = statistics.median(got["scalar"]["times"]), statistics.median(got["llvm"]["times"])
        ratios.append(s / l)
        ts.append(s)
        tl.append(l)
        compile_s = max(compile_s, got["llvm"]["first_s"] - l)
    return {"ratio": statistics.median(ratios), "min": min(ratios), "max": max(ratios),
            "a_s": statistics.median(ts), "b_s": statistics.median(tl), "compile_s": compile_s}


#: The many-materials rows: this many distinct materials (one sphere each) in one scene.
MANY = 200


def many_materials(res: int, model: str, fluorescent: bool) -> dict:
    """MANY spheres in front of the camera, each its own material (values spread so that
    Mitsuba merges none): distinct dyes (fluo_jung: concentration and emission peak) or
    quantum dots (fluo_qd: radius), against as many distinct diffuse or roughconductor
    ones under Mitsuba's path."""
    d = box(res, "fluo_path" if fluorescent else "path", bsdf=diffuse)
    for i in range(MANY):
        t = i / (MANY - 1)
        if model == "jung":
            bsdf = {"type": "fluo_jung", "concentration": 0.1 + 0.8 * t, "emission_peak": 500.0 + 80.0 * t} \
                if fluorescent else {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.1 + 0.8 * t, .5, .3]}}
        else:
            bsdf = {"type": "fluo_qd", "radius": 2.0 + 2.0 * t, **ROUGH} if fluorescent else \
                {"type": "roughconductor", **{**ROUGH, "alpha": 0.05 + 0.3 * t}}
        d[f"ball_{i}"] = {"type": "sphere", "center": [-0.9 + 0.12 * (i % 16), -0.9 + 0.14 * (i // 16), 0.5],
                          "radius": 0.05, "bsdf": bsdf}
    return d


def first_render(variant: str, d: dict, spp: int) -> dict:
    """Load and first render (tracing and compiling every kernel: the worker runs with an
    empty kernel cache) of one scene in this fresh process, and its peak memory (peak_mb)."""
    import drjit as dr

    mi.set_variant(jit_variant(variant))
    import fluo  # noqa: F401

    t0 = time.perf_counter()
    img = mi.render(mi.load_dict(d), spp=spp, seed=1)
    dr.eval(img)
    dr.sync_thread()
    return {"first_s": time.perf_counter() - t0, "peak_mb": peak_mb()}


def many_row(a, variant: str, model: str) -> dict:
    """First render (kernel compile included) and peak memory of MANY distinct fluorescent
    materials over as many native ones, each side in a fresh process with an empty kernel
    cache (HOME pointed at a new folder), sides alternating over 3 rounds."""
    import tempfile

    times, mems = {True: [], False: []}, {True: [], False: []}
    for r in range(3):
        for side in ((True, False) if r % 2 == 0 else (False, True)):
            with tempfile.TemporaryDirectory() as home:
                cmd = [sys.executable, __file__, "--worker", f"many_{variant}_{model}_{int(side)}", "--spp", str(a.spp),
                       "--res", str(a.res), "--rounds", str(a.rounds), "--backend", JIT_BACKEND]
                proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "HOME": home})
                lines = [ln[ln.index("RESULT ") + 7:] for ln in proc.stdout.splitlines() if "RESULT " in ln]
                if proc.returncode != 0 or not lines:
                    raise SystemExit(f"bench worker failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
                got = json.loads(lines[-1])
            times[side].append(got["first_s"])
            mems[side].append(got["peak_mb"])
    ratios = [f / n for f, n in zip(times[True], times[False])]
    return {"ratio": statistics.median(ratios), "min": min(ratios), "max": max(ratios),
            "a_s": statistics.median(times[True]), "b_s": statistics.median(times[False]),
            "memory_ratio": statistics.median(mems[True]) / statistics.median(mems[False]),
            "a_mb": statistics.median(mems[True]), "b_mb": statistics.median(mems[False])}


#: The backward rows' setting (issue: one backward pass at 256², 64 spp, max_depth 8).
BACKWARD_RES, BACKWARD_SPP = 256, 64
#: ... the volumetric row's: AD through fluo_volpath's recorded loop holds 11.5 GB at 32², 32
#: spp on the cuvette (its null collisions are recorded steps) and exceeds 24 GB at 64², 64 spp.
VOLUME_BACKWARD_RES, VOLUME_BACKWARD_SPP = 32, 32


def backward_pass(variant: str, integrator: str) -> dict:
    """Load the fluorescent Cornell box (its fluo_jung walls' concentration with gradients;
    Mitsuba's `prb`: diffuse walls, their reflectance) or, for the volumetric integrators,
    the quantum-dot cuvette (Q 0.8, its concentration; Mitsuba's `prbvolpath`: a homogeneous
    medium, its σt; at VOLUME_BACKWARD_RES²,
    VOLUME_BACKWARD_SPP spp) and run one reverse-mode
    pass of mi.render at BACKWARD_RES², BACKWARD_SPP spp, max_depth 8 in this fresh process:
    its peak memory (peak_mb), and what the process held before the pass."""
    import drjit as dr

    mi.set_variant(jit_variant(variant))
    import fluo  # noqa: F401

    native = integrator in ("prb", "prbvolpath")
    spp = BACKWARD_SPP
    if "volpath" in integrator:
        d = cuvette(VOLUME_BACKWARD_RES, integrator, HOMOGENEOUS if native else qd_medium(0.8))
        spp = VOLUME_BACKWARD_SPP
        d["integrator"]["max_depth"] = 8
        key = "cuvette.interior_medium." + ("sigma_t.value.value" if native else "concentration")
    else:
        d = box(BACKWARD_RES, integrator=integrator, bsdf=diffuse if native else jung)
        key = "white.reflectance.value" if native else "white.concentration"
    scene = mi.load_dict(d)
    params = mi.traverse(scene)
    dr.enable_grad(params[key])
    params.update()
    before = peak_mb()
    t0 = time.perf_counter()
    image = mi.render(scene, params, spp=spp, seed=1)
    dr.backward(dr.mean(image, axis=None))
    grad = float(np.abs(np.array(dr.ravel(dr.grad(params[key])))).sum())
    dr.sync_thread()
    return {"peak_mb": peak_mb(), "before_mb": before,
            "seconds": time.perf_counter() - t0, "grad": grad}


def backward_row(a, variant: str, sides=("fluo_prb", "fluo_path", "prb")) -> dict:
    """Peak memory of one backward pass: the replay (fluo_prb, or fluo_prbvolpath) over AD
    through the recorded loop (fluo_path, fluo_volpath), and over Mitsuba's replay (prb,
    prbvolpath) on the same scene with native materials; each in a fresh process, two rounds."""
    replay, recorded, native = sides
    got = {side: [] for side in sides}
    for r in range(2):
        for side in (sides if r == 0 else sides[::-1]):
            got[side].append(in_worker(f"backward_{variant}_{side}", a))
    mb = {side: statistics.median(x["peak_mb"] for x in runs) for side, runs in got.items()}
    ratios = [p["peak_mb"] / q["peak_mb"] for p, q in zip(got[replay], got[recorded])]
    if min(x["grad"] for runs in got.values() for x in runs) <= 0.0:
        raise SystemExit(f"backward row {variant}: a side computed no gradient: {got}")
    return {"ratio": statistics.median(ratios), "min": min(ratios), "max": max(ratios),
            "a_mb": mb[replay], "b_mb": mb[recorded], "native_mb": mb[native],
            "native_ratio": mb[replay] / mb[native],
            "a_s": statistics.median(x["seconds"] for x in got[replay]),
            "b_s": statistics.median(x["seconds"] for x in got[recorded]),
            "native_s": statistics.median(x["seconds"] for x in got[native]),
            "native_label": "prb with diffuse walls" if native == "prb" else "prbvolpath with a homogeneous medium"}


#: Rows measured in a fresh process (llvm), by name: what the worker runs.
WORKER_ROWS = {
    **{f"backward_{v}_{side}": (lambda a, v=v, side=side: backward_pass(v, side))
       for v in ("llvm_ad_spectral", "llvm_ad_rgb")
       for side in ("fluo_prb", "fluo_path", "prb", "fluo_prbvolpath", "fluo_volpath", "prbvolpath")},
    "llvm_plain": lambda a: render_pair_jit("llvm_ad_spectral", box(a.res, bsdf=diffuse, light=None),
                                            box(a.res, "path", bsdf=diffuse, light=None), a.spp, a.rounds),
    "llvm_plain_rgb": lambda a: render_pair_jit("llvm_ad_rgb", box(a.res, bsdf=diffuse, light=None),
                                                box(a.res, "path", bsdf=diffuse, light=None), a.spp, a.rounds),
    "llvm_jung": lambda a: render_pair_jit("llvm_ad_spectral", box(a.res, bsdf=jung),
                                           box(a.res, "path", bsdf=diffuse), a.spp, a.rounds),
    "llvm_reduced": lambda a: render_pair_jit("llvm_ad_rgb", box(a.res, bsdf=jung, basis="x7"),
                                              box(a.res, "path", bsdf=diffuse), a.spp, a.rounds),
    "llvm_matrix": lambda a: render_pair_jit("llvm_ad_spectral", box(a.res, bsdf=measured("fluo_matrix")),
                                             box(a.res, "path", bsdf=diffuse), a.spp, a.rounds),
    "llvm_gmm": lambda a: render_pair_jit("llvm_ad_spectral", box(a.res, bsdf=measured("fluo_gmm")),
                                          box(a.res, "path", bsdf=diffuse), a.spp, a.rounds),
    "llvm_matrix_rgb": lambda a: render_pair_jit("llvm_ad_rgb", box(a.res, bsdf=measured("fluo_matrix"), basis="x7"),
                                                 box(a.res, "path", bsdf=diffuse), a.spp, a.rounds),
    "llvm_qd": lambda a: render_pair_jit("llvm_ad_spectral", box(a.res, bsdf=lambda r: {"type": "fluo_qd", "density": 0.8,
                                                                                      **ROUGH}),
                                         box(a.res, "path", bsdf=lambda r: {"type": "roughconductor", **ROUGH}),
                                         a.spp, a.rounds),
    "llvm_qd_rgb": lambda a: render_pair_jit("llvm_ad_rgb", box(a.res, bsdf=lambda r: {"type": "fluo_qd", "density": 0.8,
                                                                                     **ROUGH}, basis="x7"),
                                             box(a.res, "path", bsdf=lambda r: {"type": "roughconductor", **ROUGH}),
                                             a.spp, a.rounds),
    "llvm_textured": lambda a: render_pair_jit("llvm_ad_spectral", box(a.res, bsdf=lambda r: {**jung(r), **TEXTURED_JUNG[0]}),
                                               box(a.res, bsdf=lambda r: {**jung(r), **TEXTURED_JUNG[1]}),
                                               a.spp, a.rounds),
    "llvm_textured_qd": lambda a: render_pair_jit("llvm_ad_spectral",
                                                  box(a.res, bsdf=lambda r: {"type": "fluo_qd", **ROUGH, **TEXTURED_QD[0]}),
                                                  box(a.res, bsdf=lambda r: {"type": "fluo_qd", **ROUGH, **TEXTURED_QD[1]}),
                                                  a.spp, a.rounds),
    "llvm_textured_qd_rgb": lambda a: render_pair_jit(
        "llvm_ad_rgb", box(a.res, bsdf=lambda r: {"type": "fluo_qd", **ROUGH, **TEXTURED_QD[0]}, basis="x7"),
        box(a.res, bsdf=lambda r: {"type": "fluo_qd", **ROUGH, **TEXTURED_QD[1]}, basis="x7"), a.spp, a.rounds),
    "llvm_volpath_plain": lambda a: render_pair_jit("llvm_ad_spectral", cuvette(a.res, "fluo_volpath", HOMOGENEOUS),
                                                    cuvette(a.res, "volpath", HOMOGENEOUS),
                                                    a.spp * MEDIA_SPP_FACTOR, a.rounds),
    "llvm_volpath_qd": lambda a: render_pair_jit("llvm_ad_spectral", cuvette(a.res, "fluo_volpath", qd_medium(0.8)),
                                                 cuvette(a.res, "volpath", qd_medium(0.0)),
                                                 a.spp * MEDIA_SPP_FACTOR, a.rounds),
    "llvm_volpath_qd_rgb": lambda a: render_pair_jit("llvm_ad_rgb", cuvette(a.res, "fluo_volpath", qd_medium(0.8)),
                                                     cuvette(a.res, "volpath", qd_medium(0.0)),
                                                     a.spp * MEDIA_SPP_FACTOR, a.rounds),
    "vertex_jung_llvm_ad_spectral": lambda a: vertex_row("llvm_ad_spectral", "jung", a.res, a.spp, a.rounds),
    "vertex_matrix_llvm_ad_spectral": lambda a: vertex_row("llvm_ad_spectral", "matrix", a.res, a.spp, a.rounds),
    "vertex_gmm_llvm_ad_spectral": lambda a: vertex_row("llvm_ad_spectral", "gmm", a.res, a.spp, a.rounds),
    "vertex_qd_llvm_ad_spectral": lambda a: vertex_row("llvm_ad_spectral", "qd", a.res, a.spp, a.rounds),
    "vertex_jung_llvm_ad_rgb": lambda a: vertex_row("llvm_ad_rgb", "jung", a.res, a.spp, a.rounds),
    "vertex_matrix_llvm_ad_rgb": lambda a: vertex_row("llvm_ad_rgb", "matrix", a.res, a.spp, a.rounds),
    "vertex_gmm_llvm_ad_rgb": lambda a: vertex_row("llvm_ad_rgb", "gmm", a.res, a.spp, a.rounds),
    "vertex_qd_llvm_ad_rgb": lambda a: vertex_row("llvm_ad_rgb", "qd", a.res, a.spp, a.rounds),
    "vertex_auto_llvm_ad_rgb": lambda a: basis_row("llvm_ad_rgb", a.res, a.spp, a.rounds),
    **{f"many_{v}_{m}_{int(f)}": (lambda a, v=v, m=m, f=f: first_render(v, many_materials(a.res, m, f), a.spp))
       for v in ("llvm_ad_spectral", "llvm_ad_rgb") for m in ("jung", "qd") for f in (True, False)},
    "speedup_scalar_spectral": lambda a: render_times("scalar_spectral", box(a.res, bsdf=jung), a.spp, a.rounds),
    "speedup_llvm_spectral": lambda a: render_times("llvm_ad_spectral", box(a.res, bsdf=jung), a.spp, a.rounds),
    "speedup_scalar_rgb": lambda a: render_times("scalar_rgb", box(a.res, bsdf=jung, basis="x7"), a.spp, a.rounds),
    "speedup_llvm_rgb": lambda a: render_times("llvm_ad_rgb", box(a.res, bsdf=jung, basis="x7"), a.spp, a.rounds),
}


ROWS = {
    "plain": ("no fluorescence: fluo_path / path, plain box (spectral)", 1.05,
              lambda a: render_pair("scalar_spectral", box(a.res, bsdf=diffuse, light=None),
                                    box(a.res, "path", bsdf=diffuse, light=None), a.spp, a.rounds)),
    "plain_rgb": ("no fluorescence: fluo_path / path, plain box (RGB)", 1.05,
                  lambda a: render_pair("scalar_rgb", box(a.res, bsdf=diffuse, light=None),
                                        box(a.res, "path", bsdf=diffuse, light=None), a.spp, a.rounds)),
    "jung": ("fluorescent box: fluo_path / path (fluo_jung, spectral)", 1.10,
             lambda a: render_pair("scalar_spectral", box(a.res, bsdf=jung), box(a.res, "path", bsdf=jung),
                                   a.spp, a.rounds)),
    "matrix": ("fluo_matrix / diffuse, same box", 1.25,
               lambda a: render_pair("scalar_spectral",
                                     box(a.res, bsdf=lambda r: {"type": "fluo_matrix",
                                                                "filename": str(MATRICES / "jung_orange.csv")}),
                                     box(a.res, bsdf=diffuse), a.spp, a.rounds)),
    "gmm": ("fluo_gmm (8) / fluo_matrix", 1.15,
            lambda a: render_pair("scalar_spectral",
                                  box(a.res, bsdf=lambda r: {"type": "fluo_gmm",
                                                             "filename": str(MATRICES / "jung_orange.gmm.json")}),
                                  box(a.res, bsdf=lambda r: {"type": "fluo_matrix",
                                                             "filename": str(MATRICES / "jung_orange.csv")}),
                                  a.spp, a.rounds)),
    "qd": ("fluo_qd (density 0.8) / roughconductor, fluo_path", 1.15,
           lambda a: render_pair("scalar_spectral",
                                 box(a.res, bsdf=lambda r: {"type": "fluo_qd", "density": 0.8, **ROUGH}),
                                 box(a.res, bsdf=lambda r: {"type": "roughconductor", **ROUGH}),
                                 a.spp, a.rounds)),
    "reduced": ("reduced RGB x7 / path (dyes removed), fluorescent box", 1.20,
                lambda a: render_pair("scalar_rgb", box(a.res, bsdf=jung, basis="x7"),
                                      box(a.res, "path", bsdf=diffuse), a.spp, a.rounds)),
    "illuminant": ("fluo_illuminant D65 / native d65, plain box (path)", 1.01,
                   lambda a: render_pair("scalar_spectral",
                                         box(a.res, "path", light={"type": "fluo_illuminant", "illuminant": "D65"}),
                                         box(a.res, "path", light={"type": "d65"}), a.spp, a.rounds)),
    "hidden": (f"plain box + {HIDDEN} hidden fluorescent spheres: fluo_path / path at N = 0", 1.15,
               lambda a: render_pair("scalar_spectral", with_hidden_spheres(box(a.res, bsdf=diffuse), HIDDEN),
                                     box(a.res, "path", bsdf=diffuse), a.spp, a.rounds)),
    "textured": ("textured / uniform fluo_jung (concentration, emission_peak), spectral", 1.30,
                 lambda a: render_pair("scalar_spectral",
                                       box(a.res, bsdf=lambda r: {**jung(r), **TEXTURED_JUNG[0]}),
                                       box(a.res, bsdf=lambda r: {**jung(r), **TEXTURED_JUNG[1]}),
                                       a.spp, a.rounds)),
    "textured_rgb": ("textured / uniform fluo_jung (concentration, emission_peak), reduced RGB x7", 1.30,
                     lambda a: render_pair("scalar_rgb",
                                           box(a.res, bsdf=lambda r: {**jung(r), **TEXTURED_JUNG[0]}, basis="x7"),
                                           box(a.res, bsdf=lambda r: {**jung(r), **TEXTURED_JUNG[1]}, basis="x7"),
                                           a.spp, a.rounds)),
    "textured_qd": ("textured / uniform fluo_qd (radius, density), spectral", 1.30,
                    lambda a: render_pair("scalar_spectral",
                                          box(a.res, bsdf=lambda r: {"type": "fluo_qd", **ROUGH, **TEXTURED_QD[0]}),
                                          box(a.res, bsdf=lambda r: {"type": "fluo_qd", **ROUGH, **TEXTURED_QD[1]}),
                                          a.spp, a.rounds)),
    "volpath_plain": ("no fluorescence: fluo_volpath / volpath, homogeneous medium", 1.05,
                      lambda a: render_pair("scalar_spectral", cuvette(a.res, "fluo_volpath", HOMOGENEOUS),
                                            cuvette(a.res, "volpath", HOMOGENEOUS), a.spp * MEDIA_SPP_FACTOR, a.rounds)),
    "volpath_qd": ("QD cuvette: fluo_volpath (Q 0.8) / volpath (Q 0), spectral", 1.5,
                   lambda a: render_pair("scalar_spectral", cuvette(a.res, "fluo_volpath", qd_medium(0.8)),
                                         cuvette(a.res, "volpath", qd_medium(0.0)), a.spp * MEDIA_SPP_FACTOR, a.rounds)),
    "volpath_qd_grid": ("QD cuvette, density grid: fluo_volpath (Q 0.8) / volpath (Q 0)", 1.5,
                        lambda a: render_pair("scalar_spectral",
                                              cuvette(a.res, "fluo_volpath", qd_medium(0.8, density_grid(GRID))),
                                              cuvette(a.res, "volpath", qd_medium(0.0, density_grid(GRID))),
                                              a.spp * MEDIA_SPP_FACTOR, a.rounds)),
    "volpath_qd_rgb": ("QD cuvette: fluo_volpath reduced x7 (Q 0.8) / volpath (Q 0), scalar_rgb", 1.5,
                       lambda a: render_pair("scalar_rgb", cuvette(a.res, "fluo_volpath", qd_medium(0.8)),
                                             cuvette(a.res, "volpath", qd_medium(0.0)), a.spp * MEDIA_SPP_FACTOR, a.rounds)),
    "vertex_jung_scalar_spectral": ("per vertex, closed box: fluo_jung / diffuse, scalar_spectral", 1.25,
                               lambda a: vertex_row("scalar_spectral", "jung", a.res, a.spp, a.rounds)),
    "vertex_matrix_scalar_spectral": ("per vertex, closed box: fluo_matrix / diffuse, scalar_spectral", 1.25,
                               lambda a: vertex_row("scalar_spectral", "matrix", a.res, a.spp, a.rounds)),
    "vertex_gmm_scalar_spectral": ("per vertex, closed box: fluo_gmm / diffuse, scalar_spectral", 1.25,
                               lambda a: vertex_row("scalar_spectral", "gmm", a.res, a.spp, a.rounds)),
    "vertex_qd_scalar_spectral": ("per vertex, closed box: fluo_qd / roughconductor, scalar_spectral", 1.25,
                               lambda a: vertex_row("scalar_spectral", "qd", a.res, a.spp, a.rounds)),
    "vertex_jung_scalar_rgb": ("per vertex, closed box: fluo_jung / diffuse, scalar_rgb", 1.25,
                               lambda a: vertex_row("scalar_rgb", "jung", a.res, a.spp, a.rounds)),
    "vertex_matrix_scalar_rgb": ("per vertex, closed box: fluo_matrix / diffuse, scalar_rgb", 1.25,
                               lambda a: vertex_row("scalar_rgb", "matrix", a.res, a.spp, a.rounds)),
    "vertex_gmm_scalar_rgb": ("per vertex, closed box: fluo_gmm / diffuse, scalar_rgb", 1.25,
                               lambda a: vertex_row("scalar_rgb", "gmm", a.res, a.spp, a.rounds)),
    "vertex_qd_scalar_rgb": ("per vertex, closed box: fluo_qd / roughconductor, scalar_rgb", 1.25,
                               lambda a: vertex_row("scalar_rgb", "qd", a.res, a.spp, a.rounds)),
    "vertex_jung_llvm_ad_spectral": ("per vertex, closed box: fluo_jung / diffuse, llvm_ad_spectral", 1.25, lambda a: in_worker("vertex_jung_llvm_ad_spectral", a)),
    "vertex_matrix_llvm_ad_spectral": ("per vertex, closed box: fluo_matrix / diffuse, llvm_ad_spectral", 1.25, lambda a: in_worker("vertex_matrix_llvm_ad_spectral", a)),
    "vertex_gmm_llvm_ad_spectral": ("per vertex, closed box: fluo_gmm / diffuse, llvm_ad_spectral", 1.25, lambda a: in_worker("vertex_gmm_llvm_ad_spectral", a)),
    "vertex_qd_llvm_ad_spectral": ("per vertex, closed box: fluo_qd / roughconductor, llvm_ad_spectral", 1.25, lambda a: in_worker("vertex_qd_llvm_ad_spectral", a)),
    "vertex_jung_llvm_ad_rgb": ("per vertex, closed box: fluo_jung / diffuse, llvm_ad_rgb", 1.25, lambda a: in_worker("vertex_jung_llvm_ad_rgb", a)),
    "vertex_matrix_llvm_ad_rgb": ("per vertex, closed box: fluo_matrix / diffuse, llvm_ad_rgb", 1.25, lambda a: in_worker("vertex_matrix_llvm_ad_rgb", a)),
    "vertex_gmm_llvm_ad_rgb": ("per vertex, closed box: fluo_gmm / diffuse, llvm_ad_rgb", 1.25, lambda a: in_worker("vertex_gmm_llvm_ad_rgb", a)),
    "vertex_qd_llvm_ad_rgb": ("per vertex, closed box: fluo_qd / roughconductor, llvm_ad_rgb", 1.25, lambda a: in_worker("vertex_qd_llvm_ad_rgb", a)),
    "vertex_auto_scalar_rgb": ("per vertex, closed box: basis auto / x7 (fluo_jung), scalar_rgb", 1.05,
                               lambda a: basis_row("scalar_rgb", a.res, a.spp * BASIS_SPP_FACTOR, a.rounds)),
    "vertex_auto_llvm_ad_rgb": ("per vertex, closed box: basis auto / x7 (fluo_jung), llvm_ad_rgb", 1.05,
                                lambda a: in_worker("vertex_auto_llvm_ad_rgb", a)),
    "load": (f"load: {COLOURED} coloured fluo_jung / diffuse (ms, MB per material)", 0.2,
             lambda a: load_row(a.res, a.rounds)),
    "llvm_plain": ("llvm: no fluorescence: fluo_path / path, plain box (llvm_ad_spectral)", 1.05,
                   lambda a: in_worker("llvm_plain", a)),
    "llvm_plain_rgb": ("llvm: no fluorescence: fluo_path / path, plain box (llvm_ad_rgb)", 1.05,
                       lambda a: in_worker("llvm_plain_rgb", a)),
    "llvm_jung": ("llvm: fluorescent box: fluo_path / path (dyes removed), llvm_ad_spectral", 1.5,
                  lambda a: in_worker("llvm_jung", a)),
    "llvm_reduced": ("llvm: reduced RGB x7 / path (dyes removed), llvm_ad_rgb", 1.5,
                     lambda a: in_worker("llvm_reduced", a)),
    "llvm_matrix": ("llvm: measured matrix box: fluo_path / path (diffuse), llvm_ad_spectral", 1.5,
                    lambda a: in_worker("llvm_matrix", a)),
    "llvm_gmm": ("llvm: Gaussian-mixture box: fluo_path / path (diffuse), llvm_ad_spectral", 1.5,
                 lambda a: in_worker("llvm_gmm", a)),
    "llvm_matrix_rgb": ("llvm: measured matrix box, reduced x7 / path (diffuse), llvm_ad_rgb", 1.5,
                        lambda a: in_worker("llvm_matrix_rgb", a)),
    "llvm_qd": ("llvm: quantum-dot box: fluo_path fluo_qd / path roughconductor, llvm_ad_spectral", 1.5,
                lambda a: in_worker("llvm_qd", a)),
    "llvm_qd_rgb": ("llvm: quantum-dot box, reduced x7 / path roughconductor, llvm_ad_rgb", 1.5,
                    lambda a: in_worker("llvm_qd_rgb", a)),
    "llvm_textured": ("llvm: textured / uniform fluo_jung (concentration, emission_peak), llvm_ad_spectral", 1.30,
                      lambda a: in_worker("llvm_textured", a)),
    "llvm_textured_qd": ("llvm: textured / uniform fluo_qd (radius, density), llvm_ad_spectral", 1.5,
                         lambda a: in_worker("llvm_textured_qd", a)),
    "llvm_textured_qd_rgb": ("llvm: textured / uniform fluo_qd (radius, density), reduced x7, llvm_ad_rgb", 1.5,
                             lambda a: in_worker("llvm_textured_qd_rgb", a)),
    "llvm_volpath_plain": ("llvm: no fluorescence: fluo_volpath / volpath, homogeneous medium (llvm_ad_spectral)",
                           1.05, lambda a: in_worker("llvm_volpath_plain", a)),
    "llvm_volpath_qd": ("llvm: QD cuvette: fluo_volpath (Q 0.8) / volpath (Q 0), llvm_ad_spectral", None,
                        lambda a: in_worker("llvm_volpath_qd", a)),
    "llvm_volpath_qd_rgb": ("llvm: QD cuvette: fluo_volpath x7 (Q 0.8) / volpath (Q 0), llvm_ad_rgb", None,
                            lambda a: in_worker("llvm_volpath_qd_rgb", a)),
    **{f"llvm_many_{m}{'_rgb' if v.endswith('rgb') else ''}":
       (f"llvm: {MANY} distinct {'fluo_jung dyes' if m == 'jung' else 'fluo_qd coatings'} / {MANY} "
        f"{'diffuse' if m == 'jung' else 'roughconductor'}: load + first render (compile), {v}", 2.0,
        lambda a, v=v, m=m: many_row(a, v, m))
       for m in ("jung", "qd") for v in ("llvm_ad_spectral", "llvm_ad_rgb")},
    "llvm_backward_memory": ("llvm: backward pass peak memory, fluo_prb / AD through fluo_path (fluo_jung box, "
                             "256², 64 spp, max_depth 8), llvm_ad_spectral", 0.5,
                             lambda a: backward_row(a, "llvm_ad_spectral")),
    "llvm_backward_memory_rgb": ("llvm: backward pass peak memory, fluo_prb / AD through fluo_path (fluo_jung box, "
                                 "256², 64 spp, max_depth 8), llvm_ad_rgb (reduced transport)", 0.5,
                                 lambda a: backward_row(a, "llvm_ad_rgb")),
    "llvm_backward_memory_volume": ("llvm: backward pass peak memory, fluo_prbvolpath / AD through fluo_volpath "
                                    "(QD cuvette, Q 0.8, 32², 32 spp, max_depth 8: recorded, 64² x 64 spp exceeds 24 GB), "
                                    "llvm_ad_spectral", 0.5,
                                    lambda a: backward_row(a, "llvm_ad_spectral",
                                                           ("fluo_prbvolpath", "fluo_volpath", "prbvolpath"))),
    "llvm_backward_memory_volume_rgb": ("llvm: backward pass peak memory, fluo_prbvolpath / AD through fluo_volpath "
                                        "(QD cuvette, Q 0.8, 32², 32 spp, max_depth 8), "
                                        "llvm_ad_rgb (reduced transport)", 0.5,
                                        lambda a: backward_row(a, "llvm_ad_rgb",
                                                               ("fluo_prbvolpath", "fluo_volpath", "prbvolpath"))),
    "llvm_speedup": ("speed-up: scalar_spectral / llvm_ad_spectral fluo_path, fluorescent box", None,
                     lambda a: speedup_row(a, "spectral")),
    "llvm_speedup_rgb": ("speed-up: scalar_rgb / llvm_ad_rgb fluo_path x7, fluorescent box", None,
                         lambda a: speedup_row(a, "rgb")),
}


BEGIN, END = "<!-- costs:begin", "<!-- costs:end -->"


def readme_region(run: dict, source: str) -> str:
    """The README region of a saved run: header line and one table row per result."""
    lines = [f"{BEGIN} (generated by benches/bench_costs.py --readme {source}; do not edit) -->",
             f"Measured by `benches/bench_costs.py` ({run['machine']}, {run['res']}x{run['res']}, "
             f"{run['spp']} spp, median of {run['rounds']} paired rounds, [min-max]):", "",
             "| row | measured | target |", "|---|---|---|"]
    for r in run["results"]:
        if r["row"] == "load":
            got = f"+{r['per_material_ms']:.2f} ms, +{r['per_material_mb']:.2f} MB per material"
            target = f"≤ {r['target']} ms"
        else:
            got = f"{r['ratio']:.2f} [{r['min']:.2f}-{r['max']:.2f}]"
            target = f"≤ {r['target']:.2f}" if r["target"] is not None else "reported"
            if "compile_s" in r:
                got += f" (kernel compile {max(0.0, r['compile_s']):.1f} s)"
            if "memory_ratio" in r:
                got += (f" ({r['a_s']:.1f} s vs {r['b_s']:.1f} s; peak memory {r['a_mb']:.0f} / {r['b_mb']:.0f} MB "
                        f"= {r['memory_ratio']:.2f}, target ≤ 2)")
            if "native_ratio" in r:
                got += (f" ({r['a_mb']:.0f} / {r['b_mb']:.0f} MB, {r['a_s']:.1f} s vs {r['b_s']:.1f} s; over Mitsuba's "
                        f"{r.get('native_label', 'prb with diffuse walls')} {r['native_mb']:.0f} MB: "
                        f"{r['native_ratio']:.2f}, target ≤ 1.5)")
        lines.append(f"| {r['label']} | {got} | {target} |")
    return "\n".join(lines + [END]) + "\n"


def write_readme(saved: Path, readme: Path) -> None:
    text = readme.read_text()
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise SystemExit(f"{readme} has no {BEGIN} ... {END} region")
    try:
        source = saved.resolve().relative_to(REPO).as_posix()
    except ValueError:
        source = str(saved)
    rest = text[end + len(END):]
    region = readme_region(json.loads(saved.read_text()), source)
    readme.write_text(text[:start] + region + (rest[1:] if rest.startswith("\n") else rest))


def jit_row(key: str) -> bool:
    """Whether a row runs in a JIT variant (so on the backend --backend names)."""
    return key.startswith("llvm_") or (key.startswith("vertex_") and "_llvm_" in key)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--rows", default=",".join(ROWS),
                    help=f"comma-separated subset of {', '.join(ROWS)}")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--readme", type=Path, metavar="SAVED_JSON",
                    help="rewrite README.md's costs region from a saved --json run (measures nothing)")
    ap.add_argument("--merge", type=Path, metavar="SAVED_JSON",
                    help="measure --rows and replace (or add) them in a saved --json run, same settings")
    ap.add_argument("--backend", choices=("llvm", "cuda"), default="llvm",
                    help="JIT backend of the llvm_* rows (cuda: on a machine with an NVIDIA GPU)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    a = ap.parse_args()
    global JIT_BACKEND
    JIT_BACKEND = a.backend
    if a.backend != "llvm":
        if any(not jit_row(key) for key in a.rows.split(",")) and not a.worker:
            ap.error("--backend cuda runs the JIT rows only (llvm_*, vertex_*_llvm_*): name them with --rows")
        ROWS.update({k: (v[0].replace("llvm", a.backend), *v[1:]) for k, v in ROWS.items() if jit_row(k)})
    if a.worker:
        mi.set_log_level(mi.LogLevel.Error)
        print("RESULT " + json.dumps(WORKER_ROWS[a.worker](a)))
        return
    if a.merge:
        saved = json.loads(a.merge.read_text())
        a.spp, a.res, a.rounds, a.json = saved["spp"], saved["res"], saved["rounds"], True
    if a.readme:
        write_readme(a.readme, REPO / "README.md")
        return
    if a.json:  # Mitsuba logs to stdout: keep the JSON clean (the row "jung" warns by design)
        mi.set_log_level(mi.LogLevel.Error)
    if a.rounds < 5:
        ap.error("--rounds must be at least 5 (median of paired rounds)")
    results = []
    for key in a.rows.split(","):
        label, target, run = ROWS[key]
        r = run(a)
        results.append({"row": key, "label": label, "target": target, **r})
        if not a.json:
            if key == "load":
                print(f"{label:70s} +{r['per_material_ms']:.2f} ms, +{r['per_material_mb']:.2f} MB "
                      f"(target <= {target} ms; load ratio {r['ratio']:.2f})", flush=True)
            else:
                goal = f"target <= {target:.2f}" if target is not None else "reported"
                extra = f", kernel compile {max(0.0, r['compile_s']):.1f} s" if "compile_s" in r else ""
                if "memory_ratio" in r:
                    extra += f", {r['a_s']:.1f} s vs {r['b_s']:.1f} s, peak memory x{r['memory_ratio']:.2f}"
                if "native_ratio" in r:
                    extra += (f", {r['a_mb']:.0f} / {r['b_mb']:.0f} MB; over Mitsuba's "
                              f"{r.get('native_label', 'prb')} ({r['native_mb']:.0f} MB) x{r['native_ratio']:.2f}")
                print(f"{label:70s} {r['ratio']:.2f} [{r['min']:.2f}-{r['max']:.2f}] ({goal}{extra})", flush=True)
    if a.merge:
        fresh = {r["row"]: r for r in results}
        merged = [fresh.pop(r["row"], r) for r in saved["results"] if r["row"] in ROWS]
        saved["results"] = sorted(merged + list(fresh.values()), key=lambda r: list(ROWS).index(r["row"]))
        a.merge.write_text(json.dumps(saved) + "\n")
        print(f"merged {', '.join(r['row'] for r in results)} into {a.merge}")
    elif a.json:
        print(json.dumps({"machine": platform.machine(), "spp": a.spp, "res": a.res, "rounds": a.rounds,
                          "results": results}))


if __name__ == "__main__":
    main()
