"""The 1-D teaching ray tracer of thesis sec. 4.2 (Figs 4.2–4.9, 4.14).

One point particle at (dy, dz) in the y–z plane is traced through the main
lens, the lenslet array and onto a column of pixels, with the thesis' own
recipe: ray angles drawn uniformly between the aperture edges (eqs
4.12–4.13), the ray count scaled by the subtended angle (eq. 4.14), transfer
matrices in slope form (eqs 4.2–4.4), the lenslet found by division and
rounding (eqs 4.10–4.11) and the pixel by eq. 4.15. Diffraction, optional,
is a Gaussian shift with the camera's σ at the lenslet plane (main-lens
f-number) and at the sensor (lenslet f-number), sec. 4.2.3.

Conventions are those of :mod:`lfstudy.simulate.raytrace`: object +dy up, +dz away
from the camera; sensor y up, row 0 at the top; no flip after tracing.
The thesis' Table 4.1 camera is ``PlenopticCamera(75, 75, 0.0074, 0.125, 0.5, 1.5, -1.0)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import xarray as xr

from lfstudy.optics import PlenopticCamera

__all__ = ["TABLE_4_1", "THESIS_CASES", "table41_camera", "trace_1d", "plot_ray_diagram", "thesis_figures"]

#: Table 4.1 arguments (np,x, np,y, pp, pl, fl, fm, M).
TABLE_4_1 = (75, 75, 0.0074, 0.125, 0.5, 1.5, -1.0)

#: The figures of sec. 4.2: (figure, dy [mm], dz [mm], diffraction).
THESIS_CASES: tuple[tuple[str, float, float, bool], ...] = (
    ("4.2", 0.0, 1.0, False),
    ("4.3", 0.0, -1.0, False),
    ("4.4", -0.062, 0.0, False),
    ("4.5", 0.0, 0.0, False),
    ("4.6", 0.062, 0.0, False),
    ("4.7", 0.063, 0.0, False),
    ("4.8", 0.010, 0.5, False),
    ("4.9", 0.030, 0.5, False),
    ("4.14", 0.062, 0.0, True),
)


def table41_camera() -> PlenopticCamera:
    """The 1-D simulator camera of Table 4.1 (fm = 1.5 mm, M = −1, 5 lenslets of 125 µm)."""
    return PlenopticCamera(*TABLE_4_1)


def trace_1d(
    camera: PlenopticCamera,
    dy: float,
    dz: float,
    n_rays: int = 50_000,
    *,
    diffraction: bool = False,
    seed: int = 0,
) -> xr.Dataset:
    """Trace one particle's rays in the y–z plane (sec. 4.2).

    Parameters
    ----------
    camera : PlenopticCamera
        Only its y geometry is used (rows, pitches, focal lengths, aperture,
        lenslet offset y; the grid rotation is ignored in 1-D).
    dy, dz : float
        Particle shift from the optical axis (up) and from the object focal
        plane (away from the camera) [mm].
    n_rays : int
        Rays at the reference angle γ_ref (on-axis, in focus); eq. 4.14 scales it.
    diffraction : bool
        Apply the Gaussian shifts at the lenslet and sensor planes.
    seed : int
        Seed of the NumPy generator.

    Returns
    -------
    xarray.Dataset
        ``signal`` over ``row`` (pixel signal, coord ``y`` [mm], row 0 at the
        top); ``ray_y`` over (``ray``, ``plane``) with ``plane`` = particle,
        main lens, lenslet array, sensor and coord ``z`` [mm] (sensor at 0,
        the object side negative); ``lenslet`` (row index of the struck
        lenslet, −1 if the ray missed the array) and ``recorded`` per ray.
    """
    if isinstance(n_rays, bool) or not isinstance(n_rays, (int, np.integer)) or n_rays < 1:
        raise ValueError(f"n_rays = {n_rays!r}: must be an integer >= 1")
    for name, v in (("dy", dy), ("dz", dz)):
        if not math.isfinite(v):
            raise ValueError(f"{name} = {v!r}: must be finite")
    so, si, fm, fl = camera.so, camera.si, camera.main_focal_length, camera.lenslet_focal_length
    pl, pp, ny = camera.lenslet_pitch, camera.pixel_pitch, camera.n_pixels_y
    d = so + dz
    if d <= fm:
        raise ValueError(f"dz = {dz!r}: allowed range is dz > f - so = {fm - so:.6g} mm")
    half = camera.aperture_diameter / 2.0
    phi_max = math.atan2(half - dy, d)  # eq. 4.12
    phi_min = math.atan2(-half - dy, d)  # eq. 4.13
    gamma_ref = 2.0 * math.atan2(half, so)
    n = round(n_rays * (phi_max - phi_min) / gamma_ref)  # eq. 4.14
    rng = np.random.default_rng(seed)
    phi = phi_min + (phi_max - phi_min) * rng.random(n)
    t = np.tan(phi)
    y_lens = dy + d * t  # eq. 4.2
    t = t - y_lens / fm  # eq. 4.3
    y_let = y_lens + si * t  # eq. 4.2
    if diffraction:
        y_let = y_let + camera.sigma_lenslet_plane * rng.standard_normal(n)
    # Struck lenslet: divide and round about the (offset) grid, row 0 on top (eqs 4.10–4.11).
    nly = camera.n_lenslets_y
    cy0 = 0.5 * (nly - 1)
    idx = np.floor(cy0 - (y_let - camera.lenslet_offset_y) / pl + 0.5)
    hit = (idx >= 0) & (idx < nly)
    sy = (cy0 - idx) * pl + camera.lenslet_offset_y
    t2 = t - (y_let - sy) / fl  # eq. 4.4
    y_sen = y_let + fl * t2
    if diffraction:
        y_sen = y_sen + camera.sigma_sensor_plane * rng.standard_normal(n)
    row = np.floor((camera.sensor_height / 2.0 - y_sen) / pp)  # eq. 4.15 (0-based)
    rec = hit & (row >= 0) & (row < ny)
    signal = np.bincount(row[rec].astype(np.int64), minlength=ny).astype(np.float64)
    _, yc = camera.pixel_centers()
    z_planes = np.array([-(fl + si + d), -(fl + si), -fl, 0.0])
    mm = lambda ln: {"units": "mm", "long_name": ln}  # noqa: E731
    return xr.Dataset(
        {
            "signal": ("row", signal, {"units": "rays", "long_name": "1-D pixel signal"}),
            "ray_y": (
                ("ray", "plane"),
                np.stack([np.full(n, dy), y_lens, y_let, y_sen], axis=1),
                mm("ray height at each plane"),
            ),
            "lenslet": ("ray", np.where(hit, idx, -1).astype(np.int64), {"long_name": "struck lenslet row"}),
            "recorded": ("ray", rec, {"long_name": "ray landed on the sensor"}),
        },
        coords={
            "y": ("row", yc, mm("sensor y (pixel centre, up)")),
            "plane": ("plane", ["particle", "main lens", "lenslet array", "sensor"]),
            "z": ("plane", z_planes, mm("axial position (sensor at 0)")),
        },
        attrs={
            "dy": float(dy),
            "dz": float(dz),
            "n_rays": n,
            "diffraction": int(bool(diffraction)),
            "seed": int(seed),
            "phi_min": phi_min,
            "phi_max": phi_max,
            "gamma_ref": gamma_ref,
            **camera.to_attrs(),
        },
    )


def _draw(ax_rays, ax_sig, camera: PlenopticCamera, tr: xr.Dataset, n_show: int, title: str) -> None:
    um = 1e3
    z = tr["z"].values * um
    ys = tr["ray_y"].values * um
    show = np.linspace(0, ys.shape[0] - 1, min(n_show, ys.shape[0])).astype(int)
    ax_rays.plot(z[:, None].repeat(show.size, 1), ys[show].T, lw=0.4, color="tab:blue", alpha=0.6)
    h = camera.sensor_height / 2 * um
    z_focal = z[1] - camera.so * um
    for zz, label in ((z_focal, "focal plane"), (z[1], "main lens"), (z[2], "lenslets"), (z[3], "sensor")):
        ax_rays.axvline(zz, color="k", lw=0.8)
        ax_rays.text(zz, 1.02, label, transform=ax_rays.get_xaxis_transform(), rotation=30, fontsize=7)
    # Lenslet boundaries on the lenslet plane.
    cy0 = 0.5 * (camera.n_lenslets_y - 1)
    edges = ((cy0 - np.arange(camera.n_lenslets_y + 1) + 0.5) * camera.lenslet_pitch + camera.lenslet_offset_y) * um
    ax_rays.plot(np.full(edges.size, z[2]), edges, "k_", ms=6)
    ax_rays.plot([z[0]], [tr.attrs["dy"] * um], "ro", ms=3)
    lim = max(h, camera.aperture_diameter / 2 * um) * 1.1
    ax_rays.set_ylim(-lim, lim)
    ax_rays.set_xlabel("Z-coordinate (µm)")
    ax_rays.set_ylabel("Y-coordinate (µm)")
    ax_rays.set_title(title, fontsize=9)
    ax_sig.plot(tr["signal"].values, tr["y"].values * um, drawstyle="steps-mid", color="tab:red")
    ax_sig.set_ylim(-lim, lim)
    ax_sig.set_xlabel("signal (rays)")
    ax_sig.tick_params(labelleft=False)
    ax_sig.set_xlim(left=0)


def plot_ray_diagram(
    camera: PlenopticCamera | None = None,
    dy: float = 0.0,
    dz: float = 0.0,
    *,
    n_rays: int = 50_000,
    n_show: int = 100,
    diffraction: bool | Sequence[bool] = (False, True),
    seed: int = 0,
):
    """Ray diagram and 1-D signal, as Figs 4.2–4.9 and 4.14.

    Draws ``n_show`` of the traced rays (evenly picked) from the particle
    through the main lens and lenslet array to the sensor, with the focal
    plane, main lens, lenslet array and sensor as vertical lines and the 1-D
    pixel signal beside the sensor. One row per entry of ``diffraction``
    (default: without and with diffraction). Uses the Agg backend.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    camera = camera or table41_camera()
    modes = [diffraction] if isinstance(diffraction, bool) else list(diffraction)
    fig = Figure(figsize=(9, 3.4 * len(modes)), layout="constrained")
    axes = fig.subplots(len(modes), 2, squeeze=False, gridspec_kw={"width_ratios": [4, 1]})
    for (ax_r, ax_s), diff in zip(axes, modes):
        tr = trace_1d(camera, dy, dz, n_rays, diffraction=diff, seed=seed)
        title = (
            f"dy = {dy * 1e3:+.0f} µm, dz = {dz * 1e3:+.0f} µm, "
            f"{'with' if diff else 'without'} diffraction ({n_show} of {tr.attrs['n_rays']:,} rays)"
        )
        _draw(ax_r, ax_s, camera, tr, n_show, title)
    return fig


def thesis_figures(camera: PlenopticCamera | None = None, **kwargs) -> dict[str, object]:
    """The ray diagrams of Figs 4.2–4.9 and 4.14 (Table 4.1 camera), keyed by figure number."""
    camera = camera or table41_camera()
    return {fig: plot_ray_diagram(camera, dy, dz, diffraction=diff, **kwargs) for fig, dy, dz, diff in THESIS_CASES}
