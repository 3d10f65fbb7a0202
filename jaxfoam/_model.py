"""The static description of a simulation: `Model`, built once by `make_model`."""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import JaxfoamError
from ._grid import Grid, make_grid
from ._params import Params
from ._scene import Scene
from ._xla_cpu import Tuning, tuning_for

# CFL number C in dt <= C dx / (c + max|v|): 0.3 stays stable with margin across the stiffness
# range of foams (model.md suggests 0.3-0.5; experiments measure where it fails).
CFL = 0.3
# Courant number dt (c + v_max) / dx (v_max: the model's speed bound) above which a rollout is refused
# (concrete parameters) or flagged (traced ones): past one cell per substep the explicit update is unstable.
MAX_COURANT = 1.0
# Free-fall speed bound uses the domain height; this factor leaves room for splashes and rebounds.
SPEED_SAFETY = 1.5


class ModelError(JaxfoamError, ValueError):
    """A model cannot be built from the given configuration; the message names the argument."""


def _value(x) -> float:
    """The float value of a scalar: concrete, or the primal value of a tracer of jax.grad / jax.jvp /
    jax.jacfwd run outside jit (the time step is picked from it and held fixed, not differentiated).
    Inside jit (or vmap) there is no value: ValueError."""
    try:
        return float(jax.lax.stop_gradient(x))
    except (TypeError, jax.errors.ConcretizationTypeError) as exc:
        raise ValueError("the time step needs the values of kappa, mu and rho, which jit and vmap do not "
                         "have: call jaxfoam.simulate / make_model outside jit (jax.grad, jax.jvp "
                         "and jax.jacfwd of it work), and jit jaxfoam.rollout instead") from exc


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


def _frame_widths(frame_times, t0: float) -> np.ndarray:
    times = np.asarray(frame_times, float).ravel()
    if times.size == 0 or not np.all(np.isfinite(times)):
        raise ModelError("frame_times must be a non-empty list of finite times in s")
    widths = np.diff(np.concatenate([[float(t0)], times]))
    if np.any(widths <= 0):
        raise ModelError(f"frame_times must be strictly increasing and after the start time {t0} s")
    return widths


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """Everything static about a simulation, and the scene's differentiable data as array leaves.

    A pytree: `scene` (its leaves: gravity m/s^2, plate motion amplitudes m and frequencies Hz, ...;
    its flags are static), `dt` and `dt_cfl` are data; every other field is static metadata, hashable,
    so `jax.jit(jaxfoam.step)` needs no factory and `jax.vmap` can run steps of different dt.

    Attributes:
      scene: the `Scene`, its data leaves in the model's dtype.
      grid: the background `Grid` (dx m, GRID_PAD cells beyond the domain).
      dt: the substep, s (`jaxfoam.step`; a rollout's frames use interval / substeps <= dt).
      dt_cfl: the CFL bound the substep was chosen under, s (None when dt was set by hand).
      substeps: substeps per frame of the frame plan, or None (a rollout then picks them from its
        frame times, which must be concrete).
      max_speed: the material speed bound the CFL step allows for, m/s (None when dt was set by hand).
      cfl: the CFL number dt_cfl was chosen with (None when dt was set by hand).
      dtype: "float32" or "float64".
      ppc: particles per cell for sampling (`Model.sample`).
      colliders: extra colliders (e.g. `jaxfoam.sdf.SDFCollider`), applied on the grid in order.
      fracture: a `jaxfoam.fracture.FractureConfig` stage after the constitutive update, or None.
      resample: a `jaxfoam.resample.ResampleConfig` pass every `resample.every` substeps, or None.
      tuning: the backend's speed choices (`jaxfoam._xla_cpu.Tuning`).
    """

    scene: Scene
    dt: float
    grid: Grid = dataclasses.field(metadata=dict(static=True))
    dt_cfl: float | None = None
    substeps: int | None = dataclasses.field(metadata=dict(static=True), default=None)
    max_speed: float | None = dataclasses.field(metadata=dict(static=True), default=None)
    cfl: float | None = dataclasses.field(metadata=dict(static=True), default=None)
    dtype: str = dataclasses.field(metadata=dict(static=True), default="float64")
    ppc: int | None = dataclasses.field(metadata=dict(static=True), default=None)
    colliders: tuple = dataclasses.field(metadata=dict(static=True), default=())
    fracture: object = dataclasses.field(metadata=dict(static=True), default=None)
    resample: object = dataclasses.field(metadata=dict(static=True), default=None)
    tuning: Tuning = dataclasses.field(metadata=dict(static=True), default_factory=tuning_for)

    @property
    def dim(self) -> int:
        return self.grid.dim

    @property
    def dx(self) -> float:
        return self.grid.dx

    def courant_limit(self):
        """The Courant number dt (c + max_speed) / dx a rollout may reach: MAX_COURANT, or the model's own
        at its reference parameters when its dt was forced past that (an explicit substeps or dt)."""
        if self.dt_cfl is None or self.cfl is None:
            return MAX_COURANT
        return jnp.maximum(MAX_COURANT, self.dt / self.dt_cfl * self.cfl * (1.0 + 1e-6))

    def replace(self, **changes) -> "Model":
        return dataclasses.replace(self, **changes)

    def sample(self, rho: float | None = None, *, seed: int = 0, first_mask=None, capacity: int | None = None):
        """The scene's initial shape sampled at the model's dx and ppc (`jaxfoam.init_state`); with a
        resample stage and no capacity, `resample.capacity_factor` times the sampled slots."""
        from ._scene import init_state
        state = init_state(self.scene, self.dx, self.ppc, rho=rho, seed=seed, first_mask=first_mask,
                           capacity=capacity, dtype=jnp.dtype(self.dtype))
        if self.resample is not None and capacity is None:
            state = self.resample.prepare(state)
        return state


def make_model(scene: Scene, dx: float, *, params_ref: Params, frame_times=None, t0: float = 0.0,
               ppc: int | None = None, cfl: float = CFL, dtype=jnp.float64, max_speed: float | None = None,
               substeps: int | None = None, dt: float | None = None, colliders=(), fracture=None,
               resample=None, tuning: Tuning | None = None) -> Model:
    """Build the `Model` of a scene at grid spacing dx (m): grid, CFL time step and frame plan.

    params_ref: the parameters the CFL time step dt <= cfl dx / (c + max|v|) is chosen for (c from
      kappa, mu, rho; a rollout may use others while the wave speed does not grow much).
    frame_times: (T,) increasing times, s, after t0 (s): the substeps per frame are chosen for the
      widest interval (each frame then runs interval / substeps). Without them, dt is the CFL step.
    max_speed: override of the material speed bound, m/s (default `speed_bound` plus the colliders').
    substeps, dt: overrides of the substeps per frame and of the substep (s).
    tuning: speed choices (default `jaxfoam._xla_cpu.tuning_for()`, by `jax.default_backend()`).
    Raises ModelError naming the argument for out-of-range values, before any compute.
    """
    params_ref.validate()
    wave_speed(params_ref)  # the time step needs values: a clear error under jit or vmap, first
    if not (isinstance(dx, (int, float)) and not isinstance(dx, bool) and dx > 0 and math.isfinite(dx)):
        raise ModelError(f"dx must be a positive grid spacing in m, got {dx!r}")
    if not (isinstance(cfl, (int, float)) and 0 < cfl <= 1.0):
        raise ModelError(f"cfl must be in (0, 1], got {cfl}")
    if dtype not in (jnp.float32, jnp.float64, np.float32, np.float64, "float32", "float64"):
        raise ModelError(f"dtype must be float32 or float64, got {dtype}")
    dtype = jnp.dtype(dtype)
    if dtype == jnp.float64 and not jax.config.jax_enable_x64:
        raise ModelError("dtype float64 needs jax.config.update('jax_enable_x64', True) before any "
                         "computation (or pass dtype=jnp.float32)")
    colliders = tuple(colliders)
    if fracture is not None:
        fracture.validate(scene.dim)
    if resample is not None:
        resample.validate(scene.dim)
    grid = make_grid(scene, dx)
    speed = speed_bound(scene) if max_speed is None else float(max_speed)
    if max_speed is None and colliders:
        speed += SPEED_SAFETY * max(c.max_speed() for c in colliders)
    dt_cfl = stable_dt(params_ref, dx, speed, cfl)
    if substeps is not None and not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
        raise ModelError(f"substeps must be an integer >= 1, got {substeps!r}")
    if dt is not None and not (isinstance(dt, (int, float)) and dt > 0 and math.isfinite(dt)):
        raise ModelError(f"dt must be a positive time step in s, got {dt!r}")
    n = None if substeps is None else int(substeps)
    if frame_times is not None:
        widest = float(np.max(_frame_widths(frame_times, t0)))
        if n is None:
            n = int(math.ceil(widest / (dt_cfl if dt is None else dt) - 1e-9))
        step = widest / n
    else:
        step = dt_cfl if dt is None else float(dt)
    # Scene data (gravity, plate motion) in the simulation's precision.
    scene = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), scene)
    return Model(scene=scene, dt=float(step), dt_cfl=float(dt_cfl), grid=grid, substeps=n, max_speed=speed, cfl=float(cfl),
                 dtype=dtype.name, ppc=ppc, colliders=colliders, fracture=fracture, resample=resample,
                 tuning=tuning_for() if tuning is None else tuning)
