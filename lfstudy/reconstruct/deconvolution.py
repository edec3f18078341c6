"""3-D deconvolution of the focal stack: Richardson–Lucy with the refocused PSF (sec. 5.6, the cheap option).

A focal stack is the particle volume blurred by the refocusing: a point at depth
z0 appears in the plane at z as a disc of diameter ~ aperture·|z − z0|/Do
(convolved with the lenslet sampling), so the stack is S = H·E with

    S[z] = Σ_z0 PSF_z0[z] ⊛ E[z0]      (⊛: 2-D convolution in x, y),

a depth-dependent, laterally shift-invariant blur. Each PSF_z0 is computed
from the camera model: the light field of a unit voxel at depth z0 on the
optical axis (the plenoptic projector of :mod:`lfstudy.reconstruct.projector`,
on the central lenslets of the calibrated light field) refocused onto the
grid's planes by the very code that made the stack
(:func:`lfstudy.lightfield.focal_stack`), so the model and the data share
every approximation.

Richardson–Lucy (Richardson 1972; Lucy 1974; references in :func:`richardson_lucy`) then iterates

    E ← E · Hᵀ(S / H·E) / Hᵀ·1,

which stays non-negative and conserves the signal; the convolutions are done
in Fourier space for all plane pairs at once.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import scipy.fft as sfft
import xarray as xr
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

__all__ = ["RichardsonLucy", "refocused_psf", "richardson_lucy"]


def refocused_psf(
    lightfield: xr.DataArray, camera: PlenopticCamera, grid: ReconstructionGrid, *, radius: int | None = None
) -> np.ndarray:
    """Focal-stack response to a unit voxel at every depth of the grid, on the optical axis.

    Parameters
    ----------
    lightfield : xarray.DataArray
        A registered light field (its coordinates give the calibrated geometry).
    camera : PlenopticCamera
    grid : ReconstructionGrid
    radius : int, optional
        Half-width of the PSF in voxels; default: the largest refocusing blur
        over the grid's depth, plus 3.

    Returns
    -------
    ndarray, shape (nz, nz, 2r + 1, 2r + 1)
        ``psf[k0, k]``: the stack plane k of a unit voxel at plane k0, centred.
    """
    from lfstudy.lightfield.refocus import StackOperator

    dz_max = float(grid.z.max() - grid.z.min())
    d_min = camera.so + float(grid.z.min())
    blur = (camera.aperture_diameter / 2.0) * dz_max / d_min  # disc radius at the farthest plane [mm]
    r = int(radius) if radius is not None else int(np.ceil(blur / grid.dx)) + 3
    # The central lenslets and a grid patch around the axis: the PSF is local.
    lr, lc = lightfield.sizes["lrow"], lightfield.sizes["lcol"]
    h = min(r + 4, lr // 2, lc // 2)
    sub = lightfield.isel(lrow=slice(lr // 2 - h, lr // 2 + h + 1), lcol=slice(lc // 2 - h, lc // 2 + h + 1))
    # Grid patch centred on the voxel nearest the axis (x, y grids contain or straddle 0).
    i0, j0 = int(np.argmin(np.abs(grid.x))), int(np.argmin(np.abs(grid.y)))
    xs = slice(max(i0 - r, 0), i0 + r + 1)
    ys = slice(max(j0 - r, 0), j0 + r + 1)
    patch = ReconstructionGrid(grid.x[xs], grid.y[ys], grid.z, grid.spacing)
    proj = PlenopticProjector(sub, camera, patch)
    refocus = StackOperator(sub, camera, camera.planes_at(grid.z), x=patch.x, y=patch.y)
    psf = np.zeros((grid.z.size, grid.z.size, 2 * r + 1, 2 * r + 1))
    ci, cj = i0 - xs.start, j0 - ys.start
    for k0 in range(grid.z.size):
        # light field of one voxel, refocused onto the patch by the code that makes the stack
        st = refocus(proj.impulse(k0, cj, ci))
        psf[k0, :, r - cj : r - cj + st.shape[1], r - ci : r - ci + st.shape[2]] = st
    return psf


def richardson_lucy(
    stack: xr.DataArray,
    psf: np.ndarray,
    grid: ReconstructionGrid,
    *,
    iterations: int = 30,
    epsilon: float = 1e-6,
    workers: int | None = None,
    progress: bool = False,
) -> tuple[np.ndarray, list[float]]:
    """Richardson–Lucy deconvolution with a depth-dependent, laterally shift-invariant PSF.

    The iteration of Richardson [1]_ and Lucy [2]_, E ← E · Hᵀ(S / H·E) / Hᵀ·1,
    with H the blur of the focal stack (see the module docstring).

    Parameters
    ----------
    stack : xarray.DataArray
        The focal stack on ``grid`` (non-negative).
    psf : ndarray (nz, nz, 2r + 1, 2r + 1)
        ``psf[k0, k]``: plane k of the stack of a unit voxel at plane k0 (:func:`refocused_psf`).
    grid : ReconstructionGrid
    iterations : int
        RL iterations.
    epsilon : float
        Relative floor of the model H·E in the ratio S / H·E (guards 0/0).
    workers : int, optional
        Threads of scipy.fft (results do not depend on it).
    progress : bool

    Returns
    -------
    volume : ndarray (nz, ny, nx)
    residual : list of float
        ‖H·E − S‖ / ‖S‖ before each update.

    References
    ----------
    .. [1] W. H. Richardson, "Bayesian-based iterative method of image
           restoration", Journal of the Optical Society of America 62 (1)
           pp 55--59 (1972), doi:10.1364/JOSA.62.000055
    .. [2] L. B. Lucy, "An iterative technique for the rectification of observed
           distributions", The Astronomical Journal 79 (6) pp 745--754 (1974),
           doi:10.1086/111605
    """
    s = np.maximum(np.asarray(stack.values, dtype=np.float64), 0.0)
    nz, ny, nx = s.shape
    r = psf.shape[-1] // 2
    shape = (sfft.next_fast_len(ny + 2 * r, real=True), sfft.next_fast_len(nx + 2 * r, real=True))
    kern = np.zeros((nz, nz, *shape))
    # kernel centred at index 0 (wrapped), so the convolution is aligned
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            kern[:, :, dy % shape[0], dx % shape[1]] = psf[:, :, dy + r, dx + r]
    # per frequency, the nz x nz matrix mixing source planes into stack planes: [freq, b, a]
    fk = sfft.rfft2(kern, axes=(2, 3), workers=workers).astype(np.complex64)
    del kern
    nf = fk.shape[2] * fk.shape[3]
    mix = np.ascontiguousarray(fk.reshape(nz, nz, nf).transpose(2, 1, 0))
    mix_t = np.ascontiguousarray(np.conj(mix).transpose(0, 2, 1))
    del fk

    def apply(vol: np.ndarray, m: np.ndarray) -> np.ndarray:
        fv = sfft.rfft2(vol, s=shape, axes=(1, 2), workers=workers).astype(np.complex64)
        fshape = fv.shape
        out = np.matmul(m, fv.reshape(nz, nf).T[:, :, None])[:, :, 0]  # batched over frequencies
        return sfft.irfft2(out.T.reshape(fshape), s=shape, axes=(1, 2), workers=workers)[:, :ny, :nx]

    def h(vol: np.ndarray) -> np.ndarray:  # S = Σ_k0 psf[k0] ⊛ E[k0]
        return apply(vol, mix)

    def ht(img: np.ndarray) -> np.ndarray:  # adjoint: correlation with the PSF
        return apply(img, mix_t)

    norm = np.maximum(ht(np.ones_like(s)), 1e-12)
    vol = np.full(s.shape, s.mean() if s.mean() > 0 else 1.0)
    floor = epsilon * max(float(s.max()), 1e-300)
    s_norm = float(np.linalg.norm(s)) or 1.0
    res: list[float] = []
    for _ in tqdm(range(iterations), desc="Richardson-Lucy", unit="it", disable=not progress):
        model = h(vol)
        res.append(float(np.linalg.norm(model - s)) / s_norm)
        ratio = s / np.maximum(model, floor)
        vol *= np.maximum(ht(ratio), 0.0) / norm  # FFT round-off may dip below 0: clip
    return vol, res


class RichardsonLucy(ReconstructionMethod):
    """``deconvolution``: Richardson–Lucy 3-D deconvolution of the focal stack with the refocused PSF."""

    name = "deconvolution"
    description = "Richardson-Lucy 3-D deconvolution of the focal stack with the depth-dependent refocused PSF"
    requires = ("stack", "lightfield", "camera", "grid")
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "iterations": {
            "type": "integer",
            "minimum": 1,
            "maximum": 1000,
            "description": "Richardson-Lucy iterations",
        },
        "epsilon": {
            "type": "number",
            "exclusiveMinimum": 0,
            "maximum": 1,
            "description": "floor of the model in S / (H E), relative to the stack maximum",
        },
    }

    @classmethod
    def memory_bytes(cls, size: ReconstructionSize, params: Mapping[str, Any] | None = None) -> float:
        """The base's arrays, the nz x nz PSF spectra over the padded planes and six float64 volumes."""
        nz, nvox = size.n_planes, size.n_voxels
        return super().memory_bytes(size, params) + (nz * nz * nvox / nz * 8 * 1.3 + 6 * nvox * 8)

    def run(
        self,
        inputs: ReconstructionInputs,
        *,
        iterations: int = 30,
        epsilon: float = 1e-6,
        progress: bool = False,
    ) -> xr.DataArray:
        stack, grid = inputs.stack, inputs.grid
        if not np.all(np.isfinite(np.asarray(stack.values))):
            raise ReconstructionError("the focal stack has non-finite voxels")
        t0 = time.perf_counter()
        psf = refocused_psf(inputs.lightfield, inputs.camera, grid)
        t1 = time.perf_counter()
        vol, res = richardson_lucy(stack, psf, grid, iterations=iterations, epsilon=epsilon, progress=progress)
        t2 = time.perf_counter()
        return grid.volume(
            vol.astype(np.float32),
            long_name="reconstructed intensity (Richardson-Lucy deconvolution of the focal stack)",
            units=str(stack.attrs.get("units", "counts")),
            iterations=int(iterations),
            epsilon=float(epsilon),
            residual=[float(x) for x in res],
            psf_radius_voxels=int(psf.shape[-1] // 2),
            psf_seconds=float(t1 - t0),
            seconds_per_iteration=float((t2 - t1) / max(iterations, 1)),
        )
