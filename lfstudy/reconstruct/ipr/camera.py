"""Where IPR compares: the model camera fitted to the calibrated lenslet centres, the sensor frame of the
light field's samples, and the volumetric calibration's frame (package docstring, "Forward model and where it
is compared").

The model camera is the nominal camera (optics, sensor) with its lenslet grid replaced by the one fitted
to the calibrated centres (:func:`calibrated_camera`), never the simulator's true grid. The light field's
samples are put back on the sensor (:func:`_raw_from_lightfield`), where the fit compares on exactly the
pixels the light field holds. With a volumetric calibration the fit runs in the nominal camera's frame and
:func:`volumetric_frame` moves positions between the two.
"""

from __future__ import annotations

import math

import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct.registry import ReconstructionError

__all__ = ["calibrated_camera", "volumetric_frame"]

_MAX_ROTATION_PX = 0.05  # largest lenslet displacement [px] a calibrated rotation may cause and be ignored


def calibrated_camera(camera: PlenopticCamera, centers: xr.Dataset) -> tuple[PlenopticCamera, dict[str, float]]:
    """The nominal camera with its lenslet grid fitted to the calibrated centres.

    The lenslet centres are the calibrated spot centres un-projected (``spot·si/(si + fl)``);
    an affine lattice ``c = o + A·(col, row)`` is fitted to the valid ones by least squares.
    The pitch is the mean of the two axes', the offset the one that puts the camera's own
    lattice (centred on its offset) on the fitted one.

    Returns
    -------
    camera : PlenopticCamera
        ``camera.with_(lenslet_pitch=..., lenslet_offset_x=..., lenslet_offset_y=..., lenslet_rotation=0)``
        with the nominal camera's main-lens f-number (never re-derived from the fitted pitch).
    info : dict
        ``grid_pitch_mm``, ``grid_offset_x_mm``, ``grid_offset_y_mm``, ``grid_rotation_rad`` (fitted,
        not used), ``grid_residual_px`` (largest distance of a calibrated centre from the model lattice).

    Raises
    ------
    ReconstructionError
        Too few valid centres, or a rotation the exact renderer cannot model out of focus.
    """
    for k in ("x", "y"):
        if k not in centers:
            raise ReconstructionError(f"centers lacks {k!r}: use lfstudy.lightfield.find_lenslet_centers")
    s = camera.si / (camera.si + camera.lenslet_focal_length)
    cx = np.asarray(centers["x"].values, dtype=np.float64) * s
    cy = np.asarray(centers["y"].values, dtype=np.float64) * s
    ok = np.asarray(centers["valid"].values, bool) if "valid" in centers else np.ones(cx.shape, bool)
    ok &= np.isfinite(cx) & np.isfinite(cy)
    if ok.sum() < 6:
        raise ReconstructionError(f"centers: {int(ok.sum())} valid lenslet centres; IPR needs at least 6")
    rows, cols = np.nonzero(ok)
    a = np.column_stack([np.ones(rows.size), cols, rows])
    (ax0, ax1, ax2), *_ = np.linalg.lstsq(a, cx[ok], rcond=None)
    (ay0, ay1, ay2), *_ = np.linalg.lstsq(a, cy[ok], rcond=None)
    pitch = 0.5 * (math.hypot(ax1, ay1) + math.hypot(ax2, ay2))
    rot = math.atan2(ay1, ax1)
    span_px = 0.5 * max(cx.shape) * pitch / camera.pixel_pitch
    if abs(rot) * span_px > _MAX_ROTATION_PX:
        raise ReconstructionError(
            f"centers: the calibrated lenslet grid is rotated by {rot:.3g} rad ({abs(rot) * span_px:.2g} px at the "
            f"array's edge, allowed {_MAX_ROTATION_PX} px): the exact renderer IPR fits with models rotated grids "
            "only in focus; use reconstruct.method mart for this camera"
        )
    # the camera's lattice is o + pitch·(k − (N − 1)/2) with N itself depending on o (the grid covers
    # the sensor): the offsets that put a lattice point on the fitted one (ax0, ay0) are a ladder of
    # half pitches, of which those whose own N keeps the phase are valid; of these, the pair whose
    # lattice holds every calibrated centre (an edge row may exist for one and not the other), then the smallest
    # offset; among equal fits the pitch nearest the fitted one. Where the sensor is a whole number of
    # lenslets (the demo's 640 x 480 px at pitch 0.1184 mm: 40 x 30), a fitted pitch a hair short needs one
    # more lenslet, whose lattice has the other phase at every offset: the pitches that make the sensor whole
    # (and the nominal one) are tried too, within the calibration's precision (the residual decides)
    # the main lens keeps its f-number: a "matched" camera would re-derive it from the fitted pitch and round
    # it to a standard stop, and at the thesis' pitch (0.125 mm, f/4 lenslets: the matched f/2 exactly) a
    # pitch fitted 1e-9 mm short rounds up to f/2.8, a 1/sqrt(2) smaller aperture image behind every lenslet
    camera = camera.with_(fnumber=camera.main_fnumber)
    pitches = {pitch, camera.lenslet_pitch}
    for size in (camera.sensor_width, camera.sensor_height):
        pitches.add(size / max(1, round(size / pitch)))
    best = None
    for p in sorted(pitches, key=lambda v: abs(v - pitch)):
        for ox in _lattice_offsets(camera, p, ax0, "x"):
            for oy in _lattice_offsets(camera, p, ay0, "y"):
                c = camera.with_(lenslet_pitch=p, lenslet_offset_x=ox, lenslet_offset_y=oy, lenslet_rotation=0.0)
                key = (round(_grid_residual(c, cx[ok], cy[ok]), 3), abs(p - pitch), math.hypot(ox, oy))
                if best is None or key < best[0]:
                    best = key, c
    if best is None:
        raise ReconstructionError("centers: no lenslet offset reproduces the calibrated grid")
    cam = best[1]
    resid = _grid_residual(cam, cx[ok], cy[ok])
    return cam, {
        "grid_pitch_mm": float(cam.lenslet_pitch),
        "grid_offset_x_mm": float(cam.lenslet_offset_x),
        "grid_offset_y_mm": float(cam.lenslet_offset_y),
        "grid_rotation_rad": float(rot),
        "grid_residual_px": float(resid),
    }


def _lattice_offsets(camera: PlenopticCamera, pitch: float, point: float, axis: str) -> list[float]:
    """The lenslet offsets along ``axis`` (within one pitch) whose lattice, with the lenslet count
    that offset gives, holds ``point`` [mm]."""

    def phase_error(o: float) -> float:
        cam = camera.with_(lenslet_pitch=pitch, **{f"lenslet_offset_{axis}": o}, lenslet_rotation=0.0)
        n = cam.n_lenslets_x if axis == "x" else cam.n_lenslets_y
        first = o - pitch * (n - 1) / 2.0 if axis == "x" else o + pitch * (n - 1) / 2.0
        return (point - first + pitch / 2.0) % pitch - pitch / 2.0

    base = phase_error(0.0)
    ladder = (base + m * pitch / 2.0 for m in range(-4, 5))
    return [float(o) for o in ladder if abs(o) < pitch and abs(phase_error(o)) < 1e-9 * pitch]


def _grid_residual(cam: PlenopticCamera, cx: np.ndarray, cy: np.ndarray) -> float:
    """Largest distance [px] of the centres (cx, cy) [mm] from the nearest lenslet centre of ``cam``."""
    mx, my = cam.lenslet_centers()
    pitch = cam.lenslet_pitch
    jx = np.clip(np.rint((cx - mx[0, 0]) / pitch).astype(int), 0, mx.shape[1] - 1)
    iy = np.clip(np.rint((my[0, 0] - cy) / pitch).astype(int), 0, mx.shape[0] - 1)
    return float(np.hypot(cx - mx[iy, jx], cy - my[iy, jx]).max() / cam.pixel_pitch)


def _raw_from_lightfield(lf: xr.DataArray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The light field's samples put back on the sensor, and the mask of the pixels it holds."""
    vals = np.asarray(lf.values, dtype=np.float64)
    lr, lc, n, _ = vals.shape
    row0 = np.asarray(lf["row0"].values, np.int64)
    col0 = np.asarray(lf["col0"].values, np.int64)
    valid = np.asarray(lf["valid"].values, bool) if "valid" in lf.coords else np.ones((lr, lc), bool)
    img = np.zeros(shape)
    mask = np.zeros(shape, np.uint8)
    k = np.arange(n)
    for i, j in zip(*np.nonzero(valid)):
        rr, cc = row0[i, j] + k, col0[i, j] + k
        img[np.ix_(rr, cc)] = vals[i, j]
        mask[np.ix_(rr, cc)] = 1
    return img, mask


def _lightfield_from_raw(img: np.ndarray, lf: xr.DataArray) -> xr.DataArray:
    """An image cut into ``lf``'s blocks (the inverse of :func:`_raw_from_lightfield`)."""
    n = lf.sizes["prow"]
    row0 = np.asarray(lf["row0"].values, np.int64)[..., None, None] + np.arange(n)[:, None]
    col0 = np.asarray(lf["col0"].values, np.int64)[..., None, None] + np.arange(n)[None, :]
    ny, nx = img.shape
    ok = (row0 >= 0) & (row0 < ny) & (col0 >= 0) & (col0 < nx)
    vals = np.where(ok, img[np.clip(row0, 0, ny - 1), np.clip(col0, 0, nx - 1)], 0.0)
    return lf.copy(data=vals.astype(lf.dtype))


def volumetric_frame(
    xyz: np.ndarray,
    lightfield: xr.DataArray,
    camera: PlenopticCamera,
    calibration: xr.Dataset,
    *,
    to: str = "calibrated",
    iterations: int = 6,
) -> np.ndarray:
    """Positions moved between the nominal camera's frame and the volumetric calibration's.

    IPR fits with the exact renderer of the nominal camera, so a fitted position ``x_nom`` is
    where the nominal camera would have to see the particle to record the image it did. The
    calibrated position is the one the fitted mapping (Hall et al. 2018) sends to the same
    sub-aperture image positions: ``x_cal = argmin_x Σ_uv |P_uv(x) − Q_uv(x_nom)|²``, P the
    calibration's polynomials and Q the thin-lens mapping of the same sub-apertures
    (:func:`lfstudy.lightfield.volcal.predict_thin_lens`), over the calibrated sub-apertures;
    ``to="nominal"`` solves the reverse, ``argmin_x Σ |Q(x) − P(x_cal)|²``. Gauss–Newton with a
    central-difference Jacobian, all particles at once (3 x 3 normal equations each).

    Parameters
    ----------
    xyz : ndarray (N, 3)
        Positions [mm] in the frame ``to`` is not.
    lightfield : xarray.DataArray
        The registered light field (its lenslet grid and shape).
    camera : PlenopticCamera
        The nominal camera.
    calibration : xarray.Dataset
        From :func:`lfstudy.lightfield.volcal.fit_volumetric`.
    to : {"calibrated", "nominal"}
    iterations : int
        Gauss–Newton steps.

    Returns
    -------
    ndarray (N, 3)
    """
    from lfstudy.lightfield.volcal import predict, predict_thin_lens

    if to not in ("calibrated", "nominal"):
        raise ReconstructionError(f"volumetric_frame: to = {to!r}: allowed values are calibrated, nominal")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if not len(xyz):
        return xyz.copy()
    ok = np.asarray(calibration["valid"].values, bool)

    def cal(p: np.ndarray) -> np.ndarray:
        v = predict(calibration, p[:, 0], p[:, 1], p[:, 2]).values[:, :, ok]
        return np.concatenate([v[0], v[1]], axis=1)

    def nom(p: np.ndarray) -> np.ndarray:
        v = predict_thin_lens(lightfield, camera, p[:, 0], p[:, 1], p[:, 2]).values[:, :, ok]
        return np.concatenate([v[0], v[1]], axis=1)

    src, dst = (nom, cal) if to == "calibrated" else (cal, nom)
    target = src(xyz)
    x = xyz.copy()
    h = 1e-4 * max(camera.lenslet_pitch / abs(camera.magnification), 1e-12)  # a thousandth of a voxel or so
    for _ in range(iterations):
        r = dst(x) - target
        jac = np.empty((*r.shape, 3))
        for a in range(3):
            e = np.zeros(3)
            e[a] = h
            jac[..., a] = (dst(x + e) - dst(x - e)) / (2.0 * h)
        jtj = np.einsum("nma,nmb->nab", jac, jac)
        jtr = np.einsum("nma,nm->na", jac, r)
        reg = 1e-12 * np.trace(jtj, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        x = x - np.linalg.solve(jtj + reg, jtr[..., None])[..., 0]
    if not np.all(np.isfinite(x)):
        raise ReconstructionError("the volumetric calibration cannot map the particle positions (non-finite)")
    return x
