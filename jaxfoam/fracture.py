"""Fracture of thinning foam (Yue et al. 2015, section 5).

Plain MPM has no fracture: points share forces through the grid while they are within a stencil
of each other, so a stretched thread thins into a chain of single points, one cell apart, that
keeps pulling (numerical strings far longer than real foam makes). This stage, run after the
constitutive update of every substep (`substep(..., fracture=FractureConfig())`), does three things:

1. detect weak points: a point whose neighbourhood holds too little material. The measure is the
   ratio of the grid density interpolated at the point, sum_n w_pn m_n / dx^d, to the point's own
   density m_p / (J_p V0_p): about 1 in the bulk, 0.6 on a flat surface, >= 0.28 (2D) / 0.21 (3D)
   at a box corner, and 0.19 (2D) for a single file of points 0.75 dx apart; below
   `density_ratio` the point is weak (defaults sit between those corner and chain values).
2. drop the resistance along the separating direction and stop accumulating the separation as
   elastic strain: a weak point's elastic shear strain is released (bbar_e = I) and its volumetric
   stretch is released (J = 1 when J > 1; compression is kept, so pieces still push each other),
   and its F becomes the isotropic J^(1/d) I of that volume ratio. Its Kirchhoff stress in the next
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

from ._constitutive import det
from ._mpm import Grid, apply_colliders, p2g, safe_div
from ._params import Params
from ._scene import Scene
from ._state import State
from .resample import _from_grid, _weights

# Default weak-point thresholds of the neighbourhood density ratio, by dimension. Measured on the
# jittered initial sampling (2^d points per cell): the smallest ratio at a box corner is 0.275 (2D)
# and 0.207 (3D); a single file of points 0.75 dx apart gives 0.19 (2D), a 2 x 2 rod of points 1 dx
# apart 0.115 (3D). The thresholds leave intact material intact and break single-file chains.
DEFAULT_DENSITY_RATIO = {2: 0.2, 3: 0.12}


@dataclasses.dataclass(frozen=True)
class FractureConfig:
    """Static fracture settings (hashable: a static argument of the jit-compiled step).

    Attributes:
      density_ratio: a point is weak when its neighbourhood density ratio is below this, in (0, 1)
        (default: DEFAULT_DENSITY_RATIO[d]).
    """

    density_ratio: float | None = None

    def threshold(self, d: int) -> float:
        return DEFAULT_DENSITY_RATIO[d] if self.density_ratio is None else float(self.density_ratio)

    def validate(self, d: int) -> "FractureConfig":
        """Raise ValueError naming the field and its allowed range; return self."""
        thr = self.threshold(d)
        if not 0 < thr < 1:
            raise ValueError(f"FractureConfig.density_ratio must be in (0, 1), got {thr}")
        return self

    def apply(self, new: State, old: State, grid_m, grid: Grid) -> State:
        """The substep hook: detect weak points at the substep's start (`old`, grid mass `grid_m`
        (G,) kg from its p2g) and release their strain in the updated state `new`."""
        weak = weak_points(old, grid_m, grid, self.threshold(old.dim))
        return release(new, weak)


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


def release(state: State, weak) -> State:
    """Release the elastic strain of weak points: bbar_e = I and F = min(J, 1)^(1/d) I (the volume
    ratio J = det F capped at 1, no directional stretch kept); compression (J < 1) is kept, and so is
    the stress, which depends on F only through J. An inverted weak point (J <= 0) keeps its F (the
    rollout's health check reports it)."""
    d = state.dim
    J = det(state.F)
    ok = weak & (J > 0.0)
    iso = jnp.minimum(jnp.where(ok, J, 1.0), 1.0) ** (1.0 / d)
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
    after = apply_colliders(v, node_x, scene, state.t + dt, colliders)
    dp = grid_m[:, None] * (after - v) / dt
    if region is not None:
        dp = jnp.where(region(node_x)[:, None], dp, 0.0)
    return jnp.sum(dp, axis=0)
