"""The method ``ipr``: the fitted particles rendered on the grid, so depth calibration, PIV, errors and report
run unchanged (package docstring).

:func:`ipr` is :func:`~lfstudy.reconstruct.ipr.ipr_particles` and :func:`particle_volume`; :class:`IPR` is the
registered method, its parameters the fields of :class:`~lfstudy.reconstruct.ipr.IPRSettings` and ``blob_sigma``.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct.grid import ReconstructionGrid, default_voxel_z
from lfstudy.reconstruct.ipr.candidates import _REFINE_XY, _REFINE_Z
from lfstudy.reconstruct.ipr.fit import ipr_particles
from lfstudy.reconstruct.ipr.settings import IPRSettings
from lfstudy.reconstruct.ipr.shake import _CACHE_BYTES
from lfstudy.reconstruct.registry import ReconstructionInputs, ReconstructionMethod, ReconstructionSize
from lfstudy.reconstruct.truth import render_truth

__all__ = ["IPR", "ipr", "particle_volume", "render_particles"]

#: One thread's fit time per seeded particle [s], an upper figure of those measured (quiet 2-core machine, 1 thread,
#: the defaults): a full demo frame 28.6 s for 1,467 particles (19.5 ms), Table 4.3 crops 300 x 300 px at 0.005 ppp
#: 17-24 s for 450 (38-53 ms; ``benchmarks/bench_ipr.py``), the full Table 4.3 frame ~44-49 min for ~79,000 (33-37 ms)
_SECONDS_PER_PARTICLE = 0.06
#: the fit's two reused image buffers (_FitImages.scratch) at most: a shake batch of 64 particles' 7 images of ~40,000
#: pixels (the full Table 4.3 frame's mean patch) with 25 % headroom, and the Gauss-Newton step's images
_SCRATCH_BYTES = 1.25 * (64 * 7 * 40_000 * 8 + 64 * 40_000 * 8)

#: The output volume's parameter (``reconstruct.ipr.blob_sigma``), besides the fit's (:class:`IPRSettings`).
_BLOB_SIGMA = {
    "type": "number",
    "minimum": 0,
    "maximum": 5,
    "description": (
        "sigma [voxels] of the output volume's particles; 0: the case's truth sigma (Q's). The paired PIV renders "
        "the particles again with piv.particle_sigma"
    ),
}


def render_particles(
    particles: xr.Dataset, grid: ReconstructionGrid, camera: PlenopticCamera, blob_sigma: float = 0.0
) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The volume on ``grid`` of a particle list: each particle's Gaussian integrated over each voxel.

    The particles as :func:`lfstudy.reconstruct.truth.render_truth` renders the truth (the
    reference volume of Q), so a perfect particle list gives the true volume.
    ``blob_sigma`` [voxels per axis] sets σ; 0 takes the case's truth σ
    (:func:`lfstudy.study.case.truth_sigma`: half a resolution cell, one lenslet at the
    focal-plane magnification in x, y and the voxel depth of :func:`default_voxel_z` in z).

    Returns
    -------
    volume : ndarray (z, y, x), float64
    sigma : (σz, σy, σx) [mm]
    """
    if blob_sigma > 0:
        dz, dy, dx = grid.voxel_size()
        sig = (blob_sigma * dz, blob_sigma * dy, blob_sigma * dx)
    else:
        dxy = camera.lenslet_pitch / abs(camera.magnification)
        sig = (default_voxel_z(camera), dxy / 2.0, dxy / 2.0)
    return render_truth({"z": grid.z, "y": grid.y, "x": grid.x}, particles, sigma_mm=sig), sig


def ipr(
    inputs: ReconstructionInputs,
    settings: IPRSettings | None = None,
    *,
    blob_sigma: float = 0.0,
    progress: bool = False,
    **params: Any,
) -> xr.DataArray:
    """The ``ipr`` volume: :func:`~lfstudy.reconstruct.ipr.ipr_particles` rendered on the grid by
    :func:`render_particles`.

    ``settings``, ``progress`` and ``params`` as :func:`~lfstudy.reconstruct.ipr.ipr_particles`; ``blob_sigma``
    as :func:`render_particles`. The volume's attrs carry the particle list's (``n_particles``, ``candidates``,
    ``removed_ghosts``, ``residual_norm``, the calibrated grid) and ``blob_sigma_mm``.
    """
    parts = ipr_particles(inputs, settings, progress=progress, **params)
    return particle_volume(parts, inputs, blob_sigma)


def particle_volume(parts: xr.Dataset, inputs: ReconstructionInputs, blob_sigma: float = 0.0) -> xr.DataArray:
    """The volume on ``inputs.grid`` of a particle list (:func:`ipr_particles`), by :func:`render_particles`,
    with the list's attrs (``n_particles``, ``candidates``, ``removed_ghosts``, ``residual_norm``, the
    calibrated grid) and ``blob_sigma_mm``."""
    vol, sig = render_particles(parts, inputs.grid, inputs.camera, blob_sigma)
    attrs = {k: v for k, v in parts.attrs.items() if k != "method"}
    return inputs.grid.volume(
        vol.astype(np.float32),
        long_name="particle volume (IPR, exact camera model)",
        units=str(inputs.lightfield.attrs.get("units", "counts")),
        blob_sigma_mm=[float(v) for v in sig],
        **attrs,
    )


class IPR(ReconstructionMethod):
    """``ipr``: iterative particle reconstruction fitted with the exact camera model."""

    name = "ipr"
    description = "iterative particle reconstruction (Wieneke 2013) with shaking, fitted with the exact renderer"
    requires = ("lightfield", "centers", "camera", "grid")
    particles = True
    uses_calibration = True
    parameters: ClassVar[dict[str, dict[str, Any]]] = {**IPRSettings.schema(), "blob_sigma": _BLOB_SIGMA}

    @classmethod
    def memory_bytes(cls, size: ReconstructionSize, params: Mapping[str, Any] | None = None) -> float:
        """The base's arrays, the candidate MART's on the case grid refined ``_REFINE_XY`` x ``_REFINE_XY`` x
        ``_REFINE_Z`` (its weight tables: (kx + ky) ~ 17 float32 weights and 2 int16 starts per plane and
        light-field sample, 16.1 weights on the full Table 4.3 frame; the four subsets' float32 coverage; six
        float64 volumes: a MART volume's buffers and the peak search's copies) and three float64 copies of the
        raw frame the fit compares with. On the full Table 4.3 frame (33 planes) 7.16 GB with the process's
        0.3 GB, against the 7.18 GB peak ``benchmarks/bench_ipr.py --memory`` measured there (with its scene's
        0.48 GB), before the shake kept images between iterations. Those live through the MART rounds, so their
        bounds are added: the shake's image cache (``_CACHE_BYTES``, 256 MB) and the fit's two reused image
        buffers (``_SCRATCH_BYTES``: a shake batch of 64 particles' 7 images, ~0.15 GB on the full frame, with the
        buffer's 25 % headroom and the Gauss–Newton step's): 7.62 GB there, not measured."""
        nz = _REFINE_Z * size.n_planes
        nvox = _REFINE_XY * _REFINE_XY * _REFINE_Z * size.n_voxels
        tables = nz * size.n_lenslets * size.pixels_per_lenslet * (17 * 4 + 2 * 2)
        mart_part = tables + nvox * (4 * 4 + 6 * 8) + 3 * size.n_pixels * 8
        return super().memory_bytes(size, params) + mart_part + _CACHE_BYTES + _SCRATCH_BYTES

    @classmethod
    def seconds(cls, size: ReconstructionSize, params: Mapping[str, Any] | None = None) -> float:
        """``_SECONDS_PER_PARTICLE`` per seeded particle: the fit's time goes with the particles (their images, and
        the candidate volumes of a seeded field of that density)."""
        return _SECONDS_PER_PARTICLE * size.n_particles

    def run(
        self, inputs: ReconstructionInputs, *, blob_sigma: float = 0.0, progress: bool = False, **params: Any
    ) -> xr.DataArray:
        return ipr(inputs, IPRSettings.of(**params), blob_sigma=blob_sigma, progress=progress)

    # The parameters are IPRSettings' fields: run's signature names each with its default (set below), where
    # detect_parameters reads the defaults the config schema states, so they are stated once, in IPRSettings.
    run.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
        [
            inspect.Parameter("self", inspect.Parameter.POSITIONAL_OR_KEYWORD),
            inspect.Parameter("inputs", inspect.Parameter.POSITIONAL_OR_KEYWORD),
            *(
                inspect.Parameter(k, inspect.Parameter.KEYWORD_ONLY, default=v)
                for k, v in {**IPRSettings.defaults(), "blob_sigma": 0.0}.items()
            ),
            inspect.Parameter("progress", inspect.Parameter.KEYWORD_ONLY, default=False),
        ]
    )

    def run_particles(
        self, inputs: ReconstructionInputs, *, blob_sigma: float = 0.0, progress: bool = False, **params: Any
    ) -> tuple[xr.DataArray, xr.Dataset]:
        """The volume of :meth:`run` and the particle list (:func:`~lfstudy.reconstruct.ipr.ipr_particles`) it was
        rendered from, out of one fit; ``params`` as :meth:`run`'s."""
        parts = ipr_particles(inputs, IPRSettings.of(**params), progress=progress)
        return particle_volume(parts, inputs, blob_sigma), parts
