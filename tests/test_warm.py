"""The warm-up job: a tiny copy of a case compiles every numba kernel its stages then use."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from lfstudy.config import read_yaml
from lfstudy.study.config import case_config, validate_config
from lfstudy.study.sweep import Sweep
from lfstudy.study.warm import tiny_case

TINY = Path(__file__).parent / "data" / "tiny.yaml"


def _ipr_config() -> dict:
    """tests/data/tiny.yaml as the demo processes it: Monte-Carlo images, IPR, paired PIV, no depth calibration."""
    raw = read_yaml(TINY)
    raw["camera"]["sensor"].update(n_pixels_x=192, n_pixels_y=192)
    raw["raytrace"] = {"method": "montecarlo", "rays_per_particle": 1500}
    raw["reconstruct"] = {"method": "ipr"}
    raw["depth_calibration"] = {"enabled": False}
    raw["sweep"] = {"ppp": [0.004], "flow": ["uniform_x"]}
    return validate_config(raw)


def test_the_tiny_case_is_the_case_on_a_few_lenslets():
    cfg = _ipr_config()
    cc = case_config(cfg, next(iter(Sweep(cfg).cases())))
    t = tiny_case(cc, lenslets=6)
    assert t["camera"]["sensor"]["n_pixels_x"] == t["camera"]["sensor"]["n_pixels_y"] == 6 * 12  # 12 px a lenslet
    assert t["camera"]["lenslet"] == cc["camera"]["lenslet"]
    assert t["reconstruct"] == cc["reconstruct"] and t["raytrace"] == cc["raytrace"]
    assert t["piv"]["window"] == [8, 8, 8] and t["piv"]["particles"] == cc["piv"]["particles"]
    assert cc["camera"]["sensor"]["n_pixels_x"] == 192  # the case's own config is left alone
    with pytest.raises(ValueError, match="lenslets"):
        tiny_case(cc, lenslets=3)


_CHILD = r"""
import json, sys
from pathlib import Path

import numba

from lfstudy import workflow as wf
from lfstudy.study.config import case_config, stage_config
from lfstudy.study.sweep import Sweep, frame_stage
from lfstudy.study.warm import warm_kernels

cfg = json.loads(sys.argv[1])
out = Path(sys.argv[2])


def compiled():
    seen = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith("lfstudy"):
            for attr, obj in vars(mod).items():
                if isinstance(obj, numba.core.dispatcher.Dispatcher):
                    seen[f"{name}.{attr}"] = len(obj.signatures)
    return seen


sweep = Sweep(cfg)
case = next(iter(sweep.cases()))
warm = warm_kernels(case_config(cfg, case))
before = compiled()


def sc(stage, frame=""):
    return stage_config(cfg, case, frame_stage(stage, frame))


def p(name):
    return str(out / name)


wf.run_particles(sc("particles"), p("particles_a.zarr"))
wf.run_displace(sc("displace"), p("particles_a.zarr"), p("particles_b.zarr"))
wf.run_pinhole(sc("pinhole"), p("pinhole.zarr"), p("pinhole.tif"))
for f in "ab":
    wf.run_simulate(sc("simulate", f), f, p(f"particles_{f}.zarr"), p(f"raw_{f}.zarr"), p(f"raw_{f}.tif"))
rendered = compiled()  # the renderers: the study's own first render jobs compile them
wf.run_calibrate(sc("calibrate"), p("pinhole.zarr"), p("centers.zarr"))
for f in "ab":
    wf.run_register(sc("register", f), p(f"raw_{f}.zarr"), p("centers.zarr"), p(f"lf_{f}.zarr"))
    wf.run_refocus(sc("refocus", f), p(f"lf_{f}.zarr"), p(f"stack_{f}.zarr"))
    wf.run_reconstruct(
        sc("reconstruct", f), p(f"stack_{f}.zarr"), p(f"lf_{f}.zarr"), p("centers.zarr"), p(f"vol_{f}.zarr"),
        p(f"parts_{f}.zarr"),
    )
wf.run_piv(sc("piv"), p("vol_a.zarr"), p("vol_b.zarr"), p("piv.zarr"), "", p("parts_a.zarr"), p("parts_b.zarr"))
after = compiled()
new = {k: after[k] - rendered.get(k, 0) for k in after if after[k] > rendered.get(k, 0)}
print("JSON" + json.dumps({"warm": warm, "new": new, "kernels": sum(1 for v in before.values() if v)}))
"""


def test_a_warmed_case_compiles_no_kernel_its_stages_need(tmp_path):
    """In a fresh interpreter, :func:`warm_kernels` on the case, then its stages through their zarr stores as the
    Snakefile's jobs run them: once the images are rendered (the renderers' kernels are the render jobs' own), the
    calibration, both frames' registration, refocusing and IPR fit and the paired PIV add no type signature to any
    numba kernel. So the jobs that wait for the warm job load every kernel from the cache instead of compiling it
    again, side by side."""
    cfg = _ipr_config()
    r = subprocess.run(
        [sys.executable, "-c", _CHILD, json.dumps(cfg, default=str), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("JSON")]
    assert r.returncode == 0 and lines, r.stderr[-4000:]
    res = json.loads(lines[0][4:])
    assert res["warm"]["error"] is None, res["warm"]["error"]
    assert {"reconstruct_a", "reconstruct_b", "piv", "paired"} <= set(res["warm"]["seconds"])
    assert res["kernels"] >= 10  # IPR's, MART's and the PIV's kernels were compiled or loaded
    assert res["new"] == {}, f"kernels compiled after the warm-up: {res['new']}"


def test_a_failing_warm_up_reports_and_does_not_raise():
    cfg = _ipr_config()
    cc = case_config(cfg, next(iter(Sweep(cfg).cases())))
    cc["reconstruct"]["method"] = "no such method"
    from lfstudy.study.warm import warm_kernels

    r = warm_kernels(cc)
    assert "refocus_a" in r["seconds"] and "reconstruct_a" not in r["seconds"]
    assert "no such method" in r["error"]
