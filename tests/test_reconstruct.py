"""Threshold + dilation reconstruction (sec. 5.5), the method registry and the render CLI."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from lfstudy.reconstruct import available_methods, disk, reconstruct, register_method, unregister_method


def _stack(values: np.ndarray) -> xr.DataArray:
    nz, ny, nx = values.shape
    mm = {"units": "mm"}
    return xr.DataArray(
        values,
        dims=("z", "y", "x"),
        name="intensity",
        coords={
            "z": ("z", np.arange(nz) * 1.0, mm),
            "y": ("y", np.arange(ny) * 0.125, mm),
            "x": ("x", np.arange(nx) * 0.125, mm),
        },
        attrs={"units": "counts"},
    )


def test_threshold_dilation_hand_computed():
    v = np.zeros((2, 5, 5))
    v[0, 2, 2] = 100.0  # one bright voxel
    v[0, 2, 3] = 1.0  # dim neighbour: kept by the dilation
    v[0, 0, 0] = 1.0  # dim, not adjacent: removed
    v[1, 1, 1] = 2.0  # dim voxel on the other plane: removed (2-D dilation per plane)
    st = _stack(v)
    mu, sd = v.mean(), v.std()
    thr = mu + 3 * sd
    assert 2.0 < thr < 100.0
    out = reconstruct(st, k=3.0, dilation_radius=1)
    expect = np.zeros_like(v)
    expect[0, 2, 2], expect[0, 2, 3] = 100.0, 1.0
    np.testing.assert_array_equal(out.values, expect)
    # The radius-1 disk is the plus-shaped footprint: 5 voxels in plane 0.
    assert out.attrs["kept_fraction"] == pytest.approx(5 / v.size)
    assert out.attrs["threshold"] == pytest.approx(thr)
    assert out.attrs["k"] == 3.0 and out.attrs["method"] == "threshold"
    assert out.dims == ("z", "y", "x") and out.chunks[0] == (1, 1)
    xr.testing.assert_identical(out["x"], st["x"])
    # No dilation: only the bright voxel; k = 0 keeps everything above the mean.
    assert reconstruct(st, k=3.0, dilation_radius=0).values.sum() == 100.0
    assert (reconstruct(st, k=0.0, dilation_radius=0).values > 0).sum() == (v > mu).sum()
    # 3-D ball dilation reaches the next plane.
    v3 = v.copy()
    v3[1, 2, 2] = 3.0
    assert reconstruct(_stack(v3), dilation_ndim=3).values[1, 2, 2] == 3.0


def test_none_method_keeps_the_stack():
    v = np.random.default_rng(0).random((3, 4, 5))
    st = _stack(v)
    out = reconstruct(st, method="none")
    np.testing.assert_array_equal(out.values, v)
    assert out.attrs["method"] == "none" and out.chunks[0] == (1, 1, 1)
    xr.testing.assert_identical(out["z"], st["z"])


def test_config_rejects_unknown_method():
    from lfstudy.config import ConfigError
    from lfstudy.study.config import validate_config

    with pytest.raises(ConfigError, match=r"reconstruct\.method.*'nosuch'.*deconvolution.*mart.*threshold"):
        validate_config({"camera": {}, "reconstruct": {"method": "nosuch"}})


def test_disk_footprints():
    assert disk(1).sum() == 5 and disk(2).sum() == 13 and disk(1, 3).sum() == 7


def test_registry_and_unknown_method():
    assert {"threshold", "none", "mart", "deconvolution"} <= set(available_methods())

    @register_method("identity-test")
    def identity(stack, scale=1.0):
        return stack * scale

    try:
        st = _stack(np.ones((1, 2, 2)))
        assert float(reconstruct(st, "identity-test", scale=2.0).sum()) == 8.0
        assert "identity-test" in available_methods()
        with pytest.raises(ValueError, match=r"unknown parameter\(s\) sclae; allowed: scale"):
            reconstruct(st, "identity-test", sclae=2.0)
    finally:
        unregister_method("identity-test")
    assert "identity-test" not in available_methods()
    with pytest.raises(ValueError, match=r"unknown reconstruction method; available: deconvolution, ipr, mart, none"):
        reconstruct(st, method="nosuch")


def test_cli_render(tmp_path, capsys):
    from lfstudy import io
    from lfstudy.cli import main
    from lfstudy.lightfield.calibrate import synthetic_pinhole
    from lfstudy.optics import PlenopticCamera

    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "name: t\nseed: 1\ncamera:\n  sensor: {n_pixels_x: 340, n_pixels_y: 272, pixel_pitch: 0.0074}\n"
        "  lenslet: {pitch: 0.125, focal_length: 0.5}\n  main_lens: {focal_length: 50.0, fnumber: matched}\n"
        "  magnification: -1.0\nrefocus: {n_planes: 8}\n"
    )
    cam = PlenopticCamera(340, 272, 0.0074, 0.125, 0.5, 50.0, -1.0)
    pin = io.write_tiff(synthetic_pinhole(cam, amplitude=3000), tmp_path / "pin.tif", dtype="float32")
    assert main(["calibrate", str(pin), "--config", str(cfg), "--out", str(tmp_path / "cen.zarr")]) == 0
    raw = np.random.default_rng(0).poisson(5.0, (272, 340)).astype("float32")
    tif = io.write_tiff(raw, tmp_path / "raw.tif")
    out = tmp_path / "out"
    assert (
        main(["render", str(tif), "--centers", str(tmp_path / "cen.zarr"), "--config", str(cfg), "--out", str(out)])
        == 0
    )
    for name in ("lightfield.zarr", "stack.zarr", "volume.zarr"):
        assert (out / name).exists()
    vol = io.open_zarr(out / "volume.zarr", name="intensity")
    z = vol["z"].values  # the reconstruction grid: uniform z over the depth of the 8 refocus planes
    planes = cam.focal_planes(8)["z"].values
    assert vol.dims == ("z", "y", "x") and np.allclose(np.diff(z), z[1] - z[0])
    assert planes.min() - 1e-9 <= z[0] < planes.min() + (z[1] - z[0]) and z[-1] <= planes.max() + 1e-9
    assert "threshold" in vol.attrs and "kept" in capsys.readouterr().out
