"""The batch-folding scatter and gather (`jaxfoam._xla_cpu.fold`, `Tuning.batch_fold`).

Contract: under `jax.vmap`, in either order with `jax.jvp`, the folded ops give what JAX's own batching
of the plain ops gives (exactly: the same additions in the same order per node).
"""
import jax
import jax.numpy as jnp
import numpy as np

from jaxfoam._xla_cpu.fold import gather_folded, gather_plain, scatter_folded, scatter_plain

B, G, K, C = 3, 40, 25, 4


def _data(seed=0):
    rng = np.random.default_rng(seed)
    idx = jnp.asarray(rng.integers(0, G - 2, size=(B, K)), jnp.int32)
    vals = jnp.asarray(rng.normal(size=(B, K, 3, C)))
    table = jnp.asarray(rng.normal(size=(B, G, C)))
    return idx, vals, table


def test_folded_scatter_and_gather_equal_jax_batching_under_vmap():
    idx, vals, table = _data()
    zeros = jnp.zeros((G, C))
    got = jax.vmap(lambda i, v: scatter_folded(zeros, i, v))(idx, vals)
    want = jax.vmap(lambda i, v: scatter_plain(zeros, i, v))(idx, vals)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    np.testing.assert_array_equal(np.asarray(jax.vmap(gather_folded)(table, idx)),
                                  np.asarray(jax.vmap(gather_plain)(table, idx)))
    # an unbatched index with batched values, and the unbatched call itself
    np.testing.assert_array_equal(np.asarray(jax.vmap(lambda v: scatter_folded(zeros, idx[0], v))(vals)),
                                  np.asarray(jax.vmap(lambda v: scatter_plain(zeros, idx[0], v))(vals)))
    np.testing.assert_array_equal(np.asarray(gather_folded(table[0], idx[0])), np.asarray(gather_plain(table[0], idx[0])))


def test_folded_ops_compose_with_jvp_in_either_order():
    idx, vals, table = _data(1)
    zeros = jnp.zeros((G, C))
    dvals, dtable = vals[::-1] * 0.5, table[::-1] * 2.0

    def f(op_s, op_g):
        return lambda i, v, t: (op_s(zeros, i, v * v), op_g(jnp.sin(t), i))

    for vmap_outer in (True, False):
        out = []
        for op_s, op_g in ((scatter_folded, gather_folded), (scatter_plain, gather_plain)):
            g = f(op_s, op_g)
            if vmap_outer:
                run = jax.vmap(lambda i, v, t, dv, dt: jax.jvp(lambda v_, t_: g(i, v_, t_), (v, t), (dv, dt)))
            else:
                run = lambda i, v, t, dv, dt: jax.jvp(lambda v_, t_: jax.vmap(g)(i, v_, t_), (v, t), (dv, dt))
            out.append(run(idx, vals, table, dvals, dtable))
        for a, b in zip(jax.tree_util.tree_leaves(out[0]), jax.tree_util.tree_leaves(out[1])):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14, atol=1e-14)
