"""Exact rendering against the Monte-Carlo tracer on the Table 4.3 camera (issue 16; a script, not a test).

Reproduces: docs/architecture.md § "Benchmarks" (exact against Monte-Carlo images: agreement, speed, memory);
lfstudy/schema.yaml (raytrace.method).

    python benchmarks/bench_render.py [--particles 300] [--crop W H] [--rays 1e3 1e4 1e5 1e6]
        [--ppp 0.01] [--mc-fraction 0.1] [--threads 1] [--skip-agreement] [--skip-speed]
        [--thesis [--thesis-crop W H] [--thesis-seeds S ...]] [--pinhole [--pinhole-seeds S ...]]
        [--study config/demo.yaml [--study-designs N] [--study-cold]]

(a) Agreement. A few hundred particles of intensity 1 (the thesis' 7 mm deep volume) on
    the Table 4.3 camera (``--crop W H``: a central W x H pixel region with its own field of
    view, said in the output). For N rays per particle, the relative L2 difference
    ||MC_N - exact|| / ||exact|| of one Monte-Carlo image against the exact one (with the
    Monte-Carlo's integer ray counts, ``match_ray_counts``), beside the noise a Monte-Carlo
    image has at that N: every pixel is a sum of binomial ray counts, so
    E||MC_N - E_N||^2 = sum over pixels and particles of n_p q (1 - q) <= sum(E_N), and the
    expected relative L2 is sqrt(sum E_N) / ||E_N|| (the (1 - q) factor, q the share of one
    particle's rays in one pixel, is < 1 % here and left out). The fitted slope of
    log(rel. L2) on log(N) should be -0.5.
(b) Speed and memory. ``render_exact`` and the 25,000-ray ``render`` at ``--ppp`` (0.01:
    158,000 particles) on the full 4872 x 3248 sensor, each in its own child process (wall
    time of the render call, peak RSS of the process, and the RSS of a child that only
    imports and compiles, for the baseline). The Monte-Carlo is timed on ``--mc-fraction``
    and twice that fraction of the particles (random subsets) and extrapolated as a fixed cost
    plus a cost per particle (``--mc-fraction 1`` times it on all); the output says so, and
    times the exact render of the first subset too. Peak memory is each child's VmHWM (since its exec).

(c) With ``--thesis``: the thesis' uniform-x case (``config/thesis.yaml``, 0.001 ppp, threshold
    reconstruction; ``--thesis-crop`` for a smaller sensor) through every stage for each seed, with
    ``exact`` + shot noise (25,000 photons per particle, the default sensor) and with the 25,000-ray
    Monte-Carlo (no sensor noise): mean and std of the measured displacement in voxels over the
    valid vectors, and their spread over the seeds.

(d) With ``--pinhole``: the calibration pinhole image (config defaults: f/16, 500,000 points, 100 rays
    per point) on the full sensor, exact (the expected image of the uniform field) and Monte-Carlo:
    render time, and the rms error of the lenslet centres ``find_lenslet_centers`` finds against the
    geometric ones, with the shot noise of 100 photons per point (as a case records it) and without.

(e) With ``--study CONFIG``: a study's own renders (``lfstudy.study.case.case_image`` and ``case_pinhole``, the
    simulate rule's calls, at the config's rays and sensor) for the first ``--study-designs`` designs, exact and
    Monte-Carlo, one process: wall seconds per image, after a warm-up render of each. This is what the choice of
    ``raytrace.method`` costs the study's simulate stage (issue 39: the demo renders with a model IPR does not fit).
    Measured (``--skip-agreement --skip-speed --study config/demo.yaml --study-designs 4 --study-cold``, 1 thread,
    load ~2 on 2 cores), 1536 particles a frame at 4000 rays: exact 0.55 / 0.38 / 0.32 / 0.35 s an image (M -1 pitch
    0.0888 / M -1 0.1184 / M -0.8 0.0888 / M -0.8 0.1184), Monte-Carlo 0.24 / 0.32 / 0.23 / 0.25 s; the pinhole image
    (60,000 points x 40 rays) exact 0.54 / 0.31 / 0.52 / 0.31 s, Monte-Carlo 0.85 / 0.80 / 0.95 / 0.97 s: the demo's 16
    particle images and 4 pinholes take 8.1 s exact, 7.7 s Monte-Carlo (at load 6-10 earlier: 1.1-2.0 s and 0.9 s an
    image). What costs is the compilation: with an empty numba cache (``--study-cold``: a fresh clone's first simulate
    jobs, each compiling until one has written the cache) the first image takes 93.7 s exact, 14.8 s Monte-Carlo. That,
    not the render, is the simulate rule's ~25 s a job in issue 39's fresh-clone timing.

JIT compile time is excluded (both kernels are warmed up on a tiny case first).
Targets (issue 16): exact >= 20x faster than the 25,000-ray tracer, <= 1.5 GB peak.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import resource
import time

import numpy as np

WIDTH, HEIGHT = 4872, 3248  # Table 4.3: KAI-16000, 7.4 um pixels; lenslets 125 um, fl 500 um; fm 50 mm, M -1


def _camera(width: int, height: int):
    from lfstudy.optics import PlenopticCamera

    return PlenopticCamera(width, height, 0.0074, 0.125, 0.5, 50.0, -1.0)


def _warm(threads: int) -> None:
    import numba

    from lfstudy.simulate import exact as ex
    from lfstudy.simulate import raytrace as rt
    from lfstudy.simulate.particles import seed_particles

    numba.set_num_threads(threads)
    cam = _camera(64, 48)
    field = seed_particles(cam, count=8, z_span=4.0, seed=0)
    ex.render_exact(cam, field, 100)
    rt.render(cam, field, 100, 0, method="montecarlo")


# ------------------------------------------------------------------ (a) agreement
def agreement(args: argparse.Namespace) -> None:
    from lfstudy.simulate import exact as ex
    from lfstudy.simulate import raytrace as rt
    from lfstudy.simulate.particles import seed_particles

    width, height = args.crop if args.crop else (WIDTH, HEIGHT)
    cam = _camera(width, height)
    where = "full sensor" if not args.crop else f"central crop {width} x {height} px of the 4872 x 3248 sensor"
    field = seed_particles(cam, count=args.particles, z_span=7.0, intensity=(1.0, 1.0), seed=16)
    print(f"(a) agreement: {args.particles} particles (intensity 1, z span 7 mm), Table 4.3 optics, {where}")
    print(f"    threads {args.threads}; one Monte-Carlo image per N (seed 1)")
    head = f"{'N rays':>9} {'rel L2 MC-exact':>16} {'expected MC noise':>18} {'ratio':>6} {'MC s':>7} {'exact s':>8}"
    print("    " + head)
    ns, rel = [], []
    for n in args.rays:
        n = int(n)
        t0 = time.perf_counter()
        exact = ex.render_exact(cam, field, n, match_ray_counts=True).values
        te = time.perf_counter() - t0
        t0 = time.perf_counter()
        mc = rt.render(cam, field, n, 1, method="montecarlo").values
        tm = time.perf_counter() - t0
        r = float(np.linalg.norm(mc - exact) / np.linalg.norm(exact))
        expected = float(math.sqrt(exact.sum()) / np.linalg.norm(exact))
        ns.append(n)
        rel.append(r)
        print(f"    {n:>9.0e} {r:>16.4e} {expected:>18.4e} {r / expected:>6.3f} {tm:>7.1f} {te:>8.2f}")
        del mc, exact
    if len(ns) >= 2:
        slope = float(np.polyfit(np.log(ns), np.log(rel), 1)[0])
        print(f"    fitted slope of log(rel L2) on log(N): {slope:.3f} (1/sqrt(N): -0.5)")


# ------------------------------------------------------------------ (b) speed
def _child(kind: str, ppp: float, fraction: float, threads: int, rays: int, q: mp.Queue) -> None:
    """One render in a fresh process: (seconds, particles rendered, peak RSS GB)."""
    from lfstudy.simulate import exact as ex
    from lfstudy.simulate import raytrace as rt
    from lfstudy.simulate.particles import seed_particles

    _warm(threads)
    cam = _camera(WIDTH, HEIGHT)
    field = seed_particles(cam, ppp=ppp, z_span=7.0, intensity=(1.0, 1.0), seed=2011)
    if fraction < 1.0:
        rng = np.random.default_rng(5)
        keep = np.sort(rng.choice(field.sizes["particle"], round(fraction * field.sizes["particle"]), replace=False))
        field = field.isel(particle=keep)
    t0 = time.perf_counter()
    if kind == "exact":
        img = ex.render_exact(cam, field, rays)
    elif kind == "montecarlo":
        img = rt.render(cam, field, rays, 1, method="montecarlo")
    else:  # baseline: imports, compiled kernels and the particle field only
        img = None
    dt = time.perf_counter() - t0
    del img
    q.put((dt, int(field.sizes["particle"]), _peak_rss_gb()))


def _peak_rss_gb() -> float:
    """This process' peak resident memory since exec (VmHWM; ru_maxrss would carry the parent's peak
    over fork + exec)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024**2
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # pragma: no cover - not Linux


def _in_child(*a) -> tuple[float, int, float]:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_child, args=(*a, q))
    p.start()
    out = q.get()
    p.join()
    return out


def speed(args: argparse.Namespace) -> None:
    print(
        f"(b) speed: Table 4.3 camera, full 4872 x 3248 sensor, {args.ppp} ppp, {args.speed_rays} rays/particle, "
        f"threads {args.threads}"
    )
    _, _, mb = _in_child("baseline", args.ppp, 1.0, args.threads, args.speed_rays)
    te, ne, me = _in_child("exact", args.ppp, 1.0, args.threads, args.speed_rays)
    tm, nm, mm = _in_child("montecarlo", args.ppp, args.mc_fraction, args.threads, args.speed_rays)
    ts, _, _ = _in_child("exact", args.ppp, args.mc_fraction, args.threads, args.speed_rays)
    if nm == ne:
        tfull, note = tm, ""
    else:
        # A render has a fixed part that does not grow with the particles (allocating and zeroing the
        # 127 MB float64 image and the chunk buffers: 1.6 s at 2 threads on the 2-core development
        # machine). A second, twice as large subset separates the two, and the full-set time is
        # extrapolated as fixed + per-particle x n (scaling the subset's time by n/nm would multiply
        # the fixed part too, in the exact method's favour).
        f2 = min(2.0 * args.mc_fraction, 1.0)
        tm2, nm2, mm2 = _in_child("montecarlo", args.ppp, f2, args.threads, args.speed_rays)
        mm = max(mm, mm2)
        per = (tm2 - tm) / (nm2 - nm)
        tfull = tm + per * (ne - nm)
        note = (
            f" (extrapolated from subsets of {nm} and {nm2} particles: {tm:.1f} s and {tm2:.1f} s, i.e. "
            f"{per * 1e6:.0f} us/particle + {tm - per * nm:.2f} s fixed)"
        )
    print(f"    particles: {ne}; baseline process (imports, compiled kernels, particles): {mb:.2f} GB peak RSS")
    print(f"    exact:       {te:8.1f} s ({te / ne * 1e6:.0f} us/particle), peak RSS {me:.2f} GB")
    print(f"    Monte-Carlo: {tfull:8.1f} s{note}, peak RSS {mm:.2f} GB")
    print(f"    exact is {tfull / te:.1f}x faster than the {args.speed_rays}-ray Monte-Carlo (target >= 20x)")
    print(f"    on the Monte-Carlo's first subset: exact {ts:.1f} s vs Monte-Carlo {tm:.1f} s: {tm / ts:.1f}x")


# ------------------------------------------------------------------ (c) thesis uniform x
def _thesis_case(raw: dict, seed: int, method: str, out) -> dict[str, float]:
    """One thesis uniform-x case through every stage (the Snakemake rules' functions, in process)."""
    import copy

    from lfstudy import io, workflow
    from lfstudy.study.config import stage_config, sweep_of, validate_config

    cfg = copy.deepcopy(raw)
    cfg["seed"] = seed
    cfg["raytrace"]["method"] = method
    cfg.setdefault("sensor", {})["shot_noise"] = method == "exact"  # the Monte-Carlo image has its ray noise
    cfg = validate_config(cfg)
    case = sweep_of(cfg).cases()[0]
    sc = {st: stage_config(cfg, case, st) for st in ("particles", "displace", "simulate", "pinhole", "calibrate")}
    sc.update({st: stage_config(cfg, case, st) for st in ("register", "refocus", "reconstruct", "piv", "errors")})
    d = out / f"{method}-{seed}"
    d.mkdir(parents=True)
    t0 = time.perf_counter()
    workflow.run_particles(sc["particles"], d / "pa.zarr")
    workflow.run_displace(sc["displace"], d / "pa.zarr", d / "pb.zarr")
    for f in "ab":
        workflow.run_simulate(sc["simulate"], f, d / f"p{f}.zarr", d / f"raw_{f}.zarr", d / f"raw_{f}.tif")
    t_sim = time.perf_counter() - t0
    workflow.run_pinhole(sc["pinhole"], d / "pinhole.zarr", d / "pinhole.tif")
    workflow.run_calibrate(sc["calibrate"], d / "pinhole.zarr", d / "centers.zarr")
    for f in "ab":
        workflow.run_register(sc["register"], d / f"raw_{f}.zarr", d / "centers.zarr", d / f"lf_{f}.zarr")
        workflow.run_refocus(sc["refocus"], d / f"lf_{f}.zarr", d / f"stack_{f}.zarr")
        workflow.run_reconstruct(
            sc["reconstruct"], d / f"stack_{f}.zarr", d / f"lf_{f}.zarr", d / "centers.zarr", d / f"vol_{f}.zarr"
        )
    workflow.run_piv(sc["piv"], d / "vol_a.zarr", d / "vol_b.zarr", d / "piv.zarr")
    piv = io.open_zarr(d / "piv.zarr").load()
    ok = piv["valid"].values
    res = {"valid": float(ok.mean()), "sim_s": t_sim, "total_s": time.perf_counter() - t0}
    for comp, ax in (("u", "x"), ("v", "y"), ("w", "z")):
        vals = piv[comp].values[ok]
        res[f"{ax}_mean"], res[f"{ax}_std"] = float(np.mean(vals)), float(np.std(vals))
    return res


def thesis(args: argparse.Namespace) -> None:
    import tempfile
    from pathlib import Path

    from lfstudy.config import read_yaml

    raw = read_yaml(Path(__file__).resolve().parents[1] / "config" / "thesis.yaml")
    w, h = args.thesis_crop
    raw["camera"]["sensor"].update(n_pixels_x=w, n_pixels_y=h)
    raw["sweep"] = {"ppp": [0.001], "flow": ["uniform_x"]}
    where = "full sensor" if (w, h) == (WIDTH, HEIGHT) else f"a {w} x {h} px sensor (central crop of Table 4.3)"
    print(
        f"(c) thesis uniform x (sec. 7.1: 0.5625 mm = 4.5 voxels, 0.001 ppp, threshold), {where}, threads "
        f"{args.threads}; exact + shot noise at 25,000 photons/particle vs Monte-Carlo 25,000 rays (no sensor noise)"
    )
    head = f"{'method':<11} {'seed':>5} {'x mean':>8} {'x std':>7} {'y std':>7} {'z std':>7} {'valid':>6} {'sim s':>6}"
    print("    " + head)
    with tempfile.TemporaryDirectory(prefix="bench-render-") as tmp:
        for method in ("exact", "montecarlo"):
            rows = []
            for seed in args.thesis_seeds:
                r = _thesis_case(raw, seed, method, Path(tmp))
                rows.append(r)
                print(
                    f"    {method:<11} {seed:>5} {r['x_mean']:>8.3f} {r['x_std']:>7.3f} {r['y_std']:>7.3f} "
                    f"{r['z_std']:>7.3f} {r['valid']:>6.1%} {r['sim_s']:>6.1f}"
                )
            xm = np.array([r["x_mean"] for r in rows])
            xs = np.array([r["x_std"] for r in rows])
            print(
                f"    {method:<11} {'all':>5} {xm.mean():>8.3f} {xs.mean():>7.3f}   (run-to-run spread of the x mean "
                f"{xm.std(ddof=1) if xm.size > 1 else float('nan'):.3f}, of the x std "
                f"{xs.std(ddof=1) if xs.size > 1 else float('nan'):.3f})"
            )
    print("    thesis: x mean 4.45 (object-frame sign), sigma 0.07 voxels; displacements in voxels")


# ------------------------------------------------------------------ (d) pinhole image
def pinhole(args: argparse.Namespace) -> None:
    import numba

    from lfstudy.lightfield.calibrate import expected_centers, find_lenslet_centers
    from lfstudy.simulate import raytrace as rt

    numba.set_num_threads(args.threads)
    cam = _camera(WIDTH, HEIGHT)
    for method in ("exact", "montecarlo"):  # compile
        rt.render_pinhole(_camera(300, 200), count=2000, method=method)
    ex_, ey_ = expected_centers(cam)
    print(
        f"(d) pinhole image: full sensor, f/16, 500,000 points x 100 rays, threads {args.threads}; lenslet-centre "
        f"error against the geometric centres (px, {ex_.size} lenslets)"
    )
    for seed in args.pinhole_seeds:
        for method, noise, label in (
            ("montecarlo", False, "montecarlo (ray noise)"),
            ("exact", True, "exact + shot noise"),
            ("exact", False, "exact"),
        ):
            t0 = time.perf_counter()
            img = rt.render_pinhole(cam, seed=seed, method=method, shot_noise=noise)
            dt = time.perf_counter() - t0
            c = find_lenslet_centers(img, cam)
            ok = c["valid"].values.astype(bool)
            err = np.hypot(c["cx"].values - ex_, c["cy"].values - ey_)[ok]
            print(
                f"    seed {seed} {label:<24} {dt:6.2f} s  rms {np.sqrt(np.mean(err**2)):.4f} px  valid {int(ok.sum())}"
            )


# ------------------------------------------------------------------ (e) a study's renders
def study(args: argparse.Namespace) -> None:
    """Time a study config's particle images and pinhole image, exact against Monte-Carlo."""
    import copy

    from lfstudy.study import case as sc
    from lfstudy.study.config import case_config, expand_cases, load_config

    cfg = load_config(args.study)
    seen, designs = set(), []
    for case in expand_cases(cfg):
        ccfg = case_config(cfg, case)
        if ccfg["calib_id"] not in seen:
            seen.add(ccfg["calib_id"])
            designs.append(ccfg)
    designs = designs[: args.study_designs]
    rays = designs[0]["raytrace"]["rays_per_particle"]
    print(f"(e) {args.study}: {len(designs)} design(s), {rays} rays/particle, threads {args.threads}, wall s per image")
    head = f"{'design (calibration group)':<52} {'particles':>9} {'exact':>7} {'MC':>7} {'pinhole exact':>14} {'MC':>7}"
    print("    " + head)
    for ccfg in designs:
        field = sc.case_particles(ccfg)
        row = {}
        for method in ("exact", "montecarlo"):
            c = copy.deepcopy(ccfg)
            c["raytrace"]["method"] = method
            sc.case_image(c, field.isel(particle=slice(0, 20)), "a")  # warm-up: compile, caches
            t0 = time.perf_counter()
            sc.case_image(c, field, "a")
            row[method] = time.perf_counter() - t0
            t0 = time.perf_counter()
            sc.case_pinhole(c)
            row[method + "_pinhole"] = time.perf_counter() - t0
        print(
            f"    {ccfg['calib_id']:<52} {field.sizes['particle']:>9} {row['exact']:>7.2f} {row['montecarlo']:>7.2f}"
            f" {row['exact_pinhole']:>14.2f} {row['montecarlo_pinhole']:>7.2f}"
        )


def _cold_child(config: str, method: str, q: mp.Queue) -> None:
    """One simulate job's render (the first design's frame a) in a process whose numba cache is empty."""
    import copy

    from lfstudy.study import case as sc
    from lfstudy.study.config import case_config, expand_cases, load_config

    cfg = load_config(config)
    ccfg = copy.deepcopy(case_config(cfg, expand_cases(cfg)[0]))
    ccfg["raytrace"]["method"] = method
    field = sc.case_particles(ccfg)
    t0 = time.perf_counter()
    sc.case_image(ccfg, field, "a")
    q.put(time.perf_counter() - t0)


def study_cold(args: argparse.Namespace) -> None:
    """A study's first render with an empty numba cache (a fresh clone's first simulate jobs), exact and
    Monte-Carlo, each in a child process with its own empty ``NUMBA_CACHE_DIR``."""
    import tempfile

    print(f"(e) cold numba cache, {args.study}, first design, frame a (compilation + render, wall s):")
    for method in ("exact", "montecarlo"):
        with tempfile.TemporaryDirectory() as tmp:
            old = os.environ.get("NUMBA_CACHE_DIR")
            os.environ["NUMBA_CACHE_DIR"] = tmp
            try:
                ctx = mp.get_context("spawn")
                q = ctx.Queue()
                p = ctx.Process(target=_cold_child, args=(args.study, method, q))
                p.start()
                dt = q.get()
                p.join()
            finally:
                if old is None:
                    os.environ.pop("NUMBA_CACHE_DIR")
                else:
                    os.environ["NUMBA_CACHE_DIR"] = old
        print(f"    {method:<11} {dt:7.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--crop", type=int, nargs=2, metavar=("W", "H"), default=None)
    ap.add_argument("--rays", type=float, nargs="+", default=[1e3, 1e4, 1e5, 1e6])
    ap.add_argument("--ppp", type=float, default=0.01)
    ap.add_argument("--speed-rays", type=int, default=25_000)
    ap.add_argument("--mc-fraction", type=float, default=0.1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--skip-agreement", action="store_true")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--thesis", action="store_true", help="run (c), the thesis uniform-x comparison")
    ap.add_argument("--thesis-crop", type=int, nargs=2, metavar=("W", "H"), default=[WIDTH, HEIGHT])
    ap.add_argument("--thesis-seeds", type=int, nargs="+", default=[2011, 2012])
    ap.add_argument("--pinhole", action="store_true", help="run (d), the calibration pinhole image")
    ap.add_argument("--pinhole-seeds", type=int, nargs="+", default=[3, 4])
    ap.add_argument("--study", default=None, help="run (e), a study config's renders, exact and Monte-Carlo")
    ap.add_argument("--study-designs", type=int, default=1)
    ap.add_argument("--study-cold", action="store_true", help="with --study: first render, empty numba cache")
    args = ap.parse_args()
    os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))
    if not args.skip_agreement:
        _warm(args.threads)
        agreement(args)
    if not args.skip_speed:
        speed(args)
    if args.thesis:
        thesis(args)
    else:
        print("(c) thesis uniform-x displacement statistics, exact + shot noise vs Monte-Carlo: not run (--thesis)")
    if args.pinhole:
        pinhole(args)
    if args.study:
        study(args)
        if args.study_cold:
            study_cold(args)


if __name__ == "__main__":
    main()
