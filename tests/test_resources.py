"""What a method knows is on its class: its memory (lfstudy.study.resources) and whether it uses the volumetric
calibration (lfstudy.study.case); neither module checks a method's name."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import ClassVar

import pytest
import yaml

from lfstudy.config import ConfigError
from lfstudy.reconstruct import ReconstructionMethod, ReconstructionSize, get_method, register_method, unregister_method
from lfstudy.study.config import validate_config
from lfstudy.study.resources import _BASE, case_memory, check_memory
from lfstudy.study.sweep import Sweep

ROOT = Path(__file__).resolve().parents[1]


def _case(path: Path, **reconstruct) -> dict:
    raw = yaml.safe_load(path.read_text())
    cfg = validate_config(raw, base=path.parent)
    sweep = Sweep(cfg)
    ccfg = copy.deepcopy(sweep.apply(next(iter(sweep.cases()))))
    ccfg["reconstruct"].update(reconstruct)
    return ccfg


def test_ipr_estimate_on_the_full_table_4_3_frame_is_the_measured_peak():
    """config/thesis.yaml is the full Table 4.3 frame on 33 planes, where benchmarks/bench_ipr.py --memory
    measured IPR's peak at 7.18 GB (the ipr module docstring) before the shake kept images between iterations;
    the class's estimate must stay near it plus the bounds of what the shake now keeps through the MART rounds
    (its image cache and the fit's two image buffers), and above the other methods' (its candidate grid has 18
    times the voxels)."""
    from lfstudy.reconstruct.ipr.method import _SCRATCH_BYTES
    from lfstudy.reconstruct.ipr.shake import _CACHE_BYTES

    ccfg = _case(ROOT / "config" / "thesis.yaml", method="ipr")
    ipr = case_memory(ccfg)["reconstruct"]
    assert ipr == pytest.approx(7.18e9 + _CACHE_BYTES + _SCRATCH_BYTES, rel=0.05)
    assert ipr < 8e9  # issue 27's bound on a full frame
    for other in ("mart", "threshold", "deconvolution"):
        assert case_memory({**ccfg, "reconstruct": {"method": other}})["reconstruct"] < 0.5 * ipr


def test_a_method_states_its_own_memory():
    """case_memory asks the method's class, a registered one too (no name checks in resources.py)."""

    class Hungry(ReconstructionMethod):
        name = "hungry-test"
        description = "needs a terabyte per voxel plane"
        parameters: ClassVar[dict] = {}

        @classmethod
        def memory_bytes(cls, size: ReconstructionSize, params=None) -> float:
            return size.n_planes * 1e12

        def run(self, inputs, *, progress=False): ...

    ccfg = _case(ROOT / "tests" / "data" / "tiny.yaml", method="threshold")
    base = case_memory(ccfg)
    register_method(Hungry)
    try:
        ccfg["reconstruct"]["method"] = "hungry-test"
        need = case_memory(ccfg)
        nz = round((need["reconstruct"] - _BASE) / 1e12)
        assert nz >= 1 and need["reconstruct"] == nz * 1e12 + _BASE
        assert {k: v for k, v in need.items() if k != "reconstruct"} == {
            k: v for k, v in base.items() if k != "reconstruct"
        }
        with pytest.raises(ConfigError, match=r"config key 'grid'.*reconstruct stage needs about"):
            check_memory(ccfg, available=1e12)
    finally:
        unregister_method("hungry-test")
    # the base class counts the light field and four float64 volumes
    size = ReconstructionSize(n_pixels=100, n_lenslets=10, pixels_per_lenslet=4, n_planes=2, n_voxels=50)
    assert ReconstructionMethod.memory_bytes(size) == 10 * 16 * 4 + 4 * 50 * 8
    assert get_method("threshold").memory_bytes(size) == ReconstructionMethod.memory_bytes(size)


def test_a_volumetric_case_needs_the_calibration_where_the_method_uses_one():
    from lfstudy.reconstruct import ReconstructionError
    from lfstudy.reconstruct.threshold import Threshold
    from lfstudy.study.case import case_reconstruction

    class Modelled(Threshold):
        name = "modelled-test"
        uses_calibration = True

    assert get_method("mart").uses_calibration and get_method("ipr").uses_calibration
    assert not any(get_method(m).uses_calibration for m in ("threshold", "none", "deconvolution"))
    raw = yaml.safe_load((ROOT / "tests" / "data" / "tiny.yaml").read_text())
    raw["refocus"]["model"] = "volumetric"
    sweep = Sweep(validate_config(raw))
    ccfg = copy.deepcopy(sweep.apply(next(iter(sweep.cases()))))
    register_method(Modelled)
    try:
        for method in ("mart", "ipr", "modelled-test"):
            ccfg["reconstruct"]["method"] = method
            with pytest.raises(ValueError, match=rf"method = '{method}' needs the dot-target calibration"):
                case_reconstruction(ccfg, None)
        # a method that does not use it goes on (here to its own check of the inputs)
        ccfg["reconstruct"]["method"] = "threshold"
        with pytest.raises(ReconstructionError, match="'threshold' needs stack"):
            case_reconstruction(ccfg, None)
    finally:
        unregister_method("modelled-test")


def test_the_reconstruct_time_limit_follows_the_method_estimate():
    """A SLURM time limit is a kill: IPR's reconstruct job asks for RUNTIME_MARGIN times its estimate (its time goes
    with the particles: the full Table 4.3 frame at 0.005 ppp took ~45 min), the grid methods for the floor, and a
    retry for twice as much."""
    from lfstudy.study.resources import RUNTIME_MARGIN, job_runtime_min, reconstruct_seconds

    ccfg = _case(ROOT / "config" / "thesis.yaml", method="ipr")
    ccfg["particles"]["ppp"] = 0.005
    n = ccfg["camera"]["sensor"]["n_pixels_x"] * ccfg["camera"]["sensor"]["n_pixels_y"] * 0.005
    est = reconstruct_seconds(ccfg)
    assert 45 * 60 < est < 3 * 45 * 60  # above the measured full frame, within three times it
    assert est == pytest.approx(get_method("ipr").seconds(ReconstructionSize(1, 1, 1, 1, 1, round(n))), rel=0.05)
    minutes = job_runtime_min(ccfg, "reconstruct", 5)
    assert minutes == pytest.approx(RUNTIME_MARGIN * est / 60, abs=1) and minutes > 60
    assert job_runtime_min(ccfg, "reconstruct", 5, attempt=2) == 2 * minutes
    assert job_runtime_min(ccfg, "piv", 5) == 5  # no estimate: the floor
    for other in ("mart", "threshold", "deconvolution"):
        assert job_runtime_min({**ccfg, "reconstruct": {"method": other}}, "reconstruct", 5) == 5
