"""Adam (Kingma & Ba 2015), written directly in JAX: one gradient evaluation per iteration."""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._base import RUNNING, AbstractOptimizer, as_array, check_positive, check_unit_interval, scalar, host
from ._solution import Reason, reason_code


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AdamState:
    """Adam state at the current iterate x (p parameters).

    Attributes:
      loss: loss at x, objective units, scalar.
      grad: gradient of the loss at x, (p,).
      m: first-moment (mean) estimate of the gradient, (p,).
      v: second-moment (uncentred variance) estimate of the gradient, (p,).
      t: number of moment updates so far, integer scalar.
      lr_scale: multiplier on the learning rate, halved (by `shrink`) each time a trial is non-finite, scalar.
      status: `fitting.optim.Reason` code, integer scalar.
    """

    loss: jax.Array
    grad: jax.Array
    m: jax.Array
    v: jax.Array
    t: jax.Array
    lr_scale: jax.Array
    status: jax.Array


@functools.partial(jax.jit, static_argnames=("beta1", "beta2", "eps"))
def _adam_update(x, grad, m, v, t, lr, lr_scale, *, beta1, beta2, eps):
    """New moments, the bias-corrected Adam step dx = -lr * mhat / (sqrt(vhat) + eps) and x + lr_scale dx."""
    m = beta1 * m + (1 - beta1) * grad
    v = beta2 * v + (1 - beta2) * grad * grad
    tf = t.astype(grad.dtype)
    m_hat = m / (1 - beta1**tf)
    v_hat = v / (1 - beta2**tf)
    dx = -lr * m_hat / (jnp.sqrt(v_hat) + eps)
    return m, v, dx, x + lr_scale * dx


@dataclasses.dataclass(frozen=True)
class Adam(AbstractOptimizer):
    """Adam with an optional inverse-time learning-rate decay.

    The step is x <- x - lr_t * mhat / (sqrt(vhat) + eps) with lr_t = learning_rate / (1 + t / decay_steps)
    (no decay when decay_steps is None). A trial whose loss is not finite is rejected and the step
    multiplied by `shrink` (up to `max_shrinks` times); the reduction is kept for later iterations.

    Attributes:
      learning_rate: step size in the units of x (x is usually a transformed, dimensionless coordinate).
      beta1, beta2: decay rates of the first and second moment estimates, in [0, 1).
      eps: added to sqrt(vhat), in gradient units; keeps the step bounded where the gradient vanishes.
      decay_steps: iterations over which the learning rate halves (inverse-time decay), or None.
      shrink: step multiplier after a non-finite trial, in (0, 1).
      max_shrinks: non-finite trials tolerated in one iteration before stopping with `nonfinite`.
    """

    learning_rate: float = 1e-2
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    decay_steps: float | None = None
    shrink: float = 0.5
    max_shrinks: int = 30

    kind = "minimize"
    State = AdamState

    def __post_init__(self):
        check_positive("Adam.learning_rate", self.learning_rate)
        check_unit_interval("Adam.beta1", self.beta1)
        check_unit_interval("Adam.beta2", self.beta2)
        check_positive("Adam.eps", self.eps)
        if self.decay_steps is not None:
            check_positive("Adam.decay_steps", self.decay_steps)
        check_unit_interval("Adam.shrink", self.shrink, closed_left=False)
        if int(self.max_shrinks) < 0:
            raise ValueError(f"Adam.max_shrinks must be >= 0, got {self.max_shrinks!r}")

    def init(self, fn, x0):
        loss, grad = fn(x0)
        status = RUNNING if math.isfinite(scalar(loss)) else reason_code(Reason.NONFINITE)
        zeros = host(np.zeros(x0.shape, x0.dtype))
        return AdamState(loss=as_array(loss), grad=as_array(grad), m=zeros, v=zeros,
                         t=host(0, np.int32), lr_scale=host(1.0, x0.dtype),
                         status=host(status, np.int32))

    def step(self, fn, x, state):
        t = int(state.t) + 1
        lr = self.learning_rate
        if self.decay_steps is not None:
            lr = lr / (1.0 + t / self.decay_steps)
        lr_scale = float(state.lr_scale)
        t_arr = host(t, np.int32)
        m, v, dx, x_new = _adam_update(x, state.grad, state.m, state.v, t_arr, host(lr, x.dtype),
                                       state.lr_scale, beta1=float(self.beta1), beta2=float(self.beta2),
                                       eps=float(self.eps))
        x_host, dx_host = np.asarray(x), np.asarray(dx)
        for k in range(int(self.max_shrinks) + 1):
            if k > 0:  # the last trial was not finite: shrink the step, and keep it shrunk
                lr_scale *= self.shrink
                x_new = host(x_host + lr_scale * dx_host)
            loss, grad = fn(x_new)
            if math.isfinite(scalar(loss)):
                return x_new, AdamState(loss=as_array(loss), grad=as_array(grad), m=m, v=v, t=t_arr,
                                        lr_scale=host(lr_scale, x.dtype), status=state.status)
        return x, dataclasses.replace(state, status=host(reason_code(Reason.NONFINITE), np.int32))
