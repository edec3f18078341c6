"""The recording config of ``lfstudy process``: load, validate, resolve paths.

The schema, ``lfstudy/process_schema.yaml``, takes the camera and the
processing sections (``refocus``, ``grid``, ``reconstruct``, ``piv``,
``compute``) from the study schema by ``$ref`` — one definition of each, so a
recording is processed with exactly the settings a study sweeps — and adds the
``recording`` section. Paths in ``recording`` are relative to the config file.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from lfstudy.config import ConfigError, read_yaml, validate_section
from lfstudy.optics import OpticsError, PlenopticCamera
from lfstudy.study.resources import check_memory
from lfstudy.study.schema import load_schema

__all__ = ["load_process_schema", "validate_process_config", "load_process_config"]

#: The URI the study schema is registered under; the recording schema's ``$id`` is beside it.
STUDY_SCHEMA_URI = "https://lfstudy.invalid/schema.yaml"


@functools.lru_cache(maxsize=1)
def _process_schema() -> dict[str, Any]:
    return yaml.safe_load(resources.files("lfstudy").joinpath("process_schema.yaml").read_text())


def _registry() -> Any:
    from referencing import Registry, Resource
    from referencing.jsonschema import DRAFT202012

    study = load_schema()  # with the reconstruction methods' parameters filled in
    return Registry().with_resource(STUDY_SCHEMA_URI, Resource.from_contents(study, default_specification=DRAFT202012))


def load_process_schema() -> dict[str, Any]:
    """The JSON schema of a recording config (its ``$ref`` point into the study schema)."""
    return copy.deepcopy(_process_schema())


def validate_process_config(cfg: Mapping[str, Any], base: str | Path | None = None) -> dict[str, Any]:
    """Validate a recording config, fill defaults, resolve the recording's paths.

    Parameters
    ----------
    cfg : mapping
        The config (as read from YAML).
    base : path, optional
        Directory the ``recording`` paths are relative to (the config file's);
        default the current directory. Absolute paths stay as they are; globs
        are resolved later, by :func:`lfstudy.process.recording.open_recording`.

    Returns
    -------
    dict
        A deep copy with defaults filled in and every path of ``recording``
        absolute. ``recording.frames`` holds exactly one of ``pairs``, ``series``.

    Raises
    ------
    ConfigError
        Naming the key, the value and what is allowed.
    """
    out = validate_section(_process_schema(), cfg, registry=_registry())
    lens = out["camera"]["lenslet"]
    if lens.get("focal_length") is None and lens.get("fnumber") is None:
        raise ConfigError("config key 'camera.lenslet': give focal_length or fnumber (fl = N·pl)")
    try:
        PlenopticCamera.from_config(out)
    except OpticsError as exc:
        raise ConfigError(f"config key 'camera': {exc}") from None
    frames = out["recording"]["frames"]
    given = [k for k in ("pairs", "series") if k in frames]
    if len(given) != 1:
        raise ConfigError(
            "config key 'recording.frames': give exactly one of 'pairs' (independent image pairs) or "
            f"'series' (a time series){'; got both' if len(given) == 2 else ''}"
        )
    root = Path(base) if base is not None else Path.cwd()

    def resolve(p: str) -> str:
        return str(p) if Path(p).is_absolute() else str(root / p)

    rec = out["recording"]
    rec["calibration"]["image"] = resolve(rec["calibration"]["image"])
    rec["dark"] = [resolve(p) for p in ([rec["dark"]] if isinstance(rec["dark"], str) else rec["dark"])]
    if "pairs" in frames:
        frames["pairs"] = [resolve(p) if isinstance(p, str) else [resolve(q) for q in p] for p in frames["pairs"]]
    else:
        s = frames["series"]
        frames["series"] = resolve(s) if isinstance(s, str) else [resolve(p) for p in s]
    if "depth_calibration" in rec:
        dc = rec["depth_calibration"]
        dc["images"] = resolve(dc["images"]) if isinstance(dc["images"], str) else [resolve(p) for p in dc["images"]]
    vc = rec.get("volumetric_calibration")
    if vc is not None:
        vc["images"] = resolve(vc["images"]) if isinstance(vc["images"], str) else [resolve(p) for p in vc["images"]]
        _check_volcal(vc)
    if out["refocus"].get("model", "thin_lens") == "volumetric" and vc is None:
        raise ConfigError(
            "config key 'refocus.model' = 'volumetric' needs the dot-target images: give "
            "recording.volumetric_calibration (images, depths, spacing), or use refocus.model: thin_lens"
        )
    _particle_mode(out)
    _check_calibration(out, resolve)
    # a recording has no simulated particles: the memory estimate's simulate stage gets a placeholder
    check_memory({**out, "particles": {"count": 1, "ppp": 1e-9}})
    # the volumes have the grid's shape: PIV windows that cannot fit are refused now, not after
    # the calibration, refocusing and reconstruction of every frame
    from lfstudy.study.case import case_grid
    from lfstudy.study.config import check_piv_grid

    check_piv_grid(out, case_grid(out).shape)
    return out


def _check_volcal(vc: dict[str, Any]) -> None:
    """Depths the polynomial can be fitted on: distinct, at least ``order + 1`` of them."""
    depths = [float(v) for v in vc["depths"]]
    order = int(vc.setdefault("order", 3))
    if len(set(depths)) != len(depths):
        raise ConfigError(
            f"config key 'recording.volumetric_calibration.depths' = {depths}: the depths must be distinct"
        )
    if len(depths) < order + 1:
        raise ConfigError(
            f"config key 'recording.volumetric_calibration.depths': {len(depths)} depths for a polynomial of order "
            f"{order} in z; give at least order + 1 = {order + 1} (order + 2 for the held-out error)"
        )


def _particle_mode(cfg: dict[str, Any]) -> None:
    """``piv.particles`` as a study has it: unset means ``paired`` where the method fits particles and no
    traverse is recorded (the study's default, :func:`lfstudy.study.sweep._default_particle_mode`), so the
    ghosts and the particles fitted in one frame only do not bias WIDIM (issue 39: on a Monte-Carlo
    recording with a lenslet gap 3 % off, RMS error of u 0.0057 -> 0.0037 mm, w 0.025 -> 0.020 mm,
    ``benchmarks/bench_recording.py``). ``paired`` needs such a method and no traverse; ``ptv`` (a binned
    track field, without correlation peaks for the metrics) is refused here rather than ignored."""
    from lfstudy.reconstruct import gives_particles

    piv = cfg["piv"]
    method = cfg["reconstruct"].get("method", "threshold")
    traverse = bool(cfg["recording"].get("depth_calibration"))
    mode = piv.get("particles")
    if mode is None:
        if gives_particles(method) and not traverse:
            piv["particles"] = "paired"
        return
    if mode == "ptv":
        raise ConfigError(
            "config key 'piv.particles' = 'ptv': lfstudy process correlates volumes (its metrics read the "
            "correlation peaks); use paired (the fitted particles paired between the frames) or none"
        )
    if mode == "paired" and not gives_particles(method):
        raise ConfigError(
            f"config key 'piv.particles' = 'paired': reads the particles a reconstruction fits, and "
            f"reconstruct.method = {method!r} fits none; use a method that does (ipr) or piv.particles: none"
        )
    if mode == "paired" and traverse:
        raise ConfigError(
            "config key 'piv.particles' = 'paired': not with recording.depth_calibration (the traverse measures "
            "WIDIM's depth gain on the reconstructed volumes, not on the paired ones); use piv.particles: none"
        )


def _check_calibration(cfg: dict[str, Any], resolve: Any) -> None:
    """``uncertainty.calibration``: its study path resolved, and the study and design checked now, before any work."""
    cal = cfg.get("uncertainty", {}).get("calibration")
    if cal is None:
        return
    from lfstudy.process.uncertainty_calibration import CalibrationError, load_calibration

    if cfg["piv"].get("uncertainty", "correlation") in (None, "none"):
        raise ConfigError(
            "config key 'uncertainty.calibration' scales σ, but piv.uncertainty is none: "
            "give piv.uncertainty (correlation, moment, independent) or leave out the calibration"
        )
    cal["study"] = resolve(cal["study"])
    try:
        load_calibration(cfg)
    except CalibrationError as exc:
        raise ConfigError(f"config key 'uncertainty.calibration.{exc.key}': {exc}") from None


def load_process_config(path: str | Path) -> dict[str, Any]:
    """Read a recording config (YAML) and validate it; its recording paths are relative to the file.

    Raises
    ------
    ConfigError
        Missing or unreadable file, invalid YAML or an invalid value.
    """
    path = Path(path)
    raw = read_yaml(path)
    return validate_process_config(raw, base=path.resolve().parent)
