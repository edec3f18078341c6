"""MART: multiplicative algebraic reconstruction with plenoptic weights (beyond thesis sec. 5.6).

The thesis names MART (Elsinga et al. 2006, the algorithm of tomographic PIV) as
the way past thresholding (sec. 5.6); later plenoptic
PIV (Fahringer & Thurow) did it with weights from the plenoptic camera's own
ray geometry. Here the weights are the beams of
:class:`~lfstudy.reconstruct.projector.PlenopticProjector`: every
light-field sample is a ray of the calibrated camera, never a ray of the
simulator.

A plenoptic camera is a set of sub-aperture *views*: pixel (pr, pc) under
every lenslet sees the volume from one direction through the main lens. MART
runs over ordered subsets of views (block-iterative MART, Censor & Elfving):
for each subset, every voxel j is multiplied by the weighted geometric mean
of the ratios measured/projected of the rays that cross it,

    E_j ← E_j · exp( μ · Σ_i F_ij·log(I_i / P_i) / Σ_i F_ij ),

F_ij the fraction of ray i's beam through voxel j, μ the relaxation. With one
subset this is SMART; with one view per subset it is close to ray-by-ray
MART. The update is multiplicative, so a volume that starts non-negative
stays non-negative, and a voxel crossed by dark rays goes to zero.

Left alone, MART concentrates every particle into the fewest voxels the data
allow (a sparse, maximum-entropy-like solution): sub-voxel positions snap to
voxel centres and the focal plane, where a plenoptic camera cannot tell depths
within one lenslet's depth of focus apart, draws particles to it. A light
Gaussian filter between iterations (``smoothing``, Discetti et al. 2013's SFIT)
keeps particles as blobs of about one resolution cell.

Initialisation: ``mlos`` (the multiplicative first guess of Worth & Nickels
2008, called multiplicative line of sight by Atkinson & Soria 2009: the
weighted geometric mean, over every view, of the ray intensities normalised by
their projection of a uniform volume; a voxel crossed by dark rays starts
dark), ``stack`` (the focal stack on the grid), or ``uniform``. Full references
in :func:`mart`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import xarray as xr
from scipy import ndimage
from tqdm.auto import tqdm

from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct.grid import ReconstructionGrid
from lfstudy.reconstruct.projector import PlenopticProjector
from lfstudy.reconstruct.registry import (
    ReconstructionError,
    ReconstructionInputs,
    ReconstructionMethod,
    ReconstructionSize,
)

__all__ = ["MART", "MartPlan", "mart", "mart_plan"]

_INITS = ("mlos", "stack", "uniform")


def _spread_order(n: int) -> list[int]:
    """0..n-1 in an order that puts consecutive entries far apart (golden-ratio stride)."""
    if n <= 2:
        return list(range(n))
    step = max(1, round(n * (math.sqrt(5) - 1) / 2))
    while math.gcd(step, n) != 1:
        step += 1
    return [(i * step) % n for i in range(n)]


@dataclass
class MartPlan:
    """What :func:`mart` computes from the geometry alone, kept for several light fields of one camera.

    The projector's weight tables, the subsets of views, the coverage of each subset and the voxels
    seen; the uniform projection A·1 of the MLOS first guess is made on first use. Made by
    :func:`mart_plan`; :func:`mart` with ``plan=`` gives the same bytes as without, minus the setup's
    time (IPR's candidate volumes reconstruct a residual on one grid many times).
    """

    proj: PlenopticProjector
    subsets: int
    min_coverage: float
    blocks: list[list[tuple[int, np.ndarray]]]
    act_c: dict[int, np.ndarray]
    dens: list[np.ndarray]
    seen: np.ndarray
    calibration: xr.Dataset | None = None
    _p1: np.ndarray | None = field(default=None, repr=False)

    def uniform_projection(self) -> np.ndarray:
        """A·1, computed once."""
        if self._p1 is None:
            self._p1 = self.proj.uniform_projection()
        return self._p1

    def planes(self, step: int, start: int = 0) -> MartPlan:
        """The plan of the grid's every ``step``-th plane from ``start`` (its grid is ``.proj.grid``).

        The weight tables are views into this plan's
        (:meth:`~lfstudy.reconstruct.projector.PlenopticProjector.planes`) and the coverage is this
        plan's on those planes, so it costs no new table memory and no setup, and :func:`mart` with it
        gives the bytes of a plan made for the thinned grid (``step`` times fewer planes: about ``step``
        times cheaper per volume).
        """
        proj = self.proj.planes(step, start)
        sl = slice(int(start), None, int(step))
        dens = [d[sl] for d in self.dens]
        seen = _seen(_coverage(dens), self.min_coverage)
        return MartPlan(proj, self.subsets, self.min_coverage, self.blocks, self.act_c, dens, seen, self.calibration)


def _coverage(dens: list[np.ndarray]) -> np.ndarray:
    """Σ of the subsets' coverages in float64, added one after the other: the bytes of ``np.sum(dens, axis=0)``
    (which adds the stacked rows in that order) without stacking them into one more array of them all."""
    cover = dens[0].astype(np.float64)
    for d in dens[1:]:
        cover += d
    return cover


def _seen(cover: np.ndarray, min_coverage: float) -> np.ndarray:
    """Voxels seen by enough views to be placed in depth: coverage >= ``min_coverage`` x its 90th percentile."""
    lit = cover[cover > 0]  # a copy, so the percentile may partition it in place (no second copy)
    if not lit.size:
        return cover > 0
    return cover >= min_coverage * float(np.percentile(lit, 90, overwrite_input=True))


def _update(vol: np.ndarray, num: np.ndarray, d: np.ndarray, upd: np.ndarray, relaxation: float) -> None:
    """``vol[upd] *= exp(clip(relaxation·num[upd]/d[upd], −20, 20))`` in place, with no voxel-sized temporary
    (``num`` is overwritten): the same bytes as that expression (tested), whose five temporaries of up to
    the grid's size (on IPR's refined grid of a full Table 4.3 frame 0.27 GB each) set MART's peak memory."""
    np.multiply(num, relaxation, out=num)
    np.divide(num, d, out=num, where=upd)
    np.clip(num, -20.0, 20.0, out=num)
    np.exp(num, out=num, where=upd)
    np.multiply(vol, num, out=vol, where=upd)


def mart_plan(
    lightfield: xr.DataArray,
    camera: PlenopticCamera,
    grid: ReconstructionGrid,
    *,
    subsets: int = 4,
    min_coverage: float = 0.5,
    min_vignetting: float = 0.25,
    calibration: xr.Dataset | None = None,
    coverage_dtype: str = "float64",
) -> MartPlan:
    """The geometry-only part of :func:`mart` (parameters as there; only ``lightfield``'s coordinates
    are read), for :func:`mart`'s ``plan``.

    ``coverage_dtype`` is how each subset's coverage (one grid-sized array per subset, accumulated in
    float64) is kept: ``"float64"`` gives :func:`mart`'s own bytes; ``"float32"`` halves them (on IPR's
    candidate grid of a full Table 4.3 frame 1.06 -> 0.53 GB), the volume then within 1e-5 of its maximum
    (tested)."""
    if coverage_dtype not in ("float64", "float32"):
        raise ReconstructionError(f"mart_plan: coverage_dtype = {coverage_dtype!r}; allowed: 'float64', 'float32'")
    if subsets < 1:
        raise ReconstructionError("reconstruct.mart: iterations must be >= 0 and subsets >= 1")
    proj = PlenopticProjector(lightfield, camera, grid, min_vignetting=min_vignetting, calibration=calibration)
    active = proj.gain > 0
    if not active.any():
        raise ReconstructionError("no light-field sample lies inside the main-lens aperture: check the calibration")
    # Sub-aperture views grouped by pixel column (they share their x weights); the columns
    # are visited in an order that spreads consecutive ones over the aperture.
    cols = proj.columns()
    order = _spread_order(len(cols))
    cols = [cols[k] for k in order]
    n_sub = max(1, min(int(subsets), len(cols)))
    blocks = [cols[s::n_sub] for s in range(n_sub)]
    act_c = {pc: proj.column_values(active, pc, prs) for pc, prs in cols}
    # per-subset coverage (Σ of beam fractions over the used samples)
    # one subset at a time (each subset's sum runs over its own columns in the same order as all at once)
    dens = []
    for block in blocks:
        acc = np.zeros((1, *grid.shape))
        for pc, prs in block:
            proj.column_accumulate_many(pc, prs, act_c[pc].astype(np.float64)[None], np.zeros(1, np.int64), acc)
        dens.append(acc[0] if coverage_dtype == "float64" else acc[0].astype(coverage_dtype))
        del acc
    # voxels that too few views see cannot be placed in depth: they stay empty
    seen = _seen(_coverage(dens), float(min_coverage))
    return MartPlan(proj, int(subsets), float(min_coverage), blocks, act_c, dens, seen, calibration)


def mart(
    lightfield: xr.DataArray,
    camera: PlenopticCamera,
    grid: ReconstructionGrid,
    *,
    iterations: int = 3,
    relaxation: float = 1.0,
    subsets: int = 4,
    init: str = "mlos",
    stack: xr.DataArray | None = None,
    noise_floor: float = 0.0,
    offset: float = 0.05,
    min_coverage: float = 0.5,
    min_vignetting: float = 0.25,
    smoothing: float = 0.5,
    track_residual: bool = False,
    progress: bool = False,
    calibration: xr.Dataset | None = None,
    plan: MartPlan | None = None,
) -> xr.DataArray:
    """Reconstruct a volume on ``grid`` from a registered light field by MART.

    MART [1]_ over ordered subsets of views, with plenoptic weights and a
    multiplicative first guess [2]_, [3]_ (see the module docstring).

    Parameters
    ----------
    lightfield : xarray.DataArray
        Registered light field (:func:`lfstudy.lightfield.register`).
    camera : PlenopticCamera
    grid : ReconstructionGrid
    iterations : int
        Passes over all views.
    relaxation : float
        μ in (0, 2].
    subsets : int
        Ordered subsets of views per iteration (1 = SMART).
    init : {"mlos", "stack", "uniform"}
        Initial volume: ``mlos`` the multiplicative first guess [2]_ (MLOS [3]_),
        ``stack`` the focal stack (needs ``stack``), ``uniform`` ones.
    stack : xarray.DataArray, optional
        Focal stack on ``grid`` (for ``init="stack"``).
    noise_floor : float
        Subtracted from the light field (a dark level); what is left at or below
        zero counts as dark.
    offset : float
        Background b of the ratios (I + b)/(P + b), as a fraction of the mean
        used sample: bounds the update of voxels that rays barely see.
    min_coverage : float
        Voxels whose summed beam fractions are below this fraction of the 90th
        percentile (seen by too few views to be placed in depth) stay empty.
    min_vignetting : float
        Samples with less of their beam inside the aperture are not used.
    smoothing : float
        σ [voxels] of a Gaussian filter applied after the initial volume and
        every iteration (spatial filtering improved tomography, Discetti et al.
        2013): particles stay blobs of about the camera's resolution instead of
        collapsing onto single voxels, which keeps sub-voxel positions for PIV.
        0 gives plain MART.
    track_residual : bool
        After every iteration compute the exact relative residual
        ‖A·E − I‖ / ‖I‖ over the used samples (one more projection each).
    progress : bool
        A tqdm bar over the iterations.
    calibration : xarray.Dataset, optional
        A volumetric calibration (:func:`lfstudy.lightfield.volcal.fit_volumetric`): the beams'
        centres come from its fitted mapping instead of the thin-lens model
        (:class:`~lfstudy.reconstruct.projector.PlenopticProjector`).
    plan : MartPlan, optional
        The geometry-only part made once by :func:`mart_plan` (same ``camera``, ``grid``, ``subsets``,
        ``min_coverage``, ``min_vignetting``, ``calibration`` and lenslet layout): the same result
        without redoing it.

    Returns
    -------
    xarray.DataArray
        ``intensity`` on the grid (float32, non-negative); attrs: the
        settings, ``residual`` per iteration (exact with ``track_residual``,
        else the residual met during the iteration), ``seconds_per_iteration``,
        ``init_seconds``, ``rays_used``, ``weight_table_bytes``, ``projector_model``
        (``thin_lens`` or ``volumetric``) and ``samples_uncalibrated`` (samples left out
        because the calibration has no sub-aperture for them).

    References
    ----------
    .. [1] G. E. Elsinga, F. Scarano, B. Wieneke, B. W. van Oudheusden,
           "Tomographic particle image velocimetry", Experiments in Fluids 41 (6)
           pp 933--947 (2006), doi:10.1007/s00348-006-0212-z
    .. [2] N. A. Worth, T. B. Nickels, "Acceleration of Tomo-PIV by estimating
           the initial volume intensity distribution", Experiments in Fluids 45
           pp 847--856 (2008), doi:10.1007/s00348-008-0504-6
    .. [3] C. Atkinson, J. Soria, "An efficient simultaneous reconstruction
           technique for tomographic particle image velocimetry", Experiments in
           Fluids 47 pp 553--568 (2009), doi:10.1007/s00348-009-0728-0
    """
    if init not in _INITS:
        raise ReconstructionError(f"reconstruct.mart.init = {init!r}: allowed values are {', '.join(_INITS)}")
    if not (0 < relaxation <= 2):
        raise ReconstructionError(f"reconstruct.mart.relaxation = {relaxation!r}: allowed range is (0, 2]")
    if iterations < 0 or subsets < 1:
        raise ReconstructionError("reconstruct.mart: iterations must be >= 0 and subsets >= 1")
    t0 = time.perf_counter()
    if plan is None:
        plan = mart_plan(
            lightfield,
            camera,
            grid,
            subsets=subsets,
            min_coverage=min_coverage,
            min_vignetting=min_vignetting,
            calibration=calibration,
        )
    elif (
        plan.proj.grid is not grid
        or plan.subsets != int(subsets)
        or plan.min_coverage != float(min_coverage)
        or plan.proj.min_vignetting != float(min_vignetting)
        or plan.calibration is not calibration
    ):
        raise ReconstructionError("reconstruct.mart: the plan was made for another grid or other settings")
    proj, blocks, act_c, dens, seen = plan.proj, plan.blocks, plan.act_c, plan.dens, plan.seen
    n_sub = len(blocks)
    meas = proj._lf_array(lightfield)
    if not np.all(np.isfinite(meas)):
        raise ReconstructionError("light field has non-finite samples")
    meas = np.maximum(meas - noise_floor, 0.0)  # the floor (dark level, noise) carries no light
    active = proj.gain > 0
    # The background b bounds every ratio (I + b)/(P + b): a dark ray removes what a voxel
    # puts into it, but cannot drive a voxel it barely touches to zero (points are smaller
    # than voxels), and a ray nothing projects into cannot blow a voxel up.
    b = max(float(offset) * float(meas[active].mean()), 1e-30)
    logm = np.log(meas + b)
    lens = proj.lenses
    cols = [c for block in blocks for c in block]
    # per column: measured log (I + b) and I, as (views, lenslets)
    logm_c = {pc: proj.column_values(logm, pc, prs) for pc, prs in cols}
    meas_c = {pc: proj.column_values(meas, pc, prs) for pc, prs in cols}
    num = np.zeros(grid.shape)
    cover = _coverage(dens)
    if init == "mlos":
        # MLOS values log(I + b) − log(A·1) of every used sample (A·1 from the tables alone), their
        # coverage-weighted sum over every view in num
        p1 = plan.uniform_projection()
        use = active & (p1 > 0)
        mlos = np.where(use, logm - np.log(np.where(use, p1, 1.0)), 0.0)
        del use
        for block in blocks:
            for pc, prs in block:
                vals = proj.column_values(mlos, pc, prs)[None]
                proj.column_accumulate_many(pc, prs, vals, np.zeros(1, np.int64), num[None])
    if init == "uniform":
        vol = np.ones(grid.shape)
    elif init == "stack":
        if stack is None:
            raise ReconstructionError("reconstruct.mart.init = 'stack' needs the focal stack on the grid")
        vol = np.maximum(np.asarray(stack.values, dtype=np.float64), 0.0)
    else:  # MLOS: weighted geometric mean of measured / projected-uniform over every view
        pos = cover > 0
        with np.errstate(over="ignore", under="ignore", invalid="ignore"):  # in place: num is free again after
            np.divide(num, cover, out=num, where=pos)
            np.exp(num, out=num, where=pos)
        vol = np.where(pos, num, 0.0)
        del pos
    del cover
    vol[~seen] = 0.0
    if smoothing > 0:  # in place (each axis' pass buffers its lines): the same bytes, no second volume
        ndimage.gaussian_filter(vol, smoothing, truncate=3.0, output=vol)
    init_s = time.perf_counter() - t0

    # ---- ordered-subset MART
    residuals: list[float] = []
    seconds: list[float] = []
    norm_i = float(np.sqrt(np.sum(meas[active] ** 2))) or 1.0
    upd = np.empty(grid.shape, bool)  # the voxels a subset updates: seen, and covered by it
    bar = tqdm(total=iterations, desc="MART", unit="it", disable=not progress)
    for _ in range(iterations):
        t1 = time.perf_counter()
        r2 = 0.0
        for block, d in zip(blocks, dens):
            np.greater(d, 0.0, out=upd)
            upd &= seen
            num.fill(0.0)
            for pc, prs in block:
                p = proj.column_forward(vol, pc, prs, np.empty((prs.size, lens.size)))
                ok = act_c[pc]
                r2 += float(np.sum((p[ok] - meas_c[pc][ok]) ** 2))
                vals = np.where(ok, logm_c[pc] - np.log(p + b), 0.0)
                proj.column_accumulate(pc, prs, vals, num)
            # a voxel's factor is the weighted geometric mean of its rays' ratios; bounded
            # (e^±20) so a voxel barely seen by a subset cannot overflow
            _update(vol, num, d, upd, relaxation)
        if smoothing > 0:  # spatial filtering between iterations (Discetti et al. 2013)
            ndimage.gaussian_filter(vol, smoothing, truncate=3.0, output=vol)
        if track_residual:
            fwd = proj.forward(vol)
            r2 = float(np.sum((fwd.reshape(meas.shape)[active] - meas[active]) ** 2))
        residuals.append(math.sqrt(r2) / norm_i)
        seconds.append(time.perf_counter() - t1)
        bar.update(1)
        bar.set_postfix(residual=f"{residuals[-1]:.4f}")
    bar.close()
    if not np.all(np.isfinite(vol)):
        raise ReconstructionError("MART diverged (non-finite voxels); lower reconstruct.mart.relaxation")
    return grid.volume(
        vol.astype(np.float32),
        long_name="reconstructed intensity (MART, plenoptic weights)",
        units=str(lightfield.attrs.get("units", "counts")),
        iterations=int(iterations),
        relaxation=float(relaxation),
        subsets=int(n_sub),
        init=init,
        noise_floor=float(noise_floor),
        offset=float(offset),
        background=float(b),
        min_coverage=float(min_coverage),
        voxels_seen=int(seen.sum()),
        min_vignetting=float(min_vignetting),
        smoothing=float(smoothing),
        residual=[float(r) for r in residuals],
        residual_kind="exact" if track_residual else "during iteration",
        seconds_per_iteration=[float(s) for s in seconds],
        init_seconds=float(init_s),
        rays_used=int(proj.n_rays),
        projector_model=proj.model,
        samples_uncalibrated=int(proj.uncalibrated_samples),
        weight_table_bytes=int(proj.table_bytes),
    )


class MART(ReconstructionMethod):
    """``mart``: multiplicative ART over ordered subsets of views, plenoptic weights."""

    name = "mart"
    description = "multiplicative ART with plenoptic weights from the camera model and the calibration"
    requires = ("lightfield", "camera", "grid")
    uses_calibration = True
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "iterations": {
            "type": "integer",
            "minimum": 0,
            "maximum": 200,
            "description": "passes over all views",
        },
        "relaxation": {
            "type": "number",
            "exclusiveMinimum": 0,
            "maximum": 2,
            "description": "relaxation mu of the multiplicative update",
        },
        "subsets": {
            "type": "integer",
            "minimum": 1,
            "maximum": 4096,
            "description": "ordered subsets of sub-aperture view columns per iteration (1 = SMART)",
        },
        "init": {
            "type": "string",
            "enum": list(_INITS),
            "description": "initial volume: multiplicative line of sight, the focal stack, or uniform",
        },
        "noise_floor": {
            "type": "number",
            "minimum": 0,
            "description": "light-field values at or below this count as dark (image units)",
        },
        "min_vignetting": {
            "type": "number",
            "minimum": 0,
            "maximum": 1,
            "description": "leave out samples with less of their beam inside the main-lens aperture",
        },
        "offset": {
            "type": "number",
            "exclusiveMinimum": 0,
            "maximum": 10,
            "description": "background b of the ratios (I + b)/(P + b), a fraction of the mean sample",
        },
        "min_coverage": {
            "type": "number",
            "minimum": 0,
            "maximum": 1,
            "description": "voxels seen by less than this fraction of the best-seen voxels' views stay empty",
        },
        "smoothing": {
            "type": "number",
            "minimum": 0,
            "maximum": 3,
            "description": "Gaussian sigma [voxels] filtering the volume after MLOS and every iteration (0: none)",
        },
    }

    @classmethod
    def memory_bytes(cls, size: ReconstructionSize, params: Mapping[str, Any] | None = None) -> float:
        """The base's arrays, the weight tables ((kx + ky) ~ 12 float32 weights and 2 int32 starts per plane and
        light-field sample: an upper bound, int16 starts where the grid allows) and eight float64 volumes."""
        tables = size.n_planes * size.n_lenslets * size.pixels_per_lenslet * (12 * 4 + 2 * 4)
        return super().memory_bytes(size, params) + (tables + 8 * size.n_voxels * 8)

    def run(
        self,
        inputs: ReconstructionInputs,
        *,
        iterations: int = 3,
        relaxation: float = 1.0,
        subsets: int = 4,
        init: str = "mlos",
        noise_floor: float = 0.0,
        min_vignetting: float = 0.25,
        offset: float = 0.05,
        min_coverage: float = 0.5,
        smoothing: float = 0.5,
        progress: bool = False,
    ) -> xr.DataArray:
        return mart(
            inputs.lightfield,
            inputs.camera,
            inputs.grid,
            iterations=iterations,
            relaxation=relaxation,
            subsets=subsets,
            init=init,
            stack=inputs.stack,
            noise_floor=noise_floor,
            min_vignetting=min_vignetting,
            offset=offset,
            min_coverage=min_coverage,
            smoothing=smoothing,
            progress=progress,
            calibration=inputs.calibration,
        )
