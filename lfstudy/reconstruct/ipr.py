"""IPR: iterative particle reconstruction with the exact camera model (beyond thesis sec. 5.6).

Iterative Particle Reconstruction (Wieneke 2013, Meas. Sci. Technol. 24 024008) with the
position refinement ("shaking") of Shake-the-Box (Schanz, Gesemann & Schröder 2016, Exp.
Fluids 57:70): the particles are the unknowns, not the voxels. Their expected image is
:func:`lfstudy.simulate.exact.render_exact`'s, the one forward model the study trusts, here
used to fit the data.

Forward model and where it is compared
--------------------------------------
The registered light field is the raw image cut into integer pixel blocks at the
*calibrated* lenslet centres (:func:`lfstudy.lightfield.register`; no pixel is resampled).
IPR puts its samples back on the sensor (``raw[row0 + prow, col0 + pcol]``) and compares
there, on exactly the pixels the light field holds (the rest is masked out). The model
camera is the nominal camera (optics, sensor) with its lenslet grid replaced by the one
fitted to the calibrated centres (pitch and offset by least squares, :func:`calibrated_camera`),
never the simulator's true grid: with a calibration error the model is wrong exactly as an
experiment's would be. The exact renderer handles rotated grids only in focus, so a
calibration whose rotation moves a lenslet by more than ``_MAX_ROTATION_PX`` pixels at the
array's edge is refused; below that the grid is taken as unrotated (the residual is in the
result's attrs, ``grid_residual_px``).

Per-particle image. A particle reaches a few dozen lenslets: its image is rendered into a
patch (its bounding box on the sensor, from :func:`lfstudy.simulate.exact`'s layout bound,
plus a margin) by the exact renderer's own per-lenslet kernels, with the sensor cropped to
the patch (the cell edges move by whole pixels, so the patch is the full render's pixels up
to rounding: the tests bound the difference by 1e-9 of the patch's peak). The fit uses a
coarser quadrature of the same integrals by default (``image_accuracy="fast"``: arc panels with
about half the Gauss–Legendre nodes, up to 16 blur widths long, 8-node band integrals, Gaussian
tails cut at 4 σ instead of 6): every image is within 1e-4 of its patch's peak and 1e-5 of its
sum of the exact one (the tests, over particles in and out of focus, at 12 depths, with spots on
and near lenslet edges; measured on the bench's 3150 images: 2.0e-5 and 1.9e-6), well below the
shot noise of a 25,000-photon particle. ``image_accuracy="exact"`` gives the renderer's own images.
Measured (``benchmarks/bench_particle_image.py``, 450 particles x 7 images of a 300 x 300 px crop at
0.005 ppp, one thread, load ~5 on 2 cores): 0.219 ms of CPU per exact image, 0.148 fast (x1.47). The
fit's results do not move beyond the seed noise (``bench_ipr.py --threads 1 --compare
image_accuracy=exact``, fast / exact, load 5–7 on 2 cores): 300 x 300 px at 0.005 ppp, seed 7: found
79.6 / 79.6 %, ghosts 18.1 / 18.4 %, rms x,y 0.070 / 0.071 voxel, z 0.145 / 0.144 voxel, CPU 20.4 /
22.7 s; seed 8: found 80.4 / 79.8 %, ghosts 20.0 / 20.3 %, rms 0.071 / 0.069 and 0.135 / 0.134
voxel, CPU 20.2 / 23.2 s; 400 x 400 px at 0.001 ppp, seed 7: the same 156 particles' figures (88.1
%, 9.6 %, 0.047 and 0.090 voxel), CPU 25.3 / 25.7 s (the MART candidates dominate there). Where the
rest of an image's time goes (same images, exact quadrature): ~20 % the particle's layout, the
separable interior lenslets and the patch memory, ~25 % the straight cuts and carries of the
lenslets on the spot's rim, ~30 % placing the arcs' panels and nodes (a crossing per pixel edge),
~25 % the nodes' blurred-edge sums; the quadrature shortens the last two only. A patch is mostly
empty (5.5 % of its pixels lit, the lit bounding box 43 % of its area).

Fit. Each outer iteration renders, for every particle, its image U and the images at
±δ in x, y and z (central differences D_x, D_y, D_z; δ = ``shake`` voxels); then, particle
after particle (Gauss–Seidel, as Wieneke's shaking), on a linearised copy of the residual, the
particle's current image is added back and the linear least-squares problem
``min ‖R_p − I'·U − Σ_k a_k·D_k‖²`` over (I', a) is solved (4 x 4 normal equations,
Levenberg–Marquardt damped); the step Δ_k = a_k/I' is clipped to ``max_step`` voxels. The
move is then chosen on the exact residual, again particle after particle: among the exact
images at the current position, the six ±δ trial positions and the Gauss–Newton step (rendered),
the one whose best intensity lowers the residual most is taken (the current one unless another
is strictly better), so no move raises the residual; a linearisation that overshoots is
replaced by the best trial (Wieneke's shaking). After each iteration particles weaker than
``min_intensity`` times the median are removed as ghosts, and pairs closer than half a voxel
are merged. The position uncertainty is the fit's covariance σ²·(JᵀJ)⁻¹ with σ² the patch's
residual variance. With ``jacobian="forward"`` the Jacobian is taken from the three +δ images
(forward differences) and the choice is among the current position, those three and the step.

Polish. Near the focal plane a particle's defocus spot on the lenslet array is smaller than a
lenslet: its image falls behind one to four lenslets and changes little (inside one lenslet, not
at all) as the particle moves within them, so the residual is flat there up to the noise and the
fit stops anywhere on the flat. On the Table 4.3 camera (spot radius 0.125·|z| mm, pitch 0.125 mm)
the missed particles and the ghosts were these: 12 of the 18 missed at 0.001 ppp (seed 3) had
|z| < 0.5 mm (of the 15 there; none missed beyond |z| = 2 mm), and each of the 14 ghosts was the fit
of a missed particle within 1.5 voxel, 13 of them at |z| < 0.75 mm, mostly 0.5–0.7 voxel off in z;
started at the true positions the same fit keeps 96 % within half a voxel (2 % ghosts). After the iterations,
``polish`` rounds move each particle whose spot radius is at most ``_POLISH_SPOT`` pitches to the
likelihood-weighted mean of a stencil around it (x, y ±0.25 voxel, z ±0.25, ±0.5 voxel; weights
exp(−ΔC/2σ²), ΔC the rise of the exact ‖R‖² at the best intensity over the stencil's lowest, σ² the
residual variance per pixel on the particle's patch; the others held fixed, then the intensities
refitted at the new positions): where the residual is sharp that is the minimum, where it is flat
the middle of the flat, the estimate of least expected error. Pairs it brings within half a voxel
are merged. ``sigma_*`` and ``residual`` stay those of the last iteration.

Split (``split`` rounds after the polish; off by default). Each particle brighter than ``split_ratio`` times
the median is tried as two at ±s/2 along x, y or z (s = 0.5–2 voxels, two least-squares intensities), the best
pair shaken on the exact residual (each in turn to the best of ±0.25, then ±0.125 voxel, the other held) and
kept where both are above the ghost floor, half a voxel apart, and ‖R‖² falls below the single particle's (given
the same moves) by more than ``split_penalty``·σ² (σ² the pair's residual variance weighted by its image squared;
a spurious particle's 4 parameters take ~4σ², the search over 12 starts more; 16 chosen). ``bench_ipr --compare
split=1`` (found / ghosts %, 1 thread, load 2–6 on 2 cores; seeds 3, 4 chose ratio 1.3 and penalty 16, 10–12 held
out): 0.005 ppp, 300 x 300 px, seeds 3 / 4 / 10 / 11 / 12: 88.4 / 14.5, 86.7 / 12.0, 83.3 / 15.1, 85.8 / 15.3, 83.1
/ 14.9 (without: 87.3 / 14.3, 84.4 / 12.2, 82.0 / 14.7, 84.4 / 14.6, 81.6 / 15.3); 0.001 ppp, 400 x 400 px: found
+0 to +0.6 points, ghosts +0 to +1.2 (seed 12: two splits, both ghosts; 800 x 800 px: 90.3 / 7.6 -> 90.5 / 8.0);
CPU +0–10 %. It stays off: ghosts rose in 4 of the 7 held-out fits. Most misses are not such pairs: at 0.001 ppp
single particles near focus fitted 0.55–0.7 voxel off in z (10 of seed 3's 12), at 0.005 ppp ghosts beside one
found and one missed particle. Nor does moving those singles along z alone help (a scan of ±1.5 voxel in 0.125
steps to the lowest exact ‖R‖², the others held; tried on branch h45, not merged): found +0 / +0 / −0.6 points on
held-out seeds 10–12 at 0.001 ppp. Given the other particles, most of them already sit at the residual's minimum
along z (by 10²–10³ σ² over the true depth), the rest on a stretch ~1.2 voxel long flat to a few σ² with the true
depth at its edge: the fix has to move a particle with its neighbours.

The residual is rendered once (the data, before the first candidate is placed) and then kept
exact incrementally: every change subtracts or adds back an exact image (the choice subtracts the
chosen one, removed ghosts and rejected residual candidates are added back), so an iteration costs
8 exact images per particle with central differences (the current one, six trials, the step) and
5 with forward ones (a fresh render of the final list agrees to 1e-9, see the tests).

Candidates: the peaks of a MART volume (:func:`lfstudy.reconstruct.mart.mart`) above
``peak_threshold`` of its maximum, on the case grid refined ``_REFINE_XY`` x ``_REFINE_XY`` x
``_REFINE_Z`` times (on the case grid, one voxel per lenslet, a 0.005 ppp field has more
particles than voxels and MART's peaks find 7 % of them within half a voxel; on the refined grid
48 %). With ``residual_candidates`` more are taken after each of the first iterations from the
MART volume of the positive residual (Wieneke's "add candidates from the residual"), except
within ``_MIN_SEPARATION`` voxels of a particle. Every candidate volume is reconstructed on one
MART plan (:func:`lfstudy.reconstruct.mart.mart_plan`: the refined grid's weight tables and the
views' coverage, made once per fit; each volume is byte for byte that of a MART run of its own);
the residual's volumes take ``residual_mart_iterations`` MART iterations (0: the multiplicative
first guess alone, four times cheaper, but see the measurements below). Once a residual round adds
fewer new particles than ``residual_candidates_min_gain`` of the list, the later rounds are skipped:
the residual then changes little from round to round, and its next volumes give the same peaks, which
are rejected again (fitted intensity below the ghost floor, or within ``_MIN_SEPARATION`` of a
particle). The attrs ``candidates_added`` (new particles per round run) and
``skipped_candidate_rounds`` say what happened. ``residual_volume`` chooses the residual rounds' volume:
``mart`` (the default, above), ``case`` (MART on the case's own grid: the residual holds only the missed
particles, few enough for one voxel per lenslet, on its own plan of 1/18 the voxels) or ``stack`` (the
residual's focal stack on the refined grid, the additive back-projection :func:`_stack_volume`, no MART
iteration). Neither holds the default's accuracy on the demo camera (``bench_ipr.py --camera demo``, figures
in its docstring; seeds 3, 4 held out): ``case`` loses 2.6–5.7 points of the particles found, ``stack`` 0.3–2.1
points and adds 0.6–2.3 points of ghosts, for 7–20 % less CPU; the candidate volumes take 15–30 % of the fit's
time there, the particle images 60–75 %.

Measured (``benchmarks/bench_ipr.py --crop 400 400``, Table 4.3 camera, seeds 0 and 1 used to
set the defaults): 0.001 ppp 88.8 % found within half a voxel, 8–10 % ghosts; 0.005 ppp
80–81 % found, 15–18 % ghosts; 17–50 s per crop on 2 shared cores. With the polish (found / ghosts
in %, ``--compare polish=0`` in the same run; seeds 3 and 4 used to choose it, 5–7 held out; 1 thread,
load 1–5 on 2 cores): 0.001 ppp, 400 x 400 px, seeds 3 / 4 / 5 / 6 / 7: 92.5 / 5.2, 93.1 / 5.8, 89.4 /
8.4, 87.5 / 10.1, 88.1 / 9.6 (without: 88.8 / 9.1, 90.6 / 8.4, 88.1 / 9.7, 86.2 / 10.7, 88.1 / 9.6);
0.005 ppp, 300 x 300 px: 87.3 / 14.3, 84.4 / 12.2, 81.8 / 14.3, 80.4 / 21.0, 79.1 / 18.6 (without:
85.3 / 15.9, 82.4 / 15.0, 80.2 / 16.0, 79.1 / 22.3, 79.6 / 18.4). It about doubles the particle
images (CPU +4–8 % at 0.001 ppp, +28–37 % at 0.005 ppp) and raises the final residual a little
(0.246 -> 0.274 at 0.005 ppp, seed 5: the weighted mean is not the residual's minimum). What is left:
particles whose image the crop cuts (``bench_ipr`` splits found into those whose whole image is on
the crop and the others: 93.1 % against 84.9 % at 0.001 ppp, seed 5; 40–50 % of a 400 x 400 px crop's
particles, about 5 % of the full sensor's), pairs behind one lenslet near the focal plane (at 0.005 ppp
most near-focus misses have a neighbour within a voxel and the fit one particle of twice the
intensity) and, at 0.005 ppp, the ghosts. Seed 6 at 400 x 400 px calibrates a lenslet pitch 5e-7 mm
short of the nominal 0.125 mm; the model camera used to re-derive its "matched" main-lens f-number from
that pitch and round it up to the next stop (f/2.8 for f/2: a smaller aperture image, half the light in
the wrong place, the residual at 0.69, 87.5 % found). :func:`calibrated_camera` now keeps the nominal
f-number: seed 6 finds 90.6 %, 8.4 % ghosts, residual 0.46 -> 0.33 (2 threads, quiet machine). Where the time goes
(``--crop 300 300 --ppp 0.005``, seed 7, 1 thread, load ~3 on 2 cores): 7–11 s of 18 s CPU in the 7 candidate MART
volumes on the refined grid (the first and one per residual round run), 8.9 s in 57,400 particle images (the
shake's 30,640, 6.4 s; the polish's 25,110, 2.3 s: near focus an image is cheap), the fit kernels ~2 s. The plan
(the tables and coverage made once per fit, not per volume) takes 10 % off the fit's CPU time (seeds 7 and 8: 32.2
-> 29.0 s and 31.7 -> 28.9 s of CPU, the MART part 13 % and 9 %; the same particles, byte for byte). Cheaper
residual volumes trade quality for time (CPU time; seeds 7 / 8 / 9 / 10, change of found in points):
``residual_mart_iterations=0`` x0.59–0.82, found −0.3 / −1.6 / −5.1 / −4.4 (ghosts up to +4.6);
``residual_candidates=5`` x0.70–0.74, found −0.3 / +0.2 / −1.1 / −1.1, ghosts −0.2 / −1.2 / +0.2 / +0.2 (the
defaults are unchanged).
``residual_plane_step=2`` reconstructs the residual's volumes on every other plane of the candidate
grid, on views into the same tables (no new memory): each residual volume costs half (seed 7, the
same ten residual light fields, 1 thread: 9.7 -> 4.7 s CPU), the fit x0.67–0.73 of the defaults' CPU
time (seeds 7 / 8 / 9 at 0.005 ppp: 24.0 -> 17.5, 22.6 -> 15.8, 22.5 -> 15.5 s; 400 x 400 at 0.001
ppp, seed 7: 25.7 -> 17.2 s), found −1.6 / +0.6 / −0.9 and +0.7 points, ghosts +1.8 / −0.5 / −0.3 and
+0.5: the trade of ``residual_candidates=5``, so the default stays 1. A separate 3 x 3 x 1 grid on the
case's own planes did better on seed 7 (found −0.3, ghosts +0.5, CPU x0.74) but adds half the tables'
memory. Skipping the residual rounds that repeat the last one (``residual_candidates_min_gain``; found /
ghosts in %, CPU s, against ``--compare residual_candidates_min_gain=0`` in the same run, 1 thread, load 1–4
on 2 cores; seeds 5–9 seen while choosing the value, 10 held out): with 0 the rounds after the fourth add
0–2 particles each at 0.001 ppp and 0–10 at 0.005 ppp (every other peak of those volumes is rejected again).
0.01 stopped too early (found −1.1 points at 0.005 ppp, seed 6, whose rounds 6–10 still added 11 particles;
−0.6 at 0.001 ppp, seed 8), 0.003 too (seed 9 at 0.005 ppp: stopped after a round adding one of 419, found
84.7 -> 84.0 %, ghosts 13.4 -> 14.1 %), so the default is 0.001 (the value chosen, then checked on seed 10):
on these crops (150–450 particles) the rounds stop after one that adds none; on a full frame (~100 times the
particles) it stops after a round adding fewer than 0.1 % of the list, which the crops cannot resolve (one
particle is 0.2–0.7 % of theirs). 0.001 ppp, 400 x 400 px, seeds 5 / 6 / 7 / 8 / 9: 89.4 / 8.4, 90.6 / 8.5,
88.1 / 9.0, 86.2 / 9.3, 90.6 / 5.8 (with 0: 89.4 / 8.4, 90.6 / 8.4, 88.1 / 9.6, 86.2 / 9.9, 90.6 / 5.8), 4–6
of the 11 MART volumes, CPU x0.46–0.66 (13.8 / 14.7 / 15.8 / 15.8 / 11.6 s against 24.3 / 24.9 / 24.1 / 26.4
/ 25.1 s); 0.005 ppp, 300 x 300 px: only seed 7 has a round adding none (the sixth): 79.3 / 17.3 against
79.1 / 18.4, CPU 21.6 -> 17.0 s; seeds 5, 6, 8, 9 run every round (the fit of the defaults before). Seed 10:
0.001 ppp 93.8 / 3.8 either way, CPU 25.8 -> 13.4 s (three rounds of ten); 0.005 ppp every round (82.0 /
14.7). At 0.005 ppp the rounds keep adding a few particles to the end. Since then, once a round adds fewer
than ``residual_late_gain`` (0.01) of the list, the later volumes take one MART iteration (half a volume's CPU)
and add about what full ones would (seeds 10 / 11: 8 / 3 particles against 9 / 2; seed 8: none, the rounds then
stop, against 10) (found / ghosts %, CPU s, 1 thread, load 2–5, same run, 0 -> 0.01; seeds 7,
8 chose it: 79.3 / 17.3 both, 82.2 / 17.6 -> 82.0 / 17.4; held out, 0.005 ppp, 300 x 300 px: seed 10 82.0 / 14.7,
23.5 s -> 82.0 / 14.1, 21.0 s, seed 11 84.4 / 14.6, 22.6 s -> 84.7 / 14.6, 20.9 s; 0.001 ppp, 400 x 400, seed 10:
the same particles). ``shake_settle`` (the shake's active set; off): a particle whose last shake moved it less
than that (0.05 voxel tried), with nothing within ``_SETTLE_RADIUS`` (2) voxels moved, added or removed, sits out
up to 2 shakes: 15–40 % of the late shakes, CPU x0.84–0.86 held out, but ghosts +1.3 / +1.7 points, found −0.7 /
−0.8 (seeds 10 / 11, 0.005 ppp; 0.001 ppp the same found): at 0.005 ppp an image's box holds hundreds of others'
images, so a neighbour beyond 2 voxels still moves its residual. Seeds 7 / 8, CPU and found: woken by lateral
distance (any depth) within 2 voxels 1–3 % sat out, x0.92 / 1.00; within 1 voxel x0.90 / 0.98, −0.6 / −2.0; a
3-voxel radius, one shake at most x0.95 / 1.02, +0.3 / −0.4; always shaking the faint (< 0.5 median): no change.
What did not help: MART restricted to the lenslets the residual lights (at 0.005 ppp the
median lenslet holds 12–37 % of the brightest lenslet's positive-residual energy, at 0.001 ppp 3–8 %;
the residual's first guess is above 3 % of its maximum in 70–75 % of the voxels, so every lenslet's
beam box holds signal), nor pruning the voxels below 1 % of the maximum after one iteration (the
pruned volume still meets 6–100 % of the beam boxes); screened on seed 7's residuals against the full
volumes' peaks (388 over ten rounds; found / extra): every other view column 240 / 199, every other
view row 305 / 230, a 2 x 2 x 2 grid 298 / 136, a warm start from the previous residual's volume with
one iteration 317 / 166 (two: 361 / 140), against 363 / 110 on every other plane. Both
dominant costs scale with the frame: at this cost per particle a full Table 4.3 frame at 0.005 ppp
stays far above the issue's 10 minutes on 2 cores (~60 min on a quiet machine, x0.9 with ``residual_late_gain``:
seed 10's 21.5 s of CPU at 1 thread scale to 63 min, 24.0 s without to 70 min; the attrs ``seconds_*``,
``particle_images`` and ``mart_volumes`` hold the split).

Memory (``benchmarks/bench_ipr.py --memory``, the full Table 4.3 frame): the candidate plan dominates, the refined
grid's weight tables (4.03 GB: each plane's own beam width, int16 starts) and the four subsets' coverage (0.53 GB,
float32), then a MART volume's buffers (0.27 GB each in float64, no voxel-sized temporaries); IPR's peak 7.18 GB
(was 9.4 GB and more in one MART volume). The particle images go ``batch`` (256) particles at a time: a shake batch
of 2048 held 4.7 GB of patches there. At 0.01 ppp (the study's and ``bench_ipr``'s figures in the benchmarks'
docstrings) IPR's Q is above MART's, its valid vectors and RMS error not: 56-64 % of the particles found, 35-37 %
ghosts, nearly all misplaced fits of real particles within 1.5 voxels of one (pairs behind one lenslet).

Output: :func:`ipr_particles` returns the particle list; the method ``ipr`` returns the
volume on the grid rendered from the particles with :func:`render_particles` (Gaussians of
the case's truth σ, half a resolution cell, integrated over each voxel), so depth
calibration, PIV, errors and report run unchanged.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import numba
import numpy as np
import xarray as xr
from numba import njit, prange
from scipy import ndimage
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from lfstudy.optics import PlenopticCamera

# The fit's Gauss-Seidel kernels (numba), shared with image_model.py.
from lfstudy.reconstruct._shake_kernels import _accumulate_masked, _choose, _stencil, _sweep
from lfstudy.reconstruct.grid import ReconstructionGrid, default_voxel_z
from lfstudy.reconstruct.registry import (
    ReconstructionError,
    ReconstructionInputs,
    ReconstructionMethod,
    ReconstructionSize,
)
from lfstudy.reconstruct.truth import render_truth
from lfstudy.simulate._render_common import (
    _G_HH,
    _G_HW,
    _G_NCOL,
    _G_NROW,
    _blurs,
    _geometry,
    solid_angle,
)
from lfstudy.simulate.exact import _K, _QUAD_EXACT, _ST_BIG, _ST_SIZE, _ST_SPILL, _render_particle, _scratch

if TYPE_CHECKING:
    from lfstudy.reconstruct.image_model import ImageModel
    from lfstudy.reconstruct.mart import MartPlan

__all__ = [
    "IPR",
    "ipr",
    "ipr_particles",
    "particle_volume",
    "calibrated_camera",
    "particle_patches",
    "render_particles",
    "volumetric_frame",
]

_MAX_ROTATION_PX = 0.05  # largest lenslet displacement [px] a calibrated rotation may cause and be ignored
_MARGIN_PX = 3  # pixels added around each patch's layout bound (covers the ±δ trial positions)
_MIN_SEPARATION = 0.5  # residual candidates nearer an existing particle [voxels, per-axis scaled] are not added
_REFINE_XY = 3  # candidate MART grid: this many voxels per case voxel in x and y
_REFINE_Z = 2  # and in z
_GHOST_FROM = 0  # first iteration after which faint particles are removed
_JACOBIANS = ("central", "forward")  # finite differences of the position Jacobian
#: Where the residual rounds' candidates come from (``residual_volume``): ``mart`` MART on the refined candidate
#: grid, ``case`` MART on the case's own grid (18x fewer voxels on the default refinement), ``stack`` the residual's
#: focal stack on the refined grid (its additive back-projection, one pass over the tables, no iteration)
_RESIDUAL_VOLUMES = ("mart", "case", "stack")
#: Quadratures of the per-particle images (the order of :data:`lfstudy.simulate.exact._QUAD_EXACT`: arc nodes
#: ceil(base + dens·L) per panel of L blur widths, at least min; longest panel; nodes of the numeric band
#: integrals; Gaussian cut-off K; band half-width, in σ). "fast": max |fast − exact| <= 1e-4 of the patch's
#: peak and |Σ fast − Σ exact| <= 1e-5 of the sum (tests; measured 2e-5 and 2e-6), ~1.5x cheaper.
_QUAD = {
    "exact": _QUAD_EXACT,
    "fast": np.array([2.0, 0.75, 2.0, 16.0, 8.0, 4.0, 4.5]),
}
#: Particles per batch of images: a shake batch holds 7 images per particle, each its patch's box (the defocus spot
#: and a lenslet, ~200 x 200 px on average over the Table 4.3 camera's 7 mm depth, 5 % of it lit): 256 particles
#: take 0.59 GB (``bench_ipr.py --memory``), the 2048 before 4.7 GB, more than the candidate MART's tables
_BATCH = 256
_SETTLE_RADIUS = 2.0  # shake_settle: a particle moved, added or removed within this many voxels wakes the settled
_SETTLE_SKIPS = 2  # and a settled particle sits out at most this many shakes in a row
_LATE_MART_ITERATIONS = 1  # residual_late_gain: MART iterations of the later residual volumes
_POLISH_SPOT = 1.5  # the polish moves particles whose defocus spot (radius) is at most this many lenslet pitches
_POLISH_XY = (-0.25, 0.0, 0.25)  # the polish stencil's offsets [voxels] in x and y
_POLISH_Z = (-0.5, -0.25, 0.0, 0.25, 0.5)  # and in z
_POLISH_T = 1.0  # the polish's weights exp(−ΔC/(2·T·σ²)): T = 1 the Gaussian likelihood of the residual


# ------------------------------------------------------------------ the calibrated model camera
def calibrated_camera(camera: PlenopticCamera, centers: xr.Dataset) -> tuple[PlenopticCamera, dict[str, float]]:
    """The nominal camera with its lenslet grid fitted to the calibrated centres.

    The lenslet centres are the calibrated spot centres un-projected (``spot·si/(si + fl)``);
    an affine lattice ``c = o + A·(col, row)`` is fitted to the valid ones by least squares.
    The pitch is the mean of the two axes', the offset the one that puts the camera's own
    lattice (centred on its offset) on the fitted one.

    Returns
    -------
    camera : PlenopticCamera
        ``camera.with_(lenslet_pitch=..., lenslet_offset_x=..., lenslet_offset_y=..., lenslet_rotation=0)``
        with the nominal camera's main-lens f-number (never re-derived from the fitted pitch).
    info : dict
        ``grid_pitch_mm``, ``grid_offset_x_mm``, ``grid_offset_y_mm``, ``grid_rotation_rad`` (fitted,
        not used), ``grid_residual_px`` (largest distance of a calibrated centre from the model lattice).

    Raises
    ------
    ReconstructionError
        Too few valid centres, or a rotation the exact renderer cannot model out of focus.
    """
    for k in ("x", "y"):
        if k not in centers:
            raise ReconstructionError(f"centers lacks {k!r}: use lfstudy.lightfield.find_lenslet_centers")
    s = camera.si / (camera.si + camera.lenslet_focal_length)
    cx = np.asarray(centers["x"].values, dtype=np.float64) * s
    cy = np.asarray(centers["y"].values, dtype=np.float64) * s
    ok = np.asarray(centers["valid"].values, bool) if "valid" in centers else np.ones(cx.shape, bool)
    ok &= np.isfinite(cx) & np.isfinite(cy)
    if ok.sum() < 6:
        raise ReconstructionError(f"centers: {int(ok.sum())} valid lenslet centres; IPR needs at least 6")
    rows, cols = np.nonzero(ok)
    a = np.column_stack([np.ones(rows.size), cols, rows])
    (ax0, ax1, ax2), *_ = np.linalg.lstsq(a, cx[ok], rcond=None)
    (ay0, ay1, ay2), *_ = np.linalg.lstsq(a, cy[ok], rcond=None)
    pitch = 0.5 * (math.hypot(ax1, ay1) + math.hypot(ax2, ay2))
    rot = math.atan2(ay1, ax1)
    span_px = 0.5 * max(cx.shape) * pitch / camera.pixel_pitch
    if abs(rot) * span_px > _MAX_ROTATION_PX:
        raise ReconstructionError(
            f"centers: the calibrated lenslet grid is rotated by {rot:.3g} rad ({abs(rot) * span_px:.2g} px at the "
            f"array's edge, allowed {_MAX_ROTATION_PX} px): the exact renderer IPR fits with models rotated grids "
            "only in focus; use reconstruct.method mart for this camera"
        )
    # the camera's lattice is o + pitch·(k − (N − 1)/2) with N itself depending on o (the grid covers
    # the sensor): the offsets that put a lattice point on the fitted one (ax0, ay0) are a ladder of
    # half pitches, of which those whose own N keeps the phase are valid; of these, the pair whose
    # lattice holds every calibrated centre (an edge row may exist for one and not the other), then the smallest
    # offset; among equal fits the pitch nearest the fitted one. Where the sensor is a whole number of
    # lenslets (the demo's 640 x 480 px at pitch 0.1184 mm: 40 x 30), a fitted pitch a hair short needs one
    # more lenslet, whose lattice has the other phase at every offset: the pitches that make the sensor whole
    # (and the nominal one) are tried too, within the calibration's precision (the residual decides)
    # the main lens keeps its f-number: a "matched" camera would re-derive it from the fitted pitch and round
    # it to a standard stop, and at the thesis' pitch (0.125 mm, f/4 lenslets: the matched f/2 exactly) a
    # pitch fitted 1e-9 mm short rounds up to f/2.8, a 1/sqrt(2) smaller aperture image behind every lenslet
    camera = camera.with_(fnumber=camera.main_fnumber)
    pitches = {pitch, camera.lenslet_pitch}
    for size in (camera.sensor_width, camera.sensor_height):
        pitches.add(size / max(1, round(size / pitch)))
    best = None
    for p in sorted(pitches, key=lambda v: abs(v - pitch)):
        for ox in _lattice_offsets(camera, p, ax0, "x"):
            for oy in _lattice_offsets(camera, p, ay0, "y"):
                c = camera.with_(lenslet_pitch=p, lenslet_offset_x=ox, lenslet_offset_y=oy, lenslet_rotation=0.0)
                key = (round(_grid_residual(c, cx[ok], cy[ok]), 3), abs(p - pitch), math.hypot(ox, oy))
                if best is None or key < best[0]:
                    best = key, c
    if best is None:
        raise ReconstructionError("centers: no lenslet offset reproduces the calibrated grid")
    cam = best[1]
    resid = _grid_residual(cam, cx[ok], cy[ok])
    return cam, {
        "grid_pitch_mm": float(cam.lenslet_pitch),
        "grid_offset_x_mm": float(cam.lenslet_offset_x),
        "grid_offset_y_mm": float(cam.lenslet_offset_y),
        "grid_rotation_rad": float(rot),
        "grid_residual_px": float(resid),
    }


def _lattice_offsets(camera: PlenopticCamera, pitch: float, point: float, axis: str) -> list[float]:
    """The lenslet offsets along ``axis`` (within one pitch) whose lattice, with the lenslet count
    that offset gives, holds ``point`` [mm]."""

    def phase_error(o: float) -> float:
        cam = camera.with_(lenslet_pitch=pitch, **{f"lenslet_offset_{axis}": o}, lenslet_rotation=0.0)
        n = cam.n_lenslets_x if axis == "x" else cam.n_lenslets_y
        first = o - pitch * (n - 1) / 2.0 if axis == "x" else o + pitch * (n - 1) / 2.0
        return (point - first + pitch / 2.0) % pitch - pitch / 2.0

    base = phase_error(0.0)
    ladder = (base + m * pitch / 2.0 for m in range(-4, 5))
    return [float(o) for o in ladder if abs(o) < pitch and abs(phase_error(o)) < 1e-9 * pitch]


def _grid_residual(cam: PlenopticCamera, cx: np.ndarray, cy: np.ndarray) -> float:
    """Largest distance [px] of the centres (cx, cy) [mm] from the nearest lenslet centre of ``cam``."""
    mx, my = cam.lenslet_centers()
    pitch = cam.lenslet_pitch
    jx = np.clip(np.rint((cx - mx[0, 0]) / pitch).astype(int), 0, mx.shape[1] - 1)
    iy = np.clip(np.rint((my[0, 0] - cy) / pitch).astype(int), 0, mx.shape[0] - 1)
    return float(np.hypot(cx - mx[iy, jx], cy - my[iy, jx]).max() / cam.pixel_pitch)


# ------------------------------------------------------------------ per-particle patches
@njit(parallel=True, cache=True)
def _patch_kernel(px, py, pz, wt, geos, gidx, buf, boff, psz, nlmax, stats, quad, nchunk):  # pragma: no cover - jitted
    """Render particle t (``px[t], py[t], pz[t]``, weight ``wt[t]``) with the cropped geometry
    ``geos[gidx[t]]`` into ``buf[boff[t, 0]:boff[t, 1]]`` (its patch, rows × cols of the crop).

    Each task has its own sensor crop and is the full render's own per-particle step
    (:func:`lfstudy.simulate.exact._render_particle`, unrotated grid, quadrature ``quad``). The
    tasks are cut into ``nchunk`` contiguous chunks run in parallel, each with one scratch (the
    render leaves it clean after every particle, as in :func:`~lfstudy.simulate.exact._render_kernel`):
    every patch is written by one task alone, so the bytes do not depend on the chunks or threads.
    """
    n = px.size
    for c in prange(nchunk):
        scr = _scratch(geos[0], psz, nlmax, quad)
        cnt = np.zeros(_ST_SIZE)
        for t in range(c * n // nchunk, (c + 1) * n // nchunk):
            if wt[t] == 0.0:
                continue
            geo = geos[gidx[t]]
            cnt[:] = 0.0
            chunk = (buf[boff[t, 0] : boff[t, 1]], 0, int(geo[_G_NROW]) - 1)
            _render_particle(geo, False, px[t], py[t], pz[t], wt[t], scr, chunk, cnt)
            for q in range(_ST_SIZE):
                stats[t, q] += cnt[q]


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
    sm, sl = _blurs(camera, diffraction, None)
    gap = None
    if model is not None and not model.ideal:
        sm, sl = sm * model.blur_scale, sl * model.blur_scale
        gap = model.gap(camera)
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
    offsets = np.zeros(n + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(size * k)
    buf = np.zeros(int(offsets[-1]))
    gidx = np.repeat(np.arange(n, dtype=np.int64), k)
    start = (offsets[:-1, None] + np.arange(k)[None, :] * size[:, None]).ravel()
    boff = np.stack([start, start + np.repeat(size, k)], axis=1).astype(np.int64)
    # task t = particle t // k at trial t % k
    tx, ty, tz = (a.reshape(k, n).T.ravel().copy() for a in (ax_, ay_, az_))
    wt = _unit_weights(camera, tx, ty, tz)
    stats = np.zeros((n * k, _ST_SIZE))
    nchunk = max(1, min(tx.size, 8 * numba.get_num_threads()))
    _patch_kernel(tx, ty, tz, wt, geos, gidx, buf, boff, psz, nlmax, stats, _QUAD[accuracy], nchunk)
    if stats[:, _ST_BIG].sum() > 0 or stats[:, _ST_SPILL].sum() > 1e-9 * max(float(wt.sum()), 1e-300):
        raise RuntimeError("particle_patches: a patch exceeded its scratch or spilled (a bug)")
    np.maximum(buf, 0.0, out=buf)  # rounding residue of either sign, as render_exact clips
    return buf, offsets, r0, c0, np.stack([h, w], axis=1)


def _refined(grid: ReconstructionGrid, rxy: int, rz: int) -> ReconstructionGrid:
    """``grid`` with each voxel split into rxy x rxy x rz (same extent; the candidate grid)."""

    def split(c: np.ndarray, k: int) -> np.ndarray:
        if k == 1 or c.size < 2:
            return c
        t = (np.arange(c.size * k) + 0.5) / k - 0.5
        out = np.interp(t, np.arange(c.size), c)
        out[t < 0] = c[0] + t[t < 0] * (c[1] - c[0])
        hi = t > c.size - 1
        out[hi] = c[-1] + (t[hi] - (c.size - 1)) * (c[-1] - c[-2])
        return out

    return ReconstructionGrid(split(grid.x, rxy), split(grid.y, rxy), split(grid.z, rz), spacing=grid.spacing)


# ------------------------------------------------------------------ candidates
def _peaks(vol: np.ndarray, grid: ReconstructionGrid, threshold: float) -> np.ndarray:
    """Local maxima of ``vol`` above ``threshold``·max, (n, 3) x, y, z [mm], by the
    intensity centroid of their 3 x 3 x 3 neighbourhood above its minimum."""
    vmax = float(vol.max()) if vol.size else 0.0
    if vmax <= 0:
        return np.zeros((0, 3))
    peak = (vol == ndimage.maximum_filter(vol, size=3, mode="constant")) & (vol > threshold * vmax)
    iz, iy, ix = np.nonzero(peak)
    pad = np.pad(vol, 1, mode="edge")
    out = np.zeros((iz.size, 3))
    for axis, (idx, coord) in enumerate(((ix, grid.x), (iy, grid.y), (iz, grid.z))):
        # centroid offset along the axis from the neighbour sums on either side
        sl_lo = [iz + 1, iy + 1, ix + 1]
        sl_hi = [iz + 1, iy + 1, ix + 1]
        ax = 2 - axis
        sl_lo[ax] = sl_lo[ax] - 1
        sl_hi[ax] = sl_hi[ax] + 1
        lo, mid, hi = pad[tuple(sl_lo)], pad[iz + 1, iy + 1, ix + 1], pad[tuple(sl_hi)]
        den = lo - 2 * mid + hi
        frac = np.where(den < 0, 0.5 * (lo - hi) / np.where(den < 0, den, 1.0), 0.0)
        frac = np.clip(frac, -0.5, 0.5)
        f = idx + frac
        out[:, axis] = np.interp(f, np.arange(coord.size), coord)
    return out


def _stack_volume(plan: MartPlan, light: xr.DataArray, smoothing: float = 0.5) -> np.ndarray:
    """The focal stack of ``light`` on the plan's grid: each voxel the mean of the (non-negative) ray intensities
    through it, weighted by their beam fractions (Σ_i F_ij·I_i / Σ_i F_ij over the plan's rays; the additive
    back-projection, MLOS's arithmetic counterpart), the voxels too few views see left empty and smoothed as MART
    smooths (``smoothing`` voxels, :func:`lfstudy.reconstruct.mart.mart`)."""
    from lfstudy.reconstruct.mart import _coverage

    proj = plan.proj
    meas = np.where(proj.gain > 0, np.maximum(proj._lf_array(light), 0.0), 0.0)
    num = np.zeros((1, *proj.grid.shape))
    chan = np.zeros(1, np.int64)
    for block in plan.blocks:
        for pc, prs in block:
            proj.column_accumulate_many(pc, prs, proj.column_values(meas, pc, prs)[None], chan, num)
    cover = _coverage(plan.dens)
    vol = np.divide(num[0], cover, out=np.zeros_like(cover), where=cover > 0)
    vol[~plan.seen] = 0.0
    if smoothing > 0:
        ndimage.gaussian_filter(vol, smoothing, truncate=3.0, output=vol)
    return vol


def _raw_from_lightfield(lf: xr.DataArray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The light field's samples put back on the sensor, and the mask of the pixels it holds."""
    vals = np.asarray(lf.values, dtype=np.float64)
    lr, lc, n, _ = vals.shape
    row0 = np.asarray(lf["row0"].values, np.int64)
    col0 = np.asarray(lf["col0"].values, np.int64)
    valid = np.asarray(lf["valid"].values, bool) if "valid" in lf.coords else np.ones((lr, lc), bool)
    img = np.zeros(shape)
    mask = np.zeros(shape, np.uint8)
    k = np.arange(n)
    for i, j in zip(*np.nonzero(valid)):
        rr, cc = row0[i, j] + k, col0[i, j] + k
        img[np.ix_(rr, cc)] = vals[i, j]
        mask[np.ix_(rr, cc)] = 1
    return img, mask


def _lightfield_from_raw(img: np.ndarray, lf: xr.DataArray) -> xr.DataArray:
    """An image cut into ``lf``'s blocks (the inverse of :func:`_raw_from_lightfield`)."""
    n = lf.sizes["prow"]
    row0 = np.asarray(lf["row0"].values, np.int64)[..., None, None] + np.arange(n)[:, None]
    col0 = np.asarray(lf["col0"].values, np.int64)[..., None, None] + np.arange(n)[None, :]
    ny, nx = img.shape
    ok = (row0 >= 0) & (row0 < ny) & (col0 >= 0) & (col0 < nx)
    vals = np.where(ok, img[np.clip(row0, 0, ny - 1), np.clip(col0, 0, nx - 1)], 0.0)
    return lf.copy(data=vals.astype(lf.dtype))


# ------------------------------------------------------------------ the volumetric calibration's frame
def volumetric_frame(
    xyz: np.ndarray,
    lightfield: xr.DataArray,
    camera: PlenopticCamera,
    calibration: xr.Dataset,
    *,
    to: str = "calibrated",
    iterations: int = 6,
) -> np.ndarray:
    """Positions moved between the nominal camera's frame and the volumetric calibration's.

    IPR fits with the exact renderer of the nominal camera, so a fitted position ``x_nom`` is
    where the nominal camera would have to see the particle to record the image it did. The
    calibrated position is the one the fitted mapping (Hall et al. 2018) sends to the same
    sub-aperture image positions: ``x_cal = argmin_x Σ_uv |P_uv(x) − Q_uv(x_nom)|²``, P the
    calibration's polynomials and Q the thin-lens mapping of the same sub-apertures
    (:func:`lfstudy.lightfield.volcal.predict_thin_lens`), over the calibrated sub-apertures;
    ``to="nominal"`` solves the reverse, ``argmin_x Σ |Q(x) − P(x_cal)|²``. Gauss–Newton with a
    central-difference Jacobian, all particles at once (3 x 3 normal equations each).

    Parameters
    ----------
    xyz : ndarray (N, 3)
        Positions [mm] in the frame ``to`` is not.
    lightfield : xarray.DataArray
        The registered light field (its lenslet grid and shape).
    camera : PlenopticCamera
        The nominal camera.
    calibration : xarray.Dataset
        From :func:`lfstudy.lightfield.volcal.fit_volumetric`.
    to : {"calibrated", "nominal"}
    iterations : int
        Gauss–Newton steps.

    Returns
    -------
    ndarray (N, 3)
    """
    from lfstudy.lightfield.volcal import predict, predict_thin_lens

    if to not in ("calibrated", "nominal"):
        raise ReconstructionError(f"volumetric_frame: to = {to!r}: allowed values are calibrated, nominal")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if not len(xyz):
        return xyz.copy()
    ok = np.asarray(calibration["valid"].values, bool)

    def cal(p: np.ndarray) -> np.ndarray:
        v = predict(calibration, p[:, 0], p[:, 1], p[:, 2]).values[:, :, ok]
        return np.concatenate([v[0], v[1]], axis=1)

    def nom(p: np.ndarray) -> np.ndarray:
        v = predict_thin_lens(lightfield, camera, p[:, 0], p[:, 1], p[:, 2]).values[:, :, ok]
        return np.concatenate([v[0], v[1]], axis=1)

    src, dst = (nom, cal) if to == "calibrated" else (cal, nom)
    target = src(xyz)
    x = xyz.copy()
    h = 1e-4 * max(camera.lenslet_pitch / abs(camera.magnification), 1e-12)  # a thousandth of a voxel or so
    for _ in range(iterations):
        r = dst(x) - target
        jac = np.empty((*r.shape, 3))
        for a in range(3):
            e = np.zeros(3)
            e[a] = h
            jac[..., a] = (dst(x + e) - dst(x - e)) / (2.0 * h)
        jtj = np.einsum("nma,nmb->nab", jac, jac)
        jtr = np.einsum("nma,nm->na", jac, r)
        reg = 1e-12 * np.trace(jtj, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        x = x - np.linalg.solve(jtj + reg, jtr[..., None])[..., 0]
    if not np.all(np.isfinite(x)):
        raise ReconstructionError("the volumetric calibration cannot map the particle positions (non-finite)")
    return x


# ------------------------------------------------------------------ the method
def _check(name: str, value: float, lo: float, hi: float, *, lo_open: bool = False) -> None:
    number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    ok = number and math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        br = "(" if lo_open else "["
        raise ReconstructionError(f"reconstruct.ipr.{name} = {value!r}: allowed range is {br}{lo}, {hi}]")


def ipr_particles(
    inputs: ReconstructionInputs,
    *,
    iterations: int = 10,
    peak_threshold: float = 0.1,
    min_intensity: float = 0.2,
    shake: float = 0.1,
    max_step: float = 0.5,
    damping: float = 0.01,
    background: float = 0.0,
    residual_candidates: int = 10,
    mart_iterations: int = 3,
    residual_mart_iterations: int = 3,
    residual_plane_step: int = 1,
    residual_candidates_min_gain: float = 0.001,
    residual_late_gain: float = 0.01,
    residual_volume: str = "mart",
    shake_settle: float = 0.0,
    jacobian: str = "central",
    image_accuracy: str = "fast",
    polish: int = 3,
    split: int = 0,
    split_penalty: float = 16.0,
    split_ratio: float = 1.3,
    image_calibration: int = 0,
    batch: int = _BATCH,
    progress: bool = False,
) -> xr.Dataset:
    """Particles fitted to a registered light field by IPR (see the module docstring).

    Parameters
    ----------
    inputs : ReconstructionInputs
        ``lightfield``, ``centers``, ``camera`` and ``grid``; with a volumetric ``calibration``
        the candidates come from MART through it, are moved into the nominal frame the exact
        renderer fits in, and the fitted positions are moved back into the calibrated frame
        (:func:`volumetric_frame`), so positions, the rendered volume and PIV are calibrated.
    iterations : int
        Outer iterations (render, fit, remove ghosts, add candidates).
    peak_threshold : float
        MART peaks below this fraction of the volume's maximum are no candidates.
    min_intensity : float
        Particles fainter than this fraction of the median intensity are removed as ghosts.
    shake : float
        Finite-difference step δ of the Jacobian, in voxels of the grid (per axis).
    max_step : float
        Largest move of a particle in one iteration, in voxels (the trust region).
    damping : float
        Levenberg–Marquardt damping λ of the position part of the normal equations.
    background : float
        Dark level subtracted from the light field (image units).
    residual_candidates : int
        After each of this many first iterations, MART peaks of the positive residual add candidates.
    mart_iterations : int
        MART iterations of the first candidate volume (of the data).
    residual_mart_iterations : int
        MART iterations of the residual's candidate volumes (0: its MLOS first guess alone).
    residual_plane_step : int
        The residual's candidate volumes are reconstructed on every ``residual_plane_step``-th plane of
        the candidate grid (:meth:`lfstudy.reconstruct.mart.MartPlan.planes`: the same weight tables,
        that many times fewer planes and about that many times cheaper); 1: every plane.
    residual_candidates_min_gain : float
        The residual-candidate rounds stop after one that adds fewer new particles than this fraction of the
        particle list (its remaining volumes would repeat the last one's rejected peaks; module docstring,
        "Candidates"); 0: every one of the ``residual_candidates`` rounds runs.
    residual_late_gain : float
        Once a residual-candidate round adds fewer new particles than this fraction of the list (but not fewer than
        ``residual_candidates_min_gain``'s), the later rounds' volumes take ``_LATE_MART_ITERATIONS`` (1) MART
        iterations instead of ``residual_mart_iterations``; 0: never.
    residual_volume : {"mart", "case", "stack"}
        The volume whose peaks are the residual rounds' candidates (module docstring, "Candidates"): ``mart`` MART
        (``residual_mart_iterations``) on the refined candidate grid; ``case`` MART (as many iterations) on the case's
        own grid, whose plan is made once besides the refined grid's; ``stack`` the residual's focal stack on the
        refined grid (the coverage-weighted mean of the rays through each voxel, no MART iteration). The first
        candidates (of the data) always come from MART on the refined grid.
    shake_settle : float
        The shake's active set [voxels]: a particle whose last shake moved it less than this, with no particle
        within ``_SETTLE_RADIUS`` voxels moved (as much), added or removed since, sits out the next shake (at most
        ``_SETTLE_SKIPS`` in a row; attrs ``shake_sat_out``: how many per iteration); 0: every particle is shaken
        every iteration.
    jacobian : {"central", "forward"}
        Finite differences of the position Jacobian: ``central`` renders the six ±δ trial images per
        particle and iteration, ``forward`` the three +δ ones (the choice then has four exact candidates
        besides the current position: the three trials and the Gauss–Newton step).
    image_accuracy : {"fast", "exact"}
        Quadrature of the per-particle images (:func:`particle_patches`): ``exact`` the renderer's own,
        ``fast`` within 1e-4 of each image's peak (module docstring, "Per-particle image").
    polish : int
        Rounds of the final polish (module docstring): each particle whose defocus spot on the lenslet array
        is at most ``_POLISH_SPOT`` pitches is moved to the likelihood-weighted mean of a stencil of positions
        around it (0: none).
    split : int
        Rounds of the split after the polish (module docstring, "Split"): each particle brighter than
        ``split_ratio`` times the median is tried as two close particles, kept where the residual falls by more
        than ``split_penalty`` times its variance (0: none).
    split_penalty : float
        The split's threshold on the drop of ‖R‖², in units of the pair fit's residual variance σ² on its pixels.
    split_ratio : float
        The split tries the particles brighter than this times the median intensity (0: every particle).
    image_calibration : int
        Rounds of the image model's calibration from the recording's own particles
        (:mod:`lfstudy.reconstruct.image_model`: the lenslet-to-sensor gap and a blur scale, fitted to the residual
        with the particles held), spread over the iterations (after iterations k·n/(rounds + 1)); the later
        iterations, the polish and the split fit with the calibrated images. 0: the nominal camera's images.
    batch : int
        Particles rendered at once (bounds the patch memory: their images' boxes, ~40,000 pixels each on average
        over the thesis' 7 mm depth, the shake's 7 per particle: 0.59 GB at 256, 4.7 GB at the former 2048).
    progress : bool
        A tqdm bar over the iterations.

    Returns
    -------
    xarray.Dataset
        Over ``particle``: ``x``, ``y``, ``z`` [mm], ``intensity`` (the exact model's: a particle of
        intensity I at the reference solid angle puts I into the image), ``residual`` (‖residual‖/‖image‖
        on its patch), ``sigma_x``, ``sigma_y``, ``sigma_z`` [mm] (from the fit's covariance). Attrs:
        the settings, ``candidates``, ``removed_ghosts``, ``residual_norm`` per iteration (relative,
        exact), ``seconds`` and its split (``seconds_mart``: the candidate volumes, ``mart_volumes`` of them;
        ``seconds_patches``: the exact particle images, ``particle_images`` of them; ``seconds_fit``: the fit
        kernels) and the calibrated grid (:func:`calibrated_camera`).
    """
    t_start = time.perf_counter()
    for name in ("lightfield", "centers", "camera", "grid"):
        if getattr(inputs, name) is None:
            raise ReconstructionError(f"reconstruct.ipr needs the {name}")
    if not isinstance(iterations, (int, np.integer)) or not 0 <= iterations <= 100:
        raise ReconstructionError(f"reconstruct.ipr.iterations = {iterations!r}: allowed range is [0, 100]")
    _check("peak_threshold", peak_threshold, 0.0, 1.0, lo_open=True)
    _check("min_intensity", min_intensity, 0.0, 1.0)
    _check("shake", shake, 0.0, 1.0, lo_open=True)
    _check("max_step", max_step, 0.0, 5.0, lo_open=True)
    _check("damping", damping, 0.0, 1e6)
    _check("background", background, 0.0, math.inf)
    for name, val in (("mart_iterations", mart_iterations), ("residual_mart_iterations", residual_mart_iterations)):
        if not isinstance(val, (int, np.integer)) or not 0 <= val <= 50:
            raise ReconstructionError(f"reconstruct.ipr.{name} = {val!r}: allowed range is [0, 50]")
    if not isinstance(residual_plane_step, (int, np.integer)) or not 1 <= residual_plane_step <= 4:
        raise ReconstructionError(
            f"reconstruct.ipr.residual_plane_step = {residual_plane_step!r}: allowed range is [1, 4]"
        )
    _check("residual_candidates_min_gain", residual_candidates_min_gain, 0.0, 1.0)
    _check("residual_late_gain", residual_late_gain, 0.0, 1.0)
    _check("shake_settle", shake_settle, 0.0, 1.0)
    if not isinstance(polish, (int, np.integer)) or not 0 <= polish <= 20:
        raise ReconstructionError(f"reconstruct.ipr.polish = {polish!r}: allowed range is [0, 20]")
    if not isinstance(split, (int, np.integer)) or isinstance(split, (bool, np.bool_)) or not 0 <= split <= 10:
        raise ReconstructionError(f"reconstruct.ipr.split = {split!r}: allowed range is [0, 10]")
    _check("split_penalty", split_penalty, 0.0, 1e6)
    _check("split_ratio", split_ratio, 0.0, 100.0)
    if residual_volume not in _RESIDUAL_VOLUMES:
        allowed = ", ".join(_RESIDUAL_VOLUMES)
        raise ReconstructionError(
            f"reconstruct.ipr.residual_volume = {residual_volume!r}: allowed values are {allowed}"
        )
    if jacobian not in _JACOBIANS:
        allowed = ", ".join(_JACOBIANS)
        raise ReconstructionError(f"reconstruct.ipr.jacobian = {jacobian!r}: allowed values are {allowed}")
    if image_accuracy not in _QUAD:
        allowed = ", ".join(_QUAD)
        raise ReconstructionError(f"reconstruct.ipr.image_accuracy = {image_accuracy!r}: allowed values are {allowed}")
    if not isinstance(batch, (int, np.integer)) or batch < 1:
        raise ReconstructionError(f"reconstruct.ipr.batch = {batch!r}: allowed range is integers >= 1")
    bad = isinstance(image_calibration, (bool, np.bool_)) or not isinstance(image_calibration, (int, np.integer))
    if bad or not 0 <= image_calibration <= 5:
        raise ReconstructionError(f"reconstruct.ipr.image_calibration = {image_calibration!r}: allowed range is [0, 5]")
    from lfstudy.reconstruct.image_model import ImageModel, calibrate_image_model, model_change
    from lfstudy.reconstruct.mart import mart, mart_plan

    lf, grid = inputs.lightfield, inputs.grid
    cam, ginfo = calibrated_camera(inputs.camera, inputs.centers)
    data, mask = _raw_from_lightfield(lf, (cam.n_pixels_y, cam.n_pixels_x))
    if not np.all(np.isfinite(data)):
        raise ReconstructionError("reconstruct.ipr: the light field has non-finite samples")
    data = np.where(mask > 0, data - background, 0.0)
    dz, dy, dx = grid.voxel_size()
    vox = np.array([dx, dy, dz])
    delta = shake * vox
    mstep = max_step * vox
    central = jacobian == "central"
    signs = (1.0, -1.0) if central else (1.0,)
    tr = np.array([[d * delta[i] if a == i else 0.0 for a in range(3)] for i in range(3) for d in signs])
    clock = {"mart": 0.0, "patches": 0.0, "fit": 0.0, "images": 0, "volumes": 0}
    cgrid = _refined(grid, _REFINE_XY, _REFINE_Z)
    t0 = time.perf_counter()
    vcal = inputs.calibration
    # tables and coverage, once for every volume; the coverage in float32 (half its memory: the candidates are the
    # volume's peaks, which the last bits of the coverage do not move)
    plan = mart_plan(lf, inputs.camera, cgrid, calibration=vcal, coverage_dtype="float32")
    # the residual's volumes: every residual_plane_step-th plane, on views into the same tables
    rplan = plan.planes(int(residual_plane_step)) if residual_plane_step > 1 else plan
    clock["mart"] += time.perf_counter() - t0
    case_plan: list[MartPlan] = []  # residual_volume "case": the case grid's plan, made on first use

    def candidates(light: xr.DataArray, iters: int, p: MartPlan = plan, kind: str = "mart") -> np.ndarray:
        t0 = time.perf_counter()
        if kind == "case":
            if not case_plan:
                cp = mart_plan(lf, inputs.camera, grid, calibration=vcal, coverage_dtype="float32")
                case_plan.append(cp.planes(int(residual_plane_step)) if residual_plane_step > 1 else cp)
            p = case_plan[0]
        g = p.proj.grid
        if kind == "stack":
            vol = _stack_volume(p, light)
        else:
            vol = mart(light, inputs.camera, g, iterations=iters, plan=p, calibration=vcal).values
        clock["mart"] += time.perf_counter() - t0
        clock["volumes"] += 1
        peaks = _peaks(vol, g, peak_threshold)
        if vcal is not None:  # the exact renderer fits in the nominal camera's frame
            peaks = volumetric_frame(peaks, lf, inputs.camera, vcal, to="nominal")
        return peaks

    xyz = candidates(lf, mart_iterations)
    n_cand = len(xyz)
    inten = np.zeros(len(xyz))
    sig = np.full((len(xyz), 3), np.inf)
    rel = np.full(len(xyz), np.inf)
    norm_d = float(np.sqrt(np.sum(data**2))) or 1.0
    res_hist: list[float] = []
    ghosts = 0
    gain: list[int] = []  # new particles accepted per residual-candidate round
    stop_after, skipped = iterations, 0  # residual-candidate rounds skipped from this iteration on
    inside = (grid.x[0], grid.x[-1]), (grid.y[0], grid.y[-1]), (grid.z[0], grid.z[-1])
    settle = float(shake_settle)
    still = np.zeros(len(xyz), bool)  # the active set's settled particles (off with shake_settle 0)
    sat = np.zeros(len(xyz), np.int64)  # shakes each has sat out in a row
    sat_out: list[int] = []  # particles not shaken, per iteration
    late = False  # residual_late_gain: a round added fewer than that of the list

    # the image model: the nominal camera's until a calibration from the recording's particles replaces it
    image = {"model": ImageModel()}
    calibrate_after = {round((k + 1) * iterations / (image_calibration + 1)) - 1 for k in range(image_calibration)}
    cal_info: list[dict[str, Any]] = []

    def patches(pos: np.ndarray, trials: np.ndarray | None = None, model: ImageModel | None = None):
        t0 = time.perf_counter()
        m = image["model"] if model is None else model
        out = particle_patches(cam, *pos.T, trials=trials, accuracy=image_accuracy, model=m)
        clock["patches"] += time.perf_counter() - t0
        clock["images"] += len(pos) * (1 if trials is None else 1 + len(trials))
        return out

    def add_images(pos: np.ndarray, amp: np.ndarray, res: np.ndarray, sign: float) -> None:
        """res += sign·amp·U on the light field's pixels (the exact images of the particles at ``pos``)."""
        for s in range(0, len(pos), batch):
            sl = slice(s, s + batch)
            buf, offs, r0, c0, shp = patches(pos[sl])
            t0 = time.perf_counter()
            _accumulate_masked(res, mask, buf, offs, r0, c0, shp, amp[sl] * 1.0, sign)
            clock["fit"] += time.perf_counter() - t0

    def fit_intensity(pos: np.ndarray, res: np.ndarray, floor: float) -> np.ndarray:
        """Intensities of new particles at ``pos`` (Gauss–Seidel on ``res``, which keeps the images of those
        brighter than ``floor``: the others are added back)."""
        out = np.zeros((len(pos), 2))
        for s in range(0, len(pos), batch):
            sl = slice(s, s + batch)
            buf, offs, r0, c0, shp = patches(pos[sl])
            t0 = time.perf_counter()
            _choose(res, mask, buf, offs, r0, c0, shp, 1, np.zeros(len(shp)), buf, offs, r0, c0, shp, out[sl])
            back = np.where(out[sl, 1] > floor, 0.0, out[sl, 1])
            _accumulate_masked(res, mask, buf, offs, r0, c0, shp, back, 1.0)
            clock["fit"] += time.perf_counter() - t0
        return out[:, 1]

    def shake_step(pos: np.ndarray, amp: np.ndarray, res: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gauss–Newton steps on a linearised copy of the residual, then the exact choice (``_choose``), which
        leaves ``res`` the exact residual of the moved particles."""
        lin = res.copy()
        out = np.zeros((len(pos), 9))
        pick = np.zeros((len(pos), 2))
        moved = pos.copy()
        offsets = np.vstack([np.zeros((1, 3)), tr])
        for s in range(0, len(pos), batch):
            sl = slice(s, s + batch)
            buf, offs, r0, c0, shp = patches(pos[sl], tr)
            t0 = time.perf_counter()
            lm = float(damping)
            _sweep(lin, mask, buf, offs, r0, c0, shp, amp[sl].copy(), delta, mstep, lm, True, central, out[sl])
            clock["fit"] += time.perf_counter() - t0
            step = pos[sl] + out[sl, :3]
            bn, on, r0n, c0n, shpn = patches(step)
            t0 = time.perf_counter()
            _choose(res, mask, buf, offs, r0, c0, shp, 1 + len(tr), amp[sl], bn, on, r0n, c0n, shpn, pick[sl])
            clock["fit"] += time.perf_counter() - t0
            k = pick[sl, 0].astype(int)
            moved[sl] = np.where((k == len(tr) + 1)[:, None], step, pos[sl] + offsets[np.minimum(k, len(tr))])
        return moved, pick[:, 1], out

    stencil = np.array([(a, b, c) for a in _POLISH_XY for b in _POLISH_XY for c in _POLISH_Z]) * vox
    stencil = np.vstack([np.zeros((1, 3)), stencil[np.any(stencil != 0.0, axis=1)]])  # the current position first

    def polish_step(pos: np.ndarray, amp: np.ndarray, res: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each particle moved to the likelihood-weighted mean of the stencil positions around it (the others
        held fixed: weights exp(−ΔC/2σ²), ΔC the rise of the exact residual's ‖R‖² over the stencil's best,
        σ² the residual variance per pixel on the particle's patch), then the intensities refitted there."""
        k = len(stencil)
        drop = np.zeros((len(pos), k + 1))
        for s in range(0, len(pos), max(1, batch // k)):
            sl = slice(s, s + max(1, batch // k))
            cand = (pos[sl][:, None, :] + stencil[None]).reshape(-1, 3)
            buf, offs, r0, c0, shp = patches(cand)
            t0 = time.perf_counter()
            _stencil(res, mask, buf, offs, r0, c0, shp, k, amp[sl] * 1.0, drop[sl])
            clock["fit"] += time.perf_counter() - t0
        s2 = np.maximum(drop[:, k], 1e-300)
        logw = (drop[:, :k] - drop[:, :k].max(axis=1, keepdims=True)) / (2.0 * _POLISH_T * s2[:, None])
        wgt = np.exp(logw)
        moved = pos + (wgt @ stencil) / wgt.sum(axis=1)[:, None]
        add_images(pos, amp, res, 1.0)
        return moved, fit_intensity(moved, res, -1.0)

    def norm(res: np.ndarray) -> float:
        return float(np.sqrt(np.sum(res**2))) / norm_d

    bar = tqdm(total=iterations, desc="IPR", unit="it", disable=not progress)
    # the residual is kept exact incrementally: every image subtracted or added back is the exact one
    res = data.copy()
    if len(xyz):  # intensities of the candidates first (positions fixed)
        inten = fit_intensity(xyz, res, -1.0)
    for it in range(iterations):
        if not len(xyz):
            break
        res_hist.append(norm(res))
        # the active set: particles settled (their last shake moved them less than shake_settle voxels, and no
        # particle within _SETTLE_RADIUS voxels moved, was added or removed since) sit out up to _SETTLE_SKIPS shakes
        act = ~(still & (sat < _SETTLE_SKIPS))
        sat = np.where(act, 0, sat + 1)
        sat_out.append(int((~act).sum()))
        old = xyz
        xyz, inten, sig, rel = xyz.copy(), inten.copy(), sig.copy(), rel.copy()
        xyz[act], inten[act], out = shake_step(old[act], inten[act], res)
        sig[act] = np.sqrt(out[:, 4:7])
        rel[act] = out[:, 7]
        moved = np.max(np.abs(xyz - old) / vox, axis=1) >= settle if settle > 0 else act
        events = [old[moved], xyz[moved]]
        still = np.where(act, ~moved, still)
        # ghosts: faint particles, and particles that left the grid
        med = float(np.median(inten[inten > 0])) if np.any(inten > 0) else 0.0
        keep = inten > (min_intensity * med if it >= _GHOST_FROM else 0.0)
        for a in range(3):
            keep &= (xyz[:, a] >= inside[a][0] - vox[a]) & (xyz[:, a] <= inside[a][1] + vox[a])
        keep &= _unmerged(xyz, inten, vox)
        ghosts += int((~keep).sum())
        gone = ~keep & (inten > 0)
        if gone.any():
            add_images(xyz[gone], inten[gone], res, 1.0)
        events.append(xyz[~keep])
        xyz, inten, sig, rel = xyz[keep], inten[keep], sig[keep], rel[keep]
        still, sat = still[keep], sat[keep]
        if it < residual_candidates and it >= stop_after:
            skipped += 1
        elif it < residual_candidates:
            its = min(_LATE_MART_ITERATIONS, residual_mart_iterations) if late else residual_mart_iterations
            new = candidates(_lightfield_from_raw(np.maximum(res, 0.0), lf), its, rplan, residual_volume)
            if len(new) and len(xyz):
                new = new[cKDTree(xyz / vox).query(new / vox)[0] > _MIN_SEPARATION]
            if len(new):
                n_cand += len(new)
                floor = min_intensity * med
                amp0 = fit_intensity(new, res, floor)
                good = amp0 > floor
                xyz = np.vstack([xyz, new[good]])
                inten = np.concatenate([inten, amp0[good]])
                sig = np.vstack([sig, np.full((int(good.sum()), 3), np.inf)])
                rel = np.concatenate([rel, np.full(int(good.sum()), np.inf)])
                still = np.concatenate([still, np.zeros(int(good.sum()), bool)])
                sat = np.concatenate([sat, np.zeros(int(good.sum()), np.int64)])
                events.append(new[good])
            gain.append(int(good.sum()) if len(new) else 0)
            if gain[-1] < residual_candidates_min_gain * len(xyz):  # the next volumes would repeat this one
                stop_after = it + 1
            late |= gain[-1] < residual_late_gain * len(xyz)  # the later volumes take fewer MART iterations
        if it in calibrate_after and len(xyz):  # the camera's own particle images (issue 39 §2)
            zr = (float(grid.z[0]), float(grid.z[-1]))
            model, res, inten, info = calibrate_image_model(
                patches, data, res, mask, xyz, inten, cam, zr, image["model"], batch=batch
            )
            image["model"] = model
            cal_info.append(info)
        if settle > 0:  # a change near a settled particle wakes it
            still = _unwoken(still, xyz, np.vstack(events), vox)
        bar.update(1)
        if res_hist:
            bar.set_postfix(particles=len(xyz), residual=f"{res_hist[-1]:.4f}")
    bar.close()
    # the final polish: near the focal plane the image changes little with the position inside a lenslet (the
    # residual is flat there, and the fit stops anywhere on the flat): the likelihood-weighted mean over a
    # stencil around the particle is the estimate of least expected error; a few rounds walk it to the middle
    near = np.nonzero(_spot_pitches(cam, xyz[:, 2]) <= _POLISH_SPOT)[0] if len(xyz) else np.zeros(0, int)
    for _ in range(polish if len(near) else 0):
        xyz[near], inten[near] = polish_step(xyz[near], inten[near], res)
    if polish and len(near):  # pairs the polish brought within half a voxel are merged
        keep = _unmerged(xyz, inten, vox)
        ghosts += int((~keep).sum())
        add_images(xyz[~keep], inten[~keep], res, 1.0)
        xyz, inten, sig, rel = xyz[keep], inten[keep], sig[keep], rel[keep]
    n_split = 0
    # close pairs the fit holds as one bright particle: tried as two (after the polish: before it, measured, the
    # polish's moves and merges undo the gain)
    for _ in range(split if len(xyz) > 1 else 0):
        floor = min_intensity * float(np.median(inten[inten > 0])) if np.any(inten > 0) else 0.0
        xyz, inten, n = _split_pairs(
            patches, res, mask, xyz, inten, vox, floor=floor, penalty=split_penalty, ratio=split_ratio
        )
        sig = np.vstack([sig, np.full((n, 3), np.inf)])
        rel = np.concatenate([rel, np.full(n, np.inf)])
        n_split += n
        if not n:
            break
        keep = _unmerged(xyz, inten, vox)  # a new particle within half a voxel of another is merged
        ghosts += int((~keep).sum())
        add_images(xyz[~keep], inten[~keep], res, 1.0)
        xyz, inten, sig, rel = xyz[keep], inten[keep], sig[keep], rel[keep]
    if len(xyz):
        res_hist.append(norm(res))
    image_attrs: dict[str, Any] = {"image_calibration": int(image_calibration), **image["model"].to_attrs()}
    if cal_info:  # what the calibration changed, per depth (and its costs per round)
        image_attrs["image_calibration_cost"] = [v for c in cal_info for v in c["image_calibration_cost"]]
        image_attrs["image_calibration_accepted"] = [int(c["image_calibration_accepted"]) for c in cal_info]
        zs = np.linspace(float(grid.z[0]), float(grid.z[-1]), 7)
        image_attrs |= model_change(cam, image["model"], zs, patches)
    if vcal is not None:
        xyz = volumetric_frame(xyz, lf, inputs.camera, vcal, to="calibrated")
    P = "particle"
    mm = lambda ln: {"units": "mm", "long_name": ln}  # noqa: E731
    return xr.Dataset(
        {
            "x": (P, xyz[:, 0], mm("particle x")),
            "y": (P, xyz[:, 1], mm("particle y (up)")),
            "z": (P, xyz[:, 2], mm("particle z (depth from the focal plane)")),
            "intensity": (P, inten, {"units": "image units per Ω_ref", "long_name": "fitted intensity"}),
            "residual": (P, rel, {"units": "1", "long_name": "fit residual / particle image on its patch"}),
            "sigma_x": (P, sig[:, 0], mm("position uncertainty x (fit covariance)")),
            "sigma_y": (P, sig[:, 1], mm("position uncertainty y (fit covariance)")),
            "sigma_z": (P, sig[:, 2], mm("position uncertainty z (fit covariance)")),
        },
        attrs={
            "method": "ipr",
            "iterations": int(iterations),
            "peak_threshold": float(peak_threshold),
            "min_intensity": float(min_intensity),
            "shake": float(shake),
            "max_step": float(max_step),
            "damping": float(damping),
            "background": float(background),
            "candidates": int(n_cand),
            "removed_ghosts": int(ghosts),
            "n_particles": len(xyz),
            "residual_norm": [float(r) for r in res_hist],
            "jacobian": jacobian,
            "image_accuracy": image_accuracy,
            "residual_candidates": int(residual_candidates),
            "mart_iterations": int(mart_iterations),
            "residual_mart_iterations": int(residual_mart_iterations),
            "residual_plane_step": int(residual_plane_step),
            "residual_candidates_min_gain": float(residual_candidates_min_gain),
            "residual_late_gain": float(residual_late_gain),
            "residual_volume": residual_volume,
            "shake_settle": float(shake_settle),
            "shake_sat_out": sat_out,
            "candidates_added": gain,
            "skipped_candidate_rounds": int(skipped),
            "polish": int(polish),
            "polished": len(near),
            "split": int(split),
            "split_penalty": float(split_penalty),
            "split_ratio": float(split_ratio),
            "splits": int(n_split),
            "seconds": float(time.perf_counter() - t_start),
            "seconds_mart": float(clock["mart"]),
            "seconds_patches": float(clock["patches"]),
            "seconds_fit": float(clock["fit"]),
            "particle_images": int(clock["images"]),
            "mart_volumes": int(clock["volumes"]),
            "weight_table_bytes": int(plan.proj.table_bytes),
            "coverage_bytes": int(sum(d.nbytes for d in plan.dens)),
            "frame": "nominal camera" if vcal is None else "volumetric calibration (Hall et al. 2018)",
            **image_attrs,
            **ginfo,
        },
    )


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


# ------------------------------------------------------------------ the split of close pairs
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


def render_particles(
    particles: xr.Dataset, grid: ReconstructionGrid, camera: PlenopticCamera, blob_sigma: float = 0.0
) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The volume on ``grid`` of a particle list: each particle's Gaussian integrated over each voxel.

    The particles as :func:`lfstudy.reconstruct.truth.render_truth` renders the truth (the
    reference volume of Q), so a perfect particle list gives the true volume.
    ``blob_sigma`` [voxels per axis] sets σ; 0 takes the case's truth σ
    (:func:`lfstudy.study.case.truth_sigma`: half a resolution cell, one lenslet at the
    focal-plane magnification in x, y and the voxel depth of :func:`default_voxel_z` in z).

    Returns
    -------
    volume : ndarray (z, y, x), float64
    sigma : (σz, σy, σx) [mm]
    """
    if blob_sigma > 0:
        dz, dy, dx = grid.voxel_size()
        sig = (blob_sigma * dz, blob_sigma * dy, blob_sigma * dx)
    else:
        dxy = camera.lenslet_pitch / abs(camera.magnification)
        sig = (default_voxel_z(camera), dxy / 2.0, dxy / 2.0)
    return render_truth({"z": grid.z, "y": grid.y, "x": grid.x}, particles, sigma_mm=sig), sig


def ipr(
    inputs: ReconstructionInputs,
    *,
    iterations: int = 10,
    peak_threshold: float = 0.1,
    min_intensity: float = 0.2,
    shake: float = 0.1,
    max_step: float = 0.5,
    damping: float = 0.01,
    background: float = 0.0,
    residual_candidates: int = 10,
    mart_iterations: int = 3,
    residual_mart_iterations: int = 3,
    residual_plane_step: int = 1,
    residual_candidates_min_gain: float = 0.001,
    residual_late_gain: float = 0.01,
    residual_volume: str = "mart",
    shake_settle: float = 0.0,
    jacobian: str = "central",
    image_accuracy: str = "fast",
    polish: int = 3,
    split: int = 0,
    split_penalty: float = 16.0,
    split_ratio: float = 1.3,
    image_calibration: int = 0,
    blob_sigma: float = 0.0,
    batch: int = _BATCH,
    progress: bool = False,
) -> xr.DataArray:
    """The ``ipr`` volume: :func:`ipr_particles` rendered on the grid by :func:`render_particles`.

    Parameters as :func:`ipr_particles`; ``blob_sigma`` as :func:`render_particles`. The
    volume's attrs carry the particle list's (``n_particles``, ``candidates``,
    ``removed_ghosts``, ``residual_norm``, the calibrated grid) and ``blob_sigma_mm``.
    """
    parts = ipr_particles(
        inputs,
        iterations=iterations,
        peak_threshold=peak_threshold,
        min_intensity=min_intensity,
        shake=shake,
        max_step=max_step,
        damping=damping,
        background=background,
        residual_candidates=residual_candidates,
        mart_iterations=mart_iterations,
        residual_mart_iterations=residual_mart_iterations,
        residual_plane_step=residual_plane_step,
        residual_candidates_min_gain=residual_candidates_min_gain,
        residual_late_gain=residual_late_gain,
        residual_volume=residual_volume,
        shake_settle=shake_settle,
        jacobian=jacobian,
        image_accuracy=image_accuracy,
        polish=polish,
        split=split,
        split_penalty=split_penalty,
        split_ratio=split_ratio,
        image_calibration=image_calibration,
        batch=batch,
        progress=progress,
    )
    return particle_volume(parts, inputs, blob_sigma)


def particle_volume(parts: xr.Dataset, inputs: ReconstructionInputs, blob_sigma: float = 0.0) -> xr.DataArray:
    """The volume on ``inputs.grid`` of a particle list (:func:`ipr_particles`), by :func:`render_particles`,
    with the list's attrs (``n_particles``, ``candidates``, ``removed_ghosts``, ``residual_norm``, the
    calibrated grid) and ``blob_sigma_mm``."""
    vol, sig = render_particles(parts, inputs.grid, inputs.camera, blob_sigma)
    attrs = {k: v for k, v in parts.attrs.items() if k != "method"}
    return inputs.grid.volume(
        vol.astype(np.float32),
        long_name="particle volume (IPR, exact camera model)",
        units=str(inputs.lightfield.attrs.get("units", "counts")),
        blob_sigma_mm=[float(v) for v in sig],
        **attrs,
    )


class IPR(ReconstructionMethod):
    """``ipr``: iterative particle reconstruction fitted with the exact camera model."""

    name = "ipr"
    description = "iterative particle reconstruction (Wieneke 2013) with shaking, fitted with the exact renderer"
    requires = ("lightfield", "centers", "camera", "grid")
    particles = True
    uses_calibration = True
    parameters: ClassVar[dict[str, dict[str, Any]]] = {
        "iterations": {"type": "integer", "minimum": 0, "maximum": 100, "description": "outer iterations"},
        "peak_threshold": {
            "type": "number",
            "exclusiveMinimum": 0,
            "maximum": 1,
            "description": "MART peaks below this fraction of its maximum are no candidates",
        },
        "min_intensity": {
            "type": "number",
            "minimum": 0,
            "maximum": 1,
            "description": "particles fainter than this fraction of the median are removed as ghosts",
        },
        "shake": {
            "type": "number",
            "exclusiveMinimum": 0,
            "maximum": 1,
            "description": "finite-difference step of the position Jacobian [voxels]",
        },
        "max_step": {
            "type": "number",
            "exclusiveMinimum": 0,
            "maximum": 5,
            "description": "largest move of a particle per iteration [voxels]",
        },
        "damping": {"type": "number", "minimum": 0, "description": "Levenberg-Marquardt damping of the positions"},
        "background": {"type": "number", "minimum": 0, "description": "dark level subtracted (image units)"},
        "residual_candidates": {
            "type": "integer",
            "minimum": 0,
            "maximum": 100,
            "description": "first iterations after which MART peaks of the residual add candidates",
        },
        "mart_iterations": {
            "type": "integer",
            "minimum": 0,
            "maximum": 50,
            "description": "MART iterations of the first candidate volume (of the data)",
        },
        "residual_mart_iterations": {
            "type": "integer",
            "minimum": 0,
            "maximum": 50,
            "description": "MART iterations of the residual's candidate volumes (0: its MLOS first guess alone)",
        },
        "residual_plane_step": {
            "type": "integer",
            "minimum": 1,
            "maximum": 4,
            "description": "the residual's candidate volumes on every n-th plane of the candidate grid (n x cheaper)",
        },
        "residual_candidates_min_gain": {
            "type": "number",
            "minimum": 0,
            "maximum": 1,
            "description": "residual-candidate rounds stop after one adding fewer than this fraction of the particles",
        },
        "residual_late_gain": {
            "type": "number",
            "minimum": 0,
            "maximum": 1,
            "description": "after a residual-candidate round adding fewer than this fraction of the particles, the "
            "later rounds' volumes take one MART iteration (0: never)",
        },
        "residual_volume": {
            "type": "string",
            "enum": list(_RESIDUAL_VOLUMES),
            "description": "the residual rounds' candidates: peaks of MART on the refined grid (mart), of MART on the "
            "case grid (case) or of the residual's focal stack on the refined grid (stack)",
        },
        "shake_settle": {
            "type": "number",
            "minimum": 0,
            "maximum": 1,
            "description": "particles whose last shake moved them less than this [voxels], nothing near them changed, "
            "sit out the next shake (0: every particle every iteration)",
        },
        "jacobian": {
            "type": "string",
            "enum": list(_JACOBIANS),
            "description": "finite differences of the position Jacobian: central (6 trial images) or forward (3)",
        },
        "image_accuracy": {
            "type": "string",
            "enum": list(_QUAD),
            "description": "quadrature of the per-particle images: fast (within 1e-4 of each image's peak) or exact",
        },
        "polish": {
            "type": "integer",
            "minimum": 0,
            "maximum": 20,
            "description": "final rounds moving near-focus particles to their likelihood-weighted mean position",
        },
        "split": {
            "type": "integer",
            "minimum": 0,
            "maximum": 10,
            "description": "rounds trying each particle brighter than split_ratio x the median as a pair (0: none)",
        },
        "split_penalty": {
            "type": "number",
            "minimum": 0,
            "maximum": 1000000,
            "description": "a split must lower the residual by more than this many times its variance",
        },
        "split_ratio": {
            "type": "number",
            "minimum": 0,
            "maximum": 100,
            "description": "the split tries the particles brighter than this times the median intensity",
        },
        "image_calibration": {
            "type": "integer",
            "minimum": 0,
            "maximum": 5,
            "description": "rounds calibrating the particle images (lenslet gap, blur) from the recording's own "
            "particles (0: the nominal camera's images)",
        },
        "blob_sigma": {
            "type": "number",
            "minimum": 0,
            "maximum": 5,
            "description": "sigma [voxels] of the output volume's particles; 0: the case's truth sigma",
        },
    }

    @classmethod
    def memory_bytes(cls, size: ReconstructionSize, params: Mapping[str, Any] | None = None) -> float:
        """The base's arrays, the candidate MART's on the case grid refined ``_REFINE_XY`` x ``_REFINE_XY`` x
        ``_REFINE_Z`` (its weight tables: (kx + ky) ~ 17 float32 weights and 2 int16 starts per plane and
        light-field sample, 16.1 weights on the full Table 4.3 frame; the four subsets' float32 coverage; six
        float64 volumes: a MART volume's buffers and the peak search's copies) and three float64 copies of the
        raw frame the fit compares with. On the full Table 4.3 frame (33 planes) 7.16 GB with the process's
        0.3 GB, against the 7.18 GB peak ``benchmarks/bench_ipr.py --memory`` measured there (with its scene's
        0.48 GB); the shake's patches (0.59 GB a batch of 256 there) stay below the MART's peak."""
        nz = _REFINE_Z * size.n_planes
        nvox = _REFINE_XY * _REFINE_XY * _REFINE_Z * size.n_voxels
        tables = nz * size.n_lenslets * size.pixels_per_lenslet * (17 * 4 + 2 * 2)
        return super().memory_bytes(size, params) + (tables + nvox * (4 * 4 + 6 * 8) + 3 * size.n_pixels * 8)

    def run(
        self,
        inputs: ReconstructionInputs,
        *,
        iterations: int = 10,
        peak_threshold: float = 0.1,
        min_intensity: float = 0.2,
        shake: float = 0.1,
        max_step: float = 0.5,
        damping: float = 0.01,
        background: float = 0.0,
        residual_candidates: int = 10,
        mart_iterations: int = 3,
        residual_mart_iterations: int = 3,
        residual_plane_step: int = 1,
        residual_candidates_min_gain: float = 0.001,
        residual_late_gain: float = 0.01,
        residual_volume: str = "mart",
        shake_settle: float = 0.0,
        jacobian: str = "central",
        image_accuracy: str = "fast",
        polish: int = 3,
        split: int = 0,
        split_penalty: float = 16.0,
        split_ratio: float = 1.3,
        image_calibration: int = 0,
        blob_sigma: float = 0.0,
        progress: bool = False,
    ) -> xr.DataArray:
        return ipr(
            inputs,
            iterations=iterations,
            peak_threshold=peak_threshold,
            min_intensity=min_intensity,
            shake=shake,
            max_step=max_step,
            damping=damping,
            background=background,
            residual_candidates=residual_candidates,
            mart_iterations=mart_iterations,
            residual_mart_iterations=residual_mart_iterations,
            residual_plane_step=residual_plane_step,
            residual_candidates_min_gain=residual_candidates_min_gain,
            residual_late_gain=residual_late_gain,
            residual_volume=residual_volume,
            shake_settle=shake_settle,
            jacobian=jacobian,
            image_accuracy=image_accuracy,
            polish=polish,
            split=split,
            split_penalty=split_penalty,
            split_ratio=split_ratio,
            image_calibration=image_calibration,
            blob_sigma=blob_sigma,
            progress=progress,
        )

    def run_particles(
        self, inputs: ReconstructionInputs, *, blob_sigma: float = 0.0, progress: bool = False, **params: Any
    ) -> tuple[xr.DataArray, xr.Dataset]:
        """The volume of :meth:`run` and the particle list (:func:`ipr_particles`) it was rendered from,
        out of one fit; ``params`` as :meth:`run`'s."""
        parts = ipr_particles(inputs, progress=progress, **params)
        return particle_volume(parts, inputs, blob_sigma), parts
