"""3-D (and 2-D) PIV by WIDIM (thesis ch. 6, App. D).

Modules: :mod:`~lfstudy.piv.engine` (multi-pass, multi-grid correlation,
validation), :mod:`~lfstudy.piv.deform` (numba B-spline window deformation),
:mod:`~lfstudy.piv.depth` (depth calibration by a traversed volume),
:mod:`~lfstudy.piv.synthetic` (exact synthetic particle pairs for tests and
benchmarks) and :mod:`~lfstudy.piv.ptv` (tracking of fitted particle lists,
binned on a PIV grid). Import from this package: the modules behind it may move.
"""

from __future__ import annotations

from lfstudy.piv.depth import correct_depth, depth_response
from lfstudy.piv.engine import grid_nodes, peak_locking_index, widim
from lfstudy.piv.ptv import bin_tracks, match_particles, validate_tracks
from lfstudy.piv.synthetic import particle_pair

__all__ = [
    "widim",
    "peak_locking_index",
    "grid_nodes",
    "particle_pair",
    "depth_response",
    "correct_depth",
    "match_particles",
    "validate_tracks",
    "bin_tracks",
]
