"""End-to-end benchmark: the thesis' uniform-x case at full size (sec. 7.1).

Reproduces: docs/architecture.md § "Benchmarks" (the sec. 7.1 case end to end, each stage timed);
lfstudy/reconstruct/threshold.py (focal_stack_as_is: PIV of the plain stack spreads less in y and z).

Table 4.3 camera (4872 x 3248 px, 289 x 193 lenslets), 0.001 ppp (15,824
particles; ``--ppp 0.01``: 158,243), the config's rendering method (exact;
``--method montecarlo`` traces ``--rays`` per particle, thesis 25,000), 7 mm
depth span, 4.5 lenslet-pixel (0.5625 mm) shift in x. Runs every stage of the
Snakemake rule chain in one process (the same functions the rules call, the
design's depth calibration included), times each, and prints the measured
displacement statistics beside the thesis' (mean -4.45 px, sigma 0.07 px; the
thesis' sign is the image frame, ours the object frame).

Target: at most 5 minutes on 2 cores at 0.001 ppp.

    python benchmarks/bench_study_thesis.py [--out DIR] [--ppp P] [--method M] [--rays N] [--seed S]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from lfstudy import io, workflow
from lfstudy.study.config import expand_cases, load_config, stage_config

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="working directory (default: a temp dir)")
    ap.add_argument("--rays", type=int, default=25000, help="rays per particle (thesis: 25,000)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ppp", type=float, default=0.001, choices=(0.001, 0.005, 0.01), help="seeding (sec. 7.3)")
    ap.add_argument(
        "--method", choices=("exact", "montecarlo"), default=None, help="raytrace.method (default: the config's)"
    )
    ap.add_argument("--seed", type=int, default=None, help="study seed (default: the config's, 2011)")
    ap.add_argument(
        "--no-depth-calibration", action="store_true", help="skip the design's depth calibration (w left as read)"
    )
    ap.add_argument("--skip-compare", action="store_true", help="skip the other reconstructions of the same stacks")
    args = ap.parse_args()

    cfg = load_config(ROOT / "config" / "thesis.yaml")
    cfg["raytrace"]["rays_per_particle"] = args.rays
    if args.method is not None:
        cfg["raytrace"]["method"] = args.method
    if args.seed is not None:
        cfg["seed"] = args.seed
    if args.no_depth_calibration:
        cfg["depth_calibration"]["enabled"] = False
    case = next(c for c in expand_cases(cfg) if c.flow == "uniform_x" and c.ppp == args.ppp)
    cid = case.case_id
    out = args.out or Path(tempfile.mkdtemp(prefix="lfstudy-bench-"))
    d = out / cid
    workflow.set_threads(args.threads)

    def sc(stage: str) -> dict:
        """What the Snakefile passes the stage: the config sections it reads."""
        return stage_config(cfg, cid, stage)

    cal = out / "calib" / sc("pinhole")["calib_id"]
    depth = cal / "depth_calibration.zarr" if sc("depthcal")["depth_calibration"]["enabled"] else None

    steps = [
        ("camera", lambda: workflow.run_optics(sc("camera"), d / "camera.json", d / "focal_planes.zarr")),
        ("particles", lambda: workflow.run_particles(sc("particles"), d / "particles_a.zarr")),
        ("displace", lambda: workflow.run_displace(sc("displace"), d / "particles_a.zarr", d / "particles_b.zarr")),
        (
            "simulate a",
            lambda: workflow.run_simulate(
                sc("simulate"), "a", d / "particles_a.zarr", d / "raw_a.zarr", d / "raw_a.tif"
            ),
        ),
        (
            "simulate b",
            lambda: workflow.run_simulate(
                sc("simulate"), "b", d / "particles_b.zarr", d / "raw_b.zarr", d / "raw_b.tif"
            ),
        ),
        ("pinhole", lambda: workflow.run_pinhole(sc("pinhole"), cal / "pinhole.zarr", cal / "pinhole.tif")),
        ("calibrate", lambda: workflow.run_calibrate(sc("calibrate"), cal / "pinhole.zarr", cal / "centers.zarr")),
        (
            "register a",
            lambda: workflow.run_register(
                sc("register"), d / "raw_a.zarr", cal / "centers.zarr", d / "lightfield_a.zarr"
            ),
        ),
        (
            "register b",
            lambda: workflow.run_register(
                sc("register"), d / "raw_b.zarr", cal / "centers.zarr", d / "lightfield_b.zarr"
            ),
        ),
        ("refocus a", lambda: workflow.run_refocus(sc("refocus"), d / "lightfield_a.zarr", d / "stack_a.zarr")),
        ("refocus b", lambda: workflow.run_refocus(sc("refocus"), d / "lightfield_b.zarr", d / "stack_b.zarr")),
        *(
            (
                f"reconstruct {f}",
                lambda f=f: workflow.run_reconstruct(
                    sc("reconstruct"),
                    d / f"stack_{f}.zarr",
                    d / f"lightfield_{f}.zarr",
                    cal / "centers.zarr",
                    d / f"volume_{f}.zarr",
                ),
            )
            for f in "ab"
        ),
        *(
            [("depthcal", lambda: workflow.run_depth_calibration(sc("depthcal"), cal / "centers.zarr", depth))]
            if depth
            else []
        ),
        (
            "piv",
            lambda: workflow.run_piv(sc("piv"), d / "volume_a.zarr", d / "volume_b.zarr", d / "piv.zarr", depth),
        ),
        (
            "errors",
            lambda: workflow.run_errors(
                sc("errors"), d / "piv.zarr", d / "volume_a.zarr", d / "particles_a.zarr", d / "errors.zarr"
            ),
        ),
    ]
    method = cfg["raytrace"]["method"]  # the validated config holds the schema's default
    rays = f"{args.rays} rays/particle" if method == "montecarlo" else "no rays"
    print(f"case {cid}  ({method}, {rays}, {args.threads} threads)  in {out}")
    total = 0.0
    for name, fn in steps:
        t0 = time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        total += dt
        print(f"  {name:<14} {dt:8.2f} s")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    print(f"total {total:.1f} s (target <= 300 s), peak RSS {peak:.2f} GB (numba JIT compile included)")

    piv = io.open_zarr(d / "piv.zarr").load()
    err = io.open_zarr(d / "errors.zarr").load()
    ok = piv["valid"].values
    for comp, ax in (("u", "x"), ("v", "y"), ("w", "z")):
        vals = piv[comp].values[ok]
        print(f"  {ax}: mean {np.mean(vals):+.3f} vox, sigma {np.std(vals):.3f} vox over {ok.sum()} valid vectors")
    print(
        "thesis sec. 7.1: x mean -4.45 px (bias 0.05) sigma 0.07; y sigma 0.03; z sigma 0.05 "
        "(image-frame sign; ours is object frame, so +4.5 is exact)"
    )
    for v in sorted(err.data_vars):
        if err[v].ndim == 0:
            print(f"  {v:<28} {float(err[v]):.4f} {err[v].attrs.get('units', '')}")

    if args.skip_compare:
        return
    # Same focal stacks, other reconstructions: how much of the spread is the threshold's.
    from lfstudy.piv import widim
    from lfstudy.reconstruct import reconstruct

    p = cfg["piv"]
    stacks = [io.open_array(d / f"stack_{f}.zarr").load() for f in "ab"]
    print("same stacks, other reconstructions (x / y / z sigma, vox):")
    for label, kw in (
        ("threshold k=3 (thesis)", {"method": "threshold", "k": 3.0}),
        ("threshold k=2", {"method": "threshold", "k": 2.0}),
        ("none (the focal stack)", {"method": "none"}),
    ):
        vols = [reconstruct(s, **kw).load() for s in stacks]
        r = widim(*vols, window=tuple(p["window"]), spacing=tuple(p["spacing"]), levels=p["levels"], mode=p["mode"])
        ok = r["valid"].values
        sig = " / ".join(f"{np.std(r[c].values[ok]):.3f}" for c in ("u", "v", "w"))
        print(f"  {label:<24} x mean {np.mean(r['u'].values[ok]):+.3f}, sigma {sig} ({ok.sum()} valid)")


if __name__ == "__main__":
    main()
