"""The study config: validate it (every swept case included), expand the sweep, each case's and stage's config.

The layers run one way: :mod:`lfstudy.config` (the error, YAML, schema
validation) ← :mod:`lfstudy.reconstruct` (the method registry) ←
:mod:`lfstudy.study.schema` (the full schema) ← the study modules
(:mod:`~lfstudy.study.sweep`, :mod:`~lfstudy.study.case`,
:mod:`~lfstudy.study.resources`) ← this module ← the workflow, the CLI and the
``Snakefile``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lfstudy.config import ConfigError, read_yaml, validate_section
from lfstudy.optics import OpticsError, PlenopticCamera
from lfstudy.reconstruct import gives_particles
from lfstudy.reconstruct.grid import GridError
from lfstudy.simulate.flows import check_flow_config, resolve_flow_paths
from lfstudy.study.case import case_grid
from lfstudy.study.resources import check_memory
from lfstudy.study.schema import load_schema
from lfstudy.study.sweep import NAMED, STAGES, Case, Sweep, format_value

__all__ = [
    "load_schema",
    "load_config",
    "validate_config",
    "sweep_of",
    "expand_cases",
    "case_config",
    "depth_calibrated",
    "stage_config",
    "cases_table",
    "check_piv_grid",
    "check_sweep_size",
    "MAX_CASES",
]

#: Cases a sweep may make unless ``LFSTUDY_MAX_CASES`` allows more: validating a case took 62 ms (tiny.yaml,
#: 500 cases, a loaded 2-core machine) and Snakemake then plans several jobs per case, so 2000 cases already
#: take minutes before any job runs, and the issue's 100 x 100 sweep sat in "Building DAG" for over 300 s.
MAX_CASES = 2000


def validate_config(
    cfg: Mapping[str, Any], base: str | Path | None = None, *, piv_grid: bool = False
) -> dict[str, Any]:
    """Validate a config mapping, returning a deep copy with defaults filled in.

    Besides the schema, checks what a schema cannot: that the camera can be
    built (f-number reachable, pitch vs pixel) for every swept combination,
    that swept flows are defined, and that each flow can be built (a file
    flow's file: its variables, coordinates and units).

    Parameters
    ----------
    cfg : Mapping
        The config as read from YAML.
    base : str or Path, optional
        The config file's folder: a file flow's relative ``path`` is taken
        relative to it (and made absolute). Default: the working directory.
    piv_grid : bool
        Check that every case's PIV windows fit its reconstruction grid
        (:func:`check_piv_grid`): on where the whole study is to run (the ``Snakefile``,
        ``lfstudy cases``), so that windows too large for the volumes stop it before any
        job; off by default, for the stage commands and the API that simulate, calibrate
        or refocus a config without its PIV (a small sensor's images), and ``lfstudy piv``
        (whose volumes are given, not the grid's).

    Raises
    ------
    ConfigError
        On the first problem, naming the key, the value and what is allowed.
    """
    cfg = validate_section(load_schema(), cfg)
    lens = cfg["camera"]["lenslet"]
    if lens.get("focal_length") is None and lens.get("fnumber") is None:
        raise ConfigError("config key 'camera.lenslet': give focal_length or fnumber (fl = N·pl)")
    for name in cfg["sweep"].get("flow", []):
        if name not in cfg["flows"]:
            raise ConfigError(
                f"config key 'sweep.flow' = {name!r}: unknown flow; allowed values are "
                + ", ".join(repr(k) for k in cfg["flows"])
            )
    root = Path(base) if base is not None else Path.cwd()
    for name, spec in cfg["flows"].items():  # the schema checked each kind's parameters
        cfg["flows"][name] = spec = resolve_flow_paths(spec, root)
        check_flow_config(spec, f"flows.{name}")
    count = cfg["particles"].get("count")
    if count is not None and len(cfg["sweep"].get("ppp", [])) > 1:
        raise ConfigError(
            f"config key 'particles.count' = {count}: a fixed particle count overrides ppp, so every swept "
            "ppp value would image the same field; drop particles.count or sweep.ppp"
        )

    sweep = sweep_of(cfg)
    check_sweep_size(len(sweep))  # before the per-case checks below: they take time per case
    schema = load_schema()
    dotted = [s for s in sweep.settings if s.key not in NAMED]
    for case in sweep.cases():
        ccfg = sweep.apply(case)
        if dotted:  # a value the sweep sets must be valid where it lands (e.g. piv.window)
            try:
                validate_section(schema, {k: v for k, v in ccfg.items() if k not in ("flow", "case_id")})
            except ConfigError as exc:
                where = ", ".join(f"{s.key}={format_value(case[s.key])}" for s in dotted)
                raise ConfigError(f"{exc} (case {where})") from None
        try:
            PlenopticCamera.from_config(ccfg)
        except OpticsError as exc:
            where = ", ".join(f"{k}={v}" for k, v in case.params.items() if k != "flow")
            raise ConfigError(f"config key 'camera' (case {where}): {exc}") from None
        sen = ccfg["sensor"]
        if sen["full_well"] is not None and sen["full_well"] <= sen["dark_level"]:
            raise ConfigError(
                f"config key 'sensor.full_well' = {sen['full_well']!r} (case {case.case_id}): must exceed "
                f"sensor.dark_level = {sen['dark_level']!r} e- (the pedestal would fill the well)"
            )
        il, par = ccfg["illumination"], ccfg["particles"]
        if il["profile"] != "none" and il["thickness"] is None:
            raise ConfigError(
                f"config key 'illumination.thickness' = null (case {case.case_id}): required with "
                f"illumination.profile {il['profile']!r} (the light volume's full width at half maximum, > 0 mm)"
            )
        if par["depth_margin"] > 0 and par["z_span"] == 0:
            raise ConfigError(
                f"config key 'particles.depth_margin' = {par['depth_margin']!r} (case {case.case_id}): needs "
                "particles.z_span > 0 (the margin is seeded at the slab's number density)"
            )
        _check_particles_setting(ccfg, case.case_id)
        try:  # the grid a case reconstructs on (grid.z_range, voxel sizes, its memory cap)
            grid = case_grid(ccfg)
        except GridError as exc:
            raise ConfigError(f"config key 'grid' (case {case.case_id}): {exc}") from None
        if piv_grid:
            check_piv_grid(ccfg, grid.shape, where=f"case {case.case_id}")
        zc = par.get("z_center", 0.0)
        if zc != 0.0 and not grid.z[0] - 1e-9 <= zc <= grid.z[-1] + 1e-9:
            raise ConfigError(
                f"config key 'particles.z_center' = {zc!r} (case {case.case_id}): the slab's centre lies outside "
                f"the reconstruction grid's depth [{grid.z[0]:.4g}, {grid.z[-1]:.4g}] mm; set grid.z_range to the "
                "seeded slab"
            )
        check_memory(ccfg, where=f"case {case.case_id}")
    return cfg


def check_sweep_size(n: int) -> None:
    """Refuse a sweep of more than :data:`MAX_CASES` cases (``LFSTUDY_MAX_CASES`` raises the limit).

    A 100 x 100 sweep is 10,000 cases: validating them and building Snakemake's DAG of their
    jobs takes many minutes before the first job runs, which looks like a hang. Counting them is
    instant, so a sweep that large is refused at once with its size, unless asked for.

    Raises
    ------
    ConfigError
        ``n`` above the limit, naming the count and how to proceed.
    """
    import os

    raw = os.environ.get("LFSTUDY_MAX_CASES", "")
    try:
        limit = int(raw) if raw.strip() else MAX_CASES
    except ValueError:
        limit = 0
    if limit < 1:
        raise ConfigError(f"environment variable LFSTUDY_MAX_CASES = {raw!r}: expected an integer >= 1")
    if n > limit:
        raise ConfigError(
            f"config key 'sweep': the sweep makes {n} cases (the product of its lists' lengths), more than the "
            f"limit of {limit}; validating and planning that many takes minutes before any job runs. Sweep fewer "
            f"values, or set LFSTUDY_MAX_CASES={n} in the environment to run them all"
        )


def check_piv_grid(ccfg: Mapping[str, Any], shape: tuple[int, ...], where: str = "") -> None:
    """The PIV settings of a config against the reconstruction grid's ``shape`` (z, y, x), before any work.

    The volumes PIV correlates have the grid's shape, so a first-level window larger than the grid
    (or spacings, levels the windows cannot take) is known from the config and the camera alone;
    without this check it surfaces only at the PIV stage, after calibration, refocusing and
    reconstruction.

    Raises
    ------
    ConfigError
        Naming ``piv.window``, ``piv.spacing`` or ``piv.levels`` with the allowed range, or
        the ``piv`` setting at fault.
    """
    from lfstudy.piv.engine import WidimSettings, config_options

    p = ccfg["piv"]
    win = [int(w) for w in p["window"]]
    shape = tuple(int(n) for n in shape)
    at = f" ({where})" if where else ""
    grid = f"the reconstruction grid of {' x '.join(map(str, shape))} voxels (z, y, x)"
    big = [(d, w, n) for d, w, n in zip("zyx", win, shape) if w > n]
    if big:
        too = ", ".join(f"{w} along {d} exceeds {n}" for d, w, n in big)
        allowed = ", ".join(f"{d} [4, {n}]" for d, n in zip("zyx", shape))
        raise ConfigError(
            f"config key 'piv.window' = {win}{at}: {too} voxels of {grid}; allowed range per axis is {allowed}. "
            "Use a smaller window, or a larger grid (grid.z_range, grid.voxel_xy, grid.voxel_z)"
        )
    spacing = [int(v) for v in p["spacing"]]
    wide = [(d, sp, w) for d, sp, w in zip("zyx", spacing, win) if sp > w]
    if wide:
        allowed = ", ".join(f"{d} [1, {w}]" for d, w in zip("zyx", win))
        raise ConfigError(
            f"config key 'piv.spacing' = {spacing}{at}: "
            + ", ".join(f"{sp} along {d} exceeds the window's {w}" for d, sp, w in wide)
            + f"; allowed range per axis is {allowed} (windows may overlap, not leave gaps)"
        )
    levels = int(p["levels"])
    sizes = WidimSettings(tuple(win), tuple(spacing), levels=levels).sizes  # the windows of each level
    small = next((k for k, (w, _) in enumerate(sizes, start=1) if min(w) < 4), None)
    if small is not None:
        raise ConfigError(
            f"config key 'piv.levels' = {levels}{at}: level {small} refines piv.window {win} to "
            f"{list(sizes[small - 1][0])}, below the 4 voxels a window needs; allowed range is [1, {small - 1}] "
            "for this window"
        )
    try:
        WidimSettings.build(shape, **{**config_options(p), "window": tuple(win)})
    except ValueError as exc:
        raise ConfigError(f"config key 'piv'{at}: {exc} (on {grid})") from None


def _check_particles_setting(ccfg: Mapping[str, Any], case_id: str) -> None:
    """``piv.particles: ptv`` or ``paired`` needs the particle lists of a method that fits them, and no
    depth calibration (the traverse measures WIDIM's depth gain on the reconstructed volumes, not the
    tracks' or the paired volumes')."""
    from lfstudy.piv.ptv import PARTICLE_MODES

    mode = ccfg["piv"].get("particles", "none")
    if mode not in PARTICLE_MODES:
        return
    box = ccfg["piv"].get("ptv_model_box")
    if box is not None and 0 < box < 1:
        raise ConfigError(
            f"config key 'piv.ptv_model_box' = {box!r} (case {case_id}): the pilot box of the uncertainty's "
            "model term spans at least the final window (1 to 5 windows per axis); 0 turns the term off"
        )
    method = ccfg["reconstruct"]["method"]
    if not gives_particles(method):
        raise ConfigError(
            f"config key 'piv.particles' = {mode!r} (case {case_id}): reads the particles a reconstruction "
            f"fits, and reconstruct.method = {method!r} fits none; use a method that does (ipr) or "
            "piv.particles: none"
        )
    if ccfg["depth_calibration"]["enabled"]:
        raise ConfigError(
            f"config key 'depth_calibration.enabled' = true (case {case_id}): not with piv.particles = {mode!r} "
            "(the traverse calibration measures the correlation PIV's depth gain, not the tracks'); set "
            "depth_calibration.enabled: false or piv.particles: none"
        )


def load_config(path: str | Path, *, piv_grid: bool = False) -> dict[str, Any]:
    """Read a YAML config file and validate it (defaults filled in); a file flow's path is
    relative to the config file's folder. ``piv_grid``: see :func:`validate_config`."""
    return validate_config(read_yaml(path), base=Path(path).resolve().parent, piv_grid=piv_grid)


def sweep_of(cfg: Mapping[str, Any]) -> Sweep:
    """The :class:`~lfstudy.study.sweep.Sweep` of a validated config."""
    return Sweep(cfg)


def expand_cases(cfg: Mapping[str, Any]) -> list[Case]:
    """All cases of the sweep (Cartesian product of its lists), in a stable order.

    A named parameter that is not swept keeps the single value of the base config.
    """
    return sweep_of(cfg).cases()


def case_config(cfg: Mapping[str, Any], case: Case | str) -> dict[str, Any]:
    """The full config of one case: the base config with the case's swept values set.

    The chosen flow's spec is placed under ``flow`` (with its name); ``case_id``,
    ``calib_id`` and ``stage_ids`` (where each stage's outputs live) are added.
    """
    sweep = sweep_of(cfg)
    case = sweep.case(case)
    out = sweep.apply(case)
    out["calib_id"] = sweep.calib_id(case)
    out["stage_ids"] = sweep.ids(case)
    return out


def depth_calibrated(ccfg: Mapping[str, Any]) -> bool:
    """Whether a case config (:func:`case_config`) maps its axial displacement through the design's depth
    calibration (``depth_calibration.enabled``)."""
    return bool((ccfg.get("depth_calibration") or {}).get("enabled", False))


def stage_config(cfg: Mapping[str, Any], case: Case | str, stage: str) -> dict[str, Any]:
    """The part of a case's config that ``stage`` reads (:data:`lfstudy.study.sweep.STAGES`),
    plus ``stage_id`` (where the stage's outputs live) and ``calib_id``.

    ``case_id`` is added only for the per-case ``errors`` stage: every other stage's output
    is shared by all cases at its location, so its config (the Snakemake rule's params, and
    the provenance attrs it writes) must not depend on which of them stands for it —
    otherwise a change of the sweep reruns shared stages whose settings did not change.
    """
    ccfg = case_config(cfg, case)
    sections = {p.split(".")[0] for p in STAGES[stage].reads}
    out: dict[str, Any] = {"stage_id": ccfg["stage_ids"][stage], "calib_id": ccfg["calib_id"]}
    if stage == "errors":
        out["case_id"] = ccfg["case_id"]
    return {**out, **{k: ccfg[k] for k in sorted(sections)}}


def cases_table(cfg: Mapping[str, Any]):
    """The expanded sweep as a pandas DataFrame indexed by case id, with derived camera columns."""
    import pandas as pd

    sweep = sweep_of(cfg)
    rows = []
    for case in sweep.cases():
        cam = PlenopticCamera.from_config(sweep.apply(case))
        rows.append(
            {
                "case_id": case.case_id,
                **case.params,
                "main_fnumber": cam.main_fnumber,
                "lenslets": f"{cam.n_lenslets_x}x{cam.n_lenslets_y}",
                "px_per_lenslet": round(cam.pixels_per_lenslet, 3),
                "fill": round(cam.lenslet_image_fill, 3),
            }
        )
    return pd.DataFrame(rows).set_index("case_id")
