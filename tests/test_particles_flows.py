from __future__ import annotations

import numpy as np
import pytest

from lfstudy.simulate.flows import FlowError, HillVortex, UniformFlow, displace, integrate, true_displacement
from lfstudy.simulate.particles import ParticleError, particle_count, pinhole_field, seed_particles


def test_ppp_counts_sensor_pixels(table43_camera):
    assert particle_count(table43_camera, 0.001) == 15824  # the thesis' 15,824 (sec. 7.1)


def test_seeding_reproducible_and_bounded(table43_camera):
    a = seed_particles(table43_camera, count=5000, z_span=7.0, intensity=(0.5, 1.0), seed=3)
    b = seed_particles(table43_camera, count=5000, z_span=7.0, intensity=(0.5, 1.0), seed=3)
    c = seed_particles(table43_camera, count=5000, z_span=7.0, intensity=(0.5, 1.0), seed=4)
    assert a.identical(b) and not a["x"].equals(c["x"])
    assert float(abs(a["x"]).max()) <= table43_camera.fov_x / 2
    assert float(abs(a["z"]).max()) <= 3.5
    assert float(a["intensity"].min()) >= 0.5 and float(a["intensity"].max()) <= 1.0
    assert a["z"].attrs["units"] == "mm"


def test_a_slab_off_the_focal_plane_is_the_centred_one_moved(table43_camera):
    """particles.z_center moves the slab (and its margin) in depth; every other draw is unchanged."""
    kw = {"count": 2000, "z_span": 4.0, "seed": 5, "depth_margin": 0.5}
    a = seed_particles(table43_camera, **kw)
    b = seed_particles(table43_camera, z_center=3.0, **kw)
    assert np.array_equal(b["x"].values, a["x"].values) and np.array_equal(b["intensity"], a["intensity"])
    assert np.allclose(b["z"].values, a["z"].values + 3.0, rtol=0, atol=1e-12)
    assert float(b["z"].min()) >= 0.5 and float(b["z"].max()) <= 5.5 and b.attrs["z_center"] == 3.0
    assert seed_particles(table43_camera, z_center=0.0, **kw).identical(a)
    with pytest.raises(ParticleError, match="z_center"):
        seed_particles(table43_camera, count=10, z_center=float("nan"))
    with pytest.raises(ParticleError, match="focal length"):
        seed_particles(table43_camera, count=10, z_span=2.0, z_center=-(table43_camera.so - 50.0))


def test_pinhole_field_is_planar(table43_camera):
    p = pinhole_field(table43_camera, count=1000)
    assert float(abs(p["z"]).max()) == 0.0 and p.sizes["particle"] == 1000


@pytest.mark.parametrize(
    "kw",
    [
        {"ppp": 0.0},
        {"ppp": 1.5},
        {"ppp": float("nan")},
        {"count": 0},
        {"ppp": 0.001, "z_span": -1.0},
        {"ppp": 0.001, "intensity": (1.0, 0.5)},
        {"ppp": 0.001, "count": 10},
        {"ppp": 0.001, "z_span": 500.0},
    ],
)
def test_bad_seeding(table43_camera, kw):
    with pytest.raises(ParticleError):
        seed_particles(table43_camera, **kw)


def test_uniform_displacement(table43_camera):
    p = seed_particles(table43_camera, count=100, z_span=2.0, seed=1)
    q = displace(p, UniformFlow((0.5625, 0.0, -0.1)), dt=1.0, n_steps=5)
    np.testing.assert_allclose(q["x"] - p["x"], 0.5625, atol=1e-12)
    np.testing.assert_allclose(q["z"] - p["z"], -0.1, atol=1e-12)


def test_hill_continuous_at_sphere():
    h = HillVortex(radius=1.5, u0=0.7, axis=(1.0, 0.0, 1.0))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3, 500))
    d /= np.linalg.norm(d, axis=0)
    inside = [np.stack(h.velocity(*(d * 1.5 * (1 - 1e-9))))]
    outside = [np.stack(h.velocity(*(d * 1.5 * (1 + 1e-9))))]
    np.testing.assert_allclose(inside[0], outside[0], atol=1e-7)
    # Far field: fluid moves at -u0 along the axis (vortex frame).
    far = np.stack(h.velocity(np.array([1e4]), np.array([0.0]), np.array([0.0])))[:, 0]
    e = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    np.testing.assert_allclose(far, -0.7 * e, atol=1e-6)


def test_hill_divergence_free():
    h = HillVortex(radius=1.0, u0=1.0, center=(0.2, -0.1, 0.3))
    rng = np.random.default_rng(1)
    pts = rng.uniform(-2.0, 2.0, size=(3, 4000)) + np.array([[0.2], [-0.1], [0.3]])
    r = np.linalg.norm(pts - np.array([[0.2], [-0.1], [0.3]]), axis=0)
    pts = pts[:, np.abs(r - 1.0) > 0.01]  # central differences must not straddle the sphere
    eps = 1e-5
    div = np.zeros(pts.shape[1])
    for k in range(3):
        dp = np.zeros((3, 1))
        dp[k] = eps
        div += (np.stack(h.velocity(*(pts + dp)))[k] - np.stack(h.velocity(*(pts - dp)))[k]) / (2 * eps)
    scale = np.abs(np.stack(h.velocity(*pts))).max()
    # Velocity gradients are O(u0/a) = 1; a compressible field would give O(1) here.
    assert np.abs(div).max() < 1e-6 * max(scale, 1.0)


def test_integration_converges():
    h = HillVortex(radius=1.5, u0=0.25)
    rng = np.random.default_rng(2)
    x, y, z = rng.uniform(-2, 2, size=(3, 300))
    a = np.stack(integrate(h, x, y, z, 1.0, 100))
    b = np.stack(integrate(h, x, y, z, 1.0, 200))
    assert np.abs(a - b).max() < 1e-6
    # Midpoint-referenced truth of a uniform flow is the flow itself.
    d = true_displacement(UniformFlow((0.1, 0.2, 0.3)), x, y, z)
    np.testing.assert_allclose(np.stack(d), np.array([[0.1], [0.2], [0.3]]) * np.ones((1, 300)))


@pytest.mark.parametrize(
    "make",
    [
        lambda: HillVortex(radius=-1.0),
        lambda: HillVortex(axis=(0, 0, 0)),
        lambda: UniformFlow((1.0, float("nan"), 0.0)),
    ],
)
def test_bad_flows(make):
    with pytest.raises(FlowError):
        make()
