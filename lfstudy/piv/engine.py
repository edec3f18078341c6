"""2-D / 3-D PIV by WIDIM (window displacement iterative multigrid), thesis ch. 6.

One code path serves images (y, x) and volumes (z, y, x):

* grid generation centred in the domain (sec. 6.1.1),
* FFT cross-correlation of mean-subtracted windows normalised to a correlation
  coefficient (sec. 6.1.2, eq. 6.1), in cache-sized blocks of windows with real
  FFTs; zero padding (linear correlation) pads to the shortest length exact over the
  lags used (~3/2 of the window, not 2x), transforms no all-zero line and inverts
  only the lines of the lags used,
* Gaussian three-point sub-voxel estimator per axis (eq. 6.2),
* normalised median test and iterative replacement (sec. 6.1.3, App. D),
* multi-pass predictor/corrector (sec. 6.1.4) and grid refinement (eqs 6.5-6.8).

Two predictor modes: ``"offset"`` reproduces the thesis (discrete integer window
offset of the second window, App. D ``piv_pass_discrete_3d``); ``"deform"`` (the
default, beyond the thesis) deforms both frames by -/+ half the dense predictor
with B-spline interpolation (symmetric, second-order offset after Wereley &
Meinhart, ref. [60]), which removes the peak-locking bias of the integer offset.

Sign convention: a pattern in ``b`` displaced by +d along an array axis relative
to ``a`` yields +d in that axis' component: ``u`` (last axis, x), ``v`` (axis
-2, y), ``w`` (axis 0, z; 3-D only).
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any

import numpy as np
import scipy.fft as sfft
import xarray as xr
from scipy import ndimage
from tqdm.auto import tqdm

from lfstudy.piv.deform import deform, dense_predictor, spline_coefficients
from lfstudy.piv.resolution import partial_windows, unresolved
from lfstudy.piv.subpixel import three_point
from lfstudy.piv.uncertainty import METHODS as _UNC_METHODS
from lfstudy.piv.uncertainty import window_uncertainty

__all__ = ["widim", "WidimSettings", "config_options", "peak_locking_index", "grid_nodes"]

_COMP = ("u", "v", "w")  # component of array axis -1, -2, -3
_DIMS3 = ("z", "y", "x")
_DIMS2 = ("y", "x")
_MODES = ("deform", "offset")
# correlation-plane voxels per batch when chunk_windows is not given (~128 MB float32)
_AUTO_BATCH_VOXELS = 2**25


# --------------------------------------------------------------------------- inputs
@dataclass
class _Input:
    data: Any  # numpy or dask array, (z, y, x) or (y, x)
    is_dask: bool
    dims: tuple[str, ...]
    coords: list[np.ndarray] | None  # 1-D physical coords per axis, or None
    coord_units: list[str] | None


def _as_input(x: Any, name: str) -> _Input:
    dims: tuple[str, ...] | None = None
    coords = units = None
    if isinstance(x, xr.DataArray):
        dims = tuple(str(d) for d in x.dims)
        if all(d in x.coords and x.coords[d].ndim == 1 for d in x.dims):
            coords = [np.asarray(x.coords[d].values, dtype=float) for d in x.dims]
            units = [str(x.coords[d].attrs.get("units", "coordinate units")) for d in x.dims]
        data = x.data
    else:
        data = x
    is_dask = hasattr(data, "dask") and hasattr(data, "chunks")
    if not is_dask:
        data = np.asarray(data)
    if data.ndim not in (2, 3):
        raise ValueError(
            f"input `{name}` must be 2-D (y, x) or 3-D (z, y, x); got {data.ndim}-D with shape {tuple(data.shape)}"
        )
    if not (np.issubdtype(data.dtype, np.number) or data.dtype == bool) or np.iscomplexobj(data):
        raise ValueError(f"input `{name}` must hold real numbers; got dtype {data.dtype}")
    if dims is None:
        dims = _DIMS3 if data.ndim == 3 else _DIMS2
    return _Input(data, is_dask, dims, coords, units)


def _count_nonfinite(inp: _Input) -> int:
    if np.issubdtype(inp.data.dtype, np.integer) or inp.data.dtype == bool:
        return 0
    if inp.is_dask:
        import dask

        # one streaming reduction: bounded memory, runs on any active scheduler/client
        (n,) = dask.compute((~_dask_isfinite(inp.data)).sum())
        return int(n)
    return int(np.count_nonzero(~np.isfinite(inp.data)))


def _plane_profiles(ia: _Input, ib: _Input) -> list[np.ndarray]:
    """Per axis, the sum of the two frames' mean intensities over each plane (one streaming pass where they are
    dask; :func:`lfstudy.piv.resolution.seeded_planes` reads it relative to its own level, so the scale is free)."""
    nd = ia.data.ndim
    # each frame reduced on its own: no volume-sized sum of the two is made
    means = [d.mean(axis=tuple(k for k in range(nd) if k != j)) for j in range(nd) for d in (ia.data, ib.data)]
    if ia.is_dask or ib.is_dask:
        import dask

        means = list(dask.compute(*means))
    return [np.asarray(ma, np.float64) + np.asarray(mb, np.float64) for ma, mb in zip(means[::2], means[1::2])]


def _dask_isfinite(arr: Any) -> Any:
    import dask.array as da

    return da.isfinite(arr)


def _as_tuple(value: Any, nd: int, name: str, *, minimum: int) -> tuple[int, ...]:
    vals = (value,) * nd if np.isscalar(value) else tuple(value)
    if len(vals) != nd:
        raise ValueError(
            f"`{name}` must be an int or a tuple of {nd} ints (one per axis {_DIMS3[-nd:]}); got {value!r}"
        )
    out = []
    for v in vals:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < minimum:
            raise ValueError(f"`{name}` must hold integers >= {minimum}; got {value!r}")
        out.append(int(v))
    return tuple(out)


def _check_number(value: Any, name: str, lo: float, *, strict: bool = True) -> float:
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not ok or not np.isfinite(value) or (value <= lo if strict else value < lo):
        rel = ">" if strict else ">="
        raise ValueError(f"`{name}` must be a finite number {rel} {lo}; got {value!r}")
    return float(value)


def _check_int(value: Any, name: str, lo: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < lo:
        raise ValueError(f"`{name}` must be an integer >= {lo}; got {value!r}")
    return int(value)


# --------------------------------------------------------------------------- grid
def grid_nodes(n: int, window: int, spacing: int) -> np.ndarray:
    """First-voxel indices of the windows along one axis, grid centred (sec. 6.1.1).

    Parameters
    ----------
    n : int
        Domain size along the axis (voxels).
    window, spacing : int
        Window size and spacing (voxels).

    Returns
    -------
    ndarray of int
        Node (first voxel) of each window; centres are ``node + (window - 1) / 2``.
    """
    count = (n - window) // spacing + 1
    offset = (n - window - (count - 1) * spacing) // 2  # centre the grid in the domain
    return offset + spacing * np.arange(count, dtype=np.int64)


def _level_sizes(window: tuple[int, ...], spacing: tuple[int, ...], rf: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    # eqs 6.5-6.8: size = ceil(size_i / Rf), spacing = ceil(spacing_i / Rf); sizes kept
    # even so the zero lag sits at the centre voxel of the correlation plane (sec. 6.1.5)
    w = tuple(-(-s // rf) for s in window)
    w = tuple(s + (s % 2) if rf > 1 else s for s in w)
    s = tuple(min(-(-sp // rf), ww) for sp, ww in zip(spacing, w))
    return w, s


# --------------------------------------------------------------------------- settings
_SUBPIXEL = ("auto", "gauss3")


def config_options(p: Mapping[str, Any]) -> dict[str, Any]:
    """The :func:`widim` keywords a config's ``piv`` section sets (window, spacing, levels, mode, sub-voxel estimator,
    predictor filter, zero padding): one mapping for the study, ``lfstudy piv`` and the config check. The
    uncertainty estimator and the progress bar are the caller's."""

    def seq(v: Any) -> Any:
        return tuple(v) if isinstance(v, (list, tuple)) else v

    return {
        "window": seq(p["window"]),
        "spacing": seq(p["spacing"]),
        "levels": p["levels"],
        "mode": p["mode"],
        "subpixel": p["subpixel"],
        "predictor_filter": p["predictor_filter"],
        "zero_pad": p.get("zero_pad", False),
        "unresolved_significance": p.get("unresolved_significance", 0.0),
    }


@dataclass(frozen=True)
class WidimSettings:
    """Validated settings of one WIDIM run (see :func:`widim` for their meaning)."""

    window: tuple[int, ...]
    spacing: tuple[int, ...]
    levels: int = 1
    mode: str = "deform"
    order: int = 5
    subpixel: str = "auto"
    zero_pad: bool = False
    max_passes: int = 10
    tol: float = 0.01
    nmt_eps: float = 0.1
    nmt_threshold: float = 2.0
    predictor_filter: float = 1.0
    chunk_windows: int | None = None
    workers: int | None = None
    unresolved_significance: float = 0.0

    @classmethod
    def build(cls, shape: Sequence[int], *, window: Any, spacing: Any = None, **kw: Any) -> WidimSettings:
        """Check every setting against the domain ``shape``; one clear ValueError per problem."""
        nd = len(shape)
        dims = _DIMS3[-nd:]
        window_t = _as_tuple(window, nd, "window", minimum=4)
        spacing_t = (
            tuple(max(1, x // 2) for x in window_t) if spacing is None else _as_tuple(spacing, nd, "spacing", minimum=1)
        )
        for ax in range(nd):
            if spacing_t[ax] > window_t[ax]:
                raise ValueError(
                    f"`spacing` must be <= `window` along axis {ax} ('{dims[ax]}'): "
                    f"allowed 1..{window_t[ax]}, got {spacing_t[ax]}"
                )
            if window_t[ax] > shape[ax]:
                raise ValueError(
                    f"`window` {window_t[ax]} along axis {ax} ('{dims[ax]}') exceeds the domain size {shape[ax]}"
                )
        d = cls(window_t, spacing_t)
        levels = _check_int(kw.get("levels", d.levels), "levels", 1)
        mode = kw.get("mode", d.mode)
        if mode not in _MODES:
            raise ValueError(f"`mode` must be one of {_MODES}; got {mode!r}")
        order = _check_int(kw.get("order", d.order), "order", 1)
        if order > 5:
            raise ValueError(f"`order` must be an integer in 1..5; got {order}")
        subpixel = kw.get("subpixel", d.subpixel)
        if subpixel not in _SUBPIXEL:
            raise ValueError(f"`subpixel` must be one of {_SUBPIXEL}; got {subpixel!r}")
        zero_pad = kw.get("zero_pad", d.zero_pad)
        if not isinstance(zero_pad, (bool, np.bool_)):
            raise ValueError(f"`zero_pad` must be True or False; got {zero_pad!r}")
        chunk = kw.get("chunk_windows")
        workers = kw.get("workers")
        margin = _check_number(
            kw.get("unresolved_significance", d.unresolved_significance), "unresolved_significance", 0.0, strict=False
        )
        if margin > 10:
            raise ValueError(f"`unresolved_significance` must be in [0, 10]; got {margin!r}")
        s = cls(
            window_t,
            spacing_t,
            levels=levels,
            mode=mode,
            order=order,
            subpixel=subpixel,
            zero_pad=bool(zero_pad),
            max_passes=_check_int(kw.get("max_passes", d.max_passes), "max_passes", 1),
            tol=_check_number(kw.get("tol", d.tol), "tol", 0.0, strict=False),
            nmt_eps=_check_number(kw.get("nmt_eps", d.nmt_eps), "nmt_eps", 0.0),
            nmt_threshold=_check_number(kw.get("nmt_threshold", d.nmt_threshold), "nmt_threshold", 0.0),
            predictor_filter=_check_number(
                kw.get("predictor_filter", d.predictor_filter), "predictor_filter", 0.0, strict=False
            ),
            chunk_windows=None if chunk is None else _check_int(chunk, "chunk_windows", 1),
            workers=None if workers is None else _check_int(workers, "workers", 1),
            unresolved_significance=margin,
        )
        for rf, (w, _) in enumerate(s.sizes, start=1):
            if min(w) < 4:
                raise ValueError(
                    f"`levels` = {levels} refines `window` {window_t} to {w} at level {rf}; "
                    f"every window side must stay >= 4 voxels: use fewer levels"
                )
        return s

    @property
    def sizes(self) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
        """(window, spacing) of every grid level (eqs 6.5–6.8)."""
        return [_level_sizes(self.window, self.spacing, rf) for rf in range(1, self.levels + 1)]

    def batch(self, w: Sequence[int]) -> int:
        """Windows correlated at once for windows of size ``w``."""
        if self.chunk_windows is not None:
            return self.chunk_windows
        plane = int(np.prod(_padded_shape(w, _radius(self.subpixel)) if self.zero_pad else w))
        return max(1, _AUTO_BATCH_VOXELS // plane)

    def attrs(self) -> dict[str, Any]:
        """The settings as netCDF/zarr-safe attributes."""
        out: dict[str, Any] = {}
        for k, v in self.__dict__.items():
            if k == "workers":
                continue  # results do not depend on it
            out[k] = list(v) if isinstance(v, tuple) else int(v) if isinstance(v, bool) else "auto" if v is None else v
        return out


# --------------------------------------------------------------------------- correlation
def _subpixel(rm: np.ndarray, r0: np.ndarray, rp: np.ndarray) -> np.ndarray:
    """Three-point peak offset (:func:`lfstudy.piv.subpixel.three_point`: Gaussian, eq. 6.2, parabolic
    where it cannot apply), 0 without a peak, clipped to one voxel."""
    eps = three_point(rm, r0, rp)
    return np.clip(np.nan_to_num(eps, nan=0.0, posinf=0.0, neginf=0.0), -1.0, 1.0)


#: 3-point Gaussian widths (σ², voxels²) above which the 5-point fit takes over.
_BROAD_SIGMA2 = 1.2**2


def _subpixel5(y: list[np.ndarray], eps3: np.ndarray) -> np.ndarray:
    """Peak offset of a broad peak: least-squares Gaussian through five points, else ``eps3``.

    ``y`` holds the correlation at lags −2..2 about the integer peak. A parabola
    fitted to ln y over the five points (equal weights: b = Σ i·ln y / 10, c =
    Σ (i² − 2)·ln y / 14) gives the offset −b/2c. Eq. 6.2 uses three points and
    is exact for a sampled Gaussian; for the broad, flat-topped peaks of
    particles elongated in depth (a plenoptic reconstruction's z, window
    truncation) it reads short, so the multi-pass loop converges slowly and
    stops short of the truth. Used only where the peak is broad (3-point
    width σ > 1.2 voxel) and all five values are positive.
    """
    pos = np.logical_and.reduce([v > 0 for v in y])
    with np.errstate(divide="ignore", invalid="ignore"):
        lm2, lm1, l0, lp1, lp2 = (np.log(np.where(pos, v, 1.0)) for v in y)
        b = (-2.0 * lm2 - lm1 + lp1 + 2.0 * lp2) / 10.0
        c = (2.0 * lm2 - lm1 - 2.0 * l0 - lp1 + 2.0 * lp2) / 14.0
        c3 = 0.5 * (lm1 - 2.0 * l0 + lp1)
        broad = pos & (c < 0) & (c3 < 0) & (-0.5 / np.where(c3 < 0, c3, -1.0) > _BROAD_SIGMA2)
        eps5 = np.clip(np.nan_to_num(-b / (2.0 * c), nan=0.0, posinf=0.0, neginf=0.0), -1.0, 1.0)
    return np.where(broad, eps5, eps3)


#: Bytes of float32 correlation plane per FFT call. The transforms, the spectrum
#: product and the peak search of a block then run in the core's cache; planes of a
#: whole batch (~128 MB) made every pass stream main memory (2-3x slower, one thread).
_FFT_BLOCK_BYTES = 2**20


def _correlate(
    wa: np.ndarray, wb: np.ndarray, zero_pad: bool, workers: int | None, subpixel: str = "auto"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched normalised FFT cross-correlation (sec. 6.1.2).

    ``wa``, ``wb`` are (n, *w) window stacks (fresh copies: modified in place).
    Returns displacement (n, nd) of the correlation peak in voxels (b relative to a),
    the peak correlation coefficient (n,) and a flag of non-empty windows (n,).
    The windows are correlated a cache-sized block at a time; each window's result
    depends on that window alone, not on the block, the batch or the thread count.
    With ``zero_pad`` the correlation is linear and its peak is searched over
    ``|lag| <= w // 2 - 1`` per axis (:func:`_padded_shape`); without, it is circular
    and searched over every lag but the two boundary lags of each axis.
    """
    n, w = wa.shape[0], tuple(wa.shape[1:])
    nd = len(w)
    plan = _CorrelationPlan.make(w, zero_pad, subpixel, workers, n)
    lag = np.empty((n, nd), dtype=np.int64)
    vals = np.empty((n, nd, len(plan.offsets)), dtype=np.float32)
    nonempty = np.empty(n, dtype=bool)
    for k in range(0, n, plan.step):  # loop over blocks of windows
        blk = slice(k, k + plan.step)
        lag[blk], vals[blk], nonempty[blk] = plan.correlate(wa[blk], wb[blk])
    r0 = vals[:, 0, plan.offsets.index(0)].astype(np.float64)  # the peak's correlation coefficient
    nb = dict(zip(plan.offsets, np.moveaxis(_unweighted(vals, lag, plan), -1, 0)))  # each (n, nd)
    disp = np.empty((n, nd), dtype=np.float64)
    for ax in range(nd):  # sub-voxel estimate per axis over all windows at once
        eps = _subpixel(nb[-1][:, ax], nb[0][:, ax], nb[1][:, ax])
        if 2 in nb and plan.shape[ax] >= 5:
            eps = _subpixel5([nb[o][:, ax] for o in (-2, -1, 0, 1, 2)], eps)
        disp[:, ax] = lag[:, ax] + eps
    peak = np.where(nonempty, r0, 0.0)
    disp[~nonempty] = 0.0
    return disp, peak, nonempty


def _unweighted(vals: np.ndarray, lag: np.ndarray, plan: _CorrelationPlan) -> np.ndarray:
    """The correlation values the sub-voxel estimators read, on a zero-padded (linear) plane with the windows'
    overlap weighting divided out; a circular plane's as they are.

    At a lag τ along an axis of N voxels only N − |τ| voxel pairs of the two windows overlap, so the linear
    correlation of a displaced pattern is its autocorrelation times (N − |τ|)/N: a weighting that pulls the
    fitted peak towards zero (Westerweel 1997, Meas. Sci. Technol. 8, 1379; Raffel et al. 2018, *Particle Image
    Velocimetry* sec. 5.4), the more the broader the peak is against the window. Particle images elongated in
    depth (e^-2 diameter 5.6 voxels) in a zero-padded 4-voxel z window read 0.29 of a displacement in one pass;
    divided by the weighting first, 0.86-0.93 (``tests/test_piv.py``). The values along each axis are divided by
    that axis' weighting alone (the other axes' lags are the peak's, a common factor of the estimate).

    A circular plane is left as it is: there the pairs that do not overlap meet wrapped voxels, uncorrelated only
    where the images are short against the window. In a 4-voxel z window with those images the division read
    0.08-0.25 of the displacement in one pass (0.23 without) and, on the demo study, raised IPR's uniform-shift
    errors by 12-45 % (docs/config.md, `piv.zero_pad`).

    ``vals`` (n, nd, K) are the correlation at ``lag + offsets`` along each axis; ``lag`` (n, nd) the signed
    integer peak.
    """
    if plan.spec is None:
        return vals
    n_ax = np.asarray(plan.w, dtype=np.float64)[None, :, None]
    tau = lag[:, :, None] + np.asarray(plan.offsets)[None, None, :]  # (n, nd, K): |τ| < N (_padded_shape)
    weight = (n_ax - np.abs(tau)) / n_ax
    return vals / np.maximum(weight, 1.0 / n_ax).astype(vals.dtype)


def _radius(subpixel: str) -> int:
    """Lags the sub-voxel estimator reads on either side of the integer peak."""
    return 2 if subpixel == "auto" else 1


def _padded_shape(w: Sequence[int], radius: int) -> tuple[int, ...]:
    """FFT size of zero-padded windows ``w`` (sec. 6.1.2): about 3/2 of the window.

    Zero padding makes the FFT correlation linear instead of circular. Two windows of
    n voxels zero-padded to L give the circular correlation c_L(p) = sum_j c(p + jL) of
    the linear one c(p) = sum_m a(m) b(m + p), which vanishes for |p| >= n: c_L(p) = c(p)
    wherever every alias p + jL (j != 0) has |p + jL| >= n, i.e. for |p| <= L - n. The
    peak search covers |p| <= n // 2 - 1 (the lags of the unpadded search, made
    symmetric; displacements beyond half a window are invalid anyway) and the sub-voxel
    estimator reads ``radius`` lags beyond it, so L >= n + n // 2 - 1 + radius gives
    exactly the correlation of padding to 2n at every lag used, with
    (3/2)^3 = 3.4x rather than 8x the window's voxels in 3-D (e.g. 8 x 32 x 32 windows:
    12 x 48 x 48 for the three-point estimator, 14 x 49 x 50 for the five-point one,
    instead of 16 x 64 x 64). L is ``scipy.fft.next_fast_len`` of that bound, for a real
    transform on the last axis and a complex one on the others, as they are transformed.
    """
    nd = len(w)
    return tuple(sfft.next_fast_len(n + n // 2 - 1 + radius, real=ax == nd - 1) for ax, n in enumerate(w))


@dataclass
class _CorrelationPlan:
    """Shapes, index tables and reused buffers of one :func:`_correlate` call.

    Unpadded windows give the circular correlation plane of their own size (lag p at
    index p mod w). Zero-padded windows give the linear correlation at the lags
    |p| <= ``origin`` per axis, the ``reach`` searched for the peak plus the estimator's
    ``offsets`` (see :func:`_padded_shape`): window b sits at ``origin`` in its padded
    array, which moves lag p to index p + origin (c'(p) = c(p - origin)), so the lags used
    form one box at the start of the plane and only its lines are inverse transformed.
    """

    w: tuple[int, ...]  # window size
    shape: tuple[int, ...]  # FFT size: w, or the padded size (_padded_shape)
    offsets: tuple[int, ...]  # peak neighbours read along each axis (0: the peak)
    workers: int | None
    step: int  # windows per block
    delta: np.ndarray  # (nd, K, nd) index offsets of the neighbours along each axis
    # unpadded: flat plane positions of the boundary lags (excluded) and flat-index strides
    edge: np.ndarray | None = None  # (prod(shape),) bool
    strides: np.ndarray | None = None  # (nd,)
    # zero-padded: searched lags |p| <= reach, window b placed at origin = reach + radius
    reach: tuple[int, ...] = ()
    origin: tuple[int, ...] = ()
    real: tuple[np.ndarray, np.ndarray] | None = None  # a, b: (step, *w[:-1], shape[-1]) float32, zero off the data
    spec: tuple[np.ndarray, np.ndarray] | None = None  # two (step, *shape[:-1], shape[-1] // 2 + 1) complex64

    @classmethod
    def make(cls, w: tuple[int, ...], zero_pad: bool, subpixel: str, workers: int | None, n: int) -> _CorrelationPlan:
        nd = len(w)
        radius = _radius(subpixel)
        offsets = tuple(range(-radius, radius + 1))
        shape = _padded_shape(w, radius) if zero_pad else w
        step = max(1, min(n, _FFT_BLOCK_BYTES // (4 * int(np.prod(shape)))))
        delta = np.zeros((nd, len(offsets), nd), dtype=np.int64)
        for ax in range(nd):
            delta[ax, :, ax] = offsets
        plan = cls(w, shape, offsets, workers, step, delta)
        if zero_pad:
            plan.reach = tuple(s // 2 - 1 for s in w)
            plan.origin = tuple(k + radius for k in plan.reach)
            half = (*shape[:-1], shape[-1] // 2 + 1)
            plan.real = tuple(np.zeros((step, *w[:-1], shape[-1]), np.float32) for _ in range(2))
            plan.spec = (np.empty((step, *half), np.complex64), np.empty((step, *half), np.complex64))
        else:
            # integer peak on the unshifted plane (lag L at index L mod S); the boundary lags of
            # the shifted plane (-S//2 and S-1-S//2) are excluded so eq. 6.2 has both neighbours
            grid = np.indices(shape).reshape(nd, -1)
            plan.edge = np.zeros(grid.shape[1], dtype=bool)
            for ax, sz in enumerate(shape):
                plan.edge |= (grid[ax] == (-(sz // 2)) % sz) | (grid[ax] == (sz - 1 - sz // 2) % sz)
            plan.strides = np.array([int(np.prod(shape[ax + 1 :])) for ax in range(nd)], dtype=np.int64)
        return plan

    def correlate(self, wa: np.ndarray, wb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Correlate one block of windows (m, *w).

        Returns the integer peak lag (m, nd), the normalised correlation at the peak's
        neighbours ``offsets`` along each axis (m, nd, K) and the non-empty flag (m,).
        """
        m, w, shape = wa.shape[0], self.w, self.shape
        axes = tuple(range(1, len(w) + 1))
        # a constant window has no pattern: exact test before any rounding of the mean
        nonempty = (_ptp(wa) > 0) & (_ptp(wb) > 0)
        wa = wa.astype(np.float32, copy=False)
        wb = wb.astype(np.float32, copy=False)
        wa -= wa.mean(axis=axes, keepdims=True)  # correlate fluctuations only [3, p. 320]
        wb -= wb.mean(axis=axes, keepdims=True)
        # std before zero padding (sec. 6.1.2); float64 sums so the flag of empty windows is exact
        sa = np.sqrt(np.square(wa, dtype=np.float64).reshape(m, -1).mean(1))
        sb = np.sqrt(np.square(wb, dtype=np.float64).reshape(m, -1).mean(1))
        r = self.plane(wa, wb)
        denom = float(np.prod(w)) * sa * sb  # eq. 6.1 scaled to a correlation coefficient
        nonempty &= denom > 1e-30  # below float32 resolution of the correlation sums
        scale = np.where(nonempty, 1.0 / np.where(nonempty, denom, 1.0), 0.0)
        scale = np.minimum(scale, np.finfo(np.float32).max).astype(np.float32)
        # The positive scale of a window does not move its peak: the raw plane is searched
        # and only the values the estimator reads are scaled (the same float32 products).
        rows = np.arange(m)[:, None, None]
        if self.spec is None:  # circular plane
            r = r.reshape(m, -1)
            flat = self._peak(r)
            idx = np.stack(np.unravel_index(flat, shape), axis=-1)  # (m, nd)
            nb = (idx[:, None, None, :] + self.delta) % np.asarray(shape)  # (m, nd, K, nd)
            vals = r[rows, nb @ self.strides]
            half = np.asarray(shape) // 2
            lag = (idx + half) % np.asarray(shape) - half  # eqs 6.3-6.4 (0-based, unshifted)
        else:  # linear correlation, lag p at index p + origin: search |p| <= reach
            core = r[(slice(None), *(slice(o - k, o + k + 1) for o, k in zip(self.origin, self.reach)))]
            flat = np.ascontiguousarray(core).reshape(m, -1).argmax(axis=1)  # first if tied
            lag = np.stack(np.unravel_index(flat, core.shape[1:]), axis=-1) - np.asarray(self.reach)
            nb = lag[:, None, None, :] + self.delta + np.asarray(self.origin)  # (m, nd, K, nd)
            vals = r[(rows, *np.moveaxis(nb, -1, 0))]
        return lag, vals * scale[:, None, None], nonempty

    def plane(self, wa: np.ndarray, wb: np.ndarray) -> np.ndarray:
        """Raw cross-correlation c(p) = sum_m a(m) b(m + p) of float32 windows (m, *w).

        Unpadded: the circular plane (m, *shape), lag p at index p mod shape. Zero-padded:
        the linear correlation at lags |p| <= origin, (m, *(2 origin + 1)), lag p at index
        p + origin (a view).
        """
        m, shape = wa.shape[0], self.shape
        axes = tuple(range(1, len(shape) + 1))
        if self.spec is None:
            fa = sfft.rfftn(wa, axes=axes, workers=self.workers)
            fb = sfft.rfftn(wb, axes=axes, workers=self.workers)
        else:
            fa = self._rfftn_padded(wa, self.spec[0][:m], self.real[0][:m], (0,) * len(shape))
            fb = self._rfftn_padded(wb, self.spec[1][:m], self.real[1][:m], self.origin)
        np.conjugate(fa, out=fa)
        fa *= fb  # cross-spectral density conj(FA) FB -> R(p) = sum a(m) b(m + p)
        if self.spec is None:
            return sfft.irfftn(fa, s=shape, axes=axes, workers=self.workers, overwrite_x=True)
        # inverse one axis at a time, each over the lines whose output lies in the box of used lags
        box = [2 * o + 1 for o in self.origin]
        for ax in axes[:-1]:
            fa = sfft.ifft(fa, axis=ax, overwrite_x=True, workers=self.workers)
            fa = fa[(slice(None),) * ax + (slice(0, box[ax - 1]),)]
        r = sfft.irfft(fa, n=shape[-1], axis=-1, workers=self.workers)
        return r[..., : box[-1]]

    def _peak(self, r: np.ndarray) -> np.ndarray:
        """Flat index of each row's maximum outside the boundary lags (first if tied)."""
        flat = r.argmax(axis=1)
        # the maximum over the whole plane is the answer unless it lies on a boundary lag
        # (rare): search those rows again with the boundary lags masked
        redo = np.flatnonzero(self.edge[flat])
        if redo.size:
            sub = r[redo]
            sub[:, self.edge] = -np.inf
            flat[redo] = sub.argmax(axis=1)
        return flat

    def _rfftn_padded(self, x: np.ndarray, out: np.ndarray, real: np.ndarray, origin: Sequence[int]) -> np.ndarray:
        """``rfftn`` of each window of ``x`` (m, *w) placed at ``origin`` in zeros of ``shape``, into ``out``.

        ``real`` (m, *w[:-1], shape[-1]) is zero off ``origin[-1] : origin[-1] + w[-1]`` and keeps
        the same ``origin`` from call to call. The last axis is transformed first on the data
        lines only; each earlier axis is then transformed in place over the lines that hold
        data, so the all-zero lines of the padding are never transformed: the spectrum of
        ``rfftn`` of the padded windows with about half the work.
        """
        w, workers = self.w, self.workers
        data = tuple(slice(o, o + s) for o, s in zip(origin, w))
        real[..., data[-1]] = x  # the padding around the data is zero from allocation, never written
        out[(slice(None), *data[:-1])] = sfft.rfft(real, axis=-1, workers=workers)
        for ax in range(len(w) - 1, 0, -1):  # array axes before the last, batch axis excluded
            # data fills data[:ax] of the axes before ax: transform axis ax over that part
            lead = (slice(None), *data[: ax - 1])
            out[(*lead, slice(0, data[ax - 1].start))] = 0
            out[(*lead, slice(data[ax - 1].stop, None))] = 0
            view = out[lead]
            res = sfft.fft(view, axis=ax, overwrite_x=True, workers=workers)
            if not np.may_share_memory(res, out):  # scipy transforms in place; guard regardless
                view[...] = res
        return out


def _ptp(win: np.ndarray) -> np.ndarray:
    flat = win.reshape(win.shape[0], -1)
    return flat.max(axis=1) - flat.min(axis=1)


def _gather(img: np.ndarray, origin: Sequence[int], starts: np.ndarray, w: Sequence[int]) -> np.ndarray:
    """Windows ``img[start : start + w]`` (float32 copies, shape (n, *w)).

    ``img`` is a slab of the domain beginning at global index ``origin`` and
    covering every in-domain voxel the windows touch; what lies beyond it is
    beyond the domain and reads as zero (App. D ``piv_pass_discrete_3d``).
    Fancy indexing of a sliding-window view copies whole window rows at once.
    """
    rel = starts - np.asarray(origin)
    before = np.maximum(0, -rel.min(axis=0))
    after = np.maximum(0, rel.max(axis=0) + np.asarray(w) - np.asarray(img.shape))
    src = img.astype(np.float32, copy=False)
    if before.any() or after.any():
        src = np.pad(src, list(zip(before, after)))
    view = np.lib.stride_tricks.sliding_window_view(src, tuple(w))
    return view[tuple((rel + before).T)]


# --------------------------------------------------------------------------- fields
def _neighbours(field: np.ndarray) -> np.ndarray:
    """Stack of the 3x3(x3) neighbours (centre excluded), NaN beyond the grid edge.

    ``field`` is (C, *grid); returns (K, C, *grid) with K = 8 (2-D) or 26 (3-D).
    """
    nd = field.ndim - 1
    pad = np.pad(field, [(0, 0)] + [(1, 1)] * nd, constant_values=np.nan)
    grid = field.shape[1:]
    out = []
    for off in itertools.product((-1, 0, 1), repeat=nd):  # neighbourhood offsets
        if any(off):
            out.append(pad[(slice(None), *tuple(slice(1 + o, 1 + o + g) for o, g in zip(off, grid)))])
    return np.stack(out)


def _median_test(d: np.ndarray, usable: np.ndarray, eps: float, threshold: float) -> np.ndarray:
    """Normalised median test (Westerweel & Scarano 2005; sec. 6.1.3, App. D).

    Returns True where the vector fails. The normalised residuals of the components
    are combined as a vector magnitude, as in App. D ``normalized_median_test_3d``.
    """
    nb = _neighbours(np.where(usable, d, np.nan))
    has = np.isfinite(nb).any(axis=0).all(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN neighbourhoods
        med = np.nanmedian(nb, axis=0)
        res = np.nanmedian(np.abs(nb - med), axis=0)
    r = np.abs(d - med) / (res + eps)
    norm = np.sqrt(np.sum(r * r, axis=0))
    return ~usable | (has & ~(norm <= threshold))


def _replace(d: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """Fill flagged vectors with the mean of their valid neighbours, iterating outwards.

    Sec. 6.1.3 step 2 (App. D averages the valid neighbours); every vector ends
    finite: with no valid vector at all the field becomes zero.
    """
    out = np.where(bad, np.nan, d)
    good = ~bad
    for _ in range(sum(d.shape[1:])):  # passes over the grid, not over windows
        if good.all():
            break
        nb = _neighbours(np.where(good, out, np.nan))
        cnt = np.isfinite(nb[:, 0]).sum(axis=0)
        fill = ~good & (cnt > 0)
        if not fill.any():
            break
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(nb, axis=0)
        out = np.where(fill, mean, out)
        good = good | fill
    return np.where(good, out, 0.0)


def _validate(
    d: np.ndarray, usable: np.ndarray, eps: float, threshold: float, max_iter: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """Iterative detection and replacement (sec. 6.1.3 steps 1-3); returns field, valid."""
    usable = usable & np.isfinite(d).all(axis=0)
    flagged = _median_test(d, usable, eps, threshold)
    out = _replace(d, flagged)
    for _ in range(max_iter - 1):  # step 3: repeat on the repaired field until no new outliers
        new = _median_test(out, np.ones_like(usable), eps, threshold) & ~flagged
        if not new.any():
            break
        flagged |= new
        out = _replace(d, flagged)
    return out, ~flagged


def _filter_predictor(field: np.ndarray, sigma: float) -> np.ndarray:
    """The predictor of the next pass: the validated field, Gaussian-filtered over the vector grid.

    Iterative deformation amplifies the corrector's noise at wavelengths near
    the vector spacing pass after pass; a low-pass filter of the predictor
    (Schrijer & Scarano 2008) keeps the iteration stable, so more passes
    converge instead of drifting. ``sigma`` is in vector spacings; 0 leaves
    the field as it is. Only the predictor is filtered: :func:`widim` still
    returns predictor + corrector of its last pass.
    """
    if sigma <= 0:
        return field
    # Normalised convolution without the outermost vectors: windows on a face of the
    # domain lose particles and read short; a plain filter would spread that bias inward.
    w = np.ones(field.shape[1:])
    for ax, n in enumerate(w.shape):
        if n >= 3:
            idx = [slice(None)] * w.ndim
            idx[ax] = [0, -1]
            w[tuple(idx)] = 0.0
    sig = [sigma] * w.ndim
    den = ndimage.gaussian_filter(w, sig, mode="constant", truncate=2.0)
    out = np.empty_like(field)
    for c in range(field.shape[0]):
        num = ndimage.gaussian_filter(field[c] * w, sig, mode="constant", truncate=2.0)
        out[c] = np.where(den > 1e-3, num / np.maximum(den, 1e-3), field[c])
    return out


# --------------------------------------------------------------------------- one pass
def _load_pair(a: _Input, b: _Input, lo_a, hi_a, lo_b, hi_b) -> tuple[np.ndarray, np.ndarray]:
    sla = tuple(slice(int(x), int(y)) for x, y in zip(lo_a, hi_a))
    slb = tuple(slice(int(x), int(y)) for x, y in zip(lo_b, hi_b))
    if a.is_dask or b.is_dask:
        import dask

        # only this batch's slabs are computed: memory bounded by the batch
        xa, xb = dask.compute(a.data[sla], b.data[slb])
    else:
        xa, xb = a.data[sla], b.data[slb]
    return np.asarray(xa, dtype=np.float64), np.asarray(xb, dtype=np.float64)


def _pass(
    a: _Input,
    b: _Input,
    nodes: list[np.ndarray],
    w: tuple[int, ...],
    pred: np.ndarray,
    centres: list[np.ndarray],
    settings: WidimSettings,
    cache: dict | None = None,
    uncertainty: str | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Correlate every window once; returns corrector (nd, *grid), peak, nonempty and, with an
    ``uncertainty`` method, σ of the corrector (nd, *grid) from the same windows, else None."""
    mode, order, batch = settings.mode, settings.order, settings.batch(w)
    full = tuple(int(s) for s in a.data.shape)
    nd = len(full)
    grid = tuple(len(n) for n in nodes)
    nwin = int(np.prod(grid))
    starts_all = np.stack([n.ravel() for n in np.meshgrid(*nodes, indexing="ij")], axis=1)
    wv = np.asarray(w)
    corr = np.empty((nwin, nd))
    peak = np.empty(nwin)
    nonempty = np.empty(nwin, dtype=bool)
    sigma = np.full((nwin, nd), np.nan) if uncertainty else None
    if mode == "offset":
        # integer predictor offsets the second window only (sec. 6.1.4, App. D)
        ioff = np.rint(pred).reshape(nd, -1).T.astype(np.int64)
    else:
        margin = int(np.ceil(np.abs(pred).max(initial=0.0) / 2)) + 16  # spline support + prefilter decay
    for k0 in range(0, nwin, batch):  # loop over batches of windows
        k1 = min(k0 + batch, nwin)
        st = starts_all[k0:k1]
        lo = st.min(axis=0)
        hi = st.max(axis=0) + wv
        if mode == "offset":
            stb = st + ioff[k0:k1]
            lob = np.clip(stb.min(axis=0), 0, full)
            hib = np.clip(stb.max(axis=0) + wv, 0, full)
            hib = np.maximum(hib, lob + 1)
            sa, sb = _load_pair(a, b, lo, hi, lob, hib)
            wa = _gather(sa, lo, st, w)
            wb = _gather(sb, lob, stb, w)
        else:
            slo = np.maximum(lo - margin, 0)
            shi = np.minimum(hi + margin, full)
            key = (tuple(slo), tuple(shi))
            if cache is not None and cache.get("key") == key:
                sa, sb, coefs = cache["slabs"]
            else:
                sa, sb = _load_pair(a, b, slo, shi, slo, shi)
                coefs = None
            if order in (3, 5):
                # numba kernel, predictor interpolated per voxel in the kernel
                if coefs is None:
                    coefs = (spline_coefficients(sa, order), spline_coefficients(sb, order))
                da = deform(coefs[0], nd, -1.0, lo, hi, slo, pred, centres, order)
                db = deform(coefs[1], nd, +1.0, lo, hi, slo, pred, centres, order)
            else:
                vox = [np.arange(l, h, dtype=float) for l, h in zip(lo, hi)]
                dense = dense_predictor(pred, centres, vox)
                base = np.meshgrid(*[v - s for v, s in zip(vox, slo)], indexing="ij")
                # symmetric offset: a sampled at x - d/2, b at x + d/2
                da = ndimage.map_coordinates(
                    sa, [g - 0.5 * dd for g, dd in zip(base, dense)], order=order, mode="grid-constant", cval=0.0
                )
                db = ndimage.map_coordinates(
                    sb, [g + 0.5 * dd for g, dd in zip(base, dense)], order=order, mode="grid-constant", cval=0.0
                )
                del base, dense
            if cache is not None and nwin <= batch:
                # one batch covers the domain: keep the slabs and spline coefficients for the
                # next pass instead of re-reading and re-filtering unchanged frames
                cache["key"], cache["slabs"] = key, (sa, sb, coefs)
            wa = _gather(da, lo, st, w)
            wb = _gather(db, lo, st, w)
            # the spline prefilter rings faintly into empty regions; judge emptiness on
            # the raw windows so an all-zero input window stays empty (peak 0, invalid)
            raw_ok = (_ptp(_gather(sa, slo, st, w)) > 0) & (_ptp(_gather(sb, slo, st, w)) > 0)
        c, p, ne = _correlate(wa, wb, settings.zero_pad, settings.workers, settings.subpixel)
        if mode != "offset":
            ne &= raw_ok
            p = np.where(raw_ok, p, 0.0)
            c[~raw_ok] = 0.0
        corr[k0:k1], peak[k0:k1], nonempty[k0:k1] = c, p, ne
        if sigma is not None:
            sigma[k0:k1] = np.where(
                ne[:, None], window_uncertainty(wa, wb, uncertainty, unweighted=settings.zero_pad), np.nan
            )
    corr_g = np.moveaxis(corr.reshape((*grid, nd)), -1, 0)
    sig_g = None if sigma is None else np.moveaxis(sigma.reshape((*grid, nd)), -1, 0)
    return corr_g, peak.reshape(grid), nonempty.reshape(grid), sig_g


# --------------------------------------------------------------------------- public API
def widim(
    a: Any,
    b: Any,
    *,
    window: int | Sequence[int] = 32,
    spacing: int | Sequence[int] | None = None,
    levels: int = 1,
    mode: str = "deform",
    order: int = 5,
    subpixel: str = "auto",
    zero_pad: bool = False,
    max_passes: int = 10,
    tol: float = 0.01,
    nmt_eps: float = 0.1,
    nmt_threshold: float = 2.0,
    predictor_filter: float = 1.0,
    chunk_windows: int | None = None,
    workers: int | None = None,
    progress: bool = False,
    uncertainty: str | None = "correlation",
    unresolved_significance: float = 0.0,
) -> xr.Dataset:
    """Multi-pass, multi-grid PIV of two images or volumes (WIDIM, thesis ch. 6).

    Parameters
    ----------
    a, b : ndarray or xarray.DataArray
        First and second frame, both 2-D ``(y, x)`` or both 3-D ``(z, y, x)``, same
        shape. DataArrays may be dask-backed; they are then read batch by batch.
        If every dimension has a 1-D coordinate of its own name, the result also
        carries physical coordinates and ``*_mm`` displacements.
    window : int or tuple of int
        Initial (level 1) window size per axis in voxels, e.g. ``(16, 32, 32)``.
    spacing : int or tuple of int, optional
        Initial window spacing per axis, ``1 <= spacing <= window``; default half
        the window (50 % overlap).
    levels : int
        Number of grid levels; level ``Rf = 1..levels`` uses ``ceil(window / Rf)``
        rounded up to even and ``ceil(spacing / Rf)`` (eqs 6.5-6.8).
    mode : {"deform", "offset"}
        ``"deform"``: symmetric image deformation by -/+ half the continuous
        predictor with B-splines (default, beyond the thesis).
        ``"offset"``: discrete integer window offset of the second window by the
        rounded predictor (the thesis' method, sec. 6.1.4).
    order : int
        B-spline order of the image deformation (1..5; ``"deform"`` mode only;
        3 and 5 use a numba kernel). Quintic is the default: its interpolation
        bias is ~0.003 vox against ~0.01 vox for cubic (2.8-voxel particles,
        benchmarks/bench_piv.py) at about twice the deformation cost.
    subpixel : {"auto", "gauss3"}
        Sub-voxel peak estimator: ``"gauss3"`` is the three-point Gaussian of eq.
        6.2; ``"auto"`` (default) fits a Gaussian through five points where the
        peak is broad (particles elongated in depth, as a plenoptic
        reconstruction makes them), which keeps the estimate unbiased there.
    zero_pad : bool
        Zero-pad the windows before the FFT so the correlation is linear, free of
        the circular wrap-around (sec. 6.1.2). The peak is searched over lags
        ``|lag| <= window // 2 - 1`` per axis (the unpadded search's lags, made
        symmetric; padding to twice the window, as before, searched up to
        ``window - 2``, but displacements beyond half a window are invalid anyway); windows are padded
        to the shortest fast FFT length at which the correlation over those lags
        and the estimator's neighbours equals the twice-padded one: about 3/2 of
        the window (e.g. 32 -> 48 or 50, 8 -> 12 or 14).
    max_passes : int
        Maximum passes per grid level (>= 1).
    tol : float
        A level ends when the corrector RMS changes by less than ``tol`` voxels
        between passes or falls below ``tol`` (App. D uses 0.1 px).
    nmt_eps, nmt_threshold : float
        Noise level ε and threshold of the normalised median test [1]_ (0.1 and 2,
        sec. 6.1.3).
    predictor_filter : float
        σ, in vector spacings, of a Gaussian filter applied to the validated
        field before it deforms the next pass (predictor filtering, Schrijer &
        Scarano [2]_): stops the passes from amplifying noise near the vector
        spacing. 0 = off (the thesis' WIDIM).
    chunk_windows : int, optional
        Windows correlated per batch; bounds memory (and the slab of a dask input
        read at once). Default: about 2**25 correlation-plane voxels per batch.
    workers : int, optional
        Threads for ``scipy.fft``; results do not depend on it.
    progress : bool
        Show a tqdm bar over the passes (level, corrector RMS and valid % as it goes).
    uncertainty : {"correlation", "independent", "moment", "none"} or None
        Per-vector standard uncertainty of each component from the final pass's
        windows (:mod:`lfstudy.piv.uncertainty`): ``"correlation"`` (default) is
        Wieneke's correlation statistics [3]_ in 3-D with the correlation of
        neighbouring voxels' contributions counted, ``"independent"`` the same as
        published, ``"moment"`` a simpler peak-width estimate; None or ``"none"``
        (the ``piv.uncertainty`` setting's word) skips it (no ``unc_*`` variables).
    unresolved_significance : float
        The ``unresolved`` flag's margin over the field's own noise, in standard deviations of what the vectors'
        errors give its curvature estimate (:func:`lfstudy.piv.resolution.unresolved`'s ``significance``;
        ``piv.unresolved_significance``), 0–10; 0 (default): the noise is not considered.
        :data:`lfstudy.piv.resolution.NOISE_MARGIN_95` (2.39) leaves a vector of pure noise unflagged with 95 %
        probability.

    Returns
    -------
    xarray.Dataset
        ``u, v[, w]`` (voxels), ``valid``, ``peak``, optional ``u_mm, v_mm[, w_mm]``,
        with ``uncertainty``: ``unc_u, unc_v[, unc_w]`` (voxels, NaN where the vector
        is invalid or replaced), ``unresolved`` (bool: the final window's filtering of
        the measured field likely exceeds σ, :func:`lfstudy.piv.resolution.unresolved`),
        ``partial`` (bool: the final window lies partly outside the seeded region,
        :func:`lfstudy.piv.resolution.partial_windows`; never ``unresolved``)
        and, with physical coordinates, ``unc_u_mm`` etc.,
        window-centre coordinates ``x, y[, z]`` (physical if available, else voxel
        index) and ``x_index, y_index[, z_index]``, and per-pass ``corrector_rms``,
        ``valid_percent`` and ``level`` over dimension ``pass``.

    Raises
    ------
    ValueError
        On mismatched shapes, non-finite voxels, windows larger than the domain
        or out-of-range parameters.

    References
    ----------
    .. [1] J. Westerweel, F. Scarano, "Universal outlier detection for PIV
           data", Experiments in Fluids 39 (6) pp 1096--1100 (2005),
           doi:10.1007/s00348-005-0016-6
    .. [2] F. F. J. Schrijer, F. Scarano, "Effect of predictor-corrector
           filtering on the stability and spatial resolution of iterative PIV
           interrogation", Experiments in Fluids 45 (5) pp 927--941 (2008),
           doi:10.1007/s00348-008-0511-7
    .. [3] B. Wieneke, "PIV uncertainty quantification from correlation
           statistics", Measurement Science and Technology 26 (7) 074002
           (2015), doi:10.1088/0957-0233/26/7/074002

    Examples
    --------
    Two 64 x 64 frames of the same particles, the second displaced by 1.5 px
    along y and -0.75 px along x (array-axis order):

    >>> from lfstudy.piv import particle_pair, widim
    >>> a, b = particle_pair((64, 64), (1.5, -0.75), density=0.02, seed=1)
    >>> res = widim(a, b, window=16)
    >>> dict(res.sizes)
    {'y': 7, 'x': 7, 'pass': 4}
    >>> round(float(res.v.median()), 1), round(float(res.u.median()), 2)
    (1.5, -0.75)
    >>> float(res.valid.mean())
    1.0
    """
    ia = _as_input(a, "a")
    ib = _as_input(b, "b")
    if tuple(ia.data.shape) != tuple(ib.data.shape):
        raise ValueError(
            f"inputs `a` and `b` must have the same shape; got a {tuple(ia.data.shape)} and b {tuple(ib.data.shape)}"
        )
    shape = tuple(int(s) for s in ia.data.shape)
    nd = len(shape)
    st = WidimSettings.build(
        shape,
        window=window,
        spacing=spacing,
        levels=levels,
        mode=mode,
        order=order,
        subpixel=subpixel,
        zero_pad=zero_pad,
        max_passes=max_passes,
        tol=tol,
        nmt_eps=nmt_eps,
        nmt_threshold=nmt_threshold,
        predictor_filter=predictor_filter,
        chunk_windows=chunk_windows,
        workers=workers,
        unresolved_significance=unresolved_significance,
    )
    if uncertainty == "none":
        uncertainty = None
    if uncertainty is not None and uncertainty not in _UNC_METHODS:
        raise ValueError(f"`uncertainty` must be one of {_UNC_METHODS}, 'none' or None; got {uncertainty!r}")
    for name, inp in (("a", ia), ("b", ib)):
        bad = _count_nonfinite(inp)
        if bad:
            raise ValueError(
                f"input `{name}` contains {bad} non-finite (NaN or inf) voxel(s) of "
                f"{int(np.prod(shape))}; mask or fill them before PIV"
            )
    if ia.coords is not None and ib.coords is not None:
        for ax in range(nd):
            if not np.allclose(ia.coords[ax], ib.coords[ax]):
                raise ValueError(f"inputs `a` and `b` have different coordinates along '{ia.dims[ax]}'")

    field = None
    cache: dict = {}
    centres_prev: list[np.ndarray] | None = None
    history = _History()
    # the bar's total is the pass budget; levels that converge early finish it sooner
    bar = tqdm(total=st.levels * st.max_passes, desc="PIV passes", unit="pass", disable=not progress, mininterval=1.0)
    for level, (w, s) in enumerate(st.sizes, start=1):  # grid refinement (sec. 6.1.5)
        nodes = [grid_nodes(shape[ax], w[ax], s[ax]) for ax in range(nd)]
        centres = [n + (w[ax] - 1) / 2.0 for ax, n in enumerate(nodes)]
        grid = tuple(len(n) for n in nodes)
        if field is None:
            field = np.zeros((nd, *grid))  # no predictor on the first pass
        else:  # predictor interpolated onto the finer grid (sec. 6.1.4)
            field = dense_predictor(field, centres_prev, centres)
        rms_old = None
        for _ in range(st.max_passes):  # multi-pass (sec. 6.1.4, Fig. 6.1)
            pred = np.rint(field) if st.mode == "offset" else _filter_predictor(field, st.predictor_filter)
            # the uncertainty of the finest level's passes; the last one's is kept
            unc_method = uncertainty if level == st.levels else None
            corr, peak, nonempty, sigma = _pass(ia, ib, nodes, w, pred, centres, st, cache, unc_method)
            d = pred + corr  # d = p + c (Fig. 6.1)
            field, valid = _validate(d, nonempty, st.nmt_eps, st.nmt_threshold)
            rms = float(np.sqrt(np.mean(np.sum(corr[:, nonempty] ** 2, axis=0)))) if nonempty.any() else 0.0
            history.add(rms, 100.0 * float(valid.mean()), level)
            bar.update(1)
            bar.set_postfix(level=level, corrector_rms=f"{rms:.3f}", valid=f"{history.valid[-1]:.1f}%")
            if rms < st.tol or (rms_old is not None and abs(rms - rms_old) < st.tol):
                break
            rms_old = rms
        centres_prev = centres
    bar.total = bar.n  # converged early: the bar ends full, at the passes actually run
    bar.refresh()
    bar.close()
    flag = partial = None
    if sigma is not None:  # a replaced vector has no uncertainty of its own
        sigma = np.where(valid, sigma, np.nan)
        # truth-free: windows partly outside the seeded region, and where the final window's filtering of the
        # measured field likely exceeds σ (issue 38)
        partial = partial_windows(_plane_profiles(ia, ib), nodes, st.sizes[-1][0])
        flag = unresolved(
            field,
            sigma,
            st.sizes[-1][0],
            st.sizes[-1][1],
            partial=partial,
            valid=valid & ~partial,
            significance=st.unresolved_significance,
        )
    ds = _to_dataset(field, valid, peak, centres, ia, shape, st, history, sigma, flag, partial)
    ds.attrs["uncertainty"] = uncertainty or "none"
    return ds


@dataclass
class _History:
    """Per-pass records: corrector RMS, valid %, grid level."""

    rms: list[float] = dc_field(default_factory=list)
    valid: list[float] = dc_field(default_factory=list)
    level: list[int] = dc_field(default_factory=list)

    def add(self, rms: float, valid: float, level: int) -> None:
        self.rms.append(rms)
        self.valid.append(valid)
        self.level.append(level)


def _to_dataset(
    field: np.ndarray,
    valid: np.ndarray,
    peak: np.ndarray,
    centres: list[np.ndarray],
    ia: _Input,
    shape: tuple[int, ...],
    settings: WidimSettings,
    history: _History,
    sigma: np.ndarray | None = None,
    flag: np.ndarray | None = None,
    partial: np.ndarray | None = None,
) -> xr.Dataset:
    nd = len(shape)
    dims = _DIMS3[-nd:]
    rec_rms, rec_valid, rec_level = history.rms, history.valid, history.level
    comp = _COMP[:nd][::-1]  # array axis order: (w, v, u) or (v, u)
    data_vars: dict[str, Any] = {}
    coords: dict[str, Any] = {}
    phys = ia.coords is not None
    for ax, dim in enumerate(dims):
        coords[f"{dim}_index"] = (
            dim,
            centres[ax],
            {"units": "voxel", "long_name": f"window centre {dim} (array index along axis {ax - nd})"},
        )
        if phys:
            c = ia.coords[ax]
            idx = np.arange(c.size, dtype=float)
            coords[dim] = (
                dim,
                np.interp(centres[ax], idx, c),
                {"units": ia.coord_units[ax], "long_name": f"window centre {dim}"},
            )
        else:
            coords[dim] = (dim, centres[ax], {"units": "voxel", "long_name": f"window centre {dim}"})
    for ax, name in enumerate(comp):
        dim = dims[ax]
        data_vars[name] = (
            dims,
            field[ax],
            {"units": "voxel", "long_name": f"{dim} displacement (array axis {ax - nd})"},
        )
        unc_name = f"standard uncertainty of the {dim} displacement (NaN: invalid or replaced vector)"
        if sigma is not None:
            data_vars[f"unc_{name}"] = (dims, sigma[ax], {"units": "voxel", "long_name": unc_name})
        if phys:
            c = ia.coords[ax]
            step = np.gradient(c) if c.size > 1 else np.ones(1)
            # signed step: a decreasing coordinate flips the physical sign on purpose
            local = np.interp(centres[ax], np.arange(c.size, dtype=float), step)
            shp = [1] * nd
            shp[ax] = -1
            data_vars[f"{name}_mm"] = (
                dims,
                field[ax] * local.reshape(shp),
                {"units": ia.coord_units[ax], "long_name": f"{dim} displacement"},
            )
            if sigma is not None:
                data_vars[f"unc_{name}_mm"] = (
                    dims,
                    sigma[ax] * np.abs(local).reshape(shp),
                    {"units": ia.coord_units[ax], "long_name": unc_name},
                )
    data_vars["valid"] = (
        dims,
        valid.astype(bool),
        {"long_name": "passed the normalised median test at the final pass (not replaced)", "units": "1"},
    )
    flags = (
        (
            "unresolved",
            flag,
            "the final window's filtering likely exceeds the uncertainty (truth-free: the measured field's curvature "
            "x L^2/24 above UNRESOLVED_FACTOR sigma in a component, lfstudy.piv.resolution; never on a partial window)",
        ),
        (
            "partial",
            partial,
            "the final window lies partly outside the seeded region (truth-free: less than SEEDED_INSIDE of its "
            "length along an axis in the planes of at least half the seeded level, lfstudy.piv.resolution): it "
            "measures its seeded part, not the box about its centre",
        ),
    )
    for name, values, long_name in flags:
        if values is not None:
            data_vars[name] = (dims, values.astype(bool), {"long_name": long_name, "units": "1"})
    data_vars["peak"] = (
        dims,
        peak,
        {"long_name": "correlation peak (normalised correlation coefficient)", "units": "1"},
    )
    npass = len(rec_rms)
    coords["pass"] = ("pass", np.arange(1, npass + 1), {"long_name": "pass number", "units": "1"})
    data_vars["corrector_rms"] = (
        "pass",
        np.asarray(rec_rms),
        {"units": "voxel", "long_name": "RMS of the corrector over all windows and components"},
    )
    data_vars["valid_percent"] = (
        "pass",
        np.asarray(rec_valid),
        {"units": "percent", "long_name": "vectors passing the normalised median test"},
    )
    data_vars["level"] = (
        "pass",
        np.asarray(rec_level, dtype=np.int64),
        {"units": "1", "long_name": "grid refinement level Rf of the pass"},
    )
    from lfstudy import __version__  # the one version lookup (package __init__)

    attrs = {
        "title": "WIDIM PIV result",
        "method": "WIDIM (Lynch 2011, ch. 6) with "
        + (
            f"symmetric order-{settings.order} B-spline image deformation"
            if settings.mode == "deform"
            else "discrete integer window offset"
        ),
        "lfstudy_version": __version__,
        "input_shape": list(shape),
        "input_dims": list(ia.dims),
        "final_window": list(settings.sizes[-1][0]),
        "final_spacing": list(settings.sizes[-1][1]),
        "sign_convention": "+d along an array axis of b relative to a gives +d; u: axis -1 (x), "
        "v: axis -2 (y), w: axis 0 (z)",
        "n_passes": npass,
        **settings.attrs(),
    }
    return xr.Dataset(data_vars, coords=coords, attrs=attrs)


def peak_locking_index(measured: Any, true: Any, *, bins: int = 10) -> float:
    """Peak-locking figure: RMS over fractional-displacement bins of the mean error.

    The vectors are grouped by the fractional part of the true displacement into
    ``bins`` equal bins over one voxel; the systematic (mean) error in each bin
    is the peak-locking error of that sub-voxel position, and the figure is the
    RMS of those bin means in voxels. Random error averages out, so the figure
    isolates the bias that makes peak locking (0 for an unbiased estimator).

    Parameters
    ----------
    measured, true : array_like
        Measured and true displacements (same shape, voxels). Non-finite pairs
        are ignored.
    bins : int
        Bins over the unit fractional interval.

    Returns
    -------
    float
        RMS of the per-bin mean error (voxels); NaN if no finite pairs.
    """
    m = np.asarray(measured, dtype=float).ravel()
    t = np.broadcast_to(np.asarray(true, dtype=float), np.shape(measured)).ravel()
    ok = np.isfinite(m) & np.isfinite(t)
    if not ok.any():
        return float("nan")
    m, t = m[ok], t[ok]
    b = np.minimum((np.mod(t, 1.0) * bins).astype(int), bins - 1)
    err = m - t
    cnt = np.bincount(b, minlength=bins)
    mean = np.bincount(b, weights=err, minlength=bins)[cnt > 0] / cnt[cnt > 0]
    return float(np.sqrt(np.mean(mean**2)))
