"""Registration (eqs 5.2-5.9) and refocusing (eqs 5.10-5.15, sec. 6.2) on simulated particles.

``_simulate`` is a minimal forward model of the thesis' ray tracer (thin main
lens, uniform aperture, thin lenslets focused at infinity, no diffraction);
the end-to-end test with :mod:`lfstudy.simulate.raytrace` runs when that module exists.
"""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from lfstudy import io
from lfstudy.lightfield.calibrate import find_lenslet_centers, synthetic_pinhole
from lfstudy.lightfield.refocus import focal_stack
from lfstudy.lightfield.registration import RegistrationError, register
from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct import default_voxel_z
from lfstudy.study.case import render_volume
from lfstudy.study.config import validate_config

CAM = PlenopticCamera(420, 340, 0.0074, 0.125, 0.5, 50.0, -1.0)  # Table 4.3 optics, small sensor
HALF_VOXEL = CAM.lenslet_pitch / abs(CAM.magnification) / 2


def _simulate(cam: PlenopticCamera, points, n_rays: int = 100_000, seed: int = 0) -> np.ndarray:
    """Raw image of point particles (X, Y, Z) [mm, object frame]."""
    rng = np.random.default_rng(seed)
    f, so, si, fl, p = cam.main_focal_length, cam.so, cam.si, cam.lenslet_focal_length, cam.lenslet_pitch
    cxg, cyg = cam.lenslet_centers()
    nly, nlx = cxg.shape
    c, s = np.cos(cam.lenslet_rotation), np.sin(cam.lenslet_rotation)
    img = np.zeros(cam.n_pixels_y * cam.n_pixels_x)
    for X, Y, Z in points:
        do = so + Z
        di = 1 / (1 / f - 1 / do)
        mp = -di / do
        r = cam.aperture_diameter / 2 * np.sqrt(rng.random(n_rays))
        a = 2 * np.pi * rng.random(n_rays)
        u, v = r * np.cos(a), r * np.sin(a)
        sx, sy = (mp * X - u) / di, (mp * Y - v) / di  # ray slopes towards the image point
        dx, dy = u + si * sx - cam.lenslet_offset_x, v + si * sy - cam.lenslet_offset_y
        gx, gy = c * dx + s * dy, -s * dx + c * dy
        j = np.rint(gx / p + (nlx - 1) / 2).astype(int)
        i = np.rint((nly - 1) / 2 - gy / p).astype(int)
        ok = (j >= 0) & (j < nlx) & (i >= 0) & (i < nly)
        xs = cxg[i[ok], j[ok]] + fl * sx[ok]  # thin lenslet focused at infinity
        ys = cyg[i[ok], j[ok]] + fl * sy[ok]
        col = np.floor((xs + cam.sensor_width / 2) / cam.pixel_pitch).astype(int)
        row = np.floor((cam.sensor_height / 2 - ys) / cam.pixel_pitch).astype(int)
        ok = (col >= 0) & (col < cam.n_pixels_x) & (row >= 0) & (row < cam.n_pixels_y)
        img += np.bincount(row[ok] * cam.n_pixels_x + col[ok], minlength=img.size)
    return img.reshape(cam.n_pixels_y, cam.n_pixels_x)


@pytest.fixture(scope="module")
def centers() -> xr.Dataset:
    return find_lenslet_centers(synthetic_pinhole(CAM, amplitude=3000, seed=1), CAM)


def _measure(plane: xr.DataArray) -> tuple[float, float, float, float]:
    """Peak, effective diameter (participation ratio) and centroid near the peak."""
    w = plane.values.astype(float)
    iy, ix = np.unravel_index(np.argmax(w), w.shape)
    sub = w[max(iy - 2, 0) : iy + 3, max(ix - 2, 0) : ix + 3]
    ys, xs = plane["y"].values[max(iy - 2, 0) : iy + 3], plane["x"].values[max(ix - 2, 0) : ix + 3]
    diam = np.sqrt(4 / np.pi * w.sum() ** 2 / (w**2).sum())
    return w.max(), diam, float((sub.sum(0) * xs).sum() / sub.sum()), float((sub.sum(1) * ys).sum() / sub.sum())


@pytest.mark.parametrize(
    "plane,x,y", [(9, 0.3, -0.2), (6, 0.5, 0.4), (12, -0.4, 0.3), (3, 0.2, 0.25), (15, -0.3, -0.35)]
)
def test_single_particle_sharpest_on_nearest_plane(centers, plane, x, y):
    planes = CAM.focal_planes()
    z = float(planes["z"].sel(plane=plane))
    lf = register(_simulate(CAM, [(x, y, z)], seed=plane), centers, CAM)
    st = focal_stack(lf, CAM, planes).compute()
    stats = np.array([_measure(st.isel(z=k)) for k in range(st.sizes["z"])])
    best = int(np.argmax(stats[:, 0]))
    assert int(st["plane"][best]) == plane
    assert float(st["z"][best]) == pytest.approx(z)
    assert int(np.argmin(stats[:, 1])) == best  # smallest image diameter there too (Figs 5.12-5.16)
    # Right place in object space, sign included (+x object -> +x in the volume).
    assert abs(stats[best, 2] - x) <= HALF_VOXEL
    assert abs(stats[best, 3] - y) <= HALF_VOXEL


def test_displacement_sign(centers):
    """A particle moved +0.5625 mm in x moves +4.5 voxels along the ascending x axis."""
    z = float(CAM.focal_planes()["z"].sel(plane=7))
    pts = [(-0.4, 0.1, z), (0.1, -0.3, z)]
    moved = [(px + 0.5625, py, pz) for px, py, pz in pts]
    cents = []
    for p in (pts, moved):
        st = focal_stack(register(_simulate(CAM, p, seed=4), centers, CAM), CAM).sel(z=z).compute()
        w = st.values
        cents.append((w.sum(0) * st["x"].values).sum() / w.sum())
    assert cents[1] - cents[0] == pytest.approx(0.5625, abs=0.05)


def test_registration_preserves_signal_and_layout(centers):
    raw = _simulate(CAM, [(0.1, 0.1, 2.0), (-0.5, 0.3, -1.0)], seed=2)
    raw += np.random.default_rng(0).random(raw.shape)  # every pixel non-zero
    lf = register(raw, centers, CAM, dtype=np.float64)
    n = lf.sizes["prow"]
    assert lf.dims == ("lrow", "lcol", "prow", "pcol") and n == 16  # floor(16.97)
    assert lf.shape[:2] == (CAM.n_lenslets_y, CAM.n_lenslets_x)
    # The assigned pixels: union of the blocks (they never overlap).
    mask = np.zeros(raw.shape, int)
    for r0, c0 in zip(lf["row0"].values.ravel(), lf["col0"].values.ravel()):  # test-side bookkeeping
        mask[max(r0, 0) : max(r0 + n, 0), max(c0, 0) : max(c0 + n, 0)] += 1
    assert mask.max() == 1
    assert float(lf.sum()) == pytest.approx(float(raw[mask == 1].sum()), rel=1e-12)
    # Angles: theta grows with the pixel column, phi falls with the pixel row (y up), bulk ~ x/si.
    assert np.all(np.diff(lf["theta"].values, axis=-1) > 0)
    assert np.all(np.diff(lf["phi"].values, axis=-1) < 0)
    np.testing.assert_allclose(lf["theta_bulk"].values, np.arctan(lf["x"].values / CAM.si))
    tx, _ty = CAM.lenslet_centers()
    v = lf["valid"].values
    assert np.abs(lf["x"].values - tx)[v].max() < 0.01 * CAM.lenslet_pitch
    for c in ("x", "y", "theta", "phi", "theta_bulk", "phi_bulk"):
        assert lf[c].attrs["units"] in ("mm", "rad")


def test_register_bad_inputs(centers):
    with pytest.raises(RegistrationError, match="420 x 340"):
        register(np.zeros((100, 100)), centers, CAM)
    bad = np.zeros((340, 420))
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        register(bad, centers, CAM)


def test_stack_planes_coords_and_zarr(centers, tmp_path):
    raw = _simulate(CAM, [(0.2, 0.1, 1.0)], n_rays=20_000)
    lf = register(raw, centers, CAM)
    planes = CAM.focal_planes()
    st = focal_stack(lf, CAM, planes)
    assert st.dims == ("z", "y", "x")
    assert st.chunks[0] == (1,) * 17  # one chunk (and one task) per plane
    # Table 5.1 spacing: the stack's t are focal_planes' t, in ascending z.
    np.testing.assert_allclose(st["t"].values, planes["t"].values[::-1])
    np.testing.assert_allclose(np.sort(st["t"].values)[[2, 8, 14]], [-5.8236, 0.0, 6.1837], atol=1e-4)
    for c in ("z", "y", "x"):
        assert np.all(np.diff(st[c].values) > 0) and st[c].attrs["units"] == "mm"
    assert np.diff(st["x"].values)[0] == pytest.approx(CAM.lenslet_pitch / abs(CAM.magnification))
    assert "y_direction" in st.attrs and st.attrs["units"]
    # A plane's total signal is the light field's (nothing lost off the grid for a central particle).
    assert float(st.isel(z=8).sum()) == pytest.approx(float(lf.sum()), rel=1e-5)
    io.write_zarr(lf, tmp_path / "lf.zarr")
    io.write_zarr(st, tmp_path / "st.zarr")
    lf2 = io.open_zarr(tmp_path / "lf.zarr", name="radiance")
    st2 = io.open_zarr(tmp_path / "st.zarr", name="intensity")
    xr.testing.assert_allclose(focal_stack(lf2.load(), CAM, planes).compute(), st2.compute())


def test_unresized_stack_shows_the_magnification_bias(centers):
    """Without resizing, off-axis particles sit at X·so/Do on the nominal grid (Fig. 7.5)."""
    planes = CAM.focal_planes()
    z = float(planes["z"].sel(plane=3))  # far plane, Do > so
    x = 1.0
    lf = register(_simulate(CAM, [(x, 0.0, z)], seed=7), centers, CAM)
    for resize in (True, False):
        st = focal_stack(lf, CAM, planes, resize=resize).sel(z=z).compute()
        _, _, cx, _ = _measure(st)
        if resize:
            assert abs(cx - x) <= HALF_VOXEL
        else:
            do = CAM.so + z
            assert cx == pytest.approx(x * CAM.so / do, abs=HALF_VOXEL)
            xo = float(st["x_object"].sel(x=cx, method="nearest"))
            assert abs(xo - x) <= 1.6 * HALF_VOXEL


def test_render_volume_config_chain(centers):
    cfg = {
        "camera": {
            "sensor": {"n_pixels_x": 420, "n_pixels_y": 340, "pixel_pitch": 0.0074},
            "lenslet": {"pitch": 0.125, "focal_length": 0.5},
            "main_lens": {"focal_length": 50.0, "fnumber": "matched"},
            "magnification": -1.0,
        },
        "refocus": {"n_planes": 24, "depth_scale": 1.5, "cubic": False, "resize": True},
        "reconstruct": {"method": "threshold", "threshold": {"k": 3.0, "dilation_radius": 1}},
    }
    cfg = validate_config(cfg)
    raw = _simulate(CAM, [(0.2, 0.1, 1.0), (-0.6, -0.3, -3.0)], n_rays=30_000)
    _lf, st, vol = render_volume(raw, centers, cfg)
    # the stack is refocused onto the reconstruction grid: uniform z steps of half the
    # Table 5.1 plane spacing at the focal plane, over the depth of the 24 widened planes
    planes = CAM.focal_planes(24, depth_scale=1.5)["z"].values
    dz = default_voxel_z(CAM)
    assert np.allclose(np.diff(st["z"].values), dz) and np.allclose(vol["z"].values, st["z"].values)
    assert planes.min() - 1e-9 <= st["z"].values[0] < planes.min() + dz
    assert vol.chunks[0] == (1,) * vol.sizes["z"]
    assert 0 < vol.attrs["kept_fraction"] < 0.2 and vol.attrs["k"] == 3.0 and vol.attrs["method"] == "threshold"


def test_single_particle_with_raytrace(centers):
    """End to end with the project's ray tracer."""
    from lfstudy.simulate import raytrace
    from lfstudy.simulate.particles import make_field

    planes = CAM.focal_planes()
    z = float(planes["z"].sel(plane=6))
    field = make_field(np.array([0.5]), np.array([-0.3]), np.array([z]), np.array([1.0]))
    pin = raytrace.render_pinhole(CAM, count=20_000, rays_per_point=100, seed=0, method="montecarlo")
    cen = find_lenslet_centers(pin, CAM)
    raw = raytrace.render(CAM, field, 100_000, 1, method="montecarlo")
    st = focal_stack(register(raw, cen, CAM), CAM, planes).compute()
    stats = np.array([_measure(st.isel(z=k)) for k in range(st.sizes["z"])])
    best = int(np.argmax(stats[:, 0]))
    assert int(st["plane"][best]) == 6
    assert abs(stats[best, 2] - 0.5) <= HALF_VOXEL and abs(stats[best, 3] + 0.3) <= HALF_VOXEL
