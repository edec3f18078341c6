"""What a measurement can say about itself, without a known flow.

Per pair of frames: the vector count and valid % (the normalised median test,
sec. 6.1.3), the correlation-peak ratio (primary over secondary correlation
peak of each final window: the detectability of Keane & Adrian, Meas. Sci.
Technol. 1992, the usual signal-to-noise measure of a PIV correlation; the
thesis does not use it), the correlation peak height, and the divergence of
the measured displacement field: an incompressible flow has none, so what the
field shows is measurement error (or compressibility, or out-of-volume motion).

Pure functions of arrays and xarray objects; :func:`pair_metrics` collects them
for one pair as a Dataset of scalars with units.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr

__all__ = ["peak_ratio", "divergence", "pair_metrics", "median_uncertainty"]

_DIMS = ("z", "y", "x")
_COMP = {"z": "w", "y": "v", "x": "u"}


def _windows(vol: np.ndarray, starts: np.ndarray, w: Sequence[int]) -> np.ndarray:
    """Windows ``vol[s : s + w]`` for every row of ``starts`` (zero beyond the volume), float32."""
    w = tuple(int(n) for n in w)
    pad = [
        (max(0, -int(starts[:, ax].min())), max(0, int(starts[:, ax].max()) + w[ax] - vol.shape[ax]))
        for ax in range(vol.ndim)
    ]
    src = np.pad(vol.astype(np.float32, copy=False), pad)
    view = np.lib.stride_tricks.sliding_window_view(src, w)
    idx = starts + np.array([p[0] for p in pad])
    return view[tuple(idx.T)].astype(np.float32)


def _ratio_batch(wa: np.ndarray, wb: np.ndarray) -> np.ndarray:
    """Primary / secondary peak of the mean-removed cross-correlation of window pairs (n, *w)."""
    from scipy import fft as sfft
    from scipy.ndimage import maximum_filter

    nd = wa.ndim - 1
    axes = tuple(range(1, nd + 1))
    wa = wa - wa.mean(axis=axes, keepdims=True)
    wb = wb - wb.mean(axis=axes, keepdims=True)
    r = sfft.irfftn(np.conj(sfft.rfftn(wa, axes=axes)) * sfft.rfftn(wb, axes=axes), s=wa.shape[1:], axes=axes)
    n = r.shape[0]
    flat = r.reshape(n, -1)
    i1 = flat.argmax(axis=1)
    p1 = flat[np.arange(n), i1]
    # the secondary peak: the highest other local maximum (27-neighbourhood, circular plane), so the
    # shoulders of a peak elongated in depth are not taken for a second peak
    local = r >= maximum_filter(r, size=(1,) + (3,) * nd, mode="wrap")
    cand = np.where(local, r, -np.inf).reshape(n, -1)
    cand[np.arange(n), i1] = -np.inf
    p2 = cand.max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where((p1 > 0) & (p2 > 0), p1 / np.where(p2 > 0, p2, 1.0), np.nan)
    return out


def peak_ratio(a: Any, b: Any, piv: xr.Dataset, *, max_voxels: int = 2**24) -> xr.DataArray:
    """Correlation-peak ratio of every final PIV window: primary over secondary peak.

    The windows of the final pass (``piv.attrs["final_window"]`` at the window
    centres ``<dim>_index``) are offset symmetrically by the measured
    displacement rounded to whole voxels (the discrete window offset of sec.
    6.1.4), mean-removed and cross-correlated (eq. 6.1 by FFT, sec. 6.1.2); the
    ratio of the highest correlation peak to the second-highest local maximum
    is the peak ratio (detectability): about 1 for noise, larger the more
    clearly one displacement wins. Windows without a positive secondary peak
    get NaN.

    Parameters
    ----------
    a, b : array-like or DataArray
        The two volumes (z, y, x) the PIV correlated.
    piv : xarray.Dataset
        Its result (:func:`lfstudy.piv.widim`).
    max_voxels : int
        Correlation-plane voxels per batch (bounds memory).

    Returns
    -------
    xarray.DataArray
        ``peak_ratio`` on the PIV grid (units 1).
    """
    va = np.asarray(a.values if isinstance(a, xr.DataArray) else a)
    vb = np.asarray(b.values if isinstance(b, xr.DataArray) else b)
    dims = _DIMS[-va.ndim :]
    w = np.asarray(piv.attrs["final_window"], dtype=int)
    centres = np.meshgrid(*[piv[f"{d}_index"].values for d in dims], indexing="ij")
    disp = [piv[_COMP[d]].values for d in dims]
    # window origins (integer: widim's nodes), and the displacement rounded to whole voxels
    lo = np.rint(np.stack([c.ravel() - (wi - 1) / 2.0 for c, wi in zip(centres, w)], axis=1)).astype(int)
    d = np.rint(np.stack([di.ravel() for di in disp], axis=1)).astype(int)
    ahead = np.floor(d / 2.0 + 0.5).astype(int)  # b's window moves ahead by about half of it, a's back
    sa, sb = lo - (d - ahead), lo + ahead
    n = sa.shape[0]
    batch = max(1, int(max_voxels // int(np.prod(w))))
    out = np.empty(n)
    for k0 in range(0, n, batch):
        k1 = min(n, k0 + batch)
        out[k0:k1] = _ratio_batch(_windows(va, sa[k0:k1], w), _windows(vb, sb[k0:k1], w))
    return xr.DataArray(
        out.reshape(centres[0].shape),
        dims=dims,
        coords={d: piv[d] for d in dims},
        name="peak_ratio",
        attrs={
            "units": "1",
            "long_name": "correlation-peak ratio (primary / secondary peak) of the final windows",
        },
    )


def divergence(piv: xr.Dataset, dt: float | None = None) -> xr.DataArray:
    """Divergence of the measured displacement field, ∂u/∂x + ∂v/∂y + ∂w/∂z.

    Central differences (one-sided at the edges) of the physical
    displacements ``u_mm, v_mm, w_mm`` over the window-centre coordinates
    [mm]: the volume change per frame interval, dimensionless. Divided by
    ``dt`` it is the velocity divergence [1/s].

    Parameters
    ----------
    piv : xarray.Dataset
        A 3-D PIV result with physical coordinates (:func:`lfstudy.piv.widim` of
        volumes with x, y, z in mm), at least two windows along every axis.
    dt : float, optional
        Time between the frames [s].

    Raises
    ------
    ValueError
        Without ``*_mm`` displacements, or with a single window along an axis.
    """
    for d in _DIMS:
        if f"{_COMP[d]}_mm" not in piv:
            raise ValueError(f"divergence needs the physical displacement {_COMP[d]}_mm (volumes with mm coordinates)")
        if piv.sizes.get(d, 0) < 2:
            raise ValueError(f"divergence needs at least 2 windows along {d}; the field has {piv.sizes.get(d, 0)}")
    div = sum(
        np.gradient(piv[f"{_COMP[d]}_mm"].values, piv[d].values, axis=ax) for ax, d in enumerate(piv[_COMP["x"]].dims)
    )
    units, what = ("1/s", "velocity divergence") if dt else ("1/frame", "divergence of the displacement per frame")
    return xr.DataArray(
        div / dt if dt else div,
        dims=piv[_COMP["x"]].dims,
        coords={d: piv[d] for d in piv[_COMP["x"]].dims},
        name="divergence",
        attrs={"units": units, "long_name": what},
    )


def median_uncertainty(sigma: np.ndarray, valid: np.ndarray) -> float:
    """The median standard uncertainty of the valid vectors that have one.

    Parameters
    ----------
    sigma : ndarray
        Per-vector standard uncertainty of one component (``unc_<c>`` of
        :func:`lfstudy.piv.widim`: NaN for an invalid or replaced vector).
    valid : ndarray of bool
        The vectors' validity (same shape).

    Returns
    -------
    float
        The median over the valid vectors with a finite σ; NaN when there is none.
    """
    s = np.asarray(sigma, dtype=float)[np.asarray(valid, dtype=bool)]
    s = s[np.isfinite(s)]
    return float(np.median(s)) if s.size else float("nan")


def _scalar(value: float, units: str, long_name: str) -> tuple[tuple, float, dict[str, str]]:
    return ((), float(value), {"units": units, "long_name": long_name})


def pair_metrics(piv: xr.Dataset, ratio: xr.DataArray | None = None, *, dt: float | None = None) -> xr.Dataset:
    """The measurement metrics of one pair as a Dataset of scalars.

    Parameters
    ----------
    piv : xarray.Dataset
        The pair's PIV result (3-D, physical coordinates).
    ratio : xarray.DataArray, optional
        :func:`peak_ratio` of the pair.
    dt : float, optional
        Time between the frames [s] (divergence in 1/s, else per frame).

    Returns
    -------
    xarray.Dataset
        ``n_vectors``, ``valid_percent``, ``empty_percent`` (windows without signal in
        a frame, correlation peak 0: nothing was there to measure, e.g. beyond the
        seeded depth, and these count as invalid), ``peak_median`` (correlation peak
        height), ``peak_ratio_median`` and ``peak_ratio_p10`` (valid vectors),
        ``mean_<c>``/``std_<c>`` [voxel] and ``mean_<c>_mm`` [mm] per component of valid
        vectors, ``unc_median_<c>`` [voxel] and ``unc_median_<c>_mm`` [mm] (median standard
        uncertainty of the valid vectors, :func:`median_uncertainty`; only where the result holds
        ``unc_<c>``), ``divergence_rms``, ``divergence_mean`` (valid vectors),
        ``divergence_norm`` (RMS divergence over √3 times the RMS of the
        full displacement gradient: 0 for a solenoidal field, 1 for a pure
        isotropic expansion); where the result holds the flags of
        :mod:`lfstudy.piv.resolution`, ``partial_percent`` (valid vectors whose window
        reaches past the seeded region) and ``unresolved_percent`` (valid vectors of full
        windows flagged unresolved, of the valid full-window vectors); where the paired PIV weighed its tracks by
        depth (``piv.paired_weights`` ``depth``), ``focus_scatter_ratio`` (the tracks' scatter in the band of |z|
        nearest the focal plane over the best band's, :func:`lfstudy.study.particle_metrics.focus_scatter_ratio`:
        well above 1, the focal plane inside the volume limits the recording's depth; NaN with too few tracks for
        two bands).
    """
    valid = piv["valid"].values.astype(bool)
    ok = valid if valid.any() else np.zeros_like(valid)
    out: dict[str, Any] = {
        "n_vectors": ((), int(valid.size), {"units": "1", "long_name": "vectors"}),
        "valid_percent": _scalar(100.0 * valid.mean(), "percent", "valid vectors (normalised median test)"),
        # WIDIM gives a window that is blank in either frame peak 0 and marks it invalid: a particle
        # reconstruction (IPR) leaves the grid exactly 0 where no particle is, so on a grid deeper than
        # the seeded volume these are most of its invalid vectors (benchmarks/bench_recording.py)
        "empty_percent": _scalar(
            100.0 * float(np.mean(piv["peak"].values <= 0)), "percent", "empty windows (no signal in a frame)"
        ),
        "peak_median": _scalar(
            np.median(piv["peak"].values[ok]) if ok.any() else np.nan, "1", "median correlation peak (valid vectors)"
        ),
    }
    if ratio is not None:
        r = ratio.values[ok]
        r = r[np.isfinite(r)]
        out["peak_ratio_median"] = _scalar(np.median(r) if r.size else np.nan, "1", "median correlation-peak ratio")
        out["peak_ratio_p10"] = _scalar(
            np.percentile(r, 10) if r.size else np.nan, "1", "10th percentile of the correlation-peak ratio"
        )
    for d in _DIMS:
        c = _COMP[d]
        if c not in piv:
            continue
        vals = piv[c].values[ok]
        out[f"mean_{c}"] = _scalar(vals.mean() if vals.size else np.nan, "voxel", f"mean {d} displacement")
        out[f"std_{c}"] = _scalar(vals.std() if vals.size else np.nan, "voxel", f"std of the {d} displacement")
        if f"{c}_mm" in piv:
            mm = piv[f"{c}_mm"].values[ok]
            out[f"mean_{c}_mm"] = _scalar(mm.mean() if mm.size else np.nan, "mm", f"mean {d} displacement")
        for sfx, units in (("", "voxel"), ("_mm", "mm")):
            if f"unc_{c}{sfx}" in piv:
                out[f"unc_median_{c}{sfx}"] = _scalar(
                    median_uncertainty(piv[f"unc_{c}{sfx}"].values, valid),
                    units,
                    f"median standard uncertainty of the {d} displacement (valid vectors)",
                )
    if "partial" in piv:
        part = piv["partial"].values.astype(bool)
        out["partial_percent"] = _scalar(
            100.0 * float(part[ok].mean()) if ok.any() else np.nan, "percent", "valid vectors of partial windows"
        )
        if "unresolved" in piv:
            full = ok & ~part
            out["unresolved_percent"] = _scalar(
                100.0 * float(piv["unresolved"].values.astype(bool)[full].mean()) if full.any() else np.nan,
                "percent",
                "valid full-window vectors flagged unresolved",
            )
    if piv.attrs.get("paired_weights") == "depth":  # every pair alike (one config): NaN where too few tracks
        from lfstudy.study.particle_metrics import focus_scatter_ratio

        out["focus_scatter_ratio"] = _scalar(
            focus_scatter_ratio(piv.attrs), "1", "paired tracks' scatter nearest focus over the best depth band's"
        )
    try:
        div = divergence(piv, dt)
    except ValueError:
        div = None
    if div is not None:
        dv = div.values[ok]
        units = div.attrs["units"]
        out["divergence_rms"] = _scalar(np.sqrt(np.mean(dv**2)) if dv.size else np.nan, units, "RMS divergence")
        out["divergence_mean"] = _scalar(dv.mean() if dv.size else np.nan, units, "mean divergence")
        grad2 = np.zeros(div.shape)
        for d in _DIMS:
            comp = piv[f"{_COMP[d]}_mm"].values
            for ax, e in enumerate(piv[_COMP["x"]].dims):
                grad2 += np.gradient(comp, piv[e].values, axis=ax) ** 2
        g = np.sqrt(np.mean(grad2[ok])) if ok.any() else np.nan
        # |div| <= sqrt(3) |grad d| (Frobenius): the ratio is 1 for a pure isotropic expansion
        rms_div = np.sqrt(np.mean(div.values[ok] ** 2)) * (dt or 1.0)
        norm = rms_div / (np.sqrt(3.0) * g) if ok.any() and g > 0 else np.nan
        out["divergence_norm"] = _scalar(norm, "1", "normalised RMS divergence")
        out["divergence_norm"][2]["description"] = (
            "RMS divergence / (sqrt(3) RMS displacement gradient): 0 for a solenoidal field, 1 for a pure expansion"
        )
    return xr.Dataset(out)
