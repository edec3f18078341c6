"""``lfstudy optics CONFIG``: derived camera parameters and the focal-plane table."""

from __future__ import annotations

import argparse

NAME = "optics"
HELP = "print the derived camera parameters and the refocus-plane table (as Table 5.1)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="study config (YAML)")
    p.add_argument("--case", help="case id from `lfstudy cases` (default: the base config)")


def run(args: argparse.Namespace) -> int:
    from lfstudy.optics import PlenopticCamera
    from lfstudy.study.case import case_grid, case_planes
    from lfstudy.study.config import case_config, load_config

    cfg = load_config(args.config)
    if args.case:
        cfg = case_config(cfg, args.case)
    cam = PlenopticCamera.from_config(cfg)
    width = max(len(k) for k in cam.summary())
    print("Camera")
    for k, v in cam.summary().items():
        print(f"  {k:<{width}}  {v}")
    fp = case_planes(cfg, cam)
    print("\nRefocus planes (eqs 5.16-5.20)")
    print(f"{'plane':>5} {'D_N,i':>10} {'D_F,i':>10} {'D_F-D_N':>9} {'/c':>8} {'D_i':>10} {'t':>9} {'z obj':>9}")
    c = fp.attrs["circle_of_confusion"]
    for p in fp["plane"].values:
        row = fp.sel(plane=p)
        n, f = float(row["near"]), float(row["far"])
        print(
            f"{int(p):>5} {n:>10.4f} {f:>10.4f} {f - n:>9.4f} {(f - n) / c:>8.4f} "
            f"{float(row['image_distance']):>10.4f} {float(row['t']):>9.4f} {float(row['z']):>9.4f}"
        )
    g = case_grid(cfg, cam)
    dz, dy, dx = g.voxel_size()
    print(
        f"\nReconstruction grid ({g.spacing}): {g.shape[0]} x {g.shape[1]} x {g.shape[2]} voxels (z, y, x) of "
        f"{dz:.4g} x {dy:.4g} x {dx:.4g} mm; z {g.z[0]:+.3f} .. {g.z[-1]:+.3f} mm"
    )
    return 0
