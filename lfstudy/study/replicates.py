"""Replicates: the same designs over several seeds, and what the study can then tell apart (issues 27, 29).

One case is one draw of particle positions, rays and sensor noise, so its metrics scatter from seed to
seed (the demo's MART crosstalk_z: +0.29, -0.27, -0.31, +0.23 for one field moved by a quarter lenslet
at a time; tolerance costs of 0-5 % against a ~5 % seed-to-seed scatter). A study gets replicates by
sweeping the study seed, ``sweep: {seed: [1, 2, 3]}``: each seed is its own case with its own derived
seeds (:func:`lfstudy.study.case.derive_seed`), and within one seed the designs and the levels of a
tolerance sweep keep sharing their particle field, rays and noise as they do without replicates
(common random numbers). The study Dataset then has a ``seed`` dimension; these pure functions reduce
it:

- :func:`replicate_dim`: the replicate dimension where a study has two or more seeds, else ``None``;
- :func:`replicate_stats`: the mean over the replicates, their standard deviation (the spread of one
  case) and their count, per design;
- :func:`paired_difference`: the mean of per-seed differences between two designs (or two levels of
  an imperfection) and its standard error. The designs of one seed share their particle field, so
  their errors are correlated and the paired difference has a smaller standard error than the two
  means' s.e. added in quadrature;
- :func:`separable`: whether a difference exceeds :data:`SEPARATION` standard errors;
- :func:`pm`: a mean and its spread as table text, ``0.0359 ± 0.0021``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import xarray as xr

__all__ = [
    "REPLICATE_DIM",
    "SEPARATION",
    "ReplicateStats",
    "replicate_dim",
    "replicate_stats",
    "paired_difference",
    "separable",
    "pm",
]

#: The study dimension of the replicates: the swept study seed (``sweep: {seed: [...]}``).
REPLICATE_DIM = "seed"
#: Two results differ beyond noise where their difference is at least this many standard errors
#: (about a 5 % chance of calling pure noise a difference, for Gaussian errors).
SEPARATION = 2.0


def replicate_dim(study: xr.Dataset) -> str | None:
    """The study's replicate dimension (:data:`REPLICATE_DIM`) where it holds two or more seeds, else ``None``."""
    return REPLICATE_DIM if REPLICATE_DIM in study.dims and study.sizes[REPLICATE_DIM] > 1 else None


@dataclass(frozen=True)
class ReplicateStats:
    """A study reduced over its replicates: three Datasets over the other dimensions.

    Attributes
    ----------
    mean, sd, n : xarray.Dataset
        Per numeric variable: the mean over the computed replicates, their sample standard deviation
        (ddof 1; NaN for a single replicate) and their count (NaN values left out). Each also holds
        ``computed`` (any replicate computed) and ``case_id`` (the first computed replicate's id, for
        the case's camera).
    dim : str
        The reduced dimension.
    """

    mean: xr.Dataset
    sd: xr.Dataset
    n: xr.Dataset
    dim: str

    @property
    def se(self) -> xr.Dataset:
        """The standard error of each mean, sd / sqrt(n)."""
        num = [v for v in self.sd.data_vars if v not in ("computed", "case_id")]
        out = self.sd.copy()
        for v in num:
            n = self.n[v]
            out[v] = (self.sd[v] / np.sqrt(n.where(n > 0))).assign_attrs(self.sd[v].attrs)
        return out

    @property
    def count(self) -> int:
        """How many replicates the study holds."""
        return int(self.n.attrs.get("replicates", 0))


def replicate_stats(study: xr.Dataset, dim: str | None = None) -> ReplicateStats:
    """Mean, spread and count of every numeric variable over the replicates (see :class:`ReplicateStats`).

    Parameters
    ----------
    study : xarray.Dataset
        A study Dataset (:func:`lfstudy.study.table.combine_cases`) with a replicate dimension.
    dim : str, optional
        The replicate dimension; default :func:`replicate_dim`.

    Raises
    ------
    ValueError
        The study has no such dimension.
    """
    dim = dim or replicate_dim(study)
    if dim is None or dim not in study.dims:
        raise ValueError(f"the study has no replicate dimension {REPLICATE_DIM!r} (sweep: {{seed: [...]}})")
    comp = study["computed"].astype(bool) if "computed" in study else None
    num = [str(v) for v in study.data_vars if v not in ("computed", "case_id") and study[v].dtype.kind in "biuf"]
    vals = study[num].astype(float)
    if comp is not None:
        vals = vals.where(comp)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = vals.mean(dim, skipna=True, keep_attrs=True)
        sd = vals.std(dim, ddof=1, skipna=True, keep_attrs=True)
    n = vals.count(dim, keep_attrs=True).astype(float)
    any_comp = comp.any(dim) if comp is not None else None
    first = None
    if "case_id" in study:
        first = xr.full_like(study["case_id"].isel({dim: 0}, drop=True), "", dtype=object)
        ok = comp if comp is not None else xr.ones_like(study["case_id"], dtype=bool)
        for k in reversed(range(study.sizes[dim])):
            first = xr.where(ok.isel({dim: k}, drop=True), study["case_id"].isel({dim: k}, drop=True), first)
        first = first.astype(object).assign_attrs(study["case_id"].attrs)
    seeds = ", ".join(str(v) for v in study[dim].values.tolist())
    out = []
    for ds in (mean, sd, n):
        ds = ds.copy()
        if any_comp is not None:
            ds["computed"] = any_comp.assign_attrs(study["computed"].attrs)
        if first is not None:
            ds["case_id"] = first
        ds.attrs = {**study.attrs, "replicates": study.sizes[dim], "replicate_seeds": seeds}
        out.append(ds)
    return ReplicateStats(out[0], out[1], out[2], dim)


def paired_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float, int]:
    """Mean and standard error of ``a - b`` over the replicates both have (paired by seed).

    Returns
    -------
    mean, se : float
        NaN where no replicate pairs up; ``se`` is NaN for a single pair.
    n : int
        How many pairs.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    d = a[ok] - b[ok]
    if d.size == 0:
        return math.nan, math.nan, 0
    se = float(np.std(d, ddof=1) / math.sqrt(d.size)) if d.size > 1 else math.nan
    return float(d.mean()), se, int(d.size)


def separable(diff: float, se: float, k: float = SEPARATION) -> bool | None:
    """Whether ``|diff|`` is at least ``k`` standard errors; ``None`` where either is unknown."""
    if not (math.isfinite(diff) and math.isfinite(se)):
        return None
    return abs(diff) >= k * se if se > 0 else diff != 0


def pm(mean: float, spread: float, fmt: str = "{:.3g}", *, sign: bool = False) -> str:
    """``mean ± spread`` as table text (``–`` for an unknown mean; the mean alone without a spread)."""
    m, s = float(mean), float(spread)
    if not math.isfinite(m):
        return "–"
    text = ("+" if sign and m > 0 else "") + fmt.format(m)
    return f"{text} ± {fmt.format(s)}" if math.isfinite(s) else text
