"""The whole Snakemake DAG on a tiny config, in a temporary directory."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lfstudy import io
from lfstudy.study.config import case_config, expand_cases, load_config, sweep_of

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.yaml"
SNAKEMAKE = [sys.executable, "-m", "snakemake"]

pytestmark = pytest.mark.slow  # Snakemake runs: the tiny study alone takes minutes on 2 cores


def _snakemake(
    workdir: Path, *extra: str, timeout: float = 600, config: Path | None = TINY
) -> subprocess.CompletedProcess:
    cmd = [
        *SNAKEMAKE,
        "-s",
        str(ROOT / "Snakefile"),
        "-d",
        str(workdir),
        *(("--configfile", str(config)) if config is not None else ()),
        "--cores",
        "2",
        *extra,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def _parse_dry_run(text: str) -> dict[str, int]:
    """Rule -> job count of a dry run's job table (``all`` left out); ``{}`` only where Snakemake
    says there is nothing to do. Anything else fails: a changed dry-run format must not read as
    "no jobs" (and so pass every "nothing reruns" check)."""
    counts: dict[str, int] = {}
    total = None
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit():
            if parts[0] == "total":
                total = int(parts[1])
            elif parts[0] != "job":
                counts[parts[0]] = int(parts[1])
    if total is None:
        assert not counts and "Nothing to be done" in text, f"dry run not understood:\n{text[-3000:]}"
        return {}
    assert counts and sum(counts.values()) == total, f"job table does not add up to its total:\n{text[-3000:]}"
    counts.pop("all", None)
    return counts


def _planned_jobs(workdir: Path, config: Path = TINY) -> dict[str, int]:
    """Rule -> job count of a dry run (empty when there is nothing to do)."""
    r = _snakemake(workdir, "-n", "--quiet", "rules", config=config)
    assert r.returncode == 0, r.stderr
    return _parse_dry_run(r.stdout + r.stderr)


def _job_stats(text: str) -> dict[str, int]:
    """Rule -> job count from the job table of a full (not ``--quiet``) dry run's output: the lines
    from "Job stats:" to its "total" (the rule blocks around it hold other "name number" lines)."""
    assert "Job stats:" in text, f"no job table in the dry run:\n{text[-3000:]}"
    table = text.split("Job stats:", 1)[1]
    end = re.search(r"^total\s+\d+\s*$", table, flags=re.M)
    assert end, f"the job table has no total:\n{table[:3000]}"
    return _parse_dry_run(table[: end.end()])


def test_the_first_exposure_is_made_once_per_design_and_shared_by_its_flows(tmp_path):
    """Frame a is the seeded field before the flow moves it: its images, light field, focal stack and volume
    live at the design (the case id without its flow) and both flows of a demo design read the same files;
    frame b's are each flow's own. The demo then plans 4 x (1 + 2) jobs per frame stage, not 4 x 2 x 2."""
    from lfstudy.study.sweep import FILES

    demo = ROOT / "config" / "demo.yaml"
    sweep = sweep_of(load_config(demo))
    cases = sweep.cases()
    flows = {c.flow for c in cases}
    assert len(flows) == 2
    for name in FILES:
        where = {c.case_id: sweep.locate(c, name) for c in cases}
        design = {c.case_id: c.case_id.rsplit("/flow~", 1)[0] for c in cases}
        if name.startswith(("raw_a", "lightfield_a", "stack_a", "volume_a", "particles_a")):
            assert all(where[c] == f"{design[c]}/{name}" for c in where), (name, where)
        elif name.startswith(("raw_b", "lightfield_b", "stack_b", "volume_b", "particles_b", "piv", "errors")):
            assert all(where[c] == f"{c}/{name}" for c in where), (name, where)
    jobs = _planned_jobs(tmp_path, config=demo)
    assert jobs["simulate"] == jobs["register"] == jobs["refocus"] == jobs["reconstruct_particles"] == 12, jobs
    assert jobs["piv"] == jobs["errors"] == 8


def test_dry_run_parser_refuses_what_it_does_not_understand():
    table = "Job stats:\njob      count\n-----  -----\npiv        2\nerrors     2\nall        1\ntotal      5\n"
    assert _parse_dry_run(table) == {"piv": 2, "errors": 2}
    assert _parse_dry_run("Building DAG of jobs...\nNothing to be done (all requested files are present).") == {}
    for text in ("", "Building DAG of jobs...\n", "piv 2\nall 1\n", table.replace("total      5", "total      6")):
        with pytest.raises(AssertionError):
            _parse_dry_run(text)


@pytest.fixture(scope="module")
def study_dir(tiny_study) -> Path:
    """The session's local run of the tiny study (conftest; the SLURM test compares with it too)."""
    return tiny_study


def test_study_runs_end_to_end(study_dir):
    cfg = load_config(TINY)
    out = study_dir / "results" / "tiny"
    study = io.open_zarr(out / "study.zarr").load()
    for dim in ("magnification", "fnumber", "lenslet_pitch", "ppp", "flow"):
        assert dim in study.dims
    assert study.sizes["ppp"] == 2
    # A 1.13-voxel x shift (0.1 mm of 0.0888 mm voxels), measured: an all-zero or an all-invalid
    # result fails here.
    for ppp in (0.002, 0.004):
        sel = study.sel(ppp=ppp).squeeze()
        assert float(sel["true_x"]) == pytest.approx(0.1 / 0.0888, rel=1e-6)
        assert abs(float(sel["bias_x"])) < 0.1, float(sel["bias_x"])
        assert float(sel["rms_x"]) < 0.2 and abs(float(sel["bias_y"])) < 0.1
        assert float(sel["valid_percent"]) > 80.0
        assert float(sel["Q"]) > 0.4
        # the oracle (the case's PIV on the true volumes) reads the shift to a few µm; the
        # reconstruction's share is the rest of the case's error, in quadrature
        assert float(sel["oracle_mean_x_mm"]) == pytest.approx(0.1, abs=0.003)
        assert float(sel["oracle_valid_percent"]) > 95.0 and float(sel["time_oracle"]) > 0
        case, oracle = float(sel["rms_total_mm"]), float(sel["oracle_rms_total_mm"])
        assert float(sel["recon_added_rms_total_mm"]) == pytest.approx(np.sqrt(max(case**2 - oracle**2, 0.0)))
        assert np.isfinite(float(sel["crosstalk_z"]))
        # the budget's third term: a uniform shift has no filtering, the oracle's error is all rest
        assert float(sel["filter_rms_total_mm"]) == pytest.approx(0.0, abs=1e-12)
        assert float(sel["rest_rms_total_mm"]) == pytest.approx(oracle)
        assert float(sel["unc_coverage_x"]) == float(sel["unc_coverage_point_x"])  # window truth = point truth
        # the flag is scored on the full windows; here MART's intensity peaks at the focal plane of a 12-plane grid
        # and both windows in z read as partial (lfstudy.piv.resolution.SEEDED_LEVEL): then there is no score
        part, flagged = float(sel["partial_percent"]), float(sel["unresolved_percent"])
        assert 0.0 <= part <= 100.0
        assert (0.0 <= flagged <= 100.0) if part < 100.0 else np.isnan(flagged)
    assert (out / "study.csv").read_text().count("\n") == 1 + len(expand_cases(cfg))
    header = (out / "study.csv").read_text().splitlines()[0].split(",")
    assert {"oracle_rms_total_mm", "oracle_rms_z_mm", "recon_added_rms_total_mm", "crosstalk_z"} <= set(header)
    assert {"filter_rms_total_mm", "rest_rms_total_mm", "unc_ratio_point_z", "unresolved_hit"} <= set(header)
    assert {"unc_coverage_oracle_x", "unc_ratio_oracle_z"} <= set(header)
    err = io.open_zarr(out / expand_cases(cfg)[0].case_id / "errors.zarr")
    assert err["oracle_w_mm"].dims == err["w_err_mm"].dims and "oracle_mean_z_mm" in err
    assert err["u_filter_mm"].dims == err["u_err_mm"].dims
    piv = io.open_zarr(out / expand_cases(cfg)[0].case_id / "piv.zarr")
    assert piv["unresolved"].dtype == bool
    # The report is self-contained: figures embedded, nothing fetched from the network.
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 5
    assert 'src="http' not in html and "<script src" not in html


def test_simulate_case_reproduces_the_workflow(study_dir):
    """`lfstudy simulate` (simulate_case) gives the same bytes as the Snakemake rules."""
    from lfstudy.study.case import simulate_case

    out = study_dir / "results" / "tiny"
    cid = expand_cases(load_config(TINY))[-1].case_id
    res = simulate_case(case_config(load_config(TINY), cid))
    for frame in "ab":  # frame a at the design (shared by its flows), frame b at the case
        raw = io.open_zarr(out / sweep_of(load_config(TINY)).locate(cid, f"raw_{frame}.zarr"), name="intensity").values
        assert np.array_equal(res[f"image_{frame}"].values, raw)
    pin = io.open_zarr(
        out / "calib" / case_config(load_config(TINY), cid)["calib_id"] / "pinhole.zarr", name="intensity"
    )
    pin = pin.values
    assert np.array_equal(res["pinhole"].values, pin)
    parts = io.open_zarr(out / cid / "particles_b.zarr").load()
    assert np.array_equal(res["particles_b"]["x"].values, parts["x"].values)


def test_snakemake_report(study_dir):
    """`snakemake --report` (no --cores needed) packs the study report with its caption."""
    import zipfile

    cmd = [
        *SNAKEMAKE,
        "-s",
        str(ROOT / "Snakefile"),
        "-d",
        str(study_dir),
        "--configfile",
        str(TINY),
        "--report",
        str(study_dir / "smk_report.zip"),
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    names = zipfile.ZipFile(study_dir / "smk_report.zip").namelist()
    assert any("/data/raw/" in n and n.endswith("/report.html") for n in names), names  # the study report


def test_second_run_does_nothing(study_dir):
    assert _planned_jobs(study_dir) == {}


def test_config_change_reruns_only_dependent_stages(study_dir, tmp_path):
    """Each stage's config sections are its params: a PIV setting reruns PIV onward only (and the
    depth calibration, which correlates its traversed volume with the case's PIV settings)."""
    text = TINY.read_text()
    assert "spacing: [4, 8, 8]" in text
    changed = tmp_path / "tiny.yaml"
    changed.write_text(text.replace("spacing: [4, 8, 8]", "spacing: [4, 6, 6]"))
    jobs = _planned_jobs(study_dir, config=changed)
    assert set(jobs) == {"depthcal", "piv", "errors", "study", "report"}
    assert jobs["piv"] == jobs["errors"] == len(expand_cases(load_config(TINY)))
    # a density of its own each (it seeds at the case's ppp), none per flow
    assert jobs["depthcal"] == len(load_config(TINY)["sweep"]["ppp"])


def test_a_smaller_sweep_reruns_no_shared_stage(study_dir, tmp_path):
    """Dropping a swept value changes which case stands for each shared stage (camera, pinhole,
    calibration); their settings did not change, so only the study table and the report rerun."""
    text = TINY.read_text()
    assert "ppp: [0.002, 0.004]" in text
    changed = tmp_path / "tiny.yaml"
    changed.write_text(text.replace("ppp: [0.002, 0.004]", "ppp: [0.004]"))
    assert set(_planned_jobs(study_dir, config=changed)) == {"study", "report"}


def test_deleting_intermediate_reruns_only_dependents_and_a_killed_rerun_restarts_cleanly(study_dir):
    """A deleted volume plans only its dependents. Then, with a focal stack deleted too, kill snakemake in
    the middle of that stack's job: the restart finishes (both chains) and no store is half-written.
    (One test: the two used to rerun the same case's chain twice, ~40 s each.)"""
    out = study_dir / "results" / "tiny"
    case = expand_cases(load_config(TINY))[0].case_id
    shutil.rmtree(out / case / "volume_b.zarr")
    jobs = _planned_jobs(study_dir)
    assert set(jobs) == {"reconstruct", "piv", "errors", "study", "report"}
    assert jobs["reconstruct"] == 1 and jobs["piv"] == 1
    shutil.rmtree(out / "study.zarr")
    # the case's focal stack: its refocus job is where the kill lands; the rest of its chain reruns
    stack_a = out / sweep_of(load_config(TINY)).locate(case, "stack_a.zarr")  # frame a: at the design
    shutil.rmtree(stack_a)
    cmd = [*SNAKEMAKE, "-s", str(ROOT / "Snakefile"), "-d", str(study_dir), "--configfile", str(TINY), "--cores", "1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    # Wait until a refocus job is writing its store (its hidden temporary store exists), then
    # kill everything hard, so the kill lands in the middle of a write.
    writing = False
    while time.time() < deadline and proc.poll() is None:
        # (that store's folder only: a recursive walk races with other jobs' temporary stores vanishing)
        if any(stack_a.parent.glob(".stack_a.zarr.lfstudy-tmp-*")):
            writing = True
            break
        time.sleep(0.01)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert writing, "the kill did not land while a focal stack was being written"
    # A killed writer may leave its hidden temporary store, but never an incomplete store under
    # the real name: every visible zarr store opens.
    for store in out.rglob("*.zarr"):
        io.open_zarr(store)
    # A SIGKILLed snakemake cannot release its lock: the documented restart is
    # --unlock, then the same command with --rerun-incomplete.
    r = _snakemake(study_dir, "--unlock")
    assert r.returncode == 0, r.stderr[-3000:]
    r = _snakemake(study_dir, "--rerun-incomplete")
    assert r.returncode == 0, r.stderr[-3000:]
    assert _planned_jobs(study_dir) == {}
    assert (out / case / "volume_b.zarr").is_dir() and stack_a.is_dir()
    for store in out.rglob("*.zarr"):
        io.open_zarr(store)
    # The rerun cleaned the killed writer's temporary output.
    assert not list(out.rglob(".*.lfstudy-*"))


def test_stage_entry_point(tmp_path):
    """`python -m lfstudy.workflow STAGE` (what the rules run): outputs on success; on failure
    exit 1, the traceback in the log and no output left behind."""
    import json

    from lfstudy.study.config import stage_config

    cfg = load_config(TINY)
    cid = expand_cases(cfg)[0].case_id
    entry = [sys.executable, "-m", "lfstudy.workflow"]
    ok = json.dumps(stage_config(cfg, cid, "camera"))
    r = subprocess.run(
        [
            *entry,
            "camera",
            "--config",
            ok,
            "--log",
            str(tmp_path / "ok.log"),
            str(tmp_path / "camera.json"),
            str(tmp_path / "planes.zarr"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, (tmp_path / "ok.log").read_text()
    assert json.loads((tmp_path / "camera.json").read_text())["stage_id"] == "mag~-1/fnum~matched/pitch~0.0888"
    assert io.open_zarr(tmp_path / "planes.zarr").sizes
    # A stage given less config than it reads fails loudly, points at its log, writes nothing.
    too_little = json.dumps(stage_config(cfg, cid, "calibrate"))  # the camera section, no refocus
    r = subprocess.run(
        [
            *entry,
            "--config",
            too_little,
            "--log",
            str(tmp_path / "bad.log"),
            "camera",
            str(tmp_path / "c2.json"),
            str(tmp_path / "p2.zarr"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1
    assert "KeyError: 'refocus'" in (tmp_path / "bad.log").read_text() and "bad.log" in r.stderr
    assert not (tmp_path / "c2.json").exists() and not (tmp_path / "p2.zarr").exists()


def test_a_given_config_does_not_inherit_the_demo(tmp_path):
    """Snakemake merges --configfile into the Snakefile's `configfile:` key by key: run where
    config/demo.yaml exists (the repository root), a study would inherit the demo's sweep keys
    (magnification, lenslet_pitch, reconstruct.method: 16 cases) and grid. The demo config is
    read only when no config is given."""
    work = tmp_path / "work"
    (work / "config").mkdir(parents=True)
    shutil.copy(ROOT / "config" / "demo.yaml", work / "config" / "demo.yaml")
    jobs = _planned_jobs(work)
    assert jobs["piv"] == 2 and jobs["reconstruct"] == 4, jobs  # tiny.yaml: 2 ppp x 1 flow, 2 frames
    r = _snakemake(work, "-n", "--quiet", "rules", "--config", "name=demo_only", config=None)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "config/demo.yaml" in r.stdout + r.stderr


def test_sweep_over_dotted_settings_shares_the_upstream_stages(study_dir, tmp_path):
    """reconstruct.method and piv.spacing swept by their dotted paths: the images, light fields and
    stacks are made once and shared, each method reconstructs once and feeds two PIV spacings, and
    the study has a dimension per swept setting. Run beside a copy of the tiny study: its images,
    light fields and stacks have the same settings, so only the swept stages run."""
    import yaml

    raw = yaml.safe_load(TINY.read_text())
    raw["sweep"] = {
        "ppp": [0.004],
        "reconstruct.method": ["threshold", "mart"],
        "piv.spacing": [[4, 8, 8], [4, 6, 6]],
    }
    raw["reconstruct"] = {"method": "threshold", "mart": {"iterations": 2}}
    raw["depth_calibration"] = {"enabled": False}  # not what is checked here (the suite's time)
    cfg_path = tmp_path / "dotted.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    jobs = _planned_jobs(tmp_path / "fresh", config=cfg_path)
    assert jobs["simulate"] == 2 and jobs["register"] == 2 and jobs["refocus"] == 2  # shared by all 4 cases
    assert jobs["reconstruct"] == 4 and jobs["piv"] == 4 and jobs["errors"] == 4
    work = tmp_path / "work"
    shutil.copytree(study_dir, work, symlinks=True)  # copy2: the outputs keep their times
    r = _snakemake(work, config=cfg_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    jobs = _job_stats(r.stdout + r.stderr)  # the run's own plan (its job table comes before the first job)
    assert not {"particles", "simulate", "register", "refocus"} & set(jobs), jobs  # the tiny study's, reused
    assert jobs["reconstruct"] == 4 and jobs["piv"] == 4 and jobs["errors"] == 4
    study = io.open_zarr(work / "results" / "tiny" / "study.zarr").load()
    assert list(study["reconstruct_method"].values) == ["threshold", "mart"]
    assert list(study["piv_spacing"].values) == ["4x8x8", "4x6x6"]
    assert study["reconstruct_method"].attrs["sweep_key"] == "reconstruct.method"
    assert int(study["computed"].sum()) == 4
    rms = study["rms_total_mm"].squeeze()
    assert np.all(np.isfinite(rms.values)), rms
    mart_id = str(study["case_id"].sel(reconstruct_method="mart", piv_spacing="4x6x6").squeeze().values)
    assert mart_id.endswith("/reconstruct.method~mart/piv.spacing~4x6x6")
    vol = io.open_array(work / "results" / "tiny" / sweep_of(load_config(cfg_path)).locate(mart_id, "volume_a.zarr"))
    assert "flow~" not in sweep_of(load_config(cfg_path)).locate(mart_id, "volume_a.zarr")  # shared by the flows
    assert vol.attrs["method"] == "mart" and float(vol.min()) >= 0.0


def test_open_study_is_lazy_and_quiet(study_dir):
    """lfstudy.open_study gives the whole study as one DataTree, and neither it nor a plain
    xarray.open_zarr of any store prints a warning."""
    import warnings

    import xarray as xr

    import lfstudy

    out = study_dir / "results" / "tiny"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tree = lfstudy.open_study(out)
        study = tree.to_dataset()
        assert "rms_total_mm" in study and study.sizes["ppp"] == 2
        cid = str(study["case_id"].sel(ppp=0.004).squeeze().values)
        piv = tree[f"{cid}/piv"].to_dataset()
        assert {"u", "v", "w", "valid"} <= set(piv.data_vars)
        assert hasattr(piv["u"].data, "dask")  # lazy
        assert any(node.name == "centers" for node in tree["calib"].subtree)
        vol_a = out / sweep_of(load_config(TINY)).locate(cid, "volume_a.zarr")  # frame a: at the design
        for store in (out / cid / "piv.zarr", vol_a, out / "study.zarr"):
            xr.open_zarr(store).close()


def test_heavy_rules_declare_their_memory(tmp_path):
    """Every heavy rule declares its case's memory estimate as Snakemake's mem_mb (retries double it), so
    neither `--cores N` nor SLURM runs more such jobs side by side than the memory holds. A fine grid puts
    the PIV and reconstruction estimates above the floor."""
    import re

    import yaml

    from lfstudy.study.config import validate_config
    from lfstudy.study.resources import RULE_STAGES, job_mem_mb, job_runtime_min
    from lfstudy.study.sweep import Sweep

    raw = yaml.safe_load(TINY.read_text())
    raw["grid"] = {"voxel_xy": 0.02, "voxel_z": 0.002}
    raw["refocus"]["model"] = "volumetric"  # plans the dot-target calibration (rule volcal) too
    path = tmp_path / "fine.yaml"
    path.write_text(yaml.safe_dump(raw))
    sweep = Sweep(validate_config(raw))
    expected = {rule: {job_mem_mb(sweep.apply(c), rule) for c in sweep.cases()} for rule in RULE_STAGES}
    assert max(expected["piv"]) > 1500 and max(expected["reconstruct"]) > 1500
    cmd = [*SNAKEMAKE, "-s", str(ROOT / "Snakefile"), "-d", str(tmp_path), "--configfile", str(path)]
    r = subprocess.run([*cmd, "-n", "--cores", "2"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    seen = {}
    for block in re.split(r"\n(?=rule \w+:)", r.stdout + r.stderr):
        m = re.match(r"rule (\w+):", block)
        if m and m.group(1) in RULE_STAGES:
            mem = re.search(r"resources: .*\bmem_mb=(\d+)", block)
            assert mem, block
            seen.setdefault(m.group(1), set()).add(int(mem.group(1)))
    assert set(seen) == set(RULE_STAGES) - {"process"}, seen
    for rule, values in seen.items():
        assert values <= expected[rule], (rule, values, expected[rule])
    # and the reconstruct jobs their time limit (job_runtime_min: the floor for these grid methods)
    runtimes = {job_runtime_min(sweep.apply(c), "reconstruct", 5) for c in sweep.cases()}
    for block in re.split(r"\n(?=rule \w+:)", r.stdout + r.stderr):
        if block.startswith(("rule reconstruct:", "rule reconstruct_particles:")):
            minutes = re.search(r"resources: .*\bruntime=(\d+)", block)
            assert minutes and int(minutes.group(1)) in runtimes, block


def test_slurm_profile_leaves_the_estimate_to_the_heavy_rules():
    """The profile's set-resources would override a rule's own mem_mb and runtime: it sets no mem_mb for the heavy
    rules and no runtime for reconstruct (its method's estimate)."""
    import yaml

    from lfstudy.study.resources import RULE_STAGES

    profile = yaml.safe_load((ROOT / "profiles" / "slurm" / "config.yaml").read_text())
    for rule, res in profile["set-resources"].items():
        assert rule not in RULE_STAGES or "mem_mb" not in res, rule
    assert "runtime" not in profile["set-resources"].get("reconstruct", {})


def test_an_ipr_case_plans_its_particle_list(tmp_path):
    """reconstruct.method swept over mart and ipr: the ipr case's reconstruction (rule
    reconstruct_particles) also writes volume_{a,b}.particles.zarr, once per frame; the mart case keeps
    rule reconstruct and its one output. A study without ipr plans no particle list."""
    import yaml

    raw = yaml.safe_load(TINY.read_text())
    raw["sweep"] = {"ppp": [0.004], "reconstruct.method": ["mart", "ipr"]}
    cfg_path = tmp_path / "ipr.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    work = tmp_path / "work"
    r = _snakemake(work, "-n", config=cfg_path)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    jobs = _job_stats(out)
    assert jobs["reconstruct"] == 2 and jobs["reconstruct_particles"] == 2 and jobs["piv"] == 2
    planned = set(re.findall(r"\S*volume_[ab]\.particles\.zarr", out))
    assert {Path(p).parent.name for p in planned} == {"reconstruct.method~ipr"} and len(planned) == 2
    assert not re.search(r"reconstruct.method~mart/volume_[ab]\.particles", out)
    # the ipr case's errors job reads both lists (found particles, ghosts); the mart case's none
    errors = {b.split("output:")[1].split()[0]: b for b in re.split(r"\n(?=rule )", out) if b.startswith("rule errors")}
    assert len(errors) == 2
    for target, block in errors.items():
        reads = set(re.findall(r"volume_[ab]\.particles\.zarr", block.split("output:")[0]))
        assert reads == ({"volume_a.particles.zarr", "volume_b.particles.zarr"} if "~ipr" in target else set())
    tiny = _snakemake(tmp_path / "tiny", "-n", config=TINY)
    assert tiny.returncode == 0 and "particles.zarr" not in tiny.stdout + tiny.stderr
    assert "reconstruct_particles" not in _job_stats(tiny.stdout + tiny.stderr)


def test_a_ptv_case_reads_the_particle_lists_in_its_piv_job(tmp_path):
    """piv.particles swept over none and ptv on an ipr study: the ptv case's piv job reads both
    frames' particle lists (inputs and command line, after the '' of the disabled depth calibration);
    the none case's reads none. Both share one reconstruction."""
    import yaml

    raw = yaml.safe_load(TINY.read_text())
    raw["reconstruct"] = {"method": "ipr"}
    raw["depth_calibration"] = {"enabled": False}
    raw["sweep"] = {"ppp": [0.004], "piv.particles": ["none", "ptv"]}
    cfg_path = tmp_path / "ptv.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    r = _snakemake(tmp_path / "work", "-n", "-p", config=cfg_path)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    assert len(re.findall(r"\nrule reconstruct_particles:", out)) == 2  # one reconstruction per frame
    blocks = {b.split("output:")[1].split()[0]: b for b in re.split(r"\n(?=rule )", out) if b.startswith("rule piv:")}
    assert len(blocks) == 2
    for target, block in blocks.items():
        reads = set(re.findall(r"volume_[ab]\.particles\.zarr", block.split("output:")[0]))
        command = block.split("resources:")[-1]
        if "piv.particles~ptv" in target:
            assert reads == {"volume_a.particles.zarr", "volume_b.particles.zarr"}
            assert re.search(r"piv\.zarr'? '' \S*volume_a\.particles\.zarr'? \S*volume_b\.particles\.zarr", command)
        else:
            assert not reads and not re.search(r"particles\.zarr", command)


def test_a_study_name_that_is_a_path_is_refused(tmp_path):
    """`name: ..` once planned report.html in the working directory's root: a study's name is a plain
    name, refused before Snakemake plans or removes anything."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.txt").write_text("mine")
    r = _snakemake(work, "-n", "--config", "name=..")
    assert r.returncode != 0
    text = r.stdout + r.stderr
    assert "config key 'name' = '..': a plain name" in text, text[-2000:]
    assert (work / "notes.txt").read_text() == "mine"
