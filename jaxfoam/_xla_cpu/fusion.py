"""Fusion boundaries for XLA:CPU: where recomputation inside a fused kernel costs more than a buffer.

XLA fuses elementwise producers into their consumers and recomputes them per consumer element. Three
cases in the MPM substep cost far more than materializing the value once:

- Scalars (a plate's position, sin and cos of the time) broadcast into a grid-sized kernel are
  recomputed per grid node.
- Each stencil offset's grid index is recomputed from the positions (floor, convert, strides) in
  its own fused kernel unless the base index is computed once per substep.
- In reverse mode the transpose of particle-to-grid is a gather of the grid cotangent (9 stencil
  offsets x particles x (d + 1) values); XLA fuses the whole transposed grid update (colliders,
  momentum / mass) into that gather and runs it once per gathered value, not once per node.
The gains are measured in docs/performance.md.

`jax.lax.optimization_barrier` does not help: XLA:CPU removes it before fusion (checked on jaxlib
0.10.2: the compiled HLO has no opt-barrier left). A `lax.cond` on a runtime predicate is kept, and
its operands and results are buffers. Each helper below uses one; the predicate is true for every
finite time or time step, and the other branch only returns what a non-finite time would give.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def hoist(tree, t):
    """`tree` (arrays computed once, e.g. from the time t, s) as materialized buffers.

    Identity for finite t; otherwise NaN for floating-point leaves (as sin(t) would give) and 0 for
    integer ones (a valid grid index). Differentiable (the JVP of a cond is a cond)."""
    def other(a):
        return jax.tree_util.tree_map(
            lambda x: jnp.full_like(x, jnp.nan) if jnp.issubdtype(x.dtype, jnp.inexact) else jnp.zeros_like(x), a)
    return jax.lax.cond(jnp.isfinite(t), lambda a: a, other, tree)


@jax.custom_jvp
def materialize_tangent(a, dt):
    """Identity on `a` (an array or a tuple of arrays); its tangent (and so, transposed, its
    cotangent) passes through a `lax.cond` on the runtime predicate isfinite(dt), which XLA:CPU
    keeps as a fusion boundary. The primal computation is untouched: only derivative programs get
    the buffer. dt may be an array (e.g. per-particle time steps): the predicate is that all of it
    is finite."""
    return a


@materialize_tangent.defjvp
def _materialize_tangent_jvp(primals, tangents):
    a, dt = primals
    zeros = lambda t: jax.tree_util.tree_map(jnp.zeros_like, t)
    ta = jax.lax.cond(jnp.all(jnp.isfinite(dt)), lambda t: t, zeros, tangents[0])
    return a, ta


@jax.custom_jvp
def materialize_linearization(a, dt):
    """Identity on `a`, like `materialize_tangent`, but in derivative programs the primal value
    passes through the cond with its tangent: a buffer that the tangent's consumers read instead of
    recomputing `a` per tangent element. The primal program is untouched."""
    return a


@materialize_linearization.defjvp
def _materialize_linearization_jvp(primals, tangents):
    a, dt = primals

    def other(p, t):
        nan = jax.tree_util.tree_map(lambda x: jnp.full_like(x, jnp.nan), p)
        return nan, jax.tree_util.tree_map(jnp.zeros_like, t)
    return jax.lax.cond(jnp.all(jnp.isfinite(dt)), lambda p, t: (p, t), other, a, tangents[0])
