"""Run every code cell of examples/explore_results.ipynb on a small synthetic study."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lfstudy import io
from lfstudy.study.sweep import Case
from lfstudy.study.table import combine_cases

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "explore_results.ipynb"

pytestmark = pytest.mark.slow


def _scalars(rms: float) -> xr.Dataset:
    return xr.Dataset(
        {
            "rms_total": ((), rms, {"units": "voxel", "long_name": "total RMS error (all components)"}),
            "valid_percent": ((), 98.0, {"units": "percent", "long_name": "valid vectors"}),
        }
    )


@pytest.fixture
def results(tmp_path):
    rows = []
    for i, (fn, pitch, ppp, flow) in enumerate(
        [
            (f, p, s, fl)
            for f in ("matched", 4.0)
            for p in (0.0888, 0.1184)
            for s in (0.001, 0.002)
            for fl in ("uniform_x", "hill")
        ][:-1]
    ):  # one case missing
        case = Case.of(magnification=-1.0, fnumber=fn, lenslet_pitch=pitch, ppp=ppp, flow=flow)
        rms = 0.05 + 10 * ppp + 0.1 * pitch + 0.01 * i
        rows.append((case, _scalars(rms)))
    io.write_zarr(combine_cases(rows), tmp_path / "study.zarr")
    case = min(rows, key=lambda r: float(r[1]["rms_total"]))[0]  # the notebook opens this case
    shape = (3, 4, 5)
    co = {d: (d, np.arange(n) * 0.7) for d, n in zip("zyx", shape)}
    piv = xr.Dataset({c: (("z", "y", "x"), np.full(shape, v)) for c, v in zip("uvw", (2.25, 0.0, 0.0))}, coords=co)
    piv["valid"] = (("z", "y", "x"), np.ones(shape, bool))
    io.write_zarr(piv, tmp_path / case.case_id / "piv.zarr")
    return tmp_path


def test_notebook_runs(results, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nb = json.loads(NOTEBOOK.read_text())
    cells = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert cells and all(not c["outputs"] and c["execution_count"] is None for c in cells)  # outputs kept empty
    monkeypatch.setenv("LFSTUDY_RESULTS", str(results))
    plt.close("all")
    ns: dict = {"__name__": "__main__"}
    for cell in cells:
        exec(compile("".join(cell["source"]), "explore_results.ipynb", "exec"), ns)
    assert ns["piv"] is not None  # the best case's piv.zarr was found and opened
    assert len(plt.get_fignums()) >= 2
    ax = plt.figure(plt.get_fignums()[0]).axes[0]
    assert len(ax.lines) == 2  # one line per lenslet pitch
    plt.close("all")
