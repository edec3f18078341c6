"""``lfstudy calibrate PINHOLE.tif --out centres.zarr``: lenslet centres from a pinhole image."""

from __future__ import annotations

import argparse

NAME = "calibrate"
HELP = "find every lenslet centre in a pinhole (or white) image (sec. 5.1) and save them to zarr"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("pinhole", help="pinhole image: TIFF (or a zarr store with an 'intensity' variable)")
    p.add_argument("--config", help="study config (YAML): checks the image size, narrows the pitch search")
    p.add_argument("--case", help="case id from `lfstudy cases` (default: the base config)")
    p.add_argument("--pixel-pitch", type=float, help="pixel pitch [mm] when no config is given")
    p.add_argument(
        "--out",
        required=True,
        help="output zarr store for the centres: new, or an earlier output of `lfstudy calibrate` with "
        "--overwrite (an existing path lfstudy did not write, or an input, is never replaced)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an earlier output of `lfstudy calibrate` at --out")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from lfstudy import io
    from lfstudy.lightfield.calibrate import CalibrationError, expected_centers, find_lenslet_centers

    cam = None
    params = None
    if args.config:
        from lfstudy.optics import PlenopticCamera
        from lfstudy.study.config import case_config, load_config

        cfg = load_config(args.config)
        if args.case:
            cfg = case_config(cfg, args.case)
        cam = PlenopticCamera.from_config(cfg)
        params = cfg
    image = io.read_image(args.pinhole)
    inputs = [args.pinhole, *([args.config] if args.config else [])]
    with io.output_dir(args.out, command="calibrate", inputs=inputs, overwrite=args.overwrite) as tmp:
        try:
            centers = find_lenslet_centers(image, cam, pixel_pitch=args.pixel_pitch)
        except CalibrationError as exc:  # "image is blank": say which
            raise CalibrationError(f"image file {args.pinhole!r}: {exc}") from None
        centers.attrs.update(io.provenance(params), source=str(args.pinhole))
        io.write_zarr(centers, tmp)
    a = centers.attrs
    print(
        f"lenslet grid: {centers.sizes['lenslet_col']} x {centers.sizes['lenslet_row']} ({a['n_valid']} valid centres)"
    )
    print(
        f"pitch: {a['pitch_x_px']:.4f} x {a['pitch_y_px']:.4f} px, rotation {a['rotation']:.3e} rad, "
        f"offset ({a['offset_x_px']:.3f}, {a['offset_y_px']:.3f}) px"
    )
    print(f"lattice residual: {a['lattice_rms_px']:.4f} px RMS")
    if cam is not None:
        ex, ey = expected_centers(cam)
        v = centers["valid"].values
        d = np.hypot(centers["cx"].values - ex, centers["cy"].values - ey)[v]
        print(f"vs geometric expectation c*(si+fl)/si: {np.sqrt(np.mean(d**2)):.4f} px RMS, max {d.max():.4f} px")
    print(f"wrote {args.out}")
    return 0
