"""IPR's image model calibrated from the recording's own particles (issue 39 §2).

The images with a model are the exact renderer's images of the imperfect camera (the gap of
:mod:`lfstudy.simulate.imperfections`, the diffraction blurs scaled); the calibration finds a gap
the nominal model lacks from particles at their positions, and keeps the nominal images where the
recording has none.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from lfstudy.lightfield import find_lenslet_centers, register, synthetic_pinhole
from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct import ReconstructionError, ReconstructionInputs, make_grid, method_schemas
from lfstudy.reconstruct.image_model import ImageModel, calibrate_image_model, model_change
from lfstudy.reconstruct.ipr import ipr_particles, particle_patches
from lfstudy.simulate import make_field
from lfstudy.simulate.exact import render_exact

CAM = PlenopticCamera(200, 200, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013, lenslet_offset_y=-0.021)
PTS = np.array([(0.21, -0.17, 0.4), (-0.32, 0.29, 1.7), (0.41, 0.28, -2.3), (0.0, 0.0, 3.1), (-0.2, -0.35, -1.2)])


def _embedded(patches, i, shape):
    buf, offs, r0, c0, shp = patches
    h, w = shp[i]
    out = np.zeros(shape)
    out[r0[i] : r0[i] + h, c0[i] : c0[i] + w] = buf[offs[i] : offs[i] + h * w].reshape(h, w)
    return out


@pytest.mark.parametrize(("gap", "scale"), [(0.04, 1.0), (-0.03, 1.7), (0.0, 0.6)])
def test_patches_with_a_model_are_the_imperfect_cameras_render(gap, scale):
    """Each patch of a model is render_exact's image of the camera with that gap and those blurs (the patch
    box follows the gap's aperture images: nothing of the image falls outside it)."""
    model = ImageModel(gap_error=gap, blur_scale=scale)
    pat = particle_patches(CAM, *PTS.T, model=model)
    sigmas = (CAM.sigma_lenslet_plane * scale, CAM.sigma_sensor_plane * scale)
    for i, p in enumerate(PTS):
        field = make_field(*[np.array([v]) for v in p], np.ones(1))
        full = render_exact(CAM, field, 1, sigmas=sigmas, imperfections={"lenslet_gap_error": gap}).values
        emb = _embedded(pat, i, full.shape)
        assert np.abs(emb - full).max() <= 1e-12 * full.max()
        assert emb.sum() == pytest.approx(full.sum(), rel=1e-12)


def test_the_ideal_model_is_the_nominal_image_bit_for_bit():
    a = particle_patches(CAM, *PTS.T)
    b = particle_patches(CAM, *PTS.T, model=ImageModel())
    for u, v in zip(a, b):
        assert np.array_equal(u, v)


def test_bad_settings_name_the_field_and_range():
    with pytest.raises(ReconstructionError, match=r"gap_error = 0.5: allowed range is \[-0.1, 0.1\]"):
        ImageModel(gap_error=0.5)
    with pytest.raises(ReconstructionError, match=r"blur_scale = 0.0: allowed range is \[0.25, 4.0\]"):
        ImageModel(blur_scale=0.0)
    # the settings are checked before any work: a pinhole image stands in for the recording
    cen = find_lenslet_centers(synthetic_pinhole(CAM, amplitude=3000, seed=1), CAM)
    pin = synthetic_pinhole(CAM, amplitude=3000, seed=2)
    lf = register(pin.clip(min=0.0), cen, CAM)
    inputs = ReconstructionInputs(lightfield=lf, centers=cen, camera=CAM, grid=make_grid(CAM, CAM.focal_planes()))
    for bad in (-1, 6, True, 1.5):
        with pytest.raises(ReconstructionError, match=r"ipr\.image_calibration = .*: allowed range is \[0, 5\]"):
            ipr_particles(inputs, image_calibration=bad)
    assert method_schemas()["ipr"]["properties"]["image_calibration"]["maximum"] == 5


def _recording(gap: float, noise: float, seed: int):
    """Sensor data of PTS (intensities 1, 1.3, ...) through a camera with ``gap``, Gaussian noise of ``noise``
    times the brightest pixel, and the render function IPR's calibration uses."""
    inten = 1.0 + 0.3 * np.arange(len(PTS))
    field = make_field(*PTS.T, inten)
    img = render_exact(CAM, field, 1, imperfections={"lenslet_gap_error": gap}).values
    rng = np.random.default_rng(seed)
    img = img + noise * img.max() * rng.standard_normal(img.shape)

    def render(pos, model=None):
        return particle_patches(CAM, *np.asarray(pos).T, model=model)

    return img, inten, render


def _residual(data, render, inten, model=None):
    """data − Σ inten·U of the images of ``model`` (default nominal: the residual a first IPR pass leaves)."""
    res = data.copy()
    buf, offs, r0, c0, shp = render(PTS, model=model)
    for i in range(len(PTS)):
        h, w = shp[i]
        res[r0[i] : r0[i] + h, c0[i] : c0[i] + w] -= inten[i] * buf[offs[i] : offs[i] + h * w].reshape(h, w)
    return res


def test_calibration_finds_the_gap_the_nominal_model_lacks():
    """Particles at their true positions, intensities a fifth off: the calibration recovers a 4 % gap error
    (within 0.002), keeps the blur near 1, lowers the residual below a tenth of the nominal one, and says
    what it changed per depth (most where the aperture images are largest)."""
    data, inten, render = _recording(0.04, 1e-3, 0)
    mask = np.ones(data.shape, np.uint8)
    res0 = _residual(data, render, inten * 0.95)
    model, res, amp, info = calibrate_image_model(render, data, res0, mask, PTS, inten * 0.95, CAM, (-3.5, 3.5))
    assert info["image_calibration_accepted"]
    assert model.gap_error == pytest.approx(0.04, abs=0.002)
    assert model.blur_scale == pytest.approx(1.0, abs=0.15)
    f0, f1 = info["image_calibration_cost"]
    assert f0 <= np.sum(res0 * res0) / np.sum(data * data) * (1 + 1e-12)  # at the best common intensity factor
    assert f1 < 0.1 * f0
    # the intensities refitted under the model, and its exact residual
    np.testing.assert_allclose(amp, inten, rtol=0.05)
    exact = _residual(data, render, amp, model)
    assert np.abs(res - exact).max() <= 1e-9 * np.abs(data).max()
    assert np.sum(res * res) <= f1 * np.sum(data * data)
    ch = model_change(CAM, model, np.array([-3.0, 0.0, 3.0]), render)
    assert ch["image_change_z"] == [-3.0, 0.0, 3.0]
    assert all(v > 0.01 for v in ch["image_change_max"])


def test_calibration_keeps_the_nominal_images_of_a_nominal_camera():
    data, inten, render = _recording(0.0, 1e-3, 1)
    mask = np.ones(data.shape, np.uint8)
    res0 = _residual(data, render, inten)
    model, res, amp, info = calibrate_image_model(render, data, res0, mask, PTS, inten, CAM, (-3.5, 3.5))
    assert model.ideal and not info["image_calibration_accepted"]
    assert res is res0 and amp is inten  # nothing changed


def test_calibration_bytes_do_not_depend_on_the_threads():
    data, inten, render = _recording(0.02, 1e-3, 2)
    mask = np.ones(data.shape, np.uint8)
    before = numba.get_num_threads()
    out = []
    try:
        for n in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(n)
            res0 = _residual(data, render, inten)
            out.append(calibrate_image_model(render, data, res0, mask, PTS, inten, CAM, (-3.5, 3.5)))
    finally:
        numba.set_num_threads(before)
    for a in out[1:]:
        assert a[0] == out[0][0]
        assert np.array_equal(a[1], out[0][1]) and np.array_equal(a[2], out[0][2])


@pytest.mark.slow  # two IPR fits of a 300 x 300 px recording: 5 s on a quiet machine, 110 s on a loaded one
def test_ipr_with_the_calibrated_images_fits_an_imperfect_camera_better():
    """A recording through a camera whose lenslet array sits 5 % off its focal length (Monte-Carlo rays, shot
    noise; the pinhole calibration through the same camera) is fitted by IPR with the nominal images and with
    images calibrated from its particles: the calibration finds the gap within 0.01, and the calibrated fit
    finds at least as many particles, with a final residual below 0.8 of the nominal fit's."""
    from scipy.spatial import cKDTree

    from lfstudy.simulate import render
    from lfstudy.simulate.raytrace import render_pinhole
    from lfstudy.simulate.sensor import apply_sensor

    cam = PlenopticCamera(300, 300, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013, lenslet_offset_y=-0.021)
    imp = {"lenslet_gap_error": 0.05}
    rng = np.random.default_rng(3)
    n = 12
    pts = np.column_stack([rng.uniform(-0.9, 0.9, n), rng.uniform(-0.9, 0.9, n), rng.uniform(-3, 3, n)])
    pin = render_pinhole(cam, seed=1, imperfections=imp, count=20000, rays_per_point=20, shot_noise=True)
    cen = find_lenslet_centers(pin, cam)
    img = render(cam, make_field(*pts.T, np.ones(n)), 20000, 7, method="montecarlo", imperfections=imp)
    lf = register(apply_sensor(img, photons_per_particle=20000, seed=2), cen, cam)
    inputs = ReconstructionInputs(lightfield=lf, centers=cen, camera=cam, grid=make_grid(cam, cam.focal_planes()))
    vox = np.array(inputs.grid.voxel_size()[::-1])
    found, resid = [], []
    for rounds in (0, 2):
        p = ipr_particles(inputs, image_calibration=rounds)
        fit = np.column_stack([p[v].values for v in "xyz"])
        found.append(int((cKDTree(fit / vox).query(pts / vox)[0] < 0.5).sum()))
        resid.append(p.attrs["residual_norm"][-1])
    assert p.attrs["image_gap_error"] == pytest.approx(0.05, abs=0.01)
    assert len(p.attrs["image_change_max"]) == 7 and p.attrs["image_calibration_accepted"][0] == 1
    assert found[1] >= found[0]
    assert resid[1] < 0.8 * resid[0]
