"""The background grid and the quadratic B-spline stencil that MLS-MPM transfers use."""
from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np

# Grid nodes beyond the domain on each side: the quadratic stencil reaches 1.5 cells past a
# particle, and the slip walls live on the domain boundary, so 3 cells keep every index in range.
GRID_PAD = 3


@dataclasses.dataclass(frozen=True)
class Grid:
    """Static background grid. origin (d,) m is node (0, ..., 0); dx m; shape nodes per axis."""

    origin: tuple
    dx: float
    shape: tuple

    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def num_nodes(self) -> int:
        return int(np.prod(self.shape))

    def node_positions(self, dtype, xp=jnp) -> jax.Array:
        """(G, d) node positions, m, in the flattened (row-major) order of the grid arrays
        (a numpy array, a compile-time constant, with xp=np)."""
        axes = [self.origin[k] + self.dx * np.arange(n) for k, n in enumerate(self.shape)]
        pos = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, self.dim)
        return xp.asarray(pos, dtype)


def make_grid(scene, dx: float) -> Grid:
    """The grid covering the scene's domain with GRID_PAD extra cells on every side."""
    lo = np.asarray(scene.domain_min)
    hi = np.asarray(scene.domain_max)
    n = np.ceil((hi - lo) / dx).astype(int) + 1 + 2 * GRID_PAD
    return Grid(origin=tuple((lo - GRID_PAD * dx).tolist()), dx=float(dx), shape=tuple(int(k) for k in n))


def _stencil(x, grid: Grid):
    """Quadratic B-spline weights: base (N, d) int, fx (N, d), w list of 3 arrays (N, d)."""
    inv_dx = 1.0 / grid.dx
    origin = jnp.asarray(grid.origin, x.dtype)
    xg = (x - origin[None, :]) * inv_dx
    base = jnp.floor(xg - 0.5)
    fx = xg - base
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    # Every stencil index is kept inside the grid (a no-op for active particles, which `constitutive`
    # keeps in the stencil-safe region; it bounds inactive or non-finite ones), so the gather and the
    # scatter need no bounds checks (XLA:CPU's checked gather is slower; docs/performance.md).
    hi = jnp.asarray(grid.shape, jnp.int32) - 3
    return jnp.clip(base.astype(jnp.int32), 0, hi[None, :]), fx, w


def _stencil_derivs(fx, grid: Grid):
    """Position derivatives of `_stencil`'s 1D weights: list of 3 arrays (N, d), d w_a / d x, 1/m."""
    inv = 1.0 / grid.dx
    return [-(1.5 - fx) * inv, -2.0 * (fx - 1.0) * inv, (fx - 0.5) * inv]


def _offsets(d):
    return list(itertools.product(range(3), repeat=d))


def _stencil_weights(w, offs):
    """Per-offset B-spline weights W (K, N): the product over axes of the 1D weights `w`."""
    d = w[0].shape[-1]
    W = []
    for off in offs:
        weight = w[off[0]][:, 0]
        for k in range(1, d):
            weight = weight * w[off[k]][:, k]
        W.append(weight)
    return jnp.stack(W)


def _strides(shape) -> list[int]:
    """Row-major strides (in elements) of an array of the given shape, as Python ints (static)."""
    return [int(s) for s in np.cumprod((tuple(shape[1:]) + (1,))[::-1])[::-1]]


def _flat_index(base, offset, grid: Grid):
    strides = _strides(grid.shape)
    idx = 0
    for k in range(grid.dim):
        idx = idx + (base[:, k] + offset[k]) * strides[k]
    return idx


def _offset_index(offset, grid: Grid) -> int:
    """Flat index difference of a stencil offset (static)."""
    return int(np.dot(offset, _strides(grid.shape)))

