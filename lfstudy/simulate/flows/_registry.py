"""Flow kinds found by name: the built-ins and those of other packages (entry-point group ``lfstudy.flows``).

A config's ``flows.<name>.kind`` is a kind's name; its other keys (bar ``dt``
and ``n_steps``, which every kind shares) are the kind's parameters, passed to
its class by keyword. A kind is a class with

* ``name`` (the kind), ``description`` (one line) and ``parameters``: JSON-schema
  properties (type, range, description) of its constructor's keyword arguments;
* ``velocity(x, y, z)``: vectorised, object frame, mm per unit time;
* optionally ``config_required`` (parameters a config must give although the
  class has a default) and ``input_files(params)`` (files the flow reads: the
  workflow makes them inputs of the rules that use the flow).

A constructor argument without a default is required. The defaults live in the
constructor only. Kinds of other packages are found through the entry-point
group :data:`ENTRY_POINT_GROUP` (``mykind = "package.module:Class"``, the entry
point's name is the kind); one that fails to load, or that reuses a built-in's name,
is skipped with a warning, so every config that does not use it keeps working (one
loader and one rule for both registries: :mod:`lfstudy.plugins`).
"""

from __future__ import annotations

import functools
import importlib
import inspect
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lfstudy.config import ConfigError, validate_section
from lfstudy.plugins import load_plugins
from lfstudy.simulate.flows._core import FlowError

__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "COMMON",
    "available_kinds",
    "get_flow_class",
    "flow_parameters",
    "flow_schema",
    "flow_from_config",
    "check_flow_config",
    "resolve_flow_paths",
    "flow_input_files",
]

#: Built-in kinds: name -> "module:Class" (imported on first use).
BUILTIN: dict[str, str] = {
    "uniform": "lfstudy.simulate.flows._analytic:UniformFlow",
    "hill": "lfstudy.simulate.flows._analytic:HillVortex",
    "lamb_oseen": "lfstudy.simulate.flows._analytic:LambOseenVortex",
    "vortex_ring": "lfstudy.simulate.flows._analytic:VortexRing",
    "channel": "lfstudy.simulate.flows._analytic:ChannelFlow",
    "blasius": "lfstudy.simulate.flows._analytic:BlasiusBoundaryLayer",
    "file": "lfstudy.simulate.flows._gridded:GriddedFlow",
}

#: Entry-point group of flow kinds from other packages.
ENTRY_POINT_GROUP = "lfstudy.flows"

#: Keys every flow entry has besides its kind's parameters (the integration over Δt).
COMMON = ("kind", "dt", "n_steps", "name")


def _load(spec: str) -> type:
    mod, _, attr = spec.partition(":")
    return getattr(importlib.import_module(mod), attr)


def flow_parameters(cls: type) -> tuple[dict[str, Any], list[str]]:
    """A kind's parameters with their defaults (from its constructor) and the required ones.

    Raises
    ------
    FlowError
        The class has no ``velocity``, its constructor takes ``*args``/``**kwargs``,
        or its keyword arguments are not the names in ``parameters``.
    """
    where = f"flow kind {getattr(cls, 'name', '?')!r} ({getattr(cls, '__name__', cls)!r})"
    if not isinstance(cls, type) or not callable(getattr(cls, "velocity", None)):
        raise FlowError(f"{where}: not a class with a velocity(x, y, z) method")
    params = getattr(cls, "parameters", None)
    if not isinstance(params, Mapping):
        raise FlowError(f"{where}: needs `parameters`, a mapping of JSON-schema properties")
    defaults: dict[str, Any] = {}
    required: list[str] = []
    for p in inspect.signature(cls).parameters.values():
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            raise FlowError(f"{where}: the constructor takes {p}; name every parameter")
        if p.default is p.empty:
            required.append(p.name)
        else:
            defaults[p.name] = p.default
    names = set(defaults) | set(required)
    if names != set(params):
        raise FlowError(
            f"{where}: the constructor takes {sorted(names)} but `parameters` declares {sorted(params)}; "
            "they must be the same"
        )
    clash = names & set(COMMON)
    if clash:
        raise FlowError(f"{where}: parameter names {sorted(clash)} are reserved for every flow")
    required += [k for k in getattr(cls, "config_required", ()) if k not in required]
    return defaults, required


@functools.lru_cache(maxsize=1)
def _plugins() -> tuple[dict[str, type], dict[str, str]]:
    """The kinds of the entry-point group, loaded: ``({name: class}, {name: why it was skipped})``."""

    def check(name: str, cls: Any) -> None:
        flow_parameters(cls)

    return load_plugins(ENTRY_POINT_GROUP, "flow kind", check, builtin=BUILTIN)


def available_kinds() -> list[str]:
    """Every flow kind a config may name: the built-ins (in their order), then installed ones (sorted)."""
    return [*BUILTIN, *sorted(_plugins()[0])]


def get_flow_class(kind: str) -> type:
    """The class of flow kind ``kind``.

    Raises
    ------
    FlowError
        Unknown kind (the message lists the available ones) or a plugin that failed to load.
    """
    if kind in BUILTIN:
        return _load(BUILTIN[kind])
    plugins, skipped = _plugins()
    if kind in plugins:
        return plugins[kind]
    if kind in skipped:
        raise FlowError(
            f"flow kind = {kind!r}: the kind installed under this name (entry point group {ENTRY_POINT_GROUP!r}) "
            f"failed to load: {skipped[kind]}"
        )
    raise FlowError(f"flow kind = {kind!r}: unknown; allowed values are {', '.join(map(repr, available_kinds()))}")


def flow_schema() -> dict[str, Any]:
    """The JSON schema of one ``flows.<name>`` entry: ``kind`` from :func:`available_kinds`, ``dt``,
    ``n_steps``, and each kind's parameters (types, ranges, required, no other keys) by ``if``/``then``.

    Defaults are not filled in (they stay in each class's constructor), so a flow
    entry is passed on as written.
    """
    kinds = available_kinds()
    common = {
        "kind": {"type": "string", "enum": kinds},
        "dt": {"type": "number", "exclusiveMinimum": 0, "default": 1.0},
        "n_steps": {"type": "integer", "minimum": 1, "default": 100},
    }
    branches = []
    for kind in kinds:
        cls = get_flow_class(kind)
        defaults, required = flow_parameters(cls)
        props = {}
        for k, v in cls.parameters.items():
            note = f" (default {defaults[k]!r})" if k in defaults else ""
            props[k] = {**v, "description": str(v.get("description", "")) + note}
        branches.append(
            {
                "if": {"properties": {"kind": {"const": kind}}, "required": ["kind"]},
                "then": {
                    "properties": {**{k: {} for k in common}, **props},
                    "required": ["kind", *required],
                    "additionalProperties": False,
                },
            }
        )
    return {
        "type": "object",
        "required": ["kind"],
        "properties": common,
        "allOf": branches,
    }


def _params(spec: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in spec.items() if k not in COMMON}


def check_flow_config(spec: Mapping[str, Any], where: str = "flow") -> None:
    """Check one flow entry: schema (kind, parameter types and ranges) and what the class itself checks.

    A kind with a ``check_config(params)`` classmethod is checked by it instead
    of being built (a file flow: the file's structure, without reading the
    velocities).

    Raises
    ------
    ConfigError
        Naming ``where`` (e.g. ``flows.vortex``), the key and what is allowed.
    """
    validate_section(flow_schema(), dict(spec), where)
    cls = get_flow_class(spec["kind"])
    params = _params(spec)
    try:
        check = getattr(cls, "check_config", None)
        if check is not None:  # e.g. a file flow: its structure, without reading the velocities
            check(params)
        else:
            cls(**params)
    except FlowError as exc:
        raise ConfigError(f"config key '{where}': {exc}") from None


def flow_from_config(spec: Mapping[str, Any]):
    """Build a flow from a config entry (``kind`` and the kind's parameters; ``dt``, ``n_steps`` and
    ``name`` are ignored here).

    Raises
    ------
    FlowError
        Unknown kind, a parameter of the wrong type or out of range (named
        with the kind and its allowed values).
    """
    kind = spec.get("kind")
    if not isinstance(kind, str):
        raise FlowError(f"flow kind = {kind!r}: allowed values are {', '.join(map(repr, available_kinds()))}")
    cls = get_flow_class(kind)
    where = f"flows.{spec['name']}" if "name" in spec else "flow"
    try:
        validate_section(flow_schema(), {k: v for k, v in spec.items() if k != "name"}, where)
    except ConfigError as exc:
        raise FlowError(str(exc)) from None
    return cls(**_params(spec))


def resolve_flow_paths(spec: Mapping[str, Any], base: str | Path) -> dict[str, Any]:
    """A copy of a flow entry whose file ``path`` (kind ``file``) is absolute: relative ones are
    taken relative to ``base`` (the config file's folder)."""
    out = dict(spec)
    if out.get("kind") == "file" and isinstance(out.get("path"), str) and out["path"]:
        p = Path(out["path"]).expanduser()
        out["path"] = str(p if p.is_absolute() else (Path(base) / p).resolve())
    return out


def flow_input_files(spec: Mapping[str, Any]) -> list[str]:
    """The files a flow entry reads (a file flow's store or file; a plugin's ``input_files``), so the
    workflow reruns the rules that use it when they change."""
    kind = spec.get("kind")
    if kind == "file":
        from lfstudy.simulate.flows._gridded import velocity_file_inputs

        return velocity_file_inputs(spec["path"])
    if kind in BUILTIN:
        return []
    cls = get_flow_class(kind)
    files = getattr(cls, "input_files", None)
    return [str(f) for f in files(_params(spec))] if files is not None else []
