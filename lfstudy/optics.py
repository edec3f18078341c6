"""Plenoptic camera optics model (thesis ch. 4.1–4.3, 5.3).

Everything here is a pure function of the camera parameters: the thin-lens
layout (eqs 4.5–4.9), the lenslet grid over the sensor (eqs 4.10–4.11,
4.26–4.27), diffraction spots (eqs 4.20–4.25), depth of field and ambiguity
(eqs 4.16–4.19), the worst-case incidence angle (eq. 4.28) and the refocus
planes found by depth-of-focus marching (eqs 5.16–5.20, Table 5.1).

Units are millimetres and radians throughout.

Sensor frame: origin at the sensor centre, x to the right, y up (as seen
looking from the sensor towards the main lens' image, i.e. the raw image as
displayed). Image arrays are row-major with row 0 at the *top*, so the pixel
row index grows as y decreases. Lenslet rows follow the same rule.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import xarray as xr

__all__ = [
    "STANDARD_F_STOPS",
    "BETA_SQUARED",
    "OpticsError",
    "PlenopticCamera",
    "round_up_f_stop",
    "diffraction_spot_diameter",
    "gaussian_sigma",
]

#: Full-stop series of common lenses (sec. 4.3.1 rounds the matched f-number
#: up to one of these so that lenslet images never overlap).
STANDARD_F_STOPS: tuple[float, ...] = (
    1.0,
    1.4,
    2.0,
    2.8,
    4.0,
    5.6,
    8.0,
    11.0,
    16.0,
    22.0,
    32.0,
    45.0,
    64.0,
)

#: Gaussian fit to the Airy disk, Adrian & Westerweel p. 101 (eq. 4.23).
BETA_SQUARED = 3.67


class OpticsError(ValueError):
    """An optical configuration that cannot be built (names field and range)."""


def round_up_f_stop(exact: float, stops: tuple[float, ...] = STANDARD_F_STOPS) -> float:
    """Round an f-number **up** to the next standard f-stop (sec. 4.3.1).

    Parameters
    ----------
    exact : float
        The exact f-number, e.g. from eq. 4.8.
    stops : tuple of float
        Available f-stops, ascending.

    Returns
    -------
    float
        The smallest stop >= ``exact`` (with a 1e-9 relative tolerance so that
        an exact 2.0 stays 2.0).

    Raises
    ------
    OpticsError
        If ``exact`` exceeds the largest stop.
    """
    for s in stops:
        if s >= exact * (1.0 - 1e-9):
            return float(s)
    raise OpticsError(
        f"main_lens.fnumber: the matched f-number {exact:.3g} is above the largest "
        f"available f-stop {stops[-1]:g}; allowed: <= {stops[-1]:g}"
    )


def diffraction_spot_diameter(magnification: float, fnumber: float, wavelength: float) -> float:
    """Diffraction-limited spot diameter, eq. 4.21 (Adrian & Westerweel).

    ``magnification`` is taken as a positive number here (the text notes the
    reference's sign convention), so its absolute value is used.
    """
    return 2.44 * (1.0 + abs(magnification)) * fnumber * wavelength  # eq. 4.21


def particle_image_diameter(magnification: float, particle_diameter: float, spot: float) -> float:
    """Particle image diameter including diffraction, eq. 4.20."""
    return math.sqrt((magnification * particle_diameter) ** 2 + spot**2)  # eq. 4.20


def gaussian_sigma(spot_diameter: float) -> float:
    """Standard deviation of the Gaussian equivalent to an Airy spot, eq. 4.25."""
    return math.sqrt(spot_diameter**2 / (8.0 * BETA_SQUARED))  # eq. 4.25


def _positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value) and value > 0):
        raise OpticsError(f"{name} = {value!r}: must be a finite number > 0")


@dataclass(frozen=True)
class PlenopticCamera:
    """A validated plenoptic (light-field) camera.

    Parameters
    ----------
    n_pixels_x, n_pixels_y : int
        Sensor pixel counts (columns, rows).
    pixel_pitch : float
        Square pixel pitch pp [mm].
    lenslet_pitch : float
        Square lenslet pitch pl [mm].
    lenslet_focal_length : float
        Lenslet focal length fl [mm]; the sensor sits at fl behind the array.
    main_focal_length : float
        Main lens focal length fm [mm].
    magnification : float
        Lateral magnification M, negative (real inverted image, eq. 4.5).
    fnumber : float or "matched"
        Main-lens f-number. ``"matched"`` applies eq. 4.8 and rounds up to a
        standard stop (sec. 4.3.1); a number is used as given and may over-
        or under-fill the lenslet images (see :attr:`lenslet_image_fill`).
    wavelength : float
        Illumination wavelength λ [mm] (532 nm = 5.32e-4 mm).
    particle_diameter : float
        Physical particle diameter dp [mm].
    min_fnumber, max_fnumber : float
        The f-numbers the main lens can reach; an explicit or matched
        f-number outside this range is rejected.
    lenslet_offset_x, lenslet_offset_y : float
        Shift of the lenslet grid from the centred position [mm] (real
        cameras are never perfectly aligned; calibration must find it).
    lenslet_rotation : float
        Rotation of the lenslet grid about the optical axis [rad].
    f_stops : tuple of float
        The standard stops used to round a matched f-number.
    """

    n_pixels_x: int
    n_pixels_y: int
    pixel_pitch: float
    lenslet_pitch: float
    lenslet_focal_length: float
    main_focal_length: float
    magnification: float
    fnumber: float | str = "matched"
    wavelength: float = 532e-6
    particle_diameter: float = 1e-3
    min_fnumber: float = 1.0
    max_fnumber: float = 32.0
    lenslet_offset_x: float = 0.0
    lenslet_offset_y: float = 0.0
    lenslet_rotation: float = 0.0
    f_stops: tuple[float, ...] = field(default=STANDARD_F_STOPS, repr=False)

    # ------------------------------------------------------------------ build
    def __post_init__(self) -> None:
        for name in ("n_pixels_x", "n_pixels_y"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                raise OpticsError(f"{name} = {v!r}: must be an integer >= 1")
        for name in (
            "pixel_pitch",
            "lenslet_pitch",
            "lenslet_focal_length",
            "main_focal_length",
            "wavelength",
            "particle_diameter",
            "min_fnumber",
            "max_fnumber",
        ):
            _positive(name, getattr(self, name))
        m = self.magnification
        if not (math.isfinite(m) and m < 0):
            raise OpticsError(f"magnification = {m!r}: must be negative (a real, inverted image; eq. 4.5)")
        if self.lenslet_pitch < 2 * self.pixel_pitch:
            raise OpticsError(
                f"lenslet_pitch = {self.lenslet_pitch} mm: must be at least two pixels "
                f"(>= {2 * self.pixel_pitch} mm) to sample any angle"
            )
        if self.lenslet_pitch > min(self.sensor_width, self.sensor_height):
            raise OpticsError(
                f"lenslet_pitch = {self.lenslet_pitch} mm: must be smaller than the sensor "
                f"({min(self.sensor_width, self.sensor_height):.4g} mm)"
            )
        if abs(self.lenslet_rotation) > math.radians(10):
            raise OpticsError(
                f"lenslet_rotation = {self.lenslet_rotation!r} rad: allowed range is "
                f"[-{math.radians(10):.4f}, {math.radians(10):.4f}] (±10°)"
            )
        for name in ("lenslet_offset_x", "lenslet_offset_y"):
            v = getattr(self, name)
            if not (math.isfinite(v) and abs(v) <= self.lenslet_pitch):
                raise OpticsError(
                    f"{name} = {v!r} mm: allowed range is [-{self.lenslet_pitch}, {self.lenslet_pitch}] "
                    "(at most one lenslet pitch)"
                )
        if self.min_fnumber > self.max_fnumber:
            raise OpticsError(f"min_fnumber = {self.min_fnumber} > max_fnumber = {self.max_fnumber}")
        n = self.main_fnumber  # validates the f-number policy
        if not (self.min_fnumber * (1 - 1e-9) <= n <= self.max_fnumber * (1 + 1e-9)):
            raise OpticsError(
                f"fnumber = {self.fnumber!r} (f/{n:g}): the main lens cannot reach it; "
                f"allowed range is [{self.min_fnumber:g}, {self.max_fnumber:g}]"
            )

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> PlenopticCamera:
        """Build a camera from the ``camera`` section of a config (or the whole config).

        Accepts the nested layout of ``config/schema.yaml``::

            camera:
              sensor: {n_pixels_x, n_pixels_y, pixel_pitch}
              lenslet: {pitch, focal_length | fnumber, offset_x, offset_y, rotation}
              main_lens: {focal_length, fnumber, min_fnumber, max_fnumber}
              magnification, wavelength, particle_diameter

        The lenslet focal length may be given directly or as a lenslet
        f-number (fl = N·pl), which keeps the lenslet f-number fixed when the
        pitch is swept.
        """
        c = cfg.get("camera", cfg)
        try:
            sensor, lens, main = c["sensor"], c["lenslet"], c["main_lens"]
            pitch = lens["pitch"]
            if lens.get("focal_length") is not None:
                fl = lens["focal_length"]
            elif lens.get("fnumber") is not None:
                _positive("camera.lenslet.fnumber", lens["fnumber"])
                fl = lens["fnumber"] * pitch
            else:
                raise OpticsError("camera.lenslet: give either focal_length or fnumber")
            kwargs = {
                "n_pixels_x": int(sensor["n_pixels_x"]),
                "n_pixels_y": int(sensor["n_pixels_y"]),
                "pixel_pitch": float(sensor["pixel_pitch"]),
                "lenslet_pitch": float(pitch),
                "lenslet_focal_length": float(fl),
                "main_focal_length": float(main["focal_length"]),
                "magnification": float(c["magnification"]),
                "fnumber": main.get("fnumber", "matched"),
            }
        except KeyError as exc:
            raise OpticsError(f"camera config is missing the key {exc.args[0]!r}") from None
        for key, name in (("wavelength", "wavelength"), ("particle_diameter", "particle_diameter")):
            if c.get(key) is not None:
                kwargs[name] = float(c[key])
        for key in ("min_fnumber", "max_fnumber"):
            if main.get(key) is not None:
                kwargs[key] = float(main[key])
        for key in ("offset_x", "offset_y", "rotation"):
            if lens.get(key) is not None:
                kwargs[f"lenslet_{key}"] = float(lens[key])
        if kwargs["fnumber"] != "matched":
            try:
                kwargs["fnumber"] = float(kwargs["fnumber"])
            except (TypeError, ValueError):
                raise OpticsError(
                    f"camera.main_lens.fnumber = {kwargs['fnumber']!r}: must be 'matched' or a number"
                ) from None
        return cls(**kwargs)

    def with_(self, **changes: Any) -> PlenopticCamera:
        """A copy with some parameters changed (validated again)."""
        return replace(self, **changes)

    def to_attrs(self) -> dict[str, Any]:
        """Flat, netCDF/zarr-safe attributes describing this camera."""
        d = asdict(self)
        d.pop("f_stops")
        d["fnumber_policy"] = str(d.pop("fnumber"))
        d["main_fnumber"] = self.main_fnumber
        d["image_distance"] = self.si
        d["object_distance"] = self.so
        return {f"camera_{k}": (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in d.items()}

    # --------------------------------------------------------------- layout
    @property
    def sensor_width(self) -> float:
        """Sensor width np,x·pp [mm]."""
        return self.n_pixels_x * self.pixel_pitch

    @property
    def sensor_height(self) -> float:
        """Sensor height np,y·pp [mm]."""
        return self.n_pixels_y * self.pixel_pitch

    @property
    def si(self) -> float:
        """Main lens to lenslet array (image) distance, eq. 4.6 [mm]."""
        return self.main_focal_length * (1.0 - self.magnification)  # eq. 4.6

    @property
    def so(self) -> float:
        """Object focal plane to main lens distance, eq. 4.7 [mm]."""
        return -self.si / self.magnification  # eq. 4.7

    @property
    def fov_x(self) -> float:
        """Object-space field of view in x [mm] (eq. 4.5 solved for FOV)."""
        return self.sensor_width / abs(self.magnification)

    @property
    def fov_y(self) -> float:
        """Object-space field of view in y [mm] (eq. 4.5)."""
        return self.sensor_height / abs(self.magnification)

    @property
    def lenslet_fnumber(self) -> float:
        """Lenslet f-number fl/pl (lenslets focused at infinity, sec. 4.2)."""
        return self.lenslet_focal_length / self.lenslet_pitch

    @property
    def matched_fnumber(self) -> float:
        """Exact image-side matched main-lens f-number, eq. 4.8."""
        return self.lenslet_fnumber / (1.0 - self.magnification)  # eq. 4.8

    @property
    def main_fnumber(self) -> float:
        """Main-lens f-number in use (matched and rounded up, or explicit)."""
        if isinstance(self.fnumber, str):
            if self.fnumber != "matched":
                raise OpticsError(f"fnumber = {self.fnumber!r}: must be 'matched' or a number")
            return round_up_f_stop(self.matched_fnumber, self.f_stops)
        _positive("fnumber", self.fnumber)
        return float(self.fnumber)

    @property
    def aperture_diameter(self) -> float:
        """Main lens aperture diameter pm, eq. 4.9 [mm]."""
        return self.main_focal_length / self.main_fnumber  # eq. 4.9

    @property
    def lenslet_image_diameter(self) -> float:
        """Diameter of one lenslet's image of the main-lens aperture on the sensor [mm].

        Similar triangles through a lenslet centre: pm·fl/si.
        """
        return self.aperture_diameter * self.lenslet_focal_length / self.si

    @property
    def lenslet_image_fill(self) -> float:
        """Lenslet image diameter / lenslet pitch: > 1 overlap (crosstalk), < 1 underfill."""
        return self.lenslet_image_diameter / self.lenslet_pitch

    @property
    def lenslet_image_status(self) -> str:
        """``"overlap"``, ``"underfill"`` or ``"matched"`` (within 0.5 %)."""
        f = self.lenslet_image_fill
        if f > 1.005:
            return "overlap"
        if f < 0.995:
            return "underfill"
        return "matched"

    @property
    def pixels_per_lenslet(self) -> float:
        """Lenslet pitch in pixels (derived, not the thesis' hard-coded 14)."""
        return self.lenslet_pitch / self.pixel_pitch

    @property
    def n_lenslets_x(self) -> int:
        """Lenslet columns needed to cover the sensor (Table 4.3: 289)."""
        return self._n_lenslets(axis=0)

    @property
    def n_lenslets_y(self) -> int:
        """Lenslet rows needed to cover the sensor (Table 4.3: 193)."""
        return self._n_lenslets(axis=1)

    def _n_lenslets(self, axis: int) -> int:
        """Lenslets along grid axis 0 (columns, x) or 1 (rows, y) covering the sensor.

        The smallest grid (centred on its offset, rotated) that covers every
        sensor corner; the tolerance keeps an exact multiple from gaining one.
        """
        c, s = math.cos(self.lenslet_rotation), math.sin(self.lenslet_rotation)
        w, h = self.sensor_width / 2.0, self.sensor_height / 2.0
        half = 0.0
        for x, y in ((w, h), (w, -h), (-w, h), (-w, -h)):
            dx, dy = x - self.lenslet_offset_x, y - self.lenslet_offset_y
            g = (c * dx + s * dy, -s * dx + c * dy)  # into the grid frame
            half = max(half, abs(g[axis]))
        return math.ceil(2.0 * half / self.lenslet_pitch - 1e-9)

    @property
    def lenslet_offset(self) -> tuple[float, float]:
        """Offsets (ox, oy) of eqs 4.10–4.11 centring the grid on the sensor [mm]."""
        ox = (self.sensor_width - self.n_lenslets_x * self.lenslet_pitch) / 2.0
        oy = (self.sensor_height - self.n_lenslets_y * self.lenslet_pitch) / 2.0
        return ox, oy

    def lenslet_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """Lenslet centres in the sensor frame, eqs 4.26–4.27 [mm].

        Returns
        -------
        cx, cy : ndarray, shape (n_lenslets_y, n_lenslets_x)
            Centre coordinates; row 0 is the top row (largest y). The grid is
            centred on the optical axis, then shifted by the lenslet offsets
            and rotated by ``lenslet_rotation``.
        """
        j = np.arange(self.n_lenslets_x) - (self.n_lenslets_x - 1) / 2.0
        i = (self.n_lenslets_y - 1) / 2.0 - np.arange(self.n_lenslets_y)
        gx, gy = np.meshgrid(j * self.lenslet_pitch, i * self.lenslet_pitch)
        return self.grid_to_sensor(gx, gy)

    def grid_to_sensor(self, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map lenslet-grid frame coordinates to the sensor frame (rotate, then shift)."""
        c, s = math.cos(self.lenslet_rotation), math.sin(self.lenslet_rotation)
        return (c * gx - s * gy + self.lenslet_offset_x, s * gx + c * gy + self.lenslet_offset_y)

    def pixel_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre coordinates (x per column, y per row) in the sensor frame [mm].

        Row 0 is the top of the image, so ``y`` decreases with the row index
        (eq. 4.15).
        """
        x = (np.arange(self.n_pixels_x) + 0.5) * self.pixel_pitch - self.sensor_width / 2.0
        y = self.sensor_height / 2.0 - (np.arange(self.n_pixels_y) + 0.5) * self.pixel_pitch
        return x, y

    # ------------------------------------------------------------ diffraction
    @property
    def lenslet_plane_magnification(self) -> float:
        """|M| = si/so used for the spot formed by the main lens on the lenslets."""
        return self.si / self.so

    @property
    def sensor_plane_magnification(self) -> float:
        """|M| = fl/si used for the spot formed by a lenslet on the sensor (sec. 4.2.3)."""
        return self.lenslet_focal_length / self.si

    @property
    def spot_lenslet_plane(self) -> float:
        """Diffraction spot diameter at the lenslet array, ds,m (eq. 4.21, main f-number)."""
        return diffraction_spot_diameter(self.lenslet_plane_magnification, self.main_fnumber, self.wavelength)

    @property
    def spot_sensor_plane(self) -> float:
        """Diffraction spot diameter at the sensor, ds,l (eq. 4.21, lenslet f-number)."""
        return diffraction_spot_diameter(self.sensor_plane_magnification, self.lenslet_fnumber, self.wavelength)

    @property
    def sigma_lenslet_plane(self) -> float:
        """Gaussian σ of the lenslet-plane diffraction blur, σm (eq. 4.25) [mm]."""
        return gaussian_sigma(self.spot_lenslet_plane)

    @property
    def sigma_sensor_plane(self) -> float:
        """Gaussian σ of the sensor-plane diffraction blur, σl (eq. 4.25) [mm]."""
        return gaussian_sigma(self.spot_sensor_plane)

    @property
    def particle_image_lenslet_plane(self) -> float:
        """Particle image diameter dτ at the lenslet plane, eq. 4.20 [mm]."""
        return particle_image_diameter(
            self.lenslet_plane_magnification, self.particle_diameter, self.spot_lenslet_plane
        )

    @property
    def particle_image_sensor_plane(self) -> float:
        """Particle image diameter dτ at the sensor plane, eq. 4.20 [mm]."""
        return particle_image_diameter(self.sensor_plane_magnification, self.particle_diameter, self.spot_sensor_plane)

    def defocus_blur(self, z: float | np.ndarray) -> np.ndarray:
        """Signed geometric blur-circle diameter on the lenslet array of a point at depth ``z`` [mm].

        The main lens' aperture D imaged out of focus (sec. 4.2.2): ``D·(1 + si·(1/(so + z) − 1/f))``,
        0 on the focal plane, positive in front of it and negative beyond. Its magnitude over the
        lenslet pitch is the number of lenslets a particle's spot spans; a change of one pitch between
        two depths is one depth cell (the circle of confusion of eq. 4.18 is the pitch).

        Parameters
        ----------
        z : float or array_like
            Depth from the object focal plane [mm], +z away from the camera.

        Returns
        -------
        numpy.ndarray
            The signed diameter [mm], shaped like ``z``.
        """
        z = np.asarray(z, dtype=float)
        return self.aperture_diameter * (1.0 + self.si * (1.0 / (self.so + z) - 1.0 / self.main_focal_length))

    # ------------------------------------------------------- depth of field
    def depth_of_field(self, z: float | np.ndarray = 0.0) -> xr.Dataset:
        """Object-space depth of field and ambiguities at depth ``z`` (eqs 4.16–4.19).

        The circle of confusion is the lenslet pitch (sec. 4.2.2).

        Parameters
        ----------
        z : float or array_like
            Particle depth from the object focal plane [mm], +z away from the camera.

        Returns
        -------
        xarray.Dataset
            ``near`` / ``far`` (object distances D_N,o, D_F,o from the main lens),
            ``z_near`` / ``z_far`` (the same as depths), ``depth_ambiguity`` ξz
            (eq. 4.18) and ``inplane_ambiguity`` ξy (eq. 4.19, at the local
            magnification of depth z), all in mm, over dimension ``z``.
        """
        z = np.atleast_1d(np.asarray(z, dtype=float))
        f, n, c = self.main_focal_length, self.main_fnumber, self.lenslet_pitch
        s = self.so + z
        if np.any(s <= f):
            raise OpticsError(
                f"z: depths must keep the particle beyond the main-lens focal length (z > {f - self.so:.4g} mm)"
            )
        denom_far = f**2 - c * (s - f) * n
        near = s * f**2 / (f**2 + c * (s - f) * n)  # eq. 4.16
        far = np.where(denom_far > 0, s * f**2 / np.where(denom_far > 0, denom_far, 1.0), np.inf)  # eq. 4.17
        local_m = f / (s - f)  # |M| of a particle at distance s (thin lens)
        ds = xr.Dataset(
            {
                "near": ("z", near, {"units": "mm", "long_name": "near depth-of-field limit D_N,o"}),
                "far": ("z", far, {"units": "mm", "long_name": "far depth-of-field limit D_F,o"}),
                "z_near": ("z", near - self.so, {"units": "mm", "long_name": "near limit depth"}),
                "z_far": ("z", far - self.so, {"units": "mm", "long_name": "far limit depth"}),
                "depth_ambiguity": ("z", far - near, {"units": "mm", "long_name": "depth ambiguity ξz"}),  # eq. 4.18
                "inplane_ambiguity": (
                    "z",
                    c / (2.0 * local_m),  # eq. 4.19
                    {"units": "mm", "long_name": "in-plane ambiguity ξy"},
                ),
            },
            coords={"z": ("z", z, {"units": "mm", "long_name": "particle depth"})},
        )
        return ds

    @property
    def max_incidence_angle(self) -> float:
        """Worst-case ray angle on the sensor, eq. 4.28 [rad]."""
        half_diag = math.hypot(self.sensor_width / 2.0, self.sensor_height / 2.0)
        return self.lenslet_pitch / (2.0 * self.lenslet_focal_length) + math.atan(half_diag / self.si)  # eq. 4.28

    # ----------------------------------------------------------- focal planes
    @property
    def default_n_planes(self) -> int:
        """Unique refocus planes: one per pixel under a lenslet, symmetric about
        the focal plane (Levoy; Table 5.1: 16.9 px → 8 per side → 17 planes)."""
        return 2 * (math.floor(self.pixels_per_lenslet + 1e-9) // 2) + 1

    def focal_planes(
        self,
        n_planes: int | None = None,
        *,
        depth_scale: float = 1.0,
        cubic: bool = False,
    ) -> xr.Dataset:
        """Refocus planes by depth-of-focus marching (eqs 5.16–5.20, Table 5.1).

        Each plane sits at the centre of a depth-of-focus "diamond" of height
        c = lenslet pitch; neighbours share a bound, marching outwards from the
        image focal plane Di = si.

        Parameters
        ----------
        n_planes : int, optional
            Number of planes; default :attr:`default_n_planes`. An even count
            puts one more plane on the near (negative t) side.
        depth_scale : float
            Widen (>1) or narrow the depth covered by the default marching; the
            thesis widens by 50 % with twice the planes for depth motion (sec.
            7.2: ``n_planes=32, depth_scale=1.5``). Implemented by marching with
            a circle of confusion c·depth_scale·n_default/n_planes, which keeps
            the diamond geometry and spans ``depth_scale`` times the depth.
        cubic : bool
            Supersample (sec. 5.4): choose the plane count so the mean object-
            space plane spacing equals the in-plane voxel size pl/|M|
            (overrides ``n_planes``).

        Returns
        -------
        xarray.Dataset
            Over dimension ``plane`` (1-based numbers as in Table 5.1):
            ``near``, ``far`` (image-side D_N,i, D_F,i), ``image_distance`` Di,
            ``t`` = Di − si, object-space depth ``z`` (+z away from the camera),
            ``z_near``/``z_far``, and ``magnification`` (−Di/Do) per plane.
        """
        if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and 0 < depth_scale <= 10):
            raise OpticsError(f"depth_scale = {depth_scale!r}: allowed range is (0, 10]")
        n0 = self.default_n_planes
        if cubic:
            base = self._march(n0, self.lenslet_pitch * depth_scale)
            # Object-space depth covered by all diamonds; n planes split it
            # into n cells of about one in-plane voxel (pl/|M|) each.
            span = float(base["z_far"].max() - base["z_near"].min())
            voxel = self.lenslet_pitch / abs(self.magnification)
            n_planes = max(1, round(span / voxel))
        if n_planes is None:
            n_planes = n0
        if not isinstance(n_planes, (int, np.integer)) or n_planes < 1 or n_planes > 4096:
            raise OpticsError(f"n_planes = {n_planes!r}: allowed range is 1..4096")
        c_eff = self._solve_coc(int(n_planes), depth_scale * self._image_span(n0, self.lenslet_pitch))
        ds = self._march(int(n_planes), c_eff)
        ds.attrs.update(
            circle_of_confusion=c_eff,
            depth_scale=float(depth_scale),
            cubic=int(bool(cubic)),
            main_fnumber=self.main_fnumber,
            main_focal_length=self.main_focal_length,
            image_distance_focus=self.si,
        )
        return ds

    def planes_at(self, z: np.ndarray | list[float]) -> xr.Dataset:
        """Refocus planes at given object-space depths (thin lens), laid out as :meth:`focal_planes`.

        Used to refocus directly onto a reconstruction grid: plane ``k`` sits at
        depth ``z[k]``, i.e. object distance Do = so + z, image distance
        Di = 1/(1/fm − 1/Do) (eq. 4.1), refocus distance t = Di − si and
        magnification −Di/Do.

        Parameters
        ----------
        z : array_like
            Object-space depths [mm], +z away from the camera; every one must keep
            the object beyond the main-lens focal length.

        Returns
        -------
        xarray.Dataset
            ``image_distance``, ``t``, ``z`` and ``magnification`` over ``plane``
            (1-based, in the order given).
        """
        z = np.atleast_1d(np.asarray(z, dtype=float))
        f = self.main_focal_length
        do = self.so + z
        if z.size == 0 or not np.all(np.isfinite(z)) or np.any(do <= f):
            raise OpticsError(
                f"planes_at: depths must be finite and keep the object beyond the focal length "
                f"(z > {f - self.so:.4g} mm)"
            )
        di = 1.0 / (1.0 / f - 1.0 / do)  # eq. 4.1
        attrs = lambda u, ln: {"units": u, "long_name": ln}  # noqa: E731
        return xr.Dataset(
            {
                "image_distance": ("plane", di, attrs("mm", "refocus image distance D_i")),
                "t": ("plane", di - self.si, attrs("mm", "refocus distance t")),
                "z": ("plane", z, attrs("mm", "object-space depth of plane")),
                "magnification": ("plane", -di / do, attrs("1", "magnification of plane")),
            },
            coords={"plane": ("plane", np.arange(1, z.size + 1), attrs("1", "plane number"))},
        )

    def _image_span(self, n_planes: int, c: float) -> float:
        """Image-side depth D_F,i(last) − D_N,i(first) covered by a marching."""
        f, n = self.main_focal_length, self.main_fnumber
        ratio = (f + n * c) / (f - n * c)
        lo, hi = -(n_planes // 2), n_planes - 1 - n_planes // 2
        return self.si * (ratio**hi * f / (f - n * c) - ratio**lo * f / (f + n * c))

    def _solve_coc(self, n_planes: int, span: float) -> float:
        """Circle of confusion whose n-plane marching covers ``span`` (bisection)."""
        if n_planes == self.default_n_planes and math.isclose(span, self._image_span(n_planes, self.lenslet_pitch)):
            return self.lenslet_pitch  # exactly Table 5.1's marching
        lo, hi = 0.0, 0.999 * self.main_focal_length / self.main_fnumber
        if self._image_span(n_planes, hi) < span:
            raise OpticsError(
                "focal planes: the requested depth cannot be covered; use a smaller depth_scale or more planes"
            )
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if self._image_span(n_planes, mid) < span:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def _march(self, n_planes: int, c: float) -> xr.Dataset:
        f, n = self.main_focal_length, self.main_fnumber
        k = f / (f + n * c)  # D_N,i = k·Di  (eqs 5.16/5.18 with Di eliminated)
        kf = f / (f - n * c)  # D_F,i = kf·Di (eqs 5.17/5.19)
        if f - n * c <= 0:
            raise OpticsError(
                f"focal planes: circle of confusion {c:.4g} mm × f/{n:g} exceeds the focal "
                f"length {f:g} mm; use fewer planes or a smaller depth_scale"
            )
        # Plane offsets from the focal plane: -(n//2) .. n-1-n//2.
        idx = np.arange(n_planes) - n_planes // 2
        # Marching: a neighbour's near bound is this plane's far bound, so
        # Di_{k+1} = Di_k·kf/k  (geometric progression, eq. 5.20).
        ratio = kf / k
        di = self.si * ratio**idx
        near, far = di * k, di * kf
        with np.errstate(divide="ignore"):
            do = 1.0 / (1.0 / f - 1.0 / di)
            do_near = 1.0 / (1.0 / f - 1.0 / far)  # far image bound ↔ near object bound
            do_far = 1.0 / (1.0 / f - 1.0 / near)
        if np.any(di <= f) or np.any(near <= f):
            raise OpticsError(
                "focal planes: marching reached the main-lens focal length; use fewer planes or a smaller depth_scale"
            )
        attrs = lambda u, ln: {"units": u, "long_name": ln}  # noqa: E731
        return xr.Dataset(
            {
                "near": ("plane", near, attrs("mm", "near depth-of-focus bound D_N,i")),
                "far": ("plane", far, attrs("mm", "far depth-of-focus bound D_F,i")),
                "image_distance": ("plane", di, attrs("mm", "refocus image distance D_i")),
                "t": ("plane", di - self.si, attrs("mm", "refocus distance t")),
                "z": ("plane", do - self.so, attrs("mm", "object-space depth of plane")),
                "z_near": ("plane", do_near - self.so, attrs("mm", "object-space near limit")),
                "z_far": ("plane", do_far - self.so, attrs("mm", "object-space far limit")),
                "magnification": ("plane", -di / do, attrs("1", "magnification of plane")),
            },
            coords={"plane": ("plane", np.arange(1, n_planes + 1), attrs("1", "plane number"))},
        )

    # ---------------------------------------------------------------- report
    def summary(self) -> dict[str, Any]:
        """Derived parameters as a flat, ordered mapping (for tables and the CLI)."""
        ox, oy = self.lenslet_offset
        return {
            "sensor [px]": f"{self.n_pixels_x} x {self.n_pixels_y}",
            "sensor size [mm]": f"{self.sensor_width:.4f} x {self.sensor_height:.4f}",
            "pixel pitch pp [mm]": self.pixel_pitch,
            "lenslet pitch pl [mm]": self.lenslet_pitch,
            "lenslet focal length fl [mm]": self.lenslet_focal_length,
            "pixels per lenslet": round(self.pixels_per_lenslet, 4),
            "lenslets": f"{self.n_lenslets_x} x {self.n_lenslets_y}",
            "lenslet offsets ox, oy [mm]": f"{ox:.5f}, {oy:.5f}",
            "main focal length fm [mm]": self.main_focal_length,
            "magnification M": self.magnification,
            "si [mm] (eq. 4.6)": round(self.si, 6),
            "so [mm] (eq. 4.7)": round(self.so, 6),
            "field of view [mm]": f"{self.fov_x:.4f} x {self.fov_y:.4f}",
            "lenslet f-number": round(self.lenslet_fnumber, 4),
            "matched main f-number (eq. 4.8)": round(self.matched_fnumber, 4),
            "main f-number in use": self.main_fnumber,
            "aperture diameter pm [mm] (eq. 4.9)": round(self.aperture_diameter, 6),
            "lenslet image fill": f"{self.lenslet_image_fill:.3f} ({self.lenslet_image_status})",
            "spot at lenslets ds,m [um]": round(self.spot_lenslet_plane * 1e3, 3),
            "sigma at lenslets [um]": round(self.sigma_lenslet_plane * 1e3, 3),
            "spot at sensor ds,l [um]": round(self.spot_sensor_plane * 1e3, 3),
            "sigma at sensor [um]": round(self.sigma_sensor_plane * 1e3, 3),
            "depth ambiguity xi_z at z=0 [mm]": round(float(self.depth_of_field(0.0)["depth_ambiguity"][0]), 5),
            "in-plane ambiguity xi_y [mm]": round(float(self.depth_of_field(0.0)["inplane_ambiguity"][0]), 5),
            "max incidence angle [deg] (eq. 4.28)": round(math.degrees(self.max_incidence_angle), 3),
        }
