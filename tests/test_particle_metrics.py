"""Particles found, ghosts and the found particles' own crosstalk (lfstudy.study.particle_metrics)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lfstudy.study.particle_metrics import particle_metrics

ROOT = Path(__file__).resolve().parents[1]
VOX = (0.1, 0.1, 0.25)  # dx, dy, dz [mm]
BOUNDS = ((0.0, 10.0), (0.0, 10.0), (-2.0, 2.0))


def _ds(xyz: np.ndarray) -> xr.Dataset:
    return xr.Dataset({k: ("particle", xyz[:, i]) for i, k in enumerate("xyz")})


def _scene(seed: int = 0, n: int = 400):
    rng = np.random.default_rng(seed)
    ta = np.column_stack([rng.uniform(0, 10, n), rng.uniform(0, 10, n), rng.uniform(-2, 2, n)])
    shift = np.array([0.3, 0.4, 0.0])  # a lateral shift of 0.5 mm
    return ta, ta + shift, rng


def test_found_ghosts_and_position_errors_are_counted():
    ta, tb, rng = _scene()
    n = len(ta)
    # frame a: the first 300 found (0.1 voxel off in z), the rest missed; 100 ghosts far from any particle
    fa = ta[:300] + np.array([0.0, 0.0, 0.025])
    ghosts = np.column_stack([rng.uniform(0, 10, 100), rng.uniform(0, 10, 100), np.full(100, 5.0)])
    # frame b: every particle found, one 0.6 voxel off in x (not found: beyond half a voxel)
    fb = tb.copy()
    fb[0, 0] += 0.06
    m = particle_metrics([_ds(np.vstack([fa, ghosts])), _ds(fb)], [_ds(ta), _ds(tb)], VOX, BOUNDS)
    inside_b = int(np.all((tb >= [0, 0, -2]) & (tb <= [10, 10, 2]), axis=1).sum())  # the shift moves some out
    found_b = inside_b - int(np.all((tb[0] >= [0, 0, -2]) & (tb[0] <= [10, 10, 2])))
    assert m["found_percent"] == pytest.approx(100 * (300 + found_b) / (n + inside_b))
    # ghosts: the 100 placed ones, plus frame b's displaced one (no true particle within half a voxel)
    assert m["ghost_percent"] == pytest.approx(100 * 101 / (400 + n))
    assert m["particle_rms_z_mm"] == pytest.approx(0.025 * math.sqrt(300 / (300 + found_b)))
    assert m["particle_rms_x_mm"] == pytest.approx(0.0)


def test_found_particles_crosstalk_is_their_own_spurious_w():
    ta, tb, rng = _scene(1)
    fa = ta + rng.normal(0, 0.01, ta.shape)
    fb = tb + rng.normal(0, 0.01, tb.shape) + [0.0, 0.0, 0.05]  # every found particle reads w = +0.05 mm
    m = particle_metrics([_ds(fa), _ds(fb)], [_ds(ta), _ds(tb)], VOX, BOUNDS)
    assert m["particle_bias_w_mm"] == pytest.approx(0.05, abs=0.003)
    assert m["particle_crosstalk_z"] == pytest.approx(0.05 / 0.5, abs=0.006)
    # ghosts that move in depth do not enter the found particles' crosstalk
    gh = np.column_stack([rng.uniform(0, 10, 200), rng.uniform(0, 10, 200), np.full(200, 4.0)])
    m2 = particle_metrics([_ds(np.vstack([fa, gh])), _ds(np.vstack([fb, gh + 0.4]))], [_ds(ta), _ds(tb)], VOX, BOUNDS)
    assert m2["particle_crosstalk_z"] == pytest.approx(m["particle_crosstalk_z"])
    assert m2["ghost_percent"] > m["ghost_percent"] + 20


def test_found_in_focus_counts_the_depth_of_field_alone():
    """Particles within the depth of field about the focal plane missed, the others found."""
    ta, tb, _ = _scene(3)
    focus = (-0.4, 0.4)
    keep = lambda t: t[np.abs(t[:, 2]) > 0.4]  # noqa: E731
    m = particle_metrics([_ds(keep(ta)), _ds(keep(tb))], [_ds(ta), _ds(tb)], VOX, BOUNDS, focus)
    assert m["found_in_focus_percent"] == 0.0 and 75.0 < m["found_percent"] < 85.0
    assert math.isnan(particle_metrics([_ds(ta), _ds(tb)], [_ds(ta), _ds(tb)], VOX, BOUNDS)["found_in_focus_percent"])


def test_a_non_uniform_flow_has_no_crosstalk_and_empty_lists_give_nan():
    ta, _, _ = _scene(2)
    tb = ta + np.column_stack([0.1 * ta[:, 1], np.zeros(len(ta)), np.zeros(len(ta))])  # shear
    m = particle_metrics([_ds(ta), _ds(tb)], [_ds(ta), _ds(tb)], VOX, BOUNDS)
    assert m["found_percent"] == pytest.approx(100.0) and m["ghost_percent"] == 0.0
    assert math.isnan(m["particle_crosstalk_z"])
    empty = _ds(np.zeros((0, 3)))
    e = particle_metrics([empty, empty], [_ds(ta), _ds(tb)], VOX, BOUNDS)
    assert e["found_percent"] == 0.0 and math.isnan(e["ghost_percent"]) and math.isnan(e["particle_rms_z_mm"])
    with pytest.raises(ValueError, match="voxel_mm"):
        particle_metrics([_ds(ta), _ds(tb)], [_ds(ta), _ds(tb)], (0.1, 0.0, 0.2), BOUNDS)
    with pytest.raises(ValueError, match="particle count"):
        particle_metrics([_ds(ta), _ds(tb)], [_ds(ta), _ds(tb[:10])], VOX, BOUNDS)


def test_the_errors_stage_scores_the_lists_beside_an_ipr_case_s_volumes(tmp_path):
    """run_errors of an ipr case reads volume_{a,b}.particles.zarr beside the volume (here the true
    particles with a third of frame b's moved 1 voxel in z, the rest exact) and writes the particle
    metrics."""
    from lfstudy import io
    from lfstudy import workflow as wf
    from lfstudy.study import case as cl
    from lfstudy.study.config import load_config, stage_config
    from lfstudy.study.sweep import Sweep

    cfg = load_config(ROOT / "tests" / "data" / "tiny.yaml")
    cfg["sweep"] = {"ppp": [0.002], "flow": ["uniform_x"], "reconstruct.method": ["ipr"]}
    sweep = Sweep(cfg)
    for case in sweep.cases():
        sc, full = stage_config(cfg, case, "errors"), sweep.apply(case)
        d = tmp_path / case["reconstruct.method"]
        d.mkdir()
        pa = cl.case_particles(full)
        pb = cl.case_displaced(full, pa)
        va, vb = cl.oracle_volumes(full, pa, pb)  # the true volumes stand for the reconstruction
        io.write_zarr(pa, d / "particles_a.zarr")
        io.write_zarr(pb, d / "particles_b.zarr")
        io.write_zarr(va, d / "volume_a.zarr")
        io.write_zarr(cl.case_piv(full, va, vb), d / "piv.zarr")
        moved = pb.copy(deep=True)
        dz = float(np.median(np.diff(cl.case_grid(full).z)))
        moved["z"][::3] = moved["z"][::3] + dz
        io.write_zarr(pa, d / "volume_a.particles.zarr")
        io.write_zarr(moved, d / "volume_b.particles.zarr")
        wf.run_errors(
            sc, d / "piv.zarr", d / "volume_a.zarr", d / "particles_a.zarr", d / "errors.zarr", d / "particles_b.zarr"
        )
        e = io.open_zarr(d / "errors.zarr")
        n = pa.sizes["particle"]
        assert float(e["ghost_percent"]) == pytest.approx(100 * len(range(0, n, 3)) / (2 * n))
        assert 75.0 < float(e["found_percent"]) < 90.0 and float(e["particle_rms_x_mm"]) == 0.0
        assert float(e["particle_bias_w_mm"]) == pytest.approx(0.0, abs=1e-12)  # only exact pairs count
        # the seeding's density per lenslet and depth cell is there for every method
        from lfstudy.study.metrics import particles_per_cell

        g = cl.case_grid(full)
        bounds = [(float(c[0]), float(c[-1])) for c in (g.x, g.y, g.z)]
        assert float(e["particles_per_cell"]) == pytest.approx(particles_per_cell(cl.case_camera(full), pa, bounds))
        assert 0.0 < float(e["particles_per_cell"]) < 1.0


def test_depth_unknown_percent_reads_the_paired_pivs_attrs():
    from lfstudy.study.particle_metrics import depth_unknown_percent

    attrs = {"paired_depth_unknown_a": 30, "paired_depth_unknown_b": 10, "paired_particles_a": 100}
    assert math.isnan(depth_unknown_percent(attrs))  # not a paired PIV's (or an older one's) attrs
    assert depth_unknown_percent(attrs | {"paired_particles_b": 300}) == pytest.approx(10.0)
    assert math.isnan(depth_unknown_percent(attrs | {"paired_particles_a": 0, "paired_particles_b": 0}))


def test_focus_scatter_ratio_reads_the_paired_pivs_weight_bands():
    """The band nearest focus over the best band (not the farthest); NaN without depth weights or bands."""
    from lfstudy.study.particle_metrics import focus_scatter_ratio

    assert focus_scatter_ratio({"paired_weight_sd_mm": [0.045, 0.017, 0.018, 0.021]}) == pytest.approx(0.045 / 0.017)
    assert focus_scatter_ratio({"paired_weight_sd_mm": [0.01, 0.02]}) == 1.0  # the band nearest focus is the best
    for attrs in ({}, {"paired_weight_sd_mm": []}, {"paired_weight_sd_mm": [0.0, 0.0]}):
        assert math.isnan(focus_scatter_ratio(attrs))
