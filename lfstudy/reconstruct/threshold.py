"""Threshold + dilation reconstruction (thesis sec. 5.5) and the plain focal stack.

``"threshold"`` keeps voxels above mean + k·σ of the whole rendered volume
(Belden et al.; k = 3), dilates the binary mask by a disk of radius 1 px in
every plane (MATLAB ``strel`` + ``imdilate``) so every particle image keeps
its neighbours for the 3-point sub-pixel fits, and multiplies the mask back
into the stack. ``"none"`` correlates the focal stack itself.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import xarray as xr
from scipy import ndimage

from lfstudy.reconstruct.registry import ReconstructionInputs, ReconstructionMethod

__all__ = ["Threshold", "FocalStack", "threshold_dilate", "focal_stack_as_is", "disk"]


def disk(radius: int, ndim: int = 2) -> np.ndarray:
    """Binary disk/ball footprint: offsets with |offset| <= radius (radius 1 → a plus/cross)."""
    if radius < 0:
        raise ValueError(f"dilation_radius = {radius!r}: must be >= 0")
    g = np.mgrid[(slice(-radius, radius + 1),) * ndim]
    return (g**2).sum(0) <= radius**2


def focal_stack_as_is(stack: xr.DataArray) -> xr.DataArray:
    """No reconstruction: correlate the refocused planes themselves.

    The hard threshold of sec. 5.5 cuts particle images off at the mask edge; on
    the thesis' uniform-x case (0.001 ppp) PIV of the plain stack spreads less in
    y and z (benchmarks/bench_study_thesis.py). Out-of-focus blur stays in.
    """
    res = stack.chunk({stack.dims[0]: 1})
    res.name = stack.name or "intensity"
    res.attrs = dict(stack.attrs)
    res.attrs.update(long_name="focal stack used as the volume (no reconstruction)", method="none")
    return res


def threshold_dilate(
    stack: xr.DataArray,
    k: float = 3.0,
    dilation_radius: int = 1,
    dilation_ndim: int = 2,
) -> xr.DataArray:
    """Sec. 5.5: threshold at mean + k·σ of the volume, dilate the mask, multiply back.

    Parameters
    ----------
    stack : xarray.DataArray (z, y, x)
    k : float
        Threshold in standard deviations above the volume mean (thesis: 3).
    dilation_radius : int
        Radius [voxels] of the disk used to dilate the binary mask (thesis: 1).
    dilation_ndim : {2, 3}
        2: dilate each plane (the thesis' 2-D ``imdilate``); 3: a 3-D ball.

    Returns
    -------
    xarray.DataArray
        ``stack × dilate(stack > mean + k·σ)``; attrs ``threshold``, ``k``,
        ``dilation_radius``, ``kept_fraction`` (voxels kept after dilation),
        ``method``.
    """
    if not (np.isfinite(k) and k >= 0):
        raise ValueError(f"k = {k!r}: must be a finite number >= 0")
    if dilation_ndim not in (2, 3):
        raise ValueError(f"dilation_ndim = {dilation_ndim!r}: allowed values are 2 and 3")
    vol = np.asarray(stack.values, dtype=np.float64)  # a stack is small (planes x lenslets)
    if not np.all(np.isfinite(vol)):
        raise ValueError("stack has non-finite voxels")
    mu, sigma = float(vol.mean()), float(vol.std())
    thr = mu + k * sigma
    mask = vol > thr
    if dilation_radius > 0:
        fp = disk(int(dilation_radius), dilation_ndim)
        if dilation_ndim == 2:
            fp = fp[None]
        mask = ndimage.binary_dilation(mask, structure=fp)
    out = (vol * mask).astype(stack.dtype, copy=False)
    res = stack.copy(data=out).chunk({stack.dims[0]: 1})  # one chunk per plane
    res.name = stack.name or "intensity"
    res.attrs = dict(stack.attrs)
    res.attrs.update(
        long_name="reconstructed intensity (threshold + dilation, sec. 5.5)",
        method="threshold",
        threshold=thr,
        threshold_mean=mu,
        threshold_std=sigma,
        k=float(k),
        dilation_radius=int(dilation_radius),
        dilation_ndim=int(dilation_ndim),
        kept_fraction=float(mask.mean()),
    )
    return res


class FocalStack(ReconstructionMethod):
    """``none``: the focal stack on the grid is the volume (no reconstruction)."""

    name = "none"
    description = "no reconstruction: PIV on the focal stack refocused onto the grid"
    requires = ("stack",)
    parameters: ClassVar[dict[str, dict[str, Any]]] = {}

    def run(self, inputs: ReconstructionInputs, *, progress: bool = False) -> xr.DataArray:
        return focal_stack_as_is(inputs.stack)


class Threshold(ReconstructionMethod):
    """``threshold``: sec. 5.5, threshold at mean + k·σ, dilate, multiply back (the thesis)."""

    name = "threshold"
    description = "thesis sec. 5.5: keep voxels above mean + k·σ of the focal stack, dilate the mask"
    requires = ("stack",)
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "k": {
            "type": "number",
            "minimum": 0,
            "maximum": 100,
            "description": "threshold in standard deviations above the volume mean (thesis: 3)",
        },
        "dilation_radius": {
            "type": "integer",
            "minimum": 0,
            "maximum": 10,
            "description": "radius [voxels] of the disk dilating the mask (thesis: 1)",
        },
        "dilation_ndim": {
            "type": "integer",
            "enum": [2, 3],
            "description": "2: dilate each plane (the thesis' imdilate); 3: a 3-D ball",
        },
    }

    def run(
        self,
        inputs: ReconstructionInputs,
        *,
        k: float = 3.0,
        dilation_radius: int = 1,
        dilation_ndim: int = 2,
        progress: bool = False,
    ) -> xr.DataArray:
        return threshold_dilate(inputs.stack, k=k, dilation_radius=dilation_radius, dilation_ndim=dilation_ndim)
