"""Diagnosis of the lateral → axial crosstalk of the MART chain (issue 27, part 2).

Reproduces: docs/conventions.md § "What a voxel is" (the demo design M -0.8, pitch 0.1184: the raw w of a 0.2
mm x shift and |w| of PIV on the numerically shifted volume: ``--magnification -0.8 --pitch 0.1184 --variants
shifta``; rerun 2026-11-28, seed 7, 1 thread, load ~17 on 2 cores, 290 s: w +0.0576 mm raw, 0.288 of the
shift, against the page's +0.060; +0.0005 mm on the shifted volume; the oracle's +0.0037 mm).

One design (a demo or thesis config, with ``--magnification`` / ``--pitch`` set), one uniform
lateral shift (``--shift`` mm at ``--angle`` degrees from +x) and a sub-lenslet phase of the particle
field (``--phase PX PY``, fractions of one lenslet at the focal plane, pl/|M|) run through the case
layer in memory (no Snakemake): particles → images → calibration → registration → focal stack →
MART → PIV, beside the oracle (the same PIV on the true volumes). Then the variants that isolate
each candidate cause:

- ``elong``: the oracle with blobs as elongated as the reconstruction's (their sigma per axis read
  from the MART volume's autocorrelation): PIV on particles elongated in z;
- ``shifta``: frame a's reconstruction shifted numerically (cubic spline) by the true lateral shift
  as frame b: reconstruction shape and PIV without the imaging of moved particles;
- ``centroids``: every true particle matched to the reconstruction (intensity-weighted centroid in
  a box around it): the mean z error per frame and its trend with x, y and the sub-lenslet phase
  (the "pull toward lenslet centres" predicts a z error that follows the phase);
- ``piv``: the case's volumes with other PIV settings (single level, no predictor filter,
  smaller windows);
- ``mart``: other MART settings (no smoothing, init from the focal stack, more iterations);
- ``ipr``: the pair mode of IPR against MART: both frames reconstructed by ``reconstruct.method: ipr``
  (its ``reconstruct.ipr`` settings, from the same light fields) and PIV'd with the case's settings,
  beside MART and the oracle; plus IPR's particles matched to the true ones (found / ghosts within half a
  voxel, mean and rms z error per band of true |z|, and the mean z error of frame b minus frame a,
  the particle-level crosstalk), the PIV on IPR's particles without its ghosts, and one ``PAIR`` line per
  method for tables.

Printed in mm and as fractions of the lateral shift: mean u, v, w, the crosstalk (mean w − w_true
over |lateral shift|), RMS per component and total, and the valid fraction. Kept small (the demo
sensor, or ``--sensor W H`` for a crop of the thesis camera) so one run takes about a minute on
two cores.

    python benchmarks/bench_crosstalk.py [--config config/demo.yaml] [--magnification -0.8]
        [--pitch 0.1184] [--shift 0.2] [--angle 0] [--phase 0 0] [--seed 7] [--sensor W H]
        [--variants elong shifta centroids piv mart]
"""

from __future__ import annotations

import argparse
import copy
import math
import pickle
import time
from pathlib import Path

import numpy as np
import xarray as xr
from scipy import ndimage

from lfstudy.config import read_yaml
from lfstudy.lightfield.calibrate import find_lenslet_centers
from lfstudy.simulate.flows import flow_from_config
from lfstudy.study import case as cl
from lfstudy.study.config import case_config, sweep_of, validate_config
from lfstudy.study.metrics import case_errors, render_truth

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("elong", "shifta", "centroids", "piv", "mart", "phase", "ipr")


def build_config(args: argparse.Namespace) -> dict:
    """The case config of one design and one lateral shift (depth calibration off)."""
    cfg = read_yaml(args.config)
    cfg = copy.deepcopy(cfg)
    cam = cfg["camera"]
    if args.magnification is not None:
        cam["magnification"] = args.magnification
    if args.pitch is not None:
        cam["lenslet"]["pitch"] = args.pitch
    if args.sensor:
        cam["sensor"]["n_pixels_x"], cam["sensor"]["n_pixels_y"] = args.sensor
    if args.ppp is not None:
        cfg["particles"]["ppp"] = args.ppp
    if args.rays is not None:
        cfg["raytrace"]["rays_per_particle"] = args.rays
    cfg["seed"] = args.seed
    if args.no_diffraction:
        cfg["raytrace"]["diffraction"] = False
    if args.no_shot_noise:
        cfg.setdefault("sensor", {})["shot_noise"] = False
    a = math.radians(args.angle)
    cfg["flows"] = {
        "lateral": {"kind": "uniform", "displacement": [args.shift * math.cos(a), args.shift * math.sin(a), 0]}
    }
    cfg["sweep"] = {"flow": ["lateral"]}
    cfg.setdefault("depth_calibration", {})["enabled"] = False
    if args.z_range:
        cfg.setdefault("grid", {})["z_range"] = list(args.z_range)
    if args.xy_refine > 1:  # finer voxels, the same PIV windows in mm
        c = validate_config(copy.deepcopy(cfg))
        cam0 = cl.case_camera(case_config(c, sweep_of(c).cases()[0]))
        k = args.xy_refine
        cfg.setdefault("grid", {})["voxel_xy"] = cam0.lenslet_pitch / abs(cam0.magnification) / k
        piv = cfg.setdefault("piv", {})
        piv["window"] = [piv["window"][0], *(w * k for w in piv["window"][1:])]
        piv["spacing"] = [piv["spacing"][0], *(s * k for s in piv["spacing"][1:])]
    if args.voxel_z:
        cfg.setdefault("grid", {})["voxel_z"] = args.voxel_z
    cfg = validate_config(cfg)
    return case_config(cfg, sweep_of(cfg).cases()[0])


def summary(piv: xr.Dataset, ccfg: dict) -> dict[str, float]:
    """Mean measured u, v, w [mm], crosstalk, RMS per axis and total [mm], valid % of a PIV result."""
    err = case_errors(piv, flow_from_config(ccfg["flow"]))
    out = {k: float(err[k]) for k in ("mean_x_mm", "mean_y_mm", "mean_z_mm", "crosstalk_z", "valid_percent")}
    out.update({k: float(err[k]) for k in ("rms_x_mm", "rms_y_mm", "rms_z_mm", "rms_total_mm")})
    return out


def show(label: str, s: dict[str, float], lateral: float) -> None:
    w = s["mean_z_mm"]
    print(
        f"  {label:<34s} u {s['mean_x_mm']:+.4f} v {s['mean_y_mm']:+.4f} w {w:+.4f} mm "
        f"(w/|s| {s['crosstalk_z']:+.3f}) | rms x {s['rms_x_mm']:.4f} y {s['rms_y_mm']:.4f} "
        f"z {s['rms_z_mm']:.4f} tot {s['rms_total_mm']:.4f} mm | valid {s['valid_percent']:.0f} %",
        flush=True,
    )


def profile(piv: xr.Dataset, disp) -> None:
    """Where the spurious w lives: mean w − w_true [mm] of the valid vectors per x column and per z row."""
    w = piv["w_mm"].where(piv["valid"]) - disp[2]
    print("    w by x [mm]: " + " ".join(f"{v:+.3f}" for v in w.mean(("z", "y")).values))
    print("    w by y [mm]: " + " ".join(f"{v:+.3f}" for v in w.mean(("z", "x")).values))
    print("    w by z [mm]: " + " ".join(f"{v:+.3f}" for v in w.mean(("y", "x")).values))


def blob_sigma(vol: np.ndarray, steps: tuple[float, float, float]) -> tuple[float, float, float]:
    """Sigma (z, y, x) [mm] of the volume's blobs: the autocorrelation's central peak as a Gaussian.

    The autocorrelation of Gaussian blobs of sigma s is a Gaussian of s·sqrt(2); its curvature at 0
    (three-point log fit per axis) gives s for blobs that do not overlap much.
    """
    v = vol - vol.mean()
    shape, axes = [2 * n for n in v.shape], (0, 1, 2)
    ac = np.fft.irfftn(np.abs(np.fft.rfftn(v, s=shape, axes=axes)) ** 2, s=shape, axes=axes)
    c0 = ac[0, 0, 0]
    out = []
    for ax, step in enumerate(steps):
        idx = [0, 0, 0]
        idx[ax] = 1
        c1 = ac[tuple(idx)]
        r = c1 / c0
        # Gaussian: r = exp(-step² / (4 s²))
        s = step / (2.0 * math.sqrt(-math.log(r))) if 0 < r < 1 else float("nan")
        out.append(s)
    return tuple(out)


def centroid_errors(vol: xr.DataArray, particles: xr.Dataset, box: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """Intensity-weighted centroid of ``vol`` in a box around every true particle inside the grid.

    Returns the true x, y, z [mm] of the matched particles and the centroid errors dx, dy, dz [mm].
    """
    z, y, x = (np.asarray(vol[d].values, float) for d in ("z", "y", "x"))
    data = np.asarray(vol.values, float)
    px, py, pz = (np.asarray(particles[d].values, float) for d in ("x", "y", "z"))
    steps = (z[1] - z[0], y[1] - y[0], x[1] - x[0])
    fi = [(p - c[0]) / s for p, c, s in zip((pz, py, px), (z, y, x), steps)]
    keep = np.ones(px.size, bool)
    for f, n, b in zip(fi, data.shape, box):
        keep &= (f >= b) & (f <= n - 1 - b)
    rows = {k: [] for k in ("x", "y", "z", "dx", "dy", "dz")}
    for i in np.flatnonzero(keep):
        c = [round(f[i]) for f in fi]
        sl = tuple(slice(ci - b, ci + b + 1) for ci, b in zip(c, box))
        w = data[sl]
        tot = w.sum()
        if tot <= 0:
            continue
        g = np.meshgrid(z[sl[0]], y[sl[1]], x[sl[2]], indexing="ij")
        cz, cy, cx = ((w * gi).sum() / tot for gi in g)
        rows["x"].append(px[i])
        rows["y"].append(py[i])
        rows["z"].append(pz[i])
        rows["dx"].append(cx - px[i])
        rows["dy"].append(cy - py[i])
        rows["dz"].append(cz - pz[i])
    return {k: np.asarray(v) for k, v in rows.items()}


def trend(values: np.ndarray, along: np.ndarray) -> float:
    """Least-squares slope of values against ``along``."""
    if values.size < 3:
        return float("nan")
    return float(np.polyfit(along, values, 1)[0])


def lattice(template: xr.Dataset, grid, d: float, phase: float, depths: np.ndarray, step: int = 6) -> xr.Dataset:
    """Isolated particles every ``step`` voxels in x, y (all at one sub-lenslet x phase), depths cycled."""
    gx = grid.x[step // 2 : -step // 2 : step] + phase * d
    gy = grid.y[step // 2 : -step // 2 : step]
    x, y = (v.ravel() for v in np.meshgrid(gx, gy))
    z = np.resize(depths, x.size)
    n = x.size
    return xr.Dataset(
        {k: ("particle", v) for k, v in (("x", x), ("y", y), ("z", z), ("intensity", np.ones(n)))},
        coords={"particle": np.arange(n)},
        attrs=template.attrs,
    )


def column_z(vol: np.ndarray, grid, p: xr.Dataset, half: int = 2) -> np.ndarray:
    """z centroid [mm] of the whole depth column +-half voxels around each isolated particle."""
    out = []
    for x, y in zip(p["x"].values, p["y"].values):
        i, j = round((x - grid.x[0]) / grid.dx), round((y - grid.y[0]) / grid.dy)
        col = vol[:, max(0, j - half) : j + half + 1, max(0, i - half) : i + half + 1].sum((1, 2))
        out.append(float((col * grid.z).sum() / col.sum()) if col.sum() > 0 else np.nan)
    return np.asarray(out)


def phase_scan(ccfg: dict, template: xr.Dataset, centers: xr.Dataset, model: bool) -> None:
    """Depth error of isolated particles against their sub-lenslet x phase, per true depth.

    ``model``: the light field is the projector's own forward model of the true volume (no
    imaging mismatch; what is left is MART's); else the case's renderer and sensor.
    """
    from lfstudy.lightfield.registration import register
    from lfstudy.reconstruct.projector import PlenopticProjector

    cam = cl.case_camera(ccfg)
    grid = cl.case_grid(ccfg, cam)
    d = cam.lenslet_pitch / abs(cam.magnification)
    depths = np.array([-1.5, -1.0, -0.5, -0.2, 0.0, 0.2, 0.5, 1.0, 1.5])
    phases = np.linspace(0.0, 0.875, 8)
    rows = []
    proj = lf0 = None
    for ph in phases:
        p = lattice(template, grid, d, ph, depths)
        if model:
            if proj is None:
                lf0 = register(cl.case_image(ccfg, p, "a"), centers, cam)
                proj = PlenopticProjector(lf0, cam, grid)
            sig = [0.25 * float(grid.voxel_size()[0]), 0.25 * grid.dy, 0.25 * grid.dx]
            truth = render_truth({"z": grid.z, "y": grid.y, "x": grid.x}, p, sigma_mm=sig)
            lf = lf0.copy(data=proj.forward(truth).astype(np.float32))
            vol = cl.case_volume(ccfg, None, lf, centers).values
        else:
            vol = cl.render_volume(cl.case_image(ccfg, p, "a"), centers, ccfg)[2].values
        ez = column_z(vol, grid, p) - p["z"].values
        rows.append([np.nanmean(ez[p["z"].values == z0]) for z0 in depths])
    rows = np.asarray(rows)
    src = "projector model" if model else "rendered images"
    print(f"  isolated particles ({src}): mean z error [mm] per x phase (rows, lenslets) and true z (columns)")
    print("    phase \\ z " + " ".join(f"{z0:+7.2f}" for z0 in depths))
    for ph, r in zip(phases, rows):
        print(f"    {ph:9.3f} " + " ".join(f"{v:+7.3f}" for v in r))
    print("    p-p      " + " ".join(f"{v:7.3f}" for v in np.ptp(rows, axis=0)))


def ipr_frames(ccfg: dict, lfs: dict, centers: xr.Dataset) -> tuple[dict, dict]:
    """Both frames by ``ipr`` with the case's ``reconstruct.ipr`` settings: the particle lists and the volumes.

    The same two steps as the method (:func:`lfstudy.reconstruct.ipr.ipr`), kept apart to score the particles.
    """
    from lfstudy.reconstruct import ReconstructionInputs
    from lfstudy.reconstruct.ipr import ipr_particles, render_particles

    cam = cl.case_camera(ccfg)
    grid = cl.case_grid(ccfg, cam)
    kw = dict(ccfg["reconstruct"].get("ipr", {}))
    blob = float(kw.pop("blob_sigma", 0.0))
    parts, vols = {}, {}
    for f in ("a", "b"):
        inp = ReconstructionInputs(lightfield=lfs[f], centers=centers, camera=cam, grid=grid)
        parts[f] = ipr_particles(inp, **kw)
        vol, _ = render_particles(parts[f], grid, cam, blob)
        vols[f] = grid.volume(vol.astype(np.float32))
    return parts, vols


def match_particles(true: xr.Dataset, fit: xr.Dataset, grid) -> dict[str, np.ndarray | float]:
    """True particles inside the grid matched to the nearest fitted one (per-axis voxel units).

    Returns found % and ghost % (within half a voxel), the true z and the z error of the found ones, and
    the indices of the fitted particles that are no ghosts.
    """
    from scipy.spatial import cKDTree

    dz, dy, dx = grid.voxel_size()
    vox = np.array([dx, dy, dz])
    t = np.column_stack([true[v].values for v in ("x", "y", "z")])
    lo = np.array([grid.x[0], grid.y[0], grid.z[0]]) - vox / 2
    hi = np.array([grid.x[-1], grid.y[-1], grid.z[-1]]) + vox / 2
    t = t[np.all((t >= lo) & (t <= hi), axis=1)]
    f = np.column_stack([fit[v].values for v in ("x", "y", "z")])
    d_t, j = cKDTree(f / vox).query(t / vox)
    d_f, _ = cKDTree(t / vox).query(f / vox)
    ok = d_t < 0.5
    return {
        "found": 100.0 * ok.mean(),
        "ghosts": 100.0 * (d_f >= 0.5).mean(),
        "z": t[ok, 2],
        "ez": f[j[ok], 2] - t[ok, 2],
        "n_true": len(t),
        "n_fit": len(f),
        "fit_found": np.flatnonzero(d_f < 0.5),
    }


def ipr_pair(ccfg: dict, pa, pb, lfs: dict, centers, mart_piv: xr.Dataset, oracle_piv: xr.Dataset, tag: str) -> None:
    """IPR against MART and the oracle on the same light fields (the ``ipr`` variant)."""
    cam = cl.case_camera(ccfg)
    grid = cl.case_grid(ccfg, cam)
    disp = ccfg["flow"]["displacement"]
    lateral = math.hypot(disp[0], disp[1])
    t0 = time.perf_counter()
    parts, vols = ipr_frames(ccfg, lfs, centers)
    t_ipr = time.perf_counter() - t0
    piv = cl.case_piv(ccfg, vols["a"], vols["b"])
    s_ipr = summary(piv, ccfg)
    show(f"IPR ({t_ipr:.0f} s, both frames)", s_ipr, lateral)
    profile(piv, disp)
    m = {}
    for f, p in (("a", pa), ("b", pb)):
        m[f] = mm = match_particles(p, parts[f], grid)
        az = np.abs(mm["z"])
        parts_txt = []
        for lo, hi in ((0.0, 0.5), (0.5, 1.0), (1.0, np.inf)):
            e = mm["ez"][(az >= lo) & (az < hi)]
            mean, rms = (e.mean(), np.sqrt(np.mean(e**2))) if e.size else (np.nan, np.nan)
            parts_txt.append(f"|z| {lo:g}-{hi:g}: n {e.size} mean {mean:+.4f} rms {rms:.4f}")
        txt = ", ".join(parts_txt)
        print(
            f"    IPR frame {f}: {mm['n_true']} true in grid, {mm['n_fit']} fitted; found {mm['found']:.1f} %, "
            f"ghosts {mm['ghosts']:.1f} %; z error [mm] {txt}"
        )
    # the PIV on the fitted particles that have a true one within half a voxel (the ghosts left out)
    from lfstudy.reconstruct.ipr import render_particles

    blob = float(ccfg["reconstruct"].get("ipr", {}).get("blob_sigma", 0.0))
    real = {}
    for f in ("a", "b"):
        near = m[f]["fit_found"]
        real[f] = grid.volume(render_particles(parts[f].isel(particle=near), grid, cam, blob)[0].astype(np.float32))
    show("IPR without its ghosts", summary(cl.case_piv(ccfg, real["a"], real["b"]), ccfg), lateral)
    dzm = m["b"]["ez"].mean() - m["a"]["ez"].mean()
    print(f"    IPR particles: mean z error b - a {dzm:+.4f} mm ({dzm / lateral:+.3f} of the shift)")
    fg = f" found {m['a']['found']:.0f}/{m['b']['found']:.0f} ghosts {m['a']['ghosts']:.0f}/{m['b']['ghosts']:.0f}"
    for label, r in (("mart", summary(mart_piv, ccfg)), ("ipr", s_ipr), ("oracle", summary(oracle_piv, ccfg))):
        print(
            f"PAIR {tag} {label} u {r['mean_x_mm']:+.4f} v {r['mean_y_mm']:+.4f} w {r['mean_z_mm']:+.4f} "
            f"w/s {r['crosstalk_z']:+.3f} rms {r['rms_total_mm']:.4f} valid {r['valid_percent']:.0f}"
            + (fg if label == "ipr" else ""),
            flush=True,
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "config" / "demo.yaml"), help="study config (demo or thesis)")
    ap.add_argument("--magnification", type=float, default=None, help="M (default: the config's)")
    ap.add_argument("--pitch", type=float, default=None, help="lenslet pitch [mm] (default: the config's)")
    ap.add_argument("--shift", type=float, default=0.2, help="lateral shift magnitude [mm]")
    ap.add_argument("--angle", type=float, default=0.0, help="shift direction [deg] from +x towards +y")
    ap.add_argument("--phase", type=float, nargs=2, default=(0.0, 0.0), metavar=("PX", "PY"),
                    help="offset of the particle field [lenslets at the focal plane, pl/|M|]")  # fmt: skip
    ap.add_argument("--seed", type=int, default=7, help="study seed (particles, rays)")
    ap.add_argument("--sensor", type=int, nargs=2, default=None, metavar=("W", "H"), help="sensor crop [px]")
    ap.add_argument("--ppp", type=float, default=None, help="particles per pixel (default: the config's)")
    ap.add_argument("--rays", type=int, default=None, help="rays per particle (default: the config's)")
    ap.add_argument("--no-diffraction", action="store_true", help="render without diffraction")
    ap.add_argument("--no-shot-noise", action="store_true", help="sensor without shot noise")
    ap.add_argument("--xy-refine", type=int, default=1, help="x, y voxels of pl/|M|/K, PIV windows K times wider")
    ap.add_argument("--z-range", type=float, nargs=2, default=None, help="grid.z_range [mm]")
    ap.add_argument("--voxel-z", type=float, default=None, help="grid.voxel_z [mm]")
    ap.add_argument("--cache", default=None, help="pickle of the particles, light fields and volumes (reused)")
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=VARIANTS, help="diagnostics to run")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    ccfg = build_config(args)
    cam = cl.case_camera(ccfg)
    grid = cl.case_grid(ccfg, cam)
    d = cam.lenslet_pitch / abs(cam.magnification)
    disp = ccfg["flow"]["displacement"]
    lateral = math.hypot(disp[0], disp[1])
    print(
        f"design M {cam.magnification:g}, pitch {cam.lenslet_pitch:g} mm (pl/|M| {d:.4f} mm), sensor "
        f"{cam.n_pixels_x}x{cam.n_pixels_y}; grid {grid.shape} dx {grid.dx:.4f} dz {grid.voxel_size()[0]:.4f} mm; "
        f"shift ({disp[0]:+.4f}, {disp[1]:+.4f}) mm = {disp[0] / grid.dx:+.3f}, {disp[1] / grid.dy:+.3f} vox; "
        f"phase {args.phase}; seed {args.seed}",
        flush=True,
    )
    cache = Path(args.cache) if args.cache else None
    if cache is not None and cache.is_file():
        with cache.open("rb") as fh:
            pa, pb, centers, lfs, stacks, vols = pickle.load(fh)
    else:
        pa = cl.case_particles(ccfg)
        pa = pa.assign(x=pa["x"] + args.phase[0] * d, y=pa["y"] + args.phase[1] * d)
        pb = cl.case_displaced(ccfg, pa)
        centers = find_lenslet_centers(cl.case_pinhole(ccfg), cam)
        vols, lfs, stacks = {}, {}, {}
        for f, p in (("a", pa), ("b", pb)):
            lfs[f], stacks[f], vols[f] = cl.render_volume(cl.case_image(ccfg, p, f), centers, ccfg)
            lfs[f], stacks[f], vols[f] = lfs[f].load(), stacks[f].load(), vols[f].load()
        if cache is not None:
            with cache.open("wb") as fh:
                pickle.dump((pa, pb, centers, lfs, stacks, vols), fh)
    print(f"  [{pa.sizes['particle']} particles; imaged and reconstructed in {time.perf_counter() - t0:.0f} s]")
    piv = cl.case_piv(ccfg, vols["a"], vols["b"])
    case = summary(piv, ccfg)
    show("case (MART)", case, lateral)
    profile(piv, disp)
    oa, ob = cl.oracle_volumes(ccfg, pa, pb)
    opiv = cl.case_piv(ccfg, oa, ob)
    show("oracle (true volumes)", summary(opiv, ccfg), lateral)
    if "ipr" in args.variants:
        tag = f"M{cam.magnification:g}/pl{cam.lenslet_pitch:g}/a{args.angle:g}/s{args.seed}"
        ipr_pair(ccfg, pa, pb, lfs, centers, piv, opiv, tag)

    steps = (float(grid.voxel_size()[0]), grid.dy, grid.dx)
    if "elong" in args.variants:
        sig_r = blob_sigma(vols["a"].values, steps)
        sig_t = blob_sigma(oa.values, steps)
        print(f"  blob sigma z,y,x [mm]: reconstruction {np.round(sig_r, 4)}, oracle {np.round(sig_t, 4)}")
        true_sig = cl.truth_sigma(cam)
        # deconvolve the oracle's own voxel integration: scale the true sigma by the measured ratio
        sig = tuple(ts * r / t for ts, r, t in zip(true_sig, sig_r, sig_t))
        coords = {"z": grid.z, "y": grid.y, "x": grid.x}
        ea, eb = (grid.volume(render_truth(coords, p, sigma_mm=sig).astype(np.float32)) for p in (pa, pb))
        show("oracle, blobs elongated like MART", summary(cl.case_piv(ccfg, ea, eb), ccfg), lateral)
    if "shifta" in args.variants:
        sh = (0.0, disp[1] / grid.dy, disp[0] / grid.dx)
        sa = grid.volume(ndimage.shift(vols["a"].values, sh, order=3, mode="nearest").astype(np.float32))
        show("MART a vs a shifted numerically", summary(cl.case_piv(ccfg, vols["a"], sa), ccfg), lateral)
        so = grid.volume(ndimage.shift(oa.values, sh, order=3, mode="nearest").astype(np.float32))
        show("oracle a vs a shifted numerically", summary(cl.case_piv(ccfg, oa, so), ccfg), lateral)
    if "centroids" in args.variants:
        nz = max(1, round(2 * sig_r[0] / steps[0])) if "elong" in args.variants else 3
        box = (nz, 1, 1)
        print(f"  centroids in a box of +-{box} voxels (z, y, x) around each true particle:")
        res = {}
        for f, p in (("a", pa), ("b", pb)):
            e = centroid_errors(vols[f], p, box)
            res[f] = e
            ph = np.mod(e["x"] / d + 0.5, 1.0) - 0.5  # x phase w.r.t. the voxel centres, in voxels
            print(
                f"    frame {f}: n {e['dz'].size}, mean dz {e['dz'].mean():+.4f} mm, dx {e['dx'].mean():+.4f}, "
                f"dy {e['dy'].mean():+.4f}; slope dz/dx {trend(e['dz'], e['x']):+.4f}, dz/dy "
                f"{trend(e['dz'], e['y']):+.4f}, dz/dz {trend(e['dz'], e['z']):+.4f} (1/1), "
                f"dz vs x-phase {trend(e['dz'], ph):+.4f} mm/voxel"
            )
            bins = np.linspace(-0.5, 0.5, 5)
            k = np.digitize(ph, bins) - 1
            print("      mean dz per x-phase quarter: " + ", ".join(f"{e['dz'][k == i].mean():+.4f}" for i in range(4)))
        print(
            f"    mean dz(b) - dz(a) = {res['b']['dz'].mean() - res['a']['dz'].mean():+.4f} mm "
            f"({(res['b']['dz'].mean() - res['a']['dz'].mean()) / lateral:+.3f} of the shift)"
        )
    if "piv" in args.variants:
        base = dict(ccfg["piv"])
        for label, change in (
            ("PIV one level", {"levels": 1}),
            ("PIV no predictor filter", {"predictor_filter": 0.0}),
            (
                "PIV windows halved in x, y",
                {
                    "window": [base["window"][0], *(max(4, w // 2) for w in base["window"][1:])],
                    "spacing": [base["spacing"][0], *(max(2, s // 2) for s in base["spacing"][1:])],
                },
            ),
        ):
            c2 = {**ccfg, "piv": {**base, **change}}
            show(label, summary(cl.case_piv(c2, vols["a"], vols["b"]), c2), lateral)
    if "mart" in args.variants:
        base = dict(ccfg["reconstruct"].get("mart", {}))
        for label, change in (
            ("MART no smoothing", {"smoothing": 0.0}),
            ("MART init stack", {"init": "stack"}),
            ("MART 10 iterations", {"iterations": 10}),
        ):
            c2 = {**ccfg, "reconstruct": {**ccfg["reconstruct"], "mart": {**base, **change}}}
            va, vb = (cl.case_volume(c2, stacks[f], lfs[f], centers).load() for f in ("a", "b"))
            show(label, summary(cl.case_piv(c2, va, vb), c2), lateral)
    if "phase" in args.variants:
        phase_scan(ccfg, pa, centers, model=False)
        phase_scan(ccfg, pa, centers, model=True)
    print(f"  [total {time.perf_counter() - t0:.0f} s]")


if __name__ == "__main__":
    main()
