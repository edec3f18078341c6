"""``lfstudy piv A B --out piv.zarr``: WIDIM PIV between two volumes (or images)."""

from __future__ import annotations

import argparse
from typing import Any

NAME = "piv"
HELP = "3-D (or 2-D) WIDIM PIV between two volumes or images (zarr stores or TIFF stacks), ch. 6"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("a", help="first frame: a zarr store with one variable (a volume), or a TIFF image/stack")
    p.add_argument("b", help="second frame, same shape")
    p.add_argument("--config", help="study config (YAML): its piv section (default: the schema's defaults)")
    p.add_argument("--window", type=int, nargs="+", help="first-level window per axis (z y x), voxels")
    p.add_argument("--spacing", type=int, nargs="+", help="first-level window spacing per axis, voxels")
    p.add_argument("--levels", type=int, help="grid refinement levels")
    p.add_argument(
        "--out",
        required=True,
        help="output zarr store of the vector field: new, or an earlier output of `lfstudy piv` with --overwrite "
        "(an existing path lfstudy did not write, or an input, is never replaced)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an earlier output of `lfstudy piv` at --out")


def _frame(path: str):
    from lfstudy import io

    if path.rstrip("/").endswith(".zarr"):
        return io.open_array(path).load()
    import xarray as xr

    data, meta = io.read_tiff(path)
    dims = ("z", "y", "x")[-data.ndim :]
    return xr.DataArray(data, dims=dims, attrs=meta)


def run(args: argparse.Namespace) -> int:
    from lfstudy import io
    from lfstudy.study.config import load_config, validate_config

    cfg = load_config(args.config) if args.config else validate_config({"camera": _NO_CAMERA})
    p = dict(cfg["piv"])
    for key in ("window", "spacing", "levels"):
        if getattr(args, key) is not None:
            p[key] = getattr(args, key)
    a, b = _frame(args.a), _frame(args.b)
    inputs = [args.a, args.b, *([args.config] if args.config else [])]
    with io.output_dir(args.out, command="piv", inputs=inputs, overwrite=args.overwrite) as tmp:
        res = _piv(a, b, p)
        res.attrs.update(io.provenance({"piv": p}), source_a=str(args.a), source_b=str(args.b))
        io.write_zarr(res, tmp)
    ok = res["valid"].values
    comps = [c for c in ("u", "v", "w") if c in res]
    means = ", ".join(f"{c} {float(res[c].values[ok].mean()):+.3f}" for c in comps) if ok.any() else "none valid"
    print(f"{ok.size} vectors, {100 * ok.mean():.1f} % valid; mean displacement [voxel]: {means}")
    print(f"wrote {args.out}")
    return 0


def _piv(a: Any, b: Any, p: dict[str, Any]) -> Any:
    """WIDIM of the two frames with the piv settings ``p``."""
    from lfstudy.piv import widim
    from lfstudy.piv.engine import config_options

    return widim(a, b, **config_options(p), progress=True, uncertainty=p.get("uncertainty", "correlation"))


#: A placeholder camera so that the schema's defaults of the piv section can be filled without a config.
_NO_CAMERA = {
    "sensor": {"n_pixels_x": 64, "n_pixels_y": 64, "pixel_pitch": 0.0074},
    "lenslet": {"pitch": 0.125, "focal_length": 0.5},
    "main_lens": {"focal_length": 50.0},
    "magnification": -1.0,
}
