"""What makes up an oracle's error beyond the windows' top-hat filtering (issue 38).

Reproduces: docs/architecture.md § "Benchmarks" (the demo Hill oracle beyond the top-hat: the
deformation's predictor filter).

On the demo's Hill case (M -1, pitch 0.0888) the top-hat filter of the final window
(``filter_rms_total_mm``, :func:`lfstudy.study.metrics.window_average`) is about a third of the
oracle's RMS error. This benchmark runs the oracle (the case's PIV on the true particle volumes,
:func:`lfstudy.study.case.oracle_piv`) of the first design of a config's sweep for one flow and
prints the candidates:

* the volume's edges: the error and the filter on interior vectors (a 3x3x3 erosion of the grid)
  against the grid's faces;
* the truth volumes' blob size: the truth averaged over the window widened by a Gaussian of the
  oracle particles' σ (and σ/√2, the width of an image's autocorrelation), its correlation r and
  least-squares slope k with the error; and the oracle rerun with its particles as long as Q's truth σ
  (as it was rendered before 2026-12-03; ``benchmarks/bench_particle_sigma.py`` for every design);
* the windows' particle sampling: the mean true displacement of the particles inside each window
  minus the truth at its centre;
* the deformation's own filter: the oracle rerun with ``piv.predictor_filter`` 0 (the predictor
  is no longer Gaussian-smoothed over the vector grid between passes).

    python benchmarks/bench_budget_gap.py [--config config/demo.yaml] [--flow hill] [--set PATH=VALUE ...]

Findings (run 2026-11-28, when the oracle's particles were Q's truth σ, as long in z as the camera's depth of
focus; since 2026-12-03 they are half a voxel per axis, ``piv.particle_sigma``; on 2 loaded cores,
NUMBA_NUM_THREADS=1; demo M -1, p 0.0888, 0.005 ppp, the study's seed, depth calibration off; final window 4 x
8 x 8 voxels = 1.0 x 0.71 x 0.71 mm, grid 7 x 9 x 12; truth blobs σ 0.355 mm in z, 0.044 mm in x, y):

* oracle RMS x / y / z / total 0.0055 / 0.0051 / 0.0340 / 0.0348 mm; top-hat filter 0.0038 /
  0.0040 / 0.0097 / 0.0112 mm (the issue's 0.011 against 0.035). The z error follows the top-hat
  (r 0.87) at 2.5x its size (k 2.52); x, y r 0.72-0.77, k 0.93-1.11.
* Not the edges: interior vectors err more (0.0427 mm, filter 0.0164) than the faces (0.0262,
  filter 0.0013).
* Not the blob's own averaging: the top-hat widened by the blobs gives 0.0130 (σ/√2) to 0.0146 mm
  (σ), the z slope stays 2.1-2.3. Not the particle sampling: the particles' mean displacement is
  0.0138 mm from the truth (11 particles per window, median).
* The deformation's own filter, where the particle images are long in z: with predictor_filter 0
  the oracle's z error halves (0.0340 -> 0.0168 mm; total 0.0184, of which the top-hat's 0.0111 is
  60 %), and with the truth blobs half as long (the same predictor filter) it falls to 0.0158 mm
  (total 0.0180). The predictor's Gaussian smoothing over the vector grid filters the curved flow,
  and with z images 1.4 z voxels long (σ) in a 4-voxel z window the final pass's correlation does
  not correct it back. Both changes at once raise x, y (0.0107-0.0108 mm: an unsmoothed predictor
  of small images is noisier), total 0.0238 mm.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
DIMS = ("z", "y", "x")


def _rms(v: np.ndarray, m: np.ndarray) -> float:
    m = m & np.isfinite(v)
    return float(np.sqrt(np.mean(v[m] ** 2))) if m.any() else np.nan


def _tot(d: dict[str, np.ndarray], m: np.ndarray) -> float:
    return float(np.sqrt(sum(_rms(d[a], m) ** 2 for a in "xyz")))


def _fit(err: np.ndarray, pred: np.ndarray, ok: np.ndarray) -> str:
    e, p = err[ok], pred[ok]
    return f"r {np.corrcoef(e, p)[0, 1]:+.2f} k {float(e @ p / (p @ p)):.2f}"


def blob_widened(flow: Any, o: Any, win: list, vox: list, sigma: np.ndarray, *, dt: float) -> dict[str, np.ndarray]:
    """The truth averaged over the window ⊗ a Gaussian of σ per axis (Gauss-Legendre x Gauss-Hermite) minus
    the truth at the centre."""
    from lfstudy.simulate.flows import true_displacement

    gl, glw = np.polynomial.legendre.leggauss(4)
    gh, ghw = np.polynomial.hermite_e.hermegauss(3)
    offs, wts = [], []
    for j in range(3):
        offs.append((win[j] * vox[j] / 2 * gl[:, None] + sigma[j] * gh[None, :]).ravel())
        wts.append((glw[:, None] / 2 * ghw[None, :] / ghw.sum()).ravel())
    dz, dy, dx = (q.ravel() for q in np.meshgrid(*offs, indexing="ij"))
    w = np.prod(np.meshgrid(*wts, indexing="ij"), axis=0).ravel()
    gz, gy, gx = np.meshgrid(*(o[d].values for d in DIMS), indexing="ij")
    pts = [(g.ravel()[:, None] + d).ravel() for g, d in ((gx, dx), (gy, dy), (gz, dz))]
    box = [v.reshape(-1, w.size) @ w for v in true_displacement(flow, *pts, dt=dt, n_steps=8)]
    ctr = true_displacement(flow, gx, gy, gz, dt=dt, n_steps=8)
    return {a: b.reshape(gx.shape) - c for a, b, c in zip("xyz", box, ctr)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "demo.yaml")
    ap.add_argument("--flow", default="hill")
    ap.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE", help="config overrides (YAML values)")
    args = ap.parse_args()
    from bench_uncertainty import _config

    from lfstudy.simulate.flows import flow_from_config
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config
    from lfstudy.study.metrics import case_errors
    from lfstudy.study.sweep import Sweep

    cfg = _config(
        argparse.Namespace(config=args.config, set=args.set, sweep=[], flows=[args.flow], ppp=None, seed=None)
    )
    case = next(iter(Sweep(cfg).cases()))
    cc = case_config(cfg, case)
    spec = cc["flow"]
    flow = flow_from_config(spec)
    dt, n_steps = spec.get("dt", 1.0), spec.get("n_steps", 100)
    pa = cl.case_particles(cc)
    pb = cl.case_displaced(cc, pa)

    def oracle(label: str, **piv: Any) -> tuple[Any, Any]:
        t0 = time.perf_counter()
        o = cl.oracle_piv({**cc, "piv": {**cc["piv"], **piv}}, pa, pb)
        e = case_errors(o, flow, dt=dt, n_steps=n_steps)
        rms = " / ".join(f"{float(e[f'rms_{a}_mm']):.4f}" for a in "xyz")
        filt = " / ".join(f"{float(e[f'filter_rms_{a}_mm']):.4f}" for a in "xyz")
        print(
            f"{label}: oracle RMS x/y/z {rms}, total {float(e['rms_total_mm']):.4f} mm; top-hat {filt}, total "
            f"{float(e['filter_rms_total_mm']):.4f} mm ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
        return o, e

    truth = np.array(cl.truth_sigma(cl.case_camera(cc)))
    o, e = oracle("as configured")
    sigma = np.array(o.attrs["particle_sigma_mm"])
    print(f"{case.case_id}: the oracle's particles σ z, y, x {np.round(sigma, 4)} mm (Q's truth {np.round(truth, 4)})")
    grid = cl.case_grid(cc)
    vox = [float(np.median(np.diff(getattr(grid, d)))) for d in DIMS]
    win = [int(v) for v in o.attrs["final_window"]]
    shape = tuple(o.sizes[d] for d in DIMS)
    print(f"final window {win} voxels = {np.round(np.array(win) * vox, 3)} mm, grid {shape}")
    err = {a: e[f"{c}_err_mm"].transpose(*DIMS).values for a, c in zip("xyz", "uvw")}
    tru = {a: e[f"{c}_true_mm"].transpose(*DIMS).values for a, c in zip("xyz", "uvw")}
    top = {a: e[f"{c}_filter_mm"].transpose(*DIMS).values for a, c in zip("xyz", "uvw")}
    ok = np.isfinite(err["x"])
    inner = ndimage.binary_erosion(np.ones(shape, bool), np.ones((3, 3, 3)), border_value=0)
    print("top-hat against the error per axis: " + ", ".join(f"{a} {_fit(err[a], top[a], ok)}" for a in "xyz"))
    print(
        f"edges: interior ({int((ok & inner).sum())}) error {_tot(err, ok & inner):.4f}, top-hat "
        f"{_tot(top, ok & inner):.4f}; faces error {_tot(err, ok & ~inner):.4f}, top-hat "
        f"{_tot(top, ok & ~inner):.4f} mm"
    )
    for scale, name in ((2**-0.5, "σ/√2"), (1.0, "σ")):
        wide = blob_widened(flow, o, win, vox, sigma * scale, dt=dt)
        fits = ", ".join(f"{a} {_fit(err[a], wide[a], ok)}" for a in "xyz")
        print(f"top-hat ⊗ blob {name}: {_tot(wide, ok):.4f} mm; {fits}")
    pos = np.stack([pa[k].values for k in DIMS], 1)
    disp = {k: pb[k].values - pa[k].values for k in "xyz"}
    half = np.array(win) * np.array(vox) / 2
    centres = [o[d].values for d in DIMS]
    part = {k: np.full(shape, np.nan) for k in "xyz"}
    count = np.zeros(shape)
    for idx in np.ndindex(shape):  # a benchmark's probe over a few hundred windows
        inside = np.all(np.abs(pos - [c[i] for c, i in zip(centres, idx)]) <= half, axis=1)
        count[idx] = inside.sum()
        if inside.any():
            for k in "xyz":
                part[k][idx] = disp[k][inside].mean() - tru[k][idx]
    print(
        f"particles per window median {np.median(count):.0f}: their mean displacement − truth {_tot(part, ok):.4f} mm"
    )
    oracle("predictor_filter 0", predictor_filter=0.0)
    orig = cl.particle_sigma
    cl.particle_sigma = lambda _c, _v: tuple(truth)  # as the oracle rendered them before 2026-12-03
    try:
        oracle("particles as long as Q's truth")
    finally:
        cl.particle_sigma = orig


if __name__ == "__main__":
    main()
