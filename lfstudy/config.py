"""Study configuration: load, validate against the JSON schema, fill defaults, expand the sweep.

The schema lives in ``lfstudy/schema.yaml`` (``config/schema.yaml`` links to it).
Every invalid value stops with one :class:`ConfigError` naming the key, the
value and what is allowed.
"""

from __future__ import annotations

import copy
import functools
import itertools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from lfstudy.optics import OpticsError, PlenopticCamera

__all__ = [
    "ConfigError",
    "SWEEP_KEYS",
    "Case",
    "load_schema",
    "load_config",
    "validate_config",
    "validate_section",
    "expand_cases",
    "case_config",
    "cases_table",
]

#: Swept parameters, in the order of case ids and of the sweep Dataset's dimensions.
SWEEP_KEYS: tuple[str, ...] = ("magnification", "fnumber", "lenslet_pitch", "ppp", "flow")
#: Short names used in case ids / paths (``mag~-1/fnum~matched/...``).
SHORT: dict[str, str] = {
    "magnification": "mag",
    "fnumber": "fnum",
    "lenslet_pitch": "pitch",
    "ppp": "ppp",
    "flow": "flow",
}


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


def validate_section(schema: Mapping[str, Any], value: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Validate ``value`` against ``schema``, returning a deep copy with defaults filled in.

    Raises
    ------
    ConfigError
        On the most specific problem, naming the key (under ``prefix``), the value and
        what is allowed.
    """
    out = copy.deepcopy(dict(value))
    errors = list(_Validator(schema).iter_errors(out))
    if errors:
        # The deepest, most specific message is the useful one.
        err = max(errors, key=lambda e: len(e.path))
        key = ".".join(p for p in (prefix, _key(err.path) if err.path else "") if p) or "<root>"
        raise ConfigError(f"config key '{key}' = {err.instance!r}: {_describe(err)}")
    # Re-run once so defaults nested inside freshly defaulted sections are filled.
    _Validator(schema).validate(out)
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
    sweep = cfg["sweep"]
    for name in sweep.get("flow", []):
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
    for case in _iter_params(cfg):
        try:
            PlenopticCamera.from_config(_apply(cfg, case))
        except OpticsError as exc:
            where = ", ".join(f"{k}={v}" for k, v in case.items() if k != "flow")
            raise ConfigError(f"config key 'camera' (case {where}): {exc}") from None
    return cfg


def load_config(path: str | Path) -> dict[str, Any]:
    """Read a YAML config file and validate it (defaults filled in)."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"config file {str(path)!r} does not exist") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"config file {str(path)!r}: expected a mapping at the top level")
    return validate_config(raw)


def _base_params(cfg: Mapping[str, Any]) -> dict[str, Any]:
    cam = cfg["camera"]
    flows = list(cfg["flows"])
    return {
        "magnification": cam["magnification"],
        "fnumber": cam["main_lens"].get("fnumber", "matched"),
        "lenslet_pitch": cam["lenslet"]["pitch"],
        "ppp": cfg["particles"]["ppp"],
        "flow": flows[0],
    }


def _iter_params(cfg: Mapping[str, Any]) -> Iterator[dict[str, Any]]:
    base = _base_params(cfg)
    axes = [cfg["sweep"].get(k, [base[k]]) for k in SWEEP_KEYS]
    for combo in itertools.product(*axes):
        yield dict(zip(SWEEP_KEYS, combo))


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


@dataclass(frozen=True)
class Case:
    """One point of the sweep."""

    magnification: float
    fnumber: float | str
    lenslet_pitch: float
    ppp: float
    flow: str

    @property
    def params(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in SWEEP_KEYS}

    @property
    def case_id(self) -> str:
        """Stable, readable id, also the results sub-path: ``mag~-1/fnum~matched/...``."""
        return "/".join(f"{SHORT[k]}~{_fmt(getattr(self, k))}" for k in SWEEP_KEYS)

    @classmethod
    def from_id(cls, case_id: str) -> Case:
        """Parse a case id back (inverse of :attr:`case_id`)."""
        inv = {v: k for k, v in SHORT.items()}
        vals: dict[str, Any] = {}
        for part in case_id.strip("/").split("/"):
            if "~" not in part:
                raise ConfigError(f"case id {case_id!r}: part {part!r} is not key~value")
            k, v = part.split("~", 1)
            if k not in inv:
                raise ConfigError(f"case id {case_id!r}: unknown key {k!r}; allowed {sorted(inv)}")
            key = inv[k]
            if key == "flow" or (key == "fnumber" and v == "matched"):
                vals[key] = v
            else:
                vals[key] = float(v)
        missing = set(SWEEP_KEYS) - set(vals)
        if missing:
            raise ConfigError(f"case id {case_id!r}: missing {sorted(missing)}")
        return cls(**vals)


def expand_cases(cfg: Mapping[str, Any]) -> list[Case]:
    """All sweep cases (Cartesian product of the sweep lists), in a stable order.

    A sweep key that is absent keeps the single value of the base config.
    """
    return [Case(**p) for p in _iter_params(cfg)]


def _apply(cfg: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(dict(cfg))
    cam = out["camera"]
    cam["magnification"] = params["magnification"]
    cam["main_lens"]["fnumber"] = params["fnumber"]
    cam["lenslet"]["pitch"] = params["lenslet_pitch"]
    out["particles"]["ppp"] = params["ppp"]
    return out


def case_config(cfg: Mapping[str, Any], case: Case | str) -> dict[str, Any]:
    """The full config of one case: base config with the case's swept values applied.

    The chosen flow's spec is placed under ``flow`` (with its name).
    """
    if isinstance(case, str):
        case = Case.from_id(case)
    if case.flow not in cfg["flows"]:
        raise ConfigError(f"case flow {case.flow!r}: unknown; allowed values are {sorted(cfg['flows'])}")
    out = _apply(cfg, case.params)
    out["flow"] = {"name": case.flow, **cfg["flows"][case.flow]}
    out["case_id"] = case.case_id
    return out


def cases_table(cfg: Mapping[str, Any]):
    """The expanded sweep as a pandas DataFrame indexed by case id, with derived camera columns."""
    import pandas as pd

    rows = []
    for case in expand_cases(cfg):
        cam = PlenopticCamera.from_config(case_config(cfg, case))
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
