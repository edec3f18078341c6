"""The tiny study on a real SLURM cluster gives the local run's results.

Needs a running cluster: ``bash scripts/local-slurm.sh`` starts a one-node one on this machine
(Debian, root), as ``.ci/run`` does. Skipped, with the reason, only where ``sbatch`` is absent and
the CI variable is unset; in CI a missing or broken SLURM is a failure.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from lfstudy import io
from lfstudy.study.config import expand_cases, load_config

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.yaml"
PROFILE = ROOT / "profiles" / "slurm"
IN_CI = os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")
TIMEOUT = 900  # s for the SLURM run (measured: see the test's docstring)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        shutil.which("sbatch") is None and not IN_CI,
        reason="no SLURM here (sbatch not on PATH); `sudo bash scripts/local-slurm.sh` starts a local one",
    ),
]


def _slurm(*args: str) -> str:
    r = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, f"{' '.join(args)} failed: {r.stderr.strip()}"
    return r.stdout


def _require_cluster() -> None:
    """Fail with a clear message unless SLURM answers and has a node that can run jobs."""
    assert shutil.which("sbatch"), "CI is set but sbatch is missing: run `bash scripts/local-slurm.sh` first"
    states = _slurm("sinfo", "-h", "-o", "%T %c").split()
    ready = [s for s in states[::2] if s.rstrip("*") in ("idle", "mixed", "allocated", "completing")]
    assert ready, f"no usable SLURM node (sinfo: {' '.join(states)}); `bash scripts/local-slurm.sh` starts one"


def _snakemake(workdir: Path, config: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        str(ROOT / "Snakefile"),
        "-d",
        str(workdir),
        "--configfile",
        str(config),
        *extra,
    ]


def _cancel(prefix: str) -> None:
    """Cancel this test's SLURM jobs (by job-name prefix), never anybody else's."""
    out = subprocess.run(["squeue", "-h", "-o", "%i %j"], capture_output=True, text=True).stdout
    ids = [
        i for i, name in (line.split(maxsplit=1) for line in out.splitlines() if " " in line) if name.startswith(prefix)
    ]
    if ids:
        subprocess.run(["scancel", *ids], capture_output=True)


def _comparable(csv: Path) -> pd.DataFrame:
    """study.csv without the per-stage wall times (they differ between any two runs)."""
    df = pd.read_csv(csv, index_col="case_id")
    return df.drop(columns=[c for c in df.columns if c.startswith("time_")]).sort_index()


def test_tiny_study_on_slurm_equals_local_run(tmp_path, request):
    """One case of the tiny study (its ppp 0.004 case alone: the same case id, seeds and shared
    calibration) through SLURM, from the lenslet calibration to the study table and report, equals
    the suite's own local run of the whole tiny study (conftest's ``tiny_study``, which the
    workflow tests use too): made while the SLURM jobs queue and poll, or reused.

    Jobs (profiles/slurm groups): the calibration and the camera job side by side, then the case's
    job, then study + report. One case rather than both: each case's job repeats the same rules,
    and the two shared the node's 2 CPUs with the local run (520 s for both cases, load 6-9).
    """
    _require_cluster()
    raw = yaml.safe_load(TINY.read_text())
    raw["sweep"]["ppp"] = [0.004]
    one = tmp_path / "tiny-one-case.yaml"
    one.write_text(yaml.safe_dump(raw))
    cases = [c.case_id for c in expand_cases(load_config(one))]
    assert len(cases) == 1 and cases[0] in {c.case_id for c in expand_cases(load_config(TINY))}
    prefix = f"lfstudy-test-{os.getpid()}"
    slurm_dir = tmp_path / "slurm"
    slurm_cmd = _snakemake(
        slurm_dir,
        one,
        "--profile",
        str(PROFILE),
        # The profile as a cluster would use it, with jobs of one CPU: a group job runs its rules
        # one after another anyway, so both cases' jobs run side by side on a 2-CPU node. Short
        # status polls: the plugin's defaults (10 s, then 40 s after each finished job) would
        # make the run minutes longer. Results do not depend on the thread count.
        "--cores",
        "1",
        "--seconds-between-status-checks",
        "1",
        "--slurm-init-seconds-before-status-checks",
        "1",
        "--slurm-jobname-prefix",
        prefix,
    )
    slurm_log = tmp_path / "slurm.log"
    t0 = time.monotonic()
    with slurm_log.open("w") as log:
        proc = subprocess.Popen(slurm_cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        # The local reference is made meanwhile (unless an earlier test made it): the SLURM run
        # spends much of its time waiting for the scheduler and for status polls.
        local_dir = request.getfixturevalue("tiny_study")
        try:
            rc = proc.wait(timeout=max(60.0, TIMEOUT - (time.monotonic() - t0)))
        except subprocess.TimeoutExpired:
            rc = None
        tail = slurm_log.read_text()[-4000:]
        assert rc is not None, f"the SLURM run did not finish within {TIMEOUT} s:\n{tail}"
        assert rc == 0, f"the SLURM run failed (exit {rc}):\n{tail}"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        _cancel(prefix)

    # It really went through SLURM: accounting lists this run's jobs as completed.
    acct = _slurm("sacct", "-X", "-n", "-P", "-S", "now-1hour", "-o", "JobName%100,State").splitlines()
    states = [s for name, s in (line.split("|", 1) for line in acct) if name.startswith(prefix)]
    # calibration, cameras, one job per case, study + report
    assert len(states) >= 3 + len(cases) and set(states) == {"COMPLETED"}, acct

    slurm_out, local_out = slurm_dir / "results" / "tiny", local_dir / "results" / "tiny"
    pd.testing.assert_frame_equal(_comparable(slurm_out / "study.csv"), _comparable(local_out / "study.csv").loc[cases])
    for case in cases:
        a = io.open_zarr(slurm_out / case / "piv.zarr").load()
        b = io.open_zarr(local_out / case / "piv.zarr").load()
        assert set(a.data_vars) == set(b.data_vars) and a.sizes == b.sizes
        for name in a.data_vars:
            assert np.array_equal(a[name].values, b[name].values, equal_nan=a[name].dtype.kind == "f"), (case, name)
        for dim in a.dims:
            assert np.array_equal(a[dim].values, b[dim].values), (case, dim)
