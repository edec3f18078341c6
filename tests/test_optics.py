from __future__ import annotations

import math

import numpy as np
import pytest

from lfstudy.optics import OpticsError, PlenopticCamera, round_up_f_stop

# Table 5.1 (t column) of the thesis, planes 1..17.
TABLE_51_T = [
    -7.6884,
    -6.7607,
    -5.8236,
    -4.8771,
    -3.9211,
    -2.9555,
    -1.9801,
    -0.9950,
    0.0,
    1.0050,
    2.0202,
    3.0455,
    4.0811,
    5.1272,
    6.1837,
    7.2509,
    8.3288,
]
TABLE_51_NEAR = [
    91.8523,
    92.7755,
    93.7079,
    94.6497,
    95.6009,
    96.5617,
    97.5322,
    98.5124,
    99.5025,
    100.5025,
    101.5126,
    102.5328,
    103.5633,
    104.6041,
    105.6554,
    106.7173,
    107.7898,
]


def test_table41_depth_of_field(table41_camera):
    """Sec. 4.2.2: DN,o = 2.57 mm, DF,o = 3.60 mm, xi_z = 1.03 mm, xi_y = 62.5 um."""
    d = table41_camera.depth_of_field(0.0)
    assert round(float(d["near"][0]), 2) == 2.57
    assert round(float(d["far"][0]), 2) == 3.60
    assert round(float(d["depth_ambiguity"][0]), 2) == 1.03
    assert round(float(d["inplane_ambiguity"][0]) * 1e3, 1) == 62.5
    assert table41_camera.n_lenslets_y == 5  # Table 4.1


def test_table42_diffraction(table43_camera):
    """Table 4.2: 5.2 um spots and sigma 0.96 um at both planes, 4.2 % of pitch, 70.5 % of pixel."""
    c = table43_camera
    assert round(c.spot_lenslet_plane * 1e3, 1) == 5.2
    assert round(c.spot_sensor_plane * 1e3, 1) == 5.2
    assert round(c.sigma_lenslet_plane * 1e3, 2) == 0.96
    assert round(c.sigma_sensor_plane * 1e3, 2) == 0.96
    assert round(100 * c.spot_lenslet_plane / c.lenslet_pitch, 1) == 4.2
    assert round(100 * c.spot_sensor_plane / c.pixel_pitch, 1) == 70.5


def test_table43_layout(table43_camera):
    c = table43_camera
    assert (c.n_lenslets_x, c.n_lenslets_y) == (289, 193)
    assert round(c.sensor_width, 2) == 36.05 and round(c.sensor_height, 2) == 24.04
    assert c.si == pytest.approx(100.0) and c.so == pytest.approx(100.0)
    assert c.main_fnumber == 2.0 and c.lenslet_image_status == "matched"
    cx, cy = c.lenslet_centers()
    assert cx.shape == (193, 289)
    # Centred grid: symmetric about the optical axis, row 0 at the top (y > 0).
    assert cx[0, 0] == pytest.approx(-cx[0, -1]) and cy[0, 0] > 0 > cy[-1, 0]
    assert np.allclose(np.diff(cx[0]), 0.125)
    # Eq. 4.11: the first lenslet starts at the offset o (array slightly larger than the sensor).
    ox, _ = c.lenslet_offset
    assert cx[0, 0] - 0.0625 == pytest.approx(ox - c.sensor_width / 2)
    # Eq. 4.28: about 19 degrees.
    assert 18.5 < math.degrees(c.max_incidence_angle) < 20.0


def test_table51_planes(table43_camera):
    fp = table43_camera.focal_planes()
    assert fp.sizes["plane"] == 17
    np.testing.assert_array_equal(np.round(fp["t"].values, 4), TABLE_51_T)
    np.testing.assert_array_equal(np.round(fp["near"].values, 4), TABLE_51_NEAR)
    # Neighbouring diamonds share a bound (marching), z sign: t < 0 is farther from the camera.
    np.testing.assert_allclose(fp["far"].values[:-1], fp["near"].values[1:])
    assert fp["z"].sel(plane=3) > 0 > fp["z"].sel(plane=15)
    assert fp["t"].attrs["units"] == "mm"


def test_focal_plane_options(table43_camera):
    base = table43_camera.focal_planes()
    wide = table43_camera.focal_planes(32, depth_scale=1.5)
    assert wide.sizes["plane"] == 32
    span = lambda d: float(d["far"].max() - d["near"].min())  # noqa: E731
    assert span(wide) == pytest.approx(1.5 * span(base), rel=0.02)
    cubic = table43_camera.focal_planes(cubic=True)
    dz = np.abs(np.diff(cubic["z"].values)).mean()
    assert dz == pytest.approx(0.125, rel=0.05)  # cubic voxels: pl / |M|


def test_f_stop_rounding_and_fill():
    assert round_up_f_stop(3.2) == 4.0 and round_up_f_stop(2.0) == 2.0
    cam = PlenopticCamera(200, 200, 0.0074, 0.125, 0.5, 50.0, -0.6)  # exact 2.5 -> f/2.8
    assert cam.matched_fnumber == pytest.approx(2.5) and cam.main_fnumber == 2.8
    assert cam.lenslet_image_status == "underfill"
    over = cam.with_(fnumber=1.4)
    assert over.lenslet_image_status == "overlap" and over.lenslet_image_fill > 1.7


@pytest.mark.parametrize(
    "change, match",
    [
        ({"magnification": 0.5}, "magnification"),
        ({"lenslet_pitch": -0.1}, "lenslet_pitch"),
        ({"fnumber": 0.7}, "cannot reach"),
        ({"fnumber": 45.0}, "cannot reach"),
        ({"pixel_pitch": float("nan")}, "pixel_pitch"),
        ({"n_pixels_x": 0}, "n_pixels_x"),
        ({"lenslet_rotation": 1.0}, "lenslet_rotation"),
    ],
)
def test_bad_camera(change, match):
    kw = {
        "n_pixels_x": 100,
        "n_pixels_y": 100,
        "pixel_pitch": 0.0074,
        "lenslet_pitch": 0.125,
        "lenslet_focal_length": 0.5,
        "main_focal_length": 50.0,
        "magnification": -1.0,
    }
    kw.update(change)
    with pytest.raises(OpticsError, match=match):
        PlenopticCamera(**kw)


def _covered(cx: np.ndarray, cy: np.ndarray, x: float, y: float, pitch: float, rotation: float) -> bool:
    """Whether the point (x, y) lies in the square cell (side ``pitch``, rotated) of one of the centres."""
    c, s = math.cos(rotation), math.sin(rotation)
    dx, dy = x - cx, y - cy
    return bool(np.any((np.abs(c * dx + s * dy) <= pitch / 2) & (np.abs(-s * dx + c * dy) <= pitch / 2)))


def test_rotated_grid_covers_sensor():
    """Every pixel, up to the sensor's corners, lies in the cell of one of the lenslet centres."""
    cam = PlenopticCamera(300, 200, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_rotation=0.02, lenslet_offset_x=0.03)
    cx, cy = cam.lenslet_centers()
    assert cx.shape == cy.shape == (cam.n_lenslets_y, cam.n_lenslets_x)
    # the centres form the rotated grid: neighbours one pitch apart along the rotated axes
    assert np.allclose(np.diff(cx, axis=1), 0.125 * math.cos(0.02))
    assert np.allclose(np.diff(cy, axis=1), 0.125 * math.sin(0.02))
    half_w, half_h = cam.sensor_width / 2, cam.sensor_height / 2
    corners = [(x, y) for x in (-half_w, half_w) for y in (-half_h, half_h)]
    edges = [(x, y) for x in np.linspace(-half_w, half_w, 41) for y in (-half_h, half_h)]
    edges += [(x, y) for y in np.linspace(-half_h, half_h, 41) for x in (-half_w, half_w)]
    uncovered = [(x, y) for x, y in corners + edges if not _covered(cx, cy, x, y, 0.125, 0.02)]
    assert not uncovered, f"sensor points outside every lenslet cell: {uncovered[:4]}"
    # the check catches a grid one column short
    assert not all(_covered(cx[:, :-1], cy[:, :-1], x, y, 0.125, 0.02) for x, y in corners)


def test_lenslet_counts_on_a_square_sensor_follow_each_axis():
    """A y offset changes the rows, not the columns, even when the sensor is square (width == height)."""
    cam = PlenopticCamera(200, 200, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_y=0.1)
    assert (cam.n_lenslets_x, cam.n_lenslets_y) == (12, 14)
    cam = PlenopticCamera(200, 200, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.1)
    assert (cam.n_lenslets_x, cam.n_lenslets_y) == (14, 12)
