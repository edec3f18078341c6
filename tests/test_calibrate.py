"""Lenslet calibration (sec. 5.1): automatic grid detection and eq. 5.1 sub-pixel fits."""

from __future__ import annotations

import numpy as np
import pytest

from lfstudy import io
from lfstudy.lightfield.calibrate import (
    CalibrationError,
    expected_centers,
    find_lenslet_centers,
    lenslet_positions,
    synthetic_pinhole,
)
from lfstudy.optics import PlenopticCamera


def _camera(**kw) -> PlenopticCamera:
    # Table 4.3 optics on a small sensor: 16.9 px per lenslet.
    return PlenopticCamera(420, 340, 0.0074, 0.125, 0.5, 50.0, -1.0, **kw)


def _rms(ds, cam):
    ex, ey = expected_centers(cam)
    v = ds["valid"].values
    d = np.hypot(ds["cx"].values - ex, ds["cy"].values - ey)[v]
    return float(np.sqrt(np.mean(d**2)))


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"lenslet_rotation": 0.005, "lenslet_offset_x": 0.01},
        {"lenslet_rotation": -0.004, "lenslet_offset_y": -0.03},
    ],
)
def test_noisy_pinhole_centres_within_005_px(kw):
    cam = _camera(**kw)
    img = synthetic_pinhole(cam, amplitude=3000, background=20, read_noise=5, seed=3)
    ds = find_lenslet_centers(img, cam)
    assert ds["cx"].shape == (cam.n_lenslets_y, cam.n_lenslets_x)
    assert ds["valid"].mean() > 0.7  # edge spots off the sensor are flagged
    assert _rms(ds, cam) < 0.05
    assert ds.attrs["rotation"] == pytest.approx(cam.lenslet_rotation, abs=2e-4)
    s = (cam.si + cam.lenslet_focal_length) / cam.si
    assert ds.attrs["pitch_px"] == pytest.approx(cam.pixels_per_lenslet * s, rel=1e-3)
    # Spot centres convert back to the lenslet centres (eqs 5.2-5.5).
    lx, ly = lenslet_positions(ds, cam)
    tx, ty = cam.lenslet_centers()
    v = ds["valid"].values
    assert np.abs(lx - tx)[v].max() < 0.2 * cam.pixel_pitch
    assert np.abs(ly - ty)[v].max() < 0.2 * cam.pixel_pitch


def test_without_camera_and_dim_lenslets():
    cam = _camera(lenslet_rotation=0.005, lenslet_offset_x=0.01)
    img = synthetic_pinhole(cam, amplitude=3000, dim_fraction=0.05, seed=5)
    ds = find_lenslet_centers(img.values)  # plain array: no camera, no pixel pitch
    assert "x" not in ds
    ex, ey = expected_centers(cam)
    pts = np.column_stack([ex.ravel(), ey.ravel()])
    v = ds["valid"].values.ravel()
    got = np.column_stack([ds["cx"].values.ravel(), ds["cy"].values.ravel()])[v]
    d = np.min(np.hypot(*(got[:, None, :] - pts[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert np.sqrt(np.mean(d**2)) < 0.05
    # Dim lenslets (5-30 % amplitude) are flagged, not fitted as if bright.
    amp = ds["amplitude"].values.ravel()
    assert (amp[v] > 0.25 * np.median(amp[v])).all()
    assert (~ds["valid"].values).sum() > 0
    # Row 0 is the top: cy grows with lenslet_row, cx with lenslet_col.
    assert np.all(np.diff(ds["cy_lattice"].values, axis=0) > 0)
    assert np.all(np.diff(ds["cx_lattice"].values, axis=1) > 0)


def test_pixel_pitch_from_dataarray_coords():
    cam = _camera()
    ds = find_lenslet_centers(synthetic_pinhole(cam, seed=1))
    v = ds["valid"].values
    x = (ds["cx"].values + 0.5) * cam.pixel_pitch - cam.sensor_width / 2
    np.testing.assert_allclose(ds["x"].values[v], x[v], atol=1e-12)
    assert ds["x"].attrs["units"] == "mm" and ds["y"].values[0].mean() > 0  # y up


def test_bad_inputs():
    cam = _camera()
    rng = np.random.default_rng(0)
    with pytest.raises(CalibrationError, match=r"420 x 340.*100 x 90|100 x 90.*420 x 340"):
        find_lenslet_centers(np.ones((90, 100)), cam)
    with pytest.raises(ValueError, match="no lenslet grid"):
        find_lenslet_centers(rng.normal(100, 5, (340, 420)))
    with pytest.raises(ValueError, match="no lenslet grid"):
        find_lenslet_centers(rng.poisson(50, (340, 420)).astype(float), cam)
    with pytest.raises(ValueError, match="blank"):
        find_lenslet_centers(np.zeros((340, 420)))
    img = synthetic_pinhole(cam).values
    img[5, 7] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        find_lenslet_centers(img, cam)


def test_cli_calibrate(tmp_path, capsys):
    from lfstudy.cli import main

    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "name: t\nseed: 1\ncamera:\n  sensor: {n_pixels_x: 420, n_pixels_y: 340, pixel_pitch: 0.0074}\n"
        "  lenslet: {pitch: 0.125, focal_length: 0.5}\n  main_lens: {focal_length: 50.0, fnumber: matched}\n"
        "  magnification: -1.0\n"
    )
    cam = _camera()
    tif = io.write_tiff(synthetic_pinhole(cam, amplitude=3000, seed=2), tmp_path / "pin.tif", dtype="float32")
    out = tmp_path / "centres.zarr"
    assert main(["calibrate", str(tif), "--config", str(cfg), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "valid centres" in text and "px RMS" in text
    ds = io.open_zarr(out).load()
    assert _rms(ds, cam) < 0.05
    assert main(["calibrate", str(tif), "--out", str(tmp_path / "c2.zarr"), "--pixel-pitch", "0.0074"]) == 0
    bad = io.write_tiff(np.zeros((50, 60), "float32"), tmp_path / "blank.tif")
    assert main(["calibrate", str(bad), "--out", str(tmp_path / "c3.zarr")]) == 2
    assert "blank" in capsys.readouterr().err


def _disk_pinhole(cam: PlenopticCamera, n_rays: int, fnumber: float = 16.0, seed: int = 0) -> np.ndarray:
    """Ray-traced f/16 pinhole image (sec. 5.1): rays from random focal-plane points through a
    uniform aperture, thin lenslets focused at infinity. Spots are ~2 px aperture disks."""
    rng = np.random.default_rng(seed)
    si, fl, p = cam.si, cam.lenslet_focal_length, cam.lenslet_pitch
    xi = (rng.random(n_rays) - 0.5) * cam.sensor_width  # image of a random object point (z = 0)
    yi = (rng.random(n_rays) - 0.5) * cam.sensor_height
    r = cam.main_focal_length / fnumber / 2 * np.sqrt(rng.random(n_rays))
    a = 2 * np.pi * rng.random(n_rays)
    u, v = r * np.cos(a), r * np.sin(a)
    sx, sy = (xi - u) / si, (yi - v) / si
    cxg, cyg = cam.lenslet_centers()
    nly, nlx = cxg.shape
    c, s = np.cos(cam.lenslet_rotation), np.sin(cam.lenslet_rotation)
    dx, dy = xi - cam.lenslet_offset_x, yi - cam.lenslet_offset_y
    j = np.rint((c * dx + s * dy) / p + (nlx - 1) / 2).astype(int)
    i = np.rint((nly - 1) / 2 - (-s * dx + c * dy) / p).astype(int)
    ok = (j >= 0) & (j < nlx) & (i >= 0) & (i < nly)
    xs, ys = cxg[i[ok], j[ok]] + fl * sx[ok], cyg[i[ok], j[ok]] + fl * sy[ok]
    col = np.floor((xs + cam.sensor_width / 2) / cam.pixel_pitch).astype(int)
    row = np.floor((cam.sensor_height / 2 - ys) / cam.pixel_pitch).astype(int)
    ok = (col >= 0) & (col < cam.n_pixels_x) & (row >= 0) & (row < cam.n_pixels_y)
    img = np.bincount(row[ok] * cam.n_pixels_x + col[ok], minlength=cam.n_pixels_x * cam.n_pixels_y)
    return img.reshape(cam.n_pixels_y, cam.n_pixels_x).astype(float)


def test_raytraced_disk_spots_within_005_px():
    """Flat-topped aperture-disk spots: the centroid estimator is chosen and stays < 0.05 px."""
    cam = _camera(lenslet_rotation=0.005, lenslet_offset_x=0.01)
    img = _disk_pinhole(cam, 2_000_000, seed=4)
    ds = find_lenslet_centers(img, cam)
    assert ds.attrs["estimator"] == "centroid"
    assert _rms(ds, cam) < 0.05


def test_fit_start_points_are_replaced_as_a_pair():
    """A centroid far from its lattice point is replaced in both coordinates, judged by one
    distance (the second coordinate must not be tested against the first's replacement)."""
    from lfstudy.lightfield.calibrate import _start_points

    lc, lr = np.array([10.0, 20.0]), np.array([10.0, 20.0])
    ccx = np.array([14.0, 20.5])  # first: 4 px off in x only; second: close
    ccy = np.array([10.5, 20.5])
    x, y = _start_points(ccx, ccy, lc, lr, h=3.0)
    np.testing.assert_array_equal(x, [10.0, 20.5])
    np.testing.assert_array_equal(y, [10.0, 20.5])  # the old code kept 10.5 here
