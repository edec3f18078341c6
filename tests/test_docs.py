"""The documentation's generated parts cover the code, and no link leaves the repository.

Fast checks of the generators behind the Sphinx build (no build here: `.ci/run` builds the docs
with warnings as errors): every schema key is in the config reference, every public name of
``lfstudy`` and of each stage subpackage is in the API reference, and every link in the README and
the docs pages resolves inside the repository.
"""

from __future__ import annotations

import importlib
import inspect
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS / "_ext"))

import lfstudy_docs  # noqa: E402

from lfstudy.process import load_process_schema  # noqa: E402
from lfstudy.study.config import load_schema  # noqa: E402

STAGES = ("lfstudy.simulate", "lfstudy.lightfield", "lfstudy.reconstruct", "lfstudy.piv", "lfstudy.study")


def _schema_paths(node, prefix=""):
    for key, sub in node.get("properties", {}).items():
        path = f"{prefix}{key}"
        yield path
        yield from _schema_paths(sub, f"{path}.")
        extra = sub.get("additionalProperties")
        if isinstance(extra, dict):
            yield f"{path}.<name>"
            yield from _schema_paths(extra, f"{path}.<name>.")


def test_config_reference_lists_every_schema_key():
    schema = load_schema()
    text = lfstudy_docs.config_reference(schema)
    paths = list(_schema_paths(schema))
    assert len(paths) > 50
    missing = [p for p in paths if f"``{p}``" not in text]
    assert not missing, f"schema keys missing from the config reference: {missing}"
    # defaults and ranges are there, e.g. piv.levels: default 3, 1..6
    row = text[text.index("``piv.levels``") :].split("   * - ")[0]
    assert "``3``" in row and "≥ 1" in row and "≤ 6" in row
    # every reconstruction method's parameters (from the registry) are in the schema it walks
    assert "``reconstruct.mart``" in text


def test_process_config_reference_lists_every_key():
    schema = load_process_schema()
    text = lfstudy_docs.process_config_reference(schema)
    missing = [p for p in _schema_paths(schema) if f"``{p}``" not in text]
    assert not missing, f"recording config keys missing from the reference: {missing}"
    assert "``recording.frames.series``" in text and "the study config's camera section" in text


def test_config_descriptions_name_schema_keys():
    """The docs' descriptions of schema keys name keys that exist (none left behind by a rename)."""
    paths = set(_schema_paths(load_schema())) | set(_schema_paths(load_process_schema()))
    stale = sorted(set(lfstudy_docs.DESCRIPTIONS) - paths)
    assert not stale, f"descriptions of keys no longer in the schema: {stale}"


def test_config_reference_of_a_hand_made_schema():
    schema = {
        "type": "object",
        "required": ["a"],
        "properties": {
            "a": {
                "type": "object",
                "description": "section *a*",
                "properties": {
                    "n": {"type": "integer", "minimum": 1, "maximum": 9, "default": 2},
                    "mode": {"type": "string", "enum": ["x", "y"], "default": "x", "description": "`x` or `y`"},
                    "v": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
                },
            },
            "named": {"type": "object", "additionalProperties": {"type": "object", "properties": {"k": {}}}},
        },
    }
    entries = {e["path"]: e for e in lfstudy_docs.schema_entries(schema)}
    assert set(entries) == {"a", "a.n", "a.mode", "a.v", "named", "named.<name>", "named.<name>.k"}
    assert entries["a"]["required"] == "yes"
    assert entries["a.n"]["default"] == "2" and entries["a.n"]["allowed"] == "≥ 1; ≤ 9"
    assert entries["a.mode"]["allowed"] == 'one of "x", "y"'
    assert entries["a.v"]["type"] == "array of number" and "exactly 3 items" in entries["a.v"]["allowed"]
    text = lfstudy_docs.config_reference(schema)
    assert r"section \*a\*" in text and "``x`` or ``y``" in text


@pytest.mark.slow
@pytest.mark.docs
def test_api_reference_lists_every_public_name():
    pytest.importorskip(
        "sphinx",
        reason="needs the docs extra (pip install -e '.[docs]'): the API pages are generated with Sphinx's "
        "ModuleAnalyzer; CI runs this test in its docs step (pytest -m docs)",
    )
    pages = lfstudy_docs.api_pages()
    text = "\n".join(pages.values())
    found = lfstudy_docs.stage_packages()
    assert set(STAGES) <= set(found), found
    for module in ("lfstudy", *found):
        assert f"{module}.rst" in pages, f"no API page for {module}"
        names = importlib.import_module(module).__all__
        page = pages[f"{module}.rst"]
        missing = [n for n in names if not re.search(rf"(?m)^(   |\.\. auto\w+:: (\S+\.)?)`*{re.escape(n)}\b", page)]
        missing = [n for n in missing if f"``{n}``" not in page]
        assert not missing, f"{module}: public names missing from its API page: {missing}"
    # each stage page names the thesis sections it implements
    for module in STAGES:
        assert "**Thesis (Lynch 2011):**" in pages[f"{module}.rst"]
    assert all(f"   {m}" in pages["index.rst"] for m in found)
    assert text.count(".. autoclass:: PlenopticCamera") == 1  # re-exported twice, documented once


def _documented_objects(module: str, documented: set[int]) -> list[tuple[str, object]]:
    """The objects whose docstrings an API page shows, as :func:`lfstudy_docs.api_page` picks them:
    each public name not documented on an earlier page, and a class's public members."""
    mod = importlib.import_module(module)
    out = []
    for name in lfstudy_docs.public_names(module):
        obj = getattr(mod, name)
        if not (inspect.isclass(obj) or inspect.isroutine(obj)) or id(obj) in documented:
            continue
        documented.add(id(obj))
        out.append((name, obj))
        if inspect.isclass(obj):
            out += [(f"{name}.{m}", v) for m, v in vars(obj).items() if not m.startswith("_") and inspect.isroutine(v)]
    return out


def test_footnotes_are_unique_on_each_api_page():
    """Numbered References (``.. [1]``) of two docstrings on one API page would be duplicate targets,
    an error in the -W docs build: the second such docstring must number on from the first."""
    documented: set[int] = set()
    clashes = []
    for module in lfstudy_docs.api_modules():
        seen: dict[str, str] = {}
        for name, obj in _documented_objects(module, documented):
            for label in set(re.findall(r"(?m)^\s*\.\. \[([^\]]+)\]", inspect.getdoc(obj) or "")):
                if label in seen:
                    clashes.append(f"{module}: [{label}] in {seen[label]} and {name}")
                seen.setdefault(label, name)
    assert not clashes, clashes


def test_generated_references_are_parsed_as_restructuredtext():
    """The directives emit reStructuredText; in a Markdown page MyST would read it as Markdown
    (tables become bullet lists), so they must sit in an eval-rst block."""
    for page in DOCS.rglob("*.md"):
        if "_build" in page.parts:
            continue
        text = page.read_text()
        for m in re.finditer(r"lfstudy-[a-z-]+-reference", text):
            before = text[: m.start()].rstrip()
            assert before.endswith("```{eval-rst}\n.."), f"{page.name}: {m.group(0)} outside an eval-rst block"


def test_escape_bars_keeps_literals():
    lines = ["voxel pl/|M| and ``|x|``", "Example::", "", "    a | b", "back |t|", ">>> x | y"]
    assert lfstudy_docs.escape_bars(lines) == [
        r"voxel pl/\|M\| and ``|x|``",
        "Example::",
        "",
        "    a | b",
        r"back \|t\|",
        ">>> x | y",
    ]


# ------------------------------------------------------------------------------ links

_MD_LINK = re.compile(r"(?<!\!)\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_MD_IMAGE = re.compile(r"!\[[^\]]*\]\(\s*([^)\s]+)")
_HTML_LINK = re.compile(r"""(?:href|src)\s*=\s*["']([^"']+)["']""")
_RST_LINK = re.compile(r"`[^`<]*<([^>`]+)>`__?")
_MD_REF_DEF = re.compile(r"(?m)^\s*\[[^\]]+\]:\s*(\S+)")

#: Where the executed pages put files to be published beside them (conf.py's ``html_extra_path``).
_SITE = "_build/tutorial_site"


def _built_files() -> set[str]:
    """Files the docs build itself puts beside the pages: what the executed pages copy into
    ``_SITE`` (``site / "name"``), e.g. the tutorial's study report and its recording's report."""
    names: set[str] = set()
    for page in sorted(DOCS.rglob("*.md")):
        text = page.read_text()
        if "_build" not in page.relative_to(DOCS).parts and _SITE in text:
            names |= set(re.findall(r'\bsite\s*/\s*"([^"/]+)"', text))
    return names


_BUILT = _built_files()


def test_built_files_are_known():
    assert '"_build" / "tutorial_site"' in (DOCS / "conf.py").read_text()  # published as html_extra_path
    assert {"tutorial-report.html", "tutorial-recording-report.html"} <= _BUILT, _BUILT


def _doc_files():
    files = [ROOT / "README.md"]
    for p in sorted(DOCS.rglob("*")):
        rel = p.relative_to(DOCS)
        if rel.parts[0] in ("_build", "api") or p.suffix not in (".md", ".rst"):
            continue
        files.append(p)
    return files


def _links(text):
    for rx in (_MD_LINK, _MD_IMAGE, _HTML_LINK, _RST_LINK, _MD_REF_DEF):
        for m in rx.finditer(text):
            yield m.group(1)


def _strip_code(text):
    """Drop fenced code blocks and inline code: commands and paths there are not links."""
    text = re.sub(r"(?ms)^(```|~~~).*?^\1", "", text)
    return re.sub(r"``[^`\n]*``|(?<![`<])`[^`<\n]*`(?![_`])", "", text)


def _bad_links(f: Path, text: str) -> list[str]:
    """Links of file ``f`` that leave the repository (a URL scheme, an absolute path, a relative path
    resolving outside ROOT) or name no file."""
    bad = []
    for target in _links(_strip_code(text)):
        if target.startswith("#"):
            continue
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):  # http:, https:, file:, mailto: ...
            bad.append(f"{target} (outside the repository)")
            continue
        path = target.split("#")[0]
        if path in _BUILT:
            continue
        dest = (f.parent / path).resolve()
        if path.startswith("/") or not dest.is_relative_to(ROOT):
            bad.append(f"{target} (outside the repository)")
        elif dest.parent == (DOCS / "api").resolve():
            continue  # the API pages are generated at build time (checked by the build)
        elif not any(Path(str(dest) + ext).exists() for ext in ("", ".md", ".rst")):
            bad.append(f"{target} (no such file)")
    return bad


def test_no_link_points_outside_the_repository():
    files = _doc_files()
    assert {"conventions.md", "architecture.md", "tutorial.md", "README.md"} <= {f.name for f in files}
    bad = [f"{f.relative_to(ROOT)}: {b}" for f in files for b in _bad_links(f, f.read_text())]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(
    "text",
    [
        "see [the notes](../shared/DESIGN.md)",
        "see [a site](https://example.org/x)",
        "see [passwords](/etc/passwd)",
        'see <a href="../../outside.html">this</a>',
        "see `the notes <../shared/DESIGN.md>`_",
        "[ref]: ../shared/DESIGN.md",
        "see [missing](docs/nothing-here.md)",
    ],
)
def test_link_check_catches_escaping_links(text):
    assert _bad_links(ROOT / "README.md", text)


def test_link_check_passes_good_links():
    text = "[a](docs/conventions.md#units) [b](#top) `[not a link](../x)` and\n```\n[c](../../x)\n```\n"
    assert _bad_links(ROOT / "README.md", text) == []


def test_readme_links_the_docs_not_the_design_notes():
    readme = (ROOT / "README.md").read_text()
    assert "../shared" not in readme
    assert "docs/architecture.md" in readme and "docs/tutorial.md" in readme
