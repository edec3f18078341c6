"""The error budget of study configs side by side: each case beside its oracle, with the particle scores.

Reproduces: docs/config.md § "Tracking the fitted particles (`piv.particles`)" (the table of IPR's lists
correlated with piv.particles none and ptv, demo_focus, seed 21) and § "Correlating the paired particles only
(`piv.particles: paired`)"; config/demo_focus.yaml (the budgets in its header).

Runs every case of each ``--config`` through the workflow's stage functions (the runner of
``bench_uncertainty.py``: no Snakemake needed, each shared output made once, ``--jobs`` tasks side
by side), then prints per case: total RMS error, the oracle's (PIV on the true volumes) and the
reconstruction's share, the crosstalk (spurious w per unit lateral shift) of the PIV and of the
particles found in both frames, particles found (all, and within the depth of field about the
focal plane, eq. 4.18) and ghosts (a method that fits particles: ipr),
valid vectors, the seeded slab's depth, and how well the per-vector uncertainty measures the error
(``unc_coverage_*``: fraction within one sigma, 0.68 if right; ``unc_ratio_*``: RMS error over RMS
sigma). Written for issue 27's question whether the lateral->axial crosstalk and IPR's misses come
from the focal plane lying inside the volume, and to compare piv.particles none and ptv
(config/demo_ptv.yaml):

    python benchmarks/bench_budget.py --configs config/demo_ipr.yaml config/demo_focus.yaml \\
        --flows diag --jobs 16 --threads 1 [--out DIR]

Targets (issue 27, coarse designs, lateral shifts, depth calibration off): |crosstalk| <= 0.05,
total RMS <= max(1.5 x oracle, oracle + 0.01 mm), >= 90 % valid vectors; printed as ok/miss.
Printed besides: Q (the reconstruction quality factor of errors.zarr) and, on uniform flows with a z
component, the mean w's error in % of the true w (``dw%``). ``--set PATH=VALUE`` (YAML values),
``--sweep KEY=[...]`` and ``--seed`` change the configs as ``bench_uncertainty.py`` does.

0.01 ppp (issue 27: "at least MART's Q and valid fraction, or the figure and the reason why not"),
thesis camera (Table 4.3) cropped to 800 x 600 px (48 x 36 lenslets, 4,800 particles a frame, 105
vectors), seed 51 (tuned on by nobody), depth calibration off, Monte-Carlo images (4,000 rays and
25,000 photons per particle), the code of 79bd03d (IPR's batch 2048), 1 thread per task, load 6-7 on
2 cores (IPR 540-1070 s a frame, MART ~7 s)::

    python benchmarks/bench_budget.py --configs config/thesis.yaml --flows uniform_x uniform_z \
        --seed 51 --jobs 1 --threads 1 --sweep "ppp=[0.01]" "reconstruct.method=[mart, ipr]" \
        --set camera.sensor.n_pixels_x=800 camera.sensor.n_pixels_y=600 \
        depth_calibration.enabled=false raytrace.method=montecarlo \
        raytrace.rays_per_particle=4000 sensor.photons_per_particle=25000

    flow       method  Q      valid %        w                rms mm (oracle)  found / ghosts %
    uniform_x  mart    0.842   97.1 (102)    ct -0.015        0.0310 (0.0046)
    uniform_x  ipr     0.951   96.2 (101)    ct -0.042        0.0470 (0.0046)  59.7 / 34.9
    uniform_z  mart    0.842  100.0 (105)    -10.7 % of w     0.0448 (0.0021)
    uniform_z  ipr     0.947   96.2 (101)    -13.6 % of w     0.0600 (0.0021)  56.3 / 36.8

IPR's Q is MART's + 0.11, its valid fraction is not (1 and 4 vectors fewer of 105) and its RMS error
is 1.3-1.5 x MART's, the z component nearly all of it (0.046 of 0.047 mm on uniform_x). Why (frame a
of uniform_x, 4,800 true particles): at 0.01 ppp on this one-voxel-per-lenslet grid (0.125 x 0.125 x
0.5 mm) 56 % of the particles have another within one voxel (per axis scaled), 93 % within 1.5.
IPR fitted 3,880 particles: 58.5 % of the true ones found within half a voxel (33.9 % of those at
|z| < 0.75 mm, 58.3 % at 0.75-2 mm, 70.3 % beyond), 35.5 % of the fitted are ghosts, and 97 % of
these lie within 1.5 voxels of a true particle (median 0.85 voxel, 41 % at |z| < 0.75 mm against
20 % of the particles): fits of real particles, or of pairs, misplaced mostly in depth, with the
found ones' intensities (median 2.2e4 against 2.9e4), so the ghost floor cannot tell them apart.
The particles found in both frames move right (their w per unit lateral shift -0.004), but the
misplaced ones differ between the frames and PIV on the rendered volume reads w = -0.024 mm for the
0.5625 mm lateral shift. No cheap fix: it is the density on the lenslet grid (pairs behind one
lenslet, the near-focus limit of 0.005 ppp, now everywhere); the second seed was not run (the four
IPR frames of one seed took 50 min of the 90).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def _row(name: str, e, true_w: float = math.nan) -> str:
    def g(k: str) -> float:
        return float(e[k]) if k in e else math.nan

    rms, orc, ct, valid = g("rms_total_mm"), g("oracle_rms_total_mm"), g("crosstalk_z"), g("valid_percent")
    w_pct = 100.0 * (g("mean_z_mm") - true_w) / abs(true_w) if true_w else math.nan
    ok = [
        abs(ct) <= 0.05 if np.isfinite(ct) else None,
        rms <= max(1.5 * orc, orc + 0.01),
        valid >= 90.0,
    ]
    verdict = "/".join("-" if o is None else ("ok" if o else "miss") for o in ok)
    return (
        f"{name:<44} {rms:7.4f} {orc:7.4f} {g('recon_added_rms_total_mm'):7.4f} {ct:+7.3f} "
        f"{g('particle_crosstalk_z'):+7.3f} {g('found_percent'):6.1f} {g('found_in_focus_percent'):6.1f} "
        f"{g('ghost_percent'):6.1f} {valid:6.1f} {g('Q'):6.3f} {w_pct:+6.1f}  {verdict:<12}"
        + "/".join(f"{g(f'unc_coverage_{a}'):.2f}" for a in "xyz")
        + "  "
        + "/".join(f"{g(f'unc_ratio_{a}'):.2f}" for a in "xyz")
    )


def main() -> None:
    import yaml
    from bench_uncertainty import _run, _tasks, _written, read_config

    from lfstudy import io
    from lfstudy.study.config import validate_config
    from lfstudy.study.sweep import Sweep

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=Path, nargs="+", required=True)
    ap.add_argument("--flows", nargs="*", default=None, help="keep these flows of each sweep (default: all)")
    ap.add_argument("--jobs", type=int, default=1, help="tasks run side by side")
    ap.add_argument("--threads", type=int, default=1, help="threads per task")
    ap.add_argument("--out", type=Path, default=None, help="working directory (default: a temp dir)")
    ap.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE", help="config overrides (YAML values)")
    ap.add_argument("--sweep", nargs="*", default=[], metavar="KEY=VALUES", help="sweep overrides (YAML lists)")
    ap.add_argument("--seed", type=int, default=None, help="the configs' seed (default: theirs)")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="lfstudy-bench-budget-"))
    runs = []
    for path in args.configs:
        raw = read_config(path, args.set)
        for item in args.sweep:
            key, _, vals = item.partition("=")
            raw.setdefault("sweep", {})[key] = yaml.safe_load(vals)
        if args.seed is not None:
            raw["seed"] = args.seed
        if args.flows:
            sweep = raw.setdefault("sweep", {})
            sweep["flow"] = [f for f in sweep.get("flow", []) if f in args.flows] or list(args.flows)
        runs.append((path, validate_config(raw, base=path.resolve().parent), out / path.stem))
    waves = [[] for _ in range(8)]
    for _, cfg, where in runs:
        for i, wave in enumerate(_tasks(cfg, where)):
            waves[i] += wave
    print(f"{sum(map(len, waves))} tasks, {args.jobs} jobs x {args.threads} threads, in {out}", flush=True)
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for wave in waves:
            todo = [(label, fn, a) for label, fn, a in wave if not _written(label, fn, a)]
            for f in [pool.submit(_run, label, fn, a, args.threads) for label, fn, a in todo]:
                label, secs = f.result()
                if secs > 20:
                    print(f"  {secs:8.1f} s  {label}", flush=True)
    print(f"all stages {time.perf_counter() - t0:.0f} s\n")
    head = f"{'case (config: slab z)':<46}rms_mm  oracle   added     ct   ct_part found% infoc% ghost%  valid%"
    head += "      Q   dw%"
    print(head + "  ct/rms/valid  unc cover x/y/z  unc ratio x/y/z")
    for path, cfg, where in runs:
        sw = Sweep(cfg)
        p = cfg["particles"]
        zc, half = float(p.get("z_center", 0.0)), float(p["z_span"]) / 2
        print(f"{path.stem}: slab {zc - half:+.2f} .. {zc + half:+.2f} mm")
        keys = [s.key for s in sw.swept]  # the settings with more than one value
        for c in sw.cases():
            e = io.open_zarr(where / sw.locate(c, "errors.zarr")).load()
            name = " ".join(f"{k.split('.')[-1][:5]}={c[k]}" for k in keys)
            flow = cfg["flows"].get(c.get("flow"), {})
            true_w = float(flow["displacement"][2]) if flow.get("kind") == "uniform" else math.nan
            print("  " + _row(name, e, true_w))


if __name__ == "__main__":
    main()
