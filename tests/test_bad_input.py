"""Bad input: one clear line naming the file or setting and what was expected, through the CLI
(exit status 2, no traceback) and through the Python API, and no half-written output."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from lfstudy import io
from lfstudy.config import ConfigError
from lfstudy.lightfield import find_lenslet_centers, register, synthetic_pinhole
from lfstudy.optics import PlenopticCamera
from lfstudy.piv import widim
from lfstudy.simulate import RaytraceError, make_field, render
from lfstudy.study.config import load_config, validate_config

ROOT = Path(__file__).resolve().parents[1]
CAM = PlenopticCamera(160, 120, 0.0074, 0.0888, 0.3552, 50.0, -1.0)
CFG_TEXT = """name: bad
camera:
  sensor: {n_pixels_x: 160, n_pixels_y: 120, pixel_pitch: 0.0074}
  lenslet: {pitch: 0.0888, fnumber: 4.0}
  main_lens: {focal_length: 50.0}
  magnification: -1.0
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    (d / "c.yaml").write_text(CFG_TEXT)
    pin = synthetic_pinhole(CAM, amplitude=3000, seed=1)
    io.write_tiff(pin, d / "pin.tif", dtype="float32")
    io.write_zarr(find_lenslet_centers(pin, CAM), d / "cen.zarr")
    good = np.random.default_rng(0).poisson(5.0, (120, 160)).astype("float32")
    io.write_tiff(good, d / "raw.tif")
    io.write_zarr(io.read_image(d / "raw.tif"), d / "raw.zarr", name="intensity")
    blob = (d / "raw.tif").read_bytes()
    (d / "truncated.tif").write_bytes(blob[: len(blob) // 2])
    (d / "text.tif").write_text("not an image")
    io.write_tiff(np.zeros((120, 200), "float32"), d / "wide.tif")
    nan = good.copy()
    nan[5, 7] = np.nan
    io.write_tiff(nan, d / "nan.tif")
    io.write_tiff(good - 10.0, d / "negative.tif")
    io.write_tiff(np.zeros_like(good), d / "zero.tif")
    v = np.random.default_rng(1).random((16, 24, 24)).astype("float32")
    io.write_tiff(v, d / "vol_a.tif")
    io.write_tiff(v[:, :, :20], d / "vol_b.tif")
    io.write_tiff(v, d / "vol_c.tif")
    return d


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ("truncated.tif", r"truncated\.tif.*cannot be read as a TIFF image.*truncated or not a TIFF"),
        ("text.tif", r"text\.tif.*cannot be read as a TIFF image"),
        ("missing.tif", r"missing\.tif.*does not exist"),
        ("wide.tif", r"raw image is 200 x 120 px .* but the camera sensor is 160 x 120 px"),
        ("nan.tif", r"1 non-finite \(NaN/inf\) pixels"),
        ("negative.tif", r"negative pixels.*counts >= 0"),
        ("zero.tif", r"all zero: nothing was recorded"),
    ],
)
def test_bad_raw_images(files, cli_error, tmp_path, raw, match):
    out = tmp_path / "out"
    line = cli_error(
        "render",
        str(files / raw),
        "--centers",
        str(files / "cen.zarr"),
        "--config",
        str(files / "c.yaml"),
        "--out",
        str(out),
    )
    assert re.search(match, line), line
    assert not out.exists() or not any(out.iterdir())  # nothing half-written
    # the same through the API
    cen = io.open_zarr(files / "cen.zarr").load()
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        register(io.read_image(files / raw), cen, CAM)


def test_bad_calibration_images(files, cli_error, tmp_path):
    line = cli_error("calibrate", str(files / "truncated.tif"), "--out", str(tmp_path / "c.zarr"))
    assert "truncated.tif" in line and "TIFF" in line
    line = cli_error("calibrate", str(files / "zero.tif"), "--out", str(tmp_path / "c.zarr"))
    assert "blank" in line
    line = cli_error(
        "calibrate",
        str(files / "wide.tif"),
        "--config",
        str(files / "c.yaml"),
        "--out",
        str(tmp_path / "c.zarr"),
    )
    assert "200 x 120 px" in line and "160 x 120 px" in line
    assert not (tmp_path / "c.zarr").exists()


def test_frames_of_different_shapes_and_windows_too_large(files, cli_error, tmp_path):
    line = cli_error("piv", str(files / "vol_a.tif"), str(files / "vol_b.tif"), "--out", str(tmp_path / "p.zarr"))
    assert "same shape" in line and "(16, 24, 24)" in line and "(16, 24, 20)" in line
    line = cli_error(
        "piv",
        str(files / "vol_a.tif"),
        str(files / "vol_c.tif"),
        "--window",
        "32",
        "16",
        "16",
        "--out",
        str(tmp_path / "p.zarr"),
    )
    assert "`window` 32 along axis 0 ('z') exceeds the domain size 16" in line
    assert not (tmp_path / "p.zarr").exists()
    a, _ = io.read_tiff(files / "vol_a.tif")  # the API raises the same messages
    with pytest.raises(ValueError, match="same shape"):
        widim(a, a[:, :, :20], window=8)
    with pytest.raises(ValueError, match="exceeds the domain size 16"):
        widim(a, a, window=(32, 16, 16))


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (
            lambda c: c.setdefault("raytrace", {}).update(rays_per_particle=0),
            r"raytrace\.rays_per_particle' = 0.*\[1, inf\)",
        ),
        (lambda c: c.setdefault("raytrace", {}).update(rays_per_particle=-5), r"raytrace\.rays_per_particle' = -5"),
        (
            lambda c: c.update(sweep={"flow": ["vortex"]}),
            r"sweep\.flow' = 'vortex': unknown flow; allowed values are 'uniform_x'",
        ),
        (lambda c: c.update(sweep={"ppp": []}), r"sweep\.ppp' = \[\]: give at least 1 value"),
        (lambda c: c.update(sweep={"piv.window": [[2, 8, 8]]}), r"piv\.window\.0' = 2.*\[4, inf\).*case piv\.window"),
        (
            lambda c: c.update(piv={"window": [16, 32, 32]}, sweep={"reconstruct.methd": ["mart"]}),
            r"sweep\.reconstruct\.methd': not a setting",
        ),
        (
            lambda c: c.setdefault("particles", {}).update(z_center=40.0),
            r"config key 'particles\.z_center' = 40\.0 .*outside the reconstruction grid's depth",
        ),
        (
            lambda c: c.update(piv={"particles": "ptv"}, depth_calibration={"enabled": False}),
            r"config key 'piv\.particles' = 'ptv' .*reconstruct\.method = 'threshold' fits none",
        ),
        (
            lambda c: c.update(piv={"particles": "ptv"}, reconstruct={"method": "ipr"}),
            r"config key 'depth_calibration\.enabled' = true .*not with piv\.particles = 'ptv'",
        ),
        (
            lambda c: c.update(piv={"particles": "paired"}, depth_calibration={"enabled": False}),
            r"config key 'piv\.particles' = 'paired' .*reconstruct\.method = 'threshold' fits none",
        ),
        (
            lambda c: c.update(piv={"particles": "paired"}, reconstruct={"method": "ipr"}),
            r"config key 'depth_calibration\.enabled' = true .*not with piv\.particles = 'paired'",
        ),
        (
            lambda c: c.update(reconstruct={"method": "ipr", "ipr": {"split": 11}}),
            r"config key 'reconstruct\.ipr\.split' = 11: allowed range is \[0, 10\]",
        ),
        (
            lambda c: c.update(piv={"particles": "ptv", "ptv_order": 3}),
            r"piv\.ptv_order' = 3",
        ),
        (
            lambda c: c.update(piv={"particles": "ptv", "ptv_model_box": 6}),
            r"piv\.ptv_model_box' = 6",
        ),
        (
            lambda c: c.update(piv={"particles": "ptv", "ptv_model_box": 0.5}),
            r"config key 'piv\.ptv_model_box' = 0\.5 .*at least the final window \(1 to 5 .*0 turns the term off",
        ),
        (
            lambda c: c["camera"]["sensor"].update(n_pixels_x=60000, n_pixels_y=60000),
            r"config key 'camera\.sensor'.*needs about .* GB .*more than this machine's",
        ),
    ],
)
def test_bad_configs(tmp_path, cli_error, edit, match):
    raw = yaml.safe_load(CFG_TEXT)
    edit(raw)
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(raw))
    line = cli_error("cases", str(path))
    assert re.search(match, line), line
    with pytest.raises(ConfigError, match=match):
        validate_config(raw)


def test_zero_or_negative_rays_in_the_api():
    field = make_field(np.zeros(1), np.zeros(1), np.zeros(1), np.ones(1))
    for n in (0, -3):
        with pytest.raises(RaytraceError, match=rf"rays_per_particle = {n}: must be an integer >= 1"):
            render(CAM, field, n, 1)


def test_store_deleted_or_damaged_between_stages(files, cli_error, tmp_path):
    cen = tmp_path / "cen.zarr"
    shutil.copytree(files / "cen.zarr", cen)
    raw = str(files / "raw.tif")
    args = ["render", raw, "--centers", str(cen), "--config", str(files / "c.yaml"), "--out", str(tmp_path / "o")]
    (cen / "zarr.json").write_text("{ not json")  # damaged
    line = cli_error(*args)
    assert "cen.zarr" in line and "cannot be read" in line and "delete it and run again" in line
    with pytest.raises(ValueError, match=r"cen\.zarr.*cannot be read"):
        io.open_zarr(cen)
    shutil.rmtree(cen)  # deleted
    line = cli_error(*args)
    assert "cen.zarr" in line and "does not exist" in line
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
    # a workflow stage reading it fails with exit 1, the message in its log, and writes nothing
    from lfstudy.study.config import expand_cases, stage_config
    from lfstudy.workflow import main as stage_main

    cfg = load_config(files / "c.yaml")
    sc = json.dumps(stage_config(cfg, expand_cases(cfg)[0], "register"))
    log, out = tmp_path / "register.log", tmp_path / "lf.zarr"
    raw_zarr = str(files / "raw.zarr")
    assert stage_main(["register", "--config", sc, "--log", str(log), raw_zarr, str(cen), str(out)]) == 1
    assert "cen.zarr' does not exist" in log.read_text() and not out.exists()
