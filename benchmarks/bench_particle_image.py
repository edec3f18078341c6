"""IPR's per-particle images, exact against fast quadrature: CPU ms per image and the error (issue 27).

Reproduces: lfstudy/reconstruct/ipr/__init__.py (its docstring: CPU ms per particle image, fast against exact
quadrature); docs/architecture.md § "Benchmarks".

    python benchmarks/bench_particle_image.py [--crop 300 300] [--ppp 0.005] [--seed 7] [--reps 3]

The particles of a ``--ppp`` field over the crop of the Table 4.3 camera (7 mm deep) are rendered
by :func:`lfstudy.reconstruct.ipr.particle_patches` as IPR renders them in one iteration (each at
its position and the six ±0.1 voxel trials), with ``accuracy="exact"`` and ``"fast"``, alternately
``--reps`` times each on one thread; printed: the least CPU time per image of each, their ratio, and
the largest |fast − exact| over every patch, as a fraction of the patch's peak and of its sum.

Measured (``benchmarks/bench_particle_image.py``, 450 particles x 7 images of a 300 x 300 px crop at 0.005 ppp, one
thread, load ~5 on 2 cores): 0.219 ms of CPU per exact image, 0.148 fast (x1.47). Where an image's time
goes (same images, exact quadrature): ~20 % the particle's layout, the separable interior lenslets and the patch
memory, ~25 % the straight cuts and carries of the lenslets on the spot's rim, ~30 % placing the arcs' panels and
nodes (a crossing per pixel edge), ~25 % the nodes' blurred-edge sums; the quadrature shortens the last two only. A
patch is mostly empty (5.5 % of its pixels lit, the lit bounding box 43 % of its area).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--crop", type=int, nargs=2, default=[300, 300], metavar=("W", "H"), help="sensor crop [px]")
    ap.add_argument("--ppp", type=float, default=0.005)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()

    import numba

    from lfstudy.optics import PlenopticCamera
    from lfstudy.reconstruct.ipr import particle_patches
    from lfstudy.simulate import seed_particles

    numba.set_num_threads(1)
    cam = PlenopticCamera(*args.crop, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013, lenslet_offset_y=-0.021)
    field = seed_particles(cam, ppp=args.ppp, z_span=7.0, seed=args.seed)
    x, y, z = (field[v].values for v in ("x", "y", "z"))
    vox = np.array([0.125, 0.125, 0.4])  # the case grid's voxel of this camera (x, y, z) [mm]
    tr = np.array([[d * 0.1 * vox[i] if a == i else 0.0 for a in range(3)] for i in range(3) for d in (1.0, -1.0)])
    for acc in ("exact", "fast"):  # compile
        particle_patches(cam, x[:3], y[:3], z[:3], trials=tr, accuracy=acc)
    best = {"exact": np.inf, "fast": np.inf}
    out = {}
    for _ in range(args.reps):
        for acc in best:
            c0 = time.process_time()
            out[acc] = particle_patches(cam, x, y, z, trials=tr, accuracy=acc)
            best[acc] = min(best[acc], time.process_time() - c0)
    n_img = x.size * (1 + len(tr))
    (ex, offs, _, _, shp), fast = out["exact"], out["fast"][0]
    peak = total = 0.0
    for i in range(x.size):
        for a, b in zip(
            np.split(ex[offs[i] : offs[i + 1]], 1 + len(tr)), np.split(fast[offs[i] : offs[i + 1]], 1 + len(tr))
        ):
            peak = max(peak, float(np.abs(b - a).max() / a.max()))
            total = max(total, float(abs(b.sum() - a.sum()) / a.sum()))
    ms = {k: 1e3 * v / n_img for k, v in best.items()}
    print(
        f"{x.size} particles x {1 + len(tr)} images ({args.crop[0]} x {args.crop[1]} px, {args.ppp} ppp, "
        f"seed {args.seed}, mean patch {shp.prod(axis=1).mean():.0f} px): exact {ms['exact']:.3f} ms/image, "
        f"fast {ms['fast']:.3f} ms/image "
        f"(x{ms['exact'] / ms['fast']:.2f}); max |fast - exact| {peak:.2e} of the patch peak, {total:.2e} of its sum"
    )


if __name__ == "__main__":
    main()
