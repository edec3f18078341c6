"""The comparative study report: one self-contained HTML file (and the same figures as PNGs).

:func:`write_report` reads the study Dataset (``lfstudy.study.metrics.combine_cases``)
and each case's artefacts, and writes one HTML file with inline CSS and every
figure embedded as a base64 PNG: it opens offline and can be mailed as is.
:func:`write_figures` writes the same figures as separate PNG files (for
``snakemake --report``'s ``report(...)`` outputs).

An artefact that is missing or unreadable never stops the report: its place
says "not available" and why. Figures are drawn on :class:`~matplotlib.figure.Figure`
objects (Agg canvas), not through ``pyplot``, so nothing leaks between calls.
"""

from __future__ import annotations

import base64
import contextlib
import html
import io as _io
import json
import math
import re
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from lfstudy import io
from lfstudy.optics import PlenopticCamera
from lfstudy.study import metric_table as mt
from lfstudy.study.case import case_planes
from lfstudy.study.config import case_config, depth_calibrated
from lfstudy.study.replicates import SEPARATION, pm, replicate_dim, replicate_stats
from lfstudy.study.sweep import format_value

__all__ = [
    "write_report",
    "write_figures",
    "write_html",
    "report_blocks",
    "best_designs",
    "case_table",
    "Block",
    "SECTIONS",
    "TOLERANCE_SECTION",
    "report_sections",
    "piv_figure_blocks",
]

#: Section ids and titles, in report order: the answer first.
SECTIONS: dict[str, str] = {
    "answer": "Recommended design",
    "overview": "Overview",
    "comparison": "Comparison across the sweep",
    "designs": "Camera designs",
    "uncertainty": "Per-vector uncertainty against the truth",
    "thesis": "Comparison with the thesis (ch. 7)",
    "representative": "Representative case",
    "cases": "Per-case results",
    "legend": "Study table columns",
}

#: The tolerance section (id, title): in the report, after the answer, only where the study sweeps an
#: imperfection (:data:`lfstudy.study.sweep.TOLERANCES`).
TOLERANCE_SECTION: tuple[str, str] = ("tolerances", "Tolerances: the error against each imperfection")


def report_sections(study: xr.Dataset) -> dict[str, str]:
    """The report's sections for this study: :data:`SECTIONS`, with :data:`TOLERANCE_SECTION` after
    the answer where the study sweeps an imperfection over two or more levels."""
    from lfstudy.study.tolerance import tolerance_dims

    if not tolerance_dims(study):
        return dict(SECTIONS)
    out: dict[str, str] = {}
    for k, v in SECTIONS.items():
        out[k] = v
        if k == "answer":
            out[TOLERANCE_SECTION[0]] = TOLERANCE_SECTION[1]
    return out


#: Thesis figures for the uniform displacements (image-frame sign), sec. 7.1–7.2.
THESIS_REFERENCE = {
    "x": {"mean": -4.45, "std": 0.07, "where": "sec. 7.1, Fig. 7.2: 4.5 px x-shift, 0.001 ppp"},
    "z": {"mean": -2.47, "std": 0.57, "where": "sec. 7.2, Fig. 7.8: 2.5 px z-shift (peak locking)"},
}


@dataclass
class Block:
    """One piece of a report section: a figure, an HTML fragment or a note."""

    section: str
    name: str
    caption: str = ""
    figure: Any = None  # matplotlib Figure
    html: str = ""  # trusted fragment built here (tables are escaped by pandas)
    note: str = ""  # plain text, escaped on output
    case: str | None = None  # per-case blocks are grouped under their case id
    title: str = ""  # the per-case group's heading (default: the case id)
    rendered: str = ""  # the block's HTML already rendered (a figure drawn in a worker process)


# ---------------------------------------------------------------- helpers
def _na(section: str, name: str, what: str, why: str, case: str | None = None) -> Block:
    return Block(section, name, note=f"{what}: not available ({why}).", case=case)


def _try(section: str, name: str, caption: str, what: str, make: Callable[[], Any], case: str | None = None) -> Block:
    """Build a figure; any failure becomes a "not available" note (the report must not crash)."""
    try:
        fig = make()
    except FileNotFoundError as exc:
        return _na(
            section,
            name,
            what,
            f"missing {Path(str(exc.args[0]) if exc.args else '?').name}" if exc.args else "missing artefact",
            case,
        )
    except Exception as exc:
        warnings.warn(f"report: {what} failed: {exc!r}", RuntimeWarning, stacklevel=2)
        return _na(section, name, what, f"{type(exc).__name__}: {exc}", case)
    return Block(section, name, caption=caption, figure=fig, case=case)


#: Where a case's files are: a directory holding all of them, or ``{file name: path}``.
CaseFiles = Path | Mapping[str, Path]


def _path(files: CaseFiles, store: str) -> Path:
    return Path(files[store]) if isinstance(files, Mapping) else Path(files) / store


def _exists(files: CaseFiles) -> bool:
    return any(Path(p).exists() for p in files.values()) if isinstance(files, Mapping) else Path(files).is_dir()


def _open(files: CaseFiles, store: str, var: str | None = None) -> xr.Dataset | xr.DataArray:
    """Open a case's ``store`` lazily; with ``var=""`` return its first data variable."""
    ds = io.open_zarr(_path(files, store))
    if var is None:
        return ds
    name = var or (next(iter(ds.data_vars)))
    return ds[name]


def _table(df: pd.DataFrame, *, index: bool = True, fmt: str = "{:.3g}") -> str:
    def f(v: Any) -> str:
        if isinstance(v, (float, np.floating)):
            return "–" if not np.isfinite(v) else fmt.format(v)
        return str(v)

    out = df.to_html(
        index=index, escape=True, border=0, classes="tbl", na_rep="–", formatters=dict.fromkeys(df.columns, f)
    )
    # Column headers may break after an underscore (locking_excess_z), so a wide table narrows to its
    # box instead of running off it; the text is escaped already, <wbr> adds no character to a copy.
    head, sep, body = out.partition("</thead>")
    return _HEADER_CELL.sub(lambda m: m[1] + m[2].replace("_", "_<wbr>") + m[3], head) + sep + body


_HEADER_CELL = re.compile(r"(<th[^>]*>)([^<]*)(</th>)")

#: Header tags of a column merged with its spread (:func:`_spread_text`).
_SPREAD = (("_sd", "± sd"), ("_se", "± s.e."))


def _spread_text(df: pd.DataFrame) -> pd.DataFrame:
    """A table with replicates, for display: each column ``c`` that has a ``c_sd`` (or ``c_se``)
    column becomes the text ``mean ± spread`` under the header ``c ± sd`` (``c ± s.e.``); a table
    without spread columns is returned as is."""
    out = df.copy()
    for c in list(df.columns):
        for suffix, tag in _SPREAD:
            if f"{c}{suffix}" in df and c in out:
                out[c] = [pm(m, v) for m, v in zip(df[c], df[f"{c}{suffix}"])]
                out = out.drop(columns=f"{c}{suffix}").rename(columns={c: f"{c} {tag}"})
    return out


def _spread_of(mean: pd.DataFrame, sd: pd.DataFrame, cols: Sequence[str]) -> pd.DataFrame:
    """``mean`` with ``<c>_sd`` (from the aligned table ``sd``) after each column of ``cols``."""
    out = mean.copy()
    order = []
    for c in mean.columns:
        order.append(c)
        if c in cols:
            out[f"{c}_sd"] = sd[c].to_numpy()
            order.append(f"{c}_sd")
    return out[order]


def _replicates_note(study: xr.Dataset) -> str:
    """One sentence on the study's replicates for a section's text ("" without replicates)."""
    dim = replicate_dim(study)
    if dim is None:
        return ""
    seeds = ", ".join(format_value(v) for v in study[dim].values.tolist())
    return (
        f" The study holds {study.sizes[dim]} replicates (seeds {seeds}): a value is the mean over them, ± their "
        "standard deviation (sd, the scatter of one case) or, where a decision rests on it, the standard error "
        "of the mean (s.e.)."
    )


def _png(fig: Any) -> bytes:
    buf = _io.BytesIO()
    # No "Software" text chunk: the file carries no link to anywhere.
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", name.replace("/", "__")).strip("-")


def case_table(study: xr.Dataset, columns: Sequence[str] | None = None) -> pd.DataFrame:
    """Computed cases as rows (index: swept parameters) and the given metrics as columns
    (default: the metric table's ``headline`` metrics).

    With replicates (a swept ``seed``): one row per design and flow, each metric the mean over the
    seeds followed by ``<metric>_sd``, their standard deviation."""
    cols = [c for c in (mt.names("headline") if columns is None else columns) if c in study]
    if not cols:
        return pd.DataFrame()
    if replicate_dim(study) is not None:
        stats = replicate_stats(study)
        return _spread_of(case_table(stats.mean, cols), case_table(stats.sd, cols), cols)
    df = study[cols + (["computed"] if "computed" in study else [])].to_dataframe()
    df = df[df["computed"].astype(bool)].drop(columns="computed") if "computed" in df else df.dropna(how="all")
    return df[cols]


def best_designs(study: xr.Dataset) -> pd.DataFrame:
    """Per flow, the case that wins each criterion, judged in physical units.

    The criteria are the metric table's ``criterion`` metrics that the study holds
    (or that derive from what it holds, like |bias|), best by their
    ``lower_is_better``: total and relative error, bias, in-plane and depth vector
    spacing, valid vectors, Q, run time. Voxel errors are not compared across
    designs: a voxel is pitch/|M| across and differs between them. Returns an
    empty table for an empty study.
    """
    df = case_table(study, [c for c in study.data_vars if c != "computed" and study[c].dtype.kind in "biuf"])
    if df.empty:
        return df
    rows = []
    for m in mt.shown_in("criterion"):
        if m.name not in df and m.derive is not None:
            with contextlib.suppress(KeyError):
                df[m.name] = m.derive(df)
    for flow, sub in df.groupby(level="flow", sort=False):
        for m in mt.shown_in("criterion"):
            if m.name not in sub or not sub[m.name].notna().any():
                continue
            idx = sub[m.name].idxmin() if m.lower_is_better else sub[m.name].idxmax()
            p = dict(zip(sub.index.names, idx))
            rows.append(
                {
                    "flow": flow,
                    "criterion": m.criterion_label,
                    "value": float(sub.loc[idx, m.name]),
                    "unit": m.units,
                    **{k: v for k, v in p.items() if k != "flow"},
                    "total RMS [mm]": float(sub.loc[idx, "rms_total_mm"]) if "rms_total_mm" in sub else math.nan,
                }
            )
    return pd.DataFrame(rows)


def piv_figure_blocks(
    section: str, piv: xr.Dataset, errors: xr.Dataset | None = None, *, case: str | None = None
) -> Iterator[Block]:
    """The figures of one PIV result: convergence per pass, displacement histograms and vector slices.

    Shared by the study report (per case, with the errors against the known flow: the histograms
    mark the mean true displacement) and the recording report (per pair, no truth).

    Parameters
    ----------
    section : str
        Report section of the blocks.
    piv : xarray.Dataset
        One WIDIM result (loaded).
    errors : xarray.Dataset, optional
        Its errors store (:func:`lfstudy.study.metrics.case_metrics`), when the flow is known.
    case : str, optional
        Group the blocks under this case (or pair) name.
    """
    from lfstudy.study import figures as rf

    yield _try(
        section,
        "convergence",
        "Corrector RMS and valid vectors per pass (Figs 6.14–6.15).",
        "PIV convergence",
        lambda: rf.piv_convergence(piv),
        case=case,
    )
    yield _try(
        section,
        "histograms",
        "Measured displacement per component, valid vectors (Figs 7.2–7.4, 7.8)"
        + ("; dashed: mean true displacement." if errors is not None else "."),
        "displacement histograms",
        lambda: rf.displacement_histograms(piv, errors),
        case=case,
    )
    yield _try(
        section,
        "vectors",
        "Vector-field slices (Figs 7.1, 7.6, 7.9).",
        "vector slices",
        lambda: rf.vector_slices(piv),
        case=case,
    )


def _case_titles(study: xr.Dataset, names: Mapping[str, str]) -> dict[str, str]:
    """Per computed case id: its design's readable name and its flow (and seed), the heading of its figures."""
    from lfstudy.study.designs import design_label

    if "case_id" not in study:
        return {}
    df = study[["case_id"]].to_dataframe().reset_index()
    dims = [str(d) for d in study.dims]
    rep = replicate_dim(study)
    out = {}
    for _, r in df.iterrows():
        if not r["case_id"]:
            continue
        lab = design_label(r, dims)
        out[str(r["case_id"])] = (
            names.get(lab, lab)
            + (f", {r['flow']}" if "flow" in r else "")
            + (f", seed {format_value(r[rep])}" if rep is not None else "")
        )
    return out


def _varied(study: xr.Dataset) -> list[str]:
    """The swept settings with two or more values, but the flow and the replicate seed."""
    rep = replicate_dim(study)
    return [str(k) for k in study.dims if study.sizes[k] > 1 and k != "flow" and k != rep]


def _computed_ids(study: xr.Dataset) -> list[str]:
    """Case ids of the computed cases, in the study's order."""
    if "case_id" not in study:
        return []
    ids = np.asarray(study["case_id"].values).ravel()
    comp = np.asarray(study["computed"].values).ravel() if "computed" in study else np.ones(ids.size, bool)
    return [str(c) for c, ok in zip(ids, comp) if ok and c]


def _cameras(study: xr.Dataset, cfg: Mapping[str, Any]) -> dict[str, PlenopticCamera]:
    """The distinct cameras of the computed cases, labelled by their magnification, f-number and pitch."""
    out: dict[str, PlenopticCamera] = {}
    for cid in _computed_ids(study):
        from lfstudy.study.designs import readable_design

        cam = PlenopticCamera.from_config(case_config(cfg, cid))
        label = readable_design({}, cam) + (
            f", {1000 * cam.pixel_pitch:.3g} µm pixels" if cam.pixel_pitch != 0.0074 else ""
        )
        out.setdefault(label, cam)
    return out


def _representative(
    study: xr.Dataset, case_dirs: Mapping[str, CaseFiles], cfg: Mapping[str, Any] | None = None
) -> tuple[str, str] | None:
    """The case shown as representative, and why: the recommended design's (of the first flow that has one
    with files), else the case with the lowest total RMS error in mm whose files exist, else the first
    existing."""
    from lfstudy.study.designs import TOTAL, recommend

    existing = [c for c, d in case_dirs.items() if _exists(d)]
    if not existing:
        return None
    with contextlib.suppress(Exception):  # no recommendation (no errors in mm): the lowest error instead
        table, _ = recommend(study, names=_names(study, cfg))
        if "case_id" in table:
            for _, r in table[table["recommended"]].iterrows():
                if str(r["case_id"]) in existing:
                    flow = f" for the {r['flow']} flow" if "flow" in table else ""
                    return str(r["case_id"]), f"the recommended design{flow}, {r['design']}"
    for var in (TOTAL, "rms_total"):
        if var in study and "case_id" in study:
            ids = np.asarray(study["case_id"].values).ravel()
            err = np.asarray(study[var].values, dtype=float).ravel()
            for k in np.argsort(np.where(np.isfinite(err), err, np.inf), kind="stable"):
                if np.isfinite(err[k]) and ids[k] in existing:
                    return str(ids[k]), "lowest total RMS error with its artefacts on disk"
    return existing[0], "the first case with its artefacts on disk"


# ------------------------------------------------------------------ blocks
def report_blocks(
    study: xr.Dataset,
    case_dirs: Mapping[str, CaseFiles],
    cfg: Mapping[str, Any],
    *,
    max_cases: int = 50,
    progress: bool = True,
    workers: int = 1,
) -> Iterator[Block]:
    """Every block of the report, section by section (figures are built lazily, one at a time).

    Parameters
    ----------
    study : xarray.Dataset
        The study Dataset (dims = swept settings).
    case_dirs : mapping case id -> directory or {file name: path}
        Where each case's files are.
    cfg : mapping
        The validated study config.
    max_cases : int
        Per-case sections drawn for at most this many cases (all stay in the tables).
    progress : bool
        Show a tqdm progress bar over the per-case figures.
    workers : int
        Processes drawing the per-case figures (1: drawn here, one after the other); with more, they are drawn
        while this process builds the sections above them, and yielded already rendered (``Block.rendered``).
    """
    cfg = dict(cfg)
    if workers > 1 and min(len(case_dirs), max_cases) > 1:  # drawn by a pool from now on, while the sections above
        cases = _pooled_case_blocks(case_dirs, cfg, max_cases=max_cases, progress=progress, workers=workers)
    else:
        cases = _case_blocks(study, case_dirs, cfg, max_cases=max_cases, progress=progress)
    yield from _answer_blocks(study, cfg)
    yield from _tolerance_blocks(study, _names(study, cfg))
    names = _names(study, cfg)
    yield from _overview_blocks(study, case_dirs)
    yield from _comparison_blocks(study, names)
    yield from _design_blocks(study, cfg)
    yield from _uncertainty_blocks(study, case_dirs, names)
    yield from _thesis_blocks(study, cfg, names)
    yield from _representative_blocks(study, case_dirs, cfg)
    titles = _case_titles(study, names)
    for b in cases:
        b.title = titles.get(b.case or "", "")
        yield b
    yield from _legend_blocks(study)


def _rank_at(cfg: Mapping[str, Any]) -> str:
    from lfstudy.study.tolerance import RANK_AT

    rank_at = str((cfg.get("report") or {}).get("rank_at", "ideal"))
    if rank_at not in RANK_AT:
        raise ValueError(f"config key 'report.rank_at' = {rank_at!r}: allowed values are {', '.join(RANK_AT)}")
    return rank_at


def _names(study: xr.Dataset, cfg: Mapping[str, Any] | None) -> dict[str, str]:
    """The designs' readable names (:func:`lfstudy.study.designs.design_names`); the labels where the config
    cannot name them."""
    from lfstudy.study.designs import design_names

    try:
        return design_names(study, cfg or None)
    except Exception as exc:  # the names are cosmetic: a report never fails on them
        warnings.warn(f"report: design names failed: {exc!r}", RuntimeWarning, stacklevel=2)
        return {}


#: The terms the report uses before it explains them, defined once at its top (issue 37 §4).
TERMS = (
    ("oracle", "the case's PIV (same grid, windows and passes) run on the true particle volumes of both frames: the "
     "best any reconstruction could hand to the PIV, so its error is what the design's grid and windows resolve"),
    ("reconstruction's share", "by how much a perfect reconstruction would cut a design's error: 1 − √(error² − "
     "added²) / error, where the reconstruction adds <i>added</i> in quadrature to the oracle's error (1 − oracle / "
     "error); 0 where the case beat its oracle"),
    ("Q", "the reconstruction quality: the normalised correlation of the reconstructed volume with the true "
     "particles drawn on the same grid (1 is perfect; Elsinga et al. 2006)"),
    ("IPR", "iterative particle reconstruction (<code>reconstruct.method: ipr</code>): a reconstruction that fits "
     "particles to the raw images instead of filling voxels (MART)"),
    ("ppp", "particles per pixel: the seeding density, particles per sensor pixel"),
    ("depth gain", "measured / true z displacement of the design's depth calibration (a traverse of the volume), "
     "by which w is divided; blank where the calibration is off"),
)  # fmt: skip


def _terms_html() -> str:
    return (
        "<p><b>Terms.</b> "
        + "; ".join(f"<i>{html.escape(t)}</i>: {d}" for t, d in TERMS)
        + ". Lengths are in mm or µm.</p>"
    )


def _case_configs(study: xr.Dataset, cfg: Mapping[str, Any] | None) -> dict[str, dict[str, Any] | None]:
    """Per computed case id: the case's config (:func:`case_config`), built once for every sentence that reads
    one; None where the config does not build that case (a test's bare study)."""
    cfg = dict(cfg or {})
    out: dict[str, dict[str, Any] | None] = {}
    for cid in _computed_ids(study):
        try:
            out[cid] = case_config(cfg, cid)
        except Exception:
            out[cid] = None
    return out


def _renderers(
    cases: Mapping[str, Mapping[str, Any] | None], cfg: Mapping[str, Any] | None
) -> dict[str, tuple[str, str]]:
    """Per computed case id (``cases``: :func:`_case_configs`): (``raytrace.method``, ``reconstruct.method``) from
    the case's config (the sweep may set either); the study config's own where a case's cannot be built."""
    cfg = dict(cfg or {})
    top = (
        str((cfg.get("raytrace") or {}).get("method", "exact")),
        str((cfg.get("reconstruct") or {}).get("method", "")),
    )
    return {
        cid: top if c is None else (str(c["raytrace"].get("method", "exact")), str(c["reconstruct"].get("method", "")))
        for cid, c in cases.items()
    }


def _piv_modes(cases: Mapping[str, Mapping[str, Any] | None]) -> dict[str, tuple[str, bool, str]]:
    """Per computed case id (``cases``: :func:`_case_configs`): (``reconstruct.method``,
    ``depth_calibration.enabled``, ``piv.particles``) as the case ran them (the sweep fills in ``paired`` for a
    particle fit without depth calibration); cases whose config cannot be built are left out."""
    return {
        cid: (str(c["reconstruct"].get("method", "")), depth_calibrated(c), str(c["piv"].get("particles", "none")))
        for cid, c in cases.items()
        if c is not None
    }


#: What each ``piv.particles`` mode does, in the report's words.
PIV_MODES = {
    "paired": "paired the fitted particles and ran WIDIM again on volumes of the paired particles alone "
    "(<code>piv.particles: paired</code>)",
    "ptv": "tracked the fitted particles and binned the tracks on the WIDIM grid (<code>piv.particles: ptv</code>)",
}


def _piv_mode_text(modes: Mapping[str, tuple[str, bool, str]]) -> str:
    """Where a particle fit ran with and without depth calibration: the two compare PIV modes, not the calibration
    alone (particles are not paired or tracked with a depth calibration, whose traverse measures WIDIM's gain)."""
    fits = [v for v in modes.values() if _fits_particles(v[0])]
    tracked = sorted({mode for _, dcal, mode in fits if not dcal and mode in PIV_MODES})
    if not (tracked and any(dcal and mode == "none" for _, dcal, mode in fits)):
        return ""
    names = ", ".join(sorted({m.upper() for m, _, _ in fits}))
    return (
        f" <b>The {html.escape(names)} cases with and without depth calibration compare two PIV modes, not the "
        f"calibration alone:</b> without it, PIV {' or '.join(PIV_MODES[m] for m in tracked)}; with it, WIDIM ran "
        "on the volumes rendered from the fitted particles and the axial displacement was corrected by the "
        "design's depth response (the traverse measures WIDIM's depth gain, so the particles are neither paired "
        "nor tracked there)."
    )


def _fits_particles(method: str) -> bool:
    from lfstudy.reconstruct.registry import gives_particles

    try:
        return gives_particles(method)
    except Exception:
        return False


#: What each renderer is, in the report's words.
RENDERERS = {
    "exact": "the exact renderer (<code>raytrace.method: exact</code>: each particle's expected image from the "
    "analytic model, no rays)",
    "montecarlo": "the Monte-Carlo renderer (<code>raytrace.method: montecarlo</code>: random rays per particle, "
    "the thesis' tracer, a model no reconstruction uses)",
}


def _renderer_text(methods: Mapping[str, tuple[str, str]]) -> str:
    """Which renderer made the images, and the inverse crime where a particle fit met the exact renderer."""
    if not methods:
        return ""
    used = sorted({r for r, _ in methods.values()})
    s = "The raw images were rendered by " + " and ".join(RENDERERS.get(r, html.escape(r)) for r in used) + "."
    crime = sorted({m for r, m in methods.values() if r == "exact" and _fits_particles(m)})
    if crime:
        s += (
            f" <b>{html.escape(', '.join(m.upper() for m in crime))} fits particles with the same analytic model "
            "that rendered its images (an inverse crime): its figures come from the fit's own model and may flatter "
            "it.</b> Render with <code>raytrace.method: montecarlo</code> for a fair test."
        )
    return s


def _inverse_crime(methods: Mapping[str, tuple[str, str]], study: xr.Dataset, flow: str) -> str:
    """The verdict's sentence on a flow whose particle-fit cases were rendered by the exact renderer."""
    if "case_id" not in study or "flow" not in study.dims:
        ids = list(methods)
    else:
        ids = [c for c in _computed_ids(study.sel(flow=[flow])) if c in methods]
    crime = sorted({m for c in ids for r, m in [methods[c]] if r == "exact" and _fits_particles(m)})
    if not crime:
        return ""
    return (
        f" The {', '.join(m.upper() for m in crime)} figures come from the fit's own model (images from the exact "
        "renderer, an inverse crime) and may flatter it."
    )


def _pct(v: float) -> str:
    return "–" if not np.isfinite(v) else f"{100 * v:.0f} %"


def _summary_html(summ: pd.DataFrame, flow: str | None, recommended: str | None) -> str:
    """One flow's compact summary table: a row per design, best first, no column that needs a scroll."""
    sub = summ[summ["flow"] == flow] if flow is not None and "flow" in summ else summ
    sub = sub.sort_values("error_mm")
    out = pd.DataFrame(
        {
            "design": [str(d) + (" (recommended)" if d == recommended else "") for d in sub["design"]],
            **(
                {"error [mm] ± sd": [pm(m, v) for m, v in zip(sub["error_mm"], sub["error_mm_sd"])]}
                if "error_mm_sd" in sub
                else {"error [mm]": sub["error_mm"].map(lambda v: f"{v:.3g}")}
            ),
            "oracle [mm]": sub["oracle_mm"].map(lambda v: f"{v:.3g}"),
            "error / oracle": sub["ratio"].map(lambda v: "–" if not np.isfinite(v) else f"{v:.1f}×"),
            "reconstruction's share": [
                "0 % (beat its oracle)" if b else _pct(c) for c, b in zip(sub["recon_cut"], sub["beat_oracle"])
            ],
            **({"windows' filtering share": sub["filter_cut"].map(_pct)} if "filter_cut" in sub else {}),
            "dominant component": [
                f"{c} ({_pct(v)})" if isinstance(c, str) and c else "–"
                for c, v in zip(sub["component"], sub["component_share"])
            ],
            "limiting stage": sub["stage"].replace("", "–"),
        }
    )
    return _table(out, index=False).replace('class="dataframe tbl"', 'class="dataframe tbl summary"')


def _answer_blocks(study: xr.Dataset, cfg: Mapping[str, Any] | None = None) -> Iterator[Block]:
    """The recommendation: per flow, the recommended design, the verdict in words and a compact summary
    table, then the Pareto front over error, in-plane and depth resolution.

    Where the study sweeps imperfections, the designs are ranked at the ideal camera or at their
    worst case over the tolerances (``report.rank_at``), and the sentences say which."""
    from lfstudy.study import figures as rf
    from lfstudy.study.designs import budget_table, flow_verdict, named, recommend, spread_columns, summary_table
    from lfstudy.study.tolerance import at_ideal, tolerance_dims, worst_case

    rank_at = _rank_at(cfg or {})
    tol = tolerance_dims(study)
    ranked = study if not tol else (worst_case(study) if rank_at == "tolerances" else at_ideal(study))
    names = _names(study, cfg)
    table, sentences = recommend(ranked, names=names)
    reps = replicate_dim(study) is not None
    if tol:
        sentences = {f: s + _tolerance_sentence(study, table, f, rank_at, names) for f, s in sentences.items()}
    if not sentences:
        yield Block("answer", "none", note="Recommendation: not available (no computed case with errors in mm).")
        return
    cases = _case_configs(study, cfg)
    methods = _renderers(cases, cfg)
    said = _renderer_text(methods) + _piv_mode_text(_piv_modes(cases))
    yield Block("answer", "terms", html=_terms_html() + f"<p>{said}</p>")
    summ = summary_table(ranked, named(budget_table(ranked), names), names)
    front_cols = [c for c in mt.names("front") if c in table]
    cols = [c for c in ("design", "flow") if c in table] + spread_columns(table, front_cols, se=("rms_total_mm",))
    cols += ["recommended"] if "recommended" in table else []
    for flow, sentence in sentences.items():
        sel = (table["flow"] == flow) if "flow" in table else np.ones(len(table), bool)
        rec = table.loc[sel & table["recommended"], "design"]
        pick = str(rec.iloc[0]) if len(rec) else None
        verdict = (flow_verdict(summ, flow if "flow" in table else None, pick) if not summ.empty else "") + (
            _inverse_crime(methods, study, flow)
        )
        yield Block(
            "answer",
            f"verdict_{flow}",
            html=f"<h3>{html.escape(flow)}</h3><p><b>{html.escape(sentence)}</b></p>"
            + (f'<p class="verdict">{html.escape(verdict.strip())}</p>' if verdict.strip() else "")
            + (_summary_html(summ, flow if "flow" in summ else None, pick) if not summ.empty else ""),
        )
        yield _try(
            "answer",
            f"pareto_{flow}",
            f"{flow}: every design's total RMS error against its in-plane resolution (colour: depth "
            "resolution, where it differs); ringed: the Pareto front, star: recommended; numbers: the designs "
            "in the key, in the summary's order.",
            "Pareto front",
            lambda flow=flow: rf.pareto_figure(table, flow),
        )
        front = table[sel & table["pareto"]]
        yield Block(
            "answer",
            f"front_{flow}",
            html=f"<details><summary>Pareto front, {html.escape(flow)}: every column</summary>"
            + _table(_spread_text(front[cols].sort_values("rms_total_mm")), index=False)
            + "</details>",
        )
        if reps:
            yield _ranking_block(table, flow)
    yield from _methods_block(study, names)
    yield Block(
        "answer",
        "method",
        html="<p>Designs are compared in millimetres and as a fraction of the true displacement: a voxel is "
        "pitch/|M| across and a fraction of a refocus-plane spacing deep, and differs between designs. A design "
        "is on the Pareto front when no other is better in all of "
        + html.escape(", ".join(f"{m.long_name} ({m.better})" for m in mt.shown_in("pareto")))
        + " at once; the recommended one is the front's lowest total RMS error with at least 80 % valid vectors."
        + (
            _replicates_note(study) + " Designs are ranked on their means; two whose total RMS errors differ by "
            f"less than {SEPARATION:g} standard errors of their difference, paired seed by seed (the designs of "
            "one seed image the same particles), are not separable."
            if reps
            else ""
        )
        + "</p>",
    )
    if tol:
        yield _limits_block(study, names)
    yield from _budget_blocks(study, names)


def _methods_block(study: xr.Dataset, names: Mapping[str, str]) -> Iterator[Block]:
    """Where the study sweeps ``reconstruct.method``: every design's total error under each method with the
    oracle beside it (:func:`lfstudy.study.designs.method_comparison`), and how the methods compare in words."""
    from lfstudy.study.designs import method_comparison

    cmp = method_comparison(study, names)
    if cmp.empty:
        return
    methods = [c.removesuffix("_mm") for c in cmp if c.endswith("_mm") and c != "oracle_mm"]
    fmt = lambda e, r: "–" if not np.isfinite(e) else f"{e:.3g} ({r:.1f}×)"  # noqa: E731
    out = pd.DataFrame({"design": cmp["design"]})
    if cmp["flow"].astype(bool).any():
        out["flow"] = cmp["flow"]
    out["oracle [mm]"] = cmp["oracle_mm"].map(lambda v: f"{v:.3g}")
    for m in methods:
        out[f"{m.upper()} [mm] (× oracle)"] = [fmt(e, r) for e, r in zip(cmp[f"{m}_mm"], cmp[f"{m}_ratio"])]
    out["lowest"] = cmp["lowest"].str.upper().replace("", "–")
    said = []
    for m in methods:
        r = cmp[f"{m}_ratio"][np.isfinite(cmp[f"{m}_ratio"])]
        if len(r):
            said.append(f"{m.upper()} errs {r.min():.1f}–{r.max():.1f}× its oracle")
    wins = cmp["lowest"].value_counts()
    n = int((cmp["lowest"] != "").sum())
    best = ", ".join(f"{m.upper()} on {int(wins.get(m, 0))}" for m in methods)
    text = "; ".join(said) + (f". The lowest error: {best} of {n} (a design on a flow)." if n else ".")
    yield Block(
        "answer",
        "reconstructions",
        html="<h3>Reconstruction methods</h3><p>Each design's total RMS error under each reconstruction the study "
        "ran, beside its oracle (the same PIV on the true particle volumes, the same for every method). "
        + html.escape(text)
        + "</p>"
        + _table(out, index=False),
    )


def _ranking_block(table: pd.DataFrame, flow: str) -> Block:
    """With replicates: every design of ``flow`` by its mean total RMS error, with the paired difference
    to the recommended design, its standard error and whether the two are separable."""
    from lfstudy.study.designs import TOTAL

    sub = table[table["flow"] == flow] if "flow" in table else table
    sub = sub.sort_values(TOTAL)
    words = {True: "yes", False: "no (within noise)"}
    out = pd.DataFrame(
        {
            "design": sub["design"],
            f"{TOTAL} ± s.e.": [pm(m, e) for m, e in zip(sub[TOTAL], sub[f"{TOTAL}_se"])],
            "replicates": sub["n_replicates"].astype(int),
            "− recommended [mm] ± s.e.": [
                "–" if r else pm(d, e, sign=True)
                for d, e, r in zip(sub["diff_rms_total_mm"], sub["diff_rms_total_mm_se"], sub["recommended"])
            ],
            "separable": [
                "recommended" if r else words.get(v, "–") for v, r in zip(sub["separable"], sub["recommended"])
            ],
            "pareto": sub["pareto"],
        }
    )
    return Block(
        "answer",
        f"ranking_{flow}",
        html=f"<details><summary>Every design against the recommended one, {html.escape(flow)}</summary><p>Total "
        "RMS error: mean over the seeds ± its standard error; the difference to the recommended design is the mean "
        "of the per-seed differences ± its standard error, <i>separable</i> where it is at least "
        f"{SEPARATION:g} standard errors.</p>" + _table(out, index=False) + "</details>",
    )


def _limits_block(study: xr.Dataset, names: Mapping[str, str] | None = None) -> Block:
    """Per design: its error at the ideal camera, what each swept imperfection alone adds, its worst
    case over the tolerances and the tolerance that limits it."""
    from lfstudy.study.designs import named
    from lfstudy.study.tolerance import limiting_tolerances

    lim = named(limiting_tolerances(study), names)
    if lim.empty:
        return _na("answer", "limits", "What limits each design at tolerances", "no computed case at the ideal camera")
    if replicate_dim(study) is not None:
        return _limits_block_replicates(study, lim)
    return Block(
        "answer",
        "limits",
        html=_LIMITS_HEAD
        + 'most (<i>limited_by</i>; "nothing" where no imperfection raises the error).</p>'
        + _table(lim, index=False),
    )


#: The opening of the "What each tolerance costs each design" block, with or without replicates.
_LIMITS_HEAD = (
    "<h4>What each tolerance costs each design</h4><p>Per design: the total RMS error at the ideal camera, what "
    "each imperfection alone adds at its worst level (+, the other imperfections ideal), the worst case over the "
    "whole tolerance sweep (combinations included) and the tolerance that costs the "
)


def _limits_block_replicates(study: xr.Dataset, lim: pd.DataFrame) -> Block:
    """:func:`_limits_block` of a study with replicates: each cost ± its standard error, and whether it is
    beyond noise."""
    out = lim.copy()
    for c in [c for c in lim.columns if f"{c} s.e." in lim]:
        out[c] = [
            pm(m, e, sign=True) + ("" if beyond else " (within noise)")
            for m, e, beyond in zip(lim[c], lim[f"{c} s.e."], lim[f"{c} beyond noise"])
        ]
        out = out.drop(columns=[f"{c} s.e.", f"{c} beyond noise"]).rename(columns={c: f"{c} ± s.e."})
    return Block(
        "answer",
        "limits",
        html=_LIMITS_HEAD
        + "most (<i>limited_by</i>)."
        + _replicates_note(study)
        + " A cost is the mean over the seeds of the "
        "difference to the ideal camera at the same seed (the levels of one seed share their particles, rays and "
        f"noise), ± its standard error; one below {SEPARATION:g} standard errors is <i>within noise</i>: the "
        "study cannot tell it from no cost. <i>limited_by</i> is the costliest imperfection beyond noise "
        '("nothing beyond noise" where none is).</p>' + _table(_spread_text(out), index=False),
    )


def _tolerance_sentence(
    study: xr.Dataset, table: pd.DataFrame, flow: str, rank_at: str, design_names: Mapping[str, str] | None = None
) -> str:
    """What the tolerance sweep says about the recommended design of ``flow`` (``table``'s designs named by
    ``design_names``)."""
    from lfstudy.study.designs import named
    from lfstudy.study.tolerance import WORST_BY, limiting_tolerances, tolerance_dims

    names = ", ".join(str(study[d].attrs.get("long_name", d)) for d in tolerance_dims(study))
    if rank_at == "ideal":
        head = (
            f" Ranked at the ideal camera (every swept imperfection, {names}, at its ideal level); "
            "report.rank_at: tolerances ranks at each design's worst case."
        )
    else:
        head = f" Ranked at tolerances: each design at its worst case over {names} (its largest total RMS error)."
    pick = table[table["recommended"] & ((table["flow"] == flow) if "flow" in table else True)]
    lim = named(limiting_tolerances(study), design_names)
    if pick.empty or lim.empty:
        return head
    row = lim[(lim["design"] == pick["design"].iloc[0]) & ((lim["flow"] == flow) if "flow" in lim else True)]
    if row.empty or not row["limited_by"].iloc[0]:
        return head
    r = row.iloc[0]
    ideal, worst = r[f"ideal {WORST_BY}"], r[f"worst {WORST_BY}"]
    if r["limited_by"] == "nothing beyond noise":
        return head + (
            f" No swept imperfection alone costs it more than the noise of the replicates ({ideal:.3g} mm at the "
            f"ideal camera; every cost is within {SEPARATION:g} standard errors of 0); its worst case over the "
            f"tolerances is {worst:.3g} mm."
        )
    if r["limited_by"] == "nothing":
        if worst > ideal:  # no imperfection alone raises it, a combination does
            return head + (
                f" No swept imperfection alone raises its error ({ideal:.3g} mm at the ideal camera); their "
                f"combination reaches {worst:.3g} mm."
            )
        return head + f" No swept imperfection raises its error ({ideal:.3g} mm at the ideal camera)."
    return head + (
        f" Its error is {ideal:.3g} mm at the ideal camera and {worst:.3g} mm at its worst over the tolerances; "
        f"the tolerance that limits it is the {r['limited_by']}."
    )


def _tolerance_blocks(study: xr.Dataset, names: Mapping[str, str] | None = None) -> Iterator[Block]:
    """Per swept imperfection: a table and a figure of the error against its level, per design (the
    other imperfections ideal), with the oracle beside it; and what limits each design."""
    from lfstudy.study import figures as rf
    from lfstudy.study.designs import named
    from lfstudy.study.tolerance import (
        ideal_levels,
        level_label,
        level_text,
        tolerance_metrics,
        tolerance_table,
    )

    ideal = ideal_levels(study)
    if not ideal:
        return
    oracle = {m: f"oracle_{m}" for m in tolerance_metrics(study) if f"oracle_{m}" in study}
    yield Block(
        "tolerances",
        "intro",
        html="<p>Imperfections the imaging has and the processing does not know (the processing keeps the "
        "nominal camera, as in an experiment). Each table and figure varies one of them, the others at their "
        "ideal level ("
        + html.escape("; ".join(level_text(study, d, v) for d, v in ideal.items()))
        + "), per design. "
        + (
            "Beside each error, the oracle's: the case's PIV on the true particle volumes, which no imperfection "
            "of the camera reaches, so the gap between the two is what the imperfection costs the "
            "reconstruction."
            if oracle
            else "The study holds no oracle (errors stores written before it)."
        )
        + " What each costs each design, and which limits it, is in the recommendation above."
        + (_replicates_note(study) + " Bars in the figures: the sd." if replicate_dim(study) is not None else "")
        + "</p>",
    )
    for d in ideal:
        t = named(tolerance_table(study, d), names)
        label = level_label(study, d)
        if t.empty:
            yield _na("tolerances", f"table_{d}", f"Error against {label}", "no computed case")
            continue
        panels = {m: f"{mt.metric(m).long_name} [{mt.metric(m).units}]" for m in tolerance_metrics(study)}
        yield _try(
            "tolerances",
            d,
            f"Error against {label}, per design, the other imperfections ideal; dashed: the oracle.",
            f"error against {label}",
            lambda t=t, label=label, panels=panels: rf.tolerance_figure(t, label, panels, oracle),
        )
        yield Block(
            "tolerances",
            f"table_{d}",
            html=f"<h4>Error against {html.escape(label)}</h4>" + _table(_spread_text(t), index=False),
        )


def _budget_blocks(study: xr.Dataset, names: Mapping[str, str] | None = None) -> Iterator[Block]:
    """Per design: the error in three parts (the windows' filtering, the reconstruction, the rest) and which
    dominates."""
    from lfstudy.study.designs import budget_table, named

    bt = named(budget_table(study), names)
    if bt.empty:
        return
    sort = [c for c in ("flow", "design") if c in bt]
    yield Block(
        "answer",
        "budget",
        html="<h4>Error budget: the PIV windows, the reconstruction and the rest</h4><p>The <i>oracle</i> is the "
        "case's PIV (same grid, windows and passes) run on the true particle volumes of both frames: the best any "
        "reconstruction could hand to the PIV. The error the reconstruction adds is the case's beyond it, in "
        "quadrature (<i>recon_added</i> = sqrt(case² − oracle²)). The oracle's own error splits in two: "
        "<i>filter_rms_total_mm</i> is the windows' filtering of the flow, the true displacement averaged over "
        "each final window (the top-hat WIDIM measures) minus its value at the vector, which no estimator built "
        "from a window's own data can see (0 for a uniform flow); <i>rest_rms_total_mm</i> = sqrt(oracle² − "
        "filter²) is what is left, the random error plus the estimator's own bias. So case² = filter² + "
        "recon_added² + rest², and <i>limited_by</i> names the largest of the three. The crosstalk columns give, "
        "for a uniform flow, the spurious w per unit of lateral shift."
        + (
            " For a method that fits particles, <i>found_percent</i> and <i>ghost_percent</i> score its particle "
            "lists against the true particles (within half a voxel), and <i>particle_crosstalk_z</i> is the "
            "crosstalk of the particles found in both frames alone: where it is near 0 and crosstalk_z is not, the "
            "crosstalk rides on the ghosts and the mislocated particles, not on the particles the fit found. "
            "<i>found_in_focus_percent</i> counts the true particles within the depth of field about the focal "
            "plane (eq. 4.18), where a particle's image is one lenslet's spot whose size changes only to second "
            "order with depth: far below found_percent, the focal plane inside the volume limits the design, and "
            "a volume off it (<code>particles.z_center</code>) avoids that."
            + (
                " <i>depth_unknown_percent</i> needs no truth: the share of the fitted particles whose depth the "
                "fit could not read (its sigma_z above <code>piv.paired_max_sigma_z</code>), left out of the paired "
                "PIV. Near the focal plane the images themselves hold little depth (their Cramér–Rao bound, "
                "<code>lfstudy.reconstruct.ipr.bound</code>): a high share is the design's, not the fit's."
                if "depth_unknown_percent" in bt
                else ""
            )
            + (
                " <i>focus_scatter_ratio</i> needs no truth either: how many times more the paired tracks' "
                "displacements scatter in the band of depth nearest the focal plane than in the best band. The fit's "
                "sigma_z misses most of that error, so this ratio, well above 1, is the sign that the focal plane "
                "inside the volume limits the design; the paired PIV weighs each track by the inverse of its band's "
                "variance (<code>piv.paired_weights</code>)."
                if "focus_scatter_ratio" in bt
                else ""
            )
            if "found_percent" in bt
            else ""
        )
        + (
            _replicates_note(study) + " The crosstalk is shown with its standard error: one case's crosstalk is a "
            f"random draw, so only a mean at least {SEPARATION:g} s.e. away from 0 is a systematic crosstalk."
            if replicate_dim(study) is not None
            else ""
        )
        + "</p>"
        + "<details><summary>The error budget of every design: every column</summary>"
        + _table(_spread_text(bt.sort_values(sort) if sort else bt), index=False)
        + "</details>"
        + _zero_added_text(bt)
        + _focus_text(bt)
        + _density_text(bt),
    )


def _focus_text(bt: pd.DataFrame) -> str:
    """The budget's pointer to the focal plane where a particle method misses the particles near it."""
    from lfstudy.study.designs import FOCUS_LIMITED, focus_limited

    designs = focus_limited(bt)
    if not designs:
        return ""
    return (
        f"<p><b>The focal plane limits {', '.join(html.escape(d) for d in designs)}:</b> the particle fit finds "
        f"fewer than {FOCUS_LIMITED:g} times as many of the particles within the depth of field about the focal "
        "plane as of all. There a particle's image is one lenslet's spot whose size changes only to second order "
        "with depth. A measured volume off the focal plane (<code>particles.z_center</code> with "
        "<code>grid.z_range</code>; <code>config/demo_focus.yaml</code>) avoids it: on the demo designs it "
        "lowered IPR's total error 2-3x.</p>"
    )


def _zero_added_text(bt: pd.DataFrame) -> str:
    """Why the budget shows 0 for the reconstruction's share of some rows: the case beat its oracle."""
    from lfstudy.study.designs import ADDED_TOTAL, ORACLE_TOTAL, TOTAL

    if not {ADDED_TOTAL, ORACLE_TOTAL, TOTAL} <= set(bt.columns):
        return ""
    beat = bt[bt[TOTAL] < bt[ORACLE_TOTAL]]
    if beat.empty:
        return ""
    rows = "; ".join(
        html.escape(str(r["design"]) + (f" on {r['flow']}" if "flow" in beat else ""))
        + f" ({r[TOTAL]:.3g} mm against {r[ORACLE_TOTAL]:.3g} mm)"
        for _, r in beat.iterrows()
    )
    return (
        f"<p><b>The reconstruction adds 0 where a case beat its oracle:</b> {rows}. The oracle's PIV has a "
        "scatter of its own, and a reconstruction can land below it by chance; the reconstruction's share there "
        "is nothing measurable, not a gain.</p>"
    )


def _density_text(bt: pd.DataFrame) -> str:
    """The budget's pointer to the seeding where a design has more particles per depth cell than it resolves
    and the reconstruction's share of its error is the larger; the rows as densely seeded whose windows' share
    is the larger are named as not limited by it. Both from :func:`lfstudy.study.designs.limiting_stage`, the
    source of the summary's limiting stage too, so the two never name different stages for one row."""
    from lfstudy.study.designs import DENSITY_LIMITED, PER_CELL, STAGES, density_limited, limiting_stage

    designs = density_limited(bt)
    if not designs:
        return ""
    hit = limiting_stage(bt).str.startswith(STAGES["seeding"])
    worst = bt.loc[hit, PER_CELL].max()

    def rows(sel: pd.Series) -> str:
        return "; ".join(
            html.escape(str(r["design"]) + (f" on {r['flow']}" if "flow" in bt else "")) for _, r in bt[sel].iterrows()
        )

    spared = ~hit & (bt[PER_CELL] > DENSITY_LIMITED).fillna(False).astype(bool)
    return (
        f"<p><b>The seeding limits {rows(hit)}:</b> up to {worst:.2f} particles share each lenslet and depth cell, "
        f"above {DENSITY_LIMITED:g}, and the reconstruction's share of the error is the larger. There two particles "
        "behind one lenslet often lie within one depth cell (their blur circles differ by less than a lenslet "
        "pitch), and no particle fit tells them apart: on the demo's coarsest design at 0.30 IPR started from the "
        "true positions kept 75 % of them, at 0.06-0.15 the other designs 91-97 %. Seed less, or choose a design "
        "with more depth cells (a larger magnification or a finer lenslet pitch)."
        + (
            f" {rows(spared)}: as densely seeded, but there the windows' share of the error is the larger, so the "
            "seeding limits nothing."
            if spared.any()
            else ""
        )
        + "</p>"
    )


def _overview_blocks(study: xr.Dataset, case_dirs: Mapping[str, CaseFiles]) -> Iterator[Block]:
    from lfstudy.study import figures as rf
    from lfstudy.study.designs import influence

    n_comp = int(study["computed"].sum()) if "computed" in study else len(case_dirs)
    n_total = int(np.prod([study.sizes[k] for k in study.dims]))
    sweep = pd.DataFrame(
        {"values": [", ".join(format_value(v) for v in study[k].values.tolist()) for k in study.dims]},
        index=[str(k) for k in study.dims],
    )
    yield Block(
        "overview",
        "sweep",
        html=(
            f"<p>{n_comp} of {n_total} combinations of the swept settings computed. Displacements and "
            "errors are in the object frame (+z away from the camera): a +x shift reads positive here, "
            "negative in the thesis' histograms. Errors are measured − true over valid vectors; across "
            "designs they are compared in mm and relative to the true displacement."
            + _replicates_note(study)
            + "</p>"
            + _table(sweep)
        ),
    )
    var = next((m for m in mt.names("overview") if m in study), "")
    ranked = [d for d, _ in influence(study, var)]
    if not ranked:
        yield Block("overview", "map", note="Overview figure: not available (no setting takes two values).")
        return
    yield _try(
        "overview",
        "map",
        f"The headline error over the two settings that move it most ({', '.join(ranked[:2])}), mean over the "
        + ("others and the seeds" if replicate_dim(study) is not None else "others")
        + ", per flow.",
        "overview map",
        lambda: rf.overview_heatmap(study, var, ranked[:2]),
    )


def _by_design(df: pd.DataFrame, names: Mapping[str, str] | None) -> pd.DataFrame:
    """A table indexed by the swept settings, as one readable ``design`` column (and ``flow``) instead: the
    settings' columns would make it scroll sideways."""
    from lfstudy.study.designs import design_label

    if df.empty:
        return df
    idx = df.index.to_frame(index=False)
    dims = [str(c) for c in idx.columns]
    labels = [design_label(r, dims) for _, r in idx.iterrows()]
    out = df.reset_index(drop=True)
    out.insert(0, "design", [(names or {}).get(lab, lab) for lab in labels])
    if "flow" in idx:
        out.insert(1, "flow", idx["flow"].to_numpy())
    return out


def _comparison_blocks(study: xr.Dataset, names: Mapping[str, str] | None = None) -> Iterator[Block]:
    from lfstudy.study import figures as rf

    varied = _varied(study)
    if not varied:
        yield Block("comparison", "none", note="Comparison: not available (no swept setting takes two values).")
    for p in varied:
        yield _try(
            "comparison",
            f"panels_{p}",
            f"Headline metrics against {p} (one line per flow, mean over the other settings"
            + ("; bars: sd over the seeds)." if replicate_dim(study) is not None else ")."),
            f"metrics against {p}",
            lambda p=p: rf.parameter_panels(study, p, mt.names("panel")),
        )
        cols = [m for m in mt.names("headline") if m in study]
        if cols:
            rdim = replicate_dim(study)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                red = [d for d in study.dims if d not in (p, "flow", rdim)]
                per = study[cols].mean(red, skipna=True)
                marg = per.to_dataframe() if rdim is None else per.mean(rdim, skipna=True).to_dataframe()
                if rdim is not None:  # the spread of this mean from seed to seed
                    marg = _spread_text(_spread_of(marg, per.std(rdim, ddof=1, skipna=True).to_dataframe(), cols))
            yield Block(
                "comparison",
                f"table_{p}",
                html=f"<details><summary>Mean over the other settings, by {html.escape(p)}</summary>"
                + _table(marg)
                + "</details>",
            )
    ct = case_table(study)
    if not ct.empty:
        title = "All computed cases" if replicate_dim(study) is None else "All computed designs (mean over the seeds)"
        yield Block(
            "comparison",
            "all_cases",
            html=f"<details><summary>{title}</summary>"
            + _table(_spread_text(_by_design(ct, names)), index=False)
            + "</details>",
        )


def _micro(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with "um" in its row labels written µm (the camera's summary spells it in ASCII)."""
    return df.rename(index=lambda i: re.sub(r"\bum\b", "µm", str(i)))


def _design_blocks(study: xr.Dataset, cfg: Mapping[str, Any]) -> Iterator[Block]:
    """Per design: resolution, measurable depth and field of view in mm; the cameras and their optics."""
    from lfstudy.study import figures as rf
    from lfstudy.study.designs import design_table, named, spread_columns

    dt = named(design_table(study), _names(study, cfg))
    cols = [c for c in ("design", "flow", *mt.names("resolution")) if c in dt]
    if not dt.empty and len(cols) > 2:
        cols = spread_columns(dt, cols)
        yield Block(
            "designs",
            "resolution",
            html="<h4>Spatial resolution, measured depth and field of view [mm]</h4>"
            + _table(_spread_text(dt[cols]), index=False),
        )
    try:
        cams = _cameras(study, cfg)
    except Exception as exc:
        cams = {}
        yield _na("designs", "table", "Camera table", f"{type(exc).__name__}: {exc}")
    if not cams:
        return
    yield Block(
        "designs",
        "table",
        html="<details><summary>The cameras' optics: every figure</summary>"
        + _table(_micro(pd.DataFrame({k: c.summary() for k, c in cams.items()})))
        + "</details>",
    )
    cam0 = next(iter(cams.values()))
    mags = [float(c.magnification) for c in cams.values()]
    yield _try(
        "designs",
        "ambiguity",
        "Depth ambiguity ξz (eq. 4.18) and in-plane ambiguity ξy (eq. 4.19) at z = 0 against |M|; dots: the "
        "designs' magnifications. Steps mark where the matched f-number rounds up to the next standard stop "
        "(sec. 4.3.1).",
        "ambiguity against magnification",
        lambda: rf.ambiguity_vs_magnification(cam0, marked=sorted(set(mags))),
    )

    def diamonds():
        planes = {k: (c, case_planes(cfg, c)) for k, c in list(cams.items())[:8]}
        return rf.focal_plane_diamonds(planes)

    yield _try(
        "designs",
        "focal_planes",
        "Depth-of-focus diamonds of the refocus planes (eqs 5.16–5.20) in image space; ticks: plane centres.",
        "focal-plane diamonds",
        diamonds,
    )


#: At most this many designs get a line of their own in the error-against-σ figure; more are pooled.
MAX_UNCERTAINTY_LINES = 10


#: An RMS error / RMS σ ratio beyond this factor either way means σ is wrong: the verdict says not to trust it.
SIGMA_OFF = 1.5


#: Said where σ of w is too small on some design and the study correlated circularly (docs/config.md, piv.zero_pad).
ZERO_PAD_HINT = (
    "A circular correlation of particle images long in depth (a MART volume's) in windows a few voxels deep reads "
    "depth motion that varies across the window short, and σ cannot see it; piv.zero_pad: true is the measured "
    "alternative (docs/config.md); a particle method's paired volumes are rendered half a voxel deep for this "
    "reason (piv.particle_sigma)."
)


def _finite(df: pd.DataFrame, col: str) -> np.ndarray:
    """The numeric values of column ``col`` of ``df``, missing ones dropped (empty without the column)."""
    return pd.to_numeric(df[col], errors="coerce").dropna().to_numpy(float) if col in df else np.array([])


def _oracle_span(df: pd.DataFrame, ax: str) -> str:
    """``lo–hi`` of the designs' ``unc_ratio_oracle_<ax>`` where every one is within :data:`SIGMA_OFF` of 1 (σ right
    against what the windows read of the true particles), else ''."""
    v = _finite(df, f"unc_ratio_oracle_{ax}")
    if not v.size or v.min() < 1 / SIGMA_OFF or v.max() > SIGMA_OFF:
        return ""
    return _span(v, ".2g")


def _uncertainty_verdict(df: pd.DataFrame, circular: bool = False) -> str:
    """The verdict in words on the per-vector σ, per component, from the designs' RMS error / RMS σ ratios
    (``unc_ratio_<axis>``): too small (do not trust it), too large (conservative), about right, or mixed; where it
    is too small on some design but right against the oracle on every one (``unc_ratio_oracle_<axis>``), it says
    that the rest is the windows' response to the flow. ``circular``: the study's PIV correlated circularly
    (``piv.zero_pad`` false); where σ of w is too small on some design the verdict then names the linear
    correlation (:data:`ZERO_PAD_HINT`)."""
    from lfstudy.study.metrics import AXES

    out = []
    for ax, c in AXES.items():
        v = _finite(df, f"unc_ratio_{ax}")
        if not v.size:
            continue
        lo, hi = float(v.min()), float(v.max())
        span = f"{lo:.2g}×" if f"{lo:.2g}" == f"{hi:.2g}" else f"{lo:.2g}–{hi:.2g}×"
        what = f"σ of {c} ({ax})"
        if lo >= 1 and hi > SIGMA_OFF:
            out.append(f"{what} is {span} too small on these designs: do not trust it.")
        elif hi <= 1 and lo < 1 / SIGMA_OFF:
            out.append(f"{what} is too large ({span} the actual error): it overstates the error, a safe bound.")
        elif lo >= 1 / SIGMA_OFF and hi <= SIGMA_OFF:
            out.append(f"{what} is about right ({span} the actual error, within {SIGMA_OFF:g}×).")
        else:
            out.append(f"{what} is {span} the actual error: right on some designs, not on others; trust it per design.")
        if hi > SIGMA_OFF and (o := _oracle_span(df, ax)):
            out.append(
                f"Against the oracle (the same windows on the true particles) it is {o}× the error: what σ misses "
                f"there is the windows' response to the flow beyond their top-hat average, not noise (the budget's "
                f"oracle error holds it)."
            )
        if ax == "z" and circular and hi > SIGMA_OFF:
            out.append(ZERO_PAD_HINT)
    return " ".join(out)


#: The unresolved flag's targets (issue 38): it catches at least this share of the vectors whose true filtering
#: exceeds 2σ ...
UNRESOLVED_HIT = 0.8
#: ... and at most this share of its flags fall on vectors whose true filtering is below σ ...
UNRESOLVED_FALSE = 0.2
#: ... and on a flow the windows do not filter (a uniform shift) it flags at most this many percent of the vectors:
#: twice the 5 % of pure noise the flag leaves with the margin lfstudy.piv.resolution.NOISE_MARGIN_95.
UNRESOLVED_STILL_PERCENT = 10.0
#: The flag's scores in the metric table (unresolved_percent, _hit, _false)
_FLAG_SCORES = tuple(m.name for m in mt.METRICS if m.name.startswith("unresolved_"))


def _span(v: np.ndarray, fmt: str) -> str:
    """``lo–hi`` of ``v`` in format ``fmt`` (one value where they print alike)."""
    lo, hi = format(float(v.min()), fmt), format(float(v.max()), fmt)
    return lo if lo == hi else f"{lo}–{hi}"


def _unresolved_verdict(df: pd.DataFrame) -> str:
    """The verdict in words on the truth-free ``unresolved`` flag, from the cases' ``unresolved_percent``,
    ``unresolved_hit``, ``unresolved_false`` and ``filter_rms_total_mm`` (a case whose windows filter nothing, a
    uniform flow, has every flag false): trust it where it meets :data:`UNRESOLVED_HIT`, :data:`UNRESOLVED_FALSE`
    and :data:`UNRESOLVED_STILL_PERCENT` on every case, else read it as a pointer. Empty without the columns or
    scores."""
    if not set(_FLAG_SCORES) <= set(df):
        return ""
    num = {c: pd.to_numeric(df[c], errors="coerce").to_numpy(float) for c in _FLAG_SCORES}
    filt = pd.to_numeric(df.get("filter_rms_total_mm", pd.Series(np.nan, index=df.index)), errors="coerce")
    still = filt.to_numpy(float) <= 1e-12
    pct_still = num["unresolved_percent"][still]
    pct_still = pct_still[np.isfinite(pct_still)]
    hit = num["unresolved_hit"][~still]
    hit = hit[np.isfinite(hit)]
    false = num["unresolved_false"][~still]
    false = false[np.isfinite(false)]
    if not (pct_still.size or hit.size):
        return ""
    out = []
    if pct_still.size:
        out.append(
            f"On the flows the windows do not filter, {_span(pct_still, '.0f')} % of the vectors are flagged "
            "unresolved (each flag false there)."
        )
    if hit.size:
        out.append(
            f"Of the vectors whose true filtering exceeds 2σ the flag catches {_span(hit, '.2f')}"
            + (f"; {_span(false, '.2f')} of its flags fall where the filtering is below σ." if false.size else ".")
        )
    good = (
        hit.size > 0
        and hit.min() >= UNRESOLVED_HIT
        and (not false.size or false.max() <= UNRESOLVED_FALSE)
        and (not pct_still.size or pct_still.max() <= UNRESOLVED_STILL_PERCENT)
    )
    if good:
        out.append("Trust the unresolved flag on these designs.")
    else:
        out.append(
            "Read the unresolved flag as a pointer to where the measured field varies on the window's scale (the "
            "flow, the reconstruction or the vectors' own noise; piv.unresolved_significance sets a margin over "
            "the noise), not as a verdict per vector "
            f"(its targets: catch ≥ {UNRESOLVED_HIT:g}, ≤ {UNRESOLVED_FALSE:g} false, ≤ "
            f"{UNRESOLVED_STILL_PERCENT:g} % flagged where nothing is filtered)."
        )
    return " ".join(out)


def _circular(study: xr.Dataset) -> bool:
    """Whether the study's PIV correlated circularly: ``piv.zero_pad`` false in its parameters and not swept."""
    try:
        piv = json.loads(study.attrs.get("parameters", "{}")).get("piv", {})
    except (TypeError, ValueError):
        return False
    swept = any(str(study[d].attrs.get("sweep_key", d)) == "piv.zero_pad" for d in study.dims)
    return not swept and not bool(piv.get("zero_pad", False))


def _flag_rows(study: xr.Dataset) -> pd.DataFrame:
    """The computed cases' ``unresolved_*`` scores and ``filter_rms_total_mm`` (those the study has), one row a
    case: what :func:`_unresolved_verdict` reads."""
    cols = [c for c in (*_FLAG_SCORES, "filter_rms_total_mm") if c in study]
    if not cols:
        return pd.DataFrame()
    extra = ["computed"] if "computed" in study else []
    df = study[cols + extra].to_dataframe().reset_index()
    return df[df["computed"].astype(bool)] if extra else df


def _uncertainty_blocks(
    study: xr.Dataset, case_dirs: Mapping[str, CaseFiles], names: Mapping[str, str] | None = None
) -> Iterator[Block]:
    """Per design and flow: the metric table's ``uncertainty`` metrics (coverage, RMS ratio per
    component) with the verdict in words, and the binned RMS error against the predicted σ, pooled over
    each design's cases."""
    from lfstudy.study import figures as rf
    from lfstudy.study.designs import design_label

    cols = [c for c in mt.names("uncertainty") if c in study and bool(study[c].notnull().any())]
    if not cols:
        yield Block(
            "uncertainty",
            "none",
            note="Uncertainty: not available (no computed case has a PIV result with per-vector uncertainties "
            "unc_*: piv.uncertainty none, or results computed before they existed).",
        )
        return

    def rows(ds: xr.Dataset) -> pd.DataFrame:
        extra = [v for v in ("computed", "case_id") if v in ds]
        df = ds[cols + extra].to_dataframe().reset_index()
        if "computed" in df:
            df = df[df["computed"].astype(bool)].drop(columns="computed")
        dims = [str(d) for d in ds.dims]
        df.insert(
            0, "design", [(names or {}).get(lab, lab) for lab in (design_label(r, dims) for _, r in df.iterrows())]
        )
        return df

    df = rows(study)  # every case: the error-against-σ curves pool each design's seeds
    show = [c for c in ("design", "flow", *cols) if c in df]
    shown = df[show]
    if replicate_dim(study) is not None:
        stats = replicate_stats(study)
        shown = _spread_text(_spread_of(rows(stats.mean)[show], rows(stats.sd)[show], cols))
    yield Block(
        "uncertainty",
        "table",
        html="<p>How well the PIV's per-vector standard uncertainty σ (<code>unc_u_mm</code>, ... in "
        "<code>piv.zarr</code>) measures its actual error against the known flow, over the valid vectors: the "
        "<i>coverage</i> is the fraction with |error| ≤ σ (0.68 for a right σ and Gaussian errors), the "
        "<i>ratio</i> RMS(error) / RMS(σ) (1 for a right σ; above 1 σ is too small). z, the depth, is measured "
        "through the parallax of the sub-apertures and has a σ of its own scale."
        + _replicates_note(study)
        + "</p>"
        + (
            f'<p class="verdict"><b>{html.escape(v)}</b></p>'
            if (v := _uncertainty_verdict(df, _circular(study)))
            else ""
        )
        + (f'<p class="verdict">{html.escape(v)}</p>' if (v := _unresolved_verdict(_flag_rows(study))) else "")
        + _table(shown.sort_values(["design", "flow"] if "flow" in df else ["design"]), index=False),
    )
    groups: dict[str, list[str]] = {}
    if "case_id" in df:
        for label, cid in zip(df["design"], df["case_id"]):
            if cid and str(cid) in case_dirs:
                groups.setdefault(str(label), []).append(str(cid))
    pooled = len(groups) > MAX_UNCERTAINTY_LINES
    if pooled:
        groups = {"all designs": [c for ids in groups.values() for c in ids]}
    curves = _uncertainty_curves(groups, case_dirs)
    if not any(len(b["count"]) for per_axis in curves.values() for b in per_axis.values()):
        yield _na(
            "uncertainty",
            "error_vs_sigma",
            "Error against the predicted uncertainty",
            "no case's errors store on disk holds errors with their σ",
        )
        return
    yield _try(
        "uncertainty",
        "error_vs_sigma",
        "RMS error against the predicted σ in bins of σ (about equal counts), valid vectors of "
        + ("all cases pooled" if pooled else "each design's cases pooled (all flows)")
        + "; dashed: 1:1, where σ is right. Above the line σ is too small, below too large.",
        "error against uncertainty",
        lambda: rf.error_vs_uncertainty(curves),
    )


def _case_error_sigma(files: CaseFiles) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per axis, a case's per-vector error and σ [mm] from its errors store (σ from ``piv.zarr``
    where an errors store written before the per-vector σ lacks it)."""
    from lfstudy.study.metrics import AXES

    err = _open(files, "errors.zarr")
    piv = None
    out = {}
    for ax, c in AXES.items():
        if f"{c}_err_mm" not in err:
            continue
        if f"unc_{c}_mm" in err:
            sigma = err[f"unc_{c}_mm"]
        else:
            piv = _open(files, "piv.zarr") if piv is None else piv
            if f"unc_{c}_mm" not in piv:
                continue
            sigma = piv[f"unc_{c}_mm"]
        e = err[f"{c}_err_mm"]
        out[ax] = (np.asarray(e.values, float).ravel(), np.asarray(sigma.transpose(*e.dims).values, float).ravel())
    return out


def _uncertainty_curves(
    groups: Mapping[str, Sequence[str]], case_dirs: Mapping[str, CaseFiles]
) -> dict[str, dict[str, dict[str, np.ndarray]]]:
    """Per group (design) and axis, :func:`~lfstudy.study.metrics.binned_uncertainty` of its cases'
    pooled errors and σ; a case without files is left out."""
    from lfstudy.study.metrics import binned_uncertainty

    curves: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for label, ids in groups.items():
        pooled: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        for cid in ids:
            try:
                per_axis = _case_error_sigma(case_dirs[cid])
            except (OSError, FileNotFoundError, KeyError, ValueError):
                continue
            for ax, pair in per_axis.items():
                pooled.setdefault(ax, []).append(pair)
        curves[label] = {
            ax: binned_uncertainty(np.concatenate([e for e, _ in v]), np.concatenate([s for _, s in v]))
            for ax, v in pooled.items()
        }
    return curves


def _thesis_blocks(
    study: xr.Dataset, cfg: Mapping[str, Any], names: Mapping[str, str] | None = None
) -> Iterator[Block]:
    from lfstudy.study.designs import design_label

    rows = []
    for flow in study["flow"].values if "flow" in study.dims else []:
        spec = cfg.get("flows", {}).get(str(flow), {})
        if spec.get("kind") != "uniform":
            continue
        d = np.asarray(spec["displacement"], float)
        ax = "xyz"[int(np.argmax(np.abs(d)))]
        ref = THESIS_REFERENCE.get(ax)
        cols = [f"mean_{ax}", f"true_{ax}", f"bias_{ax}", f"std_{ax}", f"mean_{ax}_mm", f"true_{ax}_mm"]
        sub = case_table(study.sel(flow=[flow]), cols)
        if replicate_dim(study) is not None:  # the mean over the seeds ± their sd, as text
            sub = pd.DataFrame(
                {c: [pm(m, v) for m, v in zip(sub[c], sub[f"{c}_sd"])] for c in cols if c in sub}, index=sub.index
            )
        for idx, r in sub.iterrows():
            p = dict(zip(sub.index.names, idx))
            rows.append(
                {
                    "flow": flow,
                    "axis": ax,
                    "design": (names or {}).get(lab := design_label(p, list(p)), lab),
                    "true [mm]": r.get(f"true_{ax}_mm"),
                    "mean [mm]": r.get(f"mean_{ax}_mm"),
                    "true [vox]": r.get(f"true_{ax}"),
                    "mean [vox]": r.get(f"mean_{ax}"),
                    "σ [vox]": r.get(f"std_{ax}"),
                    "thesis μ [px]": ref["mean"] if ref else math.nan,
                    "thesis σ [px]": ref["std"] if ref else math.nan,
                }
            )
    if not rows:
        yield Block(
            "thesis",
            "uniform",
            note="Uniform-displacement comparison: not available (no uniform flow among the computed cases).",
        )
        return
    yield Block(
        "thesis",
        "uniform",
        html=(
            "<p>Mean and standard deviation of the measured displacement beside the thesis' histograms ("
            + "; ".join(html.escape(v["where"]) for v in THESIS_REFERENCE.values())
            + "). The thesis reports image-frame signs (μ negative) in its own voxels (a lenslet in x, y; a "
            "refocus plane in z); ours are object-frame, in the voxels of the reconstruction grid and in mm."
            + _replicates_note(study)
            + "</p>"
            + _table(pd.DataFrame(rows), index=False)
        ),
    )


def _representative_blocks(
    study: xr.Dataset, case_dirs: Mapping[str, CaseFiles], cfg: Mapping[str, Any] | None = None
) -> Iterator[Block]:
    from lfstudy.study import figures as rf

    found = _representative(study, case_dirs, cfg)
    if found is None:
        yield Block("representative", "none", note="Representative case: not available (no case files).")
        return
    rep, why = found
    d = case_dirs[rep]
    yield Block(
        "representative",
        "id",
        html=f"<p>Case <code>{html.escape(rep)}</code>: {html.escape(why)}.</p>",
    )
    yield _try(
        "representative",
        "raw",
        "Central crop of the raw plenoptic image, frame a.",
        "raw image",
        lambda: rf.raw_crop(_open(d, "raw_a.zarr", "")),
    )
    yield _try(
        "representative",
        "refocused",
        "Refocused planes of frame a over the depth.",
        "refocused planes",
        lambda: rf.refocused_planes(_open(d, "stack_a.zarr", "")),
    )


def _legend_blocks(study: xr.Dataset) -> Iterator[Block]:
    """What every column of study.csv holds: name, units, meaning (the variables' attrs, which the
    metric table sets) and, for a metric, which way is better."""
    known = {m.name: m for m in mt.METRICS}
    rows = [{"column": "case_id", "units": "", "meaning": "results sub-path of the case", "better": ""}]
    rdim = replicate_dim(study)
    for d in study.dims:
        c = study[d]
        rows.append(
            {
                "column": str(d),
                "units": c.attrs.get("units", ""),
                "meaning": f"swept: {c.attrs.get('long_name', d)}"
                + (" (the replicates: the report shows the mean over them ± their spread)" if d == rdim else ""),
                "better": "",
            }
        )
    for name, v in study.data_vars.items():
        if name in ("computed", "case_id"):
            continue
        m = known.get(str(name))
        rows.append(
            {
                "column": str(name),
                "units": v.attrs.get("units", ""),
                "meaning": v.attrs.get("long_name", ""),
                "better": m.better if m else "",
            }
        )
    yield Block("legend", "columns", html=_table(pd.DataFrame(rows), index=False))


def _truncated(n: int, max_cases: int) -> Iterator[Block]:
    if n > max_cases:
        yield Block(
            "cases",
            "truncated",
            note=f"Per-case figures drawn for the first {max_cases} of {n} cases; every case is in the tables above.",
        )


def _case_blocks(
    study: xr.Dataset, case_dirs: Mapping[str, CaseFiles], cfg: Mapping[str, Any], *, max_cases: int, progress: bool
) -> Iterator[Block]:
    from tqdm.auto import tqdm

    k = _threshold_k(cfg)
    items = list(case_dirs.items())
    yield from _truncated(len(items), max_cases)
    for cid, d in tqdm(items[:max_cases], desc="report: cases", unit="case", disable=not progress):
        yield from _one_case_blocks(cid, d, k)


def _threshold_k(cfg: Mapping[str, Any]) -> float:
    return float(cfg.get("reconstruct", {}).get("threshold", {}).get("k", 3.0))


def _one_case_blocks(cid: str, d: CaseFiles, k: float) -> Iterator[Block]:
    """The per-case blocks of case ``cid`` (its files ``d``; ``k`` the threshold's σ factor of the histogram)."""
    from lfstudy.study import figures as rf

    if not _exists(d):
        yield _na("cases", "dir", "Case files", "missing", case=cid)
        return
    try:
        piv = _open(d, "piv.zarr").load()
    except Exception as exc:
        piv = None
        yield _na("cases", "piv", "PIV result", f"{type(exc).__name__}: {exc}"[:200], case=cid)
    try:
        err = _open(d, "errors.zarr").load()
    except Exception:
        err = None
    if piv is not None:
        yield from piv_figure_blocks("cases", piv, err, case=cid)
        yield _try(
            "cases",
            "error_map",
            "Middle x–y slice: the measured vectors beside the error magnitude against the known flow.",
            "vector and error slice",
            lambda piv=piv, err=err: rf.vector_error_slice(piv, err),
            case=cid,
        )
    yield _try(
        "cases",
        "intensity",
        f"Focal-stack intensities, threshold mean + {k:g}σ (Figs 5.17, 7.13–7.14).",
        "intensity histogram",
        lambda d=d: rf.intensity_histogram(np.asarray(_open(d, "stack_a.zarr", "").values), k=k),
        case=cid,
    )


def _rendered_case_blocks(cid: str, d: CaseFiles, k: float) -> list[Block]:
    """:func:`_one_case_blocks` with each figure drawn into its HTML (``Block.rendered``): a worker's task."""
    out = []
    for b in _one_case_blocks(cid, d, k):
        if b.figure is not None:
            b.rendered = _render(b)
            b.figure = None
        out.append(b)
    return out


def _pooled_case_blocks(
    case_dirs: Mapping[str, CaseFiles], cfg: Mapping[str, Any], *, max_cases: int, progress: bool, workers: int
) -> Iterator[Block]:
    """:func:`_case_blocks`, each case drawn by one of ``workers`` processes: submitted here (so the pool draws them
    while the caller builds the report's other sections), yielded in case order, rendered. The processes fork
    from a server that imported this module once (``forkserver``: no copy of the caller's threads; ``spawn``
    where there is none)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from tqdm.auto import tqdm

    items = list(case_dirs.items())
    k = _threshold_k(cfg)
    if "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload([__name__])
    else:  # Windows: each process imports this module itself
        ctx = mp.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=min(workers, len(items[:max_cases])), mp_context=ctx)
    futures = [pool.submit(_rendered_case_blocks, cid, d, k) for cid, d in items[:max_cases]]

    def collect() -> Iterator[Block]:
        try:
            yield from _truncated(len(items), max_cases)
            for f in tqdm(futures, desc="report: cases", unit="case", disable=not progress):
                yield from f.result()
        finally:
            pool.shutdown(cancel_futures=True)

    return collect()


# ------------------------------------------------------------------ output
_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;
max-width:1250px;color:#222;line-height:1.4;padding:0 1em}
h1{border-bottom:2px solid #345}h2{border-bottom:1px solid #ccc;margin-top:2em;color:#234}
nav ul{columns:2}figure{margin:1em 0}figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.9em;color:#555}.note{color:#a40;font-style:italic}
table.tbl{border-collapse:collapse;font-size:.8em;margin:.5em 0;max-width:100%}
table.tbl td,table.tbl th{border:1px solid #ddd;padding:2px 5px;text-align:right;overflow-wrap:break-word}
table.tbl td:first-child,table.tbl th:first-child{text-align:left}table.tbl.summary{font-size:.88em}
details table.tbl{font-size:.74em}details table.tbl td,details table.tbl th{padding:1px 3px}
table.tbl th{background:#f2f4f7}details{margin:.4em 0;border:1px solid #e4e4e4;padding:.3em .6em}
summary{cursor:pointer}code{background:#f4f4f4;padding:0 3px}
.verdict{background:#f5f7fa;border-left:3px solid #345;padding:.4em .8em}h3{color:#234;margin-top:1.6em}
.scroll{overflow-x:auto;max-width:100%}
"""


def _render(b: Block) -> str:
    if b.rendered:
        return b.rendered
    if b.figure is not None:
        data = base64.b64encode(_png(b.figure)).decode("ascii")
        alt = html.escape(b.caption or b.name)
        return (
            f'<figure><img alt="{alt}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(b.caption)}</figcaption></figure>"
        )
    if b.html:
        return f'<div class="scroll">{b.html}</div>'
    return f'<p class="note">{html.escape(b.note)}</p>'


def write_report(
    study: xr.Dataset,
    case_dirs: Mapping[str, CaseFiles],
    cfg: Mapping[str, Any],
    out_html: Path,
    *,
    max_cases: int = 50,
    progress: bool = True,
    workers: int = 1,
) -> Path:
    """Write the self-contained HTML report of a study (atomically).

    Parameters
    ----------
    study : xarray.Dataset
        Output of :func:`lfstudy.study.metrics.combine_cases` (dims = swept parameters).
    case_dirs : mapping case id -> directory or {file name: path}
        Per-case result directories; missing artefacts are reported as "not
        available".
    cfg : mapping
        The validated study config (camera, flows, refocus, reconstruct).
    out_html : Path
        Output file; written via a temporary sibling and renamed.
    max_cases : int
        At most this many per-case sections with figures.
    progress : bool
        tqdm progress bar over the per-case figures.
    workers : int
        Processes drawing the per-case figures (:func:`report_blocks`); the page is the same whatever their number.

    Returns
    -------
    Path
        ``out_html``.
    """
    from lfstudy import __version__

    name = str(cfg.get("name", "study"))
    ver = html.escape(str(study.attrs.get("lfstudy_version", __version__)))
    blocks = report_blocks(study, case_dirs, cfg, max_cases=max_cases, progress=progress, workers=workers)
    intro = (
        f"Generated {time.strftime('%Y-%m-%d %H:%M')} by lfstudy {ver}. Method: Lynch (2011), "
        "Development of a 3-D Fluid Velocimetry Technique based on Light Field Imaging."
    )
    return write_html(
        blocks,
        report_sections(study),
        f"lfstudy report: {name}",
        f"Light-field PIV study <code>{html.escape(name)}</code>",
        intro,
        out_html,
    )


def write_html(
    blocks: Iterable[Block],
    sections: Mapping[str, str],
    title: str,
    heading: str,
    intro: str,
    out_html: Path,
) -> Path:
    """Write report blocks as one self-contained HTML page (atomically).

    Parameters
    ----------
    blocks : iterable of Block
        In order; a block with ``case`` set goes into a collapsible group of that
        name at the end of its section.
    sections : mapping
        Section id → title, in page order (with a table of contents).
    title : str
        The page title (plain text).
    heading : str
        The page heading (trusted HTML).
    intro : str
        The paragraph under the heading (plain text).
    out_html : Path
        Output file; written via a temporary sibling and renamed.

    Returns
    -------
    Path
        ``out_html``.
    """
    parts: dict[str, list[str]] = {s: [] for s in sections}
    per_case: dict[tuple[str, str], list[str]] = {}
    titles: dict[tuple[str, str], str] = {}
    for b in blocks:
        frag = _render(b)
        b.figure = None  # free the figure before the next is drawn
        if b.case is not None:
            per_case.setdefault((b.section, b.case), []).append(frag)
            titles.setdefault((b.section, b.case), b.title or b.case)
        else:
            parts[b.section].append(frag)
    for (section, cid), frags in per_case.items():
        head = titles[(section, cid)]
        head = html.escape(head) + (f" <code>{html.escape(cid)}</code>" if head != cid else "")
        parts[section].append(f"<details><summary>{head}</summary>{''.join(frags)}</details>")
    toc = "".join(f'<li><a href="#{s}">{html.escape(t)}</a></li>' for s, t in sections.items())
    body = "".join(
        f'<section id="{s}"><h2>{html.escape(sections[s])}</h2>{"".join(parts[s])}</section>' for s in sections
    )
    doc = (
        f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f'<meta name="viewport" content="width=device-width,initial-scale=1">'
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>"
        f"<h1>{heading}</h1><p>{html.escape(intro)}</p>"
        f"<nav><ul>{toc}</ul></nav>{body}</body></html>"
    )
    out_html = Path(out_html)
    with io.atomic_path(out_html) as tmp:
        tmp.write_text(doc, encoding="utf-8")
    return out_html


def write_figures(
    study: xr.Dataset,
    case_dirs: Mapping[str, CaseFiles],
    cfg: Mapping[str, Any],
    out_dir: Path,
    *,
    max_cases: int = 50,
    progress: bool = True,
) -> list[Path]:
    """Write every report figure as a separate PNG (for Snakemake's ``report(...)``).

    Files are named ``<section>_<name>.png`` (per-case figures
    ``cases_<case id with / as __>_<name>.png``); tables and "not available"
    notes have no file. Each file is written atomically.

    Returns
    -------
    list of Path
        The files written, in report order.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for b in report_blocks(study, case_dirs, cfg, max_cases=max_cases, progress=progress):
        if b.figure is None:
            continue
        stem = f"{b.section}_{_safe(b.case) + '_' if b.case else ''}{b.name}"
        path = out_dir / f"{stem}.png"
        data = _png(b.figure)
        b.figure = None
        with io.atomic_path(path) as tmp:
            tmp.write_bytes(data)
        paths.append(path)
    return paths
