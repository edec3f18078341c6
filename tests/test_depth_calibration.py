"""Depth calibration by a traversed seeded volume (lfstudy.piv.depth, the depthcal stage)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lfstudy.piv.depth import correct_depth, depth_response
from lfstudy.study import case as cl
from lfstudy.study.config import case_config, expand_cases, load_config

ROOT = Path(__file__).resolve().parents[1]


def _result(w_mm: np.ndarray, z: np.ndarray, dz: float = 0.25) -> xr.Dataset:
    """A PIV result with w_mm on (z, y, x), every vector valid."""
    shape = w_mm.shape
    coords = {"z": z, "y": np.arange(shape[1]) * 0.4, "x": np.arange(shape[2]) * 0.4}
    zero = np.zeros(shape)
    return xr.Dataset(
        {
            "w_mm": (("z", "y", "x"), w_mm, {"units": "mm"}),
            "w": (("z", "y", "x"), w_mm / dz, {"units": "voxel"}),
            "u_mm": (("z", "y", "x"), zero),
            "v_mm": (("z", "y", "x"), zero),
            "valid": (("z", "y", "x"), np.ones(shape, bool)),
        },
        coords=coords,
    )


def _response(shift: float, z: np.ndarray) -> np.ndarray:
    """A compressive, non-linear depth response: weakest at the focal plane, sub-voxel shifts shortest."""
    return shift * (0.6 + 0.2 * np.tanh(np.abs(z))) * (0.8 + 0.2 * np.tanh(shift / 0.25))


def test_the_response_is_read_per_layer_and_inverted_exactly_at_the_traverses():
    z = np.array([-1.5, -0.5, 0.5, 1.5])
    shifts = [0.125, 0.25, 0.5]
    results = [(s, _result(np.broadcast_to(_response(s, z)[:, None, None], (4, 3, 3)).copy(), z)) for s in shifts]
    cal = depth_response(results)
    assert cal.attrs["resolves_depth"] == 1
    np.testing.assert_allclose(cal["gain"].sel(shift=0.25).values, _response(0.25, z) / 0.25)
    # readings equal to the response at a traverse come back as that traverse, with their sign
    for s in shifts:
        reading = np.broadcast_to(_response(s, z)[:, None, None], (4, 3, 3))
        for sign in (1.0, -1.0):
            out = correct_depth(_result(sign * reading, z), cal)
            np.testing.assert_allclose(out["w_mm"].values, sign * s, rtol=1e-12)
            np.testing.assert_allclose(out["w"].values, sign * s / 0.25, rtol=1e-12)
            np.testing.assert_allclose(out["w_mm_uncorrected"].values, sign * reading)
    # between the traverses the map is monotone and beyond the largest it keeps that traverse's gain
    readings = np.linspace(0.0, 1.0, 41)
    out = correct_depth(_result(np.broadcast_to(readings, (4, 3, 41)).copy(), z), cal)["w_mm"].values
    assert np.all(np.diff(out, axis=-1) > 0)
    assert out[0, 0, -1] == pytest.approx(1.0 * 0.5 / _response(0.5, z)[0])


def test_a_design_that_does_not_resolve_depth_is_left_as_read():
    z = np.array([-0.5, 0.5])
    flat = _result(np.full((2, 3, 3), 0.01), z)  # a 0.5 mm traverse read as 0.01 mm: gain 0.02
    cal = depth_response([(0.5, flat)], min_gain=0.3)
    assert cal.attrs["resolves_depth"] == 0
    out = correct_depth(_result(np.full((2, 3, 3), 0.02), z), cal)
    np.testing.assert_array_equal(out["w_mm"].values, 0.02)
    assert out.attrs["depth_corrected"] == 0 and out.attrs["depth_gain_total"] == pytest.approx(0.02)


def test_bad_calibration_results_are_refused_and_lost_traverses_are_not_corrected():
    z = np.array([0.0])
    ok = _result(np.full((1, 2, 2), 0.1), z)
    with pytest.raises(ValueError, match="positive"):
        depth_response([(-0.1, ok)])
    # a traverse the chain cannot follow at all (no valid vector) is a result: depth not resolved
    none_valid = ok.assign(valid=ok["valid"] & False)
    lost = depth_response([(0.05, ok), (0.1, none_valid)])
    assert lost.attrs["resolves_depth"] == 0 and lost["gain_total"].values[-1] == 0.0
    other_grid = _result(np.full((2, 2, 2), 0.1), np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="one PIV grid"):
        depth_response([(0.1, ok), (0.2, other_grid)])


def test_repeated_calibration_volumes_are_pooled_and_their_spread_is_kept():
    z = np.array([-0.5, 0.5])
    low, high = (_result(np.full((2, 3, 3), g * 0.25), z) for g in (0.8, 1.0))
    cal = depth_response([(0.25, low), (0.25, high)])
    assert cal.attrs["repeats"] == 2 and cal.sizes["shift"] == 1
    np.testing.assert_allclose(cal["gain"].values, 0.9)
    assert int(cal["n_valid"].values[0, 0]) == 18
    assert float(cal["gain_total_sd"].values[0]) == pytest.approx(np.std([0.8, 1.0], ddof=1))
    single = depth_response([(0.25, low)])
    assert single.attrs["repeats"] == 1 and "gain_total_sd" not in single
    with pytest.raises(ValueError, match="same number of repeated"):
        depth_response([(0.25, low), (0.25, high), (0.5, low)])


@pytest.mark.slow  # ~27 s (measured)
def test_the_calibration_corrects_a_held_out_depth_shift():
    """The demo's first MART design reads depth about a third short. Calibrated on its own traversed
    volume (another particle field, traverses of 0.5 and 1 voxel), a uniform z shift of 0.75 voxel —
    not a traverse — comes back within 10 %, where the raw reading is over 20 % short."""
    cfg = load_config(ROOT / "config" / "demo.yaml")
    ccfg = case_config(cfg, expand_cases(cfg)[0])
    ccfg["reconstruct"]["method"] = "mart"
    ccfg["camera"]["sensor"].update(n_pixels_x=384, n_pixels_y=384)
    ccfg["depth_calibration"].update(shifts=[0.5, 1.0], repeats=2)
    truth = 0.75 * 0.25  # mm: grid.voxel_z 0.25
    ccfg["flow"] = {"name": "uniform_z", "kind": "uniform", "displacement": [0.0, 0.0, truth]}
    cam = cl.case_camera(ccfg)
    from lfstudy.lightfield.calibrate import find_lenslet_centers

    centers = find_lenslet_centers(cl.case_pinhole(ccfg), cam)
    cal = cl.case_depth_calibration(ccfg, centers)
    assert cal.attrs["resolves_depth"] == 1 and (cal["gain_total"] < 0.9).all()
    # two independently seeded volumes: their gains differ, and their vectors are pooled
    assert cal.attrs["repeats"] == 2 and (cal["gain_total_sd"] > 0).all()

    sim = cl.simulate_case(copy.deepcopy(ccfg))
    vols = [cl.render_volume(sim[f"image_{f}"], centers, ccfg)[2].load() for f in "ab"]
    res = cl.case_piv(ccfg, *vols)
    out = correct_depth(res, cal)
    valid = out["valid"].values
    raw = float(out["w_mm_uncorrected"].values[valid].mean())
    fixed = float(out["w_mm"].values[valid].mean())
    assert raw < 0.8 * truth, raw
    assert abs(fixed - truth) < 0.1 * truth, (raw, fixed)
    # x and y are untouched
    np.testing.assert_array_equal(out["u_mm"].values, res["u_mm"].values)


@pytest.mark.parametrize("repeats", [1, 2])
def test_uncertainty_of_w_is_divided_by_the_gain_and_gains_its_spread(repeats):
    """σ_w goes through the depth map like w; with repeats the gain's own spread adds in quadrature."""
    z = np.array([-0.5, 0.5])
    gain = {0.25: [0.5, 0.5], 0.5: [0.5, 0.5]}
    if repeats == 2:
        gain = {0.25: [0.45, 0.55], 0.5: [0.45, 0.55]}  # mean 0.5, sd 0.0707 between repeats
    results = [(s, _result(np.full((2, 2, 2), s * g), z)) for s, gs in gain.items() for g in gs[:repeats]]
    cal = depth_response(results)
    res = _result(np.full((2, 2, 2), 0.1), z)  # read 0.1 mm: true 0.2 mm through gain 0.5
    res["unc_w_mm"] = (("z", "y", "x"), np.full((2, 2, 2), 0.01), {"units": "mm"})
    res["unc_w_mm"][0, 0, 0] = np.nan  # an invalid vector stays without uncertainty
    res["unc_w"] = res["unc_w_mm"] / 0.25
    out = correct_depth(res, cal)
    np.testing.assert_allclose(out["w_mm"].values, 0.2, rtol=1e-12)
    rel = 0.0 if repeats == 1 else np.std([0.45, 0.55], ddof=1) / 0.5
    expect = np.sqrt((0.01 / 0.5) ** 2 + (0.2 * rel) ** 2)
    np.testing.assert_allclose(out["unc_w_mm"].values.ravel()[1:], expect, rtol=1e-9)
    np.testing.assert_allclose(out["unc_w"].values.ravel()[1:], expect / 0.25, rtol=1e-9)
    assert np.isnan(out["unc_w_mm"].values[0, 0, 0]) and np.isnan(out["unc_w"].values[0, 0, 0])
    np.testing.assert_allclose(out["unc_w_mm_uncorrected"].values.ravel()[1:], 0.01)
