"""The reconstruction grid: voxels uniform in object-space x, y, z [mm].

Every reconstruction method, and the focal-stack path, delivers its volume on
one grid, so a displacement in voxels means the same thing everywhere in the
volume and across methods (DESIGN "One grid for every method").

Defaults (thesis sec. 5.3–5.4): x, y voxels of one lenslet at the focal-plane
magnification, pl/|M| (the in-plane resolution of the camera; the thesis'
"pixel"); z steps of half the Table 5.1 plane spacing at the focal plane
(the depth of focus of one refocus plane, eqs 5.16–5.20), so a depth
displacement is sampled at least twice per depth-resolution cell. The grid
covers the rendered depth, from the nearest to the farthest refocus plane of
the case's marching (``refocus.n_planes``, ``depth_scale``), and the field of
view of the lenslet array.

``spacing="planes"`` keeps the thesis' own depth sampling: one voxel per
refocus plane (non-uniform in z). It exists to reproduce sec. 7.2 as the
thesis ran it, not for comparisons across designs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = ["GridError", "ReconstructionGrid", "make_grid", "default_voxel_z", "SPACINGS"]

SPACINGS = ("uniform", "planes")


class GridError(ValueError):
    """A reconstruction grid that cannot be built (names the setting and the allowed range)."""


@dataclass(frozen=True, eq=False)
class ReconstructionGrid:
    """Voxel centres in the object frame [mm], all ascending.

    ``x`` and ``y`` are uniform; ``z`` is uniform unless ``spacing`` is
    ``"planes"``. Array order of a volume is (z, y, x).
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    spacing: str = "uniform"

    def __post_init__(self) -> None:
        for name in ("x", "y", "z"):
            c = np.asarray(getattr(self, name), dtype=float)
            if c.ndim != 1 or c.size < 1 or not np.all(np.isfinite(c)):
                raise GridError(f"grid {name}: need a 1-D array of finite voxel centres")
            if c.size > 1 and np.any(np.diff(c) <= 0):
                raise GridError(f"grid {name}: voxel centres must be strictly ascending")
            object.__setattr__(self, name, c)
        for name in ("x", "y"):
            c = getattr(self, name)
            if c.size > 2 and not np.allclose(np.diff(c), c[1] - c[0], rtol=1e-9, atol=0):
                raise GridError(f"grid {name}: voxel centres must be uniformly spaced")
        if self.spacing not in SPACINGS:
            raise GridError(f"grid.spacing = {self.spacing!r}: allowed values are {', '.join(SPACINGS)}")

    # ------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int, int]:
        """(nz, ny, nx)."""
        return (self.z.size, self.y.size, self.x.size)

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    @staticmethod
    def _step(c: np.ndarray) -> float:
        return float(c[1] - c[0]) if c.size > 1 else 1.0

    @property
    def dx(self) -> float:
        """Voxel size in x [mm]."""
        return self._step(self.x)

    @property
    def dy(self) -> float:
        """Voxel size in y [mm]."""
        return self._step(self.y)

    @property
    def dz(self) -> np.ndarray:
        """Voxel thickness in z at every plane [mm] (constant on a uniform grid)."""
        if self.z.size == 1:
            return np.ones(1)
        return np.abs(np.gradient(self.z))

    @property
    def uniform_z(self) -> bool:
        return self.z.size < 3 or bool(np.allclose(np.diff(self.z), self.z[1] - self.z[0], rtol=1e-9, atol=0))

    def voxel_size(self) -> tuple[float, float, float]:
        """(dz, dy, dx) [mm]; dz is the mean step on a non-uniform grid."""
        return (float(np.mean(self.dz)), self.dy, self.dx)

    def nbytes(self, dtype: Any = np.float32) -> int:
        """Bytes of one volume on this grid."""
        return self.n_voxels * np.dtype(dtype).itemsize

    # --------------------------------------------------------------- xarray
    def coords(self) -> dict[str, Any]:
        """Coordinates for a (z, y, x) DataArray, CF style."""
        mm = lambda ln: {"units": "mm", "long_name": ln}  # noqa: E731
        return {
            "z": ("z", self.z, mm("depth z (object frame, +z away from the camera)")),
            "y": ("y", self.y, mm("y (object frame, up)")),
            "x": ("x", self.x, mm("x (object frame)")),
        }

    def attrs(self) -> dict[str, Any]:
        dz, _dy, dx = self.voxel_size()
        return {
            "grid_spacing": self.spacing,
            "voxel_size": float(dx),
            "voxel_size_z": float(dz),
            "voxel_size_units": "mm",
            "grid_shape": list(self.shape),
            "y_direction": "y ascends with the row index (object frame, +y up; plot with origin='lower')",
        }

    def volume(self, data: Any, name: str = "intensity", **attrs: Any) -> xr.DataArray:
        """Wrap a (nz, ny, nx) array as a DataArray on this grid."""
        if tuple(np.shape(data)) != self.shape:
            raise GridError(f"volume of shape {tuple(np.shape(data))} does not fit the grid {self.shape}")
        return xr.DataArray(
            data, dims=("z", "y", "x"), coords=self.coords(), name=name, attrs={**self.attrs(), **attrs}
        )

    @classmethod
    def from_coords(cls, obj: xr.DataArray | xr.Dataset) -> ReconstructionGrid:
        """The grid of a volume or stack (its 1-D ``z``, ``y``, ``x`` coords in mm)."""
        try:
            x, y, z = (np.asarray(obj[d].values, dtype=float) for d in ("x", "y", "z"))
        except KeyError as exc:
            raise GridError(f"volume has no 1-D coordinate {exc.args[0]!r}; need z, y, x in mm") from None
        spacing = str(obj.attrs.get("grid_spacing", "uniform"))
        if spacing not in SPACINGS:
            spacing = "uniform"
        if spacing == "uniform" and z.size > 2 and not np.allclose(np.diff(z), z[1] - z[0], rtol=1e-9, atol=0):
            spacing = "planes"
        return cls(x, y, z, spacing)


def default_voxel_z(camera: PlenopticCamera) -> float:
    """Half the Table 5.1 plane spacing at the focal plane [mm] (the default z step).

    The spacing is the mean object-space distance from the focal plane to its
    two neighbours in the default marching (eqs 5.16–5.20), i.e. the depth of
    focus of one refocus plane.
    """
    fp = camera.focal_planes()
    z = np.sort(np.asarray(fp["z"].values, dtype=float))
    if z.size < 2:
        return float(camera.depth_of_field(0.0)["depth_ambiguity"][0]) / 2.0
    i = int(np.argmin(np.abs(z)))
    nb = [abs(z[j] - z[i]) for j in (i - 1, i + 1) if 0 <= j < z.size]
    return 0.5 * float(np.mean(nb))


def _check_z_range(z_range: Sequence[float]) -> tuple[float, float]:
    """(z_min, z_max) of ``grid.z_range``, or a GridError naming it."""
    try:
        lo, hi = (float(v) for v in z_range)
    except (TypeError, ValueError):
        raise GridError(f"grid.z_range = {z_range!r}: must be two numbers [z_min, z_max] in mm") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise GridError(f"grid.z_range = {list(z_range)}: must be finite with z_min < z_max (mm)")
    return lo, hi


def make_grid(
    camera: PlenopticCamera,
    planes: xr.Dataset,
    *,
    voxel_xy: float | None = None,
    voxel_z: float | None = None,
    spacing: str = "uniform",
    z_range: Sequence[float] | None = None,
    max_bytes: float = 4e9,
) -> ReconstructionGrid:
    """The reconstruction grid of a camera and its refocus marching.

    Parameters
    ----------
    camera : PlenopticCamera
    planes : xarray.Dataset
        The refocus planes (:meth:`PlenopticCamera.focal_planes`); their depths
        set the z range (and the z centres with ``spacing="planes"``).
    voxel_xy : float, optional
        In-plane voxel size [mm]; default pl/|M|.
    voxel_z : float, optional
        Depth step [mm] of a uniform grid; default :func:`default_voxel_z`.
    spacing : {"uniform", "planes"}
        Uniform z steps, or one voxel per refocus plane (the thesis).
    z_range : (float, float), optional
        Object-space depth [mm] to cover instead of the marching's: the
        measurement volume (e.g. the seeded slab), so that designs whose
        marching reaches different depths are compared on the same volume.
        Uniform grids keep z = 0 on a voxel centre; ``planes`` keeps the planes
        inside the range.
    max_bytes : float
        Refuse grids whose float32 volume exceeds this (the reconstruction
        holds a few such volumes).

    Returns
    -------
    ReconstructionGrid
        x, y centred on the optical axis covering the lenslet array's field of
        view; z over [nearest, farthest] plane, containing z = 0 when uniform.

    Raises
    ------
    GridError
        A voxel size that is not a positive finite number, or a grid over ``max_bytes``.
    """
    if spacing not in SPACINGS:
        raise GridError(f"grid.spacing = {spacing!r}: allowed values are {', '.join(SPACINGS)}")
    d0 = camera.lenslet_pitch / abs(camera.magnification)
    dxy = d0 if voxel_xy is None else voxel_xy
    if not (isinstance(dxy, (int, float)) and math.isfinite(dxy) and dxy > 0):
        raise GridError(f"grid.voxel_xy = {voxel_xy!r}: must be a number > 0 mm (default pl/|M| = {d0:.4g} mm)")
    # The field of view of the lenslet array, in whole voxels, centred (as the focal stack).
    nx = max(1, round(camera.n_lenslets_x * d0 / dxy))
    ny = max(1, round(camera.n_lenslets_y * d0 / dxy))
    x = (np.arange(nx) - 0.5 * (nx - 1)) * dxy
    y = (np.arange(ny) - 0.5 * (ny - 1)) * dxy
    zp = np.sort(np.asarray(planes["z"].values, dtype=float))
    lo, hi = (zp[0], zp[-1]) if z_range is None else _check_z_range(z_range)
    if spacing == "planes":
        z = zp[(zp >= lo - 1e-9) & (zp <= hi + 1e-9)]
        if z.size == 0:
            raise GridError(
                f"grid.z_range = {list(z_range or ())}: holds no refocus plane "
                f"(planes at {zp[0]:.4g} .. {zp[-1]:.4g} mm)"
            )
    else:
        dz = default_voxel_z(camera) if voxel_z is None else voxel_z
        if not (isinstance(dz, (int, float)) and math.isfinite(dz) and dz > 0):
            raise GridError(f"grid.voxel_z = {voxel_z!r}: must be a number > 0 mm")
        k0 = math.ceil(lo / dz - 1e-9)
        k1 = math.floor(hi / dz + 1e-9)
        if k1 < k0:
            if z_range is not None:
                raise GridError(f"grid.z_range = {list(z_range)}: narrower than one voxel_z step of {dz:.4g} mm")
            k0 = k1 = 0
        z = np.arange(k0, k1 + 1) * dz
    grid = ReconstructionGrid(x, y, z, spacing)
    need = grid.nbytes(np.float32)
    if need > max_bytes:
        raise GridError(
            f"grid: {grid.shape[0]} x {grid.shape[1]} x {grid.shape[2]} voxels need {need / 1e9:.3g} GB per "
            f"volume, over grid.max_bytes = {max_bytes / 1e9:.3g} GB; use larger grid.voxel_xy / grid.voxel_z "
            "or raise grid.max_bytes"
        )
    return grid
