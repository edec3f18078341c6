"""Config plumbing every stage shares: the error, YAML reading, schema validation.

This is the bottom layer: it imports nothing else of lfstudy, so every stage
(:mod:`lfstudy.reconstruct`, :mod:`lfstudy.process`, :mod:`lfstudy.study`) can
use it. The study config itself (its schema with the reconstruction methods'
parameters, :func:`~lfstudy.study.config.validate_config`, the per-case
configs) lives in :mod:`lfstudy.study.config`. Every invalid value stops with
one :class:`ConfigError` naming the key, the value and what is allowed.
"""

from __future__ import annotations

import copy
import difflib
import functools
import re
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import yaml

__all__ = ["ConfigError", "read_schema", "read_yaml", "validate_section"]


class ConfigError(ValueError):
    """An invalid configuration value (the message names key, value and allowed range)."""


@functools.cache
def _read_schema(name: str) -> dict[str, Any]:
    return yaml.safe_load(resources.files("lfstudy").joinpath(name).read_text())


def read_schema(name: str) -> dict[str, Any]:
    """A JSON schema shipped with lfstudy (``lfstudy/<name>``, e.g. ``schema.yaml``), as written.

    The study schema with the reconstruction methods' parameters filled in is
    :func:`lfstudy.study.config.load_schema`.
    """
    return copy.deepcopy(_read_schema(name))


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


#: The pattern of a study's or a recording's ``name`` (config/schema.yaml): it names results/<name>/.
PLAIN_NAME = "^[A-Za-z0-9_-][A-Za-z0-9_.-]*$"


def _key(path) -> str:
    return ".".join(str(p) for p in path) or "<root>"


_TYPES = {"object": "a mapping of keys", "array": "a list", "number": "a number", "integer": "an integer",
          "string": "a string", "boolean": "true or false", "null": "null"}  # fmt: skip


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
    if err.validator == "type":  # jsonschema's own message repeats the whole value
        kinds = s["type"] if isinstance(s["type"], list) else [s["type"]]
        return "expected " + " or ".join(_TYPES.get(k, k) for k in kinds)
    if err.validator == "minItems":
        n = s["minItems"]
        return f"give at least {n} value{'s' if n > 1 else ''}"
    if err.validator == "pattern" and s.get("pattern") == PLAIN_NAME:
        return "a plain name: letters, digits, '_', '-' and '.', not starting with '.' (no path separators)"
    if err.validator == "maxLength":
        return f"at most {s['maxLength']} characters"
    if err.validator == "enum":
        return "allowed values are " + ", ".join(repr(e) for e in s["enum"])
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


def _short(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters (a whole section is no help in a one-line message)."""
    r = repr(value)
    return r if len(r) <= limit else r[: limit - 4].rstrip() + " ..."


def _unknown_keys(err: jsonschema.ValidationError, where: str) -> str:
    """The message for keys a section does not have: their dotted paths, the allowed keys, a near miss."""
    props = err.schema.get("properties", {})
    patterns = err.schema.get("patternProperties", {})
    extra = [k for k in err.instance if k not in props and not any(re.search(p, str(k)) for p in patterns)]
    paths = ", ".join(f"'{where + '.' if where else ''}{k}'" for k in extra)
    hints = [f"{k!r} -> {m[0]!r}" for k in extra if (m := difflib.get_close_matches(str(k), props, n=1))]
    section = f"under '{where}'" if where else "at the top level"
    msg = f"config key{'s' if len(extra) > 1 else ''} {paths}: not a setting; allowed keys {section} are "
    msg += ", ".join(sorted(props))
    return msg + (f" (did you mean {', '.join(hints)}?)" if hints else "")


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
        where = ".".join(p for p in (prefix, _key(err.path) if err.path else "") if p)
        if err.validator == "additionalProperties" and isinstance(err.instance, dict):
            raise ConfigError(_unknown_keys(err, where))
        raise ConfigError(f"config key '{where or '<root>'}' = {_short(err.instance)}: {_describe(err)}")
    # Re-run once so defaults nested inside freshly defaulted sections are filled.
    _Validator(schema, **kw).validate(out)
    return out


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
