"""Why IPR finds fewer particles on one design than another: image density, candidates, the fit from the truth.

Reproduces: docs/config.md § "How much seeding a design resolves (`particles_per_cell`)";
lfstudy/study/designs.py (DENSITY_LIMITED: the share kept from the truth per particles per cell).

For each IPR case of a study config (frame a), beside the case's own fit (``volume_a.particles.zarr``,
scored where ``bench_budget.py`` wrote it in the same ``--out``):

* the source density: true particles (inside the grid) per lenslet (``/lens``), which is also the
  particles per pixel of each view (a view, one pixel behind every lenslet, images a particle on
  about one lenslet), and per voxel (``/vox``); the depth cells along a line of sight (``dcell``:
  across the views a particle's view image moves by its spot's diameter, 2 r lenslets, so two
  particles behind one lenslet differ once their 2 r differ by a lenslet: 2 |r(z1) - r(z0)| over
  the grid) and the particles per lenslet and depth cell (``/cell``); the defocus spot's radius r on
  the lenslet array in pitches (geometric, ``spot``: the median over the particles; ``r<=1%``: the
  share within one pitch) and the lenslets one particle lights (``lit``: π r², at least one);
* the overlap of the particles' raw images (the exact ones, ``particle_patches``): the share of a
  particle's light that falls on pixels where the other particles' light is larger than its own
  (``hid%``), and the share of the light on its pixels that is the others' (``for%``; both the
  median over the particles);
* the candidates: true particles with a peak of the first MART volume (refined grid, the fit's own)
  within half a voxel (``cand%``; ``cgh%``: the peaks with none);
* the case's fit: found and ghosts by the study's criterion (:mod:`lfstudy.study.particle_metrics`:
  half a voxel per axis; ``found%``, ``gh%``), and with a depth tolerance of two voxels (``fz4%``,
  ``gz4%``);
* the fit started from the truth (``truth%``, ``tgh%``, ``kept%``: the MART peaks replaced by the
  true positions, no residual rounds, the case's other settings): the upper bound of what the fit
  can hold; ``--variant K=V`` also runs the case's fit with some settings changed (``var%``);

and found % by depth band. Runs the study's stages up to the light fields itself (the runner of
``bench_uncertainty.py``, outputs reused when written):

    python benchmarks/bench_budget.py --configs config/demo_focus.yaml --jobs 1 --out DIR
    python benchmarks/bench_ipr_density.py --config config/demo_focus.yaml --out DIR [--design=-0.8:0.1184]

Measured (issue 27: why the coarsest demo design, M -0.8 pitch 0.1184, misses; demo_focus, seed 21,
frame a, today's IPR defaults, 1 thread, load 4-7 on 2 cores; ~40-60 s of CPU per fit from the truth;
fnd% and tru% are the columns found% and truth%):

  design           /lens /cell dcell  spot r<=1%   lit  hid%  for% cand%  fnd%   gh%  fz4%  gz4%  tru%  tgh%
  M -1 p 0.0888     0.69  0.06  10.7  3.43   5.3  44.2    49    45  47.3  89.1   9.9  99.1   2.6  96.8   2.1
  M -1 p 0.1184     1.20  0.15   8.0  2.58  11.7  25.1    68    55  17.7  75.7  24.3  96.9   7.2  92.8   4.0
  M -0.8 p 0.0888   0.69  0.13   5.5  1.70  23.6  10.9    42    38  28.7  72.1  25.1  95.0   5.6  90.2   8.1
  M -0.8 p 0.1184   1.21  0.30   4.1  1.28  36.7   6.2    66    52  16.1  39.8  53.1  74.0  20.7  75.4  20.3

The coarsest design is a limit of the design at 0.005 ppp, not of the fit's settings: started at the
true positions the same fit keeps only 75 % of the particles within half a voxel (20 % of what it
keeps are off), uniformly over the slab (72-77 % in each 1 mm band), where the three other designs
hold 90-97 % (2-8 % ghosts). The overlap of the images alone does not tell it (M -1 p 0.1184 has the
most, 68 % of a particle's light under brighter neighbours, and meets issue 27's targets); the
density per depth cell does: its spot grows only 0.27 -> 2.32 pitches over the 4 mm slab (M^2 = 0.64
shrinks the image-space depth), four depth cells along a line of sight for 1.2 particles per
lenslet, 0.30 particles per lenslet and depth cell against 0.06-0.15 on the others, and 37 % of its
particles sit behind one to four lenslets (r <= 1). The MART candidates find 16 % (as on M -1 p
0.1184, which the residual rounds then lift to 76 %). Its ghosts are mostly the real particles
mislocated in depth: 82 % lie within 1.5 voxels of a true one (median offsets 0.18 / 0.15 / 0.72
voxel in x / y / z), they are as bright as the found ones (median 1.07 against 0.97 of the median
intensity: no intensity floor separates them), and with a depth tolerance of two voxels (0.5 mm)
the fit finds 74 % (21 % ghosts) against 95-99 % on the others. No cheap setting helps: without the
polish (``--variant polish=0``) 42.2 % found, 50.5 % ghosts (39.8 / 53.1 with it), the same by depth
band. Half the seeding (benchmarks/demo_focus_coarsest.yaml, 0.0025 ppp: 0.15 particles per lenslet
and depth cell) lifts the bound to the other designs' (from the truth 91.4 % held, 7.4 % ghosts), but
the fit from MART's candidates finds 72.9 % (29.7 % ghosts; 92.5 / 11.9 with the two-voxel depth
tolerance), 45 % in the 1 mm nearest the focal plane (84 % from the truth), where 36 % of the particles
have a spot within one pitch; the case still misses issue 27's targets (bench_budget: RMS 0.0177 mm against
the limit 0.0153, crosstalk +0.082, 71.4 % found, 29.0 % ghosts over both frames). So on this design the
targets need less seeding than 0.0025 ppp, or the slab further from the focal plane (not measured), or
the design is left out of the coarse-design targets.
"""

from __future__ import annotations

import argparse
import itertools
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

#: The loose found criterion's z voxel, in grid voxels (within half of it: two voxels, 0.5 mm on demo_focus).
_LOOSE_Z = 4.0


def _found(true: np.ndarray, fit: np.ndarray, vox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from lfstudy.study.particle_metrics import _match

    ok, _, ghost = _match(true, fit, vox)
    return ok, ghost


def _overlap(cam, true: np.ndarray) -> tuple[float, float]:
    """Median over particles: share of its light where the others' light exceeds its own; share of the
    light on its pixels (weighted by its own) that is the others'."""
    from lfstudy.reconstruct.ipr import particle_patches

    buf, offs, r0, c0, shp = particle_patches(cam, *true.T)
    total = np.zeros((cam.n_pixels_y, cam.n_pixels_x))
    for i in range(len(true)):
        h, w = shp[i]
        total[r0[i] : r0[i] + h, c0[i] : c0[i] + w] += buf[offs[i] : offs[i + 1]].reshape(h, w)
    hidden, foreign = np.zeros(len(true)), np.zeros(len(true))
    for i in range(len(true)):
        h, w = shp[i]
        own = buf[offs[i] : offs[i + 1]].reshape(h, w)
        tot = total[r0[i] : r0[i] + h, c0[i] : c0[i] + w]
        other = np.maximum(tot - own, 0.0)
        s = own.sum()
        hidden[i] = own[other > own].sum() / s if s > 0 else math.nan
        foreign[i] = (own * other / np.maximum(tot, 1e-300)).sum() / s if s > 0 else math.nan
    return float(np.nanmedian(hidden)), float(np.nanmedian(foreign))


def _bands(z: np.ndarray, ok: np.ndarray, edges: np.ndarray) -> str:
    out = []
    for lo, hi in itertools.pairwise(edges):
        sel = (z >= lo) & (z < hi)
        out.append(f"{100 * ok[sel].mean():5.1f}" if sel.any() else "  -  ")
    return " ".join(out)


def diagnose(sc: dict, lf, centers, true_ds, fit_ds, truth: bool = True, variant: dict | None = None) -> dict:
    """The density figures, the candidates and the fit from the truth of one case's frame."""
    from lfstudy import reconstruct as rc
    from lfstudy.reconstruct import ipr as ipr_mod
    from lfstudy.reconstruct.ipr import candidates as ipr_candidates
    from lfstudy.study import case as cl

    cam = cl.case_camera(sc)
    grid = cl.case_grid(sc, cam)
    dz, dy, dx = grid.voxel_size()
    vox = np.array([dx, dy, dz])
    lo = np.array([grid.x[0], grid.y[0], grid.z[0]])
    hi = np.array([grid.x[-1], grid.y[-1], grid.z[-1]])
    t = np.column_stack([true_ds[k].values for k in "xyz"])
    t = t[np.all((t >= lo) & (t <= hi), axis=1)]
    mcam, _ = ipr_mod.calibrated_camera(cam, centers)
    r = ipr_mod._spot_pitches(mcam, t[:, 2])
    out = {
        "n": len(t),
        "per_lenslet": len(t) / (cam.n_lenslets_x * cam.n_lenslets_y),
        "spot": float(np.median(r)),
        "lit": float(np.mean(np.maximum(1.0, math.pi * r**2))),
        "per_voxel": len(t) / (len(grid.x) * len(grid.y) * len(grid.z)),
        "small": 100.0 * float(np.mean(r <= 1.0)),
    }
    # depth cells along a line of sight: across the aperture's views a particle's view image moves 2 r lenslets,
    # so two particles behind one lenslet are told apart in depth once their 2 r differ by a lenslet
    rz = ipr_mod._spot_pitches(mcam, np.array([grid.z[0], grid.z[-1]]))
    out["cells"] = float(2.0 * abs(rz[1] - rz[0]))
    out["per_cell"] = out["per_lenslet"] / out["cells"]
    out["hidden"], out["foreign"] = _overlap(mcam, t)
    out["z"], out["zlim"] = t[:, 2], (float(grid.z[0]), float(grid.z[-1]))
    nan = np.full(len(t), False)
    out["found"] = out["ghosts"] = out["found_z4"] = out["ghosts_z4"] = math.nan
    out["ok"] = nan
    if fit_ds is not None:
        fit = np.column_stack([fit_ds[k].values for k in "xyz"])
        ok, ghost = _found(t, fit, vox)
        out["found"], out["ghosts"], out["ok"] = 100 * ok.mean(), 100 * ghost.mean(), ok
        # the same with a depth tolerance of two voxels (half of four): where the design's depth cells are coarse
        lok, lghost = _found(t, fit, vox * np.array([1.0, 1.0, _LOOSE_Z]))
        out["found_z4"], out["ghosts_z4"] = 100 * lok.mean(), 100 * lghost.mean()
    for k in ("cand_found", "cand_ghosts", "truth_found", "truth_ghosts", "truth_kept", "truth_cpu"):
        out[k] = math.nan
    out["truth_ok"] = nan
    kw = dict(sc["reconstruct"].get("ipr", {}))
    kw.pop("blob_sigma", None)
    inputs = rc.ReconstructionInputs(lightfield=lf, centers=centers, camera=cam, grid=grid)
    out["var_found"] = out["var_ghosts"] = out["var_cpu"] = math.nan
    out["var_ok"] = nan
    if variant:  # the case's fit with some settings changed (from the MART candidates, as the case's)
        t0 = time.process_time()
        vfit = ipr_mod.ipr_particles(inputs, **{**kw, **variant})
        out["var_cpu"] = time.process_time() - t0
        vok, vghost = _found(t, np.column_stack([vfit[k].values for k in "xyz"]), vox)
        out["var_found"], out["var_ghosts"], out["var_ok"] = 100 * vok.mean(), 100 * vghost.mean(), vok
    if not truth:
        return out
    # the fit from the truth: the first candidate volume's peaks recorded, then replaced by the true positions
    seen: list[np.ndarray] = []
    peaks = ipr_candidates._peaks  # where the fit looks it up

    def truth_peaks(vol, g, threshold):
        seen.append(peaks(vol, g, threshold))
        return t.copy() if len(seen) == 1 else seen[-1]

    ipr_candidates._peaks = truth_peaks
    try:
        t0 = time.process_time()
        start = ipr_mod.ipr_particles(inputs, **{**kw, "residual_candidates": 0})
        out["truth_cpu"] = time.process_time() - t0
    finally:
        ipr_candidates._peaks = peaks
    cand_ok, cand_ghost = _found(t, seen[0], vox)
    out["cand_found"], out["cand_ghosts"], out["n_cand"] = 100 * cand_ok.mean(), 100 * cand_ghost.mean(), len(seen[0])
    sfit = np.column_stack([start[k].values for k in "xyz"])
    sok, sghost = _found(t, sfit, vox)
    out["truth_found"], out["truth_ghosts"], out["truth_ok"] = 100 * sok.mean(), 100 * sghost.mean(), sok
    out["truth_kept"] = 100 * len(sfit) / len(t)
    return out


def main() -> None:
    from bench_uncertainty import _run, _tasks, _written

    from lfstudy import io
    from lfstudy.config import read_yaml
    from lfstudy.study.config import stage_config, validate_config
    from lfstudy.study.sweep import Sweep

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=None, help="working directory (default: a temp dir)")
    ap.add_argument("--seed", type=int, default=None, help="study seed (default: the config's)")
    ap.add_argument(
        "--design", action="append", default=None, metavar="M:PITCH", help="keep this design (repeat; default: all)"
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-truth", action="store_true", help="the density figures only (no fit from the truth)")
    ap.add_argument("--variant", nargs="*", default=[], metavar="K=V", help="also the fit with these ipr settings")
    args = ap.parse_args()
    raw = read_yaml(args.config)
    if args.seed is not None:
        raw["seed"] = args.seed
    sweep = raw.setdefault("sweep", {})
    if "reconstruct.method" in sweep:  # the IPR cases (the case paths keep the swept setting)
        sweep["reconstruct.method"] = ["ipr"]
    elif raw.get("reconstruct", {}).get("method") != "ipr":
        raise SystemExit(f"{args.config}: reconstruct.method is not ipr and not swept: no IPR case to diagnose")
    sweep["flow"] = sweep.get("flow", [])[:1] or sweep.get("flow", [])
    cfg = validate_config(raw, base=args.config.resolve().parent)
    out = args.out or Path(tempfile.mkdtemp(prefix="lfstudy-bench-ipr-density-"))
    where = out / args.config.stem
    waves = _tasks(cfg, where)
    for wave in waves[:4]:  # up to the light fields (the case's own fit is scored where it is written)
        for label, fn, a in wave:
            if not _written(label, fn, a):
                print(f"  {_run(label, fn, a, args.threads)[1]:7.1f} s  {label}", flush=True)
    variant = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.variant)}
    sw = Sweep(cfg)
    rows = []
    for c in sw.cases():
        sc = stage_config(cfg, c, "reconstruct")
        m, p = float(sc["camera"]["magnification"]), float(sc["camera"]["lenslet"]["pitch"])
        if args.design and not any(
            math.isclose(m, float(d.split(":")[0])) and math.isclose(p, float(d.split(":")[1])) for d in args.design
        ):
            continue
        at = lambda name, c=c: where / sw.locate(c, name)  # noqa: E731
        d = diagnose(
            sc,
            io.open_array(at("lightfield_a.zarr")).load(),
            io.open_zarr(at("centers.zarr")).load(),
            io.open_zarr(at("particles_a.zarr")).load(),
            io.open_zarr(at("volume_a.particles.zarr")).load() if at("volume_a.particles.zarr").exists() else None,
            truth=not args.no_truth,
            variant=variant,
        )
        rows.append((f"M {m:g} p {p:g}", d))
    print(f"\n{args.config.stem}, seed {cfg['seed']}, frame a")
    print(
        f"{'design':<18}{'true':>6}{'/lens':>7}{'/vox':>7}{'dcell':>6}{'/cell':>6}{'spot':>6}{'r<=1%':>6}{'lit':>6}{'hid%':>6}{'for%':>6}"
        f"{'cand%':>7}{'cgh%':>6}{'found%':>7}{'gh%':>6}{'truth%':>7}{'tgh%':>6}{'kept%':>7}{'cpu':>6}"
    )
    for name, d in rows:
        print(
            f"{name:<18}{d['n']:6d}{d['per_lenslet']:7.2f}{d['per_voxel']:7.3f}{d['cells']:6.1f}{d['per_cell']:6.2f}"
            f"{d['spot']:6.2f}{d['small']:6.1f}{d['lit']:6.1f}"
            f"{100 * d['hidden']:6.1f}{100 * d['foreign']:6.1f}{d['cand_found']:7.1f}{d['cand_ghosts']:6.1f}"
            f"{d['found']:7.1f}{d['ghosts']:6.1f}{d['found_z4']:6.1f}{d['ghosts_z4']:6.1f}{d['truth_found']:7.1f}{d['truth_ghosts']:6.1f}"
            f"{d['truth_kept']:7.1f}{d['truth_cpu']:6.0f}{d['var_found']:7.1f}{d['var_ghosts']:6.1f}{d['var_cpu']:6.0f}"
        )
    if variant:
        print(f"variant: {variant}")
    print("\nfound % by depth band [mm] (the case's fit / from the truth / the variant)")
    for name, d in rows:
        edges = np.linspace(*d["zlim"], 5)
        edges[-1] += 1e-9
        head = " ".join(f"{a:.1f}-{b:.1f}" for a, b in itertools.pairwise(edges))
        print(f"{name:<18}{head}")
        for k in ("ok", "truth_ok", "var_ok"):
            print(f"{'':<18}{_bands(d['z'], d[k], edges)}")


if __name__ == "__main__":
    main()
