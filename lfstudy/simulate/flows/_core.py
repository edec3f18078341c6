"""What every flow shares: the error, the ``Flow`` protocol, vector checks and RK4 advection (sec. 4.4)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
import xarray as xr

__all__ = ["FlowError", "Flow", "integrate", "displace", "true_displacement"]


class FlowError(ValueError):
    """Bad flow parameters or input (names the field and the allowed range)."""


@runtime_checkable
class Flow(Protocol):
    """A steady velocity field in the object frame [mm per unit time].

    A flow kind is a (frozen) class whose constructor takes its parameters by
    keyword, declared in ``parameters`` (JSON-schema properties: types and
    ranges); ``name`` is its kind. ``velocity`` is vectorised: arrays of any
    (equal) shape in, three arrays of that shape out.
    """

    name: ClassVar[str]
    parameters: ClassVar[dict[str, dict[str, Any]]]

    def velocity(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


# ------------------------------------------------------------------ parameter checks
#: JSON schema of a 3-vector (centre, axis, displacement).
VEC3: dict[str, Any] = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}


def finite(kind: str, name: str, value: float, *, positive: bool = False) -> float:
    """``value`` as a float, or a FlowError naming ``kind name`` and the allowed range."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise FlowError(f"{kind} {name} = {value!r}: must be a number") from None
    if not math.isfinite(v) or (positive and v <= 0):
        raise FlowError(f"{kind} {name} = {value!r}: must be {'> 0' if positive else 'finite'}")
    return v


def vec3(kind: str, name: str, value: Sequence[float]) -> tuple[float, float, float]:
    """Three finite numbers, or a FlowError naming ``kind name``."""
    try:
        v = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        raise FlowError(f"{kind} {name} = {value!r}: need three finite numbers") from None
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise FlowError(f"{kind} {name} = {value!r}: need three finite numbers")
    return v  # type: ignore[return-value]


def unit3(kind: str, name: str, value: Sequence[float]) -> np.ndarray:
    """A direction normalised to length 1, or a FlowError for a zero or non-finite vector."""
    v = np.asarray(vec3(kind, name, value), dtype=float)
    n = float(np.linalg.norm(v))
    if n == 0:
        raise FlowError(f"{kind} {name} = {tuple(value)!r}: need a non-zero direction")
    return v / n


def axial_frame(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, center: Sequence[float], e: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position relative to ``center`` split along the unit axis ``e``.

    Returns ``(p, a, rvec)``: ``p`` (3, ...) the offset from the centre, ``a``
    its component along ``e`` and ``rvec`` (3, ...) the part perpendicular to it.
    """
    p = np.stack([np.asarray(c, dtype=float) - c0 for c, c0 in zip((x, y, z), center)])
    a = np.tensordot(e, p, axes=1)
    rvec = p - e.reshape((3,) + (1,) * a.ndim) * a
    return p, a, rvec


# ------------------------------------------------------------------ advection
def integrate(
    flow: Flow, x: np.ndarray, y: np.ndarray, z: np.ndarray, dt: float, n_steps: int = 100
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Advect points through a steady flow over ``dt`` with RK4 sub-steps.

    Replaces the thesis' Taylor series (eq. 4.37) / many small Euler steps
    with fourth-order Runge–Kutta; negative ``dt`` integrates backwards.
    """
    if not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise FlowError(f"n_steps = {n_steps!r}: must be an integer >= 1")
    if not math.isfinite(dt):
        raise FlowError(f"dt = {dt!r}: must be finite")
    p = np.stack([np.asarray(c, dtype=float).copy() for c in (x, y, z)])
    h = dt / n_steps
    f = lambda q: np.stack(flow.velocity(q[0], q[1], q[2]))  # noqa: E731
    for _ in range(int(n_steps)):
        k1 = f(p)
        k2 = f(p + 0.5 * h * k1)
        k3 = f(p + 0.5 * h * k2)
        k4 = f(p + h * k3)
        p += (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return p[0], p[1], p[2]


def displace(particles: xr.Dataset, flow: Flow, dt: float = 1.0, n_steps: int = 100) -> xr.Dataset:
    """The particle field after Δt (second exposure); intensities are kept."""
    x, y, z = integrate(flow, particles["x"].values, particles["y"].values, particles["z"].values, dt, n_steps)
    out = particles.copy(deep=True)
    out["x"].values[:] = x
    out["y"].values[:] = y
    out["z"].values[:] = z
    out.attrs.update(flow=flow.name, dt=float(dt), n_steps=int(n_steps))
    return out


def true_displacement(
    flow: Flow,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    dt: float = 1.0,
    n_steps: int = 100,
    reference: str = "midpoint",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True displacement (dx, dy, dz) [mm] attributed to points (x, y, z).

    ``reference="midpoint"`` gives the displacement of the particle whose path
    is centred on the point (X(+Δt/2) − X(−Δt/2)), which is what PIV with a
    symmetric window offset measures; ``"start"`` gives X(Δt) − X(0).
    """
    x, y, z = (np.asarray(c, dtype=float) for c in (x, y, z))
    if reference == "midpoint":
        a = integrate(flow, x, y, z, -dt / 2.0, max(1, n_steps // 2))
        b = integrate(flow, x, y, z, dt / 2.0, max(1, n_steps // 2))
    elif reference == "start":
        a = (x, y, z)
        b = integrate(flow, x, y, z, dt, n_steps)
    else:
        raise FlowError(f"reference = {reference!r}: allowed values are 'midpoint' and 'start'")
    return b[0] - a[0], b[1] - a[1], b[2] - a[2]
