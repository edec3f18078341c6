"""What the oracle's error is made of, and which per-vector terms could predict it (issue 28).

The study's per-vector uncertainty (``piv.uncertainty``, :mod:`lfstudy.piv.uncertainty`) misses
where the PIV windows filter a velocity gradient. This benchmark runs the *oracle* of study cases
(the case's PIV on the true particle volumes, :func:`lfstudy.study.case.oracle_piv`: seconds per
case, no imaging or reconstruction) and prints, per case and component (mm):

* the oracle's own coverage and RMS ratio with its own σ; its RMS error split into the mean over
  each vector's 3x3x3 neighbourhood and the rest, and what is left of it after the ``tophat`` and
  ``partw`` predictions below are taken away (the part no window response explains: the random
  error); its RMS error on interior vectors against those on the grid's faces;
* how well candidate explanations predict the error, as the correlation r with it and the least
  squares slope k (k = 1: the right size):

  - ``tophat``: the truth averaged over the final window minus the truth at its centre (the top-hat
    response of a single-pass window, Raffel et al. 2018, *Particle Image Velocimetry* sec. 6.1);
  - ``partw``: the mean true displacement of the particles inside the window minus the truth at the
    centre (what a window of these particles can measure at best);
  - ``cen*grad``: the true gradient times the offset of the window's particle centroid from its
    centre (windows whose particles sit to one side, e.g. on the seeded slab's faces);
  - ``stencil``: the textbook top-hat term Σ_j w_j²/24 ∂²u/∂x_j² from second differences of the
    *measured* field (what a user could compute), and ``decon``: the same after two van Cittert
    iterations that undo the window's own filtering of that field;
  - ``broad``: the spread of the residual displacement inside the window from the broadening of the
    cross-correlation peak beyond the two auto-correlation peaks, s_cc² − (s_aa² + s_bb²)/2 per axis
    (three-point Gaussian widths; Scharnowski, Hain & Kähler 2012, Exp. Fluids 52 985), compared with
    |error| (it has no sign);

* the coverage and ratio of σ with each data-driven term (``stencil``, ``decon``, ``broad``) added
  in quadrature: the test of whether a term may join σ (uniform flows must barely change).

Findings (run 2026-11-26; thesis camera cropped to 1600 x 1200 px, final window 8 x 16 x 16 voxels
= 4 x 2 x 2 mm, 7 x 8 x 10 vectors; demo design M -1, p 0.0888, sensor 1280 x 960 px, final window
4 x 8 x 8 voxels = 1 x 0.71 x 0.71 mm, 7 x 19 x 25 vectors; ``ring``: a vortex_ring of Γ 4, R 2, r_c 1
on the thesis camera, Γ 1.5, R 1.2, r_c 0.6 on the demo; the demo's lamb_oseen Γ 1.5, r_c 0.8, axis y):

* The oracle's error is the windows' response to the flow, not noise: the truth's top-hat average
  minus its centre value predicts it with r 0.92-0.96 and k 0.99-1.24 on Hill (thesis camera, both
  densities), r 0.79-0.86 on the ring (k 1.0 in x, y, 1.6-1.8 in z), and the particles' own mean
  displacement (``partw``) with r 0.73-0.99, k 0.94-1.21 on every gradient flow of the thesis
  camera. The lamb_oseen error comes also from windows whose particles sit to one side (the seeded
  slab's faces in z: ``cen*grad`` r 0.59-0.77). Interior vectors err more than the grid's faces
  (Hill x 0.019 against 0.0035 mm). The 3x3x3 mean is small beside the rest on Hill (0.003 against
  0.013 mm) only because the window's response changes sign within a few vectors.
* Not the predictor filter alone: with ``piv.predictor_filter`` 0 the Hill error falls from 0.0129
  to 0.0096 mm (x) and 0.0232 to 0.0188 mm (z) and still follows the top-hat (k 0.83), while the
  uniform flow's z error triples (0.0016 to 0.0047 mm); with 0.5 it is 0.0120 / 0.0193 mm.
* The correlation-statistics σ sees none of it: the oracle's own coverage is 0.05-0.40 on Hill,
  lamb_oseen and the ring (thesis camera), ratio 2.4-6.7; on the uniform flow 0.82-0.96 / 0.46-0.64.
* From the measured field the top-hat term is lost: the stencil reads 3-6x too small on Hill
  (its field is the filtered one) and is anti-correlated with the error on uniform flows (a vector's
  own random error enters its second difference with weight -2); two van Cittert iterations raise
  r only to 0.38-0.47 in x, y (0.66-0.71 in z), not at all on lamb_oseen, and diverge after.
* The peak broadening tracks |error| on Hill and the ring (r 0.56-0.78 in x, y; σ with it in
  quadrature reaches coverage 0.49-0.84, ratio 0.62-1.30 on the gradient flows) but has a floor
  where nothing varies in the window: the B-spline deformation of small particles (e^-2 diameter
  2.4 voxels: s.d. 0.09-0.11 voxel at fractional shifts, 0 at integer ones; 3.2 voxels: 0.03-0.04)
  makes the uniform flow's σ 4-20x too large (ratio 0.05-0.27). Subtracting N_eff σ² (the jitter
  that the random error implies, N_eff from the windows' intensities) removes only 14-27 % of that
  floor in x, y and none in z.
* On the demo the z error exceeds the top-hat 2-3x (Hill k 2.2, ring 3.2): its final z window
  (4 voxels = 1 mm) is shorter than a particle's e^-2 length in z (4 x 0.355 mm).

So no term is wired into ``piv.uncertainty``: none predicts the resolution error from the data
without inflating σ on uniform motion. The two-window (Richardson) estimate from WIDIM's two
levels fails too: benchmarks/bench_uncertainty_richardson.py.

The final pass's windows are read by wrapping :func:`lfstudy.piv.engine.window_uncertainty` for the
duration of the run (a benchmark's probe: the engine itself is unchanged).

    python benchmarks/bench_uncertainty_resolution.py [--config config/thesis.yaml]
        [--set camera.sensor.n_pixels_x=1600 camera.sensor.n_pixels_y=1200 ...]
        [--flows hill lamb_oseen] [--add-flow 'ring={kind: vortex_ring, ...}'] [--ppp 0.001 0.005]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
AXES = (("x", "u", 2), ("y", "v", 1), ("z", "w", 0))  # axis, component, array axis of (z, y, x)


def _config(args: argparse.Namespace) -> dict[str, Any]:
    from bench_uncertainty import read_config

    from lfstudy.study.config import validate_config

    raw = read_config(args.config, args.set)
    for item in args.add_flow:
        name, _, spec = item.partition("=")
        raw.setdefault("flows", {})[name] = yaml.safe_load(spec)
    sweep = {k: v for k, v in raw.get("sweep", {}).items() if k not in ("flow", "ppp")}
    sweep = {k: v[:1] for k, v in sweep.items()}  # one design: the first of each swept setting
    sweep["flow"] = list(args.flows)
    if args.ppp:
        sweep["ppp"] = list(args.ppp)
    raw["sweep"] = sweep
    return validate_config(raw)


def peak_widths(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Gaussian variances [voxel²] of the cross- and both auto-correlation peaks of window pairs.

    Parameters
    ----------
    a, b : ndarray, shape (n, Z, Y, X)
        The final pass's deformed windows of both frames.

    Returns
    -------
    ndarray, shape (3, n, 3)
        ``[cc, aa, bb]`` per window and array axis (z, y, x), each from the three-point Gaussian
        through the lags -1, 0, +1 (``1/s² = 2 ln C0 − ln C+ − ln C-``); NaN where a log is undefined.
    """
    a = a - a.mean(axis=(1, 2, 3), keepdims=True)
    b = b - b.mean(axis=(1, 2, 3), keepdims=True)
    c0, a0, b0 = ((x * y).sum((1, 2, 3)) for x, y in ((a, b), (a, a), (b, b)))
    out = np.full((3, a.shape[0], 3), np.nan)
    for ax in range(3):
        lo = [slice(None)] * 4
        hi = [slice(None)] * 4
        lo[ax + 1], hi[ax + 1] = slice(None, -1), slice(1, None)
        a_lo, a_hi, b_lo, b_hi = a[tuple(lo)], a[tuple(hi)], b[tuple(lo)], b[tuple(hi)]
        cp, cm = (a_lo * b_hi).sum((1, 2, 3)), (a_hi * b_lo).sum((1, 2, 3))
        ap, bp = (a_lo * a_hi).sum((1, 2, 3)), (b_lo * b_hi).sum((1, 2, 3))
        with np.errstate(divide="ignore", invalid="ignore"):
            for i, (z0, zp, zm) in enumerate(((c0, cp, cm), (a0, ap, ap), (b0, bp, bp))):
                curv = 2 * np.log(z0) - np.log(zp) - np.log(zm)
                out[i, :, ax] = np.where(curv > 0, 1.0 / curv, np.nan)
    return out


def second_difference(f: np.ndarray, axis: int) -> np.ndarray:
    """Second difference of a grid field along ``axis`` (grid units), the faces taking their neighbour's."""
    if f.shape[axis] < 3:
        return np.zeros_like(f)
    g = np.moveaxis(f, axis, 0)
    out = np.empty_like(g)
    out[1:-1] = g[:-2] - 2 * g[1:-1] + g[2:]
    out[0], out[-1] = out[1], out[-2]
    return np.moveaxis(out, 0, axis)


def tophat_term(field: np.ndarray, window_mm: list[float], spacing_mm: list[float]) -> np.ndarray:
    """(W − I) u of a top-hat window W to second order, Σ_j w_j²/24 ∂²u/∂x_j² on the vector grid."""
    return sum(
        window_mm[j] ** 2 / 24.0 * second_difference(field, j) / spacing_mm[j] ** 2
        for j in range(3)
        if field.shape[j] >= 3
    )


def _fit(err: np.ndarray, pred: np.ndarray, ok: np.ndarray) -> tuple[float, float]:
    """Correlation r and least-squares slope k of ``err`` on ``pred`` over ``ok``."""
    m = ok & np.isfinite(pred)
    # a prediction of ~0 everywhere (a uniform flow's top-hat term: rounding only) has no slope
    if m.sum() < 4 or np.sqrt(np.mean(pred[m] ** 2)) < 1e-6 * max(np.sqrt(np.mean(err[m] ** 2)), 1e-12):
        return np.nan, np.nan
    return float(np.corrcoef(err[m], pred[m])[0, 1]), float(err[m] @ pred[m] / (pred[m] @ pred[m]))


def _calib(err: np.ndarray, sig: np.ndarray, ok: np.ndarray) -> str:
    from lfstudy.study.metrics import uncertainty_calibration

    cov, ratio = uncertainty_calibration(err, sig, ok & np.isfinite(sig))
    return f"{cov:4.2f}/{ratio:4.2f}"


def _windows_of(run: Callable[[], Any]) -> tuple[Any, np.ndarray, np.ndarray]:
    """Run ``run`` (a WIDIM call) with the final pass's windows recorded: (result, a, b)."""
    import lfstudy.piv.engine as eng

    calls: list[tuple[np.ndarray, np.ndarray]] = []
    orig = eng.window_uncertainty

    def probe(a: np.ndarray, b: np.ndarray, method: str) -> np.ndarray:
        calls.append((np.array(a, dtype=np.float64), np.array(b, dtype=np.float64)))
        return orig(a, b, method)

    eng.window_uncertainty = probe
    try:
        res = run()
    finally:
        eng.window_uncertainty = orig
    n = int(np.prod([res.sizes[d] for d in ("z", "y", "x")]))
    a, b, got = [], [], 0
    for ca, cb in reversed(calls):  # the last pass's batches, in order
        if got >= n:
            break
        a.insert(0, ca)
        b.insert(0, cb)
        got += ca.shape[0]
    return res, np.concatenate(a)[-n:], np.concatenate(b)[-n:]


def analyse_case(cfg: dict[str, Any], case: Any) -> list[str]:
    """The oracle of one case and its error's make-up; the printed lines."""
    from lfstudy.simulate.flows import flow_from_config, true_displacement
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config
    from lfstudy.study.metrics import case_errors

    cc = case_config(cfg, case)
    spec = cc["flow"]
    flow = flow_from_config(spec)
    dt, n_steps = spec.get("dt", 1.0), spec.get("n_steps", 100)
    pa = cl.case_particles(cc)
    pb = cl.case_displaced(cc, pa)
    t0 = time.perf_counter()
    o, wa, wb = _windows_of(lambda: cl.oracle_piv(cc, pa, pb))
    secs = time.perf_counter() - t0
    e = case_errors(o, flow, dt=dt, n_steps=n_steps)
    grid = cl.case_grid(cc)
    vox = [float(np.median(np.diff(getattr(grid, d)))) for d in ("z", "y", "x")]
    win = [int(v) for v in o.attrs["final_window"]]
    wmm = [w * v for w, v in zip(win, vox)]
    zc, yc, xc = (o[d].values for d in ("z", "y", "x"))
    shape = (zc.size, yc.size, xc.size)
    spmm = [float(np.median(np.diff(c))) if c.size > 1 else 1.0 for c in (zc, yc, xc)]

    # the truth averaged over each final window (sampled every voxel in z, every 2nd in y and x)
    offs = [(np.arange(n) - (n - 1) / 2.0) * v for n, v in zip(win, vox)]
    offs = [offs[0], offs[1][::2], offs[2][::2]]
    dz, dy, dx = (g.ravel() for g in np.meshgrid(*offs, indexing="ij"))
    gz, gy, gx = np.meshgrid(zc, yc, xc, indexing="ij")
    pts = [(g[..., None] + d).ravel() for g, d in ((gx, dx), (gy, dy), (gz, dz))]
    box = [t.reshape(*shape, -1).mean(-1) for t in true_displacement(flow, *pts, dt=dt, n_steps=n_steps)]
    box_of = {"x": box[0], "y": box[1], "z": box[2]}

    # the particles inside each window: their mean displacement and centroid offset
    pos = np.stack([pa[k].values for k in ("z", "y", "x")], 1)
    disp = {k: pb[k].values - pa[k].values for k in "xyz"}
    half = np.array(wmm) / 2.0
    count = np.zeros(shape)
    partw = {k: np.full(shape, np.nan) for k in "xyz"}
    centroid = np.zeros((*shape, 3))
    for idx in np.ndindex(shape):
        ctr = np.array([zc[idx[0]], yc[idx[1]], xc[idx[2]]])
        inside = np.all(np.abs(pos - ctr) <= half, axis=1)
        count[idx] = inside.sum()
        if inside.any():
            centroid[idx] = pos[inside].mean(0) - ctr
            for k in "xyz":
                partw[k][idx] = disp[k][inside].mean()

    widths = peak_widths(wa, wb).reshape(3, *shape, 3)
    interior = ndimage.binary_erosion(np.ones(shape, bool), np.ones((3, 3, 3)), border_value=0)
    lines = [
        f"{case.case_id}: oracle {secs:.1f} s, grid {shape}, final window {win} vox = "
        f"{', '.join(f'{w:.2f}' for w in wmm)} mm (z, y, x), particles per window median {np.median(count):.0f}"
        f" (min {count.min():.0f}), interior vectors {interior.sum()} of {interior.size}"
    ]
    for ax, c, arr_ax in AXES:
        err = e[f"{c}_err_mm"].transpose("z", "y", "x").values
        sig = e[f"unc_{c}_mm"].transpose("z", "y", "x").values
        tru = e[f"{c}_true_mm"].transpose("z", "y", "x").values
        meas = o[f"{c}_mm"].transpose("z", "y", "x").values
        ok = np.isfinite(err) & np.isfinite(sig)
        if not ok.any():
            continue
        w8 = ok.astype(float)
        nb = np.ones((3, 3, 3))
        sysm = ndimage.convolve(np.where(ok, err, 0.0), nb, mode="constant") / np.maximum(
            ndimage.convolve(w8, nb, mode="constant"), 1.0
        )

        def rms(v: np.ndarray, m: np.ndarray = ok) -> float:
            m = m & np.isfinite(v)
            return float(np.sqrt(np.mean(v[m] ** 2))) if m.any() else np.nan

        cen_grad = sum(
            np.gradient(tru, cj, axis=j) * centroid[..., j] for j, cj in enumerate((zc, yc, xc)) if cj.size > 1
        )
        filled = np.where(np.isfinite(meas), meas, 0.0)
        stencil = tophat_term(filled, wmm, spmm)
        u_hat = filled.copy()
        for _ in range(2):  # van Cittert: u <- u + (u_meas − W u)
            u_hat = u_hat + (filled - (u_hat + tophat_term(u_hat, wmm, spmm)))
        decon = tophat_term(u_hat, wmm, spmm)
        scc, saa, sbb = widths[0][..., arr_ax], widths[1][..., arr_ax], widths[2][..., arr_ax]
        broad = np.sqrt(np.clip(scc - 0.5 * (saa + sbb), 0.0, None)) * vox[arr_ax]
        preds = {
            "tophat": box_of[ax] - tru,
            "partw": partw[ax] - tru,
            "cen*grad": cen_grad,
            "stencil": stencil,
            "decon": decon,
        }
        fits = "  ".join(
            f"{k} {rms(v):.4f} r{_fit(err, v, ok)[0]:+.2f} k{_fit(err, v, ok)[1]:+.2f}" for k, v in preds.items()
        )
        rb = np.corrcoef(np.abs(err[ok & np.isfinite(broad)]), broad[ok & np.isfinite(broad)])[0, 1]
        quad = "  ".join(
            f"+{k} {_calib(err, np.sqrt(sig**2 + v**2), ok)}"
            for k, v in (("stencil", stencil), ("decon", decon), ("broad", broad))
        )
        lines.append(
            f"  {ax}: rms err {rms(err):.4f} σ {rms(sig):.4f} cov/ratio {_calib(err, sig, ok)} | 3x3x3 mean"
            f" {rms(sysm):.4f} rest {rms(err - sysm):.4f} | not tophat {rms(err - preds['tophat']):.4f}"
            f" not partw {rms(err - preds['partw']):.4f} | interior {rms(err, ok & interior):.4f}"
            f" faces {rms(err, ok & ~interior):.4f}"
        )
        lines.append(f"     {fits}  broad {rms(broad):.4f} r(|e|){rb:+.2f}")
        lines.append(f"     σ with a term in quadrature, cov/ratio: {quad}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "thesis.yaml")
    ap.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE", help="config overrides (YAML values)")
    ap.add_argument("--flows", nargs="*", default=["uniform_x", "hill"], help="flows of the config (or --add-flow)")
    ap.add_argument("--add-flow", nargs="*", default=[], metavar="NAME=SPEC", help="a flow added (YAML mapping)")
    ap.add_argument("--ppp", nargs="*", type=float, default=None, help="seeding densities (default: the config's)")
    args = ap.parse_args()
    from lfstudy.study.sweep import Sweep

    cfg = _config(args)
    t0 = time.perf_counter()
    for case in Sweep(cfg).cases():
        print("\n".join(analyse_case(cfg, case)), flush=True)
    print(f"all cases {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
