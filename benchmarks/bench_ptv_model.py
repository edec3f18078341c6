"""The PTV uncertainty's model (curvature) term against the truth, re-binned on a study's stored particle lists.

Reproduces: docs/config.md § "The uncertainty's model term (`piv.ptv_model_box`)" (the coverage and ratio
table); lfstudy/piv/ptv.py (MODEL_BOX).

For each case directory of a ``bench_budget.py --out`` run whose config sweeps ``piv.particles: [none, ptv]``
(IPR's particle lists ``volume_{a,b}.particles.zarr``, WIDIM's result and errors under
``piv.particles~none``), the lists are tracked about the WIDIM field and binned again as the piv stage
does (:func:`lfstudy.piv.ptv.match_particles`, ``validate_tracks``, ``bin_tracks``) with each
``--boxes`` value of ``model_box`` (0: the fit's own σ alone), and the per-vector σ is scored against
the truth the errors stage stored on the same grid (``u_true_mm``, ...): coverage (fraction of valid
vectors with |error| <= σ; 0.68 if right) and RMS(error) / RMS(σ) (1 if right), x / y / z, with
issue 28's targets (coverage 0.55-0.80, ratio 0.7-1.4) as ok/miss. No stage reruns: the reconstruction
(minutes per frame) is what the study stored, the binning takes about a second.

    python benchmarks/bench_budget.py --configs benchmarks/ptv_model_demo.yaml --out DIR
    python benchmarks/bench_ptv_model.py DIR/ptv_model_demo [--boxes 0 1.25 1.5 2] [--order 1] [--bin 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

COV, RATIO = (0.55, 0.80), (0.7, 1.4)


def score(res, err) -> list[tuple[float, float, float]]:
    """Coverage, RMS ratio and RMS error [mm] per component of a binned result against the stored truth."""
    dims = ("z", "y", "x")
    out = []
    for c in "uvw":
        e = res[f"{c}_mm"].transpose(*dims).values - err[f"{c}_true_mm"].transpose(*dims).values
        s = res[f"unc_{c}_mm"].transpose(*dims).values
        ok = res["valid"].transpose(*dims).values & np.isfinite(e) & np.isfinite(s)
        e, s = np.abs(e[ok]), s[ok]
        rms = float(np.sqrt(np.mean(e**2)))
        out.append((float(np.mean(e <= s)), rms / float(np.sqrt(np.mean(s**2))), rms))
    return out


def main() -> None:
    from lfstudy import io
    from lfstudy.piv.ptv import bin_tracks, match_particles, validate_tracks

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", type=Path, nargs="+", help="a config's output directory of bench_budget.py")
    ap.add_argument("--boxes", type=float, nargs="+", default=[0.0, 1.25, 1.5, 2.0])
    ap.add_argument("--order", type=int, default=1)
    ap.add_argument("--search", type=float, default=1.5)
    ap.add_argument("--bin", type=float, default=1.0, help="bin box over the final window, per axis (the piv stage: 1)")
    args = ap.parse_args()
    print(f"{'case':<58} {'box':>5}  coverage x/y/z   ratio x/y/z     rms x/y/z [mm]       verdict")
    for root in args.roots:
        for lists_b in sorted(root.rglob("volume_b.particles.zarr")):
            case = lists_b.parent
            none = case / "piv.particles~none"
            # frame a is fitted once per design: its list and volume sit at the case's folder less its flow segment
            design = root.joinpath(*(p for p in case.relative_to(root).parts if not p.startswith("flow~")))
            first = [d for d in (case, design) if (d / "volume_a.particles.zarr").exists()]
            if not first or not (none / "piv.zarr").exists() or not (none / "errors.zarr").exists():
                continue
            piv = io.open_zarr(none / "piv.zarr").load()
            err = io.open_zarr(none / "errors.zarr").load()
            vol = io.open_array(first[0] / "volume_a.zarr")
            voxel = tuple(float(np.median(np.abs(np.diff(vol[a].values)))) for a in "xyz")
            pa = io.open_zarr(first[0] / "volume_a.particles.zarr").load()
            pb = io.open_zarr(lists_b).load()
            tracks = match_particles(pa, pb, piv, search=args.search, voxel=voxel)
            tracks = validate_tracks(tracks, voxel=tracks.attrs["voxel_mm"])
            name = f"{root.name}: " + "/".join(p for p in case.relative_to(root).parts if "~" in p and "fnum" not in p)
            for box in args.boxes:
                window = [args.bin * w for w in piv.attrs["final_window"]]
                res = bin_tracks(tracks, piv, window=window, voxel=voxel, order=args.order, model_box=box)
                sc = score(res, err)
                ok = all(COV[0] <= c <= COV[1] and RATIO[0] <= r <= RATIO[1] for c, r, _ in sc)
                print(
                    f"{name:<58} {box:5.2f}  "
                    + "/".join(f"{c:.2f}" for c, _, _ in sc)
                    + "  "
                    + "/".join(f"{r:.2f}" for _, r, _ in sc)
                    + "  "
                    + "/".join(f"{e:.4f}" for _, _, e in sc)
                    + f"  {'ok' if ok else 'miss'}  ({tracks.sizes['track']} tracks, "
                    f"{int(np.median(res.n_tracks.values))} per box)",
                    flush=True,
                )


if __name__ == "__main__":
    main()
