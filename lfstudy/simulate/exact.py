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
``_PANEL`` blur widths long, with enough nodes that a blurred edge anywhere
on a panel, however short, is integrated to 1e-10 of a blur width. Only where
the arc passes within 4.5σs of a *corner* of the blurred square (both bands at
once) is an antiderivative of a product of two blurred edges needed; it is
then integrated numerically with Gauss–Legendre panels of the same size.

Error budget: Gaussian tails beyond ``_K = 6`` σ are dropped (each ≤ 1e-9 of
the local value) and the bands of the blurred square end at ``_KS = 4.5`` σs;
Φ is evaluated with a Chebyshev fit of erfcx (relative error ≤ 2e-14); the
tests find every pixel within 1e-7 of the peak pixel of an independent
brute-force quadrature, and an in-focus image uniform to 1e-7. The total of
every particle equals ``W`` minus what misses the lenslet array or the
sensor, to ~1e-9.

Lenslet grids rotated against the sensor break the separability. In focus
(``M_k`` constant, which includes the calibration pinhole image) they are
handled exactly. Out of focus, a grid rotated by θ (up to ``_ROT_APPROX`` =
5 mrad; beyond, those particles are refused: use the Monte-Carlo tracer) is
cut into n x n sub-squares per lenslet, n = ceil(θ / 1 mrad): ``M_k`` is
the sum of its sub-squares' windows (the blurred membership is additive over
a tiling), and each sub-square is taken in the sensor-aligned frame through
its centre, where the map from the sensor to the lenslet plane is exact; its
edges then turn by θ about that centre, i.e. move by at most θ·pl/(√2·n) in
the lenslet plane. Against the mean of 8 Monte-Carlo images of 400,000 rays
per particle, the per-pixel z-test gives mean z² 0.92–1.14 at 1, 2 and 5 mrad
(the same Monte-Carlo images: 0.94–1.08 with n = ceil(θ / 0.5 mrad), 1.4–8.6
with undivided lenslets at 2–10 mrad): a residue of ~0.25 of the Monte-Carlo's
standard error at 3.2 million rays, ~0.02 at a study's 25,000. Cost on the
Table 4.3 optics (1000 x 800 px, 0.01 ppp): x1.0 at 1 mrad, x2.3 at 2 mrad,
x9.4 at 5 mrad of the unrotated render.

Camera imperfections
--------------------
:mod:`lfstudy.simulate.imperfections` (the config's ``camera.imperfections``)
enters as: the imaging camera's grid (rotation, offset, pitch); a gap g between
the lenslets and the sensor other than fl (the disc is then centred at
``(g/fl)·c_k + (g + (1 − g/fl)·si)·t0`` with radius ``R·|g·c1 + (1 − g/fl)·(1 + si·c1)|``,
and κ follows); per-lenslet centre offsets (each lenslet's disc on its own:
``_G_SCAT``, the per-lenslet path of the rotated grid); a sensor tilt (per
particle, the lenslet plane at its chief ray's point and a slope offset on the
sensor side, :func:`_particle`); the main-lens distortion moves the particles
before the kernel (their solid angle stays the true one). Their ideal values
take exactly the arithmetic of the ideal model (bit-identical images).

Data layout
-----------
The numba kernels address small flat float64 arrays by named index constants; this table
is their one description (the camera's geometry vector ``_G_*`` is described in
:mod:`lfstudy.simulate._render_common`, which the Monte-Carlo tracer reads too). Lengths
in sensor mm unless noted; "lenslet units" are lenslet-plane mm in the grid frame.

Axis descriptor ``ax``/``ay`` (``_A_*``, one row per lenslet column / row: for an
unrotated grid every lenslet of a column shares its x-descriptor, every lenslet of a row
its y-descriptor):

==========  ==  ============================================================  =============
name        #   meaning                                                       units
==========  ==  ============================================================  =============
_A_C        0   centre of the aperture image (disc) on the sensor             mm
_A_G0       1   spot centre on the lenslet plane                              lenslet units
_A_E1       2   lenslet's lower edge                                          lenslet units
_A_E2       3   lenslet's upper edge                                          lenslet units
_A_A1       4   lower edge active (cuts the spot's reach): 1, else 0          flag
_A_A2       5   upper edge active                                             flag
_A_LO       6   lower edge of the lenslet window seen on the sensor (−inf)    mm
_A_HI       7   upper edge of that window (+inf if inactive)                  mm
_A_B        8   half-width of the σs-bands about LO and HI (K_S·σs)           mm
_A_MRG      9   the two bands overlap and are merged into one: 1, else 0      flag
_A_ELO      10  lenslet edge (E1 or E2) that maps to LO                       lenslet units
_A_EHI      11  lenslet edge that maps to HI                                  lenslet units
_A_SLO      12  sign of κ (−1: the window's image is flipped)                 1
_A_E0       13  first pixel-cell edge of the patch                            mm
_A_N        14  number of pixel cells in the patch (0: nothing reached)       count
_A_T0       15  sensor cell index of the patch's first cell                   count
==========  ==  ============================================================  =============

Shared scalars ``sc`` of one particle's lenslet images (``_S_*``):

==========  ==  ============================================================  =============
_S_KAP      0   κ = (1 + si·c1)/(fl·c1): lenslet-plane shift per sensor mm    1
_S_SM       1   σm, lenslet-plane blur                                        mm
_S_SL       2   σl, sensor-plane blur                                         mm
_S_PP       3   pixel pitch                                                   mm
_S_KSL      4   K·σl, the support of a blurred pixel edge                     mm
_S_AK       5   abs(κ)                                                        1
_S_S        6   S = sqrt(σm² + κ²σl²)                                         mm
_S_RHO      7   ρ, radius of the aperture image behind a lenslet              mm
_S_NGB      8   arc nodes per panel of L blur widths: ceil(NGB + DENS·L) ..   count
_S_DENS     9   .. (``_NG_BASE``, ``_DENS``)                                  1/σ
_S_NGMIN    10  .. but at least NGMIN (``_NG_MIN``)                           count
_S_PANEL    11  longest panel (``_PANEL``)                                    σ
_S_NGN      12  nodes per panel of the numeric band integrals (``_NGN``)      count
_S_K        13  Gaussian cut-off (``_K``)                                     σ
_S_KS       14  half-width of the σs-bands (``_KS``)                          σs
==========  ==  ============================================================  =============

Slots 8–14 are the quadrature, set once per scratch (:func:`_scratch`): :data:`_QUAD_EXACT` (the
constants above, the error budget below) for :func:`render_exact`; IPR's per-particle images may
take a coarser one (:func:`lfstudy.reconstruct.ipr.particle_patches`, ``accuracy="fast"``).

Kernel counters ``stats[chunk]`` (``_ST_*``): 0 ``_ST_W`` expected intensity traced,
1 ``_ST_IN`` recorded on the sensor, 2 ``_ST_ALL`` on the lenslet array, 3 ``_ST_SPILL``
outside the chunk's rows (a bug if not 0), 4 ``_ST_REFUSED`` lenslet images refused
(rotated grid out of focus), 5 ``_ST_LENS`` lenslet images, 6 ``_ST_INTERIOR`` interior
(separable) ones, 7 ``_ST_NODES`` arc nodes, 8 ``_ST_BAND`` nodes inside a band,
9 ``_ST_BIG`` patches larger than the scratch (a bug if not 0).

Zones of a coordinate along one axis (``_zone``): 0 ``_LOW`` below the blurred window,
1 ``_BLO`` in the lower (or merged) band, 2 ``_MID`` the flat middle, 3 ``_BHI`` the upper
band, 4 ``_HIGH`` above.

Patch scratch (:func:`_workspace`, per chunk): ``direct``, ``carry_x``, ``carry_y``
(pixel cells y × x of the patch; the carries hold the cells wholly below a node, summed
once per patch); ``pcs`` and ``brk`` (rows: angle, cos, sin of the arc pieces and of their
panel breaks); ``wk`` (per cell: row 0 the node's U_k, row 1 the secondary edges' Φ, row 2
U_p(v) of a cut, rows 3–5 the band antiderivative carried along a piece: value, abscissa,
valid); ``nodv[batch, row, node]`` (rows: primary coordinate, secondary coordinate,
weight, and the two cell indices of the vectorised pass; batches 0 = x-antiderivative,
1 = with the y-window, 2 = y-antiderivative, 3 = near a corner), ``ncnt[batch]`` nodes
queued, ``vb`` (rows: argument, Φ, φ of the vectorised batch).

Tuples the kernel's steps pass (each unpacked by name where it is used): ``work``, the patch
scratch above in that order; ``spot`` (:func:`_particle`): g0x, g0y, t0x, t0y, rs, reach,
focus, bh; ``cur`` (``curx``/``cury``, :func:`_axis_current`): one axis of the current lenslet,
its descriptor ``ax``, Λ(lo) table ``lam``, full table ``full`` (per pixel cell of the patch)
and circle crossings ``ang`` (rows: angle, cos, sin); ``store`` (``cols``/``rows``,
:func:`_axis_store`): the same four per lenslet column/row the particle reaches, plus the
crossings' count ``nang`` and the window factor ``fac``; ``chunk``: (buf, r0, r1), the
chunk's image rows r0..r1 as a flat slice of the image. The patch steps call the axis of
their antiderivative ``pri`` and the other ``sec``; ``swap`` is true when ``pri`` is y (the
patch is then indexed [k, j] and its carry is carry_y).

Determinism and memory
----------------------
Particles are sorted by the sensor row of their image and cut into a fixed
number of chunks (``n_chunks``); each chunk reaches only a band of rows. The
chunks are grouped into *waves* whose row bands do not overlap (greedily, in
chunk order: a property of the layout, not of the threads); the chunks of one
wave run in parallel and add straight into the float64 image, the waves one
after the other. Every pixel therefore receives its contributions in one
fixed order: the result depends on ``n_chunks``, never on the number of
threads, and the memory is one image plus the particle arrays.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
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
    _check_rays,
    _geometry,
    _particle_arrays,
    _sensor_coords,
    ray_counts,
    solid_angle,
)
from lfstudy.simulate.imperfections import CameraImperfections, resolve

__all__ = ["render_exact", "render_pinhole_exact", "exact_memory_estimate"]

# The kernel's helpers allocate nothing, so they are compiled without the runtime's reference
# counting (numba's ``_nrt=False``): with it every call passing arrays made two atomic updates per
# array argument, a third of the kernel's time (perf, Table 4.3 camera); the result is bit-identical.
_helper = njit(cache=True, _nrt=False)


# The constants passed to the helpers go through these two, so that each helper is compiled once: numba
# compiles a function once per literal argument (``_nodes`` with swap ``True`` and with ``False``, zone 2 and an int),
# and on a fresh clone each copy costs its compile, and again in every kernel that links it.
@_helper
def _flag(v):  # pragma: no cover - jitted
    """``v`` as a run-time ``bool`` (a comparison's result is never a literal)."""
    return v != 0


@_helper
def _index(v):  # pragma: no cover - jitted
    """``v`` as a run-time integer."""
    return v + 0


_PIECES = 16  # kernel calls per render (progress granularity; does not change the result)
_K = 6.0  # Gaussian support cut-off in σ (tails beyond: Φ(−6) ≈ 1e-9)
_KS = 4.5  # half-width of the σs-bands of the blurred square, in σs (dropped tail ∫ ≤ 8e-7·σs per unit length)
_NG_MAX = 16  # most Gauss–Legendre nodes on one arc panel
# Nodes on an arc panel that travels L blur widths: ceil(_NG_BASE + _DENS·L), at least _NG_MIN. A
# blurred edge anywhere in the panel is then integrated to ≤ 1e-10·σ (Gauss–Legendre on ∫Φ: L = 2,
# 7 nodes: 4e-10; L = 4, 10: 5e-11; L = 8, 16: 8e-11). Proportional rules fail on short panels
# (2 nodes per σ: L = 2 with 4 nodes errs by 3e-6·σ), and arcs break into many short panels.
_NG_BASE = 4.0
_DENS = 1.5
_NG_MIN = 4
_NGN = 16  # Gauss–Legendre nodes per ≤ _PANEL σ panel of the numeric (corner) antiderivatives (8e-11·σ)
_PANEL = 8.0  # longest panel, in units of the narrowest blur active on it
#: The quadrature settings the kernels read from the scalars ``sc`` (``_S_NGB`` ..): the exact
#: renderer's (:func:`render_exact`, every image of the study) are the constants above; a coarser
#: set is an option of :func:`lfstudy.reconstruct.ipr.particle_patches` only (``_QUAD`` there).
_QUAD_EXACT = np.array([_NG_BASE, _DENS, _NG_MIN, _PANEL, _NGN, _K, _KS])
#: Largest |sin θ| of a rotated lenslet grid rendered out of focus (in sub-squares, see
#: :func:`_lenslet_axes`); beyond it those particles are refused (use the Monte-Carlo tracer).
_ROT_APPROX = 0.005
_ROT_STEP = 1e-3  # out of focus a grid rotated by θ is cut into ceil(θ/_ROT_STEP)² sub-squares per lenslet
_PINHOLE_NODES = 3  # Gauss–Legendre nodes per axis and lenslet of the pinhole image (error: see the tests)
_EPS_FOCUS = 1e-9  # spot radius / σm (/ lenslet pitch without σm) below which M_k is a constant over the aperture image
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi

_GL_X = np.zeros((_NG_MAX + 1, _NG_MAX))  # row n: the n-point rule on [−1, 1]
_GL_W = np.zeros((_NG_MAX + 1, _NG_MAX))
for _n in range(1, _NG_MAX + 1):
    _GL_X[_n, :_n], _GL_W[_n, :_n] = np.polynomial.legendre.leggauss(_n)
_G4_X, _G4_W = np.polynomial.legendre.leggauss(4)

# ------------------------------------------------------------------ Φ, φ and IΦ
# erfcx(x) = exp(x²)·erfc(x) on 0 <= x <= 6.1, in 16 equal pieces, each a degree-9
# polynomial in the local variable s ∈ [−1, 1] (our own Chebyshev least-squares fits
# to scipy.special.erfcx at 400 points per piece, converted to powers of s; relative
# error <= 6.3e-13). Φ and φ then cost one exp and ten fused multiply-adds together.
_ERFCX = np.array(
    [
        [
            0.8166215832960032,
            -0.15574866717615213,
            0.02401472772075978,
            -0.0031912889847528166,
            0.00037834009754102047,
            -4.088667507292017e-05,
            4.0869501192910405e-06,
            -3.8201116151961225e-07,
            3.422718357591059e-08,
            -2.8607913606036572e-09,
        ],
        [
            0.5806179828075421,
            -0.08850668220262407,
            0.011449994337367006,
            -0.001311960140194048,
            0.0001365235602055608,
            -1.3116377158292236e-05,
            1.1769388210077622e-06,
            -9.950789640063723e-08,
            8.093224211440314e-09,
            -6.189796853126485e-10,
        ],
        [
            0.4407379300447179,
            -0.054942411765057986,
            0.0060330299482966926,
            -0.0006002356246718346,
            5.508555797019722e-05,
            -4.7211339969354484e-06,
            3.8128192391269597e-07,
            -2.9220220021577632e-08,
            2.162007267015823e-09,
            -1.5150902357451324e-10,
        ],
        [
            0.35093477636299053,
            -0.03656606544776593,
            0.003451093711943814,
            -0.00030059695054973715,
            2.4472028040838493e-05,
            -1.8792907734179744e-06,
            1.3707291648550643e-07,
            -9.548565520725714e-09,
            6.444651748872102e-10,
            -4.146224800454097e-11,
        ],
        [
            0.289541355243118,
            -0.025713480959287008,
            0.002111959169988934,
            -0.00016245092449224645,
            1.1808013557421124e-05,
            -8.165677943130168e-07,
            5.400747208313815e-08,
            -3.4310836092390917e-09,
            2.1190294401627636e-10,
            -1.254660883734205e-11,
        ],
        [
            0.24542848611207638,
            -0.018893502066383423,
            0.0013663033568521458,
            -9.361040682742435e-05,
            6.115465159486408e-06,
            -3.8286026591977427e-07,
            2.306198849565161e-08,
            -1.3410877535890232e-09,
            7.604648618087344e-11,
            -4.149126331317745e-12,
        ],
        [
            0.21244472981868764,
            -0.014382651471344524,
            0.0009255355471801622,
            -5.694606185425518e-05,
            3.365556312985505e-06,
            -1.9177438810378206e-07,
            1.0567976907825544e-08,
            -5.646736727720351e-10,
            2.950316776523839e-11,
            -1.4879766230946139e-12,
        ],
        [
            0.18697432358696114,
            -0.011269703121991699,
            0.0006514939288363198,
            -3.627234165968315e-05,
            1.9515047067667992e-06,
            -1.0174276668343012e-07,
            5.152206464512275e-09,
            -2.539424914664886e-10,
            1.2269456116535188e-11,
            -5.715764586592416e-13,
        ],
        [
            0.16677898272776598,
            -0.009043800008631225,
            0.00047364196859281415,
            -2.4028709797751602e-05,
            1.183777692524992e-06,
            -5.675235536190217e-08,
            2.6524905698088676e-09,
            -1.2106027547649486e-10,
            5.428563274049979e-12,
            -2.329075153211512e-13,
        ],
        [
            0.15041100081168682,
            -0.007403775868491429,
            0.0003539041395873235,
            -1.646341954464171e-05,
            7.46728544632208e-07,
            -3.307586777145079e-08,
            1.432755827584797e-09,
            -6.077560991846914e-11,
            2.5378974502164544e-12,
            -1.0079993584749838e-13,
        ],
        [
            0.1368983320218658,
            -0.0061642208658514806,
            0.0002707061599103279,
            -1.1613384116941029e-05,
            4.87383659278192e-07,
            -2.0034199579181336e-08,
            8.074861006678684e-10,
            -3.195041592735275e-11,
            1.2477838787651698e-12,
            -4.448071935451136e-14,
        ],
        [
            0.12556701278675853,
            -0.005206621396934612,
            0.00021129468325833763,
            -8.402378520360043e-06,
            3.277673622872547e-07,
            -1.2554437781518322e-08,
            4.725743257797096e-10,
            -1.7497911106725916e-11,
            6.402837046512435e-13,
            -2.1777182401943964e-14,
        ],
        [
            0.11593660039124827,
            -0.004452703505006655,
            0.000167845180689181,
            -6.215571670342212e-06,
            2.2631036604989447e-07,
            -8.107890414676337e-09,
            2.860138594663959e-10,
            -9.944388624324469e-12,
            3.4243716523893135e-13,
            -9.687470470078894e-15,
        ],
        [
            0.10765622815818596,
            -0.003849265556323026,
            0.00013539709306136812,
            -4.688654860084241e-06,
            1.59948709317977e-07,
            -5.3785837641296645e-09,
            1.7837986852906982e-10,
            -5.840441703505346e-12,
            1.8976137455652108e-13,
            -4.6160718285303e-15,
        ],
        [
            0.10046417395808149,
            -0.0033592211564373096,
            0.00011071284695338063,
            -3.5986283932130315e-06,
            1.1542047023104529e-07,
            -3.6546436100186644e-09,
            1.1429152053202387e-10,
            -3.531905322268992e-12,
            1.0852479074422255e-13,
            -3.0773812190201998e-15,
        ],
        [
            0.09416153067349717,
            -0.002956131760422585,
            9.162403261290102e-05,
            -2.8049641580090192e-06,
            8.485158664200853e-08,
            -2.5373274963502202e-09,
            7.502899561348573e-11,
            -2.1974601902467703e-12,
            6.427958525851376e-14,
            -5.024295867788081e-16,
        ],
    ]
)
_NPIECE = _ERFCX.shape[0]
_XMAX = 6.1
_PIECE_SCALE = _NPIECE / _XMAX
_PIECE_S = 2.0 * _NPIECE / _XMAX
_UMAX = 8.6  # |u| beyond which Φ(u) is 0 or 1 to double precision (Φ(−8.6) < 4e-18)
_T0 = 2.0 / (2.0 + _XMAX)
_TS = 2.0 / (1.0 - _T0)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@njit(inline="always", fastmath={"contract"}, cache=True)
def _phi2(u):  # pragma: no cover - jitted
    """(Φ(u), φ(u)): the standard normal CDF and density, one exp for both."""
    a = abs(u)
    if a > _UMAX:
        return (0.0 if u < 0.0 else 1.0), 0.0
    x = a * _INV_SQRT2
    i = min(int(x * _PIECE_SCALE), _NPIECE - 1)
    s = x * _PIECE_S - (2 * i + 1)
    p = _ERFCX[i, 9]
    for k in range(8, -1, -1):  # Horner
        p = p * s + _ERFCX[i, k]
    e = math.exp(-0.5 * u * u)
    q = 0.5 * p * e  # Φ(−|u|)
    return (q if u < 0.0 else 1.0 - q), e * _INV_SQRT_2PI


# A branch-free Φ, φ over a batch (vectorised by LLVM): erfcx as one degree-18 polynomial in
# s = 2(t − t0)/(1 − t0) − 1, t = 2/(2 + x), x = |u|/√2 ≤ 6.1 (our own Chebyshev fit, converted
# to powers of s; Σ|coefficients| ≈ 1, absolute error of Φ <= 1e-14), and exp(−u²/2) as the
# 128th power of a degree-12 Taylor polynomial of exp(−u²/256) (relative error <= 3e-15).
@njit(fastmath={"contract"}, error_model="numpy", cache=True, _nrt=False)
def _phi_batch(vb, n):  # pragma: no cover - jitted
    """vb[1, i], vb[2, i] = Φ(vb[0, i]), φ(vb[0, i]) for i < n."""
    for i in range(n):
        u = vb[0, i]
        a = min(abs(u), _UMAX)
        s = (2.0 / (2.0 + a * _INV_SQRT2) - _T0) * _TS - 1.0
        p = -3.2278759080215116e-10
        p = p * s + 2.0434536998361989e-10
        p = p * s + 3.5785627184047373e-09
        p = p * s + -9.002949071732024e-09
        p = p * s + -6.335306386820771e-09
        p = p * s + 9.26194680909058e-08
        p = p * s + -2.1335892436130062e-07
        p = p * s + -2.8567916349902097e-07
        p = p * s + 2.9702600707255887e-06
        p = p * s + -4.5531405417459905e-06
        p = p * s + -2.3292649810330988e-05
        p = p * s + 0.00010424053185032998
        p = p * s + 0.00013393724273611757
        p = p * s + -0.0017032445269307742
        p = p * s + -0.0016630397645887478
        p = p * s + 0.03342998315456114
        p = p * s + 0.17039390543599714
        p = p * s + 0.42252662565501775
        p = p * s + 0.37680288609839263
        z = a * a * (0.5 / 128.0)
        e = 1.0 - z * (
            1.0
            - z
            * (
                0.5
                - z
                * (
                    1.0 / 6
                    - z
                    * (
                        1.0 / 24
                        - z
                        * (
                            1.0 / 120
                            - z
                            * (
                                1.0 / 720
                                - z
                                * (
                                    1.0 / 5040
                                    - z
                                    * (
                                        1.0 / 40320
                                        - z
                                        * (1.0 / 362880 - z * (1.0 / 3628800 - z * (1.0 / 39916800 - z / 479001600.0)))
                                    )
                                )
                            )
                        )
                    )
                )
            )
        )
        e = e * e
        e = e * e
        e = e * e
        e = e * e
        e = e * e
        e = e * e
        e = e * e
        q = 0.5 * p * e
        vb[1, i] = q if u < 0.0 else 1.0 - q
        vb[2, i] = e * _INV_SQRT_2PI


@njit(inline="always", cache=True)
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


@njit(inline="always", cache=True)
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


@_helper
def _mean_phi(mid, half):  # pragma: no cover - jitted
    """The mean of Φ over [mid − half, mid + half] for half < 0.125 (4-point Gauss–Legendre, error < 1e-15)."""
    acc = 0.0
    for i in range(4):
        acc += _G4_W[i] * _phi2(mid + half * _G4_X[i])[0]
    return 0.5 * acc


@njit(inline="always", cache=True)
def _window(u, e1, e2, a1, a2, sm):  # pragma: no cover - jitted
    """P(u + σm·Z ∈ [e1, e2]): the lenslet-plane membership along one grid axis (inactive edges: no cut)."""
    hi = _cdf(e2 - u, sm) if a2 else 1.0
    lo = _cdf(e1 - u, sm) if a1 else 0.0
    return hi - lo


# ------------------------------------------------------------- one blurred axis
# The flat-array layouts: see "Data layout" in the module docstring (the one description).
_A_C, _A_G0, _A_E1, _A_E2, _A_A1, _A_A2 = range(6)
_A_LO, _A_HI, _A_B, _A_MRG = range(6, 10)
_A_ELO, _A_EHI, _A_SLO = range(10, 13)
_A_E0, _A_N, _A_T0 = range(13, 16)
_A_SIZE = 16
_S_KAP, _S_SM, _S_SL, _S_PP, _S_KSL, _S_AK, _S_S, _S_RHO = range(8)
_S_NGB, _S_DENS, _S_NGMIN, _S_PANEL, _S_NGN, _S_K, _S_KS = range(8, 15)  # the quadrature (_QUAD_EXACT's order)
_S_SIZE = 15
_ST_W, _ST_IN, _ST_ALL, _ST_SPILL, _ST_REFUSED, _ST_LENS, _ST_INTERIOR, _ST_NODES, _ST_BAND, _ST_BIG = range(10)
_ST_SIZE = 10
_LOW, _BLO, _MID, _BHI, _HIGH = range(5)


@njit(inline="always", cache=True)
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


@njit(inline="always", cache=True)
def _m(ax, sc, v):  # pragma: no cover - jitted
    """The lenslet window along this axis at sensor coordinate v (computed in lenslet units)."""
    u = ax[_A_G0] + sc[_S_KAP] * (v - ax[_A_C])
    return _window(u, ax[_A_E1], ax[_A_E2], ax[_A_A1] != 0.0, ax[_A_A2] != 0.0, sc[_S_SM])


@_helper
def _setup_axis(ax, sc, c, g0, e1, e2, a1, a2, bhalf, origin):  # pragma: no cover - jitted
    """Fill an axis descriptor: the lenslet window [e1, e2] (lenslet units) seen on the sensor
    from a disc centred at c, and the patch of pixel cells it can reach (cell t spans
    [origin + t·pp, origin + (t+1)·pp])."""
    kap = sc[_S_KAP]
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
    pp = sc[_S_PP]
    rho = sc[_S_RHO]
    va = max(c - rho, ax[_A_LO] - bhalf) - sc[_S_KSL]
    vb = min(c + rho, ax[_A_HI] + bhalf) + sc[_S_KSL]
    if vb <= va:
        ax[_A_N] = 0.0
        return
    ta = math.floor((va - origin) / pp)
    tb = math.floor((vb - origin) / pp)
    ax[_A_T0] = ta
    ax[_A_N] = tb - ta + 1
    ax[_A_E0] = origin + ta * pp


@_helper
def _edge_table(ax, sc, e, q, out):  # pragma: no cover - jitted
    """out[k] = ∫_{cell k} Φ((x − q)/σc) dx for every cell: a σs-blurred lower window edge q
    (lenslet edge e) seen through the σl-blurred pixels (σc = sqrt(σs² + σl²)).

    Computed in lenslet units, (x − q)/σc = (|κ|(x − C) − (e − G0)·sgn κ)/S with
    S = sqrt(σm² + κ²σl²), so that it stays exact as κ → 0 (σc → ∞).
    """
    pp = sc[_S_PP]
    n = int(ax[_A_N])
    s = sc[_S_S]
    x0 = ax[_A_E0]
    if s <= 0.0:  # no diffraction: a hard edge
        for k in range(n):
            lo = max(q, x0 + k * pp)
            out[k] = x0 + (k + 1) * pp - lo if x0 + (k + 1) * pp > lo else 0.0
        return
    ak = sc[_S_AK]
    sig_c = s / ak
    off = (e - ax[_A_G0]) * ax[_A_SLO]
    step = ak * pp / s
    a_prev = (ak * (x0 - ax[_A_C]) - off) / s
    if step < 0.25:  # very wide blur: differences of IΦ would cancel; the cell's mean of Φ times pp
        # (width `step` used as is: a difference of the two cell ends loses ~1e-16/step, i.e. 1/κ near focus)
        for k in range(n):
            mid = (ak * (x0 + (k + 0.5) * pp - ax[_A_C]) - off) / s
            out[k] = pp * _mean_phi(mid, 0.5 * step)
        return
    r_prev = sig_c * _ramp(a_prev, 1.0)
    for k in range(n):
        a_next = a_prev + step
        if a_prev > _UMAX:  # wholly above the edge
            out[k] = pp
        elif a_next < -_UMAX:  # wholly below
            out[k] = 0.0
        else:
            r_next = sig_c * _ramp(a_next, 1.0)
            out[k] = r_next - r_prev
            r_prev = r_next
            a_prev = a_next
            continue
        a_prev = a_next
        r_prev = sig_c * _ramp(a_prev, 1.0) if a_prev <= _UMAX else 0.0


@_helper
def _axis_tables(ax, sc, lamlo, full, tmp):  # pragma: no cover - jitted
    """Per cell k: Λ_k(lo) (the blurred lower edge seen through the cell) and the full integral
    ∫ m·b_k (the cell's whole share of the window)."""
    pp = sc[_S_PP]
    n = int(ax[_A_N])
    if ax[_A_LO] == -np.inf:
        for k in range(n):
            lamlo[k] = pp
    else:
        _edge_table(ax, sc, ax[_A_ELO], ax[_A_LO], lamlo)
    if ax[_A_HI] == np.inf:
        for k in range(n):
            full[k] = lamlo[k]
    else:
        _edge_table(ax, sc, ax[_A_EHI], ax[_A_HI], tmp)
        for k in range(n):
            full[k] = lamlo[k] - tmp[k]


@_helper
def _axis_angles(ax, rho, ang, is_x):  # pragma: no cover - jitted
    """Angles (with their cos, sin: rows of ang) at which the circle (radius ρ about the axis'
    disc centre) crosses the zone boundaries of this axis; returns their number (at most 8)."""
    c = ax[_A_C]
    lo = ax[_A_LO]
    hi = ax[_A_HI]
    b = ax[_A_B]
    mrg = ax[_A_MRG] != 0.0
    n = 0
    for v in (lo - b, lo + b, hi - b, hi + b):
        if mrg and (v == lo + b or v == hi - b):
            continue
        if abs(v - c) < rho:
            w = (v - c) / rho
            r = math.sqrt(max(1.0 - w * w, 0.0))
            if is_x:
                t = math.acos(w)
                ang[0, n], ang[1, n], ang[2, n] = t, w, r
                ang[0, n + 1], ang[1, n + 1], ang[2, n + 1] = _TWO_PI - t, w, -r
            else:
                t = math.asin(w)
                ang[0, n], ang[1, n], ang[2, n] = (t if t >= 0.0 else t + _TWO_PI), r, w
                ang[0, n + 1], ang[1, n + 1], ang[2, n + 1] = math.pi - t, -r, w
            n += 2
    return n


@njit(inline="always", cache=True)
def _b(ax, sc, k, v):  # pragma: no cover - jitted
    """b_k(v): the σl-blurred box of cell k at v."""
    x0 = ax[_A_E0] + k * sc[_S_PP]
    return _cdf(x0 + sc[_S_PP] - v, sc[_S_SL]) - _cdf(x0 - v, sc[_S_SL])


@_helper
def _num_int(ax, sc, k, a, b):  # pragma: no cover - jitted
    """∫_a^b m(x)·b_k(x) dx by Gauss–Legendre panels broken at the cell edges and window edges."""
    if b <= a:
        return 0.0
    pp = sc[_S_PP]
    x0 = ax[_A_E0] + k * pp
    sig = sc[_S_SL]
    ssx = sc[_S_SM] / sc[_S_AK] if sc[_S_AK] > 0.0 else 0.0
    if ssx > 0.0 and (sig <= 0.0 or ssx < sig):
        sig = ssx
    lmax = sc[_S_PANEL] * sig if sig > 0.0 else np.inf
    ngn = int(sc[_S_NGN])
    acc = 0.0
    lo = a
    while lo < b:
        hi = b
        for v in (x0, x0 + pp, ax[_A_LO], ax[_A_HI]):
            if lo < v < hi:
                hi = v
        m = 1 if not (hi - lo > lmax) else math.ceil((hi - lo) / lmax)
        step = (hi - lo) / m
        h = 0.5 * step
        for j in range(m):
            c = lo + (j + 0.5) * step
            for g in range(ngn):
                x = c + h * _GL_X[ngn, g]
                acc += _GL_W[ngn, g] * h * _m(ax, sc, x) * _b(ax, sc, k, x)
        lo = hi
    return acc


@_helper
def _num_step(ax, sc, k, a, b):  # pragma: no cover - jitted
    """∫_a^b m(x)·b_k(x) dx over a short step (between consecutive arc nodes): 4-point Gauss–Legendre."""
    h = 0.5 * (b - a)
    c = 0.5 * (a + b)
    acc = 0.0
    for g in range(4):
        x = c + h * _G4_X[g]
        acc += _G4_W[g] * _m(ax, sc, x) * _b(ax, sc, k, x)
    return acc * h


@_helper
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
@_helper
def _nodes(pri, sec, sc, swap, work, bt, zp, sec_window, cnt):  # pragma: no cover - jitted
    """The queued nodes of batch bt of ∮ U_k(vp)·m_s(vs)·b_j(vs) d(vs) (nodv rows: vp, vs, weight).

    U_k is the antiderivative along the primary axis, b_j the blurred cells of the
    secondary axis and m_s the lenslet window along it (applied if ``sec_window``); ``zp``
    is the nodes' zone on the primary axis. ``pri``, ``sec``: the primary and secondary
    axis (``cur`` tuples); ``swap``: the primary axis is y (patch indexed [k, j], carry_y);
    ``work``: the patch scratch. Cells of the primary axis wholly below vp take their full
    share through the carry (summed once per patch). One call per arc piece: the loop
    calls only scalar functions (no per-node array passing).
    """
    pa, lam_p, full_p, _ = pri
    sa = sec[0]
    direct, carry_x, carry_y, _, _, wk, nodv, ncnt, _ = work
    carry = carry_y if swap else carry_x
    n = ncnt[bt]
    pp = sc[_S_PP]
    ksl = sc[_S_KSL]
    sl = sc[_S_SL]
    sm = sc[_S_SM]
    kap = sc[_S_KAP]
    pe0 = pa[_A_E0]
    npri = int(pa[_A_N])
    se0 = sa[_A_E0]
    ns = int(sa[_A_N])
    sg0 = sa[_A_G0]
    sc0 = sa[_A_C]
    se1 = sa[_A_E1]
    se2 = sa[_A_E2]
    sa1 = sa[_A_A1] != 0.0
    sa2 = sa[_A_A2] != 0.0
    inv_pp = 1.0 / pp
    cnt[_ST_NODES] += n
    if zp in (_BLO, _BHI):
        cnt[_ST_BAND] += n
        for k in range(npri):
            wk[5, k] = 0.0
    for i in range(n):
        vp = nodv[bt, 0, i]
        vs = nodv[bt, 1, i]
        w = nodv[bt, 2, i]
        if sec_window:
            w *= _window(sg0 + kap * (vs - sc0), se1, se2, sa1, sa2, sm)
            if w == 0.0:
                continue
        j0 = max(math.floor((vs - ksl - se0) * inv_pp), 0)
        j1 = min(math.floor((vs + ksl - se0) * inv_pp), ns - 1)
        if j1 < j0:
            continue
        for e in range(j0, j1 + 2):  # each secondary edge once
            wk[1, e - j0] = _cdf(se0 + e * pp - vs, sl)
        kfull = min(max(math.floor((vp - ksl - pe0) * inv_pp) - 1, -1), npri - 1)
        kpart = min(math.floor((vp + ksl - pe0) * inv_pp), npri - 1)
        k0 = kfull + 1
        if zp == _MID:  # the window is flat: U_k = Λ_k(lo) − ∫_vp^∞ b_k, one ramp per edge
            for e in range(k0, kpart + 2):
                wk[0, e - k0] = _ramp(vp - pe0 - e * pp, sl)
            for k in range(k0, kpart + 1):
                wk[0, k - k0] = lam_p[k] - pp + wk[0, k - k0] - wk[0, k - k0 + 1]
        elif zp == _LOW:
            for k in range(k0, kpart + 1):
                wk[0, k - k0] = 0.0
        elif zp == _HIGH:
            for k in range(k0, kpart + 1):
                wk[0, k - k0] = full_p[k]
        else:  # inside a band (only near a corner of the blurred square): numeric,
            # carried from the previous node of this piece (vp is monotone along a piece).
            for k in range(k0, kpart + 1):
                if wk[5, k] != 0.0:
                    u = wk[3, k] + _num_step(pa, sc, k, wk[4, k], vp)
                else:
                    u = _u_partial(pa, sc, lam_p, full_p, k, vp, zp)
                wk[3, k] = u
                wk[4, k] = vp
                wk[5, k] = 1.0
                wk[0, k - k0] = u
        if swap:
            for j in range(j0, j1 + 1):
                g = w * (wk[1, j + 1 - j0] - wk[1, j - j0])
                if g == 0.0:
                    continue
                if kfull >= 0:
                    carry[kfull, j] += g
                for k in range(k0, kpart + 1):
                    direct[k, j] += g * wk[0, k - k0]
        else:
            for j in range(j0, j1 + 1):
                g = w * (wk[1, j + 1 - j0] - wk[1, j - j0])
                if g == 0.0:
                    continue
                if kfull >= 0:
                    carry[j, kfull] += g
                for k in range(k0, kpart + 1):
                    direct[j, k] += g * wk[0, k - k0]


@_helper
def _nodes_vec(pri, sec, sc, swap, work, bt, sec_window, cnt):  # pragma: no cover - jitted
    """As :func:`_nodes` for nodes in the flat middle of the primary window, with σl > 0 (and σm > 0
    if the secondary window is needed): the Φ values of a whole batch are computed in one
    vectorised pass, for a fixed set of 2W + 2 pixel edges around each node (W = ⌈6σl/pp⌉)."""
    pa, lam_p, _, _ = pri
    sa = sec[0]
    direct, carry_x, carry_y, _, _, wk, nodv, ncnt, vb = work
    carry = carry_y if swap else carry_x
    n = ncnt[bt]
    pp = sc[_S_PP]
    sl = sc[_S_SL]
    sm = sc[_S_SM]
    kap = sc[_S_KAP]
    inv_pp = 1.0 / pp
    isl = 1.0 / sl
    ism = 1.0 / sm if sm > 0.0 else 0.0
    wh = math.ceil(sc[_S_KSL] * inv_pp)
    ne = 2 * wh + 2
    pe0 = pa[_A_E0]
    npri = int(pa[_A_N])
    se0 = sa[_A_E0]
    ns = int(sa[_A_N])
    sg0 = sa[_A_G0]
    sc0 = sa[_A_C]
    se1 = sa[_A_E1]
    se2 = sa[_A_E2]
    sa1 = sa[_A_A1] != 0.0
    sa2 = sa[_A_A2] != 0.0
    cnt[_ST_NODES] += n
    for i in range(n):  # arguments of every Φ the batch needs
        vp = nodv[bt, 0, i]
        vs = nodv[bt, 1, i]
        ej = math.floor((vs - se0) * inv_pp)
        ek = math.floor((vp - pe0) * inv_pp)
        nodv[bt, 3, i] = ej
        nodv[bt, 4, i] = ek
        for m in range(ne):
            vb[0, m * n + i] = (se0 + (ej - wh + m) * pp - vs) * isl  # secondary edges: Φ((E − vs)/σl)
            vb[0, (ne + m) * n + i] = (vp - pe0 - (ek - wh + m) * pp) * isl  # primary edges: IΦ((vp − E)/σl)
        if sec_window:
            us = sg0 + kap * (vs - sc0)
            vb[0, 2 * ne * n + i] = (se2 - us) * ism
            vb[0, (2 * ne + 1) * n + i] = (se1 - us) * ism
    _phi_batch(vb, (2 * ne + (2 if sec_window else 0)) * n)
    for i in range(n):
        w = nodv[bt, 2, i]
        if sec_window:
            w *= (vb[1, 2 * ne * n + i] if sa2 else 1.0) - (vb[1, (2 * ne + 1) * n + i] if sa1 else 0.0)
            if w == 0.0:
                continue
        ej = int(nodv[bt, 3, i])
        ek = int(nodv[bt, 4, i])
        j0 = max(ej - wh, 0)
        j1 = min(ej + wh, ns - 1)
        kfull = min(max(ek - wh - 1, -1), npri - 1)
        kpart = min(ek + wh, npri - 1)
        k0 = kfull + 1
        for k in range(k0, kpart + 1):  # U_k = Λ_k(lo) − ∫_vp^∞ b_k = Λ_k(lo) − pp + ramp(vp − E_k) − ramp(vp − E_k+1)
            m = k - ek + wh
            ia = (ne + m) * n + i
            ib = ia + n
            wk[0, k - k0] = lam_p[k] - pp + sl * (vb[0, ia] * vb[1, ia] + vb[2, ia] - vb[0, ib] * vb[1, ib] - vb[2, ib])
        for j in range(j0, j1 + 1):
            m = j - ej + wh
            g = w * (vb[1, (m + 1) * n + i] - vb[1, m * n + i])
            if g == 0.0:
                continue
            if swap:
                if kfull >= 0:
                    carry[kfull, j] += g
                for k in range(k0, kpart + 1):
                    direct[k, j] += g * wk[0, k - k0]
            else:
                if kfull >= 0:
                    carry[j, kfull] += g
                for k in range(k0, kpart + 1):
                    direct[j, k] += g * wk[0, k - k0]


@_helper
def _v_at(ax, sc, lamv, fullv, j, v, zone):  # pragma: no cover - jitted
    """V_j(v) = ∫_{−∞}^{v} m·b_j for any cell j (0 wholly above v, full wholly below)."""
    ksl = sc[_S_KSL]
    y0 = ax[_A_E0] + j * sc[_S_PP]
    if y0 - ksl > v:
        return 0.0
    if y0 + sc[_S_PP] + ksl < v:
        return fullv[j]
    return _u_partial(ax, sc, lamv, fullv, j, v, zone)


@_helper
def _cut(pri, sec, sc, swap, work, v, s0, s1, sign):  # pragma: no cover - jitted
    """A straight segment at primary coordinate v from s0 to s1 along the secondary axis:
    sign·U_p(v)·[V_s(s1) − V_s(s0)] for every cell pair (``pri``, ``sec``, ``swap``, ``work``:
    as for :func:`_nodes`; wk row 2 holds the U_p(v) of each cell)."""
    pa, lam_p, full_p, _ = pri
    sa, lam_s, full_s, _ = sec
    direct, carry_x, carry_y, _, _, wk, _, _, _ = work
    carry = carry_y if swap else carry_x
    uk = wk[2]
    pp = sc[_S_PP]
    ksl = sc[_S_KSL]
    ns = int(sa[_A_N])
    npri = int(pa[_A_N])
    zp = _zone(pa, v)
    if zp == _LOW:
        return
    z0 = _zone(sa, s0)
    z1 = _zone(sa, s1)
    kfull = min(max(math.floor((v - ksl - pa[_A_E0]) / pp) - 1, -1), npri - 1)
    kpart = min(math.floor((v + ksl - pa[_A_E0]) / pp), npri - 1)
    if zp == _HIGH:  # every cell takes its full share
        kfull = kpart = npri - 1
    j0 = max(math.floor((s0 - ksl - sa[_A_E0]) / pp), 0)
    j1 = min(math.floor((s1 + ksl - sa[_A_E0]) / pp), ns - 1)
    if j1 < j0:
        return
    # U_p(v) does not depend on the secondary cell: once per primary cell (inside a band it is
    # a numeric integral).
    for k in range(kfull + 1, kpart + 1):
        uk[k] = _u_partial(pa, sc, lam_p, full_p, k, v, zp)
    for j in range(j0, j1 + 1):
        dv = sign * (_v_at(sa, sc, lam_s, full_s, j, s1, z1) - _v_at(sa, sc, lam_s, full_s, j, s0, z0))
        if dv == 0.0:
            continue
        if kfull >= 0:
            if swap:
                carry[kfull, j] += dv
            else:
                carry[j, kfull] += dv
        for k in range(kfull + 1, kpart + 1):
            u = uk[k]
            if swap:
                direct[k, j] += dv * u
            else:
                direct[j, k] += dv * u


@njit(inline="always", cache=True)
def _cs_small(d):  # pragma: no cover - jitted
    """(cos d, sin d): Taylor polynomials for |d| < 0.5 (error < 1e-15), libm otherwise."""
    if abs(d) < 0.5:
        d2 = d * d
        c = 1.0 - d2 * (
            0.5
            - d2
            * (
                1.0 / 24
                - d2
                * (1.0 / 720 - d2 * (1.0 / 40320 - d2 * (1.0 / 3628800 - d2 * (1.0 / 479001600 - d2 / 87178291200.0))))
            )
        )
        sn = d * (
            1.0
            - d2
            * (
                1.0 / 6
                - d2
                * (
                    1.0 / 120
                    - d2
                    * (
                        1.0 / 5040
                        - d2 * (1.0 / 362880 - d2 * (1.0 / 39916800 - d2 * (1.0 / 6227020800 - d2 / 1307674368000.0)))
                    )
                )
            )
        )
        return c, sn
    return math.cos(d), math.sin(d)


@_helper
def _flush(bt, curx, cury, sc, work, cnt):  # pragma: no cover - jitted
    """Process batch bt of arc nodes: 0 = x-antiderivative, 1 = the same with the y-window,
    2 = y-antiderivative (x inside a band, y in the flat middle)."""
    ncnt = work[7]
    if ncnt[bt] == 0:
        return
    vec = sc[_S_SL] > 0.0 and (sc[_S_SM] > 0.0 or bt == 0)
    if bt < 2:
        if vec:
            _nodes_vec(curx, cury, sc, _flag(False), work, bt, bt == 1, cnt)
        else:
            _nodes(curx, cury, sc, _flag(False), work, bt, _index(_MID), bt == 1, cnt)
    elif vec:
        _nodes_vec(cury, curx, sc, _flag(True), work, bt, _flag(True), cnt)
    else:
        _nodes(cury, curx, sc, _flag(True), work, bt, _index(_MID), _flag(True), cnt)
    ncnt[bt] = 0


@_helper
def _arc(curx, cury, sc, work, ia, cnt):  # pragma: no cover - jitted
    """Gauss–Legendre nodes of arc piece ia (pcs[:, ia] to pcs[:, ia + 1]: angle, cos, sin),
    monotone in x and y and in one zone pair.

    In the flat middle of the x-window the nodes integrate U_x(X)·m_y(Y)·b_j(Y) dY (x-
    antiderivative); inside a σs-band of a vertical edge they integrate −u_k(X)·V_y(Y) dX
    (y-antiderivative). Panels break at every pixel edge and band centre the arc crosses.
    Nodes are appended to the lenslet's batches (processed together by :func:`_flush`),
    except near a corner of the blurred square, done at once (numeric, monotone order).
    Cosines and sines come from the crossing geometry and rotations, not from libm.
    """
    ax = curx[0]
    ay = cury[0]
    _, _, _, pcs, brk, _, nodv, ncnt, _ = work
    rho = sc[_S_RHO]
    cx = ax[_A_C]
    cy = ay[_A_C]
    ta = pcs[0, ia]
    tb = pcs[0, ia + 1]
    ca, sa = pcs[1, ia], pcs[2, ia]
    cb, sb = pcs[1, ia + 1], pcs[2, ia + 1]
    nm = math.hypot(ca + cb, sa + sb)  # the piece's mid-angle (pieces are within a quadrant)
    zx = _zone(ax, cx + rho * (ca + cb) / nm)
    zy = _zone(ay, cy + rho * (sa + sb) / nm)
    if min(zx, zy) == _LOW or max(zx, zy) == _HIGH:
        return  # outside the blurred square: no light of this lenslet
    form_a = zx == _MID
    corner = not form_a and zy != _MID
    bt = (0 if zy == _MID else 1) if form_a else (3 if corner else 2)
    tm = 0.5 * (ta + tb)
    upper = tm < math.pi  # sin θ >= 0
    right = tm < _HALF_PI or tm > 3.0 * _HALF_PI  # cos θ >= 0
    pp = sc[_S_PP]
    xa = cx + rho * ca
    xb = cx + rho * cb
    x_lo, x_hi = min(xa, xb), max(xa, xb)
    ya = cy + rho * sa
    yb = cy + rho * sb
    y_lo, y_hi = min(ya, yb), max(ya, yb)
    # Crossings with vertical lines (cos θ known) and horizontal lines (sin θ known).
    nb = 0
    e0 = ax[_A_E0]
    ka = max(math.floor((x_lo - e0) / pp), 0)
    kb = min(math.ceil((x_hi - e0) / pp), int(ax[_A_N]))
    for k in range(ka, kb + 3):
        v = e0 + k * pp if k <= kb else (ax[_A_LO] if k == kb + 1 else ax[_A_HI])
        if x_lo < v < x_hi:
            w = (v - cx) / rho
            sw = math.sqrt(max(1.0 - w * w, 0.0))
            a = math.acos(w)
            brk[0, nb] = a if upper else _TWO_PI - a
            brk[1, nb] = w
            brk[2, nb] = sw if upper else -sw
            nb += 1
    e0 = ay[_A_E0]
    ka = max(math.floor((y_lo - e0) / pp), 0)
    kb = min(math.ceil((y_hi - e0) / pp), int(ay[_A_N]))
    for k in range(ka, kb + 3):
        v = e0 + k * pp if k <= kb else (ay[_A_LO] if k == kb + 1 else ay[_A_HI])
        if y_lo < v < y_hi:
            w = (v - cy) / rho
            cw = math.sqrt(max(1.0 - w * w, 0.0))
            a = math.asin(w)
            if right:
                brk[0, nb] = a if a >= 0.0 else a + _TWO_PI
            else:
                brk[0, nb] = math.pi - a
            brk[1, nb] = cw if right else -cw
            brk[2, nb] = w
            nb += 1
    brk[0, nb] = tb
    brk[1, nb] = cb
    brk[2, nb] = sb
    nb += 1
    for i in range(1, nb):  # insertion sort by angle (a handful of crossings)
        t, c, sn = brk[0, i], brk[1, i], brk[2, i]
        j = i - 1
        while j >= 0 and brk[0, j] > t:
            brk[0, j + 1] = brk[0, j]
            brk[1, j + 1] = brk[1, j]
            brk[2, j + 1] = brk[2, j]
            j -= 1
        brk[0, j + 1] = t
        brk[1, j + 1] = c
        brk[2, j + 1] = sn
    # Panel sizes follow how many blur widths the coordinates move: σl along a pixel axis,
    # and the narrower σs across a band of the blurred square.
    ss = sc[_S_SM] / sc[_S_AK] if sc[_S_AK] > 0.0 else 0.0
    sl = sc[_S_SL]
    sigx = sl if (zx == _MID or ss <= 0.0 or (0.0 < sl < ss)) else ss
    sigy = sl if (zy == _MID or ss <= 0.0 or (0.0 < sl < ss)) else ss
    isx = rho / sigx if sigx > 0.0 else 0.0
    isy = rho / sigy if sigy > 0.0 else 0.0
    cap = nodv.shape[2]
    panel, ngb, dens, ngmin = sc[_S_PANEL], sc[_S_NGB], sc[_S_DENS], int(sc[_S_NGMIN])
    t0 = ta
    c0 = ca
    s0 = sa
    for i in range(nb):
        t1 = min(max(brk[0, i], t0), tb)
        if t1 <= t0:
            continue
        c1 = brk[1, i]
        s1 = brk[2, i]
        dd = max(abs(c1 - c0) * isx, abs(s1 - s0) * isy)
        m = max(1, math.ceil(dd / panel))
        step = (t1 - t0) / m
        h = 0.5 * step
        ng = min(max(math.ceil(ngb + dens * dd / m), ngmin), _NG_MAX)
        chs, shs = _cs_small(h)  # the first sub-panel centre is t0 + h, the next ones a step further
        cst, sst = _cs_small(step)
        cc = c0 * chs - s0 * shs
        scn = s0 * chs + c0 * shs
        for _ in range(m):
            if ncnt[bt] + ng > cap:  # flush a full batch
                if corner:
                    _nodes(cury, curx, sc, _flag(True), work, bt, zy, _flag(True), cnt)
                    ncnt[bt] = 0
                else:
                    _flush(bt, curx, cury, sc, work, cnt)
            nn = ncnt[bt]
            for q in range(ng):
                cd, sd = _cs_small(h * _GL_X[ng, q])  # angle-sum rule about the sub-panel centre
                cs = cc * cd - scn * sd
                sn = scn * cd + cc * sd
                wq = _GL_W[ng, q] * h * rho
                if form_a:  # ∮ U(x) v(y) dy, dy = ρ cos θ dθ
                    nodv[bt, 0, nn] = cx + rho * cs
                    nodv[bt, 1, nn] = cy + rho * sn
                    nodv[bt, 2, nn] = wq * cs
                else:  # −∮ u(x) V(y) dx, dx = −ρ sin θ dθ
                    nodv[bt, 0, nn] = cy + rho * sn
                    nodv[bt, 1, nn] = cx + rho * cs
                    nodv[bt, 2, nn] = wq * sn
                nn += 1
            ncnt[bt] = nn
            cc, scn = cc * cst - scn * sst, scn * cst + cc * sst
        t0 = t1
        c0 = c1
        s0 = s1
    if corner and ncnt[bt] > 0:  # numeric antiderivatives carried along this piece: done now
        _nodes(cury, curx, sc, _flag(True), work, bt, zy, _flag(True), cnt)
        ncnt[bt] = 0


@_helper
def _boundary(curx, nangx, cury, nangy, sc, work, cnt):  # pragma: no cover - jitted
    """The patch of a lenslet whose blurred square meets the rim of the aperture image (Green's theorem).

    ``curx``/``cury``: the lenslet's column and row (descriptor, Λ(lo) and full tables, circle
    crossings: see "Data layout"), of which the first ``nangx``/``nangy`` crossings are set;
    ``work``: the patch scratch of :func:`_workspace`. The patch accumulates into ``work[0]``
    (direct).
    """
    ax, _, fullx, angx = curx
    ay, _, fully, angy = cury
    direct, carry_x, carry_y, pcs, _, _, _, _, _ = work
    rho = sc[_S_RHO]
    cx = ax[_A_C]
    cy = ay[_A_C]
    bx = ax[_A_B]
    by = ay[_A_B]
    nx = int(ax[_A_N])
    ny = int(ay[_A_N])
    # Arc pieces: the circle broken at the zone boundaries and the quarter turns.
    nb = 0
    for t, c, sn in ((0.0, 1.0, 0.0), (_HALF_PI, 0.0, 1.0), (math.pi, -1.0, 0.0), (3.0 * _HALF_PI, 0.0, -1.0)):
        pcs[0, nb], pcs[1, nb], pcs[2, nb] = t, c, sn
        nb += 1
    for i in range(nangx):
        pcs[0, nb], pcs[1, nb], pcs[2, nb] = angx[0, i], angx[1, i], angx[2, i]
        nb += 1
    for i in range(nangy):
        pcs[0, nb], pcs[1, nb], pcs[2, nb] = angy[0, i], angy[1, i], angy[2, i]
        nb += 1
    for i in range(1, nb):  # insertion sort by angle
        t, c, sn = pcs[0, i], pcs[1, i], pcs[2, i]
        j = i - 1
        while j >= 0 and pcs[0, j] > t:
            pcs[0, j + 1], pcs[1, j + 1], pcs[2, j + 1] = pcs[0, j], pcs[1, j], pcs[2, j]
            j -= 1
        pcs[0, j + 1], pcs[1, j + 1], pcs[2, j + 1] = t, c, sn
    pcs[0, nb], pcs[1, nb], pcs[2, nb] = _TWO_PI, 1.0, 0.0
    nb += 1
    for i in range(nb - 1):
        if pcs[0, i + 1] > pcs[0, i]:
            _arc(curx, cury, sc, work, i, cnt)
    for bt in range(3):
        _flush(bt, curx, cury, sc, work, cnt)
    # Vertical cuts between the flat middle (x-antiderivative) and the bands (y-antiderivative).
    if ax[_A_MRG] == 0.0:
        for v, sign in ((ax[_A_LO] + bx, -1.0), (ax[_A_HI] - bx, 1.0)):
            if abs(v - cx) < rho:
                h = math.sqrt(rho * rho - (v - cx) ** 2)
                s0 = max(cy - h, ay[_A_LO] - by)
                s1 = min(cy + h, ay[_A_HI] + by)
                if s1 > s0:
                    _cut(curx, cury, sc, _flag(False), work, v, s0, s1, sign)
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
                _cut(cury, curx, sc, _flag(True), work, y0, xl, xr, 1.0)
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


@_helper
def _write_patch(direct, ax, ay, geo, chunk, fac):  # pragma: no cover - jitted
    """Add fac·direct into the chunk's rows and clear it; returns (total, on the sensor, spilled).

    ``chunk``: (buf, r0, r1), the chunk's image rows r0..r1 as a flat slice of the image.
    """
    buf, r0, r1 = chunk
    nx = int(ax[_A_N])
    ny = int(ay[_A_N])
    tx0 = int(ax[_A_T0])
    ty0 = int(ay[_A_T0])
    ncol = int(geo[_G_NCOL])
    nrow = int(geo[_G_NROW])
    total = 0.0
    inside = 0.0
    spill = 0.0
    for j in range(ny):
        row = nrow - 1 - (ty0 + j)  # y cell t is image row nrow − 1 − t (row 0 at the top)
        ok_row = 0 <= row < nrow
        for k in range(nx):
            val = direct[j, k] * fac
            direct[j, k] = 0.0
            if val == 0.0:
                continue
            total += val
            col = tx0 + k
            if ok_row and 0 <= col < ncol:
                if r0 <= row <= r1:
                    buf[(row - r0) * ncol + col] += val
                    inside += val
                else:
                    spill += val
    return total, inside, spill


@_helper
def _write_outer(fx, ax, fy, ay, geo, chunk, fac):  # pragma: no cover - jitted
    """Add fac·fy[j]·fx[k] (a separable patch) into the chunk's rows; returns (total, on the sensor, spilled)."""
    buf, r0, r1 = chunk
    nx = int(ax[_A_N])
    ny = int(ay[_A_N])
    tx0 = int(ax[_A_T0])
    ty0 = int(ay[_A_T0])
    ncol = int(geo[_G_NCOL])
    nrow = int(geo[_G_NROW])
    total = 0.0
    inside = 0.0
    spill = 0.0
    for j in range(ny):
        gy = fac * fy[j]
        if gy == 0.0:
            continue
        row = nrow - 1 - (ty0 + j)
        ok_row = 0 <= row < nrow
        base = (row - r0) * ncol
        in_chunk = r0 <= row <= r1
        for k in range(nx):
            val = gy * fx[k]
            if val == 0.0:
                continue
            total += val
            col = tx0 + k
            if ok_row and 0 <= col < ncol:
                if in_chunk:
                    buf[base + col] += val
                    inside += val
                else:
                    spill += val
    return total, inside, spill


@njit(inline="always", cache=True)
def _store(cur, store, slot):  # pragma: no cover - jitted
    """Keep a column's (row's) descriptor and tables for the lenslets that share it (the inverse of :func:`_load`)."""
    ax, lam, full, ang = cur
    axs, lams, fulls, angs, _, _ = store
    for q in range(_A_SIZE):
        axs[slot, q] = ax[q]
    for k in range(int(ax[_A_N])):
        lams[slot, k] = lam[k]
        fulls[slot, k] = full[k]
    for r in range(3):
        for q in range(8):
            angs[slot, r, q] = ang[r, q]


@njit(inline="always", cache=True)
def _load(cur, store, slot):  # pragma: no cover - jitted
    """Copy a stored column's (row's) descriptor and tables into the working arrays."""
    ax, lam, full, ang = cur
    axs, lams, fulls, angs, _, _ = store
    for q in range(_A_SIZE):
        ax[q] = axs[slot, q]
    for k in range(int(ax[_A_N])):
        lam[k] = lams[slot, k]
        full[k] = fulls[slot, k]
    for r in range(3):
        for q in range(8):
            ang[r, q] = angs[slot, r, q]


# ------------------------------------------------------------ the particle kernel, step by step
@njit(inline="always", cache=True)
def _particle(geo, x, y, z, sc):  # pragma: no cover - jitted
    """Step 1, per particle: its ray geometry, and the shared scalars ``sc`` of its lenslet images.

    The ray to aperture point a has the slope a·c1 + t0 (eqs 4.2–4.3) and meets the lenslet
    plane at a·lsc + si·t0. Returns the spot centre in the grid frame (g0x, g0y; eqs
    4.10–4.11), the chief-ray slope (t0x, t0y), the spot radius rs on the lenslet plane, its
    reach rs + Kσm, whether it is in focus, the half-width of the σs-bands, and what places the
    aperture images on the sensor: lenslet k's disc is centred at ``(g/fl)·c_k + heff·t0 + (shx, shy)``.

    Imperfections (:mod:`lfstudy.simulate.imperfections`): a gap g != fl behind the lenslets
    lands the ray at ``c·g/fl + g·t + (1 − g/fl)·L`` (so the disc's radius is R·|β|, β = g·c1 +
    (1 − g/fl)·lsc, and κ = lsc/β); a tilted sensor puts the lenslet plane at the chief ray's
    point at si + θy·x + θx·y and adds (θy, θx) to the sensor-side slopes. Their ideal values
    leave every number bit-identical to the ideal model's.
    """
    so, si, fm, fl, rad = geo[_G_SO], geo[_G_SI], geo[_G_FM], geo[_G_FL], geo[_G_R]
    ox, oy, cr, sr = geo[_G_OX], geo[_G_OY], geo[_G_COS], geo[_G_SIN]
    sm, sl, pl = geo[_G_SM], geo[_G_SL], geo[_G_PL]
    gap, tlx, tly = geo[_G_GAP], geo[_G_TLX], geo[_G_TLY]
    inv_d = 1.0 / (so + z)
    c1 = inv_d - 1.0 / fm
    t0x = -x * inv_d
    t0y = -y * inv_d
    sip = si + tly * (si * t0x) + tlx * (si * t0y)  # the (tilted) lenslet plane's distance here
    lsc = 1.0 + sip * c1
    rs = rad * abs(lsc)  # radius of the aperture's image on the lenslet plane
    q = 1.0 - gap / fl
    beta = gap * c1 + q * lsc  # sensor shift per aperture shift (fl·c1 for g = fl)
    kap = lsc / beta  # lenslet-plane shift per sensor shift
    lx = sip * t0x - ox
    ly = sip * t0y - oy
    g0x = cr * lx + sr * ly  # spot centre in the grid frame (eqs 4.10–4.11)
    g0y = -sr * lx + cr * ly
    focus = rs <= _EPS_FOCUS * (sm if sm > 0.0 else pl)  # also catches rounding of an exact focus
    sc[_S_KAP] = kap
    sc[_S_SM] = sm
    sc[_S_SL] = sl
    sc[_S_PP] = geo[_G_PP]
    kcut = sc[_S_K]
    sc[_S_KSL] = kcut * sl
    sc[_S_AK] = abs(kap)
    sc[_S_S] = math.sqrt(sm * sm + kap * kap * sl * sl)
    sc[_S_RHO] = rad * fl * abs(c1) if q == 0.0 else rad * abs(beta)  # the aperture's image on the sensor
    bh = sc[_S_KS] * sm / abs(kap) if (not focus and kap != 0.0) else 0.0
    heff = gap + q * sip  # sensor shift per chief-ray slope (fl for g = fl)
    return g0x, g0y, t0x, t0y, rs, rs + kcut * sm, focus, bh, heff, gap * tly, gap * tlx


@njit(inline="always", cache=True)
def _lenslet_span(geo, g0, reach, is_x):  # pragma: no cover - jitted
    """Step 2: the first and last lenslet column (``is_x``) or row the spot can reach (eqs 4.10–4.11)."""
    pl = geo[_G_PL]
    if is_x:
        c0 = 0.5 * (geo[_G_NLX] - 1.0)
        return max(0, math.floor((g0 - reach) / pl + c0 + 0.5)), min(
            int(geo[_G_NLX]) - 1, math.floor((g0 + reach) / pl + c0 + 0.5)
        )
    c0 = 0.5 * (geo[_G_NLY] - 1.0)
    return max(0, math.floor(c0 - (g0 + reach) / pl + 0.5)), min(
        int(geo[_G_NLY]) - 1, math.floor(c0 - (g0 - reach) / pl + 0.5)
    )


@njit(inline="always", cache=True)
def _axis_pass(geo, sc, spot, is_x, lo, hi, rotated, cur, store, tmp, cnt):  # pragma: no cover - jitted
    """Step 3, per lenslet column (``is_x``) or row ``lo..hi`` the spot (:func:`_particle`) reaches: its
    window factor (in focus: the share of the spot it takes; else 0 if the spot misses it) and, for
    an unrotated grid, its axis descriptor, tables and circle crossings, kept in ``store`` for the
    lenslets that share it."""
    g0 = spot[0] if is_x else spot[1]
    t0 = spot[2] if is_x else spot[3]
    reach, focus, bh, heff = spot[5], spot[6], spot[7], spot[8]
    sh = spot[9] if is_x else spot[10]
    gr = geo[_G_GAP] / geo[_G_FL]
    ax, lam, full, ang = cur
    _, _, _, _, nang, fac = store
    pl, sm = geo[_G_PL], geo[_G_SM]
    if is_x:
        c0, off, origin = 0.5 * (geo[_G_NLX] - 1.0), geo[_G_OX], -geo[_G_HW]
    else:
        c0, off, origin = 0.5 * (geo[_G_NLY] - 1.0), geo[_G_OY], -geo[_G_HH]
    for ll in range(lo, hi + 1):
        slot = ll - lo
        if is_x:
            e1 = (ll - c0 - 0.5) * pl
            ctr = (ll - c0) * pl
        else:
            e1 = (c0 - ll - 0.5) * pl
            ctr = (c0 - ll) * pl
        e2 = e1 + pl
        f = 1.0
        a1 = a2 = False
        if focus:  # the whole aperture lands on one lenslet-plane point
            if sm > 0.0:
                f = _window(g0, e1, e2, True, True, sm)
            elif is_x:  # the divide-and-round of eqs 4.10–4.11: gx in [e1, e2), gy in (e1, e2]
                f = 1.0 if e1 <= g0 < e2 else 0.0
            else:
                f = 1.0 if e1 < g0 <= e2 else 0.0
        else:
            a1 = abs(e1 - g0) < reach
            a2 = abs(e2 - g0) < reach
            if (not a1 and e1 > g0) or (not a2 and e2 < g0):
                f = 0.0  # the spot misses this column/row
        fac[slot] = f
        if f == 0.0 or rotated:
            continue
        _setup_axis(ax, sc, gr * (ctr + off) + heff * t0 + sh, g0, e1, e2, a1, a2, bh, origin)
        if ax[_A_N] > lam.shape[0]:
            cnt[_ST_BIG] += 1.0
            fac[slot] = 0.0
            continue
        _axis_tables(ax, sc, lam, full, tmp)
        nang[slot] = _axis_angles(ax, sc[_S_RHO], ang, is_x)
        _store(cur, store, slot)


@njit(inline="always", cache=True)
def _scatter_offset(geo, li, lj):  # pragma: no cover - jitted
    """Offset (x, y) [mm] of lenslet (li, lj)'s optical centre from its cell's centre (0 without scatter)."""
    if geo[_G_SCAT] == 0.0:
        return 0.0, 0.0
    k = _G_SIZE + 2 * (li * int(geo[_G_NLX]) + lj)
    return geo[k], geo[k + 1]


@njit(inline="always", cache=True)
def _lenslet_axes(geo, sc, li, lj, sa, sb, nsub, spot, curx, cury, tmp):  # pragma: no cover - jitted
    """Step 4a', per-lenslet grid out of focus: the descriptors, tables and circle crossings of
    sub-square (sa, sb) of lenslet (li, lj) (``nsub`` x ``nsub`` of them; its disc centre is the
    lenslet's own when the centres scatter). Returns (status, crossings x, crossings y); status 1:
    set up, 0: the spot misses it, −1: a patch is too big.

    The window of a lenslet is the sum of its sub-squares' windows (P(L + σm·Z ∈ square) is
    additive over a tiling). A rotated grid (rotation θ) is taken, per sub-square, in the frame of
    the sensor's axes through the sub-square's centre: the map from the sensor to the lenslet plane
    is exact at that centre and the sub-square's edges turn by θ about it, so they move by at most
    θ·pl/(√2·nsub) in the lenslet plane; the sub-squares still tile the lenslet to O(θ²). Unrotated
    (nsub = 1) the result is exact.
    """
    g0x, g0y, t0x, t0y = spot[0], spot[1], spot[2], spot[3]
    reach, bh, heff, shx, shy = spot[5], spot[7], spot[8], spot[9], spot[10]
    ax, lamx, fullx, angx = curx
    ay, lamy, fully, angy = cury
    pl, cr, sr = geo[_G_PL], geo[_G_COS], geo[_G_SIN]
    gr = geo[_G_GAP] / geo[_G_FL]
    cx0, cy0 = 0.5 * (geo[_G_NLX] - 1.0), 0.5 * (geo[_G_NLY] - 1.0)
    gcx = (lj - cx0) * pl
    gcy = (cy0 - li) * pl
    if nsub == 1:
        u1 = (lj - cx0 - 0.5) * pl
        v1 = (cy0 - li - 0.5) * pl
        u2, v2 = u1 + pl, v1 + pl
    else:
        u1 = (lj - cx0 - 0.5 + sa / nsub) * pl
        u2 = (lj - cx0 - 0.5 + (sa + 1) / nsub) * pl
        v1 = (cy0 - li - 0.5 + sb / nsub) * pl
        v2 = (cy0 - li - 0.5 + (sb + 1) / nsub) * pl
    if sr == 0.0 and cr == 1.0:
        gex, gey = g0x, g0y
    else:  # the spot centre in the sub-square's sensor-aligned frame: exact at its centre
        du, dv = 0.5 * (u1 + u2) - g0x, 0.5 * (v1 + v2) - g0y
        gex = 0.5 * (u1 + u2) - cr * du + sr * dv
        gey = 0.5 * (v1 + v2) - sr * du - cr * dv
    a1x, a2x = abs(u1 - gex) < reach, abs(u2 - gex) < reach
    a1y, a2y = abs(v1 - gey) < reach, abs(v2 - gey) < reach
    if (not a1x and u1 > gex) or (not a2x and u2 < gex) or (not a1y and v1 > gey) or (not a2y and v2 < gey):
        return 0, 0, 0
    dx, dy = _scatter_offset(geo, li, lj)
    cx = gr * (cr * gcx - sr * gcy + geo[_G_OX] + dx) + heff * t0x + shx
    cy = gr * (sr * gcx + cr * gcy + geo[_G_OY] + dy) + heff * t0y + shy
    _setup_axis(ax, sc, cx, gex, u1, u2, a1x, a2x, bh, -geo[_G_HW])
    _setup_axis(ay, sc, cy, gey, v1, v2, a1y, a2y, bh, -geo[_G_HH])
    if ax[_A_N] > lamx.shape[0] or ay[_A_N] > lamy.shape[0]:
        return -1, 0, 0
    _axis_tables(ax, sc, lamx, fullx, tmp)
    _axis_tables(ay, sc, lamy, fully, tmp)
    return 1, _axis_angles(ax, sc[_S_RHO], angx, _flag(True)), _axis_angles(ay, sc[_S_RHO], angy, _flag(False))


@njit(inline="always", cache=True)
def _rotated_axes(geo, sc, li, lj, spot, curx, cury, tmp):  # pragma: no cover - jitted
    """Step 4a, per-lenslet grid (rotated, or with scattered centres) in focus: lenslet (li, lj)'s
    window does not matter (M is a constant), only the disc, centred on the rotated (and scattered)
    lenslet centre (+ fl·t0). False if a patch is too big."""
    g0x, g0y, t0x, t0y, heff, shx, shy = spot[0], spot[1], spot[2], spot[3], spot[8], spot[9], spot[10]
    ax, lamx, fullx, _ = curx
    ay, lamy, fully, _ = cury
    pl, cr, sr = geo[_G_PL], geo[_G_COS], geo[_G_SIN]
    gr = geo[_G_GAP] / geo[_G_FL]
    cx0, cy0 = 0.5 * (geo[_G_NLX] - 1.0), 0.5 * (geo[_G_NLY] - 1.0)
    u1 = (lj - cx0 - 0.5) * pl
    v1 = (cy0 - li - 0.5) * pl
    gcx = (lj - cx0) * pl
    gcy = (cy0 - li) * pl
    dx, dy = _scatter_offset(geo, li, lj)
    cx = gr * (cr * gcx - sr * gcy + geo[_G_OX] + dx) + heff * t0x + shx
    cy = gr * (sr * gcx + cr * gcy + geo[_G_OY] + dy) + heff * t0y + shy
    _setup_axis(ax, sc, cx, g0x, u1, u1 + pl, _flag(False), _flag(False), 0.0, -geo[_G_HW])
    _setup_axis(ay, sc, cy, g0y, v1, v1 + pl, _flag(False), _flag(False), 0.0, -geo[_G_HH])
    if ax[_A_N] > lamx.shape[0] or ay[_A_N] > lamy.shape[0]:
        return False
    _axis_tables(ax, sc, lamx, fullx, tmp)
    _axis_tables(ay, sc, lamy, fully, tmp)
    return True


@njit(inline="always", cache=True)
def _lenslet_image(geo, sc, spot, fac, curx, nangx, cury, nangy, work, chunk, cnt):  # pragma: no cover - jitted
    """Step 4b, one lenslet's image (its column and row in ``curx``, ``cury``, with ``nangx``, ``nangy``
    circle crossings) times ``fac``, added into the chunk's rows (``chunk``: see :func:`_write_patch`):
    separable if the blurred square lies inside the aperture image, else by Green's theorem."""
    rs, focus = spot[4], spot[6]
    ax, _, fullx, _ = curx
    ay, _, fully, _ = cury
    g0x, g0y = ax[_A_G0], ay[_A_G0]  # the spot centre in the lenslet's frame (the grid's, unless rotated)
    direct = work[0]
    if ax[_A_N] == 0.0 or ay[_A_N] == 0.0:
        return
    sm = sc[_S_SM]
    u1, u2 = ax[_A_E1], ax[_A_E2]  # the lenslet's square (grid frame)
    v1, v2 = ay[_A_E1], ay[_A_E2]
    interior = False
    if not focus and ax[_A_A1] * ax[_A_A2] * ay[_A_A1] * ay[_A_A2] != 0.0:
        ksm = sc[_S_K] * sm
        ex = max(abs(u1 - ksm - g0x), abs(u2 + ksm - g0x))
        ey = max(abs(v1 - ksm - g0y), abs(v2 + ksm - g0y))
        interior = ex * ex + ey * ey <= rs * rs
    if interior:
        tot, ins, sp = _write_outer(fullx, ax, fully, ay, geo, chunk, fac)
        cnt[_ST_INTERIOR] += 1.0
    else:
        _boundary(curx, nangx, cury, nangy, sc, work, cnt)
        tot, ins, sp = _write_patch(direct, ax, ay, geo, chunk, fac)
    cnt[_ST_ALL] += tot
    cnt[_ST_IN] += ins
    cnt[_ST_SPILL] += abs(sp)
    cnt[_ST_LENS] += 1.0


@njit(inline="always", cache=True)
def _axis_store(nlmax, psz):  # pragma: no cover - jitted
    """Per-particle descriptors and tables of every lenslet column (or row): (descriptors,
    Λ(lo) tables, full tables, circle crossings, their count, window factors)."""
    return (
        np.zeros((nlmax, _A_SIZE)),
        np.zeros((nlmax, psz)),
        np.zeros((nlmax, psz)),
        np.zeros((nlmax, 3, 8)),
        np.zeros(nlmax, dtype=np.int64),
        np.zeros(nlmax),
    )


@njit(inline="always", cache=True)
def _axis_current(psz):  # pragma: no cover - jitted
    """The current lenslet's descriptor and tables along one axis (copied in: no array views in the loops)."""
    return np.zeros(_A_SIZE), np.zeros(psz), np.zeros(psz), np.zeros((3, 8))


@njit(inline="always", cache=True)
def _workspace(geo, psz):  # pragma: no cover - jitted
    """The scratch of one lenslet's boundary patch (see the layout table in the module docstring)."""
    pp, sl = geo[_G_PP], geo[_G_SL]
    nw = 2 * (2 * math.ceil(_K * sl / pp) + 2) + 2 if pp > 0.0 else 2
    return (
        np.zeros((psz, psz)),  # direct
        np.zeros((psz, psz)),  # carry_x
        np.zeros((psz, psz)),  # carry_y
        np.zeros((3, 24)),  # pcs
        np.zeros((3, 2 * psz + 16)),  # brk
        np.zeros((6, psz + 4)),  # wk
        np.zeros((4, 5, 512)),  # nodv
        np.zeros(4, dtype=np.int64),  # ncnt
        np.zeros((3, nw * 512)),  # vb
    )


@njit(inline="always", cache=True)
def _scratch(geo, psz, nlmax, quad):  # pragma: no cover - jitted
    """One thread's scratch for :func:`_render_particle`: (sc, cols, rows, curx, cury, tmp, work); ``sc``
    holds the quadrature ``quad`` (:data:`_QUAD_EXACT` or a coarser one; ``_K`` at most 6, the workspace's size)."""
    sc = np.zeros(_S_SIZE)
    for q in range(quad.size):
        sc[_S_NGB + q] = quad[q]
    return (
        sc,
        _axis_store(nlmax, psz),
        _axis_store(nlmax, psz),
        _axis_current(psz),
        _axis_current(psz),
        np.zeros(psz),
        _workspace(geo, psz),
    )


# Compiled once, on its own, and called by both kernels (not inlined into each): the two kernels share its machine
# code and numba cache, so a fresh clone compiles the render and IPR's patches in 65 s instead of 122 s
# (benchmarks/bench_compile.py).
@njit(cache=True, error_model="numpy")
def _render_particle(geo, rotated, x, y, z, w, scr, chunk, cnt):  # pragma: no cover - jitted
    """Add the expected image of one particle (``x, y, z`` [mm], expected intensity ``w``) to ``chunk``.

    Its geometry (:func:`_particle`), the lenslets it reaches (:func:`_lenslet_span`), the
    tables of their columns and rows (:func:`_axis_pass`), then each lenslet's image
    (:func:`_lenslet_image`). ``scr`` is :func:`_scratch`'s tuple, ``chunk`` = (buf, r0, r1) the
    rows it writes, ``cnt`` the ``_ST_*`` counters. The full render (:func:`_render_kernel`) and
    the per-particle patches of :mod:`lfstudy.reconstruct.ipr` both call it, so both give the
    same bytes for the same particle.
    """
    sc, cols, rows, curx, cury, tmp, work = scr
    nlmax = cols[0].shape[0]
    spot = _particle(geo, x, y, z, sc)
    g0x, g0y, reach, focus = spot[0], spot[1], spot[5], spot[6]
    # Lenslets set up one by one: a rotated grid, or scattered centres (per-lenslet discs).
    perlens = rotated or geo[_G_SCAT] != 0.0
    approx = abs(geo[_G_SIN]) <= _ROT_APPROX  # out of focus, a rotated grid in sub-squares (_lenslet_axes)
    nsub = max(1, math.ceil(abs(geo[_G_SIN]) / _ROT_STEP - 1e-9))
    j0, j1 = _lenslet_span(geo, g0x, reach, True)
    i0, i1 = _lenslet_span(geo, g0y, reach, False)
    if j1 < j0 or i1 < i0:
        return
    if j1 - j0 + 1 > nlmax or i1 - i0 + 1 > nlmax:
        cnt[_ST_BIG] += 1.0
        return
    fac0 = w / (math.pi * sc[_S_RHO] * sc[_S_RHO])  # uniform over the aperture image
    _axis_pass(geo, sc, spot, _flag(True), j0, j1, perlens, curx, cols, tmp, cnt)
    _axis_pass(geo, sc, spot, _flag(False), i0, i1, perlens, cury, rows, tmp, cnt)
    facx = cols[5]
    facy = rows[5]
    pl = geo[_G_PL]
    cx0, cy0 = 0.5 * (geo[_G_NLX] - 1.0), 0.5 * (geo[_G_NLY] - 1.0)
    for li in range(i0, i1 + 1):
        sy = li - i0
        if facy[sy] == 0.0:
            continue
        v1 = (cy0 - li - 0.5) * pl
        ddy = max(v1 - g0y, 0.0, g0y - (v1 + pl))
        if not perlens:
            _load(cury, rows, sy)
        for lj in range(j0, j1 + 1):
            sx = lj - j0
            if facx[sx] == 0.0:
                continue
            u1 = (lj - cx0 - 0.5) * pl
            ddx = max(u1 - g0x, 0.0, g0x - (u1 + pl))
            if ddx * ddx + ddy * ddy > reach * reach:
                continue
            if perlens and focus:
                if not _rotated_axes(geo, sc, li, lj, spot, curx, cury, tmp):
                    cnt[_ST_BIG] += 1.0
                    continue
                nax = nay = 0
            elif perlens:
                if not approx:
                    cnt[_ST_REFUSED] += 1.0
                    continue
                fac = fac0 * facx[sx] * facy[sy]
                for sa in range(nsub):  # the lenslet's nsub x nsub sub-squares, one image each
                    for sb in range(nsub):
                        status, nax, nay = _lenslet_axes(geo, sc, li, lj, sa, sb, nsub, spot, curx, cury, tmp)
                        if status < 0:
                            cnt[_ST_BIG] += 1.0
                        if status > 0:
                            _lenslet_image(geo, sc, spot, fac, curx, nax, cury, nay, work, chunk, cnt)
                continue
            else:
                _load(curx, cols, sx)
                nax, nay = cols[4][sx], rows[4][sy]
            fac = fac0 * facx[sx] * facy[sy]
            _lenslet_image(geo, sc, spot, fac, curx, nax, cury, nay, work, chunk, cnt)


@njit(parallel=True, fastmath=False, error_model="numpy", cache=True)
def _render_kernel(parts, chunks, geo, buf, psz, nlmax, stats, quad):  # pragma: no cover - jitted
    """Render particles ``order[starts[c]:ends[c]]`` of chunk c into its rows of the image; chunks in parallel.

    ``parts``: (px, py, pz, wt, order), the particles' positions (mm), expected intensities and
    sort order; ``chunks``: (starts, ends, boff, brow0, brow1). ``buf`` is the flat float64
    image; chunk c owns ``buf[boff[c, 0]:boff[c, 1]]``, image rows ``brow0[c]..brow1[c]`` (the
    caller passes chunks with disjoint rows only).

    Everything accumulates, so a chunk done in consecutive pieces (one call per
    piece) sums in the same order as in one piece. ``stats[c]`` accumulates the
    ``_ST_*`` counters (intensity expected / on the sensor / on the lenslet array /
    outside the chunk's rows (must stay 0), lenslets refused (rotated grid out of
    focus), lenslet images, interior ones, arc nodes, band nodes, patches too big).
    Each particle is :func:`_render_particle`, with the quadrature ``quad`` (:data:`_QUAD_EXACT`).
    """
    px, py, pz, wt, order = parts
    starts, ends, boff, brow0, brow1 = chunks
    rotated = geo[_G_SIN] != 0.0 or geo[_G_COS] != 1.0
    for c in prange(starts.shape[0]):
        scr = _scratch(geo, psz, nlmax, quad)
        cnt = np.zeros(_ST_SIZE)
        chunk = (buf[boff[c, 0] : boff[c, 1]], brow0[c], brow1[c])  # the chunk's rows of the image
        for idx in range(starts[c], ends[c]):
            i = order[idx]
            w = wt[i]
            cnt[_ST_W] += w
            if w == 0.0:
                continue
            _render_particle(geo, rotated, px[i], py[i], pz[i], w, scr, chunk, cnt)
        for q in range(_ST_SIZE):
            stats[c, q] += cnt[q]


# ------------------------------------------------------------------ wrappers
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
    camera: PlenopticCamera,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    n_chunks: int,
    sm: float,
    sl: float,
    imp: CameraImperfections | None = None,
) -> tuple[Any, ...]:
    """Sort order, chunk bounds, chunk row ranges, the scratch patch size and the most lenslets per axis
    (``imp``: the imperfections the kernel applies, as in :func:`_particle`)."""
    so, si, fm, fl = camera.so, camera.si, camera.main_focal_length, camera.lenslet_focal_length
    rad, pl, pp = camera.aperture_diameter / 2.0, camera.lenslet_pitch, camera.pixel_pitch
    d = so + z
    c1 = 1.0 / d - 1.0 / fm
    if imp is None or imp.ideal:
        yc = -(si + fl) * y / d  # image centre of the particle on the sensor (y up)
        rho = rad * fl * np.abs(c1)
        reach = rad * np.abs(1.0 + si * c1) + _K * sm
        half = reach + pl * math.sqrt(0.5) + rho + _K * sl + 2.0 * pp
    else:  # the same with the gap, tilt and scatter of _particle (a lenslet centre within reach of the spot)
        gap = imp.gap(camera)
        tlx, tly = imp.sensor_tilt_x * 1e-3, imp.sensor_tilt_y * 1e-3
        sip = si - tly * si * x / d - tlx * si * y / d
        lsc = 1.0 + sip * c1
        q = 1.0 - gap / fl
        beta = gap * c1 + q * lsc
        rho = rad * np.abs(beta)
        if float(rho.min()) <= 1e-9 * pl:
            raise RaytraceError(
                f"camera.imperfections.lenslet_gap_error = {imp.lenslet_gap_error!r}: a particle at "
                f"z = {float(z[np.argmin(rho)]):.6g} mm is imaged by the lenslets onto a point of the sensor "
                "(its aperture image has no size); the exact method cannot render it (use method='montecarlo')"
            )
        yc = -((gap / fl) * sip + gap + q * sip) * y / d + gap * tlx
        reach = rad * np.abs(lsc) + _K * sm
        table = imp.scatter(camera)
        scat = 0.0 if table is None else float(np.abs(table).max())
        half = (gap / fl) * (reach + pl * math.sqrt(0.5) + scat) + rho + _K * sl + 2.0 * pp
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
    nlmax = min(math.ceil(2.0 * float(reach.max()) / pl) + 3, max(camera.n_lenslets_x, camera.n_lenslets_y))
    return order, bounds, r0, r1, psz, nlmax


def _waves(r0: np.ndarray, r1: np.ndarray) -> list[list[int]]:
    """Group chunks into waves of pairwise disjoint row bands [r0, r1] (greedy, in chunk order)."""
    waves: list[list[int]] = []
    for c in range(r0.size):
        for wave in waves:
            if all(r1[c] < r0[d] or r1[d] < r0[c] for d in wave):
                wave.append(c)
                break
        else:
            waves.append([c])
    return waves


def _memory(camera: PlenopticCamera, n_particles: int, psz: int, nlmax: int, n_chunks: int) -> int:
    """The float64 image, the particle arrays (x, y, z, weight, order and copies) and each chunk's scratch."""
    scratch = 8 * (3 * psz * psz + 6 * nlmax * psz + 2 * nlmax * 24 + 3 * 5 * 512 + 4096)
    return int(8 * camera.n_pixels_x * camera.n_pixels_y + n_particles * 8 * 8 + n_chunks * scratch)


def exact_memory_estimate(
    camera: PlenopticCamera, particles: xr.Dataset, n_chunks: int = DEFAULT_CHUNKS, *, diffraction: bool = True
) -> int:
    """Bytes :func:`render_exact` allocates: the float64 image, the particle arrays and the per-chunk scratch."""
    x, y, z, _ = _particle_arrays(camera, particles)
    _, bounds, _, _, psz, nlmax = _layout(camera, x, y, z, n_chunks, *_blurs(camera, diffraction, None))
    return _memory(camera, x.size, psz, nlmax, bounds.size - 1)


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
    sigmas: tuple[float, float] | None = None,
    imperfections: CameraImperfections | Mapping[str, Any] | None = None,
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
        The camera. A lenslet grid rotated by more than ``_ROT_APPROX`` (0.005 rad) is
        supported for in-focus particles only (e.g. the pinhole image); otherwise a
        :class:`RaytraceError` is raised. Smaller rotations out of focus are rendered to
        first order in the angle (module docstring).
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
    sigmas : tuple of float, optional
        (σm, σl) in mm instead of the camera's diffraction blurs (``diffraction``
        is then ignored); :func:`render_pinhole_exact` uses it.
    imperfections : CameraImperfections or mapping, optional
        What the imaging camera does differently from ``camera``
        (:mod:`lfstudy.simulate.imperfections`); None or all-ideal: the ideal image, bit for bit.

    Returns
    -------
    xarray.DataArray
        ``intensity`` over (``row``, ``col``), float64 and >= 0, with the coords and
        camera attributes of ``render``, ``method = "exact"`` and the accounting of
        the expected intensity: traced, recorded, missing the lenslet array, falling
        outside the sensor, and the rounding residue below zero that was clipped
        (``intensity_clipped_negative``, ~1e-12 of the total).
    """
    n = _check_rays(rays_per_particle)
    x, y, z, inten = _particle_arrays(camera, particles)
    if not isinstance(n_chunks, (int, np.integer)) or isinstance(n_chunks, bool) or n_chunks < 1:
        raise RaytraceError(f"n_chunks = {n_chunks!r}: must be an integer >= 1")
    imp = resolve(imperfections)
    nominal, camera = camera, imp.imaging_camera(camera)  # the lenslet grid the light meets
    sm, sl = _blurs(camera, diffraction, sigmas)
    x, y = imp.distort(nominal, x, y, z)  # the light cone turns with its chief ray; Ω stays the true one
    order, bounds, r0, r1, psz, nlmax = _layout(camera, x, y, z, int(n_chunks), sm, sl, imp)
    ncol = camera.n_pixels_x
    k = bounds.size - 1
    need = _memory(camera, x.size, psz, nlmax, k)
    if need > max_image_bytes:
        raise RaytraceError(
            f"render_exact: estimated memory {need / 1e9:.3g} GB (float64 image of {camera.n_pixels_y} x {ncol} px "
            f"+ particle arrays) exceeds max_image_bytes = {max_image_bytes / 1e9:.3g} GB; raise the limit"
        )
    wt = _weights(
        camera, particles, n, inten, solid_angle_correction=solid_angle_correction, match_ray_counts=match_ray_counts
    )
    geo = _geometry(
        camera,
        sm,
        sl,
        gap=imp.gap(camera),
        tilt=(imp.sensor_tilt_x * 1e-3, imp.sensor_tilt_y * 1e-3),
        scatter=imp.scatter(camera),
    )
    # Chunk c writes rows r0[c]..r1[c] of the image itself: its slice boff[c]..boff[c + 1] of the flat image.
    image = np.zeros((camera.n_pixels_y, ncol))
    flat = image.reshape(-1)
    boff = np.stack([r0 * ncol, (r1 + 1) * ncol], axis=1).astype(np.int64)
    stats = np.zeros((k, _ST_SIZE))
    waves = [np.array(w, dtype=np.int64) for w in _waves(r0, r1)]
    parts = (x, y, z, wt, order)
    with tqdm(total=x.size, desc="exact rendering", unit="particle", disable=not progress, mininterval=1.0) as bar:
        for p in range(_PIECES):
            starts = bounds[:-1] + (bounds[1:] - bounds[:-1]) * p // _PIECES
            ends = bounds[:-1] + (bounds[1:] - bounds[:-1]) * (p + 1) // _PIECES
            for w in waves:  # disjoint row bands within a wave: its parallel chunks never write one pixel
                st = np.zeros((w.size, _ST_SIZE))
                chunks = (starts[w], ends[w], boff[w], r0[w], r1[w])
                _render_kernel(parts, chunks, geo, flat, psz, nlmax, st, _QUAD_EXACT)
                stats[w] += st
            bar.update(int((ends - starts).sum()))
    tot = stats.sum(axis=0)
    if tot[_ST_REFUSED] > 0:
        raise RaytraceError(
            f"render_exact: camera.lenslet_rotation = {camera.lenslet_rotation!r} rad (with "
            f"camera.imperfections.lenslet_rotation) and {int(tot[_ST_REFUSED])} lenslet images of out-of-focus "
            f"particles; the exact method needs |rotation| <= {_ROT_APPROX} rad unless every particle is in "
            "focus (use method='montecarlo' for larger rotations)"
        )
    if tot[_ST_SPILL] > 1e-9 * max(tot[_ST_W], 1e-300) or tot[_ST_BIG] > 0:
        raise RuntimeError(
            f"render_exact: {tot[_ST_SPILL]:.3g} of the intensity fell outside its chunk's rows and "
            f"{int(tot[_ST_BIG])} patches exceeded the scratch size (a bug)"
        )
    # Pixels the light does not reach sum line integrals that cancel: what is left is rounding of
    # either sign (|value| ~1e-12 of a lit pixel). An expected intensity is >= 0: clip, and say how much.
    clipped = -float(image[image < 0.0].sum())
    np.maximum(image, 0.0, out=image)
    attrs: dict[str, Any] = {
        "units": "1",
        "long_name": "simulated plenoptic raw image (expected sum of ray intensities)",
        **nominal.to_attrs(),
        "method": "exact",
        "rays_per_particle": n,
        "n_particles": int(x.size),
        "solid_angle_correction": int(bool(solid_angle_correction)),
        "match_ray_counts": int(bool(match_ray_counts)),
        "diffraction": int(bool(diffraction if sigmas is None else sm > 0.0 or sl > 0.0)),
        "sigma_lenslet_plane": nominal.sigma_lenslet_plane if sigmas is None else sm,
        "sigma_sensor_plane": nominal.sigma_sensor_plane if sigmas is None else sl,
        "n_chunks": int(k),
        "lenslet_images": int(tot[_ST_LENS]),
        "lenslet_images_interior": int(tot[_ST_INTERIOR]),
        "arc_nodes": int(tot[_ST_NODES]),
        "intensity_traced": float(tot[_ST_W]),
        "intensity_recorded": float(tot[_ST_IN] + clipped),
        "intensity_lost": float(tot[_ST_W] - tot[_ST_IN] - clipped),
        "intensity_lost_lenslet_array": float(max(tot[_ST_W] - tot[_ST_ALL], 0.0)),
        "intensity_lost_outside_sensor": float(max(tot[_ST_ALL] - tot[_ST_IN], 0.0)),
        "intensity_clipped_negative": clipped,
        "y_direction": "up; row 0 is the top",
    }
    if not imp.ideal:
        attrs.update(imp.to_attrs())
    return xr.DataArray(image, dims=("row", "col"), coords=_sensor_coords(nominal), name="intensity", attrs=attrs)


def render_pinhole_exact(
    camera: PlenopticCamera,
    *,
    fnumber: float = 16,
    count: int = 500_000,
    rays_per_point: int = 100,
    seed: int = 0,
    nodes: int = _PINHOLE_NODES,
    imperfections: CameraImperfections | Mapping[str, Any] | None = None,
    **kwargs: Any,
) -> xr.DataArray:
    """The calibration pinhole image (sec. 5.1): the expected image of its uniform field.

    :func:`lfstudy.simulate.raytrace.render_pinhole` images ``count`` random
    points of :func:`~lfstudy.simulate.particles.pinhole_field` (a uniform
    sample of the object focal plane) at ``fnumber``, ``rays_per_point`` rays
    each. This is its expected value over the rays *and* the point positions:
    the image of the uniform field of the same density, with no sampling noise
    (``seed`` is not used; it is kept for the Monte-Carlo's signature).

    In focus a point's lenslet-plane image is ``L = M·p``; the ray passes the
    lenslet that ``L`` plus the diffraction shift η (σm) falls in, and lands on
    the disc centred at ``c_k − fl·p/so`` (eq. 4.4) blurred by σl. Integrating the
    uniform field over p for a fixed lenslet-plane point q = L + η turns η into
    a shift of that disc by ``fl·η/si``, i.e. one more Gaussian blur:
    lenslet k's image is the integral over q in its (sharp) square of the disc
    blurred by ``σl' = sqrt(σl² + (σm·fl/si)²)``. That integrand is smooth in q
    (the disc moves by ±fl·pl/(2·si), a fraction of σl' in pixels), so a
    ``nodes`` x ``nodes`` Gauss–Legendre rule per lenslet computes it: each node
    is a point of the field rendered by :func:`render_exact` with
    ``sigmas=(0, σl')`` (it reaches its own lenslet only), carrying the
    field's intensity over its share of the square. The solid angle (eq. 4.14)
    is taken at the node rather than averaged over η (a relative change below
    1e-9 here). Extra keyword arguments go to :func:`render_exact`.

    ``imperfections`` (:mod:`lfstudy.simulate.imperfections`): the nodes lie on the imaging
    camera's lenslet squares (rotation, offset, pitch); a gap g != fl moves the disc by
    ``heff·η/si`` (heff = g + (1 − g/fl)·si) instead of ``fl·η/si``; with distortion each node is
    the image of its undistorted object point, whose share of the uniform field is divided by
    the distortion's area ratio. A tilted sensor leaves the points slightly out of focus; the
    σm-fold above then holds to the order of the spot radius over σm.

    Returns
    -------
    xarray.DataArray
        As :func:`render_exact`, with ``pinhole_fnumber``, ``pinhole_count`` and
        ``pinhole_nodes`` attributes.
    """
    from lfstudy.simulate.particles import make_field, pinhole_spans

    n = _check_rays(rays_per_point, "rays_per_point")
    if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or count < 1:
        raise RaytraceError(f"count = {count!r}: must be an integer >= 1 (points of the pinhole field)")
    if not isinstance(nodes, (int, np.integer)) or isinstance(nodes, bool) or not 1 <= nodes <= _NG_MAX:
        raise RaytraceError(f"nodes = {nodes!r}: allowed range is 1..{_NG_MAX} (Gauss–Legendre nodes per axis)")
    imp = resolve(imperfections)
    nominal = camera.with_(fnumber=float(fnumber))
    cam = imp.imaging_camera(nominal)
    sm, sl = _blurs(cam, kwargs.pop("diffraction", True), None)
    if imp.lenslet_gap_error == 0.0:
        sl_eff = math.hypot(sl, sm * cam.lenslet_focal_length / cam.si)
    else:
        gap = imp.gap(cam)
        sl_eff = math.hypot(sl, sm * (gap + (1.0 - gap / cam.lenslet_focal_length) * cam.si) / cam.si)
    # Nodes of the rule on every lenslet's square (grid frame offsets, rotated into the sensor frame).
    xi, wi = _GL_X[nodes, :nodes], _GL_W[nodes, :nodes] / 2.0
    half = cam.lenslet_pitch / 2.0
    gx, gy = (a.ravel() * half for a in np.meshgrid(xi, xi))
    w = np.outer(wi, wi).ravel()
    c, s = math.cos(cam.lenslet_rotation), math.sin(cam.lenslet_rotation)
    cx, cy = (a.reshape(-1, 1) for a in cam.lenslet_centers())
    lx = (cx + (c * gx - s * gy)).ravel()
    ly = (cy + (s * gx + c * gy)).ravel()
    # Object-plane points p = L/M (M = −si/so in focus) and their share of the field's intensity.
    xs, ys = pinhole_spans(camera)
    cell = (cam.lenslet_pitch * cam.so / cam.si) ** 2
    inten = np.tile(w * (count * cell / (xs * ys)), cx.size)
    mag = -cam.si / cam.so
    if imp.distorted:  # the object point whose distorted image is the node, and its share of the field
        h = math.hypot(cam.sensor_width / 2.0, cam.sensor_height / 2.0)
        rho = np.hypot(lx, ly) / h
        rho_u, area = imp.undistort_radius(cam, rho)
        scale = np.divide(rho_u, rho, out=np.ones_like(rho), where=rho > 0.0)
        lx, ly, inten = lx * scale, ly * scale, inten / area
    field = make_field(lx / mag, ly / mag, np.zeros_like(lx), inten)
    img = render_exact(nominal, field, n, sigmas=(0.0, sl_eff), imperfections=imp, **kwargs)
    img.attrs.update(
        long_name="simulated pinhole calibration image (expected, uniform field)",
        pinhole_fnumber=float(fnumber),
        pinhole_count=int(count),
        pinhole_nodes=int(nodes),
        sigma_lenslet_plane=sm,
        sigma_sensor_plane=sl,
        seed=int(seed),
    )
    return img
