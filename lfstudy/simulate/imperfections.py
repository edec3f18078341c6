"""Camera imperfections that only the imaging sees (issue 29 §1): the ``camera.imperfections`` section.

A real plenoptic camera is never the ideal one its processing assumes. The settings here
change how the renderers (:func:`lfstudy.simulate.exact.render_exact`, the Monte-Carlo
tracer :func:`lfstudy.simulate.raytrace.render` and the pinhole image
:func:`lfstudy.simulate.raytrace.render_pinhole`) form the raw image; the processing keeps
the nominal camera of the ``camera`` section, as in an experiment. Every setting defaults
to the ideal value, and a camera with every setting ideal renders bit-identically to one
without the section.

Lenslet array
-------------
``lenslet_rotation`` [mrad]
    Rotation of the lenslet grid about the optical axis, added to ``camera.lenslet.rotation``.
``lenslet_offset_x``, ``lenslet_offset_y`` [fraction of the pitch]
    Shift of the grid, added to ``camera.lenslet.offset_x/y``.
``lenslet_pitch_error`` [relative]
    The array's pitch is ``pitch·(1 + e)`` (the grid still covers the sensor; the main-lens
    aperture stays the nominal one).
``lenslet_gap_error`` [relative]
    The lenslet-to-sensor distance is ``g = fl·(1 + e)`` instead of the lenslet focal length
    ``fl``. Behind a thin lenslet (eq. 4.4) a ray that meets the lenslet plane at ``L`` with
    slope ``t`` lands at ``s = L + g·(t − (L − c)/fl) = c·g/fl + g·t + (1 − g/fl)·L``: with
    ``g = fl`` the image of the aperture (``c + fl·t``), otherwise a slightly defocused one
    whose size and centre now depend on the particle's depth (it changes the refocusing).
    The lenslet-plane diffraction shift (σm) chooses the lenslet only, as in the ideal model.
``lenslet_scatter`` [fraction of the pitch, rms per axis]
    Each lenslet's optical centre is displaced by an independent Gaussian (x, y) offset; the
    lenslet's cell (which rays it takes) stays on the regular grid. Drawn from
    ``numpy.random.default_rng(scatter_seed)`` in the row-major order of the lenslet grid;
    a study derives ``scatter_seed`` from its config seed.

Main lens and sensor mount
--------------------------
``distortion_k1``, ``distortion_k2`` [1]
    Radial distortion of the main lens: the image of a particle whose chief ray meets the
    nominal lenslet plane at radius ``r`` (the ideal image point, ``si·|t0|``) moves to
    ``r·(1 + k1·ρ² + k2·ρ⁴)``, ``ρ = r/h`` with ``h`` the sensor half-diagonal (Brown's radial
    model, Brown 1966 "Decentering distortion of lenses"). A field corner (ρ = 1) of an
    in-focus particle moves by ``(k1 + k2)·h``. It is a function of the chief ray's angle only,
    so it is applied by scaling the particle's lateral position at its depth (the whole light
    cone turns with its chief ray); the collected solid angle stays that of the true position.
``sensor_tilt_x``, ``sensor_tilt_y`` [mrad]
    Tilt of the lenslet array and sensor (one rigid body) against the main lens: about the
    sensor x axis (positive: the top edge, +y, further from the lens) and y axis (positive:
    the +x edge further). The lenslet plane then lies at ``si + θy·x + θx·y``; each particle's
    light cone meets it at the distance of its chief ray's point (the plane is flat across one
    particle's few lenslets: the error is the tilt times the spot radius), and the rays' slopes
    in the tilted frame gain (θy, θx).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from lfstudy.optics import PlenopticCamera
from lfstudy.simulate._render_common import RaytraceError

__all__ = ["CameraImperfections", "ImperfectionError", "RANGES", "resolve"]


class ImperfectionError(RaytraceError):
    """A camera imperfection outside its allowed range (the message names the config field)."""


#: Allowed range of each setting (inclusive), as in the config schema ``camera.imperfections``.
RANGES: dict[str, tuple[float, float]] = {
    "lenslet_rotation": (-20.0, 20.0),
    "lenslet_offset_x": (-0.5, 0.5),
    "lenslet_offset_y": (-0.5, 0.5),
    "lenslet_pitch_error": (-0.05, 0.05),
    "lenslet_gap_error": (-0.2, 0.2),
    "lenslet_scatter": (0.0, 0.1),
    "distortion_k1": (-0.2, 0.2),
    "distortion_k2": (-0.2, 0.2),
    "sensor_tilt_x": (-20.0, 20.0),
    "sensor_tilt_y": (-20.0, 20.0),
}


@dataclass(frozen=True)
class CameraImperfections:
    """The ``camera.imperfections`` settings (units in the module docstring); all ideal by default."""

    lenslet_rotation: float = 0.0
    lenslet_offset_x: float = 0.0
    lenslet_offset_y: float = 0.0
    lenslet_pitch_error: float = 0.0
    lenslet_gap_error: float = 0.0
    lenslet_scatter: float = 0.0
    distortion_k1: float = 0.0
    distortion_k2: float = 0.0
    sensor_tilt_x: float = 0.0
    sensor_tilt_y: float = 0.0
    scatter_seed: int = 0

    def __post_init__(self) -> None:
        for name, (lo, hi) in RANGES.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
                raise ImperfectionError(f"camera.imperfections.{name} = {v!r}: must be a finite number in [{lo}, {hi}]")
            if not lo <= v <= hi:
                raise ImperfectionError(f"camera.imperfections.{name} = {v!r}: allowed range is [{lo}, {hi}]")
            object.__setattr__(self, name, float(v))
        s = self.scatter_seed
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 0 <= s < 2**63:
            raise ImperfectionError(f"camera.imperfections scatter_seed = {s!r}: must be an integer in [0, 2**63)")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None, *, scatter_seed: int = 0) -> CameraImperfections:
        """From a config's ``camera.imperfections`` section (or the section itself, or the whole config).

        Missing keys are ideal; unknown keys are refused with their name.
        """
        if cfg is None:
            return cls(scatter_seed=scatter_seed)
        sec: Any = cfg
        if "camera" in sec:
            sec = sec["camera"]
        if "sensor" in sec and "lenslet" in sec:  # a camera section
            sec = sec.get("imperfections") or {}
        known = {f.name for f in fields(cls)} - {"scatter_seed"}
        bad = sorted(set(sec) - known)
        if bad:
            raise ImperfectionError(
                f"camera.imperfections: unknown key(s) {', '.join(bad)}; allowed: {', '.join(sorted(known))}"
            )
        return cls(**{k: sec[k] for k in sec}, scatter_seed=int(scatter_seed))

    # ------------------------------------------------------------------ groups
    @property
    def ideal(self) -> bool:
        """Every setting at its ideal value (the seed does not matter then)."""
        return all(getattr(self, n) == 0.0 for n in RANGES)

    @property
    def distorted(self) -> bool:
        """Whether the main lens has radial distortion."""
        return self.distortion_k1 != 0.0 or self.distortion_k2 != 0.0

    def to_attrs(self) -> dict[str, Any]:
        """Flat attributes for an image's metadata (``imperfection_*``)."""
        return {f"imperfection_{k}": v for k, v in asdict(self).items()}

    # ------------------------------------------------------------------ geometry
    def imaging_camera(self, camera: PlenopticCamera) -> PlenopticCamera:
        """The camera the light actually meets: ``camera`` with the lenslet grid's rotation, offset
        and pitch errors applied (the main-lens f-number pinned to the nominal one)."""
        grid = ("lenslet_rotation", "lenslet_offset_x", "lenslet_offset_y", "lenslet_pitch_error")
        if all(getattr(self, k) == 0.0 for k in grid):
            return camera
        pl = camera.lenslet_pitch
        changes: dict[str, Any] = {
            "lenslet_rotation": camera.lenslet_rotation + self.lenslet_rotation * 1e-3,
            "lenslet_offset_x": camera.lenslet_offset_x + self.lenslet_offset_x * pl,
            "lenslet_offset_y": camera.lenslet_offset_y + self.lenslet_offset_y * pl,
        }
        if self.lenslet_pitch_error != 0.0:
            changes.update(lenslet_pitch=pl * (1.0 + self.lenslet_pitch_error), fnumber=camera.main_fnumber)
        for k in ("lenslet_offset_x", "lenslet_offset_y"):  # the camera allows one pitch at most
            lim = changes.get("lenslet_pitch", pl)
            if abs(changes[k]) > lim:
                raise ImperfectionError(
                    f"camera.imperfections.{k}: with camera.lenslet.{k[8:]} = {getattr(camera, k)!r} mm the grid "
                    f"would move by {changes[k]!r} mm; the total must stay within one pitch ({lim:.6g} mm)"
                )
        if abs(changes["lenslet_rotation"]) > math.radians(10):
            raise ImperfectionError(
                "camera.imperfections.lenslet_rotation: with camera.lenslet.rotation the grid's rotation "
                f"{changes['lenslet_rotation']!r} rad exceeds ±10°"
            )
        return camera.with_(**changes)

    def gap(self, camera: PlenopticCamera) -> float:
        """Lenslet-to-sensor distance g [mm] (the lenslet focal length when ideal)."""
        fl = camera.lenslet_focal_length
        return fl if self.lenslet_gap_error == 0.0 else fl * (1.0 + self.lenslet_gap_error)

    def scatter(self, camera: PlenopticCamera) -> np.ndarray | None:
        """Per-lenslet optical-centre offsets [mm], shape (n_lenslets_y, n_lenslets_x, 2) (x, y in the
        sensor frame), for ``camera``'s grid (pass the imaging camera); None without scatter."""
        if self.lenslet_scatter == 0.0:
            return None
        rng = np.random.default_rng(self.scatter_seed)
        shape = (camera.n_lenslets_y, camera.n_lenslets_x, 2)
        return rng.normal(0.0, self.lenslet_scatter * camera.lenslet_pitch, size=shape)

    def distortion_factor(self, camera: PlenopticCamera, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """1 + k1·ρ² + k2·ρ⁴ at each particle (ρ: its chief ray's radius on the nominal lenslet plane /
        the sensor half-diagonal). Raises :class:`ImperfectionError` where the mapping r → r·D(r)
        is not monotonic (the image would fold over)."""
        h = math.hypot(camera.sensor_width / 2.0, camera.sensor_height / 2.0)
        d = camera.so + np.asarray(z, dtype=np.float64)
        r2 = (camera.si / h) ** 2 * (np.asarray(x) ** 2 + np.asarray(y) ** 2) / d**2
        k1, k2 = self.distortion_k1, self.distortion_k2
        slope = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2  # d(r·D)/dr
        if np.any(slope <= 0.0):
            raise ImperfectionError(
                f"camera.imperfections.distortion_k1 = {k1!r}, distortion_k2 = {k2!r}: the distortion folds the "
                f"image over at ρ = {math.sqrt(float(r2[slope <= 0.0].min())):.3g} (need 1 + 3·k1·ρ² + 5·k2·ρ⁴ > 0 "
                "wherever particles are)"
            )
        return 1.0 + k1 * r2 + k2 * r2 * r2

    def distort(
        self, camera: PlenopticCamera, x: np.ndarray, y: np.ndarray, z: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The lateral positions (x, y) [mm] whose ideal image is the distorted image of (x, y, z)."""
        if not self.distorted:
            return x, y
        f = self.distortion_factor(camera, x, y, z)
        return np.ascontiguousarray(x * f), np.ascontiguousarray(y * f)

    def undistort_radius(self, camera: PlenopticCamera, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised radius ρu whose distorted radius is ``rho`` (Newton), and the area ratio
        dA(distorted)/dA(undistorted) = D·(1 + 3k1ρu² + 5k2ρu⁴) there."""
        k1, k2 = self.distortion_k1, self.distortion_k2
        rho = np.asarray(rho, dtype=np.float64)
        ru = rho.copy()
        for _ in range(50):
            r2 = ru * ru
            f = ru * (1.0 + k1 * r2 + k2 * r2 * r2) - rho
            df = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2
            if np.any(df <= 0.0):
                raise ImperfectionError(
                    f"camera.imperfections.distortion_k1 = {k1!r}, distortion_k2 = {k2!r}: the distortion folds "
                    "the image over within the pinhole field"
                )
            step = f / df
            ru = ru - step
            if np.all(np.abs(step) <= 1e-15 * np.maximum(ru, 1e-300)):
                break
        r2 = ru * ru
        return ru, (1.0 + k1 * r2 + k2 * r2 * r2) * (1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2)


def resolve(imperfections: CameraImperfections | Mapping[str, Any] | None) -> CameraImperfections:
    """The validated settings of a renderer's ``imperfections`` argument (None: the ideal camera)."""
    if imperfections is None:
        return CameraImperfections()
    if isinstance(imperfections, CameraImperfections):
        imp = imperfections
    else:
        sec = dict(imperfections)
        imp = CameraImperfections.from_config(sec, scatter_seed=int(sec.pop("scatter_seed", 0)))
    return imp
