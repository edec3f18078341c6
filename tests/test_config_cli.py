from __future__ import annotations

import copy
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from lfstudy.cli import main
from lfstudy.config import ConfigError
from lfstudy.study.config import case_config, expand_cases, load_config, sweep_of, validate_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def demo_raw():
    return yaml.safe_load((ROOT / "config" / "demo.yaml").read_text())


def test_shipped_configs_valid():
    for name in ("demo.yaml", "thesis.yaml"):
        cfg = load_config(ROOT / "config" / name)
        # defaults filled where neither config sets them
        assert cfg["grid"]["spacing"] == "uniform" and cfg["piv"]["subpixel"] == "auto"
        assert cfg["reconstruct"]["mart"]["iterations"] == 3 and cfg["refocus"]["cubic"] is False
    thesis = load_config(ROOT / "config" / "thesis.yaml")
    assert {c.flow for c in expand_cases(thesis)} == {"uniform_x", "uniform_z", "hill"}


@pytest.mark.parametrize(
    "path",
    [p for p in sorted((ROOT / "config").glob("*.yaml")) if p.name != "schema.yaml"]
    + sorted((ROOT / "benchmarks").glob("*.yaml")),
    ids=lambda p: f"{p.parent.name}/{p.name}",
)
def test_every_shipped_study_config_loads_and_sweeps(path):
    """Every study config in config/ and benchmarks/ (the benchmarks' headers quote figures measured with them)
    still passes the schema and expands to its cases: a renamed setting would otherwise leave them to rot."""
    cases = expand_cases(load_config(path))
    assert cases and len({c.case_id for c in cases}) == len(cases)


def test_demo_sweeps_designs_flows_and_a_dotted_setting(demo_raw):
    """The demo: 2 magnifications x 2 lenslet pitches x (uniform shift, Hill's vortex), IPR without depth
    calibration, its PIV pairing the fitted particles; pinned so that its runtime cannot creep. The depth
    calibration swept by its dotted path on top shares every stage up to the reconstruction."""
    cfg = validate_config(demo_raw)
    cases = expand_cases(cfg)
    assert len(cases) == 8
    for key in ("magnification", "lenslet_pitch"):
        assert len({getattr(c, key) for c in cases}) == 2
    assert {c.flow for c in cases} == {"uniform_x", "hill"}
    assert cfg["camera"]["sensor"]["n_pixels_x"] * cfg["camera"]["sensor"]["n_pixels_y"] == 640 * 480
    assert cfg["particles"]["ppp"] == 0.005 and cfg["raytrace"]["rays_per_particle"] == 4000
    assert cfg["raytrace"]["method"] == "montecarlo"  # not the model IPR fits (issue 39)
    ids = [c.case_id for c in cases]
    assert len(set(ids)) == len(ids)
    assert ids[0] == "mag~-1/fnum~matched/pitch~0.0888/ppp~0.005/flow~uniform_x"
    assert sweep_of(cfg).case(ids[5]) == cases[5]
    one = case_config(cfg, ids[-1])
    assert one["camera"]["magnification"] == cases[-1].magnification
    assert one["flow"]["name"] == "hill" and one["reconstruct"]["method"] == "ipr"
    assert one["depth_calibration"]["enabled"] is False and one["piv"]["particles"] == "paired"
    # the calibration on/off swept share every stage up to the reconstruction: 8 volumes per frame, 4 calibrations
    raw = {**demo_raw, "sweep": {**demo_raw["sweep"], "depth_calibration.enabled": [False, True]}}
    both = validate_config(raw)
    assert {c.params["depth_calibration.enabled"] for c in expand_cases(both)} == {False, True}
    sw = sweep_of(both)
    assert len(expand_cases(both)) == 16
    assert len(sw.stage_ids("reconstruct")) == 8 and len(sw.stage_ids("depthcal")) == 4
    # every design reconstructs the seeded slab
    assert one["grid"]["z_range"] == [-one["particles"]["z_span"] / 2, one["particles"]["z_span"] / 2]


@pytest.mark.parametrize(
    "path, value, match",
    [
        (("camera", "lenslet", "pitch"), -0.1, r"camera\.lenslet\.pitch.*\(0, 10\]"),
        (("particles", "ppp"), 1.5, r"particles\.ppp.*\(0, 1\]"),
        (("particles", "ppp"), 0, r"particles\.ppp"),
        (("camera", "magnification"), 1.0, r"camera\.magnification.*< *0|camera\.magnification.*0\)"),
        (("sweep", "flow"), ["uniform_x", "tornado"], r"sweep\.flow.*tornado.*allowed"),
        (("sweep", "fnumber"), [0.5], r"cannot reach.*\[1, 32\]"),
        (("camera", "main_lens", "fnumber"), "wide", r"camera\.main_lens\.fnumber.*matched"),
        (("flows", "uniform_x", "kind"), "vortex", r"flows\.uniform_x\.kind.*'uniform', 'hill'"),
        (("camera", "sensor", "n_pixels_x"), 2.5, r"camera\.sensor\.n_pixels_x"),
        (("refocus", "unknown_key"), 1, r"unknown_key"),
    ],
)
def test_bad_config_names_key(demo_raw, path, value, match):
    cfg = copy.deepcopy(demo_raw)
    node = cfg
    for k in path[:-1]:
        node = node.setdefault(k, {})
    node[path[-1]] = value
    with pytest.raises(ConfigError, match=match):
        validate_config(cfg)


@pytest.mark.parametrize(
    "where, key, message",
    [
        ((), "camerra", "config key 'camerra': not a setting; allowed keys at the top level are camera, compute, "),
        (
            ("camera", "lenslet"),
            "pich",
            "config key 'camera.lenslet.pich': not a setting; allowed keys under 'camera.lenslet' are fnumber, "
            "focal_length, offset_x, offset_y, pitch, rotation (did you mean 'pich' -> 'pitch'?)",
        ),
        (("reconstruct", "mart"), "iters", "config key 'reconstruct.mart.iters': not a setting; allowed keys under "),
    ],
)
def test_unknown_key_names_its_path_not_the_whole_config(demo_raw, where, key, message):
    cfg = copy.deepcopy(demo_raw)
    node = cfg
    for k in where:
        node = node.setdefault(k, {})
    node[key] = 1
    with pytest.raises(ConfigError) as err:
        validate_config(cfg)
    msg = str(err.value)
    assert msg.startswith(message), msg
    assert "demo" not in msg and "{" not in msg and len(msg) < 300, msg  # no dump of the config


def test_a_wrong_type_names_what_is_expected_without_the_whole_value(demo_raw):
    cfg = copy.deepcopy(demo_raw)
    cfg["sweep"] = [[0.001] * 50] * 50
    with pytest.raises(ConfigError) as err:
        validate_config(cfg)
    msg = str(err.value)
    assert msg.startswith("config key 'sweep' = [[0.001, ") and msg.endswith(" ...: expected a mapping of keys"), msg
    assert len(msg) < 150, msg


def test_sweep_fnumber_unreachable(demo_raw):
    cfg = copy.deepcopy(demo_raw)
    cfg["sweep"]["fnumber"] = ["matched", 64.0]
    with pytest.raises(ConfigError, match="cannot reach"):
        validate_config(cfg)


def test_cli_optics_prints_table51(capsys):
    assert main(["optics", str(ROOT / "config" / "thesis.yaml")]) == 0
    out = capsys.readouterr().out
    assert "289 x 193" in out and "-5.8236" in out and "6.1837" in out


def test_cli_cases_and_errors(capsys, tmp_path):
    assert main(["cases", str(ROOT / "config" / "demo.yaml"), "--ids"]) == 0
    assert len(capsys.readouterr().out.split()) == 8
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "camera: {sensor: {n_pixels_x: 64, n_pixels_y: 64, pixel_pitch: 0.0074}, "
        "lenslet: {pitch: 0.1, focal_length: 0.4}, main_lens: {focal_length: 50}, magnification: 2}\n"
    )
    assert main(["cases", str(bad)]) == 2
    assert "camera.magnification" in capsys.readouterr().err


# ------------------------------------------------------------------ study configs through Snakemake
def _snakemake_dry_run(config: Path, workdir: Path, **env: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(workdir)]
    cmd += ["--configfile", str(config), "-n", "--quiet", "rules", "--cores", "1"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, **env})


def _tiny(tmp_path: Path, name: str, edit=None, extra: str = "") -> Path:
    """tests/data/tiny.yaml edited (re-dumped) or as written, with ``extra`` lines appended."""
    text = (ROOT / "tests" / "data" / "tiny.yaml").read_text()
    if edit is not None:
        raw = yaml.safe_load(text)
        edit(raw)
        text = yaml.safe_dump(raw, sort_keys=False)
    path = tmp_path / f"{name}.yaml"
    path.write_text(text + extra)
    return path


def _big_sweep(c: dict) -> None:  # 100 x 100 = 10,000 cases
    c["sweep"] = {"ppp": [round(0.001 + 1e-5 * k, 6) for k in range(100)], "seed": list(range(100))}


@pytest.mark.parametrize(
    ("name", "edit", "extra", "message"),
    [
        (
            "rays",
            lambda c: c["raytrace"].update(rays_per_particle=10**8),
            "",
            "config key 'raytrace.rays_per_particle' = 100000000: allowed range is [1, 10000000]",
        ),
        ("dup", None, "seed: 4\n", "key 'seed' is given twice (lines 3 and 20); YAML keeps only the last"),
        (
            "window",
            lambda c: c["piv"].update(window=[8, 64, 64]),
            "",
            "config key 'piv.window' = [8, 64, 64] (case mag~-1/fnum~matched/pitch~0.0888/ppp~0.002/flow~uniform_x): "
            "64 along y exceeds 32, 64 along x exceeds 32 voxels of the reconstruction grid of 12 x 32 x 32 voxels "
            "(z, y, x); allowed range per axis is z [4, 12], y [4, 32], x [4, 32]",
        ),
        (
            "big",
            _big_sweep,
            "",
            "config key 'sweep': the sweep makes 10000 cases (the product of its lists' lengths), more than the "
            "limit of 2000; validating and planning that many takes minutes before any job runs. Sweep fewer "
            "values, or set LFSTUDY_MAX_CASES=10000 in the environment to run them all",
        ),
    ],
)
def test_snakemake_refuses_bad_study_configs(tmp_path, name, edit, extra, message):
    """Before the DAG: a ray count the renderer cannot take, a key given twice (Snakemake's YAML reader
    keeps the last), PIV windows larger than the volumes (found otherwise at the PIV jobs, after the
    images, calibration and reconstruction), a 100 x 100 sweep (which sat in "Building DAG" for over 300 s)."""
    config = _tiny(tmp_path, name, edit, extra)
    t0 = time.perf_counter()
    r = _snakemake_dry_run(config, tmp_path / "work")
    seconds = time.perf_counter() - t0
    assert r.returncode != 0, r.stdout[-2000:]
    text = " ".join((r.stdout + r.stderr).split())
    assert message in text, text[-3000:]
    assert "Building DAG" not in text, text[-3000:]
    assert seconds < 120, seconds  # the start of Python and Snakemake; no per-case work


def test_snakemake_says_how_many_cases(tmp_path):
    r = _snakemake_dry_run(ROOT / "tests" / "data" / "tiny.yaml", tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "lfstudy: study 'tiny' sweeps 2 cases" in r.stderr


def test_sweep_size_limit_is_checked_before_the_cases(tmp_path, capsys, monkeypatch):
    """`lfstudy cases` refuses the 100 x 100 sweep at once; LFSTUDY_MAX_CASES moves the limit."""
    config = _tiny(tmp_path, "big", _big_sweep)
    t0 = time.perf_counter()
    assert main(["cases", str(config)]) == 2
    assert time.perf_counter() - t0 < 5  # validating 10,000 cases would take minutes
    assert "the sweep makes 10000 cases" in capsys.readouterr().err
    demo = ROOT / "config" / "demo.yaml"  # 8 cases
    monkeypatch.setenv("LFSTUDY_MAX_CASES", "7")
    assert main(["cases", str(demo), "--ids"]) == 2
    assert "makes 8 cases (the product of its lists' lengths), more than the limit of 7" in capsys.readouterr().err
    monkeypatch.setenv("LFSTUDY_MAX_CASES", "8")
    assert main(["cases", str(demo), "--ids"]) == 0
    for bad in ("many", "0"):
        monkeypatch.setenv("LFSTUDY_MAX_CASES", bad)
        assert main(["cases", str(demo), "--ids"]) == 2
        assert f"LFSTUDY_MAX_CASES = {bad!r}: expected an integer >= 1" in capsys.readouterr().err


def test_duplicate_keys_name_the_key_path_and_lines(tmp_path, capsys):
    path = tmp_path / "dup.yaml"
    text = (ROOT / "config" / "demo.yaml").read_text()
    path.write_text(text + "camera:\n  magnification: -2.0\n")
    assert main(["cases", str(path)]) == 2
    first = 1 + text.splitlines().index(next(ln for ln in text.splitlines() if ln.startswith("camera:")))
    assert f"key 'camera' is given twice (lines {first} and {len(text.splitlines()) + 1})" in capsys.readouterr().err
    nested = tmp_path / "nested.yaml"
    nested.write_text("name: n\ncamera:\n  lenslet: {pitch: 0.1}\n  sensor: {}\n  lenslet:\n    pitch: 0.2\n")
    assert main(["cases", str(nested)]) == 2
    assert "key 'camera.lenslet' is given twice (lines 3 and 5)" in capsys.readouterr().err
    merged = tmp_path / "merged.yaml"  # a merge key's values may be overridden: not a duplicate
    merged.write_text("a: &b {window: [8, 16, 16], spacing: [4, 8, 8]}\nb:\n  <<: *b\n  window: [4, 4, 4]\n")
    from lfstudy.config import read_yaml

    assert read_yaml(merged)["b"] == {"window": [4, 4, 4], "spacing": [4, 8, 8]}
