"""Surfaces from particles: a smoothed volume fraction on a fine grid, then its iso-surface.

Each particle's current volume (vol0 J, m^d) is spread with the cubic B-spline kernel (Monaghan
1992) of smoothing length one mean particle spacing, so the field is the material's volume fraction:
about 1 inside, 0 outside. In 3D its ISO_LEVEL surface is a triangle mesh (marching cubes), in 2D a
set of closed polygon loops (marching squares); both come from scikit-image, imported only here, when
a surface is asked for (the `export` extra). Features thinner than about one particle spacing, such as
a lone particle, have a peak volume fraction below ISO_LEVEL and leave no surface.
"""
from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from .guards import EXPORT_HINT

# A symmetric kernel's smoothed volume fraction is 1/2 at a flat face of uniformly sampled material:
# a resting block's faces come out within 0.1 particle spacing of the block's faces.
ISO_LEVEL = 0.5
# Smoothing length, in mean particle spacings: shorter ones show each surface particle as a bump;
# longer ones round edges more (the volume lost there grows as its square).
SMOOTHING = 1.25
# Grid cells per mean particle spacing: fine enough that the mesh follows the field, not the grid.
CELLS_PER_SPACING = 2
# Taubin smoothing of the extracted surface (Taubin 1995: a shrinking step lam, an inflating step mu):
# removes the bumps of the particles' sampling noise, about one spacing wide, and keeps the volume.
TAUBIN_ITERATIONS = 10
TAUBIN_LAMBDA, TAUBIN_MU = 0.5, -0.53
# Cubic B-spline normalisation sigma_d / h^d (Monaghan 1992), by dimension.
KERNEL_NORM = {2: 10.0 / (7.0 * math.pi), 3: 1.0 / math.pi}


def require_skimage():
    """scikit-image's measure module, or ImportError naming the export extra."""
    try:
        from skimage import measure
    except ImportError as exc:
        raise ImportError(f"surfaces need scikit-image: {EXPORT_HINT}") from exc
    return measure


def cubic_spline(q: np.ndarray) -> np.ndarray:
    """The cubic B-spline shape (without normalisation) at q = r / h: 1 - 3/2 q^2 + 3/4 q^3 on [0, 1],
    (2 - q)^3 / 4 on [1, 2], 0 beyond."""
    q = np.abs(q)
    inner = 1.0 - 1.5 * q ** 2 + 0.75 * q ** 3
    outer = 0.25 * np.clip(2.0 - q, 0.0, None) ** 3
    return np.where(q < 1.0, inner, outer)


@dataclasses.dataclass(frozen=True)
class VolumeField:
    """A smoothed volume fraction on a regular grid of nodes.

    Attributes: values (n_1, ..., n_d) volume fraction at the nodes (1); origin (d,) m, the first
    node's position; cell: node spacing, m.
    """

    values: np.ndarray
    origin: np.ndarray
    cell: float

    def nodes(self, axis: int) -> np.ndarray:
        """Node coordinates along `axis`, m."""
        return self.origin[axis] + self.cell * np.arange(self.values.shape[axis])


def particle_spacing(dx: float, ppc: int, d: int) -> float:
    """Mean particle spacing (dx^d / ppc)^(1/d), m."""
    return float((dx ** d / ppc) ** (1.0 / d))


def volume_field(x: np.ndarray, vol: np.ndarray, spacing: float, cell: float | None = None,
                 bounds: tuple | None = None) -> VolumeField:
    """Splat particle volumes onto a grid: phi(node) = sum_p vol_p W(|node - x_p|, h).

    Args:
      x: (n, d) positions, m.  vol: (n,) current particle volumes, m^d.
      spacing: mean particle spacing, m; the smoothing length is SMOOTHING times it.
      cell: node spacing, m (default spacing / CELLS_PER_SPACING).
      bounds: (lo (d,), hi (d,)) m the grid must cover (default: the particles' bounding box); the grid
        extends one kernel support and two cells beyond it, so the field is zero on its border and
        every iso-surface is closed.
    """
    x = np.asarray(x, np.float64)
    vol = np.asarray(vol, np.float64)
    d = x.shape[1]
    h = SMOOTHING * spacing
    cell = spacing / CELLS_PER_SPACING if cell is None else float(cell)
    lo, hi = (x.min(0), x.max(0)) if bounds is None else (np.asarray(bounds[0], float), np.asarray(bounds[1], float))
    pad = 2.0 * h + 2.0 * cell
    origin = lo - pad
    shape = tuple(int(k) for k in np.ceil((hi + pad - origin) / cell).astype(int) + 1)
    # Volumes to the nodes by multilinear weights, then the kernel by an FFT convolution on the grid:
    # the border padding exceeds the kernel's support, so the circular convolution does not wrap.
    u = (x - origin) / cell
    base = np.clip(np.floor(u).astype(np.int64), 0, np.array(shape) - 2)
    frac = u - base
    deposit = np.zeros(int(np.prod(shape)), np.float64)
    for corner in itertools.product((0, 1), repeat=d):
        c = np.array(corner)
        w = np.prod(np.where(c == 1, frac, 1.0 - frac), axis=1)
        idx = np.ravel_multi_index(tuple((base + c).T), shape)
        deposit += np.bincount(idx, weights=vol * w, minlength=deposit.size)
    dist = [np.minimum(np.arange(m), m - np.arange(m)) * cell for m in shape]  # periodic distance, m
    r = np.sqrt(sum(a ** 2 for a in np.meshgrid(*dist, indexing="ij", sparse=True)))
    kernel = cubic_spline(r / h) * (KERNEL_NORM[d] / h ** d)  # 1/m^d
    values = np.fft.irfftn(np.fft.rfftn(deposit.reshape(shape)) * np.fft.rfftn(kernel), s=shape,
                           axes=tuple(range(d)))
    return VolumeField(values=values, origin=origin, cell=cell)


def mesh_from_field(field: VolumeField, level: float = ISO_LEVEL):
    """The level surface of a 3D field, Taubin-smoothed: (vertices (v, 3) m, faces (f, 3) int, unit
    vertex normals (v, 3)).

    Faces wind counter-clockwise seen from outside (the field is larger inside), normals point out.
    """
    measure = require_skimage()
    if field.values.max() <= level:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    verts, faces, _, _ = measure.marching_cubes(field.values, level=level, spacing=(field.cell,) * 3,
                                                gradient_direction="descent")
    # skimage winds faces clockwise seen from the low side; reverse them to wind counter-clockwise outside.
    faces = np.ascontiguousarray(faces[:, ::-1], dtype=np.int64)
    verts, normals = smooth_mesh(verts + field.origin, faces)
    return verts, faces, normals


def _taubin(points: np.ndarray, src: np.ndarray, dst: np.ndarray, iterations: int) -> np.ndarray:
    """Taubin smoothing of points (v, d) over the directed neighbour pairs src -> dst."""
    deg = np.maximum(np.bincount(src, minlength=len(points)), 1)[:, None]
    p = np.array(points, np.float64)
    for _ in range(iterations):
        for factor in (TAUBIN_LAMBDA, TAUBIN_MU):
            mean = np.stack([np.bincount(src, weights=p[dst, k], minlength=len(p)) for k in range(p.shape[1])], 1)
            p += factor * (mean / deg - p)
    return p


def smooth_mesh(verts: np.ndarray, faces: np.ndarray, iterations: int | None = None):
    """Taubin-smoothed vertices (v, 3) m and their area-weighted unit normals (v, 3); topology unchanged."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.concatenate([e, e[:, ::-1]]), axis=0)
    v = _taubin(verts, e[:, 0], e[:, 1], TAUBIN_ITERATIONS if iterations is None else iterations)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = np.stack([np.bincount(faces.ravel(), weights=np.repeat(fn[:, k], 3), minlength=len(v)) for k in range(3)], 1)
    return v, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def smooth_loop(loop: np.ndarray, iterations: int | None = None) -> np.ndarray:
    """A Taubin-smoothed closed polygon (k, 2) m."""
    i = np.arange(len(loop))
    src, dst = np.concatenate([i, i]), np.concatenate([np.roll(i, 1), np.roll(i, -1)])
    return _taubin(loop, src, dst, TAUBIN_ITERATIONS if iterations is None else iterations)


def loops_from_field(field: VolumeField, level: float = ISO_LEVEL) -> list[np.ndarray]:
    """The level set of a 2D field as closed, Taubin-smoothed loops [(k, 2) m, first point not repeated]; outer loops
    counter-clockwise (positive signed area), holes clockwise, so their signed areas add to the area."""
    measure = require_skimage()
    loops = []
    for c in measure.find_contours(field.values, level=level):
        pts = field.origin + c * field.cell
        if len(pts) > 1 and np.allclose(pts[0], pts[-1]):
            pts = pts[:-1]
        if len(pts) >= 3:
            loops.append(smooth_loop(pts))
    # find_contours orients every loop the same way around the high values: make that way positive.
    total = sum(signed_area(p) for p in loops)
    return [p[::-1] for p in loops] if total < 0 else loops


def signed_area(loop: np.ndarray) -> float:
    """Shoelace signed area of a closed polygon (k, 2), m^2 (positive counter-clockwise)."""
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def mesh_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume of a closed, outward-wound triangle mesh (divergence theorem), m^3."""
    a, b, c = (verts[faces[:, k]] for k in range(3))
    return float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6.0)


def frame_particles(traj, k: int):
    """Active particles of frame k of a SavedTrajectory: (positions (n, d) m, volumes (n,) m^d,
    mean particle spacing m). Volumes are dx^d / ppc times J when the file holds J."""
    from ._scene import DEFAULT_PPC

    d = traj.dim
    a = np.asarray(traj.frames["active"][k], bool)
    x = np.asarray(traj.frames["x"][k], np.float64)[a]
    ppc = traj.ppc or DEFAULT_PPC[d]
    vol0 = traj.dx ** d / ppc
    J = np.asarray(traj.frames["J"][k], np.float64)[a] if "J" in traj.frames else np.ones(len(x))
    J = np.where(np.isfinite(J) & (J > 0), J, 1.0)
    return x, vol0 * J, particle_spacing(traj.dx, ppc, d)


def frame_surface(traj, k: int, bounds: tuple | None = None):
    """The surface of frame k: 3D (vertices, faces, normals), 2D a list of loops (see above)."""
    x, vol, spacing = frame_particles(traj, k)
    if len(x) == 0:
        return (np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))) if traj.dim == 3 else []
    field = volume_field(x, vol, spacing, bounds=bounds)
    return mesh_from_field(field) if traj.dim == 3 else loops_from_field(field)
