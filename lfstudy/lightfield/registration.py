"""Registration: raw plenoptic image → 4-D light field (thesis sec. 5.1, eqs 5.2–5.9).

Every lenslet gets the integer block of ``n × n`` pixels nearest its
calibrated lenslet-image centre, ``n = floor(spot pitch in px)`` (derived
from the calibration, not the thesis' hard-coded 14), so neighbouring blocks
never overlap and no pixel is interpolated (the thesis' reason for not
resampling as Ng et al. do).

Coordinates (sensor frame, mm and rad):

- ``x``, ``y`` per lenslet: the lenslet centre. The calibrated spot centre
  is the lenslet centre projected from the main-lens centre, so the lenslet
  centre is ``spot·si/(si + fl)`` (eqs 5.2–5.3 applied to the spot, then
  un-projected).
- ``theta_bulk``, ``phi_bulk`` per lenslet: ``atan(x/si)``, ``atan(y/si)``
  (eqs 5.4–5.5), the chief-ray angle from the main-lens centre.
- ``theta`` per (lenslet, pixel column) and ``phi`` per (lenslet, pixel
  row): ``atan(xl/fl)``, ``atan(yl/fl)`` with ``xl``, ``yl`` the pixel-centre
  offsets from the spot centre (eqs 5.6–5.9). They depend on the lenslet
  because the calibrated centres are sub-pixel.

The ray slope used for refocusing is ``tan(theta) + tan(theta_bulk)``,
which equals (pixel − lenslet centre)/fl exactly for a thin lenslet focused
at infinity; the thesis' ``theta + theta_bulk`` is its small-angle form.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = ["RegistrationError", "register", "pixels_per_lenslet"]


class RegistrationError(ValueError):
    """Raw image and calibration do not fit together."""


def pixels_per_lenslet(centers: xr.Dataset, camera: PlenopticCamera | None = None) -> int:
    """Side of the pixel block assigned to each lenslet: floor of the spot pitch in px."""
    if "pitch_x_px" in centers.attrs:
        pitch = min(float(centers.attrs["pitch_x_px"]), float(centers.attrs["pitch_y_px"]))
    elif camera is not None:
        pitch = camera.pixels_per_lenslet * (camera.si + camera.lenslet_focal_length) / camera.si
    else:
        raise RegistrationError("centres carry no pitch_px attrs and no camera was given")
    return math.floor(pitch + 1e-6)


@numba.njit(nogil=True, cache=True)
def _gather(img, row0, col0, n, out):  # pragma: no cover - compiled
    ny, nx = img.shape
    for l in range(row0.size):
        for i in range(n):
            r = row0[l] + i
            if r < 0 or r >= ny:
                continue
            for j in range(n):
                c = col0[l] + j
                if 0 <= c < nx:
                    out[l, i, j] = img[r, c]
    return out


def register(
    raw: xr.DataArray | np.ndarray,
    centers: xr.Dataset,
    camera: PlenopticCamera,
    *,
    dtype: Any = np.float32,
) -> xr.DataArray:
    """Register a raw plenoptic image into a 4-D light field (eqs 5.2–5.9).

    Parameters
    ----------
    raw : DataArray or ndarray, shape (rows, cols)
        Raw sensor image, row 0 at the top.
    centers : xarray.Dataset
        Output of :func:`lfstudy.lightfield.calibrate.find_lenslet_centers` (``cx``,
        ``cy`` in px over ``lenslet_row``/``lenslet_col``; ``valid``).
    camera : PlenopticCamera
        Supplies pixel pitch, si and fl; its sensor must match ``raw``.
    dtype : numpy dtype
        Radiance dtype (float32 halves the memory of a full sensor).

    Returns
    -------
    xarray.DataArray ``radiance``
        Dims ``("lrow", "lcol", "prow", "pcol")`` (lenslet row 0 at the top;
        pixel row 0 at the top of the block). Coords: ``x``, ``y``,
        ``spot_x``, ``spot_y``, ``theta_bulk``, ``phi_bulk``, ``row0``,
        ``col0``, ``valid`` on (lrow, lcol); ``theta`` on (lrow, lcol, pcol);
        ``phi`` on (lrow, lcol, prow). Pixels of a block outside the sensor
        are 0; ``valid`` is the calibration flag and the block being on the sensor.
    """
    img = raw.values if isinstance(raw, xr.DataArray) else np.asarray(raw)
    if img.ndim != 2:
        raise RegistrationError(f"raw image must be 2-D (rows, cols); got shape {img.shape}")
    ny, nx = img.shape
    if (ny, nx) != (camera.n_pixels_y, camera.n_pixels_x):
        raise RegistrationError(
            f"raw image is {nx} x {ny} px (cols x rows) but the camera sensor is "
            f"{camera.n_pixels_x} x {camera.n_pixels_y} px"
        )
    if not np.all(np.isfinite(img)):
        raise RegistrationError(f"raw image has {int((~np.isfinite(img)).sum())} non-finite (NaN/inf) pixels")
    if np.any(img < 0):
        raise RegistrationError(
            f"raw image has {int((img < 0).sum())} negative pixels (min {float(img.min()):.4g}): a recorded image "
            "holds counts >= 0; subtract a dark level with clipping, or check the file"
        )
    if not np.any(img > 0):
        raise RegistrationError("raw image is all zero: nothing was recorded (exposure, or the wrong file?)")
    for k in ("cx", "cy"):
        if k not in centers:
            raise RegistrationError(
                f"centres dataset lacks {k!r} (use lfstudy.lightfield.calibrate.find_lenslet_centers)"
            )
    if "image_rows" in centers.attrs and (int(centers.attrs["image_rows"]), int(centers.attrs["image_cols"])) != (
        ny,
        nx,
    ):
        raise RegistrationError(
            f"centres were calibrated on a {centers.attrs['image_cols']} x {centers.attrs['image_rows']} px "
            f"image but the raw image is {nx} x {ny} px"
        )
    n = pixels_per_lenslet(centers, camera)
    cx = np.asarray(centers["cx"].values, dtype=np.float64)
    cy = np.asarray(centers["cy"].values, dtype=np.float64)
    lr, lc = cx.shape
    # Integer n x n block nearest the centre: pixels start .. start+n-1 centred on c.
    col0 = np.rint(cx - (n - 1) / 2.0).astype(np.int64)
    row0 = np.rint(cy - (n - 1) / 2.0).astype(np.int64)
    rad = np.zeros((lr * lc, n, n), dtype=dtype)
    _gather(np.ascontiguousarray(img), row0.ravel(), col0.ravel(), n, rad)
    on = (row0 >= 0) & (row0 + n <= ny) & (col0 >= 0) & (col0 + n <= nx)
    valid = on & (np.asarray(centers["valid"].values, bool) if "valid" in centers else True)

    pp, si, fl = camera.pixel_pitch, camera.si, camera.lenslet_focal_length
    sx = (cx + 0.5) * pp - nx * pp / 2.0  # eq. 5.2 (spot centre)
    sy = ny * pp / 2.0 - (cy + 0.5) * pp  # eq. 5.3
    x, y = sx * si / (si + fl), sy * si / (si + fl)  # lenslet centre (un-projected)
    k = np.arange(n)
    px_x = (col0[:, :, None] + k + 0.5) * pp - nx * pp / 2.0  # pixel-centre x
    px_y = ny * pp / 2.0 - (row0[:, :, None] + k + 0.5) * pp
    theta = np.arctan((px_x - sx[:, :, None]) / fl)  # eqs 5.6, 5.8
    phi = np.arctan((px_y - sy[:, :, None]) / fl)  # eqs 5.7, 5.9

    L2, L3 = ("lrow", "lcol"), ("lrow", "lcol", "pcol")
    mm = lambda ln: {"units": "mm", "long_name": ln}  # noqa: E731
    rad_ = lambda ln: {"units": "rad", "long_name": ln}  # noqa: E731
    coords = {
        "lrow": ("lrow", np.arange(lr), {"units": "1", "long_name": "lenslet row (0 at top)"}),
        "lcol": ("lcol", np.arange(lc), {"units": "1", "long_name": "lenslet column"}),
        "prow": ("prow", k, {"units": "1", "long_name": "pixel row within lenslet (0 at top)"}),
        "pcol": ("pcol", k, {"units": "1", "long_name": "pixel column within lenslet"}),
        "x": (L2, x, mm("lenslet centre x (sensor frame)")),
        "y": (L2, y, mm("lenslet centre y (sensor frame, up)")),
        "spot_x": (L2, sx, mm("lenslet-image centre x, eq. 5.2")),
        "spot_y": (L2, sy, mm("lenslet-image centre y, eq. 5.3")),
        "theta_bulk": (L2, np.arctan2(x, si), rad_("bulk angle l_theta, eq. 5.4")),
        "phi_bulk": (L2, np.arctan2(y, si), rad_("bulk angle l_phi, eq. 5.5")),
        "theta": (L3, theta, rad_("local ray angle p_theta, eq. 5.8")),
        "phi": (("lrow", "lcol", "prow"), phi, rad_("local ray angle p_phi (y up), eq. 5.9")),
        "row0": (L2, row0, {"units": "px", "long_name": "first sensor row of the block"}),
        "col0": (L2, col0, {"units": "px", "long_name": "first sensor column of the block"}),
        "valid": (L2, valid, {"units": "1", "long_name": "calibrated and block on the sensor"}),
    }
    attrs = {
        "units": (raw.attrs.get("units", "counts") if isinstance(raw, xr.DataArray) else "counts"),
        "long_name": "radiance (pixel signal) of the 4-D light field",
        "pixels_per_lenslet": int(n),
        "pixel_pitch": float(pp),
        "image_distance": float(si),
        "lenslet_focal_length": float(fl),
        "n_pixels_x": int(nx),
        "n_pixels_y": int(ny),
        "y_direction": "lrow and prow grow downwards; y and phi point up (sensor frame)",
        "ray_slope": "tan(theta) + tan(theta_bulk) = (pixel - lenslet centre)/fl",
    }
    attrs.update(camera.to_attrs())
    return xr.DataArray(
        rad.reshape(lr, lc, n, n), dims=("lrow", "lcol", "prow", "pcol"), coords=coords, attrs=attrs, name="radiance"
    )
