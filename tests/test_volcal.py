"""Volumetric calibration from a dot target (issue 29 §2; Hall et al. 2018, Appl. Opt. 57(4) 914).

The fitted mapping must reproduce the thin-lens model on the ideal camera (where that model
is exact), and must place particles where they are on a camera the thin-lens model gets
wrong (main-lens distortion and a lenslet gap error), where the thin-lens refocus does not.
"""

from __future__ import annotations

import numpy as np
import pytest

from lfstudy.lightfield import find_lenslet_centers, focal_stack, register
from lfstudy.lightfield import volcal as vc
from lfstudy.optics import PlenopticCamera
from lfstudy.simulate import raytrace as rt
from lfstudy.simulate.dottarget import DotTargetError, render_dot_target
from lfstudy.simulate.particles import make_field

#: Table 4.3 optics on a 35 x 28 lenslet sensor.
CAM = PlenopticCamera(600, 480, 0.0074, 0.125, 0.5, 50.0, -1.0)
DEPTHS = np.linspace(-3.0, 3.0, 7)
SPACING = 0.5  # 4 lenslets: 9 x 7 dots over the field
IMPERFECT = {"distortion_k1": 0.05, "lenslet_gap_error": 0.02}


def _calibrate(imp):
    pinhole = rt.render_pinhole(CAM, count=20000, rays_per_point=50, seed=1, method="exact", imperfections=imp)
    centers = find_lenslet_centers(pinhole, CAM)
    imgs = render_dot_target(CAM, DEPTHS, spacing=SPACING, photons=20000, imperfections=imp, seed=3)
    lfs = [register(imgs.isel(depth=k).drop_vars("depth"), centers, CAM) for k in range(DEPTHS.size)]
    return centers, vc.fit_volumetric(lfs, DEPTHS, CAM, spacing=SPACING)


@pytest.fixture(scope="module")
def ideal():
    return _calibrate(None)


@pytest.fixture(scope="module")
def imperfect():
    return _calibrate(IMPERFECT)


def _grid():
    d = CAM.lenslet_pitch / abs(CAM.magnification)
    xg = (np.arange(CAM.n_lenslets_x) - 0.5 * (CAM.n_lenslets_x - 1)) * d
    yg = (np.arange(CAM.n_lenslets_y) - 0.5 * (CAM.n_lenslets_y - 1)) * d
    return xg, yg, d


def _locate(stack, zg, xg, yg):
    """The brightest voxel's plane and the 3 x 3 in-plane centroid around it."""
    v = stack.values.astype(float)
    k, j, i = np.unravel_index(np.argmax(v), v.shape)
    w = v[k, j - 1 : j + 2, i - 1 : i + 2]
    w = w - w.min()
    return zg[k], (w.sum(0) * xg[i - 1 : i + 2]).sum() / w.sum(), (w.sum(1) * yg[j - 1 : j + 2]).sum() / w.sum()


def test_dot_target_images_are_reproducible_and_laid_out():
    a = render_dot_target(CAM, [-1.0, 1.0], spacing=SPACING, seed=5)
    b = render_dot_target(CAM, [-1.0, 1.0], spacing=SPACING, seed=5)
    assert a.dims == ("depth", "row", "col") and a.shape == (2, 480, 600)
    np.testing.assert_array_equal(a.values, b.values)
    assert a.attrs["n_dots"] == vc.dot_grid(SPACING, CAM.fov_x, CAM.fov_y)[0].size
    assert float(a.min()) >= 0.0  # a sensor reads counts
    c = render_dot_target(CAM, [-1.0, 1.0], spacing=SPACING, seed=6)
    assert not np.array_equal(a.values, c.values)  # the noise follows the seed


def test_fit_reproduces_the_thin_lens_model_on_the_ideal_camera(ideal):
    _, cal = ideal
    assert cal.attrs["order"] == 3 and cal.sizes["term"] == 20
    assert cal["valid"].sum() > 150  # the sub-apertures inside the main-lens aperture
    assert cal.attrs["holdout_depth"] == 0.0
    assert 0 < cal.attrs["holdout_rms_lenslets"] < 0.15
    assert 0 < cal.attrs["fit_rms_lenslets"] < 0.35
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.4, 0.4, (2, 200)) * np.array([[CAM.fov_x], [CAM.fov_y]])
    z = rng.uniform(-2.5, 2.5, 200)
    lf = register(rt.render(CAM, make_field([0.0], [0.0], [0.0], [1.0]), 1000, 0), ideal[0], CAM)
    s0, t0 = vc._nominal_positions(lf, CAM, x, y, z)
    p = vc.predict(cal, x, y, z).values
    ok = cal["valid"].values
    err = np.hypot(p[0] - s0, p[1] - t0)[:, ok]
    assert abs(np.mean((p[0] - s0)[:, ok])) < 0.02 and abs(np.mean((p[1] - t0)[:, ok])) < 0.02
    assert np.sqrt(np.mean(err**2)) < 0.2  # lenslets


def test_volumetric_stack_locates_particles_the_thin_lens_model_misplaces(ideal, imperfect):
    xg, yg, d = _grid()
    zg = np.linspace(-2.5, 2.5, 11)
    pts = [(-1.5, -1.1, 0.5), (1.6, 1.0, -2.0), (0.3, 0.2, 1.0)]
    worst = {"thin": 0.0, "vol": 0.0, "vol_ideal": 0.0}
    for imp, (centers, cal), names in ((IMPERFECT, imperfect, ("thin", "vol")), (None, ideal, (None, "vol_ideal"))):
        for x, y, z in pts:
            img = rt.render(CAM, make_field([x], [y], [z], [1.0]), 20000, 0, imperfections=imp)
            lf = register(img, centers, CAM)
            stacks = {
                names[0]: focal_stack(lf, CAM, CAM.planes_at(zg), x=xg, y=yg) if names[0] else None,
                names[1]: vc.volumetric_stack(lf, cal, zg, xg, yg),
            }
            for name, st in stacks.items():
                if name is None:
                    continue
                _, cx, cy = _locate(st, zg, xg, yg)
                worst[name] = max(worst[name], abs(cx - x) / d, abs(cy - y) / d)
    assert worst["thin"] > 0.2  # distortion and the gap error move the corner particles
    assert worst["vol"] < 0.12  # voxels
    assert worst["vol_ideal"] < 0.12


def test_volumetric_stack_conserves_the_plane_signal_like_the_splat(ideal):
    centers, cal = ideal
    xg, yg, _ = _grid()
    img = rt.render(CAM, make_field([0.2], [-0.1], [1.5], [1.0]), 20000, 0)
    lf = register(img, centers, CAM)
    zg = np.array([-1.0, 0.0, 1.5])
    vol = vc.volumetric_stack(lf, cal, zg, xg, yg).values.sum(axis=(1, 2))
    thin = focal_stack(lf, CAM, CAM.planes_at(zg), x=xg, y=yg).values.sum(axis=(1, 2))
    # the calibrated sub-apertures carry nearly all the light; the sums agree to a few per cent
    np.testing.assert_allclose(vol, thin, rtol=0.05)


def test_bad_settings_name_the_field(ideal):
    centers, cal = ideal
    with pytest.raises(vc.VolumetricCalibrationError, match=r"volumetric_calibration\.order = 7.*\[1, 5\]"):
        vc.polynomial_exponents(7)
    with pytest.raises(vc.VolumetricCalibrationError, match=r"volumetric_calibration\.spacing"):
        vc.dot_grid(-1.0, 1.0, 1.0)
    with pytest.raises(DotTargetError, match=r"volumetric_calibration\.depths.*2 distinct"):
        render_dot_target(CAM, [1.0, 1.0], spacing=SPACING)
    lf = register(rt.render(CAM, make_field([0.0], [0.0], [0.0], [1.0]), 1000, 0), centers, CAM)
    with pytest.raises(vc.VolumetricCalibrationError, match=r"order \+ 1 = 4 distinct"):
        vc.fit_volumetric([lf, lf, lf], [0.0, 1.0, 2.0], CAM, spacing=SPACING)
    with pytest.raises(vc.VolumetricCalibrationError, match=r"window = 9 lenslets exceeds the dot pitch"):
        vc.fit_volumetric([lf] * 4, [0.0, 1.0, 2.0, 3.0], CAM, spacing=SPACING, window=9)
    xg, yg, _ = _grid()
    with pytest.raises(vc.VolumetricCalibrationError, match=r"volumetric_calibration\.depths cover.*extrapolate"):
        vc.volumetric_stack(lf, cal, np.array([0.0, 5.0]), xg, yg)


def test_the_calibration_type_owns_its_range_and_shape_checks(ideal):
    """VolumetricCalibration is the one place of the checks: a whole fit, the light field it was fitted on,
    depths within the calibrated ones (5 % of their range either side); the refocus, MART's projector
    and the reconstruction inputs all say the same."""
    from lfstudy.reconstruct import ReconstructionError, ReconstructionInputs
    from lfstudy.reconstruct.grid import ReconstructionGrid
    from lfstudy.reconstruct.projector import PlenopticProjector, ProjectorError

    centers, cal = ideal
    vcal = vc.VolumetricCalibration(cal)
    assert vc.VolumetricCalibration.of(vcal) is vcal and vc.VolumetricCalibration.of(cal).dataset is cal
    assert vcal.z_range == (DEPTHS.min(), DEPTHS.max())
    lf = register(rt.render(CAM, make_field([0.0], [0.0], [0.0], [1.0]), 1000, 0), centers, CAM)
    assert vcal.lightfield_shape == (lf.sizes["lrow"], lf.sizes["lcol"], lf.sizes["prow"])
    vcal.check_lightfield(lf)
    # the margin, on both sides: 6 mm calibrated, 0.3 mm allowed beyond either end
    lo, hi = vcal.z_range
    vcal.check_depths([lo - 0.29, hi + 0.29])
    for z in ([lo - 0.31, 0.0], [0.0, hi + 0.31]):
        with pytest.raises(vc.VolumetricCalibrationError, match=r"depths cover z = -3\.\.3 mm but the grid spans"):
            vcal.check_depths(z)
    # not a whole fit: the missing variable or attr is named
    with pytest.raises(vc.VolumetricCalibrationError, match="lacks 'coef'"):
        vc.VolumetricCalibration(cal.drop_vars("coef"))
    bare = cal.copy()
    bare.attrs = {k: v for k, v in cal.attrs.items() if k != "z_max"}
    with pytest.raises(vc.VolumetricCalibrationError, match=r"lacks the attrs \['z_max'\]"):
        vc.VolumetricCalibration(bare)
    with pytest.raises(vc.VolumetricCalibrationError, match="got DataArray"):
        vc.VolumetricCalibration(cal["coef"])
    with pytest.raises(ReconstructionError, match="lacks 'valid'"):
        ReconstructionInputs(calibration=cal.drop_vars("valid"))
    # another light field's calibration: the same message from each user
    other = cal.assign_attrs(n_lcol=cal.attrs["n_lcol"] + 1)
    nr, nc, n = vcal.lightfield_shape
    msg = rf"light field \({nr} x {nc} lenslets, {n} px each\) is not the one .* fitted on \({nr} x {nc + 1}, {n} px\)"
    xg, yg, _ = _grid()
    with pytest.raises(vc.VolumetricCalibrationError, match=msg):
        vc.volumetric_stack(lf, other, np.array([0.0]), xg, yg)
    with pytest.raises(ProjectorError, match=msg):
        PlenopticProjector(lf, CAM, ReconstructionGrid(xg, yg, np.array([0.0, 1.0])), calibration=other)


# ------------------------------------------------------------------ MART's projector and IPR's frame
def _point_volume(grid, x, y, z):
    """A unit point on the grid's tent voxels (bilinear in x, y; on the plane at z)."""
    v = np.zeros(grid.shape)
    k = int(np.argmin(np.abs(grid.z - z)))
    fx, fy = (x - grid.x[0]) / grid.dx, (y - grid.y[0]) / grid.dy
    i, j = int(fx), int(fy)
    wx, wy = fx - i, fy - j
    v[k, j : j + 2, i : i + 2] = np.outer([1 - wy, wy], [1 - wx, wx])
    return v


def test_mapped_projector_agrees_with_the_thin_lens_on_the_ideal_camera(ideal):
    """Where the thin lens is exact, the beams placed through the fitted mapping land where its beams do:
    every view's image of a point has the same centroid to a small fraction of a lenslet and the same
    signal (the calibration's own error, ~0.1 lenslet, is all that separates them)."""
    from lfstudy.reconstruct.grid import ReconstructionGrid
    from lfstudy.reconstruct.projector import PlenopticProjector, ProjectorError

    centers, cal = ideal
    xg, yg, _ = _grid()
    grid = ReconstructionGrid(xg, yg, np.linspace(-2.5, 2.5, 6))
    lf = register(rt.render(CAM, make_field([0.0], [0.0], [0.0], [1.0]), 1000, 0), centers, CAM)
    thin = PlenopticProjector(lf, CAM, grid)
    vol = PlenopticProjector(lf, CAM, grid, calibration=cal)
    assert vol.model == "volumetric" and thin.model == "thin_lens"
    assert vol.uncalibrated_samples < 0.01 * thin.n_rays  # the edge sub-apertures volcal drops
    shape = thin.shape_lf
    rows, cols = np.arange(shape[0])[:, None, None, None], np.arange(shape[1])[None, :, None, None]
    for x, y, z in [(-1.5, -1.1, -2.5), (1.6, 1.0, 1.5), (0.3, 0.2, 0.5)]:
        a, b = (p.forward(_point_volume(grid, x, y, z)) for p in (thin, vol))
        ta, tb = a.sum((0, 1)), b.sum((0, 1))
        np.testing.assert_allclose(tb.sum(), ta.sum(), rtol=0.03)
        use = (ta > 0.2 * ta.max()) & (tb > 0.2 * tb.max())
        ds = (b * cols).sum((0, 1))[use] / tb[use] - (a * cols).sum((0, 1))[use] / ta[use]
        dt = (b * rows).sum((0, 1))[use] / tb[use] - (a * rows).sum((0, 1))[use] / ta[use]
        assert abs(ds.mean()) < 0.05 and abs(dt.mean()) < 0.05  # lenslets
        assert np.sqrt(np.mean(ds**2 + dt**2)) < 0.3
    with pytest.raises(ProjectorError, match=r"volumetric_calibration\.depths cover.*extrapolate"):
        PlenopticProjector(lf, CAM, ReconstructionGrid(xg, yg, np.array([0.0, 4.0])), calibration=cal)


def test_mart_through_the_mapping_places_the_particles_the_thin_lens_misplaces(imperfect):
    """Under distortion and a lenslet gap error MART with the nominal projector puts a corner particle half a
    voxel off (0.49 when written); through the volumetric calibration within 0.2 (0.19; MART's own bias on
    the ideal camera at such points is up to 0.19 voxel in y)."""
    from lfstudy.reconstruct.grid import ReconstructionGrid
    from lfstudy.reconstruct.mart import mart

    centers, cal = imperfect
    _, _, d = _grid()
    h = d / 2  # half-voxel grid: MART's snapping to voxel centres stays below the distortion's shift
    xg = np.arange(-34, 35) * h
    yg = np.arange(-27, 28) * h
    grid = ReconstructionGrid(xg, yg, np.linspace(-2.4, 2.4, 7))
    pts = np.array([(-1.5, -1.1, 0.4), (-1.7, 1.2, -0.8), (1.4, -1.2, 1.6)])
    img = rt.render(CAM, make_field(*pts.T, np.ones(len(pts))), 20000, 0, imperfections=IMPERFECT)
    lf = register(img, centers, CAM)
    X, Y = np.meshgrid(xg, yg)
    worst = {}
    for name, c in (("thin", None), ("vol", cal)):
        v = mart(lf, CAM, grid, calibration=c)
        assert v.attrs["projector_model"] == ("thin_lens" if c is None else "volumetric")
        v = v.values.astype(float)
        err = []
        for x, y, _ in pts:
            near = (np.abs(X - x) < 3.5 * d) & (np.abs(Y - y) < 3.5 * d)
            w = v[:, near]
            err += [abs((w * X[near]).sum() / w.sum() - x) / d, abs((w * Y[near]).sum() / w.sum() - y) / d]
        worst[name] = max(err)
    assert worst["thin"] > 0.35
    assert worst["vol"] < 0.25


def test_ipr_frame_correction_recovers_a_known_frame_change(ideal):
    """A calibration whose mapping is the thin lens of an affinely moved point, P(x) = Q(A·x + b): a particle
    IPR fits at x_nom in the nominal frame is at A⁻¹(x_nom − b) in the calibrated one, and back."""
    from lfstudy.reconstruct.ipr import volumetric_frame

    centers, cal = ideal
    lf = register(rt.render(CAM, make_field([0.0], [0.0], [0.0], [1.0]), 1000, 0), centers, CAM)
    A = np.array([[1.01, 0.005, 0.0], [-0.004, 0.99, 0.0], [0.0, 0.0, 1.02]])
    b = np.array([0.04, -0.03, 0.1])
    rng = np.random.default_rng(4)
    fit = np.column_stack([rng.uniform(-2.2, 2.2, 400), rng.uniform(-1.7, 1.7, 400), rng.uniform(-3, 3, 400)])
    moved = fit @ A.T + b
    st = vc.predict_thin_lens(lf, CAM, *moved.T).values  # (axis, point, prow, pcol)
    dmat = vc._design(*vc._norm(cal, *fit.T), cal["exponents"].values)
    coef = np.einsum("kp,apij->aijk", np.linalg.pinv(dmat), st)
    fake = cal.copy()
    fake["coef"] = (("axis", "prow", "pcol", "term"), coef)
    x_nom = np.array([[-1.5, -1.1, 0.5], [1.6, 1.0, -2.0], [0.3, 0.2, 1.0]])
    x_cal = volumetric_frame(x_nom, lf, CAM, fake, to="calibrated")
    truth = np.linalg.solve(A, (x_nom - b).T).T
    _, _, d = _grid()
    assert np.abs(x_cal - x_nom).max() > 0.5 * d  # the frames differ by many voxels' worth...
    np.testing.assert_allclose(x_cal, truth, atol=0.02 * d)  # ...and the correction recovers it
    back = volumetric_frame(x_cal, lf, CAM, fake, to="nominal")
    np.testing.assert_allclose(back, x_nom, atol=0.02 * d)


def test_a_refocus_model_sweep_shares_the_camera_stage():
    """refocus.model swept beside an imperfection (config/tolerances_volcal.yaml's layout): the camera
    file is made once per design, the stacks and reconstructions once per model, and only the
    volumetric cases read a dot-target calibration."""
    from pathlib import Path

    import yaml

    from lfstudy.study.config import expand_cases, sweep_of, validate_config

    raw = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "demo.yaml").read_text())
    raw["sweep"] = {"refocus.model": ["thin_lens", "volumetric"], "camera.imperfections.distortion_k1": [0.0, 0.06]}
    cfg = validate_config(raw)
    sw = sweep_of(cfg)
    assert len(expand_cases(cfg)) == 4
    assert len(sw.stage_ids("camera")) == 1
    assert len(sw.stage_ids("refocus")) == 4 and len(sw.stage_ids("reconstruct")) == 4
