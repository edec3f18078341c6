"""Helpers the Snakefile calls: one function per rule, I/O at the edges.

Keeping rule bodies here (not in the Snakefile) makes them importable,
testable and usable from a notebook.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from lfstudy import io
from lfstudy.config import case_config
from lfstudy.optics import PlenopticCamera

__all__ = ["set_threads", "run_optics"]


def set_threads(n: int) -> None:
    """Honour Snakemake's ``threads:`` in numba and dask (they ignore OMP_NUM_THREADS)."""
    import dask
    import numba

    n = max(1, int(n))
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    dask.config.set(scheduler="threads", num_workers=n)


def run_optics(cfg: Mapping[str, Any], case_id: str, out_json: str | Path, out_planes: str | Path) -> None:
    """Camera stage: derived parameters (JSON) and the refocus-plane table (zarr)."""
    ccfg = case_config(cfg, case_id)
    cam = PlenopticCamera.from_config(ccfg)
    r = ccfg["refocus"]
    planes = cam.focal_planes(r["n_planes"], depth_scale=r["depth_scale"], cubic=r["cubic"])
    planes.attrs.update(io.provenance(ccfg, ccfg["seed"]))
    io.write_zarr(planes, out_planes)
    out_json = Path(out_json)
    with io.atomic_path(out_json) as tmp:
        tmp.write_text(json.dumps({"case_id": case_id, **{k: str(v) for k, v in cam.summary().items()}}, indent=2))
