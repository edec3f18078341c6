"""σ calibrated by a simulated study: how far the per-vector uncertainty of a recording can be trusted.

A study knows, per case and component, how the PIV's standard uncertainty σ compares with the
real error: ``unc_ratio_<ax>`` = RMS(error) / RMS(σ) (:func:`lfstudy.study.metrics.case_errors`;
1 where σ is right). A recording processed with the same camera and processing as a design of
that study inherits the study's verdict: its σ is scaled, per component, by what the study
measured on the design's cases.

- :func:`read_study` reads a study table (``study.zarr`` or ``study.csv``, or the results
  directory holding them).
- :func:`design_cases` picks the cases of one design (its swept values; the flows and replicate
  seeds are pooled) or one case, with errors that list what the study holds.
- :func:`calibration_factors` is the science: per component, the geometric mean of the cases'
  ratios, so that RMS(error) / RMS(k σ) is 1 on a typical case of the design (a case that reads
  2 and one that reads 0.5 pool to 1, as they should for a scale factor).
- :func:`fit_calibration` ties them together; :func:`apply_calibration` scales a PIV result's
  ``unc_<c>`` / ``unc_<c>_mm`` and keeps the raw ones as ``unc_raw_<c>`` / ``unc_raw_<c>_mm``.

What the calibration cannot know: errors that the study did not simulate. A lenslet array
that is not the modelled one, optics aberrations, background light, a flow with finer structure
than the study's flows, a seeding density or particle images outside the design's: none of
these is in the study's ratios. The factor corrects σ's known bias on the simulated design; it
does not make σ see new error sources.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

__all__ = [
    "CalibrationError",
    "UncertaintyCalibration",
    "read_study",
    "design_cases",
    "calibration_factors",
    "fit_calibration",
    "apply_calibration",
    "load_calibration",
    "calibration_metrics",
    "calibration_note",
]

#: The displacement component of each axis (PIV variable names).
COMPONENTS = {"x": "u", "y": "v", "z": "w"}
#: The study column read per axis: RMS(error) / RMS(σ) of each case (read by name, so it means whatever
#: the study's metric means: since issue 38, the error against the truth averaged over the final window).
RATIO = "unc_ratio_{ax}"
COVERAGE = "unc_coverage_{ax}"
#: Cases whose largest and smallest ratio differ by more than this factor get a warning: a factor pooled over
#: them is off by up to its square root on each (measured, tiny camera with MART, 75 vectors a case: a uniform
#: shift reads 0.9-2.5 and Hill's vortex 6.4-8.5 in x against the point truth; pooled, 3 of 12 held-out
#: case-components meet issue 38's band, fitted on Hill alone 5 of 6 Hill ones).
SPREAD = 2.0
#: Study dimensions pooled within a design: the flows and the replicate seeds (lfstudy.study.designs).
POOLED = ("flow", "seed")


class CalibrationError(ValueError):
    """A calibration that cannot be made; ``key`` is the config key at fault (``study``, ``design``, ``case``)."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


@dataclass(frozen=True)
class UncertaintyCalibration:
    """The scale of σ per component, measured by a study on one design.

    Attributes
    ----------
    study : str
        Where the study table was read.
    design : dict
        The design's swept values (dimension name → value as text), flows and seeds left out.
    cases : tuple of str
        The case ids the factors were fitted on.
    factor : dict
        Per axis (``x``, ``y``, ``z``): σ is multiplied by this.
    ratio_min, ratio_max : dict
        Per axis: the smallest and largest ratio among the cases (how much a single factor hides).
    coverage : dict
        Per axis: the mean raw coverage over the cases (fraction of ``|error| <= σ``).
    """

    study: str
    design: dict[str, str]
    cases: tuple[str, ...]
    factor: dict[str, float]
    ratio_min: dict[str, float] = field(default_factory=dict)
    ratio_max: dict[str, float] = field(default_factory=dict)
    coverage: dict[str, float] = field(default_factory=dict)

    @property
    def design_line(self) -> str:
        """The design as one line (``magnification=-1 lenslet_pitch=0.0888 ppp=0.005``)."""
        return " ".join(f"{k}={v}" for k, v in self.design.items()) or "(one design)"

    def attrs(self) -> dict[str, Any]:
        """Flat provenance attrs (zarr/CSV friendly): the study, the design, the cases and the factors."""
        out: dict[str, Any] = {
            "uncertainty_calibration_study": self.study,
            "uncertainty_calibration_design": self.design_line,
            "uncertainty_calibration_cases": ", ".join(self.cases),
        }
        for ax, f in self.factor.items():
            out[f"uncertainty_calibration_factor_{ax}"] = float(f)
        return out

    def summary(self) -> str:
        """One line: the factors and the spread of the cases' ratios they pool."""
        parts = ", ".join(
            f"{ax} × {self.factor[ax]:.3g} (cases {self.ratio_min.get(ax, math.nan):.3g}–"
            f"{self.ratio_max.get(ax, math.nan):.3g})"
            for ax in self.factor
        )
        return (
            f"σ calibrated by the study {self.study} on {self.design_line} ({len(self.cases)} cases; "
            f"RMS error / RMS σ there): {parts}"
        )


def read_study(path: str | Path) -> xr.Dataset:
    """The study table at ``path``: a results directory (its ``study.zarr``, else ``study.csv``),
    a ``study.zarr`` store or a ``study.csv`` file.

    Raises
    ------
    CalibrationError
        (key ``study``) nothing readable there.
    """
    from lfstudy import io
    from lfstudy.study.table import from_csv

    p = Path(path)
    if p.is_dir() and not p.name.endswith(".zarr"):
        for name in ("study.zarr", "study.csv"):
            if (p / name).exists():
                return read_study(p / name)
        raise CalibrationError(
            "study", f"{str(p)!r} holds no study table (study.zarr or study.csv): give a study's results directory"
        )
    if not p.exists():
        raise CalibrationError(
            "study", f"{str(p)!r} does not exist; give a study's results directory, its study.zarr or its study.csv"
        )
    try:
        if p.suffix == ".csv":
            return from_csv(p)
        ds = io.open_zarr(p)
    except (OSError, ValueError, KeyError) as exc:
        raise CalibrationError("study", f"{str(p)!r} is not a readable study table: {exc}") from None
    if not isinstance(ds, xr.Dataset) or "case_id" not in ds:
        raise CalibrationError("study", f"{str(p)!r} is not a study table (no case_id)")
    return ds.load()


def _text(value: Any) -> str:
    from lfstudy.study.sweep import format_value

    if isinstance(value, (np.floating, np.integer)):
        value = value.item()
    return format_value(value)


def _aliases(study: xr.Dataset) -> dict[str, str]:
    """Every name a design key may use for a study dimension: its name, sweep key and case-id segment."""
    from lfstudy.study.sweep import NAMED

    out: dict[str, str] = {}
    for d in study.dims:
        key = str(study[d].attrs.get("sweep_key", d))
        names = {str(d), key}
        if key in NAMED:
            names.add(NAMED[key].short)
        for n in names:
            out[n] = str(d)
    return out


def _rows(study: xr.Dataset) -> list[dict[str, Any]]:
    """The computed cases: their dimension values as text and their case id."""
    dims = [str(d) for d in study.dims]
    comp = study["computed"].values.astype(bool) if "computed" in study else np.ones(study["case_id"].shape, bool)
    rows = []
    for idx in zip(*np.nonzero(comp)):
        row = {d: _text(study[d].values[i]) for d, i in zip(dims, idx)}
        row["_index"] = tuple(int(i) for i in idx)
        row["case_id"] = str(study["case_id"].values[idx])
        rows.append(row)
    return rows


def _design_of(row: Mapping[str, Any], dims: Sequence[str]) -> dict[str, str]:
    return {d: row[d] for d in dims if d not in POOLED}


def _label(design: Mapping[str, str]) -> str:
    return " ".join(f"{k}={v}" for k, v in design.items()) or "(one design)"


def design_cases(
    study: xr.Dataset, design: Mapping[str, Any] | None = None, case: str | None = None
) -> list[dict[str, Any]]:
    """The computed cases of one design (or one case) of a study.

    Parameters
    ----------
    study : xarray.Dataset
        A study table (:func:`read_study`).
    design : mapping, optional
        Swept values that pick the design, keyed by a study dimension's name, its sweep key or its
        case-id segment (``magnification``, ``lenslet_pitch`` or ``pitch``, ``reconstruct.method``).
        It may also name a flow or a seed to fit on those only. Values compare as case-id text
        (``-1`` and ``-1.0`` match). Omitted: the study must hold a single design.
    case : str, optional
        One case id instead of a design.

    Returns
    -------
    list of dict
        Per case: its dimension values (text), ``case_id`` and ``_index`` (its position in the table).

    Raises
    ------
    CalibrationError
        An unknown key, no matching case or cases of more than one design (the message lists the
        designs the study holds).
    """
    dims = [str(d) for d in study.dims]
    rows = _rows(study)
    designs = list({_label(_design_of(r, dims)): None for r in rows})
    listing = "; ".join(designs) if len(designs) <= 12 else "; ".join(designs[:12]) + f"; ... ({len(designs)})"
    if case is not None:
        if design:
            raise CalibrationError("case", "give a design or a case, not both")
        hit = [r for r in rows if r["case_id"] == str(case).strip("/")]
        if not hit:
            ids = [r["case_id"] for r in rows]
            shown = ", ".join(ids[:8]) + (f", ... ({len(ids)})" if len(ids) > 8 else "")
            raise CalibrationError("case", f"{case!r} is not a computed case of the study; its cases: {shown}")
        return hit
    alias = _aliases(study)
    want: dict[str, str] = {}
    for k, v in (design or {}).items():
        if str(k) not in alias:
            raise CalibrationError(
                "design", f"{k!r} is not a swept setting of the study; its settings: {', '.join(dims)}"
            )
        want[alias[str(k)]] = _text(v)
    hit = [r for r in rows if all(r[d] == v for d, v in want.items())]
    if not hit:
        raise CalibrationError(
            "design", f"no computed case of the study has {_label(want)}; the study's designs: {listing}"
        )
    found = list({_label(_design_of(r, dims)): None for r in hit})
    if len(found) > 1:
        free = [d for d in dims if d not in POOLED and d not in want and len({r[d] for r in hit}) > 1]
        raise CalibrationError(
            "design",
            f"{_label(want) if want else 'no design given'}: matches {len(found)} designs ({'; '.join(found)}); "
            f"add {', '.join(free)} to pick one",
        )
    return hit


def calibration_factors(ratios: Mapping[str, Iterable[float]]) -> dict[str, float]:
    """The factor σ is scaled by, per axis: the geometric mean of the cases' RMS(error) / RMS(σ).

    A scale factor pools in logarithms: cases that read 2 and 0.5 pool to 1. NaN and non-positive
    ratios (a case without σ, or without valid vectors) are left out.

    Parameters
    ----------
    ratios : mapping axis -> iterable of float
        Each case's ratio per axis.

    Returns
    -------
    dict
        Per axis: the factor; NaN where no case has a finite positive ratio.

    Examples
    --------
    >>> f = calibration_factors({"x": [2.0, 0.5], "z": [3.0, float("nan"), 3.0], "y": [float("nan")]})
    >>> {k: round(v, 9) for k, v in f.items()}
    {'x': 1.0, 'z': 3.0, 'y': nan}
    """
    out = {}
    for ax, vals in ratios.items():
        r = np.asarray(list(vals), dtype=float)
        r = r[np.isfinite(r) & (r > 0)]
        out[ax] = float(np.exp(np.mean(np.log(r)))) if r.size else math.nan
    return out


def fit_calibration(
    study: xr.Dataset,
    design: Mapping[str, Any] | None = None,
    case: str | None = None,
    *,
    source: str = "",
    axes: Sequence[str] = ("x", "y", "z"),
) -> UncertaintyCalibration:
    """The calibration of σ on one design (or case) of a study (:func:`design_cases`, :func:`calibration_factors`).

    Raises
    ------
    CalibrationError
        As :func:`design_cases`; or (key ``study``) the study has no ``unc_ratio_<ax>`` for these
        cases (run with ``piv.uncertainty: none``, or before the uncertainty existed).
    """
    rows = design_cases(study, design, case)
    dims = [str(d) for d in study.dims]
    ratios, cover, lo, hi = {}, {}, {}, {}
    for ax in axes:
        col = RATIO.format(ax=ax)
        if col not in study:
            raise CalibrationError(
                "study", f"the study table has no {col} (its cases ran with piv.uncertainty none, or before it existed)"
            )
        vals = np.array([float(study[col].values[r["_index"]]) for r in rows])
        ok = vals[np.isfinite(vals) & (vals > 0)]
        if not ok.size:
            raise CalibrationError("study", f"no case of {_label(_design_of(rows[0], dims))} has a finite {col}")
        ratios[ax] = vals
        lo[ax], hi[ax] = float(ok.min()), float(ok.max())
        ccol = COVERAGE.format(ax=ax)
        if ccol in study:
            cv = np.array([float(study[ccol].values[r["_index"]]) for r in rows])
            cover[ax] = float(np.nanmean(cv)) if np.isfinite(cv).any() else math.nan
    return UncertaintyCalibration(
        study=source,
        design=_design_of(rows[0], dims),
        cases=tuple(r["case_id"] for r in rows),
        factor=calibration_factors(ratios),
        ratio_min=lo,
        ratio_max=hi,
        coverage=cover,
    )


def apply_calibration(piv: xr.Dataset, cal: UncertaintyCalibration) -> xr.Dataset:
    """``piv`` with its σ scaled by the calibration; the raw σ kept beside it.

    ``unc_<c>`` and ``unc_<c>_mm`` become the calibrated σ (so every reader of σ, the report,
    the metrics and the export, shows it); ``unc_raw_<c>`` and ``unc_raw_<c>_mm`` keep the
    estimator's own. The Dataset's attrs record the calibration (:meth:`UncertaintyCalibration.attrs`).
    A component without ``unc_<c>`` is left out.
    """
    out = piv.copy()
    for ax, c in COMPONENTS.items():
        f = cal.factor.get(ax, math.nan)
        for sfx in ("", "_mm"):
            name = f"unc_{c}{sfx}"
            if name not in piv:
                continue
            raw = piv[name]
            out[f"unc_raw_{c}{sfx}"] = raw.copy().assign_attrs(
                long_name=f"{raw.attrs.get('long_name', name)} (the estimator's own, before the study's calibration)"
            )
            out[name] = (raw * f).assign_attrs(
                {
                    **raw.attrs,
                    "long_name": f"{raw.attrs.get('long_name', name)}, calibrated by a study (× {f:.4g})",
                    "calibration_factor": float(f),
                }
            )
    out.attrs.update(cal.attrs())
    return out


def calibration_metrics(piv: xr.Dataset, cal: UncertaintyCalibration) -> dict[str, Any]:
    """Scalars of one pair for its metrics table: the factor per axis (``unc_cal_factor_<ax>``) and the
    median raw σ of the valid vectors (``unc_raw_median_<c>`` [voxel], ``unc_raw_median_<c>_mm`` [mm])."""
    from lfstudy.process.metrics import median_uncertainty

    out: dict[str, Any] = {}
    valid = piv["valid"].values.astype(bool)
    for ax, c in COMPONENTS.items():
        if f"unc_raw_{c}" not in piv:
            continue
        out[f"unc_cal_factor_{ax}"] = (
            (),
            float(cal.factor[ax]),
            {"units": "1", "long_name": f"study calibration factor of the {ax} uncertainty (unc_{c} = factor × raw)"},
        )
        for sfx, units in (("", "voxel"), ("_mm", "mm")):
            if f"unc_raw_{c}{sfx}" in piv:
                out[f"unc_raw_median_{c}{sfx}"] = (
                    (),
                    median_uncertainty(piv[f"unc_raw_{c}{sfx}"].values, valid),
                    {
                        "units": units,
                        "long_name": f"median raw (uncalibrated) standard uncertainty of the {ax} "
                        "displacement (valid vectors)",
                    },
                )
    return out


def calibration_note(attrs: Mapping[str, Any]) -> str:
    """Which σ a processed recording shows, in words, from its ``piv.zarr`` attrs
    (:meth:`UncertaintyCalibration.attrs`)."""
    study = attrs.get("uncertainty_calibration_study")
    if study is None:
        return "σ is the estimator's own (piv.uncertainty), not calibrated by a study."
    f = ", ".join(
        f"{ax} × {float(attrs[f'uncertainty_calibration_factor_{ax}']):.3g}"
        for ax in COMPONENTS
        if f"uncertainty_calibration_factor_{ax}" in attrs
    )
    return (
        f"σ shown is calibrated by the study {study} on {attrs.get('uncertainty_calibration_design', '')} "
        f"({f}); the estimator's own is unc_raw_* in piv.zarr. The study cannot know errors it did not simulate."
    )


def config_mismatches(design: Mapping[str, str], cfg: Mapping[str, Any], study: xr.Dataset) -> list[str]:
    """The design's swept values that a recording config sets differently (``key: design value vs config value``).

    Only settings the recording config holds are compared (a recording has no seeding density).
    """
    from lfstudy.study.sweep import NAMED

    out = []
    for d, v in design.items():
        key = str(study[d].attrs.get("sweep_key", d)) if d in study.coords else d
        path = NAMED[key].path if key in NAMED else key
        node: Any = cfg
        for part in path.split("."):
            if not isinstance(node, Mapping) or part not in node:
                node = None
                break
            node = node[part]
        if node is None or isinstance(node, Mapping):
            continue
        if _text(node) != v:
            out.append(f"{path}: the design's {v}, the recording's {_text(node)}")
    return out


def load_calibration(cfg: Mapping[str, Any]) -> UncertaintyCalibration | None:
    """The calibration a validated recording config asks for (``uncertainty.calibration``), or None.

    Reads the study (the path as resolved by the config loader), fits the factors on the
    design or case it names and warns (:class:`UserWarning`) where a swept setting of the
    design differs from the recording's own (a study of another camera says little about this one).

    Raises
    ------
    CalibrationError
        As :func:`read_study` and :func:`fit_calibration`.
    """
    import warnings

    spec = (cfg.get("uncertainty") or {}).get("calibration")
    if spec is None:
        return None
    study = read_study(spec["study"])
    cal = fit_calibration(study, spec.get("design") or None, spec.get("case"), source=str(spec["study"]))
    wide = [
        f"{ax} {cal.ratio_min[ax]:.3g}–{cal.ratio_max[ax]:.3g}"
        for ax in cal.factor
        if cal.ratio_max.get(ax, 0.0) > SPREAD * cal.ratio_min.get(ax, math.inf)
    ]
    if wide:
        warnings.warn(
            f"uncertainty.calibration: the {len(cal.cases)} cases of {cal.design_line} disagree on σ's scale "
            f"(RMS error / RMS σ: {', '.join(wide)}), so one factor fits few of them: name the flow most like the "
            "recording's in the design (a window-filtered vortex and a uniform shift differ most) or fit on more seeds",
            UserWarning,
            stacklevel=2,
        )
    diff = config_mismatches(cal.design, cfg, study)
    if diff:
        warnings.warn(
            "uncertainty.calibration: the study's design is not the recording's: " + "; ".join(diff),
            UserWarning,
            stacklevel=2,
        )
    return cal
