"""Particle state of a simulation: a frozen pytree with a fixed capacity and an active mask."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """Material points at one instant. N is the capacity, d the dimension (2 or 3).

    Attributes:
      t: simulated time, s, scalar.
      x: positions, m, (N, d).
      v: velocities, m/s, (N, d).
      C: APIC / MLS-MPM affine velocity matrix (the particle's velocity gradient), 1/s, (N, d, d).
      F: deformation gradient, dimensionless, (N, d, d); in 2D plane strain F_zz = 1 is implicit.
      bbar_e: volume-preserving elastic left Cauchy-Green tensor, dimensionless, (N, 3, 3), det = 1.
      vol0: initial volume, m^3 (m^2 per metre of depth in 2D), (N,).
      mass: mass, kg (kg per metre of depth in 2D), (N,).
      gamma_dot: Herschel-Bulkley plastic rate of the last step, 1/s, (N,).
      active: whether the slot holds a material point, bool, (N,).
    """

    t: jax.Array
    x: jax.Array
    v: jax.Array
    C: jax.Array
    F: jax.Array
    bbar_e: jax.Array
    vol0: jax.Array
    mass: jax.Array
    gamma_dot: jax.Array
    active: jax.Array

    @property
    def dim(self) -> int:
        return self.x.shape[-1]

    @property
    def capacity(self) -> int:
        return self.x.shape[0]

    def replace(self, **changes) -> "State":
        return dataclasses.replace(self, **changes)


def make_state(x, vol0, mass, v=None, capacity=None, dtype=None, t=0.0) -> State:
    """A state at rest (F = I, bbar_e = I) from positions, volumes and masses.

    Args:
      x: (n, d) positions, m.  vol0: (n,) volumes, m^3.  mass: (n,) masses, kg.
      v: optional (n, d) or (d,) initial velocity, m/s.
      capacity: total slots N >= n; slots past n are inactive (zero mass and volume).
      dtype: float dtype of the state (default: that of x).
    """
    x = jnp.asarray(x, dtype)
    n, d = x.shape
    dtype = x.dtype
    cap = n if capacity is None else int(capacity)
    if cap < n:
        raise ValueError(f"capacity must be >= the number of particles ({n}), got {cap}")
    pad = cap - n

    def fill(a, value=0.0):
        a = jnp.asarray(a, dtype)
        return jnp.concatenate([a, jnp.full((pad,) + a.shape[1:], value, dtype)]) if pad else a

    v = jnp.zeros((n, d), dtype) if v is None else jnp.broadcast_to(jnp.asarray(v, dtype), (n, d))
    # Inactive slots sit at the first particle's position so every stencil index stays in range.
    x_all = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, d))]) if pad else x
    return State(
        t=jnp.asarray(t, dtype),
        x=x_all,
        v=fill(v),
        C=jnp.zeros((cap, d, d), dtype),
        F=jnp.broadcast_to(jnp.eye(d, dtype=dtype), (cap, d, d)),
        bbar_e=jnp.broadcast_to(jnp.eye(3, dtype=dtype), (cap, 3, 3)),
        vol0=fill(vol0),
        mass=fill(mass),
        gamma_dot=jnp.zeros((cap,), dtype),
        active=jnp.arange(cap) < n,
    )
