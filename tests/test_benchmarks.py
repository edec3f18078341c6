"""The benchmark scripts still import and parse their options.

The benchmarks are not run by the tests (they take minutes on the full sensor), so nothing else
notices when a refactoring moves a name they import: ``bench_study_thesis.py`` failed with an
ImportError for several commits after ``calib_id`` moved. ``--help`` imports every module a script
needs at its top and builds its option parser, then exits before any work.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(BENCH.glob("bench_*.py"))


ROOT = BENCH.parent
#: Where benchmark scripts are named (their docstrings and the docs quote measured numbers from them).
_NAMING = ("README.md", "Snakefile", "docs", "lfstudy", "benchmarks", "reports", "config", "profiles", "examples")
_TEXT = ("", ".py", ".md", ".rst", ".yaml", ".yml", ".ipynb", ".txt")
_NAMED = re.compile(r"benchmarks/(bench_\w+\.py)")


def _named_benchmarks() -> dict[str, list[str]]:
    """Benchmark script -> the files that name it as ``benchmarks/<script>``."""
    named: dict[str, list[str]] = {}
    for top in _NAMING:
        path = ROOT / top
        files = [path] if path.is_file() else sorted(path.rglob("*"))
        for f in files:
            rel = f.relative_to(ROOT)
            if not f.is_file() or f.suffix not in _TEXT or {"_build", "api", "out", "__pycache__"} & set(rel.parts):
                continue
            for name in _NAMED.findall(f.read_text(errors="replace")):
                named.setdefault(name, []).append(rel.as_posix())
    return named


def test_every_benchmark_is_checked():
    """Every script in benchmarks/ is one of the cases below (a script not named bench_*.py would
    escape them; helpers start with ``_``), and every benchmark the code and the docs name exists."""
    scripts = sorted(p for p in BENCH.rglob("*.py") if not p.name.startswith("_") and "out" not in p.parts)
    assert scripts == SCRIPTS, f"benchmark scripts not named bench_*.py: {sorted(set(scripts) - set(SCRIPTS))}"
    named = _named_benchmarks()
    assert named, "no file names a benchmark script: the search above is broken"
    missing = {name: where for name, where in named.items() if not (BENCH / name).is_file()}
    assert not missing, f"benchmark scripts named but missing: {missing}"


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_imports_and_parses_options(script):
    res = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage:" in res.stdout


_REPRODUCES = re.compile(r"(?m)^Reproduces: (.+?)(?:\n\n|\Z)", re.S)
_CITED = re.compile(r"((?:docs|lfstudy|config)/[\w/.-]+\.(?:md|py|yaml))((?:[^;]*?§ \"[^\"]+\")*)")


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_each_benchmark_says_which_documented_figure_it_reproduces(script):
    """A benchmark is kept for a figure a reader may want to reproduce: its module docstring has a
    ``Reproduces:`` paragraph citing the files (and the sections of the doc pages) that hold the figure,
    and each cited file names the script (so the figure there says where it came from)."""
    import ast

    doc = ast.get_docstring(ast.parse(script.read_text())) or ""
    m = _REPRODUCES.search(doc)
    assert m, f"{script.name}: no 'Reproduces:' paragraph in its docstring"
    cited = _CITED.findall(" ".join(m.group(1).split()))
    assert cited, f"{script.name}: 'Reproduces:' cites no file under docs/, lfstudy/ or config/"
    for path, sections in cited:
        f = ROOT / path
        assert f.is_file(), f"{script.name} cites {path}, which does not exist"
        text = f.read_text()
        assert re.search(rf"\b{re.escape(script.stem)}\b(?!_)", text), f"{path} does not name {script.name}"
        headings = {h.strip() for h in re.findall(r"(?m)^#+ (.+)$", text)}
        for title in re.findall(r'§ "([^"]+)"', sections):
            assert title in headings, f"{script.name} cites {path} § {title!r}, not a heading there"


# Stand-ins for two stage functions (bench_uncertainty reads the output argument by the function's name:
# run_particles writes args[1], run_displace args[2]); module level, so the pool's workers can unpickle them.
def run_particles(sc: dict, out: Path) -> None:
    import time

    time.sleep(sc.get("sleep", 0.0))  # a slow first stage: a dependent started early would find no input
    out.write_text(sc["tag"])


def run_displace(sc: dict, src: Path, out: Path) -> None:
    if sc.get("fail"):
        raise ValueError("planted failure")
    out.write_text(src.read_text() + sc["tag"])


def test_bench_uncertainty_schedules_by_inputs_and_runs_on_past_a_failure(tmp_path, monkeypatch, capsys):
    """bench_uncertainty's scheduler: a task starts only once the tasks writing its inputs are done, an
    output already there is kept, and a failing task leaves out its dependents while the others finish."""
    monkeypatch.syspath_prepend(str(BENCH))
    sys.modules.pop("bench_uncertainty", None)
    from bench_uncertainty import _schedule

    p = {k: tmp_path / f"{k}.txt" for k in ("p1", "p2", "p3", "d1", "d2", "d3", "e3")}
    p["p3"].write_text("old")  # an earlier run's output: kept, its task not run again
    waves = [
        [
            ("p1", run_particles, ({"tag": "a", "sleep": 0.5}, p["p1"])),
            ("p2", run_particles, ({"tag": "b"}, p["p2"])),
            ("p3", run_particles, ({"tag": "new"}, p["p3"])),
        ],
        [
            ("d1", run_displace, ({"tag": "1"}, p["p1"], p["d1"])),
            ("d2", run_displace, ({"tag": "2", "fail": True}, p["p2"], p["d2"])),
            ("d3", run_displace, ({"tag": "3"}, p["p3"], p["d3"])),
        ],
        [("e3", run_displace, ({"tag": "x"}, p["d2"], p["e3"]))],  # needs the failed task's output
    ]
    assert _schedule(waves, jobs=2, threads=1) == 2  # d2 failed, e3 left out
    assert p["d1"].read_text() == "a1"  # waited for the slow p1
    assert p["d3"].read_text() == "old3"
    assert not p["d2"].exists() and not p["e3"].exists()
    printed = capsys.readouterr().out
    assert "FAILED d2: ValueError: planted failure" in printed and "left out (an input failed): e3" in printed
    assert "  p3" not in printed  # kept, not rerun


def test_bench_uncertainty_starts_the_ipr_fits_first(tmp_path, monkeypatch):
    """The scheduler's order of ready tasks on a real study's stage configs: IPR fits before MART, the denser
    seeding first; then PIV and errors; then the earlier stages."""
    import yaml

    from lfstudy.study.config import validate_config

    monkeypatch.syspath_prepend(str(BENCH))
    sys.modules.pop("bench_uncertainty", None)
    from bench_uncertainty import _priority, _tasks

    raw = yaml.safe_load((ROOT / "tests" / "data" / "tiny.yaml").read_text())
    raw |= {"depth_calibration": {"enabled": False}}
    raw["sweep"] = {"ppp": [0.001, 0.004], "reconstruct.method": ["mart", "ipr"]}
    waves = _tasks(validate_config(raw), tmp_path)
    tasks = [(w, label, fn, a) for w, wave in enumerate(waves) for label, fn, a in wave]
    order = [t[1] for t in sorted(tasks, key=lambda t: _priority(t[0], t[2], t[3]))]
    recon = [label for label in order if label.startswith("reconstruct")]
    kinds = [("ipr" if "method~ipr" in x else "mart", "0.004" if "ppp~0.004" in x else "0.001") for x in recon]
    assert kinds == [("ipr", "0.004")] * 2 + [("ipr", "0.001")] * 2 + [("mart", "0.004")] * 2 + [("mart", "0.001")] * 2
    assert order[: len(recon)] == recon
    rest = [label.split()[0] for label in order[len(recon) :]]
    n_case = rest.count("piv") + rest.count("errors")
    assert n_case == 8 and set(rest[:n_case]) == {"piv", "errors"}
    assert rest.index("camera") < rest.index("simulate") < rest.index("register") < rest.index("refocus")
