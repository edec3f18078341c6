"""Where the dask parts of one case run: the threaded scheduler or a ``dask.distributed`` client.

The ``compute`` config section chooses the scheduler of the stages whose work is
dask graphs (refocus: one task per plane; the reconstruction and PIV of dask-backed
volumes; every zarr write). It changes where the tasks run, never what they
compute: the graphs are the same, so results are bit-identical to the threaded
scheduler (tests/test_compute.py compares the bytes).

This module is the edge: the workflow's stage code and the CLI enter
:func:`dask_scheduler` around a stage; the science functions know nothing of it.

For a SLURM cluster, start the workers with ``dask-jobqueue`` (``SLURMCluster``) and
give its ``scheduler_address`` as ``compute.address`` (see the README).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Mapping
from typing import Any

__all__ = ["SCHEDULERS", "dask_scheduler", "describe"]

#: The allowed values of ``compute.scheduler``.
SCHEDULERS = ("threads", "distributed")


def describe(compute: Mapping[str, Any] | None) -> str:
    """One line saying where a stage's dask tasks run (for logs and the CLI)."""
    spec = dict(compute or {})
    if spec.get("scheduler", "threads") == "threads":
        return "dask threaded scheduler"
    if spec.get("address"):
        return f"dask.distributed scheduler at {spec['address']}"
    return (
        f"dask.distributed LocalCluster ({spec.get('n_workers') or 'auto'} workers x "
        f"{spec.get('threads_per_worker') or 1} threads)"
    )


@contextlib.contextmanager
def dask_scheduler(compute: Mapping[str, Any] | None, *, threads: int | None = None) -> Iterator[Any]:
    """Run the enclosed dask computations on the scheduler a ``compute`` section asks for.

    Parameters
    ----------
    compute : mapping or None
        The validated ``compute`` config section: ``scheduler`` (``threads`` or
        ``distributed``), ``address`` (a running scheduler, e.g. a dask-jobqueue
        ``SLURMCluster``; null starts a ``LocalCluster``), ``n_workers`` and
        ``threads_per_worker`` (LocalCluster only). None or ``threads``: nothing
        changes (the caller's threaded scheduler stays in force).
    threads : int, optional
        Cores this stage may use (Snakemake's ``threads``): a LocalCluster
        without ``n_workers`` starts ``threads // threads_per_worker`` workers
        (at least one). Default: the machine's CPU count.

    Yields
    ------
    distributed.Client or None
        The client (set as dask's default scheduler inside the block), or None
        for the threaded scheduler.

    Raises
    ------
    ValueError
        An unknown ``compute.scheduler``, or ``n_workers`` / ``threads_per_worker`` below 1.
    """
    spec = dict(compute or {})
    scheduler = spec.get("scheduler", "threads")
    if scheduler not in SCHEDULERS:
        raise ValueError(
            f"config key 'compute.scheduler' = {scheduler!r}: allowed values are "
            + ", ".join(repr(s) for s in SCHEDULERS)
        )
    if scheduler == "threads":
        yield None
        return
    from dask.distributed import Client, LocalCluster

    if spec.get("address"):
        with Client(spec["address"]) as client:
            yield client
        return
    per_worker = int(spec.get("threads_per_worker") or 1)
    n_workers = spec.get("n_workers")
    for key, value in (("threads_per_worker", per_worker), ("n_workers", n_workers)):
        if value is not None and int(value) < 1:
            raise ValueError(f"config key 'compute.{key}' = {value!r}: allowed range is [1, inf)")
    if n_workers is None:
        n_workers = max(1, int(threads or os.cpu_count() or 1) // per_worker)
    # processes=True: workers are separate interpreters, as on a real cluster (numba and numpy
    # release the GIL anyway); no dashboard (it needs bokeh and a free port); quiet logs.
    with (
        LocalCluster(
            n_workers=int(n_workers),
            threads_per_worker=per_worker,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client
