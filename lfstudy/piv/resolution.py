"""Truth-free flag of vectors the PIV windows do not resolve (issue 38).

WIDIM measures the displacement averaged over its final window, to first order the top-hat
average of the flow. For a smooth field that average differs from the value at the window centre
by the top-hat term (Raffel et al. 2018, *Particle Image Velocimetry* sec. 6.1)

    B_c = Σ_j L_j² / 24 · ∂²u_c / ∂x_j²,

L_j the window's length along axis j. The per-vector uncertainty σ (:mod:`lfstudy.piv.uncertainty`)
estimates the random error of what a window measures and cannot see B. :func:`filter_estimate`
reads B from the *measured* field's own second differences on the vector grid (spacing S_j):
``Σ_j (L_j / S_j)² / 24 · (u[i−1] − 2 u[i] + u[i+1])_j``, in the field's units.
:func:`unresolved` flags a vector where that estimate exceeds ``factor`` times σ in any component.

The estimate reads short where the window is as large as the flow's structure (the measured field
is the filtered one, and a second difference over two vector spacings smooths it again), and a
vector's own random error enters its second difference: with independent errors of σ the estimate
has a spread of 0.7σ per component at 50 % overlap (a third of the vectors flagged by noise alone),
but WIDIM's overlapping windows share particles, so neighbouring errors are correlated and the
spread is far smaller (the thesis camera's uniform oracles: 4-9 % flagged). ``factor`` trades the
flag's misses against its false flags (``UNRESOLVED_FACTOR``, chosen on study cases:
``benchmarks/bench_unresolved.py``, whose docstring holds the figures).

What it achieves (thesis camera, Hill's vortex, the oracle): it catches 0.67-0.80 of the vectors
whose true filtering exceeds 2σ, but 0.39-0.52 of its flags fall where the filtering is below σ;
on a MART reconstruction the noise dominates (23 % of a uniform flow's vectors flagged). On the
reconstructions of the thesis camera cropped to 800 x 600 px (seeds 2011 and 2012, 105 vectors a case;
``benchmarks/bench_uncertainty.py``, its cases in ``benchmarks/bench_uncertainty_calibration.py``'s
docstring): Hill with MART hit 0.41-0.63, false 0.55-0.63 (0.001 and 0.005 ppp), with IPR hit 0.81-0.82
/ false 0.51 at 0.001 ppp and 0.67 / 0.45, 0.85 / 0.38 at 0.005 ppp, 50-75 % of the vectors flagged; a
uniform shift 19-24 % flagged with either method. Issue 38's targets (hit >= 0.8 with false <= 0.2) are
not met. Read it as "the flow varies on the window's scale here", not as a per-vector verdict.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["filter_estimate", "unresolved", "UNRESOLVED_FACTOR"]

#: A vector is unresolved where ``|filter_estimate| > UNRESOLVED_FACTOR · σ`` in any component
#: (benchmarks/bench_unresolved.py).
UNRESOLVED_FACTOR = 1.0


def _second_difference(f: np.ndarray, axis: int) -> np.ndarray:
    """Second difference along ``axis`` in grid units; each face takes its inner neighbour's."""
    g = np.moveaxis(f, axis, 0)
    out = np.empty_like(g)
    out[1:-1] = g[:-2] - 2.0 * g[1:-1] + g[2:]
    out[0], out[-1] = out[1], out[-2]
    return np.moveaxis(out, 0, axis)


def filter_estimate(field: np.ndarray, window: Sequence[float], spacing: Sequence[float]) -> np.ndarray:
    """The top-hat term of each component from the measured field's curvature.

    Parameters
    ----------
    field : ndarray, shape (nd, *grid)
        Measured displacement per component on the vector grid (any units; NaN-free: WIDIM's field
        after replacement).
    window, spacing : sequence of float, length nd
        Final window and vector spacing per grid axis, in one unit (voxels).

    Returns
    -------
    ndarray, shape (nd, *grid)
        ``Σ_j (L_j / S_j)² / 24 · Δ²_j u_c`` (units of ``field``); an axis with fewer than three
        vectors adds nothing.
    """
    f = np.asarray(field, dtype=np.float64)
    nd = f.ndim - 1
    if len(window) != nd or len(spacing) != nd:
        raise ValueError(f"filter_estimate: window and spacing need {nd} values (one per grid axis)")
    if not np.all(np.isfinite(f)):
        raise ValueError("filter_estimate: `field` holds non-finite values; replace them first")
    out = np.zeros_like(f)
    for j in range(nd):
        if f.shape[1 + j] < 3:
            continue
        out += (float(window[j]) / float(spacing[j])) ** 2 / 24.0 * _second_difference(f, 1 + j)
    return out


def unresolved(
    field: np.ndarray,
    sigma: np.ndarray,
    window: Sequence[float],
    spacing: Sequence[float],
    *,
    factor: float = UNRESOLVED_FACTOR,
) -> np.ndarray:
    """Vectors where the window's filtering is likely larger than their uncertainty.

    Parameters
    ----------
    field : ndarray, shape (nd, *grid)
        Measured displacement per component (voxels).
    sigma : ndarray, shape (nd, *grid)
        Its standard uncertainty (voxels; NaN: none, never flagged on that component).
    window, spacing : sequence of float
        Final window and vector spacing per grid axis (voxels).
    factor : float
        Flag where ``|filter_estimate| > factor · σ`` in any component (> 0).

    Returns
    -------
    ndarray of bool, shape grid
    """
    if not (np.isfinite(factor) and factor > 0):
        raise ValueError(f"unresolved: `factor` must be > 0; got {factor!r}")
    est = np.abs(filter_estimate(field, window, spacing))
    s = np.asarray(sigma, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(s) & (est > factor * s)
    return hit.any(axis=0)
