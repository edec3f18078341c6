"""Particle tracking between two fitted particle lists, binned on a PIV grid (issue 27).

A reconstruction that fits particles (IPR) gives their positions in both frames. Cross-correlation
windows average the displacement over their volume and filter its gradient: on Hill's vortex the
demo designs' error equals the oracle's (WIDIM on the true volumes), whatever the reconstruction.
A matched particle pair is a displacement with no window. Here:

1. :func:`match_particles`: every particle of frame a is moved by a predictor (the case's WIDIM
   result, interpolated trilinearly at the particle's midpoint position), and paired with the
   nearest particle of frame b within a search radius, measured in voxels per axis (the scaled
   distance of the found criterion of :mod:`lfstudy.study.particle_metrics`). A pair is kept only
   if it is mutual: the b particle's nearest predicted a position is that same particle.
   Predictor-based nearest-neighbour matching is the standard 3-D PTV step (Malik, Dracos &
   Papantoniou 1993, Exp. Fluids 15 279; with a predicted position as in Shake-the-Box,
   Schanz, Gesemann & Schröder 2016, Exp. Fluids 57:70); the mutual condition drops the
   ambiguous pairs (two candidates for one partner).
2. :func:`bin_tracks`: at every vector of the PIV grid, the tracks inside the final window's box
   are fitted by linear least squares, ``d = c0 + G·(x − x_c)`` per component, and the fit is
   evaluated at the centre (``c0``). A linear field is then recovered exactly wherever the tracks
   lie; the top-hat mean of the same tracks is off by ``G·(x̄ − x_c)``, the gradient times the
   offset of their centroid. The standard uncertainty of ``c0`` is ``sqrt(s² [(XᵀX)⁻¹]₀₀)``
   with ``s²`` the residual variance over ``n − 4`` degrees of freedom (ordinary least squares,
   e.g. Draper & Smith 1998, *Applied Regression Analysis*, ch. 5). That variance sees the noise,
   not the bias the fit's order leaves on a curved field (Hill's vortex: RMS error 1.8 times the
   RMS σ in x and y). A model term is added in quadrature: the bias the fit's weights give the next
   order's terms, whose coefficients a pilot fit over a box 1.5 windows wide estimates, less the
   pilot's own noise (:func:`_model_sd`; Fan & Gijbels 1996).

The functions are pure (arrays and xarray objects in, out) and know nothing of the study: the
workflow reads the particle lists written beside the volumes and calls them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

__all__ = [
    "PARTICLE_MODES",
    "SEARCH",
    "MODEL_BOX",
    "FIT_PARAMETERS",
    "positions",
    "predict",
    "match_particles",
    "validate_tracks",
    "bin_tracks",
    "PAIRED_WEIGHTS",
    "depth_weights",
    "PAIRED_UNCERTAINTY",
    "track_sigma",
]

#: Default search radius of a match, in voxels per axis (scaled distance).
SEARCH = 1.5

#: The ``piv.particles`` settings that read the fitted particle lists of both frames: ``ptv`` (the tracks
#: binned on the WIDIM grid) and ``paired`` (WIDIM again on volumes of the paired particles alone).
PARTICLE_MODES = ("ptv", "paired")

#: Parameters of the local polynomial fit per component, by order: c0 (0, the mean), the three
#: gradient terms (1), the six second-derivative terms (2), the ten third-derivative terms (3: only
#: the model term's pilot fit of an order-2 binning, :func:`bin_tracks` ``model_box``).
FIT_PARAMETERS = {0: 1, 1: 4, 2: 10, 3: 20}

#: The orders :func:`bin_tracks` fits.
ORDERS = (0, 1, 2)

#: Default pilot box of the uncertainty's model term, in final windows per axis (:func:`bin_tracks`
#: ``model_box``), chosen on the demo design against 1.25 and 2 (``docs/config.md``,
#: ``benchmarks/bench_ptv_model.py``): 1.25 (a pilot of ~2 windows' tracks) over-covers a linear
#: field, 2 averages the curvature of Hill's vortex away.
MODEL_BOX = 1.5

#: Largest pilot box of the model term, in final windows per axis.
MODEL_BOX_MAX = 5.0

_XYZ = ("x", "y", "z")
_COMP = ("u", "v", "w")  # displacement along x, y, z


def positions(particles: Any) -> np.ndarray:
    """Particle positions as an ``(n, 3)`` array of x, y, z [mm].

    Parameters
    ----------
    particles : xarray.Dataset or array_like
        A particle list (``x``, ``y``, ``z`` over ``particle``, as IPR writes it) or an
        ``(n, 3)`` array of x, y, z.

    Returns
    -------
    ndarray
        Float64 positions; ``(0, 3)`` for an empty list.
    """
    if isinstance(particles, xr.Dataset):
        return np.column_stack([np.asarray(particles[k].values, float).ravel() for k in _XYZ]).reshape(-1, 3)
    arr = np.asarray(particles, float)
    if arr.size == 0:
        return np.zeros((0, 3))
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"particle positions must be an (n, 3) array of x, y, z; got shape {arr.shape}")
    return arr


def _voxel_of(piv: xr.Dataset) -> np.ndarray:
    """Voxel size [mm] per axis (x, y, z) from a WIDIM result's window centres: mm over index."""
    out = []
    for ax in _XYZ:
        idx = f"{ax}_index"
        if ax not in piv.coords or idx not in piv.coords or piv.sizes[ax] < 2:
            raise ValueError(
                f"cannot infer the voxel size along {ax} from the PIV result (no '{idx}' coordinate "
                "or a single window); pass voxel=(dx, dy, dz) in mm"
            )
        out.append(float(np.median(np.abs(np.diff(piv[ax].values) / np.diff(piv[idx].values)))))
    return np.asarray(out)


def _voxel(voxel: Sequence[float] | None, piv: xr.Dataset) -> np.ndarray:
    vox = _voxel_of(piv) if voxel is None else np.asarray(voxel, float)
    if vox.shape != (3,) or not np.all(np.isfinite(vox) & (vox > 0)):
        raise ValueError(f"voxel = {voxel!r}: three sizes > 0 mm (x, y, z)")
    return vox


def predict(predictor: xr.Dataset, xyz: np.ndarray) -> np.ndarray:
    """The predictor's displacement [mm] at points, trilinear over its valid vectors.

    Parameters
    ----------
    predictor : xarray.Dataset
        A WIDIM result (:func:`lfstudy.piv.widim`): ``u_mm, v_mm, w_mm`` and ``valid`` on
        ``(z, y, x)`` window centres with coordinates in mm.
    xyz : ndarray (n, 3)
        Points x, y, z [mm].

    Returns
    -------
    ndarray (n, 3)
        Displacement along x, y, z [mm]: the valid vectors interpolated trilinearly with their
        validity as weight (a normalised interpolation: an invalid neighbour does not count);
        where no valid vector is among the eight neighbours, the nearest valid one; points beyond
        the grid take its edge. Zero when the predictor has no valid vector.
    """
    xyz = positions(xyz)
    dims = ("z", "y", "x")
    valid = predictor["valid"].transpose(*dims).values.astype(bool)
    comps = [predictor[f"{c}_mm"].transpose(*dims).values.astype(float) for c in ("w", "v", "u")]
    valid &= np.all([np.isfinite(c) for c in comps], axis=0)
    out = np.zeros((len(xyz), 3))
    if not valid.any() or not len(xyz):
        return out
    axes = [np.asarray(predictor[d].values, float) for d in dims]
    flip = [slice(None, None, -1) if a.size > 1 and a[0] > a[-1] else slice(None) for a in axes]
    axes = [a[f] for a, f in zip(axes, flip)]
    valid = valid[tuple(flip)]
    comps = [c[tuple(flip)] for c in comps]
    pts = xyz[:, ::-1]  # z, y, x
    pts = np.column_stack([np.clip(pts[:, k], a[0], a[-1]) for k, a in enumerate(axes)])
    # a single window along an axis: the interpolator needs two nodes; repeat it one step on
    grid = [a if a.size > 1 else np.array([a[0], a[0] + 1.0]) for a in axes]
    pad = tuple((0, 0) if a.size > 1 else (0, 1) for a in axes)

    def interp(values: np.ndarray) -> np.ndarray:  # values on the windows; padded here, once
        return RegularGridInterpolator(grid, np.pad(values, pad, mode="edge"), method="linear")(pts)

    den = interp(valid.astype(float))
    num = [interp(np.where(valid, c, 0.0)) for c in comps]
    ok = den > 1e-9
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)[valid]
    if not ok.all():
        _, near = cKDTree(centres).query(pts[~ok])
    for k, (n, c) in enumerate(zip(num, comps)):
        col = 2 - k  # w -> z (column 2), v -> y, u -> x
        out[ok, col] = n[ok] / den[ok]
        if not ok.all():
            out[~ok, col] = c[valid][near]
    return out


def match_particles(
    a: Any,
    b: Any,
    predictor: xr.Dataset,
    *,
    search: float = SEARCH,
    voxel: Sequence[float] | None = None,
    iterations: int = 2,
) -> xr.Dataset:
    """Pair the particles of two frames: mutual nearest neighbours about the predicted positions.

    Each particle of frame a at ``x_a`` is moved by the predictor's displacement ``d``, taken at
    the midpoint ``x_a + d/2`` (``iterations`` fixed-point steps from ``d = P(x_a)``, the midpoint
    reference of WIDIM's central-difference vectors), to its predicted position ``p = x_a + d``.
    Distances are in voxels per axis (``|(x − y) / voxel|``). Particle ``i`` of a and ``j`` of b
    form a track when ``j`` is the nearest b particle to ``p_i``, ``i`` the nearest predicted
    position to ``x_b,j``, and they lie within ``search`` of each other (Malik, Dracos &
    Papantoniou 1993; the mutual condition drops a candidate that is another particle's better
    match).

    Parameters
    ----------
    a, b : xarray.Dataset or ndarray (n, 3)
        The particle lists of frames a and b (x, y, z [mm]).
    predictor : xarray.Dataset
        The WIDIM result between the frames (:func:`predict`).
    search : float
        Search radius in voxels per axis (> 0).
    voxel : (dx, dy, dz), optional
        Voxel size [mm]; default the predictor's (window centres in mm over their voxel index).
    iterations : int
        Midpoint iterations of the predicted displacement (>= 0; 0: the predictor at ``x_a``).

    Returns
    -------
    xarray.Dataset
        Over dimension ``track``: ``x, y, z`` (the pair's midpoint [mm]), ``u_mm, v_mm, w_mm``
        (``x_b − x_a`` [mm]), ``index_a``, ``index_b`` (rows of the inputs), ``miss`` (distance
        of ``x_b`` from the predicted position, voxels) and, where both lists carry position
        uncertainties (``sigma_x/y/z``, as IPR writes them), ``sigma_u_mm``, ``sigma_v_mm``,
        ``sigma_w_mm``: ``sqrt(σ_a² + σ_b²)``. Attrs: ``search``, ``voxel_mm``, ``n_a``,
        ``n_b``, ``n_tracks``.

    Examples
    --------
    >>> import numpy as np, xarray as xr
    >>> from lfstudy.piv import match_particles
    >>> g = {"z": [0.0, 1.0], "y": [0.0, 1.0], "x": [0.0, 1.0]}
    >>> one = xr.DataArray(np.ones((2, 2, 2)), coords=g, dims=("z", "y", "x"))
    >>> pred = xr.Dataset({"u_mm": 0.1 * one, "v_mm": 0 * one, "w_mm": 0 * one, "valid": one > 0})
    >>> a = np.array([[0.2, 0.5, 0.5], [0.7, 0.5, 0.5]])
    >>> t = match_particles(a, a + [0.11, 0.0, 0.0], pred, voxel=(0.05, 0.05, 0.05))
    >>> t.index_b.values.tolist(), np.round(t.u_mm.values, 3).tolist()
    ([0, 1], [0.11, 0.11])
    """
    if not (isinstance(search, (int, float)) and math.isfinite(search) and search > 0):
        raise ValueError(f"search = {search!r}: the search radius must be a number > 0 (voxels)")
    if int(iterations) < 0:
        raise ValueError(f"iterations = {iterations!r}: must be >= 0")
    vox = _voxel(voxel, predictor)
    xa, xb = positions(a), positions(b)
    d = predict(predictor, xa)
    for _ in range(int(iterations)):
        d = predict(predictor, xa + 0.5 * d)
    pa = xa + d
    ia = np.zeros(0, int)
    jb = np.zeros(0, int)
    miss = np.zeros(0)
    if len(xa) and len(xb):
        dist, j = cKDTree(xb / vox).query(pa / vox, distance_upper_bound=float(search))
        _, i_back = cKDTree(pa / vox).query(xb / vox, distance_upper_bound=float(search))
        hit = j < len(xb)
        idx = np.flatnonzero(hit)
        mutual = i_back[j[hit]] == idx
        ia, jb, miss = idx[mutual], j[hit][mutual], dist[hit][mutual]
    mid = 0.5 * (xa[ia] + xb[jb])
    disp = xb[jb] - xa[ia]
    sig = _sigmas(a, b, ia, jb)
    T = "track"
    mm = lambda ln: {"units": "mm", "long_name": ln}  # noqa: E731
    return xr.Dataset(
        {
            **{ax: (T, mid[:, k], mm(f"track midpoint {ax}")) for k, ax in enumerate(_XYZ)},
            **{
                f"{c}_mm": (T, disp[:, k], mm(f"{ax} displacement (b − a)"))
                for k, (c, ax) in enumerate(zip(_COMP, _XYZ))
            },
            "index_a": (T, ia.astype(np.int64), {"units": "1", "long_name": "particle of frame a"}),
            "index_b": (T, jb.astype(np.int64), {"units": "1", "long_name": "particle of frame b"}),
            "miss": (T, miss, {"units": "voxel", "long_name": "distance of b from the predicted position"}),
            **{
                f"sigma_{c}_mm": (T, sig[:, k], mm(f"{ax} displacement uncertainty (both particles' sigma)"))
                for k, (c, ax) in enumerate(zip(_COMP, _XYZ))
                if sig is not None
            },
        },
        attrs={
            "search": float(search),
            "voxel_mm": [float(v) for v in vox],
            "iterations": int(iterations),
            "n_a": len(xa),
            "n_b": len(xb),
            "n_tracks": len(ia),
        },
    )


def _exponents(order: int) -> list[tuple[int, int, int]]:
    """Exponents (of x, y, z) of the monomials of the local polynomial of ``order``, by degree: 1; x, y,
    z; x², y², z², xy, xz, yz; then the ten cubic ones (the pilot fit of :func:`_model_sd`)."""
    out = [(0, 0, 0)]
    if order >= 1:
        out += [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    if order >= 2:
        out += [(2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1)]
    if order >= 3:
        out += [(i, j, 3 - i - j) for i in range(3, -1, -1) for j in range(3 - i, -1, -1)]
    return out


def _design(dx: np.ndarray, order: int) -> np.ndarray:
    """Columns of the local polynomial of ``order`` at ``dx`` (n, 3): the monomials of
    :func:`_exponents` (1: 1, x, y, z; 2: also the six quadratic terms; 3: also the ten cubic ones)."""
    ones = np.ones(len(dx))
    powers = [[ones] for _ in range(3)]  # powers[axis][k] = dx[:, axis] ** k, by products (exact)
    for axis in range(3):
        for _ in range(order):
            powers[axis].append(powers[axis][-1] * dx[:, axis])
    return np.column_stack([powers[0][i] * powers[1][j] * powers[2][k] for i, j, k in _exponents(order)])


def _sigmas(a: Any, b: Any, ia: np.ndarray, jb: np.ndarray) -> np.ndarray | None:
    """``sqrt(σ_a² + σ_b²)`` per track and axis from the lists' ``sigma_x/y/z`` [mm] (IPR's fit
    covariance), or None where either list has none."""
    names = [f"sigma_{ax}" for ax in _XYZ]
    if not all(isinstance(p, xr.Dataset) and all(nm in p for nm in names) for p in (a, b)):
        return None
    sa = np.column_stack([np.asarray(a[nm].values, float) for nm in names]).reshape(-1, 3)[ia]
    sb = np.column_stack([np.asarray(b[nm].values, float) for nm in names]).reshape(-1, 3)[jb]
    return np.sqrt(sa * sa + sb * sb)


def _fit(dx: np.ndarray, y: np.ndarray, w: np.ndarray, order: int) -> tuple[np.ndarray, ...] | None:
    """Weighted least squares of ``y`` (n, 3) on the local polynomial of ``order`` in ``dx``, weights
    ``w`` (n, 3) per component: the value at dx = 0 and its standard uncertainty per component
    (``s² [(XᵀWX)⁻¹]₀₀``, ``s²`` the weighted residual variance), the intercept's weights ``l`` (3, n)
    (``c0 = lᵀ y``) and the coefficients (3, p) with the covariance of the fit (3, p, p); None where the
    design is rank deficient. Order 0 is the weighted mean."""
    X = _design(dx, order)
    n, p = X.shape
    value, sd = np.empty(3), np.empty(3)
    ell, coefs, covs = np.empty((3, n)), np.empty((3, p)), np.empty((3, p, p))
    for k in range(3):
        if k == 0 or not np.array_equal(w[:, k], w[:, k - 1]):  # unweighted: one inverse for all three
            xtwx = X.T @ (X * w[:, k, None])
            if np.linalg.matrix_rank(xtwx) < p:
                return None
            inv = np.linalg.inv(xtwx)
        coef = inv @ (X.T @ (w[:, k] * y[:, k]))
        res = y[:, k] - X @ coef
        s2 = float(np.sum(w[:, k] * res * res)) / (n - p)
        value[k], sd[k] = coef[0], math.sqrt(max(s2 * inv[0, 0], 0.0))
        ell[k] = (inv[0] @ X.T) * w[:, k]
        coefs[k], covs[k] = coef, s2 * inv
    return value, sd, ell, coefs, covs


def _model_sd(
    dx: np.ndarray,
    ell: np.ndarray,
    pilot_dx: np.ndarray,
    pilot_y: np.ndarray,
    pilot_w: np.ndarray,
    order: int,
) -> np.ndarray:
    """The model (truncation) term of an order-``order`` fit's value per component: the bias its
    intercept weights ``ell`` (3, n) give the next order's terms at the bin's tracks ``dx`` (n, 3),
    their coefficients taken from a pilot fit of order ``order + 1`` to the tracks of a larger box
    (``pilot_*``, same scaled coordinates). ``b = Σ_i l_i Σ_|α|=p+1 β_α dx_i^α`` is the leading bias of
    local polynomial regression (Fan & Gijbels 1996, *Local Polynomial Modelling and Its
    Applications*, eq. 3.5; Ruppert & Wand 1994, Ann. Statist. 22 1346, thm 2.1), with β the pilot
    estimate of the (p+1)-th derivatives (the plug-in of Ruppert, Sheather & Wand 1995, JASA 90 1257).
    The pilot's own noise would add to |b| on a field with no curvature, so the returned term is
    ``sqrt(max(b² − var(b), 0))``, ``var(b) = aᵀ C a`` (a = the bin's weighted moments of the
    (p+1)-th monomials, C the pilot coefficients' covariance): an unbiased estimate of b² clipped at
    zero. Zero where the pilot fit is not possible (too few tracks, rank deficient)."""
    out = np.zeros(3)
    nxt = order + 1
    lo, hi = FIT_PARAMETERS[order], FIT_PARAMETERS[nxt]
    if len(pilot_dx) < hi + 2:
        return out
    pilot = _fit(pilot_dx, pilot_y, pilot_w, nxt)
    if pilot is None:
        return out
    _, _, _, coefs, covs = pilot
    top = _design(dx, nxt)[:, lo:hi]  # the (p+1)-th degree monomials at the bin's tracks
    for k in range(3):
        a = ell[k] @ top
        b = float(a @ coefs[k, lo:hi])
        var = float(a @ covs[k, lo:hi, lo:hi] @ a)
        out[k] = math.sqrt(max(b * b - var, 0.0))
    return out


def _weights(tracks: xr.Dataset, n: int, weighted: bool, vox: np.ndarray) -> np.ndarray:
    """Per track and component, 1 / σ² of the displacement from the tracks' ``sigma_*_mm`` (a floor of
    0.01 voxel; 0 where σ is not finite: the track does not count); ones without them or unweighted."""
    names = [f"sigma_{c}_mm" for c in _COMP]
    if not weighted or not all(nm in tracks for nm in names):
        return np.ones((n, 3))
    sd = np.column_stack([np.asarray(tracks[nm].values, float) for nm in names]).reshape(-1, 3)
    sd = np.maximum(sd, 0.01 * vox)
    return np.where(np.isfinite(sd), 1.0 / np.where(np.isfinite(sd), sd, 1.0) ** 2, 0.0)


def bin_tracks(
    tracks: xr.Dataset,
    piv_grid: xr.Dataset,
    *,
    window: Sequence[float] | None = None,
    voxel: Sequence[float] | None = None,
    order: int = 1,
    weighted: bool = False,
    model_box: float = MODEL_BOX,
) -> xr.Dataset:
    """The tracks' displacement at every vector of a PIV grid, by a local linear fit.

    At each window centre ``x_c`` the tracks whose midpoints lie in the box of the window (``window``
    voxels per axis about ``x_c``) are fitted by weighted least squares, per component,
    ``d = c0 + G·(x − x_c)``, and ``c0`` is the vector. Its standard uncertainty is
    ``sqrt(s² [(XᵀWX)⁻¹]₀₀)``, ``s²`` the weighted residual variance over ``n − 4`` degrees of
    freedom (W: the tracks' inverse variances, or 1):
    the scatter of the tracks about the local linear field (position noise of both frames, the
    field's curvature), through the leverage of their layout. A fit of ``p`` parameters
    (:data:`FIT_PARAMETERS`) needs ``max(4, p + 2)`` tracks not all on a plane; with fewer the next
    lower order is fitted, down to the (weighted) mean (its uncertainty the standard error, with at
    least 2 tracks); with fewer the vector is invalid. ``order=2`` adds the quadratic terms
    (second-order polynomial binning, as the ensemble PTV of Agüera, Cafiero, Astarita & Discetti
    2016, Meas. Sci. Technol. 27 124011): the box's curvature bias goes, at more noise. The
    residual variance does not measure the bias the fit's order leaves on a curved field, so
    (``model_box`` > 0) a model term is added to the uncertainty in quadrature: the next order's
    terms, fitted over a pilot box, through the fit's weights (:func:`_model_sd`).

    Parameters
    ----------
    tracks : xarray.Dataset
        :func:`match_particles`' result.
    piv_grid : xarray.Dataset
        The WIDIM result whose grid the vectors go on (its window centres ``z, y, x`` [mm], their
        voxel index ``*_index``, ``final_window`` attribute).
    window : (wz, wy, wx), optional
        Box size in voxels; default the grid's ``final_window``.
    voxel : (dx, dy, dz), optional
        Voxel size [mm]; default the grid's.
    order : {0, 1, 2}
        Order of the local polynomial: 0 the mean of the tracks (the top-hat average of a
        window), 1 linear (default), 2 quadratic.
    model_box : float
        The model (truncation) term of the uncertainty: 0 leaves it out; else the pilot box, in
        final windows per axis (1 to :data:`MODEL_BOX_MAX`), whose tracks a fit of order
        ``order + 1`` gets the next order's coefficients from. The bias those terms give the
        vector (:func:`_model_sd`) is added to the fit's standard uncertainty in quadrature; the
        vectors do not change. Default :data:`MODEL_BOX` (1.5). Measured on
        ``benchmarks/ptv_model_demo.yaml`` (M −1, pitch 0.0888, seed 21, order 1; coverage and RMS
        error / RMS σ, x / y / z): Hill's vortex 0.49 / 0.53 / 0.54 and 1.86 / 1.80 / 1.32 without it,
        0.61 / 0.65 / 0.59 and 1.35 / 1.28 / 1.11 with it; the uniform flow 1.05 / 1.07 / 1.06 ->
        0.98 / 0.97 / 0.94 (the pilot's noise the subtraction does not take off: ``b² − var`` is
        clipped at 0). A box of 1.25 windows gives 0.74 / 0.77 / 0.71 there, 2 windows 1.52 / 1.45
        on Hill's x and y (``docs/config.md``).
    weighted : bool
        Weight each track's component by ``1 / σ²`` of its displacement where the tracks carry
        ``sigma_u_mm`` ... (:func:`match_particles` from lists with position uncertainties, as IPR
        writes them); a track with an infinite σ is left out. The uncertainty's scale is still the
        weighted residual variance, so a σ that is right only in proportion does no harm. Off by
        default: on the demo design (``config/demo_ptv.yaml``, M −1, pitch 0.0888, uniform flow)
        IPR's σ tells the worse tracks apart (RMS w error 0.018 mm in the quarter of the tracks with
        the smallest σ_w, 0.032 mm in the third), but the weighted fit's total RMS error is the same
        to 1 % there and on Hill's vortex.

    Returns
    -------
    xarray.Dataset
        The WIDIM result with its vectors replaced: ``u, v, w`` [voxel], ``u_mm, v_mm, w_mm``,
        ``unc_*`` and ``unc_*_mm`` (NaN where invalid) and ``valid`` from the tracks (where invalid,
        the WIDIM vector stays, as WIDIM keeps a replaced one); the WIDIM vectors as ``piv_u_mm``,
        ``piv_v_mm``, ``piv_w_mm``, ``piv_valid`` (and ``piv_unc_*_mm``); ``n_tracks`` (tracks in the
        box), ``ptv_fit`` (1 + the order fitted: 3 quadratic, 2 linear, 1 mean; 0 invalid) and
        ``unc_model_u_mm``, ... (the model term inside ``unc_*_mm``; 0 where the pilot box has too
        few tracks or ``model_box`` is 0, NaN where invalid). Attrs
        of the WIDIM result (the errors stage reads ``final_window``, ``final_spacing``) plus
        ``particles = "ptv"``,
        ``ptv_window``, ``ptv_order``, ``ptv_model_box``, ``ptv_search``, ``ptv_tracks``.
    """
    dims = ("z", "y", "x")
    for need in ("u_mm", "v_mm", "w_mm", "valid"):
        if need not in piv_grid:
            raise ValueError(f"bin_tracks: the PIV grid has no {need!r} (a 3-D WIDIM result with coordinates in mm)")
    if order not in ORDERS:
        raise ValueError(f"order = {order!r}: the local polynomial's order is one of {list(ORDERS)}")
    if not (isinstance(model_box, (int, float)) and (model_box == 0 or 1 <= model_box <= MODEL_BOX_MAX)):
        raise ValueError(
            f"model_box = {model_box!r}: 0 (no model term) or the pilot box over the window, 1 to {MODEL_BOX_MAX}"
        )
    vox = _voxel(voxel, piv_grid)
    win = piv_grid.attrs.get("final_window") if window is None else window
    if win is None or len(win) != 3 or not all(float(w) > 0 for w in win):
        raise ValueError(f"window = {win!r}: three box sizes > 0 in voxels (z, y, x)")
    half = 0.5 * np.asarray(win, float)[::-1] * vox  # x, y, z [mm]
    zz, yy, xx = np.meshgrid(*(np.asarray(piv_grid[d].values, float) for d in dims), indexing="ij")
    centres = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    pos = positions(tracks)
    disp = np.column_stack([np.asarray(tracks[f"{c}_mm"].values, float) for c in _COMP]).reshape(-1, 3)
    m = len(centres)
    val = np.full((m, 3), np.nan)
    unc = np.full((m, 3), np.nan)
    count = np.zeros(m, np.int64)
    kind = np.zeros(m, np.int8)
    model = np.zeros((m, 3))
    wts = _weights(tracks, len(pos), weighted, vox)
    usable = np.all(wts > 0, axis=1)  # a track with an infinite sigma does not count
    pos, disp, wts = pos[usable], disp[usable], wts[usable]
    if len(pos):
        # the box is the unit ball of the max norm on positions scaled by the half window
        tree = cKDTree(pos / half)
        near = tree.query_ball_point(centres / half, r=1.0, p=np.inf)
        wide = tree.query_ball_point(centres / half, r=float(model_box), p=np.inf) if model_box else None
        for k, idx in enumerate(near):
            idx = np.sort(np.asarray(idx, int))
            count[k] = n = len(idx)
            for o in range(int(order), -1, -1):
                if n >= (max(4, FIT_PARAMETERS[o] + 2) if o else 2):
                    dx = (pos[idx] - centres[k]) / half
                    fit = _fit(dx, disp[idx], wts[idx], o)
                    if fit is not None:
                        val[k], unc[k] = fit[:2]
                        kind[k] = o + 1
                        if wide is not None:
                            pid = np.sort(np.asarray(wide[k], int))
                            pdx = (pos[pid] - centres[k]) / half
                            model[k] = _model_sd(dx, fit[2], pdx, disp[pid], wts[pid], o)
                        break
        unc = np.sqrt(unc * unc + model * model)
    shape = xx.shape
    valid = (kind > 0).reshape(shape)
    out = piv_grid.copy()
    for c in _COMP:
        out[f"piv_{c}_mm"] = piv_grid[f"{c}_mm"].transpose(*dims).copy()
        out[f"piv_{c}_mm"].attrs["long_name"] = f"WIDIM {piv_grid[f'{c}_mm'].attrs.get('long_name', c)}"
        if f"unc_{c}_mm" in piv_grid:
            out[f"piv_unc_{c}_mm"] = piv_grid[f"unc_{c}_mm"].transpose(*dims).copy()
    out["piv_valid"] = piv_grid["valid"].transpose(*dims).copy()
    for k, (c, ax) in enumerate(zip(_COMP, _XYZ)):
        old_mm = piv_grid[f"{c}_mm"].transpose(*dims).values.astype(float)
        step = _signed_step(piv_grid, ax, vox[k])
        mm_ = np.where(valid, val[:, k].reshape(shape), old_mm)
        sd = np.where(valid, unc[:, k].reshape(shape), np.nan)
        desc = f"{ax} displacement (PTV: local linear fit of the tracks in the window)"
        udesc = f"standard uncertainty of the {ax} displacement (PTV fit; NaN where invalid)"
        out[f"{c}_mm"] = (dims, mm_, {"units": "mm", "long_name": desc})
        out[c] = (dims, mm_ / step, {"units": "voxel", "long_name": desc})
        out[f"unc_{c}_mm"] = (dims, sd, {"units": "mm", "long_name": udesc})
        out[f"unc_{c}"] = (dims, sd / np.abs(step), {"units": "voxel", "long_name": udesc})
    for k, (c, ax) in enumerate(zip(_COMP, _XYZ)):
        out[f"unc_model_{c}_mm"] = (
            dims,
            np.where(valid, model[:, k].reshape(shape), np.nan),
            {"units": "mm", "long_name": f"model (curvature) term of the {ax} uncertainty (in unc_{c}_mm)"},
        )
    out["valid"] = (dims, valid, {"units": "1", "long_name": "enough tracks in the window (>= 2)"})
    out["n_tracks"] = (dims, count.reshape(shape), {"units": "1", "long_name": "tracks in the window box"})
    out["ptv_fit"] = (
        dims,
        kind.reshape(shape),
        {"units": "1", "long_name": "vector from: 3 quadratic fit, 2 linear fit, 1 mean of the tracks, 0 invalid"},
    )
    out.attrs.update(
        title="PTV result binned on the WIDIM grid",
        method="PTV: predictor-based mutual nearest-neighbour tracks (lfstudy.piv.ptv), local "
        f"order-{int(order)} least-squares fit per window; predictor " + str(piv_grid.attrs.get("method", "WIDIM")),
        particles="ptv",
        uncertainty="ptv_fit",
        ptv_window=[float(w) for w in win],
        ptv_order=int(order),
        ptv_model_box=float(model_box),
        ptv_weighted=int(bool(weighted) and bool(np.any(wts != 1.0))),
        ptv_search=float(tracks.attrs.get("search", math.nan)),
        ptv_tracks=len(pos),
        ptv_particles_a=int(tracks.attrs.get("n_a", -1)),
        ptv_particles_b=int(tracks.attrs.get("n_b", -1)),
    )
    return out


def _signed_step(piv: xr.Dataset, ax: str, default: float) -> np.ndarray:
    """The signed voxel step [mm] along ``ax`` at each window centre, broadcast on (z, y, x)
    (WIDIM's ``*_mm`` is the voxel displacement times it)."""
    shp = [1, 1, 1]
    shp[("z", "y", "x").index(ax)] = -1
    idx = f"{ax}_index"
    if idx in piv.coords and piv.sizes[ax] > 1:
        step = np.gradient(np.asarray(piv[ax].values, float)) / np.gradient(np.asarray(piv[idx].values, float))
    else:
        step = np.full(piv.sizes[ax], float(default))
    return step.reshape(shp)


def _neighbour_median(pos: np.ndarray, d: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The displacements ``d`` (n, 3) of each track's ``k`` nearest other tracks (positions ``pos`` (n, 3) in
    voxels per axis), (n, k, 3), and their median per component, (n, 3): the neighbourhood of the median test
    (:func:`validate_tracks`) and of the depth weights' scatter (:func:`depth_weights`)."""
    _, nb = cKDTree(pos).query(pos, k=k + 1)
    dn = d[nb[:, 1:]]  # the track itself is its own nearest
    return dn, np.median(dn, axis=1)


def validate_tracks(
    tracks: xr.Dataset,
    *,
    voxel: Sequence[float],
    neighbours: int = 8,
    eps: float = 0.1,
    threshold: float = 2.0,
) -> xr.Dataset:
    """Drop outlier tracks by the normalised median test on scattered vectors.

    Each track's displacement is compared with the median of its ``neighbours`` nearest tracks
    (distance in voxels per axis), per component, normalised by the neighbours' median absolute
    residual plus ``eps`` voxels: the universal outlier detection of Westerweel & Scarano (2005,
    Exp. Fluids 39 1096) on an unstructured set (Duncan, Dabiri, Hove & Gharib 2010, Meas. Sci.
    Technol. 21 057002). A track whose normalised residual exceeds ``threshold`` in any component
    (a false pair: a ghost or a missed partner's neighbour) is dropped.

    Parameters
    ----------
    tracks : xarray.Dataset
        :func:`match_particles`' result.
    voxel : (dx, dy, dz)
        Voxel size [mm]: the unit of the distances and of ``eps``.
    neighbours : int
        Tracks the median is taken over (>= 3).
    eps, threshold : float
        Noise level [voxel] and threshold of the test (Westerweel & Scarano's 0.1 and 2).

    Returns
    -------
    xarray.Dataset
        The kept tracks; attrs ``n_rejected`` (dropped by the test) added.
    """
    vox = np.asarray(voxel, float)
    if int(neighbours) < 3:
        raise ValueError(f"neighbours = {neighbours!r}: the median needs at least 3")
    n = tracks.sizes.get("track", 0)
    if n <= int(neighbours):
        return tracks.assign_attrs(n_rejected=0)
    pos = positions(tracks) / vox
    d = np.column_stack([np.asarray(tracks[f"{c}_mm"].values, float) for c in _COMP]) / vox
    dn, med = _neighbour_median(pos, d, int(neighbours))
    rm = np.median(np.abs(dn - med[:, None, :]), axis=1)
    bad = np.any(np.abs(d - med) / (rm + float(eps)) > float(threshold), axis=1)
    out = tracks.isel(track=np.flatnonzero(~bad))
    out.attrs.update(tracks.attrs, n_rejected=int(bad.sum()), n_tracks=int((~bad).sum()))
    return out


#: ``piv.paired_weights`` values: ``depth`` weighs each track by the inverse of the tracks' displacement variance at
#: its depth (:func:`depth_weights`), ``none`` weighs every track alike.
PAIRED_WEIGHTS = ("depth", "none")

#: :func:`depth_weights`: at most this many bands of equal track counts in |z|, and at least this many tracks a
#: band (fewer tracks, fewer bands; under two bands every weight is 1). 40 tracks give a band's robust standard
#: deviation within about 20 % (the MAD's efficiency, 37 % of the mean's, on a Gaussian).
DEPTH_BANDS = 6
TRACKS_PER_BAND = 40
#: :func:`depth_weights`: the tracks each track's residual is taken against (their median; as the median test's)
NEIGHBOURS = 8
_SCATTER_FLOOR = 1e-3  # depth_weights: the least scatter a band is taken to have [voxels per axis]


def depth_weights(
    tracks: xr.Dataset,
    *,
    voxel: Sequence[float],
    neighbours: int = NEIGHBOURS,
    bands: int = DEPTH_BANDS,
    per_band: int = TRACKS_PER_BAND,
) -> tuple[np.ndarray, dict[str, list[float]]]:
    """Weights of the tracks by how well their depth is known: the inverse of the tracks' own displacement
    variance at their distance from the focal plane, relative to the best band's.

    A plenoptic camera reads a particle's depth from the spread of its image over the lenslets. Near the
    focal plane the image falls behind one to four lenslets and hardly changes with depth (the Cramér–Rao
    bound there is 0.4-1.8 z voxels on the demo designs, :mod:`lfstudy.reconstruct.ipr.bound`), so a fitted
    particle's depth errs there several times more than away from it, in each frame independently: on the demo
    the tracks' w scatters 2.5-4.7× more in the band nearest focus than elsewhere. The fit's own ``sigma_z`` (its
    covariance at the minimum it found) does not see this, since the error is the choice of minimum, not its
    width. The variance is measured on the tracks themselves, without the truth: each track's displacement less
    the median of its ``neighbours`` nearest tracks' (distance in voxels per axis: the residual of
    :func:`validate_tracks`' median test), its robust variance (1.4826 · MAD, squared, summed over u, v, w [mm²])
    per band of |z|, interpolated linearly between the bands' median |z|. The flow's own variation over the
    neighbours enters too: alike in every band where the flow's gradient is the same, more at the volume's edges
    (the far bands on a volume centred on the focal plane), where the neighbours lie to one side. A least-squares
    plane through 16 neighbours instead of their median (no gradient term; the residual scaled by the prediction's
    leverage) was tried: on the demo's IPR lists it gained no more (total RMS of the 16 cases of two seeds: median
    change -8.8 % against -9.1 %, mean -7.8 % against -8.8 %; docs/config.md, benchmarks/bench_paired_weights.py).

    Parameters
    ----------
    tracks : xarray.Dataset
        :func:`match_particles`' (or :func:`validate_tracks`') result: positions ``x``, ``y``, ``z`` [mm] (the
        midpoints; z from the focal plane) and displacements ``u_mm``, ``v_mm``, ``w_mm``.
    voxel : (dx, dy, dz)
        Voxel size [mm]: the unit of the neighbours' distances.
    neighbours : int
        Tracks each residual's median is taken over (>= 3).
    bands, per_band : int
        At most ``bands`` bands of |z| with equal counts, each of at least ``per_band`` tracks.

    Returns
    -------
    weights : ndarray (n,)
        In (0, 1]: the best band's variance over the track's (1 everywhere with fewer than two bands).
    info : dict
        ``depth_mm`` (the bands' median |z|) and ``sd_mm`` (their robust standard deviation of the displacement,
        the three components' in quadrature); empty lists with fewer than two bands.

    Notes
    -----
    Inverse-variance weights are the least-squares optimum for a mean of independent estimates (e.g. Bevington &
    Robinson 2003, *Data Reduction and Error Analysis*, ch. 4). A correlation's peak weighs each pair by the
    product of its two images' intensities, so the paired PIV scales each particle's intensity by the square root
    of its track's weight (:func:`lfstudy.study.case.case_paired_piv`).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> n = 600
    >>> xyz = rng.uniform([0, 0, -2], [4, 4, 2], (n, 3))
    >>> sd = np.where(np.abs(xyz[:, 2]) < 0.5, 0.04, 0.01)  # depth read 4x worse near focus
    >>> d = rng.normal(0.0, 1.0, (n, 3)) * np.column_stack([np.full(n, 0.002), np.full(n, 0.002), sd])
    >>> tr = xr.Dataset({k: ("track", v) for k, v in zip(("x", "y", "z", "u_mm", "v_mm", "w_mm"), [*xyz.T, *d.T])})
    >>> w, info = depth_weights(tr, voxel=(0.1, 0.1, 0.25))
    >>> bool(np.median(w[np.abs(xyz[:, 2]) < 0.3]) < 0.2 < 0.8 < np.median(w[np.abs(xyz[:, 2]) > 1.0]))
    True
    """
    vox = np.asarray(voxel, float)
    n = tracks.sizes.get("track", 0)
    scatter = _band_scatter(tracks, vox, neighbours, bands, per_band)
    if scatter is None:
        return np.ones(n), {"depth_mm": [], "sd_mm": []}
    depth, mid, var3 = scatter
    var = var3.sum(axis=1)  # u, v, w summed
    # a scatter below a thousandth of a voxel is no PIV's: a band of tracks that agree with their neighbours (a
    # noise-free field) weighs as the best, not infinitely more
    var = np.maximum(var, np.sum((_SCATTER_FLOOR * vox) ** 2))
    weights = np.min(var) / np.interp(depth, mid, var)
    return weights, {"depth_mm": mid.tolist(), "sd_mm": np.sqrt(var).tolist()}


def _band_scatter(
    tracks: xr.Dataset, vox: np.ndarray, neighbours: int, bands: int, per_band: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The tracks' displacement scatter per band of |z| (:func:`depth_weights`): each track's |z| [mm] (n,), the
    bands' median |z| (nb,) and their robust variance per component u, v, w [mm²] (nb, 3), 1.4826 · MAD of each
    track's displacement less its ``neighbours`` nearest tracks' median, squared; None under two bands of
    ``per_band`` tracks."""
    n = tracks.sizes.get("track", 0)
    nb_bands = min(int(bands), n // max(int(per_band), 1))
    if int(neighbours) < 3:
        raise ValueError(f"neighbours = {neighbours!r}: the median needs at least 3")
    if nb_bands < 2 or n <= int(neighbours):
        return None
    pos = positions(tracks)
    d = np.column_stack([np.asarray(tracks[f"{c}_mm"].values, float) for c in _COMP])
    r = d - _neighbour_median(pos / vox, d, int(neighbours))[1]
    depth = np.abs(pos[:, 2])
    band = np.minimum(np.argsort(np.argsort(depth, kind="stable"), kind="stable") * nb_bands // n, nb_bands - 1)
    var = np.zeros((nb_bands, 3))
    mid = np.zeros(nb_bands)
    for k in range(nb_bands):
        rk = r[band == k]
        var[k] = (1.4826 * np.median(np.abs(rk - np.median(rk, axis=0)), axis=0)) ** 2
        mid[k] = np.median(depth[band == k])
    return depth, mid, var


#: ``piv.paired_uncertainty`` values: ``tracks`` takes each paired vector's σ per component as the larger of the
#: correlation's and the tracks' own (:func:`track_sigma`); ``correlation`` the correlation's alone.
PAIRED_UNCERTAINTY = ("tracks", "correlation")


def track_sigma(
    tracks: xr.Dataset,
    grid: xr.Dataset,
    window_mm: Sequence[float],
    *,
    voxel: Sequence[float],
    weights: np.ndarray | None = None,
    neighbours: int = NEIGHBOURS,
    bands: int = DEPTH_BANDS,
    per_band: int = TRACKS_PER_BAND,
) -> np.ndarray:
    """Per vector, the standard deviation of the weighted mean of the tracks inside its final window, from the
    tracks' own scatter at their depth: what the paired particles' misplacement alone leaves in the vector.

    A paired vector is the correlation of the tracks inside its window, so it errs at least by their mean error.
    Near the focal plane a fitted particle's depth errs several times more than away from it
    (:func:`depth_weights`), and there the window holds few tracks; the correlation's σ, read from the
    correlation plane, sees little of it (held-out coarse demo designs: σ of w covered 0.37-0.54 of the errors, its
    RMS 0.93-1.60 times too small; the larger of the two σ 0.58-0.76 and 0.56-1.10, docs/config.md). Each
    track's variance per component is its band's robust variance
    (:func:`depth_weights`' bands, interpolated at the track's |z|, each component's own), and the window's
    estimate is their weighted mean: ``var_c = Σ w_t² v_c(|z_t|) / (Σ w_t)²`` over the tracks inside the window
    (``w_t`` the correlation's weights, 1 without). No truth is used, so recordings too.

    Parameters
    ----------
    tracks : xarray.Dataset
        :func:`validate_tracks`' result: positions ``x``, ``y``, ``z`` [mm] and ``u_mm``, ``v_mm``, ``w_mm``.
    grid : xarray.Dataset
        The PIV result whose vectors get a σ: coordinates ``z``, ``y``, ``x`` [mm] (dims in that order).
    window_mm : (wx, wy, wz)
        The final window's size [mm]: a track is inside a vector's window within half of it per axis.
    voxel : (dx, dy, dz)
        Voxel size [mm]: the neighbours' distances (:func:`depth_weights`).
    weights : ndarray (n,), optional
        The tracks' weights in the correlation (:func:`depth_weights`); default 1.
    neighbours, bands, per_band : int
        As :func:`depth_weights`.

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        σ of u, v, w [mm]; NaN where the window holds no track, and everywhere under two bands of tracks.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> n = 4000
    >>> xyz = rng.uniform([0, 0, -2], [4, 4, 2], (n, 3))
    >>> sd = np.where(np.abs(xyz[:, 2]) < 0.5, 0.04, 0.01)  # depth read 4x worse near focus
    >>> d = rng.normal(0.0, 1.0, (n, 3)) * np.column_stack([np.full(n, 0.002), np.full(n, 0.002), sd])
    >>> tr = xr.Dataset({k: ("track", v) for k, v in zip(("x", "y", "z", "u_mm", "v_mm", "w_mm"), [*xyz.T, *d.T])})
    >>> grid = xr.Dataset(coords={"z": [-1.5, 0.0, 1.5], "y": [2.0], "x": [2.0]})
    >>> s = track_sigma(tr, grid, (1.0, 1.0, 1.0), voxel=(0.1, 0.1, 0.25))
    >>> s.shape, bool(s[2, 1, 0, 0] > 2 * max(s[2, 0, 0, 0], s[2, 2, 0, 0]))
    ((3, 3, 1, 1), True)
    """
    vox = np.asarray(voxel, float)
    shape = tuple(grid.sizes[d] for d in ("z", "y", "x"))
    out = np.full((3, *shape), np.nan)
    scatter = _band_scatter(tracks, vox, neighbours, bands, per_band)
    if scatter is None:
        return out
    depth, mid, var3 = scatter
    floor = (_SCATTER_FLOOR * vox) ** 2
    v = np.column_stack([np.maximum(np.interp(depth, mid, var3[:, c]), floor[c]) for c in range(3)])
    w = np.ones(len(depth)) if weights is None else np.asarray(weights, float)
    half = np.asarray(window_mm, float) / 2.0
    # a track is inside a window where it is within half the window per axis: a unit ball of the max-norm
    tree = cKDTree(positions(tracks) / half)
    zz, yy, xx = np.meshgrid(*(np.asarray(grid[d].values, float) for d in ("z", "y", "x")), indexing="ij")
    centres = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]) / half
    flat = out.reshape(3, -1)
    for i, inside in enumerate(tree.query_ball_point(centres, r=1.0, p=np.inf)):
        if inside:
            wi = w[inside]
            flat[:, i] = np.sqrt((wi**2) @ v[inside] / wi.sum() ** 2)
    return out
