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
:mod:`~lfstudy.study.figures` (the HTML report). Each name imports its module on first use,
so the per-case stages start without the metrics and the report.
"""

from __future__ import annotations

import importlib
from typing import Any

# Every name loads its module on first use (PEP 562): a per-case job imports lfstudy.study.case, and with it this
# package, without the metrics' and the report's imports (scipy.special, matplotlib: ~0.3 s of every job's
# start-up on the demo, before this).
_NAMES = {
    "case": ("simulate_case", "render_volume", "derive_seed"),
    "metric_table": ("METRICS", "Metric", "metric", "shown_in"),
    "metrics": (
        "AXES",
        "case_errors",
        "case_metrics",
        "error_statistics",
        "locking_excess",
        "peak_locking_c1",
        "reconstruction_quality",
        "render_truth",
    ),
    "sweep": ("NAMED", "Case", "Setting", "Sweep"),
    "table": ("combine_cases", "from_csv", "stage_times", "to_csv"),
    "report": ("write_report", "write_figures", "report_blocks", "best_designs", "case_table"),
}
_MODULE = {name: mod for mod, names in _NAMES.items() for name in names}

__all__ = [name for names in _NAMES.values() for name in names]


def __getattr__(name: str) -> Any:
    if name in _MODULE:
        value = getattr(importlib.import_module(f"lfstudy.study.{_MODULE[name]}"), name)
        globals()[name] = value  # the next lookup is a plain attribute
        return value
    raise AttributeError(f"module 'lfstudy.study' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
