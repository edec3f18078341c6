"""σ calibrated by a study (issue 38, Beyond): the factors from a study table, the choice of a design,
the refusals, and the scaled σ beside the raw one. Fast: synthetic study tables, no Snakemake.

`lfstudy process` applying it to a recording is in tests/test_process.py (it reuses that file's recording).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr
import yaml

from lfstudy import io
from lfstudy.config import ConfigError
from lfstudy.process.uncertainty_calibration import (
    CalibrationError,
    apply_calibration,
    calibration_factors,
    fit_calibration,
    read_study,
)
from lfstudy.study.sweep import NAMED, Case, Setting
from lfstudy.study.table import combine_cases, to_csv

SEED = Setting("seed", "seed", "seed", "study seed", "1")
SETTINGS = [*NAMED.values(), SEED]
PITCHES = (0.0888, 0.1184)
FLOWS = ("uniform_x", "hill")
SEEDS = (1, 2)


def _ratio(pitch: float, flow: str, seed: int, ax: str) -> float:
    """A made-up ratio per case and axis: z too small by ~3 on the fine pitch, ~2 on the coarse one."""
    base = {"x": 1.1, "y": 0.9, "z": 3.0 if pitch == PITCHES[0] else 2.0}[ax]
    return base * (1.3 if flow == "hill" else 1.0) * (1.0 + 0.05 * seed)


@pytest.fixture(scope="module")
def study() -> xr.Dataset:
    rows = []
    for pitch in PITCHES:
        for flow in FLOWS:
            for seed in SEEDS:
                case = Case.of(
                    magnification=-1.0, fnumber="matched", lenslet_pitch=pitch, ppp=0.005, flow=flow, seed=seed
                )
                vals = {f"unc_ratio_{ax}": ((), _ratio(pitch, flow, seed, ax)) for ax in "xyz"}
                vals |= {f"unc_coverage_{ax}": ((), 0.6) for ax in "xyz"}
                rows.append((case, xr.Dataset(vals)))
    return combine_cases(rows, SETTINGS)


def test_factor_is_the_geometric_mean_of_the_designs_cases(study):
    cal = fit_calibration(study, {"mag": -1, "pitch": 0.0888}, source="s")
    assert len(cal.cases) == 4 and all("pitch~0.0888" in c for c in cal.cases)
    for ax in "xyz":
        r = [_ratio(0.0888, f, s, ax) for f in FLOWS for s in SEEDS]
        assert cal.factor[ax] == pytest.approx(math.prod(r) ** 0.25, rel=1e-12)
        assert (cal.ratio_min[ax], cal.ratio_max[ax]) == pytest.approx((min(r), max(r)))
    assert cal.design == {"magnification": "-1", "fnumber": "matched", "lenslet_pitch": "0.0888", "ppp": "0.005"}
    # a flow or a seed narrows the cases the factor is fitted on; the design stays the same
    one = fit_calibration(study, {"lenslet_pitch": 0.1184, "flow": "uniform_x", "seed": 2})
    assert one.factor["z"] == pytest.approx(_ratio(0.1184, "uniform_x", 2, "z"))
    assert one.cases == ("seed~2/mag~-1/fnum~matched/pitch~0.1184/ppp~0.005/flow~uniform_x",)
    by_case = fit_calibration(study, case=one.cases[0])
    assert by_case.factor == one.factor
    # cases that read 2 and 0.5 pool to 1, NaN and non-positive ratios are left out
    assert calibration_factors({"x": [2.0, 0.5, np.nan, 0.0, -1.0]})["x"] == pytest.approx(1.0)
    assert math.isnan(calibration_factors({"x": [np.nan]})["x"])


@pytest.mark.parametrize("name", ["study.zarr", "study.csv", "."])
def test_study_read_from_zarr_csv_or_its_folder(study, tmp_path, name):
    io.write_zarr(study, tmp_path / "study.zarr")
    to_csv(study, tmp_path / "study.csv")
    back = read_study(tmp_path / name)
    cal = fit_calibration(back, {"pitch": 0.1184})
    assert cal.factor == pytest.approx(fit_calibration(study, {"pitch": 0.1184}).factor, rel=1e-12)


@pytest.mark.parametrize(
    ("design", "case", "key", "words"),
    [
        (
            {},
            None,
            "design",
            ["matches 2 designs", "add lenslet_pitch", "lenslet_pitch=0.0888", "lenslet_pitch=0.1184"],
        ),
        ({"pitch": 0.1}, None, "design", ["no computed case", "lenslet_pitch=0.1", "the study's designs:"]),
        ({"focal": 50}, None, "design", ["'focal' is not a swept setting", "lenslet_pitch"]),
        (None, "mag~-1/nope", "case", ["not a computed case", "seed~1/mag~-1/fnum~matched/pitch~0.0888"]),
        ({"pitch": 0.0888}, "mag~-1", "case", ["not both"]),
    ],
)
def test_bad_designs_name_the_key_and_list_the_study(study, design, case, key, words):
    with pytest.raises(CalibrationError) as info:
        fit_calibration(study, design, case)
    assert info.value.key == key
    for w in words:
        assert w in str(info.value), str(info.value)


def test_a_study_without_sigma_or_without_table_is_refused(study, tmp_path):
    with pytest.raises(CalibrationError, match="has no unc_ratio_x") as info:
        fit_calibration(study.drop_vars([f"unc_ratio_{ax}" for ax in "xyz"]), {"pitch": 0.0888})
    assert info.value.key == "study"
    nan = study.copy()
    nan["unc_ratio_z"] = nan["unc_ratio_z"] * np.nan
    with pytest.raises(CalibrationError, match="finite unc_ratio_z"):
        fit_calibration(nan, {"pitch": 0.0888})
    for p in (tmp_path / "missing", tmp_path):
        with pytest.raises(CalibrationError, match="study") as info:
            read_study(p)
        assert info.value.key == "study"


def test_apply_keeps_the_raw_sigma_beside_the_calibrated(study):
    cal = fit_calibration(study, {"pitch": 0.0888}, source="results/s")
    rng = np.random.default_rng(0)
    dims = ("z", "y", "x")
    raw = {c: rng.uniform(0.01, 0.2, (2, 3, 4)) for c in "uvw"}
    piv = xr.Dataset(
        {f"unc_{c}": (dims, raw[c], {"units": "voxel", "long_name": "σ"}) for c in "uvw"}
        | {"unc_u_mm": (dims, raw["u"] * 0.09, {"units": "mm"})}
    )
    out = apply_calibration(piv, cal)
    for c, ax in zip("uvw", "xyz"):
        np.testing.assert_array_equal(out[f"unc_raw_{c}"].values, raw[c])
        np.testing.assert_allclose(out[f"unc_{c}"].values, raw[c] * cal.factor[ax], rtol=1e-12)
        assert out[f"unc_{c}"].attrs["units"] == "voxel"
    np.testing.assert_allclose(out["unc_u_mm"].values, raw["u"] * 0.09 * cal.factor["x"], rtol=1e-12)
    assert "unc_raw_w_mm" not in out  # only what the result holds
    assert out.attrs["uncertainty_calibration_study"] == "results/s"
    assert out.attrs["uncertainty_calibration_factor_z"] == pytest.approx(cal.factor["z"])
    np.testing.assert_array_equal(piv["unc_u"].values, raw["u"])  # the input is left as it was


def _recording_cfg(study_ref: str, **cal) -> dict:
    from lfstudy.study.config import load_config

    tiny = load_config(__import__("pathlib").Path(__file__).parent / "data" / "tiny.yaml")
    return {
        "camera": tiny["camera"],
        "recording": {"calibration": {"image": "pin.tif"}, "frames": {"pairs": [["a.tif", "b.tif"]]}},
        "uncertainty": {"calibration": {"study": study_ref, **cal}},
    }


def test_recording_config_checks_the_calibration_before_any_work(study, tmp_path):
    from lfstudy.process import validate_process_config

    io.write_zarr(study, tmp_path / "res" / "study.zarr")
    ok = validate_process_config(_recording_cfg("res", design={"pitch": 0.0888}), base=tmp_path)
    assert ok["uncertainty"]["calibration"]["study"] == str(tmp_path / "res")  # relative to the config
    cases = [
        (_recording_cfg("nowhere"), "'uncertainty.calibration.study'", "does not exist"),
        (_recording_cfg("res"), "'uncertainty.calibration.design'", "matches 2 designs"),
        (_recording_cfg("res", case="x~1"), "'uncertainty.calibration.case'", "not a computed case"),
        (_recording_cfg("res", design={"pitch": [1]}), "'uncertainty.calibration.design", "pitch"),
        (_recording_cfg("res", designs={}), "uncertainty.calibration", "designs"),
    ]
    for cfg, key, words in cases:
        with pytest.raises(ConfigError) as info:
            validate_process_config(cfg, base=tmp_path)
        assert key in str(info.value) and words in str(info.value), str(info.value)
    off = _recording_cfg("res", design={"pitch": 0.0888})
    off["piv"] = {"uncertainty": "none"}
    with pytest.raises(ConfigError, match=r"piv\.uncertainty is none"):
        validate_process_config(off, base=tmp_path)
    # cases that disagree by more than SPREAD: a warning that names the axes and the range
    with pytest.warns(UserWarning, match=r"disagree on σ's scale \(RMS error / RMS σ: x 1\.1\d–4\.5\), so one factor"):
        study2 = study.copy()
        study2["unc_ratio_x"] = study2["unc_ratio_x"].where(study2["flow"] != "hill", 3.0 * study2["unc_ratio_x"])
        io.write_zarr(study2, tmp_path / "res2" / "study.zarr")
        validate_process_config(_recording_cfg("res2", design={"pitch": 0.0888, "seed": 1}), base=tmp_path)
    # a design of another camera than the recording's: processed, with a warning naming the setting
    other = _recording_cfg("res", design={"pitch": 0.1184})
    with pytest.warns(UserWarning, match=r"camera.lenslet.pitch: the design's 0.1184, the recording's 0.0888"):
        validate_process_config(yaml.safe_load(yaml.safe_dump(other)), base=tmp_path)
