#!/usr/bin/env python3
"""The lean fit (issue 20, item 3): `magcal fit` time, report time and memory per sample,
today's code against the code at --baseline-commit, measured in the same run.

    python3 bench/bench_fit.py [--repeat 3] [--baseline-commit f6f3a45]
                               [--report-baseline-commit f639afc]
                               [--previous-commit c6ef128] [--previous-only]
                               [--rows 36000,144000] [--no-memory] [--no-report]

Baselines: --baseline-commit (the fit before this work: per-sample einsum normal
equations) and --report-baseline-commit (the report as this work found it: the same
figures as today, drawn with constrained layout; the older commit's report has fewer
figures, so its time is printed but is no baseline) and --previous-commit (the tree before
the latest step: c6ef128, main before the fspeed14 work; also run with MAGCAL_WORKERS=1,
so that the ratio of the sensors' fits themselves is seen without the forks; and its
`magcal fit --no-report` end to end against today's, imports included). Each baseline's generator/ is
extracted from git (`git archive`) into a temporary directory; every measurement runs in a fresh subprocess with PYTHONPATH pointing at one
tree or the other, BLAS pinned to one thread (on a shared machine a threaded BLAS is
slowed by contention, which would blur the ratio). On the shared campaign
samsat_fm1/thermal_12pos.csv:

* fit: generator.pipeline.fit (read, all five sensors' fits: candidate degrees,
  held-out folds, covariances, checks), best wall time (time.perf_counter) and best CPU
  time of --repeat rounds (each round a fresh process per tree, trees interleaved, the
  better of two fits in it: the first also pays lazy imports). CPU is the process's own
  plus its reaped children's (os.times): today's fit runs the sensors in 2 forked
  children (generator.forked), whose CPU the process's own time would leave out. Today's
  fit is also run with MAGCAL_WORKERS=1 (the sensors one after the other, in the
  process), so that what the children buy is seen in the same run: wall time on a free
  second core, against the CPU the forks add;
* of it, fit.thermal.fit_unit (the sensors' fits alone, the issue's "fit itself"; wrapped
  in the driver): pipeline.fit also reads the files and, since a695085 (review #19 F),
  runs campaign.check.settling_warnings after the fits, in the process (~0.8 s CPU, then
  ~0.3 s); since fspeed12 that analysis runs inside fit_unit, beside the sensors' fits
  (fit_unit(beside=): one more item of the forked hand-out), so today's fit_unit holds
  it too; with the sensors serial it is timed on its own and taken off ("the sensors'
  fits alone");
* `magcal fit --no-report` end to end (python -m generator.cli in a fresh process, start-up
  and imports included, sensors forked as a user runs it) of today's tree and
  --previous-commit's, best wall and CPU (wait4, with the children's) of --repeat;
* report: generator.report.report.fit_report of that fit, figures drawn serially in the
  process (the CPU time they cost), best of --repeat; today's also as `magcal fit` draws
  them (2 forked children), wall and CPU;
* memory per sample: peak RSS (wait4) of generator.pipeline.fit (what `magcal fit
  --no-report` runs; the baseline has no --no-report) on the campaign
  repeated to each of --rows rows (bench_io.write_long_file), as the slope between the
  two lengths -- bytes the fit holds per additional sample, start-up and imports
  excluded.

Prints the figures of both trees and their ratios (baseline / today): the result is the
ratio, not the seconds. No thresholds (the issue's targets: fit under 1 s, figures under
1 s more, memory per sample far below the ~2 kB it measured).

One run (2026-11-24 ~12:05-12:17 UTC, 2 cores shared with other jobs, load average ~6,
--repeat 2; absolute seconds are inflated by the load, the ratios are the result):
  fit:    10.12 s (f6f3a45), 11.50 s (f639afc) -> 2.34 s   ratio 4.33x, 4.92x
  fit against ceb8243: 4.20 s -> 2.34 s   ratio 1.79x
  report (figures drawn serially): 8.89 s (f639afc) -> 7.17 s   ratio 1.24x
  fit memory per sample (peak RSS slope 36,000 -> 144,000 rows): 1959 B -> 907 B, 2.16x
A second run after the last commits (12:23-12:25 UTC, load average ~3.5, --repeat 2
--no-memory --no-report; 4deb5c3):
  fit:    9.30 s (f6f3a45), 10.97 s (f639afc) -> 2.03 s   ratio 4.59x, 5.41x
  fit against ceb8243: 3.87 s -> 2.03 s   ratio 1.91x
What made the step from ceb8243: each Gauss-Newton iterate's cost and gradient from sums
centred on the run's start (reference.ResidualStats; J^T W J already came from moments),
the held-out fold fits without the temperature-error covariance, one pass for the
linear start's sums and the plain and cross moments, single solves for a constant M.
Not yet at the issue's targets: the fit is still ~2x the 1 s target (145 reference
fits per campaign, each ~10 passes over its samples plus ~5 ms of fixed numpy/Python
cost; the held-out comparison is ~70 % of it, cProfile), and the figures (not changed in
this step) are ~7x the 1 s target.

A run after the forked sensor fits, Horner's M(T)/b(T) and the figure cuts (2026-11-24
14:04-14:10 UTC, load average ~2.5-3.6 on the 2 shared cores, --repeat 2
--previous-commit 6c7136b, the tree before these steps):
  today's fit, sensors serial (MAGCAL_WORKERS=1) -> forked: wall 3.17 s -> 3.23 s
    (ratio 0.98x), CPU 2.07 s -> 2.27 s (ratio 0.91x)
  fit CPU: 9.30 s (f6f3a45), 11.05 s (f639afc) -> 2.27 s   ratio 4.10x, 4.87x
  fit against 6c7136b: CPU 2.31 s -> 2.27 s (ratio 1.02x), wall 2.35 s -> 3.23 s
  report, figures drawn serially, CPU: 7.28 s (f639afc) -> 5.48 s   ratio 1.33x
  today's report, figures serial -> forked: wall 7.74 s -> 8.50 s, CPU 5.48 s -> 5.63 s
  fit memory per sample: 1966 B -> 911 B   ratio 2.16x
The wall times of that run are the load's: the forked children only shorten the wall
time when the second core is free, and during it the other jobs held it (a figure
worker's calls took ~2-3x their CPU time in wall). Alternating the two in one process a
few minutes later (fit after a first one, MAGCAL_WORKERS=1 / 2, three times each): wall
2.03, 2.15, 2.10 s serial against 2.25, 1.36, 1.44 s forked, CPU 2.02-2.08 s against
2.17-2.33 s (the forks cost ~0.1-0.25 s of CPU: five sensors over two children, 3 + 2,
bound the wall time at ~3/5 of the serial one). Serially the fit's CPU went 2.31 s ->
2.07 s (Horner's rule for M(T), b(T): ~12 % of the fit before, cProfile; the reference
directions counted on a sample of the rows).

A run after the fspeed10 steps (2026-11-24 18:29-18:31 UTC, load average 2.4-2.6 on the
2 shared cores, --repeat 2 --no-memory --no-report; --previous-commit 5335ede, main
before them; e1fb205):
  fit against 5335ede, sensors serial (MAGCAL_WORKERS=1): CPU 4.36 s -> 2.04 s (ratio
    2.14x), wall 4.49 s -> 2.05 s (ratio 2.19x)
  fit against 5335ede, forked (CPU with the children's): CPU 4.58 s -> 2.17 s (ratio
    2.11x), wall 4.64 s -> 2.16 s (ratio 2.15x)
  today's fit, serial -> forked: wall 2.05 s -> 2.16 s (0.95x: the other jobs held the
    second core during the run; five fits in a row in one process right after, 18:32
    UTC: forked 1.34-2.26 s wall, 1.34 s when the second core was free; serially
    1.99-2.17 s CPU)
  fit CPU: 8.97 s (f6f3a45), 10.42 s (f639afc) -> 2.17 s   ratio 4.13x, 4.80x
The coefficients.json of seven fits (bench/fit_equivalence.py, 18:36 UTC: the shared
unit's thermal campaign, all its files, its orbit file on a prior, the demo's ground
campaigns, three simulated units of other parts) are identical to 5335ede's bit for bit
but for the 1-sigma of the thermal campaign's fit (uncertainty_1sigma and the
observability sigmas: at most 5e-15 relative, the temperature reporting step's
covariance summed per bin); coefficients, degrees, flags, warnings and texts identical. What made the step: the segment finder
(merged after the profile above: 1.7 s of the 4.4 s at 5335ede, process time per part)
tests its (start, stop) pairs as arrays in bands of decreasing duration and stops at the
first band with a pass (0.14 s for five sensors); the noise check's M(T)^+ and the checks'
b(T), M(T) once per reported temperature value (calibration.PerValue); the temperature
reporting step's covariance from each (file, value) bin's moments instead of a (N, 12 K)
row per sample; fixed costs of each reference fit (J^T W J assembled in place, one
file's groups without a sort, the linear start's design once, the clipped second
differences on contiguous axes).
Where the serial 2.0-2.1 s goes now (process time per part, MAGCAL_WORKERS=1): the
held-out folds' joint fits 30 % (20 fits of 27,000 samples, ~30 ms each: ~8 passes over
the samples that no moment can replace -- residuals at each Gauss-Newton start and end,
second differences, M(T)^-1 r), their per-level fits 26 % (120 constant fits of ~2,500
samples, ~4 ms each, mostly fixed numpy cost), the five final fits 15 %, the noise and
misfit checks 10 %, reading the samples and finding the segments 9 %. Evaluated and not
taken: warm-starting the folds' Gauss-Newton from the full fit (an iterate costs no pass
over the samples, ~0.3 ms, and the runs take ~3 iterates: < 0.05 s to gain, for results
that move within the stopping tolerance instead of being identical); moments shared
across folds (only the moment passes are additive, ~7 ms of a fold's ~30 ms, and the
cross moments with x_hat depend on each subset's mean offset). The 1 s target is not
reached: serially ~2x it, forked ~1.35x when the second core is free.

A run after the fspeed11 steps (2026-11-24 19:54-19:59 UTC, load average 2.5-3.4 on the
2 shared cores: other helpers' jobs held the second core, so every wall time of the run
is the load's; --repeat 3 --no-memory --no-report; --previous-commit ce2b43f, main before
them; f058c6a):
  fit against ce2b43f, sensors serial (MAGCAL_WORKERS=1): CPU 2.90 s -> 2.64 s (ratio
    1.10x)
  of it fit.thermal.fit_unit, the sensors' fits alone, serial: CPU 2.03 s -> 1.86 s
    (ratio 1.09x); forked (CPU with the children's): 2.12 s -> 2.05 s
  today's fit_unit, serial -> forked: wall 2.49 s -> 3.16 s (the second core was taken)
  fit CPU: 8.92 s (f6f3a45), 10.61 s (f639afc) -> 2.87 s (forked, with the children's)
A second run on the final tree (a1356ca: also the sensors handed to the children on
demand; 20:08-20:13 UTC, load average 2.2-5.7, same options):
  fit against ce2b43f, sensors serial: CPU 2.95 s -> 2.80 s (ratio 1.05x)
  of it fit_unit, serial: CPU 2.09 s -> 1.97 s (ratio 1.06x); forked: wall 2.23 s ->
    2.15 s, CPU with the children's 2.22 s -> 2.10 s
  today's fit_unit, serial -> forked: wall 1.98 s -> 2.15 s (the second core was taken)
  fit CPU: 9.31 s (f6f3a45), 10.98 s (f639afc) -> 2.93 s (forked, with the children's)
So the step is 5-10 % of the sensors' fits' CPU, within what the load moves between
runs. Alternating serial and forked in one process right after (20:13 UTC, load ~3.5,
fit_unit, three times each): serial 2.31, 1.93, 1.87 s wall (CPU 1.86-2.23 s); forked
2.02, 1.96, 1.25 s wall (1.25 s the one time the second core was free; pipeline.fit
2.14 s wall then, against 2.71-3.59 s serially).
pipeline.fit is no longer the sensors' fits alone: since a695085 (review #19 F, merged
before ce2b43f) it runs campaign.check.settling_warnings after them, in the process: it
reads the files again and runs check_campaign (segments, a reference fit and the design
covariance per sensor), ~0.8 s CPU of the 2.6-2.9 s (cProfile: poly_covariance 0.24 s,
find_segments 0.18 s, reference_fit 0.14 s, reading 0.07 s). That is outside generator/fit.
What made the step (each checked bit for bit on the recorded calls of the campaign: 15
find_segments calls, the 120 held-out per-level fits and the 25 joint fits): the
segment finder's settled windows and its settled-part search take their spans from one
pair of max/min range tables per run (find_segments 0.331 s -> 0.264 s on the 15 calls);
normal_matrix writes its M-M blocks and errors-in-variables diagonal in one indexed
operation each (110-163 us -> 50 us per call at degree 0, ~10 calls per fit); M(T)^-1 v
with M = I (the nominal prior: every fit's information point) is v itself, not a LAPACK
solve (2.5 ms -> 0.04 ms per 27,000 rows). Also bit-identical, no measurable time:
difference_noise_var's first clip pass as one reduction per axis row, the constant fit's
one-node projection skipped.
Evaluated and not taken:
* batching the per-level constant fits: a level fit costs ~3.1 ms fixed plus ~0.7 us per
  sample (40 recorded level fits subsampled and repeated to 552 / 2,208 / 8,832 samples
  per fit: 3.51 / 4.69 / 7.53 ms, load ~4.5), so of the 120 held-out level fits' ~0.55 s,
  ~0.37 s is fixed cost -- spread over ~150 small numpy calls per fit (Gauss-Newton ~40 %,
  then the moments, the noise bound's clip iterations, the linear start, the two eigen
  splits, ~0.3 ms each), no single one worth a special case. Only a stacked version of
  reference_fit's whole degree-0 path (two passes, per-problem noise clipping, splits,
  Gauss-Newton with its line search, per-file weights) would remove it: at most ~0.3 s
  of the ~1.9 s serial fit_unit, not written in this session;
* finer-grained hand-out of the forked work (generator.forked.forked_map(on_demand=True)
  now exists and fit_unit hands the sensors out with it: a child that finished a cheap
  sensor takes the next; the campaign's five equal sensors still split 3 + 2): the
  sensors' fits (serial CPU per part, MAGCAL_WORKERS=1, load ~3.5) are preparation
  (gather, segments) 8 %, held-out folds
  63 % (joint 0.65 s, per-level 0.59 s, scoring 0.06 s), final fits 16 %, checks and the
  rest 13 %. Five equal sensors in two children bound the wall time at 3/5 of the
  serial CPU (~1.1 s at 1.86 s); a perfect balance at 1/2 (~0.93 s). Folds handed out on
  demand while the preparation and the final fits stay per sensor (three forked phases,
  each sensor's samples pickled back after the first): ~(0.37 x 3/5 + 0.63 / 2) = 0.54 of
  the serial CPU, i.e. < 0.1 s gained before the extra forks and pickling; the full
  balance needs a dispatcher that hands each child its next item with its payload (the
  final fit after its folds, the samples shipped once per child and sensor): ~0.15 s at
  most. Not taken in this session.
The 1 s target is not reached: the sensors' fits take ~1.9-2.0 s CPU serially (~2x),
forked 1.25 s wall when the second core was free (its floor with five equal sensors in
two children is 3/5 of the serial CPU, ~1.15-1.2 s); pipeline.fit adds ~0.8 s of the
settling analysis, serial, in the parent.

After that (a7be45f: the settling warnings from the telemetry the fit has read and the
campaign check's cells only, 0.82 -> 0.30 s CPU) and the figs11 figure cuts, one run on
main 3a8fdab (2026-11-24 ~20:48-20:52 UTC, --repeat 2 --no-memory --previous-commit
5335ede, main at the start of this day's last session; the full test suite ran on the
other core, so the forked wall times are the load's):
  fit against 5335ede, sensors serial: CPU 4.30 s -> 2.20 s (1.95x), of it fit_unit
    4.20 s -> 1.87 s (2.25x)
  fit against 5335ede, forked: wall 3.55 s -> 1.89 s (1.88x), CPU 4.48 s -> 2.31 s
  fit CPU against f6f3a45 (before issue 20): 8.73 s -> 2.31 s (3.78x)
  report (figures drawn serially, with the report's own analysis), CPU: 6.51 s (5335ede)
    -> 3.31 s (1.97x); 7.05 s (f639afc) -> 3.31 s (2.13x)
Still not the issue's 1 s for the fit or for the figures.

A run after the fspeed12 steps (2026-11-24 22:58-23:07 UTC, load average 5.4-7.1 on the
2 shared cores: other helpers' jobs held both cores for the whole session, so every wall
time of the run is the load's and even the CPU times are inflated by the contention
(the same tree's CPU moved by 10-20 % between runs); --repeat 3 --no-memory --no-report;
--previous-commit 8248fa4, main before them; 61fb0e7):
  the sensors' fits alone (fit_unit less the settling analysis), serial: CPU 2.01 s ->
    1.92 s (ratio 1.05x)
  pipeline.fit, sensors serial: CPU 2.38 s -> 2.29 s (1.04x); forked, CPU with the
    children's: 2.67 s -> 2.60 s (1.03x)
  magcal fit --no-report end to end (imports included, forked): CPU 3.86 s -> 3.34 s
    (ratio 1.16x); wall 7.74 s -> 6.73 s (the load's)
  fit CPU against f6f3a45 (before issue 20): 9.63 s -> 2.60 s (3.70x)
An earlier run (22:42-22:50 UTC, load 4.5-7.0, same options, tree at efe91bc): the
sensors' fits alone 1.92 s -> 1.85 s (1.04x); magcal fit --no-report CPU 3.60 s -> 3.32 s
(1.09x). Forked wall times could be taken only once in the session with the load below
3 (22:35 UTC, load ~2.4, tree at 172d19b, one process, fits after a first one): fit_unit
1.13, 1.17, 1.13, 1.18 s wall (it now includes the settling analysis) and pipeline.fit
1.22-1.28 s; main's 8248fa4 three minutes before (load ~1-2, not interleaved) 1.25 s at
best for fit_unit and 1.63 s for pipeline.fit (1.71-4.59 s in its other runs). More
children than cores (MAGCAL_WORKERS=3 and 5, alternated with 2 in that minute) did not
help: 1.15-2.01 s and 1.28-2.44 s.
What made the step:
* the held-out per-level constant fits of a fold run side by side (fit.reference_batch):
  reference_fit is now a driver of reference_fit_steps, the one definition of the fit, a
  generator that yields its Gauss-Newton runs; reference_fits runs many such generators
  and does the constant fits' runs together, one stacked iterate for all (K = 1, masks
  over the eigenbasis for the fitted directions; each run stops on its own rule). The
  120 recorded level fits of the campaign: 0.51 s -> 0.39 s CPU (one process, 22:31 UTC,
  load ~1, alternated twice). The stacked iterates are the scalar ones' arithmetic in
  another order: coefficients within 5e-14 relative on those 120 calls
  (host_tests/test_reference_batch.py bounds them at 1e-5 of a 1-sigma, the stopping
  rule's reach). What remains per level fit (~3.2 ms) is its passes over the samples
  (moments, residual statistics, second-difference noise bounds: ~40 % by cProfile) and
  the per-fit logic between the runs (splits, linear start, weights, covariance: about
  as much), still run fit by fit;
* the settling analysis (campaign.check.settling_warnings, ~0.3 s CPU, reads only the
  files) runs as one more item of fit_unit's forked hand-out (fit_unit(beside=)), in the
  child that has two sensors, instead of after the fits in the parent: pipeline.fit's
  wall is fit_unit's plus reading, where it was fit_unit's plus ~0.3-0.4 s. With five
  equal sensors the two children are then balanced (3 sensors against 2 plus the
  analysis), so a finer hand-out of the sensors' phases has nothing left to gain;
* magcal fit no longer imports scipy.stats and scipy.ndimage (fit.special: the chi-square
  quantile via scipy.special.gammaincinv, the 3- and 5-sample running median by a min/max
  network; bit for bit the values of chi2.ppf and median_filter, host_tests/
  test_fit_special.py): magcal fit --no-report, user CPU 3.41-3.54 s -> 3.10-3.13 s,
  user+sys 3.64-3.77 s -> 3.29-3.44 s (22:27 UTC, load ~3.5, alternated three times);
* reference._powers in place (the joint fits' degree-12 moment powers 1.5 -> 0.4 ms per
  call), find_segments' band from the step and noise it computes anyway.
bench/fit_equivalence.py against 8248fa4 (22:51-22:54 UTC, tree at 61fb0e7): all seven
cases' coefficients.json identical bit for bit but for the held-out comparison's
"segments" scores (stats.holdout.segments.rms_vector_nT / rms_norm_nT, the per-level fits
now stacked): at most 4.3e-14 relative (demo), 9.7e-15 on the thermal campaign;
fm1_orbit_on_prior identical in every value. Coefficients, sigmas, degrees, choices,
flags, warnings and texts identical.
The 1 s target is NOT reached (not demonstrably, and by the estimate not quite): the
sensors' fits take ~1.85-1.9 s CPU serially under this session's load (~1.75 s estimated
on a quiet machine: last session's 1.87 s less the level batch's ~0.12 s), and five equal
sensors in two children bound fit_unit's wall at 3/5 of that, ~1.05 s plus the forks'
cost on a free second core (1.13 s measured at load ~2.4). What is left is per-sample work
that no rearrangement removes without changing bits: of the serial fit (py-spy, 22:38
UTC) the joint fits 42 % (20 held-out folds of 27,000 samples and the five final fits,
~40 ms each: moments 10 %, LAPACK's per-sample 3x3 solves of M(T)^-1 r 7 %, residual
statistics 6 %), the per-level fits 23 %, the noise and misfit checks 9 %, gathering and
segments 7 %.

A run after the fspeed14 steps (2026-11-25 01:36-01:38 UTC, tree at 4f8db14, the quietest
minutes of the session: the 1-minute load average 1.4 when the best wall times were
taken, this benchmark's own forked fits included; --repeat 5 --previous-only --no-report
--no-memory, --previous-commit c6ef128, main before these steps; best of 10 fits per
figure, two per process):
  pipeline.fit, sensors serial (MAGCAL_WORKERS=1): CPU 2.15 s -> 1.65 s (ratio 1.30x)
    of it fit_unit (sensors and settling analysis): CPU 2.03 s -> 1.56 s (ratio 1.30x)
    the sensors' fits alone: CPU 1.78 s -> 1.40 s (ratio 1.27x)
  forked (as magcal fit runs it): fit_unit wall 1.14 s -> 0.92 s (ratio 1.24x), CPU
    with the children's 2.16 s -> 1.69 s; pipeline.fit wall 1.23 s -> 1.01 s, CPU 2.26 s
    -> 1.79 s (the forks cost ~0.14 s of CPU against the serial fit)
  magcal fit --no-report end to end (imports included): wall 1.93 s -> 1.74 s, CPU 2.94 s
    -> 2.52 s
A second run on the final tree (d908c2e: also the per-value temperature index below;
02:05-02:07 UTC, load 1.3 at the start, 2.6 at the end, same options):
  pipeline.fit serial CPU 2.02 s -> 1.62 s (1.25x); fit_unit serial CPU 1.94 s -> 1.52 s
    (1.28x); the sensors' fits alone 1.70 s -> 1.37 s (1.24x)
  forked: fit_unit wall 1.13 s (load 2.4) -> 0.91 s (load 1.4) (1.25x), CPU with the
    children's 2.09 s -> 1.66 s; pipeline.fit wall 1.54 s -> 1.32 s, CPU 2.21 s ->
    1.77 s (the best pipeline.fit and the best fit_unit come from different fits: in
    the fit whose fit_unit took 0.91 s, pipeline.fit took 1.32 s or more; where that
    extra time went was not measured; the load rose during the run)
  magcal fit --no-report end to end: wall 1.79 s -> 1.57 s, CPU 2.77 s -> 2.32 s (1.19x)
The 1 s target for the fit itself is reached: fit_unit forked, 0.91-0.92 s wall on a free
second core (pipeline.fit, which also reads and checks the file, 1.01 s at best). Under
load it is not: at load ~1.2 (01:43 UTC, tree at 726115c, one process, six fits) fit_unit
took 0.98-1.21 s; with the other helpers' jobs on both cores (load 4-6, 01:10-01:35 UTC)
pipeline.fit took 2.0-2.9 s wall forked, and its serial CPU, alternated with c6ef128's in
the same minutes (01:25 UTC, load ~6, three processes each), was 1.80-2.21 s against
2.27-2.57 s.
What made the step (each bit for bit unless said; bench/fit_equivalence.py against
c6ef128, 01:32 UTC and again on 4f8db14 (01:39) and d908c2e (01:56) with the same
result: all seven cases' decisions, degrees, flags, warnings and texts identical,
coefficients and their 1-sigma identical bit for bit; fm1_all,
fm1_orbit_on_prior, demo and u_mmc identical in every value; fm1_thermal, u_lis and
u_phys differ in noise and held-out figures by at most 2.0e-16 relative -- mmc2's
observability noise data_bound_nT 1.2e-16, lis1's holdout.joint.rms_vector_nT 1.7e-16,
gen1's holdout.joint.rms_norm_nT 2.0e-16 -- from the one change that is not bit for
bit, the first below):
* M(T_n)^-1 v_n per sample by the adjugate (reference._solve3; LU where some M is near
  singular, |det| < 1e-3 of the product of its row norms): 5.0 -> 1.0 ms per 27,000
  samples, 30 calls a campaign; within a few ulps of LAPACK's LU
  (host_tests/test_solve3.py holds it to 1e-13 of the solution on calibration-like M);
  its result only enters the reading-noise bound, so nothing of the Gauss-Newton runs
  moved;
* the settling analysis (campaign.check with cells_only) skips what settling_warnings
  does not read (positions' directions and counts, levels' coverage, the cells'
  saturated counts, gaps), takes each level's near-sample mask once, and the approach
  look-back as a slice of a time-ordered file: 0.275 -> 0.20 s CPU (same cells, same
  warnings; the full check's result identical);
* the segment finder: both range tables looked up at once (segments._spans), the stop
  grid without np.unique, the four running sums in one cumsum, the block limit once:
  0.26 -> 0.21 s on the campaign's 10 calls (host_tests/test_segments_same.py holds
  every Segment field to c6ef128's code on the campaign, the PX4 office log's chip
  temperatures and generated hold profiles);
* the outer-product columns of the moments (reading_moments, the temperature-error
  moments, the linear start's design) written one contiguous product at a time (a 3x3
  broadcast runs inner loops of 3): reading_moments 5.0 -> 3.2 ms per 27,000 samples;
* the goodness checks evaluate the calibration on its samples once for both tests
  (goodness.Calibrated), one file's temperature step and pseudo-inverses from the same
  np.unique; the temperature bins from one np.unique of T; b(T) by Horner along the
  samples (calibration.b_at, ~4x); the fold subsets by index; one file's residual
  statistics without a masked copy;
* each sensor's distinct temperatures found once (_Samples.temperature_index, kept by the
  fold subsets): the held-out test sets' residuals, the score and the checks evaluate
  b(T), M(T) once per reported value (PerValue, the same numbers): ~30 ms of the serial
  fit.
Evaluated and not taken: the residual statistics' start residual with one product for
all powers and in-place sums (bit for bit, but no faster inside the fit: the line
profile moved within its noise); M(T) by Horner along the samples (bit for bit, but the
(9, N) -> (N, 3, 3) transpose costs more than it saves at 36,000 samples); the
calibrated readings z = M(T) y from contiguous rows (not the einsum's bits); the
moments' products in a transposed layout (3x faster, but BLAS then sums in another
order: up to 1e-13 relative on generated calls, and the moments feed the Gauss-Newton
runs, whose line search would then decide differently at convergence).
The hand-out (item 4): five sensors of ~0.28 s each and the settling analysis (~0.16 s)
over two children on demand split 3 sensors against 2 sensors + the analysis whatever
the order of the items (first or last: 3 s against 2 s + e either way while e < s), so
the settling item stays last; the wall is ~3/5 of the sensors' CPU plus the forks
(0.92 s measured against 3 x 0.28 = 0.84 s).

On main after the merges of this session (fspeed14, fitmem14's read cap, the recordings
checks, the reader's text columns; afa7856; 2026-11-25 02:16 UTC, no helper running, load
1.3; `--repeat 5 --previous-only --no-report --no-memory`, against c6ef128 in the same run):
  fit_unit forked (the issue's "fit itself"): wall 1.09 s -> 0.86 s (ratio 1.26x), CPU with
    the children's 2.07 s -> 1.59 s; serial CPU 1.97 s -> 1.52 s (1.30x)
  pipeline.fit forked (reading the file included): wall 1.19 s -> 0.97 s (1.23x); serial
    CPU 2.05 s -> 1.60 s (1.28x)
  magcal fit --no-report end to end (imports included): wall 1.79 s -> 1.53 s (1.17x)
A loop of eight pipeline.fit calls in one process two minutes before (load 0.65-0.76):
fit_unit 0.84-0.87 s, pipeline.fit 0.94-0.97 s wall. So the fit itself is under 1 s on a
2-core machine whose second core is free (under load it is not: 1.6-1.7 s with both cores
taken by other jobs, 01:55 UTC). The figures (bench/bench_figures.py, same minutes,
baseline c6ef128, load 1.5): they add 0.87-0.90 s to the report's wall time; the report's
own analysis and pages without figures take 0.67 s more.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import io
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "bench"))
from bench_io import FM1, write_long_file  # noqa: E402

DRIVER = r"""
import json, os, sys, time
from generator import pipeline
from generator.report import figures as F
from generator.report.report import fit_report
unit, data, out, report = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]


def timed(fn):
    # wall (perf_counter) and CPU of this process plus of its reaped children (os.times:
    # the forked sensor fits and figure workers are reaped before fn returns)
    w0, c0 = time.perf_counter(), os.times()
    r = fn()
    w1, c1 = time.perf_counter(), os.times()
    own = (c1.user - c0.user) + (c1.system - c0.system)
    kids = (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system)
    return r, w1 - w0, own, own + kids


# the sensors' fits alone (fit.thermal.fit_unit, which pipeline.fit imports when it runs):
# pipeline.fit also reads the files and, since a695085, runs the campaign check's
# settling analysis (campaign.check.settling_warnings) after them, in the process
from generator.fit import thermal as _thermal
_fit_unit, _inner = _thermal.fit_unit, []


def _timed_fit_unit(*a, **k):
    r, wall, own, cpu = timed(lambda: _fit_unit(*a, **k))
    _inner.append((wall, cpu, os.getloadavg()[0]))
    return r


_thermal.fit_unit = _timed_fit_unit
# since fspeed12, pipeline.fit runs the settling analysis inside fit_unit (beside the
# sensors' fits, as one more item of the forked hand-out): timed on its own where it runs
# in this process (sensors serial), so that the sensors' fits alone are seen as well
_settle = []
if hasattr(pipeline, "_settling_analysis"):
    _analysis = pipeline._settling_analysis

    def _timed_analysis(*a, **k):
        r, wall, own, cpu = timed(lambda: _analysis(*a, **k))
        _settle.append((wall, own))
        return r

    pipeline._settling_analysis = _timed_analysis
fits = []
for _ in range(2):          # the first fit also pays the lazy imports inside the fit
    cs, wall, own, cpu = timed(lambda: pipeline.fit(unit, [data]))
    fits.append((wall, own, cpu, os.getloadavg()[0]))
res = {"fit_wall_s": min(f[0] for f in fits), "fit_s": min(f[1] for f in fits),
       "fit_cpu_s": min(f[2] for f in fits),
       # the 1-minute load average when the best wall time was taken
       "fit_wall_load": min(fits)[3], "fit_unit_wall_load": min(_inner)[2],
       "fit_unit_wall_s": min(f[0] for f in _inner), "fit_unit_cpu_s": min(f[1] for f in _inner),
       # the sensors' fits alone: fit_unit less the settling analysis run inside it
       "sensors_cpu_s": min(f[1] - (s[1] if s else 0.0)
                            for f, s in zip(_inner, _settle or [None] * len(_inner)))}
if report == "serial":      # figures drawn in this process: the CPU they cost
    F.parallel.__init__ = lambda self, workers=None: setattr(self, "workers", 1)
if report != "none":        # "forked": as `magcal fit` draws them
    _, wall, own, cpu = timed(lambda: fit_report(cs, out, [data]))
    res.update(report_wall_s=wall, report_s=own, report_cpu_s=cpu)
print(json.dumps(res))
"""


FIT_ONLY = "import sys; from generator import pipeline; pipeline.fit(sys.argv[1], [sys.argv[2]])"


def _env(tree: Path, **extra) -> dict:
    return dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1",
                OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg", **extra)


def extract(rev: str, dest: Path) -> Path:
    """generator/ (and the templates it reads) of `rev` into dest."""
    blob = subprocess.run(["git", "-C", str(REPO), "archive", rev, "generator"],
                          check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(blob)) as tf:
        tf.extractall(dest)
    return dest


def timings(tree: Path, out: Path, report: str, **env) -> dict:
    """report: "none", "serial" (figures in the process) or "forked" (as `magcal fit`)."""
    p = subprocess.run([sys.executable, "-c", DRIVER, str(FM1 / "unit.toml"),
                        str(FM1 / "thermal_12pos.csv"), str(out), report],
                       env=_env(tree, **env), capture_output=True, text=True, cwd=out.parent)
    if p.returncode:
        raise SystemExit(f"{tree}: {p.stderr.strip().splitlines()[-1]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def cli_timing(tree: Path, out: Path, **env) -> dict:
    """`magcal fit UNIT DATA -o OUT --no-report -q` of a tree end to end, as a user runs it
    (python -m generator.cli: start-up and imports included): wall (perf_counter around
    the process) and CPU (wait4: the process's and its reaped children's, the forked
    sensor fits)."""
    import time

    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "generator.cli", "fit", str(FM1 / "unit.toml"),
                          str(FM1 / "thermal_12pos.csv"), "-o", str(out), "--no-report",
                          "-q"], env=_env(tree, **env), stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, cwd=out.parent)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    if status:
        raise SystemExit(f"{tree}: magcal fit --no-report failed: {p.stderr.read().decode()[-300:]}")
    return {"cli_wall_s": wall, "cli_cpu_s": ru.ru_utime + ru.ru_stime}


def peak_rss_mib(tree: Path, data: Path, out: Path) -> float:
    p = subprocess.Popen([sys.executable, "-c", FIT_ONLY, str(FM1 / "unit.toml"), str(data)],
                         env=_env(tree), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         cwd=out.parent)
    _, status, rusage = os.wait4(p.pid, 0)
    if status:
        raise SystemExit(f"{tree}: fit of {data} failed: {p.stderr.read().decode()[-300:]}")
    return rusage.ru_maxrss / 1024.0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--baseline-commit", default="f6f3a45")
    ap.add_argument("--report-baseline-commit", default="f639afc")
    ap.add_argument("--previous-commit", default="c6ef128")
    ap.add_argument("--previous-only", action="store_true",
                    help="measure today against --previous-commit only (not the two older "
                         "baselines, whose figures are recorded below)")
    ap.add_argument("--rows", default="36000,144000",
                    help="two input lengths for the memory slope")
    ap.add_argument("--no-memory", action="store_true")
    ap.add_argument("--no-report", action="store_true", help="time the fit only")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        trees = {"previous": extract(a.previous_commit, tmp / "previous"), "today": REPO}
        if not a.previous_only:
            trees["baseline"] = extract(a.baseline_commit, tmp / "baseline")
            trees["report_baseline"] = extract(a.report_baseline_commit, tmp / "rb")
        # --repeat rounds, each tree once per round (interleaved: a shared machine's load
        # changes over the run and would otherwise favour one tree); the best of the rounds
        # today twice more: its fit with MAGCAL_WORKERS=1 (the sensors one after the other
        # in the process: what the forked children buy, in wall and in CPU), and its report
        # as `magcal fit` draws it (forked figures: wall and CPU with the children's)
        runs = {k: (tree, "none" if a.no_report else "serial", {})
                for k, tree in trees.items()}
        runs["today_serial"] = (REPO, "none", {"MAGCAL_WORKERS": "1"})
        runs["previous_serial"] = (trees["previous"], "none", {"MAGCAL_WORKERS": "1"})
        if not a.no_report:
            runs["today_forked_report"] = (REPO, "forked", {})
        res = {}
        cli = {}
        for _ in range(a.repeat):
            for k, (tree, report, env) in runs.items():
                r = timings(tree, tmp / f"rep_{k}", report, **env)
                # the best of each figure; a load goes with its wall time
                res[k] = {m: (v if k not in res else min(v, res[k][m])) for m, v in r.items()}
                for w in ("fit_wall", "fit_unit_wall"):
                    if r[f"{w}_s"] == res[k][f"{w}_s"]:
                        res[k][f"{w}_load"] = r[f"{w}_load"]
            for k in ("previous", "today"):        # `magcal fit --no-report`, forked
                r = cli_timing(trees[k], tmp / f"cli_{k}")
                cli[k] = {m: (v if k not in cli else min(v, cli[k][m])) for m, v in r.items()}
        if not a.no_memory and not a.previous_only:
            n1, n2 = (int(v) for v in a.rows.split(","))
            files = {}
            for n in (n1, n2):
                files[n] = tmp / f"fit_{n}.csv"
                write_long_file(FM1 / "thermal_12pos.csv", files[n], n)
            for k in ("baseline", "today"):
                tree = trees[k]
                m = {n: peak_rss_mib(tree, files[n], tmp / f"out_{k}_{n}") for n in (n1, n2)}
                res[k]["rss_MiB"] = m
                res[k]["bytes_per_sample"] = (m[n2] - m[n1]) * 2**20 / (n2 - n1)
    pv, t = res["previous"], res["today"]
    b, rb = res.get("baseline"), res.get("report_baseline")
    ts = res["today_serial"]
    print(f"samsat_fm1 thermal_12pos, best of {a.repeat}, BLAS 1 thread; previous "
          f"{a.previous_commit}" + ("" if a.previous_only else
                                    f", baseline {a.baseline_commit}, report baseline "
                                    f"{a.report_baseline_commit}")
          + "; CPU = the process's own + its reaped children's (the forked sensor fits "
          "and figures); load: the 1-minute load average when the best wall was taken")
    print(f"  today's fit, sensors serial (MAGCAL_WORKERS=1) -> forked: wall "
          f"{ts['fit_wall_s']:.2f} s -> {t['fit_wall_s']:.2f} s (ratio "
          f"{ts['fit_wall_s'] / t['fit_wall_s']:.2f}x; load {t['fit_wall_load']:.1f}), CPU "
          f"{ts['fit_cpu_s']:.2f} s -> "
          f"{t['fit_cpu_s']:.2f} s (ratio {ts['fit_cpu_s'] / t['fit_cpu_s']:.2f}x)")
    if b:
        print(f"  fit CPU: {b['fit_cpu_s']:.2f} s ({a.baseline_commit}), "
              f"{rb['fit_cpu_s']:.2f} s ({a.report_baseline_commit}) -> "
              f"{t['fit_cpu_s']:.2f} s   ratio {b['fit_cpu_s'] / t['fit_cpu_s']:.2f}x, "
              f"{rb['fit_cpu_s'] / t['fit_cpu_s']:.2f}x")
    print(f"  fit against {a.previous_commit}, forked: CPU {pv['fit_cpu_s']:.2f} s -> "
          f"{t['fit_cpu_s']:.2f} s (ratio {pv['fit_cpu_s'] / t['fit_cpu_s']:.2f}x), wall "
          f"{pv['fit_wall_s']:.2f} s (load {pv['fit_wall_load']:.1f}) -> "
          f"{t['fit_wall_s']:.2f} s (load {t['fit_wall_load']:.1f}) (ratio "
          f"{pv['fit_wall_s'] / t['fit_wall_s']:.2f}x)")
    ps = res["previous_serial"]
    print(f"  fit against {a.previous_commit}, sensors serial (MAGCAL_WORKERS=1): CPU "
          f"{ps['fit_cpu_s']:.2f} s -> {ts['fit_cpu_s']:.2f} s (ratio "
          f"{ps['fit_cpu_s'] / ts['fit_cpu_s']:.2f}x), wall {ps['fit_wall_s']:.2f} s -> "
          f"{ts['fit_wall_s']:.2f} s (ratio {ps['fit_wall_s'] / ts['fit_wall_s']:.2f}x)")
    pu, tu = res["previous_serial"], res["today_serial"]
    print(f"  of it fit.thermal.fit_unit (the sensors' fits, without reading the files; "
          f"today's also runs the settling analysis, beside the fits, which "
          f"{a.previous_commit}'s pipeline.fit ran after it):")
    print(f"    sensors serial (MAGCAL_WORKERS=1): CPU {pu['fit_unit_cpu_s']:.2f} s -> "
          f"{tu['fit_unit_cpu_s']:.2f} s (ratio {pu['fit_unit_cpu_s'] / tu['fit_unit_cpu_s']:.2f}x)")
    print(f"    forked: wall {pv['fit_unit_wall_s']:.2f} s (load "
          f"{pv['fit_unit_wall_load']:.1f}) -> {t['fit_unit_wall_s']:.2f} s (load "
          f"{t['fit_unit_wall_load']:.1f}) "
          f"(ratio {pv['fit_unit_wall_s'] / t['fit_unit_wall_s']:.2f}x), CPU with the "
          f"children's {pv['fit_unit_cpu_s']:.2f} s -> {t['fit_unit_cpu_s']:.2f} s")
    print(f"    today, serial -> forked: wall {tu['fit_unit_wall_s']:.2f} s -> "
          f"{t['fit_unit_wall_s']:.2f} s")
    print(f"    the sensors' fits alone (today's fit_unit less the settling analysis), "
          f"serial: CPU {pu['sensors_cpu_s']:.2f} s -> {tu['sensors_cpu_s']:.2f} s (ratio "
          f"{pu['sensors_cpu_s'] / tu['sensors_cpu_s']:.2f}x)")
    cp, ct = cli["previous"], cli["today"]
    print(f"  magcal fit --no-report end to end (imports included, forked): wall "
          f"{cp['cli_wall_s']:.2f} s -> {ct['cli_wall_s']:.2f} s (ratio "
          f"{cp['cli_wall_s'] / ct['cli_wall_s']:.2f}x), CPU {cp['cli_cpu_s']:.2f} s -> "
          f"{ct['cli_cpu_s']:.2f} s (ratio {cp['cli_cpu_s'] / ct['cli_cpu_s']:.2f}x)")
    res["cli"] = cli
    if not a.no_report and b:
        tf = res["today_forked_report"]
        print(f"  report, figures drawn serially, CPU: {rb['report_cpu_s']:.2f} s "
              f"({a.report_baseline_commit}) -> {t['report_cpu_s']:.2f} s   ratio "
              f"{rb['report_cpu_s'] / t['report_cpu_s']:.2f}x   [{a.baseline_commit}, "
              f"fewer figures: {b['report_cpu_s']:.2f} s]")
        print(f"  today's report, figures serial -> forked (as magcal fit): wall "
              f"{t['report_wall_s']:.2f} s -> {tf['report_wall_s']:.2f} s, CPU "
              f"{t['report_cpu_s']:.2f} s -> {tf['report_cpu_s']:.2f} s")
    if b and "bytes_per_sample" in t:
        print(f"  fit memory per sample (peak RSS slope, pipeline.fit): "
              f"{b['bytes_per_sample']:.0f} B -> {t['bytes_per_sample']:.0f} B   ratio "
              f"{b['bytes_per_sample'] / max(t['bytes_per_sample'], 1.0):.2f}x  "
              f"(peak RSS baseline {b['rss_MiB']}, today {t['rss_MiB']} MiB)")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
