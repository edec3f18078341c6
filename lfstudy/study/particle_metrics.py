"""How well a particle reconstruction (``reconstruct.method: ipr``) found the true particles.

For a method that fits particles the study knows more than the PIV error: which true particles
were found, how many fitted ones are ghosts, and whether the particles found in both frames
carry the lateral→axial crosstalk themselves (issue 27). On the demo designs at 0.005 ppp the
found particles' own spurious w is 1–4 % of the lateral shift, while the PIV's is 10–17 %: the
crosstalk rides on the ghosts, which pair up between the frames like the coherent ghosts of
tomographic PIV (Elsinga et al. 2011, Exp. Fluids 50 825) and shift in depth. These metrics put
that in every case's ``errors.zarr``.

A true particle is *found* when a fitted one lies within half a voxel of it, the distance
measured in voxels per axis (the criterion of ``benchmarks/bench_ipr.py``); a fitted particle
with no true one within half a voxel is a *ghost*. Only true particles inside the
reconstruction grid count as findable. ``found_in_focus_percent`` counts those within the depth
of field about the focal plane (eq. 4.18): there a particle's image is one lenslet's spot whose
size changes only to second order with depth, and on the demo designs IPR misses 57–95 % of them
(``particles.z_center`` moves the measured slab off the focal plane).

``depth_unknown_percent`` needs no truth: the share of the fitted particles whose depth the fit could not read
(``sigma_z`` above ``piv.paired_max_sigma_z``), which the paired PIV leaves out
(:func:`lfstudy.study.case.case_paired_piv`); near the focal plane the images hold little depth
(:mod:`lfstudy.reconstruct.ipr.bound`). ``focus_scatter_ratio`` needs none either: how much more the paired tracks'
displacements scatter in the band of |z| nearest the focal plane than in the best band (the paired PIV's depth
weights, :func:`lfstudy.piv.ptv.depth_weights`). The fit's ``sigma_z`` misses most of that error (it is the
minimum the fit chose, not the minimum's width), so the ratio, not the share above, shows where the focal plane
limits a design: 2.5-4.7 on the demo's eight cases (seed 7).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import xarray as xr
from scipy.spatial import cKDTree

from lfstudy.study.metrics import crosstalk_z

__all__ = ["FOUND_WITHIN", "depth_unknown_percent", "focus_scatter_ratio", "particle_metrics"]

#: A fitted particle within this many voxels (per-axis scaled distance) finds a true one.
FOUND_WITHIN = 0.5

_XYZ = ("x", "y", "z")


def _positions(ds: xr.Dataset) -> np.ndarray:
    """(n, 3) positions [mm]; (0, 3) for an empty list."""
    return np.column_stack([np.asarray(ds[k].values, float).ravel() for k in _XYZ])


def _match(true: np.ndarray, fit: np.ndarray, voxel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each true particle: found (bool) and the index of its nearest fitted one; for each fitted
    particle: whether it is a ghost."""
    if not len(fit) or not len(true):
        return np.zeros(len(true), bool), np.zeros(len(true), int), np.ones(len(fit), bool)
    d_true, j = cKDTree(fit / voxel).query(true / voxel)
    d_fit, _ = cKDTree(true / voxel).query(fit / voxel)
    return d_true < FOUND_WITHIN, j, d_fit >= FOUND_WITHIN


def particle_metrics(
    fitted: Sequence[xr.Dataset],
    true: Sequence[xr.Dataset],
    voxel_mm: Sequence[float],
    bounds_mm: Sequence[tuple[float, float]],
    focus_mm: tuple[float, float] | None = None,
) -> dict[str, float]:
    """Particles found, ghosts, position errors and the found particles' own displacement error.

    Parameters
    ----------
    fitted : (Dataset, Dataset)
        The fitted particle lists of frames a and b (``x``, ``y``, ``z`` [mm] over ``particle``).
    true : (Dataset, Dataset)
        The true particles of frames a and b; frame b is frame a displaced, particle for particle.
    voxel_mm : (dx, dy, dz)
        The reconstruction grid's voxel size [mm]: the unit of the found criterion.
    bounds_mm : ((x0, x1), (y0, y1), (z0, z1))
        The grid's extent [mm] (first and last voxel centres): true particles outside it are not
        findable and are left out of ``found_percent``.
    focus_mm : (z_near, z_far), optional
        The depth of field about the focal plane [mm] (eq. 4.18,
        :meth:`~lfstudy.optics.PlenopticCamera.depth_of_field`): ``found_in_focus_percent`` is
        ``found_percent`` of the true particles inside it (NaN without it or where none is).

    Returns
    -------
    dict
        ``found_percent`` (true particles inside the grid found, both frames together),
        ``ghost_percent`` (of the fitted particles, both frames), ``found_in_focus_percent``,
        ``particle_rms_{x,y,z}_mm``
        (position error of the found ones), ``particle_bias_w_mm`` (mean error of the fitted
        z displacement of the particles found in both frames) and ``particle_crosstalk_z`` (that
        per unit of lateral shift, :func:`~lfstudy.study.metrics.crosstalk_z`: NaN unless the
        flow is uniform and lateral). NaN where nothing is there to count.
    """
    if len(fitted) != 2 or len(true) != 2:
        raise ValueError("particle_metrics: give the fitted and the true particles of both frames (a, b)")
    vox = np.asarray(voxel_mm, float)
    if vox.shape != (3,) or not np.all(vox > 0):
        raise ValueError(f"particle_metrics: voxel_mm = {voxel_mm!r}: three sizes > 0 (x, y, z)")
    ta, tb = (_positions(t) for t in true)
    if ta.shape != tb.shape:
        raise ValueError("particle_metrics: the true frames differ in particle count (frame b must be frame a moved)")
    lo = np.array([b[0] for b in bounds_mm], float)
    hi = np.array([b[1] for b in bounds_mm], float)
    n_in = n_found = n_fit = n_ghost = n_focus = n_found_focus = 0
    errs, found, nearest = [], [], []
    for f, t in zip(fitted, (ta, tb)):
        g = _positions(f)
        inside = np.all((t >= lo) & (t <= hi), axis=1)
        ok, j, ghost = _match(t, g, vox)
        ok &= inside
        n_in += int(inside.sum())
        n_found += int(ok.sum())
        n_fit += len(g)
        n_ghost += int(ghost.sum())
        if focus_mm is not None:
            near = inside & (t[:, 2] >= focus_mm[0]) & (t[:, 2] <= focus_mm[1])
            n_focus += int(near.sum())
            n_found_focus += int((ok & near).sum())
        errs.append(g[j[ok]] - t[ok])  # (0, 3) where nothing is found
        found.append(ok)
        nearest.append(g[j] if len(g) else np.full_like(t, np.nan))
    e = np.vstack(errs)
    out = {
        "found_percent": 100.0 * n_found / n_in if n_in else math.nan,
        "ghost_percent": 100.0 * n_ghost / n_fit if n_fit else math.nan,
        "found_in_focus_percent": 100.0 * n_found_focus / n_focus if n_focus else math.nan,
    }
    for k, a in enumerate(_XYZ):
        out[f"particle_rms_{a}_mm"] = float(np.sqrt(np.mean(e[:, k] ** 2))) if len(e) else math.nan
    both = found[0] & found[1]
    fit_d = nearest[1][both] - nearest[0][both]
    true_d = tb[both] - ta[both]
    if both.any():
        out["particle_bias_w_mm"] = float(np.mean(fit_d[:, 2] - true_d[:, 2]))
        meas = {a: fit_d[:, k] for k, a in enumerate(_XYZ)}
        tru = {a: true_d[:, k] for k, a in enumerate(_XYZ)}
        out["particle_crosstalk_z"] = crosstalk_z(meas, tru, np.ones(int(both.sum()), bool))
    else:
        out["particle_bias_w_mm"] = out["particle_crosstalk_z"] = math.nan
    return out


def depth_unknown_percent(piv_attrs: dict) -> float:
    """The share [%] of both frames' fitted particles the paired PIV left out because the fit could not read
    their depth (``paired_depth_unknown_a``/``_b`` of ``paired_particles_a``/``_b``, attrs of
    :func:`lfstudy.study.case.case_paired_piv`'s result); NaN where the PIV did not pair particles."""
    keys = ("paired_depth_unknown_a", "paired_depth_unknown_b", "paired_particles_a", "paired_particles_b")
    if not all(k in piv_attrs for k in keys):
        return math.nan
    unknown = int(piv_attrs["paired_depth_unknown_a"]) + int(piv_attrs["paired_depth_unknown_b"])
    total = int(piv_attrs["paired_particles_a"]) + int(piv_attrs["paired_particles_b"])
    return 100.0 * unknown / total if total else math.nan


def focus_scatter_ratio(piv_attrs: dict) -> float:
    """The paired tracks' displacement scatter in the band of |z| nearest the focal plane over the least of any band
    (``paired_weight_sd_mm`` of :func:`lfstudy.study.case.case_paired_piv`'s result, bands in order of |z|; 1 where
    the band nearest focus is the best); NaN where the PIV did not weigh its tracks by depth (no bands)."""
    sd = np.asarray(piv_attrs.get("paired_weight_sd_mm", []), dtype=float)
    if sd.size < 2 or not np.all(np.isfinite(sd)) or not sd.min() > 0:
        return math.nan
    return float(sd[0] / sd.min())
