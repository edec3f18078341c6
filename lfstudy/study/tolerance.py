"""Which tolerance matters (issue 29 §3): the study's errors against the imperfections it sweeps.

A swept setting under one of :data:`lfstudy.study.sweep.TOLERANCES` (``camera.imperfections.*``,
``illumination.*``, ``sensor.background.*`` ...) is a *tolerance*: something a real camera or
experiment has and the processing does not know, not a design choice. A *design* here is a point of
the other swept settings but the flow. Pure functions of the study Dataset
(:func:`lfstudy.study.table.combine_cases`):

- :func:`tolerance_dims`, :func:`ideal_levels`: which dimensions are tolerances and their ideal
  level (the schema default, the value every imperfection has in an ideal experiment);
- :func:`tolerance_table`: per design and flow, the error against the levels of one imperfection,
  the other imperfections at their ideal level, with the oracle's error beside it;
- :func:`at_ideal`, :func:`worst_case`: the study reduced to its designs, at the ideal camera or at
  each design's worst case (largest total RMS error in mm) over the tolerance sweep;
- :func:`limiting_tolerances`: per design, what each imperfection alone costs it over the ideal
  camera, and which one limits it.

Where the study has replicates (a swept ``seed``, :mod:`lfstudy.study.replicates`), the tables hold
the means over the seeds with their standard deviations, the worst level of a design is the one with
the largest mean, and a cost is the mean of the per-seed differences to the ideal camera (the levels
of one seed share their particles, rays and noise: common random numbers) with its standard error;
a cost below :data:`~lfstudy.study.replicates.SEPARATION` standard errors is *within noise*.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from lfstudy.study import metric_table as mt
from lfstudy.study.replicates import REPLICATE_DIM, replicate_dim, replicate_stats, separable
from lfstudy.study.sweep import format_value, tolerance_dims

__all__ = [
    "RANK_AT",
    "tolerance_dims",
    "ideal_levels",
    "tolerance_metrics",
    "tolerance_table",
    "at_ideal",
    "worst_case",
    "limiting_tolerances",
    "level_label",
    "level_text",
]

#: Where the recommendation ranks the designs (config ``report.rank_at``).
RANK_AT = ("ideal", "tolerances")
#: The metric designs are ranked by at their worst case (largest is worst).
WORST_BY = "rms_total_mm"


def _path(study: xr.Dataset, dim: str) -> str:
    """The config path of a study dimension: its ``sweep_key`` attribute (the dotted path)."""
    return str(study[dim].attrs.get("sweep_key", dim))


def _schema_default(path: str) -> Any:
    from lfstudy.study.schema import load_schema

    node: Any = load_schema()
    for part in path.split("."):
        node = node.get("properties", {}).get(part) if isinstance(node, Mapping) else None
        if node is None:
            return None
    return node.get("default") if isinstance(node, Mapping) else None


def ideal_levels(study: xr.Dataset, dims: Sequence[str] | None = None) -> dict[str, Any]:
    """Per tolerance dimension, its ideal level: the schema default of the setting (every
    imperfection defaults to ideal) where the sweep lists it, else the first level swept."""
    out: dict[str, Any] = {}
    for d in tolerance_dims(study) if dims is None else dims:
        levels = study[d].values.tolist()
        default = _schema_default(_path(study, d))
        match = [v for v in levels if format_value(v) == format_value(default)] if default is not None else []
        if not match and isinstance(default, (int, float)) and not isinstance(default, bool):
            match = [v for v in levels if isinstance(v, (int, float)) and math.isclose(v, default, abs_tol=1e-15)]
        out[d] = match[0] if match else levels[0]
    return out


def level_label(study: xr.Dataset, dim: str) -> str:
    """A tolerance dimension's label with its units (the schema's ``title`` and ``units``)."""
    c = study[dim]
    name = str(c.attrs.get("long_name", dim))
    units = str(c.attrs.get("units", ""))
    return f"{name} [{units}]" if units and units != "1" else name


def level_text(study: xr.Dataset, dim: str, level: Any) -> str:
    """One level of a tolerance in words, with its units: ``lenslet grid rotation error 3 mrad``."""
    c = study[dim]
    units = str(c.attrs.get("units", ""))
    value = format_value(level.item() if hasattr(level, "item") else level)
    return f"{c.attrs.get('long_name', dim)} {value}" + (f" {units}" if units and units != "1" else "")


def tolerance_metrics(study: xr.Dataset) -> list[str]:
    """The metric table's ``tolerance`` metrics the study holds: the total error first, then the
    components and the other figures (valid vectors)."""
    ms = [m for m in mt.shown_in("tolerance") if m.name in study]
    return [m.name for m in sorted(ms, key=lambda m: (m.group != "error", m.name))]


def _design_dims(study: xr.Dataset) -> list[str]:
    tol = set(tolerance_dims(study))
    return [str(d) for d in study.dims if d not in ("flow", REPLICATE_DIM) and str(d) not in tol]


def _label(row: Mapping[str, Any], dims: Sequence[str]) -> str:
    from lfstudy.study.designs import design_label

    return design_label(row, dims) or "the design"


def tolerance_table(study: xr.Dataset, dim: str) -> pd.DataFrame:
    """Per design and flow, the error against the levels of the imperfection ``dim``, every other
    tolerance at its ideal level (:func:`ideal_levels`).

    Returns
    -------
    pandas.DataFrame
        Columns ``design``, ``flow`` (where the study has one), the level (named by
        :func:`level_label`), then each :func:`tolerance_metrics` metric followed by its oracle
        (``oracle_<name>``) where the study holds it. Only computed cases; empty if none. With
        replicates: the means over the seeds, each metric followed by its standard deviation
        (``<name>_sd``).
    """
    if replicate_dim(study) is not None:
        stats = replicate_stats(study)
        mean, sd = tolerance_table(stats.mean, dim), tolerance_table(stats.sd, dim)
        if mean.empty:
            return mean
        keep = []
        for c in mean.columns:
            keep.append(c)
            if c in tolerance_metrics(study):
                mean[f"{c}_sd"] = sd[c].to_numpy()
                keep.append(f"{c}_sd")
        return mean[keep]
    others = {d: v for d, v in ideal_levels(study).items() if d != dim}
    sub = study.sel(others) if others else study
    cols: list[str] = []
    for m in tolerance_metrics(study):
        cols += [m] + ([f"oracle_{m}"] if f"oracle_{m}" in study else [])
    if not cols:
        return pd.DataFrame()
    extra = [v for v in ("computed",) if v in sub]
    df = sub[cols + extra].to_dataframe().reset_index()
    if "computed" in df:
        df = df[df["computed"].astype(bool)].drop(columns="computed")
    if df.empty:
        return pd.DataFrame()
    dims = _design_dims(study)
    df.insert(0, "design", [_label(r, dims) for _, r in df.iterrows()])
    level = level_label(study, dim)
    df = df.rename(columns={dim: level})
    keep = ["design", *(["flow"] if "flow" in df else []), level, *cols]
    return df[keep].reset_index(drop=True)


def at_ideal(study: xr.Dataset) -> xr.Dataset:
    """The study at the ideal camera: every swept imperfection at its ideal level (dimension dropped)."""
    levels = ideal_levels(study)
    return study.sel(levels) if levels else study


def worst_case(study: xr.Dataset, by: str = WORST_BY) -> xr.Dataset:
    """Each design (and flow) at its worst case over the tolerance sweep: the computed case with the
    largest ``by`` (default the total RMS error in mm) among its tolerance levels.

    Every variable of a design is that case's, so its resolution and valid vectors stay those of the
    case whose error is reported. The tolerance dimensions are dropped; ``worst_<dim>`` holds the
    level of the worst case (a string, as the case id writes it) and ``tolerance_cases`` how many
    computed cases of the design it was chosen from. A study without swept imperfections is
    returned as is. With replicates the worst level is the one with the largest mean over the
    seeds, and every seed keeps its case at that level.
    """
    tol = tolerance_dims(study)
    if not tol:
        return study
    if by not in study:
        raise KeyError(f"worst case over the tolerances: the study has no {by!r}")
    stacked = study.stack(_tol=tol)
    ok = stacked["computed"].astype(bool) if "computed" in stacked else xr.ones_like(stacked[by], dtype=bool)
    rep = replicate_dim(study)
    if rep is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = stacked[by].where(ok).mean(rep, skipna=True)
        score = mean.where(mean.notnull(), -np.inf)
    else:
        score = stacked[by].where(ok & stacked[by].notnull(), -np.inf)
    idx = score.argmax("_tol")
    worst = stacked.isel(_tol=idx)
    levels = {d: (worst[d].dims, worst[d].values) for d in tol}
    worst = worst.drop_vars(["_tol", *tol], errors="ignore")
    for d in tol:
        worst[f"worst_{d}"] = (
            levels[d][0],
            np.vectorize(lambda v: format_value(v.item() if hasattr(v, "item") else v), otypes=[object])(levels[d][1]),
            {"long_name": f"level of the worst case: {study[d].attrs.get('long_name', d)}"},
        )
    n = ok.sum("_tol")
    worst["tolerance_cases"] = n.assign_attrs(units="1", long_name="computed cases over the tolerance sweep")
    if "computed" in worst:
        worst["computed"] = worst["computed"] & (n > 0)
    worst.attrs = dict(study.attrs)
    return worst


def limiting_tolerances(study: xr.Dataset, by: str = WORST_BY) -> pd.DataFrame:
    """Per design and flow: what each swept imperfection alone costs over the ideal camera, and
    which one limits the design.

    The cost of an imperfection is the largest ``by`` over its levels (the other imperfections
    ideal) minus ``by`` at the ideal camera. Columns: ``design``, ``flow``, ``ideal <by>``, one
    ``+<label>`` column per imperfection (its cost), ``worst <by>`` (over the whole tolerance
    sweep, combinations included) and ``limited_by`` (the costliest imperfection with its worst
    level, or "nothing" when no imperfection raises the error). Empty without swept imperfections.

    With replicates (:mod:`lfstudy.study.replicates`) the cost of an imperfection at a level is the
    mean over the seeds of the paired difference to the ideal camera; its worst level is the one of
    the largest mean cost. ``ideal <by>`` and ``worst <by>`` are means with their standard deviation
    (``_sd``), each cost has its standard error (``+<label> s.e.``) and whether it is beyond noise
    (``+<label> beyond noise``: at least :data:`~lfstudy.study.replicates.SEPARATION` standard errors
    above 0); ``limited_by`` is the costliest imperfection beyond noise, or "nothing beyond noise".
    """
    tol = tolerance_dims(study)
    if not tol or by not in study:
        return pd.DataFrame()
    rep = replicate_dim(study)
    if rep is not None:
        return _limiting_replicates(study, by, rep)
    ideal = ideal_levels(study)
    base = at_ideal(study)
    worst = worst_case(study, by)
    design = _design_dims(study)
    df = base[[by]].to_dataframe()[[by]].rename(columns={by: f"ideal {by}"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for d in tol:
            others = {k: v for k, v in ideal.items() if k != d}
            alone = study[by].sel(others) if others else study[by]
            peak = alone.max(d, skipna=True)
            at = alone.fillna(-np.inf).argmax(d)
            df[f"+{level_label(study, d)}"] = (peak - base[by]).to_dataframe(name="c")["c"]
            df[f"_level_{d}"] = (
                xr.DataArray(np.asarray(study[d].values)[at.values], dims=at.dims, coords=at.coords)
                .to_dataframe(name="c")["c"]
                .map(lambda v: format_value(v.item() if hasattr(v, "item") else v))
            )
    df[f"worst {by}"] = worst[by].to_dataframe()[by]
    df = df.reset_index()
    if "computed" in base:
        comp = base["computed"].to_dataframe().reset_index()["computed"].astype(bool)
        df = df[comp.to_numpy()]
    costs = [f"+{level_label(study, d)}" for d in tol]
    limited = []
    for _, r in df.iterrows():
        vals = np.asarray([r[c] for c in costs], float)
        if not np.isfinite(vals).any() or np.nanmax(vals) <= 0:
            limited.append("nothing" if np.isfinite(vals).any() else "")
            continue
        k = int(np.nanargmax(vals))
        limited.append(level_text(study, tol[k], r[f"_level_{tol[k]}"]))
    df["limited_by"] = limited
    df.insert(0, "design", [_label(r, design) for _, r in df.iterrows()])
    keep = ["design", *(["flow"] if "flow" in df else []), f"ideal {by}", *costs, f"worst {by}", "limited_by"]
    return df[keep].reset_index(drop=True)


def _limiting_replicates(study: xr.Dataset, by: str, rep: str) -> pd.DataFrame:
    """:func:`limiting_tolerances` of a study with replicates: costs paired seed by seed."""
    tol = tolerance_dims(study)
    ideal = ideal_levels(study)
    val = study[by].where(study["computed"].astype(bool)) if "computed" in study else study[by]
    base = val.sel(ideal)
    stats = replicate_stats(study)
    mean_base, sd_base = at_ideal(stats.mean), at_ideal(stats.sd)
    worst = replicate_stats(worst_case(study, by), rep)
    order = mean_base[by].dims

    def column(da: xr.DataArray) -> pd.Series:
        return da.transpose(*order).to_dataframe(name="c")["c"]

    df = pd.DataFrame({f"ideal {by}": column(mean_base[by]), f"ideal {by}_sd": column(sd_base[by])})
    costs = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for d in tol:
            others = {k: v for k, v in ideal.items() if k != d}
            diff = (val.sel(others) if others else val) - base  # paired: the same seed at both levels
            n = diff.count(rep)
            mean_cost = diff.mean(rep, skipna=True)
            se = diff.std(rep, ddof=1, skipna=True) / np.sqrt(n.where(n > 0))
            at = mean_cost.fillna(-np.inf).argmax(d)
            col = f"+{level_label(study, d)}"
            costs.append(col)
            df[col] = column(mean_cost.isel({d: at}, drop=True))
            df[f"{col} s.e."] = column(se.isel({d: at}, drop=True))
            df[f"_level_{d}"] = column(
                xr.DataArray(np.asarray(study[d].values)[at.values], dims=at.dims, coords=at.coords)
            ).map(lambda v: format_value(v.item() if hasattr(v, "item") else v))
    df[f"worst {by}"] = column(worst.mean[by])
    df[f"worst {by}_sd"] = column(worst.sd[by])
    df = df.reset_index()
    if "computed" in mean_base:
        df = df[column(mean_base["computed"]).astype(bool).to_numpy()]
    for col in costs:
        df[f"{col} beyond noise"] = [bool(c > 0 and separable(c, e)) for c, e in zip(df[col], df[f"{col} s.e."])]
    limited = []
    for _, r in df.iterrows():
        best, label = -np.inf, "nothing beyond noise"
        for col, d in zip(costs, tol):
            if r[f"{col} beyond noise"] and r[col] > best:
                best, label = r[col], level_text(study, d, r[f"_level_{d}"])
        limited.append(label if np.isfinite(np.asarray([r[c] for c in costs], float)).any() else "")
    df["limited_by"] = limited
    df.insert(0, "design", [_label(r, _design_dims(study)) for _, r in df.iterrows()])
    spread = [x for c in costs for x in (c, f"{c} s.e.", f"{c} beyond noise")]
    keep = ["design", *(["flow"] if "flow" in df else []), f"ideal {by}", f"ideal {by}_sd", *spread]
    keep += [f"worst {by}", f"worst {by}_sd", "limited_by"]
    return df[keep].reset_index(drop=True)
