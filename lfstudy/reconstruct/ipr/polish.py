"""Step 4, the polish: near-focus particles moved to the likelihood-weighted mean of a stencil around them
(package docstring, step 4).

Near the focal plane a particle's defocus spot on the lenslet array is smaller than a lenslet: its image
falls behind one to four lenslets and changes little as the particle moves within them, so the residual is
flat there up to the noise and the shake stops anywhere on the flat. After the iterations, ``polish`` rounds
move each particle whose spot radius is at most ``_POLISH_SPOT`` pitches to the likelihood-weighted mean of a
stencil around it (weights exp(−ΔC/2σ²), ΔC the rise of the exact ‖R‖² over the stencil's lowest, σ² the
residual variance per pixel on the particle's patch; :func:`lfstudy.reconstruct._shake_kernels._stencil`), the
others held fixed, then refit the intensities there: where the residual is sharp that is the minimum, where it
is flat the middle of the flat, the estimate of least expected error. The particles move one run after another
(Gauss–Seidel, as the shake), each run of at most ``_POLISH_CHUNK`` particles whose patches do not overlap and
on the residual the runs before it left: moved all at once, two particles behind the same lenslets each took the
other's data for its own and both moved into it.

Most particles sit on a sharp minimum, where the whole stencil's mean is the current position: the stencil's
positions along one axis (8 of 44) are rendered first, and the rest only where one of those weighs at least
e^-``_POLISH_SCREEN`` of the current position (on the demo camera 46–66 % of the near-focus particles are
screened out and the polish's images 46 % fewer, the fit's particles the same on seeds 1–4; on the Table 4.3
camera found −0.4 / −0.2 / 0 points, seeds 5–7; ``benchmarks/bench_ipr.py``'s docstring).

The same drops of the exact residual take a warm start's depths from the frame's own data (:func:`_scan_depths`,
``ipr_particles(start=...)``): along z only, the best of a 17-point scan over ±2 voxels.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit

# The fit's Gauss-Seidel kernels (numba), shared with image_model.py.
from lfstudy.reconstruct._shake_kernels import _stencil
from lfstudy.reconstruct.ipr.patches import _FitImages, _spot_pitches
from lfstudy.reconstruct.ipr.shake import _Particles, _unmerged

_POLISH_SPOT = 1.5  # the polish moves particles whose defocus spot (radius) is at most this many lenslet pitches
_POLISH_XY = (-0.25, 0.0, 0.25)  # the polish stencil's offsets [voxels] in x and y
_POLISH_Z = (-0.5, -0.25, 0.0, 0.25, 0.5)  # and in z
_POLISH_T = 1.0  # the polish's weights exp(−ΔC/(2·T·σ²)): T = 1 the Gaussian likelihood of the residual
#: the polish's screen: a particle whose every axis neighbour on the stencil has a log-weight below −this (its
#: weight below e^-10 = 4.5e-5 of the current position's) sits on a sharp minimum, and the rest of the stencil is
#: not rendered for it (measured on the demo camera, seeds 1 and 2, three rounds each: of the 643 particles it
#: screens out the whole stencil moved none more than 0.02 voxel; with e^-7 one of 708 by 0.30 voxel)
_POLISH_SCREEN = 10.0
#: the polish moves at most this many particles together (a run whose patches do not overlap): enough to spread
#: the images' per-call cost (~0.3 ms a call against 0.07-0.2 ms an image), while each run sees the residual the
#: runs before it left
_POLISH_CHUNK = 32
#: a run is packed from at most this many times _POLISH_CHUNK of the first particles not yet in one (bounds the
#: packing's work where every patch meets every other)
_POLISH_SCAN = 8


def _polish_stencil(vox: np.ndarray) -> tuple[np.ndarray, int]:
    """The polish's stencil offsets (k, 3) [mm] for voxels ``vox`` (x, y, z) [mm]: the current position first,
    then the offsets along one axis (the screen's), then the others; and how many the first two groups hold."""
    stencil = np.array([(a, b, c) for a in _POLISH_XY for b in _POLISH_XY for c in _POLISH_Z]) * vox
    moved = np.count_nonzero(stencil, axis=1)
    return np.vstack([np.zeros((1, 3)), stencil[moved == 1], stencil[moved > 1]]), 1 + int(np.sum(moved == 1))


def _stencil_drops(
    images: _FitImages, pos: np.ndarray, amp: np.ndarray, res: np.ndarray, stencil: np.ndarray
) -> np.ndarray:
    """The exact residual's drop at each stencil position of every particle, the others held fixed, and the
    residual variance per pixel at the current position (``_stencil``'s output: (n, k + 1)); ``stencil[0]`` is 0."""
    k = len(stencil)
    drop = np.zeros((len(pos), k + 1))
    per = max(1, 7 * images.batch // k)  # particles a call: as many images as a shake batch's (7 a particle)
    for s in range(0, len(pos), per):
        sl = slice(s, s + per)
        cand = (pos[sl][:, None, :] + stencil[None]).reshape(-1, 3)
        buf, offs, r0, c0, shp = images.patches(cand, slot=0)
        t0 = time.perf_counter()
        _stencil(res, images.mask, buf, offs, r0, c0, shp, k, amp[sl] * 1.0, drop[sl])
        images.clock["fit"] += time.perf_counter() - t0
    return drop


@njit(cache=True)
def _runs_kernel(r0, c0, r1, c1, most, scan):  # pragma: no cover - jitted
    """``_runs``' packing: run after run, the first unassigned particles (in list order, at most ``scan`` of them
    tried per run) whose boxes [r0, r1) x [c0, c1) meet none of the run's members, until it holds ``most``."""
    n = r0.size
    order = np.empty(n, np.int64)
    ends = np.empty(n, np.int64)
    taken = np.zeros(n, np.bool_)
    members = np.empty(most, np.int64)
    first, pos, k = 0, 0, 0
    while first < n:
        m, tried, i = 0, 0, first
        while i < n and m < most and tried < scan:
            if not taken[i]:
                tried += 1
                free = True
                for j in range(m):
                    q = members[j]
                    if r0[q] < r1[i] and r0[i] < r1[q] and c0[q] < c1[i] and c0[i] < c1[q]:
                        free = False
                        break
                if free:
                    members[m] = i
                    m += 1
                    taken[i] = True
                    order[pos] = i
                    pos += 1
            i += 1
        ends[k] = pos
        k += 1
        while first < n and taken[first]:
            first += 1
    return order, ends[:k]


def _runs(boxes: np.ndarray, most: int) -> list[np.ndarray]:
    """The particles (indices) in runs of at most ``most``, no two of whose sensor ``boxes`` (row0, col0, rows,
    cols) overlap: each run takes the first particles of the list not yet in one whose boxes meet none of its
    members (at most ``_POLISH_SCAN`` · ``most`` tried). Every particle is in exactly one run."""
    b = np.asarray(boxes, np.int64).reshape(-1, 4)
    r0, c0 = np.ascontiguousarray(b[:, 0]), np.ascontiguousarray(b[:, 1])
    order, ends = _runs_kernel(r0, c0, r0 + b[:, 2], c0 + b[:, 3], int(most), _POLISH_SCAN * int(most))
    return np.split(order, ends[:-1])


def _polish_step(
    images: _FitImages, pos: np.ndarray, amp: np.ndarray, res: np.ndarray, stencil: np.ndarray, n_axes: int
) -> tuple[np.ndarray, np.ndarray]:
    """Each particle moved to the likelihood-weighted mean of the stencil positions around it (the others
    held fixed: weights exp(−ΔC/2σ²), ΔC the rise of the exact residual's ‖R‖² over the stencil's best,
    σ² the residual variance per pixel on the particle's patch), then the intensity refitted there.

    Gauss–Seidel, as the shake: the particles go in runs of at most ``_POLISH_CHUNK`` whose patches do not
    overlap (:func:`_runs`), each run on the residual the runs before it left. Moved all at once, two
    particles sharing lenslets would each see the other's data as its own and both move into it (the demo's
    coarse designs: the residual rose from 0.17 to 0.31 of the data's norm; ``benchmarks/bench_ipr.py``).
    The runs are packed (:func:`_runs`), not cut from the list where two patches meet: the images' per-call cost
    would otherwise dominate runs of a few particles."""
    moved, inten = pos.copy(), amp.copy()
    for run in _runs(images.boxes(pos), _POLISH_CHUNK):
        moved[run], inten[run] = _polish_run(images, pos[run], amp[run], res, stencil, n_axes)
    return moved, inten


def _polish_run(
    images: _FitImages, pos: np.ndarray, amp: np.ndarray, res: np.ndarray, stencil: np.ndarray, n_axes: int
) -> tuple[np.ndarray, np.ndarray]:
    """One run of :func:`_polish_step`: particles whose patches do not overlap, moved together.

    The stencil's first ``n_axes`` positions (the current one and those along one axis) are rendered for every
    particle; the rest only for those where one of them weighs at least e^-``_POLISH_SCREEN`` of the current
    position: elsewhere the minimum is sharp, the whole stencil's mean is the current position (screened
    particles keep their weighted mean over the axis positions)."""
    k = len(stencil)
    drop = np.full((len(pos), k), -np.inf)
    axes = _stencil_drops(images, pos, amp, res, stencil[:n_axes])
    drop[:, :n_axes] = axes[:, :n_axes]
    s2 = np.maximum(axes[:, n_axes], 1e-300)
    rise = (axes[:, 1:n_axes] - axes[:, [0]]) / (2.0 * _POLISH_T * s2[:, None])
    full = np.nonzero(rise.max(axis=1, initial=-np.inf) >= -_POLISH_SCREEN)[0]
    if len(full) and k > n_axes:  # the rest of the stencil, its current position again first (``_stencil``'s order)
        rest = _stencil_drops(images, pos[full], amp[full], res, np.vstack([stencil[:1], stencil[n_axes:]]))
        drop[full, n_axes:] = rest[:, 1 : k - n_axes + 1]
    logw = (drop - drop.max(axis=1, keepdims=True)) / (2.0 * _POLISH_T * s2[:, None])
    wgt = np.exp(logw)
    moved = pos + (wgt @ stencil) / wgt.sum(axis=1)[:, None]
    images.add_images(pos, amp, res, 1.0)
    return moved, images.fit_intensity(moved, res, -1.0)


#: a warm start's depth scan: offsets along z [voxels] at which each started particle's exact residual drop is
#: evaluated before the shake (``_scan_depths``)
_START_SCAN = tuple(np.arange(-2.0, 2.01, 0.25))
#: a warm start's intensities: Gauss–Seidel sweeps over all its particles (:meth:`_FitImages.fit_intensity`), before
#: and after the depth scan. At the true positions of a demo frame (M -0.8, pitch 0.1184 mm, 0.005 ppp, exact
#: noiseless images) one sweep leaves 0.362 of the image unexplained, 2 sweeps 0.141, 10 0.016, 20 0.008; the
#: shake, started from one sweep's intensities, then moved the true particles off (77.5 % kept within half a
#: voxel, 14.2 % ghosts), from 20 sweeps' it kept them (89.8 %, 4.1 %). On the study's own images, started at the
#: truth with the depth scan, the four demo designs keep 80.5-96.2 % (65.3-94.3 % with one sweep;
#: benchmarks/bench_ipr_depth_slope.py). Each sweep renders the start's images once more (10 sweeps of a
#: 1,536-particle start: ~15,000 images, against ~200,000 in the fit). The cold fit keeps one sweep: 10-20 for
#: MART's candidates changed nothing measurable (found 30.5-32.6 % against 31.2 % on that frame)
_START_SWEEPS = 10


def _scan_depths(
    images: _FitImages, pos: np.ndarray, amp: np.ndarray, res: np.ndarray, vox: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A warm start's depths taken from this frame's data: each particle (the others held fixed) moved along z
    to the offset of ``_START_SCAN`` where the exact residual drops most, then the intensities refitted there.

    Near focus the residual is flat in z over about a voxel, and the shake and the polish leave a particle
    where it starts on the flat: started from a predictor's depth, the particle would keep the predictor's
    error in w. The best of the scan is the data's, whatever the start within ±2 voxels."""
    if not len(pos) or not _START_SCAN:
        return pos, amp
    stencil = np.zeros((len(_START_SCAN) + 1, 3))
    stencil[1:, 2] = np.asarray(_START_SCAN) * vox[2]
    drop = _stencil_drops(images, pos, amp, res, stencil)[:, : len(stencil)]
    moved = pos + stencil[np.argmax(drop, axis=1)]
    images.add_images(pos, amp, res, 1.0)
    return moved, images.fit_intensity(moved, res, -1.0, _START_SWEEPS)


def _polish(
    images: _FitImages, p: _Particles, res: np.ndarray, vox: np.ndarray, rounds: int
) -> tuple[_Particles, int, int]:
    """``rounds`` polish rounds of the particles near focus (spot radius at most ``_POLISH_SPOT`` pitches), then
    the pairs it brought within half a voxel merged (the fainter's image added back to ``res``). ``sig`` and
    ``rel`` stay the last shake's. Returns the list, how many particles were polished and how many merged away."""
    xyz, inten = p.xyz, p.inten
    near = np.nonzero(_spot_pitches(images.cam, xyz[:, 2]) <= _POLISH_SPOT)[0] if len(xyz) else np.zeros(0, int)
    if not (rounds and len(near)):
        return p, len(near), 0
    stencil, n_axes = _polish_stencil(vox)
    for _ in range(rounds):
        xyz[near], inten[near] = _polish_step(images, xyz[near], inten[near], res, stencil, n_axes)
    keep = _unmerged(xyz, inten, vox)  # pairs the polish brought within half a voxel are merged
    images.add_images(xyz[~keep], inten[~keep], res, 1.0)
    return p.take(keep), len(near), int((~keep).sum())
