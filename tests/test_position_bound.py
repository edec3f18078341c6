"""lfstudy.reconstruct.ipr.bound: the Cramér–Rao bound of a particle's position."""

from __future__ import annotations

import numpy as np
import pytest

from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct.ipr.bound import fisher_information, position_bound
from lfstudy.reconstruct.ipr.patches import particle_patches
from lfstudy.reconstruct.registry import ReconstructionError

CAM = PlenopticCamera(160, 160, 0.0074, 0.0888, 0.3552, 50.0, -1.0)
X0, Y0 = 0.013, -0.021  # inside one lenslet's footprint


@pytest.mark.parametrize("z0", [1.5, 0.3])
def test_maximum_likelihood_depth_reaches_the_bound(z0):
    """The bound is attained: the maximum-likelihood depth (x, y and intensity known) on Poisson draws of the
    expected image spreads by 1/sqrt(F_zz), within the spread of 400 draws' standard deviation."""
    rays = 4000.0
    fisher = fisher_information(CAM, [X0], [Y0], [z0], [1.0], rays, crowded=False)[0]
    bound = 1.0 / np.sqrt(fisher[2, 2])
    dz = np.linspace(-6 * bound, 6 * bound, 241)
    trials = np.column_stack([np.zeros_like(dz), np.zeros_like(dz), dz])
    pt, _, _, _, shp = particle_patches(CAM, [X0], [Y0], [z0], trials=trials, pad=4)
    size = int(shp[0, 0] * shp[0, 1])
    imgs = pt[: (dz.size + 1) * size].reshape(dz.size + 1, size) * rays
    counts = np.random.default_rng(3).poisson(np.broadcast_to(imgs[0], (400, size)))
    loglik = counts @ np.log(np.maximum(imgs[1:], 1e-300)).T - imgs[1:].sum(1)
    k = np.clip(loglik.argmax(1), 1, dz.size - 2)
    a, b, c = (loglik[np.arange(400), k + j] for j in (-1, 0, 1))
    est = dz[k] + 0.5 * (a - c) / (a - 2 * b + c) * (dz[1] - dz[0])
    assert est.std() == pytest.approx(bound, rel=0.15)
    assert abs(est.mean()) < 0.25 * bound


def test_bound_scales_with_photons_depth_and_crowding():
    z = np.array([0.02, 0.6, 1.5, -1.5])
    one = np.ones(4)
    iso = position_bound(CAM, np.full(4, X0), np.full(4, Y0), z, one, 4000, crowded=False)
    assert np.all(np.isfinite(iso))
    # Poisson: four times the photons halve the bound
    np.testing.assert_allclose(
        position_bound(CAM, np.full(4, X0), np.full(4, Y0), z, one, 16000, crowded=False), iso / 2, rtol=1e-6
    )
    # at the focal plane the image hardly changes with depth: the bound is many times the defocused one's
    assert iso[0, 2] > 20 * iso[1:, 2].max()
    # a neighbour's light in the same pixels is noise: the crowded bound is larger
    xs, ys, zs = np.array([X0, X0 + 0.01]), np.array([Y0, Y0]), np.array([1.5, 1.4])
    crowd = position_bound(CAM, xs, ys, zs, np.ones(2), 4000)
    alone = position_bound(CAM, xs, ys, zs, np.ones(2), 4000, crowded=False)
    assert np.all(crowd > alone)


@pytest.mark.parametrize(
    ("kw", "match"),
    [({"rays": 0.0}, "rays"), ({"intensity": [0.0]}, "intensity"), ({"x": [0.0, 1.0]}, "one value per particle")],
)
def test_bad_input_names_the_field(kw, match):
    args = {"x": [X0], "y": [Y0], "z": [1.0], "intensity": [1.0], "rays": 4000.0} | kw
    with pytest.raises(ReconstructionError, match=match):
        position_bound(CAM, args["x"], args["y"], args["z"], args["intensity"], args["rays"])
