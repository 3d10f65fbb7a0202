"""Particle resampling under large deformation (Yue et al. 2015, section 5).

Advected material points spread unevenly: a sheet stretched along one axis thins along the other,
and its points separate along the stretch until cells inside the material hold no point at all, a
non-physical void. `resample` keeps the distribution even with the fixed-capacity arrays of `State`:

1. merge: pairs of points closer than `merge_radius` become one point at their centre of mass
   (mass, volume and momentum summed; F, bbar_e, C, gamma_dot mass-averaged); repeated for
   `merge_rounds` rounds of mutual-nearest pairs.
2. insert: cells inside the material holding fewer than `sparse_fraction * ppc` points are refilled
   up to ppc. Candidates are a jittered sub-cell lattice whose jitter keeps candidates at least
   `insert_radius` apart (Poisson-disk style); a candidate is rejected closer than `insert_radius`
   to an existing point or where the material SDF (`jaxfoam.sdf.material_sdf`, the closing of the
   particle set) is not negative, so the outside and real cavities stay empty. Accepted candidates
   go into inactive slots.
   Mass, volume and momentum come from the neighbours through the grid: node n gives the fraction
   f_n = W_n / (n_n + W_n) of what its old points deposited there (W_n, n_n: B-spline-weighted
   counts of new and old points at n); a new point j takes the share w_jn / W_n of each node's
   pool. Old points keep their velocity and lose the fraction sum_n w_in f_n of their mass and
   volume, so total mass, volume and linear momentum are conserved to round-off, and a uniform
   region ends with equal masses. The new point's v, F, bbar_e (renormalized to det 1), C and
   gamma_dot are the mass-weighted averages of what it received.

All decisions (which points merge, which candidates are accepted, the SDF) are made on
stop-gradient positions: derivatives treat them as constant and flow through the mass-weighted
transfers, which are smooth. Units: SI (m, kg, s).
"""
from __future__ import annotations

import dataclasses
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._constitutive import det
from ._grid import Grid, _offsets, _stencil, _strides
from ._scene import DEFAULT_PPC
from ._state import State
from .sdf import material_sdf

# Smallest B-spline-weighted count of old points around a candidate (points in its 3^d stencil,
# weighted): below it a new point would take almost no mass; 0.05 is 1/80 of a full 2D cell.
MIN_SUPPORT = 0.05
# SDF lattice points per dx by dimension: dx/2 resolves gaps of one cell in 2D; in 3D it has 8x the
# points and makes a resampling pass about 20x slower (docs/performance.md), so 3D uses dx.
DEFAULT_SDF_REFINE = {2: 2, 3: 1}


@dataclasses.dataclass(frozen=True)
class ResampleConfig:
    """Static resampling settings (hashable: a static argument of the jit-compiled rollout).

    Attributes:
      every: substeps between resampling passes (>= 1). A pass is costly: measured on a shared 2-core
        CPU it took the CPU time of about 30 substeps (2D sheet, 11k slots) and 10 substeps (3D pie
        scene, 5.4k slots); choose `every` so that points move less than about a cell in between.
      ppc: target points per cell (default: 4 in 2D, 8 in 3D); must be k^d for an integer k.
      sparse_fraction: a cell with fewer than sparse_fraction * ppc points is refilled, in (0, 1].
      insert_radius: Poisson-disk radius, in units of the target spacing s = dx / ppc^(1/d), in (0, 1).
      merge_radius: merge distance in units of s, in [0, insert_radius) (0 disables merging).
      closing_radius: radius of the material SDF's closing, in units of dx (gaps up to twice it are
        treated as material, wider cavities are kept).
      sdf_refine: SDF lattice points per dx (>= 1; default 2 in 2D, 1 in 3D, where a finer lattice
        costs 8x per level).
      merge_rounds: rounds of mutual-nearest merging per pass (>= 0); each round merges at least the
        closest remaining pair, in practice nearly all of them (8 rounds removed every pair closer
        than the radius from 1,500 uniformly random points, 4 left 7 pairs).
      merge_cell_capacity: points examined per hash cell of side merge_radius in the pair search.
      capacity_factor: a Simulator given no capacity gives the state this many times the sampled
        number of slots (room for inserted points).
      seed: seed of the candidate jitter (the pass index is folded in).
    """

    every: int = 20
    ppc: int | None = None
    sparse_fraction: float = 0.5
    insert_radius: float = 0.5
    merge_radius: float = 0.3
    closing_radius: float = 1.0
    sdf_refine: int | None = None
    merge_rounds: int = 8
    merge_cell_capacity: int = 4
    capacity_factor: float = 2.0
    seed: int = 0

    def validate(self, d: int) -> "ResampleConfig":
        """Raise ValueError naming the field and its allowed range; return self."""
        if not (isinstance(self.every, int) and self.every >= 1):
            raise ValueError(f"ResampleConfig.every must be an integer >= 1 (substeps), got {self.every!r}")
        ppc = self.target_ppc(d)
        k = round(ppc ** (1.0 / d))
        if k ** d != ppc:
            raise ValueError(f"ResampleConfig.ppc must be k^{d} for an integer k (e.g. {2 ** d}), got {ppc}")
        if not 0 < self.sparse_fraction <= 1:
            raise ValueError(f"ResampleConfig.sparse_fraction must be in (0, 1], got {self.sparse_fraction}")
        if not 0 < self.insert_radius < 1:
            raise ValueError(f"ResampleConfig.insert_radius must be in (0, 1) (units of the spacing), "
                             f"got {self.insert_radius}")
        if not 0 <= self.merge_radius < self.insert_radius:
            raise ValueError(f"ResampleConfig.merge_radius must be in [0, insert_radius = "
                             f"{self.insert_radius}), got {self.merge_radius}")
        if not self.closing_radius > 0:
            raise ValueError(f"ResampleConfig.closing_radius must be > 0 (units of dx), got {self.closing_radius}")
        if not (self.sdf_refine is None or (isinstance(self.sdf_refine, int) and self.sdf_refine >= 1)):
            raise ValueError(f"ResampleConfig.sdf_refine must be an integer >= 1, got {self.sdf_refine!r}")
        if not (isinstance(self.merge_rounds, int) and self.merge_rounds >= 0):
            raise ValueError(f"ResampleConfig.merge_rounds must be an integer >= 0, got {self.merge_rounds!r}")
        if not self.capacity_factor >= 1:
            raise ValueError(f"ResampleConfig.capacity_factor must be >= 1, got {self.capacity_factor}")
        if not (isinstance(self.merge_cell_capacity, int) and self.merge_cell_capacity >= 1):
            raise ValueError(f"ResampleConfig.merge_cell_capacity must be an integer >= 1, "
                             f"got {self.merge_cell_capacity!r}")
        return self

    def apply(self, state: State, grid: Grid, index, hold=None) -> State:
        """The rollout hook: resampling pass number `index` (an integer, folded into the jitter key);
        `hold`: optional (N,) bool, points whose cells are not refilled (see `insert`)."""
        return resample(state, grid, self, rollout_key(self, index), hold)

    def prepare(self, state: State) -> State:
        """The initial state with ceil(capacity_factor * active count) slots (never fewer than now)."""
        n = int(jnp.sum(state.active))
        return with_capacity(state, max(state.capacity, int(math.ceil(self.capacity_factor * n))))

    def target_ppc(self, d: int) -> int:
        return DEFAULT_PPC[d] if self.ppc is None else int(self.ppc)

    def spacing(self, dx: float, d: int) -> float:
        """Target point spacing s = dx / ppc^(1/d), m."""
        return dx / round(self.target_ppc(d) ** (1.0 / d))


def with_capacity(state: State, capacity: int) -> State:
    """The same state with `capacity` slots (>= the current one); new slots are inactive."""
    n = state.capacity
    if capacity < n:
        raise ValueError(f"capacity must be >= the current capacity {n}, got {capacity}")
    pad = capacity - n
    if pad == 0:
        return state
    d = state.dim
    dt = state.x.dtype

    def grow(a, fill):
        return jnp.concatenate([a, jnp.broadcast_to(jnp.asarray(fill, a.dtype), (pad,) + a.shape[1:])])

    return state.replace(
        x=grow(state.x, state.x[0]), v=grow(state.v, 0.0), C=grow(state.C, 0.0),
        F=grow(state.F, jnp.eye(d, dtype=dt)), bbar_e=grow(state.bbar_e, jnp.eye(3, dtype=dt)),
        vol0=grow(state.vol0, 0.0), mass=grow(state.mass, 0.0), gamma_dot=grow(state.gamma_dot, 0.0),
        active=grow(state.active, False))


# ----------------------------------------------------------------------------------------------
# Grid transfers without stress (quadratic B-splines of the simulation grid)
# ----------------------------------------------------------------------------------------------

def _weights(x, grid: Grid):
    """(index (3^d, N) int, weight (3^d, N)) of the quadratic B-spline stencil of points x (N, d)."""
    base, _, w = _stencil(x, grid)
    d = x.shape[-1]
    offs = np.asarray(_offsets(d))                       # (3^d, d), static
    W = jnp.stack(w)                                     # (3, N, d)
    wts = W[offs[:, 0], :, 0]
    for k in range(1, d):
        wts = wts * W[offs[:, k], :, k]
    strides = jnp.asarray(_strides(grid.shape), jnp.int32)
    idx = jnp.sum((base[None, :, :] + jnp.asarray(offs, jnp.int32)[:, None, :]) * strides[None, None, :], -1)
    return idx, wts


def _to_grid(idx, wts, vals, num_nodes):
    """sum_p w_pn vals_p: (G, c) from vals (N, c)."""
    contrib = wts[:, :, None] * vals[None, :, :]
    return jnp.zeros((num_nodes, vals.shape[1]), vals.dtype).at[idx.reshape(-1)].add(
        contrib.reshape(-1, vals.shape[1]), mode="drop")


def _from_grid(idx, wts, field):
    """sum_n w_pn field_n: (N, c) from field (G, c)."""
    g = field.at[idx.reshape(-1)].get(mode="fill", fill_value=0.0).reshape(idx.shape + field.shape[1:])
    return jnp.sum(wts[:, :, None] * g, axis=0)


def _pack(state: State):
    """Per-point quantities that are mass-averaged when points are created or merged: (N, c)."""
    n = state.capacity
    return jnp.concatenate([state.v, state.C.reshape(n, -1), state.F.reshape(n, -1),
                            state.bbar_e.reshape(n, -1), state.gamma_dot[:, None]], axis=1)


def _unpack(q, d):
    n = q.shape[0]
    i = 0
    out = []
    for size, shape in ((d, (d,)), (d * d, (d, d)), (d * d, (d, d)), (9, (3, 3)), (1, ())):
        out.append(q[:, i:i + size].reshape((n,) + shape))
        i += size
    return out


def _fix_tensors(F, bbar, dtype):
    """Averaged F and bbar_e made admissible: bbar_e renormalized to det 1; an F whose average lost
    orientation (det <= 0, neighbours rotated far apart) replaced by the isotropic J^(1/d) I."""
    d = F.shape[-1]
    dB = det(bbar)
    pos = dB > 0
    bbar = jnp.where(pos[:, None, None], bbar * (jnp.where(pos, dB, 1.0) ** (-1.0 / 3.0))[:, None, None],
                     jnp.eye(3, dtype=dtype)[None])
    J = det(F)
    return jnp.where((J > 0)[:, None, None], F, jnp.eye(d, dtype=dtype)[None]), bbar


# ----------------------------------------------------------------------------------------------
# Merging
# ----------------------------------------------------------------------------------------------

def _hash_layout(grid: Grid, cell: float):
    n = tuple(int(math.ceil((s - 1) * grid.dx / cell)) + 1 for s in grid.shape)
    return n, _strides(n)


def nearest_within(x, active, radius: float, grid: Grid, cell_capacity: int = 4):
    """Nearest other active point within `radius` (m) of each point: (index (N,) or -1, distance (N,) m).

    A spatial hash of cell side `radius`, sorted by key; each point examines up to `cell_capacity`
    points in each of its 3^d neighbouring hash cells. Decisions only: no gradient flows.
    """
    x = jax.lax.stop_gradient(x)
    N, d = x.shape
    shape, strides = _hash_layout(grid, radius)
    total = int(np.prod(shape))
    origin = jnp.asarray(grid.origin, x.dtype)
    c = jnp.clip(jnp.floor((x - origin[None, :]) / radius).astype(jnp.int32), 0,
                 jnp.asarray(shape, jnp.int32)[None, :] - 1)
    key = jnp.where(active, jnp.sum(c * jnp.asarray(strides, jnp.int32)[None, :], -1), total)
    order = jnp.argsort(key)
    skey = key[order]
    offs = jnp.asarray(list(itertools.product((-1, 0, 1), repeat=d)), jnp.int32)     # (3^d, d)
    cn = c[:, None, :] + offs[None, :, :]                                                # (N, 3^d, d)
    ok_cell = jnp.all((cn >= 0) & (cn < jnp.asarray(shape, jnp.int32)[None, None, :]), axis=-1) & active[:, None]
    qkey = jnp.where(ok_cell, jnp.sum(cn * jnp.asarray(strides, jnp.int32)[None, None, :], -1), total + 1)
    start = jnp.searchsorted(skey, qkey.reshape(-1), side="left").reshape(qkey.shape)
    pos = start[:, :, None] + jnp.arange(cell_capacity, dtype=start.dtype)[None, None, :]  # (N, 3^d, K)
    posc = jnp.minimum(pos, N - 1)
    j = order[posc]
    ok = ok_cell[:, :, None] & (pos < N) & (skey[posc] == qkey[:, :, None]) & (j != jnp.arange(N)[:, None, None])
    d2 = jnp.where(ok, jnp.sum((x[j] - x[:, None, None, :]) ** 2, -1), jnp.inf).reshape(N, -1)
    # Nearest first, ties to the lower index (a consistent order makes the closest pair mutual).
    j = j.reshape(N, -1)
    best_d2 = jnp.min(d2, axis=-1)
    best_j = jnp.min(jnp.where((d2 == best_d2[:, None]) & jnp.isfinite(d2), j, N), axis=-1)
    within = best_d2 < radius * radius
    return jnp.where(within, best_j, -1), jnp.where(within, jnp.sqrt(jnp.where(within, best_d2, 0.0)), jnp.inf)


def merge(state: State, grid: Grid, radius: float, rounds: int = 4, cell_capacity: int = 4):
    """Merge points closer than `radius` (m): returns (state, number of points removed).

    Each round merges every mutual-nearest pair within the radius (the closest pair overall is
    always one, so every round makes progress) into the lower slot, at the pair's centre of mass,
    with summed mass, volume and momentum and mass-averaged F, bbar_e, C, gamma_dot; the other slot
    becomes inactive.
    """
    if radius <= 0 or rounds == 0:
        return state, jnp.zeros((), jnp.int32)
    d = state.dim
    N = state.capacity
    ar = jnp.arange(N)

    def one_round(_, carry):
        s, removed = carry
        nn, _ = nearest_within(s.x, s.active, radius, grid, cell_capacity)
        has = nn >= 0
        j = jnp.where(has, nn, 0)
        mutual = has & (nn[j] == ar)
        keep = mutual & (ar < j)
        gone = mutual & (ar > j)
        mi, mj = s.mass, s.mass[j]
        M = mi + mj
        Ms = jnp.where(M > 0, M, 1.0)
        q = _pack(s)
        qm = (mi[:, None] * q + mj[:, None] * q[j]) / Ms[:, None]
        xm = (mi[:, None] * s.x + mj[:, None] * s.x[j]) / Ms[:, None]
        v, C, F, bbar, gd = _unpack(qm, d)
        F, bbar = _fix_tensors(F, bbar, s.x.dtype)
        k1, k2, k3 = keep[:, None], keep[:, None, None], gone[:, None, None]
        eye_d = jnp.eye(d, dtype=s.x.dtype)[None]
        eye_3 = jnp.eye(3, dtype=s.x.dtype)[None]
        s = s.replace(
            x=jnp.where(k1, xm, s.x),
            v=jnp.where(k1, v, jnp.where(gone[:, None], 0.0, s.v)),
            C=jnp.where(k2, C, jnp.where(k3, 0.0, s.C)),
            F=jnp.where(k2, F, jnp.where(k3, eye_d, s.F)),
            bbar_e=jnp.where(k2, bbar, jnp.where(k3, eye_3, s.bbar_e)),
            vol0=jnp.where(keep, s.vol0 + s.vol0[j], jnp.where(gone, 0.0, s.vol0)),
            mass=jnp.where(keep, M, jnp.where(gone, 0.0, s.mass)),
            gamma_dot=jnp.where(keep, gd, jnp.where(gone, 0.0, s.gamma_dot)),
            active=s.active & ~gone)
        return s, removed + jnp.sum(gone).astype(jnp.int32)

    return jax.lax.fori_loop(0, rounds, one_round, (state, jnp.zeros((), jnp.int32)))


# ----------------------------------------------------------------------------------------------
# Insertion
# ----------------------------------------------------------------------------------------------

def _candidate_layout(grid: Grid, k: int):
    """Static layout of the sub-cell lattice: integer sub-cell coordinates (S, d) ordered cell by
    cell (cell-major, k^d sub-cells of one cell contiguous) and the flat cell index of each."""
    d = grid.dim
    cells = np.stack(np.meshgrid(*[np.arange(s) for s in grid.shape], indexing="ij"), -1).reshape(-1, d)
    sub = np.stack(np.meshgrid(*[np.arange(k)] * d, indexing="ij"), -1).reshape(-1, d)
    ij = (cells[:, None, :] * k + sub[None, :, :]).reshape(-1, d)
    return ij.astype(np.int32), len(cells)


def insert(state: State, grid: Grid, config: ResampleConfig, key, hold=None):
    """Refill sparse cells inside the material (see the module docstring).

    hold: optional (N,) bool: cells holding one of these active points are never refilled. The
      rollout passes the points of a fracturing neck (`jaxfoam.fracture.FractureConfig.holds`): a
      neck thinner than the critical thickness has released its stress and must be left to thin and
      separate; refilling it as it is drawn out would keep the pieces joined by a thread that
      carries no load.
    Returns (state, number of points inserted, LatticeSDF of the material used for the decision).
    """
    d = state.dim
    dt_ = state.x.dtype
    N = state.capacity
    ppc = config.target_ppc(d)
    k = round(ppc ** (1.0 / d))
    s = grid.dx / k
    r_ins = config.insert_radius * s
    origin = jnp.asarray(grid.origin, dt_)
    xs = jax.lax.stop_gradient(state.x)
    act = state.active

    # Points per cell (cells indexed like the grid nodes at their lower corner).
    cstr = _strides(grid.shape)
    ci = jnp.floor((xs - origin[None, :]) / grid.dx).astype(jnp.int32)
    cflat = sum(ci[:, a] * cstr[a] for a in range(d))
    C = grid.num_nodes
    count = jnp.zeros((C,), jnp.int32).at[jnp.where(act, cflat, C)].add(1, mode="drop")

    # Candidates: one per sub-cell, jittered by at most (s - r_ins) / 2 so that two candidates are
    # always at least r_ins apart.
    ij_np, _ = _candidate_layout(grid, k)
    S = ij_np.shape[0]
    sshape = tuple(n * k for n in grid.shape)
    sstr = _strides(sshape)
    ij = jnp.asarray(ij_np)
    flat_sub = jnp.asarray(sum(ij_np[:, a].astype(np.int64) * sstr[a] for a in range(d)))
    k_jit, k_prio = jax.random.split(key)
    amp = 0.5 * (1.0 - config.insert_radius)
    jitter = jax.random.uniform(k_jit, (S, d), dt_, -amp, amp)
    cand = origin[None, :] + (ij.astype(dt_) + 0.5 + jitter) * s
    # Lookup from sub-cell lattice position to candidate number.
    lookup = jnp.zeros((S,), jnp.int32).at[flat_sub].set(jnp.arange(S, dtype=jnp.int32))

    # Rejection: an existing point within r_ins (it can only sit in the 3^d neighbouring sub-cells).
    pi = jnp.floor((xs - origin[None, :]) / s).astype(jnp.int32)
    offs = jnp.asarray(list(itertools.product((-1, 0, 1), repeat=d)), jnp.int32)
    q = pi[:, None, :] + offs[None, :, :]                                                # (N, 3^d, d)
    ok = act[:, None] & jnp.all((q >= 0) & (q < jnp.asarray(sshape, jnp.int32)[None, None, :]), axis=-1)
    cnum = lookup[jnp.where(ok, jnp.sum(q * jnp.asarray(sstr, jnp.int32)[None, None, :], -1), 0)]
    near = ok & (jnp.sum((cand[cnum] - xs[:, None, :]) ** 2, -1) < r_ins * r_ins)
    blocked = jnp.zeros((S,), bool).at[jnp.where(near, cnum, S).reshape(-1)].max(near.reshape(-1), mode="drop")

    refine = DEFAULT_SDF_REFINE[d] if config.sdf_refine is None else config.sdf_refine
    sdf = material_sdf(xs, act, grid.origin, grid.shape, grid.dx, config.closing_radius, refine)
    inside = sdf(cand) < 0.0
    sparse = count.astype(xs.dtype) < config.sparse_fraction * ppc
    if hold is not None:
        held = jnp.zeros((C,), bool).at[jnp.where(act & hold, cflat, C)].set(True, mode="drop")
        sparse = sparse & ~held
    deficit = jnp.maximum(ppc - count, 0)
    eligible = (inside & ~blocked).reshape(C, k ** d) & sparse[:, None]
    # In each cell accept `deficit` eligible candidates in a random order.
    prio = jnp.where(eligible, jax.random.uniform(k_prio, (C, k ** d), dt_), 2.0)
    rank = jnp.argsort(jnp.argsort(prio, axis=1), axis=1)
    accept = (eligible & (rank < deficit[:, None].astype(rank.dtype))).reshape(-1)

    # Compress the accepted candidates into at most N free slots.
    n_free = jnp.sum(~act)
    sel = jnp.nonzero(accept, size=N, fill_value=S)[0]
    valid = (sel < S) & (jnp.arange(N) < n_free)
    xc = cand[jnp.minimum(sel, S - 1)]

    # Donation through the grid.
    pidx, pw = _weights(state.x, grid)
    pw = pw * act.astype(dt_)[None, :]
    cidx, cw = _weights(xc, grid)
    n_old = _to_grid(pidx, pw, jnp.ones((N, 1), dt_), grid.num_nodes)[:, 0]
    support = _from_grid(cidx, cw, n_old[:, None])[:, 0]
    valid = valid & (support >= MIN_SUPPORT)
    cw = cw * valid.astype(dt_)[None, :]
    W = _to_grid(cidx, cw, jnp.ones((N, 1), dt_), grid.num_nodes)[:, 0]
    has_new = W > 0
    f = jnp.where(has_new, W / jnp.where(has_new, n_old + W, 1.0), 0.0)  # share each node gives away
    m = state.mass * act.astype(dt_)
    q = _pack(state)
    pools = _to_grid(pidx, pw, jnp.concatenate([m[:, None], (state.vol0 * act.astype(dt_))[:, None], m[:, None] * q],
                                               axis=1), grid.num_nodes) * f[:, None]
    share = jnp.where(has_new[:, None], pools / jnp.where(has_new, W, 1.0)[:, None], 0.0)
    got = _from_grid(cidx, cw, share)
    new_m, new_vol = got[:, 0], got[:, 1]
    valid = valid & (new_m > 0)
    ms = jnp.where(new_m > 0, new_m, 1.0)
    v, Cm, F, bbar, gd = _unpack(got[:, 2:] / ms[:, None], d)
    F, bbar = _fix_tensors(F, bbar, dt_)
    # Old points give away sum_n w_pn f_n of their mass and volume (velocity unchanged).
    give = _from_grid(pidx, pw, f[:, None])[:, 0]
    state = state.replace(mass=state.mass * (1.0 - give), vol0=state.vol0 * (1.0 - give))

    free = jnp.nonzero(~act, size=N, fill_value=N)[0]
    slot = jnp.where(valid, free, N)

    def put(a, b):
        return a.at[slot].set(b.astype(a.dtype), mode="drop")

    state = state.replace(
        x=put(state.x, xc), v=put(state.v, v), C=put(state.C, Cm), F=put(state.F, F),
        bbar_e=put(state.bbar_e, bbar), vol0=put(state.vol0, new_vol), mass=put(state.mass, new_m),
        gamma_dot=put(state.gamma_dot, gd), active=put(state.active, jnp.ones((N,), bool)))
    return state, jnp.sum(valid).astype(jnp.int32), sdf


def resample(state: State, grid: Grid, config: ResampleConfig, key, hold=None) -> State:
    """One resampling pass: merge too-close points, then refill sparse cells inside the material.

    key: a jax.random key for the candidate jitter; hold: optional (N,) bool, points whose cells are
    not refilled (see `insert`; slots that merging deactivates hold nothing). Pure and jit-compatible
    (fixed shapes).
    """
    return resample_with_stats(state, grid, config, key, hold)[0]


def resample_with_stats(state: State, grid: Grid, config: ResampleConfig, key, hold=None):
    """`resample` that also returns a dict: merged (points removed), inserted, and the material sdf."""
    state, merged = merge(state, grid, config.merge_radius * config.spacing(grid.dx, state.dim),
                          config.merge_rounds, config.merge_cell_capacity)
    state, inserted, sdf = insert(state, grid, config, key, hold)
    return state, dict(merged=merged, inserted=inserted, sdf=sdf)


def rollout_key(config: ResampleConfig, index):
    """The jitter key of resampling pass `index` (an integer array inside the rollout)."""
    return jax.random.fold_in(jax.random.PRNGKey(config.seed), index)
