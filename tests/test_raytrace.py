"""The 2-D ray tracer (thesis sec. 4.1–4.3): geometry, accounting, determinism, diffraction, input checks."""

from __future__ import annotations

import math
from pathlib import Path

import numba
import numpy as np
import pytest

from lfstudy.optics import PlenopticCamera
from lfstudy.simulate import raytrace as rt
from lfstudy.simulate.particles import make_field, seed_particles

#: Table 4.3 optics on a small sensor with an odd lenslet count (9 x 7), so a
#: lenslet sits on the optical axis as in Fig. 4.17.
CAM = PlenopticCamera(150, 110, 0.0074, 0.125, 0.5, 50.0, -1.0)


def _field(*pts, intensity=1.0):
    p = np.atleast_2d(np.asarray(pts, dtype=float))
    return make_field(p[:, 0], p[:, 1], p[:, 2], np.full(len(p), intensity))


def _lenslet_block(cam, img, i, j, margin=0.0):
    """Pixel mask of lenslet (row i, col j)'s image: pixel centres within pl/2 (+ margin) of its projected centre."""
    cx, cy = cam.lenslet_centers()
    scale = (cam.si + cam.lenslet_focal_length) / cam.si  # centre of the lenslet's aperture image
    x, y = img["x"].values, img["y"].values
    half = cam.lenslet_pitch / 2 + margin
    return (np.abs(y[:, None] - cy[i, j] * scale) <= half) & (np.abs(x[None, :] - cx[i, j] * scale) <= half)


def _centroid(img):
    w = img.values
    return float((w.sum(0) * img["x"].values).sum() / w.sum()), float((w.sum(1) * img["y"].values).sum() / w.sum())


def test_in_focus_on_axis_lights_one_lenslet():
    """Fig. 4.17: all signal of an in-focus on-axis particle lies under the central lenslet."""
    assert CAM.n_lenslets_x % 2 == 1 and CAM.n_lenslets_y % 2 == 1
    img = rt.render(CAM, _field((0.0, 0.0, 0.0)), 20_000, 1, method="montecarlo")
    mask = _lenslet_block(CAM, img, CAM.n_lenslets_y // 2, CAM.n_lenslets_x // 2, margin=CAM.pixel_pitch)
    total = img.values.sum()
    assert total > 0
    assert img.values[mask].sum() / total > 0.999
    # Matched f-number: the aperture image nearly fills the lenslet block (~17 px across).
    rows, cols = np.nonzero(img.values)
    assert 12 <= cols.max() - cols.min() + 1 <= 18 and 12 <= rows.max() - rows.min() + 1 <= 18


def test_defocus_spreads_over_lenslets_and_sign_matters():
    """Fig. 4.18: at dz = ±1 mm the image covers several lenslets, with different patterns."""
    a = rt.render(CAM, _field((0.0, 0.0, 1.0)), 20_000, 2, diffraction=False, method="montecarlo").values
    b = rt.render(CAM, _field((0.0, 0.0, -1.0)), 20_000, 2, diffraction=False, method="montecarlo").values
    centre = _lenslet_block(CAM, rt.render(CAM, _field((0, 0, 0)), 10, 0, method="montecarlo"), 3, 4)
    for img in (a, b):
        assert img[centre].sum() / img.sum() < 0.6
    an, bn = a / a.sum(), b / b.sum()
    corr = (an * bn).sum() / math.sqrt((an * an).sum() * (bn * bn).sum())
    assert corr < 0.6


def test_recorded_signal_equals_traced_less_lost():
    field = seed_particles(CAM, count=30, z_span=4.0, intensity=(0.5, 2.0), seed=4)
    img = rt.render(CAM, field, 3000, 5, method="montecarlo")
    a = img.attrs
    assert a["rays_traced"] == a["rays_recorded"] + a["rays_dropped_outside_sensor"] + a["rays_dropped_lenslet_array"]
    assert "rays_dropped_aperture" not in a  # aperture sampling is rejection-free: nothing to count
    assert a["rays_dropped_outside_sensor"] > 0  # field edge particles spill off the sensor
    assert img.values.sum() == pytest.approx(a["intensity_traced"] - a["intensity_lost"], rel=1e-6)
    # Eq. 4.14 generalised: every particle traces about n rays, more when closer.
    counts = rt.ray_counts(CAM, field, 3000)
    assert a["rays_traced"] == counts.sum()
    order = np.argsort(field["z"].values)
    assert counts[order[0]] > counts[order[-1]] and np.all(np.abs(counts - 3000) < 300)


def test_solid_angle_reference_and_off_axis():
    r = CAM.aperture_diameter / 2
    ref = 2 * math.pi * (1 - CAM.so / math.hypot(CAM.so, r))
    assert rt.solid_angle(CAM, 0.0, 0.0, 0.0)[0] == pytest.approx(ref, rel=1e-10)
    off = rt.solid_angle(CAM, 10.0, 0.0, 0.0)[0]
    assert off == pytest.approx(ref * (CAM.so / math.hypot(CAM.so, 10.0)) ** 3, rel=2e-3)  # cos^3 law


@pytest.mark.parametrize("axis", ["x", "y"])
def test_centroid_moves_inverted(axis):
    """A defocused particle's image moves opposite to it (M < 0), by about si/(so + z)."""
    z, shift = 1.0, 0.2
    p0 = _centroid(rt.render(CAM, _field((0.0, 0.0, z)), 20_000, 3, method="montecarlo"))
    pt = (shift, 0.0, z) if axis == "x" else (0.0, shift, z)
    p1 = _centroid(rt.render(CAM, _field(pt), 20_000, 3, method="montecarlo"))
    k = 0 if axis == "x" else 1
    expected = -shift * CAM.si / (CAM.so + z) * (CAM.si + CAM.lenslet_focal_length) / CAM.si
    assert (p1[k] - p0[k]) == pytest.approx(expected, rel=0.05)
    assert abs(p1[1 - k] - p0[1 - k]) < 0.01


def test_bit_identical_across_threads_and_seeds_differ():
    field = seed_particles(CAM, count=40, z_span=3.0, seed=9)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = rt.render(CAM, field, 2000, 11, method="montecarlo").values
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = rt.render(CAM, field, 2000, 11, method="montecarlo").values
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(one, two)
    other = rt.render(CAM, field, 2000, 12, method="montecarlo").values
    assert not np.array_equal(one, other)
    assert other.sum() == pytest.approx(one.sum(), rel=0.02)


def test_progress_bar_reports_rays_and_leaves_image_unchanged(capsys):
    field = seed_particles(CAM, count=40, z_span=3.0, seed=9)
    quiet = rt.render(CAM, field, 2000, 11, method="montecarlo")
    capsys.readouterr()
    shown = rt.render(CAM, field, 2000, 11, progress=True, method="montecarlo")
    err = capsys.readouterr().err
    assert "ray tracing" in err and "100%" in err
    assert np.array_equal(quiet.values, shown.values)
    assert quiet.attrs["intensity_lost"] == shown.attrs["intensity_lost"]


def test_diffraction_sigmas_at_the_right_planes():
    """Main lens at f/16, lenslets at f/2: sigma at the lenslet plane 7.7 um, at the sensor 0.48 um.

    An in-focus point imaged 10 um inside a lenslet edge: the lenslet-plane blur
    sends ~10 % of its rays through the neighbouring lenslet (a spot one
    lenslet image away), while the sensor-plane blur barely widens the tiny
    aperture image (~1 px). With the sigmas swapped neither would hold.
    """
    cam = PlenopticCamera(150, 110, 0.0074, 0.125, 0.25, 50.0, -1.0, fnumber=16.0)
    assert cam.sigma_lenslet_plane > 10 * cam.sigma_sensor_plane
    y_img = -(cam.lenslet_pitch / 2 - 0.010)  # 10 um inside the lower edge of the central lenslet
    img = rt.render(cam, _field((0.0, -y_img, 0.0)), 40_000, 6, method="montecarlo")
    w = img.values
    own = _lenslet_block(cam, img, 3, 4)
    below = _lenslet_block(cam, img, 4, 4)
    crossed = w[below].sum() / w.sum()
    assert 0.05 < crossed < 0.2  # P(N(0,1) > 10/7.7) = 0.097
    # Spread of the spot within the own lenslet image (pixels): tight.
    ws = np.where(own, w, 0.0)
    x, _y = img["x"].values, img["y"].values
    mx = (ws.sum(0) * x).sum() / ws.sum()
    sx = math.sqrt((ws.sum(0) * (x - mx) ** 2).sum() / ws.sum())
    assert sx / cam.pixel_pitch < 0.6
    no_diff = rt.render(cam, _field((0.0, -y_img, 0.0)), 40_000, 6, diffraction=False, method="montecarlo").values
    assert no_diff[below].sum() == 0


def test_pinhole_image_spots_at_lenslet_images():
    img = rt.render_pinhole(CAM, count=4000, rays_per_point=50, seed=1, method="montecarlo")
    assert img.attrs["camera_main_fnumber"] == 16.0 and img.attrs["pinhole_fnumber"] == 16.0
    w = img.values
    # Each lenslet images the (small, f/16) aperture at c (si + fl) / si: central spot's centroid there.
    mask = _lenslet_block(CAM, img, 3, 4)
    ws = np.where(mask, w, 0)
    cx = (ws.sum(0) * img["x"].values).sum() / ws.sum()
    cy = (ws.sum(1) * img["y"].values).sum() / ws.sum()
    assert abs(cx) < 0.2 * CAM.pixel_pitch and abs(cy) < 0.2 * CAM.pixel_pitch
    # A spot, not a filled disc: most pixels of the lenslet block are dark.
    assert (ws > 0.01 * ws.max()).sum() < 0.15 * mask.sum()


def test_output_layout_and_attrs():
    img = rt.render(CAM, _field((0.1, 0.0, 0.5)), 500, 0, method="montecarlo")
    assert img.name == "intensity" and img.dims == ("row", "col")
    assert img.shape == (CAM.n_pixels_y, CAM.n_pixels_x)
    x, y = CAM.pixel_centers()
    np.testing.assert_array_equal(img["x"].values, x)
    np.testing.assert_array_equal(img["y"].values, y)
    assert img["y"].values[0] > img["y"].values[-1]
    assert img["x"].attrs["units"] == "mm" and img.attrs["y_direction"] == "up; row 0 is the top"
    for k in (
        "seed",
        "rays_per_particle",
        "rays_traced",
        "rays_recorded",
        "rays_dropped_lenslet_array",
        "rays_dropped_outside_sensor",
        "camera_lenslet_pitch",
        "camera_main_fnumber",
    ):
        assert k in img.attrs


def test_noise_and_bit_depth():
    field = _field((0.0, 0.0, 0.0), intensity=2.0)
    clean = rt.render(CAM, field, 5000, 3, method="montecarlo")
    noisy = rt.render(CAM, field, 5000, 3, shot_noise=True, read_noise=1.0, method="montecarlo")
    assert not np.array_equal(clean.values, noisy.values)
    assert np.array_equal(
        noisy.values, rt.render(CAM, field, 5000, 3, shot_noise=True, read_noise=1.0, method="montecarlo").values
    )
    q = rt.render(CAM, field, 5000, 3, bit_depth=8, full_well=float(clean.max()) / 2, method="montecarlo")
    assert q.dtype == np.uint8 and q.max() == 255
    assert q.attrs["saturated_pixels"] == int((clean.values * 255 / (float(clean.max()) / 2) > 255.5).sum()) > 0
    q12 = rt.render(CAM, field, 5000, 3, bit_depth=12, method="montecarlo")
    assert q12.dtype == np.uint16 and q12.max() == 4095 and q12.attrs["saturated_pixels"] == 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"rays_per_particle": 0}, "rays_per_particle"),
        ({"rays_per_particle": 2.5}, "rays_per_particle"),
        ({"particles": _field((0.0, 0.0, 0.0)).isel(particle=slice(0, 0))}, "empty"),
        ({"particles": _field((0.0, 0.0, -60.0))}, r"particles\.z"),
        ({"particles": _field((0.0, 0.0, -100.0))}, r"particles\.z"),
        ({"particles": _field((0.0, 0.0, -50.0))}, r"particles\.z"),  # exactly at the focal length
        ({"particles": _field((0.0, 0.0, 0.0)).assign(x=("particle", [np.nan]))}, r"particles\.x"),
        ({"particles": _field((0.0, 0.0, 0.0)).assign(intensity=("particle", [-1.0]))}, r"particles\.intensity"),
        ({"max_image_bytes": 1000}, "max_image_bytes"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_input(kwargs, match):
    args = {
        "camera": CAM,
        "particles": _field((0.0, 0.0, 0.0)),
        "rays_per_particle": 10,
        "seed": 0,
        "method": "montecarlo",
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        rt.render(**args)


def test_angle_histograms_table43():
    """Sec. 4.3.4: a sizeable fraction of rays exceeds 10 deg; none exceeds the geometric bound.

    Eq. 4.28 leaves out the aperture radius, so it is exceeded by a small
    fraction of rays (recorded in the attrs, < 2 %).
    """
    cam = PlenopticCamera(4872, 3248, 0.0074, 0.125, 0.5, 50.0, -1.0)
    field = seed_particles(cam, count=100, z_span=7.0, seed=2)
    h = rt.angle_histograms(cam, field, 1000, 1)
    a = h.attrs
    tol = 5 * cam.sigma_lenslet_plane / cam.lenslet_focal_length  # diffraction shifts the exit slope
    assert max(a["max_abs_theta"], a["max_abs_phi"]) <= a["incidence_angle_bound"] + tol
    assert a["max_incidence_angle_eq428"] == pytest.approx(math.radians(19.39), abs=1e-3)  # "approximately 19 degrees"
    assert a["fraction_theta_over_10deg"] > 0.1 and a["fraction_phi_over_10deg"] > 0.05
    assert a["fraction_theta_over_eq428"] < 0.02 and a["fraction_phi_over_eq428"] < 0.02
    assert int(h["theta_count"].sum()) <= a["rays_recorded"] and h["theta_count"].sum() > 0.95 * a["rays_recorded"]


def test_cli_simulate_writes_files(tmp_path):
    import yaml

    from lfstudy import io
    from lfstudy.cli import main

    cfg = yaml.safe_load((Path(__file__).parents[1] / "config" / "demo.yaml").read_text())
    cfg["camera"]["sensor"].update(n_pixels_x=160, n_pixels_y=120)
    cfg["particles"]["ppp"] = 0.002
    cfg["raytrace"]["rays_per_particle"] = 200
    cfg["pinhole"].update(count=2000, rays_per_point=10)
    cfg["sweep"] = {"ppp": [0.002], "flow": ["uniform_x"]}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    assert main(["simulate", str(path), "--out", str(out)]) == 0
    for name in (
        "particles_a.zarr",
        "particles_b.zarr",
        "image_a.tif",
        "image_a.zarr",
        "image_b.tif",
        "image_b.zarr",
        "pinhole.tif",
        "pinhole.zarr",
    ):
        assert (out / name).exists(), name
    data, meta = io.read_tiff(out / "image_a.tif")
    assert data.shape == (120, 160) and data.dtype == np.float32
    assert meta["camera_n_pixels_x"] == 160 and meta["y_direction"] == "up; row 0 is the top"
    a = io.open_zarr(out / "particles_a.zarr").load()
    b = io.open_zarr(out / "particles_b.zarr").load()
    np.testing.assert_allclose(b["x"] - a["x"], 0.2)  # demo's uniform_x flow
    img_a = io.open_zarr(out / "image_a.zarr", name="intensity").load()
    img_b = io.open_zarr(out / "image_b.zarr", name="intensity").load()
    assert img_a.sum() > 0 and not np.array_equal(img_a.values, img_b.values)
    pin = io.open_zarr(out / "pinhole.zarr", name="intensity")
    assert pin.attrs["pinhole_fnumber"] == 16


def test_kernel_math_helpers_accuracy():
    """The branch-free log and sin/cos of the ray kernel match libm over their whole input range."""
    from numba import njit

    @njit
    def evaluate(u):
        out = np.empty((3, u.size))
        for i in range(u.size):
            out[0, i] = rt._log01(u[i])
            out[1, i], out[2, i] = rt._sincos_turn(u[i])
        return out

    # Every uniform the kernel can draw lies in [2^-33, 1): include both ends and every octave.
    u = np.concatenate(
        [(np.arange(2**16) + 0.5) * 2.0**-16, 1.37 * 2.0 ** -np.arange(1, 34), [2.0**-33, 1.0 - 2.0**-33]]
    )
    out = evaluate(u)
    assert np.abs(out[0] - np.log(u)).max() < 1e-12
    assert np.abs(out[1] - np.sin(2 * np.pi * u)).max() < 2e-9
    assert np.abs(out[2] - np.cos(2 * np.pi * u)).max() < 2e-9
