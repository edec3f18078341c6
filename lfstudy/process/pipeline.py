"""Recorded plenoptic images → calibration → light fields → volumes → PIV → metrics and report.

The chain of one simulated case (:mod:`lfstudy.study.case`: the same camera,
grid, refocusing, reconstruction and PIV functions of a config), run on
recorded frames instead of ray-traced ones:

1. the dark frames' mean (if any) is subtracted from every image, clipped at 0;
2. the calibration image (pinhole or white, sec. 5.1) gives the lenslet centres;
3. every frame is registered (eqs 5.2–5.9), refocused onto the reconstruction
   grid (eqs 5.10–5.20) and reconstructed (sec. 5.5 or the configured method), once;
4. with a recorded dot target (``recording.volumetric_calibration``), its images
   are registered and the volumetric calibration is fitted (Hall et al. 2018,
   :mod:`lfstudy.lightfield.volcal`); with ``refocus.model: volumetric`` every
   frame (and the traverse) is refocused through it instead of the thin-lens model;
5. with a recorded traverse (``recording.depth_calibration``), the depth
   response of this camera and processing is measured (:mod:`lfstudy.piv.depth`);
6. every pair (1–2, 2–3, … for a series) is correlated by WIDIM (ch. 6), its w
   mapped back through the depth response, and measured without a known flow
   (:mod:`lfstudy.process.metrics`); with a method that fits particles (ipr) and no
   traverse, WIDIM runs again on the particles paired between the frames
   (``piv.particles: paired``, the default there, as in a study).

Everything is written into a temporary sibling of the output directory, renamed
into place at the end: a recording that stops with an error leaves nothing
half-written. An existing output directory is replaced only if an earlier run of
``lfstudy process`` wrote it (its ``.lfstudy-output.json``) and ``overwrite`` is given.

Output directory::

    centers.zarr, calibration.zarr, dark.zarr     the calibration (dark only with dark frames)
    volcal.zarr                                   the volumetric calibration (only with a dot target)
    depth_calibration.zarr                        the depth response (only with a recorded traverse)
    frames/<k>/lightfield.zarr, stack.zarr, volume.zarr
    frames/<k>/particles.zarr                     the particle list (a method that fits particles: ipr)
    piv.zarr        every pair's vector field along ``time`` (series) or ``pair``
    metrics.zarr, metrics.csv                     measurement metrics per pair (unc_median_<c>: median σ)

With ``uncertainty.calibration`` (:mod:`lfstudy.process.uncertainty_calibration`) ``unc_<c>`` is σ
scaled by the study's factor per component and ``unc_raw_<c>`` the estimator's own; the attrs of
``piv.zarr`` and ``metrics.zarr`` and the columns ``unc_cal_factor_<ax>``, ``unc_raw_median_<c>``
of ``metrics.csv`` record the calibration.
    report.html     self-contained
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from lfstudy import io
from lfstudy.process.metrics import divergence, median_uncertainty, pair_metrics, peak_ratio
from lfstudy.process.recording import (
    Recording,
    frame_dir,
    mean_dark,
    open_recording,
    read_frame,
    recording_files,
    warn_saturated,
)
from lfstudy.process.uncertainty_calibration import (
    UncertaintyCalibration,
    apply_calibration,
    calibration_metrics,
    load_calibration,
)
from lfstudy.study import case as cl

__all__ = ["calibrate_recording", "process_recording", "open_result", "uncertainty_summary"]


def calibrate_recording(image: xr.DataArray, camera: Any, kind: str = "pinhole") -> xr.Dataset:
    """Lenslet centres from a recorded calibration image (sec. 5.1).

    A pinhole image (main lens stopped down) shows one small spot per lenslet,
    each centred by eq. 5.1 or its centroid (:func:`~lfstudy.lightfield.find_lenslet_centers`).
    A white image (a uniform target at the working aperture) shows one disk per
    lenslet, and at the matched f-number the disks touch: a single disk's
    centroid is then uncertain (0.3 px RMS on the tiny test camera), the
    affine lattice fitted to all of them is not (0.05 px from the pinhole
    calibration of the same camera), so the lattice positions are the centres.

    Raises
    ------
    ValueError
        The image holds no lenslet lattice (one line naming ``recording.calibration.image``).
    """
    from lfstudy.lightfield import CalibrationError, find_lenslet_centers, pixel_to_sensor

    try:
        centers = find_lenslet_centers(image, camera, estimator="centroid" if kind == "white" else "auto")
    except CalibrationError as exc:
        src = Path(str(image.attrs.get("source", "?"))).name
        raise ValueError(f"recording.calibration.image {src!r} ({kind}): {exc}") from None
    if kind == "white":
        centers = centers.copy()
        centers["cx"] = centers["cx_lattice"].copy()
        centers["cy"] = centers["cy_lattice"].copy()
        x, y = pixel_to_sensor(centers["cx"].values, centers["cy"].values, image.shape, camera.pixel_pitch)
        centers["x"] = (centers["x"].dims, x, centers["x"].attrs)
        centers["y"] = (centers["y"].dims, y, centers["y"].attrs)
        centers.attrs["estimator"] = "lattice"
    return centers


def _pair_coords(rec: Recording) -> dict[str, Any]:
    n = len(rec.pairs)
    dim = rec.pair_dim
    if rec.series:
        step, units = (rec.dt, "s") if rec.dt else (1.0, "frame")
        main = (
            dim,
            (np.arange(n) + 0.5) * step,
            {"units": units, "long_name": "time of the pair (between its frames)"},
        )
    else:
        main = (dim, np.arange(n), {"units": "1", "long_name": "pair number"})
    # frame numbers, not file names: zarr v3 has no stable string type (the names are in attrs)
    return {
        dim: main,
        "frame_a": (dim, np.array([i + 1 for i, _ in rec.pairs]), {"long_name": "first frame (1-based)"}),
        "frame_b": (dim, np.array([j + 1 for _, j in rec.pairs]), {"long_name": "second frame (1-based)"}),
    }


def process_recording(
    cfg: Mapping[str, Any],
    out: str | Path,
    *,
    overwrite: bool = False,
    inputs: Iterable[str | Path] = (),
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> Path:
    """Process a recording config into ``out`` (see the module docstring for the layout).

    Parameters
    ----------
    cfg : mapping
        A validated recording config (:func:`lfstudy.process.config.load_process_config`).
    out : path
        Output directory, written by :func:`lfstudy.io.output_dir`: moved into place when
        everything is written. An existing one is replaced only if it is an earlier output
        of ``lfstudy process`` and ``overwrite`` is given; it may not be, hold or lie inside
        an input (a recording file, ``inputs``).
    overwrite : bool
        Replace an earlier output of ``lfstudy process``.
    inputs : paths
        Further inputs to protect besides the recording's files (the config file).
    progress : bool
        Progress bars of the refocusing and the PIV passes.
    log : callable, optional
        Receives one line per step (e.g. ``print``).

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    ValueError, FileNotFoundError
        A bad recording (:class:`~lfstudy.process.recording.RecordingError`), a
        calibration image without a lenslet lattice, a bad config value, an output
        that may not be written (:class:`~lfstudy.io.OutputError`, before any work);
        nothing is written.
    """
    say = log or (lambda _line: None)
    cam = cl.case_camera(cfg)
    rec = open_recording(cfg["recording"], cam)
    grid = cl.case_grid(cfg, cam)  # a grid too big for the memory bound fails here, before any work
    _check_volcal_depths(cfg, rec, grid.z)
    with warnings.catch_warnings():  # its warnings came with the config's validation already
        warnings.simplefilter("ignore", UserWarning)
        sigma_cal = load_calibration(cfg)  # None without uncertainty.calibration
    out = Path(out)
    prov = io.provenance(cfg)
    protect = [*recording_files(cfg["recording"]), *inputs]
    with io.output_dir(out, command="process", inputs=protect, overwrite=overwrite) as tmp:
        dark = mean_dark(rec)
        if dark is not None:
            dark_da = xr.DataArray(dark, dims=("row", "col"), name="intensity", attrs={"units": "counts", **prov})
            dark_da.attrs["long_name"] = f"mean of {len(rec.dark)} dark frames"
            io.write_zarr(dark_da, tmp / "dark.zarr")
        calib, _ = read_frame(rec, rec.calibration, dark, key="recording.calibration.image", counts=False)
        centers = calibrate_recording(calib, cam, rec.calibration_kind)
        centers.attrs.update(prov, source=str(rec.calibration.path), kind=rec.calibration_kind)
        calib.attrs.update(prov)
        io.write_zarr(calib, tmp / "calibration.zarr")
        io.write_zarr(centers, tmp / "centers.zarr")
        say(
            f"calibration ({rec.calibration_kind}) {rec.calibration.label}: {int(centers.attrs['n_valid'])} lenslets, "
            f"pitch {float(centers.attrs['pitch_px']):.4f} px, lattice residual "
            f"{float(centers.attrs['lattice_rms_px']):.4f} px RMS"
        )
        volcal = _volumetric_calibration(cfg, rec, centers, dark, tmp, prov, say)
        if cfg["refocus"].get("model", "thin_lens") != "volumetric":
            volcal = None  # fitted and stored, but the frames are refocused by the thin-lens model
        depth = _depth_calibration(cfg, rec, centers, dark, tmp, prov, say, progress=progress, calibration=volcal)
        if sigma_cal is not None:
            say(sigma_cal.summary())
        saturated: dict[str, float] = {}
        results: list[xr.Dataset] = []
        metrics: list[xr.Dataset] = []
        for k, frame in enumerate(rec.frames):
            raw, saturated[frame.label] = read_frame(rec, frame, dark)
            lf, stack, volume, particles = cl.render_frame(raw, centers, cfg, calibration=volcal)
            d = tmp / frame_dir(k)
            for obj, name in ((lf, "lightfield"), (stack, "stack"), (volume, "volume"), (particles, "particles")):
                if obj is None:  # no particle list: the method fits none
                    continue
                obj.attrs.update(prov, source=frame.label)
                io.write_zarr(obj, d / f"{name}.zarr", progress=progress and name == "stack")
            found = "" if particles is None else f", {particles.sizes['particle']} particles"
            say(
                f"frame {k + 1}/{len(rec.frames)} {frame.label}: volume {' x '.join(map(str, volume.shape))} voxels "
                f"(z, y, x){found}, {100 * saturated[frame.label]:.3g} % saturated"
            )
            for p, (i, j) in enumerate(rec.pairs):
                if j != k:
                    continue
                res, m = _measure(cfg, rec, tmp, i, j, depth, progress=progress, sigma_cal=sigma_cal)
                m["saturated_percent"] = (
                    (),
                    100.0 * max(saturated[rec.frames[i].label], saturated[rec.frames[j].label]),
                    {"units": "percent", "long_name": "saturated pixels (worse frame)"},
                )
                results.append(res)
                metrics.append(m)
                say(_pair_line(p, rec, m))
        warn_saturated(rec, saturated)
        coords = _pair_coords(rec)
        dim = rec.pair_dim
        piv = xr.concat(results, dim=dim, join="outer", combine_attrs="drop_conflicts").assign_coords(coords)
        piv.attrs.update(prov, title="WIDIM PIV of a recording", **_recording_attrs(rec))
        if sigma_cal is not None:
            piv.attrs.update(sigma_cal.attrs())
        io.write_zarr(piv, tmp / "piv.zarr")
        summary = uncertainty_summary(piv)
        if summary:
            say(summary)
        table = xr.concat(metrics, dim=dim, combine_attrs="drop_conflicts").assign_coords(coords)
        table.attrs.update(prov, **_recording_attrs(rec))
        if sigma_cal is not None:
            table.attrs.update(sigma_cal.attrs())
        io.write_zarr(table, tmp / "metrics.zarr")
        with io.atomic_path(tmp / "metrics.csv") as csv:
            table.to_dataframe().to_csv(csv)
        from lfstudy.process.report import write_process_report

        write_process_report(tmp, cfg, rec, tmp / "report.html")
    say(f"wrote {out}")
    return out


def _recording_attrs(rec: Recording) -> dict[str, Any]:
    out = {f"recording_{k}": v for k, v in rec.summary().items() if v is not None}
    out["frame_labels"] = [f.label for f in rec.frames]  # frame_a/frame_b number these from 1
    return out


def _check_volcal_depths(cfg: Mapping[str, Any], rec: Recording, z: np.ndarray) -> None:
    """Refuse, before any work, a volumetric refocus onto depths the dot target does not cover
    (the polynomial would extrapolate; :func:`lfstudy.lightfield.volcal.volumetric_stack` allows
    :data:`~lfstudy.lightfield.volcal.DEPTH_MARGIN` of the calibrated range either side)."""
    from lfstudy.lightfield.volcal import DEPTH_MARGIN
    from lfstudy.process.recording import RecordingError

    if cfg["refocus"].get("model", "thin_lens") != "volumetric" or not rec.volcal_depths:
        return
    lo, hi = min(rec.volcal_depths), max(rec.volcal_depths)
    tol = DEPTH_MARGIN * (hi - lo)  # the margin VolumetricCalibration.check_depths allows the fitted one
    if float(z.min()) < lo - tol or float(z.max()) > hi + tol:
        raise RecordingError(
            f"recording.volumetric_calibration.depths cover z = {lo:.4g}..{hi:.4g} mm but the reconstruction grid "
            f"spans z = {float(z.min()):.4g}..{float(z.max()):.4g} mm: image the card over the grid's depth, or "
            "narrow grid.z_range"
        )


def _volumetric_calibration(
    cfg: Mapping[str, Any],
    rec: Recording,
    centers: xr.Dataset,
    dark: Any,
    root: Path,
    prov: Mapping[str, Any],
    say: Callable[[str], None],
) -> xr.Dataset | None:
    """The volumetric calibration from the recorded dot target (``recording.volumetric_calibration``), or None.

    Each dot-target image is dark-corrected and registered with the recording's lenslet
    calibration ``centers``; :func:`lfstudy.lightfield.volcal.fit_volumetric` fits the
    per-sub-aperture polynomial on the known dot positions and depths. Written to ``volcal.zarr``.
    """
    from lfstudy.lightfield.registration import register
    from lfstudy.lightfield.volcal import VolumetricCalibrationError, fit_volumetric

    if not rec.volcal_frames:
        return None
    vc = cfg["recording"]["volumetric_calibration"]
    cam = cl.case_camera(cfg)
    key = "recording.volumetric_calibration.images"
    lfs = []
    for frame in rec.volcal_frames:
        raw, _ = read_frame(rec, frame, dark, key=key)
        lfs.append(register(raw, centers, cam))
    extent = vc.get("extent")
    try:
        cal = fit_volumetric(
            lfs,
            rec.volcal_depths,
            cam,
            spacing=float(vc["spacing"]),
            extent=None if extent is None else (float(extent[0]), float(extent[1])),
            order=int(vc.get("order", 3)),
            origin=tuple(float(v) for v in vc.get("origin", (0.0, 0.0))),
            hold_out=-1 if len(rec.volcal_depths) >= int(vc.get("order", 3)) + 2 else None,
        )
    except VolumetricCalibrationError as exc:  # name the recording's keys
        msg = str(exc).replace("volumetric_calibration.", "recording.volumetric_calibration.")
        raise VolumetricCalibrationError(msg) from None
    cal.attrs.update(prov, sources=[f.label for f in rec.volcal_frames])
    io.write_zarr(cal, root / "volcal.zarr")
    a = cal.attrs
    held = (
        f", held-out z = {a['holdout_depth']:.4g} mm {a['holdout_rms_lenslets']:.4f} lenslets RMS"
        if np.isfinite(a["holdout_rms_lenslets"])
        else ", no held-out depth (order + 2 depths needed)"
    )
    say(
        f"volumetric calibration ({len(rec.volcal_frames)} dot-target images, z = {a['z_min']:.4g}..{a['z_max']:.4g} "
        f"mm): {a['n_dots']} dots, {a['valid_subapertures']} sub-apertures, order {a['order']}, fit residual "
        f"{a['fit_rms_lenslets']:.4f} lenslets RMS{held}"
    )
    return cal


def _depth_calibration(
    cfg: Mapping[str, Any],
    rec: Recording,
    centers: xr.Dataset,
    dark: Any,
    root: Path,
    prov: Mapping[str, Any],
    say: Callable[[str], None],
    *,
    progress: bool,
    calibration: xr.Dataset | None = None,
) -> xr.Dataset | None:
    """The depth response from the recorded traverse (``recording.depth_calibration``), or None.

    Every traverse image goes through the frames' chain (dark, registration,
    focal stack, reconstruction; through the volumetric ``calibration`` where
    ``refocus.model`` is volumetric) and is correlated with the start image by the
    recording's PIV; :func:`lfstudy.piv.depth.depth_response` reads the response.
    """
    from lfstudy.piv.depth import depth_response

    if not rec.depth_frames:
        return None
    key = "recording.depth_calibration.images"
    vols = []
    for frame in rec.depth_frames:
        raw, _ = read_frame(rec, frame, dark, key=key)
        vols.append(cl.render_frame(raw, centers, cfg, calibration=calibration)[2].load())
    pairs = [(s, cl.case_piv(cfg, vols[0], v)) for s, v in zip(rec.depth_shifts, vols[1:])]
    min_gain = float(cfg["recording"]["depth_calibration"].get("min_gain", 0.3))
    cal = depth_response(pairs, min_gain=min_gain)
    cal.attrs.update(prov, sources=[f.label for f in rec.depth_frames])
    io.write_zarr(cal, root / "depth_calibration.zarr")
    gains = ", ".join(f"{g:.3f} at {s:.4g} mm" for s, g in zip(cal["shift"].values, cal["gain_total"].values))
    state = "" if cal.attrs["resolves_depth"] else f" (below min_gain {min_gain}: w left as read)"
    say(f"depth calibration ({len(rec.depth_frames)} images): gain {gains}{state}")
    return cal


def _measure(
    cfg: Mapping[str, Any],
    rec: Recording,
    root: Path,
    i: int,
    j: int,
    depth: xr.Dataset | None = None,
    *,
    progress: bool,
    sigma_cal: UncertaintyCalibration | None = None,
) -> tuple[xr.Dataset, xr.Dataset]:
    """PIV of frames ``i``, ``j`` (their stored volumes), its w mapped through the depth response
    when there is one, or run again on the paired particles (``piv.particles: paired``,
    :func:`lfstudy.study.case.case_paired_piv`), its σ scaled by the study's calibration when
    there is one, and the pair's metrics."""
    from lfstudy.piv.depth import correct_depth

    a = io.open_array(root / frame_dir(i) / "volume.zarr").load()
    b = io.open_array(root / frame_dir(j) / "volume.zarr").load()
    res = cl.case_piv(cfg, a, b, progress=progress)
    if depth is not None:
        res = correct_depth(res, depth)
    if cfg["piv"].get("particles") == "paired":  # a particle method without a traverse (process.config)
        parts = [io.open_zarr(root / frame_dir(k) / "particles.zarr").load() for k in (i, j)]
        res = cl.case_paired_piv(cfg, res, a, b, *parts, voxel=cl.volume_voxel(a))
    if sigma_cal is not None:  # after the depth correction: the study's σ of w is the corrected one
        res = apply_calibration(res, sigma_cal)
    ratio = peak_ratio(a, b, res)
    res["peak_ratio"] = ratio
    with contextlib.suppress(ValueError):  # a single window along an axis: no divergence
        res["divergence"] = divergence(res, rec.dt)
    m = pair_metrics(res, ratio, dt=rec.dt)
    m["piv_seconds"] = ((), float(res.attrs["piv_seconds"]), {"units": "s", "long_name": "PIV run time"})
    if sigma_cal is not None:
        m.update(calibration_metrics(res, sigma_cal))
    return res, m


def _pair_line(p: int, rec: Recording, m: xr.Dataset) -> str:
    i, j = rec.pairs[p]
    mean = ", ".join(f"{c} {float(m[f'mean_{c}']):+.3f}" for c in ("u", "v", "w") if f"mean_{c}" in m)
    line = (
        f"pair {p + 1}/{len(rec.pairs)} (frames {i + 1}-{j + 1}): {int(m['n_vectors'])} vectors, "
        f"{float(m['valid_percent']):.1f} % valid, mean [voxel] {mean}"
    )
    if float(m["empty_percent"]) > 0:  # invalid for want of particles, not outliers: say so
        line += (
            f" ({float(m['empty_percent']):.1f} % of the windows empty in a frame: no particles there; "
            "grid.z_range the seeded depth?)"
        )
    if "peak_ratio_median" in m:
        line += f", peak ratio {float(m['peak_ratio_median']):.3g}"
    if "divergence_rms" in m:
        line += f", divergence {float(m['divergence_rms']):.3g} {m['divergence_rms'].attrs['units']} RMS"
    if "focus_scatter_ratio" in m and np.isfinite(float(m["focus_scatter_ratio"])):
        line += f", tracks' scatter nearest focus {float(m['focus_scatter_ratio']):.2g}x the best depth band's"
    sig = ", ".join(f"{c} {float(m[f'unc_median_{c}']):.3g}" for c in ("u", "v", "w") if f"unc_median_{c}" in m)
    if sig:
        line += f", median σ [voxel] {sig}"
    return line


def uncertainty_summary(piv: xr.Dataset) -> str | None:
    """One line: the median standard uncertainty per component over every pair's valid vectors,
    in mm and voxels (:func:`~lfstudy.process.metrics.median_uncertainty`); None for a result
    without ``unc_*`` (``piv.uncertainty: none``)."""
    parts = []
    valid = piv["valid"].values.astype(bool)
    for c in ("u", "v", "w"):
        if f"unc_{c}" not in piv:
            continue
        vox = median_uncertainty(piv[f"unc_{c}"].values, valid)
        if f"unc_{c}_mm" in piv:
            mm = median_uncertainty(piv[f"unc_{c}_mm"].values, valid)
            parts.append(f"{c} {mm:.3g} mm ({vox:.3g} voxel)")
        else:  # volumes without coordinates in mm
            parts.append(f"{c} {vox:.3g} voxel")
    if not parts:
        return None
    n = int(valid.sum())
    calibrated = any(f"unc_raw_{c}" in piv for c in ("u", "v", "w"))
    which = " (calibrated by the study; the report shows it, the raw σ is unc_raw_*)" if calibrated else ""
    return f"uncertainty: median σ{which} of the {n} valid vectors of all pairs: " + ", ".join(parts)


def open_result(out: str | Path) -> xr.Dataset:
    """The vector fields of a processed recording, lazily (dask), with the pairs' metrics.

    Returns
    -------
    xarray.Dataset
        ``piv.zarr`` (``u, v, w`` [voxel], ``u_mm…``, ``unc_u…``, ``unc_u_mm…`` (standard
        uncertainty), ``valid``, ``peak``,
        ``peak_ratio``, ``divergence`` over (``time`` | ``pair``, z, y, x)) with
        the scalar metrics of ``metrics.zarr`` as variables along the pair
        dimension, prefixed ``metric_``.
    """
    out = Path(out)
    piv = io.open_zarr(out / "piv.zarr")
    metrics = io.open_zarr(out / "metrics.zarr")
    extra = {f"metric_{k}": v for k, v in metrics.data_vars.items()}
    return piv.assign(extra)
