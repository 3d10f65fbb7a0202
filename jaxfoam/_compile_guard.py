"""A guard against running out of memory mappings when one process compiles many programs.

Every compiled XLA:CPU program keeps its machine code in memory mappings, and JAX keeps each compiled
program in its caches for the life of the process (`jaxfoam.rollout` and the calibration's jitted
residual and Jacobian are compiled once per grid, scene and fit setting, and reused). A fit problem
at a new grid spacing adds about 720 mappings (2D drop, dx 1 cm; `jax.clear_caches()` frees them).
Linux caps a process at vm.max_map_count mappings (65,530 by default), so a script or notebook that
binds a few dozen fit problems in one process would die with "LLVM compilation error: Cannot
allocate memory".

`release_if_near_map_limit` is called before a new `Simulator` is bound (so before every fit
problem): when the process holds more than MAP_FRACTION of the limit it clears JAX's caches, which
frees the compiled programs; programs still in use are compiled again on their next call. It reads
the counts from /proc and does nothing where they are not available.
"""
from __future__ import annotations

import jax

# Fraction of vm.max_map_count above which compiled programs are released: half the limit leaves room
# for ~45 more fit problems before the next check, and is not reached by ordinary sessions (a fresh
# process with jaxfoam loaded holds ~700 mappings).
MAP_FRACTION = 0.5


def _map_count() -> int | None:
    try:
        with open("/proc/self/maps", "rb") as fh:
            return sum(1 for _ in fh)
    except OSError:
        return None


def _map_limit() -> int | None:
    try:
        with open("/proc/sys/vm/max_map_count") as fh:
            return int(fh.read().strip())
    except (OSError, ValueError):
        return None


def release_if_near_map_limit(count: int | None = None, limit: int | None = None) -> bool:
    """Clear JAX's caches of compiled programs if this process holds more than MAP_FRACTION of its
    allowed memory mappings. count, limit: the process's mappings and the limit (read from /proc when
    None). Returns whether the caches were cleared."""
    count = _map_count() if count is None else count
    limit = _map_limit() if limit is None else limit
    if count is None or limit is None or limit <= 0 or count <= MAP_FRACTION * limit:
        return False
    jax.clear_caches()
    return True
