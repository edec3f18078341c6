"""A case's refocus, reconstruction and PIV under a dask.distributed client give the threaded
scheduler's bytes (config section ``compute``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lfstudy import io, workflow
from lfstudy.compute import dask_scheduler
from lfstudy.config import ConfigError
from lfstudy.study.config import case_config, expand_cases, load_config, validate_config

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.yaml"
DISTRIBUTED = {"scheduler": "distributed", "address": None, "n_workers": 2, "threads_per_worker": 1}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """The tiny study's first case up to its light fields and calibration."""
    from lfstudy.study.case import simulate_case

    cfg = load_config(TINY)
    ccfg = case_config(cfg, expand_cases(cfg)[0])
    d = tmp_path_factory.mktemp("case")
    sim = simulate_case(ccfg)
    io.write_zarr(sim["pinhole"], d / "pinhole.zarr", name="intensity")
    workflow.run_calibrate(ccfg, d / "pinhole.zarr", d / "centers.zarr")
    for f in "ab":
        io.write_zarr(sim[f"image_{f}"], d / f"raw_{f}.zarr", name="intensity")
        workflow.run_register(ccfg, d / f"raw_{f}.zarr", d / "centers.zarr", d / f"lightfield_{f}.zarr")
    return ccfg, d


def _stages(ccfg, d: Path, out: Path) -> None:
    for f in "ab":
        workflow.run_refocus(ccfg, d / f"lightfield_{f}.zarr", out / f"stack_{f}.zarr")
        workflow.run_reconstruct(
            ccfg, out / f"stack_{f}.zarr", d / f"lightfield_{f}.zarr", d / "centers.zarr", out / f"volume_{f}.zarr"
        )
    workflow.run_piv(ccfg, out / "volume_a.zarr", out / "volume_b.zarr", out / "piv.zarr")


def _same_bytes(a: Path, b: Path) -> None:
    x, y = io.open_zarr(a).load(), io.open_zarr(b).load()
    assert set(x.variables) == set(y.variables), (a.name, set(x.variables) ^ set(y.variables))
    for name in x.variables:
        u, v = x[name].values, y[name].values
        assert u.dtype == v.dtype and u.shape == v.shape, (a.name, name)
        assert u.tobytes() == v.tobytes(), (a.name, name)


@pytest.mark.slow  # the `case` fixture simulates a case (~40 s measured), then a dask LocalCluster
def test_distributed_equals_threaded(case, tmp_path):
    from distributed import get_task_stream

    ccfg, d = case
    workflow.set_threads(2)
    _stages(ccfg, d, tmp_path / "threads")
    with dask_scheduler(DISTRIBUTED, threads=2) as client:
        assert client is not None and len(client.scheduler_info()["workers"]) == 2
        with get_task_stream(client) as tasks:
            _stages(ccfg, d, tmp_path / "distributed")
    assert len(tasks.data) > 0  # the graphs really ran on the cluster's workers
    for name in ("stack_a", "stack_b", "volume_a", "volume_b", "piv"):
        _same_bytes(tmp_path / "threads" / f"{name}.zarr", tmp_path / "distributed" / f"{name}.zarr")
    piv = io.open_zarr(tmp_path / "distributed" / "piv.zarr")
    assert float(piv["valid"].mean()) > 0.8  # a real result, not two empty ones


@pytest.mark.slow  # the `case` fixture (~40 s measured)
def test_workflow_stage_runs_under_the_client(case, tmp_path):
    """`python -m lfstudy.workflow refocus --compute JSON` (what the Snakefile runs)."""
    ccfg, d = case
    workflow.set_threads(1)
    workflow.run_refocus(ccfg, d / "lightfield_a.zarr", tmp_path / "threads.zarr")
    log = tmp_path / "refocus.log"
    argv = ["refocus", "--config", json.dumps(ccfg), "--log", str(log), "--threads", "2"]
    args = [str(d / "lightfield_a.zarr"), str(tmp_path / "distributed.zarr")]
    assert workflow.main([*argv, "--compute", json.dumps({**DISTRIBUTED, "n_workers": 1}), *args]) == 0
    assert "dask: dask.distributed LocalCluster (1 workers x 1 threads)" in log.read_text()
    _same_bytes(tmp_path / "threads.zarr", tmp_path / "distributed.zarr")


def test_compute_section_is_validated():
    cfg = load_config(TINY)
    assert cfg["compute"] == {"scheduler": "threads", "address": None, "n_workers": None, "threads_per_worker": 1}
    raw = {k: v for k, v in cfg.items() if k != "compute"}
    with pytest.raises(ConfigError, match=r"compute.scheduler.*allowed values are 'threads', 'distributed'"):
        validate_config({**raw, "compute": {"scheduler": "mpi"}})
    with pytest.raises(ConfigError, match=r"compute.n_workers.*= 0"):
        validate_config({**raw, "compute": {"scheduler": "distributed", "n_workers": 0}})


def test_threads_is_a_no_op():
    with dask_scheduler(None) as c, dask_scheduler({"scheduler": "threads"}) as c2:
        assert c is None and c2 is None
    with pytest.raises(ValueError, match=r"compute\.scheduler"), dask_scheduler({"scheduler": "mpi"}):
        pass
