"""Dot-target images for the volumetric calibration (issue 29 §2; Hall et al. 2018, Appl. Opt. 57(4) 914).

A planar card of point sources on a square grid (``spacing`` mm, centred on the optical
axis, covering ``extent``) is traversed through known depths ``z_k`` and imaged at each
through the camera *including* its imperfections (:mod:`lfstudy.simulate.imperfections`):
the images an experimenter records with a dot card on a traverse. The processing
(:mod:`lfstudy.lightfield.volcal`) then fits the mapping from object (x, y, z) to each
sub-aperture image's coordinates from these images and the known dot positions only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import xarray as xr

from lfstudy.lightfield.volcal import dot_grid
from lfstudy.optics import PlenopticCamera
from lfstudy.simulate.imperfections import CameraImperfections
from lfstudy.simulate.particles import make_field
from lfstudy.simulate.raytrace import render

__all__ = ["DotTargetError", "dot_grid", "render_dot_target"]


class DotTargetError(ValueError):
    """A dot-target setting outside its allowed range (the message names the config field)."""


def render_dot_target(
    camera: PlenopticCamera,
    depths: Sequence[float],
    *,
    spacing: float,
    extent: tuple[float, float] | None = None,
    photons: float = 20000.0,
    read_noise: float = 2.0,
    seed: int = 0,
    diffraction: bool = True,
    imperfections: CameraImperfections | Mapping[str, Any] | None = None,
    max_image_bytes: float = 4e9,
) -> xr.DataArray:
    """Raw images of a dot card at known depths through the (imperfect) camera, with sensor noise.

    Each image is the exact expected image (:func:`lfstudy.simulate.raytrace.render`,
    ``method="exact"``) of every dot as a point source of ``photons`` photons at the
    reference solid angle, then Poisson shot noise and Gaussian read noise [e⁻ rms].

    Parameters
    ----------
    camera : PlenopticCamera
        The nominal camera.
    depths : sequence of float
        The card's depths z_k [mm] (object frame, +z away from the camera), at least 2, distinct.
    spacing : float
        Dot pitch [mm].
    extent : (float, float), optional
        Width and height [mm] the dots cover; default the field of view (``camera.fov_x``, ``fov_y``).
    photons : float
        Photons per dot, > 0.
    read_noise : float
        Read noise [e⁻ rms], >= 0.
    seed : int
        Noise seed; image k uses ``seed + k``, so one seed gives the same bytes.
    diffraction : bool
        Diffraction blur of the renderer.
    imperfections : CameraImperfections or mapping, optional
        What the imaging camera does differently from ``camera`` (``camera.imperfections``).
    max_image_bytes : float
        The renderer's allocation limit.

    Returns
    -------
    xarray.DataArray ``intensity``
        Dims ``("depth", "row", "col")``, coord ``depth`` [mm] (in the order given); attrs
        ``spacing``, ``extent_x``, ``extent_y``, ``n_dots``.
    """
    z = np.asarray(list(depths), dtype=float)
    if z.ndim != 1 or z.size < 2 or not np.all(np.isfinite(z)) or np.unique(z).size != z.size:
        raise DotTargetError(
            f"volumetric_calibration.depths = {list(depths)!r}: need at least 2 distinct finite depths (mm)"
        )
    if not (np.isfinite(photons) and photons > 0):
        raise DotTargetError(f"volumetric_calibration.photons = {photons!r}: must be a finite number > 0")
    if not (np.isfinite(read_noise) and read_noise >= 0):
        raise DotTargetError(f"volumetric_calibration.read_noise = {read_noise!r}: must be a finite number >= 0")
    ex, ey = (camera.fov_x, camera.fov_y) if extent is None else extent
    gx, gy = dot_grid(spacing, float(ex), float(ey))
    images = []
    for k, zk in enumerate(z):
        field = make_field(gx, gy, np.full(gx.size, zk), np.ones(gx.size))
        img = render(
            camera,
            field,
            max(1, round(photons)),
            int(seed) + k,
            diffraction=diffraction,
            shot_noise=True,
            read_noise=float(read_noise),
            max_image_bytes=max_image_bytes,
            method="exact",
            imperfections=imperfections,
        )
        images.append(np.maximum(img.values, 0.0).astype(np.float32))  # counts >= 0, as a sensor reads
    first = img
    out = xr.DataArray(
        np.stack(images),
        dims=("depth", "row", "col"),
        coords={
            "depth": ("depth", z, {"units": "mm", "long_name": "dot-card depth z"}),
            "x": ("col", first["x"].values, first["x"].attrs),
            "y": ("row", first["y"].values, first["y"].attrs),
        },
        name="intensity",
        attrs={
            "units": "e-",
            "long_name": "dot-target image",
            "spacing": float(spacing),
            "extent_x": float(ex),
            "extent_y": float(ey),
            "n_dots": int(gx.size),
            "photons": float(photons),
            "read_noise": float(read_noise),
            "seed": int(seed),
        },
    )
    out.attrs.update(camera.to_attrs())
    return out
