"""Image deformation kernels for ``lfstudy.piv`` (``mode="deform"``).

``scipy.ndimage.map_coordinates`` is generic and single-threaded; it dominated the
run time of a deformation pass. Here the cubic (or quintic) B-spline is evaluated by a numba
kernel that also builds the sampling coordinates ``x -/+ d(x)/2`` on the fly, and
the dense predictor ``d(x)`` is obtained separably (one 1-D linear interpolation
per axis) from the vector grid. Each output voxel is computed independently, so
the result does not depend on the number of threads.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
from scipy import ndimage

__all__ = ["dense_predictor", "spline_coefficients", "deform"]

_PAD = 16  # zeros around the slab: the prefilter decays as 0.268**k (cubic), 0.43**k (quintic)


def _axis_weights(points: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # linear interpolation indices/weights; clamped = constant extrapolation beyond the
    # outermost window centres (linear extrapolation would amplify edge noise)
    if centres.size == 1:
        z = np.zeros(points.size, dtype=np.int64)
        return z, z, np.zeros(points.size)
    f = np.interp(points, centres, np.arange(centres.size, dtype=float))
    i0 = np.minimum(np.floor(f).astype(np.int64), centres.size - 2)
    return i0, i0 + 1, f - i0


def dense_predictor(field: np.ndarray, centres: Sequence[np.ndarray], points: Sequence[np.ndarray]) -> np.ndarray:
    """Multilinear interpolation of a gridded vector field onto a separable grid.

    Parameters
    ----------
    field : ndarray, shape (C, *grid)
        Vector components on the window-centre grid.
    centres : sequence of ndarray
        Window-centre index coordinates per axis (increasing).
    points : sequence of ndarray
        Target index coordinates per axis.

    Returns
    -------
    ndarray, shape (C, *(len(p) for p in points))
        Interpolated field; constant beyond the outermost centres.
    """
    out = np.asarray(field, dtype=np.float64)
    for ax, (c, p) in enumerate(zip(centres, points)):  # one 1-D interpolation per axis
        i0, i1, t = _axis_weights(np.asarray(p, dtype=float), np.asarray(c, dtype=float))
        shp = [1] * out.ndim
        shp[ax + 1] = -1
        t = t.reshape(shp)
        out = np.take(out, i0, axis=ax + 1) * (1.0 - t) + np.take(out, i1, axis=ax + 1) * t
    return out


@numba.njit(cache=True)
def _bweights(x: float, order: int) -> tuple:
    """First tap and the tap weights (6, zero-filled) of the cubic or quintic B-spline."""
    i = int(np.floor(x))
    t = x - i
    if order == 0:  # a single plane (2-D data): the plane itself, weight 1
        return 0, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if order == 3:
        t2 = t * t
        t3 = t2 * t
        return i - 1, (
            (1.0 - t) ** 3 / 6.0,
            (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
            (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
            t3 / 6.0,
            0.0,
            0.0,
        )
    # quintic: taps i-2 .. i+3 at distances u = |t - j|
    return i - 2, (_b5(t + 2.0), _b5(t + 1.0), _b5(t), _b5(1.0 - t), _b5(2.0 - t), _b5(3.0 - t))


@numba.njit(cache=True)
def _b5(u: float) -> float:
    u = abs(u)
    if u < 1.0:
        u2 = u * u
        return (66.0 - 60.0 * u2 + 30.0 * u2 * u2 - 10.0 * u2 * u2 * u) / 120.0
    if u < 2.0:
        u2 = u * u
        return (51.0 + 75.0 * u - 210.0 * u2 + 150.0 * u2 * u - 45.0 * u2 * u2 + 5.0 * u2 * u2 * u) / 120.0
    if u < 3.0:
        return (3.0 - u) ** 5 / 120.0
    return 0.0


@numba.njit(cache=True, inline="always")
def _lerp3(
    f: np.ndarray, c: int, z0: int, z1: int, az: float, y0: int, y1: int, ay: float, x0: int, x1: int, ax: float
) -> float:
    f00 = f[c, z0, y0, x0] * (1 - ax) + f[c, z0, y0, x1] * ax
    f01 = f[c, z0, y1, x0] * (1 - ax) + f[c, z0, y1, x1] * ax
    f10 = f[c, z1, y0, x0] * (1 - ax) + f[c, z1, y0, x1] * ax
    f11 = f[c, z1, y1, x0] * (1 - ax) + f[c, z1, y1, x1] * ax
    return (f00 * (1 - ay) + f01 * ay) * (1 - az) + (f10 * (1 - ay) + f11 * ay) * az


@numba.njit(parallel=True, cache=True)
def _deform3(
    coef: np.ndarray,
    origin: np.ndarray,
    field: np.ndarray,
    iz: np.ndarray,
    tz: np.ndarray,
    iy: np.ndarray,
    ty: np.ndarray,
    ix: np.ndarray,
    tx: np.ndarray,
    sign: float,
    order: int,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    # out[k,j,i] = spline(coef) at (k,j,i) + origin + sign * d(k,j,i) / 2, where d is the
    # trilinear interpolation of `field` with per-axis lower index i* and weight t*
    nz, ny, nx = coef.shape
    oz, oy, ox = out.shape
    flat_z = nz == 1  # 2-D data carried as a single plane
    ntap = order + 1
    for k in numba.prange(oz):
        kz0 = iz[k]
        kz1 = min(kz0 + 1, field.shape[1] - 1)
        az = tz[k]
        for j in range(oy):
            jy0 = iy[j]
            jy1 = min(jy0 + 1, field.shape[2] - 1)
            ay = ty[j]
            for i in range(ox):
                ix0 = ix[i]
                ix1 = min(ix0 + 1, field.shape[3] - 1)
                ax = tx[i]
                z = k + origin[0] + 0.5 * sign * _lerp3(field, 0, kz0, kz1, az, jy0, jy1, ay, ix0, ix1, ax)
                y = j + origin[1] + 0.5 * sign * _lerp3(field, 1, kz0, kz1, az, jy0, jy1, ay, ix0, ix1, ax)
                x = i + origin[2] + 0.5 * sign * _lerp3(field, 2, kz0, kz1, az, jy0, jy1, ay, ix0, ix1, ax)
                z0, wz = _bweights(z, order if not flat_z else 0)
                y0, wy = _bweights(y, order)
                x0, wx = _bweights(x, order)
                acc = 0.0
                for a in range(ntap):
                    zz = z0 + a
                    wza = wz[a]
                    if wza == 0.0 or zz < 0 or zz >= nz:
                        continue
                    for b in range(ntap):
                        yy = y0 + b
                        if yy < 0 or yy >= ny:
                            continue
                        acc1 = 0.0
                        for c in range(ntap):
                            xx = x0 + c
                            if 0 <= xx < nx:
                                acc1 += wx[c] * coef[zz, yy, xx]
                        acc += wza * wy[b] * acc1
                out[k, j, i] = acc


def spline_coefficients(img: np.ndarray, order: int = 3) -> np.ndarray:
    """Cubic or quintic B-spline coefficients of a 2-D or 3-D frame, zero-extended.

    A zero border of ``_PAD`` voxels is added before the prefilter, so samples
    beyond the data read as zero (the window padding of App. D). 2-D frames are
    returned as a single plane ``(1, ny + 2 pad, nx + 2 pad)``.
    """
    img = np.asarray(img, dtype=np.float64)
    if img.ndim == 2:
        return ndimage.spline_filter(np.pad(img, _PAD), order=order, mode="mirror")[None]
    return ndimage.spline_filter(np.pad(img, _PAD), order=order, mode="mirror")


def deform(
    coef: np.ndarray,
    nd: int,
    sign: float,
    box_lo: Sequence[int],
    box_hi: Sequence[int],
    slab_lo: Sequence[int],
    field: np.ndarray,
    centres: Sequence[np.ndarray],
    order: int = 3,
) -> np.ndarray:
    """Frame sampled at ``x + sign * d(x) / 2`` on a box (cubic or quintic B-spline).

    The dense predictor ``d(x)`` is the multilinear interpolation of the vector
    grid (constant beyond the outermost centres), evaluated inside the kernel.

    Parameters
    ----------
    coef : ndarray
        :func:`spline_coefficients` of a slab starting at global index ``slab_lo``.
    nd : int
        2 or 3, dimensionality of the data.
    sign : float
        -1 for the first frame, +1 for the second (symmetric offset).
    box_lo, box_hi : sequence of int
        Global index range of the output box.
    field : ndarray, shape (nd, *grid)
        Predictor (voxels, array-axis order) on the window-centre grid.
    centres : sequence of ndarray
        Window-centre index coordinates per axis.
    order : {3, 5}
        B-spline order; must match the one of ``coef``.

    Returns
    -------
    ndarray
        The deformed frame on the box (float64).
    """
    field = np.asarray(field, dtype=np.float64)
    lo, hi, slo = list(box_lo), list(box_hi), list(slab_lo)
    cen = [np.asarray(c, dtype=float) for c in centres]
    if nd == 2:  # carry 2-D as one z plane with zero z displacement
        field = np.concatenate([np.zeros((1, *field.shape[1:])), field])[:, None]
        lo, hi, slo, cen = [0, *lo], [1, *hi], [0, *slo], [np.zeros(1), *cen]
        pads = (0, _PAD, _PAD)
    else:
        pads = (_PAD,) * 3
    origin = np.array([l - s + p for l, s, p in zip(lo, slo, pads)], dtype=float)
    w = [_axis_weights(np.arange(l, h, dtype=float), c) for l, h, c in zip(lo, hi, cen)]
    out = np.empty([h - l for l, h in zip(lo, hi)], dtype=np.float64)
    _deform3(
        coef,
        origin,
        np.ascontiguousarray(field),
        w[0][0],
        w[0][2],
        w[1][0],
        w[1][2],
        w[2][0],
        w[2][2],
        float(sign),
        order,
        out,
    )
    return out[0] if nd == 2 else out
