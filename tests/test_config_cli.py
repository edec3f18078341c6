from __future__ import annotations

import copy
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


def test_demo_sweeps_designs_flows_and_a_dotted_setting(demo_raw):
    """The demo: 2 magnifications x 2 lenslet pitches x (uniform shift, Hill's vortex), MART, without and
    with the depth calibration; pinned so that its runtime cannot creep."""
    cfg = validate_config(demo_raw)
    cases = expand_cases(cfg)
    assert len(cases) == 16
    for key in ("magnification", "lenslet_pitch"):
        assert len({getattr(c, key) for c in cases}) == 2
    assert {c.flow for c in cases} == {"uniform_x", "hill"}
    assert {c.params["depth_calibration.enabled"] for c in cases} == {False, True}
    assert cfg["camera"]["sensor"]["n_pixels_x"] * cfg["camera"]["sensor"]["n_pixels_y"] == 640 * 480
    assert cfg["particles"]["ppp"] == 0.005 and cfg["raytrace"]["rays_per_particle"] == 4000
    ids = [c.case_id for c in cases]
    assert len(set(ids)) == len(ids)
    assert ids[0] == "mag~-1/fnum~matched/pitch~0.0888/ppp~0.005/flow~uniform_x/depth_calibration.enabled~false"
    assert sweep_of(cfg).case(ids[5]) == cases[5]
    one = case_config(cfg, ids[-1])
    assert one["camera"]["magnification"] == cases[-1].magnification
    assert one["flow"]["name"] == "hill" and one["reconstruct"]["method"] == "mart"
    assert one["depth_calibration"]["enabled"] is True
    # the calibration on/off share every stage up to the reconstruction: 8 volumes per frame, 4 calibrations
    sw = sweep_of(cfg)
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
    assert len(capsys.readouterr().out.split()) == 16
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "camera: {sensor: {n_pixels_x: 64, n_pixels_y: 64, pixel_pitch: 0.0074}, "
        "lenslet: {pitch: 0.1, focal_length: 0.4}, main_lens: {focal_length: 50}, magnification: 2}\n"
    )
    assert main(["cases", str(bad)]) == 2
    assert "camera.magnification" in capsys.readouterr().err
