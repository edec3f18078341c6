from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lfstudy.optics import PlenopticCamera


@pytest.fixture
def table41_camera() -> PlenopticCamera:
    """The 1-D simulator camera of Table 4.1 (fm = 1.5 mm, M = -1)."""
    return PlenopticCamera(75, 75, 0.0074, 0.125, 0.5, 1.5, -1.0)


@pytest.fixture
def table43_camera() -> PlenopticCamera:
    """The KAI-16000 camera of Table 4.3."""
    return PlenopticCamera(4872, 3248, 0.0074, 0.125, 0.5, 50.0, -1.0)


ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.yaml"


@pytest.fixture(scope="session")
def tiny_study(tmp_path_factory) -> Path:
    """Working directory of the tiny study (tests/data/tiny.yaml) run locally by Snakemake on 2 cores,
    once per session: the workflow tests use it, and the SLURM test compares its cluster run with it.

    Tests that change it must leave it complete (rerun what they delete).
    """
    work = tmp_path_factory.mktemp("study")
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work)]
    r = subprocess.run([*cmd, "--configfile", str(TINY), "--cores", "2"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    return work


def _uses_tiny_study(item) -> bool:
    """The test uses the tiny study: as a fixture, or (the SLURM test) through ``request.getfixturevalue``
    once its cluster run is submitted."""
    return "tiny_study" in getattr(item, "fixturenames", ()) or item.path.name == "test_slurm.py"


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects by marker
def pytest_collection_modifyitems(config, items):
    """A test that uses the tiny study (directly or through a fixture) is `slow`: the first one runs
    the whole Snakemake workflow (minutes on 2 cores). Under pytest-xdist (`-n 2 --dist loadgroup`,
    the README's command) the tests are grouped so that no fixture is built twice."""
    for item in items:
        if _uses_tiny_study(item):
            item.add_marker(pytest.mark.slow)
            # One worker of `pytest -n 2 --dist loadgroup` builds the session's tiny study for all its users.
            item.add_marker(pytest.mark.xdist_group("tiny_study"))
        else:
            # A file's tests stay on one worker, so its module-scoped fixtures are built once.
            item.add_marker(pytest.mark.xdist_group(item.path.name))


@pytest.fixture
def cli_error(capsys):
    """Run the CLI expecting a refusal: exit 2, one 'lfstudy <command>: error: ' line on stderr,
    no traceback. Returns that line."""
    from lfstudy.cli import main

    def run(*argv: str) -> str:
        assert main(list(argv)) == 2
        err = capsys.readouterr().err
        lines = [ln for ln in err.strip().splitlines() if ln.strip()]
        assert len(lines) == 1, err
        assert "Traceback" not in err and lines[0].startswith(f"lfstudy {argv[0]}: error: "), err
        return lines[0]

    return run


# The longest files after the tiny study's group (cold, 2 cores, issue 37's note: test_process 165 s, test_exact_render
# 74 s with the renderer's compile, test_workflow's own 59 s, test_piv 49 s, test_report 38 s): they are handed out
# first, so that the short files even out the two workers at the end (longest first).
_LONG_FILES = ("test_process.py", "test_exact_render.py", "test_workflow.py", "test_piv.py", "test_report.py")


def _suite_order(item) -> tuple[int, int]:
    """(0, 0): the SLURM test, which submits its jobs and makes the tiny study while they queue and poll;
    (1, 0): the other users of the tiny study; (2, k): the k-th of the long files; (3, 0): the rest."""
    if _uses_tiny_study(item):
        return (0 if item.path.name == "test_slurm.py" else 1, 0)
    name = item.path.name
    return (2, _LONG_FILES.index(name)) if name in _LONG_FILES else (3, 0)


class _TinyStudyFirst:
    """The tiny study's group is the longest (the study, then the SLURM run and the sweeps on it): it goes
    first, so that one xdist worker starts it at once and the other files fill the second worker; the long
    files follow, the short ones last. Within the group the SLURM test comes first: its cluster run then
    overlaps the making of the tiny study, instead of following the whole group (measured: 11 min 53 s for
    the suite with it last, on 2 cores)."""

    @pytest.hookimpl(trylast=True)  # after pytest's own reordering by fixture scope
    def pytest_collection_modifyitems(self, items):
        items.sort(key=_suite_order)  # stable: the order within each part is kept


def pytest_configure(config):
    config.pluginmanager.register(_TinyStudyFirst(), "lfstudy-tiny-study-first")
    if config.getoption("dist", "no") != "loadgroup":
        return
    # xdist hands out the groups in the order above, not by their number of tests (its default): the tiny study's
    # group has few tests but is the longest, and came last (measured cold: 521 s on one worker, 364 s on the other).
    config.option.loadscopereorder = False
    # pytest-xdist 3.8 groups by a suffix on the node id, which pytest 9.2 no longer reads (pytest-xdist#1386):
    # `--dist loadgroup` then silently spreads every group over the workers and the tiny study is built twice
    # (2-3 min more on 2 cores). The test extra pins pytest < 9.2; say so where another pytest is installed.
    if not hasattr(config, "workerinput"):
        import xdist

        xdist_version = tuple(int(p) for p in xdist.__version__.split(".")[:2])
        if pytest.version_tuple[:2] >= (9, 2) and xdist_version <= (3, 8):
            raise pytest.UsageError(
                f"pytest {pytest.__version__} with pytest-xdist {xdist.__version__}: --dist loadgroup ignores "
                "xdist_group (pytest-xdist#1386); install the test extra (pip install -e '.[test]': pytest < 9.2)"
            )
