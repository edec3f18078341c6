"""The flow kinds against their analytic forms, the file flow, the config and the plugin entry point (issue 28 §3)."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
import pytest
import xarray as xr
import yaml

from lfstudy import plugins as plugins_module
from lfstudy.config import ConfigError
from lfstudy.simulate.flows import (
    BlasiusBoundaryLayer,
    ChannelFlow,
    FlowError,
    GriddedFlow,
    LambOseenVortex,
    UniformFlow,
    VortexRing,
    available_kinds,
    blasius_solution,
    displace,
    flow_from_config,
    flow_input_files,
    integrate,
)
from lfstudy.simulate.flows import _registry as registry
from lfstudy.study.config import load_config, validate_config

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.yaml"


def _divergence(flow, pts: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    div = np.zeros(pts.shape[1])
    for k in range(3):
        dp = np.zeros((3, 1))
        dp[k] = eps
        div += (np.stack(flow.velocity(*(pts + dp)))[k] - np.stack(flow.velocity(*(pts - dp)))[k]) / (2 * eps)
    return div


def _frame(axis):
    """An orthonormal (e1, e2, e) with e along ``axis``."""
    e = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.cross(e, [1.0, 0.0, 0.0] if abs(e[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(e, e1), e


# ------------------------------------------------------------------ Lamb–Oseen
def test_lamb_oseen_is_its_profile_about_a_tilted_axis():
    gamma, rc, c, axis = 3.0, 0.8, np.array([0.3, -0.2, 0.5]), (1.0, 2.0, -0.5)
    flow = LambOseenVortex(circulation=gamma, core_radius=rc, center=tuple(c), axis=axis)
    e1, e2, e = _frame(axis)
    r = np.array([0.0, 1e-4, 0.1, 0.5, 1.1209 * rc, 2.0, 40.0])
    a = np.linspace(-2, 2, r.size)  # the position along the axis does not matter
    pts = c[:, None] + e1[:, None] * r + e[:, None] * a
    vel = np.stack(flow.velocity(*pts))
    ut = gamma / (2 * np.pi * r[1:]) * -np.expm1(-(r[1:] ** 2) / rc**2)  # 1 − exp(−r²/r_c²), no cancellation
    np.testing.assert_allclose(vel[:, 1:] @ np.diag(1 / ut), np.tile(e2[:, None], (1, r.size - 1)), rtol=1e-9)
    assert np.abs(vel[:, 0]).max() < 1e-15  # on the axis (to the points' rounding); solid-body rotation next to it
    assert float(flow.azimuthal(1e-8)) == pytest.approx(gamma * 1e-8 / (2 * np.pi * rc**2), rel=1e-12)
    # the peak 0.6382 Γ/(2π r_c) at r = 1.1209 r_c; the potential vortex far out
    assert float(flow.azimuthal(1.1209 * rc)) == pytest.approx(0.63817 * gamma / (2 * np.pi * rc), rel=1e-4)
    assert np.linalg.norm(vel[:, -1]) == pytest.approx(gamma / (2 * np.pi * 40.0), rel=1e-12)
    # circulation around a circle of radius ρ: Γ (1 − exp(−ρ²/r_c²)) (trapezoid, spectrally exact)
    th = np.linspace(0, 2 * np.pi, 257)[:-1]
    for rho in (0.5, 1.5):
        ring = c[:, None] + rho * (np.outer(e1, np.cos(th)) + np.outer(e2, np.sin(th)))
        tang = -np.outer(e1, np.sin(th)) + np.outer(e2, np.cos(th))
        circ = np.sum(np.stack(flow.velocity(*ring)) * tang) * rho * 2 * np.pi / th.size
        assert circ == pytest.approx(gamma * (1 - np.exp(-(rho**2) / rc**2)), rel=1e-10)
    pts = np.random.default_rng(0).uniform(-3, 3, size=(3, 500))
    assert np.abs(_divergence(flow, pts)).max() < 1e-7


# ------------------------------------------------------------------ vortex ring
def _ring_thin(gamma, R, z):
    return gamma * R**2 / (2 * (R**2 + z**2) ** 1.5)


def test_vortex_ring_on_its_axis_is_the_thin_ring():
    gamma, R, rc = 2.0, 2.0, 0.2
    axis, c = (0.0, 1.0, 1.0), np.array([0.1, 0.0, -0.3])
    flow = VortexRing(circulation=gamma, radius=R, core_radius=rc, center=tuple(c), axis=axis)
    *_, e = _frame(axis)
    z = np.array([-5.0, -1.0, 0.0, 0.7, 3.0, 20.0])
    vel = np.stack(flow.velocity(*(c[:, None] + e[:, None] * z)))
    # R/σ = 14: the Gaussian core's factor q differs from 1 by far less than the tolerance
    np.testing.assert_allclose(vel, np.outer(e, _ring_thin(gamma, R, z)), rtol=1e-12, atol=1e-15)
    # Γ > 0 drives the fluid through the ring along +axis
    assert np.all(vel.T @ e > 0)


def test_vortex_ring_symmetry_far_field_and_core():
    gamma, R, rc = 1.5, 1.0, 0.1
    axis = (0.3, -0.4, 1.0)
    e1, e2, e = _frame(axis)
    flow = VortexRing(circulation=gamma, radius=R, core_radius=rc, axis=axis)
    rng = np.random.default_rng(1)
    a, r, phi = rng.uniform(-2, 2, 200), rng.uniform(0, 3, 200), rng.uniform(0, 2 * np.pi, 200)

    def at(a, r, phi):
        rad = np.outer(e1, np.cos(phi)) + np.outer(e2, np.sin(phi))
        vel = np.stack(flow.velocity(*(e[:, None] * a + rad * r)))
        return vel.T @ e, np.sum(vel * rad, axis=0), vel - np.outer(e, vel.T @ e) - rad * np.sum(vel * rad, axis=0)

    ua, ur, rest = at(a, r, phi)
    ua0, ur0, _ = at(a, r, np.zeros_like(phi))
    np.testing.assert_allclose(ua, ua0, atol=1e-12)  # axisymmetric, no swirl
    np.testing.assert_allclose(ur, ur0, atol=1e-12)
    assert np.abs(rest).max() < 1e-12
    ua_m, ur_m, _ = at(-a, r, phi)  # mirror symmetric about the ring's plane
    np.testing.assert_allclose(ua_m, ua, atol=1e-12)
    np.testing.assert_allclose(ur_m, -ur, atol=1e-12)
    # far field: the dipole of impulse Γ π R² (the next term is O((R/|x|)²) smaller)
    d = 60.0 * R
    for th in (0.0, 0.7, np.pi / 2):
        xhat = e * np.cos(th) + e1 * np.sin(th)
        vel = np.stack(flow.velocity(*(d * xhat[:, None])))[:, 0]
        dipole = gamma * R**2 / 4 * (3 * np.cos(th) * xhat - e) / d**3
        np.testing.assert_allclose(vel, dipole, atol=2e-3 * np.abs(dipole).max())
    # circulation round the core (radius 5 r_c in the meridional plane): Γ up to curvature corrections
    th = np.linspace(0, 2 * np.pi, 513)[:-1]
    rho = 5 * rc
    loop = e1[:, None] * (R + rho * np.cos(th)) + e[:, None] * rho * np.sin(th)
    tang = -e1[:, None] * np.sin(th) + e[:, None] * np.cos(th)
    circ = np.sum(np.stack(flow.velocity(*loop)) * tang) * rho * 2 * np.pi / th.size
    assert circ == pytest.approx(-gamma, rel=2e-3)  # counter-clockwise in (e1, e) is against Γ's sense
    pts = np.concatenate([rng.uniform(-2, 2, (3, 300)), (e1[:, None] * (R + rng.normal(0, rc, 300)))], axis=1)
    assert np.abs(_divergence(flow, pts, eps=1e-5)).max() < 1e-5 * gamma / rc**2


def test_vortex_ring_on_a_grid_equals_the_flat_points():
    """A grid of any dimension (the errors stage passes its 3-D window centres) gives the flat
    points' velocities in its own shape (the kernel flattened a before broadcasting r: a crash)."""
    flow = VortexRing(circulation=2.0, radius=1.0, core_radius=0.4, axis=(0, 1, 1))
    grid = np.meshgrid(np.linspace(-2, 2, 4), np.linspace(-1, 1, 3), np.linspace(-1.5, 1.5, 5), indexing="ij")
    vel = flow.velocity(*grid)
    flat = flow.velocity(*(g.ravel() for g in grid))
    for v, f in zip(vel, flat):
        assert v.shape == grid[0].shape
        np.testing.assert_array_equal(v.ravel(), f)
    assert np.abs(np.stack(flat)).max() > 0.1


def test_vortex_ring_quadrature_has_converged():
    """The node rule (8 per integrand width) agrees with a 4x finer one to 1e-10 of the peak speed."""
    ring = VortexRing(circulation=1.0, radius=2.0, core_radius=0.05)
    fine = type("Fine", (VortexRing,), {"NODES_PER_WIDTH": 32.0})(circulation=1.0, radius=2.0, core_radius=0.05)
    rng = np.random.default_rng(2)
    a = np.concatenate([rng.uniform(-3, 3, 2000), rng.normal(0, 0.05, 2000)])
    r = np.abs(np.concatenate([rng.uniform(0, 4, 2000), 2 + rng.normal(0, 0.05, 2000)]))
    got, ref = np.stack(ring.meridional(a, r)), np.stack(fine.meridional(a, r))
    assert np.abs(got - ref).max() < 1e-10 * np.abs(ref).max()
    # the same bytes whatever the batch
    np.testing.assert_array_equal(np.stack(ring.meridional(a[:7], r[:7])), got[:, :7])


# ------------------------------------------------------------------ wall-bounded laminar flows
def test_channel_is_plane_poiseuille():
    flow = ChannelFlow(u_max=0.3, half_height=1.5, center=(0.0, 0.2, 0.0), normal=(0, 0, 2), direction=(0, 1, 0))
    z = np.linspace(-2, 2, 41)
    u, v, w = flow.velocity(np.full_like(z, 0.7), np.full_like(z, -0.4), z)
    expect = np.where(np.abs(z) <= 1.5, 0.3 * (1 - (z / 1.5) ** 2), 0.0)
    np.testing.assert_allclose(v, expect, atol=1e-15)
    assert np.all(u == 0) and np.all(w == 0)
    # the bulk velocity is 2/3 U_max
    zz = np.linspace(-1.5, 1.5, 20001)
    assert np.trapezoid(flow.profile(zz), zz) / 3.0 == pytest.approx(0.2, rel=1e-7)
    with pytest.raises(FlowError, match="perpendicular"):
        ChannelFlow(u_max=1.0, half_height=1.0, normal=(0, 1, 0), direction=(1, 1, 0))


def test_blasius_similarity_solution():
    sol = blasius_solution()
    assert sol["fpp0"] == pytest.approx(0.332057, abs=1e-6)  # Schlichting & Gersten: 0.332057
    assert sol["eta99"] == pytest.approx(4.91, abs=0.005)  # δ99 = 4.91 x/√Re_x
    assert sol["beta"] == pytest.approx(1.7208, abs=1e-4)  # δ* = 1.7208 x/√Re_x
    U, nu = 2.0, 0.05
    flow = BlasiusBoundaryLayer(u_inf=U, nu=nu, origin=(-30.0, -1.0, 0.0))
    x = 25.0  # 25 mm downstream of the leading edge
    d99 = 4.91 * x / math.sqrt(U * x / nu)
    assert float(flow.thickness(x)) == pytest.approx(d99, rel=1e-3)
    u, v, w = flow.velocity(np.array([x - 30.0]), np.array([float(flow.thickness(x)) - 1.0]), np.array([0.0]))
    assert u[0] == pytest.approx(0.99 * U, rel=1e-9) and v[0] > 0 and w[0] == 0
    # the wall, the free stream, upstream and below the wall
    u, v, _ = flow.velocity(np.array([x - 30, x - 30, -40.0, x - 30]), np.array([-1.0, 50.0, 0.0, -2.0]), np.zeros(4))
    assert u[0] == 0 and v[0] == 0 and u[1] == pytest.approx(U, abs=1e-12) and u[2] == U and u[3] == 0
    # continuity (exact) and the boundary-layer momentum equation u u_x + v u_y = ν u_yy
    rng = np.random.default_rng(3)
    px, py = rng.uniform(-20.0, 10.0, 400), rng.uniform(-0.95, 1.0, 400)
    pts = np.stack([px, py, rng.uniform(-1, 1, 400)])
    assert np.abs(_divergence(flow, pts, eps=1e-4)).max() < 1e-6 * U / d99
    h = 1e-3
    f = lambda dx, dy: np.stack(flow.velocity(px + dx, py + dy, pts[2]))  # noqa: E731
    u0, v0 = f(0, 0)[:2]
    ux = (f(h, 0)[0] - f(-h, 0)[0]) / (2 * h)
    uy = (f(0, h)[0] - f(0, -h)[0]) / (2 * h)
    uyy = (f(0, h)[0] - 2 * u0 + f(0, -h)[0]) / h**2
    resid = u0 * ux + v0 * uy - nu * uyy
    assert np.abs(resid).max() < 1e-3 * U**2 / d99
    # the same layer given by its thickness at a reference station
    by_d = BlasiusBoundaryLayer(u_inf=U, delta99=d99, x_ref=x)
    assert float(by_d.thickness(x)) == pytest.approx(d99, rel=1e-12)
    with pytest.raises(FlowError, match="either nu"):
        BlasiusBoundaryLayer(u_inf=U, nu=nu, delta99=1.0, x_ref=2.0)
    with pytest.raises(FlowError, match="either nu"):
        BlasiusBoundaryLayer(u_inf=U, delta99=1.0)


# ------------------------------------------------------------------ file flow
def _bilinear(x, y, z):
    """A field trilinear interpolation reproduces exactly (in span{1, x, y, z, xy, yz, xz, xyz})."""
    return 0.2 + 0.05 * y * z, -0.03 * x + 0.01 * x * y * z, 0.04 * z - 0.02 * x * z


class _Bilinear:
    name = "bilinear"
    parameters: ClassVar[dict] = {}

    def velocity(self, x, y, z):
        return _bilinear(x, y, z)


def _field_dataset(*, meters=False):
    x = np.linspace(-3.0, 3.0, 13)
    y = np.linspace(2.5, -2.5, 11)  # decreasing: flipped on reading
    z = np.array([-2.0, -1.2, -0.5, 0.0, 0.3, 1.0, 2.0])  # stretched
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    u, v, w = _bilinear(X, Y, Z)
    s = 1e-3 if meters else 1.0
    vu = "m/s" if meters else "mm/s"
    ds = xr.Dataset(
        {n: (("x", "y", "z"), a * s, {"units": vu}) for n, a in zip("uvw", (u, v, w))},
        coords={c: (c, a * s, {"units": "m" if meters else "mm"}) for c, a in zip("xyz", (x, y, z))},
    )
    return ds.transpose("z", "y", "x")  # stored (z, y, x): any order is read


@pytest.mark.parametrize("fmt", ["zarr", "netcdf"])
def test_file_flow_interpolates_and_advects_like_the_analytic_field(tmp_path, fmt):
    ds = _field_dataset(meters=fmt == "netcdf")
    path = tmp_path / ("field.zarr" if fmt == "zarr" else "field.nc")
    if fmt == "zarr":
        ds.to_zarr(path, consolidated=False)
    else:
        ds.to_netcdf(path, engine="scipy")  # netCDF-3: read without extra packages
    flow = GriddedFlow(path=str(path))
    assert flow.time_unit == "s" and flow.extent[1] == pytest.approx((-2.5, 2.5))
    rng = np.random.default_rng(4)
    p = rng.uniform([-2.9, -2.4, -1.9], [2.9, 2.4, 1.9], size=(300, 3)).T
    np.testing.assert_allclose(np.stack(flow.velocity(*p)), np.stack(_bilinear(*p)), atol=1e-12)
    parts = xr.Dataset({c: ("particle", p[k] * 0.8) for k, c in enumerate("xyz")})
    got = displace(parts, flow, dt=1.0, n_steps=20)
    ref = displace(parts, _Bilinear(), dt=1.0, n_steps=20)
    for c in "xyz":
        np.testing.assert_allclose(got[c].values, ref[c].values, atol=1e-12)
    # shifted into the object frame by offset
    moved = GriddedFlow(path=str(path), offset=(10.0, 0.0, 0.0))
    np.testing.assert_allclose(np.stack(moved.velocity(p[0] + 10, p[1], p[2])), np.stack(_bilinear(*p)), atol=1e-12)


def test_file_flow_outside_the_grid(tmp_path):
    path = tmp_path / "f.zarr"
    _field_dataset().to_zarr(path, consolidated=False)
    flow = GriddedFlow(path=str(path))
    with pytest.raises(FlowError, match=r"f\.zarr.*1 of 2 points.*x \[-3, 3\], y \[-2\.5, 2\.5\], z \[-2, 2\]"):
        flow.velocity(np.array([0.0, 0.0]), np.array([0.0, 0.0]), np.array([0.0, 2.5]))
    # particles leaving the grid during the integration: the same error
    with pytest.raises(FlowError, match="outside the field's extent"):
        integrate(flow, np.array([2.9]), np.array([0.0]), np.array([0.0]), dt=100.0, n_steps=10)
    near = GriddedFlow(path=str(path), outside="nearest")
    np.testing.assert_allclose(
        np.stack(near.velocity(np.array([9.0]), np.array([0.5]), np.array([-7.0])))[:, 0],
        np.array(_bilinear(3.0, 0.5, -2.0)),
        atol=1e-12,
    )


def _write(ds, path):
    ds.to_zarr(path, consolidated=False)
    return str(path)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda ds: ds.drop_vars("w"), r"'w' is missing"),
        (lambda ds: ds.drop_vars("y"), r"coordinate 'y'"),
        (lambda ds: ds.assign_coords(z=("z", [0.0, 1.0, 0.5, 2.0, 3.0, 4.0, 5.0])), "not strictly monotonic"),
        (lambda ds: ds.assign(u=ds["u"].where(ds["x"] < 2)), r"'u' holds 231 NaN.*x=10, y=0, z=0"),
        (lambda ds: ds.assign(v=ds["v"].assign_attrs(units="furlong/fortnight")), "not a length"),
        (lambda ds: ds.assign(v=ds["v"].assign_attrs(units="knots")), "not a velocity"),
        (lambda ds: ds.assign(w=ds["w"].assign_attrs(units="mm/ms")), "different time units"),
        (lambda ds: ds.expand_dims(time=[0.0]), r"select one time step"),
    ],
)
def test_file_flow_bad_files(tmp_path, edit, match):
    path = _write(edit(_field_dataset()), tmp_path / "bad.zarr")
    with pytest.raises(FlowError, match=match) as err:
        GriddedFlow(path=path)
    assert "bad.zarr" in str(err.value)


def test_file_flow_missing_and_unreadable_files(tmp_path):
    with pytest.raises(FlowError, match="does not exist"):
        GriddedFlow(path=str(tmp_path / "none.zarr"))
    hdf = tmp_path / "dns.nc"
    hdf.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))  # netCDF-4 files are HDF5
    with pytest.raises(FlowError, match=r"dns\.nc"):
        GriddedFlow(path=str(hdf))
    with pytest.raises(FlowError, match=r"zarr store .* or netCDF"):
        (tmp_path / "f.csv").write_text("u,v,w\n")
        GriddedFlow(path=str(tmp_path / "f.csv"))


# ------------------------------------------------------------------ config
def _tiny():
    return yaml.safe_load(TINY.read_text())


ALL_KINDS = {
    "shift": {"kind": "uniform", "displacement": [0.1, 0.0, 0.0]},
    "hill": {"kind": "hill", "radius": 1.0, "u0": 0.1},
    "vortex": {"kind": "lamb_oseen", "circulation": 2.0, "core_radius": 1.0, "axis": [0, 1, 0]},
    "ring": {"kind": "vortex_ring", "circulation": 1.0, "radius": 1.0, "core_radius": 0.3, "n_steps": 20},
    "channel": {"kind": "channel", "u_max": 0.1, "half_height": 2.0, "normal": [0, 0, 1]},
    "bl": {"kind": "blasius", "u_inf": 0.1, "delta99": 1.0, "x_ref": 50.0, "origin": [-50, 0, -1], "normal": [0, 0, 1]},
    "dns": {"kind": "file", "path": "dns/field.zarr", "offset": [0, 0, 0.5], "dt": 0.5},
}


def test_config_round_trip_of_every_kind(tmp_path, monkeypatch):
    (tmp_path / "dns").mkdir()
    _field_dataset().to_zarr(tmp_path / "dns" / "field.zarr", consolidated=False)
    raw = _tiny()
    raw["flows"] = copy.deepcopy(ALL_KINDS)
    raw["sweep"] = {"ppp": [0.002], "flow": list(ALL_KINDS)}
    cfg_path = tmp_path / "study.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    monkeypatch.chdir(ROOT)  # relative paths are relative to the config file, not the working directory
    cfg = load_config(cfg_path)
    assert set(available_kinds()) >= {s["kind"] for s in ALL_KINDS.values()}
    assert cfg["flows"]["dns"]["path"] == str(tmp_path / "dns" / "field.zarr")
    assert cfg["flows"]["ring"]["n_steps"] == 20 and cfg["flows"]["vortex"]["dt"] == 1.0
    assert "center" not in cfg["flows"]["vortex"]  # a kind's defaults stay in its class
    kinds = {}
    for name, spec in cfg["flows"].items():
        flow = flow_from_config({"name": name, **spec})
        kinds[name] = type(flow).__name__
        v = np.stack(flow.velocity(np.zeros(2), np.array([0.5, -0.5]), np.zeros(2)))
        assert v.shape == (3, 2) and np.all(np.isfinite(v))
    assert kinds["ring"] == "VortexRing" and kinds["dns"] == "GriddedFlow" and kinds["bl"] == "BlasiusBoundaryLayer"
    assert flow_from_config(cfg["flows"]["vortex"]) == LambOseenVortex(2.0, 1.0, axis=(0, 1, 0))
    # the config as validated validates again to itself (absolute path kept)
    assert validate_config(copy.deepcopy(cfg)) == cfg
    assert flow_input_files(cfg["flows"]["dns"]) and all(
        f.startswith(str(tmp_path / "dns" / "field.zarr")) for f in flow_input_files(cfg["flows"]["dns"])
    )
    assert flow_input_files(cfg["flows"]["vortex"]) == []


@pytest.mark.parametrize(
    "spec, match",
    [
        ({"kind": "lamb_osen", "circulation": 1.0}, r"flows\.f\.kind.*'uniform', 'hill', 'lamb_oseen'"),
        ({"kind": "lamb_oseen", "circulation": 1.0}, r"flows\.f.*'core_radius' is a required"),
        ({"kind": "lamb_oseen", "circulation": 1.0, "core_radius": 0}, r"flows\.f\.core_radius.*\(0, inf\)"),
        ({"kind": "lamb_oseen", "circulation": 1.0, "core_radius": 1, "radius": 2}, r"flows\.f\.radius.*core_radius"),
        ({"kind": "lamb_oseen", "circulation": 1.0, "core_radius": 1, "axis": [0, 0, 0]}, r"flows\.f.*non-zero"),
        ({"kind": "vortex_ring", "circulation": 1, "radius": 1, "core_radius": 2}, r"flows\.f.*at most the ring"),
        ({"kind": "channel", "u_max": 1, "half_height": 1, "center": [0, 0]}, r"flows\.f\.center.*3"),
        ({"kind": "blasius", "u_inf": -1, "nu": 1}, r"flows\.f\.u_inf.*\(0, inf\)"),
        ({"kind": "blasius", "u_inf": 1}, r"flows\.f.*either nu"),
        ({"kind": "file", "path": "missing.zarr"}, r"flows\.f.*missing\.zarr.*does not exist"),
        ({"kind": "file", "path": "x.zarr", "outside": "clip"}, r"flows\.f\.outside.*'error', 'nearest'"),
        ({"kind": "uniform"}, r"flows\.f.*'displacement' is a required"),
        ({"kind": "hill", "radius": 1.0, "u0": 1.0, "dt": 0}, r"flows\.f\.dt"),
    ],
)
def test_bad_flow_configs_name_the_key(spec, match, tmp_path):
    raw = _tiny()
    raw["flows"]["f"] = spec
    with pytest.raises(ConfigError, match=match):
        validate_config(raw, base=tmp_path)


def test_flow_from_config_checks_its_input():
    with pytest.raises(FlowError, match=r"flows\.v\.core_radius"):
        flow_from_config({"name": "v", "kind": "lamb_oseen", "circulation": 1.0, "core_radius": -1.0})
    with pytest.raises(FlowError, match="unknown; allowed values are 'uniform'"):
        flow_from_config({"kind": "tornado"})
    assert flow_from_config({"kind": "uniform", "displacement": [1, 2, 3], "dt": 2}) == UniformFlow((1.0, 2.0, 3.0))


# ------------------------------------------------------------------ plugins
@pytest.fixture
def plugins(monkeypatch):
    """Fake installed packages: the entry points of group lfstudy.flows are what the test sets."""
    eps: list = []

    def entry_points(group: str) -> list:
        return list(eps) if group == registry.ENTRY_POINT_GROUP else []

    monkeypatch.setattr(plugins_module, "entry_points", entry_points)
    registry._plugins.cache_clear()
    yield eps
    registry._plugins.cache_clear()


class Swirl:
    """A solid-body rotation about z (a plugin kind)."""

    name = "swirl"
    description = "solid-body rotation about z"
    parameters: ClassVar[dict] = {
        "omega": {"type": "number", "minimum": -1, "maximum": 1, "description": "rate [rad per unit time]"}
    }

    def __init__(self, omega=0.1):
        self.omega = omega

    def velocity(self, x, y, z):
        x = np.asarray(x, float)
        return -self.omega * np.asarray(y, float), self.omega * x, np.zeros_like(x)


class NoVelocity:
    parameters: ClassVar[dict] = {}


def _ep(name, obj):
    def load():
        if isinstance(obj, Exception):
            raise obj
        return obj

    return SimpleNamespace(name=name, value=f"pkg.module:{name}", group=registry.ENTRY_POINT_GROUP, load=load)


def test_a_plugin_kind_works_like_a_builtin(plugins):
    plugins += [_ep("swirl", Swirl), _ep("broken", ImportError("no module named pkg")), _ep("odd", NoVelocity)]
    with pytest.warns(RuntimeWarning) as caught:
        kinds = available_kinds()
    msgs = " | ".join(str(w.message) for w in caught)
    assert "'broken'" in msgs and "ImportError" in msgs and "'odd'" in msgs and "velocity(x, y, z)" in msgs
    assert kinds[-1] == "swirl" and "broken" not in kinds and "odd" not in kinds
    from lfstudy.study.config import load_schema

    text = load_schema()["properties"]["flows"]["additionalProperties"]["properties"]["kind"]["description"]
    assert "swirl (solid-body rotation about z)" in text and "broken" not in text
    raw = _tiny()
    raw["flows"]["turn"] = {"kind": "swirl", "omega": 0.2}
    raw["sweep"]["flow"] = ["turn"]
    cfg = validate_config(raw)
    flow = flow_from_config(cfg["flows"]["turn"])
    assert isinstance(flow, Swirl) and flow.omega == 0.2
    x, y, _ = integrate(flow, np.array([1.0]), np.array([0.0]), np.array([0.0]), dt=np.pi / 0.2 / 2, n_steps=200)
    assert (x[0], y[0]) == (pytest.approx(0.0, abs=1e-8), pytest.approx(1.0, abs=1e-8))
    # its parameters are validated by the schema; typos list every kind, the plugin's too
    raw["flows"]["turn"] = {"kind": "swirl", "omega": 3}
    with pytest.raises(ConfigError, match=r"flows\.turn\.omega' = 3: allowed range is \[-1, 1\]"):
        validate_config(raw)
    raw["flows"]["turn"] = {"kind": "swirll"}
    with pytest.raises(ConfigError, match=r"flows\.turn\.kind.*'file', 'swirl'"):
        validate_config(raw)
    raw["flows"]["turn"] = {"kind": "broken"}
    with pytest.raises(ConfigError, match="allowed values"):
        validate_config(raw)
    with pytest.raises(FlowError, match=r"'broken'.*failed to load: ImportError"):
        flow_from_config({"kind": "broken"})


def test_a_plugin_named_as_a_builtin_kind_is_skipped_without_loading(plugins):
    """The rule of both registries (lfstudy.plugins): an entry point that reuses a built-in's name is
    skipped with a warning naming it, before it is imported; the config's kind stays the built-in."""
    loaded = []

    def load():
        loaded.append("uniform")
        return Swirl

    impostor = SimpleNamespace(name="uniform", value="pkg.module:Uniform", group=registry.ENTRY_POINT_GROUP, load=load)
    plugins += [impostor, _ep("swirl", Swirl)]
    with pytest.warns(RuntimeWarning) as caught:
        kinds = available_kinds()
    msgs = [str(w.message) for w in caught]
    assert len(msgs) == 1 and "'uniform'" in msgs[0] and "pkg.module:Uniform" in msgs[0]
    assert "built-in flow kind" in msgs[0] and registry.ENTRY_POINT_GROUP in msgs[0]
    assert loaded == []  # never imported
    assert kinds.count("uniform") == 1 and kinds[-1] == "swirl"
    assert registry.get_flow_class("uniform") is UniformFlow
    assert isinstance(flow_from_config({"kind": "uniform", "displacement": [1, 0, 0]}), UniformFlow)


def test_a_plugin_must_declare_its_constructor_parameters():
    class Loose(Swirl):
        def __init__(self, omega=0.1, **kw):
            super().__init__(omega)

    class Undeclared(Swirl):
        def __init__(self, omega=0.1, beta=0.0):
            super().__init__(omega)

    with pytest.raises(FlowError, match=r"\*\*kw"):
        registry.flow_parameters(Loose)
    with pytest.raises(FlowError, match=r"\['beta', 'omega'\] but `parameters` declares \['omega'\]"):
        registry.flow_parameters(Undeclared)
    assert registry.flow_parameters(Swirl) == ({"omega": 0.1}, [])


# ------------------------------------------------------------------ docs
def test_the_flows_page_lists_every_kind_and_parameter():
    page = (ROOT / "docs" / "flows.md").read_text()
    for kind in registry.BUILTIN:
        cls = registry.get_flow_class(kind)
        assert f"`{kind}`" in page, kind
        for p in cls.parameters:
            assert f"`{p}`" in page, (kind, p)
    assert registry.ENTRY_POINT_GROUP in page
    assert "flows" in (ROOT / "docs" / "index.md").read_text()


# ------------------------------------------------------------------ a study case with a new kind
def test_a_study_case_with_a_lamb_oseen_flow_runs_through_its_errors_stage(tmp_path):
    """The tiny study's first case with a Lamb–Oseen vortex: the workflow's displace and errors stages
    (their stage configs, as Snakemake passes them) on the true volumes of both frames."""
    from lfstudy import io
    from lfstudy import workflow as wf
    from lfstudy.simulate.flows import true_displacement
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config, expand_cases, stage_config

    raw = _tiny()
    spec = {"kind": "lamb_oseen", "circulation": 3.0, "core_radius": 3.0, "center": [0.3, -0.2, 0.0]}
    raw["flows"] = {"vortex": spec}
    raw["sweep"] = {"ppp": [0.004], "flow": ["vortex"]}
    cfg = validate_config(raw)
    cid = expand_cases(cfg)[0].case_id
    ccfg = case_config(cfg, cid)
    a = cl.case_particles(ccfg)
    io.write_zarr(a, tmp_path / "particles_a.zarr")
    wf.run_displace(stage_config(cfg, cid, "displace"), tmp_path / "particles_a.zarr", tmp_path / "particles_b.zarr")
    b = io.open_zarr(tmp_path / "particles_b.zarr").load()
    vortex = LambOseenVortex(circulation=3.0, core_radius=3.0, center=(0.3, -0.2, 0.0))  # as the config says
    moved = integrate(vortex, a["x"].values, a["y"].values, a["z"].values, 1.0, 100)
    for c, m in zip("xyz", moved):
        np.testing.assert_array_equal(b[c].values, m)
    va, vb = cl.oracle_volumes(ccfg, a, b)  # a perfect reconstruction stands in for the case's
    io.write_zarr(va, tmp_path / "volume_a.zarr")
    io.write_zarr(cl.case_piv(ccfg, va, vb), tmp_path / "piv.zarr")
    paths = [tmp_path / n for n in ("piv.zarr", "volume_a.zarr", "particles_a.zarr", "errors.zarr")]
    wf.run_errors(stage_config(cfg, cid, "errors"), *paths, particles_b=tmp_path / "particles_b.zarr")
    err = io.open_zarr(tmp_path / "errors.zarr").load()
    assert err.attrs["case_id"] == cid and "flow~vortex" in cid
    grid = {d: g.values for d, g in zip("zyx", xr.broadcast(err["z"], err["y"], err["x"]))}
    truth = true_displacement(vortex, grid["x"], grid["y"], grid["z"])
    for c, t in zip("uvw", truth):
        np.testing.assert_allclose(err[f"{c}_true_mm"].values, t, rtol=1e-12, atol=1e-15)
    # the PIV on the true volumes follows the rotation: its error is a fraction of the displacement
    # the PIV on the true volumes follows the rotation where it keeps its vectors (the tiny grid's 3 x 3
    # in-plane windows reject most of a rotation's outer vectors): its error is a fraction of the truth
    valid = np.isfinite(err["u_err_mm"].values)
    assert valid.sum() >= 2
    for c in "uv":
        true_rms = np.sqrt(np.mean(err[f"{c}_true_mm"].values[valid] ** 2))
        assert np.sqrt(np.nanmean(err[f"{c}_err_mm"].values ** 2)) < 0.3 * true_rms, c


@pytest.mark.slow  # a Snakemake dry run (seconds)
def test_the_workflow_reads_a_file_flow_relative_to_its_config_and_makes_it_an_input(tmp_path):
    """A file flow's path is relative to the config file; its zarr store's files are inputs of the rules
    that use the flow (displace, errors) and of no other, so editing the snapshot reruns exactly those."""
    import subprocess
    import sys

    (tmp_path / "cfg" / "dns").mkdir(parents=True)
    _field_dataset().to_zarr(tmp_path / "cfg" / "dns" / "snap.zarr", consolidated=False)
    raw = _tiny()
    raw["flows"] = {"dns": {"kind": "file", "path": "dns/snap.zarr", "outside": "nearest"}}
    raw["sweep"] = {"ppp": [0.004], "flow": ["dns"]}
    cfg_path = tmp_path / "cfg" / "study.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    work = tmp_path / "work"
    work.mkdir()
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work), "-n", "--cores", "1"]
    r = subprocess.run([*cmd, "--configfile", str(cfg_path)], capture_output=True, text=True, timeout=300, cwd=work)
    assert r.returncode == 0, r.stderr[-3000:]
    store = str(tmp_path / "cfg" / "dns" / "snap.zarr")
    jobs = {}
    for block in (r.stdout + r.stderr).split("\nrule ")[1:]:
        name = block.split(":", 1)[0].strip()
        line = next((ln for ln in block.splitlines() if ln.strip().startswith("input:")), "")
        jobs[name] = store + "/zarr.json" in line
    assert jobs["displace"] and jobs["errors"], jobs
    assert not any(v for k, v in jobs.items() if k not in ("displace", "errors")), jobs
