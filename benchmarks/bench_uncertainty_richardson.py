"""A two-window (Richardson) estimate of the PIV windows' own error, tested against the truth (issue 28).

WIDIM with ``levels: 2`` measures the field twice: with windows W1 (level 1) and W2 = W1/2 (the
final level). If each level's error is the top-hat response of its window to a smooth field,
B(W) ≈ Σ_j W_j²/24 ∂²u/∂x_j² (Raffel et al. 2018, *Particle Image Velocimetry* sec. 6.1), then
with r = W2/W1 on every axis u_final − u_level1 ≈ B_final (1 − 1/r²), and the final level's bias is

    b = (u_final − P u_level1) · r² / (r² − 1)          (= −(u_final − P u_level1) / 3 at r = 1/2),

Richardson's extrapolation (L. F. Richardson 1911, Phil. Trans. R. Soc. A 210 307) of the two
levels. ``P`` puts the level-1 field on the final grid: ``lin`` is the engine's multilinear
``dense_predictor`` (it adds its own curvature error, up to S1²/8 ∂²u between coarse nodes),
``cub`` a not-a-knot cubic spline per axis (no second-order error; linear on an axis with two
coarse vectors). The candidate σ is sqrt(σ² + b²).

This benchmark reads the level-1 field by wrapping :func:`lfstudy.piv.engine.dense_predictor` for
the duration of the run (the engine is unchanged) and prints, per case and component, for the
oracle (:func:`lfstudy.study.case.oracle_piv`, the case's PIV on the true volumes) and, given
reconstructed case directories, for the real PIV of their volumes (through the depth
calibration as the workflow applies it, P u_level1 mapped through it too):

* the RMS error, σ's coverage/ratio (:func:`lfstudy.study.metrics.uncertainty_calibration`);
* per interpolation ``lin`` / ``cub``: RMS of b, its correlation r with the error and the
  least-squares slope k of the error on b (k = 1: the right size), and the coverage/ratio of
  sqrt(σ² + b²), with RMS(sqrt(σ² + b²)) / RMS(σ) (``σx``: how much σ grows).

    python benchmarks/bench_uncertainty_richardson.py --cases DIR [DIR ...]
        [--extra-flow 'ring={kind: vortex_ring, ...}' ...]
    python benchmarks/bench_uncertainty_richardson.py --config config/thesis.yaml
        --set camera.sensor.n_pixels_x=1600 camera.sensor.n_pixels_y=1200 --flows uniform_x hill

``--cases``: leaf directories of a bench_uncertainty.py / workflow output (``piv.zarr`` and
``errors.zarr`` there, the volumes and particles in it or its parents); the case config is the
one stored with its ``errors.zarr``. ``--extra-flow``: oracle-only cases, each case's config with
its flow swapped (same particles). ``--config``: oracle-only cases of a config's sweep.
Each row also prints the truth's top-hat bias of the final window (``tophat``: its r, k against the
error) and ``ideal``: Richardson applied to the truth's own top-hat responses of both windows
against the final one's (no PIV: whether the flows are in the W² regime at all).

Findings (run 2026-11-26 on 2 cores at load 4-8; reconstructed volumes of earlier
bench_uncertainty.py runs, threshold reconstruction, depth-calibrated, re-run through today's PIV:
thesis camera cropped to 1200 x 900 px, final window 8 x 16 x 16 voxels, grid 7 x 5 x 8, level 1
2-4 vectors per axis, ppp 0.001 and 0.005; demo design M -1, p 0.0888, 640 x 480 px, final window
4 x 8 x 8 voxels, grid 7 x 9 x 12, ppp 0.005; the lamb_oseen and ring flows of
bench_uncertainty_resolution.py; r = 1/2 on every axis, so b = −(u_final − P u_level1)/3):

* Uniform motion: σ grows only x1.01-1.06 (``lin``; ``cub`` up to x1.12), but b there is the final
  level's own random error at −1/3 weight (r −0.72 to −0.99, k −2.5 to −3.2 against the error; the
  demo oracle's z, error 0.0008 mm: r −0.39, k −1.0).
* Gradient flows, oracle: b does not predict the error. Thesis Hill r +0.17-0.58 with k 0.8-2.6 (RMS
  b 3.7-7x smaller than the error, which the truth's top-hat predicts with r 0.93-0.98, k 1.0-1.2);
  thesis lamb_oseen (x, z; its y has no flow) and ring r −0.26 to +0.07; demo Hill and ring r
  +0.08-0.27 in x, y, lamb_oseen x r +0.36 but b 2.6x larger than the error (k 0.11). Only z on the
  demo's Hill and ring (lin, r +0.67-0.68) tracks it, and there the error is 2-4x the top-hat (the
  short z window).
* Gradient flows, real PIV: b is noise: r −0.63 to +0.22 (the negative ones in z, where the random
  error dominates).
* sqrt(σ² + b²): the thesis Hill oracle's coverage moves 0.06/0.22/0.25 → 0.09/0.31/0.40 (x/y/z),
  the real Hill 0.39/0.40 → 0.42/0.45 (x/y); larger gains (thesis ring oracle x 0.05 → 0.18) come
  from σ inflated x1.45-2.4 by a b uncorrelated with the error: a fudge, not a prediction; on the
  demo's real lamb_oseen it takes x out of the target band (0.61/0.95 → 0.82/0.53).
* Why: the flows are not in the W² regime of the level-1 window. Richardson on the truth's own
  top-hat responses (``ideal``, no PIV) gives the thesis Hill's final bias with r 0.55-0.76 and k
  2.1-8.5 (the level-1 window, 8 x 4 x 4 mm, is larger than the vortex of radius 1.5 mm), the thesis
  ring and lamb_oseen k 1.4-2.8; only the demo's smaller windows reach r 0.81-0.99, k 1.15-1.54. On
  top, the measured b follows the truth's top-hat at only r −0.08 to +0.75 (the level-1 field is a
  WIDIM field of 2-4 vectors per axis: iterative deformation with a filtered predictor, then
  interpolation), and the final level's noise enters at 1/3 weight. The cubic spline is no better
  than the engine's linear interpolation (with 2-4 coarse vectors per axis it extrapolates).

So the term is not wired into ``piv.uncertainty``: it leaves uniform σ alone but does not predict
the resolution error on any gradient flow tested.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
import yaml
from scipy.interpolate import CubicSpline

ROOT = Path(__file__).resolve().parents[1]
COMPS = (("x", "u"), ("y", "v"), ("z", "w"))
DIMS = ("z", "y", "x")


def _levels_of(run: Callable[[], xr.Dataset]) -> tuple[xr.Dataset, np.ndarray, list[np.ndarray]]:
    """Run a WIDIM call; return its result, the level-1 field (3, *coarse grid) [voxel] and its centres."""
    import lfstudy.piv.engine as eng

    calls: list[tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]] = []
    orig = eng.dense_predictor

    def probe(field: np.ndarray, centres: Any, points: Any) -> np.ndarray:
        calls.append(
            (np.array(field, dtype=float), [np.array(c, float) for c in centres], [np.array(p) for p in points])
        )
        return orig(field, centres, points)

    eng.dense_predictor = probe
    try:
        res = run()
    finally:
        eng.dense_predictor = orig
    final = [res[f"{d}_index"].values for d in DIMS]
    for field, c1, pts in reversed(calls):  # widim's call at the last level change
        if all(p.shape == f.shape and np.allclose(p, f) for p, f in zip(pts, final)):
            return res, field, c1
    raise RuntimeError("no level change recorded: the probe needs piv.levels >= 2")


def cubic_on(field: np.ndarray, centres: list[np.ndarray], points: list[np.ndarray]) -> np.ndarray:
    """A not-a-knot cubic spline per axis (linear with two nodes, constant with one), extrapolating."""
    out = field
    for ax, (c, p) in enumerate(zip(centres, points)):
        if c.size == 1:
            out = np.repeat(out, p.size, axis=ax + 1)
        elif c.size == 2:
            t = ((p - c[0]) / (c[1] - c[0])).reshape([-1 if i == ax + 1 else 1 for i in range(out.ndim)])
            lo, hi = np.take(out, [0], axis=ax + 1), np.take(out, [1], axis=ax + 1)
            out = lo + (hi - lo) * t
        else:
            out = CubicSpline(c, out, axis=ax + 1, bc_type="not-a-knot", extrapolate=True)(p)
    return out


def _as_mm(res: xr.Dataset, field: np.ndarray) -> xr.Dataset:
    """A copy of ``res`` whose displacements are ``field`` (3, z, y, x) [voxel], in mm as the engine does."""
    out = res.copy()
    for ax, (dim, comp) in enumerate(zip(DIMS, ("w", "v", "u"))):
        step = np.gradient(res[dim].values) / np.gradient(res[f"{dim}_index"].values)
        shp = [1, 1, 1]
        shp[ax] = -1
        out[comp] = (DIMS, field[ax])
        out[f"{comp}_mm"] = (DIMS, field[ax] * step.reshape(shp))
    return out


def richardson_terms(
    res: xr.Dataset, field1: np.ndarray, c1: list[np.ndarray], w1: list[int], depth: xr.Dataset | None
) -> dict[str, dict[str, np.ndarray]]:
    """b [mm] per interpolation (``lin``, ``cub``) and component (``x``, ``y``, ``z``), on (z, y, x)."""
    from lfstudy.piv.depth import correct_depth
    from lfstudy.piv.engine import dense_predictor

    w2 = [int(v) for v in res.attrs["final_window"]]
    r2 = np.array([(b / a) ** 2 for a, b in zip(w1, w2)])
    if not np.allclose(r2, r2[0]):
        raise ValueError(f"windows refine by different ratios per axis: {w1} -> {w2}")
    factor = r2[0] / (r2[0] - 1.0)
    c2 = [res[f"{d}_index"].values for d in DIMS]
    final = np.stack([res[c].transpose(*DIMS).values for c in ("w", "v", "u")])
    out = {}
    for name, interp in (("lin", dense_predictor), ("cub", cubic_on)):
        coarse = _as_mm(res, interp(field1, c1, c2))
        fine = _as_mm(res, final)
        if depth is not None:  # the depth map is not linear: map both fields, then difference
            coarse, fine = correct_depth(coarse, depth), correct_depth(fine, depth)
        out[name] = {ax: factor * (fine[f"{c}_mm"] - coarse[f"{c}_mm"]).transpose(*DIMS).values for ax, c in COMPS}
    return out


def _fit(err: np.ndarray, pred: np.ndarray, ok: np.ndarray) -> tuple[float, float]:
    m = ok & np.isfinite(pred)
    # a prediction of ~0 everywhere (a uniform flow's top-hat: rounding only) has no slope
    if m.sum() < 4 or np.sqrt(np.mean(pred[m] ** 2)) < 1e-6 * max(np.sqrt(np.mean(err[m] ** 2)), 1e-12):
        return np.nan, np.nan
    return float(np.corrcoef(err[m], pred[m])[0, 1]), float(err[m] @ pred[m] / (pred[m] @ pred[m]))


def tophat_truth(res: xr.Dataset, flow_spec: dict, window: list[int] | None = None) -> dict[str, np.ndarray]:
    """The truth averaged over a window (default: the final one) at each vector minus the truth at its
    centre [mm]: the top-hat bias of that window."""
    from lfstudy.simulate.flows import flow_from_config, true_displacement

    flow = flow_from_config(flow_spec)
    dt, n = flow_spec.get("dt", 1.0), flow_spec.get("n_steps", 100)
    win = [int(v) for v in (window or res.attrs["final_window"])]
    cz, cy, cx = (res[d].values for d in DIMS)
    vox = [float(np.median(np.gradient(res[d].values) / np.gradient(res[f"{d}_index"].values))) for d in DIMS]
    # midpoint rule over the window, at most 8 samples per axis
    offs = [((np.arange(min(w, 8)) + 0.5) / min(w, 8) - 0.5) * w * abs(v) for w, v in zip(win, vox)]
    oz, oy, ox = (g.ravel() for g in np.meshgrid(*offs, indexing="ij"))
    gz, gy, gx = np.meshgrid(cz, cy, cx, indexing="ij")
    shape = gz.shape
    pts = [(g[..., None] + o).ravel() for g, o in ((gx, ox), (gy, oy), (gz, oz))]
    box = [t.reshape(*shape, -1).mean(-1) for t in true_displacement(flow, *pts, dt=dt, n_steps=n)]
    ctr = true_displacement(flow, gx.ravel(), gy.ravel(), gz.ravel(), dt=dt, n_steps=n)
    return {ax: box[i] - ctr[i].reshape(shape) for i, ax in enumerate("xyz")}


def report(
    label: str, res: xr.Dataset, terms: dict[str, dict[str, np.ndarray]], flow_spec: dict, w1: list[int]
) -> list[str]:
    """The per-component lines of one PIV result."""
    from lfstudy.simulate.flows import flow_from_config
    from lfstudy.study.metrics import case_errors, uncertainty_calibration

    e = case_errors(
        res, flow_from_config(flow_spec), dt=flow_spec.get("dt", 1.0), n_steps=flow_spec.get("n_steps", 100)
    )
    th = tophat_truth(res, flow_spec)
    th1 = tophat_truth(res, flow_spec, w1)
    w2 = [int(v) for v in res.attrs["final_window"]]
    r2 = (w2[0] / w1[0]) ** 2
    lines = [f"  {label}: grid {tuple(res.sizes[d] for d in DIMS)}, final window {res.attrs['final_window']}"]
    for ax, c in COMPS:
        err = e[f"{c}_err_mm"].transpose(*DIMS).values
        sig = e[f"unc_{c}_mm"].transpose(*DIMS).values
        ok = np.isfinite(err) & np.isfinite(sig)
        cov, rat = uncertainty_calibration(err, sig, ok)
        rms = float(np.sqrt(np.mean(err[ok] ** 2)))
        s = f"    {ax}: rms err {rms:.4f} σ {np.sqrt(np.mean(sig[ok] ** 2)):.4f} cov/ratio {cov:4.2f}/{rat:4.2f}"
        r, k = _fit(err, th[ax], ok)
        s += f" | tophat {np.sqrt(np.mean(th[ax][ok] ** 2)):.4f} r{r:+.2f} k{k:+.2f}"
        # Richardson on the truth's own top-hat responses of both windows: does the W² regime hold?
        r, k = _fit(th[ax], (th[ax] - th1[ax]) * r2 / (r2 - 1.0), ok)
        if np.sqrt(np.mean(th[ax][ok] ** 2)) < 1e-9:  # no top-hat bias (a uniform flow): rounding only
            r = k = np.nan
        s += f" (ideal b~tophat r{r:+.2f} k{k:+.2f})"
        for name, per in terms.items():
            b = per[ax]
            r, k = _fit(err, b, ok)
            tot = np.sqrt(sig**2 + b**2)
            m = ok & np.isfinite(tot)
            cov2, rat2 = uncertainty_calibration(err, tot, m)
            grow = np.sqrt(np.mean(tot[m] ** 2) / np.mean(sig[m] ** 2))
            rt, _ = _fit(b, th[ax], m)  # does b follow the true top-hat bias (apart from noise)?
            s += (
                f" | {name} b {np.sqrt(np.mean(b[m] ** 2)):.4f} r{r:+.2f} k{k:+.2f} (b~tophat r{rt:+.2f})"
                f" -> {cov2:4.2f}/{rat2:4.2f} σx{grow:.2f}"
            )
        lines.append(s)
    return lines


def _open_up(leaf: Path, name: str, stop: Path) -> Path:
    """``name`` in ``leaf`` or its nearest parent that has it (a workflow's shared outputs)."""
    for d in (leaf, *leaf.parents):
        if (d / name).exists():
            return d / name
        if d == stop:
            break
    raise FileNotFoundError(f"{name} not found above {leaf}")


def _depth_of(leaf: Path, case_id: str) -> xr.Dataset | None:
    """The case's depth calibration where its PIV was depth-corrected (the calib tree of the workflow)."""
    from lfstudy import io

    piv = io.open_zarr(leaf / "piv.zarr")
    if "w_mm_uncorrected" not in piv:
        return None
    root = leaf
    for _ in case_id.split("/"):
        root = root.parent
    parts = case_id.split("/")
    keep = [p for p in parts if not p.startswith("flow~")]
    for n in range(len(keep), 0, -1):
        cand = root / "calib" / Path(*keep[:n]) / "depth_calibration.zarr"
        if cand.exists():
            return io.open_zarr(cand).load()
    raise FileNotFoundError(f"{leaf}: its PIV is depth-corrected, but no depth_calibration.zarr under {root}/calib")


_DONE: set[str] = set()


def run_case_dir(leaf: Path, extra: dict[str, dict]) -> list[str]:
    """Real PIV of a reconstructed case and its oracle (plus oracle-only cases with the extra flows)."""
    from lfstudy import io
    from lfstudy.study import case as cl

    ccfg = json.loads(io.open_zarr(leaf / "errors.zarr").attrs["parameters"])
    if "illumination" not in ccfg:  # an output of a version before the section: its default
        from lfstudy.config import read_yaml
        from lfstudy.study.config import validate_config

        ccfg["illumination"] = validate_config(read_yaml(ROOT / "config" / "thesis.yaml"))["illumination"]
    stop = leaf
    for _ in ccfg["case_id"].split("/"):
        stop = stop.parent
    depth = _depth_of(leaf, ccfg["case_id"])
    w1 = list(ccfg["piv"]["window"])
    va = io.open_array(_open_up(leaf, "volume_a.zarr", stop)).load()
    vb = io.open_array(_open_up(leaf, "volume_b.zarr", stop)).load()
    pa = io.open_zarr(_open_up(leaf, "particles_a.zarr", stop)).load()
    pb = io.open_zarr(_open_up(leaf, "particles_b.zarr", stop)).load()
    lines = [f"{ccfg['case_id']}{' (depth-calibrated)' if depth is not None else ''}"]
    t0 = time.perf_counter()
    res, f1, c1 = _levels_of(lambda: cl.case_piv(ccfg, va, vb))
    secs = time.perf_counter() - t0
    if depth is not None:
        from lfstudy.piv.depth import correct_depth

        terms = richardson_terms(res, f1, c1, w1, depth)
        res = correct_depth(res, depth)
    else:
        terms = richardson_terms(res, f1, c1, w1, None)
    lines += report(f"real PIV ({secs:.1f} s)", res, terms, ccfg["flow"], w1)
    o, f1, c1 = _levels_of(lambda: cl.oracle_piv(ccfg, pa, pb))
    lines += report("oracle", o, richardson_terms(o, f1, c1, w1, None), ccfg["flow"], w1)
    key = str(_open_up(leaf, "particles_a.zarr", stop))
    if key in _DONE:  # the extra flows of these particles ran already (another flow of the same seeding)
        return lines
    _DONE.add(key)
    for name, spec in extra.items():
        cc = dict(ccfg, flow={"name": name, **spec})
        o, f1, c1 = _levels_of(lambda cc=cc: cl.oracle_piv(cc, pa, cl.case_displaced(cc, pa)))
        lines += report(f"oracle, flow {name}", o, richardson_terms(o, f1, c1, w1, None), cc["flow"], w1)
    return lines


def run_config(args: argparse.Namespace) -> list[str]:
    """Oracle-only cases of a config's sweep (first design, the given flows and ppp)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_uncertainty_resolution import _config

    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config
    from lfstudy.study.sweep import Sweep

    cfg = _config(args)
    lines = []
    for case in Sweep(cfg).cases():
        cc = case_config(cfg, case)
        pa = cl.case_particles(cc)
        pb = cl.case_displaced(cc, pa)
        o, f1, c1 = _levels_of(lambda cc=cc, pa=pa, pb=pb: cl.oracle_piv(cc, pa, pb))
        lines.append(case.case_id)
        w1 = list(cc["piv"]["window"])
        lines += report("oracle", o, richardson_terms(o, f1, c1, w1, None), cc["flow"], w1)
        print("\n".join(lines[-4:]), flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", type=Path, default=[], help="reconstructed case directories")
    ap.add_argument("--extra-flow", nargs="*", default=[], metavar="NAME=SPEC", help="oracle-only flows (YAML)")
    ap.add_argument("--config", type=Path, default=None, help="oracle-only cases of this config")
    ap.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE", help="config overrides (YAML values)")
    ap.add_argument("--flows", nargs="*", default=["uniform_x", "hill"], help="the config's flows")
    ap.add_argument("--add-flow", nargs="*", default=[], metavar="NAME=SPEC", help="a flow added to the config")
    ap.add_argument("--ppp", nargs="*", type=float, default=None, help="seeding densities (default: the config's)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    extra = {}
    for item in args.extra_flow:
        name, _, spec = item.partition("=")
        extra[name] = yaml.safe_load(spec)
    for leaf in args.cases:
        print("\n".join(run_case_dir(leaf, extra)), flush=True)
    if args.config is not None:
        run_config(args)
    print(f"all cases {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
