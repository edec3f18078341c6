"""Outputs never replace data lfstudy did not write: io.output_dir, io.atomic_path's temporaries, and the
--out of every command that writes a directory or store (process: tests/test_process.py)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr

from lfstudy import io
from lfstudy.cli import main


def _host() -> str:
    import re

    return re.sub(r"[^A-Za-z0-9_.]", "_", socket.gethostname())


def _dead_pid() -> int:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(dead.stdout)


def test_atomic_path_leaves_live_writers_temporaries(tmp_path):
    """Only the temporaries of a dead writer of this host are cleared, not a live run's (nor another
    host's, which this host cannot tell alive), nor files merely named like a temporary."""
    dead_pid = _dead_pid()
    live = tmp_path / f".s.zarr.lfstudy-tmp-{_host()}-{os.getpid()}-0123abcd"
    killed = tmp_path / f".s.zarr.lfstudy-tmp-{_host()}-{dead_pid}-0123abcd"
    other = tmp_path / f".s.zarr.lfstudy-tmp-elsewhere-{dead_pid}-0123abcd"
    users = [tmp_path / ".s.zarr.tmp-89abcdef", tmp_path / f".s.zarr.tmp-{_host()}-{dead_pid}-0123abcd"]
    for p in (live, killed, other, *users):
        p.mkdir()
    (users[0] / "keep.txt").write_text("mine")
    with io.atomic_path(tmp_path / "s.zarr") as tmp:
        tmp.mkdir()
        assert tmp.name.startswith(f".s.zarr.lfstudy-tmp-{_host()}-{os.getpid()}-")
    assert live.is_dir() and other.is_dir() and not killed.exists()
    assert all(p.is_dir() for p in users) and (users[0] / "keep.txt").read_text() == "mine"
    assert (tmp_path / "s.zarr").is_dir()


def test_a_swap_killed_midway_is_repaired_by_the_next_run(tmp_path):
    """A writer killed during its swap leaves the earlier output parked as .NAME.lfstudy-old-...: the
    next run moves it back when nothing replaced it, and removes it when the new output is in place."""
    dead_pid = _dead_pid()
    out = tmp_path / "o"
    with io.output_dir(out, command="piv") as tmp:
        (tmp / "a").write_text("1")
    parked = tmp_path / f".o.lfstudy-old-{_host()}-{dead_pid}-0123abcd"
    out.rename(parked)  # killed after parking the earlier output, before moving the new one in
    assert io.clear_stale(out) == [parked]
    assert (out / "a").read_text() == "1" and not parked.exists()
    parked.mkdir()
    (parked / "a").write_text("0")  # killed after the swap, before removing the earlier output
    with io.output_dir(out, command="piv", overwrite=True) as tmp:
        (tmp / "a").write_text("2")
    assert (out / "a").read_text() == "2" and not list(tmp_path.glob(".*"))


def test_output_dir_marks_and_replaces_only_with_overwrite(tmp_path):
    out = tmp_path / "o"
    with io.output_dir(out, command="piv") as tmp:
        (tmp / "a").write_text("1")
    assert io.output_marker(out)["command"] == "piv" and (out / "a").read_text() == "1"
    with pytest.raises(io.OutputError, match="give --overwrite"), io.output_dir(out, command="piv"):
        pass
    with pytest.raises(io.OutputError, match="is an output of lfstudy piv"):
        io.check_output(out, command="calibrate", overwrite=True)
    with pytest.raises(RuntimeError), io.output_dir(out, command="piv", overwrite=True) as tmp:
        (tmp / "b").write_text("2")
        raise RuntimeError  # a failed run leaves the earlier output as it was
    assert sorted(p.name for p in out.iterdir()) == [io.MARKER, "a"]
    with io.output_dir(out, command="piv", overwrite=True) as tmp:
        (tmp / "b").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [io.MARKER, "b"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with io.output_dir(empty, command="piv") as tmp:  # an empty directory holds nothing to lose
        (tmp / "a").write_text("1")
    assert not list(tmp_path.glob(".*"))
    with pytest.raises(io.OutputError, match="root of the file system"):
        io.check_output("/", command="piv")


@pytest.fixture
def frames(tmp_path) -> tuple[Path, Path]:
    rng = np.random.default_rng(0)
    a = np.zeros((16, 32, 32), np.float32)
    idx = rng.integers(2, 28, (40, 3))
    a[idx[:, 0] % 14 + 1, idx[:, 1], idx[:, 2]] = 1.0
    b = np.roll(a, 1, axis=2)
    pa, pb = tmp_path / "in" / "a.tif", tmp_path / "in" / "b.tif"
    pa.parent.mkdir()
    tifffile.imwrite(pa, a)
    tifffile.imwrite(pb, b)
    return pa, pb


def _piv(pa: Path, pb: Path, out: Path | str, *extra: str) -> list[str]:
    return ["piv", str(pa), str(pb), "--window", "8", "16", "16", "--levels", "1", "--out", str(out), *extra]


def test_piv_out(frames, tmp_path, cli_error, capsys):
    pa, pb = frames
    user = tmp_path / "d"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    line = cli_error(*_piv(pa, pb, user, "--overwrite"))
    assert "no lfstudy output" in line, line
    assert (user / "notes.txt").read_text() == "mine"
    line = cli_error(*_piv(pa, pb, pa.parent))
    assert "an input of this run" in line, line
    assert sorted(p.name for p in pa.parent.iterdir()) == ["a.tif", "b.tif"]
    out = tmp_path / "piv.zarr"
    assert main(_piv(pa, pb, out)) == 0
    assert io.output_marker(out)["command"] == "piv" and "u" in io.open_zarr(out)
    capsys.readouterr()
    line = cli_error(*_piv(pa, pb, out))
    assert "give --overwrite" in line, line
    assert main(_piv(pa, pb, out, "--overwrite")) == 0
    capsys.readouterr()
    vol = io.write_zarr(xr.DataArray(tifffile.imread(pa), dims=("z", "y", "x")), tmp_path / "vol.zarr", name="v")
    line = cli_error(*_piv(vol, pb, vol, "--overwrite"))  # an input store is never replaced
    assert "an input of this run" in line, line
    assert "v" in io.open_zarr(vol)


def test_piv_leaves_files_named_like_its_own(frames, tmp_path, capsys):
    """A user's `.NAME.lock` and `.NAME.tmp-*/` beside --out are not lfstudy's lock or temporary: a run
    leaves them as they were; a swap a killed run left half done is tidied by the next run."""
    pa, pb = frames
    out = tmp_path / "pivnew.zarr"
    lock = tmp_path / ".pivnew.zarr.lock"
    lock.write_text("mine")
    keep = tmp_path / ".pivnew.zarr.tmp-0123abcd" / "keep.txt"
    keep.parent.mkdir()
    keep.write_text("mine")
    assert main(_piv(pa, pb, out)) == 0
    assert lock.read_text() == "mine" and keep.read_text() == "mine"
    parked = tmp_path / f".pivnew.zarr.lfstudy-old-{_host()}-{_dead_pid()}-0123abcd"
    parked.mkdir()  # the earlier output of a run killed during its swap, after the new one was moved in
    (parked / "zarr.json").write_text("{}")
    assert main(_piv(pa, pb, out, "--overwrite")) == 0
    assert not parked.exists() and "u" in io.open_zarr(out)
    assert sorted(p.name for p in tmp_path.glob(".*")) == [".pivnew.zarr.lock", ".pivnew.zarr.tmp-0123abcd"]
    capsys.readouterr()


def test_calibrate_out(tmp_path, cli_error):
    img = xr.DataArray(np.ones((8, 8)), dims=("row", "col"))
    io.write_tiff(img, tmp_path / "p.tif")
    user = tmp_path / "c.zarr"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    line = cli_error("calibrate", str(tmp_path / "p.tif"), "--pixel-pitch", "0.0074", "--out", str(user))
    assert "no lfstudy output" in line, line
    assert (user / "notes.txt").read_text() == "mine"


def test_render_and_simulate_refuse_user_data(tmp_path, cli_error):
    cfg = Path(__file__).parent / "data" / "tiny.yaml"
    user = tmp_path / "d"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    line = cli_error("simulate", str(cfg), "--out", str(user))
    assert "no lfstudy output" in line, line
    (user / "volume.zarr").mkdir()
    (user / "volume.zarr" / "zarr.json").write_text("{}")  # a store of the user
    raw = tmp_path / "raw.tif"
    tifffile.imwrite(raw, np.zeros((384, 384), np.uint16))
    cen = tmp_path / "cen.zarr"
    line = cli_error("render", str(raw), "--centers", str(cen), "--config", str(cfg), "--out", str(user))
    assert "volume.zarr' exists and is no lfstudy output" in line, line
    assert sorted(p.name for p in user.iterdir()) == ["notes.txt", "volume.zarr"]


def test_export_replaces_a_file_only_with_overwrite(frames, tmp_path, cli_error, capsys):
    pa, pb = frames
    store = tmp_path / "piv.zarr"
    assert main(_piv(pa, pb, store)) == 0
    target = tmp_path / "piv.vtr"
    target.write_text("mine")
    capsys.readouterr()
    line = cli_error("export", str(store), "--out", str(target))
    assert "exists; give --overwrite" in line and target.read_text() == "mine", line
    line = cli_error("export", str(store), "--out", str(store / "x.vtr"), "--overwrite")
    assert "lies inside the exported store" in line, line
    assert main(["export", str(store), "--out", str(target), "--overwrite"]) == 0
    assert target.read_bytes().startswith(b"<?xml")


def test_simulate_quiet_and_its_out(tmp_path, cli_error, capsys):
    """`simulate --quiet` prints no progress bar; its output is marked, and a rerun needs --overwrite."""
    cfg = Path(__file__).parent / "data" / "tiny.yaml"
    out = tmp_path / "sim"
    assert main(["simulate", str(cfg), "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "%" not in captured.err and "[#" not in captured.out + captured.err, captured.err
    assert io.output_marker(out)["command"] == "simulate" and (out / "image_a.tif").is_file()
    line = cli_error("simulate", str(cfg), "--out", str(out))
    assert "give --overwrite" in line, line
