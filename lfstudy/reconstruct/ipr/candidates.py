"""Step 1, the candidates: peaks of MART volumes of the data and, in the first iterations, of the positive
residual (package docstring, step 1).

The first candidates are the peaks of a MART volume of the light field (:func:`lfstudy.reconstruct.mart.mart`)
above ``peak_threshold`` of its maximum, on the case grid refined ``_REFINE_XY`` x ``_REFINE_XY`` x ``_REFINE_Z``
times (:func:`_refined`; on the case grid, one voxel per lenslet, a 0.005 ppp field has more particles than
voxels). Every volume is reconstructed on one MART plan made once per fit (:class:`_CandidateVolumes`). After
each of the first iterations a residual round (:func:`_residual_candidates`) adds the peaks of the positive
residual's volume (``residual_volume``: MART on the refined grid, MART on the case grid, or the focal stack
:func:`_stack_volume`) that are not within ``_MIN_SEPARATION`` voxels of a particle and whose fitted
intensity is above the ghost floor.
"""

from __future__ import annotations

import time

import numpy as np
import xarray as xr
from scipy import ndimage
from scipy.spatial import cKDTree

from lfstudy.reconstruct.grid import ReconstructionGrid
from lfstudy.reconstruct.ipr.camera import _lightfield_from_raw, volumetric_frame
from lfstudy.reconstruct.ipr.patches import _FitImages
from lfstudy.reconstruct.mart import MartPlan, _coverage, mart, mart_plan
from lfstudy.reconstruct.registry import ReconstructionInputs

_MIN_SEPARATION = 0.5  # residual candidates nearer an existing particle [voxels, per-axis scaled] are not added
_REFINE_XY = 3  # candidate MART grid: this many voxels per case voxel in x and y
_REFINE_Z = 2  # and in z
_LATE_MART_ITERATIONS = 1  # residual_late_gain: MART iterations of the later residual volumes


def _refined(grid: ReconstructionGrid, rxy: int, rz: int) -> ReconstructionGrid:
    """``grid`` with each voxel split into rxy x rxy x rz (same extent; the candidate grid)."""

    def split(c: np.ndarray, k: int) -> np.ndarray:
        if k == 1 or c.size < 2:
            return c
        t = (np.arange(c.size * k) + 0.5) / k - 0.5
        out = np.interp(t, np.arange(c.size), c)
        out[t < 0] = c[0] + t[t < 0] * (c[1] - c[0])
        hi = t > c.size - 1
        out[hi] = c[-1] + (t[hi] - (c.size - 1)) * (c[-1] - c[-2])
        return out

    return ReconstructionGrid(split(grid.x, rxy), split(grid.y, rxy), split(grid.z, rz), spacing=grid.spacing)


def _peaks(vol: np.ndarray, grid: ReconstructionGrid, threshold: float) -> np.ndarray:
    """Local maxima of ``vol`` above ``threshold``·max, (n, 3) x, y, z [mm], by the
    intensity centroid of their 3 x 3 x 3 neighbourhood above its minimum."""
    vmax = float(vol.max()) if vol.size else 0.0
    if vmax <= 0:
        return np.zeros((0, 3))
    peak = (vol == ndimage.maximum_filter(vol, size=3, mode="constant")) & (vol > threshold * vmax)
    iz, iy, ix = np.nonzero(peak)
    pad = np.pad(vol, 1, mode="edge")
    out = np.zeros((iz.size, 3))
    for axis, (idx, coord) in enumerate(((ix, grid.x), (iy, grid.y), (iz, grid.z))):
        # centroid offset along the axis from the neighbour sums on either side
        sl_lo = [iz + 1, iy + 1, ix + 1]
        sl_hi = [iz + 1, iy + 1, ix + 1]
        ax = 2 - axis
        sl_lo[ax] = sl_lo[ax] - 1
        sl_hi[ax] = sl_hi[ax] + 1
        lo, mid, hi = pad[tuple(sl_lo)], pad[iz + 1, iy + 1, ix + 1], pad[tuple(sl_hi)]
        den = lo - 2 * mid + hi
        frac = np.where(den < 0, 0.5 * (lo - hi) / np.where(den < 0, den, 1.0), 0.0)
        frac = np.clip(frac, -0.5, 0.5)
        f = idx + frac
        out[:, axis] = np.interp(f, np.arange(coord.size), coord)
    return out


def _stack_volume(plan: MartPlan, light: xr.DataArray, smoothing: float = 0.5) -> np.ndarray:
    """The focal stack of ``light`` on the plan's grid: each voxel the mean of the (non-negative) ray intensities
    through it, weighted by their beam fractions (Σ_i F_ij·I_i / Σ_i F_ij over the plan's rays; the additive
    back-projection, MLOS's arithmetic counterpart), the voxels too few views see left empty and smoothed as MART
    smooths (``smoothing`` voxels, :func:`lfstudy.reconstruct.mart.mart`)."""
    proj = plan.proj
    meas = np.where(proj.gain > 0, np.maximum(proj._lf_array(light), 0.0), 0.0)
    num = np.zeros((1, *proj.grid.shape))
    chan = np.zeros(1, np.int64)
    for block in plan.blocks:
        for pc, prs in block:
            proj.column_accumulate_many(pc, prs, proj.column_values(meas, pc, prs)[None], chan, num)
    cover = _coverage(plan.dens)
    vol = np.divide(num[0], cover, out=np.zeros_like(cover), where=cover > 0)
    vol[~plan.seen] = 0.0
    if smoothing > 0:
        ndimage.gaussian_filter(vol, smoothing, truncate=3.0, output=vol)
    return vol


class _CandidateVolumes:
    """The candidate volumes of one fit and their peaks [mm, the nominal camera's frame].

    The refined grid's MART plan (its weight tables and the views' coverage) is made once, here, for every
    volume; the residual rounds' volumes use every ``plane_step``-th plane of it (views into the same tables),
    or, with ``residual_volume`` ``case``, a plan of the case's own grid made on first use. Time and volume count
    go into ``clock`` (``mart``, ``volumes``).
    """

    def __init__(
        self, inputs: ReconstructionInputs, cgrid: ReconstructionGrid, plane_step: int, threshold: float, clock: dict
    ) -> None:
        self.inputs, self.plane_step, self.threshold, self.clock = inputs, int(plane_step), threshold, clock
        t0 = time.perf_counter()
        # tables and coverage, once for every volume; the coverage in float32 (half its memory: the candidates are
        # the volume's peaks, which the last bits of the coverage do not move)
        lf, cam, vcal = inputs.lightfield, inputs.camera, inputs.calibration
        self.plan = mart_plan(lf, cam, cgrid, calibration=vcal, coverage_dtype="float32")
        # the residual's volumes: every plane_step-th plane, on views into the same tables
        self.rplan = self.plan.planes(self.plane_step) if self.plane_step > 1 else self.plan
        clock["mart"] += time.perf_counter() - t0
        self._case: MartPlan | None = None  # residual_volume "case": the case grid's plan, made on first use

    def first(self, light: xr.DataArray, iters: int) -> np.ndarray:
        """The peaks of the data's MART volume (``iters`` iterations) on the refined grid."""
        return self._peaks_of(light, iters, self.plan, "mart")

    def residual(self, light: xr.DataArray, iters: int, kind: str) -> np.ndarray:
        """The peaks of a residual's volume of kind ``kind`` (``residual_volume``)."""
        return self._peaks_of(light, iters, self.rplan, kind)

    def _peaks_of(self, light: xr.DataArray, iters: int, p: MartPlan, kind: str) -> np.ndarray:
        t0 = time.perf_counter()
        inputs, vcal = self.inputs, self.inputs.calibration
        if kind == "case":
            if self._case is None:
                cp = mart_plan(
                    inputs.lightfield, inputs.camera, inputs.grid, calibration=vcal, coverage_dtype="float32"
                )
                self._case = cp.planes(self.plane_step) if self.plane_step > 1 else cp
            p = self._case
        g = p.proj.grid
        if kind == "stack":
            vol = _stack_volume(p, light)
        else:
            vol = mart(light, inputs.camera, g, iterations=iters, plan=p, calibration=vcal).values
        self.clock["mart"] += time.perf_counter() - t0
        self.clock["volumes"] += 1
        peaks = _peaks(vol, g, self.threshold)
        if vcal is not None:  # the exact renderer fits in the nominal camera's frame
            peaks = volumetric_frame(peaks, inputs.lightfield, inputs.camera, vcal, to="nominal")
        return peaks


def _residual_candidates(
    volumes: _CandidateVolumes,
    images: _FitImages,
    res: np.ndarray,
    xyz: np.ndarray,
    vox: np.ndarray,
    iters: int,
    kind: str,
    floor: float,
) -> tuple[int, np.ndarray, np.ndarray]:
    """One residual round (Wieneke's "add candidates from the residual"): the peaks of the positive residual's
    volume (``kind``, ``iters`` MART iterations) farther than ``_MIN_SEPARATION`` voxels from every particle at
    ``xyz``, their intensities fitted on ``res`` (which keeps the images of those brighter than ``floor``).

    Returns the number of candidates tried and the positions and intensities of those kept (above ``floor``).
    """
    new = volumes.residual(_lightfield_from_raw(np.maximum(res, 0.0), volumes.inputs.lightfield), iters, kind)
    if len(new) and len(xyz):
        new = new[cKDTree(xyz / vox).query(new / vox)[0] > _MIN_SEPARATION]
    if not len(new):
        return 0, new, np.zeros(0)
    amp0 = images.fit_intensity(new, res, floor)
    good = amp0 > floor
    return len(new), new[good], amp0[good]
