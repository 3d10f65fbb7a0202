"""Parameter recovery: fit synthetic silhouettes made at a 2x finer grid and compare with the truth.

For each scene (hanging_plate, drop, squeeze in 2D; hanging_plate in 3D; experiments/scenes/*.json)
and each of three parameter sets in shaving-cream ranges (a seeded Latin hypercube over mu 50-400 Pa,
sigma_y 15-80 Pa, eta 1-30 Pa s^m log-uniform, m 0.3-1.0 uniform):

1. `jaxfoam.synth.synthesize` renders the scene at dx_data = dx_fit / 2 into tracked-video-like
   silhouettes (boundary pixel noise, dropped frames, plate pixels of weight 0, pixel size dx_data / 2);
2. `jaxfoam.calibrate.calibrate` fits mu, sigma_y, eta and m at dx_fit from the default starts and
   bounds (nothing here is tuned to these data: the fitter's defaults are used as a user would);
3. the study (never the fitter) reads the file's /truth and reports each parameter's error, whether
   the truth lies inside the 95% interval (the combined one, and the Gauss-Newton part alone),
   iterations, evaluations and wall time; two diagnostics explain a miss: the fit's loss at the true
   parameters (optimizer stuck in another basin, or the fit grid's optimum away from the truth) and
   the plastic shear-rate range the truth produces (eta and m separate only over a wide range).

The three optimizers (Levenberg-Marquardt, L-BFGS, Adam) are compared on the same data (loss against
wall time). The full study also refits the drop at dx_fit / sqrt(2) against data made at half that
(FINE), to see whether a finer fit grid brings the parameters closer to the truth, and the drop on a
frictionless floor (SLIP), to see how much of the drop's bias the floor's friction causes, the drop with
particle floor contact (CONTACT), to see how much of it the grid-contact gap under the landed foam causes,
the squeeze's data fitted over the squeeze and the hold only (WINDOW), to see how much of its bias the
lift causes, and fits the 2D scenes on the fitter's default grid (DEFAULT_GRID, 64 cells across, data at
half its spacing), what a user who keeps the default gets. The hanging plate and the drop are also
fitted to data made otherwise, one change at a time (DATA): on a grid 4x finer than the fit, with 4x the
boundary noise and 3x the dropped frames, through a camera with finer pixels, from a scene that starts
at the first mask as a tracked video's does, with masks grown by a pixel, and simulated with other
numerics (9 particles per cell, CFL 0.5, float32) as another simulator's would be. The main table's 2D
fits and the default grid's squeeze are repeated in float32 (PRECISION) on the same data. Goals (issue 4): mu and sigma_y within 10%,
m within 0.1, eta within 25% (or reported not identifiable with an interval containing the truth);
truth inside the interval in >= 90% of cases; a 2D fit under 15 minutes on 2 CPU cores.

Every case is saved as it finishes (its record in experiments/results/recovery_cases/<case>.json,
committed; its data and fit log in out/recovery/; a killed study resumes where it stopped), and the
table and chart are rebuilt from the finished cases (`--report` needs only the committed records).
Usage: python -m experiments.recovery [--quick] [--sets N] [--only TEXT] [--report]
                                      [--refit-check] [--shift-check] [--measured-check]
(--report: only rebuild table and chart; re-running skips finished fits and resumes a killed one from its log.
The checks are diagnostics of the discretization check, cached beside the records: --refit-check continues
the main table's and the default grid's LM fits on both grids, --shift-check evaluates the check's estimates on
shifted grids, --measured-check runs the check's measured move for fits recorded before the fitter had it, so
that the report shows every fit as the fitter reports it now.)
Writes experiments/results/recovery[_quick].md and .png. SI units.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import fitting
import jaxfoam  # noqa: F401  (float64)
from experiments import _common as C
from jaxfoam.calibrate import (DEFAULT_DX_REFIT, DEFAULT_STARTS, DX_CHECK_JACOBIAN, FRAME_BOUNDARY_SPACINGS, GCI_SAFETY,
                               FitSettings, calibrate)
from jaxfoam.io import read_silhouettes
from jaxfoam.synth import synthesize

NAME = "recovery"
ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
WORK = ROOT.parent / "out" / "recovery"
# Each finished case's record and its small diagnostics (JSON) are committed here, so the tables and chart
# can be rebuilt (--report) on a fresh clone; the data files and fit logs (megabytes) stay in WORK.
CASES = ROOT / "results" / "recovery_cases"
# The issue's shaving-cream ranges of the truths (SI units); log-uniform except m.
TRUTH_RANGES = {"mu": (50.0, 400.0), "sigma_y": (15.0, 80.0), "eta": (1.0, 30.0), "m": (0.3, 1.0)}
TRUTH_SEED = 2015
N_SETS = 3
# Synthetic-data realism: boundary pixel flips and dropped frames like a tracked video.
NOISE = 0.05
DROP_FRAMES = 0.1
# Goals of the issue: relative error for mu, sigma_y, eta; absolute for m.
GOALS = {"mu": ("rel", 0.10), "sigma_y": ("rel", 0.10), "eta": ("rel", 0.25), "m": ("abs", 0.1)}


@dataclasses.dataclass(frozen=True)
class SceneCase:
    """A scene of the study: file, fit grid spacing (m), simulated duration (s), frames, and the fit's
    time window (s, `FitSettings.time_window`; None: every frame)."""

    name: str
    dx_fit: float
    duration: float
    frames: int
    window: tuple | None = None
    # How the data differ from the study's (DATA probe; the defaults are the main table's): the data grid
    # is dx_fit / data_ratio, `noise` and `drop_frames` as `synthesize` takes them, the camera's pixel
    # size (m; None: half the data grid, synthesize's default), and whether the file's scene starts from
    # its first mask (as a tracked video's does) instead of the primitive it was simulated from.
    tag: str = ""
    data_ratio: float = 2.0
    noise: float = NOISE
    drop_frames: float = DROP_FRAMES
    pixel_size: float | None = None
    first_mask: bool = False
    dilate_px: int = 0  # masks grown by this many pixels where the weight is not 0 (a fatter renderer)
    # The data simulation's own numerics (None: synthesize's defaults, the fit's: 4 particles per cell in
    # 2D, CFL 0.3, float64), as another simulator's would differ.
    ppc: int | None = None
    cfl: float | None = None
    data_dtype: str = "float64"
    # The fit's floating-point precision (`FitSettings.dtype`); the data are the same case's in float64.
    fit_dtype: str = "float64"


# Fit resolutions: ~8-10 cells across the foam in 2D, ~6 in 3D (the cost of one Jacobian grows as
# dx^-3 in 2D and dx^-4 in 3D; dx 0.01 m keeps a 2D fit within minutes on a shared 2-core machine).
# Durations cover each scene's informative phase: the hanging foam stretching under the oscillating
# plate, the drop's impact and spreading, the squeeze, the hold and the lift.
FULL = [SceneCase("hanging_plate_2d", 0.01, 0.8, 12), SceneCase("drop_2d", 0.01, 0.4, 12),
        SceneCase("squeeze_2d", 0.01, 1.4, 12), SceneCase("hanging_plate_3d", 0.016, 0.6, 8)]
QUICK = [SceneCase("hanging_plate_2d", 0.01, 0.6, 8), SceneCase("drop_2d", 0.01, 0.4, 8),
         SceneCase("squeeze_2d", 0.01, 1.0, 8), SceneCase("hanging_plate_3d", 0.016, 0.6, 8)]
# Finer-grid probe of the full study: a scene again at dx_fit / sqrt(2) (data at half that), LM only, the
# same truths, noise and budget: does a finer fit grid bring the fitted parameters closer to the truth?
FINE = [SceneCase("drop_2d", 0.01 / math.sqrt(2.0), 0.4, 12)]
# Floor-friction probe of the full study: the drop on a frictionless floor (scene drop_2d_frictionless, else
# identical), at the study's dx_fit, LM only, the same truths, noise and budget. On the scene's floor the
# landed foam's base sticks and the foam spreads by shearing above it, a layer a few cells thick on the fit
# grid: experiments/floor_contact measures how much less the foam spreads on the 1 cm grid than on finer
# ones. Does the drop's bias go with the friction?
SLIP = [SceneCase("drop_2d_frictionless", 0.01, 0.4, 12)]
# Floor-contact probe of the full study: the drop with particle floor contact (scene
# drop_2d_particle_contact, else identical; data made on that scene), at the study's dx_fit, LM only, the
# same truths, noise and budget. With the default grid contact the landed foam rests about 0.7 cells above
# the floor, 7 mm on the 1 cm fit grid against 3.7 mm in the 5 mm data (experiments/floor_contact); with
# particle contact it rests on the floor on any grid. Does the drop's bias go with that gap?
CONTACT = [SceneCase("drop_2d_particle_contact", 0.01, 0.4, 12)]


def _domain(name: str) -> dict:
    """Study scene `name`'s domain ({"min": [...], "max": [...]}, m)."""
    return json.loads((SCENES / f"{name}.json").read_text())["domain"]


def default_fit_dx(name: str) -> float:
    """The fitter's default dx (m) for a study scene: its largest domain extent / FIT_CELLS[dim]."""
    from jaxfoam.calibrate import FIT_CELLS

    dom = _domain(name)
    extent = max(hi - lo for lo, hi in zip(dom["min"], dom["max"]))
    return extent / FIT_CELLS[len(dom["min"])]


def fitter_refit(r: dict) -> int:
    """The fitter's default `dx_refit` (LM iterations of the check's measured move) for finished fit r's scene."""
    return DEFAULT_DX_REFIT[len(_domain(case_of(r).name)["min"])]


# The fitter's default grid (`jaxfoam fit` without --dx: the largest domain extent / FIT_CELLS, 64 cells in
# 2D, 4.7-5.5 mm here), LM only, the same truths, noise and budget, data at half that spacing: what a user
# who keeps the default gets, against the study's coarser 1 cm grid.
DEFAULT_GRID = [dataclasses.replace(c, dx_fit=default_fit_dx(c.name)) for c in FULL if not c.name.endswith("3d")]
# Time-window probe of the full study: the squeeze's data of the main table (the same files), fitted at the
# study's dx_fit over the squeeze and the hold only (t <= 0.8 s, the end of the hold in the scene's plate
# motion), LM only, the same budget: the fit grid reproduces those phases at the truth more closely than the
# lift, in which the foam stuck to the rising plate stretches (the per-frame table of the default grid).
WINDOW = [SceneCase("squeeze_2d", 0.01, 1.4, 12, window=(0.0, 0.8)),
          SceneCase("squeeze_2d", default_fit_dx("squeeze_2d"), 1.4, 12, window=(0.0, 0.8))]
PROBES = FINE + SLIP + CONTACT + WINDOW + DEFAULT_GRID
# Data-variation probe: the fitter will meet data from other simulators, resolutions and cameras, so the
# main table's hanging plate and drop are fitted as they are (1 cm, LM, the same budget) to data made
# differently, one change at a time, none of them tuned for: `fine4` data on a grid 4x finer than the fit
# (2.5 mm) instead of 2x; `noisy` boundary flips 0.2 and 30% of frames dropped (0.05, 10%); `pix` a camera
# with 1.25 mm pixels (2.5 mm), so the fitter coarsens the images by 2^2; `mask` the file's scene starts
# from its first, noisy, mask (`first_mask`), as a tracked video's does, instead of the exact primitive;
# `fat` every mask grown by one pixel (2.5 mm), as a renderer or tracker that draws the boundary a pixel
# further out would give; `numerics` the data simulated with other numerics than the fit's, as another MPM
# code's would be: 9 particles per cell (4), CFL 0.5 (0.3) and float32 (float64).
DATA = [SceneCase(name, 0.01, dur, 12, **var) for var in (
            dict(tag="fine4", data_ratio=4.0), dict(tag="noisy", noise=0.2, drop_frames=0.3),
            dict(tag="pix", pixel_size=0.00125), dict(tag="mask", first_mask=True), dict(tag="fat", dilate_px=1),
            dict(tag="numerics", ppc=9, cfl=0.5, data_dtype="float32"))
        for name, dur in (("hanging_plate_2d", 0.8), ("drop_2d", 0.4))] + [
    # the squeeze starts from its first mask too: its foam rests on the floor with the plate just above it
    SceneCase("squeeze_2d", 0.01, 1.4, 12, tag="mask", first_mask=True)]
# Precision probe: the main table's 2D fits and the default grid's squeeze (its slowest fits, 15.6 and
# 17.5 min) again in float32 (`FitSettings.dtype`, `jaxfoam fit --dtype float32`) on the same data files,
# the same budget: float32 steps run about 1.6x faster in 2D (experiments/bench_step.md); does a fit keep
# its accuracy, and how much of that speed does it keep?
PRECISION = [dataclasses.replace(c, fit_dtype="float32") for c in FULL if not c.name.endswith("3d")] + [
    dataclasses.replace(c, fit_dtype="float32") for c in DEFAULT_GRID if c.name == "squeeze_2d"]
# Budgets: starts and iterations per optimizer; the optimizer comparison runs on the same data. The full
# study's 2D LM fits take the fitter's default number of starts, as a user's fit would (on an idle 2-core
# machine one 2D start takes 0.5-2 min); 3D fits (8-12 min a start) and the L-BFGS and Adam comparison
# runs take one start. Start 0 is the same initial guess for every optimizer (the centre of the start
# ranges), so the comparison reads each fit's first start.
BUDGET = {True: dict(starts={"lm": 1, "lbfgs": 1, "adam": 1}, iters={"lm": 12, "lbfgs": 12, "adam": 20}),
          False: dict(starts={"lm": DEFAULT_STARTS, "lbfgs": 1, "adam": 1}, iters={"lm": 20, "lbfgs": 20, "adam": 40})}


def starts_for(c: "SceneCase", opt: str, quick: bool) -> int:
    """Multi-start count of a fit in the study (BUDGET; 3D fits always one start)."""
    return 1 if c.name.endswith("3d") else int(BUDGET[quick]["starts"][opt])
# Which (scene, set) pairs get the optimizer comparison (all three optimizers).
COMPARE = {True: [("drop_2d", 0)], False: [("drop_2d", 0), ("squeeze_2d", 0), ("hanging_plate_2d", 1), ("hanging_plate_2d", 2)]}


# Conclusions of the full run, written from its tables (appended to recovery.md only).
VERDICT = """
**Latest (2026-11-25, end of day): the measured move runs 4 iterations in 2D.** With 2, moves that were
still growing went uncounted: the default grid's drop set 1 reported mu identifiable, 16% off. The
fitter's `dx_refit` default is now per dimension, 4 in 2D and 2 in 3D (`DEFAULT_DX_REFIT`), and every
record was re-reported from cached runs of 4 iterations: the 66 probes and other LM fits, the 12 main-table
and 9 default-grid fits, and the 8 L-BFGS and Adam fits (the 21 main and default runs reproduce the refit
checks' finer-grid moves to 2e-6 relative). Default grid: goal met 36/36 (35/36 with 2), inside 36/36. With the 3D fits
(2 iterations, unchanged), the study at the fitter's default discretization meets the goal in 48/48
parameter-cases, the truth inside all 48. Main table at 1 cm: inside 48/48, goal met 47/48, as with 2.
Probes and the other LM fits: inside 264/264 (263/264), goal met 256/264 (the same). Every interval of
every LM fit in the study now contains the truth. The misses left are all the hanging plate's mu at 1 cm:
set 0, +12% to +17% in every variant of its data, and the fat-mask set 1, +11%; each reported
identifiable, the truth inside intervals about -30%/+35% around the fit (main table: [189, 368] Pa
around 267.5). The 4 iterations took 17-118 s on the default grid (2: 9-62 s), 8-22% of a fit; its slowest fit, the squeeze set 1, goes from 12.1 to
14.1 min at the study's recorded load, under the 15 min goal. In 3D, 4 iterations took 166-442 s (2:
68-147 s), up to 1.8x the fit itself, and moved no 3D interval end by more than 12%; hence 2 there.
Fitted afresh with the new fitter, the default grid's squeeze set 1 (the slowest fit) reached the same
optimum and intervals equal to the re-report's to 1e-8 relative, in 9.2 min wall, 117 s of it the 4
iterations (single run, 2026-11-25).

**Latest (2026-11-25, later): the discretization check measures its move.** The check's two first-order
estimates of how far the estimate moves between dx and dx / sqrt(2) missed where the residual is not
linear over the move (the drop set 0's mu moved -18% in a refit where they said -1.4% and +1.1%). The
fitter now also runs `dx_refit` = 2 LM iterations on the finer grid from the optimum and counts the
largest of the three moves. Every record was re-reported from a cached run of those iterations (section
"Discretization check with a measured move"; same optima). Main table: truth inside 48/48 (was 47/48),
goal met 47/48 (46/48), the drop set 0's mu (-20%) now reported not identifiable with the truth inside.
Default grid: 36/36 inside, goal met 35/36 (34/36; the squeeze set 2's mu, +17%, now not identifiable).
Probes and the other LM fits: goal met 256/264 (248/264), inside 263/264 (260/264); every verdict that
changed went from a miss, or a claim of identifiability, to not identifiable with the truth inside. The
misses left: mu reported identifiable with the truth inside its interval but more than 10% off, on the
hanging plate set 0 at 1 cm (+12% to +17% in every variant of its data) and the default grid's drop set 1
(-16%; with 4 iterations instead of 2, as the refit checks ran, it too would be reported not
identifiable; 4 took 2.0x and 3.0x the time of 2 on that fit and on the default grid's slowest, 129 s
against 43 s there); and the particle-contact drop's weak foam, mu -54%, not identifiable but outside.
The iterations add 1-62 s (2-25%; 4-11% on the default grid, whose slowest fit goes from 12.1 to 12.8 min)
to a 2D LM fit and 68-147 s (27-65%) to a 3D one. Fewer parameters are reported identifiable: 1 of 48 in the main
table, 2 of 36 on the default grid. The moves the refit and shift sections show were printed as if the
fitter's coordinate were log(theta); it is logit-log for these bounded parameters, and the relative changes
are now computed through it (about 1.3-1.7x the numbers printed before). Two default-grid fits were run
afresh with the new fitter to test the re-report: the squeeze set 1 (the slowest) reached the same optimum
(loss equal to 13 digits), its measured move equal to the cached one to 1e-10 and its intervals to 9
digits, in 8.0 min wall with the check (12.1 min recorded under heavier load); the squeeze set 2, whose m
ended on its bound, the same optimum in 6.7 min, but the cache starts m just inside the bound, not at the
fit's own coordinate there, and its measured moves differ (mu -0.041 against -0.042 cached, sigma_y +0.134
against +0.020, in the fitted coordinate), and so its intervals (sigma_y [2.4, 143] against [3.3, 107] Pa, eta
[0.064, 243] against [0.050, 500] Pa s^m; mu's within 4%), with the same verdicts. For fits with a
parameter on a bound the re-report is that approximate.

**Latest (2026-11-25): every record now ran at the fitter's time step.** Sets 1 and 2 of every scene
have a frame dropped inside the fitted span, and every frame of their fits' rollouts used to run at
half the fitter's CFL step (the substeps are sized for the widest frame interval). With the gaps filled
by unobserved frames (`jaxfoam.calibrate.simulation_frames`), the main table's 8 such fits and the
default grid's 2 squeeze fits were re-run on 2026-11-24 and the 36 probe fits on 2026-11-25 (the earlier
records kept as `*.halved-dt`). Main table: truth inside 47/48 combined intervals (45/48 before the
re-run), goal met 46/48 (44/48); the misses left are the drop set 0's mu (-20%, just outside; that
dataset has no gap) and the hanging plate set 0's mu (+15%, reported identifiable, the truth inside
its interval). 2D fits take 0.5-1.5 min. Default grid: 36/36 inside, goal met 34/36 (the drop set 1's
mu, -16%, is now reported identifiable, with the truth inside; at the halved step it was -23% and not
identifiable), each fit 2.8-12.1 min, under the 15 min goal. mu is still within 10% in none of the 9
2D fits at 1 cm (the hanging plate set 1's +10.07% just outside) and most parameters are reported not
identifiable: the fit grid's bias, not the optimizer, limits the accuracy. The re-run probes (data made
differently), against the main table's same fits (hanging plate and drop: inside 23/24, goal met 22/24;
with the squeeze 35/36 and 34/36): data on a 4x finer grid 24/24 inside (goal met 23/24), 4x the noise
and 30% of frames dropped 24/24 (23/24), 1.25 mm pixels 22/24 (21/24; besides the drop set 0's mu as in
the main table, the weak hanging foam's sigma_y, +28%, reported identifiable), masks one pixel fatter
24/24 (22/24), the scene seeded from the first mask 36/36 (32/36). Across all of them the hanging plate's sets 0 and 1 give
mu +7% to +17%, reported identifiable in most: a bias of the 1 cm grid that the check's numerical error
covers but does not remove. The frictionless drop now fits sets 0 and 1 within the goal (mu -6% and -7%,
sigma_y -3% and -3%; set 2, the weak foam: mu -54%, not identifiable); particle floor contact does not
remove the drop's bias (mu -33%, -33%, -54%, the last outside its interval).

**Grid alignment (2026-11-25).** The discretization check samples one grid per spacing. Shifting the fit's
grid against the scene by a quarter or half a cell (same dx; section "Discretization check against grid
shifts") moves the estimate, by the check's own first-order formulas, more than refining dx to dx /
sqrt(2) does in 21 of the 24 mu / sigma_y cases: the hanging plate set 0's mu -8% to -18% at half a cell
(refinement +3%), the drop set 0's mu -11% at a quarter cell (refinement -1%; these relative changes were
quoted 0.6-0.75x too small until the report converted the fitted coordinate's moves properly, 2026-11-25,
later). Where the node lattice falls
on the sticky face, the floor and the initial shape is part of the fit grid's error. The reported
numerical error (extrapolated to the continuum and times the safety factor 3) covers every predicted
shift move in 23 of 24 (the one exception the 3D set 0's unidentifiable sigma_y), so the intervals
already count it; it does explain estimates like the hanging plate's mu, +7% to +17% off in every 1 cm
variant of sets 0 and 1 while the refinement moves it by 3-8%. The refits on the check's finer grid now
cover all 12 main-table fits (sets 1 and 2 re-run with the gaps filled): the check's error covers the move
in 23 of 24, the fit grid's Jacobian is the closer prediction in 15 of 24, as before the re-run. The
paragraphs below are the study's earlier history.

**Hanging-plate scene fixed before this run.** The foam used to be glued by a 5 mm overlap into a 2 cm
board, less than one cell at the fit dx, so whether and when it tore off depended on how many node
layers of the sticky board the overlap reached. Measured with (mu, sigma_y, eta, m) = (97.8 Pa, 24.3 Pa,
2.69 Pa s^m, 0.69): mean height at t = 0.5 s 0.191 m at dx = 1 cm against 0.070 m at 5 mm, and moving
the whole scene by 2.5-7.5 mm at dx = 1 cm moved the tear-off between t = 0.3 s and 0.7 s. The scene now
glues a 2 cm layer into a 4 cm board: 0.120 m (dx 1 cm), 0.118 m (7 mm), 0.121 m (5 mm)
(tests/test_plate_grip.py). A first-order sensitivity remains: the sticky face sits on node layers, and
a 5 mm translation of the scene at dx = 1 cm still delays the tear-off by about 0.1 s.

**This run.** Every fit was re-run on 2026-11-24 (the fit logs of the 2026-11-23 run were not kept).
The fits reproduced that run's losses to the printed digits, except on the hanging plate's set 2, whose
tear-off at another time than in the data makes the loss chaotic (LM's first start 0.042 -> 0.040, L-BFGS
0.075 -> 0.055). Wall times fell about threefold: a 3-start 2D LM fit at 1 cm took 0.5-2.3 min (1.4-7.9
min on 2026-11-23), a 3D fit 3.0-4.1 min (8.1-12.1). The code in between made the transfers' and the
return map's kernels fewer and cheaper; how much each change contributed at these sizes (700-1,400
particles) was not measured.

One uncertainty rule changed before this run. A fit that does not reproduce its data (a frame's
boundaries more than one particle spacing apart) now reports each parameter's bounds as its interval,
not identifiable, and keeps the interval at its optimum as `interval_local`. Before, it printed a warning
beside a local interval that could be narrow and wrong: the weak hanging foam's mu of 40 Pa with
[38.0, 42.4] against a truth of 98 Pa. That case is now inside. Coverage stays at 43/48 all the same:
the squeeze set 1's sigma_y interval moved with round-off from [8.79, 37.79] to [8.89, 37.40], and the
truth, 37.49, now lies just above it.

**The discretization check changed later the same day, and every fit was re-reported from its log at the
same optimum** (section "Discretization check"). The check estimated how far the estimate moves from dx
to dx / sqrt(2) with the fit grid's Jacobian only. On the default-grid squeeze set 0, four LM iterations
at 3.3 mm from the optimum moved sigma_y +41% where that estimate said +8% (the finer grid's own
Jacobian: +60%; these three, and the slump's, are the fitted coordinate's moves as if they were log moves,
see above); on the slump of the tests the fit grid's Jacobian was the closer one (+7.2% and +5.1%
against +6.3%), and on six 1 cm fits continued on both grids it was the closer in 9 of 12 moves of mu
and sigma_y (section "Discretization check against refits"; the drop set 0's mu moved -18.2% there,
against -1.4% and +1.1% predicted, the one move the check's error does not cover). With the squeeze's
three and the 3D hanging plate's three fits added later (all 12 main-table fits), the fit grid's estimate
is the closer in 15 of 24 moves and the check's error covers 23 of 24 (the squeeze set 0's sigma_y moved
+66%, predicted +22% and +26%, covered; the 3D set 1's mu -58%, predicted +16% and -85%, covered). The check now takes
the larger of the two estimates per parameter, for one Jacobian on the finer grid instead of one
rollout. Coverage in the main table went from 43/48 to 45/48 (93.8%; the drop set 0's sigma_y and the
hanging plate set 1's eta are now inside), the goal from 42/48 to 44/48, and on the default grid from
32/36 to 35/36 (all three squeeze fits' mu had been outside). The price is fewer parameters reported
identifiable: 2 of 48 in the main table (3 before; the hanging plate set 1's mu, +5%, is now reported
not identifiable, its interval [106, 293] Pa), 3 of 36 on the default grid (7 before). The check's extra
Jacobian added 0.02-1.6 min to a fit's wall time (re-reported wall times against the earlier records;
the default-grid squeeze set 1: 16.0 -> 17.5 min; the 3D fits +1.5-1.6 min).

**Multi-start fixes the stuck fit and finds lower losses, which here are not closer to the truth.**
Hanging plate set 1: start 1 (the centre of the start ranges) stops at loss 0.051 with mu -71%; start 2
reaches 0.00056, 5x below the loss at the truth, with mu +5% and sigma_y -3%. On the drop, the other
starts reach losses 1.2-1.8x below start 1's, but mu moves away from the truth (set 0: +10% -> -20%,
now outside its interval; set 2: +597% (not identifiable) -> -64%, outside): the lower the loss on the 1
cm grid, the more the fit absorbs that grid's bias.

**Optimizer: no single winner; the default stays LM with multi-start.** Same data, each optimizer's
first start (the same initial guess), 20 iterations (Adam 40): drop set 0 L-BFGS reached loss 0.0048 in
0.1 min against LM 0.0071 (0.2 min, stopped on ftol) and Adam 0.0089 (0.2 min); squeeze set 0 LM
0.00078, L-BFGS 0.00081, Adam 0.00099 (0.5, 0.4, 0.5 min), all below the loss at the truth (0.0022);
hanging plate set 1 LM's first start stopped at 0.051, 19x the loss at the truth (0.0027), while L-BFGS
went to 0.00061 with mu +7%, sigma_y -8% (0.6 min), and Adam's best iterate reached 0.00064 with mu -3%
(1.0 min); hanging plate set 2 LM's first start stopped at 0.040 with mu -59%, L-BFGS at 0.055 with mu
-38%, Adam at 0.076 with mu -3% (0.7, 0.9, 1.0 min): there the lowest loss is the worst estimate,
because the fit grid cannot reproduce these data at the truth (below). L-BFGS reached the lowest loss
in 2 of 4 comparisons, LM in 2. With one start none of the three is reliable on its own.

**Hanging plate, set 2: the 1 cm grid cannot reproduce the 5 mm data of a weak foam.** The truth
(mu 97.8 Pa, sigma_y 24.3 Pa) has loss 12.7 on the fit grid, 330x the fitted 0.038: at dx = 1 cm the
foam tears off at another time than in the data (even at the data's own 5 mm, with other particle
positions, the truth has loss 2.4: the tear-off time is sensitive to the discretization), so LM
settles on compensating wrong parameters (mu 40 Pa; its local interval [38.7, 41.7] misses the truth, so
the fitter reports the bounds instead). The fitter's goodness-of-fit
check (`FitResult.frame_boundary_error`: the mean distance between fitted and observed silhouette
boundaries, per frame, against one particle spacing) flags it (1.19 spacings) and the 3D set 2 fit
(1.80); with the earlier single-start fits it also flagged the stuck LM fit of set 1 (1.52) and two
drop fits (1.23, 1.03), which the 3-start fits now reproduce (0.72-0.87). The check catches misfit,
not a coarse grid that fits the data with wrong parameters: the squeeze fits reproduce their data at
0.31-0.45 spacings with mu 52-180% off.

**What each scene constrains (fit dx 1 cm against data at 5 mm).**
- mu (elastic sag and rebound): the hanging plate +15%, +5%, -59% (set 2, flagged), reported
  identifiable in set 0 (set 1 too before the check's change); the drop -20%, -37%, -64% (identifiable in set 0 only); the squeeze
  +75%, +180%, -52% (not identifiable).
- sigma_y: not identifiable in any 2D LM fit at this grid once the numerical error is counted; the
  hanging plate set 1 (the foam tears off) gives -3%, the squeeze's permanent set -33%, -51%, -27%, the
  drop (15-27% of particle-frames yield, during the impact) -59% to -95%, and a hanging slab that holds
  (set 0: sigma_y = 49 Pa against rho g L = 51 Pa; 14% of particle-frames yield, at 0.004-0.5 1/s) -79%.
- eta and m: not separated by any scene. The yielding particle-frames see plastic rates of 0.004-0.5
  1/s (hanging, set 0), 0.1-3.1 1/s (hanging, set 1), 0.03-5.6 1/s (squeeze) and 0.01-33 1/s only
  during the drop's impact; eta gamma_dot^m is then either small against sigma_y or seen too briefly,
  and eta and m trade off (|correlation| >= 0.98 in every fit with a finite correlation; the notes name
  the direction).
- The fit grid's bias dominates what is left: in all 9 2D LM fits the loss at the truth on the 1 cm
  grid is 1.4-10x the fitted loss (330x for hanging plate set 2), so that grid's optimum is not at the
  truth. The fitter's discretization check measures this (numerical error above the statistical one in
  every fit) and widens the intervals, which is why the truth is inside most of them while the errors
  are large. The shift is not usable as a correction: applying the 9 stored shifts of the earlier
  single-start fits (extrapolated to the continuum at first order) moved mu further from the truth in 3
  fits (squeeze set 0: 411 -> 606 Pa against 233) and closer in 6, by erratic amounts (drop set 2: 682
  -> 14 Pa against 98).
- On the fitter's default grid (64 cells across: 5.5 mm for the hanging plate, 4.7 mm for the drop and
  the squeeze; data at half that; section "The fitter's default grid") mu comes within 10% in 3 of 9 fits
  (hanging plate +1%, -5%; drop +3%), against 1 of 9 at 1 cm, and sigma_y in 1 (the hanging plate's
  -1%; the squeeze's set 2 -11%). The squeeze is not converged there: mu -31%, -17%, +17%; with the
  fit grid's Jacobian alone the check under-estimated that grid's error and left each outside a
  reported-identifiable interval (fit_convergence measured mu moving 36% from 48 to 64 cells on the
  squeeze); with both grids' Jacobians set 0's mu is reported not identifiable with the truth inside
  ([54, 429] Pa), set 2's is inside ([91, 143] Pa, still reported identifiable at +17%), and set 1's
  stays outside ([125, 161] Pa against 171). The
  weak hanging foam (set 2) is still not reproduced (2.35 spacings) and the drop's set 2 ends with mu at
  its upper bound, also flagged. Coverage on that grid is 35/36 (47/48 with the 3D fits), the goal met in
  34/36 (32/36 and 31/36 with the earlier check). The price is time: 2.8-17.5 min per 3-start fit, the
  squeeze's sets 1 and 2 above the 15-minute goal. Where a fit is well posed, a finer grid brings the
  estimate closer; the discretization check's first-order estimate still misjudges the error in both
  directions (hanging plate set 0: mu +1% with an estimated numerical error of 127 Pa; squeeze set 1: mu
  -17% with an estimate of 18 Pa; squeeze set 0: -31% with 188 Pa, 19 Pa with the fit grid's Jacobian
  alone).
- Where the default grid's bias sits (the per-frame table under "The fitter's default grid": at the true
  parameters, the mean distance between the fit grid's silhouette and the data, in particle spacings).
  The hanging plate's set 0, whose mu came out +1%, stays within 0.11-0.34 spacings in every frame.
  The squeeze stays within 0.25-0.41 while it is squeezed and held (to 0.76 s), and reaches 0.5-1.5 once
  the plate lifts the foam stuck to it. The drop is at 0.34-0.44 before it lands and at 0.54-1.28
  after (from 0.11 s), as the foam spreads over the rough floor. The hanging plate's set 1 stays
  within 0.11-0.65 until 0.65 s and is at 1.49-1.53 at 0.73-0.80 s, and its set 2 (the weak foam that
  tears off) reaches 2.2-6.4. The fits move the parameters to match those phases: stretching, tearing
  and the sheared layer on a rough floor, which the fit grid resolves worst.
- Fitting the squeeze without its lift removes the grid's bias from the fit, but does not make sigma_y
  identifiable (section "Time window"). The fit covers t <= 0.8 s, the end of the hold in the scene's
  plate motion, a window not chosen from the truth.
  - The loss at the truth falls to 1.1-1.4x the fitted loss, from 2.8-5.9x over all frames.
  - Every interval covers its truth: 24/24 at 1 cm and on the default grid, goal met 24/24.
  - A default-grid fit takes 2.6-4.5 min, against 7.5-16.0 min over all frames.
  - Without the lift's elastic recovery, mu runs off and is reported not identifiable.
  - sigma_y is reported not identifiable too: +8%, -11%, -9% at 1 cm, and -26%, -59%, -13% on the
    default grid.
  The fitter's discretization check flags the lift's frames by itself (fit.json
  settings.dx_check.frame_change, and a note).
- A finer fit grid alone did not close the gap on the drop (section "Finer fit grid"): fitted at
  7.07 mm to data made at 3.54 mm (3 starts, 3.0-5.7 min), mu is off by -35%, -30% and +275% (1 cm:
  -20%, -37%, -64%), and the loss at the truth is still 2.2-4.9x the fitted loss.
- The drop's floor friction causes most of its bias (section "Frictionless floor"). The impact sticks
  the foam's base to the floor (Coulomb friction 0.5: the blob moves 0.3 m/s sideways and lands at
  over 1 m/s, so the friction impulse exceeds its sideways momentum) and the foam then spreads by
  shearing above it: on the 1 cm grid the landed foam of sets 0 and 1 ends 12-13 mm narrower and
  its centroid 7 mm higher than at 2.5 mm (`experiments/results/floor_contact.md`), and its silhouettes lie 1.9-2.0
  mm from the 2.5 mm run's on average, against 1.1-1.3 mm on a frictionless floor. The same truths,
  noise and budget on a frictionless floor give mu -6%, -5% and sigma_y -3%, +8% for sets 0 and 1 (with
  friction: mu -20%, -37%, sigma_y -65%, -59%), both parameters identifiable in set 1, and a loss at
  the truth only 1.3-1.7x the fitted loss (3.0-4.3x with friction); the weak foam of set 2 stays off
  (mu -43%, outside its interval). A fit of a drop on a rough floor therefore needs a grid that resolves
  the sheared layer above the floor. (Scratch probes with the grid shifted half a cell, so that the floor
  lies midway between node rows, the foam rests on it and the friction's node row reaches only the
  lowest particles: the widths converged no better, set 0's right edge at 0.4 s at 61, 73, 77 mm for dx
  10, 5, 2.5 mm against 60, 73, 76 mm unshifted, so the friction row's reach is not the cause; and fits
  of data made that way halved the drop's fitted losses but left mu at -24%, -34%, -8%.)
- Particle floor contact does not remove the drop's bias either (section "Particle floor contact";
  `"floor": {"contact": "particle"}`, added on 2026-11-24, data made with it). The landed foam then rests
  on the floor on every grid instead of 0.7 cells above it, its silhouettes on the 1 cm grid lie 1.27-1.38
  mm from the 2.5 mm run's instead of 1.61-1.97 mm (`experiments/results/floor_contact.md`), the fitted
  losses fall 1.9-4.5x and, for sets 0 and 1, the loss at the truth 5.2-5.6x; but mu comes out -33%,
  -48% and -70% (set 2 outside its interval, reported identifiable). So the gap under the landed foam is
  not what pulls mu down; the sheared layer above the rough floor is, as the frictionless probe says.

**Data made differently (section "Data made differently", 2026-11-24).** The fitter will meet data from
other simulators, resolutions and cameras. The hanging plate's and the drop's truths were fitted as in the
main table to data changed one way at a time, none chosen from these results. Finer data (a grid 4x finer
than the fit), 4x the boundary noise with 30% of frames dropped, 1.25 mm pixels, and masks grown by one
pixel leave the fits about where the main table's bias already puts them: the truth is inside 22-23 of
24 intervals per variant (the main table's same six fits: 22/24), mu is within 10% in one fit of six in
each (main: one). A boundary drawn one pixel (2.5 mm) further out moved mu by -9 to +2 percentage points of the
truth (hanging plate +12%, +6%, -57% against +15%, +5%, -59%; drop -20%, -41%, -73% against -20%, -37%,
-64%) and raised the hanging plate's fitted loss 1.5-4x: the fit does not absorb a renderer's or
tracker's boundary offset into the parameters. With 4x finer data
the drop's sets 0 and 1 are flagged as not reproduced (boundaries 1.32-1.35 particle spacings apart): the
1 cm grid cannot follow 2.5 mm data of the spreading foam, and the fitter says so.
- **The first-mask start found a bug.** A tracked video's scene starts from its first mask, in which the
  board hides the foam glued into it. Seeded from the visible pixels alone, the hanging foam met the
  board's face by less than a cell and fell off on the 1 cm grid: the loss at the truth was 440, 421 and
  136 (exact shape: 0.00065, 0.0027, 12.7), and the fits ended at mu +635%, +723%, +1899% with the data
  not reproduced (records kept as `mask_hanging_plate_2d_set*_lm.json.visible-only`). Foam that hangs
  from a sticky plate is now continued into it where the plate hides it (`jaxfoam.io.glue_under_plates`,
  used by `Silhouettes.first_mask`). The losses at the truth are then 0.00077, 0.0013 and 9.1, and the fits
  track the exact-shape ones: mu +16%, +8% and -62% (main table: +15%, +5%, -59%). The drop, which no plate
  holds, was unaffected (mu -18%, -40%, -68% against -20%, -37%, -64%), and so was the squeeze's start,
  whose foam rests on the floor under the plate (run afterwards from its first mask: every interval
  covers its truth, 12/12, all four parameters reported not identifiable; mu -26%, -11%, -41% against
  +75%, +180%, -52% from the exact shape).
"""


def truth_sets() -> list[dict]:
    """The N_SETS parameter sets: a seeded Latin hypercube over TRUTH_RANGES (log-uniform except m)."""
    u = fitting.latin_hypercube(N_SETS, 4, TRUTH_SEED)
    out = []
    for row in u:
        t = {}
        for j, (n, (lo, hi)) in enumerate(TRUTH_RANGES.items()):
            t[n] = float(lo + row[j] * (hi - lo)) if n == "m" else float(math.exp(
                math.log(lo) + row[j] * (math.log(hi) - math.log(lo))))
        out.append({k: float(f"{v:.4g}") for k, v in t.items()})
    return out


def plan(quick: bool, n_sets: int | None = None) -> list[tuple]:
    """(priority, scene case, set index, optimizer) in the order they run: LM on the first set of every
    2D scene, then the optimizer comparison, then the remaining 2D sets, then 3D."""
    cases = QUICK if quick else FULL
    sets = list(range((1 if quick else N_SETS) if n_sets is None else min(int(n_sets), N_SETS)))
    jobs = []
    for k in sets:
        for c in cases:
            pri = 10 + k if c.name.endswith("3d") else (0 if k == 0 else 1 + k)
            jobs.append((pri, c, k, "lm"))
    for name, k in COMPARE[quick]:
        c = next(c for c in cases if c.name == name)
        for opt in ("lbfgs", "adam"):
            jobs.append((1, c, k, opt))
    if not quick:
        jobs.extend((20 + k, c, k, "lm") for k in sets for c in FINE + SLIP + CONTACT + WINDOW)
        jobs.extend((25 + k, c, k, "lm") for k in sets for c in DATA)
        jobs.extend((30 + k, c, k, "lm") for k in sets for c in DEFAULT_GRID)
        jobs.extend(((35 if c.dx_fit != 0.01 else 27) + k, c, k, "lm") for k in sets for c in PRECISION)
    return sorted(jobs, key=lambda j: j[0])


def case_id(c: SceneCase, k: int, quick: bool) -> str:
    if c.fit_dtype != "float64":  # a fit setting: the prefix, then that of the same case in float64
        return "f32_" + case_id(dataclasses.replace(c, fit_dtype="float64"), k, quick)
    if c in WINDOW:  # the window's prefix, then that of the same case without it (the data's)
        return "win_" + case_id(dataclasses.replace(c, window=None), k, quick)
    if c.tag:
        return f"{c.tag}_{c.name}_set{k}"
    prefix = 'q_' if quick else 'fine_' if c in FINE else 'dflt_' if c in DEFAULT_GRID else ''
    return f"{prefix}{c.name}_set{k}"


def data_path(c: SceneCase, k: int, quick: bool) -> Path:
    """The synthetic silhouette file of a case; a fit window or the fit's precision changes the fit, not
    the data, so such a case shares the file of the same case without it."""
    return WORK / f"{case_id(dataclasses.replace(c, window=None, fit_dtype='float64'), k, quick)}_data.h5"


def make_data(c: SceneCase, k: int, quick: bool) -> tuple[Path, float]:
    """The synthetic silhouette file of a case (made once): (path, wall seconds spent now)."""
    WORK.mkdir(parents=True, exist_ok=True)
    path = data_path(c, k, quick)
    if path.exists():
        return path, 0.0
    t0 = time.perf_counter()
    scene = json.loads((SCENES / f"{c.name}.json").read_text())
    truth = truth_sets()[k]
    data = synthesize(scene, truth, dx=c.dx_fit / c.data_ratio, frames=c.frames, duration=c.duration,
                      pixel_size=c.pixel_size, noise=c.noise, drop_frames=c.drop_frames, seed=k,
                      first_mask=c.first_mask, progress=lambda m: print("  synth:", m, flush=True),
                      **({} if c.ppc is None else dict(ppc=c.ppc)), **({} if c.cfl is None else dict(cfl=c.cfl)),
                      dtype=jnp.float32 if c.data_dtype == "float32" else jnp.float64)
    if c.dilate_px:
        from jaxfoam.track import dilate

        grown = np.stack([dilate(m, c.dilate_px) for m in data.masks]) & (data.weights > 0)
        data = dataclasses.replace(data, masks=grown.astype(np.uint8))
    data.write(path)
    return path, time.perf_counter() - t0


# Plastic shear rates below this (1/s) count as not yielding (the elastic creep of the return map).
YIELD_RATE = 1e-3
SHEAR_FRAMES = 20  # frames of the truth rollout sampled for the shear-rate range


def shear_rates(c: SceneCase, k: int, quick: bool) -> dict:
    """The plastic shear rates the truth produces in a case (rolled out at dx_fit, SHEAR_FRAMES frames):
    the fraction of particle-frames that yield and the 10th/50th/90th percentiles of their rate (1/s).
    eta and m can only be separated when these span a wide range (stress sigma_y + eta gamma_dot^m).
    Cached in CASES/<case>_shear.json."""
    path = CASES / f"{case_id(c, k, quick)}_shear.json"
    if path.exists():
        return json.loads(path.read_text())
    from jaxfoam import Params, load_scene, simulate

    scene = load_scene(json.loads((SCENES / f"{c.name}.json").read_text()))
    t = truth_sets()[k]
    p = Params(mu=t["mu"], kappa=scene.kappa, sigma_y=t["sigma_y"], eta=t["eta"], m=t["m"], rho=scene.density)
    times = np.linspace(c.duration / SHEAR_FRAMES, c.duration, SHEAR_FRAMES)
    g = np.asarray(simulate(scene, p, times, c.dx_fit).frames["gamma_dot"]).ravel()
    y = g[g > YIELD_RATE]
    out = dict(yielding=float(y.size / g.size),
               p10=float(np.percentile(y, 10)) if y.size else 0.0,
               p50=float(np.percentile(y, 50)) if y.size else 0.0,
               p90=float(np.percentile(y, 90)) if y.size else 0.0)
    CASES.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out) + "\n")
    return out


def _fit_problem(c: SceneCase, k: int, quick: bool):
    """(data, the fit's `CalibrationProblem`) of a case: its grid, time window and seed, LM settings."""
    from jaxfoam.calibrate import build_problem

    data = read_silhouettes(data_path(c, k, quick))
    return data, build_problem(data, FitSettings(dx=c.dx_fit, optimizer="lm", seed=0, time_window=c.window,
                                                 dtype=c.fit_dtype))


def truth_loss(c: SceneCase, k: int, quick: bool) -> float:
    """The fit's loss 0.5 |r|^2 at the true parameters (one rollout at dx_fit): below the fitted loss, the
    optimizer stopped short of the truth's basin; above it, the fit grid's bias (or the data's
    ambiguity) moved the optimum away from the truth. Cached in CASES/<case>_truthloss.json."""
    path = CASES / f"{case_id(c, k, quick)}_truthloss.json"
    if path.exists():
        return float(json.loads(path.read_text())["loss"])
    data, problem = _fit_problem(c, k, quick)
    theta = np.array([data.truth[n] for n in problem.transform.names])
    loss = problem.loss(problem.transform.to_unconstrained(theta))
    CASES.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dict(loss=loss)) + "\n")
    return loss


def truth_frames(c: SceneCase, k: int, quick: bool) -> dict:
    """Per used frame, how far the fit grid's silhouette at the true parameters lies from the data: the
    fitter's goodness-of-fit measure (`jaxfoam.calibrate.silhouette_mismatch`, mean boundary distance, in
    particle spacings) and the frame times, s. Shows in which phase of a scene the fit grid and the data
    grid differ. One rollout at dx_fit; cached in CASES/<case>_truthframes.json."""
    path = CASES / f"{case_id(c, k, quick)}_truthframes.json"
    if path.exists():
        return json.loads(path.read_text())
    from jaxfoam.calibrate import FIT_PPC, silhouette_mismatch
    from jaxfoam.silhouette import particle_spacing

    data, problem = _fit_problem(c, k, quick)
    occ = problem.render({n: data.truth[n] for n in problem.transform.names})
    _, boundary = silhouette_mismatch(occ, problem.masks, problem.weights, problem.cfg.pixel_size)
    s = particle_spacing(problem.dx, FIT_PPC[problem.scene.dim], problem.scene.dim)
    out = dict(times=[float(data.times[i]) for i in problem.frames], boundary=[float(b / s) for b in boundary])
    CASES.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out) + "\n")
    return out


# Refit diagnostic of the discretization check: LM iterations on the check's finer grid, from the fit's optimum.
REFIT_ITERATIONS = 4
# The fitter's dx_refit before it became DEFAULT_DX_REFIT (2026-11-25, later): the report shows both.
PREVIOUS_DX_REFIT = 2


def _cached_check(r: dict, kind: str) -> tuple[Path, dict | None]:
    """The cache file CASES/<case>_<kind>.json of a check on finished fit r, and its content (None if absent)."""
    path = CASES / f"{r['case']}_{kind}.json"
    return path, (json.loads(path.read_text()) if path.exists() else None)


def _fit_and_data(r: dict):
    """(SceneCase, fit dict, Silhouettes) of finished fit record r."""
    c = case_of(r)
    return c, r["fit"], read_silhouettes(data_path(c, r["set"], r["case"].startswith("q_")))


def refit_check(r: dict, compute: bool = True) -> dict | None:
    """How far the estimate of a finished LM fit moves between its grid and the discretization check's finer
    one (dx * DX_CHECK_RATIO; the fit's pixel level, time window and seed): the fit is continued for at most
    REFIT_ITERATIONS LM iterations from its optimum on both grids, and the difference of the two end points
    (so that what the fit itself had left to gain on its own grid does not count as the grid's effect) is
    set against the check's predicted move (both of its estimates) and its numerical error, in fitted
    coordinates. Uses no truth: it tests the check itself. Cached in CASES/<case>_refit.json; None when not
    cached and `compute` is False."""
    if r["optimizer"] != "lm":  # the cache is keyed by case: it holds the LM fit's refit
        raise ValueError(f"refit_check: {r['case']} is an {r['optimizer']} fit; the refit check is of LM fits")
    path, cached = _cached_check(r, "refit")
    if cached is not None or not compute:
        return cached
    from jaxfoam.calibrate import DX_CHECK_RATIO, fit_transform, make_starts

    c, fit, data = _fit_and_data(r)
    start = {n: fit["params"][n] for n in fit["fitted"]}
    same = FitSettings(dx=c.dx_fit, optimizer="lm", seed=0, time_window=c.window, starts=1, initial=start,
                       max_iter=REFIT_ITERATIONS, pixel_level=fit["settings"]["pixel_level"], dx_check=False)
    t0 = time.perf_counter()
    tr = fit_transform(same)
    ends = {}
    for label, dx in (("fit_grid", c.dx_fit), ("finer_grid", c.dx_fit * DX_CHECK_RATIO)):
        res = calibrate(data, dataclasses.replace(same, dx=dx))
        ends[label] = dict(z=np.asarray(res.uncertainty.z if res.uncertainty is not None else
                                        tr.to_unconstrained(np.array([res.params[n] for n in tr.names]))),
                           iterations=int(res.iterations), reason=res.reason, loss=float(res.loss),
                           loss_start=float(res.loss_history[0]))
    z0 = make_starts(tr, same)[0][0]
    check = fit["settings"]["dx_check"]
    out = dict(names=list(tr.names), moved_z=[float(v) for v in ends["finer_grid"]["z"] - ends["fit_grid"]["z"]],
               left_on_fit_grid_z=[float(v) for v in ends["fit_grid"]["z"] - z0], shift_z=check["shift_z"],
               shift_z_fit_jacobian=check["shift_z_fit_jacobian"], shift_z_own_jacobians=check["shift_z_own_jacobians"],
               error_z=check["error_z"], wall=time.perf_counter() - t0,
               **{f"{k}_{q}": v[q] for k, v in ends.items() for q in ("iterations", "reason", "loss", "loss_start")})
    CASES.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out) + "\n")
    return out


# Grid shifts of the shift check, as fractions of the fit's dx: the grid (the scene's domain) is moved by
# that much along every axis, the geometry and the camera stay. A quarter and a half cell: the largest
# and an intermediate misalignment (a shift by one cell is the same lattice again).
SHIFT_FRACTIONS = (0.25, 0.5)


def shift_check(r: dict, compute: bool = True) -> dict | None:
    """How far the estimate of a finished LM fit would move on the same grid spacing with the grid shifted
    against the scene (SHIFT_FRACTIONS of a cell along every axis): the discretization check's two first-order
    estimates (the fit grid's Jacobian; each grid's own), applied to the shifted grid instead of the finer one,
    at the fit's optimum, set against the numerical error the check reported (fitted coordinates). The
    refinement check samples one grid per spacing; where the result depends on how the node lattice falls on
    the geometry (a sticky face, a floor, the initial shape), a shift shows it. Uses no truth. Cached in
    CASES/<case>_shift.json; None when not cached and `compute` is False."""
    path, cached = _cached_check(r, "shift")
    if cached is not None or not compute:
        return cached
    from jaxfoam.calibrate import build_problem, make_starts, predicted_move

    c, fit, data = _fit_and_data(r)
    settings = FitSettings(dx=c.dx_fit, optimizer="lm", seed=0, time_window=c.window, starts=1,
                           initial={n: fit["params"][n] for n in fit["fitted"]},
                           pixel_level=fit["settings"]["pixel_level"], dx_check=False)
    t0 = time.perf_counter()
    base = build_problem(data, settings)
    tr = base.transform
    # the optimum as a start (a parameter that ended on a bound is taken just inside it)
    z = make_starts(tr, settings)[0][0]
    r0, J0 = (np.asarray(a, np.float64) for a in base.residual_and_jacobian(z))
    moves = {}
    for frac in SHIFT_FRACTIONS:
        scene = json.loads(data.scene_json)
        h = frac * c.dx_fit
        scene["domain"] = {k: [v - h for v in scene["domain"][k]] for k in ("min", "max")}
        other = build_problem(dataclasses.replace(data, scene_json=json.dumps(scene)), settings)
        with_fit, with_own, _ = predicted_move(base, other, z, J0, r0)
        moves[str(frac)] = dict(fit_jacobian=[float(v) for v in with_fit], own_jacobians=[float(v) for v in with_own])
    out = dict(names=list(tr.names), fractions=list(SHIFT_FRACTIONS), moves=moves,
               error_z=fit["settings"]["dx_check"]["error_z"], shift_z=fit["settings"]["dx_check"]["shift_z"],
               wall=time.perf_counter() - t0)
    CASES.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out) + "\n")
    return out


def _record_optimum(r: dict):
    """(transform, theta (p,), z (p,)) of finished fit r: the fitter's transform for its bounds and fixed
    parameters, and its optimum in physical and fitted coordinates (a value on a bound taken just inside it,
    as `make_starts` does)."""
    from jaxfoam.calibrate import fit_transform, make_starts

    st = r["fit"]["settings"]
    settings = FitSettings(bounds={n: tuple(b) for n, b in st["bounds"].items()}, fixed=dict(st["fixed"]),
                           initial={n: r["fit"]["params"][n] for n in r["fit"]["fitted"]}, starts=1)
    tr = fit_transform(settings)
    z = np.asarray(make_starts(tr, settings)[0][0], np.float64)
    return tr, np.asarray(tr.to_physical(z), np.float64), z


def _theta_of_move(r: dict, name: str, v: float, base: float = 0.0) -> tuple[float, float]:
    """Physical values (before, after) of parameter `name` of finished fit r when its fitted coordinate
    moves by v from the optimum's (plus `base`): the fitter's transform is logit-log for a bounded positive
    parameter, so a move in it is not a relative change (d z / d log theta = 1 / ((log hi - log lo) t (1 - t)),
    t the parameter's place between its bounds in log)."""
    tr, _, z = _record_optimum(r)
    i = list(tr.names).index(name)
    z0, z1 = z.copy(), z.copy()
    z0[i] += base
    z1[i] += base + v
    return float(np.asarray(tr.to_physical(z0))[i]), float(np.asarray(tr.to_physical(z1))[i])


def _move(r: dict, name: str, v: float, base: float = 0.0) -> str:
    """A move v of `name`'s fitted coordinate (from the optimum plus `base`) as the relative change of the
    parameter it makes."""
    a, b = _theta_of_move(r, name, v, base)
    return _log_change(math.log(b / a)) if a > 0 and b > 0 else "n/a"


def _error_range(r: dict, name: str, e: float) -> str:
    """The numerical error e (a half-width in the fitted coordinate) as the relative range around the estimate."""
    return f"{_move(r, name, -e)} / {_move(r, name, e)}"


def _log_change(v: float) -> str:
    """A move v in log coordinates as a relative change, or as the factor e^v beyond +700% / -99.9% (where
    a percentage says little; e^v written out when it would overflow)."""
    if -7.0 < v < 2.08:
        return f"{100 * math.expm1(v):+.1f}%"
    return f"x{math.exp(v):.3g}" if -700.0 < v < 700.0 else f"x e^{v:.3g}"


def _shift_section(lm: list[dict]) -> str:
    """The `shift_check` of the main table's LM fits (cached ones only), for mu and sigma_y."""
    rows, n, covered, larger = [], 0, 0, 0
    for r in lm:
        sc = shift_check(r, compute=False)
        if sc is None:
            continue
        fr = sc["fractions"]
        for i, name in enumerate(sc["names"]):
            if name not in ("mu", "sigma_y"):
                continue
            biggest = max(max(abs(m["fit_jacobian"][i]), abs(m["own_jacobians"][i])) for m in sc["moves"].values())
            e, refine = sc["error_z"][i], abs(sc["shift_z"][i])
            n += 1
            covered += biggest <= e
            larger += biggest > refine
            rows.append([r["scene"], r["set"], name]
                        + [_move(r, name, sc['moves'][str(f)][k][i]) for f in sc["fractions"]
                           for k in ("fit_jacobian", "own_jacobians")]
                        + [_move(r, name, sc['shift_z'][i]), _error_range(r, name, e),
                           "yes" if biggest <= e else "**no**", f"{r['evaluation'][name]['error'] * 100:+.0f}%"])
    if not rows:
        return ""
    heads = [f"{f:g} cell: {k}" for f in fr for k in ("fit grid's J", "own J")]
    return (f"\n## Discretization check against grid shifts (LM, main table)\n\n"
            f"At each fit's optimum, the move of mu and sigma_y that the discretization check's two first-order "
            f"estimates (with the fit grid's Jacobian; with each grid's own) predict when the grid of the same "
            f"spacing is shifted against the scene by {' and '.join(f'{f:g}' for f in fr)} of a cell along every "
            f"axis (the scene's domain moved, geometry and camera kept), beside the check's own predicted move "
            f"between dx and dx / sqrt(2) (`refinement`, the larger of its two estimates) and the numerical error "
            f"it reports (the range it spans around the estimate). `error vs truth` is the fit's actual error. "
            f"Moves are computed in the fit's coordinates (logit-log for these bounded parameters) and shown as the "
            f"relative change of the parameter they make (before 2026-11-25 this section showed the coordinate "
            f"moves as if they were log moves, about 0.6-0.75x the true relative changes at these values); "
            f"`covers` compares them in those coordinates. `python -m experiments.recovery --shift-check` computes "
            f"them.\n\n"
            + C.md_table(["scene", "set", "param"] + heads + ["refinement", "numerical error", "covers the shifts",
                                                               "error vs truth"], rows)
            + f"\nShift checks cached for {len(rows) // 2} of the {len(lm)} fits. The largest predicted shift move "
              f"exceeds the refinement move the check is built on in {larger}/{n} parameter-cases; the reported "
              f"numerical error covers every predicted shift move in {covered}/{n}.\n")


def _refit_section(lm: list[dict]) -> str:
    """The `refit_check` of the main table's LM fits (cached ones only): per fit and parameter, the move of
    the estimate in REFIT_ITERATIONS LM iterations on the finer grid against the check's two predictions."""
    rows, covered, n, closer = [], 0, 0, {"fit": 0, "own": 0}
    for r in lm:
        rc = refit_check(r, compute=False)
        if rc is None:
            continue
        for i, name in enumerate(rc["names"]):
            if name not in ("mu", "sigma_y"):
                continue
            mv, a, b, e = rc["moved_z"][i], rc["shift_z_fit_jacobian"][i], rc["shift_z_own_jacobians"][i], rc["error_z"][i]
            n += 1
            covered += abs(mv) <= e
            closer["fit" if abs(a - mv) <= abs(b - mv) else "own"] += 1
            left = rc['left_on_fit_grid_z'][i]
            rows.append([r["scene"], r["set"], name, _move(r, name, mv, left), _move(r, name, a),
                         _move(r, name, b), _error_range(r, name, e), "yes" if abs(mv) <= e else "**no**",
                         _move(r, name, left),
                         f"{rc['fit_grid_iterations']}; {rc['finer_grid_iterations']}"])
    if not rows:
        return ""
    return (f"\n## Discretization check against refits on its finer grid (LM, main table)\n\n"
            f"Each fit continued for at most {REFIT_ITERATIONS} LM iterations from its optimum on its own grid and on "
            f"the check's grid (dx / sqrt(2), the same pixels): how far mu and sigma_y (moves in the fit's logit-log "
            f"coordinates, shown as the relative changes of the parameters they make) the finer grid's end point lies from the fit grid's (`moved`; `left on fit grid`: how "
            f"far the fit grid's own continuation went, which the difference removes), against the check's two "
            f"first-order predictions of that move (with the fit "
            f"grid's Jacobian; with each grid's own; the check uses the larger) and the numerical error it "
            f"reports (the range around the estimate: extrapolated to the continuum and times the safety factor; "
            f"`covers` compares in the fit's coordinates). "
            f"No truth enters. `python -m experiments.recovery --refit-check` computes the refits.\n\n"
            + C.md_table(["scene", "set", "param", "moved", "predicted: fit grid's J", "predicted: own J",
                          "numerical error", "covers the move", "left on fit grid", "iterations (fit grid; finer)"],
                         rows)
            + f"\nRefits cached for {len(rows) // 2} of the {len(lm)} fits"
              + (" (the others not run)" if len(rows) // 2 < len(lm) else "")
              + f". The numerical error covers the refit's move in {covered}/{n}; the prediction closer to the move is "
              f"the fit grid's Jacobian's in {closer['fit']}/{n} and the own Jacobians' in {closer['own']}/{n}.\n")


def with_measured_move(r: dict, measured_z, iterations: int) -> dict:
    """Fit record r's fit dict (reported with the discretization check's two first-order estimates only) as
    the fitter reports it with `FitSettings.dx_refit` = iterations: the check's move per parameter the
    largest of the two estimates and `measured_z`, the move of that many LM iterations on the check's grid
    from the optimum (fitted coordinates); the numerical error and the combined interval recomputed from it
    and the statistical interval, identifiability judged again. A fit that does not reproduce its data
    keeps its bounds. Uses no truth."""
    from types import SimpleNamespace

    from jaxfoam.calibrate import check_error, combine_intervals, judge_reported_intervals, numerical_half_width

    fit = json.loads(json.dumps(r["fit"]))
    check = fit["settings"]["dx_check"]
    tr, theta, z = _record_optimum(r)
    names = list(tr.names)
    measured = np.asarray(measured_z, np.float64)
    err, shift = check_error([check["shift_z_fit_jacobian"], check["shift_z_own_jacobians"], measured])

    def coord(i, v):  # a physical interval end in fitted coordinates (an end on a bound just inside it)
        w = theta.copy()
        w[i] = min(max(float(v), tr.lower[i] + 1e-12 * (tr.upper[i] - tr.lower[i])),
                   tr.upper[i] - 1e-12 * (tr.upper[i] - tr.lower[i]))
        return float(np.asarray(tr.to_unconstrained(w))[i])

    stat_z = np.array([[coord(i, v) for v in fit["interval_statistical"][n]] for i, n in enumerate(names)])
    both = combine_intervals(SimpleNamespace(z=z, interval_z=stat_z), err, tr)
    interval = {n: [float(v) for v in both[i]] for i, n in enumerate(names)}
    fit["numerical_error"].update(zip(names, (float(v) for v in numerical_half_width(tr, z, err))))
    check.update(refit=int(iterations), shift_z_refit=[float(v) for v in measured], shift_z=[float(v) for v in shift],
                 error_z=[float(v) for v in err])
    if fit.get("reproduces_data", True):
        ident = {n: bool(fit["identifiable"][n]) for n in names}
        # the statistical verdict (before the interval rules) is not stored: a parameter the current check
        # reports identifiable passed it, one it reports not identifiable keeps that verdict
        ident, _ = judge_reported_intervals(interval, fit["params"], tr, ident)
        fit["interval"], fit["identifiable"] = {**fit["interval"], **interval}, {**fit["identifiable"], **ident}
    return fit


def measured_check(r: dict, compute: bool = True, iterations: int | None = None) -> dict | None:
    """The move that the fitter's discretization check now measures (`FitSettings.dx_refit` = `iterations`,
    None: the fitter's default for the scene's dimension, LM iterations on its finer grid, dx *
    DX_CHECK_RATIO, from the optimum; the fit's
    pixel level, precision, time window and seed) for a finished fit recorded before the check measured it,
    so that the record can be reported as the fitter reports it now (`with_measured_move`). `wall` is the
    time of those iterations alone, what the fitter adds to a fit (the finer grid's first residual and
    Jacobian, which the check computed already, are timed apart as `wall_first`). Uses no truth. Cached in
    CASES/<case>_<optimizer>_measured<iterations>.json; None
    when not cached and `compute` is False."""
    from jaxfoam.calibrate import DX_CHECK_RATIO, build_problem, make_starts, refit_move

    iterations = fitter_refit(r) if iterations is None else int(iterations)
    path = CASES / f"{r['case']}_{r['optimizer']}_measured{iterations}.json"
    if path.exists() or not compute:
        return json.loads(path.read_text()) if path.exists() else None
    c = case_of(r)
    make_data(c, r["set"], r["case"].startswith("q_"))
    _, fit, data = _fit_and_data(r)
    settings = FitSettings(dx=c.dx_fit * DX_CHECK_RATIO, optimizer="lm", seed=0, time_window=c.window, starts=1,
                           dtype=c.fit_dtype, initial={n: fit["params"][n] for n in fit["fitted"]},
                           pixel_level=fit["settings"]["pixel_level"])
    other = build_problem(data, settings)
    z = make_starts(other.transform, settings)[0][0]
    t0 = time.perf_counter()
    at_z = tuple(np.asarray(a) for a in other.residual_and_jacobian(z))
    t1 = time.perf_counter()
    m = refit_move(other, z, int(iterations), at_z=at_z)
    out = dict(names=list(other.transform.names), refit=int(iterations), move_z=[float(v) for v in m["move"]],
               iterations=m["iterations"], reason=m["reason"], loss=list(m["loss"]),
               wall=time.perf_counter() - t1, wall_first=t1 - t0, date=time.strftime("%Y-%m-%d"))
    CASES.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out) + "\n")
    return out


def with_current_check(r: dict) -> dict:
    """Record r as the fitter reports it now: a fit whose check ran without the measured move is re-reported
    with its cached `measured_check` (fit and evaluation replaced, the earlier ones kept under
    `estimates_only`; the refit's time added to the fit's wall time); unchanged when the check measured the
    move already, or when no measured check is cached (then `check_measured` is False)."""
    check = r["fit"]["settings"].get("dx_check") or {}
    if "refit" in check or not check:
        return dict(r, check_measured=bool(check))
    mc = measured_check(r, compute=False)
    if mc is None:
        return dict(r, check_measured=False)
    fit = with_measured_move(r, mc["move_z"], mc["refit"])
    fit["wall_time"] = float(r["fit"]["wall_time"]) + float(mc["wall"])
    fit["settings"]["dx_check"].update(refit_iterations=mc["iterations"], refit_reason=mc["reason"],
                                       refit_loss=mc["loss"], rereported_from_cache=True)
    return dict(r, fit=fit, evaluation=evaluate(fit, r["truth"]), check_measured=True,
                estimates_only=dict(fit=r["fit"], evaluation=r["evaluation"]))


def _measured_move_section(groups: list[tuple[str, list[dict]]], names) -> str:
    """Coverage and goal of fit groups with the check's first-order estimates only (as the fits were first
    reported), with the measured move of the fitter's DEFAULT_DX_REFIT iterations for the scene's dimension
    (as reported now), and with the PREVIOUS_DX_REFIT iterations the fitter ran before (where cached)."""
    rows, changed = [], []
    count = lambda evs, key: sum(ev[n][key] for ev in evs for n in names)
    fmt = lambda e: (f"[{e['interval'][0]:.4g}, {e['interval'][1]:.4g}]"
                     f"{'' if e['identifiable'] else ' n.i.'}{'' if e['inside'] else ' out'}")
    for label, recs in groups:
        recs = [r for r in recs if "estimates_only" in r]
        if not recs:
            continue
        before = [r["estimates_only"]["evaluation"] for r in recs]
        now = [r["evaluation"] for r in recs]
        previous, previous_wall = [], []
        for r in recs:
            mp = measured_check(r, compute=False, iterations=PREVIOUS_DX_REFIT)
            if mp is not None:
                previous.append(evaluate(with_measured_move(dict(r, fit=r["estimates_only"]["fit"]), mp["move_z"],
                                                            PREVIOUS_DX_REFIT), r["truth"]))
                previous_wall.append(float(mp["wall"]))
        whole = len(previous) == len(recs)
        cell = lambda key: (f"{count(before, key)} -> {count(now, key)}"
                            + (f" ({count(previous, key)})" if whole else ""))
        extra = [r["fit"]["wall_time"] - r["estimates_only"]["fit"]["wall_time"] for r in recs]
        base = [r["estimates_only"]["fit"]["wall_time"] for r in recs]
        span = lambda v: f"{min(v):.0f}-{max(v):.0f} s"
        share = lambda v: f"{100 * min(e / b for e, b in zip(v, base)):.0f}-{100 * max(e / b for e, b in zip(v, base)):.0f}%"
        rows.append([label, len(recs), len(names) * len(recs), cell("inside"), cell("goal_met"), cell("identifiable"),
                     span(extra) + (f" ({span(previous_wall)})" if whole else ""),
                     share(extra) + (f" ({share(previous_wall)})" if whole else "")])
        for r, a, b in zip(recs, before, now):
            for n in names:
                if (a[n]["inside"], a[n]["goal_met"], a[n]["identifiable"]) != (b[n]["inside"], b[n]["goal_met"],
                                                                                 b[n]["identifiable"]):
                    changed.append([label, r["scene"], r["set"], r["case"].split("_set")[0].split(r["scene"])[0].rstrip("_")
                                    or "-", n, f"{r['truth'][n]:.4g}", f"{a[n]['value']:.4g}",
                                    f"{a[n]['error'] * (100 if a[n]['kind'] == 'rel' else 1):+.3g}"
                                    + ("%" if a[n]["kind"] == "rel" else ""), fmt(a[n]), fmt(b[n]),
                                    f"{'yes' if a[n]['goal_met'] else 'no'} -> {'yes' if b[n]['goal_met'] else 'no'}"])
    if not rows:
        return ""
    return (f"\n## Discretization check with a measured move (LM)\n\n"
            f"Since 2026-11-25 the fitter's discretization check also measures the move it estimates: "
            f"`FitSettings.dx_refit` LM iterations on its finer grid from the optimum (`jaxfoam fit --dx-refit N`, "
            f"0 to skip; by default {DEFAULT_DX_REFIT[2]} in 2D and {DEFAULT_DX_REFIT[3]} in 3D, "
            f"{PREVIOUS_DX_REFIT} in both until 2026-11-25, later), the largest of that and the two first-order "
            f"estimates counting. The fits above ran before; each is re-reported from a cached run of those "
            f"iterations (`measured_check`: the same start, grid and tolerances as the fitter's; same optimum and "
            f"statistical interval), its wall time with their time added. Parameter-cases with the truth inside "
            f"the combined interval, with the goal met, and reported identifiable: estimates only -> with the "
            f"fitter's default iterations (in brackets: {PREVIOUS_DX_REFIT} iterations everywhere), and the time "
            f"the iterations added (in brackets: {PREVIOUS_DX_REFIT}; each measured alone, on the shared "
            f"machine):\n\n"
            + C.md_table(["group", "fits", "parameter-cases", "inside", "goal met", "identifiable",
                          "time added", "of the fit's wall time"], rows)
            + ("\nThe parameter-cases whose verdict changed:\n\n"
               + C.md_table(["group", "scene", "set", "variant", "param", "truth", "fit", "error", "estimates only",
                             "with the measured move", "goal met"], changed) if changed else
               "\nNo parameter-case changed its verdict.\n"))


def _truth_frames_table(recs: list[dict]) -> str:
    """One row per case: the truth's per-frame boundary distance on the fit grid (`truth_frames`)."""
    rows, width = [], 0
    for r in sorted(recs, key=lambda r: (r["scene"], r["set"])):
        try:
            tf = truth_frames(case_of(r), r["set"], r["case"].startswith("q_"))
        except Exception:  # a diagnostic must not fail the report
            continue
        cells = [f"{t:.2f} s: {b:.2f}" for t, b in zip(tf["times"], tf["boundary"])]
        width = max(width, len(cells))
        rows.append([r["scene"], r["set"], f"{r['dx_fit'] * 1e3:.2f}"] + cells)
    rows = [row + [""] * (3 + width - len(row)) for row in rows]
    return C.md_table(["scene", "set", "fit dx (mm)"] + [f"frame {i + 1}" for i in range(width)], rows)


def case_of(r: dict) -> SceneCase:
    """The SceneCase of a finished record (quick records from QUICK, the others from FULL or PROBES)."""
    if r["case"].startswith("f32_"):
        return dataclasses.replace(case_of(dict(r, case=r["case"][len("f32_"):])), fit_dtype="float32")
    tagged = [c for c in DATA if r["case"] == case_id(c, r["set"], False)]
    if tagged:
        return tagged[0]
    if r["case"].startswith("q_"):
        cases = QUICK
    elif r["case"].startswith("win_"):
        cases = WINDOW
    else:  # a window case shares its scene and grid with the case it windows
        cases = [c for c in FULL + PROBES if c not in WINDOW]
    return next(c for c in cases if c.name == r["scene"] and c.dx_fit == r["dx_fit"])


def _truth_loss_of(r: dict) -> float:
    c = case_of(r)
    try:
        return truth_loss(c, r["set"], r["case"].startswith("q_"))
    except Exception:  # the table must not fail over a diagnostic
        return float("nan")


def goodness(r: dict) -> tuple[float, float]:
    """(smallest per-frame IoU, largest per-frame mean boundary distance in particle spacings) of a fit
    against its data: the fitter's goodness-of-fit check (`FitResult.frame_iou`, `.frame_boundary_error`,
    `.frame_boundary_limit`). Fits recorded before the check existed get it from one rollout at the
    fitted parameters, cached in CASES/<case>_<optimizer>_gof.json. NaNs if it cannot be computed."""
    from jaxfoam.calibrate import FIT_PPC
    from jaxfoam.silhouette import particle_spacing

    fit = r["fit"]
    dim = 3 if r["scene"].endswith("3d") else 2
    spacing = particle_spacing(r["dx_fit"], fit["settings"].get("ppc") or FIT_PPC[dim], dim)
    if fit.get("frame_boundary_error"):
        return float(min(fit["frame_iou"])), float(max(fit["frame_boundary_error"])) / spacing
    path = CASES / f"{r['case']}_{r['optimizer']}_gof.json"
    if not path.exists():
        try:
            from jaxfoam.calibrate import build_problem, silhouette_mismatch

            data = read_silhouettes(WORK / f"{r['case']}_data.h5")
            problem = build_problem(data, FitSettings(dx=r["dx_fit"], optimizer="lm", seed=0))
            theta = np.array([fit["params"][n] for n in problem.transform.names])
            iou, boundary = silhouette_mismatch(problem.render(theta), problem.masks, problem.weights,
                                                problem.cfg.pixel_size)
        except Exception:  # the table must not fail over a diagnostic
            return float("nan"), float("nan")
        path.write_text(json.dumps(dict(frame_iou=[float(v) for v in iou],
                                        frame_boundary_error=[float(v) for v in boundary])) + "\n")
    g = json.loads(path.read_text())
    return float(min(g["frame_iou"])), float(max(g["frame_boundary_error"])) / spacing


def _fmt_gof(r: dict) -> str:
    iou, spacings = goodness(r)
    return f"{iou:.2f}; {spacings:.2f}" + (" **no**" if spacings > FRAME_BOUNDARY_SPACINGS else "")


def _error(value: float, truth: float, kind: str) -> float:
    """Relative (kind "rel") or absolute error of a fitted value."""
    return (value - truth) / truth if kind == "rel" else value - truth


def evaluate(fit: dict, truth: dict) -> dict:
    """Errors, goal flags and interval coverage of one fit against the truth."""
    out = {}
    for n, (kind, tol) in GOALS.items():
        v, t = fit["params"][n], truth[n]
        err = _error(v, t, kind)
        lo, hi = (float(x) if not isinstance(x, str) else (math.inf if x == "inf" else -math.inf)
                  for x in fit["interval"][n])
        slo, shi = (float(x) if not isinstance(x, str) else (math.inf if x == "inf" else -math.inf)
                    for x in fit["interval_statistical"][n])
        inside = lo <= t <= hi
        ident = bool(fit["identifiable"][n])
        out[n] = dict(value=v, truth=t, error=err, kind=kind, within_goal=abs(err) <= tol,
                      inside=inside, inside_statistical=slo <= t <= shi, identifiable=ident,
                      goal_met=(abs(err) <= tol) or ((not ident) and inside), interval=[lo, hi])
    return out


def reported_with_current_rules(record: dict) -> bool:
    """Whether a finished fit's intervals were computed with the fitter's current uncertainty rules
    (the discretization check's safety factor `jaxfoam.calibrate.GCI_SAFETY`, its Jacobian,
    `DX_CHECK_JACOBIAN`, records from before the latter was recorded reused the fit grid's, and its measured
    move, `DEFAULT_DX_REFIT` iterations for the scene's dimension). The report applies the measured move to older records from a
    cache instead (`with_current_check`)."""
    check = record["fit"]["settings"].get("dx_check") or {}
    # records from before 2026-11-24 lack interval_local: a misfit then still reported its local interval
    return (check.get("safety") == GCI_SAFETY and check.get("jacobian", "fit") == DX_CHECK_JACOBIAN
            and check.get("refit") == fitter_refit(record) and "interval_local" in record["fit"])


def run_job(c: SceneCase, k: int, opt: str, quick: bool) -> Path:
    """Fit one case (resuming its log), or re-report a finished one whose intervals were computed with
    other uncertainty rules: `calibrate` then reads every iteration back from the fit log, runs no
    optimizer step, and recomputes the uncertainty at the same optimum (the fit's wall time keeps the
    logged optimizer time and adds this set-up and uncertainty)."""
    cid = case_id(c, k, quick)
    res_path = CASES / f"{cid}_{opt}.json"
    log = WORK / f"{cid}_{opt}.fitlog.h5"
    old = json.loads(res_path.read_text()) if res_path.exists() else None
    if old is not None and len(old["fit"]["runs"]) != starts_for(c, opt, quick):
        # a fit with another number of starts: kept aside, and this case fitted afresh
        tag = f".superseded-{len(old['fit']['runs'])}start"
        res_path.rename(res_path.with_name(res_path.name + tag))
        if log.exists():
            log.rename(log.with_name(log.name + tag))
        old = None
    if old is not None and (reported_with_current_rules(old) or not log.exists()):
        return res_path
    print(f"== {cid} {opt}: " + ("re-reporting the logged fit" if old else "data"), flush=True)
    data_path, synth_wall = make_data(c, k, quick)
    data = read_silhouettes(data_path)
    b = BUDGET[quick]
    settings = FitSettings(dx=c.dx_fit, optimizer=opt, starts=starts_for(c, opt, quick), max_iter=b["iters"][opt],
                           seed=0, time_window=c.window, dtype=c.fit_dtype)
    t0 = time.perf_counter()
    res = calibrate(data, settings, log=log, resume=True, progress=lambda m: print("  " + m, flush=True))
    fit = res.to_dict()
    if old is not None and not np.allclose([fit["params"][n] for n in GOALS], [old["fit"]["params"][n] for n in GOALS],
                                           rtol=1e-9, atol=0.0):
        raise RuntimeError(f"{cid} {opt}: re-reporting moved the fitted parameters; the log does not hold this fit")
    record = dict(case=cid, scene=c.name, set=k, optimizer=opt, dx_fit=c.dx_fit, dx_data=c.dx_fit / c.data_ratio,
                  data_variant=dict(tag=c.tag, noise=c.noise, drop_frames=c.drop_frames, pixel_size=data.camera.pixel_size,
                                    first_mask=c.first_mask),
                  duration=c.duration, frames=c.frames, truth=data.truth, fit=fit,
                  evaluation=evaluate(fit, data.truth),
                  fit_wall_this_session=old["fit_wall_this_session"] if old else time.perf_counter() - t0,
                  synth_wall=old["synth_wall"] if old else synth_wall, histories=_histories(log))
    if old is not None:
        prev = old["fit"]["settings"].get("dx_check") or {}
        record["rereported"] = dict(wall=time.perf_counter() - t0, date=time.strftime("%Y-%m-%d"),
                                    previous_safety=prev.get("safety"), previous_jacobian=prev.get("jacobian", "fit"),
                                    previous_evaluation=old["evaluation"],
                                    previous_numerical_error=old["fit"].get("numerical_error"))
    CASES.mkdir(parents=True, exist_ok=True)
    res_path.write_text(json.dumps(record, indent=1) + "\n")
    print(res.report(), flush=True)
    return res_path


def _histories(log: Path) -> dict:
    """Loss and wall-time histories of every start in a fit log."""
    runs = fitting.read_fitlog(log)["runs"]
    return {str(i): dict(loss=np.asarray(r["loss"]).tolist(), time=np.asarray(r["time"]).tolist()) for i, r in runs.items()}


# ----------------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------------

def load_records(quick: bool) -> list[dict]:
    recs = []
    for c in (QUICK if quick else FULL + PROBES + DATA + PRECISION):
        for k in range(N_SETS):
            for opt in ("lm", "lbfgs", "adam"):
                p = CASES / f"{case_id(c, k, quick)}_{opt}.json"
                if p.exists():
                    recs.append(json.loads(p.read_text()))
    return recs


def _fmt_shear(r: dict) -> str:
    c = case_of(r)
    try:
        sh = shear_rates(c, r["set"], r["case"].startswith("q_"))
    except Exception as exc:  # the table must not fail over a diagnostic
        return f"({type(exc).__name__})"
    return f"{100 * sh['yielding']:.0f}%; {sh['p10']:.2g}-{sh['p90']:.2g}"


def halved_step(r: dict) -> float:
    """How many times narrower than the fitter's time step a finished fit ran: 1 for a fit made with gap
    filling (`jaxfoam.calibrate.simulation_frames`) or whose data have no gap, k > 1 for a fit made before
    it whose data have a frame dropped inside the fitted span, so that every frame ran the substeps of
    its widest interval (k = that interval over the narrowest). Computed from the record's times."""
    from jaxfoam.calibrate import simulation_frames

    d = r["fit"]["data"]
    times = np.asarray(d["times"], float)[d["frames_used"]]
    t0 = float(d["times"][0]) if (r.get("data_variant") or {}).get("first_mask") else 0.0
    widest = float(np.max(np.diff(np.concatenate([[t0], times]))))
    sim_times, _ = simulation_frames(t0, times)
    filled = float(np.max(np.diff(np.concatenate([[t0], sim_times]))))
    n_fill = math.ceil(filled / r["fit"]["settings"]["dt"] - 1e-6)
    return widest / filled if r["fit"]["settings"]["substeps_per_frame"] > n_fill else 1.0


def _wall(r: dict, seconds: float | None = None) -> str:
    """A fit's wall time in minutes, marked † when it ran at a narrowed time step (`halved_step`)."""
    w = r["fit"]["wall_time"] if seconds is None else seconds
    return f"{w / 60:.1f}" + ("†" if halved_step(r) > 1.0 else "")


def _fmt_err(e: dict) -> str:
    s = f"{100 * e['error']:+.0f}%" if e["kind"] == "rel" else f"{e['error']:+.2f}"
    flags = ("" if e["inside"] else " out") + ("" if e["identifiable"] else " n.i.")
    return s + flags


def _probe_table(probe: list[dict], lm: list[dict], names, base_scene, base_of=None) -> str:
    """A probe's fits (FINE, SLIP, CONTACT), each after the study's LM fit of the same set on `base_scene(record)`:
    grids, errors, loss, loss at the truth, goodness of fit, wall time."""
    rows = []
    for r in sorted(probe, key=lambda r: (r["scene"], r["dx_fit"], r["set"])):
        same = [b for b in lm if b["scene"] == base_scene(r) and b["set"] == r["set"]]
        # the base fit on the probe's grid when there is one, else the study's
        base = next((b for b in same if b["dx_fit"] == r["dx_fit"]), same[0] if same else None)
        if base_of is not None and same:
            base = base_of(r, same)
        for x in ([base] if base else []) + [r]:
            cx = case_of(x)
            w = cx.window
            label = (x["scene"] + (f", t {w[0]:g}-{w[1]:g} s" if w else "")
                     + (f", {cx.fit_dtype}" if cx.fit_dtype != "float64" else ""))
            rows.append([label, x["set"], f"{x['dx_fit'] * 1e3:.2f}", f"{x['dx_data'] * 1e3:.2f}"]
                        + [_fmt_err(x["evaluation"][n]) for n in names]
                        + [f"{x['fit']['loss']:.3g}", f"{_truth_loss_of(x):.3g}", _fmt_gof(x),
                           _wall(x)])
    return C.md_table(["scene", "set", "fit dx (mm)", "data dx (mm)"] + [f"err {n}" for n in names]
                      + ["loss", "loss at truth", "min IoU; max boundary (spacings)", "wall min"], rows)


def _varied_table(varied: list[dict], lm: list[dict], names) -> str:
    """Per (scene, set): the main table's fit, then each data variant's (DATA order)."""
    order = {t: i for i, t in enumerate(dict.fromkeys(c.tag for c in DATA))}
    rows = []
    for scene, k in sorted({(r["scene"], r["set"]) for r in varied}):
        base = [b for b in lm if b["scene"] == scene and b["set"] == k]
        these = sorted((r for r in varied if r["scene"] == scene and r["set"] == k), key=lambda r: order[case_of(r).tag])
        for x in base + these:
            tag = case_of(x).tag or "main table"
            rows.append([scene, k, tag, f"{x['dx_data'] * 1e3:.2f}", f"{x['fit']['data']['pixel_size'] * 1e3:.2f}"]
                        + [_fmt_err(x["evaluation"][n]) for n in names]
                        + [f"{x['fit']['loss']:.3g}", f"{_truth_loss_of(x):.3g}", _fmt_gof(x),
                           _wall(x)])
    return C.md_table(["scene", "set", "data", "data dx (mm)", "pixel (mm)"] + [f"err {n}" for n in names]
                      + ["loss", "loss at truth", "min IoU; max boundary (spacings)", "wall min"], rows)


def _data_section(varied: list[dict], lm: list[dict], names) -> str:
    """The DATA probe: each variant's fits beside the main table's fit of the same set, and per variant the
    coverage and goal counts."""
    out = [f"\n## Data made differently (hanging plate and drop; squeeze with `mask`; 1 cm, LM, {DEFAULT_STARTS} starts)\n\n"
           "The main table's truths and fit settings, with data made otherwise, one change at a time (none "
           "chosen from these results): `fine4` data on a grid 4x finer than the fit instead of 2x; `noisy` "
           "boundary flips 0.2 and 30% of frames dropped (0.05, 10%); `pix` 1.25 mm camera pixels (2.5 mm), "
           "which the fitter coarsens; `mask` the file's scene starts from its first, noisy, mask, as a tracked "
           "video's does, not from the exact primitive; `fat` every mask grown by one pixel (2.5 mm), as a renderer "
           "or tracker that draws the boundary a pixel further out would; `numerics` the data simulated with "
           "another simulator's numerics: 9 particles per cell, CFL 0.5 and float32 (the fit: 4, 0.3, float64). "
           "Beside each, the main table's fit of the same set.\n\n",
           _varied_table(varied, lm, names), "\n"]
    base = {(r["scene"], r["set"]) for r in varied}
    same = [r for r in lm if (r["scene"], r["set"]) in base]
    n0, inside0, goals0, within0 = _tally(same, names)
    for tag in dict.fromkeys(case_of(r).tag for r in varied):
        rs = [r for r in varied if case_of(r).tag == tag]
        n, inside_v, goals_v, within_v = _tally(rs, names)
        out.append(f"- `{tag}`: truth inside the combined interval in {inside_v}/{n} parameter-cases, goal met in "
                   f"{goals_v}/{n}; within the error goal: " + ", ".join(f"{p} {within_v[p]}/{len(rs)}" for p in names)
                   + f"; wall time {min(r['fit']['wall_time'] for r in rs) / 60:.1f}-"
                     f"{max(r['fit']['wall_time'] for r in rs) / 60:.1f} min per fit.\n")
    out.append(f"- the main table's fits of the same sets: inside {inside0}/{n0}, goal met {goals0}/{n0}; within the "
               "error goal: " + ", ".join(f"{p} {within0[p]}/{len(same)}" for p in names) + ".\n")
    return "".join(out)


def _same_step_base(r: dict, base: list[dict]) -> dict:
    """The float64 fit of a float32 record's data made with the same time step: the current record, or the
    one it superseded when the gap filling changed its step (kept as <case>_lm.json.halved-dt)."""
    b = next(b for b in base if b["scene"] == r["scene"] and b["set"] == r["set"] and b["dx_fit"] == r["dx_fit"])
    old = CASES / f"{b['case']}_lm.json.halved-dt"
    if b["fit"]["settings"]["substeps_per_frame"] != r["fit"]["settings"]["substeps_per_frame"] and old.exists():
        return json.loads(old.read_text())
    return b


def _precision_section(f32: list[dict], base: list[dict], names) -> str:
    """The PRECISION probe: each float32 fit beside the float64 fit of the same data, and per grid the
    coverage, goal counts and the wall time against float64's."""
    out = [f"\n## Fits in float32 (main table's 2D fits and the default grid's squeeze; LM, {DEFAULT_STARTS} starts)\n\n"
           "The same data files, grids and budget as the float64 fits beside them, with the fit's rollouts, "
           "Jacobians and renderer in float32 (`jaxfoam fit --dtype float32`). The wall-time ratio is float64's "
           "over float32's, per fit.\n\n",
           _probe_table(f32, base, names, base_scene=lambda r: r["scene"],
                        base_of=lambda r, same: _same_step_base(r, same)), "\n"]
    for dx in sorted({r["dx_fit"] for r in f32}, reverse=True):
        rs = [r for r in f32 if r["dx_fit"] == dx]
        pairs = [(r, _same_step_base(r, base)) for r in rs]
        n, inside_v, goals_v, within_v = _tally(rs, names)
        n0, inside0, goals0, within0 = _tally([b for _, b in pairs], names)
        speed = [b["fit"]["wall_time"] / r["fit"]["wall_time"] for r, b in pairs]
        out.append(f"- dx {dx * 1e3:.2f} mm, float32: truth inside the combined interval in {inside_v}/{n} "
                   f"parameter-cases, goal met in {goals_v}/{n} (float64: {inside0}/{n0}, {goals0}/{n0}); within the "
                   "error goal: " + ", ".join(f"{p} {within_v[p]}/{len(rs)} ({within0[p]})" for p in names)
                   + f"; wall time {min(r['fit']['wall_time'] for r in rs) / 60:.1f}-"
                     f"{max(r['fit']['wall_time'] for r in rs) / 60:.1f} min per fit, "
                     f"{min(speed):.2f}-{max(speed):.2f}x faster than float64.\n")
    return "".join(out)


def _tally(recs: list[dict], names) -> tuple[int, int, int, dict]:
    """(parameter-cases, truth inside the interval, goal met, name -> within the error goal) of fits."""
    inside = sum(r["evaluation"][p]["inside"] for r in recs for p in names)
    goals = sum(r["evaluation"][p]["goal_met"] for r in recs for p in names)
    within = {p: sum(r["evaluation"][p]["within_goal"] for r in recs) for p in names}
    return len(names) * len(recs), inside, goals, within


def _default_grid_section(dflt: list[dict], lm: list[dict], names) -> str:
    """The DEFAULT_GRID probe: its fits beside the study's 1 cm fits of the same sets, and its coverage and
    goal counts (the same measures as the main table's summary)."""
    n, inside, goals, within = _tally(dflt, names)
    walls = [r["fit"]["wall_time"] / 60 for r in dflt]
    same = [b for b in lm if any(b["scene"] == r["scene"] and b["set"] == r["set"] for r in dflt)]
    lm3d = [b for b in lm if b["scene"].endswith("3d")]
    n3d, in3d, g3d, _ = _tally(lm3d, names)
    from jaxfoam.calibrate import FIT_CELLS

    grid = [r["dx_fit"] * 1e3 for r in dflt]
    coarse = f"{same[0]['dx_fit'] * 1e3:g} mm" if same else "dx_fit"
    return (f"\n## The fitter's default grid (2D, LM, {DEFAULT_STARTS} starts)\n\n"
            f"`jaxfoam fit` without `--dx` fits on the largest domain extent / {FIT_CELLS[2]} ({min(grid):.1f}-"
            f"{max(grid):.1f} mm for these scenes). The same truths, noise and budget, fitted on that grid to data "
            f"made at half its spacing; beside each, the same set at the study's {coarse}.\n\n"
            + _probe_table(dflt, lm, names, base_scene=lambda r: r["scene"])
            + f"\nOn the default grid: truth inside the combined interval in {inside}/{n} parameter-cases, goal met in "
            f"{goals}/{n}; within the error goal: " + ", ".join(f"{p} {within[p]}/{len(dflt)}" for p in names)
            + f" (at {coarse}, the same sets: " + ", ".join(
                f"{p} {sum(b['evaluation'][p]['within_goal'] for b in same)}/{len(same)}" for p in names)
            + f"). Wall time {min(walls):.1f}-{max(walls):.1f} min per fit (goal < 15 min)."
            + (f" With the 3D fits of the main table (dx {lm3d[0]['dx_fit'] * 1e3:g} mm) the truth is inside {inside + in3d}/{n + n3d} intervals "
               f"and the goal is met in {goals + g3d}/{n + n3d}." if n3d else "") + "\n"
            + "\nWhere the default grid differs from the data: at the true parameters, the mean distance between "
              "the fit grid's silhouette and the data's boundary in each used frame (time: particle spacings; "
              "the fitter's goodness-of-fit measure, limit 1):\n\n" + _truth_frames_table(dflt))


def _check_change_section(groups: list[tuple[str, list[dict]]], names) -> str:
    """How the discretization check's larger estimate (DX_CHECK_JACOBIAN "both", re-reported from the fit
    logs at the same optima) changed coverage and goals against the fit grid's Jacobian alone, per group of
    fits; empty when no record keeps its earlier evaluation."""
    rows = []
    for label, recs in groups:
        was = [r for r in recs if (r.get("rereported") or {}).get("previous_jacobian") == "fit"
               and "previous_evaluation" in r["rereported"]]
        if not was:
            continue
        n = len(names) * len(was)
        old = [r["rereported"]["previous_evaluation"] for r in was]
        new = [r["evaluation"] for r in was]

        def count(evs, key):
            return sum(e[p][key] for e in evs for p in names)

        rows.append([label, len(was), f"{count(old, 'inside')}/{n}", f"{count(new, 'inside')}/{n}",
                     f"{count(old, 'goal_met')}/{n}", f"{count(new, 'goal_met')}/{n}",
                     f"{count(old, 'identifiable')}/{n}", f"{count(new, 'identifiable')}/{n}"])
    if not rows:
        return ""
    return ("\n## Discretization check: the fit grid's Jacobian against both grids' (LM)\n\n"
            "The same optima, re-reported from their fit logs after the check changed (2026-11-24) from one "
            "estimate of the move between dx and dx / sqrt(2), with the fit grid's Jacobian, to the larger of that "
            "and the estimate with each grid's own Jacobian (`jaxfoam.calibrate.DX_CHECK_JACOBIAN`, "
            "docs/calibrate.md). Parameter-cases with the truth inside the reported interval, with the goal met "
            "(within tolerance, or not identifiable with the truth inside), and reported identifiable:\n\n"
            + C.md_table(["fits", "n", "inside: fit grid's J", "inside: both", "goal met: fit grid's J",
                          "goal met: both", "identifiable: fit grid's J", "identifiable: both"], rows))


def report(quick: bool, n_sets: int | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = [with_current_check(r) for r in load_records(quick)]
    jobs = plan(quick, n_sets)
    done = {(r["case"], r["optimizer"]) for r in recs}
    missing = [f"{c.name}{' at dx ' + format(c.dx_fit, '.4g') + ' m' if c in FINE + DEFAULT_GRID else ''} set {k} ({opt})"
               for _, c, k, opt in jobs if (case_id(c, k, quick), opt) not in done]
    n_done = len(recs)
    load_all = list(recs)
    fine = [r for r in recs if r["case"].startswith("fine_")]
    dflt = [r for r in recs if r["case"].startswith("dflt_")]
    slip = [r for r in recs if any(r["scene"] == c.name for c in SLIP)]
    contact = [r for r in recs if any(r["scene"] == c.name for c in CONTACT)]
    win = [r for r in recs if r["case"].startswith("win_")]
    f32 = [r for r in recs if r["case"].startswith("f32_")]
    varied = [r for r in recs if case_of(r).tag]
    recs = [r for r in recs if not r["case"].startswith(("fine_", "dflt_", "win_", "f32_")) and r not in slip
            and r not in contact and r not in varied]
    lm = [r for r in recs if r["optimizer"] == "lm"]
    names = list(GOALS)

    rows = []
    for r in lm:
        ev, fit = r["evaluation"], r["fit"]
        rows.append([r["scene"], r["set"], ", ".join(f"{n}={r['truth'][n]:.3g}" for n in names),
                     ", ".join(f"{fit['params'][n]:.3g}" for n in names)]
                    + [_fmt_err(ev[n]) for n in names]
                    + [f"{fit['loss']:.3g}", f"{_truth_loss_of(r):.3g}", _fmt_gof(r),
                       fit["iterations"], fit["evaluations"], fit["reason"], _wall(r),
                       _fmt_shear(r)])
    n_par = sum(len(names) for _ in lm)
    inside = sum(r["evaluation"][n]["inside"] for r in lm for n in names)
    inside_stat = sum(r["evaluation"][n]["inside_statistical"] for r in lm for n in names)
    goals = sum(r["evaluation"][n]["goal_met"] for r in lm for n in names)
    per_param = {n: (sum(r["evaluation"][n]["goal_met"] for r in lm), sum(r["evaluation"][n]["inside"] for r in lm))
                 for n in names}
    fits_2d = [r["fit"]["wall_time"] for r in lm if not r["scene"].endswith("3d")]

    body = []
    body.append("## What was run\n\n")
    b = BUDGET[quick]
    scenes = ", ".join(f"{c.name} (fit dx {c.dx_fit} m, data dx {c.dx_fit / 2} m, {c.duration} s, {c.frames} frames)"
                       for c in (QUICK if quick else FULL))
    body.append(
        f"{'Quick' if quick else 'Full'} study: scenes {scenes}; "
        f"parameter sets {sorted({k for _, _, k, _ in jobs})} of {truth_sets()}; "
        f"starts per fit {b['starts']} (3D fits: 1), iteration budgets per start {b['iters']}; data noise {NOISE} "
        f"(boundary pixel flips), "
        f"{DROP_FRAMES:.0%} of frames dropped, plate pixels weight 0. All four parameters are fitted with the "
        f"fitter's default bounds, starts and discretization check; density and kappa are the scene's.\n\n")
    body.append(f"Finished: {n_done} of {len(jobs)} planned fits."
                + (f" **Not run (out of time on the shared 2-core machine):** {', '.join(missing)}." if missing else "")
                + "\n\n")
    stale = [r for r in load_records(quick) if halved_step(r) > 1.0]
    if stale:
        body.append(
            f"**Time step of fits with a dropped frame (2026-11-24).** Every frame of a rollout runs the same "
            f"number of substeps, sized for its widest frame interval, so until the fitter filled gaps in the "
            f"data with unobserved frames (`jaxfoam.calibrate.simulation_frames`), a frame dropped inside the "
            f"fitted span made every frame run at half (or a third of) the fit's CFL time step, for 2-3x the "
            f"cost: the datasets of sets 1 and 2 have such a gap in every scene. The main table's LM fits, the "
            f"optimizer comparison's and the default grid's squeeze fits were re-run with the gaps filled (the "
            f"earlier records are kept as `<case>_<optimizer>.json.halved-dt`); {len(stale)} records below still ran "
            f"at the narrower step and are marked † at their wall time (the probes' and the float32 fits', the "
            f"last compared with the float64 fits made at the same step); their `loss at truth` is evaluated "
            f"with the gaps filled, as every other's.\n\n")
    if lm:
        body.append("## Recovery (Levenberg-Marquardt)\n\n")
        body.append("Errors: relative for mu, sigma_y, eta, absolute for m; `out` = truth outside the 95% interval, "
                    "`n.i.` = reported not identifiable. `loss at truth`: the fit's loss evaluated at the true "
                    "parameters on the fit grid (below `loss`: the optimizer stopped in another basin; above it: "
                    "the fit grid's own optimum lies away from the truth). The shear-rate column gives the "
                    "fraction of particle-frames that yield and the 10th-90th percentile of their plastic rate "
                    "in a rollout of the truth at the fit dx: eta and m are only separable when it spans "
                    "decades. `min IoU; max boundary`: the fitter's goodness-of-fit check, the smallest per-frame IoU "
                    "of the fitted silhouette with the data and the largest per-frame mean distance between their "
                    "boundaries in particle spacings (dx / 2 here); above FRAME_BOUNDARY_SPACINGS (1) the fitter "
                    "reports that it did not reproduce the data (**no**) and reports each parameter's bounds as its "
                    "interval, not identifiable (the interval at its optimum kept as `interval_local`).\n\n")
        body.append(C.md_table(["scene", "set", "truth (mu, sigma_y, eta, m)", "fit"] + [f"err {n}" for n in names]
                               + ["loss", "loss at truth", "min IoU; max boundary (spacings)", "iter", "evals", "stop", "wall min",
                                  "yielding; shear rate p10-p90 (1/s)"], rows))
        body.append("\nTrue value, fit and combined 95% interval of every parameter (LM):\n\n")
        irows = [[r["scene"], r["set"], n, f"{r['truth'][n]:.4g}", f"{r['fit']['params'][n]:.4g}",
                  "[" + ", ".join(f"{v:.4g}" for v in r["evaluation"][n]["interval"]) + "]",
                  "yes" if r["evaluation"][n]["inside"] else "**no**",
                  "yes" if r["evaluation"][n]["identifiable"] else "no"] for r in lm for n in names]
        body.append(C.md_table(["scene", "set", "param", "truth", "fit", "95% interval", "truth inside",
                                "identifiable"], irows))
        body.append(f"\nTruth inside the combined 95% interval: {inside}/{n_par} parameter-cases "
                    f"({100 * inside / max(n_par, 1):.1f}%; goal >= 90%: "
                    f"{'met' if inside >= 0.9 * n_par else 'missed'}); inside the Gauss-Newton interval alone: "
                    f"{inside_stat}/{n_par}. Goal met (within tolerance, or not identifiable with the truth inside): "
                    f"{goals}/{n_par}; per parameter (goal met, inside interval) of {len(lm)}: "
                    + ", ".join(f"{n} {g}/{i}" for n, (g, i) in per_param.items()) + ". ")
        good = [r for r in lm if goodness(r)[1] <= FRAME_BOUNDARY_SPACINGS]
        body.append(f"Fits that reproduce their data (boundaries within {FRAME_BOUNDARY_SPACINGS:g} particle spacing): {len(good)}/{len(lm)}; among them the truth is "
                    f"inside the combined interval in {sum(r['evaluation'][n]['inside'] for r in good for n in names)}"
                    f"/{len(names) * len(good)} parameter-cases and the goal is met in "
                    f"{sum(r['evaluation'][n]['goal_met'] for r in good for n in names)}/{len(names) * len(good)}. ")
        if fits_2d:
            body.append(f"2D fit wall time: {min(fits_2d) / 60:.1f}-{max(fits_2d) / 60:.1f} min (goal < 15 min), "
                        f"on a shared 2-core machine.\n")
        notes = [(r["scene"], r["set"], note) for r in lm for note in r["fit"]["notes"]]
        if notes:
            body.append("\nIdentifiability notes of the fits:\n\n" + "".join(f"- {s} set {k}: {n}\n" for s, k, n in notes))
    comp = [r for r in recs if (r["scene"], r["set"]) in {(s, k) for s, k in COMPARE[quick]}]
    if comp:
        body.append("\n## Optimizers on the same data\n\n")
        body.append("Each optimizer's first start (the same initial guess, the centre of the start ranges); "
                    "`wall min` is that start's optimizer time. For a multi-start LM fit whose best start is "
                    "another one, the goodness-of-fit column is `-` and the errors carry no interval flags "
                    "(intervals are computed at the best start only).\n\n")
        crow = []
        for r in comp:
            run, best = r["fit"]["runs"][0], r["fit"]["best_run"] == 0
            errs = [_fmt_err(r["evaluation"][n]) if best else
                    _fmt_err(dict(kind=GOALS[n][0], inside=True, identifiable=True,
                                  error=_error(run["end"][n], r["truth"][n], GOALS[n][0]))) for n in names]
            label = r["optimizer"] + (f" (start 1 of {len(r['fit']['runs'])})" if len(r["fit"]["runs"]) > 1 else "")
            # the lowest loss of the start (the fitter reports the best iterate: Adam's last need not be it)
            loss = r["fit"]["loss"] if best else min(r["histories"]["0"]["loss"])
            crow.append([r["scene"], r["set"], label, loss, _truth_loss_of(r), _fmt_gof(r) if best else "-",
                         run["iterations"], run["evaluations"], run["reason"], _wall(r, run["wall_time"])] + errs)
        body.append(C.md_table(["scene", "set", "optimizer", "final loss", "loss at truth", "min IoU; max boundary (spacings)", "iter", "evals",
                                "stop",
                                "wall min"]
                               + [f"err {n}" for n in names], crow))
    if lm:
        body.append("\n## Which scene constrains which parameter (LM fits)\n\n"
                    "Per scene: in how many fits the parameter was identifiable, and the median error "
                    "(relative; absolute for m) over the fits.\n\n")
        srows = []
        for scene in dict.fromkeys(r["scene"] for r in lm):
            rs = [r for r in lm if r["scene"] == scene]
            row = [scene, len(rs)]
            for n in names:
                ident = sum(r["evaluation"][n]["identifiable"] for r in rs)
                med = float(np.median([abs(r["evaluation"][n]["error"]) for r in rs]))
                row.append(f"{ident}/{len(rs)}, {100 * med:.0f}%" if GOALS[n][0] == "rel" else f"{ident}/{len(rs)}, {med:.2f}")
            srows.append(row)
        body.append(C.md_table(["scene", "fits"] + [f"{n}: identifiable, median err" for n in names], srows))
    if fine:
        body.append(f"\n## Finer fit grid (LM, {DEFAULT_STARTS} starts)\n\n"
                    "The same truths, noise and budget, fitted at dx_fit / sqrt(2) to data made at half that "
                    "(FINE); beside each, the same set at the study's dx_fit.\n\n")
        body.append(_probe_table(fine, lm, names, base_scene=lambda r: r["scene"]))
    if slip:
        body.append(f"\n## Frictionless floor (drop, LM, {DEFAULT_STARTS} starts)\n\n"
                    "The drop's truths, noise and budget on the same scene with floor friction 0 (data made on "
                    "that scene); beside each, the same set on the scene's floor (friction 0.5). "
                    "`experiments/results/floor_contact.md` measures the two floors across grid spacings.\n\n")
        body.append(_probe_table(slip, lm, names, base_scene=lambda r: "drop_2d"))
    if contact:
        body.append(f"\n## Particle floor contact (drop, LM, {DEFAULT_STARTS} starts)\n\n"
                    "The drop's truths, noise and budget on the same scene with particle floor contact (data made "
                    "on that scene): the landed foam rests on the floor on every grid instead of about 0.7 cells "
                    "above it; beside each, the same set with the default grid contact. "
                    "`experiments/results/floor_contact.md` compares the two contacts across grid spacings.\n\n")
        body.append(_probe_table(contact, lm, names, base_scene=lambda r: "drop_2d"))
    if win:
        w = WINDOW[0].window
        body.append(f"\n## Time window (squeeze, LM, {DEFAULT_STARTS} starts)\n\n"
                    f"The squeeze's data of the main table (the same files), fitted over t = {w[0]:g}-{w[1]:g} s "
                    "only: the squeeze and the hold, without the lift, in which the foam stuck to the rising plate "
                    "stretches (`FitSettings.time_window`, `jaxfoam fit --time-window`); beside each, the main "
                    "table's fit of all frames. `loss at truth` is over the window's frames.\n\n")
        body.append(_probe_table(win, lm + dflt, names, base_scene=lambda r: r["scene"]))
        for dx in sorted({r["dx_fit"] for r in win}, reverse=True):
            rs = [r for r in win if r["dx_fit"] == dx]
            n, inside_w, goals_w, within_w = _tally(rs, names)
            body.append(f"\nIn the window at dx {dx * 1e3:.2f} mm: truth inside the combined interval in "
                        f"{inside_w}/{n} parameter-cases, goal met in {goals_w}/{n}; within the error goal: "
                        + ", ".join(f"{p} {within_w[p]}/{len(rs)}" for p in names)
                        + f"; wall time {min(r['fit']['wall_time'] for r in rs) / 60:.1f}-"
                          f"{max(r['fit']['wall_time'] for r in rs) / 60:.1f} min per fit.\n")
    if dflt:
        body.append(_default_grid_section(dflt, lm, names))
    if varied:
        body.append(_data_section(varied, lm, names))
    if f32:
        body.append(_precision_section(f32, lm + dflt, names))
    body.append(_refit_section(lm))
    body.append(_measured_move_section([("main table", lm), ("default grid", [r for r in dflt if r["optimizer"] == "lm"]),
                                        ("probes and others", [r for r in load_all if r["optimizer"] == "lm"
                                                               and r not in lm and r not in dflt])], names))
    body.append(_shift_section(lm))
    body.append(_check_change_section([("main table, 1 cm (3D: 16 mm)", lm), ("default grid", dflt),
                                       ("probes: finer grid, floor, contact, window", fine + slip + contact + win)],
                                      names))
    if not quick and VERDICT:
        body.append("\n## Verdict\n\n" + VERDICT.strip() + "\n")

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    ax = axes[0]
    for j, n in enumerate(names):
        for i, r in enumerate(lm):
            e = r["evaluation"][n]
            t = e["truth"]
            lo, hi = e["interval"]
            if e["kind"] == "rel":
                y, ylo, yhi = e["error"], lo / t - 1, hi / t - 1
            else:
                y, ylo, yhi = e["error"], lo - t, hi - t
            ylo, yhi = max(ylo, -2.0), min(yhi, 2.0)
            x = j + (i - (len(lm) - 1) / 2) * 0.8 / max(len(lm), 1)
            ax.errorbar([x], [y], yerr=[[max(y - ylo, 0.0)], [max(yhi - y, 0.0)]], fmt="o" if e["identifiable"] else "s",
                        color="C0" if e["inside"] else "C3", ms=4, capsize=2, lw=1)
        kind, tol = GOALS[n]
        ax.fill_between([j - 0.45, j + 0.45], -tol, tol, color="0.85", zorder=0)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels([f"{n}\n({'rel' if GOALS[n][0] == 'rel' else 'abs'})" for n in names])
    ax.set_ylim(-1.5, 1.5)
    ax.set_ylabel("error (relative, or absolute for m) with 95% interval")
    ax.set_title("LM recovery: blue = truth inside, red = outside; grey = goal")
    ax = axes[1]
    for r in lm:
        for n in names:
            e = r["evaluation"][n]
            ax.scatter(e["truth"], e["value"], color=f"C{names.index(n)}", s=14)
    lim = [1e-1, 1e3]
    ax.plot(lim, lim, "k-", lw=0.6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("truth")
    ax.set_ylabel("fit")
    ax.set_title("fit vs truth (" + ", ".join(f"C{i}: {n}" for i, n in enumerate(names)) + ")", fontsize=9)
    ax = axes[2]
    styles = {"lm": "-", "lbfgs": "--", "adam": ":"}
    for r in comp:  # each optimizer's first start: the common initial guess
        h = r["histories"]["0"]
        colour = f"C{COMPARE[quick].index((r['scene'], r['set']))}"
        ax.semilogy(h["time"], h["loss"], styles[r["optimizer"]], color=colour,
                    label=f"{r['scene']} {r['set']} {r['optimizer']}")
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel("loss 0.5 |r|^2")
    ax.set_title("optimizers on the same data")
    if comp:
        ax.legend(fontsize=7)
    fig.tight_layout()
    C.save_fig(fig, NAME, quick)
    plt.close(fig)
    C.write_md(NAME, quick, "Parameter recovery from synthetic silhouettes", "".join(body))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one parameter set per scene, coarser fits, one start")
    ap.add_argument("--report", action="store_true", help="only rebuild the table and chart from finished cases")
    ap.add_argument("--only", default=None, help="run only jobs whose scene name contains this text")
    ap.add_argument("--refit-check", action="store_true",
                    help="refit the main table's LM fits on the discretization check's finer grid (cached), then report")
    ap.add_argument("--measured-check", type=int, nargs="?", const=0, default=None, metavar="N",
                    help="for every finished fit reported before the discretization check measured its move, run "
                         f"those LM iterations (alone: the fitter's, {DEFAULT_DX_REFIT[2]} in 2D and "
                         f"{DEFAULT_DX_REFIT[3]} in 3D; N: another budget, shown beside) on the check's grid (cached) "
                         "so the report shows it as the fitter reports it now, then report")
    ap.add_argument("--shift-check", action="store_true",
                    help="the discretization check's estimate on half- and quarter-cell shifted grids for the main table's LM fits (cached), then report")
    ap.add_argument("--sets", type=int, default=None,
                    help=f"parameter sets per scene (default 1 with --quick, {N_SETS} without)")
    args = ap.parse_args(argv)
    for wanted, label, check, cases in ((args.refit_check, "refit", refit_check, FULL + DEFAULT_GRID),
                                        (args.shift_check, "shift", shift_check, FULL)):
        if not wanted:
            continue
        for r in load_records(args.quick):
            if r["optimizer"] == "lm" and case_of(r) in (QUICK if args.quick else cases):
                print(f"== {label} check {r['case']}", flush=True)
                check(r)
        args.report = True
    if args.measured_check is not None:
        for r in load_records(args.quick):
            if "refit" not in (r["fit"]["settings"].get("dx_check") or {"refit": None}):
                n = args.measured_check or fitter_refit(r)
                print(f"== measured check ({n}) {r['case']} {r['optimizer']}", flush=True)
                measured_check(r, iterations=n)
        args.report = True
    if not args.report:
        for _, c, k, opt in plan(args.quick, args.sets):
            if args.only and args.only not in c.name:
                continue
            try:
                run_job(c, k, opt, args.quick)
                report(args.quick, args.sets)
            except Exception as exc:  # one failed case must not stop the study; it is reported as missing
                print(f"== {case_id(c, k, args.quick)} {opt} FAILED: {type(exc).__name__}: {exc}", flush=True)
    report(args.quick, args.sets)


if __name__ == "__main__":
    main()
