"""σ of the particles in the PIV's particle volumes (piv.particle_sigma): the oracle's true volumes and the
paired particles' volumes are rendered with it, not with Q's truth σ."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from lfstudy.study.config import validate_config

TINY = Path(__file__).resolve().parents[1] / "tests" / "data" / "tiny.yaml"
W = 0.05  # mm: an axial shift of half a z voxel on a 0.1 mm z grid


def _case(**piv):
    from lfstudy.study.config import case_config, expand_cases

    raw = yaml.safe_load(TINY.read_text())
    raw["flows"] = {"axial": {"kind": "uniform", "displacement": [0.0, 0.0, W]}}
    raw["sweep"] = {"ppp": [0.004], "flow": ["axial"]}
    raw["grid"] = {"z_range": [-1.2, 1.2], "voxel_z": 0.1}
    raw["piv"] = {"window": [8, 16, 16], "spacing": [4, 8, 8], "levels": 2, "mode": "deform", **piv}
    cfg = validate_config(raw)
    return case_config(cfg, expand_cases(cfg)[0].case_id)


def test_the_oracle_reads_an_axial_shift_in_full_with_half_voxel_particles_and_short_with_the_truth_sigma():
    """On a z grid finer than the camera's depth of focus, Q's truth σ is several z voxels long against a
    4-voxel-deep final window, and the correlation of such images reads w short (the demo's Hill oracle read
    0.30-0.74 of it). The oracle's default particles (half a voxel per axis) read the shift in full."""
    from lfstudy.study import case as cl

    ccfg = _case()
    cam = cl.case_camera(ccfg)
    sz = cl.truth_sigma(cam)[0] / 0.1
    assert sz > 2.5, sz  # the premise: the truth's particles are long in z on this grid
    a = cl.case_particles(ccfg)
    b = cl.case_displaced(ccfg, a)
    w = {}
    for label, k in (("default", None), ("truth", sz)):
        c = _case() if k is None else _case(particle_sigma=float(k))
        res = cl.oracle_piv(c, a, b)
        ok = res["valid"].values.astype(bool)
        assert ok.mean() > 0.9, label
        w[label] = float(np.median(res["w_mm"].values[ok]))
        sig = res.attrs["particle_sigma_mm"]
        assert sig[0] == pytest.approx((0.5 if k is None else k) * 0.1) and sig[2] == pytest.approx(sig[1])
    assert w["default"] == pytest.approx(W, rel=0.05), w
    assert w["truth"] < 0.85 * W, w


def test_particle_sigma_is_checked_by_the_schema():
    """A σ of 0 or beyond 5 voxels is refused, naming the field."""
    with pytest.raises(Exception, match="particle_sigma"):
        _case(particle_sigma=0.0)
    with pytest.raises(Exception, match="particle_sigma"):
        _case(particle_sigma=6.0)
