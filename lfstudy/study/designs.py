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
  the recommended design, what it trades away and what limits its error.
- :func:`error_limit`, :func:`budget_table`: per design, the error in three parts:
  the PIV windows' filtering of the flow, what the reconstruction adds beyond the
  oracle (the case's PIV on the true particle volumes) and the rest of the oracle's
  error (random, plus the estimator's bias), and which of the three limits it.
- :func:`design_names`: one readable name per design, with units ("M −1, f/2.0, 88.8 µm lenslets").
- :func:`summary_table`, :func:`flow_verdict`: per flow, one compact row per design (error, oracle, the
  reconstruction's share, dominant component, limiting stage) and the verdict in words.
- :func:`influence`: which swept settings move a metric most.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
import xarray as xr

from lfstudy.study import metric_table as mt
from lfstudy.study.replicates import (
    REPLICATE_DIM,
    SEPARATION,
    paired_difference,
    replicate_dim,
    replicate_stats,
    separable,
)

__all__ = [
    "design_table",
    "design_values",
    "pareto_front",
    "recommend",
    "influence",
    "design_label",
    "error_limit",
    "budget_table",
    "focus_limited",
    "density_limited",
    "spread_columns",
    "design_names",
    "readable_design",
    "limiting_stage",
    "reconstruction_cut",
    "summary_table",
    "flow_verdict",
    "method_comparison",
]

#: The total error designs are ranked by (mm).
TOTAL = "rms_total_mm"
#: The error budget (rows of the metric table): the oracle's total error, the reconstruction's share, the windows'
#: filtering of the truth and the oracle's error beyond it (case² = filter² + recon_added² + rest²).
ORACLE_TOTAL = "oracle_rms_total_mm"
ADDED_TOTAL = "recon_added_rms_total_mm"
FILTER_TOTAL = "filter_rms_total_mm"
REST_TOTAL = "rest_rms_total_mm"
#: The budget's signed metrics (no better end: the crosstalk): whether they differ from 0 is the finding
#: (issue 27), so with replicates they are shown with their standard error.
SIGNED = tuple(m.name for m in mt.shown_in("budget") if m.lower_is_better is None)
#: Labels of what limits a design's error (:func:`error_limit`).
LIMITS = {
    "reconstruction": "the reconstruction",
    "windows": "the PIV windows",
    "random": "the random error (and the estimator's bias)",
}


def design_label(row: Mapping[str, object], dims: Sequence[str]) -> str:
    """A short label of a design: its swept values but the flow and the replicate seed
    (``M=-1 fnum=matched pitch=0.125 ...``)."""
    short = {"magnification": "M", "fnumber": "f/#", "lenslet_pitch": "pitch", "ppp": "ppp"}
    parts = []
    for d in dims:
        if d in ("flow", REPLICATE_DIM):
            continue
        v = row[d]
        txt = f"{float(v):g}" if isinstance(v, (int, float, np.floating)) else str(v)
        parts.append(f"{short.get(d, d)}={txt}")
    return " ".join(parts)


#: The swept settings a readable design name spells as the camera ("M −1, f/2.0, 88.8 µm lenslets").
_CAMERA_DIMS = ("magnification", "fnumber", "lenslet_pitch")


def _minus(text: str) -> str:
    """A number as set in prose: a true minus sign, not a hyphen."""
    return text.replace("-", "\N{MINUS SIGN}")


def _fnumber_text(n: object) -> str:
    try:
        v = float(n)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return "matched f-number" if str(n) == "matched" else f"f-number {n}"
    return f"f/{v:.1f}" if v < 10 else f"f/{v:.0f}"


def _setting_text(study: xr.Dataset | None, dim: str, value: object) -> str:
    """One swept setting's value in words, named by its long name and units ("depth calibration on",
    "seeding density 0.005")."""
    from lfstudy.study.sweep import format_value

    attrs = study[dim].attrs if study is not None and dim in study.coords else {}
    name = str(attrs.get("long_name", dim))
    if isinstance(value, (bool, np.bool_)) or str(value) in ("True", "False", "true", "false"):
        on = str(value) in ("True", "true")
        return f"{name.removesuffix('.enabled').replace('_', ' ').replace('.', ' ')} {'on' if on else 'off'}"
    v = value.item() if hasattr(value, "item") else value
    units = str(attrs.get("units", ""))
    name = name.split(" (")[0]  # "seeding density (particles per sensor pixel)": the short name
    return f"{name} {_minus(format_value(v))}" + (f" {units}" if units not in ("", "1") else "")


def readable_design(
    values: Mapping[str, object], camera: object | None = None, *, study: xr.Dataset | None = None
) -> str:
    """One readable name of a design, with units: its camera as "M −1, f/2.0, 88.8 µm lenslets", then
    every other swept setting in ``values`` but the flow and the replicate seed.

    Parameters
    ----------
    values : mapping dim -> value
        The design's swept values (the settings that take two or more values, and any camera setting).
    camera : PlenopticCamera, optional
        The design's camera: its magnification, main-lens f-number (a matched one resolved to the stop in
        use) and lenslet pitch. Without it they come from ``values``.
    study : xarray.Dataset, optional
        Supplies the settings' long names and units.
    """
    m = getattr(camera, "magnification", values.get("magnification"))
    fn = getattr(camera, "main_fnumber", values.get("fnumber"))
    pl = getattr(camera, "lenslet_pitch", values.get("lenslet_pitch"))
    parts = []
    if m is not None:
        parts.append(f"M {_minus(f'{float(m):g}')}")  # type: ignore[arg-type]
    if fn is not None:
        parts.append(_fnumber_text(fn))
    if pl is not None:
        parts.append(f"{1000 * float(pl):.3g} µm lenslets")  # type: ignore[arg-type]
    for d, v in values.items():
        if d in _CAMERA_DIMS or d in ("flow", REPLICATE_DIM):
            continue
        parts.append(_setting_text(study, d, v))
    return ", ".join(parts)


#: Where the swept camera settings live in a config's ``camera`` section.
_CAMERA_PATHS = {"magnification": ("magnification",), "fnumber": ("main_lens", "fnumber"),
                 "lenslet_pitch": ("lenslet", "pitch")}  # fmt: skip


def _camera_of(cfg: Mapping[str, object], row: Mapping[str, object]) -> object | None:
    """The config's camera with the row's swept camera values set (None where it cannot be built)."""
    import copy

    from lfstudy.optics import PlenopticCamera

    cam = copy.deepcopy(dict(cfg.get("camera") or {}))  # type: ignore[call-overload]
    for dim, path in _CAMERA_PATHS.items():
        if dim not in row:
            continue
        v = row[dim]
        with contextlib.suppress(TypeError, ValueError):
            v = float(v)  # type: ignore[arg-type]
        node = cam
        for k in path[:-1]:
            node = node.setdefault(k, {})
        node[path[-1]] = v
    try:
        return PlenopticCamera.from_config({**cfg, "camera": cam})
    except Exception:
        return None


def design_names(study: xr.Dataset, cfg: Mapping[str, object] | None = None) -> dict[str, str]:
    """Every design's readable name (:func:`readable_design`) by its :func:`design_label`.

    The camera of each design comes from its first computed case's config (``cfg``: the validated
    study config), so a matched f-number reads as the stop in use; without ``cfg`` (or where a case's
    camera cannot be built) the swept values name it. Where the study sweeps imperfections, a design is
    keyed both by its label over the design settings (the tolerance tables', a study ranked at the ideal
    camera or the worst case) and over every setting (a row per level: the name then ends with the levels).
    A name shared by two designs falls back to their labels (a design is never renamed into another)."""
    from lfstudy.optics import PlenopticCamera
    from lfstudy.study.config import case_config
    from lfstudy.study.sweep import tolerance_dims

    extra = [v for v in ("computed", "case_id") if v in study]
    if not study.dims or not extra:
        return {}
    dims = [str(d) for d in study.dims]
    tol = set(tolerance_dims(study))
    design_dims = [d for d in dims if d not in tol]
    varied = [d for d in design_dims if study.sizes[d] > 1 or d in _CAMERA_DIMS]
    df = study[extra].to_dataframe().reset_index()
    if "computed" in df:
        df = df[df["computed"].astype(bool)]
    keyings: list[dict[str, str]] = [{}, {}]
    cams: dict[str, object] = {}
    for _, r in df.iterrows():
        short = design_label(r, design_dims)
        if short not in cams:
            cam = None
            if cfg:
                try:
                    cam = PlenopticCamera.from_config(case_config(cfg, str(r["case_id"])))
                except Exception:  # a case outside the config's sweep: its camera values on the config's camera
                    cam = _camera_of(cfg, r)
            cams[short] = cam
        name = readable_design({d: r[d] for d in varied}, cams[short], study=study)
        keyings[0].setdefault(short, name)
        if tol:
            levels = ", ".join(_setting_text(study, d, r[d]) for d in dims if d in tol)
            keyings[1].setdefault(design_label(r, dims), f"{name}, {levels}")
    out: dict[str, str] = {}
    for keyed in keyings:
        names = list(keyed.values())
        out.update({k: (v if names.count(v) == 1 else k) for k, v in keyed.items()})
    return out


def named(df: pd.DataFrame, names: Mapping[str, str] | None) -> pd.DataFrame:
    """``df`` with its ``design`` column (labels) replaced by the readable names of ``names``."""
    if not names or "design" not in df:
        return df
    out = df.copy()
    out["design"] = [names.get(str(d), str(d)) for d in out["design"]]
    return out


def _rows(study: xr.Dataset, cols: Sequence[str]) -> pd.DataFrame:
    extra = [v for v in ("computed", "case_id") if v in study]
    df = study[list(cols) + extra].to_dataframe().reset_index()
    if "computed" in df:
        df = df[df["computed"].astype(bool)].drop(columns="computed")
    dims = [str(d) for d in study.dims]
    df.insert(0, "design", [design_label(r, dims) for _, r in df.iterrows()])
    return df.reset_index(drop=True)


def design_table(study: xr.Dataset) -> pd.DataFrame:
    """One row per computed case: the swept values, ``design`` (label), ``case_id`` and the
    physical figures of merit that the study holds (the metric table's ``front``, ``resolution``,
    ``pareto`` and ``budget`` metrics).

    Where the study has replicates (:func:`~lfstudy.study.replicates.replicate_dim`), one row per
    design: each metric is its mean over the replicates, ``<metric>_sd`` their standard deviation,
    ``<metric>_se`` the standard error of the mean and ``n_replicates`` how many were computed
    (of the total error)."""
    cols = [c for c in mt.names("front", "resolution", "pareto", "budget") if c in study]
    if not cols:
        return pd.DataFrame()
    if replicate_dim(study) is None:
        return _rows(study, cols)
    stats = replicate_stats(study)
    df = _rows(stats.mean, cols)
    sd, se, n = (_rows(ds, cols) for ds in (stats.sd, stats.se, stats.n))
    for c in cols:
        df[f"{c}_sd"] = sd[c].to_numpy()
        df[f"{c}_se"] = se[c].to_numpy()
    df["n_replicates"] = n[cols[0] if "rms_total_mm" not in cols else "rms_total_mm"].to_numpy()
    return df


def spread_columns(df: pd.DataFrame, cols: Sequence[str], *, se: Sequence[str] = ()) -> list[str]:
    """``cols`` with the spread column of each that ``df`` has right after it: ``<c>_se`` for the
    columns in ``se`` (a decision is made on them), ``<c>_sd`` for the others."""
    out: list[str] = []
    for c in cols:
        out.append(c)
        spread = f"{c}_se" if c in se else f"{c}_sd"
        if spread in df:
            out.append(spread)
    return out


def design_values(study: xr.Dataset, var: str) -> pd.DataFrame:
    """``var`` of every computed case as a table: one row per design and flow (index ``design``,
    ``flow`` where the study has flows), one column per replicate seed (a single column ``value``
    without replicates). For paired comparisons (:func:`~lfstudy.study.replicates.paired_difference`)."""
    dim = replicate_dim(study)
    df = _rows(study, [var])
    index = ["design", *(["flow"] if "flow" in df else [])]
    if dim is None:
        return df.set_index(index)[[var]].rename(columns={var: "value"})
    return df.pivot(index=index, columns=dim, values=var)


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


def error_limit(oracle_mm: float, added_mm: float, filter_mm: float = math.nan) -> str:
    """What limits a design's error: the largest of the budget's three parts.

    The case's error splits in quadrature into the windows' filtering of the flow (``filter_mm``),
    what the reconstruction adds (``added_mm``) and the rest of the oracle's error, sqrt(oracle² −
    filter²): the random error and the estimator's own bias. ``"windows"``, ``"reconstruction"`` or
    ``"random"`` names the largest. Without the filter term (NaN: a study from before it) the oracle's
    whole error counts as the windows'. ``""`` where the oracle or the added share is unknown (a study
    without the oracle)."""
    from lfstudy.study.metrics import quadrature_excess

    o, a, f = float(oracle_mm), float(added_mm), float(filter_mm)
    if not (math.isfinite(o) and math.isfinite(a)):
        return ""
    if not math.isfinite(f):
        return "reconstruction" if a > o else "windows"
    parts = {"windows": f, "reconstruction": a, "random": quadrature_excess(o, f)}
    return max(parts, key=parts.__getitem__)


#: A particle method's scores (rows of the metric table): true particles found, and found within the depth of
#: field about the focal plane.
FOUND = "found_percent"
FOUND_IN_FOCUS = "found_in_focus_percent"
#: A particle method is focus-limited where it finds fewer than this fraction of the particles within the
#: depth of field about the focal plane than of all (issue 27: 0.17-0.37 on the demo designs at 0.005 ppp).
FOCUS_LIMITED = 0.5


def focus_limited(table: pd.DataFrame) -> list[str]:
    """The designs (labels, in order) whose particle reconstruction finds fewer than
    :data:`FOCUS_LIMITED` times as many of the true particles within the depth of field about the focal
    plane (``found_in_focus_percent``) as of all (``found_percent``), in any case of ``table`` (a
    :func:`budget_table`): there a particle's image is one lenslet's spot and the focal plane inside the
    measured volume limits the design, where the reconstruction's share of its error is the larger
    (``limited_by``; :func:`limiting_stage`). Empty where the study holds no particle scores."""
    if not {FOUND, FOUND_IN_FOCUS, "design"} <= set(table.columns):
        return []
    return _designs_where(table, _stage_masks(table)["focus"])


def _designs_where(table: pd.DataFrame, hit: pd.Series) -> list[str]:
    """The design labels of the rows where ``hit`` holds (NaN: no), each once, in order."""
    return list(dict.fromkeys(table.loc[hit.fillna(False).astype(bool), "design"].astype(str)))


#: The seeding a design resolves (row of the metric table: particles per lenslet and depth cell).
PER_CELL = "particles_per_cell"
#: Above this many particles per lenslet and depth cell the seeding limits a particle fit: on the demo designs at
#: 0.005 ppp IPR started from the true positions kept 91-97 % of the particles at 0.06-0.15 and 75 % at 0.30
#: (benchmarks/bench_ipr_density.py, one intensity sweep, no residual rounds); with a warm start's joint intensities
#: 87-96 % and 80.5 % (benchmarks/bench_ipr_depth_slope.py); on the Table 4.3 camera (7 mm deep) IPR found 88-94 % at
#: 0.001 ppp (0.02), 79-87 % at 0.005 ppp (0.10) and 56-64 % at 0.01 ppp (0.20).
DENSITY_LIMITED = 0.2


def density_limited(table: pd.DataFrame) -> list[str]:
    """The designs (labels, in order) with more than :data:`DENSITY_LIMITED` particles per lenslet and depth
    cell (``particles_per_cell``) in any case of ``table`` (a :func:`budget_table`): there two particles
    share a lenslet's line of sight within one depth cell too often for a particle fit to tell them apart,
    whatever its settings; only where the reconstruction's share of the error is the larger (``limited_by``;
    :func:`limiting_stage`): where the windows' is, the seeding limits nothing. Empty where the study holds no
    such column."""
    if not {PER_CELL, "design"} <= set(table.columns):
        return []
    return _designs_where(table, _stage_masks(table)["seeding"])


def budget_table(study: xr.Dataset) -> pd.DataFrame:
    """Per computed case: the design, its flow, the metric table's ``budget`` metrics (the case's error
    beside the oracle's, the windows' filtering, the rest of the oracle's error and the reconstruction's
    share) and ``limited_by`` (:func:`error_limit`, the largest of the three parts).
    Empty when the study holds no oracle.

    With replicates: the means, each followed by its standard deviation ``<metric>_sd``, but the
    crosstalk's followed by its standard error ``<metric>_se`` (its sign is the finding, issue 27);
    ``limited_by`` compares the means."""
    df = design_table(study)
    if df.empty or ORACLE_TOTAL not in df or ADDED_TOTAL not in df:
        return pd.DataFrame()
    names = [c for c in mt.names("budget") if c in df]
    cols = [c for c in ("design", "flow") if c in df] + spread_columns(df, names, se=SIGNED)
    out = df[cols].copy()
    filt = df[FILTER_TOTAL] if FILTER_TOTAL in df else pd.Series(math.nan, index=df.index)
    out["limited_by"] = [
        LIMITS.get(error_limit(o, a, f), "") for o, a, f in zip(df[ORACLE_TOTAL], df[ADDED_TOTAL], filt)
    ]
    return out


def recommend(
    study: xr.Dataset,
    *,
    min_valid: float = 80.0,
    objectives: Sequence[tuple[str, str]] | None = None,
    names: Mapping[str, str] | None = None,
) -> tuple[pd.DataFrame, dict[str, str]]:
    """Per flow: the designs on the Pareto front, and a sentence recommending one.

    The front is over ``objectives`` (default: the metric table's ``pareto`` metrics).

    The recommended design is the Pareto design with the lowest total RMS error
    in mm among those with at least ``min_valid`` % valid vectors (any Pareto
    design if none has). What it trades away: the in-plane and depth
    resolution of the finest-resolving Pareto design, against its error.

    With replicates (a swept ``seed``) the front and the pick are on the means over the seeds, and
    every design of a flow is compared with the recommended one by the paired difference of their
    total errors seed by seed (:func:`~lfstudy.study.replicates.paired_difference`): the sentence
    names the designs of the front it is not separable from (difference below
    :data:`~lfstudy.study.replicates.SEPARATION` standard errors).

    Designs whose total error is that close to the recommended one's (not separable with replicates,
    within :data:`TIE_FRACTION` of it without) tie with it: the sentence names them, and never says
    the recommended design dominates them.

    ``names`` maps design labels to the names the table and the sentences use (:func:`design_names`).

    Returns
    -------
    table : pandas.DataFrame
        The design table with ``pareto`` (bool) and ``recommended`` (bool) columns; with
        replicates also ``diff_rms_total_mm`` and ``diff_rms_total_mm_se`` (the paired difference
        to the flow's recommended design and its standard error) and ``separable`` (bool, or
        ``None`` where unknown).
    sentences : dict flow -> str
    """
    df = named(design_table(study), names)
    if df.empty or "rms_total_mm" not in df:
        return df, {}
    df["pareto"] = False
    df["recommended"] = False
    reps = replicate_dim(study) is not None
    values = design_values(study, "rms_total_mm") if reps else None
    if values is not None and names:
        values = values.rename(index=dict(names), level="design")
    if reps:
        df["diff_rms_total_mm"] = math.nan
        df["diff_rms_total_mm_se"] = math.nan
        df["separable"] = None
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
        extra = ""
        if values is not None:
            extra = _separation(df, sub.index, pick, front_index=cand.index, values=values, flow=flow)
        ties = _ties(df, sub.index, pick, front_index=cand.index, replicates=values is not None)
        sentences[str(flow)] = _sentence(pick, cand, str(flow), min_valid, good.empty, ties=ties) + extra
    return df, sentences


#: Without replicates, two designs whose total RMS errors differ by less than this fraction are a tie: one
#: case per design cannot tell them apart (issue 37: 0.0357 / 0.0359 / 0.0365 mm were "dominated").
TIE_FRACTION = 0.05


def _ties(df: pd.DataFrame, rows: pd.Index, pick: pd.Series, *, front_index: pd.Index, replicates: bool) -> list[str]:
    """The designs of ``rows`` whose total error ties with ``pick``'s, as text ("<name> (0.0359 mm)"): with
    replicates those not separable from it and off the front (:func:`_separation` names the front's),
    without them those within :data:`TIE_FRACTION` of its error."""
    out = []
    for i in rows:
        if i == pick.name:
            continue
        if replicates:
            tie = df.at[i, "separable"] is False and i not in front_index
        else:
            e = float(df.at[i, TOTAL])
            tie = math.isfinite(e) and abs(e - float(pick[TOTAL])) <= TIE_FRACTION * float(pick[TOTAL])
        if tie:
            out.append(f"{df.at[i, 'design']} ({_fmt(df.at[i, TOTAL], 'mm')})")
    return out


def _key(design: str, flow: object) -> tuple[object, ...] | str:
    return (design, flow) if flow is not None else design


def _separation(
    df: pd.DataFrame, rows: pd.Index, pick: pd.Series, *, front_index: pd.Index, values: pd.DataFrame, flow: object
) -> str:
    """Fill the paired differences to ``pick`` of the flow's ``rows`` and say which front designs it is
    not separable from."""
    ref = values.loc[_key(pick["design"], flow)].to_numpy(float)
    for i in rows:
        d, se, _ = paired_difference(values.loc[_key(df.at[i, "design"], flow)].to_numpy(float), ref)
        df.at[i, "diff_rms_total_mm"] = d if i != pick.name else 0.0
        df.at[i, "diff_rms_total_mm_se"] = se if i != pick.name else math.nan
        df.at[i, "separable"] = separable(d, se) if i != pick.name else None
    n = int(pick.get("n_replicates", 0))
    s = (
        f" Over {n} replicates (seeds) its total RMS error is {_fmt(pick['rms_total_mm'])} ± "
        f"{_fmt(pick.get(TOTAL + '_se', math.nan), 'mm')} (mean ± standard error; "
        f"{_fmt(pick.get(TOTAL + '_sd', math.nan), 'mm')} from seed to seed)."
    )
    others = [i for i in front_index if i != pick.name]
    close = [i for i in others if df.at[i, "separable"] is False]
    unknown = [i for i in others if df.at[i, "separable"] is None]
    if close:
        names = "; ".join(
            f"{df.at[i, 'design']} ({df.at[i, 'diff_rms_total_mm']:+.3g} ± {df.at[i, 'diff_rms_total_mm_se']:.3g} mm)"
            for i in close
        )
        s += (
            f" It is not separable from {names}: the difference in total RMS error, paired seed by seed, is "
            f"less than {SEPARATION:g} standard errors, so more replicates are needed to choose between them."
        )
    elif others and not unknown:
        s += (
            f" Every other design on the front has a larger error by at least {SEPARATION:g} standard errors of "
            "the difference, paired seed by seed."
        )
    return s


def _fmt(v: float, unit: str = "") -> str:
    if v is None or not np.isfinite(v):
        return "–"
    return f"{v:.3g}{(' ' + unit) if unit else ''}"


def _sentence(
    pick: pd.Series, cand: pd.DataFrame, flow: str, min_valid: float, none_valid: bool, *, ties: Sequence[str] = ()
) -> str:
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
    elif not ties:
        s += " It dominates every other design."
    if ties:
        s += (
            f" Its error ties with {'; '.join(ties)}: "
            + (
                "the difference is within the noise of the replicates"
                if "n_replicates" in pick
                else f"within {100 * TIE_FRACTION:g} %, and one case per design cannot tell them apart"
            )
            + ", so choose among them on resolution or cost."
        )
    s += _budget_sentence(pick)
    if none_valid:
        s += f" No design on the front reaches {min_valid:g} % valid vectors: treat this study's answer with care."
    return s


def _budget_sentence(pick: pd.Series) -> str:
    """Which part of the recommended design's error budget dominates (nothing without the oracle)."""
    oracle, added = pick.get(ORACLE_TOTAL, math.nan), pick.get(ADDED_TOTAL, math.nan)
    filt, rest = pick.get(FILTER_TOTAL, math.nan), pick.get(REST_TOTAL, math.nan)
    limit = error_limit(oracle, added, filt)
    three = np.isfinite(filt)
    parts = (
        f" (in quadrature: the windows' filtering of the flow {_fmt(filt, 'mm')}, the reconstruction "
        f"{_fmt(added, 'mm')}, the random error and the estimator's bias {_fmt(rest, 'mm')})"
    )
    if limit == "reconstruction":
        return (
            f" Its error is mostly the reconstruction's: on the true particle volumes the same grid and PIV windows "
            f"give {_fmt(oracle, 'mm')}, the reconstruction adds {_fmt(added, 'mm')}"
            + (parts if three else " (in quadrature)")
            + ", so a better reconstruction would lower it."
        )
    if limit == "windows" and three:
        return (
            f" Its error is mostly the PIV windows' filtering of the flow: averaged over the final windows the true "
            f"displacement differs from its value at the vectors by {_fmt(filt, 'mm')}{parts}, so smaller windows "
            "(or a denser seeding that allows them) would lower it, a better reconstruction would not."
        )
    if limit == "windows":
        return (
            f" Its error is mostly the PIV windows': on the true particle volumes the same grid and windows give "
            f"{_fmt(oracle, 'mm')}, the reconstruction adds only {_fmt(added, 'mm')} (in quadrature), so "
            + _reconstruction_gain(pick.get(TOTAL, math.nan), added)
        )
    if limit == "random":
        return (
            f" Its error is mostly random (with the estimator's own bias){parts}: neither the windows' filtering nor "
            "the reconstruction sets it, more particles per window (or larger windows, at the cost of resolution) "
            "would lower it."
        )
    return ""


def influence(study: xr.Dataset, var: str) -> list[tuple[str, float]]:
    """Swept dimensions ranked by how much they move ``var``: the range of its mean over the
    other dimensions (NaN-aware), largest first; flows are compared, not averaged, and the
    replicate seeds are averaged, never ranked."""
    if var not in study:
        return []
    da = study[var]
    out = []
    for d in da.dims:
        if d in ("flow", REPLICATE_DIM) or da.sizes[d] < 2:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            m = da.mean([x for x in da.dims if x not in (d, "flow")], skipna=True)
            rng = float((m.max(d) - m.min(d)).mean(skipna=True)) if "flow" in m.dims else float(m.max() - m.min())
        out.append((str(d), rng if np.isfinite(rng) else 0.0))
    return sorted(out, key=lambda kv: -kv[1])


# ------------------------------------------------------------------ the verdict per flow
#: Where every design's error exceeds its oracle's by more than this factor, the reconstruction, not the optics,
#: ranks the designs (issue 37: 8-33x on the demo's uniform flow).
RECONSTRUCTION_RANKS = 3.0
#: Below this fraction, removing the reconstruction's share would "gain little"; above, the verdict says by how
#: much a better reconstruction would cut the error.
LITTLE_GAIN = 0.10
#: The error budget's third term (the windows' filtering), where the study holds it.
FILTER_TOTAL = "filter_rms_total_mm"
#: What limits a design beyond the two budget terms: the seeding and the focal plane, both through the
#: reconstruction (:func:`limiting_stage`).
STAGES = {"seeding": "the seeding", "focus": "the focal plane"}


def reconstruction_cut(error_mm: float, added_mm: float) -> float:
    """The fraction by which a perfect reconstruction would cut a design's error: removing the share
    ``added_mm`` it adds in quadrature leaves sqrt(error² − added²), so the cut is 1 − that / error
    (1 − oracle / error where the reconstruction's share is the only one beyond the oracle). 0 where it
    adds nothing (the case beat its oracle); NaN where either is unknown."""
    e, a = float(error_mm), float(added_mm)
    if not (math.isfinite(e) and math.isfinite(a)) or e <= 0:
        return math.nan
    return 1.0 - math.sqrt(max(e * e - a * a, 0.0)) / e


def _reconstruction_gain(error_mm: float, added_mm: float) -> str:
    """The end of a budget sentence: by how much a better reconstruction would cut the error."""
    cut = reconstruction_cut(error_mm, added_mm)
    if math.isfinite(cut) and cut > LITTLE_GAIN:
        return (
            f"a better reconstruction would still cut the error by {100 * cut:.0f} %: the windows and the grid set "
            "most of it, not all."
        )
    return (
        "a better reconstruction would gain little"
        + (f" (at most {100 * cut:.0f} %)" if math.isfinite(cut) else "")
        + ": the windows and the grid set the error."
    )


def limiting_stage(table: pd.DataFrame) -> pd.Series:
    """Per row of a :func:`budget_table`: the stage that limits the design's error, the one source of the
    summary's *limiting stage* and of the report's seeding and focal-plane pointers.

    The budget's ``limited_by`` (the reconstruction or the PIV windows, ...); where it is the reconstruction
    and the seeding crowds the depth cells (``particles_per_cell`` above :data:`DENSITY_LIMITED`), the
    seeding, through the reconstruction; where it is the reconstruction and a particle fit misses the
    particles near the focal plane (:data:`FOCUS_LIMITED`), the focal plane. A seeding or a focal plane
    that would limit a particle fit limits nothing where the reconstruction's share is not the larger."""
    if "limited_by" not in table:
        return pd.Series([""] * len(table), index=table.index, dtype=object)
    out = table["limited_by"].astype(str).copy()
    for key, hit in _stage_masks(table).items():
        out[hit] = f"{STAGES[key]} (through the reconstruction)"
    return out


def _stage_masks(table: pd.DataFrame) -> dict[str, pd.Series]:
    """Per :data:`STAGES` key, the rows of a :func:`budget_table` it limits: the reconstruction's share is the
    larger (``limited_by``) and the seeding crowds the depth cells, or the fit misses the particles near the
    focal plane. A table without ``limited_by`` (built by hand) is judged on the seeding and focus alone."""
    recon = (
        table["limited_by"].astype(str) == LIMITS["reconstruction"]
        if "limited_by" in table
        else pd.Series(True, index=table.index)
    )
    out = {}
    if PER_CELL in table:
        out["seeding"] = recon & (table[PER_CELL] > DENSITY_LIMITED).fillna(False).astype(bool)
    if {FOUND, FOUND_IN_FOCUS} <= set(table.columns):
        out["focus"] = recon & (table[FOUND_IN_FOCUS] < FOCUS_LIMITED * table[FOUND]).fillna(False).astype(bool)
    return out


def _component_shares(study: xr.Dataset, names: Mapping[str, str] | None) -> pd.DataFrame:
    """Per design and flow: the component (x, y or z) with the largest RMS error and its share of the
    squared total (means over the replicates where the study has them)."""
    comps = [f"rms_{a}_mm" for a in "xyz"]
    if not all(c in study for c in comps):
        return pd.DataFrame()
    src = replicate_stats(study).mean if replicate_dim(study) is not None else study
    df = named(_rows(src, comps), names)
    sq = df[comps].astype(float) ** 2
    tot = sq.sum(axis=1)
    big = sq.idxmax(axis=1, skipna=True) if not sq.isna().all(axis=None) else pd.Series(np.nan, index=df.index)
    keys = [c for c in ("design", "flow") if c in df]
    out = df[keys].copy()
    out["component"] = [str(c)[4] if isinstance(c, str) else "" for c in big]
    out["component_share"] = [
        float(sq.at[i, c] / tot[i]) if isinstance(c, str) and tot[i] > 0 else math.nan for i, c in big.items()
    ]
    return out


def summary_table(
    study: xr.Dataset, budget: pd.DataFrame | None = None, names: Mapping[str, str] | None = None
) -> pd.DataFrame:
    """Per design and flow, the report's compact summary: the total error, the oracle's, the
    reconstruction's share (``recon_cut``: the fraction a perfect reconstruction would cut, :func:`reconstruction_cut`),
    the windows' filtering share where the study holds it (``filter_cut``), the dominant component and its share,
    and the limiting stage (:func:`limiting_stage`).

    Parameters
    ----------
    study : xarray.Dataset
        The study.
    budget : pandas.DataFrame, optional
        Its :func:`budget_table` (computed here when not given); the numbers come from it.
    names : mapping, optional
        Design labels to readable names (:func:`design_names`); ``budget`` must use the same.

    Returns
    -------
    pandas.DataFrame
        Columns ``design``, ``flow`` (where the study has flows), ``error_mm`` (with replicates its mean, and
        ``error_mm_sd`` the standard deviation over the seeds), ``oracle_mm``,
        ``ratio`` (error / oracle), ``recon_cut``, ``beat_oracle`` (bool), ``filter_cut`` (where the study
        holds the filtering term), ``component``, ``component_share`` and ``stage``; empty without the oracle.
    """
    bt = named(budget_table(study), names) if budget is None else budget
    if bt.empty:
        return pd.DataFrame()
    keys = [c for c in ("design", "flow") if c in bt]
    out = bt[keys].copy()
    out["error_mm"] = bt[TOTAL].astype(float)
    if f"{TOTAL}_sd" in bt:  # replicates: the scatter of one case
        out["error_mm_sd"] = bt[f"{TOTAL}_sd"].astype(float)
    out["oracle_mm"] = bt[ORACLE_TOTAL].astype(float)
    out["ratio"] = out["error_mm"] / out["oracle_mm"]
    out["recon_cut"] = [reconstruction_cut(e, a) for e, a in zip(bt[TOTAL], bt[ADDED_TOTAL])]
    out["beat_oracle"] = (bt[TOTAL] < bt[ORACLE_TOTAL]).to_numpy()
    if FILTER_TOTAL in bt:
        out["filter_cut"] = [reconstruction_cut(e, a) for e, a in zip(bt[TOTAL], bt[FILTER_TOTAL])]
    comp = _component_shares(study, names)
    if not comp.empty:
        out = out.merge(comp, on=keys, how="left")
    else:
        out["component"], out["component_share"] = "", math.nan
    out["stage"] = limiting_stage(bt).to_numpy()
    return out


def _range(values: Sequence[float], fmt: str) -> str:
    lo, hi = min(values), max(values)
    return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else f"{fmt.format(lo)}–{fmt.format(hi)}"


def flow_verdict(summary: pd.DataFrame, flow: str | None, recommended: str | None = None) -> str:
    """The verdict in words on one flow's designs, from their :func:`summary_table` rows.

    - Where every design's error exceeds its oracle's by more than :data:`RECONSTRUCTION_RANKS`, the ranking
      reflects the reconstruction's artefacts, not the optics (with the range of the factor and of the
      dominant component's share).
    - For the recommended design: by how much a better reconstruction would cut its error (or that it would
      gain little, at most :data:`LITTLE_GAIN`).
    - The designs that beat their oracle (the reconstruction's share is then 0).
    """
    sub = summary[summary["flow"] == flow] if "flow" in summary and flow is not None else summary
    sub = sub[np.isfinite(sub["ratio"].astype(float))]
    if sub.empty:
        return ""
    on = f"On {flow}" if flow is not None else "Here"
    out = []
    ratios = sub["ratio"].astype(float).tolist()
    if min(ratios) > RECONSTRUCTION_RANKS:
        s = f"{on} every design's error is {_range(ratios, '{:.0f}')}× its oracle's"
        s += " (the same PIV on the true particles)"
        comps = set(sub["component"].dropna().astype(str)) - {""}
        shares = sub["component_share"].astype(float)
        if len(comps) == 1 and np.isfinite(shares).all():
            s += f", {_range((100 * shares).tolist(), '{:.0f}')} % of it (in quadrature) in {comps.pop()}"
        out.append(
            s + ": the ranking reflects the reconstruction's artefacts, not the optics. Compare the designs on "
            "their oracles for what the optics allow."
        )
    pick = sub[sub["design"] == recommended] if recommended is not None else sub.iloc[:0]
    if not pick.empty:
        r = pick.iloc[0]
        cut = float(r["recon_cut"])
        if bool(r["beat_oracle"]):
            out.append(
                f"The recommended design beat its oracle ({_fmt(r['error_mm'], 'mm')} against "
                f"{_fmt(r['oracle_mm'], 'mm')}): the reconstruction adds nothing measurable, the windows set its error."
            )
        elif math.isfinite(cut) and cut > LITTLE_GAIN:
            out.append(
                f"A better reconstruction would cut the recommended design's error by {100 * cut:.0f} % (from "
                f"{_fmt(r['error_mm'], 'mm')} towards the oracle's {_fmt(r['oracle_mm'], 'mm')})."
            )
        elif math.isfinite(cut):
            out.append(
                f"A better reconstruction would gain little on the recommended design: at most {100 * cut:.0f} % of "
                f"its {_fmt(r['error_mm'], 'mm')}."
            )
    beat = sub[sub["beat_oracle"].astype(bool)]
    beat = beat[beat["design"] != recommended] if recommended is not None else beat
    if not beat.empty:
        out.append(
            f"{'; '.join(str(d) for d in beat['design'])} beat {'its' if len(beat) == 1 else 'their'} oracle "
            "(an error below the PIV's on the true particles, within that PIV's own scatter): the reconstruction's "
            "share is 0 there."
        )
    return " ".join(out)


#: The study's dimension of a swept reconstruction method (``reconstruct.method``).
METHOD_DIM = "reconstruct_method"


def method_comparison(study: xr.Dataset, names: Mapping[str, str] | None = None) -> pd.DataFrame:
    """Where the study sweeps ``reconstruct.method``: one row per design (its other swept settings) and flow,
    with the oracle's total RMS error (PIV on the true volumes: one figure for every method) and each method's,
    in mm and as a multiple of the oracle's. Empty where fewer than two methods ran or there is no oracle.

    Columns: ``design`` (the readable name of ``names`` less the method, else the label), ``flow``,
    ``oracle_mm``, ``<method>_mm`` and ``<method>_ratio`` per method in the sweep's order, and ``lowest`` (the
    method of the lowest error; empty where one is missing).
    """
    if METHOD_DIM not in study.dims or study.sizes[METHOD_DIM] < 2:
        return pd.DataFrame()
    df = design_table(study)
    if df.empty or TOTAL not in df or ORACLE_TOTAL not in df or METHOD_DIM not in df:
        return pd.DataFrame()
    methods = [str(m) for m in study[METHOD_DIM].values]
    names = names or {}

    def base(label: str, method: str) -> str:
        name = names.get(label, label)
        for tail in (f", {_setting_text(study, METHOD_DIM, method)}", f" {METHOD_DIM}={method}"):
            name = name.removesuffix(tail)
        return name

    df = df.assign(
        design=[base(str(d), str(m)) for d, m in zip(df["design"], df[METHOD_DIM])],
        flow=df.get("flow", ""),
    )
    rows = []
    for (design, flow), g in df.groupby(["design", "flow"], sort=False):
        row: dict[str, object] = {"design": design, "flow": flow, "oracle_mm": float(g[ORACLE_TOTAL].mean())}
        for m in methods:
            e = g.loc[g[METHOD_DIM].astype(str) == m, TOTAL]
            row[f"{m}_mm"] = float(e.iloc[0]) if len(e) else math.nan
            row[f"{m}_ratio"] = row[f"{m}_mm"] / row["oracle_mm"] if row["oracle_mm"] > 0 else math.nan
        errs = [row[f"{m}_mm"] for m in methods]
        row["lowest"] = methods[int(np.argmin(errs))] if all(np.isfinite(errs)) else ""
        rows.append(row)
    return pd.DataFrame(rows)
