"""The plenoptic projector: the registered light field as a linear function of a voxel volume.

Every light-field sample (lenslet l, pixel p behind it) is a beam of rays: the
rays that cross the lenslet's aperture (a pl × pl square at the lenslet plane)
and reach the pixel (a pp × pp square at fl behind a lenslet focused at
infinity, i.e. a box of slopes t = (pixel − lenslet centre)/fl ± pp/(2 fl),
eqs 5.6–5.9). Everything here comes from the calibration and the camera
model, never from the simulator's rays (no inverse crime): the lenslet
centres and the pixel slopes are the light field's coordinates
(:func:`lfstudy.lightfield.register`).

Geometry (paraxial thin lenses, sec. 4.1). A ray at lenslet-plane position
l with slope t left the main lens at a = l − si·t; before the lens its slope
was t + a/fm, so at object distance d = so + z it passed

    X(z) = α·l − β·t,   α = 1 − d/fm,   β = si·α + d,

(α = 1/M, β = 0 at z = 0: the lenslet images onto one in-plane voxel). With l
and t uniform over their boxes, the beam's cross-section at depth z is the
sum of two uniform variables: a trapezoid of half-widths |α|·pl/2 and
|β|·pp/(2 fl) per axis. The fraction F of the beam crossing voxel q of plane
z is a difference of the trapezoid's CDF (exact, no sampling).

Weights. Changing variables from (point, aperture point) to (l, t) has
Jacobian d² per axis pair; with the collected solid angle ∝ (so/d)² (eq.
4.14) the fraction of a voxel's light that a sample records is

    w = K·v·Fx·Fy,   K = so²·(pl·pp/fl)² / (dx·dy·π·R²),

R the main-lens aperture radius and v the fraction of the sample's rays that
pass inside the aperture disc (vignetting; 0 for pixels outside the lenslet's
image of the aperture). Summed over the samples of an in-focus lenslet, w = 1:
a volume value is the image signal its light produces. The lenslet grid's
rotation is neglected in the beam (the lenslet square is taken axis-aligned).

Per-axis weight tables are precomputed per plane (a few voxels per beam per
axis), so projection and back-projection are multiply-adds only. Forward
projection runs in parallel over rays, back-projection over planes: every
output element is written by one thread in a fixed order, so results do not
depend on the thread count.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import xarray as xr
from numba import njit, prange

from lfstudy.lightfield.volcal import VolumetricCalibration, VolumetricCalibrationError
from lfstudy.optics import PlenopticCamera
from lfstudy.reconstruct.grid import ReconstructionGrid

__all__ = ["ProjectorError", "PlenopticProjector"]


class ProjectorError(ValueError):
    """Light field, calibration, camera and grid do not fit together."""


# ------------------------------------------------------------------ kernels
@njit(inline="always", cache=True)
def _sum_uniform_cdf(d, a, b):
    """CDF at d of U(−a, a) + U(−b, b) (a trapezoid), for a, b >= 0."""
    if a < b:
        a, b = b, a
    if d <= -a - b:
        return 0.0
    if d >= a + b:
        return 1.0
    if b <= 1e-12 * a:  # one box only (in focus: β = 0)
        return (d + a) / (2.0 * a)
    if d <= b - a:
        e = d + a + b
        return e * e / (8.0 * a * b)
    if d <= a - b:
        return (d + a) / (2.0 * a)
    e = a + b - d
    return 1.0 - e * e / (8.0 * a * b)


@njit(inline="always", cache=True)
def _sum_uniform_cdf_integral(d, a, b):
    """∫_{−∞}^{d} CDF(s) ds for the CDF of :func:`_sum_uniform_cdf` (piecewise cubic; → d for large d)."""
    if a < b:
        a, b = b, a
    if d <= -a - b:
        return 0.0
    if d >= a + b:
        return d
    if b <= 1e-12 * a:
        e = d + a
        return e * e / (4.0 * a)
    b2a = b * b / (3.0 * a)
    if d <= b - a:
        e = d + a + b
        return e * e * e / (24.0 * a * b)
    if d <= a - b:
        e = d + a
        return b2a + (e * e - b * b) / (4.0 * a)
    e = a + b - d
    return b2a + a - b + (d - a + b) - (8.0 * b * b * b - e * e * e) / (24.0 * a * b)


@njit(parallel=True, cache=True)
def _axis_tables(centre, slope, alpha, beta, half_l, half_t, c0, dc, nc, kks, start, w, woff):  # pragma: no cover
    """Per pixel p (of a lenslet), plane k and lenslet l: first voxel and K weights of the beam along one axis.

    Tables are laid out [k, l, p] so a view (one pixel under every lenslet) reads
    them contiguously, plane by plane; the weights are flat, plane k's ``kks[k]`` per beam from
    ``woff[k]`` (:func:`_wbase`: no plane padded to the widest plane's K).

    A voxel is a linear-interpolation (tent) basis function of half-width dc,
    so a point between two voxel centres is shared between them and
    reconstructions keep sub-voxel positions. The weight of voxel q is the
    tent averaged over the beam's trapezoid profile: the second difference of
    the profile's CDF integral, (G(e + dc) − 2 G(e) + G(e − dc))/dc with
    e = x_q − beam centre (exact).
    """
    nz = alpha.shape[0]
    nl, n = slope.shape
    for k in prange(nz):
        kk = kks[k]  # voxels a beam can touch in this plane
        a = abs(alpha[k]) * half_l
        b = abs(beta[k]) * half_t
        for l in range(nl):
            for p in range(n):
                xc = alpha[k] * centre[l] - beta[k] * slope[l, p]
                o = _wbase(woff, k, l, p, n, kk)
                start[k, l, p] = _beam_row(xc, a, b, c0, dc, nc, kk, w[o : o + kk])


@njit(inline="always", cache=True)
def _wbase(woff, k, l, p, n, kk):
    """Index in a flat weight table of the first of beam (l, p)'s ``kk`` weights on plane k."""
    return woff[k] + (l * n + p) * kk


@njit(inline="always", cache=True)
def _beam_row(xc, a, b, c0, dc, nc, kk, w):
    """One beam's table row on one plane: its first voxel (the ``kk`` it can touch kept inside the
    ``nc`` of the axis) and their weights in ``w``, for a beam centred at ``xc``."""
    q0 = math.floor((xc - a - b - c0) / dc)
    if q0 > nc - kk:
        q0 = nc - kk
    if q0 < 0:
        q0 = 0
    _tent_weights(xc, a, b, c0, dc, q0, kk, w)
    return q0


@njit(inline="always", cache=True)
def _tent_weights(xc, a, b, c0, dc, q0, kk, w):
    """w[j] = tent voxel q0 + j averaged over the trapezoid beam profile centred at xc (second
    difference of the profile's CDF integral)."""
    gm = _sum_uniform_cdf_integral(c0 + (q0 - 1) * dc - xc, a, b)
    g0 = _sum_uniform_cdf_integral(c0 + q0 * dc - xc, a, b)
    for j in range(kk):
        gp = _sum_uniform_cdf_integral(c0 + (q0 + j + 1) * dc - xc, a, b)
        w[j] = (gp - 2.0 * g0 + gm) / dc
        gm = g0
        g0 = gp


@njit(parallel=True, cache=True)
def _axis_tables_at(xcs, alpha, beta, half_l, half_t, c0, dc, nc, kks, start, w, woff):  # pragma: no cover - jitted
    """:func:`_axis_tables` with the beam centres given, ``xcs[k, l, p]`` (the volumetric mapping)."""
    nz, nl, n = xcs.shape
    for k in prange(nz):
        kk = kks[k]
        a = abs(alpha[k]) * half_l
        b = abs(beta[k]) * half_t
        for l in range(nl):
            for p in range(n):
                o = _wbase(woff, k, l, p, n, kk)
                start[k, l, p] = _beam_row(xcs[k, l, p], a, b, c0, dc, nc, kk, w[o : o + kk])


@njit(inline="always", cache=True)
def _poly2(c, ex, ey, xp, yp):
    """Σ_t c[t]·x^ex[t]·y^ey[t] and its gradient, from the powers xp[i] = x^i, yp[i] = y^i."""
    v = 0.0
    gx = 0.0
    gy = 0.0
    for t in range(c.shape[0]):
        a = ex[t]
        b = ey[t]
        v += c[t] * xp[a] * yp[b]
        if a > 0:
            gx += c[t] * a * xp[a - 1] * yp[b]
        if b > 0:
            gy += c[t] * b * xp[a] * yp[b - 1]
    return v, gx, gy


@njit(inline="always", cache=True)
def _powers(x, out):
    out[0] = 1.0
    for i in range(1, out.shape[0]):
        out[i] = out[i - 1] * x


@njit(inline="always", cache=True)
def _partner(r, d, n, valid_line):
    """The neighbour of sub-aperture r that interpolates (or extrapolates) towards offset d: r + sign(d)
    if calibrated, else r − sign(d), else r itself (no gradient)."""
    sd = 1 if d >= 0.0 else -1
    q = r + sd
    if 0 <= q < n and valid_line[q]:
        return q
    q = r - sd
    if 0 <= q < n and valid_line[q]:
        return q
    return r


@njit(parallel=True, cache=True)
def _mapped_centres(c2, ex, ey, valid, s0, t0, u, v, x0, y0, xs, ys, wgt, xcs, ycs, bad, shear):  # pragma: no cover
    """Beam centres through the volumetric mapping (Hall 2018), reduced to the per-axis tables.

    For plane k, lenslet l and sample (pr, pc): the polynomial of the sample's fractional
    sub-aperture (u[l, pc], v[l, pr]), linearly interpolated from the nearest calibrated
    sub-aperture and its calibrated neighbours (c2: coefficients in normalised x, y with z
    fixed to the plane), is solved for the object point (x, y) it maps to the lenslet's
    position (s0[l], t0[l]) by Newton steps from the thin-lens centre (x0, y0). The x table
    of (k, l, pc) is the ``wgt``-weighted mean over pr of the sample centres, the y table of
    (k, l, pr) the mean over pc. ``bad[l, pr, pc]``: the sample's sub-aperture is not
    calibrated or a solve did not converge (it is left out). ``shear[l]``: the largest
    |centre − table| [mm] the per-axis reduction makes at lenslet l.
    """
    nz = c2.shape[0]
    n = c2.shape[2]
    nt = c2.shape[4]
    nl = s0.shape[0]
    for l in prange(nl):
        cs = np.empty(nt)
        ct = np.empty(nt)
        xp = np.empty(max(ex.max(), ey.max()) + 1)
        yp = np.empty(xp.shape[0])
        X = np.zeros((nz, n, n))
        Y = np.zeros((nz, n, n))
        for pr in range(n):
            rv = math.floor(v[l, pr] + 0.5)
            dv = v[l, pr] - rv
            for pc in range(n):
                if wgt[l, pr, pc] <= 0.0:
                    continue
                ru = math.floor(u[l, pc] + 0.5)
                du = u[l, pc] - ru
                if ru < 0 or ru >= n or rv < 0 or rv >= n or not valid[rv, ru]:
                    bad[l, pr, pc] = True
                    continue
                pu = _partner(ru, du, n, valid[rv])
                pv = _partner(rv, dv, n, valid[:, ru])
                fu = du / (pu - ru) if pu != ru else 0.0
                fv = dv / (pv - rv) if pv != rv else 0.0
                for k in range(nz):
                    for t in range(nt):
                        b0 = c2[k, 0, rv, ru, t]
                        cs[t] = b0 + fu * (c2[k, 0, rv, pu, t] - b0) + fv * (c2[k, 0, pv, ru, t] - b0)
                        b1 = c2[k, 1, rv, ru, t]
                        ct[t] = b1 + fu * (c2[k, 1, rv, pu, t] - b1) + fv * (c2[k, 1, pv, ru, t] - b1)
                    xn = x0[k, l, pc] / xs
                    yn = y0[k, l, pr] / ys
                    conv = False
                    for _ in range(20):
                        _powers(xn, xp)
                        _powers(yn, yp)
                        ps, psx, psy = _poly2(cs, ex, ey, xp, yp)
                        pt, ptx, pty = _poly2(ct, ex, ey, xp, yp)
                        fs = ps - s0[l]
                        ft = pt - t0[l]
                        if abs(fs) + abs(ft) < 1e-9:  # lenslets
                            conv = True
                            break
                        det = psx * pty - psy * ptx
                        if not (math.isfinite(det) and det != 0.0):
                            break
                        xn -= (pty * fs - psy * ft) / det
                        yn -= (psx * ft - ptx * fs) / det
                    if not conv:
                        bad[l, pr, pc] = True
                        break
                    X[k, pr, pc] = xn * xs
                    Y[k, pr, pc] = yn * ys
        sh = 0.0
        for k in range(nz):
            for pc in range(n):
                sw = 0.0
                sx = 0.0
                for pr in range(n):
                    if wgt[l, pr, pc] > 0.0 and not bad[l, pr, pc]:
                        sw += wgt[l, pr, pc]
                        sx += wgt[l, pr, pc] * X[k, pr, pc]
                xcs[k, l, pc] = sx / sw if sw > 0.0 else x0[k, l, pc]
            for pr in range(n):
                sw = 0.0
                sy = 0.0
                for pc in range(n):
                    if wgt[l, pr, pc] > 0.0 and not bad[l, pr, pc]:
                        sw += wgt[l, pr, pc]
                        sy += wgt[l, pr, pc] * Y[k, pr, pc]
                ycs[k, l, pr] = sy / sw if sw > 0.0 else y0[k, l, pr]
            for pr in range(n):
                for pc in range(n):
                    if wgt[l, pr, pc] > 0.0 and not bad[l, pr, pc]:
                        sh = max(sh, abs(X[k, pr, pc] - xcs[k, l, pc]), abs(Y[k, pr, pc] - ycs[k, l, pr]))
        shear[l] = sh


@njit(parallel=True, cache=True)
def _vignetting(lx, ly, sx, sy, si, half_l, half_t, radius, out):  # pragma: no cover - jitted
    """Fraction of each sample's rays whose aperture point a = l − si·t lies in the disc."""
    nl, n = sx.shape
    reach = math.sqrt(2.0) * (half_l + si * half_t)
    r2 = radius * radius
    for l in prange(nl):
        for pr in range(n):
            ay0 = ly[l] - si * sy[l, pr]
            for pc in range(n):
                ax0 = lx[l] - si * sx[l, pc]
                rc = math.sqrt(ax0 * ax0 + ay0 * ay0)
                if rc + reach <= radius:
                    out[l, pr, pc] = 1.0
                    continue
                if rc - reach >= radius:
                    out[l, pr, pc] = 0.0
                    continue
                # 3 x 3 midpoints of each uniform (lenslet box, slope box) per axis: 81 rays
                hit = 0
                for i1 in range(3):
                    for i2 in range(3):
                        ax = ax0 + (i1 - 1) * (2.0 * half_l / 3.0) - si * (i2 - 1) * (2.0 * half_t / 3.0)
                        for j1 in range(3):
                            for j2 in range(3):
                                ay = ay0 + (j1 - 1) * (2.0 * half_l / 3.0) - si * (j2 - 1) * (2.0 * half_t / 3.0)
                                if ax * ax + ay * ay <= r2:
                                    hit += 1
                out[l, pr, pc] = hit / 81.0


@njit(inline="always", cache=True)
def _ray_sum(vol, k, y0, x0, wy, oy, wx, ox, ny, nx):
    """Σ_a Σ_b wy[oy + a]·wx[ox + b]·vol[k, y0 + a, x0 + b] over the ny x nx weights of one beam."""
    s = 0.0
    for a in range(ny):
        wa = wy[oy + a]
        if wa == 0.0:
            continue
        acc = 0.0
        for b in range(nx):
            acc += wx[ox + b] * vol[k, y0 + a, x0 + b]
        s += wa * acc
    return s


@njit(parallel=True, cache=True)
def _forward(vol, lens, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, gain, out):  # pragma: no cover - jitted
    """out[l, pr, pc] = gain[l, pr, pc] · Σ_k Σ_voxels Fy·Fx·vol, for the active lenslets ``lens``."""
    nz = vol.shape[0]
    n = out.shape[1]
    for m in prange(lens.shape[0]):
        l = lens[m]
        for pr in range(n):
            for pc in range(n):
                g = gain[l, pr, pc]
                if g == 0.0:
                    continue
                s = 0.0
                for k in range(nz):
                    oy = _wbase(oys, k, l, pr, n, kys[k])
                    ox = _wbase(oxs, k, l, pc, n, kxs[k])
                    s += _ray_sum(vol, k, sys_[k, l, pr], sxs[k, l, pc], wys, oy, wxs, ox, kys[k], kxs[k])
                out[l, pr, pc] = g * s


@njit(parallel=True, cache=True)
def _adjoint(vals, lens, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, gain, out):  # pragma: no cover - jitted
    """out += Aᵀ vals: every sample's gain·value spread over its voxels (planes in parallel)."""
    nz = out.shape[0]
    n = vals.shape[1]
    for k in prange(nz):
        kx = kxs[k]
        ky = kys[k]
        for m in range(lens.shape[0]):
            l = lens[m]
            for pr in range(n):
                y0 = sys_[k, l, pr]
                for pc in range(n):
                    g = gain[l, pr, pc] * vals[l, pr, pc]
                    if g == 0.0:
                        continue
                    x0 = sxs[k, l, pc]
                    oy = _wbase(oys, k, l, pr, n, ky)
                    ox = _wbase(oxs, k, l, pc, n, kx)
                    for a in range(ky):
                        wa = wys[oy + a] * g
                        if wa == 0.0:
                            continue
                        for b in range(kx):
                            out[k, y0 + a, x0 + b] += wa * wxs[ox + b]


@njit(parallel=True, cache=True)
def _view_forward(vol, lens, pr, pc, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, partial):  # pragma: no cover - jitted
    """Projection of one view (pixel pr, pc under every lenslet), plane by plane: partial[k, m]."""
    nz = vol.shape[0]
    n = sxs.shape[2]
    for k in prange(nz):
        kx = kxs[k]
        ky = kys[k]
        for m in range(lens.shape[0]):
            l = lens[m]
            oy = _wbase(oys, k, l, pr, n, ky)
            ox = _wbase(oxs, k, l, pc, n, kx)
            partial[k, m] = _ray_sum(vol, k, sys_[k, l, pr], sxs[k, l, pc], wys, oy, wxs, ox, ky, kx)


@njit(parallel=True, cache=True)
def _view_accumulate(lens, pr, pc, vals, use, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, num):  # pragma: no cover
    """num += Σ F·vals over the beams of one view (fractions F = Fy·Fx; planes in parallel)."""
    nz = num.shape[0]
    n = sxs.shape[2]
    for k in prange(nz):
        kx = kxs[k]
        ky = kys[k]
        for m in range(lens.shape[0]):
            if not use[m]:
                continue
            l = lens[m]
            v = vals[m]
            y0 = sys_[k, l, pr]
            x0 = sxs[k, l, pc]
            oy = _wbase(oys, k, l, pr, n, ky)
            ox = _wbase(oxs, k, l, pc, n, kx)
            for a in range(ky):
                wa = wys[oy + a] * v
                if wa == 0.0:
                    continue
                for b in range(kx):
                    num[k, y0 + a, x0 + b] += wa * wxs[ox + b]


#: Plane blocks of the column projection: a fixed count, so the sum over planes is done in
#: the same order whatever the number of threads.
_PLANE_BLOCKS = 8


@njit(parallel=True, cache=True)
def _column_forward(vol, lens, pc, prs, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, out):  # pragma: no cover - jitted
    """Projection of the views (prs[j], pc) of one pixel column: out[block, j, m] for lenslet lens[m].

    The views of a column share their x weights, so per plane and lenslet the
    volume is first interpolated in x along the rows any of them crosses, then
    each view sums its y weights over that column. Planes are split into
    ``out.shape[0]`` fixed blocks (one partial sum each), read in table order.
    """
    nz = vol.shape[0]
    nb = out.shape[0]
    nv = prs.shape[0]
    n = sxs.shape[2]
    for blk in prange(nb):
        col = np.empty(vol.shape[1])
        for j in range(nv):
            for m in range(lens.shape[0]):
                out[blk, j, m] = 0.0
        for k in range(blk * nz // nb, (blk + 1) * nz // nb):
            kx = kxs[k]
            ky = kys[k]
            for m in range(lens.shape[0]):
                l = lens[m]
                x0 = sxs[k, l, pc]
                ylo = sys_[k, l, prs[0]]
                yhi = ylo
                for j in range(1, nv):
                    y0 = sys_[k, l, prs[j]]
                    ylo = min(ylo, y0)
                    yhi = max(yhi, y0)
                ox = _wbase(oxs, k, l, pc, n, kx)
                for y in range(ylo, yhi + ky):
                    acc = 0.0
                    for b in range(kx):
                        acc += wxs[ox + b] * vol[k, y, x0 + b]
                    col[y] = acc
                for j in range(nv):
                    y0 = sys_[k, l, prs[j]]
                    oy = _wbase(oys, k, l, prs[j], n, ky)
                    s = 0.0
                    for a in range(ky):
                        s += wys[oy + a] * col[y0 + a]
                    out[blk, j, m] += s


@njit(parallel=True, cache=True)
def _column_accumulate(lens, pc, prs, vals, chans, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, out):  # pragma: no cover
    """out[chans[c]] += Σ F·vals[c, j, m] over the beams of the views (prs[j], pc) of one column.

    Several value sets share one pass over the weight tables (channels ``c``);
    planes run in parallel, each written by one thread in a fixed order.
    """
    nz = out.shape[1]
    nv = prs.shape[0]
    nc = vals.shape[0]
    n = sxs.shape[2]
    for k in prange(nz):
        kx = kxs[k]
        ky = kys[k]
        col = np.zeros((nc, out.shape[2]))
        for m in range(lens.shape[0]):
            l = lens[m]
            ylo = sys_[k, l, prs[0]]
            yhi = ylo
            any_v = False
            for j in range(nv):
                y0 = sys_[k, l, prs[j]]
                ylo = min(ylo, y0)
                yhi = max(yhi, y0)
                for c in range(nc):
                    if vals[c, j, m] != 0.0:
                        any_v = True
            if not any_v:
                continue
            for j in range(nv):
                y0 = sys_[k, l, prs[j]]
                oy = _wbase(oys, k, l, prs[j], n, ky)
                for c in range(nc):
                    v = vals[c, j, m]
                    if v == 0.0:
                        continue
                    for a in range(ky):
                        col[c, y0 + a] += wys[oy + a] * v
            x0 = sxs[k, l, pc]
            ox = _wbase(oxs, k, l, pc, n, kx)
            for c in range(nc):
                o = chans[c]
                for y in range(ylo, yhi + ky):
                    cv = col[c, y]
                    if cv != 0.0:
                        for b in range(kx):
                            out[o, k, y, x0 + b] += cv * wxs[ox + b]
                        col[c, y] = 0.0


@njit(parallel=True, cache=True)
def _uniform_projection(lens, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, gain, out):  # pragma: no cover - jitted
    """out[l, pr, pc] = A·1: the projection of a uniform unit volume, from the table sums alone.

    With every voxel 1 a beam's sum over plane k is (Σ_b wx)(Σ_a wy), so no
    volume is read (the beam fractions that leave the grid are missing, as in
    the forward projection).
    """
    n = out.shape[1]
    nz = sxs.shape[0]
    for m in prange(lens.shape[0]):
        l = lens[m]
        sx = np.empty(n)
        sy = np.empty(n)
        acc = np.zeros((n, n))
        for k in range(nz):
            for p in range(n):
                t = 0.0
                ox = _wbase(oxs, k, l, p, n, kxs[k])
                for b in range(kxs[k]):
                    t += wxs[ox + b]
                sx[p] = t
                t = 0.0
                oy = _wbase(oys, k, l, p, n, kys[k])
                for a in range(kys[k]):
                    t += wys[oy + a]
                sy[p] = t
            for pr in range(n):
                for pc in range(n):
                    acc[pr, pc] += sy[pr] * sx[pc]
        for pr in range(n):
            for pc in range(n):
                out[l, pr, pc] = gain[l, pr, pc] * acc[pr, pc]


@njit(cache=True)
def _impulse(k, j, i, lens, sxs, wxs, oxs, kxs, sys_, wys, oys, kys, gain, out):  # pragma: no cover - jitted
    """out[l, pr, pc] = gain · Fy(j) · Fx(i) of plane k: the light field of one unit voxel."""
    n = out.shape[1]
    kx = kxs[k]
    ky = kys[k]
    for m in range(lens.shape[0]):
        l = lens[m]
        for pr in range(n):
            a = j - sys_[k, l, pr]
            if a < 0 or a >= ky:
                continue
            wa = wys[_wbase(oys, k, l, pr, n, ky) + a]
            if wa == 0.0:
                continue
            for pc in range(n):
                b = i - sxs[k, l, pc]
                if b < 0 or b >= kx:
                    continue
                out[l, pr, pc] = gain[l, pr, pc] * wa * wxs[_wbase(oxs, k, l, pc, n, kx) + b]


# ------------------------------------------------------------------ the volumetric mapping
def _volumetric_centres(
    lf: xr.DataArray,
    cal: xr.Dataset,
    grid: ReconstructionGrid,
    alpha: np.ndarray,
    beta: np.ndarray,
    lx: np.ndarray,
    ly: np.ndarray,
    sx: np.ndarray,
    sy: np.ndarray,
    vig: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Per-axis beam centres (nz, nl, n) through the volumetric calibration (:func:`_mapped_centres`).

    Sub-apertures: volcal indexes them on the angular grid of
    :func:`lfstudy.lightfield.volcal.resample_angular`, sub-aperture j at the local slope
    (j − (n−1)/2)·pp/fl exactly; a registered sample's local slope tan θ puts it at the
    fractional index tan θ·fl/pp + (n−1)/2 (rows: −tan φ, as there). Lenslet (row a, column b)
    sits at (s, t) = (b, a) in the sub-aperture images.

    Returns
    -------
    xcs, ycs : ndarray
        Beam centres [mm] per plane, lenslet and pixel column (x) or row (y).
    bad : ndarray (nl, n, n) bool
        Samples left out: sub-aperture not calibrated, or the mapping not invertible there.
    shear : float
        The largest distance [mm] between a sample's own centre and its per-axis table entry.
    """
    z = np.asarray(grid.z, dtype=np.float64)
    try:  # the calibration's own checks: a whole fit, of this light field, over the grid's depths
        vcal = VolumetricCalibration.of(cal)
        vcal.check_lightfield(lf)
        vcal.check_depths(z, "reconstruction grid")
    except VolumetricCalibrationError as exc:
        raise ProjectorError(str(exc)) from None
    cal = vcal.dataset
    a = cal.attrs
    nly, nlx, n = lf.sizes["lrow"], lf.sizes["lcol"], lf.sizes["prow"]
    exps = np.asarray(cal["exponents"].values, dtype=np.int64)
    coef = np.asarray(cal["coef"].values, dtype=np.float64)  # (axis, prow, pcol, term)
    pairs = sorted({(int(e[0]), int(e[1])) for e in exps})
    col = {p: i for i, p in enumerate(pairs)}
    zn = (z - a["z_center"]) / a["z_scale"]
    m = np.zeros((z.size, exps.shape[0], len(pairs)))
    for t, (ea, eb, ec) in enumerate(exps):
        m[:, t, col[(int(ea), int(eb))]] = zn ** int(ec)
    c2 = np.ascontiguousarray(np.einsum("aijt,ktq->kaijq", coef, m))  # the polynomial in x, y on each plane
    ex = np.array([p[0] for p in pairs], np.int64)
    ey = np.array([p[1] for p in pairs], np.int64)
    fl_pp = float(lf.attrs.get("lenslet_focal_length")) / float(lf.attrs.get("pixel_pitch"))
    nl = nly * nlx
    u = np.tan(lf["theta"].transpose("lrow", "lcol", "pcol").values).reshape(nl, n) * fl_pp + 0.5 * (n - 1)
    v = -np.tan(lf["phi"].transpose("lrow", "lcol", "prow").values).reshape(nl, n) * fl_pp + 0.5 * (n - 1)
    rows, cols = np.divmod(np.arange(nl), nlx)
    x0 = alpha[:, None, None] * lx[None, :, None] - beta[:, None, None] * sx[None]
    y0 = alpha[:, None, None] * ly[None, :, None] - beta[:, None, None] * sy[None]
    xcs = np.empty_like(x0)
    ycs = np.empty_like(y0)
    bad = np.zeros((nl, n, n), np.bool_)
    shear = np.zeros(nl)
    _mapped_centres(
        c2,
        ex,
        ey,
        np.ascontiguousarray(cal["valid"].values, dtype=np.bool_),
        cols.astype(np.float64),
        rows.astype(np.float64),
        np.ascontiguousarray(u),
        np.ascontiguousarray(v),
        x0,
        y0,
        float(a["x_scale"]),
        float(a["y_scale"]),
        vig,
        xcs,
        ycs,
        bad,
        shear,
    )
    if not np.all(np.isfinite(xcs)) or not np.all(np.isfinite(ycs)):
        raise ProjectorError("the volumetric calibration maps some beams to non-finite positions: refit it")
    return xcs, ycs, bad, float(shear.max(initial=0.0))


# ------------------------------------------------------------------ the projector
class PlenopticProjector:
    """Matrix-free plenoptic projector A: volume on a grid ↔ registered light field.

    Parameters
    ----------
    lightfield : xarray.DataArray
        A registered light field (:func:`lfstudy.lightfield.register`); only its
        coordinates are used here (lenslet centres ``x``, ``y``, ray angles
        ``theta``, ``phi``, bulk angles, ``valid``).
    camera : PlenopticCamera
        Main-lens focal length, aperture, si, so, lenslet pitch and focal
        length, pixel pitch.
    grid : ReconstructionGrid
        The voxel grid (x, y uniform).
    min_vignetting : float
        Samples whose rays are less than this fraction inside the aperture are
        left out (their measurement says little and the vignetting model is
        coarsest there).
    max_bytes : float
        Refuse weight tables larger than this.

    Notes
    -----
    ``forward(vol)`` returns the light field A·vol with the layout of
    ``lightfield``; ``adjoint(lf)`` returns Aᵀ·lf on the grid. They are exact
    transposes of each other (same tables, same gains).
    """

    def __init__(
        self,
        lightfield: xr.DataArray,
        camera: PlenopticCamera,
        grid: ReconstructionGrid,
        *,
        min_vignetting: float = 0.25,
        max_bytes: float = 6e9,
        calibration: xr.Dataset | None = None,
    ) -> None:
        lf = lightfield.transpose("lrow", "lcol", "prow", "pcol")
        for c in ("x", "y", "theta", "phi", "theta_bulk", "phi_bulk"):
            if c not in lf.coords:
                raise ProjectorError(
                    f"light field lacks the coordinate {c!r}; register it with lfstudy.lightfield.register"
                )
        if not (0.0 <= min_vignetting <= 1.0):
            raise ProjectorError(f"min_vignetting = {min_vignetting!r}: allowed range is [0, 1]")
        pp = float(lf.attrs.get("pixel_pitch", camera.pixel_pitch))
        if not math.isclose(pp, camera.pixel_pitch, rel_tol=1e-9):
            raise ProjectorError(f"light field pixel pitch {pp} mm does not match the camera's {camera.pixel_pitch} mm")
        for key, val in (("image_distance", camera.si), ("lenslet_focal_length", camera.lenslet_focal_length)):
            if key in lf.attrs and not math.isclose(float(lf.attrs[key]), val, rel_tol=1e-6):
                raise ProjectorError(f"light field {key} = {lf.attrs[key]} mm does not match the camera's {val} mm")
        self.camera = camera
        self.grid = grid
        self.shape_lf = (lf.sizes["lrow"], lf.sizes["lcol"], lf.sizes["prow"], lf.sizes["pcol"])
        nly, nlx, n, n2 = self.shape_lf
        if n != n2:
            raise ProjectorError(f"light field blocks must be square; got {n} x {n2} pixels")
        nl = nly * nlx
        self.n = n
        lx = np.ascontiguousarray(lf["x"].values, dtype=np.float64).ravel()
        ly = np.ascontiguousarray(lf["y"].values, dtype=np.float64).ravel()
        # Ray slopes at the lenslet plane: tan(local) + tan(bulk) = (pixel − lenslet centre)/fl.
        sx = np.ascontiguousarray(
            np.tan(lf["theta"].transpose("lrow", "lcol", "pcol").values) + np.tan(lf["theta_bulk"].values)[..., None]
        ).reshape(nl, n)
        sy = np.ascontiguousarray(
            np.tan(lf["phi"].transpose("lrow", "lcol", "prow").values) + np.tan(lf["phi_bulk"].values)[..., None]
        ).reshape(nl, n)
        valid = np.asarray(lf["valid"].values, bool).ravel() if "valid" in lf.coords else np.ones(nl, bool)
        f, si, so = camera.main_focal_length, camera.si, camera.so
        fl, pl = camera.lenslet_focal_length, camera.lenslet_pitch
        half_l, half_t = pl / 2.0, camera.pixel_pitch / (2.0 * fl)
        d = so + grid.z
        self.alpha = 1.0 - d / f
        self.beta = si * self.alpha + d
        # voxels a beam can touch along an axis, over all planes
        reach = np.abs(self.alpha) * half_l + np.abs(self.beta) * half_t
        dx, dy = grid.dx, grid.dy
        # tent voxels touched by a beam: its width plus one voxel each side, per plane
        self.kxs = np.minimum(grid.x.size, np.ceil(2.0 * reach / dx).astype(np.int64) + 3)
        self.kys = np.minimum(grid.y.size, np.ceil(2.0 * reach / dy).astype(np.int64) + 3)
        self.kx, self.ky = int(self.kxs.max()), int(self.kys.max())
        nz = grid.z.size
        # a beam's first voxel fits int16 on any grid up to 32,767 voxels a side (the refined candidate grid of a
        # full Table 4.3 frame: 867 x 579): half of int32's 0.47 GB there, the same indices
        idx = np.int16 if max(grid.x.size, grid.y.size) <= np.iinfo(np.int16).max else np.int32
        need = nl * n * int(self.kxs.sum() + self.kys.sum()) * 4 + 2 * nz * nl * n * np.dtype(idx).itemsize
        if need > max_bytes:
            raise ProjectorError(
                f"projector: weight tables of {need / 1e9:.3g} GB exceed {max_bytes / 1e9:.3g} GB "
                f"({nz} planes x {nl} lenslets x {n} pixels); use a coarser grid (grid.voxel_z)"
            )
        # flat weight tables, plane k's beams with kxs[k] (kys[k]) weights each from oxs[k] (oys[k]): padding
        # every plane to the widest one's K cost a fifth more (the refined grid of a full Table 4.3 frame: K 7-10)
        self.sxs = np.empty((nz, nl, n), idx)
        self.oxs = np.concatenate([[0], np.cumsum(nl * n * self.kxs)[:-1]]).astype(np.int64)
        self.wxs = np.zeros(int(nl * n * self.kxs.sum()), np.float32)
        self.sys = np.empty((nz, nl, n), idx)
        self.oys = np.concatenate([[0], np.cumsum(nl * n * self.kys)[:-1]]).astype(np.int64)
        self.wys = np.zeros(int(nl * n * self.kys.sum()), np.float32)
        vig = np.zeros((nl, n, n), np.float64)
        radius = camera.aperture_diameter / 2.0
        _vignetting(lx, ly, sx, sy, si, half_l, half_t, radius, vig)
        vig[~valid] = 0.0
        vig[vig < min_vignetting] = 0.0
        self.model = "thin_lens" if calibration is None else "volumetric"
        self.uncalibrated_samples = 0
        self.mapping_shear = 0.0
        if calibration is None:
            # Grid y ascends with the array index like object +y, and the sensor frame's y points up too.
            _axis_tables(
                lx,
                sx,
                self.alpha,
                self.beta,
                half_l,
                half_t,
                grid.x[0],
                dx,
                grid.x.size,
                self.kxs,
                self.sxs,
                self.wxs,
                self.oxs,
            )
            _axis_tables(
                ly,
                sy,
                self.alpha,
                self.beta,
                half_l,
                half_t,
                grid.y[0],
                dy,
                grid.y.size,
                self.kys,
                self.sys,
                self.wys,
                self.oys,
            )
        else:
            xcs, ycs, bad, shear = _volumetric_centres(
                lf, calibration, grid, self.alpha, self.beta, lx, ly, sx, sy, vig
            )
            self.uncalibrated_samples = int(np.count_nonzero(bad & (vig > 0)))
            vig[bad] = 0.0
            self.mapping_shear = float(shear) / min(dx, dy)
            _axis_tables_at(
                xcs,
                self.alpha,
                self.beta,
                half_l,
                half_t,
                grid.x[0],
                dx,
                grid.x.size,
                self.kxs,
                self.sxs,
                self.wxs,
                self.oxs,
            )
            _axis_tables_at(
                ycs,
                self.alpha,
                self.beta,
                half_l,
                half_t,
                grid.y[0],
                dy,
                grid.y.size,
                self.kys,
                self.sys,
                self.wys,
                self.oys,
            )
        self.vignetting = vig
        k_const = so**2 * (pl * camera.pixel_pitch / fl) ** 2 / (dx * dy * math.pi * radius**2)
        self.gain = np.ascontiguousarray(k_const * vig)
        self.lenses = np.flatnonzero(vig.reshape(nl, -1).max(axis=1) > 0).astype(np.int64)
        self._partial: np.ndarray | None = None
        self._gain_columns: dict[tuple[int, bytes], np.ndarray] = {}
        self.min_vignetting = float(min_vignetting)

    def planes(self, step: int, start: int = 0) -> PlenopticProjector:
        """The projector of the grid's planes ``start``, ``start + step``, ... (z every ``step``-th plane).

        Each plane's tables depend on that plane's depth alone, so the new projector's are views into
        this one's (no copy, no new memory) and its projections are those of a projector built for the
        thinned grid, byte for byte.
        """
        nz = self.grid.shape[0]
        if not (isinstance(step, (int, np.integer)) and step >= 1 and 0 <= start < nz):
            raise ProjectorError(f"planes: step = {step!r} must be >= 1 and start = {start!r} in [0, {nz})")
        sl = slice(int(start), None, int(step))
        g = self.grid
        other = copy.copy(self)
        other.grid = ReconstructionGrid(g.x, g.y, g.z[sl], spacing=g.spacing)
        other.alpha, other.beta = self.alpha[sl], self.beta[sl]
        other.kxs, other.kys = self.kxs[sl], self.kys[sl]
        other.sxs, other.sys = self.sxs[sl], self.sys[sl]  # the weights stay the same flat tables
        other.oxs, other.oys = self.oxs[sl], self.oys[sl]
        other._partial = None
        return other

    # ---------------------------------------------------------------- info
    @property
    def n_rays(self) -> int:
        """Samples that take part (inside the aperture, on valid lenslets)."""
        return int(np.count_nonzero(self.gain))

    @property
    def tables(self) -> tuple[np.ndarray, ...]:
        """The beam tables every kernel reads, in their argument order: x starts, flat weights, plane offsets and
        widths, then the same for y."""
        return self.sxs, self.wxs, self.oxs, self.kxs, self.sys, self.wys, self.oys, self.kys

    @property
    def table_bytes(self) -> int:
        nb = self.sxs.shape[1] * self.sxs.shape[2] * 4  # this grid's planes (a planes() view shares the tables)
        return int(nb * (self.kxs.sum() + self.kys.sum()) + self.sxs.nbytes + self.sys.nbytes)

    def _lf_array(self, lf: Any) -> np.ndarray:
        arr = lf.transpose("lrow", "lcol", "prow", "pcol").values if isinstance(lf, xr.DataArray) else np.asarray(lf)
        if tuple(arr.shape) != self.shape_lf:
            raise ProjectorError(
                f"light field of shape {tuple(arr.shape)} does not match the calibration's {self.shape_lf}"
            )
        return np.ascontiguousarray(arr, dtype=np.float64).reshape(self.shape_lf[0] * self.shape_lf[1], self.n, self.n)

    def _vol_array(self, vol: Any) -> np.ndarray:
        arr = vol.values if isinstance(vol, xr.DataArray) else np.asarray(vol)
        if tuple(arr.shape) != self.grid.shape:
            raise ProjectorError(f"volume of shape {tuple(arr.shape)} does not fit the grid {self.grid.shape}")
        return np.ascontiguousarray(arr, dtype=np.float64)

    # ---------------------------------------------------------------- A, Aᵀ
    def forward(self, vol: Any) -> np.ndarray:
        """A·vol: the light field (lrow, lcol, prow, pcol) a volume produces."""
        v = self._vol_array(vol)
        out = np.zeros((self.shape_lf[0] * self.shape_lf[1], self.n, self.n))
        _forward(v, self.lenses, *self.tables, self.gain, out)
        return out.reshape(self.shape_lf)

    def adjoint(self, lf: Any) -> np.ndarray:
        """Aᵀ·lf: a light field spread back over the grid (nz, ny, nx)."""
        g = self._lf_array(lf)
        out = np.zeros(self.grid.shape)
        _adjoint(g, self.lenses, *self.tables, self.gain, out)
        return out

    def impulse(self, k: int, j: int, i: int) -> np.ndarray:
        """A·e for the unit voxel (k, j, i): its light field (lrow, lcol, prow, pcol), from plane k's tables."""
        out = np.zeros((self.shape_lf[0] * self.shape_lf[1], self.n, self.n))
        _impulse(int(k), int(j), int(i), self.lenses, *self.tables, self.gain, out)
        return out.reshape(self.shape_lf)

    # ---------------------------------------------------------------- views
    def views(self) -> list[tuple[int, int]]:
        """The (pixel row, pixel column) of every sub-aperture view that holds a sample."""
        nl = self.shape_lf[0] * self.shape_lf[1]
        used = self.gain.reshape(nl, self.n, self.n).max(axis=0) > 0
        return [(int(r), int(c)) for r, c in zip(*np.nonzero(used))]

    def view_forward(self, vol: np.ndarray, pr: int, pc: int, out: np.ndarray) -> np.ndarray:
        """Projection of view (pr, pc) for every active lenslet (``self.lenses`` order)."""
        if self._partial is None or self._partial.shape != (self.grid.shape[0], self.lenses.size):
            self._partial = np.empty((self.grid.shape[0], self.lenses.size))
        _view_forward(vol, self.lenses, pr, pc, *self.tables, self._partial)
        np.sum(self._partial, axis=0, out=out)  # planes in a fixed order: thread-count independent
        out *= self.gain[self.lenses, pr, pc]
        return out

    def columns(self) -> list[tuple[int, np.ndarray]]:
        """Views grouped by pixel column: ``[(pc, rows pr of the active views), ...]``."""
        cols: dict[int, list[int]] = {}
        for pr, pc in self.views():
            cols.setdefault(pc, []).append(pr)
        return [(pc, np.asarray(prs, dtype=np.int64)) for pc, prs in sorted(cols.items())]

    def column_forward(self, vol: np.ndarray, pc: int, prs: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Projections of the views (prs[j], pc): ``out[j, m]`` for lenslet ``self.lenses[m]``."""
        nb = min(_PLANE_BLOCKS, self.grid.shape[0])
        part = np.empty((nb, prs.size, self.lenses.size))
        _column_forward(vol, self.lenses, pc, prs, *self.tables, part)
        np.sum(part, axis=0, out=out)  # blocks in a fixed order: thread-count independent
        key = (int(pc), prs.tobytes())
        if key not in self._gain_columns:  # gathered once: a gather per call cost more than the sums
            self._gain_columns[key] = self.column_values(self.gain, pc, prs)
        out *= self._gain_columns[key]
        return out

    def column_values(self, samples: np.ndarray, pc: int, prs: np.ndarray) -> np.ndarray:
        """``samples`` (lenslet, prow, pcol) of the views (prs[j], pc) as ``(j, m)`` for ``self.lenses[m]``."""
        return np.ascontiguousarray(samples[self.lenses[:, None], prs[None, :], pc].T)

    def column_accumulate(self, pc: int, prs: np.ndarray, vals: np.ndarray, num: np.ndarray) -> None:
        """num += Σ_beams F·vals[j, m] over the views (prs[j], pc); a zero value skips its beam."""
        self.column_accumulate_many(pc, prs, vals[None], np.zeros(1, np.int64), num[None])

    def column_accumulate_many(
        self, pc: int, prs: np.ndarray, vals: np.ndarray, chans: np.ndarray, out: np.ndarray
    ) -> None:
        """out[chans[c]] += Σ_beams F·vals[c, j, m] for several value sets in one pass over the tables."""
        _column_accumulate(self.lenses, pc, prs, vals, chans, *self.tables, out)

    def uniform_projection(self) -> np.ndarray:
        """A·1 as (lenslet, prow, pcol): what a uniform unit volume projects, without reading a volume."""
        nl = self.shape_lf[0] * self.shape_lf[1]
        out = np.zeros((nl, self.n, self.n))
        _uniform_projection(self.lenses, *self.tables, self.gain, out)
        return out

    def view_accumulate(self, pr: int, pc: int, vals: np.ndarray, use: np.ndarray, num: np.ndarray) -> None:
        """num += Σ_beams F·vals over view (pr, pc), for the beams with ``use`` (F: beam fraction per voxel)."""
        _view_accumulate(self.lenses, pr, pc, vals, use, *self.tables, num)
