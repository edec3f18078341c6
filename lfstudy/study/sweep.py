"""The sweep table: the settings a study varies, and how cases, stage outputs and the study are named.

One definition drives everything a swept setting touches. A study's ``sweep``
section lists values of the five named parameters (``magnification``,
``fnumber``, ``lenslet_pitch``, ``ppp``, ``flow``) and of any other config
setting by its dotted path (``reconstruct.method``, ``piv.window``,
``raytrace.rays_per_particle``, ``camera.sensor.pixel_pitch`` ...). From the
table come:

- the cases (the Cartesian product of the lists), each validated as a whole
  config;
- case ids and result paths, ``mag~-1/fnum~matched/pitch~0.125/ppp~0.001/
  flow~uniform_x[/reconstruct.method~mart]`` — segments ordered by the
  pipeline stage that first reads them (:data:`SECTION_ORDER`), so the output
  directory of a stage is a prefix of the case id and holds only the settings
  it depends on: cases that differ in a reconstruction setting share their
  ray-traced images, light fields and focal stacks; the first exposure (frame
  a, before the flow moves the particles) is shared by the flows of a design
  (its stages write at the case id without the flow); the calibration is shared
  by the cases whose camera (bar the working f-number) is the same;
- labels and units (the schema's ``title`` and ``units`` annotations), the
  study Dataset's dimensions and the report's axes.

Adding a sweepable setting needs no code change: any leaf of the config
schema can be swept by its path.
"""

from __future__ import annotations

import copy
import itertools
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from lfstudy.config import ConfigError
from lfstudy.study.schema import load_schema

__all__ = [
    "SECTION_ORDER",
    "STAGES",
    "Setting",
    "NAMED",
    "Case",
    "Sweep",
    "format_value",
    "FILES",
    "SHARED",
    "FRAME_STAGES",
    "frame_stage",
    "first_exposure_of",
    "TOLERANCES",
    "is_tolerance",
]

#: Config sections in the order the pipeline first reads them: the order of case-id segments.
SECTION_ORDER: tuple[str, ...] = (
    "seed",
    "camera",
    "particles",
    "flow",
    "flows",
    "illumination",
    "raytrace",
    "sensor",
    "pinhole",
    "refocus",
    "grid",
    "reconstruct",
    "piv",
    "depth_calibration",
)


#: Config paths (sections or dotted sub-paths) of the imperfections a real experiment has and the
#: processing does not know (issue 29): a swept setting under one of them is a *tolerance*, not a
#: design choice. The report draws the error against each and can rank designs at their worst case
#: over them (``report.rank_at``); every setting here defaults to its ideal value in the schema.
TOLERANCES: tuple[str, ...] = (
    "camera.imperfections",
    "illumination",
    "particles.diameter",
    "particles.depth_margin",
    "sensor.background",
    "sensor.hot_pixels",
)


def is_tolerance(path: str) -> bool:
    """Whether the setting at config ``path`` (dotted) is an imperfection (:data:`TOLERANCES`)."""
    return _under(path, TOLERANCES)


@dataclass(frozen=True)
class _Stage:
    reads: tuple[str, ...]  # config paths (sections or dotted sub-paths) the stage reads
    upstream: tuple[str, ...]  # stages whose outputs it reads
    ignores: tuple[str, ...] = ()  # paths under ``reads`` that do not change its output


#: Every per-case stage of the workflow: what it reads and which stages feed it. The
#: Snakefile passes a stage only these config sections (and reruns it when they change);
#: a stage's outputs live at the case-id prefix holding every setting it depends on.
STAGES: dict[str, _Stage] = {
    # camera.imperfections reach the images only (the processing keeps the nominal camera)
    # (and the refocus planes it lays out do not depend on the refocus model)
    "camera": _Stage(("camera", "refocus"), (), ("camera.imperfections", "refocus.model")),
    "particles": _Stage(("seed", "camera", "particles"), (), ("camera.imperfections",)),
    "displace": _Stage(("flow",), ("particles",)),
    # the light volume dims each exposure's particles at their own depth
    "simulate": _Stage(("seed", "camera", "illumination", "raytrace", "sensor"), ("particles", "displace")),
    # the pinhole image is taken at its own f-number whatever the working one (sec. 5.1)
    "pinhole": _Stage(("seed", "camera", "pinhole", "raytrace", "sensor"), (), ("camera.main_lens.fnumber",)),
    "calibrate": _Stage(("camera",), ("pinhole",), ("camera.main_lens.fnumber",)),
    "register": _Stage(("camera",), ("simulate", "calibrate")),
    # the dot-target volumetric calibration (Hall et al. 2018): the card imaged through the case's
    # camera, imperfections and all, over the grid's depth, fitted on the lenslet calibration
    "volcal": _Stage(("seed", "camera", "raytrace", "refocus", "grid", "volumetric_calibration"), ("calibrate",)),
    # with refocus.model: volumetric the planes are sampled through it (the thin lens needs none)
    "refocus": _Stage(("camera", "refocus", "grid", "volumetric_calibration"), ("register", "volcal")),
    # MART's and IPR's beams go through the volumetric calibration too where refocus.model is volumetric
    "reconstruct": _Stage(
        ("camera", "refocus", "grid", "reconstruct", "volumetric_calibration"),
        ("refocus", "register", "calibrate", "volcal"),
    ),
    # the traversed-volume depth calibration of a design and its processing: every setting of the
    # images and of their processing, but not the flow (it images its own seeded volume)
    "depthcal": _Stage(
        (
            "seed",
            "camera",
            "particles",
            "illumination",
            "raytrace",
            "sensor",
            "refocus",
            "grid",
            "reconstruct",
            "piv",
            "depth_calibration",
            "volumetric_calibration",
        ),
        ("calibrate", "volcal"),
        ("depth_calibration.enabled",),  # whether the PIV uses it, not what it is
    ),
    "piv": _Stage(("piv", "depth_calibration"), ("reconstruct", "reconstruct_a", "depthcal")),
    # the errors stage also runs the oracle: the case's PIV on the true volumes, on the case's grid
    # (the true particles lit as in the images); it reads reconstruct.method to know whether a
    # particle list lies beside the volumes (found particles and ghosts)
    "errors": _Stage(
        ("flow", "camera", "illumination", "refocus", "grid", "reconstruct", "piv"),
        ("piv", "reconstruct", "reconstruct_a", "particles", "displace"),
    ),
}

#: The stages each exposure goes through. The first exposure (frame a) is the seeded field before any
#: displacement, so its images, light field, focal stack and volume do not depend on the flow: its stages
#: (``<stage>_a``, reading what the stage reads, fed by frame a's stages) write where the settings they depend on
#: say (:meth:`Sweep.stage_id`), shared by every flow of a design. Frame b's keep the plain names.
FRAME_STAGES: tuple[str, ...] = ("simulate", "register", "refocus", "reconstruct")
_FIRST_EXPOSURE_UPSTREAM = {
    "simulate": ("particles",),
    "register": ("simulate_a", "calibrate"),
    "refocus": ("register_a", "volcal"),
    "reconstruct": ("refocus_a", "register_a", "calibrate", "volcal"),
}
STAGES.update({f"{s}_a": _Stage(STAGES[s].reads, _FIRST_EXPOSURE_UPSTREAM[s], STAGES[s].ignores) for s in FRAME_STAGES})


def first_exposure_of(stage: str) -> str | None:
    """The :data:`FRAME_STAGES` stage that ``stage`` runs for frame a (``simulate`` for ``simulate_a``), else None."""
    base = stage.removesuffix("_a")
    return base if base != stage and base in FRAME_STAGES else None


def frame_stage(stage: str, frame: str) -> str:
    """The stage that runs ``stage`` (a key of :data:`STAGES`) for exposure ``frame`` ("a", "b" or "" for a
    stage of both): ``<stage>_a`` for frame a of the :data:`FRAME_STAGES`, else ``stage``."""
    return f"{stage}_a" if frame == "a" and stage in FRAME_STAGES else stage


#: Stages whose outputs are shared by every case with equal settings and live under ``calib/``:
#: the pinhole image, the lenslet calibration and the depth calibration.
SHARED: tuple[str, ...] = ("pinhole", "calibrate", "volcal", "depthcal")

#: Every per-case file of the workflow and the stage that writes it.
FILES: dict[str, str] = {
    "camera.json": "camera",
    "focal_planes.zarr": "camera",
    "particles_a.zarr": "particles",
    "particles_b.zarr": "displace",
    **{f"raw_{f}.{e}": frame_stage("simulate", f) for f in "ab" for e in ("zarr", "tif")},
    "pinhole.zarr": "pinhole",
    "pinhole.tif": "pinhole",
    "centers.zarr": "calibrate",
    "depth_calibration.zarr": "depthcal",
    "volcal.zarr": "volcal",
    **{f"lightfield_{f}.zarr": frame_stage("register", f) for f in "ab"},
    **{f"stack_{f}.zarr": frame_stage("refocus", f) for f in "ab"},
    **{f"volume_{f}.zarr": frame_stage("reconstruct", f) for f in "ab"},
    # the particle list of a method that fits particles (ipr), beside its volume; other methods have none
    **{f"volume_{f}.particles.zarr": frame_stage("reconstruct", f) for f in "ab"},
    "piv.zarr": "piv",
    "errors.zarr": "errors",
}


@dataclass(frozen=True)
class Setting:
    """One sweepable setting.

    Attributes
    ----------
    key : str
        Its name in the ``sweep`` section (``ppp``, ``reconstruct.method``).
    path : str
        The config path it sets (``particles.ppp``); ``flow`` picks ``flows.<name>``.
    short : str
        Its case-id segment name (``ppp``, ``mag``, ``reconstruct.method``).
    label, units : str
        Axis label and units (report, study Dataset).
    """

    key: str
    path: str
    short: str
    label: str
    units: str

    @property
    def dim(self) -> str:
        """Dimension name in the study Dataset (a valid identifier: ``reconstruct_method``)."""
        return self.key.replace(".", "_")

    @property
    def section(self) -> str:
        return self.path.split(".")[0]


#: The named parameters of the thesis' study, always part of a case id.
NAMED: dict[str, Setting] = {
    "magnification": Setting("magnification", "camera.magnification", "mag", "magnification M", "1"),
    "fnumber": Setting("fnumber", "camera.main_lens.fnumber", "fnum", "main-lens f-number", "1"),
    "lenslet_pitch": Setting("lenslet_pitch", "camera.lenslet.pitch", "pitch", "lenslet pitch", "mm"),
    "ppp": Setting("ppp", "particles.ppp", "ppp", "seeding density (particles per sensor pixel)", "1"),
    "flow": Setting("flow", "flow", "flow", "flow case", "1"),
}

_SAFE = re.compile(r"^[A-Za-z0-9_.+-]+$")


def tolerance_dims(study: Any) -> list[str]:
    """The dimensions of a study Dataset that sweep an imperfection (:data:`TOLERANCES`) over two or more
    levels, in the study's order (a dimension's config path is its ``sweep_key`` attribute)."""
    return [str(d) for d in study.dims if study.sizes[d] > 1 and is_tolerance(str(study[d].attrs.get("sweep_key", d)))]


def format_value(value: Any) -> str:
    """A swept value as written in case ids and study coordinates (``0.001``, ``matched``, ``8x16x16``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, (int, float)):
        return f"{value:g}" if isinstance(value, float) else str(value)
    if isinstance(value, (list, tuple)):
        return "x".join(format_value(v) for v in value)
    return str(value)


def _get(cfg: Mapping[str, Any], path: str) -> Any:
    node: Any = cfg
    for part in path.split("."):
        node = node[part]
    return node


def _set(cfg: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split(".")
    node = cfg
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = copy.deepcopy(value)


def _under(path: str, prefixes: Sequence[str]) -> bool:
    return any(path == p or path.startswith(p + ".") for p in prefixes)


def _schema_node(schema: Mapping[str, Any], path: str) -> Mapping[str, Any] | None:
    node: Any = schema
    for part in path.split("."):
        props = node.get("properties", {}) if isinstance(node, Mapping) else {}
        if part not in props:
            return None
        node = props[part]
    return node


@dataclass(frozen=True)
class Case:
    """One point of a sweep: the value of every setting, in case-id order."""

    keys: tuple[str, ...]
    values: tuple[Any, ...]
    segments: tuple[str, ...]

    @classmethod
    def of(cls, **values: Any) -> Case:
        """A case from keyword values: the named parameters (all five) and dotted settings
        (``**{"reconstruct.method": "mart"}``), in case-id order. For tables and notebooks;
        a study's cases come from :meth:`Sweep.cases`."""
        missing = [k for k in NAMED if k not in values]
        if missing:
            raise KeyError(f"Case.of needs the named parameters {missing}")
        rank = {s: i for i, s in enumerate(SECTION_ORDER)}
        keys = sorted(
            values,
            key=lambda k: (
                rank.get((NAMED[k].path if k in NAMED else k).split(".")[0], len(rank)),
                list(NAMED).index(k) if k in NAMED else len(NAMED),
            ),
        )
        shorts = [NAMED[k].short if k in NAMED else k for k in keys]
        vals = tuple(values[k] for k in keys)
        return cls(tuple(keys), vals, tuple(f"{s}~{format_value(v)}" for s, v in zip(shorts, vals)))

    def __getitem__(self, key: str) -> Any:
        try:
            return self.values[self.keys.index(key)]
        except ValueError:
            raise KeyError(key) from None

    def get(self, key: str, default: Any = None) -> Any:
        return self[key] if key in self.keys else default

    @property
    def params(self) -> dict[str, Any]:
        """``{sweep key: value}``."""
        return dict(zip(self.keys, self.values))

    @property
    def case_id(self) -> str:
        """The case id and results sub-path: ``mag~-1/fnum~matched/...``."""
        return "/".join(self.segments)

    # the named parameters, for convenience
    @property
    def magnification(self) -> float:
        return float(self["magnification"])

    @property
    def fnumber(self) -> float | str:
        return self["fnumber"]

    @property
    def lenslet_pitch(self) -> float:
        return float(self["lenslet_pitch"])

    @property
    def ppp(self) -> float:
        return float(self["ppp"])

    @property
    def flow(self) -> str:
        return str(self["flow"])


def _default_particle_mode(ccfg: dict[str, Any]) -> None:
    """Fill in ``piv.particles: paired`` where it is unset, the method fits particles and the depth
    calibration is off: on held-out cases it lowered IPR's total error on lateral shifts (coarse demo
    designs 8 of 12 within issue 27's targets against 6 of 12; thesis camera at 0.001-0.01 ppp 0.0145 ->
    0.0068, 0.0130 -> 0.0089, 0.0470 -> 0.0195, 0.0316 -> 0.0247 mm) and changed gradient flows by at
    most 5 % (docs/config.md). Everywhere else it stays unset (none), so those stage configs, and their
    outputs, keep their bytes."""
    piv = ccfg.get("piv")
    if not isinstance(piv, dict) or "particles" in piv or ccfg.get("depth_calibration", {}).get("enabled", True):
        return
    from lfstudy.reconstruct import ReconstructionError, gives_particles

    try:
        fits = gives_particles(ccfg.get("reconstruct", {}).get("method", ""))
    except ReconstructionError:  # an unknown method is refused by the config checks, with its name
        return
    if fits:
        piv["particles"] = "paired"


class Sweep:
    """The sweep of a validated study config (see the module docstring).

    Parameters
    ----------
    cfg : mapping
        A config with defaults filled in (:func:`lfstudy.study.config.validate_config`,
        or the raw schema-valid mapping while validating).
    schema : mapping, optional
        The config schema, for labels, units and checking dotted paths.
    """

    def __init__(self, cfg: Mapping[str, Any], schema: Mapping[str, Any] | None = None) -> None:
        self.cfg = cfg
        schema = schema if schema is not None else load_schema()
        sweep = dict(cfg.get("sweep", {}) or {})
        by_path = {s.path: s for s in NAMED.values()}
        settings: list[Setting] = list(NAMED.values())
        lists: dict[str, list[Any]] = {}
        for key, vals in sweep.items():
            if key in NAMED:
                lists[key] = list(vals)
                continue
            if key in by_path:  # a named parameter by its path: one name for one setting
                name = by_path[key].key
                if name in sweep:
                    raise ConfigError(f"config key 'sweep.{key}': the same setting as sweep.{name}; give one")
                lists[name] = list(vals)
                continue
            node = _schema_node(schema, key)
            if node is None or "properties" in node or key.split(".")[0] not in SECTION_ORDER:
                raise ConfigError(
                    f"config key 'sweep.{key}': not a setting of the config; sweep a named parameter "
                    f"({', '.join(NAMED)}) or a config setting by its dotted path (e.g. reconstruct.method)"
                )
            label = str(node.get("title") or key)
            settings.append(Setting(key, key, key, label, str(node.get("units", ""))))
            lists[key] = list(vals)
        for key, vals in lists.items():
            if not vals:
                raise ConfigError(f"config key 'sweep.{key}' = []: give at least one value")
            for v in vals:
                if not _SAFE.match(format_value(v)):
                    raise ConfigError(
                        f"config key 'sweep.{key}': value {v!r} cannot name a result directory "
                        "(allowed characters: letters, digits, _ . + -)"
                    )
            if len({format_value(v) for v in vals}) != len(vals):
                raise ConfigError(f"config key 'sweep.{key}' = {vals!r}: values must be distinct")
        # order: by the section the pipeline reads first, the named parameters in their thesis order
        rank = {s: i for i, s in enumerate(SECTION_ORDER)}
        named_order = list(NAMED)
        settings.sort(
            key=lambda s: (
                rank[s.section],
                named_order.index(s.key) if s.key in NAMED else len(NAMED),
            )
        )
        self.settings: tuple[Setting, ...] = tuple(settings)
        # the base config's value only for a setting not swept (a swept one may have no default)
        self._lists = {s.key: lists[s.key] if s.key in lists else [self._base(s)] for s in settings}
        self._cases: list[Case] | None = None

    def _base(self, s: Setting) -> Any:
        if s.key == "flow":
            return next(iter(self.cfg["flows"]))
        if s.key == "fnumber":
            return self.cfg["camera"]["main_lens"].get("fnumber", "matched")
        return _get(self.cfg, s.path)

    # ------------------------------------------------------------------ cases
    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(s.key for s in self.settings)

    def values(self, key: str) -> list[Any]:
        """The values of a setting, as listed (or the base config's single value)."""
        return list(self._lists[key])

    @property
    def swept(self) -> tuple[Setting, ...]:
        """Settings with more than one value."""
        return tuple(s for s in self.settings if len(self._lists[s.key]) > 1)

    def cases(self) -> list[Case]:
        """All cases (the Cartesian product), in a stable order."""
        if self._cases is None:
            keys = self.keys
            self._cases = [
                Case(
                    keys,
                    tuple(combo),
                    tuple(f"{s.short}~{format_value(v)}" for s, v in zip(self.settings, combo)),
                )
                for combo in itertools.product(*(self._lists[k] for k in keys))
            ]
        return list(self._cases)

    def __iter__(self) -> Iterator[Case]:
        return iter(self.cases())

    def __len__(self) -> int:
        return math.prod(len(v) for v in self._lists.values())

    def case(self, case_id: str | Case) -> Case:
        """The case with this id.

        Raises
        ------
        ConfigError
            The id is not one of the sweep's.
        """
        if isinstance(case_id, Case):
            return case_id
        for c in self.cases():
            if c.case_id == case_id.strip("/"):
                return c
        raise ConfigError(f"case id {case_id!r} is not a case of this study's sweep (see `lfstudy cases`)")

    def apply(self, case: Case) -> dict[str, Any]:
        """The full config of one case: base config with the case's values set, the flow's
        spec under ``flow`` (with its name) and ``case_id``."""
        out = copy.deepcopy(dict(self.cfg))
        for s, v in zip(self.settings, case.values):
            if s.key == "flow":
                if v not in out["flows"]:
                    raise ConfigError(f"case flow {v!r}: unknown; allowed values are {sorted(out['flows'])}")
                out["flow"] = {"name": v, **out["flows"][v]}
            else:
                _set(out, s.path, v)
        out["case_id"] = case.case_id
        _default_particle_mode(out)
        return out

    # ------------------------------------------------------------------ stages
    def _depends(self, stage: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """Config paths a stage's output depends on (its own and its upstream stages'), and ignores."""
        chain: list[_Stage] = []
        todo = [stage]
        seen: set[str] = set()
        while todo:
            st = todo.pop()
            if st in seen:
                continue
            seen.add(st)
            chain.append(STAGES[st])
            todo += STAGES[st].upstream
        reads = tuple(p for spec in chain for p in spec.reads)
        # an ignore holds only where no stage of the chain reads the path for a reason of its own
        # (the calibration ignores the working f-number; the images downstream of it do not)
        ignores = tuple(
            p
            for p in dict.fromkeys(q for spec in chain for q in spec.ignores)
            if all(_under(p, spec.ignores) for spec in chain if _under(p, spec.reads))
        )
        return reads, ignores

    def depends_on(self, stage: str) -> tuple[Setting, ...]:
        """The settings a stage's output depends on."""
        reads, ignores = self._depends(stage)
        return tuple(s for s in self.settings if _under(s.path, reads) and not _under(s.path, ignores))

    def stage_id(self, case: Case | str, stage: str) -> str:
        """Where a stage's outputs live: the case-id prefix up to the last setting it depends on; for frame a's
        stages (``<stage>_a``, :data:`FRAME_STAGES`) the case's segments of exactly the settings they depend on
        (the case id without its flow), so the flows of a design share the first exposure's files."""
        case = self.case(case)
        deps = {s.key for s in self.depends_on(stage)}
        if first_exposure_of(stage):
            own = "/".join(seg for s, seg in zip(self.settings, case.segments) if s.key in deps)
            if own:
                return own
        last = max((i for i, s in enumerate(self.settings) if s.key in deps), default=0)
        return "/".join(case.segments[: last + 1])

    def shared_id(self, case: Case | str, stage: str) -> str:
        """Where a shared stage (:data:`SHARED`) writes under ``calib/``: the case's segments of
        exactly the settings the stage depends on, so cases share it when those are equal."""
        case = self.case(case)
        deps = {s.key for s in self.depends_on(stage)}
        return "/".join(seg for s, seg in zip(self.settings, case.segments) if s.key in deps)

    def calib_id(self, case: Case | str) -> str:
        """The shared calibration's id: the segments of the settings the pinhole image depends on."""
        return self.shared_id(case, "calibrate")

    def _where(self, case: Case | str, stage: str) -> str:
        return self.shared_id(case, stage) if stage in SHARED else self.stage_id(case, stage)

    def ids(self, case: Case | str) -> dict[str, str]:
        """Where every stage of a case writes: ``{stage: stage id (shared id for the shared stages)}``."""
        case = self.case(case)
        return {st: self._where(case, st) for st in STAGES}

    def stage_ids(self, stage: str) -> dict[str, Case]:
        """Every distinct output location of a stage, with a case that has it (for its config)."""
        out: dict[str, Case] = {}
        for c in self.cases():
            out.setdefault(self._where(c, stage), c)
        return out

    def locate(self, case: Case | str, name: str) -> str:
        """Results-relative path of one of a case's files (:data:`FILES`): ``<stage id>/<name>``,
        or ``calib/<shared id>/<name>`` for the shared stages."""
        stage = FILES[name]
        if stage in SHARED:
            return f"calib/{self.shared_id(case, stage)}/{name}"
        return f"{self.stage_id(case, stage)}/{name}"
