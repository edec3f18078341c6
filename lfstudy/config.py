"""Study configuration: load, validate against the JSON schema, fill defaults, expand the sweep.

The schema lives in ``lfstudy/schema.yaml`` (``config/schema.yaml`` links to it).
Every invalid value stops with one :class:`ConfigError` naming the key, the
value and what is allowed.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from lfstudy.optics import OpticsError, PlenopticCamera

__all__ = [
    "ConfigError",
    "load_schema",
    "read_yaml",
    "load_config",
    "validate_config",
    "validate_section",
    "sweep_of",
    "expand_cases",
    "case_config",
    "stage_config",
    "cases_table",
]


class ConfigError(ValueError):
    """An invalid configuration value (the message names key, value and allowed range)."""


@functools.lru_cache(maxsize=1)
def _schema() -> dict[str, Any]:
    schema = yaml.safe_load(resources.files("lfstudy").joinpath("schema.yaml").read_text())
    # Each reconstruction method declares its own parameters: reconstruct.<name>.
    from lfstudy.reconstruct.registry import available_methods, method_schemas

    rec = schema["properties"]["reconstruct"]["properties"]
    rec["method"]["enum"] = available_methods()
    for name, sub in method_schemas().items():
        rec[name] = sub
    return schema


def load_schema() -> dict[str, Any]:
    """The JSON schema of a study config: ``schema.yaml`` plus every reconstruction
    method's parameters (``reconstruct.<method>``, from the method registry)."""
    return copy.deepcopy(_schema())


def _with_defaults(validator_class):
    # The documented jsonschema recipe: fill "default" values while validating.
    validate_props = validator_class.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for prop, sub in properties.items():
                if "default" in sub and prop not in instance:
                    instance[prop] = copy.deepcopy(sub["default"])
        yield from validate_props(validator, properties, instance, schema)

    return jsonschema.validators.extend(validator_class, {"properties": set_defaults})


_Validator = _with_defaults(jsonschema.Draft202012Validator)


def _key(path) -> str:
    return ".".join(str(p) for p in path) or "<root>"


def _describe(err: jsonschema.ValidationError) -> str:
    s, _v = err.schema, err.instance
    if err.validator in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        lo = s.get("minimum", s.get("exclusiveMinimum"))
        hi = s.get("maximum", s.get("exclusiveMaximum"))
        lb = "[" if "minimum" in s else "("
        rb = "]" if "maximum" in s else ")"
        lo_s = "-inf" if lo is None else f"{lo}"
        hi_s = "inf" if hi is None else f"{hi}"
        return f"allowed range is {lb}{lo_s}, {hi_s}{rb}"
    if err.validator == "minItems":
        n = s["minItems"]
        return f"give at least {n} value{'s' if n > 1 else ''}"
    if err.validator == "enum":
        return "allowed values are " + ", ".join(repr(e) for e in s["enum"])
    if err.validator == "additionalProperties":
        allowed = sorted(s.get("properties", {}))
        return f"{err.message}; allowed keys are {', '.join(allowed)}"
    if err.validator == "oneOf":
        opts = []
        for sub in s["oneOf"]:
            if "enum" in sub:
                opts += [repr(e) for e in sub["enum"]]
            elif "exclusiveMinimum" in sub:
                opts.append(f"a number > {sub['exclusiveMinimum']}")
            else:
                opts.append(sub.get("type", "?"))
        return "allowed: " + " or ".join(opts)
    return err.message


def validate_section(
    schema: Mapping[str, Any], value: Mapping[str, Any], prefix: str = "", *, registry: Any = None
) -> dict[str, Any]:
    """Validate ``value`` against ``schema``, returning a deep copy with defaults filled in.

    ``registry`` (a :class:`referencing.Registry`) resolves ``$ref`` to other schema
    files, e.g. the recording schema's references to the study schema's sections.

    Raises
    ------
    ConfigError
        On the most specific problem, naming the key (under ``prefix``), the value and
        what is allowed.
    """
    out = copy.deepcopy(dict(value))
    kw = {"registry": registry} if registry is not None else {}
    errors = list(_Validator(schema, **kw).iter_errors(out))
    if errors:
        # The deepest, most specific message is the useful one.
        err = max(errors, key=lambda e: len(e.path))
        key = ".".join(p for p in (prefix, _key(err.path) if err.path else "") if p) or "<root>"
        raise ConfigError(f"config key '{key}' = {err.instance!r}: {_describe(err)}")
    # Re-run once so defaults nested inside freshly defaulted sections are filled.
    _Validator(schema, **kw).validate(out)
    return out


def validate_config(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Validate a config mapping, returning a deep copy with defaults filled in.

    Besides the schema, checks what a schema cannot: that the camera can be
    built (f-number reachable, pitch vs pixel) for every swept combination,
    and that swept flows are defined.

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
    for name, spec in cfg["flows"].items():
        if spec["kind"] == "uniform" and "displacement" not in spec:
            raise ConfigError(f"config key 'flows.{name}.displacement': required for kind 'uniform' ([dx, dy, dz] mm)")
        if spec["kind"] == "hill" and ("radius" not in spec or "u0" not in spec):
            raise ConfigError(f"config key 'flows.{name}': kind 'hill' needs radius (> 0 mm) and u0")
    count = cfg["particles"].get("count")
    if count is not None and len(cfg["sweep"].get("ppp", [])) > 1:
        raise ConfigError(
            f"config key 'particles.count' = {count}: a fixed particle count overrides ppp, so every swept "
            "ppp value would image the same field; drop particles.count or sweep.ppp"
        )
    from lfstudy.reconstruct.grid import GridError
    from lfstudy.study.case import case_grid
    from lfstudy.study.resources import check_memory
    from lfstudy.study.sweep import NAMED, format_value

    sweep = sweep_of(cfg)
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
        try:  # the grid a case reconstructs on (grid.z_range, voxel sizes, its memory cap)
            case_grid(ccfg)
        except GridError as exc:
            raise ConfigError(f"config key 'grid' (case {case.case_id}): {exc}") from None
        check_memory(ccfg, where=f"case {case.case_id}")
    return cfg


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML config file as a mapping (not validated).

    Raises
    ------
    ConfigError
        The file is missing, not valid YAML, or not a mapping at the top level.
    """
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"config file {str(path)!r} does not exist") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"config file {str(path)!r}: expected a mapping at the top level")
    return raw


def load_config(path: str | Path) -> dict[str, Any]:
    """Read a YAML config file and validate it (defaults filled in)."""
    return validate_config(read_yaml(path))


def sweep_of(cfg: Mapping[str, Any]) -> Any:
    """The :class:`~lfstudy.study.sweep.Sweep` of a validated config."""
    from lfstudy.study.sweep import Sweep

    return Sweep(cfg)


def expand_cases(cfg: Mapping[str, Any]) -> list[Any]:
    """All cases of the sweep (Cartesian product of its lists), in a stable order.

    A named parameter that is not swept keeps the single value of the base config.
    """
    return sweep_of(cfg).cases()


def case_config(cfg: Mapping[str, Any], case: Any) -> dict[str, Any]:
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


def stage_config(cfg: Mapping[str, Any], case: Any, stage: str) -> dict[str, Any]:
    """The part of a case's config that ``stage`` reads (:data:`lfstudy.study.sweep.STAGES`),
    plus ``stage_id`` (where the stage's outputs live) and ``calib_id``.

    ``case_id`` is added only for the per-case ``errors`` stage: every other stage's output
    is shared by all cases at its location, so its config (the Snakemake rule's params, and
    the provenance attrs it writes) must not depend on which of them stands for it —
    otherwise a change of the sweep reruns shared stages whose settings did not change.
    """
    from lfstudy.study.sweep import STAGES

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
