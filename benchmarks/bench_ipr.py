"""IPR on a crop of the Table 4.3 camera: particles found, ghosts, position errors, time, memory (issue 27).

Reproduces: lfstudy/reconstruct/ipr/__init__.py (its docstring's figures: found, ghosts and time on crops, the
full frame's 7.18 GB peak with ``--memory``; the full log of the measurements is at the end of this docstring);
docs/architecture.md § "Benchmarks".

    python benchmarks/bench_ipr.py [--crop 600 600] [--ppp 0.001 0.005] [--rays 2000] [--camera table43|demo]
        [--photons 25000] [--threads 2] [--iterations N] [--seed 0 [1 ...]] [--compare jacobian=forward ...]
        [--imperfections lenslet_gap_error=0.05]
    python benchmarks/bench_ipr.py --memory [--memory-particles 100] [--threads 1]

For each ppp, a particle field over the crop's field of view and the thesis' 7 mm depth is
imaged with Monte-Carlo rays (``--rays`` per particle) plus shot noise (``--photons`` per
particle), on a camera whose lenslet grid is offset by (0.013, -0.021) mm; the lenslet grid is
calibrated from a pinhole image, and :func:`lfstudy.reconstruct.ipr.ipr_particles` fits with the
exact model on that calibrated grid (no inverse crime). Printed: particles found (a true particle
with a fitted one within half a voxel, per-axis scaled), ghosts (fitted particles with no true one
within half a voxel) as % of the fitted, rms position error of the found ones in mm and voxels
(x, y together, z on its own), IPR wall time (after a warm-up that compiles the kernels) and the
process' peak RSS. ``--crop`` trades coverage for time: the full sensor is 4872 x 3248.

Where the time goes: the split of the IPR time into the candidate MART volumes, the exact particle
images (:func:`lfstudy.reconstruct.ipr.particle_patches`) and the fit kernels (the rest: peaks,
bookkeeping), the full frame extrapolated at the crop's cost per particle (the crop's particle
count scaled by the sensor area), and per iteration the particles the shake's active set let sit out
(``shake_settle``; none by default). ``--compare k=v ...`` fits the same scene again with each setting
(one ``ipr_particles`` keyword each, e.g. ``jacobian=forward``, ``residual_candidates=3`` or
``residual_mart_iterations=0``; several keywords joined by commas, ``shake_settle=0.05,residual_late_gain=0``)
and prints the same line and the time ratio to the defaults, in the same run. The CPU time (all threads) is
printed beside the wall time: on a shared machine it moves less with the load.

``--imperfections k=v,...`` (``camera.imperfections`` of :mod:`lfstudy.simulate.imperfections`) renders the particles
and the pinhole calibration (then the exact pinhole image, with shot noise) through a camera the fit does not know;
``--compare image_calibration=2`` fits it again with images calibrated from its own particles
(:mod:`lfstudy.reconstruct.image_model`, issue 39 §2). Found / ghosts in %, final residual, rms z in mm, CPU s
(``--crop 300 300 --ppp 0.005 --threads 1``, load 10-17 on 2 cores): a lenslet array 5 % off its focal length
(``lenslet_gap_error=0.05``), nominal images -> calibrated: seed 12 70.2 / 33.8, 0.364, 0.109 -> 80.7 / 17.9, 0.297,
0.068 (CPU 32.5 -> 54.5 s; the search then rendered two images per particle and trial, now one); seed 13 69.1 / 31.0,
0.367, 0.111 -> 78.4 / 17.1, 0.305, 0.067 (CPU 27.6 -> 42.1 s). The ideal camera (``lenslet_gap_error=0``): seed 12
79.3 / 15.9, 0.293, 0.070; seed 13 80.2 / 16.9, 0.291 -> 80.4 / 16.7, 0.290 (CPU 26.5 -> 39.9 s). So the gap costs
9-10 points of found and doubles the ghosts, and the calibration gives them back; ``distortion_k1=0.01`` costs
nothing on this crop (seed 12: 80.0 / 16.1). On the ideal camera the first round took a blur x1.51 (gap -0.0007;
‖R‖² -0.7 %, a wider image hedging the positions after three iterations), the second kept it (load ~2: IPR 25.3 ->
36.9 s, the same found and ghosts); the largest change of an image on the axis was 3-10 % of its peak. What the
calibration took (load ~3): seed 13, gap 0.05: gap +0.041, blur x1.94 (IPR 29.9 -> 43.7 s); seed 14, gap 0.02: 78.4 /
20.5, 0.299, 0.085 -> 80.0 / 17.1, 0.284, 0.068, gap +0.016, blur x1.70 (33.8 -> 44.3 s); seed 15, gap 0.05: 69.8 /
29.9 -> 79.8 / 18.4 (gap +0.041, blur x2.33), with the blur held at 1 (the gap alone, a script's patch of
``_STEPS``) 79.1 / 20.4 (gap +0.038). The gap comes out ~20 % short and the blur wide: the particles it is fitted to
sit where the nominal images put them after three iterations, and a wider image hedges their errors.

Targets (issue 27): >= 95 % found within half a voxel at 0.001 ppp, >= 80 % at 0.005 ppp,
<= 10 % ghosts; a full frame at 0.005 ppp in <= 10 min on 2 cores and <= 8 GB. The targets are judged on
``found`` over all the true particles of the crop. Printed besides: found over those inside the reconstruction
grid (the grid holds the seeded field: none outside, the count says so) and split into the particles whose whole
image lies on the crop (defocus spot plus a lenslet inside its edges) and those near its edges, whose light field
the crop cuts: on a 400 x 400 px crop 40-45 % of the particles, on the full sensor about 5 %.
0.01 ppp (``--ppp 0.01 --crop 400 400 --seed 51 --threads 1 --compare batch=2048``, load 6-7 on 2 cores): 1,600
true particles, 1,471 fitted; found 64.4 %, ghosts 36.4 %; rms x,y 0.114 voxel, z 0.204 voxel; IPR 180 s (CPU 58 s),
11 MART volumes 68 s, 185,255 particle images 91 s; every residual round adds particles (247 ... 31). The former
batch of 2048: found 62.9 %, ghosts 35.8 % (the batch moves only the first intensity fit of new candidates: the
faint ones' images go back into the residual after each batch), peak RSS 1.43 GB against 0.76 GB.
``bench_budget.py``'s docstring has the study at 0.01 ppp (Q, valid vectors, MART beside IPR) and why IPR's
particles fall short there.

The demo camera (``--camera demo``: config/demo.yaml's first design, M -1, 0.0888 mm lenslets at f/4, its 4 mm slab
on 0.25 mm planes; issue 39). Where a full 640 x 480 frame's time goes (the demo's own Monte-Carlo images of case
``mag~-1/.../flow~uniform_x``, frame a, through the reconstruct stage's function ``run_reconstruct``, 1 thread, load
~2-3 on 2 cores): IPR 68.2 s of CPU (114.4 s wall beside a test run) for 1,467 particles: the 11 candidate MART volumes
29 % of the wall time, 227,548 particle images 62 %, the fit kernels 9 %; MART's volume of the same frame 0.9-2.3 s
(IPR / MART ~30x). With a cold numba cache (IPR's kernels compiled in the call, as in a fresh clone's first jobs) the
same fit took 139.0 s of CPU: 15 % / 74 % / 10 %. ``residual_volume=stack`` on that frame: 58.9 s of CPU (x0.86),
240,395 images, 1,495 particles (1,467 with ``mart``).
On 320 x 240 crops (``--crop 320 240 --ppp 0.005 --rays 2000 --photons 4000 --threads 1``, 384 particles) the
candidate volumes took 29-32 % of the wall time, the images 59-63 %.
The residual rounds' candidate volume (``--compare residual_volume=case residual_volume=case,residual_mart_iterations=1
residual_volume=stack residual_mart_iterations=0``; seeds 1, 2 looked at, 3, 4 held out; found / ghosts %, CPU s;
load 2-20 on 2 cores, so CPU, not wall):

==========  =================  =================  =====================  =================  =======================
seed        ``mart`` (default)  ``case``          ``case``, 1 iteration  ``stack``          MLOS (0 MART iterations)
==========  =================  =================  =====================  =================  =======================
1           81.5 / 15.0, 16.5  78.1 / 18.1, 13.2  75.8 / 18.8, 11.9      81.2 / 17.3, 13.7  81.8 / 16.7, 14.2
2           81.2 / 15.8, 15.6  75.8 / 19.3, 11.9  74.2 / 19.7, 11.0      80.5 / 16.4, 13.6  79.7 / 16.4, 13.0
3 (held)    79.4 / 18.0, 17.5  73.7 / 22.3, 12.9  71.9 / 21.5, 12.4      77.3 / 20.1, 14.4  77.1 / 21.1, 13.1
4 (held)    78.4 / 17.8, 14.5  75.8 / 17.9, 12.8  74.2 / 19.0, 11.6      77.9 / 18.9, 13.5  79.7 / 16.5, 14.5
==========  =================  =================  =====================  =================  =======================

None holds the default's accuracy: the case grid (one voxel per lenslet) loses 2.6-5.7 points of found; the focal stack
(``stack``) 0.3-2.1 points and adds 0.6-2.3 points of ghosts, for 7-18 % less CPU; MLOS alone moves found by -2.3 to
+1.3 points, ghosts by -1.3 to +3.1. The default stays ``mart``. The residual volumes are not where the time is: the
particle images are (issue 39's tabulated image).

Memory (``--memory [--memory-particles 100]``; issue 27: a full frame at 0.005 ppp in <= 8 GB). One IPR fit on the
full 4872 x 3248 px frame with a few particles: two candidate MART volumes on the refined grid (867 x 579 x 66,
33.1 M voxels, 0.27 GB a float64 volume), one MART iteration each (a volume's buffers are made once, whatever its
iterations: the memory is that of the default three, the time a third), the shake and the polish. Printed: the
peak RSS from the call on (Linux VmHWM, reset through /proc/self/clear_refs; it includes the 0.48 GB the scene holds
before), the weight tables and coverage, and the patches of one shake batch at uniform depths (the batch the few
particles do not fill: at 0.005 ppp every batch is full). Measured, seed 51, 1 thread, load 6-7 on 2 cores (one
full-frame volume of three iterations took 618 s there):

- 79bd03d: the plan alone (``mart_plan``) peaked at 8.21 GB (weight tables 5.18 GB, every plane padded to the
  widest plane's 10 voxels per beam, int32 starts; coverage 1.06 GB), a candidate volume of three iterations at
  9.44 GB (voxel-sized temporaries of the update, the smoothing and the MLOS guess, and ``np.sum`` of the four
  coverages stacked into one more 1.06 GB array); one shake batch of 2048 particles 4.72 GB of patches (~41,000 px
  per image box, 7 images a particle) on top of the plan.
- db2b9e4 (tables flat with each plane's own K: 4.03 GB; MART in place): IPR's peak 8.09 GB.
- now (the plan's coverage in float32: 0.53 GB; summed without stacking): IPR's peak 7.18 GB; a shake batch of 256
  particles (the new default) 0.59 GB, during the fit with the plan's 4.6 GB and the frame's arrays held, below
  the MART's peak. A full frame at 0.005 ppp: ~7.2 GB (the particle list itself, ~80,000 x a few floats, is
  small). MART's own volumes and the projector's tables keep their bytes (tests).

The measurements behind the defaults (moved here from the docstring of ``lfstudy.reconstruct.ipr``, which keeps a
line of figures per step; found / ghosts in % of the true / fitted particles, 1 thread unless said, the load on the
2 shared cores as given):

The fit (the defaults, then each setting against them; ``--crop 400 400``, Table 4.3 camera, seeds 0 and 1 used to
set the defaults): 0.001 ppp 88.8 % found within half a voxel, 8–10 % ghosts; 0.005 ppp 80–81 % found, 15–18 %
ghosts; 17–50 s per crop on 2 shared cores. With the polish (found / ghosts in %, ``--compare polish=0`` in the same
run; seeds 3 and 4 used to choose it, 5–7 held out; 1 thread, load 1–5 on 2 cores): 0.001 ppp, 400 x 400 px, seeds 3
/ 4 / 5 / 6 / 7: 92.5 / 5.2, 93.1 / 5.8, 89.4 / 8.4, 87.5 / 10.1, 88.1 / 9.6 (without: 88.8 / 9.1, 90.6 / 8.4, 88.1
/ 9.7, 86.2 / 10.7, 88.1 / 9.6); 0.005 ppp, 300 x 300 px: 87.3 / 14.3, 84.4 / 12.2, 81.8 / 14.3, 80.4 / 21.0, 79.1 /
18.6 (without: 85.3 / 15.9, 82.4 / 15.0, 80.2 / 16.0, 79.1 / 22.3, 79.6 / 18.4). It about doubles the particle
images (CPU +4–8 % at 0.001 ppp, +28–37 % at 0.005 ppp) and raises the final residual a little (0.246 -> 0.274 at
0.005 ppp, seed 5: the weighted mean is not the residual's minimum). What is left: particles whose image the crop
cuts (``bench_ipr`` splits found into those whose whole image is on the crop and the others: 93.1 % against 84.9 %
at 0.001 ppp, seed 5; 40–50 % of a 400 x 400 px crop's particles, about 5 % of the full sensor's), pairs behind one
lenslet near the focal plane (at 0.005 ppp most near-focus misses have a neighbour within a voxel and the fit one
particle of twice the intensity) and, at 0.005 ppp, the ghosts. Seed 6 at 400 x 400 px calibrates a lenslet pitch
5e-7 mm short of the nominal 0.125 mm; the model camera used to re-derive its "matched" main-lens f-number from that
pitch and round it up to the next stop (f/2.8 for f/2: a smaller aperture image, half the light in the wrong place,
the residual at 0.69, 87.5 % found). :func:`calibrated_camera` now keeps the nominal f-number: seed 6 finds 90.6 %,
8.4 % ghosts, residual 0.46 -> 0.33 (2 threads, quiet machine). Where the time goes (``--crop 300 300 --ppp 0.005``,
seed 7, 1 thread, load ~3 on 2 cores): 7–11 s of 18 s CPU in the 7 candidate MART volumes on the refined grid (the
first and one per residual round run), 8.9 s in 57,400 particle images (the shake's 30,640, 6.4 s; the polish's
25,110, 2.3 s: near focus an image is cheap), the fit kernels ~2 s. The plan (the tables and coverage made once per
fit, not per volume) takes 10 % off the fit's CPU time (seeds 7 and 8: 32.2 -> 29.0 s and 31.7 -> 28.9 s of CPU, the
MART part 13 % and 9 %; the same particles, byte for byte). Cheaper residual volumes trade quality for time (CPU
time; seeds 7 / 8 / 9 / 10, change of found in points): ``residual_mart_iterations=0`` x0.59–0.82, found −0.3 / −1.6
/ −5.1 / −4.4 (ghosts up to +4.6); ``residual_candidates=5`` x0.70–0.74, found −0.3 / +0.2 / −1.1 / −1.1, ghosts
−0.2 / −1.2 / +0.2 / +0.2 (the defaults are unchanged). ``residual_plane_step=2`` reconstructs the residual's
volumes on every other plane of the candidate grid, on views into the same tables (no new memory): each residual
volume costs half (seed 7, the same ten residual light fields, 1 thread: 9.7 -> 4.7 s CPU), the fit x0.67–0.73 of
the defaults' CPU time (seeds 7 / 8 / 9 at 0.005 ppp: 24.0 -> 17.5, 22.6 -> 15.8, 22.5 -> 15.5 s; 400 x 400 at 0.001
ppp, seed 7: 25.7 -> 17.2 s), found −1.6 / +0.6 / −0.9 and +0.7 points, ghosts +1.8 / −0.5 / −0.3 and +0.5: the
trade of ``residual_candidates=5``, so the default stays 1. A separate 3 x 3 x 1 grid on the case's own planes did
better on seed 7 (found −0.3, ghosts +0.5, CPU x0.74) but adds half the tables' memory. Skipping the residual rounds
that repeat the last one (``residual_candidates_min_gain``; found / ghosts in %, CPU s, against ``--compare
residual_candidates_min_gain=0`` in the same run, 1 thread, load 1–4 on 2 cores; seeds 5–9 seen while choosing the
value, 10 held out): with 0 the rounds after the fourth add 0–2 particles each at 0.001 ppp and 0–10 at 0.005 ppp
(every other peak of those volumes is rejected again). 0.01 stopped too early (found −1.1 points at 0.005 ppp, seed
6, whose rounds 6–10 still added 11 particles; −0.6 at 0.001 ppp, seed 8), 0.003 too (seed 9 at 0.005 ppp: stopped
after a round adding one of 419, found 84.7 -> 84.0 %, ghosts 13.4 -> 14.1 %), so the default is 0.001 (the value
chosen, then checked on seed 10): on these crops (150–450 particles) the rounds stop after one that adds none; on a
full frame (~100 times the particles) it stops after a round adding fewer than 0.1 % of the list, which the crops
cannot resolve (one particle is 0.2–0.7 % of theirs). 0.001 ppp, 400 x 400 px, seeds 5 / 6 / 7 / 8 / 9: 89.4 / 8.4,
90.6 / 8.5, 88.1 / 9.0, 86.2 / 9.3, 90.6 / 5.8 (with 0: 89.4 / 8.4, 90.6 / 8.4, 88.1 / 9.6, 86.2 / 9.9, 90.6 / 5.8),
4–6 of the 11 MART volumes, CPU x0.46–0.66 (13.8 / 14.7 / 15.8 / 15.8 / 11.6 s against 24.3 / 24.9 / 24.1 / 26.4 /
25.1 s); 0.005 ppp, 300 x 300 px: only seed 7 has a round adding none (the sixth): 79.3 / 17.3 against 79.1 / 18.4,
CPU 21.6 -> 17.0 s; seeds 5, 6, 8, 9 run every round (the fit of the defaults before). Seed 10: 0.001 ppp 93.8 / 3.8
either way, CPU 25.8 -> 13.4 s (three rounds of ten); 0.005 ppp every round (82.0 / 14.7). At 0.005 ppp the rounds
keep adding a few particles to the end. Since then, once a round adds fewer than ``residual_late_gain`` (0.01) of
the list, the later volumes take one MART iteration (half a volume's CPU) and add about what full ones would (seeds
10 / 11: 8 / 3 particles against 9 / 2; seed 8: none, the rounds then stop, against 10) (found / ghosts %, CPU s, 1
thread, load 2–5, same run, 0 -> 0.01; seeds 7, 8 chose it: 79.3 / 17.3 both, 82.2 / 17.6 -> 82.0 / 17.4; held out,
0.005 ppp, 300 x 300 px: seed 10 82.0 / 14.7, 23.5 s -> 82.0 / 14.1, 21.0 s, seed 11 84.4 / 14.6, 22.6 s -> 84.7 /
14.6, 20.9 s; 0.001 ppp, 400 x 400, seed 10: the same particles). ``shake_settle`` (the shake's active set; off): a
particle whose last shake moved it less than that (0.05 voxel tried), with nothing within ``_SETTLE_RADIUS`` (2)
voxels moved, added or removed, sits out up to 2 shakes: 15–40 % of the late shakes, CPU x0.84–0.86 held out, but
ghosts +1.3 / +1.7 points, found −0.7 / −0.8 (seeds 10 / 11, 0.005 ppp; 0.001 ppp the same found): at 0.005 ppp an
image's box holds hundreds of others' images, so a neighbour beyond 2 voxels still moves its residual. Seeds 7 / 8,
CPU and found: woken by lateral distance (any depth) within 2 voxels 1–3 % sat out, x0.92 / 1.00; within 1 voxel
x0.90 / 0.98, −0.6 / −2.0; a 3-voxel radius, one shake at most x0.95 / 1.02, +0.3 / −0.4; always shaking the faint
(< 0.5 median): no change. What did not help: MART restricted to the lenslets the residual lights (at 0.005 ppp the
median lenslet holds 12–37 % of the brightest lenslet's positive-residual energy, at 0.001 ppp 3–8 %; the residual's
first guess is above 3 % of its maximum in 70–75 % of the voxels, so every lenslet's beam box holds signal), nor
pruning the voxels below 1 % of the maximum after one iteration (the pruned volume still meets 6–100 % of the beam
boxes); screened on seed 7's residuals against the full volumes' peaks (388 over ten rounds; found / extra): every
other view column 240 / 199, every other view row 305 / 230, a 2 x 2 x 2 grid 298 / 136, a warm start from the
previous residual's volume with one iteration 317 / 166 (two: 361 / 140), against 363 / 110 on every other plane.
Both dominant costs scale with the frame: at this cost per particle a full Table 4.3 frame at 0.005 ppp stays far
above the issue's 10 minutes on 2 cores (~60 min on a quiet machine, x0.9 with ``residual_late_gain``: seed 10's
21.5 s of CPU at 1 thread scale to 63 min, 24.0 s without to 70 min; the attrs ``seconds_*``, ``particle_images``
and ``mart_volumes`` hold the split).

Threads (``--crop 1184 800 --ppp 0.005 --seed 10 --threads N``, 2026-12-04 on 91ca240; 1 and 2 threads on this
2-core machine, 4 and 16 on a 16-core Xeon lent for the session; the same 4245 particles, 82.5 % found, 12.8 % ghosts
on every run; wall s: IPR / MART candidates / particle images / the Gauss–Seidel kernels (``seconds_fit``), then by
step candidates / shake / polish):

=======  =====  =====  ======  ============  ==========  =====  ======
threads  IPR    MART   images  Gauss–Seidel  candidates  shake  polish
=======  =====  =====  ======  ============  ==========  =====  ======
1        220.7  123.3  70.4    24.4          125.7       77.9   17.0
2        155.9  82.4   43.9    26.9          84.7        60.6   10.5
4        101.4  49.7   24.6    24.6          51.5        43.4   6.4
16       62.2   26.3   9.2     24.2          27.9        30.2   4.0
=======  =====  =====  ======  ============  ==========  =====  ======

Against 1 thread here (two CPUs, so roughly), the images scale x7.7 at 16 threads, the MART volumes less (x4.7:
``_column_forward`` splits the planes into 8 blocks), and the Gauss–Seidel kernels not at all: at 16 threads they are
39 % of the fit. The full frame at 0.005 ppp (79,121 particles, seed 10, 16 threads on that machine) had not finished
after 9 min 15 s (the kernels' compile and the scene included; 3097 s of CPU, 5.6 cores on average), its peak RSS
7.94 GB by then: a real frame, not the few particles of ``--memory``, sits at issue 27's 8 GB.

Since then the Gauss–Seidel kernels visit only the pixels each patch's images light (``lit_pixels``, the same bytes;
the same crop, seed and particles, this machine, quiet): 1 thread IPR 206.3 s, MART 120.4, images 68.8, Gauss–Seidel
14.7 (24.4), shake 67.8 (77.9); 2 threads IPR 127.4 s, MART 74.4, images 38.0, Gauss–Seidel 12.5 (26.9), shake 41.6
(60.6). The MART volumes moved by 3–10 % between runs of the same code, so read the fit's total with that spread.

The images (``image_accuracy``): the fit's results do not move beyond the seed noise (``bench_ipr.py --threads 1
--compare image_accuracy=exact``, fast / exact, load 5–7 on 2 cores): 300 x 300 px at 0.005 ppp, seed 7: found 79.6
/ 79.6 %, ghosts 18.1 / 18.4 %, rms x,y 0.070 / 0.071 voxel, z 0.145 / 0.144 voxel, CPU 20.4 / 22.7 s; seed 8: found
80.4 / 79.8 %, ghosts 20.0 / 20.3 %, rms 0.071 / 0.069 and 0.135 / 0.134 voxel, CPU 20.2 / 23.2 s; 400 x 400 px at
0.001 ppp, seed 7: the same 156 particles' figures (88.1 %, 9.6 %, 0.047 and 0.090 voxel), CPU 25.3 / 25.7 s (the
MART candidates dominate there). (CPU per image: ``bench_particle_image.py``'s docstring.)

Forward differences for the shake's Jacobian (``--compare jacobian=forward``: three trial images a particle and
iteration instead of six; run 2026-12-04, ``--camera demo --crop 320 240 --ppp 0.005 --rays 2000 --photons 4000
--threads 1 --seed 1 2 3 4``, quiet machine; defaults -> forward, found / ghosts %, rms x,y and z mm, CPU s): seed 1
82.3 / 14.7, 0.0058, 0.0348, 8.8 -> 81.2 / 15.9, 0.0061, 0.0332, 6.7; seed 2 81.8 / 16.0, 0.0059, 0.0368, 9.0 -> 79.9 /
18.1, 0.0062, 0.0369, 7.3; seed 3 80.5 / 17.2, 0.0053, 0.0349, 9.7 -> 78.4 / 19.8, 0.0056, 0.0385, 8.2; seed 4 79.4 /
16.9, 0.0048, 0.0343, 8.2 -> 80.2 / 17.0, 0.0053, 0.0347, 7.8. CPU x0.76-0.95 (fewer images, and the residual rounds
stop earlier), found -2.1 to +0.8 points, ghosts +0.1 to +2.6, x,y rms +3 to +10 %: the default stays central.

The polish's screen (``_POLISH_SCREEN`` in ``lfstudy/reconstruct/ipr/polish.py``; issue 39, fewer images per
particle). Where the images went on the demo camera (``--camera demo --crop 320 240 --ppp 0.005 --rays 2000 --photons
4000 --threads 1``, seed 1, counted by caller): the polish's stencils 30,738 (51.5 %), the shake 28,560 (47.8 %). 192 of
the 360 particles are near focus, and in the first round 79 % of them move less than 0.02 voxel: their current
position already holds the stencil's weight. Rendering the stencil's 8 axis positions first (with the current one)
and the other 36 only where an axis position weighs at least e^-10 of the current one: seeds 1 / 2 (used to choose
e^-10) and 3 / 4 (held out) give the same found, ghosts and rms as before to the digit (81.5 / 15.0, 81.2 / 15.8,
79.4 / 18.0, 78.4 / 17.8), particle images 55,681 -> 43,862 and 56,570 -> 46,086 (-21 %, -19 %; the polish's -46 %),
CPU of seeds 1 and 2 over two alternating runs each (the screen off by setting it to inf: the stencil's current
position then rendered twice, 56,257 / 57,149 images) 10.5 / 11.5 and 12.5 / 12.7 s without, 9.4 / 12.0 and 9.1 / 9.6
s with it (load 1-2). Held out on the Table 4.3 camera (``--crop 300 300 --ppp 0.005
--threads 1``, seeds 5 / 6 / 7, before -> after): found 81.3 -> 80.9, 80.2 -> 80.0, 79.3 -> 79.3 %, ghosts 14.6 -> 14.9,
21.0 -> 21.2, 17.3 -> 17.3 %, images -18 / -17 / -18 %, CPU 17.0 / 18.4 / 16.7 -> 16.8 / 18.6 / 18.8 s (there the
near-focus images the screen saves are the cheapest, 0.1 ms, and the load varied). With e^-7 instead one screened
particle of 708 would have moved 0.30 voxel; with e^-10 none of 643 more than 0.02.

By step (the fit's attrs ``seconds_step_<step>`` / ``particle_images_<step>``, printed as "by step"; run 2026-12-04,
``--camera demo --crop 320 240 --ppp 0.005 --rays 2000 --photons 4000 --threads 1 --seed 1 2``, quiet machine): the
candidates (the MART plan and 11 volumes, and the new candidates' intensities) 4.1 / 4.6 s, the shake with the ghosts'
removal 3.6 / 3.6 s (17,270 / 18,194 images), the polish 1.5-1.6 s (13,737 / 14,173 images), of 9.3 / 9.8 s. On the
demo's four designs, their full 640 x 480 frames (seed 7, frame a, the study's stored light fields refitted with the
defaults, 1 thread; CPU s, candidates / shake / polish, and found / ghosts %): M -1, pitch 0.0888 mm 36.8 s, 14.7 /
17.2 / 4.9, 80.6 / 14.3; M -1, 0.1184 mm 41.6 s, 15.1 / 16.2 / 10.3, 62.4 / 33.4; M -0.8, 0.0888 mm 35.8 s, 12.8 /
10.4 / 12.6, 53.1 / 43.1; M -0.8, 0.1184 mm 39.7 s, 11.9 / 10.3 / 17.6, 30.3 / 63.3. The polish's share grows from 13 %
to 44 % where the fit finds least: there the residual is flat about most particles, the screen passes them, and
each gets the whole 45-point stencil (76 % of the M -0.8, 0.1184 mm frame's particles, three rounds). Two ways to cut
it were measured there and not kept, since each moves some particles: a finer screen (an off-axis stencil point
rendered only where one of its axis projections weighs at least e^-10) keeps 56 % of the off-axis points and changes
the weighted mean of 0.11 % of the full-stencil particle-rounds by more than 0.01 voxel (at most 0.5); letting a
particle that moved less than 0.005 voxel in a round sit out the next would skip about half of them in rounds 2 and
3, but 2.8-3.2 % of those then move 0.02-0.5 voxel in the round they would have skipped. A rule that skips a
particle because its patch saw no change does not apply: at 0.005 ppp each patch's box meets those of ~75 others.

The polish's order (issue 39; ``_runs`` in ``lfstudy/reconstruct/ipr/polish.py``). The polish moved every particle at
once, each by drops of the residual computed with the others where they were: on the demo's coarse designs (every
particle near focus, several behind each lenslet) two particles sharing lenslets each took the other's data for its
own and both moved into it, and the residual rose from 0.16-0.20 to 0.21-0.35 of the data's norm (``residual_norm``'s
last entry, demo study, all 16 frames). Now it moves them one run after another, each run at most 32 particles whose
patches do not overlap, packed from the list, on the residual the runs before it left (Gauss–Seidel, as the shake):
the residual falls in the polish (0.161 -> 0.156 and the like). ``--camera demo --crop 320 240 --ppp 0.005 --rays 2000
--photons 4000 --threads 1`` (found / ghosts %, z rms mm; before -> after; no seed was used to choose anything): seed
1 81.5 / 15.0 -> 81.8 / 14.7, 0.0357 -> 0.0344; 2 81.2 / 15.8 -> 81.2 / 16.1, 0.0366 -> 0.0373; 3 79.4 / 18.0 -> 80.7 /
16.4, 0.0372 -> 0.0352; 4 78.4 / 17.8 -> 79.7 / 16.4, 0.0355 -> 0.0358; particle images 43,862 / 46,086 -> 42,234 /
43,384 (seeds 1, 2). Table 4.3 camera (``--crop 300 300 --ppp 0.005 --threads 1``), seeds 5 / 6 / 7: 80.9 / 14.9 ->
82.2 / 12.9, 80.0 / 21.2 -> 81.1 / 19.6, 79.3 / 17.3 -> 80.0 / 17.3; z rms 0.0751 / 0.0775 / 0.0741 mm (0.148-0.155
voxel). Cut from the list where two patches meet instead of packed, the runs held a few particles each and the images'
per-call cost (~0.3 ms) raised the polish's CPU per image by ~70 %.

The batch (``batch``, particles rendered at once; not a config key): it sets the patch memory and changes the fit by
rounding only (the faint residual candidates are now added back once every candidate is fitted, not batch by batch).
An image costs less in smaller batches (quiet machine, one thread): ``--camera demo ... --seed 1 --compare batch=256
batch=64 batch=256`` (the same 360 particles, found and ghosts to the digit) 7.0 / 6.6 s of wall at 64 against 7.9 /
7.5 s at 256, the images 4.1 / 3.8 s against 5.1 / 4.7 s. One frame of the demo study (M -1, 0.1184 mm, uniform_x
frame a, its stored light field refitted, back to back with the commit before the polish's order and this batch):
36.1 -> 29.4 s (the shake's 101,736 images 0.144 -> 0.105 ms each; the polish's images 100,498 -> 69,270, its
order); the MART candidates 8.9 / 8.6 s of it. ``particle_patches`` alone (320 particles of that design, one image
each): ~0.33 ms a call on top of 0.09 ms an image (half of it Gauss–Legendre nodes recomputed in ``solid_angle``).
The default is 64 (0.15 GB of patches on the full Table 4.3 frame, against 0.59 GB at 256); below ~32 particles a
call the calls' own cost shows.

The polish (``polish``): before it, the missed particles and the ghosts were near the focal plane. On the Table 4.3
camera (spot radius 0.125·|z| mm, pitch 0.125 mm) the missed particles and the ghosts were these: 12 of the 18
missed at 0.001 ppp (seed 3) had |z| < 0.5 mm (of the 15 there; none missed beyond |z| = 2 mm), and each of the 14
ghosts was the fit of a missed particle within 1.5 voxel, 13 of them at |z| < 0.75 mm, mostly 0.5–0.7 voxel off in
z; started at the true positions the same fit keeps 96 % within half a voxel (2 % ghosts).

The split (``split``): ``bench_ipr --compare split=1`` (found / ghosts %, 1 thread, load 2–6 on 2 cores; seeds 3, 4
chose ratio 1.3 and penalty 16, 10–12 held out): 0.005 ppp, 300 x 300 px, seeds 3 / 4 / 10 / 11 / 12: 88.4 / 14.5,
86.7 / 12.0, 83.3 / 15.1, 85.8 / 15.3, 83.1 / 14.9 (without: 87.3 / 14.3, 84.4 / 12.2, 82.0 / 14.7, 84.4 / 14.6,
81.6 / 15.3); 0.001 ppp, 400 x 400 px: found +0 to +0.6 points, ghosts +0 to +1.2 (seed 12: two splits, both ghosts;
800 x 800 px: 90.3 / 7.6 -> 90.5 / 8.0); CPU +0–10 %. It stays off: ghosts rose in 4 of the 7 held-out fits. Most
misses are not such pairs: at 0.001 ppp single particles near focus fitted 0.55–0.7 voxel off in z (10 of seed 3's
12), at 0.005 ppp ghosts beside one found and one missed particle. Nor does moving those singles along z alone help
(a scan of ±1.5 voxel in 0.125 steps to the lowest exact ‖R‖², the others held; tried on branch h45, not merged):
found +0 / +0 / −0.6 points on held-out seeds 10–12 at 0.001 ppp. Given the other particles, most of them already
sit at the residual's minimum along z (by 10²–10³ σ² over the true depth), the rest on a stretch ~1.2 voxel long
flat to a few σ² with the true depth at its edge: the fix has to move a particle with its neighbours.

The residual rounds' volume (``residual_volume``): none holds the default's accuracy on the demo camera (``--camera
demo``, the table above; seeds 3, 4 held out): ``case`` loses 2.6–5.7 points of the particles found, ``stack``
0.3–2.1 points and adds 0.6–2.3 points of ghosts, for 7–20 % less CPU; the candidate volumes take 15–30 % of the
fit's time there, the particle images 60–75 %.

Memory (``--memory``, the full Table 4.3 frame): the candidate plan dominates, the refined grid's weight tables
(4.03 GB: each plane's own beam width, int16 starts) and the four subsets' coverage (0.53 GB, float32), then a MART
volume's buffers (0.27 GB each in float64, no voxel-sized temporaries); IPR's peak 7.18 GB (was 9.4 GB and more in
one MART volume). The particle images go ``batch`` (256) particles at a time: a shake batch of 2048 held 4.7 GB of
patches there. At 0.01 ppp (the study's and ``bench_ipr``'s figures in the benchmarks' docstrings) IPR's Q is above
MART's, its valid vectors and RMS error not: 56-64 % of the particles found, 35-37 % ghosts, nearly all misplaced
fits of real particles within 1.5 voxels of one (pairs behind one lenslet).
"""

from __future__ import annotations

import argparse
import inspect
import resource
import time

import numpy as np

WIDTH, HEIGHT = 4872, 3248  # Table 4.3


def _scene(
    width: int,
    height: int,
    ppp: float,
    rays: int,
    photons: int,
    seed: int,
    camera: str = "table43",
    imperfections=None,
):
    """The scene: ``table43`` the Table 4.3 camera over the thesis' 7 mm depth on the marching's grid; ``demo``
    the demo's first design (``config/demo.yaml``: 7.4 um pixels, 0.0888 mm lenslets at f/4, M -1, its 4 mm slab
    on a 0.25 mm z grid); ``imperfections`` (a mapping) renders the images and the pinhole by the imperfect
    camera the fit does not know."""
    from lfstudy.lightfield import find_lenslet_centers, register, synthetic_pinhole
    from lfstudy.optics import PlenopticCamera
    from lfstudy.reconstruct import ReconstructionInputs, make_grid
    from lfstudy.simulate import render, seed_particles
    from lfstudy.simulate.raytrace import render_pinhole
    from lfstudy.simulate.sensor import apply_sensor

    if camera == "demo":
        cam = PlenopticCamera(width, height, 0.0074, 0.0888, 4 * 0.0888, 50.0, -1.0, lenslet_offset_x=0.009)
        span, zr, vz = 4.0, (-2.0, 2.0), 0.25
    else:
        cam = PlenopticCamera(width, height, 0.0074, 0.125, 0.5, 50.0, -1.0, lenslet_offset_x=0.013)
        span, zr, vz = 7.0, None, None
    cam = cam.with_(lenslet_offset_y=-0.021)
    field = seed_particles(cam, ppp=ppp, z_span=span, seed=seed)
    if imperfections is None:
        pin = synthetic_pinhole(cam, amplitude=3000, seed=seed + 1)
    else:  # the calibration sees the imperfect camera too (the exact pinhole image, with shot noise)
        pin = render_pinhole(cam, seed=seed + 1, imperfections=imperfections, shot_noise=True)
    cen = find_lenslet_centers(pin, cam)
    img = render(cam, field, rays, seed + 2, method="montecarlo", imperfections=imperfections)
    lf = register(apply_sensor(img, photons_per_particle=photons, seed=seed + 3), cen, cam)
    grid = make_grid(cam, cam.focal_planes(), z_range=zr, voxel_z=vz)
    return field, ReconstructionInputs(lightfield=lf, centers=cen, camera=cam, grid=grid)


def _whole_image(cam, true: np.ndarray) -> np.ndarray:
    """True where a particle's whole image lies on the sensor: its defocus spot on the lenslet array (around
    where the chief ray meets it) plus one lenslet pitch inside the sensor's edges. The others, near the
    crop's edges, lose part of their light field (on a crop many more than on the full sensor)."""
    from lfstudy.reconstruct.ipr import _spot_pitches

    x, y, z = true.T
    d = cam.so + z
    reach = (_spot_pitches(cam, z) + 1.0) * cam.lenslet_pitch
    return (np.abs(cam.si * x / d) + reach <= cam.sensor_width / 2) & (
        np.abs(cam.si * y / d) + reach <= cam.sensor_height / 2
    )


def _score(field, parts, grid, cam=None) -> dict[str, float]:
    from scipy.spatial import cKDTree

    vox = np.array(grid.voxel_size()[::-1])
    true = np.column_stack([field[v].values for v in ("x", "y", "z")])
    fit = np.column_stack([parts[v].values for v in ("x", "y", "z")])
    lo = np.array([grid.x[0], grid.y[0], grid.z[0]]) - vox / 2
    hi = np.array([grid.x[-1], grid.y[-1], grid.z[-1]]) + vox / 2
    inside = np.all((true >= lo) & (true <= hi), axis=1)
    whole = _whole_image(cam, true) if cam is not None else np.ones(len(true), bool)
    if not len(fit):
        return {"found": 0.0, "ghosts": 0.0, "n_fit": 0}
    d_true, j = cKDTree(fit / vox).query(true / vox)
    d_fit, _ = cKDTree(true / vox).query(fit / vox)
    found = d_true < 0.5
    err = fit[j[found]] - true[found]
    return {
        "n_true": len(true),
        "n_fit": len(fit),
        "found": 100.0 * found.mean(),
        "n_outside": int((~inside).sum()),
        "found_inside": 100.0 * found[inside].mean() if inside.any() else float("nan"),
        "n_whole": int(whole.sum()),
        "found_whole": 100.0 * found[whole].mean() if whole.any() else float("nan"),
        "found_cut": 100.0 * found[~whole].mean() if (~whole).any() else float("nan"),
        "ghosts": 100.0 * (d_fit >= 0.5).mean(),
        "rms_xy_mm": float(np.sqrt(np.mean(err[:, :2] ** 2))),
        "rms_z_mm": float(np.sqrt(np.mean(err[:, 2] ** 2))),
        "rms_xy_vox": float(np.sqrt(np.mean((err[:, :2] / vox[:2]) ** 2))),
        "rms_z_vox": float(np.sqrt(np.mean((err[:, 2] / vox[2]) ** 2))),
        "mean_z_mm": float(np.mean(err[:, 2])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--crop", type=int, nargs=2, default=None, metavar=("W", "H"), help="sensor crop [px] (600 600; --memory: none)"
    )
    ap.add_argument("--ppp", type=float, nargs="+", default=[0.001, 0.005])
    ap.add_argument("--rays", type=int, default=2000, help="Monte-Carlo rays per particle")
    ap.add_argument("--photons", type=int, default=25_000, help="photons per particle (shot noise)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=None, help="default: the method's")
    ap.add_argument("--seed", type=int, nargs="+", default=[0], help="scene seeds (each run in turn)")
    ap.add_argument("--camera", choices=("table43", "demo"), default="table43", help="the scene (see _scene)")
    ap.add_argument("--compare", nargs="*", default=[], metavar="K=V", help="ipr_particles settings to compare")
    ap.add_argument(
        "--imperfections",
        default=None,
        metavar="K=V,...",
        help="camera.imperfections the images (particles and pinhole) have and the fit does not know",
    )
    ap.add_argument("--memory", action="store_true", help="peak memory of IPR on the full frame (see the docstring)")
    ap.add_argument("--memory-particles", type=int, default=100, help="--memory: particles seeded")
    args = ap.parse_args()

    import numba

    from lfstudy.reconstruct.ipr import ipr_particles
    from lfstudy.reconstruct.ipr.fit import STEPS

    numba.set_num_threads(args.threads)
    if args.memory:
        _memory(args)
        return
    w, h = args.crop or (600, 600)
    if args.camera == "demo":
        print(f"demo camera (config/demo.yaml's first design) {w} x {h} px; {args.threads} threads")
    else:
        print(f"Table 4.3 camera cropped to {w} x {h} px (full: {WIDTH} x {HEIGHT}); {args.threads} threads")
    runs = [("defaults", {})] + [(c, _setting(c)) for c in args.compare]
    field, inputs = _scene(160, 160, 0.002, 200, args.photons, 99, args.camera)  # warm-up: compile the kernels
    for _, setting in runs:  # of every setting (another one may compile other kernel specialisations)
        ipr_particles(inputs, **(setting | {"iterations": 1}))
    for ppp, seed in ((p, s) for p in args.ppp for s in args.seed):
        t0 = time.perf_counter()
        imp = None if args.imperfections is None else _setting(args.imperfections)
        field, inputs = _scene(w, h, ppp, args.rays, args.photons, seed, args.camera, imp)
        t_sim = time.perf_counter() - t0
        print(f"ppp {ppp}, seed {seed}: {len(field.x)} true particles (simulation {t_sim:.1f} s; imperfections {imp})")
        t_ref = None
        for name, setting in runs:
            kw = ({} if args.iterations is None else {"iterations": args.iterations}) | setting
            t0, c0 = time.perf_counter(), time.process_time()
            parts = ipr_particles(inputs, **kw)
            t_ipr, c_ipr = time.perf_counter() - t0, time.process_time() - c0
            t_ref = t_ref or t_ipr
            s = _score(field, parts, inputs.grid, inputs.camera)
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
            a = parts.attrs
            rest = t_ipr - a["seconds_mart"] - a["seconds_patches"] - a["seconds_fit"]
            full = t_ipr * (WIDTH * HEIGHT) / (w * h)
            print(
                f"  {name}: {s['n_fit']} fitted; found {s['found']:.1f} % within half a voxel, "
                f"ghosts {s['ghosts']:.1f} % of fitted; rms error x,y {s['rms_xy_mm']:.4f} mm "
                f"({s['rms_xy_vox']:.3f} vox), z {s['rms_z_mm']:.4f} mm ({s['rms_z_vox']:.3f} vox), mean z error "
                f"{s['mean_z_mm']:+.4f} mm; residual {a['residual_norm'][0]:.3f} -> {a['residual_norm'][-1]:.3f}\n"
                f"    found {s['found_inside']:.1f} % of the {s['n_true'] - s['n_outside']} inside the grid "
                f"({s['n_outside']} outside); {s['found_whole']:.1f} % of the {s['n_whole']} whose whole image is on "
                f"the crop, {s['found_cut']:.1f} % of the {s['n_true'] - s['n_whole']} near its edges\n"
                f"    IPR {t_ipr:.1f} s (x{t_ipr / t_ref:.2f} the defaults; CPU {c_ipr:.1f} s): "
                f"MART candidates {a['seconds_mart']:.1f} s "
                f"({a['mart_volumes']} volumes), {a['particle_images']} particle images {a['seconds_patches']:.1f} s "
                f"(and {a.get('particle_images_reused', 0)} reused from the shake's cache) "
                f"({1e3 * a['seconds_patches'] / max(a['particle_images'], 1):.2f} ms each), "
                f"fit {a['seconds_fit']:.1f} s, rest {rest:.1f} s; "
                f"full frame at this cost per particle {full / 60:.0f} min; peak RSS {rss:.2f} GB\n"
                "    by step (s / images): "
                + ", ".join(f"{k} {a[f'seconds_step_{k}']:.1f} / {a[f'particle_images_{k}']}" for k in STEPS)
                + "\n"
                f"    residual candidates: new particles per round {a['candidates_added']}, "
                f"{a['skipped_candidate_rounds']} rounds skipped; shakes sat out per iteration {a['shake_sat_out']}"
            )
            if a.get("image_calibration"):  # the camera's own particle images (issue 39 §2)
                change = ", ".join(
                    f"{z:+.1f} mm {m:.2f}" for z, m in zip(a.get("image_change_z", []), a.get("image_change_max", []))
                )
                print(
                    f"    image model: gap error {a['image_gap_error']:+.4f}, blur x{a['image_blur_scale']:.3f} "
                    f"(accepted per round {a.get('image_calibration_accepted')}, "
                    f"cost {a.get('image_calibration_cost')}); "
                    f"largest change of an image on the axis, of its nominal peak, per depth: {change or 'none'}"
                )


def _vm(key: str) -> float:
    """``VmHWM`` (peak) or ``VmRSS`` of this process [GB], from /proc/self/status (Linux)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024 / 1e9
    return float("nan")


def _reset_peak() -> bool:
    """Reset this process' VmHWM to its current RSS (Linux ``clear_refs`` 5); False where refused."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _memory(args: argparse.Namespace) -> None:
    """Peak RSS of one IPR fit on the full frame (``--crop`` if given) with ``--memory-particles`` particles:
    the candidate grid's MART tables, coverage and volumes (which do not depend on the particle count), then the
    patch buffers of one batch of the shake at the thesis' depths (which the few particles do not fill)."""
    from lfstudy.reconstruct.ipr import _MARGIN_PX, _REFINE_XY, _REFINE_Z, _refined, ipr_particles, particle_patches

    w, h = args.crop or (WIDTH, HEIGHT)
    ppp = args.memory_particles / (w * h)
    t0 = time.perf_counter()
    field, inputs = _scene(w, h, ppp, args.rays, args.photons, args.seed[0], args.camera)
    cg = _refined(inputs.grid, _REFINE_XY, _REFINE_Z)
    print(
        f"{w} x {h} px, {len(field.x)} particles; case grid {inputs.grid.shape}, candidate grid {cg.shape} "
        f"({cg.shape[0] * cg.shape[1] * cg.shape[2] / 1e6:.1f} M voxels); scene {time.perf_counter() - t0:.0f} s, "
        f"RSS {_vm('VmRSS'):.2f} GB (peak {_vm('VmHWM'):.2f} GB)",
        flush=True,
    )
    reset = _reset_peak()
    base = _vm("VmRSS")
    t0 = time.perf_counter()
    # two candidate volumes (the first and one of the residual) of one MART iteration each: the memory of a volume
    # does not depend on its iterations (every buffer is made once per volume), its time does (~5 min per full-frame
    # volume of three iterations on one shared core)
    kw = {"iterations": 1, "residual_candidates": 1, "mart_iterations": 1, "residual_mart_iterations": 1}
    kw |= {"residual_candidates_min_gain": 0.0, "polish": 1}
    parts = ipr_particles(inputs, **kw)
    a = parts.attrs
    peak = _vm("VmHWM") if reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(
        f"IPR ({kw}, {a['mart_volumes']} MART volumes) {time.perf_counter() - t0:.0f} s: peak RSS {peak:.2f} GB "
        f"({'since the IPR call' if reset else 'of the process'}; RSS before it {base:.2f} GB, of which the scene's "
        f"light field, centres and images); weight tables {a['weight_table_bytes'] / 1e9:.2f} GB, coverage "
        f"{a['coverage_bytes'] / 1e9:.2f} GB, one float64 volume {np.prod(cg.shape) * 8 / 1e9:.2f} GB",
        flush=True,
    )
    # one batch of the shake (the current image and six trials per particle) at uniform depths over the grid
    from lfstudy.reconstruct.ipr import calibrated_camera

    cam, _ = calibrated_camera(inputs.camera, inputs.centers)
    rng = np.random.default_rng(args.seed[0])
    g = inputs.grid
    n = inspect.signature(ipr_particles).parameters["batch"].default
    pos = np.column_stack([rng.uniform(c[0], c[-1], n) for c in (g.x, g.y, g.z)])
    vox = np.array(g.voxel_size()[::-1])
    tr = np.vstack([np.diag(0.1 * vox), -np.diag(0.1 * vox)])
    buf = particle_patches(cam, *pos.T, trials=tr, pad=_MARGIN_PX, accuracy="fast")[0]
    print(
        f"one shake batch ({n} particles x 7 images, z uniform over the grid): {buf.nbytes / 1e9:.2f} GB of patches; "
        f"at most {peak + 2 * buf.nbytes / 1e9:.2f} GB with the step's images beside them on top of the peak above"
    )


def _setting(text: str) -> dict[str, object]:
    """``k=v`` (or ``k=v,k2=v2``: one setting of several keywords) as ipr_particles keywords (each v an int, a
    float or a string)."""
    out: dict[str, object] = {}
    for item in text.split(","):
        k, _, v = item.partition("=")
        for cast in (int, float, str):
            try:
                out[k] = cast(v)
                break
            except ValueError:
                pass
    return out


if __name__ == "__main__":
    main()
