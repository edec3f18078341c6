"""The benchmark scripts still import and parse their options.

The benchmarks are not run by the tests (they take minutes on the full sensor), so nothing else
notices when a refactoring moves a name they import: ``bench_study_thesis.py`` failed with an
ImportError for several commits after ``calib_id`` moved. ``--help`` imports every module a script
needs at its top and builds its option parser, then exits before any work.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(BENCH.glob("bench_*.py"))


def test_every_benchmark_is_checked():
    assert len(SCRIPTS) >= 6, f"benchmark scripts not found under {BENCH}"


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_imports_and_parses_options(script):
    res = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage:" in res.stdout
