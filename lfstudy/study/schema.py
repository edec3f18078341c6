"""The study config's JSON schema: ``lfstudy/schema.yaml``, every reconstruction method's and flow kind's parameters.

The schema file (``config/schema.yaml`` links to it) states the sections; each
reconstruction method declares its own parameters (``reconstruct.<name>``,
from :mod:`lfstudy.reconstruct`) and each flow kind its own (``flows.<name>``,
from :mod:`lfstudy.simulate.flows`), so the full schema is assembled here, above
the config plumbing (:mod:`lfstudy.config`) and both registries. The lists of
methods and flow kinds in the descriptions of ``reconstruct.method`` and
``flows.<name>.kind`` come from the registries too (built-in and installed ones).
"""

from __future__ import annotations

import copy
import functools
from typing import Any

from lfstudy.config import read_schema
from lfstudy.reconstruct.registry import available_methods, get_method, method_schemas
from lfstudy.simulate.flows import flow_schema, get_flow_class

__all__ = ["load_schema"]


@functools.lru_cache(maxsize=1)
def _schema() -> dict[str, Any]:
    schema = read_schema("schema.yaml")
    rec = schema["properties"]["reconstruct"]["properties"]
    names = available_methods()
    rec["method"]["enum"] = names
    # the list of methods is the registry's, each with its class's description (never a hand-kept copy)
    listed = "; ".join(f"{n} ({get_method(n).description})" for n in names)
    rec["method"]["description"] = f"{rec['method']['description'].strip()} {listed}"
    for name, sub in method_schemas().items():
        rec[name] = sub
    return schema


def _kinds_text(kinds: list[str]) -> str:
    return "; ".join(f"{k} ({getattr(get_flow_class(k), 'description', '')})" for k in kinds)


def load_schema() -> dict[str, Any]:
    """The JSON schema of a study config: ``schema.yaml`` plus every reconstruction
    method's parameters (``reconstruct.<method>``, from the method registry) and every
    flow kind's (``flows.<name>``: the kind's parameters by ``if``/``then``, from the flow
    registry, :func:`lfstudy.simulate.flows.flow_schema`)."""
    schema = copy.deepcopy(_schema())
    flows = schema["properties"]["flows"]["additionalProperties"]
    sub = flow_schema()
    kind = flows["properties"]["kind"]
    kind["enum"] = sub["properties"]["kind"]["enum"]
    kind["description"] = f"{kind['description'].strip()} {_kinds_text(kind['enum'])}"
    flows["allOf"] = sub["allOf"]
    return schema
