"""Bad input: one clear line naming the file or setting and what was expected, through the CLI
(exit status 2, no traceback) and through the Python API, and no half-written output."""

from __future__ import annotations

import json
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr
import yaml

from lfstudy import io
from lfstudy.cli import main
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
piv: {window: [8, 8, 8], spacing: [4, 4, 4], levels: 1}  # fits the grid (24 x 10 x 14 voxels)
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
    assert str(files / raw) in line, line  # every one names the file
    assert not out.exists() or not any(out.iterdir())  # nothing half-written
    # the same through the API
    cen = io.open_zarr(files / "cen.zarr").load()
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        register(io.read_image(files / raw), cen, CAM)


def test_bad_calibration_images(files, cli_error, tmp_path):
    line = cli_error("calibrate", str(files / "truncated.tif"), "--out", str(tmp_path / "c.zarr"))
    assert "truncated.tif" in line and "TIFF" in line
    line = cli_error("calibrate", str(files / "zero.tif"), "--out", str(tmp_path / "c.zarr"))
    assert f"image file {str(files / 'zero.tif')!r}: image is blank" in line, line
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
            r"raytrace\.rays_per_particle' = 0.*\[1, 10000000\]",
        ),
        (
            lambda c: c.setdefault("raytrace", {}).update(rays_per_particle=10**8),
            r"raytrace\.rays_per_particle' = 100000000: allowed range is \[1, 10000000\]",
        ),
        (
            lambda c: c.update(piv={"window": [8, 16, 16]}),
            r"config key 'piv\.window' = \[8, 16, 16\] \(case .*\): 16 along y exceeds 10, 16 along x exceeds 14 "
            r"voxels of the reconstruction grid of 24 x 10 x 14 voxels \(z, y, x\); allowed range per axis is "
            r"z \[4, 24\], y \[4, 10\], x \[4, 14\]",
        ),
        (
            lambda c: c.update(piv={"window": [8, 8, 8], "spacing": [4, 4, 4], "levels": 5}),
            r"config key 'piv\.levels' = 5 \(case .*\): level 4 refines piv\.window \[8, 8, 8\] to \[2, 2, 2\], "
            r"below the 4 voxels a window needs; allowed range is \[1, 3\]",
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
            lambda c: c.update(piv={"unresolved_significance": 11}),
            r"config key 'piv\.unresolved_significance' = 11: allowed range is \[0, 10\]",
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
        validate_config(raw, piv_grid=True)


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


# ------------------------------------------------------------------ recordings (lfstudy process)
@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A recording of the small camera: a pinhole calibration image and two noise frames (PIV of noise
    runs to the end; these tests are about what the run says)."""
    d = tmp_path_factory.mktemp("recording")
    pin = synthetic_pinhole(CAM, amplitude=3000, seed=1)
    io.write_tiff(pin, d / "pin.tif", dtype="float32")
    rng = np.random.default_rng(2)
    for k in range(2):
        tifffile.imwrite(d / f"f{k}.tif", rng.poisson(50.0, (120, 160)).astype(np.uint16))
    tifffile.imwrite(d / "zero.tif", np.zeros((120, 160), np.uint16))
    signed = rng.poisson(50.0, (2, 120, 160)).astype(np.int16)
    signed[1, 3, 4:7] = -12  # an unsigned camera's counts above 32767 read as int16
    tifffile.imwrite(d / "signed_1.tif", signed[0])
    tifffile.imwrite(d / "signed_2.tif", signed[1])
    (d / "adir.tif").mkdir()
    return d


def _recording_config(d: Path, name: str, frames: dict, *, pitch: float = 0.0888, piv: dict | None = None) -> Path:
    cfg = yaml.safe_load(CFG_TEXT)
    cfg["name"] = name
    cfg["camera"]["lenslet"]["pitch"] = pitch
    if piv is not None:
        cfg["piv"] = piv
    cfg["recording"] = {"calibration": {"image": "pin.tif"}, "frames": frames}
    path = d / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_recorded_frames_name_their_file(recording, cli_error, tmp_path):
    """An all-zero frame and a signed frame with negative pixels: the error names the key and the file."""
    d = recording
    line = cli_error("process", str(_recording_config(d, "zero", {"pairs": [["f0.tif", "zero.tif"]]})))
    assert f"recording.frames: 'zero.tif' ({str(d / 'zero.tif')!r}) is all zero: nothing was recorded" in line, line
    line = cli_error("process", str(_recording_config(d, "signed", {"series": "signed_*.tif"})))
    assert (
        f"recording.frames: 'signed_2.tif' ({str(d / 'signed_2.tif')!r}) has 3 negative pixels (min -12, int16)" in line
    )
    assert "holds counts >= 0" in line, line
    assert not (Path("results") / "zero").exists() and not (Path("results") / "signed").exists()


def test_pitch_warning_is_printed_before_a_later_error(recording, capsys, tmp_path):
    """A lenslet pitch 10 % off calibrates with a warning; the warning is on stderr before the error that
    ends the run (here a blank frame read after the calibration), not lost with it."""
    cfg = _recording_config(recording, "pitch", {"pairs": [["f0.tif", "zero.tif"]]}, pitch=0.0977)
    assert main(["process", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 2, lines
    assert re.match(
        r"lfstudy process: warning: lenslet pitch 13\.2\d* px in the config differs .*\(\+10\.\d %\)", lines[0]
    )
    assert lines[1].startswith("lfstudy process: error: recording.frames: 'zero.tif'"), lines


@pytest.mark.parametrize(
    ("frames", "message"),
    [
        (
            {"series": ["f0.tif", "adir.tif"]},
            "recording.frames.series: '{d}/adir.tif' is a folder, not an image file; name the TIFF files in it",
        ),
        ({"series": []}, "config key 'recording.frames.series' = []: give at least 2 values"),
        (
            {"pairs": [["f0.tif", "f1.tif", "f0.tif"]]},
            "config key 'recording.frames.pairs.0' = ['f0.tif', 'f1.tif', 'f0.tif']: give exactly 2 values, not 3",
        ),
    ],
)
def test_recording_config_errors_say_what_is_wrong(recording, cli_error, frames, message):
    """Not "does not exist" for a folder, not "allowed: string or array" for a list."""
    line = cli_error("process", str(_recording_config(recording, "bad", frames)))
    assert message.format(d=recording) in line, line


def test_a_config_path_that_is_a_folder(recording, cli_error):
    for command in ("process", "cases"):
        line = cli_error(command, str(recording))
        assert line.endswith(f"config file {str(recording)!r} is a folder; give the YAML file in it"), line
        assert "Errno" not in line
    (recording / "c.yaml").write_text(CFG_TEXT)
    cfg, out = str(recording / "c.yaml"), str(recording / "out")
    line = cli_error("render", str(recording / "adir.tif"), "--centers", "c.zarr", "--config", cfg, "--out", out)
    assert line.endswith(f"image file {str(recording / 'adir.tif')!r} is a folder, not a TIFF image or a zarr store")


def test_a_piv_window_larger_than_the_grid_fails_before_calibration(recording, cli_error, capsys):
    cfg = _recording_config(recording, "window", {"pairs": [["f0.tif", "f1.tif"]]}, piv={"window": [8, 16, 16]})
    line = cli_error("process", str(cfg))
    assert (
        "config key 'piv.window' = [8, 16, 16]: 16 along y exceeds 10, 16 along x exceeds 14 voxels of the "
        "reconstruction grid of 24 x 10 x 14 voxels (z, y, x); allowed range per axis is z [4, 24], y [4, 10], "
        "x [4, 14]" in line
    ), line
    assert "calibration" not in capsys.readouterr().out  # nothing was processed


def test_duplicate_keys_in_a_recording_config(recording, cli_error):
    path = recording / "dup.yaml"
    text = _recording_config(recording, "dup", {"pairs": [["f0.tif", "f1.tif"]]}).read_text()
    path.write_text(text + "piv: {window: [4, 4, 4]}\n")
    first = 1 + next(k for k, ln in enumerate(text.splitlines()) if ln.startswith("piv:"))
    line = cli_error("process", str(path))
    n = len(text.splitlines()) + 1
    assert f"config file {str(path)!r}: key 'piv' is given twice (lines {first} and {n})" in line, line


def test_a_small_process_run_gives_no_runtime_warning(recording, tmp_path):
    """One vector per axis (the windows span the grid): every vector sits at the origin, where
    matplotlib's quiver divided by a zero step on every such run (RuntimeWarning at draw time)."""
    from lfstudy.process import load_process_config
    from lfstudy.study.case import case_grid

    cfg = _recording_config(recording, "one", {"pairs": [["f0.tif", "f1.tif"]]})
    shape = list(case_grid(load_process_config(cfg)).shape)
    cfg = _recording_config(
        recording, "one", {"pairs": [["f0.tif", "f1.tif"]]}, piv={"window": shape, "spacing": shape, "levels": 1}
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["process", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    assert (tmp_path / "o" / "report.html").is_file()
    piv = io.open_zarr(tmp_path / "o" / "piv.zarr")
    assert piv.sizes["x"] == piv.sizes["y"] == piv.sizes["z"] == 1 and float(abs(piv["x"]).max()) == 0.0
    runtime = [f"{w.filename}:{w.lineno}: {w.message}" for w in caught if issubclass(w.category, RuntimeWarning)]
    assert not runtime, runtime


def test_a_store_missing_chunks_says_damaged(files, cli_error, tmp_path):
    """Chunk files deleted from a volume: zarr would read them as NaN ("3072 non-finite voxels" from
    PIV); the store is named damaged, with the variable."""
    a, _ = io.read_tiff(files / "vol_a.tif")
    vol = xr.DataArray(a, dims=("z", "y", "x"), name="intensity").chunk({"z": 4})
    for name in ("a.zarr", "b.zarr"):
        io.write_zarr(vol, tmp_path / name)
    chunks = sorted((tmp_path / "b.zarr" / "intensity").rglob("c/*/*/*"))
    assert len(chunks) == 4
    chunks[1].unlink()
    out = tmp_path / "p.zarr"
    line = cli_error(
        "piv", str(tmp_path / "a.zarr"), str(tmp_path / "b.zarr"), "--window", "4", "8", "8", "--out", str(out)
    )
    assert (
        f"zarr store {str(tmp_path / 'b.zarr')!r} is damaged: variable 'intensity' lacks 1 of its 4 chunk files" in line
    ), line
    assert "non-finite" not in line and not out.exists()
    # a store whose chunks are all NaN (every vector invalid) is complete, not damaged
    nan = xr.DataArray(np.full((8, 8, 8), np.nan, "float32"), dims=("z", "y", "x"), name="u").chunk({"z": 4})
    io.write_zarr(nan, tmp_path / "nan.zarr")
    assert int(np.isnan(io.open_array(tmp_path / "nan.zarr").values).sum()) == 512
