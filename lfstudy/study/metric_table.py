"""The one table of the study's per-case metrics: what each is, and where it is shown.

Every scalar a case's errors store holds (:func:`lfstudy.study.metrics.case_metrics`) has a row
here: its name, units, long name, whether lower is better, and the places of the report and of the
design comparison it appears in. Everything else reads this table at call time:

- the variables' attrs in ``errors.zarr`` and in the study (:func:`lfstudy.study.table.combine_cases`),
  and so the report's legend of the ``study.csv`` columns;
- the leading columns of the study table (place ``summary``);
- the report's case tables, panels and overview map (``headline``, ``panel``, ``overview``);
- the best-design rows (``criterion``), the Pareto objectives (``pareto``) and the report's
  Pareto-front, resolution and error-budget tables (``front``, ``resolution``, ``budget``);
- the report's uncertainty table (``uncertainty``).

Three name prefixes carry a meaning of their own: ``oracle_<stat>`` is the statistic ``<stat>`` of
:func:`~lfstudy.study.metrics.case_errors` on the *oracle* (the case's PIV run on the true particle
volumes, :func:`lfstudy.study.case.oracle_piv`), ``recon_added_<stat>`` is the share of the
case's ``<stat>`` the oracle does not explain, sqrt(max(case² − oracle², 0)), and ``rest_<stat>`` the
oracle's beyond the windows' filtering ``filter_<stat>``, sqrt(max(oracle² − filter², 0))
(:func:`lfstudy.study.metrics.error_budget`). A row with any of them needs no code of its own.

Adding a metric is one :class:`Metric` row plus the code that computes its value
(``docs/howto/add-metric.md``). Like xclim's indicators, units and long names are declared once
and every output's attrs come from that declaration.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["PLACES", "Metric", "METRICS", "metric", "shown_in", "names", "metric_attrs", "objectives"]

#: Where a metric can be shown, and what that means.
PLACES: dict[str, str] = {
    "summary": "leads the study table's variables (and study.csv's columns after the settings)",
    "headline": "a column of the report's case tables (mean over the other settings; all computed cases)",
    "panel": "a panel of the report's figures against each swept setting",
    "overview": "the report's overview map (the first of these the study holds)",
    "criterion": "a row of the best-design table: the case that does best on it, per flow",
    "pareto": "an objective of the Pareto front the recommendation is chosen from",
    "front": "a column of the report's Pareto-front table (and of the design table)",
    "resolution": "a column of the report's resolution and field-of-view table (and of the design table)",
    "budget": "a column of the report's error-budget table: per design, what the PIV windows give on the true "
    "particles (the oracle) beside what the reconstruction adds (and of the design table)",
    "tolerance": "a column of the report's tolerance tables and a panel of its tolerance figures: per design, "
    "against the level of each swept imperfection (with the oracle's oracle_<name> beside it where the study "
    "holds one)",
    "uncertainty": "a column of the report's uncertainty table: per design and flow, how well the PIV's per-vector "
    "standard uncertainty measures the error against the truth",
}


@dataclass(frozen=True)
class Metric:
    """One per-case metric: one row of :data:`METRICS`.

    Parameters
    ----------
    name : str
        Variable name in the errors store, the study and ``study.csv``.
    units : str
        CF-style units (``"mm"``, ``"voxel"``, ``"1"``, ``"percent"``, ``"s"``).
    long_name : str
        What it is, in a few words (the legend's meaning, the panels' titles).
    lower_is_better : bool or None
        ``True``/``False`` where designs are ranked on it; ``None`` where neither end is better
        (a signed bias, the depth gain, a count). Required for ``criterion`` and ``pareto``.
    shown : iterable of str
        Places of :data:`PLACES` it appears in (besides the study table and CSV, which hold every metric).
    group : str
        Kind of figure: ``error``, ``displacement``, ``resolution``, ``quality``, ``count``, ``cost``.
    description : str
        Longer explanation, stored as the ``description`` attribute.
    criterion : str
        Wording of its best-design row; default "lowest/highest <long name>".
    derive : callable, optional
        For a metric computed from others in a table (the best-design table): ``derive(table)``
        returns its column from the table's columns (a ``KeyError`` when one is missing).
    """

    name: str
    units: str
    long_name: str
    lower_is_better: bool | None = None
    shown: frozenset[str] = field(default_factory=frozenset)
    group: str = ""
    description: str = ""
    criterion: str = ""
    derive: Callable[[Any], Any] | None = None

    def __post_init__(self) -> None:
        shown = frozenset([self.shown] if isinstance(self.shown, str) else self.shown)
        object.__setattr__(self, "shown", shown)
        unknown = sorted(shown - set(PLACES))
        if unknown:
            raise ValueError(f"metric {self.name!r}: unknown place(s) {unknown}; places are {sorted(PLACES)}")
        if shown & {"criterion", "pareto"} and self.lower_is_better is None:
            raise ValueError(
                f"metric {self.name!r} ranks designs ({sorted(shown & {'criterion', 'pareto'})}): set lower_is_better"
            )

    @property
    def attrs(self) -> dict[str, str]:
        """The variable attributes: units, long name and (if any) description."""
        out = {"units": self.units, "long_name": self.long_name}
        if self.description:
            out["description"] = self.description
        return out

    @property
    def better(self) -> str:
        """``"lower"``, ``"higher"`` or ``""``."""
        return "" if self.lower_is_better is None else ("lower" if self.lower_is_better else "higher")

    @property
    def criterion_label(self) -> str:
        """The best-design row's wording."""
        return self.criterion or f"{'lowest' if self.lower_is_better else 'highest'} {self.long_name}"


def _bias_norm_mm(table: Any) -> Any:
    """|b| = sqrt(bx² + by² + bz²) [mm] from a table's per-axis biases."""
    return np.sqrt(sum(table[f"bias_{a}_mm"] ** 2 for a in "xyz"))


def _per_axis(
    name: str,
    units: str,
    long_name: str,
    *,
    axes: str = "xyz",
    shown: dict[str, Iterable[str]] | None = None,
    **kw: Any,
) -> tuple[Metric, ...]:
    """One metric per axis: ``name``, ``long_name`` and ``description`` hold ``{ax}``; ``shown`` maps an axis to
    its places."""
    shown = shown or {}
    desc = kw.pop("description", "")
    return tuple(
        Metric(
            name.format(ax=a),
            units,
            long_name.format(ax=a),
            shown=frozenset(shown.get(a, ())),
            description=desc.format(ax=a),
            **kw,
        )
        for a in axes
    )


_ORACLE = (
    "of the oracle: the case's PIV (same grid, windows and passes) run on the true particle volumes of both "
    "frames, each particle a Gaussian of piv.particle_sigma voxels (half a voxel), as the paired PIV renders the "
    "fitted particles; the best any particle reconstruction could hand to the "
    "PIV. No depth calibration applies to it (its volumes are true, w is read as is)"
)
_ADDED = (
    "error the reconstruction adds to what the PIV windows give on the true volumes: "
    "sqrt(max({case}² − {oracle}², 0)), assuming the two add in quadrature (independent errors); 0 where the "
    "case does as well as the oracle"
)
_FILTER = (
    "RMS over the valid vectors of the windows' filtering of the truth in {ax}: the true displacement averaged "
    "over each vector's final window (the top-hat WIDIM measures) minus the true displacement at its centre; 0 "
    "for a uniform flow, (L²/24) ∂²u/∂x² per axis for a smooth one (L the window length). The part of the "
    "oracle's error no estimator built from a window's own data can see"
)
_REST = (
    "error of the oracle beyond the windows' filtering, sqrt(max({oracle}² − {filter}², 0)): the random error "
    "plus the estimator's own bias. With the reconstruction's share the case's error splits in quadrature into "
    "filter² + recon_added² + rest²"
)
_CROSSTALK = (
    "uniform flows: mean spurious z displacement per unit of imposed lateral displacement, "
    "(mean measured w − true w) / |(true u, true v)| over valid vectors (after the depth calibration where "
    "it is enabled); NaN for a non-uniform flow or no lateral shift"
)

_LOCKING = (
    "fraction of measured displacements within 0.25 voxel of an integer minus that expected for Gaussian errors "
    "about the truth"
)

# The per-axis uncertainty metrics: in the report's uncertainty table, every axis.
_UNC_SHOWN = dict.fromkeys("xyz", ("uncertainty",))

#: Every per-case metric, in order: the ``summary`` ones lead the study table in this order, and every
#: report table and figure lists its metrics in this order.
METRICS: tuple[Metric, ...] = (
    # the answer: errors comparable across designs
    Metric(
        "rel_error", "1", "total RMS error / mean true displacement magnitude", True,
        {"summary", "headline", "panel", "overview", "criterion", "front"}, "error",
        criterion="lowest error / displacement",
    ),
    Metric(
        "rms_total_mm", "mm", "total RMS error (all components)", True,
        {"summary", "headline", "panel", "overview", "criterion", "pareto", "front", "budget", "tolerance"},
        "error", criterion="lowest total RMS error",
    ),
    Metric(
        "bias_norm_mm", "mm", "bias magnitude |b|", True, {"criterion"}, "error",
        criterion="lowest bias |b|", derive=_bias_norm_mm,
    ),
    Metric("bias_z_mm", "mm", "bias error z (mean of measured − true)", None, {"summary", "headline"}, "error"),
    Metric("rms_z_mm", "mm", "RMS error z", True, {"summary", "headline", "tolerance"}, "error"),
    Metric("rms_x_mm", "mm", "RMS error x", True, {"summary", "tolerance"}, "error"),
    Metric(
        "valid_percent", "percent", "valid vectors", False,
        {"summary", "headline", "panel", "criterion", "front", "budget", "tolerance"}, "quality",
        criterion="most valid vectors",
    ),
    Metric(
        "Q", "1", "reconstruction quality Q", False, {"summary", "headline", "panel", "criterion", "front"},
        "quality",
        description="normalised correlation of the reconstructed volume with the true particles as Gaussians of "
        "half the camera's resolution cell on the same grid (Elsinga et al. 2006; truth_sigma_mm in errors.zarr)",
    ),
    # the error budget: what the PIV windows give on the true volumes, what the reconstruction adds
    Metric(
        "oracle_rms_total_mm", "mm", "oracle total RMS error (PIV on the true volumes)", True, {"budget"}, "error",
        description="total RMS error " + _ORACLE,
    ),
    Metric(
        "recon_added_rms_total_mm", "mm", "total RMS error added by the reconstruction", True, {"budget"}, "error",
        description="total RMS " + _ADDED.format(case="rms_total_mm", oracle="oracle_rms_total_mm"),
    ),
    Metric(
        "filter_rms_total_mm", "mm", "total RMS of the windows' filtering of the truth", True, {"budget"}, "error",
        description="total " + _FILTER.format(ax="x, y, z"),
    ),
    Metric(
        "rest_rms_total_mm", "mm", "total RMS error beyond the windows' filtering and the reconstruction", True,
        {"budget"}, "error", description="total " + _REST.format(oracle="oracle_rms_total_mm",
                                                               filter="filter_rms_total_mm"),
    ),
    Metric("crosstalk_z", "1", "spurious w per unit lateral shift", None, {"headline", "budget"}, "error",
           description=_CROSSTALK),
    Metric(
        "oracle_crosstalk_z", "1", "oracle spurious w per unit lateral shift", None, {"budget"}, "error",
        description="crosstalk_z " + _ORACLE,
    ),
    Metric("oracle_valid_percent", "percent", "oracle valid vectors", False, {"budget"}, "quality",
           description="valid vectors " + _ORACLE),
    Metric(
        "particles_per_cell", "1", "particles per lenslet and depth cell", None, {"budget"}, "count",
        description="true particles inside the grid per lenslet under it and per depth cell along a lenslet's line "
        "of sight (a change of one lenslet pitch in the particle's blur circle, eq. 4.18): above "
        "designs.DENSITY_LIMITED the seeding, not the reconstruction's settings, limits a particle fit",
    ),
    # a particle reconstruction's list against the true particles (lfstudy.study.particle_metrics; ipr only)
    Metric(
        "found_percent", "percent", "true particles found within half a voxel", False, {"budget"}, "quality",
        description="true particles inside the grid with a fitted particle within half a voxel (per-axis voxel "
        "units), both frames (a method that fits particles only)",
    ),
    Metric(
        "found_in_focus_percent", "percent", "true particles found within the depth of field at focus", False,
        {"budget"}, "quality",
        description="found_percent of the true particles within the depth of field about the focal plane (eq. 4.18), "
        "where a particle's image is one lenslet's spot: far below found_percent, the focal plane inside the "
        "volume limits the design (particles.z_center moves the volume off it)",
    ),
    Metric(
        "ghost_percent", "percent", "fitted particles that are ghosts", True, {"budget"}, "quality",
        description="fitted particles with no true particle within half a voxel, both frames",
    ),
    Metric(
        "depth_unknown_percent", "percent", "fitted particles whose depth the images do not give", True,
        {"budget"}, "quality",
        description="fitted particles, both frames, whose depth uncertainty from the fit (sigma_z) exceeds "
        "piv.paired_max_sigma_z, left out of the paired PIV: near the focal plane the images hold little depth "
        "(lfstudy.reconstruct.ipr.bound); needs no truth (piv.particles paired only)",
    ),
    Metric(
        "focus_scatter_ratio", "1", "tracks' scatter nearest focus over the best depth band's", True,
        {"budget"}, "quality",
        description="the paired tracks' displacement scatter (robust, u, v and w) in the band of |z| nearest the "
        "focal plane over the least of any band (piv.paired_weights depth, lfstudy.piv.ptv.depth_weights): well "
        "above 1, the focal plane inside the volume limits the design's depth; needs no truth (the fit's sigma_z, "
        "behind depth_unknown_percent, misses most of this error)",
    ),
    Metric("particle_rms_x_mm", "mm", "position error x of the found particles", True, (), "error"),
    Metric("particle_rms_y_mm", "mm", "position error y of the found particles", True, (), "error"),
    Metric("particle_rms_z_mm", "mm", "position error z of the found particles", True, (), "error"),
    Metric(
        "particle_bias_w_mm", "mm", "mean w error of the particles found in both frames", None, (), "error",
        description="mean of (fitted − true) z displacement over the true particles found in both frames",
    ),
    Metric(
        "particle_crosstalk_z", "1", "found particles' spurious w per unit lateral shift", None, {"budget"}, "error",
        description="crosstalk_z of the particles found in both frames (their fitted displacement, not the PIV's): "
        "near crosstalk_z, the found particles carry it; near 0, the ghosts and missed particles do",
    ),
    # resolution in mm
    Metric(
        "spacing_mm_x", "mm", "vector spacing along x", True,
        {"summary", "headline", "criterion", "pareto", "front", "resolution"}, "resolution",
        criterion="finest in-plane spacing",
    ),
    Metric("spacing_mm_y", "mm", "vector spacing along y", True, {"resolution"}, "resolution"),
    Metric(
        "spacing_mm_z", "mm", "vector spacing along z", True,
        {"summary", "headline", "criterion", "pareto", "front", "resolution"}, "resolution",
        criterion="finest depth spacing",
    ),
    Metric(
        "depth_mm", "mm", "depth spanned by valid vectors", None,
        {"summary", "headline", "front", "resolution"}, "resolution",
    ),
    Metric(
        "depth_gain", "1", "depth gain", None, {"headline"}, "resolution",
        description="measured / true z displacement of the design's traversed-volume depth calibration, which w "
        "was divided by (NaN: depth_calibration.enabled is false, w is the raw reading)",
    ),
    Metric("window_mm_x", "mm", "final PIV window along x", True, {"resolution"}, "resolution"),
    Metric("window_mm_y", "mm", "final PIV window along y", True, (), "resolution"),
    Metric("window_mm_z", "mm", "final PIV window along z", True, {"resolution"}, "resolution"),
    Metric("fov_x_mm", "mm", "field of view in x", None, {"resolution"}, "resolution"),
    Metric("fov_y_mm", "mm", "field of view in y", None, {"resolution"}, "resolution"),
    Metric(
        "locking_excess_z", "1", "excess near-integer fraction z", None, {"headline"}, "error", description=_LOCKING
    ),
    Metric(
        "time_total", "s", "total run time", True, {"summary", "headline", "criterion"}, "cost",
        criterion="shortest run time",
    ),
    # the rest: in the study table and study.csv only
    *_per_axis("locking_excess_{ax}", "1", "excess near-integer fraction {ax}", axes="xy", group="error",
               description=_LOCKING),
    Metric("rms_total", "voxel", "total RMS error (all components)", True, (), "error"),
    *_per_axis("rms_{ax}", "voxel", "RMS error {ax}", lower_is_better=True, group="error"),
    Metric("rms_y_mm", "mm", "RMS error y", True, {"tolerance"}, "error"),
    *_per_axis("bias_{ax}", "voxel", "bias error {ax} (mean of measured − true)", group="error"),
    *_per_axis("bias_{ax}_mm", "mm", "bias error {ax} (mean of measured − true)", axes="xy", group="error"),
    *_per_axis("std_{ax}", "voxel", "random error {ax} (std of measured − true)", lower_is_better=True, group="error"),
    *_per_axis("std_{ax}_mm", "mm", "random error {ax} (std of measured − true)", lower_is_better=True, group="error"),
    *_per_axis("mean_{ax}", "voxel", "mean measured {ax} displacement", group="displacement"),
    *_per_axis("mean_{ax}_mm", "mm", "mean measured {ax} displacement", group="displacement"),
    *_per_axis("true_{ax}", "voxel", "mean true {ax} displacement", group="displacement"),
    *_per_axis("true_{ax}_mm", "mm", "mean true {ax} displacement", group="displacement"),
    *_per_axis("oracle_rms_{ax}_mm", "mm", "oracle RMS error {ax}", lower_is_better=True, group="error",
               description="RMS error " + _ORACLE),
    *_per_axis("oracle_mean_{ax}_mm", "mm", "oracle mean measured {ax} displacement", group="displacement",
               description="mean measured displacement " + _ORACLE),
    *_per_axis("recon_added_rms_{ax}_mm", "mm", "RMS error {ax} added by the reconstruction", lower_is_better=True,
               group="error", description="RMS " + _ADDED.format(case="rms_{ax}_mm", oracle="oracle_rms_{ax}_mm")),
    *_per_axis("filter_rms_{ax}_mm", "mm", "RMS of the windows' filtering of the true {ax} displacement",
               lower_is_better=True, group="error", description=_FILTER),
    *_per_axis("rest_rms_{ax}_mm", "mm", "RMS error {ax} beyond the windows' filtering and the reconstruction",
               lower_is_better=True, group="error",
               description=_REST.format(oracle="oracle_rms_{ax}_mm", filter="filter_rms_{ax}_mm")),
    *_per_axis("unc_coverage_{ax}", "1", "uncertainty coverage {ax}", shown=_UNC_SHOWN, group="error",
               description="fraction of the valid vectors whose |error| in {ax} against the truth averaged over the "
               "vector's final window (what the window measures) is within their standard uncertainty (unc_* of the "
               "PIV; 0.68 where the uncertainty is right)"),
    *_per_axis("unc_ratio_{ax}", "1", "RMS error / RMS uncertainty {ax}", shown=_UNC_SHOWN,
               group="error",
               description="RMS of the {ax} error against the truth averaged over the vector's final window over RMS "
               "of the PIV's standard uncertainty, over the valid vectors (1 where the uncertainty is right)"),
    *_per_axis("unc_coverage_point_{ax}", "1", "uncertainty coverage {ax} against the point truth", group="error",
               description="unc_coverage_{ax} with the error against the truth at the window centre (the window's "
               "filtering counted as error)"),
    *_per_axis("unc_ratio_point_{ax}", "1", "RMS error / RMS uncertainty {ax} against the point truth",
               group="error",
               description="unc_ratio_{ax} with the error against the truth at the window centre (the window's "
               "filtering counted as error)"),
    *_per_axis("unc_coverage_oracle_{ax}", "1", "uncertainty coverage {ax} against the oracle", group="error",
               description="unc_coverage_{ax} with the error against the oracle's vector (the same WIDIM on the true "
               "particles: the windows' whole response to the flow), over the vectors valid in both"),
    *_per_axis("unc_ratio_oracle_{ax}", "1", "RMS error / RMS uncertainty {ax} against the oracle", group="error",
               description="unc_ratio_{ax} with the error against the oracle's vector (the same WIDIM on the true "
               "particles: the windows' whole response to the flow), over the vectors valid in both"),
    Metric(
        "unresolved_percent", "percent", "full-window vectors flagged unresolved", None, (), "quality",
        description="of the valid vectors whose window is not partial, the share the PIV flags 'unresolved' "
        "(piv.zarr: the window's filtering of the measured field likely exceeds σ, with "
        "piv.unresolved_significance also beyond what the vectors' own errors put into its curvature; truth-free, "
        "lfstudy.piv.resolution)",
    ),
    Metric(
        "unresolved_hit", "1", "share of the true filter errors > 2σ flagged", False, (), "quality",
        description="of the valid full-window vectors whose true filtering (window-averaged − point truth) exceeds "
        "2σ in any component, the share flagged unresolved (1: the flag misses none); NaN where there are none",
    ),
    Metric(
        "unresolved_false", "1", "share of the flags on true filter errors < σ", True, (), "quality",
        description="of the valid full-window vectors flagged unresolved, the share whose true filtering is below σ "
        "in every component (0: no false flag); NaN where none is flagged",
    ),
    Metric(
        "partial_percent", "percent", "valid vectors of partial windows", None, (), "quality",
        description="valid vectors whose final window lies partly outside the seeded region (piv.zarr 'partial': "
        "truth-free, from the volumes' mean intensity per plane, lfstudy.piv.resolution.partial_windows); they "
        "measure their seeded part, and the unresolved scores leave them out",
    ),
    Metric("true_mag_mm", "mm", "mean magnitude of the true displacement", None, (), "displacement"),
    Metric("n_vectors", "1", "number of PIV vectors", None, (), "count"),
    Metric("n_valid", "1", "number of valid vectors", None, (), "count"),
    Metric(
        "time_oracle", "s", "oracle run time", True, (), "cost",
        description="rendering the true volumes of both frames and their PIV, inside the errors stage (time_errors)",
    ),
)  # fmt: skip


def metric(name: str) -> Metric:
    """The row of ``name``; a ``KeyError`` naming the table when it has none."""
    for m in METRICS:
        if m.name == name:
            return m
    raise KeyError(f"{name!r} is not in the metric table (lfstudy.study.metric_table.METRICS)")


def shown_in(place: str) -> tuple[Metric, ...]:
    """The metrics shown in ``place`` (one of :data:`PLACES`), in table order."""
    if place not in PLACES:
        raise ValueError(f"unknown place {place!r}; places are {sorted(PLACES)}")
    return tuple(m for m in METRICS if place in m.shown)


def names(*places: str) -> list[str]:
    """Names of the metrics shown in any of ``places``, in table order."""
    chosen = {m.name for p in places for m in shown_in(p)}
    return [m.name for m in METRICS if m.name in chosen]


def metric_attrs(name: str) -> dict[str, str]:
    """The attrs of metric ``name`` (units, long name, description)."""
    return metric(name).attrs


def objectives() -> tuple[tuple[str, str], ...]:
    """The Pareto objectives, ``(name, "min" | "max")``, from the ``pareto`` metrics."""
    return tuple((m.name, "min" if m.lower_is_better else "max") for m in shown_in("pareto"))
