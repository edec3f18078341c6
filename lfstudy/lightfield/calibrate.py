"""Lenslet calibration from a pinhole (or white) image (thesis sec. 5.1, eq. 5.1).

The thesis places a hand-tuned Cartesian grid over the pinhole image and
fits a 2-D Gaussian (eq. 5.1) with ``fminsearch`` under every lenslet (about
10 minutes). Here the grid is found automatically and every spot is fitted
at once:

1. **Lattice detection** - the power spectrum of a central crop shows the
   lenslet lattice as peaks at its two reciprocal vectors; their positions
   give pitch and rotation, the phase of the (separable) DFT at those
   vectors gives the offset.
2. **Lattice fit** - windowed, background-subtracted centroids around the
   predicted positions are fitted by an affine lattice (least squares),
   first near the crop, then over the whole sensor (so distortion-free
   grids are predicted to a few hundredths of a pixel everywhere).
3. **Sub-pixel refinement** - a 2-D Gaussian with background (eq. 5.1 plus
   a constant) is fitted to every spot by Levenberg-Marquardt iterations
   vectorised over all lenslets; a windowed centroid is computed too and
   the estimator that scatters less about the lattice is kept (flat-topped
   aperture-disk spots favour the centroid).

What is returned
----------------
``cx``/``cy`` (and ``x``/``y`` in mm) are the centres of the *lenslet
images* (spots) as measured on the sensor. Under a pinhole main lens the
spot is the image of the main-lens aperture centre through the lenslet, i.e.
the lenslet centre ``c`` projected from the main-lens centre onto the
sensor: ``c·(si + fl)/si`` (the chief ray of the "bulk angle", eqs 5.4-5.5).
:func:`lenslet_positions` converts them back to the lenslet centres ``c``
(what registration uses as the spatial coordinate); :func:`expected_centers`
gives the geometric expectation for a camera, in pixels.

Pixel convention: pixel (row r, col c) has its centre at (c, r); the sensor
frame has its origin at the sensor centre, x right, y up (row 0 at the top).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = [
    "PitchWarning",
    "CalibrationError",
    "find_lenslet_centers",
    "expected_centers",
    "lenslet_positions",
    "synthetic_pinhole",
    "pixel_to_sensor",
]


#: Relative difference of the configured and the fitted lenslet pitch above which calibration warns.
PITCH_TOLERANCE = 0.02


class PitchWarning(UserWarning):
    """The lenslet pitch the config gives differs from the pitch fitted to the image."""


class CalibrationError(ValueError):
    """The image cannot be calibrated (no grid, NaNs, wrong size...)."""


# ----------------------------------------------------------------- helpers
def pixel_to_sensor(
    cx: np.ndarray, cy: np.ndarray, shape: tuple[int, int], pixel_pitch: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (col, row; pixel centres at integers) → sensor frame [mm] (eqs 5.2-5.3)."""
    ny, nx = shape
    x = (np.asarray(cx) + 0.5) * pixel_pitch - nx * pixel_pitch / 2.0  # eq. 5.2
    y = ny * pixel_pitch / 2.0 - (np.asarray(cy) + 0.5) * pixel_pitch  # eq. 5.3
    return x, y


def sensor_to_pixel(
    x: np.ndarray, y: np.ndarray, shape: tuple[int, int], pixel_pitch: float
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pixel_to_sensor`."""
    ny, nx = shape
    return (
        (np.asarray(x) + nx * pixel_pitch / 2.0) / pixel_pitch - 0.5,
        (ny * pixel_pitch / 2.0 - np.asarray(y)) / pixel_pitch - 0.5,
    )


def expected_centers(camera: PlenopticCamera, *, projected: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Geometric lenslet-image centres of a camera, in pixels (col, row).

    Parameters
    ----------
    camera : PlenopticCamera
    projected : bool
        True: the lenslet centres projected from the main-lens centre onto the
        sensor, ``c·(si + fl)/si`` (what a pinhole image shows). False: the
        lenslet centres themselves.

    Returns
    -------
    cx, cy : ndarray, shape (n_lenslets_y, n_lenslets_x)
    """
    x, y = camera.lenslet_centers()
    if projected:
        s = (camera.si + camera.lenslet_focal_length) / camera.si
        x, y = x * s, y * s
    return sensor_to_pixel(x, y, (camera.n_pixels_y, camera.n_pixels_x), camera.pixel_pitch)


def lenslet_positions(centers: xr.Dataset, camera: PlenopticCamera) -> tuple[np.ndarray, np.ndarray]:
    """Lenslet centres [mm, sensor frame] from calibrated spot centres.

    The spot under a lenslet is its centre projected from the main-lens
    centre, so the lenslet centre is ``spot·si/(si + fl)``.
    """
    s = camera.si / (camera.si + camera.lenslet_focal_length)
    return np.asarray(centers["x"].values) * s, np.asarray(centers["y"].values) * s


def _as_array(image: Any, camera: PlenopticCamera | None) -> np.ndarray:
    img = image.values if isinstance(image, xr.DataArray) else np.asarray(image)
    if img.ndim != 2:
        raise CalibrationError(f"image must be 2-D (rows, cols); got shape {img.shape}")
    if camera is not None and img.shape != (camera.n_pixels_y, camera.n_pixels_x):
        raise CalibrationError(
            f"image is {img.shape[1]} x {img.shape[0]} px (cols x rows) but the camera sensor is "
            f"{camera.n_pixels_x} x {camera.n_pixels_y} px"
        )
    if min(img.shape) < 8:
        raise CalibrationError(f"image of shape {img.shape} is too small to hold a lenslet grid")
    img = np.asarray(img, dtype=np.float64)
    bad = ~np.isfinite(img)
    if bad.any():
        raise CalibrationError(
            f"image has {int(bad.sum())} non-finite (NaN/inf) pixels; calibration needs a finite "
            "pinhole image (replace dead pixels first)"
        )
    if float(img.max()) == float(img.min()):
        raise CalibrationError("image is blank (constant): no lenslet grid to detect")
    return img


# ---------------------------------------------------------- lattice detection
def _parabolic(lm: float, l0: float, lp: float) -> float:
    d = lm - 2.0 * l0 + lp
    return 0.0 if d >= 0 else 0.5 * (lm - lp) / d


def _detect_reciprocal(img: np.ndarray, pitch_hint: float | None) -> tuple[np.ndarray, float]:
    """Reciprocal lattice vectors (rows k1 ≈ +col, k2 ≈ +row; cycles/px) from the power spectrum."""
    ny, nx = img.shape
    s = int(min(1024, ny, nx)) // 2 * 2
    r0, c0 = (ny - s) // 2, (nx - s) // 2
    crop = img[r0 : r0 + s, c0 : c0 + s]
    win = np.hanning(s)
    power = np.abs(np.fft.rfft2((crop - crop.mean()) * win[:, None] * win[None, :])) ** 2
    ky = np.fft.fftfreq(s)[:, None]
    kx = np.fft.rfftfreq(s)[None, :]
    kk = np.hypot(kx, ky)
    if pitch_hint is not None:
        band = (kk > 1 / (1.2 * pitch_hint)) & (kk < 1 / (0.8 * pitch_hint))
    else:
        band = (kk >= 4.0 / s) & (kk <= 1 / 2.5)
    pb = np.where(band, power, 0.0)
    floor = float(np.median(power[band])) if band.any() else 0.0
    i = np.unravel_index(np.argmax(pb), pb.shape)
    peak = float(pb[i])
    if not (peak > 200.0 * max(floor, 1e-300)):
        if pitch_hint is not None:  # a grid of another pitch? Say so rather than doubt the image
            try:
                k_found, _ = _detect_reciprocal(img, None)
            except CalibrationError:
                pass
            else:
                found = 1.0 / float(np.mean(np.hypot(k_found[:, 0], k_found[:, 1])))
                raise CalibrationError(
                    f"lenslet pitch {pitch_hint:.3f} px in the config does not match the image's {found:.3f} px "
                    f"({100 * (pitch_hint / found - 1):+.0f} % off): check camera.lenslet.pitch, "
                    "camera.sensor.pixel_pitch and the magnification"
                )
        raise CalibrationError(
            "no lenslet grid detected: the image spectrum has no periodic peak "
            f"(peak/median power {peak / max(floor, 1e-300):.3g} < 200); is this a pinhole image?"
        )

    def refine(idx: tuple[int, int]) -> np.ndarray:
        r, c = idx
        lp = np.log(power + 1e-300)
        dr = _parabolic(lp[(r - 1) % s, c], lp[r, c], lp[(r + 1) % s, c])
        dc = _parabolic(lp[r, c - 1], lp[r, c], lp[r, c + 1]) if 0 < c < power.shape[1] - 1 else 0.0
        fy = np.fft.fftfreq(s)[r]
        return np.array([(c + dc) / s, fy + dr / s])  # (kx, ky)

    ka = refine(i)
    # The second basis vector: strongest peak roughly perpendicular to the first.
    ang = np.abs(kx * ka[0] + ky * ka[1]) / (kk * np.hypot(*ka) + 1e-300)
    band2 = band & (ang < 0.5) & (kk > 0.6 * np.hypot(*ka)) & (kk < 1.6 * np.hypot(*ka))
    pb2 = np.where(band2, power, 0.0)
    j = np.unravel_index(np.argmax(pb2), pb2.shape)
    if not pb2[j] > 200.0 * max(floor, 1e-300):
        raise CalibrationError("no 2-D lenslet grid detected: only one periodic direction in the image")
    kb = refine(j)
    # Order: k1 mostly along +col, k2 mostly along +row (row index grows downwards).
    k1, k2 = (ka, kb) if abs(ka[0]) >= abs(kb[0]) else (kb, ka)
    k1 = k1 if k1[0] > 0 else -k1
    k2 = k2 if k2[1] > 0 else -k2
    return np.vstack([k1, k2]), float(peak / max(floor, 1e-300))


def _dft_phase(img: np.ndarray, k: np.ndarray, rows: slice, cols: slice, centre: np.ndarray) -> float:
    """Phase of the DFT at wave vector k over a window (separable: e_rᵀ·I·e_c)."""
    r = np.arange(rows.start, rows.stop) - centre[1]
    c = np.arange(cols.start, cols.stop) - centre[0]
    wr, wc = np.hanning(r.size), np.hanning(c.size)
    er = wr * np.exp(-2j * np.pi * k[1] * r)
    ec = wc * np.exp(-2j * np.pi * k[0] * c)
    sub = img[rows, cols]
    return float(np.angle(er @ (sub - sub.mean()) @ ec))


# ---------------------------------------------------------- spot measurement
def _windows(img: np.ndarray, pc: np.ndarray, pr: np.ndarray, h: int) -> tuple[np.ndarray, ...]:
    """Gather (N, w, w) windows centred on the nearest pixels; flags windows leaving the image."""
    ny, nx = img.shape
    ic, ir = np.rint(pc).astype(np.int64), np.rint(pr).astype(np.int64)
    inside = (ic - h >= 0) & (ic + h < nx) & (ir - h >= 0) & (ir + h < ny)
    off = np.arange(-h, h + 1)
    cc = np.clip(ic[:, None] + off[None, :], 0, nx - 1)
    rr = np.clip(ir[:, None] + off[None, :], 0, ny - 1)
    win = img[rr[:, :, None], cc[:, None, :]]
    return win, ic, ir, inside


def _centroid(img: np.ndarray, pc: np.ndarray, pr: np.ndarray, h: int, n_iter: int = 2):
    """Background-subtracted windowed centroid, re-centred ``n_iter`` times."""
    for _ in range(n_iter):
        win, ic, ir, inside = _windows(img, pc, pr, h)
        bg = np.minimum(win[:, 0, :].mean(1), win[:, -1, :].mean(1))
        bg = np.minimum(bg, np.minimum(win[:, :, 0].mean(1), win[:, :, -1].mean(1)))
        w = np.clip(win - bg[:, None, None], 0.0, None)
        tot = w.sum((1, 2))
        off = np.arange(-h, h + 1, dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            dc = (w.sum(1) @ off) / tot
            dr = (w.sum(2) @ off) / tot
        ok = tot > 0
        pc = np.where(ok, ic + dc, pc)
        pr = np.where(ok, ir + dr, pr)
    return pc, pr, tot, inside


def _gauss_fit(
    img: np.ndarray, pc: np.ndarray, pr: np.ndarray, h: int, sigma0: float, n_iter: int = 8
) -> tuple[np.ndarray, ...]:
    """Levenberg-Marquardt fit of eq. 5.1 plus background, vectorised over spots.

    Parameters per spot: amplitude c, centre (cx, cy), σx, σy, background b.
    Returns cx, cy, amplitude, σx, σy, converged flag and the inside-image flag.
    """
    win, ic, ir, inside = _windows(img, pc, pr, h)
    n = win.shape[0]
    off = np.arange(-h, h + 1, dtype=np.float64)
    X = np.broadcast_to(off[None, :], (2 * h + 1, 2 * h + 1)).ravel()
    Y = np.broadcast_to(off[:, None], (2 * h + 1, 2 * h + 1)).ravel()
    d = win.reshape(n, -1)
    b = np.percentile(d, 20, axis=1)
    p = np.empty((n, 6))
    p[:, 0] = np.maximum(d.max(1) - b, 1e-12)
    p[:, 1] = pc - ic
    p[:, 2] = pr - ir
    p[:, 3] = sigma0
    p[:, 4] = sigma0
    p[:, 5] = b
    lam = np.full(n, 1e-3)

    def model(q):
        ex = (X[None, :] - q[:, 1:2]) / q[:, 3:4]
        ey = (Y[None, :] - q[:, 2:3]) / q[:, 4:5]
        g = np.exp(-0.5 * (ex * ex + ey * ey))
        return q[:, 0:1] * g + q[:, 5:6], g, ex, ey

    m, g, ex, ey = model(p)
    cost = ((d - m) ** 2).sum(1)
    eye = np.eye(6)[None]
    for _ in range(n_iter):
        a = p[:, 0:1] * g
        J = np.stack(
            [
                g,
                a * ex / p[:, 3:4],
                a * ey / p[:, 4:5],
                a * ex * ex / p[:, 3:4],
                a * ey * ey / p[:, 4:5],
                np.ones_like(g),
            ],
            axis=2,
        )
        JtJ = np.einsum("nki,nkj->nij", J, J)
        Jtr = np.einsum("nki,nk->ni", J, d - m)
        diag = np.einsum("nii->ni", JtJ)
        A = JtJ + lam[:, None, None] * diag[:, :, None] * eye
        try:
            step = np.linalg.solve(A, Jtr[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            A = A + 1e-9 * eye * (diag.max(1)[:, None, None] + 1.0)
            step = np.linalg.solve(A, Jtr[:, :, None])[:, :, 0]
        q = p + step
        q[:, 3:5] = np.clip(q[:, 3:5], 0.2, 2.0 * h + 1.0)
        with np.errstate(over="ignore", invalid="ignore"):
            m2, g2, ex2, ey2 = model(q)
            c2 = ((d - m2) ** 2).sum(1)
        better = np.isfinite(c2) & (c2 <= cost)
        p = np.where(better[:, None], q, p)
        m = np.where(better[:, None], m2, m)
        g = np.where(better[:, None], g2, g)
        ex = np.where(better[:, None], ex2, ex)
        ey = np.where(better[:, None], ey2, ey)
        cost = np.where(better, c2, cost)
        lam = np.where(better, lam * 0.3, lam * 10.0)
    conv = np.isfinite(p).all(1) & (np.abs(p[:, 1]) <= h) & (np.abs(p[:, 2]) <= h) & (p[:, 0] > 0)
    return ic + p[:, 1], ir + p[:, 2], p[:, 0], p[:, 3], p[:, 4], conv, inside


def _spot_sigma(img: np.ndarray, pc: np.ndarray, pr: np.ndarray, pitch: float) -> float:
    """Spot σ [px] from the mean of central spots (second moment above background)."""
    h = max(1, int(0.45 * pitch))
    win, _, _, inside = _windows(img, pc, pr, h)
    win = win[inside]
    if win.shape[0] == 0:
        return 1.0
    mean = win.mean(0)
    mean = np.clip(mean - np.percentile(mean, 30), 0, None)
    off = np.arange(-h, h + 1, dtype=np.float64)
    tot = mean.sum()
    if tot <= 0:
        return 1.0
    mx, my = mean.sum(0) @ off / tot, mean.sum(1) @ off / tot
    vx = mean.sum(0) @ (off - mx) ** 2 / tot
    vy = mean.sum(1) @ (off - my) ** 2 / tot
    return float(np.sqrt(max(0.5 * (vx + vy) - 1.0 / 12.0, 0.04)))


def _fit_lattice(n: np.ndarray, m: np.ndarray, pc: np.ndarray, pr: np.ndarray) -> np.ndarray:
    """Affine lattice pos = o + n·a1 + m·a2, least squares with one outlier rejection pass."""
    D = np.column_stack([np.ones_like(n, dtype=float), n, m])
    keep = np.ones(n.size, bool)
    coef = None
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(D[keep], np.column_stack([pc[keep], pr[keep]]), rcond=None)
        res = np.hypot(*(D @ coef - np.column_stack([pc, pr])).T)
        mad = np.median(res[keep]) + 1e-6
        keep = res < max(6.0 * mad, 0.05)
    return coef  # rows: origin, a1, a2; columns: (col, row)


# ------------------------------------------------------------------ public
def find_lenslet_centers(
    image: xr.DataArray | np.ndarray,
    camera: PlenopticCamera | None = None,
    *,
    pitch_px: float | None = None,
    pixel_pitch: float | None = None,
    min_amplitude: float = 0.25,
    window: int | None = None,
    n_iter: int = 8,
    estimator: str = "auto",
) -> xr.Dataset:
    """Find every lenslet-image centre in a pinhole image (sec. 5.1, eq. 5.1).

    Parameters
    ----------
    image : DataArray or ndarray, shape (rows, cols)
        Pinhole (or white) image, row 0 at the top.
    camera : PlenopticCamera, optional
        If given: the image size must match its sensor, the pitch search is
        narrowed around the expected spot pitch, and the output grid is the
        camera's lenslet grid (``n_lenslets_y x n_lenslets_x``; lenslets whose
        spot is off the sensor are flagged invalid). Without a camera the
        grid is every lattice row/column with a spot on the sensor.
    pitch_px : float, optional
        Approximate spot pitch [px] to narrow the search (±20 %).
    pixel_pitch : float, optional
        Pixel pitch [mm] for ``x``/``y``; default from the camera or from the
        DataArray's ``x`` coordinate. Without any, ``x``/``y`` are omitted.
    min_amplitude : float
        Spots dimmer than this fraction of the median amplitude are flagged.
    window : int, optional
        Half-width [px] of the fitting window; default from the measured spot size.
    n_iter : int
        Levenberg-Marquardt iterations.
    estimator : {"auto", "gauss", "centroid"}
        Sub-pixel estimator: the eq. 5.1 Gaussian fit, a background-subtracted
        ±2σ centroid, or (default) whichever scatters less about the fitted
        lattice (the centroid wins on flat-topped aperture-disk spots).

    Returns
    -------
    xarray.Dataset
        Over (``lenslet_row``, ``lenslet_col``), row 0 at the top: ``cx``,
        ``cy`` (spot centres, pixel units, pixel (r, c) centred at (c, r)),
        ``x``, ``y`` (the same in mm, sensor frame), ``valid``, ``amplitude``,
        ``sigma_x``/``sigma_y`` (px), ``cx_lattice``/``cy_lattice`` (the fitted
        lattice). Invalid lenslets carry the lattice position in ``cx``/``cy``.
        Attrs: ``pitch_px`` (mean), ``pitch_x_px``, ``pitch_y_px``,
        ``rotation`` (rad, sensor frame, y up), ``offset_x_px``/``offset_y_px``
        (lattice point nearest the image centre, relative to it),
        ``lattice_rms_px``, ``n_valid``, ``estimator``, ``quantity``.

    Raises
    ------
    CalibrationError (a ValueError)
        Wrong size for the camera, non-finite pixels, blank image, or no grid.
    """
    img = _as_array(image, camera)
    if estimator not in ("auto", "gauss", "centroid"):
        raise ValueError(f"estimator = {estimator!r}: allowed values are 'auto', 'gauss', 'centroid'")
    if pixel_pitch is None:
        if camera is not None:
            pixel_pitch = camera.pixel_pitch
        elif isinstance(image, xr.DataArray) and "x" in image.coords and image.sizes.get(image.dims[-1], 0) > 1:
            pixel_pitch = float(abs(image["x"].values[1] - image["x"].values[0]))
    if pitch_px is None and camera is not None:
        pitch_px = camera.pixels_per_lenslet * (camera.si + camera.lenslet_focal_length) / camera.si
    guess = _lattice_guess(img, pitch_px)
    lattice = _fit_lattice_to_spots(img, guess, window, min_amplitude)
    grid = _lenslet_grid(lattice, camera, img.shape)
    spots = _refine_spots(img, grid, lattice, n_iter, min_amplitude, estimator)
    out = _centers_dataset(img.shape, guess, lattice, grid, spots, pixel_pitch, camera)
    if pitch_px is not None and abs(out.attrs["pitch_px"] / pitch_px - 1) > PITCH_TOLERANCE:
        fitted = float(out.attrs["pitch_px"])
        warnings.warn(
            f"lenslet pitch {pitch_px:.3f} px in the config differs from the image's fitted {fitted:.3f} px "
            f"({100 * (pitch_px / fitted - 1):+.1f} %): {int(out.attrs['n_valid'])} lenslets found, those the "
            "config's grid misses are lost; correct camera.lenslet.pitch (or the pixel pitch, the magnification)",
            PitchWarning,
            stacklevel=2,
        )
    return out


@dataclass
class _Guess:
    """Lattice from the spectrum: reciprocal vectors K, basis A (columns a1, a2), a lattice point."""

    K: np.ndarray
    A: np.ndarray
    origin: np.ndarray
    prominence: float
    pitch: float
    crop: int  # side of the central crop used
    centre: np.ndarray  # its centre (col, row)


@dataclass
class _Lattice:
    """The affine lattice fitted to spot centroids (rows: origin, a1, a2) and the spot window."""

    coef: np.ndarray
    half_window: int
    sigma: float


@dataclass
class _Grid:
    """Lattice indices (n, m) of the output grid, its shape and the lattice positions."""

    n: np.ndarray
    m: np.ndarray
    shape: tuple[int, int]
    col: np.ndarray
    row: np.ndarray


def _lattice_guess(img: np.ndarray, pitch_px: float | None) -> _Guess:
    """Step 1: pitch and rotation from the power spectrum, offset from the DFT phase."""
    ny, nx = img.shape
    K, prominence = _detect_reciprocal(img, pitch_px)
    A = np.linalg.inv(K)  # columns a1, a2 in (col, row)
    s = int(min(1024, ny, nx)) // 2 * 2
    r0, c0 = (ny - s) // 2, (nx - s) // 2
    centre = np.array([c0 + s / 2.0, r0 + s / 2.0])
    ph = np.array([_dft_phase(img, K[i], slice(r0, r0 + s), slice(c0, c0 + s), centre) for i in range(2)])
    origin = centre + A @ (-ph / (2 * np.pi))  # a lattice point near the crop centre
    return _Guess(K, A, origin, prominence, float(np.mean(np.hypot(A[0], A[1]))), s, centre)


def _predict(coef: np.ndarray, n: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lattice positions (col, row) of indices (n, m): origin + n·a1 + m·a2."""
    p = coef[0][None, :] + np.outer(n, coef[1]) + np.outer(m, coef[2])
    return p[:, 0], p[:, 1]


def _fit_lattice_to_spots(img: np.ndarray, g: _Guess, window: int | None, min_amplitude: float) -> _Lattice:
    """Step 2: affine lattice fitted to windowed centroids, first near the crop (where the FFT
    prediction is good), then over the whole sensor."""
    ny, nx = img.shape
    corners = np.array([[-0.5, -0.5], [nx - 0.5, -0.5], [-0.5, ny - 0.5], [nx - 0.5, ny - 0.5]])
    lat = (corners - g.origin) @ g.K.T  # (n, m) of the corners
    nn, mm = np.meshgrid(
        np.arange(int(np.floor(lat[:, 0].min())), int(np.ceil(lat[:, 0].max())) + 1),
        np.arange(int(np.floor(lat[:, 1].min())), int(np.ceil(lat[:, 1].max())) + 1),
    )
    nf, mf = nn.ravel().astype(float), mm.ravel().astype(float)
    coef = np.vstack([g.origin, g.A[:, 0], g.A[:, 1]])
    pc, pr = _predict(coef, nf, mf)
    near = np.hypot(pc - g.centre[0], pr - g.centre[1]) < 0.25 * g.crop
    sigma = _spot_sigma(img, pc[near], pr[near], g.pitch)
    h = int(window) if window is not None else int(np.clip(np.ceil(2.5 * sigma), 1, max(1, int(0.45 * g.pitch))))
    fitted = None
    for radius in (0.5 * g.crop, np.inf):
        qc, qr = _predict(coef, nf, mf)
        sel = np.hypot(qc - g.centre[0], qr - g.centre[1]) <= radius
        ccx, ccy, tot, inside = _centroid(img, qc, qr, h)
        good = sel & inside & (tot > 0)
        if good.sum() < 3:
            break
        good[good] &= tot[good] > min_amplitude * np.median(tot[good])
        if good.sum() < 3:
            break
        coef = fitted = _fit_lattice(nf[good], mf[good], ccx[good], ccy[good])
    if fitted is None:
        raise CalibrationError("no lenslet grid detected: too few spots found in the image")
    return _Lattice(fitted, h, sigma)


def _lenslet_grid(lat: _Lattice, camera: PlenopticCamera | None, shape: tuple[int, int]) -> _Grid:
    """Step 3: the output grid: the camera's lenslet grid, or every lattice row and column on the sensor."""
    ny, nx = shape
    coef = lat.coef
    if camera is not None:
        ex, ey = expected_centers(camera)
        i0, j0 = camera.n_lenslets_y // 2, camera.n_lenslets_x // 2
        q0 = np.array([ex[i0, j0], ey[i0, j0]])
        nm0 = np.rint(np.linalg.solve(np.column_stack([coef[1], coef[2]]), q0 - coef[0])).astype(int)
        jj, ii = np.meshgrid(np.arange(camera.n_lenslets_x) - j0, np.arange(camera.n_lenslets_y) - i0)
        nf, mf = (jj + nm0[0]).ravel().astype(float), (ii + nm0[1]).ravel().astype(float)
        lc, lr = _predict(coef, nf, mf)
        return _Grid(nf, mf, (camera.n_lenslets_y, camera.n_lenslets_x), lc, lr)
    # lattice indices of the sensor corners, then the rows and columns with a spot on the sensor
    inv = np.linalg.inv(np.column_stack([coef[1], coef[2]]))
    corners = np.array([[-0.5, -0.5], [nx - 0.5, -0.5], [-0.5, ny - 0.5], [nx - 0.5, ny - 0.5]])
    lat_c = (corners - coef[0]) @ inv.T
    nn, mm = np.meshgrid(
        np.arange(int(np.floor(lat_c[:, 0].min())) - 1, int(np.ceil(lat_c[:, 0].max())) + 2),
        np.arange(int(np.floor(lat_c[:, 1].min())) - 1, int(np.ceil(lat_c[:, 1].max())) + 2),
    )
    nf, mf = nn.ravel().astype(float), mm.ravel().astype(float)
    lc, lr = _predict(coef, nf, mf)
    on = (lc >= -0.5) & (lc <= nx - 0.5) & (lr >= -0.5) & (lr <= ny - 0.5)
    rows_any = on.reshape(nn.shape).any(1)
    cols_any = on.reshape(nn.shape).any(0)
    keep = (rows_any[:, None] & cols_any[None, :]).ravel()
    return _Grid(nf[keep], mf[keep], (int(rows_any.sum()), int(cols_any.sum())), lc[keep], lr[keep])


def _start_points(
    ccx: np.ndarray, ccy: np.ndarray, lc: np.ndarray, lr: np.ndarray, h: float
) -> tuple[np.ndarray, np.ndarray]:
    """Starting centres of the fits: the centroid where it lies within ``h`` of the lattice
    position, else the lattice position (both coordinates from the same test)."""
    near = np.hypot(ccx - lc, ccy - lr) < h
    return np.where(near, ccx, lc), np.where(near, ccy, lr)


@dataclass
class _Spots:
    cx: np.ndarray
    cy: np.ndarray
    valid: np.ndarray
    amp: np.ndarray
    sx: np.ndarray
    sy: np.ndarray
    conv: np.ndarray
    resid: np.ndarray
    sig_med: float
    rms_g: float
    rms_c: float
    use_c: bool


def _refine_spots(
    img: np.ndarray, grid: _Grid, lat: _Lattice, n_iter: int, min_amplitude: float, estimator: str
) -> _Spots:
    """Step 4: sub-pixel centres: eq. 5.1 Gaussian fit and a ±2σ centroid; keep the estimator
    that scatters less about the lattice (flat-topped aperture-disk spots favour the centroid)."""
    lc, lr, h = grid.col, grid.row, lat.half_window
    pitch = float(0.5 * (np.hypot(*lat.coef[1]) + np.hypot(*lat.coef[2])))
    ccx, ccy, _, _ = _centroid(img, lc, lr, h, n_iter=1)
    ccx, ccy = _start_points(ccx, ccy, lc, lr, h)
    fx, fy, amp, sx, sy, conv, inside = _gauss_fit(img, ccx, ccy, h, lat.sigma, n_iter)
    med = np.median(amp[conv & inside]) if (conv & inside).any() else 0.0
    valid = conv & inside & (amp >= min_amplitude * med) & (np.hypot(fx - lc, fy - lr) < max(1.0, 0.2 * pitch))
    if valid.sum() < 0.5 * inside.sum() or valid.sum() < 4:
        raise CalibrationError(
            f"no lenslet grid detected: only {int(valid.sum())} of {int(inside.sum())} lattice "
            "points hold a spot that fits eq. 5.1"
        )
    # The centroid is nearly unbiased for flat-topped spots (the aperture disk of a ray-traced
    # or real pinhole image), where the Gaussian model of eq. 5.1 is biased by the sub-pixel
    # phase; the Gaussian fit is better for Gaussian spots in noise.
    sig_med = float(np.median(np.sqrt(sx * sy)[valid])) if valid.any() else lat.sigma
    hc = int(np.clip(np.ceil(2.0 * sig_med), 1, max(1, int(0.45 * pitch))))
    gx, gy, _, _ = _centroid(img, lc, lr, hc, n_iter=2)
    rms_g = float(np.sqrt(np.mean(((fx - lc) ** 2 + (fy - lr) ** 2)[valid])))
    okc = valid & np.isfinite(gx) & np.isfinite(gy)
    rms_c = float(np.sqrt(np.mean(((gx - lc) ** 2 + (gy - lr) ** 2)[okc]))) if okc.any() else np.inf
    use_c = estimator == "centroid" or (estimator == "auto" and rms_c < rms_g)
    if use_c:
        fx, fy, valid = np.where(okc, gx, lc), np.where(okc, gy, lr), okc
    resid = np.hypot(fx - lc, fy - lr)[valid]
    return _Spots(
        np.where(valid, fx, lc), np.where(valid, fy, lr), valid, amp, sx, sy, conv, resid, sig_med, rms_g, rms_c, use_c
    )


def _centers_dataset(
    shape_img: tuple[int, int],
    g: _Guess,
    lat: _Lattice,
    grid: _Grid,
    sp: _Spots,
    pixel_pitch: float | None,
    camera: PlenopticCamera | None,
) -> xr.Dataset:
    """Step 5: the labelled result."""
    ny, nx = shape_img
    shape = grid.shape
    a1, a2 = lat.coef[1], lat.coef[2]
    cx, cy = sp.cx.reshape(shape), sp.cy.reshape(shape)
    dims = ("lenslet_row", "lenslet_col")
    px = lambda ln: {"units": "px", "long_name": ln}  # noqa: E731
    data: dict[str, Any] = {
        "cx": (dims, cx, px("lenslet-image centre column (pixel centres at integers)")),
        "cy": (dims, cy, px("lenslet-image centre row (row 0 at the top)")),
        "valid": (dims, sp.valid.reshape(shape), {"units": "1", "long_name": "spot found and fitted"}),
        "amplitude": (
            dims,
            np.where(sp.conv, sp.amp, 0.0).reshape(shape),
            {"units": "counts", "long_name": "fitted spot amplitude c (eq. 5.1)"},
        ),
        "sigma_x": (dims, sp.sx.reshape(shape), px("fitted spot sigma_x (eq. 5.1)")),
        "sigma_y": (dims, sp.sy.reshape(shape), px("fitted spot sigma_y (eq. 5.1)")),
        "cx_lattice": (dims, grid.col.reshape(shape), px("affine-lattice column")),
        "cy_lattice": (dims, grid.row.reshape(shape), px("affine-lattice row")),
    }
    if pixel_pitch is not None:
        x, y = pixel_to_sensor(cx, cy, (ny, nx), pixel_pitch)
        data["x"] = (dims, x, {"units": "mm", "long_name": "lenslet-image centre x (sensor frame, eq. 5.2)"})
        data["y"] = (dims, y, {"units": "mm", "long_name": "lenslet-image centre y (sensor frame, y up, eq. 5.3)"})
    # Offset: the lattice point nearest the image centre, relative to it.
    ic = np.array([(nx - 1) / 2.0, (ny - 1) / 2.0])
    nm = np.rint(np.linalg.solve(np.column_stack([a1, a2]), ic - lat.coef[0]))
    onear = lat.coef[0] + nm[0] * a1 + nm[1] * a2 - ic
    attrs: dict[str, Any] = {
        "quantity": (
            "lenslet-image (spot) centres as measured: the lenslet centres projected from the "
            "main-lens centre onto the sensor, c*(si+fl)/si (bulk angle, eqs 5.4-5.5)"
        ),
        "pitch_px": float(0.5 * (np.hypot(*a1) + np.hypot(*a2))),
        "pitch_x_px": float(np.hypot(*a1)),
        "pitch_y_px": float(np.hypot(*a2)),
        "rotation": float(math.atan2(-a1[1], a1[0])),
        "rotation_units": "rad (sensor frame, counter-clockwise, y up)",
        "offset_x_px": float(onear[0]),
        "offset_y_px": float(-onear[1]),
        "spot_sigma_px": float(sp.sig_med),
        "estimator": "centroid" if sp.use_c else "gauss (eq. 5.1)",
        "rms_about_lattice_gauss_px": sp.rms_g,
        "rms_about_lattice_centroid_px": sp.rms_c,
        "window_half_width_px": int(lat.half_window),
        "lattice_rms_px": float(np.sqrt(np.mean(sp.resid**2))) if sp.resid.size else float("nan"),
        "n_valid": int(sp.valid.sum()),
        "grid_prominence": float(g.prominence),
        "image_rows": int(ny),
        "image_cols": int(nx),
        "y_direction": "lenslet_row 0 is the top row; y (mm) points up",
    }
    if pixel_pitch is not None:
        attrs["pixel_pitch"] = float(pixel_pitch)
    if camera is not None:
        attrs.update(camera.to_attrs())
    coords = {
        "lenslet_row": ("lenslet_row", np.arange(shape[0]), {"units": "1", "long_name": "lenslet row (0 at top)"}),
        "lenslet_col": ("lenslet_col", np.arange(shape[1]), {"units": "1", "long_name": "lenslet column"}),
    }
    return xr.Dataset(data, coords=coords, attrs=attrs)


def synthetic_pinhole(
    camera: PlenopticCamera,
    *,
    sigma_px: float = 0.8,
    amplitude: float = 1000.0,
    background: float = 20.0,
    read_noise: float = 5.0,
    dim_fraction: float = 0.0,
    seed: int = 0,
) -> xr.DataArray:
    """A quick pinhole image: pixel-integrated Gaussian spots at the projected centres.

    Spots sit at :func:`expected_centers` (``c·(si+fl)/si``); the image has
    Poisson shot noise plus Gaussian read noise. ``dim_fraction`` of the
    lenslets get 5-30 % of the amplitude (tests the dim-lenslet flag).
    A stand-in for :func:`lfstudy.simulate.raytrace.render_pinhole` in tests and benchmarks.
    """
    from scipy.special import erf

    rng = np.random.default_rng(seed)
    ny, nx = camera.n_pixels_y, camera.n_pixels_x
    cx, cy = (a.ravel() for a in expected_centers(camera))
    amp = np.full(cx.size, float(amplitude))
    if dim_fraction > 0:
        dim = rng.random(cx.size) < dim_fraction
        amp[dim] *= rng.uniform(0.05, 0.3, dim.sum())
    h = int(np.ceil(4 * sigma_px)) + 1
    off = np.arange(-h, h + 1)
    ic, ir = np.rint(cx).astype(int), np.rint(cy).astype(int)
    cols = ic[:, None] + off[None, :]
    rows = ir[:, None] + off[None, :]
    k = 1.0 / (math.sqrt(2) * sigma_px)
    wx = 0.5 * (erf((cols + 0.5 - cx[:, None]) * k) - erf((cols - 0.5 - cx[:, None]) * k))
    wy = 0.5 * (erf((rows + 0.5 - cy[:, None]) * k) - erf((rows - 0.5 - cy[:, None]) * k))
    w = amp[:, None, None] * wy[:, :, None] * wx[:, None, :]
    rr = np.broadcast_to(rows[:, :, None], w.shape)
    cc = np.broadcast_to(cols[:, None, :], w.shape)
    ok = (rr >= 0) & (rr < ny) & (cc >= 0) & (cc < nx)
    img = np.bincount((rr[ok] * nx + cc[ok]), weights=w[ok], minlength=ny * nx).reshape(ny, nx)
    img = rng.poisson(img + background).astype(np.float64) + rng.normal(0.0, read_noise, img.shape)
    x, y = camera.pixel_centers()
    return xr.DataArray(
        img,
        dims=("row", "col"),
        name="intensity",
        coords={
            "x": ("col", x, {"units": "mm", "long_name": "sensor x"}),
            "y": ("row", y, {"units": "mm", "long_name": "sensor y (up)"}),
        },
        attrs={
            "units": "counts",
            "long_name": "synthetic pinhole image",
            "seed": int(seed),
            "y_direction": "row 0 is the top (largest y)",
        },
    )
