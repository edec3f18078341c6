"""Where IPR's depths go: one frame of a finished study refitted from other images or from the truth (issue 39).

Reproduces: lfstudy/reconstruct/ipr/polish.py (``_START_SWEEPS``: what a warm start's joint intensities hold of the
truth); lfstudy/study/designs.py (``DENSITY_LIMITED``: the share of the true particles a fit from the truth keeps).

Reads a finished study (the README's first command writes ``results/demo``): frame a of one design, its true
particles (``particles_a.zarr``), its recorded image (``raw_a.zarr``, the study's Monte-Carlo rays) and the design's
calibrated lenslet centres. Fits it again with :func:`lfstudy.reconstruct.ipr.ipr_particles` (the config's
settings, one thread) once per ``--runs`` entry ``IMAGES:START``:

* ``IMAGES``: ``mc`` the study's own image; ``exact`` the exact renderer's expected image of the same particles
  (the fit's own model, no noise: an inverse crime, the upper bound of what the images hold); ``noisy`` the exact
  image with the case's photon shot noise (one photon per ray, as the Monte-Carlo image has) — ``noisy`` against
  ``mc`` separates the photon noise from any difference between the two renderers;
* ``START``: ``cold`` the fit as the study runs it (MART's candidates); ``truth`` a warm start at the true positions
  (``start=``; its depth scan and joint intensities, then the usual iterations and residual rounds): what the fit
  keeps of a correct answer.

Printed per run: particles fitted, found and ghosts (the study's criterion, half a voxel per scaled axis), the
least-squares slope and offset of the fitted z on the true z of the particles matched laterally (nearest true
particle within half a lateral voxel, whatever its depth), the RMS of their depth error, the mean depth error in
eight 0.5 mm bands from the grid's near end to its far end, the RMS depth error of the found particles (each
true particle's nearest fit) within 0.4 mm of focus, 0.4-1 mm and beyond (the study's w error of a lateral shift is
theirs, averaged over a window), the relative residual per iteration and the CPU time.

    python benchmarks/bench_ipr_depth_slope.py [--results results/demo] [--config config/demo.yaml]
        [--design mag~-0.8/fnum~matched/pitch~0.1184] [--runs mc:cold exact:cold noisy:truth ...] [--set k=v ...]

Findings (run 2026-12-03 on 2 cores, loaded; the demo study of 08508ba, seed 7, frame a; M -0.8, pitch 0.1184 mm
unless said; found / ghosts %, slope):

* The depth compression is not the renderer and not the calibrated grid: ``mc:cold`` 28.6 / 64.3, slope 0.841;
  ``exact:cold`` (no noise, the fit's own model) 31.2 / 63.7, slope 0.854. The calibrated centres sit on the true
  lattice (pitch 16.0842 px against 16.0842 nominal). The residual of the cold exact fit stops at 0.14 of the image
  (25 iterations instead of 10: 0.12, found 35.0 %): the fit does not find the noise-free answer it could hold.
* From the truth (``truth`` starts, before the joint intensities; joint intensities through a script's patch of
  ``_START_SWEEPS``, 20 sweeps, no depth scan): one intensity sweep left 0.36 of the exact image unexplained and the
  shake then moved the true particles off (exact 77.5 / 14.2, ``mc`` 73.4 / 18.6); 20 sweeps left 0.008 (exact)
  and the fit kept 89.8 / 4.1 (exact), 82.9 / 12.2 (``mc``), 82.0 / 12.5 (``noisy``). With the study's photon noise
  the slope from the truth is 0.938 (``mc``) and 0.945 (``noisy``) against 0.979 without noise, the far bands
  pulled 0.1 mm (0.4 voxel) towards focus: the noise, not the renderer, makes the rest of the compression.
* ``truth`` with the product's warm start (depth scan, now 10 joint sweeps), ``mc`` images, before -> after c26159b,
  found / ghosts: M -0.8 p 0.1184 65.3 / 27.2 -> 80.5 / 14.2; M -0.8 p 0.0888 80.9 / 15.3 -> 87.0 / 10.8;
  M -1 p 0.1184 85.4 / 11.5 -> 92.9 / 5.2; M -1 p 0.0888 94.3 / 4.7 -> 96.2 / 3.4.
* The finest design's depth scatter is the cold fit's, not the images' (the demo study of 7f2235b, seed 7, frame
  a, M -1, pitch 0.0888; ``--runs mc:cold mc:truth``, found particles' z RMS in um by |z|, loaded 2 cores): cold
  79.4 / 15.6, all 34.6, |z| < 0.4 mm 61.4, 0.4-1 mm 34.4, >= 1 mm 27.1, residual 0.169; from the truth 96.2 / 3.4,
  all 18.1, 33.3, 14.2, 11.8, residual 0.136. The same images hold half the cold fit's depth error away from focus
  (the single-particle bound there: 5.8 um median, ``bench_position_bound.py``): the cold fit stops in a worse
  minimum (its ghosts carry the light of the particles it missed), and that scatter is the w error of the study's
  lateral shift (0.0155 mm on this design against an oracle of 0.0011). Which of its errors holds the fit there:
  warm starts (``ipr_particles(start=...)``, a script's, same images and settings) from the stored cold fit
  (222 ghosts, 317 true particles missed) gave, found / ghosts %, z RMS all / >= 1 mm [um], residual: restarted as
  it is 81.8 / 14.8, 31.6 / 21.3, 0.152; without its ghosts (an oracle's removal) 84.8 / 11.7, 31.8 / 21.6, 0.153;
  with the missed particles added (an oracle's) 88.9 / 12.0, 29.3 / 18.9, 0.138. The missing particles, whose
  light the neighbours take, hold the depths off more than the ghosts do; a second pass of the fit from its own
  answer (the warm start's depth scan and joint intensities, then the iterations and rounds again) takes a fifth
  off the far particles' depth error for a second fit's CPU (66.6 s against 70.3).
* The leads that followed, tried on the finest design's cold fit (the demo study of 7f2235b, seed 7, frame a; a
  script's patch of the fit, 1 thread): a depth scan of every fitted particle after the last shake (+-2 voxels in
  0.25 steps, the others held fixed, in runs of non-overlapping patches, before the polish) moved 37 of 1,427
  particles; found 79.4 -> 79.4 %, ghosts 15.6 -> 15.6 %, found particles' z RMS 34.6 -> 34.4 um (>= 1 mm 27.1 ->
  27.0), CPU 40.4 -> 49.7 s: each misplaced depth is the best one given its neighbours. The ghosts are mostly those
  misplaced particles: 92 % of the 222 lie within 1.5 voxels of a true particle, 91 % of those of one counted missed,
  offset 0.64 z voxel against 0.15 laterally (median; M -0.8, p 0.0888: 81 %, 85 %, 0.69 z voxel). What is left is
  a joint move of a particle and its line-of-sight neighbours; the PIV now weighs the tracks by the depth scatter
  their band shows (``piv.paired_weights``, ``benchmarks/bench_paired_weights.py``).
* Tried on the cold fit of the coarsest design, no gain (found / ghosts): 10-20 joint sweeps for MART's candidates
  30.5-32.6 / 63-65; a depth scan of every candidate over +-2 voxels 28.3 / 67.2 and over the whole slab (+-8)
  25.8 / 70.3; a shake that moves a particle only where the residual drops by more than twice the patch's residual
  variance 30.1 / 65.7 (from the truth it kept 87.2 / 7.2). The cold fit's shortfall on this design is its
  candidates and the depth its images hold near focus (``bench_position_bound.py``: 0.4-1.8 z voxels there), not
  its intensities or its moves.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
_BAND_MM = 0.5


def _score(truth, fit, grid) -> str:
    from scipy.spatial import cKDTree

    from lfstudy.study.particle_metrics import _match

    vox = np.array(grid.voxel_size()[::-1])
    t = np.column_stack([truth[k].values for k in "xyz"])
    f = np.column_stack([fit[k].values for k in "xyz"])
    ok, nearest, ghost = _match(t, f, vox)
    # the depth error of the found particles (their nearest fit, within half a voxel), by distance from focus
    ez, depth = f[nearest[ok], 2] - t[ok, 2], np.abs(t[ok, 2])
    found_rms = []
    for lo, hi in ((0.0, 0.4), (0.4, 1.0), (1.0, np.inf)):
        inside = (depth >= lo) & (depth < hi)
        found_rms.append(
            f"|z| {lo:g}-{hi:g} mm " + (f"{1e3 * np.sqrt(np.mean(ez[inside] ** 2)):.1f}" if inside.sum() > 3 else "-")
        )
    dist, j = cKDTree(t[:, :2] / vox[:2]).query(f[:, :2] / vox[:2])
    lat = dist < 0.5
    zt, zf = t[j[lat], 2], f[lat, 2]
    slope, off = np.polyfit(zt, zf, 1) if lat.sum() > 2 else (np.nan, np.nan)
    z0, z1 = float(grid.z[0]), float(grid.z[-1])
    edges = np.arange(z0, z1 + 1e-9, _BAND_MM)
    band = np.digitize(zt, edges)
    means = " ".join(
        f"{np.mean(zf[band == b] - zt[band == b]):+.3f}" if (band == b).sum() > 3 else "  -   "
        for b in range(1, len(edges))
    )
    return (
        f"{len(f)} fitted; found {100 * ok.mean():.1f} %, ghosts {100 * ghost.mean():.1f} %; z on true z: slope "
        f"{slope:.3f}, offset {off:+.4f} mm ({lat.sum()} matched laterally), rms {np.sqrt(np.mean((zf - zt) ** 2)):.4f}"
        f" mm\n    mean z error per {_BAND_MM:g} mm band from z = {z0:g} mm: {means}"
        f"\n    z error of the found particles, RMS [um]: all {1e3 * np.sqrt(np.mean(ez**2)):.1f}; "
        + " ".join(found_rms)
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=ROOT / "results" / "demo", help="a finished study's results")
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "demo.yaml", help="its config")
    ap.add_argument("--design", default="mag~-0.8/fnum~matched/pitch~0.1184", help="the design's path in results")
    ap.add_argument("--ppp", default="0.005", help="the seeding level's path element (ppp~...)")
    ap.add_argument("--runs", nargs="+", default=["mc:cold", "exact:cold", "mc:truth"], metavar="IMAGES:START")
    ap.add_argument(
        "--set", nargs="*", default=[], metavar="K=V", help="ipr_particles settings for every run (K=V,K2=V2 too)"
    )
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    import numba
    from bench_ipr import _setting

    from lfstudy import io
    from lfstudy.lightfield import register
    from lfstudy.reconstruct import ReconstructionInputs
    from lfstudy.reconstruct.ipr import ipr_particles
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config, load_config

    numba.set_num_threads(args.threads)
    cfg = load_config(args.config)
    flow = next(iter(cfg["flows"]))
    ccfg = case_config(cfg, f"{args.design}/ppp~{args.ppp}/flow~{flow}")
    cam = cl.case_camera(ccfg)
    grid = cl.case_grid(ccfg, cam)
    where = args.results / args.design / f"ppp~{args.ppp}"
    parts = args.design.split("/")
    centers = io.open_zarr(args.results / "calib" / parts[0] / parts[-1] / "centers.zarr").load()
    truth = io.open_zarr(where / "particles_a.zarr").load()
    kw = {k: v for k, v in dict(ccfg["reconstruct"].get("ipr", {})).items() if k != "blob_sigma"}
    changed: dict[str, object] = {}
    for text in args.set:  # bench_ipr's parsing of ipr_particles keywords (k=v or k=v,k2=v2)
        changed |= _setting(text)
    kw |= changed
    n = truth.sizes["particle"]
    print(f"{args.results} {args.design}, frame a: {n} true particles; the config's IPR settings, changed: {changed}")
    for run in args.runs:
        images, start = run.split(":")
        if images == "mc":
            raw = io.open_array(where / "raw_a.zarr").load()
        elif images in ("exact", "noisy"):
            c2 = copy.deepcopy(ccfg)
            c2["raytrace"]["method"] = "exact"
            c2["sensor"]["shot_noise"] = images == "noisy"
            raw = cl.case_image(c2, truth, "a", illuminate=False)
        else:
            raise SystemExit(f"--runs {run!r}: IMAGES is mc, exact or noisy")
        if start not in ("cold", "truth"):
            raise SystemExit(f"--runs {run!r}: START is cold or truth")
        inputs = ReconstructionInputs(lightfield=register(raw, centers, cam), centers=centers, camera=cam, grid=grid)
        warm = np.column_stack([truth[k].values for k in "xyz"]) if start == "truth" else None
        c0 = time.process_time()
        fit = ipr_particles(inputs, start=warm, **kw)
        cpu = time.process_time() - c0
        res = ", ".join(f"{r:.3f}" for r in fit.attrs["residual_norm"])
        print(f"  {run}: {_score(truth, fit, grid)}\n    residual {res}; CPU {cpu:.1f} s", flush=True)


if __name__ == "__main__":
    main()
