"""A gridded velocity field from a file (zarr or netCDF): how a user brings a DNS snapshot.

The file holds data variables ``u``, ``v``, ``w`` on the 1-D coordinates
``x``, ``y``, ``z`` (a rectilinear grid: any spacing, each coordinate strictly
monotonic; a decreasing one is flipped). Coordinates are mm and velocities
mm per unit time unless their ``units`` attribute says otherwise: lengths
m, cm, mm, µm are converted to mm; a velocity's unit is ``<length>/<time>``
(``mm/s``, ``m s-1``, ``m s^-1``, ``mm per unit time``), whose time is then
the flow's time unit (``dt`` counts in it). The field is interpolated
trilinearly (:class:`scipy.interpolate.RegularGridInterpolator`) and advected
by the same RK4 as the analytic flows.

Points outside the grid's extent (after ``offset``) stop with a
:class:`FlowError` naming the file and its extent (``outside: error``, the
default: a truth that was made up would flatter or spoil every error), or take
the value at the nearest grid point (``outside: nearest``: the field held
constant beyond its edges).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from lfstudy.simulate.flows._core import VEC3, FlowError, vec3

__all__ = ["GriddedFlow", "read_velocity_grid", "velocity_file_inputs"]

#: Length units a coordinate or velocity may carry, in mm.
LENGTH_UNITS: dict[str, float] = {
    "mm": 1.0,
    "millimeter": 1.0,
    "millimetre": 1.0,
    "millimeters": 1.0,
    "millimetres": 1.0,
    "m": 1000.0,
    "meter": 1000.0,
    "metre": 1000.0,
    "meters": 1000.0,
    "metres": 1000.0,
    "cm": 10.0,
    "um": 1e-3,
    "µm": 1e-3,
    "μm": 1e-3,
    "micron": 1e-3,
    "microns": 1e-3,
}
_VELOCITY = re.compile(
    r"^\s*(?P<len>[^\s/]+)\s*(?:/\s*(?P<t1>.+?)|\s+per\s+(?P<t2>.+?)|\s+(?P<t3>[^\s]+?)\s*(?:\^|\*\*)?\s*-1)\s*$"
)
OUTSIDE = ("error", "nearest")
_NETCDF = (".nc", ".nc4", ".cdf", ".netcdf", ".h5", ".hdf5")


def _length_scale(where: str, units: str) -> float:
    key = units.strip()
    if key not in LENGTH_UNITS:
        raise FlowError(f"{where} units = {units!r}: not a length; allowed: mm, m, cm, um")
    return LENGTH_UNITS[key]


def _velocity_scale(where: str, units: str) -> tuple[float, str]:
    """(factor to mm per time unit, the time unit) of a velocity's ``units`` attribute."""
    m = _VELOCITY.match(units)
    if not m:
        raise FlowError(
            f"{where} units = {units!r}: not a velocity; give <length>/<time> with length mm, m, cm or um "
            "(e.g. 'mm/s', 'm s-1', 'mm per unit time')"
        )
    time = next(t for t in (m["t1"], m["t2"], m["t3"]) if t)
    return _length_scale(where, m["len"]), time.strip()


def _open(path: Path):
    """Open a zarr store or a netCDF file lazily with xarray (a clear error for what cannot be read)."""
    import xarray as xr

    if not path.exists():
        raise FlowError(f"flow file {str(path)!r} does not exist")
    is_zarr = path.is_dir() or path.suffix == ".zarr"
    try:
        if is_zarr:  # zarr v2 or v3, consolidated or not (quietly)
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*consolidated metadata.*")
                return xr.open_zarr(path, consolidated=None, chunks=None)
        if path.suffix.lower() not in _NETCDF:
            raise FlowError(f"flow file {str(path)!r}: expected a zarr store (a folder, .zarr) or netCDF (.nc)")
        with open(path, "rb") as fh:
            magic = fh.read(4)
        if magic.startswith(b"\x89HDF"):
            import importlib.util

            if not any(importlib.util.find_spec(m) for m in ("h5netcdf", "netCDF4")):
                raise FlowError(
                    f"flow file {str(path)!r} is netCDF-4 (HDF5): reading it needs h5netcdf "
                    "(pip install 'lfstudy[netcdf4]') or netCDF4; or save it as netCDF-3 or zarr"
                )
        return xr.open_dataset(path, chunks=None, cache=False)
    except FlowError:
        raise
    except Exception as exc:  # xarray/zarr raise many kinds for an unreadable file
        raise FlowError(f"flow file {str(path)!r} cannot be read: {type(exc).__name__}: {exc}") from None


def _coords(ds, where: str) -> tuple[list[np.ndarray], list[bool]]:
    """The x, y, z coordinates in mm (increasing) and which were flipped."""
    out, flipped = [], []
    for c in "xyz":
        if c not in ds.coords or ds[c].ndim != 1 or ds[c].dims != (c,):
            raise FlowError(f"{where}: needs a 1-D coordinate {c!r} on dimension {c!r} (has {sorted(ds.coords)})")
        v = np.asarray(ds[c].values, dtype=float)
        if v.size < 2:
            raise FlowError(f"{where}: coordinate {c!r} has {v.size} point; need at least 2")
        if not np.all(np.isfinite(v)):
            raise FlowError(f"{where}: coordinate {c!r} holds NaN or infinite values")
        units = ds[c].attrs.get("units")
        if units is not None:
            v = v * _length_scale(f"{where}: coordinate {c!r}", str(units))
        d = np.diff(v)
        if np.all(d < 0):
            v, flip = v[::-1].copy(), True
        elif np.all(d > 0):
            flip = False
        else:
            raise FlowError(f"{where}: coordinate {c!r} is not strictly monotonic (repeated or unsorted values)")
        out.append(v)
        flipped.append(flip)
    return out, flipped


def _variables(ds, where: str) -> tuple[list[float], str]:
    """Checks that u, v, w exist on (x, y, z); their scale to mm and the time unit."""
    scales, times = [], set()
    for name in "uvw":
        if name not in ds.data_vars:
            have = sorted(map(str, ds.data_vars))
            raise FlowError(f"{where}: needs data variables 'u', 'v', 'w'; {name!r} is missing (has {have})")
        if set(ds[name].dims) != {"x", "y", "z"} or ds[name].ndim != 3:
            raise FlowError(
                f"{where}: variable {name!r} has dims {ds[name].dims}; need exactly ('x', 'y', 'z') in any order "
                "(select one time step, e.g. ds.isel(time=0), before saving)"
            )
        units = ds[name].attrs.get("units")
        if units is None:
            scales.append(1.0)
        else:
            s, t = _velocity_scale(f"{where}: variable {name!r}", str(units))
            scales.append(s)
            times.add(t)
    if len(times) > 1:
        raise FlowError(f"{where}: u, v, w are in different time units {sorted(times)}")
    return scales, (times.pop() if times else "unit time")


def velocity_file_inputs(path: str | Path) -> list[str]:
    """Every file a flow file consists of (a zarr store's files; a netCDF file itself), for the workflow."""
    p = Path(path)
    if p.is_dir():
        return sorted(str(f) for f in p.rglob("*") if f.is_file())
    return [str(p)]


def read_velocity_grid(path: str | Path, *, check_only: bool = False) -> dict[str, Any]:
    """Read and check a gridded velocity field (the module docstring says what it must hold).

    Parameters
    ----------
    path : str or Path
        A zarr store or a netCDF file.
    check_only : bool
        Check the structure (variables, coordinates, units) without reading
        the velocities (fast: what the config validation does).

    Returns
    -------
    dict
        ``x``, ``y``, ``z`` (increasing, mm), ``values`` (nx, ny, nz, 3) in mm per
        time unit (absent with ``check_only``) and ``time_unit``.

    Raises
    ------
    FlowError
        Missing file, variable or coordinate, bad units, non-monotonic
        coordinates, NaN or infinite velocities (named with the file).
    """
    path = Path(path)
    where = f"flow file {str(path)!r}"
    ds = _open(path)
    try:
        (x, y, z), flipped = _coords(ds, where)
        scales, time_unit = _variables(ds, where)
        out: dict[str, Any] = {"x": x, "y": y, "z": z, "time_unit": time_unit}
        if check_only:
            return out
        comps = []
        for name, s in zip("uvw", scales):
            a = np.asarray(ds[name].transpose("x", "y", "z").values, dtype=float)
            bad = ~np.isfinite(a)
            if bad.any():
                i = np.argwhere(bad)[0]
                raise FlowError(
                    f"{where}: variable {name!r} holds {int(bad.sum())} NaN or infinite values (the first at index "
                    f"x={i[0]}, y={i[1]}, z={i[2]}); fill or crop them"
                )
            comps.append(a * s)
        values = np.stack(comps, axis=-1)
        for k, flip in enumerate(flipped):
            if flip:
                values = np.flip(values, axis=k)
        out["values"] = np.ascontiguousarray(values)
        return out
    finally:
        ds.close()


@dataclass(frozen=True)
class GriddedFlow:
    """A velocity field read from a zarr store or netCDF file, interpolated trilinearly.

    Parameters
    ----------
    path : str
        The file (absolute, or relative to the working directory; a study
        config resolves it relative to the config file's folder).
    offset : (float, float, float)
        Added to the file's coordinates to place the field in the object frame
        [mm] (a DNS box from 0 to L: ``offset: [-L/2, ...]`` centres it).
    outside : {"error", "nearest"}
        A point outside the field's extent: stop with an error naming the file
        and its extent, or take the nearest grid point's velocity.
    """

    path: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    outside: str = "error"
    _grid: dict[str, Any] = field(init=False, repr=False, compare=False)
    _interp: Any = field(init=False, repr=False, compare=False)

    name: ClassVar[str] = "file"
    description: ClassVar[str] = "a gridded velocity field from a zarr or netCDF file (u, v, w on x, y, z)"
    config_required: ClassVar[tuple[str, ...]] = ()
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "path": {
            "type": "string",
            "minLength": 1,
            "description": "zarr store or netCDF file: absolute, or relative to the config file's folder",
        },
        "offset": {**VEC3, "description": "added to the file's coordinates: its place in the object frame [mm]"},
        "outside": {
            "type": "string",
            "enum": list(OUTSIDE),
            "description": "a point outside the field: error (stop, naming the extent) or nearest (edge value)",
        },
    }

    def __post_init__(self) -> None:
        from scipy.interpolate import RegularGridInterpolator

        object.__setattr__(self, "path", str(self.path))
        object.__setattr__(self, "offset", vec3("file", "offset", self.offset))
        if self.outside not in OUTSIDE:
            raise FlowError(f"file outside = {self.outside!r}: allowed values are 'error', 'nearest'")
        g = read_velocity_grid(self.path)
        axes = tuple(a + o for a, o in zip((g["x"], g["y"], g["z"]), self.offset))
        g.update(x=axes[0], y=axes[1], z=axes[2])
        object.__setattr__(self, "_grid", g)
        interp = RegularGridInterpolator(axes, g["values"], method="linear", bounds_error=False, fill_value=None)
        object.__setattr__(self, "_interp", interp)

    @classmethod
    def check_config(cls, params: dict[str, Any]) -> None:
        """Check a config's parameters and the file's structure without reading the velocities."""
        vec3("file", "offset", params.get("offset", (0.0, 0.0, 0.0)))
        if params.get("outside", "error") not in OUTSIDE:
            raise FlowError(f"file outside = {params['outside']!r}: allowed values are 'error', 'nearest'")
        read_velocity_grid(params["path"], check_only=True)

    @property
    def extent(self) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        """((x0, x1), (y0, y1), (z0, z1)) of the field in the object frame [mm]."""
        return tuple((float(self._grid[c][0]), float(self._grid[c][-1])) for c in "xyz")  # type: ignore[return-value]

    @property
    def time_unit(self) -> str:
        """The time unit of the file's velocities (``dt`` counts in it)."""
        return str(self._grid["time_unit"])

    def velocity(self, x, y, z):
        shape = np.broadcast(np.asarray(x), np.asarray(y), np.asarray(z)).shape
        pts = np.stack([np.broadcast_to(np.asarray(c, dtype=float), shape).ravel() for c in (x, y, z)], axis=-1)
        ext = self.extent
        lo = np.array([e[0] for e in ext])
        hi = np.array([e[1] for e in ext])
        out = (pts < lo) | (pts > hi) | ~np.isfinite(pts)
        if out.any():
            if self.outside == "nearest":
                pts = np.clip(pts, lo, hi)
            else:
                rows = out.any(axis=1)
                first = pts[np.argmax(rows)]
                box = ", ".join(f"{c} [{a:g}, {b:g}]" for c, (a, b) in zip("xyz", ext))
                raise FlowError(
                    f"flow file {self.path!r}: {int(rows.sum())} of {rows.size} points lie outside the field's extent "
                    f"{box} mm (the first at ({first[0]:g}, {first[1]:g}, {first[2]:g}) mm); extend the field, move "
                    "it with offset, or set outside: nearest"
                )
        vel = self._interp(pts)
        return tuple(vel[:, k].reshape(shape) for k in range(3))
