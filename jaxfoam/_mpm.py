"""One MLS-MPM substep in named stages: p2g -> grid_update -> g2p -> constitutive [-> fracture].

Dimension-generic: d = x.shape[-1]; the 3^d stencil is unrolled at trace time as elementwise (N,)-array
operations. Every stage has the signature `stage(model, params, work) -> work` (`Work` carries the
substep's state and intermediate grid and particle fields); `jaxfoam.step` chains them. The transfers'
memory layout and speed-only derivative rules live in `jaxfoam._xla_cpu`.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from . import _tensor as T
from ._boundary import _clamp, apply_colliders, floor_touch, particle_floor
from ._constitutive import _kirchhoff, _return_map_components
from ._grid import Grid, _flat_index, _stencil
from ._model import Model
from ._params import Params
from ._scene import Scene
from ._state import State
from ._xla_cpu import Tuning, tuning_for
from ._xla_cpu.layout import _bbar_comps, _bbar_pack, _comps, from_components, to_components
from ._xla_cpu.transfers import g2p_transfer, p2g_transfer


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


def p2g(state: State, params: Params, grid: Grid, dt, idx0=None, hand_adjoint: bool = False,
        tuning: Tuning | None = None) -> tuple[jax.Array, jax.Array]:
    """Particle to grid: scatter mass and momentum (including the MLS-MPM stress impulse).

    idx0: optional (N,) flat grid index of each particle's stencil base (computed from x if None).
    hand_adjoint: the scatter's reverse-mode derivative is the hand-written one (`jaxfoam.adjoint.HandWritten`):
      the result is then not forward-differentiable (jvp, jacfwd).
    tuning: speed choices (default: the backend's).
    Returns (grid momentum (G, d) kg m/s, grid mass (G,) kg). Inactive particles carry zero mass
    and volume and contribute nothing. `state` may be in either form (`to_components`).
    """
    tuning = tuning_for() if tuning is None else tuning
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
    grid_mv = p2g_transfer(grid, tuning, x, idx0, mvA, A, mass, state.t, hand_adjoint)
    # Reverse mode: the grid cotangent as a buffer before the gather that transposes this scatter (the
    # hand-written adjoint does it itself); the grid is kept per substep by the checkpoint policy.
    if not hand_adjoint:
        grid_mv = tuning.tangent_buffer("grid_momentum", grid_mv, dt)
    return checkpoint_name(grid_mv, "p2g_grid")


def g2p(state: State, grid_v, grid: Grid, tuning: Tuning | None = None) -> tuple[jax.Array, jax.Array]:
    """Grid to particle: APIC velocity (N, d) m/s and affine matrix / velocity gradient C (N, d, d) 1/s."""
    v, C = _g2p(state, grid_v, grid, tuning=tuning_for() if tuning is None else tuning)
    return v, T.array(C, state.x[:, 0])


def _g2p(state: State, grid_v, grid: Grid, idx0=None, hand_adjoint: bool = False, *, tuning: Tuning):
    """`g2p` with C returned as components (rows of (N,) arrays), 1/s; `hand_adjoint` as in `p2g`."""
    if idx0 is None:
        idx0 = _flat_index(_stencil(state.x, grid)[0], (0,) * state.dim, grid)
    return g2p_transfer(grid, tuning, state.x, grid_v, idx0, state.t, hand_adjoint)


def constitutive(state: State, v, C, params: Params, grid: Grid, dt, scene: Scene | None = None,
                 tuning: Tuning | None = None) -> State:
    """Advance F and bbar_e with f = I + dt C (eq. 11-16), advect positions, keep them on the grid.

    v (N, d) m/s and C (N, d, d) 1/s from `g2p`; returns the state in the form it was given in.
    scene: with a floor of particle contact, `particle_floor` limits v before the advection."""
    tuning = tuning_for() if tuning is None else tuning
    new = _constitutive(to_components(state), v, _comps(C), params, grid, dt, scene, tuning)
    return new if isinstance(state.F, tuple) else from_components(new)


def _constitutive(state: State, v, Cc, params: Params, grid: Grid, dt, scene: Scene | None,
                  tuning: Tuning) -> State:
    """`constitutive` on the component form (`to_components`), C given as components."""
    d = state.dim
    if scene is not None and scene.particle_contact_floor:
        v = particle_floor(state.x, v, state.vol0, scene, dt)
    like = state.x[:, 0]
    fc = T.add_diag(T.scale(Cc, dt), 1.0)
    F = T.matmul(fc, state.F)
    b_old = _bbar_comps(state.bbar_e)
    bc, _, gamma = _return_map_components(b_old, _pad3(fc), params, dt, tuning)
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




def grid_update(grid_mv, grid_m, scene: Scene, grid: Grid, t, dt, colliders=(), touch=None,
                tuning: Tuning | None = None) -> jax.Array:
    """Grid velocities (G, d) m/s at the end of the substep: momentum / mass, gravity, colliders
    (touch: `floor_touch`'s nodes, for a floor with particle contact)."""
    tuning = tuning_for() if tuning is None else tuning
    v = safe_div(grid_mv, grid_m[:, None])
    v = v + jnp.where(grid_m[:, None] > 0, dt * scene.gravity.astype(v.dtype)[None, :], 0.0)
    # Derivative programs: v with its tangent as buffers, which the colliders' tangent kernels read.
    v = tuning.linearization_buffer("grid_velocity", v, dt)
    return apply_colliders(v, grid.node_positions(v.dtype), scene, t + dt, colliders, grid_m, dt, grid.dx,
                           grid=grid, touch=touch, tuning=tuning)


@dataclasses.dataclass(frozen=True)
class Work:
    """What one substep's stages pass on (a trace-time container, not a pytree).

    state: the substep's input State (component form); dt: the substep, s; hand_adjoint: reverse mode
    through the transfers' hand-written derivatives. Filled in by the stages: idx0 (N,) stencil base
    index; grid_mv (G, d) kg m/s and grid_m (G,) kg; touch (G,) bool or None; grid_v (G, d) m/s;
    v (N, d) m/s and C (components) 1/s; new, the updated State."""

    state: State
    dt: object
    hand_adjoint: bool = False
    idx0: object = None
    grid_mv: object = None
    grid_m: object = None
    touch: object = None
    grid_v: object = None
    v: object = None
    C: object = None
    new: State | None = None

    def replace(self, **changes) -> "Work":
        return dataclasses.replace(self, **changes)


def locate(model: Model, params: Params, w: Work) -> Work:
    """Each particle's stencil base index, once per substep for both transfers."""
    s = w.state
    idx0 = model.tuning.buffer("stencil_index", _flat_index(_stencil(s.x, model.grid)[0], (0,) * s.dim, model.grid),
                               s.t)
    return w.replace(idx0=idx0)


def p2g_stage(model: Model, params: Params, w: Work) -> Work:
    grid_mv, grid_m = p2g(w.state, params, model.grid, w.dt, w.idx0, w.hand_adjoint, model.tuning)
    return w.replace(grid_mv=grid_mv, grid_m=grid_m)


def grid_stage(model: Model, params: Params, w: Work) -> Work:
    s = w.state
    touch = floor_touch(s.x, s.vol0, s.active, model.grid, model.scene, w.idx0)
    grid_v = grid_update(w.grid_mv, w.grid_m, model.scene, model.grid, s.t, w.dt, model.colliders, touch,
                         model.tuning)
    return w.replace(touch=touch, grid_v=grid_v)


def g2p_stage(model: Model, params: Params, w: Work) -> Work:
    v, C = _g2p(w.state, w.grid_v, model.grid, w.idx0, w.hand_adjoint, tuning=model.tuning)
    # Named: kept by reverse mode's per-substep rematerialization (jaxfoam.adjoint.REMAT_SAVED).
    v, C = checkpoint_name((v, C), "g2p")
    return w.replace(v=v, C=C)


def constitutive_stage(model: Model, params: Params, w: Work) -> Work:
    new = _constitutive(w.state, w.v, w.C, params, model.grid, w.dt, model.scene, model.tuning)
    return w.replace(new=new)


def fracture_stage(model: Model, params: Params, w: Work) -> Work:
    frac = model.fracture.apply(from_components(w.new), from_components(w.state), w.grid_m, model.grid)
    return w.replace(new=to_components(frac))


def stages(model: Model) -> tuple:
    """The substep's stages, in order, as (name, stage) pairs."""
    out = [("locate", locate), ("p2g", p2g_stage), ("grid_update", grid_stage), ("g2p", g2p_stage),
           ("constitutive", constitutive_stage)]
    if model.fracture is not None:
        out.append(("fracture", fracture_stage))
    return tuple(out)


def substep(model: Model, state: State, params: Params, dt=None, hand_adjoint: bool = False) -> State:
    """One substep on the component form (`to_components`) of `state`, of length dt s (default
    model.dt); the stages under their `jax.named_scope`s."""
    w = Work(state=state, dt=model.dt if dt is None else dt, hand_adjoint=hand_adjoint)
    for name, stage in stages(model):
        with jax.named_scope(name):
            w = stage(model, params, w)
    return w.new


def step(model: Model, state: State, params: Params) -> State:
    """The pure MLS-MPM step: `state` advanced by model.dt s under `params` (`jax.jit(jaxfoam.step)`).

    Returns the state in the form it was given in (arrays, or the component form a loop of steps runs
    faster on: `jaxfoam._xla_cpu.layout.to_components`). Concrete parameters out of range raise
    ValueError naming the field (`Params.validate`; traced ones under jit pass)."""
    params.validate()
    new = substep(model, to_components(state), params)
    return new if isinstance(state.F, tuple) else from_components(new)
