"""Light and particle imperfections (issue 29 §1): the light volume, background light, hot pixels,
particle diameters and particles seeded beyond the measurement volume.

Every setting defaults to the ideal camera and then changes no bit; each does what its
docstring says; the exact renderer and the Monte-Carlo tracer agree under them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.special import ndtr

from lfstudy.config import ConfigError, read_yaml
from lfstudy.reconstruct.truth import render_truth, voxel_edges
from lfstudy.simulate import exact as ex
from lfstudy.simulate import raytrace as rt
from lfstudy.simulate.particles import (
    ParticleError,
    illumination_profile,
    particle_diameters,
    seed_particles,
)
from lfstudy.simulate.sensor import SensorError, apply_sensor, hot_pixel_mask
from lfstudy.study import case as cl
from lfstudy.study.config import case_config, expand_cases, stage_config, validate_config

TINY = Path(__file__).parent / "data" / "tiny.yaml"


def _raw(**sections):
    """tiny.yaml on a 96 x 80 px sensor (8 x 6 lenslets, about 30 particles), one case."""
    raw = read_yaml(TINY)
    raw["camera"]["sensor"].update(n_pixels_x=96, n_pixels_y=80)
    raw["sweep"] = {"ppp": [0.004], "flow": ["uniform_x"]}
    raw["pinhole"]["count"] = 4000
    raw["flows"]["uniform_x"]["displacement"] = [0.1, 0.0, 0.4]  # through the light volume in z
    for name, value in sections.items():
        raw[name] = {**raw.get(name, {}), **value}
    return raw


def _case(**sections):
    cfg = validate_config(_raw(**sections))
    return case_config(cfg, expand_cases(cfg)[0])


def _quiet(ccfg, **sensor):
    """The case with a noise-free sensor (the expected image: comparisons are exact)."""
    return {**ccfg, "sensor": {**ccfg["sensor"], "shot_noise": False, **sensor}}


def _method(ccfg, method):
    return {**ccfg, "raytrace": {**ccfg["raytrace"], "method": method}}


def _everything(ccfg):
    """Particles of both frames, images of both frames by both renderers, pinhole, truth volumes."""
    a = cl.case_particles(ccfg)
    b = cl.case_displaced(ccfg, a)
    out = {f"{f}_{v}": p[v].values for f, p in (("a", a), ("b", b)) for v in ("x", "y", "z", "intensity")}
    for m in ("exact", "montecarlo"):
        out[f"image_a_{m}"] = cl.case_image(_method(ccfg, m), a, "a").values
        out[f"image_b_{m}"] = cl.case_image(_method(ccfg, m), b, "b").values
    out["pinhole"] = cl.case_pinhole(ccfg).values
    va, vb = cl.oracle_volumes(ccfg, a, b)
    out["truth_a"], out["truth_b"] = va.values, vb.values
    return out


# ------------------------------------------------------------------ ideal defaults
def test_every_setting_at_its_ideal_value_changes_no_bit():
    """The default config, and every new setting given explicitly at (or in effect at) its ideal
    value, give the same particles, images (exact, Monte-Carlo, pinhole) and truth volumes; the
    particles are still today's draw: default_rng(seed).random((4, n)) mapped onto the slab."""
    ccfg = _case()
    ideal = _case(
        illumination={"profile": "none", "center": 0.7, "thickness": 2.0, "edge_width": 0.3},
        particles={"depth_margin": 0.0, "diameter": {"distribution": "fixed", "mean_um": 2.5, "sd_um": 0.8}},
        sensor={
            "background": {"uniform": 0.0, "lenslet": 0.0},
            "hot_pixels": {"fraction": 0.05, "level": 0.0, "seed": 4},  # no level: no hot pixel
        },
    )
    ref, alt = _everything(ccfg), _everything(ideal)
    assert ref.keys() == alt.keys()
    for k in ref:
        np.testing.assert_array_equal(ref[k], alt[k], err_msg=k)
    # today's field, drawn the way it always was
    cam = cl.case_camera(ccfg)
    n = ref["a_x"].size
    seed = cl.derive_seed(ccfg["seed"], "particles", float(ccfg["camera"]["magnification"]), 0.004)
    u = np.random.default_rng(seed).random((4, n))
    np.testing.assert_array_equal(ref["a_x"], (u[0] - 0.5) * cam.fov_x)
    np.testing.assert_array_equal(ref["a_z"], (u[2] - 0.5) * ccfg["particles"]["z_span"])
    np.testing.assert_array_equal(ref["a_intensity"], np.ones(n))
    assert "diameter" not in cl.case_particles(ideal)
    # the noise-free default image is the exact renderer's own image of the field
    field = cl.case_particles(ccfg)
    np.testing.assert_array_equal(
        cl.case_image(_quiet(ccfg), field, "a").values,
        ex.render_exact(cam, field, ccfg["raytrace"]["rays_per_particle"]).values,
    )


# ------------------------------------------------------------------ illumination
def test_illumination_profiles_follow_their_formulas():
    z = np.linspace(-3.0, 3.0, 601)
    c, t, e = 0.4, 1.6, 0.1
    g = illumination_profile(z, profile="gaussian", center=c, thickness=t)
    np.testing.assert_allclose(g, np.exp(-4 * math.log(2) * ((z - c) / t) ** 2), rtol=1e-14)
    half = illumination_profile(np.array([c - t / 2, c, c + t / 2]), profile="gaussian", center=c, thickness=t)
    np.testing.assert_allclose(half, [0.5, 1.0, 0.5], rtol=1e-14)  # thickness is the FWHM
    hard = illumination_profile(z, profile="tophat", center=c, thickness=t)
    np.testing.assert_array_equal(hard, (np.abs(z - c) <= t / 2).astype(float))
    soft = illumination_profile(z, profile="tophat", center=c, thickness=t, edge_width=e)
    # a top hat blurred by a Gaussian of sd e: the two edges as normal CDFs
    np.testing.assert_allclose(soft, ndtr((z - c + t / 2) / e) - ndtr((z - c - t / 2) / e), atol=1e-15)
    edge = illumination_profile(
        np.array([c + t / 2, c + t / 2 + e]), profile="tophat", center=c, thickness=t, edge_width=e
    )
    np.testing.assert_allclose(edge, [0.5, ndtr(-1.0)], rtol=1e-6)  # 50 % at the edge, 16 % one e out
    np.testing.assert_array_equal(illumination_profile(z), np.ones_like(z))
    with pytest.raises(ParticleError, match=r"illumination.profile"):
        illumination_profile(z, profile="sheet")
    with pytest.raises(ParticleError, match=r"illumination.thickness = 0.*> 0"):
        illumination_profile(z, profile="gaussian", thickness=0.0)
    with pytest.raises(ParticleError, match=r"illumination.edge_width = -1.*>= 0"):
        illumination_profile(z, profile="tophat", edge_width=-1.0)


def test_the_light_volume_dims_each_exposure_at_its_own_depth_in_both_renderers():
    """The renderers get the lit intensities: the case's image equals the ideal case's image of the
    field with its intensities multiplied by the profile by hand (both renderers, bit for bit), and
    frame b is lit at frame b's depths."""
    il = {"profile": "gaussian", "center": 0.3, "thickness": 1.0}
    lit, plain = _case(illumination=il), _case()
    a = cl.case_particles(lit)
    b = cl.case_displaced(lit, a)
    for p in (a, b):
        dimmed = p.assign(intensity=p["intensity"] * np.exp(-4 * math.log(2) * ((p["z"] - 0.3) / 1.0) ** 2))
        np.testing.assert_allclose(cl.case_illuminated(lit, p)["intensity"], dimmed["intensity"], rtol=1e-15)
        for m in ("exact", "montecarlo"):
            np.testing.assert_array_equal(
                cl.case_image(_method(lit, m), p, "b").values,
                cl.case_image(_method(plain, m), cl.case_illuminated(lit, p), "b").values,
            )
    fa, fb = cl.case_illuminated(lit, a)["intensity"].values, cl.case_illuminated(lit, b)["intensity"].values
    assert np.all(fa <= 1.0) and fa.min() < 0.5 and not np.allclose(fa, fb)  # dz = 0.4 mm changes the light
    assert cl.case_illuminated(plain, a) is a  # none: the field itself
    img = cl.case_image(_quiet(lit), a, "a").values
    assert img.sum() < cl.case_image(_quiet(plain), a, "a").values.sum()
    # the truth volumes are of the lit particles too
    va, _ = cl.oracle_volumes(lit, a, b)
    np.testing.assert_array_equal(va.values, cl.oracle_volumes(plain, cl.case_illuminated(lit, a), b)[0].values)


# ------------------------------------------------------------------ diameters
def test_lognormal_diameters_scale_intensity_by_d_squared():
    """Mean and sd of the drawn diameters, intensity = (d/mean)², mean intensity 1 + (sd/mean)²
    (each within 5 standard errors); positions untouched."""
    cam = cl.case_camera(_case())
    m, s, n = 1.5, 0.6, 40_000
    ideal = seed_particles(cam, count=n, z_span=3.0, seed=5)
    field = seed_particles(cam, count=n, z_span=3.0, seed=5, diameter="lognormal", diameter_mean_um=m, diameter_sd_um=s)
    for v in ("x", "y", "z"):
        np.testing.assert_array_equal(field[v].values, ideal[v].values)
    d = field["diameter"].values
    assert field["diameter"].attrs["units"] == "um" and np.all(d > 0)
    assert abs(d.mean() - m) < 5 * s / math.sqrt(n)
    m4 = np.mean((d - d.mean()) ** 4)
    assert abs(d.std() - s) < 5 * math.sqrt((m4 - d.var() ** 2) / n) / (2 * s)  # SE of a sample sd
    np.testing.assert_allclose(field["intensity"].values, (d / m) ** 2, rtol=1e-14)
    f = (d / m) ** 2
    assert abs(f.mean() - (1 + (s / m) ** 2)) < 5 * f.std() / math.sqrt(n)
    np.testing.assert_array_equal(particle_diameters(5, mean_um=2.0, sd_um=1.0), np.full(5, 2.0))  # fixed
    with pytest.raises(ParticleError, match=r"particles.diameter.distribution"):
        particle_diameters(3, distribution="normal")
    with pytest.raises(ParticleError, match=r"particles.diameter.mean_um"):
        particle_diameters(3, distribution="lognormal", mean_um=0.0)
    # through the config: the mean defaults to camera.particle_diameter (1 µm)
    p = cl.case_particles(_case(particles={"diameter": {"distribution": "lognormal", "sd_um": 0.3}}))
    assert p.attrs["diameter_mean_um"] == pytest.approx(1000 * cam.particle_diameter)
    np.testing.assert_allclose(p["intensity"], (p["diameter"] / p.attrs["diameter_mean_um"]) ** 2, rtol=1e-14)


# ------------------------------------------------------------------ sensor
def test_background_light_and_hot_pixels():
    """Uniform background: mean QE·B and Poisson variance; lenslet background: mean L per pixel,
    bright under the lenslets, dark between them; hot pixels: count, positions fixed by their seed
    (the same in both frames and in the pinhole image), level added, may saturate."""
    dark = __import__("xarray").DataArray(np.zeros((300, 400)), dims=("row", "col"), attrs={"rays_per_particle": 10})
    img = apply_sensor(dark, photons_per_particle=10, quantum_efficiency=0.5, background=30.0, seed=2).values
    sem = math.sqrt(15.0 / img.size)
    assert abs(img.mean() - 15.0) < 5 * sem and abs(img.var() / 15.0 - 1) < 5 * math.sqrt(2 / img.size)
    hot = hot_pixel_mask((300, 400), 0.01, seed=9)
    assert hot.sum() == 1200
    np.testing.assert_array_equal(hot, hot_pixel_mask((300, 400), 0.01, seed=9))
    assert (hot & hot_pixel_mask((300, 400), 0.01, seed=10)).sum() < 60  # another seed, other pixels
    rec = apply_sensor(
        dark, photons_per_particle=10, shot_noise=False, hot_pixel_fraction=0.01, hot_pixel_level=500.0,
        hot_pixel_seed=9, full_well=300.0,
    )  # fmt: skip
    np.testing.assert_array_equal(rec.values, np.where(hot, 300.0, 0.0))  # the well clips them
    assert rec.attrs["sensor_hot_pixels"] == 1200 and rec.attrs["saturated_pixels"] == 1200
    with pytest.raises(SensorError, match=r"hot_pixels.fraction"):
        hot_pixel_mask((4, 4), 1.5, 0)
    with pytest.raises(SensorError, match=r"background"):
        apply_sensor(dark, photons_per_particle=1, background=-1.0)

    ccfg = _case()
    field = cl.case_particles(ccfg)
    base = cl.case_image(_quiet(ccfg), field, "a").values
    lens = cl.case_image(_quiet(ccfg, background={"uniform": 2.0, "lenslet": 40.0}), field, "a").values
    bg = lens - base
    assert bg.mean() == pytest.approx(42.0, rel=1e-12) and bg.min() >= 2.0 - 1e-9
    # the lenslet structure: periodic with the lenslet pitch (12 px), dark between the lenslet images
    lens_only = bg - 2.0
    period = round(cl.case_camera(ccfg).lenslet_pitch / cl.case_camera(ccfg).pixel_pitch)
    corr = [np.corrcoef(lens_only[:, :-k].ravel(), lens_only[:, k:].ravel())[0, 1] for k in (period, period // 2)]
    assert corr[0] > 0.9 and corr[1] < 0.0, corr
    assert lens_only.min() < 0.25 * lens_only.mean() < lens_only.max() / 5

    hp = {"hot_pixels": {"fraction": 0.02, "level": 1e6}}
    ha = cl.case_image(_quiet(ccfg, **hp), field, "a").values >= 1e6
    hb = cl.case_image(_quiet(ccfg, **hp), cl.case_displaced(ccfg, field), "b").values >= 1e6
    pin = cl.case_pinhole(_quiet(ccfg, **hp)).values >= 1e6
    assert ha.sum() == round(0.02 * ha.size)
    np.testing.assert_array_equal(ha, hb)
    np.testing.assert_array_equal(ha, pin)
    seeded = cl.case_image(_quiet(ccfg, hot_pixels={**hp["hot_pixels"], "seed": 77}), field, "a").values >= 1e6
    np.testing.assert_array_equal(seeded, hot_pixel_mask(ha.shape, 0.02, 77))


# ------------------------------------------------------------------ depth margin
def test_particles_beyond_the_slab_are_imaged_but_not_in_the_truth():
    """depth_margin: the slab's particles unchanged, round(n·2m/z_span) more at |z| in
    (z_span/2, z_span/2 + m] on both sides; they add their own image to the frame (the exact
    renderer is linear), while the truth volume changes only within 4 σz of the grid's depth ends
    and not at all from the particles more than 4 σz beyond them."""
    grid, slab = {"z_range": [-4.0, 4.0], "voxel_z": 0.5}, {"z_span": 8.0}
    ccfg, wide = _case(grid=grid, particles=slab), _case(grid=grid, particles={**slab, "depth_margin": 6.0})
    a, w = cl.case_particles(ccfg), cl.case_particles(wide)
    n = a.sizes["particle"]
    assert w.sizes["particle"] == n + round(n * 2 * 6.0 / 8.0) == n + w.attrs["n_margin"]
    for v in ("x", "y", "z", "intensity"):
        np.testing.assert_array_equal(w[v].values[:n], a[v].values)
    zm = w["z"].values[n:]
    assert np.all((np.abs(zm) > 4.0) & (np.abs(zm) <= 10.0)) and (zm > 0).any() and (zm < 0).any()
    margin = w.isel(particle=slice(n, None))
    # in the image
    q = _quiet(ccfg)
    both = cl.case_image(q, w, "a").values
    # (the exact kernel sums in float32 chunks: equal to a millionth of the brightest pixel)
    np.testing.assert_allclose(
        both, cl.case_image(q, a, "a").values + cl.case_image(q, margin, "a").values, rtol=0, atol=1e-6 * both.max()
    )
    veil = cl.case_image(q, margin, "a").values  # defocused: spread over much of the sensor
    assert veil.sum() > 0.2 * cl.case_image(q, a, "a").values.sum() and (veil > 1e-3 * both.max()).mean() > 0.3
    # not in the truth
    g = cl.case_grid(ccfg)
    edges = voxel_edges(g.z)
    sz = cl.truth_sigma(cl.case_camera(ccfg))[0]
    far = (zm < edges[0] - 4 * sz) | (zm > edges[-1] + 4 * sz)
    assert far.sum() > 0.5 * zm.size
    coords = {"z": g.z, "y": g.y, "x": g.x}
    assert not render_truth(
        coords, margin.isel(particle=np.flatnonzero(far)), sigma_mm=cl.truth_sigma(cl.case_camera(ccfg))
    ).any()
    ta, tw = (cl.oracle_volumes(c, p, p)[0].values for c, p in ((ccfg, a), (wide, w)))
    # planes a margin particle's Gaussian can reach (|z| > 4 mm, 4 sigma): the rest bit-identical
    near = (edges[1:] > 4.0 - 4 * sz) | (edges[:-1] < -4.0 + 4 * sz)
    assert (~near).sum() >= 3
    np.testing.assert_array_equal(tw[~near], ta[~near])
    assert not np.array_equal(tw[near], ta[near])  # the near ones do reach the grid's end planes


# ------------------------------------------------------------------ exact vs Monte-Carlo
def test_exact_and_montecarlo_agree_under_the_imperfections():
    """A lit, lognormal, margin-seeded field: per pixel the mean of K Monte-Carlo images equals the
    exact image (ray counts matched) within its standard error, as in test_exact_render: each ray
    carries its particle's intensity I, so a pixel's variance is sum I² n p (1 - p), the exact image
    of the field with intensities I² (1 - p ~ 1: p is small per pixel); mean z² ~ 1, no outlier."""
    ccfg = _case(
        illumination={"profile": "tophat", "center": -0.2, "thickness": 1.5, "edge_width": 0.2},
        particles={"depth_margin": 1.0, "diameter": {"distribution": "lognormal", "sd_um": 0.4}},
    )
    cam = cl.case_camera(ccfg)
    field = cl.case_illuminated(ccfg, cl.case_particles(ccfg))
    assert field["intensity"].min() < 0.05 and field["intensity"].max() > 1.0
    n, seeds = 4000, range(6)
    exact = ex.render_exact(cam, field, n, match_ray_counts=True).values
    var = ex.render_exact(cam, field.assign(intensity=field["intensity"] ** 2), n, match_ray_counts=True).values
    mc = np.mean([rt.render(cam, field, n, s, method="montecarlo").values for s in seeds], axis=0)
    sel = exact >= 10 * float(field["intensity"].max())  # enough rays for the normal approximation
    z = (mc[sel] - exact[sel]) / np.sqrt(var[sel] / len(seeds))
    assert sel.sum() > 300
    assert 0.75 < np.mean(z**2) < 1.3 and np.abs(z).max() < 6.0, (np.mean(z**2), np.abs(z).max())
    assert mc.sum() == pytest.approx(exact.sum(), rel=0.01)


# ------------------------------------------------------------------ config
def test_config_checks_and_sweeps_by_dotted_path():
    with pytest.raises(ConfigError, match=r"illumination.thickness.*required"):
        validate_config(_raw(illumination={"profile": "gaussian"}))
    with pytest.raises(ConfigError, match=r"particles.depth_margin.*z_span > 0"):
        validate_config(_raw(particles={"depth_margin": 1.0, "z_span": 0.0}))
    with pytest.raises(ConfigError, match=r"sensor.hot_pixels.fraction"):
        validate_config(_raw(sensor={"hot_pixels": {"fraction": 2}}))
    with pytest.raises(ConfigError, match=r"illumination.profile"):
        validate_config(_raw(illumination={"profile": "sheet"}))
    raw = _raw(illumination={"thickness": 2.0})
    raw["sweep"].update({"illumination.profile": ["none", "gaussian"], "sensor.background.uniform": [0.0, 5.0]})
    cfg = validate_config(raw)
    cases = expand_cases(cfg)
    assert len(cases) == 4 and "illumination.profile~gaussian" in cases[-1].case_id
    ids = [case_config(cfg, c)["stage_ids"] for c in cases]
    assert len({i["particles"] for i in ids}) == 1  # one seeded field for every light setting
    assert len({i["simulate"] for i in ids}) == 4 and len({i["errors"] for i in ids}) == 4
    assert len({i["pinhole"] for i in ids}) == 2  # the background reaches the pinhole image; the sheet does not
    assert "illumination" in stage_config(cfg, cases[-1], "errors")


def test_the_levels_of_a_tolerance_sweep_share_the_image_noise():
    """Common random numbers: cases that differ only in an imperfection render with the same seeds (their
    stage ids differ, the noise stream does not), so the tolerance table compares like with like."""
    import yaml

    from lfstudy.study.case import _noise_stream
    from lfstudy.study.config import stage_config, validate_config
    from lfstudy.study.sweep import Sweep

    raw = yaml.safe_load((Path(__file__).parent / "data" / "tiny.yaml").read_text())
    raw["sweep"] = {"ppp": [0.002, 0.004], "camera.imperfections.lenslet_gap_error": [0.0, 0.02]}
    cfg = validate_config(raw)
    cases = Sweep(cfg).cases()
    sids = {
        (c.ppp, c["camera.imperfections.lenslet_gap_error"]): stage_config(cfg, c, "simulate")["stage_id"]
        for c in cases
    }
    assert sids[(0.002, 0.0)] != sids[(0.002, 0.02)]
    assert _noise_stream(sids[(0.002, 0.0)]) == _noise_stream(sids[(0.002, 0.02)])
    assert _noise_stream(sids[(0.002, 0.0)]) != _noise_stream(sids[(0.004, 0.0)])
