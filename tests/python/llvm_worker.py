"""Render jobs in an llvm variant in a fresh process, for the tests (not a test module).

Mitsuba 3.8 cannot load a scene in an llvm variant in a process that has rendered in a
scalar variant ("jit_assemble(): variable ... scheduled in wrong ThreadState", with
Mitsuba's own plugins alone), and pytest renders scalar scenes first; so tests hand their
llvm renders to this script: ``python llvm_worker.py '<json list of jobs>'``. A job is
``{"variant", "xml" (scene text) or "file" (path), "params" (substitutions), "spp",
"seed", "integrator" (optional: replaces the scene's integrator by this plugin name)}``,
or ``{"variant", "bsdf" (a plugin dict), "points": [[wi, wo, wavelengths], ...]}`` to
evaluate a BSDF (``eval``, f·cos θo) at given directions and hero wavelengths, or
``{"variant", "xml", "spp", "seed", "gradients": {parameter key: step}}`` for the
derivative of the image mean by automatic differentiation and by central differences
(same seed) for each parameter of ``mi.traverse`` (``"ad_only": true``: AD alone;
``"relative": true``: along the parameter's own values; ``"span": [i, j]``: and only on its
entries i to j − 1), or ``{"variant", "load": a plugin
dict}`` to instantiate one plugin (an error says why it cannot be), or ``{"variant",
"traverse": a plugin dict}`` for the keys ``mi.traverse`` lists (and which are differentiable).
It prints one line ``RESULT <json>``: per job the image's per-channel mean, the
per-pixel image (``"image": true`` in the job), the BSDF values, or the error message.
"""

from __future__ import annotations

import json
import sys

import mitsuba as mi
import numpy as np


def run(job: dict) -> dict:
    mi.set_variant(job["variant"])
    import fluo  # noqa: F401  (registers the plugins)

    if "bsdf" in job:
        return {"values": eval_bsdf(mi.load_dict(job["bsdf"]), job["points"])}
    if "load" in job:
        mi.load_dict(job["load"])
        return {"loaded": True}
    if "traverse" in job:
        params = mi.traverse(mi.load_dict(job["traverse"]))
        differentiable = [k for k in params.keys() if not params.flags(k) & mi.ParamFlags.NonDifferentiable]
        return {"keys": list(params.keys()), "differentiable": differentiable}
    if "gradients" in job:
        return {"gradients": gradients(mi.load_string(job["xml"]), job["gradients"], job["spp"], job.get("seed", 0),
                                       job.get("forward", False), job.get("ad_only", False),
                                       job.get("relative", False), job.get("span"), job.get("fd_spp"))}
    params = job.get("params", {})
    if "xml" in job:
        scene = mi.load_string(job["xml"], **params)
    else:
        scene = mi.load_file(job["file"], **params)
    kwargs = {}
    if "integrator" in job:
        kwargs["integrator"] = mi.load_dict({"type": job["integrator"], "max_depth": job.get("max_depth", 6)})
    img = np.array(mi.render(scene, spp=job["spp"], seed=job.get("seed", 0), **kwargs), dtype=np.float64)
    out = {"mean": img.mean(axis=(0, 1)).tolist(), "finite": bool(np.isfinite(img).all())}
    if job.get("image"):
        out["image"] = img.tolist()
    return out


def eval_bsdf(bsdf, points) -> list:
    """bsdf.eval at each (wi, wo, wavelengths) point (local frame, uv = 0.5)."""
    out = []
    for wi, wo, wavelengths in points:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*wi)
        si.uv = mi.Point2f(0.5, 0.5)
        if mi.is_spectral:
            si.wavelengths = type(si.wavelengths)(*wavelengths)
        value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo))
        out.append([float(v) for v in np.array(value).ravel()])
    return out


def gradients(scene, steps: dict, spp: int, seed: int, forward: bool = False, ad_only: bool = False,
              relative: bool = False, span: list | None = None, fd_spp: int | None = None) -> dict:
    """{key: [AD derivative, central difference]} of the mean image for each parameter, along
    the parameter's all-ones direction (every channel of a colour moves together; with
    `relative`, along its own values: x·(1 + t), so zero entries stay zero; `span` [i, j):
    only entries i to j − 1 move); with
    `forward`, the forward difference (a parameter at the lower end of its range); with
    `ad_only`, [AD derivative, None]; `fd_spp`: the differences' sample count (primal renders
    cost no AD memory: where the two renders decorrelate, as media's moving majorants make
    them, more samples there rather than in the AD pass)."""
    import drjit as dr

    params = mi.traverse(scene)
    out = {}
    for key, h in steps.items():
        x0 = type(params[key])(params[key])
        tensor = dr.is_tensor_v(x0)  # (a grid's voxels: moved through its flat array)
        flat = x0.array if tensor else x0
        direction = flat if relative else 1.0
        if span is not None:
            at = dr.arange(mi.UInt32, dr.width(flat))
            direction = dr.select((at >= span[0]) & (at < span[1]), direction, 0.0)

        def moved(d):  # x0 + direction·d, as the parameter's own type
            value = flat + direction * d
            return type(x0)(value, x0.shape) if tensor else value
        t = mi.Float(0.0)
        dr.enable_grad(t)
        params[key] = moved(t)
        params.update()
        loss = dr.mean(mi.render(scene, params=params, spp=spp, seed=seed), axis=None)
        try:
            dr.backward(loss)
            ad = float(dr.grad(t)[0])
        except RuntimeError as err:  # the image does not depend on it through differentiable code
            if "does not depend on the input variable" not in str(err):
                raise
            ad = 0.0
        if ad_only:
            out[key] = [ad, None]
            continue
        values = []
        for d in ((0.0, h) if forward else (-h, h)):
            params[key] = moved(d)
            params.update()
            values.append(float(dr.mean(mi.render(scene, params=params, spp=fd_spp or spp, seed=seed),
                                        axis=None).array[0]))
        params[key] = x0
        params.update()
        out[key] = [ad, (values[1] - values[0]) / (h if forward else 2 * h)]
    return out


def main() -> None:
    results = []
    for job in json.loads(sys.argv[1]):
        try:
            results.append(run(job))
        except Exception as err:  # reported to the test, which decides (with its causes:
            text, cause = str(err), err.__cause__  # render errors are chained by Dr.Jit)
            while cause is not None:
                text, cause = f"{text}\ncaused by: {cause}", cause.__cause__
            results.append({"error": text})
    print("RESULT " + json.dumps(results))


if __name__ == "__main__":
    main()
