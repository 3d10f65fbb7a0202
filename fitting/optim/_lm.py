"""Levenberg-Marquardt: damped Gauss-Newton on a residual vector with Nielsen's damping update.

Loss L(x) = 0.5 * |r(x)|^2. Each trial solves (J^T J + mu D) h = -J^T r with D the running maximum of
diag(J^T J) (Moré's scaling, which makes the damping invariant to rescaling a parameter), evaluates
(r, J) at x + h in one call, and accepts the trial when the actual decrease is positive. The gain ratio
rho = actual / predicted decrease drives Nielsen's update (Madsen, Nielsen & Tingleff 2004, eq. 3.16):
on acceptance mu *= max(1/3, 1 - (2 rho - 1)^3), nu = 2; on rejection mu *= nu, nu *= 2.

With `broyden_steps` = k > 0 and an objective that also evaluates residuals alone (`fn.residual`), a
trial costs one residual: J is carried by Broyden's rank-1 update J += (r_new - r - J h) h^T / h^T h
(Madsen, Nielsen & Tingleff 2004, sec. 3.4) and evaluated exactly again after k accepted steps, after a
rejected trial, and before the model's predicted decrease may end the run.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import jax.scipy.linalg  # noqa: F401  (cho_factor / cho_solve)
import numpy as np

from ._base import RUNNING, AbstractOptimizer, as_array, check_positive, scalar, host
from ._solution import Reason, reason_code

# A predicted decrease below this multiple of eps * loss (eps of the parameters' dtype) is round-off:
# the point cannot be improved.
_ROUNDOFF_FACTOR = 16.0
# Floor of the scaling D relative to its largest entry, so a parameter the residuals ignore (zero column
# of J) still gets a damped, finite step.
_SCALE_FLOOR = 1e-12


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LMState:
    """Levenberg-Marquardt state at the current iterate x (n residuals, p parameters).

    Attributes:
      loss: 0.5 * |r|^2 at x, scalar (units of r squared).
      grad: J^T r, gradient of the loss at x, (p,).
      residual: r(x), (n,).
      jacobian: dr/dx at x, (n, p).
      damping: mu, dimensionless (relative to the scaling D), scalar.
      nu: Nielsen's rejection growth factor, scalar.
      scale: D, running maximum of diag(J^T J), (p,).
      status: `fitting.optim.Reason` code, integer scalar.
      age: accepted steps since J was last evaluated exactly (0: J is exact at x), integer scalar.
    """

    loss: jax.Array
    grad: jax.Array
    residual: jax.Array
    jacobian: jax.Array
    damping: jax.Array
    nu: jax.Array
    scale: jax.Array
    status: jax.Array
    age: jax.Array = dataclasses.field(default_factory=lambda: np.zeros((), np.int32))


@jax.jit
def _broyden(jacobian, residual, residual_new, h):
    """Broyden's rank-1 update of J along the step h (the secant condition J_new h = r_new - r)."""
    return jacobian + jnp.outer(residual_new - residual - jacobian @ h, h) / jnp.dot(h, h)


@jax.jit
def _normal_equations(residual, jacobian, scale_prev):
    """J^T J, J^T r and the updated scaling D = max(D_prev, diag(J^T J), floor)."""
    jtj = jacobian.T @ jacobian
    grad = jacobian.T @ residual
    scale = jnp.maximum(scale_prev, jnp.diagonal(jtj))
    scale = jnp.maximum(scale, _SCALE_FLOOR * jnp.max(scale) + jnp.finfo(scale.dtype).tiny)
    return jtj, grad, scale


@jax.jit
def _damped_step(x, jtj, grad, scale, damping):
    """Solve (J^T J + mu D) h = -J^T r (Cholesky: the matrix is SPD for mu > 0); return x + h, h and the
    predicted decrease 0.5 h.(mu D h - J^T r) of the Gauss-Newton model."""
    a = jtj + damping * jnp.diag(scale)
    h = -jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), grad)
    predicted = 0.5 * jnp.dot(h, damping * scale * h - grad)
    return x + h, h, predicted


@jax.jit
def _half_sq(residual):
    return 0.5 * jnp.dot(residual, residual)


@dataclasses.dataclass(frozen=True)
class LevenbergMarquardt(AbstractOptimizer):
    """Levenberg-Marquardt with Nielsen's damping update.

    Attributes:
      initial_damping: mu at the start, relative to the scaling D (1e-3 trusts Gauss-Newton early).
      max_damping: a step is given up (status `stalled`) when mu exceeds this.
      max_rejections: rejected trials allowed in one iteration before stopping with `stalled`
        (or `nonfinite` when all of them were non-finite).
      broyden_steps: 0 evaluates (r, J) at every trial; k > 0 evaluates residuals alone at the trials and
        updates J by Broyden's rule, evaluating it exactly after k accepted steps (see the module's
        docstring); an objective without `residual` gets exact Jacobians.
    """

    initial_damping: float = 1e-3
    max_damping: float = 1e16
    max_rejections: int = 40
    broyden_steps: int = 0

    kind = "least_squares"
    State = LMState

    def __post_init__(self):
        check_positive("LevenbergMarquardt.initial_damping", self.initial_damping)
        check_positive("LevenbergMarquardt.max_damping", self.max_damping)
        if int(self.max_rejections) < 1:
            raise ValueError(f"LevenbergMarquardt.max_rejections must be >= 1, got {self.max_rejections!r}")
        if isinstance(self.broyden_steps, bool) or not isinstance(self.broyden_steps, (int, np.integer)) \
                or int(self.broyden_steps) < 0:
            raise ValueError(f"LevenbergMarquardt.broyden_steps must be an integer >= 0, got "
                             f"{self.broyden_steps!r}")

    def config(self) -> dict:
        cfg = super().config()
        if not self.broyden_steps:
            del cfg["broyden_steps"]  # logs written before the option resume with exact Jacobians
        return cfg

    def init(self, fn, x0):
        r, jac = fn(x0)
        r, jac = as_array(r), as_array(jac)
        if jac.ndim != 2 or jac.shape != (r.shape[0], x0.shape[0]):
            raise ValueError(f"least-squares oracle must return r (n,) and J (n, p={x0.shape[0]}), got shapes "
                             f"{r.shape} and {jac.shape}")
        _, grad, scale = _normal_equations(r, jac, host(np.zeros(x0.shape, x0.dtype)))
        loss = _half_sq(r)
        status = RUNNING if math.isfinite(scalar(loss)) else reason_code(Reason.NONFINITE)
        return LMState(loss=loss, grad=grad, residual=r, jacobian=jac,
                       damping=host(self.initial_damping, x0.dtype), nu=host(2.0, x0.dtype),
                       scale=scale, status=host(status, np.int32))

    def step(self, fn, x, state):
        # Broyden's updates need residuals alone; without them every trial evaluates (r, J).
        residual_only = getattr(fn, "residual", None) if self.broyden_steps else None
        if residual_only is not None and int(state.age) >= int(self.broyden_steps):
            state = self._exact(fn, x, state)

        def model(state):
            return state, _normal_equations(state.residual, state.jacobian, state.scale), scalar(state.loss)

        state, (jtj, grad, scale), loss = model(state)
        damping, nu = scalar(state.damping), scalar(state.nu)
        x_host = np.asarray(x)
        eps = float(np.finfo(x_host.dtype).eps)
        all_nonfinite = True
        reason = Reason.STALLED
        for _ in range(int(self.max_rejections)):
            x_new, h, predicted = _damped_step(x, jtj, grad, scale, host(damping, x.dtype))
            predicted = scalar(predicted)
            tiny = not predicted > _ROUNDOFF_FACTOR * eps * loss  # nothing left to gain at this precision
            if tiny or np.array_equal(np.asarray(x_new), x_host):  # or the step is below x's resolution
                if int(state.age) > 0:  # an approximate model does not decide convergence
                    state, (jtj, grad, scale), loss = model(self._exact(fn, x, state))
                    continue
                reason, all_nonfinite = (Reason.CONVERGED_FTOL if tiny else Reason.CONVERGED_XTOL), False
                break
            if residual_only is None:
                r_new, jac_new = fn(x_new)
                r_new, jac_new = as_array(r_new), as_array(jac_new)
            else:
                r_new, jac_new = as_array(residual_only(x_new)), None
            loss_new = _half_sq(r_new)
            loss_new_host = scalar(loss_new)
            if math.isfinite(loss_new_host):
                all_nonfinite = False
            rho = (loss - loss_new_host) / predicted if math.isfinite(loss_new_host) else -math.inf
            if rho > 0:
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                age = 0 if jac_new is not None else int(state.age) + 1
                if jac_new is None:
                    jac_new = _broyden(state.jacobian, state.residual, r_new, h)
                _, grad_new, _ = _normal_equations(r_new, jac_new, scale)
                return x_new, LMState(loss=loss_new, grad=grad_new, residual=r_new, jacobian=jac_new,
                                      damping=host(damping, x.dtype), nu=host(2.0, x.dtype), scale=scale,
                                      status=state.status, age=host(age, np.int32))
            damping *= nu
            nu *= 2.0
            if damping > self.max_damping:
                break
            if int(state.age) > 0:  # the failed trial may be the model's fault: evaluate J exactly
                state, (jtj, grad, scale), loss = model(self._exact(fn, x, state))
        if all_nonfinite and reason == Reason.STALLED:
            reason = Reason.NONFINITE
        return x, dataclasses.replace(state, damping=host(damping, x.dtype), nu=host(nu, x.dtype),
                                      scale=scale, status=host(reason_code(reason), np.int32))

    def _exact(self, fn, x, state):
        """The state with (r, J) evaluated exactly at x (damping kept)."""
        r, jac = fn(x)
        r, jac = as_array(r), as_array(jac)
        return dataclasses.replace(state, loss=_half_sq(r), residual=r, jacobian=jac, age=host(0, np.int32))
