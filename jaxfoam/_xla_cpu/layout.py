"""The substep's memory layout: the state as per-component (N,) arrays, and particles sorted by cell.

Inside a rollout the state stays in component form from one substep to the next (structure of arrays);
XLA:CPU evaluates shared per-particle expressions once per matrix entry when they are packed into
(N, d, d) arrays (docs/performance.md).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from .. import _tensor as T
from .._grid import Grid, _flat_index, _stencil
from .._state import State


def _bbar_pack(b, d):
    """The independent components of a symmetric bbar_e given as 3x3 components: the upper
    triangle (6 arrays) in 3D; in 2D plane strain (xz = yz = 0 exactly) xx, xy, yy, zz."""
    if d == 2:
        return (b[0][0], b[0][1], b[1][1], b[2][2])
    return (b[0][0], b[0][1], b[0][2], b[1][1], b[1][2], b[2][2])


def _bbar_comps(b):
    """3x3 components of bbar_e from an (N, 3, 3) array, from `_bbar_pack`'s tuple (the plane-strain
    zeros as constants, which the component algebra folds away) or from 3x3 components (as is)."""
    if not isinstance(b, tuple):
        return T.comps(b)
    if isinstance(b[0], tuple):
        return b
    if len(b) == 4:
        xx, xy, yy, zz = b
        return ((xx, xy, 0.0), (xy, yy, 0.0), (0.0, 0.0, zz))
    xx, xy, xz, yy, yz, zz = b
    return ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))


def to_components(state: State) -> State:
    """The substep's working form: C and F as tuples of rows of (N,) component arrays, bbar_e as the
    tuple of its independent components (symmetric; in 2D plane strain xx, xy, yy, zz only, the
    plane-strain zeros as constants that the component algebra folds away).
    """
    if isinstance(state.F, tuple):
        return state
    return state.replace(C=T.comps(state.C), F=T.comps(state.F),
                         bbar_e=_bbar_pack(T.comps(state.bbar_e), state.dim))


def from_components(state: State) -> State:
    """Inverse of `to_components`: the public form with (N, d, d) and (N, 3, 3) arrays."""
    if not isinstance(state.F, tuple):
        return state
    like = state.x[:, 0]
    return state.replace(C=T.array(state.C, like), F=T.array(state.F, like),
                         bbar_e=T.array(_bbar_comps(state.bbar_e), like))


def _permute(state: State, perm) -> State:
    """Every per-particle leaf (full or component form) reordered as leaf[perm]; t unchanged."""
    return jax.tree_util.tree_map(lambda a: a[perm] if jnp.ndim(a) >= 1 else a, state)


def sort_by_cell(state: State, grid: Grid) -> tuple[State, jax.Array]:
    """The particles reordered by grid cell (row-major cell index; inactive slots last).

    Returns (sorted state, perm) with sorted = original[perm]; `unsort(sorted, perm)` restores the
    order. Particles that share a stencil then scatter to and gather from neighbouring memory
    (experiments/bench_step.md measures it).
    The permutation is data, not differentiated: gradients flow through the reordering unchanged.
    """
    base = _stencil(jax.lax.stop_gradient(state.x), grid)[0]
    key = jnp.where(state.active, _flat_index(base, (0,) * grid.dim, grid), grid.num_nodes)
    perm = jnp.argsort(key, stable=True)
    return _permute(state, perm), perm


def unsort(state: State, perm) -> State:
    """Inverse of `sort_by_cell`: the slots back in their original order."""
    inv = jnp.zeros_like(perm).at[perm].set(jnp.arange(perm.shape[0], dtype=perm.dtype))
    return _permute(state, inv)


def _comps(a):
    return a if isinstance(a, tuple) else T.comps(a)

