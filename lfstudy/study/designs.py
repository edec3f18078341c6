"""The study's answer: designs compared in physical units, their Pareto front and a recommendation.

A voxel is pitch/|M| across and a fraction of a refocus-plane spacing deep: it
differs between designs, so comparing errors in voxels favours coarse designs.
Everything here compares in millimetres and as a fraction of the true
displacement. A *design* is one case of the sweep but for its flow (camera,
seeding and processing settings); designs are compared flow by flow.

- :func:`design_table`: one row per computed case with the physical figures of
  merit (total RMS error in mm and relative, in-plane and depth resolution as
  vector spacing in mm, measured depth, field of view, valid vectors, Q).
- :func:`pareto_front`: the non-dominated rows for given objectives.
- :func:`recommend`: per flow, the Pareto set over the metric table's ``pareto``
  metrics (total error, in-plane and depth resolution) and one sentence naming
  the recommended design and what it trades away.
- :func:`influence`: which swept settings move a metric most.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
import xarray as xr

from lfstudy.study import metric_table as mt

__all__ = ["design_table", "pareto_front", "recommend", "influence", "design_label"]


def design_label(row: Mapping[str, object], dims: Sequence[str]) -> str:
    """A short label of a design: its swept values but the flow (``M=-1 fnum=matched pitch=0.125 ...``)."""
    short = {"magnification": "M", "fnumber": "f/#", "lenslet_pitch": "pitch", "ppp": "ppp"}
    parts = []
    for d in dims:
        if d == "flow":
            continue
        v = row[d]
        txt = f"{float(v):g}" if isinstance(v, (int, float, np.floating)) else str(v)
        parts.append(f"{short.get(d, d)}={txt}")
    return " ".join(parts)


def design_table(study: xr.Dataset) -> pd.DataFrame:
    """One row per computed case: the swept values, ``design`` (label), ``case_id`` and the
    physical figures of merit that the study holds (the metric table's ``front``, ``resolution``
    and ``pareto`` metrics)."""
    cols = [c for c in mt.names("front", "resolution", "pareto") if c in study]
    extra = [v for v in ("computed", "case_id") if v in study]
    if not cols:
        return pd.DataFrame()
    df = study[cols + extra].to_dataframe().reset_index()
    if "computed" in df:
        df = df[df["computed"].astype(bool)].drop(columns="computed")
    dims = [str(d) for d in study.dims]
    df.insert(0, "design", [design_label(r, dims) for _, r in df.iterrows()])
    return df.reset_index(drop=True)


def pareto_front(df: pd.DataFrame, objectives: Sequence[tuple[str, str]] | None = None) -> np.ndarray:
    """Boolean mask of the non-dominated rows.

    A row is dominated when another row is at least as good in every objective
    (``(column, "min" | "max")``; default the metric table's ``pareto`` metrics)
    and strictly better in one. Rows with a missing objective are never on the
    front (and dominate nothing).
    """
    objectives = mt.objectives() if objectives is None else objectives
    cols = [c for c, _ in objectives if c in df]
    if not cols or df.empty:
        return np.zeros(len(df), bool)
    vals = np.column_stack(
        [np.asarray(df[c], float) * (1.0 if sense == "min" else -1.0) for c, sense in objectives if c in df]
    )
    ok = np.isfinite(vals).all(axis=1)
    front = ok.copy()
    for i in np.flatnonzero(ok):
        others = vals[ok]
        dominated = np.any(np.all(others <= vals[i], axis=1) & np.any(others < vals[i], axis=1))
        front[i] = not dominated
    return front


def recommend(
    study: xr.Dataset, *, min_valid: float = 80.0, objectives: Sequence[tuple[str, str]] | None = None
) -> tuple[pd.DataFrame, dict[str, str]]:
    """Per flow: the designs on the Pareto front, and a sentence recommending one.

    The front is over ``objectives`` (default: the metric table's ``pareto`` metrics).

    The recommended design is the Pareto design with the lowest total RMS error
    in mm among those with at least ``min_valid`` % valid vectors (any Pareto
    design if none has). What it trades away: the in-plane and depth
    resolution of the finest-resolving Pareto design, against its error.

    Returns
    -------
    table : pandas.DataFrame
        The design table with ``pareto`` (bool) and ``recommended`` (bool) columns.
    sentences : dict flow -> str
    """
    df = design_table(study)
    if df.empty or "rms_total_mm" not in df:
        return df, {}
    df["pareto"] = False
    df["recommended"] = False
    sentences: dict[str, str] = {}
    flows = df["flow"].unique() if "flow" in df else [None]
    for flow in flows:
        sel = df["flow"] == flow if flow is not None else np.ones(len(df), bool)
        sub = df[sel]
        front = pareto_front(sub, objectives)
        df.loc[sub.index[front], "pareto"] = True
        cand = sub[front]
        if cand.empty:
            continue
        good = cand[cand["valid_percent"] >= min_valid] if "valid_percent" in cand else cand
        pick = (good if not good.empty else cand).sort_values("rms_total_mm").iloc[0]
        df.loc[pick.name, "recommended"] = True
        sentences[str(flow)] = _sentence(pick, cand, str(flow), min_valid, good.empty)
    return df, sentences


def _fmt(v: float, unit: str = "") -> str:
    if v is None or not np.isfinite(v):
        return "–"
    return f"{v:.3g}{(' ' + unit) if unit else ''}"


def _sentence(pick: pd.Series, cand: pd.DataFrame, flow: str, min_valid: float, none_valid: bool) -> str:
    rel = pick.get("rel_error", math.nan)
    s = (
        f"For the {flow} flow, build {pick['design']}: total RMS error {_fmt(pick['rms_total_mm'], 'mm')}"
        + (f" ({100 * rel:.3g} % of the displacement)" if np.isfinite(rel) else "")
        + f", vectors every {_fmt(pick.get('spacing_mm_x', math.nan), 'mm')} in x–y and "
        f"{_fmt(pick.get('spacing_mm_z', math.nan), 'mm')} in z"
        + (f", {pick['valid_percent']:.3g} % valid" if "valid_percent" in pick else "")
        + "."
    )
    # finest-resolving: by the table's resolution objectives, in table order (in-plane, then depth)
    finer = [m.name for m in mt.shown_in("pareto") if m.group == "resolution" and m.name in cand]
    finest = cand.sort_values(finer).iloc[0] if finer and "spacing_mm_x" in cand else None
    if finest is not None and finest.name != pick.name:
        s += (
            f" It trades away resolution: {finest['design']} resolves {_fmt(finest['spacing_mm_x'], 'mm')} in x–y "
            f"and {_fmt(finest['spacing_mm_z'], 'mm')} in z, at {_fmt(finest['rms_total_mm'], 'mm')} error."
        )
    elif len(cand) > 1:
        s += " It is also the finest-resolving design on the front: nothing is traded away."
    else:
        s += " It dominates every other design."
    if none_valid:
        s += f" No design on the front reaches {min_valid:g} % valid vectors: treat this study's answer with care."
    return s


def influence(study: xr.Dataset, var: str) -> list[tuple[str, float]]:
    """Swept dimensions ranked by how much they move ``var``: the range of its mean over the
    other dimensions (NaN-aware), largest first; flows are compared, not averaged."""
    if var not in study:
        return []
    da = study[var]
    out = []
    for d in da.dims:
        if d == "flow" or da.sizes[d] < 2:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            m = da.mean([x for x in da.dims if x not in (d, "flow")], skipna=True)
            rng = float((m.max(d) - m.min(d)).mean(skipna=True)) if "flow" in m.dims else float(m.max() - m.min())
        out.append((str(d), rng if np.isfinite(rng) else 0.0))
    return sorted(out, key=lambda kv: -kv[1])
