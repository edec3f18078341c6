"""Export to VTK (ParaView) and ImageJ TIFF (Fiji): files read back by other readers with their
coordinates and voxel size intact."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
import xarray as xr
from PIL import Image
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkIOXML import vtkXMLRectilinearGridReader

from lfstudy import io
from lfstudy.cli import main
from lfstudy.export import export_store, to_imagej, to_vtk

# Focal planes at constant magnification are not evenly spaced in z; x and y are.
Z_PLANES = np.array([-3.05, -1.73, -0.35, 1.08, 2.59])


def _piv() -> xr.Dataset:
    """A PIV result shaped like the workflow's: (z, y, x) window centres in mm, a per-pass variable."""
    rng = np.random.default_rng(1)
    coords = {"z": Z_PLANES, "y": -1.4 + 0.355 * np.arange(6), "x": -1.9 + 0.355 * np.arange(7)}
    shape = (5, 6, 7)
    data = {n: (("z", "y", "x"), rng.normal(size=shape)) for n in ("u", "v", "w", "peak")}
    data.update({f"{n}_mm": (("z", "y", "x"), 0.0888 * data[n][1]) for n in "uvw"})
    data["valid"] = (("z", "y", "x"), rng.random(shape) > 0.2)
    data["corrector_rms"] = (("pass",), np.array([0.5, 0.1]))
    return xr.Dataset(data, coords={**coords, "pass": [1, 2]})


def _piv_unc() -> xr.Dataset:
    """The PIV result with per-vector standard uncertainties (widim's names), NaN for invalid vectors."""
    ds = _piv()
    rng = np.random.default_rng(3)
    valid = ds["valid"].values
    for n in "uvw":
        sigma = np.where(valid, rng.uniform(0.02, 0.3, valid.shape), np.nan)
        ds[f"unc_{n}"] = (("z", "y", "x"), sigma)
        ds[f"unc_{n}_mm"] = (("z", "y", "x"), 0.0888 * sigma)
    return ds


def _volume(z: np.ndarray) -> xr.DataArray:
    rng = np.random.default_rng(2)
    return xr.DataArray(
        rng.random((z.size, 8, 10), dtype=np.float32),
        dims=("z", "y", "x"),
        coords={"z": z, "y": -0.3 + 0.0888 * np.arange(8), "x": -0.44 + 0.0888 * np.arange(10)},
        name="intensity",
        attrs={"voxel_size": 0.0888, "method": "threshold"},
    )


def _read_vtr(path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Coordinates and point arrays of a .vtr file, read by VTK itself (ParaView's reader)."""
    reader = vtkXMLRectilinearGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    nx, ny, nz = grid.GetDimensions()
    coords = {
        "x": vtk_to_numpy(grid.GetXCoordinates()),
        "y": vtk_to_numpy(grid.GetYCoordinates()),
        "z": vtk_to_numpy(grid.GetZCoordinates()),
    }
    pd = grid.GetPointData()
    arrays = {}
    for i in range(pd.GetNumberOfArrays()):
        a = vtk_to_numpy(pd.GetArray(i))
        # VTK points run x fastest: back to (z, y, x) [, component].
        arrays[pd.GetArrayName(i)] = a.reshape((nz, ny, nx, *a.shape[1:]))
    return coords, arrays


def test_piv_to_vtk_reads_back_with_coordinates(tmp_path):
    ds = _piv()
    out = to_vtk(ds, tmp_path / "piv.vtr")
    coords, arrays = _read_vtr(out)
    for d in "xyz":
        np.testing.assert_array_equal(coords[d], ds[d].values)  # non-uniform z kept exactly
    assert set(arrays) == {"displacement", "displacement_mm", "valid", "peak"}  # per-pass variable left out
    for vec, comps in (("displacement", "uvw"), ("displacement_mm", ("u_mm", "v_mm", "w_mm"))):
        assert arrays[vec].shape == (5, 6, 7, 3)
        for k, c in enumerate(comps):
            np.testing.assert_array_equal(arrays[vec][..., k], ds[c].values)
    np.testing.assert_array_equal(arrays["valid"], ds["valid"].values.astype(np.uint8))
    np.testing.assert_array_equal(arrays["peak"], ds["peak"].values)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["piv.vtr"]  # no temporary file left


def test_piv_uncertainty_to_vtk_as_point_data(tmp_path):
    """σ of every component is a scalar of its own, NaN (invalid vectors) kept: ParaView thresholds on it."""
    ds = _piv_unc()
    _, arrays = _read_vtr(to_vtk(ds, tmp_path / "piv.vtr"))
    unc = {f"unc_{n}{s}" for n in "uvw" for s in ("", "_mm")}
    assert set(arrays) == {"displacement", "displacement_mm", "valid", "peak"} | unc
    for name in unc:
        np.testing.assert_array_equal(arrays[name], ds[name].values)  # NaN where NaN (equal_nan)
    assert np.isnan(arrays["unc_w_mm"][~ds["valid"].values]).all()
    assert np.isfinite(arrays["unc_w_mm"][ds["valid"].values]).all()


def test_volume_to_vtk_descending_axis_sorted(tmp_path):
    vol = _volume(Z_PLANES)
    flipped = vol.isel(y=slice(None, None, -1))  # stored descending: written ascending, values follow
    coords, arrays = _read_vtr(to_vtk(flipped, tmp_path / "vol.vtr"))
    np.testing.assert_array_equal(coords["y"], vol.y.values)
    np.testing.assert_array_equal(arrays["intensity"], vol.values)


def test_volume_to_imagej_keeps_voxel_size_and_origin(tmp_path):
    vol = _volume(-1.0 + 0.25 * np.arange(6))
    out = to_imagej(vol, tmp_path / "vol.tif")
    with tifffile.TiffFile(out) as tf:
        assert tf.is_imagej and tf.series[0].axes == "ZYX"
        data = tf.asarray()
        ij = tf.imagej_metadata
        xres = tf.pages[0].tags["XResolution"].value
        yres = tf.pages[0].tags["YResolution"].value
    np.testing.assert_array_equal(data, vol.values)
    dx, dy = xres[1] / xres[0], yres[1] / yres[0]
    assert ij["unit"] == "mm" and ij["spacing"] == pytest.approx(0.25, rel=1e-12)
    assert dx == pytest.approx(0.0888, rel=1e-9) and dy == pytest.approx(0.0888, rel=1e-9)
    # ImageJ's calibrated coordinate (index - origin) * size gives back ours.
    for d, step, n in (("x", dx, 10), ("y", dy, 8), ("z", ij["spacing"], 6)):
        np.testing.assert_allclose((np.arange(n) - ij[f"{d}origin"]) * step, vol[d].values, rtol=0, atol=1e-9)
    assert json.loads(ij["Info"])["method"] == "threshold"
    # An independent TIFF reader (Pillow) sees the same stack, pixel size and ImageJ header.
    with Image.open(out) as im:
        assert im.n_frames == 6 and im.size == (10, 8) and im.mode == "F"
        assert float(im.tag_v2[282]) == pytest.approx(1 / 0.0888, rel=1e-9)
        desc = im.tag_v2[270]
        im.seek(3)
        np.testing.assert_array_equal(np.asarray(im), vol.values[3])
    assert "spacing=0.25" in desc and "unit=mm" in desc


def test_imagej_refuses_or_resamples_non_uniform_z(tmp_path):
    vol = _volume(Z_PLANES)
    with pytest.raises(ValueError, match="not evenly spaced"):
        to_imagej(vol, tmp_path / "stack.tif")
    assert not (tmp_path / "stack.tif").exists()
    out = to_imagej(vol, tmp_path / "stack.tif", resample_z=True)
    with tifffile.TiffFile(out) as tf:
        data, ij = tf.asarray(), tf.imagej_metadata
    z = Z_PLANES[0] + np.arange(5) * ij["spacing"]
    np.testing.assert_allclose((np.arange(5) - ij["zorigin"]) * ij["spacing"], z, atol=1e-9)
    np.testing.assert_allclose(z[[0, -1]], Z_PLANES[[0, -1]], atol=1e-9)  # same z range
    np.testing.assert_allclose(data, vol.interp(z=z).values, rtol=1e-6)
    np.testing.assert_array_equal(data[0], vol.values[0])
    assert "resampled_z" in json.loads(ij["Info"])


def test_imagej_refuses_uneven_x(tmp_path):
    vol = _volume(-1.0 + 0.25 * np.arange(6))
    vol = vol.assign_coords(x=vol.x.values**3)
    with pytest.raises(ValueError, match="x is not evenly spaced"):
        to_imagej(vol, tmp_path / "v.tif")


def test_export_store_and_cli(tmp_path, capsys):
    io.write_zarr(_piv(), tmp_path / "piv.zarr")
    io.write_zarr(_volume(-1.0 + 0.25 * np.arange(6)), tmp_path / "volume.zarr")
    assert main(["export", str(tmp_path / "piv.zarr"), "--out", str(tmp_path / "out" / "piv.vtr")]) == 0
    assert main(["export", str(tmp_path / "volume.zarr"), "--out", str(tmp_path / "volume.tif")]) == 0
    _, arrays = _read_vtr(tmp_path / "out" / "piv.vtr")
    assert "displacement_mm" in arrays
    assert tifffile.imread(tmp_path / "volume.tif").shape == (6, 8, 10)
    # One PIV variable as TIFF: z of the PIV grid is the focal planes', so it needs resampling.
    export_store(tmp_path / "piv.zarr", tmp_path / "u.tif", variables=["u_mm"], resample_z=True)
    assert tifffile.imread(tmp_path / "u.tif").shape == (5, 6, 7)
    capsys.readouterr()
    bad = [
        (["export", str(tmp_path / "missing.zarr"), "--out", str(tmp_path / "m.vtr")], "does not exist"),
        (["export", str(tmp_path / "piv.zarr"), "--out", str(tmp_path / "p.tif")], "--var NAME"),
        (["export", str(tmp_path / "piv.zarr"), "--out", str(tmp_path / "p.vtk")], "use .vtr"),
        (["export", str(tmp_path / "piv.zarr"), "--out", str(tmp_path / "p.tif"), "--format", "vtk"], "end in .vtr"),
        (["export", str(tmp_path / "piv.zarr"), "--out", str(tmp_path / "p.vtr"), "--var", "nope"], "no variable"),
    ]
    for argv, message in bad:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("lfstudy export: error:") and message in err and err.count("\n") == 1, err


def test_tiff_of_a_component_carries_its_uncertainty_channel(tmp_path, capsys):
    """One PIV component as TIFF: a two-channel hyperstack (value, σ) that tifffile and Pillow read, with
    channel names and per-channel display ranges; --no-uncertainty and a store without σ give one channel."""
    ds = _piv_unc().assign_coords(z=-1.0 + 0.25 * np.arange(5))  # evenly spaced: no resampling
    io.write_zarr(ds, tmp_path / "piv.zarr")
    assert main(["export", str(tmp_path / "piv.zarr"), "--out", str(tmp_path / "w.tif"), "--var", "w_mm"]) == 0
    with tifffile.TiffFile(tmp_path / "w.tif") as tf:
        assert tf.is_imagej and tf.series[0].axes == "ZCYX"
        data, ij = tf.asarray(), tf.imagej_metadata
    assert data.shape == (5, 2, 6, 7) and ij["channels"] == 2
    np.testing.assert_array_equal(data[:, 0], ds["w_mm"].values.astype(np.float32))
    np.testing.assert_array_equal(data[:, 1], ds["unc_w_mm"].values.astype(np.float32))  # NaN kept
    assert json.loads(ij["Info"])["channels"] == ["w_mm", "unc_w_mm"]
    assert list(ij["Labels"][:4]) == ["w_mm", "unc_w_mm", "w_mm", "unc_w_mm"]
    sig = ds["unc_w_mm"].values
    np.testing.assert_allclose(ij["Ranges"][2:], [np.nanmin(sig), np.nanmax(sig)], rtol=1e-6)
    with Image.open(tmp_path / "w.tif") as im:
        assert im.n_frames == 10 and im.size == (7, 6)
        im.seek(1)  # plane z=0, channel 2
        np.testing.assert_array_equal(np.asarray(im), data[0, 1])
    # the voxel-unit component pairs with the voxel-unit σ; --no-uncertainty writes one channel
    export_store(tmp_path / "piv.zarr", tmp_path / "u.tif", variables=["u"])
    assert json.loads(tifffile.TiffFile(tmp_path / "u.tif").imagej_metadata["Info"])["channels"] == ["u", "unc_u"]
    argv = ["export", str(tmp_path / "piv.zarr"), "--out", str(tmp_path / "u1.tif"), "--var", "u", "--no-uncertainty"]
    assert main(argv) == 0
    assert tifffile.imread(tmp_path / "u1.tif").shape == (5, 6, 7)
    # several --var: channels in the order given
    export_store(tmp_path / "piv.zarr", tmp_path / "uv.tif", variables=["u_mm", "v_mm", "peak"])
    assert tifffile.imread(tmp_path / "uv.tif").shape == (5, 3, 6, 7)
    # a store written before the uncertainty existed: the component alone, no error
    old = ds[[v for v in ds.data_vars if not str(v).startswith("unc_")]]
    io.write_zarr(old, tmp_path / "old.zarr")
    export_store(tmp_path / "old.zarr", tmp_path / "old.tif", variables=["w_mm"])
    assert tifffile.imread(tmp_path / "old.tif").shape == (5, 6, 7)
    _, arrays = _read_vtr(export_store(tmp_path / "old.zarr", tmp_path / "old.vtr"))
    assert "displacement_mm" in arrays and not any(k.startswith("unc_") for k in arrays)
    # channels must share the grid
    with pytest.raises(ValueError, match="not on the grid"):
        to_imagej([ds["u_mm"], ds["v_mm"].isel(x=slice(1, None))], tmp_path / "bad.tif")
    capsys.readouterr()
