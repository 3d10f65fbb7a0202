"""Simulator (a Model bound to an initial state and frame times), simulate, and failure reports."""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ._compile_guard import release_if_near_map_limit
from ._errors import JaxfoamError
from ._model import CFL, Model, _value, make_model
from ._params import Params
from ._rollout import HEALTH_NAMES, observe_default, rollout
from ._scene import Scene
from ._state import State
from ._xla_cpu import tuning_for
from .adjoint import FRAME_TAPE_BYTES, Checkpointed, checkpoint_blocks


class SimulationError(JaxfoamError, FloatingPointError):
    """A rollout turned non-finite (or inverted); the message says at which frame, time and particle."""


@dataclasses.dataclass(frozen=True)
class Plan:
    """A simulator's frame plan: frame times (T,) s, substeps per frame, start time t0 s."""

    frame_times: tuple
    substeps: int
    t0: float

    @property
    def frame_dts(self) -> np.ndarray:
        """The substep of each frame, s: its interval / substeps."""
        return np.diff(np.asarray((self.t0,) + self.frame_times)) / self.substeps


class Simulator:
    """A `Model` bound to an initial state and frame times: `jaxfoam.rollout` with those filled in.

    Args:
      scene: a parsed Scene (`load_scene`).
      frame_times: (T,) increasing times, s, after the start time, at which frames are recorded.
      params: reference parameters used for the CFL time step (the rollout may be called with others;
        the step stays stable while the wave speed does not grow much).
      dx: grid spacing, m.  ppc: particles per cell (default 4 in 2D, 8 in 3D).
      dtype: jnp.float32 or jnp.float64.  cfl: CFL number.  first_mask: (mask, camera) for
      initial_shape 'first_mask'.  seed: sampling seed.  capacity: particle slots (>= sampled count).
      state0: an initial state instead of sampling the scene.
      Every other keyword (max_speed, substeps, resample, fracture, colliders, tuning) goes to
      `make_model`; sort=False turns off the tuning's sorting by cell.
    Attributes: model, grid, state0, frame_times (T,) s, plan (`Plan`), dt (largest substep, s), dt_cfl, substeps,
      step (`jaxfoam.step` bound to the model), checkpoint_blocks (reverse mode's blocks per frame).
    """

    def __init__(self, scene: Scene, frame_times, params: Params, dx: float, ppc: int | None = None,
                 dtype=jnp.float64, cfl: float = CFL, first_mask=None, seed: int = 0,
                 capacity: int | None = None, state0: State | None = None, sort: bool | None = None,
                 **model_options):
        params.validate()
        # A process that binds many simulators (fits of many datasets or grids) frees its compiled
        # programs before it runs out of memory mappings (jaxfoam._compile_guard).
        release_if_near_map_limit()
        if sort is not None:
            base = model_options.get("tuning") or tuning_for()
            model_options["tuning"] = base.replace(sort_by_cell=bool(sort))
        t0 = 0.0 if state0 is None else float(state0.t)
        self.model: Model = make_model(scene, dx, params_ref=params, frame_times=frame_times, t0=t0, ppc=ppc,
                                       cfl=cfl, dtype=dtype, **model_options)
        self.scene = scene
        if state0 is None:
            state0 = self.model.sample(rho=_value(params.rho), seed=seed, first_mask=first_mask, capacity=capacity)
        elif self.model.resample is not None and capacity is None:
            state0 = self.model.resample.prepare(state0)
        self.state0 = state0
        self.frame_times = np.asarray(frame_times, float).ravel()
        self.plan = Plan(tuple(self.frame_times.tolist()), self.model.substeps, float(self.state0.t))

    @property
    def grid(self):
        return self.model.grid

    @property
    def dx(self) -> float:
        return self.model.dx

    @property
    def dtype(self):
        return jnp.dtype(self.model.dtype)

    @property
    def dt(self) -> float:
        return self.model.dt

    @property
    def max_speed(self) -> float:
        """The material speed bound of the CFL step, m/s."""
        return self.model.max_speed

    @property
    def dt_cfl(self) -> float:
        return self.model.dt_cfl

    @property
    def substeps(self) -> int:
        """Substeps per frame (every frame has the same count; its dt is the frame interval / count)."""
        return self.model.substeps

    @property
    def total_substeps(self) -> int:
        return self.substeps * len(self.frame_times)

    @property
    def resample(self):
        return self.model.resample

    @property
    def fracture(self):
        return self.model.fracture

    @property
    def colliders(self) -> tuple:
        return self.model.colliders

    @property
    def checkpoint_blocks(self) -> int:
        """Checkpointed blocks per frame in reverse mode (1: each frame recomputed as a whole)."""
        return checkpoint_blocks(self.state0, self.grid, self.substeps, FRAME_TAPE_BYTES)

    def step(self, state: State, params: Params) -> State:
        """`jaxfoam.step(self.model, state, params)`: one substep of dt s."""
        from ._mpm import step
        return step(self.model, state, params)

    def rollout(self, params: Params, state0: State | None = None, scene: Scene | None = None,
                observe: Callable = observe_default, adjoint=Checkpointed()):
        """`jaxfoam.rollout` of the model from state0 (default: the sampled one) at the frame times:
        (final State, frames pytree (T, ...), health). scene: replaces the model's scene data
        (differentiable: gravity, plate motion)."""
        model = self.model
        if scene is not None:
            model = model.replace(scene=jax.tree_util.tree_map(lambda a: jnp.asarray(a, model.dtype), scene))
        return rollout(model, self.state0 if state0 is None else state0, params, self.frame_times,
                       observe=observe, adjoint=adjoint)

    def check(self, frames, health, frame_times=None) -> None:
        """Raise SimulationError naming the first frame, time, quantity and particle that went bad
        (frame_times: those of the rollout checked, s, when not the simulator's own)."""
        times = self.frame_times if frame_times is None else frame_times
        ok, first = jax.device_get(health)
        bad = ~ok
        if not bad.any():
            return
        k = int(np.argmax(bad.any(axis=1)))
        q = int(np.argmax(bad[k]))
        name = HEALTH_NAMES[q]
        p = int(first[k, q])
        where = ""
        if isinstance(frames, dict) and "x" in frames and k > 0:  # frame 0 has no recorded predecessor
            where = f" at position {np.asarray(frames['x'][k - 1, p]).tolist()} m (previous frame)"
        if q == len(HEALTH_NAMES) - 1:
            raise SimulationError(
                f"the substep exceeded the stability limit at frame {k} (t = {np.asarray(times)[k]:.6g} s): "
                f"{name} with these parameters' wave speed and the fastest particle ({p}){where}. The model's "
                f"dt = {self.dt:.3g} s was chosen for its reference parameters (params_ref): build it with the "
                f"parameters you run (make_model / Simulator), or lower cfl.")
        raise SimulationError(
            f"simulation became non-finite at frame {k} (t = {np.asarray(times)[k]:.6g} s, "
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
    return Trajectory(frames=frames, times=np.asarray(sim.frame_times), final=final,
                      dx=sim.dx, dt=sim.dt, substeps=sim.substeps, scene=scene, params=params)
