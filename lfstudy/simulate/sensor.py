"""A physical image sensor on top of a rendered (expected or Monte-Carlo) raw image.

The renderers of :mod:`lfstudy.simulate` produce the expected number of
rays of a particle that land on each pixel; here that signal becomes what a
camera records. For every pixel, in this order:

1. **photons**: the image scaled so that a particle of intensity 1 at the
   reference solid angle (eq. 4.14) delivers ``photons_per_particle`` photons
   in total (``photons = image · photons_per_particle / rays_per_particle``),
   plus the expected ``background`` light [photons/pixel] (a constant, or an
   image such as :func:`lenslet_background`: stray light through the lenslets);
2. **photo-electrons**: ``quantum_efficiency · photons`` expected, drawn from
   a Poisson distribution when ``shot_noise`` is on (photon shot noise; the
   quantum efficiency thins the photon stream, so the electrons are Poisson too);
3. **dark level**: a constant pedestal of ``dark_level`` electrons (the dark
   signal and black level of the pixel; it occupies the well, it is noise-free
   here: add its shot noise through ``read_noise`` if wanted), and on the hot
   pixels (:func:`hot_pixel_mask`: a seeded fraction of the pixels, the same in
   every image of one sensor) ``hot_pixel_level`` electrons more;
4. **full well**: the well holds at most ``full_well`` electrons (saturation);
5. **read noise**: additive Gaussian noise of ``read_noise`` electrons rms;
6. **ADC**: with ``bit_depth``, counts = round(electrons / gain), clipped to
   [0, 2**bit_depth − 1], with ``gain`` in electrons per count (default: the
   full well maps to the top count, or 1 e⁻/count without a full well).

Without ``bit_depth`` the result stays in electrons (float64, not clipped at
zero, so the read noise stays unbiased). The variance of a pixel before the
ADC is ``quantum_efficiency · photons + read_noise²`` (Poisson + Gaussian); the
tests check it. Random numbers come from ``numpy.random.default_rng(seed)``
(Poisson first, then normal, whole image at once), so one seed gives one image;
the hot pixels' positions come from their own seed. With no background and no
hot pixels (the defaults) the image is the ideal photon counter's, bit for bit.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import xarray as xr

__all__ = ["SensorError", "apply_sensor", "sensor_noise_variance", "hot_pixel_mask", "lenslet_background"]


class SensorError(ValueError):
    """Bad sensor-model input (the message names the field and its allowed range)."""


def _number(name: str, value: Any, *, low: float | None = None, low_open: bool = False) -> float:
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    v = float(value) if ok else math.nan
    if not (ok and math.isfinite(v)) or (low is not None and (v <= low if low_open else v < low)):
        rng = "a finite number" if low is None else f"a finite number {'>' if low_open else '>='} {low:g}"
        raise SensorError(f"{name} = {value!r}: must be {rng}")
    return v


def _check(
    photons_per_particle: Any,
    quantum_efficiency: Any,
    shot_noise: Any,
    read_noise: Any,
    dark_level: Any,
    full_well: Any,
    bit_depth: Any,
    gain: Any,
    seed: Any,
) -> dict[str, Any]:
    out: dict[str, Any] = {
        "photons_per_particle": _number("photons_per_particle", photons_per_particle, low=0.0),
        "read_noise": _number("read_noise", read_noise, low=0.0),
        "dark_level": _number("dark_level", dark_level, low=0.0),
    }
    qe = _number("quantum_efficiency", quantum_efficiency, low=0.0, low_open=True)
    if qe > 1.0:
        raise SensorError(f"quantum_efficiency = {quantum_efficiency!r}: allowed range is (0, 1]")
    out["quantum_efficiency"] = qe
    if not isinstance(shot_noise, (bool, np.bool_)):
        raise SensorError(f"shot_noise = {shot_noise!r}: must be true or false")
    out["shot_noise"] = bool(shot_noise)
    if full_well is not None:
        fw = _number("full_well", full_well, low=0.0, low_open=True)
        if fw <= out["dark_level"]:
            raise SensorError(
                f"full_well = {full_well!r} e-: must exceed dark_level = {out['dark_level']:g} e- "
                "(the pedestal would fill the well)"
            )
        full_well = fw
    out["full_well"] = full_well
    if bit_depth is not None and (
        isinstance(bit_depth, bool) or not isinstance(bit_depth, (int, np.integer)) or not 1 <= bit_depth <= 32
    ):
        raise SensorError(f"bit_depth = {bit_depth!r}: allowed range is the integers 1..32 (or none)")
    out["bit_depth"] = None if bit_depth is None else int(bit_depth)
    out["gain"] = None if gain is None else _number("gain", gain, low=0.0, low_open=True)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SensorError(f"seed = {seed!r}: must be an integer >= 0")
    out["seed"] = int(seed)
    return out


def _background(background: Any, shape: tuple[int, ...]) -> np.ndarray | float | None:
    """The checked background [photons/pixel]: None when it is 0 everywhere."""
    if isinstance(background, (np.ndarray, xr.DataArray)):
        bg = np.asarray(background, dtype=np.float64)
        if bg.shape != shape:
            raise SensorError(f"background: shape {bg.shape} differs from the image's {shape}")
        if not np.all(np.isfinite(bg)) or np.any(bg < 0):
            raise SensorError("background: must be finite and >= 0 photons/pixel")
        return bg if np.any(bg > 0) else None
    v = _number("background", background, low=0.0)
    return v if v > 0 else None


def sensor_noise_variance(expected_photons: np.ndarray | float, quantum_efficiency: float, read_noise: float) -> Any:
    """Variance [e⁻²] of a pixel before saturation and the ADC: Poisson (QE·photons) + read noise²."""
    return quantum_efficiency * np.asarray(expected_photons, dtype=np.float64) + read_noise**2


def hot_pixel_mask(shape: tuple[int, int], fraction: float, seed: int) -> np.ndarray:
    """The hot pixels of a sensor: ``round(fraction · pixels)`` distinct pixels drawn by ``seed``.

    Parameters
    ----------
    shape : (int, int)
        The image shape (rows, cols).
    fraction : float
        Fraction of hot pixels, in [0, 1].
    seed : int
        Seed of ``numpy.random.default_rng`` (>= 0): one seed, one set of positions, so a
        sensor's frames (and its calibration image) share them.

    Returns
    -------
    numpy.ndarray of bool, ``shape``
    """
    f = _number("hot_pixels.fraction", fraction, low=0.0)
    if f > 1.0:
        raise SensorError(f"hot_pixels.fraction = {fraction!r}: allowed range is [0, 1]")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SensorError(f"hot_pixels.seed = {seed!r}: must be an integer >= 0")
    mask = np.zeros(shape, dtype=bool)
    count = round(f * mask.size)
    if count:
        mask.flat[np.random.default_rng(int(seed)).choice(mask.size, size=count, replace=False)] = True
    return mask


def lenslet_background(white: xr.DataArray | np.ndarray) -> np.ndarray:
    """A lenslet-structured background of mean 1 per pixel: a white image divided by its mean.

    ``white`` is the expected image of a uniform field at the image's f-number (e.g.
    :func:`lfstudy.simulate.render_pinhole` at the working f-number, exact: every
    lenslet's image of the main-lens aperture, the gaps between them dark). Times a level
    [photons/pixel], it is the ``background`` of :func:`apply_sensor`: diffuse stray light
    reaching the sensor through the main lens and the lenslets.
    """
    w = np.asarray(getattr(white, "values", white), dtype=np.float64)
    mean = float(w.mean()) if w.size else 0.0
    if not (np.all(np.isfinite(w)) and np.all(w >= 0) and mean > 0):
        raise SensorError("lenslet background: the white image must be finite, >= 0 and not all zero")
    return w / mean


def apply_sensor(
    image: xr.DataArray,
    *,
    photons_per_particle: float,
    quantum_efficiency: float = 1.0,
    shot_noise: bool = True,
    read_noise: float = 0.0,
    dark_level: float = 0.0,
    full_well: float | None = None,
    bit_depth: int | None = None,
    gain: float | None = None,
    seed: int = 0,
    rays_per_particle: int | None = None,
    background: float | np.ndarray = 0.0,
    hot_pixel_fraction: float = 0.0,
    hot_pixel_level: float = 0.0,
    hot_pixel_seed: int = 0,
) -> xr.DataArray:
    """Record a rendered raw image with a physical sensor (photons → electrons → counts).

    Parameters
    ----------
    image : xarray.DataArray
        A raw image from :func:`lfstudy.simulate.exact.render_exact` (expected,
        noise-free) or :func:`lfstudy.simulate.raytrace.render` (Monte-Carlo),
        non-negative, with ``attrs['rays_per_particle']``.
    photons_per_particle : float
        Photons a particle of intensity 1 at the reference solid angle delivers
        (>= 0; eq. 4.14 scales it with each particle's solid angle, as the rays).
    quantum_efficiency : float
        Fraction of photons converted to electrons, in (0, 1].
    shot_noise : bool
        Draw the electrons from a Poisson distribution (photon shot noise).
    read_noise : float
        Gaussian read noise [e⁻ rms], >= 0.
    dark_level : float
        Constant pedestal [e⁻] (dark signal and black level; noise-free), >= 0.
    full_well : float, optional
        Well capacity [e⁻]; must exceed ``dark_level``. None: no saturation.
    bit_depth : int, optional
        ADC resolution, 1..32 bits: the result is unsigned counts. None: float electrons.
    gain : float, optional
        Electrons per count (> 0). Default: ``full_well / (2**bit_depth − 1)``,
        or 1 without a full well.
    seed : int
        Seed of ``numpy.random.default_rng`` (>= 0).
    rays_per_particle : int, optional
        Overrides ``image.attrs['rays_per_particle']``.
    background : float or numpy.ndarray
        Expected background light [photons/pixel], >= 0: a constant or an image of the
        image's shape (e.g. ``level · lenslet_background(white)``), added to the photons
        before the quantum efficiency and the shot noise. 0: none.
    hot_pixel_fraction, hot_pixel_level, hot_pixel_seed : float, float, int
        Hot pixels (:func:`hot_pixel_mask`): the fraction of pixels in [0, 1] that get
        ``hot_pixel_level`` [e⁻, >= 0] on top of the dark level (before the full well, so they
        may saturate), at positions drawn by ``hot_pixel_seed`` (not ``seed``: one sensor's
        hot pixels stay put from image to image). Fraction or level 0: none.

    Returns
    -------
    xarray.DataArray
        The recorded image (same coords; ``units`` "counts" or "e-"), with attrs
        recording every setting, ``photons_per_unit_intensity`` (the scale of
        step 1), ``gain`` (with an ADC) and the saturated pixels (count and
        fraction: electrons at the full well or counts at the top of the ADC).
    """
    p = _check(
        photons_per_particle, quantum_efficiency, shot_noise, read_noise, dark_level, full_well, bit_depth, gain, seed
    )
    if not isinstance(image, xr.DataArray) or image.ndim != 2:
        raise SensorError("image: must be a 2-D xarray.DataArray (row, col)")
    n = rays_per_particle if rays_per_particle is not None else image.attrs.get("rays_per_particle")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise SensorError(
            f"rays_per_particle = {n!r}: must be an integer >= 1 (give it, or render the image with "
            "lfstudy.simulate, which records it in the attributes)"
        )
    signal = np.asarray(image.values, dtype=np.float64)
    if not np.all(np.isfinite(signal)) or np.any(signal < 0):
        raise SensorError("image: values must be finite and >= 0 (an expected or ray-traced intensity image)")
    bg = _background(background, signal.shape)
    level = _number("hot_pixels.level", hot_pixel_level, low=0.0)
    hot = hot_pixel_mask(signal.shape, hot_pixel_fraction, hot_pixel_seed)  # checked even when unused
    hot = hot if level > 0 and hot.any() else None
    scale = p["photons_per_particle"] / int(n)
    electrons = p["quantum_efficiency"] * scale * signal  # expected photo-electrons
    if bg is not None:  # (skipped when off: the ideal image stays bit-identical)
        electrons += p["quantum_efficiency"] * bg
    rng = np.random.default_rng(p["seed"])
    if p["shot_noise"]:
        electrons = rng.poisson(electrons).astype(np.float64)
    electrons += p["dark_level"]
    if hot is not None:
        electrons[hot] += level
    saturated = np.zeros(signal.shape, dtype=bool)
    if p["full_well"] is not None:
        saturated = electrons >= p["full_well"]
        np.minimum(electrons, p["full_well"], out=electrons)
    if p["read_noise"] > 0:
        electrons += rng.normal(0.0, p["read_noise"], signal.shape)
    attrs = dict(image.attrs)
    attrs.update(
        sensor_photons_per_particle=p["photons_per_particle"],
        sensor_quantum_efficiency=p["quantum_efficiency"],
        sensor_shot_noise=int(p["shot_noise"]),
        sensor_read_noise=p["read_noise"],
        sensor_dark_level=p["dark_level"],
        sensor_full_well=-1.0 if p["full_well"] is None else p["full_well"],
        sensor_bit_depth=0 if p["bit_depth"] is None else p["bit_depth"],
        sensor_seed=p["seed"],
        photons_per_unit_intensity=scale,
        long_name="recorded plenoptic raw image",
    )
    if bg is not None:
        attrs.update(sensor_background_mean=float(np.mean(bg)))
    if hot is not None:
        attrs.update(
            sensor_hot_pixels=int(hot.sum()), sensor_hot_pixel_level=level, sensor_hot_pixel_seed=int(hot_pixel_seed)
        )
    if p["bit_depth"] is None:
        attrs.update(units="e-", saturated_pixels=int(saturated.sum()), saturated_fraction=float(saturated.mean()))
        return image.copy(data=electrons).assign_attrs(attrs)
    top = float(2 ** p["bit_depth"] - 1)
    g = p["gain"] if p["gain"] is not None else (p["full_well"] / top if p["full_well"] is not None else 1.0)
    counts = np.clip(np.rint(electrons / g), 0.0, top)
    saturated |= counts >= top
    dtype = np.uint8 if p["bit_depth"] <= 8 else np.uint16 if p["bit_depth"] <= 16 else np.uint32
    attrs.update(
        units="counts",
        sensor_gain=g,
        saturated_pixels=int(saturated.sum()),
        saturated_fraction=float(saturated.mean()),
    )
    return image.copy(data=counts.astype(dtype)).assign_attrs(attrs)
