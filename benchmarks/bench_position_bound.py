"""IPR's particles against the Cramér–Rao bound of their images, per depth band (issue 39).

Reproduces: docs/architecture.md § "Benchmarks" (the demo's IPR fits against the bound: at the bound near the
focal plane, about twice it away from focus) and lfstudy/reconstruct/ipr/bound.py.

Reads a finished study (the README's first command writes ``results/demo``): for every design, frame a's true
particles (``particles_a.zarr``) and IPR's fit of them (``volume_a.particles.zarr``). Computes each true
particle's bound (:func:`lfstudy.reconstruct.ipr.bound.position_bound`, crowded: the neighbours' photons are
noise) on the study's Monte-Carlo images (``raytrace.rays_per_particle`` rays a particle, the ideal photon
counter), pairs each true particle with the nearest fitted one (within one voxel, axes scaled by the grid's
voxel) and prints per depth band:

* ``n``: true particles on the sensor in the band; ``found``: share with a fitted particle within half a voxel
  (the study's ``found_percent``), ``xy``: within half a voxel laterally whatever its depth;
* x and z: the median |error| of the paired particles against the median bound. For a Gaussian error of the
  bound's size the median |error| is 0.674 × the bound, so ``eff`` = median |error| / (0.674 × median bound)
  is 1 for a fit that reaches the bound (the bounds vary within a band, so read it to a factor of ~1.3).

    python benchmarks/bench_position_bound.py [--results results/demo] [--config config/demo.yaml]

Findings (run 2026-12-03 on 2 cores, NUMBA_NUM_THREADS=1; the demo study of be43fdb, its own seed, frame a of each
design; median |error| / median bound in mm, x and z; ``eff`` as above):

======================  =========================  ==========================  ==========================
design                  z in [1, 2) (far)          z in [0.4, 1)               z in [-0.4, 0.4) (focus)
======================  =========================  ==========================  ==========================
M -1, p 0.0888          found 93 %; x 0.0009 /     86 %; x 0.0006 / 0.0004     40 %; x 0.0098 / 0.0124
                        0.0005, z 0.0101 / 0.0058  (2.5), z 0.0097 / 0.0042    (1.2), z 0.0910 / 0.1087
                        (eff 2.6, 2.6)             (3.5)                       (1.2)
M -1, p 0.1184          84 %; x eff 3.9, z 0.0192  64 %; x eff 7.0, z 0.0423   21 %; z 0.1108 / 0.2202
                        / 0.0074 (3.9)             / 0.0070 (8.9)              (0.7)
M -0.8, p 0.0888        85 %; x eff 3.4, z 0.0184  37 %; z 0.0863 / 0.1803     18 %; z 0.0955 / 0.4254
                        / 0.0090 (3.0)             (0.7)                       (0.3)
M -0.8, p 0.1184        46 %; x eff 9.5, z 0.0642  8 %; z 0.1059 / 0.3570      9 %; z 0.0833 / 0.4600
                        / 0.0119 (8.0)             (0.4)                       (0.3)
======================  =========================  ==========================  ==========================

(The negative bands match their positive ones within the spread.) Near the focal plane the images hold little
depth: the bound is 0.11-0.46 mm (0.4-1.8 z voxels) and the fit's median error is below it (eff < 1: a biased
fit, held near its start, beats the unbiased bound); the particles there are "not found" within half a voxel
because their depth is not in the images, on every design, and on the M -0.8 designs that band reaches |z| = 1 mm.
Away from focus the fit errs 2.6-3.9x the single-particle bound on the finer designs and 8-9.5x on the coarsest.
That is not convergence: on bench_ipr's demo scene (seed 37) 16 iterations instead of 10 move z's RMS 0.0313 ->
0.0302 mm and a shake step δ of 0.05 instead of 0.1 voxel 0.0313 -> 0.0316. The bound takes the neighbours'
positions as known; a joint fit of a crowded image (14-16 % ghosts, 17 % missed) pays for their errors too.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BANDS = ((-2.0, -1.0), (-1.0, -0.4), (-0.4, 0.4), (0.4, 1.0), (1.0, 2.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=ROOT / "results" / "demo", help="a finished study's folder")
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "demo.yaml")
    args = ap.parse_args()
    from scipy.spatial import cKDTree

    from lfstudy.io import open_zarr
    from lfstudy.reconstruct.ipr.bound import position_bound
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config, load_config
    from lfstudy.study.sweep import Sweep

    cfg = load_config(args.config)
    if cfg["raytrace"]["method"] != "montecarlo":
        raise SystemExit("bench_position_bound: raytrace.method must be montecarlo (its rays are the photons)")
    rays = float(cfg["raytrace"]["rays_per_particle"])
    sweep = Sweep(cfg)
    seen: set[str] = set()
    for case in sweep.cases():
        cc = case_config(cfg, case)
        if cc["reconstruct"]["method"] != "ipr" or cc["sensor"].get("shot_noise"):
            continue
        truth_path = args.results / sweep.locate(case, "particles_a.zarr")
        fit_path = args.results / sweep.locate(case, "volume_a.particles.zarr")
        if str(truth_path) in seen:
            continue
        seen.add(str(truth_path))
        if not fit_path.exists():
            print(f"{case.case_id}: no {fit_path} (run the study first)")
            continue
        t0 = time.perf_counter()
        cam = cl.case_camera(cc)
        grid = cl.case_grid(cc, cam)
        vox = np.array([float(np.median(np.diff(c))) for c in (grid.x, grid.y, grid.z)])
        truth = cl.case_illuminated(cc, open_zarr(truth_path).load())
        fit = open_zarr(fit_path).load()
        t = np.column_stack([truth[v].values for v in "xyz"])
        f = np.column_stack([fit[v].values for v in "xyz"])
        half = np.array([cam.n_pixels_x, cam.n_pixels_y]) * cam.pixel_pitch / abs(cam.magnification) / 2
        on = np.all(np.abs(t[:, :2]) < half, axis=1)
        t, inten = t[on], truth["intensity"].values[on]
        bound = position_bound(cam, t[:, 0], t[:, 1], t[:, 2], inten, rays)
        dist, j = cKDTree(f / vox).query(t / vox)
        dxy, _ = cKDTree(f[:, :2] / vox[:2]).query(t[:, :2] / vox[:2])
        err = f[j] - t
        print(
            f"{truth_path.parent.relative_to(args.results)}: {len(t)} true particles on the sensor, {len(f)} fitted, "
            f"voxel {np.round(vox, 4)} mm; found {np.mean(dist < 0.5) * 100:.1f} % ({time.perf_counter() - t0:.0f} s)"
        )
        for lo, hi in BANDS:
            s = (t[:, 2] >= lo) & (t[:, 2] < hi)
            m = s & (dist < 1.0) & np.all(np.isfinite(bound), axis=1)
            if not m.any():
                continue
            parts = []
            for k, ax in ((0, "x"), (2, "z")):
                e, b = np.median(np.abs(err[m, k])), np.median(bound[m, k])
                parts.append(f"{ax} |err| {e:.4f} bound {b:.4f} eff {e / (0.674 * b):.1f}")
            print(
                f"  z [{lo:+.1f}, {hi:+.1f}): n {int(s.sum())}, found {np.mean(dist[s] < 0.5) * 100:.0f} %, "
                f"xy {np.mean(dxy[s] < 0.5) * 100:.0f} %; " + "; ".join(parts),
                flush=True,
            )


if __name__ == "__main__":
    main()
