"""The report of a processed recording: one self-contained HTML file.

The study report's building blocks (:mod:`lfstudy.study.report`: blocks, the
HTML page; :mod:`lfstudy.study.figures`: the figures) without its truth-based
parts: no errors against a known flow and no reconstruction quality Q, but
what a measurement can say about itself (:mod:`lfstudy.process.metrics`),
with maps and histograms of the per-vector standard uncertainty σ.
"""

from __future__ import annotations

import html
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from lfstudy import io
from lfstudy.process.recording import Recording, frame_dir
from lfstudy.process.uncertainty_calibration import calibration_note
from lfstudy.study import figures as rf
from lfstudy.study.report import Block, _table, _try, piv_figure_blocks, write_html

__all__ = ["SECTIONS", "METRICS", "write_process_report", "volcal_block"]

#: Section ids and titles, in report order.
SECTIONS: dict[str, str] = {
    "metrics": "Measurement metrics",
    "recording": "Recording and calibration",
    "pairs": "Per-pair results",
    "legend": "Metrics table columns",
}

#: The metrics of the table and of the time-series figure, in order.
METRICS = (
    "valid_percent",
    "empty_percent",
    "peak_ratio_median",
    "peak_median",
    "mean_u",
    "mean_v",
    "mean_w",
    "std_u",
    "std_v",
    "std_w",
    "unc_median_u",
    "unc_median_v",
    "unc_median_w",
    "divergence_rms",
    "divergence_norm",
    "saturated_percent",
    "n_vectors",
    "piv_seconds",
)


def _metric_blocks(table: xr.Dataset, dim: str) -> Iterator[Block]:
    cols = [c for c in METRICS if c in table]
    df = table[cols].to_dataframe()[cols]
    for c in ("frame_b", "frame_a"):  # inserted in front: frame_a first
        if c in table.coords:
            df.insert(0, c, table[c].values)
    yield Block(
        "metrics",
        "table",
        html=_table(df.reset_index()[[dim, *df.columns]], index=False),
    )
    if table.sizes[dim] > 1:
        yield _try(
            "metrics",
            "series",
            f"Metrics per pair along {dim}.",
            "metrics per pair",
            lambda: rf.series_metrics(table, [c for c in cols if c not in ("n_vectors", "piv_seconds")], dim),
        )


def _recording_blocks(root: Path, rec: Recording, cfg: Mapping[str, Any]) -> Iterator[Block]:
    from lfstudy.study.case import case_camera

    cam = case_camera(cfg)
    facts = {**rec.summary(), **{f"camera {k}": v for k, v in cam.summary().items()}}
    facts["reconstruction"] = cfg["reconstruct"]["method"]
    facts["PIV window, spacing, levels"] = f"{cfg['piv']['window']}, {cfg['piv']['spacing']}, {cfg['piv']['levels']}"
    df = pd.DataFrame({"value": [str(v) for v in facts.values()]}, index=list(facts))
    yield Block("recording", "facts", html=_table(df))
    try:
        c = io.open_zarr(root / "centers.zarr").attrs
        cal = pd.DataFrame(
            {
                "value": [
                    f"{int(c['n_valid'])}",
                    f"{float(c['pitch_x_px']):.4f} x {float(c['pitch_y_px']):.4f}",
                    f"{float(c['rotation']):.3e}",
                    f"({float(c['offset_x_px']):.3f}, {float(c['offset_y_px']):.3f})",
                    f"{float(c['lattice_rms_px']):.4f}",
                    str(c.get("estimator", "")),
                ]
            },
            index=[
                "valid lenslet centres",
                "spot pitch x, y [px]",
                "lattice rotation [rad]",
                "lattice offset [px]",
                "lattice residual [px RMS]",
                "spot estimator",
            ],
        )
        yield Block("recording", "calibration", html=_table(cal))
    except (OSError, ValueError, KeyError) as exc:
        yield Block("recording", "calibration", note=f"Calibration: not available ({exc}).")
    vc = volcal_block(root)
    if vc is not None:
        yield vc
    yield _try(
        "recording",
        "calibration_image",
        f"Calibration image ({rec.calibration_kind}), central crop" + (", mean dark subtracted" if rec.dark else ""),
        "calibration image",
        lambda: rf.raw_crop(io.open_zarr(root / "calibration.zarr", name="intensity")),
    )


def volcal_block(root: Path) -> Block | None:
    """The volumetric calibration's facts (``volcal.zarr``: Hall et al. 2018), or None without one."""
    path = Path(root) / "volcal.zarr"
    if not path.exists():
        return None
    a = io.open_zarr(path).attrs
    held = (
        f"{float(a['holdout_rms_lenslets']):.4f} at z = {float(a['holdout_depth']):.4g} mm"
        if np.isfinite(float(a["holdout_rms_lenslets"]))
        else "–"
    )
    depths = ", ".join(f"{float(z):.4g}" for z in a["depths"])
    facts = {
        "volumetric calibration: dot-target depths [mm]": f"{len(a['depths'])}: {depths}",
        "volumetric calibration: dot spacing [mm], dots per image": f"{float(a['spacing']):.4g}, {int(a['n_dots'])}",
        "volumetric calibration: order, calibrated sub-apertures": f"{int(a['order'])}, {int(a['valid_subapertures'])}",
        "volumetric calibration: fit residual [lenslets RMS]": f"{float(a['fit_rms_lenslets']):.4f}",
        "volumetric calibration: held-out depth error [lenslets RMS]": held,
    }
    df = pd.DataFrame({"value": list(facts.values())}, index=list(facts))
    return Block("recording", "volcal", html=_table(df))


def _pair_blocks(
    root: Path, rec: Recording, piv: xr.Dataset, cfg: Mapping[str, Any], max_pairs: int
) -> Iterator[Block]:
    dim = rec.pair_dim
    k_thr = float(cfg["reconstruct"].get("threshold", {}).get("k", 3.0))
    n = piv.sizes[dim]
    if n > max_pairs:
        yield Block("pairs", "truncated", note=f"Figures for the first {max_pairs} of {n} pairs; all are in the table.")
    for p in range(min(n, max_pairs)):
        i, j = rec.pairs[p]
        name = f"pair {p + 1}: {rec.frames[i].label} → {rec.frames[j].label}"
        one = piv.isel({dim: p}).load()
        if "corrector_rms" in one:
            one = one.dropna("pass", subset=["corrector_rms"])
        yield from piv_figure_blocks("pairs", one, case=name)
        if any(f"unc_{c}" in one for c in ("u", "v", "w")):  # a result with per-vector uncertainty
            yield _try(
                "pairs",
                "uncertainty_maps",
                "Standard uncertainty σ of each component per vector, middle x–y slice (colour scales over the "
                "whole field); blank: invalid or replaced vector. Red crosses: vectors flagged unresolved, "
                "where the measured field's curvature says the final window's averaging of the flow likely "
                "exceeds σ (with piv.unresolved_significance: by more than the vectors' own errors could put "
                "there; σ covers the random error of what a window measures, not that averaging). Grey dots: "
                "windows partly outside the seeded region (they measure their seeded part, not the box about "
                "their centre; never flagged unresolved). "
                f"{calibration_note(piv.attrs)}",
                "uncertainty maps",
                lambda one=one: rf.uncertainty_maps(one),
                case=name,
            )
            yield _try(
                "pairs",
                "uncertainty_histograms",
                "Standard uncertainty σ per component over the valid vectors; dashed: the median (the metrics "
                "table's unc_median_*).",
                "uncertainty histograms",
                lambda one=one: rf.uncertainty_histograms(one),
                case=name,
            )
        stack = root / frame_dir(i) / "stack.zarr"
        yield _try(
            "pairs",
            "planes",
            f"Refocused planes of {rec.frames[i].label} (cf. Figs 5.12–5.16).",
            "refocused planes",
            lambda stack=stack: rf.refocused_planes(io.open_array(stack)),
            case=name,
        )
        yield _try(
            "pairs",
            "intensity",
            f"Focal-stack intensities of {rec.frames[i].label}, threshold mean + {k_thr:g}σ (Fig. 5.17).",
            "intensity histogram",
            lambda stack=stack: rf.intensity_histogram(np.asarray(io.open_array(stack).values), k=k_thr),
            case=name,
        )


def _legend_blocks(table: xr.Dataset) -> Iterator[Block]:
    rows = [
        {
            "column": c,
            "meaning": table[c].attrs.get("long_name", "")
            + (f": {table[c].attrs['description']}" if table[c].attrs.get("description") else ""),
            "units": table[c].attrs.get("units", ""),
        }
        for c in table.data_vars
    ]
    yield Block("legend", "columns", html=_table(pd.DataFrame(rows), index=False))


def write_process_report(
    root: str | Path, cfg: Mapping[str, Any], rec: Recording, out_html: str | Path, *, max_pairs: int = 20
) -> Path:
    """Write the HTML report of a processed recording.

    Parameters
    ----------
    root : path
        The processed recording's directory (``piv.zarr``, ``metrics.zarr``, …).
    cfg : mapping
        Its validated recording config.
    rec : Recording
        Its recording (:func:`lfstudy.process.recording.open_recording`).
    out_html : path
        Output file, written atomically.
    max_pairs : int
        Per-pair figures for at most this many pairs.
    """
    from lfstudy import __version__

    root = Path(root)
    table = io.open_zarr(root / "metrics.zarr").load()
    piv = io.open_zarr(root / "piv.zarr")
    dim = rec.pair_dim

    def blocks() -> Iterator[Block]:
        yield from _metric_blocks(table, dim)
        yield from _recording_blocks(root, rec, cfg)
        yield from _pair_blocks(root, rec, piv, cfg, max_pairs)
        yield from _legend_blocks(table)

    name = str(cfg.get("name", "recording"))
    intro = (
        f"Generated {time.strftime('%Y-%m-%d %H:%M')} by lfstudy {__version__} from {len(rec.frames)} recorded "
        f"frames ({len(rec.pairs)} {'pairs of a time series' if rec.series else 'pairs'}). No flow is known: "
        "the metrics are what a measurement says about itself (valid vectors, correlation-peak ratio, divergence, "
        "the per-vector standard uncertainty). "
        "Method: Lynch (2011), Development of a 3-D Fluid Velocimetry Technique based on Light Field Imaging."
    )
    heading = f"Light-field PIV of the recording <code>{html.escape(name)}</code>"
    return write_html(blocks(), SECTIONS, f"lfstudy recording: {name}", heading, intro, Path(out_html))
