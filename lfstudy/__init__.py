"""lfstudy: parametric studies of single-camera light-field (plenoptic) 3-D PIV.

Stages are pure functions over numpy/xarray objects, one subpackage per stage
group (``lfstudy.simulate``, ``lfstudy.lightfield``, ``lfstudy.reconstruct``,
``lfstudy.piv``, ``lfstudy.study``); I/O lives in ``lfstudy.io`` and the sweep in
the top-level ``Snakefile``. ``lfstudy.open_study("results/<name>")`` opens a
study's results as one lazy DataTree.

The names below load on first use (PEP 562), so importing one stage (e.g.
``lfstudy.piv``, which reads ``__version__``) does not load the others.
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version
from typing import Any

try:
    __version__ = version("lfstudy")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0+unknown"

#: name -> the module that defines it (imported on first access)
_LAZY = {"PlenopticCamera": "lfstudy.optics", "open_study": "lfstudy.io"}

__all__ = ["PlenopticCamera", "open_study", "__version__"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later lookups skip this hook
        return value
    raise AttributeError(f"module 'lfstudy' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
