"""Errors of a light-field PIV case against the known flow (thesis ch. 7).

Pure computations over xarray objects, no file I/O (the study table and the
stage times are in :mod:`lfstudy.study.table`):

- :func:`case_errors`: true displacement at every PIV window centre, the error
  field per component (measured − true) in voxels and mm, and per-case
  scalars (bias, RMS, standard deviation, valid %, mean and spread of the
  measured displacement, peak locking) as in sec. 7.1–7.4;
- :func:`reconstruction_quality`: the reconstruction quality factor Q of
  Elsinga et al. (2006) against :func:`render_truth`;
- :func:`oracle_metrics` and :func:`error_budget`: the same statistics of the
  *oracle* (the case's PIV on the true particle volumes,
  :func:`lfstudy.study.case.oracle_piv`) and the error the reconstruction adds
  to it, in quadrature;
- :func:`case_metrics`: all of a case's metrics (the above, the field of view and
  the depth gain), what the workflow's errors stage writes.

Every scalar's units and long name come from the metric table
(:mod:`lfstudy.study.metric_table`), not from here.

Sign convention: everything is in the object frame (+z away from the camera).
A particle moved +0.5625 mm in x images as +4.5 voxels of 0.125 mm; the
thesis' histograms (Fig. 7.2: mean −4.45 px) carry the opposite sign.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import xarray as xr
from scipy.special import ndtr

from lfstudy.reconstruct.truth import render_truth
from lfstudy.simulate.flows import Flow, true_displacement
from lfstudy.study import metric_table
from lfstudy.study.metric_table import metric_attrs

__all__ = [
    "AXES",
    "case_errors",
    "error_statistics",
    "peak_locking_c1",
    "locking_excess",
    "reconstruction_quality",
    "render_truth",
    "field_of_view",
    "particles_per_cell",
    "depth_gain",
    "crosstalk_z",
    "binned_uncertainty",
    "window_average",
    "unresolved_scores",
    "oracle_metrics",
    "oracle_uncertainty",
    "oracle_error",
    "quadrature_excess",
    "error_budget",
    "with_metrics",
    "case_metrics",
]

#: Displacement component of each axis (pivpy names) and its array dimension.
AXES: dict[str, str] = {"x": "u", "y": "v", "z": "w"}


def _attrs(units: str, long_name: str, **extra: Any) -> dict[str, Any]:
    return {"units": units, "long_name": long_name, **extra}


def _table_attrs(ds: xr.Dataset) -> None:
    """Every 0-d variable's units and long name, from the metric table (a ``KeyError`` for one it lacks)."""
    for name, var in ds.data_vars.items():
        if var.ndim == 0:
            var.attrs = {**metric_attrs(str(name)), **var.attrs}


def _scalar(value: float) -> tuple[tuple[()], float, dict[str, str]]:
    """A 0-d variable (set it as ``out[name] = ...``); its attrs are added from the metric table."""
    return ((), value, {})


# --------------------------------------------------------------- statistics
def error_statistics(error: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """Bias, RMS and standard deviation of the errors selected by ``mask``.

    Parameters
    ----------
    error : ndarray
        Error values (measured − true).
    mask : ndarray of bool
        Vectors to include (valid and finite); broadcast against ``error``.

    Returns
    -------
    bias, rms, std : float
        Mean error, root-mean-square error and population standard deviation
        (ddof = 0, so rms² = bias² + std² exactly). NaN, without a warning,
        when no vector is selected.
    """
    e = np.asarray(error, dtype=float)[np.broadcast_to(mask, np.shape(error))]
    if e.size == 0:
        return math.nan, math.nan, math.nan
    bias = float(e.mean())
    rms = float(np.sqrt(np.mean(e * e)))
    std = float(e.std())
    return bias, rms, std


def peak_locking_c1(displacement: np.ndarray, *, bins: int = 10) -> float:
    """Degree of peak locking C1 of Christensen (2004), in [0, 1].

    The fractional parts of the measured displacements (voxels) are
    histogrammed into ``bins`` equal bins over one voxel (Christensen uses
    0.1 px bins); ``C1 = 1 − N_min / N_max``. 0 means fractional parts spread
    evenly (no locking), 1 that some sub-voxel bin is empty.

    C1 presumes a broad displacement distribution (turbulence, the vortex of
    sec. 7.4). For a uniform displacement the fractional parts sit in one or
    two bins *by construction* and C1 is ~1 whatever the estimator; compare
    C1 only between cases of the same flow, and use :func:`locking_excess`
    for a figure that accounts for the truth.

    Returns
    -------
    float
        C1, or NaN if ``displacement`` holds no finite value.
    """
    d = np.asarray(displacement, dtype=float).ravel()
    d = d[np.isfinite(d)]
    if d.size == 0:
        return math.nan
    frac = d - np.floor(d)
    n = np.bincount(np.minimum((frac * bins).astype(np.int64), bins - 1), minlength=bins)
    return float(1.0 - n.min() / n.max())


def locking_excess(measured: np.ndarray, true: np.ndarray, *, half_width: float = 0.25) -> float:
    """Excess fraction of measured displacements near an integer voxel, in [−1, 1].

    ``F_meas`` is the fraction of measured displacements within ``half_width``
    voxels of an integer. ``F_ref`` is the same fraction expected if the
    errors were Gaussian about the truth with the observed bias and standard
    deviation (no locking): the mean over vectors of
    P(|t_i + b + σZ − k| < h for some integer k), Z ~ N(0, 1). The figure is
    ``F_meas − F_ref``: ~0 for an unbiased-in-sub-voxel-position estimator,
    positive when the estimates pile up on integers (the bimodal histogram of
    Fig. 7.8: a true 2.5 voxel shift measured as 2 or 3). Unlike
    :func:`peak_locking_c1` it is meaningful for a uniform displacement.

    Returns
    -------
    float
        ``F_meas − F_ref``; NaN if there is no finite pair.
    """
    m = np.asarray(measured, dtype=float).ravel()
    t = np.broadcast_to(np.asarray(true, dtype=float), np.shape(measured)).ravel()
    ok = np.isfinite(m) & np.isfinite(t)
    if not ok.any():
        return math.nan
    m, t = m[ok], t[ok]
    f_meas = float(np.mean(np.abs(m - np.rint(m)) < half_width))
    err = m - t
    b, s = float(err.mean()), float(err.std())
    mu = t + b
    if s == 0.0:
        f_ref = float(np.mean(np.abs(mu - np.rint(mu)) < half_width))
    else:
        # Probability mass of N(mu, s) within ±h of each integer k near mu.
        reach = math.ceil(6.0 * s) + 1
        k = np.rint(mu)[:, None] + np.arange(-reach, reach + 1)[None, :]
        p = ndtr((k + half_width - mu[:, None]) / s) - ndtr((k - half_width - mu[:, None]) / s)
        f_ref = float(np.mean(p.sum(axis=1)))
    return f_meas - f_ref


# ------------------------------------------------------------ voxel size
def _voxel_steps(
    piv: xr.Dataset, voxel_size: float | Sequence[float] | Mapping[str, float] | None
) -> dict[str, np.ndarray]:
    """Voxel size [mm] per axis at each window centre (1-D along that axis)."""
    out: dict[str, np.ndarray] = {}
    for i, ax in enumerate(("x", "y", "z")):
        if ax not in piv.dims:
            continue
        n = piv.sizes[ax]
        if voxel_size is not None:
            if isinstance(voxel_size, Mapping):
                val = voxel_size[ax]
            elif np.ndim(voxel_size) == 0:
                val = voxel_size
            else:  # (x, y, z) order
                val = list(voxel_size)[i]
            out[ax] = np.full(n, float(val))
            continue
        idx = f"{ax}_index"
        if idx in piv.coords and n > 1:
            # Window centres in mm over centres in voxel index: the local step,
            # as WIDIM used for *_mm (z planes need not be evenly spaced).
            out[ax] = np.abs(np.gradient(piv[ax].values.astype(float)) / np.gradient(piv[idx].values.astype(float)))
            continue
        spacing = piv.attrs.get("final_spacing")
        dims = [d for d in ("z", "y", "x") if d in piv.dims]
        if spacing is not None and n > 1 and len(spacing) == len(dims):
            # Window-centre step [mm] over the final window spacing [voxels].
            sp = float(spacing[dims.index(ax)])
            out[ax] = np.abs(np.gradient(piv[ax].values.astype(float))) / sp
            continue
        comp = AXES[ax]
        if comp in piv and f"{comp}_mm" in piv:
            vox, mm = piv[comp].values, piv[f"{comp}_mm"].values
            ok = np.isfinite(vox) & np.isfinite(mm) & (np.abs(vox) > 1e-9)
            if ok.any():
                out[ax] = np.full(n, float(np.median(np.abs(mm[ok] / vox[ok]))))
                continue
        raise ValueError(
            f"case_errors: cannot infer the voxel size along {ax} (no '{idx}' coordinate, no non-zero "
            f"'{comp}'/'{comp}_mm' pair); pass voxel_size=(dx, dy, dz) in mm"
        )
    return out


# --------------------------------------------------------------- case errors


def _truth_at(flow: Any, pts: Mapping[str, np.ndarray], dt: float, n_steps: int) -> tuple[np.ndarray, ...]:
    """The true displacement (x, y, z, mm) at points given per axis (an axis left out is at 0), integrated
    about the midpoint of the frames' interval, as the PIV vectors are."""
    zeros = np.zeros(np.shape(next(iter(pts.values()))))
    xyz = (pts.get(ax, zeros) for ax in ("x", "y", "z"))
    return true_displacement(flow, *xyz, dt=dt, n_steps=n_steps, reference="midpoint")


def case_errors(
    piv: xr.Dataset,
    flow: Flow,
    *,
    dt: float = 1.0,
    n_steps: int = 100,
    voxel_size: float | Sequence[float] | Mapping[str, float] | None = None,
    window_truth: bool = True,
) -> xr.Dataset:
    """Error of a PIV result against the known flow, field and per-case scalars (ch. 7).

    Parameters
    ----------
    piv : xarray.Dataset
        WIDIM result (``lfstudy.piv.widim``): dims ``("z", "y", "x")`` of window
        centres with coords in mm (object frame), ``u, v, w`` [voxel] and/or
        ``u_mm, v_mm, w_mm`` [mm], ``valid`` (bool).
    flow : Flow
        The imposed flow (``lfstudy.simulate.flows.flow_from_config``).
    dt, n_steps : float, int
        Time separation and RK4 sub-steps of the true displacement.
    voxel_size : float, (dx, dy, dz) or mapping, optional
        Voxel size [mm]. By default the local step at each window centre,
        window centre [mm] over window centre [voxel index] (the ``x_index``
        coords of WIDIM), else the window-centre step over the ``final_spacing``
        attribute, else the median ratio ``u_mm / u``.
    window_truth : bool
        Average the truth over each vector's final window (:func:`window_average`; the result's
        ``final_window`` attribute) for the filter and uncertainty figures; False skips that cost
        (they are then NaN).

    Returns
    -------
    xarray.Dataset
        Fields over the PIV grid: ``<c>_true`` / ``<c>_true_mm`` (true
        displacement at the window centre, midpoint reference, i.e. the path
        of the particle centred on the window), ``<c>_err`` / ``<c>_err_mm``
        (measured − true, NaN where invalid) for c in u, v, w, ``unc_<c>`` /
        ``unc_<c>_mm`` (the PIV's standard uncertainty of the same vectors, NaN where
        the error is; only where the PIV result holds one) and ``voxel_<ax>``. Scalars,
        over valid vectors with finite values, for ax in x, y, z (``_mm`` suffix: in mm, else voxels):

        - ``bias_<ax>``: mean error; ``rms_<ax>``: RMS error; ``std_<ax>``:
          standard deviation of the error (ddof 0, rms² = bias² + std²);
          ``rms_total``: sqrt(rms_x² + rms_y² + rms_z²);
        - ``mean_<ax>``: mean of the *measured* displacement (cf. Fig. 7.2:
          μ = −4.45 px in the thesis' image-frame sign; ours is +; for a
          uniform flow ``std_<ax>`` is the σ of its histogram), ``true_<ax>``:
          mean true displacement;
        - ``locking_excess_<ax>`` (:func:`locking_excess`), a peak-locking
          figure that holds for uniform displacements too;
        - ``unc_coverage_<ax>``, ``unc_ratio_<ax>`` (:func:`uncertainty_calibration`):
          how well the PIV's per-vector uncertainty ``unc_<c>[_mm]`` measures the
          error against the truth averaged over each vector's final window, what the
          window measures (NaN where the result has no uncertainty or no ``final_window``);
          ``unc_coverage_point_<ax>``, ``unc_ratio_point_<ax>``: the same against the
          point truth (the window's filtering counted as error);
        - ``filter_rms_<ax>_mm``, ``filter_rms_total_mm``: RMS of the windows' filtering
          of the truth, the window-averaged minus the point truth (:func:`window_average`;
          also per vector as ``<c>_filter_mm``); NaN without ``final_window``;
        - ``true_mag_mm`` (mean |true displacement|) and ``rel_error`` (total
          RMS error in mm over it): comparable across designs;
        - ``window_mm_<ax>``, ``spacing_mm_<ax>`` (final window and vector
          spacing in mm) and ``depth_mm`` (depth spanned by valid vectors);
        - ``crosstalk_z`` (:func:`crosstalk_z`): spurious w per unit of lateral
          shift of a uniform flow, NaN for any other;
        - ``unresolved_percent``, ``unresolved_hit``, ``unresolved_false``
          (:func:`unresolved_scores`): the PIV's truth-free ``unresolved`` flag against the
          true filtering, over the valid vectors whose windows are not ``partial`` (NaN without
          the flag, σ or ``final_window``); ``partial_percent``: valid vectors whose window lies
          partly outside the seeded region (the PIV's ``partial``, NaN without it);
        - ``n_vectors``, ``n_valid``, ``valid_percent``.

        With no valid vector every statistic is NaN and ``valid_percent`` is 0
        (no exception, no warning).
    """
    steps = _voxel_steps(piv, voxel_size)
    dims = tuple(d for d in ("z", "y", "x") if d in piv.dims)
    axes = [ax for ax in ("x", "y", "z") if ax in dims]
    grid = xr.broadcast(*(piv[d] for d in dims))
    pts = {d: g.transpose(*dims).values.astype(float) for d, g in zip(dims, grid)}
    tx, ty, tz = _truth_at(flow, pts, dt, n_steps)
    zeros = np.zeros_like(pts[dims[0]])
    true_mm = {"x": tx, "y": ty, "z": tz}

    valid = piv["valid"].transpose(*dims).values.astype(bool) if "valid" in piv else np.ones(zeros.shape, bool)
    coords = {d: piv[d] for d in dims}
    out = xr.Dataset(coords=coords)
    fin = valid.copy()
    meas_vox: dict[str, np.ndarray] = {}
    meas_mm: dict[str, np.ndarray] = {}
    step_b: dict[str, np.ndarray] = {}
    for ax in axes:
        c = AXES[ax]
        shp = [1] * len(dims)
        shp[dims.index(ax)] = -1
        step = steps[ax].reshape(shp)
        step_b[ax] = step
        if c in piv:
            vx = piv[c].transpose(*dims).values.astype(float)
            mm = piv[f"{c}_mm"].transpose(*dims).values.astype(float) if f"{c}_mm" in piv else vx * step
        elif f"{c}_mm" in piv:
            mm = piv[f"{c}_mm"].transpose(*dims).values.astype(float)
            vx = mm / step
        else:
            raise ValueError(f"case_errors: the PIV result has neither '{c}' nor '{c}_mm'")
        meas_vox[ax], meas_mm[ax] = vx, mm
        fin &= np.isfinite(vx) & np.isfinite(mm) & np.isfinite(true_mm[ax])
        out[f"voxel_{ax}"] = (ax, steps[ax], _attrs("mm", f"voxel size along {ax} at the window centre"))

    n_vec = int(valid.size)
    n_valid = int(fin.sum())
    filt = _window_truth(piv, flow, pts, dims, steps, dt=dt, n_steps=n_steps) if window_truth else None
    for ax in axes:
        c = AXES[ax]
        t_mm = np.broadcast_to(true_mm[ax], zeros.shape)
        t_vx = t_mm / step_b[ax]
        e_mm = np.where(fin, meas_mm[ax] - t_mm, np.nan)
        e_vx = np.where(fin, meas_vox[ax] - t_vx, np.nan)
        out[f"{c}_true"] = (dims, t_vx, _attrs("voxel", f"true {ax} displacement at the window centre"))
        out[f"{c}_true_mm"] = (dims, t_mm, _attrs("mm", f"true {ax} displacement at the window centre"))
        out[f"{c}_err"] = (dims, e_vx, _attrs("voxel", f"{ax} displacement error (measured − true)"))
        out[f"{c}_err_mm"] = (dims, e_mm, _attrs("mm", f"{ax} displacement error (measured − true)"))
        for err, meas, tru, sfx in ((e_vx, meas_vox[ax], t_vx, ""), (e_mm, meas_mm[ax], t_mm, "_mm")):
            bias, rms, std = error_statistics(err, fin)
            mb = error_statistics(meas, fin)[0]  # mean of the measured values
            tb = error_statistics(tru, fin)[0]
            out[f"bias_{ax}{sfx}"] = _scalar(bias)
            out[f"rms_{ax}{sfx}"] = _scalar(rms)
            out[f"std_{ax}{sfx}"] = _scalar(std)
            out[f"mean_{ax}{sfx}"] = _scalar(mb)
            out[f"true_{ax}{sfx}"] = _scalar(tb)
        mv = meas_vox[ax][fin]
        # C1 (peak_locking_c1) reads ~1 for any uniform displacement, so the study keeps the
        # truth-aware excess near-integer fraction instead
        out[f"locking_excess_{ax}"] = _scalar(locking_excess(mv, t_vx[fin]))
        sigma_mm = _uncertainty_mm(piv, c, dims, step_b[ax])
        if sigma_mm is not None:  # per vector beside its error (the report's error-against-σ figure)
            s_mm = np.where(fin, sigma_mm, np.nan)
            desc = f"standard uncertainty of the {ax} displacement (unc_{c} of the PIV; NaN where the error is)"
            out[f"unc_{c}"] = (dims, s_mm / np.abs(step_b[ax]), _attrs("voxel", desc))
            out[f"unc_{c}_mm"] = (dims, s_mm, _attrs("mm", desc))
        # σ estimates the random error of what the window measures: judge it against the truth averaged
        # over the window (issue 38), the point truth's figures beside it
        e_win = np.where(fin, meas_mm[ax] - t_mm - filt[ax], np.nan) if filt is not None else None
        cov, ratio = uncertainty_calibration(e_win, sigma_mm, fin) if e_win is not None else (math.nan, math.nan)
        out[f"unc_coverage_{ax}"] = _scalar(cov)
        out[f"unc_ratio_{ax}"] = _scalar(ratio)
        cov, ratio = uncertainty_calibration(e_mm, sigma_mm, fin)
        out[f"unc_coverage_point_{ax}"] = _scalar(cov)
        out[f"unc_ratio_point_{ax}"] = _scalar(ratio)
        if filt is not None:
            f_mm = filt[ax]
            desc = f"the window's filtering of the true {ax} displacement (window-averaged − point truth)"
            out[f"{c}_filter_mm"] = (dims, np.where(fin, f_mm, np.nan), _attrs("mm", desc))
            out[f"filter_rms_{ax}_mm"] = _scalar(error_statistics(f_mm, fin)[1])
        else:
            out[f"filter_rms_{ax}_mm"] = _scalar(math.nan)
    rt = math.sqrt(sum(float(out[f"rms_{ax}"]) ** 2 for ax in axes)) if n_valid else math.nan
    out["rms_total"] = _scalar(rt)
    rt_mm = math.sqrt(sum(float(out[f"rms_{ax}_mm"]) ** 2 for ax in axes)) if n_valid else math.nan
    out["rms_total_mm"] = _scalar(rt_mm)
    ft = math.sqrt(sum(float(out[f"filter_rms_{ax}_mm"]) ** 2 for ax in axes)) if n_valid else math.nan
    out["filter_rms_total_mm"] = _scalar(ft)
    scores = (math.nan,) * 3
    partial = piv["partial"].transpose(*dims).values.astype(bool) if "partial" in piv else None
    if "unresolved" in piv and filt is not None:
        sig = {ax: _uncertainty_mm(piv, AXES[ax], dims, step_b[ax]) for ax in axes}
        if all(v is not None for v in sig.values()):
            flag = piv["unresolved"].transpose(*dims).values.astype(bool)
            # a partial window measures its seeded part, not the box the filter term averages over: the flag is
            # judged on the full windows
            full = fin & ~partial if partial is not None else fin
            scores = unresolved_scores(flag, {ax: filt[ax] for ax in axes}, sig, full)
    for name, v in zip(("unresolved_percent", "unresolved_hit", "unresolved_false"), scores):
        out[name] = _scalar(v)
    out["partial_percent"] = _scalar(
        100.0 * float(np.count_nonzero(partial & fin)) / n_valid if partial is not None and n_valid else math.nan
    )
    mag = np.sqrt(sum(np.broadcast_to(true_mm[ax], zeros.shape) ** 2 for ax in axes))
    true_mag = float(mag[fin].mean()) if n_valid else math.nan
    out["true_mag_mm"] = _scalar(true_mag)
    out["rel_error"] = _scalar(rt_mm / true_mag if n_valid and true_mag > 0 else math.nan)
    _resolution(out, piv, dims, steps, fin)
    out["crosstalk_z"] = _scalar(crosstalk_z(meas_mm, true_mm, fin) if "z" in axes else math.nan)
    out["n_vectors"] = _scalar(n_vec)
    out["n_valid"] = _scalar(n_valid)
    out["valid_percent"] = _scalar(100.0 * n_valid / n_vec if n_vec else 0.0)
    _table_attrs(out)
    out.attrs.update(
        title="PIV errors against the known flow",
        flow=getattr(flow, "name", type(flow).__name__),
        dt=float(dt),
        n_steps=int(n_steps),
        true_displacement_reference="midpoint",
        sign_convention="object frame, +z away from the camera; error = measured - true",
    )
    return out


#: Gauss-Legendre points per axis of the window average (:func:`window_average`): exact for a
#: polynomial flow up to degree 7 along each axis.
WINDOW_POINTS = 4
#: RK4 steps per particle path of the window average's samples (:func:`_window_truth`).
WINDOW_STEPS = 8


def window_average(
    flow: Flow,
    centres: Mapping[str, np.ndarray],
    window_mm: Mapping[str, np.ndarray],
    *,
    dt: float = 1.0,
    n_steps: int = 100,
    points: int = WINDOW_POINTS,
    chunk: int = 200_000,
) -> dict[str, np.ndarray]:
    """The true displacement averaged over a box (top-hat) window about each point.

    WIDIM measures the displacement of the particles inside its final window: to first order the
    truth's top-hat average over that window, not the truth at its centre (Raffel et al. 2018,
    *Particle Image Velocimetry* sec. 6.1). For a flow u = a + b·x + ½ c·x² along one axis the
    average over a window of length L exceeds the centre value by c L²/24.

    Parameters
    ----------
    flow : Flow
        The imposed flow.
    centres : mapping ``x, y, z`` -> ndarray [mm]
        Window centres, all of one shape (an axis left out: a window of no extent along it).
    window_mm : mapping ``x, y, z`` -> ndarray or float [mm]
        Window length along each axis of ``centres``, broadcastable to their shape (> 0).
    dt, n_steps : float, int
        Of the true displacement (midpoint reference, as :func:`case_errors`).
    points : int
        Gauss-Legendre points per axis (``points``³ samples per window in 3-D).
    chunk : int
        Samples evaluated at once (memory bound, not a result's parameter).

    Returns
    -------
    dict ``x, y, z`` -> ndarray [mm]
        The averaged displacement per component, the centres' shape.
    """
    axes = [ax for ax in ("x", "y", "z") if ax in centres]
    if not axes:
        raise ValueError("window_average: `centres` names none of the axes x, y, z")
    shape = np.shape(centres[axes[0]])
    if int(points) < 1:
        raise ValueError(f"window_average: `points` must be >= 1; got {points!r}")
    node, weight = np.polynomial.legendre.leggauss(int(points))
    # the tensor-product rule over the window's axes: offsets in units of a half window, weights summing to 1
    grids = np.meshgrid(*([node] * len(axes)), indexing="ij")
    offs = [g.ravel() for g in grids]
    wts = np.prod(np.meshgrid(*([weight / 2.0] * len(axes)), indexing="ij"), axis=0).ravel()
    half = {}
    for ax in axes:
        h = np.broadcast_to(np.asarray(window_mm[ax], float), shape) / 2.0
        if not np.all(np.isfinite(h) & (h > 0)):
            raise ValueError(f"window_average: window_mm[{ax!r}] must be finite and > 0")
        half[ax] = h.ravel()
    ctr = {ax: np.broadcast_to(np.asarray(centres[ax], float), shape).ravel() for ax in axes}
    n = ctr[axes[0]].size
    out = {ax: np.zeros(n) for ax in ("x", "y", "z")}
    per = max(1, int(chunk) // wts.size)
    for lo in range(0, n, per):  # blocks of windows, every sample of a window in one array call
        sl = slice(lo, min(n, lo + per))
        pts = {ax: (ctr[ax][sl, None] + half[ax][sl, None] * o[None, :]).ravel() for ax, o in zip(axes, offs)}
        d = _truth_at(flow, pts, dt, n_steps)
        for ax, comp in zip(("x", "y", "z"), d):
            out[ax][sl] = np.asarray(comp).reshape(-1, wts.size) @ wts
    return {ax: v.reshape(shape) for ax, v in out.items()}


def _window_truth(
    piv: xr.Dataset,
    flow: Flow,
    pts: Mapping[str, np.ndarray],
    dims: tuple[str, ...],
    steps: dict,
    *,
    dt: float,
    n_steps: int,
) -> dict[str, np.ndarray] | None:
    """The windows' filtering of the truth: the truth averaged over each vector's final window
    (``final_window`` voxels × the local voxel size, centred on the vector) minus the truth at its
    centre, per component [mm]; None where the result does not say its final window."""
    win = piv.attrs.get("final_window")
    if win is None or len(win) != len(dims):
        return None
    shape = pts[dims[0]].shape
    window_mm = {}
    for i, d in enumerate(dims):
        shp = [1] * len(dims)
        shp[i] = -1
        window_mm[d] = np.broadcast_to(float(win[i]) * np.abs(steps[d]).reshape(shp), shape)
    ctr = {d: pts[d] for d in dims}
    # RK4 with WINDOW_STEPS steps per path and its own centre value: the filter term (a difference of two
    # averages) agrees with 200 steps to ~1e-8 mm on Hill's vortex at a tenth of the cost
    k = max(1, min(int(n_steps), WINDOW_STEPS))
    box = window_average(flow, ctr, window_mm, dt=dt, n_steps=k)
    centre = window_average(flow, ctr, window_mm, dt=dt, n_steps=k, points=1)
    return {ax: box[ax] - centre[ax] for ax in box}


def _uncertainty_mm(piv: xr.Dataset, c: str, dims: tuple[str, ...], step: np.ndarray) -> np.ndarray | None:
    """The PIV's standard uncertainty of component ``c`` in mm (``unc_<c>_mm``, else ``unc_<c>`` × voxel), or None."""
    if f"unc_{c}_mm" in piv:
        return piv[f"unc_{c}_mm"].transpose(*dims).values.astype(float)
    if f"unc_{c}" in piv:
        return piv[f"unc_{c}"].transpose(*dims).values.astype(float) * np.abs(step)
    return None


def uncertainty_calibration(error: np.ndarray, sigma: np.ndarray | None, mask: np.ndarray) -> tuple[float, float]:
    """How well per-vector uncertainties measure the actual errors.

    Parameters
    ----------
    error : ndarray
        Measured − true, per vector.
    sigma : ndarray or None
        Standard uncertainty per vector (same units), NaN where the vector has none.
    mask : ndarray of bool
        Valid vectors.

    Returns
    -------
    coverage, ratio : float
        Fraction of the valid vectors with a finite σ whose ``|error| <= σ`` (0.68 for
        a Gaussian error and a right σ) and RMS(error) / RMS(σ) over the same vectors
        (1 for a right σ). NaN without uncertainties or without such vectors.
    """
    if sigma is None:
        return math.nan, math.nan
    ok = mask & np.isfinite(sigma) & np.isfinite(error)
    if not ok.any():
        return math.nan, math.nan
    e, s = np.abs(error[ok]), sigma[ok]
    rms_s = float(np.sqrt(np.mean(s**2)))
    ratio = float(np.sqrt(np.mean(e**2))) / rms_s if rms_s > 0 else math.nan
    return float(np.mean(e <= s)), ratio


def unresolved_scores(
    flag: np.ndarray, filter_err: Mapping[str, np.ndarray], sigma: Mapping[str, np.ndarray], mask: np.ndarray
) -> tuple[float, float, float]:
    """How well a truth-free ``unresolved`` flag finds the vectors the windows' filtering spoils.

    Parameters
    ----------
    flag : ndarray of bool
        The PIV's ``unresolved`` flag per vector.
    filter_err, sigma : mapping axis -> ndarray
        The true filtering (window-averaged − point truth) and the PIV's standard uncertainty per
        component, same units (σ NaN: the component counts as neither above 2σ nor below σ).
    mask : ndarray of bool
        Valid vectors.

    Returns
    -------
    percent, hit, false : float
        Flagged valid vectors [%]; of the valid vectors with ``|filter| > 2σ`` in any component the
        share flagged (NaN without such vectors); of the flagged vectors the share with ``|filter| < σ``
        in every component with a σ (NaN without flags). Between σ and 2σ either answer is fine.
    """
    m = np.asarray(mask, bool)
    f = np.asarray(flag, bool) & m
    if not m.any():
        return math.nan, math.nan, math.nan
    with np.errstate(invalid="ignore"):
        big = np.zeros(m.shape, bool)
        small = np.ones(m.shape, bool)
        for ax, fe in filter_err.items():
            a, sg = np.abs(np.asarray(fe, float)), np.asarray(sigma[ax], float)
            big |= a > 2.0 * sg
            small &= ~(a >= sg)  # NaN σ: no evidence either way
    big &= m
    hit = float(f[big].mean()) if big.any() else math.nan
    false = float(small[f].mean()) if f.any() else math.nan
    return 100.0 * float(f.sum()) / float(m.sum()), hit, false


def binned_uncertainty(error: np.ndarray, sigma: np.ndarray, n_bins: int = 8) -> dict[str, np.ndarray]:
    """RMS error against the predicted uncertainty, in bins of σ (the calibration curve of an
    uncertainty estimate: on the 1:1 line where σ is right, cf. Wieneke 2015, Fig. 9).

    Parameters
    ----------
    error : ndarray
        Measured − true, per vector (any shape; NaN: no error).
    sigma : ndarray
        Predicted standard uncertainty of the same vectors, same units (NaN: none).
    n_bins : int
        Bins of about equal count between the quantiles of σ (fewer when σ repeats or
        there are fewer vectors than bins).

    Returns
    -------
    dict of ndarray
        Per bin: ``sigma_rms`` (RMS σ), ``error_rms`` (RMS error), ``coverage`` (fraction with
        ``|error| <= σ``) and ``count``; empty arrays without a vector that has both.
    """
    e = np.asarray(error, float).ravel()
    s = np.asarray(sigma, float).ravel()
    ok = np.isfinite(e) & np.isfinite(s)
    e, s = e[ok], s[ok]
    keys = ("sigma_rms", "error_rms", "coverage", "count")
    if not e.size:
        return {k: np.empty(0) for k in keys}
    edges = np.unique(np.quantile(s, np.linspace(0.0, 1.0, max(1, min(int(n_bins), e.size)) + 1)))
    idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, max(0, edges.size - 2))
    out: dict[str, list[float]] = {k: [] for k in keys}
    for b in np.unique(idx):
        m = idx == b
        out["sigma_rms"].append(float(np.sqrt(np.mean(s[m] ** 2))))
        out["error_rms"].append(float(np.sqrt(np.mean(e[m] ** 2))))
        out["coverage"].append(float(np.mean(np.abs(e[m]) <= s[m])))
        out["count"].append(float(m.sum()))
    return {k: np.asarray(v) for k, v in out.items()}


def crosstalk_z(measured_mm: Mapping[str, np.ndarray], true_mm: Mapping[str, Any], mask: np.ndarray) -> float:
    """Spurious z displacement per unit of imposed lateral displacement, for a uniform flow.

    ``(mean(w_meas) − w_true) / |(u_true, v_true)|`` over the vectors of ``mask``: the w a design
    reads for a purely lateral shift, as a fraction of it (a plenoptic camera sees depth through
    the parallax of its sub-apertures, so a lateral shift can leak into w).

    Parameters
    ----------
    measured_mm, true_mm : mapping ``x, y, z`` -> array [mm]
        Measured and true displacement at the window centres (the truth broadcastable to them).
    mask : ndarray of bool
        Vectors to average (valid, finite).

    Returns
    -------
    float
        NaN when no vector is selected, when the true displacement differs between the selected
        vectors (not a uniform flow) or when its lateral part is zero.
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        return math.nan
    t = {a: np.broadcast_to(np.asarray(true_mm[a], float), mask.shape)[mask] for a in ("x", "y", "z")}
    # uniform: one true displacement at every window (to the rounding of the RK4 path)
    scale = max(1.0, *(float(np.abs(v).max()) for v in t.values()))
    if any(float(np.ptp(v)) > 1e-9 * scale for v in t.values()):
        return math.nan
    lateral = math.hypot(float(t["x"][0]), float(t["y"][0]))
    if lateral == 0.0:
        return math.nan
    return (float(np.asarray(measured_mm["z"], float)[mask].mean()) - float(t["z"][0])) / lateral


def _resolution(out: xr.Dataset, piv: xr.Dataset, dims: tuple[str, ...], steps: dict, fin: np.ndarray) -> None:
    """Spatial resolution of a result in mm: final window and vector spacing per axis, and the
    depth its valid vectors span (window centres plus one final window)."""
    win, spa = piv.attrs.get("final_window"), piv.attrs.get("final_spacing")
    for ax in ("x", "y", "z"):
        if ax not in dims:
            continue
        vox = float(np.median(steps[ax]))
        i = dims.index(ax)
        if win is not None and len(win) == len(dims):
            out[f"window_mm_{ax}"] = _scalar(float(win[i]) * vox)
        if spa is not None and len(spa) == len(dims):
            out[f"spacing_mm_{ax}"] = _scalar(float(spa[i]) * vox)
    if "z" in dims:
        zc = np.broadcast_to(piv["z"].values.reshape([-1 if d == "z" else 1 for d in dims]), fin.shape)[fin]
        span = float(zc.max() - zc.min()) if zc.size else 0.0
        w = float(out["window_mm_z"]) if "window_mm_z" in out else 0.0
        out["depth_mm"] = _scalar(span + w if zc.size else math.nan)


# ----------------------------------------------------------- reconstruction Q
def reconstruction_quality(
    volume: xr.DataArray,
    particles: xr.Dataset,
    *,
    sigma_mm: float | Sequence[float],
    planes_per_block: int = 8,
) -> float:
    """Reconstruction quality Q of Elsinga et al. (2006).

    Q = Σ E·E_true / sqrt(Σ E² · Σ E_true²), the normalised correlation of the
    reconstructed volume E and the true volume E_true (:func:`render_truth`:
    one Gaussian of physical size ``sigma_mm`` per particle, integrated over
    the voxels of the volume's own grid). Elsinga et al. deem Q > 0.75 adequate
    for tomographic PIV. With a physical size fixed by the camera (the study
    uses half its resolution cell, :func:`lfstudy.study.case.truth_sigma`),
    methods and grids are compared on one footing.

    Parameters
    ----------
    volume : xarray.DataArray (z, y, x)
        Reconstructed intensity, coords ascending [mm]; may be dask-backed:
        it is read ``planes_per_block`` planes at a time.
    particles : xarray.Dataset
        Particle field of the same exposure (``x, y, z, intensity`` [mm]).
    sigma_mm : float or (sz, sy, sx)
        Standard deviation of the true particles [mm].
    planes_per_block : int
        Planes of ``volume`` computed at once.

    Returns
    -------
    float
        Q in [−1, 1] (in [0, 1] for non-negative volumes); NaN if either
        volume is identically zero.
    """
    vol = volume.transpose("z", "y", "x")
    coords = {d: np.asarray(vol[d].values, float) for d in ("z", "y", "x")}
    for d, c in coords.items():
        if c.size > 1 and np.any(np.diff(c) <= 0):
            raise ValueError(f"reconstruction_quality: coordinate {d} must be strictly ascending")
    truth = render_truth(coords, particles, sigma_mm=sigma_mm)
    num = e2 = 0.0
    for k in range(0, truth.shape[0], max(1, int(planes_per_block))):
        e = np.asarray(vol.isel(z=slice(k, k + planes_per_block)).values, dtype=np.float64)
        tr = truth[k : k + e.shape[0]]
        num += float(np.sum(e * tr))
        e2 += float(np.sum(e * e))
    t2 = float(np.sum(truth * truth))
    if e2 == 0.0 or t2 == 0.0:
        return math.nan
    return num / math.sqrt(e2 * t2)


# ------------------------------------------------------- the case's metrics
def field_of_view(camera: Any) -> dict[str, float]:
    """The design's field of view in x and y [mm] (:attr:`PlenopticCamera.fov_x`, ``fov_y``)."""
    return {"fov_x_mm": float(camera.fov_x), "fov_y_mm": float(camera.fov_y)}


def particles_per_cell(camera: Any, particles: xr.Dataset, bounds_mm: Sequence[tuple[float, float]]) -> float:
    """The seeding a design must resolve: particles per lenslet and depth cell.

    A particle behind a lenslet is told from another behind it by its depth once their spots on the
    lenslet array differ by a lenslet pitch (eq. 4.18's circle of confusion), so the grid's depth
    holds ``|b(z1) − b(z0)| / p`` depth cells (b the signed blur diameter,
    :meth:`~lfstudy.optics.PlenopticCamera.defocus_blur`; at least one) along each lenslet's line of
    sight, counted over the depth the particles occupy inside the grid (a grid deeper than the seeded
    slab holds no particles in its extra cells). The particles inside the grid are divided by those
    cells and the lenslets under the grid (its lateral extent over a lenslet's footprint at the focal
    plane, ``p·so/si``).

    Parameters
    ----------
    camera : PlenopticCamera
        The case's design.
    particles : xarray.Dataset
        True particles (``x``, ``y``, ``z`` [mm]).
    bounds_mm : ((x0, x1), (y0, y1), (z0, z1))
        The reconstruction grid's extent [mm].

    Returns
    -------
    float
        Particles per lenslet and depth cell (NaN for a grid without lateral extent).
    """
    (x0, x1), (y0, y1), (z0, z1) = ((float(a), float(b)) for a, b in bounds_mm)
    xyz = np.column_stack([np.asarray(particles[k].values, float).ravel() for k in ("x", "y", "z")])
    inside = np.all((xyz >= [x0, y0, z0]) & (xyz <= [x1, y1, z1]), axis=1)
    footprint = camera.lenslet_pitch * camera.so / camera.si
    lenslets = (x1 - x0) * (y1 - y0) / footprint**2
    if not inside.any() or lenslets <= 0:
        return 0.0 if lenslets > 0 else math.nan
    zs = xyz[inside, 2]
    blur = camera.defocus_blur(np.array([zs.min(), zs.max()]))
    cells = max(1.0, abs(float(blur[1] - blur[0])) / camera.lenslet_pitch)
    return float(inside.sum()) / (lenslets * cells)


def depth_gain(piv: xr.Dataset) -> float:
    """The depth gain the PIV result's w was divided by (:func:`lfstudy.piv.depth.correct_depth`);
    NaN when it was not depth-corrected."""
    return float(piv.attrs.get("depth_gain_total", math.nan))


#: Name prefixes of the oracle's statistics and of the reconstruction's share (rows of the metric table).
ORACLE_PREFIX = "oracle_"
ADDED_PREFIX = "recon_added_"
#: Name prefixes of the windows' filtering of the truth (:func:`case_errors`) and of the oracle's error beyond it.
FILTER_PREFIX = "filter_"
REST_PREFIX = "rest_"


def oracle_metrics(oracle: xr.Dataset, flow: Flow, *, dt: float = 1.0, n_steps: int = 100) -> dict[str, float]:
    """The oracle's metrics: :func:`case_errors` of the PIV result on the true volumes.

    Every row of the metric table named ``oracle_<stat>`` takes the statistic ``<stat>`` of
    ``case_errors(oracle, flow)``: an oracle metric is one table row.

    Parameters
    ----------
    oracle : xarray.Dataset
        The case's PIV run on the true particle volumes (:func:`lfstudy.study.case.oracle_piv`).
    flow : Flow
        The imposed flow.
    dt, n_steps : float, int
        Of the true displacement.

    Returns
    -------
    dict
        ``{"oracle_<stat>": value}`` for every such row of the table.
    """
    err = case_errors(oracle, flow, dt=dt, n_steps=n_steps, window_truth=False)  # the case's filter serves
    out: dict[str, float] = {}
    for m in metric_table.METRICS:
        if m.name.startswith(ORACLE_PREFIX):
            stat = m.name.removeprefix(ORACLE_PREFIX)
            if stat not in err:
                raise KeyError(f"metric {m.name!r}: case_errors gives no {stat!r} for the oracle")
            out[m.name] = float(err[stat])
    return out


def quadrature_excess(total: float, part: float) -> float:
    """``sqrt(max(total² − part², 0))``: what ``total`` holds beyond ``part`` when independent errors
    add in quadrature (0 where ``part`` is the larger; NaN where either is NaN)."""
    total, part = float(total), float(part)
    if not (math.isfinite(total) and math.isfinite(part)):
        return math.nan
    return math.sqrt(max(total * total - part * part, 0.0))


def error_budget(case: Mapping[str, float], oracle: Mapping[str, float]) -> dict[str, float]:
    """The case's error in three parts, in quadrature: case² = filter² + recon_added² + rest².

    Every table row ``recon_added_<stat>`` is :func:`quadrature_excess` of the case's ``<stat>`` over
    the oracle's ``oracle_<stat>``; every row ``rest_<stat>`` is that of the oracle's ``oracle_<stat>``
    over the case's ``filter_<stat>`` (:func:`case_errors`: the windows' top-hat filtering of the truth).

    The oracle is what the design's grid and PIV windows give on perfect volumes; the case's error
    beyond it comes from the reconstruction (and the imaging before it). The oracle's own error is the
    windows' filtering of the flow (no estimator built from a window's data sees it) and the rest: the
    random error and the estimator's own bias. :func:`lfstudy.study.designs.error_limit` names the
    largest part. A case without ``filter_<stat>`` gets NaN rests.
    """
    out: dict[str, float] = {}
    for m in metric_table.METRICS:
        if m.name.startswith(ADDED_PREFIX):
            stat = m.name.removeprefix(ADDED_PREFIX)
            out[m.name] = quadrature_excess(case[stat], oracle[ORACLE_PREFIX + stat])
        elif m.name.startswith(REST_PREFIX):
            stat = m.name.removeprefix(REST_PREFIX)
            out[m.name] = quadrature_excess(oracle[ORACLE_PREFIX + stat], case.get(FILTER_PREFIX + stat, math.nan))
    return out


def with_metrics(ds: xr.Dataset, values: Mapping[str, float], **extra_attrs: Mapping[str, Any]) -> xr.Dataset:
    """``ds`` with each of ``values`` as a 0-d variable whose attrs come from the metric table.

    ``extra_attrs`` maps a name to attrs added beside the table's (case-specific facts such as
    the truth's size behind Q). A name missing from the table raises ``KeyError``.
    """
    out = ds.copy()
    for name, value in values.items():
        out[name] = ((), float(value), {**metric_attrs(name), **dict(extra_attrs.get(name, {}))})
    return out


def case_metrics(
    piv: xr.Dataset,
    flow: Flow,
    camera: Any,
    volume: xr.DataArray,
    particles: xr.Dataset,
    *,
    sigma_mm: float | Sequence[float],
    dt: float = 1.0,
    n_steps: int = 100,
    oracle: xr.Dataset | None = None,
    extra: Mapping[str, float] | None = None,
) -> xr.Dataset:
    """Every metric of one case: :func:`case_errors`, the field of view, Q, the depth gain and,
    given the oracle's PIV result, the error budget.

    Parameters
    ----------
    piv : xarray.Dataset
        The case's PIV result (loaded).
    flow : Flow
        The imposed flow.
    camera : PlenopticCamera
        The case's design (its field of view).
    volume : xarray.DataArray
        The reconstruction of frame a (may be lazy), for :func:`reconstruction_quality`.
    particles : xarray.Dataset
        The true particles of frame a.
    sigma_mm : float or (sz, sy, sx)
        Size of the true particles for Q (:func:`lfstudy.study.case.truth_sigma`).
    dt, n_steps : float, int
        Of the true displacement (:func:`case_errors`).
    oracle : xarray.Dataset, optional
        The case's PIV on the true volumes (:func:`lfstudy.study.case.oracle_piv`), on the case's
        PIV grid.
    extra : mapping, optional
        Further scalars computed elsewhere, each a row of the metric table (e.g. the particle
        metrics of :func:`lfstudy.study.particle_metrics.particle_metrics`).

    Returns
    -------
    xarray.Dataset
        The fields and scalars of :func:`case_errors` plus ``fov_x_mm``, ``fov_y_mm``, ``Q``
        (with ``truth_sigma_mm``) and ``depth_gain``; with ``oracle``, the ``oracle_*`` metrics
        (:func:`oracle_metrics`), the ``recon_added_*`` ones (:func:`error_budget`), ``time_oracle``
        (its ``oracle_seconds`` attr) and the oracle's vectors ``oracle_u_mm``, ``oracle_v_mm``,
        ``oracle_w_mm`` and ``oracle_valid``. Every scalar's attrs come from the metric table.
    """
    err = case_errors(piv, flow, dt=dt, n_steps=n_steps)
    q = reconstruction_quality(volume, particles, sigma_mm=sigma_mm)
    sigma = [float(s) for s in np.broadcast_to(np.asarray(sigma_mm, float), (3,))]
    values = {**field_of_view(camera), "Q": q, "depth_gain": depth_gain(piv)}
    if oracle is not None:
        orc = oracle_metrics(oracle, flow, dt=dt, n_steps=n_steps)
        case = {str(n): float(v) for n, v in err.data_vars.items() if v.ndim == 0}
        values.update(orc, **error_budget(case, orc), time_oracle=float(oracle.attrs.get("oracle_seconds", math.nan)))
        err = _with_oracle_vectors(err, oracle)
        values.update(oracle_uncertainty(err))
    values.update(extra or {})
    return with_metrics(err, values, Q={"truth_sigma_mm": sigma})


def oracle_uncertainty(err: xr.Dataset) -> dict[str, float]:
    """σ judged against the oracle: ``unc_coverage_oracle_<ax>`` and ``unc_ratio_oracle_<ax>``.

    The oracle is the case's own WIDIM on the true particles, so its vectors are what the windows measure of the
    flow, their whole response included (the top-hat, the deformation and its predictor filter, the particle
    images), plus its own small random error. The case's vector minus the oracle's is then the error the
    reconstruction and the correlation add, which σ estimates (:func:`uncertainty_calibration`). Under a vortex
    as wide as a few windows WIDIM's response is not the top-hat of ``unc_coverage_<ax>``: on the thesis camera's
    Lamb–Oseen vortex x's ratio is 2–5 against the window-averaged truth and 0.65–1.65 against the oracle
    (``benchmarks/bench_uncertainty_calibration.py --truth oracle``).

    Parameters
    ----------
    err : xarray.Dataset
        :func:`case_errors`' result with the oracle's vectors (``oracle_<c>_mm``, ``oracle_valid``) and σ
        (``unc_<c>_mm``).

    Returns
    -------
    dict
        Per axis the coverage and the RMS ratio over the vectors valid in both; NaN where the case has no σ or
        no oracle vector for that component.

    Examples
    --------
    >>> import numpy as np, xarray as xr
    >>> d = ("x",)
    >>> err = xr.Dataset({"u_err_mm": (d, [0.1, 0.3]), "u_true_mm": (d, [1.0, 1.0]),
    ...                   "oracle_u_mm": (d, [1.1, 1.1]), "unc_u_mm": (d, [0.15, 0.15]),
    ...                   "oracle_valid": (d, [True, True])})
    >>> out = oracle_uncertainty(err)
    >>> out["unc_coverage_oracle_x"], round(out["unc_ratio_oracle_x"], 3)
    (0.5, 0.943)
    """
    out: dict[str, float] = {}
    for ax in ("x", "y", "z"):
        c = AXES[ax]
        cov = ratio = math.nan
        d = oracle_error(err, c)
        if d is not None and f"unc_{c}_mm" in err:
            s = err[f"unc_{c}_mm"].transpose(*err[f"{c}_err_mm"].dims).values.astype(float)
            cov, ratio = uncertainty_calibration(d, s, np.isfinite(d))
        out[f"unc_coverage_oracle_{ax}"] = cov
        out[f"unc_ratio_oracle_{ax}"] = ratio
    return out


def oracle_error(err: xr.Dataset, comp: str) -> np.ndarray | None:
    """Per vector, the case's ``comp`` displacement (u, v or w) minus the oracle's [mm], NaN where either is
    invalid, in the dims order of ``<comp>_err_mm``; None where ``err`` has no oracle vectors
    (:func:`case_metrics` without an oracle).

    Parameters
    ----------
    err : xarray.Dataset
        :func:`case_metrics`' result: ``<comp>_err_mm``, ``<comp>_true_mm``, ``oracle_<comp>_mm`` and
        ``oracle_valid``.
    comp : {"u", "v", "w"}
        The component.

    Returns
    -------
    ndarray or None

    Examples
    --------
    >>> import xarray as xr
    >>> d = ("x",)
    >>> err = xr.Dataset({"u_err_mm": (d, [0.1, 0.3]), "u_true_mm": (d, [1.0, 1.0]),
    ...                   "oracle_u_mm": (d, [1.1, 1.2]), "oracle_valid": (d, [True, False])})
    >>> oracle_error(err, "u")
    array([0., nan])
    """
    names = (f"{comp}_err_mm", f"{comp}_true_mm", f"oracle_{comp}_mm", "oracle_valid")
    if not all(n in err for n in names):
        return None
    dims = err[names[0]].dims
    e, t, o = (err[n].transpose(*dims).values.astype(float) for n in names[:3])
    ok = err["oracle_valid"].transpose(*dims).values.astype(bool)
    # measured − oracle = (measured − point truth) + point truth − oracle
    return np.where(ok, e + t - o, np.nan)


def _with_oracle_vectors(err: xr.Dataset, oracle: xr.Dataset) -> xr.Dataset:
    """``err`` with the oracle's displacements and validity as ``oracle_<c>_mm`` and ``oracle_valid``
    (the oracle's PIV grid is the case's: the same volume grid and windows)."""
    dims = tuple(d for d in ("z", "y", "x") if d in err.dims)
    for d in dims:
        if oracle.sizes.get(d) != err.sizes[d] or not np.allclose(oracle[d].values, err[d].values):
            raise ValueError(f"the oracle's PIV grid differs from the case's along {d}: were both run on one grid?")
    out = err.copy()
    for ax in dims:
        c = AXES[ax]
        if f"{c}_mm" in oracle:
            long_name = f"{ax} displacement of the oracle (the case's PIV on the true volumes)"
            out[f"oracle_{c}_mm"] = (dims, oracle[f"{c}_mm"].transpose(*dims).values, _attrs("mm", long_name))
    if "valid" in oracle:
        out["oracle_valid"] = (dims, oracle["valid"].transpose(*dims).values, {"long_name": "oracle vector valid"})
    return out
