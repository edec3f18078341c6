"""What numba's first compile costs a fresh clone: the heavy kernels' cold compile, stage by stage (issue 37).

Reproduces: lfstudy/simulate/exact.py (the comment on ``_render_particle``: why it is compiled on its own) and
the suite-time figures of issue 37's note.

    python benchmarks/bench_compile.py [--threads 1] [--order exact,patches,montecarlo,mart]

One child process with an empty ``NUMBA_CACHE_DIR`` (a fresh clone's first run) calls, in ``--order``, each
stage's public entry point twice on a small scene of the Table 4.3 camera (160 x 160 px, 20 particles):

- ``exact``: :func:`lfstudy.simulate.exact.render_exact`;
- ``patches``: IPR's exact particle images, :func:`lfstudy.reconstruct.ipr.particle_patches` (with two trials);
- ``montecarlo``: the Monte-Carlo tracer, :func:`lfstudy.simulate.raytrace.render` (200 rays a particle);
- ``mart``: a MART volume (:func:`lfstudy.reconstruct.mart.mart`, two iterations) of the exact image's light field
  on a synthetic pinhole's lenslet grid.

Printed per stage: the first call (compile + run), the second (run), their difference (the compile), and the
md5 of the stage's output (the same bytes whatever the compile order; compare runs of two commits). The whole
child's wall time and the number of compiled specializations of :func:`~lfstudy.simulate.exact._render_particle`
close the table.

Measured (``--threads 1``, quiet 2-core machine; compile = first call − second call, s; the same md5s):

==============================================  ======  =======  ==========  ====  ==========
commit                                          exact   patches  montecarlo  mart  child wall
==============================================  ======  =======  ==========  ====  ==========
2a95f55: ``_render_particle`` inlined in both   74.5    48.0     10.7        8.7   145.2
now: compiled once, called by both kernels      53.0    12.2     11.9        10.1  90.2
==============================================  ======  =======  ==========  ====  ==========

Numba compiles a helper once per literal argument: ``_nodes`` took three copies (swap ``True`` / ``False``, the zone 2
and an int), ``_nodes_vec``, ``_cut``, ``_u_partial``, ``_setup_axis`` and ``_axis_angles`` two each, and every copy
was optimised again in each kernel that links it. The constants now pass through ``_flag`` / ``_index`` (run-time
values) and each helper compiles once (2026-12-03, ``--threads 1``, the same md5s, two alternating runs each, the
machine ~1.7x slower than in the table above; load 1 from the runs themselves):

==============================================  ===========  =======  ==========  ===========  ===========
commit                                          exact        patches  montecarlo  mart         child wall
==============================================  ===========  =======  ==========  ===========  ===========
e0e2e27: literal constants                      90.1 / 93.7  28.1 /   26.9 /      17.7 / 17.4  166.3 /
                                                             28.0     28.4                     171.3
now: one compile per helper                     66.2 / 75.8  21.2 /   26.8 /      16.7 / 16.4  134.4 /
                                                             23.0     25.8                     144.7
==============================================  ===========  =======  ==========  ===========  ===========

IPR's patches compiled first (``--order patches``, its helpers then compile with it): 84.5 -> 59.7 s of CPU. The
demo's ``warm`` job (``lfstudy.study.warm`` on its first case, cold cache, one thread): 151-178 s -> 137 s, its IPR
part 124-148 -> 104 s. An image costs the same (``bench_particle_image.py``, fast images 0.267-0.280 against
0.265-0.285 ms, the same values).

In the cold suite of 2a95f55 the two kernels compiled in 125.6 and 101.1 s beside the other worker. The render and
patch times are the same within the machine's noise (1500 particles, 600 x 600 px, best of 6: render 0.29-0.38 s,
1500 patches with two trials 0.98-1.62 s, both commits).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

_CHILD = r"""
import hashlib, json, sys, time
import numpy as np, xarray as xr

order = sys.argv[1].split(",")
from lfstudy.optics import PlenopticCamera
from lfstudy.simulate import exact

cam = PlenopticCamera(160, 160, 0.0074, 0.125, 0.5, 50.0, -1.0)
rng = np.random.default_rng(1)
n = 20
x, y, z = rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), rng.uniform(-2, 2, n)
parts = xr.Dataset({k: ("particle", v) for k, v in dict(x=x, y=y, z=z, intensity=np.ones(n)).items()})


def md5(*arrays):
    return hashlib.md5(b"".join(np.ascontiguousarray(np.asarray(a)).tobytes() for a in arrays)).hexdigest()[:12]


def run(stage):
    if stage == "exact":
        return md5(exact.render_exact(cam, parts))
    if stage == "patches":
        from lfstudy.reconstruct.ipr import particle_patches

        return md5(*particle_patches(cam, x, y, z, trials=np.array([[0.01, 0, 0], [0, 0, 0.05]])))
    if stage == "montecarlo":
        from lfstudy.simulate.raytrace import render

        return md5(render(cam, parts, 200, 3, method="montecarlo"))
    if stage == "mart":
        from lfstudy.lightfield import find_lenslet_centers, register, synthetic_pinhole
        from lfstudy.reconstruct import make_grid
        from lfstudy.reconstruct.mart import mart

        centers = find_lenslet_centers(synthetic_pinhole(cam, amplitude=3000, seed=1), cam)
        lf = register(exact.render_exact(cam, parts), centers, cam)
        grid = make_grid(cam, cam.focal_planes(), z_range=(-2.0, 2.0))
        return md5(mart(lf, cam, grid, iterations=2).values)
    raise SystemExit(f"unknown stage {stage!r}")


out = []
for stage in order:
    t0 = time.perf_counter()
    h = run(stage)
    t1 = time.perf_counter()
    run(stage)
    t2 = time.perf_counter()
    out.append(dict(stage=stage, first=t1 - t0, second=t2 - t1, md5=h))
out.append(dict(specializations=len(exact._render_particle.signatures)))
print("JSON" + json.dumps(out))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--order", default="exact,patches,montecarlo,mart")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, NUMBA_NUM_THREADS=str(a.threads))
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-c", _CHILD, a.order], env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("JSON")]
    if r.returncode or not lines:
        sys.exit(f"the child failed (rc {r.returncode}):\n{r.stderr[-4000:]}")
    rows = json.loads(lines[0][4:])
    print(f"{'stage':<11} {'first s':>8} {'second s':>9} {'compile s':>10}  md5")
    for row in rows[:-1]:
        first, second = row["first"], row["second"]
        print(f"{row['stage']:<11} {first:8.2f} {second:9.3f} {first - second:10.2f}  {row['md5']}")
    print(f"child wall {wall:.1f} s (import included); _render_particle specializations: {rows[-1]['specializations']}")


if __name__ == "__main__":
    main()
