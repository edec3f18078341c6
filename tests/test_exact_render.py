"""The exact renderer: the expected Monte-Carlo image without rays (thesis sec. 4.1–4.3, eq. 4.14)."""

from __future__ import annotations

import doctest
import math

import numba
import numpy as np
import pytest
from scipy.special import ndtr

from lfstudy.optics import PlenopticCamera
from lfstudy.simulate import exact as ex
from lfstudy.simulate import raytrace as rt
from lfstudy.simulate.particles import make_field, pinhole_spans, seed_particles

#: Table 4.3 optics on a small sensor with an odd lenslet count (9 x 7): a lenslet on the axis.
CAM = PlenopticCamera(150, 110, 0.0074, 0.125, 0.5, 50.0, -1.0)


def _field(*pts, intensity=1.0):
    p = np.atleast_2d(np.asarray(pts, dtype=float))
    return make_field(p[:, 0], p[:, 1], p[:, 2], np.full(len(p), intensity))


def _omega_fraction(cam, x, y, z):
    rad = cam.aperture_diameter / 2
    ref = 2 * math.pi * (1 - cam.so / math.hypot(cam.so, rad))
    return rt.solid_angle(cam, x, y, z)[0] / ref


def test_in_focus_particle_on_a_lenslet_axis_fills_exactly_that_lenslet():
    """In focus the whole aperture lands in one lenslet: its image is the aperture disc
    (radius pl/2 at the matched f-number), uniform, blurred only by σl at its rim."""
    n = 1000
    img = ex.render_exact(CAM, _field((0.0, 0.0, 0.0)), n)
    w = img.values
    x, y = np.meshgrid(img["x"].values, img["y"].values)
    r = np.hypot(x, y)  # the central lenslet's image is centred on the axis
    rho = CAM.aperture_diameter / 2 * CAM.lenslet_focal_length * (1 / CAM.main_focal_length - 1 / CAM.so)
    assert rho == pytest.approx(CAM.lenslet_pitch / 2, rel=1e-12)
    half_diag = CAM.pixel_pitch / math.sqrt(2)
    tail = 6 * CAM.sigma_sensor_plane
    inside = r + half_diag + tail < rho  # pixel and its blur wholly inside the disc
    outside = r - half_diag - tail > rho
    assert inside.sum() > 100 and outside.sum() > 10_000
    total = n * _omega_fraction(CAM, 0.0, 0.0, 0.0)
    uniform = total * CAM.pixel_pitch**2 / (math.pi * rho**2)
    np.testing.assert_allclose(w[inside], uniform, rtol=1e-7)
    assert np.abs(w[outside]).max() < 1e-9 * uniform
    assert w.sum() == pytest.approx(total, rel=1e-9)
    # Nothing beyond the lenslet's own square image (its neighbours get no light in focus): pixels
    # whose nearest edge lies more than the σl tail beyond the square are dark.
    reach = CAM.lenslet_pitch / 2 + tail + CAM.pixel_pitch / 2
    block = (np.abs(x) <= reach) & (np.abs(y) <= reach)
    assert w[~block].sum() < 1e-9 * total


@pytest.mark.parametrize(
    "pt",
    [(0.0, 0.0, 0.0), (0.12, -0.08, 1.3), (-0.2, 0.15, -2.1), (0.0625, 0.0625, 0.0), (0.03, 0.01, -3.0)],
)
def test_total_is_the_collected_solid_angle_fraction(pt):
    """Eq. 4.14: a particle's recorded total is n·Ω_i/Ω_ref (times its intensity), to 1e-6.

    Every point keeps its light on this small sensor (the last one spreads over 44 lenslets;
    further out, e.g. z = +3.5 mm, part of the edge lenslets' images falls off the sensor,
    which the Monte-Carlo comparison below covers)."""
    n = 25_000
    img = ex.render_exact(CAM, _field(pt, intensity=1.7), n)
    expected = 1.7 * n * _omega_fraction(CAM, *pt)
    assert img.values.sum() == pytest.approx(expected, rel=1e-6)
    assert img.attrs["intensity_traced"] == pytest.approx(expected, rel=1e-12)
    assert img.attrs["intensity_lost"] < 1e-6 * expected
    # match_ray_counts: the Monte-Carlo's integer ray count round(n·Ω_i/Ω_ref) instead.
    mc_n = rt.ray_counts(CAM, _field(pt), n)[0]
    rounded = ex.render_exact(CAM, _field(pt, intensity=1.7), n, match_ray_counts=True)
    assert rounded.values.sum() == pytest.approx(1.7 * mc_n, rel=1e-6)


def _mc_mean(cam, field, n, seeds, **kw):
    imgs = [rt.render(cam, field, n, s, **kw, method="montecarlo") for s in seeds]
    return np.mean([i.values for i in imgs], axis=0), imgs


@pytest.mark.parametrize(
    "pt, label",
    [
        ((0.0, 0.0, 0.0), "in focus"),
        ((0.03, -0.02, 1.0), "+1 mm"),
        ((-0.05, 0.04, -1.0), "-1 mm"),
        ((0.0625, 0.0625, 0.0), "lenslet corner"),
        ((0.5, 0.3, 0.8), "sensor edge"),
    ],
)
def test_exact_is_the_mean_of_monte_carlo_images(pt, label):
    """Per pixel, the mean of K Monte-Carlo images equals the exact image within its standard
    error: z = (mean − exact)/SE with the binomial SE of N rays; mean z² ≈ 1, no outlier."""
    n, seeds = 200_000, range(8)
    field = _field(pt)
    exact = ex.render_exact(CAM, field, n, match_ray_counts=True)
    mean, imgs = _mc_mean(CAM, field, n, seeds)
    nrays = rt.ray_counts(CAM, field, n)[0]
    p = exact.values / nrays  # probability that one ray lands in the pixel
    se = np.sqrt(nrays * p * (1 - p) / len(seeds))
    sel = p * nrays * len(seeds) >= 25  # enough rays for the normal approximation
    z = (mean[sel] - exact.values[sel]) / se[sel]
    assert sel.sum() > 100, label
    assert 0.75 < np.mean(z**2) < 1.3, (label, np.mean(z**2))
    assert np.abs(z).max() < 6.0, label
    # Where the exact image is 0 to double precision no ray lands either.
    assert mean[exact.values < 1e-12 * nrays].sum() == 0.0
    # The accounting of what is lost matches the rays dropped.
    lost_mc = np.mean([i.attrs["intensity_lost"] for i in imgs])
    assert exact.attrs["intensity_lost"] == pytest.approx(lost_mc, abs=5 * math.sqrt(nrays / len(seeds)) + 1e-6)
    if label == "sensor edge":
        assert exact.attrs["intensity_lost_outside_sensor"] > 0.05 * nrays


def test_no_diffraction_is_the_mean_of_monte_carlo_images():
    """With hard lenslet and pixel edges (diffraction off) too."""
    n, seeds = 300_000, range(6)
    field = _field((0.02, 0.01, 1.4))
    exact = ex.render_exact(CAM, field, n, diffraction=False, match_ray_counts=True)
    mean, _ = _mc_mean(CAM, field, n, seeds, diffraction=False)
    nrays = rt.ray_counts(CAM, field, n)[0]
    p = exact.values / nrays
    sel = p * nrays * len(seeds) >= 25
    z = (mean[sel] - exact.values[sel]) / np.sqrt(nrays * p[sel] * (1 - p[sel]) / len(seeds))
    assert 0.75 < np.mean(z**2) < 1.3 and np.abs(z).max() < 6.0


def _gl_panels(a, b, n_panels, order=8):
    """Composite Gauss–Legendre nodes and weights on [a, b] (a, b arrays of one shape: one rule each)."""
    g, w = np.polynomial.legendre.leggauss(order)
    a, b = np.asarray(a, dtype=float)[..., None], np.asarray(b, dtype=float)[..., None]
    edges = a + (b - a) * np.linspace(0.0, 1.0, n_panels + 1)
    c, h = 0.5 * (edges[..., 1:] + edges[..., :-1]), 0.5 * (edges[..., 1:] - edges[..., :-1])
    return (c[..., None] + h[..., None] * g).reshape(*c.shape[:-1], -1), (h[..., None] * w).reshape(*c.shape[:-1], -1)


def _reference(cam, px, py, pz):
    """Independent brute force (Fubini, not Green's theorem): E_P = (1/πρ²) Σ_k ∫ dy m_y b_j(y)
    ∫_{chord(y)} m_x b_k(x) dx over each lenslet's aperture image, with erf windows. The disc's
    y runs over Gauss–Legendre panels in the angle φ (y = c + ρ sin φ, chord ±ρ cos φ); the chord
    integral is C_k(x_b) − C_k(x_a), C_k(x) = ∫^x m_x·b_k over pixel column k's blurred support
    (Gauss–Legendre panels of 8 nodes, none wider than 3 of the narrowest blur, σl or σm/|κ|:
    ∫Φ over 3σ with 8 nodes is exact to ~1e-11 σ)."""
    so, si, fm, fl = cam.so, cam.si, cam.main_focal_length, cam.lenslet_focal_length
    rad, pl, pp = cam.aperture_diameter / 2, cam.lenslet_pitch, cam.pixel_pitch
    sm, sl = cam.sigma_lenslet_plane, cam.sigma_sensor_plane
    cx0, cy0 = (cam.n_lenslets_x - 1) / 2, (cam.n_lenslets_y - 1) / 2
    d = so + pz
    c1 = 1 / d - 1 / fm
    t0x, t0y = -px / d, -py / d
    rho, kap = rad * fl * abs(c1), (1 + si * c1) / (fl * c1)
    g0x, g0y = si * t0x, si * t0y
    sig = min(sl, sm / abs(kap))  # the narrowest blur on the sensor
    xe = -cam.sensor_width / 2 + np.arange(cam.n_pixels_x + 1) * pp
    ye = cam.sensor_height / 2 - np.arange(cam.n_pixels_y + 1) * pp
    assert 7 * sl < pp
    lo_k, hi_k = xe[:-1] - 7 * sl, xe[1:] + 7 * sl  # column k's blurred support
    n_col = math.ceil((hi_k[0] - lo_k[0]) / (3.0 * sig))
    phi, wphi = _gl_panels(-math.pi / 2, math.pi / 2, math.ceil(math.pi * rho / (3.0 * sig)))

    def window(u, e1):  # P(u + σm·Z ∈ [e1, e1 + pl])
        return ndtr((e1 + pl - u) / sm) - ndtr((e1 - u) / sm)

    img = np.zeros((cam.n_pixels_y, cam.n_pixels_x))
    for li in range(cam.n_lenslets_y):
        for lj in range(cam.n_lenslets_x):
            u1, v1 = (lj - cx0 - 0.5) * pl, (cy0 - li - 0.5) * pl
            cx, cy = (lj - cx0) * pl + fl * t0x, (cy0 - li) * pl + fl * t0y
            ys, wy = cy + rho * np.sin(phi), wphi * rho * np.cos(phi)
            my = window(g0y + kap * (ys - cy), v1)
            if my.max() < 1e-13:
                continue
            by = ndtr((ye[:-1][None, :] - ys[:, None]) / sl) - ndtr((ye[1:][None, :] - ys[:, None]) / sl)
            half = rho * np.cos(phi)

            def cum(e, kk, cx=cx, u1=u1):  # C_k(e) for columns kk (one per node): 0 below the support, full above
                xs, wx = _gl_panels(lo_k[kk], np.clip(e, lo_k[kk], hi_k[kk]), n_col)
                f = window(g0x + kap * (xs - cx), u1)
                f *= ndtr((xe[kk + 1][:, None] - xs) / sl) - ndtr((xe[kk][:, None] - xs) / sl)
                return (wx * f).sum(axis=-1)

            full = cum(hi_k, np.arange(cam.n_pixels_x))
            chord = np.zeros((ys.size, cam.n_pixels_x))
            rows = np.arange(ys.size)
            for sign, e in ((1.0, cx + half), (-1.0, cx - half)):  # C_k(x_b) − C_k(x_a)
                c = full[None, :] * (hi_k[None, :] <= e[:, None])
                kc = np.floor((e - xe[0]) / pp).astype(int)
                for dk in (-1, 0, 1):  # the columns whose blurred support (±7σl < one pixel) holds e
                    k = kc + dk
                    ok = (k >= 0) & (k < cam.n_pixels_x)
                    c[rows[ok], k[ok]] = cum(e[ok], k[ok])
                chord += sign * c
            img += by.T @ ((wy * my)[:, None] * chord)
    return img / (math.pi * rho * rho)


def test_agrees_with_brute_force_quadrature():
    """The closed forms and arc quadrature against a plain 2-D quadrature, to 1e-6 of the peak
    pixel (the module's error budget is ~1e-7): a defocused particle whose aperture image
    crosses several lenslet edges and bands, on a sensor wider than the 4 x 4 lenslet array so
    that no light is lost and the reference must sum to 1."""
    cam = PlenopticCamera(70, 70, 0.0074, 0.125, 0.5, 50.0, -1.0)
    pt = (0.011, -0.017, 0.9)
    exact = ex.render_exact(cam, _field(pt), 1, solid_angle_correction=False).values
    ref = _reference(cam, *pt)
    assert ref.sum() == pytest.approx(1.0, abs=1e-9)  # the reference is converged
    assert np.abs(exact - ref).max() < 1e-6 * ref.max()
    assert np.linalg.norm(exact - ref) < 3e-7 * np.linalg.norm(ref)


def test_continuous_through_focus():
    """Near focus the aperture's image on the lenslet plane (radius rs = R·|1 + si·c1|) shrinks to
    a point and the lenslet windows M_k become constant over it. The defocus branch must meet the
    in-focus one (M_k constant) without a jump: the image changes at first order in rs,
    |ΔE_P| <= rs·sup|∇M|·U (U a fully lit pixel, sup|∇M| <= √2·φ(0)/σm), plus the 1e-7 quadrature
    budget; and the change is linear in rs (from 1e-9 to 1e-5 mm, over four decades)."""
    pt = (0.0612, 0.0608, 0.0)  # near a lenslet corner: four lenslets share the light, M varies most
    ref = ex.render_exact(CAM, _field(pt), 1).values
    rad, sm = CAM.aperture_diameter / 2, CAM.sigma_lenslet_plane
    rho = rad * CAM.lenslet_focal_length * (1 / CAM.main_focal_length - 1 / CAM.so)
    lit = _omega_fraction(CAM, *pt) * CAM.pixel_pitch**2 / (math.pi * rho**2)  # U
    change = {}
    for dz in (1e-11, 1e-9, -1e-9, 1e-7, -1e-7, 1e-5):
        img = ex.render_exact(CAM, _field((pt[0], pt[1], dz)), 1).values
        rs = rad * abs(1 + CAM.si * (1 / (CAM.so + dz) - 1 / CAM.main_focal_length))
        change[dz] = np.abs(img - ref).max() / lit
        assert change[dz] <= math.sqrt(2) * 0.3989 * rs / sm + 1e-7, dz
        change[dz] /= rs / sm
    # First order: the change per unit rs/σm is one constant (no floor from the defocus branch).
    per_rs = np.array([change[dz] for dz in (1e-9, -1e-9, 1e-7, -1e-7, 1e-5)])
    assert per_rs.max() < 1.02 * per_rs.min(), per_rs


def test_layout_attrs_and_accounting_like_render():
    field = seed_particles(CAM, count=30, z_span=4.0, intensity=(0.5, 2.0), seed=4)
    img = ex.render_exact(CAM, field, 3000)
    mc = rt.render(CAM, field, 3000, 5, method="montecarlo")
    assert img.name == "intensity" and img.dims == ("row", "col") and img.shape == mc.shape
    np.testing.assert_array_equal(img["x"].values, mc["x"].values)
    np.testing.assert_array_equal(img["y"].values, mc["y"].values)
    assert img["x"].attrs == mc["x"].attrs and img["y"].attrs == mc["y"].attrs
    for k, v in mc.attrs.items():
        if k.startswith("camera_") or k in ("y_direction", "units", "rays_per_particle", "n_particles"):
            assert img.attrs[k] == v, k
    a = img.attrs
    assert a["method"] == "exact"
    assert a["intensity_traced"] == pytest.approx(a["intensity_recorded"] + a["intensity_lost"])
    assert a["intensity_lost"] == pytest.approx(a["intensity_lost_lenslet_array"] + a["intensity_lost_outside_sensor"])
    assert a["intensity_lost_outside_sensor"] > 0  # field-edge particles spill off the sensor
    assert img.values.sum() == pytest.approx(a["intensity_recorded"], rel=1e-12)
    assert mc.values.sum() == pytest.approx(img.values.sum(), rel=0.01)


def test_bit_identical_across_threads_and_progress_bar(capsys):
    field = seed_particles(CAM, count=60, z_span=4.0, seed=9)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = ex.render_exact(CAM, field, 2000).values
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = ex.render_exact(CAM, field, 2000).values
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(one, two)
    capsys.readouterr()
    shown = ex.render_exact(CAM, field, 2000, progress=True).values
    assert "exact rendering" in capsys.readouterr().err
    assert np.array_equal(one, shown)
    # Another chunking sums in another order: equal to rounding only.
    np.testing.assert_allclose(ex.render_exact(CAM, field, 2000, n_chunks=3).values, one, rtol=1e-12, atol=1e-12)


def test_render_dispatch_and_noise():
    field = _field((0.01, 0.0, 0.5), intensity=2.0)
    e = rt.render(CAM, field, 5000, 3, method="exact")
    assert e.attrs["method"] == "exact" and e.attrs["seed"] == 3
    np.testing.assert_array_equal(e.values, ex.render_exact(CAM, field, 5000).values)
    noisy = rt.render(CAM, field, 5000, 3, method="exact", shot_noise=True, read_noise=1.0)
    assert not np.array_equal(noisy.values, e.values)
    assert np.array_equal(noisy.values, rt.render(CAM, field, 5000, 3, method="exact", shot_noise=True, read_noise=1.0))
    q = rt.render(CAM, field, 5000, 3, method="exact", bit_depth=12)
    assert q.dtype == np.uint16 and q.max() == 4095
    with pytest.raises(ValueError, match="method"):
        rt.render(CAM, field, 10, 0, method="exactly")


def test_pinhole_image_exact_matches_monte_carlo_and_handles_a_rotated_grid():
    """The calibration image (sec. 5.1): every point in focus, so a rotated, shifted grid is exact too."""
    cam = CAM.with_(lenslet_rotation=0.005, lenslet_offset_x=0.01)
    pin = ex.render_pinhole_exact(cam, count=3000, rays_per_point=40, seed=1)
    assert pin.attrs["pinhole_fnumber"] == 16.0 and pin.attrs["camera_main_fnumber"] == 16.0
    np.testing.assert_array_equal(
        pin.values, rt.render_pinhole(cam, count=3000, rays_per_point=40, seed=1, method="exact")
    )
    mc, _ = _mc_mean(
        cam.with_(fnumber=16.0), __import__("lfstudy").simulate.pinhole_field(cam, count=3000, seed=1), 40, [1, 2, 3, 4]
    )
    exact = ex.render_exact(
        cam.with_(fnumber=16.0),
        __import__("lfstudy").simulate.pinhole_field(cam, count=3000, seed=1),
        40,
        match_ray_counts=True,
    ).values
    sel = exact >= 10
    # Many particles per pixel: the Poisson-like SE of a sum of binomials (variance ≤ mean) bounds z.
    z = (mc[sel] - exact[sel]) / np.sqrt(exact[sel] / 4)
    assert np.mean(z**2) < 1.3 and np.abs(z).max() < 6.0
    # Out of focus a grid rotated by more than 5 mrad is refused (up to 5 mrad it is cut into
    # sub-squares: tests/test_imperfections_camera.py).
    with pytest.raises(ValueError, match="lenslet_rotation"):
        ex.render_exact(cam.with_(lenslet_rotation=0.05), _field((0.0, 0.0, 1.0)), 100)


def test_pinhole_image_is_the_expectation_of_its_uniform_field():
    """The pinhole image is the expected image of the uniform field that the Monte-Carlo's random points
    sample. Checked against an independent discretisation of the same integral: a dense regular grid of
    points over the whole field (spacing σm/1.5, the trapezoid rule, which converges spectrally for this
    smooth integrand) rendered with the lenslet-plane blur σm itself, where the pinhole image moves σm
    into the sensor blur and integrates over each lenslet's sharp square with a 3 x 3 Gauss rule."""
    cam = CAM.with_(lenslet_rotation=0.005, lenslet_offset_x=0.01)
    count, n = 3000, 40
    pin = ex.render_pinhole_exact(cam, count=count, rays_per_point=n)
    assert pin.attrs["pinhole_nodes"] == 3 and pin.attrs["sigma_lenslet_plane"] > 0
    f16 = cam.with_(fnumber=16.0)
    xs, ys = pinhole_spans(cam)
    h = f16.sigma_lenslet_plane * f16.so / f16.si / 1.5
    nx, ny = round(xs / h), round(ys / h)
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) * xs / nx - xs / 2, (np.arange(ny) + 0.5) * ys / ny - ys / 2)
    grid = make_field(gx.ravel(), gy.ravel(), 0 * gx.ravel(), np.full(gx.size, count / gx.size))
    dense = ex.render_exact(f16, grid, n)
    peak = dense.values.max()
    assert np.abs(pin.values - dense.values).max() < 1e-7 * peak
    assert pin.values.sum() == pytest.approx(dense.values.sum(), rel=1e-7)
    # The Gauss rule has converged: 3 nodes per axis against 6.
    assert np.abs(ex.render_pinhole_exact(cam, count=count, rays_per_point=n, nodes=6).values - pin.values).max() < (
        1e-7 * peak
    )
    # No sampling: the seed does not matter, and the image scales with the field's density.
    other_seed = ex.render_pinhole_exact(cam, count=count, rays_per_point=n, seed=9)
    np.testing.assert_array_equal(pin.values, other_seed.values)
    np.testing.assert_allclose(ex.render_pinhole_exact(cam, count=2 * count, rays_per_point=n).values, 2 * pin.values)
    for kw, match in (({"count": 0}, "count"), ({"nodes": 0}, "nodes"), ({"rays_per_point": 0}, "rays_per_point")):
        with pytest.raises(ValueError, match=match):
            ex.render_pinhole_exact(cam, **{"count": count, "rays_per_point": n, **kw})


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"rays_per_particle": 0}, "rays_per_particle"),
        ({"rays_per_particle": 2.5}, "rays_per_particle"),
        ({"particles": _field((0.0, 0.0, 0.0)).isel(particle=slice(0, 0))}, "empty"),
        ({"particles": _field((0.0, 0.0, -50.0))}, r"particles\.z"),
        ({"particles": _field((0.0, 0.0, 0.0)).assign(x=("particle", [np.nan]))}, r"particles\.x"),
        ({"particles": _field((0.0, 0.0, 0.0)).assign(intensity=("particle", [-1.0]))}, r"particles\.intensity"),
        ({"n_chunks": 0}, "n_chunks"),
        ({"max_image_bytes": 1000}, "max_image_bytes"),
        ({"sigmas": (-1e-3, 1e-3)}, "sigmas"),
        ({"sigmas": (1e-3, float("nan"))}, "sigmas"),
        ({"sigmas": (1e-3,)}, "sigmas"),
    ],
)
def test_bad_input(kwargs, match):
    args = {"camera": CAM, "particles": _field((0.0, 0.0, 0.0)), "rays_per_particle": 10}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        ex.render_exact(**args)


def test_memory_estimate_is_about_one_image():
    cam = PlenopticCamera(4872, 3248, 0.0074, 0.125, 0.5, 50.0, -1.0)
    field = seed_particles(cam, count=2000, z_span=7.0, seed=1)
    est = ex.exact_memory_estimate(cam, field)
    image = 8 * cam.n_pixels_x * cam.n_pixels_y
    assert image < est < 1.3 * image


def test_render_examples_run_as_a_doctest():
    """The Examples of ``render`` (the package's face, default method exact) run and print what they say."""
    tests = doctest.DocTestFinder().find(rt.render, "render", globs={})
    assert sum(len(t.examples) for t in tests) >= 5
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    for t in tests:
        runner.run(t)
    assert runner.failures == 0, f"{runner.failures} of {runner.tries} examples of render failed (output above)"
