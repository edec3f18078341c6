"""Volumetric calibration of a plenoptic camera and the focal stack that uses it (issue 29 §2).

Hall, Fahringer, Guildenbecher and Thurow 2018, "Volumetric calibration of a plenoptic
camera", Applied Optics 57(4) 914 (here: Hall 2018). The thin-lens refocusing
(:mod:`lfstudy.lightfield.refocus`, eqs 5.10–5.15 of the thesis) assumes the nominal camera:
an ideal main lens and lenslets exactly ``fl`` in front of the sensor. A real camera has
distortion and a gap error that the model does not know. Hall 2018 calibrate instead from a
dot card imaged at several known depths: for every angular sample (u, v) of the light field
they fit a polynomial mapping the object point (x, y, z) to where it appears in that
sub-aperture image, (s, t). Refocusing then samples each sub-aperture image at the mapped
point instead of shifting by the thin-lens amount.

Here a sub-aperture image is the same pixel (``prow``, ``pcol``) of every lenslet block of the
registered light field (:func:`lfstudy.lightfield.register`); its coordinates are the
fractional lenslet column ``s`` and row ``t`` (units: lenslets). The polynomial is in every
monomial ``x^a y^b z^c`` with ``a + b + c <= order`` (default 3: 20 terms, Hall 2018's cubic),
in normalised coordinates ``x/x_scale``, ``y/y_scale``, ``(z − z_center)/z_scale``.

Steps
-----
1. :func:`fit_volumetric`: the dots of each depth are found in each sub-aperture image
   around the position the nominal thin-lens model predicts for them (so each centroid is
   matched to its known dot), centroided (the signal above the image's median plus a quarter of
   the window's peak over it, iterated), and each sub-aperture's polynomial is fitted by linear
   least squares (one pass rejecting outliers beyond 4 robust σ). One depth is held out first
   to report the prediction error there; the returned mapping uses all depths.
2. :func:`volumetric_stack`: the focal stack on an object grid: voxel (x, y, z) is
   ``Σ_uv I_uv(P_uv(x, y, z)) · |det ∂P_uv/∂(x, y)| · dx·dy``, a bilinear sample of each
   sub-aperture image times the lenslet area one voxel covers there, which is what the
   thin-lens splat accumulates (the signal of one plane is conserved in both).
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import dask
import dask.array as da
import numba
import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = [
    "VolumetricCalibration",
    "VolumetricCalibrationError",
    "dot_grid",
    "fit_volumetric",
    "predict",
    "predict_thin_lens",
    "volumetric_stack",
    "polynomial_exponents",
]


class VolumetricCalibrationError(ValueError):
    """The dot-target data or a volumetric-calibration setting do not allow the fit (names the field)."""


#: How far beyond its calibrated depths a calibration may be used, as a fraction of their range: the
#: polynomial's extrapolation there stays within its fit (the grid's end planes may sit a little outside).
DEPTH_MARGIN = 0.05

#: The attrs :func:`fit_volumetric` writes that using a calibration reads.
_ATTRS = ("x_scale", "y_scale", "z_center", "z_scale", "z_min", "z_max", "n_lrow", "n_lcol", "pixels_per_lenslet")


@dataclass(frozen=True, eq=False)
class VolumetricCalibration:
    """A fitted volumetric calibration (the Dataset of :func:`fit_volumetric`) and the checks of what it can map.

    The Dataset stays what is stored and passed around; this type owns the checks every user of it
    makes: that it is a whole calibration, that a light field is the one it was fitted on
    (:meth:`check_lightfield`) and that a grid's depths are within its calibrated range
    (:meth:`check_depths`, :data:`DEPTH_MARGIN`).

    Parameters
    ----------
    dataset : xarray.Dataset
        From :func:`fit_volumetric` (``coef``, ``exponents``, ``valid`` and its attrs).

    Raises
    ------
    VolumetricCalibrationError
        Not a Dataset, or a variable or attribute of the fit missing (naming it).
    """

    dataset: xr.Dataset

    def __post_init__(self) -> None:
        cal = self.dataset
        if not isinstance(cal, xr.Dataset):
            raise VolumetricCalibrationError(
                f"calibration must be the volumetric calibration Dataset of lfstudy.lightfield.volcal.fit_volumetric, "
                f"got {type(cal).__name__}"
            )
        for key in ("coef", "exponents", "valid"):
            if key not in cal:
                raise VolumetricCalibrationError(
                    f"the volumetric calibration lacks {key!r}: fit it with lfstudy.lightfield.volcal.fit_volumetric"
                )
        missing = [k for k in _ATTRS if k not in cal.attrs]
        if missing:
            raise VolumetricCalibrationError(
                f"the volumetric calibration lacks the attrs {missing}: fit it with "
                "lfstudy.lightfield.volcal.fit_volumetric"
            )

    @classmethod
    def of(cls, calibration: xr.Dataset | VolumetricCalibration) -> VolumetricCalibration:
        """``calibration`` as this type (checked once; an instance is returned as it is)."""
        return calibration if isinstance(calibration, cls) else cls(calibration)

    @property
    def z_range(self) -> tuple[float, float]:
        """The calibrated depths' (min, max) [mm]."""
        a = self.dataset.attrs
        return float(a["z_min"]), float(a["z_max"])

    @property
    def lightfield_shape(self) -> tuple[int, int, int]:
        """(lenslet rows, lenslet columns, pixels per lenslet) of the light fields it was fitted on."""
        a = self.dataset.attrs
        return int(a["n_lrow"]), int(a["n_lcol"]), int(a["pixels_per_lenslet"])

    def check_lightfield(self, lightfield: xr.DataArray) -> None:
        """Raise unless ``lightfield`` has the lenslets and pixels per lenslet the calibration was fitted on.

        Raises
        ------
        VolumetricCalibrationError
            Naming both shapes.
        """
        shape = (lightfield.sizes["lrow"], lightfield.sizes["lcol"], lightfield.sizes["prow"])
        want = self.lightfield_shape
        if shape != want:
            raise VolumetricCalibrationError(
                f"the light field ({shape[0]} x {shape[1]} lenslets, {shape[2]} px each) is not the one the volumetric "
                f"calibration was fitted on ({want[0]} x {want[1]}, {want[2]} px)"
            )

    def check_depths(self, z: Any, what: str = "grid") -> None:
        """Raise unless the depths ``z`` [mm] lie within the calibrated ones, :data:`DEPTH_MARGIN` of their
        range either side (beyond, the polynomial would extrapolate).

        Parameters
        ----------
        z : array_like
            The depths [mm] to be mapped (a grid's planes).
        what : str
            What spans them, for the message.

        Raises
        ------
        VolumetricCalibrationError
            Naming ``volumetric_calibration.depths`` and both ranges.
        """
        zg = np.asarray(z, dtype=float)
        lo, hi = self.z_range
        tol = DEPTH_MARGIN * (hi - lo)
        if zg.min() < lo - tol or zg.max() > hi + tol:
            raise VolumetricCalibrationError(
                f"volumetric_calibration.depths cover z = {lo:.4g}..{hi:.4g} mm but the {what} spans "
                f"{zg.min():.4g}..{zg.max():.4g} mm: the polynomial would extrapolate; calibrate over the grid's depth"
            )


def dot_grid(
    spacing: float, extent_x: float, extent_y: float, origin: tuple[float, float] = (0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """The dots' (x, y) [mm] of a square grid of pitch ``spacing`` through ``origin`` within the extent.

    Parameters
    ----------
    spacing : float
        Dot pitch [mm], > 0.
    extent_x, extent_y : float
        Full width and height [mm] the dots lie within (|x| <= extent_x/2, |y| <= extent_y/2).
    origin : (float, float)
        The (x, y) [mm] of one dot of the grid (default the optical axis): the dots are
        ``origin + (i, j)·spacing`` for integers i, j.

    Returns
    -------
    x, y : ndarray
        1-D, row-major over the grid (y ascending, then x ascending).
    """
    if not (np.isfinite(spacing) and spacing > 0):
        raise VolumetricCalibrationError(
            f"volumetric_calibration.spacing = {spacing!r}: must be a finite number > 0 (mm)"
        )
    for name, e in (("extent_x", extent_x), ("extent_y", extent_y)):
        if not (np.isfinite(e) and e >= 0):
            raise VolumetricCalibrationError(
                f"volumetric_calibration.{name} = {e!r}: must be a finite number >= 0 (mm)"
            )
    ox, oy = (float(v) for v in origin)
    if not (np.isfinite(ox) and np.isfinite(oy)):
        raise VolumetricCalibrationError(f"volumetric_calibration.origin = {origin!r}: must be finite (mm)")

    def ks(e: float, o: float) -> np.ndarray:
        lo = int(np.ceil((-0.5 * e - o) / spacing - 1e-9))
        hi = int(np.floor((0.5 * e - o) / spacing + 1e-9))
        return np.arange(lo, hi + 1)

    gx = ks(extent_x, ox) * spacing + ox
    gy = ks(extent_y, oy) * spacing + oy
    if gx.size == 0 or gy.size == 0:
        raise VolumetricCalibrationError(
            f"volumetric_calibration: no dot of the grid through origin {origin!r} with spacing {spacing!r} mm "
            f"lies within the extent {extent_x!r} x {extent_y!r} mm"
        )
    x, y = np.meshgrid(gx, gy)
    return x.ravel(), y.ravel()


def polynomial_exponents(order: int) -> np.ndarray:
    """Exponents (a, b, c) of the monomials ``x^a y^b z^c`` with ``a + b + c <= order``, shape (terms, 3)."""
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or not 1 <= order <= 5:
        raise VolumetricCalibrationError(f"volumetric_calibration.order = {order!r}: must be an integer in [1, 5]")
    out = [(a, b, d - a - b) for d in range(order + 1) for a in range(d, -1, -1) for b in range(d - a, -1, -1)]
    return np.array(out, dtype=np.int64)


def _design(xn: np.ndarray, yn: np.ndarray, zn: np.ndarray, exps: np.ndarray) -> np.ndarray:
    return np.stack([xn**a * yn**b * zn**c for a, b, c in exps], axis=-1)


@numba.njit(nogil=True, cache=True)
def _centroids(rad, bgs, s0, t0, half, n_iter, out_s, out_t, out_w):  # pragma: no cover - compiled
    """Iterated centroid of each (dot, prow, pcol) in its sub-aperture image around (s0, t0)."""
    lr, lc, n, _ = rad.shape
    m = s0.shape[0]
    for d in range(m):
        for i in range(n):
            for j in range(n):
                s, t, w = s0[d, i, j], t0[d, i, j], 0.0
                for _ in range(n_iter):
                    cs, ct = math.floor(s + 0.5), math.floor(t + 0.5)
                    if cs - half < 0 or cs + half >= lc or ct - half < 0 or ct + half >= lr:
                        w = -1.0
                        break
                    peak = -1e300
                    for r in range(ct - half, ct + half + 1):
                        for c in range(cs - half, cs + half + 1):
                            if rad[r, c, i, j] > peak:
                                peak = rad[r, c, i, j]
                    bg = bgs[i, j]
                    thr = bg + 0.25 * (peak - bg)
                    sw, ss, st = 0.0, 0.0, 0.0
                    for r in range(ct - half, ct + half + 1):
                        for c in range(cs - half, cs + half + 1):
                            v = rad[r, c, i, j] - thr
                            if v > 0.0:
                                sw += v
                                ss += v * c
                                st += v * r
                    if sw <= 0.0:
                        w = 0.0
                        break
                    s, t, w = ss / sw, st / sw, sw
                out_s[d, i, j], out_t[d, i, j], out_w[d, i, j] = s, t, w
    return out_s


def resample_angular(lightfield: xr.DataArray) -> np.ndarray:
    """The light field at the same angles in every lenslet: (lrow, lcol, prow, pcol), float64.

    Registration takes each lenslet's integer pixel block nearest its sub-pixel spot centre
    (eqs 5.2–5.9), so block pixel ``j`` lies ``j − (n−1)/2 + δ`` px from the centre with a
    sub-pixel ``δ`` that varies from lenslet to lenslet (the spot pitch is not a whole number of
    pixels). A sub-aperture image of raw blocks would then mix angles in a sawtooth across the
    array that no smooth polynomial follows. As Hall 2018 do, the blocks are resampled (linear
    interpolation inside the block, ends clamped) to offsets ``j − (n−1)/2`` exactly.
    """
    lf = lightfield.transpose("lrow", "lcol", "prow", "pcol")
    rad = np.asarray(lf.values, dtype=np.float64)
    n = rad.shape[2]
    fl_pp = float(lf.attrs["lenslet_focal_length"]) / float(lf.attrs["pixel_pitch"])
    k = np.arange(n) - 0.5 * (n - 1)
    dx = np.mean(np.tan(lf["theta"].transpose("lrow", "lcol", "pcol").values) * fl_pp - k, axis=-1)
    dy = np.mean(-np.tan(lf["phi"].transpose("lrow", "lcol", "prow").values) * fl_pp - k, axis=-1)
    out = np.empty_like(rad)
    _shift_blocks(rad, dx, dy, out)
    return out


@numba.njit(nogil=True, cache=True)
def _shift_blocks(rad, dx, dy, out):  # pragma: no cover - compiled
    lr, lc, n, _ = rad.shape
    for a in range(lr):
        for b in range(lc):
            for i in range(n):
                fy = min(max(i - dy[a, b], 0.0), n - 1.0)
                i0 = min(int(fy), n - 2)
                wy = fy - i0
                for j in range(n):
                    fx = min(max(j - dx[a, b], 0.0), n - 1.0)
                    j0 = min(int(fx), n - 2)
                    wx = fx - j0
                    out[a, b, i, j] = (
                        rad[a, b, i0, j0] * (1 - wx) * (1 - wy)
                        + rad[a, b, i0, j0 + 1] * wx * (1 - wy)
                        + rad[a, b, i0 + 1, j0] * (1 - wx) * wy
                        + rad[a, b, i0 + 1, j0 + 1] * wx * wy
                    )
    return out


def _lenslet_affine(lightfield: xr.DataArray) -> np.ndarray:
    """Least-squares affine map sensor (x, y) [mm] → (lcol, lrow) of the registered lenslet centres."""
    lf = lightfield
    lrow, lcol = np.meshgrid(lf["lrow"].values, lf["lcol"].values, indexing="ij")
    ok = np.asarray(lf["valid"].values, bool) if "valid" in lf.coords else np.ones(lrow.shape, bool)
    a = np.column_stack([lf["x"].values[ok], lf["y"].values[ok], np.ones(int(ok.sum()))])
    coef, *_ = np.linalg.lstsq(a, np.column_stack([lcol[ok], lrow[ok]]).astype(float), rcond=None)
    return coef  # (3, 2)


def _nominal_positions(lightfield, camera, x, y, z) -> tuple[np.ndarray, np.ndarray]:
    """Thin-lens prediction (eqs 5.10–5.15 inverted) of each dot in each sub-aperture image, (m, n, n) each.

    A ray of lenslet L with local slope a = tan(theta) has slope a + L/si (eqs 5.4–5.9) and
    meets the refocus plane t at L + t(a + L/si); the dot images at M_p·x there, so
    L = (M_p·x − t·a)/(1 + t/si).
    """
    lf = lightfield
    si = camera.si
    n, pp_fl = lf.sizes["pcol"], float(lf.attrs["pixel_pitch"]) / float(lf.attrs["lenslet_focal_length"])
    ax = (np.arange(n) - 0.5 * (n - 1)) * pp_fl  # (pcol,) slopes of the resampled sub-apertures
    ay = -ax  # (prow,): rows grow downwards, y up
    planes = camera.planes_at(z)
    tz = planes["t"].values[:, None, None]
    mz = planes["magnification"].values[:, None, None]
    lx = (mz * x[:, None, None] - tz * ax[None, None, :]) / (1.0 + tz / si)  # (m, 1, pcol)
    ly = (mz * y[:, None, None] - tz * ay[None, :, None]) / (1.0 + tz / si)  # (m, prow, 1)
    lx, ly = np.broadcast_arrays(lx, ly)
    c = _lenslet_affine(lf)
    s = lx * c[0, 0] + ly * c[1, 0] + c[2, 0]
    t = lx * c[0, 1] + ly * c[1, 1] + c[2, 1]
    return np.ascontiguousarray(s), np.ascontiguousarray(t)


def _lstsq(d: np.ndarray, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    coef, *_ = np.linalg.lstsq(d, np.column_stack([s, t]), rcond=None)
    return coef[:, 0], coef[:, 1]


def _fit_all(dmat, s, t, keep, min_samples):
    """Per sub-aperture polynomial fit with one outlier-rejection pass; coefficients (2, n, n, T), used mask."""
    n = s.shape[1]
    nterm = dmat.shape[1]
    coef = np.zeros((2, n, n, nterm))
    ok = np.zeros((n, n), bool)
    used = np.zeros_like(keep)
    for i in range(n):
        for j in range(n):
            k = keep[:, i, j]
            if k.sum() < min_samples:
                continue
            cs, ct = _lstsq(dmat[k], s[k, i, j], t[k, i, j])
            res = np.hypot(dmat @ cs - s[:, i, j], dmat @ ct - t[:, i, j])
            mad = 1.4826 * np.median(res[k])
            k = k & (res <= max(4.0 * mad, 0.05))
            if k.sum() < min_samples:
                continue
            coef[0, i, j], coef[1, i, j] = _lstsq(dmat[k], s[k, i, j], t[k, i, j])
            ok[i, j] = True
            used[:, i, j] = k
    return coef, ok, used


def _trim(dmat, S, T, coef, ok, used) -> np.ndarray:
    """Drop the edge sub-apertures the aperture vignettes: fewer than 60 % of the best one's dots,
    or a residual over twice the median one (their few, dim samples fit poorly)."""
    nsamp = used.sum(axis=0)
    rms = np.full(ok.shape, np.inf)
    for i, j in zip(*np.nonzero(ok)):
        k = used[:, i, j]
        rms[i, j] = np.sqrt(
            np.mean((dmat[k] @ coef[0, i, j] - S[k, i, j]) ** 2 + (dmat[k] @ coef[1, i, j] - T[k, i, j]) ** 2)
        )
    if not ok.any():
        return ok
    return ok & (nsamp >= 0.6 * nsamp[ok].max()) & (rms <= 2.0 * np.median(rms[ok]))


def fit_volumetric(
    lightfields: Sequence[xr.DataArray],
    depths: Sequence[float],
    camera: PlenopticCamera,
    *,
    spacing: float,
    extent: tuple[float, float] | None = None,
    order: int = 3,
    window: int | None = None,
    min_signal: float = 0.2,
    hold_out: int | None = -1,
    origin: tuple[float, float] = (0.0, 0.0),
) -> xr.Dataset:
    """Fit the volumetric calibration (Hall 2018): per sub-aperture, a polynomial (x, y, z) → (s, t).

    Parameters
    ----------
    lightfields : sequence of xarray.DataArray
        The registered light fields (:func:`lfstudy.lightfield.register`) of the dot-target
        images, one per depth, all with the same lenslet calibration.
    depths : sequence of float
        The card's depth [mm] in each image (at least ``order + 1``, distinct).
    camera : PlenopticCamera
        The nominal camera (only to predict where each dot is, to match it).
    spacing : float
        Dot pitch [mm] on the card.
    extent : (float, float), optional
        The width and height [mm] the dots cover, as rendered (default the field of view).
    order : int
        Polynomial order (1–5; default 3).
    window : int, optional
        Side of the centroid window [lenslets], odd; default the largest odd number below the
        dot pitch in lenslets (at least 3).
    min_signal : float
        A dot's centroid in one sub-aperture counts when its signal is at least this fraction
        of the dot's brightest sub-aperture at that depth (vignetted samples are dropped).
    hold_out : int or None
        Index into ``depths`` of the depth held out to report the prediction error there;
        -1 (default): the inner depth nearest the middle; None: no hold-out.
    origin : (float, float)
        The (x, y) [mm] of one dot on the card (:func:`dot_grid`; default the optical axis).

    Returns
    -------
    xarray.Dataset
        ``coef`` (axis [s, t], prow, pcol, term), ``exponents`` (term, power [x, y, z]),
        ``valid`` and ``rms`` [lenslets] and ``n_samples`` per (prow, pcol). Attrs: the
        normalisation (``x_scale``, ``y_scale``, ``z_center``, ``z_scale``), the calibrated
        depth range ``z_min``/``z_max``, ``fit_rms_lenslets`` (all samples),
        ``holdout_depth``, ``holdout_rms_lenslets`` (the held-out depth predicted by the
        fit without it) and the light field's shape.
    """
    exps = polynomial_exponents(order)
    z = np.asarray(list(depths), dtype=float)
    if len(lightfields) != z.size:
        raise VolumetricCalibrationError(f"{len(lightfields)} light fields for {z.size} depths")
    if z.size < order + 1 or np.unique(z).size != z.size or not np.all(np.isfinite(z)):
        raise VolumetricCalibrationError(
            f"volumetric_calibration.depths: need at least order + 1 = {order + 1} distinct finite depths "
            f"for a polynomial of order {order} in z (got {list(z)})"
        )
    if not 0.0 <= min_signal < 1.0:
        raise VolumetricCalibrationError(f"min_signal = {min_signal!r}: allowed range is [0, 1)")
    lf0 = lightfields[0]
    ex, ey = (camera.fov_x, camera.fov_y) if extent is None else extent
    gx, gy = dot_grid(spacing, float(ex), float(ey), origin)
    pitch_lenslets = spacing * abs(camera.magnification) / camera.lenslet_pitch
    if window is None:
        window = max(3, (math.floor(pitch_lenslets) - 1) // 2 * 2 + 1)
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise VolumetricCalibrationError(f"volumetric_calibration.window = {window!r}: must be an odd integer >= 3")
    if window > pitch_lenslets:
        raise VolumetricCalibrationError(
            f"volumetric_calibration.window = {window} lenslets exceeds the dot pitch ({pitch_lenslets:.3g} "
            "lenslets): neighbouring dots would share a window; use a larger spacing"
        )
    n = lf0.sizes["prow"]
    m = gx.size
    s_all, t_all, w_all = (np.empty((z.size, m, n, n)) for _ in range(3))
    for k, (lf, zk) in enumerate(zip(lightfields, z)):
        if lf.sizes != lf0.sizes:
            raise VolumetricCalibrationError("the dot-target light fields differ in shape")
        rad = resample_angular(lf)
        s0, t0 = _nominal_positions(lf, camera, gx, gy, np.full(m, zk))
        bgs = np.ascontiguousarray(np.median(rad, axis=(0, 1)))  # the card is mostly dark: its background
        _centroids(rad, bgs, s0, t0, window // 2, 4, s_all[k], t_all[k], w_all[k])
    # a sample counts with enough signal against the dot's brightest sub-aperture (per depth)
    peak = w_all.max(axis=(2, 3), keepdims=True)
    keep = (w_all > 0) & (w_all >= min_signal * np.where(peak > 0, peak, np.inf))
    xs, ys = max(float(np.abs(gx).max()), 1e-12), max(float(np.abs(gy).max()), 1e-12)
    zc, zs = 0.5 * (z.max() + z.min()), 0.5 * (z.max() - z.min())
    X = np.broadcast_to(gx, (z.size, m)).ravel()
    Y = np.broadcast_to(gy, (z.size, m)).ravel()
    Z = np.repeat(z, m)
    dmat = _design(X / xs, Y / ys, (Z - zc) / zs, exps)
    S, T, K = (a.reshape(z.size * m, n, n) for a in (s_all, t_all, keep))
    min_samples = 2 * exps.shape[0]

    hold_depth, hold_rms = float("nan"), float("nan")
    if hold_out is not None:
        if hold_out == -1:
            inner = np.argsort(z)[1:-1]
            if inner.size == 0:
                raise VolumetricCalibrationError("volumetric_calibration: a hold-out needs at least 3 depths")
            hold_out = int(inner[np.argmin(np.abs(z[inner] - zc))])
        if not 0 <= hold_out < z.size:
            raise VolumetricCalibrationError(f"hold_out = {hold_out}: must index the {z.size} depths")
        if z.size - 1 < order + 1:
            raise VolumetricCalibrationError(
                f"volumetric_calibration: holding out one of {z.size} depths leaves fewer than order + 1 = {order + 1}"
            )
        out_rows = np.repeat(np.arange(z.size) == hold_out, m)
        c_h, ok_h, used_h = _fit_all(dmat, S, T, K & ~out_rows[:, None, None], min_samples)
        ok_h = _trim(dmat, S, T, c_h, ok_h, used_h)
        rows = np.flatnonzero(out_rows)
        e2 = []
        for i, j in zip(*np.nonzero(ok_h)):
            k = rows[K[rows, i, j]]
            e2.append((dmat[k] @ c_h[0, i, j] - S[k, i, j]) ** 2 + (dmat[k] @ c_h[1, i, j] - T[k, i, j]) ** 2)
        hold_depth = float(z[hold_out])
        hold_rms = float(np.sqrt(np.concatenate(e2).mean())) if e2 else float("nan")

    coef, ok, used = _fit_all(dmat, S, T, K, min_samples)
    ok = _trim(dmat, S, T, coef, ok, used)
    if not ok.any():
        raise VolumetricCalibrationError(
            "volumetric calibration: no sub-aperture has enough dots found (check the depths, spacing and exposure)"
        )
    rms = np.full((n, n), np.nan)
    nsamp = used.sum(axis=0)
    e2_all = []
    for i, j in zip(*np.nonzero(ok)):
        k = used[:, i, j]
        e2 = (dmat[k] @ coef[0, i, j] - S[k, i, j]) ** 2 + (dmat[k] @ coef[1, i, j] - T[k, i, j]) ** 2
        rms[i, j] = math.sqrt(e2.mean())
        e2_all.append(e2)
    fit_rms = float(np.sqrt(np.concatenate(e2_all).mean()))
    le = {"units": "lenslets"}
    return xr.Dataset(
        {
            "coef": (("axis", "prow", "pcol", "term"), coef, {"long_name": "polynomial coefficients (s, t)", **le}),
            "exponents": (("term", "power"), exps, {"long_name": "exponents of x, y, z per term"}),
            "valid": (("prow", "pcol"), ok, {"long_name": "sub-aperture calibrated"}),
            "rms": (("prow", "pcol"), rms, {"long_name": "fit residual rms", **le}),
            "n_samples": (("prow", "pcol"), nsamp, {"long_name": "dot centroids used"}),
        },
        coords={
            "axis": ("axis", ["s", "t"]),
            "power": ("power", ["x", "y", "z"]),
            "prow": ("prow", np.arange(n)),
            "pcol": ("pcol", np.arange(n)),
        },
        attrs={
            "method": "Hall et al. 2018, Appl. Opt. 57(4) 914: polynomial (x, y, z) -> (s, t) per sub-aperture",
            "order": int(order),
            "x_scale": xs,
            "y_scale": ys,
            "z_center": float(zc),
            "z_scale": float(zs),
            "z_min": float(z.min()),
            "z_max": float(z.max()),
            "depths": [float(v) for v in z],
            "spacing": float(spacing),
            "origin_x": float(origin[0]),
            "origin_y": float(origin[1]),
            "window": int(window),
            "n_dots": int(m),
            "n_lrow": int(lf0.sizes["lrow"]),
            "n_lcol": int(lf0.sizes["lcol"]),
            "pixels_per_lenslet": int(n),
            "fit_rms_lenslets": fit_rms,
            "holdout_depth": hold_depth,
            "holdout_rms_lenslets": hold_rms,
            "valid_subapertures": int(ok.sum()),
        },
    )


def _norm(cal: xr.Dataset, x, y, z):
    a = cal.attrs
    return x / a["x_scale"], y / a["y_scale"], (z - a["z_center"]) / a["z_scale"]


def predict(cal: xr.Dataset, x: Any, y: Any, z: Any) -> xr.DataArray:
    """The calibrated (s, t) [lenslets] of object points in every sub-aperture.

    Returns
    -------
    xarray.DataArray
        Dims ``("axis", "point", "prow", "pcol")``; NaN where the sub-aperture is not calibrated.
    """
    x, y, z = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, float)) for v in (x, y, z)))
    d = _design(*_norm(cal, x.ravel(), y.ravel(), z.ravel()), cal["exponents"].values)
    out = np.einsum("pk,aijk->apij", d, cal["coef"].values)
    out[:, :, ~cal["valid"].values] = np.nan
    return xr.DataArray(out, dims=("axis", "point", "prow", "pcol"), coords={"axis": ["s", "t"]})


def predict_thin_lens(lightfield: xr.DataArray, camera: PlenopticCamera, x: Any, y: Any, z: Any) -> xr.DataArray:
    """The thin-lens (s, t) [lenslets] of object points in every sub-aperture of the resampled angular grid.

    What the nominal camera predicts where :func:`predict` gives the calibrated mapping (eqs
    5.10–5.15 inverted, on the lenslet grid registered in ``lightfield``).

    Returns
    -------
    xarray.DataArray
        Dims ``("axis", "point", "prow", "pcol")``, as :func:`predict`.
    """
    x, y, z = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, float)) for v in (x, y, z)))
    s, t = _nominal_positions(lightfield, camera, x.ravel(), y.ravel(), z.ravel())
    return xr.DataArray(np.stack([s, t]), dims=("axis", "point", "prow", "pcol"), coords={"axis": ["s", "t"]})


@numba.njit(nogil=True, cache=True)
def _gather(rad, d, dx_, dy_, cs, ct, ii, jj, area, out):  # pragma: no cover - compiled
    """out[v] = Σ_uv bilinear(rad[:, :, i, j], P(v)) · |det ∂P/∂(x, y)| · area."""
    lr, lc = rad.shape[0], rad.shape[1]
    nv, nt = d.shape
    for q in range(ii.size):
        i, j = ii[q], jj[q]
        for v in range(nv):
            s = 0.0
            t = 0.0
            sx = 0.0
            sy = 0.0
            tx = 0.0
            ty = 0.0
            for k in range(nt):
                s += d[v, k] * cs[q, k]
                t += d[v, k] * ct[q, k]
                sx += dx_[v, k] * cs[q, k]
                sy += dy_[v, k] * cs[q, k]
                tx += dx_[v, k] * ct[q, k]
                ty += dy_[v, k] * ct[q, k]
            c0 = math.floor(s)
            r0 = math.floor(t)
            if c0 < 0 or r0 < 0 or c0 + 1 >= lc or r0 + 1 >= lr:
                continue
            ws = s - c0
            wt = t - r0
            val = (
                rad[r0, c0, i, j] * (1.0 - ws) * (1.0 - wt)
                + rad[r0, c0 + 1, i, j] * ws * (1.0 - wt)
                + rad[r0 + 1, c0, i, j] * (1.0 - ws) * wt
                + rad[r0 + 1, c0 + 1, i, j] * ws * wt
            )
            out[v] += val * abs(sx * ty - sy * tx) * area
    return out


class _VolRays:
    """The light field and calibration arrays of :func:`volumetric_stack` (kept out of dask's tokenizer)."""

    __slots__ = ("cs", "ct", "exps", "ii", "jj", "rad")

    def __init__(self, lightfield: xr.DataArray, cal: xr.Dataset) -> None:
        self.rad = resample_angular(lightfield)
        ii, jj = np.nonzero(cal["valid"].values)
        self.ii, self.jj = ii.astype(np.int64), jj.astype(np.int64)
        coef = cal["coef"].values
        self.cs = np.ascontiguousarray(coef[0, ii, jj])
        self.ct = np.ascontiguousarray(coef[1, ii, jj])
        self.exps = cal["exponents"].values


def _vplane(rays: _VolRays, attrs: dict, z: float, xg: np.ndarray, yg: np.ndarray, dtype) -> np.ndarray:
    X, Y = np.meshgrid(xg, yg)
    xs, ys = attrs["x_scale"], attrs["y_scale"]
    xn, yn = X.ravel() / xs, Y.ravel() / ys
    zn = np.full(xn.size, (z - attrs["z_center"]) / attrs["z_scale"])
    e = rays.exps
    d = _design(xn, yn, zn, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        dxn = np.stack([a * np.where(a > 0, xn ** np.maximum(a - 1, 0), 0.0) * yn**b * zn**c for a, b, c in e], -1)
        dyn = np.stack([b * xn**a * np.where(b > 0, yn ** np.maximum(b - 1, 0), 0.0) * zn**c for a, b, c in e], -1)
    dx = float(xg[1] - xg[0]) if xg.size > 1 else 1.0
    dy = float(yg[1] - yg[0]) if yg.size > 1 else 1.0
    out = np.zeros(xn.size)
    _gather(rays.rad, d, dxn / xs, dyn / ys, rays.cs, rays.ct, rays.ii, rays.jj, abs(dx * dy), out)
    return out.reshape(1, yg.size, xg.size).astype(dtype, copy=False)


def volumetric_stack(
    lightfield: xr.DataArray,
    calibration: xr.Dataset | VolumetricCalibration,
    z: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    *,
    dtype: Any = np.float32,
    camera: PlenopticCamera | None = None,
) -> xr.DataArray:
    """Refocus a light field onto object planes through the volumetric calibration (Hall 2018).

    Voxel (x, y, z) = Σ over calibrated sub-apertures of the bilinear sample of the sub-aperture
    image at P_uv(x, y, z), times the lenslet area the voxel covers there (module docstring):
    the thin-lens shift-and-add with the fitted mapping in place of eqs 5.10–5.15.

    Parameters
    ----------
    lightfield : xarray.DataArray
        A registered light field (:func:`lfstudy.lightfield.register`) with the shape the
        calibration was fitted on.
    calibration : xarray.Dataset or VolumetricCalibration
        From :func:`fit_volumetric`.
    z, x, y : ndarray
        The object grid [mm]: ascending depths (within the calibrated depths, 5 % of their range
        either side) and uniform ascending x and y.
    dtype : numpy dtype
        Output dtype.
    camera : PlenopticCamera, optional
        Only for the output's attrs.

    Returns
    -------
    xarray.DataArray ``intensity``, dims ``("z", "y", "x")``, lazy (one dask chunk per plane),
    laid out as :func:`lfstudy.lightfield.focal_stack` with ``resize=True``.
    """
    vcal = VolumetricCalibration.of(calibration)
    calibration = vcal.dataset
    a = calibration.attrs
    vcal.check_lightfield(lightfield)
    zg, xg, yg = (np.asarray(v, dtype=float) for v in (z, x, y))
    vcal.check_depths(zg)
    rays = _VolRays(lightfield, calibration)
    tag = uuid.uuid4().hex
    rays_d = dask.delayed(rays, name=f"volcal-rays-{tag}")
    fn = dask.delayed(_vplane, name=f"volcal-fn-{tag}", pure=True)
    attrs_in = {k: a[k] for k in ("x_scale", "y_scale", "z_center", "z_scale")}
    blocks = [
        da.from_delayed(
            fn(rays_d, attrs_in, float(zk), xg, yg, dtype, dask_key_name=f"volcal-{tag}-{i}"),
            shape=(1, yg.size, xg.size),
            dtype=dtype,
        )
        for i, zk in enumerate(zg)
    ]
    coords = {
        "z": ("z", zg, {"units": "mm", "long_name": "depth z (object frame, +z away from camera)"}),
        "y": ("y", yg, {"units": "mm", "long_name": "y (object frame, up)"}),
        "x": ("x", xg, {"units": "mm", "long_name": "x (object frame)"}),
    }
    attrs = {
        "units": lightfield.attrs.get("units", "counts"),
        "long_name": "refocused intensity (volumetric calibration)",
        "y_direction": "y ascends with the row index (object frame, +y up; plot with origin='lower')",
        "resize": 1,
        "voxel_size": float(xg[1] - xg[0]) if xg.size > 1 else float("nan"),
        "voxel_size_units": "mm",
        "refocus": "volumetric calibration (Hall et al. 2018): bilinear gather of each sub-aperture at P_uv(x, y, z)",
        "volcal_order": int(a["order"]),
        "volcal_fit_rms_lenslets": float(a["fit_rms_lenslets"]),
    }
    if camera is not None:
        attrs.update(camera.to_attrs())
    return xr.DataArray(
        da.concatenate(blocks, axis=0), dims=("z", "y", "x"), coords=coords, attrs=attrs, name="intensity"
    )
