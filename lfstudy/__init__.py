"""lfstudy: parametric studies of single-camera light-field (plenoptic) 3-D PIV.

Stages are pure functions over numpy/xarray objects, one subpackage per stage
group (``lfstudy.simulate``, ``lfstudy.lightfield``, ``lfstudy.reconstruct``,
``lfstudy.piv``, ``lfstudy.study``); I/O lives in ``lfstudy.io`` and the sweep in
the top-level ``Snakefile``. ``lfstudy.open_study("results/<name>")`` opens a
study's results as one lazy DataTree.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lfstudy")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0+unknown"

from lfstudy.io import open_study
from lfstudy.optics import PlenopticCamera

__all__ = ["PlenopticCamera", "open_study", "__version__"]
