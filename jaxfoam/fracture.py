"""Fracture of thinning foam (Yue et al. 2015, section 5).

Plain MPM has no fracture: points share forces through the grid while they are within a stencil
of each other, so a stretched thread thins into a chain of points that keeps pulling (with
resampling keeping it sampled, a pulled viscous strip never pinches off at all: see
experiments/results/fracture_demo.md). This stage, run after the constitutive update of every
substep (`make_model(..., fracture=FractureConfig())`), does three things:

1. detect weak points, by one or two criteria:
   a. neighbourhood density (always on): the ratio of the grid density interpolated at the point,
      sum_n w_pn m_n / dx^d, to the point's own density m_p / (J_p V0_p): about 1 in the bulk, 0.6 on
      a flat surface, >= 0.28 (2D) / 0.21 (3D) at a box corner, and 0.19 (2D) for a single file of
      points 0.75 dx apart; below `density_ratio` the point is weak (defaults sit between those corner
      and chain values). It is relative to the grid: it breaks what is about one cell wide, a width
      that shrinks with dx, so alone it cannot give a pinch-off that converges with resolution.
   b. critical neck thickness (`neck_thickness` = h_c, m; off by default): the point is weak where the
      material around it is thinner than h_c. The thickness (`neck_thickness()`) is sqrt(12 lambda),
      lambda the smallest eigenvalue of the covariance of the mass around the point weighted by a
      kernel of physical width (std h_c / sqrt(2) per axis, on an auxiliary grid of spacing h_c): a slab,
      thread or sheet of width w below h_c reads w (within 4%, at any dx well below h_c), a flat
      surface or a box corner 1.35-1.5 h_c, the bulk sqrt(6) h_c. It depends on the material's shape
      only, not on dx, and it is geometric: shear or compression of thick material never fires it.
      A pulled strip then breaks when its neck reaches h_c, at a plate travel that converges with dx
      where plain MPM's does not (experiments/results/fracture_demo.md); the break must come before
      the strip splits numerically between rows of points, which resampling (`jaxfoam.resample`)
      prevents. Cost: one deposit and one gather of 1 + d + d(d+1)/2 moments per point per substep.
2. drop the resistance along the separating direction and stop accumulating the separation as
   elastic strain: a weak point's elastic shear strain is released (bbar_e = I) and its volumetric
   stretch is released (J = 1 when J > 1; compression is kept, so pieces still push each other),
   and its F becomes the isotropic J^(1/d) I of that volume ratio (a point in a neck thinner than
   h_c releases its compression too, F = I: see `release`). Its Kirchhoff stress in the next
   p2g is then tau = kappa/2 (J^2 - 1) I with J <= 1: compressive only, so the points pulling the
   chain together no longer pull. The stress depends on F only through J, so the isotropic F changes
   no force; it discards the directional stretch, which otherwise grows without bound on a point with
   no neighbours (debris shed by a thinning neck): nothing resists its affine velocity C (its shear
   is released every substep), F integrates f = I + dt C and its singular values part
   exponentially until det F loses all precision and the point turns non-finite (measured on a
   lone point of the shaving-cream foam dropped on the floor at 1.2 m/s: |C| 100 to 170 1/s, the
   condition number of F 5e4 at 0.05 s and 8e15 at 0.21 s, non-finite at 0.23 s in float32).
3. reconnection: the released strain is the plastic adjustment. When a weak point's neighbourhood
   fills again (pieces touch, or resampling refills it), it is no longer weak and accumulates elastic
   strain from that relaxed state: the foam resists stretching again, as after bubbles reconnect.
   With a critical thickness set, resampling leaves the cells of a neck thinner than h_c unfilled
   (`holds`), so the released neck thins and the pieces separate; the density-ratio criterion holds
   nothing (resampling refills what it flags, as it should in a stretched sheet).

The release is isotropic (a weak point keeps no deviatoric stress in any direction): a
simplification of "resistance along the separating direction" that needs no eigen-decomposition
(whose derivative is singular at repeated eigenvalues) and matters little where a point has lost
its neighbours. The weak/strong decision is made on stop-gradient values: derivatives treat it as
constant; the release itself is smooth. Units: SI.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ._constitutive import det
from ._boundary import apply_colliders, floor_touch
from ._grid import Grid, _flat_index, _offsets, _stencil, _stencil_weights
from ._mpm import p2g, safe_div
from ._params import Params
from ._scene import Scene
from ._state import State
from .resample import _from_grid, _weights

# Default weak-point thresholds of the neighbourhood density ratio, by dimension. Measured on the
# jittered initial sampling (2^d points per cell): the smallest ratio at a box corner is 0.275 (2D)
# and 0.207 (3D); a single file of points 0.75 dx apart gives 0.19 (2D), a 2 x 2 rod of points 1 dx
# apart 0.115 (3D). The thresholds leave intact material intact and break single-file chains.
DEFAULT_DENSITY_RATIO = {2: 0.2, 3: 0.12}
# Spacing of the neck-thickness estimate's auxiliary grid, in units of the critical thickness h_c.
# Its kernel (B-spline of that grid, std NECK_GRID * h_c / sqrt(2) per axis) sees a flat surface or a
# box corner as about 1.5 h_c thick (never weak) and a thread of width w <= h_c as about w thick.
NECK_GRID = 1.0


@dataclasses.dataclass(frozen=True)
class FractureConfig:
    """Static fracture settings (hashable: a static argument of the jit-compiled step).

    Attributes:
      density_ratio: a point is weak when its neighbourhood density ratio is below this, in (0, 1)
        (default: DEFAULT_DENSITY_RATIO[d]). Relative to the grid: it breaks chains about one cell
        wide, whatever dx is.
      neck_thickness: critical thickness h_c, m (> 0), or None (default: off). A point is also weak
        where the material around it is thinner than h_c (`neck_thickness`), a physical length: a
        foam thread cannot be thinner than a few bubbles (shaving cream: bubbles 20-100 um), and at
        simulation scale h_c is the thinnest neck the grid represents, about 3 dx of the finest grid
        used or more. Off by default because no such length is known for a scene in general.
    """

    density_ratio: float | None = None
    neck_thickness: float | None = None

    def threshold(self, d: int) -> float:
        return DEFAULT_DENSITY_RATIO[d] if self.density_ratio is None else float(self.density_ratio)

    def validate(self, d: int) -> "FractureConfig":
        """Raise ValueError naming the field and its allowed range; return self."""
        thr = self.threshold(d)
        if not 0 < thr < 1:
            raise ValueError(f"FractureConfig.density_ratio must be in (0, 1), got {thr}")
        if self.neck_thickness is not None and not (np.isfinite(self.neck_thickness) and self.neck_thickness > 0):
            raise ValueError(f"FractureConfig.neck_thickness must be a length > 0 m or None, got {self.neck_thickness}")
        return self

    def masks(self, state: State, grid_m, grid: Grid):
        """((N,) bool, (N,) bool): points weak by the density ratio, and points in a neck thinner than
        neck_thickness (all False when it is None); grid mass `grid_m` (G,) kg from the p2g of `state`."""
        sparse = weak_points(state, grid_m, grid, self.threshold(state.dim))
        neck = self.holds(state, grid)
        return sparse, jnp.zeros_like(sparse) if neck is None else neck

    def holds(self, state: State, grid: Grid):
        """(N,) bool or None: the points in a neck thinner than neck_thickness (None when it is off),
        whose cells resampling must not refill. A released neck refilled as it is drawn
        out keeps the two pieces joined by a thread that carries no load, so the pieces never
        separate geometrically (measured in experiments/results/fracture_demo.md). The density-ratio
        criterion holds nothing: it is relative to the grid, and resampling exists to refill exactly
        the sparse, grid-thin regions it flags in a stretched sheet."""
        if self.neck_thickness is None:
            return None
        return state.active & (neck_thickness(state, grid, self.neck_thickness) < self.neck_thickness)

    def weak(self, state: State, grid_m, grid: Grid) -> jax.Array:
        """(N,) bool: the weak points of `state` by either criterion."""
        sparse, neck = self.masks(state, grid_m, grid)
        return sparse | neck

    def apply(self, new: State, old: State, grid_m, grid: Grid) -> State:
        """The substep hook: detect weak points at the substep's start (`old`, grid mass `grid_m`
        (G,) kg from its p2g) and release their strain in the updated state `new`; points in a thin
        neck also release compression (see `release`)."""
        sparse, neck = self.masks(old, grid_m, grid)
        return release(new, sparse | neck, volume=neck)


def density_ratio(state: State, grid_m, grid: Grid) -> jax.Array:
    """Neighbourhood density ratio (N,): grid density at each point over the point's own density.

    grid_m: (G,) grid mass, kg, deposited by `state` (p2g). Inactive points get 1.
    """
    x = jax.lax.stop_gradient(state.x)
    idx, w = _weights(x, grid)
    rho_grid = _from_grid(idx, w, jax.lax.stop_gradient(grid_m)[:, None])[:, 0] / grid.dx ** state.dim
    J = det(jax.lax.stop_gradient(state.F))
    vol = state.vol0 * J
    own = jnp.where(vol > 0, state.mass / jnp.where(vol > 0, vol, 1.0), 0.0)
    ratio = jnp.where(own > 0, rho_grid / jnp.where(own > 0, own, 1.0), 1.0)
    return jnp.where(state.active, jax.lax.stop_gradient(ratio), 1.0)


def weak_points(state: State, grid_m, grid: Grid, threshold: float) -> jax.Array:
    """(N,) bool: active points whose neighbourhood density ratio is below `threshold`."""
    return state.active & (density_ratio(state, grid_m, grid) < threshold)


def neck_grid(grid: Grid, h_c: float) -> Grid:
    """The auxiliary grid of the neck-thickness estimate: spacing NECK_GRID * h_c (m), covering `grid`.

    Its spacing depends on h_c only, not on the simulation's dx, so the estimate is resolution
    independent once the points sample the material finely (dx well below h_c)."""
    H = NECK_GRID * float(h_c)
    extent = (np.asarray(grid.shape) - 1) * grid.dx
    shape = tuple(int(k) for k in np.ceil(extent / H).astype(int) + 5)
    origin = tuple((np.asarray(grid.origin) - 2 * H).tolist())
    return Grid(origin=origin, dx=H, shape=shape)


def _smallest_eigenvalue(S):
    """Smallest eigenvalue (N,) of symmetric (N, d, d) matrices, d = 2 or 3, in closed form (the
    trigonometric solution of the characteristic cubic in 3D)."""
    d = S.shape[-1]
    tr = jnp.trace(S, axis1=-2, axis2=-1)
    if d == 2:
        a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        return 0.5 * tr - jnp.sqrt(0.25 * (a - c) ** 2 + b ** 2)
    q = tr / 3.0
    off = S[:, 0, 1] ** 2 + S[:, 0, 2] ** 2 + S[:, 1, 2] ** 2
    p2 = sum((S[:, i, i] - q) ** 2 for i in range(3)) + 2.0 * off
    p = jnp.sqrt(p2 / 6.0)
    ok = p > 1e-30 * jnp.maximum(jnp.abs(q), 1e-300)
    B = (S - q[:, None, None] * jnp.eye(3, dtype=S.dtype)[None]) / jnp.where(ok, p, 1.0)[:, None, None]
    r = jnp.clip(0.5 * det(B), -1.0, 1.0)
    phi = jnp.arccos(r) / 3.0
    return jnp.where(ok, q + 2.0 * p * jnp.cos(phi + 2.0 * np.pi / 3.0), q)


def neck_thickness(state: State, grid: Grid, h_c: float) -> jax.Array:
    """Local thickness of the material around each point (N,), m (stop-gradient values).

    The material's mass around a point, weighted by a smooth kernel of physical width (the B-spline
    of `neck_grid`, std NECK_GRID h_c / sqrt(2) per axis), has a covariance whose smallest eigenvalue
    lambda is the spread across the thinnest direction; the thickness is sqrt(12 lambda), the width
    of a uniform slab of that spread. Each point counts as a small box of its current volume (edge
    (J V0)^(1/d)), so a single file of points is as thick as one point. A thread or sheet of width
    w below about h_c gives about w; a flat surface or a box corner about 1.5 h_c; the bulk about
    2.4 h_c. Inactive points get inf.

    Computed with one deposit (mass, first and second moments about the auxiliary nodes) and one
    gather on the auxiliary grid of spacing NECK_GRID h_c: the estimate depends on h_c and on where
    the material is, not on dx.
    """
    d = state.dim
    aux = neck_grid(grid, h_c)
    H = aux.dx
    x = jax.lax.stop_gradient(state.x)
    dtype = x.dtype
    m = jnp.where(state.active, jax.lax.stop_gradient(state.mass), 0.0)
    J = det(jax.lax.stop_gradient(state.F))
    own = m * jnp.where(state.active & (J > 0), jnp.abs(state.vol0 * J), 0.0) ** (2.0 / d) / 12.0
    pairs = [(i, j) for i in range(d) for j in range(i, d)]           # upper triangle of the moments
    base, fx, w = _stencil(x, aux)
    offs = np.asarray(_offsets(d))                                    # (K, d), static
    wts = _stencil_weights(w, _offsets(d))                            # (K, N)
    rel = [H * (fx[None, :, i] - jnp.asarray(offs[:, i], dtype)[:, None]) for i in range(d)]  # x_p - x_n
    idx = jnp.concatenate([_flat_index(base, off, aux) for off in _offsets(d)])  # (K N,), offset-major
    # Moments of the mass about each node: sum_p w m [1, r, r r^T + edge^2/12 I] (one scatter).
    wm = wts * m[None, :]
    chans = ([wm] + [wm * rel[i] for i in range(d)]
             + [wm * rel[i] * rel[j] + (wts * own[None, :] if i == j else 0.0) for i, j in pairs])
    nodes = jnp.zeros((aux.num_nodes, len(chans)), dtype).at[idx].add(
        jnp.stack(chans, -1).reshape(-1, len(chans)), mode="drop")
    # Gather back and move each node's moments to the point: with s = x_q - x_n and r = x_p - x_n,
    # x_q - x_p = s - r, so S1' = S1 - S0 r and S2' = S2 - S1 r^T - r S1^T + S0 r r^T.
    g = nodes.at[idx].get(mode="fill", fill_value=0.0).reshape(wts.shape + (len(chans),))
    S0, S1 = g[..., 0], [g[..., 1 + i] for i in range(d)]
    M0 = jnp.sum(wts * S0, 0)
    M1 = [jnp.sum(wts * (S1[i] - S0 * rel[i]), 0) for i in range(d)]
    M2 = {(i, j): jnp.sum(wts * (g[..., 1 + d + c] - S1[i] * rel[j] - rel[i] * S1[j] + S0 * rel[i] * rel[j]), 0)
          for c, (i, j) in enumerate(pairs)}
    M0s = jnp.where(M0 > 0, M0, 1.0)
    mean = [M1[i] / M0s for i in range(d)]
    cov = [[None] * d for _ in range(d)]
    for i, j in pairs:
        cov[i][j] = cov[j][i] = M2[(i, j)] / M0s - mean[i] * mean[j]
    lam = jnp.maximum(_smallest_eigenvalue(jnp.stack([jnp.stack(row, -1) for row in cov], -2)), 0.0)
    return jnp.where(state.active & (M0 > 0), jnp.sqrt(12.0 * lam), jnp.inf)


def release(state: State, weak, volume=None) -> State:
    """Release the elastic strain of weak points: bbar_e = I and F = min(J, 1)^(1/d) I (the volume
    ratio J = det F capped at 1, no directional stretch kept); compression (J < 1) is kept, and so is
    the stress, which depends on F only through J. An inverted weak point (J <= 0) keeps its F (the
    rollout's health check reports it).

    volume: optional (N,) bool, weak points whose compression is released too (F = I, no stress at
    all): points that stay weak for many substeps, as in a neck thinner than h_c. Capping J at 1 every
    substep is a ratchet there: J follows the noise of the flow's divergence, its rises are cut off and
    its falls kept, so J drifts down and the compressive pressure it builds sprays the released neck
    apart (on the pulled strip of experiments/fracture_demo.py, up to 20 mm sideways from a 10 mm
    strip with J capped; within its half-width with F = I).
    """
    d = state.dim
    J = det(state.F)
    ok = weak & (J > 0.0)
    iso = jnp.minimum(jnp.where(ok, J, 1.0), 1.0) ** (1.0 / d)
    if volume is not None:
        iso = jnp.where(volume, 1.0, iso)
    eye_d = jnp.eye(d, dtype=state.x.dtype)[None]
    eye3 = jnp.eye(3, dtype=state.x.dtype)[None]
    return state.replace(F=jnp.where(ok[:, None, None], iso[:, None, None] * eye_d, state.F),
                         bbar_e=jnp.where(weak[:, None, None], eye3, state.bbar_e))


def collider_force(state: State, params: Params, scene: Scene, grid: Grid, dt, region=None,
                   colliders=()) -> jax.Array:
    """Force (d,) N (N/m in 2D) that the colliders exert on the material at the start of a substep.

    The grid momentum change the boundary conditions impose, sum_n m_n (v_n^after - v_n^before) / dt,
    over nodes where `region(node_x) -> (G,) bool` is true (all nodes if None). With a region
    around one plate this is that plate's pull on the foam.
    """
    grid_mv, grid_m = p2g(state, params, grid, dt)
    v = safe_div(grid_mv, grid_m[:, None])
    v = v + jnp.where(grid_m[:, None] > 0, dt * scene.gravity.astype(v.dtype)[None, :], 0.0)
    node_x = grid.node_positions(v.dtype)
    touch = floor_touch(state.x, state.vol0, state.active, grid, scene)
    after = apply_colliders(v, node_x, scene, state.t + dt, colliders, grid_m, dt, grid.dx, grid=grid, touch=touch)
    dp = grid_m[:, None] * (after - v) / dt
    if region is not None:
        dp = jnp.where(region(node_x)[:, None], dp, 0.0)
    return jnp.sum(dp, axis=0)
