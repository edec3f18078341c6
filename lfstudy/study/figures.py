"""Figures of the study report: pure functions from data to a matplotlib Figure.

No file I/O here (``lfstudy.study.report`` reads the artefacts and embeds or saves
the figures). Figures are created with :class:`matplotlib.figure.Figure`
directly, never through ``pyplot``'s global state, so they work on the Agg
backend in a Snakemake job and are garbage-collected when dropped.
Figure numbers refer to Lynch (2011).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import xarray as xr
from matplotlib import rc_context
from matplotlib.figure import Figure

from lfstudy.optics import OpticsError, PlenopticCamera

__all__ = [
    "ambiguity_vs_magnification",
    "focal_plane_diamonds",
    "raw_crop",
    "refocused_planes",
    "intensity_histogram",
    "piv_convergence",
    "displacement_histograms",
    "vector_slices",
    "series_metrics",
    "metrics_vs_parameter",
    "uncertainty_maps",
    "uncertainty_histograms",
    "error_vs_uncertainty",
    "tolerance_figure",
]

_COMP = {"x": "u", "y": "v", "z": "w"}


def _plain_ticks(make: Callable[..., Figure]) -> Callable[..., Figure]:
    """Draw with plain tick labels: a metric that barely varies (0.83570 … 0.83571) labels its
    ticks with their values, not as an offset (``1e−5+8.357e−1``) that reads as the value."""

    @functools.wraps(make)
    def plain(*args: Any, **kwargs: Any) -> Figure:
        with rc_context({"axes.formatter.useoffset": False}):
            return make(*args, **kwargs)

    return plain


def _fig(w: float, h: float, **adjust: float) -> Figure:
    # Fixed margins, not a layout engine: constrained layout triples the
    # drawing time of a report with hundreds of small figures.
    fig = Figure(figsize=(w, h), dpi=90)
    fig.subplots_adjust(
        **{"left": 0.1, "right": 0.95, "bottom": 0.14, "top": 0.88, "wspace": 0.3, "hspace": 0.45, **adjust}
    )
    return fig


# ------------------------------------------------------------------ optics
@_plain_ticks
def ambiguity_vs_magnification(
    camera: PlenopticCamera, magnifications: Sequence[float] | None = None, *, marked: Sequence[float] = ()
) -> Figure:
    """Depth and in-plane ambiguity ξz, ξy against magnification (Fig. 4.11, eqs 4.18–4.19).

    Parameters
    ----------
    camera : PlenopticCamera
        Supplies the focal length, lenslet pitch and f-number policy; its
        magnification is replaced by each value of ``magnifications``.
    magnifications : sequence of float, optional
        Negative magnifications; default −0.1 … −3.
    marked : sequence of float
        Magnifications of the sweep, marked on the curves.
    """
    ms = np.linspace(-0.1, -3.0, 59) if magnifications is None else np.asarray(magnifications, float)
    allm = np.unique(np.concatenate([ms, np.asarray(marked, float)]))
    rows = []
    for m in allm:
        try:
            dof = camera.with_(magnification=float(m)).depth_of_field(0.0)
        except OpticsError:
            continue  # this M is not reachable with the f-number policy
        rows.append((abs(m), float(dof["depth_ambiguity"][0]), float(dof["inplane_ambiguity"][0])))
    fig = _fig(6.5, 3.6, top=0.9)
    ax = fig.add_subplot()
    if rows:
        a = np.array(sorted(rows))
        ax.plot(a[:, 0], a[:, 1], "-", color="C0", label="depth ambiguity ξz")
        ax.plot(a[:, 0], a[:, 2], "-", color="C1", label="in-plane ambiguity ξy")
        for m in marked:
            hit = np.isclose(a[:, 0], abs(m))
            if hit.any():
                ax.plot(a[hit, 0], a[hit, 1], "o", color="C0")
                ax.plot(a[hit, 0], a[hit, 2], "o", color="C1")
        ax.set_yscale("log")
    ax.set_xlabel("|magnification M|")
    ax.set_ylabel("ambiguity [mm]")
    ax.set_title(f"Ambiguity vs magnification, f = {camera.main_focal_length:g} mm (cf. Fig. 4.11)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    return fig


@_plain_ticks
def focal_plane_diamonds(cameras: Mapping[str, tuple[PlenopticCamera, xr.Dataset]]) -> Figure:
    """Depth-of-focus diamonds of the refocus planes in image space (Fig. 5.9, eqs 5.16–5.20).

    Each plane's diamond spans its near and far image-side bounds D_N,i, D_F,i
    (on the axis, t = D − si) and the circle of confusion c at D_i; plane
    centres are marked.

    Parameters
    ----------
    cameras : mapping label -> (camera, planes)
        ``planes`` from :meth:`PlenopticCamera.focal_planes`.
    """
    n = max(1, len(cameras))
    h = 1.9 * n + 1.0
    fig = _fig(7.0, h, left=0.12, top=1 - 0.75 / h, bottom=0.55 / h, hspace=0.6)
    axes = fig.subplots(n, 1, squeeze=False)[:, 0]
    for ax, (label, (cam, planes)) in zip(axes, cameras.items()):
        c = float(planes.attrs.get("circle_of_confusion", cam.lenslet_pitch))
        si = cam.si
        for k in range(planes.sizes["plane"]):
            near = float(planes["near"][k]) - si
            far = float(planes["far"][k]) - si
            mid = float(planes["t"][k])
            ax.fill(
                [near, mid, far, mid], [0, c / 2, 0, -c / 2], alpha=0.35, color="C0" if k % 2 else "C1", lw=0.5, ec="k"
            )
        ax.plot(planes["t"], np.zeros(planes.sizes["plane"]), "k|", ms=8)
        ax.set_ylabel("height [mm]")
        ax.set_title(f"{label}: {planes.sizes['plane']} planes, f/{cam.main_fnumber:g}", fontsize=9)
    axes[-1].set_xlabel("refocus distance t = D_i − s_i [mm]")
    fig.suptitle("Focal-plane depth-of-focus diamonds (cf. Fig. 5.9, Table 5.1)", y=1 - 0.2 / h)
    return fig


# ----------------------------------------------------------------- images
@_plain_ticks
def raw_crop(raw: xr.DataArray, *, size: int = 160) -> Figure:
    """The central ``size`` × ``size`` pixels of a raw plenoptic image (cf. Fig. 4.21).

    ``raw`` has dims (row, col) with physical ``x``/``y`` coords [mm]; only the
    crop is read (lazy input stays lazy).
    """
    nr, nc = raw.sizes[raw.dims[0]], raw.sizes[raw.dims[1]]
    r0, c0 = max(0, nr // 2 - size // 2), max(0, nc // 2 - size // 2)
    crop = raw.isel({raw.dims[0]: slice(r0, r0 + size), raw.dims[1]: slice(c0, c0 + size)})
    img = np.asarray(crop.values, float)
    fig = _fig(4.8, 4.4, left=0.16, right=0.92)
    ax = fig.add_subplot()
    extent = None
    if "x" in crop.coords and "y" in crop.coords and crop["x"].ndim == 1 and crop["y"].ndim == 1:
        x, y = crop["x"].values, crop["y"].values
        extent = (x[0], x[-1], y[-1], y[0])  # row 0 at the top
    im = ax.imshow(img, cmap="gray", extent=extent, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.8, label="intensity")
    ax.set_xlabel("sensor x [mm]" if extent else "column")
    ax.set_ylabel("sensor y [mm]" if extent else "row")
    ax.set_title(f"Raw image, central {img.shape[0]}×{img.shape[1]} px")
    return fig


@_plain_ticks
def refocused_planes(stack: xr.DataArray, *, n: int = 4) -> Figure:
    """``n`` planes of a focal stack spread over its depth (cf. Figs 5.12–5.16)."""
    nz = stack.sizes["z"]
    ks = np.unique(np.linspace(0, nz - 1, min(n, nz)).round().astype(int))
    fig = _fig(3.2 * len(ks), 3.2, left=0.08, top=0.82, bottom=0.16)
    axes = fig.subplots(1, len(ks), squeeze=False)[0]
    x, y = stack["x"].values, stack["y"].values
    for ax, k in zip(axes, ks):
        img = np.asarray(stack.isel(z=int(k)).transpose("y", "x").values, float)
        ax.imshow(img, cmap="gray", origin="lower", extent=(x[0], x[-1], y[0], y[-1]), interpolation="nearest")
        ax.set_title(f"z = {float(stack['z'][k]):+.3f} mm", fontsize=9)
        ax.set_xlabel("x [mm]")
    axes[0].set_ylabel("y [mm]")
    fig.suptitle("Refocused planes (constant magnification, object frame)")
    return fig


@_plain_ticks
def intensity_histogram(values: np.ndarray, *, k: float = 3.0, bins: int = 100, title: str = "") -> Figure:
    """Histogram of rendered intensities with the threshold mean + kσ (Figs 5.17, 7.13–7.14, sec. 5.5)."""
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    mu, sd = float(v.mean()), float(v.std())
    thr = mu + k * sd
    fig = _fig(6.0, 3.4, left=0.12, top=0.9)
    ax = fig.add_subplot()
    ax.hist(v, bins=bins, color="0.5")
    ax.axvline(mu, color="C0", ls="--", label=f"mean {mu:.3g}")
    ax.axvline(thr, color="C3", label=f"threshold mean + {k:g}σ = {thr:.3g}")
    ax.set_yscale("log")
    ax.set_xlabel("intensity")
    ax.set_ylabel("voxels")
    kept = 100.0 * float(np.mean(v > thr)) if v.size else math.nan
    ax.set_title(title or f"Focal-stack intensities ({kept:.2f} % above threshold)", fontsize=10)
    ax.legend(fontsize=8)
    return fig


# -------------------------------------------------------------------- PIV
@_plain_ticks
def piv_convergence(piv: xr.Dataset) -> Figure:
    """Corrector RMS and valid-vector percentage per pass, with the level Rf (Figs 6.14–6.15)."""
    p = piv["pass"].values if "pass" in piv.coords else np.arange(1, piv.sizes["pass"] + 1)
    lvl = piv["level"].values if "level" in piv else None
    fig = _fig(9.0, 3.2, left=0.08, right=0.92, wspace=0.5, top=0.88, bottom=0.16)
    axes = fig.subplots(1, 2)
    for ax, name, ylabel, log in (
        (axes[0], "corrector_rms", "corrector RMS [voxel]", True),
        (axes[1], "valid_percent", "valid vectors [%]", False),
    ):
        if name in piv:
            ax.plot(p, piv[name].values, "o-", color="C0")
        if log:
            ax.set_yscale("log")
        ax.set_xlabel("pass")
        ax.set_ylabel(ylabel)
        if lvl is not None:
            tw = ax.twinx()
            tw.step(p, lvl, where="mid", color="C1", alpha=0.6)
            tw.set_ylabel("refinement level Rf", color="C1")
            tw.set_yticks(np.unique(lvl))
    axes[0].set_title("Corrector RMS (cf. Fig. 6.14)", fontsize=10)
    axes[1].set_title("Valid vectors (cf. Fig. 6.15)", fontsize=10)
    return fig


@_plain_ticks
def displacement_histograms(piv: xr.Dataset, errors: xr.Dataset | None = None, *, bins: int = 50) -> Figure:
    """Histograms of the measured displacement per component with μ and σ (Figs 7.2–7.4, 7.8).

    Valid vectors only, in mm where the result holds ``<c>_mm`` (else in voxels), object-frame sign. The
    mean true displacement (from ``errors``) is drawn as a dashed line.
    """
    comps = [(ax, c) for ax, c in _COMP.items() if c in piv]
    mm = all(f"{c}_mm" in piv for _, c in comps)  # in mm where the result has it: designs compare in mm
    unit = "mm" if mm else "vox"
    fig = _fig(4.0 * max(1, len(comps)), 3.3, left=0.07, top=0.84, bottom=0.16)
    axes = fig.subplots(1, max(1, len(comps)), squeeze=False)[0]
    valid = piv["valid"].values.astype(bool) if "valid" in piv else None
    for a, (axn, c) in zip(axes, comps):
        d = np.asarray(piv[f"{c}_mm" if mm else c].values, float)
        d = d[valid & np.isfinite(d)] if valid is not None else d[np.isfinite(d)]
        if d.size:
            # The thesis' 50 bins over 4800 vectors; fewer for small grids.
            a.hist(d, bins=int(min(bins, max(10, 2 * math.sqrt(d.size)))), color="C0", alpha=0.8)
            a.text(
                0.03,
                0.95,
                f"μ = {d.mean():+.3g} {unit}\nσ = {d.std():.3g} {unit}\nn = {d.size}",
                transform=a.transAxes,
                va="top",
                fontsize=8,
                bbox={"fc": "white", "alpha": 0.8, "lw": 0},
            )
        else:
            a.text(0.5, 0.5, "no valid vector", ha="center", transform=a.transAxes)
        true = f"true_{axn}_mm" if mm else f"true_{axn}"
        if errors is not None and true in errors and np.isfinite(float(errors[true])):
            a.axvline(float(errors[true]), color="C3", ls="--", label="true mean")
            a.legend(fontsize=7, loc="upper right")
        a.set_xlabel(f"{axn} displacement {c} [{'mm' if mm else 'voxel'}]")
    axes[0].set_ylabel("count")
    fig.suptitle("Displacement histograms, valid vectors (cf. Figs 7.2–7.4, 7.8)")
    return fig


def _quiver(ax: Any, x: Any, y: Any, u: Any, v: Any, **kw: Any) -> Any:
    """``ax.quiver``, with a fixed scale when no arrow has a length (a pair of identical frames):
    matplotlib's autoscale divides by the mean arrow length.

    Arrows all at the origin (one vector per axis on a grid centred on 0: a small recording)
    are drawn with ``angles="uv"``: with ``angles="xy"`` matplotlib measures the arrows over a
    step of 0.001 times the data's extent, which is 0 there, and divides by it at draw time
    (``RuntimeWarning: invalid value encountered in divide`` on every such run). With the axes'
    equal default range about a single point both give the same arrow.
    """
    if not np.any(np.nan_to_num(np.hypot(u, v))):
        kw.setdefault("scale", 1.0)
    if kw.get("angles") == "xy" and not np.any(np.nan_to_num(np.abs(x))) and not np.any(np.nan_to_num(np.abs(y))):
        kw["angles"] = "uv"
    return ax.quiver(x, y, u, v, **kw)


@_plain_ticks
def vector_slices(piv: xr.Dataset) -> Figure:
    """Quiver plots: u, v on the middle z slice; u, w on the middle y slice; and
    the middle z slice with the mean displacement subtracted (cf. Figs 7.1, 7.6, 7.9)."""
    fig = _fig(13.5, 4.2, left=0.06, right=0.98, top=0.9, bottom=0.14, wspace=0.25)
    axes = fig.subplots(1, 3)
    valid = piv["valid"] if "valid" in piv else xr.ones_like(piv["u"], dtype=bool)
    get = lambda c: piv[f"{c}_mm"] if f"{c}_mm" in piv else piv[c]  # noqa: E731
    unit = "mm" if "u_mm" in piv else "voxel"
    if "z" in piv.dims:
        kz, ky = piv.sizes["z"] // 2, piv.sizes["y"] // 2
        sl_xy = {"z": kz}
        sl_xz = {"y": ky}
    else:  # 2-D result
        sl_xy, sl_xz, kz = {}, None, None
    u, v = get("u").where(valid), get("v").where(valid)
    x, y = piv["x"].values, piv["y"].values
    uxy = u.isel(sl_xy).transpose("y", "x").values
    vxy = v.isel(sl_xy).transpose("y", "x").values
    ax = axes[0]
    _quiver(ax, x, y, uxy, vxy, angles="xy")
    ax.set_title("x–y slice" + (f" at z = {float(piv['z'][kz]):+.2f} mm" if kz is not None else ""), fontsize=9)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_aspect("equal")
    ax = axes[1]
    if sl_xz is not None and "w" in piv:
        w = get("w").where(valid)
        _quiver(
            ax,
            x,
            piv["z"].values,
            u.isel(sl_xz).transpose("z", "x").values,
            w.isel(sl_xz).transpose("z", "x").values,
            angles="xy",
        )
        ax.set_title(f"x–z slice at y = {float(piv['y'][ky]):+.2f} mm", fontsize=9)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("z [mm] (+ away from camera)")
    else:
        ax.set_axis_off()
    ax = axes[2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        du, dv = uxy - np.nanmean(uxy), vxy - np.nanmean(vxy)
    _quiver(ax, x, y, du, dv, angles="xy", color="C3")
    ax.set_title(f"x–y slice, mean subtracted ({unit})", fontsize=9)
    ax.set_xlabel("x [mm]")
    ax.set_aspect("equal")
    return fig


@_plain_ticks
def series_metrics(table: xr.Dataset, metrics: Sequence[str], dim: str, *, ncols: int = 3) -> Figure:
    """Scalar metrics of a processed recording against its pairs (time, or pair number).

    One panel per metric, labelled from its ``long_name`` and ``units``.
    """
    metrics = [m for m in metrics if m in table]
    nrows = max(1, math.ceil(len(metrics) / ncols))
    fig = _fig(4.0 * ncols, 2.7 * nrows, left=0.07, right=0.98, top=0.93, bottom=0.1, wspace=0.35, hspace=0.6)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    t = table[dim]
    for ax, m in zip(axes, metrics):
        ax.plot(t.values, np.asarray(table[m].values, float), "o-", color="C0", ms=3)
        ax.set_title(_label(table[m]), fontsize=9)
        ax.set_xlabel(f"{dim} [{t.attrs['units']}]" if t.attrs.get("units") not in (None, "1") else dim)
    for ax in axes[len(metrics) :]:
        ax.set_axis_off()
    return fig


# ------------------------------------------------------------ comparative
def _label(da: xr.DataArray) -> str:
    ln = da.attrs.get("long_name", da.name)
    u = da.attrs.get("units")
    return f"{ln} [{u}]" if u and u != "1" else str(ln)


@_plain_ticks
def metrics_vs_parameter(
    study: xr.Dataset, metrics: Sequence[str], param: str, line_param: str | None = None, *, ncols: int = 4
) -> Figure:
    """Every metric against one swept parameter (the comparative figure).

    One subplot per metric; x: the values of ``param``; one line per value of
    ``line_param`` (colour) and per flow (line style). Other swept
    parameters are averaged over the computed cases (NaN-aware), which is
    stated in the axis label.
    """
    metrics = [m for m in metrics if m in study]
    nrows = max(1, math.ceil(len(metrics) / ncols))
    h = 2.7 * nrows + 1.2
    fig = _fig(3.6 * ncols, h, left=0.06, right=0.98, top=1 - 0.8 / h, bottom=0.85 / h, hspace=0.6, wspace=0.3)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    xs = study[param].values
    numeric = np.issubdtype(np.asarray(xs).dtype, np.number)
    xpos = xs.astype(float) if numeric else np.arange(len(xs))
    flows = list(study["flow"].values) if "flow" in study.dims and param != "flow" else [None]
    lines = list(study[line_param].values) if line_param else [None]
    styles = ["-", "--", ":", "-."]
    other = [d for d in study[metrics[0]].dims if d not in (param, line_param, "flow")] if metrics else []
    for ax, m in zip(axes, metrics):
        da = study[m]
        for fi, fl in enumerate(flows):
            for li, lv in enumerate(lines):
                sub = da
                if fl is not None:
                    sub = sub.sel(flow=fl)
                if lv is not None:
                    sub = sub.sel({line_param: lv})
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    red = [d for d in other if d in sub.dims] + (
                        ["flow"] if param != "flow" and fl is None and "flow" in sub.dims else []
                    )
                    y = sub.mean(red, skipna=True) if red else sub
                y = np.asarray(y.transpose(param).values, float)
                if not np.isfinite(y).any():
                    continue
                lab = ", ".join(
                    s
                    for s in (
                        f"{line_param}={lv}" if lv is not None else "",
                        str(fl) if fl is not None and len(flows) > 1 else "",
                    )
                    if s
                )
                ax.plot(xpos, y, styles[fi % len(styles)], marker="o", color=f"C{li % 10}", label=lab or None)
        if m.startswith("bias"):
            ax.axhline(0.0, color="k", lw=0.5)
        if param == "ppp" and numeric and np.all(xpos > 0) and len(xpos) > 1:
            ax.set_xscale("log")
        if not numeric:
            ax.set_xticks(xpos, [str(v) for v in xs])
        ax.set_title(_label(da), fontsize=8)
        ax.set_xlabel(_label(study[param]), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    for ax in axes[len(metrics) :]:
        ax.set_axis_off()
    handles, labels = axes[0].get_legend_handles_labels() if metrics else ([], [])
    if labels:
        fig.legend(handles, labels, loc="lower center", ncols=min(6, len(labels)), fontsize=8)
    note = f"; mean over {', '.join(other)}" if other else ""
    fig.suptitle(f"Error metrics against {param}{note}", y=1 - 0.2 / h)
    return fig


# ------------------------------------------------------------ the answer
def _categorical(ax: Any, values: Sequence[Any], axis: str = "x") -> np.ndarray:
    """Positions 0..n-1 labelled with the values as the case ids write them (discrete sweep values)."""
    from lfstudy.study.sweep import format_value

    pos = np.arange(len(values))
    labels = [format_value(v.item() if hasattr(v, "item") else v) for v in values]
    rot = 30 if max((len(s) for s in labels), default=0) * len(labels) > 40 else 0
    if axis == "x":
        ax.set_xticks(pos, labels, rotation=rot, ha="right" if rot else "center")
    else:
        ax.set_yticks(pos, labels)
    return pos


@_plain_ticks
def overview_heatmap(study: xr.Dataset, var: str, dims: Sequence[str]) -> Figure:
    """The headline metric over the two most influential swept settings, one panel per flow.

    Cells hold the mean over every other setting (NaN-aware), written in the cell;
    lower is better (the colour map is reversed), so the best corner reads at a glance.
    """
    da = study[var]
    flows = list(study["flow"].values) if "flow" in study.dims else [None]
    d1, d2 = dims[0], dims[1] if len(dims) > 1 else None
    fig = _fig(4.6 * len(flows) + 0.8, 3.9, left=0.12, right=0.92, bottom=0.22, top=0.85, wspace=0.45)
    axes = np.atleast_1d(fig.subplots(1, len(flows)))
    vals = []
    for fl in flows:
        sub = da.sel(flow=fl) if fl is not None else da
        keep = [d for d in (d2, d1) if d]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            m = sub.mean([d for d in sub.dims if d not in keep], skipna=True)
        vals.append(np.atleast_2d(np.asarray(m.transpose(*keep).values, float)))
    finite = np.concatenate([v[np.isfinite(v)] for v in vals]) if vals else np.array([])
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    im = None
    for ax, fl, v in zip(axes, flows, vals):
        im = ax.imshow(v, origin="lower", aspect="auto", cmap="viridis_r", vmin=vmin, vmax=vmax)
        for (i, j), x in np.ndenumerate(v):
            if np.isfinite(x):
                ax.text(
                    j, i, f"{x:.3g}", ha="center", va="center", fontsize=8, color="w" if x > (vmin + vmax) / 2 else "k"
                )
        _categorical(ax, study[d1].values, "x")
        ax.set_xlabel(_label(study[d1]), fontsize=8)
        if d2:
            _categorical(ax, study[d2].values, "y")
            ax.set_ylabel(_label(study[d2]), fontsize=8)
        else:
            ax.set_yticks([])
        ax.set_title(str(fl) if fl is not None else "", fontsize=9)
        ax.tick_params(labelsize=7)
    if im is not None:
        cb = fig.colorbar(im, ax=list(axes), shrink=0.85)
        cb.set_label(_label(da), fontsize=8)
    fig.suptitle(f"{_label(da)}: mean over the other settings (lower is better)", fontsize=10)
    return fig


#: A metric whose values span less than this fraction of their size is drawn as constant (issue 37: Q ran
#: 0.835758-0.835772 on the demo designs, and its ticks read as a range).
STEADY = 1e-3


def _steady_axis(ax: Any, values: np.ndarray) -> None:
    """Where ``values`` span less than :data:`STEADY` of their size, fix the y axis at ±2 % about their
    mean (ticks with few digits) and write the value in the panel: the spread is rounding, not a finding."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return
    mean = float(v.mean())
    if float(np.ptp(v)) > STEADY * abs(mean) or mean == 0.0:
        return
    half = 0.02 * abs(mean)
    ax.set_ylim(mean - half, mean + half)
    ax.text(
        0.5, 0.9, f"{mean:.4g} on every case (within {100 * STEADY:g} %)", transform=ax.transAxes, ha="center",
        fontsize=7, color="0.3", bbox={"fc": "white", "alpha": 0.8, "lw": 0},
    )  # fmt: skip


@_plain_ticks
def parameter_panels(study: xr.Dataset, dim: str, metrics: Sequence[str]) -> Figure:
    """A few headline metrics against one swept setting (categorical axis), one line per flow,
    the other settings averaged over the computed cases. With replicates (a swept ``seed``) each
    point is the mean over the seeds of that average, its bar their standard deviation."""
    from lfstudy.study.replicates import replicate_dim

    rep = replicate_dim(study)
    metrics = [m for m in metrics if m in study]
    n = max(1, len(metrics))
    fig = _fig(3.3 * n, 3.1, left=0.07, right=0.98, bottom=0.27, top=0.84, wspace=0.4)
    axes = np.atleast_1d(fig.subplots(1, n))
    flows = list(study["flow"].values) if "flow" in study.dims and dim != "flow" else [None]
    for ax, m in zip(axes, metrics):
        pos = _categorical(ax, study[dim].values)
        _steady_axis(ax, np.asarray(study[m].where(study["computed"]) if "computed" in study else study[m], float))
        for i, fl in enumerate(flows):
            sub = study[m].sel(flow=fl) if fl is not None else study[m]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                y = sub.mean([d for d in sub.dims if d not in (dim, rep)], skipna=True)
                if rep is not None:
                    y, sd = y.mean(rep, skipna=True), y.std(rep, ddof=1, skipna=True)
            label = str(fl) if fl is not None else None
            if rep is None:
                ax.plot(pos, np.asarray(y.values, float), "o-", color=f"C{i}", label=label)
            else:
                ax.errorbar(
                    pos, np.asarray(y.values, float), np.asarray(sd.values, float), fmt="o-", color=f"C{i}",
                    capsize=2, label=label,
                )  # fmt: skip
        if m.startswith("bias"):
            ax.axhline(0.0, color="k", lw=0.5)
        ax.set_title(_label(study[m]), fontsize=8)
        ax.set_xlabel(_label(study[dim]), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    h, lab = axes[0].get_legend_handles_labels()
    if lab:
        fig.legend(h, lab, loc="upper right", fontsize=7, ncols=min(4, len(lab)))
    over = "mean over the other settings" + ("; bars: sd over the seeds" if rep is not None else "")
    fig.suptitle(f"Against {dim} ({over})", fontsize=10, x=0.4)
    return fig


@_plain_ticks
def tolerance_figure(
    table: Any, level: str, panels: Mapping[str, str], oracle: Mapping[str, str] | None = None
) -> Figure:
    """The error against one imperfection's level, per design (colour) and flow (line style).

    Parameters
    ----------
    table : pandas.DataFrame
        :func:`lfstudy.study.tolerance.tolerance_table`: ``design``, ``flow`` (optional), the level
        column and the metrics.
    level : str
        The level column (its name, the setting's label with units, labels the x axes).
    panels : mapping column -> title
        One panel per metric, in order.
    oracle : mapping column -> oracle column, optional
        Drawn dashed in the design's colour in that metric's panel (the PIV on the true volumes).
    """
    oracle = dict(oracle or {})
    cols = [c for c in panels if c in table]
    n = max(1, len(cols))
    fig = _fig(3.0 * n, 3.0, left=0.3 / n + 0.02, right=0.98, bottom=0.2, top=0.8, wspace=0.45)
    axes = np.atleast_1d(fig.subplots(1, n))
    levels = list(dict.fromkeys(table[level].tolist())) if level in table else []
    numeric = all(isinstance(v, (int, float, np.integer, np.floating)) for v in levels)
    designs = list(dict.fromkeys(table["design"])) if "design" in table else [""]
    flows = list(dict.fromkeys(table["flow"])) if "flow" in table else [None]
    styles = ["o-", "s:", "^-.", "d--"]
    for ax, c in zip(axes, cols):
        pos = {v: v for v in levels} if numeric else dict(zip(levels, _categorical(ax, levels)))
        for i, dsg in enumerate(designs):
            for j, fl in enumerate(flows):
                sel = (table["design"] == dsg) if "design" in table else np.ones(len(table), bool)
                if fl is not None:
                    sel = sel & (table["flow"] == fl)
                sub = table[sel]
                if sub.empty:
                    continue
                x = np.asarray([pos[v] for v in sub[level]], float)
                order = np.argsort(x, kind="stable")
                label = dsg + (f", {fl}" if fl is not None and len(flows) > 1 else "")
                y = np.asarray(sub[c], float)[order]
                if f"{c}_sd" in sub:  # replicates: the mean over the seeds, bars their sd
                    sd = np.asarray(sub[f"{c}_sd"], float)[order]
                    ax.errorbar(
                        x[order], y, sd, fmt=styles[j % len(styles)], color=f"C{i % 10}", ms=4, capsize=2, label=label
                    )
                else:
                    ax.plot(x[order], y, styles[j % len(styles)], color=f"C{i % 10}", ms=4, label=label)
                if c in oracle and oracle[c] in sub:
                    yo = np.asarray(sub[oracle[c]], float)[order]
                    ax.plot(x[order], yo, "--", color=f"C{i % 10}", lw=0.9, alpha=0.8)
        ax.set_title(panels[c] + (" (dashed: oracle)" if c in oracle else ""), fontsize=8)
        ax.set_xlabel(level, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    h, lab = axes[0].get_legend_handles_labels()
    if lab:
        fig.legend(h, lab, loc="upper center", fontsize=7, ncols=min(3, len(lab)), bbox_to_anchor=(0.5, 1.0))
    return fig


def _constant(values: np.ndarray) -> bool:
    """Whether finite ``values`` are one value (to 1e-6 of it): a colour bar or an axis over them would draw
    rounding noise as a range."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return v.size == 0 or float(np.ptp(v)) <= 1e-6 * max(float(np.max(np.abs(v))), 1e-300)


@_plain_ticks
def pareto_figure(table: Any, flow: str) -> Figure:
    """Total RMS error [mm] against in-plane vector spacing [mm], colour: depth spacing [mm] (no colour bar
    where it is one value on every design: the title says it); the Pareto designs ringed, the recommended one
    starred. Every design is numbered beside its point (never on it) and named in the key below the axes."""
    sub = table[table["flow"] == flow] if "flow" in table else table
    sub = sub.sort_values("rms_total_mm", kind="stable")
    names = [str(d) for d in sub["design"]] if "design" in sub else [""] * len(sub)
    key_h = 0.19 * len(names) + 0.2
    h = 3.9 + key_h
    c = sub["spacing_mm_z"].to_numpy(float) if "spacing_mm_z" in sub else np.zeros(len(sub))
    const = _constant(c)
    fig = _fig(7.2, h, left=0.11, right=0.97 if const else 0.86, bottom=(key_h + 0.55) / h, top=1 - 0.4 / h)
    ax = fig.subplots()
    x, y = sub["spacing_mm_x"].to_numpy(float), sub["rms_total_mm"].to_numpy(float)
    if "rms_total_mm_sd" in sub:  # replicates: the mean over the seeds, bars their sd
        ax.errorbar(x, y, np.asarray(sub["rms_total_mm_sd"], float), fmt="none", ecolor="0.5", lw=0.8, zorder=2)
    if const:
        ax.scatter(x, y, color="C0", s=36, zorder=3)
    else:
        sc = ax.scatter(x, y, c=c, cmap="viridis", s=36, zorder=3)
        cb = fig.colorbar(sc, ax=ax)
        cb.set_label("vector spacing z [mm] (depth resolution)", fontsize=9)
    front = sub["pareto"].to_numpy(bool) if "pareto" in sub else np.zeros(len(sub), bool)
    ax.scatter(x[front], y[front], s=160, facecolors="none", edgecolors="C3", lw=1.5, zorder=4, label="Pareto front")
    rec = sub["recommended"].to_numpy(bool) if "recommended" in sub else np.zeros(len(sub), bool)
    ax.scatter(x[rec], y[rec], marker="*", s=260, color="C3", zorder=5, label="recommended")
    # Numbers beside the points, pushed apart where points crowd: a name would run through its neighbours.
    span = np.ptp(y[np.isfinite(y)]) if np.isfinite(y).any() else 1.0
    last: dict[float, float] = {}
    for k, (xi, yi) in enumerate(zip(x, y), start=1):
        if not (np.isfinite(xi) and np.isfinite(yi)):
            continue
        col = round(float(xi), 6)
        dy = 0
        if col in last and abs(yi - last[col]) < 0.06 * (span or 1.0):
            dy = 9  # one label height above its neighbour's
        last[col] = yi
        ax.annotate(
            str(k), (xi, yi), textcoords="offset points", xytext=(9, -4 + dy), fontsize=9, fontweight="bold",
            bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.8},
        )  # fmt: skip
    key = "\n".join(f"{k}  {n}" for k, n in enumerate(names, start=1))
    fig.text(0.02, (key_h + 0.05) / h, key, fontsize=8.5, va="top", ha="left", family="sans-serif")
    ax.set_xlabel("vector spacing x [mm] (in-plane resolution)", fontsize=9)
    ax.set_ylabel(
        "total RMS error [mm]" + (" (mean ± sd over the seeds)" if "rms_total_mm_sd" in sub else ""), fontsize=9
    )
    ax.tick_params(labelsize=8)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    title = f"{flow}: error against resolution (lower left is better)"
    if const and np.isfinite(c).any():
        title += f"\nvector spacing z {c[np.isfinite(c)][0]:.3g} mm on every design"
    ax.set_title(title, fontsize=9.5)
    return fig


@_plain_ticks
def vector_error_slice(piv: xr.Dataset, err: xr.Dataset | None) -> Figure:
    """Middle x–y slice: the measured vectors beside the error magnitude |measured − true| [mm]."""
    fig = _fig(10.5, 4.2, left=0.07, right=0.95, top=0.88, bottom=0.14, wspace=0.3)
    ax1, ax2 = fig.subplots(1, 2)
    valid = piv["valid"] if "valid" in piv else xr.ones_like(piv["u"], dtype=bool)
    get = lambda c: piv[f"{c}_mm"] if f"{c}_mm" in piv else piv[c]  # noqa: E731
    sl = {"z": piv.sizes["z"] // 2} if "z" in piv.dims else {}
    u = get("u").where(valid).isel(sl).transpose("y", "x").values
    v = get("v").where(valid).isel(sl).transpose("y", "x").values
    x, y = piv["x"].values, piv["y"].values
    _quiver(ax1, x, y, u, v, angles="xy")
    where = f" at z = {float(piv['z'][sl['z']]):+.2f} mm" if sl else ""
    ax1.set_title(f"measured u, v{where}", fontsize=9)
    ax1.set_xlabel("x [mm]")
    ax1.set_ylabel("y [mm]")
    ax1.set_aspect("equal")
    if err is not None and "u_err_mm" in err:
        comps = [c for c in ("u", "v", "w") if f"{c}_err_mm" in err]
        mag = np.sqrt(sum(err[f"{c}_err_mm"] ** 2 for c in comps)).isel(sl).transpose("y", "x")
        ok = valid.isel(sl).transpose("y", "x").values.astype(bool) & np.isfinite(mag.values)
        # An invalid vector has no error to show: grey and hatched, never a colour of the scale (a blank cell
        # on a light colour map read as the largest error).
        im = ax2.pcolormesh(x, y, np.where(ok, mag.values, np.nan), shading="nearest", cmap="viridis")
        if not ok.all():
            from matplotlib.patches import Patch

            ax2.pcolor(
                x, y, np.ma.masked_where(ok, np.ones(ok.shape)), shading="nearest", cmap="Greys", vmin=0, vmax=4,
                hatch="///", edgecolor="0.45", lw=0,
            )  # fmt: skip
            hatch = Patch(facecolor="0.85", edgecolor="0.45", hatch="///", label=f"invalid vector ({int((~ok).sum())})")
            # above the map, beside the title: inside it the key covered cells
            ax2.legend(handles=[hatch], fontsize=7, loc="lower right", bbox_to_anchor=(1.0, 1.0), frameon=False)
        cb = fig.colorbar(im, ax=ax2)
        cb.set_label("|error| [mm], valid vectors", fontsize=8)
        ax2.set_title(f"|error|{where}", fontsize=9, loc="left")
        ax2.set_xlabel("x [mm]")
        ax2.set_aspect("equal")
    else:
        ax2.set_axis_off()
        ax2.text(0.5, 0.5, "no error field (no truth)", ha="center", transform=ax2.transAxes)
    return fig


# ------------------------------------------------------------------ uncertainty
def _sigma_of(piv: xr.Dataset, c: str) -> tuple[xr.DataArray | None, str]:
    """The standard uncertainty of component ``c`` (mm if stored, else voxels) and its unit."""
    if f"unc_{c}_mm" in piv:
        return piv[f"unc_{c}_mm"], "mm"
    if f"unc_{c}" in piv:
        return piv[f"unc_{c}"], "voxel"
    return None, ""


def uncertainty_maps(piv: xr.Dataset) -> Figure:
    """Maps of the per-vector standard uncertainty σ of u, v, w on the middle x–y slice, one colour
    scale per component (over the whole field, so the slice reads against every depth); blank: no σ
    (invalid or replaced vector). Vectors the PIV flags ``unresolved`` (the final window's filtering
    of the flow likely exceeds σ, :mod:`lfstudy.piv.resolution`) carry a red cross, those of windows
    partly outside the seeded region (``partial``) a grey dot. A measurement without a known flow sees
    where it can trust its vectors.

    Raises
    ------
    ValueError
        The result holds no ``unc_*`` variable (``piv.uncertainty: none`` or an older store).
    """
    comps = [(ax, c) for ax, c in _COMP.items() if _sigma_of(piv, c)[0] is not None]
    if not comps:
        raise ValueError("the PIV result holds no per-vector uncertainty (unc_u, unc_v, unc_w)")
    fig = _fig(4.2 * len(comps), 3.6, left=0.07, right=0.96, top=0.84, bottom=0.14, wspace=0.35)
    axes = fig.subplots(1, len(comps), squeeze=False)[0]
    sel = {"z": piv.sizes["z"] // 2} if "z" in piv.dims else {}
    where = "".join(f" at {d} = {float(piv[d][i]):+.2f} mm" for d, i in sel.items())
    flagged = partial = None
    if "unresolved" in piv:
        flagged = np.asarray(piv["unresolved"].isel(sel).transpose("y", "x").values, bool)
    if "partial" in piv:
        partial = np.asarray(piv["partial"].isel(sel).transpose("y", "x").values, bool)
    for a, (axn, c) in zip(axes, comps):
        sigma, unit = _sigma_of(piv, c)
        assert sigma is not None
        finite = np.asarray(sigma.values, float)
        finite = finite[np.isfinite(finite)]
        lim = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        sl = sigma.isel(sel).transpose("y", "x")
        im = a.pcolormesh(
            piv["x"].values, piv["y"].values, sl.values, shading="nearest", cmap="viridis", vmin=lim[0], vmax=lim[1]
        )
        fig.colorbar(im, ax=a).set_label(f"σ_{c} [{unit}]", fontsize=8)
        if flagged is not None and flagged.any():  # the truth-free flag: the window's filtering may exceed σ
            yy, xx = np.nonzero(flagged)
            a.scatter(piv["x"].values[xx], piv["y"].values[yy], marker="x", s=14, c="red", linewidths=0.8)
        if partial is not None and partial.any():  # the window reaches past the seeded region
            yy, xx = np.nonzero(partial)
            a.scatter(piv["x"].values[xx], piv["y"].values[yy], marker=".", s=10, c="0.5")
        a.set_title(f"σ of {c} ({axn})", fontsize=9)
        a.set_xlabel("x [mm]")
        a.set_aspect("equal")
    axes[0].set_ylabel("y [mm]")
    flags = f"; red x: unresolved, {int(flagged.sum())} of {flagged.size} vectors" if flagged is not None else ""
    if partial is not None and partial.any():
        flags += f"; grey dot: partial window, {int(partial.sum())} of {partial.size}"
    fig.suptitle(f"Per-vector standard uncertainty{where} (blank: invalid or replaced vector{flags})")
    return fig


def uncertainty_histograms(piv: xr.Dataset, *, bins: int = 40) -> Figure:
    """Histograms of the per-vector standard uncertainty σ of u, v, w over the valid vectors, with
    the median (dashed) and the 10th–90th percentiles in the legend box.

    Raises
    ------
    ValueError
        The result holds no ``unc_*`` variable.
    """
    comps = [(ax, c) for ax, c in _COMP.items() if _sigma_of(piv, c)[0] is not None]
    if not comps:
        raise ValueError("the PIV result holds no per-vector uncertainty (unc_u, unc_v, unc_w)")
    fig = _fig(4.0 * len(comps), 3.3, left=0.07, top=0.84, bottom=0.16)
    axes = fig.subplots(1, len(comps), squeeze=False)[0]
    valid = piv["valid"].values.astype(bool) if "valid" in piv else None
    for a, (axn, c) in zip(axes, comps):
        sigma, unit = _sigma_of(piv, c)
        assert sigma is not None
        s = np.asarray(sigma.values, float)
        s = s[valid & np.isfinite(s)] if valid is not None else s[np.isfinite(s)]
        if s.size:
            a.hist(s, bins=int(min(bins, max(10, 2 * math.sqrt(s.size)))), color="C2", alpha=0.8)
            med = float(np.median(s))
            a.axvline(med, color="k", ls="--", lw=1)
            p10, p90 = np.percentile(s, [10, 90])
            a.text(
                0.97,
                0.95,
                f"median {med:.3g} {unit}\n10–90 %: {p10:.3g}–{p90:.3g}\nn = {s.size}",
                transform=a.transAxes,
                ha="right",
                va="top",
                fontsize=8,
                bbox={"fc": "white", "alpha": 0.8, "lw": 0},
            )
        else:
            a.text(0.5, 0.5, "no valid vector with σ", ha="center", transform=a.transAxes)
        a.set_xlabel(f"σ of {c} ({axn}) [{unit}]")
    axes[0].set_ylabel("count")
    fig.suptitle("Per-vector standard uncertainty, valid vectors")
    return fig


def error_vs_uncertainty(curves: Mapping[str, Mapping[str, Mapping[str, np.ndarray]]], *, unit: str = "mm") -> Figure:
    """RMS error against the predicted standard uncertainty σ, binned, per component: x and y
    beside each other, z on a panel of its own (its σ is several times larger); the 1:1 line is
    where σ is right (above it σ is too small, below too large).

    Parameters
    ----------
    curves : mapping label -> axis (``x``, ``y``, ``z``) -> bins
        Per line (a design, pooled over its cases): per axis the bins of
        :func:`lfstudy.study.metrics.binned_uncertainty` (``sigma_rms``, ``error_rms``,
        ``coverage``, ``count``).
    unit : str
        Of σ and the error.

    Raises
    ------
    ValueError
        No curve holds a bin.
    """
    axes_names = [ax for ax in ("x", "y", "z") if any(len(c.get(ax, {}).get("count", ())) for c in curves.values())]
    if not axes_names:
        raise ValueError("no vector with both an error and an uncertainty")
    from matplotlib.ticker import LogLocator, NullFormatter, StrMethodFormatter

    # The legend goes below the panels, in columns: beside them (or on the z panel) 8 designs covered the curves.
    n_lines = len(curves) + 1
    ncols = 2 if len(axes_names) < 3 else 3
    leg_h = 0.2 * math.ceil(n_lines / ncols) + 0.3
    h = 3.6 + leg_h
    fig = _fig(
        4.3 * len(axes_names) + 0.6, h, left=0.07, right=0.98, top=1 - 0.5 / h, bottom=(leg_h + 0.55) / h, wspace=0.3
    )
    axes = fig.subplots(1, len(axes_names), squeeze=False)[0]
    for a, axn in zip(axes, axes_names):
        lo, hi = np.inf, 0.0
        for k, (label, per_axis) in enumerate(curves.items()):
            b = per_axis.get(axn)
            if b is None or not len(b["count"]):
                continue
            s, e = np.asarray(b["sigma_rms"]), np.asarray(b["error_rms"])
            pos = (s > 0) & (e > 0)
            a.plot(s[pos], e[pos], "o-", ms=3.5, lw=1.2, color=f"C{k % 10}", label=label)
            if pos.any():
                lo = min(lo, float(s[pos].min()), float(e[pos].min()))
                hi = max(hi, float(s[pos].max()), float(e[pos].max()))
        if np.isfinite(lo) and hi > 0:
            line = np.array([lo / 1.5, hi * 1.5])
            a.plot(line, line, "k--", lw=1, label="1:1")
            a.set_xscale("log")
            a.set_yscale("log")
            # Labels on 1, 2, 5 of each decade only, in plain numbers; unlabelled minor ticks: matplotlib labels
            # every minor tick of a span under a decade, and they ran into one unreadable strip.
            for axis in (a.xaxis, a.yaxis):
                axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0), numticks=6))
                axis.set_major_formatter(StrMethodFormatter("{x:.2g}"))
                axis.set_minor_formatter(NullFormatter())
            a.tick_params(labelsize=8)
        a.set_xlabel(f"predicted σ of {_COMP[axn]} ({axn}), RMS in bin [{unit}]")
        a.set_title(f"{axn}" + (" (depth)" if axn == "z" else ""), fontsize=9)
        a.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"RMS error in bin [{unit}]")
    handles, labels = axes[-1].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower left", bbox_to_anchor=(0.02, 0.01), ncols=ncols, fontsize=8, frameon=False)
    fig.suptitle("Error against the predicted uncertainty (binned by σ; on the 1:1 line where σ is right)")
    return fig
