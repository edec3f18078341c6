"""Benchmark of the reconstructions on one grid: threshold, deconvolution and MART (issue: depth).

Reproduces: docs/architecture.md § "Benchmarks" (the methods on the same images); config/thesis.yaml (the
uniform_z_thesis flow: ``--thesis72``).

Table 4.3 optics (``config/thesis.yaml``), full sensor by default (``--sensor W H`` for a
central region). For every flow and seeding density: the particle fields, both raw images
(Monte-Carlo ray tracing, 25,000 rays), the pinhole calibration, registration and the focal
stacks on the reconstruction grid are made once; every method then reconstructs the same
stacks and light fields, and PIV and the errors follow. Every stage runs as the Snakemake
rules run it (``python -m lfstudy.workflow STAGE``), in a child process, so its wall time and
peak memory are its own.

Printed per case and method: seconds per frame (and per MART iteration), peak RSS of the
reconstruction, Q (against the true particles, half the camera's resolution cell), valid
vectors, mean measured z displacement against the truth (and its error in % of the truth),
bias / RMS / std per component in mm and voxels, total RMS. Each (density, method) gets its
depth calibration (the ``depthcal`` stage: a traversed seeded volume of its own) and the z
figures are printed after it and before it (raw). ``--thesis72`` adds sec. 7.2 as
the thesis ran it (a 2.5-voxel z shift of 1.9974 mm; 32 planes over 1.5x the depth, one voxel
per refocus plane, threshold) beside the thesis' mu -2.47 px, sigma 0.57 px.

    python benchmarks/bench_reconstruct.py [--ppp 0.001 0.005 0.01] [--flows uniform_z hill]
        [--methods threshold deconvolution mart] [--sensor W H] [--out DIR] [--threads 2] [--thesis72]
        [--iterations N] [--relaxation MU] [--no-depth-calibration]
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lfstudy import io
from lfstudy.study.config import load_config, stage_config, sweep_of, validate_config

ROOT = Path(__file__).resolve().parents[1]
THESIS_72 = {"mean": -2.47, "std": 0.57}  # sec. 7.2, Fig. 7.8 (px = refocus planes, image-frame sign)


def _run(stage: str, cfg: dict, case, args: list[str], logdir: Path, threads: int) -> tuple[float, float]:
    """One stage in a child process, as a Snakemake rule runs it; returns (seconds, peak RSS GB)."""
    sc = json.dumps(stage_config(cfg, case, stage))
    log = logdir / f"{stage}-{time.monotonic_ns()}.log"
    cmd = [
        sys.executable,
        "-m",
        "lfstudy.workflow",
        stage,
        "--config",
        sc,
        "--log",
        str(log),
        "--threads",
        str(threads),
        *map(str, args),
    ]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    _, status, usage = os.wait4(proc.pid, 0)
    dt = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"stage {stage} failed, see {log}:\n" + log.read_text()[-3000:])
    return dt, usage.ru_maxrss / 1024**2


def _case_cfg(base: dict, ppp: float, flow: str, method: str, extra: dict | None = None) -> tuple[dict, object]:
    """One case; its method (and any variant setting) is a swept value, so it gets its own results
    path while the stages upstream of it are shared with the other methods."""
    cfg = copy.deepcopy(base)
    cfg["sweep"] = {"ppp": [ppp], "flow": [flow], "reconstruct.method": [method]}
    cfg["sweep"].update({k: [v] for k, v in (extra or {}).items()})
    cfg = validate_config(cfg)
    return cfg, sweep_of(cfg).cases()[0]


def _stats(err_path: Path) -> dict[str, float]:
    err = io.open_zarr(err_path).load()
    return {v: float(err[v]) for v in err.data_vars if err[v].ndim == 0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ppp", type=float, nargs="+", default=[0.001, 0.005, 0.01])
    ap.add_argument("--flows", nargs="+", default=["uniform_z", "hill"])
    ap.add_argument("--methods", nargs="+", default=["threshold", "deconvolution", "mart"])
    ap.add_argument(
        "--sensor",
        type=int,
        nargs=2,
        metavar=("W", "H"),
        default=None,
        help="central region of the sensor in px (default: the full 4872 x 3248)",
    )
    ap.add_argument("--rays", type=int, default=25000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="working directory (kept: images are reused)")
    ap.add_argument("--thesis72", action="store_true", help="add sec. 7.2 as the thesis ran it")
    ap.add_argument("--iterations", type=int, default=None, help="MART iterations (default: the config's)")
    ap.add_argument("--relaxation", type=float, default=None, help="MART relaxation (default: the config's)")
    ap.add_argument(
        "--no-depth-calibration", action="store_true", help="the raw chain (depth_calibration.enabled: false)"
    )
    args = ap.parse_args()

    base = load_config(ROOT / "config" / "thesis.yaml")
    base["raytrace"]["rays_per_particle"] = args.rays
    if args.iterations is not None:
        base.setdefault("reconstruct", {}).setdefault("mart", {})["iterations"] = args.iterations
    if args.relaxation is not None:
        base.setdefault("reconstruct", {}).setdefault("mart", {})["relaxation"] = args.relaxation
    if args.no_depth_calibration:
        base.setdefault("depth_calibration", {})["enabled"] = False
    if args.sensor:
        base["camera"]["sensor"].update(n_pixels_x=args.sensor[0], n_pixels_y=args.sensor[1])
    out = args.out or Path(tempfile.mkdtemp(prefix="lfstudy-bench-rec-"))
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    sensor = base["camera"]["sensor"]
    print(
        f"Table 4.3 optics, sensor {sensor['n_pixels_x']} x {sensor['n_pixels_y']} px, {args.rays} rays/particle, "
        f"{args.threads} threads, in {out}"
    )

    jobs = [(p, f, m, None) for f in args.flows for p in args.ppp for m in args.methods]
    if args.thesis72:
        thesis = {"refocus.n_planes": 32, "refocus.depth_scale": 1.5, "grid.spacing": "planes"}
        jobs += [(0.001, "uniform_z_thesis", "threshold", thesis), (0.001, "uniform_z_thesis", "mart", None)]
    rows = []
    for ppp, flow, method, extra in jobs:
        cfg, case = _case_cfg(base, ppp, flow, method, extra)
        sw = sweep_of(cfg)
        loc = lambda name, case=case, sw=sw: out / sw.locate(case, name)  # noqa: E731
        t = lambda stage, a, case=case, cfg=cfg: _run(stage, cfg, case, a, logs, args.threads)  # noqa: E731
        # shared stages: made once per (flow, ppp [, refocus variant]) and reused by every method
        if not loc("particles_a.zarr").exists():
            t("particles", [loc("particles_a.zarr")])
        if not loc("particles_b.zarr").exists():
            t("displace", [loc("particles_a.zarr"), loc("particles_b.zarr")])
        for f in "ab":
            if not loc(f"raw_{f}.zarr").exists():
                dt, _ = t("simulate", [f, loc(f"particles_{f}.zarr"), loc(f"raw_{f}.zarr"), loc(f"raw_{f}.tif")])
                print(f"  simulate {flow} {ppp} {f}: {dt:.1f} s")
        if not loc("centers.zarr").exists():
            t("pinhole", [loc("pinhole.zarr"), loc("pinhole.tif")])
            t("calibrate", [loc("pinhole.zarr"), loc("centers.zarr")])
        for f in "ab":
            if not loc(f"lightfield_{f}.zarr").exists():
                t("register", [loc(f"raw_{f}.zarr"), loc("centers.zarr"), loc(f"lightfield_{f}.zarr")])
            if not loc(f"stack_{f}.zarr").exists():
                t("refocus", [loc(f"lightfield_{f}.zarr"), loc(f"stack_{f}.zarr")])
        rec = []
        for f in "ab":
            rec.append(
                t(
                    "reconstruct",
                    [loc(f"stack_{f}.zarr"), loc(f"lightfield_{f}.zarr"), loc("centers.zarr"), loc(f"volume_{f}.zarr")],
                )
            )
        depth = []
        if cfg["depth_calibration"]["enabled"]:
            if not loc("depth_calibration.zarr").exists():
                dt_cal, gb_cal = t("depthcal", [loc("centers.zarr"), loc("depth_calibration.zarr")])
                print(f"  depth calibration {ppp:g} ppp {method}: {dt_cal:.1f} s (peak {gb_cal:.2f} GB)")
            depth = [loc("depth_calibration.zarr")]
        dt_piv, _ = t("piv", [loc("volume_a.zarr"), loc("volume_b.zarr"), loc("piv.zarr"), *depth])
        t("errors", [loc("piv.zarr"), loc("volume_a.zarr"), loc("particles_a.zarr"), loc("errors.zarr")])
        s = _stats(loc("errors.zarr"))
        piv = io.open_zarr(loc("piv.zarr")).load()
        raw = piv["w_mm_uncorrected"] if "w_mm_uncorrected" in piv else piv["w_mm"]
        s["mean_z_raw_mm"] = float(raw.where(piv["valid"]).mean())
        vol = io.open_array(loc("volume_a.zarr"))
        per_it = vol.attrs.get("seconds_per_iteration")
        per_it = float(np.mean(per_it)) if isinstance(per_it, list) and per_it else per_it
        rows.append((ppp, flow, method, extra, rec, per_it, dt_piv, s, dict(vol.sizes)))
        _print(rows[-1])
    print("\nsummary: z mean error (% of truth; raw: before the depth calibration) | Q | valid % | rms total | s/frame")
    for ppp, flow, method, extra, rec, _, _, s, _ in rows:
        tag = method + (" (thesis 7.2 planes)" if extra else "")
        zerr = 100.0 * (s["mean_z_mm"] - s["true_z_mm"]) / s["true_z_mm"] if s.get("true_z_mm") else float("nan")
        zraw = 100.0 * (s["mean_z_raw_mm"] - s["true_z_mm"]) / s["true_z_mm"] if s.get("true_z_mm") else float("nan")
        print(
            f"  {flow:<17} {ppp:<6g} {tag:<28} z {zerr:+6.1f} % (raw {zraw:+6.1f} %)  Q {s['Q']:.3f}  "
            f"valid {s['valid_percent']:5.1f}  "
            f"rms {s['rms_total_mm']:.4f} mm {s['rms_total']:.3f} vox  {np.mean([r[0] for r in rec]):6.1f} s"
        )


def _print(row) -> None:
    ppp, flow, method, extra, rec, per_it, dt_piv, s, sizes = row
    tag = method + (" [thesis 7.2: 32 planes x 1.5 depth, voxel = plane]" if extra else "")
    print(f"\n{flow}, {ppp:g} ppp, {tag}: grid {sizes['z']} x {sizes['y']} x {sizes['x']} (z, y, x)")
    print(
        "  reconstruct: "
        + ", ".join(f"frame {f} {dt:.1f} s (peak {gb:.2f} GB)" for f, (dt, gb) in zip("ab", rec))
        + (f", {per_it:.1f} s per iteration" if isinstance(per_it, float) else "")
        + f"; piv {dt_piv:.1f} s"
    )
    true_z = s.get("true_z_mm", float("nan"))
    zerr = 100.0 * (s["mean_z_mm"] - true_z) / true_z if true_z else float("nan")
    zraw = 100.0 * (s["mean_z_raw_mm"] - true_z) / true_z if true_z else float("nan")
    print(
        f"  Q {s['Q']:.3f}, valid {s['valid_percent']:.1f} %, z: true {true_z:+.4f} mm, measured "
        f"{s['mean_z_mm']:+.4f} mm ({zerr:+.1f} %); before the depth calibration {s['mean_z_raw_mm']:+.4f} mm "
        f"({zraw:+.1f} %), depth gain {s['depth_gain']:.3f}"
    )
    for ax in "xyz":
        print(
            f"  {ax}: bias {s[f'bias_{ax}_mm']:+.4f} mm ({s[f'bias_{ax}']:+.3f} vox), rms {s[f'rms_{ax}_mm']:.4f} mm "
            f"({s[f'rms_{ax}']:.3f} vox), std {s[f'std_{ax}_mm']:.4f} mm ({s[f'std_{ax}']:.3f} vox)"
        )
    print(f"  total rms {s['rms_total_mm']:.4f} mm ({s['rms_total']:.3f} vox)")
    if flow == "uniform_z_thesis":
        # the thesis' voxel: one refocus plane of its 32-plane, 1.5x-deep stack at the focal plane
        plane = 0.7989718803016714
        print(
            f"  in the thesis' voxels (one plane, {plane:.4f} mm): mean {s['mean_z_mm'] / plane:+.2f}, "
            f"sigma {s['sd_z_mm'] / plane:.2f} (thesis, image-frame sign: mu {THESIS_72['mean']}, "
            f"sigma {THESIS_72['std']})"
        )


if __name__ == "__main__":
    main()
