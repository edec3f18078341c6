"""Replicates (issues 27, 29): a study sweeping the seed reports means over the seeds ± their spread.

Constructed studies (no Snakemake): designs whose total errors scatter from seed to seed with a part
common to the designs of one seed (they image the same particles), as a real study's do.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lfstudy.study.config import load_config
from lfstudy.study.sweep import Sweep
from lfstudy.study.table import combine_cases

ROOT = Path(__file__).resolve().parents[1]
SEEDS = [1, 2, 3, 4]
#: Per-seed scatter every design of one seed shares (the particle field), and each design's own.
COMMON = {1: 0.003, 2: -0.002, 3: 0.001, 4: -0.002}
OWN = {0.0888: [0, 0, 0, 0], 0.1184: [0.002, -0.002, 0.001, -0.001], 0.148: [0.001, -0.001, 0.0, 0.0]}
#: Mean total error and in-plane spacing per design (lenslet pitch): all three on the Pareto front.
MEAN = {0.0888: 0.010, 0.1184: 0.0105, 0.148: 0.020}
SPACING = {0.0888: 0.9, 0.1184: 0.7, 0.148: 0.5}
#: MART's crosstalk of one field moved by 0, 1/4, 1/2, 3/4 lenslet (issue 27): a random draw per seed.
CROSSTALK = [0.288, -0.273, -0.312, 0.228]


def _config(sweep: dict) -> dict:
    cfg = load_config(ROOT / "config" / "demo.yaml")
    cfg["sweep"] = {"magnification": [-1.0], "flow": ["uniform_x"], **sweep}
    return cfg


@pytest.fixture(scope="module")
def rep_study():
    """Three designs x four seeds. Pitch 0.0888 is the lowest mean error; 0.1184 is 0.0005 mm worse, within
    its paired scatter (s.e. 0.0009 mm): not separable; 0.148 is 0.010 mm worse (s.e. 0.0003): separable."""
    cfg = _config({"seed": SEEDS, "lenslet_pitch": list(MEAN)})
    sweep = Sweep(cfg)
    rows = []
    for case in sweep.cases():
        p, k = case.lenslet_pitch, SEEDS.index(case["seed"])
        e = MEAN[p] + COMMON[case["seed"]] + OWN[p][k]
        vals = {
            "rms_total_mm": e,
            "rel_error": e / 0.2,
            "spacing_mm_x": SPACING[p],
            "spacing_mm_z": 0.5,
            "valid_percent": 95.0 + k,
            "oracle_rms_total_mm": 0.004,
            "recon_added_rms_total_mm": float(np.sqrt(e**2 - 0.004**2)),
            "crosstalk_z": CROSSTALK[k],
        }
        rows.append((case, xr.Dataset({n: ((), v) for n, v in vals.items()})))
    return combine_cases(rows, sweep.settings), cfg


def test_a_study_sweeps_the_seed_as_its_replicates(rep_study):
    """Each seed is its own case (its own derived seeds); within a seed the designs share their particle field."""
    from lfstudy.study.case import derive_seed
    from lfstudy.study.config import case_config

    study, cfg = rep_study
    sweep = Sweep(cfg)
    assert sweep.keys[0] == "seed" and len(sweep) == 12
    ids = [c.case_id for c in sweep.cases()]
    assert ids[0].startswith("seed~1/mag~-1/") and len(set(ids)) == 12
    part = {}
    for cid in ids:
        cc = case_config(cfg, cid)
        key = derive_seed(cc["seed"], "particles", float(cc["camera"]["magnification"]), float(cc["particles"]["ppp"]))
        part.setdefault(cc["seed"], set()).add(key)
    assert all(len(v) == 1 for v in part.values())  # common random numbers across the designs of one seed
    assert len({next(iter(v)) for v in part.values()}) == len(SEEDS)  # each replicate its own field
    assert dict(study.sizes)["seed"] == 4 and study["seed"].attrs["sweep_key"] == "seed"


def test_the_recommendation_ranks_on_the_mean_and_names_what_it_cannot_separate(rep_study, tmp_path):
    from lfstudy.study.designs import budget_table, design_table, recommend
    from lfstudy.study.replicates import paired_difference, replicate_stats
    from lfstudy.study.report import _answer_blocks, write_html

    study, cfg = rep_study
    dt = design_table(study)
    assert len(dt) == 3 and "seed" not in dt and not dt["design"].str.contains("seed").any()
    fine = dt[dt["lenslet_pitch"] == 0.0888].iloc[0]
    e = [MEAN[0.0888] + COMMON[s] for s in SEEDS]
    assert fine["rms_total_mm"] == pytest.approx(np.mean(e))
    assert fine["rms_total_mm_sd"] == pytest.approx(np.std(e, ddof=1))
    assert fine["rms_total_mm_se"] == pytest.approx(np.std(e, ddof=1) / 2) and fine["n_replicates"] == 4
    table, sentences = recommend(study)
    assert table["pareto"].all() and table.loc[table["recommended"], "lenslet_pitch"].tolist() == [0.0888]
    by = table.set_index("lenslet_pitch")
    d, se, n = paired_difference(np.asarray(OWN[0.1184]) + 0.0005, np.zeros(4))
    assert by.loc[0.1184, "diff_rms_total_mm"] == pytest.approx(d) and n == 4
    assert by.loc[0.1184, "diff_rms_total_mm_se"] == pytest.approx(se) and d < 2 * se
    assert by.loc[0.1184, "separable"] is False and by.loc[0.148, "separable"] is True
    # the paired s.e. is smaller than the unpaired one: the seed's common part cancels
    stats = replicate_stats(study).se["rms_total_mm"].squeeze()
    assert by.loc[0.148, "diff_rms_total_mm_se"] < float(np.hypot(*stats.sel(lenslet_pitch=[0.0888, 0.148]).values))
    s = sentences["uniform_x"]
    assert "Over 4 replicates" in s and "not separable from M=-1 f/#=matched pitch=0.1184" in s
    assert "pitch=0.148 (" not in s  # separable: not named
    # the budget table: crosstalk as mean ± s.e. (its sign is the finding), the rest ± sd
    bt = budget_table(study)
    row = bt[bt["design"].str.contains("pitch=0.0888")].iloc[0]
    assert row["crosstalk_z"] == pytest.approx(np.mean(CROSSTALK))
    assert row["crosstalk_z_se"] == pytest.approx(np.std(CROSSTALK, ddof=1) / 2) and "crosstalk_z_sd" not in bt
    assert "rms_total_mm_sd" in bt
    blocks = list(_answer_blocks(study, cfg))
    fig = next(b.figure for b in blocks if b.name == "pareto_uniform_x")
    bars = fig.axes[0].containers  # the Pareto figure: each design's mean with its sd over the seeds
    assert len(bars) == 1 and np.allclose(bars[0].lines[2][0].get_segments()[0][:, 1] - fine["rms_total_mm"],
                                          [-fine["rms_total_mm_sd"], fine["rms_total_mm_sd"]])  # fmt: skip
    for b in blocks:
        b.figure = None
    text = write_html(blocks, {"answer": "A"}, "t", "t", "", tmp_path / "a.html").read_text()
    assert "crosstalk_<wbr>z ± s.e." in text
    assert f"{np.mean(CROSSTALK):.3g} ± {np.std(CROSSTALK, ddof=1) / 2:.3g}" in text
    assert "rms_<wbr>total_<wbr>mm ± s.e." in text and "no (within noise)" in text and "<td>yes</td>" in text


def test_a_report_without_replicates_has_no_spread(rep_study):
    """One seed: the plain study (no seed dimension beyond one value), no ± anywhere in the answer."""
    from lfstudy.study.designs import budget_table, recommend
    from lfstudy.study.replicates import replicate_dim

    study, _ = rep_study
    one = study.isel(seed=[0])
    assert replicate_dim(one) is None
    table, sentences = recommend(one)
    assert "separable" not in table and "replicates" not in sentences["uniform_x"]
    assert "crosstalk_z_se" not in budget_table(one)


GAP = "camera.imperfections.lenslet_gap_error"
ROT = "camera.imperfections.lenslet_rotation"


def test_a_tolerance_cost_is_judged_against_its_standard_error(tmp_path):
    """A 2 % gap error costs 0.005 mm at every seed (± 0.0002): beyond noise. A 3 mrad rotation costs
    0.0003 mm on average against a per-seed scatter of 0.002 mm: within noise. The seeds' common scatter
    (0.003 mm, larger than either cost) cancels in the paired differences."""

    from lfstudy.study.replicates import pm
    from lfstudy.study.report import _answer_blocks, write_html
    from lfstudy.study.tolerance import limiting_tolerances, tolerance_table, worst_case

    cfg = _config({"seed": SEEDS, "lenslet_pitch": [0.0888], GAP: [0.0, 0.02], ROT: [0.0, 3.0]})
    cfg["report"] = {"rank_at": "tolerances"}
    sweep = Sweep(cfg)
    gap_noise, rot_noise = [0.0002, -0.0002, 0.0001, -0.0001], [0.002, -0.0018, 0.0015, -0.0005]
    rows = []
    for case in sweep.cases():
        k = SEEDS.index(case["seed"])
        e = 0.010 + COMMON[case["seed"]]
        e += (0.005 + gap_noise[k]) if case[GAP] else 0.0
        e += rot_noise[k] if case[ROT] else 0.0  # mean 0.0003 mm
        vals = {"rms_total_mm": e, "rms_x_mm": e / 2, "valid_percent": 95.0, "spacing_mm_x": 0.4, "spacing_mm_z": 0.5}
        rows.append((case, xr.Dataset({n: ((), v) for n, v in vals.items()})))
    study = combine_cases(rows, sweep.settings)
    lim = limiting_tolerances(study).iloc[0]
    gap, rot = "+lenslet-to-sensor gap error", "+lenslet grid rotation error [mrad]"
    assert lim[gap] == pytest.approx(0.005) and lim[f"{gap} beyond noise"]
    assert lim[f"{gap} s.e."] == pytest.approx(np.std(gap_noise, ddof=1) / 2)
    assert lim[rot] == pytest.approx(np.mean(rot_noise)) and not lim[f"{rot} beyond noise"]
    assert lim[rot] > 0 and lim["limited_by"] == "lenslet-to-sensor gap error 0.02"
    assert lim["ideal rms_total_mm_sd"] == pytest.approx(np.std(list(COMMON.values()), ddof=1))
    # the worst case is the level of the largest mean, each seed keeping its own case there
    w = worst_case(study)
    assert w.sizes["seed"] == 4 and set(np.asarray(w["worst_" + GAP.replace(".", "_")].values).ravel()) == {"0.02"}
    t = tolerance_table(study, GAP.replace(".", "_"))
    assert (
        len(t) == 2
        and "rms_total_mm_sd" in t
        and t["rms_total_mm_sd"].iloc[1]
        == pytest.approx(np.std([COMMON[s] + gap_noise[k] for k, s in enumerate(SEEDS)], ddof=1))
    )
    # the report says so, per design and imperfection (the flow's verdict and the costs)
    blocks = [b for b in _answer_blocks(study, cfg) if b.name in ("verdict_uniform_x", "limits")]
    assert [b.name for b in blocks] == ["verdict_uniform_x", "limits"]
    text = write_html(blocks, {"answer": "A"}, "t", "t", "", tmp_path / "t.html").read_text()
    rot_text = pm(np.mean(rot_noise), np.std(rot_noise, ddof=1) / 2, sign=True)
    assert f"<td>{rot_text} (within noise)</td>" in text and rot_text.startswith("+0.0003 ± ")
    assert f"<td>{pm(0.005, np.std(gap_noise, ddof=1) / 2, sign=True)}</td>" in text
    assert "ideal rms_<wbr>total_<wbr>mm ± sd" in text
    assert "limits it is the lenslet-to-sensor gap error 0.02" in text
    # no imperfection beyond noise: the sentence says the costs are within the noise
    calm = study.copy()
    calm["rms_total_mm"] = study["rms_total_mm"].where(
        study[GAP.replace(".", "_")] == 0.0, study["rms_total_mm"].sel({GAP.replace(".", "_"): 0.0})
    )
    assert limiting_tolerances(calm)["limited_by"].iloc[0] == "nothing beyond noise"
    s = next(b.html for b in _answer_blocks(calm, cfg) if b.name == "verdict_uniform_x")
    assert "No swept imperfection alone costs it more than the noise of the replicates" in s


def test_the_comparison_shows_the_spread_and_never_plots_against_the_seed(rep_study, tmp_path):
    from lfstudy.study.report import _comparison_blocks
    from lfstudy.study.table import from_csv, to_csv

    study, _ = rep_study
    blocks = list(_comparison_blocks(study))
    assert [b.name for b in blocks] == ["panels_lenslet_pitch", "table_lenslet_pitch", "all_cases"]
    ax = blocks[0].figure.axes[0]
    assert len(ax.containers) == 1  # one flow: its line with the sd over the seeds as bars
    assert "rms_<wbr>total_<wbr>mm ± sd" in blocks[1].html
    assert "All computed designs (mean over the seeds)" in blocks[2].html
    back = from_csv(to_csv(study, tmp_path / "study.csv"))  # the flat table keeps the replicates
    assert back.sizes["seed"] == 4 and float(back["rms_total_mm"].mean()) == pytest.approx(
        float(study["rms_total_mm"].mean())
    )
