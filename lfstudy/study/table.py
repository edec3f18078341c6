"""The study table: every case's scalar results in one Dataset over the swept settings.

:func:`combine_cases` builds it (dimensions = the sweep's settings, so
``study.sel(ppp=0.001)`` or ``study.sel(reconstruct_method="mart")`` work),
:func:`to_csv` / :func:`from_csv` write and read its flat form, and
:func:`stage_times` reads the run time of every stage of a case from the
Snakemake benchmark tables. File I/O lives here; the per-case statistics are
in :mod:`lfstudy.study.metrics`.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from lfstudy.study import metric_table
from lfstudy.study.sweep import NAMED, Case, Setting, format_value

__all__ = ["study_value", "combine_cases", "to_csv", "from_csv", "stage_times"]


def study_value(value: Any) -> float | str:
    """A swept value as a study coordinate: a float for numbers, else its case-id text."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)):
        return float(value)
    return format_value(value)


def _column(values: list[Any]) -> tuple[list[Any], np.ndarray]:
    """Coordinate value of each case and the sorted coordinate of one setting.

    Numbers stay numbers (ascending); a setting with any text value (a sweep
    mixing 'matched' and f-numbers, method names, windows) is text in the
    order met. Object strings: zarr v3 stores them as vlen-utf8 ('<U' has no
    v3 spec yet).
    """
    numeric = all(isinstance(study_value(v), float) for v in values)
    conv = [float(v) if numeric else format_value(v) for v in values]
    coord = sorted(set(conv)) if numeric else list(dict.fromkeys(conv))
    return conv, np.asarray(coord, dtype=float if numeric else object)


def combine_cases(
    per_case: Iterable[tuple[Case | Mapping[str, Any], xr.Dataset]],
    settings: Sequence[Setting] | None = None,
) -> xr.Dataset:
    """One Dataset whose dimensions are the swept settings.

    Parameters
    ----------
    per_case : iterable of (case, scalars)
        ``case``: a :class:`~lfstudy.study.sweep.Case` (or a mapping of its
        values by setting key); ``scalars``: a Dataset of 0-d variables (the
        scalars of :func:`lfstudy.study.metrics.case_errors`, ``Q``,
        ``time_<stage>``). Non-scalar and non-numeric variables are ignored.
    settings : sequence of Setting, optional
        The sweep's settings (:attr:`Sweep.settings`); default the five named parameters.

    Returns
    -------
    xarray.Dataset
        One dimension per setting (named :attr:`Setting.dim`, with units and a
        long name), one float variable per scalar (NaN where not computed),
        ``computed`` (bool) and ``case_id`` (text) per case. A metric's attrs come
        from the metric table (:mod:`lfstudy.study.metric_table`), another
        variable's from the first case that has it; the table's ``summary``
        metrics come first.
    """
    settings = list(settings) if settings is not None else list(NAMED.values())
    rows = []
    for case, scalars in per_case:
        params = case.params if isinstance(case, Case) else dict(case)
        cid = case.case_id if isinstance(case, Case) else ""
        rows.append(({s.key: params[s.key] for s in settings}, scalars, cid))
    coords: dict[str, np.ndarray] = {}
    at_of: list[list[int]] = [[] for _ in rows]
    for s in settings:
        conv, coords[s.key] = _column([r[0][s.key] for r in rows])
        index = {v: i for i, v in enumerate(coords[s.key].tolist())}
        for k, v in enumerate(conv):
            at_of[k].append(index[v])
    shape = tuple(len(coords[s.key]) for s in settings)
    dims = tuple(s.dim for s in settings)
    data: dict[str, np.ndarray] = {}
    attrs: dict[str, dict[str, Any]] = {}
    computed = np.zeros(shape, bool)
    ids = np.full(shape, "", dtype=object)
    for (_, scalars, cid), at_list in zip(rows, at_of):
        at = tuple(at_list)
        computed[at] = True
        ids[at] = cid
        for name, var in scalars.data_vars.items():
            if var.ndim != 0 or var.dtype.kind not in "biuf":
                continue
            if name not in data:
                data[name] = np.full(shape, np.nan)
                attrs[name] = dict(var.attrs)
            data[name][at] = float(var.values)
    lead = metric_table.names("summary")
    order = [m for m in lead if m in data] + sorted(n for n in data if n not in lead)
    known = {m.name: m.attrs for m in metric_table.METRICS}
    ds = xr.Dataset(
        {n: (dims, data[n], known.get(n, attrs[n])) for n in order},
        coords={
            s.dim: (s.dim, coords[s.key], {"units": s.units, "long_name": s.label, "sweep_key": s.key})
            for s in settings
        },
    )
    ds["computed"] = (dims, computed, {"units": "1", "long_name": "case computed"})
    ds["case_id"] = (dims, ids, {"units": "1", "long_name": "case id (results sub-path)"})
    ds.attrs["title"] = "light-field PIV parametric study: results per case"
    return ds


def to_csv(study: xr.Dataset, path: str | Path) -> Path:
    """Write the study as a flat table, one row per computed case.

    Columns: ``case_id``, the swept settings, then every variable. Units stay in
    the zarr store (variable attrs); the table reads back with :func:`from_csv`
    or ``pandas.read_csv``.
    """
    from lfstudy.io import atomic_path

    df = study.to_dataframe().reset_index()
    if "computed" in df:
        df = df[df["computed"].astype(bool)].drop(columns="computed")
    cols = ["case_id", *study.dims, *[c for c in df.columns if c not in ("case_id", *study.dims)]]
    path = Path(path)
    with atomic_path(path) as tmp:
        df[cols].to_csv(tmp, index=False)
    return path


_SHORT_TO_KEY = {s.short: s.key for s in NAMED.values()}


def from_csv(path: str | Path) -> xr.Dataset:
    """Read a table written by :func:`to_csv` back into a study Dataset (units of the metric table's metrics).

    The swept settings are the segments of the case ids (``mag~-1/.../reconstruct.method~mart``).
    """
    import pandas as pd

    df = pd.read_csv(path, dtype=str, keep_default_na=False)
    if df.empty:
        raise ValueError(f"study table {str(path)!r} has no case")
    keys = [_SHORT_TO_KEY.get(seg.split("~", 1)[0], seg.split("~", 1)[0]) for seg in df["case_id"].iloc[0].split("/")]
    settings = [NAMED[k] if k in NAMED else Setting(k, k, k, k, "") for k in keys]
    dims = {s.key: s.dim for s in settings}
    rows = []
    for _, r in df.iterrows():
        params = {}
        for k in keys:
            v = r[dims[k]]
            try:
                params[k] = float(v)
            except ValueError:
                params[k] = v
        vals = {
            c: ((), float(r[c]) if r[c] != "" else np.nan)
            for c in df.columns
            if c not in dims.values() and c != "case_id"
        }
        rows.append((params, xr.Dataset(vals)))
    ds = combine_cases(rows, settings)
    ids = {}
    for _, r in df.iterrows():
        ids[tuple(r[dims[k]] for k in keys)] = r["case_id"]
    flat = ds["case_id"].values
    for idx in np.ndindex(flat.shape):
        key = tuple(format_value(ds[s.dim].values[i]) for s, i in zip(settings, idx))
        flat[idx] = ids.get(key, "")
    return ds


def stage_times(benchmark_dir: str | Path, ids: Mapping[str, str]) -> dict[str, float]:
    """Wall-clock seconds of every workflow stage of one case, from Snakemake benchmark tables.

    Parameters
    ----------
    benchmark_dir : path
        ``results/<name>/benchmarks``, holding ``<rule>/<id>.tsv`` and, for the
        per-frame rules, ``<rule>/<id>_<f>.tsv`` (summed).
    ids : mapping stage -> id
        Where each stage of the case wrote (its stage id or calibration id,
        :meth:`lfstudy.study.sweep.Sweep.ids`): a stage shared by several cases
        counts in each of them. Repeated benchmark runs (several rows) are
        averaged. Where frame a has a stage of its own (``simulate_a`` ...,
        :data:`lfstudy.study.sweep.FRAME_STAGES`: the first exposure, shared by
        the flows) its table ``<rule>/<its id>_a.tsv`` counts under the rule,
        and the plain stage's id counts frame b's alone.

    Returns
    -------
    dict
        ``{rule: seconds}`` plus ``"total"`` (sum); empty if nothing is found.
    """
    import pandas as pd

    from lfstudy.study.sweep import first_exposure_of

    root = Path(benchmark_dir)
    out: dict[str, float] = {}
    if not root.is_dir():
        return out
    for stage, sid in ids.items():
        rule, frames = stage, "(_[a-z])?"
        if first_exposure_of(stage):
            rule, frames = first_exposure_of(stage), "_a"
        elif f"{stage}_a" in ids:
            frames = "_b"
        d = root / rule / Path(sid).parent
        if not d.is_dir():
            continue
        pat = re.compile(rf"^{re.escape(Path(sid).name)}{frames}\.tsv$")
        total, found = 0.0, False
        for f in sorted(d.iterdir()):
            if not pat.match(f.name):
                continue
            try:
                s = pd.read_csv(f, sep="\t")["s"].astype(float)
            except (KeyError, ValueError, pd.errors.ParserError, pd.errors.EmptyDataError):
                continue
            if len(s):
                total += float(s.mean())
                found = True
        if found:
            out[rule] = out.get(rule, 0.0) + total
    if out:
        out["total"] = float(sum(out.values()))
    return out
