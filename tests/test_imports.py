"""The import graph runs one way (issue 26): read from every module's imports, module- and function-level.

Function-level imports load lazily but still close a circle at run time, so they
count. The layers checked: the config plumbing (``lfstudy.config``) imports no
other lfstudy module; the reconstruction methods do not import the study, the
workflow or the processing of recordings; no two modules import each other
(directly or round a longer loop); a stage does not load the camera model
through the package face.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "lfstudy"


def _module_name(path: Path, pkg_root: Path) -> str:
    parts = path.relative_to(pkg_root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules(root: Path = PKG) -> dict[str, Path]:
    return {_module_name(p, root): p for p in sorted(root.rglob("*.py"))}


def imports_of(path: Path, modules: dict[str, Path], pkg_root: Path = PKG) -> set[str]:
    """The lfstudy modules ``path`` imports anywhere in its body (``from a import b`` counts
    as ``a.b`` where ``b`` is a module, else as ``a``)."""
    this = _module_name(path, pkg_root)
    pkg = this if path.name == "__init__.py" else this.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from .x import y
                anchor = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.add(sub if sub in modules else base)
    return {m for m in out if m in modules and m != this}


def import_graph(root: Path = PKG) -> dict[str, set[str]]:
    """``{module: lfstudy modules it imports}`` for every module under ``root``."""
    modules = _modules(root)
    return {name: imports_of(path, modules, root) for name, path in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_the_config_plumbing_imports_no_other_lfstudy_module(graph):
    assert graph["lfstudy.config"] == set()


def test_reconstruction_does_not_import_the_layers_above_it(graph):
    above = ("lfstudy.study", "lfstudy.workflow", "lfstudy.process", "lfstudy.cli", "lfstudy.commands")
    bad = {
        m: sorted(i for i in imps if i.startswith(above))
        for m, imps in graph.items()
        if m.startswith("lfstudy.reconstruct")
    }
    assert not {m: v for m, v in bad.items() if v}


def test_process_report_does_not_import_the_pipeline(graph):
    assert "lfstudy.process.report" in graph["lfstudy.process.pipeline"]  # the pipeline writes the report
    assert "lfstudy.process.pipeline" not in graph["lfstudy.process.report"]


def test_no_import_circles(graph):
    found = circles(graph)
    assert not found, "modules that import each other: " + "; ".join(" <-> ".join(sorted(c)) for c in found)


def test_the_checks_see_function_level_and_relative_imports(tmp_path):
    """The graph reader itself: a circle hidden in a function body is found."""
    pkg = tmp_path / "lfstudy"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "top.py").write_text("def f():\n    from lfstudy.sub import low\n")
    (pkg / "sub" / "low.py").write_text("def g():\n    from .. import top\n")
    g = import_graph(pkg)
    assert g["lfstudy.top"] == {"lfstudy.sub.low"} and g["lfstudy.sub.low"] == {"lfstudy.top"}
    assert circles(g) == [{"lfstudy.top", "lfstudy.sub.low"}]


@pytest.mark.parametrize(
    ("module", "absent"),
    [
        ("lfstudy.piv", "lfstudy.optics"),  # PIV knows no optics
        ("lfstudy.config", "lfstudy.reconstruct"),
        ("lfstudy", "lfstudy.optics"),  # the package face loads no stage
    ],
)
def test_importing_a_stage_does_not_load_another(module, absent):
    code = f"import sys, {module}; print({absent!r} in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "False", f"import {module} loads {absent}"
