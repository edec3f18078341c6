"""The fit's settings: one frozen dataclass holding every parameter, its default, its range and its doc.

:class:`IPRSettings` is the only place the parameters are stated. The method class's config schema
(``reconstruct.ipr``, :attr:`lfstudy.reconstruct.ipr.IPR.parameters`) and its ``run`` signature, whose
defaults the schema reads (:func:`lfstudy.reconstruct.detect_parameters`), are made from its fields; the
range check on construction reads the same schema fragments, so a direct call of
:func:`~lfstudy.reconstruct.ipr.ipr_particles` and a config are held to the same ranges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from lfstudy.reconstruct.ipr.patches import _QUAD
from lfstudy.reconstruct.registry import ReconstructionError

__all__ = ["IPRSettings"]

_JACOBIANS = ("central", "forward")  # finite differences of the position Jacobian
#: Where the residual rounds' candidates come from (``residual_volume``): ``mart`` MART on the refined candidate
#: grid, ``case`` MART on the case's own grid (18x fewer voxels on the default refinement), ``stack`` the residual's
#: focal stack on the refined grid (its additive back-projection, one pass over the tables, no iteration)
_RESIDUAL_VOLUMES = ("mart", "case", "stack")
#: Particles per batch of images: a shake batch holds 7 images per particle, each its patch's box (the defocus spot
#: and a lenslet, ~200 x 200 px on average over the Table 4.3 camera's 7 mm depth, 5 % of it lit): 64 particles
#: take ~0.15 GB, 256 took 0.59 GB (``bench_ipr.py --memory``), the 2048 before 4.7 GB. The batch changes the fit
#: by rounding only (tests), and its cost: an image costs less in smaller batches (a call's patches are tens to
#: hundreds of MB at 256; the cause is not measured further), the shake's images 0.144 -> 0.105 ms on a demo frame
#: (``bench_ipr.py``'s docstring); below ~32 the calls' own cost (~0.3 ms each) shows
_BATCH = 64


def _param(default: Any, description: str, *, config: bool = True, **schema: Any) -> Any:
    """A settings field: its default and its JSON-schema fragment (type, range or enum, the config's one-line
    description). ``config=False``: a setting of the call only (not a ``reconstruct.ipr`` key)."""
    return field(default=default, metadata={"schema": {**schema, "description": description}, "config": config})


@dataclass(frozen=True)
class IPRSettings:
    """The settings of an IPR fit (:func:`lfstudy.reconstruct.ipr.ipr_particles`), range-checked.

    Each field is a ``reconstruct.ipr`` config key (but ``batch``); the defaults are the method's.

    Parameters
    ----------
    iterations : int
        Outer iterations (render, shake, remove ghosts, add candidates), 0–100.
    peak_threshold : float
        MART peaks below this fraction of the volume's maximum are no candidates, (0, 1].
    min_intensity : float
        Particles fainter than this fraction of the median intensity are removed as ghosts, [0, 1].
    shake : float
        Finite-difference step δ of the position Jacobian, in voxels of the grid (per axis), (0, 1].
    max_step : float
        Largest move of a particle in one iteration, in voxels (the trust region), (0, 5].
    damping : float
        Levenberg–Marquardt damping λ of the position part of the normal equations, [0, 1e6].
    background : float
        Dark level subtracted from the light field (image units), ≥ 0.
    residual_candidates : int
        After each of this many first iterations, MART peaks of the positive residual add candidates, 0–100.
    mart_iterations : int
        MART iterations of the first candidate volume (of the data), 0–50.
    residual_mart_iterations : int
        MART iterations of the residual's candidate volumes (0: its MLOS first guess alone), 0–50.
    residual_plane_step : int
        The residual's candidate volumes are reconstructed on every ``residual_plane_step``-th plane of
        the candidate grid (:meth:`lfstudy.reconstruct.mart.MartPlan.planes`: the same weight tables,
        that many times fewer planes and about that many times cheaper); 1: every plane. 1–4.
    residual_candidates_min_gain : float
        The residual-candidate rounds stop after one that adds fewer new particles than this fraction of the
        particle list (its remaining volumes would repeat the last one's rejected peaks; package docstring,
        step 1); 0: every one of the ``residual_candidates`` rounds runs. [0, 1].
    residual_late_gain : float
        Once a residual-candidate round adds fewer new particles than this fraction of the list (but not fewer than
        ``residual_candidates_min_gain``'s), the later rounds' volumes take ``_LATE_MART_ITERATIONS`` (1) MART
        iterations instead of ``residual_mart_iterations``; 0: never. [0, 1].
    residual_volume : {"mart", "case", "stack"}
        The volume whose peaks are the residual rounds' candidates (package docstring, step 1): ``mart`` MART
        (``residual_mart_iterations``) on the refined candidate grid; ``case`` MART (as many iterations) on the case's
        own grid, whose plan is made once besides the refined grid's; ``stack`` the residual's focal stack on the
        refined grid (the coverage-weighted mean of the rays through each voxel, no MART iteration). The first
        candidates (of the data) always come from MART on the refined grid.
    shake_settle : float
        The shake's active set [voxels]: a particle whose last shake moved it less than this, with no particle
        within ``_SETTLE_RADIUS`` voxels moved (as much), added or removed since, sits out the next shake (at most
        ``_SETTLE_SKIPS`` in a row; attrs ``shake_sat_out``: how many per iteration); 0: every particle is shaken
        every iteration. [0, 1].
    jacobian : {"central", "forward"}
        Finite differences of the position Jacobian: ``central`` renders the six ±δ trial images per
        particle and iteration, ``forward`` the three +δ ones (the choice then has four exact candidates
        besides the current position: the three trials and the Gauss–Newton step).
    image_accuracy : {"fast", "exact"}
        Quadrature of the per-particle images (:func:`~lfstudy.reconstruct.ipr.particle_patches`): ``exact`` the
        renderer's own, ``fast`` within 1e-4 of each image's peak (package docstring, step 2).
    polish : int
        Rounds of the final polish (package docstring, step 4): each particle whose defocus spot on the lenslet
        array is at most ``_POLISH_SPOT`` pitches is moved to the likelihood-weighted mean of a stencil of positions
        around it (0: none). 0–20.
    split : int
        Rounds of the split after the polish (package docstring, step 5): each particle brighter than
        ``split_ratio`` times the median is tried as two close particles, kept where the residual falls by more
        than ``split_penalty`` times its variance (0: none). 0–10.
    split_penalty : float
        The split's threshold on the drop of ‖R‖², in units of the pair fit's residual variance σ² on its pixels,
        [0, 1e6].
    split_ratio : float
        The split tries the particles brighter than this times the median intensity (0: every particle), [0, 100].
    image_calibration : int
        Rounds of the image model's calibration from the recording's own particles
        (:mod:`lfstudy.reconstruct.image_model`: the lenslet-to-sensor gap and a blur scale, fitted to the residual
        with the particles held), spread over the iterations (after iterations k·n/(rounds + 1)); the later
        iterations, the polish and the split fit with the calibrated images. 0: the nominal camera's images. 0–5.
    batch : int
        Particles rendered at once (bounds the patch memory: their images' boxes, ~40,000 pixels each on average
        over the thesis' 7 mm depth, the shake's 7 per particle: ~0.15 GB at 64, 0.59 GB at 256); it changes the
        fit by rounding only; not a config key. ≥ 1.

    Raises
    ------
    ReconstructionError
        A value of the wrong type or out of its range, naming the key (``reconstruct.ipr.<name>``) and what is
        allowed.

    Examples
    --------
    >>> from lfstudy.reconstruct.ipr import IPRSettings
    >>> s = IPRSettings(split=1)
    >>> s.polish, s.split, s.image_accuracy
    (3, 1, 'fast')
    >>> IPRSettings(polish=21)
    Traceback (most recent call last):
    ...
    lfstudy.reconstruct.registry.ReconstructionError: reconstruct.ipr.polish = 21: allowed range is [0, 20]
    """

    iterations: int = _param(10, "outer iterations", type="integer", minimum=0, maximum=100)
    peak_threshold: float = _param(
        0.1,
        "MART peaks below this fraction of its maximum are no candidates",
        type="number",
        exclusiveMinimum=0,
        maximum=1,
    )
    min_intensity: float = _param(
        0.2,
        "particles fainter than this fraction of the median are removed as ghosts",
        type="number",
        minimum=0,
        maximum=1,
    )
    shake: float = _param(
        0.1, "finite-difference step of the position Jacobian [voxels]", type="number", exclusiveMinimum=0, maximum=1
    )
    max_step: float = _param(
        0.5, "largest move of a particle per iteration [voxels]", type="number", exclusiveMinimum=0, maximum=5
    )
    damping: float = _param(
        0.01, "Levenberg-Marquardt damping of the positions", type="number", minimum=0, maximum=1000000
    )
    background: float = _param(0.0, "dark level subtracted (image units)", type="number", minimum=0)
    residual_candidates: int = _param(
        10,
        "first iterations after which MART peaks of the residual add candidates",
        type="integer",
        minimum=0,
        maximum=100,
    )
    mart_iterations: int = _param(
        3, "MART iterations of the first candidate volume (of the data)", type="integer", minimum=0, maximum=50
    )
    residual_mart_iterations: int = _param(
        3,
        "MART iterations of the residual's candidate volumes (0: its MLOS first guess alone)",
        type="integer",
        minimum=0,
        maximum=50,
    )
    residual_plane_step: int = _param(
        1,
        "the residual's candidate volumes on every n-th plane of the candidate grid (n x cheaper)",
        type="integer",
        minimum=1,
        maximum=4,
    )
    residual_candidates_min_gain: float = _param(
        0.001,
        "residual-candidate rounds stop after one adding fewer than this fraction of the particles",
        type="number",
        minimum=0,
        maximum=1,
    )
    residual_late_gain: float = _param(
        0.01,
        "after a residual-candidate round adding fewer than this fraction of the particles, the "
        "later rounds' volumes take one MART iteration (0: never)",
        type="number",
        minimum=0,
        maximum=1,
    )
    residual_volume: str = _param(
        "mart",
        "the residual rounds' candidates: peaks of MART on the refined grid (mart), of MART on the "
        "case grid (case) or of the residual's focal stack on the refined grid (stack)",
        type="string",
        enum=list(_RESIDUAL_VOLUMES),
    )
    shake_settle: float = _param(
        0.0,
        "particles whose last shake moved them less than this [voxels], nothing near them changed, "
        "sit out the next shake (0: every particle every iteration)",
        type="number",
        minimum=0,
        maximum=1,
    )
    jacobian: str = _param(
        "central",
        "finite differences of the position Jacobian: central (6 trial images) or forward (3)",
        type="string",
        enum=list(_JACOBIANS),
    )
    image_accuracy: str = _param(
        "fast",
        "quadrature of the per-particle images: fast (within 1e-4 of each image's peak) or exact",
        type="string",
        enum=list(_QUAD),
    )
    polish: int = _param(
        3,
        "final rounds moving near-focus particles to their likelihood-weighted mean position",
        type="integer",
        minimum=0,
        maximum=20,
    )
    split: int = _param(
        0,
        "rounds trying each particle brighter than split_ratio x the median as a pair (0: none)",
        type="integer",
        minimum=0,
        maximum=10,
    )
    split_penalty: float = _param(
        16.0,
        "a split must lower the residual by more than this many times its variance",
        type="number",
        minimum=0,
        maximum=1000000,
    )
    split_ratio: float = _param(
        1.3,
        "the split tries the particles brighter than this times the median intensity",
        type="number",
        minimum=0,
        maximum=100,
    )
    image_calibration: int = _param(
        0,
        "rounds calibrating the particle images (lenslet gap, blur) from the recording's own "
        "particles (0: the nominal camera's images)",
        type="integer",
        minimum=0,
        maximum=5,
    )
    batch: int = _param(
        _BATCH, "particles rendered at once (the patch memory)", config=False, type="integer", minimum=1
    )

    def __post_init__(self) -> None:
        for f in fields(self):
            _check(f.name, getattr(self, f.name), f.metadata["schema"])

    @classmethod
    def schema(cls) -> dict[str, dict[str, Any]]:
        """``{config key: JSON-schema fragment}`` of the fields that are ``reconstruct.ipr`` keys (no defaults:
        the method's ``run`` signature states them, :func:`lfstudy.reconstruct.detect_parameters`)."""
        return {f.name: dict(f.metadata["schema"]) for f in fields(cls) if f.metadata["config"]}

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """``{config key: default}`` of the fields that are ``reconstruct.ipr`` keys."""
        return {f.name: f.default for f in fields(cls) if f.metadata["config"]}

    @classmethod
    def of(cls, settings: IPRSettings | None = None, **params: Any) -> IPRSettings:
        """``settings`` (default: the defaults) with ``params`` replacing its fields.

        Raises
        ------
        ReconstructionError
            A name that is no field (listing the fields), or a value out of its range.
        """
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(params) - set(names))
        if unknown:
            raise ReconstructionError(
                f"reconstruct.ipr: unknown setting(s) {', '.join(unknown)}; the settings are {', '.join(names)}"
            )
        base = cls() if settings is None else settings
        if not isinstance(base, IPRSettings):
            raise ReconstructionError(f"reconstruct.ipr: settings = {settings!r} is no IPRSettings")
        return cls(**{**{n: getattr(base, n) for n in names}, **params})


def _check(name: str, value: Any, spec: dict[str, Any]) -> None:
    """``value`` against one field's schema fragment: its type (booleans are no numbers), finite, in range or one
    of its values; else a ReconstructionError naming ``reconstruct.ipr.<name>`` and what is allowed."""
    if "enum" in spec:
        if value not in spec["enum"]:
            allowed = ", ".join(spec["enum"])
            raise ReconstructionError(f"reconstruct.ipr.{name} = {value!r}: allowed values are {allowed}")
        return
    integer = spec["type"] == "integer"
    kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    ok = isinstance(value, kinds) and not isinstance(value, (bool, np.bool_)) and math.isfinite(value)
    lo_open = "exclusiveMinimum" in spec
    lo = spec.get("exclusiveMinimum", spec.get("minimum", -math.inf))
    hi = spec.get("maximum", math.inf)
    ok = ok and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        if not integer:  # the bounds of a real as reals: [0.0, 1.0]
            lo, hi = float(lo), float(hi)
        raise ReconstructionError(
            f"reconstruct.ipr.{name} = {value!r}: allowed range is {'(' if lo_open else '['}{lo}, {hi}]"
        )
