"""Multi-start: run an optimizer from a small seeded Latin hypercube of initial guesses, keep the best."""
from __future__ import annotations

import dataclasses
import time
from typing import Callable, Mapping

import numpy as np

from ._driver import check_max_time
from ._solution import Solution
from .fitlog import FitLog, FitLogError
from .population import BatchOracle, run_population
from .transforms import ParameterTransform

# Fraction of each parameter's sampling range left out at both ends: a start on a bound is a saturated
# sigmoid (zero gradient) in the fitted coordinates.
DEFAULT_MARGIN = 0.05


def latin_hypercube(n: int, p: int, seed) -> np.ndarray:
    """n points of a Latin hypercube in [0, 1)^p: along every axis each of the n strata [k/n, (k+1)/n)
    holds exactly one point, placed uniformly inside it.

    Args:
      n: number of points (>= 1).  p: dimension (>= 1).  seed: anything `np.random.default_rng` accepts.
    Returns:
      (n, p) float64.
    """
    if int(n) < 1 or int(p) < 1:
        raise ValueError(f"latin_hypercube needs n >= 1 and p >= 1, got n={n!r}, p={p!r}")
    rng = np.random.default_rng(seed)
    u = np.empty((n, p))
    for j in range(p):
        u[:, j] = (rng.permutation(n) + rng.random(n)) / n
    return u


def lhs_starts(transform: ParameterTransform, n_starts: int, seed, *,
               sample_bounds: Mapping[str, tuple] | None = None, margin: float = DEFAULT_MARGIN):
    """Initial guesses in fitted coordinates from a seeded Latin hypercube over the parameters' ranges.

    Args:
      transform: the parameter maps; its bounds (or `sample_bounds`) give each range, sampled uniformly
        (in log for log parameters).
      n_starts: number of starts.  seed: integer seed (recorded in the fit log).
      sample_bounds: name -> (lo, hi) physical range, required for parameters without two finite bounds.
      margin: fraction of each range excluded at both ends, in [0, 0.5).
    Returns:
      (z (S, p), unit (S, p)): starting points in fitted coordinates and the unit-cube design.
    """
    if not 0.0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin!r}")
    unit = latin_hypercube(n_starts, transform.size, seed)
    theta = transform.from_unit(margin + (1.0 - 2.0 * margin) * unit, sample_bounds)
    z = np.stack([np.asarray(transform.to_unconstrained(t)) for t in theta])
    return z, unit


@dataclasses.dataclass(frozen=True)
class MultiStartResult:
    """All runs of a multi-start fit.

    Attributes:
      best: the solution with the lowest finite loss (ties: lowest index).
      best_index: its run index.
      solutions: one `Solution` per start, in start order.
      starts: (S, p) initial guesses (fitted coordinates).
      seed: the Latin-hypercube seed (None if the starts were given).
    """

    best: Solution
    best_index: int
    solutions: list
    starts: np.ndarray
    seed: int | None

    def table(self, names=None) -> str:
        """A plain-text summary, one line per start."""
        p = self.starts.shape[1]
        names = names or [f"x{i}" for i in range(p)]
        head = f"{'run':>3}  {'loss':>12}  {'reason':<16} {'iter':>5} {'evals':>6}  start -> end"
        lines = [head]
        for i, s in enumerate(self.solutions):
            mark = "*" if i == self.best_index else " "
            start = ", ".join(f"{n}={v:.4g}" for n, v in zip(names, self.starts[i]))
            end = ", ".join(f"{v:.4g}" for v in s.x)
            lines.append(f"{i:>3}{mark} {s.loss:>12.5g}  {s.reason.value:<16} {s.iterations:>5} "
                         f"{s.evaluations:>6}  [{start}] -> [{end}]")
        return "\n".join(lines)


def multistart(solve: Callable[..., Solution], starts, *, log=None, resume: bool = False, seed=None,
               unit=None, max_time: float | None = None, population: BatchOracle | None = None) -> MultiStartResult:
    """Run `solve` from every start and keep the best.

    Args:
      solve: x0 -> Solution accepting the driver keywords log, run, resume, seed, e.g.
        ``lambda x0, **kw: fitting.optim.least_squares(fn, x0, fitting.optim.LevenbergMarquardt(), **kw)``.
      starts: (S, p) initial guesses (fitted coordinates), e.g. from `lhs_starts`.
      log: fit-log path or open `FitLog`; run i is logged as run i.
      resume: continue a logged multi-start (finished runs are read back without evaluating anything,
        the interrupted one continues, the rest start); the starts must equal the logged ones.
      seed: the seed that produced the starts (recorded).  unit: their unit-cube design (recorded).
      max_time: wall-time budget of all starts together, s (None: unlimited). Each start gets what is
        left of it as the driver's `max_time` keyword (so `solve` must accept it); the first start
        always evaluates its starting point, a later start the budget leaves no time for is not
        evaluated (`Reason.MAX_TIME`, loss inf, empty history). With `resume`, runs stopped by the
        budget continue and unstarted ones start, under the new budget.
      population: run the starts together, each in its own thread, with `solve` evaluating through this
        `BatchOracle` (`fitting.optim.population`): every start then follows its sequential path and
        each step of all of them costs one batched evaluation. With `max_time`, every start gets the
        whole budget (they share the wall clock).
    """
    check_max_time(max_time)
    deadline = None if max_time is None else time.perf_counter() + float(max_time)
    starts = np.asarray(starts, np.float64)
    if starts.ndim != 2 or starts.shape[0] < 1:
        raise ValueError(f"starts must be (S >= 1, p), got shape {starts.shape}")
    unit = np.full_like(starts, np.nan) if unit is None else np.asarray(unit, np.float64)
    owns = log is not None and not isinstance(log, FitLog)
    fitlog = FitLog(log) if owns else log
    try:
        if fitlog is not None:
            logged = fitlog.read_starts()
            if resume and logged is not None:
                if not np.array_equal(logged[0], starts) or logged[2] != (None if seed is None else int(seed)):
                    raise FitLogError(f"{fitlog.path}: cannot resume, the logged multi-start has other starts "
                                      f"or seed (seed {logged[2]} in the log, {seed} now)")
            else:
                if not resume:
                    fitlog.clear()
                fitlog.write_starts(starts, unit, seed)
        solutions = []
        if population is not None:
            budget = {} if deadline is None else {"max_time": max(1e-9, deadline - time.perf_counter())}
            solutions = run_population(lambda x0, run, **kw: solve(x0, log=fitlog, run=run, resume=resume, seed=seed,
                                                                   **kw), starts, population, **budget)
        for i, x0 in enumerate(starts if population is None else ()):
            budget = {}
            if deadline is not None:
                # The first start always evaluates its starting point, so there is a point to report.
                budget["max_time"] = max(1e-9 if i == 0 else 0.0, deadline - time.perf_counter())
            solutions.append(solve(x0, log=fitlog, run=i, resume=resume, seed=seed, **budget))
    finally:
        if owns:
            fitlog.close()
    losses = np.array([s.loss if np.isfinite(s.loss) else np.inf for s in solutions])
    best = int(np.argmin(losses))
    return MultiStartResult(best=solutions[best], best_index=best, solutions=solutions, starts=starts,
                            seed=None if seed is None else int(seed))
