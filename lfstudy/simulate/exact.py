"""Exact plenoptic rendering: the expected raw image, without Monte-Carlo rays (thesis sec. 4.1–4.3).

:func:`render_exact` computes, for every pixel, the *expected value* of the
Monte-Carlo image of :func:`lfstudy.simulate.raytrace.render` (the same camera
model, conventions and outputs), so the two are interchangeable and directly
comparable. There is no random number and no ray: the image is deterministic
and bit-identical at any thread count.

The model (the ray kernel of :mod:`~lfstudy.simulate.raytrace`)
----------------------------------------------------------------
A ray from a particle at depth ``d = so + z`` to the aperture point ``a``
(uniform over the main-lens disc of radius R) has the slope ``t = a·c1 + t0``
(eqs 4.2–4.3, ``c1 = 1/d − 1/fm``, ``t0 = −p/d``) and reaches the lenslet plane
at ``L = a·(1 + si·c1) + si·t0``. The main-lens diffraction (sec. 4.2.3) adds a
Gaussian shift of σm (``camera.sigma_lenslet_plane``) to ``L`` before the
lenslet is chosen (eqs 4.10–4.11); the ray then lands at ``c_k + fl·t`` behind
lenslet k (eq. 4.4) plus a Gaussian shift of σl (``camera.sigma_sensor_plane``).

Both positions are affine in ``a``. Behind lenslet k the ray density on the
sensor is therefore uniform over a disc D_k of radius ``ρ = R·fl·|c1|`` centred
at ``C_k = c_k + fl·t0`` (the image of the aperture), weighted by the
probability ``M_k(s)`` that the lenslet-plane point of the ray, blurred by σm,
falls in lenslet k's square. ``M_k`` is a product of two erf windows (one per
grid axis) in ``u = L0 + κ·(s − C_k)``, ``κ = (1 + si·c1)/(fl·c1)``: the
lenslet's square seen from the sensor is the preimage of that square, with
edges blurred by ``σs = σm/|κ|``. The expected value of pixel P is

    E_P = W · (1/πρ²) Σ_k ∫_{D_k} M_k(s) · B_P(s) ds,

with ``B_P = 1_P ∗ G(σl)``, the pixel's box blurred by the sensor-plane
diffraction (eq. 4.15 with sec. 4.2.3), and ``W = intensity · n·Ω/Ω_ref``
(eq. 4.14 generalised, :func:`~lfstudy.simulate.raytrace.solid_angle`). In
focus (``1 + si·c1 = 0``) the whole aperture lands in one lenslet-plane point
and ``M_k`` is a constant; a lenslet k whose square is far from the disc's
rim is "interior" and its image is separable.

How the integral is evaluated
-----------------------------
For an unrotated lenslet grid both ``M_k`` and ``B_P`` are products of a
function of x and one of y, so the only non-separable element is the disc.
Green's theorem turns the area integral over ``D_k ∩ S`` (S: the lenslet's
square widened by its blur) into line integrals along its boundary, using

* x-antiderivatives (``∮ U(x) v(y) dy``) where the x-window is flat, and
* y-antiderivatives (``−∮ u(x) V(y) dx``) inside the σs-band of a vertical
  square edge, with the two regions joined along vertical cut lines.

Every antiderivative that is needed is a closed form in Φ and the integrated
normal ``IΦ(u) = u·Φ(u) + φ(u)``: the product of a σs-blurred edge and a
σl-blurred pixel edge integrated over the whole line is a single blurred edge
of ``σc = sqrt(σs² + σl²)``. Straight segments are done exactly; along the
circular arcs a fixed Gauss–Legendre rule is used on panels that break at
every pixel edge, band edge and band centre the arc crosses and are at most
``_PANEL`` blur widths long. Only where the arc passes within 6σs of a
*corner* of the blurred square (both bands at once) is an antiderivative of a
product of two blurred edges needed; it is then integrated numerically with
Gauss–Legendre panels of the same size.

Error budget: Gaussian tails beyond ``_K = 6`` σ are dropped (each ≤ 1e-9 of
the local value); Φ is evaluated with a Chebyshev fit of erfcx (relative
error ≤ 2e-14); the arc and corner quadratures are accurate to about 1e-7 of a
pixel's value (the tests compare with an independent brute-force quadrature).
The total of every particle equals ``W`` minus what misses the lenslet array
or the sensor, to ~1e-9.

Lenslet grids rotated against the sensor break the separability. In focus
(``M_k`` constant, which includes the calibration pinhole image) they are
handled exactly; out of focus they are refused (use the Monte-Carlo tracer).

Determinism and memory
----------------------
Particles are sorted by the sensor row of their image and cut into a fixed
number of chunks (``n_chunks``); each chunk is rendered, in that order, into
its own float64 buffer that spans only the rows it can reach, and the buffers
are added in chunk order. The result depends on ``n_chunks``, never on the
number of threads, and the memory is about one image plus the particle arrays.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import xarray as xr
from numba import njit, prange
from tqdm.auto import tqdm

from lfstudy.optics import PlenopticCamera
from lfstudy.simulate.raytrace import (
    DEFAULT_CHUNKS,
    RaytraceError,
    _check_rays,
    _particle_arrays,
    _sensor_coords,
    ray_counts,
    solid_angle,
)

__all__ = ["render_exact", "render_pinhole_exact", "exact_memory_estimate"]

_PIECES = 16  # kernel calls per render (progress granularity; does not change the result)
_K = 6.0  # Gaussian support cut-off in σ (tails beyond: Φ(−6) ≈ 1e-9)
_NG = 8  # Gauss–Legendre nodes per arc panel
_NGN = 10  # Gauss–Legendre nodes per panel of the numeric (corner) antiderivatives
_PANEL = 4.0  # longest panel, in units of the narrowest blur active on it
_EPS_FOCUS = 1e-9  # spot radius / σm below which M_k is a constant over the aperture image
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi

_GL_X, _GL_W = np.polynomial.legendre.leggauss(_NG)
_GN_X, _GN_W = np.polynomial.legendre.leggauss(_NGN)
_G4_X, _G4_W = np.polynomial.legendre.leggauss(4)

# ------------------------------------------------------------------ Φ, φ and IΦ
# erfcx(x) = exp(x²)·erfc(x) on 0 <= x <= 6.1 as a Chebyshev series in
# s = 2(t − t0)/(1 − t0) − 1, t = 2/(2 + x), t0 = 2/8.1 (our own least-squares
# fit at 4000 Chebyshev points of scipy.special.erfcx; relative error
# <= 1.1e-14). With it Φ and φ cost one exp together and vectorise.
_ERFCX = np.array(
    [
        0.46141236735657853,
        0.4465892571854806,
        0.08441915996399187,
        0.007857876146952885,
        -0.00018721817076624366,
        -9.572323628135069e-05,
        2.9675440026967953e-06,
        1.4590791811506852e-06,
        -1.3094059949446722e-07,
        -1.9333374662626875e-08,
        4.53438549424818e-09,
        -4.060220671570851e-11,
        -1.0391060480156449e-10,
        1.4793713022033425e-11,
        5.97299256423912e-13,
        -4.963884385864078e-13,
        6.492308092361736e-14,
        3.0982026232525966e-15,
        -2.5421149729252076e-15,
        3.872753279065746e-16,
    ]
)
_T0 = 2.0 / 8.1
_TS = 2.0 / (1.0 - _T0)
_UMAX = 8.6  # |u| beyond which Φ(u) is 0 or 1 to double precision (Φ(−8.6) < 4e-18)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@njit(cache=True)
def _phi2(u):  # pragma: no cover - jitted
    """(Φ(u), φ(u)): the standard normal CDF and density, one exp for both."""
    a = abs(u)
    if a > _UMAX:
        return (0.0 if u < 0.0 else 1.0), 0.0
    s = (2.0 / (2.0 + a * _INV_SQRT2) - _T0) * _TS - 1.0
    b1 = 0.0
    b2 = 0.0
    for k in range(_ERFCX.size - 1, 0, -1):  # Clenshaw
        b0 = 2.0 * s * b1 - b2 + _ERFCX[k]
        b2 = b1
        b1 = b0
    e = math.exp(-0.5 * u * u)
    q = 0.5 * (s * b1 - b2 + _ERFCX[0]) * e  # Φ(−|u|)
    return (q if u < 0.0 else 1.0 - q), e * _INV_SQRT_2PI


@njit(cache=True)
def _cdf(num, sig):  # pragma: no cover - jitted
    """P(num + sig·Z > 0) = Φ(num/sig); a step (½ at 0) for sig = 0."""
    if sig > 0.0:
        u = num / sig
        if u > _UMAX:
            return 1.0
        if u < -_UMAX:
            return 0.0
        return _phi2(u)[0]
    return 1.0 if num > 0.0 else (0.5 if num == 0.0 else 0.0)


@njit(cache=True)
def _ramp(num, sig):  # pragma: no cover - jitted
    """∫_{−∞}^{num} Φ(t/sig) dt = sig·IΦ(num/sig); max(num, 0) for sig = 0."""
    if sig > 0.0:
        u = num / sig
        if u > _UMAX:
            return num
        if u < -_UMAX:
            return 0.0
        p, d = _phi2(u)
        return sig * (u * p + d)
    return num if num > 0.0 else 0.0


@njit(cache=True)
def _iphi_diff(a, b):  # pragma: no cover - jitted
    """IΦ(b) − IΦ(a) = ∫_a^b Φ, without cancellation when b − a is small (4-point Gauss–Legendre)."""
    h = 0.5 * (b - a)
    if abs(h) < 0.125:
        m = 0.5 * (a + b)
        acc = 0.0
        for i in range(4):
            acc += _G4_W[i] * _phi2(m + h * _G4_X[i])[0]
        return acc * h
    return _ramp(b, 1.0) - _ramp(a, 1.0)


@njit(cache=True)
def _window(u, e1, e2, a1, a2, sm):  # pragma: no cover - jitted
    """P(u + σm·Z ∈ [e1, e2]): the lenslet-plane membership along one grid axis (inactive edges: no cut)."""
    hi = _cdf(e2 - u, sm) if a2 else 1.0
    lo = _cdf(e1 - u, sm) if a1 else 0.0
    return hi - lo


# ------------------------------------------------------------- one blurred axis
# Axis descriptor (one float64 row per axis, x then y), all in sensor mm unless noted.
_A_C, _A_G0, _A_E1, _A_E2, _A_A1, _A_A2 = range(6)  # disc centre; spot centre, edges (lenslet units); active
_A_LO, _A_HI, _A_B, _A_MRG = range(6, 10)  # sensor-frame window edges (±inf if inactive), band half-width, merged
_A_ELO, _A_EHI, _A_SLO = range(10, 13)  # lenslet edges giving LO and HI; sign of κ
_A_E0, _A_N = range(13, 15)  # first pixel edge of the patch, number of cells
_A_SIZE = 15

# Shared scalars: κ, σm, σl, pixel pitch, cut-off K·σl, |κ|, S = sqrt(σm² + κ²σl²), disc radius ρ
_S_KAP, _S_SM, _S_SL, _S_PP, _S_KSL, _S_AK, _S_S, _S_RHO = range(8)
_S_SIZE = 8

_LOW, _BLO, _MID, _BHI, _HIGH = 0, 1, 2, 3, 4

# Geometry vector layout of the particle kernel.
_G_SO, _G_SI, _G_FM, _G_FL, _G_R, _G_PL, _G_PP, _G_HW, _G_HH = range(9)
_G_OX, _G_OY, _G_COS, _G_SIN, _G_NLX, _G_NLY, _G_SM, _G_SL, _G_NROW, _G_NCOL = range(9, 19)
_G_SIZE = 19


@njit(cache=True)
def _zone(ax, v):  # pragma: no cover - jitted
    """Zone of coordinate v on an axis: below the window, in a band (lo/hi), flat middle, above."""
    lo = ax[_A_LO]
    hi = ax[_A_HI]
    b = ax[_A_B]
    if v <= lo - b:
        return _LOW
    if v >= hi + b:
        return _HIGH
    if ax[_A_MRG] != 0.0:
        return _BLO  # one merged band
    if v < lo + b:
        return _BLO
    if v > hi - b:
        return _BHI
    return _MID


@njit(cache=True)
def _m(ax, sc, v):  # pragma: no cover - jitted
    """The lenslet window along this axis at sensor coordinate v (computed in lenslet units)."""
    u = ax[_A_G0] + sc[_S_KAP] * (v - ax[_A_C])
    return _window(u, ax[_A_E1], ax[_A_E2], ax[_A_A1] != 0.0, ax[_A_A2] != 0.0, sc[_S_SM])


@njit(cache=True)
def _lam(ax, sc, x0, x1, e, q):  # pragma: no cover - jitted
    """∫_{x0}^{x1} Φ((x − q)/σc) dx: a σs-blurred lower window edge q (lenslet edge e) seen
    through the σl blur of a pixel [x0, x1] (σc = sqrt(σs² + σl²)); robust as κ → 0."""
    s = sc[_S_S]
    if s > 0.0:
        ak = sc[_S_AK]
        off = (e - ax[_A_G0]) * ax[_A_SLO]
        a0 = (ak * (x0 - ax[_A_C]) - off) / s
        a1 = (ak * (x1 - ax[_A_C]) - off) / s
        return (s / ak) * _iphi_diff(a0, a1)
    lo = max(q, x0)
    return x1 - lo if x1 > lo else 0.0


@njit(cache=True)
def _axis_tables(ax, sc, lamlo, full):  # pragma: no cover - jitted
    """Per cell k: Λ_k(lo) (the blurred lower edge seen through the cell) and the full integral
    ∫ m·b_k (the cell's whole share of the window)."""
    pp = sc[_S_PP]
    n = int(ax[_A_N])
    for k in range(n):
        x0 = ax[_A_E0] + k * pp
        x1 = x0 + pp
        ll = pp if ax[_A_LO] == -np.inf else _lam(ax, sc, x0, x1, ax[_A_ELO], ax[_A_LO])
        lh = 0.0 if ax[_A_HI] == np.inf else _lam(ax, sc, x0, x1, ax[_A_EHI], ax[_A_HI])
        lamlo[k] = ll
        full[k] = ll - lh


@njit(cache=True)
def _b(ax, sc, k, v):  # pragma: no cover - jitted
    """b_k(v): the σl-blurred box of cell k at v."""
    x0 = ax[_A_E0] + k * sc[_S_PP]
    return _cdf(x0 + sc[_S_PP] - v, sc[_S_SL]) - _cdf(x0 - v, sc[_S_SL])


@njit(cache=True)
def _num_int(ax, sc, k, a, b):  # pragma: no cover - jitted
    """∫_a^b m(x)·b_k(x) dx by Gauss–Legendre panels broken at the cell edges and window edges."""
    if b <= a:
        return 0.0
    pp = sc[_S_PP]
    x0 = ax[_A_E0] + k * pp
    brk = np.empty(6)
    nb = 0
    for v in (x0, x0 + pp, ax[_A_LO], ax[_A_HI]):
        if a < v < b:
            brk[nb] = v
            nb += 1
    brk[nb] = b
    nb += 1
    brk[:nb].sort()
    sig = sc[_S_SL]
    ssx = sc[_S_SM] / sc[_S_AK] if sc[_S_AK] > 0.0 else 0.0
    if ssx > 0.0 and (sig <= 0.0 or ssx < sig):
        sig = ssx
    lmax = _PANEL * sig if sig > 0.0 else np.inf
    acc = 0.0
    lo = a
    for i in range(nb):
        hi = brk[i]
        m = 1 if not (hi - lo > lmax) else math.ceil((hi - lo) / lmax)
        step = (hi - lo) / m
        for j in range(m):
            c = lo + (j + 0.5) * step
            h = 0.5 * step
            for g in range(_NGN):
                x = c + h * _GN_X[g]
                acc += _GN_W[g] * h * _m(ax, sc, x) * _b(ax, sc, k, x)
        lo = hi
    return acc


@njit(cache=True)
def _u_partial(ax, sc, lamlo, full, k, v, zone):  # pragma: no cover - jitted
    """U_k(v) = ∫_{−∞}^{v} m·b_k for a cell k whose blurred support contains v."""
    pp = sc[_S_PP]
    ksl = sc[_S_KSL]
    sl = sc[_S_SL]
    x0 = ax[_A_E0] + k * pp
    if zone == _LOW:
        return 0.0
    if zone == _HIGH:
        return full[k]
    if zone == _MID:
        # The window is flat (1) beyond the lower band: Λ_k(lo) − ∫_v^∞ b_k.
        return lamlo[k] - pp + _ramp(v - x0, sl) - _ramp(v - x0 - pp, sl)
    # Inside a band: closed form at the band's start, numeric across the band.
    b = ax[_A_B]
    if zone == _BHI:
        a0 = ax[_A_HI] - b
        if x0 - ksl > a0:
            base = 0.0
        elif x0 + pp + ksl < a0:
            base = full[k]
        else:
            base = lamlo[k] - pp + _ramp(a0 - x0, sl) - _ramp(a0 - x0 - pp, sl)
    else:
        a0 = ax[_A_LO] - b
        base = 0.0
    return base + _num_int(ax, sc, k, max(a0, x0 - ksl), min(v, x0 + pp + ksl))


# ---------------------------------------------------------------- patch assembly
@njit(cache=True)
def _cells_near(ax, sc, v):  # pragma: no cover - jitted
    """(last cell whose blurred support lies wholly below v, last cell whose support reaches v)."""
    pp = sc[_S_PP]
    ksl = sc[_S_KSL]
    n = int(ax[_A_N])
    kfull = math.floor((v - ksl - ax[_A_E0]) / pp) - 1
    kpart = math.floor((v + ksl - ax[_A_E0]) / pp)
    if kfull > n - 1:
        kfull = n - 1
    if kpart > n - 1:
        kpart = n - 1
    if kfull < -1:
        kfull = -1
    return kfull, kpart


@njit(cache=True)
def _add(direct, swap, i_sec, i_pri, val):  # pragma: no cover - jitted
    if swap:
        direct[i_pri, i_sec] += val
    else:
        direct[i_sec, i_pri] += val


@njit(cache=True)
def _node(pri, sec, sc, lam_p, full_p, direct, carry, swap, vp, vs, w, zp, sec_window):  # pragma: no cover
    """One boundary node of ∮ U_p(vp)·m_s(vs)·b_j(vs) d(vs-direction): cells of the primary axis
    wholly below vp take their full share through the carry (summed at the end)."""
    if sec_window:
        w *= _m(sec, sc, vs)
        if w == 0.0:
            return
    pp = sc[_S_PP]
    ksl = sc[_S_KSL]
    ns = int(sec[_A_N])
    j0 = math.floor((vs - ksl - sec[_A_E0]) / pp)
    j1 = math.floor((vs + ksl - sec[_A_E0]) / pp)
    if j0 < 0:
        j0 = 0
    if j1 > ns - 1:
        j1 = ns - 1
    kfull, kpart = _cells_near(pri, sc, vp)
    for j in range(j0, j1 + 1):
        g = w * _b(sec, sc, j, vs)
        if g == 0.0:
            continue
        if kfull >= 0:
            _add(carry, swap, j, kfull, g)
        for k in range(kfull + 1, kpart + 1):
            u = _u_partial(pri, sc, lam_p, full_p, k, vp, zp)
            if u != 0.0:
                _add(direct, swap, j, k, g * u)


@njit(cache=True)
def _cut(pri, sec, sc, lam_p, full_p, lam_s, full_s, direct, carry, swap, v, s0, s1, sign):  # pragma: no cover
    """A straight segment at primary coordinate v from s0 to s1 along the secondary axis:
    sign·U_p(v)·[V_s(s1) − V_s(s0)] for every cell pair."""
    pp = sc[_S_PP]
    ksl = sc[_S_KSL]
    ns = int(sec[_A_N])
    zp = _zone(pri, v)
    z0 = _zone(sec, s0)
    z1 = _zone(sec, s1)
    kfull, kpart = _cells_near(pri, sc, v)
    if zp == _LOW:
        return
    j0 = math.floor((s0 - ksl - sec[_A_E0]) / pp)
    j1 = math.floor((s1 + ksl - sec[_A_E0]) / pp)
    if j0 < 0:
        j0 = 0
    if j1 > ns - 1:
        j1 = ns - 1
    k_lo_full = kfull
    if zp == _HIGH:  # every cell takes its full share
        k_lo_full = kpart = int(pri[_A_N]) - 1
    for j in range(j0, j1 + 1):
        y0 = sec[_A_E0] + j * pp
        v1 = _v_at(sec, sc, lam_s, full_s, j, s1, z1, y0)
        v0 = _v_at(sec, sc, lam_s, full_s, j, s0, z0, y0)
        dv = sign * (v1 - v0)
        if dv == 0.0:
            continue
        if k_lo_full >= 0:
            _add(carry, swap, j, k_lo_full, dv)
        for k in range(k_lo_full + 1, kpart + 1):
            u = _u_partial(pri, sc, lam_p, full_p, k, v, zp)
            if u != 0.0:
                _add(direct, swap, j, k, dv * u)


@njit(cache=True)
def _v_at(ax, sc, lamv, fullv, j, v, zone, y0):  # pragma: no cover - jitted
    """V_j(v) = ∫_{−∞}^{v} m·b_j for any cell j (0 wholly above v, full wholly below)."""
    ksl = sc[_S_KSL]
    if y0 - ksl > v:
        return 0.0
    if y0 + sc[_S_PP] + ksl < v:
        return fullv[j]
    return _u_partial(ax, sc, lamv, fullv, j, v, zone)


@njit(cache=True)
def _circle_angle_x(v, cx, rho, upper):  # pragma: no cover - jitted
    w = min(1.0, max(-1.0, (v - cx) / rho))
    a = math.acos(w)
    return a if upper else _TWO_PI - a


@njit(cache=True)
def _circle_angle_y(v, cy, rho, right):  # pragma: no cover - jitted
    w = min(1.0, max(-1.0, (v - cy) / rho))
    a = math.asin(w)
    if right:
        return a if a >= 0.0 else a + _TWO_PI
    return math.pi - a


@njit(cache=True)
def _arc(ax, ay, sc, lamx, fullx, lamy, fully, direct, carry_x, carry_y, ta, tb, brk):  # pragma: no cover
    """Gauss–Legendre nodes of one arc piece [ta, tb] (monotone in x and y, in one zone pair).

    In the flat middle of the x-window the node integrates U_x(X)·m_y(Y)·b_j(Y) dY (x-
    antiderivative); inside a σs-band of a vertical edge it integrates −u_k(X)·V_y(Y) dX
    (y-antiderivative). Panels break at every pixel edge and band centre the arc crosses.
    """
    rho = sc[_S_RHO]
    cx = ax[_A_C]
    cy = ay[_A_C]
    tm = 0.5 * (ta + tb)
    zx = _zone(ax, cx + rho * math.cos(tm))
    zy = _zone(ay, cy + rho * math.sin(tm))
    if min(zx, zy) == _LOW or max(zx, zy) == _HIGH:
        return  # outside the blurred square: no light of this lenslet
    form_a = zx == _MID
    upper = tm < math.pi
    right = tm < _HALF_PI or tm > 3.0 * _HALF_PI
    pp = sc[_S_PP]
    nb = 0
    xa = cx + rho * math.cos(ta)
    xb = cx + rho * math.cos(tb)
    x_lo, x_hi = min(xa, xb), max(xa, xb)
    ya = cy + rho * math.sin(ta)
    yb = cy + rho * math.sin(tb)
    y_lo, y_hi = min(ya, yb), max(ya, yb)
    for k in range(int(ax[_A_N]) + 1):
        v = ax[_A_E0] + k * pp
        if x_lo < v < x_hi:
            brk[nb] = _circle_angle_x(v, cx, rho, upper)
            nb += 1
    for k in range(int(ay[_A_N]) + 1):
        v = ay[_A_E0] + k * pp
        if y_lo < v < y_hi:
            brk[nb] = _circle_angle_y(v, cy, rho, right)
            nb += 1
    for v in (ax[_A_LO], ax[_A_HI]):
        if x_lo < v < x_hi:
            brk[nb] = _circle_angle_x(v, cx, rho, upper)
            nb += 1
    for v in (ay[_A_LO], ay[_A_HI]):
        if y_lo < v < y_hi:
            brk[nb] = _circle_angle_y(v, cy, rho, right)
            nb += 1
    brk[nb] = tb
    nb += 1
    brk[:nb].sort()
    # Longest panel: _PANEL widths of the narrowest blur acting here.
    sig = sc[_S_SL]
    if zx != _MID or zy != _MID:
        ss = sc[_S_SM] / sc[_S_AK] if sc[_S_AK] > 0.0 else 0.0
        if ss > 0.0 and (sig <= 0.0 or ss < sig):
            sig = ss
    lmax = _PANEL * sig / rho if sig > 0.0 else np.inf  # in radians
    t0 = ta
    for i in range(nb):
        t1 = min(max(brk[i], t0), tb)
        if t1 <= t0:
            continue
        m = 1 if not (t1 - t0 > lmax) else math.ceil((t1 - t0) / lmax)
        step = (t1 - t0) / m
        for p in range(m):
            c = t0 + (p + 0.5) * step
            h = 0.5 * step
            for q in range(_NG):
                th = c + h * _GL_X[q]
                cs = math.cos(th)
                sn = math.sin(th)
                wq = _GL_W[q] * h * rho
                if form_a:  # ∮ U(x) v(y) dy, dy = ρ cos θ dθ
                    _node(
                        ax,
                        ay,
                        sc,
                        lamx,
                        fullx,
                        direct,
                        carry_x,
                        False,
                        cx + rho * cs,
                        cy + rho * sn,
                        wq * cs,
                        _MID,
                        zy != _MID,
                    )
                else:  # −∮ u(x) V(y) dx, dx = −ρ sin θ dθ
                    _node(
                        ay, ax, sc, lamy, fully, direct, carry_y, True, cy + rho * sn, cx + rho * cs, wq * sn, zy, True
                    )
        t0 = t1


@njit(cache=True)
def _setup_axis(ax, c, g0, e1, e2, a1, a2, kap, bhalf):  # pragma: no cover - jitted
    """Fill an axis descriptor: the lenslet window [e1, e2] (lenslet units) seen on the sensor."""
    ax[_A_C] = c
    ax[_A_G0] = g0
    ax[_A_E1] = e1
    ax[_A_E2] = e2
    ax[_A_A1] = 1.0 if a1 else 0.0
    ax[_A_A2] = 1.0 if a2 else 0.0
    if kap > 0.0:  # lenslet-low edge maps to the sensor-low edge
        elo, alo, ehi, ahi, sgn = e1, a1, e2, a2, 1.0
    else:  # κ < 0: the image of the window is flipped
        elo, alo, ehi, ahi, sgn = e2, a2, e1, a1, -1.0
    ax[_A_ELO] = elo
    ax[_A_EHI] = ehi
    ax[_A_SLO] = sgn
    ax[_A_LO] = c + (elo - g0) / kap if alo else -np.inf
    ax[_A_HI] = c + (ehi - g0) / kap if ahi else np.inf
    ax[_A_B] = bhalf
    ax[_A_MRG] = 1.0 if (alo and ahi and ax[_A_HI] - bhalf <= ax[_A_LO] + bhalf) else 0.0


@njit(cache=True)
def _lenslet(
    ax, ay, sc, interior, geo, lamx, fullx, lamy, fully, direct, carry_x, carry_y, pcs, brk, buf, r0, r1, fac
):  # pragma: no cover
    """Render one lenslet's share of one particle into the chunk buffer ``buf`` (rows r0..r1).

    Returns (total of the patch, part written on the sensor, part outside the chunk's rows).
    """
    pp = geo[_G_PP]
    hw = geo[_G_HW]
    hh = geo[_G_HH]
    ncol = int(geo[_G_NCOL])
    nrow = int(geo[_G_NROW])
    ksl = sc[_S_KSL]
    rho = sc[_S_RHO]
    cx = ax[_A_C]
    cy = ay[_A_C]
    bx = ax[_A_B]
    by = ay[_A_B]
    x_a = max(cx - rho, ax[_A_LO] - bx) - ksl
    x_b = min(cx + rho, ax[_A_HI] + bx) + ksl
    y_a = max(cy - rho, ay[_A_LO] - by) - ksl
    y_b = min(cy + rho, ay[_A_HI] + by) + ksl
    if x_b <= x_a or y_b <= y_a:
        return 0.0, 0.0, 0.0
    ca = math.floor((x_a + hw) / pp)
    cb = math.floor((x_b + hw) / pp)
    rb = math.floor((hh - y_a) / pp)  # lowest row (largest index)
    ra = math.floor((hh - y_b) / pp)
    nx = cb - ca + 1
    ny = rb - ra + 1
    psz = direct.shape[0]
    if nx > psz or ny > psz:
        return 0.0, 0.0, -1.0  # patch larger than the scratch (a bug: flagged, never silent)
    ax[_A_E0] = -hw + ca * pp
    ax[_A_N] = nx
    ay[_A_E0] = hh - (rb + 1) * pp
    ay[_A_N] = ny
    _axis_tables(ax, sc, lamx, fullx)
    _axis_tables(ay, sc, lamy, fully)
    if interior:  # the blurred square lies inside the aperture image: separable
        for j in range(ny):
            for k in range(nx):
                direct[j, k] = fully[j] * fullx[k]
    else:
        # Arc pieces: break the circle at the zone boundaries and the extremes.
        nb = 0
        for t in (0.0, _HALF_PI, math.pi, 3.0 * _HALF_PI):
            pcs[nb] = t
            nb += 1
        for a in range(2):
            axd = ax if a == 0 else ay
            c0 = cx if a == 0 else cy
            lo = axd[_A_LO]
            hi = axd[_A_HI]
            b = axd[_A_B]
            mrg = axd[_A_MRG] != 0.0
            for v in (lo - b, lo + b, hi - b, hi + b):
                if mrg and (v == lo + b or v == hi - b):
                    continue
                if abs(v - c0) < rho:
                    w = (v - c0) / rho
                    if a == 0:
                        t = math.acos(w)
                        pcs[nb] = t
                        pcs[nb + 1] = _TWO_PI - t
                    else:
                        t = math.asin(w)
                        pcs[nb] = t if t >= 0.0 else t + _TWO_PI
                        pcs[nb + 1] = math.pi - t
                    nb += 2
        pcs[nb] = _TWO_PI
        nb += 1
        pcs[:nb].sort()
        for i in range(nb - 1):
            if pcs[i + 1] > pcs[i]:
                _arc(ax, ay, sc, lamx, fullx, lamy, fully, direct, carry_x, carry_y, pcs[i], pcs[i + 1], brk)
        # Vertical cuts between the flat middle (x-antiderivative) and the bands (y-antiderivative).
        if ax[_A_MRG] == 0.0:
            for v, sign in ((ax[_A_LO] + bx, -1.0), (ax[_A_HI] - bx, 1.0)):
                if abs(v - cx) < rho:
                    h = math.sqrt(rho * rho - (v - cx) ** 2)
                    s0 = max(cy - h, ay[_A_LO] - by)
                    s1 = min(cy + h, ay[_A_HI] + by)
                    if s1 > s0:
                        _cut(ax, ay, sc, lamx, fullx, lamy, fully, direct, carry_x, False, v, s0, s1, sign)
        # The top edge of the blurred square inside the bands (y-antiderivative: V is full there).
        y0 = ay[_A_HI] + by
        if abs(y0 - cy) < rho:
            hx = math.sqrt(rho * rho - (y0 - cy) ** 2)
            lo = ax[_A_LO]
            hi = ax[_A_HI]
            for band in range(2):
                if ax[_A_MRG] != 0.0:
                    if band == 1:
                        break
                    b0, b1 = lo - bx, hi + bx
                elif band == 0:
                    b0, b1 = lo - bx, lo + bx
                else:
                    b0, b1 = hi - bx, hi + bx
                if not (b1 > b0) or b0 == -np.inf or b1 == np.inf:
                    continue
                xl = max(b0, cx - hx)
                xr = min(b1, cx + hx)
                if xr > xl:
                    _cut(ay, ax, sc, lamy, fully, lamx, fullx, direct, carry_y, True, y0, xl, xr, 1.0)
        # Carries: cells wholly below a node take their full share.
        for j in range(ny):
            acc = 0.0
            for k in range(nx - 1, -1, -1):
                acc += carry_x[j, k]
                carry_x[j, k] = 0.0
                direct[j, k] += fullx[k] * acc
        for k in range(nx):
            acc = 0.0
            for j in range(ny - 1, -1, -1):
                acc += carry_y[j, k]
                carry_y[j, k] = 0.0
                direct[j, k] += fully[j] * acc
    total = 0.0
    inside = 0.0
    spill = 0.0
    for j in range(ny):
        row = rb - j
        for k in range(nx):
            val = direct[j, k] * fac
            direct[j, k] = 0.0
            total += val
            col = ca + k
            if 0 <= row < nrow and 0 <= col < ncol:
                if r0 <= row <= r1:
                    buf[(row - r0) * ncol + col] += val
                    inside += val
                else:
                    spill += val
    return total, inside, spill


@njit(parallel=True, fastmath=False, error_model="numpy", cache=True)
def _render_kernel(px, py, pz, wt, order, starts, ends, geo, buf, boff, brow0, brow1, psz, stats):  # pragma: no cover
    """Render particles ``order[starts[c]:ends[c]]`` of chunk c into its buffer; chunks in parallel.

    Everything accumulates, so a chunk done in consecutive pieces (one call per
    piece) sums in the same order as in one piece. stats[c] += (intensity
    expected, on the sensor, on the lenslet array, outside the chunk's rows (must
    stay 0), lenslets refused (rotated grid out of focus), lenslets rendered).
    """
    so, si, fm, fl, rad = geo[_G_SO], geo[_G_SI], geo[_G_FM], geo[_G_FL], geo[_G_R]
    pl, pp = geo[_G_PL], geo[_G_PP]
    ox, oy, cr, sr = geo[_G_OX], geo[_G_OY], geo[_G_COS], geo[_G_SIN]
    nlx, nly = geo[_G_NLX], geo[_G_NLY]
    sm, sl = geo[_G_SM], geo[_G_SL]
    rotated = sr != 0.0 or cr != 1.0
    cx0, cy0 = 0.5 * (nlx - 1.0), 0.5 * (nly - 1.0)
    inv_fm = 1.0 / fm
    for c in prange(starts.shape[0]):
        ax = np.zeros(_A_SIZE)
        ay = np.zeros(_A_SIZE)
        sc = np.zeros(_S_SIZE)
        lamx = np.zeros(psz)
        fullx = np.zeros(psz)
        lamy = np.zeros(psz)
        fully = np.zeros(psz)
        direct = np.zeros((psz, psz))
        carry_x = np.zeros((psz, psz))
        carry_y = np.zeros((psz, psz))
        pcs = np.zeros(32)
        brk = np.zeros(2 * psz + 16)
        b = buf[boff[c] : boff[c + 1]]
        r0 = brow0[c]
        r1 = brow1[c]
        s_w = 0.0
        s_in = 0.0
        s_all = 0.0
        s_spill = 0.0
        n_ref = 0.0
        n_len = 0.0
        for idx in range(starts[c], ends[c]):
            i = order[idx]
            w = wt[i]
            s_w += w
            if w == 0.0:
                continue
            # The ray to aperture point a: slope a·c1 + t0 (eqs 4.2–4.3), lenslet plane a·lsc + si·t0.
            inv_d = 1.0 / (so + pz[i])
            c1 = inv_d - inv_fm
            t0x = -px[i] * inv_d
            t0y = -py[i] * inv_d
            lsc = 1.0 + si * c1
            rs = rad * abs(lsc)  # radius of the aperture's image on the lenslet plane
            rho = rad * fl * abs(c1)  # radius of the aperture's image on the sensor (per lenslet)
            kap = lsc / (fl * c1)  # lenslet-plane shift per sensor shift
            lx = si * t0x - ox
            ly = si * t0y - oy
            g0x = cr * lx + sr * ly  # spot centre in the grid frame (eqs 4.10–4.11)
            g0y = -sr * lx + cr * ly
            focus = rs == 0.0 or (sm > 0.0 and rs <= _EPS_FOCUS * sm)
            reach = rs + _K * sm
            j0 = max(0, math.floor((g0x - reach) / pl + cx0 + 0.5))
            j1 = min(int(nlx) - 1, math.floor((g0x + reach) / pl + cx0 + 0.5))
            i0 = max(0, math.floor(cy0 - (g0y + reach) / pl + 0.5))
            i1 = min(int(nly) - 1, math.floor(cy0 - (g0y - reach) / pl + 0.5))
            sc[_S_KAP] = kap
            sc[_S_SM] = sm
            sc[_S_SL] = sl
            sc[_S_PP] = pp
            sc[_S_KSL] = _K * sl
            sc[_S_AK] = abs(kap)
            sc[_S_S] = math.sqrt(sm * sm + kap * kap * sl * sl)
            sc[_S_RHO] = rho
            bh = _K * sm / abs(kap) if (not focus and kap != 0.0) else 0.0
            fac0 = w / (math.pi * rho * rho)  # uniform over the aperture image
            for li in range(i0, i1 + 1):
                for lj in range(j0, j1 + 1):
                    u1 = (lj - cx0 - 0.5) * pl
                    u2 = u1 + pl
                    v1 = (cy0 - li - 0.5) * pl
                    v2 = v1 + pl
                    ddx = max(u1 - g0x, 0.0, g0x - u2)
                    ddy = max(v1 - g0y, 0.0, g0y - v2)
                    if ddx * ddx + ddy * ddy > reach * reach:
                        continue
                    mconst = 1.0
                    interior = False
                    a1x = a2x = a1y = a2y = False
                    if focus:  # the whole aperture lands on one lenslet-plane point
                        if sm > 0.0:
                            mconst = _window(g0x, u1, u2, True, True, sm) * _window(g0y, v1, v2, True, True, sm)
                        else:  # the divide-and-round of eqs 4.10–4.11: gx in [u1, u2), gy in (v1, v2]
                            mconst = 1.0 if (u1 <= g0x < u2 and v1 < g0y <= v2) else 0.0
                        if mconst == 0.0:
                            continue
                    else:
                        a1x = abs(u1 - g0x) < reach
                        a2x = abs(u2 - g0x) < reach
                        a1y = abs(v1 - g0y) < reach
                        a2y = abs(v2 - g0y) < reach
                        if (not a1x and u1 > g0x) or (not a2x and u2 < g0x):
                            continue
                        if (not a1y and v1 > g0y) or (not a2y and v2 < g0y):
                            continue
                        if rotated and (a1x or a2x or a1y or a2y):
                            n_ref += 1.0
                            continue
                        if a1x and a2x and a1y and a2y:
                            ex = max(abs(u1 - _K * sm - g0x), abs(u2 + _K * sm - g0x))
                            ey = max(abs(v1 - _K * sm - g0y), abs(v2 + _K * sm - g0y))
                            interior = ex * ex + ey * ey <= rs * rs
                    gcx = (lj - cx0) * pl
                    gcy = (cy0 - li) * pl
                    # Lenslet centre (sensor frame) + fl·t0: the centre of the aperture's image (eq. 4.4).
                    ccx = cr * gcx - sr * gcy + ox + fl * t0x
                    ccy = sr * gcx + cr * gcy + oy + fl * t0y
                    _setup_axis(ax, ccx, g0x, u1, u2, a1x, a2x, kap, bh)
                    _setup_axis(ay, ccy, g0y, v1, v2, a1y, a2y, kap, bh)
                    tot, ins, sp = _lenslet(
                        ax,
                        ay,
                        sc,
                        interior,
                        geo,
                        lamx,
                        fullx,
                        lamy,
                        fully,
                        direct,
                        carry_x,
                        carry_y,
                        pcs,
                        brk,
                        b,
                        r0,
                        r1,
                        fac0 * mconst,
                    )
                    s_all += tot
                    s_in += ins
                    if sp != 0.0:
                        s_spill += abs(sp)
                    n_len += 1.0
        stats[c, 0] += s_w
        stats[c, 1] += s_in
        stats[c, 2] += s_all
        stats[c, 3] += s_spill
        stats[c, 4] += n_ref
        stats[c, 5] += n_len


# ------------------------------------------------------------------ wrappers
def _geometry(camera: PlenopticCamera, diffraction: bool) -> np.ndarray:
    g = np.zeros(_G_SIZE)
    g[_G_SO], g[_G_SI], g[_G_FM] = camera.so, camera.si, camera.main_focal_length
    g[_G_FL], g[_G_R] = camera.lenslet_focal_length, camera.aperture_diameter / 2.0
    g[_G_PL], g[_G_PP] = camera.lenslet_pitch, camera.pixel_pitch
    g[_G_HW], g[_G_HH] = camera.sensor_width / 2.0, camera.sensor_height / 2.0
    g[_G_OX], g[_G_OY] = camera.lenslet_offset_x, camera.lenslet_offset_y
    g[_G_COS], g[_G_SIN] = math.cos(camera.lenslet_rotation), math.sin(camera.lenslet_rotation)
    g[_G_NLX], g[_G_NLY] = camera.n_lenslets_x, camera.n_lenslets_y
    g[_G_SM] = camera.sigma_lenslet_plane if diffraction else 0.0
    g[_G_SL] = camera.sigma_sensor_plane if diffraction else 0.0
    g[_G_NROW], g[_G_NCOL] = camera.n_pixels_y, camera.n_pixels_x
    return g


def _weights(
    camera: PlenopticCamera,
    particles: xr.Dataset,
    n: int,
    inten: np.ndarray,
    *,
    solid_angle_correction: bool,
    match_ray_counts: bool,
) -> np.ndarray:
    """Expected traced intensity of each particle: intensity × rays (eq. 4.14 generalised)."""
    if match_ray_counts or not solid_angle_correction:
        return inten * ray_counts(camera, particles, n, solid_angle_correction=solid_angle_correction)
    x, y, z = (np.asarray(particles[v].values, dtype=np.float64).ravel() for v in ("x", "y", "z"))
    rad = camera.aperture_diameter / 2.0
    ref = 2.0 * np.pi * (1.0 - camera.so / math.hypot(camera.so, rad))
    return inten * (n * solid_angle(camera, x, y, z) / ref)  # eq. 4.14 without the rounding


def _layout(
    camera: PlenopticCamera, x: np.ndarray, y: np.ndarray, z: np.ndarray, n_chunks: int, diffraction: bool
) -> tuple[np.ndarray, ...]:
    """Sort order, chunk bounds, chunk row ranges and the scratch patch size."""
    so, si, fm, fl = camera.so, camera.si, camera.main_focal_length, camera.lenslet_focal_length
    rad, pl, pp = camera.aperture_diameter / 2.0, camera.lenslet_pitch, camera.pixel_pitch
    sm = camera.sigma_lenslet_plane if diffraction else 0.0
    sl = camera.sigma_sensor_plane if diffraction else 0.0
    d = so + z
    c1 = 1.0 / d - 1.0 / fm
    yc = -(si + fl) * y / d  # image centre of the particle on the sensor (y up)
    rho = rad * fl * np.abs(c1)
    half = rad * np.abs(1.0 + si * c1) + _K * sm + pl * math.sqrt(0.5) + rho + _K * sl + 2.0 * pp
    hh = camera.sensor_height / 2.0
    nrow = camera.n_pixels_y
    top = np.clip(np.floor((hh - (yc + half)) / pp), 0, nrow - 1).astype(np.int64)
    bot = np.clip(np.floor((hh - (yc - half)) / pp), 0, nrow - 1).astype(np.int64)
    order = np.argsort(-yc, kind="stable").astype(np.int64)  # top of the sensor first
    k = max(1, min(int(n_chunks), x.size))
    bounds = np.linspace(0, x.size, k + 1).round().astype(np.int64)
    r0 = np.array([top[order[bounds[c] : bounds[c + 1]]].min() for c in range(k)], dtype=np.int64)
    r1 = np.array([bot[order[bounds[c] : bounds[c + 1]]].max() for c in range(k)], dtype=np.int64)
    psz = math.ceil((2.0 * float(rho.max()) + 2.0 * _K * sl) / pp) + 4
    return order, bounds, r0, r1, psz


def exact_memory_estimate(
    camera: PlenopticCamera, particles: xr.Dataset, n_chunks: int = DEFAULT_CHUNKS, *, diffraction: bool = True
) -> int:
    """Bytes :func:`render_exact` allocates: the float64 image, the chunk buffers (rows each chunk can reach)
    and the particle arrays."""
    x, y, z, _ = _particle_arrays(camera, particles)
    _, _, r0, r1, _ = _layout(camera, x, y, z, n_chunks, diffraction)
    rows = int(np.maximum(r1 - r0 + 1, 0).sum())
    return int(8 * camera.n_pixels_x * (camera.n_pixels_y + rows) + x.size * 8 * 8)


def render_exact(
    camera: PlenopticCamera,
    particles: xr.Dataset,
    rays_per_particle: int = 25_000,
    *,
    diffraction: bool = True,
    solid_angle_correction: bool = True,
    match_ray_counts: bool = False,
    n_chunks: int = DEFAULT_CHUNKS,
    max_image_bytes: float = 4e9,
    progress: bool = False,
) -> xr.DataArray:
    """The expected raw plenoptic image of a particle field, computed exactly (no rays).

    Each pixel holds the expected value of the Monte-Carlo image of
    :func:`lfstudy.simulate.raytrace.render` with the same ``rays_per_particle``:
    for every lenslet a particle's light cone reaches, the image of the main-lens
    aperture behind it (a disc of radius R·fl·|1/d − 1/fm|), weighted by the
    probability that the ray passes that lenslet (its square, blurred by the
    lenslet-plane diffraction σm, sec. 4.2.3), integrated over each pixel blurred
    by the sensor-plane diffraction σl, and scaled by the collected solid angle
    (eq. 4.14). See the module docstring for the method and its error bound.

    Parameters
    ----------
    camera : PlenopticCamera
        The camera. Rotated lenslet grids are supported for in-focus particles
        only (e.g. the pinhole image); otherwise a :class:`RaytraceError` is raised.
    particles : xarray.Dataset
        Particle field (``x``, ``y``, ``z`` in mm, ``intensity`` >= 0).
    rays_per_particle : int
        The Monte-Carlo ray count this image is the expectation of: the image
        scales with it (a particle of intensity 1 at the reference solid angle
        delivers ``rays_per_particle`` in total).
    diffraction : bool
        Blur the lenslet-plane and sensor-plane positions (sec. 4.2.3).
    solid_angle_correction : bool
        Scale each particle by Ω_i/Ω_ref (eq. 4.14 generalised); otherwise by 1.
    match_ray_counts : bool
        Use the Monte-Carlo's integer ray counts round(n·Ω_i/Ω_ref) instead of
        n·Ω_i/Ω_ref, so the image is the exact expectation of ``render`` (the
        rounding changes a particle's total by up to 0.5/n).
    n_chunks : int
        Particle chunks (buffers); part of the result's definition (summation
        order), independent of the thread count.
    max_image_bytes : float
        Refuse (RaytraceError) if the estimated allocation exceeds this.
    progress : bool
        Show a tqdm bar of the particles rendered (it does not change the result).

    Returns
    -------
    xarray.DataArray
        ``intensity`` over (``row``, ``col``), float64, with the coords and camera
        attributes of ``render``, ``method = "exact"`` and the accounting of the
        expected intensity: traced, recorded, missing the lenslet array, falling
        outside the sensor.
    """
    n = _check_rays(rays_per_particle)
    x, y, z, inten = _particle_arrays(camera, particles)
    if not isinstance(n_chunks, (int, np.integer)) or isinstance(n_chunks, bool) or n_chunks < 1:
        raise RaytraceError(f"n_chunks = {n_chunks!r}: must be an integer >= 1")
    order, bounds, r0, r1, psz = _layout(camera, x, y, z, int(n_chunks), diffraction)
    ncol = camera.n_pixels_x
    rows = np.maximum(r1 - r0 + 1, 0)
    need = 8 * ncol * (camera.n_pixels_y + int(rows.sum())) + x.size * 8 * 8
    if need > max_image_bytes:
        raise RaytraceError(
            f"render_exact: estimated memory {need / 1e9:.3g} GB (float64 image of {camera.n_pixels_y} x {ncol} px "
            f"+ chunk buffers of {int(rows.sum())} rows) exceeds max_image_bytes = {max_image_bytes / 1e9:.3g} GB; "
            "use fewer n_chunks or raise the limit"
        )
    wt = _weights(
        camera, particles, n, inten, solid_angle_correction=solid_angle_correction, match_ray_counts=match_ray_counts
    )
    geo = _geometry(camera, diffraction)
    k = bounds.size - 1
    boff = np.concatenate([[0], np.cumsum(rows * ncol)]).astype(np.int64)
    buf = np.zeros(int(boff[-1]))
    stats = np.zeros((k, 6))
    with tqdm(total=x.size, desc="exact rendering", unit="particle", disable=not progress, mininterval=1.0) as bar:
        for p in range(_PIECES):
            starts = bounds[:-1] + (bounds[1:] - bounds[:-1]) * p // _PIECES
            ends = bounds[:-1] + (bounds[1:] - bounds[:-1]) * (p + 1) // _PIECES
            _render_kernel(x, y, z, wt, order, starts, ends, geo, buf, boff, r0, r1, psz, stats)
            bar.update(int((ends - starts).sum()))
    tot = stats.sum(axis=0)
    if tot[4] > 0:
        raise RaytraceError(
            f"render_exact: camera.lenslet_rotation = {camera.lenslet_rotation!r} rad with {int(tot[4])} lenslet "
            "images of out-of-focus particles; the exact method needs an unrotated lenslet grid unless every "
            "particle is in focus (use method='montecarlo' for rotated grids)"
        )
    if tot[3] > 1e-9 * max(tot[0], 1e-300):
        raise RuntimeError(f"render_exact: {tot[3]:.3g} of the intensity fell outside its chunk's rows (a bug)")
    # Fixed-order sum of the chunk buffers (deterministic whatever the threads).
    image = np.zeros((camera.n_pixels_y, ncol))
    for c in range(k):
        if rows[c] > 0:
            image[r0[c] : r1[c] + 1] += buf[boff[c] : boff[c + 1]].reshape(rows[c], ncol)
    del buf
    attrs: dict[str, Any] = {
        "units": "1",
        "long_name": "simulated plenoptic raw image (expected sum of ray intensities)",
        **camera.to_attrs(),
        "method": "exact",
        "rays_per_particle": n,
        "n_particles": int(x.size),
        "solid_angle_correction": int(bool(solid_angle_correction)),
        "match_ray_counts": int(bool(match_ray_counts)),
        "diffraction": int(bool(diffraction)),
        "sigma_lenslet_plane": camera.sigma_lenslet_plane,
        "sigma_sensor_plane": camera.sigma_sensor_plane,
        "n_chunks": int(k),
        "lenslet_images": int(tot[5]),
        "intensity_traced": float(tot[0]),
        "intensity_recorded": float(tot[1]),
        "intensity_lost": float(tot[0] - tot[1]),
        "intensity_lost_lenslet_array": float(max(tot[0] - tot[2], 0.0)),
        "intensity_lost_outside_sensor": float(max(tot[2] - tot[1], 0.0)),
        "y_direction": "up; row 0 is the top",
    }
    return xr.DataArray(image, dims=("row", "col"), coords=_sensor_coords(camera), name="intensity", attrs=attrs)


def render_pinhole_exact(
    camera: PlenopticCamera,
    *,
    fnumber: float = 16,
    count: int = 500_000,
    rays_per_point: int = 100,
    seed: int = 0,
    **kwargs: Any,
) -> xr.DataArray:
    """The calibration pinhole image (sec. 5.1) computed exactly.

    The same point field as :func:`lfstudy.simulate.raytrace.render_pinhole`
    (``pinhole_field(camera, count=count, seed=seed)``, all in the object focal
    plane) imaged at ``fnumber``; every point is in focus, so each lenslet it
    reaches shows the σl-blurred image of the stopped-down aperture, weighted by
    the lenslet-plane diffraction. Extra keyword arguments go to :func:`render_exact`.
    """
    from lfstudy.simulate.particles import pinhole_field

    _check_rays(rays_per_point, "rays_per_point")
    cam = camera.with_(fnumber=float(fnumber))
    field = pinhole_field(camera, count=count, seed=seed)
    img = render_exact(cam, field, rays_per_point, **kwargs)
    img.attrs.update(
        long_name="simulated pinhole calibration image (expected)",
        pinhole_fnumber=float(fnumber),
        pinhole_count=int(count),
        seed=int(seed),
    )
    return img
