"""σ of the particles in the PIV's particle volumes (``piv.particle_sigma``) against a finished study (issues 38, 39).

Reproduces: docs/config.md § "The particles the PIV correlates (`piv.particle_sigma`)"; lfstudy/schema.yaml
(``piv.particle_sigma``); lfstudy/study/case.py (the comment of ``PARTICLE_SIGMA``).

Reads a finished study (the README's first command writes ``results/demo``) and, for every case whose
reconstruction fitted particles (``volume_a.particles.zarr``), reruns from the stored particle lists:

* the oracle (:func:`lfstudy.study.case.oracle_piv`: the case's PIV on the true particles' volumes), and
* the paired PIV (:func:`lfstudy.study.case.case_paired_piv`, its predictor WIDIM on the stored volumes),

once per σ of ``--sigma`` (z voxels; ``truth``: Q's truth σ, the camera's depth of focus, which both used
before 2026-12-03; the lateral σ is ``--sigma`` voxels too, except for ``truth``). It prints per component the RMS
error against the truth averaged over the final window (the budget's reference for σ), the gain (the
least-squares slope of the measured component on that truth: 1 is unbiased; 0 where the truth is 0), and for
the paired PIV the σ coverage and RMS ratio and the valid vectors.

    python benchmarks/bench_particle_sigma.py [--results results/demo] [--config config/demo.yaml]
        [--sigma truth 0.7 0.5]

Findings (run 2026-12-03 on 2 cores; the demo studies of 920773b at seed 7 and of 2b29782 at seed 8, their IPR
particle lists, the current paired PIV; w in mm against the window-averaged truth):

* The oracle on Hill's vortex: with the truth σ (1.4-3.7 z voxels in a 4-voxel-deep final window) w reads at
  0.30-0.74 of its size, RMS 0.027-0.068 mm; at 0.5 voxel gain 0.97-1.00, RMS 0.008-0.011 mm (the top-hat
  filter of the window is 0.011-0.016 mm in total). On the uniform shift its total RMS goes 0.0016-0.0081 ->
  0.0016-0.0047 mm.
* The paired IPR PIV: with the truth σ its w gain on Hill is 0.19-0.78 and σ of w covers 0.01-0.09 of the
  errors (RMS ratio 3.3-12.5); at 0.5 voxel gain 0.55-0.96, coverage 0.39-0.65, ratio 1.1-1.6, w RMS 0.027-0.077
  -> 0.021-0.071 mm. Its w error on the uniform shift (true w 0) rises from 0.005-0.018 to 0.015-0.063 mm
  (total 0.0071-0.0326 -> 0.0152-0.0683): the long images had pulled every w towards 0, which a flow with w = 0
  rewards; the small ones show the fitted particles' depth scatter. Valid vectors 87-100 % (was 98-100), 63-75 %
  on the coarsest design's uniform shift (M -0.8, pitch 0.1184), whose seeding the report names as its limit.
  The truth-σ rows reproduce the studies' own study.csv (uniform_x 0.0084 / 0.0100 / 0.0101 / 0.0314 mm at seed 7).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _scores(res, err, truth_win, sigma: bool) -> str:
    """One line: per component RMS against the window-averaged truth, gain, and (``sigma``) σ's coverage/ratio."""
    ok = res["valid"].values.astype(bool)
    parts = [f"valid {100 * ok.mean():5.1f} %"]
    for c in "uvw":
        meas, tw = res[f"{c}_mm"].values, truth_win[c]
        m = ok & np.isfinite(meas) & np.isfinite(tw)
        e = meas[m] - tw[m]
        den = float(np.sum(tw[m] ** 2))
        gain = float(np.sum(meas[m] * tw[m]) / den) if den > 1e-12 else float("nan")
        line = f"{c} rms {np.sqrt(np.mean(e**2)):.4f}" + ("" if np.isnan(gain) else f" gain {gain:.2f}")
        if sigma and f"unc_{c}_mm" in res:
            s = res[f"unc_{c}_mm"].values[m]
            f = np.isfinite(s)
            ratio = np.sqrt(np.mean(e[f] ** 2) / np.mean(s[f] ** 2))
            line += f" cov {np.mean(np.abs(e[f]) <= s[f]):.2f} ratio {ratio:.2f}"
        parts.append(line)
    return " | ".join(parts)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=ROOT / "results" / "demo", help="the study's results directory")
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "demo.yaml", help="the study's config")
    ap.add_argument("--sigma", nargs="+", default=["truth", "0.7", "0.5"], help="σ [voxels per axis] or truth")
    args = ap.parse_args(argv)

    from lfstudy import io
    from lfstudy.reconstruct.registry import gives_particles
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config, load_config
    from lfstudy.study.sweep import Sweep

    cfg = load_config(args.config)
    sweep = Sweep(cfg)
    truth_sigma, default_sigma = cl.truth_sigma, cl.particle_sigma
    for case in sweep.cases():
        cc = case_config(cfg, case)
        if not gives_particles(cc["reconstruct"]["method"]):
            continue
        paths = {n: args.results / sweep.locate(case, n) for n in (
            "particles_a.zarr", "particles_b.zarr", "volume_a.zarr", "volume_b.zarr",
            "volume_a.particles.zarr", "volume_b.particles.zarr", "errors.zarr",
        )}  # fmt: skip
        if not all(p.exists() for p in paths.values()):
            print(f"{case.case_id}: not finished (run the study first)")
            continue
        true_a, true_b = (io.open_zarr(paths[f"particles_{f}.zarr"]).load() for f in "ab")
        fit_a, fit_b = (io.open_zarr(paths[f"volume_{f}.particles.zarr"]).load() for f in "ab")
        va, vb = (io.open_array(paths[f"volume_{f}.zarr"]).load() for f in "ab")
        err = io.open_zarr(paths["errors.zarr"]).load()
        truth_win = {c: (err[f"{c}_true_mm"] + err[f"{c}_filter_mm"]).values for c in "uvw"}
        voxel = cl.volume_voxel(va)
        pred = cl.case_piv(cc, va, vb)
        print(f"{case.case_id}: truth σ (z, y, x) {np.round(truth_sigma(cl.case_camera(cc)), 4).tolist()} mm, "
              f"voxel (x, y, z) {np.round(voxel, 4).tolist()} mm")  # fmt: skip
        for label in args.sigma:
            c2 = {**cc, "piv": dict(cc["piv"])}
            if label == "truth":  # Q's σ, as both were rendered before: anisotropic, so patched in
                sig = truth_sigma(cl.case_camera(cc))
                cl.particle_sigma = lambda _c, _v, sig=sig: tuple(sig)
            else:
                c2["piv"]["particle_sigma"] = float(label)
            try:
                oracle = cl.oracle_piv(c2, true_a, true_b)
                paired = cl.case_paired_piv(c2, pred, va, vb, fit_a, fit_b, voxel=voxel)
            finally:
                cl.particle_sigma = default_sigma
            print(f"  σ {label:>5}  oracle  {_scores(oracle, err, truth_win, False)}")
            print(f"  σ {label:>5}  paired  {_scores(paired, err, truth_win, True)}")


if __name__ == "__main__":
    main()
