"""The Examples sections of the public API run and print what they show.

Only the public faces are searched (``lfstudy`` and every module or subpackage of it that declares
``__all__``, the names in it and their methods), not every module: ``--doctest-modules`` would
import each implementation module on its own and run examples of private helpers that are not part
of the documented API. Each docstring with examples is one test, so a failure names it.
"""

from __future__ import annotations

import doctest
import importlib
import inspect
import pkgutil

import pytest

import lfstudy

#: The face functions that must carry an Examples section (issue: one per pipeline face).
REQUIRED = ("lfstudy.simulate.render", "lfstudy.piv.widim", "lfstudy.reconstruct.reconstruct", "lfstudy.io.open_study")


def _public_modules() -> list[str]:
    names = ["lfstudy"]
    for info in pkgutil.iter_modules(lfstudy.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"lfstudy.{info.name}")
        if hasattr(mod, "__all__"):
            names.append(mod.__name__)
    return names


def _examples() -> dict[str, doctest.DocTest]:
    """``{qualified name: DocTest}`` of every public object (and its methods) whose docstring has
    examples, each object once (the first module that exports it names it)."""
    finder = doctest.DocTestFinder(recurse=False)
    found: dict[str, doctest.DocTest] = {}
    seen: set[int] = set()
    for modname in _public_modules():
        mod = importlib.import_module(modname)
        for name in mod.__all__:
            obj = getattr(mod, name)
            members = [(name, obj)]
            if inspect.isclass(obj):
                members += [(f"{name}.{m}", v) for m, v in vars(obj).items() if not m.startswith("_")]
            for qual, o in members:
                if not (inspect.isroutine(o) or inspect.isclass(o)) or id(o) in seen:
                    continue
                seen.add(id(o))
                for test in finder.find(o, f"{modname}.{qual}", globs={}):
                    if test.examples:
                        found[test.name] = test
    return found


EXAMPLES = _examples()


def _defined_at(qualname: str) -> object:
    module, name = qualname.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("name", REQUIRED)
def test_face_functions_have_examples(name):
    doc = inspect.getdoc(_defined_at(name)) or ""
    assert "Examples\n--------" in doc, f"{name} has no Examples section"
    assert ">>> " in doc.split("Examples\n--------", 1)[1], f"{name}'s Examples section has no example"
    obj = _defined_at(name)
    assert any(_defined_at(n) is obj for n in EXAMPLES), f"{name}'s examples are not collected"


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_docstring_examples(name):
    test = EXAMPLES[name]
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    out: list[str] = []
    runner.run(test, out=out.append)
    result = runner.summarize(verbose=False)
    assert result.attempted == len(test.examples)
    assert result.failed == 0, "".join(out)
