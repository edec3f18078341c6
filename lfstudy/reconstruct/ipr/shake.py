"""Step 3, the shake: each outer iteration's Gauss–Newton steps and the exact choice of the move, then the
removal of ghosts and merged pairs (package docstring, step 3).

For every particle the images at its position and at ±δ in x, y and z are rendered (central differences;
δ = ``shake`` voxels); particle after particle (Gauss–Seidel, as Wieneke's shaking) the linear least-squares
problem ``min ‖R_p − I'·U − Σ_k a_k·D_k‖²`` over (I', a) is solved on a linearised copy of the residual
(:func:`lfstudy.reconstruct._shake_kernels._sweep`), and the move is chosen on the exact residual among the
current position, the trial positions and the Gauss–Newton step (:func:`~lfstudy.reconstruct._shake_kernels._choose`),
so no move raises the residual. With ``shake_settle`` the particles that settled sit the shake out
(:func:`_unwoken` wakes them).

Those two kernels run particle after particle, so they do not gain from threads: at 16 threads they were 39 % of a
Table 4.3 crop's fit. They visit only the pixels of each patch that its images light
(:func:`~lfstudy.reconstruct._shake_kernels.lit_pixels`, found for a batch at once, in parallel; a few per cent of
the patch's box) and give the bytes they gave over the whole box (tested). Measured (``benchmarks/bench_ipr.py``,
the threads table): 1184 × 800 px at 0.005 ppp, their time 24.4 → 14.7 s at 1 thread and 26.9 → 12.5 s at 2, the
fit's 220.7 → 206.3 s and 155.9 → 127.4 s.

A particle's images depend on its position alone, not on the residual: where a shake keeps a particle where it
was (the exact choice found no better position: 15–45 % of the particles in the demo's later iterations), its
position and trial images are kept (:class:`_Cached`, up to ``_CACHE_BYTES``) and the next shake reuses them
instead of rendering the same images again; alone, that gives the fit without the cache to the bit. Where the
Gauss–Newton step moved a particle less than ``_CHORD`` δ from where its trials were rendered (most particles once
they converge: 64–93 % move less than 0.05 voxel from the 4th iteration on, demo frame), the next shake keeps
those trials too, with the image at its new position (the chord method: the Jacobian of the trials' base, a
fraction of δ away; the move is still chosen on the exact residual, among exact images whose positions are
known). Measured (demo camera, 480 × 480 px at 0.005 ppp, seeds 31–36, one thread): 10–12 % of the images reused
without the chord, 24–26 % with it; the images' CPU 11.5 → 9.0 s a fit; found 83.7 → 83.4 %, ghosts 14.4 → 14.4 %,
x,y RMS 0.00502 → 0.00504 mm, z 0.0336 → 0.0337 mm (the seeds' spread is larger than these differences).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

# The fit's Gauss-Seidel kernels (numba), shared with image_model.py.
from lfstudy.reconstruct._shake_kernels import _choose, _sweep, lit_pixels
from lfstudy.reconstruct.ipr.patches import _block_offsets, _FitImages

_GHOST_FROM = 0  # first iteration after which faint particles are removed
_SETTLE_RADIUS = 2.0  # shake_settle: a particle moved, added or removed within this many voxels wakes the settled
_SETTLE_SKIPS = 2  # and a settled particle sits out at most this many shakes in a row
#: the shake's image cache (module docstring) holds at most this many bytes of images (a demo frame's up to ~0.2 GB;
#: on a full Table 4.3 frame it fills, and the particles beyond it are rendered as before)
_CACHE_BYTES = 256e6
#: the chord method (module docstring): a particle the Gauss-Newton step moved less than this fraction of the
#: finite-difference step δ (per axis) from its trials' base keeps those trials for the next shake (0: only the
#: particles that stayed keep their images, and the fit is the one without a cache to the bit)
_CHORD = 0.25


@dataclass(frozen=True)
class _Cached:
    """One particle's shake images kept for the next shake: its image at ``pos`` (3,) [mm] and the trial images
    at ``base`` + the offsets ``trials`` (``base`` is ``pos`` unless the chord method kept older trials, module
    docstring), under the image model ``model``, in the patch (``r0``, ``c0``, ``shape``) of ``base``, one after
    the other in ``block`` (flat, as :func:`~lfstudy.reconstruct.ipr.particle_patches` lays them out)."""

    pos: np.ndarray
    base: np.ndarray
    trials: np.ndarray
    model: Any
    r0: int
    c0: int
    shape: np.ndarray
    block: np.ndarray

    def valid(self, pos: list[float], trials: np.ndarray, model: Any) -> bool:
        """Whether these images are the particle's at ``pos`` (x, y, z [mm]: the same floats) with the trials
        ``trials``."""
        return (
            model is self.model
            and pos == self.pos.tolist()
            and (trials is self.trials or np.array_equal(trials, self.trials))
        )


@dataclass
class _Particles:
    """The fit's particle list: positions ``xyz`` (n, 3) [mm], intensities, the position uncertainties ``sig``
    (n, 3) [mm] and relative residuals ``rel`` of the last shake (inf until shaken), and the active set's state:
    ``still`` (settled) and ``sat`` (shakes sat out in a row)."""

    xyz: np.ndarray
    inten: np.ndarray
    sig: np.ndarray
    rel: np.ndarray
    still: np.ndarray
    sat: np.ndarray
    cache: np.ndarray | None = None  # object (n,): each particle's :class:`_Cached` images or None

    @classmethod
    def unshaken(cls, xyz: np.ndarray, inten: np.ndarray) -> _Particles:
        """New particles at ``xyz`` of intensities ``inten``: no uncertainty yet, none settled."""
        n = len(xyz)
        return cls(xyz, inten, np.full((n, 3), np.inf), np.full(n, np.inf), np.zeros(n, bool), np.zeros(n, np.int64))

    def __len__(self) -> int:
        return len(self.xyz)

    def cached(self) -> np.ndarray:
        """The cache (object (n,), None where a particle has no images kept)."""
        return np.full(len(self), None, dtype=object) if self.cache is None else self.cache

    def take(self, keep: np.ndarray) -> _Particles:
        """The particles where ``keep``."""
        parts = (getattr(self, k)[keep] for k in ("xyz", "inten", "sig", "rel", "still", "sat"))
        return _Particles(*parts, cache=None if self.cache is None else self.cache[keep])

    def append(self, new: _Particles) -> _Particles:
        """These particles, then ``new``'s."""
        cache = None if self.cache is None and new.cache is None else np.concatenate([self.cached(), new.cached()])
        return _Particles(
            np.vstack([self.xyz, new.xyz]),
            np.concatenate([self.inten, new.inten]),
            np.vstack([self.sig, new.sig]),
            np.concatenate([self.rel, new.rel]),
            np.concatenate([self.still, new.still]),
            np.concatenate([self.sat, new.sat]),
            cache,
        )


def _batch_images(
    images: _FitImages, pos: np.ndarray, tr: np.ndarray, cache: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """:meth:`_FitImages.patches` of the particles at ``pos`` with the trials ``tr`` (laid out as it lays them out,
    in :meth:`_FitImages.scratch`'s slot 0: valid until its next use), the images of those whose ``cache`` entry
    is valid copied from it instead of rendered, and the trials' base per particle (``pos`` where rendered)."""
    keys = pos.tolist()
    hit = np.array([c is not None and c.valid(q, tr, images.model) for c, q in zip(cache, keys)], dtype=bool)
    n, k = len(pos), 1 + len(tr)
    images.clock["reused"] += int(hit.sum()) * k
    base = pos.copy()
    miss = np.nonzero(~hit)[0]
    box = np.zeros((n, 4), np.int64)  # r0, c0, rows, cols
    if len(miss):
        box[miss] = images.boxes(pos[miss])
    for i in np.nonzero(hit)[0]:
        c = cache[i]
        base[i], box[i] = c.base, (c.r0, c.c0, *c.shape)
    offsets = _block_offsets(box, k)
    buf = images.scratch(int(offsets[-1]), 0)
    for i in np.nonzero(hit)[0]:
        buf[offsets[i] : offsets[i + 1]] = cache[i].block
    if len(miss):
        images.render_into(pos[miss], tr, buf, offsets[miss], box[miss])
    # contiguous, as particle_patches returns them (the kernels' compiled signatures)
    r0, c0, shp = (np.ascontiguousarray(a) for a in (box[:, 0], box[:, 1], box[:, 2:]))
    return (buf, offsets, r0, c0, shp), base


def _recentred(
    block: np.ndarray, r0: int, c0: int, shape: np.ndarray, img: np.ndarray, box: tuple
) -> np.ndarray | None:
    """``block`` (a particle's images in the patch (r0, c0, shape)) with its first image replaced by ``img`` (the
    image in the patch ``box`` = (r0, c0, rows, cols)); None where ``img`` has light outside the block's patch."""
    h, w = int(shape[0]), int(shape[1])
    br0, bc0, bh, bw = (int(v) for v in box)
    im = img.reshape(bh, bw)
    ra, rb = max(r0, br0), min(r0 + h, br0 + bh)
    ca, cb = max(c0, bc0), min(c0 + w, bc0 + bw)
    if ra >= rb or ca >= cb:
        return None
    if np.count_nonzero(im[ra - br0 : rb - br0, ca - bc0 : cb - bc0]) != np.count_nonzero(im):
        return None
    out = block.copy()
    centre = out[: h * w].reshape(h, w)
    centre[:] = 0.0
    centre[ra - r0 : rb - r0, ca - c0 : cb - c0] = im[ra - br0 : rb - br0, ca - bc0 : cb - bc0]
    return out


def _shake_step(
    images: _FitImages,
    pos: np.ndarray,
    amp: np.ndarray,
    res: np.ndarray,
    tr: np.ndarray,
    delta: np.ndarray,
    mstep: np.ndarray,
    damping: float,
    central: bool,
    cache: np.ndarray | None = None,
    keep: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss–Newton steps on a linearised copy of the residual, then the exact choice (``_choose``), which
    leaves ``res`` the exact residual of the moved particles.

    ``tr`` (k, 3) [mm] are the trial offsets (±δ or +δ along each axis), ``delta`` and ``mstep`` (3,) [mm] the
    finite-difference step and the largest move; ``cache`` (object (n,)) the particles' kept images
    (:class:`_Cached` or None). Returns the moved positions, their intensities, the sweep's output per particle
    (step, intensity, variances of x, y, z, relative residual, ...) and the new cache: with ``keep``, the images of
    the particles that stayed where they were and, with the chord method, of those the step kept near their trials'
    base, up to ``_CACHE_BYTES``; else none.
    """
    lin = res.copy()
    out = np.zeros((len(pos), 9))
    pick = np.zeros((len(pos), 2))
    moved = pos.copy()
    offsets = np.vstack([np.zeros((1, 3)), tr])
    mask, batch, clock = images.mask, images.batch, images.clock
    cache = np.full(len(pos), None, dtype=object) if cache is None else cache
    kept = np.full(len(pos), None, dtype=object)
    room = _CACHE_BYTES if keep else 0.0
    near = _CHORD * delta  # the chord method's reach from the trials' base, per axis [mm]
    nt = len(tr)
    for s in range(0, len(pos), batch):
        sl = slice(s, s + batch)
        (buf, offs, r0, c0, shp), base = _batch_images(images, pos[sl], tr, cache[sl])
        t0 = time.perf_counter()
        lm = float(damping)
        lit = lit_pixels(mask, buf, offs, r0, c0, shp, 1 + nt)  # (lit, start, stop, nmask)
        _sweep(lin, mask, buf, offs, r0, c0, shp, *lit, amp[sl].copy(), delta, mstep, lm, True, central, out[sl])
        clock["fit"] += time.perf_counter() - t0
        step = pos[sl] + out[sl, :3]
        bn, on, r0n, c0n, shpn = images.patches(step, slot=1)
        t0 = time.perf_counter()
        _choose(res, mask, buf, offs, r0, c0, shp, *lit[:3], 1 + nt, amp[sl], bn, on, r0n, c0n, shpn, pick[sl])
        clock["fit"] += time.perf_counter() - t0
        k = pick[sl, 0].astype(int)
        # a trial is the image at its base + offset (the base is the position unless the chord method kept it)
        moved[sl] = np.where(
            (k == nt + 1)[:, None], step, np.where((k == 0)[:, None], pos[sl], base + offsets[k % (nt + 1)])
        )
        # the images next time: the same where the particle stayed; with its new image where the step kept it near
        # the trials' base (the chord method); none else
        stepped = (k == nt + 1) & np.all(np.abs(step - base) <= near, axis=1) if _CHORD > 0 else np.zeros(len(k), bool)
        for j in np.nonzero((k == 0) | stepped)[0]:
            block = buf[offs[j] : offs[j + 1]]
            if block.nbytes > room:
                break
            if k[j] != 0:
                block = _recentred(
                    block, int(r0[j]), int(c0[j]), shp[j], bn[on[j] : on[j + 1]], (r0n[j], c0n[j], *shpn[j])
                )
                if block is None:
                    continue
            else:
                block = block.copy()
            room -= block.nbytes
            i = s + j
            kept[i] = _Cached(
                moved[i].copy(), base[j].copy(), tr, images.model, int(r0[j]), int(c0[j]), shp[j].copy(), block
            )
    return moved, pick[:, 1], out, kept


def _shake(
    images: _FitImages,
    p: _Particles,
    res: np.ndarray,
    vox: np.ndarray,
    settle: float,
    tr: np.ndarray,
    delta: np.ndarray,
    mstep: np.ndarray,
    damping: float,
    central: bool,
    keep: bool = True,
) -> tuple[_Particles, int, list[np.ndarray]]:
    """One iteration's shake of the active set (:func:`_shake_step` with ``tr``, ``delta``, ``mstep``, ``damping``,
    ``central``; ``keep``: whether a later shake may reuse its images, False for the last). Returns the shaken
    list, how many sat out, and the events: the old and new positions of the particles that moved (by at least
    ``settle`` voxels; with ``settle`` 0 every shaken one)."""
    # the active set: particles settled (their last shake moved them less than shake_settle voxels, and no
    # particle within _SETTLE_RADIUS voxels moved, was added or removed since) sit out up to _SETTLE_SKIPS shakes
    act = ~(p.still & (p.sat < _SETTLE_SKIPS))
    sat = np.where(act, 0, p.sat + 1)
    old = p.xyz
    xyz, inten, sig, rel = p.xyz.copy(), p.inten.copy(), p.sig.copy(), p.rel.copy()
    cache = p.cached().copy()
    xyz[act], inten[act], out, cache[act] = _shake_step(
        images, old[act], inten[act], res, tr, delta, mstep, damping, central, cache[act], keep
    )
    sig[act] = np.sqrt(out[:, 4:7])
    rel[act] = out[:, 7]
    moved = np.max(np.abs(xyz - old) / vox, axis=1) >= settle if settle > 0 else act
    still = np.where(act, ~moved, p.still)
    return _Particles(xyz, inten, sig, rel, still, sat, cache), int((~act).sum()), [old[moved], xyz[moved]]


def _unwoken(still: np.ndarray, xyz: np.ndarray, events: np.ndarray, vox: np.ndarray) -> np.ndarray:
    """``still`` (the settled particles at ``xyz``) less those within ``_SETTLE_RADIUS`` voxels (per-axis scaled)
    of an event: a particle's old or new position where it moved, was added or removed."""
    out = np.asarray(still, bool).copy()
    if len(events) and out.any():
        d = cKDTree(np.asarray(events) / vox).query(xyz[out] / vox, distance_upper_bound=_SETTLE_RADIUS)[0]
        out[out] = d > _SETTLE_RADIUS
    return out


def _unmerged(xyz: np.ndarray, inten: np.ndarray, vox: np.ndarray) -> np.ndarray:
    """False for the fainter of each pair closer than half a voxel (per axis, scaled)."""
    keep = np.ones(len(xyz), bool)
    if len(xyz) < 2:
        return keep
    pairs = cKDTree(xyz / vox).query_pairs(0.5, output_type="ndarray")
    for a, b in pairs[np.argsort(-np.maximum(inten[pairs[:, 0]], inten[pairs[:, 1]]))] if len(pairs) else ():
        if keep[a] and keep[b]:
            keep[b if inten[a] >= inten[b] else a] = False
    return keep


def _near_grid(xyz: np.ndarray, inside: tuple[tuple[float, float], ...], vox: np.ndarray) -> np.ndarray:
    """True for the positions ``xyz`` (n, 3) [mm] within a voxel of the grid's extent ``inside`` ((lo, hi) [mm]
    per axis): those the fit keeps."""
    keep = np.ones(len(xyz), bool)
    for a in range(3):
        keep &= (xyz[:, a] >= inside[a][0] - vox[a]) & (xyz[:, a] <= inside[a][1] + vox[a])
    return keep


def _remove_ghosts(
    images: _FitImages,
    p: _Particles,
    res: np.ndarray,
    vox: np.ndarray,
    inside: tuple[tuple[float, float], ...],
    floor: float,
) -> tuple[_Particles, np.ndarray]:
    """The ghosts removed: particles not brighter than ``floor``, those more than a voxel outside the grid's
    extent ``inside`` ((lo, hi) [mm] per axis) and the fainter of each pair closer than half a voxel; their images
    are added back to ``res``. Returns the list kept and the removed particles' positions."""
    keep = (p.inten > floor) & _near_grid(p.xyz, inside, vox)
    keep &= _unmerged(p.xyz, p.inten, vox)
    gone = ~keep & (p.inten > 0)
    if gone.any():
        images.add_images(p.xyz[gone], p.inten[gone], res, 1.0)
    return p.take(keep), p.xyz[~keep]
