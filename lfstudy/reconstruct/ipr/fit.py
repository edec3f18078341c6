"""The fit: :func:`ipr_particles` runs the steps in order (package docstring).

Candidates of the data (:mod:`~lfstudy.reconstruct.ipr.candidates`), their intensities; then ``iterations``
outer iterations, each a shake (:mod:`~lfstudy.reconstruct.ipr.shake`), the removal of ghosts, a residual round
of candidates in the first ``residual_candidates`` and, where scheduled, a round of the image model's calibration
(:mod:`lfstudy.reconstruct.image_model`); then the polish (:mod:`~lfstudy.reconstruct.ipr.polish`) and the split
(:mod:`~lfstudy.reconstruct.ipr.split`). The residual is rendered once (the data, before the first candidate is
placed) and then kept exact incrementally: every change subtracts or adds back an exact image.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import xarray as xr
from tqdm.auto import tqdm

from lfstudy.reconstruct.image_model import calibrate_image_model, model_change
from lfstudy.reconstruct.ipr.camera import _raw_from_lightfield, calibrated_camera, volumetric_frame
from lfstudy.reconstruct.ipr.candidates import (
    _LATE_MART_ITERATIONS,
    _REFINE_XY,
    _REFINE_Z,
    _CandidateVolumes,
    _refined,
    _residual_candidates,
)
from lfstudy.reconstruct.ipr.patches import _FitImages
from lfstudy.reconstruct.ipr.polish import _START_SWEEPS, _polish, _scan_depths
from lfstudy.reconstruct.ipr.settings import IPRSettings
from lfstudy.reconstruct.ipr.shake import _GHOST_FROM, _near_grid, _Particles, _remove_ghosts, _shake, _unwoken
from lfstudy.reconstruct.ipr.split import _split
from lfstudy.reconstruct.registry import ReconstructionError, ReconstructionInputs

__all__ = ["ipr_particles"]

#: the steps whose wall time and particle images the fit's attrs give (``seconds_step_<step>``,
#: ``particle_images_<step>``); their sum is the fit's (its remainder: the set-up, the final residual norm)
STEPS = ("candidates", "shake", "image_calibration", "polish", "split")


class _StepClock:
    """The wall time and the particle images of each of the fit's :data:`STEPS` (``with clock("shake"): ...``),
    read from the images' counter, so the split needs no change in the steps themselves."""

    def __init__(self, images: _FitImages) -> None:
        self.images = images
        self.seconds = dict.fromkeys(STEPS, 0.0)
        self.count = dict.fromkeys(STEPS, 0)

    @contextmanager
    def __call__(self, step: str) -> Iterator[None]:
        t0, n0 = time.perf_counter(), self.images.clock["images"]
        try:
            yield
        finally:
            self.seconds[step] += time.perf_counter() - t0
            self.count[step] += self.images.clock["images"] - n0

    def attrs(self) -> dict[str, Any]:
        """``seconds_step_<step>`` [s] and ``particle_images_<step>`` of every step."""
        out: dict[str, Any] = {f"seconds_step_{k}": float(v) for k, v in self.seconds.items()}
        return out | {f"particle_images_{k}": int(v) for k, v in self.count.items()}


def ipr_particles(
    inputs: ReconstructionInputs,
    settings: IPRSettings | None = None,
    *,
    progress: bool = False,
    start: np.ndarray | None = None,
    **params: Any,
) -> xr.Dataset:
    """Particles fitted to a registered light field by IPR (see the package docstring).

    Parameters
    ----------
    inputs : ReconstructionInputs
        ``lightfield``, ``centers``, ``camera`` and ``grid``; with a volumetric ``calibration``
        the candidates come from MART through it, are moved into the nominal frame the exact
        renderer fits in, and the fitted positions are moved back into the calibrated frame
        (:func:`~lfstudy.reconstruct.ipr.volumetric_frame`), so positions, the rendered volume and PIV are
        calibrated.
    settings : IPRSettings, optional
        The fit's settings (:class:`~lfstudy.reconstruct.ipr.IPRSettings`: each field, its default and its
        range); default: the defaults.
    progress : bool
        A tqdm bar over the iterations.
    start : array_like (n, 3), optional
        A warm start: positions x, y, z [mm] (in the calibrated frame where a volumetric ``calibration`` is
        given, as the fit returns them) that replace the candidates of the first MART volume, e.g. the other
        frame's fitted particles moved by a predicted displacement, as Shake-the-Box starts each frame from its
        tracks' predictions. Each started particle's depth is then taken from this frame's own residual (moved
        along z, within 2 voxels, to where it drops most): near focus the residual is flat in z and the fit would
        keep the start's depth, so the predictor's error in w. The residual rounds still add what the start
        misses; positions more than a voxel outside the grid are dropped. On the demo camera
        (``benchmarks/bench_ipr_warm_start.py``, frame b started from frame a's particles moved by a MART+WIDIM
        predictor 24-51 % short in w) the mean w of the particles found in both frames is within 2.1 % of the cold
        fit's of the same settings, the particles found differ by -1.4 to +3.1 points and the CPU is about the same:
        no gain. Without the depth scan it found 5.6-7.1 points more, but the mean w leaned 2.1-7.9 % towards the
        predictor: the gain was the predictor's depth, which is also its bias. The start's intensities are fitted
        jointly (``_START_SWEEPS`` Gauss–Seidel sweeps, before and after the scan): started at the true positions
        the fit keeps 80.5-96.2 % of the four demo designs' particles (65.3-94.3 % with one sweep,
        ``benchmarks/bench_ipr_depth_slope.py``); from the predictor, on the same two scenes, found 85.6 / 80.3 %
        (85.9 / 80.1 % with one sweep), mean w 0.0984 / 0.0973 mm (0.0985 / 0.0973), for 13-16 % more images.
    **params
        Fields of :class:`~lfstudy.reconstruct.ipr.IPRSettings` replacing those of ``settings``
        (``ipr_particles(inputs, polish=0)``).

    Returns
    -------
    xarray.Dataset
        Over ``particle``: ``x``, ``y``, ``z`` [mm], ``intensity`` (the exact model's: a particle of
        intensity I at the reference solid angle puts I into the image), ``residual`` (‖residual‖/‖image‖
        on its patch), ``sigma_x``, ``sigma_y``, ``sigma_z`` [mm] (from the fit's covariance). Attrs:
        the settings, ``candidates``, ``removed_ghosts``, ``residual_norm`` per iteration (relative,
        exact), ``seconds`` and its split (``seconds_mart``: the candidate volumes, ``mart_volumes`` of them;
        ``seconds_patches``: the exact particle images, ``particle_images`` of them; ``seconds_fit``: the fit
        kernels), its split by step (``seconds_step_<step>`` and ``particle_images_<step>`` for each of
        :data:`STEPS`: the candidates, the shake with the ghosts' removal, the image calibration, the polish and
        the split) and the calibrated grid (:func:`~lfstudy.reconstruct.ipr.calibrated_camera`).

    Raises
    ------
    ReconstructionError
        A required input missing, a setting unknown or out of its range (naming ``reconstruct.ipr.<name>``),
        a light field with non-finite samples, or a calibrated lenslet grid the exact renderer cannot model.
    """
    t_start = time.perf_counter()
    for name in ("lightfield", "centers", "camera", "grid"):
        if getattr(inputs, name) is None:
            raise ReconstructionError(f"reconstruct.ipr needs the {name}")
    s = IPRSettings.of(settings, **params)

    lf, grid, vcal = inputs.lightfield, inputs.grid, inputs.calibration
    cam, ginfo = calibrated_camera(inputs.camera, inputs.centers)
    data, mask = _raw_from_lightfield(lf, (cam.n_pixels_y, cam.n_pixels_x))
    if not np.all(np.isfinite(data)):
        raise ReconstructionError("reconstruct.ipr: the light field has non-finite samples")
    data = np.where(mask > 0, data - s.background, 0.0)
    dz, dy, dx = grid.voxel_size()
    vox = np.array([dx, dy, dz])
    delta = s.shake * vox
    mstep = s.max_step * vox
    central = s.jacobian == "central"
    signs = (1.0, -1.0) if central else (1.0,)
    tr = np.array([[d * delta[i] if a == i else 0.0 for a in range(3)] for i in range(3) for d in signs])
    images = _FitImages(cam, mask, s.image_accuracy, s.batch)
    steps = _StepClock(images)
    inside = (grid.x[0], grid.x[-1]), (grid.y[0], grid.y[-1]), (grid.z[0], grid.z[-1])
    # step 1: the candidates of the data (or the warm start), on the candidate grid's MART plan made once for all
    with steps("candidates"):
        volumes = _CandidateVolumes(
            inputs, _refined(grid, _REFINE_XY, _REFINE_Z), s.residual_plane_step, s.peak_threshold, images.clock
        )
        xyz = volumes.first(lf, s.mart_iterations) if start is None else _start_positions(start, inputs, inside, vox)
    n_cand = len(xyz)
    p = _Particles.unshaken(xyz, np.zeros(len(xyz)))
    norm_d = float(np.sqrt(np.sum(data**2))) or 1.0
    res_hist: list[float] = []
    ghosts = 0
    gain: list[int] = []  # new particles accepted per residual-candidate round
    stop_after, skipped = s.iterations, 0  # residual-candidate rounds skipped from this iteration on
    settle = float(s.shake_settle)
    sat_out: list[int] = []  # particles not shaken, per iteration
    late = False  # residual_late_gain: a round added fewer than that of the list
    calibrate_after = {
        round((k + 1) * s.iterations / (s.image_calibration + 1)) - 1 for k in range(s.image_calibration)
    }
    cal_info: list[dict[str, Any]] = []

    def norm(res: np.ndarray) -> float:
        return float(np.sqrt(np.sum(res**2))) / norm_d

    bar = tqdm(total=s.iterations, desc="IPR", unit="it", disable=not progress)
    # the residual is kept exact incrementally: every image subtracted or added back is the exact one
    res = data.copy()
    if len(p):  # intensities of the candidates first (positions fixed); a warm start's jointly (_START_SWEEPS)
        with steps("candidates"):
            p.inten = images.fit_intensity(p.xyz, res, -1.0, 1 if start is None else _START_SWEEPS)
            if start is not None:  # a warm start's depths from this frame's own data, not the start's
                p.xyz, p.inten = _scan_depths(images, p.xyz, p.inten, res, vox)
    for it in range(s.iterations):
        if not len(p):
            break
        res_hist.append(norm(res))
        # step 3: the shake, then the ghosts (faint particles, particles that left the grid, merged pairs)
        last = it == s.iterations - 1  # no later shake reuses its images
        with steps("shake"):
            p, n_out, events = _shake(images, p, res, vox, settle, tr, delta, mstep, s.damping, central, not last)
            sat_out.append(n_out)
            lit = p.inten > 0
            med = float(np.median(p.inten[lit])) if np.any(lit) else 0.0
            n_before = len(p)
            ghost_floor = s.min_intensity * med if it >= _GHOST_FROM else 0.0
            p, removed = _remove_ghosts(images, p, res, vox, inside, ghost_floor)
        ghosts += n_before - len(p)
        events.append(removed)
        # step 1 again: candidates from the residual, in the first residual_candidates iterations
        if it < s.residual_candidates and it >= stop_after:
            skipped += 1
        elif it < s.residual_candidates:
            its = min(_LATE_MART_ITERATIONS, s.residual_mart_iterations) if late else s.residual_mart_iterations
            floor = s.min_intensity * med
            with steps("candidates"):
                tried, new, amp = _residual_candidates(volumes, images, res, p.xyz, vox, its, s.residual_volume, floor)
            if tried:
                n_cand += tried
                p = p.append(_Particles.unshaken(new, amp))
                events.append(new)
            gain.append(len(new) if tried else 0)
            if gain[-1] < s.residual_candidates_min_gain * len(p):  # the next volumes would repeat this one
                stop_after = it + 1
            late |= gain[-1] < s.residual_late_gain * len(p)  # the later volumes take fewer MART iterations
        if it in calibrate_after and len(p):  # the camera's own particle images (issue 39 §2)
            zr = (float(grid.z[0]), float(grid.z[-1]))
            with steps("image_calibration"):
                model, res, p.inten, info = calibrate_image_model(
                    images.patches, data, res, mask, p.xyz, p.inten, cam, zr, images.model, batch=s.batch
                )
            images.model = model
            cal_info.append(info)
        if settle > 0:  # a change near a settled particle wakes it
            p.still = _unwoken(p.still, p.xyz, np.vstack(events), vox)
        bar.update(1)
        if res_hist:
            bar.set_postfix(particles=len(p), residual=f"{res_hist[-1]:.4f}")
    bar.close()
    # step 4: the polish of the particles near focus
    with steps("polish"):
        p, n_polished, merged = _polish(images, p, res, vox, s.polish)
    ghosts += merged
    # step 5: the split of bright particles into close pairs
    with steps("split"):
        p, n_split, merged = _split(images, p, res, vox, s.split, s.min_intensity, s.split_penalty, s.split_ratio)
    ghosts += merged
    if len(p):
        res_hist.append(norm(res))
    image_attrs: dict[str, Any] = {"image_calibration": int(s.image_calibration), **images.model.to_attrs()}
    if cal_info:  # what the calibration changed, per depth (and its costs per round)
        image_attrs["image_calibration_cost"] = [v for c in cal_info for v in c["image_calibration_cost"]]
        image_attrs["image_calibration_accepted"] = [int(c["image_calibration_accepted"]) for c in cal_info]
        zs = np.linspace(float(grid.z[0]), float(grid.z[-1]), 7)
        image_attrs |= model_change(cam, images.model, zs, images.patches)
    xyz = p.xyz
    if vcal is not None:
        xyz = volumetric_frame(xyz, lf, inputs.camera, vcal, to="calibrated")
    clock = images.clock
    P = "particle"
    mm = lambda ln: {"units": "mm", "long_name": ln}  # noqa: E731
    return xr.Dataset(
        {
            "x": (P, xyz[:, 0], mm("particle x")),
            "y": (P, xyz[:, 1], mm("particle y (up)")),
            "z": (P, xyz[:, 2], mm("particle z (depth from the focal plane)")),
            "intensity": (P, p.inten, {"units": "image units per Ω_ref", "long_name": "fitted intensity"}),
            "residual": (P, p.rel, {"units": "1", "long_name": "fit residual / particle image on its patch"}),
            "sigma_x": (P, p.sig[:, 0], mm("position uncertainty x (fit covariance)")),
            "sigma_y": (P, p.sig[:, 1], mm("position uncertainty y (fit covariance)")),
            "sigma_z": (P, p.sig[:, 2], mm("position uncertainty z (fit covariance)")),
        },
        attrs={
            "method": "ipr",
            "iterations": int(s.iterations),
            "peak_threshold": float(s.peak_threshold),
            "min_intensity": float(s.min_intensity),
            "shake": float(s.shake),
            "max_step": float(s.max_step),
            "damping": float(s.damping),
            "background": float(s.background),
            "candidates": int(n_cand),
            "removed_ghosts": int(ghosts),
            "n_particles": len(xyz),
            "residual_norm": [float(r) for r in res_hist],
            "jacobian": s.jacobian,
            "image_accuracy": s.image_accuracy,
            "residual_candidates": int(s.residual_candidates),
            "mart_iterations": int(s.mart_iterations),
            "residual_mart_iterations": int(s.residual_mart_iterations),
            "residual_plane_step": int(s.residual_plane_step),
            "residual_candidates_min_gain": float(s.residual_candidates_min_gain),
            "residual_late_gain": float(s.residual_late_gain),
            "residual_volume": s.residual_volume,
            "shake_settle": float(s.shake_settle),
            "shake_sat_out": sat_out,
            "candidates_added": gain,
            "skipped_candidate_rounds": int(skipped),
            "polish": int(s.polish),
            "polished": n_polished,
            "split": int(s.split),
            "split_penalty": float(s.split_penalty),
            "split_ratio": float(s.split_ratio),
            "splits": int(n_split),
            "seconds": float(time.perf_counter() - t_start),
            "seconds_mart": float(clock["mart"]),
            "seconds_patches": float(clock["patches"]),
            "seconds_fit": float(clock["fit"]),
            "particle_images": int(clock["images"]),
            "particle_images_reused": int(clock["reused"]),
            "mart_volumes": int(clock["volumes"]),
            **steps.attrs(),
            "weight_table_bytes": int(volumes.plan.proj.table_bytes),
            "coverage_bytes": int(sum(d.nbytes for d in volumes.plan.dens)),
            "warm_start": 0 if start is None else len(np.asarray(start)),
            "frame": "nominal camera" if vcal is None else "volumetric calibration (Hall et al. 2018)",
            **image_attrs,
            **ginfo,
        },
    )


def _start_positions(
    start: Any, inputs: ReconstructionInputs, inside: tuple[tuple[float, float], ...], vox: np.ndarray
) -> np.ndarray:
    """A warm start's positions (n, 3) [mm] in the fit's (nominal) frame, those more than a voxel outside the
    grid's extent ``inside`` dropped (as the fit drops its particles); a clear error for anything that is not
    finite positions."""
    xyz = np.asarray(start, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.all(np.isfinite(xyz)):
        raise ReconstructionError(
            f"reconstruct.ipr: start must be finite positions x, y, z [mm] of shape (n, 3); got shape {xyz.shape}"
            + ("" if xyz.ndim != 2 or xyz.shape[1] != 3 else " with non-finite values")
        )
    xyz = xyz[_near_grid(xyz, inside, vox)]
    if inputs.calibration is not None and len(xyz):  # the exact renderer fits in the nominal camera's frame
        xyz = volumetric_frame(xyz, inputs.lightfield, inputs.camera, inputs.calibration, to="nominal")
    return xyz
