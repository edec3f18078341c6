"""Computational refocusing: 4-D light field → focal stack (z, y, x) (sec. 5.2, 6.2).

Each ray (pixel) of the light field is propagated by ``t`` from the lenslet
plane (eq. 4.2: ``x' = x + t·slope``) and its signal is splatted bilinearly
onto the synthetic pixel grid of that plane (Fig. 5.6).

Grids (object space, mm, ascending with the index)
--------------------------------------------------
All planes share one object-space x/y grid: ``n_lenslets`` voxels per axis,
centred on the optical axis, voxel ``d = lenslet pitch/|M|`` (one lenslet at
the focal-plane magnification M).

- ``resize=True`` (default, sec. 6.2/Fig. 6.16): a ray reaching image point
  ``X_i`` on plane p is placed at the object point ``X_i/M_p`` with the
  plane's own magnification ``M_p = −D_i/D_o``. This is the synthetic sensor
  of eqs 5.10–5.13 resampled to constant magnification, done in one
  splat rather than a render followed by an interpolating resize (no second
  interpolation, and the inversion by the main lens is undone, so +x in the
  object is +x in the stack). Signal falling outside the grid is dropped
  (the thesis fills the uncovered margin with zeros).
- ``resize=False``: the thesis' raw render - the synthetic sensor of plane p
  is the lenslet array scaled by SF = (t + si)/si (eqs 5.10–5.13) and its
  pixels are mapped to the *common* nominal grid, i.e. ``X_i/(M·SF)``. The
  index coords ``x``/``y`` are then only nominal; the true object
  coordinates of each plane are the 2-D coords ``x_object(z, x)`` and
  ``y_object(z, y)`` (= nominal·M·SF/M_p = nominal·D_o/s_o). PIV on the index
  coords reproduces the depth-dependent bias of Fig. 7.5.
"""

from __future__ import annotations

import math
import uuid
from typing import Any

import dask
import dask.array as da
import numba
import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = ["focal_stack", "StackOperator"]


@numba.njit(nogil=True, cache=True, fastmath=True)
def _splat(rad, lx, ly, sx, sy, t, scale, cx0, cy0, nx, ny, out):  # pragma: no cover - compiled
    """Bilinear splat (Fig. 5.6) of every ray propagated by t; index = position·scale + (cx0, cy0)."""
    n_l, n_r, n_c = rad.shape
    for l in range(n_l):
        for i in range(n_r):
            fy = (ly[l] + t * sy[l, i]) * scale + cy0
            j0 = math.floor(fy)
            if j0 < -1 or j0 >= ny:
                continue
            wy = fy - j0
            for k in range(n_c):
                v = rad[l, i, k]
                if v == 0.0:
                    continue
                fx = (lx[l] + t * sx[l, k]) * scale + cx0
                i0 = math.floor(fx)
                if i0 < -1 or i0 >= nx:
                    continue
                wx = fx - i0
                if j0 >= 0:
                    if i0 >= 0:
                        out[j0, i0] += v * (1.0 - wx) * (1.0 - wy)
                    if i0 + 1 < nx:
                        out[j0, i0 + 1] += v * wx * (1.0 - wy)
                if j0 + 1 < ny:
                    if i0 >= 0:
                        out[j0 + 1, i0] += v * (1.0 - wx) * wy
                    if i0 + 1 < nx:
                        out[j0 + 1, i0 + 1] += v * wx * wy
    return out


class _Rays:
    """The light field flattened for the splat (kept out of dask's tokenizer)."""

    __slots__ = ("lx", "ly", "rad", "sx", "sy")

    def __init__(self, lightfield: xr.DataArray) -> None:
        lf = lightfield.transpose("lrow", "lcol", "prow", "pcol")
        nl = lf.sizes["lrow"] * lf.sizes["lcol"]
        n = lf.sizes["prow"]
        self.rad = np.ascontiguousarray(np.asarray(lf.values).reshape(nl, n, lf.sizes["pcol"]))
        if self.rad.dtype not in (np.float32, np.float64):
            self.rad = self.rad.astype(np.float32)
        self.lx = np.asarray(lf["x"].values, np.float64).ravel()
        self.ly = np.asarray(lf["y"].values, np.float64).ravel()
        # Ray slopes: tan(local) + tan(bulk) (eqs 5.4-5.9), exact for thin lenslets.
        self.sx = (
            np.tan(lf["theta"].transpose("lrow", "lcol", "pcol").values) + np.tan(lf["theta_bulk"].values)[:, :, None]
        ).reshape(nl, -1)
        self.sy = (
            np.tan(lf["phi"].transpose("lrow", "lcol", "prow").values) + np.tan(lf["phi_bulk"].values)[:, :, None]
        ).reshape(nl, -1)


def _plane(rays: _Rays, t: float, scale: float, cx0: float, cy0: float, nx: int, ny: int, dtype) -> np.ndarray:
    out = np.zeros((ny, nx), dtype=np.float64)
    _splat(rays.rad, rays.lx, rays.ly, rays.sx, rays.sy, float(t), float(scale), cx0, cy0, nx, ny, out)
    return out.astype(dtype, copy=False)[None]


class _StackGeometry:
    """Planes (ascending z), their splat scales and the x, y grid of a focal stack."""

    def __init__(self, lightfield, camera, planes, resize, x, y) -> None:
        if planes is None:
            planes = camera.focal_planes()
        for k in ("t", "z", "magnification"):
            if k not in planes:
                raise ValueError(f"planes dataset lacks {k!r} (use PlenopticCamera.focal_planes)")
        order = np.argsort(np.asarray(planes["z"].values), kind="stable")
        self.planes = planes.isel(plane=order)
        d = camera.lenslet_pitch / abs(camera.magnification)  # voxel at the focal plane
        if x is None and y is None:
            ny, nx = lightfield.sizes["lrow"], lightfield.sizes["lcol"]
            xg = (np.arange(nx) - 0.5 * (nx - 1)) * d
            yg = (np.arange(ny) - 0.5 * (ny - 1)) * d
        else:
            xg, yg = (np.asarray(v, dtype=float) for v in (x, y))
            steps = [np.diff(v) for v in (xg, yg) if v.size > 1]
            d = float(steps[0][0]) if steps else d
            if any(s.size and not np.allclose(s, d, rtol=1e-9, atol=0) for s in steps):
                raise ValueError("focal_stack: x and y must be uniform, ascending and share one step")
            ny, nx = yg.size, xg.size
        self.nx, self.ny, self.xg, self.yg, self.d = nx, ny, xg, yg, d
        self.cx0, self.cy0 = -float(xg[0]) / d, -float(yg[0]) / d  # index of the optical axis
        si = camera.si
        self.t = np.asarray(self.planes["t"].values, float)
        self.mp = np.asarray(self.planes["magnification"].values, float)
        self.sf = (self.t + si) / si  # eqs 5.10-5.13
        self.scale = 1.0 / (self.mp * d) if resize else 1.0 / (camera.magnification * self.sf * d)


class StackOperator:
    """The refocusing as an eager linear operator: radiance (lrow, lcol, prow, pcol) → stack (z, y, x).

    The same splat as :func:`focal_stack` for a fixed light-field geometry and
    planes, applied to any radiance values (e.g. a model light field); used to
    compute point-spread functions of the focal stack.
    """

    def __init__(
        self,
        lightfield: xr.DataArray,
        camera: PlenopticCamera,
        planes: xr.Dataset | None = None,
        *,
        resize: bool = True,
        x: np.ndarray | None = None,
        y: np.ndarray | None = None,
    ) -> None:
        self.geometry = _StackGeometry(lightfield, camera, planes, resize, x, y)
        self.rays = _Rays(lightfield)
        self.shape_lf = tuple(lightfield.transpose("lrow", "lcol", "prow", "pcol").shape)

    def __call__(self, radiance: np.ndarray) -> np.ndarray:
        g, rays = self.geometry, self.rays
        rad = np.ascontiguousarray(np.asarray(radiance, dtype=np.float64).reshape(rays.rad.shape))
        out = np.zeros((g.t.size, g.ny, g.nx))
        for i in range(g.t.size):
            _splat(
                rad,
                rays.lx,
                rays.ly,
                rays.sx,
                rays.sy,
                float(g.t[i]),
                float(g.scale[i]),
                g.cx0,
                g.cy0,
                g.nx,
                g.ny,
                out[i],
            )
        return out


def focal_stack(
    lightfield: xr.DataArray,
    camera: PlenopticCamera,
    planes: xr.Dataset | None = None,
    *,
    resize: bool = True,
    x: np.ndarray | None = None,
    y: np.ndarray | None = None,
    dtype: Any = np.float32,
) -> xr.DataArray:
    """Refocus a light field onto a stack of planes (eqs 5.10–5.15, Fig. 5.6, sec. 6.2).

    Parameters
    ----------
    lightfield : xarray.DataArray
        Output of :func:`lfstudy.lightfield.register`.
    camera : PlenopticCamera
        Supplies si, the focal-plane magnification and the lenslet pitch.
    planes : xarray.Dataset, optional
        Planes over ``plane`` with ``t``, ``z``, ``magnification`` (and
        ``image_distance``) as from :meth:`PlenopticCamera.focal_planes`;
        default ``camera.focal_planes()`` (Table 5.1 marching).
    resize : bool
        Resize every plane to constant magnification (default; sec. 6.2). See
        the module docstring for the ``False`` layout.
    x, y : ndarray, optional
        Uniform, ascending object-space voxel centres [mm] of the planes (a
        reconstruction grid, :class:`lfstudy.reconstruct.ReconstructionGrid`);
        default one voxel of pl/|M| per lenslet, centred on the optical axis.
    dtype : numpy dtype
        Output dtype.

    Returns
    -------
    xarray.DataArray ``intensity``, dims ``("z", "y", "x")``, lazy (dask)
        One chunk and one task per plane. ``z``, ``y``, ``x`` are object-space
        coordinates [mm], all ascending (planes reordered by ascending z);
        non-index coords ``t``, ``plane``, ``magnification``,
        ``image_distance`` on z (and ``x_object``/``y_object`` if not
        resized). Attrs: units, long_name, ``y_direction``, ``resize``,
        ``voxel_size``, camera parameters.
    """
    g = _StackGeometry(lightfield, camera, planes, resize, x, y)
    planes, t, mp, sf, scale = g.planes, g.t, g.mp, g.sf, g.scale
    nx, ny, cx0, cy0, xg, yg, d, m0 = g.nx, g.ny, g.cx0, g.cy0, g.xg, g.yg, g.d, camera.magnification
    rays = _Rays(lightfield)
    tag = uuid.uuid4().hex
    rays_d = dask.delayed(rays, name=f"lightfield-rays-{tag}")
    plane_fn = dask.delayed(_plane, name=f"refocus-fn-{tag}", pure=True)
    blocks = [
        da.from_delayed(
            plane_fn(rays_d, t[i], scale[i], cx0, cy0, nx, ny, dtype, dask_key_name=f"refocus-{tag}-{i}"),
            shape=(1, ny, nx),
            dtype=dtype,
        )
        for i in range(t.size)
    ]
    data = da.concatenate(blocks, axis=0)

    zc = lambda k: planes[k].values  # noqa: E731
    coords: dict[str, Any] = {
        "z": ("z", zc("z"), {"units": "mm", "long_name": "depth z (object frame, +z away from camera)"}),
        "y": ("y", yg, {"units": "mm", "long_name": "y (object frame, up)" + ("" if resize else ", nominal")}),
        "x": ("x", xg, {"units": "mm", "long_name": "x (object frame)" + ("" if resize else ", nominal")}),
        "t": ("z", t, {"units": "mm", "long_name": "refocus distance t"}),
        "plane": ("z", zc("plane"), {"units": "1", "long_name": "plane number (Table 5.1)"}),
        "magnification": ("z", mp, {"units": "1", "long_name": "magnification of plane M_p"}),
    }
    if "image_distance" in planes:
        coords["image_distance"] = ("z", zc("image_distance"), {"units": "mm", "long_name": "image distance D_i"})
    if not resize:
        f = m0 * sf / mp  # true/nominal object coordinate = D_o/s_o
        coords["x_object"] = (
            ("z", "x"),
            f[:, None] * xg[None, :],
            {"units": "mm", "long_name": "true object x of the un-resized plane"},
        )
        coords["y_object"] = (
            ("z", "y"),
            f[:, None] * yg[None, :],
            {"units": "mm", "long_name": "true object y of the un-resized plane"},
        )
    attrs = {
        "units": lightfield.attrs.get("units", "counts"),
        "long_name": "refocused intensity" + (" (constant magnification)" if resize else " (not resized)"),
        "y_direction": "y ascends with the row index (object frame, +y up; plot with origin='lower')",
        "resize": int(bool(resize)),
        "voxel_size": float(d),
        "voxel_size_units": "mm",
        "refocus": "eqs 5.10-5.15, bilinear splat (Fig. 5.6)"
        + (", resized to constant magnification (sec. 6.2)" if resize else ""),
    }
    attrs.update(camera.to_attrs())
    return xr.DataArray(data, dims=("z", "y", "x"), coords=coords, attrs=attrs, name="intensity")
