"""Per-vector uncertainty against the truth on study cases (issue 28): coverage and RMS ratio.

Reproduces: lfstudy/piv/resolution.py (the ``unresolved`` flag's hit and false rates on the thesis camera's
MART and IPR reconstructions); with bench_uncertainty_calibration.py, docs/config.md § "σ calibrated by a
study (`uncertainty.calibration`)" (the thesis camera's raw coverage and ratio); it is also the runner of
bench_budget.py and bench_ipr_density.py (their coverage and ratio columns in the config reference).

Runs the cases of a config (default: the thesis camera, Table 4.3) through the same stage
functions the Snakefile's rules call, in this process's workers (no Snakemake: this also runs
on a machine with many cores and no Snakemake), each stage's distinct output once as in the
workflow (shared images, calibration and depth calibration); each task starts as soon as its
inputs are written, the IPR fits first (the longest). Then prints, per case and
component, the fraction of valid vectors whose |error| is within their standard uncertainty
(``unc_coverage``; 0.68 where σ is right) and RMS(error)/RMS(σ) (``unc_ratio``; 1 where it is
right), both against the truth averaged over each final window (issue 38) and against the point
truth, with the error, the oracle's and the windows' filtering beside them, the z row on its own,
and the ``unresolved`` flag's scores per case.

Targets (issue 28): coverage 0.55-0.80 and ratio 0.7-1.4 per component, on the thesis camera
at 0.001 and 0.005 ppp (uniform, Hill and a new flow) and on a demo design.

    python benchmarks/bench_uncertainty.py [--config config/thesis.yaml] [--flows uniform_x hill]
        [--ppp 0.001 0.005] [--set depth_calibration.enabled=false ...] [--jobs 2] [--threads 1]
        [--sweep piv.uncertainty=[correlation,independent,moment]]
        [--out DIR] [--table]
"""

from __future__ import annotations

import argparse
import os
import re
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
TARGET_COV, TARGET_RATIO = (0.55, 0.80), (0.7, 1.4)


def read_config(path: Path, sets: list[str]) -> dict[str, Any]:
    """The raw config at ``path`` with each ``--set PATH=VALUE`` (dotted path, YAML value) applied."""
    from lfstudy.config import read_yaml

    raw = read_yaml(path)
    for item in sets:
        key, _, val = item.partition("=")
        node = raw
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = yaml.safe_load(val)
    return raw


def _config(args: argparse.Namespace) -> dict[str, Any]:
    from lfstudy.study.config import validate_config

    raw = read_config(args.config, args.set)
    sweep = raw.setdefault("sweep", {})
    for item in args.sweep:
        key, _, vals = item.partition("=")
        sweep[key] = yaml.safe_load(vals)
    if args.flows:
        sweep["flow"] = list(args.flows)
    if args.ppp:
        sweep["ppp"] = list(args.ppp)
    if args.seed is not None:
        raw["seed"] = args.seed
    return validate_config(raw)


def _tasks(cfg: dict[str, Any], out: Path) -> list[list[tuple[str, Callable[..., None], tuple]]]:
    """The workflow's stages as waves of independent tasks: (label, function, args)."""
    from lfstudy import workflow as wf
    from lfstudy.piv.ptv import PARTICLE_MODES
    from lfstudy.study.config import stage_config
    from lfstudy.study.sweep import Sweep, frame_stage

    sw = Sweep(cfg)

    def at(case, name: str) -> Path:
        return out / sw.locate(case, name)

    def each(stage: str):
        return [(sid, case, stage_config(cfg, case, stage)) for sid, case in sw.stage_ids(stage).items()]

    def frames(stage: str):
        """(frame, sid, case, config) of a stage run per frame: frame a once per design at its own stage
        (lfstudy.study.sweep.frame_stage), frame b per case."""
        return [(f, *t) for f in "ab" for t in each(frame_stage(stage, f))]

    depth_on = cfg["depth_calibration"]["enabled"]
    waves: list[list[tuple[str, Callable[..., None], tuple]]] = [[], [], [], [], [], [], [], []]
    for sid, c, sc in each("camera"):
        waves[0].append((f"camera {sid}", wf.run_optics, (sc, at(c, "camera.json"), at(c, "focal_planes.zarr"))))
    for sid, c, sc in each("particles"):
        waves[0].append((f"particles {sid}", wf.run_particles, (sc, at(c, "particles_a.zarr"))))
    for sid, c, sc in each("pinhole"):
        waves[0].append((f"pinhole {sid}", wf.run_pinhole, (sc, at(c, "pinhole.zarr"), at(c, "pinhole.tif"))))
    for sid, c, sc in each("displace"):
        args = (sc, at(c, "particles_a.zarr"), at(c, "particles_b.zarr"))
        waves[1].append((f"displace {sid}", wf.run_displace, args))
    for sid, c, sc in each("calibrate"):
        waves[1].append((f"calibrate {sid}", wf.run_calibrate, (sc, at(c, "pinhole.zarr"), at(c, "centers.zarr"))))
    for f, sid, c, sc in frames("simulate"):
        args = (sc, f, at(c, f"particles_{f}.zarr"), at(c, f"raw_{f}.zarr"), at(c, f"raw_{f}.tif"))
        waves[2].append((f"simulate {f} {sid}", wf.run_simulate, args))
    if depth_on:
        for sid, c, sc in each("depthcal"):
            args = (sc, at(c, "centers.zarr"), at(c, "depth_calibration.zarr"))
            waves[2].append((f"depthcal {sid}", wf.run_depth_calibration, args))
    for f, sid, c, sc in frames("register"):
        args = (sc, at(c, f"raw_{f}.zarr"), at(c, "centers.zarr"), at(c, f"lightfield_{f}.zarr"))
        waves[3].append((f"register {f} {sid}", wf.run_register, args))
    for f, sid, c, sc in frames("refocus"):
        args = (sc, at(c, f"lightfield_{f}.zarr"), at(c, f"stack_{f}.zarr"))
        waves[4].append((f"refocus {f} {sid}", wf.run_refocus, args))
    for f, sid, c, sc in frames("reconstruct"):
        args = (sc, at(c, f"stack_{f}.zarr"), at(c, f"lightfield_{f}.zarr"), at(c, "centers.zarr"))
        args += (at(c, f"volume_{f}.zarr"),)
        if sc["reconstruct"]["method"] == "ipr":
            args += (at(c, f"volume_{f}.particles.zarr"),)
        waves[5].append((f"reconstruct {f} {sid}", wf.run_reconstruct, args))
    for sid, c, sc in each("piv"):
        depth = at(c, "depth_calibration.zarr") if depth_on else None
        args = (sc, at(c, "volume_a.zarr"), at(c, "volume_b.zarr"), at(c, "piv.zarr"), depth)
        if sc["piv"].get("particles", "none") in PARTICLE_MODES:  # the fitted particles of both frames (IPR)
            args += tuple(at(c, f"volume_{f}.particles.zarr") for f in "ab")
        waves[6].append((f"piv {sid}", wf.run_piv, args))
    for c in sw.cases():
        sc = stage_config(cfg, c, "errors")
        args = (sc, at(c, "piv.zarr"), at(c, "volume_a.zarr"), at(c, "particles_a.zarr"), at(c, "errors.zarr"))
        args += (at(c, "particles_b.zarr"),)
        if sc["reconstruct"]["method"] == "ipr":  # the lists live at their frames' stages (frame a at the design)
            args += tuple(at(c, f"volume_{f}.particles.zarr") for f in "ab")
        waves[7].append((f"errors {c.case_id}", wf.run_errors, args))
    return waves


#: The argument that is a task's output, per stage function (the rest are its inputs and settings).
_OUTPUT_ARG = {
    "run_optics": 2,
    "run_particles": 1,
    "run_pinhole": 1,
    "run_displace": 2,
    "run_calibrate": 2,
    "run_simulate": 3,
    "run_depth_calibration": 2,
    "run_register": 3,
    "run_refocus": 2,
    "run_reconstruct": 4,
    "run_piv": 3,
    "run_errors": 4,
}


def _written(label: str, fn: Callable[..., None], args: tuple) -> bool:
    """Whether a task's output is there already (an earlier run into the same --out): it is kept."""
    return Path(args[_OUTPUT_ARG[fn.__name__]]).exists()


def _priority(wave: int, fn: Callable[..., None], args: tuple) -> tuple[float, bool, int]:
    """Sort key of a ready task: the longest first (an IPR fit takes 10-30x a MART reconstruction and grows
    with the seeding, so the fits do not start last and hold the run's end), then a case's PIV and errors (as
    soon as its volumes are there: a run stopped early keeps whole cases), then the earlier stages first
    (the calibration before the images: the reconstructions need both)."""
    cost = 0.0
    if fn.__name__ == "run_reconstruct":
        sc = args[0]
        # the stage config holds no ppp (the images it reads do); its stage id names it (ppp~<value>)
        ppp = re.search(r"(?:^|/)ppp~([^/]+)", sc["stage_id"])
        cost = (30.0 if sc["reconstruct"]["method"] == "ipr" else 1.0) * (float(ppp.group(1)) if ppp else 1.0)
    return -cost, fn.__name__ not in ("run_piv", "run_errors"), wave


def _schedule(waves: list[list[tuple[str, Callable[..., None], tuple]]], jobs: int, threads: int) -> int:
    """Run the tasks in ``jobs`` workers, each as soon as the tasks writing its inputs are done.

    A task depends on the tasks whose output (``_OUTPUT_ARG``) is among its arguments; the waves give a
    topological order. An output already there (an earlier run into the same --out) is kept: stages rerun
    only where missing. A task that raises is reported and the tasks that need its output are left out
    (the other cases run on); returns the number of tasks that failed or were left out.
    """
    tasks = [(w, label, fn, a) for w, wave in enumerate(waves) for label, fn, a in wave]
    writer = {Path(a[_OUTPUT_ARG[fn.__name__]]): i for i, (_, _, fn, a) in enumerate(tasks)}
    deps = [
        {writer[x] for j, x in enumerate(a) if isinstance(x, Path) and j != _OUTPUT_ARG[fn.__name__] and x in writer}
        for _, _, fn, a in tasks
    ]
    done = {i for i, (_, label, fn, a) in enumerate(tasks) if _written(label, fn, a)}
    waiting = [i for i in range(len(tasks)) if i not in done]
    running: dict[Any, int] = {}
    failed: set[int] = set()
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        while waiting or running:
            for i in [i for i in waiting if deps[i] & failed]:
                waiting.remove(i)
                failed.add(i)
                print(f"  left out (an input failed): {tasks[i][1]}", flush=True)
            ready = sorted(
                (i for i in waiting if deps[i] <= done),
                key=lambda i: (*_priority(tasks[i][0], tasks[i][2], tasks[i][3]), i),
            )
            for i in ready[: jobs - len(running)]:
                waiting.remove(i)
                _, label, fn, a = tasks[i]
                running[pool.submit(_run, label, fn, a, threads)] = i
            if not running:
                if waiting:
                    raise RuntimeError(f"bench_uncertainty: {len(waiting)} tasks wait on inputs no task writes")
                break
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                i = running.pop(f)
                try:
                    label, secs = f.result()
                except Exception as exc:  # one case's failure is reported; the others run on
                    failed.add(i)
                    print(f"  FAILED {tasks[i][1]}: {type(exc).__name__}: {exc}", flush=True)
                    continue
                done.add(i)
                print(f"  {secs:8.1f} s  {label}", flush=True)
    return len(failed)


def _run(label: str, fn: Callable[..., None], args: tuple, threads: int) -> tuple[str, float]:
    from lfstudy import workflow as wf

    wf.set_threads(threads)
    t0 = time.perf_counter()
    fn(*args)
    return label, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "thesis.yaml")
    ap.add_argument("--flows", nargs="*", default=None, help="the sweep's flows (default: the config's)")
    ap.add_argument("--ppp", nargs="*", type=float, default=None, help="the sweep's ppp (default: the config's)")
    ap.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE", help="config overrides (YAML values)")
    ap.add_argument(
        "--sweep",
        nargs="*",
        default=[],
        metavar="KEY=[V1,V2]",
        help="swept settings added (YAML list), e.g. piv.uncertainty=[correlation,independent,moment]",
    )
    ap.add_argument("--seed", type=int, default=None, help="study seed (default: the config's)")
    ap.add_argument("--jobs", type=int, default=1, help="tasks run side by side")
    ap.add_argument("--threads", type=int, default=max(1, (os.cpu_count() or 1)), help="threads per task")
    ap.add_argument("--out", type=Path, default=None, help="working directory (default: a temp dir)")
    ap.add_argument("--table", action="store_true", help="only print the table of the cases written in --out")
    args = ap.parse_args()

    cfg = _config(args)
    if args.table:
        if args.out is None:
            raise SystemExit("--table needs --out (the run's directory)")
        _table(cfg, args.out)
        return
    out = args.out or Path(tempfile.mkdtemp(prefix="lfstudy-bench-unc-"))
    waves = _tasks(cfg, out)
    print(f"{args.config.name}: {sum(map(len, waves))} tasks, {args.jobs} jobs x {args.threads} threads, in {out}")
    t_all = time.perf_counter()
    n_failed = _schedule(waves, args.jobs, args.threads)
    print(f"all stages {time.perf_counter() - t_all:.0f} s")
    _table(cfg, out)
    if n_failed:
        raise SystemExit(f"{n_failed} tasks failed or were left out (FAILED lines above)")


def _table(cfg: dict[str, Any], out: Path) -> None:
    from lfstudy import io
    from lfstudy.study.sweep import Sweep

    sw = Sweep(cfg)
    rows = []
    for c in sw.cases():
        path = out / sw.locate(c, "errors.zarr")
        if path.exists():  # a run stopped early (a time limit) still tabulates the cases it finished
            rows.append((c, io.open_zarr(path).load()))
        else:
            print(f"no errors.zarr for {c.case_id}: left out of the table")
    if not rows:
        return
    keys = [s.key for s in sw.swept]
    names = {c.case_id: " ".join(f"{k}={c[k]}" for k in keys) or c.case_id for c, _ in rows}
    w = max(map(len, names.values())) + 1
    print("\ncase" + " " * (w - 4) + "ax  coverage  ratio   rms_mm  oracle_mm  valid%  point cov/ratio  filter_mm")
    zrows = []
    for c, e in rows:
        name = names[c.case_id]
        for ax in "xyz":
            line = (
                f"{name:<{w}}{ax:>2}  {float(e[f'unc_coverage_{ax}']):8.3f}  {float(e[f'unc_ratio_{ax}']):5.2f}"
                f"  {float(e[f'rms_{ax}_mm']):7.4f}  {float(e.get(f'oracle_rms_{ax}_mm', np.nan)):9.4f}"
                f"  {float(e['valid_percent']):6.1f}  {float(e.get(f'unc_coverage_point_{ax}', np.nan)):6.3f}/"
                f"{float(e.get(f'unc_ratio_point_{ax}', np.nan)):4.2f}"
                f"  {float(e.get(f'filter_rms_{ax}_mm', np.nan)):9.4f}"
            )
            (zrows if ax == "z" else []).append(line)
            if ax != "z":
                print(line)
    print("z (on its own):")
    for line in zrows:
        print(line)
    print(
        "\nunresolved flag over the full windows (percent flagged, hit of > 2σ, false of the flags < σ), and the "
        "valid vectors of partial windows:"
    )
    for c, e in rows:
        print(
            f"{names[c.case_id]:<{w}}  {float(e.get('unresolved_percent', np.nan)):5.1f} %  hit "
            f"{float(e.get('unresolved_hit', np.nan)):.2f}  false {float(e.get('unresolved_false', np.nan)):.2f}  "
            f"partial {float(e.get('partial_percent', np.nan)):5.1f} %"
        )
    print("\nthe budget's filter term against the oracle (total RMS, mm):")
    for c, e in rows:
        ft, ot = float(e.get("filter_rms_total_mm", np.nan)), float(e.get("oracle_rms_total_mm", np.nan))
        share = ft / ot if ot > 0 else np.nan
        print(f"{names[c.case_id]:<{w}}  filter {ft:.4f}  oracle {ot:.4f}  filter/oracle {share:.2f}")
    cov = np.array([[float(e[f"unc_coverage_{ax}"]) for ax in "xyz"] for _, e in rows])
    rat = np.array([[float(e[f"unc_ratio_{ax}"]) for ax in "xyz"] for _, e in rows])
    inside = (cov >= TARGET_COV[0]) & (cov <= TARGET_COV[1]) & (rat >= TARGET_RATIO[0]) & (rat <= TARGET_RATIO[1])
    print(
        f"\nin the target band (coverage {TARGET_COV}, ratio {TARGET_RATIO}): {inside.sum()} of {inside.size}"
        f" case-components; per component x/y/z: {' / '.join(str(int(v)) for v in inside.sum(axis=0))}"
        f" of {len(rows)}"
    )


if __name__ == "__main__":
    main()
