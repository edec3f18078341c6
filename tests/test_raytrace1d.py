"""The 1-D teaching simulator (sec. 4.2, Figs 4.2–4.9, 4.14) on the Table 4.1 camera."""

from __future__ import annotations

import numpy as np
import pytest

from lfstudy.simulate import raytrace1d as r1

CAM = r1.table41_camera()


def _central_block(tr, margin=0.0):
    y = tr["y"].values
    return np.abs(y) <= CAM.lenslet_pitch / 2 + margin  # central lenslet (5 lenslets, the middle on axis)


def _corr(a, b):
    a, b = a / a.sum(), b / b.sum()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_table41_layout():
    assert CAM.n_lenslets_y == 5 and CAM.si == pytest.approx(3.0) and CAM.main_fnumber == 2.0


def test_in_focus_on_axis_lights_central_lenslet_only():
    tr = r1.trace_1d(CAM, 0.0, 0.0)
    s = tr["signal"].values
    assert s.sum() == tr.attrs["n_rays"] and s[~_central_block(tr, CAM.pixel_pitch)].sum() == 0
    assert (tr["lenslet"].values == 2).all()


def test_depth_sign_gives_different_patterns():
    """Figs 4.2-4.3: dz = +1000 and -1000 um spread over lenslets with different patterns."""
    a = r1.trace_1d(CAM, 0.0, 1.0)["signal"].values
    b = r1.trace_1d(CAM, 0.0, -1.0)["signal"].values
    assert _corr(a, b) < 0.8
    for tr in (r1.trace_1d(CAM, 0.0, 1.0), r1.trace_1d(CAM, 0.0, -1.0)):
        assert len(np.unique(tr["lenslet"].values)) >= 2


def test_inplane_ambiguity_within_a_lenslet():
    """Figs 4.4-4.7: dy = -62, 0, +62 um give nearly the same signal; +63 um changes lenslet."""
    sig = {dy: r1.trace_1d(CAM, dy, 0.0, seed=1) for dy in (-0.062, 0.0, 0.062, 0.063)}
    base = sig[0.0]["signal"].values
    for dy in (-0.062, 0.062):
        s = sig[dy]["signal"].values
        assert (sig[dy]["lenslet"].values == 2).all()  # all through the central lenslet
        assert _corr(s, base) > 0.9
    moved = sig[0.063]
    assert (moved["lenslet"].values == 3).all()  # inverted image: object up -> lower lenslet (row 3)
    assert moved["signal"].values[_central_block(moved)].sum() == 0


def test_diffraction_spreads_edge_signal_to_neighbour():
    """Fig. 4.14: with diffraction, dy = +62 um leaks some rays into the adjoining lenslet."""
    tr = r1.trace_1d(CAM, 0.062, 0.0, diffraction=True, seed=2)
    frac = (tr["lenslet"].values == 3).mean()
    assert 0.1 < frac < 0.6  # 0.5 um from the edge, sigma 0.96 um: ~30 %


def test_plot_ray_diagram_returns_figure():
    fig = r1.plot_ray_diagram(CAM, 0.0, 1.0, n_rays=5000)
    assert len(fig.axes) == 4
    assert len(fig.axes[0].lines) >= 100
    fig.savefig(__import__("io").BytesIO(), format="png")


def test_bad_input():
    with pytest.raises(ValueError, match="n_rays"):
        r1.trace_1d(CAM, 0.0, 0.0, 0)
    with pytest.raises(ValueError, match="dz"):
        r1.trace_1d(CAM, 0.0, -2.0)
