"""The study (thesis ch. 7): errors against the truth, the sweep table and the report.

Modules: :mod:`~lfstudy.study.config` (the study config: validated with every
swept case, each case's and stage's config; its schema in
:mod:`~lfstudy.study.schema`), :mod:`~lfstudy.study.sweep` (the sweep table:
settings, cases, where each stage's outputs live), :mod:`~lfstudy.study.case` (one case's config → its
science: the layer the workflow, the CLI and notebooks share),
:mod:`~lfstudy.study.metrics` (per-case errors, Q), :mod:`~lfstudy.study.metric_table` (every
metric's units, long name, better direction and where it is shown), :mod:`~lfstudy.study.table`
(the study Dataset and CSV), :mod:`~lfstudy.study.tolerance` (the error against each swept imperfection,
the worst case over them), :mod:`~lfstudy.study.report` and
:mod:`~lfstudy.study.figures` (the HTML report). The report (matplotlib) is imported on first use, so the
per-case stages that only need the metrics start fast.
"""

from __future__ import annotations

from typing import Any

from lfstudy.study.case import derive_seed, render_volume, simulate_case
from lfstudy.study.metric_table import METRICS, Metric, metric, shown_in
from lfstudy.study.metrics import (
    AXES,
    case_errors,
    case_metrics,
    error_statistics,
    locking_excess,
    peak_locking_c1,
    reconstruction_quality,
    render_truth,
)
from lfstudy.study.sweep import NAMED, Case, Setting, Sweep
from lfstudy.study.table import combine_cases, from_csv, stage_times, to_csv

_REPORT = ("write_report", "write_figures", "report_blocks", "best_designs", "case_table")

__all__ = [
    "simulate_case",
    "render_volume",
    "derive_seed",
    "AXES",
    "METRICS",
    "Metric",
    "metric",
    "shown_in",
    "case_errors",
    "case_metrics",
    "error_statistics",
    "peak_locking_c1",
    "locking_excess",
    "reconstruction_quality",
    "stage_times",
    "combine_cases",
    "to_csv",
    "from_csv",
    "render_truth",
    "Sweep",
    "Setting",
    "Case",
    "NAMED",
    *_REPORT,
]


def __getattr__(name: str) -> Any:  # PEP 562: the report's names load matplotlib lazily
    if name in _REPORT:
        from lfstudy.study import report

        return getattr(report, name)
    raise AttributeError(f"module 'lfstudy.study' has no attribute {name!r}")
