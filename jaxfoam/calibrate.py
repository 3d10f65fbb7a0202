"""Calibration: fit mu, sigma_y, eta and m of a scene to tracked silhouettes.

The glue between the silhouette data (`jaxfoam.io`), the simulator (`jaxfoam.Simulator`), the
differentiable renderer (`jaxfoam.silhouette`) and the optimizers (`fitting`):

1. `build_problem(data, settings)`: the scene comes from the data file; density and kappa are known
   inputs of the scene (never fitted; `fixed` may override them). A `Simulator` is bound once at the
   fit's dx, at the data's frame times, from the scene's initial shape (`first_mask`: the first mask
   and camera, and the simulation starts at the first frame's time). Its time step is the CFL step
   of the stiffest material the bounds allow (the largest mu), with a fixed number of substeps per
   frame, so the objective is a smooth function of the parameters.
2. The residual z -> r: fitted coordinates z (log / bounded maps of `fitting.ParameterTransform`)
   -> parameters -> rollout -> particle positions at the observed times -> soft silhouettes at the
   data's camera -> weighted residual images plus the distance-field terms (`silhouette.residuals`).
   The observed masks are compared at the pyramid level whose pixels are closest to (not larger than)
   the fit's particle spacing (`pixel_level`), so a fine video does not cost more than the simulation
   can resolve. Frames at or before the simulation's start carry no information on the parameters
   and are left out.
3. The Jacobian dr/dz by forward mode: one jvp rollout per fitted parameter (4 at most), each giving
   r and one column (no tape: memory independent of the number of substeps).
4. `calibrate(data, settings)`: the optimizer (Levenberg-Marquardt by default, or L-BFGS / Adam on
   0.5 |r|^2) from a multi-start (the centre of the starting range, then a seeded Latin hypercube),
   every iteration written to an HDF5 fit log (`resume=True` continues a killed fit), then the
   Gauss-Newton uncertainty at the best optimum (correlations, identifiability notes), widened by
   an estimate of the discretization error of the estimate (`discretization_error`: the residual and
   Jacobian once more on a finer grid), into 95% intervals, returned as a `FitResult`.

The command line is `jaxfoam fit data.h5 --out fit.json` (see `add_fit_parser`).
A fitter never reads the data's /truth: nothing here touches `Silhouettes.truth`.
Units: SI throughout (m, s, kg, Pa); fitted coordinates are dimensionless.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import functools
import hashlib
import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

import fitting
from fitting.uncertainty import DEFAULT_MAX_RELATIVE_WIDTH

from ._guards import (DEFAULT_MAX_PARTICLES, DEFAULT_MAX_SUBSTEPS, check_dtype_range, check_output, check_particles,
                      check_substeps, estimate_particles, missing_modules, substeps_per_frame, atomic_output)
from ._params import FIT_FIELDS, Params
from ._scene import Scene, init_state
from ._simulate import Simulator, _rollout_jit
from .fracture import FractureConfig
from .resample import ResampleConfig
from .io import Camera, Silhouettes, plate_footprint, read_silhouettes
from .silhouette import (BSPLINE_SUPPORT, RenderConfig, make_render_config, make_target, particle_spacing,
                         pyramid, render_frames, residuals)

# Bounds of the fitted parameters, SI units (Pa, Pa, Pa s^m, -): a wide envelope around foam
# rheometry (shear moduli of tens to ~1000 Pa, yield stresses of ~1 to a few 100 Pa, consistencies
# of ~0.1-100 Pa s^m, shear-thinning exponents 0.3-1; Durian 1990, Ovarlez 2010), so a bound is only
# reached by a fit that has gone wrong. mu's upper bound also sets the time step (see `build_problem`).
DEFAULT_BOUNDS = {"mu": (5.0, 2000.0), "sigma_y": (0.5, 500.0), "eta": (0.05, 500.0), "m": (0.2, 1.5)}
# Where multi-start initial guesses are drawn (log-uniform for mu, sigma_y, eta; uniform for m): the
# shaving-cream ranges of the same sources, a little widened. Start 0 is the centre of these ranges.
DEFAULT_START_RANGES = {"mu": (30.0, 600.0), "sigma_y": (5.0, 150.0), "eta": (0.5, 60.0), "m": (0.3, 1.0)}
# Parameters the fitter may fit; kappa (Pa) and rho (kg/m^3) are known inputs that `fixed` may override.
KNOWN_INPUTS = ("kappa", "rho")
OPTIMIZERS = ("lm", "lbfgs", "adam")
# Iteration budgets per optimizer: LM converges in ~10 Gauss-Newton steps on smooth problems, the
# quasi-Newton and first-order methods need more accepted iterations for the same decrease.
DEFAULT_MAX_ITER = {"lm": 30, "lbfgs": 60, "adam": 150}
# Adam's step in fitted (log) coordinates: 0.05 is a 5% relative change of a parameter per step;
# it halves over DEFAULT_ADAM_DECAY iterations so the iterate settles.
ADAM_LEARNING_RATE = 0.05
ADAM_DECAY = 50.0
# Stop when the loss changes by less than this fraction in an iteration, or the fitted coordinates by
# less than XTOL (relative): far below any interval a silhouette fit can give, and it spares rollouts.
FTOL = 1e-7
XTOL = 1e-6
DEFAULT_STARTS = 3
# Goodness of fit: per used frame, the mean displacement between the fitted and the observed
# silhouette boundaries (area of their symmetric difference over the observed perimeter, m). A silhouette
# drawn from particles places its boundary to within about half a particle spacing, so frames whose
# boundaries are on average more than one particle spacing apart (dx / 2 at the default ppc) are a misfit
# the discretization does not explain: a local minimum, or an event (tear-off, contact) the grid places at
# another time. IoU is reported too but does not decide: it penalizes thin shapes (right drop fits had
# IoU ~0.7 once the foam was a pancake a few cells thick).
FRAME_BOUNDARY_SPACINGS = 1.0
DEFAULT_LEVEL = 0.95
# Residual autocorrelation is integrated over lags up to this many kernel supports, per axis.
CORRELATION_WINDOW_SUPPORTS = 1.0
# Discretization check: the residual and Jacobian are evaluated once more on a grid this many times
# finer, and the shift of the estimate they imply is extrapolated to the continuum assuming first-order convergence
# (MPM silhouettes, with grid-boundary layers of about a cell, converge at best at first order in dx).
# Finer rather than coarser: a coarse fit is rarely in the asymptotic range, and the finer grid is
# the side the data (video, or a finer simulation) lie on; a Jacobian at dx / sqrt(2) costs about
# 2.8x one at dx in 2D (4x in 3D).
DX_CHECK_RATIO = 1.0 / math.sqrt(2.0)
DX_CHECK_ORDER = 1.0
# Which Jacobian the check's estimate of the move between the grids uses: "both" since 2026-11-24, the
# larger of the estimates with the fit grid's Jacobian and with each grid's own (`discretization_error`),
# at the price of one Jacobian on the finer grid (about 2.8x one at dx in 2D) instead of one rollout.
# Until then only the fit grid's ("fit"). Neither is reliable alone, measured against fits continued
# from the optimum on both grids (experiments/results/recovery.md, "Discretization check against
# refits"; moves in the fitted coordinates, quoted as the relative changes they make): on the default-grid
# squeeze set 1 sigma_y moved +46% in four LM iterations at 3.3 mm, the fit grid's Jacobian predicted +13%
# and the own Jacobians +6%; on the 12 main-table fits (24 moves of mu and sigma_y) the fit grid's
# prediction was the closer one in 15 and the own Jacobians' in 9, and the larger of the two, as the
# check's error, covered 23; on the slump of tests/test_calibrate.py a converged refit moved sigma_y
# +6.3%, predicted +7.2% (fit grid) and +5.1% (own).
DX_CHECK_JACOBIAN = "both"
# The check's measured move (FitSettings.dx_refit): LM iterations on the finer grid from the optimum, per
# dimension. The first-order estimates above miss where the residual is not linear over the move: in the
# recovery study's drop set 0 at 1 cm, 4 such iterations moved mu -18% where the estimates said -1.4% and
# +1.1% (the one refinement move of 24 the check's error missed), and the fit had reported mu identifiable,
# 20% off, the truth outside its interval. The iterations stop earlier when LM converges (FTOL, XTOL). The
# study re-reported every record with 2 and with 4 (experiments/results/recovery.md, "Discretization check
# with a measured move"). 2D: 4, because 2 (the default until 2026-11-25, later) left moves still growing:
# the default grid's drop set 1 then reported mu identifiable, 16% off (4: not identifiable, the truth
# inside); 4 took 17-118 s there (2: 9-62 s), the slowest fit (squeeze set 1) 12.1 -> 14.1 min. 3D: 2, because
# each iteration's Jacobian at dx / sqrt(2) costs about 4x one at dx (2.8x in 2D): 4 took 166-442 s on the
# study's 3D fits (2: 68-147 s), up to 1.8x the fit itself, and changed none of their intervals by more
# than 12%.
DEFAULT_DX_REFIT = {2: 4, 3: 2}
# Safety factor on the extrapolated numerical error: Roache's grid convergence index takes 3 for a
# two-grid estimate whose order is assumed, 1.25 only when three or more grids measure the order. The
# check uses two grids and an assumed order, so 3. (Until 2026-11-23 this was 1.25: in the recovery
# study the truth then lay outside 6 of 48 reported intervals, among them a hanging-plate mu whose
# actual error, 34 Pa, equalled its estimated numerical error; experiments/results/recovery.md.)
GCI_SAFETY = 3.0
# A parameter whose reported interval covers at least this fraction of its bounds is not identifiable:
# the data then say no more than the bounds do (e.g. m in [0.25, 1.5] with bounds [0.2, 1.5]).
BOUND_SPAN_FRACTION = 0.9
# The fit's default discretization and precision, from the measurements in experiments/MODEL_CHOICE.md
# (its `defaults` block states the same values; tests/test_model_choice.py keeps the two equal).
# Cells across the largest extent: 2D 64, the best grid measured on the drop; 3D 32, the affordable one (section 1).
FIT_CELLS = {2: 64, 3: 32}
# Particles per cell: 1 is 2-10x less accurate; 9 costs 2.25x the particles and helps one scene of three (section 1).
FIT_PPC = {2: 4, 3: 8}
# CFL number: 3.3x margin to instability; larger CFL worsens the current hanging plate and channel flow (section 2).
FIT_CFL = 0.3
# Precision: float32 fits reach float64's optima but run only 1.0-1.5x as fast (recovery study; section 2).
FIT_DTYPE = "float64"
# Particle resampling and fracture in the fit's rollouts: off (None). Section 4: on the three 2D fit scenes
# (32 cells) fracture changed no fit, resampling moved the parameters within the plain fit's 95% interval
# at 2.2-3.1x the fit's wall time (experiments/results/fit_features.md).
FIT_RESAMPLE = None
FIT_FRACTURE = None
# Jacobian columns are independent jvp rollouts. A fit's rollout (a few hundred to a few thousand
# particles) runs its small kernels one at a time on one core, so on the CPU backend the columns are
# split into this many groups evaluated concurrently from threads (results bit-identical): measured
# 1.13-1.31x faster per Jacobian on 2 cores shared with two other jobs (drop, 179 particles).
# 1 evaluates every column in one sequential call; other backends always do.
JACOBIAN_THREADS = 2
# Every frame of a rollout runs the same number of substeps, sized for its widest frame interval, so a
# gap in the data (a dropped frame) would shrink every frame's time step. The fit's rollouts record
# frames at the data's times with unobserved frames inserted into each gap, so that no interval is wider
# than the narrowest one (dropped frames of a video at a steady rate are filled back in exactly). At most
# this many simulated frames per observed one (data with a few frames close together: then the inserted
# frames are spaced at the duration / (this * observed frames)); a frame costs one sort and one record.
MAX_FRAMES_PER_OBSERVED = 4
# The coarsest pixel level keeps this many pixels across the image (choose_pixel_level's floor), and a
# fit's camera must put this many pixels across the scene domain.
MIN_LEVEL_PIXELS = 8
MIN_DOMAIN_PIXELS = 8


class CalibrationError(ValueError):
    """Bad calibration input (settings, data); the message names the field."""


# ----------------------------------------------------------------------------------------------
# Settings and results
# ----------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class FitSettings:
    """What to fit and how (all SI units).

    Attributes:
      dx: grid spacing of the fit, m (None: the largest domain extent / FIT_CELLS: 64 in 2D, 32 in 3D).
      ppc: particles per cell (None: FIT_PPC: 4 in 2D, 8 in 3D).
      optimizer: "lm" (Levenberg-Marquardt), "lbfgs" or "adam".
      fixed: name -> value: fitted parameters held fixed (mu, sigma_y, eta, m), or overrides of the
        scene's known inputs kappa (Pa) and rho (kg/m^3).
      bounds: name -> (lo, hi) replacing DEFAULT_BOUNDS for that parameter.
      start_ranges: name -> (lo, hi) replacing DEFAULT_START_RANGES (clipped to the bounds).
      starts: number of multi-start initial guesses (>= 1).
      initial: name -> value (physical units): the first start's guess for those fitted parameters, e.g. the
        result of an earlier fit of the same data (`--start FIT.json`); the others start at the centre of
        their start ranges, and starts after the first are the Latin-hypercube points as usual. None: the
        centre of the start ranges. Each value must lie within its bounds (one on a bound starts just inside).
      max_iter: accepted iterations per start (None: DEFAULT_MAX_ITER of the optimizer).
      time_window: (t_lo, t_hi), s: fit only the frames whose times lie in it (None: every frame after the
        start); the rollouts then stop at the last of them. For data whose late phase the model (or a
        coarse grid) does not resolve, e.g. foam tearing off a plate.
      time_budget: wall-time budget of the optimization (all starts together), s; None: unlimited. It is
        checked before each iteration: a start stops when the time left is shorter than its previous
        iteration took, and starts with no time left do not run. The best point found is then reported
        (with a note), and the fit can be continued with `resume` under a new budget. Building the
        simulator before, and the uncertainty and discretization check after, are not counted.
      seed: Latin-hypercube seed of the starts (and particle sampling seed).
      pixel_level: pyramid level of the observations (0 = the data's pixels, l = 2^l times larger);
        None picks the coarsest level whose pixels are not larger than the particle spacing.
      level: confidence level of the intervals.
      dtype: "float64" (FIT_DTYPE) or "float32".
      distance_weight, chamfer_weight: weights of the distance-field terms in the residual.
      dx_check: estimate the numerical (discretization) error of the estimate from the residual and
        Jacobian on a grid of spacing DX_CHECK_RATIO dx and widen the intervals by it (see
        `discretization_error`).
      dx_refit: Levenberg-Marquardt iterations (>= 0; None: DEFAULT_DX_REFIT, 4 in 2D, 2 in 3D) that the discretization
        check also runs on its finer grid from the optimum; the move they measure enters the check beside its
        two first-order estimates (the largest counts). 0: the estimates only. Ignored without dx_check. Costs
        one or two Jacobians on the finer grid per iteration.
      resample: particle resampling in every rollout of the fit (loss, Jacobian, discretization check,
        pictures): None or False (off, FIT_RESAMPLE), True (a default `jaxfoam.resample.ResampleConfig`),
        a dict of its fields, or a ResampleConfig. Its target ppc, if not given, is the fit's ppc (which
        must then be k^d); the initial state gets `capacity_factor` times the sampled slots.
      fracture: the fracture stage in every substep of the fit's rollouts: None or False (off,
        FIT_FRACTURE), True (a default `jaxfoam.fracture.FractureConfig`), a dict, or a FractureConfig.

    With resampling or fracture on, the Jacobian (and so the optimizer's steps and the Gauss-Newton
    intervals) is the derivative of the rollout with the discrete decisions held fixed: which points
    merge, which candidates are inserted where (and the material SDF that admits them), and which points
    are weak, are made on stop-gradient values and enter as data. The mass-weighted transfers that follow
    a decision, and the strain release of a weak point, are differentiated. Between decision flips the
    loss is smooth and the Jacobian exact; at a flip the loss jumps, which no derivative sees (a
    finite-difference or line-search step across it may see a different loss than the model predicts).
    """

    dx: float | None = None
    ppc: int | None = None
    optimizer: str = "lm"
    fixed: Mapping = dataclasses.field(default_factory=dict)
    bounds: Mapping = dataclasses.field(default_factory=dict)
    start_ranges: Mapping = dataclasses.field(default_factory=dict)
    starts: int = DEFAULT_STARTS
    initial: Mapping | None = None
    max_iter: int | None = None
    time_budget: float | None = None
    time_window: tuple | None = None
    seed: int = 0
    pixel_level: int | None = None
    level: float = DEFAULT_LEVEL
    dtype: str = FIT_DTYPE
    distance_weight: float = 1.0
    chamfer_weight: float = 1.0
    dx_check: bool = True
    dx_refit: int | None = None
    resample: object = FIT_RESAMPLE
    fracture: object = FIT_FRACTURE

    def __post_init__(self):
        # True / dict -> the config object (frozen dataclass: set through object.__setattr__).
        object.__setattr__(self, "resample", _as_config(self.resample, ResampleConfig, "resample"))
        object.__setattr__(self, "fracture", _as_config(self.fracture, FractureConfig, "fracture"))

    def validate(self) -> "FitSettings":
        if self.optimizer not in OPTIMIZERS:
            raise CalibrationError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.dx is not None and not (self.dx > 0 and math.isfinite(self.dx)):
            raise CalibrationError(f"dx must be a positive grid spacing in m, got {self.dx!r}")
        if self.ppc is not None and int(self.ppc) < 1:
            raise CalibrationError(f"ppc must be >= 1, got {self.ppc!r}")
        if self.dx_refit is not None and (isinstance(self.dx_refit, bool) or int(self.dx_refit) != self.dx_refit
                                          or self.dx_refit < 0):
            raise CalibrationError(f"dx_refit must be a whole number of iterations >= 0, got {self.dx_refit!r}")
        for name, value in self.fixed.items():
            if name not in FIT_FIELDS + KNOWN_INPUTS:
                raise CalibrationError(f"fixed: unknown parameter {name!r}; expected one of {FIT_FIELDS + KNOWN_INPUTS}")
            if not math.isfinite(float(value)):
                raise CalibrationError(f"fixed: {name} must be a finite number, got {value!r}")
        if all(n in self.fixed for n in FIT_FIELDS):
            raise CalibrationError(f"fixed: every parameter {FIT_FIELDS} is fixed, nothing is left to fit")
        for label, table in (("bounds", self.bounds), ("start_ranges", self.start_ranges)):
            for name, (lo, hi) in table.items():
                if name not in FIT_FIELDS:
                    raise CalibrationError(f"{label}: unknown parameter {name!r}; expected one of {FIT_FIELDS}")
                if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
                    raise CalibrationError(f"{label}: {name} needs finite 0 < lo < hi, got {lo}:{hi}")
        if not int(self.starts) >= 1:
            raise CalibrationError(f"starts must be >= 1, got {self.starts!r}")
        for name, value in (self.initial or {}).items():
            if name not in FIT_FIELDS:
                raise CalibrationError(f"initial: unknown parameter {name!r}; expected one of {FIT_FIELDS}")
            if name in self.fixed:
                raise CalibrationError(f"initial: {name} is fixed (fixed={dict(self.fixed)}); give it one or the other")
            lo, hi = self.bounds_of(name)
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise CalibrationError(f"initial: {name} must be a number, got {value!r}") from None
            if not (math.isfinite(v) and lo <= v <= hi):
                raise CalibrationError(f"initial: {name} = {value!r} must lie within its bounds [{lo:g}, {hi:g}]")
        if self.max_iter is not None and int(self.max_iter) < 0:
            raise CalibrationError(f"max_iter must be >= 0, got {self.max_iter!r}")
        if self.time_budget is not None and not (isinstance(self.time_budget, (int, float)) and
                                                 math.isfinite(self.time_budget) and self.time_budget > 0):
            raise CalibrationError(f"time_budget must be None or a positive number of seconds, got "
                                   f"{self.time_budget!r}")
        if self.time_window is not None:
            try:
                lo, hi = (float(v) for v in self.time_window)
            except (TypeError, ValueError):
                raise CalibrationError(f"time_window must be (t_lo, t_hi) in s, got {self.time_window!r}") from None
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi):
                raise CalibrationError(f"time_window needs finite 0 <= t_lo < t_hi in s, got {lo}:{hi}")
        if self.pixel_level is not None and int(self.pixel_level) < 0:
            raise CalibrationError(f"pixel_level must be >= 0, got {self.pixel_level!r}")
        if not 0.0 < self.level < 1.0:
            raise CalibrationError(f"level must be in (0, 1), got {self.level!r}")
        if self.dtype not in ("float32", "float64"):
            raise CalibrationError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if not (self.distance_weight >= 0 and self.chamfer_weight >= 0):
            raise CalibrationError("distance_weight and chamfer_weight must be >= 0")
        for label, cfg in (("resample", self.resample), ("fracture", self.fracture)):
            if cfg is not None:
                _check_config(cfg, label)  # the checks that hold in 2D or 3D; build_problem checks the scene's d
        return self

    def resample_for(self, d: int, ppc: int):
        """The ResampleConfig the fit uses in dimension d at `ppc` particles per cell (its target ppc
        defaults to the fit's), validated; None when resampling is off."""
        if self.resample is None:
            return None
        cfg = self.resample
        if cfg.ppc is None:
            k = round(ppc ** (1.0 / d))
            if k ** d != ppc:
                raise CalibrationError(f"resample: the fit's ppc = {ppc} is not k^{d} for an integer k, so the "
                                       f"resampler has no target lattice; give resample.ppc (e.g. {2 ** d}) or a "
                                       f"ppc such as {2 ** d} or {3 ** d}")
            cfg = dataclasses.replace(cfg, ppc=int(ppc))
        try:
            return cfg.validate(d)
        except ValueError as exc:
            raise CalibrationError(f"resample: {exc}") from exc

    def fracture_for(self, d: int):
        """The FractureConfig the fit uses in dimension d, validated; None when fracture is off."""
        if self.fracture is None:
            return None
        try:
            return self.fracture.validate(d)
        except ValueError as exc:
            raise CalibrationError(f"fracture: {exc}") from exc

    @property
    def fitted(self) -> tuple:
        """Names of the fitted parameters, in FIT_FIELDS order."""
        return tuple(n for n in FIT_FIELDS if n not in self.fixed)

    @property
    def iterations(self) -> int:
        return DEFAULT_MAX_ITER[self.optimizer] if self.max_iter is None else int(self.max_iter)

    def bounds_of(self, name) -> tuple:
        return tuple(float(v) for v in self.bounds.get(name, DEFAULT_BOUNDS[name]))

    def start_range_of(self, name) -> tuple:
        lo, hi = self.bounds_of(name)
        slo, shi = self.start_ranges.get(name, DEFAULT_START_RANGES[name])
        slo, shi = max(float(slo), lo), min(float(shi), hi)
        if not slo < shi:  # the user's bounds exclude the default range: start anywhere inside them
            slo, shi = lo, hi
        return slo, shi

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["fixed"] = {k: float(v) for k, v in self.fixed.items()}
        d["bounds"] = {n: list(self.bounds_of(n)) for n in FIT_FIELDS}
        d["start_ranges"] = {n: list(self.start_range_of(n)) for n in FIT_FIELDS}
        d["max_iter"] = self.iterations
        d["initial"] = None if self.initial is None else {k: float(v) for k, v in self.initial.items()}
        # The feature configs as dicts of their fields (None when off).
        d["resample"] = None if self.resample is None else dataclasses.asdict(self.resample)
        d["fracture"] = None if self.fracture is None else dataclasses.asdict(self.fracture)
        return d


def _as_config(value, kind, label):
    """None/False -> None; True -> kind(); dict -> kind(**dict); an instance of kind -> itself."""
    if value is None or value is False:
        return None
    if value is True:
        return kind()
    if isinstance(value, kind):
        return value
    if isinstance(value, Mapping):
        fields = {f.name for f in dataclasses.fields(kind)}
        unknown = sorted(set(value) - fields)
        if unknown:
            raise CalibrationError(f"{label}: unknown field(s) {unknown}; expected some of {sorted(fields)}")
        try:
            return kind(**dict(value))
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{label}: {exc}") from exc
    raise CalibrationError(f"{label} must be None, True/False, a dict of {kind.__name__} fields or a "
                           f"{kind.__name__}, got {value!r}")


def _check_config(cfg, label):
    """Raise CalibrationError if `cfg` (ResampleConfig or FractureConfig) is invalid in both 2D and 3D
    (a field out of range whatever the scene); the scene's own dimension is checked by build_problem."""
    errors = []
    for d in (2, 3):
        try:
            cfg.validate(d)
            return
        except (ValueError, TypeError) as exc:
            errors.append(exc)
    raise CalibrationError(f"{label}: {errors[0]}")


@dataclasses.dataclass(frozen=True)
class FitResult:
    """The outcome of `calibrate`.

    Attributes:
      params: every material parameter used, name -> value (mu Pa, sigma_y Pa, eta Pa s^m, m,
        kappa Pa, rho kg/m^3): fitted ones at the optimum, fixed and known ones as given.
      fitted: names of the fitted parameters.
      interval: fitted name -> (lo, hi), the `level` interval (physical units): the statistical
        (Gauss-Newton) half-width and the numerical error combined in quadrature, in fitted coordinates.
      interval_statistical: the Gauss-Newton interval alone (noise-like misfit only).
      numerical_error: fitted name -> estimated error of the estimate from the fit's discretization, as
        a half-width in physical units (GCI_SAFETY times the first-order extrapolated shift, mapped
        through the parameter's transform; 0 without dx_check).
      stderr: fitted name -> local standard error (physical units), statistical.
      correlation: (p, p) correlation matrix of the fitted parameters (order of `fitted`).
      identifiable: fitted name -> whether the data determine it.
      notes: plain-language identifiability findings.
      loss: 0.5 |r|^2 at the optimum (dimensionless): the lowest over every iterate of every start.
      loss_history: (K+1,) loss per iteration of the best start.
      time_history: (K+1,) wall time of each of those iterations, s since its start.
      runs: one dict per start: start and end parameters, loss, reason, iterations, evaluations, wall time.
      best_run: index of the start with the lowest loss.  best_iteration: its iteration with that loss
        (the last one, except for Adam, whose loss may rise again).
      reason: why the best start stopped.  iterations, evaluations: of the best start.
      settings: the `FitSettings` as a dict, plus the resolved dx, pixel level and substeps.
      data: summary of the data (frames, image size, pixel size, frames used).
      wall_time: seconds for the whole calibration: set-up, every start's optimizer time (summed over
        resumes, from the fit log) and the uncertainty.
      n_effective: effective number of independent residuals used for the intervals.
      uncertainty: the `fitting.Uncertainty` (None when the Jacobian was not finite).
      residual: (n,) residual vector at the optimum (not written to JSON; `plot_overlay` uses it).
      frame_iou: per used frame, the IoU of the fitted silhouette (soft occupancy >= 1/2) with the
        observed mask over weighted pixels.  frame_boundary_error: per used frame, the mean distance
        between the two silhouettes' boundaries, m (`silhouette_mismatch`).  frame_boundary_limit: the
        largest admitted, m: FRAME_BOUNDARY_SPACINGS particle spacings. `reproduces_data` is False, and
        a note says so, when a frame exceeds it. The intervals assume a fit that reproduces the data, so
        `interval` is then each parameter's bounds (the data, as fitted, exclude nothing the bounds
        allow) and no parameter is identifiable; the interval computed at the optimum is kept in
        `interval_local`.
      interval_local: the combined interval at the optimum before the goodness-of-fit check (equal to
        `interval` when the fit reproduces the data).
    """

    params: dict
    fitted: tuple
    interval: dict
    interval_statistical: dict
    numerical_error: dict
    stderr: dict
    correlation: np.ndarray
    identifiable: dict
    notes: tuple
    loss: float
    loss_history: np.ndarray
    time_history: np.ndarray
    runs: list
    best_run: int
    best_iteration: int
    reason: str
    iterations: int
    evaluations: int
    settings: dict
    data: dict
    wall_time: float
    n_effective: float
    uncertainty: fitting.Uncertainty | None = None
    residual: np.ndarray | None = None
    frame_iou: tuple = ()
    frame_boundary_error: tuple = ()
    frame_boundary_limit: float = math.nan
    interval_local: dict | None = None

    @property
    def reproduces_data(self) -> bool:
        """Whether every used frame's fitted silhouette boundary lies within frame_boundary_limit of the
        observed one on average."""
        return bool(len(self.frame_boundary_error)) and max(self.frame_boundary_error) <= self.frame_boundary_limit

    def to_dict(self) -> dict:
        """JSON-able dict (infinite interval ends as "inf"/"-inf", undefined values as null)."""

        def clean(v):
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple, np.ndarray)):
                return [clean(x) for x in v]
            if isinstance(v, (np.floating, float)):
                v = float(v)
                return None if math.isnan(v) else (v if math.isfinite(v) else ("inf" if v > 0 else "-inf"))
            if isinstance(v, (np.integer,)):
                return int(v)
            if isinstance(v, np.bool_):
                return bool(v)
            return v

        return clean({
            "format": "jaxfoam-fit", "version": 1,
            "params": self.params, "fitted": list(self.fitted), "level": self.settings.get("level"),
            "interval": self.interval, "interval_statistical": self.interval_statistical,
            "interval_local": self.interval if self.interval_local is None else self.interval_local,
            "numerical_error": self.numerical_error, "stderr": self.stderr, "correlation": self.correlation,
            "identifiable": self.identifiable, "notes": list(self.notes), "loss": self.loss,
            "loss_history": self.loss_history, "time_history": self.time_history, "runs": self.runs,
            "best_run": self.best_run, "best_iteration": self.best_iteration, "reason": self.reason, "iterations": self.iterations,
            "evaluations": self.evaluations, "settings": self.settings, "data": self.data,
            "wall_time": self.wall_time, "n_effective": self.n_effective,
            "frame_iou": list(self.frame_iou), "frame_boundary_error": list(self.frame_boundary_error),
            "frame_boundary_limit": self.frame_boundary_limit, "reproduces_data": self.reproduces_data,
        })

    def write(self, path) -> None:
        """Write `to_dict()` as JSON to `path`."""
        text = json.dumps(self.to_dict(), indent=2) + "\n"
        with atomic_output(path) as tmp:
            Path(tmp).write_text(text)

    def report(self) -> str:
        """A plain-text summary: values, intervals, correlations, notes."""
        pct = f"{100 * self.settings['level']:g}%"
        lines = [f"{'parameter':<10} {'value':>11}   {pct} interval{'':<14} statistical part    numerical error"]
        for n in FIT_FIELDS + KNOWN_INPUTS:
            v = self.params[n]
            if n in self.fitted:
                lo, hi = self.interval[n]
                slo, shi = self.interval_statistical[n]
                lines.append(f"{n:<10} {v:>11.5g}   {f'[{lo:.4g}, {hi:.4g}]':<26} {f'[{slo:.4g}, {shi:.4g}]':<19} "
                             f"{self.numerical_error[n]:.3g}" + ("" if self.identifiable[n] else
                                                                 "  (not identifiable)"))
            else:
                lines.append(f"{n:<10} {v:>11.5g}   (fixed)" if n in FIT_FIELDS else
                             f"{n:<10} {v:>11.5g}   (known input)")
        if len(self.fitted) > 1:
            lines.append("correlation: " + "  ".join(
                f"{a}-{b} {self.correlation[i, j]:+.2f}" for i, a in enumerate(self.fitted)
                for j, b in enumerate(self.fitted) if i < j))
        lines.extend(self.notes)
        if len(self.frame_boundary_error):
            worst = max(self.frame_boundary_error)
            lines.append(f"goodness of fit per frame: mean boundary distance max {worst:.3g} m (limit "
                         f"{self.frame_boundary_limit:.3g} m = {FRAME_BOUNDARY_SPACINGS:g} particle spacing), silhouette "
                         f"IoU min {min(self.frame_iou):.3f}: the data are "
                         f"{'reproduced' if self.reproduces_data else 'NOT reproduced'}")
        lines.append(f"loss {self.loss:.5g} after {self.iterations} iterations ({self.reason}), best of "
                     f"{len(self.runs)} start(s); {self.wall_time:.1f} s wall")
        return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# The problem: simulator, observations, residual and its Jacobian
# ----------------------------------------------------------------------------------------------

def observe_positions(state, params) -> dict:
    """Per-frame record of a fit: positions x (N, d) m and the active mask (N,)."""
    return dict(x=state.x, active=state.active)


@dataclasses.dataclass(frozen=True)
class _Static:
    """Hashable configuration of the residual (a static argument of the jitted functions)."""

    transform: fitting.ParameterTransform
    grid: object
    substeps: int
    cfg: RenderConfig
    distance_weight: float
    chamfer_weight: float
    resample: ResampleConfig | None = None
    fracture: FractureConfig | None = None
    observed: tuple = ()  # indices of the observed frames among the rollout's (`simulation_frames`)


def simulation_frames(t0: float, times, max_ratio: int = MAX_FRAMES_PER_OBSERVED) -> tuple[np.ndarray, np.ndarray]:
    """The frame times (s) a fit's rollout records, and where the observed `times` are among them.

    Each interval between t0 (s) and the observed times, in order, is split into equal parts no wider
    than h, the narrowest interval (or duration / (max_ratio * len(times)) where that is wider), so the
    substeps per frame, sized for the widest recorded interval, keep the CFL time step instead of
    shrinking it for every frame when the data have gaps. Returns (frame times (S,), indices (F,) of the
    observed times in them); without gaps they are `times` and arange(F)."""
    times = np.asarray(times, float)
    edges = np.concatenate([[float(t0)], times])
    widths = np.diff(edges)
    h = max(float(widths.min()), (edges[-1] - edges[0]) / (max_ratio * len(times)))
    parts = np.maximum(1, np.ceil(widths / h * (1.0 - 1e-9))).astype(int)
    out, idx = [], []
    for a, b, n in zip(edges[:-1], edges[1:], parts):
        out.extend(a + (b - a) * np.arange(1, n) / n)
        out.append(b)
        idx.append(len(out) - 1)
    return np.asarray(out), np.asarray(idx)


def _observed(frames: dict, static) -> tuple:
    """Positions and active flags of a rollout's frames at the observed times (`_Static.observed`)."""
    idx = np.asarray(static.observed)
    return frames["x"][idx], frames["active"][idx]


def _params_from(z, static: _Static, base: Params) -> Params:
    theta = static.transform.to_physical(z)
    return base.replace(**{n: theta[i] for i, n in enumerate(static.transform.names)})


def _residual(z, static: _Static, base: Params, state0, scene, frame_times, frame_dts, target):
    params = _params_from(z, static, base)
    _, frames, _ = _rollout_jit(state0, params, scene, frame_times, frame_dts, static.grid, static.substeps,
                                observe_positions, False, static.resample, static.fracture)
    x, active = _observed(frames, static)
    return residuals(x, active, target, static.cfg, distance=static.distance_weight,
                     chamfer_weight=static.chamfer_weight)


@functools.partial(jax.jit, static_argnames=("static",))
def _residual_jit(z, static, base, state0, scene, frame_times, frame_dts, target):
    return _residual(z, static, base, state0, scene, frame_times, frame_dts, target)


@functools.partial(jax.jit, static_argnames=("static",))
def _residual_and_jacobian(z, static, base, state0, scene, frame_times, frame_dts, target):
    """(r (n,), dr/dz (n, p)) by forward mode: one jvp rollout per fitted parameter (p <= 4).

    Each column is `jax.jvp` along one basis vector, run in sequence by `lax.map` (one compiled
    rollout body). Not `jax.jacfwd`: it vmaps the tangents, which ran 42x slower than the forward
    rollout on XLA:CPU in an early version (2,813 particles, 4 tangents) where one jvp (along sigma_y)
    cost about one forward rollout. Re-measured on 2026-11-25 (default-grid drop fit, 794 particles,
    3,530 substeps, 2 cores, the whole residual and Jacobian as multiples of the residual's wall
    time): these columns in two threads (`CalibrationProblem.residual_and_jacobian`) 4.0x, in one
    thread 7.5x, `jax.jacfwd` 6.0x. Nor `jax.linearize` once with the linear map applied per column:
    it stores every substep's residuals, and ran 2.4x slower (drop scene, 179 particles, 3,310
    substeps: 2.27 against 0.95 s wall, one thread).
    """

    def fn(zz):
        return _residual(zz, static, base, state0, scene, frame_times, frame_dts, target)

    def column(e):
        return jax.jvp(fn, (z,), (e,))

    rs, cols = jax.lax.map(column, jnp.eye(z.shape[0], dtype=z.dtype))
    return rs[0], cols.T


@functools.partial(jax.jit, static_argnames=("static",))
def _residual_and_columns(z, basis, static, base, state0, scene, frame_times, frame_dts, target):
    """r (n,) and the directional derivatives dr/dz . e (k, n) along the rows e of `basis` (k, p),
    one jvp rollout per row in sequence (`lax.map`); a zero row gives a zero column."""

    def fn(zz):
        return _residual(zz, static, base, state0, scene, frame_times, frame_dts, target)

    rs, cols = jax.lax.map(lambda e: jax.jvp(fn, (z,), (e,)), basis)
    return rs[0], cols


@functools.partial(jax.jit, static_argnames=("static",))
def _positions(z, static, base, state0, scene, frame_times, frame_dts):
    params = _params_from(z, static, base)
    _, frames, health = _rollout_jit(state0, params, scene, frame_times, frame_dts, static.grid, static.substeps,
                                     observe_positions, False, static.resample, static.fracture)
    return frames["x"], frames["active"], health


class CalibrationProblem:
    """A dataset bound to a simulator, a renderer and a parameter transform (built by `build_problem`).

    Attributes:
      data: the `Silhouettes`.  settings: the `FitSettings`.  scene: the parsed scene.
      sim: the `Simulator` at the fit's dx (frame times: the used data times, with unobserved frames
        filling the gaps, `simulation_frames`; `observed` says which are the data's).
      transform: `fitting.ParameterTransform` of the fitted parameters.
      base: `Params` with the fixed and known values (fitted entries are placeholders).
      frames: (F,) indices into the data's frames that enter the residual.
      masks, weights, camera: observations at the chosen pyramid level.  cfg: its `RenderConfig`.
      pixel_level: that level.  dx: the fit's grid spacing, m.
    """

    def __init__(self, data: Silhouettes, settings: FitSettings, sim: Simulator, transform, base: Params,
                 frames: np.ndarray, level: int, masks, weights, camera: Camera, cfg: RenderConfig, target,
                 observed=None):
        self.data, self.settings, self.sim, self.scene = data, settings, sim, sim.scene
        self.transform, self.base, self.frames = transform, base, frames
        self.observed = np.arange(len(frames)) if observed is None else np.asarray(observed)
        self.pixel_level, self.masks, self.weights, self.camera, self.cfg = level, masks, weights, camera, cfg
        self.target = target
        self.dx = sim.dx
        self.static = _Static(transform=transform, grid=sim.grid, substeps=sim.substeps, cfg=cfg,
                              distance_weight=float(settings.distance_weight),
                              chamfer_weight=float(settings.chamfer_weight),
                              resample=sim.resample, fracture=sim.fracture,
                              observed=tuple(int(i) for i in self.observed))
        dt = sim.dtype
        self._times = jnp.asarray(sim.plan.frame_times, dt)
        self._dts = jnp.asarray(sim.plan.frame_dts, dt)
        self._base = base.astype(dt)
        self.jacobian_threads = JACOBIAN_THREADS
        self._columns_compiled = False

    def _args(self):
        return (self.static, self._base, self.sim.state0, self.scene, self._times, self._dts)

    def residual(self, z) -> jax.Array:
        """Residual vector r(z), (n,), dimensionless (see `silhouette.residuals`)."""
        return _residual_jit(jnp.asarray(z, self.sim.dtype), *self._args(), self.target)

    def residual_and_jacobian(self, z):
        """(r (n,), dr/dz (n, p)) by forward mode (one jvp rollout per fitted parameter).

        On the CPU backend the columns run in JACOBIAN_THREADS concurrent groups of equal size (the last
        padded with zero directions, whose columns are dropped), so one compiled program serves every
        group; the first call compiles it on this thread before any other starts."""
        z = jnp.asarray(z, self.sim.dtype)
        p = z.shape[0]
        k = min(int(self.jacobian_threads), p) if jax.default_backend() == "cpu" else 1
        if k <= 1:
            return _residual_and_jacobian(z, *self._args(), self.target)
        rows = -(-p // k)
        eye = np.eye(rows * k, p, dtype=np.dtype(self.sim.dtype))  # rows beyond p are zero directions
        groups = [jnp.asarray(eye[i * rows:(i + 1) * rows]) for i in range(k)]
        run = lambda basis: jax.block_until_ready(
            _residual_and_columns(z, basis, *self._args(), self.target))
        first = None
        if not self._columns_compiled:  # compile on this thread, then run the other groups concurrently
            first = run(groups[0])
            self._columns_compiled = True
        with concurrent.futures.ThreadPoolExecutor(k - 1) as pool:
            later = [pool.submit(run, g) for g in groups[1:]]
            out = [run(groups[0]) if first is None else first] + [f.result() for f in later]
        cols = jnp.concatenate([c for _, c in out])[:p]
        return out[0][0], cols.T

    def loss(self, z) -> float:
        r = np.asarray(self.residual(z))
        return 0.5 * float(r @ r)

    def simulate(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Particle positions (F, N, d) m and active flags (F, N) at the residual's frames for physical
        parameter values `theta` (dict or (p,) in `transform.names` order)."""
        z = self.transform.to_unconstrained(theta)
        x, active, health = _positions(jnp.asarray(z, self.sim.dtype), *self._args())
        self.sim.check({"x": x}, health)
        return np.asarray(x)[self.observed], np.asarray(active)[self.observed]

    def render(self, theta) -> np.ndarray:
        """Soft silhouettes (F, H, W) in [0, 1) at the observation level for parameters `theta`."""
        x, active = self.simulate(theta)
        return np.asarray(render_frames(jnp.asarray(x), jnp.asarray(active), self.cfg))

    def params_of(self, z) -> dict:
        """Every material parameter (name -> float) at fitted coordinates z."""
        theta = np.asarray(self.transform.to_physical(jnp.asarray(z)))
        out = {n: float(getattr(self.base, n)) for n in FIT_FIELDS + KNOWN_INPUTS}
        out.update({n: float(theta[i]) for i, n in enumerate(self.transform.names)})
        return out

    def pixel_images(self, r) -> np.ndarray:
        """The weighted pixel residual images (F, H, W) inside a residual vector r."""
        F = len(self.frames)
        H, W = self.cfg.shape
        return np.asarray(r).reshape(F, -1)[:, :H * W].reshape(F, H, W)


def _data_fingerprint(data: Silhouettes) -> str:
    """A short hash of what the fit sees (masks, weights, times, camera, scene): a fit log made from
    other data is refused on resume."""
    h = hashlib.sha256()
    for a in (data.masks, data.weights, data.times):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps(data.camera.as_dict(), sort_keys=True).encode())
    h.update(data.scene_json.encode())
    return h.hexdigest()[:16]


def choose_pixel_level(pixel_size: float, spacing: float, image_shape) -> int:
    """The coarsest pyramid level whose pixels (pixel_size 2^l, m) are not larger than the particle
    spacing (m), keeping at least 8 pixels across the image."""
    level = 0
    while (pixel_size * 2 ** (level + 1) <= spacing * (1 + 1e-9)
           and min(image_shape) / 2 ** (level + 1) >= 8):
        level += 1
    return level


def max_pixel_level(image_shape) -> int:
    """The coarsest pyramid level that keeps at least MIN_LEVEL_PIXELS pixels across the image."""
    return max(0, int(math.floor(math.log2(max(1, min(image_shape)) / MIN_LEVEL_PIXELS))))


def check_fit_data(data: Silhouettes, scene: Scene, used) -> None:
    """Refuse data a fit cannot use: a camera whose pixels are larger than the domain (a units slip), masks
    with no foam, or foam in every pixel, in every used frame (pixels of weight > 0)."""
    p = data.camera.pixel_size
    span = min(scene.domain_max[k] - scene.domain_min[k] for k in range(2))
    if span / p < MIN_DOMAIN_PIXELS:
        raise CalibrationError(f"camera.pixel_size = {p:g} m: the scene domain ({span:g} m across) spans "
                               f"{span / p:.3g} pixels, fewer than {MIN_DOMAIN_PIXELS}; the pixel size is in m "
                               f"per pixel (not mm or um)")
    seen = data.weights[used] > 0
    foam = data.masks[used].astype(bool) & seen
    if not foam.any():
        raise CalibrationError(f"masks: no foam pixel (of weight > 0) in any of the {len(used)} used frame(s); "
                               f"nothing to fit (check the tracking threshold or --time-window)")
    if np.array_equal(foam, seen):
        raise CalibrationError(f"masks: every pixel of weight > 0 is foam in every used frame; the silhouette has "
                               f"no boundary to fit (check the tracking threshold or the camera)")


def build_problem(data: Silhouettes, settings: FitSettings | None = None, *,
                  max_particles: int = DEFAULT_MAX_PARTICLES,
                  max_substeps: int = DEFAULT_MAX_SUBSTEPS) -> CalibrationProblem:
    """Bind a dataset to a simulator at the fit's dx, a renderer and a parameter transform.

    Args:
      data: the observations (`jaxfoam.io.read_silhouettes`).
      settings: `FitSettings` (default: all defaults).
      max_particles, max_substeps: budgets of one rollout (BudgetError, checked before it is bound).
    Returns a `CalibrationProblem`. Raises CalibrationError for unusable settings or data (no frame
    after the start of the simulation, an empty first mask, masks without foam or a boundary).
    """
    settings = (settings or FitSettings()).validate()
    dtype = jnp.float64 if settings.dtype == "float64" else jnp.float32
    scene: Scene = data.load_scene(dtype=dtype)
    d = scene.dim
    extent = float(np.max(np.asarray(scene.domain_max) - np.asarray(scene.domain_min)))
    dx = extent / FIT_CELLS[d] if settings.dx is None else float(settings.dx)
    ppc = FIT_PPC[d] if settings.ppc is None else int(settings.ppc)
    fixed = dict(settings.fixed)
    kappa = float(fixed.get("kappa", scene.kappa))
    rho = float(fixed.get("rho", scene.density))
    fitted = settings.fitted
    bounds = {n: settings.bounds_of(n) for n in fitted}
    transform = fit_transform(settings)

    # The time step is that of the stiffest admissible material (mu at its upper bound, or fixed), so
    # every rollout of the fit is stable with one substep count.
    mu_ref = float(fixed["mu"]) if "mu" in fixed else bounds["mu"][1]
    mid = {n: float(np.sqrt(np.prod(settings.bounds_of(n)))) for n in FIT_FIELDS}
    ref = Params(mu=mu_ref, kappa=kappa, sigma_y=float(fixed.get("sigma_y", mid["sigma_y"])),
                 eta=float(fixed.get("eta", mid["eta"])), m=float(fixed.get("m", 0.5 * sum(settings.bounds_of("m")))),
                 rho=rho).validate()
    base = ref.replace(mu=float(fixed.get("mu", mu_ref)))

    times = np.asarray(data.times, float)
    first_mask = scene.initial_shape["type"] == "first_mask"
    if settings.pixel_level is not None and settings.pixel_level > max_pixel_level(data.image_shape):
        raise CalibrationError(f"pixel_level must be in [0, {max_pixel_level(data.image_shape)}] for "
                               f"{data.image_shape[0]}x{data.image_shape[1]} pixel images (each level halves them; "
                               f"at least {MIN_LEVEL_PIXELS} pixels across), got {settings.pixel_level}")
    check_dtype_range(dict(mu=base.mu, kappa=kappa, sigma_y=base.sigma_y, eta=base.eta, m=base.m, rho=rho),
                      settings.dtype)
    estimate = estimate_particles(scene, dx, ppc)
    if estimate is not None:
        check_particles(estimate, d, jnp.dtype(dtype).itemsize, max_particles, dx=dx, ppc=ppc)
    try:
        state0 = init_state(scene, dx, ppc, rho=rho, seed=settings.seed,
                            first_mask=data.first_mask if first_mask else None, dtype=dtype)
    except ValueError as exc:
        raise CalibrationError(f"initial shape: {exc}") from exc
    # With a first_mask shape the material is known at the first frame's time: start there.
    t0 = float(times[0]) if first_mask else 0.0
    state0 = state0.replace(t=jnp.asarray(t0, dtype))
    used = np.nonzero(times > t0 + 1e-12)[0]
    if len(used) == 0:
        raise CalibrationError(f"times: no frame after the start of the simulation (t0 = {t0} s); the fit needs "
                               f"at least one frame after the initial shape")
    if settings.time_window is not None:
        lo, hi = (float(v) for v in settings.time_window)
        used = used[(times[used] >= lo) & (times[used] <= hi)]
        if len(used) == 0:
            raise CalibrationError(f"time_window: no frame after the start (t0 = {t0} s) lies in [{lo}, {hi}] s; "
                                   f"the data's frames are at {np.round(times, 4).tolist()} s")
    # Resampling needs free slots: the Simulator grows state0 to resample.capacity_factor times its
    # sampled count (inactive slots are neither simulated nor rendered).
    check_fit_data(data, scene, used)
    check_particles(int(np.sum(state0.active)), d, jnp.dtype(dtype).itemsize, max_particles, dx=dx, ppc=ppc)
    resample = settings.resample_for(d, ppc)
    fracture = settings.fracture_for(d)
    sim_times, observed = simulation_frames(t0, times[used])
    per_frame = substeps_per_frame(scene, ref, dx, FIT_CFL, sim_times, t0)
    check_substeps(per_frame, len(sim_times), max_substeps, span=float(sim_times[-1]) - t0,
                   dt=float(np.max(np.diff(np.concatenate([[t0], sim_times])))) / per_frame,
                   times_option="the data's times")
    sim = Simulator(scene, sim_times, ref, dx, ppc, dtype=dtype, state0=state0, cfl=FIT_CFL,
                    resample=resample, fracture=fracture)

    spacing = particle_spacing(dx, ppc, d)
    level = (choose_pixel_level(data.camera.pixel_size, spacing, data.image_shape) if settings.pixel_level is None
             else int(settings.pixel_level))
    masks, weights, camera = pyramid(without_plate_pixels(data, scene), level + 1)[level]
    masks, weights = masks[used], weights[used]
    if not np.any(weights > 0):
        raise CalibrationError("weights: every pixel of the used frames has weight 0; nothing to fit")
    cfg = make_render_config(camera, masks.shape[1:], dx, ppc, d)
    target = make_target(masks, weights, camera, dtype=dtype)
    return CalibrationProblem(data, settings, sim, transform, base, used, level, masks, weights, camera, cfg, target,
                              observed)


# ----------------------------------------------------------------------------------------------
# Uncertainty
# ----------------------------------------------------------------------------------------------

def correlation_area(images: np.ndarray, window: int) -> float:
    """Effective area, in pixels, over which residual pixels are correlated.

    The residual images (F, H, W) are pooled into one autocovariance C(lag) (zero-padded FFT); the
    area is the sum of the positive part of C(lag) / C(0) over lags |lag_x|, |lag_y| <= window (the
    reach of the rendering kernel: a soft silhouette cannot vary on shorter scales, so pixels within
    it share their errors). At least 1 (independent pixels). 1 for an all-zero residual.
    """
    imgs = np.asarray(images, np.float64)
    F, H, W = imgs.shape
    shape = (2 * H, 2 * W)
    spec = np.fft.rfft2(imgs, s=shape)
    acov = np.fft.irfft2(np.sum(np.abs(spec) ** 2, axis=0), s=shape)
    c0 = acov[0, 0]
    if not c0 > 0:
        return 1.0
    w = int(max(0, window))
    rows = np.r_[0:min(w + 1, H), shape[0] - np.arange(1, min(w, H - 1) + 1)]
    cols = np.r_[0:min(w + 1, W), shape[1] - np.arange(1, min(w, W - 1) + 1)]
    block = acov[np.ix_(rows, cols)] / c0
    return max(1.0, float(np.sum(np.maximum(block, 0.0))))


def without_plate_pixels(data: Silhouettes, scene) -> Silhouettes:
    """The data with weight 0 wherever a plate of the scene covers a pixel at that frame's time.

    A plate is solid in the image plane: foam seen there in a video lies in front of or behind it (3D) or
    is not there at all (2D), while the simulation holds foam inside a sticky plate, the layer it grips
    (and `Silhouettes.first_mask` continues hanging foam into it). The fit compares neither. `jaxfoam
    synth` and `jaxfoam track` already write weight 0 there; files from elsewhere may not.
    """
    if not scene.plates:
        return data
    keep = np.stack([~plate_footprint(scene, float(t), data.camera, data.image_shape) for t in data.times])
    if np.all(data.weights[~keep] == 0):
        return data
    return dataclasses.replace(data, weights=(data.weights * keep).astype(np.float32))


def fit_uncertainty(problem: CalibrationProblem, z, r=None, J=None, level: float = DEFAULT_LEVEL):
    """Gauss-Newton uncertainty at fitted coordinates z: (`fitting.Uncertainty`, n_eff).

    Rows whose residual and Jacobian are exactly zero (pixels no simulated particle reaches and the data
    leave empty) are dropped; the remaining n residuals count as n / A independent ones, A the
    `correlation_area` of the pixel residuals.
    """
    if r is None or J is None:
        r, J = problem.residual_and_jacobian(z)
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return None, float("nan")
    keep = (r != 0) | np.any(J != 0, axis=1)
    n = int(keep.sum())
    p = J.shape[1]
    window = int(math.ceil(BSPLINE_SUPPORT * problem.cfg.kernel_width / problem.cfg.pixel_size *
                           CORRELATION_WINDOW_SUPPORTS))
    area = correlation_area(problem.pixel_images(r), window)
    n_eff = min(float(n), max(n / area, p + 1.0))
    if n <= p:
        return None, float("nan")
    unc = fitting.gauss_newton_uncertainty(r[keep], J[keep], np.asarray(z, np.float64), problem.transform,
                                           n_eff=n_eff, level=level)
    return unc, n_eff


def discretization_error(problem: CalibrationProblem, z, J, ratio: float = DX_CHECK_RATIO, details=None, r=None,
                         refit: int = 0, progress: Callable[[str], None] | None = None):
    """The numerical error of an estimate z due to the fit's grid: (error_z (p,) >= 0, shift_z (p,)).

    The residual and its Jacobian at z are evaluated once more with grid spacing `ratio` dx (same
    observations, pixel level and seed). How far the estimate moves from dx to ratio dx is estimated to
    first order in two ways (`DX_CHECK_JACOBIAN`):
      * with the fit grid's Jacobian: -(Jp^T Jp)^+ Jp^T (rp_other - rp) over the pixel rows (the rows both
        grids share; Jp the pixel rows of J at dx);
      * with each grid's own: the difference of the two grids' Gauss-Newton steps from z,
        d = -(J^T J)^+ J^T r over all rows of that grid's residual, d_other - d.
    They agree where the residual is linear over the move; where they do not, the linearization is not
    to be trusted, and the check takes, per parameter, the larger move (shift_z: that one, with its sign).
    With refit > 0 a third, measured, move enters: that of `refit` Levenberg-Marquardt iterations on the
    finer grid from z (the fit's tolerances; the first reuses the residual and Jacobian computed there for
    the estimates). It includes what the fit had left to gain on its own grid, so it errs on the wide side.
    With theta(h) = theta_0 + C h^q (q = DX_CHECK_ORDER) the estimate at dx is off the continuum one by
    |shift| / |ratio^q - 1|; error_z is that times GCI_SAFETY. Returns infinite errors when the other
    grid's residual or Jacobian is not finite. r: the residual at z on the fit's grid, if at hand.
    details: a dict that receives "frame_change" (F,), the norm of each used frame's pixel-residual change
    between the two grids, and "shift_fit_jacobian", "shift_own_jacobians" (p,), the two estimates; with
    refit also "shift_refit" (p,), "refit_iterations", "refit_reason" and "refit_loss" (start, end).
    progress: callable(str) receiving one line per refit iteration, or None.
    """
    settings = dataclasses.replace(problem.settings, dx=problem.dx * ratio, pixel_level=problem.pixel_level)
    other = build_problem(problem.data, settings)
    p = np.shape(J)[1]
    at_z = {}
    with_fit, with_own, frame_change = predicted_move(problem, other, z, J, r, other_at_z=at_z)
    if details is not None:
        details["frame_change"] = frame_change
    if with_fit is None:
        return np.full(p, np.inf), np.full(p, np.nan)
    if details is not None:
        details["shift_fit_jacobian"], details["shift_own_jacobians"] = with_fit, with_own
    moves = [with_fit, with_own]
    if refit:
        measured = refit_move(other, z, int(refit), at_z=(at_z["r"], at_z["J"]), progress=progress)
        if details is not None:
            details.update(shift_refit=measured["move"], refit_iterations=measured["iterations"],
                           refit_reason=measured["reason"], refit_loss=measured["loss"])
        if not np.all(np.isfinite(measured["move"])):
            return np.full(p, np.inf), np.full(p, np.nan)
        moves.append(measured["move"])
    return check_error(moves, ratio)


def check_error(moves, ratio: float = DX_CHECK_RATIO):
    """The discretization check's (error_z (p,), shift_z (p,)) from its moves between dx and ratio dx (k, p),
    fitted coordinates: per parameter the largest move (with its sign), extrapolated to the continuum at
    order DX_CHECK_ORDER and times GCI_SAFETY."""
    moves = np.asarray(moves, np.float64)
    shift = moves[np.argmax(np.abs(moves), axis=0), np.arange(moves.shape[1])]
    return GCI_SAFETY * np.abs(shift) / abs(ratio ** DX_CHECK_ORDER - 1.0), shift


def numerical_half_width(transform: fitting.ParameterTransform, z, error_z) -> np.ndarray:
    """The numerical error error_z (half-widths in fitted coordinates around z) as half-widths in physical
    units, (p,): half the distance between theta(z - error_z) and theta(z + error_z) (the maps are not linear)."""
    z, e = np.asarray(z, np.float64), np.asarray(error_z, np.float64)
    up = np.asarray(transform.to_physical(jnp.asarray(z + e)))
    down = np.asarray(transform.to_physical(jnp.asarray(z - e)))
    return 0.5 * np.abs(up - down)


def refit_move(other: CalibrationProblem, z, iterations: int, at_z=None,
               progress: Callable[[str], None] | None = None) -> dict:
    """How far `iterations` Levenberg-Marquardt iterations on `other` (another discretization of the same
    data) move the estimate from z (fitted coordinates): dict(move (p,), iterations, reason, loss (start,
    end)). at_z: (r, J) of `other` at z if already computed (spares the first evaluation)."""
    z = np.asarray(z, np.float64)
    start = None if at_z is None else tuple(np.asarray(a) for a in at_z)

    def evaluate(x):
        if start is not None and np.array_equal(np.asarray(x, np.float64), z):
            return start
        return other.residual_and_jacobian(x)

    def said(info: fitting.IterationInfo):
        if progress is not None:
            progress(f"[dx check refit] iter {info.iteration:>3}  loss {info.loss:.6g}  "
                     f"{_format_params(other.params_of(info.x), other.transform.names)}  ({info.time:.1f} s)")

    sol = fitting.least_squares(evaluate, z, fitting.LevenbergMarquardt(), with_jac=True, max_iterations=iterations,
                                ftol=FTOL, xtol=XTOL, callback=said)
    losses = np.asarray(sol.history.loss, np.float64)
    return dict(move=np.asarray(sol.x, np.float64) - z, iterations=int(sol.iterations), reason=sol.reason.value,
                loss=(float(losses[0]) if len(losses) else math.nan, float(sol.loss)))


def predicted_move(problem: CalibrationProblem, other: CalibrationProblem, z, J, r=None, other_at_z=None):
    """First-order estimates of how far the estimate z moves from `problem`'s discretization to `other`'s
    (the same observations and pixel level; another grid): (with the fit grid's Jacobian, with each grid's
    own, per-frame norm of the pixel-residual change (F,)), the first two (p,) in fitted coordinates, or
    None where a residual or Jacobian is not finite (`discretization_error` has the two formulas). J, r:
    the Jacobian and residual at z on `problem`'s grid (r computed if None). other_at_z: a dict that
    receives "r" and "J", `other`'s residual and Jacobian at z."""
    F = len(problem.frames)
    npix = problem.cfg.height * problem.cfg.width
    J = np.asarray(J, np.float64)
    p = J.shape[1]
    r = np.asarray(problem.residual(z) if r is None else r, np.float64)
    ro, Jo = (np.asarray(a, np.float64) for a in other.residual_and_jacobian(z))
    if other_at_z is not None:
        other_at_z.update(r=ro, J=Jo)
    rp, rc = r.reshape(F, -1)[:, :npix], ro.reshape(F, -1)[:, :npix]
    frame_change = np.sqrt(np.sum(np.square(rc - rp), axis=1))
    if not all(np.all(np.isfinite(a)) for a in (ro, Jo, r, J)):
        return None, None, frame_change
    Jp = J.reshape(F, -1, p)[:, :npix].reshape(-1, p)
    with_fit = np.linalg.lstsq(Jp, -(rc - rp).ravel(), rcond=None)[0]
    with_own = np.linalg.lstsq(Jo, -ro, rcond=None)[0] - np.linalg.lstsq(J, -r, rcond=None)[0]
    return with_fit, with_own, frame_change


# A frame whose pixel residual changes between dx and DX_CHECK_RATIO dx by more than this times the median
# frame's is one the fit grid resolves worse than the others. Set from the recovery study at 1 cm (frames of
# fits that recovered mu within 10%: 0.8-1.2x; the squeeze's lift 1.6-1.9x, the hanging foam's tear-off
# 1.5-3.7x). It only selects frames for a note; it changes no result.
UNEVEN_FRAME_RATIO = 1.5


def uneven_frames_note(times, change, dx: float) -> str | None:
    """A note naming the frames (times s) whose residual change between the two grids of the
    discretization check (`change`, per frame) exceeds UNEVEN_FRAME_RATIO times the median frame's, with a
    suggested --time-window when they are the last frames; None when no frame does."""
    change = np.asarray(change, np.float64)
    if change.size < 3 or not np.all(np.isfinite(change)):
        return None
    med = float(np.median(change))
    if not med > 0:
        return None
    ratio = change / med
    bad = np.nonzero(ratio > UNEVEN_FRAME_RATIO)[0]
    if len(bad) == 0:
        return None
    at = ", ".join(f"{times[i]:.3g}" for i in bad)
    note = (f"The dx = {dx:.3g} m grid resolves some frames worse than the rest: between dx and "
            f"{DX_CHECK_RATIO:.3g} dx the residual of the frames at t = {at} s changes {ratio[bad].min():.2g}-"
            f"{ratio[bad].max():.2g}x as much as the median frame's. If the foam stretches, tears or spreads over a "
            f"rough floor there, the grid biases the parameters through them")
    first = int(bad[0])
    if first > 0 and list(bad) == list(range(first, len(change))):
        note += f"; a fit without them (--time-window 0:{times[first - 1]:.4g}) is less biased by it"
    return note + " (docs/calibrate.md)."


def combine_intervals(unc: fitting.Uncertainty, error_z, transform: fitting.ParameterTransform) -> np.ndarray:
    """(p, 2) physical intervals whose half-width in fitted coordinates is the statistical half-width
    and the numerical error combined in quadrature."""
    z = np.asarray(unc.z, np.float64)
    half_stat = 0.5 * (unc.interval_z[:, 1] - unc.interval_z[:, 0])
    half = np.sqrt(np.square(half_stat) + np.square(np.asarray(error_z, np.float64)))
    with np.errstate(invalid="ignore"):
        ends = np.stack([np.asarray(transform.to_physical(z - half)), np.asarray(transform.to_physical(z + half))], 1)
    return np.sort(ends, axis=1)


# ----------------------------------------------------------------------------------------------
# The fit
# ----------------------------------------------------------------------------------------------

def judge_reported_intervals(interval: dict, params: dict, transform, identifiable: dict):
    """Identifiability judged again on the reported intervals (statistical and numerical combined).

    A parameter is not identifiable when its interval is wider than DEFAULT_MAX_RELATIVE_WIDTH times
    its value, covers at least BOUND_SPAN_FRACTION of its bounds, or is unbounded. Args: interval
    name -> (lo, hi) and params name -> value in physical units; transform the fit's
    `fitting.ParameterTransform` (its names and bounds); identifiable name -> bool from the
    statistical check. Returns (updated identifiable dict, list of notes for the changed ones).
    """
    out, notes = dict(identifiable), []
    for i, n in enumerate(transform.names):
        lo, hi = interval[n]
        value = float(params[n])
        span = float(transform.upper[i]) - float(transform.lower[i])
        wide = (hi - lo) > DEFAULT_MAX_RELATIVE_WIDTH * max(abs(value), np.finfo(np.float64).tiny)
        fills = math.isfinite(span) and (hi - lo) >= BOUND_SPAN_FRACTION * span
        if out.get(n, False) and (wide or fills or not (math.isfinite(lo) and math.isfinite(hi))):
            out[n] = False
            why = (f"covers {100 * (hi - lo) / span:.0f}% of its bounds [{transform.lower[i]:.4g}, "
                   f"{transform.upper[i]:.4g}]" if fills
                   else f"is wider than {DEFAULT_MAX_RELATIVE_WIDTH:g} times its value {value:.4g}")
            notes.append(f"{n} is not identifiable from these data: its reported interval [{lo:.4g}, {hi:.4g}] "
                         f"(statistical and numerical error combined) {why}.")
    return out, notes


def make_optimizer(name: str):
    """The `fitting` optimizer for "lm", "lbfgs" or "adam"."""
    if name == "lm":
        return fitting.LevenbergMarquardt()
    if name == "lbfgs":
        return fitting.LBFGS()
    if name == "adam":
        return fitting.Adam(learning_rate=ADAM_LEARNING_RATE, decay_steps=ADAM_DECAY)
    raise CalibrationError(f"optimizer must be one of {OPTIMIZERS}, got {name!r}")


def fit_transform(settings: FitSettings) -> fitting.ParameterTransform:
    """The fitted coordinates of a fit: log for the positive parameters, bounded for all, within the
    settings' bounds."""
    fitted = settings.fitted
    return fitting.ParameterTransform.create(fitted, positive=[n for n in fitted if n != "m"],
                                             bounds={n: settings.bounds_of(n) for n in fitted})


def make_starts(transform: fitting.ParameterTransform, settings: FitSettings):
    """Initial guesses (S, p) in fitted coordinates and their unit-cube design (S, p): the centre of the
    starting ranges (log-centre for log parameters), with `settings.initial`'s values in place of the
    centre's, then S - 1 seeded Latin-hypercube points. The unit design of the first start is 0.5, and NaN
    (not drawn from the design) for a parameter set by `initial`."""
    ranges = {n: settings.start_range_of(n) for n in transform.names}
    first = np.array(transform.from_unit(np.full((1, transform.size), 0.5), ranges)[0], np.float64)
    unit0 = np.full(transform.size, 0.5)
    for i, n in enumerate(transform.names):
        if settings.initial and n in settings.initial:
            # a value on a bound (a fit that ended there) starts just inside it: the transform is open there
            lo, hi = settings.bounds_of(n)
            first[i] = min(max(float(settings.initial[n]), lo + 1e-9 * (hi - lo)), hi - 1e-9 * (hi - lo))
            unit0[i] = math.nan
    z = [np.asarray(transform.to_unconstrained(first))]
    unit = [unit0]
    if settings.starts > 1:
        zl, ul = fitting.lhs_starts(transform, settings.starts - 1, settings.seed, sample_bounds=ranges)
        z.extend(list(zl))
        unit.extend(list(ul))
    return np.stack(z), np.stack(unit)


def default_log_path(out) -> Path:
    """The fit log beside a fit.json: fit.json -> fit.fitlog.h5."""
    out = Path(out)
    return out.with_name(out.stem + ".fitlog.h5")


def _format_params(d: dict, names) -> str:
    return "  ".join(f"{n}={d[n]:.4g}" for n in names)


def _path_settings(settings: FitSettings) -> dict:
    """The settings the optimizer's path depends on (not the uncertainty options, nor the iteration
    and time budgets, which a resumed fit may extend), as JSON values."""
    return json.loads(json.dumps({k: v for k, v in settings.to_dict().items()
                                  if k not in ("dx_check", "dx_refit", "level", "max_iter", "time_budget")}))


def _same_fit(logged: dict, fingerprint: dict) -> bool:
    """Whether a fit log's fingerprint (data, path settings, dx) is this fit's. A setting that did not
    exist when the log was written matches when this fit leaves it at its default, which is the
    behaviour the log's version had (e.g. `resample` and `fracture`, off)."""
    current = json.loads(json.dumps(fingerprint))
    defaults = _path_settings(FitSettings())
    settings = dict(logged.get("settings", {}))
    for key, value in current["settings"].items():
        if key not in settings and value == defaults.get(key, object()):
            settings[key] = value
    return dict(logged, settings=settings) == current


def calibrate(data, settings: FitSettings | None = None, *, log=None, resume: bool = False,
              progress: Callable[[str], None] | None = None,
              callback: Callable[[fitting.IterationInfo, dict], None] | None = None,
              problem: CalibrationProblem | None = None) -> FitResult:
    """Fit mu, sigma_y, eta and m (those not fixed) to silhouette data.

    Args:
      data: a `Silhouettes` or the path of a silhouette file.
      settings: `FitSettings` (default: Levenberg-Marquardt, DEFAULT_STARTS starts, defaults for the rest).
      log: path of the HDF5 fit log (every iteration of every start); None for no log.
      resume: continue the fit recorded in `log` (same data and settings required): finished starts are
        read back, the interrupted one continues from its last iteration, later ones run.
      progress: callable(str) receiving one line per iteration (iteration, loss, parameters), or None.
      callback: callable(IterationInfo, params dict) after every iteration; an exception it raises stops
        the fit (the log stays resumable).
      problem: a prebuilt `build_problem(data, settings)` (reuses its simulator).
    Returns a `FitResult`.
    """
    wall0 = time.perf_counter()
    if not isinstance(data, Silhouettes):
        data = read_silhouettes(data)
    settings = (settings or FitSettings()).validate()
    say = progress or (lambda msg: None)
    if problem is None:
        problem = build_problem(data, settings)
    tr = problem.transform
    names = tr.names
    sim = problem.sim
    say(f"fit: {problem.scene.kind} {problem.scene.dim}D, dx = {problem.dx:.4g} m, "
        f"{int(np.sum(sim.state0.active))} particles, {len(problem.frames)} frames "
        f"(t = {problem.data.times[problem.frames[0]]:.4g}..{problem.data.times[problem.frames[-1]]:.4g} s"
        + (f"; {len(sim.plan.frame_times)} simulated, gaps filled" if len(sim.plan.frame_times) > len(problem.frames)
           else "") + f"), {sim.substeps} substeps/frame "
        f"of dt = {sim.dt:.3g} s, images {problem.cfg.height}x{problem.cfg.width} px at level "
        f"{problem.pixel_level} ({problem.cfg.pixel_size:.3g} m/px); fitting {', '.join(names)} with "
        f"{settings.optimizer}, {settings.starts} start(s)"
        + (f" within {settings.time_budget:.4g} s" if settings.time_budget is not None else "")
        + (f"; resampling every {sim.resample.every} substeps ({sim.state0.capacity} slots)" if sim.resample else "")
        + ("; fracture on" if sim.fracture else ""))

    starts, unit = make_starts(tr, settings)
    optimizer = make_optimizer(settings.optimizer)
    n_starts = len(starts)

    def evaluate(z):
        return problem.residual_and_jacobian(z)

    def on_iteration(info: fitting.IterationInfo):
        theta = problem.params_of(info.x)
        say(f"[start {info.run + 1}/{n_starts}] iter {info.iteration:>3}  loss {info.loss:.6g}  "
            f"{_format_params(theta, names)}  ({info.time:.1f} s)")
        if callback is not None:
            callback(info, theta)

    def solve(x0, **kw):
        return fitting.least_squares(evaluate, x0, optimizer, with_jac=True, max_iterations=settings.iterations,
                                     ftol=FTOL, xtol=XTOL, callback=on_iteration, **kw)

    # What the optimizer's path depends on (not the uncertainty options, nor the iteration budget, which a
    # resumed fit may extend): a log is resumed only with these.
    fit_settings = _path_settings(settings)
    fingerprint = dict(data=_data_fingerprint(data), settings=fit_settings, dx=problem.dx)
    fitlog = None
    if log is not None:
        fitlog = fitting.FitLog(log)
        logged = fitlog.file.attrs.get("calibration")
        if resume and logged is not None and not _same_fit(json.loads(logged), fingerprint):
            fitlog.close()
            raise CalibrationError(f"{log}: cannot resume: the log was written for other data or settings "
                                   f"(start afresh without --resume, or use another log)")
        fitlog.file.attrs["calibration"] = json.dumps(fingerprint)
        fitlog.flush()
    before = time.perf_counter() - wall0
    try:
        ms = fitting.multistart(solve, starts, log=fitlog, resume=resume, seed=settings.seed, unit=unit,
                                max_time=settings.time_budget)
    except OSError as exc:  # h5py's error for a log damaged on disk
        raise CalibrationError(f"{log}: the fit log cannot be read or written ({exc}); start afresh without "
                               f"--resume, or use another log") from exc
    finally:
        if fitlog is not None:
            fitlog.close()
    after0 = time.perf_counter()

    # The lowest loss of any iterate of any start: Adam accepts every finite step, so its last
    # iterate need not be its best one (LM and L-BFGS only accept decreases).
    # (A start the time budget left unrun has no iterate; the first start always has one.)
    lows = [float(np.min(s.history.loss)) if len(s.history.loss) else math.inf for s in ms.solutions]
    best_index = int(np.argmin(lows))
    best = ms.solutions[best_index]
    k_best = int(np.argmin(best.history.loss))
    if k_best == len(best.history.loss) - 1:
        z_best, loss_best = np.asarray(best.x), float(best.loss)
        r, J = best.residual, best.jacobian
    else:
        z_best, loss_best = np.asarray(best.history.x[k_best]), float(best.history.loss[k_best])
        r = J = None
        say(f"best iterate: start {best_index + 1}, iteration {k_best} (loss {loss_best:.6g}), not the last one")
    if r is None or J is None or not np.all(np.isfinite(np.asarray(r))):
        r, J = problem.residual_and_jacobian(z_best)
    unc, n_eff = fit_uncertainty(problem, z_best, r, J, level=settings.level)
    params = problem.params_of(z_best)
    p = len(names)
    numerical = {n: 0.0 for n in names}
    dx_check = None
    dx_refit = DEFAULT_DX_REFIT[problem.scene.dim] if settings.dx_refit is None else int(settings.dx_refit)
    if unc is not None:
        stat = {n: tuple(float(v) for v in unc.interval[i]) for i, n in enumerate(names)}
        interval = dict(stat)
        stderr = {n: float(unc.stderr_theta[i]) for i, n in enumerate(names)}
        corr = np.asarray(unc.correlation)
        identifiable = {n: n not in unc.non_identifiable for n in names}
        notes = list(unc.messages)
        if settings.dx_check:
            say(f"discretization check: the residual and Jacobian at the optimum with dx = {problem.dx * DX_CHECK_RATIO:.4g} m"
                + (f", then up to {dx_refit} LM iterations there" if dx_refit else ""))
            details = {}
            err_z, shift_z = discretization_error(problem, z_best, J, details=details, r=r, refit=dx_refit,
                                                  progress=say)
            change = details.get("frame_change")
            both = combine_intervals(unc, err_z, tr)
            half_stat = 0.5 * (unc.interval_z[:, 1] - unc.interval_z[:, 0])
            half_num = numerical_half_width(tr, z_best, err_z)
            for i, n in enumerate(names):
                numerical[n] = float(half_num[i])
                interval[n] = tuple(float(v) for v in both[i])
                if err_z[i] > half_stat[i]:
                    notes.append(f"{n}: the numerical error of the dx = {problem.dx:.3g} m grid (about "
                                 f"{numerical[n]:.3g}) exceeds the statistical uncertainty; a finer --dx narrows "
                                 f"the interval.")
            dx_check = dict(ratio=DX_CHECK_RATIO, order=DX_CHECK_ORDER, safety=GCI_SAFETY,
                            jacobian=DX_CHECK_JACOBIAN,
                            shift_z_fit_jacobian=[float(v) for v in details.get("shift_fit_jacobian", [math.nan] * p)],
                            shift_z_own_jacobians=[float(v) for v in details.get("shift_own_jacobians", [math.nan] * p)],
                            shift_z=[float(v) for v in shift_z], error_z=[float(v) for v in err_z],
                            refit=dx_refit,
                            shift_z_refit=([float(v) for v in details["shift_refit"]] if "shift_refit" in details
                                           else None),
                            refit_iterations=details.get("refit_iterations"), refit_reason=details.get("refit_reason"),
                            refit_loss=list(details["refit_loss"]) if "refit_loss" in details else None,
                            frame_change=None if change is None else [float(v) for v in change])
            uneven = None if change is None else uneven_frames_note(
                [float(data.times[i]) for i in problem.frames], change, problem.dx)
            if uneven:
                notes.append(uneven)
        identifiable, more = judge_reported_intervals(interval, params, tr, identifiable)
        notes.extend(more)
        notes = tuple(notes)
    else:
        stat = interval = {n: (-math.inf, math.inf) for n in names}
        stderr = {n: math.nan for n in names}
        corr = np.full((p, p), np.nan)
        identifiable = {n: False for n in names}
        notes = ("The residual or its Jacobian is not finite at the optimum: no uncertainty could be computed.",)
    runs = []
    for i, s in enumerate(ms.solutions):
        runs.append(dict(start=problem.params_of(starts[i]), end=problem.params_of(s.x), loss=float(s.loss),
                         reason=s.reason.value, iterations=int(s.iterations), evaluations=int(s.evaluations),
                         wall_time=float(s.wall_time)))
    stopped = [i + 1 for i, s in enumerate(ms.solutions) if s.reason == fitting.Reason.MAX_TIME and len(s.history.loss)]
    unstarted = [i + 1 for i, s in enumerate(ms.solutions) if s.reason == fitting.Reason.MAX_TIME
                 and not len(s.history.loss)]
    if stopped or unstarted:
        said = []
        if stopped:
            said.append(f"stopped start(s) {', '.join(map(str, stopped))} before convergence")
        if unstarted:
            said.append(f"left start(s) {', '.join(map(str, unstarted))} unrun")
        notes = tuple(notes) + (f"The time budget ({settings.time_budget:.4g} s) {' and '.join(said)}: the result is "
                                f"the best point found so far. Continue with --resume (the fit log keeps every "
                                f"iteration) and a new or no budget.",)
    settings_out = dict(settings.to_dict(), dx=problem.dx, ppc=FIT_PPC[problem.scene.dim]
                        if settings.ppc is None else int(settings.ppc),
                        dx_refit=dx_refit,
                        pixel_level=problem.pixel_level, pixel_size_fit=problem.cfg.pixel_size,
                        substeps_per_frame=sim.substeps, dt=sim.dt, fitted=list(names),
                        transforms=dict(zip(names, tr.kinds)), log=None if log is None else os.fspath(log),
                        dx_check=dx_check,
                        # the configs as the rollouts used them (resample's ppc resolved to the fit's)
                        resample=None if sim.resample is None else dataclasses.asdict(sim.resample),
                        fracture=None if sim.fracture is None else dataclasses.asdict(sim.fracture),
                        capacity=int(sim.state0.capacity))
    T, H, W = data.shape
    data_out = dict(frames=T, height=H, width=W, pixel_size=data.camera.pixel_size,
                    times=[float(t) for t in data.times], frames_used=[int(i) for i in problem.frames],
                    scene_kind=problem.scene.kind, dim=problem.scene.dim, source=data.source)
    result = FitResult(params=params, fitted=names, interval=interval, interval_statistical=stat,
                     numerical_error=numerical, stderr=stderr, correlation=corr,
                     identifiable=identifiable, notes=notes, loss=loss_best,
                     loss_history=np.asarray(best.history.loss), time_history=np.asarray(best.history.time),
                     runs=runs, best_run=best_index, best_iteration=k_best, reason=best.reason.value,
                     iterations=int(best.iterations), evaluations=int(best.evaluations), settings=settings_out,
                     data=data_out, n_effective=float(n_eff),
                     wall_time=before + sum(s.wall_time for s in ms.solutions) + time.perf_counter() - after0,
                     uncertainty=unc, residual=np.asarray(r))
    return _with_goodness_of_fit(problem, result)


def silhouette_mismatch(occupancy, masks, weights, pixel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, how far a simulated silhouette is from an observed one, over pixels of weight > 0.

    Args: occupancy (F, H, W) soft occupancy (inside where >= 1/2; NaN counts as outside), masks
    (F, H, W) observed (inside where >= 1/2), weights (F, H, W), pixel_size m.
    Returns (iou (F,), boundary (F,) m): the intersection over union (1 when both are empty), and the
    mean boundary displacement, the area of the symmetric difference over the observed perimeter (a
    band of width b along the boundary has area b x perimeter); the perimeter counts observed pixels
    with a 4-neighbour outside the mask, times pixel_size (that of the simulated silhouette when nothing
    is observed; 0 when both are empty).
    """
    occ = np.nan_to_num(np.asarray(occupancy, np.float64), nan=0.0)
    w = np.asarray(weights) > 0
    sim = (occ >= 0.5) & w
    obs = (np.asarray(masks, np.float64) >= 0.5) & w
    inter = np.sum(sim & obs, axis=(1, 2))
    union = np.sum(sim | obs, axis=(1, 2))
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)

    def perimeter(a):
        p = np.pad(a, ((0, 0), (1, 1), (1, 1)))
        inner = p[:, :-2, 1:-1] & p[:, 2:, 1:-1] & p[:, 1:-1, :-2] & p[:, 1:-1, 2:]
        return np.sum(a & ~inner, axis=(1, 2))

    per = np.where(obs.any(axis=(1, 2)), perimeter(obs), perimeter(sim)) * pixel_size
    diff = np.sum(sim ^ obs, axis=(1, 2)) * pixel_size ** 2
    boundary = np.where(diff > 0, diff / np.maximum(per, pixel_size), 0.0)
    return iou, boundary


def _with_goodness_of_fit(problem: CalibrationProblem, result: FitResult) -> FitResult:
    """The result with its per-frame silhouette IoU (read back from the stored residual, no rollout)
    and, when a frame is not reproduced, a note saying so and what to try."""
    iou, boundary = silhouette_mismatch(fitted_occupancy(problem, result), problem.masks, problem.weights,
                                        problem.cfg.pixel_size)
    notes = list(result.notes)
    ppc = FIT_PPC[problem.scene.dim] if problem.settings.ppc is None else int(problem.settings.ppc)
    limit = FRAME_BOUNDARY_SPACINGS * particle_spacing(problem.dx, ppc, problem.scene.dim)
    bad = np.nonzero(boundary > limit)[0]
    interval, identifiable = dict(result.interval), dict(result.identifiable)
    if len(bad):
        times = np.asarray(problem.data.times)[np.asarray(problem.frames)]
        k = int(np.argmax(boundary))
        tr = problem.transform
        interval = {n: (float(tr.lower[i]), float(tr.upper[i])) for i, n in enumerate(tr.names)}
        identifiable = {n: False for n in identifiable}
        notes.append(f"the fitted simulation does not reproduce {len(bad)} of {len(iou)} frames (silhouette boundaries "
                     f"more than {FRAME_BOUNDARY_SPACINGS:g} particle spacing = {limit:.3g} m apart on average; worst "
                     f"{boundary[k]:.3g} m, IoU {iou[k]:.2f}, at t = {times[k]:.4g} s). The intervals computed at this "
                     f"optimum assume a fit that reproduces the data, so each reported interval is the parameter's "
                     f"bounds and no parameter is reported identifiable (the interval at the optimum is kept as "
                     f"interval_local). Likely a local minimum (more --starts, another --optimizer) or an event such "
                     f"as a tear-off or a contact that the dx = {problem.dx:.3g} m grid places differently from the "
                     f"data (finer --dx).")
    return dataclasses.replace(result, frame_iou=tuple(float(v) for v in iou),
                               frame_boundary_error=tuple(float(v) for v in boundary), frame_boundary_limit=limit,
                               notes=tuple(notes), interval=interval, identifiable=identifiable,
                               interval_local=dict(result.interval))


# ----------------------------------------------------------------------------------------------
# Pictures
# ----------------------------------------------------------------------------------------------

def plot_loss(result: FitResult, path) -> None:
    """Loss against iteration for every start (the best one bold), log scale; PNG at `path`."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=110)
    log = result.settings.get("log")
    histories = {}
    if log and os.path.exists(log):
        for i, run in fitting.read_fitlog(log)["runs"].items():
            histories[i] = np.asarray(run["loss"])
    if not histories:
        histories = {result.best_run: result.loss_history}
    for i, h in sorted(histories.items()):
        best = i == result.best_run
        ax.semilogy(np.arange(len(h)), np.maximum(h, 1e-300), "-o" if best else "-", lw=2 if best else 1,
                    ms=3, alpha=1 if best else 0.6, label=f"start {i + 1}" + (" (best)" if best else ""))
    ax.set_xlabel("iteration")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_ylabel("loss 0.5 |r|^2")
    ax.set_title(f"{result.settings['optimizer']} fit: loss per iteration")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def fitted_occupancy(problem: CalibrationProblem, result: FitResult) -> np.ndarray:
    """The simulated soft silhouettes (F, H, W) at the optimum, as the loss saw them.

    Read back from the stored residual (pixel residual = sqrt(w / sum w) (O - M) / sqrt(F)), so no
    rollout is needed; NaN where the weight is 0 (not compared). Falls back to a rollout without it.
    """
    if result.residual is None:
        return problem.render({n: result.params[n] for n in problem.transform.names})
    F = len(problem.frames)
    w = np.asarray(problem.weights, np.float64)
    scale = np.sqrt(w / np.maximum(w.sum(axis=(1, 2), keepdims=True), 1e-12)) / math.sqrt(F)
    img = problem.pixel_images(result.residual)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(w > 0, problem.masks + img / np.where(w > 0, scale, 1.0), np.nan)


def plot_overlay(problem: CalibrationProblem, result: FitResult, path, n_panels: int = 4) -> None:
    """Observed masks (grey) with the simulated silhouette at the fitted parameters (red contour at
    occupancy 1/2) for up to `n_panels` frames spread over the fit; weight-0 pixels hatched blue."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    occ = fitted_occupancy(problem, result)
    F = occ.shape[0]
    picks = np.unique(np.round(np.linspace(0, F - 1, min(n_panels, F))).astype(int))
    H, W = problem.cfg.shape
    extent = problem.camera.extent((H, W))
    fig, axes = plt.subplots(1, len(picks), figsize=(3.0 * len(picks), 3.2), dpi=110, squeeze=False)
    xc, yc = problem.camera.pixel_centers((H, W))
    for ax, k in zip(axes[0], picks):
        ax.imshow(problem.masks[k], cmap="Greys", vmin=0, vmax=1.6, extent=extent, origin="upper",
                  interpolation="nearest")
        hidden = np.ma.masked_where(problem.weights[k] > 0, np.ones((H, W)))
        ax.imshow(hidden, cmap="Blues", vmin=0, vmax=2, alpha=0.5, extent=extent, origin="upper",
                  interpolation="nearest")
        ax.contour(xc, yc, occ[k], levels=[0.5], colors="red", linewidths=1.2)
        t = problem.data.times[problem.frames[k]]
        ax.set_title(f"t = {t:.3f} s", fontsize=9)
        ax.set_xlabel("x (m)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("y (m)", fontsize=8)
    fig.suptitle("observed (grey) vs simulated at the fit (red); blue: weight 0", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------

def _parse_assignments(text: str, label: str) -> dict:
    out = {}
    for item in filter(None, (s.strip() for s in str(text).split(","))):
        if "=" not in item:
            raise CalibrationError(f"--{label}: expected name=value pairs separated by commas, got {item!r}")
        k, v = (s.strip() for s in item.split("=", 1))
        if k == "density":
            k = "rho"
        out[k] = v
    return out


def parse_fixed(text: str | None) -> dict:
    """'kappa=3000,m=0.5' -> {'kappa': 3000.0, 'm': 0.5} (names from FIT_FIELDS, kappa, rho/density)."""
    if not text:
        return {}
    return _parse_numbers(text, "fix", FIT_FIELDS + KNOWN_INPUTS)


def _parse_numbers(text: str, label: str, allowed) -> dict:
    """'a=1,b=2' -> {'a': 1.0, 'b': 2.0} for names in `allowed`; errors name the option --label."""
    out = {}
    for k, v in _parse_assignments(text, label).items():
        if k not in allowed:
            raise CalibrationError(f"--{label}: unknown parameter {k!r}; expected one of {tuple(allowed)}")
        try:
            out[k] = float(v)
        except ValueError as exc:
            raise CalibrationError(f"--{label}: {k} must be a number, got {v!r}") from exc
    return out


_DURATION_UNITS = {"": 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}


def parse_duration(text: str | None) -> float | None:
    """The --time-budget option: '900', '900s', '15m', '15min' or '1.5h' -> seconds (None when absent)."""
    if text is None:
        return None
    t = str(text).strip().lower()
    number = t.rstrip("abcdefghijklmnopqrstuvwxyz")
    unit = t[len(number):]
    try:
        seconds = float(number) * _DURATION_UNITS[unit]
    except (ValueError, KeyError):
        raise CalibrationError(f"--time-budget: expected a duration such as 900, 900s, 15m or 1.5h, "
                               f"got {text!r}") from None
    if not (math.isfinite(seconds) and seconds > 0):
        raise CalibrationError(f"--time-budget: must be a positive duration, got {text!r}")
    return seconds


def parse_window(text: str | None) -> tuple | None:
    """The --time-window option: 'T_LO:T_HI' in s -> (T_LO, T_HI) (None when absent)."""
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in str(text).split(":"))
    except ValueError:
        raise CalibrationError(f"--time-window: expected T_LO:T_HI in s, e.g. 0:0.8, got {text!r}") from None
    return (lo, hi)


def parse_start(text: str | None, fixed: Mapping | None = None) -> dict | None:
    """The first start's guess from `--start`: 'mu=150,sigma_y=30' -> {'mu': 150.0, 'sigma_y': 30.0}, or the
    path of a fit.json whose fitted parameters are taken (those held fixed in this fit are left out), e.g.
    a fit of the same data on a coarser grid. None when not given."""
    if not text:
        return None
    path = Path(text)
    if "=" not in text and path.suffix == ".json":
        try:
            params = json.loads(path.read_text(encoding="utf-8"))["params"]
            out = {k: float(v) for k, v in params.items() if k in FIT_FIELDS and k not in (fixed or {})}
        except FileNotFoundError:
            raise CalibrationError(f"--start: no such fit result {text!r}") from None
        except (ValueError, KeyError, TypeError, AttributeError, OSError) as exc:  # JSON, UTF-8, a directory
            raise CalibrationError(f"--start: {text!r} is not a fit result (a fit.json with 'params'): {exc}") from None
        if not all(math.isfinite(v) for v in out.values()):
            raise CalibrationError(f"--start: {text!r} holds non-finite parameters {out}")
        if not out:
            raise CalibrationError(f"--start: {text!r} holds none of the fitted parameters {FIT_FIELDS}")
        return out
    return _parse_numbers(text, "start", FIT_FIELDS)


def parse_bounds(text: str | None) -> dict:
    """'mu=50:400,m=0.3:1' -> {'mu': (50.0, 400.0), 'm': (0.3, 1.0)}."""
    if not text:
        return {}
    out = {}
    for k, v in _parse_assignments(text, "bounds").items():
        if k not in FIT_FIELDS:
            raise CalibrationError(f"--bounds: unknown parameter {k!r}; expected one of {FIT_FIELDS}")
        try:
            lo, hi = (float(s) for s in v.split(":"))
        except ValueError as exc:
            raise CalibrationError(f"--bounds: {k} needs lo:hi, got {v!r}") from exc
        out[k] = (lo, hi)
    return out


def parse_feature(text: str | None, kind, label: str):
    """The --resample / --fracture option: None (flag absent) -> None; '' (flag alone) -> kind() with its
    defaults; 'every=10,sparse_fraction=0.4' -> kind(every=10, sparse_fraction=0.4) (integer fields parsed
    as int, the rest as float, 'none' as None)."""
    if text is None:
        return None
    types = {f.name: str(f.type) for f in dataclasses.fields(kind)}
    out = {}
    for k, v in _parse_assignments(text, label).items():
        if k not in types:
            raise CalibrationError(f"--{label}: unknown field {k!r}; expected some of {sorted(types)}")
        try:
            out[k] = None if v.lower() == "none" else (int(v) if types[k].startswith("int") else float(v))
        except ValueError as exc:
            raise CalibrationError(f"--{label}: {k} must be a {types[k].split()[0]}, got {v!r}") from exc
    return kind(**out)


def add_fit_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `fit` subcommand to an argparse subparsers object (runs via args.func(args))."""
    ap = subparsers.add_parser(
        "fit", help="calibrate mu, sigma_y, eta, m from silhouette data",
        description="Fit the Herschel-Bulkley parameters (mu Pa, sigma_y Pa, eta Pa s^m, m) of the scene in a "
                    "silhouette file. Density and kappa are known inputs from the scene. Writes fit.json, a loss "
                    "curve (<out>_loss.png), observed vs simulated silhouettes (<out>_overlay.png) and an HDF5 fit "
                    "log of every iteration (<out>.fitlog.h5) that --resume continues.")
    from .cli import _add_budget_options, int_at_least, positive_float

    ap.add_argument("data", help="silhouette file (.h5)")
    ap.add_argument("--out", required=True, help="result file (.json)")
    ap.add_argument("--dx", type=positive_float, default=None,
                    help=f"grid spacing of the fit, m (default: the largest domain extent / {FIT_CELLS[2]} in 2D, "
                         f"/ {FIT_CELLS[3]} in 3D)")
    ap.add_argument("--ppc", type=int_at_least(1), default=None,
                    help=f"particles per cell (default {FIT_PPC[2]} in 2D, {FIT_PPC[3]} in 3D)")
    ap.add_argument("--optimizer", choices=OPTIMIZERS, default="lm", help="default lm (Levenberg-Marquardt)")
    ap.add_argument("--fix", default=None,
                    help="hold parameters fixed, e.g. m=0.5,eta=10; kappa=.. or rho=.. override the scene's values")
    ap.add_argument("--bounds", default=None, help="bounds lo:hi, e.g. mu=20:1000,m=0.3:1.2 (defaults: "
                    + ", ".join(f"{k}={lo:g}:{hi:g}" for k, (lo, hi) in DEFAULT_BOUNDS.items()) + ")")
    ap.add_argument("--starts", type=int_at_least(1), default=DEFAULT_STARTS, help=f"multi-start guesses (default {DEFAULT_STARTS})")
    ap.add_argument("--start", default=None, metavar="NAME=VALUE,...|FIT.json",
                    help="the first start's guess, e.g. mu=150,sigma_y=30, or a fit.json to continue from (e.g. a "
                         "fit of the same data on a coarser --dx); default: the centre of the start ranges")
    ap.add_argument("--max-iter", type=int_at_least(0), default=None,
                    help="iterations per start (default " + ", ".join(f"{k} {v}" for k, v in DEFAULT_MAX_ITER.items())
                    + ")")
    ap.add_argument("--time-window", default=None, metavar="T_LO:T_HI",
                    help="fit only the frames with times in [T_LO, T_HI] s, e.g. 0:0.8 (default: all)")
    ap.add_argument("--time-budget", default=None, metavar="DURATION",
                    help="wall-time budget of the optimization, all starts together: 900 (s), 15m or 1.5h "
                         "(default: none). The best point found is reported when it runs out; --resume continues")
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="seed of the starts and particle sampling (default 0)")
    ap.add_argument("--pixel-level", type=int_at_least(0), default=None,
                    help="compare at 2^level larger pixels (default: the coarsest not larger than the particle spacing)")
    ap.add_argument("--dtype", choices=("float32", "float64"), default=FIT_DTYPE,
                    help=f"precision (default {FIT_DTYPE})")
    ap.add_argument("--log", default=None, help="fit log path (default <out>.fitlog.h5 beside the result)")
    ap.add_argument("--resume", action="store_true", help="continue the fit recorded in the fit log")
    ap.add_argument("--no-dx-check", action="store_true",
                    help="skip the discretization check (intervals then hold the statistical part only)")
    ap.add_argument("--dx-refit", type=int_at_least(0), default=None, metavar="N",
                    help=f"LM iterations the discretization check runs on its finer grid from the optimum; the move "
                         f"they measure counts beside its first-order estimates (default {DEFAULT_DX_REFIT[2]} in 2D, "
                         f"{DEFAULT_DX_REFIT[3]} in 3D; 0: the estimates only; each iteration costs one or two "
                         f"Jacobians on that grid)")
    ap.add_argument("--resample", nargs="?", const="", default=None, metavar="FIELD=VALUE,...",
                    help="particle resampling in every rollout of the fit (default off); alone it uses the "
                         "ResampleConfig defaults (every=20 substeps, target ppc = the fit's ppc, ...), or "
                         "override fields, e.g. --resample every=10,sparse_fraction=0.4")
    ap.add_argument("--fracture", nargs="?", const="", default=None, metavar="FIELD=VALUE,...",
                    help="the fracture stage in every substep of the fit (default off); alone it uses the "
                         "FractureConfig defaults (density_ratio 0.2 in 2D, 0.12 in 3D), or e.g. "
                         "--fracture density_ratio=0.15")
    ap.add_argument("--no-plots", action="store_true", help="skip the pictures")
    _add_budget_options(ap)
    ap.set_defaults(func=run_fit)
    return ap


def settings_from_args(args) -> FitSettings:
    """The validated `FitSettings` of parsed `fit` arguments."""
    fixed = parse_fixed(args.fix)
    return FitSettings(dx=args.dx, ppc=args.ppc, optimizer=args.optimizer, fixed=fixed,
                       bounds=parse_bounds(args.bounds), starts=args.starts,
                       initial=parse_start(getattr(args, "start", None), fixed), max_iter=args.max_iter,
                       time_budget=parse_duration(getattr(args, "time_budget", None)),
                       time_window=parse_window(getattr(args, "time_window", None)), seed=args.seed,
                       pixel_level=args.pixel_level, dtype=args.dtype,
                       dx_check=not args.no_dx_check, dx_refit=args.dx_refit,
                       resample=parse_feature(getattr(args, "resample", None), ResampleConfig, "resample"),
                       fracture=parse_feature(getattr(args, "fracture", None), FractureConfig, "fracture"),
                       ).validate()


class _Terminated(KeyboardInterrupt):
    """SIGTERM (a job scheduler's or `timeout`'s stop) delivered to a running fit."""


@contextlib.contextmanager
def _terminate_as_interrupt():
    """Within the block, SIGTERM raises `_Terminated` like Ctrl-C raises KeyboardInterrupt, so a stopped
    fit ends with a message on how to resume instead of silently (main thread only; a no-op elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise _Terminated

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def run_fit(args) -> int:
    """Run the `fit` subcommand from parsed arguments; returns the exit status."""
    settings = settings_from_args(args)
    out = Path(args.out)
    log = Path(args.log) if args.log else default_log_path(out)
    check_output(out, "--out", {"the data": args.data})
    check_output(log, "--log", {"the data": args.data, "--out": out})
    data = read_silhouettes(args.data)
    if args.resume and log.exists():
        fitting.FitLog(log, mode="r").close()  # a file that is not a fit log is refused before any work
    plots = not args.no_plots
    if plots and missing_modules("matplotlib"):
        print("jaxfoam fit: note: matplotlib is not installed, so the pictures are skipped (install the viz "
              "extra: pip install 'jaxfoam[viz]')", flush=True)
        plots = False
    problem = build_problem(data, settings, max_particles=args.max_particles, max_substeps=args.max_substeps)
    if not args.resume and log.exists():
        log.unlink()  # a fresh fit: an old log of this name is replaced

    def say(msg):
        print(msg, flush=True)

    try:
        with _terminate_as_interrupt():
            result = calibrate(data, settings, log=log, resume=args.resume, progress=say, problem=problem)
    except KeyboardInterrupt as exc:
        sys.stderr.write(f"\njaxfoam fit: {'terminated' if isinstance(exc, _Terminated) else 'interrupted'}; the fit "
                         f"log {log} keeps every finished iteration: run the same command with --resume to "
                         f"continue\n")
        return 143 if isinstance(exc, _Terminated) else 130
    result.write(out)
    print(result.report())
    print(f"wrote {out} (fit log {log})")
    if plots:
        loss_png = out.with_name(out.stem + "_loss.png")
        overlay_png = out.with_name(out.stem + "_overlay.png")
        plot_loss(result, loss_png)
        plot_overlay(problem, result, overlay_png)
        print(f"wrote {loss_png} and {overlay_png}")
    return 0
