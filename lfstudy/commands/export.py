"""``lfstudy export STORE --out FILE``: a PIV result or volume to ParaView (VTK) or Fiji (TIFF)."""

from __future__ import annotations

import argparse

NAME = "export"
HELP = (
    "export a PIV result, volume or focal stack (zarr) to ParaView (.vtr rectilinear grid) or "
    "ImageJ/Fiji (.tif hyperstack with the voxel size), with coordinates in mm"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("store", help="zarr store written by the workflow: piv.zarr, volume_a.zarr, stack_a.zarr ...")
    p.add_argument(
        "--out",
        required=True,
        help="output file: .vtr (VTK, ParaView) or .tif (ImageJ/Fiji); an existing file is replaced only with "
        "--overwrite, a directory or the exported store never",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing file at --out")
    p.add_argument("--format", choices=("vtk", "tiff"), help="default: from the extension of --out")
    p.add_argument(
        "--var",
        action="append",
        dest="variables",
        metavar="NAME",
        help="data variable to write (repeatable); VTK: default all (z, y, x) variables (a PIV result's "
        "uncertainties unc_u_mm ... among them); TIFF: default the store's only variable, several become channels",
    )
    p.add_argument(
        "--no-uncertainty",
        dest="uncertainty",
        action="store_false",
        help="TIFF of one PIV component: leave out the channel of its standard uncertainty (unc_u_mm for u_mm ...), "
        "which is added when the store holds it",
    )
    p.add_argument(
        "--resample-z",
        action="store_true",
        help="TIFF: interpolate non-uniform z planes (focal planes) linearly onto evenly spaced ones; "
        "without it such a stack is refused, as ImageJ has one z spacing",
    )


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lfstudy.export import export_store

    out, store = Path(args.out).resolve(), Path(args.store).resolve()
    if out == store or store in out.parents:
        raise ValueError(f"--out {args.out!r} lies inside the exported store {args.store!r}; choose another --out")
    if out.is_dir():
        raise ValueError(f"--out {args.out!r} is a directory; name the file to write")
    if out.exists() and not args.overwrite:
        raise ValueError(f"--out {args.out!r} exists; give --overwrite to replace it, or choose another --out")
    out = export_store(
        args.store,
        args.out,
        fmt=args.format,
        variables=args.variables,
        resample_z=args.resample_z,
        uncertainty=args.uncertainty,
    )
    print(f"wrote {out}")
    return 0
