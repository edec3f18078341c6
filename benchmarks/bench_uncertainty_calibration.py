"""σ calibrated by a study (issue 38, Beyond): fit on some cases, check on others.

Reproduces: docs/config.md § "σ calibrated by a study (`uncertainty.calibration`)" (the held-out
bands, raw against calibrated).

Reads the cases a study run wrote (``benchmarks/bench_uncertainty.py --out DIR`` or a Snakemake
results directory: each case's ``errors.zarr``), builds the study table from their scalars
(:func:`lfstudy.study.table.combine_cases`, as the workflow's ``study`` rule does), fits the factor per
component on the cases of the fit seeds (:func:`lfstudy.process.uncertainty_calibration.fit_calibration`,
from the table's ``unc_ratio_<ax>`` alone, as ``lfstudy process`` does) and prints, per held-out case and
component, coverage (fraction of ``|error| <= σ``) and RMS(error)/RMS(σ) of the raw and of the calibrated
σ, from the case's per-vector errors, the z rows on their own. Targets (issue 38): coverage 0.55-0.80,
ratio 0.7-1.4. With ``--bins`` it also prints the ratio of the held-out cases in terciles of the
correlation peak height (does the factor depend on it?).

    python benchmarks/bench_uncertainty.py --config CFG --sweep "seed=[7,8]" --out DIR   # the cases
    python benchmarks/bench_uncertainty_calibration.py --config CFG --out DIR --fit-seeds 7 [--flows F] [--bins]
        [--set ...] [--sweep KEY=[V1,V2] ...] [--where KEY=VALUE ...] [--truth window|point|oracle]

``--set`` and ``--sweep`` repeat the run's (bench_uncertainty.py's meaning); ``--where`` keeps the cases of one
design of a run that swept several (``--where reconstruct.method=mart ppp=0.005``). ``--truth`` is the truth the
printed coverage and ratio are against: ``window`` (default) the truth averaged over each final window, as the
study's ``unc_ratio_<ax>`` the factor is fitted on (issue 38), ``point`` the truth at the window centre, ``oracle``
the case's oracle (the same WIDIM on the true particles: what the windows measure of the flow, their filtering and
the deformation's predictor filter included; its own random error too), where the oracle has a valid vector.

Measured (2 loaded cores; CFG = benchmarks/uncertainty_calibration_tiny.yaml: tiny camera, MART, 0.004 ppp,
8 x 16 x 16 windows at 2 x 4 x 4 spacing, 75 vectors a case; fit on seed 3, checked on seeds 4 and 5; errors
against the point truth, ``--truth point``), held-out case-components in the band, raw -> calibrated:

- ``--flows hill``: 0 -> 5 of 6 (x ratio 6.4-7.0 -> 0.82-0.90, y 5.1-8.5 -> 0.66-1.09, z 2.8-3.7 -> 0.87-1.16;
  z coverage 0.29 -> 0.65-0.71);
- ``--flows uniform_x``: 2 -> 1 of 6 (seed 3's x ratio 0.92 against 2.3-2.5 on seeds 4, 5: a field-wide x bias
  of -0.0047 mm there, which no scale of σ describes);
- both flows pooled: 2 -> 3 of 12 (factors x 2.67, y 3.08, z 1.76: between the flows, right for neither).

The ratio per tercile of the correlation peak height shows no common trend (uniform x 2.3/2.6/2.6, Hill x
4.7/8.0/8.5, Hill z 4.2/3.8/2.5): the factor is not modelled on it.

Measured on the thesis camera (issue 38, 2026-11-28): config/thesis.yaml with SET = ``--set
camera.sensor.n_pixels_x=800 camera.sensor.n_pixels_y=600 depth_calibration.enabled=false
raytrace.method=montecarlo``, seeds 2011 and 2012, the thesis' 2-level WIDIM (final window 8 x 16 x 16 voxels at
4 x 8 x 8, 7 x 3 x 5 = 105 vectors a case); errors against the window-averaged truth; each design (method, ppp)
fitted on one seed with its flows pooled and checked on the other, both ways. The twelve 0.005 ppp cases ran on
a 16-core machine, ``bench_uncertainty.py --flows hill uniform_x lamb_oseen --ppp 0.005 --set SET --sweep
"reconstruct.method=[mart,ipr]" "seed=[2011,2012]" --jobs 16 --threads 1`` (336 s in all, an IPR frame 242-298
s); the 0.001 ppp ones (``--flows hill uniform_x --ppp 0.001``) on 2 loaded cores, where the 0.005 ppp MART
cases and Hill's IPR ones also ran (the same figures: MART to 1e-16, IPR to 2e-7). A design is read with ``--set
SET "sweep.flow=[hill,uniform_x,lamb_oseen]" "sweep.ppp=[0.005,0.001]" --sweep "reconstruct.method=[mart,ipr]"
"seed=[2011,2012]" --where reconstruct.method=mart ppp=0.005 --fit-seeds 2011``. Held-out case-components in
the band, raw -> calibrated (of 9 per way with three flows, 6 with two):

- MART 0.005 ppp (uniform_x, Hill, lamb_oseen): 4 -> 5 and 4 -> 6 (factors x 1.68-1.74, y 0.96-0.98, z
  1.75-1.87). y is right raw on every flow (coverage 0.58-0.80, ratio 0.79-1.17). x: Hill 1.53-1.68 and
  lamb_oseen 3.3-3.4 against the uniform shift's 0.90-0.94, so the pooled factor puts Hill in the band (0.69-0.72
  / 0.88-1.00) and the uniform shift out (0.89-0.92 / 0.51-0.56), lamb_oseen stays out (1.97-1.99). z: the
  calibrated ratio is 0.79-1.25 everywhere but the coverage only 0.37-0.56 on the vortices: the z error has
  heavier tails than a Gaussian of σ (a few large errors carry the RMS), so no scale meets both; Hill's z
  never enters the band. Fitted per flow on Hill alone, Hill's held-out x 0.45 / 1.68 -> 0.66 / 1.10, z 0.22 /
  2.19 -> 0.41 / 1.13.
- MART 0.001 ppp (uniform_x, Hill): 3 -> 2 and 5 -> 3: raw σ is already near right there (x 0.83-1.07, y
  0.85-1.34, uniform z 0.99-1.09), the factors (0.92-1.34) only move the cases about the band's edges.
- IPR 0.001 ppp (uniform_x, Hill; paired PTV): 3 -> 1 and 1 -> 3. The flows disagree in x (Hill 1.43-1.53,
  the uniform shift 0.39-0.50: σ far too large where the particle tracks are clean), so the pooled factor
  (0.77-0.84) suits neither; Hill's z 1.82-2.44 (coverage 0.21-0.29).
- IPR 0.005 ppp (uniform_x, Hill, lamb_oseen; paired PTV): 3 -> 5 and 3 -> 6 (factors x 1.53-1.56, y
  0.99-1.05, z 1.75-1.99). y is right raw on every flow; x as MART's (Hill 1.37-1.50, lamb_oseen 4.0-4.2, the
  uniform shift 0.60-0.65), so the factor helps Hill (0.53-0.60 / 0.87-0.99) and hurts the uniform shift
  (0.94 / 0.40-0.41); z calibrated is in the band on the uniform shift and lamb_oseen (0.58-0.80 /
  0.73-1.26), Hill's stays at 0.37-0.44 / 1.15-1.39. On Hill alone (``--flows hill``): x 0.34-0.41 /
  1.37-1.50 -> 0.50-0.58 / 0.91-1.10, z 0.22-0.26 / 2.29-2.43 -> 0.44-0.49 / 0.94-1.06: the ratio is
  repaired, the coverage is not (as MART's z).

Rerun 2026-12-04 at 0.001 ppp with lamb_oseen (``--flows hill uniform_x lamb_oseen --ppp 0.001``, the paired
vectors' σ floor from their tracks the default; 12 cases in 5.5 min on 2 cores), held out, raw -> calibrated: MART 4 ->
3 and 6 -> 6 of 9, IPR 2 -> 3 and 2 -> 3. lamb_oseen's x is out for both (ratio MART 2.0-2.5, IPR 3.4-3.5; the oracle
errs as much there, 0.065 mm); with ``--truth oracle`` it is in or near the band (IPR 0.81 / 0.78-0.85, MART 0.52-0.61
/ 0.78-0.94), held out MART 4 and 6, IPR 3 and 3 of 9 raw. IPR's uniform shift: σ 2-3x too large (x ratio 0.36-0.48).
Not run: a larger crop (more vectors a case).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
TARGET_COV, TARGET_RATIO = (0.55, 0.80), (0.7, 1.4)
AXES = {"x": "u", "y": "v", "z": "w"}


def _inside(cov: float, ratio: float) -> str:
    ok = TARGET_COV[0] <= cov <= TARGET_COV[1] and TARGET_RATIO[0] <= ratio <= TARGET_RATIO[1]
    return "in" if ok else "out"


def _error(e, comp: str, truth: str) -> np.ndarray:
    """A case's per-vector error [mm] against the point truth, the window-averaged truth or the oracle (NaN where
    the oracle has no valid vector)."""
    err = e[f"{comp}_err_mm"].values
    if truth == "point":
        return err
    if truth == "oracle":
        from lfstudy.study.metrics import oracle_error

        out = oracle_error(e, comp)
        if out is None:
            raise SystemExit(f"--truth oracle: the case has no oracle_{comp}_mm (errors written without the oracle)")
        return out
    if f"{comp}_filter_mm" not in e:
        raise SystemExit(f"--truth window: the case has no {comp}_filter_mm (errors written without window_truth)")
    # measured − window-averaged truth = (measured − point truth) − (window-averaged − point truth)
    return err - e[f"{comp}_filter_mm"].values


def _matches(case, where: list[str]) -> bool:
    """Whether a case has every ``KEY=VALUE`` of ``--where`` (values read as YAML, else as text)."""
    for item in where:
        key, _, val = item.partition("=")
        want = yaml.safe_load(val)
        if case[key] != want and str(case[key]) != val:
            return False
    return True


def main() -> None:
    from bench_uncertainty import read_config

    from lfstudy import io
    from lfstudy.process.uncertainty_calibration import fit_calibration
    from lfstudy.study.config import validate_config
    from lfstudy.study.metrics import uncertainty_calibration
    from lfstudy.study.sweep import Sweep
    from lfstudy.study.table import combine_cases

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, required=True, help="the config the cases ran with (its sweep)")
    ap.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE", help="the same overrides as the run")
    ap.add_argument("--sweep", nargs="*", default=[], metavar="KEY=[V1,V2]", help="the same sweeps as the run")
    ap.add_argument("--where", nargs="*", default=[], metavar="KEY=VALUE", help="only the cases of one design")
    ap.add_argument(
        "--truth", choices=("window", "point", "oracle"), default="window", help="the truth the errors are against"
    )
    ap.add_argument("--out", type=Path, required=True, help="the run's directory (the cases' errors.zarr)")
    ap.add_argument("--fit-seeds", nargs="+", type=int, required=True, help="seeds the factor is fitted on")
    ap.add_argument("--flows", nargs="*", default=None, help="only these flows' cases (fit and check)")
    ap.add_argument("--bins", action="store_true", help="ratio per tercile of the correlation peak height")
    args = ap.parse_args()

    raw = read_config(args.config, args.set)
    for item in args.sweep:
        key, _, vals = item.partition("=")
        raw.setdefault("sweep", {})[key] = yaml.safe_load(vals)
    cfg = validate_config(raw)
    sw = Sweep(cfg)
    cases = [c for c in sw.cases() if (args.out / sw.locate(c, "errors.zarr")).exists()]
    if args.flows:
        cases = [c for c in cases if c["flow"] in args.flows]
    cases = [c for c in cases if _matches(c, args.where)]
    if not cases:
        raise SystemExit(f"no case of {args.out} has errors.zarr and matches --flows / --where")
    errs = {c.case_id: io.open_zarr(args.out / sw.locate(c, "errors.zarr")).load() for c in cases}
    study = combine_cases([(c, errs[c.case_id]) for c in cases], sw.settings)
    for d in study.dims:
        if d not in ("flow", "seed") and study.sizes[d] > 1:
            raise SystemExit(f"more than one design in {args.out}: pick one with --set (dimension {d})")
    rows = []
    fit = [c for c in cases if int(c["seed"]) in args.fit_seeds]
    held = [c for c in cases if int(c["seed"]) not in args.fit_seeds]
    sub = study.sel(
        seed=list(args.fit_seeds), flow=sorted({c["flow"] for c in cases}, key=list(study["flow"].values).index)
    )
    cal = fit_calibration(sub, source=str(args.out))
    print(cal.summary())
    print(f"fitted on {len(fit)} cases (seeds {args.fit_seeds}), checked on {len(held)} held-out cases")
    against = {"window": "the window-averaged truth", "point": "the point truth", "oracle": "the oracle"}[args.truth]
    print(f"errors against {against}\n")
    header = f"{'case':<44}{'set':>5} ax   raw cov  ratio  |  cal cov  ratio   band raw/cal"
    print(header)
    zlines = []
    for c in fit + held:
        e = errs[c.case_id]
        tag = "fit" if c in fit else "check"
        name = " ".join(f"{k}={c[k]}" for k in ("flow", "seed"))
        for ax, comp in AXES.items():
            err, sig = _error(e, comp, args.truth), e[f"unc_{comp}_mm"].values
            fin = np.isfinite(err)
            cov0, r0 = uncertainty_calibration(err, sig, fin)
            cov1, r1 = uncertainty_calibration(err, sig * cal.factor[ax], fin)
            line = (
                f"{name:<44}{tag:>5} {ax}  {cov0:8.3f} {r0:6.2f}  | {cov1:8.3f} {r1:6.2f}   "
                f"{_inside(cov0, r0)}/{_inside(cov1, r1)}"
            )
            rows.append((tag, ax, cov0, r0, cov1, r1))
            (zlines if ax == "z" else []).append(line)
            if ax != "z":
                print(line)
    print("z (on its own):")
    for line in zlines:
        print(line)
    for tag in ("fit", "check"):
        sel = [r for r in rows if r[0] == tag]
        if not sel:
            continue
        raw = sum(_inside(r[2], r[3]) == "in" for r in sel)
        calib = sum(_inside(r[4], r[5]) == "in" for r in sel)
        print(
            f"{tag}: in the band (coverage {TARGET_COV}, ratio {TARGET_RATIO}): raw {raw}, calibrated {calib} "
            f"of {len(sel)} case-components"
        )
    if args.bins:
        print("\nheld-out cases: RMS error / RMS raw σ per tercile of the correlation peak height (low / mid / high)")
        for c in held:
            piv = io.open_zarr(args.out / sw.locate(c, "piv.zarr")).load()
            e = errs[c.case_id]
            dims = e["u_err_mm"].dims
            peak = piv["peak"].transpose(*dims).values
            for ax, comp in AXES.items():
                err, sig = _error(e, comp, args.truth), e[f"unc_{comp}_mm"].values
                ok = np.isfinite(err) & np.isfinite(sig) & np.isfinite(peak)
                edges = np.quantile(peak[ok], [0, 1 / 3, 2 / 3, 1])
                parts = []
                for lo, hi in itertools.pairwise(edges):
                    m = ok & (peak >= lo) & (peak <= hi)
                    parts.append(np.sqrt(np.mean(err[m] ** 2)) / np.sqrt(np.mean(sig[m] ** 2)))
                print(f"  {c['flow']} seed={c['seed']} {ax}: " + " / ".join(f"{p:.2f}" for p in parts))


if __name__ == "__main__":
    main()
