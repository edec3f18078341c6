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
from lfstudy.study.sweep import format_value, is_tolerance

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


def tolerance_dims(study: xr.Dataset) -> list[str]:
    """The study's dimensions that sweep an imperfection (:data:`~lfstudy.study.sweep.TOLERANCES`)
    over two or more levels, in the study's order."""
    return [str(d) for d in study.dims if study.sizes[d] > 1 and is_tolerance(_path(study, str(d)))]


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
    return [str(d) for d in study.dims if d != "flow" and str(d) not in tol]


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
        (``oracle_<name>``) where the study holds it. Only computed cases; empty if none.
    """
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
    returned as is.
    """
    tol = tolerance_dims(study)
    if not tol:
        return study
    if by not in study:
        raise KeyError(f"worst case over the tolerances: the study has no {by!r}")
    stacked = study.stack(_tol=tol)
    ok = stacked["computed"].astype(bool) if "computed" in stacked else xr.ones_like(stacked[by], dtype=bool)
    score = stacked[by].where(ok & stacked[by].notnull(), -np.inf)
    idx = score.argmax("_tol")
    worst = stacked.isel(_tol=idx)
    levels = {d: worst[d].values for d in tol}
    worst = worst.drop_vars(["_tol", *tol], errors="ignore")
    for d in tol:
        worst[f"worst_{d}"] = (
            worst[by].dims,
            np.vectorize(lambda v: format_value(v.item() if hasattr(v, "item") else v), otypes=[object])(levels[d]),
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
    """
    tol = tolerance_dims(study)
    if not tol or by not in study:
        return pd.DataFrame()
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
