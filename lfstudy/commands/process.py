"""``lfstudy process CONFIG [--out DIR]``: recorded plenoptic images → volumes → 3-D PIV."""

from __future__ import annotations

import argparse

NAME = "process"
HELP = (
    "process recorded plenoptic images (calibration, dark frames, image pairs or a time series) "
    "into light fields, volumes, 3-D PIV, measurement metrics and an HTML report"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="recording config (YAML; schema lfstudy/process_schema.yaml)")
    p.add_argument(
        "--out",
        help="output directory (default: results/<name> of the config); it must be new, or an earlier output "
        "of `lfstudy process` (marked by its .lfstudy-output.json) with --overwrite; a directory holding "
        "the recording or its config is never written. Checked before any processing",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an earlier output of `lfstudy process` at --out")
    p.add_argument("--threads", type=int, help="threads of numba and dask (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    import sys
    import warnings
    from pathlib import Path

    from lfstudy.compute import dask_scheduler, describe
    from lfstudy.lightfield.calibrate import PitchWarning
    from lfstudy.process import SaturationWarning, load_process_config, process_recording

    cfg = load_process_config(args.config)
    if args.threads:
        from lfstudy.workflow import set_threads

        set_threads(args.threads)
    out = Path(args.out) if args.out else Path("results") / cfg["name"]
    if cfg["compute"]["scheduler"] != "threads":
        print(f"dask: {describe(cfg['compute'])}")
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        # a recording's warnings as one line each, in the CLI's style, printed when they arise: a
        # later error ends the run, and the warning (a lenslet pitch 10 % off) is often its cause
        if issubclass(category, (SaturationWarning, PitchWarning)):
            print(f"lfstudy process: warning: {message}", file=sys.stderr, flush=True)
        else:
            shown(message, category, filename, lineno, file, line)

    with warnings.catch_warnings():
        warnings.simplefilter("always", SaturationWarning)
        warnings.simplefilter("always", PitchWarning)
        warnings.showwarning = show
        # the scheduler is chosen here, at the edge; the pipeline is the same under either
        with dask_scheduler(cfg["compute"], threads=args.threads):
            process_recording(
                cfg, out, overwrite=args.overwrite, inputs=[args.config], progress=not args.quiet, log=print
            )
    return 0
