"""Volumetric (dot-target) calibration against the thin-lens model on an imperfect camera (issue 29 §2).

The thesis camera (Table 4.3) on a cropped sensor (default 1200 x 900 px) at 0.001 ppp, uniform
x shift; three runs of the same case, each through the case stage functions in this process
(images, lenslet calibration, registration, refocus, reconstruction, PIV, errors; depth
calibration off):

- ``ideal``: the ideal camera, thin-lens refocus (the reference);
- ``thin_lens``: main-lens distortion k1 (the field corners move by ``--corner`` voxels in
  focus: k1 = corner·voxel/h, h the sensor half-diagonal) plus a lenslet gap error, thin-lens
  refocus with the nominal camera;
- ``volumetric``: the same camera, refocused through the dot-target calibration
  (:func:`lfstudy.study.case.case_volcal`).

Prints the mean displacement bias and total RMS error [voxels] of each, the calibration's fit
and hold-out residuals, and the target (issue 29): bias <= 0.1 voxel and RMS within 25 % of
the ideal camera's with the volumetric calibration.

    NUMBA_NUM_THREADS=2 python benchmarks/bench_volcal.py [--crop 1200 900] [--corner 2] [--gap 0.02]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def _config(args: argparse.Namespace) -> dict[str, Any]:
    from lfstudy.config import read_yaml
    from lfstudy.study.config import validate_config

    raw = read_yaml(ROOT / "config" / "thesis.yaml")
    raw["camera"]["sensor"].update(n_pixels_x=args.crop[0], n_pixels_y=args.crop[1])
    raw["sweep"] = {"ppp": [args.ppp], "flow": ["uniform_x"]}
    raw["depth_calibration"] = {"enabled": False}
    return validate_config(raw)


def _run(cfg: dict[str, Any], imperfections: dict[str, float], model: str) -> tuple[Any, Any, float]:
    from lfstudy.lightfield.calibrate import find_lenslet_centers
    from lfstudy.simulate.flows import flow_from_config
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config
    from lfstudy.study.metrics import case_metrics
    from lfstudy.study.sweep import Sweep

    ccfg = case_config(cfg, Sweep(cfg).cases()[0])
    ccfg = {**ccfg, "camera": {**ccfg["camera"], "imperfections": dict(imperfections)}}
    ccfg["refocus"] = {**ccfg["refocus"], "model": model}
    t0 = time.perf_counter()
    cam = cl.case_camera(ccfg)
    centers = find_lenslet_centers(cl.case_pinhole(ccfg), cam)
    cal = cl.case_volcal(ccfg, centers) if model == "volumetric" else None
    pa = cl.case_particles(ccfg)
    pb = cl.case_displaced(ccfg, pa)
    vols = [
        cl.render_frame(cl.case_image(ccfg, p, f), centers, ccfg, calibration=cal)[2].load()
        for p, f in ((pa, "a"), (pb, "b"))
    ]
    piv = cl.case_piv(ccfg, *vols)
    spec = ccfg["flow"]
    err = case_metrics(
        piv,
        flow_from_config(spec),
        cam,
        vols[0],
        cl.case_illuminated(ccfg, pa),
        sigma_mm=cl.truth_sigma(cam),
        dt=spec.get("dt", 1.0),
        n_steps=spec.get("n_steps", 100),
    )
    return err, cal, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--crop", nargs=2, type=int, default=[1200, 900], metavar=("NX", "NY"))
    ap.add_argument("--ppp", type=float, default=0.001)
    ap.add_argument("--corner", type=float, default=2.0, help="in-focus displacement of the field corners [voxels]")
    ap.add_argument("--gap", type=float, default=0.02, help="lenslet gap error (relative)")
    ap.add_argument("--only", nargs="*", default=["ideal", "thin_lens", "volumetric"])
    args = ap.parse_args()

    from lfstudy.optics import PlenopticCamera

    cfg = _config(args)
    cam = PlenopticCamera.from_config(cfg)
    h = 0.5 * math.hypot(cam.sensor_width, cam.sensor_height)
    voxel = cam.lenslet_pitch  # the in-focus image of one voxel (pl/|M|) on the sensor
    k1 = args.corner * voxel / h
    imp = {"distortion_k1": k1, "lenslet_gap_error": args.gap}
    print(f"thesis camera {args.crop[0]} x {args.crop[1]} px, ppp {args.ppp}, uniform_x; k1 = {k1:.4f}, gap {args.gap}")
    runs = {"ideal": ({}, "thin_lens"), "thin_lens": (imp, "thin_lens"), "volumetric": (imp, "volumetric")}
    res = {}
    for name in args.only:
        err, cal, secs = _run(cfg, *runs[name])
        res[name] = err
        bias = [float(err[f"bias_{ax}"]) for ax in "xyz"]
        print(
            f"{name:11s} bias x/y/z {bias[0]:+.3f} {bias[1]:+.3f} {bias[2]:+.3f} voxel, |bias| "
            f"{math.sqrt(sum(b * b for b in bias)):.3f}, rms_total {float(err['rms_total']):.3f} voxel, "
            f"valid {float(err['valid_percent']):.1f} %  ({secs:.0f} s)",
            flush=True,
        )
        if cal is not None:
            a = cal.attrs
            print(
                f"            calibration: {a['n_dots']} dots x {len(a['depths'])} depths, {a['valid_subapertures']} "
                f"sub-apertures, fit rms {a['fit_rms_lenslets']:.3f}, hold-out z={a['holdout_depth']:.3g} mm "
                f"rms {a['holdout_rms_lenslets']:.3f} lenslets"
            )
    if "ideal" in res and "volumetric" in res:
        v, i = res["volumetric"], res["ideal"]
        b = max(abs(float(v[f"bias_{ax}"])) for ax in "xyz")
        r = float(v["rms_total"]) / float(i["rms_total"])
        print(f"target: max |bias| {b:.3f} <= 0.1 voxel: {b <= 0.1}; rms / ideal {r:.2f} <= 1.25: {r <= 1.25}")


if __name__ == "__main__":
    main()
