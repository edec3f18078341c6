"""Reconstruction methods: one interface, found by name (thesis sec. 5.5–5.6).

A method is a subclass of :class:`ReconstructionMethod` with a ``name``, a
``description``, the inputs it ``requires`` (what a real experiment has: the
registered light field, the lenslet calibration, the camera, the
reconstruction grid, and the focal stack refocused on that grid) and its
``parameters`` (JSON-schema properties with types and ranges, which the config
schema includes as ``reconstruct.<name>``). Its ``run`` takes those parameters
as explicit keyword-only arguments and returns a volume on the grid. A method
that fits particles (``particles = True``, as ``ipr``) also has ``run_particles``:
the volume and the particle list it was rendered from, out of one fit
(:func:`reconstruct_particles`); the workflow and ``lfstudy process`` then write
the list beside the volume. The
defaults live in one place, ``run``'s signature (:func:`detect_parameters`, as
xarray's backends): the schema and the filled-in config read them from there.

Built-in methods are listed in :data:`BUILTIN` and imported on first use;
methods of other packages are found through the entry-point group
``lfstudy.reconstruct`` (``name = "package.module:Class"``), so
``reconstruct.method: mine`` works without an import in the config (one that
fails to load, or that reuses a built-in's name, is skipped with a warning, so the
others and every config that does not use it keep working: one loader and one rule
for both registries, :mod:`lfstudy.plugins`);
:func:`register_method` adds one at run time (a notebook, a test), and replaces a
built-in only when asked to (``replace=True``)::

    @register_method
    class Blur(ReconstructionMethod):
        name = "blur"
        description = "Gaussian blur of the focal stack"
        requires = ("stack",)
        parameters = {"sigma": {"type": "number", "exclusiveMinimum": 0}}

        def run(self, inputs, *, sigma=1.0, progress=False):
            ...

    reconstruct(inputs, method="blur", sigma=2.0)
"""

from __future__ import annotations

import functools
import importlib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import xarray as xr

from lfstudy.config import ConfigError, validate_section
from lfstudy.optics import PlenopticCamera
from lfstudy.plugins import load_plugins
from lfstudy.reconstruct.grid import ReconstructionGrid

__all__ = [
    "INPUTS",
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "ReconstructionError",
    "ReconstructionInputs",
    "ReconstructionMethod",
    "ReconstructionSize",
    "available_methods",
    "detect_parameters",
    "get_method",
    "method_schemas",
    "register_method",
    "unregister_method",
    "reconstruct",
    "reconstruct_particles",
    "gives_particles",
]

#: What a method may require.
INPUTS = ("stack", "lightfield", "centers", "camera", "grid")

#: Built-in methods: name -> "module:Class" (imported on first use).
BUILTIN: dict[str, str] = {
    "threshold": "lfstudy.reconstruct.threshold:Threshold",
    "none": "lfstudy.reconstruct.threshold:FocalStack",
    "mart": "lfstudy.reconstruct.mart:MART",
    "deconvolution": "lfstudy.reconstruct.deconvolution:RichardsonLucy",
    "ipr": "lfstudy.reconstruct.ipr:IPR",
}

#: Entry-point group of methods from other packages.
ENTRY_POINT_GROUP = "lfstudy.reconstruct"

_REGISTERED: dict[str, type[ReconstructionMethod]] = {}


class ReconstructionError(ValueError):
    """Bad reconstruction input: unknown method, bad parameter, missing or mismatched input."""


@dataclass(frozen=True, eq=False)
class ReconstructionInputs:
    """What an experiment has for one frame; a method takes what it ``requires``.

    Attributes
    ----------
    stack : xarray.DataArray, optional
        Focal stack refocused on the grid, dims (z, y, x).
    lightfield : xarray.DataArray, optional
        Registered 4-D light field (:func:`lfstudy.lightfield.register`).
    centers : xarray.Dataset, optional
        Lenslet calibration (:func:`lfstudy.lightfield.find_lenslet_centers`).
    camera : PlenopticCamera, optional
    grid : ReconstructionGrid, optional
        Default: the grid of ``stack`` (its coords).
    calibration : xarray.Dataset, optional
        The volumetric (dot-target) calibration (:func:`lfstudy.lightfield.volcal.fit_volumetric`,
        Hall et al. 2018; a :class:`~lfstudy.lightfield.volcal.VolumetricCalibration` is taken as its
        Dataset) where ``refocus.model`` is ``volumetric``: the methods that model the camera (``mart``,
        ``ipr``) then place their beams through it instead of the thin lens.
    """

    stack: xr.DataArray | None = None
    lightfield: xr.DataArray | None = None
    centers: xr.Dataset | None = None
    camera: PlenopticCamera | None = None
    grid: ReconstructionGrid | None = None
    calibration: xr.Dataset | None = None

    def __post_init__(self) -> None:
        if self.stack is not None:
            if not isinstance(self.stack, xr.DataArray) or tuple(self.stack.dims) != ("z", "y", "x"):
                raise ReconstructionError("stack must be a 3-D DataArray with dims ('z', 'y', 'x')")
            sg = ReconstructionGrid.from_coords(self.stack)
            if self.grid is None:
                object.__setattr__(self, "grid", sg)
            elif sg.shape != self.grid.shape or not all(
                np.allclose(getattr(sg, a), getattr(self.grid, a)) for a in ("x", "y", "z")
            ):
                raise ReconstructionError(
                    f"the focal stack ({sg.shape}) is not on the reconstruction grid ({self.grid.shape}); "
                    "refocus it onto the grid's planes"
                )
        if self.lightfield is not None and self.centers is not None:
            lf, cen = self.lightfield, self.centers
            shape_c = (cen.sizes.get("lenslet_row"), cen.sizes.get("lenslet_col"))
            shape_l = (lf.sizes.get("lrow"), lf.sizes.get("lcol"))
            if shape_c != shape_l:
                raise ReconstructionError(
                    f"the light field has {shape_l[0]} x {shape_l[1]} lenslets (rows x cols) but the calibration "
                    f"has {shape_c[0]} x {shape_c[1]}: they do not belong together"
                )
        if self.calibration is not None:
            from lfstudy.lightfield.volcal import VolumetricCalibration, VolumetricCalibrationError

            try:  # a whole fit (the calibration's own check); the methods take its Dataset
                object.__setattr__(self, "calibration", VolumetricCalibration.of(self.calibration).dataset)
            except VolumetricCalibrationError as exc:
                raise ReconstructionError(str(exc)) from None


@dataclass(frozen=True)
class ReconstructionSize:
    """What sizes one frame's reconstruction, for a method's :meth:`ReconstructionMethod.memory_bytes`.

    Attributes
    ----------
    n_pixels : int
        Sensor pixels.
    n_lenslets : int
        Lenslets (rows x columns).
    pixels_per_lenslet : int
        The side of a lenslet's block of the light field.
    n_planes : int
        Planes of the reconstruction grid.
    n_voxels : int
        Voxels of the reconstruction grid.
    n_particles : int
        Particles seeded in the frame (0: unknown), for a method whose time goes with them.
    """

    n_pixels: int
    n_lenslets: int
    pixels_per_lenslet: int
    n_planes: int
    n_voxels: int
    n_particles: int = 0

    @property
    def lightfield_bytes(self) -> int:
        """The float32 light field."""
        return self.n_lenslets * self.pixels_per_lenslet**2 * 4


class ReconstructionMethod:
    """Base class of a reconstruction method (see the module docstring)."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    requires: ClassVar[tuple[str, ...]] = ("stack",)
    parameters: ClassVar[dict[str, dict[str, Any]]] = {}
    #: True for a method that fits particles: its ``run_particles`` gives the list with the volume.
    particles: ClassVar[bool] = False
    #: True for a method that models the camera and so places its beams through a volumetric calibration
    #: (``ReconstructionInputs.calibration``) where ``refocus.model`` is ``volumetric``: a case then needs one.
    uses_calibration: ClassVar[bool] = False

    @classmethod
    def memory_bytes(cls, size: ReconstructionSize, params: Mapping[str, Any] | None = None) -> float:
        """Estimated peak memory [bytes] of reconstructing one frame (:mod:`lfstudy.study.resources`).

        The base counts what every method holds: the light field and four float64 volumes on the
        grid (the focal stack, the result and their working copies). A method with large arrays
        of its own (weight tables, spectra) adds them.

        Parameters
        ----------
        size : ReconstructionSize
            The camera's and the grid's sizes.
        params : mapping, optional
            The method's parameters (``reconstruct.<name>``), for a method whose memory depends on one.
        """
        return size.lightfield_bytes + 4 * size.n_voxels * 8

    @classmethod
    def seconds(cls, size: ReconstructionSize, params: Mapping[str, Any] | None = None) -> float:
        """An upper estimate of one frame's reconstruction time [s] on one core, for a batch system's time limit
        (:func:`lfstudy.study.resources.job_runtime_min`); 0: none beyond the rule's floor (the profile's
        measured figures cover the grid methods). A method whose time grows past that floor (``ipr``: with the
        particles) states its own.

        Parameters
        ----------
        size : ReconstructionSize
            The camera's, the grid's and the seeding's sizes.
        params : mapping, optional
            The method's parameters (``reconstruct.<name>``).
        """
        return 0.0

    def run(self, inputs: ReconstructionInputs, *, progress: bool = False, **params: Any) -> xr.DataArray:
        raise NotImplementedError  # pragma: no cover - subclasses implement run

    def run_particles(
        self, inputs: ReconstructionInputs, *, progress: bool = False, **params: Any
    ) -> tuple[xr.DataArray, xr.Dataset]:
        """The volume of :meth:`run` and the particle list it was rendered from, out of one fit.

        Only methods with ``particles = True`` have it. The list is a Dataset over ``particle``
        with at least ``x``, ``y``, ``z`` [mm] and ``intensity``.
        """
        raise ReconstructionError(f"reconstruct.method = {self.name!r} fits no particles (particles = False)")

    @classmethod
    def schema(cls) -> dict[str, Any]:
        """The JSON schema of this method's parameters (``reconstruct.<name>``), defaults from ``run``."""
        defaults = detect_parameters(cls)
        return {
            "type": "object",
            "additionalProperties": False,
            "default": {},
            "description": f"parameters of reconstruct.method '{cls.name}': {cls.description}",
            "properties": {k: {**v, "default": defaults[k]} for k, v in cls.parameters.items()},
        }

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """``{parameter: default}``, from ``run``'s signature."""
        return detect_parameters(cls)


def detect_parameters(cls: type[ReconstructionMethod]) -> dict[str, Any]:
    """A method's parameters and their defaults, read from its ``run`` signature.

    The keyword-only arguments of ``run`` other than ``progress`` are the
    parameters; their defaults are the only statement of the defaults (the
    schema's ``default`` values are filled in from here).

    Raises
    ------
    ReconstructionError
        ``run`` takes ``*args`` or ``**kwargs``, a parameter has no default,
        the keyword-only arguments are not the names of ``parameters``, or a
        ``default`` stated in ``parameters`` differs from the signature's.
    """
    where = f"reconstruction method {cls.__name__} ({cls.name!r})"
    out: dict[str, Any] = {}
    for p in inspect.signature(cls.run).parameters.values():
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            raise ReconstructionError(f"{where}: run() takes {p}; name every parameter as a keyword-only argument")
        if p.kind is p.KEYWORD_ONLY and p.name != "progress":
            if p.default is p.empty:
                raise ReconstructionError(f"{where}: run() parameter {p.name!r} needs a default")
            out[p.name] = p.default
    if set(out) != set(cls.parameters):
        raise ReconstructionError(
            f"{where}: run() takes the parameters {sorted(out)} but `parameters` declares "
            f"{sorted(cls.parameters)}; they must be the same"
        )
    for k, spec in cls.parameters.items():
        if "default" in spec and spec["default"] != out[k]:
            raise ReconstructionError(
                f"{where}: parameter {k!r} has default {spec['default']!r} in `parameters` but {out[k]!r} in "
                "run(); state it once, in run()"
            )
    return out


def _load(spec: str) -> type[ReconstructionMethod]:
    mod, _, attr = spec.partition(":")
    return getattr(importlib.import_module(mod), attr)


@functools.lru_cache(maxsize=1)
def _plugins() -> tuple[dict[str, type[ReconstructionMethod]], dict[str, str]]:
    """The methods of the entry-point group, loaded: ``({name: class}, {name: why it was skipped})``.

    A plugin named as a built-in, or that fails to import, is not a method or declares
    its parameters wrongly, is skipped with a warning (as xarray's backend loader does), so one
    broken package does not stop every config from loading.
    """

    def check(name: str, cls: Any) -> None:
        if not (isinstance(cls, type) and issubclass(cls, ReconstructionMethod)):
            raise ReconstructionError(f"{cls!r} is not a ReconstructionMethod subclass")
        detect_parameters(cls)

    return load_plugins(ENTRY_POINT_GROUP, "reconstruction method", check, builtin=BUILTIN)


def available_methods() -> list[str]:
    """Names accepted by :func:`reconstruct`: built-in, installed (entry points) and registered."""
    return sorted(set(BUILTIN) | set(_plugins()[0]) | set(_REGISTERED))


def get_method(name: str) -> type[ReconstructionMethod]:
    """The method class called ``name``.

    Raises
    ------
    ReconstructionError
        Unknown name (the message lists the available ones).
    """
    if name in _REGISTERED:
        return _REGISTERED[name]
    if name in BUILTIN:
        return _load(BUILTIN[name])
    plugins, skipped = _plugins()
    if name in plugins:
        return plugins[name]
    if name in skipped:
        raise ReconstructionError(
            f"reconstruct.method = {name!r}: the method installed under this name (entry point group "
            f"{ENTRY_POINT_GROUP!r}) failed to load: {skipped[name]}"
        )
    raise ReconstructionError(
        f"reconstruct.method = {name!r}: unknown reconstruction method; available: {', '.join(available_methods())}"
    )


def method_schemas() -> dict[str, dict[str, Any]]:
    """``{name: parameter schema}`` of every available method (for the config schema)."""
    return {name: get_method(name).schema() for name in available_methods()}


def _function_method(name: str, func: Callable[..., xr.DataArray]) -> type[ReconstructionMethod]:
    """Wrap ``func(stack, **params) -> volume`` as a method requiring only the stack."""
    sig = inspect.signature(func)
    kw_params = [
        p.replace(kind=p.KEYWORD_ONLY)
        for p in list(sig.parameters.values())[1:]
        if p.default is not p.empty and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    ]
    params: dict[str, dict[str, Any]] = {p.name: {} for p in kw_params}

    def run(self, inputs, *, progress=False, **kw):
        return func(inputs.stack, **kw)

    # the parameters as run()'s keyword-only arguments, where detect_parameters reads the defaults
    P = inspect.Parameter
    run.__signature__ = inspect.Signature(
        [
            P("self", P.POSITIONAL_OR_KEYWORD),
            P("inputs", P.POSITIONAL_OR_KEYWORD),
            *kw_params,
            P("progress", P.KEYWORD_ONLY, default=False),
        ]
    )

    doc = (func.__doc__ or "").strip().splitlines()
    return type(
        f"FunctionMethod_{name}",
        (ReconstructionMethod,),
        {
            "name": name,
            "description": doc[0] if doc else name,
            "requires": ("stack",),
            "parameters": params,
            "run": run,
        },
    )


def register_method(obj: Any = None, *, replace: bool = False) -> Any:
    """Register a method at run time (a notebook, a test).

    Parameters
    ----------
    obj : ReconstructionMethod subclass or str
        A method class (``@register_method``), or a name for a plain function
        ``f(stack, **params)`` (``@register_method("name")``).
    replace : bool
        Allow the name of a built-in method (:data:`BUILTIN`): the registered one then
        stands for it until :func:`unregister_method`. Without it a built-in's name is
        refused, so a config's ``mart`` is the built-in MART unless the session asked
        otherwise (installed plugins cannot take a built-in's name at all:
        :mod:`lfstudy.plugins`). Another run-time registration of the same name is
        replaced either way (a notebook cell run again).

    Returns
    -------
    The class (for ``@register_method``) or a decorator.

    Raises
    ------
    ReconstructionError
        An empty or built-in name (without ``replace``), unknown ``requires`` or parameters
        declared wrongly (:func:`detect_parameters`).
    """
    if obj is None:  # @register_method(replace=True)
        return functools.partial(register_method, replace=replace)

    def free(name: str) -> None:
        if name in BUILTIN and not replace:
            raise ReconstructionError(
                f"reconstruction method {name!r} is built in; register_method(..., replace=True) replaces it "
                f"for this session (unregister_method({name!r}) restores it), or choose another name"
            )

    if isinstance(obj, type) and issubclass(obj, ReconstructionMethod):
        if not obj.name:
            raise ReconstructionError(f"{obj.__name__}: a reconstruction method needs a non-empty name")
        free(obj.name)
        bad = set(obj.requires) - set(INPUTS)
        if bad:
            raise ReconstructionError(f"{obj.__name__}.requires: unknown inputs {sorted(bad)}; allowed {INPUTS}")
        detect_parameters(obj)
        _REGISTERED[obj.name] = obj
        return obj
    if not isinstance(obj, str) or not obj:
        raise ReconstructionError(f"reconstruction method name must be a non-empty string, got {obj!r}")
    free(obj)

    def deco(func: Callable[..., xr.DataArray]) -> Callable[..., xr.DataArray]:
        _REGISTERED[obj] = _function_method(obj, func)
        return func

    return deco


def unregister_method(name: str) -> None:
    """Remove a method registered with :func:`register_method` (a built-in it replaced is back)."""
    _REGISTERED.pop(name, None)


def _check_params(cls: type[ReconstructionMethod], params: dict[str, Any]) -> dict[str, Any]:
    unknown = sorted(set(params) - set(cls.parameters))
    if unknown:
        raise ReconstructionError(
            f"reconstruct.{cls.name}: unknown parameter(s) {', '.join(unknown)}; "
            f"allowed: {', '.join(sorted(cls.parameters)) or 'none'}"
        )
    try:
        return validate_section(cls.schema(), params, f"reconstruct.{cls.name}")
    except ConfigError as exc:
        raise ReconstructionError(str(exc)) from None


def reconstruct(
    inputs: ReconstructionInputs | xr.DataArray,
    method: str = "threshold",
    *,
    progress: bool = False,
    **params: Any,
) -> xr.DataArray:
    """Reconstruct a particle volume with a method found by name.

    Parameters
    ----------
    inputs : ReconstructionInputs or xarray.DataArray
        What the method may use; a bare DataArray is taken as the focal stack
        (enough for ``threshold``, ``none`` and ``deconvolution`` without a camera).
    method : str
        A name from :func:`available_methods`.
    progress : bool
        Show the method's progress bar (iterations).
    **params
        The method's parameters (defaults from its ``run`` signature).

    Returns
    -------
    xarray.DataArray
        The volume on the grid, dims (z, y, x), attrs ``method`` and the
        parameters used.

    Raises
    ------
    ReconstructionError (a ValueError)
        Unknown method, unknown or out-of-range parameter, a required input
        missing, or inputs that do not fit together.

    Examples
    --------
    The thesis' threshold + dilation (sec. 5.5) of a 3 x 5 x 5 focal stack
    holding one bright voxel on a dim background: the voxel passes the
    threshold, and the dilation by a disk of radius 1 keeps its four
    in-plane neighbours with it.

    >>> import numpy as np, xarray as xr
    >>> from lfstudy.reconstruct import reconstruct
    >>> stack = np.full((3, 5, 5), 0.01)
    >>> stack[1, 2, 2] = 1.0
    >>> vol = reconstruct(xr.DataArray(stack, dims=("z", "y", "x")), "threshold", k=3.0, dilation_radius=1)
    >>> vol.dims, vol.attrs["method"]
    (('z', 'y', 'x'), 'threshold')
    >>> (vol.values[1] > 0).astype(int)
    array([[0, 0, 0, 0, 0],
           [0, 0, 1, 0, 0],
           [0, 1, 1, 1, 0],
           [0, 0, 1, 0, 0],
           [0, 0, 0, 0, 0]])
    >>> int((vol.values > 0).sum())
    5
    """
    inputs, cls, full = _prepare(inputs, method, params)
    vol = cls().run(inputs, progress=progress, **full)
    vol.attrs.update({"method": cls.name, **{f"param_{k}": v for k, v in full.items()}})
    return vol


def _prepare(
    inputs: ReconstructionInputs | xr.DataArray, method: str, params: dict[str, Any]
) -> tuple[ReconstructionInputs, type[ReconstructionMethod], dict[str, Any]]:
    """The checks of :func:`reconstruct`: the inputs, the method class and its full parameters."""
    if isinstance(inputs, xr.DataArray):
        inputs = ReconstructionInputs(stack=inputs)
    if not isinstance(inputs, ReconstructionInputs):
        raise ReconstructionError("inputs must be a ReconstructionInputs or a focal-stack DataArray")
    cls = get_method(method)
    missing = [r for r in cls.requires if getattr(inputs, r) is None]
    if missing:
        raise ReconstructionError(
            f"reconstruct.method = {method!r} needs {', '.join(missing)} (it requires {', '.join(cls.requires)})"
        )
    return inputs, cls, _check_params(cls, dict(params))


def gives_particles(method: str) -> bool:
    """Whether reconstruction method ``method`` fits particles (``particles = True``): its
    reconstruction has a particle list besides the volume (:func:`reconstruct_particles`).

    Raises
    ------
    ReconstructionError
        Unknown method.
    """
    return bool(get_method(method).particles)


def reconstruct_particles(
    inputs: ReconstructionInputs | xr.DataArray,
    method: str = "threshold",
    *,
    progress: bool = False,
    **params: Any,
) -> tuple[xr.DataArray, xr.Dataset | None]:
    """:func:`reconstruct`, with the particle list of a method that fits particles.

    Parameters and checks as :func:`reconstruct`.

    Returns
    -------
    volume : xarray.DataArray
        As :func:`reconstruct` returns it (the same attrs).
    particles : xarray.Dataset or None
        The particle list the volume was rendered from, out of the same fit (a method with
        ``particles = True``), with the volume's ``method`` and ``param_*`` attrs; None for
        a method that fits no particles.
    """
    if not get_method(method).particles:
        return reconstruct(inputs, method, progress=progress, **params), None
    inputs, cls, full = _prepare(inputs, method, params)
    vol, parts = cls().run_particles(inputs, progress=progress, **full)
    stamp = {"method": cls.name, **{f"param_{k}": v for k, v in full.items()}}
    vol.attrs.update(stamp)
    parts.attrs.update(stamp)
    return vol, parts
