"""`rollout`: a jit-compiled scan over frames of substeps, differentiated as its `adjoint` says."""
from __future__ import annotations

import functools
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ._constitutive import det, deviatoric_stress_norm
from ._model import Model, ModelError
from ._mpm import substep
from ._params import Params
from ._state import State
from ._xla_cpu.layout import from_components, sort_by_cell, to_components, unsort
from .adjoint import Checkpointed, check_adjoint, checkpoint_blocks

STATE_FIELDS = ("x", "v", "C", "F", "bbar_e")
HEALTH_NAMES = STATE_FIELDS + ("J <= 0 (inverted)", "Courant number above the model's limit")


def observe_default(state: State, params: Params) -> dict:
    """Per-frame record: positions x (N, d) m, velocities v m/s, plastic rate gamma_dot 1/s,
    deviatoric stress magnitude s Pa, volume ratio J, active mask."""
    return dict(x=state.x, v=state.v, gamma_dot=state.gamma_dot,
                s=deviatoric_stress_norm(state.bbar_e, params), J=det(state.F), active=state.active)


def _wave_speed(params: Params):
    """sqrt((kappa + 4/3 mu) / rho), m/s, traceable (0 for a non-positive argument)."""
    sq = (params.kappa + 4.0 / 3.0 * params.mu) / params.rho
    return jnp.sqrt(jnp.where(sq > 0, sq, 0.0))


def health(state: State, params: Params, dt, model: Model):
    """Per entry of HEALTH_NAMES: whether all active values of the STATE_FIELDS are finite, no active
    particle is inverted (J <= 0), and the substep dt s keeps the Courant number dt (c + v_max) / dx
    within `Model.courant_limit` for these parameters' wave speed c; and the first bad particle of each
    (for the Courant entry: the fastest particle)."""
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
    speed = jnp.where(state.active, jnp.sqrt(jnp.sum(state.v * state.v, axis=1)), 0.0)
    ok.append(dt * (_wave_speed(params) + (model.max_speed or 0.0)) <= model.courant_limit() * model.dx)
    first.append(jnp.argmax(speed))
    return jnp.stack(ok), jnp.stack(first).astype(jnp.int32)


def check_courant(model: Model, params: Params, dts) -> None:
    """Raise ModelError when concrete `params` make the largest substep of `dts` (s) exceed the model's
    Courant limit (`Model.courant_limit`) with its material speed bound (nothing for traced values)."""
    if not _concrete((params, dts, model.dt, model.dt_cfl)):
        return
    from ._model import wave_speed
    c = wave_speed(params)
    dt = float(np.max(np.asarray(dts)))
    bound = float(model.courant_limit()) * model.dx / (c + (model.max_speed or 0.0))
    if dt > bound:
        raise ModelError(f"the substep dt = {dt:.4g} s exceeds the stability bound {bound:.4g} s of these "
                         f"parameters (wave speed c = sqrt((kappa + 4/3 mu) / rho) = {c:.4g} m/s, dx = "
                         f"{model.dx:g} m): build the model (make_model / Simulator) with params_ref set to them")


def _concrete(x) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(x))


def frame_plan(model: Model, state0: State, frame_times):
    """(frame times (T,), substep per frame (T,) s, substeps per frame) of a rollout.

    Concrete times are checked (increasing, after state0.t, each frame's substep <= model.dt) and the
    substeps come from them when the model has none; traced times need model.substeps."""
    dtype = jnp.dtype(model.dtype)
    if _concrete((frame_times, state0.t, model.dt)):
        times = np.asarray(frame_times, np.float64).ravel()
        t0 = float(state0.t)
        if times.size == 0 or not np.all(np.isfinite(times)):
            raise ModelError("frame_times must be a non-empty list of finite times in s")
        widths = np.diff(np.concatenate([[t0], times]))
        if np.any(widths <= 0):
            raise ModelError(f"frame_times must be strictly increasing and after the start time {t0} s")
        n = model.substeps or int(math.ceil(widths.max() / model.dt - 1e-9))
        # Times held in the state's precision (a float32 state's t) are allowed their round-off.
        slack = 4.0 * float(np.finfo(dtype).eps) * max(abs(t0), float(np.max(np.abs(times))))
        if (widths.max() - slack) / n > model.dt * (1.0 + 1e-9):
            raise ModelError(f"frame interval {widths.max():.6g} s needs more than the model's {n} substeps of "
                             f"at most dt = {model.dt:.6g} s: build the model with these frame_times")
        return jnp.asarray(times, dtype), jnp.asarray(widths / n, dtype), n
    if model.substeps is None:
        raise ModelError("traced frame_times need a model with a frame plan: make_model(..., frame_times=...)")
    times = jnp.asarray(frame_times, dtype).ravel()
    widths = jnp.diff(jnp.concatenate([jnp.asarray(state0.t, dtype)[None], times]))
    return times, widths / model.substeps, model.substeps


def rollout(model: Model, state0: State, params: Params, frame_times, *, observe: Callable = observe_default,
            adjoint=Checkpointed()):
    """Simulate from state0 and record `observe(state, params)` at each of `frame_times` (T,) s.

    Pure, jit-compiled and differentiable with respect to params, state0 and the model's scene data;
    vmaps over params and initial states. Each frame runs model.substeps substeps of its interval /
    substeps (<= model.dt). observe: a hashable function (a static argument). adjoint: how reverse mode
    differentiates it (`jaxfoam.adjoint`; forward mode works with every adjoint but `HandWritten`).
    Returns (final State, frames pytree with a leading (T,) axis, health: ((T, 7) bool ok, (T, 7)
    first bad particle) per frame and entry of HEALTH_NAMES; `Simulator.check` reads it).
    Raises ValueError for parameters out of range or, with concrete parameters, a substep beyond their
    Courant limit (`check_courant`), before any compute.
    """
    check_adjoint(adjoint)
    params.validate()
    times, dts, n = frame_plan(model, state0, frame_times)
    check_courant(model, params, dts)
    params = params.astype(jnp.dtype(model.dtype))
    return _rollout(model, state0, params, times, dts, n, observe, adjoint)


@functools.partial(jax.jit, static_argnums=(5, 6, 7))
def _rollout(model: Model, state0: State, params: Params, frame_times, frame_dts, substeps: int, observe,
             adjoint):
    resample, fracture, grid = model.resample, model.fracture, model.grid
    sort = model.tuning.sort_by_cell
    hand = adjoint.hand_adjoint
    blocks = checkpoint_blocks(state0, grid, substeps, adjoint.frame_tape_bytes) if adjoint.checkpoint else 1

    def frame(state, inputs):
        t_target, dt = inputs[:2]

        def _resample_pass(s, k):
            # Cells of a fracturing neck are not refilled (FractureConfig.holds; None when off).
            st = from_components(s)
            hold = None if fracture is None else fracture.holds(st, grid)
            return to_components(resample.apply(st, grid, k, hold))

        # Within a frame the state is carried in component form (jaxfoam._xla_cpu.layout).
        def sub(s, i):
            s = substep(model, s, params, dt, hand)
            if resample is not None:
                # Resampling pass after every `resample.every`-th substep of the whole rollout.
                k = inputs[2] * substeps + i + 1
                s = jax.lax.cond(k % resample.every == 0, lambda s: _resample_pass(s, k), lambda s: s, s)
            return s, None

        state = to_components(state)
        if sort:
            state, perm = sort_by_cell(state, grid)
        xs = None if resample is None else jnp.arange(substeps)
        if adjoint.checkpoint:
            policy = jax.checkpoint_policies.save_only_these_names(*adjoint.saved)
            sub_ck = jax.checkpoint(sub, policy=policy)
            if blocks > 1:
                # Blocks of `size` substeps (the last one shorter), each a checkpoint (frame_tape_bytes).
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
        return state, (observe(state, params), health(state, params, dt, model))

    if adjoint.checkpoint:
        # Reverse mode stores one state per frame and recomputes the frame in its backward pass.
        frame = jax.checkpoint(frame)
    xs = (frame_times, frame_dts) if resample is None else (frame_times, frame_dts, jnp.arange(len(frame_times)))
    final, (frames, healths) = jax.lax.scan(frame, state0, xs)
    return final, frames, healths
