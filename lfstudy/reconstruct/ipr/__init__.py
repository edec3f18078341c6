"""IPR: iterative particle reconstruction with the exact camera model (beyond thesis sec. 5.6).

Iterative Particle Reconstruction [1]_ with the position refinement ("shaking") of Shake-the-Box [2]_: the
particles are the unknowns, not the voxels. Their expected image is
:func:`lfstudy.simulate.exact.render_exact`'s, the one forward model the study trusts, here used to fit the
data. :func:`ipr_particles` returns the particle list; the method ``ipr`` (:class:`IPR`, :func:`ipr`) the volume
rendered from it, so depth calibration, PIV, errors and report run unchanged. Every setting, its default and
its range is a field of :class:`IPRSettings` (the config's ``reconstruct.ipr``).

Forward model and where it is compared
--------------------------------------
The registered light field is the raw image cut into integer pixel blocks at the *calibrated* lenslet
centres (:func:`lfstudy.lightfield.register`; no pixel is resampled). IPR puts its samples back on the
sensor and compares there, on exactly the pixels the light field holds (the rest is masked out). The model
camera is the nominal camera (optics, sensor) with its lenslet grid replaced by the one fitted to the
calibrated centres (pitch and offset by least squares, :func:`calibrated_camera`), never the simulator's true
grid: with a calibration error the model is wrong exactly as an experiment's would be. The exact renderer
handles rotated grids only in focus, so a calibration whose rotation moves a lenslet by more than
``_MAX_ROTATION_PX`` pixels at the array's edge is refused; below that the grid is taken as unrotated (the
residual is in the result's attrs, ``grid_residual_px``). With a volumetric calibration the fit runs in the
nominal camera's frame and :func:`volumetric_frame` moves the positions between the frames. The residual is
rendered once (the data) and then kept exact incrementally: every change subtracts or adds back an exact
image (a fresh render of the final list agrees to 1e-9, see the tests).

The steps, one module each
--------------------------
1. **Candidates** (:mod:`~lfstudy.reconstruct.ipr.candidates`): the peaks of a MART volume
   (:func:`lfstudy.reconstruct.mart.mart`, ``mart_iterations`` 3) above ``peak_threshold`` (0.1) of its
   maximum, on the case grid refined ``_REFINE_XY`` x ``_REFINE_XY`` x ``_REFINE_Z`` (3 x 3 x 2) times (on the
   case grid, one voxel per lenslet, MART's peaks find 7 % of a 0.005 ppp field within half a voxel; on the
   refined grid 48 %). After each of the first ``residual_candidates`` (10) iterations more come from the
   volume of the positive residual (Wieneke's "add candidates from the residual"), except within
   ``_MIN_SEPARATION`` voxels of a particle; ``residual_volume`` (``mart``) chooses that volume (MART on the
   refined grid, MART on the case grid, or the focal stack). Every volume is reconstructed on one MART plan
   made once per fit. Once a round adds fewer new particles than ``residual_candidates_min_gain`` (0.001) of
   the list the later rounds are skipped (their volumes would give the same peaks, rejected again); once it
   adds fewer than ``residual_late_gain`` (0.01) the later volumes take one MART iteration.
2. **Image model** (:mod:`~lfstudy.reconstruct.ipr.patches`): each particle's exact image in its own sensor
   patch (:func:`particle_patches`, the exact renderer's per-lenslet kernels on the cropped sensor), by
   default by a coarser quadrature of the same integrals (``image_accuracy`` ``fast``: within 1e-4 of each
   image's peak and 1e-5 of its sum, tested), with the image model's calibration from the recording's own
   particles where ``image_calibration`` asks for it (:mod:`lfstudy.reconstruct.image_model`).
3. **Shake** (:mod:`~lfstudy.reconstruct.ipr.shake`): each of ``iterations`` (10) outer iterations renders,
   for every particle, its image U and the images at ±δ in x, y and z (δ = ``shake``, 0.1 voxel; central
   differences, ``jacobian``); particle after particle (Gauss–Seidel, as Wieneke's shaking) the linear
   least-squares problem ``min ‖R_p − I'·U − Σ_k a_k·D_k‖²`` over (I', a) is solved on a linearised copy of the
   residual (4 x 4 normal equations, Levenberg–Marquardt ``damping`` 0.01), the step clipped to ``max_step``
   (0.5) voxels; the move is then chosen on the exact residual among the current position, the six trials and
   the step, so no move raises the residual. Particles fainter than ``min_intensity`` (0.2) times the median
   are removed as ghosts and pairs closer than half a voxel merged. The position uncertainty is the fit's
   covariance σ²·(JᵀJ)⁻¹, σ² the patch's residual variance. An iteration costs 8 exact images per particle,
   fewer where the next shake reuses them: a particle the shake kept where it was keeps its seven images, and
   one the Gauss–Newton step moved less than a quarter of δ keeps its trials (the chord method); on the demo
   camera a quarter of the shake's images are reused (:mod:`~lfstudy.reconstruct.ipr.shake`). The Gauss–Seidel
   kernels visit only the pixels each patch's images light, a few per cent of its box (the same bytes).
4. **Polish** (:mod:`~lfstudy.reconstruct.ipr.polish`): near the focal plane a particle's image falls behind
   one to four lenslets and the residual is flat as it moves within them; ``polish`` (3) rounds move each
   particle whose defocus spot is at most ``_POLISH_SPOT`` lenslet pitches to the likelihood-weighted mean of a
   stencil around it (the estimate of least expected error on the flat), the stencil's off-axis positions
   rendered only where its axis positions show the minimum is not sharp (``_POLISH_SCREEN``); the particles
   move one run after another (Gauss–Seidel, runs of particles whose patches do not overlap).
5. **Split** (:mod:`~lfstudy.reconstruct.ipr.split`; ``split`` 0, off): each particle brighter than
   ``split_ratio`` (1.3) times the median is tried as a close pair, kept where ‖R‖² falls by more than
   ``split_penalty`` (16) times its variance.

Figures (found: a true particle with a fitted one within half a voxel; full logs in the docstrings of
``benchmarks/bench_ipr.py`` and ``benchmarks/bench_particle_image.py``, where each setting's choice is measured):

- the fit, Table 4.3 camera, 1 thread on 2 shared cores: 0.001 ppp (400 x 400 px) 88–94 % found, 4–10 %
  ghosts, 12–26 s of CPU; 0.005 ppp (300 x 300 px) 79–87 % found, 12–21 % ghosts, 17–24 s of CPU;
- the ``fast`` images: 0.148 against 0.219 ms of CPU per image (x1.47), the fit's results within the seed noise;
- the polish: found −0.5 to +3.7 points, ghosts −3.9 to +0.2 (seeds 3–7), CPU +4–37 %; run by run (Gauss–Seidel)
  instead of all at once: found +0.7 to +1.3 points, ghosts −2.0 to 0 (Table 4.3 seeds 5–7), the demo study's RMS
  lower on every held-out case;
- the split: found +0 to +2.3 points, ghosts up in 4 of 7 held-out fits (so it stays off);
- ``residual_volume`` ``case`` / ``stack`` (demo camera): found −2.6 to −5.7 / −0.3 to −2.1 points for 7–20 % less CPU;
- memory: the full Table 4.3 frame peaks at 7.18 GB, the candidate plan's weight tables 4.03 GB of it.

References
----------
.. [1] B. Wieneke, "Iterative reconstruction of volumetric particle distribution", Meas. Sci. Technol. 24,
       024008 (2013).
.. [2] D. Schanz, S. Gesemann and A. Schröder, "Shake-The-Box: Lagrangian particle tracking at high particle
       image densities", Exp. Fluids 57, 70 (2016).
.. [3] K. P. Lynch, "Development of a 3-D fluid velocimetry technique based on light field imaging", M.Sc.
       thesis, Auburn University (2011): the camera (Table 4.3) and the MART the candidates come from (sec. 5.6).

Examples
--------
The settings, range-checked (a field out of range names the config key and its range):

>>> from lfstudy.reconstruct.ipr import IPRSettings
>>> IPRSettings().iterations, IPRSettings(polish=0).polish
(10, 0)

One particle's exact image in its patch, 1 mm behind the focal plane of a Table 4.3 camera cropped to
300 x 300 px: its box on the sensor (about 5 x 5 lenslets) and the light it holds, Ω/Ω_ref less what misses
the lenslets (a particle of intensity 1 at the reference solid angle puts 1 into the image):

>>> from lfstudy.optics import PlenopticCamera
>>> from lfstudy.reconstruct.ipr import particle_patches
>>> cam = PlenopticCamera(300, 300, 0.0074, 0.125, 0.5, 50.0, -1.0)
>>> buf, offsets, row0, col0, shape = particle_patches(cam, [0.0], [0.0], [1.0])
>>> [int(v) for v in shape[0]], bool(buf.min() >= 0.0)
([88, 88], True)
>>> round(float(buf.sum()), 2)
0.98
"""

from __future__ import annotations

from lfstudy.reconstruct.ipr.camera import calibrated_camera, volumetric_frame
from lfstudy.reconstruct.ipr.fit import ipr_particles
from lfstudy.reconstruct.ipr.method import IPR, ipr, particle_volume, render_particles
from lfstudy.reconstruct.ipr.patches import particle_patches
from lfstudy.reconstruct.ipr.settings import IPRSettings

# isort: split
# private names the tests and benchmarks reach through the package, as before it was split into modules
from lfstudy.reconstruct._shake_kernels import _stencil, _sweep  # noqa: F401
from lfstudy.reconstruct.ipr.camera import _raw_from_lightfield  # noqa: F401
from lfstudy.reconstruct.ipr.candidates import _REFINE_XY, _REFINE_Z, _peaks, _refined  # noqa: F401
from lfstudy.reconstruct.ipr.patches import _MARGIN_PX, _spot_pitches  # noqa: F401
from lfstudy.reconstruct.ipr.shake import _SETTLE_RADIUS, _unwoken  # noqa: F401
from lfstudy.reconstruct.ipr.split import _split_pairs  # noqa: F401

__all__ = [
    "IPR",
    "IPRSettings",
    "ipr",
    "ipr_particles",
    "particle_volume",
    "calibrated_camera",
    "particle_patches",
    "render_particles",
    "volumetric_frame",
]
