"""Signed distance functions (SDF): analytic collider shapes and the material's own SDF.

Convention: phi(x) < 0 inside, > 0 outside, |phi| the distance to the surface, m. Every shape works
in 2D and 3D alike (the dimension is the length of its tuples); points are (..., d) arrays.

- Shapes are frozen, hashable dataclasses (they are static configuration of a simulation):
  `Sphere`, `Box`, `Capsule`, `Cylinder`, `Ellipsoid`, and the Boolean combinations `Union`,
  `Intersection`, `Difference`. `head_with_nose` builds the analytic face of the pie-throw scene.
- `SDFCollider` turns a shape with a prescribed rigid translation into a grid boundary condition
  (sticky, sticky up to a tensile `adhesion`, or slip with Coulomb friction) with `apply(v, node_x, t)`;
  a `Simulator(colliders=...)` applies it after the scene's own plates, floor and walls.
- `material_sdf` computes the signed distance of the region occupied by the particles (the
  morphological closing of the particle set, sampled on a lattice); resampling inserts particles only
  where it is negative.
"""
from __future__ import annotations

import dataclasses
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._xla_cpu import tuning_for
from ._grid import _strides


def _norm(v, axis=-1):
    """Euclidean norm with a finite gradient at 0 (double where)."""
    sq = jnp.sum(v * v, axis=axis)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def _vec(p, x):
    return jnp.asarray(p, x.dtype).reshape((1,) * (x.ndim - 1) + (-1,))


def _check_dim(x, n, name):
    if x.shape[-1] != n:
        raise ValueError(f"{name}: points have dimension {x.shape[-1]} but the shape has dimension {n}")


# ----------------------------------------------------------------------------------------------
# Analytic shapes
# ----------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Sphere:
    """Ball (a disc in 2D): center (d,) m, radius m."""

    center: tuple
    radius: float

    def __call__(self, x):
        _check_dim(x, len(self.center), "Sphere")
        return _norm(x - _vec(self.center, x)) - self.radius


@dataclasses.dataclass(frozen=True)
class Box:
    """Axis-aligned box: center (d,) m, half_size (d,) m; `rounding` m rounds its edges (exact SDF)."""

    center: tuple
    half_size: tuple
    rounding: float = 0.0

    def __call__(self, x):
        _check_dim(x, len(self.center), "Box")
        q = jnp.abs(x - _vec(self.center, x)) - (_vec(self.half_size, x) - self.rounding)
        outside = _norm(jnp.maximum(q, 0.0))
        inside = jnp.minimum(jnp.max(q, axis=-1), 0.0)
        return outside + inside - self.rounding


@dataclasses.dataclass(frozen=True)
class Capsule:
    """Segment a-b (each (d,) m) thickened by `radius` m (exact SDF)."""

    a: tuple
    b: tuple
    radius: float

    def __call__(self, x):
        _check_dim(x, len(self.a), "Capsule")
        a, b = _vec(self.a, x), _vec(self.b, x)
        ab = b - a
        t = jnp.clip(jnp.sum((x - a) * ab, -1) / jnp.sum(ab * ab, -1), 0.0, 1.0)
        return _norm(x - a - t[..., None] * ab) - self.radius


@dataclasses.dataclass(frozen=True)
class Cylinder:
    """Finite cylinder about coordinate axis `axis` (0, 1 or 2): center (d,) m, radius m, half_height m.

    In 2D the cross-section perpendicular to the axis is a segment, so the "cylinder" is the
    rectangle |x_axis - c| <= half_height, |x_other - c| <= radius (a slot through a 2D cracker).
    """

    center: tuple
    radius: float
    half_height: float
    axis: int = 1

    def __call__(self, x):
        d = len(self.center)
        _check_dim(x, d, "Cylinder")
        rel = x - _vec(self.center, x)
        others = [k for k in range(d) if k != self.axis]
        radial = _norm(jnp.stack([rel[..., k] for k in others], -1)) - self.radius
        along = jnp.abs(rel[..., self.axis]) - self.half_height
        q = jnp.stack([radial, along], -1)
        return _norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q, axis=-1), 0.0)


@dataclasses.dataclass(frozen=True)
class Ellipsoid:
    """Ellipsoid (an ellipse in 2D): center (d,) m, radii (d,) m.

    There is no closed-form distance to an ellipsoid; this is the first-order estimate
    phi = k0 (k0 - 1) / k1 with k0 = |x/r|, k1 = |x/r^2| (exact sign, exact on spheres, within a
    factor max(r)/min(r) of the distance elsewhere): good enough to find nodes inside and normals.
    """

    center: tuple
    radii: tuple

    def __call__(self, x):
        _check_dim(x, len(self.center), "Ellipsoid")
        r = _vec(self.radii, x)
        rel = x - _vec(self.center, x)
        k0 = _norm(rel / r)
        k1 = _norm(rel / (r * r))
        pos = k1 > 0
        return jnp.where(pos, k0 * (k0 - 1.0) / jnp.where(pos, k1, 1.0), -float(min(self.radii)))


@dataclasses.dataclass(frozen=True)
class Union:
    """Union of shapes (min of their SDFs; exact outside, a bound inside)."""

    shapes: tuple

    def __call__(self, x):
        return jnp.min(jnp.stack([s(x) for s in self.shapes], -1), axis=-1)


@dataclasses.dataclass(frozen=True)
class Intersection:
    """Intersection of shapes (max of their SDFs)."""

    shapes: tuple

    def __call__(self, x):
        return jnp.max(jnp.stack([s(x) for s in self.shapes], -1), axis=-1)


@dataclasses.dataclass(frozen=True)
class Difference:
    """`base` with `cut` removed: max(phi_base, -phi_cut) (a cracker with holes)."""

    base: object
    cut: object

    def __call__(self, x):
        return jnp.maximum(self.base(x), -self.cut(x))


def head_with_nose(center, head_radii, nose_length, nose_radius, facing: int = 0, facing_sign: float = -1.0):
    """An analytic face: an ellipsoid head plus a capsule nose pointing along -/+ axis `facing`.

    center (d,) m, head_radii (d,) m, nose_length m (how far the nose tip sticks out of the head),
    nose_radius m. The nose starts inside the head, at 0.6 of the head radius along `facing`, at
    0.1 of the vertical radius below the centre (where a nose sits on a face).
    """
    d = len(center)
    c = np.asarray(center, float)
    r = np.asarray(head_radii, float)
    e = np.zeros(d)
    e[facing] = facing_sign
    root = c + e * 0.6 * r[facing] - 0.1 * r[1] * (np.arange(d) == 1)
    tip = c + e * (r[facing] + nose_length) - 0.1 * r[1] * (np.arange(d) == 1)
    return Union((Ellipsoid(tuple(c.tolist()), tuple(r.tolist())),
                  Capsule(tuple(root.tolist()), tuple(tip.tolist()), float(nose_radius))))


# ----------------------------------------------------------------------------------------------
# Colliders from SDFs
# ----------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class SDFCollider:
    """A rigid collider: `shape` translated by a prescribed offset o(t), applied on grid nodes.

    Attributes:
      shape: an SDF shape (in its rest position), m.
      times: (k,) s, and offsets: (k, d) m, the translation o(t) interpolated linearly between the
        samples (held constant outside them). A static collider has times (0.0,) and a zero offset.
      friction: Coulomb coefficient (>= 0) for slip contact, or "sticky" (nodes inside take the
        collider velocity).
      thickness: nodes with phi < thickness (m) count as inside: a positive value makes thin shapes
        (thinner than a grid cell) catch nodes on both sides.
      adhesion: tensile strength of a sticky contact, Pa (>= 0), or None (default: it never lets go).
        A sticky node is released when holding it would take a pull above this: the traction
        m_n (v_n - v_c).n / (dt dx^(d-1)) of the material moving away from the surface (outward
        normal n, the SDF gradient; per unit depth in 2D). A released node keeps its own velocity,
        so the material parts from the surface there, as a marshmallow parts from a cracker pulled
        off it; shear and compression are still held. Needs `apply(..., mass=, dt=, dx=)`, which
        the grid update passes.
    `apply(v, node_x, t)` returns the grid velocities (G, d) m/s after contact at time t (s): inside
    nodes get the collider velocity (sticky) or lose the approaching normal velocity relative to it,
    the tangential part reduced by friction times the removed normal speed (as the floor does).
    """

    shape: object
    times: tuple = (0.0,)
    offsets: tuple = ()
    friction: float | str = "sticky"
    thickness: float = 0.0
    adhesion: float | None = None

    def __post_init__(self):
        if self.friction != "sticky" and not (isinstance(self.friction, (int, float)) and self.friction >= 0):
            raise ValueError(f"SDFCollider.friction must be a number >= 0 or 'sticky', got {self.friction!r}")
        if self.adhesion is not None:
            if self.friction != "sticky":
                raise ValueError(f"SDFCollider.adhesion applies to a sticky collider only (friction 'sticky'), "
                                 f"got friction {self.friction!r}")
            if isinstance(self.adhesion, bool) or not (isinstance(self.adhesion, (int, float))
                                                       and math.isfinite(self.adhesion) and self.adhesion >= 0):
                raise ValueError(f"SDFCollider.adhesion must be a tensile strength >= 0 Pa or None, got {self.adhesion!r}")
        if len(self.offsets) and len(self.offsets) != len(self.times):
            raise ValueError(f"SDFCollider: {len(self.times)} times but {len(self.offsets)} offsets")
        if np.any(np.diff(np.asarray(self.times, float)) <= 0):
            raise ValueError("SDFCollider.times must be strictly increasing (s)")

    def offset(self, t, d, dtype):
        """Translation o(t), m, (d,)."""
        if not len(self.offsets):
            return jnp.zeros((d,), dtype)
        ts = jnp.asarray(self.times, dtype)
        os_ = jnp.asarray(self.offsets, dtype)
        return jnp.stack([jnp.interp(t, ts, os_[:, k]) for k in range(d)])

    def velocity(self, t, d, dtype):
        """Collider velocity, m/s, (d,): the slope of the current segment of o(t)."""
        if len(self.offsets) < 2:
            return jnp.zeros((d,), dtype)
        ts = np.asarray(self.times, float)
        os_ = np.asarray(self.offsets, float)
        slopes = jnp.asarray(np.diff(os_, axis=0) / np.diff(ts)[:, None], dtype)
        seg = jnp.searchsorted(jnp.asarray(ts, dtype), t, side="right") - 1
        inside = (seg >= 0) & (seg < len(ts) - 1)
        return jnp.where(inside, slopes[jnp.clip(seg, 0, len(ts) - 2)], 0.0)

    def max_speed(self) -> float:
        """Largest speed of the prescribed motion, m/s (for the time-step bound)."""
        if len(self.offsets) < 2:
            return 0.0
        ts = np.asarray(self.times, float)
        os_ = np.asarray(self.offsets, float)
        return float(np.max(np.linalg.norm(np.diff(os_, axis=0), axis=1) / np.diff(ts)))

    def phi(self, x, t):
        """The collider's SDF at time t (s) at points x (..., d), m."""
        return self.shape(x - self.offset(t, x.shape[-1], x.dtype).reshape((1,) * (x.ndim - 1) + (-1,)))

    def _normal(self, rel_x):
        """Outward unit normal (G, d) = normalized SDF gradient (autodiff of the shape); 0 where flat."""
        g = jax.vmap(jax.grad(lambda p: self.shape(p[None, :])[0]))(rel_x)
        gn = _norm(g)
        return jnp.where(gn[:, None] > 0, g / jnp.where(gn > 0, gn, 1.0)[:, None], 0.0)

    def apply(self, v, node_x, t, mass=None, dt=None, dx=None):
        d = v.shape[-1]
        # Computed once, not per grid node (a buffer point of the backend's tuning).
        o, vc = tuning_for().buffer("collider_motion", (self.offset(t, d, v.dtype), self.velocity(t, d, v.dtype)), t)
        vc = vc[None, :]
        rel_x = node_x - o[None, :]
        phi = self.shape(rel_x)
        inside = phi < self.thickness
        if self.friction == "sticky":
            if self.adhesion is None:
                return jnp.where(inside[:, None], vc, v)
            if mass is None or dt is None or dx is None:
                raise ValueError("SDFCollider.apply: a collider with adhesion needs the grid mass, dt and dx "
                                 "(mass=, dt=, dx=)")
            vn = jnp.sum((v - vc) * self._normal(rel_x), -1)
            pull = mass * vn / (dt * dx ** (d - 1))            # Pa: the tension needed to hold the node
            hold = inside & (pull <= self.adhesion)
            return jnp.where(hold[:, None], vc, v)
        n = self._normal(rel_x)
        vrel = v - vc
        vn = jnp.sum(vrel * n, -1)
        approaching = inside & (vn < 0)
        vt = vrel - vn[:, None] * n
        speed = _norm(vt)
        new_speed = jnp.maximum(speed + float(self.friction) * vn, 0.0)
        scale = jnp.where(speed > 0, new_speed / jnp.where(speed > 0, speed, 1.0), 0.0)
        return jnp.where(approaching[:, None], vc + vt * scale[:, None], v)


# ----------------------------------------------------------------------------------------------
# The material's SDF, sampled on a lattice
# ----------------------------------------------------------------------------------------------

@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LatticeSDF:
    """A signed distance sampled at lattice points origin + (i + 1/2) h, i in [0, shape), clamped to
    [-band, band] m; evaluated anywhere by multilinear interpolation (+band outside the lattice).

    values: (prod(shape),) m, flattened row-major. Static: origin (d,) m, h m, shape, band m.
    """

    values: jax.Array
    origin: tuple = dataclasses.field(metadata=dict(static=True), default=())
    h: float = dataclasses.field(metadata=dict(static=True), default=1.0)
    shape: tuple = dataclasses.field(metadata=dict(static=True), default=())
    band: float = dataclasses.field(metadata=dict(static=True), default=1.0)

    def __call__(self, x):
        """phi at points x (n, d), m, (n,)."""
        d = len(self.shape)
        u = (x - jnp.asarray(self.origin, x.dtype)[None, :]) / self.h - 0.5
        i0 = jnp.floor(u)
        t = u - i0
        i0 = i0.astype(jnp.int32)
        strides = _strides(self.shape)
        out = jnp.zeros(x.shape[:1], x.dtype)
        valid_all = jnp.ones(x.shape[:1], bool)
        for corner in itertools.product((0, 1), repeat=d):
            wgt = jnp.ones(x.shape[:1], x.dtype)
            flat = jnp.zeros(x.shape[:1], jnp.int32)
            for k in range(d):
                ik = i0[:, k] + corner[k]
                valid_all = valid_all & (ik >= 0) & (ik < self.shape[k])
                flat = flat + jnp.clip(ik, 0, self.shape[k] - 1) * strides[k]
                wgt = wgt * (t[:, k] if corner[k] else 1.0 - t[:, k])
            out = out + wgt * self.values[flat]
        return jnp.where(valid_all, out, self.band)


def _ball_offsets(radius_cells: float, d: int):
    """Integer offsets o with |o| <= radius_cells, and their lengths (in lattice units)."""
    w = int(math.floor(radius_cells + 1e-9))
    offs = [o for o in itertools.product(range(-w, w + 1), repeat=d)
            if math.sqrt(sum(c * c for c in o)) <= radius_cells + 1e-9]
    return offs


def _count_in_offsets(a, offsets):
    """c[i] = number of offsets o with a[i + o] true (outside the array counts false): a convolution."""
    d = a.ndim
    w = max(max(abs(c) for c in o) for o in offsets)
    kern = np.zeros((2 * w + 1,) * d)
    for o in offsets:
        kern[tuple(c + w for c in o)] = 1.0
    dims = "".join("DHW"[3 - d:][k] for k in range(d))
    spec = ("NC" + dims, "OI" + dims, "NC" + dims)
    out = jax.lax.conv_general_dilated(
        a.astype(jnp.float32)[None, None], jnp.asarray(kern, jnp.float32)[None, None],
        window_strides=(1,) * d, padding=[(w, w)] * d, dimension_numbers=spec)
    return out[0, 0]


def material_sdf(x, active, origin, cells, dx: float, closing_radius: float = 1.0, refine: int = 2,
                 band: float | None = None) -> LatticeSDF:
    """The signed distance of the region the particles occupy, sampled on a lattice of spacing dx/refine.

    The region is the morphological closing of the particle set with radius R = closing_radius * dx:
    the points whose every R-ball lies within R of some particle. It fills gaps narrower than 2R
    between particles (the non-physical voids of a stretched particle distribution) while keeping
    its outer boundary at the outermost particles and leaving cavities wider than 2R empty; a lone
    particle or a single file of particles has no interior.

    Args:
      x: (N, d) positions, m; active: (N,) bool (inactive slots are ignored).
      origin: (d,) m and cells: (d,) ints, the box [origin, origin + cells dx] the lattice covers.
      dx: grid spacing, m.  closing_radius: R / dx (> 0).  refine: lattice points per dx (>= 1).
      band: clamp of |phi|, m (default 1.5 dx / refine: a narrow band, enough for the sign and the
        distance to the surface next to it; a wider band costs a convolution per distance level).
    Returns a LatticeSDF, negative inside. Positions only steer decisions: no gradient flows through.
    """
    if closing_radius <= 0:
        raise ValueError(f"closing_radius must be > 0 (in units of dx), got {closing_radius}")
    if int(refine) < 1:
        raise ValueError(f"refine (lattice points per dx) must be >= 1, got {refine}")
    x = jax.lax.stop_gradient(x)
    d = x.shape[-1]
    h = dx / int(refine)
    R = closing_radius * dx
    band = 1.5 * h if band is None else float(band)
    shape = tuple(int(c) * int(refine) for c in cells)
    L = int(np.prod(shape))
    strides = _strides(shape)
    org = jnp.asarray(origin, x.dtype)
    # 1. Dilation: lattice points within R of a particle (one scatter from each particle's window).
    u = (x - org[None, :]) / h - 0.5
    base = jnp.floor(u).astype(jnp.int32)
    w = int(math.ceil(R / h)) + 1
    offs = jnp.asarray(list(itertools.product(range(-w + 1, w + 1), repeat=d)), jnp.int32)  # (K, d)
    ik = base[:, None, :] + offs[None, :, :]                                                  # (N, K, d)
    p = org[None, None, :] + (ik.astype(x.dtype) + 0.5) * h
    ok = active[:, None] & jnp.all((ik >= 0) & (ik < jnp.asarray(shape, jnp.int32)[None, None, :]), axis=-1)
    ok = ok & (jnp.sum((p - x[:, None, :]) ** 2, -1) <= R * R)
    flat = jnp.sum(ik * jnp.asarray(strides, jnp.int32)[None, None, :], -1)
    near = jnp.zeros((L,), bool).at[jnp.where(ok, flat, L).reshape(-1)].max(ok.reshape(-1), mode="drop")
    near = near.reshape(shape)
    # 2. Erosion by R: closed where the whole R-ball of lattice points is near (a ball convolution).
    ball = _ball_offsets(R / h, d)
    closed = _count_in_offsets(near, ball) >= len(ball) - 0.5
    # 3. Narrow-band signed distance between lattice points across the boundary of `closed`: for
    # each distance of the window, in increasing order, whether a point of the other side lies there.
    far = jnp.asarray(band, x.dtype)
    d_out = jnp.full(shape, far, x.dtype)  # inside points: distance to the nearest outside point
    d_in = jnp.full(shape, far, x.dtype)   # outside points: distance to the nearest inside point
    rings = {}
    for off in _ball_offsets(band / h, d):
        if any(off):
            rings.setdefault(round(sum(c * c for c in off)), []).append(off)
    for r2 in sorted(rings, reverse=True):
        dist = h * math.sqrt(r2)
        n_in = _count_in_offsets(closed, rings[r2])
        d_out = jnp.where(n_in < len(rings[r2]) - 0.5, dist, d_out)
        d_in = jnp.where(n_in > 0.5, dist, d_in)
    # The surface lies between the two lattice points: half a spacing from each.
    phi = jnp.where(closed, -(d_out - 0.5 * h), d_in - 0.5 * h)
    phi = jnp.clip(phi, -far, far)
    return LatticeSDF(values=phi.reshape(-1), origin=tuple(float(o) for o in origin), h=float(h),
                      shape=shape, band=float(band))


# ----------------------------------------------------------------------------------------------
# Shapes and colliders from JSON-style descriptions
# ----------------------------------------------------------------------------------------------

SHAPE_KEYS = {
    "sphere": {"type", "center", "radius"},
    "box": {"type", "center", "half_size", "rounding"},
    "capsule": {"type", "a", "b", "radius"},
    "cylinder": {"type", "center", "radius", "half_height", "axis"},
    "ellipsoid": {"type", "center", "radii"},
    "union": {"type", "shapes"},
    "intersection": {"type", "shapes"},
    "difference": {"type", "base", "cut"},
    "head_with_nose": {"type", "center", "head_radii", "nose_length", "nose_radius", "facing", "facing_sign"},
}
COLLIDER_KEYS = {"shape", "times", "offsets", "friction", "thickness", "adhesion"}


def _tuple(v, field):
    try:
        out = tuple(float(a) for a in v)
    except TypeError as exc:
        raise ValueError(f"{field}: expected a list of numbers, got {v!r}") from exc
    if not all(math.isfinite(a) for a in out):
        raise ValueError(f"{field}: values must be finite, got {v!r}")
    return out


def _pos(v, field):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v > 0 and math.isfinite(v)):
        raise ValueError(f"{field}: expected a number > 0 (m), got {v!r}")
    return float(v)


def shape_from_spec(spec: dict, field: str = "shape"):
    """An SDF shape from a dict such as {"type": "box", "center": [...], "half_size": [...]} (m).

    Types: sphere (center, radius), box (center, half_size, rounding=0), capsule (a, b, radius),
    cylinder (center, radius, half_height, axis=1), ellipsoid (center, radii), union / intersection
    (shapes: list), difference (base, cut), head_with_nose (center, head_radii, nose_length,
    nose_radius, facing=0, facing_sign=-1). Raises ValueError naming the field.
    """
    if not isinstance(spec, dict) or spec.get("type") not in SHAPE_KEYS:
        raise ValueError(f"{field}.type: expected one of {sorted(SHAPE_KEYS)}, got "
                         f"{spec.get('type') if isinstance(spec, dict) else spec!r}")
    kind = spec["type"]
    unknown = sorted(set(spec) - SHAPE_KEYS[kind])
    if unknown:
        raise ValueError(f"{field}: unknown key(s) {unknown} for type {kind!r}; allowed {sorted(SHAPE_KEYS[kind])}")
    try:
        if kind == "sphere":
            return Sphere(_tuple(spec["center"], f"{field}.center"), _pos(spec["radius"], f"{field}.radius"))
        if kind == "box":
            return Box(_tuple(spec["center"], f"{field}.center"), _tuple(spec["half_size"], f"{field}.half_size"),
                       float(spec.get("rounding", 0.0)))
        if kind == "capsule":
            return Capsule(_tuple(spec["a"], f"{field}.a"), _tuple(spec["b"], f"{field}.b"),
                           _pos(spec["radius"], f"{field}.radius"))
        if kind == "cylinder":
            return Cylinder(_tuple(spec["center"], f"{field}.center"), _pos(spec["radius"], f"{field}.radius"),
                            _pos(spec["half_height"], f"{field}.half_height"), int(spec.get("axis", 1)))
        if kind == "ellipsoid":
            return Ellipsoid(_tuple(spec["center"], f"{field}.center"), _tuple(spec["radii"], f"{field}.radii"))
        if kind in ("union", "intersection"):
            parts = tuple(shape_from_spec(s, f"{field}.shapes[{i}]") for i, s in enumerate(spec["shapes"]))
            return Union(parts) if kind == "union" else Intersection(parts)
        if kind == "difference":
            return Difference(shape_from_spec(spec["base"], f"{field}.base"),
                              shape_from_spec(spec["cut"], f"{field}.cut"))
        return head_with_nose(_tuple(spec["center"], f"{field}.center"),
                              _tuple(spec["head_radii"], f"{field}.head_radii"),
                              _pos(spec["nose_length"], f"{field}.nose_length"),
                              _pos(spec["nose_radius"], f"{field}.nose_radius"),
                              int(spec.get("facing", 0)), float(spec.get("facing_sign", -1.0)))
    except KeyError as exc:
        raise ValueError(f"{field}.{exc.args[0]}: required for type {kind!r}") from exc


def collider_from_spec(spec: dict, field: str = "collider") -> SDFCollider:
    """An SDFCollider from {"shape": {...}, "times": [s...], "offsets": [[m...]...],
    "friction": number >= 0 | "sticky", "thickness": m, "adhesion": Pa (sticky only)}. Raises ValueError
    naming the field."""
    if not isinstance(spec, dict) or "shape" not in spec:
        raise ValueError(f"{field}.shape: required")
    unknown = sorted(set(spec) - COLLIDER_KEYS)
    if unknown:
        raise ValueError(f"{field}: unknown key(s) {unknown}; allowed {sorted(COLLIDER_KEYS)}")
    shape = shape_from_spec(spec["shape"], f"{field}.shape")
    times = _tuple(spec.get("times", [0.0]), f"{field}.times")
    offsets = tuple(_tuple(o, f"{field}.offsets[{i}]") for i, o in enumerate(spec.get("offsets", [])))
    try:
        return SDFCollider(shape, times, offsets, spec.get("friction", "sticky"), float(spec.get("thickness", 0.0)),
                           spec.get("adhesion"))
    except ValueError as exc:
        raise ValueError(f"{field}: {exc}") from exc
