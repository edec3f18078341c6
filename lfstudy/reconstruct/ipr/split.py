"""Step 5, the split (off by default): bright particles tried as close pairs (package docstring, step 5).

Each particle brighter than ``split_ratio`` times the median is tried as two at ±s/2 along x, y or z
(s = 0.5–2 voxels, two least-squares intensities); the best pair is shaken on the exact residual (each member
in turn to the best of ±0.25, then ±0.125 voxel, the other held) and kept where both are above the ghost
floor, half a voxel apart, and ‖R‖² falls below the single particle's (given the same moves) by more than
``split_penalty``·σ² (σ² the pair's residual variance weighted by its image squared).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lfstudy.reconstruct.ipr.patches import _FitImages
from lfstudy.reconstruct.ipr.shake import _Particles, _unmerged

_SPLIT_SEPARATIONS = (0.5, 1.0, 1.5, 2.0)  # trial separations of the pair [voxels] along x, y or z
_SPLIT_SHAKE = (0.25, 0.125)  # the pair's Gauss–Seidel shake: one pass per step [voxels]


class _Image:
    """One exact image in its sensor patch, the light field's mask applied: rows r0.., columns c0.."""

    __slots__ = ("c0", "r0", "u")

    def __init__(self, r0: int, c0: int, u: np.ndarray) -> None:
        self.r0, self.c0, self.u = r0, c0, u

    def box(self) -> tuple[slice, slice]:
        return slice(self.r0, self.r0 + self.u.shape[0]), slice(self.c0, self.c0 + self.u.shape[1])

    def dot(self, img: np.ndarray) -> float:
        return float(np.sum(img[self.box()] * self.u))

    def cross(self, other: _Image) -> float:
        ra, rb = max(self.r0, other.r0), min(self.r0 + self.u.shape[0], other.r0 + other.u.shape[0])
        ca, cb = max(self.c0, other.c0), min(self.c0 + self.u.shape[1], other.c0 + other.u.shape[1])
        if ra >= rb or ca >= cb:
            return 0.0
        a = self.u[ra - self.r0 : rb - self.r0, ca - self.c0 : cb - self.c0]
        return float(np.sum(a * other.u[ra - other.r0 : rb - other.r0, ca - other.c0 : cb - other.c0]))


def _images(render: Any, pos: np.ndarray, mask: np.ndarray) -> list[_Image]:
    """The exact images of unit particles at ``pos`` (``render`` as :func:`particle_patches`), masked."""
    buf, offs, r0, c0, shp = render(pos)
    out = []
    for j in range(len(pos)):
        h, w = int(shp[j, 0]), int(shp[j, 1])
        r, c = int(r0[j]), int(c0[j])
        out.append(_Image(r, c, buf[offs[j] : offs[j + 1]].reshape(h, w) * mask[r : r + h, c : c + w]))
    return out


def _split_pairs(
    render: Any,
    res: np.ndarray,
    mask: np.ndarray,
    xyz: np.ndarray,
    inten: np.ndarray,
    vox: np.ndarray,
    *,
    floor: float,
    penalty: float,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """One round of the split: each particle brighter than ``ratio`` times the median tried as two (module
    docstring, "Split"); ``res`` (the exact residual) is updated in place for every split accepted.

    For particle p (image U0, intensity I0; R = res + I0·U0 the residual without it) and each trial pair
    p ± s/2 along x, y or z (s in ``_SPLIT_SEPARATIONS`` voxels) the two intensities are the least-squares
    solution θ = G⁻¹b (G the pair's 2 x 2 Gram matrix, b = (⟨R, U_A⟩, ⟨R, U_B⟩)), which lowers ‖R‖² by bᵀθ;
    the best pair is shaken (Gauss–Seidel: each member in turn moved to the best of its ±δ trial positions on
    the exact residual, the other held), the intensities refitted. The split is kept when both intensities
    exceed ``floor``, the members are at least half a voxel apart and the residual falls below the single
    particle's (at its best intensity, given the same shake) by more than ``penalty``·σ², σ² the pair fit's
    residual variance on the pixels its image lights (weights the model image squared).

    Returns the new positions and intensities (the second members appended) and the number of splits.
    """
    lit = inten[inten > 0]
    if len(lit) < 2:
        return xyz, inten, 0
    med = float(np.median(lit))
    order = [int(i) for i in np.argsort(-inten, kind="stable") if inten[i] > ratio * med]
    eye = np.eye(3)
    trials = [(k, s) for k in range(3) for s in _SPLIT_SEPARATIONS]
    new_pos, new_amp = [], []
    xyz, inten = xyz.copy(), inten.copy()
    for i in order:
        p0, i0 = xyz[i].copy(), float(inten[i])
        half = np.array([0.5 * s * vox[k] * eye[k] for k, s in trials])
        imgs = _images(render, np.vstack([p0[None], p0 + half, p0 - half]), mask)
        u0, pa, pb = imgs[0], imgs[1 : 1 + len(trials)], imgs[1 + len(trials) :]
        g00 = u0.cross(u0)
        if g00 <= 0.0:
            continue
        b0 = u0.dot(res) + i0 * g00

        def corr(v: _Image, *held: tuple[_Image, float], u0: _Image = u0, i0: float = i0) -> float:
            """⟨R − Σ held, v⟩ with R = res + I0·U0."""
            return v.dot(res) + i0 * u0.cross(v) - sum(a * h.cross(v) for h, a in held)

        def pair_fit(a: _Image, b: _Image) -> tuple[np.ndarray, float]:
            g = np.array([[a.cross(a), a.cross(b)], [a.cross(b), b.cross(b)]])
            rhs = np.array([corr(a), corr(b)])
            det = g[0, 0] * g[1, 1] - g[0, 1] ** 2
            if det <= 1e-12 * g[0, 0] * g[1, 1]:
                return np.zeros(2), -np.inf
            theta = np.array([g[1, 1] * rhs[0] - g[0, 1] * rhs[1], g[0, 0] * rhs[1] - g[0, 1] * rhs[0]]) / det
            return theta, float(rhs @ theta)

        fits = [pair_fit(a, b) for a, b in zip(pa, pb)]
        best = max(range(len(trials)), key=lambda t: fits[t][1] if fits[t][0].min() > floor else -np.inf)
        theta, q = fits[best]
        if not (theta.min() > floor and q > b0 * b0 / g00):
            continue

        def shake(pos: np.ndarray, img: _Image, step: float, *held: tuple[_Image, float]) -> list:
            """The best of ``pos`` and its ±step trial positions on R − Σ held: (position, image, intensity)."""
            moves = np.vstack([step * vox * eye, -step * vox * eye])
            imgs = [img, *_images(render, pos + moves, mask)]
            cs = [corr(v, *held) for v in imgs]
            gains = [c * c / v.cross(v) if (c > 0.0 and v.cross(v) > 0.0) else 0.0 for c, v in zip(cs, imgs)]
            k = int(np.argmax(gains)) if max(gains) > gains[0] * (1.0 + 1e-12) else 0
            amp = cs[k] / imgs[k].cross(imgs[k]) if gains[k] > 0.0 else 0.0
            return [pos + (moves[k - 1] if k else 0.0), imgs[k], amp, gains[k]]

        mem = [[p0 + half[best], pa[best], theta[0]], [p0 - half[best], pb[best], theta[1]]]
        one = [p0, u0, i0, b0 * b0 / g00]
        for step in _SPLIT_SHAKE:
            for m in range(2):
                mem[m] = shake(mem[m][0], mem[m][1], step, (mem[1 - m][1], mem[1 - m][2]))[:3]
            one = shake(one[0], one[1], step)  # the single particle gets the same moves
        theta, q = pair_fit(mem[0][1], mem[1][1])
        sep = np.abs(mem[0][0] - mem[1][0]) / vox
        if theta.min() <= floor or float(np.sqrt(np.sum(sep**2))) < 0.5:
            continue
        # σ² on the pixels the pair lights: the residual after the split weighted by the model image squared
        boxes = (u0, mem[0][1], mem[1][1])
        r0_, c0_ = min(im.r0 for im in boxes), min(im.c0 for im in boxes)
        r1_ = max(im.r0 + im.u.shape[0] for im in boxes)
        c1_ = max(im.c0 + im.u.shape[1] for im in boxes)
        loc = res[r0_:r1_, c0_:c1_].copy()
        model = np.zeros_like(loc)
        for im, amp in ((u0, -i0), (mem[0][1], theta[0]), (mem[1][1], theta[1])):
            sl = slice(im.r0 - r0_, im.r0 - r0_ + im.u.shape[0]), slice(im.c0 - c0_, im.c0 - c0_ + im.u.shape[1])
            loc[sl] -= amp * im.u
            if amp > 0:
                model[sl] += amp * im.u
        w = model * model
        s2 = float(np.sum(w * loc * loc) / np.sum(w)) if np.sum(w) > 0 else np.inf
        if q - one[3] <= penalty * s2:
            continue
        res[r0_:r1_, c0_:c1_] = loc
        xyz[i], inten[i] = mem[0][0], theta[0]
        new_pos.append(mem[1][0])
        new_amp.append(theta[1])
    if new_pos:
        xyz = np.vstack([xyz, np.array(new_pos)])
        inten = np.concatenate([inten, np.array(new_amp)])
    return xyz, inten, len(new_pos)


def _split(
    images: _FitImages,
    p: _Particles,
    res: np.ndarray,
    vox: np.ndarray,
    rounds: int,
    min_intensity: float,
    penalty: float,
    ratio: float,
) -> tuple[_Particles, int, int]:
    """Up to ``rounds`` rounds of :func:`_split_pairs` (the ghost floor ``min_intensity`` times the median), each
    followed by the merge of a new particle within half a voxel of another (its image added back to ``res``);
    the rounds stop at one that splits none. Returns the list (a split's second member appended, unshaken), the
    splits and the particles merged away."""
    n_split = merged = 0
    # close pairs the fit holds as one bright particle: tried as two (after the polish: before it, measured, the
    # polish's moves and merges undo the gain)
    for _ in range(rounds if len(p) > 1 else 0):
        n0, inten = len(p), p.inten
        floor = min_intensity * float(np.median(inten[inten > 0])) if np.any(inten > 0) else 0.0
        xyz, inten, n = _split_pairs(
            images.patches, res, images.mask, p.xyz, inten, vox, floor=floor, penalty=penalty, ratio=ratio
        )
        # the first member replaces the particle (position and intensity), the second is appended
        kept = _Particles(xyz[:n0], inten[:n0], p.sig, p.rel, p.still, p.sat)
        p = kept.append(_Particles.unshaken(xyz[n0:], inten[n0:]))
        n_split += n
        if not n:
            break
        keep = _unmerged(p.xyz, p.inten, vox)  # a new particle within half a voxel of another is merged
        merged += int((~keep).sum())
        images.add_images(p.xyz[~keep], p.inten[~keep], res, 1.0)
        p = p.take(keep)
    return p, n_split, merged
