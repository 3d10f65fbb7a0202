"""The transfers' scatter and gather with a batching rule that folds a vmap axis into the grid.

Under `jax.vmap`, JAX batches a scatter or gather by adding a batch dimension to its indices; the
rules here instead run one scatter (gather) over B copies of the grid laid end to end, each copy's
indices offset by its place, so a batch of rollouts transfers as one simulation of B times the
particles does. Each op is a `jax.custom_jvp` (linear: its tangent is the same op on the tangent)
around a `jax.custom_batching.custom_vmap`, so forward mode and vmap compose in either order.
Reverse mode is not defined through them: `Tuning.batch_fold` is for forward-mode programs.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

WINDOW_SCATTER = jax.lax.ScatterDimensionNumbers(update_window_dims=(1, 2), inserted_window_dims=(),
                                                 scatter_dims_to_operand_dims=(0,))
WINDOW_GATHER = jax.lax.GatherDimensionNumbers(offset_dims=(1, 2), collapsed_slice_dims=(), start_index_map=(0,))
IN_BOUNDS = jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS


def scatter_plain(zeros, idx, vals):
    """zeros (G, c) plus the windows vals (K, 3, c) added at rows idx (K,) .. idx + 2."""
    return jax.lax.scatter_add(zeros, idx[:, None], vals, WINDOW_SCATTER, mode=IN_BOUNDS)


def gather_plain(table, start):
    """Rows start .. start + 2 of table (G, c) per entry of start (K,): (K, 3, c)."""
    return jax.lax.gather(table, start[:, None], WINDOW_GATHER, (3, table.shape[1]), mode=IN_BOUNDS)


def _batched(args, flags, size):
    return tuple(a if b else jnp.broadcast_to(a, (size,) + a.shape) for a, b in zip(args, flags))


def _offsets(idx, size, rows):
    """idx (B, K) shifted to copy b's rows (b * rows) and flattened: (B K,)."""
    return (idx + (jnp.arange(size, dtype=idx.dtype) * rows)[:, None]).reshape(-1)


@custom_vmap
def _scatter(zeros, idx, vals):
    return scatter_plain(zeros, idx, vals)


@_scatter.def_vmap
def _scatter_rule(size, in_batched, zeros, idx, vals):
    zeros, idx, vals = _batched((zeros, idx, vals), in_batched, size)
    rows, c = zeros.shape[1:]
    out = _scatter(zeros.reshape(size * rows, c), _offsets(idx, size, rows), vals.reshape((-1,) + vals.shape[2:]))
    return out.reshape(size, rows, c), True


@custom_vmap
def _gather(table, start):
    return gather_plain(table, start)


@_gather.def_vmap
def _gather_rule(size, in_batched, table, start):
    table, start = _batched((table, start), in_batched, size)
    rows, c = table.shape[1:]
    out = _gather(table.reshape(size * rows, c), _offsets(start, size, rows))
    return out.reshape(size, -1, 3, c), True


@jax.custom_jvp
def scatter_folded(zeros, idx, vals):
    """`scatter_plain` whose vmap runs one scatter over the batch's grids end to end."""
    return _scatter(zeros, idx, vals)


@scatter_folded.defjvp
def _scatter_folded_jvp(primals, tangents):
    zeros, idx, vals = primals
    dzeros, _, dvals = tangents
    return _scatter(zeros, idx, vals), _scatter(dzeros, idx, dvals)


@jax.custom_jvp
def gather_folded(table, start):
    """`gather_plain` whose vmap runs one gather over the batch's grids end to end."""
    return _gather(table, start)


@gather_folded.defjvp
def _gather_folded_jvp(primals, tangents):
    table, start = primals
    return _gather(table, start), _gather(tangents[0], start)
