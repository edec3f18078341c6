"""Seeded particle fields, their illumination and the calibration pinhole field (thesis sec. 4.3.2, 5.1).

A particle field is an :class:`xarray.Dataset` over dimension ``particle``
with variables ``x``, ``y``, ``z`` (object frame, mm: origin where the object
focal plane meets the optical axis, +z away from the camera, Fig. 4.16) and
``intensity`` (relative scattering coefficient); a field seeded with a
diameter distribution also carries ``diameter`` [µm].

Departures from the ideal field, each off by default (and then the field is
bit-identical to the ideal one):

- **diameters** (:func:`particle_diameters`): lognormal diameters scale each
  particle's intensity by ``(d / mean)²``, the scattering cross-section of
  particles larger than the wavelength (Mie regime: the cross-section tends to
  twice the geometric one, van de Hulst, *Light Scattering by Small Particles*,
  1957; Raffel et al., *Particle Image Velocimetry*, 2018, on tracer particles;
  Mie's oscillations about the d² trend are left out; the thesis takes one
  diameter, Table 4.3). Only the intensity follows d: the
  particle image size stays eq. 4.20's at the camera's ``particle_diameter``,
  where diffraction dominates (a 1 µm particle at |M| = 1 adds 0.5 % to a
  10 µm diffraction spot in quadrature);
- **depth margin** (``depth_margin`` of :func:`seed_particles`): particles
  seeded beyond the slab ``z_span`` on both sides at the slab's number density,
  which blur into every image but lie outside the measurement volume;
- **illumination** (:func:`illumination_profile`, :func:`illuminate`): a light
  volume of finite thickness in z dims each particle by the profile at its own
  depth, per exposure (a particle that moves through the sheet changes brightness).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = [
    "ParticleError",
    "particle_count",
    "seed_particles",
    "pinhole_field",
    "pinhole_spans",
    "make_field",
    "particle_diameters",
    "PROFILES",
    "illumination_profile",
    "illuminate",
]

#: Illumination profiles in z (:func:`illumination_profile`); ``none`` lights every particle alike.
PROFILES: tuple[str, ...] = ("none", "gaussian", "tophat")

#: Diameter distributions (:func:`particle_diameters`).
DISTRIBUTIONS: tuple[str, ...] = ("fixed", "lognormal")


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


def particle_diameters(
    n: int, *, distribution: str = "fixed", mean_um: float = 1.0, sd_um: float = 0.0, seed: int | Any = 0
) -> np.ndarray:
    """Particle diameters [µm]: one ``mean_um`` (``fixed``) or lognormal of arithmetic mean and sd.

    The lognormal's parameters follow from the arithmetic mean m and standard deviation s:
    σ² = ln(1 + s²/m²), μ = ln m − σ²/2, so that E[d] = m and sd[d] = s; then
    E[d²] = m² + s² (the mean intensity factor ``(d/m)²`` is ``1 + (s/m)²``).

    Parameters
    ----------
    n : int
        Number of diameters (>= 0).
    distribution : {"fixed", "lognormal"}
    mean_um, sd_um : float
        Arithmetic mean (> 0) and standard deviation (>= 0) [µm]; ``sd_um`` is unused by ``fixed``.
    seed : int or numpy.random.SeedSequence
        Seed of the generator (lognormal only).
    """
    if distribution not in DISTRIBUTIONS:
        raise ParticleError(
            f"particles.diameter.distribution = {distribution!r}: allowed values are "
            + ", ".join(map(repr, DISTRIBUTIONS))
        )
    if not (isinstance(mean_um, (int, float)) and math.isfinite(mean_um) and mean_um > 0):
        raise ParticleError(f"particles.diameter.mean_um = {mean_um!r}: must be a finite number > 0 µm")
    if not (isinstance(sd_um, (int, float)) and math.isfinite(sd_um) and sd_um >= 0):
        raise ParticleError(f"particles.diameter.sd_um = {sd_um!r}: must be a finite number >= 0 µm")
    if distribution == "fixed" or sd_um == 0:
        return np.full(int(n), float(mean_um))
    var = math.log1p((sd_um / mean_um) ** 2)
    return np.random.default_rng(seed).lognormal(math.log(mean_um) - var / 2, math.sqrt(var), int(n))


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
    depth_margin: float = 0.0,
    diameter: str = "fixed",
    diameter_mean_um: float | None = None,
    diameter_sd_um: float = 0.0,
    z_center: float = 0.0,
) -> xr.Dataset:
    """Uniformly seeded particle field (sec. 4.3.2), optionally with a depth margin and diameters.

    Parameters
    ----------
    camera : PlenopticCamera
        Supplies the default x/y spans (its field of view) and the pixel
        count for ``ppp``.
    ppp, count : float or int
        Seeding as particles per sensor pixel, or an explicit count (exactly one);
        of the slab ``z_span`` (the depth margin adds to it).
    x_span, y_span : float, optional
        Extents centred on the optical axis [mm]; default the field of view.
    z_span : float
        Depth extent [mm] centred on ``z_center`` (thesis: 0–7 mm, on the focal plane).
    intensity : (float, float)
        Bounds imin, imax of the uniform intensity coefficient.
    seed : int
        Seed of the NumPy ``Generator`` (PCG64); the same seed gives the same field.
    depth_margin : float
        Extra depth [mm] seeded on each side of the slab, ``z_span/2 < |z| <= z_span/2 +
        depth_margin``, at the slab's number density: round(n · 2·depth_margin / z_span) more
        particles, after the slab's ``n`` (whose ids and values do not change). They blur
        into the images; the truth volumes hold only what lies on the reconstruction grid.
        0 (the default): none, and the field is the ideal one bit for bit.
    diameter : {"fixed", "lognormal"}
        Diameter distribution (:func:`particle_diameters`); with ``lognormal`` each
        intensity is multiplied by ``(d / diameter_mean_um)²`` (Mie regime, see the
        module docstring) and the field gains ``diameter`` [µm]. ``fixed``: no change.
    diameter_mean_um, diameter_sd_um : float
        Arithmetic mean (default: the camera's ``particle_diameter``) and standard
        deviation of the diameters [µm].
    z_center : float
        Depth of the slab's centre from the focal plane [mm] (+z away from the camera). 0, the
        default, centres the slab on the focal plane (the thesis). A slab clear of the focal
        plane avoids its depth ambiguity: in focus a particle's image is one lenslet's spot,
        whose size changes only to second order with depth. The margin follows the slab.

    Notes
    -----
    The slab's particles come from ``default_rng(seed)`` as they always did; the margin's
    and the diameters come from their own streams (``SeedSequence(seed, spawn_key=(k,))``),
    so switching either on leaves every other draw unchanged.
    """
    if (ppp is None) == (count is None):
        raise ParticleError("give exactly one of ppp (particles per pixel) or count")
    n = particle_count(camera, ppp) if ppp is not None else count
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ParticleError(f"count = {n!r}: must be an integer >= 1")
    xs = camera.fov_x if x_span is None else x_span
    ys = camera.fov_y if y_span is None else y_span
    for name, v in (("x_span", xs), ("y_span", ys), ("z_span", z_span), ("depth_margin", depth_margin)):
        if not (isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v) and v >= 0):
            raise ParticleError(f"{name} = {v!r}: must be a finite number >= 0 mm")
    if not (isinstance(z_center, (int, float, np.integer, np.floating)) and math.isfinite(z_center)):
        raise ParticleError(f"z_center = {z_center!r}: must be a finite number [mm]")
    reach = z_span / 2 + depth_margin
    if reach - min(z_center, 0.0) >= camera.so - camera.main_focal_length:
        raise ParticleError(
            f"z_span = {z_span}, depth_margin = {depth_margin}, z_center = {z_center}: particles would reach the "
            "main lens' focal length; allowed range is z_span/2 + depth_margin - z_center < "
            f"{camera.so - camera.main_focal_length:.4g} mm"
        )
    if depth_margin > 0 and z_span == 0:
        raise ParticleError(
            f"depth_margin = {depth_margin}: needs z_span > 0 (the margin is seeded at the slab's number density)"
        )
    lo, hi = (float(v) for v in intensity)
    if not (0 <= lo <= hi):
        raise ParticleError(f"intensity = {list(intensity)}: need 0 <= imin <= imax")
    mean_um = 1000.0 * camera.particle_diameter if diameter_mean_um is None else diameter_mean_um
    rng = np.random.default_rng(seed)
    u = rng.random((4, int(n)))
    x, y, z, inten = (u[0] - 0.5) * xs, (u[1] - 0.5) * ys, (u[2] - 0.5) * z_span, lo + (hi - lo) * u[3]
    extra: dict[str, object] = {}
    n_margin = round(int(n) * 2 * depth_margin / z_span) if depth_margin > 0 else 0
    if n_margin:
        v = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,))).random((4, n_margin))
        t = 2.0 * v[2] - 1.0  # side and depth into the margin
        zm = np.sign(t) * (z_span / 2 + np.abs(t) * depth_margin)
        x = np.concatenate([x, (v[0] - 0.5) * xs])
        y = np.concatenate([y, (v[1] - 0.5) * ys])
        z = np.concatenate([z, zm])
        inten = np.concatenate([inten, lo + (hi - lo) * v[3]])
        extra.update(depth_margin=float(depth_margin), n_margin=int(n_margin))
    if z_center != 0.0:  # (0: the centred slab's bytes, unchanged)
        z = z + float(z_center)
        extra.update(z_center=float(z_center))
    d = None
    if diameter != "fixed" or diameter_mean_um is not None or diameter_sd_um:
        # validated whatever the distribution; only a lognormal one changes the field
        d = particle_diameters(
            x.size,
            distribution=diameter,
            mean_um=mean_um,
            sd_um=diameter_sd_um,
            seed=np.random.SeedSequence(seed, spawn_key=(2,)),
        )
    if diameter == "lognormal":
        inten = inten * (d / mean_um) ** 2
        extra.update(
            diameter_distribution="lognormal", diameter_mean_um=float(mean_um), diameter_sd_um=float(diameter_sd_um)
        )
    field = make_field(
        x,
        y,
        z,
        inten,
        seed=int(seed),
        ppp=float(ppp) if ppp is not None else float(n) / (camera.n_pixels_x * camera.n_pixels_y),
        x_span=float(xs),
        y_span=float(ys),
        z_span=float(z_span),
        **extra,
    )
    if diameter == "lognormal":
        field["diameter"] = ("particle", d, {"units": "um", "long_name": "particle diameter"})
    return field


def illumination_profile(
    z: np.ndarray, *, profile: str = "none", center: float = 0.0, thickness: float = 1.0, edge_width: float = 0.0
) -> np.ndarray:
    """Relative light intensity of the light volume at depths ``z`` [mm] (at most 1, >= 0).

    ``thickness`` t is the full width at half maximum of either profile, centred on ``center`` c:

    - ``gaussian``: ``exp(−4 ln 2 · (z − c)² / t²)`` (a Gaussian laser sheet; its 1/e² full
      width is 1.699·t);
    - ``tophat``: a top hat of width t whose edges are blurred by a Gaussian of standard
      deviation ``edge_width`` e (soft edges: each rises from 16 % to 84 % over 2e),
      ``½ [erf((z − c + t/2)/(√2 e)) − erf((z − c − t/2)/(√2 e))]``; e = 0: 1 for
      |z − c| <= t/2, else 0;
    - ``none``: 1 everywhere.
    """
    from scipy.special import erf

    if profile not in PROFILES:
        raise ParticleError(f"illumination.profile = {profile!r}: allowed values are " + ", ".join(map(repr, PROFILES)))
    z = np.asarray(z, dtype=np.float64)
    if profile == "none":
        return np.ones_like(z)
    checks = (("center", center, ""), ("thickness", thickness, " > 0"), ("edge_width", edge_width, " >= 0"))
    for name, v, low in checks:
        ok = isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v)
        if not ok or (low == " > 0" and v <= 0) or (low == " >= 0" and v < 0):
            raise ParticleError(f"illumination.{name} = {v!r}: must be a finite number{low} mm")
    dz = z - center
    if profile == "gaussian":
        return np.exp(-4.0 * math.log(2.0) * (dz / thickness) ** 2)
    if edge_width == 0:
        return (np.abs(dz) <= thickness / 2).astype(np.float64)
    s = math.sqrt(2.0) * edge_width
    return 0.5 * (erf((dz + thickness / 2) / s) - erf((dz - thickness / 2) / s))


def illuminate(
    field: xr.Dataset, *, profile: str = "none", center: float = 0.0, thickness: float = 1.0, edge_width: float = 0.0
) -> xr.Dataset:
    """The field as the light volume lights it: each intensity times :func:`illumination_profile` at its z.

    Apply it to each exposure's own positions (a particle moving through the sheet changes
    brightness between frames). ``profile="none"`` returns ``field`` itself, unchanged; otherwise
    a copy whose attrs record the profile (``illumination_*``).
    """
    if profile == "none":
        illumination_profile(np.zeros(0), profile=profile)  # the name check
        return field
    f = illumination_profile(
        field["z"].values, profile=profile, center=center, thickness=thickness, edge_width=edge_width
    )
    out = field.copy()
    out["intensity"] = field["intensity"] * f
    out["intensity"].attrs.update(field["intensity"].attrs)
    out.attrs.update(
        illumination_profile=profile,
        illumination_center=float(center),
        illumination_thickness=float(thickness),
        illumination_edge_width=float(edge_width),
    )
    return out


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
