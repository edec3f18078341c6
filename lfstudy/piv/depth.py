"""Depth calibration of a plenoptic PIV chain by a traversed seeded volume.

A plenoptic reconstruction is not shift-invariant in depth: the depth
resolution is poorest at the focal plane (all rays of an in-focus particle
reach one lenslet, sec. 4.3), so a reconstructed particle's depth profile
leans towards it and the reconstructed depth of a particle moves less than
the particle does. PIV then reads an axial displacement that is short by a
design-dependent factor (10 % on the thesis camera, up to a third on coarse
designs), while x and y are unaffected.

The calibration is the one an experiment can make: image a seeded volume,
traverse the camera (or the volume) by a known ``shift`` along the optical
axis, image it again, process both exposures exactly like the measurement
and read the depth *response* ``R(z, shift)``: the mean measured w per depth
layer of the PIV grid. The response is not linear (sub-voxel shifts read
shorter than whole-voxel ones), so the traverse is made at several shifts and
every measured ``w`` of that design and processing is mapped back through the
inverse of its layer's response curve. The functions here are pure: the case layer renders
and processes the calibration volume (:func:`lfstudy.study.case.case_depth_calibration`).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

__all__ = ["depth_response", "correct_depth"]

#: Layers with fewer valid vectors than this take the response of the whole volume.
MIN_LAYER_VECTORS = 5


def depth_response(results: list[tuple[float, xr.Dataset]], *, min_gain: float = 0.3) -> xr.Dataset:
    """Depth response of a chain from calibration PIV results at known z shifts.

    Parameters
    ----------
    results : list of (float, xarray.Dataset)
        ``(shift_mm, result)``: WIDIM results between the calibration volume
        and the same volume moved by ``shift_mm`` (> 0) along +z, all on the
        same PIV grid (``w_mm`` and ``valid`` on z, y, x). Several results at
        one shift (repeated calibration volumes) are pooled: their valid
        vectors count together.
    min_gain : float
        Smallest gain (measured / true) the correction inverts: smaller gains
        at any shift or layer are raised to it, so that the inversion never
        multiplies noise by more than ``1 / min_gain``; a whole-volume gain
        below it at the largest shift marks the design as not resolving depth
        (attr ``resolves_depth`` 0: :func:`correct_depth` then leaves w as read).

    Returns
    -------
    xarray.Dataset
        ``response`` (shift, z) [mm]: mean valid ``w_mm`` of the layer (the
        whole volume's where the layer has fewer than :data:`MIN_LAYER_VECTORS`
        valid vectors), made increasing in the shift; ``gain`` (shift, z) =
        response / shift; ``gain_total`` (shift) of the whole volume;
        ``n_valid`` (shift, z). With repeats (two or more results at every
        shift), ``gain_total_sd`` (shift): the standard deviation of the
        whole-volume gain between repeats. Coordinate ``shift`` [mm]. Attrs
        ``resolves_depth`` (1/0), ``min_gain`` and ``repeats``.

    Raises
    ------
    ValueError
        If a shift is not positive or the results are not on one grid. A
        traverse without any valid vector reads a gain of 0 (the design does
        not follow it), which is a result, not an error.
    """
    if not results:
        raise ValueError("depth calibration: no calibration result")
    results = sorted(results, key=lambda r: r[0])
    z = results[0][1]["z"].values
    groups: dict[float, list[tuple[np.ndarray, np.ndarray]]] = {}
    for shift, res in results:
        if not (np.isfinite(shift) and shift > 0):
            raise ValueError(f"depth calibration: every shift must be positive, got {shift!r} mm")
        if res["z"].shape != z.shape or not np.allclose(res["z"].values, z):
            raise ValueError("depth calibration: the results of the shifts are not on one PIV grid")
        valid = res["valid"].transpose("z", "y", "x").values.astype(bool)
        w = res["w_mm"].transpose("z", "y", "x").values.astype(float)
        groups.setdefault(float(shift), []).append((w, valid & np.isfinite(w)))
    repeats = {len(g) for g in groups.values()}
    if len(repeats) != 1:
        raise ValueError("depth calibration: every shift needs the same number of repeated results")
    shifts, gains, totals, counts, spreads = [], [], [], [], []
    for shift, group in groups.items():
        w = np.stack([g[0] for g in group])
        valid = np.stack([g[1] for g in group])
        # no valid vector: the chain cannot follow this traverse at all (reads gain 0)
        total = float(w[valid].mean()) / shift if valid.any() else 0.0
        n = valid.sum(axis=(0, 2, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            layer = np.where(valid, w, 0.0).sum(axis=(0, 2, 3)) / n / shift
        g = np.maximum(np.where(n >= MIN_LAYER_VECTORS, layer, total), min_gain)
        per_repeat = [float(wr[vr].mean()) / shift if vr.any() else 0.0 for wr, vr in zip(w, valid)]
        shifts.append(shift)
        totals.append(total)
        gains.append(g)
        counts.append(n)
        spreads.append(float(np.std(per_repeat, ddof=1)) if len(per_repeat) > 1 else 0.0)
    n_repeats = repeats.pop()
    sh = np.asarray(shifts)
    r = np.asarray(gains) * sh[:, None]
    r = np.maximum.accumulate(r, axis=0)  # a response curve must rise with the shift to be inverted
    out = xr.Dataset(
        {
            "response": (("shift", "z"), r, {"units": "mm", "long_name": "mean measured z displacement"}),
            "gain": (("shift", "z"), r / sh[:, None], {"units": "1", "long_name": "depth gain (measured / true)"}),
            "gain_total": ("shift", np.asarray(totals), {"units": "1", "long_name": "depth gain of the whole volume"}),
            "n_valid": (
                ("shift", "z"),
                np.asarray(counts, dtype=np.int64),
                {"units": "1", "long_name": "valid vectors"},
            ),
        },
        coords={
            "shift": ("shift", sh, {"units": "mm", "long_name": "traverse along +z"}),
            "z": ("z", z, {"units": "mm", "long_name": "depth of the PIV layer"}),
        },
        attrs={
            "title": "depth calibration (traversed seeded volume)",
            # below min_gain the design does not resolve depth: correcting would only amplify noise
            "resolves_depth": int(totals[-1] >= min_gain),
            "min_gain": float(min_gain),
            "repeats": int(n_repeats),
        },
    )
    if n_repeats > 1:
        out["gain_total_sd"] = (
            "shift",
            np.asarray(spreads),
            {"units": "1", "long_name": "standard deviation of the whole-volume depth gain between repeats"},
        )
    return out


def _invert(w: np.ndarray, response: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """True displacement of readings ``w`` through one layer's response curve (odd in w)."""
    xs = np.concatenate(([0.0], response))
    ys = np.concatenate(([0.0], shifts))
    a = np.abs(w)
    inside = np.interp(a, xs, ys)
    beyond = a * shifts[-1] / response[-1]  # past the largest traverse: its gain
    return np.sign(w) * np.where(a <= response[-1], inside, beyond)


def correct_depth(result: xr.Dataset, calibration: xr.Dataset) -> xr.Dataset:
    """Map a PIV result's axial displacement back through the chain's depth response.

    Parameters
    ----------
    result : xarray.Dataset
        WIDIM result with ``w_mm`` (and ``w`` in voxels) on a ``z`` coordinate [mm].
    calibration : xarray.Dataset
        :func:`depth_response` of the same design and processing; its curves
        are interpolated linearly in z (held beyond the first and last layer).

    Returns
    -------
    xarray.Dataset
        A copy with ``w_mm`` and ``w`` corrected, the raw readings as
        ``w_uncorrected`` / ``w_mm_uncorrected``, and the attrs
        ``depth_gain_total`` (whole-volume gain at the traverse nearest one
        z voxel), ``depth_calibration_shifts_mm`` and ``depth_corrected``
        (0 where the design does not resolve depth and w is left as read).
        Uncertainties ``unc_w_mm`` / ``unc_w``, where present, go through the same
        map (divided by the gain the reading was divided by) and, with repeated
        calibrations (``gain_total_sd``), gain the spread of the gain in
        quadrature: σ_w² = (σ_raw / g)² + (w σ_g / g)², g and σ_g of the traverse
        nearest one z voxel; the raw ones are kept as ``unc_w_mm_uncorrected``.
    """
    out = result.copy()
    raw_mm = result["w_mm"]
    shifts = calibration["shift"].values.astype(float)
    totals = calibration["gain_total"].values
    out["w_mm_uncorrected"] = raw_mm.assign_attrs(long_name="z displacement before the depth calibration")
    if "w" in result:
        out["w_uncorrected"] = result["w"].assign_attrs(long_name="z displacement before the depth calibration")
    step = shifts[0]
    if "w" in result:
        with np.errstate(invalid="ignore", divide="ignore"):
            step = float(np.nanmedian(np.abs(raw_mm.values / result["w"].values)))
    one_voxel = int(np.argmin(np.abs(shifts - step)))  # mm per z voxel: the traverse nearest one voxel
    corrected = bool(calibration.attrs.get("resolves_depth", 1))
    out.attrs.update(
        depth_gain_total=float(totals[one_voxel]),
        depth_calibration_shifts_mm=[float(s) for s in shifts],
        depth_corrected=int(corrected),
    )
    if not corrected:
        return out
    zc = calibration["z"].values
    resp = calibration["response"].transpose("shift", "z").values
    dims = result["w_mm"].dims
    w = result["w_mm"].transpose("z", ...).values.astype(float)
    fixed = np.empty_like(w)
    for k, zk in enumerate(result["z"].values):
        curve = np.array([np.interp(zk, zc, resp[i]) for i in range(shifts.size)])
        fixed[k] = _invert(w[k], np.maximum.accumulate(curve), shifts)
    new_mm = xr.DataArray(fixed, dims=raw_mm.transpose("z", ...).dims).transpose(*dims)
    out["w_mm"] = new_mm.assign_coords(raw_mm.coords).assign_attrs(raw_mm.attrs)
    if "w" in result:
        raw = result["w"]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = xr.where(raw_mm != 0, out["w_mm"] / raw_mm, 1.0)  # the same map in voxels
        out["w"] = (raw * ratio).assign_attrs(raw.attrs)
    _propagate_uncertainty(out, result, calibration, one_voxel)
    return out


def _propagate_uncertainty(out: xr.Dataset, result: xr.Dataset, calibration: xr.Dataset, one_voxel: int) -> None:
    """Carry ``unc_w_mm`` / ``unc_w`` through the depth correction (in place on ``out``)."""
    if "unc_w_mm" not in result:
        return
    raw_mm = result["w_mm"]
    g = float(calibration["gain_total"].values[one_voxel])
    with np.errstate(invalid="ignore", divide="ignore"):
        # the map's local factor (true / read); a zero reading takes the whole-volume gain
        factor = xr.where(raw_mm != 0, out["w_mm"] / raw_mm, 1.0 / g if g > 0 else 1.0)
    rel_sd = 0.0
    if "gain_total_sd" in calibration and g > 0:
        rel_sd = float(calibration["gain_total_sd"].values[one_voxel]) / g
    for name, w in (("unc_w_mm", out["w_mm"]), ("unc_w", out.get("w"))):
        if name not in result or w is None:
            continue
        raw = result[name]
        out[f"{name}_uncorrected"] = raw.assign_attrs(long_name="uncertainty of z before the depth calibration")
        sig = np.sqrt((raw * np.abs(factor)) ** 2 + (w * rel_sd) ** 2)
        out[name] = sig.where(np.isfinite(raw)).transpose(*raw.dims).assign_attrs(raw.attrs)
