"""Step 2 of the fit (package docstring), the image model: each particle's exact image in its own sensor patch.

A particle reaches a few dozen lenslets: its image is rendered into a patch (its bounding box on the sensor,
from :func:`lfstudy.simulate.exact`'s layout bound, plus a margin) by the exact renderer's own per-lenslet
kernels, with the sensor cropped to the patch (the cell edges move by whole pixels, so the patch is the full
render's pixels up to rounding: the tests bound the difference by 1e-9 of the patch's peak). The fit uses a
coarser quadrature of the same integrals by default (``image_accuracy="fast"``, ``_QUAD``: arc panels with about
half the Gauss–Legendre nodes, up to 16 blur widths long, 8-node band integrals, Gaussian tails cut at 4 σ instead
of 6): every image is within 1e-4 of its patch's peak and 1e-5 of its sum of the exact one (the tests, over
particles in and out of focus, at 12 depths, with spots on and near lenslet edges), well below the shot noise of
a 25,000-photon particle; 0.148 against 0.219 ms of CPU per image (``benchmarks/bench_particle_image.py``, whose
docstring has where an image's time goes). ``image_accuracy="exact"`` gives the renderer's own images.

:func:`particle_patches` renders them; :class:`_FitImages` is what one fit does with them (renders in batches
with the fit's image model and quadrature, adds them to the residual, fits intensities) and what it counts.
"""

from __future__ import annotations

import math
import time

import numba
import numpy as np
from numba import njit, prange

from lfstudy.optics import PlenopticCamera

# The fit's Gauss-Seidel kernels (numba), shared with image_model.py.
from lfstudy.reconstruct._shake_kernels import _accumulate_masked, refit_intensities
from lfstudy.reconstruct.image_model import ImageModel
from lfstudy.reconstruct.registry import ReconstructionError
from lfstudy.simulate._render_common import (
    _G_COS,
    _G_HH,
    _G_HW,
    _G_NCOL,
    _G_NROW,
    _G_SIN,
    _blurs,
    _geometry,
    solid_angle,
)
from lfstudy.simulate.exact import _K, _QUAD_EXACT, _ST_BIG, _ST_SIZE, _ST_SPILL, _render_particle, _scratch

__all__ = ["particle_patches"]

_MARGIN_PX = 3  # pixels added around each patch's layout bound (covers the ±δ trial positions)
#: Quadratures of the per-particle images (the order of :data:`lfstudy.simulate.exact._QUAD_EXACT`: arc nodes
#: ceil(base + dens·L) per panel of L blur widths, at least min; longest panel; nodes of the numeric band
#: integrals; Gaussian cut-off K; band half-width, in σ). "fast": max |fast − exact| <= 1e-4 of the patch's
#: peak and |Σ fast − Σ exact| <= 1e-5 of the sum (tests; measured 2e-5 and 2e-6), ~1.5x cheaper.
_QUAD = {
    "exact": _QUAD_EXACT,
    "fast": np.array([2.0, 0.75, 2.0, 16.0, 8.0, 4.0, 4.5]),
}


@njit(parallel=True, cache=True)
def _patch_kernel(px, py, pz, wt, geos, gidx, buf, boff, psz, nlmax, stats, quad, nchunk):  # pragma: no cover - jitted
    """Render particle t (``px[t], py[t], pz[t]``, weight ``wt[t]``) with the cropped geometry
    ``geos[gidx[t]]`` into ``buf[boff[t, 0]:boff[t, 1]]`` (its patch, rows × cols of the crop).

    Each task has its own sensor crop and is the full render's own per-particle step
    (:func:`lfstudy.simulate.exact._render_particle`, unrotated grid, quadrature ``quad``). The
    tasks are cut into ``nchunk`` contiguous chunks run in parallel, each with one scratch (the
    render leaves it clean after every particle, as in :func:`~lfstudy.simulate.exact._render_kernel`):
    every patch is written by one task alone, so the bytes do not depend on the chunks or threads. Each task
    zeroes its patch first (``buf`` comes uninitialised) and clips its rounding residue of either sign to 0
    after, as render_exact clips: both while the patch is in the cache, in parallel.
    """
    n = px.size
    for c in prange(nchunk):
        scr = _scratch(geos[0], psz, nlmax, quad)
        cnt = np.zeros(_ST_SIZE)
        for t in range(c * n // nchunk, (c + 1) * n // nchunk):
            seg = buf[boff[t, 0] : boff[t, 1]]
            seg[:] = 0.0
            if wt[t] == 0.0:
                continue
            geo = geos[gidx[t]]
            cnt[:] = 0.0
            # the full render's argument types (a typed row 0, the grid's rotation read from geo, False for the
            # model camera), so both kernels call the one compiled _render_particle
            chunk = (seg, np.int64(0), int(geo[_G_NROW]) - 1)
            rotated = geo[_G_SIN] != 0.0 or geo[_G_COS] != 1.0
            _render_particle(geo, rotated, px[t], py[t], pz[t], wt[t], scr, chunk, cnt)
            for q in range(_ST_SIZE):
                stats[t, q] += cnt[q]
            for i in range(seg.size):
                if seg[i] < 0.0:
                    seg[i] = 0.0


def _patch_boxes(
    camera: PlenopticCamera,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    sm: float,
    sl: float,
    pad: int,
    gap: float | None = None,
):
    """Sensor bounding boxes (row0, col0, rows, cols) of the particles' images; the bound of
    :func:`lfstudy.simulate.exact._layout` plus ``pad`` pixels; ``psz`` and ``nlmax`` for the scratch.
    ``gap``: the lenslet-to-sensor distance (default the lenslet focal length), as the renderer's."""
    so, si, fm, fl = camera.so, camera.si, camera.main_focal_length, camera.lenslet_focal_length
    rad, pl, pp = camera.aperture_diameter / 2.0, camera.lenslet_pitch, camera.pixel_pitch
    d = so + z
    c1 = 1.0 / d - 1.0 / fm
    reach = rad * np.abs(1.0 + si * c1) + _K * sm
    if gap is None or gap == fl:
        xc, yc = -(si + fl) * x / d, -(si + fl) * y / d
        rho = rad * fl * np.abs(c1)
        half = reach + pl * math.sqrt(0.5) + rho + _K * sl + 2.0 * pp
    else:  # the gap's disc (radius R·|β|) and its lenslet centres scaled by g/fl (exact._layout, no tilt)
        xc, yc = -(si + gap) * x / d, -(si + gap) * y / d
        rho = rad * np.abs(gap * c1 + (1.0 - gap / fl) * (1.0 + si * c1))
        half = (gap / fl) * (reach + pl * math.sqrt(0.5)) + rho + _K * sl + 2.0 * pp
    hw, hh = camera.sensor_width / 2.0, camera.sensor_height / 2.0
    nr, nc = camera.n_pixels_y, camera.n_pixels_x
    r0 = np.clip(np.floor((hh - (yc + half)) / pp).astype(np.int64) - pad, 0, nr - 1)
    r1 = np.clip(np.floor((hh - (yc - half)) / pp).astype(np.int64) + pad, 0, nr - 1)
    c0 = np.clip(np.floor((xc - half + hw) / pp).astype(np.int64) - pad, 0, nc - 1)
    c1_ = np.clip(np.floor((xc + half + hw) / pp).astype(np.int64) + pad, 0, nc - 1)
    psz = math.ceil((2.0 * float(rho.max()) + 2.0 * _K * sl) / pp) + 4
    nlmax = min(math.ceil(2.0 * float(reach.max()) / pl) + 3, max(camera.n_lenslets_x, camera.n_lenslets_y))
    return r0, c0, r1 - r0 + 1, c1_ - c0 + 1, psz, nlmax


def _model_blurs(
    camera: PlenopticCamera, model: ImageModel | None, diffraction: bool = True
) -> tuple[float, float, float | None]:
    """The blurs (main lens', lenslet's) and the lenslet-to-sensor gap the images take under ``model`` (None or
    ideal: the nominal camera's blurs and gap None, the lenslet focal length)."""
    sm, sl = _blurs(camera, diffraction, None)
    if model is None or model.ideal:
        return sm, sl, None
    return sm * model.blur_scale, sl * model.blur_scale, model.gap(camera)


def _unit_weights(camera: PlenopticCamera, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Ω/Ω_ref per particle (eq. 4.14 generalised): a particle of intensity I delivers I·Ω/Ω_ref."""
    rad = camera.aperture_diameter / 2.0
    ref = 2.0 * np.pi * (1.0 - camera.so / math.hypot(camera.so, rad))
    return solid_angle(camera, x, y, z) / ref


def _spot_pitches(camera: PlenopticCamera, z: np.ndarray) -> np.ndarray:
    """Radius of a particle's defocus spot on the lenslet array (the main lens' blur circle, geometric), in
    lenslet pitches: below about one the image falls behind one to four lenslets and changes little with
    the particle's position inside them."""
    c1 = 1.0 / (camera.so + np.asarray(z, dtype=np.float64)) - 1.0 / camera.main_focal_length
    return camera.aperture_diameter / 2.0 * np.abs(1.0 + camera.si * c1) / camera.lenslet_pitch


def particle_patches(
    camera: PlenopticCamera,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    *,
    trials: np.ndarray | None = None,
    diffraction: bool = True,
    pad: int = _MARGIN_PX,
    accuracy: str = "exact",
    model: ImageModel | None = None,
    into: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact images of unit-intensity particles, each in its own sensor patch.

    Parameters
    ----------
    camera : PlenopticCamera
        Unrotated lenslet grid (the model camera of :func:`calibrated_camera`).
    x, y, z : ndarray, shape (n,)
        Positions [mm].
    trials : ndarray, shape (k, 3), optional
        Offsets (dx, dy, dz) [mm]: each particle is rendered at each offset too, into the same
        patch (the patch is the box of the unshifted position plus ``pad`` pixels). Default: none.
    diffraction : bool
        The camera's diffraction blurs (sec. 4.2.3), as :func:`~lfstudy.simulate.exact.render_exact`.
    pad : int
        Pixels added around the layout bound of each patch.
    accuracy : {"exact", "fast"}
        The quadrature: ``exact`` is :func:`~lfstudy.simulate.exact.render_exact`'s (1e-10 of a blur
        width); ``fast`` (``_QUAD``: fewer arc nodes, Gaussian tails cut at 4 σ) is within 1e-4 of each
        image's peak and 1e-5 of its sum (tested), ~1.5x cheaper. Same patches either way.
    model : ImageModel, optional
        The departures from the nominal camera the images take (:class:`ImageModel`: a lenslet-to-sensor gap
        other than the lenslet focal length, the diffraction blurs scaled), as calibrated from a recording's
        own particles (:func:`calibrate_image_model`); default (None or ideal): the nominal camera's images,
        bit for bit.
    into : (buf, starts), optional
        Render into ``buf`` (float64, flat), particle i's images from ``starts[i]`` on, laid out as below (the
        caller sized the patches by :meth:`_FitImages.boxes`); the other elements of ``buf`` are left as they
        are. Returned as ``patches``, with ``offsets`` the ``starts`` (n,). Default: a new buffer.

    Returns
    -------
    patches : ndarray, shape (n·(k + 1)·h·w summed), float64
        Flat; particle i's images (unshifted first, then each trial) start at ``offsets[i]``,
        each ``rows[i] × cols[i]``, row-major.
    offsets, row0, col0, shape : ndarray
        ``offsets`` (n + 1,), the patch's first sensor row and column, and ``(rows, cols)`` (n, 2).

    The image of unit intensity is the expected image of ``render_exact`` with one ray per
    particle: it sums to Ω/Ω_ref minus what misses the lenslet array or the sensor.
    """
    if abs(camera.lenslet_rotation) > 0:
        raise ReconstructionError("particle_patches: the camera's lenslet grid must be unrotated")
    if accuracy not in _QUAD:
        raise ReconstructionError(f"particle_patches: accuracy = {accuracy!r}; allowed values are {', '.join(_QUAD)}")
    x, y, z = (np.ascontiguousarray(np.asarray(a, dtype=np.float64).ravel()) for a in (x, y, z))
    n = x.size
    tr = np.zeros((1, 3)) if trials is None else np.vstack([np.zeros((1, 3)), np.asarray(trials, float)])
    k = tr.shape[0]
    sm, sl, gap = _model_blurs(camera, model, diffraction)
    r0, c0, h, w, psz, nlmax = _patch_boxes(camera, x, y, z, sm, sl, pad, gap)
    # the trial offsets may widen the scratch needed: size it on every position
    ax_, ay_, az_ = (np.concatenate([v + d for d in tr[:, i]]) for i, v in enumerate((x, y, z)))
    *_, psz, nlmax = _patch_boxes(camera, ax_, ay_, az_, sm, sl, pad, gap)
    geo = _geometry(camera, sm, sl, gap=gap)
    pp = camera.pixel_pitch
    geos = np.repeat(geo[None], n, axis=0)
    geos[:, _G_HW] = geo[_G_HW] - c0 * pp  # the crop's left edge is sensor x = −HW + c0·pp
    geos[:, _G_NCOL] = w
    geos[:, _G_HH] = geo[_G_HH] - (camera.n_pixels_y - r0 - h) * pp  # its bottom edge
    geos[:, _G_NROW] = h
    size = h * w
    if into is None:
        offsets = np.zeros(n + 1, dtype=np.int64)
        offsets[1:] = np.cumsum(size * k)
        buf = np.empty(int(offsets[-1]))  # each task zeroes its own patch (_patch_kernel)
        starts = offsets[:-1]
    else:
        buf, offsets = into
        starts = offsets = np.asarray(offsets, dtype=np.int64)
        if buf.dtype != np.float64 or buf.ndim != 1 or np.any(starts < 0) or np.any(starts + size * k > buf.size):
            raise ValueError("particle_patches: into's buffer does not hold the patches at its starts")
    gidx = np.repeat(np.arange(n, dtype=np.int64), k)
    start = (starts[:, None] + np.arange(k)[None, :] * size[:, None]).ravel()
    boff = np.stack([start, start + np.repeat(size, k)], axis=1).astype(np.int64)
    # task t = particle t // k at trial t % k
    tx, ty, tz = (a.reshape(k, n).T.ravel().copy() for a in (ax_, ay_, az_))
    wt = _unit_weights(camera, tx, ty, tz)
    stats = np.zeros((n * k, _ST_SIZE))
    nchunk = max(1, min(tx.size, 8 * numba.get_num_threads()))
    _patch_kernel(tx, ty, tz, wt, geos, gidx, buf, boff, psz, nlmax, stats, _QUAD[accuracy], nchunk)
    if stats[:, _ST_BIG].sum() > 0 or stats[:, _ST_SPILL].sum() > 1e-9 * max(float(wt.sum()), 1e-300):
        raise RuntimeError("particle_patches: a patch exceeded its scratch or spilled (a bug)")
    return buf, offsets, r0, c0, np.stack([h, w], axis=1)


def _block_offsets(box: np.ndarray, k: int) -> np.ndarray:
    """Where each particle's ``k`` images start in a flat buffer of :func:`particle_patches`' layout, and its end:
    (n + 1,), from the patches' boxes (row0, col0, rows, cols) (n, 4)."""
    offsets = np.zeros(len(box) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(box[:, 2] * box[:, 3] * k)
    return offsets


class _FitImages:
    """The particle images of one fit: :func:`particle_patches` on the model camera ``cam`` with the fit's
    quadrature (``accuracy``) and current image model (``model``, replaced by the image calibration), ``batch``
    particles at a time, on the light field's pixels (``mask``); ``clock`` counts the time and the images
    (``patches``, ``images``; ``reused``: the shake's images taken from its cache instead; ``fit`` the kernels;
    ``mart`` and ``volumes`` the candidate volumes')."""

    def __init__(self, cam: PlenopticCamera, mask: np.ndarray, accuracy: str, batch: int) -> None:
        self.cam, self.mask, self.accuracy, self.batch = cam, mask, accuracy, batch
        # the nominal camera's images until a calibration from the recording's particles replaces them
        self.model = ImageModel()
        self.clock = {"mart": 0.0, "patches": 0.0, "fit": 0.0, "images": 0, "reused": 0, "volumes": 0}
        self._scratch = [np.empty(0), np.empty(0)]

    def scratch(self, size: int, slot: int = 0) -> np.ndarray:
        """A buffer of ``size`` float64 (uninitialised) in slot 0 or 1, the same memory call after call (grown as
        needed), valid until the next call for that slot: a new buffer for every batch's images cost its page
        faults again (~1.5 GB/s: a demo shake batch's 22 MB in ~15 ms)."""
        if self._scratch[slot].size < size:
            self._scratch[slot] = np.empty(int(size * 1.25))
        return self._scratch[slot][:size]

    def patches(
        self,
        pos: np.ndarray,
        trials: np.ndarray | None = None,
        model: ImageModel | None = None,
        into: tuple[np.ndarray, np.ndarray] | None = None,
        slot: int | None = None,
    ):
        """:func:`particle_patches` of the particles at ``pos`` (n, 3) [mm], with the fit's image model unless
        ``model`` is given (the calibration's trials); ``into`` as there, or with ``slot`` (and no ``model``) in that
        :meth:`scratch` slot (the images then valid until its next use)."""
        if slot is not None and model is None:  # laid out here, by the fit's model's boxes
            box = self.boxes(pos)
            offsets = _block_offsets(box, 1 if trials is None else 1 + len(trials))
            buf = self.scratch(int(offsets[-1]), slot)
            self.render_into(pos, trials, buf, offsets[:-1], box)
            return buf, offsets, *(np.ascontiguousarray(a) for a in (box[:, 0], box[:, 1], box[:, 2:]))
        t0 = time.perf_counter()
        m = self.model if model is None else model
        out = particle_patches(self.cam, *pos.T, trials=trials, accuracy=self.accuracy, model=m, into=into)
        self.clock["patches"] += time.perf_counter() - t0
        self.clock["images"] += len(pos) * (1 if trials is None else 1 + len(trials))
        return out

    def render_into(
        self, pos: np.ndarray, trials: np.ndarray | None, buf: np.ndarray, starts: np.ndarray, box: np.ndarray
    ) -> None:
        """:meth:`patches` of the particles at ``pos`` into ``buf`` at ``starts``, laid out by their boxes ``box``
        (:meth:`boxes`, (n, 4)); a RuntimeError (a bug) where the rendered patches are not those boxes."""
        _, _, r0, c0, shp = self.patches(pos, trials, into=(buf, starts))
        if not np.array_equal(np.stack([r0, c0, shp[:, 0], shp[:, 1]], axis=1), box):
            raise RuntimeError("_FitImages: the rendered patches are not the boxes laid out for them (a bug)")

    def boxes(self, pos: np.ndarray) -> np.ndarray:
        """The sensor boxes (row0, col0, rows, cols) (n, 4) of the patches :meth:`patches` renders for the
        particles at ``pos`` (n, 3) [mm], with the fit's image model."""
        sm, sl, gap = _model_blurs(self.cam, self.model)
        r0, c0, h, w, _, _ = _patch_boxes(self.cam, *np.asarray(pos, float).T, sm, sl, _MARGIN_PX, gap)
        return np.stack([r0, c0, h, w], axis=1)

    def add_images(self, pos: np.ndarray, amp: np.ndarray, res: np.ndarray, sign: float) -> None:
        """res += sign·amp·U on the light field's pixels (the exact images of the particles at ``pos``)."""
        for s in range(0, len(pos), self.batch):
            sl = slice(s, s + self.batch)
            buf, offs, r0, c0, shp = self.patches(pos[sl], slot=0)
            t0 = time.perf_counter()
            _accumulate_masked(res, self.mask, buf, offs, r0, c0, shp, amp[sl] * 1.0, sign)
            self.clock["fit"] += time.perf_counter() - t0

    def fit_intensity(self, pos: np.ndarray, res: np.ndarray, floor: float, sweeps: int = 1) -> np.ndarray:
        """Intensities of new particles at ``pos`` (Gauss–Seidel on ``res``, which keeps the images of those
        brighter than ``floor``: the others are added back once all are fitted, so the result does not depend
        on the batches).

        ``sweeps`` > 1 repeats the Gauss–Seidel sweep over all of them (each sweep adds a particle's image back
        before refitting it, so the intensities converge to the joint least-squares fit of overlapping images;
        each sweep renders the images again). One sweep gives the first particle of an overlapping group its
        neighbours' light too: at the true positions of a dense field it leaves a third of the image unexplained
        (``_START_SWEEPS``)."""
        out = np.zeros((len(pos), 2))
        cur = np.zeros(len(pos))
        mask = self.mask
        for _ in range(max(1, int(sweeps))):
            for s in range(0, len(pos), self.batch):
                sl = slice(s, s + self.batch)
                buf, offs, r0, c0, shp = self.patches(pos[sl], slot=0)
                t0 = time.perf_counter()
                refit_intensities(res, mask, buf, offs, r0, c0, shp, cur[sl], out[sl])
                cur[sl] = out[sl, 1]
                self.clock["fit"] += time.perf_counter() - t0
        back = (out[:, 1] <= floor) & (out[:, 1] != 0.0)
        if back.any():
            self.add_images(pos[back], out[back, 1], res, 1.0)
        return out[:, 1]
