"""Ray-tracer throughput and memory on the full Table 4.3 sensor (a script, not a test).

Reproduces: docs/architecture.md § "Benchmarks" (rays/s at 1 and 2 threads, peak memory, ratio to NumPy; the
targets below).

    python benchmarks/bench_raytrace.py [--rays 25000] [--ppp 0.001] [--threads 1 2]

Prints rays/s for each thread count (numba.set_num_threads), wall time, peak
resident memory (ru_maxrss of this process, which includes the interpreter,
numba/LLVM and the particle field) and the speed ratio against a plain
vectorised NumPy implementation of the same model on a small case.
JIT compile time is excluded: the kernel is warmed up on a tiny case first.
Targets: >= 30 million rays/s on 2 cores, <= 1.5 GB peak.
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import numba
import numpy as np

from lfstudy.optics import PlenopticCamera
from lfstudy.simulate import raytrace as rt
from lfstudy.simulate.particles import seed_particles


def numpy_render(
    camera: PlenopticCamera, particles, rays_per_particle: int, seed: int, block: int = 2_000_000
) -> np.ndarray:
    """The same physics as :func:`lfstudy.simulate.raytrace.render`, vectorised in NumPy (PCG64 streams).

    Solid-angle ray counts, uniform aperture sampling, main lens, diffraction at
    the lenslet plane, lenslet (lens + prism), diffraction at the sensor,
    pixel binning; rays processed in blocks to bound memory.
    """
    x, y, z, inten = (particles[v].values for v in ("x", "y", "z", "intensity"))
    nrays = rt.ray_counts(camera, particles, rays_per_particle)
    pid = np.repeat(np.arange(x.size), nrays)
    rng = np.random.default_rng(seed)
    so, si, fm, fl = camera.so, camera.si, camera.main_focal_length, camera.lenslet_focal_length
    pl, pp, rad = camera.lenslet_pitch, camera.pixel_pitch, camera.aperture_diameter / 2
    c, s = math.cos(camera.lenslet_rotation), math.sin(camera.lenslet_rotation)
    nlx, nly = camera.n_lenslets_x, camera.n_lenslets_y
    cx0, cy0 = (nlx - 1) / 2, (nly - 1) / 2
    ny, nx = camera.n_pixels_y, camera.n_pixels_x
    image = np.zeros(ny * nx)
    for b in range(0, pid.size, block):
        p = pid[b : b + block]
        n = p.size
        r = rad * np.sqrt(rng.random(n))
        a = 2 * np.pi * rng.random(n)
        ax, ay = r * np.cos(a), r * np.sin(a)
        d = so + z[p]
        tx = (ax - x[p]) / d - ax / fm
        ty = (ay - y[p]) / d - ay / fm
        lx = ax + si * tx + camera.sigma_lenslet_plane * rng.standard_normal(n)
        ly = ay + si * ty + camera.sigma_lenslet_plane * rng.standard_normal(n)
        dx, dy = lx - camera.lenslet_offset_x, ly - camera.lenslet_offset_y
        fj = np.floor((c * dx + s * dy) / pl + cx0 + 0.5)
        fi = np.floor(cy0 - (-s * dx + c * dy) / pl + 0.5)
        gx, gy = (fj - cx0) * pl, (cy0 - fi) * pl
        scx = c * gx - s * gy + camera.lenslet_offset_x
        scy = s * gx + c * gy + camera.lenslet_offset_y
        sx = lx + fl * (tx - (lx - scx) / fl) + camera.sigma_sensor_plane * rng.standard_normal(n)
        sy = ly + fl * (ty - (ly - scy) / fl) + camera.sigma_sensor_plane * rng.standard_normal(n)
        col = np.floor((sx + camera.sensor_width / 2) / pp)
        row = np.floor((camera.sensor_height / 2 - sy) / pp)
        ok = (fj >= 0) & (fj < nlx) & (fi >= 0) & (fi < nly) & (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
        image += np.bincount((row[ok] * nx + col[ok]).astype(np.int64), weights=inten[p[ok]], minlength=ny * nx)
    return image.reshape(ny, nx)


def peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # kB on Linux


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rays", type=int, default=25_000)
    ap.add_argument("--ppp", type=float, default=0.001)
    ap.add_argument("--z-span", type=float, default=7.0)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--numpy-particles", type=int, default=200)
    args = ap.parse_args()

    cam = PlenopticCamera(4872, 3248, 0.0074, 0.125, 0.5, 50.0, -1.0)  # Table 4.3
    field = seed_particles(cam, ppp=args.ppp, z_span=args.z_span, seed=1)
    n = field.sizes["particle"]
    print(
        f"Table 4.3 sensor {cam.n_pixels_x} x {cam.n_pixels_y}, {n:,} particles ({args.ppp} ppp), "
        f"{args.rays:,} rays/particle, z span {args.z_span} mm, {rt.DEFAULT_CHUNKS} chunk buffers"
    )
    print(f"estimated render memory {rt.memory_estimate(cam, n) / 1e9:.2f} GB")
    t = time.perf_counter()
    rt.render(cam, field.isel(particle=slice(0, 4)), 10, 0, method="montecarlo")  # JIT (or cache load), excluded below
    print(f"warm-up on a tiny case (compile or cache load, excluded): {time.perf_counter() - t:.2f} s")
    print(f"peak RSS after warm-up: {peak_gb():.2f} GB")

    ref = None
    for nt in args.threads:
        numba.set_num_threads(min(nt, numba.config.NUMBA_NUM_THREADS))
        t, c = time.perf_counter(), time.process_time()
        img = rt.render(cam, field, args.rays, 3, method="montecarlo")
        dt, dc = time.perf_counter() - t, time.process_time() - c
        rays = img.attrs["rays_traced"]
        # CPU seconds / threads is the wall time the run would take on idle cores
        # (a shared machine inflates the wall time, not the CPU time).
        print(
            f"threads={numba.get_num_threads()}: {rays:,} rays in {dt:.2f} s wall -> {rays / dt / 1e6:.1f} M rays/s; "
            f"CPU {dc:.2f} s -> {rays / dc / 1e6:.1f} M rays per CPU-second; peak RSS so far {peak_gb():.2f} GB"
        )
        if ref is None:
            ref = img.values
        else:
            print(f"  bit-identical to the first run: {np.array_equal(ref, img.values)}")
        del img

    # NumPy reference on a small case (same physics, its own random streams).
    small = field.isel(particle=slice(0, args.numpy_particles))
    numba.set_num_threads(min(max(args.threads), numba.config.NUMBA_NUM_THREADS))
    t, c = time.perf_counter(), time.process_time()
    img = rt.render(cam, small, args.rays, 3, method="montecarlo")
    t_nb, c_nb = time.perf_counter() - t, time.process_time() - c
    t, c = time.perf_counter(), time.process_time()
    ref_np = numpy_render(cam, small, args.rays, 3)
    t_np, c_np = time.perf_counter() - t, time.process_time() - c
    rays = img.attrs["rays_traced"]
    print(
        f"small case, {small.sizes['particle']} particles, {rays:,} rays: numba ({numba.get_num_threads()} threads) "
        f"{t_nb:.2f} s wall / {c_nb:.2f} s CPU, NumPy {t_np:.2f} s wall / {c_np:.2f} s CPU: "
        f"ratio {t_np / t_nb:.1f}x wall, {c_np / c_nb:.1f}x CPU"
    )
    print(
        f"  total signal numba {img.values.sum():.0f} vs NumPy {ref_np.sum():.0f} (differ only by the random streams)"
    )
    print(f"peak RSS (whole run): {peak_gb():.2f} GB")


if __name__ == "__main__":
    main()
