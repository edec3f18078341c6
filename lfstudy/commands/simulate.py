"""``lfstudy simulate CONFIG [--case ID] [--out DIR]``: render and record one case's raw images."""

from __future__ import annotations

import argparse

NAME = "simulate"
HELP = (
    "simulate one case (sec. 4.3): the particle field before and after the flow's displacement, "
    "both raw images and the pinhole calibration image (raytrace.method, then the sensor; TIFF + zarr)"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="study config (YAML)")
    p.add_argument("--case", help="case id from `lfstudy cases` (default: the first case of the sweep)")
    p.add_argument(
        "--out",
        default="simulate",
        help="output directory (default: ./simulate): new, or an earlier output of `lfstudy simulate` with "
        "--overwrite (an existing directory lfstudy did not write is never replaced)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an earlier output of `lfstudy simulate` at --out")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from lfstudy import io
    from lfstudy.simulate.raytrace import write_image
    from lfstudy.study.case import simulate_case
    from lfstudy.study.config import case_config, expand_cases, load_config

    cfg = load_config(args.config)
    case_id = args.case or expand_cases(cfg)[0].case_id
    ccfg = case_config(cfg, case_id)
    t0 = time.perf_counter()
    out = Path(args.out)
    with io.output_dir(out, command="simulate", inputs=[args.config], overwrite=args.overwrite) as tmp:
        res = simulate_case(ccfg, progress=not args.quiet)
        for name in ("particles_a", "particles_b"):
            io.write_zarr(res[name], tmp / f"{name}.zarr")
        for name in ("image_a", "image_b", "pinhole"):
            write_image(res[name], tmp / name)
    a = res["image_a"].attrs
    print(f"case {case_id}")
    n_part = res["particles_a"].sizes["particle"]
    if a.get("method") == "exact":
        print(
            f"particles: {n_part}, rendered exactly: expected intensity {a['intensity_traced']:,.0f} per frame "
            f"(recorded {a['intensity_recorded']:,.0f}, off the sensor {a['intensity_lost_outside_sensor']:,.0f})"
        )
        print(f"pinhole: f/{res['pinhole'].attrs['pinhole_fnumber']:g}, rendered exactly")
    else:
        print(
            f"particles: {n_part}, rays traced per frame: {a['rays_traced']:,} "
            f"(recorded {a['rays_recorded']:,}, off the sensor {a['rays_dropped_outside_sensor']:,})"
        )
        print(f"pinhole: f/{res['pinhole'].attrs['pinhole_fnumber']:g}, {res['pinhole'].attrs['rays_traced']:,} rays")
    shot = "shot noise" if a.get("sensor_shot_noise") else "no shot noise"
    print(
        f"sensor: {a.get('sensor_photons_per_particle', 0):g} photons per particle, QE "
        f"{a.get('sensor_quantum_efficiency', 1):g}, {shot}, read noise {a.get('sensor_read_noise', 0):g} e-"
    )
    print(f"wrote {out} in {time.perf_counter() - t0:.1f} s")
    return 0
