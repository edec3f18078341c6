"""Known flows and particle displacement (thesis sec. 4.4).

Flows are vectorised, steady velocity fields ``flow.velocity(x, y, z)`` in the
object frame (mm per unit time). Particles are displaced over Δt by classic
fourth-order Runge–Kutta with many sub-steps (the thesis used 1,000 Euler
sub-steps; RK4 converges far faster, see ``tests/test_particles_flows.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import xarray as xr

__all__ = [
    "FlowError",
    "Flow",
    "UniformFlow",
    "HillVortex",
    "flow_from_config",
    "integrate",
    "displace",
    "true_displacement",
]


class FlowError(ValueError):
    """Bad flow parameters (names the field and the allowed range)."""


class Flow(Protocol):
    """A steady velocity field in the object frame."""

    name: str

    def velocity(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class UniformFlow:
    """Uniform velocity (sec. 4.4): every particle moves by ``velocity``·Δt.

    Parameters
    ----------
    velocity : (float, float, float)
        (u, v, w) in mm per unit time; with Δt = 1 this is the displacement.
    """

    velocity_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = "uniform"

    def __post_init__(self) -> None:
        if len(self.velocity_mm) != 3 or not all(math.isfinite(v) for v in self.velocity_mm):
            raise FlowError(f"uniform displacement = {self.velocity_mm!r}: need three finite numbers [mm]")

    def velocity(self, x, y, z):
        x = np.asarray(x, dtype=float)
        u, v, w = self.velocity_mm
        return np.full_like(x, u), np.full_like(x, v), np.full_like(x, w)


@dataclass(frozen=True)
class HillVortex:
    """Hill's spherical vortex (eqs 4.29–4.36), in the frame moving with the vortex.

    Parameters
    ----------
    radius : float
        Radius a of the vorticity-containing sphere [mm].
    u0 : float
        Induced velocity [mm per unit time]; far from the sphere the fluid
        moves at −u0 along the axis (the steady, vortex-fixed frame).
    center : (float, float, float)
        Sphere centre in the object frame [mm].
    axis : (float, float, float)
        Direction of the induced motion (normalised internally).
    """

    radius: float = 1.5
    u0: float = 1.0
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    name: str = "hill"
    _axis: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise FlowError(f"hill radius = {self.radius!r}: must be > 0 mm")
        if not math.isfinite(self.u0):
            raise FlowError(f"hill u0 = {self.u0!r}: must be finite")
        ax = np.asarray(self.axis, dtype=float)
        if ax.shape != (3,) or not np.all(np.isfinite(ax)) or np.linalg.norm(ax) == 0:
            raise FlowError(f"hill axis = {self.axis!r}: need a non-zero 3-vector")
        if len(self.center) != 3 or not all(math.isfinite(c) for c in self.center):
            raise FlowError(f"hill center = {self.center!r}: need three finite numbers [mm]")
        object.__setattr__(self, "_axis", ax / np.linalg.norm(ax))

    def velocity(self, x, y, z):
        a, u0, e = self.radius, self.u0, self._axis
        px = np.asarray(x, dtype=float) - self.center[0]
        py = np.asarray(y, dtype=float) - self.center[1]
        pz = np.asarray(z, dtype=float) - self.center[2]
        zz = px * e[0] + py * e[1] + pz * e[2]  # Z: along the induced motion
        rx, ry, rz = px - zz * e[0], py - zz * e[1], pz - zz * e[2]
        rr = np.sqrt(rx * rx + ry * ry + rz * rz)  # R: distance from the axis
        r2 = rr * rr + zz * zz
        inside = r2 <= a * a  # eqs 4.33–4.34
        u_in = 1.5 * u0 * (1.0 - (2.0 * rr * rr + zz * zz) / a**2)  # eq. 4.29
        v_in = 1.5 * u0 * zz * rr / a**2  # eq. 4.30
        with np.errstate(divide="ignore", invalid="ignore"):
            q = np.where(inside, 1.0, (a * a / np.where(r2 > 0, r2, 1.0)) ** 2.5)
        u_ex = u0 * (q * (2.0 * zz * zz - rr * rr) / (2.0 * a * a) - 1.0)  # eq. 4.31
        v_ex = 1.5 * u0 * zz * rr / a**2 * q  # eq. 4.32
        ua = np.where(inside, u_in, u_ex)  # eq. 4.35
        ur = np.where(inside, v_in, v_ex)  # eq. 4.36
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(rr > 0, 1.0 / np.where(rr > 0, rr, 1.0), 0.0)
        # Radial unit vector (rx, ry, rz)/R; on the axis the radial part is 0.
        return (ua * e[0] + ur * rx * inv, ua * e[1] + ur * ry * inv, ua * e[2] + ur * rz * inv)


def flow_from_config(spec: Mapping[str, Any]) -> UniformFlow | HillVortex:
    """Build a flow from a config entry (``kind: uniform`` or ``kind: hill``)."""
    kind = spec.get("kind")
    if kind == "uniform":
        d = spec.get("displacement")
        if d is None or len(d) != 3:
            raise FlowError(f"flow displacement = {d!r}: need [dx, dy, dz] in mm")
        return UniformFlow(tuple(float(v) for v in d))
    if kind == "hill":
        return HillVortex(
            radius=float(spec.get("radius", 1.5)),
            u0=float(spec.get("u0", 1.0)),
            center=tuple(float(v) for v in spec.get("center", (0.0, 0.0, 0.0))),
            axis=tuple(float(v) for v in spec.get("axis", (0.0, 0.0, 1.0))),
        )
    raise FlowError(f"flow kind = {kind!r}: allowed values are 'uniform' and 'hill'")


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
