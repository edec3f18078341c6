"""I/O at the edges: zarr v3 stores written atomically, TIFF images, provenance.

Every store is written to a temporary sibling path and renamed into place, so
an interrupted job never leaves a half-written store behind; readers open
stores lazily (dask-backed).
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from lfstudy.safe_output import MARKER, OutputError, atomic_path, check_output, clear_stale, output_dir, output_marker

__all__ = [
    "provenance",
    "atomic_path",
    "clear_stale",
    "output_dir",
    "check_output",
    "output_marker",
    "OutputError",
    "MARKER",
    "write_zarr",
    "open_zarr",
    "open_array",
    "open_study",
    "read_image",
    "write_tiff",
    "read_tiff",
]


def provenance(params: Mapping[str, Any] | None = None, seed: int | None = None) -> dict[str, Any]:
    """Attributes recording the package version, the case parameters and the seed."""
    from lfstudy import __version__

    attrs: dict[str, Any] = {"lfstudy_version": __version__}
    if params is not None:
        attrs["parameters"] = json.dumps(params, sort_keys=True, default=str)
    if seed is not None:
        attrs["seed"] = int(seed)
    return attrs


def _jsonable_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    out = {}
    for k, v in attrs.items():
        if isinstance(v, (np.generic,)):
            v = v.item()
        elif isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, (tuple,)):
            v = list(v)
        elif not isinstance(v, (str, int, float, bool, list, dict, type(None))):
            v = str(v)
        out[k] = v
    return out


def write_zarr(
    obj: xr.DataArray | xr.Dataset,
    path: str | Path,
    *,
    name: str | None = None,
    compressor_level: int = 3,
    progress: bool = False,
) -> Path:
    """Write a DataArray/Dataset to a zarr v3 store atomically.

    Compression uses zstd via ``encoding={var: {"compressors": [...]}}`` (the
    zarr v3 spelling, not ``compressor``). Dask-backed data are computed chunk
    by chunk while writing (optionally with a progress bar).
    """
    from zarr.codecs import ZstdCodec

    ds = obj.to_dataset(name=name or obj.name or "data") if isinstance(obj, xr.DataArray) else obj
    ds = _variable_length_strings(ds.copy())
    ds.attrs = _jsonable_attrs(ds.attrs)
    for v in ds.variables.values():
        v.attrs = _jsonable_attrs(v.attrs)
        # Encodings inherited from a store we read (its zarr chunks) would clash
        # with the dask chunks of what we computed; chunking follows dask.
        v.encoding = {}
    encoding = {v: {"compressors": [ZstdCodec(level=compressor_level)]} for v in ds.data_vars}
    # Every chunk is written, even one all fill value (NaN: invalid vectors), and the store says so:
    # a chunk missing from such a store is damage, which open_zarr reports instead of NaN data.
    ds.attrs[_EVERY_CHUNK] = 1
    path = Path(path)
    # Consolidated metadata: readers (xarray, a notebook) open the store from one file, without
    # listing its directory (where Snakemake drops a .snakemake_timestamp) or warning. zarr-python
    # warns that v3 has no spec for it yet; it reads it back, so the warning is silenced here.
    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Cc]onsolidated metadata.*")
        if progress:
            from dask.diagnostics import ProgressBar

            with ProgressBar():
                ds.to_zarr(tmp, mode="w", encoding=encoding, zarr_format=3, consolidated=True, write_empty_chunks=True)
        else:
            ds.to_zarr(tmp, mode="w", encoding=encoding, zarr_format=3, consolidated=True, write_empty_chunks=True)
    return path


def _variable_length_strings(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` with its fixed-width strings (numpy ``<U``) as Python strings.

    zarr 3 stores ``<U`` arrays as ``FixedLengthUTF32``, a data type without a Zarr v3 specification (zarr warns
    that other libraries may not read it); object strings become the specified variable-length ``string``.
    :func:`open_zarr` turns them back into ``<U``.
    """
    fixed = {k: v for k, v in ds.variables.items() if v.dtype.kind == "U"}
    if not fixed:
        return ds
    new = {k: v.copy(data=np.asarray(v.values, dtype=object)) for k, v in fixed.items()}
    coords = {k: v for k, v in new.items() if k in ds.coords}
    return ds.assign_coords(coords).assign({k: v for k, v in new.items() if k not in coords})


def _fixed_width_strings(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` with the variable-length strings zarr reads (numpy ``StringDType``) as ``<U``: the dtype they were
    written from (:func:`_variable_length_strings`), which the rest of the code and xarray's indexes expect.
    Strings are labels, small: they are read here."""
    var = {k: v for k, v in ds.variables.items() if v.dtype.kind == "T"}
    if not var:
        return ds
    new = {k: v.copy(data=np.asarray(v.values, dtype=object).astype(str)) for k, v in var.items()}
    coords = {k: v for k, v in new.items() if k in ds.coords}
    return ds.assign_coords(coords).assign({k: v for k, v in new.items() if k not in coords})


#: Root attribute of a store whose every chunk :func:`write_zarr` wrote (stores of older versions lack it).
_EVERY_CHUNK = "lfstudy_every_chunk_written"


def _missing_chunks(path: Path) -> tuple[str, int, int] | None:
    """The first array of a store with chunks missing: (name, missing, total); None if complete."""
    import zarr

    group = zarr.open_group(path, mode="r")
    for name, arr in sorted(group.arrays()):
        missing = arr.nchunks - arr.nchunks_initialized
        if missing:
            return name, missing, arr.nchunks
    return None


def open_zarr(path: str | Path, *, name: str | None = None) -> xr.Dataset | xr.DataArray:
    """Open a store lazily (dask). With ``name``, return that variable as a DataArray.

    Raises
    ------
    FileNotFoundError
        The store does not exist.
    ValueError
        The store cannot be read, lacks chunks :func:`write_zarr` wrote (damaged: zarr
        would read them as fill values, NaN), or has no variable ``name``.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"zarr store {str(path)!r} does not exist")
    try:
        with warnings.catch_warnings():
            # stores written before consolidated metadata: read them without it, quietly
            # (Snakemake drops a .snakemake_timestamp file into directory() outputs)
            warnings.filterwarnings("ignore", message=".*snakemake_timestamp.*")
            warnings.filterwarnings("ignore", message=".*consolidated metadata.*")
            ds = xr.open_zarr(path, zarr_format=3, consolidated=None)
    except Exception as exc:  # a damaged store: say which, not a traceback from deep in zarr
        raise ValueError(
            f"zarr store {str(path)!r} cannot be read ({type(exc).__name__}: {exc}); it is damaged or not a "
            "zarr v3 store: delete it and run again to remake it"
        ) from None
    if ds.attrs.pop(_EVERY_CHUNK, None):
        gap = _missing_chunks(path)
        if gap is not None:
            var, missing, total = gap
            raise ValueError(
                f"zarr store {str(path)!r} is damaged: variable {var!r} lacks {missing} of its {total} chunk files "
                "(deleted or lost; zarr would read them as fill values, NaN); delete the store and run again to "
                "remake it"
            )
    ds = _fixed_width_strings(ds)
    if name is not None and name not in ds:
        raise ValueError(f"zarr store {str(path)!r} has no variable {name!r} (it holds {', '.join(ds.data_vars)})")
    return ds[name] if name is not None else ds


def open_array(path: str | Path) -> xr.DataArray:
    """Open the one data variable of a store lazily (a raw image, light field, stack or volume).

    Raises
    ------
    FileNotFoundError
        The store does not exist.
    ValueError
        The store holds no data variable, or several (then name one with
        :func:`open_zarr`).
    """
    ds = open_zarr(path)
    names = list(ds.data_vars)
    if len(names) != 1:
        raise ValueError(
            f"zarr store {str(path)!r} holds {len(names)} data variables ({', '.join(names) or 'none'}); "
            "expected exactly one"
        )
    return ds[names[0]]


def read_image(path: str | Path) -> xr.DataArray:
    """Read a 2-D image from a TIFF file or a zarr store (its ``intensity`` variable), eagerly.

    TIFF pixel data come back as a DataArray ``intensity`` over (``row``,
    ``col``) with the JSON metadata of :func:`write_tiff` (if any) as attrs.
    """
    path = Path(path)
    if path.is_dir() and not path.name.endswith(".zarr") and not (path / "zarr.json").exists():
        raise ValueError(f"image file {str(path)!r} is a folder, not a TIFF image or a zarr store")
    if path.name.endswith(".zarr") or path.is_dir():
        return open_zarr(path, name="intensity").load()
    if not path.exists():
        raise FileNotFoundError(f"image file {str(path)!r} does not exist")
    data, meta = read_tiff(path)
    if data.ndim != 2:
        raise ValueError(f"image file {str(path)!r}: expected one 2-D image, got an array of shape {data.shape}")
    return xr.DataArray(data, dims=("row", "col"), name="intensity", attrs=meta)


def open_study(path: str | Path) -> xr.DataTree:
    """A finished (or running) study as one lazy xarray DataTree.

    The root holds the study table (``study.zarr``: one dimension per swept
    setting); below it the tree mirrors the results directory: every store
    ``<stage id>/<name>.zarr`` is the node ``<stage id>/<name>`` (a case id's
    segments are nested groups, so ``tree["mag~-1/fnum~matched/.../flow~uniform_x/piv"]``
    is a case's vector field) and the shared calibrations sit under ``calib``.
    Every variable is dask-backed: nothing is read until used.

    Parameters
    ----------
    path : path
        ``results/<study name>`` (the directory holding ``study.zarr``).

    Raises
    ------
    FileNotFoundError
        The directory holds no ``study.zarr``.

    Examples
    --------
    A results directory with a two-row study table and one case's vector field:

    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np, xarray as xr
    >>> from lfstudy import io
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     table = xr.Dataset({"rms_total": ("ppp", [0.21, 0.34])}, coords={"ppp": [0.002, 0.004]})
    ...     _ = io.write_zarr(table, Path(tmp) / "study.zarr")
    ...     piv = xr.Dataset({"u": (("z", "y", "x"), np.zeros((2, 3, 4)))})
    ...     _ = io.write_zarr(piv, Path(tmp) / "ppp~0.002" / "piv.zarr")
    ...     tree = io.open_study(tmp)
    ...     print(tree.groups)
    ...     print(tree["rms_total"].values, tree["ppp~0.002/piv"]["u"].shape)
    ('/', '/ppp~0.002', '/ppp~0.002/piv')
    [0.21 0.34] (2, 3, 4)
    """
    root = Path(path)
    if not (root / "study.zarr").exists():
        raise FileNotFoundError(f"{str(root)!r} holds no study.zarr: is it results/<study name> of a finished run?")
    nodes: dict[str, xr.Dataset] = {"/": open_zarr(root / "study.zarr")}
    for store in sorted(root.rglob("*.zarr")):
        rel = store.relative_to(root)
        if rel.parts[0] in ("logs", "benchmarks") or rel.as_posix() == "study.zarr":
            continue
        nodes["/" + rel.with_suffix("").as_posix()] = open_zarr(store)
    return xr.DataTree.from_dict(nodes)


def write_tiff(
    image: xr.DataArray | np.ndarray,
    path: str | Path,
    *,
    metadata: Mapping[str, Any] | None = None,
    dtype: str | None = None,
) -> Path:
    """Write a 2-D image (or stack) to TIFF atomically, with JSON metadata.

    The DataArray's attrs (camera parameters, seed...) go into the TIFF's
    ImageDescription as JSON so Fiji/ImageJ users and ``read_tiff`` see them.
    """
    import tifffile

    data = image.values if isinstance(image, xr.DataArray) else np.asarray(image)
    meta = dict(image.attrs) if isinstance(image, xr.DataArray) else {}
    meta.update(metadata or {})
    if dtype is not None:
        data = data.astype(dtype)
    path = Path(path)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, data, description=json.dumps(_jsonable_attrs(meta)), metadata=None)
    return path


def read_tiff(path: str | Path) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a TIFF image and the JSON metadata written by :func:`write_tiff` (if any)."""
    import tifffile

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"image file {str(path)!r} does not exist")
    if path.is_dir():  # not "[Errno 21] Is a directory"
        raise ValueError(f"image file {str(path)!r} is a folder, not a TIFF image")
    try:
        with tifffile.TiffFile(path) as tf:
            data = tf.asarray()
            desc = tf.pages[0].description if tf.pages else ""
    except (ValueError, OSError, IndexError) as exc:  # tifffile's errors for truncated or foreign files
        raise ValueError(
            f"image file {str(path)!r} cannot be read as a TIFF image ({exc}): truncated or not a TIFF"
        ) from None
    try:
        meta = json.loads(desc) if desc else {}
    except json.JSONDecodeError:
        meta = {"description": desc}
    return data, meta
