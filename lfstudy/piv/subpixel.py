"""The three-point sub-voxel peak estimator, shared by the correlation and the uncertainty.

One estimator, so the displacement WIDIM measures (:mod:`lfstudy.piv.engine`) and the uncertainty
that turns the correlation's asymmetry into a displacement (:mod:`lfstudy.piv.uncertainty`) read a
peak the same way.
"""

from __future__ import annotations

import numpy as np

__all__ = ["three_point"]


def three_point(rm: np.ndarray, r0: np.ndarray, rp: np.ndarray) -> np.ndarray:
    """Offset of a peak from its integer maximum through three samples (lags −1, 0, +1).

    The three-point Gaussian (thesis eq. 6.2)

        d = (ln R− − ln R+) / (2 ln R− − 4 ln R0 + 2 ln R+)

    where all three are positive and the log-curvature is negative, else the parabola through
    them, ``(R− − R+) / (2 R− − 4 R0 + 2 R+)``, where its curvature is negative (a log of a
    non-positive value is undefined; shifting the samples by their minimum instead would bias the
    Gaussian).

    Parameters
    ----------
    rm, r0, rp : ndarray
        The samples at lags −1, 0 and +1 (broadcast together).

    Returns
    -------
    ndarray of float64
        The signed offset [samples]; NaN where neither fit has a maximum (no peak).
    """
    rm, r0, rp = (np.asarray(v, dtype=np.float64) for v in (rm, r0, rp))
    pos = (rm > 0) & (r0 > 0) & (rp > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lm, l0, lp = (np.log(np.where(pos, v, 1.0)) for v in (rm, r0, rp))
        gden = 2 * lm - 4 * l0 + 2 * lp
        gauss = (lm - lp) / gden  # eq. 6.2
        pden = 2 * rm - 4 * r0 + 2 * rp
        parab = (rm - rp) / pden
    return np.where(pos & (gden < 0), gauss, np.where(pden < 0, parab, np.nan))
