"""Benchmark of lfstudy.piv.widim (prints its figures; not a test).

1. A 32 x 193 x 289 voxel pair (the thesis' focal-stack size) with a known
   uniform shift, 3 grid levels, in both modes: seconds, peak memory, error.
2. Single-pass correlation throughput (windows/s) against OpenPIV's
   ``openpiv.pyprocess3D.extended_search_area_piv3D`` on the same windows.

Run: ``python benchmarks/bench_piv.py [--threads N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import resource
import time
import tracemalloc

import numpy as np

from lfstudy.piv import peak_locking_index, widim
from lfstudy.piv.synthetic import particle_pair

SHAPE = (32, 193, 289)
SHIFT = (0.8, -1.35, 2.45)  # (z, y, x) voxels


def _errors(ds, shift) -> str:
    inner = ds.isel({d: slice(1, -1) for d in ds.u.dims})
    ok = inner.valid.values
    parts = []
    for c, s in zip(("w", "v", "u"), shift):
        e = inner[c].values[ok] - s
        parts.append(f"{c}: bias {e.mean():+.4f} rms {np.sqrt(np.mean(e**2)):.4f}")
    return "; ".join(parts)


def bench_full(a, b, threads: int) -> None:
    kw = {"window": (16, 48, 48), "spacing": (8, 24, 24), "levels": 3, "workers": threads}
    for mode, order in (("deform", 5), ("deform", 3), ("offset", 5)):
        tracemalloc.start()
        t0 = time.perf_counter()
        ds = widim(a, b, mode=mode, order=order, **kw)
        if mode == "deform":
            mode = f"deform o{order}"
        dt = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        grid = "x".join(str(n) for n in ds.u.shape)
        print(
            f"[{mode}] 3 levels, final window {ds.attrs['final_window']}, grid {grid}, "
            f"{ds.sizes['pass']} passes: {dt:.2f} s (target <= 15 s), "
            f"peak traced memory {peak / 2**20:.0f} MiB"
        )
        print(f"[{mode}]   valid {100 * float(ds.valid.mean()):.1f} %; {_errors(ds, SHIFT)}")
        print(f"[{mode}]   corrector RMS per pass: {np.round(ds.corrector_rms.values, 3).tolist()}")


def bench_peak_locking(threads: int) -> None:
    shape = (32, 64, 96)
    res = {("deform", 5): ([], []), ("deform", 3): ([], []), ("offset", 5): ([], [])}
    for k, f in enumerate(np.arange(0.0, 1.0, 0.1)):
        a, b = particle_pair(shape, (0.0, 0.0, 1.0 + f), density=0.01, seed=200 + k)
        for (mode, order), (m, t) in res.items():
            ds = widim(a, b, window=16, spacing=8, mode=mode, order=order, workers=threads)
            u = ds.u.isel(z=slice(1, -1), y=slice(1, -1), x=slice(1, -1)).values.ravel()
            m.append(u)
            t.append(np.full(u.size, 1.0 + f))
    for (mode, order), (m, t) in res.items():
        m, t = np.concatenate(m), np.concatenate(t)
        mode = f"deform o{order}" if mode == "deform" else mode
        print(
            f"[{mode}] 3-D x-shift sweep 1.0..1.9: peak-locking index "
            f"{peak_locking_index(m, t):.4f} vox, total rms {np.sqrt(np.mean((m - t) ** 2)):.4f} vox"
        )


def bench_throughput(a, b, threads: int) -> None:
    window, spacing = (16, 32, 32), (8, 16, 16)
    t0 = time.perf_counter()
    ds = widim(a, b, window=window, spacing=spacing, mode="offset", max_passes=1, workers=threads)
    ours = time.perf_counter() - t0
    n = ds.u.size
    rate = n / ours
    print(f"single pass, window {window} spacing {spacing}: lfstudy {n} windows in {ours:.3f} s = {rate:.0f} windows/s")
    try:
        from openpiv import pyprocess3D
    except ImportError:
        print("openpiv not installed: OpenPIV comparison skipped (pip install openpiv)")
        return
    overlap = tuple(w - s for w, s in zip(window, spacing))
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):  # silence its tqdm bar
        u, _v, _w = pyprocess3D.extended_search_area_piv3D(
            a.astype(np.float64),
            b.astype(np.float64),
            window_size=window,
            overlap=overlap,
            search_area_size=window,
            subpixel_method="gaussian",
        )
    theirs = time.perf_counter() - t0
    m = u.size
    rate_o = m / theirs
    print(f"single pass, same windows: OpenPIV {m} windows in {theirs:.3f} s = {rate_o:.0f} windows/s")
    print(f"throughput ratio lfstudy / OpenPIV = {rate / rate_o:.1f}x (target >= 5x)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2, help="scipy.fft workers (default 2)")
    args = p.parse_args()
    print(f"cpu count {os.cpu_count()}, fft workers {args.threads}")
    t0 = time.perf_counter()
    a, b = particle_pair(SHAPE, SHIFT, density=0.01, seed=1)
    widim(a[:16, :64, :64], b[:16, :64, :64], window=16)  # warm the numba kernels' cache
    print(f"synthetic pair {SHAPE}, shift (z,y,x) {SHIFT}: rendered in {time.perf_counter() - t0:.2f} s")
    bench_full(a, b, args.threads)
    bench_throughput(a, b, args.threads)
    bench_peak_locking(args.threads)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"process peak RSS {rss:.0f} MiB")


if __name__ == "__main__":
    main()
