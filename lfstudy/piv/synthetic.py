"""Synthetic Gaussian-particle image/volume pairs for testing ``lfstudy.piv``.

Particles are rendered analytically: each voxel receives the integral of an
isotropic Gaussian over its extent (a product of erf differences per axis), so
sub-voxel displacements are represented exactly and the known displacement is
the ground truth against which the PIV engine is measured.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from math import sqrt

import numpy as np
from scipy.special import erf

__all__ = ["render_particles", "particle_pair"]


def render_particles(
    positions: np.ndarray,
    shape: Sequence[int],
    *,
    diameter: float | Sequence[float] = 2.8,
    intensity: np.ndarray | float = 1.0,
) -> np.ndarray:
    """Render Gaussian particles into a 2-D or 3-D array.

    Parameters
    ----------
    positions : ndarray, shape (P, ndim)
        Particle centres in array-index units (voxel ``i`` spans ``[i-0.5, i+0.5]``).
    shape : sequence of int
        Output array shape (``ndim`` = 2 or 3).
    diameter : float or sequence of float
        e^-2 particle image diameter in voxels (sigma = diameter / 4), or one per
        axis (an elongated particle, as a plenoptic reconstruction makes in z).
    intensity : float or ndarray, shape (P,)
        Integrated intensity of each particle.

    Returns
    -------
    ndarray
        float64 array of ``shape``.
    """
    shape = tuple(int(s) for s in shape)
    nd = len(shape)
    pos = np.asarray(positions, dtype=float).reshape(-1, nd)
    sigmas = np.broadcast_to(np.asarray(diameter, dtype=float) / 4.0, (nd,))
    weights = np.broadcast_to(np.asarray(intensity, dtype=float), (pos.shape[0],))
    prof_list, idx_list, ok_list = [], [], []
    for ax in range(nd):  # loop over axes, not particles
        half = int(np.ceil(4.0 * sigmas[ax])) + 1  # support well beyond the Gaussian tail
        offs = np.arange(-half, half + 1)
        s2 = sqrt(2.0) * sigmas[ax]
        i = np.floor(pos[:, ax] + 0.5).astype(np.int64)[:, None] + offs  # (P, K)
        d = i - pos[:, ax, None]
        prof = 0.5 * (erf((d + 0.5) / s2) - erf((d - 0.5) / s2))
        prof_list.append(prof)
        idx_list.append(i)
        ok_list.append((i >= 0) & (i < shape[ax]))
    # outer products per particle over the local support
    vals = weights[:, None] * prof_list[0]
    flat = idx_list[0]
    ok = ok_list[0]
    for ax in range(1, nd):
        vals = (vals[..., None] * prof_list[ax][:, None, :]).reshape(pos.shape[0], -1)
        flat = (flat[..., None] * shape[ax] + idx_list[ax][:, None, :]).reshape(pos.shape[0], -1)
        ok = (ok[..., None] & ok_list[ax][:, None, :]).reshape(pos.shape[0], -1)
    out = np.bincount(flat[ok], weights=vals[ok], minlength=int(np.prod(shape)))
    return out.reshape(shape)


def particle_pair(
    shape: Sequence[int],
    displacement: Sequence[float] | Callable[[np.ndarray], np.ndarray],
    *,
    density: float = 0.01,
    diameter: float | Sequence[float] = 2.8,
    seed: int = 0,
    margin: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Two frames of the same random particles, the second displaced.

    The displacement is defined at the particle's *mid-point* position ``m``:
    frame ``a`` has the particle at ``m - d(m)/2`` and frame ``b`` at
    ``m + d(m)/2``, so a PIV estimate at a window centre ``c`` has the exact
    truth ``d(c)`` even for non-uniform (sheared, rotating) fields.

    Parameters
    ----------
    shape : sequence of int
        Frame shape, (y, x) or (z, y, x).
    displacement : sequence of float or callable
        Uniform displacement per array axis (axis order), or a function mapping
        positions (P, ndim) in index units to displacements (P, ndim).
    density : float
        Particles per voxel (pixel in 2-D).
    diameter : float or sequence of float
        e^-2 particle image diameter in voxels (one per axis for elongated particles).
    seed : int
        Seed of the random positions and intensities.
    margin : int
        Particles are seeded this far beyond each face so that particles enter
        and leave the frame naturally.

    Returns
    -------
    a, b : ndarray
        The two frames (float64).
    """
    shape = tuple(int(s) for s in shape)
    nd = len(shape)
    rng = np.random.default_rng(seed)
    ext = np.array(shape, dtype=float) + 2 * margin
    n = rng.poisson(density * float(np.prod(ext)))
    m = rng.random((n, nd)) * ext - margin - 0.5
    inten = rng.uniform(0.5, 1.0, n)
    if callable(displacement):
        d = np.asarray(displacement(m), dtype=float).reshape(n, nd)
    else:
        d = np.broadcast_to(np.asarray(displacement, dtype=float), (n, nd))
    a = render_particles(m - d / 2, shape, diameter=diameter, intensity=inten)
    b = render_particles(m + d / 2, shape, diameter=diameter, intensity=inten)
    return a, b
