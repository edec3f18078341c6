"""The paired PIV's track weights (``piv.paired_weights``) against a finished study (issue 39: the demo's RMS targets).

Reproduces: docs/config.md § "Weighing the tracks by depth (`piv.paired_weights`)" and § "The paired vectors' σ from
the tracks themselves (`piv.paired_uncertainty`)"; lfstudy/schema.yaml (``piv.paired_weights``,
``piv.paired_uncertainty``); lfstudy/piv/ptv.py (:func:`~lfstudy.piv.ptv.depth_weights`,
:func:`~lfstudy.piv.ptv.track_sigma`).

Reads a finished study (the README's first command writes ``results/demo``) and, for every case whose
reconstruction fitted particles (``volume_a.particles.zarr``), reruns the paired PIV
(:func:`lfstudy.study.case.case_paired_piv`, its predictor WIDIM on the stored volumes) from the stored particle
lists once per ``--weights`` value, and scores it as the study does (:func:`lfstudy.study.metrics.case_errors`).
Printed per case: the oracle's total RMS error and the issue's target, max(1.5 × oracle, oracle + 0.01 mm); then per
setting the total RMS error [mm] (against the point truth, the study's ``rms_total_mm``), w's RMS error, the
crosstalk of a lateral shift (``crosstalk_z``), the valid vectors, σ's coverage and RMS ratio per component (against
the window-averaged truth, the study's ``unc_coverage_<ax>`` / ``unc_ratio_<ax>``), the ``unresolved`` share, and for
``depth`` the tracks' robust displacement scatter [um] per band of |z| (the bands' median |z| [mm]).

    python benchmarks/bench_paired_weights.py [--results results/demo] [--config config/demo.yaml]
        [--weights none depth] [--set piv.paired_max_sigma_z=1000 ...]

Findings (run 2026-12-03 on 2 cores; IPR particle lists of the demo studies of 7f2235b at seed 7, where the weights
were designed, and of 2b29782 at seed 8, held out; the table is in docs/config.md § "Weighing the tracks by depth"):
``none`` reproduces the seed-7 study's study.csv (total RMS 0.0160 / 0.0284 / 0.0231 / 0.0453 / 0.0350 / 0.0489 /
0.0683 / 0.0768 mm). ``depth`` takes the uniform shift's total RMS down 4-25 % on every design and seed (finest design
0.0160 -> 0.0126 and 0.0152 -> 0.0121 mm against targets of 0.0116 and 0.0118), Hill's vortex -12 to +5 % (worse on the
finest design, +2 and +5 %); median of the 16 cases -9.1 %. The band nearest focus scatters 2.5-6x the others.

``--weights depth --set piv.paired_uncertainty=correlation`` against the default (``tracks``), run 2026-12-04 on the
same lists of seeds 7 and 8 (``--config`` a copy of config/demo.yaml with ``sweep.seed: [7, 8]``, the lists of a
``bench_uncertainty.py`` run) and on held-out coarse designs (M -0.85 and -0.9, pitch 0.104 and 0.112 mm, lateral y,
diagonal and axial shifts, seed 23): case-components in issue 38's band (coverage 0.55-0.80, ratio 0.7-1.4)
34 -> 41 of 48 (z 6 -> 11 of 16) and 24 -> 32 of 36 (z 0 -> 8 of 12); total RMS unchanged.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _line(err, piv) -> str:
    """One setting's scores, as the study's study.csv has them."""
    out = [
        f"total {float(err.rms_total_mm):.4f}",
        f"w {float(err.rms_z_mm):.4f}",
        f"crosstalk {float(err.crosstalk_z):+.3f}" if "crosstalk_z" in err and np.isfinite(err.crosstalk_z) else "",
        f"valid {float(err.valid_percent):5.1f} %",
        "sigma cov/ratio "
        + " ".join(f"{ax} {float(err[f'unc_coverage_{ax}']):.2f}/{float(err[f'unc_ratio_{ax}']):.2f}" for ax in "xyz")
        if "unc_ratio_z" in err
        else "",
        f"unresolved {float(err.unresolved_percent):.1f} %" if "unresolved_percent" in err else "",
    ]
    depth, sd = piv.attrs.get("paired_weight_depth_mm", []), piv.attrs.get("paired_weight_sd_mm", [])
    if len(depth):
        out.append("bands " + " ".join(f"{d:.2f}:{1e3 * s:.0f}" for d, s in zip(depth, sd)))
    return " | ".join(o for o in out if o)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=ROOT / "results" / "demo", help="the study's results directory")
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "demo.yaml", help="the study's config")
    ap.add_argument("--weights", nargs="+", default=["none", "depth"], help="piv.paired_weights values to compare")
    ap.add_argument("--set", nargs="*", default=[], metavar="piv.KEY=VALUE", help="other piv settings for every run")
    args = ap.parse_args(argv)

    from lfstudy import io
    from lfstudy.reconstruct.registry import gives_particles
    from lfstudy.simulate.flows import flow_from_config
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config, load_config
    from lfstudy.study.metrics import case_errors
    from lfstudy.study.sweep import Sweep

    extra = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if not key.startswith("piv."):
            raise SystemExit(f"--set {item!r}: only piv.<key>=<value>")
        extra[key[4:]] = yaml.safe_load(value)
    cfg = load_config(args.config)
    sweep = Sweep(cfg)
    for case in sweep.cases():
        cc = case_config(cfg, case)
        if not gives_particles(cc["reconstruct"]["method"]):
            continue
        names = ("volume_a.zarr", "volume_b.zarr", "volume_a.particles.zarr", "volume_b.particles.zarr", "errors.zarr")
        paths = {n: args.results / sweep.locate(case, n) for n in names}
        if not all(p.exists() for p in paths.values()):
            print(f"{case.case_id}: not finished (run the study first)")
            continue
        fit_a, fit_b = (io.open_zarr(paths[f"volume_{f}.particles.zarr"]).load() for f in "ab")
        va, vb = (io.open_array(paths[f"volume_{f}.zarr"]).load() for f in "ab")
        oracle = float(io.open_zarr(paths["errors.zarr"])["oracle_rms_total_mm"])
        spec = cc["flow"]
        flow = flow_from_config(spec)
        voxel = cl.volume_voxel(va)
        pred = cl.case_piv(cc, va, vb)
        print(f"{case.case_id}: oracle {oracle:.4f} mm, target {max(1.5 * oracle, oracle + 0.01):.4f} mm")
        for weights in args.weights:
            c2 = {**cc, "piv": {**cc["piv"], **extra, "paired_weights": weights}}
            piv = cl.case_paired_piv(c2, pred, va, vb, fit_a, fit_b, voxel=voxel)
            err = case_errors(piv, flow, dt=spec.get("dt", 1.0), n_steps=spec.get("n_steps", 100))
            print(f"  {weights:>5}  {_line(err, piv)}", flush=True)


if __name__ == "__main__":
    main()
