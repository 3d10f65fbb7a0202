"""MLS-MPM transfers as windowed scatters and gathers, with their speed-only derivative rules.

Particle-to-grid and grid-to-particle move the 3 consecutive nodes along the last axis (contiguous in
the flat grid) as one window: 3^(d-1) scatter / gather indices per particle instead of 3^d (XLA:CPU's
scatter and gather cost mostly per index). The forward-mode rule of the scatter and the hand-written
reverse-mode rules of both transfers compute what autodiff would, in fewer kernels
(docs/performance.md). `jaxfoam._mpm` calls `p2g_transfer` and `g2p_transfer`.
"""
from __future__ import annotations

import functools
import itertools
import operator

import jax
import jax.numpy as jnp

from .._grid import Grid, _offset_index, _offsets, _stencil, _stencil_derivs, _strides
from .fold import gather_folded, gather_plain, scatter_folded, scatter_plain

def _window_payload(grid: Grid, fx, w, mvA, A, mass=None, tangent=None):
    """The APIC payload W_ip (mv_p + A_p (x_i - x_p)) [, W_ip m_p] in the windowed scatter's order:
    (3^(d-1) N, 3, c), c = d or d + 1. fx, w: the particles' `_stencil` fractions and 1D weights;
    mvA (N, d), A (N, d, d).

    It is computed directly in that window order, (offset of the other axes, particle, last-axis node,
    channel), from (N,) and (N, 3) factors: built per offset as (K, N) arrays and transposed to it, the
    payload kernel is a strided copy (docs/gradients.md has the measurement).

    tangent: optional (dx (N, d) m, dmvA, dA, dmass): then the payload's directional derivative along
    them is returned instead (`_p2g_impl`'s forward-mode rule), with r_ip = x_i - x_p and
      d[W (mv + A r)] = W (dmv - A dx + dA r) + (grad_p W . dx) (mv + A r),
      d[W m] = W dm + (grad_p W . dx) m."""
    d = A.shape[-1]
    last = d - 1
    # The last axis's 3 weights and node offsets per particle: (N, 3).
    w_last = jnp.stack([w[a][:, last] for a in range(3)], axis=1)
    dp_last = (jnp.arange(3, dtype=fx.dtype)[None, :] - fx[:, last:]) * grid.dx
    if tangent is not None:
        dx, dmvA, dA, dmass = tangent
        dw = _stencil_derivs(fx, grid)
        dw_last = jnp.stack([dw[a][:, last] for a in range(3)], axis=1) * dx[:, last:]
        # A's share of d r = -dx folded into the momentum: dmv - A dx.
        dmv_eff = [dmvA[:, i] - sum(A[:, i, k] * dx[:, k] for k in range(d)) for i in range(d)]
    blocks = []
    for r in _offsets(d - 1):
        ws = [w[r[k]][:, k] for k in range(d - 1)]
        w_r = functools.reduce(operator.mul, ws, jnp.ones_like(fx[:, 0]))
        W = w_r[:, None] * w_last
        dpos = [((r[k] - fx[:, k]) * grid.dx)[:, None] for k in range(d - 1)] + [dp_last]
        P = [mvA[:, i:i + 1] + sum(A[:, i, k:k + 1] * dpos[k] for k in range(d)) for i in range(d)]
        if tangent is None:
            cols = [W * P[i] for i in range(d)]
            if mass is not None:
                cols.append(W * mass[:, None])
        else:
            # grad_p W . dx = (sum over the other axes of their weight derivative) w_last + w_r dw_last.
            dw_r = sum(functools.reduce(operator.mul, [dw[r[j]][:, j] * dx[:, j] if j == k else ws[j]
                                                       for j in range(d - 1)], jnp.ones_like(fx[:, 0]))
                       for k in range(d - 1))
            G = dw_r[:, None] * w_last + w_r[:, None] * dw_last
            cols = [W * (dmv_eff[i][:, None] + sum(dA[:, i, k:k + 1] * dpos[k] for k in range(d))) + G * P[i]
                    for i in range(d)]
            if mass is not None:
                cols.append(W * dmass[:, None] + G * mass[:, None])
        blocks.append(jnp.stack(cols, axis=-1))  # (N, 3, c)
    return jnp.concatenate(blocks, axis=0)


def _window_scatter(grid: Grid, idx0, vals, fold: bool = False):
    """Scatter-add of a `_window_payload` (3^(d-1) N, 3, c) to the grid: (G, c). One index per particle
    and offset of the other axes, a (3, c) window of the last axis's 3 nodes each (`fold.scatter_plain`;
    fold: the batch-folding op, `Tuning.batch_fold`)."""
    d = grid.dim
    idx = jnp.concatenate([idx0 + _offset_index(off + (0,), grid) for off in _offsets(d - 1)])
    return (scatter_folded if fold else scatter_plain)(jnp.zeros((grid.num_nodes, vals.shape[-1]), vals.dtype),
                                                       idx, vals)


def _p2g_scatter(grid: Grid, fx, w, idx0, mvA, A, mass=None, fold: bool = False):
    """Scatter-add of the APIC payload W_ip (mv_p + A_p (x_i - x_p)) [, W_ip m_p] to the grid:
    (G, d) or, with mass, (G, d + 1) (`_window_payload`, `_window_scatter`)."""
    return _window_scatter(grid, idx0, _window_payload(grid, fx, w, mvA, A, mass), fold)


def _window_gather(table, start, fold: bool = False):
    """The rows start, start + 1, start + 2 of `table` (G, c) per particle: (N, 3, c) (`fold.gather_plain`)."""
    return (gather_folded if fold else gather_plain)(table, start)


def _window_loop(table, x, idx0, grid: Grid, init, body, pos_scale=1.0, fold: bool = False):
    """Sum over the 3^d stencil nodes i of each particle p, gathering the grid rows `table` (G, c) of
    the last axis's 3 nodes as one window: `body(carry, g (N, c), W (N,), dpos) -> carry` runs per
    node with g = table[i], W = w_ip and dpos = pos_scale (x_i - x_p) (d arrays (N,), m times
    pos_scale). Used by the forward grid-to-particle transfer in 2D float32 (Tuning.g2p_loop_2d_float32).

    The sum over offsets runs as a scan over the first axis's 3 offsets (the others unrolled in the
    body), gathering inside the body: the table is then materialized once as a loop input (fused
    into one gather, the grid update was recomputed per gathered value), and the carry is
    materialized once (as an unrolled sum XLA:CPU fused it into every consumer in the constitutive
    update and recomputed it there)."""
    d = x.shape[1]
    _, fx, w = _stencil(x, grid)
    strides = _strides(grid.shape)
    geo = []
    for r in itertools.product(range(3), repeat=d - 1):
        wr = functools.reduce(operator.mul, [w[r[k - 1]][:, k] for k in range(1, d)])
        dpr = [(r[k - 1] - fx[:, k]) * (grid.dx * pos_scale) for k in range(1, d)]
        geo.append((r, wr, dpr))

    def step(carry, xs):
        a, wa = xs
        dp0 = (a.astype(x.dtype) - fx[:, 0]) * (grid.dx * pos_scale)
        ia = idx0 + a * strides[0]
        windows = {}
        for r, wr, dpr in geo:
            mid = r[:-1]
            if mid not in windows:
                start = ia + sum(mid[k - 1] * strides[k] for k in range(1, d - 1))
                windows[mid] = _window_gather(table, start)
            carry = body(carry, windows[mid][:, r[-1], :], wa * wr, [dp0] + dpr)
        return carry, None

    xs = (jnp.arange(3, dtype=jnp.int32), jnp.stack([w[a][:, 0] for a in range(3)]))
    return jax.lax.scan(step, init, xs)[0]


def _window_sum(table, x, idx0, grid: Grid, init, body, t, tuning, derivs=False, pos_scale=1.0):
    """Sum over the 3^d stencil nodes i of each particle p, gathering the grid rows `table` (G, c) of
    the last axis's 3 nodes as one window: `body(carry, g (N, c), W (N,), dpos[, dW]) -> carry` runs
    per node with g = table[i], W = w_ip, dpos = pos_scale (x_i - x_p) (d arrays (N,), m times
    pos_scale) and, with `derivs`, dW = grad_p w_ip (d arrays (N,), 1/m). `table` should be a
    buffer (`hoist`): XLA:CPU fuses its producer (the grid update) into the gathers otherwise and
    evaluates it once per gathered value. Used by the hand-written adjoints and by grid-to-particle
    (except in 2D float32 with Tuning.g2p_loop_2d_float32).

    Unrolled over all 3^d nodes, the summed values returned as buffers (Tuning "stencil_sums"):
    XLA:CPU then computes each in one kernel over the particles instead of fusing it into every consumer.

    t: the substep's start time, s: the buffers' cond tests isfinite(t) (`hoist`), as the other
    buffers of the substep do; it stays a cond (a fusion boundary) under a vmap over parameters.
    tuning: the `Tuning` whose buffer points apply."""
    d = x.shape[1]
    _, fx, w = _stencil(x, grid)
    dw = _stencil_derivs(fx, grid) if derivs else None
    strides = _strides(grid.shape)
    windows = {}
    carry = init
    for off in _offsets(d):
        mid = off[:-1]
        if mid not in windows:
            start = idx0 + sum(mid[k] * strides[k] for k in range(d - 1))
            windows[mid] = _window_gather(table, start, tuning.batch_fold)
        ws = [w[off[k]][:, k] for k in range(d)]
        dpos = [(off[k] - fx[:, k]) * (grid.dx * pos_scale) for k in range(d)]
        extra = ()
        if derivs:
            extra = ([functools.reduce(operator.mul, [dw[off[k]][:, k] if k == j else ws[k] for k in range(d)])
                      for j in range(d)],)
        carry = body(carry, windows[mid][:, off[-1], :], functools.reduce(operator.mul, ws), dpos, *extra)
    leaves, treedef = jax.tree_util.tree_flatten(carry)
    return jax.tree_util.tree_unflatten(treedef, list(tuning.buffer("stencil_sums", tuple(leaves), t)))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _p2g_impl(grid, fold, x, idx0, mvA, A, mass):
    """`_p2g_scatter` of the payload (mvA, A, mass) at positions x: (grid momentum (G, d), mass (G,)).

    Its forward-mode derivative is written out (`_window_payload` with a tangent): one kernel per
    stencil block for the tangent payload, which autodiff built from the transposes of the payload's
    broadcasts and stacks; it transposes for reverse mode like any linear code."""
    _, fx, w = _stencil(x, grid)
    d = x.shape[1]
    out = _p2g_scatter(grid, fx, w, idx0, mvA, A, mass, fold=fold)
    return out[:, :d], out[:, d]


@_p2g_impl.defjvp
def _p2g_impl_jvp(grid, fold, primals, tangents):
    x, idx0, mvA, A, mass = primals
    dx, _, dmvA, dA, dmass = tangents
    _, fx, w = _stencil(x, grid)
    d = x.shape[1]
    out = _p2g_scatter(grid, fx, w, idx0, mvA, A, mass, fold=fold)
    dout = _window_scatter(grid, idx0, _window_payload(grid, fx, w, mvA, A, mass, tangent=(dx, dmvA, dA, dmass)),
                           fold)
    return (out[:, :d], out[:, d]), (dout[:, :d], dout[:, d])


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _p2g_transfer(grid, tuning, x, idx0, mvA, A, mass, t):
    """`_p2g_impl` with a hand-written reverse-mode derivative in x, mvA, A and mass: the grid
    cotangent is gathered once per stencil window and contracted per particle. (The two outputs
    are joined into one (G, d + 1) table in the backward pass: one concatenation, where autodiff's
    transpose of the slices pads each to the full table and adds them.) t: the substep's start time, s (`_window_sum`); its
    cotangent is zero."""
    return _p2g_impl(grid, False, x, idx0, mvA, A, mass)


def _p2g_transfer_fwd(grid, tuning, x, idx0, mvA, A, mass, t):
    return _p2g_impl(grid, False, x, idx0, mvA, A, mass), (x, idx0, mvA, A, mass, t)


def _p2g_transfer_bwd(grid, tuning, res, ct):
    """Cotangents of (x, idx0, mvA, A, mass, t) (idx0's and t's zero) from the grid cotangent
    ct = (c_i (d), c_i^m) per node i (the cotangents of the momentum (G, d) and of the mass (G,)).

    With W_ip the weight, r_ip = x_i - x_p and s_ip = c_i . (mv_p + A_p r_ip) + c_i^m m_p:
      d mv_p = sum_i W_ip c_i,   d A_p = sum_i W_ip c_i r_ip^T,   d m_p = sum_i W_ip c_i^m,
      d x_p = sum_i grad_p W_ip s_ip - A_p^T (sum_i W_ip c_i)      (d r_ip / d x_p = -I).
    One pass over the stencil windows of ct (the gather that autodiff would also do), all sums
    accumulated per particle in it."""
    x, idx0, mvA, A, mass, t = res
    d = x.shape[1]
    # One (G, d + 1) table, as a buffer (jaxfoam._fusion): fused into the gather below, XLA:CPU
    # would evaluate the transposed grid update once per gathered value.
    ct = tuning.buffer("adjoint_inputs", jnp.concatenate([ct[0], ct[1][:, None]], axis=1), t)
    z = jnp.zeros_like(x[:, 0])

    def body(carry, g, W, dpos, dW):
        G0, G1, Dx = carry
        s = g[:, d] * mass
        for i in range(d):
            s = s + g[:, i] * (mvA[:, i] + sum(A[:, i, j] * dpos[j] for j in range(d)))
        Wg = [W * g[:, c] for c in range(d + 1)]
        G0 = tuple(G0[c] + Wg[c] for c in range(d + 1))
        G1 = tuple(tuple(G1[i][j] + Wg[i] * dpos[j] for j in range(d)) for i in range(d))
        Dx = tuple(Dx[a] + dW[a] * s for a in range(d))
        return G0, G1, Dx

    init = ((z,) * (d + 1), tuple((z,) * d for _ in range(d)), (z,) * d)
    G0, G1, Dx = _window_sum(ct, x, idx0, grid, init, body, t, tuning, derivs=True)
    dmv = jnp.stack(G0[:d], axis=1)
    dA = jnp.stack([jnp.stack(row, axis=1) for row in G1], axis=1)
    # d(x_i - x_p)/dx_p = -1: the affine term's share.
    dx = jnp.stack([Dx[a] - sum(A[:, i, a] * G0[i] for i in range(d)) for a in range(d)], axis=1)
    return dx, None, dmv, dA, G0[d], None


_p2g_transfer.defvjp(_p2g_transfer_fwd, _p2g_transfer_bwd)


def _g2p_impl(x, grid_v, grid: Grid, idx0, t, tuning):
    """(v (N, d) m/s, C components 1/s) gathered at x from grid_v; t: the substep's start time, s
    (the cond that keeps the gathered table and the sums as buffers, `_window_sum`)."""
    scale = 4.0 / grid.dx ** 2
    d = x.shape[1]

    def accumulate(carry, g, W, dp):
        v, C = carry
        vi = W[:, None] * g
        return v + vi, tuple(tuple(C[i][j] + vi[:, i] * dp[j] for j in range(d)) for i in range(d))

    zc = jnp.zeros_like(x[:, 0])
    zero = (jnp.zeros_like(x), tuple(tuple(zc for _ in range(d)) for _ in range(d)))
    # C = 4/dx^2 sum_i w_ip v_i (x_i - x_p)^T: the offsets come scaled by 4/dx^2.
    if tuning.g2p_loop_2d_float32 and d == 2 and x.dtype == jnp.float32:
        return _window_loop(grid_v, x, idx0, grid, zero, accumulate, pos_scale=scale, fold=tuning.batch_fold)
    # The grid velocities as a buffer (`_window_sum`).
    return _window_sum(tuning.buffer("g2p_table", grid_v, t), x, idx0, grid, zero, accumulate, t, tuning,
                       pos_scale=scale)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _g2p_transfer(grid, tuning, x, grid_v, idx0, t):
    """`_g2p` (v (N, d) m/s, C components 1/s) with a hand-written reverse-mode derivative in x and
    grid_v: one gather of the grid velocities for the position derivative and one scatter-add of
    the cotangent payload (the same APIC form as particle-to-grid)."""
    return _g2p_impl(x, grid_v, grid, idx0, t, tuning)


def _g2p_transfer_fwd(grid, tuning, x, grid_v, idx0, t):
    # The residuals are the inputs only: v is summed again in the backward pass's stencil sum, so a
    # rematerialized substep need not redo this transfer (its outputs are saved by name).
    return _g2p_impl(x, grid_v, grid, idx0, t, tuning), (x, grid_v, idx0, t)


def _g2p_transfer_bwd(grid, tuning, res, ct):
    """Cotangents of (x, grid_v, idx0, t) (the last two zero) from (cv, cC), the cotangents of
    v_p = sum_i W_ip v_i and C_p = k sum_i W_ip v_i r_ip^T (k = 4 / dx^2, r_ip = x_i - x_p):
      d v_i = sum_p W_ip (cv_p + k cC_p r_ip)   (a particle-to-grid scatter of that payload),
      d x_p = sum_i grad_p W_ip v_i . (cv_p + k cC_p r_ip) - k cC_p^T v_p."""
    x, grid_v, idx0, t = res
    cv, cC = ct
    d = x.shape[1]
    scale = 4.0 / grid.dx ** 2
    # The cotangents as buffers (jaxfoam._fusion): fused into the payload, XLA:CPU recomputed their
    # producers (the transposed constitutive update) per stencil node.
    cv, cC = tuning.buffer("adjoint_inputs", (cv, cC), t)
    cCs = [[scale * cC[i][j] for j in range(d)] for i in range(d)]

    def body(carry, g, W, dpos, dW):
        Dx, v = carry
        s = 0.0
        for i in range(d):
            s = s + g[:, i] * (cv[:, i] + sum(cCs[i][j] * dpos[j] for j in range(d)))
        return tuple(Dx[a] + dW[a] * s for a in range(d)), v + W[:, None] * g

    z = jnp.zeros_like(x[:, 0])
    # grid_v, a residual, is gathered as it is: a cond-materialized copy first was slower.
    Dx, v = _window_sum(grid_v, x, idx0, grid, ((z,) * d, jnp.zeros_like(x)), body, t, tuning, derivs=True)
    # d(x_i - x_p)/dx_p = -1 in C's offsets: sum_i cC_ia (scale sum_k W_k g_k,i) = sum_i cCs_ia v_i.
    dx = jnp.stack([Dx[a] - sum(cCs[i][a] * v[:, i] for i in range(d)) for a in range(d)], axis=1)
    # The stencil's fractions and weights as buffers: fused in, XLA:CPU recomputed them from the
    # positions in each stencil block's payload kernel (9 in 3D); in the forward p2g buffers lost.
    _, fx, w = _stencil(x, grid)
    fx, w = tuning.buffer("adjoint_inputs", (fx, w), t)
    A = jnp.stack([jnp.stack(row, axis=1) for row in cCs], axis=1)
    dgrid = _p2g_scatter(grid, fx, w, idx0, cv, A)
    return dx, dgrid, None, None


_g2p_transfer.defvjp(_g2p_transfer_fwd, _g2p_transfer_bwd)



def p2g_transfer(grid: Grid, tuning, x, idx0, mvA, A, mass, t, hand_adjoint: bool = False):
    """Scatter-add of the APIC payload W_ip (mv_p + A_p (x_i - x_p)) and W_ip m_p to the grid:
    (momentum (G, d), mass (G,)). x (N, d) m, idx0 (N,) stencil base index, mvA (N, d), A (N, d, d),
    mass (N,); t the substep's start time, s. hand_adjoint: the hand-written reverse-mode rule
    (`_p2g_transfer`; the result is then not forward-differentiable)."""
    if hand_adjoint:
        return _p2g_transfer(grid, tuning, x, idx0, mvA, A, mass, t)
    return _p2g_impl(grid, tuning.batch_fold, x, idx0, mvA, A, mass)


def g2p_transfer(grid: Grid, tuning, x, grid_v, idx0, t, hand_adjoint: bool = False):
    """APIC gather at x (N, d) m of grid_v (G, d) m/s: (v (N, d), C as rows of (N,) components, 1/s);
    hand_adjoint as in `p2g_transfer`."""
    if hand_adjoint:
        return _g2p_transfer(grid, tuning, x, grid_v, idx0, t)
    return _g2p_impl(x, grid_v, grid, idx0, t, tuning)
