"""PTV on fitted particle lists (lfstudy.piv.ptv): matching about a predictor, binning on a PIV grid."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from lfstudy.piv.ptv import bin_tracks, depth_weights, match_particles, predict, validate_tracks
from lfstudy.simulate.flows import HillVortex

VOXEL = np.array([0.0888, 0.0888, 0.25])  # x, y, z [mm]: the demo design's reconstruction grid
WINDOW = (4, 8, 8)  # final window (z, y, x) in voxels
SPACING = (2, 4, 4)


def _grid(field, extent=((0.0, 3.2), (0.0, 3.2), (0.5, 4.5)), *, valid=None) -> xr.Dataset:
    """A WIDIM-like result on window centres: ``field(x, y, z) -> (u, v, w)`` [mm] at each centre."""
    axes = {}
    for k, (ax, (lo, hi)) in enumerate(zip("xyz", extent)):
        w, s = WINDOW[::-1][k], SPACING[::-1][k]
        n = round((hi - lo) / VOXEL[k])
        idx = np.arange(0, n - w + 1, s) + (w - 1) / 2
        axes[ax] = (idx, lo + idx * VOXEL[k])
    zz, yy, xx = np.meshgrid(axes["z"][1], axes["y"][1], axes["x"][1], indexing="ij")
    u, v, w = field(xx, yy, zz)
    dims = ("z", "y", "x")
    ds = xr.Dataset(
        {f"{c}_mm": (dims, np.broadcast_to(d, xx.shape).astype(float)) for c, d in zip("uvw", (u, v, w))},
        coords={**{ax: (ax, axes[ax][1]) for ax in "zyx"}, **{f"{ax}_index": (ax, axes[ax][0]) for ax in "zyx"}},
        attrs={"final_window": list(WINDOW), "final_spacing": list(SPACING), "method": "test grid"},
    )
    for c, k in zip("uvw", range(3)):
        ds[c] = ds[f"{c}_mm"] / VOXEL[k]
    ds["valid"] = (dims, np.ones(xx.shape, bool) if valid is None else valid)
    return ds


def _particles(rng, n, extent=((0.0, 3.2), (0.0, 3.2), (0.5, 4.5))) -> np.ndarray:
    lo, hi = np.array(extent).T
    return lo + rng.random((n, 3)) * (hi - lo)


def _scenario(rng, field, n=1200, noise_vox=0.1, ghosts=0.1, missing=0.1):
    """True pairs of a field (midpoint displacement), position noise, missed particles and ghosts in
    both frames; returns the lists and the index in b of each a particle's true partner (-1: none)."""
    xa = _particles(rng, n)
    d = np.column_stack(field(*(xa + 0.5 * np.column_stack(field(*xa.T))).T))  # one midpoint step
    xb = xa + d
    xa = xa + rng.normal(0, noise_vox, xa.shape) * VOXEL
    xb = xb + rng.normal(0, noise_vox, xb.shape) * VOXEL
    keep_a = rng.random(n) > missing
    keep_b = rng.random(n) > missing
    partner = np.where(keep_a & keep_b, np.cumsum(keep_b) - 1, -1)[keep_a]
    a = np.vstack([xa[keep_a], _particles(rng, int(ghosts * n))])
    b = np.vstack([xb[keep_b], _particles(rng, int(ghosts * n))])
    partner = np.concatenate([partner, np.full(int(ghosts * n), -1)])
    return a, b, partner


def _uniform(x, y, z):
    return 0.13 + 0 * x, 0.075 + 0 * x, 0.05 + 0 * x


def _rotation(x, y, z, omega=0.08):
    """A small solid-body rotation about the z axis through (1.6, 1.6), plus a shear in depth."""
    return -omega * (y - 1.6), omega * (x - 1.6), 0.02 * (x - 1.6)


@pytest.mark.parametrize("field", [_uniform, _rotation], ids=["uniform", "rotation"])
def test_matching_recovers_a_known_field_with_ghosts_and_missing_particles(field):
    rng = np.random.default_rng(3)
    a, b, partner = _scenario(rng, field)
    # a predictor off by 0.3 voxel per axis (as a WIDIM field is off at the particles)
    off = 0.3 * VOXEL

    def shifted(x, y, z):
        u, v, w = field(x, y, z)
        return u + off[0], v + off[1], w + off[2]

    tracks = match_particles(a, b, _grid(shifted), search=1.5, voxel=VOXEL)
    ia, jb = tracks.index_a.values, tracks.index_b.values
    right = partner[ia] == jb
    pairs = int((partner >= 0).sum())
    assert right.sum() >= 0.85 * pairs  # most true pairs found
    # a particle whose partner is missing pairs with a neighbour: the median test drops most
    valid = validate_tracks(tracks, voxel=VOXEL)
    kept = partner[valid.index_a.values] == valid.index_b.values
    assert (~right).sum() > 0.04 * len(ia) and (~kept).sum() <= 0.02 * len(kept)
    assert kept.sum() >= 0.8 * pairs and valid.attrs["n_rejected"] == len(ia) - len(kept)
    true_d = np.column_stack(field(*np.column_stack([tracks[k].values for k in "xyz"]).T))
    got = np.column_stack([tracks[f"{c}_mm"].values for c in "uvw"])
    err = (got - true_d)[right] / VOXEL
    # the error of a right pair is the two frames' position noise: sqrt(2) x 0.1 voxel
    assert np.all(np.abs(np.median(err, axis=0)) < 0.03)
    assert np.all(np.abs(err.std(axis=0) - np.sqrt(2) * 0.1) < 0.03)


def test_mutual_nearest_drops_ambiguous_pairs():
    grid = _grid(lambda x, y, z: (0.0 * x, 0.0 * x, 0.0 * x))
    v = VOXEL
    c = np.array([1.6, 1.6, 2.5])
    # a0 and a1 both predict near b0; b0's nearest a is a1: a0 keeps no partner (its nearest b is taken)
    a = np.array([c - np.array([0.6 * v[0], 0, 0]), c + np.array([0.2 * v[0], 0, 0])])
    b = np.array([c, c + np.array([3.0 * v[0], 0, 0])])
    t = match_particles(a, b, grid, search=1.5, voxel=v)
    assert t.index_a.values.tolist() == [1] and t.index_b.values.tolist() == [0]
    # without the second candidate a0 is matched to b0
    t0 = match_particles(a[:1], b, grid, search=1.5, voxel=v)
    assert t0.index_a.values.tolist() == [0] and t0.index_b.values.tolist() == [0]
    # beyond the search radius nothing pairs (distance in voxels per axis: 2 z voxels)
    far = match_particles(c[None], (c + np.array([0, 0, 2.0 * v[2]]))[None], grid, search=1.5, voxel=v)
    assert far.sizes["track"] == 0
    with pytest.raises(ValueError, match="search"):
        match_particles(a, b, grid, search=0.0, voxel=v)


def test_predictor_skips_invalid_vectors():
    valid = np.ones(_grid(_uniform).valid.shape, bool)
    valid[:, :, 3] = False
    bad = _grid(lambda x, y, z: (np.where(np.isclose(x, x), 0.13, 0.0), 0 * x, 0 * x), valid=valid)
    bad["u_mm"][:, :, 3] = 9.0  # an outlier WIDIM marked invalid
    x = float(bad.x[3])
    d = predict(bad, np.array([[x, 1.6, 2.5], [x + 0.1, 1.6, 2.5], [-5.0, 1.6, 2.5]]))
    np.testing.assert_allclose(d[:, 0], 0.13)


def test_binning_a_linear_field_is_exact_and_a_curved_one_beats_the_window_mean():
    rng = np.random.default_rng(5)
    hill = HillVortex(radius=1.2, u0=0.1, center=(1.6, 1.6, 2.5))
    grid = _grid(lambda x, y, z: hill.velocity(x, y, z))
    x = _particles(rng, 1500)

    def tracks_of(field):
        d = np.column_stack(field(*x.T))
        return xr.Dataset(
            {
                **{k: ("track", x[:, i]) for i, k in enumerate("xyz")},
                **{f"{c}_mm": ("track", d[:, i]) for i, c in enumerate("uvw")},
            }
        )

    lin = lambda x, y, z: (0.1 + 0.05 * (y - 1.0), -0.02 * (z - 2.0), 0.03 * (x - 1.0))  # noqa: E731
    res = bin_tracks(tracks_of(lin), grid, voxel=VOXEL)
    ok = res.valid.values & (res.ptv_fit.values == 2)
    assert ok.mean() > 0.7
    zz, yy, xx = np.meshgrid(res.z, res.y, res.x, indexing="ij")
    for c, t in zip("uvw", lin(xx, yy, zz)):
        np.testing.assert_allclose(res[f"{c}_mm"].values[ok], np.broadcast_to(t, xx.shape)[ok], atol=1e-12)

    res = bin_tracks(tracks_of(hill.velocity), grid, voxel=VOXEL)
    ok = res.valid.values & (res.ptv_fit.values == 2)
    truth = np.stack(hill.velocity(xx, yy, zz))
    fit = np.stack([res[f"{c}_mm"].values for c in "uvw"])
    # the window's top-hat mean of the same tracks (what a correlation window averages)
    half = 0.5 * np.array(WINDOW[::-1]) * VOXEL
    centres = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    d = np.column_stack(hill.velocity(*x.T))
    mean = np.stack([d[np.all(np.abs(x - p) <= half, axis=1)].mean(axis=0) for p in centres[ok.ravel()]], axis=1)
    rms_fit = np.sqrt(np.mean((fit[:, ok] - truth[:, ok]) ** 2))
    rms_mean = np.sqrt(np.mean((mean - truth[:, ok]) ** 2))
    assert rms_fit < 0.95 * rms_mean  # the gradient's share of the box mean goes
    # the quadratic fit (12 tracks or more in the box) takes the curvature's share too
    quad = bin_tracks(tracks_of(hill.velocity), grid, voxel=VOXEL, order=2)
    q = quad.ptv_fit.values[ok] == 3
    assert q.mean() > 0.8
    err_q = np.stack([quad[f"{c}_mm"].values for c in "uvw"])[:, ok][:, q] - truth[:, ok][:, q]
    rms_mean_q = np.sqrt(np.mean((mean[:, q] - truth[:, ok][:, q]) ** 2))
    assert np.sqrt(np.mean(err_q**2)) < 0.6 * rms_mean_q
    with pytest.raises(ValueError, match="order"):
        bin_tracks(tracks_of(hill.velocity), grid, voxel=VOXEL, order=3)
    # the WIDIM vectors are kept beside
    np.testing.assert_array_equal(res.piv_u_mm.values, grid.u_mm.values)


def test_the_fit_uncertainty_covers_position_noise():
    rng = np.random.default_rng(11)
    grid = _grid(_rotation)
    x = _particles(rng, 2500)
    sd = 0.15 * VOXEL * np.sqrt(2)
    d = np.column_stack(_rotation(*x.T)) + rng.normal(0, 1, x.shape) * sd
    tr = xr.Dataset(
        {
            **{k: ("track", x[:, i]) for i, k in enumerate("xyz")},
            **{f"{c}_mm": ("track", d[:, i]) for i, c in enumerate("uvw")},
        }
    )
    res = bin_tracks(tr, grid, voxel=VOXEL)
    zz, yy, xx = np.meshgrid(res.z, res.y, res.x, indexing="ij")
    ok = res.valid.values
    for c, t in zip("uvw", _rotation(xx, yy, zz)):
        e = np.abs(res[f"{c}_mm"].values - t)[ok]
        s = res[f"unc_{c}_mm"].values[ok]
        assert np.all(np.isfinite(s)) and np.all(np.isnan(res[f"unc_{c}_mm"].values[~ok]))
        assert 0.6 < np.mean(e <= s) < 0.8  # about 68 %
        assert 0.8 < np.sqrt(np.mean(e**2)) / np.sqrt(np.mean(s**2)) < 1.25
        np.testing.assert_allclose(res[c].values, res[f"{c}_mm"].values / VOXEL["uvw".index(c)])


def _tracks(x: np.ndarray, d: np.ndarray) -> xr.Dataset:
    return xr.Dataset(
        {
            **{k: ("track", x[:, i]) for i, k in enumerate("xyz")},
            **{f"{c}_mm": ("track", d[:, i]) for i, c in enumerate("uvw")},
        }
    )


def _quadratic(x, y, z):
    """A field whose curvature the order-1 fit cannot follow: u and w quadratic in x and y, v in z."""
    return 0.1 + 0.4 * (x - 1.3) ** 2, 0.05 - 0.3 * (z - 2.2) ** 2, 0.2 * (x - 1.5) * (y - 1.7)


def test_the_model_term_is_the_fit_bias_of_a_quadratic_field_and_nothing_on_a_linear_one():
    rng = np.random.default_rng(17)
    x = _particles(rng, 1000)
    grid = _grid(_uniform)
    zz, yy, xx = np.meshgrid(grid.z, grid.y, grid.x, indexing="ij")
    # quadratic, no noise: the pilot's quadratic fit is exact, so the term is the order-1 fit's actual bias
    quad = _tracks(x, np.column_stack(_quadratic(*x.T)))
    res = bin_tracks(quad, grid, voxel=VOXEL, order=1, model_box=1.25)  # any box: the pilot is exact
    fit = bin_tracks(quad, grid, voxel=VOXEL, order=1, model_box=0)
    ok = res.valid.values & (res.ptv_fit.values == 2)
    assert ok.mean() > 0.7 and res.attrs["ptv_model_box"] == 1.25
    for c, t in zip("uvw", _quadratic(xx, yy, zz)):
        bias = np.abs(res[f"{c}_mm"].values - t)[ok]
        assert bias.max() > 1e-4  # the curvature biases the linear fit
        np.testing.assert_allclose(res[f"unc_model_{c}_mm"].values[ok], bias, rtol=1e-6, atol=1e-12)
        # in quadrature with the fit's own term (its residuals: the curvature it cannot follow)
        s_fit = fit[f"unc_{c}_mm"].values[ok]
        model = res[f"unc_model_{c}_mm"].values[ok]
        np.testing.assert_allclose(res[f"unc_{c}_mm"].values[ok], np.hypot(s_fit, model), rtol=1e-12)
    # linear, no noise: no term; with noise the pilot's own noise is taken off (most terms exactly 0)
    lin = np.column_stack(_rotation(*x.T))
    res = bin_tracks(_tracks(x, lin), grid, voxel=VOXEL)
    lin_fit = res.ptv_fit.values == 2  # (a box that falls back to the mean has the gradient's bias)
    assert lin_fit.mean() > 0.7
    for c in "uvw":
        assert np.max(np.abs(res[f"unc_model_{c}_mm"].values[lin_fit])) < 1e-12
    noisy = lin + rng.normal(0, 0.15 * VOXEL * np.sqrt(2), x.shape)
    on, off = (bin_tracks(_tracks(x, noisy), grid, voxel=VOXEL, model_box=b) for b in (1.5, 0))
    ok = on.valid.values
    for c, t in zip("uvw", _rotation(xx, yy, zz)):
        assert np.mean(on[f"unc_model_{c}_mm"].values[ok] == 0) > 0.5
        np.testing.assert_array_equal(on[f"{c}_mm"].values, off[f"{c}_mm"].values)  # the vectors do not change
        s_on, s_off = on[f"unc_{c}_mm"].values[ok], off[f"unc_{c}_mm"].values[ok]
        assert np.all(s_on >= s_off)
        # what the pilot's noise adds keeps the σ within issue 28's band on a field with no curvature
        e = np.abs(on[f"{c}_mm"].values - t)[ok]
        assert 0.55 <= np.mean(e <= s_on) <= 0.8 and 0.7 <= np.sqrt(np.mean(e**2) / np.mean(s_on**2)) <= 1.4
    assert np.all(off.unc_model_u_mm.values[ok] == 0)
    for bad in (0.5, 6.0, "2"):
        with pytest.raises(ValueError, match="model_box"):
            bin_tracks(_tracks(x, lin), grid, voxel=VOXEL, model_box=bad)


def test_few_tracks_fall_back_to_the_mean_then_invalid():
    grid = _grid(_uniform)
    c = np.array([float(grid.x[2]), float(grid.y[2]), float(grid.z[2])])
    x = np.array([c, c + np.array([0.01, 0, 0]), c + np.array([0, 0.01, 0])])
    tr = xr.Dataset(
        {
            **{k: ("track", x[:, i]) for i, k in enumerate("xyz")},
            **{f"{k}_mm": ("track", [0.1, 0.2, 0.3]) for k in "uvw"},
        }
    )
    res = bin_tracks(tr, grid, voxel=VOXEL)
    v = res.isel(z=2, y=2, x=2)
    assert int(v.ptv_fit) == 1 and bool(v.valid) and int(v.n_tracks) == 3
    assert float(v.u_mm) == pytest.approx(0.2) and float(v.unc_u_mm) == pytest.approx(0.1 / np.sqrt(3))
    far = res.isel(z=-1, y=-1, x=-1)
    assert not bool(far.valid) and int(far.ptv_fit) == 0 and np.isnan(float(far.unc_u_mm))
    assert float(far.u_mm) == float(grid.u_mm[-1, -1, -1])  # the WIDIM vector stays where invalid
    with pytest.raises(ValueError, match="window"):
        bin_tracks(tr, grid, window=(4, 8), voxel=VOXEL)


def _blobs(xyz: np.ndarray, coords: dict[str, np.ndarray]) -> xr.DataArray:
    """Particle images on a (z, y, x) grid with coordinates in mm: each particle splatted trilinearly,
    blurred by a Gaussian of 0.8 voxel."""
    from scipy.ndimage import gaussian_filter

    shape = tuple(len(coords[d]) for d in "zyx")
    f = (xyz[:, ::-1] - [coords[d][0] for d in "zyx"]) / VOXEL[::-1]
    i0 = np.floor(f).astype(int)
    vol = np.zeros(shape)
    for corner in np.ndindex(2, 2, 2):
        idx = i0 + corner
        w = np.prod(np.where(corner, f - i0, 1 - (f - i0)), axis=1)
        ok = np.all((idx >= 0) & (idx < shape), axis=1)
        np.add.at(vol, tuple(idx[ok].T), w[ok])
    return xr.DataArray(gaussian_filter(vol, 0.8).astype(np.float32), coords=coords, dims=("z", "y", "x"))


def _scene(rng: np.random.Generator, n: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A 16 x 40 x 40 voxel grid's coords and ``n`` particles (x, y, z) [mm] seeded uniformly inside it."""
    coords = {"z": 0.5 + VOXEL[2] * np.arange(16), "y": VOXEL[1] * np.arange(40), "x": VOXEL[0] * np.arange(40)}
    return coords, _particles(rng, n, [(coords[k][0], coords[k][-1]) for k in "xyz"])


def test_the_piv_stage_tracks_the_particle_lists(tmp_path):
    """run_piv with piv.particles ptv: WIDIM on the volumes, then the lists tracked about it; the result
    is the errors stage's input (u..w, valid, unc, final_window), WIDIM's vectors beside it."""
    from lfstudy import io
    from lfstudy import workflow as wf

    rng = np.random.default_rng(2)
    coords, a = _scene(rng, 260)
    shift = np.array([1.3, -0.7, 0.4]) * VOXEL
    b = a + shift
    paths = {}
    for f, pts in (("a", a), ("b", b)):
        io.write_zarr(_blobs(pts, coords), tmp_path / f"volume_{f}.zarr", name="intensity")
        noisy = pts + rng.normal(0, 0.05, pts.shape) * VOXEL
        io.write_zarr(xr.Dataset({k: ("particle", noisy[:, i]) for i, k in enumerate("xyz")}), tmp_path / f"p_{f}.zarr")
        paths[f] = str(tmp_path / f"p_{f}.zarr")
    piv = {"window": [8, 16, 16], "spacing": [4, 8, 8], "levels": 1, "mode": "offset", "subpixel": "auto"}
    piv |= {"predictor_filter": 1.0, "uncertainty": "none", "particles": "ptv", "ptv_search": 1.5, "ptv_order": 1}
    ccfg = {"stage_id": "t", "piv": piv}
    va, vb, out = tmp_path / "volume_a.zarr", tmp_path / "volume_b.zarr", tmp_path / "piv.zarr"
    wf.run_piv(ccfg, va, vb, out, "", paths["a"], paths["b"])
    res = io.open_zarr(out).load()
    assert res.attrs["particles"] == "ptv" and res.attrs["final_window"] == [8, 16, 16]
    assert res.attrs["ptv_tracks"] >= 0.9 * len(a) and float(res.valid.mean()) > 0.9
    ok = res.valid.values
    for k, c in enumerate("uvw"):
        assert np.abs(res[f"{c}_mm"].values[ok] - shift[k]).max() < 0.1 * VOXEL[k]
        assert np.all(np.isfinite(res[f"unc_{c}_mm"].values[ok])) and f"piv_{c}_mm" in res
    with pytest.raises(ValueError, match="needs both frames' particle lists"):
        wf.run_piv(ccfg, va, vb, tmp_path / "p2.zarr")
    with pytest.raises(ValueError, match="tracks no particles"):
        wf.run_piv({**ccfg, "piv": {**piv, "particles": "none"}}, va, vb, tmp_path / "p3.zarr", "", *paths.values())


def test_the_benchmarks_pass_the_lists_to_a_ptv_piv_task(tmp_path, monkeypatch):
    """bench_uncertainty's task building (bench_budget runs it): a ptv case's piv task gets both lists."""
    import sys
    from pathlib import Path

    import yaml

    from lfstudy.study.config import validate_config

    root = Path(__file__).resolve().parents[1]
    monkeypatch.syspath_prepend(str(root / "benchmarks"))
    sys.modules.pop("bench_uncertainty", None)
    from bench_uncertainty import _tasks

    raw = yaml.safe_load((root / "tests" / "data" / "tiny.yaml").read_text())
    raw |= {"reconstruct": {"method": "ipr"}, "depth_calibration": {"enabled": False}}
    raw["sweep"] = {"ppp": [0.004], "piv.particles": ["none", "ptv"]}
    piv = {t[0]: t[2] for t in _tasks(validate_config(raw), tmp_path)[6]}
    assert len(piv) == 2
    for label, args in piv.items():
        lists = [str(a) for a in args[5:]]
        if "ptv" in label:
            assert [Path(p).name for p in lists] == ["volume_a.particles.zarr", "volume_b.particles.zarr"]
            assert args[4] is None  # no depth calibration
        else:
            assert not lists


def test_weights_follow_the_tracks_sigma():
    """weighted=True: a track's component counts by 1 / sigma^2 (both particles' sigma, from lists
    that carry them); one with an infinite sigma is left out."""
    grid = _grid(_uniform)
    c = np.array([float(grid.x[2]), float(grid.y[2]), float(grid.z[2])])
    rng = np.random.default_rng(4)
    a = c + (rng.random((9, 3)) - 0.5) * VOXEL * [6, 6, 3]
    b = a + np.array(_uniform(*a.T)).T
    b[0] += [0.02, 0.0, 0.0]  # a bad track, flagged by a large sigma
    sig = np.full((9, 3), 0.1 * VOXEL / np.sqrt(2))
    sig[0] = 10 * VOXEL
    sig[1, 2] = np.inf  # a particle without a finite fit covariance

    def lst(x):
        ds = xr.Dataset({k: ("particle", x[:, i]) for i, k in enumerate("xyz")})
        return ds.assign({f"sigma_{k}": ("particle", sig[:, i]) for i, k in enumerate("xyz")})

    tracks = match_particles(lst(a), lst(b), grid, voxel=VOXEL)
    assert tracks.sizes["track"] == 9 and np.isinf(tracks.sigma_w_mm.values[1])
    plain = bin_tracks(tracks, grid, voxel=VOXEL, order=0).isel(z=2, y=2, x=2)
    wtd = bin_tracks(tracks, grid, voxel=VOXEL, order=0, weighted=True).isel(z=2, y=2, x=2)
    assert float(plain.u_mm) == pytest.approx(0.13 + 0.02 / 9)
    assert abs(float(wtd.u_mm) - 0.13) < 1e-3 * 0.02 and int(wtd.n_tracks) == 8


def test_the_predictor_reads_a_descending_axis():
    """A grid whose y coordinate decreases (image rows) predicts the same displacement at a point."""
    grid = _grid(_rotation)
    pts = np.array([[1.0, 1.3, 2.0], [2.2, 0.9, 3.1]])
    up = predict(grid, pts)
    down = predict(grid.isel(y=slice(None, None, -1)), pts)
    np.testing.assert_allclose(down, up, atol=1e-12)
    np.testing.assert_allclose(up[:, :2], np.column_stack(_rotation(*pts.T))[:, :2], atol=1e-12)  # linear: exact


def test_the_predictor_reads_a_grid_one_window_deep():
    """A grid with a single window along an axis (a small crop) predicts as the full grid: the validity
    weights were padded twice there and the interpolator refused them. The rotation does not vary in z,
    so the one plane of windows holds the whole field (linear in x, y: exact)."""
    grid = _grid(_rotation)
    one = grid.isel(z=[2])
    pts = np.array([[1.0, 1.3, float(grid.z[2])], [2.2, 0.9, float(grid.z[2]) + 0.7]])
    np.testing.assert_allclose(predict(one, pts), np.column_stack(_rotation(*pts.T)), atol=1e-12)
    np.testing.assert_allclose(predict(one, pts), predict(grid, pts), atol=1e-12)


def test_paired_piv_drops_particles_fitted_in_one_frame_only(tmp_path):
    """piv.particles paired: a fifth of frame b's particles misplaced one voxel in depth (real particles
    fitted at the wrong place, as IPR's ghosts on the coarse designs) bias WIDIM's w; paired against
    frame a, most fail the tracks' median test, and WIDIM on the volumes of the paired particles alone
    reads the true shift."""
    from lfstudy import io
    from lfstudy import workflow as wf

    rng = np.random.default_rng(5)
    coords, a = _scene(rng, 300)
    shift = np.array([1.3, -0.7, 0.0]) * VOXEL
    b = a + shift
    b[rng.random(len(b)) < 0.2, 2] += VOXEL[2]  # misplaced in depth
    paths = {}
    for f, pts in (("a", a), ("b", b)):
        vol = _blobs(pts, coords).assign_attrs(blob_sigma_mm=list(0.8 * VOXEL[::-1]))
        io.write_zarr(vol, tmp_path / f"volume_{f}.zarr", name="intensity")
        lists = xr.Dataset({k: ("particle", pts[:, i]) for i, k in enumerate("xyz")})
        io.write_zarr(lists.assign(intensity=("particle", np.ones(len(pts)))), tmp_path / f"p_{f}.zarr")
        paths[f] = str(tmp_path / f"p_{f}.zarr")
    piv = {"window": [8, 16, 16], "spacing": [4, 8, 8], "levels": 1, "mode": "offset", "subpixel": "auto"}
    piv |= {"predictor_filter": 1.0, "uncertainty": "none", "particles": "paired", "ptv_search": 1.5}
    ccfg = {"stage_id": "t", "piv": piv}
    va, vb, out = tmp_path / "volume_a.zarr", tmp_path / "volume_b.zarr", tmp_path / "piv.zarr"
    wf.run_piv(ccfg, va, vb, out, "", paths["a"], paths["b"])
    res = io.open_zarr(out).load()
    assert res.attrs["particles"] == "paired" and res.attrs["paired_rejected"] > 0
    assert 0.7 * len(a) <= res.attrs["paired_tracks"] <= 0.85 * len(a)
    ok = res.valid.values & res.piv_valid.values
    w_plain = float(np.mean(res.piv_w_mm.values[ok]))
    w_paired = float(np.mean(res.w_mm.values[ok]))
    assert w_plain > 0.1 * VOXEL[2]  # the misplaced fifth pulls WIDIM's w up
    assert abs(w_paired) < 0.25 * abs(w_plain)
    for k, c in enumerate("uv"):
        assert abs(float(np.mean(res[f"{c}_mm"].values[ok])) - shift[k]) < 0.05 * VOXEL[k]
    with pytest.raises(ValueError, match="takes no depth calibration"):
        wf.run_piv(ccfg, va, vb, tmp_path / "p2.zarr", str(tmp_path / "depth.zarr"), paths["a"], paths["b"])


#: WIDIM settings of the paired-PIV tests, less the window and its spacing
_PAIRED = {"levels": 1, "mode": "offset", "subpixel": "auto", "predictor_filter": 1.0, "uncertainty": "none"}
_PAIRED |= {"particles": "paired", "ptv_search": 1.5}


def _write_fitted_frame(tmp_path, f: str, fit: np.ndarray, coords: dict, sigma_z: np.ndarray) -> str:
    """Frame ``f``'s volume of the fitted particles ``fit`` (``volume_<f>.zarr``) and their list with depth
    uncertainties ``sigma_z`` [mm] (``p_<f>.zarr``, whose path is returned), as the reconstruct stage writes them."""
    from lfstudy import io

    vol = _blobs(fit, coords).assign_attrs(blob_sigma_mm=list(0.8 * VOXEL[::-1]))
    io.write_zarr(vol, tmp_path / f"volume_{f}.zarr", name="intensity")
    lists = xr.Dataset({k: ("particle", fit[:, i]) for i, k in enumerate("xyz")})
    lists = lists.assign(intensity=("particle", np.ones(len(fit))), sigma_z=("particle", sigma_z))
    io.write_zarr(lists, tmp_path / f"p_{f}.zarr")
    return str(tmp_path / f"p_{f}.zarr")


def _paired_w_rms(tmp_path, piv: dict, label: str, paths: dict) -> tuple[xr.Dataset, float]:
    """The piv stage on the frames :func:`_write_fitted_frame` wrote (``piv_<label>.zarr``): its result and the RMS
    of w over the vectors valid in both WIDIMs (over 90 % of them)."""
    from lfstudy import io
    from lfstudy import workflow as wf

    out = tmp_path / f"piv_{label}.zarr"
    va, vb = tmp_path / "volume_a.zarr", tmp_path / "volume_b.zarr"
    wf.run_piv({"stage_id": "t", "piv": piv}, va, vb, out, "", paths["a"], paths["b"])
    res = io.open_zarr(out).load()
    ok = res.valid.values & res.piv_valid.values
    assert ok.mean() > 0.9
    return res, float(np.sqrt(np.mean(res.w_mm.values[ok] ** 2)))


def test_paired_piv_leaves_out_particles_whose_depth_the_fit_could_not_read(tmp_path):
    """piv.paired_max_sigma_z: a third of the particles sit where the images hardly give depth (as near the
    focal plane), and their sigma_z says so. Their fitted z in frame b reads a third of a voxel deep (a lateral
    shift read as depth, as on the coarse demo designs: crosstalk). Left out (the default limit), w reads the
    true zero; kept (a limit of 1000 voxels), w leans towards their error."""
    rng = np.random.default_rng(11)
    coords, true = _scene(rng, 300)
    shift = np.array([1.3, -0.7, 0.0]) * VOXEL
    blind = rng.random(len(true)) < 1 / 3
    paths = {}
    for f, pts in (("a", true), ("b", true + shift)):
        fit = pts.copy()
        fit[blind, 2] += VOXEL[2] / 3 if f == "b" else 0.0
        paths[f] = _write_fitted_frame(tmp_path, f, fit, coords, np.where(blind, 0.5, 0.01) * VOXEL[2])
    piv = {"window": [8, 16, 16], "spacing": [4, 8, 8], **_PAIRED}
    w_rms = {}
    for label, extra in (("default", {}), ("kept", {"paired_max_sigma_z": 1000.0})):
        res, w_rms[label] = _paired_w_rms(tmp_path, piv | extra, label, paths)
        left_out = (res.attrs["paired_depth_unknown_a"], res.attrs["paired_depth_unknown_b"])
        assert left_out == ((int(blind.sum()),) * 2 if label == "default" else (0, 0))
        assert res.attrs["paired_particles_a"] == len(true)
    assert res.attrs["paired_max_sigma_z_mm"] == pytest.approx(1000.0 * VOXEL[2])
    assert w_rms["default"] < 0.02 * VOXEL[2]
    assert w_rms["kept"] > 2 * w_rms["default"]


def test_an_ipr_case_without_depth_calibration_pairs_its_particles_unless_told_otherwise():
    """piv.particles unset: paired for a method that fits particles with the depth calibration off; unset (none)
    for MART and for IPR with the calibration on; an explicit none or ptv is kept."""
    from pathlib import Path

    from lfstudy.study.config import load_config
    from lfstudy.study.sweep import Sweep

    cfg = load_config(Path(__file__).resolve().parents[1] / "tests" / "data" / "tiny.yaml")
    cfg["sweep"] = {"ppp": [0.004], "reconstruct.method": ["mart", "ipr"], "depth_calibration.enabled": [False, True]}
    sweep = Sweep(cfg)
    modes = {
        (c["reconstruct.method"], c["depth_calibration.enabled"]): sweep.apply(c)["piv"].get("particles")
        for c in sweep.cases()
    }
    assert modes == {("mart", False): None, ("ipr", False): "paired", ("mart", True): None, ("ipr", True): None}
    for explicit in ("none", "ptv"):
        cfg["piv"]["particles"] = explicit
        cfg["sweep"] = {"ppp": [0.004], "reconstruct.method": ["ipr"], "depth_calibration.enabled": [False]}
        sweep = Sweep(cfg)
        assert [sweep.apply(c)["piv"]["particles"] for c in sweep.cases()] == [explicit]


def _tracks_of(xyz: np.ndarray, d: np.ndarray) -> xr.Dataset:
    """Tracks at midpoints ``xyz`` (n, 3) [mm] with displacements ``d`` (n, 3) [mm]."""
    names = ("x", "y", "z", "u_mm", "v_mm", "w_mm")
    return xr.Dataset({k: ("track", v) for k, v in zip(names, [*xyz.T, *d.T])})


def test_depth_weights_follow_the_tracks_scatter_by_distance_from_focus():
    """Tracks within 0.5 mm of the focal plane (z = 0) scatter 4x more in w than the rest: their weight, the best
    band's variance over theirs, is about 1/16 (the u, v scatter is the same everywhere and adds a little), the
    far tracks' about 1; the bands' scatter is reported."""
    rng = np.random.default_rng(3)
    n = 1200
    xyz = rng.uniform([0.0, 0.0, -2.0], [3.5, 3.5, 2.0], (n, 3))
    near = np.abs(xyz[:, 2]) < 0.5
    sd = np.column_stack([np.full(n, 0.002), np.full(n, 0.002), np.where(near, 0.04, 0.01)])
    d = np.array([0.1, 0.0, 0.0]) + rng.normal(size=(n, 3)) * sd
    w, info = depth_weights(_tracks_of(xyz, d), voxel=VOXEL)
    assert len(info["depth_mm"]) == len(info["sd_mm"]) == 6
    expected = (0.01**2 + 2 * 0.002**2) / (0.04**2 + 2 * 0.002**2)
    assert np.median(w[np.abs(xyz[:, 2]) < 0.2]) == pytest.approx(expected, rel=0.5)
    assert np.median(w[np.abs(xyz[:, 2]) > 1.0]) > 0.8
    assert info["sd_mm"][0] > 3 * info["sd_mm"][-1]  # the band nearest focus scatters most
    assert np.all((w > 0) & (w <= 1))


def test_depth_weights_under_a_gradient_with_the_same_scatter_everywhere_stay_near_one():
    """A linear shear (u grows with z, 0.03 mm per mm) with the same noise at every depth: inside the volume the
    neighbours' median takes the flow's variation and the bands weigh about alike; at its edges (the far bands)
    the neighbours lie to one side, the shear adds to the scatter and weighs them down, but not away (measured
    0.42 at the edge, 0.7-1 inside, where the noise of the bands' estimates alone gives 0.71-1)."""
    rng = np.random.default_rng(4)
    n = 1200
    xyz = rng.uniform([0.0, 0.0, -2.0], [3.5, 3.5, 2.0], (n, 3))
    d = np.column_stack([0.1 + 0.03 * xyz[:, 2], np.zeros(n), np.zeros(n)]) + rng.normal(size=(n, 3)) * 0.005
    w, _ = depth_weights(_tracks_of(xyz, d), voxel=VOXEL)
    assert np.median(w[np.abs(xyz[:, 2]) < 1.5]) > 0.7 and w.min() > 0.3


def test_depth_weights_without_enough_tracks_or_noise_are_one():
    """Fewer tracks than two bands' worth, or tracks that agree exactly with their neighbours: every weight 1 (no
    band to compare, nothing to weigh); a median of fewer than 3 neighbours is refused."""
    rng = np.random.default_rng(5)
    xyz = rng.uniform([0.0, 0.0, -2.0], [3.5, 3.5, 2.0], (79, 3))
    d = rng.normal(size=(79, 3)) * 0.01
    w, info = depth_weights(_tracks_of(xyz, d), voxel=VOXEL)  # 79 tracks: one band of 40
    assert np.all(w == 1.0) and info == {"depth_mm": [], "sd_mm": []}
    xyz = rng.uniform([0.0, 0.0, -2.0], [3.5, 3.5, 2.0], (400, 3))
    w, _ = depth_weights(_tracks_of(xyz, np.tile([0.1, 0.0, 0.0], (400, 1))), voxel=VOXEL)
    assert np.all(w == 1.0)
    with pytest.raises(ValueError, match="neighbours = 2"):
        depth_weights(_tracks_of(xyz, d[:1].repeat(400, axis=0)), voxel=VOXEL, neighbours=2)


def _blind_near_focus(tmp_path, rng: np.random.Generator, n: int) -> tuple[dict[str, str], np.ndarray]:
    """Two frames of ``n`` particles shifted laterally (1.3, -0.7, 0) voxels, fitted with 0.02 voxel of scatter, and
    0.3 z voxel more in each frame where z < 1.5 mm (as near the focal plane); their lists' paths and the true
    positions of frame a."""
    coords, true = _scene(rng, n)
    shift = np.array([1.3, -0.7, 0.0]) * VOXEL
    blind = true[:, 2] < 1.5
    paths = {}
    for f, pts in (("a", true), ("b", true + shift)):
        fit = pts + rng.normal(size=pts.shape) * VOXEL * 0.02
        fit[blind, 2] += rng.normal(size=int(blind.sum())) * 0.3 * VOXEL[2]
        paths[f] = _write_fitted_frame(tmp_path, f, fit, coords, np.full(len(fit), 1e-3))
    return paths, true


def test_paired_piv_weighs_the_tracks_whose_depth_scatters_down(tmp_path):
    """piv.paired_weights: the particles in the first quarter of the depth read their depth with 0.3 voxel of
    scatter in each frame (as near the focal plane), the rest with 0.02; the fit's sigma_z does not say so.
    Weighted by depth (the default) WIDIM's w on the paired particles errs less than with every track alike, and
    the result names the weights and the bands' scatter."""
    paths, _ = _blind_near_focus(tmp_path, np.random.default_rng(12), 600)
    # windows the volume's whole depth deep: each holds particles of both kinds, and the weights choose among them
    piv = {"window": [16, 16, 16], "spacing": [8, 8, 8], **_PAIRED}
    res, w_rms = {}, {}
    for label, extra in (("default", {}), ("none", {"paired_weights": "none"})):
        res[label], w_rms[label] = _paired_w_rms(tmp_path, piv | extra, label, paths)
    depth, plain = res["default"].attrs, res["none"].attrs
    assert depth["paired_weights"] == "depth" and plain["paired_weights"] == "none"
    assert depth["paired_weight_sd_mm"][0] > 3 * depth["paired_weight_sd_mm"][-1] and depth["paired_weight_min"] < 0.1
    assert len(plain["paired_weight_sd_mm"]) == 0 and plain["paired_weight_min"] == 1.0
    assert w_rms["default"] < 0.75 * w_rms["none"]
    with pytest.raises(ValueError, match=r"piv\.paired_weights = 'inverse'"):
        _paired_w_rms(tmp_path, piv | {"paired_weights": "inverse"}, "inverse", paths)


def test_paired_sigma_takes_the_tracks_scatter_where_the_depth_is_read_badly(tmp_path):
    """piv.paired_uncertainty: the particles nearest the focal plane (z < 1.5 mm here) read their depth with 0.3
    voxel of scatter in each frame, the rest with 0.02. The correlation's σ of w hardly sees it; with the tracks'
    own scatter (the default) σ of w there is the larger of the two and covers the errors as a standard uncertainty
    should, both parts are kept, and ``correlation`` gives the correlation's σ alone."""
    from lfstudy.piv.ptv import track_sigma

    paths, true = _blind_near_focus(tmp_path, np.random.default_rng(21), 900)
    # windows a quarter of the depth deep: those nearest focus hold only badly read tracks (as on the demo)
    piv = {"window": [4, 16, 16], "spacing": [2, 8, 8], **_PAIRED, "uncertainty": "correlation"}
    res, _ = _paired_w_rms(tmp_path, piv, "tracks", paths)
    corr, _ = _paired_w_rms(tmp_path, piv | {"paired_uncertainty": "correlation"}, "corr", paths)
    assert res.attrs["paired_uncertainty"] == "tracks" and corr.attrs["paired_uncertainty"] == "correlation"
    assert "unc_tracks_w_mm" in res and "unc_tracks_w_mm" not in corr
    np.testing.assert_array_equal(res.unc_correlation_w_mm.values, corr.unc_w_mm.values)
    fin = np.isfinite(res.unc_w_mm.values)
    assert fin.mean() > 0.9
    np.testing.assert_array_equal(
        res.unc_w_mm.values[fin], np.fmax(corr.unc_w_mm.values, res.unc_tracks_w_mm.values)[fin]
    )
    near = (res.z.values < 1.5)[:, None, None] & fin & res.valid.values
    far = (res.z.values > 2.5)[:, None, None] & fin & res.valid.values
    assert near.sum() >= 12 and far.sum() >= 12
    tracks_w = res.unc_tracks_w_mm.values
    assert np.median(tracks_w[near]) > 3 * np.median(tracks_w[far])
    err = np.abs(res.w_mm.values)  # the true w is 0
    cover = {k: float(np.mean(err[near] <= r.unc_w_mm.values[near])) for k, r in (("tracks", res), ("corr", corr))}
    assert cover["tracks"] >= cover["corr"] and 0.55 <= cover["tracks"] <= 0.95, cover
    # the tracks' σ alone is the size of the error where the depth is read badly (measured 0.0069 against 0.0117)
    assert 0.4 < np.median(tracks_w[near]) / np.sqrt(np.mean(err[near] ** 2)) < 1.5
    # the unit of the voxels' σ follows the mm's
    np.testing.assert_allclose(res.unc_w.values[fin] * VOXEL[2], res.unc_w_mm.values[fin], rtol=1e-9)
    with pytest.raises(ValueError, match=r"piv\.paired_uncertainty = 'both'"):
        _paired_w_rms(tmp_path, piv | {"paired_uncertainty": "both"}, "both", paths)
    # too few tracks for two bands: no σ from them
    few = _tracks_of(true[:50], np.zeros((50, 3)))
    assert np.isnan(track_sigma(few, res, (1.0, 1.0, 1.0), voxel=VOXEL)).all()
