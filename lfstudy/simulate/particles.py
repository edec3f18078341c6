"""Seeded particle fields and the calibration pinhole field (thesis sec. 4.3.2, 5.1).

A particle field is an :class:`xarray.Dataset` over dimension ``particle``
with variables ``x``, ``y``, ``z`` (object frame, mm: origin where the object
focal plane meets the optical axis, +z away from the camera, Fig. 4.16) and
``intensity`` (relative scattering coefficient).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = ["ParticleError", "particle_count", "seed_particles", "pinhole_field", "pinhole_spans", "make_field"]


class ParticleError(ValueError):
    """Bad particle-field input (names the field and allowed range)."""


def particle_count(camera: PlenopticCamera, ppp: float) -> int:
    """Number of particles for a seeding density in particles per **sensor** pixel.

    Sec. 7.1: ppp counts the CCD pixels, not the refocused voxels
    (Table 4.3 at 0.001 ppp → 15,824 particles).
    """
    if not (isinstance(ppp, (int, float)) and math.isfinite(ppp) and 0 < ppp <= 1):
        raise ParticleError(f"ppp = {ppp!r}: allowed range is (0, 1] particles per sensor pixel")
    return round(ppp * camera.n_pixels_x * camera.n_pixels_y)


def make_field(x: np.ndarray, y: np.ndarray, z: np.ndarray, intensity: np.ndarray, **attrs: object) -> xr.Dataset:
    """Wrap particle coordinates into the labelled particle-field Dataset."""
    x, y, z, intensity = (np.asarray(a, dtype=np.float64) for a in (x, y, z, intensity))
    n = x.shape[0]
    if not (y.shape == z.shape == intensity.shape == (n,)):
        raise ParticleError("x, y, z and intensity must be 1-D arrays of one length")
    for name, a in (("x", x), ("y", y), ("z", z), ("intensity", intensity)):
        if not np.all(np.isfinite(a)):
            raise ParticleError(f"particle {name}: {int((~np.isfinite(a)).sum())} non-finite values")
    if np.any(intensity < 0):
        raise ParticleError("particle intensity: must be >= 0")
    mm = lambda ln: {"units": "mm", "long_name": ln}  # noqa: E731
    return xr.Dataset(
        {
            "x": ("particle", x, mm("particle x (object frame)")),
            "y": ("particle", y, mm("particle y (object frame)")),
            "z": ("particle", z, mm("particle depth z, +z away from camera")),
            "intensity": ("particle", intensity, {"units": "1", "long_name": "relative intensity"}),
        },
        coords={"particle": ("particle", np.arange(n), {"units": "1", "long_name": "particle id"})},
        attrs=dict(attrs),
    )


def seed_particles(
    camera: PlenopticCamera,
    *,
    ppp: float | None = None,
    count: int | None = None,
    x_span: float | None = None,
    y_span: float | None = None,
    z_span: float = 0.0,
    intensity: Sequence[float] = (1.0, 1.0),
    seed: int = 0,
) -> xr.Dataset:
    """Uniformly seeded particle field (sec. 4.3.2).

    Parameters
    ----------
    camera : PlenopticCamera
        Supplies the default x/y spans (its field of view) and the pixel
        count for ``ppp``.
    ppp, count : float or int
        Seeding as particles per sensor pixel, or an explicit count (exactly one).
    x_span, y_span : float, optional
        Extents centred on the optical axis [mm]; default the field of view.
    z_span : float
        Depth extent centred on the focal plane [mm] (thesis: 0–7 mm).
    intensity : (float, float)
        Bounds imin, imax of the uniform intensity coefficient.
    seed : int
        Seed of the NumPy ``Generator`` (PCG64); the same seed gives the same field.
    """
    if (ppp is None) == (count is None):
        raise ParticleError("give exactly one of ppp (particles per pixel) or count")
    n = particle_count(camera, ppp) if ppp is not None else count
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ParticleError(f"count = {n!r}: must be an integer >= 1")
    xs = camera.fov_x if x_span is None else x_span
    ys = camera.fov_y if y_span is None else y_span
    for name, v in (("x_span", xs), ("y_span", ys), ("z_span", z_span)):
        if not (math.isfinite(v) and v >= 0):
            raise ParticleError(f"{name} = {v!r}: must be a finite number >= 0 mm")
    if z_span / 2 >= camera.so - camera.main_focal_length:
        raise ParticleError(
            f"z_span = {z_span}: particles would reach the main lens' focal length; "
            f"allowed range is [0, {2 * (camera.so - camera.main_focal_length):.4g}) mm"
        )
    lo, hi = (float(v) for v in intensity)
    if not (0 <= lo <= hi):
        raise ParticleError(f"intensity = {list(intensity)}: need 0 <= imin <= imax")
    rng = np.random.default_rng(seed)
    u = rng.random((4, int(n)))
    return make_field(
        (u[0] - 0.5) * xs,
        (u[1] - 0.5) * ys,
        (u[2] - 0.5) * z_span,
        lo + (hi - lo) * u[3],
        seed=int(seed),
        ppp=float(ppp) if ppp is not None else float(n) / (camera.n_pixels_x * camera.n_pixels_y),
        x_span=float(xs),
        y_span=float(ys),
        z_span=float(z_span),
    )


def pinhole_spans(camera: PlenopticCamera) -> tuple[float, float]:
    """x and y extent [mm] of the calibration field: the field of view plus one lenslet on each side."""
    margin = 2 * camera.lenslet_pitch / abs(camera.magnification)
    return camera.fov_x + margin, camera.fov_y + margin


def pinhole_field(camera: PlenopticCamera, *, count: int = 500_000, seed: int = 0) -> xr.Dataset:
    """Calibration "pinhole" field (sec. 5.1): many points on the object focal plane.

    The thesis used 500,000 points × 100 rays at f/16 to approximate a uniform
    field; image it with ``camera.with_(fnumber=16)``. Points cover
    :func:`pinhole_spans` (the field of view plus one lenslet) so edge lenslets are lit too.
    """
    xs, ys = pinhole_spans(camera)
    return seed_particles(camera, count=count, x_span=xs, y_span=ys, z_span=0.0, seed=seed)
