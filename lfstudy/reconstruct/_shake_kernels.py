"""The Gauss–Seidel kernels of IPR's fit (numba): add images into a residual, the linearised shake sweep,
the choice of a move on the exact residual, and the polish stencil.

Pure array kernels over the patch layout of :func:`lfstudy.reconstruct.ipr.particle_patches` (images in
one flat buffer, ``offs`` into it, each patch's top-left pixel ``r0, c0`` and shape ``shp``), shared by
:mod:`lfstudy.reconstruct.ipr` and :mod:`lfstudy.reconstruct.image_model`. See the ``lfstudy.reconstruct.ipr``
package docstring for the fit they carry out (Wieneke 2013's shaking).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True)
def _accumulate_masked(img, mask, buf, offs, r0, c0, shp, inten, sign):  # pragma: no cover - jitted
    """img[patch] += sign·inten[i]·U_i on the pixels where ``mask`` is set, particle after particle."""
    for i in range(r0.size):
        h, w = shp[i, 0], shp[i, 1]
        o = offs[i]
        a = sign * inten[i]
        if a == 0.0:
            continue
        for r in range(h):
            for c in range(w):
                if mask[r0[i] + r, c0[i] + c] != 0:
                    img[r0[i] + r, c0[i] + c] += a * buf[o + r * w + c]


@njit(parallel=True, cache=True)
def _lit(mask, buf, offs, r0, c0, shp, nimg, start, lit, stop, nmask):  # pragma: no cover - jitted
    """Patch i's lit pixels into ``lit[start[i]:stop[i]]`` (its box's slot, ``r·w + c`` in row order) and its box's
    masked pixels into ``nmask[i]`` (:func:`lit_pixels`)."""
    for i in prange(r0.size):
        h, w = shp[i, 0], shp[i, 1]
        sz = h * w
        s0 = start[i]
        for p in range(sz):  # the slot holds the flags first (each image a contiguous pass), then the list
            lit[s0 + p] = 0
        for k in range(nimg):
            o = offs[i] + k * sz
            for p in range(sz):
                if buf[o + p] != 0.0:
                    lit[s0 + p] = 1
        n = 0
        nm = 0
        for r in range(h):
            for c in range(w):
                if mask[r0[i] + r, c0[i] + c] == 0:
                    continue
                nm += 1
                p = r * w + c
                if lit[s0 + p] != 0:  # read before the list's entry n <= p overwrites it
                    lit[s0 + n] = p
                    n += 1
        stop[i] = s0 + n
        nmask[i] = nm


def lit_pixels(
    mask: np.ndarray, buf: np.ndarray, offs: np.ndarray, r0: np.ndarray, c0: np.ndarray, shp: np.ndarray, nimg: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of each patch that its images light, for the Gauss–Seidel kernels.

    A particle's image lights a few per cent of its patch's box (the spots behind the lenslets it reaches): on the
    other pixels every term of :func:`_sweep`'s and :func:`_choose`'s sums is zero, so those kernels visit the lit
    pixels only and give the same bytes. Found once per batch, in parallel (the kernels themselves run particle after
    particle).

    Parameters
    ----------
    mask : ndarray of uint8, (rows, cols)
        The sensor pixels the light field holds.
    buf, offs, r0, c0, shp : ndarray
        The patches (:func:`lfstudy.reconstruct.ipr.particle_patches`' layout), ``nimg`` images each.
    nimg : int
        Images per patch (a pixel is lit where any of them is non-zero).

    Returns
    -------
    lit : ndarray of int32
        Patch i's lit pixels are ``lit[start[i]:stop[i]]``, as ``r·w + c`` in its box, in row order.
    start, stop : ndarray of int64, (n,)
        Each patch's slot in ``lit`` (its box's pixels) and the end of its lit pixels there.
    nmask : ndarray of int64, (n,)
        Each box's pixels in the mask (lit or not): the count of the residual's variance.
    """
    n = r0.size
    start = np.asarray(offs[:n], np.int64) // int(nimg)  # each box's slot: its pixels, once
    lit = np.empty(int(offs[n]) // int(nimg), np.int32)
    stop = np.zeros(n, np.int64)
    nmask = np.zeros(n, np.int64)
    _lit(mask, buf, offs, r0, c0, shp, int(nimg), start, lit, stop, nmask)
    return lit, start, stop, nmask


@njit(cache=True)
def _sweep(
    res, mask, buf, offs, r0, c0, shp, lit, start, stop, nmask, inten, delta, max_step, damping, move, central, out
):  # pragma: no cover - jitted
    """One Gauss–Seidel pass of the linearised fit over the particles (module docstring).

    ``buf`` holds per particle 7 images: U, then +x, −x, +y, −y, +z, −z (steps ``delta``; central
    differences), or with ``central`` False 4: U, +x, +y, +z (forward differences).
    ``lit``, ``start``, ``stop``, ``nmask``: the patches' lit pixels (:func:`lit_pixels`); the sums run over those,
    the residual's variance over every masked pixel of the box, in row order either way.
    ``res`` is the residual image (data − model), updated in place. ``out[i]`` receives
    (dx, dy, dz, I', var_x, var_y, var_z, relative residual, pixels).
    """
    n = r0.size
    for i in range(n):
        h, w = shp[i, 0], shp[i, 1]
        sz = h * w
        o = offs[i]
        ii = inten[i]
        g = np.zeros((4, 4))
        v = np.zeros(4)
        npx = float(nmask[i])
        # add the particle back, then the normal equations of [U, D_x, D_y, D_z]
        for t in range(start[i], stop[i]):
            p = lit[t]
            rr, cc = r0[i] + p // w, c0[i] + p % w
            q = o + p
            u = buf[q]
            res[rr, cc] += ii * u
            f0 = u
            if central:
                f1 = (buf[q + sz] - buf[q + 2 * sz]) / (2.0 * delta[0])
                f2 = (buf[q + 3 * sz] - buf[q + 4 * sz]) / (2.0 * delta[1])
                f3 = (buf[q + 5 * sz] - buf[q + 6 * sz]) / (2.0 * delta[2])
            else:
                f1 = (buf[q + sz] - u) / delta[0]
                f2 = (buf[q + 2 * sz] - u) / delta[1]
                f3 = (buf[q + 3 * sz] - u) / delta[2]
            fv = (f0, f1, f2, f3)
            rv = res[rr, cc]
            for a in range(4):
                v[a] += fv[a] * rv
                for b in range(a, 4):
                    g[a, b] += fv[a] * fv[b]
        for a in range(4):
            for b in range(a):
                g[a, b] = g[b, a]
        step = np.zeros(3)
        inew = 0.0
        var = np.zeros(3)
        if g[0, 0] > 0.0:
            if move:
                ga = g.copy()
                for a in range(1, 4):
                    ga[a, a] *= 1.0 + damping
                theta = np.linalg.solve(ga, v)
                inew = theta[0]
                if inew > 0.0:
                    for a in range(3):
                        step[a] = min(max(theta[a + 1] / inew, -max_step[a]), max_step[a])
            else:
                inew = v[0] / g[0, 0]
            inew = max(inew, 0.0)
        # subtract the (linearised) image of the moved particle; its residual and covariance
        mm2 = 0.0
        for t in range(start[i], stop[i]):
            p = lit[t]
            rr, cc = r0[i] + p // w, c0[i] + p % w
            q = o + p
            m = buf[q]
            for a in range(3):
                if central:
                    m += step[a] * (buf[q + (2 * a + 1) * sz] - buf[q + (2 * a + 2) * sz]) / (2.0 * delta[a])
                else:
                    m += step[a] * (buf[q + (a + 1) * sz] - buf[q]) / delta[a]
            m *= inew
            res[rr, cc] -= m
            mm2 += m * m
        rr2 = 0.0  # over the whole box (each pixel changed once above, so the same terms in the same order)
        for r in range(h):
            for c in range(w):
                rr, cc = r0[i] + r, c0[i] + c
                if mask[rr, cc] != 0:
                    rr2 += res[rr, cc] * res[rr, cc]
        if move and inew > 0.0 and npx > 4.0:
            s2 = rr2 / (npx - 4.0)
            jt = g.copy()  # J = [U, I'·D]: scale the derivative rows and columns by I'
            for a in range(1, 4):
                for b in range(4):
                    jt[a, b] *= inew
                    jt[b, a] *= inew
            det_ok = True
            for a in range(4):
                if jt[a, a] <= 0.0:
                    det_ok = False
            if det_ok:
                cov = np.linalg.inv(jt) * s2
                for a in range(3):
                    var[a] = max(cov[a + 1, a + 1], 0.0)
        out[i, 0] = step[0]
        out[i, 1] = step[1]
        out[i, 2] = step[2]
        out[i, 3] = inew
        out[i, 4] = var[0]
        out[i, 5] = var[1]
        out[i, 6] = var[2]
        out[i, 7] = math.sqrt(rr2 / mm2) if mm2 > 0.0 else np.inf
        out[i, 8] = npx


@njit(cache=True)
def _choose(
    res, mask, buf, offs, r0, c0, shp, lit, start, stop, nimg, inten, bufn, offn, r0n, c0n, shpn, out
):  # pragma: no cover
    """Gauss–Seidel choice of each particle's next position among exact images: its ``nimg`` images in
    ``buf`` (the current one, then the ±δ trials) and the Gauss–Newton step's in ``bufn``.

    The particle (intensity ``inten[i]``, image 0) is added back to the residual ``res``; for every
    candidate image U the best intensity a/uu (a = ⟨R, U⟩, uu = ⟨U, U⟩) lowers ‖R‖² by a²/uu, so the
    candidate with the largest drop is taken (the current one unless another is strictly better: a move
    never raises the residual) and its image subtracted. ``out[i]`` = (choice, intensity): choice k < nimg
    is buf's image k, ``nimg`` the step.
    """
    for i in range(r0.size):
        h, w = shp[i, 0], shp[i, 1]
        sz = h * w
        o = offs[i]
        a = np.zeros(nimg + 1)
        uu = np.zeros(nimg + 1)
        for t in range(start[i], stop[i]):
            p = lit[t]
            rr, cc = r0[i] + p // w, c0[i] + p % w
            q = o + p
            res[rr, cc] += inten[i] * buf[q]
            rv = res[rr, cc]
            for k in range(nimg):
                u = buf[q + k * sz]
                a[k] += rv * u
                uu[k] += u * u
        hn, wn = shpn[i, 0], shpn[i, 1]
        for r in range(hn):
            for c in range(wn):
                rr, cc = r0n[i] + r, c0n[i] + c
                if mask[rr, cc] == 0:
                    continue
                u = bufn[offn[i] + r * wn + c]
                a[nimg] += res[rr, cc] * u
                uu[nimg] += u * u
        best, gain = 0, -1.0
        for k in range(nimg + 1):
            g = a[k] * a[k] / uu[k] if (uu[k] > 0.0 and a[k] > 0.0) else 0.0
            if g > gain * (1.0 + 1e-12):
                best, gain = k, g
        amp = a[best] / uu[best] if (uu[best] > 0.0 and a[best] > 0.0) else 0.0
        if best < nimg:
            for t in range(start[i], stop[i]):
                p = lit[t]
                res[r0[i] + p // w, c0[i] + p % w] -= amp * buf[o + best * sz + p]
        else:
            for r in range(hn):
                for c in range(wn):
                    rr, cc = r0n[i] + r, c0n[i] + c
                    if mask[rr, cc] != 0:
                        res[rr, cc] -= amp * bufn[offn[i] + r * wn + c]
        out[i, 0] = best
        out[i, 1] = amp


def refit_intensities(
    res: np.ndarray,
    mask: np.ndarray,
    buf: np.ndarray,
    offs: np.ndarray,
    r0: np.ndarray,
    c0: np.ndarray,
    shp: np.ndarray,
    inten: np.ndarray,
    out: np.ndarray,
) -> None:
    """One Gauss–Seidel pass over the intensities of the patches' particles, positions held: :func:`_choose` with
    each particle's own image (one per patch) as its only candidate, handed again as the "step" image.

    ``res`` (the residual, with the particles' images at ``inten`` subtracted) is updated in place; ``out[i]`` =
    (choice, refitted intensity). The particle's image is summed twice, once over its lit pixels and once over its
    box as the step's; both give the same gain, so the choice is always the current image.
    """
    lit, start, stop, _ = lit_pixels(mask, buf, offs, r0, c0, shp, 1)
    _choose(res, mask, buf, offs, r0, c0, shp, lit, start, stop, 1, inten, buf, offs, r0, c0, shp, out)


@njit(cache=True)
def _stencil(res, mask, buf, offs, r0, c0, shp, k, inten, out):  # pragma: no cover - jitted
    """The exact residual's drop at each of ``k`` positions of every particle, the others held fixed.

    ``buf`` holds k images per particle, each in its own patch (image j = i·k + c, ``offs[j]``, ``r0[j]``,
    ``c0[j]``, ``shp[j]``), the first at the particle's current position (intensity ``inten[i]``). The
    particle is added back to ``res``; for image c with a = ⟨R, U⟩ > 0, uu = ⟨U, U⟩ the best intensity
    lowers ‖R‖² by a²/uu; then the particle is subtracted again (``res`` is left as it was).
    ``out[i, c]`` = a²/uu (0 where a ≤ 0), ``out[i, k]`` the residual variance per pixel on the first
    patch with the particle at its current position and best intensity.
    """
    for i in range(inten.size):
        j0 = i * k
        h, w = shp[j0, 0], shp[j0, 1]
        o = offs[j0]
        for r in range(h):
            for c in range(w):
                if mask[r0[j0] + r, c0[j0] + c] != 0:
                    res[r0[j0] + r, c0[j0] + c] += inten[i] * buf[o + r * w + c]
        for m in range(k):
            j = j0 + m
            h, w = shp[j, 0], shp[j, 1]
            o = offs[j]
            a = 0.0
            uu = 0.0
            rr2 = 0.0
            npx = 0.0
            for r in range(h):
                for c in range(w):
                    rr, cc = r0[j] + r, c0[j] + c
                    if mask[rr, cc] == 0:
                        continue
                    u = buf[o + r * w + c]
                    rv = res[rr, cc]
                    a += rv * u
                    uu += u * u
                    rr2 += rv * rv
                    npx += 1.0
            out[i, m] = a * a / uu if (a > 0.0 and uu > 0.0) else 0.0
            if m == 0:
                out[i, k] = max(rr2 - out[i, 0], 0.0) / max(npx, 1.0)
        h, w = shp[j0, 0], shp[j0, 1]
        o = offs[j0]
        for r in range(h):
            for c in range(w):
                if mask[r0[j0] + r, c0[j0] + c] != 0:
                    res[r0[j0] + r, c0[j0] + c] -= inten[i] * buf[o + r * w + c]
