"""The physical sensor model: photons, quantum efficiency, shot and read noise, dark level, full well, ADC."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from lfstudy.simulate.sensor import SensorError, apply_sensor, sensor_noise_variance


def _flat(value: float, shape=(400, 500), rays: int = 1000) -> xr.DataArray:
    """A uniform expected image (every pixel the same mean), as a renderer would return it."""
    return xr.DataArray(np.full(shape, value), dims=("row", "col"), attrs={"rays_per_particle": rays, "units": "1"})


@pytest.mark.parametrize("qe, read", [(1.0, 0.0), (0.6, 0.0), (0.6, 3.0), (1.0, 12.0)])
def test_noise_variance_is_poisson_plus_read_noise(qe, read):
    """200,000 pixels of one mean: the sample mean and variance match QE·photons (+ dark) and
    QE·photons + read² within 5 standard errors of each (var of a sample variance ≈ 2σ⁴/n + κ₄/n)."""
    photons = 40.0  # per pixel: image 40 at 1000 rays/particle with 1000 photons/particle
    img = apply_sensor(
        _flat(photons), photons_per_particle=1000, quantum_efficiency=qe, read_noise=read, dark_level=7.0, seed=11
    )
    v = img.values.ravel()
    mean_e = qe * photons + 7.0
    var = float(sensor_noise_variance(photons, qe, read))
    assert var == pytest.approx(qe * photons + read**2)
    n = v.size
    assert abs(v.mean() - mean_e) < 5 * np.sqrt(var / n)
    se_var = np.sqrt((2 * var**2 + qe * photons) / n)  # Gaussian part + the Poisson excess kurtosis term
    assert abs(v.var(ddof=1) - var) < 5 * se_var
    assert img.attrs["units"] == "e-" and img.attrs["sensor_seed"] == 11
    # Without shot noise only the read noise is left.
    quiet = apply_sensor(
        _flat(photons), photons_per_particle=1000, quantum_efficiency=qe, shot_noise=False, read_noise=read, seed=11
    )
    assert quiet.values.var(ddof=1) == pytest.approx(read**2, rel=0.02, abs=1e-12)


def test_same_seed_same_bytes_other_seed_other_image():
    a = apply_sensor(_flat(5.0, (50, 60)), photons_per_particle=1000, read_noise=2.0, seed=3)
    b = apply_sensor(_flat(5.0, (50, 60)), photons_per_particle=1000, read_noise=2.0, seed=3)
    c = apply_sensor(_flat(5.0, (50, 60)), photons_per_particle=1000, read_noise=2.0, seed=4)
    assert np.array_equal(a.values, b.values) and not np.array_equal(a.values, c.values)


def test_photon_scale_full_well_and_adc():
    """photons = image · photons_per_particle / rays_per_particle; the well clips, the ADC rounds by the gain."""
    img = _flat(1.0, (4, 5), rays=100).copy(data=np.array([[0.0, 1.0, 2.0, 50.0, 500.0]] * 4))
    e = apply_sensor(img, photons_per_particle=200, quantum_efficiency=0.5, shot_noise=False, dark_level=10)
    np.testing.assert_allclose(e.values[0], [10.0, 11.0, 12.0, 60.0, 510.0])
    assert e.attrs["photons_per_unit_intensity"] == 2.0
    sat = apply_sensor(img, photons_per_particle=200, shot_noise=False, dark_level=10, full_well=100.0)
    np.testing.assert_allclose(sat.values[0], [10.0, 12.0, 14.0, 100.0, 100.0])
    assert sat.attrs["saturated_pixels"] == 8
    adc = apply_sensor(img, photons_per_particle=200, shot_noise=False, dark_level=10, full_well=100.0, bit_depth=8)
    assert adc.dtype == np.uint8 and adc.attrs["units"] == "counts"
    assert adc.attrs["sensor_gain"] == pytest.approx(100.0 / 255)
    np.testing.assert_array_equal(adc.values[0], np.rint(np.array([10.0, 12.0, 14.0, 100.0, 100.0]) * 2.55))
    g = apply_sensor(img, photons_per_particle=200, shot_noise=False, bit_depth=12, gain=2.0)
    assert g.dtype == np.uint16
    np.testing.assert_array_equal(g.values[0], [0, 1, 2, 50, 500])
    # Read noise below zero: kept in electrons (unbiased), clipped to 0 counts by the ADC.
    dark = _flat(0.0, (100, 100))
    assert apply_sensor(dark, photons_per_particle=1000, read_noise=5.0, seed=1).values.min() < 0
    assert apply_sensor(dark, photons_per_particle=1000, read_noise=5.0, bit_depth=10, seed=1).values.min() == 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"photons_per_particle": -1.0}, "photons_per_particle"),
        ({"photons_per_particle": float("nan")}, "photons_per_particle"),
        ({"quantum_efficiency": 0.0}, "quantum_efficiency"),
        ({"quantum_efficiency": 1.5}, "quantum_efficiency"),
        ({"read_noise": -0.1}, "read_noise"),
        ({"dark_level": -1}, "dark_level"),
        ({"bit_depth": 0}, "bit_depth"),
        ({"bit_depth": 33}, "bit_depth"),
        ({"bit_depth": 12.0}, "bit_depth"),
        ({"full_well": 50.0, "dark_level": 60.0}, "full_well"),
        ({"full_well": 0.0}, "full_well"),
        ({"gain": 0.0}, "gain"),
        ({"shot_noise": "yes"}, "shot_noise"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_input_one_clear_error(kwargs, match):
    args = {"photons_per_particle": 1000.0, **kwargs}
    with pytest.raises(SensorError, match=match):
        apply_sensor(_flat(1.0, (3, 3)), **args)


def test_bad_image():
    with pytest.raises(SensorError, match="rays_per_particle"):
        apply_sensor(xr.DataArray(np.ones((3, 3)), dims=("row", "col")), photons_per_particle=10)
    with pytest.raises(SensorError, match=">= 0"):
        apply_sensor(_flat(-1.0, (3, 3)), photons_per_particle=10)


def test_case_image_renders_with_the_method_and_records_with_the_sensor():
    """The case layer: raytrace.method picks the renderer, the sensor section records it, seeded
    from the case (same config -> same bytes); a noise-free ideal sensor returns the exact image."""
    from pathlib import Path

    from lfstudy.config import read_yaml
    from lfstudy.simulate.exact import render_exact
    from lfstudy.study.case import case_camera, case_image, case_particles
    from lfstudy.study.config import case_config, expand_cases, validate_config

    raw = read_yaml(Path(__file__).parent / "data" / "tiny.yaml")
    raw["camera"]["sensor"].update(n_pixels_x=96, n_pixels_y=80)
    raw["sweep"] = {"ppp": [0.004], "flow": ["uniform_x"]}
    cfg = validate_config(raw)
    assert cfg["raytrace"]["method"] == "exact" and cfg["sensor"]["shot_noise"] is True
    ccfg = case_config(cfg, expand_cases(cfg)[0].case_id)
    field = case_particles(ccfg)
    a = case_image(ccfg, field, "a")
    assert np.array_equal(a.values, case_image(ccfg, field, "a").values)
    assert a.attrs["method"] == "exact" and a.attrs["sensor_shot_noise"] == 1
    assert a.attrs["sensor_photons_per_particle"] == cfg["raytrace"]["rays_per_particle"]  # null: one per ray
    expected = render_exact(case_camera(ccfg), field, cfg["raytrace"]["rays_per_particle"]).values
    assert not np.array_equal(a.values, expected) and np.all(a.values == np.round(a.values))  # Poisson counts
    quiet = {**ccfg, "sensor": {**ccfg["sensor"], "shot_noise": False}}
    np.testing.assert_array_equal(case_image(quiet, field, "a").values, expected)
    adc = {**ccfg, "sensor": {**ccfg["sensor"], "full_well": 400.0, "bit_depth": 12, "read_noise": 3.0}}
    counts = case_image(adc, field, "a")
    assert counts.dtype == np.uint16 and counts.attrs["sensor_gain"] == pytest.approx(400.0 / 4095)
    mc = case_image({**ccfg, "raytrace": {**ccfg["raytrace"], "method": "montecarlo"}}, field, "a")
    assert "rays_traced" in mc.attrs and mc.shape == a.shape
