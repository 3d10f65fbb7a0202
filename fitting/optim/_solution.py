"""Reason codes, the per-iteration record and the `Solution` a driver returns."""
from __future__ import annotations

import dataclasses
import enum
from typing import Any

import numpy as np


class Reason(str, enum.Enum):
    """Why an optimization stopped (or `RUNNING` while it has not)."""

    RUNNING = "running"
    CONVERGED_FTOL = "converged_ftol"
    CONVERGED_GTOL = "converged_gtol"
    CONVERGED_XTOL = "converged_xtol"
    MAX_ITERATIONS = "max_iterations"
    MAX_EVALUATIONS = "max_evaluations"
    NONFINITE = "nonfinite"
    STALLED = "stalled"
    # Appended last: the fit log stores reasons by their index in this enum (REASON_CODES).
    MAX_TIME = "max_time"

    @property
    def converged(self) -> bool:
        return self in (Reason.CONVERGED_FTOL, Reason.CONVERGED_GTOL, Reason.CONVERGED_XTOL)

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Reason.RUNNING: "still running",
    Reason.CONVERGED_FTOL: "converged: the loss changed by less than ftol (relative) in the last iteration",
    Reason.CONVERGED_GTOL: "converged: the largest gradient component is below gtol",
    Reason.CONVERGED_XTOL: "converged: the parameters moved by less than xtol (relative) in the last iteration",
    Reason.MAX_ITERATIONS: "stopped: the iteration budget (max_iterations) is spent",
    Reason.MAX_EVALUATIONS: "stopped: the objective-evaluation budget (max_evaluations) is spent",
    Reason.NONFINITE: "stopped: the objective is not finite at the start, or every shrunk trial step was non-finite",
    Reason.STALLED: "stopped: no decrease found along the search direction (line search or damping limit reached)",
    Reason.MAX_TIME: "stopped: the wall-time budget (max_time) is spent; resuming from the fit log continues the run",
}

# Optimizer states keep their status as an integer array (a pytree leaf that an HDF5 log can store);
# this is the code of each reason.
REASON_CODES = tuple(Reason)


def reason_code(reason: Reason) -> int:
    return REASON_CODES.index(Reason(reason))


def reason_from_code(code) -> Reason:
    return REASON_CODES[int(code)]


@dataclasses.dataclass(frozen=True)
class History:
    """Accepted iterates, one row per iteration (row 0 is the starting point).

    Attributes:
      loss: (K+1,) loss after each iteration, in the objective's units.
      x: (K+1, p) parameters (in the optimizer's coordinates) after each iteration.
      evaluations: (K+1,) cumulative number of objective evaluations.
      time: (K+1,) wall time since the start of the fit, s (continues across resumes).
      nonfinite: (K+1,) cumulative number of evaluations that returned a non-finite value.
    """

    loss: np.ndarray
    x: np.ndarray
    evaluations: np.ndarray
    time: np.ndarray
    nonfinite: np.ndarray


@dataclasses.dataclass(frozen=True)
class IterationInfo:
    """What a driver passes to its callback after each accepted iteration (and after the start, iteration 0).

    Attributes:
      iteration: number of completed iterations.
      x: (p,) current parameters.
      loss: current loss (objective units).
      grad: (p,) gradient of the loss at x.
      state: the optimizer's state pytree.
      evaluations: cumulative objective evaluations.
      time: wall time since the fit started, s.
      run: index of the run (multi-start index; 0 for a single fit).
    """

    iteration: int
    x: np.ndarray
    loss: float
    grad: np.ndarray
    state: Any
    evaluations: int
    time: float
    run: int


@dataclasses.dataclass(frozen=True)
class Solution:
    """Result of `minimize` or `least_squares`.

    Attributes:
      x: (p,) best accepted parameters (optimizer coordinates).
      loss: loss at x (for least squares 0.5 * sum(r**2)).
      grad: (p,) gradient of the loss at x.
      reason: why the loop stopped.
      iterations: accepted iterations.
      evaluations: objective evaluations, every call counted (rejected trials included).
      nonfinite_evaluations: how many of those returned a non-finite value.
      wall_time: seconds from the start of the fit to its end (across resumes).
      history: per-iteration record.
      state: final optimizer state.
      residual: (n,) residuals at x for least-squares fits when known without another evaluation, else None.
      jacobian: (n, p) d residual / d x at x, same availability.
      run: run index (multi-start).
    """

    x: np.ndarray
    loss: float
    grad: np.ndarray
    reason: Reason
    iterations: int
    evaluations: int
    nonfinite_evaluations: int
    wall_time: float
    history: History
    state: Any
    residual: np.ndarray | None = None
    jacobian: np.ndarray | None = None
    run: int = 0

    @property
    def converged(self) -> bool:
        return self.reason.converged

    @property
    def message(self) -> str:
        return self.reason.message
