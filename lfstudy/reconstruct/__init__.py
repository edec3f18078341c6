"""Volume reconstruction (thesis sec. 5.5–5.6) on one object-space grid.

Modules: :mod:`~lfstudy.reconstruct.grid` (the reconstruction grid),
:mod:`~lfstudy.reconstruct.registry` (the method interface, found by name),
:mod:`~lfstudy.reconstruct.threshold` (sec. 5.5 threshold + dilation, and
``none``), :mod:`~lfstudy.reconstruct.projector` (plenoptic weights),
:mod:`~lfstudy.reconstruct.mart` (MART),
:mod:`~lfstudy.reconstruct.deconvolution` (Richardson–Lucy on the focal stack),
:mod:`~lfstudy.reconstruct.ipr` (iterative particle reconstruction fitted with the exact
camera model) and :mod:`~lfstudy.reconstruct.truth` (particles as voxel-integrated Gaussians
on a grid: the truth Q is measured against, and IPR's volume).
Import from this package: the modules behind it may move.
"""

from __future__ import annotations

from lfstudy.reconstruct.grid import GridError, ReconstructionGrid, default_voxel_z, make_grid
from lfstudy.reconstruct.registry import (
    ReconstructionError,
    ReconstructionInputs,
    ReconstructionMethod,
    ReconstructionSize,
    available_methods,
    detect_parameters,
    get_method,
    gives_particles,
    method_schemas,
    reconstruct,
    reconstruct_particles,
    register_method,
    unregister_method,
)
from lfstudy.reconstruct.threshold import disk, focal_stack_as_is, threshold_dilate

__all__ = [
    "reconstruct",
    "reconstruct_particles",
    "gives_particles",
    "ReconstructionInputs",
    "ReconstructionMethod",
    "ReconstructionSize",
    "ReconstructionError",
    "available_methods",
    "detect_parameters",
    "get_method",
    "method_schemas",
    "register_method",
    "unregister_method",
    "ReconstructionGrid",
    "GridError",
    "make_grid",
    "default_voxel_z",
    "threshold_dilate",
    "focal_stack_as_is",
    "disk",
]
