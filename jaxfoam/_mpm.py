"""One MLS-MPM substep in named stages: p2g -> grid_update -> g2p -> constitutive.

Dimension-generic: d = x.shape[-1]; the 3^d stencil is unrolled at trace time as elementwise
(N,)-array operations (XLA:CPU is slow at reductions over tiny axes). All stencil offsets go through
one scatter-add, and grid-to-particle gathers in a scan over the first axis's offsets; both move the
last axis's 3 nodes per index as one window.

Reverse mode can go through hand-written adjoints of the two transfers (`hand_adjoint=True`): one
gather-and-contract pass per transfer instead of autodiff's transposed broadcasts and stacks
(docs/gradients.md: reverse mode 1.08-1.13x faster); autodiff's own derivative stays the default, as
the only one that forward mode (jvp, jacfwd) can use.
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import operator

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name
import numpy as np

from . import _tensor as T
from ._constitutive import _kirchhoff, _return_map_components
from ._fusion import hoist, materialize_linearization, materialize_tangent
from ._params import Params
from ._scene import Scene
from ._state import State

# Grid nodes beyond the domain on each side: the quadratic stencil reaches 1.5 cells past a
# particle, and the slip walls live on the domain boundary, so 3 cells keep every index in range.
GRID_PAD = 3
# Particle-to-grid and grid-to-particle move the 3 consecutive nodes along the last axis (contiguous in
# the flat grid) as one window: 3^(d-1) scatter / gather indices per particle instead of 3^d. XLA:CPU's
# scatter and gather cost mostly per index: 2D step 1.09x (f32) / 1.11x (f64), 3D 1.12x (f32).
_WINDOW_SCATTER = jax.lax.ScatterDimensionNumbers(update_window_dims=(1, 2), inserted_window_dims=(),
                                                  scatter_dims_to_operand_dims=(0,))
_WINDOW_GATHER = jax.lax.GatherDimensionNumbers(offset_dims=(1, 2), collapsed_slice_dims=(), start_index_map=(0,))
_IN_BOUNDS = jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS
# Forward grid-to-particle in 2D float32 as a scan over the first axis's stencil offsets
# (`_window_loop`) instead of the unrolled sum (`_window_sum`) of every other case. Unrolled, the 2D
# float32 step ran 0.98-1.04x in same-process A/Bs, but the same-run Taichi ratio (bench_peer, median
# of 31 rounds) fell from 1.04 and 1.08 to 0.97, 0.98 and 1.01 (runs in the same hour), and its g2p
# kernels took 180-257 us per step against 130-163 for the loop (bench_step's 2D case); with the
# loop kept there, 1.09 and 1.05. Unrolled elsewhere: 2D float64 1.13x, 3D 1.06-1.07x.
G2P_LOOP_2D_FLOAT32 = True


@dataclasses.dataclass(frozen=True)
class Grid:
    """Static background grid. origin (d,) m is node (0, ..., 0); dx m; shape nodes per axis."""

    origin: tuple
    dx: float
    shape: tuple

    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def num_nodes(self) -> int:
        return int(np.prod(self.shape))

    def node_positions(self, dtype, xp=jnp) -> jax.Array:
        """(G, d) node positions, m, in the flattened (row-major) order of the grid arrays
        (a numpy array, a compile-time constant, with xp=np)."""
        axes = [self.origin[k] + self.dx * np.arange(n) for k, n in enumerate(self.shape)]
        pos = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, self.dim)
        return xp.asarray(pos, dtype)


def make_grid(scene: Scene, dx: float) -> Grid:
    """The grid covering the scene's domain with GRID_PAD extra cells on every side."""
    lo = np.asarray(scene.domain_min)
    hi = np.asarray(scene.domain_max)
    n = np.ceil((hi - lo) / dx).astype(int) + 1 + 2 * GRID_PAD
    return Grid(origin=tuple((lo - GRID_PAD * dx).tolist()), dx=float(dx), shape=tuple(int(k) for k in n))


@jax.custom_jvp
def safe_div(num, den):
    """num / den where den > 0, else 0 (grid momentum / grid mass).

    Its derivative (dnum - q dden) / den never squares den: in float32 the textbook derivative
    d(1/den) = -dden/den^2 underflows for tiny stencil-edge masses and poisons reverse mode.
    """
    pos = den > 0
    return jnp.where(pos, num / jnp.where(pos, den, 1.0), 0.0)


@safe_div.defjvp
def _safe_div_jvp(primals, tangents):
    num, den = primals
    dnum, dden = tangents
    q = safe_div(num, den)
    pos = den > 0
    return q, jnp.where(pos, (dnum - q * dden) / jnp.where(pos, den, 1.0), 0.0)


def _stencil(x, grid: Grid):
    """Quadratic B-spline weights: base (N, d) int, fx (N, d), w list of 3 arrays (N, d)."""
    inv_dx = 1.0 / grid.dx
    origin = jnp.asarray(grid.origin, x.dtype)
    xg = (x - origin[None, :]) * inv_dx
    base = jnp.floor(xg - 0.5)
    fx = xg - base
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    # Every stencil index is kept inside the grid (a no-op for active particles, which `constitutive`
    # keeps in the stencil-safe region; it bounds inactive or non-finite ones), so the gather and the
    # scatter need no bounds checks (XLA:CPU's checked gather is 2x slower).
    hi = jnp.asarray(grid.shape, jnp.int32) - 3
    return jnp.clip(base.astype(jnp.int32), 0, hi[None, :]), fx, w


def _stencil_derivs(fx, grid: Grid):
    """Position derivatives of `_stencil`'s 1D weights: list of 3 arrays (N, d), d w_a / d x, 1/m."""
    inv = 1.0 / grid.dx
    return [-(1.5 - fx) * inv, -2.0 * (fx - 1.0) * inv, (fx - 0.5) * inv]


def _offsets(d):
    return list(itertools.product(range(3), repeat=d))


def _stencil_weights(w, offs):
    """Per-offset B-spline weights W (K, N): the product over axes of the 1D weights `w`."""
    d = w[0].shape[-1]
    W = []
    for off in offs:
        weight = w[off[0]][:, 0]
        for k in range(1, d):
            weight = weight * w[off[k]][:, k]
        W.append(weight)
    return jnp.stack(W)


def _strides(shape) -> list[int]:
    """Row-major strides (in elements) of an array of the given shape, as Python ints (static)."""
    return [int(s) for s in np.cumprod((tuple(shape[1:]) + (1,))[::-1])[::-1]]


def _flat_index(base, offset, grid: Grid):
    strides = _strides(grid.shape)
    idx = 0
    for k in range(grid.dim):
        idx = idx + (base[:, k] + offset[k]) * strides[k]
    return idx


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


def _offset_index(offset, grid: Grid) -> int:
    """Flat index difference of a stencil offset (static)."""
    return int(np.dot(offset, _strides(grid.shape)))


def to_components(state: State) -> State:
    """The substep's working form: C and F as tuples of rows of (N,) component arrays, bbar_e as the
    tuple of its independent components (symmetric; in 2D plane strain xx, xy, yy, zz only).

    Inside a rollout the state stays in this form from one substep to the next (structure of arrays).
    Packing the components into (N, d, d) arrays every substep made XLA:CPU evaluate the shared
    per-particle expressions once per matrix entry, in the forward step and far worse in its
    transpose: the reverse-mode constitutive update ran at 10x its forward time packed, 1.6x unpacked.
    Keeping only bbar_e's independent components, with the plane-strain zeros as constants that the
    component algebra folds away, made the 2D step 1.11-1.13x faster (3D 1.01x) and reverse mode
    1.17x faster; the 2D results are bit for bit the same (the lower triangle equalled the upper).
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
    order. Particles that share a stencil then scatter to and gather from neighbouring memory: on
    randomly ordered particles the step ran 17% (2D) and 26% (3D) faster sorted (experiments/bench_step.md).
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


def _window_payload(grid: Grid, fx, w, mvA, A, mass=None, tangent=None):
    """The APIC payload W_ip (mv_p + A_p (x_i - x_p)) [, W_ip m_p] in the windowed scatter's order:
    (3^(d-1) N, 3, c), c = d or d + 1. fx, w: the particles' `_stencil` fractions and 1D weights;
    mvA (N, d), A (N, d, d).

    It is computed directly in that window order, (offset of the other axes, particle, last-axis node,
    channel), from (N,) and (N, 3) factors: built per offset as (K, N) arrays and transposed to it, the
    payload kernel was a strided copy, and the whole scatter ran 1.23x (with mass) / 1.24x (without)
    slower (2D, 5440 particles, float64).

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


def _window_scatter(grid: Grid, idx0, vals):
    """Scatter-add of a `_window_payload` (3^(d-1) N, 3, c) to the grid: (G, c). One index per particle
    and offset of the other axes, a (3, c) window of the last axis's 3 nodes each (_WINDOW_SCATTER)."""
    d = grid.dim
    idx = jnp.concatenate([idx0 + _offset_index(off + (0,), grid) for off in _offsets(d - 1)])
    return jax.lax.scatter_add(jnp.zeros((grid.num_nodes, vals.shape[-1]), vals.dtype), idx[:, None], vals,
                               _WINDOW_SCATTER, mode=_IN_BOUNDS)


def _p2g_scatter(grid: Grid, fx, w, idx0, mvA, A, mass=None):
    """Scatter-add of the APIC payload W_ip (mv_p + A_p (x_i - x_p)) [, W_ip m_p] to the grid:
    (G, d) or, with mass, (G, d + 1) (`_window_payload`, `_window_scatter`)."""
    return _window_scatter(grid, idx0, _window_payload(grid, fx, w, mvA, A, mass))


def _window_gather(table, start):
    """The rows start, start + 1, start + 2 of `table` (G, c) per particle: (N, 3, c) (_WINDOW_GATHER)."""
    return jax.lax.gather(table, start[:, None], _WINDOW_GATHER, (3, table.shape[1]), mode=_IN_BOUNDS)


def _window_loop(table, x, idx0, grid: Grid, init, body, pos_scale=1.0):
    """Sum over the 3^d stencil nodes i of each particle p, gathering the grid rows `table` (G, c) of
    the last axis's 3 nodes as one window: `body(carry, g (N, c), W (N,), dpos) -> carry` runs per
    node with g = table[i], W = w_ip and dpos = pos_scale (x_i - x_p) (d arrays (N,), m times
    pos_scale). Used by the forward grid-to-particle transfer in 2D float32 (G2P_LOOP_2D_FLOAT32).

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


def _window_sum(table, x, idx0, grid: Grid, init, body, t, derivs=False, pos_scale=1.0):
    """Sum over the 3^d stencil nodes i of each particle p, gathering the grid rows `table` (G, c) of
    the last axis's 3 nodes as one window: `body(carry, g (N, c), W (N,), dpos[, dW]) -> carry` runs
    per node with g = table[i], W = w_ip, dpos = pos_scale (x_i - x_p) (d arrays (N,), m times
    pos_scale) and, with `derivs`, dW = grad_p w_ip (d arrays (N,), 1/m). `table` should be a
    buffer (`hoist`): XLA:CPU fuses its producer (the grid update) into the gathers otherwise and
    evaluates it once per gathered value. Used by the hand-written adjoints and by grid-to-particle
    (except in 2D float32, G2P_LOOP_2D_FLOAT32).

    Unrolled over all 3^d nodes, with the summed values returned as buffers (`hoist`): XLA:CPU then
    computes each of them in one kernel over the particles; without the buffers it fused the sums
    into their consumers and recomputed them there. The earlier form, a scan over the first axis's
    3 offsets with the other axes unrolled in its body, made every accumulator a kernel per
    iteration (27 kernels per substep for the 9 sums of the particle-to-grid adjoint in 2D).
    Measured against it (same process, float64 unless noted): the transposed transfers of a
    reverse-mode substep 1036 instead of 1377 us (p2g 673 -> 439, g2p 337 -> 284; 2D hanging plate,
    dx 2.5 mm), reverse mode 1.115x (that scene, 10 frames) and 1.049x (3D, dx 8 mm); the forward
    step (bench_step's cases) 1.13x in 2D, 1.07x in 3D, 1.06x in 3D float32.

    t: the substep's start time, s: the buffers' cond tests isfinite(t) (`hoist`), as the other
    buffers of the substep do; it stays a cond (a fusion boundary) under a vmap over parameters."""
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
            windows[mid] = _window_gather(table, start)
        ws = [w[off[k]][:, k] for k in range(d)]
        dpos = [(off[k] - fx[:, k]) * (grid.dx * pos_scale) for k in range(d)]
        extra = ()
        if derivs:
            extra = ([functools.reduce(operator.mul, [dw[off[k]][:, k] if k == j else ws[k] for k in range(d)])
                      for j in range(d)],)
        carry = body(carry, windows[mid][:, off[-1], :], functools.reduce(operator.mul, ws), dpos, *extra)
    leaves, treedef = jax.tree_util.tree_flatten(carry)
    return jax.tree_util.tree_unflatten(treedef, list(hoist(tuple(leaves), t)))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _p2g_impl(grid, x, idx0, mvA, A, mass):
    """`_p2g_scatter` of the payload (mvA, A, mass) at positions x: (grid momentum (G, d), mass (G,)).

    Its forward-mode derivative is written out (`_window_payload` with a tangent): one kernel per
    stencil block for the tangent payload, which autodiff built from the transposes of the payload's
    broadcasts and stacks; it transposes for reverse mode like any linear code."""
    _, fx, w = _stencil(x, grid)
    d = x.shape[1]
    out = _p2g_scatter(grid, fx, w, idx0, mvA, A, mass)
    return out[:, :d], out[:, d]


@_p2g_impl.defjvp
def _p2g_impl_jvp(grid, primals, tangents):
    x, idx0, mvA, A, mass = primals
    dx, _, dmvA, dA, dmass = tangents
    _, fx, w = _stencil(x, grid)
    d = x.shape[1]
    out = _p2g_scatter(grid, fx, w, idx0, mvA, A, mass)
    dout = _window_scatter(grid, idx0, _window_payload(grid, fx, w, mvA, A, mass, tangent=(dx, dmvA, dA, dmass)))
    return (out[:, :d], out[:, d]), (dout[:, :d], dout[:, d])


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _p2g_transfer(grid, x, idx0, mvA, A, mass, t):
    """`_p2g_impl` with a hand-written reverse-mode derivative in x, mvA, A and mass: the grid
    cotangent is gathered once per stencil window and contracted per particle. (The two outputs
    are joined into one (G, d + 1) table in the backward pass: one concatenation, where autodiff's
    transpose of the slices padded each to the full table and added them, 52 of ~4600 us per
    reverse-mode substep at dx 2.5 mm.) t: the substep's start time, s (`_window_sum`); its
    cotangent is zero."""
    return _p2g_impl(grid, x, idx0, mvA, A, mass)


def _p2g_transfer_fwd(grid, x, idx0, mvA, A, mass, t):
    return _p2g_impl(grid, x, idx0, mvA, A, mass), (x, idx0, mvA, A, mass, t)


def _p2g_transfer_bwd(grid, res, ct):
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
    ct = hoist(jnp.concatenate([ct[0], ct[1][:, None]], axis=1), t)
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
    G0, G1, Dx = _window_sum(ct, x, idx0, grid, init, body, t, derivs=True)
    dmv = jnp.stack(G0[:d], axis=1)
    dA = jnp.stack([jnp.stack(row, axis=1) for row in G1], axis=1)
    # d(x_i - x_p)/dx_p = -1: the affine term's share.
    dx = jnp.stack([Dx[a] - sum(A[:, i, a] * G0[i] for i in range(d)) for a in range(d)], axis=1)
    return dx, None, dmv, dA, G0[d], None


_p2g_transfer.defvjp(_p2g_transfer_fwd, _p2g_transfer_bwd)


def p2g(state: State, params: Params, grid: Grid, dt, idx0=None,
        hand_adjoint: bool = False) -> tuple[jax.Array, jax.Array]:
    """Particle to grid: scatter mass and momentum (including the MLS-MPM stress impulse).

    idx0: optional (N,) flat grid index of each particle's stencil base (computed from x if None).
    hand_adjoint: the scatter's reverse-mode derivative is the hand-written one (`_p2g_transfer`):
      faster vjp/grad, but the result is then not forward-differentiable (jvp, jacfwd).
    Returns (grid momentum (G, d) kg m/s, grid mass (G,) kg). Inactive particles carry zero mass
    and volume and contribute nothing. `state` may be in either form (`to_components`).
    """
    x, d = state.x, state.dim
    act = state.active.astype(x.dtype)
    mass = state.mass * act
    vol = state.vol0 * act
    tau = _kirchhoff(_comps(state.F), _bbar_comps(state.bbar_e), params, d)
    Cc = _comps(state.C)
    # MLS-MPM: the force on node i is -sum_p V0_p tau_p grad w_ip, with grad w = 4/dx^2 w (x_i - x_p).
    k_stress = (-dt * 4.0 / grid.dx ** 2) * vol
    affine = [[k_stress * tau[i][j] + mass * Cc[i][j] for j in range(d)] for i in range(d)]
    mv = [mass * state.v[:, i] for i in range(d)]
    mvA = jnp.stack(mv, axis=1)
    A = jnp.stack([jnp.stack(row, axis=1) for row in affine], axis=1)
    if idx0 is None:
        idx0 = _flat_index(_stencil(x, grid)[0], (0,) * d, grid)
    if hand_adjoint:
        grid_mv = _p2g_transfer(grid, x, idx0, mvA, A, mass, state.t)
    else:
        grid_mv = _p2g_impl(grid, x, idx0, mvA, A, mass)
    # Reverse mode: the grid cotangent is materialized before the gather that transposes this
    # scatter (jaxfoam._fusion; the hand-written adjoint does it itself), and the grid is kept per
    # substep by the rematerialization policy.
    if not hand_adjoint:
        grid_mv = materialize_tangent(grid_mv, dt)
    return checkpoint_name(grid_mv, "p2g_grid")


# max(x, 0), min(x, 0) and clipping as selects (NaN passes through, as with jnp.maximum). The derivative
# of a select is a select; jnp.maximum's derivative splits ties half and half, which costs compares and
# a division per element in the transposed program: the colliders' transpose over the grid nodes was the
# largest single kernel of a reverse-mode substep (211 us of ~7 ms, 2D hanging plate, dx 2.5 mm).
def _pos_part(x):
    return jnp.where(x < 0, jnp.zeros_like(x), x)


def _neg_part(x):
    return jnp.where(x > 0, jnp.zeros_like(x), x)


def _clamp(x, lo, hi):
    return jnp.where(x < lo, lo, jnp.where(x > hi, hi, x))


def _floor_rule(v, scene: Scene):
    """The floor's velocities for nodes at or below it (v (..., d) m/s): no slip when sticky, else
    Coulomb friction with the scene coefficient on approaching nodes (others unchanged)."""
    d = v.shape[-1]
    if scene.floor_sticky:
        return jnp.zeros_like(v)
    vn = v[..., 1]
    tang = [v[..., k] for k in range(d) if k != 1]
    if d == 2:
        # One tangential component: speed |v_x|, new v_x = sign(v_x) max(|v_x| + mu_f v_n, 0)
        # (no square root or division: the 3D form cost two extra grid kernels per step).
        new_t = [jnp.sign(tang[0]) * _pos_part(jnp.abs(tang[0]) + scene.floor_friction * vn)]
    else:
        sq = sum(c * c for c in tang)
        pos = sq > 0
        speed = jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)
        new_speed = _pos_part(speed + scene.floor_friction * vn)
        scale = jnp.where(pos, new_speed / jnp.where(pos, speed, 1.0), 0.0)
        new_t = [c * scale for c in tang]
    friction = jnp.stack(new_t[:1] + [jnp.zeros_like(vn)] + new_t[1:], axis=-1)
    return jnp.where((vn < 0)[..., None], friction, v)


# Particle floor contact: a particle touches the floor when the gap below its extent is at most this
# fraction of its half-extent (`particle_floor`) or of dx (`floor_touch`): round-off of the landing
# step, which puts the gap at 0.
FLOOR_TOUCH = 1e-6


def _half_extent(vol0, d):
    """A particle's half-extent vol0^(1/d) / 2, m (0 for an empty slot, with a finite derivative)."""
    has = vol0 > 0
    return jnp.where(has, 0.5 * jnp.power(jnp.where(has, vol0, 1.0), 1.0 / d), 0.0)


def particle_floor(x, v, vol0, scene: Scene, dt):
    """Floor contact on particles (scene.floor_contact == "particle"): velocities (N, d) m/s.

    A particle's half-extent is r = vol0^(1/d) / 2 m (half its sampling spacing: the extent the
    silhouette renderer gives it). It may not end the substep with its extent below the floor: with
    gap = y - r - floor_y (m), a downward v_y < -max(gap, 0) / dt is raised to that, so it lands on
    the floor (a particle that already overlaps it, as a jittered initial sample may, goes no deeper).
    The normal velocity so removed, dv (m/s), is Coulomb's impulse per unit mass: the tangential
    speed drops by friction * dv (not below 0). On a sticky floor such a particle, and one touching the
    floor (gap <= FLOOR_TOUCH r), loses its tangential velocity and cannot lift off.
    x (N, d) m, v (N, d) m/s, vol0 (N,) m^d (m^2 in 2D), dt s.
    """
    d = x.shape[1]
    r = _half_extent(vol0, d)
    gap = x[:, 1] - r - scene.floor_y
    # A particle already overlapping the floor (a jittered initial sample) is not pushed out, only
    # kept from going deeper: pushing it out within one substep would launch it.
    vmin = -_pos_part(gap) / dt
    vy = v[:, 1]
    hit = vy < vmin
    tang = [k for k in range(d) if k != 1]
    if scene.floor_sticky:
        held = hit | (gap <= FLOOR_TOUCH * r)
        new_vy = jnp.where(hit, vmin, jnp.where(held, 0.0, vy))
        cols = {k: jnp.where(held, 0.0, v[:, k]) for k in tang}
    else:
        dv = jnp.where(hit, vmin - vy, 0.0)
        new_vy = jnp.where(hit, vmin, vy)
        sq = sum(v[:, k] * v[:, k] for k in tang)
        pos = sq > 0
        speed = jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)
        scale = jnp.where(pos, _pos_part(speed - scene.floor_friction * dv) / jnp.where(pos, speed, 1.0), 0.0)
        cols = {k: v[:, k] * scale for k in tang}
    cols[1] = new_vy
    return jnp.stack([cols[k] for k in range(d)], axis=1)


def floor_touch(x, vol0, active, grid: Grid, scene: Scene, idx0=None) -> jax.Array | None:
    """(G,) bool, for particle floor contact: the nodes whose stencil support holds a particle whose
    extent (half-size vol0^(1/d) / 2, m) reaches the floor (to FLOOR_TOUCH dx). Only those of the
    nodes at or below the floor take the floor's rule, so the grid holds material that touches the
    floor, not material that merely comes within a stencil's reach of it (a decision on values, not
    differentiated). x (N, d) m, vol0 (N,) m^d, active (N,) bool; idx0 the stencil base index.
    None when the scene has no floor with particle contact (`Scene.particle_contact_floor`)."""
    if not scene.particle_contact_floor:
        return None
    d = x.shape[1]
    has = active & (vol0 > 0)
    low = jax.lax.stop_gradient(jnp.where(has, x[:, 1] - _half_extent(vol0, d), jnp.inf))
    if idx0 is None:
        idx0 = _flat_index(_stencil(x, grid)[0], (0,) * d, grid)
    idx0 = jax.lax.stop_gradient(idx0)
    idx = jnp.concatenate([idx0 + _offset_index(off, grid) for off in _offsets(d)])
    lowest = jnp.full((grid.num_nodes,), jnp.inf, x.dtype).at[idx].min(jnp.tile(low, 3 ** d),
                                                                        mode=_IN_BOUNDS)
    return lowest <= scene.floor_y + FLOOR_TOUCH * grid.dx


def _wall_rule(vk, low: bool):
    """A slip wall on velocity component k at a node on or beyond it: the outward part removed."""
    return _pos_part(vk) if low else _neg_part(vk)


def _floor_layers(grid: Grid, dtype, floor_y: float) -> int:
    """How many leading node layers along y lie at or below the floor (the comparison, in `dtype`,
    that the mask form of `apply_colliders` makes on the node positions)."""
    pos = (grid.origin[1] + grid.dx * np.arange(grid.shape[1])).astype(dtype)
    return int(np.sum(pos <= np.asarray(floor_y, dtype)))


def apply_colliders(v, node_x, scene: Scene, t, colliders=(), grid_m=None, dt=None, dx=None,
                    grid: Grid | None = None, touch=None) -> jax.Array:
    """Boundary conditions on grid velocities v (G, d) m/s at nodes node_x (G, d) m, time t s.

    - plates: nodes inside a plate take its velocity (sticky) or lose the approaching normal
      component relative to it (slip);
    - floor (y <= floor_y): no slip when sticky, else Coulomb friction with the scene coefficient
      on approaching nodes; with particle contact (scene.floor_contact == "particle") only where
      `touch` (G,) bool (`floor_touch`) is true, and the bottom wall then acts no higher than half
      a cell below the floor;
    - domain walls: slip (outward normal velocity removed) on nodes on or beyond the boundary;
    - colliders: extra static colliders, each with `apply(v, node_x, t) -> v` (e.g.
      `jaxfoam.sdf.SDFCollider`), applied last, in order; a collider with a finite `adhesion` (Pa)
      also gets the grid mass `grid_m` (G,) kg (kg/m in 2D), the substep `dt` s and the spacing `dx`
      m as keywords, to measure the traction the material pulls on it with.

    grid: when node_x are `grid`'s nodes (as in `grid_update`), the floor and the walls, which sit on
    fixed node layers, are applied to those layers only (static slices) instead of as selects over
    every node: the same values, for a fraction of the work (docs/gradients.md).
    """
    d = v.shape[-1]
    for plate in scene.plates:
        # Computed once, not per grid node (jaxfoam._fusion).
        c, vp = hoist((plate.position(t), plate.velocity(t)), t)
        rel = node_x - c[None, :]
        inside = jnp.all(jnp.abs(rel) <= plate.half_size[None, :], axis=-1)
        if plate.sticky:
            v = jnp.where(inside[:, None], vp[None, :], v)
        else:
            gap = plate.half_size[None, :] - jnp.abs(rel)  # distance to each face pair
            axis = jnp.argmin(gap, axis=-1)
            normal = jax.nn.one_hot(axis, d, dtype=v.dtype) * jnp.sign(
                jnp.take_along_axis(rel, axis[:, None], -1))
            vrel = v - vp[None, :]
            vn = sum(vrel[:, k] * normal[:, k] for k in range(d))
            vrel = vrel - _neg_part(vn)[:, None] * normal
            v = jnp.where(inside[:, None], vp[None, :] + vrel, v)
    wall_lo = np.asarray(scene.domain_min, np.float64).copy()
    if scene.floor_y is not None:
        particle = scene.particle_contact_floor
        if particle:
            if touch is None:
                raise ValueError("a floor with particle contact needs `touch` (jaxfoam._mpm.floor_touch)")
            spacing = grid.dx if grid is not None else dx
            if spacing is None:
                raise ValueError("a floor with particle contact needs the grid spacing dx")
            # The bottom wall must not hold up material that has not reached the floor either.
            wall_lo[1] = min(wall_lo[1], scene.floor_y - 0.5 * float(spacing))
        if grid is None:
            below = node_x[:, 1] <= scene.floor_y
            if particle:
                below = below & touch
            v = jnp.where(below[:, None], _floor_rule(v, scene), v)
        else:
            floor_n = _floor_layers(grid, np.dtype(v.dtype), scene.floor_y)
            v = v.reshape(tuple(grid.shape) + (d,))
            rows = v[:, :floor_n]
            ruled = _floor_rule(rows, scene)
            if particle:
                ruled = jnp.where(touch.reshape(tuple(grid.shape))[:, :floor_n, ..., None], ruled, rows)
            v = v.at[:, :floor_n].set(ruled).reshape(-1, d)
    if grid is None:
        lo = jnp.asarray(wall_lo, v.dtype)
        hi = jnp.asarray(scene.domain_max, v.dtype)
        at_lo, at_hi = node_x <= lo[None, :], node_x >= hi[None, :]
    else:
        pos = grid.node_positions(np.dtype(v.dtype), xp=np)
        at_lo = pos <= np.asarray(wall_lo, pos.dtype)[None, :]
        at_hi = pos >= np.asarray(scene.domain_max, pos.dtype)[None, :]
    v = jnp.where(at_lo, _wall_rule(v, True), v)
    v = jnp.where(at_hi, _wall_rule(v, False), v)
    for collider in colliders:
        if getattr(collider, "adhesion", None) is not None:
            v = collider.apply(v, node_x, t, mass=grid_m, dt=dt, dx=dx)
        else:
            v = collider.apply(v, node_x, t)
    return v


def grid_update(grid_mv, grid_m, scene: Scene, grid: Grid, t, dt, colliders=(), touch=None) -> jax.Array:
    """Grid velocities (G, d) m/s at the end of the substep: momentum / mass, gravity, colliders
    (touch: `floor_touch`'s nodes, for a floor with particle contact)."""
    v = safe_div(grid_mv, grid_m[:, None])
    v = v + jnp.where(grid_m[:, None] > 0, dt * scene.gravity.astype(v.dtype)[None, :], 0.0)
    # Derivative programs: v and its tangent become buffers (jaxfoam._fusion), so the colliders'
    # transpose is computed once, and their tangent kernels read v instead of recomputing it from the
    # momentum and mass per tangent element (jacfwd 1.02-1.14x, reverse mode 1.02-1.10x in three
    # alternating one-core runs on the 2D hanging plate at dx 2.5 mm, against the tangent alone).
    v = materialize_linearization(v, dt)
    return apply_colliders(v, grid.node_positions(v.dtype), scene, t + dt, colliders, grid_m, dt, grid.dx,
                           grid=grid, touch=touch)


def g2p(state: State, grid_v, grid: Grid) -> tuple[jax.Array, jax.Array]:
    """Grid to particle: APIC velocity (N, d) m/s and affine matrix / velocity gradient C (N, d, d) 1/s."""
    v, C = _g2p(state, grid_v, grid)
    return v, T.array(C, state.x[:, 0])


def _g2p(state: State, grid_v, grid: Grid, idx0=None, hand_adjoint: bool = False):
    """`g2p` with C returned as components (rows of (N,) arrays), 1/s; `hand_adjoint` as in `p2g`."""
    if idx0 is None:
        idx0 = _flat_index(_stencil(state.x, grid)[0], (0,) * state.dim, grid)
    if hand_adjoint:
        return _g2p_transfer(grid, state.x, grid_v, idx0, state.t)
    return _g2p_impl(state.x, grid_v, grid, idx0, state.t)


def _g2p_impl(x, grid_v, grid: Grid, idx0, t):
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
    if G2P_LOOP_2D_FLOAT32 and d == 2 and x.dtype == jnp.float32:
        return _window_loop(grid_v, x, idx0, grid, zero, accumulate, pos_scale=scale)
    # The grid velocities as a buffer (`_window_sum`).
    return _window_sum(hoist(grid_v, t), x, idx0, grid, zero, accumulate, t, pos_scale=scale)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _g2p_transfer(grid, x, grid_v, idx0, t):
    """`_g2p` (v (N, d) m/s, C components 1/s) with a hand-written reverse-mode derivative in x and
    grid_v: one gather of the grid velocities for the position derivative and one scatter-add of
    the cotangent payload (the same APIC form as particle-to-grid)."""
    return _g2p_impl(x, grid_v, grid, idx0, t)


def _g2p_transfer_fwd(grid, x, grid_v, idx0, t):
    # The residuals are the inputs only: v is summed again in the backward pass's stencil sum, so a
    # rematerialized substep need not redo this transfer (its outputs are saved by name).
    return _g2p_impl(x, grid_v, grid, idx0, t), (x, grid_v, idx0, t)


def _g2p_transfer_bwd(grid, res, ct):
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
    cv, cC = hoist((cv, cC), t)
    cCs = [[scale * cC[i][j] for j in range(d)] for i in range(d)]

    def body(carry, g, W, dpos, dW):
        Dx, v = carry
        s = 0.0
        for i in range(d):
            s = s + g[:, i] * (cv[:, i] + sum(cCs[i][j] * dpos[j] for j in range(d)))
        return tuple(Dx[a] + dW[a] * s for a in range(d)), v + W[:, None] * g

    z = jnp.zeros_like(x[:, 0])
    # grid_v, a residual, is gathered as it is: materialized by a cond first, reverse mode ran 0.97x.
    Dx, v = _window_sum(grid_v, x, idx0, grid, ((z,) * d, jnp.zeros_like(x)), body, t, derivs=True)
    # d(x_i - x_p)/dx_p = -1 in C's offsets: sum_i cC_ia (scale sum_k W_k g_k,i) = sum_i cCs_ia v_i.
    dx = jnp.stack([Dx[a] - sum(cCs[i][a] * v[:, i] for i in range(d)) for a in range(d)], axis=1)
    # The stencil's fractions and weights as buffers: fused in, XLA:CPU recomputed them from the
    # positions in each stencil block's payload kernel (9 in 3D): 3D reverse mode 1.080x (hanging
    # plate, dx 8 mm, 7 rounds), 2D 1.02x. (The same in the forward p2g: 0.93-0.97x.)
    _, fx, w = _stencil(x, grid)
    fx, w = hoist((fx, w), t)
    A = jnp.stack([jnp.stack(row, axis=1) for row in cCs], axis=1)
    dgrid = _p2g_scatter(grid, fx, w, idx0, cv, A)
    return dx, dgrid, None, None


_g2p_transfer.defvjp(_g2p_transfer_fwd, _g2p_transfer_bwd)


def constitutive(state: State, v, C, params: Params, grid: Grid, dt, scene: Scene | None = None) -> State:
    """Advance F and bbar_e with f = I + dt C (eq. 11-16), advect positions, keep them on the grid.

    v (N, d) m/s and C (N, d, d) 1/s from `g2p`; returns the state in the form it was given in.
    scene: with a floor of particle contact, `particle_floor` limits v before the advection."""
    new = _constitutive(to_components(state), v, _comps(C), params, grid, dt, scene)
    return new if isinstance(state.F, tuple) else from_components(new)


def _constitutive(state: State, v, Cc, params: Params, grid: Grid, dt, scene: Scene | None = None) -> State:
    """`constitutive` on the component form (`to_components`), C given as components."""
    d = state.dim
    if scene is not None and scene.particle_contact_floor:
        v = particle_floor(state.x, v, state.vol0, scene, dt)
    like = state.x[:, 0]
    fc = T.add_diag(T.scale(Cc, dt), 1.0)
    F = T.matmul(fc, state.F)
    b_old = _bbar_comps(state.bbar_e)
    bc, _, gamma = _return_map_components(b_old, _pad3(fc), params, dt)
    # Particles never leave the stencil-safe region (the walls stop them long before).
    lo = jnp.asarray(grid.origin, like.dtype) + grid.dx
    hi = jnp.asarray(grid.origin, like.dtype) + grid.dx * (jnp.asarray(grid.shape, like.dtype) - 2.0)
    x = _clamp(state.x + dt * v, lo[None, :], hi[None, :])
    keep = state.active

    def keep_mat(new, old):
        return tuple(tuple(jnp.where(keep, jnp.broadcast_to(jnp.asarray(n_, like.dtype), like.shape), o_)
                           for n_, o_ in zip(rn, ro)) for rn, ro in zip(new, old))

    zero = tuple(tuple(jnp.zeros_like(like) for _ in range(d)) for _ in range(d))
    return state.replace(
        x=jnp.where(keep[:, None], x, state.x), v=jnp.where(keep[:, None], v, 0.0),
        C=keep_mat(Cc, zero), F=keep_mat(F, state.F),
        bbar_e=tuple(jnp.where(keep, n_, o_) for n_, o_ in zip(_bbar_pack(bc, d), _bbar_pack(b_old, d))),
        gamma_dot=jnp.where(keep, gamma, 0.0), t=state.t + dt)


def _pad3(M):
    """Embed d x d components in the 3x3 identity (plane strain: f_zz = 1)."""
    d = len(M)
    return tuple(tuple(M[i][j] if (i < d and j < d) else (1.0 if i == j else 0.0) for j in range(3))
                 for i in range(3))


def substep(state: State, params: Params, scene: Scene, grid: Grid, dt, fracture=None, colliders=(),
            hand_adjoint: bool = False) -> State:
    """One explicit MLS-MPM step of length dt (s): the chain of named stages.

    Optional static stages: `colliders` (see `apply_colliders`), and `fracture`, an object with
    `apply(new_state, old_state, grid_m, grid) -> State` run after the constitutive update
    (`jaxfoam.fracture.FractureConfig`). With the defaults the step is the plain MLS-MPM step.
    hand_adjoint: the transfers' reverse-mode derivatives are hand-written (see `p2g`); the step is
    then differentiable in reverse mode only.
    Returns the state in the form it was given in (arrays, or components: `to_components`).
    """
    new = _substep(to_components(state), params, scene, grid, dt, fracture, colliders, hand_adjoint)
    return new if isinstance(state.F, tuple) else from_components(new)


def _substep(state: State, params: Params, scene: Scene, grid: Grid, dt, fracture=None, colliders=(),
             hand_adjoint: bool = False) -> State:
    """`substep` on the component form."""
    # The flat grid index of each particle's stencil base, computed once per substep for p2g and g2p
    # (left to XLA, every offset's index fusion recomputed it from the positions: 3D step 1.08x faster).
    idx0 = hoist(_flat_index(_stencil(state.x, grid)[0], (0,) * state.dim, grid), state.t)
    with jax.named_scope("p2g"):
        grid_mv, grid_m = p2g(state, params, grid, dt, idx0, hand_adjoint)
    touch = floor_touch(state.x, state.vol0, state.active, grid, scene, idx0)
    with jax.named_scope("grid_update"):
        grid_v = grid_update(grid_mv, grid_m, scene, grid, state.t, dt, colliders, touch)
    with jax.named_scope("g2p"):
        v, C = _g2p(state, grid_v, grid, idx0, hand_adjoint)
        # Named: kept by reverse mode's per-substep rematerialization (jaxfoam._simulate.REMAT_SAVED).
        v, C = checkpoint_name((v, C), "g2p")
    with jax.named_scope("constitutive"):
        new = _constitutive(state, v, C, params, grid, dt, scene)
    if fracture is not None:
        with jax.named_scope("fracture"):
            new = to_components(fracture.apply(from_components(new), from_components(state), grid_m, grid))
    return new


def make_step(scene: Scene, grid: Grid, dt: float, fracture=None, colliders=()):
    """Bind the static configuration once: returns the pure `step(state, params) -> state`.

    The step returns the state in the form it is given: a loop of many steps runs faster on
    `to_components(state)` (convert back with `from_components` when done), as `simulate` does.
    """

    def step(state: State, params: Params) -> State:
        return substep(state, params, scene, grid, dt, fracture, colliders)

    return step
