"""Compile a study's numba kernels once, on a tiny copy of one of its cases, before its jobs need them.

Every numba kernel of lfstudy is cached on disk (``cache=True``), so only a fresh clone, or one whose
code changed, compiles. But a study's jobs start side by side: on 2 cores the demo's first two IPR fits
each compiled the same kernels, 78-82 s apiece against 30-35 s warm (README command 1 on a fresh clone).
The Snakefile's ``warm`` job runs :func:`warm_kernels` first, with a high priority, while the other core
renders and registers the first images; every reconstruction that has yet to run waits for it and then
loads the kernels from the cache.

The tiny case is the study's own case (its camera, reconstruction and PIV settings: the kernels' type
signatures come from the same code paths and dtypes) cut to a few lenslets, so that it runs in a few seconds
once compiled. Spots at the lenslet centres (:func:`lfstudy.lightfield.calibrate.synthetic_pinhole`) stand for
its images: the reconstruction's kernels compile on any image, and the renderers' are left to the study's own
first render jobs, which run beside this one (rendering here too compiled them twice, 9-10 s each). Its numbers
are thrown away.
"""

from __future__ import annotations

import copy
import math
import time
import traceback
from collections.abc import Mapping
from typing import Any

__all__ = ["tiny_case", "warm_kernels"]

#: Lenslets along each side of the tiny sensor: the PIV's windows of 8 voxels fit it.
LENSLETS = 8


def tiny_case(ccfg: Mapping[str, Any], lenslets: int = LENSLETS) -> dict[str, Any]:
    """A copy of a case config whose sensor holds ``lenslets`` x ``lenslets`` lenslets.

    The optics and the processing settings are the case's; the PIV's windows become 8 voxels (4 at the finest
    of two levels, 50 % overlap), the smallest a tiny volume holds.

    Parameters
    ----------
    ccfg : mapping
        A full case config (:func:`lfstudy.study.config.case_config`).
    lenslets : int
        Lenslets along each side of the sensor (>= 4).

    Returns
    -------
    dict
        The tiny case's config.
    """
    if lenslets < 4:
        raise ValueError(f"tiny_case: `lenslets` must be >= 4; got {lenslets}")
    t = copy.deepcopy(dict(ccfg))
    sensor, lenslet = t["camera"]["sensor"], t["camera"]["lenslet"]
    px = math.ceil(float(lenslet["pitch"]) / float(sensor["pixel_pitch"]))
    sensor["n_pixels_x"] = sensor["n_pixels_y"] = lenslets * px
    t["piv"].update(window=[8, 8, 8], spacing=[4, 4, 4], levels=2)
    return t


def warm_kernels(ccfg: Mapping[str, Any], lenslets: int = LENSLETS) -> dict[str, Any]:
    """Run a tiny copy of a case through the stages after the rendering, to compile their numba kernels.

    Calibrates, registers, refocuses and reconstructs both frames of a synthetic image (spots at the lenslet
    centres) and runs the PIV (with the particle pairing where ``piv.particles`` asks for it), each with the
    case's settings. A stage that fails ends the warm-up without raising: warming only saves time, and the
    study's own job then reports the problem where it belongs.

    Parameters
    ----------
    ccfg : mapping
        A full case config (:func:`lfstudy.study.config.case_config`).
    lenslets : int
        Lenslets along each side of the tiny sensor.

    Returns
    -------
    dict
        ``seconds``: per stage, the time it took (compile included); ``error``: the traceback of the
        stage that failed, or None.
    """
    from lfstudy.lightfield.calibrate import find_lenslet_centers, synthetic_pinhole
    from lfstudy.lightfield.registration import register
    from lfstudy.piv.ptv import PARTICLE_MODES
    from lfstudy.study import case as cl

    seconds: dict[str, float] = {}
    t0 = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal t0
        now = time.perf_counter()
        seconds[stage] = round(now - t0, 2)
        t0 = now

    try:
        t = tiny_case(ccfg, lenslets)
        cam = cl.case_camera(t)
        # Spots at the lenslet centres stand for the pinhole image and both exposures: the reconstruction's
        # kernels compile on any image, and the renderers' are not compiled here (the study's first pinhole
        # and simulate jobs compile them, side by side with this one, instead of both doing it).
        sim = {"pinhole": synthetic_pinhole(cam, seed=1)}
        for f, seed in (("a", 2), ("b", 3)):
            sim[f"image_{f}"] = synthetic_pinhole(cam, sigma_px=1.2, read_noise=0.0, seed=seed)
        lap("images")
        centers = find_lenslet_centers(sim["pinhole"], cam)
        lap("calibrate")
        if t["refocus"].get("model", "thin_lens") == "volumetric":
            return {"seconds": seconds, "error": None}  # its calibration is a stage of its own (volcal)
        out = {}
        for f in "ab":
            lf = register(sim[f"image_{f}"], centers, cam)
            lap(f"register_{f}")
            stack = cl.case_stack(t, lf).load()
            lap(f"refocus_{f}")
            out[f] = cl.case_reconstruction(t, stack, lf, centers)
            lap(f"reconstruct_{f}")
        (va, pa), (vb, pb) = out["a"], out["b"]
        res = cl.case_piv(t, va, vb)
        lap("piv")
        mode = t["piv"].get("particles", "none")
        if mode in PARTICLE_MODES and pa is not None:
            cl.case_tracked_piv(t, res, va, vb, pa, pb)
            lap(mode)
    except Exception:  # warming is an optimisation: the stage's own job reports the failure
        return {"seconds": seconds, "error": traceback.format_exc()}
    return {"seconds": seconds, "error": None}
