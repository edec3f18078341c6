"""``lfstudy render RAW.tif --centers centres.zarr --config CONFIG --out DIR``: raw image → volume."""

from __future__ import annotations

import argparse

NAME = "render"
HELP = "register, refocus and reconstruct a raw plenoptic image (ch. 5): light field, focal stack, volume"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("raw", help="raw plenoptic image: TIFF (or a zarr store with an 'intensity' variable)")
    p.add_argument("--centers", required=True, help="lenslet centres from `lfstudy calibrate` (zarr)")
    p.add_argument("--config", required=True, help="study config (YAML): camera, refocus, reconstruct")
    p.add_argument("--case", help="case id from `lfstudy cases` (default: the base config)")
    p.add_argument(
        "--out",
        required=True,
        help="output directory, made if missing, receiving lightfield.zarr, stack.zarr, volume.zarr; an existing "
        "store of those names is replaced only if it is an earlier output of `lfstudy render` and --overwrite is "
        "given; nothing else in the directory is touched",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an earlier output of `lfstudy render` at --out")


def run(args: argparse.Namespace) -> int:
    from contextlib import ExitStack
    from pathlib import Path

    from lfstudy import io
    from lfstudy.lightfield import RegistrationError
    from lfstudy.study.case import render_volume
    from lfstudy.study.config import case_config, load_config

    cfg = load_config(args.config)
    if args.case:
        cfg = case_config(cfg, args.case)
    out = Path(args.out)
    names = ("lightfield", "stack", "volume")
    inputs = [args.raw, args.centers, args.config]
    with ExitStack() as outputs:  # every store checked, locked and begun before any work
        tmps = [
            outputs.enter_context(
                io.output_dir(out / f"{n}.zarr", command="render", inputs=inputs, overwrite=args.overwrite)
            )
            for n in names
        ]
        raw = io.read_image(args.raw)
        centers = io.open_zarr(args.centers).load()
        try:
            lf, stack, volume = render_volume(raw, centers, cfg)
        except RegistrationError as exc:  # "raw image is all zero": say which
            raise RegistrationError(f"image file {args.raw!r}: {exc}") from None
        prov = io.provenance(cfg, cfg.get("seed"))
        for obj, tmp in zip((lf, stack, volume), tmps):
            obj.attrs.update(prov, source=str(args.raw))
            io.write_zarr(obj, tmp)
    a = volume.attrs
    print(f"light field: {dict(lf.sizes)}")
    print(
        f"focal stack: {dict(stack.sizes)}, z {float(stack.z[0]):.3f} .. {float(stack.z[-1]):.3f} mm, "
        f"voxel {stack.attrs['voxel_size']:.4g} mm, resize={bool(stack.attrs['resize'])}"
    )
    print(f"volume: method {a['method']}, {' x '.join(str(n) for n in volume.shape)} voxels (z, y, x)")
    if "threshold" in a:  # the thesis' method reports its cut
        print(f"  threshold {a['threshold']:.4g} (k = {a['k']:g}), kept {100 * a['kept_fraction']:.2f} % of voxels")
    print(f"wrote {out}")
    return 0
