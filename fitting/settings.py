"""Fit settings and the calibration's defaults (bounds, starts, grid, discretization check)."""
from __future__ import annotations

import dataclasses
import math
from typing import Mapping

from jaxfoam import FIT_FIELDS, JaxfoamError
from jaxfoam.fracture import FractureConfig
from jaxfoam.resample import ResampleConfig


# Bounds of the fitted parameters, SI units (Pa, Pa, Pa s^m, -): a wide envelope around foam
# rheometry (shear moduli of tens to ~1000 Pa, yield stresses of ~1 to a few 100 Pa, consistencies
# of ~0.1-100 Pa s^m, shear-thinning exponents 0.3-1; Durian 1990, Ovarlez 2010), so a bound is only
# reached by a fit that has gone wrong. mu's upper bound also sets the time step (see `build_problem`).
DEFAULT_BOUNDS = {"mu": (5.0, 2000.0), "sigma_y": (0.5, 500.0), "eta": (0.05, 500.0), "m": (0.2, 1.5),
                  "friction": (0.01, 2.0)}
# Where multi-start initial guesses are drawn (log-uniform for mu, sigma_y, eta; uniform for m): the
# shaving-cream ranges of the same sources, a little widened. Start 0 is the centre of these ranges.
DEFAULT_START_RANGES = {"mu": (30.0, 600.0), "sigma_y": (5.0, 150.0), "eta": (0.5, 60.0), "m": (0.3, 1.0),
                        "friction": (0.1, 1.0)}
# Scene parameters a fit may estimate beside the material (`fit_also`): the floor's Coulomb coefficient
# (dimensionless), which a user rarely knows for their table.
NUISANCE_FIELDS = ("friction",)
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
# LM's Jacobian: exact at every trial (0). Broyden updates (k > 0) saved little where 2D starts converge
# and move the end of starts stopped by their budget (docs/performance.md).
DEFAULT_BROYDEN_STEPS = 0
# Goodness of fit: frames whose fitted and observed boundaries are on average more than this many
# particle spacings apart are a misfit the discretization does not explain (docs/calibrate.md, "The defaults and why").
FRAME_BOUNDARY_SPACINGS = 1.0
DEFAULT_LEVEL = 0.95
# Residual autocorrelation is integrated over lags up to this many kernel supports, per axis.
CORRELATION_WINDOW_SUPPORTS = 1.0
# Discretization check: one more residual and Jacobian on a grid this much finer, extrapolated at first
# order (MPM silhouettes converge at best at first order in dx); the finer side is the data's side.
DX_CHECK_RATIO = 1.0 / math.sqrt(2.0)
DX_CHECK_ORDER = 1.0
# The check's predicted move uses the larger of the fit grid's and each grid's own Jacobian: neither
# alone covered the refits of the recovery study (docs/calibrate.md, "The defaults and why").
DX_CHECK_JACOBIAN = "both"
# LM iterations of the check's measured move on the finer grid, per dimension: 4 in 2D (fewer left moves
# still growing), 2 in 3D (each costs about 4x a fit-grid Jacobian); docs/calibrate.md, "The defaults and why".
DEFAULT_DX_REFIT = {2: 4, 3: 2}
# Safety factor on the extrapolated numerical error: Roache's grid convergence index for a two-grid
# estimate with an assumed order.
GCI_SAFETY = 3.0
# A parameter whose reported interval covers at least this fraction of its bounds is not identifiable:
# the data then say no more than the bounds do (e.g. m in [0.25, 1.5] with bounds [0.2, 1.5]).
BOUND_SPAN_FRACTION = 0.9
# The fit's default discretization and precision: the measurements of experiments/MODEL_CHOICE.md (its
# `defaults` block states the same values; tests/fitting/test_model_choice.py keeps the two equal).
FIT_CELLS = {2: 64, 3: 32}  # cells across the largest extent: 2D the best grid measured, 3D the affordable one
FIT_PPC = {2: 4, 3: 8}
FIT_CFL = 0.3
FIT_DTYPE = "float64"  # float32 reaches float64's optima with too little speed gain to trade precision for
# Particle resampling and fracture in the fit's rollouts: off; on the 2D fit scenes neither moved a fit
# outside the plain fit's interval (experiments/results/fit_features.md).
FIT_RESAMPLE = None
FIT_FRACTURE = None
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


class CalibrationError(JaxfoamError, ValueError):
    """Bad calibration input (settings, data); the message names the field."""


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """What to fit and how (all SI units).

    Attributes:
      dx: grid spacing of the fit, m (None: the largest domain extent / FIT_CELLS: 64 in 2D, 32 in 3D).
      ppc: particles per cell (None: FIT_PPC: 4 in 2D, 8 in 3D).
      floor_phase: where the fit grid's node rows lie against the scene's floor: the floor is this many
        cells above the row below it, in [0, 1) (the domain is extended below to place them). None: the
        rows at the domain's lower bound + k dx, as `jaxfoam simulate` and `synthesize` place them (a floor
        at that bound lies on a row). Ignored without a floor.
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
      broyden_steps: Levenberg-Marquardt's trials evaluate the residuals alone and update the Jacobian by
        Broyden's rule, evaluating it exactly every this many accepted steps, after a rejected trial and
        before stopping (0: (r, J) at every trial). Sequential starts only: a population evaluates exact
        Jacobians. The intervals always use the exact Jacobian at the optimum.
      time_window: (t_lo, t_hi), s: fit only the frames whose times lie in it (None: every frame after the
        start); the rollouts then stop at the last of them. For data whose late phase the model (or a
        coarse grid) does not resolve, e.g. foam tearing off a plate.
      resolved_frames: fit only the frames (of time_window, or of all) before the first one whose silhouette
        moves more than FRAME_BOUNDARY_SPACINGS particle spacings between the fit grid and DX_CHECK_RATIO dx,
        measured at the start point and again at each optimum, refitting until the window stays put
        (`fitting.horizon`). For records whose late frames the grid, not the material, shapes.
      time_budget: wall-time budget of the optimization (all starts together), s; None: unlimited. It is
        checked before each iteration: a start stops when the time left is shorter than its previous
        iteration took, and starts with no time left do not run. The best point found is then reported
        (with a note), and the fit can be continued with `resume` under a new budget. Building the
        simulator before, and the uncertainty and discretization check after, are not counted.
      population: run the starts together (`fitting.optim.population`), each step of all of them one
        batched evaluation of their Jacobians, sharded over `devices`; every start follows the path it
        follows alone. None: on when the backend is not the CPU or the fit spans several processes
        (`jax.distributed`); on 2 CPU cores the starts in turn ran faster (docs/performance.md).
      devices: devices the population's batch is split over (None: all of them). On the CPU there is
        one device unless the process asked for more (`jaxfoam fit --devices N` does).
      seed: Latin-hypercube seed of the starts (and particle sampling seed).
      pixel_level: pyramid level of the observations (0 = the data's pixels, l = 2^l times larger);
        None picks the coarsest level whose pixels are not larger than the particle spacing.
      level: confidence level of the intervals.
      dtype: "float64" (FIT_DTYPE) or "float32".
      distance_weight, chamfer_weight: weights of the distance-field terms in the residual.
      dx_check: estimate the numerical (discretization) error of the estimate from the residual and
        Jacobian on a grid of spacing DX_CHECK_RATIO dx and widen the intervals by it (see
        `discretization_error`).
      fit_also: scene parameters fitted beside the material, from NUISANCE_FIELDS: "friction" (the floor's
        Coulomb coefficient; the scene needs a floor that is not sticky). Their bounds, start ranges and
        first guess may be given like the material's; they get intervals and identifiability notes too.
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
    floor_phase: float | None = None
    optimizer: str = "lm"
    fixed: Mapping = dataclasses.field(default_factory=dict)
    bounds: Mapping = dataclasses.field(default_factory=dict)
    start_ranges: Mapping = dataclasses.field(default_factory=dict)
    starts: int = DEFAULT_STARTS
    initial: Mapping | None = None
    max_iter: int | None = None
    broyden_steps: int = DEFAULT_BROYDEN_STEPS
    time_budget: float | None = None
    time_window: tuple | None = None
    resolved_frames: bool = False
    population: bool | None = None
    devices: int | None = None
    seed: int = 0
    pixel_level: int | None = None
    level: float = DEFAULT_LEVEL
    dtype: str = FIT_DTYPE
    distance_weight: float = 1.0
    chamfer_weight: float = 1.0
    dx_check: bool = True
    dx_refit: int | None = None
    fit_also: tuple = ()
    resample: object = FIT_RESAMPLE
    fracture: object = FIT_FRACTURE

    def __post_init__(self):
        # True / dict -> the config object (frozen dataclass: set through object.__setattr__).
        object.__setattr__(self, "resample", _as_config(self.resample, ResampleConfig, "resample"))
        object.__setattr__(self, "fracture", _as_config(self.fracture, FractureConfig, "fracture"))
        object.__setattr__(self, "fit_also", tuple(self.fit_also))

    def validate(self) -> "FitSettings":
        if self.optimizer not in OPTIMIZERS:
            raise CalibrationError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.dx is not None and not (self.dx > 0 and math.isfinite(self.dx)):
            raise CalibrationError(f"dx must be a positive grid spacing in m, got {self.dx!r}")
        if self.ppc is not None and int(self.ppc) < 1:
            raise CalibrationError(f"ppc must be >= 1, got {self.ppc!r}")
        if self.floor_phase is not None and (isinstance(self.floor_phase, bool) or not (
                isinstance(self.floor_phase, (int, float)) and 0.0 <= self.floor_phase < 1.0)):
            raise CalibrationError(f"floor_phase must be None or a fraction of a cell in [0, 1), got "
                                   f"{self.floor_phase!r}")
        if self.dx_refit is not None and (isinstance(self.dx_refit, bool) or int(self.dx_refit) != self.dx_refit
                                          or self.dx_refit < 0):
            raise CalibrationError(f"dx_refit must be a whole number of iterations >= 0, got {self.dx_refit!r}")
        for name, value in self.fixed.items():
            if name not in FIT_FIELDS + KNOWN_INPUTS:
                raise CalibrationError(f"fixed: unknown parameter {name!r}; expected one of {FIT_FIELDS + KNOWN_INPUTS}")
            if not math.isfinite(float(value)):
                raise CalibrationError(f"fixed: {name} must be a finite number, got {value!r}")
        if all(n in self.fixed for n in FIT_FIELDS) and not self.fit_also:
            raise CalibrationError(f"fixed: every parameter {FIT_FIELDS} is fixed, nothing is left to fit")
        for name in self.fit_also:
            if name not in NUISANCE_FIELDS:
                raise CalibrationError(f"fit_also: unknown parameter {name!r}; expected some of {NUISANCE_FIELDS}")
        if len(set(self.fit_also)) != len(self.fit_also):
            raise CalibrationError(f"fit_also: a parameter is named twice in {self.fit_also}")
        known = FIT_FIELDS + self.fit_also
        for label, table in (("bounds", self.bounds), ("start_ranges", self.start_ranges)):
            for name, (lo, hi) in table.items():
                if name not in known:
                    raise CalibrationError(f"{label}: unknown parameter {name!r}; expected one of {known}")
                if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
                    raise CalibrationError(f"{label}: {name} needs finite 0 < lo < hi, got {lo}:{hi}")
        if not int(self.starts) >= 1:
            raise CalibrationError(f"starts must be >= 1, got {self.starts!r}")
        if self.population not in (None, True, False):
            raise CalibrationError(f"population must be None, True or False, got {self.population!r}")
        if self.devices is not None and not (isinstance(self.devices, int) and self.devices >= 1):
            raise CalibrationError(f"devices must be None (all local devices) or an integer >= 1, got {self.devices!r}")
        for name, value in (self.initial or {}).items():
            if name not in known:
                raise CalibrationError(f"initial: unknown parameter {name!r}; expected one of {known}")
            if name in self.fixed:
                raise CalibrationError(f"initial: {name} is fixed (fixed={dict(self.fixed)}); give it one or the other")
            lo, hi = self.bounds_of(name)
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise CalibrationError(f"initial: {name} must be a number, got {value!r}") from None
            if not (math.isfinite(v) and lo <= v <= hi):
                raise CalibrationError(f"initial: {name} = {value!r} must lie within its bounds [{lo:g}, {hi:g}]")
        if isinstance(self.broyden_steps, bool) or not isinstance(self.broyden_steps, int) \
                or self.broyden_steps < 0:
            raise CalibrationError(f"broyden_steps must be an integer >= 0, got {self.broyden_steps!r}")
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
        if self.resolved_frames not in (True, False):
            raise CalibrationError(f"resolved_frames must be True or False, got {self.resolved_frames!r}")
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
        """Names of the fitted parameters: the material's in FIT_FIELDS order, then `fit_also`."""
        return tuple(n for n in FIT_FIELDS if n not in self.fixed) + self.fit_also

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
        d["bounds"] = {n: list(self.bounds_of(n)) for n in FIT_FIELDS + self.fit_also}
        d["start_ranges"] = {n: list(self.start_range_of(n)) for n in FIT_FIELDS + self.fit_also}
        d["fit_also"] = list(self.fit_also)
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
