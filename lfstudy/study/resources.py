"""What a case needs: peak memory per stage, estimated from its config, against the machine's.

The estimates are the stages' own large arrays (image buffers, light field, volumes,
weight tables, correlation batches), rounded up; the interpreter and libraries add
about 0.3 GB per process. The reconstruction's comes from its method's class
(:meth:`lfstudy.reconstruct.ReconstructionMethod.memory_bytes`), so a plugin method
states its own. :func:`check_memory` turns a case that cannot fit into one
clear config error before anything runs, instead of an out-of-memory kill hours into
a study.
:func:`job_mem_mb` gives the same estimate to the workflow as each rule's Snakemake
``mem_mb`` resource, so neither the local scheduler nor SLURM runs more of them side
by side than the memory holds.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Any

from lfstudy.config import ConfigError

__all__ = [
    "machine_memory",
    "case_memory",
    "check_memory",
    "job_mem_mb",
    "job_runtime_min",
    "reconstruct_seconds",
    "RULE_STAGES",
]

_BASE = 0.3e9  # interpreter, numpy, xarray, numba: measured ~0.25 GB per stage process


def machine_memory() -> int:
    """Physical memory of this machine [bytes] (0 if the system does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 0


def case_memory(ccfg: Mapping[str, Any]) -> dict[str, float]:
    """Estimated peak memory [bytes] of every heavy stage of one case config.

    Returns
    -------
    dict
        ``{"simulate", "register", "reconstruct", "piv": bytes}``.
    """
    return _case_estimates(ccfg)[0]


def reconstruct_seconds(ccfg: Mapping[str, Any]) -> float:
    """The case's reconstruction method's estimate of one frame's time on one core [s]
    (:meth:`~lfstudy.reconstruct.registry.ReconstructionMethod.seconds`; 0: none), from the sizes of
    :func:`case_memory`."""
    return _case_estimates(ccfg)[1]


def _case_estimates(ccfg: Mapping[str, Any]) -> tuple[dict[str, float], float]:
    """:func:`case_memory`'s bytes and :func:`reconstruct_seconds`' seconds, from one count of the sizes."""
    from lfstudy.optics import PlenopticCamera
    from lfstudy.reconstruct.grid import default_voxel_z
    from lfstudy.reconstruct.registry import ReconstructionSize, get_method

    cam = PlenopticCamera.from_config(ccfg)
    npx = cam.n_pixels_x * cam.n_pixels_y
    par = ccfg["particles"]
    n_part = par.get("count") or math.ceil(par["ppp"] * npx)
    if par.get("depth_margin", 0.0) > 0 and par["z_span"] > 0:  # the margin's particles, at the slab's density
        n_part += math.ceil(n_part * 2 * par["depth_margin"] / par["z_span"])
    # montecarlo: 8 float32 chunk buffers + the float64 image + particles (raytrace.memory_estimate);
    # exact: the float64 image + particles; then the sensor model's float64 copies (signal, electrons, noise)
    rt_method = (ccfg.get("raytrace", {}) or {}).get("method", "exact")
    render = (8 * npx * 4 if rt_method == "montecarlo" else 0) + npx * 8 + n_part * 8 * 8
    simulate = render + 3 * npx * 8
    if ((ccfg.get("sensor", {}) or {}).get("background", {}) or {}).get("lenslet", 0.0) > 0:
        simulate += 3 * npx * 8  # the white image, its cached normalised copy and the background
    n = int(cam.pixels_per_lenslet * (cam.si + cam.lenslet_focal_length) / cam.si)
    lf = cam.n_lenslets_x * cam.n_lenslets_y * n * n * 4
    register = npx * 8 + 3 * lf  # the raw image, the light field and its working copies
    # the reconstruction grid: the depth of the refocus marching at the configured steps
    g = ccfg.get("grid", {}) or {}
    d0 = cam.lenslet_pitch / abs(cam.magnification)
    dxy = g.get("voxel_xy") or d0
    r = ccfg.get("refocus", {}) or {}
    planes = cam.focal_planes(r.get("n_planes"), depth_scale=r.get("depth_scale", 1.0), cubic=bool(r.get("cubic")))
    z_range = g.get("z_range")
    depth = float(planes["z"].max() - planes["z"].min()) if z_range is None else float(z_range[1] - z_range[0])
    nz = (
        len(planes["z"])  # (an upper bound with z_range)
        if g.get("spacing") == "planes"
        else int(depth / (g.get("voxel_z") or default_voxel_z(cam))) + 1
    )
    nvox = nz * round(cam.n_lenslets_x * d0 / dxy) * round(cam.n_lenslets_y * d0 / dxy)
    # the method's own estimate (its weight tables, spectra, candidate volumes: the class knows them)
    rcfg = ccfg.get("reconstruct", {}) or {}
    method = rcfg.get("method", "threshold")
    size = ReconstructionSize(npx, cam.n_lenslets_x * cam.n_lenslets_y, n, nz, nvox, n_part)
    params = rcfg.get(method, {}) or {}
    reconstruct = get_method(method).memory_bytes(size, params)
    piv = 2 * nvox * 4 + 4 * nvox * 8 + 2**25 * 4 * 3  # volumes, spline coefficients, a correlation batch
    out = {"simulate": simulate, "register": register, "reconstruct": reconstruct, "piv": piv}
    return {k: v + _BASE for k, v in out.items()}, get_method(method).seconds(size, params)


#: the config key that sizes each stage, and what it holds
_KEYS = {
    "simulate": ("camera.sensor", "the rendered image, its buffers and the sensor model's copies"),
    "register": ("camera.sensor", "the raw image and its light field"),
    "reconstruct": ("grid", "the reconstruction's volumes and weights (reconstruct.method)"),
    "piv": ("grid", "the two volumes PIV correlates"),
}


def check_memory(ccfg: Mapping[str, Any], *, available: float | None = None, where: str = "") -> None:
    """Raise a ConfigError if a stage of this case needs more memory than the machine has.

    Parameters
    ----------
    ccfg : mapping
        A case config.
    available : float, optional
        Bytes to compare with; default 90 % of :func:`machine_memory` (no check if unknown).
    where : str
        The case, for the message.
    """
    avail = available if available is not None else 0.9 * machine_memory()
    if not avail:
        return
    need = case_memory(ccfg)
    stage, most = max(need.items(), key=lambda kv: kv[1])
    if most > avail:
        key, what = _KEYS[stage]
        raise ConfigError(
            f"config key '{key}'{' (' + where + ')' if where else ''}: the {stage} stage needs about "
            f"{most / 1e9:.3g} GB for {what}, more than this machine's {avail / 1e9:.3g} GB; use a smaller "
            "sensor, a coarser grid (grid.voxel_xy, grid.voxel_z) or a bigger machine"
        )


#: The stages of :func:`case_memory` whose arrays a workflow rule holds (the largest one counts).
#: A pinhole image is rendered like a raw image; calibration holds an image and its spectra like
#: registration; refocusing builds what reconstruction starts from; the depth calibration
#: reconstructs and correlates; ``process`` (`lfstudy process` on a recording) runs every stage.
RULE_STAGES: dict[str, tuple[str, ...]] = {
    "simulate": ("simulate",),
    "pinhole": ("simulate",),
    "calibrate": ("register",),
    "register": ("register",),
    "refocus": ("reconstruct",),
    "reconstruct": ("reconstruct",),
    "depthcal": ("reconstruct", "piv"),
    # the dot card imaged and registered at each depth, one at a time
    "volcal": ("simulate", "register"),
    "piv": ("piv",),
    "process": ("simulate", "register", "reconstruct", "piv"),
}

#: What a Snakemake job holds besides its stage: under SLURM every job step runs its own Snakemake
#: (0.4-0.45 GB measured, profiles/slurm/config.yaml), rounded up.
JOB_EXTRA = 0.5e9
#: The least a heavy job asks for [MB]: the profile's measured figure for demo-sized jobs.
JOB_FLOOR_MB = 1500


def job_mem_mb(ccfg: Mapping[str, Any], rule: str, attempt: int = 1) -> int:
    """Memory [MB] a workflow rule declares as its Snakemake ``mem_mb`` resource.

    The largest :func:`case_memory` stage the rule holds (:data:`RULE_STAGES`) plus
    :data:`JOB_EXTRA`, at least :data:`JOB_FLOOR_MB`, times ``attempt`` (a job killed
    for memory is retried with twice as much).

    Parameters
    ----------
    ccfg : mapping
        A case config (for ``process``: a recording config; it has no particles).
    rule : str
        A key of :data:`RULE_STAGES`.
    attempt : int
        Snakemake's attempt number (1, 2, ... with ``retries``).
    """
    if rule == "process":
        ccfg = {**ccfg, "particles": {"count": 1, "ppp": 1e-9}}
    need = case_memory(ccfg)
    most = max(need[s] for s in RULE_STAGES[rule])
    return max(1, int(attempt)) * max(JOB_FLOOR_MB, math.ceil((most + JOB_EXTRA) / 1e6))


#: A reconstruct job's time limit is at least this many times its method's estimate: the estimate is already the top
#: of the measured costs (the profile's floors are 10x measured figures; 10x an upper estimate would ask a SLURM
#: queue for 26 h for one frame of the thesis camera at 0.01 ppp), and a job killed for time retries with twice it.
RUNTIME_MARGIN = 3


def job_runtime_min(ccfg: Mapping[str, Any], rule: str, floor: int, attempt: int = 1) -> int:
    """Minutes a workflow rule declares as its Snakemake ``runtime`` resource (a SLURM time limit).

    ``floor`` (the profile's measured figure) unless the case's reconstruction method estimates more:
    :data:`RUNTIME_MARGIN` times :meth:`~lfstudy.reconstruct.registry.ReconstructionMethod.seconds` for
    ``reconstruct`` (IPR's time goes with the particles: a full Table 4.3 frame at 0.005 ppp ~45 min, far above
    the grid methods' minutes); times ``attempt`` (a job killed for time is retried with twice as much).

    Parameters
    ----------
    ccfg : mapping
        A case config.
    rule : str
        A workflow rule (only ``reconstruct`` has an estimate; any other gets ``floor``).
    floor : int
        The least [min].
    attempt : int
        Snakemake's attempt number.
    """
    est = reconstruct_seconds(ccfg) if rule == "reconstruct" else 0.0
    return max(1, int(attempt)) * max(int(floor), math.ceil(RUNTIME_MARGIN * est / 60.0))
