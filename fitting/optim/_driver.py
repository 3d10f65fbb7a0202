"""The one loop driver: `minimize` and `least_squares`.

The driver owns the iteration count, the evaluation budget, the tolerance tests, non-finite detection,
the fit log and the callback; an optimizer only proposes and accepts steps (see `fitting.optim._base`).
The objective is called only through a counting oracle, once per point an optimizer asks for; jit is
the caller's business (pass a jitted objective).
"""
from __future__ import annotations

import dataclasses
import math
import time as _time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ._base import AbstractOptimizer, as_array, scalar, state_arrays, state_from_arrays, host
from ._lm import LevenbergMarquardt
from ._solution import History, IterationInfo, Reason, Solution
from .fitlog import FitLog


class _BudgetExhausted(Exception):
    """Raised by the oracle when the next evaluation would exceed max_evaluations."""


class _Oracle:
    """Counts evaluations, enforces the budget and maps any non-finite output to value = +inf."""

    def __init__(self, evaluate, max_evaluations, evaluations=0, nonfinite=0, residual=None):
        self.evaluate = evaluate
        self.max_evaluations = max_evaluations
        self.evaluations = int(evaluations)
        self.nonfinite = int(nonfinite)
        if residual is not None:
            self.residual = self._residual_only
            self._residual = residual

    def _count(self):
        if self.max_evaluations is not None and self.evaluations >= self.max_evaluations:
            raise _BudgetExhausted
        self.evaluations += 1

    def _checked(self, value, *arrays):
        """value, or inf in its shape when it or any of the arrays is not finite (counted)."""
        if not all(np.isfinite(np.asarray(a)).all() for a in (value,) + arrays):
            self.nonfinite += 1
            value = host(np.full(value.shape, np.inf, value.dtype))
        return value

    def _residual_only(self, x):
        """r(x) alone (one evaluation)."""
        self._count()
        return self._checked(as_array(self._residual(x)))

    def __call__(self, x):
        self._count()
        value, deriv = self.evaluate(x)
        value, deriv = as_array(value), as_array(deriv)
        return self._checked(value, deriv), deriv


@jax.jit
def _loss_and_grad(r, jac):
    """0.5 |r|^2 and its gradient J^T r."""
    return 0.5 * jnp.dot(r, r), jac.T @ r


class _LossFromResiduals:
    """(r, J) oracle seen as (0.5 |r|^2, J^T r), keeping the (r, J) of this step's trials so the
    accepted point's residuals and Jacobian are known without evaluating again."""

    def __init__(self, oracle: _Oracle):
        self.oracle = oracle
        self.trials = []
        self.current = None

    def __call__(self, x):
        r, jac = self.oracle(x)
        self.trials.append((x, r, jac))
        return _loss_and_grad(r, jac)

    def accept(self, x):
        for xt, r, jac in self.trials:
            if xt is x or np.array_equal(np.asarray(xt), np.asarray(x)):
                self.current = (r, jac)
                break
        self.trials = []


def value_and_jacfwd(residual: Callable) -> Callable:
    """x -> (r(x), dr/dx(x)) from one forward-mode pass (`jax.jacfwd` with the residual as aux)."""

    def both(x):
        def pair(z):
            r = residual(z)
            return r, r

        jac, r = jax.jacfwd(pair, has_aux=True)(x)
        return r, jac

    return both


def check_max_time(value):
    """Raise ValueError unless a wall-time budget is None or a finite number of seconds >= 0."""
    if value is not None and not (isinstance(value, (int, float, np.floating, np.integer)) and
                                  math.isfinite(value) and value >= 0):
        raise ValueError(f"max_time must be None or a finite number of seconds >= 0, got {value!r}")


def _check_tol(name, value):
    if value is not None and (not math.isfinite(value) or value < 0):
        raise ValueError(f"{name} must be None or a finite number >= 0, got {value!r}")


def _as_vector(x0):
    x = np.asarray(x0)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(jnp.result_type(float))  # the default float of this JAX (float64 with x64 on)
    if x.ndim != 1 or x.shape[0] < 1:
        raise ValueError(f"x0 must be a 1-D array of at least one parameter, got shape {x.shape}")
    if not np.all(np.isfinite(np.asarray(x))):
        raise ValueError(f"x0 must be finite, got {np.asarray(x).tolist()}")
    return host(x)


def _tolerance_reason(hist_x, hist_loss, grad, ftol, xtol, gtol):
    """The common convergence tests on the last accepted iteration."""
    if gtol is not None and float(np.max(np.abs(np.asarray(grad)))) <= gtol:
        return Reason.CONVERGED_GTOL
    if len(hist_loss) < 2:
        return None
    f0, f1 = float(hist_loss[-2]), float(hist_loss[-1])
    if ftol is not None and abs(f0 - f1) <= ftol * max(abs(f0), abs(f1)):
        return Reason.CONVERGED_FTOL
    x0, x1 = np.asarray(hist_x[-2]), np.asarray(hist_x[-1])
    if xtol is not None and np.max(np.abs(x1 - x0)) <= xtol * (xtol + np.max(np.abs(x1))):
        return Reason.CONVERGED_XTOL
    return None


def minimize(fn: Callable, x0, optimizer: AbstractOptimizer, *, with_grad: bool = False, **kwargs) -> Solution:
    """Minimize a scalar loss with a gradient optimizer (`Adam`, `LBFGS`).

    Args:
      fn: x (p,) -> loss (scalar), or -> (loss, grad (p,)) when with_grad is True. Without with_grad
        the gradient comes from `jax.value_and_grad(fn)` (one call returns both).
      x0: (p,) starting point (optimizer coordinates, usually `ParameterTransform` unconstrained ones).
      optimizer: a minimize-kind optimizer.
      **kwargs: driver settings, see `least_squares`.
    """
    if optimizer.kind != "minimize":
        raise ValueError(f"{type(optimizer).__name__} needs residuals: use fitting.optim.least_squares")
    evaluate = fn if with_grad else jax.value_and_grad(fn)
    return _iterate("minimize", evaluate, x0, optimizer, **kwargs)


def least_squares(fn: Callable, x0, optimizer: AbstractOptimizer | None = None, *, with_jac: bool = False,
                  residual: Callable | None = None, **kwargs) -> Solution:
    """Minimize 0.5 * |r(x)|^2 with Levenberg-Marquardt (default) or any gradient optimizer.

    Args:
      fn: x (p,) -> residuals r (n,), or -> (r, J (n, p)) when with_jac is True (for instance a
        forward-mode rollout that returns both). Without with_jac, J comes from `value_and_jacfwd(fn)`.
      x0: (p,) starting point.
      residual: x -> r alone, cheaper than fn, for optimizers that use it (`LevenbergMarquardt` with
        `broyden_steps`); without with_jac, fn itself. Each call counts as an evaluation.
      optimizer: `LevenbergMarquardt()` by default; `Adam` and `LBFGS` run on the loss 0.5 |r|^2 with
        gradient J^T r.
      max_iterations: accepted iterations allowed (default 100).
      max_evaluations: objective calls allowed (None: unlimited).
      ftol: stop when |L_k - L_{k-1}| <= ftol * max(|L_k|, |L_{k-1}|) (None disables).
      xtol: stop when max|x_k - x_{k-1}| <= xtol * (xtol + max|x_k|) (None disables).
      gtol: stop when max|grad| <= gtol, in loss units per unit of x (None disables).
      max_time: wall-time budget of this call, s (None: unlimited). It is checked before each iteration:
        the run stops (reason MAX_TIME) when the time left is shorter than the previous iteration of this
        call took, so one iteration may overrun it; the starting point of a fresh run is always evaluated,
        unless max_time is 0: then nothing is evaluated or logged, and the solution has loss inf and an
        empty history (a multi-start passes 0 to the starts its budget left no time for). A run stopped
        by its budget continues when resumed (each call brings its own budget).
      callback: called with an `IterationInfo` after each accepted iteration (and iteration 0), after
        the fit log has been flushed; an exception it raises ends the fit (the log stays resumable).
      log: path of an HDF5 fit log (or an open `FitLog`), None for no log.
      run: run index inside the log (the multi-start index).
      resume: continue the run found in the log (same settings and x0 required); False starts afresh.
      seed: recorded with the run (the multi-start seed), not used by the optimizers.

    Returns:
      a `Solution`; for least squares its `residual` and `jacobian` hold (r, J) at x when known.
    """
    optimizer = LevenbergMarquardt() if optimizer is None else optimizer
    evaluate = fn if with_jac else value_and_jacfwd(fn)
    if residual is None and not with_jac:
        residual = fn
    return _iterate("least_squares", evaluate, x0, optimizer, residual=residual, **kwargs)


def _iterate(kind, evaluate, x0, optimizer, *, max_iterations=100, max_evaluations=None, ftol=1e-10,
             xtol=1e-10, gtol=None, callback=None, log=None, run=0, resume=False, seed=None,
             max_time=None, residual=None) -> Solution:
    if not isinstance(optimizer, AbstractOptimizer):
        raise ValueError(f"optimizer must be a fitting optimizer (Adam, LBFGS, LevenbergMarquardt), got "
                         f"{optimizer!r}")
    x0 = _as_vector(x0)
    if int(max_iterations) < 0:
        raise ValueError(f"max_iterations must be >= 0, got {max_iterations!r}")
    if max_evaluations is not None and int(max_evaluations) < 1:
        raise ValueError(f"max_evaluations must be None or >= 1, got {max_evaluations!r}")
    for name, value in (("ftol", ftol), ("xtol", xtol), ("gtol", gtol)):
        _check_tol(name, value)
    check_max_time(max_time)
    meta = {"kind": kind, "optimizer": optimizer.config(), "ftol": ftol, "xtol": xtol, "gtol": gtol,
            "max_iterations": int(max_iterations), "max_evaluations": max_evaluations, "n_params": x0.shape[0]}

    owns_log = log is not None and not isinstance(log, FitLog)
    fitlog = FitLog(log) if owns_log else log
    try:
        return _loop(kind, evaluate, x0, optimizer, meta, fitlog, int(run), bool(resume), seed,
                     int(max_iterations), max_evaluations, ftol, xtol, gtol, callback, max_time, residual)
    finally:
        if owns_log:
            fitlog.close()


def _not_started(x0, run) -> Solution:
    """The solution of a run that the time budget left no time to start: nothing evaluated."""
    p = x0.shape[0]
    empty = History(loss=np.zeros(0), x=np.zeros((0, p)), evaluations=np.zeros(0, np.int64), time=np.zeros(0),
                    nonfinite=np.zeros(0, np.int64))
    return Solution(x=np.asarray(x0), loss=math.inf, grad=np.full(p, np.nan), reason=Reason.MAX_TIME, iterations=0,
                    evaluations=0, nonfinite_evaluations=0, wall_time=0.0, history=empty, state=None, run=run)


def _loop(kind, evaluate, x0, optimizer, meta, fitlog, run, resume, seed, max_iterations, max_evaluations,
          ftol, xtol, gtol, callback, max_time=None, residual=None):
    clock0 = _time.perf_counter()
    deadline = None if max_time is None else clock0 + float(max_time)
    runlog = fitlog.run(run) if fitlog is not None else None
    rows = {"x": [], "loss": [], "evaluations": [], "time": [], "nonfinite": []}
    time_offset = 0.0
    restored = None
    if resume and runlog is not None and runlog.rows > 0:
        runlog.check(meta, x0)
        restored = runlog.restore()

    oracle = _Oracle(evaluate, max_evaluations, residual=residual if kind == "least_squares" else None)
    residual_view = None
    fn = oracle
    if kind == "least_squares" and optimizer.kind == "minimize":
        residual_view = fn = _LossFromResiduals(oracle)

    def elapsed():
        return time_offset + (_time.perf_counter() - clock0)

    def solution(x, state, reason, wall_time):
        residual = jacobian = None
        if kind == "least_squares":
            if hasattr(state, "residual"):
                residual = np.asarray(state.residual)
                # a Broyden-updated J is not the Jacobian: leave it unknown
                jacobian = np.asarray(state.jacobian) if int(getattr(state, "age", 0)) == 0 else None
            elif residual_view is not None and residual_view.current is not None:
                residual, jacobian = (np.asarray(a) for a in residual_view.current)
        history = History(**{k: np.asarray(v) for k, v in rows.items()})
        return Solution(x=np.asarray(x), loss=scalar(state.loss), grad=np.asarray(state.grad), reason=reason,
                        iterations=len(rows["loss"]) - 1, evaluations=oracle.evaluations,
                        nonfinite_evaluations=oracle.nonfinite, wall_time=wall_time, history=history,
                        state=state, residual=residual, jacobian=jacobian, run=run)

    def record(iteration, x, state):
        now = elapsed()
        for key, value in (("x", np.asarray(x)), ("loss", scalar(state.loss)), ("evaluations", oracle.evaluations),
                           ("time", now), ("nonfinite", oracle.nonfinite)):
            rows[key].append(value)
        if runlog is not None:
            runlog.append(iteration=iteration, x=x, loss=scalar(state.loss), evaluations=oracle.evaluations,
                          nonfinite=oracle.nonfinite, time=now, state=state_arrays(state))
        if callback is not None:
            callback(IterationInfo(iteration=iteration, x=np.asarray(x), loss=scalar(state.loss),
                                   grad=np.asarray(state.grad), state=state, evaluations=oracle.evaluations,
                                   time=now, run=run))

    if restored is not None:
        for key in rows:
            rows[key] = list(restored[key])
        x = jnp.asarray(restored["x"][-1])
        state = state_from_arrays(optimizer.State, restored["state"])
        oracle.evaluations = int(restored["evaluations"][-1])
        oracle.nonfinite = int(restored["nonfinite"][-1])
        time_offset = float(restored["time"][-1])
        finished = restored["finished"]
        if finished is not None:
            reason = Reason(finished["reason"])
            more_budget = ((reason == Reason.MAX_ITERATIONS and len(rows["loss"]) - 1 < max_iterations) or
                           (reason == Reason.MAX_EVALUATIONS and
                            (max_evaluations is None or finished["evaluations"] < max_evaluations)) or
                           reason == Reason.MAX_TIME)  # each call brings its own time budget
            if not more_budget:
                oracle.evaluations, oracle.nonfinite = finished["evaluations"], finished["nonfinite"]
                state = dataclasses.replace(state, status=host(finished["status"], np.int32))
                return solution(x, state, reason, finished["wall_time"])
            runlog.unfinish()
    else:
        if max_time is not None and float(max_time) <= 0.0:
            return _not_started(x0, run)
        if runlog is not None:
            runlog.begin(meta, x0, seed)
        x = x0
        try:
            state = optimizer.init(fn, x0)
        except _BudgetExhausted:  # cannot happen with max_evaluations >= 1; kept for clarity
            raise RuntimeError("no evaluation allowed for the starting point") from None
        if residual_view is not None:
            residual_view.accept(x)
        record(0, x, state)

    reason = None
    last_step = 0.0  # seconds the previous iteration of this call took (the time-budget forecast)
    while reason is None:
        done, reason = optimizer.terminate(state)
        if done:
            break
        reason = _tolerance_reason(rows["x"], rows["loss"], state.grad, ftol, xtol, gtol)
        if reason is not None:
            break
        if len(rows["loss"]) - 1 >= max_iterations:
            reason = Reason.MAX_ITERATIONS
            break
        if max_evaluations is not None and oracle.evaluations >= max_evaluations:
            reason = Reason.MAX_EVALUATIONS
            break
        step0 = _time.perf_counter()
        if deadline is not None and step0 + last_step > deadline:
            reason = Reason.MAX_TIME
            break
        try:
            x_new, state_new = optimizer.step(fn, x, state)
        except _BudgetExhausted:
            reason = Reason.MAX_EVALUATIONS
            break
        last_step = _time.perf_counter() - step0
        done, step_reason = optimizer.terminate(state_new)
        if done and x_new is x:
            state, reason = state_new, step_reason  # the step failed: x unchanged, not an iteration
            break
        if not math.isfinite(scalar(state_new.loss)):
            raise RuntimeError(f"{type(optimizer).__name__} accepted a non-finite loss; this is a bug")
        x, state = x_new, state_new
        if residual_view is not None:
            residual_view.accept(x)
        record(len(rows["loss"]), x, state)
        reason = None

    wall = elapsed()
    if runlog is not None:
        runlog.finish(reason.value, evaluations=oracle.evaluations, nonfinite=oracle.nonfinite, wall_time=wall,
                      status=int(state.status))
    return solution(x, state, reason, wall)
