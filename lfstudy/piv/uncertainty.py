"""Per-vector displacement uncertainty of a WIDIM result.

Three estimators of the standard uncertainty of each component (:data:`METHODS`), all from the
final pass's deformed windows ``a`` (frame 1 moved back by -d/2) and ``b`` (frame 2 moved by +d/2),
which match up to the residual displacement. All three estimate the random error of what a window
measures: the window's filtering of a flow that varies inside it (the top-hat response) is a
separate term no estimator built from the window's own data can see (issue 38; the study's
``filter_rms_*`` and the ``unresolved`` flag of :mod:`lfstudy.piv.resolution`).

``"independent"``: correlation statistics as published (Wieneke 2015, Meas. Sci. Technol. 26
074002), extended to 3-D. Along array axis k every voxel pair adds ``c+_i = a(i) b(i + e_k)`` to the
correlation at lag +1 and ``c-_i = a(i + e_k) b(i)`` to the one at lag -1. At a converged
(symmetric) peak the difference ``ΔC = Σ (c+_i − c-_i)`` is zero in expectation; its standard
deviation, from the spread of the individual contributions taken as independent, is
``σ_ΔC = sqrt(Σ (ΔC_i − mean ΔC)²)``. The peak's neighbours are then taken as
``C± = C̄ ± σ_ΔC / 2`` about their mean ``C̄ = (C+ + C-) / 2`` and the three-point estimator WIDIM
uses (:func:`lfstudy.piv.subpixel.three_point`: the Gaussian of thesis eq. 6.2, parabolic where a
logarithm is undefined) turns that asymmetry into a displacement:
``σ_d = |d(C0, C̄ + σ_ΔC/2, C̄ − σ_ΔC/2)|``. The estimator is scale free, so the raw
(un-normalised) sums serve.

``"correlation"`` (the default): the same with neighbouring contributions counted as correlated.
A particle image spans several voxels, so the ΔC_i of neighbouring voxels are not independent and
the published sum reads σ_ΔC short. ``σ_ΔC²`` is multiplied by ``Var(Σ ΔC_i) / Σ (ΔC_i − mean)²``,
estimated per window from the autocorrelation ρ_j(l) of the ΔC_i field along each axis j, separably:
``Π_j (1 + 2 Σ_l ρ_j(l))``, each sum over the positive lags up to the first ρ <= 0 (at most
``_MAX_LAG`` voxels).

``"moment"``: a simple moment estimate for comparison: the Gaussian width ``s_k`` of the
correlation peak along k (from the same three points, ``1/s_k² = 2 ln C0 − ln C+ − ln C-``)
times the noise-to-signal ratio of the peak, ``sqrt((1 − ρ) / ρ)`` with ``ρ = C0 / sqrt(Σa² Σb²)``
the correlation coefficient at the peak, over the square root of the number of independent
matches, the window's voxels over the peak's volume ``Π (2 sqrt(π) s_j)``.

The sums run over the voxels of each window in numba sweeps (no correlation plane): cheap beside
the deformation and FFT of a pass. Where WIDIM's correlation is zero-padded (``piv.zero_pad``) its
estimator divides the windows' overlap weighting out of the correlation (:func:`lfstudy.piv.engine._unweighted`);
the lag-±1 sums, over the n − 1 overlapping pairs of an n-voxel axis, are then divided by (n − 1)/n too
(``unweighted``), so σ stays that estimator's response (tested: σ of w covers 0.65 of the errors of noisy
depth-elongated particles, 0.38 left weighted).
"""

from __future__ import annotations

import numba
import numpy as np

from lfstudy.piv.subpixel import three_point

__all__ = ["window_uncertainty", "METHODS"]

#: Uncertainty estimators of :func:`window_uncertainty`.
METHODS = ("correlation", "moment", "independent")

#: Largest lag (voxels) over which neighbouring contributions ΔC_i are summed as correlated.
_MAX_LAG = 4


@numba.njit(cache=True)
def _window_means(a: np.ndarray, b: np.ndarray, w: int) -> tuple[float, float]:  # pragma: no cover - compiled
    """Means of window ``w`` of ``a`` and of ``b`` (n, Z, Y, X), summed in float64 (the windows are float32)."""
    _, nz, ny, nx = a.shape
    ma = 0.0
    mb = 0.0
    for i in range(nz):
        for j in range(ny):
            for k in range(nx):
                ma += a[w, i, j, k]
                mb += b[w, i, j, k]
    return ma / (nz * ny * nx), mb / (nz * ny * nx)


@numba.njit(parallel=True, cache=True)
def _sums(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Per window (n, Z, Y, X): [Σa², Σb², C0, then per axis (C+, C-, ΣΔC, ΣΔC², count)]."""
    n, nz, ny, nx = a.shape
    out = np.zeros((n, 18))
    for w in numba.prange(n):
        ma, mb = _window_means(a, b, w)
        s = np.zeros(18)
        for i in range(nz):
            for j in range(ny):
                for k in range(nx):
                    a0 = a[w, i, j, k] - ma
                    b0 = b[w, i, j, k] - mb
                    s[0] += a0 * a0
                    s[1] += b0 * b0
                    s[2] += a0 * b0
                    for ax in range(3):
                        ii, jj, kk = i, j, k
                        if ax == 0:
                            ii += 1
                            if ii >= nz:
                                continue
                        elif ax == 1:
                            jj += 1
                            if jj >= ny:
                                continue
                        else:
                            kk += 1
                            if kk >= nx:
                                continue
                        a1 = a[w, ii, jj, kk] - ma
                        b1 = b[w, ii, jj, kk] - mb
                        cp = a0 * b1  # a(i) b(i + e): lag +1
                        cm = a1 * b0  # a(i + e) b(i): lag -1
                        dc = cp - cm
                        o = 3 + 5 * ax
                        s[o] += cp
                        s[o + 1] += cm
                        s[o + 2] += dc
                        s[o + 3] += dc * dc
                        s[o + 4] += 1.0
        for q in range(18):  # element by element: a slice assignment compiles numba's shape check and its message
            out[w, q] = s[q]
    return out


@numba.njit(parallel=True, cache=True)
def _dc_factor(a: np.ndarray, b: np.ndarray, max_lag: int) -> np.ndarray:  # pragma: no cover - compiled
    """Per window (n, Z, Y, X) and axis k: Var(Σ ΔC_i) / Σ (ΔC_i − mean)², from the correlation of
    neighbouring contributions (separable: the product over the axes j of 1 + 2 Σ_l ρ_j(l), the sum
    of each positive lag's autocorrelation ρ_j(l) up to the first that is <= 0, at most ``max_lag``)."""
    n, nz, ny, nx = a.shape
    out = np.ones((n, 3))
    for w in numba.prange(n):
        ma, mb = _window_means(a, b, w)
        for k in range(3):
            ez = 1 if k == 0 else 0
            ey = 1 if k == 1 else 0
            ex = 1 if k == 2 else 0
            mz, my, mx = nz - ez, ny - ey, nx - ex
            if mz < 1 or my < 1 or mx < 1:
                continue
            d = np.empty((mz, my, mx))
            for i in range(mz):
                for j in range(my):
                    for q in range(mx):
                        a0 = a[w, i, j, q] - ma
                        b0 = b[w, i, j, q] - mb
                        a1 = a[w, i + ez, j + ey, q + ex] - ma
                        b1 = b[w, i + ez, j + ey, q + ex] - mb
                        d[i, j, q] = a0 * b1 - a1 * b0
            # explicit loops, not array expressions: inside the prange each would compile as a parfor of its own
            dm = 0.0
            for i in range(mz):
                for j in range(my):
                    for q in range(mx):
                        dm += d[i, j, q]
            dm /= d.size
            v0 = 0.0
            for i in range(mz):
                for j in range(my):
                    for q in range(mx):
                        d[i, j, q] -= dm
                        v0 += d[i, j, q] * d[i, j, q]
            v0 /= d.size
            if v0 <= 0.0:
                continue
            # every lag of every axis in one sweep over the field (the counts are the overlaps' sizes)
            acc = np.zeros((3, max_lag + 1))
            for i in range(mz):
                for j in range(my):
                    for q in range(mx):
                        v = d[i, j, q]
                        for lag in range(1, max_lag + 1):
                            if i + lag < mz:
                                acc[0, lag] += v * d[i + lag, j, q]
                            if j + lag < my:
                                acc[1, lag] += v * d[i, j + lag, q]
                            if q + lag < mx:
                                acc[2, lag] += v * d[i, j, q + lag]
            f = 1.0
            msz = (mz, my, mx)
            for ax in range(3):
                tot = 0.0
                for lag in range(1, min(max_lag, msz[ax] - 1) + 1):
                    cnt = (
                        (mz - (lag if ax == 0 else 0)) * (my - (lag if ax == 1 else 0)) * (mx - (lag if ax == 2 else 0))
                    )
                    rho = acc[ax, lag] / cnt / v0
                    if rho <= 0.0:
                        break
                    tot += rho
                f *= 1.0 + 2.0 * tot
            out[w, k] = f
    return out


def _gauss_offset(c0: np.ndarray, cp: np.ndarray, cm: np.ndarray) -> np.ndarray:
    """|offset| of the three-point estimator WIDIM uses (:func:`lfstudy.piv.subpixel.three_point`); NaN without a
    peak."""
    return np.abs(three_point(cm, c0, cp))


def window_uncertainty(
    a: np.ndarray, b: np.ndarray, method: str = "correlation", *, unweighted: bool = False
) -> np.ndarray:
    """Standard uncertainty of the displacement of each window pair, per array axis.

    Parameters
    ----------
    a, b : ndarray, shape (n, *w)
        The final pass's deformed (or offset) windows of frame 1 and 2, 2-D or 3-D
        windows; they should match at lag 0 (a converged pass).
    method : {"correlation", "moment", "independent"}
        Estimator (module docstring).
    unweighted : bool
        The lag-±1 sums divided by their overlap weighting (n − 1)/n along the axis, as WIDIM's estimator divides
        a zero-padded correlation (:func:`lfstudy.piv.engine._unweighted`), so that σ is that estimator's response;
        False (a circular plane) leaves them as they are.

    Returns
    -------
    ndarray, shape (n, nd)
        σ of the displacement along each array axis [voxels]; NaN where a window
        has no correlation peak at lag 0 (empty, or the peak is not the maximum).
    """
    if method not in METHODS:
        raise ValueError(f"`uncertainty` must be one of {METHODS} or None; got {method!r}")
    nd = a.ndim - 1
    a4 = np.ascontiguousarray(a, dtype=np.float32).reshape((a.shape[0],) + (1,) * (3 - nd) + a.shape[1:])
    b4 = np.ascontiguousarray(b, dtype=np.float32).reshape(a4.shape)
    s = _sums(a4, b4)
    fac = _dc_factor(a4, b4, _MAX_LAG) if method == "correlation" else None
    saa, sbb, c0 = s[:, 0], s[:, 1], s[:, 2]
    out = np.empty((a.shape[0], nd))
    for k in range(nd):  # array axis k of the window is axis 3 - nd + k of the kernel
        o = 3 + 5 * (3 - nd + k)
        cp, cm, s1, s2, cnt = (s[:, o + j] for j in range(5))
        # the lag-±1 sums run over the n − 1 voxel pairs that overlap along the axis, the peak's over n: divided by
        # that weighting where WIDIM's estimator divides its correlation by it, so σ is the estimator's own response
        unw = a.shape[1 + k] / max(a.shape[1 + k] - 1, 1) if unweighted else 1.0
        cp, cm = cp * unw, cm * unw
        with np.errstate(divide="ignore", invalid="ignore"):
            if method in ("correlation", "independent"):
                sig_dc = unw * np.sqrt(np.maximum(s2 - s1 * s1 / np.maximum(cnt, 1.0), 0.0))
                if method == "correlation":
                    sig_dc = sig_dc * np.sqrt(fac[:, 3 - nd + k])
                cbar = 0.5 * (cp + cm)
                sig = _gauss_offset(c0, cbar + 0.5 * sig_dc, cbar - 0.5 * sig_dc)
            else:
                ok = (c0 > 0) & (cp > 0) & (cm > 0)
                curv = 2 * np.log(np.where(ok, c0, 1.0)) - np.log(np.where(ok, cp, 1.0)) - np.log(np.where(ok, cm, 1.0))
                out[:, k] = np.where(ok & (curv > 0), 1.0 / np.sqrt(np.where(curv > 0, curv, 1.0)), np.nan)
                continue
        out[:, k] = np.where((c0 > cp) & (c0 > cm), sig, np.nan)
    if method == "moment":
        width = out  # peak widths s_k
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = c0 / np.sqrt(saa * sbb)
            n_eff = np.prod(a.shape[1:]) / np.prod(2.0 * np.sqrt(np.pi) * width, axis=1)
            nsr = np.sqrt(np.maximum(1.0 - rho, 0.0) / rho)
            out = width * (nsr / np.sqrt(n_eff))[:, None]
            out[~((n_eff > 0) & (rho > 0))] = np.nan
    return out
