"""Reconstruction on one object-space grid: grid, plenoptic projector, MART, deconvolution (issue: depth)."""

from __future__ import annotations

import inspect
import json
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import yaml
from scipy import ndimage

from lfstudy import plugins as plugins_module
from lfstudy.config import ConfigError
from lfstudy.lightfield import find_lenslet_centers, focal_stack, register, synthetic_pinhole
from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct import (
    GridError,
    ReconstructionError,
    ReconstructionInputs,
    ReconstructionMethod,
    available_methods,
    default_voxel_z,
    focal_stack_as_is,
    get_method,
    make_grid,
    reconstruct,
    register_method,
    threshold_dilate,
    unregister_method,
)
from lfstudy.reconstruct.deconvolution import richardson_lucy
from lfstudy.reconstruct.ipr import IPRSettings, ipr
from lfstudy.reconstruct.mart import mart, mart_plan
from lfstudy.reconstruct.projector import PlenopticProjector
from lfstudy.reconstruct.registry import BUILTIN, ENTRY_POINT_GROUP, detect_parameters
from lfstudy.simulate import make_field, render
from lfstudy.study.config import load_schema, validate_config

CAM = PlenopticCamera(300, 300, 0.0074, 0.125, 0.5, 50.0, -1.0)  # Table 4.3 optics, 18 x 18 lenslets
#: Well separated particles at sub-voxel positions: in focus, in front of and behind the focal plane.
POINTS = [(0.33, -0.27, 0.1), (-0.52, 0.41, 1.7), (0.61, 0.48, -2.3), (-0.38, -0.55, -0.9)]


@pytest.fixture(scope="module")
def frame():
    cen = find_lenslet_centers(synthetic_pinhole(CAM, amplitude=3000, seed=1), CAM)
    field = make_field(*[np.array(v) for v in zip(*POINTS)], np.ones(len(POINTS)))
    lf = register(render(CAM, field, 60_000, 7, method="montecarlo"), cen, CAM)
    grid = make_grid(CAM, CAM.focal_planes())
    stack = focal_stack(lf, CAM, CAM.planes_at(grid.z), x=grid.x, y=grid.y).compute()
    return ReconstructionInputs(stack=stack, lightfield=lf, centers=cen, camera=CAM, grid=grid)


def test_default_grid_is_uniform_and_covers_the_marching():
    planes = CAM.focal_planes()
    grid = make_grid(CAM, planes)
    zp = np.sort(planes["z"].values)
    dz = default_voxel_z(CAM)
    # half the Table 5.1 spacing at the focal plane: about 0.5 mm for these optics
    assert dz == pytest.approx(0.25 * (zp[9] - zp[7]), rel=1e-9) and 0.45 < dz < 0.55
    assert np.allclose(np.diff(grid.z), dz) and np.any(np.isclose(grid.z, 0.0, atol=1e-12))
    assert zp[0] - 1e-9 <= grid.z[0] < zp[0] + dz and zp[-1] - dz < grid.z[-1] <= zp[-1] + 1e-9
    assert grid.dx == grid.dy == pytest.approx(0.125) and grid.shape[1:] == (18, 18)
    assert np.allclose(grid.x, -grid.x[::-1])  # centred on the optical axis
    thesis = make_grid(CAM, planes, spacing="planes")
    assert np.allclose(thesis.z, zp) and not thesis.uniform_z
    fine = make_grid(CAM, planes, voxel_xy=0.0625, voxel_z=0.25)
    assert fine.shape[1:] == (36, 36) and fine.dx == pytest.approx(0.0625)


def test_grid_z_range_covers_the_measurement_volume():
    """grid.z_range: the same depth whatever the marching (z = 0 stays a voxel centre)."""
    planes = CAM.focal_planes()
    dz = default_voxel_z(CAM)
    g = make_grid(CAM, planes, z_range=(-1.3, 2.2))
    assert np.allclose(np.diff(g.z), dz) and np.any(np.isclose(g.z, 0.0, atol=1e-12))
    assert -1.3 <= g.z[0] < -1.3 + dz and 2.2 - dz < g.z[-1] <= 2.2
    thesis = make_grid(CAM, planes, spacing="planes", z_range=(-2.0, 2.0))
    zp = np.sort(planes["z"].values)
    assert np.array_equal(thesis.z, zp[(zp >= -2.0) & (zp <= 2.0)]) and 0 < thesis.z.size < zp.size
    for bad in ((2.0, -2.0), (0.1, 0.2), ("a", 1), (np.nan, 1.0)):
        with pytest.raises(GridError, match=r"grid\.z_range"):
            make_grid(CAM, planes, z_range=bad)
    with pytest.raises(ConfigError, match=r"config key 'grid'.*grid\.z_range = \[1\.0, -1\.0\]"):
        cfg = yaml.safe_load((Path(__file__).parents[1] / "config" / "demo.yaml").read_text())
        validate_config({**cfg, "grid": {"z_range": [1.0, -1.0]}})


def test_grid_bad_input_names_the_setting():
    planes = CAM.focal_planes()
    with pytest.raises(GridError, match=r"grid\.voxel_z = -1"):
        make_grid(CAM, planes, voxel_z=-1)
    with pytest.raises(GridError, match=r"grid: .*exceed|over grid\.max_bytes"):
        make_grid(CAM, planes, voxel_xy=0.001, voxel_z=0.001, max_bytes=1e9)
    with pytest.raises(ConfigError, match=r"grid\.spacing.*allowed values are 'uniform', 'planes'"):
        validate_config({"camera": {}, "grid": {"spacing": "log"}})


def test_projector_and_its_transpose_are_adjoint(frame):
    proj = PlenopticProjector(frame.lightfield, CAM, frame.grid)
    rng = np.random.default_rng(0)
    vol = rng.random(frame.grid.shape)
    lf = rng.random(frame.lightfield.shape)
    lhs = float(np.sum(proj.forward(vol) * lf))
    rhs = float(np.sum(vol * proj.adjoint(lf)))
    assert lhs == pytest.approx(rhs, rel=1e-12)
    # and a voxel's light is (nearly) all recorded: Σ_samples w ≈ 1 near the axis
    e = np.zeros(frame.grid.shape)
    e[int(np.argmin(np.abs(frame.grid.z))), 9, 9] = 1.0
    assert 0.9 < proj.forward(e).sum() < 1.05


def test_column_kernels_and_uniform_projection_match_the_full_projector(frame):
    """MART's per-column projections, multi-channel back-projection and A·1 equal A and Aᵀ."""
    proj = PlenopticProjector(frame.lightfield, CAM, frame.grid)
    rng = np.random.default_rng(1)
    vol = rng.random(frame.grid.shape)
    full = proj.forward(vol).reshape(-1, proj.n, proj.n)
    ones = proj.forward(np.ones(frame.grid.shape)).reshape(-1, proj.n, proj.n)
    np.testing.assert_allclose(proj.uniform_projection(), ones, rtol=1e-12, atol=1e-15)
    lf = np.where(proj.gain > 0, rng.random(full.shape), 0.0)  # samples outside the aperture carry nothing
    out = np.zeros((3, *frame.grid.shape))
    for pc, prs in proj.columns():
        got = proj.column_forward(vol, pc, prs, np.empty((prs.size, proj.lenses.size)))
        np.testing.assert_allclose(got, proj.column_values(full, pc, prs), rtol=1e-12)
        vals = proj.column_values(lf, pc, prs)
        proj.column_accumulate_many(pc, prs, np.stack([vals, 2 * vals]), np.array([0, 2]), out)
    # Aᵀ weighs each sample by its gain; the MART back-projection by the beam fraction alone
    per_gain = np.where(proj.gain > 0, lf / np.where(proj.gain > 0, proj.gain, 1.0), 0.0)
    ref = proj.adjoint(per_gain.reshape(proj.shape_lf))
    np.testing.assert_allclose(out[0], ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out[2], 2 * ref, rtol=1e-10, atol=1e-12)
    assert not out[1].any()


def _centroid(vol: np.ndarray, grid, p, half=(3, 2, 2)):
    """Intensity centroid (z, y, x) [mm] in a box around the true position p = (x, y, z)."""
    x, y, z = p
    iz, iy, ix = (int(np.argmin(np.abs(c - v))) for c, v in ((grid.z, z), (grid.y, y), (grid.x, x)))
    sl = [slice(max(i - h, 0), i + h + 1) for i, h in zip((iz, iy, ix), half)]
    sub = vol[tuple(sl)]
    cs = [grid.z[sl[0]], grid.y[sl[1]], grid.x[sl[2]]]
    w = sub.sum()
    return [float((sub.sum(axis=tuple(a for a in range(3) if a != k)) * cs[k]).sum() / w) for k in range(3)]


@pytest.mark.parametrize(
    ("method", "params"),
    [("threshold", {}), ("none", {}), ("deconvolution", {"iterations": 20}), ("mart", {"iterations": 3})],
)
def test_particles_come_back_at_their_voxels(frame, method, params):
    vol = reconstruct(frame, method, **params)
    assert vol.dims == ("z", "y", "x") and np.allclose(vol["z"].values, frame.grid.z)
    v = np.asarray(vol.values, dtype=float)
    assert np.all(v >= 0) and np.all(np.isfinite(v))
    dz = frame.grid.dz.mean()
    for p in POINTS:
        cz, cy, cx = _centroid(v, frame.grid, p)
        assert abs(cx - p[0]) < 0.5 * frame.grid.dx, (method, p, cx)
        assert abs(cy - p[1]) < 0.5 * frame.grid.dy, (method, p, cy)
        assert abs(cz - p[2]) < 1.0 * dz, (method, p, cz)


def test_mart_is_non_negative_and_its_residual_falls_on_noise_free_data(frame):
    """Data made by the model itself (consistent, noise-free): every iteration lowers ‖A·E − I‖."""
    proj = PlenopticProjector(frame.lightfield, CAM, frame.grid)
    truth = np.zeros(frame.grid.shape)
    rng = np.random.default_rng(3)
    for _ in range(6):
        truth[rng.integers(8, 25), rng.integers(3, 15), rng.integers(3, 15)] = rng.uniform(1e3, 3e3)
    lf = frame.lightfield.copy(data=proj.forward(truth))
    vol = mart(lf, CAM, frame.grid, iterations=6, init="uniform", track_residual=True, offset=1e-6, smoothing=0.0)
    res = np.asarray(vol.attrs["residual"])
    assert np.all(np.diff(res) < 0), res
    assert res[-1] < 0.5 * res[0]
    assert float(vol.min()) >= 0.0


def test_mart_plan_gives_the_same_bytes_and_is_checked(frame):
    """A plan (the geometry-only part, made once: IPR's candidate volumes reuse it) changes no byte of
    MART's volume, for any light field of that layout; a plan for other settings is refused."""
    plan = mart_plan(frame.lightfield, CAM, frame.grid)
    for lf, init in ((frame.lightfield, "mlos"), (0.5 * frame.lightfield + 3.0, "mlos"), (frame.lightfield, "uniform")):
        ref = mart(lf, CAM, frame.grid, iterations=1, init=init).values
        np.testing.assert_array_equal(mart(lf, CAM, frame.grid, iterations=1, init=init, plan=plan).values, ref)
    with pytest.raises(ReconstructionError, match=r"plan was made for another grid or other settings"):
        mart(frame.lightfield, CAM, frame.grid, iterations=1, subsets=2, plan=plan)


def test_mart_plan_planes_are_the_thinned_grid_s_plan(frame):
    """A plan's every-other-plane plan (IPR's residual candidate volumes) reads views of the same weight tables
    (no new table memory) and gives the bytes of a plan made for the thinned grid; MART on it touches only
    those planes' voxels (its volume is the thinned grid's)."""
    plan = mart_plan(frame.lightfield, CAM, frame.grid)
    for start in (0, 1):
        sub = plan.planes(2, start)
        g = sub.proj.grid
        assert np.array_equal(g.z, frame.grid.z[start::2]) and g.shape[1:] == frame.grid.shape[1:]
        assert np.shares_memory(sub.proj.wxs, plan.proj.wxs) and np.shares_memory(sub.proj.sys, plan.proj.sys)
        fresh = mart_plan(frame.lightfield, CAM, g)
        np.testing.assert_array_equal(sub.seen, fresh.seen)
        ref = mart(frame.lightfield, CAM, g, iterations=1, plan=fresh)
        got = mart(frame.lightfield, CAM, g, iterations=1, plan=sub)
        np.testing.assert_array_equal(got.values, ref.values)
        assert got.shape == g.shape and float(got.max()) > 0
    with pytest.raises(ReconstructionError, match=r"plan was made for another grid"):
        mart(frame.lightfield, CAM, frame.grid, iterations=1, plan=plan.planes(2))
    with pytest.raises(ValueError, match=r"planes: step = 0 must be >= 1"):
        plan.planes(0)


def test_reconstruction_bad_input(frame):
    with pytest.raises(ReconstructionError, match=r"reconstruct\.method = 'nosuch'.*available"):
        reconstruct(frame, "nosuch")
    with pytest.raises(ReconstructionError, match=r"reconstruct\.mart\.iterations' = -1.*allowed range is \[0, 200\]"):
        reconstruct(frame, "mart", iterations=-1)
    with pytest.raises(ConfigError, match=r"reconstruct\.mart\.relaxation' = 3.*\(0, 2\]"):
        validate_config({"camera": {}, "reconstruct": {"method": "mart", "mart": {"relaxation": 3}}})
    with pytest.raises(ReconstructionError, match=r"needs lightfield"):
        reconstruct(ReconstructionInputs(stack=frame.stack, camera=CAM, grid=frame.grid), "mart")
    # a light field that belongs to another calibration
    other = frame.lightfield.isel(lcol=slice(0, 12))
    with pytest.raises(ReconstructionError, match=r"do not belong together"):
        ReconstructionInputs(stack=frame.stack, lightfield=other, centers=frame.centers, camera=CAM)
    # a stack that is not on the grid
    with pytest.raises(ReconstructionError, match=r"not on the reconstruction grid"):
        ReconstructionInputs(stack=frame.stack.isel(z=slice(1, None)), grid=frame.grid)
    bad = frame.stack.copy(data=np.where(frame.stack.values > 0, np.nan, 0.0))
    with pytest.raises(ReconstructionError, match="non-finite"):
        reconstruct(ReconstructionInputs(stack=bad, lightfield=frame.lightfield, camera=CAM), "deconvolution")


def test_method_schemas_reach_the_config():
    camera = {
        "sensor": {"n_pixels_x": 300, "n_pixels_y": 300, "pixel_pitch": 0.0074},
        "lenslet": {"pitch": 0.125, "focal_length": 0.5},
        "main_lens": {"focal_length": 50.0},
        "magnification": -1.0,
    }
    cfg = validate_config({"camera": camera, "reconstruct": {"method": "mart"}})
    assert cfg["reconstruct"]["mart"]["iterations"] == 3 and cfg["reconstruct"]["threshold"]["k"] == 3.0
    assert cfg["grid"] == {"spacing": "uniform", "voxel_xy": None, "voxel_z": None, "z_range": None, "max_bytes": 4e9}


# --------------------------------------------------------------------------- defaults and plug-ins

#: each built-in method's algorithm function (the public pure function its run() calls)
ALGORITHMS = {
    "threshold": threshold_dilate,
    "none": focal_stack_as_is,
    "mart": mart,
    "deconvolution": richardson_lucy,
    "ipr": ipr,
}


def _keyword_defaults(func) -> dict:
    out = {p.name: p.default for p in inspect.signature(func).parameters.values() if p.default is not p.empty}
    if func is ipr:  # ipr takes the fit's settings as one IPRSettings (or its fields), whose defaults are these
        out |= IPRSettings.defaults()
    return out


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_a_methods_defaults_are_stated_once(name):
    """run()'s signature states the defaults; the config schema and the algorithm function agree with it."""
    cls = get_method(name)
    run = detect_parameters(cls)
    assert set(run) == set(cls.parameters)
    assert all("default" not in spec for spec in cls.parameters.values()), "a default stated twice"
    schema = load_schema()["properties"]["reconstruct"]["properties"][name]["properties"]
    assert {k: v["default"] for k, v in schema.items()} == run
    algo = _keyword_defaults(ALGORITHMS[name])
    assert {k: algo[k] for k in run if k in algo} == run, f"{ALGORITHMS[name].__name__} has other defaults"
    assert set(run) <= set(algo), f"{ALGORITHMS[name].__name__} does not take {sorted(set(run) - set(algo))}"


def test_a_methods_parameters_must_match_its_run_signature():
    class Base(ReconstructionMethod):
        name = "t"
        parameters: ClassVar[dict] = {"a": {"type": "number"}}

    class KwArgs(Base):
        def run(self, inputs, *, progress=False, **params): ...

    class NoDefault(Base):
        def run(self, inputs, *, a, progress=False): ...

    class Undeclared(Base):
        def run(self, inputs, *, a=1.0, b=2, progress=False): ...

    class TwoDefaults(Base):
        parameters: ClassVar[dict] = {"a": {"type": "number", "default": 2.0}}

        def run(self, inputs, *, a=1.0, progress=False): ...

    class Good(Base):
        parameters: ClassVar[dict] = {"a": {"type": "number", "default": 1.0}}  # the same default: allowed

        def run(self, inputs, *, a=1.0, progress=False): ...

    for cls, msg in [
        (KwArgs, r"\*\*params"),
        (NoDefault, "'a' needs a default"),
        (Undeclared, r"takes the parameters \['a', 'b'\] but `parameters` declares \['a'\]"),
        (TwoDefaults, "default 2.0 in `parameters` but 1.0 in run"),
    ]:
        with pytest.raises(ReconstructionError, match=msg):
            register_method(cls)
    assert detect_parameters(Good) == {"a": 1.0}


@pytest.fixture
def plugins(monkeypatch):
    """Installed entry points replaced by the test's (the registry's and the schema's caches cleared)."""
    from lfstudy.reconstruct import registry
    from lfstudy.study import schema

    def install(*eps: EntryPoint) -> None:
        monkeypatch.setattr(plugins_module, "entry_points", lambda group: [e for e in eps if e.group == group])
        registry._plugins.cache_clear()
        schema._schema.cache_clear()

    yield install
    monkeypatch.undo()
    registry._plugins.cache_clear()
    schema._schema.cache_clear()


def test_a_plugin_that_fails_to_load_is_skipped_with_a_warning(plugins):
    plugins(
        EntryPoint("broken", "lfstudy_no_such_package.methods:Broken", ENTRY_POINT_GROUP),
        EntryPoint("notamethod", "lfstudy.reconstruct.threshold:disk", ENTRY_POINT_GROUP),
        EntryPoint("thr2", "lfstudy.reconstruct.threshold:Threshold", ENTRY_POINT_GROUP),
    )
    camera = {
        "sensor": {"n_pixels_x": 300, "n_pixels_y": 300, "pixel_pitch": 0.0074},
        "lenslet": {"pitch": 0.125, "focal_length": 0.5},
        "main_lens": {"focal_length": 50.0},
        "magnification": -1.0,
    }
    with pytest.warns(RuntimeWarning) as rec:
        cfg = validate_config({"camera": camera, "reconstruct": {"method": "thr2"}})
    msgs = [str(w.message) for w in rec]
    assert any("'broken'" in m and "lfstudy_no_such_package" in m and "ModuleNotFoundError" in m for m in msgs)
    assert any("'notamethod'" in m and "not a ReconstructionMethod" in m for m in msgs)
    assert cfg["reconstruct"]["thr2"] == {"k": 3.0, "dilation_radius": 1, "dilation_ndim": 2}
    # the schema's text lists the installed method with the built-ins, from the registry
    text = load_schema()["properties"]["reconstruct"]["properties"]["method"]["description"]
    assert all(f"{m} ({get_method(m).description})" in text for m in ("thr2", *BUILTIN)) and "broken" not in text
    assert "thr2" in available_methods() and "broken" not in available_methods()
    with pytest.raises(ReconstructionError, match=r"'broken': the method installed .* failed to load: ModuleNot"):
        get_method("broken")
    with pytest.raises(ConfigError, match=r"reconstruct.method' = 'broken'"):
        validate_config({"camera": camera, "reconstruct": {"method": "broken"}})


def test_the_schema_lists_no_method_or_kind_by_hand():
    """schema.yaml states no list of methods or flow kinds (it went stale: ipr was missing); the assembled
    schema's descriptions name every one, with its class's description."""
    from lfstudy.config import read_schema
    from lfstudy.simulate.flows import BUILTIN as KINDS
    from lfstudy.simulate.flows import get_flow_class

    raw = read_schema("schema.yaml")["properties"]
    hand = raw["reconstruct"]["properties"]["method"]["description"]
    hand_kind = raw["flows"]["additionalProperties"]["properties"]["kind"]["description"]
    assert not any(f"{m}:" in hand or f"{m} (" in hand for m in BUILTIN)
    assert not any(f"{k}," in hand_kind or f"{k} (" in hand_kind for k in KINDS)
    full = load_schema()["properties"]
    text = full["reconstruct"]["properties"]["method"]["description"]
    assert all(f"{m} ({get_method(m).description})" in text for m in BUILTIN)
    kind = full["flows"]["additionalProperties"]["properties"]["kind"]
    assert kind["enum"][: len(KINDS)] == list(KINDS)
    assert all(f"{k} ({get_flow_class(k).description})" in kind["description"] for k in KINDS)


def test_a_plugin_named_as_a_builtin_method_is_skipped_without_loading(plugins):
    """The rule of both registries (lfstudy.plugins): an entry point that reuses a built-in's name is
    skipped with a warning naming it, before it is imported; reconstruct.method mart stays MART."""
    from lfstudy.reconstruct.mart import MART

    plugins(
        EntryPoint("mart", "lfstudy_no_such_package.methods:FastMart", ENTRY_POINT_GROUP),
        EntryPoint("thr2", "lfstudy.reconstruct.threshold:Threshold", ENTRY_POINT_GROUP),
    )
    with pytest.warns(RuntimeWarning) as rec:
        names = available_methods()
    msgs = [str(w.message) for w in rec]
    # one warning, naming the entry point and the rule (no ModuleNotFoundError: it was not imported)
    assert len(msgs) == 1 and "'mart'" in msgs[0] and "lfstudy_no_such_package.methods:FastMart" in msgs[0]
    assert "built-in reconstruction method" in msgs[0] and "ModuleNotFound" not in msgs[0]
    assert names.count("mart") == 1 and "thr2" in names
    assert get_method("mart") is MART


def test_register_method_replaces_a_builtin_only_when_asked():
    from lfstudy.reconstruct.threshold import Threshold

    class MyThreshold(Threshold):
        name = "threshold"

    with pytest.raises(ReconstructionError, match=r"'threshold' is built in; register_method\(\.\.\., replace=True\)"):
        register_method(MyThreshold)
    with pytest.raises(ReconstructionError, match="'mart' is built in"):
        register_method("mart")
    assert get_method("threshold") is Threshold
    try:
        assert register_method(MyThreshold, replace=True) is MyThreshold
        assert get_method("threshold") is MyThreshold
        assert available_methods().count("threshold") == 1
    finally:
        unregister_method("threshold")
    assert get_method("threshold") is Threshold
    # the decorator forms
    try:
        register_method(replace=True)(MyThreshold)
        assert get_method("threshold") is MyThreshold
    finally:
        unregister_method("threshold")
    assert get_method("threshold") is Threshold


# --------------------------------------------------------------------------- methods that fit particles
def test_a_particle_method_gives_its_list_with_the_volume(frame):
    """ipr declares particles = True: reconstruct_particles gives the volume reconstruct gives (the same
    values and attrs) and the particle list it was rendered from; the others give no list."""
    from lfstudy.reconstruct import gives_particles, reconstruct_particles
    from lfstudy.reconstruct.ipr import render_particles

    assert gives_particles("ipr") and not any(gives_particles(m) for m in ("mart", "threshold", "none"))
    kw = {"iterations": 1, "residual_candidates": 0}
    vol, parts = reconstruct_particles(frame, "ipr", **kw)
    ref = reconstruct(frame, "ipr", **kw)
    np.testing.assert_array_equal(vol.values, ref.values)
    # every attr but the wall times (seconds, and IPR's split of them: seconds_mart, seconds_patches, ...)
    assert {k: v for k, v in vol.attrs.items() if not k.startswith("seconds")} == {
        k: v for k, v in ref.attrs.items() if not k.startswith("seconds")
    }
    assert parts.sizes["particle"] == vol.attrs["n_particles"] > 0
    assert parts.attrs["method"] == "ipr" and parts.attrs["param_iterations"] == 1
    for v in ("x", "y", "z", "sigma_x", "sigma_y", "sigma_z"):
        assert parts[v].attrs["units"] == "mm" and parts[v].attrs["long_name"]
    assert {"intensity", "residual"} <= set(parts.data_vars)
    # the volume is the list's render: one fit, not two
    np.testing.assert_allclose(
        vol.values, render_particles(parts, frame.grid, CAM)[0].astype(np.float32), rtol=0, atol=0
    )
    mart_vol, none = reconstruct_particles(frame, "mart", iterations=1)
    assert none is None
    np.testing.assert_array_equal(mart_vol.values, reconstruct(frame, "mart", iterations=1).values)
    with pytest.raises(ReconstructionError, match="fits no particles"):
        get_method("mart")().run_particles(frame)
    with pytest.raises(ReconstructionError, match=r"'reconstruct.ipr.shake' = 0.0: allowed range"):
        reconstruct_particles(frame, "ipr", shake=0.0)


@pytest.fixture(scope="module")
def ipr_case(tmp_path_factory):
    """A tiny ipr case of tests/data/tiny.yaml (8 particles, 2 iterations): its stage config and the
    stores the reconstruct stage reads."""
    from lfstudy import io
    from lfstudy.study import case as cl
    from lfstudy.study.config import case_config, expand_cases, stage_config

    raw = yaml.safe_load((Path(__file__).parent / "data" / "tiny.yaml").read_text())
    raw.update(
        particles={"count": 8, "z_span": 3.0},
        sweep={"flow": ["uniform_x"]},
        reconstruct={"method": "ipr", "ipr": {"iterations": 2, "residual_candidates": 1}},
    )
    cfg = validate_config(raw)
    case = expand_cases(cfg)[0]
    full = case_config(cfg, case)
    cam = cl.case_camera(full)
    cen = find_lenslet_centers(cl.case_pinhole(full), cam)
    lf = register(cl.case_image(full, cl.case_particles(full), "a"), cen, cam)
    d = tmp_path_factory.mktemp("ipr_case")
    io.write_zarr(cl.case_stack(full, lf), d / "stack.zarr", name="intensity")
    io.write_zarr(lf, d / "lightfield.zarr", name="radiance")
    io.write_zarr(cen, d / "centers.zarr")
    return stage_config(cfg, case, "reconstruct"), d


def test_reconstruct_stage_writes_the_particle_list(ipr_case):
    """run_reconstruct of an ipr case writes the volume and, beside it, the particle list the volume was
    rendered from (one fit), with units and provenance; a path that does not fit the method is refused."""
    from lfstudy import io
    from lfstudy.reconstruct.ipr import render_particles
    from lfstudy.study import case as cl
    from lfstudy.workflow import run_reconstruct

    ccfg, d = ipr_case
    ins = (d / "stack.zarr", d / "lightfield.zarr", d / "centers.zarr")
    run_reconstruct(ccfg, *ins, d / "volume_a.zarr", d / "volume_a.particles.zarr")
    vol = io.open_array(d / "volume_a.zarr").load()
    parts = io.open_zarr(d / "volume_a.particles.zarr").load()
    assert vol.attrs["method"] == "ipr" and parts.attrs["method"] == "ipr"
    assert parts.sizes["particle"] == vol.attrs["n_particles"] > 0
    assert set(parts.data_vars) >= {"x", "y", "z", "intensity", "residual", "sigma_x", "sigma_y", "sigma_z"}
    assert parts["z"].attrs["units"] == "mm" and parts["residual"].attrs["long_name"]
    assert json.loads(parts.attrs["parameters"])["reconstruct"]["method"] == "ipr"
    assert parts.attrs["lfstudy_version"] == vol.attrs["lfstudy_version"]
    grid = cl.case_grid(ccfg)
    np.testing.assert_array_equal(vol.values, render_particles(parts, grid, cl.case_camera(ccfg))[0].astype(np.float32))
    # the Snakefile declares the list exactly for the methods that fit particles
    with pytest.raises(ValueError, match=r"reconstruct.method = 'ipr' needs a particle-list path"):
        run_reconstruct(ccfg, *ins, d / "v2.zarr")
    mart = {**ccfg, "reconstruct": {**ccfg["reconstruct"], "method": "mart"}}
    with pytest.raises(ValueError, match=r"reconstruct.method = 'mart' fits no particles"):
        run_reconstruct(mart, *ins, d / "v3.zarr", d / "v3.particles.zarr")
    assert not (d / "v2.zarr").exists() and not (d / "v3.zarr").exists() and not (d / "v3.particles.zarr").exists()


def test_mart_update_in_place_gives_the_expression_s_bytes():
    """MART's multiplicative update, smoothing and coverage threshold run in place (no voxel-sized temporaries:
    they set the peak memory of IPR's candidate grid on a full frame) and give the bytes of the expressions
    they replace, with uncovered voxels, factors beyond the e^±20 bound and zero coverage among them."""
    from lfstudy.reconstruct.mart import _seen, _update

    rng = np.random.default_rng(5)
    shape = (6, 9, 11)
    vol = rng.uniform(0.0, 3.0, shape)
    num = rng.normal(0.0, 8.0, shape)
    d = np.where(rng.random(shape) < 0.2, 0.0, rng.uniform(0.01, 2.0, shape))
    upd = (d > 0) & (rng.random(shape) < 0.9)
    ref = vol.copy()
    ref[upd] *= np.exp(np.clip(0.7 * num[upd] / d[upd], -20.0, 20.0))
    got = vol.copy()
    _update(got, num.copy(), d, upd, 0.7)
    assert np.array_equal(got, ref) and not np.array_equal(got, vol)
    sm = vol.copy()
    ndimage.gaussian_filter(sm, 0.5, truncate=3.0, output=sm)
    assert np.array_equal(sm, ndimage.gaussian_filter(vol, 0.5, truncate=3.0))
    assert np.array_equal(_seen(d, 0.5), d >= 0.5 * np.percentile(d[d > 0], 90))
    assert not _seen(np.zeros(shape), 0.5).any()


def test_mart_plan_float32_coverage_moves_the_volume_by_rounding_only(frame):
    """IPR keeps its candidate plan's coverage in float32 (half its memory): the volume stays within 1e-5 of its
    maximum of the float64 plan's and its peaks (IPR's candidates) within 1e-4 voxel; a bad dtype is refused."""
    from lfstudy.reconstruct.ipr import _peaks

    p64 = mart_plan(frame.lightfield, CAM, frame.grid)
    p32 = mart_plan(frame.lightfield, CAM, frame.grid, coverage_dtype="float32")
    assert [d.dtype for d in p32.dens] == [np.float32] * len(p64.dens)
    assert sum(d.nbytes for d in p32.dens) * 2 == sum(d.nbytes for d in p64.dens)
    v64 = mart(frame.lightfield, CAM, frame.grid, iterations=2, plan=p64).values
    v32 = mart(frame.lightfield, CAM, frame.grid, iterations=2, plan=p32).values
    assert not np.array_equal(v32, v64) and np.abs(v32 - v64).max() <= 1e-5 * v64.max()
    a, b = _peaks(v64, frame.grid, 0.1), _peaks(v32, frame.grid, 0.1)
    assert len(a) > 3 and a.shape == b.shape
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-4 * frame.grid.dx)
    with pytest.raises(ReconstructionError, match=r"coverage_dtype = 'float16'; allowed: 'float64', 'float32'"):
        mart_plan(frame.lightfield, CAM, frame.grid, coverage_dtype="float16")
