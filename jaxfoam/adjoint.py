"""How a rollout is differentiated: one object per choice, passed as `adjoint=`.

- `Checkpointed()`: reverse mode recomputes each frame from its stored input state, keeping the named
  values REMAT_SAVED per substep; the frame's substeps run as checkpointed blocks when its store would
  exceed `frame_tape_bytes`. Forward mode works through it too. The default of `jaxfoam.rollout`.
- `HandWritten()`: `Checkpointed` with the transfers' hand-written reverse-mode derivatives (the same
  gradient, fewer kernels); reverse mode only: forward mode through it raises.
- `Autodiff()`: JAX's own derivative of the plain scan (reverse mode stores every substep).
- `ForwardMode(tangents=..., threads=...)`: forward-mode Jacobians: "vmap" pushes all tangents through
  one rollout (`jax.jacfwd`), "map" one `jax.jvp` rollout per input, in `threads` concurrent groups.

`rollout`, `observable_jacobian` and the fitter's Jacobian take these; `DEFAULT_JACOBIAN` is the one
default for Jacobians (docs/performance.md has the measurements behind it).
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import math

import jax
import numpy as np

# Values each substep's recomputation keeps in reverse mode (`jax.ad_checkpoint.checkpoint_name`): the
# return map's plastic rate, the g2p velocity and velocity gradient, the p2g grid momentum and mass.
REMAT_SAVED = ("hb_gamma", "g2p", "p2g_grid")
# A frame whose reverse-mode store exceeds this many bytes runs its substeps as checkpointed blocks
# (one more forward pass per frame): scenes of fit size stay on one level, large 3D scenes get blocks.
FRAME_TAPE_BYTES = 512 * 2 ** 20
TANGENT_MODES = ("vmap", "map")


class AdjointError(ValueError):
    """An adjoint was built with an invalid option or used where it cannot apply."""


@dataclasses.dataclass(frozen=True)
class Autodiff:
    """JAX's derivative of the plain rollout: forward and reverse mode; reverse mode stores every substep."""

    checkpoint = False
    hand_adjoint = False
    reverse = True


@dataclasses.dataclass(frozen=True)
class Checkpointed:
    """Reverse mode through per-frame rematerialization (memory ~ frames, not substeps).

    saved: names kept per substep in the recomputation (REMAT_SAVED).
    frame_tape_bytes: a frame's store above which its substeps are checkpointed in blocks, bytes.
    """

    saved: tuple = REMAT_SAVED
    frame_tape_bytes: float = FRAME_TAPE_BYTES
    checkpoint = True
    hand_adjoint = False
    reverse = True

    def __post_init__(self):
        if not (isinstance(self.frame_tape_bytes, (int, float)) and self.frame_tape_bytes > 0):
            raise AdjointError(f"frame_tape_bytes must be a positive number of bytes, got {self.frame_tape_bytes!r}")
        object.__setattr__(self, "saved", tuple(self.saved))


@dataclasses.dataclass(frozen=True)
class HandWritten(Checkpointed):
    """`Checkpointed` with the transfers' hand-written reverse-mode derivatives; reverse mode only."""

    hand_adjoint = True


@dataclasses.dataclass(frozen=True)
class ForwardMode:
    """Forward-mode Jacobians.

    tangents: "vmap" (all tangents through one rollout) or "map" (one jvp rollout per scalar input).
    threads: for "map", the columns run in this many concurrent groups on the CPU backend (None: the
      backend tuning's `jacobian_threads`); one compiled program serves every group.
    """

    tangents: str = "map"
    threads: int | None = None
    checkpoint = False
    hand_adjoint = False
    reverse = False

    def __post_init__(self):
        if self.tangents not in TANGENT_MODES:
            raise AdjointError(f"ForwardMode.tangents must be one of {TANGENT_MODES}, got {self.tangents!r}")
        if self.threads is not None and not (isinstance(self.threads, int) and self.threads >= 1):
            raise AdjointError(f"ForwardMode.threads must be an integer >= 1 or None, got {self.threads!r}")

    def resolve_threads(self, tuning) -> int:
        """The number of column groups to run (1 off the CPU backend or for "vmap")."""
        if self.tangents != "map" or jax.default_backend() != "cpu":
            return 1
        return tuning.jacobian_threads if self.threads is None else self.threads


# The Jacobian default, every dimension: one jvp rollout per parameter, in the tuning's threads.
DEFAULT_JACOBIAN = ForwardMode(tangents="map")
ADJOINTS = (Autodiff, Checkpointed, HandWritten, ForwardMode)


def check_adjoint(adjoint) -> None:
    if not isinstance(adjoint, ADJOINTS):
        raise AdjointError(f"adjoint must be one of Autodiff(), Checkpointed(), HandWritten(), ForwardMode(), "
                           f"got {adjoint!r}")


def checkpoint_blocks(state0, grid, substeps: int, budget: float = FRAME_TAPE_BYTES) -> int:
    """Checkpointed blocks per frame for reverse mode: 1 while a frame's store (per substep: the
    state, the rate, g2p's v and C per particle and p2g's d + 1 values per node) fits in `budget`
    bytes, else enough blocks to fit, at most ceil(sqrt(substeps)) (beyond that blocks do not help)."""
    n, d = state0.x.shape
    item = np.dtype(state0.x.dtype).itemsize
    per = sum(np.dtype(a.dtype).itemsize * a.size for a in jax.tree_util.tree_leaves(state0))
    per += item * (n * (1 + d + d * d) + grid.num_nodes * (d + 1))
    need = math.ceil(substeps * per / budget)
    return 1 if need <= 1 else min(need, max(2, math.isqrt(substeps - 1) + 1))


def threaded_columns(run_group, p: int, threads: int, dtype, compiled: bool):
    """Forward-mode columns in `threads` concurrent groups of equal size (the last padded with zero
    directions, whose columns are dropped), so one compiled program serves every group.

    run_group(basis (k, p)) -> (value, columns (k, ...)); `compiled`: whether that program exists (if
    not, the first group runs on this thread before the others start). Returns (value, (p, ...))."""
    k = max(1, min(int(threads), p))
    rows = -(-p // k)
    eye = np.eye(rows * k, p, dtype=np.dtype(dtype))
    groups = [eye[i * rows:(i + 1) * rows] for i in range(k)]
    run = lambda basis: jax.block_until_ready(run_group(basis))
    first = None if compiled else run(groups[0])
    if k == 1:
        out = [first if first is not None else run(groups[0])]
    else:
        with concurrent.futures.ThreadPoolExecutor(k - 1) as pool:
            later = [pool.submit(run, g) for g in groups[1:]]
            out = [run(groups[0]) if first is None else first] + [f.result() for f in later]
    cols = jax.numpy.concatenate([c for _, c in out])[:p]
    return out[0][0], cols


__all__ = ["ADJOINTS", "DEFAULT_JACOBIAN", "FRAME_TAPE_BYTES", "REMAT_SAVED", "AdjointError", "Autodiff",
           "Checkpointed", "ForwardMode", "HandWritten", "checkpoint_blocks", "threaded_columns"]
