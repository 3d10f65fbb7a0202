"""Boundary conditions on the grid and on particles: plates, the floor, the domain walls, colliders."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._grid import Grid, _flat_index, _offset_index, _offsets, _stencil
from ._scene import Scene
from ._xla_cpu import Tuning, tuning_for
from ._xla_cpu.fold import IN_BOUNDS as _IN_BOUNDS


# max(x, 0), min(x, 0) and clipping as selects (NaN passes through, as with jnp.maximum). The derivative
# of a select is a select; jnp.maximum's derivative splits ties half and half, which costs compares and
# a division per element in the transposed program (the colliders' transpose over the grid nodes).
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


def _next_out(field, axis: int, side: int):
    """field (*grid shape, d) shifted so each node holds its neighbour one cell along `side` (+1 or -1) of
    `axis` (the last layer repeats itself)."""
    n = field.shape[axis]
    if side > 0:
        idx = np.minimum(np.arange(n) + 1, n - 1)
    else:
        idx = np.maximum(np.arange(n) - 1, 0)
    return jnp.take(field, idx, axis=axis)


def _face_grip(v, rel, half_size, vp, grid: Grid):
    """Grip "face" outside a sticky box (`Plate.grip`): nodes 0 < d < dx outside it (Chebyshev distance d,
    m) take vp + (v_next - vp) d / (d + dx), v_next the node one cell further out along the axis of the
    largest excess, so the velocity profile reaches vp at the face; along that axis's outward normal only
    where this pushes the node outward relative to its own velocity. v (G, d) m/s, rel (G, d) m node
    minus plate centre, half_size (d,) m, vp (d,) m/s."""
    d = v.shape[-1]
    excess = jnp.abs(rel) - half_size[None, :]
    dist = jnp.max(_pos_part(excess), axis=-1)
    axis = jnp.argmax(excess, axis=-1)
    band = (dist > 0) & (dist < grid.dx)
    field = v.reshape(tuple(grid.shape) + (d,))
    nxt = jnp.zeros_like(v)
    for k in range(d):
        for side in (1, -1):
            pick = (axis == k) & ((rel[:, k] > 0) if side > 0 else (rel[:, k] <= 0))
            nxt = jnp.where(pick[:, None], _next_out(field, k, side).reshape(-1, d), nxt)
    frac = dist / (dist + grid.dx)
    target = vp[None, :] + frac[:, None] * (nxt - vp[None, :])
    # Along the face normal the band only pushes (the plate approaching): it never pulls material the
    # nodes inside the plate do not hold.
    normal = jax.nn.one_hot(axis, d, dtype=v.dtype) * jnp.sign(jnp.take_along_axis(rel, axis[:, None], -1))
    push = sum((target[:, k] - v[:, k]) * normal[:, k] for k in range(d))
    target = target - _neg_part(push)[:, None] * normal
    return jnp.where(band[:, None], target, v)


def _wall_rule(vk, low: bool):
    """A slip wall on velocity component k at a node on or beyond it: the outward part removed."""
    return _pos_part(vk) if low else _neg_part(vk)


def _floor_layers(grid: Grid, dtype, floor_y: float) -> int:
    """How many leading node layers along y lie at or below the floor (the comparison, in `dtype`,
    that the mask form of `apply_colliders` makes on the node positions)."""
    pos = (grid.origin[1] + grid.dx * np.arange(grid.shape[1])).astype(dtype)
    return int(np.sum(pos <= np.asarray(floor_y, dtype)))


def apply_colliders(v, node_x, scene: Scene, t, colliders=(), grid_m=None, dt=None, dx=None,
                    grid: Grid | None = None, touch=None, tuning: Tuning | None = None) -> jax.Array:
    """Boundary conditions on grid velocities v (G, d) m/s at nodes node_x (G, d) m, time t s.

    - plates: nodes inside a plate take its velocity (sticky; with grip "face" those within a cell
      outside it take the velocity interpolated between the face and the next node out, `Plate`) or
      lose the approaching normal component relative to it (slip);
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
    every node: the same values, for a fraction of the work.
    tuning: speed choices (default: the backend's).
    """
    tuning = tuning_for() if tuning is None else tuning
    d = v.shape[-1]
    for plate in scene.plates:
        c, vp = tuning.buffer("plate_motion", (plate.position(t), plate.velocity(t)), t)
        rel = node_x - c[None, :]
        inside = jnp.all(jnp.abs(rel) <= plate.half_size[None, :], axis=-1)
        if plate.sticky and plate.grip == "face":
            if grid is None:
                raise ValueError("a plate with grip 'face' needs the grid (apply_colliders(..., grid=...))")
            v = jnp.where(inside[:, None], vp[None, :], _face_grip(v, rel, plate.half_size, vp, grid))
        elif plate.sticky:
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
                raise ValueError("a floor with particle contact needs `touch` (jaxfoam._boundary.floor_touch)")
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
