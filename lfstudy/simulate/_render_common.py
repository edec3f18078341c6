"""What the Monte-Carlo tracer and the exact renderer share: input checks, the solid angle and
ray counts (eq. 4.14), the sensor coordinates, the noise / integer export, and one camera
geometry vector that both numba kernels read.

Private: :mod:`~lfstudy.simulate.raytrace` and :mod:`~lfstudy.simulate.exact` import this
module and never each other, except the method dispatch of
:func:`lfstudy.simulate.raytrace.render`; the public names are re-exported there and from
:mod:`lfstudy.simulate`.

Geometry vector
---------------
A float64 vector (numba freezes module globals at compile time, so everything that varies
from camera to camera is an argument), built by :func:`_geometry`. Lengths in mm, in the
sensor frame (origin at the sensor centre, x right, y up):

==========  =====  ==========================================================  ======
name        index  meaning                                                     units
==========  =====  ==========================================================  ======
_G_SO       0      object distance so (object focal plane to main lens)        mm
_G_SI       1      image distance si (main lens to lenslet plane)              mm
_G_FM       2      main-lens focal length fm                                   mm
_G_FL       3      lenslet focal length fl (lenslet plane to sensor)           mm
_G_R        4      main-lens aperture radius R                                 mm
_G_PL       5      lenslet pitch pl                                            mm
_G_PP       6      pixel pitch pp                                              mm
_G_HW       7      sensor half-width                                           mm
_G_HH       8      sensor half-height                                          mm
_G_OX       9      lenslet grid origin x (offset of the grid centre)           mm
_G_OY       10     lenslet grid origin y                                       mm
_G_COS      11     cos of the lenslet grid rotation                            1
_G_SIN      12     sin of the lenslet grid rotation                            1
_G_NLX      13     lenslets per row                                            count
_G_NLY      14     lenslets per column                                         count
_G_SM       15     σm, diffraction blur at the lenslet plane (0: none)         mm
_G_SL       16     σl, diffraction blur at the sensor plane (0: none)          mm
_G_NROW     17     pixel rows                                                  count
_G_NCOL     18     pixel columns                                               count
==========  =====  ==========================================================  ======
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
import xarray as xr
from numba import njit

from lfstudy.optics import PlenopticCamera

#: Particle chunks (= image buffers) of the kernels. Fixed so that the image is
#: the same whatever the thread count; more threads than chunks gain nothing.
DEFAULT_CHUNKS = 8


class RaytraceError(ValueError):
    """Bad simulator input (the message names the field and its allowed range)."""


# The geometry vector (table in the module docstring).
_G_SO, _G_SI, _G_FM, _G_FL, _G_R, _G_PL, _G_PP, _G_HW, _G_HH = range(9)
_G_OX, _G_OY, _G_COS, _G_SIN, _G_NLX, _G_NLY, _G_SM, _G_SL, _G_NROW, _G_NCOL = range(9, 19)
_G_GAP, _G_TLX, _G_TLY, _G_SCAT = range(19, 23)
_G_SIZE = 23


def _geometry(
    camera: PlenopticCamera,
    sm: float,
    sl: float,
    *,
    gap: float | None = None,
    tilt: tuple[float, float] = (0.0, 0.0),
    scatter: np.ndarray | None = None,
) -> np.ndarray:
    """The geometry vector of ``camera`` with the diffraction blurs (σm, σl) in mm (0: none).

    ``gap`` (lenslet-to-sensor distance, default the lenslet focal length), ``tilt`` (θx, θy)
    [rad] and ``scatter`` (per-lenslet centre offsets, shape (nly, nlx, 2) [mm]) are the imaging
    imperfections of :mod:`lfstudy.simulate.imperfections`.
    """
    nt = 0 if scatter is None else 2 * camera.n_lenslets_x * camera.n_lenslets_y
    g = np.zeros(_G_SIZE + nt)
    g[_G_SO], g[_G_SI], g[_G_FM] = camera.so, camera.si, camera.main_focal_length
    g[_G_FL], g[_G_R] = camera.lenslet_focal_length, camera.aperture_diameter / 2.0
    g[_G_PL], g[_G_PP] = camera.lenslet_pitch, camera.pixel_pitch
    g[_G_HW], g[_G_HH] = camera.sensor_width / 2.0, camera.sensor_height / 2.0
    g[_G_OX], g[_G_OY] = camera.lenslet_offset_x, camera.lenslet_offset_y
    g[_G_COS], g[_G_SIN] = math.cos(camera.lenslet_rotation), math.sin(camera.lenslet_rotation)
    g[_G_NLX], g[_G_NLY] = camera.n_lenslets_x, camera.n_lenslets_y
    g[_G_SM], g[_G_SL] = sm, sl
    g[_G_NROW], g[_G_NCOL] = camera.n_pixels_y, camera.n_pixels_x
    g[_G_GAP] = camera.lenslet_focal_length if gap is None else gap
    g[_G_TLX], g[_G_TLY] = tilt
    if scatter is not None:
        table = np.asarray(scatter, dtype=np.float64)
        if table.shape != (camera.n_lenslets_y, camera.n_lenslets_x, 2):
            raise RaytraceError(f"scatter: shape {table.shape}; need (n_lenslets_y, n_lenslets_x, 2)")
        g[_G_SCAT] = 1.0
        g[_G_SIZE:] = table.ravel()
    return g


def _blurs(
    camera: PlenopticCamera, diffraction: bool, sigmas: tuple[float, float] | None = None
) -> tuple[float, float]:
    """(σm, σl) in mm: ``sigmas`` if given (validated), else the camera's diffraction blurs or none."""
    if sigmas is None:
        return (camera.sigma_lenslet_plane, camera.sigma_sensor_plane) if diffraction else (0.0, 0.0)
    try:
        sm, sl = (float(v) for v in sigmas)
    except (TypeError, ValueError):
        raise RaytraceError(f"sigmas = {sigmas!r}: must be two numbers (σm, σl) in mm") from None
    if not (math.isfinite(sm) and math.isfinite(sl) and sm >= 0.0 and sl >= 0.0):
        raise RaytraceError(f"sigmas = {sigmas!r}: allowed range is finite and >= 0 mm")
    return sm, sl


# ------------------------------------------------------------------ inputs
def _check_rays(rays_per_particle: Any, name: str = "rays_per_particle") -> int:
    if isinstance(rays_per_particle, bool) or not isinstance(rays_per_particle, (int, np.integer)):
        raise RaytraceError(f"{name} = {rays_per_particle!r}: must be an integer >= 1")
    if rays_per_particle < 1:
        raise RaytraceError(f"{name} = {rays_per_particle!r}: must be an integer >= 1")
    return int(rays_per_particle)


def _particle_arrays(camera: PlenopticCamera, particles: xr.Dataset) -> tuple[np.ndarray, ...]:
    """Validated contiguous float64 arrays x, y, z, intensity."""
    try:
        arrs = [
            np.ascontiguousarray(np.asarray(particles[v].values, dtype=np.float64).ravel())
            for v in ("x", "y", "z", "intensity")
        ]
    except KeyError as exc:
        raise RaytraceError(f"particles: missing variable {exc.args[0]!r}; need x, y, z, intensity") from None
    x, y, z, inten = arrs
    if x.size == 0:
        raise RaytraceError("particles: the particle set is empty; need at least 1 particle")
    if not (x.size == y.size == z.size == inten.size):
        raise RaytraceError("particles: x, y, z and intensity must have one length")
    for name, a in (("x", x), ("y", y), ("z", z), ("intensity", inten)):
        bad = ~np.isfinite(a)
        if bad.any():
            raise RaytraceError(f"particles.{name}: {int(bad.sum())} NaN/inf values; must be finite")
    if np.any(inten < 0):
        raise RaytraceError(f"particles.intensity: {int((inten < 0).sum())} negative values; allowed range is >= 0")
    zmin = camera.main_focal_length - camera.so
    if np.any(z <= zmin):
        raise RaytraceError(
            f"particles.z: {int((z <= zmin).sum())} particles at or inside the main-lens focal length "
            f"(or behind the lens); allowed range is z > f - so = {zmin:.6g} mm"
        )
    return x, y, z, inten


# ---------------------------------------------------------- solid angle
@lru_cache(maxsize=8)
def _aperture_nodes(rad: float, n_radial: int, n_angular: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quadrature nodes (x, y) on the aperture disc of radius ``rad`` and their weights (including the
    Jacobian r dr dφ): Gauss–Legendre in r, the trapezoid rule in φ. Read-only, made once per disc."""
    t, w = np.polynomial.legendre.leggauss(n_radial)
    r = 0.5 * rad * (t + 1.0)
    wr = 0.5 * rad * w * r  # includes the Jacobian r dr
    phi = np.arange(n_angular) * (2.0 * np.pi / n_angular)
    ax = (r[:, None] * np.cos(phi)[None, :]).ravel()
    ay = (r[:, None] * np.sin(phi)[None, :]).ravel()
    wa = np.repeat(wr, n_angular) * (2.0 * np.pi / n_angular)
    for a in (ax, ay, wa):
        a.flags.writeable = False
    return ax, ay, wa


@njit(cache=True, fastmath={"contract"})
def _solid_angle_kernel(x, y, z, so, ax, ay, wa, out):  # pragma: no cover - jitted
    """out[i] = Σ_j wa[j]·d/r³ (d = so + z[i], r the distance from point i to node j): one pass over the
    nodes per point, no point-by-node temporaries (IPR asks for a few hundred points at a time, thousands of
    times a fit)."""
    for i in range(x.size):
        d = so + z[i]
        dd = d * d
        acc = 0.0
        for j in range(ax.size):
            dx = ax[j] - x[i]
            dy = ay[j] - y[i]
            r2 = dd + dx * dx + dy * dy
            acc += wa[j] * (d / (r2 * math.sqrt(r2)))
        out[i] = acc


def solid_angle(
    camera: PlenopticCamera, x: np.ndarray, y: np.ndarray, z: np.ndarray, *, n_radial: int = 16, n_angular: int = 32
) -> np.ndarray:
    """Solid angle [sr] the main-lens aperture disc subtends from points (x, y, z).

    Gauss–Legendre quadrature in the aperture radius and the (periodic,
    spectrally accurate) trapezoid rule in azimuth of dΩ = d·dA / r³, with
    d = so + z the axial distance; exact to ~1e-12 for the paraxial
    geometries of interest.
    """
    x, y, z = (np.ascontiguousarray(np.atleast_1d(np.asarray(a, dtype=np.float64))) for a in (x, y, z))
    ax, ay, wa = _aperture_nodes(float(camera.aperture_diameter / 2.0), int(n_radial), int(n_angular))
    out = np.empty(x.shape)
    _solid_angle_kernel(x.ravel(), y.ravel(), z.ravel(), float(camera.so), ax, ay, wa, out.reshape(-1))
    return out


def ray_counts(
    camera: PlenopticCamera, particles: xr.Dataset, rays_per_particle: int, *, solid_angle_correction: bool = True
) -> np.ndarray:
    """Rays traced for each particle: eq. 4.14 generalised to 2-D.

    ``round(n · Ω_i / Ω_ref)``, Ω_ref being the aperture's solid angle from the
    on-axis point of the object focal plane, 2π(1 − so/√(so² + R²)).
    """
    n = _check_rays(rays_per_particle)
    x, y, z, _ = _particle_arrays(camera, particles)
    if not solid_angle_correction:
        return np.full(x.size, n, dtype=np.int64)
    rad = camera.aperture_diameter / 2.0
    ref = 2.0 * np.pi * (1.0 - camera.so / math.hypot(camera.so, rad))
    return np.rint(n * solid_angle(camera, x, y, z) / ref).astype(np.int64)  # eq. 4.14


# ------------------------------------------------------------------ outputs
def _sensor_coords(camera: PlenopticCamera) -> dict[str, Any]:
    x, y = camera.pixel_centers()
    return {
        "x": ("col", x, {"units": "mm", "long_name": "sensor x (pixel centre)"}),
        "y": ("row", y, {"units": "mm", "long_name": "sensor y (pixel centre, up)"}),
    }


def _check_noise(read_noise: Any, bit_depth: Any) -> None:
    """The noise and export options of :func:`render`, checked before any work."""
    if not (isinstance(read_noise, (int, float)) and math.isfinite(read_noise) and read_noise >= 0):
        raise RaytraceError(f"read_noise = {read_noise!r}: must be a finite number >= 0")
    if bit_depth is not None and (not isinstance(bit_depth, (int, np.integer)) or not 1 <= bit_depth <= 32):
        raise RaytraceError(f"bit_depth = {bit_depth!r}: allowed range is 1..32")


def _finish(
    da: xr.DataArray, seed: int, shot_noise: bool, read_noise: float, full_well: float | None, bit_depth: int | None
) -> xr.DataArray:
    """The optional noise and integer export of :func:`render` (either method).

    The noise is :func:`lfstudy.simulate.sensor.apply_sensor` with one photo-electron
    per unit of intensity (photons per particle = rays per particle, quantum
    efficiency 1, no dark level or full well): Poisson shot noise, then Gaussian
    read noise. Read noise can make a pixel negative; it stays negative here (an
    unbiased float signal) and :func:`quantize` clips it to 0.
    """
    if shot_noise or read_noise > 0:
        from lfstudy.simulate.sensor import apply_sensor

        n = int(da.attrs["rays_per_particle"])
        attrs = dict(da.attrs)
        da = apply_sensor(
            da, photons_per_particle=n, shot_noise=bool(shot_noise), read_noise=float(read_noise), seed=int(seed)
        )
        da.attrs.update(
            units=attrs.get("units", "1"),
            long_name=attrs.get("long_name", ""),
            shot_noise=int(bool(shot_noise)),
            read_noise=float(read_noise),
        )
    if bit_depth is not None:
        da = quantize(da, int(bit_depth), full_well)
    return da


def quantize(image: xr.DataArray, bit_depth: int, full_well: float | None = None) -> xr.DataArray:
    """Integer export: scale, round and clip to ``bit_depth`` bits.

    Policy: the signal ``full_well`` (default: the image maximum, i.e. no
    saturation) maps to 2**bit_depth − 1; values are rounded to the nearest
    integer and clipped to [0, 2**bit_depth − 1]. Pixels clipped high are
    counted in ``attrs['saturated_pixels']``; the scale factor is recorded.
    """
    if not isinstance(bit_depth, (int, np.integer)) or not 1 <= bit_depth <= 32:
        raise RaytraceError(f"bit_depth = {bit_depth!r}: allowed range is 1..32")
    top = float(2 ** int(bit_depth) - 1)
    fw = float(image.max()) if full_well is None else float(full_well)
    if not (math.isfinite(fw) and fw > 0):
        if full_well is not None:
            raise RaytraceError(f"full_well = {full_well!r}: must be a finite number > 0")
        fw = 1.0  # an all-zero image
    scaled = np.rint(image.values * (top / fw))
    saturated = int((scaled > top).sum())
    dtype = np.uint8 if bit_depth <= 8 else np.uint16 if bit_depth <= 16 else np.uint32
    out = image.copy(data=np.clip(scaled, 0, top).astype(dtype))
    out.attrs.update(
        bit_depth=int(bit_depth), full_well=fw, counts_per_unit=top / fw, saturated_pixels=saturated, units="counts"
    )
    return out
