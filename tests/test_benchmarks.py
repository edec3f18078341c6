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
