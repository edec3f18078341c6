"""Rule bodies of the Snakefile: one function per rule, I/O at the edges.

Keeping the rule bodies here (not in the Snakefile) makes them importable,
testable and usable from a notebook. Every output is written atomically
(``lfstudy.io``), so an interrupted job leaves no half-written store.

The science of one case comes from the case layer (:mod:`lfstudy.study.case`);
this module only reads its inputs, calls it and writes the outputs.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import time
import traceback
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from lfstudy import io
from lfstudy.compute import dask_scheduler, describe
from lfstudy.study import case as cl

__all__ = [
    "logged",
    "set_threads",
    "main",
    "run_optics",
    "run_particles",
    "run_displace",
    "run_simulate",
    "run_pinhole",
    "run_calibrate",
    "run_register",
    "run_refocus",
    "run_reconstruct",
    "run_depth_calibration",
    "run_piv",
    "run_errors",
    "run_study",
    "run_report",
    "run_warm",
    "DASK_STAGES",
]


@contextlib.contextmanager
def logged(path: str | Path) -> Iterator[None]:
    """Send a rule's prints, warnings, progress bars and traceback to its log file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(path, "w") as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        handler = logging.StreamHandler(fh)
        logging.getLogger().addHandler(handler)
        print(f"started {time.strftime('%Y-%m-%d %H:%M:%S')}", flush=True)
        try:
            yield
        except BaseException:
            traceback.print_exc(file=fh)
            fh.flush()
            # Snakemake shows stderr of the failing job: say where the details are.
            print(f"lfstudy: rule failed, see {path}", file=sys.__stderr__)
            raise
        finally:
            print(f"finished in {time.perf_counter() - t0:.2f} s", flush=True)
            logging.getLogger().removeHandler(handler)


def set_threads(n: int) -> None:
    """Honour Snakemake's ``threads:`` in numba and dask (they ignore OMP_NUM_THREADS)."""
    import dask
    import numba

    n = max(1, int(n))
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    dask.config.set(scheduler="threads", num_workers=n)


def _write_json(obj: Mapping[str, Any], path: str | Path) -> None:
    with io.atomic_path(Path(path)) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, default=str))


# ----------------------------------------------------------------- stages
def run_optics(ccfg: Mapping[str, Any], out_json: str | Path, out_planes: str | Path) -> None:
    """Camera stage: derived parameters (JSON) and the refocus-plane table (zarr)."""
    cam = cl.case_camera(ccfg)
    planes = cl.case_planes(ccfg, cam)
    planes.attrs.update(io.provenance(ccfg, None))
    io.write_zarr(planes, out_planes)
    _write_json({"stage_id": ccfg["stage_id"], **{k: str(v) for k, v in cam.summary().items()}}, out_json)


def run_particles(ccfg: Mapping[str, Any], out: str | Path) -> None:
    """Seed the first-exposure particle field."""
    io.write_zarr(cl.case_particles(ccfg), out)


def run_displace(ccfg: Mapping[str, Any], particles: str | Path, out: str | Path) -> None:
    """Second-exposure particle field: the first one advected by the case's flow."""
    io.write_zarr(cl.case_displaced(ccfg, io.open_zarr(particles).load()), out)


def run_simulate(
    ccfg: Mapping[str, Any], frame: str, particles: str | Path, out_zarr: str | Path, out_tiff: str | Path
) -> None:
    """Ray-trace one raw plenoptic image (frame ``a`` or ``b``)."""
    img = cl.case_image(ccfg, io.open_zarr(particles).load(), frame, progress=True)
    io.write_zarr(img, out_zarr, name="intensity")
    io.write_tiff(img, out_tiff, dtype="float32")


def run_pinhole(ccfg: Mapping[str, Any], out_zarr: str | Path, out_tiff: str | Path) -> None:
    """Ray-trace the calibration pinhole image (sec. 5.1)."""
    img = cl.case_pinhole(ccfg, progress=True)
    io.write_zarr(img, out_zarr, name="intensity")
    io.write_tiff(img, out_tiff, dtype="float32")


def run_calibrate(ccfg: Mapping[str, Any], pinhole: str | Path, out: str | Path) -> None:
    """Find every lenslet centre in the pinhole image (automatic grid detection)."""
    from lfstudy.lightfield.calibrate import find_lenslet_centers

    img = io.open_zarr(pinhole, name="intensity").load()
    centers = find_lenslet_centers(img, cl.case_camera(ccfg))
    centers.attrs.update(io.provenance(ccfg, None))
    io.write_zarr(centers, out)


def run_register(ccfg: Mapping[str, Any], raw: str | Path, centers: str | Path, out: str | Path) -> None:
    """Raw image → 4-D light field (eqs 5.2–5.9)."""
    from lfstudy.lightfield.registration import register

    lf = register(io.open_zarr(raw, name="intensity").load(), io.open_zarr(centers).load(), cl.case_camera(ccfg))
    lf.attrs.update(io.provenance(ccfg, None))
    io.write_zarr(lf, out, name=lf.name or "radiance")


def run_volcal(ccfg: Mapping[str, Any], centers: str | Path, out: str | Path) -> None:
    """The dot-target volumetric calibration of a design (:func:`lfstudy.study.case.case_volcal`)."""
    cal = cl.case_volcal(ccfg, io.open_zarr(centers).load())
    a = cal.attrs
    print(
        f"volumetric calibration: {a['valid_subapertures']} sub-apertures from {a['n_dots']} dots, fit residual "
        f"{a['fit_rms_lenslets']:.3g} lenslets, held-out depth {a['holdout_depth']} mm: "
        f"{a['holdout_rms_lenslets']:.3g}",
        flush=True,
    )
    io.write_zarr(cal, out)


def _volcal(path: str | Path | None) -> Any:
    """The volumetric calibration a stage samples its planes through, or None ('' from the Snakefile)."""
    return io.open_zarr(path).load() if path else None


def run_refocus(ccfg: Mapping[str, Any], lightfield: str | Path, out: str | Path, volcal: str | Path = "") -> None:
    """Light field → focal stack (z, y, x), resized to constant magnification; with
    ``refocus.model: volumetric`` sampled through the dot-target calibration ``volcal``."""
    stack = cl.case_stack(ccfg, io.open_array(lightfield).load(), _volcal(volcal))
    stack.attrs.update(io.provenance(ccfg, None))
    io.write_zarr(stack, out, name=stack.name or "intensity", progress=True)  # one task per plane


def run_reconstruct(
    ccfg: Mapping[str, Any],
    stack: str | Path,
    lightfield: str | Path,
    centers: str | Path,
    out: str | Path,
    particles: str | Path | None = None,
    volcal: str | Path = "",
) -> None:
    """Focal stack, light field and calibration → particle volume on the reconstruction grid; for a
    method that fits particles (``ipr``) also its particle list (``particles``: the store it goes to,
    required for such a method and refused for the others: the Snakefile declares it per case, and
    passes ``''`` for none). ``volcal``: the dot-target calibration where ``refocus.model`` is
    ``volumetric`` (MART's and IPR's beams go through it).

    The list is written before the volume, both atomically: an interrupted job leaves no volume
    without its list.
    """
    from lfstudy.reconstruct import gives_particles

    method = ccfg["reconstruct"]["method"]
    if gives_particles(method) != bool(particles):
        need = "needs a particle-list path" if gives_particles(method) else "fits no particles: no particle-list path"
        raise ValueError(f"reconstruct stage: reconstruct.method = {method!r} {need} (got {particles!r})")
    vol, parts = cl.case_reconstruction(
        ccfg,
        io.open_array(stack),
        io.open_array(lightfield).load(),
        io.open_zarr(centers).load(),
        progress=True,
        calibration=_volcal(volcal),
    )
    prov = io.provenance(ccfg, None)
    if parts is not None:
        parts.attrs.update(prov)
        print(f"{parts.sizes['particle']} particles", flush=True)
        io.write_zarr(parts, particles)
    vol.attrs.update(prov)
    io.write_zarr(vol, out, name=vol.name or "intensity")


def run_depth_calibration(
    ccfg: Mapping[str, Any], centers: str | Path, out: str | Path, volcal: str | Path = ""
) -> None:
    """Depth gain of a design and its processing from a traversed seeded volume (:mod:`lfstudy.piv.depth`);
    ``volcal``: the dot-target calibration where ``refocus.model`` is ``volumetric``."""
    cal = cl.case_depth_calibration(ccfg, io.open_zarr(centers).load(), progress=True, calibration=_volcal(volcal))
    sd = cal["gain_total_sd"].values if "gain_total_sd" in cal else None
    for i, (s, v, g) in enumerate(zip(cal["shift"].values, cal["shift_voxels"].values, cal["gain_total"].values)):
        layers = cal["gain"].sel(shift=s).values
        spread = f" +- {sd[i]:.3f} between {cal.attrs['repeats']} volumes" if sd is not None else ""
        print(
            f"depth gain {g:.3f}{spread} (layers {layers.min():.3f}-{layers.max():.3f}), "
            f"{s:.4g} mm ({v:.2g} voxel) traverse"
        )
    io.write_zarr(cal, out)


def run_piv(
    ccfg: Mapping[str, Any],
    vol_a: str | Path,
    vol_b: str | Path,
    out: str | Path,
    depth: str | Path | None = None,
    particles_a: str | Path | None = None,
    particles_b: str | Path | None = None,
) -> None:
    """3-D WIDIM PIV between the two reconstructed volumes, the axial displacement mapped back
    through the design's depth response when a depth calibration (``depth``) is given.

    With ``piv.particles: ptv`` the particle lists the reconstruction wrote beside the volumes
    (``particles_a``, ``particles_b``: required then, refused otherwise) are tracked about the WIDIM
    field and binned on its grid (:func:`lfstudy.study.case.case_ptv`): that is the stored result, the
    WIDIM vectors kept beside it (``piv_u_mm``, ...). With ``piv.particles: paired`` the same lists
    are paired about the WIDIM field and WIDIM runs again on volumes of the paired particles alone
    (:func:`lfstudy.study.case.case_paired_piv`). ``''`` (from the Snakefile) means none.
    """
    from lfstudy.piv.depth import correct_depth
    from lfstudy.piv.ptv import PARTICLE_MODES

    mode = ccfg["piv"].get("particles", "none")
    tracked = mode in PARTICLE_MODES
    lists = [p for p in (particles_a, particles_b) if p]
    if tracked != bool(lists) or len(lists) not in (0, 2):
        need = "needs both frames' particle lists" if tracked else "tracks no particles: no particle lists"
        raise ValueError(f"piv stage: piv.particles = {mode!r} {need} (got {lists})")
    if tracked and depth:
        raise ValueError(f"piv stage: piv.particles = {mode!r} takes no depth calibration (depth_calibration.enabled)")
    a, b = io.open_array(vol_a).load(), io.open_array(vol_b).load()
    res = cl.case_piv(ccfg, a, b, progress=True)
    if depth:  # Snakemake passes '' where the calibration is disabled
        res = correct_depth(res, io.open_zarr(depth).load())
    if tracked:
        res = cl.case_tracked_piv(ccfg, res, a, b, *[io.open_zarr(p).load() for p in lists])
        n = res.attrs[f"{mode}_tracks"], res.attrs[f"{mode}_particles_a"], res.attrs[f"{mode}_particles_b"]
        print(
            f"{mode}: {n[0]} tracks of {n[1]} and {n[2]} particles, {100 * float(res['valid'].mean()):.1f} % "
            f"valid vectors ({res.attrs[f'{mode}_seconds']:.2f} s)",
            flush=True,
        )
    res.attrs.update(io.provenance(ccfg, None))
    io.write_zarr(res, out)


def run_errors(
    ccfg: Mapping[str, Any],
    piv: str | Path,
    volume: str | Path,
    particles: str | Path,
    out: str | Path,
    particles_b: str | Path | None = None,
    fitted_a: str | Path | None = None,
    fitted_b: str | Path | None = None,
) -> None:
    """Errors of one case against the known flow, its field of view, Q and depth gain
    (:func:`lfstudy.study.metrics.case_metrics`); given the second frame's particles
    (``particles_b``), also the oracle (:func:`lfstudy.study.case.oracle_piv`: the case's PIV
    on the true volumes) and the error budget. For a method that fits particles (``ipr``) the
    particle lists written beside both volumes (``volume_a.particles.zarr``, ``volume_b...``) are
    scored against the true particles too (:func:`lfstudy.study.particle_metrics.particle_metrics`:
    found, ghosts, the found particles' own crosstalk; needs ``particles_b``), and the share of its particles the
    paired PIV left out for want of depth (:func:`lfstudy.study.particle_metrics.depth_unknown_percent`) and its
    tracks' scatter nearest focus (:func:`lfstudy.study.particle_metrics.focus_scatter_ratio`);
    ``fitted_a``, ``fitted_b``: their paths where they are not beside ``volume`` (the study's frame a lives at the
    design, frame b at the flow)."""
    from lfstudy.reconstruct import gives_particles
    from lfstudy.simulate.flows import flow_from_config
    from lfstudy.study.metrics import case_metrics, particles_per_cell
    from lfstudy.study.particle_metrics import depth_unknown_percent, focus_scatter_ratio, particle_metrics

    spec = ccfg["flow"]
    cam = cl.case_camera(ccfg)
    parts = io.open_zarr(particles).load()
    oracle = None
    grid = cl.case_grid(ccfg, cam)
    bounds = [(float(c[0]), float(c[-1])) for c in (grid.x, grid.y, grid.z)]
    found: dict[str, float] = {"particles_per_cell": particles_per_cell(cam, parts, bounds)}
    if particles_b:  # '' or None: no oracle
        parts_b = io.open_zarr(particles_b).load()
        oracle = cl.oracle_piv(ccfg, parts, parts_b, progress=True)
        print(f"oracle (PIV on the true volumes): {oracle.attrs['oracle_seconds']:.2f} s", flush=True)
        if gives_particles(ccfg["reconstruct"]["method"]):
            vol = Path(volume)
            paths = [p or vol.with_name(f"volume_{f}.particles.zarr") for f, p in zip("ab", (fitted_a, fitted_b))]
            fitted = [io.open_zarr(p).load() for p in paths]
            dof = cam.depth_of_field(0.0)
            focus = (float(dof["z_near"][0]), float(dof["z_far"][0]))
            found.update(particle_metrics(fitted, [parts, parts_b], grid.voxel_size()[::-1], bounds, focus))
            print(f"particles: {found['found_percent']:.1f} % found, {found['ghost_percent']:.1f} % ghosts", flush=True)
    piv_ds = io.open_zarr(piv).load()
    if gives_particles(ccfg["reconstruct"]["method"]):
        found["depth_unknown_percent"] = depth_unknown_percent(piv_ds.attrs)
        found["focus_scatter_ratio"] = focus_scatter_ratio(piv_ds.attrs)
    err = case_metrics(
        piv_ds,
        flow_from_config(spec),
        cam,
        io.open_array(volume),
        cl.case_illuminated(ccfg, parts),  # Q against the particles as lit in the image
        sigma_mm=cl.truth_sigma(cam),
        dt=spec.get("dt", 1.0),
        n_steps=spec.get("n_steps", 100),
        oracle=oracle,
        extra=found,
    )
    err.attrs.update(io.provenance(ccfg, None), case_id=ccfg["case_id"])
    io.write_zarr(err, out)


def run_study(
    cfg: Mapping[str, Any],
    case_ids: list[str],
    error_paths: list[str | Path],
    benchmark_dir: str | Path,
    out_zarr: str | Path,
    out_csv: str | Path,
) -> None:
    """Combine every case's scalar results into one Dataset over the swept settings."""
    from lfstudy.study.sweep import Sweep
    from lfstudy.study.table import combine_cases, stage_times, to_csv

    sweep = Sweep(cfg)
    rows = []
    for cid, path in zip(case_ids, error_paths):
        case = sweep.case(cid)
        err = io.open_zarr(path).load()
        scalars = err[[v for v in err.data_vars if err[v].ndim == 0]]
        for stage, secs in stage_times(benchmark_dir, sweep.ids(case)).items():
            scalars[f"time_{stage}"] = ((), float(secs), {"units": "s", "long_name": f"{stage} run time"})
        rows.append((case, scalars))
    study = combine_cases(rows, sweep.settings)
    study.attrs.update(io.provenance(dict(cfg), cfg.get("seed")))
    io.write_zarr(study, out_zarr)
    to_csv(study, out_csv)


def run_report(
    cfg: Mapping[str, Any],
    case_ids: list[str],
    out_dir: str | Path,
    study: str | Path,
    out_html: str | Path,
    *,
    threads: int = 1,
) -> None:
    """The self-contained HTML report of the study; its per-case figures drawn by ``threads`` processes."""
    from lfstudy.study.report import write_report
    from lfstudy.study.sweep import FILES, Sweep

    sweep = Sweep(cfg)
    files = {cid: {name: Path(out_dir) / sweep.locate(cid, name) for name in FILES} for cid in case_ids}
    write_report(io.open_zarr(study).load(), files, dict(cfg), Path(out_html), workers=threads)


def run_study_stage(cfg: Mapping[str, Any], out_dir: str | Path, out_zarr: str | Path, out_csv: str | Path) -> None:
    """:func:`run_study` over every case of ``cfg`` (the whole validated config), reading the results under
    ``out_dir`` (``results/<name>``: each case's ``errors.zarr`` and the ``benchmarks`` tables): the Snakefile's
    ``study`` rule, a plain process (a ``run:`` rule started another Snakemake, ~10 s, on the study's last step)."""
    from lfstudy.study.sweep import Sweep

    sweep = Sweep(cfg)
    cases = [c.case_id for c in sweep.cases()]
    errors = [Path(out_dir) / sweep.locate(c, "errors.zarr") for c in cases]
    run_study(cfg, cases, errors, Path(out_dir) / "benchmarks", out_zarr, out_csv)


def run_report_stage(
    cfg: Mapping[str, Any], out_dir: str | Path, study: str | Path, out_html: str | Path, *, threads: int = 1
) -> None:
    """:func:`run_report` over every case of ``cfg`` (the whole validated config), their files under ``out_dir``:
    the Snakefile's ``report`` rule, a plain process as :func:`run_study_stage` (``threads``: its processes)."""
    from lfstudy.study.sweep import Sweep

    run_report(cfg, [c.case_id for c in Sweep(cfg).cases()], out_dir, study, out_html, threads=threads)


def run_warm(cfg: Mapping[str, Any], out: str | Path) -> None:
    """Compile the study's numba kernels on a tiny copy of each case in ``cfg["cases"]`` (one per reconstruction
    method the study sweeps; :func:`lfstudy.study.warm.warm_kernels`) before its jobs need them. Writes each
    case's stage times and error (None, or the traceback of a stage that failed: warming never fails the study)."""
    from lfstudy.study.warm import warm_kernels

    done = []
    for ccfg in cfg["cases"]:
        r = warm_kernels(ccfg)
        method = ccfg["reconstruct"]["method"]
        print(f"warm {method}: {r['seconds']}" + (f"\n{r['error']}" if r["error"] else ""), flush=True)
        done.append({"case_id": ccfg.get("case_id"), "method": method, **r})
    _write_json({"cases": done}, out)


#: The stages whose dask graphs a ``compute`` section may send to a dask.distributed client.
DASK_STAGES = ("refocus", "reconstruct", "depthcal", "piv")

_RUNNERS = {
    "camera": run_optics,
    "particles": run_particles,
    "displace": run_displace,
    "simulate": run_simulate,
    "pinhole": run_pinhole,
    "calibrate": run_calibrate,
    "depthcal": run_depth_calibration,
    "volcal": run_volcal,
    "register": run_register,
    "refocus": run_refocus,
    "reconstruct": run_reconstruct,
    "piv": run_piv,
    "errors": run_errors,
    "study": run_study_stage,
    "report": run_report_stage,
    "warm": run_warm,
}


def main(argv: list[str] | None = None) -> int:
    """Run one per-case stage: ``python -m lfstudy.workflow STAGE --config JSON --log F --threads N ARGS...``.

    The Snakefile's shell rules call this: a plain interpreter start is
    several times cheaper than Snakemake spawning itself for a ``run:`` job,
    which matters for sweeps of many small cases. ``--config`` is the
    stage's JSON config (:func:`lfstudy.study.config.stage_config`); ARGS are the stage function's
    remaining arguments (frame and paths) in order. ``--compute`` is the config's ``compute``
    section as JSON: the stages of :data:`DASK_STAGES` then run under the dask scheduler it
    names (:func:`lfstudy.compute.dask_scheduler`); the others ignore it.
    """
    import argparse
    import inspect

    ap = argparse.ArgumentParser(prog="python -m lfstudy.workflow", description=main.__doc__)
    ap.add_argument("stage", choices=sorted(_RUNNERS))
    ap.add_argument("--config", required=True, help="the stage's config as JSON")
    ap.add_argument("--log", required=True, help="log file (stdout, stderr, traceback)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--compute",
        default="{}",
        help="the config's compute section as JSON: the dask scheduler of refocus, reconstruct and piv",
    )
    ap.add_argument("args", nargs="*")
    ns = ap.parse_intermixed_args(argv)  # options before, between or after the positionals
    try:
        with logged(ns.log):
            set_threads(ns.threads)
            compute = json.loads(ns.compute) if ns.stage in DASK_STAGES else None
            if compute and compute.get("scheduler", "threads") != "threads":
                print(f"dask: {describe(compute)}", flush=True)
            # the scheduler is chosen here, at the edge: the stage and the science below it are the same
            with dask_scheduler(compute, threads=ns.threads):
                runner = _RUNNERS[ns.stage]
                # a stage that runs processes of its own (the report's figures) takes the rule's threads for them
                extra = {"threads": ns.threads} if "threads" in inspect.signature(runner).parameters else {}
                runner(json.loads(ns.config), *ns.args, **extra)
    except Exception:  # the traceback is in the log; logged() said where
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
