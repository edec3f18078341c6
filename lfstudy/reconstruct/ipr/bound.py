"""How well a particle's position can be read from its image at all: the Cramér–Rao bound.

A particle fit (IPR) reads each particle's x, y, z and intensity from the raw image. However good the fit,
photon noise sets a limit: no unbiased estimator has a smaller standard deviation than the bound
``sqrt(diag F⁻¹)`` of the Fisher information ``F`` of the image about those four parameters. On the
plenoptic camera the bound depends strongly on depth. Near the focal plane a particle lights one lenslet's
aperture image whatever its exact depth, so the image says little about z, or about x and y within that
lenslet. Away from focus, the spot spreads over several lenslets, and their pattern gives depth in fine steps.

:func:`position_bound` computes the bound from the exact expected images (:func:`particle_patches`, the
images the Monte-Carlo renderer draws from) with Poisson ray counts. Each ray deposits its particle's
intensity ``I`` into one pixel (:mod:`lfstudy.simulate.raytrace`). So a pixel's mean is ``Σ_k I_k R g_k``
and its variance ``Σ_k I_k² R g_k``, where ``R`` is the rays per particle and ``g_k`` particle k's image of
unit intensity. In the *crowded* bound the neighbours' light enters the variance: their photons are noise
in the pixels they share. Their positions are taken as known, so the bound of a joint fit of all particles
is larger again. The *isolated* bound leaves the neighbours out.

``benchmarks/bench_position_bound.py`` compares the demo's IPR fits with this bound per depth band.

References
----------
S. M. Kay, *Fundamentals of Statistical Signal Processing: Estimation Theory*, Prentice Hall 1993, ch. 3
(the bound). R. J. Ober, S. Ram, E. S. Ward, "Localization
accuracy in single-molecule microscopy", Biophys. J. 86 (2004) 1185 (the same bound for a particle's image).
"""

from __future__ import annotations

import numpy as np

from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct.ipr.patches import particle_patches
from lfstudy.reconstruct.registry import ReconstructionError

__all__ = ["fisher_information", "position_bound"]

#: Step of the central differences of the images [mm] (0.1 µm: far below a pixel's footprint, far above
#: the exact images' quadrature error).
STEP_MM = 1e-4


def fisher_information(
    camera: PlenopticCamera,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    intensity: np.ndarray,
    rays: float,
    *,
    crowded: bool = True,
) -> np.ndarray:
    """Fisher information of each particle's image about its (x, y, z, intensity), Poisson ray counts.

    Parameters
    ----------
    camera : PlenopticCamera
        The camera (unrotated lenslet grid, as :func:`particle_patches` requires).
    x, y, z : ndarray, shape (n,)
        The particles' positions [mm].
    intensity : ndarray, shape (n,)
        Their intensities (> 0); each of a particle's rays deposits its intensity.
    rays : float
        Rays (photons) per particle of unit solid angle (``raytrace.rays_per_particle``; > 0).
    crowded : bool
        Count the other particles' light in each pixel's variance (default); False: each particle alone.

    Returns
    -------
    ndarray, shape (n, 4, 4)
        ``F = Σ_p ∂μ_p ∂μ_pᵀ / var_p`` over the particle's patch, parameters (x [mm], y [mm], z [mm],
        intensity).
    """
    x, y, z = (np.asarray(v, dtype=np.float64).ravel() for v in (x, y, z))
    inten = np.asarray(intensity, dtype=np.float64).ravel()
    n = x.size
    if not (y.size == z.size == inten.size == n):
        raise ReconstructionError("position_bound: x, y, z and intensity need one value per particle")
    if not (np.isfinite(rays) and rays > 0):
        raise ReconstructionError(f"position_bound: `rays` must be > 0; got {rays!r}")
    if n and not (np.all(np.isfinite(inten)) and np.all(inten > 0)):
        raise ReconstructionError("position_bound: every `intensity` must be finite and > 0")
    out = np.zeros((n, 4, 4))
    if n == 0:
        return out
    h = STEP_MM
    trials = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0], [0, 0, h], [0, 0, -h]])
    pt, off, r0, c0, shp = particle_patches(camera, x, y, z, trials=trials)
    size = shp[:, 0] * shp[:, 1]
    if crowded:  # every particle's ray counts in the pixels it lights: the variance of their sum
        var = np.zeros((camera.n_pixels_y, camera.n_pixels_x))
        for i in range(n):
            hh, ww = shp[i]
            img = pt[off[i] : off[i] + size[i]].reshape(hh, ww)
            var[r0[i] : r0[i] + hh, c0[i] : c0[i] + ww] += inten[i] ** 2 * rays * img
    for i in range(n):
        hh, ww = shp[i]
        im = pt[off[i] : off[i] + 7 * size[i]].reshape(7, size[i]) * (inten[i] * rays)  # mean images
        # d mean / d (x, y, z) by central differences, d mean / d I exactly
        jac = np.stack([(im[1 + 2 * k] - im[2 + 2 * k]) / (2 * h) for k in range(3)] + [im[0] / inten[i]])
        v = var[r0[i] : r0[i] + hh, c0[i] : c0[i] + ww].ravel() if crowded else inten[i] * im[0]
        lit = v > 0
        out[i] = (jac[:, lit] / v[lit]) @ jac[:, lit].T
    return out


def position_bound(
    camera: PlenopticCamera,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    intensity: np.ndarray,
    rays: float,
    *,
    crowded: bool = True,
) -> np.ndarray:
    """The Cramér–Rao bound of each particle's x, y and z on Poisson images of ``rays`` rays per particle.

    The parameters are :func:`fisher_information`'s; the intensity is estimated alongside (its uncertainty
    enters the positions' bounds).

    Returns
    -------
    ndarray, shape (n, 3)
        ``sqrt(diag F⁻¹)`` of x, y, z [mm]; ``inf`` where the image holds no information (the Fisher matrix is
        singular, e.g. a particle whose light misses the sensor).

    Examples
    --------
    >>> from lfstudy.optics import PlenopticCamera
    >>> cam = PlenopticCamera(160, 160, 0.0074, 0.0888, 0.3552, 50.0, -1.0)
    >>> x, y, z = np.full(2, 0.013), np.full(2, -0.021), np.array([0.02, 1.5])  # inside one lenslet's footprint
    >>> b = position_bound(cam, x, y, z, np.ones(2), 4000, crowded=False)
    >>> bool(b[0, 2] > 20 * b[1, 2])  # depth is read far better away from the focal plane
    True
    """
    fisher = fisher_information(camera, x, y, z, intensity, rays, crowded=crowded)
    out = np.full((fisher.shape[0], 3), np.inf)
    for i, f in enumerate(fisher):
        try:
            d = np.diag(np.linalg.inv(f))[:3]
        except np.linalg.LinAlgError:
            continue
        if np.all(np.isfinite(d)) and np.all(d > 0):
            out[i] = np.sqrt(d)
    return out
