"""Tests of lfstudy.study.report: one self-contained HTML file from synthetic case artefacts."""

from __future__ import annotations

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


def fake_piv(shift_vox: float, noise: float, seed: int, shape=(3, 4, 5)) -> xr.Dataset:
    """A WIDIM-like result (contract of lfstudy.piv.widim) with Gaussian noise."""
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
    data["peak"] = (("z", "y", "x"), np.full(shape, 0.7))
    data["corrector_rms"] = ("pass", [2.0, 0.3, 0.05, 0.02])
    data["valid_percent"] = ("pass", [88.0, 95.0, 98.0, 98.5])
    data["level"] = ("pass", [1, 1, 2, 2])
    return xr.Dataset(data, coords={**coords, "pass": ("pass", [1, 2, 3, 4])}, attrs={"final_spacing": [8, 8, 8]})


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
        piv = fake_piv(shift - 0.02 * i, 0.02 + 0.1 * case.ppp * 100, seed=i)
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
