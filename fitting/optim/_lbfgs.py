"""L-BFGS (Nocedal & Wright 2006, Alg. 7.4/7.5) with a strong-Wolfe line search (Alg. 3.5/3.6).

A method is a descent (the two-loop recursion gives the quasi-Newton direction) times a search (the
line search picks the step length). Every trial evaluation returns value and gradient together, so the
accepted point's gradient is never recomputed.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._base import RUNNING, AbstractOptimizer, as_array, check_positive, scalar, host
from ._solution import Reason, reason_code

# Safeguard of the interpolated trial inside a zoom bracket: stay this fraction of the bracket away from
# its ends, so a degenerate cubic cannot stall the bracket (Nocedal & Wright 2006, sec. 3.5).
_ZOOM_MARGIN = 0.1
# Extrapolation factor of the bracketing phase when the trial is still too short.
_EXTRAPOLATE = 2.0


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LBFGSState:
    """L-BFGS state at the current iterate x (p parameters, M = history size).

    Attributes:
      loss: loss at x, objective units, scalar.
      grad: gradient at x, (p,).
      s_hist: the last M steps x_{k+1} - x_k, oldest first, (M, p); rows before M - count are unused.
      y_hist: the matching gradient changes g_{k+1} - g_k, (M, p).
      count: number of valid (s, y) pairs, integer scalar in [0, M].
      status: `fitting.optim.Reason` code, integer scalar.
    """

    loss: jax.Array
    grad: jax.Array
    s_hist: jax.Array
    y_hist: jax.Array
    count: jax.Array
    status: jax.Array


@jax.jit
def _two_loop(grad, s_hist, y_hist, count):
    """Quasi-Newton direction -H grad from the (s, y) pairs (two-loop recursion, H0 = gamma I).

    Unused rows (before M - count) get rho = 0 and drop out of both loops.
    """
    M = s_hist.shape[0]
    valid = jnp.arange(M, dtype=jnp.asarray(count).dtype) >= M - count
    sy = jnp.sum(s_hist * y_hist, axis=1)
    rho = jnp.where(valid, 1.0 / jnp.where(valid, sy, 1.0), 0.0)

    def newest_first(q, pair):
        s, y, rho_i = pair
        alpha = rho_i * jnp.dot(s, q)
        return q - alpha * y, alpha

    q, alphas = jax.lax.scan(newest_first, grad, (s_hist, y_hist, rho), reverse=True)
    yy = jnp.dot(y_hist[-1], y_hist[-1])
    has = count > 0
    gamma = jnp.where(has, sy[-1] / jnp.where(has, yy, 1.0), 1.0)

    def oldest_first(r, pair):
        s, y, rho_i, alpha = pair
        beta = rho_i * jnp.dot(y, r)
        return r + s * (alpha - beta), None

    r, _ = jax.lax.scan(oldest_first, gamma * q, (s_hist, y_hist, rho, alphas))
    return -r


@jax.jit
def _push(s_hist, y_hist, count, s, y):
    """Append a pair (dropping the oldest when full)."""
    s_hist = jnp.concatenate([s_hist[1:], s[None, :]], axis=0)
    y_hist = jnp.concatenate([y_hist[1:], y[None, :]], axis=0)
    return s_hist, y_hist, jnp.minimum(count + 1, s_hist.shape[0])


def _cubic_min(a_lo, f_lo, d_lo, a_hi, f_hi, d_hi):
    """Minimizer of the cubic through two points with slopes (N&W eq. 3.59), or nan if it has none."""
    if not all(math.isfinite(v) for v in (f_lo, d_lo, f_hi, d_hi)) or a_hi == a_lo:
        return math.nan
    d1 = d_lo + d_hi - 3.0 * (f_lo - f_hi) / (a_lo - a_hi)
    disc = d1 * d1 - d_lo * d_hi
    if disc < 0:
        return math.nan
    d2 = math.copysign(math.sqrt(disc), a_hi - a_lo)
    denom = d_hi - d_lo + 2.0 * d2
    if denom == 0:
        return math.nan
    return a_hi - (a_hi - a_lo) * (d_hi + d2 - d1) / denom


@dataclasses.dataclass(frozen=True)
class LBFGS(AbstractOptimizer):
    """Limited-memory BFGS with a strong-Wolfe line search.

    Attributes:
      history: number M of (s, y) pairs kept.
      c1: sufficient-decrease (Armijo) constant, in (0, c2).
      c2: curvature constant of the strong Wolfe condition, in (c1, 1); 0.9 is usual for quasi-Newton.
      initial_step: length (max-norm, units of x) of the first trial step when there is no curvature
        history yet (first iteration, or after a reset); later iterations try the quasi-Newton step 1.
      max_line_search: evaluations allowed in one line search before it gives up.
    """

    history: int = 10
    c1: float = 1e-4
    c2: float = 0.9
    initial_step: float = 0.1
    max_line_search: int = 20

    kind = "minimize"
    State = LBFGSState

    def __post_init__(self):
        if int(self.history) < 1:
            raise ValueError(f"LBFGS.history must be >= 1, got {self.history!r}")
        if not 0.0 < self.c1 < self.c2 < 1.0:
            raise ValueError(f"LBFGS needs 0 < c1 < c2 < 1, got c1={self.c1!r}, c2={self.c2!r}")
        check_positive("LBFGS.initial_step", self.initial_step)
        if int(self.max_line_search) < 1:
            raise ValueError(f"LBFGS.max_line_search must be >= 1, got {self.max_line_search!r}")

    def init(self, fn, x0):
        loss, grad = fn(x0)
        status = RUNNING if math.isfinite(scalar(loss)) else reason_code(Reason.NONFINITE)
        hist = host(np.zeros((int(self.history), x0.shape[0]), x0.dtype))
        return LBFGSState(loss=as_array(loss), grad=as_array(grad), s_hist=hist, y_hist=hist,
                          count=host(0, np.int32), status=host(status, np.int32))

    def step(self, fn, x, state):
        s_hist, y_hist, count = state.s_hist, state.y_hist, state.count
        x_host, g_host = np.asarray(x), np.asarray(state.grad)
        tiny = np.finfo(np.float64).tiny
        for _ in range(2):  # a failed quasi-Newton search is retried once along -grad
            d = None
            if int(count) > 0:
                d = np.asarray(_two_loop(state.grad, s_hist, y_hist, count))
                dphi0 = float(g_host @ d)
                alpha0 = 1.0
                if not (dphi0 < 0 and math.isfinite(dphi0)):  # not a descent direction: forget the history
                    d = None
            if d is None:
                count = host(0, np.int32)
                d = -g_host
                dphi0 = float(g_host @ d)
                alpha0 = self.initial_step / max(float(np.max(np.abs(d))), tiny)
            found, all_nonfinite, x_new, loss, grad = self._line_search(fn, x_host, scalar(state.loss), dphi0, d,
                                                                        alpha0)
            if found:
                s = np.asarray(x_new) - x_host
                y = np.asarray(grad) - g_host
                sy, yy = float(s @ y), float(y @ y)
                if sy > 0 and sy > np.finfo(np.float64).eps * yy:  # keep H positive definite
                    s_hist, y_hist, count = _push(s_hist, y_hist, count, host(s), host(y))
                return x_new, LBFGSState(loss=as_array(loss), grad=as_array(grad), s_hist=s_hist,
                                         y_hist=y_hist, count=count, status=state.status)
            if int(count) == 0:
                break
            count = host(0, np.int32)
        reason = Reason.NONFINITE if all_nonfinite else Reason.STALLED
        return x, dataclasses.replace(state, status=host(reason_code(reason), np.int32))

    def _line_search(self, fn, x, f0, dphi0, d, alpha0):
        """Strong-Wolfe search along d from x (host arrays); returns (found, all_nonfinite, x_new, loss, grad).

        A non-finite trial counts as an infinitely high loss: it fails the sufficient-decrease test, so
        the bracket shrinks toward the last good point (by bisection, since it cannot be interpolated).
        """
        c1, c2 = self.c1, self.c2
        budget = [int(self.max_line_search)]
        finite_seen = [False]
        best = [None]  # lowest point satisfying sufficient decrease, the fallback if no Wolfe point is found

        def evaluate(a):
            budget[0] -= 1
            xa = host(x + a * d)
            fa, ga = fn(xa)
            fa = scalar(fa)
            da = float(np.asarray(ga) @ d) if math.isfinite(fa) else math.nan
            if math.isfinite(fa):
                finite_seen[0] = True
                if fa <= f0 + c1 * a * dphi0 and fa < f0 and (best[0] is None or fa < best[0][1]):
                    best[0] = (xa, fa, ga)
            return xa, fa, ga, da

        def fallback():
            if best[0] is not None:
                return True, False, *best[0]
            return False, not finite_seen[0], None, None, None

        def zoom(lo, hi):
            # lo, hi: (alpha, f, dphi); lo satisfies sufficient decrease and has the lowest f so far.
            while budget[0] > 0:
                a_lo, f_lo, d_lo = lo
                a_hi, f_hi, d_hi = hi
                width = a_hi - a_lo
                if abs(width) <= np.finfo(np.float64).eps * max(abs(a_lo), abs(a_hi)):
                    break
                a = _cubic_min(a_lo, f_lo, d_lo, a_hi, f_hi, d_hi)
                lo_edge, hi_edge = a_lo + _ZOOM_MARGIN * width, a_hi - _ZOOM_MARGIN * width
                lo_b, hi_b = min(lo_edge, hi_edge), max(lo_edge, hi_edge)
                if not math.isfinite(a) or not lo_b <= a <= hi_b:
                    a = 0.5 * (a_lo + a_hi)
                xa, fa, ga, da = evaluate(a)
                if not math.isfinite(fa) or fa > f0 + c1 * a * dphi0 or fa >= f_lo:
                    hi = (a, fa, da)
                else:
                    if abs(da) <= -c2 * dphi0:
                        return True, False, xa, fa, ga
                    if da * (a_hi - a_lo) >= 0:
                        hi = lo
                    lo = (a, fa, da)
            return fallback()

        prev = (0.0, f0, dphi0)
        a = alpha0
        first = True
        while budget[0] > 0:
            xa, fa, ga, da = evaluate(a)
            if not math.isfinite(fa) or fa > f0 + c1 * a * dphi0 or (not first and fa >= prev[1]):
                return zoom(prev, (a, fa, da))
            if abs(da) <= -c2 * dphi0:
                return True, False, xa, fa, ga
            if da >= 0:
                return zoom((a, fa, da), prev)
            prev = (a, fa, da)
            a = a * _EXTRAPOLATE
            first = False
        return fallback()
