"""lfstudy: parametric studies of single-camera light-field (plenoptic) 3-D PIV.

Stages are pure functions over numpy/xarray objects (see ``lfstudy.optics``,
``lfstudy.simulate.particles``, ``lfstudy.simulate.flows`` ...); I/O lives in ``lfstudy.io`` and
the sweep in the top-level ``Snakefile``.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lfstudy")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0+unknown"

from lfstudy.optics import PlenopticCamera

__all__ = ["PlenopticCamera", "__version__"]
