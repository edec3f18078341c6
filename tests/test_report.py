"""Tests of lfstudy.study.report: one self-contained HTML file from synthetic case artefacts."""

from __future__ import annotations

import html
import re
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lfstudy import io
from lfstudy.simulate.flows import flow_from_config
from lfstudy.study.config import expand_cases, load_config
from lfstudy.study.metrics import case_errors
from lfstudy.study.report import SECTIONS, best_designs, write_figures, write_report
from lfstudy.study.table import combine_cases

ROOT = Path(__file__).resolve().parents[1]
VOX = 0.0888  # demo lenslet pitch at M = -1


def fake_piv(shift_vox: float, noise: float, seed: int, shape=(3, 4, 5), unc: bool = True) -> xr.Dataset:
    """A WIDIM-like result (contract of lfstudy.piv.widim) with Gaussian noise; with ``unc`` the per-vector
    standard uncertainty ``unc_<c>[_mm]`` is the noise's σ (NaN for the invalid vector)."""
    rng = np.random.default_rng(seed)
    idx = {d: (np.arange(n) + 0.5) * 8 for d, n in zip("zyx", shape)}
    coords = {d: (d, (idx[d] - idx[d].mean()) * VOX, {"units": "mm"}) for d in "zyx"}
    coords.update({f"{d}_index": (d, idx[d], {"units": "voxel"}) for d in "zyx"})
    data = {}
    for c, mean in zip("uvw", (shift_vox, 0.0, 0.0)):
        val = mean + rng.normal(0, noise, shape)
        data[c] = (("z", "y", "x"), val, {"units": "voxel"})
        data[f"{c}_mm"] = (("z", "y", "x"), val * VOX, {"units": "mm"})
    valid = np.ones(shape, bool)
    valid[0, 0, 0] = False
    data["valid"] = (("z", "y", "x"), valid)
    if unc:
        for c in "uvw":
            sigma = np.where(valid, noise, np.nan)
            data[f"unc_{c}"] = (("z", "y", "x"), sigma, {"units": "voxel"})
            data[f"unc_{c}_mm"] = (("z", "y", "x"), sigma * VOX, {"units": "mm"})
    data["peak"] = (("z", "y", "x"), np.full(shape, 0.7))
    data["corrector_rms"] = ("pass", [2.0, 0.3, 0.05, 0.02])
    data["valid_percent"] = ("pass", [88.0, 95.0, 98.0, 98.5])
    data["level"] = ("pass", [1, 1, 2, 2])
    return xr.Dataset(
        data,
        coords={**coords, "pass": ("pass", [1, 2, 3, 4])},
        attrs={"final_spacing": [8, 8, 8], "final_window": [16, 16, 16]},
    )


def fake_images(d: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    raw = xr.DataArray(
        rng.random((60, 80)).astype("f4"),
        dims=("row", "col"),
        name="intensity",
        coords={"x": ("col", (np.arange(80) - 39.5) * 0.0074), "y": ("row", (29.5 - np.arange(60)) * 0.0074)},
    )
    io.write_zarr(raw, d / "raw_a.zarr")
    stack = xr.DataArray(
        rng.gamma(1.0, 0.1, (6, 12, 14)).astype("f4"),
        dims=("z", "y", "x"),
        name="intensity",
        coords={"z": np.linspace(-1, 1, 6), "y": (np.arange(12) - 5.5) * VOX, "x": (np.arange(14) - 6.5) * VOX},
    ).chunk({"z": 1})
    io.write_zarr(stack, d / "stack_a.zarr")


@pytest.fixture(scope="module")
def study_dirs(tmp_path_factory):
    """8 demo cases (one lenslet pitch): 5 complete, one with only piv.zarr, one empty dir, one absent."""
    tmp = tmp_path_factory.mktemp("results")
    cfg = load_config(ROOT / "config" / "demo.yaml")
    cfg["sweep"] = {
        "magnification": [-1.0, -0.8],
        "fnumber": ["matched", 4.0],
        "lenslet_pitch": [0.0888],
        "ppp": [0.001, 0.002],
        "flow": ["uniform_x"],
    }
    cases = expand_cases(cfg)
    rows, dirs = [], {}
    for i, case in enumerate(cases):
        d = tmp / case.case_id
        dirs[case.case_id] = d
        if i == len(cases) - 1:
            continue  # never computed: missing directory and NaN in the study
        d.mkdir(parents=True)
        if i == len(cases) - 2:
            continue  # directory without any artefact
        spec = cfg["flows"][case.flow]
        shift = spec["displacement"][0] / VOX
        piv = fake_piv(shift - 0.02 * i, 0.02 + 0.1 * case.ppp * 100, seed=i, unc=i != 0)  # 0: no σ (old store)
        io.write_zarr(piv, d / "piv.zarr")
        err = case_errors(piv, flow_from_config(spec))
        err["Q"] = ((), 0.8 - case.ppp * 50, {"units": "1", "long_name": "reconstruction quality Q"})
        err["time_total"] = ((), 10.0 + i, {"units": "s", "long_name": "run time"})
        if i != len(cases) - 3:  # this one has only piv.zarr
            io.write_zarr(err, d / "errors.zarr")
            fake_images(d, i)
        rows.append((case, err[[v for v in err.data_vars if err[v].ndim == 0]]))
    return combine_cases(rows), dirs, cfg


def test_write_report_self_contained(study_dirs, tmp_path):
    study, dirs, cfg = study_dirs
    out = write_report(study, dirs, cfg, tmp_path / "report.html", progress=False, max_cases=7)
    assert out.exists() and list(tmp_path.iterdir()) == [out]  # atomic: no temporary left
    text = out.read_text()
    assert text.count("data:image/png;base64") >= 10
    assert 'src="http' not in text and 'href="http' not in text and "<link" not in text
    assert "<script" not in text
    for title in SECTIONS.values():
        assert title in text
    assert "not available" in text  # the case dirs without artefacts
    assert "lowest total RMS error" in text
    # the thesis comparison shows each uniform case's measured mean (computed from its PIV result)
    means = study["mean_x"].where(study["computed"]).values.ravel()
    for m in means[np.isfinite(means)][:3]:
        assert f"{m:.3g}" in text
    # every embedded image decodes as a PNG
    import base64

    for b64 in re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", text)[:3]:
        assert base64.b64decode(b64)[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("forkserver", [True, False])
def test_the_report_is_the_same_whatever_its_workers(study_dirs, tmp_path, monkeypatch, forkserver):
    """Per-case figures drawn by two processes (while the main one builds the other sections) give the page one
    process gives, byte for byte but the generation time; the missing and partial cases' notes included, and a
    truncated list of cases says so. Also where there is no forkserver (Windows: the processes are spawned)."""
    import multiprocessing

    if not forkserver:
        monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    study, dirs, cfg = study_dirs
    pages = []
    for workers in (1, 2):
        out = write_report(
            study, dirs, cfg, tmp_path / f"r{workers}.html", progress=False, max_cases=7, workers=workers
        )
        pages.append(re.sub(r"Generated \d{4}-\d\d-\d\d \d\d:\d\d", "", out.read_text()))
    assert pages[0] == pages[1]
    assert "not available" in pages[1] and "Per-case figures drawn for the first 7 of 8" in pages[1]


def test_best_designs_picks_lowest_rms(study_dirs):
    study = study_dirs[0]
    best = best_designs(study)
    row = best[best["criterion"] == "lowest total RMS error"].iloc[0]
    for flow in study["flow"].values:  # per flow, in mm
        r = best[(best["criterion"] == "lowest total RMS error") & (best["flow"] == flow)].iloc[0]
        assert r["value"] == pytest.approx(float(study["rms_total_mm"].sel(flow=flow).min()))
    assert row["unit"] == "mm"


def test_write_figures(study_dirs, tmp_path):
    study, dirs, cfg = study_dirs
    few = dict(list(dirs.items())[:2])
    paths = write_figures(study, few, cfg, tmp_path / "figs", progress=False)
    names = {p.name for p in paths}
    assert all(p.exists() and p.read_bytes()[:4] == b"\x89PNG" for p in paths)
    assert "comparison_panels_ppp.png" in names and "overview_map.png" in names
    assert "answer_pareto_uniform_x.png" in names
    assert "comparison_panels_lenslet_pitch.png" not in names  # a single value is not plotted against
    assert "designs_ambiguity.png" in names
    assert any(n.startswith("cases_mag-") and n.endswith("histograms.png") for n in names)


def test_report_with_nothing_on_disk(study_dirs, tmp_path):
    """No case directory at all and a single-case study: still a report, saying what is missing."""
    study, dirs, cfg = study_dirs
    one = study.isel(magnification=[0], fnumber=[0], lenslet_pitch=[0], ppp=[0])
    missing = {cid: tmp_path / "nowhere" / cid for cid in list(dirs)[:2]}
    out = write_report(one, missing, cfg, tmp_path / "r.html", progress=False)
    text = out.read_text()
    assert "not available" in text
    assert SECTIONS["designs"] in text


def test_pareto_front_is_exactly_the_non_dominated_rows():
    import pandas as pd

    from lfstudy.study.designs import pareto_front

    df = pd.DataFrame(
        {
            "rms_total_mm": [0.10, 0.20, 0.05, 0.10, 0.30, np.nan],
            "spacing_mm_x": [1.0, 0.5, 2.0, 1.0, 0.5, 0.1],
            "spacing_mm_z": [2.0, 2.0, 4.0, 3.0, 1.0, 0.1],
        }
    )
    # row 3 is dominated by row 0 (equal error and x, coarser z); the NaN row never counts
    np.testing.assert_array_equal(pareto_front(df), [True, True, True, False, True, False])
    # a brute-force check of the definition on random tables
    rng = np.random.default_rng(0)
    for _ in range(20):
        t = pd.DataFrame(rng.integers(0, 4, (12, 3)).astype(float), columns=list(df.columns))
        v = t.to_numpy()
        expect = [not any(np.all(v[j] <= v[i]) and np.any(v[j] < v[i]) for j in range(len(v))) for i in range(len(v))]
        np.testing.assert_array_equal(pareto_front(t), expect)


def test_designs_are_ranked_in_mm_not_voxels(tmp_path):
    """Two designs whose voxels differ 1.7x: the coarse one has the smaller error in voxels, the fine
    one in mm. The recommendation, the best-design table and the report follow mm."""
    from lfstudy.study.designs import recommend
    from lfstudy.study.report import best_designs
    from lfstudy.study.sweep import Case
    from lfstudy.study.table import combine_cases

    def scalars(rms_vox, vox):
        return xr.Dataset(
            {
                "rms_total": ((), rms_vox, {"units": "voxel", "long_name": "total RMS error"}),
                "rms_total_mm": ((), rms_vox * vox, {"units": "mm", "long_name": "total RMS error"}),
                "rel_error": ((), rms_vox * vox / 0.5, {"units": "1", "long_name": "relative error"}),
                "spacing_mm_x": ((), 8 * vox, {"units": "mm", "long_name": "vector spacing x"}),
                "spacing_mm_z": ((), 2.0, {"units": "mm", "long_name": "vector spacing z"}),
                "valid_percent": ((), 95.0, {"units": "percent", "long_name": "valid vectors"}),
            }
        )

    fine = Case.of(magnification=-1.0, fnumber="matched", lenslet_pitch=0.0888, ppp=0.002, flow="uniform_x")
    coarse = Case.of(magnification=-1.0, fnumber="matched", lenslet_pitch=0.15, ppp=0.002, flow="uniform_x")
    study = combine_cases([(fine, scalars(0.20, 0.0888)), (coarse, scalars(0.15, 0.15))])
    # in voxels the coarse design "wins" (0.15 < 0.20); in mm the fine one does (0.0178 < 0.0225)
    assert float(study["rms_total"].sel(lenslet_pitch=0.15).squeeze()) < float(
        study["rms_total"].sel(lenslet_pitch=0.0888).squeeze()
    )
    table, sentences = recommend(study)
    rec = table[table["recommended"]]
    assert len(rec) == 1 and float(rec["lenslet_pitch"].iloc[0]) == pytest.approx(0.0888)
    assert "pitch=0.0888" in sentences["uniform_x"] and "0.0178 mm" in sentences["uniform_x"]
    best = best_designs(study)
    row = best[best["criterion"] == "lowest total RMS error"].iloc[0]
    assert row["lenslet_pitch"] == pytest.approx(0.0888) and row["unit"] == "mm"
    assert "lowest total RMS error" in set(best["criterion"]) and not any(best["unit"] == "voxel")


# ------------------------------------------------------------ the metric table
def _study_with(values: dict[str, list[float]]):
    """A study of two to four cases (ppp values) holding the given metrics, with attrs from their dict."""
    from lfstudy.study.sweep import Case

    rows = []
    n = len(next(iter(values.values())))
    for i, ppp in enumerate((0.001, 0.002, 0.003, 0.004)[:n]):
        case = Case.of(magnification=-1.0, fnumber="matched", lenslet_pitch=0.0888, ppp=ppp, flow="uniform_x")
        rows.append((case, xr.Dataset({k: ((), v[i], {"units": "?", "long_name": k}) for k, v in values.items()})))
    return combine_cases(rows)


def test_the_metric_table_drives_every_place(monkeypatch, tmp_path):
    """A metric registered in the table alone reaches the attrs, the legend, the panels, the case
    tables, the best designs, the Pareto objectives and the design tables as its flags say."""
    import dataclasses

    from lfstudy.study import metric_table as mt
    from lfstudy.study import report as rp
    from lfstudy.study.designs import budget_table, design_table, recommend
    from lfstudy.study.metrics import with_metrics

    fake = mt.Metric(
        "wobble_mm",
        "mm",
        "wobble of the vectors",
        lower_is_better=False,
        shown={"summary", "headline", "panel", "criterion", "pareto", "front", "budget"},
        group="error",
    )
    hidden = mt.Metric("hum", "1", "hum of the camera", None, (), "count")
    monkeypatch.setattr(mt, "METRICS", (*mt.METRICS, fake, hidden))
    base = {"rms_total_mm": [0.01, 0.02], "spacing_mm_x": [0.7, 0.7], "spacing_mm_z": [0.7, 0.7]}
    study = _study_with({**base, "valid_percent": [99.0, 98.0], "hum": [1.0, 2.0], "wobble_mm": [0.3, 0.5]})
    # attrs come from the table, not from the case's Dataset; summary metrics lead the study
    assert study["wobble_mm"].attrs == {"units": "mm", "long_name": "wobble of the vectors"}
    assert study["hum"].attrs["long_name"] == "hum of the camera"
    lead = ["rms_total_mm", "valid_percent", "spacing_mm_x", "spacing_mm_z", "wobble_mm"]
    assert list(study.data_vars)[:6] == [*lead, "hum"]
    assert with_metrics(xr.Dataset(), {"wobble_mm": 1.0})["wobble_mm"].attrs["units"] == "mm"
    # the report's places
    assert "wobble_mm" in rp.case_table(study).columns and "hum" not in rp.case_table(study).columns
    best = rp.best_designs(study)
    row = best[best["criterion"] == "highest wobble of the vectors"].iloc[0]
    assert row["value"] == 0.5 and row["unit"] == "mm" and row["ppp"] == 0.002  # higher is better
    assert ("wobble_mm", "max") in mt.objectives()
    table, _ = recommend(study)
    assert "wobble_mm" in design_table(study) and table["pareto"].sum() == 2  # wobble trades against error
    budget = {"oracle_rms_total_mm": [0.005, 0.005], "recon_added_rms_total_mm": [0.008, 0.019]}
    assert "wobble_mm" in budget_table(_study_with({**base, "wobble_mm": [0.3, 0.5], **budget}))
    out = write_report(study, {}, load_config(ROOT / "config" / "demo.yaml"), tmp_path / "r.html", progress=False)
    text = out.read_text()
    legend = text[text.index('id="legend"') :]
    assert "wobble_<wbr>mm" in text[text.index('id="answer"') : text.index('id="overview"')]  # front table
    assert re.search(r"<td>wobble_mm</td>\s*<td>mm</td>\s*<td>wobble of the vectors</td>\s*<td>higher</td>", legend)
    assert re.search(r"<td>hum</td>\s*<td>1</td>\s*<td>hum of the camera</td>\s*<td></td>", legend)
    figs = write_figures(study, {}, {}, tmp_path / "figs", progress=False)
    panels = next(p for p in figs if p.name == "comparison_panels_ppp.png")
    # one more panel: the figure is wider by one panel's width (3.3 in at 90 dpi)
    monkeypatch.setattr(mt, "METRICS", tuple(dataclasses.replace(m, shown=m.shown - {"panel"}) if m is fake else m
                                             for m in mt.METRICS))  # fmt: skip
    fewer = write_figures(study, {}, {}, tmp_path / "figs2", progress=False)
    from PIL import Image

    w1 = Image.open(panels).size[0]
    w0 = Image.open(next(p for p in fewer if p.name == "comparison_panels_ppp.png")).size[0]
    assert w1 - w0 == pytest.approx(3.3 * 90, abs=2)


def test_every_metric_name_comes_from_the_table():
    """report.py and designs.py hold no list of metric names of their own: no literal sequence of two
    or more, and every metric-like name they spell out is a row of the table."""
    import ast

    from lfstudy.study import metric_table as mt

    known = {m.name for m in mt.METRICS}
    looks = re.compile(r"^(rel_error|Q|n_valid|n_vectors|valid_percent|time_total|depth_gain|"
                       r"(rms|bias|std|mean|true|spacing|window|fov|locking_excess|depth)(_[a-z]+)+)$")  # fmt: skip
    for mod in ("report", "designs"):
        tree = ast.parse((ROOT / "lfstudy" / "study" / f"{mod}.py").read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
                names = [e.value for e in node.elts if isinstance(e, ast.Constant) and e.value in known]
                assert len(names) < 2, f"{mod}.py line {node.lineno}: a list of metric names {names}"
            if isinstance(node, ast.Dict):
                names = [k.value for k in node.keys if isinstance(k, ast.Constant) and k.value in known]
                assert len(names) < 2, f"{mod}.py line {node.lineno}: a dict keyed by metric names {names}"
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and looks.match(node.value):
                assert node.value in known, f"{mod}.py line {node.lineno}: {node.value!r} is not in the metric table"
    for gone in ("HEADLINE", "PANELS"):
        assert not hasattr(__import__("lfstudy.study.report", fromlist=["x"]), gone)


def test_a_table_row_must_say_which_way_is_better_to_rank_designs():
    from lfstudy.study.metric_table import Metric

    with pytest.raises(ValueError, match="lower_is_better"):
        Metric("x_mm", "mm", "x", None, {"criterion"})
    with pytest.raises(ValueError, match="unknown place"):
        Metric("x_mm", "mm", "x", True, {"hedline"})


def test_panels_have_readable_tick_labels():
    """A metric that barely varies (Q 0.835758-0.835772 on the demo, issue 37) is drawn as the constant it is:
    ticks of a few digits about it and its value written in the panel, never an offset (1e-6+8.357e-1) nor
    ticks 0.835758 ... 0.835772 that read as a range. A metric that varies keeps plain ticks about its values."""
    from lfstudy.study.figures import parameter_panels

    study = _study_with({"Q": [0.8357001, 0.8357031], "valid_percent": [99.0, 98.0]})
    fig = parameter_panels(study, "ppp", ["Q", "valid_percent"])
    fig.canvas.draw()
    q, valid = fig.axes[0], fig.axes[1]
    labels = [t.get_text() for t in q.get_yticklabels() if t.get_text()]
    assert labels and all(len(lab.replace("0.", "", 1)) <= 3 for lab in labels), labels
    assert any("0.8357 on every case" in t.get_text() for t in q.texts)
    lo, hi = valid.get_ylim()
    assert 97.5 < lo < 98.0 < 99.0 < hi < 99.5 and not valid.texts  # varies: untouched


def test_wide_tables_fit_their_box(study_dirs, tmp_path):
    """No table needs a sideways scroll at 1000 px (issue 37; checked in headless Chromium on a demo-shaped
    study, see the report's docs): cells wrap (no nowrap rule), headers break after '_', a table of every
    column folds into a <details>, and a table indexed by the swept settings shows one readable design
    column instead of one column per setting."""
    study, _, cfg = study_dirs
    text = write_report(study, {}, cfg, tmp_path / "r.html", progress=False).read_text()
    assert "nowrap" not in text and re.search(r"table\.tbl\{[^}]*max-width:100%", text)
    i = text.index("<summary>All computed cases</summary>")
    assert text.rfind("<details>", 0, i) > text.rfind("</details>", 0, i)
    head = text[i : text.index("</thead>", i)]
    assert "locking_<wbr>excess_<wbr>z" in head and "<td" not in head
    assert "<th>design</th>" in head and "<th>magnification</th>" not in head and "<th>ppp</th>" not in head
    # every table outside a <details> is narrow: at most 11 columns
    outside = re.sub(r"<details>.*?</details>", "", text, flags=re.S)
    for table in re.findall(r"<table.*?</table>", outside, flags=re.S):
        head = table[: table.index("</tr>")]
        assert head.count("<th") <= 11, head[:300]


def test_the_recommendation_says_what_limits_the_error(tmp_path):
    """The oracle (the case's PIV on the true volumes) against the error the reconstruction adds: the
    recommendation names the larger, the report's budget table shows both per design."""
    from lfstudy.study.designs import budget_table, error_limit, recommend

    base = {"rms_total_mm": [0.067, 0.09], "spacing_mm_x": [0.7, 0.7], "spacing_mm_z": [0.7, 0.7]}
    base["valid_percent"] = [99.0, 98.0]
    recon = _study_with({**base, "oracle_rms_total_mm": [0.007, 0.01], "recon_added_rms_total_mm": [0.0666, 0.089]})
    windows = _study_with({**base, "oracle_rms_total_mm": [0.06, 0.08], "recon_added_rms_total_mm": [0.03, 0.04]})
    s_recon = recommend(recon)[1]["uniform_x"]
    s_windows = recommend(windows)[1]["uniform_x"]
    assert "mostly the reconstruction's" in s_recon and "0.007 mm" in s_recon and "0.0666 mm" in s_recon
    assert "mostly the PIV windows'" in s_windows and "0.06 mm" in s_windows
    # no oracle in the study: no claim either way, no budget table
    plain = recommend(_study_with(base))[1]["uniform_x"]
    assert "mostly" not in plain and budget_table(_study_with(base)).empty
    assert error_limit(0.01, 0.02) == "reconstruction" and error_limit(0.02, 0.01) == "windows"
    assert error_limit(float("nan"), 0.01) == ""
    # three parts: the windows' filtering, the reconstruction, the rest (sqrt(oracle² − filter²))
    assert error_limit(0.05, 0.02, 0.04) == "windows" and error_limit(0.05, 0.02, 0.01) == "random"
    assert error_limit(0.02, 0.05, 0.015) == "reconstruction"
    three = {**base, "oracle_rms_total_mm": [0.06, 0.08], "recon_added_rms_total_mm": [0.03, 0.04]}
    filt = _study_with({**three, "filter_rms_total_mm": [0.055, 0.075], "rest_rms_total_mm": [0.024, 0.028]})
    rand = _study_with({**three, "filter_rms_total_mm": [0.01, 0.01], "rest_rms_total_mm": [0.059, 0.079]})
    assert list(budget_table(filt)["limited_by"]) == ["the PIV windows"] * 2
    assert list(budget_table(rand)["limited_by"]) == ["the random error (and the estimator's bias)"] * 2
    s_filt, s_rand = recommend(filt)[1]["uniform_x"], recommend(rand)[1]["uniform_x"]
    assert "filtering of the flow" in s_filt and "0.055 mm" in s_filt and "smaller windows" in s_filt
    assert "mostly random" in s_rand and "0.059 mm" in s_rand
    bt = budget_table(recon)
    assert list(bt["limited_by"]) == ["the reconstruction"] * 2
    assert {"oracle_rms_total_mm", "recon_added_rms_total_mm", "rms_total_mm"} <= set(bt.columns)
    out = write_report(recon, {}, load_config(ROOT / "config" / "demo.yaml"), tmp_path / "r.html", progress=False)
    answer = out.read_text()
    answer = answer[answer.index('id="answer"') : answer.index('id="overview"')]
    assert "Error budget" in answer and "recon_<wbr>added_<wbr>rms_<wbr>total_<wbr>mm" in answer
    assert "<td>the reconstruction</td>" in answer


def test_binned_uncertainty_lies_on_the_1to1_line_where_sigma_is_right():
    """Errors drawn with the σ each vector predicts: every bin's RMS error is its RMS σ (to the
    sampling error of ~2500 vectors a bin, 1.4 %: 5 % allowed) and the coverage 0.68; a σ half the
    truth lies a factor 2 off the line."""
    from lfstudy.study.metrics import binned_uncertainty

    rng = np.random.default_rng(0)
    sigma = 10 ** rng.uniform(-2, -1, 20000)
    err = sigma * rng.normal(size=sigma.size)
    err[:50] = np.nan  # no error: left out
    b = binned_uncertainty(err, sigma, n_bins=8)
    assert len(b["count"]) == 8 and b["count"].sum() == 19950
    assert np.all(np.diff(b["sigma_rms"]) > 0)  # bins ordered by σ, spanning its decade
    assert b["sigma_rms"][0] < 0.02 and b["sigma_rms"][-1] > 0.07
    np.testing.assert_allclose(b["error_rms"] / b["sigma_rms"], 1.0, atol=0.05)
    np.testing.assert_allclose(b["coverage"], 0.6827, atol=0.04)
    small = binned_uncertainty(err, sigma / 2, n_bins=8)
    np.testing.assert_allclose(small["error_rms"] / small["sigma_rms"], 2.0, atol=0.1)
    assert len(binned_uncertainty(np.full(3, np.nan), np.ones(3))["count"]) == 0
    assert len(binned_uncertainty(np.ones(4), np.full(4, 0.5))["count"]) == 1  # one σ: one bin


def test_report_shows_the_uncertainty_per_design(study_dirs, tmp_path):
    """The uncertainty section: coverage and ratio per design and flow (the study's values), and the
    error-against-σ figure pooled per design from the errors stores; the case without σ shows a dash."""
    from lfstudy.study import report as rp

    study, dirs, _ = study_dirs
    with_errors = [c for c, d in dirs.items() if (d / "errors.zarr").exists()]
    assert "unc_u_mm" in io.open_zarr(dirs[with_errors[1]] / "errors.zarr")  # the errors stage keeps σ per vector
    assert "unc_u_mm" not in io.open_zarr(dirs[with_errors[0]] / "errors.zarr")  # case 0: a PIV without σ
    # the section alone, as the report renders it (the whole report lists it: test_write_report_self_contained)
    blocks = list(rp._uncertainty_blocks(study, dirs))
    assert [b.name for b in blocks] == ["table", "error_vs_sigma"] and blocks[1].figure is not None
    section = {"uncertainty": SECTIONS["uncertainty"]}
    sec = rp.write_html(blocks, section, "t", "t", "", tmp_path / "u.html").read_text()
    assert sec.count("data:image/png;base64,") == 1 and "not available" not in sec
    for col in ("unc_coverage_x", "unc_ratio_z"):
        assert col.replace("_", "_<wbr>") in sec
        vals = study[col].values[np.isfinite(study[col].values)]
        assert vals.size >= 4 and f"{vals[0]:.3g}" in sec
    assert np.isnan(study["unc_coverage_x"].values.ravel()[0])  # case 0 has no σ
    # the curves: each design's cases pooled, per axis; a case's σ from its errors store
    groups = {"one": with_errors}
    curves = rp._uncertainty_curves(groups, dirs)["one"]
    assert set(curves) == {"x", "y", "z"}
    n_valid = sum(int(io.open_zarr(dirs[c] / "piv.zarr")["valid"].sum()) for c in groups["one"][1:])
    assert curves["x"]["count"].sum() == n_valid  # every valid vector with σ, case 0 (no σ) left out
    # no files on disk: a note, not a failed figure
    gone = list(rp._uncertainty_blocks(study, {}))
    assert [b.name for b in gone] == ["table", "error_vs_sigma"] and "not available" in gone[1].note
    # the unresolved flag's verdict beside σ's, from the study's scores (the tiny study's windows are all partial:
    # no scores there, so none is said)
    assert "unresolved flag" not in blocks[0].html
    like = study["unc_coverage_x"]
    scored = study.assign(
        unresolved_percent=xr.full_like(like, 30.0),
        unresolved_hit=xr.full_like(like, 0.9),
        unresolved_false=xr.full_like(like, 0.5),
        filter_rms_total_mm=xr.full_like(like, 0.01),
    )
    verdict = next(iter(rp._uncertainty_blocks(scored, {}))).html
    assert "the flag catches 0.90; 0.50 of its flags fall where the filtering is below σ" in verdict
    assert "not as a verdict per vector" in verdict
    # a study without any σ says so instead of drawing
    bare = study.drop_vars([v for v in study.data_vars if str(v).startswith("unc_")])
    none = list(rp._uncertainty_blocks(bare, {}))
    assert len(none) == 1 and "not available" in none[0].note


# ------------------------------------------------------------ tolerances (issue 29 §3)
GAP = "camera.imperfections.lenslet_gap_error"
ROT = "camera.imperfections.lenslet_rotation"


@pytest.fixture(scope="module")
def tol_study():
    """The study of :func:`_tolerance_study` and its config, built once (about 2 s)."""
    return _tolerance_study()


def _tolerance_study():
    """Two designs (lenslet pitch) x gap error [-0.01, 0, 0.02] x lenslet rotation [0, 3] mrad, one flow.

    Fine pitch: the better design at the ideal camera (0.010 mm against 0.015 mm) but sensitive to the gap
    (+1.5 mm per unit of |gap error|); coarse pitch: +0.5 mm per unit. Rotation costs both a little (fine
    0.001 mm/mrad, coarse 0.0005). Equal resolution, so only the error ranks them."""
    from lfstudy.study.sweep import Sweep

    cfg = load_config(ROOT / "config" / "demo.yaml")
    cfg["sweep"] = {
        "magnification": [-1.0],
        "lenslet_pitch": [0.0888, 0.1184],
        "flow": ["uniform_x"],
        GAP: [-0.01, 0.0, 0.02],
        ROT: [0.0, 3.0],
    }
    sweep = Sweep(cfg)
    rows = []
    for case in sweep.cases():
        fine = case.lenslet_pitch < 0.1
        g, r = abs(case[GAP]), case[ROT]
        e = (0.010 if fine else 0.015) + (1.5 if fine else 0.5) * g + (0.001 if fine else 0.0005) * r
        vals = {
            "rms_total_mm": e,
            "rms_x_mm": e / 2,
            "rms_y_mm": e / 3,
            "rms_z_mm": 0.8 * e,
            "valid_percent": 95.0 - 100 * g,
            "oracle_rms_total_mm": 0.004,
            "spacing_mm_x": 0.4,
            "spacing_mm_z": 0.5,
        }
        rows.append((case, xr.Dataset({k: ((), v) for k, v in vals.items()})))
    return combine_cases(rows, sweep.settings), cfg


def test_tolerance_section_only_where_an_imperfection_is_swept(study_dirs, tol_study, tmp_path):
    """The section and its figure per imperfection appear for a tolerance sweep; a study sweeping only design
    and processing settings (or an imperfection at one level) has neither."""
    from lfstudy.study import report as rp
    from lfstudy.study.sweep import is_tolerance
    from lfstudy.study.tolerance import tolerance_dims

    assert is_tolerance(GAP) and is_tolerance("illumination.thickness") and is_tolerance("sensor.hot_pixels.level")
    assert not is_tolerance("depth_calibration.enabled") and not is_tolerance("camera.lenslet.pitch")
    assert not is_tolerance("sensor.read_noise") and not is_tolerance("particles.ppp")
    study, _ = tol_study
    dims = ["camera_imperfections_lenslet_gap_error", "camera_imperfections_lenslet_rotation"]
    assert tolerance_dims(study) == dims
    sections = rp.report_sections(study)
    assert list(sections)[:2] == ["answer", rp.TOLERANCE_SECTION[0]]
    plain = study_dirs[0]
    assert rp.report_sections(plain) == rp.SECTIONS and not list(rp._tolerance_blocks(plain))
    one = study.isel({dims[0]: [1], dims[1]: [0]})  # imperfections at one level each: nothing to compare
    assert tolerance_dims(one) == [] and rp.TOLERANCE_SECTION[0] not in rp.report_sections(one)
    blocks = list(rp._tolerance_blocks(study))
    assert [b.name for b in blocks] == ["intro", dims[0], f"table_{dims[0]}", dims[1], f"table_{dims[1]}"]
    assert all(b.figure is not None for b in blocks if b.name in dims)
    for b in blocks:  # the figures' content: test_tolerance_tables_and_figures_are_labelled_from_the_schema
        b.figure = None
    sec = rp.write_html(blocks, {"tolerances": "T"}, "t", "t", "", tmp_path / "t.html").read_text()
    assert "not available" not in sec and sec.count("<h4>Error against ") == 2
    # the oracle beside each error, in mm
    assert "oracle_<wbr>rms_<wbr>total_<wbr>mm" in sec and "<td>0.004</td>" in sec


def test_tolerance_tables_and_figures_are_labelled_from_the_schema(tol_study):
    """Levels named by the schema's title and units; the other imperfections at their ideal level (the schema
    default 0, not the first level swept: the gap sweep starts at -0.01)."""
    from lfstudy.study.report import _tolerance_blocks
    from lfstudy.study.tolerance import ideal_levels, tolerance_table

    study, _ = tol_study
    gap, rot = "camera_imperfections_lenslet_gap_error", "camera_imperfections_lenslet_rotation"
    assert ideal_levels(study) == {gap: 0.0, rot: 0.0}
    t = tolerance_table(study, rot)
    assert list(t.columns)[:3] == ["design", "flow", "lenslet grid rotation error [mrad]"]
    assert {"rms_total_mm", "oracle_rms_total_mm", "rms_x_mm", "rms_y_mm", "rms_z_mm", "valid_percent"} <= set(t)
    assert list(t.columns).index("oracle_rms_total_mm") == list(t.columns).index("rms_total_mm") + 1
    assert len(t) == 4  # 2 designs x 2 rotations, the gap ideal
    fine = t[t["design"].str.contains("pitch=0.0888")].set_index("lenslet grid rotation error [mrad]")
    assert fine.loc[3.0, "rms_total_mm"] == pytest.approx(0.010 + 0.003)  # gap 0 (ideal), not -0.01
    tg = tolerance_table(study, gap)
    assert "lenslet-to-sensor gap error" in tg and len(tg) == 6  # dimensionless: no "[1]"
    figs = {b.name: b.figure for b in _tolerance_blocks(study) if b.figure is not None}
    ax = figs[rot].axes[0]
    assert ax.get_xlabel() == "lenslet grid rotation error [mrad]"
    assert ax.get_title() == "total RMS error (all components) [mm] (dashed: oracle)"
    assert [a.get_title() for a in figs[gap].axes][1:4] == [f"RMS error {c} [mm]" for c in "xyz"]
    assert len(ax.lines) == 4  # per design: the case and its oracle
    np.testing.assert_allclose(ax.lines[0].get_xdata(), [0.0, 3.0])


def test_worst_case_ranking_picks_the_robust_design(tol_study):
    """At the ideal camera the fine pitch wins; at its worst over the tolerances (gap 0.02, rotation 3 mrad:
    0.043 mm against 0.0265 mm) the coarse one does, and the recommendation names the gap error as what
    limits it."""
    from lfstudy.study.designs import recommend
    from lfstudy.study.report import _answer_blocks
    from lfstudy.study.tolerance import at_ideal, limiting_tolerances, worst_case

    study, cfg = tol_study
    worst = worst_case(study)
    fine, coarse = (worst["rms_total_mm"].sel(lenslet_pitch=p).squeeze() for p in (0.0888, 0.1184))
    assert float(fine) == pytest.approx(0.010 + 1.5 * 0.02 + 0.003) and float(coarse) == pytest.approx(0.0265)
    w = worst.sel(lenslet_pitch=0.0888).squeeze()
    assert str(w["worst_camera_imperfections_lenslet_gap_error"].values) == "0.02"
    assert float(w["valid_percent"]) == pytest.approx(93.0)  # every variable is the worst case's
    assert int(w["tolerance_cases"]) == 6

    def pick(ds):
        t = recommend(ds)[0]
        return float(t.loc[t["recommended"], "lenslet_pitch"].iloc[0])

    assert pick(at_ideal(study)) == pytest.approx(0.0888) and pick(worst) == pytest.approx(0.1184)
    lim = limiting_tolerances(study).set_index("design")
    row = lim.loc[lim.index.str.contains("pitch=0.1184")].iloc[0]
    assert row["+lenslet-to-sensor gap error"] == pytest.approx(0.01)  # 0.5 x 0.02
    assert row["+lenslet grid rotation error [mrad]"] == pytest.approx(0.0015)
    assert row["limited_by"] == "lenslet-to-sensor gap error 0.02"

    def answer(rank_at):
        c = {**cfg, "report": {"rank_at": rank_at}}
        blocks = {b.name: b.html for b in _answer_blocks(study, c)}
        return {"sentences": blocks["verdict_uniform_x"], "limits": blocks["limits"]}

    blocks = answer("tolerances")
    ideal, tol = answer("ideal")["sentences"], blocks["sentences"]
    # the recommendation says what limits every design: fine pitch the gap too (+0.03 mm)
    assert blocks["limits"].count("<td>lenslet-to-sensor gap error 0.02</td>") == 2
    assert "88.8 µm lenslets" in ideal.split("It trades")[0] and "Ranked at the ideal camera" in ideal
    assert "build M −1, f/2.0, 118 µm lenslets" in tol and "Ranked at tolerances" in tol
    assert "0.0265 mm at its worst" in tol and "limits it is the lenslet-to-sensor gap error 0.02" in tol
    with pytest.raises(ValueError, match=r"report\.rank_at"):
        list(_answer_blocks(study, {"report": {"rank_at": "worst"}}))


def test_rank_at_is_a_validated_setting(tmp_path):
    from lfstudy.config import ConfigError

    assert load_config(ROOT / "config" / "demo.yaml")["report"]["rank_at"] == "ideal"
    cfg = load_config(ROOT / "config" / "tolerances.yaml")
    assert cfg["report"]["rank_at"] == "tolerances"
    text = (ROOT / "config" / "demo.yaml").read_text() + "report: {rank_at: worst}\n"
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(ConfigError, match="rank_at"):
        load_config(tmp_path / "bad.yaml")


def test_the_answer_names_a_cost_only_the_combination_of_imperfections_has():
    """No imperfection alone raises either design's error, the two together do: the recommendation says so
    instead of claiming the tolerances cost nothing."""
    from lfstudy.study.report import _answer_blocks
    from lfstudy.study.sweep import Sweep

    cfg = load_config(ROOT / "config" / "demo.yaml")
    cfg["sweep"] = {"magnification": [-1.0], "lenslet_pitch": [0.0888, 0.1184], "flow": ["uniform_x"]}
    cfg["sweep"].update({GAP: [0.0, 0.02], ROT: [0.0, 3.0]})
    cfg["report"] = {"rank_at": "tolerances"}
    sweep = Sweep(cfg)
    rows = []
    for case in sweep.cases():
        both = case[GAP] != 0 and case[ROT] != 0
        e = (0.010 if case.lenslet_pitch < 0.1 else 0.015) + (0.004 if both else 0.0)
        vals = {"rms_total_mm": e, "rms_x_mm": e / 2, "rms_y_mm": e / 3, "rms_z_mm": 0.8 * e}
        vals.update(valid_percent=95.0, oracle_rms_total_mm=0.004, spacing_mm_x=0.4, spacing_mm_z=0.5)
        rows.append((case, xr.Dataset({k: ((), v) for k, v in vals.items()})))
    study = combine_cases(rows, sweep.settings)
    text = next(b.html for b in _answer_blocks(study, cfg) if b.name == "verdict_uniform_x")
    assert "No swept imperfection alone raises its error (0.01 mm at the ideal camera)" in text
    assert "their combination reaches 0.014 mm" in text


@pytest.mark.parametrize(
    "limited, hit, miss, said",
    [
        # a particle method that finds 20 % of the particles within the depth of field about the focal plane but
        # 80 % of all is limited by the focal plane inside the volume; at 45 % against 80 % it is not
        (
            "focus_limited",
            {"found_percent": [80.0, 80.0], "found_in_focus_percent": [60.0, 20.0], "depth_unknown_percent": [5, 40]},
            {"found_percent": [80.0, 80.0], "found_in_focus_percent": [60.0, 45.0]},
            ("The focal plane limits", "particles.z_center", "<i>depth_unknown_percent</i> needs no truth"),
        ),
        # 0.3 particles per lenslet and depth cell: limited by the seeding, and by how much; at the limit itself not
        (
            "density_limited",
            {"particles_per_cell": [0.1, 0.3]},
            {"particles_per_cell": [0.1, 0.2]},
            ("The seeding limits", "up to 0.30 particles"),
        ),
    ],
)
def test_the_budget_names_what_limits_a_design(limited, hit, miss, said, tmp_path):
    """The budget names the design a limit applies to (the second) and says what to change; where the metric
    stays within the limit, or the study lacks it, it says nothing."""
    from lfstudy.study import designs

    assert designs.DENSITY_LIMITED == 0.2
    base = {"rms_total_mm": [0.02, 0.03], "spacing_mm_x": [0.7, 0.7], "spacing_mm_z": [0.7, 0.7]}
    base |= {"valid_percent": [99.0, 98.0], "oracle_rms_total_mm": [0.005, 0.005]}
    base |= {"recon_added_rms_total_mm": [0.019, 0.029]}
    limit = getattr(designs, limited)
    over, within = _study_with({**base, **hit}), _study_with({**base, **miss})
    assert limit(designs.budget_table(over)) == [designs.budget_table(over)["design"].iloc[1]]
    assert limit(designs.budget_table(within)) == [] and limit(designs.budget_table(_study_with(base))) == []
    cfg = load_config(ROOT / "config" / "demo.yaml")
    text = write_report(over, {}, cfg, tmp_path / "over.html", progress=False).read_text()
    assert all(s in text for s in said)
    text = write_report(within, {}, cfg, tmp_path / "within.html", progress=False).read_text()
    assert said[0] not in text


# ------------------------------------------------------------ the verdict in words (issue 37 §4)
def _verdict_study(error, oracle, *, spacing=None, z_share=0.9, **more):
    """Designs (ppp values) with the given total errors and oracles [mm], the reconstruction's share from them
    (in quadrature), the error z_share (of its square) in z."""
    from lfstudy.study.metrics import quadrature_excess

    n = len(error)
    e, o = np.asarray(error, float), np.asarray(oracle, float)
    xy = e * np.sqrt((1 - z_share) / 2)
    vals = {
        "rms_total_mm": e, "rms_x_mm": xy, "rms_y_mm": xy, "rms_z_mm": e * np.sqrt(z_share),
        "spacing_mm_x": spacing or [0.7] * n, "spacing_mm_z": [0.5] * n, "valid_percent": [95.0] * n,
        "oracle_rms_total_mm": o, "recon_added_rms_total_mm": [quadrature_excess(a, b) for a, b in zip(e, o)],
    }  # fmt: skip
    return _study_with({k: list(map(float, v)) for k, v in {**vals, **more}.items()})


def _answer_text(study, tmp_path, cfg=None):
    cfg = cfg or load_config(ROOT / "config" / "demo.yaml")
    text = write_report(study, {}, cfg, tmp_path / "r.html", progress=False).read_text()
    return html.unescape(text[text.index('id="answer"') : text.index('id="overview"')])


def test_the_verdict_says_when_the_reconstruction_ranks_the_designs(tmp_path):
    """Every design 10-16x its oracle, 90 % of it in z: the ranking reflects the reconstruction, not the
    optics, said with the figures; at 2.5-3x (below RECONSTRUCTION_RANKS) it is not said."""
    from lfstudy.study.designs import RECONSTRUCTION_RANKS

    assert RECONSTRUCTION_RANKS == 3.0
    answer = _answer_text(_verdict_study([0.05, 0.08], [0.005, 0.005]), tmp_path)
    assert "every design's error is 10–16× its oracle's" in answer and "90 % of it (in quadrature) in z" in answer
    assert "the ranking reflects the reconstruction's artefacts, not the optics" in answer
    answer = _answer_text(_verdict_study([0.05, 0.06], [0.02, 0.02]), tmp_path)
    assert "not the optics" not in answer and "3.0×" in answer  # the summary's error / oracle


def test_the_verdict_gives_the_reconstructions_share_ties_and_zeros(tmp_path):
    """The Hill case of issue 37: 0.0357 mm against an oracle of 0.0264 (windows-limited): a better
    reconstruction cuts 26 %, never "gain little"; 0.0359 and 0.0365 mm tie with it (within 5 %, no
    replicates), never "dominates"; a design that beat its oracle shows a 0 share with a word."""
    answer = _answer_text(_verdict_study([0.0357, 0.0359, 0.0365, 0.045], [0.0264, 0.03, 0.031, 0.046]), tmp_path)
    assert "would cut the recommended design's error by 26 %" in answer
    assert "would still cut the error by 26 %" in answer  # the recommendation's budget sentence agrees
    assert "gain little" not in answer and "dominates" not in answer
    assert "ties with" in answer and "(0.0359 mm); " in answer and "(0.0365 mm)" in answer and "within 5 %" in answer
    assert "0 % (beat its oracle)" in answer and "beat its oracle" in answer
    assert "The reconstruction adds 0 where a case beat its oracle" in answer
    # a clear winner whose reconstruction adds 2 %: it dominates, and a better reconstruction gains little
    answer = _answer_text(_verdict_study([0.03, 0.05], [0.0295, 0.03]), tmp_path)
    assert "It dominates every other design" in answer and "ties with" not in answer
    assert "would gain little on the recommended design: at most 2 %" in answer


def test_the_summary_table_leads_each_flow(tmp_path):
    """One compact table per flow before the figures: design (readable, with units), error, oracle, their
    ratio, the reconstruction's share, the dominant component and the limiting stage; a windows' filtering
    share only where the study holds that term."""
    from lfstudy.study.designs import budget_table, summary_table

    study = _verdict_study([0.05, 0.08], [0.005, 0.07])
    answer = _answer_text(study, tmp_path)
    i = answer.index('class="dataframe tbl summary"')
    assert i < answer.index("data:image/png") and answer.index('class="verdict"') < i
    head = answer[i : answer.index("</thead>", i)]
    cols = re.findall(r"<th[^>]*>(.*?)</th>", head)
    assert cols == ["design", "error [mm]", "oracle [mm]", "error / oracle", "reconstruction's share",
                    "dominant component", "limiting stage"]  # fmt: skip
    assert "M −1, f/2.0, 88.8 µm lenslets, seeding density 0.001 (recommended)" in answer
    assert "<td>z (90 %)</td>" in answer and "<td>the PIV windows</td>" in answer
    s = summary_table(study)
    assert "filter_cut" not in s
    np.testing.assert_allclose(s["recon_cut"], [1 - 0.005 / 0.05, 1 - 0.07 / 0.08])  # what a perfect one cuts
    bt = budget_table(study)
    bt["filter_rms_total_mm"] = [0.01, 0.02]  # the third budget term, once the study holds it
    assert "filter_cut" in summary_table(study, bt)


def test_the_seeding_and_limited_by_name_one_stage(tmp_path):
    """Two designs seeded at 0.3 particles per lenslet and depth cell: the reconstruction-limited one is
    seeding-limited in the summary and the paragraph; the windows-limited one in neither (the seeding limits
    a particle fit only where the fit's share of the error is the larger)."""
    from lfstudy.study.designs import budget_table, density_limited, limiting_stage

    study = _verdict_study([0.03, 0.05], [0.028, 0.01], particles_per_cell=[0.3, 0.3])
    bt = budget_table(study)
    assert list(bt["limited_by"]) == ["the PIV windows", "the reconstruction"]
    assert list(limiting_stage(bt)) == ["the PIV windows", "the seeding (through the reconstruction)"]
    assert density_limited(bt) == [bt["design"].iloc[1]]
    answer = _answer_text(study, tmp_path)
    para = answer[answer.index("The seeding limits") :]
    para = para[: para.index("</p>")]
    bold = para[: para.index("</b>")]
    assert "seeding density 0.002" in bold and "seeding density 0.001" not in bold
    assert "seeding density 0.001 on uniform_x: as densely seeded, but there the windows' share" in answer


def test_designs_have_one_readable_name_everywhere(study_dirs, tmp_path):
    """Every table, sentence and figure key names a design as "M −1, f/2.0, 88.8 µm lenslets, ..." (the matched
    f-number resolved from the config): no label "M=-1 f/#=matched pitch=0.0888", and µm, never "um"."""
    from lfstudy.study.designs import design_names

    study, dirs, cfg = study_dirs
    names = design_names(study, cfg)
    assert names["M=-1 f/#=matched pitch=0.0888 ppp=0.001"] == "M −1, f/2.0, 88.8 µm lenslets, seeding density 0.001"
    assert names["M=-1 f/#=4 pitch=0.0888 ppp=0.002"] == "M −1, f/4.0, 88.8 µm lenslets, seeding density 0.002"
    assert len(set(names.values())) == len(names)
    text = write_report(study, dirs, cfg, tmp_path / "r.html", progress=False, max_cases=2).read_text()
    visible = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "", text)
    assert "pitch=0.0888" not in visible and "f/#=" not in visible
    assert "µm]" in visible and not re.search(r"\d ?um\b|\bum\]", visible)  # the camera table too
    assert "M −1, f/2.0, 88.8 µm lenslets, seeding density 0.001" in visible
    for term in ("<i>Q</i>:", "<i>IPR</i>:", "<i>ppp</i>:", "<i>depth gain</i>:"):  # defined before their use
        assert visible.index(term) < visible.index('id="overview"')


@pytest.mark.parametrize("renderer, crime", [("exact", True), ("montecarlo", False)])
def test_the_report_names_the_renderer_and_the_inverse_crime(renderer, crime, tmp_path):
    """A particle fit (IPR) on images of the exact renderer (the model it fits) is an inverse crime the
    verdict names; on Monte-Carlo images it is not. The renderer is named either way; MART never commits it."""
    cfg = load_config(ROOT / "config" / "demo.yaml")
    cfg["raytrace"]["method"] = renderer
    study = _verdict_study([0.05, 0.08], [0.005, 0.005])
    for method in ("ipr", "mart"):
        cfg["reconstruct"]["method"] = method
        answer = _answer_text(study, tmp_path, cfg)
        assert ("exact renderer" if renderer == "exact" else "Monte-Carlo renderer") in answer
        said = "an inverse crime" in answer and "IPR figures come from the fit's own model" in answer
        assert said == (crime and method == "ipr")


def test_the_unresolved_flag_verdict():
    """The flag's verdict: the uniform flows' flagged share, the catch and the false share where the windows filter,
    'trust' only where every case meets issue 38's targets; nothing without the scores."""
    import pandas as pd

    from lfstudy.study.report import _unresolved_verdict

    cases = {
        "unresolved_percent": [5.1, 2.8, 38.1, 31.3],
        "unresolved_hit": [float("nan"), float("nan"), 0.86, 0.81],
        "unresolved_false": [1.0, 1.0, 0.63, 0.45],
        "filter_rms_total_mm": [1.6e-16, 0.0, 0.011, 0.016],
    }
    v = _unresolved_verdict(pd.DataFrame(cases))
    assert "On the flows the windows do not filter, 3–5 % of the vectors are flagged" in v
    assert "catches 0.81–0.86; 0.45–0.63 of its flags fall where the filtering is below σ." in v
    assert "not as a verdict per vector" in v and "Trust" not in v
    good = dict(cases, unresolved_false=[1.0, 1.0, 0.10, 0.05])
    assert _unresolved_verdict(pd.DataFrame(good)).endswith("Trust the unresolved flag on these designs.")
    # a uniform flow flagged on 15 % of its vectors: no trust, whatever the catch
    assert "Trust" not in _unresolved_verdict(pd.DataFrame(dict(good, unresolved_percent=[15.0, 2.8, 38.1, 31.3])))
    assert _unresolved_verdict(pd.DataFrame({"unresolved_percent": [1.0]})) == ""
    nan = float("nan")
    assert _unresolved_verdict(pd.DataFrame({k: [nan] for k in cases})) == ""


def test_the_uncertainty_verdict():
    """σ 1.3-7.5x too small: do not trust it; within 1.5x either way: about right; mixed: per design."""
    import pandas as pd

    from lfstudy.study.report import _uncertainty_verdict

    v = _uncertainty_verdict(pd.DataFrame({"unc_ratio_z": [1.3, 7.5, 2.0], "unc_ratio_x": [0.9, 1.2, 1.1]}))
    assert "σ of w (z) is 1.3–7.5× too small on these designs: do not trust it." in v
    assert "σ of u (x) is about right" in v
    assert "not on others" in _uncertainty_verdict(pd.DataFrame({"unc_ratio_y": [0.9, 3.0]}))
    # a circular correlation with σ of w too small on some design: the verdict names the linear correlation
    assert "piv.zero_pad: true" in _uncertainty_verdict(pd.DataFrame({"unc_ratio_z": [0.9, 3.0]}), circular=True)
    assert "zero_pad" not in _uncertainty_verdict(pd.DataFrame({"unc_ratio_z": [0.9, 3.0]}), circular=False)
    assert "zero_pad" not in _uncertainty_verdict(pd.DataFrame({"unc_ratio_z": [0.9, 1.2]}), circular=True)
    # too small against the window-averaged truth, right against the oracle: the windows' response, not noise
    odd = pd.DataFrame({"unc_ratio_x": [2.0, 3.5], "unc_ratio_oracle_x": [0.78, 0.94]})
    assert "Against the oracle (the same windows on the true particles) it is 0.78–0.94×" in _uncertainty_verdict(odd)
    assert "oracle" not in _uncertainty_verdict(odd.assign(unc_ratio_oracle_x=[0.78, 1.7]))  # wrong there too
    assert "oracle" not in _uncertainty_verdict(pd.DataFrame({"unc_ratio_x": [0.9, 1.1], "unc_ratio_oracle_x": [1, 1]}))
    import json

    import xarray as xr

    from lfstudy.study.report import _circular

    def study(zero_pad):
        return xr.Dataset(attrs={"parameters": json.dumps({"piv": {"zero_pad": zero_pad}})})

    assert _circular(study(False)) and not _circular(study(True))


def test_figures_of_the_answer_and_the_cases_read_right():
    """The Pareto plot draws no colour bar for a depth spacing that is one value on every design (its title
    says it), numbers its designs beside the points in 9-pt type and names them in a key; the error map shows
    invalid vectors hatched with a legend, not as a colour of the scale; the histograms are in mm."""
    import pandas as pd

    from lfstudy.simulate.flows import flow_from_config
    from lfstudy.study.figures import displacement_histograms, pareto_figure, vector_error_slice

    t = pd.DataFrame({"design": ["a", "b"], "spacing_mm_x": [0.3, 0.4], "rms_total_mm": [0.04, 0.05],
                      "spacing_mm_z": [0.5, 0.5], "pareto": [True, False], "recommended": [True, False]})  # fmt: skip
    fig = pareto_figure(t, "hill")
    assert len(fig.axes) == 1 and "0.5 mm on every design" in fig.axes[0].get_title()
    labels = list(fig.axes[0].texts)
    assert [a.get_text() for a in labels] == ["1", "2"] and all(a.get_fontsize() >= 9 for a in labels)
    assert all(a.get_position() != (0, 0) and a.xyann[0] > 0 for a in labels)  # beside the point, not on it
    assert any("1  a" in x.get_text() and "2  b" in x.get_text() for x in fig.texts)
    t["spacing_mm_z"] = [0.5, 0.7]
    assert len(pareto_figure(t, "hill").axes) == 2  # a colour bar where it differs
    piv = fake_piv(2.0, 0.05, seed=0)  # one invalid vector, at (0, 0, 0)
    err = case_errors(piv, flow_from_config({"kind": "uniform", "displacement": [0.2, 0.0, 0.0]}))
    fig = vector_error_slice(piv.isel(z=[0, 0, 0]), err.isel(z=[0, 0, 0]))  # the middle slice holds it
    leg = fig.axes[1].get_legend()
    assert leg is not None and leg.get_texts()[0].get_text() == "invalid vector (1)"
    fig = displacement_histograms(piv, err)
    assert fig.axes[0].get_xlabel() == "x displacement u [mm]"


def test_the_representative_case_is_the_recommended_design(study_dirs):
    from lfstudy.study.designs import recommend
    from lfstudy.study.report import _representative

    study, dirs, cfg = study_dirs
    table, _ = recommend(study)
    ids = [c for c in table.loc[table["recommended"], "case_id"] if (dirs[c] / "piv.zarr").exists()]
    case, why = _representative(study, dirs, cfg)
    assert ids and case == ids[0] and why.startswith("the recommended design for the uniform_x flow, M −1")


def test_the_sigma_figure_has_readable_ticks_and_its_legend_clear_of_the_curves():
    """Issue 38: eight designs whose σ spans under a decade (0.02-0.07 mm) with errors 1.2-6.8x σ: the tick
    labels of each panel do not overlap (matplotlib labelled every minor tick of such a span: 36 overlaps
    before) and the legend lies below the panels, not on them."""
    from lfstudy.study.figures import error_vs_uncertainty

    curves = {}
    for k in range(8):
        s = np.linspace(0.02, 0.06, 6) * (1 + 0.02 * k)
        bins = {"sigma_rms": s, "error_rms": s * (1.2 + 0.8 * k), "count": np.full(6, 50)}
        curves[f"M −1, f/2.0, {88.8 + k:.1f} µm lenslets, depth calibration off"] = dict.fromkeys("xyz", bins)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = error_vs_uncertainty(curves)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    r = canvas.get_renderer()
    panels = list(fig.axes)
    for a in panels:
        for axis in (a.xaxis, a.yaxis):
            boxes = [
                t.get_window_extent(r) for t in axis.get_ticklabels(which="both") if t.get_visible() and t.get_text()
            ]
            assert len(boxes) >= 2
            assert not any(b1.overlaps(b2) for i, b1 in enumerate(boxes) for b2 in boxes[i + 1 :])
    legend = fig.legends[0].get_window_extent(r)
    assert legend.y1 < min(a.get_window_extent(r).y0 for a in panels)
    assert len(fig.legends[0].get_texts()) == 9  # 8 designs and the 1:1 line


@pytest.mark.parametrize("method", ["ipr", "mart"])
def test_the_report_says_a_particle_fit_with_depth_calibration_compares_piv_modes(method, tmp_path):
    """IPR swept with and without depth calibration: without it the sweep pairs the fitted particles, with it
    WIDIM runs on the rendered volumes and the depth correction; the answer says the two rows compare PIV modes.
    MART runs WIDIM either way and is not said to; IPR without the calibration swept is not either."""
    from lfstudy.study.sweep import Sweep

    def answer(sweep_dcal):
        cfg = load_config(ROOT / "config" / "demo.yaml")
        cfg["reconstruct"]["method"] = method
        cfg["sweep"] = {"magnification": [-1.0], "lenslet_pitch": [0.0888], "flow": ["uniform_x"]}
        if sweep_dcal:
            cfg["sweep"]["depth_calibration.enabled"] = [False, True]
        sweep = Sweep(cfg)
        vals = {"rms_total_mm": 0.02, "oracle_rms_total_mm": 0.005, "spacing_mm_x": 0.7, "valid_percent": 95.0}
        rows = [
            (c, xr.Dataset({k: ((), v, {"units": "mm", "long_name": k}) for k, v in vals.items()}))
            for c in sweep.cases()
        ]
        return _answer_text(combine_cases(rows, sweep.settings), tmp_path, cfg)

    text = answer(True)
    said = "cases with and without depth calibration compare two PIV modes" in text
    assert said == (method == "ipr")
    if said:
        assert "The IPR cases" in text and "piv.particles: paired" in text
        assert "corrected by the design's depth response" in text
    assert "compare two PIV modes" not in answer(False)


def test_the_report_compares_the_reconstruction_methods_where_both_ran(tmp_path):
    """reconstruct.method swept (MART, IPR): a table of each design's error under each method with its oracle
    beside it, the multiples of the oracle and the method of the lowest error, and the ranges in words; a
    study of one method has none."""
    from lfstudy.study.designs import method_comparison
    from lfstudy.study.sweep import Sweep

    cfg = load_config(ROOT / "config" / "demo.yaml")
    cfg["sweep"] = {"magnification": [-1.0, -0.8], "lenslet_pitch": [0.0888], "flow": ["uniform_x"]}
    cfg["sweep"]["reconstruct.method"] = ["mart", "ipr"]
    sweep = Sweep(cfg)
    err = {("mart", -1.0): 0.036, ("ipr", -1.0): 0.009, ("mart", -0.8): 0.035, ("ipr", -0.8): 0.040}
    rows = []
    for c in sweep.cases():
        e, o = err[(c["reconstruct.method"], c.magnification)], 0.002 if c.magnification == -1.0 else 0.004
        vals = {"rms_total_mm": e, "oracle_rms_total_mm": o, "spacing_mm_x": 0.7, "valid_percent": 95.0}
        rows.append((c, xr.Dataset({k: ((), v, {"units": "mm", "long_name": k}) for k, v in vals.items()})))
    study = combine_cases(rows, sweep.settings)
    from lfstudy.study.designs import design_names

    cmp = method_comparison(study, design_names(study, cfg))
    assert list(cmp["design"]) == ["M −1, f/2.0, 88.8 µm lenslets", "M −0.8, f/2.8, 88.8 µm lenslets"]
    assert cmp["mart_mm"].tolist() == [0.036, 0.035] and cmp["ipr_mm"].tolist() == [0.009, 0.040]
    assert cmp["oracle_mm"].tolist() == [0.002, 0.004] and cmp["lowest"].tolist() == ["ipr", "mart"]
    np.testing.assert_allclose(cmp["ipr_ratio"], [4.5, 10.0])
    answer = _answer_text(study, tmp_path, cfg)
    assert (
        "Reconstruction methods" in answer and "MART errs 8.8–18.0× its oracle; IPR errs 4.5–10.0× its oracle" in answer
    )
    assert "The lowest error: MART on 1, IPR on 1 of 2 (a design on a flow)." in answer and "0.009 (4.5×)" in answer
    cfg["sweep"].pop("reconstruct.method")
    one = Sweep(cfg)
    assert method_comparison(combine_cases([(c, rows[0][1]) for c in one.cases()], one.settings)).empty
