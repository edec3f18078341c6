"""The camera's own particle images: IPR's image model calibrated from a recording's particles (issue 39 §2).

IPR fits a recording with the exact images of the *nominal* camera (:func:`lfstudy.reconstruct.ipr.particle_patches`).
A real camera departs from its drawing in ways no config describes; Shake-the-Box calibrates its optical transfer
function from the recording's own particles (Schanz et al. 2013, Meas. Sci. Technol. 24 024009). A tabulated
image cannot be used here (``benchmarks/bench_particle_table.py``: near focus the image jumps between lenslets over
~1 µm of particle motion, so a table within 1e-4 of the peak needs tens of GB to TB per design), so the calibration
is of the exact model's own parameters instead, the few through which an imperfect camera's images depart from the
nominal ones without moving the calibrated lenslet centres:

``gap_error`` [relative]
    The lenslet-to-sensor distance is ``fl·(1 + gap_error)``: the lenslet array defocused against the sensor
    (:mod:`lfstudy.simulate.imperfections` ``lenslet_gap_error``). The aperture images then change size with the
    particle's depth (radius ``R·|g·c1 + (1 − g/fl)·(1 + si·c1)|``), the very cue IPR reads depth from.
``blur_scale`` [1]
    The diffraction blurs σm (lenslet plane) and σl (sensor plane) times this: a stand-in for aberrations that
    widen every edge of the images.

Calibration (:func:`calibrate_image_model`): with the particles of a first IPR pass held at their positions and
intensities, the cost of a model θ is the residual's ‖data − k·Σ I_p·U_p(θ)‖² at the best common factor k of the
intensities (without it a blur scale would stand in for intensities that are all a little off; the images of at most
``_PARTICLES`` particles moved to θ, the others held); θ is found by coordinate descent, a parabola through three
costs per parameter and round, the steps halved each round; the intensities are then refitted under θ (one
Gauss–Seidel pass, the IPR fit's own intensity step). It is kept only where the cost falls by more than ``_ACCEPT``
times the residual variance per pixel σ² (two parameters fitted to the noise lower ‖R‖² by ~2σ²). The positions are
then shaken again with the calibrated images (IPR alternates: a calibration after some iterations, the rest with
it).

What it changed is reported per depth (:func:`model_change`): the calibrated image of a particle on the axis
against the nominal one at depths over the grid (largest difference as a fraction of the nominal peak, and the
ratio of the peaks).

Examples
--------
>>> from lfstudy.reconstruct.image_model import ImageModel
>>> ImageModel().ideal
True
>>> ImageModel(gap_error=0.02).gap_mm(0.5)
0.51

References
----------
Schanz, D., Gesemann, S., Schröder, A., Wieneke, B. & Novara, M. 2013, "Non-uniform optical transfer functions in
particle imaging: calibration and application to tomographic reconstruction", Meas. Sci. Technol. 24 024009.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct.registry import ReconstructionError

__all__ = ["ImageModel", "calibrate_image_model", "model_change"]

#: Search bounds of the calibration: gap_error (a gap within ±10 % of fl) and blur_scale (a quarter to 4 times)
_GAP_RANGE = (-0.1, 0.1)
_BLUR_RANGE = (0.25, 4.0)
#: First steps of the coordinate descent: gap_error, ln(blur_scale); halved each round
_STEPS = (0.01, 0.2)
_ROUNDS = 6
#: A calibrated model is kept only where ‖R‖² falls by more than this many σ² (residual variance per pixel)
_ACCEPT = 25.0
#: The search moves at most this many particles' images (a full frame holds ~100,000; a crop a few hundred)
_PARTICLES = 2000
#: The aperture image must stay this many pixels wide at every depth of the grid (β = 0: the lenslets image the
#: aperture onto a point, which the exact renderer refuses)
_MIN_DISC_PX = 1.0


@dataclass(frozen=True)
class ImageModel:
    """Departures of the particle images from the nominal camera's (module docstring).

    Parameters
    ----------
    gap_error : float
        Relative error of the lenslet-to-sensor distance (0: the lenslet focal length).
    blur_scale : float
        Factor on both diffraction blurs (1: the camera's).
    """

    gap_error: float = 0.0
    blur_scale: float = 1.0

    def __post_init__(self) -> None:
        lo, hi = _GAP_RANGE
        ok = isinstance(self.gap_error, (int, float)) and math.isfinite(self.gap_error)
        if not (ok and lo <= self.gap_error <= hi):
            raise ReconstructionError(f"image model gap_error = {self.gap_error!r}: allowed range is [{lo}, {hi}]")
        lo, hi = _BLUR_RANGE
        ok = isinstance(self.blur_scale, (int, float)) and math.isfinite(self.blur_scale)
        if not (ok and lo <= self.blur_scale <= hi):
            raise ReconstructionError(f"image model blur_scale = {self.blur_scale!r}: allowed range is [{lo}, {hi}]")

    @property
    def ideal(self) -> bool:
        """The nominal camera's images (no departure)."""
        return self.gap_error == 0.0 and self.blur_scale == 1.0

    def gap_mm(self, fl: float) -> float:
        """Lenslet-to-sensor distance [mm] for lenslet focal length ``fl`` [mm]."""
        return fl if self.gap_error == 0.0 else fl * (1.0 + self.gap_error)

    def gap(self, camera: PlenopticCamera) -> float:
        """Lenslet-to-sensor distance [mm] of ``camera``."""
        return self.gap_mm(camera.lenslet_focal_length)

    def renders(self, camera: PlenopticCamera, z_range: tuple[float, float]) -> bool:
        """Whether the exact renderer can image every depth in ``z_range`` [mm] with this gap: the aperture
        images keep at least ``_MIN_DISC_PX`` pixels of diameter (they vanish where β = 0)."""
        g, fl = self.gap(camera), camera.lenslet_focal_length
        z = np.linspace(z_range[0], z_range[1], 257)
        c1 = 1.0 / (camera.so + z) - 1.0 / camera.main_focal_length
        beta = g * c1 + (1.0 - g / fl) * (1.0 + camera.si * c1)
        if np.any(np.sign(beta) != np.sign(beta[0])):
            return False
        return bool(camera.aperture_diameter * np.abs(beta).min() >= _MIN_DISC_PX * camera.pixel_pitch)

    def to_attrs(self) -> dict[str, float]:
        return {"image_gap_error": float(self.gap_error), "image_blur_scale": float(self.blur_scale)}


def _cost(
    render: Callable[..., Any],
    data: np.ndarray,
    mask: np.ndarray,
    xyz: np.ndarray,
    inten: np.ndarray,
    model: ImageModel,
    batch: int,
) -> tuple[float, np.ndarray, np.ndarray]:
    """‖R‖² of ``model`` after one Gauss–Seidel pass over the intensities (starting from ``inten``), with that
    residual R and the refitted intensities."""
    from lfstudy.reconstruct._shake_kernels import _accumulate_masked, refit_intensities

    res = data.copy()
    for s in range(0, len(xyz), batch):  # subtract every particle first: the pass then sees its neighbours
        buf, offs, r0, c0, shp = render(xyz[s : s + batch], model=model)
        _accumulate_masked(res, mask, buf, offs, r0, c0, shp, inten[s : s + batch] * 1.0, -1.0)
    out = np.zeros((len(xyz), 2))
    for s in range(0, len(xyz), batch):
        sl = slice(s, s + batch)
        buf, offs, r0, c0, shp = render(xyz[sl], model=model)
        refit_intensities(res, mask, buf, offs, r0, c0, shp, inten[sl] * 1.0, out[sl])
    return float(np.sum(res * res)), res, out[:, 1]


def calibrate_image_model(
    render: Callable[..., Any],
    data: np.ndarray,
    res: np.ndarray,
    mask: np.ndarray,
    xyz: np.ndarray,
    inten: np.ndarray,
    camera: PlenopticCamera,
    z_range: tuple[float, float],
    start: ImageModel | None = None,
    *,
    batch: int = 256,
) -> tuple[ImageModel, np.ndarray, np.ndarray, dict[str, Any]]:
    """The image model that fits the recording's particles best (module docstring).

    Parameters
    ----------
    render : callable
        ``render(pos, model=...)`` -> the unit images of the particles at ``pos`` in their patches
        (:func:`lfstudy.reconstruct.ipr.particle_patches`' tuple).
    data, res, mask : ndarray (rows, cols)
        The recording on the sensor (background subtracted), its residual under ``start``
        (``data − Σ inten·U(start)``) and the pixels the light field holds.
    xyz, inten : ndarray
        The particles of a first fit (positions [mm], intensities), held fixed.
    camera : PlenopticCamera
        The model camera (:func:`lfstudy.reconstruct.ipr.calibrated_camera`).
    z_range : (float, float)
        The grid's depths [mm]: a gap whose aperture images vanish there is not tried.
    start : ImageModel, optional
        Where the search starts (default: the nominal images).
    batch : int
        Particles rendered at once.

    Returns
    -------
    model : ImageModel
        The calibrated model (``start`` where no model lowers ‖R‖² by more than ``_ACCEPT``·σ²).
    residual, intensities : ndarray
        Under ``model``: the exact residual with every intensity refitted (one Gauss–Seidel pass); ``res`` and
        ``inten`` themselves where ``start`` is kept.
    info : dict
        ``image_calibration_cost`` (‖R‖² under ``start`` and under the model, the intensities held up to a common
        factor, relative to ‖data‖²), ``image_calibration_evaluations``, ``image_calibration_particles`` (those
        the search used) and ``image_calibration_accepted``.

    The search moves the images of at most ``_PARTICLES`` particles (evenly spread over the list; the others
    stay in ``res`` with their ``start`` images): each trial model costs one image per particle used.
    """
    from lfstudy.reconstruct._shake_kernels import _accumulate_masked

    start = start or ImageModel()
    xyz = np.asarray(xyz, dtype=np.float64)
    inten = np.asarray(inten, dtype=np.float64)
    norm = float(np.sum(data * data)) or 1.0
    use = np.unique(np.linspace(0, len(xyz) - 1, min(len(xyz), _PARTICLES)).round().astype(np.int64))
    if not len(xyz):
        use = use[:0]
    pos, amp = xyz[use], inten[use]
    base = res.copy()  # the residual with the particles used taken out (their start images added back)
    for s in range(0, len(use), batch):
        buf, offs, r0, c0, shp = render(pos[s : s + batch], model=start)
        _accumulate_masked(base, mask, buf, offs, r0, c0, shp, amp[s : s + batch] * 1.0, 1.0)
    cache: dict[tuple[float, float], float] = {}

    def cost(p: np.ndarray) -> float:
        key = (round(float(p[0]), 12), round(float(p[1]), 12))
        if key not in cache:
            m = ImageModel(gap_error=key[0], blur_scale=math.exp(key[1]))
            if not m.renders(camera, z_range):
                cache[key] = math.inf
            else:  # ‖base − k·M‖² at the best common factor k of the intensities (M = Σ I·U(m))
                mod = np.zeros_like(base)
                for s in range(0, len(use), batch):
                    buf, offs, r0, c0, shp = render(pos[s : s + batch], model=m)
                    _accumulate_masked(mod, mask, buf, offs, r0, c0, shp, amp[s : s + batch] * 1.0, 1.0)
                bm, mm = float(np.sum(base * mod)), float(np.sum(mod * mod))
                cache[key] = float(np.sum(base * base)) - (bm * bm / mm if mm > 0.0 else 0.0)
        return cache[key]

    lo = np.array([_GAP_RANGE[0], math.log(_BLUR_RANGE[0])])
    hi = np.array([_GAP_RANGE[1], math.log(_BLUR_RANGE[1])])
    p0 = np.array([start.gap_error, math.log(start.blur_scale)])
    p = p0.copy()
    step = np.array(_STEPS, dtype=np.float64)
    for _ in range(_ROUNDS):
        for j in range(2):
            f0 = cost(p)
            pm, pp_ = p.copy(), p.copy()
            pm[j] = max(p[j] - step[j], lo[j])
            pp_[j] = min(p[j] + step[j], hi[j])
            fm, fp = cost(pm), cost(pp_)
            trial = [(f0, p.copy()), (fm, pm), (fp, pp_)]
            # the parabola's vertex through the three (equal spacing where not clipped)
            den = fm - 2.0 * f0 + fp
            if math.isfinite(den) and den > 0.0 and pm[j] < p[j] < pp_[j]:
                v = p.copy()
                v[j] = float(np.clip(p[j] + 0.5 * step[j] * (fm - fp) / den, p[j] - 2 * step[j], p[j] + 2 * step[j]))
                v[j] = float(np.clip(v[j], lo[j], hi[j]))
                trial.append((cost(v), v))
            p = min(trial, key=lambda t: t[0])[1]
        step /= 2.0
    f_start, f_best = cost(p0), cost(p)
    s2 = f_start / max(float(np.count_nonzero(mask)), 1.0)
    accepted = bool(f_best < f_start - _ACCEPT * s2)
    info = {
        "image_calibration_cost": [f_start / norm, f_best / norm],
        "image_calibration_evaluations": len(cache),
        "image_calibration_particles": len(use),
        "image_calibration_accepted": accepted,
    }
    if not accepted:
        return start, res, inten, info
    model = ImageModel(gap_error=round(float(p[0]), 12), blur_scale=math.exp(round(float(p[1]), 12)))
    _, res_new, amp_new = _cost(render, data, mask, xyz, inten, model, batch)
    return model, res_new, amp_new, info


def model_change(
    camera: PlenopticCamera, model: ImageModel, z: np.ndarray, render: Callable[..., Any]
) -> dict[str, list[float]]:
    """What a calibrated model changed, per depth: the image of a particle on the optical axis at each ``z``
    [mm] under ``model`` against the nominal one (``render(pos, model=...)`` as for
    :func:`calibrate_image_model`; each in its own patch, compared on the union of the two).

    Returns ``image_change_z`` (the depths), ``image_change_max`` (largest |calibrated − nominal| as a fraction
    of the nominal peak) and ``image_change_peak`` (calibrated peak / nominal peak).
    """
    z = np.asarray(z, dtype=np.float64)
    pos = np.column_stack([np.zeros(z.size), np.zeros(z.size), z])
    a = render(pos, model=ImageModel())
    b = render(pos, model=model)
    mx, pk = [], []
    for i in range(z.size):
        ua = _embed(a, i)
        ub = _embed(b, i)
        r0, c0 = min(ua[0], ub[0]), min(ua[1], ub[1])
        r1 = max(ua[0] + ua[2].shape[0], ub[0] + ub[2].shape[0])
        c1 = max(ua[1] + ua[2].shape[1], ub[1] + ub[2].shape[1])
        ca, cb = np.zeros((r1 - r0, c1 - c0)), np.zeros((r1 - r0, c1 - c0))
        for can, (r, c, u) in ((ca, ua), (cb, ub)):
            can[r - r0 : r - r0 + u.shape[0], c - c0 : c - c0 + u.shape[1]] = u
        peak = float(ca.max()) or 1.0
        mx.append(float(np.abs(cb - ca).max() / peak))
        pk.append(float(cb.max() / peak))
    return {"image_change_z": [float(v) for v in z], "image_change_max": mx, "image_change_peak": pk}


def _embed(patches: tuple[np.ndarray, ...], i: int) -> tuple[int, int, np.ndarray]:
    buf, offs, r0, c0, shp = patches
    h, w = int(shp[i, 0]), int(shp[i, 1])
    return int(r0[i]), int(c0[i]), buf[offs[i] : offs[i] + h * w].reshape(h, w)
