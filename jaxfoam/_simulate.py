"""Rollouts: the CFL time step, a jit-compiled scan over frames of substeps, and failure reports."""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ._compile_guard import release_if_near_map_limit
from ._constitutive import deviatoric_stress_norm, det
from ._mpm import Grid, _substep, from_components, make_grid, make_step, sort_by_cell, to_components, unsort
from ._params import Params
from ._scene import Scene, init_state
from ._state import State

# CFL number C in dt <= C dx / (c + max|v|): 0.3 stays stable with margin across the stiffness
# range of foams (model.md suggests 0.3-0.5; experiments measure where it fails).
CFL = 0.3
# Free-fall speed bound uses the domain height; this factor leaves room for splashes and rebounds.
SPEED_SAFETY = 1.5

STATE_FIELDS = ("x", "v", "C", "F", "bbar_e")
# Reverse mode: every substep is a `jax.checkpoint` whose backward pass recomputes the substep from
# its input state, except for these named values, which the frame's recomputation stores per substep:
# the plastic rate of the return map ("hb_gamma", jaxfoam._constitutive), the g2p velocity and
# velocity gradient ("g2p") and the p2g grid momentum and mass ("p2g_grid", jaxfoam._mpm), so the
# solve, the gather and the scatter are not redone there. The remaining recomputation is elementwise
# work that XLA fuses into the transpose's kernels. docs/gradients.md has the measurements.
REMAT_SAVED = ("hb_gamma", "g2p", "p2g_grid")
# Reorder the particles by grid cell at the start of every frame (and restore the order at its end,
# so particle i stays particle i in every output): scatter and gather then touch neighbouring memory;
# +17% (2D) / +26% (3D) particle-steps/s on randomly ordered particles, for one argsort per frame.
SORT_BY_CELL = True
# Reverse mode recomputes each frame storing every substep's input state and REMAT_SAVED values. When
# that store would exceed this many bytes, the frame's substeps run as checkpointed blocks (at most
# ~sqrt(substeps) of them), for one more forward pass of each frame. On the 2D hanging plate at dx 2.5 mm
# (72 substeps per frame), 3 / 9 blocks took the working memory from 124 to 56 / 37 MB at 0.80x / 0.76x
# the reverse-mode speed. 512 MB keeps scenes of that size on one level; large 3D scenes get blocks.
FRAME_TAPE_BYTES = 512 * 2 ** 20


def checkpoint_blocks(state0: State, grid: Grid, substeps: int, budget: float = FRAME_TAPE_BYTES) -> int:
    """Checkpointed blocks per frame for reverse mode: 1 while a frame's store (per substep: the
    state, the rate, g2p's v and C per particle and p2g's d + 1 values per node) fits in `budget`
    bytes, else enough blocks to fit, at most ceil(sqrt(substeps)) (beyond that blocks do not help)."""
    n, d = state0.x.shape
    item = jnp.dtype(state0.x.dtype).itemsize
    per = sum(np.dtype(a.dtype).itemsize * a.size for a in jax.tree_util.tree_leaves(state0))
    per += item * (n * (1 + d + d * d) + grid.num_nodes * (d + 1))
    need = math.ceil(substeps * per / budget)
    return 1 if need <= 1 else min(need, max(2, math.isqrt(substeps - 1) + 1))


class SimulationError(FloatingPointError):
    """A rollout turned non-finite (or inverted); the message says at which frame, time and particle."""


def _value(x) -> float:
    """The float value of a scalar: concrete, or the primal value of a tracer of jax.grad / jax.jvp /
    jax.jacfwd run outside jit (the time step is picked from it and held fixed, not differentiated).
    Inside jit (or vmap) there is no value: ValueError."""
    try:
        return float(jax.lax.stop_gradient(x))
    except (TypeError, jax.errors.ConcretizationTypeError) as exc:
        raise ValueError("the time step needs the values of kappa, mu and rho, which jit and vmap do not "
                         "have: call jaxfoam.simulate / build the Simulator outside jit (jax.grad, jax.jvp "
                         "and jax.jacfwd of it work), and jit Simulator.rollout instead") from exc


def wave_speed(params: Params) -> float:
    """Elastic P-wave speed c = sqrt((kappa + 4/3 mu) / rho), m/s, from the parameters' values (under
    jax.grad / jvp outside jit, their primal values)."""
    kappa, mu, rho = (_value(params.kappa), _value(params.mu), _value(params.rho))
    return math.sqrt((kappa + 4.0 / 3.0 * mu) / rho)


def speed_bound(scene: Scene) -> float:
    """A bound of material speeds, m/s: plate speed, free fall over the domain height, initial velocity."""
    g = float(np.linalg.norm(np.asarray(scene.gravity)))
    height = float(np.max(np.asarray(scene.domain_max) - np.asarray(scene.domain_min)))
    v0 = float(np.linalg.norm(scene.initial_velocity)) if scene.initial_velocity else 0.0
    return SPEED_SAFETY * (math.sqrt(2.0 * g * height) + scene.max_plate_speed() + v0)


def stable_dt(params: Params, dx: float, max_speed: float, cfl: float = CFL) -> float:
    """The CFL time step C dx / (c + max|v|), s."""
    return cfl * dx / (wave_speed(params) + max_speed)


def observe_default(state: State, params: Params) -> dict:
    """Per-frame record: positions x (N, d) m, velocities v m/s, plastic rate gamma_dot 1/s,
    deviatoric stress magnitude s Pa, volume ratio J, active mask."""
    return dict(x=state.x, v=state.v, gamma_dot=state.gamma_dot,
                s=deviatoric_stress_norm(state.bbar_e, params), J=det(state.F), active=state.active)


def _health(state: State):
    """Per field of STATE_FIELDS: whether all active values are finite, and the first bad particle."""
    ok, first = [], []
    for name in STATE_FIELDS:
        a = getattr(state, name)
        good = jnp.all(jnp.isfinite(a.reshape(a.shape[0], -1)), axis=1) | ~state.active
        ok.append(jnp.all(good))
        first.append(jnp.argmin(good))
    J = det(state.F)
    inverted = (J <= 0) & state.active
    ok.append(~jnp.any(inverted))
    first.append(jnp.argmax(inverted))
    return jnp.stack(ok), jnp.stack(first).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class Plan:
    """Static rollout configuration: frame times (T,) s and substeps per frame."""

    frame_times: tuple
    substeps: int
    t0: float

    @property
    def frame_dts(self) -> np.ndarray:
        t = np.asarray((self.t0,) + self.frame_times)
        return np.diff(t) / self.substeps


def _rollout_impl(state0, params, scene, frame_times, frame_dts, grid, substeps, observe, checkpoint,
                  resample=None, fracture=None, colliders=(), sort=SORT_BY_CELL, hand_adjoint=False,
                  blocks=1):
    def frame(state, inputs):
        t_target, dt = inputs[:2]

        def _resample_pass(s, n):
            # Cells of a fracturing neck are not refilled (FractureConfig.holds; None when off).
            st = from_components(s)
            hold = None if fracture is None else fracture.holds(st, grid)
            return to_components(resample.apply(st, grid, n, hold))

        # Within a frame the state is carried in component form (jaxfoam._mpm.to_components).
        def sub(s, i):
            s = _substep(s, params, scene, grid, dt, fracture, colliders, hand_adjoint)
            if resample is not None:
                # Resampling pass after every `resample.every`-th substep of the whole rollout.
                n = inputs[2] * substeps + i + 1
                s = jax.lax.cond(n % resample.every == 0, lambda s: _resample_pass(s, n), lambda s: s, s)
            return s, None

        state = to_components(state)
        if sort:
            state, perm = sort_by_cell(state, grid)

        xs = None if resample is None else jnp.arange(substeps)
        if checkpoint:
            policy = jax.checkpoint_policies.save_only_these_names(*REMAT_SAVED)
            sub_ck = jax.checkpoint(sub, policy=policy)
            if blocks > 1:
                # Blocks of `size` substeps (the last one shorter), each a checkpoint (FRAME_TAPE_BYTES).
                size = -(-substeps // blocks)
                full, rest = divmod(substeps, size)
                block = jax.checkpoint(lambda s, idx: (jax.lax.scan(sub_ck, s, idx)[0], None))
                state, _ = jax.lax.scan(block, state, jnp.arange(full * size).reshape(full, size))
                if rest:
                    state, _ = block(state, jnp.arange(full * size, substeps))
            else:
                state, _ = jax.lax.scan(sub_ck, state, xs, length=substeps)
        else:
            state, _ = jax.lax.scan(sub, state, xs, length=substeps)
        if sort:
            state = unsort(state, perm)
        state = from_components(state).replace(t=t_target)
        return state, (observe(state, params), _health(state))

    if checkpoint:
        # Reverse mode stores one state per frame and recomputes the frame, storing each substep's
        # input state and REMAT_SAVED values; each substep is then recomputed (elementwise parts only)
        # inside its backward pass: peak memory grows with the number of frames and the substeps per
        # frame, not with the total number of substeps.
        frame = jax.checkpoint(frame)
    xs = (frame_times, frame_dts) if resample is None else (frame_times, frame_dts, jnp.arange(len(frame_times)))
    final, (frames, health) = jax.lax.scan(frame, state0, xs)
    return final, frames, health


_rollout_jit = jax.jit(_rollout_impl, static_argnames=("grid", "substeps", "observe", "checkpoint", "resample",
                                                       "fracture", "colliders", "sort", "hand_adjoint",
                                                       "blocks"))


class Simulator:
    """A scene bound to a resolution and frame times (the static configuration, bound once).

    Args:
      scene: a parsed Scene (`load_scene`).
      frame_times: (T,) increasing times, s, after the start time, at which frames are recorded.
      params: reference parameters used for the CFL time step (the rollout may be called with others;
        the step stays stable while the wave speed does not grow much).
      dx: grid spacing, m.  ppc: particles per cell (default 4 in 2D, 8 in 3D).
      dtype: jnp.float32 or jnp.float64.  cfl: CFL number.  first_mask: (mask, camera) for
      initial_shape 'first_mask'.  seed: sampling seed.  capacity: particle slots (>= sampled count).
      max_speed: override of the material speed bound, m/s.  substeps: override of substeps per frame.
      resample: a `jaxfoam.resample.ResampleConfig` (or None): particle resampling every
        `resample.every` substeps inside the rollout; with no capacity given, the state gets
        `resample.capacity_factor` times the sampled number of slots.
      fracture: a `jaxfoam.fracture.FractureConfig` (or None): the fracture stage of each substep.
      colliders: a tuple of extra colliders (e.g. `jaxfoam.sdf.SDFCollider`), applied on the grid.
      sort: reorder particles by grid cell during each frame (SORT_BY_CELL; outputs keep the order).
      frame_tape_bytes: reverse mode's per-frame store, bytes, above which a frame's substeps are
        checkpointed in blocks (FRAME_TAPE_BYTES; see `checkpoint_blocks`).
    Attributes: grid, state0, plan, dt (largest substep, s), substeps, step (the pure
      `step(state, params)` at dt), checkpoint_blocks (checkpointed blocks per frame in reverse mode;
      1 = each frame recomputed as a whole).
    """

    def __init__(self, scene: Scene, frame_times, params: Params, dx: float, ppc: int | None = None,
                 dtype=jnp.float64, cfl: float = CFL, first_mask=None, seed: int = 0,
                 capacity: int | None = None, max_speed: float | None = None, substeps: int | None = None,
                 state0: State | None = None, resample=None, fracture=None, colliders=(),
                 sort: bool = SORT_BY_CELL, frame_tape_bytes: float = FRAME_TAPE_BYTES):
        params.validate()
        if not (isinstance(frame_tape_bytes, (int, float)) and frame_tape_bytes > 0):
            raise ValueError(f"frame_tape_bytes must be a positive number of bytes, got {frame_tape_bytes!r}")
        if not (isinstance(dx, (int, float)) and dx > 0 and math.isfinite(dx)):
            raise ValueError(f"dx must be a positive grid spacing in m, got {dx!r}")
        if not (0 < cfl <= 1.0):
            raise ValueError(f"cfl must be in (0, 1], got {cfl}")
        if dtype not in (jnp.float32, jnp.float64, np.float32, np.float64):
            raise ValueError(f"dtype must be float32 or float64, got {dtype}")
        if dtype in (jnp.float64, np.float64) and not jax.config.jax_enable_x64:
            raise ValueError("dtype float64 needs jax.config.update('jax_enable_x64', True) "
                             "(importing jaxfoam enables it unless JAXFOAM_X64=0)")
        times = np.asarray(frame_times, float).ravel()
        if times.size == 0 or not np.all(np.isfinite(times)):
            raise ValueError("frame_times must be a non-empty list of finite times in s")
        # A process that binds many simulators (fits of many datasets or grids) frees its compiled
        # programs before it runs out of memory mappings (jaxfoam._compile_guard).
        release_if_near_map_limit()
        self.scene = scene
        self.dtype = jnp.dtype(dtype)
        self.dx = float(dx)
        self.grid: Grid = make_grid(scene, dx)
        self.state0 = state0 if state0 is not None else init_state(
            scene, dx, ppc, rho=_value(params.rho), seed=seed, first_mask=first_mask, capacity=capacity,
            dtype=dtype)
        self.resample, self.fracture, self.colliders = resample, fracture, tuple(colliders)
        self.sort = bool(sort)
        if resample is not None:
            resample.validate(scene.dim)
            if capacity is None:
                self.state0 = resample.prepare(self.state0)
        t0 = float(self.state0.t)
        if np.any(np.diff(np.concatenate([[t0], times])) <= 0):
            raise ValueError(f"frame_times must be strictly increasing and after the start time {t0} s")
        self.max_speed = speed_bound(scene) if max_speed is None else float(max_speed)
        if max_speed is None and self.colliders:
            self.max_speed += SPEED_SAFETY * max(c.max_speed() for c in self.colliders)
        self.dt_cfl = stable_dt(params, dx, self.max_speed, cfl)
        widest = float(np.max(np.diff(np.concatenate([[t0], times]))))
        n = int(math.ceil(widest / self.dt_cfl - 1e-9)) if substeps is None else int(substeps)
        if n < 1:
            raise ValueError(f"substeps must be >= 1, got {n}")
        self.plan = Plan(frame_times=tuple(times.tolist()), substeps=n, t0=t0)
        self.checkpoint_blocks = checkpoint_blocks(self.state0, self.grid, n, frame_tape_bytes)
        self.dt = widest / n
        self.step = make_step(scene, self.grid, self.dt, fracture, self.colliders)

    @property
    def substeps(self) -> int:
        """Substeps per frame (every frame has the same count; its dt is the frame interval / count)."""
        return self.plan.substeps

    @property
    def total_substeps(self) -> int:
        return self.plan.substeps * len(self.plan.frame_times)

    def rollout(self, params: Params, state0: State | None = None, scene: Scene | None = None,
                observe: Callable = observe_default, checkpoint: bool = True, hand_adjoint: bool = False):
        """Pure, jit-compiled, differentiable rollout: returns (final State, frames pytree (T, ...), health).

        Differentiate with respect to params, state0 or the scene's data leaves (gravity, plate
        motion). `observe(state, params)` picks what each frame records (must be a hashable function).
        checkpoint: per-frame rematerialization for reverse mode (no cost in a forward run).
        hand_adjoint: reverse mode through the hand-written derivatives of particle-to-grid and
          grid-to-particle (`jaxfoam._mpm._p2g_transfer`, `_g2p_transfer`): the same gradient, faster
          (docs/gradients.md); the rollout is then differentiable in reverse mode only (grad, vjp,
          jacrev), not in forward mode (jvp, jacfwd). `observable_jacobian(mode="rev")` sets it.
        """
        state0 = self.state0 if state0 is None else state0
        scene = self.scene if scene is None else scene
        params = params.astype(self.dtype)
        # The scene's data leaves (gravity, plate motion) follow the simulation's precision.
        scene = jax.tree_util.tree_map(lambda a: jnp.asarray(a, self.dtype), scene)
        return _rollout_jit(state0, params, scene, jnp.asarray(self.plan.frame_times, self.dtype),
                            jnp.asarray(self.plan.frame_dts, self.dtype), self.grid, self.plan.substeps,
                            observe, checkpoint, self.resample, self.fracture, self.colliders, self.sort,
                            hand_adjoint, self.checkpoint_blocks)

    def check(self, frames, health) -> None:
        """Raise SimulationError naming the first frame, time, quantity and particle that went bad."""
        ok, first = jax.device_get(health)
        bad = ~ok
        if not bad.any():
            return
        k = int(np.argmax(bad.any(axis=1)))
        q = int(np.argmax(bad[k]))
        name = (STATE_FIELDS + ("J <= 0 (inverted)",))[q]
        p = int(first[k, q])
        where = ""
        if isinstance(frames, dict) and "x" in frames and k > 0:  # frame 0 has no recorded predecessor
            where = f" at position {np.asarray(frames['x'][k - 1, p]).tolist()} m (previous frame)"
        raise SimulationError(
            f"simulation became non-finite at frame {k} (t = {self.plan.frame_times[k]:.6g} s, "
            f"within substeps of dt = {self.dt:.3g} s): first bad quantity '{name}' at particle {p}{where}. "
            f"Reduce the time step (dt = {self.dt:.3g} s, CFL bound {self.dt_cfl:.3g} s: lower cfl or "
            f"leave substeps to the CFL bound) or dx, "
            f"or check the parameters.")


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A finished rollout: frames (dict of (T, N, ...) arrays), frame times (T,) s, final state, and
    the discretization used (dx m, dt s, substeps per frame)."""

    frames: dict
    times: np.ndarray
    final: State
    dx: float
    dt: float
    substeps: int
    scene: Scene
    params: Params


def _traced(tree) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(tree))


def simulate(scene: Scene, params: Params, frame_times, dx: float, ppc: int | None = None,
             dtype=jnp.float64, **kwargs) -> Trajectory:
    """Simulate a scene and return the frames at `frame_times` (s). Validates inputs first; raises
    SimulationError if the rollout turns non-finite. Keyword arguments go to `Simulator`.

    Differentiable with respect to `params` by jax.grad, jax.vjp, jax.jvp and jax.jacfwd called
    outside jit: the frames then come back as JAX arrays. The time step and substeps are chosen from
    the parameters' values and held fixed (the derivative is that of the discrete map, as for
    `Simulator.rollout`); the particle masses are rho * vol0 (unless a `state0` is passed), so d/d rho
    flows through them. Inside jit or vmap it raises ValueError (no parameter values). Each call
    builds a Simulator (sampling, and a compile the first time for a configuration): for many
    gradients of one setup, build a Simulator once and differentiate `Simulator.rollout`.
    """
    sim = Simulator(scene, frame_times, params, dx, ppc, dtype=dtype, **kwargs)
    traced = _traced(params)
    state0 = sim.state0
    if traced and "state0" not in kwargs:
        # The sampled masses are vol0 * rho's value; with rho as a derivative input they carry its tangent.
        state0 = state0.replace(mass=jnp.asarray(params.rho, state0.vol0.dtype) * state0.vol0)
    final, frames, health = sim.rollout(params, state0=state0)
    if traced:
        value = lambda tree: jax.tree_util.tree_map(jax.lax.stop_gradient, tree)
        sim.check(value(frames), value(health))
    else:
        sim.check(frames, health)
        frames = jax.device_get(frames)
    return Trajectory(frames=frames, times=np.asarray(sim.plan.frame_times), final=final,
                      dx=sim.dx, dt=sim.dt, substeps=sim.substeps, scene=scene, params=params)
