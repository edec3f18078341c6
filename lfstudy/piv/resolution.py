"""Truth-free flag of vectors the PIV windows do not resolve (issue 38).

WIDIM measures the displacement averaged over its final window, to first order the top-hat
average of the flow. For a smooth field that average differs from the value at the window centre
by the top-hat term (Raffel et al. 2018, *Particle Image Velocimetry* sec. 6.1)

    B_c = Σ_j L_j² / 24 · ∂²u_c / ∂x_j²,

L_j the window's length along axis j. The per-vector uncertainty σ (:mod:`lfstudy.piv.uncertainty`)
estimates the random error of what a window measures and cannot see B. :func:`filter_estimate`
reads B from the *measured* field's own second differences on the vector grid (spacing S_j):
``Σ_j (L_j / S_j)² / 24 · (u[i−1] − 2 u[i] + u[i+1])_j``, in the field's units.
:func:`unresolved` flags a vector where the mean of that estimate over the vector and its neighbours
(weights 1/4, 1/2, 1/4 along each grid axis) exceeds ``factor`` times σ in any component.

The estimate reads short where the window is as large as the flow's structure (the measured field
is the filtered one, and a second difference over two vector spacings smooths it again: 2-3x short on
the thesis camera's Hill oracle in x and y), and a vector's own random error enters its second
difference. The 1-2-1 mean keeps a curvature that is coherent over a few vectors and takes the noise
down, and ``UNRESOLVED_FACTOR`` = 0.3 makes up for the shortfall.

The vectors' errors alone are then the flag's false alarms. With ``significance`` (``piv.unresolved_significance``;
0, off, by default) a vector is flagged only where its estimate also stands out of that noise by that many standard
deviations (``NOISE_MARGIN_95``, 2.39, for 95 % of pure-noise vectors unflagged). The noise is modelled, not
tuned: where a vector's error is the mean of its window's particles' errors, overlapping windows share it in
proportion to the length they share (correlation 1 − |i − j|·S/L along each axis, 0.5 between neighbours at 50 %
overlap; the demo's reconstructions measured 0.4-0.85). Through the estimator's operator that gives each vector's
spread for errors of unit size (:func:`estimate_noise_gain`: 0.15 inside a grid at 50 % overlap, 0.21 on a face,
0.34 at a corner, where the second differences are copied and the mean has no neighbour). The errors' size is read
from the field itself (:func:`noise_level`: the robust spread of its mixed differences over cells of 2 x 2 x 2
vectors, which no flow that does not vary along all three axes at once enters), not taken from σ, since on
reconstructions σ is the part of the error a window's correlation sees (their errors 1.1-2.9 σ on the demo). At
2.39, 5.0 % of a field of such noise is flagged (tests).

A window that reaches past the seeded region (the faces of a light sheet's slab, a refocused depth
range larger than the seeding) measures the displacement of its seeded part, not of the box about its
centre, and the face puts a curvature into the measured field that is not the flow's.
:func:`partial_windows` marks such windows from the volumes alone: the planes of each axis whose mean
intensity is at least half the profile's level, and those between them (:func:`seeded_planes`), are
the seeded region, and a window with less than ``SEEDED_INSIDE`` (7/8) of its length inside along some
axis is partial. They are stored as ``partial`` and never flagged ``unresolved``; the study judges the
flag on the full windows.
The profile is the reconstruction's: MART's intensity also peaks at the focal plane, so on a grid hardly
deeper than its windows every window can read as partial where the seeding fills it (the tiny test
camera's two windows in z; ``SEEDED_LEVEL``).

What it achieves (``benchmarks/bench_unresolved.py``, whose docstring holds the figures: the thesis
camera cropped to 1600 x 1200 px, 2-level WIDIM to 8 x 16 x 16-voxel windows, the oracle): the seeded
slab (7 mm) fills only two of the grid's seven z planes of windows, so 67 % of the valid vectors are
partial. On the full windows, Hill's vortex: hit 0.90-0.96 of the vectors whose true filtering exceeds
2σ, false 0.07-0.14 on the seeds the factor was chosen on (2011, 2012), 0.88-0.95 / 0.05-0.07 on seed 2013
(issue 38's targets: >= 0.8 and <= 0.2); Lamb-Oseen hit 0.98-1.00, false 0.03-0.05; a uniform shift 0-9 %
flagged. Before the partial windows were set apart, all but 0-4 of the Hill oracle's false flags (98-119 a
case) lay on windows at the slab's faces, nearly all with a real error above 2σ, not the filter's. On reconstructions
(``benchmarks/bench_uncertainty.py``, the thesis camera cropped to 1200 x 900 px, 0.005 ppp, Monte-Carlo
images, seed 2011, 67-75 % of the vectors partial), run on a2ff4e5: Hill with MART hit 0.80, false 0.11, with
IPR 0.93 / 0.09; a uniform shift 26 % (MART) and 28 % (IPR) flagged, the reconstructions' own errors in the second
differences. The same case rerun on 8cf565e reads MART 0.76 / 0.11 and IPR 0.96 / 0.16 (below): MART's catch sits
at the target's edge.

Those figures are without the significance (the default). With it at 2.39 (the same oracles, seeds 2011 and 2012,
0.001 and 0.005 ppp, flagged % / hit / false): a uniform shift 0-2 % (0-4 % without); Hill 42-57 % / 0.67-0.85 /
0.00-0.01 (71-82 % / 0.90-0.96 / 0.07-0.14); Lamb-Oseen 68-76 % / 0.67-0.86 / 0.03-0.06 (94-98 % / 0.98-1.00 /
0.03-0.05). On the oracles the field's noise level reads 0.4-1.7 σ on the uniform shift and Lamb-Oseen, within 2x of
their errors, but 4.3-6.8 σ in x and y on Hill (their errors 2.1-4.4 σ): the vortex, sampled at the windows' scale,
enters the mixed differences too. The thesis camera's reconstructions (1200 x 900 px, 0.005 ppp, Monte-Carlo images,
seed 2011, 71-75 % partial; flags recomputed from one run's stores), without -> with: MART uniform 27.1 -> 15.7 %,
Hill 76 % / 0.76 / 0.11 -> 33 % / 0.47 / 0.00; IPR uniform 24.3 -> 20.0 %, Hill 91 % / 0.96 / 0.16 -> 31 % / 0.44 /
0.08. The demo's IPR designs (a seed-7 demo study; paired particles, no partial window): a uniform shift 38-66 % ->
2.8-14.9 % flagged, Hill 65-76 % / 0.72-0.94 / 0.73-0.85 -> 10.8-38.1 % / 0.00-0.86 / 0.45-0.84; there the true
filtering is below σ on most vectors (median 0.01-0.11 σ, 18-56 vectors a case above 2σ), and what stays flagged is
mostly the reconstruction's own curvature, which the noise model does not hold. So the margin takes most false flags
off the demo's uniform shift but costs the hits where issue 38 sets its targets (the thesis camera's Hill, which the
flag without it meets on the oracles and on IPR): it is an option, not the default, and no margin in between does
both (1, 1.5 and 2 on the same stores: at 1 the thesis IPR Hill keeps 0.92 / 0.14, but the demo's uniform shift is
still 26-51 % flagged). Read the flag as "the field varies on the window's scale here" (the flow's or the
reconstruction's), not as a per-vector verdict; the study report says per study how far it held.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.ndimage import convolve1d
from scipy.stats import norm as _normal

__all__ = [
    "filter_estimate",
    "estimate_noise_gain",
    "noise_level",
    "unresolved",
    "seeded_planes",
    "partial_windows",
    "UNRESOLVED_FACTOR",
    "NOISE_MARGIN_95",
    "SEEDED_INSIDE",
    "SEEDED_LEVEL",
]

#: A vector is unresolved where the 1-2-1 mean of its ``filter_estimate`` exceeds ``UNRESOLVED_FACTOR · σ`` in
#: absolute value in any component. The estimate reads 2-3x short where the window is as large as the flow's
#: structure and the mean takes a little more of it, hence 0.3 (chosen on the thesis camera's oracles and
#: reconstructions, 1.3-1.5x fewer flags on a uniform shift than half of σ without the mean:
#: benchmarks/bench_unresolved.py).
UNRESOLVED_FACTOR = 0.3
#: A margin of the flag over the vectors' own noise (``unresolved(significance=...)``, ``piv.unresolved_significance``)
#: in standard deviations of what they give the estimate (:func:`estimate_noise_gain` times the field's
#: :func:`noise_level`): the two-sided normal quantile at which a vector of pure noise passes in none of its three
#: components with 95 % probability (each 1 − 0.95^(1/3)), 2.39. Not the default: it trades the hits for fewer false
#: flags (module docstring).
NOISE_MARGIN_95 = float(_normal.ppf(1.0 - (1.0 - 0.95 ** (1.0 / 3.0)) / 2.0))
#: The mean of the estimate over each vector and its neighbours along each grid axis (weights 1/4, 1/2, 1/4): a
#: curvature of the flow is coherent over several vectors, the second differences of the vectors' random errors
#: are not (with independent errors their spread falls to about a quarter).
_SMOOTH = np.array([0.25, 0.5, 0.25])
#: A window is partial where less than this share of its length along some axis lies in the seeded planes.
SEEDED_INSIDE = 0.875
#: The seeded planes: their mean intensity is at least this share of the profile's 95th percentile (the seeded
#: region's faces at half its level, as a full width at half maximum). MART's background outside the thesis camera's
#: slab stays below 0.2 of it, but its reconstructed intensity also peaks at the focal plane: on the tiny test camera
#: (12 planes of depth, seeded throughout) 1.35 there and 0.3-0.5 two planes away, so both of its two windows in z
#: read as partial. A quarter instead keeps one of them full there but lets one more plane of the thesis camera's
#: MART background in (its Hill false flags 0.11 -> 0.37): benchmarks/bench_unresolved.py.
SEEDED_LEVEL = 0.5


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


def _d2_matrix(n: int) -> np.ndarray:
    """:func:`_second_difference` along one axis of ``n`` nodes as a matrix."""
    m = np.zeros((n, n))
    for i in range(1, n - 1):
        m[i, i - 1 : i + 2] = (1.0, -2.0, 1.0)
    if n >= 3:
        m[0], m[-1] = m[1], m[-2]
    return m


def _smooth_matrix(n: int) -> np.ndarray:
    """The 1-2-1 mean along one axis of ``n`` nodes (``convolve1d(mode="nearest")``) as a matrix; none below 3."""
    if n < 3:
        return np.eye(n)
    m = np.zeros((n, n))
    for i in range(n):
        for o, w in zip((-1, 0, 1), _SMOOTH):
            m[i, min(max(i + o, 0), n - 1)] += w
    return m


def _overlap(n: int, window: float, spacing: float) -> np.ndarray:
    """Correlation of the errors of ``n`` vectors along one axis whose windows overlap: the share of its length two
    windows have in common (1 − |i − j|·S/L, at least 0), as where their errors are the mean of the particles
    each holds."""
    i = np.arange(n)
    return np.clip(1.0 - np.abs(i[:, None] - i[None, :]) * float(spacing) / float(window), 0.0, None)


def estimate_noise_gain(shape: Sequence[int], window: Sequence[float], spacing: Sequence[float]) -> np.ndarray:
    """Standard deviation of the 1-2-1 mean of :func:`filter_estimate` that the vectors' errors alone give, per
    vector, for errors of unit standard deviation correlated as overlapping windows share their particles
    (:func:`_overlap` along each axis, their product across axes).

    The estimate is linear in the field, a sum over axes of operators separable across axes, and the
    correlation is separable too, so each vector's variance is a sum of products of one-axis terms (no matrix of
    the whole grid). Interior vectors of a grid at 50 % overlap: 0.150 (0.091 for independent errors); a face
    0.21, a corner 0.34, where the second differences are copied and the mean has no neighbour.

    Parameters
    ----------
    shape : sequence of int
        The vector grid.
    window, spacing : sequence of float
        Final window and vector spacing per grid axis, in one unit.

    Returns
    -------
    ndarray, shape ``shape``
    """
    nd = len(shape)
    smooth = [_smooth_matrix(int(n)) for n in shape]
    corr = [_overlap(int(n), window[k], spacing[k]) for k, n in enumerate(shape)]
    terms = [
        (
            (float(window[j]) / float(spacing[j])) ** 2 / 24.0,
            [smooth[k] @ _d2_matrix(int(shape[k])) if k == j else smooth[k] for k in range(nd)],
        )
        for j in range(nd)
        if shape[j] >= 3
    ]
    var = np.zeros(tuple(int(n) for n in shape))
    for aj, mj in terms:
        for al, ml in terms:
            prod = np.ones_like(var)
            for k in range(nd):
                shp = [1] * nd
                shp[k] = -1
                prod = prod * np.einsum("ij,jk,ik->i", mj[k], corr[k], ml[k]).reshape(shp)
            var += aj * al * prod
    return np.sqrt(np.clip(var, 0.0, None))


def noise_level(
    field: np.ndarray, valid: np.ndarray | None, window: Sequence[float], spacing: Sequence[float]
) -> np.ndarray:
    """The standard deviation of the vectors' errors, per component, read from the measured field itself.

    The mixed difference over each cell of 2 x 2 (x 2) neighbouring vectors (their sum with alternating signs) is
    blind to any field that does not vary along every axis at once, so to a smooth flow up to a mixed third
    derivative; for errors of standard deviation s correlated as overlapping windows share their particles
    (:func:`_overlap`: ρ = 1 − S/L between neighbours) its standard deviation is s·Π_j √(2(1 − ρ_j)). Its robust
    spread (1.4826 × the median absolute deviation) over the cells whose vectors are all valid, divided by that
    factor, is the estimate. An axis with one vector is left out.

    Parameters
    ----------
    field : ndarray, shape (nd, *grid)
        Measured displacement per component.
    valid : ndarray of bool, shape grid, or None
        The vectors WIDIM kept (a replaced vector is its neighbours' interpolation and no error of its own);
        None: all.
    window, spacing : sequence of float
        Final window and vector spacing per grid axis, in one unit.

    Returns
    -------
    ndarray, shape (nd,)
        Units of ``field``; NaN with fewer than 8 complete cells.
    """
    f = np.asarray(field, dtype=np.float64)
    ok = np.ones(f.shape[1:], bool) if valid is None else np.asarray(valid, bool)
    gain = 1.0
    for ax in range(f.ndim - 1):
        if f.shape[1 + ax] < 2:
            continue
        lo = [slice(None)] * f.ndim
        hi = list(lo)
        lo[1 + ax], hi[1 + ax] = slice(None, -1), slice(1, None)
        f = f[tuple(hi)] - f[tuple(lo)]
        ok = ok[tuple(hi[1:])] & ok[tuple(lo[1:])]
        rho = max(0.0, 1.0 - float(spacing[ax]) / float(window[ax]))
        gain *= 2.0 * (1.0 - rho)
    out = np.full(f.shape[0], np.nan)
    if np.count_nonzero(ok) >= 8 and gain > 0:
        for c in range(f.shape[0]):
            v = f[c][ok]
            out[c] = 1.4826 * float(np.median(np.abs(v - np.median(v)))) / np.sqrt(gain)
    return out


def seeded_planes(profile: np.ndarray, level: float = SEEDED_LEVEL) -> np.ndarray:
    """The planes of one axis that hold the seeding, from the volumes' mean intensity per plane.

    Parameters
    ----------
    profile : ndarray, shape (n,)
        Mean intensity of each plane across the other axes (both frames).
    level : float
        A plane is seeded where its mean is at least ``level`` times the profile's 95th percentile (0, 1].

    Returns
    -------
    ndarray of bool, shape (n,)
        The planes from the first to the last at that level: a dip inside (the focal planes, whose
        particles the paired PIV leaves out where the images do not give their depth) is no face of the
        region. All True where the profile has no positive level (nothing to tell the planes apart by).

    Examples
    --------
    >>> seeded_planes(np.array([0.0, 0.1, 1.0, 1.1, 0.2, 0.9, 0.2])).astype(int).tolist()
    [0, 0, 1, 1, 1, 1, 0]
    """
    if not 0.0 < level <= 1.0:
        raise ValueError(f"seeded_planes: `level` must be in (0, 1]; got {level!r}")
    p = np.nan_to_num(np.asarray(profile, dtype=np.float64), nan=0.0)
    ref = float(np.percentile(p, 95)) if p.size else 0.0
    if not ref > 0:
        return np.ones(p.shape, bool)
    above = np.flatnonzero(p >= level * ref)
    out = np.zeros(p.shape, bool)
    out[above[0] : above[-1] + 1] = True  # the span between the faces: a gap inside is no face
    return out


def partial_windows(
    profiles: Sequence[np.ndarray],
    nodes: Sequence[np.ndarray],
    window: Sequence[int],
    *,
    inside: float = SEEDED_INSIDE,
) -> np.ndarray:
    """Windows that lie partly outside the seeded region (truth-free).

    Such a window measures the displacement of its seeded part, not of the box about its centre, and the
    region's face puts a curvature into the measured field that is not the flow's: at the faces of the
    thesis camera's seeded slab the curvature flagged vectors whose true filtering is below σ
    (benchmarks/bench_unresolved.py). They are marked ``partial`` instead of being judged by
    :func:`unresolved`.

    Parameters
    ----------
    profiles : sequence of ndarray
        Per axis of the volume, the mean intensity of each plane (:func:`seeded_planes`).
    nodes : sequence of ndarray of int
        Per axis, the first voxel of each window (``lfstudy.piv.engine.grid_nodes``).
    window : sequence of int
        Window length per axis (voxels).
    inside : float
        A window is partial where less than this share of its length along some axis lies in the
        seeded planes, (0, 1].

    Returns
    -------
    ndarray of bool, shape ``tuple(len(n) for n in nodes)``
    """
    if not 0.0 < inside <= 1.0:
        raise ValueError(f"partial_windows: `inside` must be in (0, 1]; got {inside!r}")
    grid = tuple(len(n) for n in nodes)
    out = np.zeros(grid, bool)
    for j, (prof, nd, w) in enumerate(zip(profiles, nodes, window)):
        seeded = seeded_planes(prof).astype(np.float64)
        frac = np.array([seeded[int(n) : int(n) + int(w)].mean() for n in nd])
        shp = [1] * len(grid)
        shp[j] = -1
        out |= (frac < inside).reshape(shp)
    return out


def unresolved(
    field: np.ndarray,
    sigma: np.ndarray,
    window: Sequence[float],
    spacing: Sequence[float],
    *,
    factor: float = UNRESOLVED_FACTOR,
    partial: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    significance: float = 0.0,
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
        Flag where the 1-2-1 mean (per grid axis) of the estimate exceeds ``factor · σ`` in absolute
        value in any component (> 0).
    partial : ndarray of bool, shape grid, optional
        Windows partly outside the seeded region (:func:`partial_windows`): never flagged, their
        curvature is the region's face.
    valid : ndarray of bool, shape grid, optional
        The vectors WIDIM kept, those :func:`noise_level` reads the errors' size from (default: all).
    significance : float
        And only where that mean exceeds ``significance`` standard deviations of what the vectors' errors alone
        give it (:func:`estimate_noise_gain` × :func:`noise_level`, per component; ≥ 0, 0: the noise is not
        considered). Where the noise level cannot be read (too few vectors) the noise is not considered.

    Returns
    -------
    ndarray of bool, shape grid
    """
    if not (np.isfinite(factor) and factor > 0):
        raise ValueError(f"unresolved: `factor` must be > 0; got {factor!r}")
    if not (np.isfinite(significance) and significance >= 0):
        raise ValueError(f"unresolved: `significance` must be >= 0; got {significance!r}")
    est = filter_estimate(field, window, spacing)
    for ax in range(1, est.ndim):
        if est.shape[ax] >= 3:
            est = convolve1d(est, _SMOOTH, axis=ax, mode="nearest")
    est = np.abs(est)
    s = np.asarray(sigma, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(s) & (est > factor * s)
        if significance > 0:  # and more than the vectors' own errors put there (NaN level: not considered)
            level = noise_level(field, valid, window, spacing).reshape((-1,) + (1,) * (est.ndim - 1))
            hit &= ~(est <= significance * level * estimate_noise_gain(est.shape[1:], window, spacing))
    flag = hit.any(axis=0)
    if partial is not None:
        flag &= ~np.asarray(partial, bool)
    return flag
