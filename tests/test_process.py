"""`lfstudy process` on a recording made by the simulator: noisy 12-bit TIFFs of the tiny test camera
with a rotated, offset lenslet grid, a fixed-pattern dark offset and dark frames, processed as if
recorded (the camera description knows nothing of the rotation or the offset).

Tolerances: the tiny study (tests/test_workflow.py) measures the same 0.1 mm (1.126 voxel) x shift
of the same camera to |bias| < 0.1 voxel with > 80 % valid vectors; a recording is held to the same.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
import yaml

from lfstudy import io
from lfstudy.cli import main
from lfstudy.study.config import load_config

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.yaml"
SHIFT_MM = 0.1  # per frame, in x
VOXEL_MM = 0.0888  # pitch / |M| of the tiny camera
DT = 0.002  # s between frames
FULL_12 = 4095


def _tags(full: int) -> list[tuple]:
    return [(281, "H", 1, full, True)]  # MaxSampleValue: a 12-bit camera's full scale in a 16-bit file


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> dict:
    """Pinhole image, two dark frames and three frames of a uniform x shift, as recorded TIFFs."""
    from lfstudy.optics import PlenopticCamera
    from lfstudy.simulate import displace, flow_from_config, render, render_pinhole
    from lfstudy.study.case import case_particles

    d = tmp_path_factory.mktemp("recording")
    cfg = load_config(TINY)
    cam_cfg = cfg["camera"]
    # the real lenslet array is rotated and offset; the camera description does not say so
    real = {**cfg, "camera": {**cam_cfg, "lenslet": {**cam_cfg["lenslet"], "rotation": 0.01, "offset_x": 0.021}}}
    real["camera"]["lenslet"]["offset_y"] = -0.013
    cam = PlenopticCamera.from_config(real)
    field = case_particles(real)
    rng = np.random.default_rng(5)
    pattern = 60.0 + rng.normal(0.0, 5.0, (cam.n_pixels_y, cam.n_pixels_x))  # fixed-pattern offset

    def record(expected: np.ndarray, gain: float) -> np.ndarray:
        counts = rng.poisson(expected * gain) + pattern + rng.normal(0.0, 2.0, expected.shape)
        return np.clip(np.rint(counts), 0, FULL_12).astype(np.uint16)

    pin = render_pinhole(cam, fnumber=16, count=20000, rays_per_point=30, seed=11, method="montecarlo").values
    pin12 = record(pin, 3000.0 / pin.max())
    tifffile.imwrite(d / "pinhole.tif", pin12, extratags=_tags(FULL_12))
    clean = []
    for k in range(3):
        moved = displace(field, flow_from_config({"kind": "uniform", "displacement": [SHIFT_MM * k, 0, 0]}), 1.0, 1)
        clean.append(render(cam, moved, 1500, 100 + k, method="montecarlo").values)
    # the brightest particle images clip at full scale, as in a real recording
    gain = 7000.0 / max(float(c.max()) for c in clean)
    frames = [record(c, gain) for c in clean]
    for k, f in enumerate(frames):
        tifffile.imwrite(d / f"frame_{k + 1}.tif", f, extratags=_tags(FULL_12))
    darks = [record(np.zeros_like(pin), 1.0) for _ in range(2)]
    for k, f in enumerate(darks):
        tifffile.imwrite(d / f"dark_{k + 1}.tif", f, extratags=_tags(FULL_12))
    # the same recording as 16-bit data: one multi-page stack of the frames, one of the darks
    tifffile.imwrite(d / "series16.tif", np.stack(frames) * 16, photometric="minisblack")
    tifffile.imwrite(d / "dark16.tif", np.stack(darks) * 16, photometric="minisblack")
    tifffile.imwrite(d / "pinhole16.tif", pin12 * 16)
    base = {"name": "rec", "camera": cam_cfg, "refocus": cfg["refocus"], "piv": cfg["piv"]}
    return {
        "dir": d,
        "base": base,
        "clean": clean,
        "camera": real,
        "sat": [float(np.mean(f >= FULL_12)) for f in frames],
    }


def _config(rec: dict, name: str, recording: dict, calibration: str = "pinhole.tif", **over) -> Path:
    cfg = {**rec["base"], **over, "recording": {"calibration": {"image": calibration}, "dt": DT, **recording}}
    path = rec["dir"] / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.fixture(scope="module")
def series(recording, tmp_path_factory):
    """The 12-bit files as a time series (a glob), dark frames subtracted, through the CLI."""
    cfg = _config(recording, "series", {"dark": "dark_*.tif", "frames": {"series": "frame_*.tif"}})
    out = tmp_path_factory.mktemp("out") / "series"
    assert main(["process", str(cfg), "--out", str(out), "--quiet"]) == 0
    return out


def test_series_measures_the_shift(series, recording, capsys):
    from lfstudy.process import open_result

    res = open_result(series)
    assert res["u"].chunks is not None  # lazy (dask)
    assert res.sizes["time"] == 2 and res["time"].attrs["units"] == "s"
    np.testing.assert_allclose(res["time"].values, [0.5 * DT, 1.5 * DT])
    assert list(res["frame_a"].values) == [1, 2] and list(res["frame_b"].values) == [2, 3]
    valid = res["valid"].values
    true = SHIFT_MM / VOXEL_MM
    u = res["u"].values[valid]
    assert abs(u.mean() - true) < 0.1, u.mean() - true
    assert abs(res["v"].values[valid].mean()) < 0.1 and abs(res["w"].values[valid].mean()) < 0.2
    for t in range(2):
        assert valid[t].mean() > 0.8, valid[t].mean()
    # the stores of every frame, as the simulated pipeline writes them
    for k in range(3):
        for name in ("lightfield", "stack", "volume"):
            assert (series / f"frames/{k:03d}/{name}.zarr").is_dir()
    assert (series / "centers.zarr").is_dir() and (series / "dark.zarr").is_dir()


def test_series_metrics_and_report(series, recording):
    m = pd.read_csv(series / "metrics.csv", index_col="time")
    assert len(m) == 2
    assert (m["n_vectors"] == 18).all()
    assert (m["valid_percent"] > 80).all()
    assert (m["peak_ratio_median"] > 2).all()  # one displacement clearly wins in every window
    assert np.isfinite(m["divergence_rms"]).all() and (m["divergence_norm"] < 1).all()
    np.testing.assert_allclose(m["saturated_percent"], 100 * np.maximum(recording["sat"][:-1], recording["sat"][1:]))
    metrics = io.open_zarr(series / "metrics.zarr")
    assert metrics["divergence_rms"].attrs["units"] == "1/s"
    assert metrics["valid_percent"].attrs["units"] == "percent"
    piv = io.open_zarr(series / "piv.zarr")
    assert piv["divergence"].attrs["units"] == "1/s" and "peak_ratio" in piv
    # the median standard uncertainty per component and pair: metrics.csv against piv.zarr's unc_<c>
    piv = piv.load()
    for c in "uvw":
        for t in range(2):
            one = piv.isel(time=t)
            sigma = one[f"unc_{c}"].values[one["valid"].values]
            assert np.isfinite(sigma).all()  # every valid vector has its σ
            assert m[f"unc_median_{c}"].iloc[t] == pytest.approx(np.median(sigma), rel=1e-12)
            assert m[f"unc_median_{c}_mm"].iloc[t] == pytest.approx(
                np.median(one[f"unc_{c}_mm"].values[one["valid"].values])
            )
            assert 0 < m[f"unc_median_{c}"].iloc[t] < 1.0  # voxel: a clear uniform shift
    assert metrics["unc_median_w_mm"].attrs["units"] == "mm"
    # the truth-free flag of vectors whose window's filtering may exceed σ, for recordings too (issue 38)
    assert piv["unresolved"].dtype == bool and piv["unresolved"].dims == piv["u"].dims
    assert not piv["unresolved"].values[~piv["valid"].values].any()  # no σ, no flag
    html = (series / "report.html").read_text()
    assert "Red crosses: vectors flagged unresolved" in html
    assert html.count("data:image/png;base64,") >= 10  # 4 of them the σ maps and histograms of the 2 pairs
    assert html.count("<figcaption>Standard uncertainty σ of each component per vector") == 2  # one per pair
    assert "<figcaption>Standard uncertainty σ per component over the valid vectors" in html and "unc_median_w" in html
    assert 'src="http' not in html and "<script src" not in html
    assert "peak_ratio_median" in html and "Q" not in re.findall(r"<th>(\w+)</th>", html)


def test_sigma_calibrated_by_a_study(series, recording, tmp_path, capsys):
    """uncertainty.calibration (issue 38): the same recording processed with a study of its design scales σ by
    the study's factor per component; the raw σ stays beside it, equal to the uncalibrated run's, and the
    summary, metrics.csv, the attrs and the report name the study and the factors."""
    import xarray as xr

    from lfstudy.study.sweep import Case
    from lfstudy.study.table import combine_cases, to_csv

    ratios = {"x": (1.2, 1.8), "y": (0.7, 0.7), "z": (3.0, 5.0)}  # two flows of the tiny design
    rows = []
    for k, flow in enumerate(("uniform_x", "hill")):
        case = Case.of(magnification=-1.0, fnumber="matched", lenslet_pitch=0.0888, ppp=0.004, flow=flow)
        rows.append((case, xr.Dataset({f"unc_ratio_{ax}": ((), r[k]) for ax, r in ratios.items()})))
    to_csv(combine_cases(rows), tmp_path / "study" / "study.csv")
    factor = {ax: float(np.sqrt(r[0] * r[1])) for ax, r in ratios.items()}
    cfg = _config(
        recording,
        "calibrated",
        {"dark": "dark_*.tif", "frames": {"series": "frame_*.tif"}},
        uncertainty={"calibration": {"study": str(tmp_path / "study"), "design": {"mag": -1, "pitch": 0.0888}}},
    )
    out = tmp_path / "out"
    assert main(["process", str(cfg), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "σ calibrated by the study" in said and f"z × {factor['z']:.3g}" in said
    assert "median σ (calibrated by the study" in said
    raw = io.open_zarr(series / "piv.zarr").load()
    cal = io.open_zarr(out / "piv.zarr").load()
    for c, ax in zip("uvw", "xyz"):
        for sfx in ("", "_mm"):
            np.testing.assert_array_equal(cal[f"unc_raw_{c}{sfx}"].values, raw[f"unc_{c}{sfx}"].values)
            np.testing.assert_allclose(cal[f"unc_{c}{sfx}"].values, factor[ax] * raw[f"unc_{c}{sfx}"].values, rtol=1e-6)
        assert cal.attrs[f"uncertainty_calibration_factor_{ax}"] == pytest.approx(factor[ax])
    assert cal.attrs["uncertainty_calibration_study"] == str(tmp_path / "study")
    m = pd.read_csv(out / "metrics.csv", index_col="time")
    m0 = pd.read_csv(series / "metrics.csv", index_col="time")
    for c, ax in zip("uvw", "xyz"):
        np.testing.assert_allclose(m[f"unc_cal_factor_{ax}"], factor[ax])
        np.testing.assert_allclose(m[f"unc_raw_median_{c}"], m0[f"unc_median_{c}"], rtol=1e-6)
        np.testing.assert_allclose(m[f"unc_median_{c}"], factor[ax] * m0[f"unc_median_{c}"], rtol=1e-5)
    html = (out / "report.html").read_text()
    # the σ maps of both pairs say which σ they show
    assert len(re.findall(r"<figcaption>[^<]*σ shown is calibrated by the study", html)) == 2
    assert "σ shown is calibrated" not in (series / "report.html").read_text()


def test_saturation_warns_with_the_fraction(recording, tmp_path, capsys):
    assert max(recording["sat"]) > 0  # the fixture clips the brightest particle images
    pairs = {"pairs": [["frame_1.tif", "frame_2.tif"]]}
    cfg = _config(recording, "pairs", {"dark": "dark_*.tif", "frames": pairs, "max_saturated": 0.0})
    out = tmp_path / "pairs"
    assert main(["process", str(cfg), "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    text = captured.err
    err = [ln for ln in text.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("lfstudy process: warning: "), text  # nothing else (zarr...)
    worst = 100 * max(recording["sat"][:2])
    assert re.search(r"2 of 2 frames saturated .* full scale 4095, 12-bit\): up to ([\d.]+) %", err[0]), err[0]
    assert float(re.search(r"up to ([\d.]+) %", err[0]).group(1)) == pytest.approx(worst, rel=1e-2)
    pair = io.open_zarr(out / "piv.zarr")
    assert pair.sizes["pair"] == 1 and list(pair["pair"].values) == [0]
    # the summary prints the median σ per component, in mm and voxels, over the valid vectors
    pair = pair.load()
    valid = pair["valid"].values
    med = {k: np.median(pair[f"unc_{k}"].values[valid]) for k in ("u", "v", "w", "u_mm", "v_mm", "w_mm")}
    want = ", ".join(f"{c} {med[c + '_mm']:.3g} mm ({med[c]:.3g} voxel)" for c in "uvw")
    lines = captured.out.splitlines()
    assert f"uncertainty: median σ of the {int(valid.sum())} valid vectors of all pairs: {want}" in lines, captured.out
    assert re.search(r"^pair 1/1 .*, median σ \[voxel\] u [\d.e-]+, v [\d.e-]+, w [\d.e-]+$", lines[-3]), lines[-3]


def test_16bit_stack_gives_the_same_vectors(recording, series, tmp_path):
    """The 16-bit multi-page stack (16 x the 12-bit data, darks too) gives the 12-bit files' vectors."""
    rec16 = {"dark": "dark16.tif", "frames": {"series": "series16.tif"}}
    cfg = _config(recording, "stack", rec16, calibration="pinhole16.tif")
    out = tmp_path / "stack"
    assert main(["process", str(cfg), "--out", str(out), "--quiet"]) == 0
    a, b = io.open_zarr(series / "piv.zarr").load(), io.open_zarr(out / "piv.zarr").load()
    assert b.attrs["recording_bit_depth"] == 16 and a.attrs["recording_bit_depth"] == 12
    for name in ("u", "v", "w"):
        np.testing.assert_allclose(b[name].values, a[name].values, atol=1e-4)
    assert (a["valid"].values == b["valid"].values).all()


def test_recording_matches_the_simulated_path(recording, series):
    """The recorded path (noisy, quantised, dark-corrected TIFFs) gives the vectors of the simulated
    path (the noise-free float images of the same camera, calibrated on a noise-free pinhole)."""
    from lfstudy.lightfield import find_lenslet_centers
    from lfstudy.optics import PlenopticCamera
    from lfstudy.simulate import render_pinhole
    from lfstudy.study.case import case_piv, render_volume

    cfg = load_config(TINY)
    real = PlenopticCamera.from_config(recording["camera"])
    pin = render_pinhole(real, fnumber=16, count=20000, rays_per_point=30, seed=11, method="montecarlo")
    centers = find_lenslet_centers(pin, PlenopticCamera.from_config(cfg))
    vols = [render_volume(img, centers, cfg)[2].compute() for img in recording["clean"][:2]]
    sim = case_piv(cfg, *vols)
    rec = io.open_zarr(series / "piv.zarr").isel(time=0).load()
    both = sim["valid"].values & rec["valid"].values
    assert both.mean() > 0.7
    du = rec["u"].values[both] - sim["u"].values[both]
    assert abs(du.mean()) < 0.05 and np.sqrt(np.mean(du**2)) < 0.15, (du.mean(), np.sqrt(np.mean(du**2)))


# ------------------------------------------------------------------ bad recordings
def _no_output(out: Path) -> None:
    assert not out.exists() and not list(out.parent.glob(f".{out.name}.lfstudy-*"))


def test_frames_of_different_size(recording, cli_error, tmp_path):
    d = recording["dir"]
    img = tifffile.imread(d / "frame_2.tif")
    tifffile.imwrite(d / "narrow.tif", img[:, :380], extratags=_tags(FULL_12))
    cfg = _config(recording, "bad_size", {"frames": {"series": ["frame_1.tif", "narrow.tif"]}})
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "recording.frames: frames differ in size" in line and "380 x 384 px" in line, line
    _no_output(tmp_path / "o")


def test_frames_of_different_bit_depth(recording, cli_error, tmp_path):
    cfg = _config(recording, "bad_depth", {"frames": {"pairs": [["frame_1.tif", "frame_2.tif"], "series16.tif"]}})
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "recording.frames.pairs[1]: 3 frames" in line, line  # a three-page stack is no pair
    cfg = _config(recording, "bad_depth2", {"dark": "dark16.tif", "frames": {"series": "frame_*.tif"}})
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "recording.dark: frames differ in bit depth" in line and "12-bit (uint16)" in line, line
    assert "16-bit (uint16)" in line
    rec16 = {"dark": "dark16.tif", "frames": {"series": "series16.tif"}}
    line = cli_error("process", str(_config(recording, "bad_depth4", rec16)), "--out", str(tmp_path / "o"))
    assert "recording.calibration.image: 'pinhole.tif' is 12-bit (uint16) but the frames and dark" in line, line
    d = recording["dir"]
    tifffile.imwrite(d / "depth16.tif", tifffile.imread(d / "frame_2.tif") * 16)
    cfg = _config(recording, "bad_depth3", {"frames": {"series": ["frame_1.tif", "depth16.tif"]}})
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "recording.frames: frames differ in bit depth" in line, line
    _no_output(tmp_path / "o")


def test_calibration_image_without_a_lattice(recording, cli_error, tmp_path):
    d = recording["dir"]
    noise = np.random.default_rng(0).poisson(100.0, (384, 384)).astype(np.uint16)
    tifffile.imwrite(d / "noise.tif", noise)
    cfg = _config(recording, "bad_calib", {"frames": {"series": "frame_*.tif"}})
    text = yaml.safe_load(cfg.read_text())
    text["recording"]["calibration"]["image"] = "noise.tif"
    cfg.write_text(yaml.safe_dump(text))
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "recording.calibration.image 'noise.tif' (pinhole): no lenslet grid detected" in line, line
    _no_output(tmp_path / "o")


def test_sensor_size_not_the_cameras(recording, cli_error, tmp_path):
    cam = yaml.safe_load(yaml.safe_dump(recording["base"]["camera"]))
    cam["sensor"]["n_pixels_x"] = 400
    cfg = _config(recording, "bad_sensor", {"frames": {"series": "frame_*.tif"}}, camera=cam)
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "384 x 384 px (cols x rows) but camera.sensor is 400 x 384 px" in line, line
    _no_output(tmp_path / "o")


def test_bad_recording_config(recording, cli_error, tmp_path):
    cfg = _config(recording, "bad_cfg", {"frames": {"series": "frame_*.tif"}}, piv={"window": [2, 16, 16]})
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "config key 'piv.window.0' = 2: allowed range is [4, inf)" in line, line
    cfg = _config(recording, "bad_cfg2", {"frames": {}})
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "give exactly one of 'pairs'" in line, line
    cfg = _config(recording, "bad_cfg3", {"frames": {"series": "missing_*.tif"}})
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "no file matches" in line and "missing_*.tif" in line, line
    _no_output(tmp_path / "o")


def test_snakemake_process_target(recording, tmp_path):
    """`snakemake process --config process=RECORDING.yaml` plans one job with the recording's files as
    inputs (dry run: the processing itself is tested above)."""
    import subprocess
    import sys

    cfg = _config(recording, "smk", {"dark": "dark_*.tif", "frames": {"series": "frame_*.tif"}})
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(tmp_path)]
    cmd += ["--configfile", str(TINY), "-n", "--cores", "1", "process", "--config", f"process={cfg}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    text = r.stdout + r.stderr
    assert "process_recording" in text and "results/rec" in text
    for name in ("pinhole.tif", "dark_2.tif", "frame_3.tif", "smk.yaml"):
        assert name in text, name
    # the job declares the memory of every stage of the recording's config (lfstudy.study.resources)
    from lfstudy.process import load_process_config
    from lfstudy.study.resources import job_mem_mb

    block = text[text.index("rule process_recording:") :]
    mem = re.search(r"resources: .*\bmem_mb=(\d+)", block)
    assert mem and int(mem.group(1)) == job_mem_mb(load_process_config(cfg), "process"), block[:2000]


# ------------------------------------------------------------------ the Snakemake target never loses a recording
def _sums(root: Path) -> dict[str, str]:
    """sha256 of every file below ``root`` (relative paths)."""
    import hashlib

    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _kept(before: dict[str, str], root: Path) -> None:
    after = _sums(root)
    lost = {k for k, v in before.items() if after.get(k) != v}
    assert not lost, f"lost or changed: {sorted(lost)}"


def _user_recording(rec: dict, where: Path, name: str) -> Path:
    """The recording as a user keeps it: its TIFFs and its config side by side in ``where``."""
    import shutil

    where.mkdir(parents=True, exist_ok=True)
    for f in ("pinhole.tif", "frame_1.tif", "frame_2.tif", "dark_1.tif", "dark_2.tif"):
        shutil.copy(rec["dir"] / f, where / f)
    cfg = {
        **rec["base"],
        "name": name,
        "recording": {
            "calibration": {"image": "pinhole.tif"},
            "dark": "dark_*.tif",
            "dt": DT,
            "frames": {"pairs": [["frame_1.tif", "frame_2.tif"]]},
        },
    }
    path = where / "rec.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _snakemake_process(work: Path, cfg: Path, timeout: int = 900) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work)]
    cmd += ["--configfile", str(TINY), "--cores", "1", "process", "--config", f"process={cfg}"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("name", ["..", "."])
def test_snakemake_process_refuses_a_name_that_is_a_path(recording, tmp_path, name):
    """`name: ..` once deleted the whole working directory through the target's directory() output, and
    `name: .` another study's results: a name is a plain name, refused before Snakemake removes anything.
    (The other names that are paths are refused by the same check, below, without a Snakemake start each.)"""
    work = tmp_path / "W"
    cfg = _user_recording(recording, work, name)
    (work / "results" / "other").mkdir(parents=True)
    (work / "results" / "other" / "study.csv").write_text("a,b\n1,2\n")
    before = _sums(work)
    r = _snakemake_process(work, cfg)
    assert r.returncode != 0
    assert "config key 'name'" in r.stderr and "a plain name" in r.stderr, r.stderr[-2000:]
    _kept(before, work)


@pytest.mark.parametrize("name", ["a/b", ".hidden", "..", "", "x" * 101])
def test_a_recording_name_that_is_a_path_is_refused_by_the_loader(recording, tmp_path, name):
    """The check the Snakemake target runs at parse time (the recording config's loader), on the other names
    that are paths or empty or too long: refused, naming the key and what a name may be."""
    from lfstudy.config import ConfigError
    from lfstudy.process.config import load_process_config

    cfg = _user_recording(recording, tmp_path / "rec", name)
    with pytest.raises(ConfigError, match=r"config key 'name'"):
        load_process_config(cfg)


def test_snakemake_process_refuses_a_recording_under_its_output(recording, tmp_path):
    """A recording kept in results/<name>/ (where the target writes) is refused at parse time: all of its
    files stay (they were deleted as the directory() output)."""
    work = tmp_path / "W"
    cfg = _user_recording(recording, work / "results" / "rec", "rec")
    before = _sums(work)
    r = _snakemake_process(work, cfg)
    assert r.returncode != 0
    assert "lies inside results/rec/" in r.stderr, r.stderr[-2000:]
    _kept(before, work)
    assert len(before) == 6


@pytest.mark.slow
def test_snakemake_process_keeps_user_files_in_its_output(recording, tmp_path):
    """A user's folder at results/<name>/ is refused by the job (rc 1, notes kept); a finished output is
    replaced on a rerun only while it holds nothing but lfstudy's files: a note added to it is named
    and kept, with the earlier output."""
    work = tmp_path / "W"
    cfg = _user_recording(recording, tmp_path / "recording", "rec")
    user = work / "results" / "rec"
    user.mkdir(parents=True)
    (user / "notes.txt").write_text("mine")
    r = _snakemake_process(work, cfg)
    assert r.returncode != 0
    log = (work / "results" / "rec.process.log").read_text()
    assert "exists and is no lfstudy output" in log, log
    assert (user / "notes.txt").read_text() == "mine" and sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    assert not (work / "results" / "rec.process.json").exists()
    (user / "notes.txt").unlink()
    r = _snakemake_process(work, cfg)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (user / "piv.zarr").is_dir() and io.output_marker(user)["command"] == "process"
    record = json.loads((work / "results" / "rec.process.json").read_text())
    assert record == io.output_marker(user)
    (user / "notes.txt").write_text("mine")
    with cfg.open("a") as f:
        f.write("# edited\n")  # the recording's config changed: Snakemake reruns the job
    before = {d: _sums(d) for d in (user, cfg.parent)}
    r = _snakemake_process(work, cfg)
    assert r.returncode != 0
    log = (work / "results" / "rec.process.log").read_text()
    assert "holds files lfstudy did not write: 'notes.txt'" in log, log
    for d, sums in before.items():
        _kept(sums, d)  # the note, the earlier output and the recording


def test_white_image_calibration(recording):
    """A white image (the working aperture: the lenslet disks touch) gives the pinhole image's centres."""
    from lfstudy.lightfield import find_lenslet_centers
    from lfstudy.optics import PlenopticCamera
    from lfstudy.process import calibrate_recording
    from lfstudy.simulate import render_pinhole

    nominal = PlenopticCamera.from_config(recording["base"])
    real = PlenopticCamera.from_config(recording["camera"])
    white = render_pinhole(real, fnumber=real.main_fnumber, count=40000, rays_per_point=30, seed=1, method="montecarlo")
    pin = find_lenslet_centers(
        render_pinhole(real, fnumber=16, count=20000, rays_per_point=30, seed=2, method="montecarlo"), nominal
    )
    cen = calibrate_recording(white, nominal, "white")
    ok = cen["valid"].values & pin["valid"].values
    assert ok.mean() > 0.9
    d = np.hypot(cen["cx"].values - pin["cx"].values, cen["cy"].values - pin["cy"].values)[ok]
    assert np.sqrt(np.mean(d**2)) < 0.1, np.sqrt(np.mean(d**2))
    dx = (cen["x"].values - pin["x"].values)[ok]  # the mm coordinates follow the centres
    assert np.sqrt(np.mean(dx**2)) < 0.1 * real.pixel_pitch


def test_bit_depth_of_each_kind_of_tiff(tmp_path):
    """8-bit, 12-bit (in a 16-bit file, from MaxSampleValue or recording.bit_depth), 16-bit and float
    frames; values above the declared full scale are refused."""
    from types import SimpleNamespace

    from lfstudy.process.recording import RecordingError, open_recording, read_frame, tiff_info

    img = np.random.default_rng(1).integers(0, 200, (24, 32))
    tifffile.imwrite(tmp_path / "a8.tif", img.astype(np.uint8))
    tifffile.imwrite(tmp_path / "a12.tif", (img * 16).astype(np.uint16), extratags=_tags(FULL_12))
    tifffile.imwrite(tmp_path / "a16.tif", (img * 300).astype(np.uint16))
    tifffile.imwrite(tmp_path / "af.tif", img.astype(np.float32))
    depth = {n: tiff_info(tmp_path / f"{n}.tif").depth for n in ("a8", "a12", "a16", "af")}
    assert depth == {"a8": "8-bit (uint8)", "a12": "12-bit (uint16)", "a16": "16-bit (uint16)", "af": "32-bit float"}
    assert tiff_info(tmp_path / "a16.tif", bit_depth=12).bits == 12
    with pytest.raises(RecordingError, match=r"recording.bit_depth' = 12: .* float"):
        tiff_info(tmp_path / "af.tif", bit_depth=12)
    cam = SimpleNamespace(n_pixels_x=32, n_pixels_y=24)
    spec = {"calibration": {"image": str(tmp_path / "a16.tif")}, "dark": [], "bit_depth": 12}
    rec = open_recording({**spec, "frames": {"series": [str(tmp_path / "a16.tif")] * 2}}, cam)
    with pytest.raises(RecordingError, match=r"holds values up to \d+, above full scale 4095"):
        read_frame(rec, rec.frames[0])
    rec = open_recording({**spec, "bit_depth": None, "frames": {"series": [str(tmp_path / "a8.tif")] * 2}}, cam)
    frame, saturated = read_frame(rec, rec.frames[0])
    assert rec.full_scale == 255 and saturated == 0 and frame.dtype == np.float64


def test_a_recorded_traverse_calibrates_depth(recording, tmp_path):
    """A recording with a traverse (start image, +0.1 and +0.2 mm along z) and one pair moved 0.15 mm
    along z (not a traverse): the depth calibration is stored and brings the mean w closer to the truth
    (18 vectors on this tiny sensor: measured -13 % raw, +7 % calibrated)."""
    from lfstudy.optics import PlenopticCamera
    from lfstudy.simulate import render
    from lfstudy.study.case import case_particles

    cam = PlenopticCamera.from_config(recording["camera"])
    other = {**recording["camera"], "seed": 99}  # the traverse images another seeded volume
    d = recording["dir"]

    def write(name: str, field, seed: int) -> str:
        img = render(cam, field, 1500, seed, method="montecarlo").values
        tifffile.imwrite(d / name, np.rint(img * (3000.0 / img.max())).astype(np.uint16), extratags=_tags(FULL_12))
        return name

    ref = case_particles(other)
    images = [write(f"traverse_{k}.tif", ref.assign(z=ref["z"] + s), 300 + k) for k, s in enumerate((0.0, 0.1, 0.2))]
    field = case_particles(recording["camera"])
    truth = 0.15
    pair = [write("z_1.tif", field, 400), write("z_2.tif", field.assign(z=field["z"] + truth), 401)]
    common = {"frames": {"pairs": [pair]}}
    mart = {"method": "mart"}
    plain = _config(recording, "z_plain", common, reconstruct=mart)
    calibrated = _config(
        recording, "z_cal", {**common, "depth_calibration": {"images": images, "shifts": [0.1, 0.2]}}, reconstruct=mart
    )
    w = {}
    for name, cfg in (("plain", plain), ("calibrated", calibrated)):
        out = tmp_path / name
        assert main(["process", str(cfg), "--out", str(out), "--quiet"]) == 0
        piv = io.open_zarr(out / "piv.zarr").load()
        valid = piv["valid"].values
        w[name] = float(piv["w_mm"].values[valid].mean())
    cal = io.open_zarr(tmp_path / "calibrated" / "depth_calibration.zarr").load()
    assert cal.attrs["resolves_depth"] == 1 and list(cal["shift"].values) == [0.1, 0.2]
    assert not (tmp_path / "plain" / "depth_calibration.zarr").exists()
    assert w["plain"] < 0.9 * truth, w  # the raw chain reads depth short
    # the issue's depth target (10 % of the truth), and closer than the raw reading
    assert abs(w["calibrated"] - truth) < min(0.1 * truth, abs(w["plain"] - truth)), w


def test_a_traverse_needs_one_image_per_shift(recording, cli_error, tmp_path):
    dc = {"images": ["frame_1.tif", "frame_2.tif"], "shifts": [0.1, 0.2]}
    cfg = _config(recording, "bad_traverse", {"frames": {"series": "frame_*.tif"}, "depth_calibration": dc})
    out = tmp_path / "out"
    line = cli_error("process", str(cfg), "--out", str(out))
    assert "recording.depth_calibration.images: 2 images for 2 traverses" in line, line
    _no_output(out)


# ------------------------------------------------------------------ --out never deletes what lfstudy did not write
def _pair_config(rec: dict, name: str = "pair") -> Path:
    return _config(rec, name, {"frames": {"pairs": [["frame_1.tif", "frame_2.tif"]]}})


def test_out_refuses_data_lfstudy_did_not_write(recording, cli_error, tmp_path, monkeypatch):
    """An existing directory or file at --out, the recording's folder, `.` and `..` are refused before any
    processing (one line, exit 2), and everything in them is left as it was."""
    cfg = _pair_config(recording)
    user = tmp_path / "d"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    line = cli_error("process", str(cfg), "--out", str(user))
    assert "exists and is no lfstudy output" in line and "never replaces data it did not write" in line, line
    line = cli_error("process", str(cfg), "--out", str(user), "--overwrite")  # not even with --overwrite
    assert "no lfstudy output" in line, line
    assert (user / "notes.txt").read_text() == "mine" and sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    afile = tmp_path / "result.txt"
    afile.write_text("mine")
    line = cli_error("process", str(cfg), "--out", str(afile), "--overwrite")
    assert "is an existing file" in line, line
    assert afile.read_text() == "mine"
    d = recording["dir"]
    before = sorted(p.name for p in d.iterdir())
    line = cli_error("process", str(cfg), "--out", str(d), "--overwrite")
    assert "an input of this run" in line, line
    monkeypatch.chdir(d)
    line = cli_error("process", str(cfg), "--out", ".", "--overwrite")
    assert "--out '.' holds" in line and "an input of this run" in line, line
    line = cli_error("process", str(cfg), "--out", "..")
    assert "--out '..' holds" in line and "an input of this run" in line, line
    line = cli_error("process", str(cfg), "--out", "pinhole.tif/o")  # inside an input file
    assert "lies inside" in line and "pinhole.tif" in line, line
    assert sorted(p.name for p in d.iterdir()) == before
    assert not list(tmp_path.glob(".*"))  # no temporary or lock left behind


def test_out_that_cannot_be_written_fails_before_processing(recording, cli_error, tmp_path):
    cfg = _pair_config(recording)
    (tmp_path / "f").write_text("")
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "f" / "o"))
    assert "cannot create" in line and "/f'" in line, line
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        line = cli_error("process", str(cfg), "--out", str(ro / "o"))
        assert "not writable" in line, line
    # an output that cannot be moved into place (an immutable empty folder) fails before processing
    imm = tmp_path / "imm"
    imm.mkdir()
    made = subprocess.run(["chattr", "+i", str(imm)], capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"this file system or user cannot make an immutable folder: {made.stderr.strip()}")
    try:
        line = cli_error("process", str(cfg), "--out", str(imm))
    finally:
        subprocess.run(["chattr", "-i", str(imm)], check=True)
    assert "cannot be replaced: moving it failed" in line, line
    assert not any(p.name.startswith(".imm.") for p in tmp_path.iterdir())


def test_a_file_added_to_out_while_the_run_writes_is_kept(recording, tmp_path):
    """An empty --out that gets a file while the run writes is not replaced at the swap: the run fails
    naming the file, which is kept, and nothing of the run is left behind."""
    out = tmp_path / "D"
    out.mkdir()
    cmd = [sys.executable, "-m", "lfstudy.cli", "process", str(_pair_config(recording)), "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(12000):  # the run's temporary appears before any processing
            if list(tmp_path.glob(".D.lfstudy-tmp-*")):
                break
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.01)
        (out / "notes.txt").write_text("mine")
        _, err = proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert proc.returncode == 2, err
    assert "now holds files lfstudy did not write: 'notes.txt'" in err or "now is no lfstudy output" in err, err
    assert "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"] and (out / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["D"]


def test_out_overwrites_only_its_own_output(recording, cli_error, tmp_path, capsys):
    """A finished output carries the marker of `lfstudy process`; a rerun replaces it only with --overwrite,
    and an output of another command is refused even then."""
    cfg = _pair_config(recording)
    out = tmp_path / "o"
    assert main(["process", str(cfg), "--out", str(out), "--quiet"]) == 0
    marker = json.loads((out / io.MARKER).read_text())
    assert marker["command"] == "process" and str(cfg) in marker["inputs"]
    (out / "metrics.csv").write_text("stale")
    capsys.readouterr()
    line = cli_error("process", str(cfg), "--out", str(out))
    assert "holds an earlier output of lfstudy process; give --overwrite" in line, line
    assert main(["process", str(cfg), "--out", str(out), "--quiet", "--overwrite"]) == 0
    assert (out / "metrics.csv").read_text() != "stale" and (out / "piv.zarr").is_dir()
    assert not list(tmp_path.glob(".*"))
    # --overwrite replaces what lfstudy wrote, never a file put into the output since: it names them
    import shutil

    (out / "notes.txt").write_text("mine")
    shutil.copy(recording["dir"] / "frame_1.tif", out / "piv.zarr" / "frame_1.tif")
    before = _sums(out)
    capsys.readouterr()
    assert main(["process", str(cfg), "--out", str(out), "--overwrite"]) == 2
    err = capsys.readouterr().err  # the recording's saturation warning may come first
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("lfstudy process: error: "), err
    assert "holds files lfstudy did not write: 'notes.txt', 'piv.zarr/frame_1.tif'" in err, err
    assert _sums(out) == before and not list(tmp_path.glob(".*"))
    (out / "notes.txt").unlink()
    (out / "piv.zarr" / "frame_1.tif").unlink()
    marker["command"] = "piv"
    (out / io.MARKER).write_text(json.dumps(marker))
    capsys.readouterr()
    line = cli_error("process", str(cfg), "--out", str(out), "--overwrite")
    assert "is an output of lfstudy piv" in line, line


def test_second_run_on_the_same_out_is_refused(recording, cli_error, tmp_path):
    """Another process writing the same --out holds its lock: a second run is refused at once and leaves
    the first one's temporary directory alone."""
    out = tmp_path / "o"
    holder = (
        "import sys, time; from lfstudy import io\n"
        "with io.output_dir(sys.argv[1], command='process') as tmp:\n"
        "    (tmp / 'piv.zarr').mkdir(); print(tmp, flush=True); time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", holder, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        tmp = Path(proc.stdout.readline().strip())
        assert tmp.is_dir()
        line = cli_error("process", str(_pair_config(recording)), "--out", str(out))
        assert "is being written by another lfstudy run" in line, line
        assert (tmp / "piv.zarr").is_dir()  # the live run's work is untouched
    finally:
        proc.kill()
        proc.wait()


def _pitch_camera(rec: dict, scale: float) -> dict:
    cam = yaml.safe_load(yaml.safe_dump(rec["base"]["camera"]))
    cam["lenslet"]["pitch"] = round(cam["lenslet"]["pitch"] * scale, 5)
    return cam


def test_config_pitch_not_the_images(recording, cli_error, tmp_path):
    """A configured lenslet pitch 33 % off the image's is named as such, not as a doubt about the image."""
    cfg = _config(recording, "bad_pitch", {"frames": {"series": "frame_*.tif"}}, camera=_pitch_camera(recording, 1.33))
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    pattern = r"lenslet pitch ([\d.]+) px in the config does not match the image's ([\d.]+) px \(\+(\d+) % off\)"
    m = re.search(pattern, line)
    assert m and "pinhole image?" not in line, line
    assert float(m.group(2)) == pytest.approx(12.0, rel=0.01)  # 0.0888 mm of 0.0074 mm pixels
    _no_output(tmp_path / "o")


def test_config_pitch_a_few_percent_off_warns(recording):
    """4 % off still finds a grid, but loses lenslets: a warning gives the fitted pitch."""
    from lfstudy.lightfield.calibrate import PitchWarning
    from lfstudy.optics import PlenopticCamera
    from lfstudy.process import calibrate_recording

    img = io.read_image(recording["dir"] / "pinhole.tif")
    cam = PlenopticCamera.from_config({**recording["base"], "camera": _pitch_camera(recording, 1.04)})
    with pytest.warns(PitchWarning, match=r"differs from the image's fitted 12\.0\d\d px \(\+4\.\d %\)"):
        calibrate_recording(img, cam)
    with warnings.catch_warnings():
        warnings.simplefilter("error", PitchWarning)  # the right pitch: no warning
        calibrate_recording(img, PlenopticCamera.from_config(recording["base"]))


def test_a_nan_frame_names_its_file(recording, cli_error, tmp_path):
    d = recording["dir"]
    for name in ("pinhole", "frame_1", "frame_2"):
        img = tifffile.imread(d / f"{name}.tif").astype(np.float32)
        if name == "frame_2":
            img[10, 20:23] = np.nan
        tifffile.imwrite(d / f"float_{name}.tif", img)
    pairs = {"pairs": [["float_frame_1.tif", "float_frame_2.tif"]]}
    cfg = _config(recording, "nan", {"frames": pairs}, calibration="float_pinhole.tif")
    line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
    assert "recording.frames: 'float_frame_2.tif'" in line and "has 3 non-finite (NaN/inf) pixels" in line, line
    assert str(d / "float_frame_2.tif") in line, line
    _no_output(tmp_path / "o")


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_a_degenerate_pair_is_measured_quietly(recording, tmp_path, capsys):
    """The same frame twice (zero displacement, no divergence to normalise): metrics without
    numpy/matplotlib RuntimeWarnings on the console."""
    cfg = _config(recording, "same", {"frames": {"pairs": [["frame_1.tif", "frame_1.tif"]]}})
    out = tmp_path / "o"
    assert main(["process", str(cfg), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "Warning" not in err, err
    m = pd.read_csv(out / "metrics.csv")
    assert m["valid_percent"].iloc[0] > 80 and abs(m["mean_u"].iloc[0]) < 1e-6


def test_ipr_writes_each_frames_particle_list(tmp_path):
    """reconstruct.method: ipr on a recording: every frame's volume is rendered from its particle list,
    which is written beside it (frames/<k>/particles.zarr, position, intensity, residual and the fit's
    uncertainty), and the pair is correlated as for any method. A small recording of its own: IPR
    refuses the rotated lenslet grid of the module's one."""
    from lfstudy.optics import PlenopticCamera
    from lfstudy.reconstruct.ipr import render_particles
    from lfstudy.simulate import displace, flow_from_config, render, render_pinhole
    from lfstudy.study.case import case_grid, case_particles

    cfg = load_config(TINY)
    real = {**cfg, "particles": {**cfg["particles"], "count": 8}}
    cam = PlenopticCamera.from_config(real)
    field = case_particles(real)
    rng = np.random.default_rng(7)
    pin = render_pinhole(cam, fnumber=16, count=20000, rays_per_point=30, seed=11, method="montecarlo").values
    tifffile.imwrite(tmp_path / "pinhole.tif", rng.poisson(pin * 3000.0 / pin.max()).astype(np.uint16))
    for k in range(2):
        moved = displace(field, flow_from_config({"kind": "uniform", "displacement": [SHIFT_MM * k, 0, 0]}), 1.0, 1)
        img = render(cam, moved, 20_000, 100 + k, method="montecarlo").values
        tifffile.imwrite(tmp_path / f"frame_{k + 1}.tif", rng.poisson(img).astype(np.uint16))
    rec = {
        "name": "ipr",
        "camera": cfg["camera"],
        "refocus": cfg["refocus"],
        "piv": cfg["piv"],
        "reconstruct": {"method": "ipr", "ipr": {"iterations": 3}},
        "recording": {
            "calibration": {"image": "pinhole.tif"},
            "dt": DT,
            "frames": {"pairs": [["frame_1.tif", "frame_2.tif"]]},
        },
    }
    path = tmp_path / "ipr.yaml"
    path.write_text(yaml.safe_dump(rec))
    out = tmp_path / "out"
    assert main(["process", str(path), "--out", str(out), "--quiet"]) == 0
    grid = case_grid({**cfg, "reconstruct": rec["reconstruct"]})
    for k in range(2):
        parts = io.open_zarr(out / f"frames/{k:03d}/particles.zarr").load()
        vol = io.open_array(out / f"frames/{k:03d}/volume.zarr").load()
        assert parts.attrs["method"] == vol.attrs["method"] == "ipr" and parts.attrs["source"] == f"frame_{k + 1}.tif"
        assert set(parts.data_vars) >= {"x", "y", "z", "intensity", "residual", "sigma_x", "sigma_y", "sigma_z"}
        assert parts["x"].attrs["units"] == "mm" and parts.sizes["particle"] == vol.attrs["n_particles"] > 0
        np.testing.assert_array_equal(vol.values, render_particles(parts, grid, cam)[0].astype(np.float32))
        # the list is the frame's: its brightest particle lies within a voxel of a true one of that frame
        # (measured 0.42 and 0.34 voxel; this IPR finds 1-2 of the 8 on the tiny camera)
        true = np.column_stack([field[v].values + (SHIFT_MM * k if v == "x" else 0.0) for v in "xyz"])
        best = int(np.argmax(parts["intensity"].values))
        fit = np.array([float(parts[v][best]) for v in "xyz"])
        vox = np.array(grid.voxel_size()[::-1])
        assert np.linalg.norm((fit - true) / vox, axis=1).min() < 1.0
    piv = io.open_zarr(out / "piv.zarr")
    assert piv.sizes["pair"] == 1
    # piv.particles unset, no traverse: WIDIM again on the paired particles, as a study does
    assert piv.attrs["particles"] == "paired" and "piv_u_mm" in piv and piv.attrs["paired_particles_a"] > 0


def test_piv_particles_refusals(recording, cli_error, tmp_path):
    """piv.particles in a recording config: ptv (no correlation peaks for the metrics) and paired without a
    particle method or with a recorded traverse are refused before any work, naming the key."""
    frames = {"frames": {"series": "frame_*.tif"}}
    cases = [
        ({"method": "ipr"}, {"particles": "ptv"}, frames, "piv.particles' = 'ptv'"),
        ({"method": "mart"}, {"particles": "paired"}, frames, "reconstruct.method = 'mart' fits none"),
        (
            {"method": "ipr"},
            {"particles": "paired"},
            {**frames, "depth_calibration": {"images": ["frame_1.tif", "frame_2.tif"], "shifts": [1.0]}},
            "not with recording.depth_calibration",
        ),
    ]
    for k, (rc, piv, rec, msg) in enumerate(cases):
        cfg = _config(recording, f"particles_{k}", rec, reconstruct=rc, piv={**recording["base"]["piv"], **piv})
        line = cli_error("process", str(cfg), "--out", str(tmp_path / "o"))
        assert msg in line, line
    _no_output(tmp_path / "o")
    # unset: paired with ipr and no traverse, none otherwise (the config as validated)
    from lfstudy.process.config import load_process_config

    for rc, rec, want in (
        ({"method": "ipr"}, frames, "paired"),
        ({"method": "mart"}, frames, None),
        ({"method": "ipr"}, cases[2][2], None),
    ):
        cfg = load_process_config(_config(recording, "particles_unset", rec, reconstruct=rc))
        assert cfg["piv"].get("particles") == want


def test_median_uncertainty_and_summary_without_sigma():
    """The median σ leaves out invalid vectors and NaN σ (replaced vectors); a result without unc_* (an
    older store, piv.uncertainty none) has no summary line and no unc_median metric, and no error."""
    import xarray as xr

    from lfstudy.process.metrics import median_uncertainty, pair_metrics
    from lfstudy.process.pipeline import uncertainty_summary

    sigma = np.array([[0.1, np.nan, 0.3], [5.0, 0.2, 0.4]])
    valid = np.array([[True, True, True], [False, True, True]])
    assert median_uncertainty(sigma, valid) == pytest.approx(0.25)  # of 0.1, 0.3, 0.2, 0.4
    assert np.isnan(median_uncertainty(sigma, np.zeros_like(valid)))
    coords = {"z": [0.0], "y": [0.0, 1.0], "x": [0.0, 1.0, 2.0]}
    ds = xr.Dataset(
        {c: (("z", "y", "x"), np.ones((1, 2, 3))) for c in ("u", "v", "w", "peak")}
        | {"valid": (("z", "y", "x"), valid[None])},
        coords=coords,
    )
    assert uncertainty_summary(ds) is None
    assert not any(k.startswith("unc_") for k in pair_metrics(ds).data_vars)
    ds["unc_w"] = (("z", "y", "x"), sigma[None])
    assert uncertainty_summary(ds) == "uncertainty: median σ of the 5 valid vectors of all pairs: w 0.25 voxel"
    assert float(pair_metrics(ds)["unc_median_w"]) == pytest.approx(0.25)
    assert "partial_percent" not in pair_metrics(ds)  # no flags in the result: no figure
    part = np.array([[True, False, False], [False, False, True]])
    flag = np.array([[True, True, False], [True, False, False]])  # a partial window is never flagged by widim
    ds = ds.assign(partial=(("z", "y", "x"), part[None]), unresolved=(("z", "y", "x"), flag[None]))
    m = pair_metrics(ds)
    assert float(m["partial_percent"]) == pytest.approx(40.0)  # 2 of the 5 valid vectors
    assert float(m["unresolved_percent"]) == pytest.approx(100.0 / 3)  # of the 3 valid full windows: (0, 1)
    # the paired PIV's depth weights (piv.paired_weights): the band nearest focus over the best band, truth-free
    assert "focus_scatter_ratio" not in m
    ds.attrs.update(paired_weights="depth", paired_weight_sd_mm=[])  # too few tracks for bands: NaN, not absent
    assert np.isnan(float(pair_metrics(ds)["focus_scatter_ratio"]))
    ds.attrs["paired_weight_sd_mm"] = [0.03, 0.01, 0.012]
    assert float(pair_metrics(ds)["focus_scatter_ratio"]) == pytest.approx(3.0)


def test_empty_windows_are_counted_apart():
    """A volume that holds particles in its lower half only (a grid deeper than the seeded slab, as IPR
    leaves it: exactly 0 where no particle is): WIDIM's windows in the blank half have peak 0 and are
    invalid, and empty_percent says how many of the invalid vectors are such windows, not outliers."""
    from types import SimpleNamespace

    from lfstudy.piv import widim
    from lfstudy.process.metrics import pair_metrics
    from lfstudy.process.pipeline import _pair_line

    rng = np.random.default_rng(3)
    a = np.zeros((32, 24, 24))
    pos = rng.integers(2, 22, size=(120, 3))
    pos[:, 0] = rng.integers(2, 14, 120)  # z < 16: the upper half stays blank
    a[tuple(pos.T)] = rng.uniform(0.5, 1.0, 120)
    b = np.roll(a, 1, axis=2)  # one voxel in x
    res = widim(a, b, window=(8, 8, 8), spacing=(4, 4, 4), levels=1)
    m = pair_metrics(res)
    # the windows with nothing in a or in b, from the volumes themselves
    starts = [np.rint(res[f"{d}_index"].values - 3.5).astype(int) for d in ("z", "y", "x")]
    blank = np.array(
        [
            [
                [
                    not (a[z : z + 8, y : y + 8, x : x + 8].any() and b[z : z + 8, y : y + 8, x : x + 8].any())
                    for x in starts[2]
                ]
                for y in starts[1]
            ]
            for z in starts[0]
        ]
    )
    assert blank[starts[0] >= 16].all() and blank.mean() < 0.6  # the blank half, and few others
    empty = float(m["empty_percent"])
    assert empty == pytest.approx(100.0 * blank.mean())  # exactly those windows
    assert not res["valid"].values[blank].any()
    assert float(m["valid_percent"]) <= 100.0 - empty + 1e-9  # every empty window is invalid
    assert m["empty_percent"].attrs["units"] == "percent"

    rec = SimpleNamespace(pairs=[(0, 1)])  # what the pair's line reads of a Recording
    assert "% of the windows empty in a frame" in _pair_line(0, rec, m)


# ------------------------------------------------------------------ recording.volumetric_calibration (issue 29 §2)
VOLCAL_DEPTHS = [-2.0, -1.1, -0.25, 0.6, 1.45, 2.3]  # over the tiny grid's z = -1.78..2.13 mm
VOLCAL_SPACING = 0.5  # mm: 5.6 lenslets, 5 x 5 dots over the field


@pytest.fixture(scope="module")
def dot_target(recording) -> list[str]:
    """The dot card imaged through the real (rotated, offset) lenslet array at each depth, as 12-bit TIFFs
    (Monte-Carlo: the exact renderer refuses this 10 mrad rotation out of focus)."""
    from lfstudy.lightfield.volcal import dot_grid
    from lfstudy.optics import PlenopticCamera
    from lfstudy.simulate import render
    from lfstudy.simulate.particles import make_field

    cam = PlenopticCamera.from_config(recording["camera"])
    gx, gy = dot_grid(VOLCAL_SPACING, cam.fov_x, cam.fov_y)
    names = []
    for k, z in enumerate(VOLCAL_DEPTHS):
        field = make_field(gx, gy, np.full(gx.size, z), np.ones(gx.size))
        img = render(cam, field, 20000, 200 + k, method="montecarlo").values
        names.append(f"dots_{k}.tif")
        img = np.clip(np.rint(img * (3000.0 / img.max())), 0, FULL_12).astype(np.uint16)
        tifffile.imwrite(recording["dir"] / names[-1], img, extratags=_tags(FULL_12))
    return names


def _volcal_config(rec: dict, name: str, volcal: dict | None, model: str = "volumetric") -> Path:
    recording = {"frames": {"pairs": [["frame_1.tif", "frame_2.tif"]]}}
    if volcal is not None:
        recording["volumetric_calibration"] = volcal
    return _config(rec, name, recording, refocus={**rec["base"]["refocus"], "model": model})


def test_a_recorded_dot_target_calibrates_and_refocuses(recording, dot_target, tmp_path, capsys, monkeypatch):
    """The dot target is fitted (residual and held-out error in the summary, the store and the report's
    table) and the frames are refocused through it: the pair measures the shift as the thin-lens chain does."""
    from lfstudy.process import report

    # the HTML (figures: seconds) is the other tests'; its volumetric-calibration table is checked below
    monkeypatch.setattr(report, "write_process_report", lambda root, cfg, rec, out: Path(out).write_text("<html>"))
    vc = {"images": "dots_*.tif", "depths": VOLCAL_DEPTHS, "spacing": VOLCAL_SPACING}
    out = tmp_path / "vol"
    assert main(["process", str(_volcal_config(recording, "volcal", vc)), "--out", str(out)]) == 0
    log = capsys.readouterr().out
    line = next(ln for ln in log.splitlines() if ln.startswith("volumetric calibration"))
    cal = io.open_zarr(out / "volcal.zarr").load()
    a = cal.attrs
    assert a["depths"] == VOLCAL_DEPTHS and a["spacing"] == VOLCAL_SPACING and a["n_dots"] == 25
    assert a["sources"] == dot_target
    assert a["holdout_depth"] == -0.25  # the inner depth nearest the middle of the range
    # within half a lenslet (one in-plane voxel) of every centroid, at the fitted and at the held-out depth
    assert 0 < a["fit_rms_lenslets"] < 0.5 and 0 < a["holdout_rms_lenslets"] < 0.5, a
    assert f"fit residual {a['fit_rms_lenslets']:.4f} lenslets RMS" in line, line
    assert f"held-out z = -0.25 mm {a['holdout_rms_lenslets']:.4f} lenslets RMS" in line, line
    assert int(cal["valid"].sum()) > 60  # most of the 12 x 12 sub-apertures
    stack = io.open_array(out / "frames/000/stack.zarr")
    assert stack.attrs["refocus"].startswith("volumetric calibration")
    piv = io.open_zarr(out / "piv.zarr").load()
    valid = piv["valid"].values
    assert valid.mean() > 0.8
    assert abs(piv["u"].values[valid].mean() - SHIFT_MM / VOXEL_MM) < 0.1
    assert abs(piv["v"].values[valid].mean()) < 0.1
    table = report.volcal_block(out).html
    assert f"{a['holdout_rms_lenslets']:.4f} at z = -0.25 mm" in table and f"{a['fit_rms_lenslets']:.4f}" in table
    assert report.volcal_block(tmp_path) is None


def test_volumetric_calibration_refusals(recording, cli_error, tmp_path):
    """Each bad setting is one line naming the field, before anything is written."""
    five = [f"frame_{k}.tif" for k in (1, 2, 3)] + ["frame_1.tif", "frame_2.tif"]  # stand-ins: counts only
    cases = {
        "no_section": (None, "config key 'refocus.model' = 'volumetric' needs the dot-target images"),
        "missing": (
            {"images": ["dots_x.tif"] * 6, "depths": VOLCAL_DEPTHS, "spacing": 0.5},
            "recording.volumetric_calibration.images: image file",
        ),
        "count": (
            {"images": five, "depths": VOLCAL_DEPTHS, "spacing": 0.5},
            "recording.volumetric_calibration.images: 5 images for 6 depths",
        ),
        "few_depths": (
            {"images": five[:3], "depths": [-1.0, 0.0, 1.0], "spacing": 0.5},
            "'recording.volumetric_calibration.depths': 3 depths for a polynomial of order 3",
        ),
        "same_depth": (
            {"images": five, "depths": [-1.0, 0.0, 0.0, 1.0, 2.0], "spacing": 0.5},
            "the depths must be distinct",
        ),
        "shallow": (
            {"images": five, "depths": [-1.0, -0.5, 0.0, 0.5, 1.0], "spacing": 0.5},
            "recording.volumetric_calibration.depths cover z = -1..1 mm but the reconstruction grid spans",
        ),
        "spacing": ({"images": five, "depths": VOLCAL_DEPTHS, "spacing": -0.5}, "recording.volumetric_calibration"),
    }
    for name, (vc, expect) in cases.items():
        out = tmp_path / name
        line = cli_error("process", str(_volcal_config(recording, f"volcal_{name}", vc)), "--out", str(out))
        assert expect in line, (name, line)
        _no_output(out)


def test_dot_grid_origin():
    from lfstudy.lightfield.volcal import VolumetricCalibrationError, dot_grid

    x0, y0 = dot_grid(0.5, 2.8, 2.0)
    x1, y1 = dot_grid(0.5, 2.8, 2.0, origin=(0.0, 0.0))
    np.testing.assert_array_equal(x0, x1)
    np.testing.assert_array_equal(y0, y1)
    assert x0.size == 5 * 5 and np.abs(x0).max() == 1.0
    x, y = dot_grid(0.5, 2.8, 2.0, origin=(0.2, -0.1))
    assert np.isclose(x, 0.2).any() and np.isclose(y, -0.1).any()
    assert np.abs(x).max() <= 1.4 and np.abs(y).max() <= 1.0
    np.testing.assert_allclose(np.unique(np.round(np.diff(np.unique(x)), 12)), [0.5])
    assert sorted(np.unique(np.round(x, 9))) == pytest.approx([-1.3, -0.8, -0.3, 0.2, 0.7, 1.2])
    with pytest.raises(VolumetricCalibrationError, match="no dot of the grid"):
        dot_grid(5.0, 2.8, 2.0, origin=(2.5, 0.0))


def test_uncertainty_maps_mark_the_unresolved_vectors():
    """The recording report's σ maps cross out the vectors flagged unresolved on the slice shown."""
    import xarray as xr

    from lfstudy.study.figures import uncertainty_maps

    shape = (3, 4, 5)
    flag = np.zeros(shape, bool)
    flag[1, 2, 3] = flag[1, 0, 0] = True  # the middle slice (z index 1): two flags
    flag[0, 1, 1] = True  # another slice: not drawn
    coords = {d: np.arange(n, dtype=float) for d, n in zip("zyx", shape)}
    piv = xr.Dataset(
        {"unc_u_mm": (("z", "y", "x"), np.full(shape, 0.01)), "unresolved": (("z", "y", "x"), flag)}, coords=coords
    )
    fig = uncertainty_maps(piv)
    assert "red x: unresolved, 2 of 20 vectors" in fig._suptitle.get_text()
    assert len(fig.axes[0].collections) == 2  # the σ map and the crosses
    assert "red x" not in uncertainty_maps(piv.drop_vars("unresolved"))._suptitle.get_text()
    part = np.zeros(shape, bool)
    part[:, 3] = True  # the row y = 3 reaches past the seeded region: five windows on the slice
    fig = uncertainty_maps(piv.assign(partial=(("z", "y", "x"), part)))
    assert "grey dot: partial window, 5 of 20" in fig._suptitle.get_text()
    assert len(fig.axes[0].collections) == 3  # the σ map, the crosses and the dots
