"""fluo_prbvolpath: fluo_volpath with path replay for reverse-mode gradients (fluo_volpath.cpp's
docs).

References: its primal is fluo_volpath's (the same loop and random numbers: equal images);
its derivatives equal those of AD through fluo_volpath's recorded loop where both trace the
same events (roulette off: both sample media without gradients and weigh each event by its
coefficients with them), and central finite differences of the image mean (same seed) for a
native homogeneous medium's extinction, whose derivative AD through Mitsuba's volpath (and
fluo_volpath's loop before the detached sampling) gets wrong. The media parameters' own
finite-difference checks are test_fluo_volpath.py's test08 (recorded loop). In RGB the
replay's continuations are checked against the recorded loop (grey medium) and central
differences (fluorescent medium: a surface's parameters, test06, and its own, test07). The AD variants run in a fresh process (llvm_worker.py).
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest
from conftest import VARIANTS
from test_fluo_prb import JUNG, box, check, compare_replay, run_worker
from test_fluo_volpath import _MEDIA_GRADIENT_SCENE, _qd_medium_xml

MEDIUM = "box.interior_medium."
NO_RR = ('<integer name="max_depth" value="8"/>', '<integer name="max_depth" value="8"/><integer name="rr_depth" value="100"/>')
#: A grey homogeneous medium with a forward-scattering phase function (Mitsuba's own plugins).
NATIVE = ('<medium type="homogeneous" name="interior"><rgb name="albedo" value="0.7"/>'
          '<float name="sigma_t" value="1.0"/><phase type="hg"><float name="g" value="0.3"/></phase></medium>')
DYE = ('<medium type="fluo_dye_medium" name="interior"><float name="sigma_a" value="30"/>'
       '<float name="quantum_yield" value="0.5"/><float name="emission_peak" value="560"/>'
       '<float name="stokes_shift" value="60"/><float name="scale" value="0.01"/><phase type="isotropic"/></medium>')


def cube(integrator: str, medium: str, res: int = 16) -> str:
    """test08's scene (a 2 cm cube of `medium` before a D65 panel) rendered by `integrator`."""
    xml = _MEDIA_GRADIENT_SCENE.format(basis="", medium=medium, res=res, film="")
    return xml.replace('type="fluo_volpath"', f'type="{integrator}"')


@pytest.mark.parametrize("variant", VARIANTS)
def test01_primal_is_fluo_volpath(variant):
    """fluo_prbvolpath renders what fluo_volpath renders (the same class and loop): a
    fluorescent medium (Q = 0.8) and a fluorescent surface in a box."""
    mi.set_variant(variant)
    for scene in ((lambda i: cube(i, _qd_medium_xml(0.8), res=8)), (lambda i: box(i, JUNG))):
        images = [np.array(mi.render(mi.load_string(scene(i)), spp=8, seed=5))
                  for i in ("fluo_prbvolpath", "fluo_volpath")]
        assert images[0].mean() > 0.01
        np.testing.assert_allclose(images[0], images[1], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("variant", VARIANTS)
def test02_polarized_variants_refuse_it(variant):
    """The polarized variant of this family refuses fluo_prbvolpath, naming fluo_volpath."""
    mi.set_variant(variant.replace("_rgb", "_spectral") + "_polarized")
    mi.load_dict({"type": "fluo_volpath"})
    with pytest.raises(Exception, match=r"fluo_prbvolpath: path replay is not available in the polarized"
                                        r".*fluo_volpath"):
        mi.load_dict({"type": "fluo_prbvolpath"})


def test03_replay_equals_the_recorded_loop():
    """llvm_ad_spectral, roulette off, 64 spp: the replay's derivatives equal the recorded
    loop's to 1e-4 relative (measured: at most 5e-6) for a fluorescent medium's amount and
    spectrum (fluo_qd_medium: concentration, radius; fluo_dye_medium: emission_peak; spectral
    tracking, shifts, shadow rays through it), a native homogeneous medium's extinction, and
    a fluorescent surface's and a grey wall's parameters in a box."""
    cases = [(_qd_medium_xml(0.8), {"concentration": 0, "radius": 0}), (DYE, {"emission_peak": 0}),
             (NATIVE, {"sigma_t.value.value": 0})]
    jobs = []
    for medium, keys in cases:
        for integrator in ("fluo_prbvolpath", "fluo_volpath"):
            jobs.append({"variant": "llvm_ad_spectral", "xml": cube(integrator, medium).replace(*NO_RR),
                         "spp": 64, "seed": 3, "gradients": {MEDIUM + k: v for k, v in keys.items()},
                         "ad_only": True})
    surface = box("fluo_volpath", JUNG).replace('<integer name="rr_depth" value="3"/>',
                                                '<integer name="rr_depth" value="9"/>')
    for integrator in ("fluo_prbvolpath", "fluo_volpath"):
        jobs.append({"variant": "llvm_ad_spectral", "xml": surface.replace('"fluo_volpath"', f'"{integrator}"'),
                     "spp": 64, "seed": 3, "ad_only": True,
                     "gradients": {"dye.concentration": 0, "wall.reflectance.value": 0}})
    compare_replay(jobs, rel=1e-4)


def test04_native_extinction_and_phase_match_finite_differences():
    """d(mean image)/dσt of a homogeneous medium (τ = 2 across the cube) and d/dg of its
    Henyey-Greenstein phase function within 10 % of central differences: through
    fluo_prbvolpath (llvm_ad_spectral, llvm_ad_rgb) and through fluo_volpath's recorded loop
    (llvm_ad_rgb). Measured: σt spectral −0.2053 against −0.2085, RGB recorded −0.2050 and
    replayed −0.2051 against −0.2082; g 0.0596 against 0.0606, 0.0597 and 0.0598 against
    0.0605. Before: σt with fluo_volpath sampling collisions with the derivative's motion
    −0.0089 and −0.0096 (Mitsuba's volpath −0.0189); g through the recorded loop, the phase
    function sampled with gradients (HG's sampled weight is 1), 0.0213."""
    jobs = [{"variant": variant, "xml": cube(integrator, NATIVE), "spp": 512, "fd_spp": 4096, "seed": 3,
             "gradients": {MEDIUM + "sigma_t.value.value": 0.05, MEDIUM + "phase_function.g": 0.05}}
            for variant, integrator in (("llvm_ad_spectral", "fluo_prbvolpath"), ("llvm_ad_rgb", "fluo_volpath"),
                                        ("llvm_ad_rgb", "fluo_prbvolpath"))]
    check(run_worker(jobs)[0], jobs)


def foggy(integrator: str, medium: str) -> str:
    """test_fluo_prb's box (fluo_jung sphere, grey walls, D65 sky, 365 nm lamp, roulette off)
    with a 0.8-unit cube of `medium` between the sphere and the camera's left."""
    cube_ = ('<shape type="cube" id="fog"><transform name="to_world"><scale value="0.4"/>'
             f'<translate x="-0.95" y="0.1" z="1.0"/></transform><bsdf type="null"/>{medium}</shape>')
    xml = box(integrator, JUNG).replace('<integer name="rr_depth" value="3"/>', '<integer name="rr_depth" value="9"/>')
    return xml.replace("</scene>", cube_ + "</scene>")


def test05_rgb_replay_equals_the_recorded_loop():
    """llvm_ad_rgb, roulette off, 32 spp: the replay (each iteration's radiance still to come
    from continuations carrying the identity's rows, as fluo_prb's; a next-event estimate's
    K coefficients T·c from continuations of its shadow ray) and AD through fluo_volpath's
    recorded loop give the same derivatives to 1e-4 relative for the dye's amount and shape,
    the walls' reflectance and the medium's σt (the shadow rays' steps from continuations
    of each ray per unit of its transmittance; measured −0.00334271789 vs −0.00334271765),
    in a box whose light crosses a grey homogeneous medium (its null/real choices do not
    depend on the throughput: the continuations follow the path's own events)."""
    jobs = [{"variant": "llvm_ad_rgb", "xml": foggy(integrator, NATIVE),
             "spp": 32, "seed": 3, "ad_only": True,
             "gradients": {"dye.concentration": 0, "dye.emission_peak": 0, "wall.reflectance.value": 0,
                           "fog.interior_medium.sigma_t.value.value": 0}}
            for integrator in ("fluo_prbvolpath", "fluo_volpath")]
    compare_replay(jobs, rel=1e-4)


def test06_rgb_replay_through_a_fluorescent_medium_matches_finite_differences():
    """llvm_ad_rgb: the replay through a fluorescent medium (fluo_qd_medium, Q = 0.8: band
    tracking, whose null/real choices follow the matrix throughput, so continuations draw
    their own, equally valid, events; shadow rays multiply its 3xK operators) gives the
    dye's and the walls' derivatives within 10 % of central differences (AD 256 spp,
    differences 2048)."""
    jobs = [{"variant": "llvm_ad_rgb", "xml": foggy("fluo_prbvolpath", _qd_medium_xml(0.8)), "spp": 256,
             "fd_spp": 2048, "seed": 3, "gradients": {"dye.concentration": 0.1, "wall.reflectance.value": 0.05}}]
    check(run_worker(jobs)[0], jobs)


def test07_rgb_replay_of_a_fluorescent_medium_matches_finite_differences():
    """llvm_ad_rgb (basis x7): the replay of fluo_qd_medium's own parameters (concentration,
    a constant density, the host's σs, the radius: the reduced operators' weights along the
    path, and each shadow ray's steps through the medium from continuations of the ray per
    unit of its transmittance and of its 3×K operator) within 10 % of central differences
    (test_fluo_volpath.py test08's scene and steps; AD 512 spp, differences 2048). Measured:
    concentration −0.862 vs −0.911, density −0.0431 vs −0.0455, σs −0.00439 vs −0.00449,
    radius −0.204 vs −0.203 (the recorded loop's, test08: −0.861, −0.0431, −0.00439,
    −0.205)."""
    steps = {MEDIUM + "concentration": 0.0025, MEDIUM + "density.value.value": 0.05,
             MEDIUM + "sigma_s.value.value": 1.0, MEDIUM + "radius": 0.02}
    xml = _MEDIA_GRADIENT_SCENE.format(basis='<string name="basis" value="x7"/>', medium=_qd_medium_xml(0.8),
                                       res=16, film="")
    jobs = [{"variant": "llvm_ad_rgb", "spp": 512, "fd_spp": 2048, "seed": 1, "gradients": steps,
             "xml": xml.replace('type="fluo_volpath"', 'type="fluo_prbvolpath"')}]
    check(run_worker(jobs)[0], jobs)


def test08_mask_opacity_replayed_and_recorded():
    """A mask's opacity (Mitsuba's `mask` around a white diffuse panel before the sphere):
    the lobe choice's derivative (the sampled weight does not depend on the opacity: the
    value's at the detached direction, the null transmission's past the null lobe) and,
    through fluo_volpath, the shadow rays' null transmission 1 − opacity (once). The replay
    equals the recorded loop (fluo_prb / fluo_path, fluo_prbvolpath / fluo_volpath) to 1e-4
    in both AD variants and is within 10 % of central differences (steps of 0.2: the image is
    nearly linear in the opacity; AD 512 spp, differences 4096). Measured (RGB): fluo_prb
    0.1600 against 0.1600, fluo_prbvolpath 0.1536 against 0.1533 (fluo_path's shadow rays
    stop at the mask, as Mitsuba's path's). Before, with a small panel behind a grey medium,
    fluo_volpath's recorded loop gave 0.00074 against 0.00177 (the choice not
    differentiated, the null transmission's derivative twice) and the RGB replay refused
    to replay it."""
    panel = ('<shape type="rectangle" id="panel"><transform name="to_world"><scale value="0.8"/>'
             '<translate x="0" y="0.2" z="1.5"/></transform><bsdf type="mask"><float name="opacity" value="0.5"/>'
             '<bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></bsdf></shape></scene>')
    scene = box("fluo_path", JUNG).replace('<integer name="rr_depth" value="3"/>',
                                           '<integer name="rr_depth" value="9"/>').replace("</scene>", panel)
    jobs = []
    for variant in ("llvm_ad_rgb", "llvm_ad_spectral"):
        for replay, recorded in (("fluo_prb", "fluo_path"), ("fluo_prbvolpath", "fluo_volpath")):
            for integrator in (replay, recorded):
                job = {"variant": variant, "xml": scene.replace('"fluo_path"', f'"{integrator}"'), "spp": 512,
                       "seed": 3, "gradients": {"panel.bsdf.opacity.value": 0.2}}
                job.update({"fd_spp": 4096} if integrator == replay else {"ad_only": True})
                jobs.append(job)
    results, _ = run_worker(jobs)
    for i in range(0, len(jobs), 2):
        (ad, fd), (ref, _) = (results[i + j]["gradients"]["panel.bsdf.opacity.value"] for j in (0, 1))
        print(jobs[i]["variant"], jobs[i]["xml"][:0], "replay", ad, "recorded", ref, "differences", fd)
        assert ad == pytest.approx(ref, rel=1e-4) and abs(ad - fd) <= 0.1 * abs(fd), (jobs[i]["variant"], ad, ref, fd)
