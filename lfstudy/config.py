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

__all__ = ["ConfigError", "UniqueKeyLoader", "read_schema", "read_yaml", "validate_section"]


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
    if err.validator in ("minItems", "maxItems") and s.get("minItems") == s.get("maxItems"):
        return f"give exactly {s['minItems']} values, not {len(err.instance)}"  # a pair
    if err.validator == "maxItems":
        n = s["maxItems"]
        return f"give at most {n} value{'s' if n > 1 else ''}, not {len(err.instance)}"
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


_JSON_TYPES = {list: "array", dict: "object", str: "string", bool: "boolean", type(None): "null"}


def _json_type(value: Any) -> str:
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "number"
    return next((t for cls, t in _JSON_TYPES.items() if isinstance(value, cls)), "?")


def _declares(option: Mapping[str, Any], kind: str) -> bool:
    """Whether a schema option declares the JSON type ``kind`` (an integer is a number too)."""
    t = option.get("type")
    declared = set(t if isinstance(t, list) else [t] if t is not None else [])
    return kind in declared or (kind == "integer" and "number" in declared)


def _meant_option(err: jsonschema.ValidationError) -> jsonschema.ValidationError:
    """For a ``oneOf`` that no option fits: the error of the option a list or mapping was meant for.

    "allowed: string or array" says nothing useful about a list (``series: []``, a pair of three
    files): it is an array already. When exactly one option declares the value's type, that
    option's own (deepest) error is the message — "give at least 2 values". Otherwise, for a
    scalar (``fnumber: wide`` is neither 'matched' nor a number: both are worth saying), or when
    several options fit, the ``oneOf`` error stays.
    """
    while err.validator == "oneOf" and err.context and isinstance(err.instance, (list, dict)):
        options = err.schema["oneOf"]
        failed = {sub.relative_schema_path[0] for sub in err.context}
        if len(failed) < len(options):  # some option fits: the value is valid under several
            break
        kind = _json_type(err.instance)
        meant = [i for i, opt in enumerate(options) if _declares(opt, kind)]
        if len(meant) != 1:
            break
        subs = [sub for sub in err.context if sub.relative_schema_path[0] == meant[0]]
        err = max(subs, key=lambda e: len(e.absolute_path))
    return err


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
        err = _meant_option(max(errors, key=lambda e: len(e.path)))
        where = ".".join(p for p in (prefix, _key(err.absolute_path) if err.absolute_path else "") if p)
        if err.validator == "additionalProperties" and isinstance(err.instance, dict):
            raise ConfigError(_unknown_keys(err, where))
        raise ConfigError(f"config key '{where or '<root>'}' = {_short(err.instance)}: {_describe(err)}")
    # Re-run once so defaults nested inside freshly defaulted sections are filled.
    _Validator(schema, **kw).validate(out)
    return out


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, path: str, first: int, second: int) -> None:
        super().__init__(path)
        self.path, self.first, self.second = path, first, second


class UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader refusing a key given twice in one mapping.

    YAML says keys are unique, yet PyYAML keeps the last of duplicates silently: a config
    with two ``piv:`` sections would run with the second only. The composed node tree is
    walked before construction, so the error names the key's dotted path and both lines.
    Merge keys (``<<: *anchor``) are not duplicates: what they bring in may be overridden.
    """

    def get_single_node(self) -> yaml.Node | None:
        node = super().get_single_node()
        if node is not None:
            _check_unique(node, "")
        return node


def _check_unique(node: yaml.Node, where: str, seen_nodes: set[int] | None = None) -> None:
    seen_nodes = set() if seen_nodes is None else seen_nodes
    if id(node) in seen_nodes:  # an alias: its anchor's node was checked (and may refer to itself)
        return
    seen_nodes.add(id(node))
    if isinstance(node, yaml.MappingNode):
        seen: dict[tuple[str, str], int] = {}
        for key_node, value_node in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(key_node, yaml.ScalarNode):
                continue
            key = (key_node.tag, key_node.value)  # 1 and "1" are different keys
            path = f"{where}.{key_node.value}" if where else str(key_node.value)
            line = key_node.start_mark.line + 1
            if key in seen:
                raise _DuplicateKey(path, seen[key], line)
            seen[key] = line
            _check_unique(value_node, path, seen_nodes)
    elif isinstance(node, yaml.SequenceNode):
        for k, item in enumerate(node.value):
            _check_unique(item, f"{where}.{k}" if where else str(k), seen_nodes)


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML config file as a mapping (not validated).

    Raises
    ------
    ConfigError
        The file is missing, a folder, not valid YAML (a key given twice in one mapping
        included), or not a mapping at the top level.
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"config file {str(path)!r} is a folder; give the YAML file in it")
    try:
        raw = yaml.load(path.read_text(), Loader=UniqueKeyLoader)  # a SafeLoader
    except FileNotFoundError:
        raise ConfigError(f"config file {str(path)!r} does not exist") from None
    except _DuplicateKey as exc:
        raise ConfigError(
            f"config file {str(path)!r}: key '{exc.path}' is given twice (lines {exc.first} and {exc.second}); "
            "YAML keeps only the last, so keep one"
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"config file {str(path)!r}: expected a mapping at the top level")
    return raw
