"""lfstudy.io: the zarr stores' string labels."""

from __future__ import annotations

import json
import warnings

import numpy as np
import xarray as xr

from lfstudy import io


def test_string_labels_use_zarrs_specified_type_and_read_back_as_written(tmp_path):
    ds = xr.Dataset(
        {"err": ("component", np.arange(3.0)), "note": ("component", np.array(["ok", "edge", "ok"]))},
        coords={"component": np.array(["x", "y", "z"]), "axis": ("component", np.array(["u", "vv", "w"]))},
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # zarr's UnstableSpecificationWarning for fixed-width strings
        io.write_zarr(ds, tmp_path / "s.zarr")
    for var in ("component", "axis", "note"):
        meta = json.loads((tmp_path / "s.zarr" / var / "zarr.json").read_text())
        assert meta["data_type"] == "string", var
    back = io.open_zarr(tmp_path / "s.zarr")
    assert back.identical(ds)
    assert back["note"].dtype == ds["note"].dtype and back["component"].dtype.kind == "U"
    assert float(back["err"].sel(component="y")) == 1.0
