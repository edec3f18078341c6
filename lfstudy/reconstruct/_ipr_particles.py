"""The ``ipr`` method with its particle list: :class:`lfstudy.reconstruct.ipr.IPR` plus ``run_particles``.

The workflow and ``lfstudy process`` write the particle list an IPR volume is rendered from
beside the volume, out of one fit. ``run_particles`` is :func:`lfstudy.reconstruct.ipr.ipr`
with the list kept (the tests check both give the same volume); it moves into ``IPR`` itself,
and the registry's ``BUILTIN["ipr"]`` back to ``lfstudy.reconstruct.ipr:IPR``, once that
module is free to change.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import xarray as xr

from lfstudy.reconstruct import ipr as _ipr
from lfstudy.reconstruct.registry import ReconstructionInputs

__all__ = ["IPR"]


class IPR(_ipr.IPR):
    """``ipr``: iterative particle reconstruction fitted with the exact camera model."""

    particles = True

    def run_particles(
        self, inputs: ReconstructionInputs, *, blob_sigma: float = 0.0, progress: bool = False, **params: Any
    ) -> tuple[xr.DataArray, xr.Dataset]:
        """The volume of :meth:`run` and the particle list (:func:`~lfstudy.reconstruct.ipr.ipr_particles`)
        it was rendered from; ``params`` as :meth:`run`'s."""
        parts = _ipr.ipr_particles(inputs, progress=progress, **params)
        vol, sig = _ipr.render_particles(parts, inputs.grid, inputs.camera, blob_sigma)
        attrs = {k: v for k, v in parts.attrs.items() if k != "method"}
        volume = inputs.grid.volume(
            vol.astype(np.float32),
            long_name="particle volume (IPR, exact camera model)",
            units=str(inputs.lightfield.attrs.get("units", "counts")),
            blob_sigma_mm=[float(v) for v in sig],
            **attrs,
        )
        return volume, parts
