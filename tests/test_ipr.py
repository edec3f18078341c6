"""IPR (issue 27, part 3): particles fitted with the exact camera model on the calibrated grid.

No inverse crime: the images are Monte-Carlo ray traced with shot noise on a camera whose
lenslet grid is offset; IPR fits with the exact renderer on the grid calibrated from a
pinhole image, never the true one.
"""

from __future__ import annotations

import numpy as np
import pytest

from lfstudy.lightfield import find_lenslet_centers, register, synthetic_pinhole
from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct import (
    ReconstructionError,
    ReconstructionInputs,
    get_method,
    make_grid,
    method_schemas,
    reconstruct,
    reconstruct_particles,
)
from lfstudy.reconstruct.ipr import calibrated_camera, ipr_particles, particle_patches, render_particles
from lfstudy.simulate import make_field, render
from lfstudy.simulate.exact import render_exact
from lfstudy.simulate.sensor import apply_sensor
from lfstudy.study.metrics import reconstruction_quality

#: Table 4.3 optics on 18 x 18 lenslets, the lenslet grid off the optical axis (the calibration must find it)
CAM = PlenopticCamera(300, 300, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013, lenslet_offset_y=-0.021)
N = 12
PHOTONS = 20_000


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.9, 0.9, N), rng.uniform(-0.9, 0.9, N), rng.uniform(-3, 3, N)])
    cen = find_lenslet_centers(synthetic_pinhole(CAM, amplitude=3000, seed=1), CAM)
    img = render(CAM, make_field(*pts.T, np.ones(N)), 20_000, 7, method="montecarlo")
    lf = register(apply_sensor(img, photons_per_particle=PHOTONS, seed=2), cen, CAM)
    grid = make_grid(CAM, CAM.focal_planes())
    return pts, ReconstructionInputs(lightfield=lf, centers=cen, camera=CAM, grid=grid)


@pytest.fixture(scope="module")
def fitted(scene):
    """One IPR fit through the registry, shared: the volume and the particle list it was rendered from."""
    return reconstruct_particles(scene[1], "ipr")


def test_particle_patches_are_the_exact_render():
    """Each cropped patch is render_exact's image of that particle alone (the crop moves cell edges by
    whole pixels only): equal to 1e-12 of the peak, with the same total."""
    pts = np.array([(0.33, -0.27, 0.1), (-0.52, 0.41, 1.7), (0.61, 0.48, -2.3), (1.0, 1.0, 3.4), (0.0, 0.0, 0.0)])
    buf, offs, r0, c0, shp = particle_patches(CAM, *pts.T)
    for i, p in enumerate(pts):
        full = render_exact(CAM, make_field(*[np.array([v]) for v in p], np.ones(1)), 1).values
        h, w = shp[i]
        emb = np.zeros_like(full)
        emb[r0[i] : r0[i] + h, c0[i] : c0[i] + w] = buf[offs[i] : offs[i] + h * w].reshape(h, w)
        assert np.abs(emb - full).max() <= 1e-12 * full.max()
        assert emb.sum() == pytest.approx(full.sum(), rel=1e-12)
    # trial images: the first of each particle is the unshifted one, the others its shifted renders
    tr = np.array([[0.01, 0.0, 0.0], [0.0, 0.0, -0.05]])
    buf2, offs2, *_ = particle_patches(CAM, *pts.T, trials=tr)
    h, w = shp[1]
    base = buf2[offs2[1] : offs2[1] + h * w]
    moved, _, r0m, c0m, shpm = particle_patches(CAM, *(pts[1] + tr[1])[:, None])
    emb = np.zeros((300, 300))
    emb[r0m[0] : r0m[0] + shpm[0, 0], c0m[0] : c0m[0] + shpm[0, 1]] = moved.reshape(shpm[0])
    np.testing.assert_allclose(base, buf[offs[1] : offs[1] + h * w], rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        buf2[offs2[1] + 2 * h * w : offs2[1] + 3 * h * w].reshape(h, w),
        emb[r0[1] : r0[1] + h, c0[1] : c0[1] + w],
        rtol=0,
        atol=1e-12 * emb.max(),
    )


def test_particle_patches_into_a_buffer_are_the_same_images():
    """``into``: the images rendered at the caller's starts in its buffer (whatever was there: each patch is
    zeroed first) are the ones of a new buffer, and the rest of the buffer is left alone; a buffer too small is
    refused."""
    pts = np.array([(0.33, -0.27, 0.1), (-0.52, 0.41, 1.7), (0.61, 0.48, -2.3)])
    tr = np.array([[0.01, 0.0, 0.0], [0.0, 0.0, -0.05]])
    buf, offs, r0, c0, shp = particle_patches(CAM, *pts.T, trials=tr, accuracy="fast")
    sizes = np.diff(offs)
    starts = np.concatenate([[5], 5 + np.cumsum(sizes[:-1] + 7)])  # gaps of 7 between the blocks
    out = np.full(int(starts[-1] + sizes[-1] + 3), np.nan)
    got, at, r0i, c0i, shpi = particle_patches(CAM, *pts.T, trials=tr, accuracy="fast", into=(out, starts))
    assert got is out and np.array_equal(at, starts)
    assert np.array_equal(r0i, r0) and np.array_equal(c0i, c0) and np.array_equal(shpi, shp)
    for i in range(len(pts)):
        assert np.array_equal(out[starts[i] : starts[i] + sizes[i]], buf[offs[i] : offs[i + 1]])
    assert np.isnan(out[:5]).all() and np.isnan(out[-3:]).all() and np.isnan(out[starts[1] - 7 : starts[1]]).all()
    with pytest.raises(ValueError, match="into"):
        particle_patches(CAM, *pts.T, trials=tr, into=(np.zeros(10), starts))


def test_fast_patches_are_within_their_stated_bound():
    """``accuracy="fast"`` (IPR's default images) against the exact quadrature, patch by patch and trial by
    trial: max |diff| <= 1e-4 of the patch's peak and |sum diff| <= 1e-5 of its sum, for particles in and out
    of focus, at several depths and with the spot's centre on, near and between lenslet edges."""
    rng = np.random.default_rng(11)
    zs = np.array([-3.4, -2.2, -1.1, -0.4, -0.05, 0.0, 0.02, 0.3, 0.9, 1.7, 2.6, 3.4])
    pl, ox, oy = CAM.lenslet_pitch, CAM.lenslet_offset_x, CAM.lenslet_offset_y
    ex = (rng.integers(3, 15, zs.size) - 9.0) * pl + rng.choice([0.0, 1e-4, 2e-3, 0.03, 0.0625], zs.size)
    ey = (rng.integers(3, 15, zs.size) - 9.0) * pl + rng.choice([0.0, -1e-4, 5e-3, 0.0625], zs.size)
    d = CAM.so + zs  # spot centre on the lenslet plane at e: object x = -(e + o)·d/si
    x, y = -(ex + ox) * d / CAM.si, -(ey + oy) * d / CAM.si
    tr = np.array([[0.0125, 0.0, 0.0], [0.0, -0.0125, 0.0], [0.0, 0.0, 0.04]])
    exact, offs, r0, c0, shp = particle_patches(CAM, x, y, zs, trials=tr, accuracy="exact")
    fast, offs_f, r0_f, c0_f, shp_f = particle_patches(CAM, x, y, zs, trials=tr, accuracy="fast")
    assert np.array_equal(offs, offs_f) and np.array_equal(r0, r0_f) and np.array_equal(c0, c0_f)
    assert np.array_equal(shp, shp_f)
    worst = [0.0, 0.0]
    for i in range(zs.size):
        for k, (a, b) in enumerate(
            zip(np.split(exact[offs[i] : offs[i + 1]], 4), np.split(fast[offs[i] : offs[i + 1]], 4))
        ):
            assert a.max() > 0.0, (i, k)
            worst[0] = max(worst[0], np.abs(b - a).max() / a.max())
            worst[1] = max(worst[1], abs(b.sum() - a.sum()) / a.sum())
    assert worst[0] <= 1e-4 and worst[1] <= 1e-5, worst
    assert worst[0] > 0.0  # the fast quadrature is another one
    with pytest.raises(ReconstructionError, match="accuracy = 'coarse'; allowed values are exact, fast"):
        particle_patches(CAM, x[:1], y[:1], zs[:1], accuracy="coarse")


def test_calibrated_camera_finds_the_offset_grid():
    cen = find_lenslet_centers(synthetic_pinhole(CAM, amplitude=3000, seed=1), CAM)
    cam, info = calibrated_camera(CAM.with_(lenslet_offset_x=0.0, lenslet_offset_y=0.0), cen)
    assert abs(cam.lenslet_offset_x - 0.013) < 5e-4 and abs(cam.lenslet_offset_y + 0.021) < 5e-4
    assert cam.lenslet_pitch == pytest.approx(0.125, rel=1e-4) and info["grid_residual_px"] < 0.2
    tilted = CAM.with_(lenslet_rotation=0.01)
    with pytest.raises(ReconstructionError, match=r"centers: the calibrated lenslet grid is rotated"):
        calibrated_camera(tilted, find_lenslet_centers(synthetic_pinhole(tilted, amplitude=3000, seed=1), tilted))


@pytest.mark.parametrize("height", [300, 400])
def test_calibrated_camera_keeps_the_phase_when_the_lenslet_count_changes(height):
    """The lenslet count depends on the offset (the grid covers the sensor), so an offset moved by half a
    pitch can flip N's parity and move the lattice by half a pitch: every offset must come back onto the
    calibrated centres (found on a 400 x 400 crop: the lattice half a pitch off, 8.4 px, and offsets out of range)."""
    import xarray as xr

    for oy in np.linspace(-0.07, 0.07, 15):
        cam = PlenopticCamera(400, height, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013, lenslet_offset_y=oy)
        cx, cy = cam.lenslet_centers()
        s = (cam.si + cam.lenslet_focal_length) / cam.si
        cen = xr.Dataset({"x": (("row", "col"), cx * s), "y": (("row", "col"), cy * s)})
        fit, info = calibrated_camera(cam.with_(lenslet_offset_x=0.0, lenslet_offset_y=0.0), cen)
        assert info["grid_residual_px"] < 1e-6, (oy, fit.lenslet_offset_y)


def test_calibrated_camera_keeps_the_main_lens_f_number():
    """A pitch fitted 8e-9 relative short of the thesis' 0.125 mm (seed 6 of bench_ipr at 400 x 400 calibrates
    0.1249995) made the matched main lens round from f/2 up to f/2.8: the model's aperture image 0.71 of the
    real one, the spot moved 2 px, half the light in the wrong place."""
    import xarray as xr

    cam = PlenopticCamera(400, 400, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013, lenslet_offset_y=-0.021)
    assert cam.with_(lenslet_pitch=0.125 - 1e-9).main_fnumber > cam.main_fnumber  # the trap
    cx, cy = cam.lenslet_centers()
    s = (1 - 8e-9) * (cam.si + cam.lenslet_focal_length) / cam.si
    fit, _ = calibrated_camera(cam, xr.Dataset({"x": (("row", "col"), cx * s), "y": (("row", "col"), cy * s)}))
    assert fit.lenslet_pitch < 0.125 and fit.main_fnumber == cam.main_fnumber
    assert fit.aperture_diameter == pytest.approx(cam.aperture_diameter, rel=1e-12)


@pytest.mark.parametrize("scale", [1 - 2.7e-7, 1 - 1e-5])
def test_calibrated_camera_when_the_sensor_is_a_whole_number_of_lenslets(scale):
    """The demo design M -0.8, pitch 0.1184 mm: 640 x 480 px of 7.4 um are exactly 40 x 30 lenslets. A pitch
    fitted to the calibrated centres a hair short (2.7e-7 relative in the case of seed 1) makes the camera
    need 41 lenslets at offset 0 and 42 at half a pitch, and neither lattice holds the centres (found by the
    pair mode of benchmarks/bench_crosstalk.py: "no lenslet offset reproduces the calibrated grid")."""
    import xarray as xr

    cam = PlenopticCamera(640, 480, 0.0074, 0.1184, 0.4736, 50.0, -0.8)
    cx, cy = cam.lenslet_centers()
    s = scale * (cam.si + cam.lenslet_focal_length) / cam.si
    cen = xr.Dataset({"x": (("row", "col"), cx * s), "y": (("row", "col"), cy * s)})
    _, info = calibrated_camera(cam, cen)
    # the lattice is within 0.01 px of every centre (whichever offset and lenslet count give it)
    assert info["grid_residual_px"] < 0.01


def test_ipr_finds_the_particles(scene, fitted):
    """Measured: 11 of 12 within half a voxel (median 0.012 voxel), 1 ghost; the one missed is 0.17 mm from
    the focal plane, where a lenslet hides the position (8 of 12 and 2 ghosts when this test was written)."""
    pts, inputs = scene
    parts = fitted[1]
    vox = np.array(inputs.grid.voxel_size()[::-1])
    fit = np.column_stack([parts[v].values for v in ("x", "y", "z")])
    d = np.linalg.norm((fit[:, None, :] - pts[None]) / vox, axis=2)
    found = d.min(axis=0) < 0.5
    assert found.sum() >= 7
    assert np.median(d.min(axis=0)[found]) < 0.05
    assert (d.min(axis=1) >= 0.5).sum() <= 3  # ghosts
    # intensities of the found ones: the photons per particle, to 5 %
    near = d.argmin(axis=0)[found]
    assert np.median(parts["intensity"].values[near]) == pytest.approx(PHOTONS, rel=0.05)
    # the uncertainty is finite and small where it converged
    assert np.all(np.isfinite(parts["sigma_z"].values[near])) and np.median(parts["sigma_z"].values[near]) < vox[2]
    assert parts.attrs["residual_norm"][-1] < parts.attrs["residual_norm"][0]


def test_ipr_volume_beats_mart(scene, fitted):
    """The ``ipr`` method's volume (the particles as the truth's Gaussians) has a higher Q than MART's."""
    pts, inputs = scene
    truth = make_field(*pts.T, np.ones(N))
    sig = render_particles(truth, inputs.grid, CAM)[1]
    vol = fitted[0]
    q_ipr = reconstruction_quality(vol, truth, sigma_mm=sig)
    q_mart = reconstruction_quality(reconstruct(inputs, "mart"), truth, sigma_mm=sig)
    assert vol.dims == ("z", "y", "x") and vol.attrs["n_particles"] >= 7
    assert q_ipr > q_mart + 0.1, (q_ipr, q_mart)


def test_ipr_parameters_and_bad_input(scene):
    _, inputs = scene
    defaults = get_method("ipr").defaults()
    assert defaults["iterations"] == 10 and method_schemas()["ipr"]["properties"]["shake"]["default"] == 0.1
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr.*shake"):
        reconstruct(inputs, "ipr", shake=0.0)
    with pytest.raises(ReconstructionError, match=r"needs centers"):
        reconstruct(ReconstructionInputs(lightfield=inputs.lightfield, camera=CAM, grid=inputs.grid), "ipr")
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.jacobian = .backward.: allowed values"):
        ipr_particles(inputs, jacobian="backward")
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.batch = 0"):
        ipr_particles(inputs, batch=0)
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.residual_mart_iterations = -1: allowed range"):
        ipr_particles(inputs, residual_mart_iterations=-1)
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.residual_plane_step = 0: allowed range"):
        ipr_particles(inputs, residual_plane_step=0)
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.polish = 21: allowed range is \[0, 20\]"):
        ipr_particles(inputs, polish=21)
    for bad in (11, -1, 1.5, True):
        with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.split = .*: allowed range is \[0, 10\]"):
            ipr_particles(inputs, split=bad)
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.split_penalty = -1.0: allowed range"):
        ipr_particles(inputs, split_penalty=-1.0)
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.split_ratio = nan: allowed range"):
        ipr_particles(inputs, split_ratio=float("nan"))
    assert method_schemas()["ipr"]["properties"]["split"]["maximum"] == 10
    assert method_schemas()["ipr"]["properties"]["residual_candidates_min_gain"]["maximum"] == 1
    for bad in (-0.01, 1.5, float("nan"), "0.01", True):
        with pytest.raises(ReconstructionError, match=r"min_gain = .*: allowed range is \[0.0, 1.0\]"):
            ipr_particles(inputs, residual_candidates_min_gain=bad)
    for name in ("shake_settle", "residual_late_gain"):
        with pytest.raises(
            ReconstructionError, match=rf"reconstruct\.ipr\.{name} = 1.5: allowed range is \[0.0, 1.0\]"
        ):
            ipr_particles(inputs, **{name: 1.5})


def test_ipr_particles_states_the_methods_defaults():
    """The fit's settings are stated once, in IPRSettings: the method's run signature (where the schema reads its
    defaults) is its config fields and blob_sigma with their defaults; ipr_particles and ipr take an IPRSettings (or
    its fields as keywords) and restate none of them; a keyword that is no setting is refused by name."""
    import dataclasses
    import inspect

    from lfstudy.reconstruct.ipr import IPRSettings, ipr, ipr_particles

    fields = {f.name: f.default for f in dataclasses.fields(IPRSettings) if f.metadata["config"]}
    assert fields == IPRSettings.defaults() and "batch" not in fields
    assert get_method("ipr").defaults() == {**fields, "blob_sigma": 0.0}
    for f in (ipr, ipr_particles):
        assert not set(fields) & set(inspect.signature(f).parameters), f"{f.__name__} restates a setting"
    assert IPRSettings.of(IPRSettings(polish=1), split=2) == IPRSettings(polish=1, split=2)
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr: unknown setting\(s\) polsh; the settings are"):
        IPRSettings.of(polsh=1)


def test_the_package_examples_run_as_doctests():
    """The Examples of the package docstring and of IPRSettings run and print what they show (tests/test_doctests.py
    collects the top-level stage packages' faces only, not lfstudy.reconstruct.ipr)."""
    import doctest

    import lfstudy.reconstruct.ipr as pkg

    finder = doctest.DocTestFinder(recurse=False)
    tests = finder.find(pkg, pkg.__name__, globs={}) + finder.find(pkg.IPRSettings, "IPRSettings", globs={})
    assert sum(len(t.examples) for t in tests) >= 8
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    out: list[str] = []
    for t in tests:
        runner.run(t, out=out.append)
    assert runner.summarize(verbose=False).failed == 0, "".join(out)


def test_ipr_residual_is_kept_exact(scene, fitted):
    """The fit keeps its residual incrementally (moves, ghosts added back, rejected candidates added back):
    its last ``residual_norm`` is that of the particle list rendered afresh with the fit's images (the fast
    quadrature by default), to 1e-9."""
    from lfstudy.reconstruct.ipr import _raw_from_lightfield

    _, inputs = scene
    parts = fitted[1]
    cam, _ = calibrated_camera(CAM, inputs.centers)
    data, mask = _raw_from_lightfield(inputs.lightfield, (cam.n_pixels_y, cam.n_pixels_x))
    data = np.where(mask > 0, data, 0.0)
    acc = parts.attrs["image_accuracy"]
    assert acc == "fast"
    buf, offs, r0, c0, shp = particle_patches(cam, *(parts[v].values for v in "xyz"), accuracy=acc)
    model = np.zeros_like(data)
    for i, amp in enumerate(parts["intensity"].values):
        h, w = shp[i]
        model[r0[i] : r0[i] + h, c0[i] : c0[i] + w] += amp * buf[offs[i] : offs[i + 1]].reshape(h, w)
    fresh = np.sqrt(np.sum((np.where(mask > 0, data - model, 0.0)) ** 2)) / np.sqrt(np.sum(data**2))
    assert parts.attrs["residual_norm"][-1] == pytest.approx(fresh, rel=1e-9)
    assert parts.attrs["polished"] > 0  # the polish's moves are in it too
    # the residual-candidate rounds: each round's new particles, then the rounds skipped once one added fewer
    # than residual_candidates_min_gain of the list (with 12 particles: none); one MART volume per round run
    gain, skipped = parts.attrs["candidates_added"], parts.attrs["skipped_candidate_rounds"]
    assert len(gain) + skipped == parts.attrs["residual_candidates"] and parts.attrs["mart_volumes"] == 1 + len(gain)
    assert 12 * parts.attrs["residual_candidates_min_gain"] < 1
    assert all(g > 0 for g in gain[:-1]) and (gain[-1] == 0) == (skipped > 0)
    split = sum(parts.attrs[k] for k in ("seconds_mart", "seconds_patches", "seconds_fit"))
    assert 0 < split <= parts.attrs["seconds"]
    # the split by step: every image is counted in exactly one step, and the steps' times within the fit's
    from lfstudy.reconstruct.ipr.fit import STEPS

    steps = {k: parts.attrs[f"particle_images_{k}"] for k in STEPS}
    assert sum(steps.values()) == parts.attrs["particle_images"]
    assert steps["shake"] > 0 and steps["polish"] > 0 and steps["image_calibration"] == 0
    step_s = [parts.attrs[f"seconds_step_{k}"] for k in STEPS]
    assert min(step_s) >= 0 and 0 < sum(step_s) <= parts.attrs["seconds"]
    assert parts.attrs["seconds_step_candidates"] >= parts.attrs["seconds_mart"]


def test_gauss_newton_step_finds_a_shifted_particle():
    """One linearised step (``_sweep``) from a particle's image at p towards data rendered at p + s
    (s = 0.3 voxel in x and z) goes the right way with either finite-difference Jacobian; what it leaves of
    the offset (in voxels) is 0.31 with central differences and 0.50 with forward ones (measured)."""
    from lfstudy.reconstruct._shake_kernels import lit_pixels
    from lfstudy.reconstruct.ipr import _sweep

    vox = np.array([0.125, 0.125, 0.4])
    delta = 0.1 * vox
    p = np.array([0.21, -0.13, 1.6])
    s = np.array([0.3, 0.0, -0.3]) * vox
    true, _, tr0, tc0, tshp = particle_patches(CAM, *(p + s)[:, None])
    left = {}
    for jacobian, signs in (("central", (1.0, -1.0)), ("forward", (1.0,))):
        tr = np.array([[d * delta[i] if a == i else 0.0 for a in range(3)] for i in range(3) for d in signs])
        buf, offs, r0, c0, shp = particle_patches(CAM, *p[:, None], trials=tr)
        res = np.zeros((300, 300))
        res[tr0[0] : tr0[0] + tshp[0, 0], tc0[0] : tc0[0] + tshp[0, 1]] = 2.0 * true.reshape(tshp[0])
        out = np.zeros((1, 9))
        mask = np.ones((300, 300), np.uint8)
        lit = lit_pixels(mask, buf, offs, r0, c0, shp, len(tr) + 1)
        _sweep(res, mask, buf, offs, r0, c0, shp, *lit, np.zeros(1), delta, vox, 0.0, True, jacobian == "central", out)
        assert np.all(np.sign(out[0, [0, 2]]) == np.sign(s[[0, 2]])) and out[0, 3] > 0
        left[jacobian] = np.linalg.norm((s - out[0, :3]) / vox) / np.linalg.norm(s / vox)
    assert left["central"] < 0.4 and left["forward"] < 0.6 and left["central"] < left["forward"], left


def test_gauss_seidel_kernels_on_the_lit_pixels_give_the_bytes_of_the_whole_box():
    """``_sweep`` and ``_choose`` visit each patch's lit pixels only (``lit_pixels``): the residual, the steps,
    intensities, variances and choices are the bytes they give when handed every masked pixel of each box (the
    kernels as they were, looping over the whole box), for overlapping particles in and out of focus, part of
    the sensor masked out. The lit pixels are a few per cent of the boxes."""
    from lfstudy.reconstruct._shake_kernels import _choose, _sweep, lit_pixels

    rng = np.random.default_rng(5)
    n = 24
    pts = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), rng.uniform(-3, 3, n)])
    vox = np.array([0.125, 0.125, 0.4])
    delta = 0.1 * vox
    tr = np.array([[d * delta[i] if a == i else 0.0 for a in range(3)] for i in range(3) for d in (1.0, -1.0)])
    buf, offs, r0, c0, shp = particle_patches(CAM, *pts.T, trials=tr)
    bn, on, r0n, c0n, shpn = particle_patches(CAM, *(pts + 0.03).T)
    mask = np.ones((300, 300), np.uint8)
    mask[:, 170:190] = 0
    data = (
        rng.normal(0.0, 0.002, (300, 300)) + render_exact(CAM, make_field(*(pts + 0.02).T, np.full(n, 1.1)), 1).values
    )
    lit = lit_pixels(mask, buf, offs, r0, c0, shp, 7)
    boxes = [np.arange(int(h * w)) for h, w in shp]
    every = [b[mask[r0[i] + b // shp[i, 1], c0[i] + b % shp[i, 1]] != 0] for i, b in enumerate(boxes)]
    whole = np.concatenate(every).astype(np.int32)
    stop = np.cumsum([len(e) for e in every])
    whole_lists = (whole, stop - [len(e) for e in every], stop, np.array([len(e) for e in every]))
    assert np.array_equal(lit[3], whole_lists[3])  # the masked pixels per box
    assert 0 < (lit[2] - lit[1]).sum() < 0.2 * whole.size
    got = {}
    for name, lists in (("lit", lit), ("whole", whole_lists)):
        res = data.copy()
        out = np.zeros((n, 9))
        _sweep(res, mask, buf, offs, r0, c0, shp, *lists, np.ones(n), delta, vox, 0.01, True, True, out)
        pick = np.zeros((n, 2))
        res2 = data.copy()
        _choose(res2, mask, buf, offs, r0, c0, shp, *lists[:3], 7, np.ones(n), bn, on, r0n, c0n, shpn, pick)
        got[name] = (res.tobytes(), out.tobytes(), res2.tobytes(), pick.tobytes())
    assert got["lit"] == got["whole"]


def test_polish_stencil_drops_are_the_exact_residuals():
    """``_stencil`` (the polish's kernel): for each stencil position the drop of ‖R‖² at the best intensity,
    a²/uu with the particle added back, equal to numpy's on the same images; the residual is left as it was;
    data rendered at one stencil position is that position's drop, the largest; the residual variance is
    0 there (noise-free)."""
    from lfstudy.reconstruct.ipr import _stencil

    vox = np.array([0.125, 0.125, 0.5])
    p = np.array([0.07, -0.11, 0.2])  # near the focal plane, as the particles the polish moves
    st = np.array([[0, 0, 0], [0.25, 0, 0], [0, -0.25, 0], [0, 0, 0.5], [0, 0, -0.5]]) * vox
    buf, offs, r0, c0, shp = particle_patches(CAM, *(p + st).T)
    true = 3
    res = np.zeros((300, 300))
    for j, amp in ((true, 2.0), (0, -0.5)):  # data 2·U_true; the particle now at p with intensity 0.5
        h, w = shp[j]
        res[r0[j] : r0[j] + h, c0[j] : c0[j] + w] += amp * buf[offs[j] : offs[j + 1]].reshape(h, w)
    mask = np.ones((300, 300), np.uint8)
    before = res.copy()
    out = np.zeros((1, len(st) + 1))
    _stencil(res, mask, buf, offs, r0, c0, shp, len(st), np.array([0.5]), out)
    assert np.array_equal(res, before)
    back = before.copy()
    back[r0[0] : r0[0] + shp[0, 0], c0[0] : c0[0] + shp[0, 1]] += 0.5 * buf[offs[0] : offs[1]].reshape(shp[0])
    for j in range(len(st)):
        u = np.zeros((300, 300))
        u[r0[j] : r0[j] + shp[j, 0], c0[j] : c0[j] + shp[j, 1]] = buf[offs[j] : offs[j + 1]].reshape(shp[j])
        a, uu = np.sum(back * u), np.sum(u * u)
        assert out[0, j] == pytest.approx(max(a, 0.0) ** 2 / uu, rel=1e-9)
    assert out[0].argmax() == true and out[0, true] == pytest.approx(np.sum(back**2), rel=1e-9)
    assert out[0, -1] > 0  # the current position does not fit the data: a residual remains


def test_spot_pitches_is_the_geometric_blur_circle():
    """The defocus spot on the lenslet array: none at the focal plane, rad·si·|z|/(so·(so + z)) in pitches
    (thin lens, si = so here), the same on both sides to first order."""
    from lfstudy.reconstruct.ipr import _spot_pitches

    z = np.array([0.0, 0.5, -0.5, 3.0])
    r = _spot_pitches(CAM, z)
    rad = CAM.aperture_diameter / 2.0
    np.testing.assert_allclose(r, rad * CAM.si * np.abs(z) / (CAM.so * (CAM.so + z)) / CAM.lenslet_pitch, atol=1e-12)
    assert r[0] == pytest.approx(0.0, abs=1e-12) and r[1] == pytest.approx(r[2], rel=0.02)


def test_shake_active_set_sits_out_only_the_settled(scene, fitted):
    """``shake_settle``: a particle whose last shake moved it less than that sits out the next shake unless a
    particle near it moved, was added or removed (``_unwoken``); a particle that sat out keeps its position and
    intensity, so with every particle settled (shake_settle 1 voxel: max_step is 0.5) and nothing removed, a
    second iteration leaves the list of one iteration byte for byte; the default shakes every particle."""
    from lfstudy.reconstruct.ipr import _SETTLE_RADIUS, _unwoken

    vox = np.array([0.1, 0.1, 0.4])
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.5, 0.5, 0.0]])
    near = (_SETTLE_RADIUS - 0.1) * vox  # within the radius on each axis scaled by its own voxel
    events = np.array([[0.0, 0.0, 0.0] + near * [1, 0, 0], [0.0, 0.0, 2.0] - near * [0, 0, 1]])
    assert _unwoken(np.array([True, True, True, False]), xyz, events, vox).tolist() == [False, True, False, False]
    assert _unwoken(np.ones(4, bool), xyz, np.zeros((0, 3)), vox).all()
    assert fitted[1].attrs["shake_sat_out"] == [0] * fitted[1].attrs["iterations"]
    _, inputs = scene
    kw = {"residual_candidates": 0, "polish": 0, "min_intensity": 0.0, "mart_iterations": 0}
    one = ipr_particles(inputs, iterations=1, **kw)
    two = ipr_particles(inputs, iterations=2, shake_settle=1.0, **kw)
    assert one.attrs["shake_sat_out"] == [0] and two.attrs["shake_sat_out"] == [0, len(one.x)] and len(one.x) > 5
    for v in ("x", "y", "z", "intensity"):
        assert np.array_equal(two[v].values, one[v].values)


def test_split_recovers_a_close_pair_and_keeps_a_single_particle():
    """``_split_pairs`` (``split``): two particles 1 voxel apart in z near the focal plane, fitted as one of twice
    the intensity between them, come back as two within half a voxel of the true ones, the residual's drop kept
    in ``res``; the same bright particle alone is not split (the pair does not lower its residual by the penalty).
    Shot noise of ``PHOTONS`` per particle; the other particles (intensity 1) set the median."""
    from lfstudy.reconstruct.ipr import _split_pairs

    vox = np.array([0.125, 0.125, 0.5])
    mid = np.array([0.07, -0.11, 0.15])
    pair = mid + np.array([[0, 0, 0.5], [0, 0, -0.5]]) * vox
    others = np.array([(-0.7, 0.6, 1.5), (0.7, 0.6, -1.5), (-0.7, -0.6, 2.5)])
    render = lambda pos: particle_patches(CAM, *np.asarray(pos).T, accuracy="fast")  # noqa: E731
    mask = np.ones((300, 300), np.uint8)

    def image(pos, amp):
        img = np.zeros((300, 300))
        buf, offs, r0, c0, shp = render(pos)
        for i, a in enumerate(amp):
            h, w = shp[i]
            img[r0[i] : r0[i] + h, c0[i] : c0[i] + w] += a * buf[offs[i] : offs[i + 1]].reshape(h, w)
        return img

    rng = np.random.default_rng(5)
    fit = np.vstack([mid, others])
    for true, split in ((np.vstack([pair, others]), True), (np.vstack([mid, others]), False)):
        amp = np.array([1.0, 1.0, 1.0, 1.0] if split else [2.0, 1.0, 1.0, 1.0])
        amp = np.concatenate([[1.0], amp]) if split else amp
        data = rng.poisson(PHOTONS * image(true, amp)) / PHOTONS
        inten = np.array([2.0, 1.0, 1.0, 1.0])
        res = data - image(fit, inten)
        before = np.sum(res**2)
        xyz, out, n = _split_pairs(render, res, mask, fit, inten, vox, floor=0.2, penalty=16.0, ratio=1.3)
        assert n == int(split) and len(xyz) == 4 + n
        np.testing.assert_array_equal(xyz[1:4], others)  # the others are not tried (not bright)
        if split:
            d = np.abs(xyz[[0, 4]][:, None, :] - pair[None]) / vox
            assert np.all(np.min(np.linalg.norm(d, axis=2), axis=1) < 0.5), xyz[[0, 4]]
            assert np.all(out[[0, 4]] > 0.6) and np.all(out[[0, 4]] < 1.4)  # about one particle each
            assert np.sum(res**2) < before  # the residual kept is the split's
            np.testing.assert_allclose(res, data - image(xyz, out), atol=1e-9)
        else:
            assert np.sum(res**2) == before and np.array_equal(out, inten)


@pytest.mark.parametrize("kind", ["case", "stack"])
def test_residual_volume_candidates_find_the_particles(scene, kind):
    """The residual rounds' other candidate volumes (``residual_volume``: MART on the case grid, the residual's
    focal stack) find the particles the first volume leaves out. A high ``peak_threshold`` makes the first MART
    volume give only its brightest peaks, so most particles must come from the residual rounds."""
    pts, inputs = scene
    parts = ipr_particles(inputs, residual_volume=kind, peak_threshold=0.6, iterations=6, polish=0)
    a = parts.attrs
    assert a["residual_volume"] == kind and a["mart_volumes"] == 1 + len(a["candidates_added"])
    vox = np.array(inputs.grid.voxel_size()[::-1])
    fit = np.column_stack([parts[v].values for v in ("x", "y", "z")])
    d = np.linalg.norm((fit[:, None, :] - pts[None]) / vox, axis=2)
    found = d.min(axis=0) < 0.5
    first = ipr_particles(inputs, residual_candidates=0, peak_threshold=0.6, iterations=1, polish=0)
    assert found.sum() >= 7 and found.sum() >= first.sizes["particle"] + 3, (found.sum(), first.sizes["particle"])
    assert sum(a["candidates_added"]) >= 3
    assert (d.min(axis=1) >= 0.5).sum() <= 3  # ghosts


def test_residual_volume_bad_value_names_the_setting(scene):
    _, inputs = scene
    with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr\.residual_volume = 'voxels': allowed values"):
        ipr_particles(inputs, residual_volume="voxels")
    schema = method_schemas()["ipr"]["properties"]["residual_volume"]
    assert schema["enum"] == ["mart", "case", "stack"] and schema["default"] == "mart"


@pytest.mark.parametrize("kind", ["case", "stack"])
def test_residual_volume_same_bytes_whatever_the_threads(scene, kind):
    import numba

    _, inputs = scene
    kw = {"residual_volume": kind, "iterations": 2, "residual_candidates": 2, "polish": 0}
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = ipr_particles(inputs, **kw)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = ipr_particles(inputs, **kw)
    finally:
        numba.set_num_threads(old)
    for v in ("x", "y", "z", "intensity"):
        assert np.array_equal(one[v].values, two[v].values)
    assert one.attrs["candidates_added"] == two.attrs["candidates_added"] and len(one.attrs["candidates_added"]) >= 1


def test_the_batch_changes_the_fit_by_rounding_only(scene):
    """``batch`` (particles rendered at once) sets only the patch memory and the cost: the shake's Gauss–Seidel
    sweep, the exact choice, the polish's runs and the intensities (faint candidates added back once all are
    fitted) go particle after particle whatever the batches. A fit in batches of 3 (the polish stencil's 7 x 3
    images a call) gives the default's particles up to rounding (a patch's scratch is sized by its batch: the
    images agree to ~1e-15 of their peak)."""
    _, inputs = scene
    kw = {"iterations": 3, "residual_candidates": 2}
    one, small = ipr_particles(inputs, **kw), ipr_particles(inputs, batch=3, **kw)
    assert one.sizes["particle"] == small.sizes["particle"] >= 8
    for v in ("x", "y", "z"):
        np.testing.assert_allclose(one[v].values, small[v].values, rtol=0, atol=1e-8)
    np.testing.assert_allclose(one.attrs["residual_norm"], small.attrs["residual_norm"], rtol=1e-9)


def test_the_shake_reuses_the_images_of_particles_that_stayed(scene, monkeypatch):
    """A particle's images depend on its position alone: where a shake kept a particle where it was, the next
    shake takes its seven images from the cache instead of rendering them. Without the chord method
    (``_CHORD`` 0) the fit is the one without the cache (up to the rounding of a patch's scratch, sized by its
    batch), with fewer images rendered; the cache is bounded (``_CACHE_BYTES``: 0 keeps none) and the last
    iteration keeps none. With the chord method (the default) more images are reused, the particles the same
    within 0.05 voxel."""
    from lfstudy.reconstruct.ipr import shake

    _, inputs = scene
    kw = {"iterations": 4, "residual_candidates": 2}
    chord = ipr_particles(inputs, **kw)
    monkeypatch.setattr(shake, "_CHORD", 0.0)
    cached = ipr_particles(inputs, **kw)
    monkeypatch.setattr(shake, "_CACHE_BYTES", 0.0)
    plain = ipr_particles(inputs, **kw)
    assert plain.attrs["particle_images_reused"] == 0
    assert 0 < cached.attrs["particle_images_reused"] < chord.attrs["particle_images_reused"]
    assert cached.attrs["particle_images"] + cached.attrs["particle_images_reused"] == plain.attrs["particle_images"]
    assert cached.sizes["particle"] == plain.sizes["particle"] == chord.sizes["particle"] >= 8
    for v in ("x", "y", "z", "intensity"):
        np.testing.assert_allclose(cached[v].values, plain[v].values, rtol=0, atol=1e-8)
    np.testing.assert_allclose(cached.attrs["residual_norm"], plain.attrs["residual_norm"], rtol=1e-9)
    vox = np.array(inputs.grid.voxel_size()[::-1])
    for a, v in enumerate(("x", "y", "z")):
        assert np.abs(chord[v].values - plain[v].values).max() < 0.05 * vox[a]


def test_a_recentred_block_keeps_the_trials_and_refuses_light_outside_its_patch():
    """The chord method's block: the first image replaced by the new one (another patch, cropped into the block's),
    the trials kept; None where the new image has light outside the block's patch."""
    from lfstudy.reconstruct.ipr.shake import _recentred

    block = np.arange(3 * 4 * 5, dtype=float)  # three 4 x 5 images in the patch at row 10, column 20
    new = np.zeros((3, 3))
    new[1, 1] = 7.0  # lit at sensor (12, 22): inside
    out = _recentred(block, 10, 20, np.array([4, 5]), new.ravel(), (11, 21, 3, 3))
    centre = np.zeros((4, 5))
    centre[2, 2] = 7.0
    assert np.array_equal(out[:20], centre.ravel()) and np.array_equal(out[20:], block[20:])
    new[2, 2] = 1.0  # lit at sensor (13, 23): inside
    assert _recentred(block, 10, 20, np.array([4, 5]), new.ravel(), (11, 21, 3, 3)) is not None
    assert _recentred(block, 10, 20, np.array([4, 5]), new.ravel(), (12, 22, 3, 3)) is None  # (14, 24): outside


def test_a_cached_image_is_used_only_at_its_own_position_and_model():
    """The cache's check: the same position, trials and image model (by identity: a calibration replaces it)."""
    from lfstudy.reconstruct.image_model import ImageModel
    from lfstudy.reconstruct.ipr.shake import _Cached

    model, tr = ImageModel(), np.array([[0.01, 0.0, 0.0], [-0.01, 0.0, 0.0]])
    c = _Cached(np.array([0.1, 0.2, 0.3]), np.array([0.1, 0.2, 0.3]), tr, model, 0, 0, np.array([2, 2]), np.zeros(12))
    assert c.valid([0.1, 0.2, 0.3], tr, model) and c.valid([0.1, 0.2, 0.3], tr.copy(), model)
    assert not c.valid([0.1, 0.2, 0.3 + 1e-12], tr, model)
    assert not c.valid([0.1, 0.2, 0.3], tr * 2, model)
    assert not c.valid([0.1, 0.2, 0.3], tr, ImageModel())


def test_polish_screen_skips_only_sharp_minima(monkeypatch):
    """The polish's screen (``_POLISH_SCREEN``): a particle fitted where its data is (a sharp minimum: every axis
    neighbour of the stencil far less likely) renders only the current and axis positions and stays where the
    whole stencil would leave it; one 0.25 voxel off its data renders the whole stencil and moves as it would
    without the screen. Two well-separated near-focus particles, data with 1 % noise."""
    from lfstudy.reconstruct.ipr import polish as pol
    from lfstudy.reconstruct.ipr.patches import _FitImages

    vox = np.array([0.125, 0.125, 0.5])
    true = np.array([[-0.6, -0.5, 0.3], [0.6, 0.5, -0.2]])
    fit = true + np.array([[0.0, 0.0, 0.0], [0.25, 0.0, 0.0]]) * vox
    buf, offs, r0, c0, shp = particle_patches(CAM, *true.T)
    data = np.zeros((300, 300))
    for j in range(2):
        data[r0[j] : r0[j] + shp[j, 0], c0[j] : c0[j] + shp[j, 1]] += buf[offs[j] : offs[j + 1]].reshape(shp[j])
    data += 0.01 * data.max() * np.random.default_rng(3).standard_normal(data.shape)
    stencil, n_axes = pol._polish_stencil(vox)
    assert n_axes == 9 and len(stencil) == 45 and np.all(np.count_nonzero(stencil[1:n_axes], axis=1) == 1)

    def step(screen: float):
        monkeypatch.setattr(pol, "_POLISH_SCREEN", screen)
        images = _FitImages(CAM, np.ones((300, 300), np.uint8), "fast", 256)
        amp = np.ones(2)
        res = data.copy()
        images.add_images(fit, amp, res, -1.0)
        moved, _ = pol._polish_step(images, fit.copy(), amp, res, stencil, n_axes)
        return moved, images.clock["images"]

    moved, n_img = step(pol._POLISH_SCREEN)
    full, n_full = step(np.inf)
    # both: the residual's 2 images, the 9 axis positions, 2 moved back and 2 refitted; the second particle
    # also the rest of the stencil, its current position again first
    rest = 1 + len(stencil) - n_axes
    assert n_img == 2 + 2 * n_axes + rest + 4 and n_full == n_img + rest
    np.testing.assert_allclose(moved[0], fit[0], atol=0.02 * vox.min())
    np.testing.assert_allclose(moved, full, atol=0.02 * vox.min())
    assert abs(moved[1, 0] - true[1, 0]) < abs(fit[1, 0] - true[1, 0])  # moved towards its data


def test_polish_moves_particles_sharing_lenslets_one_after_another(monkeypatch):
    """The polish is Gauss–Seidel: the particles go in runs whose patches do not overlap, each on the residual
    the runs before it left. Four pairs of near-focus particles one voxel apart in z (intensities 1.2 and 0.8),
    each pair fitted as two particles at its midpoint: one after the other, one goes to each true particle and
    the residual falls to about a quarter; moved all at once (the old polish), both see the brighter one's data
    and move into it, and the residual stays twice as high."""
    from lfstudy.reconstruct.ipr import polish as pol
    from lfstudy.reconstruct.ipr.patches import _FitImages

    vox = np.array([0.125, 0.125, 0.5])
    rng = np.random.default_rng(0)
    lateral = ((-0.5, -0.45), (0.55, 0.5), (-0.5, 0.55), (0.45, -0.5))
    mid = np.array([[x, y, rng.uniform(-0.3, 0.3)] for x, y in lateral])
    half = np.array([0.0, 0.0, 0.5 * vox[2]])
    true = np.vstack([mid - half, mid + half])
    inten = np.r_[np.full(4, 1.2), np.full(4, 0.8)]
    buf, offs, r0, c0, shp = particle_patches(CAM, *true.T)
    data = np.zeros((300, 300))
    for j in range(len(true)):
        image = inten[j] * buf[offs[j] : offs[j + 1]].reshape(shp[j])
        data[r0[j] : r0[j] + shp[j, 0], c0[j] : c0[j] + shp[j, 1]] += image
    data += 0.01 * data.max() * rng.standard_normal(data.shape)
    fit = np.repeat(mid, 2, axis=0)
    stencil, n_axes = pol._polish_stencil(vox)
    images = _FitImages(CAM, np.ones((300, 300), np.uint8), "fast", 256)
    runs = pol._runs(images.boxes(fit), 32)
    assert sorted(np.concatenate(runs).tolist()) == list(range(len(fit)))  # every particle in one run
    assert len(runs) == 2 and all(len(set(r // 2)) == len(r) for r in runs)  # a pair shares its box: never one run

    def polish(rounds: int = 3):
        amp, res, xyz = np.ones(len(fit)), data.copy(), fit.copy()
        images.add_images(xyz, amp, res, -1.0)
        for _ in range(rounds):
            xyz, amp = pol._polish_step(images, xyz, amp, res, stencil, n_axes)
        return xyz, np.linalg.norm(res) / np.linalg.norm(data)

    xyz, rel = polish()
    d = np.abs(xyz[:, None, :] - true[None]) / vox  # (fitted, true, axis) in voxels
    near = np.all(d <= 0.3, axis=2)
    assert near.any(axis=0).sum() >= 7  # seven of the eight true particles have a fitted one within 0.3 voxel
    monkeypatch.setattr(pol, "_runs", lambda boxes, most: [np.arange(len(boxes))])
    _, rel_together = polish()
    assert rel < 0.2 and rel_together > 2 * rel


def test_a_warm_start_replaces_the_first_candidate_volume(scene):
    """``start``: the fit begins from the given positions instead of the first MART volume's peaks (one volume
    fewer, ``warm_start`` their count); from the true positions it keeps every particle within half a voxel;
    a position more than a voxel outside the grid is dropped (the same fit, byte for byte); anything but finite
    (n, 3) positions is refused, naming ``start``."""
    pts, inputs = scene
    kw = {"iterations": 2, "residual_candidates": 1, "polish": 0}
    cold = ipr_particles(inputs, **kw)
    warm = ipr_particles(inputs, start=pts, **kw)
    assert cold.attrs["warm_start"] == 0 and warm.attrs["warm_start"] == len(pts)
    assert warm.attrs["mart_volumes"] == cold.attrs["mart_volumes"] - 1
    vox = np.array(inputs.grid.voxel_size()[::-1])
    fit = np.column_stack([warm[v].values for v in ("x", "y", "z")])
    assert (np.abs(fit[None] - pts[:, None]) / vox).max(axis=2).min(axis=1).max() < 0.5  # every true one found
    far = ipr_particles(inputs, start=np.vstack([pts, [[50.0, 0.0, 0.0]]]), **kw)
    for v in ("x", "y", "z", "intensity"):
        assert np.array_equal(far[v].values, warm[v].values)
    for bad in (pts[:, :2], np.where(np.arange(3) == 1, np.nan, pts)):
        with pytest.raises(ReconstructionError, match=r"reconstruct\.ipr: start must be finite positions"):
            ipr_particles(inputs, start=bad, **kw)


def test_a_warm_start_fits_its_intensities_jointly():
    """``fit_intensity(..., sweeps)``: at the true positions of twenty particles crowded behind a few lenslets
    (intensities 0.5-1.5, exact images, no noise) one Gauss-Seidel sweep gives the first particle of each
    overlapping group its neighbours' light and leaves much of the image unexplained; the warm start's
    ``_START_SWEEPS`` sweeps converge towards the joint fit: the residual falls several-fold and the
    intensities come close to the true ones."""
    from lfstudy.reconstruct.ipr.patches import _FitImages
    from lfstudy.reconstruct.ipr.polish import _START_SWEEPS

    rng = np.random.default_rng(4)
    true = np.column_stack([rng.uniform(-0.3, 0.3, 20), rng.uniform(-0.3, 0.3, 20), rng.uniform(-2.0, 2.0, 20)])
    inten = rng.uniform(0.5, 1.5, 20)
    buf, offs, r0, c0, shp = particle_patches(CAM, *true.T)
    data = np.zeros((300, 300))
    for j in range(len(true)):
        data[r0[j] : r0[j] + shp[j, 0], c0[j] : c0[j] + shp[j, 1]] += inten[j] * buf[offs[j] : offs[j + 1]].reshape(
            shp[j]
        )
    images = _FitImages(CAM, np.ones((300, 300), np.uint8), "fast", 8)  # batches of 8: the sweeps span batches

    def fit(sweeps: int) -> tuple[np.ndarray, float]:
        res = data.copy()
        amp = images.fit_intensity(true, res, -1.0, sweeps)
        return amp, float(np.linalg.norm(res) / np.linalg.norm(data))

    amp1, rel1 = fit(1)
    amp, rel = fit(_START_SWEEPS)
    assert rel1 > 0.1 and rel < rel1 / 3
    assert np.abs(amp - inten).max() < 0.5 * np.abs(amp1 - inten).max()
    assert np.median(np.abs(amp - inten) / inten) < 0.05


def test_a_warm_start_takes_its_depths_from_the_data():
    """``_scan_depths``: particles started 1.25 voxel above and 1.5 voxel below their data's depth (a
    predictor's error in w) come back to within a quarter voxel of it, whatever the start, before the shake;
    the residual is left exact (the data less the moved particles' images)."""
    from lfstudy.reconstruct.ipr.patches import _FitImages
    from lfstudy.reconstruct.ipr.polish import _scan_depths

    vox = np.array([0.125, 0.125, 0.5])
    true = np.array([[-0.6, -0.5, 1.3], [0.6, 0.5, -2.1]])
    start = true + np.array([[0.0, 0.0, 1.25], [0.0, 0.0, -1.5]]) * vox
    images = _FitImages(CAM, np.ones((300, 300), np.uint8), "fast", 256)
    data = np.zeros((300, 300))
    images.add_images(true, np.ones(2), data, 1.0)
    res = data.copy()
    amp = images.fit_intensity(start, res, -1.0)
    moved, inten = _scan_depths(images, start, amp, res, vox)
    assert np.all(np.abs(moved[:, 2] - true[:, 2]) <= 0.25 * vox[2] + 1e-12) and np.all(moved[:, :2] == start[:, :2])
    back = data.copy()
    images.add_images(moved, inten, back, -1.0)
    np.testing.assert_allclose(res, back, atol=1e-12)
