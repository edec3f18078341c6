"""Benchmark: full-size (Table 4.3) calibration, registration and refocusing.

Reproduces: docs/architecture.md § "Benchmarks" (calibration and refocus of the full Table 4.3 sensor; the
targets below).

Prints seconds, peak memory and the calibration error against the targets:
calibration <= 30 s and <= 0.05 px RMS; light field -> 32 resized planes
<= 10 s on 2 cores with <= 3 GB peak memory. The lenslet grid is calibrated
from a ray-traced pinhole image (``lfstudy.simulate.render_pinhole`` with the
shipped configs' pinhole settings, as the workflow's calibration stage renders
it), so the spot finder meets real lenslet images (the stopped-down aperture,
diffraction, ray noise), not spots of its own fit model; the error is against
the geometric centres projected from the main-lens centre. The raw image
refocused is synthetic (Gaussian particle spots + Poisson noise).

Run: ``python benchmarks/bench_refocus.py [--threads 2]``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import resource
import time

import numpy as np


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # kB -> GB (Linux)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--planes", type=int, default=32)
    # the shipped configs' pinhole section (config/thesis.yaml, schema defaults)
    ap.add_argument("--pinhole-fnumber", type=float, default=16.0)
    ap.add_argument("--pinhole-count", type=int, default=500_000)
    args = ap.parse_args()
    os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[: args.threads]))
    import dask

    from lfstudy.lightfield.calibrate import expected_centers, find_lenslet_centers
    from lfstudy.lightfield.refocus import focal_stack
    from lfstudy.lightfield.registration import register
    from lfstudy.optics import PlenopticCamera
    from lfstudy.simulate import render_pinhole

    cam = PlenopticCamera(
        4872,
        3248,
        0.0074,
        0.125,
        0.5,
        50.0,
        -1.0,
        lenslet_rotation=0.002,
        lenslet_offset_x=0.01,
        lenslet_offset_y=-0.004,
    )
    print(
        f"camera: {cam.n_pixels_x} x {cam.n_pixels_y} px, {cam.n_lenslets_x} x {cam.n_lenslets_y} lenslets, "
        f"rotation {cam.lenslet_rotation} rad, offset ({cam.lenslet_offset_x}, {cam.lenslet_offset_y}) mm; "
        f"{args.threads} threads"
    )

    # --- calibration from a ray-traced pinhole image ----------------------------
    t0 = time.perf_counter()
    pin = render_pinhole(
        cam, fnumber=args.pinhole_fnumber, count=args.pinhole_count, rays_per_point=100, seed=1, method="montecarlo"
    )
    t_pin = time.perf_counter() - t0
    print(
        f"pinhole image: ray-traced in {t_pin:.2f} s (f/{args.pinhole_fnumber:g}, {args.pinhole_count} points x "
        f"100 rays); pixel mean {float(pin.mean()):.2f}, max {float(pin.max()):.1f} (sum of ray intensities)"
    )
    find_lenslet_centers(pin.isel(row=slice(0, 400), col=slice(0, 400)).values)  # warm-up (imports)
    t0 = time.perf_counter()
    centers = find_lenslet_centers(pin, cam)
    t_cal = time.perf_counter() - t0
    ex, ey = expected_centers(cam)  # projected from the main-lens centre: where a pinhole spot lies
    v = centers["valid"].values
    dx, dy = (centers["cx"].values - ex)[v], (centers["cy"].values - ey)[v]
    rms = float(np.sqrt(np.mean(dx**2 + dy**2)))
    print(
        f"calibration (ray-traced pinhole): {t_cal:.2f} s (target <= 30 s), {int(v.sum())} valid centres of "
        f"{v.size}; error {rms:.4f} px RMS radial (bias {dx.mean():+.4f} x, {dy.mean():+.4f} y; std "
        f"{dx.std():.4f} x, {dy.std():.4f} y; max {np.hypot(dx, dy).max():.3f}) (target <= 0.05 px)"
    )
    del pin

    # --- synthetic raw image: blurred particle spots of random size/brightness -----
    rng = np.random.default_rng(2)
    n = 200_000
    raw = np.zeros(cam.n_pixels_y * cam.n_pixels_x)
    r = rng.integers(1, cam.n_pixels_y - 2, n)
    c = rng.integers(1, cam.n_pixels_x - 2, n)
    a = rng.uniform(50, 500, n)
    for dr, dc, w in ((0, 0, 1.0), (0, 1, 0.4), (1, 0, 0.4), (0, -1, 0.4), (-1, 0, 0.4)):
        raw += np.bincount((r + dr) * cam.n_pixels_x + c + dc, weights=a * w, minlength=raw.size)
    raw = rng.poisson(raw.reshape(cam.n_pixels_y, cam.n_pixels_x) + 2.0).astype(np.float32)
    print(f"raw image: {raw.nbytes / 1e6:.0f} MB float32; peak RSS so far {peak_rss_gb():.2f} GB")

    # --- registration + refocus --------------------------------------------------
    t0 = time.perf_counter()
    lf = register(raw, centers, cam)
    t_reg = time.perf_counter() - t0
    planes = cam.focal_planes(args.planes, depth_scale=1.5)
    # JIT warm-up on a tiny stack (numba caches to disk; first run compiles).
    focal_stack(lf.isel(lrow=slice(0, 2), lcol=slice(0, 2)), cam, planes.isel(plane=slice(0, 1))).compute()
    t0 = time.perf_counter()
    st = focal_stack(lf, cam, planes, resize=True)
    with dask.config.set(scheduler="threads", num_workers=args.threads):
        vol = st.compute()
    t_ref = time.perf_counter() - t0
    print(f"registration: {t_reg:.2f} s -> light field {dict(lf.sizes)} ({lf.nbytes / 1e6:.0f} MB)")
    print(
        f"refocus: {t_ref:.2f} s for {vol.sizes['z']} resized planes of {vol.sizes['y']} x {vol.sizes['x']} "
        f"(target <= 10 s); {lf.size * vol.sizes['z'] / t_ref / 1e6:.0f} M ray-splats/s"
    )
    print(f"registration + refocus: {t_reg + t_ref:.2f} s")
    print(f"peak memory (process max RSS): {peak_rss_gb():.2f} GB (target <= 3 GB)")


if __name__ == "__main__":
    main()
