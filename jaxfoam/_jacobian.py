"""Jacobians of per-frame observables of a rollout with respect to chosen inputs.

What is differentiable (through `Simulator.rollout`):
  - material parameters: mu, sigma_y, eta, m, kappa (Pa, Pa, Pa s^m, -, Pa);
  - rho (kg/m^3): enters only through particle masses, so "rho" here sets the masses to rho * vol0
    (as `init_state` makes them) before the rollout;
  - collider motion: "plate<i>.<field>" for the data fields of `Scene.plates[i]` (amplitude m,
    frequency Hz, phase rad, ramp_time s, sample_positions m, ...), and the scene's "gravity" (m/s^2)
    and "floor_friction";
  - the initial state: "state0.<field>" (x m, v m/s, C 1/s, F, bbar_e, vol0, mass kg).
Geometry that only decides which grid nodes a collider covers (a plate's center and half_size, the
floor height) acts through a discrete membership test: its derivative is zero almost everywhere.

How it is differentiated is the `adjoint` (`jaxfoam.adjoint`): `ForwardMode` pushes one tangent per
scalar input through the rollout (no tape, memory independent of the rollout length, cost grows with
the number of inputs): the choice for the few material parameters a Gauss-Newton fit wants, and the
default (`DEFAULT_JACOBIAN`). `HandWritten`, `Checkpointed` or `Autodiff` pull one cotangent per scalar
output back (memory grows with the number of frames, cost with the number of outputs): the choice for
a scalar loss or for many inputs (state0 fields).
"""
from __future__ import annotations

import dataclasses
import math
import re
import weakref
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from ._params import FIT_FIELDS, Params
from ._rollout import observe_default
from ._scene import Plate, Scene
from ._simulate import Simulator
from ._state import State
from .adjoint import DEFAULT_JACOBIAN, ForwardMode, check_adjoint, threaded_columns

PARAM_FIELDS = tuple(f.name for f in dataclasses.fields(Params))
SCENE_FIELDS = ("gravity", "floor_friction")
PLATE_FIELDS = tuple(f.name for f in dataclasses.fields(Plate) if not f.metadata.get("static"))
STATE_FIELDS = ("x", "v", "C", "F", "bbar_e", "vol0", "mass")
_PLATE_RE = re.compile(r"^plate(\d+)\.(\w+)$")


class ObservableJacobian(NamedTuple):
    """The value of an observable and its Jacobian.

    Attributes:
      value: observable(frames), any shape S (its units).
      jacobian: dict name -> array of shape S + shape of that input (units of value per unit of input).
      health: the rollout's health record (pass it with the frames' positions to `Simulator.check`).
      wrt: the input names, in order.
    """

    value: jax.Array
    jacobian: dict
    health: tuple
    wrt: tuple

    def matrix(self) -> jax.Array:
        """The Jacobian as a (value.size, P) matrix: inputs in `wrt` order, each flattened row-major."""
        n = math.prod(jnp.shape(self.value))
        return jnp.concatenate([jnp.reshape(self.jacobian[k], (n, -1)) for k in self.wrt], axis=1)


def _check_wrt(wrt, scene: Scene) -> tuple:
    if isinstance(wrt, str):
        wrt = (wrt,)
    wrt = tuple(wrt)
    if not wrt:
        raise ValueError("wrt must name at least one input, e.g. ('mu', 'sigma_y', 'eta', 'm')")
    if len(set(wrt)) != len(wrt):
        raise ValueError(f"wrt names an input twice: {wrt}")
    for name in wrt:
        m = _PLATE_RE.match(name)
        if m:
            i, field = int(m.group(1)), m.group(2)
            if i >= len(scene.plates):
                raise ValueError(f"wrt entry {name!r}: the scene has {len(scene.plates)} plate(s) "
                                 f"(plate0 .. plate{len(scene.plates) - 1})")
            if field not in PLATE_FIELDS:
                raise ValueError(f"wrt entry {name!r}: a plate's differentiable fields are {PLATE_FIELDS}")
            continue
        if name.startswith("state0."):
            if name[7:] not in STATE_FIELDS:
                raise ValueError(f"wrt entry {name!r}: differentiable state fields are {STATE_FIELDS}")
            continue
        if name not in PARAM_FIELDS + SCENE_FIELDS:
            raise ValueError(f"wrt entry {name!r} is unknown; expected one of {PARAM_FIELDS + SCENE_FIELDS}, "
                             f"'plate<i>.<field>' with field in {PLATE_FIELDS}, or 'state0.<field>' with "
                             f"field in {STATE_FIELDS}")
    return wrt


def _get(name, params: Params, state0: State, scene: Scene):
    """The current value of input `name` (an array)."""
    m = _PLATE_RE.match(name)
    if m:
        return getattr(scene.plates[int(m.group(1))], m.group(2))
    if name.startswith("state0."):
        return getattr(state0, name[7:])
    if name in SCENE_FIELDS:
        return getattr(scene, name)
    return getattr(params, name)


def _put(leaves: dict, params: Params, state0: State, scene: Scene):
    """(params, state0, scene) with the inputs in `leaves` substituted."""
    pc = {k: v for k, v in leaves.items() if k in PARAM_FIELDS}
    sc = {k: v for k, v in leaves.items() if k in SCENE_FIELDS}
    st = {k[7:]: v for k, v in leaves.items() if k.startswith("state0.")}
    plates = list(scene.plates)
    for k, v in leaves.items():
        m = _PLATE_RE.match(k)
        if m:
            i = int(m.group(1))
            plates[i] = dataclasses.replace(plates[i], **{m.group(2): v})
    params = params.replace(**pc)
    if "rho" in leaves:
        # rho acts through the masses (the time step stays the one fixed at construction).
        st.setdefault("mass", state0.vol0 * leaves["rho"])
    state0 = state0.replace(**st)
    scene = dataclasses.replace(scene, plates=tuple(plates), **sc)
    return params, state0, scene


def make_observable_jacobian(sim: Simulator, observable: Callable, wrt=FIT_FIELDS, adjoint=DEFAULT_JACOBIAN,
                             observe: Callable = observe_default) -> Callable:
    """A jit-compiled `fn(params, state0=None, scene=None) -> ObservableJacobian` for repeated use.

    Same arguments as `observable_jacobian` (which calls this and caches the result per simulator).
    """
    check_adjoint(adjoint)
    if not callable(observable):
        raise ValueError(f"observable must be a function frames dict -> array, got {observable!r}")
    wrt = _check_wrt(wrt, sim.scene)
    forward = isinstance(adjoint, ForwardMode)
    threads = adjoint.resolve_threads(sim.model.tuning) if forward else 1

    def value(leaves, params, state0, scene):
        params, state0, scene = _put(leaves, params, state0, scene)
        _, frames, health = sim.rollout(params, state0=state0, scene=scene, observe=observe, adjoint=adjoint)
        out = jnp.asarray(observable(frames))
        return out, (out, health)

    def reverse(leaves, params, state0, scene):
        # jax.jacrev vmaps the pullback over a basis of the output space even for a scalar output; a
        # scalar observable takes one plain pullback instead.
        out, pullback, aux = jax.vjp(lambda lv: value(lv, params, state0, scene), leaves, has_aux=True)
        if out.ndim == 0:
            return pullback(jnp.ones_like(out))[0], aux
        basis = jnp.eye(out.size, dtype=out.dtype).reshape((out.size,) + out.shape)
        rows = jax.vmap(pullback)(basis)[0]
        return {k: v.reshape(out.shape + leaves[k].shape) for k, v in rows.items()}, aux

    def columns(leaves, params, state0, scene, basis):
        # One jvp rollout per row of `basis` (K, P) over the flattened inputs, in sequence: (K,) + S.
        flat, treedef = jax.tree_util.tree_flatten(leaves)
        sizes = [math.prod(a.shape) for a in flat]

        def column(e):
            parts, start = [], 0
            for a, n in zip(flat, sizes):
                parts.append(e[start:start + n].reshape(a.shape))
                start += n
            _, tan, aux = jax.jvp(lambda lv: value(lv, params, state0, scene), (leaves,),
                                  (jax.tree_util.tree_unflatten(treedef, parts),), has_aux=True)
            return tan, aux

        cols, auxs = jax.lax.map(column, basis)
        return cols, jax.tree_util.tree_map(lambda x: x[0], auxs)

    def blocks_of(cols, leaves):
        # (P,) + S columns back to {name: S + input shape}.
        flat, treedef = jax.tree_util.tree_flatten(leaves)
        out_shape = cols.shape[1:]
        blocks, start = [], 0
        for a in flat:
            n = math.prod(a.shape)
            blocks.append(jnp.moveaxis(cols[start:start + n], 0, -1).reshape(out_shape + a.shape))
            start += n
        return jax.tree_util.tree_unflatten(treedef, blocks)

    def leaves_of(params, state0, scene):
        params = params.astype(sim.dtype)
        leaves = {k: jnp.asarray(_get(k, params, state0, scene)) for k in wrt}
        for k, v in leaves.items():
            if not jnp.issubdtype(v.dtype, jnp.floating):
                raise ValueError(f"wrt entry {k!r} is not a floating-point array (dtype {v.dtype})")
        return params, leaves

    def run(params, state0, scene):
        params, leaves = leaves_of(params, state0, scene)
        if not forward:
            J, (out, health) = reverse(leaves, params, state0, scene)
        elif adjoint.tangents == "vmap":
            J, (out, health) = jax.jacfwd(value, has_aux=True)(leaves, params, state0, scene)
        else:
            p = sum(math.prod(v.shape) for v in leaves.values())
            cols, (out, health) = columns(leaves, params, state0, scene, jnp.eye(p, dtype=params.mu.dtype))
            J = blocks_of(cols, leaves)
        return out, J, health

    def run_group(params, state0, scene, basis):
        params, leaves = leaves_of(params, state0, scene)
        cols, (out, health) = columns(leaves, params, state0, scene, basis)
        return (out, health), cols

    opts = dict(sim.model.tuning.compiler_options) or None
    run = jax.jit(run, compiler_options=opts)
    run_group = jax.jit(run_group, compiler_options=opts)
    compiled = []

    def fn(params: Params, state0: State | None = None, scene: Scene | None = None) -> ObservableJacobian:
        params.validate()
        state0 = sim.state0 if state0 is None else state0
        scene = sim.scene if scene is None else scene
        if threads <= 1:
            return ObservableJacobian(*run(params, state0, scene), wrt)
        _, leaves = leaves_of(params, state0, scene)
        p = sum(math.prod(v.shape) for v in leaves.values())
        (out, health), cols = threaded_columns(lambda b: run_group(params, state0, scene, jnp.asarray(b)), p,
                                               threads, sim.dtype, bool(compiled))
        compiled.append(True)
        return ObservableJacobian(out, blocks_of(cols, leaves), health, wrt)

    def lower(params: Params, state0: State | None = None, scene: Scene | None = None):
        """The lowered program (for `.compile().cost_analysis()` / `.memory_analysis()`), all columns in one."""
        return run.lower(params, sim.state0 if state0 is None else state0, sim.scene if scene is None else scene)

    fn.lower = lower
    fn.adjoint = adjoint
    fn.threads = threads
    return fn


_CACHE: "weakref.WeakKeyDictionary[Simulator, dict]" = weakref.WeakKeyDictionary()
# Compiled Jacobian functions kept per simulator (oldest dropped first): a few observables and modes.
CACHE_PER_SIMULATOR = 8


def observable_jacobian(sim: Simulator, params: Params, observable: Callable, wrt=FIT_FIELDS,
                        adjoint=DEFAULT_JACOBIAN, *, state0: State | None = None, scene: Scene | None = None,
                        observe: Callable = observe_default) -> ObservableJacobian:
    """Value and Jacobian of `observable(frames)` with respect to the inputs named in `wrt`.

    Args:
      sim: a Simulator (fixes the grid, frame times and the time step: perturbed inputs keep the same
        dt, so finite differences of the same simulator are clean).
      params: material parameters (SI units) at which to differentiate.
      observable: frames dict (arrays (T, N, ...) as recorded by `observe`) -> array of any shape S,
        e.g. `lambda fr: jnp.mean(fr["x"][:, :, 1], axis=1)` (mean height per frame, m, S = (T,)).
        The compiled function is cached per (simulator, observable, wrt, adjoint, observe): pass the
        same function object on repeated calls (a new lambda each call recompiles).
      wrt: input names: Params fields ("mu", "sigma_y", "eta", "m", "kappa", "rho"), scene fields
        ("gravity", "floor_friction"), plate motion ("plate0.amplitude", "plate0.frequency", ...),
        initial state ("state0.x", "state0.v", ...). Default: the four fitted parameters.
      adjoint: `jaxfoam.adjoint.ForwardMode(tangents="vmap" | "map", threads=...)` for forward mode
        (default DEFAULT_JACOBIAN), or `HandWritten()` / `Checkpointed()` / `Autodiff()` for reverse
        mode (one cotangent per scalar output). All give the same Jacobian to round-off.
      state0, scene: override the simulator's initial state and scene.
      observe: per-frame record function passed to the rollout.
    Returns:
      ObservableJacobian(value (S), jacobian {name: (S + input shape)}, health, wrt); `.matrix()` gives
      the (prod S, P) matrix for Gauss-Newton.
    Raises:
      ValueError (AdjointError) for an unknown adjoint or input name.
    """
    check_adjoint(adjoint)
    key = (observable, _check_wrt(wrt, sim.scene), adjoint, observe)
    per_sim = _CACHE.setdefault(sim, {})
    if key not in per_sim:
        if len(per_sim) >= CACHE_PER_SIMULATOR:
            del per_sim[next(iter(per_sim))]
        per_sim[key] = make_observable_jacobian(sim, observable, key[1], adjoint, observe)
    return per_sim[key](params, state0=state0, scene=scene)
