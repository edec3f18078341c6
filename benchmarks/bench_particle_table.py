"""Can a tabulated particle image (an OTF, as Shake-the-Box's) replace IPR's exact images? (issue 39 §1)

Reproduces: lfstudy/reconstruct/image_model.py (why IPR has no tabulated particle image, its module
docstring) and docs/cli.md.

    python benchmarks/bench_particle_table.py [--camera thesis|demo] [--particles 60] [--seed 5]

The issue's proposal: on the ideal plenoptic camera a particle's image depends only on its depth and on its
position relative to the lenslet grid, so one table of patches over (sub-lenslet x, sub-lenslet y, z),
rendered once by the exact renderer and interpolated, would give every image within 1e-4 of its peak, and
the shake's derivatives from the same interpolation. Two things decide it, and this script measures both
with :func:`lfstudy.reconstruct.ipr.particle_patches` (the exact images IPR fits with):

1. **Periodicity.** Moving a particle so that its spot on the lenslet array moves by m whole lenslets
   moves its sensor image by ``m·P'``, ``P' = pl·(1 + fl/si)`` (the aperture images sit at
   ``c_k·(si + fl)/si``; module docstring of :mod:`lfstudy.simulate.exact`), which is a whole number of
   pixels only by accident. The image at (offset, z) in lenslet k + m is then the one in lenslet k moved by
   a fraction of a pixel, and the pixel-integrated image of a sub-pixel shift is not a shifted table entry:
   the table needs the pixels' phase as two more axes (or the image as a continuous function, integrated
   over the pixels at each use). Printed: ``P'`` in pixels, its distance from a whole number, and the
   largest difference between a particle's image and the one m lenslets over, moved back by the nearest
   whole number of pixels (m = 1, 3), as a fraction of the peak.
2. **Sampling.** Whatever the axes, the table interpolates images between nodes. Printed: the largest
   |interpolated − exact| over the particles (fraction of each image's peak), interpolating along x and
   along z between exact images at nodes h voxels apart, linearly (2 nodes) and by Catmull-Rom cubics
   (4 nodes), at the points 1/4 and 1/2 of the way between nodes; split into particles near focus (spot
   radius at most 1.5 pitches, where the polish works) and the others. With it, the table's size at that
   spacing: (1/h)² nodes per lenslet cell times the depth's nodes, each a patch of the mean lit pixels
   (a sparse table, float32: its smallest form; the pixel-phase axes of point 1 not counted).

The exact images' CPU cost per image (one thread) is printed beside, the figure a table has to beat.

Measured (40 particles, seed 5, 1 thread, load 10-12 on 2 cores; "near" = spot radius <= 1.5 pitches):

- Table 4.3 camera (``--camera thesis``, 300 x 300 px, z in +-3.5 mm, 18 of 40 near focus): the aperture images
  are 16.9764 px apart (-0.0236 px from whole per lenslet); a particle's image one lenslet over, moved back by
  17 px, differs by 2.4e-2 of the peak (three lenslets: 7.1e-2). Interpolation along x, cubic: nodes 0.01 voxel
  apart 9.5e-3 near focus, 1.1e-4 defocused; 0.003 voxel 2.0e-4 and 2.5e-6 (linear 2.4e-3). Along z, cubic: 0.03
  voxel 1.3e-3, 0.01 voxel 4.0e-5. A table with nodes 0.01 voxel apart: 1.75e7 patches x 704 lit px = 49 GB
  (float32, sparse, no phase axes); 0.003 voxel: 1.8 TB. Exact images 0.29-0.48 ms CPU each here.
- The demo's 0.1184 mm, M -0.8 design (``--camera demo``, z in +-2 mm: every particle near focus): aperture images
  16.0842 px apart (+0.084 px per lenslet), one lenslet over 8.4e-2 of the peak, three 2.5e-1. Along x, cubic:
  0.01 voxel 3.7e-3, 0.003 voxel 8.4e-5 (the first spacing within 1e-4): 5.9e8 patches x 297 lit px = 704 GB.
  Along z, cubic: 0.03 voxel 1.7e-4, 0.01 voxel 6.2e-6. Exact images 0.15-0.33 ms CPU each.

Why: near focus the spot is smaller than a lenslet and the lenslet a ray lands in is decided on the scale of the
main lens' diffraction on the lenslet plane, sigma_m = 0.96 um (thesis) / 1.21 um (demo), about 1 % of a pitch:
the image jumps between lenslets over that much motion, and no interpolation between nodes much coarser than it
follows the jump. Conclusion: no table meets 1e-4 of the peak at a size a design can hold (tens of GB to TB,
before the two pixel-phase axes that the non-integer aperture-image spacing adds); IPR keeps its exact images
(``image_accuracy``), and the speed has to come from fewer images or cheaper candidates.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _cameras(name: str):
    from lfstudy.optics import PlenopticCamera

    if name == "thesis":  # Table 4.3 (as bench_particle_image / bench_ipr), its 7 mm depth; voxel 0.125 x 0.125 x 0.4
        cam = PlenopticCamera(300, 300, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013, lenslet_offset_y=-0.021)
        return cam, 7.0, np.array([0.125, 0.125, 0.4])
    # the demo's coarse design: pitch 0.1184 mm (16 px), f/4 lenslets, M -0.8, z in [-2, 2] mm, voxel_z 0.25
    cam = PlenopticCamera(320, 320, 0.0074, 0.1184, 4 * 0.1184, 50.0, -0.8)
    return cam, 4.0, np.array([0.1184 / 0.8, 0.1184 / 0.8, 0.25])


def _max(v: np.ndarray, sel: np.ndarray) -> str:
    return f"{v[sel].max():.2e}" if sel.any() else "none"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--camera", choices=("thesis", "demo"), default="thesis")
    ap.add_argument("--particles", type=int, default=60)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--spacings", type=float, nargs="+", default=[0.1, 0.03, 0.01, 0.003], help="node spacing [voxels]")
    args = ap.parse_args()

    import numba

    from lfstudy.reconstruct.ipr import _spot_pitches, particle_patches

    numba.set_num_threads(1)
    cam, z_span, vox = _cameras(args.camera)
    rng = np.random.default_rng(args.seed)
    n = args.particles
    x = rng.uniform(-0.3, 0.3, n)
    y = rng.uniform(-0.3, 0.3, n)
    z = rng.uniform(-z_span / 2, z_span / 2, n)
    near = _spot_pitches(cam, z) <= 1.5
    particle_patches(cam, x[:2], y[:2], z[:2])  # compile

    # 1. periodicity: the sensor image of a spot moved by m lenslets
    pp, pl, si, fl = cam.pixel_pitch, cam.lenslet_pitch, cam.si, cam.lenslet_focal_length
    p_img = pl * (1.0 + fl / si) / pp
    print(
        f"{args.camera}: pitch {pl} mm = {pl / pp:.4f} px; aperture images {p_img:.4f} px apart "
        f"({p_img - round(p_img):+.4f} px from a whole number per lenslet); main-lens diffraction on the lenslet "
        f"plane sigma_m {1e3 * cam.sigma_lenslet_plane:.2f} um = {cam.sigma_lenslet_plane / pl:.4f} pitch (the "
        "lenslet a ray lands in changes over that much spot motion)"
    )
    d = cam.so + z
    for m in (1, 3):
        dx = -m * pl * d / si  # the spot (lenslet plane, −si·x/d) moves by m pitches
        shift = round(m * p_img)  # the nearest whole pixels (the image moves towards +x on the sensor for −x)
        worst = 0.0
        for i in range(n):
            tr = np.array([[dx[i], 0.0, 0.0]])
            buf, _, _, _, shp = particle_patches(cam, [x[i]], [y[i]], [z[i]], trials=tr, pad=int(m * p_img) + 8)
            h, w = shp[0]
            a, b = buf.reshape(2, h, w)
            # the image moves by ±m·P' (its sign: the sensor's axes); the better of the two is the residue
            cands = [np.abs(np.roll(b, s, axis=1) - a).max() for s in (shift, -shift)]
            worst = max(worst, min(cands) / a.max())
        print(f"  spot moved by {m} lenslet(s), image moved back by {shift} px: max |diff| {worst:.2e} of the peak")

    # 2. sampling: interpolation between exact images at nodes h voxels apart, along x and z
    ts = (0.25, 0.5)
    for axis in (0, 2):
        for h in args.spacings:
            tr = [k * h for k in (-1, 0, 1, 2)] + [t * h for t in ts]  # 4 nodes, then the points between 0 and 1
            off = np.zeros((len(tr), 3))
            off[:, axis] = np.array(tr) * vox[axis]
            c0_ = time.process_time()
            buf, offs, *_ = particle_patches(cam, x, y, z, trials=off, pad=8)
            cpu = time.process_time() - c0_
            lin = np.zeros(n)
            cub = np.zeros(n)
            lit = np.zeros(n)
            for i in range(n):
                im = buf[offs[i] : offs[i + 1]].reshape(1 + len(tr), -1)[1:]
                nodes = im[:4]
                lit[i] = float(np.count_nonzero(nodes[1] > 1e-12 * nodes[1].max()))
                for j, t in enumerate(ts):
                    ex = im[4 + j]
                    pk = ex.max()
                    a_lin = (1 - t) * nodes[1] + t * nodes[2]
                    t2, t3 = t * t, t**3  # Catmull-Rom weights of the nodes -1, 0, 1, 2
                    wc = np.array([-t3 + 2 * t2 - t, 3 * t3 - 5 * t2 + 2, -3 * t3 + 4 * t2 + t, t3 - t2]) / 2
                    a_cub = wc @ nodes
                    lin[i] = max(lin[i], np.abs(a_lin - ex).max() / pk)
                    cub[i] = max(cub[i], np.abs(a_cub - ex).max() / pk)
            nodes_table = (1.0 / h) ** 2 * (z_span / vox[2] / h)
            mb = nodes_table * lit.mean() * 4 / 1e6
            print(
                f"  {'xyz'[axis]}, nodes {h} voxel apart: linear {lin.max():.2e} (near focus {_max(lin, near)}, "
                f"defocused {_max(lin, ~near)}), cubic {cub.max():.2e} (near {_max(cub, near)}, "
                f"defocused {_max(cub, ~near)}); table at h in x, y, z: {nodes_table:.3g} patches x "
                f"{lit.mean():.0f} lit px = {mb:.3g} MB; exact images {1e3 * cpu / (n * (1 + len(tr))):.3f} ms CPU each"
            )
    print(f"({n} particles, seed {args.seed}, {int(near.sum())} near focus)")


if __name__ == "__main__":
    main()
