"""fitting.optim: optimizers, parameter transforms, multi-start, HDF5 fit logs and uncertainty, in JAX.

Independent of the simulator: everything is generic over a loss or a residual function.

* `minimize(fn, x0, optimizer)` (Adam, LBFGS) and `least_squares(fn, x0, optimizer)`
  (LevenbergMarquardt by default) run one loop that owns iteration counting, budgets, tolerances,
  non-finite detection, the fit log (`log=`, `resume=`) and the callback; they return a `Solution`.
* `ParameterTransform` maps fitted coordinates to physical parameters (log, bounded, ...).
* `lhs_starts` / `multistart` run an optimizer from a seeded Latin hypercube of starts.
* `gauss_newton_uncertainty` / `solution_uncertainty`: covariance, intervals, correlations and a
  plain-language identifiability report.
"""
from ._adam import Adam, AdamState
from ._base import AbstractOptimizer
from ._driver import least_squares, minimize, value_and_jacfwd
from ._lbfgs import LBFGS, LBFGSState
from ._lm import LevenbergMarquardt, LMState
from ._solution import History, IterationInfo, Reason, Solution
from .fitlog import FitLog, FitLogError, read_fitlog
from .multistart import MultiStartResult, latin_hypercube, lhs_starts, multistart
from .population import BatchOracle, PopulationStopped, run_population
from .transforms import ParameterTransform
from .uncertainty import Uncertainty, gauss_newton_uncertainty, solution_uncertainty, student_t_quantile

__all__ = [
    "AbstractOptimizer", "Adam", "AdamState", "LBFGS", "LBFGSState", "LevenbergMarquardt", "LMState",
    "minimize", "least_squares", "value_and_jacfwd", "Solution", "History", "IterationInfo", "Reason",
    "FitLog", "FitLogError", "read_fitlog", "ParameterTransform", "latin_hypercube", "lhs_starts",
    "multistart", "MultiStartResult", "BatchOracle", "PopulationStopped", "run_population", "Uncertainty", "gauss_newton_uncertainty", "solution_uncertainty",
    "student_t_quantile",
]
