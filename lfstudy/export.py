"""Export to ParaView (VTK) and ImageJ/Fiji (TIFF hyperstacks) with physical coordinates.

* :func:`to_vtk`: a PIV result or a volume/focal stack as a VTK XML rectilinear grid (``.vtr``):
  one grid node per window centre or voxel centre, at its coordinates in mm. A rectilinear grid
  takes each axis' coordinates as given, so the focal stack's non-uniform z planes stay exact.
  Written by `pyevtk <https://github.com/pyscience-projects/pyevtk>`_ (``gridToVTK``): it writes
  the rectilinear grid format in one call from NumPy arrays, needs nothing but NumPy, and is a
  few hundred kB, where the ``vtk`` wheel (which reads the files back in the tests, as ParaView
  does) is over 100 MB; meshio only writes unstructured grids, one hexahedron per voxel.
* :func:`to_imagej`: a volume or focal stack as an ImageJ hyperstack TIFF (axes ZYX) written by
  tifffile, with the voxel size (x/y in the resolution tags, z as ``spacing``), the unit (mm)
  and the origin (``xorigin``/``yorigin``/``zorigin``, in voxels), so Fiji shows calibrated
  coordinates equal to ours. ImageJ knows only one z spacing: a non-uniform z axis (focal planes
  at constant magnification are not evenly spaced) is refused unless ``resample_z=True``, which
  interpolates linearly onto as many evenly spaced planes over the same z range and says so in
  the file's Info.

Axis order is kept as stored (index 0 = smallest coordinate, after sorting): ImageJ draws row 0
at the top, so its calibrated y (pointing down) equals ours.

Per-vector uncertainty: a PIV result's standard uncertainties ``unc_u``, ``unc_v``, ``unc_w``
(voxels) and ``unc_u_mm``, ``unc_v_mm``, ``unc_w_mm`` (:mod:`lfstudy.piv.uncertainty`; NaN for an
invalid or replaced vector) are VTK point data like every (z, y, x) variable. A TIFF of one PIV
component gets its uncertainty as a second channel (``u_mm`` and ``unc_u_mm``). A store written
before the uncertainty existed has no ``unc_*`` variable and exports as before, without them.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from lfstudy import io

__all__ = ["to_vtk", "to_imagej", "export_store", "uncertainty_of", "FORMATS"]

GRID_DIMS = ("z", "y", "x")
FORMATS = {".vtr": "vtk", ".tif": "tiff", ".tiff": "tiff"}
# Relative tolerance on spacings for an axis to count as uniform: coordinates are float64 from
# linspace/arange-like constructions, so real differences are far above this.
_UNIFORM_RTOL = 1e-6
# PIV components written as one 3-vector each (ParaView glyphs/streamlines need vectors).
_VECTORS = {"displacement": ("u", "v", "w"), "displacement_mm": ("u_mm", "v_mm", "w_mm")}


def _grid(obj: xr.Dataset | xr.DataArray, what: str) -> xr.Dataset | xr.DataArray:
    """``obj`` on (z, y, x) with 1-D coordinates, each axis ascending (raises ValueError if not)."""
    missing = [d for d in GRID_DIMS if d not in obj.dims]
    if missing:
        raise ValueError(f"{what} needs dimensions (z, y, x); it has ({', '.join(map(str, obj.dims))})")
    for d in GRID_DIMS:
        if d not in obj.coords or obj[d].ndim != 1:
            raise ValueError(f"{what} has no 1-D coordinate for dimension {d!r} (physical positions are needed)")
        c = np.asarray(obj[d].values, dtype=float)
        if not np.all(np.isfinite(c)) or (c.size > 1 and np.any(np.diff(np.sort(c)) == 0)):
            raise ValueError(f"{what}: coordinate {d!r} has repeated or non-finite values")
    # VTK and ImageJ both want increasing coordinates; sorting is a no-op for our stores.
    return obj.sortby(list(GRID_DIMS))


def _spacing(coord: xr.DataArray) -> float | None:
    """The constant spacing of an ascending coordinate, or None when it is not uniform."""
    c = np.asarray(coord.values, dtype=float)
    if c.size < 2:
        return 1.0  # a single plane has no spacing; ImageJ needs some positive number
    step = (c[-1] - c[0]) / (c.size - 1)
    return float(step) if np.allclose(np.diff(c), step, rtol=_UNIFORM_RTOL, atol=0) else None


def _vtk_array(a: xr.DataArray) -> np.ndarray:
    """(z, y, x) data as the (x, y, z) array pyevtk writes (x fastest, as VTK stores points)."""
    v = np.asarray(a.transpose(*GRID_DIMS).values)
    if v.dtype == bool:
        v = v.astype(np.uint8)  # VTK has no bool arrays
    elif v.dtype.kind not in "iuf":
        raise ValueError(f"variable {a.name!r} has dtype {v.dtype}, which VTK cannot store")
    # A transposed C-ordered array is Fortran-ordered: pyevtk writes it without copying twice.
    return v.transpose(2, 1, 0)


def to_vtk(obj: xr.Dataset | xr.DataArray, path: str | Path, *, variables: Sequence[str] | None = None) -> Path:
    """Write a PIV result or a volume as a VTK XML rectilinear grid (``.vtr``), atomically.

    Parameters
    ----------
    obj
        A Dataset (a PIV result: ``u``, ``v``, ``w``, ``u_mm`` ..., ``valid``, ``peak``) or a
        DataArray (volume, focal stack) over (z, y, x) with 1-D coordinates in mm. Data
        variables without exactly these dimensions (PIV per-pass diagnostics) are left out.
    path
        Output file; must end in ``.vtr`` (ParaView picks its reader by the extension).
    variables
        Only these data variables (default: every (z, y, x) variable).

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    Grid nodes are the window or voxel centres at their coordinates (point data), so ParaView
    shows values where they were measured. ``u, v, w`` and ``u_mm, v_mm, w_mm`` become the
    3-vectors ``displacement`` (voxels) and ``displacement_mm``; ``valid`` becomes 0/1 (uint8).
    Coordinates are in mm (VTK has no units).

    Raises
    ------
    ValueError
        No (z, y, x) grid with coordinates, no variable to write, or a wrong extension.
    """
    from pyevtk.hl import gridToVTK

    path = Path(path)
    if path.suffix != ".vtr":
        raise ValueError(f"VTK output {str(path)!r} must end in .vtr (a rectilinear grid)")
    ds = obj.to_dataset(name=obj.name or "data") if isinstance(obj, xr.DataArray) else obj
    ds = _grid(ds, "VTK export")
    names = [n for n in ds.data_vars if set(ds[n].dims) == set(GRID_DIMS)]
    if variables is not None:
        unknown = [v for v in variables if v not in names]
        if unknown:
            raise ValueError(f"no (z, y, x) variable {', '.join(map(repr, unknown))}; have {', '.join(names)}")
        names = [n for n in names if n in variables]
    if not names:
        raise ValueError("VTK export: no data variable over (z, y, x) to write")

    point_data: dict[str, np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for vec, comps in _VECTORS.items():
        if all(c in names for c in comps):
            arrays = [_vtk_array(ds[c]) for c in comps]
            # pyevtk writes vectors with one item size for all three components.
            dtype = np.result_type(*arrays)
            point_data[vec] = tuple(np.asfortranarray(a, dtype=dtype) for a in arrays)
            names = [n for n in names if n not in comps]
    for n in names:
        point_data[str(n)] = _vtk_array(ds[n])
    coords = [np.ascontiguousarray(ds[d].values, dtype=np.float64) for d in ("x", "y", "z")]

    with io.atomic_path(path) as tmp:
        # gridToVTK appends ".vtr" to the name it is given.
        written = Path(gridToVTK(str(tmp), *coords, pointData=point_data))
        try:
            os.replace(written, tmp)
        finally:
            written.unlink(missing_ok=True)
    return path


def uncertainty_of(name: str, available: Sequence[str]) -> str | None:
    """The name of the standard-uncertainty variable of PIV component ``name`` among ``available``.

    ``u`` → ``unc_u``, ``w_mm`` → ``unc_w_mm`` (:func:`lfstudy.piv.widim`'s names), or None when the
    variable is not a displacement component or the store holds no uncertainty for it (a store
    written before the per-vector uncertainty, or ``piv.uncertainty: none``).
    """
    base = name[: -len("_mm")] if name.endswith("_mm") else name
    if base not in ("u", "v", "w"):
        return None
    unc = f"unc_{name}"
    return unc if unc in available else None


def _imagej_stack(da: xr.DataArray, resample_z: bool) -> tuple[xr.DataArray, dict[str, float], dict[str, Any]]:
    """``da`` on (z, y, x) ready for ImageJ: its spacing per axis and the Info entries it adds."""
    da = _grid(da, "TIFF export")
    if set(da.dims) != set(GRID_DIMS):
        raise ValueError(f"TIFF export needs exactly (z, y, x); {da.name!r} has ({', '.join(map(str, da.dims))})")
    da = da.transpose(*GRID_DIMS)
    info: dict[str, Any] = {k: v for k, v in da.attrs.items() if isinstance(v, (str, int, float, bool, list))}
    spacing = {d: _spacing(da[d]) for d in GRID_DIMS}
    for d in ("x", "y"):
        if spacing[d] is None:
            raise ValueError(f"TIFF export: {d} is not evenly spaced; ImageJ stores one pixel size per axis")
    if spacing["z"] is None:
        z = np.asarray(da.z.values, dtype=float)
        dz = np.diff(z)
        if not resample_z:
            raise ValueError(
                f"TIFF export: the {z.size} z planes are not evenly spaced (steps {dz.min():.4g} .. {dz.max():.4g} mm) "
                "and ImageJ stores one z spacing; export to VTK (.vtr) to keep them, or resample (--resample-z)"
            )
        uniform = np.linspace(z[0], z[-1], z.size)
        da = da.astype(np.float64 if da.dtype == np.float64 else np.float32).interp(z=uniform, method="linear")
        spacing["z"] = float(uniform[1] - uniform[0])
        info["resampled_z"] = (
            f"linear interpolation from {z.size} planes (steps {dz.min():.6g} .. {dz.max():.6g} mm) "
            f"onto {z.size} evenly spaced planes"
        )
    return da, spacing, info  # type: ignore[return-value]


def _imagej_dtype(data: np.ndarray) -> np.ndarray:
    if data.dtype == bool:
        return data.astype(np.uint8)
    if data.dtype not in (np.uint8, np.uint16, np.float32):
        return data.astype(np.float32)
    return data


def _data_range(data: np.ndarray) -> tuple[float, float] | None:
    finite = data[np.isfinite(data)] if data.dtype.kind == "f" else data.ravel()
    return (float(finite.min()), float(finite.max())) if finite.size else None


def to_imagej(array: xr.DataArray | Sequence[xr.DataArray], path: str | Path, *, resample_z: bool = False) -> Path:
    """Write a volume or focal stack as an ImageJ/Fiji hyperstack TIFF with its voxel size, atomically.

    Parameters
    ----------
    array
        Data over (z, y, x) with 1-D coordinates in mm; x and y evenly spaced. A sequence of
        DataArrays on the same grid becomes the channels of one hyperstack (axes ZCYX): a PIV
        component and its standard uncertainty, say.
    path
        Output TIFF file.
    resample_z
        ImageJ has a single z spacing. With False (default) a non-uniform z axis is an error;
        with True the planes are interpolated linearly onto as many evenly spaced planes over
        the same z range (recorded in the file's Info).

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    float64 is stored as float32 (ImageJ has no 64-bit images) and bool as uint8; uint8 and
    uint16 are kept (channels share the dtype that holds all of them). The display range
    (``min``/``max``; per channel ``Ranges``) is the data range, NaN left out. The DataArray's
    attributes go into the ImageJ Info (Image > Show Info) as JSON; with channels, each under
    its name, with ``channels`` listing the names in order, which are also every plane's label.

    Raises
    ------
    ValueError
        Not a (z, y, x) grid with coordinates; x or y not evenly spaced; z not evenly spaced and
        ``resample_z`` False; channels on different grids.
    """
    import tifffile

    arrays = [array] if isinstance(array, xr.DataArray) else list(array)
    if not arrays or not all(isinstance(a, xr.DataArray) for a in arrays):
        raise ValueError("TIFF export writes DataArrays: one variable, or a sequence of them as channels")
    prepared = [_imagej_stack(a, resample_z) for a in arrays]
    da, spacing, info = prepared[0]
    for other, _, _ in prepared[1:]:
        for d in GRID_DIMS:
            if other.sizes[d] != da.sizes[d] or not np.allclose(other[d].values, da[d].values, rtol=1e-9, atol=0):
                raise ValueError(
                    f"TIFF export: channel {other.name!r} is not on the grid of {da.name!r} (coordinate {d!r}); "
                    "the channels of one hyperstack share their voxels"
                )
    if len(arrays) == 1:
        data = _imagej_dtype(np.asarray(da.values))
        axes = "ZYX"
    else:
        names = [str(a.name) for a, _, _ in prepared]
        info = {"channels": names, **{n: inf for n, (_, _, inf) in zip(names, prepared)}}
        chans = [_imagej_dtype(np.asarray(a.values)) for a, _, _ in prepared]
        dtype = np.result_type(*chans)
        if dtype not in (np.uint8, np.uint16, np.float32):
            dtype = np.float32
        data = np.stack([c.astype(dtype, copy=False) for c in chans], axis=1)  # (z, c, y, x)
        axes = "ZCYX"
    origin = {d: float(da[d].values[0]) for d in GRID_DIMS}
    metadata: dict[str, Any] = {
        "axes": axes,
        "spacing": spacing["z"],
        "unit": "mm",
        # ImageJ's calibrated position is (index - origin) * pixel size: origin in voxels.
        "xorigin": -origin["x"] / spacing["x"],
        "yorigin": -origin["y"] / spacing["y"],
        "zorigin": -origin["z"] / spacing["z"],
        "Info": json.dumps(info, sort_keys=True, default=str),
    }
    if axes == "ZYX":
        rng = _data_range(data)
        if rng is not None:
            metadata.update(min=rng[0], max=rng[1])
    else:
        ranges = [_data_range(data[:, k]) or (0.0, 1.0) for k in range(data.shape[1])]
        metadata.update(
            mode="grayscale",
            min=ranges[0][0],
            max=ranges[0][1],
            Ranges=[v for r in ranges for v in r],
            Labels=[n for _ in range(data.shape[0]) for n in info["channels"]],  # one per plane, z then c
        )
    path = Path(path)
    with io.atomic_path(path) as tmp:
        tifffile.imwrite(
            tmp,
            data,
            imagej=True,
            resolution=(1.0 / spacing["x"], 1.0 / spacing["y"]),
            metadata=metadata,
        )
    return path


def export_store(
    store: str | Path,
    out: str | Path,
    *,
    fmt: str | None = None,
    variables: Sequence[str] | None = None,
    resample_z: bool = False,
    uncertainty: bool = True,
) -> Path:
    """Export a zarr store (PIV result, volume, focal stack) to VTK or ImageJ TIFF.

    Parameters
    ----------
    store
        A store written by the workflow (``piv.zarr``, ``volume_a.zarr``, ``stack_a.zarr`` ...).
    out
        Output file: ``.vtr`` (VTK) or ``.tif``/``.tiff`` (ImageJ).
    fmt
        ``"vtk"`` or ``"tiff"``; default from the extension of ``out`` (which must agree).
    variables
        Data variables to write. VTK: default every (z, y, x) variable (a PIV result's
        ``unc_*`` uncertainties among them). TIFF: default the store's only variable, else name
        one; several become the channels of one hyperstack.
    resample_z
        TIFF only: interpolate a non-uniform z axis onto evenly spaced planes (see
        :func:`to_imagej`).
    uncertainty
        TIFF of one PIV component (``u``, ``w_mm`` ...): add its standard uncertainty
        (:func:`uncertainty_of`) as a second channel when the store holds it. A store without
        one (written before the per-vector uncertainty) gives the single channel.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    FileNotFoundError
        The store does not exist.
    ValueError
        Unknown or mismatched format, a variable the store lacks, or data that cannot be
        exported as asked.
    """
    out = Path(out)
    by_suffix = FORMATS.get(out.suffix.lower())
    if fmt is None:
        if by_suffix is None:
            raise ValueError(f"cannot tell the format from {out.name!r}: use .vtr (VTK) or .tif (ImageJ TIFF)")
        fmt = by_suffix
    if fmt not in ("vtk", "tiff"):
        raise ValueError(f"unknown format {fmt!r}: vtk or tiff")
    if by_suffix != fmt:
        want = ".vtr" if fmt == "vtk" else ".tif or .tiff"
        raise ValueError(f"{fmt} output {str(out)!r} must end in {want}")
    ds = io.open_zarr(store)
    for v in variables or ():
        if v not in ds.data_vars:
            raise ValueError(f"store {str(store)!r} has no variable {v!r}; it has {', '.join(map(str, ds.data_vars))}")
    if fmt == "vtk":
        return to_vtk(ds, out, variables=variables)
    names = list(dict.fromkeys(variables)) if variables else []
    if not names:
        names = list(ds.data_vars)
        if len(names) != 1:
            raise ValueError(
                f"store {str(store)!r} holds {len(names)} variables ({', '.join(map(str, names))}); "
                "name the one to write as TIFF (lfstudy export --var NAME)"
            )
    if uncertainty and len(names) == 1:
        unc = uncertainty_of(str(names[0]), [str(v) for v in ds.data_vars])
        if unc is not None:
            names.append(unc)
    if len(names) == 1:
        return to_imagej(ds[names[0]], out, resample_z=resample_z)
    return to_imagej([ds[n] for n in names], out, resample_z=resample_z)
