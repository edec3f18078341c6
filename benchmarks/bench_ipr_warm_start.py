"""IPR's second frame started from the first frame's particles (a warm start, as Shake-the-Box's; issue 39 §1).

Reproduces: lfstudy/reconstruct/ipr/fit.py (the figures in the docstring of ``ipr_particles``' ``start``).

    python benchmarks/bench_ipr_warm_start.py [--camera demo|table43] [--crop 320 240] [--ppp 0.005]
        [--shift 0.2 0.0 0.1] [--seed 1 [2 ...]] [--compare iterations=3,residual_candidates=2 ...]

Two frames of one particle field, the second moved by ``--shift`` [mm], each imaged with Monte-Carlo rays (2000 a
particle, 4000 photons of shot noise; other rays and noise per frame) through a camera whose lenslet grid the
calibration finds (the scene of ``bench_ipr.py``). Frame a is fitted cold (the defaults); frame b cold, and then warm:
``ipr_particles(..., start=...)`` from frame a's fitted particles moved by a predictor that knows nothing of the truth,
WIDIM (the demo's windows 8 x 16 x 16, spacing 4 x 8 x 8, two levels) between MART volumes of the two frames on the
case grid, interpolated at frame a's particles (:func:`lfstudy.piv.ptv.predict`). Each ``--compare`` setting is a
further warm fit with those ``ipr_particles`` keywords.

Printed per fit: particles fitted, found within half a voxel of a true one (of those inside the grid), ghosts, rms z of
the found [mm], CPU s (one thread), exact particle images and MART volumes; and for the particles found in both frames
(each true particle's nearest fit within half a voxel) the median and mean of the fitted displacement a -> b and its
rms error [mm] per axis: where the warm start leaves b's particles near their start, their displacement leans
towards the predictor's.

Measured (demo camera, 320 x 240 px, 0.005 ppp, shift (0.2, 0, 0.1) mm, 1 thread, quiet 2 cores (load 1-2), ``--seed
1 2 --compare iterations=3,residual_candidates=2 iterations=5``; found inside the grid / ghosts %, CPU s, and the mean w
[mm] of the particles found in both frames, true 0.1; frame a cold: 81.5 / 15.0 and 81.2 / 15.8, 8.0 / 8.8 s). "no
scan": the same warm fits with the depth scan off (a script's patch of ``_START_SCAN = ()`` in
``lfstudy/reconstruct/ipr/polish.py``), as the start was first built:

=========================  ================================  ================================
frame b                    seed 1 (predictor w 0.076, -24 %)  seed 2 (predictor w 0.049, -51 %)
=========================  ================================  ================================
cold (defaults)            84.7 / 14.1, 8.3 s, w .0988        79.5 / 17.7, 8.1 s, w .0971
cold, 5 iterations         83.3 / 15.9, 5.3 s, w .0998        78.7 / 20.1, 5.3 s, w .0981
cold, 3 it., 2 rounds      81.4 / 17.5, 3.7 s, w .0989        75.8 / 21.7, 3.7 s, w .1001
warm (defaults)            83.3 / 15.0, 8.8 s, w .0994        80.6 / 18.4, 8.4 s, w .0959
warm, 5 iterations         82.5 / 17.2, 6.0 s, w .0989        81.2 / 19.0, 5.7 s, w .0964
warm, 3 it., 2 rounds      82.5 / 17.7, 4.3 s, w .0977        78.9 / 21.3, 4.2 s, w .0980
no scan (defaults)         87.3 / 11.7, 7.7 s, w .0959        82.6 / 16.9, 8.4 s, w .0937
no scan, 5 iterations      86.4 / 14.6, 4.6 s, w .0977        83.1 / 17.8, 5.2 s, w .0936
no scan, 3 it., 2 rounds   87.0 / 14.6, 3.3 s, w .0963        82.9 / 18.4, 3.7 s, w .0922
=========================  ================================  ================================

("3 it., 2 rounds": ``iterations=3,residual_candidates=2``.) Without the scan the warm start looked like the lever:
5.6 / 7.1 points more found than the cold fit of the same settings, and at 3.3-3.7 s (0.4-0.45x the cold defaults'
CPU) as many or more particles as the cold defaults. But those particles near focus, where the residual is flat in z,
kept the predictor's depth: the mean w lay 2.1-7.9 % of the true w below the cold fit's of the same settings. With
the scan (each started particle moved along z, within 2 voxels, to where this frame's residual drops most) the pull
is within 2.1 points (+0.6 to -2.1), and so is the gain: the warm fits find -1.4 to +3.1 points against the cold fits
of the same settings, for about the same CPU (the scan's 17 images a particle against the first MART volume). The
warm start's gain was the predictor's depth, which is also its bias; the study does not use it.

With the start's intensities fitted jointly (c26159b: ten Gauss-Seidel sweeps before and after the scan, instead of
one), rerun 2026-12-03 beside the code before it, same command, loaded 2 cores; warm (defaults) seed 1 / seed 2, before
-> after: found 85.9 / 80.1 -> 85.6 / 80.3 %, ghosts 13.5 / 18.0 -> 12.4 / 18.8 %, mean w of the particles found in
both frames 0.0985 / 0.0973 -> 0.0984 / 0.0973 mm, their rms w error 0.0465 / 0.0422 -> 0.0431 / 0.0408 mm, images
35,088 / 35,654 -> 39,553 / 41,435. From a predictor on this design the joint intensities change little; from the
true positions on the crowded designs they keep far more (``bench_ipr_depth_slope.py``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _two_frames(camera: str, width: int, height: int, ppp: float, shift: np.ndarray, seed: int):
    """The true fields of frames a and b and the fit's inputs of each (one calibration for both)."""
    from lfstudy.lightfield import find_lenslet_centers, register, synthetic_pinhole
    from lfstudy.optics import PlenopticCamera
    from lfstudy.reconstruct import ReconstructionInputs, make_grid
    from lfstudy.simulate import render, seed_particles
    from lfstudy.simulate.sensor import apply_sensor

    if camera == "demo":  # config/demo.yaml's first design, its 4 mm slab on 0.25 mm planes (as bench_ipr.py)
        cam = PlenopticCamera(width, height, 0.0074, 0.0888, 4 * 0.0888, 50.0, -1.0, lenslet_offset_x=0.009)
        span, zr, vz = 4.0, (-2.0, 2.0), 0.25
    else:  # Table 4.3 over the thesis' 7 mm depth
        cam = PlenopticCamera(width, height, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013)
        span, zr, vz = 7.0, None, None
    cam = cam.with_(lenslet_offset_y=-0.021)
    cen = find_lenslet_centers(synthetic_pinhole(cam, amplitude=3000, seed=seed + 1), cam)
    grid = make_grid(cam, cam.focal_planes(), z_range=zr, voxel_z=vz)
    fa = seed_particles(cam, ppp=ppp, z_span=span, seed=seed)
    fb = fa.assign(x=fa.x + shift[0], y=fa.y + shift[1], z=fa.z + shift[2])
    out = []
    for k, field in enumerate((fa, fb)):
        img = render(cam, field, 2000, seed + 2 + 10 * k, method="montecarlo")
        lf = register(apply_sensor(img, photons_per_particle=4000, seed=seed + 3 + 10 * k), cen, cam)
        out.append((field, ReconstructionInputs(lightfield=lf, centers=cen, camera=cam, grid=grid)))
    return out


def _xyz(ds) -> np.ndarray:
    return np.column_stack([np.asarray(ds[v].values, float) for v in ("x", "y", "z")])


def _found_in_both(true_a, true_b, fit_a, fit_b, vox):
    """Per true particle found in both frames (nearest fit within half a voxel): the fitted displacement a -> b."""
    from scipy.spatial import cKDTree

    da, ia = cKDTree(fit_a / vox).query(true_a / vox)
    db, ib = cKDTree(fit_b / vox).query(true_b / vox)
    ok = (da < 0.5) & (db < 0.5)
    return fit_b[ib[ok]] - fit_a[ia[ok]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--camera", choices=("demo", "table43"), default="demo")
    ap.add_argument("--crop", type=int, nargs=2, default=[320, 240], metavar=("W", "H"))
    ap.add_argument("--ppp", type=float, default=0.005)
    ap.add_argument("--shift", type=float, nargs=3, default=[0.2, 0.0, 0.1], help="frame b's displacement [mm]")
    ap.add_argument("--seed", type=int, nargs="+", default=[1])
    ap.add_argument("--compare", nargs="*", default=["iterations=3,residual_candidates=2"], metavar="K=V,...")
    args = ap.parse_args()

    import numba
    from bench_ipr import _score, _setting

    from lfstudy.piv import widim
    from lfstudy.piv.ptv import predict
    from lfstudy.reconstruct.ipr import ipr_particles
    from lfstudy.reconstruct.mart import mart

    numba.set_num_threads(1)
    shift = np.array(args.shift)
    for seed in args.seed:
        (field_a, inp_a), (field_b, inp_b) = _two_frames(args.camera, *args.crop, args.ppp, shift, seed)
        vox = np.array(inp_a.grid.voxel_size()[::-1])
        ta, tb = _xyz(field_a), _xyz(field_b)
        ipr_particles(inp_a, iterations=1, residual_candidates=0, polish=0)  # compile outside the timings
        print(f"{args.camera} camera {args.crop[0]} x {args.crop[1]} px, {args.ppp} ppp, seed {seed}, shift {shift} mm")

        def fit(inp, field, label, **kw):
            c0 = time.process_time()
            p = ipr_particles(inp, **kw)
            cpu = time.process_time() - c0
            s = _score(field, p, inp.grid)
            print(
                f"  {label}: {len(p.x)} fitted; found {s['found_inside']:.1f} % (inside the grid), ghosts "
                f"{s['ghosts']:.1f} %, rms z {s['rms_z_mm']:.4f} mm; CPU {cpu:.1f} s, {p.attrs['particle_images']} "
                f"images, {p.attrs['mart_volumes']} MART volumes"
            )
            return p

        pa = fit(inp_a, field_a, "a cold")
        fits = {"b cold": fit(inp_b, field_b, "b cold")}
        for text in args.compare:  # the same settings without the warm start: what the start itself is worth
            fits[f"b cold {text}"] = fit(inp_b, field_b, f"b cold {text}", **_setting(text))
        c0 = time.process_time()
        va, vb = (mart(i.lightfield, i.camera, i.grid) for i in (inp_a, inp_b))
        pred = widim(va, vb, window=(8, 16, 16), spacing=(4, 8, 8), levels=2, mode="deform")
        d = predict(pred, _xyz(pa))
        print(
            f"  predictor (MART + WIDIM, CPU {time.process_time() - c0:.1f} s) at a's particles: median "
            f"{np.round(np.median(d, axis=0), 4)} mm, rms error {np.round(np.sqrt(np.mean((d - shift) ** 2, 0)), 4)} mm"
        )
        start = _xyz(pa) + d
        fits["b warm"] = fit(inp_b, field_b, "b warm", start=start)
        for text in args.compare:
            fits[f"b warm {text}"] = fit(inp_b, field_b, f"b warm {text}", start=start, **_setting(text))
        for label, pb in fits.items():
            dd = _found_in_both(ta, tb, _xyz(pa), _xyz(pb), vox)
            print(
                f"  displacement of the {len(dd)} found in both, {label}: median {np.round(np.median(dd, 0), 4)} "
                f"mean {np.round(dd.mean(0), 4)} rms error {np.round(np.sqrt(np.mean((dd - shift) ** 2, 0)), 4)} mm"
            )


if __name__ == "__main__":
    main()
