"""Sphinx extension: the parts of the docs that are generated from the code, so they cannot drift.

* :func:`config_reference` walks the study config schema (``lfstudy/schema.yaml`` plus every
  reconstruction method's parameters, :func:`lfstudy.study.config.load_schema`) and writes every key
  with its type, default, allowed values and description; the ``lfstudy-config-reference``
  directive puts it into a page.
* :func:`api_pages` writes one API page per pipeline stage: the package's docstring, a summary
  table of its ``__all__`` and the documentation of each name (autodoc + autosummary). Stage
  subpackages are discovered, so a new one gets a page without an edit here.
* :func:`cli_reference` prints every ``lfstudy`` sub-command's ``--help`` (the
  ``lfstudy-cli-reference`` directive).

The generator functions are plain Python, so ``tests/test_docs.py`` checks them without a
Sphinx build.
"""

from __future__ import annotations

import importlib
import inspect
import json
import pkgutil
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parents[1]
API_DIR = DOCS / "api"

# --------------------------------------------------------------------------- config reference

_RANGE_KEYS = (
    ("minimum", "≥"),
    ("exclusiveMinimum", ">"),
    ("maximum", "≤"),
    ("exclusiveMaximum", "<"),
)


def _ref_name(node: Mapping[str, Any]) -> str:
    """``schema.yaml#/properties/camera`` -> ``camera`` (a section taken from the study schema)."""
    return str(node["$ref"]).rsplit("/", 1)[-1]


def _type_of(node: Mapping[str, Any]) -> str:
    if "$ref" in node:
        return f"the study config's {_ref_name(node)} section"
    if "oneOf" in node or "anyOf" in node:
        return " or ".join(_type_of(n) for n in node.get("oneOf", node.get("anyOf", [])))
    t = node.get("type")
    if t is None:
        return "enum" if "enum" in node else "any"
    types = [t] if isinstance(t, str) else list(t)
    out = []
    for ty in types:
        if ty == "array" and isinstance(node.get("items"), Mapping):
            out.append(f"array of {_type_of(node['items'])}")
        else:
            out.append(str(ty))
    return " or ".join(out)


def _allowed(node: Mapping[str, Any]) -> str:
    """Allowed values of one schema node: enum, range, pattern, lengths (recursing into oneOf/items)."""
    parts: list[str] = []
    if "enum" in node:
        parts.append("one of " + ", ".join(json.dumps(v) for v in node["enum"]))
    for key, sym in _RANGE_KEYS:
        if key in node:
            parts.append(f"{sym} {node[key]:g}" if isinstance(node[key], (int, float)) else f"{sym} {node[key]}")
    if node.get("minLength"):
        parts.append(f"at least {node['minLength']} character{'s' if node['minLength'] != 1 else ''}")
    if "pattern" in node:
        parts.append(f"matches {node['pattern']}")
    if "minItems" in node or "maxItems" in node:
        lo, hi = node.get("minItems"), node.get("maxItems")
        if lo is not None and lo == hi:
            parts.append(f"exactly {lo} items")
        else:
            if lo is not None:
                parts.append(f"at least {lo} item{'s' if lo != 1 else ''}")
            if hi is not None:
                parts.append(f"at most {hi} items")
    items = node.get("items")
    if isinstance(items, Mapping):
        sub = _allowed(items)
        if sub:
            parts.append(f"each item {sub}")
    for alt in node.get("oneOf", node.get("anyOf", [])):
        sub = _allowed(alt)
        if sub:
            parts.append(f"({_type_of(alt)}) {sub}")
    return "; ".join(parts)


#: Descriptions of the schema keys that carry none in ``lfstudy/schema.yaml`` (a description
#: there wins). ``tests/test_docs.py`` fails on an entry whose key is no longer in the schema.
DESCRIPTIONS: dict[str, str] = {
    "seed": "study seed; every random stream (particles, rays, pinhole) is derived from it and the "
    "case's settings, so a rerun reproduces every store",
    "camera": "the plenoptic camera (thesis sec. 4.1–4.3, Table 4.3)",
    "camera.sensor": "the image sensor",
    "camera.sensor.n_pixels_x": "sensor pixels per row (columns)",
    "camera.sensor.n_pixels_y": "sensor pixel rows",
    "camera.sensor.pixel_pitch": "square pixel pitch pp [mm] (Table 4.3: 0.0074)",
    "camera.lenslet": "the lenslet (microlens) array in front of the sensor",
    "camera.lenslet.pitch": "square lenslet pitch pl [mm]; at least two pixels (Table 4.3: 0.125)",
    "camera.lenslet.focal_length": "lenslet focal length fl [mm]; the sensor sits fl behind the array. "
    "Give this or `fnumber`",
    "camera.lenslet.fnumber": "lenslet f-number: fl = fnumber × pitch, which keeps it fixed when the pitch "
    "is swept. Give this or `focal_length`",
    "camera.lenslet.offset_x": "shift of the lenslet grid from the centred position in x [mm], at most "
    "one pitch (calibration must find it)",
    "camera.lenslet.offset_y": "shift of the lenslet grid from the centred position in y [mm], at most one pitch",
    "camera.lenslet.rotation": "rotation of the lenslet grid about the optical axis [rad], at most ±10°",
    "camera.main_lens": "the main (imaging) lens",
    "camera.main_lens.focal_length": "main-lens focal length fm [mm] (Table 4.3: 50)",
    "camera.main_lens.fnumber": "main-lens f-number: matched = eq. 4.8 rounded up to a standard stop "
    "(sec. 4.3.1), so lenslet images just touch; a number is used as given and may over- or under-fill "
    "the lenslet images",
    "camera.main_lens.min_fnumber": "smallest f-number the lens reaches; a matched or given f-number "
    "below it is refused",
    "camera.main_lens.max_fnumber": "largest f-number the lens reaches",
    "camera.magnification": "lateral magnification M at the focal plane, negative (a real, inverted "
    "image; eq. 4.5); sets si and so (eqs 4.6–4.7)",
    "camera.wavelength": "illumination wavelength λ [mm] (532 nm = 0.000532), for the diffraction spots "
    "(eqs 4.20–4.25)",
    "camera.particle_diameter": "physical particle diameter dp [mm]",
    "particles": "the simulated seeding (sec. 4.3.2): uniform random positions in a box centred on the focal plane",
    "particles.ppp": "seeding density in particles per sensor pixel (sec. 7.1: 0.001 ppp on the Table 4.3 "
    "sensor is 15,824 particles)",
    "particles.count": "an explicit particle count instead of ppp (null = use ppp); cannot be combined with "
    "a ppp sweep",
    "particles.x_span": "x extent of the particle box, centred on the optical axis [mm]; null = the field of view",
    "particles.y_span": "y extent of the particle box [mm]; null = the field of view",
    "particles.z_span": "depth extent of the particle box, centred on the focal plane [mm] (thesis: 0–7)",
    "particles.intensity": "bounds [imin, imax] of each particle's uniform random intensity coefficient",
    "raytrace": "raw-image rendering: the exact expected image (default) or Monte-Carlo rays (sec. 4.1–4.3)",
    "raytrace.rays_per_particle": "rays traced per particle from the on-axis focal point; others get "
    "more or fewer by the solid angle of the aperture (eq. 4.14)",
    "raytrace.diffraction": "blur rays by the diffraction spots at the lenslet and sensor planes (sec. 4.2.3)",
    "raytrace.max_image_bytes": "refuse a ray trace whose image buffers would exceed this many bytes",
    "pinhole": "the calibration image (sec. 5.1): a dense field of points imaged with the main lens "
    "stopped down, so each lenslet shows a small spot at its centre",
    "pinhole.fnumber": "main-lens f-number of the pinhole image",
    "pinhole.count": "points of the pinhole field",
    "pinhole.rays_per_point": "rays traced per point",
    "flows.<name>": "a flow case, named by its key (e.g. uniform_x, hill); the Flows page lists each kind's "
    "own parameters (types, defaults, ranges) and formulas",
    "flows.<name>.dt": "time between the two exposures; particles are advected over dt",
    "flows.<name>.n_steps": "fourth-order Runge–Kutta steps over dt",
    "refocus": "the refocus planes (eqs 5.16–5.20, Table 5.1) and the focal stack (sec. 5.2, 6.2)",
    "refocus.n_planes": "number of refocus planes of the marching; null = one per pixel under a lenslet, "
    "symmetric about the focal plane",
    "refocus.depth_scale": "widen (> 1) or narrow (< 1) the depth the marching covers, and so the "
    "reconstruction grid's depth (sec. 7.2: 1.5 with 32 planes)",
    "refocus.cubic": "supersample (sec. 5.4): as many planes as make the mean plane spacing equal the "
    "in-plane voxel size (overrides n_planes)",
    "refocus.resize": "resize every plane to constant magnification (sec. 6.2), undoing the main lens' "
    "inversion; false = the thesis' raw render on nominal coordinates",
    "piv": "3-D PIV by WIDIM (ch. 6, App. D)",
    "piv.spacing": "first-level window spacing (z, y, x) in voxels (8, 16, 16 with the default window: 50 % overlap)",
    "piv.levels": "grid levels: level Rf = 1..levels uses the window and spacing divided by Rf (eqs 6.5–6.8)",
    "piv.mode": "deform: symmetric B-spline deformation of both volumes by the predictor (removes the "
    "integer offset's peak locking); offset: the thesis' discrete window offset (App. D)",
    "sweep.magnification": "values of camera.magnification",
    "sweep.fnumber": "values of camera.main_lens.fnumber (matched or a number)",
    "sweep.lenslet_pitch": "values of camera.lenslet.pitch [mm]",
    "sweep.ppp": "values of particles.ppp (particles per sensor pixel)",
    "sweep.flow": "names of flow cases from the flows section",
    # lfstudy/process_schema.yaml (lfstudy process)
    "recording": "the recorded images and how to read them",
    "recording.calibration": "the calibration image of the recording's camera (sec. 5.1)",
    "sweep.<name>": "values of any other setting, named by its dotted path (piv.window, reconstruct.method, ...)",
}


def _description(node: Mapping[str, Any], path: str) -> str:
    if "$ref" in node:
        return f"the same keys, defaults and ranges as `{_ref_name(node)}` of a study config"
    text = node.get("description") or node.get("title") or DESCRIPTIONS.get(path, "")
    return " ".join(str(text).split())


def schema_entries(schema: Mapping[str, Any], prefix: str = "") -> Iterator[dict[str, str]]:
    """Every key of a JSON schema as a flat record, depth first in schema order.

    Each record has ``path`` (dotted; ``<name>`` stands for a free key such as a flow's name),
    ``type``, ``default``, ``required``, ``allowed`` and ``description``.
    """
    required = set(schema.get("required", []))
    for key, node in schema.get("properties", {}).items():
        path = f"{prefix}{key}"
        yield {
            "path": path,
            "type": _type_of(node),
            "default": json.dumps(node["default"]) if "default" in node else "",
            "required": "yes" if key in required else "",
            "allowed": _allowed(node),
            "description": _description(node, path),
        }
        if node.get("properties"):
            yield from schema_entries(node, f"{path}.")
        extra = node.get("additionalProperties")
        if isinstance(extra, Mapping):
            name = f"{path}.<name>"
            yield {
                "path": name,
                "type": _type_of(extra),
                "default": "",
                "required": "",
                "allowed": _allowed(extra),
                "description": _description(extra, name),
            }
            if extra.get("properties"):
                yield from schema_entries(extra, f"{name}.")


def _rst_text(text: str) -> str:
    """Plain text safe inside reStructuredText; `backticked` words become inline literals."""
    out = []
    for i, chunk in enumerate(re.split(r"`([^`]+)`", text)):
        if i % 2:
            out.append(f"``{chunk}``")
        else:
            out.append(re.sub(r"([\\*`|_\[\]<>])", r"\\\1", chunk))
    return "".join(out)


def _literal(text: str) -> str:
    return f"``{text}``" if text else ""


def config_reference(schema: Mapping[str, Any] | None = None, top_title: str = "Top-level settings") -> str:
    """The config reference as reStructuredText: one table per top-level section."""
    if schema is None:
        from lfstudy.study.config import load_schema

        schema = load_schema()
    top = schema.get("properties", {})
    sections: dict[str, list[dict[str, str]]] = {}
    for e in schema_entries(schema):
        key = e["path"].split(".")[0]
        node = top.get(key, {})
        is_section = bool(node.get("properties") or isinstance(node.get("additionalProperties"), Mapping))
        sections.setdefault(key if is_section else "", []).append(e)
    if "" in sections:  # top-level settings first
        sections = {"": sections.pop(""), **sections}
    lines: list[str] = []
    for section, rows in sections.items():
        node = top.get(section, {})
        title = f"``{section}``" if section else top_title
        lines += [title, "-" * len(title), ""]
        desc = _description(node, section) if section else ""
        if desc:
            lines += [_rst_text(desc), ""]
        if section in set(schema.get("required", [])):
            lines += ["This section is required.", ""]
        lines += [
            ".. list-table::",
            "   :header-rows: 1",
            "   :widths: 22 14 12 22 30",
            "   :class: config-reference",
            "",
            "   * - key",
            "     - type",
            "     - default",
            "     - allowed",
            "     - description",
        ]
        for r in rows:
            req = " (required)" if r["required"] else ""
            lines += [
                f"   * - ``{r['path']}``{req}",
                f"     - {_rst_text(r['type'])}",
                f"     - {_literal(r['default'])}",
                f"     - {_literal(r['allowed'])}",
                f"     - {_rst_text(r['description'])}",
            ]
        lines.append("")
    return "\n".join(lines)


def process_config_reference(schema: Mapping[str, Any] | None = None) -> str:
    """The reference of a recording config (``lfstudy process``, ``lfstudy/process_schema.yaml``)."""
    if schema is None:
        from lfstudy.process import load_process_schema

        schema = load_process_schema()
    return config_reference(schema, top_title="Top-level settings of a recording config")


# --------------------------------------------------------------------------- API pages

#: Known pages: module -> (title, thesis sections it implements, one line on the stage).
#: Order is the pipeline's. Stage subpackages not listed here are found and appended.
STAGES: dict[str, tuple[str, str, str]] = {
    "lfstudy": (
        "Entry points",
        "ch. 4–7 (the camera model of ch. 4–5; the study of ch. 7)",
        "The names most scripts need, importable from ``lfstudy`` itself.",
    ),
    "lfstudy.optics": (
        "Camera optics",
        "sec. 4.1–4.3 (eqs 4.5–4.28), sec. 5.3 (eqs 5.16–5.20, Table 5.1)",
        "The plenoptic camera model: thin-lens layout, lenslet grid, diffraction, depth of field "
        "and the refocus planes.",
    ),
    "lfstudy.simulate": (
        "Simulation",
        "ch. 4: sec. 4.1–4.4, App. A",
        "Seeded particle fields, known flows and the plenoptic image of a particle field.",
    ),
    "lfstudy.lightfield": (
        "Light field",
        "sec. 5.1–5.4, 6.2",
        "Raw image → lenslet calibration → 4-D light field → focal stack.",
    ),
    "lfstudy.reconstruct": (
        "Reconstruction",
        "sec. 5.5–5.6",
        "The reconstruction grid and the reconstruction methods, found by name.",
    ),
    "lfstudy.piv": (
        "PIV",
        "ch. 6, App. D",
        "WIDIM: multi-pass, multi-grid cross-correlation of volumes (or images).",
    ),
    "lfstudy.study": (
        "Study",
        "ch. 7",
        "Errors against the known flow, the sweep table, the study Dataset and the report.",
    ),
    "lfstudy.study.designs": (
        "Designs",
        "ch. 7 (sec. 7.1–7.4 compared in mm)",
        "The study's answer: designs in physical units, the Pareto front, the recommendation.",
    ),
    "lfstudy.study.tolerance": (
        "Tolerances",
        "— (issue 29: imperfections the processing does not know, swept as settings)",
        "Which tolerance matters: the error against each swept imperfection per design, and each design's "
        "worst case over them.",
    ),
    "lfstudy.study.replicates": (
        "Replicates",
        "— (issues 27 and 29: the study seed swept, every metric a mean over the seeds ± its spread)",
        "A study over several seeds: each design's mean and spread, paired differences between designs or "
        "tolerance levels, and what is within noise.",
    ),
    "lfstudy.process": (
        "Recorded images",
        "sec. 5.1–5.6 and ch. 6 applied to recordings (calibration, light field, refocus, "
        "reconstruction, PIV; no known flow)",
        "Processing a pair or a time series of recorded plenoptic images (``lfstudy process``).",
    ),
    "lfstudy.study.config": (
        "Study configuration",
        "— (the parameters of ch. 4–7 as a validated YAML file)",
        "Loading and validating a study config (every swept case), expanding the sweep, each case's "
        "and each stage's config.",
    ),
    "lfstudy.config": (
        "Configuration plumbing",
        "— (no science: the error, YAML reading and schema validation every stage shares)",
        "The bottom layer of the configs: it imports no other lfstudy module.",
    ),
    "lfstudy.io": (
        "Input and output",
        "— (no science: stores, images and provenance)",
        "Atomic zarr/TIFF writing, lazy reading, the study as one DataTree.",
    ),
    "lfstudy.export": (
        "Export",
        "— (ParaView and Fiji files of the results of ch. 5–6)",
        "PIV results and volumes to VTK rectilinear grids and ImageJ hyperstacks.",
    ),
}

#: Modules after which discovered stage subpackages are placed (before the support modules).
_BEFORE_SUPPORT = "lfstudy.study.config"


def stage_packages() -> list[str]:
    """The subpackages of ``lfstudy`` that declare ``__all__`` (the pipeline stages), discovered."""
    import lfstudy

    out = []
    for info in pkgutil.iter_modules(lfstudy.__path__):
        if info.ispkg and not info.name.startswith("_"):
            mod = importlib.import_module(f"lfstudy.{info.name}")
            if hasattr(mod, "__all__"):
                out.append(mod.__name__)
    return out


def api_modules() -> list[str]:
    """Every module with an API page, in page order."""
    known = list(STAGES)
    extra = [m for m in stage_packages() if m not in STAGES and m != "lfstudy.commands"]
    i = known.index(_BEFORE_SUPPORT)
    return known[:i] + extra + known[i:]


def _first_line(doc: str | None) -> str:
    return (doc or "").strip().split("\n\n")[0].replace("\n", " ")


def _defining_module(package: str, name: str, obj: Any) -> str:
    """Where a re-exported constant is defined (so its ``#:`` comment is found), else ``package``."""
    from sphinx.pycode import ModuleAnalyzer

    candidates = [package]
    mod = importlib.import_module(package)
    if hasattr(mod, "__path__"):
        candidates += [f"{package}.{i.name}" for i in pkgutil.iter_modules(mod.__path__)]
    for modname in candidates:
        try:
            m = importlib.import_module(modname)
            if getattr(m, name, None) is not obj:
                continue
            if ("", name) in ModuleAnalyzer.for_module(modname).find_attr_docs():
                return modname
        except Exception:  # a module that cannot be analysed: fall back to the package
            continue
    return package


def _kind(obj: Any) -> str:
    if inspect.isclass(obj):
        return "exception" if issubclass(obj, BaseException) else "class"
    if inspect.isfunction(obj) or inspect.isbuiltin(obj) or inspect.ismethod(obj):
        return "function"
    return "data"


def public_names(module: str) -> list[str]:
    """A module's ``__all__``."""
    return list(importlib.import_module(module).__all__)


def api_page(module: str, documented: dict[int, str] | None = None) -> str:
    """The reStructuredText of one API page. ``documented`` maps ``id(obj)`` to where it is
    already documented (filled in here), so an object re-exported twice is documented once."""
    documented = {} if documented is None else documented
    mod = importlib.import_module(module)
    title, thesis, blurb = STAGES.get(module, (_first_line(mod.__doc__).split(":")[0].strip(" ."), "", ""))
    head = f"{title}: ``{module}``"
    lines = [head, "=" * len(head), ""]
    if thesis:
        lines += [f"**Thesis (Lynch 2011):** {thesis}.", ""]
    if blurb:
        lines += [blurb, ""]
    lines += [f".. automodule:: {module}", "   :no-members:", "   :no-index:", "", f".. currentmodule:: {module}", ""]
    names = public_names(module)
    own, elsewhere = [], []
    for name in names:
        obj = getattr(mod, name)
        key = id(obj)
        hashable_singleton = isinstance(obj, (int, float, str, bool, type(None))) and not inspect.isclass(obj)
        if not hashable_singleton and key in documented:
            elsewhere.append((name, documented[key]))
        else:
            own.append((name, obj))
            if not hashable_singleton:
                documented[key] = f"{module}.{name}"
    if own:
        lines += [".. autosummary::", "   :nosignatures:", ""]
        lines += [f"   {name}" for name, _ in own]
        lines.append("")
    if elsewhere:
        lines += ["Also exported here (documented on another page):", ""]
        lines += [f"* ``{name}``: :py:obj:`{target}`" for name, target in elsewhere]
        lines.append("")
    for name, obj in own:
        kind = _kind(obj)
        if kind == "class":
            lines += [f".. autoclass:: {name}", "   :members:", ""]
        elif kind == "exception":
            lines += [f".. autoexception:: {name}", ""]
        elif kind == "function":
            lines += [f".. autofunction:: {name}", ""]
        else:
            where = _defining_module(module, name, obj)
            lines += [f".. autodata:: {where}.{name}", "   :no-value:", ""]
            if where != module:
                lines += [f"   Exported as ``{module}.{name}``.", ""]
    return "\n".join(lines)


def api_pages() -> dict[str, str]:
    """``{file name: reStructuredText}`` of the API reference: an index and one page per module."""
    documented: dict[int, str] = {}
    pages: dict[str, str] = {}
    toc = []
    for module in api_modules():
        fname = f"{module}.rst"
        pages[fname] = api_page(module, documented)
        toc.append(f"   {module}")
    head = "API reference"
    pages["index.rst"] = "\n".join(
        [
            head,
            "=" * len(head),
            "",
            "The public functions and classes, one page per pipeline stage in the order the data flows",
            "(camera → simulation → light field → reconstruction → PIV → study), then the",
            "configuration, I/O and export modules. Each stage is a pure function over NumPy/xarray",
            "objects; import it from its stage package (``from lfstudy.piv import widim``): the",
            "modules behind a package may move. Each page names the thesis sections it implements;",
            "the docstrings cite equations and figures. This reference is generated from each",
            "package's ``__all__`` when the docs are built.",
            "",
            ".. toctree::",
            "   :maxdepth: 1",
            "",
            *toc,
            "",
        ]
    )
    return pages


def write_api_pages(directory: Path = API_DIR) -> list[Path]:
    """Write :func:`api_pages` into ``directory`` (only files whose text changed, so Sphinx's
    incremental build rereads only those); remove stale generated pages."""
    directory.mkdir(parents=True, exist_ok=True)
    pages = api_pages()
    written = []
    for old in directory.glob("*.rst"):
        if old.name not in pages:
            old.unlink()
    for name, text in pages.items():
        p = directory / name
        if not p.exists() or p.read_text() != text:
            p.write_text(text)
        written.append(p)
    return written


# --------------------------------------------------------------------------- CLI reference


def cli_reference() -> str:
    """Every ``lfstudy`` sub-command's help as reStructuredText (one section each)."""
    import argparse

    from lfstudy.cli import build_parser

    parser = build_parser()
    lines: list[str] = []
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sorted(sub.choices.items()):
        p.prog = f"lfstudy {name}"
        title = f"``lfstudy {name}``"
        lines += [title, "-" * len(title), "", ".. code-block:: text", ""]
        lines += [f"   {ln}" if ln.strip() else "" for ln in p.format_help().splitlines()]
        lines.append("")
    return "\n".join(lines)


# --------------------------------------------------------------------------- docstrings

_LITERAL = re.compile(r"(``.+?``)")


def escape_bars(lines: list[str]) -> list[str]:
    """Docstrings write absolute values as plain text (``pl/|M|``, ``|error|``); reStructuredText
    would read ``|M|`` as a substitution. Escape every ``|`` outside inline literals, literal
    blocks (after ``::``) and doctest lines."""
    out: list[str] = []
    block_indent: int | None = None  # indentation of the line that opened a literal block
    for line in lines:
        indent = len(line) - len(line.lstrip())
        if block_indent is not None and line.strip() and indent <= block_indent:
            block_indent = None
        if block_indent is not None or line.lstrip().startswith((">>>", "... ")):
            out.append(line)
        else:
            parts = _LITERAL.split(line)
            out.append("".join(p if i % 2 else p.replace("|", r"\|") for i, p in enumerate(parts)))
        if line.rstrip().endswith("::") and block_indent is None:
            block_indent = indent
    return out


def _process_docstring(app, what, name, obj, options, lines):  # pragma: no cover - Sphinx event
    # A constant without a ``#:`` comment would show its type's docstring (dict, tuple ...).
    if what in ("data", "attribute") and obj is not None and not inspect.isclass(obj):
        tdoc = inspect.getdoc(type(obj)) or ""
        if tdoc and "\n".join(lines).strip() == tdoc.strip():
            lines[:] = []
            return
    lines[:] = escape_bars(lines)


# --------------------------------------------------------------------------- Sphinx glue


def setup(app):  # pragma: no cover - exercised by the docs build
    from docutils import nodes
    from docutils.statemachine import StringList
    from sphinx.util.docutils import SphinxDirective
    from sphinx.util.nodes import nested_parse_with_titles

    class _Generated(SphinxDirective):
        has_content = False
        generator: Any = None

        def run(self):
            import lfstudy

            self.env.note_dependency(str(Path(lfstudy.__file__).parent / "schema.yaml"))
            node = nodes.Element()
            text = type(self).generator()
            nested_parse_with_titles(self.state, StringList(text.splitlines(), source="(generated)"), node)
            return node.children

    class ConfigReference(_Generated):
        generator = staticmethod(config_reference)

    class ProcessConfigReference(_Generated):
        generator = staticmethod(process_config_reference)

    class CliReference(_Generated):
        generator = staticmethod(cli_reference)

    def _write_api(app_):
        write_api_pages(Path(app_.srcdir) / "api")

    app.add_directive("lfstudy-config-reference", ConfigReference)
    app.add_directive("lfstudy-process-config-reference", ProcessConfigReference)
    app.add_directive("lfstudy-cli-reference", CliReference)
    app.connect("builder-inited", _write_api, priority=100)
    app.connect("autodoc-process-docstring", _process_docstring, priority=400)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
