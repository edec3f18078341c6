"""Plenoptic ray-tracing simulator, 2-D (thesis sec. 4.1–4.3, Appendix A).

Every particle is a point source. Its rays are traced with paraxial transfer
matrices written out in slope form: free space (eq. 4.2) to the main lens,
the thin main lens (eq. 4.3), free space ``si`` to the lenslet array, the
struck lenslet as a thin lens plus prism (eq. 4.4), and free space ``fl`` to
the sensor, where each ray deposits its particle's intensity into one pixel
(eq. 4.15).

Conventions (shared with :mod:`lfstudy.optics` and the later stages):

* mm and rad; the object frame has its origin where the object focal plane
  meets the optical axis, +z away from the camera (a particle at depth z is
  ``so + z`` in front of the main lens);
* lenslet- and sensor-plane coordinates are in the sensor frame (origin at the
  sensor centre, x right, y up; row 0 is the top row). The image is *not*
  flipped: object +y lands at sensor −y (the main lens inverts, M < 0);
* the lenslet a ray strikes is found by division and rounding in the grid
  frame (eqs 4.10–4.11 generalised to a shifted and rotated grid);
* diffraction (sec. 4.2.3) is a Gaussian shift of the ray position with
  σ = ``camera.sigma_lenslet_plane`` at the lenslet plane (main-lens
  f-number, |M| = si/so) and σ = ``camera.sigma_sensor_plane`` at the sensor
  (lenslet f-number, |M| = fl/si). Appendix A's Fortran applies them the
  other way round; we follow the text.

Imperfections (:mod:`lfstudy.simulate.imperfections`, ``imperfections=`` of :func:`render`):
the kernel traces through the imaging camera's grid, with the lenslet-to-sensor
gap g (``s = c·g/fl + g·t + (1 − g/fl)·l``), each lenslet's own optical centre,
and a tilted sensor (per particle, the lenslet plane at its chief ray's point;
slopes on the sensor side in the tilted frame); the main-lens distortion moves
the particles before the kernel. The ideal values keep every sum bit-identical.

Ray generation
--------------
Rays leave each particle towards points drawn uniformly over the circular
main-lens aperture (r = R·√u, θ = 2πv, rejection-free), so no ray is ever
generated outside the aperture (the thesis' angular sampling wastes the rays
outside the disc; here none is dropped there). Equal area on the aperture is
equal solid angle to within (R/d)² (paraxial optics).

The number of rays of particle *i* follows the solid-angle correction of
eq. 4.14 generalised to 2-D: ``n_i = round(n · Ω_i / Ω_ref)`` where Ω_i is the
solid angle the aperture disc subtends from the particle (Gauss–Legendre
quadrature of dΩ = d·dA / r³) and Ω_ref the one from the on-axis point of the
object focal plane. Closer or on-axis particles thus collect more light, as in
the thesis; ``solid_angle=False`` gives every particle exactly ``n`` rays.

Determinism
-----------
The numba kernel runs ``prange`` over a *fixed* number of particle chunks
(``n_chunks``, independent of the thread count). Each chunk traces its
particles in order into its own image buffer, and the buffers are summed in
chunk order. Random numbers are counter-based: SplitMix64 evaluated at
position ``(particle key) + (ray counter)``, so a particle's rays never depend
on which thread runs it. One seed therefore gives a bit-identical image with
1 or N threads.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from numba import njit, prange
from tqdm.auto import tqdm

from lfstudy.optics import PlenopticCamera
from lfstudy.simulate._render_common import (
    _G_COS,
    _G_FL,
    _G_FM,
    _G_GAP,
    _G_HH,
    _G_HW,
    _G_NCOL,
    _G_NLX,
    _G_NLY,
    _G_NROW,
    _G_OX,
    _G_OY,
    _G_PL,
    _G_PP,
    _G_R,
    _G_SCAT,
    _G_SI,
    _G_SIN,
    _G_SIZE,
    _G_SL,
    _G_SM,
    _G_SO,
    _G_TLX,
    _G_TLY,
    DEFAULT_CHUNKS,
    RaytraceError,
    _blurs,
    _check_noise,
    _check_rays,
    _finish,
    _geometry,
    _particle_arrays,
    _sensor_coords,
    quantize,
    ray_counts,
    solid_angle,
)
from lfstudy.simulate.exact import render_exact, render_pinhole_exact
from lfstudy.simulate.imperfections import CameraImperfections, resolve

__all__ = [
    "RaytraceError",
    "DEFAULT_CHUNKS",
    "solid_angle",
    "ray_counts",
    "memory_estimate",
    "render",
    "render_pinhole",
    "quantize",
    "angle_histograms",
    "incidence_angle_bound",
    "write_image",
]

_PIECES = 16  # kernel calls per render (progress granularity; fixed, part of the summation order)


# ---------------------------------------------------------------- random numbers
# SplitMix64 (Steele, Lea & Flood 2014): state advances by the golden gamma and
# is finalised by a bijective mix. Evaluating it at an arbitrary counter makes
# it a counter-based generator: stream position = particle key + ray counter.
_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S32 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(32)
_LOW32 = np.uint64(0xFFFFFFFF)


@njit(inline="always", cache=True)
def _mix64(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


_S20 = np.uint64(20)
_ONE_BITS = np.uint64(0x3FF0000000000000)  # IEEE-754 bits of 1.0
_G2 = np.uint64((0x9E3779B97F4A7C15 * 2) & 0xFFFFFFFFFFFFFFFF)
_G3 = np.uint64((0x9E3779B97F4A7C15 * 3) & 0xFFFFFFFFFFFFFFFF)
_HALF_ULP32 = 2.0**-33
_LN2 = math.log(2.0)
_SQRT_HALF = math.sqrt(0.5)
_BLOCK = 256  # rays per vectorised block


@njit(inline="always", cache=True)
def _unit_bits(h32):
    """Bits of the double 1 + h32·2⁻³² in [1, 2) (32 random mantissa bits).

    Building the double from bits avoids the 64-bit int→float conversion,
    which AVX2 lacks, so the hash loop vectorises.
    """
    return (h32 << _S20) | _ONE_BITS


@njit(inline="always", cache=True)
def _lift_octaves(t, e, below, factor, octaves):
    """One branch-free range-reduction step: if t < below, scale t by factor and count octaves."""
    c = t < below
    return t * (factor if c else 1.0), e + (octaves if c else 0.0)


@njit(inline="always", cache=True)
def _log01(u):
    """Natural log of u in [2⁻³³, 1), branch-free so that it vectorises.

    Binary range reduction to t in [√½, √2) by compare-and-select, then the
    atanh series log t = 2·atanh((t−1)/(t+1)); |error| < 1e-12.
    """
    t, e = _lift_octaves(u, 0.0, 2.0**-32, 2.0**32, 32.0)
    t, e = _lift_octaves(t, e, 2.0**-16, 2.0**16, 16.0)
    t, e = _lift_octaves(t, e, 2.0**-8, 2.0**8, 8.0)
    t, e = _lift_octaves(t, e, 2.0**-4, 2.0**4, 4.0)
    t, e = _lift_octaves(t, e, 0.25, 4.0, 2.0)
    t, e = _lift_octaves(t, e, 0.5, 2.0, 1.0)
    t, e = _lift_octaves(t, e, _SQRT_HALF, 2.0, 1.0)  # t in [½, 1) -> [√½, √2)
    s = (t - 1.0) / (t + 1.0)
    s2 = s * s
    poly = 1.0 + s2 * (1.0 / 3 + s2 * (1.0 / 5 + s2 * (1.0 / 7 + s2 * (1.0 / 9 + s2 * (1.0 / 11 + s2 * (1.0 / 13))))))
    return 2.0 * s * poly - e * _LN2


@njit(inline="always", cache=True)
def _sincos_turn(u):
    """(sin 2πu, cos 2πu) for u in [0, 1): quadrant reduction + Taylor series.

    Absolute error < 2e-9 (far below a pixel at any scale traced here);
    branch-free, so that the ray loop vectorises.
    """
    x = 4.0 * u
    q = math.floor(x + 0.5)  # nearest quarter turn 0..4
    t = (x - q) * (0.5 * math.pi)  # |t| <= π/4
    t2 = t * t
    s = t * (1.0 + t2 * (-1.0 / 6 + t2 * (1.0 / 120 + t2 * (-1.0 / 5040 + t2 * (1.0 / 362880)))))
    c = 1.0 + t2 * (-0.5 + t2 * (1.0 / 24 + t2 * (-1.0 / 720 + t2 * (1.0 / 40320 + t2 * (-1.0 / 3628800)))))
    k = q - 4.0 * math.floor(q * 0.25)  # quarter turns mod 4, as a float
    odd = (k == 1.0) | (k == 3.0)
    a = c if odd else s
    b = s if odd else c
    return (-a if k >= 2.0 else a), (-b if ((k == 1.0) | (k == 2.0)) else b)


@njit(inline="always", cache=True)
def _normal_pair(bits_u, bits_v):
    """Box–Muller: two independent standard normals from two [1, 2) doubles."""
    rad = math.sqrt(-2.0 * _log01(bits_u - (1.0 - _HALF_ULP32)))
    sn, cs = _sincos_turn(bits_v - 1.0)
    return rad * cs, rad * sn


_MISSED_ARRAY, _OFF_SENSOR = -1.0, -2.0  # pixel codes of lost rays


@njit(parallel=True, fastmath=False, error_model="numpy", cache=True)
def _trace(
    px, py, pz, pint, nrays, starts, ends, seed, g, record, hmax, buffers, stats, lost, hist, amax
):  # pragma: no cover - jitted
    """Trace particles ``starts[k]:ends[k]`` of chunk k into buffer k; chunks in parallel.

    ``g`` is the geometry vector of :mod:`lfstudy.simulate._render_common` (σm, σl = 0 without
    diffraction); ``record``: deposit into the buffers; ``hmax``: the histograms' half range [rad].

    Everything accumulates, so a chunk traced in consecutive pieces (one call
    per piece, for progress) sums in the same order as in one piece.
    stats[k] += (rays traced, rays missing the lenslet array, rays off the sensor,
    rays recorded); lost[k] += intensity not recorded; hist[k, 0|1, :] = θ|φ
    histograms of recorded rays (if hist has bins); amax[k] = max |θ|, |φ|, γ.

    A particle's rays go in blocks of ``_BLOCK``: a branch-free loop that the
    compiler vectorises draws the random numbers and traces every ray to its
    pixel index, then a scalar loop deposits the intensities. Ray j of
    particle i uses the hashes at counters key_i + (3j, 3j+1, 3j+2)·γ: the
    aperture point, the lenslet-plane and the sensor-plane diffraction.
    """
    so, si, fm, fl, rad = g[_G_SO], g[_G_SI], g[_G_FM], g[_G_FL], g[_G_R]
    pl, pp, hw, hh = g[_G_PL], g[_G_PP], g[_G_HW], g[_G_HH]
    ox, oy, cr, sr = g[_G_OX], g[_G_OY], g[_G_COS], g[_G_SIN]
    nlx, nly = g[_G_NLX], g[_G_NLY]
    # Without diffraction the normals are still drawn (the loop stays
    # branch-free) but scaled by zero.
    sm = g[_G_SM]
    sl = g[_G_SL]
    # Imperfections (lfstudy.simulate.imperfections); their ideal values (gap = fl, no tilt, no
    # scatter) leave every sum below bit-identical: gr = 1, q = 0, a tilt adds 0.0.
    gap, tlx, tly = g[_G_GAP], g[_G_TLX], g[_G_TLY]
    gr = gap / fl  # 1 for the ideal gap
    q = 1.0 - gr  # the landing's share of the lenslet-plane point (eq. 4.4 with a gap g != fl)
    scat = g[_G_SCAT] != 0.0
    nlxi = int(nlx)
    cx0, cy0 = 0.5 * (nlx - 1.0), 0.5 * (nly - 1.0)
    # Reciprocals hoisted out of the ray loop (fastmath stays off).
    inv_fm, inv_pl, inv_fl, inv_pp = 1.0 / fm, 1.0 / pl, 1.0 / fl, 1.0 / pp
    nrow, ncol = g[_G_NROW], g[_G_NCOL]
    nbins = hist.shape[2]
    key0 = _mix64(seed)
    for k in prange(starts.shape[0]):
        buf = buffers[k].ravel()  # a view: buffers are C-contiguous
        bits = np.empty((6, _BLOCK), dtype=np.uint64)
        unit = bits.view(np.float64)  # the same memory read as [1, 2) doubles
        pix = np.empty(_BLOCK)
        slope = np.empty((2, _BLOCK))
        land = np.empty((4, _BLOCK))  # sensor x, y and lenslet column, row of each ray (for the scatter pass)
        n_traced = 0
        n_miss = 0
        n_off = 0
        n_rec = 0
        lost_k = 0.0
        for i in range(starts[k], ends[k]):
            inten = pint[i]
            # The ray to aperture point (ax, ay) is affine in (ax, ay):
            # free space (eq. 4.2) + thin main lens (eq. 4.3) give the slope
            # t = a·c1 + t0, and free space si puts it at l = a·(1 + si·c1) + si·t0.
            inv_d = 1.0 / (so + pz[i])
            c1 = inv_d - inv_fm
            tx0 = -px[i] * inv_d
            ty0 = -py[i] * inv_d
            # A tilted sensor: the lenslet plane at the chief ray's point lies at si + θy·x + θx·y.
            sip = si + tly * (si * tx0) + tlx * (si * ty0)
            lsc = 1.0 + sip * c1
            lx0 = sip * tx0 - ox
            ly0 = sip * ty0 - oy
            sx0 = tx0 + tly  # chief-ray slope in the tilted frame (the sensor side)
            sy0 = ty0 + tlx
            key = _mix64(key0 ^ (np.uint64(i) * _GAMMA))
            ni = nrays[i]
            n_traced += ni
            for j0 in range(0, ni, _BLOCK):
                m = min(_BLOCK, ni - j0)
                base = key + np.uint64(j0) * _G3
                for t in range(m):  # random bits (vectorised)
                    ctr = base + np.uint64(t) * _G3
                    h = _mix64(ctr)
                    bits[0, t] = _unit_bits(h >> _S32)
                    bits[1, t] = _unit_bits(h & _LOW32)
                    h = _mix64(ctr + _GAMMA)
                    bits[2, t] = _unit_bits(h >> _S32)
                    bits[3, t] = _unit_bits(h & _LOW32)
                    h = _mix64(ctr + _G2)
                    bits[4, t] = _unit_bits(h >> _S32)
                    bits[5, t] = _unit_bits(h & _LOW32)
                for t in range(m):  # optics (vectorised, branch-free)
                    # Aperture point, uniform over the disc (rejection-free).
                    r = rad * math.sqrt(unit[0, t] - (1.0 - _HALF_ULP32))
                    sn, cs = _sincos_turn(unit[1, t] - 1.0)
                    ax = r * cs
                    ay = r * sn
                    tx = ax * c1 + tx0
                    ty = ay * c1 + ty0
                    # Lenslet plane, relative to the grid origin, with the
                    # main-lens diffraction spot (sec. 4.2.3).
                    n1, n2 = _normal_pair(unit[2, t], unit[3, t])
                    lxn = ax * lsc + lx0
                    lyn = ay * lsc + ly0
                    dx = lxn + sm * n1
                    dy = lyn + sm * n2
                    # Struck lenslet: grid frame, divide and round (eqs 4.10–4.11).
                    fj = math.floor((cr * dx + sr * dy) * inv_pl + cx0 + 0.5)
                    fi = math.floor(cy0 - (cr * dy - sr * dx) * inv_pl + 0.5)
                    miss = (fj < 0.0) | (fj >= nlx) | (fi < 0.0) | (fi >= nly)
                    gcx = (fj - cx0) * pl
                    gcy = (cy0 - fi) * pl
                    ccx = cr * gcx - sr * gcy  # lenslet centre − grid origin
                    ccy = sr * gcx + cr * gcy
                    # Lenslet = thin lens + prism (eq. 4.4), free space g to the sensor:
                    # s = l + g·(t − (l − c)/fl) = c·g/fl + g·t + (1 − g/fl)·l (= c + fl·t for g = fl),
                    # with the slope t in the tilted frame and l the lenslet-plane point before the
                    # diffraction shift (which only chooses the lenslet).
                    tx2 = tx - (dx - ccx) * inv_fl
                    ty2 = ty - (dy - ccy) * inv_fl
                    n3, n4 = _normal_pair(unit[4, t], unit[5, t])
                    sx = gr * (ccx + ox) + gap * (ax * c1 + sx0) + q * (lxn + ox) + sl * n3  # sensor diffraction
                    sy = gr * (ccy + oy) + gap * (ay * c1 + sy0) + q * (lyn + oy) + sl * n4  # (sec. 4.2.3)
                    # Pixel: column grows with x, row 0 at the top (eq. 4.15).
                    fc = math.floor((sx + hw) * inv_pp)
                    fr = math.floor((hh - sy) * inv_pp)
                    off = (fc < 0.0) | (fc >= ncol) | (fr < 0.0) | (fr >= nrow)
                    pix[t] = _MISSED_ARRAY if miss else (_OFF_SENSOR if off else fr * ncol + fc)
                    slope[0, t] = tx2
                    slope[1, t] = ty2
                    land[0, t] = sx
                    land[1, t] = sy
                    land[2, t] = fj
                    land[3, t] = fi
                if scat:  # each lenslet's optical centre off its cell's centre: move the rays it took
                    for t in range(m):  # (a pass of its own keeps the loop above branch-free)
                        if pix[t] == _MISSED_ARRAY:
                            continue
                        ks = _G_SIZE + 2 * (int(land[3, t]) * nlxi + int(land[2, t]))
                        sx = land[0, t] + gr * g[ks]
                        sy = land[1, t] + gr * g[ks + 1]
                        slope[0, t] += g[ks] * inv_fl
                        slope[1, t] += g[ks + 1] * inv_fl
                        fc = math.floor((sx + hw) * inv_pp)
                        fr = math.floor((hh - sy) * inv_pp)
                        off = (fc < 0.0) | (fc >= ncol) | (fr < 0.0) | (fr >= nrow)
                        pix[t] = _OFF_SENSOR if off else fr * ncol + fc
                for t in range(m):  # deposit (scalar: scattered adds)
                    p = pix[t]
                    if p < 0.0:
                        if p == _MISSED_ARRAY:
                            n_miss += 1
                        else:
                            n_off += 1
                        lost_k += inten
                        continue
                    n_rec += 1
                    if record:
                        buf[int(p)] += inten
                    if nbins > 0:
                        th = math.atan(slope[0, t])
                        ph = math.atan(slope[1, t])
                        gam = math.atan(math.hypot(slope[0, t], slope[1, t]))
                        amax[k, 0] = max(amax[k, 0], abs(th))
                        amax[k, 1] = max(amax[k, 1], abs(ph))
                        amax[k, 2] = max(amax[k, 2], gam)
                        b = math.floor((th + hmax) / (2.0 * hmax) * nbins)
                        if 0.0 <= b < nbins:
                            hist[k, 0, int(b)] += 1
                        b = math.floor((ph + hmax) / (2.0 * hmax) * nbins)
                        if 0.0 <= b < nbins:
                            hist[k, 1, int(b)] += 1
        stats[k, 0] += n_traced
        stats[k, 1] += n_miss
        stats[k, 2] += n_off
        stats[k, 3] += n_rec
        lost[k] += lost_k


# ---------------------------------------------------------------- kernel call
def _chunk_bounds(n: int, n_chunks: int) -> np.ndarray:
    k = max(1, min(int(n_chunks), n))
    return np.linspace(0, n, k + 1).round().astype(np.int64)


def _seed_u64(seed: Any) -> np.uint64:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not (0 <= seed < 2**64):
        raise RaytraceError(f"seed = {seed!r}: must be an integer in [0, 2**64)")
    return np.uint64(int(seed))


def memory_estimate(camera: PlenopticCamera, n_particles: int, n_chunks: int = DEFAULT_CHUNKS) -> int:
    """Bytes ``render`` allocates: float32 chunk buffers, the float64 image, particle arrays."""
    npx = camera.n_pixels_x * camera.n_pixels_y
    k = max(1, min(int(n_chunks), int(n_particles)))
    return int(k * npx * 4 + npx * 8 + n_particles * 5 * 8)


def _run_kernel(
    camera,
    x,
    y,
    z,
    inten,
    nrays,
    seed,
    *,
    diffraction,
    n_chunks,
    record=True,
    nbins=0,
    hmax=1.0,
    progress=False,
    geometry=None,
):
    bounds = _chunk_bounds(x.size, n_chunks)
    k = bounds.size - 1
    shape = (k, camera.n_pixels_y, camera.n_pixels_x) if record else (k, 1, 1)
    buffers = np.zeros(shape, dtype=np.float32)
    stats = np.zeros((k, 4), dtype=np.int64)
    lost = np.zeros(k, dtype=np.float64)
    hist = np.zeros((k, 2, nbins), dtype=np.int64)
    amax = np.zeros((k, 3), dtype=np.float64)
    g = _geometry(camera, *_blurs(camera, diffraction)) if geometry is None else geometry
    # Each chunk is traced in _PIECES consecutive pieces (a fixed count, so the
    # bytes never depend on the progress bar or the threads); one bar step per piece.
    cum = np.concatenate([[0], np.cumsum(nrays, dtype=np.int64)])
    with tqdm(
        total=int(cum[-1]), desc="ray tracing", unit="ray", unit_scale=True, disable=not progress, mininterval=1.0
    ) as bar:
        for p in range(_PIECES):
            starts = bounds[:-1] + (bounds[1:] - bounds[:-1]) * p // _PIECES
            ends = bounds[:-1] + (bounds[1:] - bounds[:-1]) * (p + 1) // _PIECES
            _trace(x, y, z, inten, nrays, starts, ends, seed, g, record, hmax, buffers, stats, lost, hist, amax)
            bar.update(int((cum[ends] - cum[starts]).sum()))
    return buffers, stats, lost, hist, amax


# ------------------------------------------------------------------ public API
METHODS = ("exact", "montecarlo")  #: rendering methods of :func:`render`; the first is the default


def render(
    camera: PlenopticCamera,
    particles: xr.Dataset,
    rays_per_particle: int,
    seed: int,
    *,
    diffraction: bool = True,
    solid_angle_correction: bool = True,
    shot_noise: bool = False,
    read_noise: float = 0.0,
    full_well: float | None = None,
    bit_depth: int | None = None,
    n_chunks: int = DEFAULT_CHUNKS,
    max_image_bytes: float = 4e9,
    progress: bool = False,
    method: str = METHODS[0],
    imperfections: CameraImperfections | Mapping[str, Any] | None = None,
) -> xr.DataArray:
    """Render the raw plenoptic image of a particle field (sec. 4.3), exactly or by ray tracing.

    The one place that chooses the method: ``"exact"`` (the default, as in the
    config schema's ``raytrace.method``) computes the expected image without
    rays (:func:`lfstudy.simulate.exact.render_exact`); ``"montecarlo"`` traces
    ``rays_per_particle`` random rays per particle (this module's kernel, the
    thesis' tracer). Both then add the optional noise and integer export.

    Parameters
    ----------
    camera : PlenopticCamera
        The camera (geometry, lenslet grid, diffraction sigmas).
    particles : xarray.Dataset
        Particle field over ``particle`` with ``x``, ``y``, ``z`` (object frame,
        mm) and ``intensity`` (>= 0), as from :mod:`lfstudy.simulate.particles`.
    rays_per_particle : int
        Rays per particle at the reference solid angle (eq. 4.14); the exact
        image is the expectation of that many rays (it scales with it).
    seed : int
        Seed of the counter-based ray streams (Monte-Carlo) and of the noise;
        the same seed gives a bit-identical image whatever the thread count.
    diffraction : bool
        Apply the Gaussian diffraction shifts at the lenslet and sensor planes.
    solid_angle_correction : bool
        Scale each particle's ray count by its aperture solid angle (eq. 4.14
        generalised); otherwise every particle gets ``rays_per_particle`` rays.
    shot_noise : bool
        Replace each pixel's signal s by a Poisson draw of mean s (the signal
        is read as photo-electrons); drawn by
        :func:`lfstudy.simulate.sensor.apply_sensor` from
        ``numpy.random.default_rng(seed)``. For a full camera model (photons,
        quantum efficiency, dark level, full well, gain) call ``apply_sensor``
        on the noise-free image instead.
    read_noise : float
        Standard deviation of additive Gaussian read noise (same units), from
        the same generator. Pixels may come out negative (the float signal
        stays unbiased); the integer export clips them to 0.
    full_well, bit_depth : float, int, optional
        Integer export (:func:`quantize`): with ``bit_depth`` the signal is
        scaled so that ``full_well`` (default: the image maximum) maps to
        2**bit_depth − 1, rounded and clipped to [0, 2**bit_depth − 1]; the
        number of clipped-high pixels is ``attrs['saturated_pixels']``.
    n_chunks : int
        Particle chunks (image buffers) of the kernel; part of the result's
        definition (summation order), not a tuning knob for threads.
    max_image_bytes : float
        Refuse (ValueError) if the estimated allocation exceeds this.
    progress : bool
        Show a tqdm bar of the rays traced (it does not change the result).
    method : {"exact", "montecarlo"}
        ``"exact"``: the expected value of the Monte-Carlo image, computed
        without rays (deterministic; ``seed`` only drives ``shot_noise`` /
        ``read_noise``). ``"montecarlo"``: trace the rays (the reference).
    imperfections : CameraImperfections or mapping, optional
        What the imaging camera does differently from ``camera``
        (:mod:`lfstudy.simulate.imperfections`, the config's ``camera.imperfections``);
        None or all-ideal settings give the ideal camera's image, bit for bit.

    Returns
    -------
    xarray.DataArray
        ``intensity`` over (``row``, ``col``) with sensor coords ``x``/``y`` [mm]
        (row 0 at the top, y up), float64 (or unsigned integer with
        ``bit_depth``); attrs hold the camera parameters, the seed and the
        accounting of what was traced, recorded and lost (outside the lenslet
        array / outside the sensor): ray counts for ``"montecarlo"``, expected
        intensities for ``"exact"``.

    Examples
    --------
    A 60 x 45 pixel sensor with the Table 4.3 optics (7.4 µm pixels, 125 µm
    lenslets of 0.5 mm focal length, a 50 mm main lens at magnification −1)
    and two particles, one on the object focal plane and one 1 mm behind it:

    >>> from lfstudy.optics import PlenopticCamera
    >>> from lfstudy.simulate import make_field, render
    >>> camera = PlenopticCamera(60, 45, 0.0074, 0.125, 0.5, 50.0, -1.0)
    >>> field = make_field([0.0, 0.03], [0.0, -0.02], [0.0, 1.0], [1.0, 1.0])
    >>> image = render(camera, field, rays_per_particle=1000, seed=0)
    >>> image.shape, image.attrs["method"]
    ((45, 60), 'exact')
    >>> round(float(image.sum()), 3)
    1699.127
    >>> traced = render(camera, field, 1000, seed=0, method="montecarlo")
    >>> int(traced.attrs["rays_recorded"]), int(traced.sum())
    (1730, 1730)
    """
    if method not in METHODS:
        raise RaytraceError(f"method = {method!r}: allowed values are {', '.join(map(repr, METHODS))}")
    n = _check_rays(rays_per_particle)
    seed64 = _seed_u64(seed)
    x, y, z, inten = _particle_arrays(camera, particles)
    _check_noise(read_noise, bit_depth)
    if not isinstance(n_chunks, (int, np.integer)) or n_chunks < 1:
        raise RaytraceError(f"n_chunks = {n_chunks!r}: must be an integer >= 1")
    options = {
        "diffraction": diffraction,
        "solid_angle_correction": solid_angle_correction,
        "n_chunks": n_chunks,
        "max_image_bytes": max_image_bytes,
        "progress": progress,
        "imperfections": resolve(imperfections),
    }
    if method == "exact":
        da = render_exact(camera, particles, n, **options)
    else:
        da = _render_montecarlo(camera, particles, (x, y, z, inten), n, seed64, **options)
    da.attrs["seed"] = int(seed)
    return _finish(da, int(seed), shot_noise, read_noise, full_well, bit_depth)


def _render_montecarlo(
    camera: PlenopticCamera,
    particles: xr.Dataset,
    arrays: tuple[np.ndarray, ...],
    n: int,
    seed64: np.uint64,
    *,
    diffraction: bool,
    solid_angle_correction: bool,
    n_chunks: int,
    max_image_bytes: float,
    progress: bool,
    imperfections: CameraImperfections,
) -> xr.DataArray:
    """The noise-free Monte-Carlo image of :func:`render` (inputs already checked)."""
    x, y, z, inten = arrays
    imp = imperfections
    cam = imp.imaging_camera(camera)  # the lenslet grid the light meets
    geometry = _geometry(
        cam,
        *_blurs(cam, diffraction),
        gap=imp.gap(cam),
        tilt=(imp.sensor_tilt_x * 1e-3, imp.sensor_tilt_y * 1e-3),
        scatter=imp.scatter(cam),
    )
    x, y = imp.distort(camera, x, y, z)  # the light cone turns with its chief ray; Ω stays the true one
    need = memory_estimate(camera, x.size, n_chunks)
    if need > max_image_bytes:
        raise RaytraceError(
            f"render: estimated memory {need / 1e9:.3g} GB ({min(n_chunks, x.size)} float32 chunk buffers + "
            f"float64 image of {camera.n_pixels_y} x {camera.n_pixels_x} px) exceeds max_image_bytes = "
            f"{max_image_bytes / 1e9:.3g} GB; use fewer n_chunks or raise the limit"
        )
    nrays = ray_counts(camera, particles, n, solid_angle_correction=solid_angle_correction)
    buffers, stats, lost, _, _ = _run_kernel(
        cam,
        x,
        y,
        z,
        inten,
        nrays,
        seed64,
        diffraction=diffraction,
        n_chunks=n_chunks,
        progress=progress,
        geometry=geometry,
    )
    # Fixed-order sum of the chunk buffers (deterministic whatever the threads).
    image = np.zeros(buffers.shape[1:], dtype=np.float64)
    for b in buffers:
        image += b
    del buffers
    tot = stats.sum(axis=0)
    attrs: dict[str, Any] = {
        "units": "1",
        "long_name": "simulated plenoptic raw image (sum of ray intensities)",
        **camera.to_attrs(),
        "seed": int(seed64),
        "rays_per_particle": n,
        "n_particles": int(x.size),
        "solid_angle_correction": int(bool(solid_angle_correction)),
        "diffraction": int(bool(diffraction)),
        "sigma_lenslet_plane": camera.sigma_lenslet_plane,
        "sigma_sensor_plane": camera.sigma_sensor_plane,
        "n_chunks": int(stats.shape[0]),
        "rays_traced": int(tot[0]),
        "rays_dropped_lenslet_array": int(tot[1]),
        "rays_dropped_outside_sensor": int(tot[2]),
        "rays_recorded": int(tot[3]),
        "intensity_traced": float(np.dot(nrays.astype(np.float64), inten)),
        "intensity_lost": float(lost.sum()),
        "y_direction": "up; row 0 is the top",
    }
    if not imp.ideal:
        attrs.update(imp.to_attrs())
    return xr.DataArray(image, dims=("row", "col"), coords=_sensor_coords(camera), name="intensity", attrs=attrs)


def render_pinhole(
    camera: PlenopticCamera,
    *,
    fnumber: float = 16,
    count: int = 500_000,
    rays_per_point: int = 100,
    seed: int = 0,
    method: str = METHODS[0],
    imperfections: CameraImperfections | Mapping[str, Any] | None = None,
    **kwargs: Any,
) -> xr.DataArray:
    """Calibration "pinhole" image (sec. 5.1).

    Many points on the object focal plane (:func:`lfstudy.simulate.particles.pinhole_field`)
    imaged with the main lens stopped down to ``fnumber``: each lenslet then
    images a small spot of the aperture at its projected centre. The camera's
    diffraction sigmas follow the new f-number automatically.

    ``method="exact"`` (the default, as for :func:`render`) computes the
    expected image of the uniform field these points sample
    (:func:`lfstudy.simulate.exact.render_pinhole_exact`, no point or ray
    noise); ``"montecarlo"`` traces ``rays_per_point`` rays from each of
    ``count`` random points. Extra keyword arguments go to :func:`render`
    (its noise options apply to both methods). ``imperfections``: as for :func:`render` (the
    points are imaged through the imperfect camera; their field is the nominal camera's).
    """
    from lfstudy.simulate.particles import pinhole_field

    if method not in METHODS:
        raise RaytraceError(f"method = {method!r}: allowed values are {', '.join(map(repr, METHODS))}")
    _check_rays(rays_per_point, "rays_per_point")
    if method == "exact":
        defaults = (("shot_noise", False), ("read_noise", 0.0), ("full_well", None), ("bit_depth", None))
        noise = [kwargs.pop(k, d) for k, d in defaults]
        _check_noise(noise[1], noise[3])
        da = render_pinhole_exact(
            camera,
            fnumber=fnumber,
            count=count,
            rays_per_point=rays_per_point,
            seed=seed,
            imperfections=imperfections,
            **kwargs,
        )
        return _finish(da, int(seed), *noise)
    cam = camera.with_(fnumber=float(fnumber))
    field = pinhole_field(camera, count=count, seed=seed)
    img = render(cam, field, rays_per_point, seed, method=method, imperfections=imperfections, **kwargs)
    img.attrs.update(
        long_name="simulated pinhole calibration image", pinhole_fnumber=float(fnumber), pinhole_count=int(count)
    )
    return img


# ------------------------------------------------------------ angular statistics
def incidence_angle_bound(camera: PlenopticCamera) -> float:
    """Geometric per-axis bound on the ray angle at the sensor [rad].

    A ray from the aperture edge (−R) to the far edge (+pl/2) of a lenslet at
    the sensor edge (half-width W/2, half-height counted likewise) leaves the
    lenslet with slope (W/2 + pl/2 + R)/si + pl/(2 fl). Eq. 4.28
    (:attr:`PlenopticCamera.max_incidence_angle`) adds the lenslet half-angle
    to the chief-ray angle of the sensor corner and leaves out the aperture
    radius, so a small fraction of rays exceeds it (see
    :func:`angle_histograms`); this bound holds for every ray (up to the
    diffraction shifts, a few σ/fl).
    """
    half = max(camera.sensor_width, camera.sensor_height) / 2.0 + camera.lenslet_pitch / 2.0
    slope = (half + camera.aperture_diameter / 2.0) / camera.si + camera.lenslet_pitch / (
        2.0 * camera.lenslet_focal_length
    )
    return math.atan(slope)


def angle_histograms(
    camera: PlenopticCamera,
    particles: xr.Dataset,
    rays_per_particle: int,
    seed: int,
    *,
    bins: int = 90,
    max_angle: float = math.radians(30.0),
    diffraction: bool = True,
    n_chunks: int = DEFAULT_CHUNKS,
) -> xr.Dataset:
    """Histograms of the ray angles θ (x–z plane) and φ (y–z plane) arriving at the sensor.

    Sec. 4.3.4, Figs 4.25–4.26: sensors with microlenses lose quantum
    efficiency beyond about ±10°. The same rays as :func:`render` (same seed)
    are traced, but no image is kept, so a full-size sensor costs no memory.

    Returns
    -------
    xarray.Dataset
        ``theta_count`` / ``phi_count`` over ``angle`` (bin centres, rad), with
        attrs: the eq. 4.28 bound (``max_incidence_angle_eq428``), the
        geometric bound (:func:`incidence_angle_bound`), the largest |θ|, |φ|
        and total incidence angle traced, the fractions of rays beyond 10° and
        beyond eq. 4.28 (per axis), and the ray counts.
    """
    n = _check_rays(rays_per_particle)
    if not isinstance(bins, (int, np.integer)) or bins < 1:
        raise RaytraceError(f"bins = {bins!r}: must be an integer >= 1")
    if not (0 < max_angle < math.pi / 2):
        raise RaytraceError(f"max_angle = {max_angle!r}: allowed range is (0, pi/2) rad")
    x, y, z, inten = _particle_arrays(camera, particles)
    nrays = ray_counts(camera, particles, n)
    _, stats, _, hist, amax = _run_kernel(
        camera,
        x,
        y,
        z,
        inten,
        nrays,
        _seed_u64(seed),
        diffraction=diffraction,
        n_chunks=n_chunks,
        record=False,
        nbins=int(bins),
        hmax=float(max_angle),
    )
    h = hist.sum(axis=0)
    edges = np.linspace(-max_angle, max_angle, int(bins) + 1)
    centres = 0.5 * (edges[1:] + edges[:-1])
    rec = int(stats[:, 3].sum())
    eq428 = camera.max_incidence_angle

    def frac(counts: np.ndarray, limit: float) -> float:
        # Whole bins beyond the limit (bin edges are reported with the result).
        return float(counts[np.abs(centres) > limit].sum() / max(rec, 1))

    angle_attrs = {"units": "rad", "long_name": "incidence angle at the sensor"}
    return xr.Dataset(
        {
            "theta_count": ("angle", h[0], {"units": "rays", "long_name": "rays per θ bin (x–z plane)"}),
            "phi_count": ("angle", h[1], {"units": "rays", "long_name": "rays per φ bin (y–z plane)"}),
        },
        coords={"angle": ("angle", centres, angle_attrs), "angle_edges": ("edge", edges, angle_attrs)},
        attrs={
            "max_incidence_angle_eq428": eq428,
            "incidence_angle_bound": incidence_angle_bound(camera),
            "max_abs_theta": float(amax[:, 0].max()),
            "max_abs_phi": float(amax[:, 1].max()),
            "max_incidence_angle_traced": float(amax[:, 2].max()),
            "fraction_theta_over_10deg": frac(h[0], math.radians(10)),
            "fraction_phi_over_10deg": frac(h[1], math.radians(10)),
            "fraction_theta_over_eq428": frac(h[0], eq428),
            "fraction_phi_over_eq428": frac(h[1], eq428),
            "rays_recorded": rec,
            "rays_traced": int(stats[:, 0].sum()),
            "seed": int(seed),
            "rays_per_particle": n,
            **camera.to_attrs(),
        },
    )


def write_image(image: xr.DataArray, stem: str | Path) -> tuple[Path, Path]:
    """Write an image as ``STEM.tif`` (camera parameters in its JSON metadata) and ``STEM.zarr``.

    Float images are stored as float32 TIFF; integer (bit-depth) images keep
    their dtype. Both go through :mod:`lfstudy.io` (atomic writes).
    """
    from lfstudy import io

    stem = Path(stem)
    dtype = None if np.issubdtype(image.dtype, np.integer) else "float32"
    tif = io.write_tiff(image, stem.with_name(stem.name + ".tif"), dtype=dtype)
    zar = io.write_zarr(image, stem.with_name(stem.name + ".zarr"), name="intensity")
    return tif, zar
