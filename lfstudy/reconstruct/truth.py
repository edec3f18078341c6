"""The true volume of a particle list: Gaussians integrated over each voxel.

One definition shared by the study (the reference of Q, the oracle's volumes:
:mod:`lfstudy.study.metrics` re-exports it) and by the reconstruction methods that fit
particles (:mod:`lfstudy.reconstruct.ipr` renders its particle list with it). It lives
here, below both, because a reconstruction method may not import the study.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import xarray as xr
from scipy.special import ndtr

__all__ = ["render_truth", "voxel_edges"]


def voxel_edges(coord: np.ndarray) -> np.ndarray:
    """Voxel boundaries of ascending centres: midpoints, the end voxels symmetric."""
    c = np.asarray(coord, dtype=float)
    if c.size == 1:
        return np.array([c[0] - 0.5, c[0] + 0.5])
    mid = 0.5 * (c[1:] + c[:-1])
    return np.concatenate([[2 * c[0] - mid[0]], mid, [2 * c[-1] - mid[-1]]])


def render_truth(
    coords: Mapping[str, np.ndarray],
    particles: xr.Dataset,
    *,
    sigma_mm: float | Sequence[float],
    truncate: float = 4.0,
) -> np.ndarray:
    """The true volume: every particle a Gaussian of physical size, integrated over each voxel.

    Parameters
    ----------
    coords : mapping with ``z``, ``y``, ``x``
        Ascending voxel centres [mm] (may be uneven; voxels end half-way to
        their neighbours).
    particles : xarray.Dataset
        ``x, y, z`` [mm] and optional ``intensity`` over ``particle``.
    sigma_mm : float or (sz, sy, sx)
        Gaussian standard deviation [mm] per axis.
    truncate : float
        Blobs are cut at ``truncate`` sigmas.

    Returns
    -------
    ndarray, shape (nz, ny, nx), float64
        Each particle's intensity spread over the voxels by the integral of its
        Gaussian over each voxel (exact for separable Gaussians), so the result
        does not depend on where the particle sits relative to the voxel centres.
        A particle off the grid adds the part of its Gaussian that lies on it; one
        more than ``truncate`` sigmas beyond the grid's edge adds nothing.
    """
    dims = ("z", "y", "x")
    shape = tuple(len(coords[d]) for d in dims)
    sig = np.broadcast_to(np.asarray(sigma_mm, dtype=float), (3,))
    if np.any(~np.isfinite(sig)) or np.any(sig <= 0):
        raise ValueError(f"sigma_mm = {sigma_mm!r}: must be > 0 mm per axis")
    out = np.zeros(shape, dtype=np.float64)
    n = particles.sizes.get("particle", len(particles["x"]))
    if n == 0:
        return out
    amp = np.asarray(particles["intensity"].values, float) if "intensity" in particles else np.ones(n)
    pos = [np.asarray(particles[d].values, float) for d in dims]
    # a particle whose truncated Gaussian misses the grid (e.g. one of a depth margin seeded beyond
    # it) adds nothing; the stencil clipped at the grid's ends would leak its far tail into the edge
    reach = np.ones(n, dtype=bool)
    for a, d in enumerate(dims):
        edges = voxel_edges(coords[d])
        reach &= (pos[a] + truncate * sig[a] > edges[0]) & (pos[a] - truncate * sig[a] < edges[-1])
    if not reach.all():
        amp, pos, n = amp[reach], [p[reach] for p in pos], int(reach.sum())
        if n == 0:
            return out
    idx, wts = [], []
    for a, d in enumerate(dims):
        edges = voxel_edges(coords[d])
        p = pos[a]
        lo = np.clip(np.searchsorted(edges, p - truncate * sig[a]) - 1, 0, shape[a] - 1)
        hi = np.clip(np.searchsorted(edges, p + truncate * sig[a]), 1, shape[a])
        span = int(max(1, (hi - lo).max()))
        i = lo[:, None] + np.arange(span)[None, :]
        valid = i < hi[:, None]
        i = np.minimum(i, shape[a] - 1)
        cdf = ndtr((edges[np.minimum(i + 1, shape[a])] - p[:, None]) / sig[a]) - ndtr((edges[i] - p[:, None]) / sig[a])
        idx.append(i)
        wts.append(np.where(valid, cdf, 0.0))
    # separable: per-axis weights on a (particle, offset) stencil, outer product, one bincount
    for k in range(0, n, 20000):  # bounded temporaries
        s = slice(k, k + 20000)
        flat = (idx[0][s, :, None, None] * shape[1] + idx[1][s, None, :, None]) * shape[2] + idx[2][s, None, None, :]
        val = amp[s, None, None, None] * wts[0][s, :, None, None] * wts[1][s, None, :, None] * wts[2][s, None, None, :]
        keep = val > 0
        out += np.bincount(flat[keep], weights=val[keep], minlength=out.size).reshape(shape)
    return out
