"""Analytic flows with their truth: uniform, Hill's vortex, Lamb–Oseen vortex, vortex ring, channel, Blasius.

Each kind is a frozen dataclass: its fields are its config parameters (by the
same names), ``parameters`` their JSON-schema types and ranges, and
``velocity(x, y, z)`` the vectorised field in the object frame [mm per unit
time]. Fields that a config must give although the class has a default list
themselves in ``config_required``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numba
import numpy as np

from lfstudy.simulate.flows._core import VEC3, FlowError, axial_frame, finite, unit3, vec3

__all__ = [
    "UniformFlow",
    "HillVortex",
    "LambOseenVortex",
    "VortexRing",
    "ChannelFlow",
    "BlasiusBoundaryLayer",
    "blasius_solution",
]

_CENTER = {**VEC3, "description": "centre in the object frame [mm]"}


@dataclass(frozen=True)
class UniformFlow:
    """Uniform velocity (sec. 4.4): every particle moves by ``displacement``·Δt.

    Parameters
    ----------
    displacement : (float, float, float)
        (u, v, w) in mm per unit time; with Δt = 1 this is the displacement.
    """

    displacement: tuple[float, float, float] = (0.0, 0.0, 0.0)

    name: ClassVar[str] = "uniform"
    description: ClassVar[str] = "one displacement everywhere (sec. 4.4)"
    config_required: ClassVar[tuple[str, ...]] = ("displacement",)
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "displacement": {**VEC3, "description": "[dx, dy, dz] in mm per unit time, object frame"},
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "displacement", vec3("uniform", "displacement", self.displacement))

    def velocity(self, x, y, z):
        x = np.asarray(x, dtype=float)
        u, v, w = self.displacement
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
    _axis: np.ndarray = field(init=False, repr=False, compare=False)

    name: ClassVar[str] = "hill"
    description: ClassVar[str] = "Hill's spherical vortex in its own frame (eqs 4.29–4.36)"
    config_required: ClassVar[tuple[str, ...]] = ("radius", "u0")
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "radius": {"type": "number", "exclusiveMinimum": 0, "description": "sphere radius a [mm]"},
        "u0": {"type": "number", "description": "induced velocity [mm per unit time]; far field −u0 along axis"},
        "center": _CENTER,
        "axis": {**VEC3, "description": "direction of the induced motion (normalised)"},
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius", finite("hill", "radius", self.radius, positive=True))
        object.__setattr__(self, "u0", finite("hill", "u0", self.u0))
        object.__setattr__(self, "center", vec3("hill", "center", self.center))
        object.__setattr__(self, "_axis", unit3("hill", "axis", self.axis))
        object.__setattr__(self, "axis", vec3("hill", "axis", self.axis))

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


@dataclass(frozen=True)
class LambOseenVortex:
    """A Lamb–Oseen (Gaussian-core) line vortex about an arbitrary axis.

    Azimuthal velocity at distance r from the axis (Lamb 1932, *Hydrodynamics*
    §334a; Saffman 1992, *Vortex Dynamics* eq. 1.3.14 with r_c² = 4νt)::

        u_θ(r) = Γ / (2π r) · (1 − exp(−r² / r_c²))

    a solid-body core (u_θ ≈ Γ r / (2π r_c²)) turning into the potential
    vortex Γ / (2π r); the peak, 0.6382 Γ / (2π r_c), lies at r = 1.1209 r_c.
    No axial or radial velocity. Positive Γ turns right-handed about ``axis``.

    Parameters
    ----------
    circulation : float
        Γ [mm² per unit time].
    core_radius : float
        r_c [mm] (> 0).
    center : (float, float, float)
        A point of the vortex axis, object frame [mm].
    axis : (float, float, float)
        Direction of the vortex axis (normalised internally).
    """

    circulation: float
    core_radius: float
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    _axis: np.ndarray = field(init=False, repr=False, compare=False)

    name: ClassVar[str] = "lamb_oseen"
    description: ClassVar[str] = "Lamb–Oseen vortex about an arbitrary axis"
    config_required: ClassVar[tuple[str, ...]] = ()
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "circulation": {"type": "number", "description": "circulation Γ [mm² per unit time]"},
        "core_radius": {"type": "number", "exclusiveMinimum": 0, "description": "core radius r_c [mm]"},
        "center": {**VEC3, "description": "a point of the vortex axis, object frame [mm]"},
        "axis": {**VEC3, "description": "direction of the vortex axis (normalised); Γ > 0 turns right-handed"},
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "circulation", finite("lamb_oseen", "circulation", self.circulation))
        object.__setattr__(self, "core_radius", finite("lamb_oseen", "core_radius", self.core_radius, positive=True))
        object.__setattr__(self, "center", vec3("lamb_oseen", "center", self.center))
        object.__setattr__(self, "_axis", unit3("lamb_oseen", "axis", self.axis))
        object.__setattr__(self, "axis", vec3("lamb_oseen", "axis", self.axis))

    def azimuthal(self, r: np.ndarray) -> np.ndarray:
        """u_θ(r) [mm per unit time] at distance ``r`` [mm] from the axis."""
        r = np.asarray(r, dtype=float)
        return self.circulation / (2 * np.pi) * r * _core_factor(r * r, self.core_radius)

    def velocity(self, x, y, z):
        e = self._axis
        p, _, rvec = axial_frame(x, y, z, self.center, e)
        r2 = np.sum(rvec * rvec, axis=0)
        # u = Γ/(2π) (1 − exp(−r²/r_c²))/r² · (e × p): e × p is r times the azimuthal unit vector
        g = self.circulation / (2 * np.pi) * _core_factor(r2, self.core_radius)
        return (
            g * (e[1] * p[2] - e[2] * p[1]),
            g * (e[2] * p[0] - e[0] * p[2]),
            g * (e[0] * p[1] - e[1] * p[0]),
        )


def _core_factor(r2: np.ndarray, rc: float) -> np.ndarray:
    """(1 − exp(−r²/r_c²)) / r², finite (1/r_c²) on the axis."""
    s = r2 / (rc * rc)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = -np.expm1(-s) / r2
    return np.where(s > 1e-12, out, (1.0 - 0.5 * s) / (rc * rc))


# ------------------------------------------------------------------ vortex ring
_SQRT_2_PI = math.sqrt(2.0 / math.pi)


@numba.njit(cache=True, fastmath=False)
def _ring_kernel(a, r, radius, sigma, nodes_per_width, out_a, out_r):  # pragma: no cover - numba
    """Biot–Savart of a Gaussian-smoothed circular filament at (axial a, radial r), per point.

    Trapezoid rule in the filament angle φ over [0, π] (the integrand is even in
    φ in the point's own meridian plane); the node count is set per point from
    its distance to the filament, so every point's value is independent of the
    others (same bytes at any batch size or thread count).
    """
    R = radius
    for i in range(a.size):
        z = a[i]
        rr = r[i]
        d = math.sqrt((rr - R) ** 2 + z * z)
        width = math.sqrt(d * d + sigma * sigma)
        n = math.ceil(nodes_per_width * math.pi * R / width)
        n = min(max(n, 16), 1 << 16)
        h = math.pi / n
        su = 0.0
        sr = 0.0
        for k in range(n + 1):
            c = math.cos(k * h)
            s2 = rr * rr + R * R - 2.0 * rr * R * c + z * z
            rho2 = s2 / (sigma * sigma)
            if rho2 < 1e-2:  # q(ρ)/ρ³ by its series: the closed form cancels
                f = _SQRT_2_PI * (1.0 / 3.0 - rho2 / 10.0 + rho2 * rho2 / 56.0 - rho2 * rho2 * rho2 / 432.0)
            else:
                rho = math.sqrt(rho2)
                f = (math.erf(rho / math.sqrt(2.0)) - _SQRT_2_PI * rho * math.exp(-0.5 * rho2)) / (rho2 * rho)
            w = 0.5 if (k == 0 or k == n) else 1.0
            f *= w
            su += (R - rr * c) * f
            sr += z * c * f
        scale = 2.0 * h * R / (sigma * sigma * sigma)  # ∫0..2π = 2 ∫0..π; q/|x−s|³ = (q/ρ³)/σ³
        out_a[i] = scale * su
        out_r[i] = scale * sr


@dataclass(frozen=True)
class VortexRing:
    """A vortex ring: Biot–Savart of a circular filament with a Gaussian core, by quadrature.

    The vorticity is the circle of radius R convolved with a 3-D Gaussian of
    standard deviation σ = r_c/√2, so that far from the ring's curvature the
    core is a Lamb–Oseen vortex of radius r_c (:class:`LambOseenVortex`). Its
    velocity is the Biot–Savart integral over the ring with the Gaussian
    smoothing function (Winckelmans & Leonard 1993, J. Comput. Phys. 109, 247,
    eq. 20)::

        u(x) = Γ/(4π) ∮ q(|x − s|/σ) ds × (x − s) / |x − s|³,
        q(ρ) = erf(ρ/√2) − √(2/π) ρ exp(−ρ²/2)

    evaluated in each point's meridian plane by the trapezoid rule in the ring
    angle (spectrally accurate for this smooth periodic integrand; the node
    count grows as the point nears the core). The field is exactly
    divergence-free and decays as the dipole of impulse Γ π R² (Saffman 1992,
    *Vortex Dynamics* sec. 3.3). On the axis it is
    u = Γ R² q(√(R² + z²)/σ) / (2 (R² + z²)^{3/2}), the thin ring's
    Γ R²/(2 (R² + z²)^{3/2}) where R ≫ r_c.

    **Frame**: the lab frame of a ring held in place — the fluid is at rest at
    infinity and the ring does not move. A free ring would travel along its
    axis at about Γ/(4πR)(ln(8R/r_c) − 0.558) (Saffman 1970, Stud. Appl.
    Math. 49, 371); that self-induced translation is not included (for the
    ring's own frame add a uniform flow of minus that speed).

    Parameters
    ----------
    circulation : float
        Γ [mm² per unit time]; positive Γ drives the fluid through the ring
        along ``+axis``.
    radius : float
        Ring radius R [mm] (> 0).
    core_radius : float
        r_c [mm] (> 0, at most R).
    center : (float, float, float)
        Centre of the ring, object frame [mm].
    axis : (float, float, float)
        Normal of the ring's plane (normalised internally).
    """

    circulation: float
    radius: float
    core_radius: float
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    _axis: np.ndarray = field(init=False, repr=False, compare=False)

    name: ClassVar[str] = "vortex_ring"
    description: ClassVar[str] = "vortex ring with a Gaussian core, at rest (Biot–Savart by quadrature)"
    config_required: ClassVar[tuple[str, ...]] = ()
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "circulation": {"type": "number", "description": "circulation Γ [mm² per unit time]"},
        "radius": {"type": "number", "exclusiveMinimum": 0, "description": "ring radius R [mm]"},
        "core_radius": {"type": "number", "exclusiveMinimum": 0, "description": "core radius r_c [mm], ≤ R"},
        "center": {**VEC3, "description": "centre of the ring, object frame [mm]"},
        "axis": {**VEC3, "description": "normal of the ring's plane (normalised); Γ > 0 drives the fluid along it"},
    }

    #: Trapezoid nodes per width √(d² + σ²) of the integrand (d: distance to the filament).
    NODES_PER_WIDTH: ClassVar[float] = 8.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "circulation", finite("vortex_ring", "circulation", self.circulation))
        object.__setattr__(self, "radius", finite("vortex_ring", "radius", self.radius, positive=True))
        object.__setattr__(self, "core_radius", finite("vortex_ring", "core_radius", self.core_radius, positive=True))
        if self.core_radius > self.radius:
            raise FlowError(
                f"vortex_ring core_radius = {self.core_radius!r}: must be at most the ring radius ({self.radius!r} mm)"
            )
        object.__setattr__(self, "center", vec3("vortex_ring", "center", self.center))
        object.__setattr__(self, "_axis", unit3("vortex_ring", "axis", self.axis))
        object.__setattr__(self, "axis", vec3("vortex_ring", "axis", self.axis))

    def meridional(self, a: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(axial, radial) velocity at axial offset ``a`` and distance ``r`` from the axis [mm]."""
        # broadcast before flattening: a grid of any dimension (the errors stage's window centres)
        a, r = np.broadcast_arrays(np.asarray(a, dtype=float), np.asarray(r, dtype=float))
        a = np.ascontiguousarray(a.ravel())
        r = np.ascontiguousarray(r.ravel())
        ua = np.empty_like(a)
        ur = np.empty_like(a)
        sigma = self.core_radius / math.sqrt(2.0)
        _ring_kernel(a, r, self.radius, sigma, self.NODES_PER_WIDTH, ua, ur)
        k = self.circulation / (4 * np.pi)
        return k * ua, k * ur

    def velocity(self, x, y, z):
        e = self._axis
        shape = np.broadcast(np.asarray(x), np.asarray(y), np.asarray(z)).shape
        x, y, z = (np.broadcast_to(np.asarray(c, dtype=float), shape) for c in (x, y, z))
        _, a, rvec = axial_frame(x, y, z, self.center, e)
        rr = np.sqrt(np.sum(rvec * rvec, axis=0))
        ua, ur = self.meridional(a, rr)
        ua, ur = ua.reshape(shape), ur.reshape(shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(rr > 0, ur / np.where(rr > 0, rr, 1.0), 0.0)
        return tuple(ua * e[k] + inv * rvec[k] for k in range(3))


# ------------------------------------------------------------------ wall-bounded laminar flows
_WALL_NORMAL = {**VEC3, "description": "wall-normal direction (normalised)"}
_STREAMWISE = {**VEC3, "description": "flow direction (normalised), perpendicular to normal"}


def _wall_frame(kind: str, normal, direction) -> tuple[np.ndarray, np.ndarray]:
    n = unit3(kind, "normal", normal)
    t = unit3(kind, "direction", direction)
    if abs(float(n @ t)) > 1e-9:
        raise FlowError(
            f"{kind} direction = {tuple(direction)!r}: must be perpendicular to normal = {tuple(normal)!r} "
            "(the flow would cross the walls)"
        )
    return n, t


@dataclass(frozen=True)
class ChannelFlow:
    """Laminar plane channel (Poiseuille) flow between two walls.

    With d the distance from the mid-plane along the wall normal (White 2006,
    *Viscous Fluid Flow* eq. 3-41)::

        u = U_max (1 − (d/h)²)   for |d| ≤ h,   0 beyond the walls

    along ``direction``; no wall-normal or spanwise velocity. The mean
    velocity is 2/3 U_max, the wall shear rate 2 U_max/h.

    Parameters
    ----------
    u_max : float
        Centre-line velocity U_max [mm per unit time].
    half_height : float
        h: half the wall spacing [mm] (> 0).
    center : (float, float, float)
        A point of the mid-plane, object frame [mm].
    normal : (float, float, float)
        Wall-normal direction.
    direction : (float, float, float)
        Flow direction, perpendicular to ``normal``.
    """

    u_max: float
    half_height: float
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 1.0, 0.0)
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    _n: np.ndarray = field(init=False, repr=False, compare=False)
    _t: np.ndarray = field(init=False, repr=False, compare=False)

    name: ClassVar[str] = "channel"
    description: ClassVar[str] = "laminar plane channel (Poiseuille) flow"
    config_required: ClassVar[tuple[str, ...]] = ()
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "u_max": {"type": "number", "description": "centre-line velocity U_max [mm per unit time]"},
        "half_height": {"type": "number", "exclusiveMinimum": 0, "description": "half the wall spacing h [mm]"},
        "center": {**VEC3, "description": "a point of the channel's mid-plane, object frame [mm]"},
        "normal": _WALL_NORMAL,
        "direction": _STREAMWISE,
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "u_max", finite("channel", "u_max", self.u_max))
        object.__setattr__(self, "half_height", finite("channel", "half_height", self.half_height, positive=True))
        object.__setattr__(self, "center", vec3("channel", "center", self.center))
        n, t = _wall_frame("channel", self.normal, self.direction)
        object.__setattr__(self, "normal", vec3("channel", "normal", self.normal))
        object.__setattr__(self, "direction", vec3("channel", "direction", self.direction))
        object.__setattr__(self, "_n", n)
        object.__setattr__(self, "_t", t)

    def profile(self, d: np.ndarray) -> np.ndarray:
        """u(d) [mm per unit time] at distance ``d`` [mm] from the mid-plane."""
        s = np.asarray(d, dtype=float) / self.half_height
        return np.where(np.abs(s) <= 1.0, self.u_max * (1.0 - s * s), 0.0)

    def velocity(self, x, y, z):
        _, d, _ = axial_frame(x, y, z, self.center, self._n)
        u = self.profile(d)
        return u * self._t[0], u * self._t[1], u * self._t[2]


_BLASIUS_ETA_MAX = 12.0


@functools.cache
def blasius_solution() -> dict[str, Any]:
    """The Blasius similarity solution f(η), solved once (and cached).

    f''' + ½ f f'' = 0, f(0) = f'(0) = 0, f'(∞) = 1 (Blasius 1908; Schlichting
    & Gersten 2017, *Boundary-Layer Theory* eq. 6.35), by shooting on f''(0)
    with an 8th-order Runge–Kutta to η = 12, where f' − 1 < 1e-12.

    Returns
    -------
    dict
        ``eta``, ``f``, ``fp`` (f'), ``fpp`` (f'') tabulated on [0, 12],
        ``fpp0`` (f''(0) = 0.332057), ``eta99`` (f'(η99) = 0.99: δ99 =
        η99 √(νx/U) = 4.91 x/√Re_x), ``beta`` (η − f(η) far out: the
        displacement thickness δ* = β √(νx/U) = 1.7208 x/√Re_x) and
        ``fp_spline``/``f_spline`` (cubic Hermite interpolants).
    """
    from scipy.integrate import solve_ivp
    from scipy.interpolate import CubicHermiteSpline
    from scipy.optimize import brentq

    def rhs(_eta, y):
        return [y[1], y[2], -0.5 * y[0] * y[2]]

    def miss(s: float) -> float:
        sol = solve_ivp(rhs, (0.0, _BLASIUS_ETA_MAX), [0.0, 0.0, s], method="DOP853", rtol=1e-12, atol=1e-14)
        return sol.y[1, -1] - 1.0

    fpp0 = brentq(miss, 0.2, 0.5, xtol=1e-15, rtol=1e-15)
    eta = np.linspace(0.0, _BLASIUS_ETA_MAX, 2401)
    sol = solve_ivp(rhs, (0.0, _BLASIUS_ETA_MAX), [0.0, 0.0, fpp0], method="DOP853", rtol=1e-12, atol=1e-14, t_eval=eta)
    f, fp, fpp = sol.y
    fp_spline = CubicHermiteSpline(eta, fp, fpp)
    f_spline = CubicHermiteSpline(eta, f, fp)
    i = int(np.searchsorted(fp, 0.99))
    eta99 = brentq(lambda s: float(fp_spline(s)) - 0.99, eta[i - 1], eta[i], xtol=1e-14)
    return {
        "eta": eta,
        "f": f,
        "fp": fp,
        "fpp": fpp,
        "fpp0": float(fpp0),
        "eta99": float(eta99),
        "beta": float(eta[-1] - f[-1]),
        "fp_spline": fp_spline,
        "f_spline": f_spline,
    }


@dataclass(frozen=True)
class BlasiusBoundaryLayer:
    """Laminar flat-plate boundary layer (the Blasius similarity solution).

    With ξ the distance downstream of the leading edge and y the distance
    from the wall, η = y √(U∞/(ν ξ)) and (Schlichting & Gersten 2017, eqs
    6.33–6.34)::

        u = U∞ f'(η),   v = ½ √(ν U∞/ξ) (η f'(η) − f(η))

    along ``direction`` and ``normal`` (:func:`blasius_solution`). Upstream of
    the leading edge (ξ ≤ 0) the fluid moves at U∞; below the wall (y < 0) it
    is at rest. The field is exactly divergence-free; v grows as 1/√ξ
    towards the leading edge, so place the field of view well downstream of
    it. Give the viscosity ``nu``, or the thickness ``delta99`` at ``x_ref``
    (then ν = U∞ (δ99/η99)²/x_ref, η99 = 4.91).

    Parameters
    ----------
    u_inf : float
        Free-stream velocity U∞ [mm per unit time] (> 0).
    nu : float, optional
        Kinematic viscosity ν [mm² per unit time].
    delta99 : float, optional
        99 % thickness [mm] at ``x_ref`` (instead of ``nu``).
    x_ref : float, optional
        Distance downstream of the leading edge where ``delta99`` holds [mm].
    origin : (float, float, float)
        The leading edge (a point on the wall), object frame [mm].
    normal : (float, float, float)
        Wall normal, pointing into the fluid.
    direction : (float, float, float)
        Free-stream direction, perpendicular to ``normal``.
    """

    u_inf: float
    nu: float | None = None
    delta99: float | None = None
    x_ref: float | None = None
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 1.0, 0.0)
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    _nu: float = field(init=False, repr=False, compare=False)
    _n: np.ndarray = field(init=False, repr=False, compare=False)
    _t: np.ndarray = field(init=False, repr=False, compare=False)

    name: ClassVar[str] = "blasius"
    description: ClassVar[str] = "laminar flat-plate boundary layer (Blasius)"
    config_required: ClassVar[tuple[str, ...]] = ()
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "u_inf": {"type": "number", "exclusiveMinimum": 0, "description": "free-stream velocity U∞ [mm per unit time]"},
        "nu": {
            "type": ["number", "null"],
            "exclusiveMinimum": 0,
            "description": "kinematic viscosity ν [mm² per unit time]; or give delta99 and x_ref",
        },
        "delta99": {
            "type": ["number", "null"],
            "exclusiveMinimum": 0,
            "description": "99 % thickness [mm] at x_ref, instead of nu",
        },
        "x_ref": {
            "type": ["number", "null"],
            "exclusiveMinimum": 0,
            "description": "distance downstream of the leading edge where delta99 holds [mm]",
        },
        "origin": {**VEC3, "description": "the leading edge, a point on the wall, object frame [mm]"},
        "normal": {**VEC3, "description": "wall normal into the fluid (normalised)"},
        "direction": _STREAMWISE,
    }

    def __post_init__(self) -> None:
        u = finite("blasius", "u_inf", self.u_inf, positive=True)
        object.__setattr__(self, "u_inf", u)
        object.__setattr__(self, "origin", vec3("blasius", "origin", self.origin))
        n, t = _wall_frame("blasius", self.normal, self.direction)
        object.__setattr__(self, "normal", vec3("blasius", "normal", self.normal))
        object.__setattr__(self, "direction", vec3("blasius", "direction", self.direction))
        object.__setattr__(self, "_n", n)
        object.__setattr__(self, "_t", t)
        by_thickness = self.delta99 is not None or self.x_ref is not None
        if (self.nu is None) == (not by_thickness) or (by_thickness and (self.delta99 is None or self.x_ref is None)):
            raise FlowError(
                f"blasius nu = {self.nu!r}, delta99 = {self.delta99!r}, x_ref = {self.x_ref!r}: give either nu "
                "(> 0 mm² per unit time) or both delta99 and x_ref (> 0 mm)"
            )
        if self.nu is not None:
            nu = finite("blasius", "nu", self.nu, positive=True)
        else:
            d99 = finite("blasius", "delta99", self.delta99, positive=True)
            xr_ = finite("blasius", "x_ref", self.x_ref, positive=True)
            nu = u * (d99 / blasius_solution()["eta99"]) ** 2 / xr_
        object.__setattr__(self, "_nu", nu)

    @property
    def viscosity(self) -> float:
        """ν [mm² per unit time] (given, or from ``delta99`` at ``x_ref``)."""
        return self._nu

    def thickness(self, xi: np.ndarray | float) -> np.ndarray:
        """δ99 [mm] at distance ``xi`` downstream of the leading edge."""
        return blasius_solution()["eta99"] * np.sqrt(self._nu * np.asarray(xi, dtype=float) / self.u_inf)

    def velocity(self, x, y, z):
        sol = blasius_solution()
        p = np.stack([np.asarray(c, dtype=float) - c0 for c, c0 in zip((x, y, z), self.origin)])
        xi = np.tensordot(self._t, p, axes=1)
        yw = np.tensordot(self._n, p, axes=1)
        U, nu = self.u_inf, self._nu
        inside = (xi > 0) & (yw >= 0)
        xs = np.where(inside, xi, 1.0)
        eta = np.where(inside, yw, 0.0) * np.sqrt(U / (nu * xs))
        far = eta >= _BLASIUS_ETA_MAX
        ec = np.minimum(eta, _BLASIUS_ETA_MAX)
        fp = np.where(far, 1.0, sol["fp_spline"](ec))
        f = np.where(far, eta - sol["beta"], sol["f_spline"](ec))
        u = np.where(inside, U * fp, np.where(yw >= 0, U, 0.0))
        v = np.where(inside, 0.5 * np.sqrt(nu * U / xs) * (eta * fp - f), 0.0)
        return tuple(u * self._t[k] + v * self._n[k] for k in range(3))
