"""Backend-specific speed choices, behind one frozen `Tuning` object per backend.

Physics code names the points where a buffer pays (`tuning.buffer("g2p_table", v, t)`) and reads the
switches below; every choice is an identity on the results (to round-off), tested against the plain
path (`PLAIN`) and the reference step in tests/. XLA:CPU gets `XLA_CPU` (measured there:
docs/performance.md); other backends get `PLAIN` until measured otherwise.
"""
from __future__ import annotations

import dataclasses

import jax
import jaxlib.version

from .fusion import hoist, materialize_linearization, materialize_tangent

# Buffer points of the substep, by kind. "value": the value is materialized (`hoist`); "tangent": only
# its tangent in derivative programs (`materialize_tangent`); "linearization": value and tangent there.
BUFFERS = {
    "stencil_index": "value",      # each particle's stencil base index, once per substep
    "plate_motion": "value",       # plate position and velocity, not recomputed per grid node
    "collider_motion": "value",    # SDF collider offset and velocity (jaxfoam.sdf)
    "g2p_table": "value",          # grid velocities before the gathers
    "stencil_sums": "value",       # the per-particle sums of the stencil gathers
    "adjoint_inputs": "value",     # the hand-written adjoints' cotangents and stencil weights
    "grid_momentum": "tangent",    # the grid cotangent before the gather that transposes p2g
    "return_map": "tangent",       # trial state, radial-return ratio and det-1 factor
    "grid_velocity": "linearization",  # v = mv / m with its tangent, for the colliders' tangents
}


@dataclasses.dataclass(frozen=True)
class Tuning:
    """Speed-only choices of a simulation (static, hashable; results equal to round-off).

    Attributes:
      buffers: the enabled buffer points (names of BUFFERS).
      g2p_loop_2d_float32: forward grid-to-particle in 2D float32 as a scan over the first axis's
        stencil offsets instead of the unrolled sum.
      halley_low_precision: in float64, all Halley steps of the return map's rate solve but the last
        evaluate exp and log1p in float32 (the last full-precision step restores round-off accuracy).
      sort_by_cell: reorder particles by grid cell for each frame (outputs keep the order).
      jacobian_threads: concurrent groups of forward-mode Jacobian columns (`ForwardMode`'s default).
      batch_fold: under `jax.vmap`, the transfers' scatters and gathers run over the batch's grids laid end
        to end (`jaxfoam._xla_cpu.fold`) instead of with batched indices; forward-mode programs only.
      fold_batches: whether batched forward-mode programs (a fit's population) switch batch_fold on.
      compiler_options: XLA compiler options of differentiated rollouts, as (name, value) pairs.
    """

    buffers: frozenset = frozenset(BUFFERS)
    g2p_loop_2d_float32: bool = True
    halley_low_precision: bool = True
    sort_by_cell: bool = True
    jacobian_threads: int = 2
    batch_fold: bool = False
    fold_batches: bool = True
    compiler_options: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "buffers", frozenset(self.buffers))
        object.__setattr__(self, "compiler_options", tuple(tuple(kv) for kv in dict(self.compiler_options).items()))
        unknown = sorted(set(self.buffers) - set(BUFFERS))
        if unknown:
            raise ValueError(f"Tuning.buffers: unknown buffer points {unknown}; known: {sorted(BUFFERS)}")
        if not (isinstance(self.jacobian_threads, int) and self.jacobian_threads >= 1):
            raise ValueError(f"Tuning.jacobian_threads must be an integer >= 1, got {self.jacobian_threads!r}")

    def _on(self, name: str, kind: str) -> bool:
        if BUFFERS.get(name) != kind:
            raise ValueError(f"{name!r} is not a buffer point of kind {kind!r} (BUFFERS)")
        return name in self.buffers

    def buffer(self, name: str, tree, t):
        """`tree` as materialized buffers (`hoist`, t the time in s) when `name` is enabled, else as is."""
        return hoist(tree, t) if self._on(name, "value") else tree

    def tangent_buffer(self, name: str, a, dt):
        """`a` with its tangent materialized in derivative programs (`materialize_tangent`) when enabled."""
        return materialize_tangent(a, dt) if self._on(name, "tangent") else a

    def linearization_buffer(self, name: str, a, dt):
        """`a` and its tangent materialized together in derivative programs when enabled."""
        return materialize_linearization(a, dt) if self._on(name, "linearization") else a

    def replace(self, **changes) -> "Tuning":
        return dataclasses.replace(self, **changes)


# Reductions over tiny axes (the transposes of per-particle broadcasts) stay with XLA's own loops: jaxlib
# 0.10.2 sends them to YNNPACK by default, which ran them slower (docs/performance.md).
_CPU_OPTIONS = ((("xla_cpu_experimental_ynn_fusion_type", ""),)
                if tuple(jaxlib.version.__version_info__[:3]) >= (0, 10, 2) else ())
# XLA:CPU: every buffer point and switch on (each measured there, docs/performance.md).
XLA_CPU = Tuning(compiler_options=_CPU_OPTIONS)
# The plain path: no buffers, unrolled transfers, full-precision solves, no sorting, one Jacobian thread.
PLAIN = Tuning(buffers=frozenset(), g2p_loop_2d_float32=False, halley_low_precision=False, sort_by_cell=False,
               jacobian_threads=1, fold_batches=False)


def tuning_for(backend: str | None = None) -> Tuning:
    """The tuning for a JAX backend name (default: `jax.default_backend()`): XLA_CPU on "cpu", else PLAIN."""
    backend = jax.default_backend() if backend is None else backend
    return XLA_CPU if backend == "cpu" else PLAIN


__all__ = ["BUFFERS", "PLAIN", "XLA_CPU", "Tuning", "tuning_for"]
