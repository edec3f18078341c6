"""Tests of lfstudy.study.metrics: errors against the truth, Q, run times, the sweep Dataset."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lfstudy import io
from lfstudy.simulate.flows import HillVortex, UniformFlow
from lfstudy.study.metrics import (
    case_errors,
    locking_excess,
    peak_locking_c1,
    reconstruction_quality,
    render_truth,
)
from lfstudy.study.sweep import Case
from lfstudy.study.table import combine_cases, from_csv, stage_times, to_csv

ROOT = Path(__file__).resolve().parents[1]
VOX = 0.125  # mm, the thesis' lenslet pitch at M = -1


def synthetic_piv(
    u, v, w, *, valid=None, shape=(4, 5, 6), spacing=(8, 16, 16), vox=VOX, with_index=True, with_mm=True
) -> xr.Dataset:
    """A WIDIM-like result on a (z, y, x) grid of window centres (voxels and mm)."""
    _nz, _ny, _nx = shape
    idx = {d: (np.arange(n) + 0.5) * s for d, n, s in zip("zyx", shape, spacing)}
    coords = {d: (d, (idx[d] - idx[d].mean()) * vox, {"units": "mm"}) for d in "zyx"}
    if with_index:
        coords.update({f"{d}_index": (d, idx[d], {"units": "voxel"}) for d in "zyx"})
    b = lambda a: np.broadcast_to(np.asarray(a, float), shape).copy()  # noqa: E731
    data = {}
    for c, val in zip("uvw", (u, v, w)):
        data[c] = (("z", "y", "x"), b(val), {"units": "voxel"})
        if with_mm:
            data[f"{c}_mm"] = (("z", "y", "x"), b(val) * vox, {"units": "mm"})
    data["valid"] = (("z", "y", "x"), np.ones(shape, bool) if valid is None else valid)
    data["peak"] = (("z", "y", "x"), np.full(shape, 0.8))
    data["corrector_rms"] = ("pass", [1.0, 0.2, 0.05])
    data["valid_percent"] = ("pass", [90.0, 97.0, 99.0])
    attrs = {"final_spacing": list(spacing), "final_window": [2 * v for v in spacing]}  # 50 % overlap
    ds = xr.Dataset(data, coords=coords, attrs=attrs)
    return ds.assign_coords({"pass": ("pass", [1, 2, 3]), "level": ("pass", [1, 2, 2])})


def test_uniform_x_sign_and_zero_bias():
    # Sec. 7.1: a +0.5625 mm flow imaged by 0.125 mm voxels is +4.5 voxels in the object frame.
    err = case_errors(synthetic_piv(4.5, 0.0, 0.0), UniformFlow((0.5625, 0.0, 0.0)))
    for ax in "xyz":
        assert float(err[f"bias_{ax}"]) == pytest.approx(0.0, abs=1e-12)
        assert float(err[f"rms_{ax}"]) == pytest.approx(0.0, abs=1e-12)
    assert float(err["mean_x"]) == pytest.approx(4.5)
    assert float(err["mean_x_mm"]) == pytest.approx(0.5625)
    assert float(err["true_x"]) == pytest.approx(4.5)
    assert float(err["valid_percent"]) == 100.0
    assert err["u_true"].dims == ("z", "y", "x")
    assert np.allclose(err["voxel_x"], VOX)


@pytest.mark.parametrize("with_index,with_mm", [(True, True), (False, True), (True, False)])
def test_known_errors_exact(with_index, with_mm):
    rng = np.random.default_rng(0)
    shape = (4, 5, 6)
    noise = rng.normal(0.0, 0.07, shape)
    u = 4.45 + noise  # thesis' 0.05 voxel under-estimate
    valid = np.ones(shape, bool)
    valid[0, 0, :3] = False
    u[0, 0, :3] = 1e6  # outliers flagged invalid must not count
    u[1, 1, 1] = np.nan  # a NaN never leaks into the statistics
    err = case_errors(
        synthetic_piv(u, 0.0, 0.25, valid=valid, with_index=with_index, with_mm=with_mm),
        UniformFlow((0.5625, 0.0, 0.0)),
    )
    sel = valid & np.isfinite(u)
    e = u[sel] - 4.5
    assert float(err["bias_x"]) == pytest.approx(e.mean(), abs=1e-12)
    assert float(err["rms_x"]) == pytest.approx(np.sqrt(np.mean(e**2)), abs=1e-12)
    assert float(err["std_x"]) == pytest.approx(e.std(), abs=1e-12)
    assert float(err["bias_x_mm"]) == pytest.approx(e.mean() * VOX, abs=1e-12)
    assert float(err["bias_z"]) == pytest.approx(0.25)
    assert float(err["std_z"]) == pytest.approx(0.0, abs=1e-12)
    assert float(err["rms_total"]) == pytest.approx(math.hypot(float(err["rms_x"]), 0.25))
    assert float(err["valid_percent"]) == pytest.approx(100.0 * sel.sum() / sel.size)
    assert int(err["n_valid"]) == sel.sum()
    assert np.isnan(err["u_err"].values[~sel]).all()
    assert np.isfinite(err["u_err"].values[sel]).all()
    assert float(err["bias_x"]) ** 2 + float(err["std_x"]) ** 2 == pytest.approx(float(err["rms_x"]) ** 2)


def test_all_invalid_gives_nan_and_zero_percent():
    piv = synthetic_piv(4.5, 0, 0, valid=np.zeros((4, 5, 6), bool))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        err = case_errors(piv, UniformFlow((0.5625, 0, 0)))
    assert float(err["valid_percent"]) == 0.0
    for name in ("bias_x", "rms_x", "std_z", "rms_total", "mean_x", "rel_error", "depth_mm", "locking_excess_z"):
        assert np.isnan(float(err[name])), name


def test_hill_vortex_truth_is_midpoint():
    flow = HillVortex(radius=1.5, u0=0.25)
    piv = synthetic_piv(0.0, 0.0, 0.0)
    err = case_errors(piv, flow, dt=1.0, n_steps=50)
    # Measured zero: the error is minus the true displacement everywhere.
    assert np.allclose(err["w_err_mm"], -err["w_true_mm"])
    assert float(err["rms_z_mm"]) > 0


def test_voxel_size_required_when_not_inferable():
    piv = synthetic_piv(0.0, 0.0, 0.0, with_index=False)
    piv.attrs.clear()
    with pytest.raises(ValueError, match="voxel_size"):
        case_errors(piv, UniformFlow((0, 0, 0)))
    err = case_errors(piv, UniformFlow((0.125, 0, 0)), voxel_size=0.125)
    assert float(err["bias_x"]) == pytest.approx(-1.0)


def test_peak_locking_figures():
    rng = np.random.default_rng(1)
    broad = rng.uniform(-5, 5, 20000)
    assert peak_locking_c1(broad) < 0.1
    assert peak_locking_c1(np.round(broad)) == pytest.approx(1.0)
    # Sec. 7.2: a true 2.5 voxel shift measured as 2 or 3 (locked) vs Gaussian about 2.5.
    locked = 2.5 + rng.choice([-0.5, 0.5], 5000) + rng.normal(0, 0.05, 5000)
    free = 2.5 + rng.normal(0, 0.07, 5000)
    assert locking_excess(locked, 2.5) > 0.3
    assert abs(locking_excess(free, 2.5)) < 0.02
    assert np.isnan(locking_excess([np.nan], [1.0]))


def _particles(n, seed):
    rng = np.random.default_rng(seed)
    return xr.Dataset(
        {
            "x": ("particle", rng.uniform(-1.4, 1.4, n)),
            "y": ("particle", rng.uniform(-1.2, 1.2, n)),
            "z": ("particle", rng.uniform(-0.8, 0.5, n)),
            "intensity": ("particle", rng.uniform(0.5, 1.0, n)),
        }
    )


def _grid(shape=(40, 36, 44), step=(0.05, 0.02, 0.02)):
    return {d: (np.arange(n) - (n - 1) / 2) * s for d, n, s in zip("zyx", shape, step)}


def _gaussian(coords, centre, sigma):
    """A Gaussian blob evaluated at the voxel centres (independent of render_truth)."""
    g = [np.exp(-0.5 * ((coords[d] - c) / s) ** 2) for d, c, s in zip("zyx", centre, sigma)]
    return g[0][:, None, None] * g[1][None, :, None] * g[2][None, None, :]


def test_reconstruction_quality_matches_the_analytic_overlap_of_two_gaussians():
    """Q of a Gaussian volume against a Gaussian particle of another size and position is the
    normalised overlap of two Gaussians: Π sqrt(2 s1 s2 / (s1² + s2²)) · exp(−Δ² / (2 (s1² + s2²)))."""
    coords = _grid()
    truth_sigma = (0.2, 0.06, 0.06)
    vol_sigma = (0.3, 0.05, 0.08)
    shift = (0.1, 0.0, 0.04)  # the volume's blob is off the particle by this much
    p = xr.Dataset({d: ("particle", [0.0]) for d in "xyz"})
    vol = xr.DataArray(_gaussian(coords, shift, vol_sigma), dims=("z", "y", "x"), coords=coords)
    expect = 1.0
    for s1, s2, d in zip(truth_sigma, vol_sigma, shift):
        expect *= np.sqrt(2 * s1 * s2 / (s1**2 + s2**2)) * np.exp(-(d**2) / (2 * (s1**2 + s2**2)))
    q = reconstruction_quality(vol, p, sigma_mm=truth_sigma)
    assert q == pytest.approx(expect, rel=0.01)
    assert q < 0.9  # the sizes and the offset really do lower it
    assert reconstruction_quality(vol.chunk({"z": 3}), p, sigma_mm=truth_sigma, planes_per_block=5) == pytest.approx(q)
    assert np.isnan(reconstruction_quality(vol * 0, p, sigma_mm=truth_sigma))


def test_reconstruction_quality_of_unrelated_fields_is_low():
    coords = _grid((20, 48, 56), (0.1, 0.05, 0.05))
    p, other = _particles(12, 3), _particles(12, 99)
    vol = xr.DataArray(render_truth(coords, other, sigma_mm=0.05), dims=("z", "y", "x"), coords=coords)
    assert reconstruction_quality(vol, p, sigma_mm=0.05) < 0.15


def test_render_truth_is_voxel_integrated():
    """Intensity is conserved and the centroid is the particle's, wherever it sits in its voxel."""
    coords = {d: np.arange(15) * 0.1 for d in "zyx"}
    coords["z"] = np.cumsum(np.linspace(0.08, 0.14, 15))  # uneven planes too
    for pos in (0.70, 0.73, 0.755):
        p = xr.Dataset({d: ("particle", [pos]) for d in "xyz"} | {"intensity": ("particle", [2.0])})
        v = render_truth(coords, p, sigma_mm=0.1)
        assert v.sum() == pytest.approx(2.0, rel=5e-4)  # cut at 4 sigma per axis: 6e-5 each
        cx = float((v.sum((0, 1)) * coords["x"]).sum() / v.sum())
        assert cx == pytest.approx(pos, abs=0.002)
    with pytest.raises(ValueError, match="sigma_mm"):
        render_truth(coords, p, sigma_mm=0.0)


def _case(mag, fnum, pitch, ppp, flow, **dotted):
    return Case.of(magnification=mag, fnumber=fnum, lenslet_pitch=pitch, ppp=ppp, flow=flow, **dotted)


def test_stage_times(tmp_path):
    cid = _case(-1.0, "matched", 0.125, 0.001, "uniform_x").case_id
    for rule, names, secs in (("piv", [""], [3.0]), ("simulate", ["_a", "_b"], [1.0, 2.0])):
        for nm, s in zip(names, secs):
            f = tmp_path / rule / f"{cid}{nm}.tsv"
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_text(f"s\th:m:s\tmax_rss\n{s}\t0:00:0{int(s)}\t100.0\n")
    other = tmp_path / "piv" / (cid + "_fast.tsv")  # another flow's table: not ours
    other.write_text("s\th:m:s\n50\t0:00:50\n")
    t = stage_times(tmp_path, {"piv": cid, "simulate": cid, "refocus": cid})
    assert t == {"piv": 3.0, "simulate": 3.0, "total": 6.0}
    assert stage_times(tmp_path / "missing", {"piv": cid}) == {}
    # frame a's own stage (shared by the flows) at the design: its table counts under the rule, frame b's at the case
    design = cid.rsplit("/flow~", 1)[0]
    (tmp_path / "simulate" / f"{design}_a.tsv").write_text("s\th:m:s\n4.0\t0:00:04\n")
    t = stage_times(tmp_path, {"piv": cid, "simulate": cid, "simulate_a": design})
    assert t == {"piv": 3.0, "simulate": 6.0, "total": 9.0}


def _scalars(rms, q):
    return xr.Dataset(
        {
            "rms_x": ((), rms, {"units": "voxel", "long_name": "RMS error x"}),
            "Q": ((), q, {"units": "1", "long_name": "reconstruction quality Q"}),
        }
    )


def test_combine_cases_dims_sel_and_csv(tmp_path):
    rows = [
        (_case(-1.0, "matched", 0.125, 0.001, "uniform_x"), _scalars(0.07, 0.8)),
        (_case(-1.0, 4.0, 0.125, 0.001, "uniform_x"), _scalars(0.09, 0.7)),
        (_case(-1.0, "matched", 0.125, 0.005, "uniform_x"), _scalars(0.2, 0.5)),
        (_case(-0.8, "matched", 0.125, 0.001, "hill"), _scalars(0.3, 0.6)),
    ]
    study = combine_cases(rows)
    assert study["rms_x"].dims == ("magnification", "fnumber", "lenslet_pitch", "ppp", "flow")
    assert list(study["fnumber"].values) == ["matched", "4"]
    sub = study.sel(ppp=0.001)
    assert float(
        sub["rms_x"].sel(magnification=-1.0, fnumber="4", lenslet_pitch=0.125, flow="uniform_x")
    ) == pytest.approx(0.09)
    assert np.isnan(
        float(study["rms_x"].sel(magnification=-0.8, fnumber="4", lenslet_pitch=0.125, ppp=0.005, flow="hill"))
    )
    assert study["rms_x"].attrs["units"] == "voxel"
    assert int(study["computed"].sum()) == 4
    for v in study.variables.values():
        assert "units" in v.attrs and "long_name" in v.attrs
    # zarr round trip (string coords) and CSV round trip
    io.write_zarr(study, tmp_path / "study.zarr")
    back = io.open_zarr(tmp_path / "study.zarr").load()
    xr.testing.assert_allclose(back["rms_x"], study["rms_x"])
    csv = to_csv(study, tmp_path / "study.csv")
    import pandas as pd

    df = pd.read_csv(csv)
    assert len(df) == 4
    assert "mag~-1/fnum~4/pitch~0.125/ppp~0.001/flow~uniform_x" in set(df["case_id"])
    again = from_csv(csv)
    xr.testing.assert_allclose(again["rms_x"], study["rms_x"])
    xr.testing.assert_allclose(again["Q"], study["Q"])


def test_on_real_widim_result():
    """The contract end to end: widim on a +4.5 voxel x-shift, physical coords in mm."""
    from lfstudy.piv import widim
    from lfstudy.piv.synthetic import particle_pair

    a, b = particle_pair((24, 48, 48), (0.0, 0.0, 4.5), density=0.02, seed=1)
    co = {d: (np.arange(n) - (n - 1) / 2) * VOX for d, n in zip("zyx", a.shape)}
    fa = xr.DataArray(a, dims=("z", "y", "x"), coords=co)
    res = widim(fa, fa.copy(data=b), window=(16, 16, 16), spacing=(8, 8, 8), levels=1)
    err = case_errors(res, UniformFlow((0.5625, 0.0, 0.0)))
    assert float(err["mean_x"]) == pytest.approx(4.5, abs=0.1)  # object frame: +, not -4.45
    assert abs(float(err["bias_x"])) < 0.1
    assert float(err["std_x"]) < 0.2
    assert float(err["valid_percent"]) > 90


def test_resolution_and_relative_error_in_mm():
    """Designs compare in mm: window and spacing in mm per axis, the depth valid vectors span, and
    the total error over the true displacement."""
    piv = synthetic_piv(4.6, 0.0, 0.0, shape=(4, 5, 6), spacing=(8, 16, 16))
    piv.attrs["final_window"] = [16, 32, 32]
    valid = np.ones((4, 5, 6), bool)
    valid[0] = False  # the first row of windows in z is invalid
    piv["valid"] = (("z", "y", "x"), valid)
    err = case_errors(piv, UniformFlow((0.5625, 0.0, 0.0)))
    assert float(err["window_mm_x"]) == pytest.approx(32 * VOX) and float(err["window_mm_z"]) == pytest.approx(16 * VOX)
    assert float(err["spacing_mm_y"]) == pytest.approx(16 * VOX) and float(err["spacing_mm_z"]) == pytest.approx(
        8 * VOX
    )
    # valid centres span 3 rows of 8 voxels (16 voxels) plus one final window of 16
    assert float(err["depth_mm"]) == pytest.approx((16 + 16) * VOX)
    assert float(err["true_mag_mm"]) == pytest.approx(0.5625)
    assert float(err["rel_error"]) == pytest.approx(0.1 * VOX / 0.5625)
    for v in ("window_mm_x", "spacing_mm_z", "depth_mm", "rel_error", "true_mag_mm"):
        assert err[v].attrs["units"] in ("mm", "1") and err[v].attrs["long_name"]


def test_sigma_against_the_oracle_takes_what_the_windows_measure_out_of_the_error():
    """The oracle reads the flow 0.1 voxel short everywhere (as a window response would), and the case is the
    oracle plus noise of the size of its σ: against the truth σ misses that response, against the oracle it is
    right; vectors invalid in the oracle are left out."""
    from types import SimpleNamespace

    from lfstudy.study.metrics import case_metrics

    shape = (4, 5, 6)
    rng = np.random.default_rng(3)
    e = rng.normal(0.0, 0.05, shape)
    oracle = synthetic_piv(4.4, 0.0, 0.0).assign_attrs(oracle_seconds=1.0)
    oracle["valid"] = (("z", "y", "x"), np.ones(shape, bool))
    oracle["valid"].values[0, :, :] = False
    case = synthetic_piv(4.4 + e, 0.0, 0.0).assign_attrs(final_window=[16, 32, 32])
    case["unc_u_mm"] = (("z", "y", "x"), np.full(shape, 0.05 * VOX))
    z, y, x = (np.linspace(-1, 1, n) for n in (9, 10, 11))
    parts = xr.Dataset({"x": ("particle", [0.1]), "y": ("particle", [0.0]), "z": ("particle", [0.2])})
    vol = xr.DataArray(render_truth({"z": z, "y": y, "x": x}, parts, sigma_mm=0.2), dims=("z", "y", "x"))
    vol = vol.assign_coords(z=z, y=y, x=x)
    cam = SimpleNamespace(fov_x=12.5, fov_y=9.0)
    out = case_metrics(case, UniformFlow((0.5625, 0, 0)), cam, vol, parts, sigma_mm=0.2, oracle=oracle)
    ok = np.ones(shape, bool)
    ok[0] = False
    assert float(out["unc_coverage_oracle_x"]) == pytest.approx(np.mean(np.abs(e[ok]) <= 0.05), abs=1e-12)
    assert float(out["unc_ratio_oracle_x"]) == pytest.approx(np.sqrt(np.mean(e[ok] ** 2)) / 0.05, rel=1e-9)
    assert 0.5 < float(out["unc_coverage_oracle_x"]) < 0.85
    # against the (window-averaged = point) truth the 0.1-voxel response counts as error: σ reads 2x short
    assert float(out["unc_coverage_x"]) < 0.3 and float(out["unc_ratio_x"]) > 1.8
    assert np.isnan(float(out["unc_ratio_oracle_y"]))  # no σ of v
    assert out["unc_ratio_oracle_x"].attrs["long_name"] and out["unc_coverage_oracle_z"].attrs["units"] == "1"


def test_case_metrics_adds_fov_q_and_depth_gain_with_table_attrs():
    """The science run_errors used to do inline: a pure function of the PIV result, the camera, the
    volume and the particles; every scalar's attrs from the metric table."""
    from types import SimpleNamespace

    from lfstudy.study.metric_table import METRICS, metric
    from lfstudy.study.metrics import case_metrics

    piv = synthetic_piv(4.5, 0.0, 0.0)
    piv.attrs.update(depth_gain_total=0.61, final_window=[16, 32, 32])
    z, y, x = (np.linspace(-1, 1, n) for n in (9, 10, 11))
    parts = xr.Dataset({"x": ("particle", [0.1]), "y": ("particle", [0.0]), "z": ("particle", [0.2])})
    vol = xr.DataArray(render_truth({"z": z, "y": y, "x": x}, parts, sigma_mm=0.2), dims=("z", "y", "x"))
    vol = vol.assign_coords(z=z, y=y, x=x)
    cam = SimpleNamespace(fov_x=12.5, fov_y=9.0)
    out = case_metrics(piv, UniformFlow((0.5625, 0.0, 0.0)), cam, vol, parts, sigma_mm=0.2)
    assert float(out["Q"]) == pytest.approx(1.0) and out["Q"].attrs["truth_sigma_mm"] == [0.2, 0.2, 0.2]
    assert float(out["fov_x_mm"]) == 12.5 and float(out["fov_y_mm"]) == 9.0
    assert float(out["depth_gain"]) == pytest.approx(0.61)
    assert float(out["rms_total_mm"]) == pytest.approx(
        float(case_errors(piv, UniformFlow((0.5625, 0, 0)))["rms_total_mm"])
    )
    del piv.attrs["depth_gain_total"]
    assert np.isnan(float(case_metrics(piv, UniformFlow((0.5625, 0, 0)), cam, vol, parts, sigma_mm=0.2)["depth_gain"]))
    # with the oracle (here exact, the case 0.1 voxel off in w): its metrics, the budget and its vectors
    case_piv = synthetic_piv(4.5, 0.0, 0.1).assign_attrs(final_window=[16, 32, 32])
    oracle = synthetic_piv(4.5, 0.0, 0.0).assign_attrs(oracle_seconds=1.5)
    # a particle method's list (here the true particles themselves) adds its rows through ``extra``
    from lfstudy.optics import PlenopticCamera
    from lfstudy.study.metrics import particles_per_cell
    from lfstudy.study.particle_metrics import particle_metrics

    moved = parts.assign(x=parts.x + 0.5625)
    found = particle_metrics([parts, moved], [parts, moved], (0.2, 0.2, 0.2), [(-1, 1)] * 3, (-0.5, 0.5))
    thesis = PlenopticCamera(4872, 3248, 0.0074, 0.125, 0.5, 50.0, -1.0)
    found["particles_per_cell"] = particles_per_cell(thesis, parts, [(-1, 1)] * 3)  # run_errors adds it to every case
    # and, for a particle method, the share the paired PIV left out for want of depth (from its result's attrs)
    from lfstudy.study.particle_metrics import depth_unknown_percent

    paired = {"paired_depth_unknown_a": 0, "paired_depth_unknown_b": 1}
    paired |= {"paired_particles_a": 1, "paired_particles_b": 1}
    found["depth_unknown_percent"] = depth_unknown_percent(paired)
    found["focus_scatter_ratio"] = 2.5  # focus_scatter_ratio(piv.attrs), as run_errors adds it
    out = case_metrics(case_piv, UniformFlow((0.5625, 0, 0)), cam, vol, parts, sigma_mm=0.2, oracle=oracle, extra=found)
    assert float(out["found_percent"]) == 100.0 and float(out["particle_crosstalk_z"]) == 0.0
    assert float(out["depth_unknown_percent"]) == 50.0 and float(out["focus_scatter_ratio"]) == 2.5
    zero = pytest.approx(0, abs=1e-12)
    assert float(out["oracle_rms_total_mm"]) == zero and float(out["oracle_mean_x_mm"]) == pytest.approx(0.5625)
    assert float(out["recon_added_rms_total_mm"]) == pytest.approx(0.1 * VOX)  # all of the case's error
    assert float(out["recon_added_rms_z_mm"]) == pytest.approx(0.1 * VOX) and float(out["recon_added_rms_x_mm"]) == zero
    assert float(out["crosstalk_z"]) == pytest.approx(0.1 / 4.5) and float(out["oracle_crosstalk_z"]) == zero
    assert float(out["time_oracle"]) == 1.5 and float(out["oracle_valid_percent"]) == 100.0
    assert out["oracle_w_mm"].dims == ("z", "y", "x") and bool(out["oracle_valid"].all())
    # the budget's third term: a uniform flow has no filtering, so the oracle's error is all rest (here 0)
    assert float(out["filter_rms_total_mm"]) == zero and float(out["rest_rms_total_mm"]) == zero
    with pytest.raises(ValueError, match="oracle's PIV grid differs"):
        case_metrics(case_piv, UniformFlow((0.5625, 0, 0)), cam, vol, parts, sigma_mm=0.2, oracle=oracle.isel(x=[0]))
    # every scalar is a row of the table and carries its attrs; every row but the derived ones is computed
    scalars = [n for n, v in out.data_vars.items() if v.ndim == 0]
    for n in scalars:
        m = metric(n)
        assert out[n].attrs["units"] == m.units and out[n].attrs["long_name"] == m.long_name
    derived = {m.name for m in METRICS if m.derive is not None} | {"time_total"}
    assert {m.name for m in METRICS} - derived == set(scalars)


def test_from_csv_gets_units_back_from_the_table(tmp_path):
    study = combine_cases([(_case(-1.0, "matched", 0.125, 0.001, "uniform_x"), _scalars(0.07, 0.8))])
    back = from_csv(to_csv(study, tmp_path / "s.csv"))
    assert back["rms_x"].attrs["units"] == "voxel" and back["Q"].attrs["long_name"] == "reconstruction quality Q"


# ------------------------------------------------------------ the oracle and the error budget
def test_crosstalk_is_spurious_w_per_unit_lateral_shift():
    """A uniform 4.5-voxel x shift read with w = +0.9 voxel: 0.2 of the lateral shift leaks into w;
    NaN for a non-uniform flow and for no lateral shift."""
    from lfstudy.study.metrics import crosstalk_z

    err = case_errors(synthetic_piv(4.5, 0.0, 0.9), UniformFlow((0.5625, 0.0, 0.0)))
    assert float(err["crosstalk_z"]) == pytest.approx(0.2)
    assert err["crosstalk_z"].attrs["units"] == "1"
    # diagonal shift, and a true w that is not spurious: (0.9 − 0.5) / |(3, 4)|
    err = case_errors(synthetic_piv(3.0, 4.0, 0.9), UniformFlow((3 * VOX, 4 * VOX, 0.5 * VOX)))
    assert float(err["crosstalk_z"]) == pytest.approx(0.4 / 5.0)
    # only valid vectors count
    valid = np.ones((4, 5, 6), bool)
    valid[0] = False
    w = np.zeros((4, 5, 6))
    w[0] = 100.0  # outliers, invalid
    err = case_errors(synthetic_piv(4.5, 0.0, w, valid=valid), UniformFlow((0.5625, 0.0, 0.0)))
    assert float(err["crosstalk_z"]) == pytest.approx(0.0, abs=1e-12)
    assert math.isnan(float(case_errors(synthetic_piv(0.0, 0.0, 2.0), UniformFlow((0.0, 0.0, 0.25)))["crosstalk_z"]))
    hill = case_errors(synthetic_piv(0.1, 0.0, 0.3), HillVortex(radius=0.5, u0=0.1))
    assert math.isnan(float(hill["crosstalk_z"]))
    assert math.isnan(crosstalk_z({"z": np.ones(3)}, {"x": 1.0, "y": 0.0, "z": 0.0}, np.zeros(3, bool)))


def test_error_budget_splits_in_quadrature():
    from lfstudy.study.metric_table import METRICS
    from lfstudy.study.metrics import error_budget, quadrature_excess

    assert quadrature_excess(0.05, 0.03) == pytest.approx(0.04)
    assert quadrature_excess(0.03, 0.05) == 0.0  # the case beats the oracle: nothing added
    assert math.isnan(quadrature_excess(math.nan, 0.01)) and math.isnan(quadrature_excess(0.01, math.nan))
    case = {"rms_total_mm": 0.067, "rms_x_mm": 0.02, "rms_y_mm": 0.01, "rms_z_mm": 0.063}
    oracle = {"oracle_rms_total_mm": 0.007, "oracle_rms_x_mm": 0.004, "oracle_rms_y_mm": 0.002,
              "oracle_rms_z_mm": 0.005}  # fmt: skip
    out = error_budget(case, oracle)
    # one value per recon_added_ and rest_ row of the table (the rests NaN here: no filter term)
    assert set(out) == {m.name for m in METRICS if m.name.startswith(("recon_added_", "rest_"))}
    assert math.isnan(out["rest_rms_total_mm"])
    assert out["recon_added_rms_total_mm"] == pytest.approx(math.sqrt(0.067**2 - 0.007**2))
    assert out["recon_added_rms_z_mm"] ** 2 + 0.005**2 == pytest.approx(0.063**2)


def test_oracle_recovers_a_uniform_shift():
    """PIV on the true volumes of the tiny study's case (a 0.1 mm x shift, 1.13 voxels) reads the shift
    to a few µm, every vector valid, no spurious w; on the case's own reconstruction grid."""
    from lfstudy.simulate.flows import flow_from_config
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config, expand_cases, load_config
    from lfstudy.study.metrics import oracle_metrics

    cfg = load_config(ROOT / "tests" / "data" / "tiny.yaml")
    ccfg = case_config(cfg, expand_cases(cfg)[0])
    a = cl.case_particles(ccfg)
    b = cl.case_displaced(ccfg, a)
    va, _ = cl.oracle_volumes(ccfg, a, b)
    grid = cl.case_grid(ccfg)
    assert va.shape == grid.shape and np.array_equal(va["x"].values, grid.x) and va.dtype == np.float32
    assert va.attrs["voxel_size"] == grid.attrs()["voxel_size"] and float(va.sum()) > 0
    res = cl.oracle_piv(ccfg, a, b)
    assert res.attrs["oracle_seconds"] >= res.attrs["piv_seconds"] > 0
    m = oracle_metrics(res, flow_from_config(ccfg["flow"]))
    assert m["oracle_valid_percent"] == 100.0
    assert m["oracle_mean_x_mm"] == pytest.approx(0.1, abs=0.003)
    assert abs(m["oracle_mean_y_mm"]) < 0.001 and abs(m["oracle_mean_z_mm"]) < 0.003
    assert m["oracle_rms_total_mm"] < 0.005 and abs(m["oracle_crosstalk_z"]) < 0.03
    # the same particles twice: no displacement at all
    still = oracle_metrics(cl.oracle_piv(ccfg, a, a), flow_from_config({"kind": "uniform", "displacement": [0, 0, 0]}))
    assert still["oracle_rms_total_mm"] < 1e-3


@pytest.mark.parametrize("in_mm", [True, False])
def test_uncertainty_coverage_and_ratio_against_the_truth(in_mm):
    """unc_coverage_<ax> / unc_ratio_<ax>: fraction |error| <= σ and RMS(error)/RMS(σ), valid vectors only."""
    from lfstudy.study.metric_table import metric

    rng = np.random.default_rng(3)
    shape = (4, 5, 6)
    e = rng.normal(0.0, 0.05, shape)
    sig = np.full(shape, 0.05)
    sig[0, 0, 0] = np.nan  # a vector without an uncertainty is left out
    valid = np.ones(shape, bool)
    valid[1, 1, :2] = False  # invalid vectors too
    piv = synthetic_piv(4.5 + e, 0.0, 0.0, valid=valid)
    if in_mm:
        piv["unc_u_mm"] = (("z", "y", "x"), sig * VOX)
    else:
        piv["unc_u"] = (("z", "y", "x"), sig)
    err = case_errors(piv, UniformFlow((0.5625, 0.0, 0.0)))
    ok = valid & np.isfinite(sig)
    assert float(err["unc_coverage_x"]) == pytest.approx(np.mean(np.abs(e[ok]) <= 0.05), abs=1e-12)
    assert float(err["unc_ratio_x"]) == pytest.approx(np.sqrt(np.mean(e[ok] ** 2)) / 0.05, rel=1e-9)
    # a uniform flow: the window-averaged truth is the point truth
    assert float(err["unc_coverage_point_x"]) == float(err["unc_coverage_x"])
    assert float(err["unc_ratio_point_x"]) == pytest.approx(float(err["unc_ratio_x"]), rel=1e-12)
    assert np.isnan(float(err["unc_coverage_y"])) and np.isnan(float(err["unc_ratio_z"]))  # no unc_v, unc_w
    assert err["unc_ratio_x"].attrs["units"] == "1" and metric("unc_coverage_z").long_name


def test_widim_uncertainty_is_calibrated_against_the_truth():
    """The engine's σ on a real 3-D pair with 5 % noise, 196 valid vectors.

    Measured (seed 2): coverage 0.53 / 0.53 / 0.60 and RMS ratio 1.27 / 1.28 / 1.23 for z / y / x:
    the correlation statistics read ~20-30 % short here. The bounds hold those with the spread of
    a coverage over 196 vectors (±0.035) and a margin; a σ 1.5x smaller (ratio ~1.9) or 2x larger
    (ratio ~0.63) fails them.
    """
    from lfstudy.piv import widim
    from lfstudy.piv.synthetic import particle_pair

    a, b = particle_pair((40, 64, 64), (0.3, 0.0, 0.74), density=0.015, diameter=(4.0, 2.8, 2.8), seed=2)
    rng = np.random.default_rng(5)
    a, b = (f + rng.normal(0.0, 0.05 * a.max(), a.shape) for f in (a, b))
    co = {d: (np.arange(n) - (n - 1) / 2) * VOX for d, n in zip("zyx", a.shape)}
    fa = xr.DataArray(a, dims=("z", "y", "x"), coords=co)
    res = widim(fa, fa.copy(data=b), window=16, spacing=8)
    err = case_errors(res, UniformFlow((0.74 * VOX, 0.0, 0.3 * VOX)))
    for ax in "xyz":
        cov, ratio = float(err[f"unc_coverage_{ax}"]), float(err[f"unc_ratio_{ax}"])
        print(ax, int(err["n_valid"]), round(cov, 3), round(ratio, 3))
        assert 0.45 <= cov <= 0.85 and 0.7 <= ratio <= 1.45, (ax, cov, ratio)


def test_particles_per_cell_counts_lenslets_and_depth_cells_of_the_depth_of_field():
    """The blur circle is one lenslet pitch at the depth of field's ends (eqs 4.16-4.17 with the pitch as circle
    of confusion) and changes sign at focus; the density divides the particles inside the grid by the lenslets
    under it and the pitch-steps of the blur over its depth."""
    from lfstudy.optics import PlenopticCamera
    from lfstudy.study.metrics import particles_per_cell

    cam = PlenopticCamera(4872, 3248, 0.0074, 0.125, 0.5, 50.0, -1.0)
    dof = cam.depth_of_field(0.0)
    ends = np.array([float(dof["z_near"][0]), float(dof["z_far"][0])])
    np.testing.assert_allclose(np.abs(cam.defocus_blur(ends)), cam.lenslet_pitch, rtol=1e-9)
    assert cam.defocus_blur(0.0) == pytest.approx(0.0, abs=1e-12)
    assert cam.defocus_blur(-1.0) > 0 > cam.defocus_blur(1.0)
    rng = np.random.default_rng(0)
    xyz = rng.uniform([-2, -2, -3], [2, 2, 3], (1000, 3))
    xyz[:100, 2] = 5.0  # outside the grid's depth: not counted
    parts = xr.Dataset({k: ("particle", xyz[:, i]) for i, k in enumerate("xyz")})
    bounds = [(-2.0, 2.0), (-2.0, 2.0), (-3.0, 3.0)]
    lenslets = 16.0 / (cam.lenslet_pitch * cam.so / cam.si) ** 2
    zs = xyz[100:, 2]
    cells = abs(cam.defocus_blur(zs.max()) - cam.defocus_blur(zs.min())) / cam.lenslet_pitch
    assert particles_per_cell(cam, parts, bounds) == pytest.approx(900 / (lenslets * cells))
    # a grid deeper than the seeded slab: the same cells (the particles' depth), the same density
    assert particles_per_cell(cam, parts, [(-2.0, 2.0), (-2.0, 2.0), (-4.0, 4.0)]) == pytest.approx(
        900 / (lenslets * cells)
    )
    # a grid thinner than one depth cell holds one
    thin = [(-2.0, 2.0), (-2.0, 2.0), (-0.01, 0.01)]
    inside = int(np.sum(np.abs(xyz[:, 2]) <= 0.01))
    assert particles_per_cell(cam, parts, thin) == pytest.approx(inside / lenslets)


class _Shear2:
    """A steady flow u = a y² + b z² (v = w = 0): particles keep y and z, so the displacement is u·dt
    exactly and its top-hat average over a box of sides L_y, L_z is a (y² + L_y²/12) + b (z² + L_z²/12)."""

    name = "shear2"

    def __init__(self, a: float, b: float) -> None:
        self.a, self.b = a, b

    def velocity(self, x, y, z):
        return self.a * y**2 + self.b * z**2, np.zeros_like(x), np.zeros_like(x)


def test_window_average_of_a_quadratic_flow_is_the_top_hat_curvature_term():
    """The filter term of a quadratic flow is (L²/24) ∂²u/∂x² per axis, exactly (Gauss-Legendre)."""
    from lfstudy.study.metrics import window_average

    y, z = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-2, 2, 4), indexing="ij")
    centres = {"x": np.zeros_like(y), "y": y, "z": z}
    win = {"x": 0.5, "y": 2.0, "z": np.full(y.shape, 4.0)}
    box = window_average(_Shear2(0.03, 0.01), centres, win, n_steps=4)
    np.testing.assert_allclose(box["x"], 0.03 * (y**2 + 4.0 / 12) + 0.01 * (z**2 + 16.0 / 12), rtol=1e-12)
    assert np.all(box["y"] == 0) and np.all(box["z"] == 0)
    with pytest.raises(ValueError, match="window_mm"):
        window_average(_Shear2(0.03, 0.01), centres, {**win, "y": 0.0})


def test_filter_term_and_window_averaged_uncertainty_figures():
    """case_errors' filter_rms is the RMS of (window-averaged − point) truth: 0 for a uniform flow,
    a L_y²/12 + b L_z²/12 for the quadratic one; unc_coverage/ratio judge σ against the window-averaged
    truth, the _point ones against the point truth; without final_window the window figures are NaN."""
    a, b = 0.03, 0.01
    win = [8, 16, 16]  # voxels of VOX along z, y, x
    ly, lz = 16 * VOX, 8 * VOX
    shift = a * ly**2 / 12 + b * lz**2 / 12
    piv = synthetic_piv(0.0, 0.0, 0.0).assign_attrs(final_window=win)
    zz, yy = np.meshgrid(piv.z.values, piv.y.values, indexing="ij")
    point = (a * yy**2 + b * zz**2)[:, :, None] * np.ones(piv.sizes["x"])
    rng = np.random.default_rng(1)
    noise = rng.normal(0.0, 0.002, point.shape)
    measured = point + shift + noise  # a window that measures its average, plus random error
    piv["u_mm"] = (("z", "y", "x"), measured)
    piv["u"] = piv["u_mm"] / VOX
    piv["unc_u_mm"] = (("z", "y", "x"), np.full(point.shape, 0.002))
    err = case_errors(piv, _Shear2(a, b), n_steps=4)
    assert float(err["filter_rms_x_mm"]) == pytest.approx(shift, rel=1e-9)
    assert float(err["filter_rms_y_mm"]) == 0 and float(err["filter_rms_z_mm"]) == 0
    assert float(err["filter_rms_total_mm"]) == pytest.approx(shift, rel=1e-9)
    np.testing.assert_allclose(err["u_filter_mm"].values, shift, rtol=1e-9)
    assert float(err["unc_coverage_x"]) == pytest.approx(np.mean(np.abs(noise) <= 0.002), abs=1e-12)
    assert float(err["unc_ratio_x"]) == pytest.approx(np.sqrt(np.mean(noise**2)) / 0.002, rel=1e-6)
    assert float(err["unc_ratio_point_x"]) == pytest.approx(np.sqrt(np.mean((noise + shift) ** 2)) / 0.002, rel=1e-6)
    assert float(err["unc_coverage_point_x"]) < float(err["unc_coverage_x"])
    uni = case_errors(synthetic_piv(4.5, 0.0, 0.0).assign_attrs(final_window=win), UniformFlow((0.5625, 0.0, 0.0)))
    assert float(uni["filter_rms_total_mm"]) == pytest.approx(0.0, abs=1e-15)  # the rule's weights' rounding
    bare = synthetic_piv(4.5, 0.0, 0.0)
    del bare.attrs["final_window"]
    bare = case_errors(bare, UniformFlow((0.5625, 0.0, 0.0)))
    assert math.isnan(float(bare["filter_rms_total_mm"])) and math.isnan(float(bare["unc_coverage_x"]))


def test_error_budget_rest_is_the_oracle_beyond_the_filter():
    """case² = filter² + recon_added² + rest²: rest = sqrt(oracle² − filter²); NaN without the filter."""
    from lfstudy.study.metrics import error_budget

    case = {"rms_total_mm": 0.05, "rms_x_mm": 0.03, "rms_y_mm": 0.0, "rms_z_mm": 0.04, "filter_rms_total_mm": 0.024,
            "filter_rms_x_mm": 0.012, "filter_rms_y_mm": 0.0, "filter_rms_z_mm": 0.021}  # fmt: skip
    oracle = {"oracle_rms_total_mm": 0.03, "oracle_rms_x_mm": 0.02, "oracle_rms_y_mm": 0.0, "oracle_rms_z_mm": 0.022}
    out = error_budget(case, oracle)
    assert out["rest_rms_total_mm"] == pytest.approx(0.018)
    parts = out["rest_rms_total_mm"] ** 2 + 0.024**2 + out["recon_added_rms_total_mm"] ** 2
    assert parts == pytest.approx(0.05**2)
    assert out["rest_rms_z_mm"] == pytest.approx(math.sqrt(0.022**2 - 0.021**2))
    no_filter = {k: v for k, v in case.items() if not k.startswith("filter_")}
    assert math.isnan(error_budget(no_filter, oracle)["rest_rms_total_mm"])


def test_unresolved_scores_hit_and_false_against_the_true_filter():
    from lfstudy.study.metrics import unresolved_scores

    filt = {"x": np.array([0.0, 0.5, 3.0, 3.0, 1.5, 0.2]), "y": np.zeros(6)}
    sig = {"x": np.ones(6), "y": np.ones(6)}
    flag = np.array([True, False, True, False, True, False])
    valid = np.ones(6, bool)
    pct, hit, false = unresolved_scores(flag, filt, sig, valid)
    # > 2σ: vectors 2, 3 (one flagged); flagged: 0, 2, 4, of which 0 is below σ (4 is between: either is fine)
    assert pct == pytest.approx(50.0) and hit == pytest.approx(0.5) and false == pytest.approx(1 / 3)
    assert math.isnan(unresolved_scores(np.zeros(6, bool), filt, sig, valid)[2])


def test_partial_windows_are_counted_apart_from_the_unresolved_scores():
    """A partial window (piv 'partial') measures its seeded part, not the box: partial_percent counts the valid
    vectors of such windows, and the unresolved scores are over the full windows only."""
    piv = synthetic_piv(4.5, 0.0, 0.0)
    shape = piv["u"].shape
    for c in "uvw":
        piv[f"unc_{c}"] = (("z", "y", "x"), np.full(shape, 0.05))
    partial = np.zeros(shape, bool)
    partial[0] = True
    flag = partial.copy()  # every partial window flagged (the product never does; the scores must not count them)
    flag[1, 0, :3] = True
    piv["partial"] = (("z", "y", "x"), partial)
    piv["unresolved"] = (("z", "y", "x"), flag)
    err = case_errors(piv, UniformFlow((0.5625, 0.0, 0.0)))
    n_full = int((~partial).sum())
    assert float(err["partial_percent"]) == pytest.approx(100.0 * partial.sum() / partial.size)
    assert float(err["unresolved_percent"]) == pytest.approx(100.0 * 3 / n_full)
    assert float(err["unresolved_false"]) == 1.0  # a uniform flow: no filtering, every flag false
    assert math.isnan(float(case_errors(piv.drop_vars("partial"), UniformFlow((0.5625, 0, 0)))["partial_percent"]))
