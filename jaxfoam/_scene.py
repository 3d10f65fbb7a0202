"""Scene descriptions (shared/specs/silhouettes.md): parsing, validation, and particle sampling."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import JaxfoamError
from ._state import State, make_state

KINDS = ("hanging_plate", "drop", "squeeze")
SCENE_KEYS = {"kind", "dim", "gravity", "density", "kappa", "domain", "floor", "plate", "plates",
              "initial_shape", "initial_velocity", "name", "notes"}
REQUIRED_KEYS = ("kind", "dim", "density", "kappa", "domain", "initial_shape")
PLATE_KEYS = {"center", "half_size", "motion", "sticky", "grip"}
# How a sticky plate grips (docs/data.md): "nodes", the grid nodes inside it take its velocity (the no-slip
# wall then sits near the lowest node row inside the face, 0-1 cell in); "face", the nodes within a cell
# outside it also take the velocity interpolated between the face and the next node out.
PLATE_GRIPS = ("nodes", "face")
MOTION_KEYS = {
    "none": {"type"},
    "sinusoid": {"type", "axis", "amplitude", "frequency", "phase", "ramp_time"},
    "samples": {"type", "times", "positions"},
}
SHAPE_KEYS = {"first_mask": {"type"}, "box": {"type", "min", "max"}, "ellipse": {"type", "center", "radii"}}
FLOOR_KEYS = {"y", "friction", "contact"}
# Floor contact models (docs/data.md): "grid" applies the floor's rule to the grid nodes at or below it
# (the material then rests up to about a cell above a floor it lands on); "particle" applies it to
# each particle's extent (jaxfoam._boundary.particle_floor), so a landed foam's edge lies on the floor.
FLOOR_CONTACTS = ("grid", "particle")

# Particles per cell: 2 per axis is the MPM standard (Stomakhin 2013), enough to keep every cell
# of the material covered under moderate stretch.
DEFAULT_PPC = {2: 4, 3: 8}
# Sample points drawn over the whole domain at most (the sampling work arrays grow with their number).
MAX_CANDIDATES = 50_000_000


class SceneError(JaxfoamError, ValueError):
    """A scene description that does not follow the spec; the message names the field."""


class PlausibilityWarning(UserWarning):
    """A legal but suspicious input (a units slip, a plate that never meets the material)."""


# Round-off allowance, m, when a shape's edge lies on the domain's or the floor's boundary.
GEOMETRY_TOL = 1e-9


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Plate:
    """A rigid axis-aligned box collider (a board, a cracker).

    Data leaves (differentiable): center (d,) m, half_size (d,) m, axis (d,) unit direction,
    amplitude m, frequency Hz, phase rad, ramp_time s, sample_times (k,) s, sample_positions (k, d) m.
    Static: motion ("none" | "sinusoid" | "samples"), sticky (nodes inside take the plate velocity;
    otherwise only the approaching normal component is removed), grip (a sticky plate's reach,
    PLATE_GRIPS: "nodes" inside it only; "face": also each node a distance 0 < d < dx outside the box
    (Chebyshev distance, m), which takes v_plate + (v_next - v_plate) d / (d + dx), v_next the velocity
    of the node one cell further out along the nearest face's normal: the linear profile that meets the
    plate's velocity at its face; along that normal only where it pushes the node away from the plate).
    Centre at time t: center + axis A r(t) sin(2 pi f t + phase), r(t) = min(1, t / ramp_time),
    or the samples interpolated linearly (held constant outside their time range).
    """

    center: jax.Array
    half_size: jax.Array
    axis: jax.Array
    amplitude: jax.Array
    frequency: jax.Array
    phase: jax.Array
    ramp_time: jax.Array
    sample_times: jax.Array
    sample_positions: jax.Array
    motion: str = dataclasses.field(metadata=dict(static=True), default="none")
    sticky: bool = dataclasses.field(metadata=dict(static=True), default=True)
    grip: str = dataclasses.field(metadata=dict(static=True), default="nodes")

    def position(self, t):
        """Plate centre at time t (s), m, (d,)."""
        if self.motion == "samples":
            return jnp.stack([jnp.interp(t, self.sample_times, self.sample_positions[:, k])
                              for k in range(self.center.shape[0])])
        if self.motion == "sinusoid":
            return self.center + self.axis * self.amplitude * _ramp(t, self.ramp_time) * jnp.sin(
                2 * jnp.pi * self.frequency * t + self.phase)
        return self.center

    def velocity(self, t):
        """Plate velocity at time t (s), m/s, (d,) (the exact derivative of `position`)."""
        return jax.jacfwd(self.position)(t)


def _ramp(t, ramp_time):
    pos = ramp_time > 0
    return jnp.where(pos, jnp.minimum(1.0, t / jnp.where(pos, ramp_time, 1.0)), 1.0)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scene:
    """A parsed scene. Data leaves (gravity, plates, floor friction) may be differentiated.

    Attributes:
      gravity: (d,) m/s^2.  plates: tuple of Plate.  floor_friction: Coulomb coefficient (scalar).
      kind, dim, density (kg/m^3), kappa (Pa), domain_min/max (m), floor_y (m or None),
      floor_sticky, floor_contact ("grid" or "particle", FLOOR_CONTACTS), initial_shape (the JSON dict,
      frozen), initial_velocity (m/s), source (JSON text):
      static.
    """

    gravity: jax.Array
    plates: tuple
    floor_friction: jax.Array
    kind: str = dataclasses.field(metadata=dict(static=True), default="drop")
    dim: int = dataclasses.field(metadata=dict(static=True), default=2)
    density: float = dataclasses.field(metadata=dict(static=True), default=1.0)
    kappa: float = dataclasses.field(metadata=dict(static=True), default=1.0)
    domain_min: tuple = dataclasses.field(metadata=dict(static=True), default=())
    domain_max: tuple = dataclasses.field(metadata=dict(static=True), default=())
    floor_y: float | None = dataclasses.field(metadata=dict(static=True), default=None)
    floor_sticky: bool = dataclasses.field(metadata=dict(static=True), default=False)
    floor_contact: str = dataclasses.field(metadata=dict(static=True), default="grid")
    initial_velocity: tuple = dataclasses.field(metadata=dict(static=True), default=())
    source: str = dataclasses.field(metadata=dict(static=True), default="{}")

    @property
    def spec(self) -> dict:
        """The scene description as a JSON-compatible dict."""
        return json.loads(self.source)

    @property
    def initial_shape(self) -> dict:
        return self.spec["initial_shape"]

    @property
    def particle_contact_floor(self) -> bool:
        """Whether the scene has a floor with particle contact (`jaxfoam._boundary.particle_floor`)."""
        return self.floor_y is not None and self.floor_contact == "particle"

    def max_plate_speed(self) -> float:
        """An upper bound of the plates' speed, m/s (for the time-step estimate)."""
        vmax = 0.0
        for p in self.plates:
            if p.motion == "sinusoid":
                vmax = max(vmax, float(abs(p.amplitude)) * (2 * math.pi * float(abs(p.frequency))
                           + (1.0 / float(p.ramp_time) if float(p.ramp_time) > 0 else 0.0)))
            elif p.motion == "samples":
                t = np.asarray(p.sample_times)
                x = np.asarray(p.sample_positions)
                if len(t) > 1:
                    vmax = max(vmax, float(np.max(np.linalg.norm(np.diff(x, axis=0), axis=1) / np.diff(t))))
        return vmax


def _err(field, msg):
    raise SceneError(f"scene field '{field}': {msg}")


def _vec(value, field, d, positive=False):
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        _err(field, f"expected a list of {d} numbers, got {value!r}")
    if arr.shape != (d,):
        _err(field, f"expected a list of {d} numbers (dim = {d}), got {value!r}")
    if not np.all(np.isfinite(arr)):
        _err(field, f"values must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        _err(field, f"values must be > 0, got {value!r}")
    return arr


def _num(value, field, lo=None, lo_open=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _err(field, f"expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        _err(field, f"must be finite, got {value}")
    if lo is not None and (value < lo or (lo_open and value == lo)):
        _err(field, f"must be {'>' if lo_open else '>='} {lo}, got {value}")
    return value


def _keys(obj, allowed, field):
    if not isinstance(obj, dict):
        _err(field, f"expected an object, got {obj!r}")
    unknown = sorted(set(obj) - set(allowed))
    if unknown:
        _err(field, f"unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _parse_plate(p, field, d, dtype):
    _keys(p, PLATE_KEYS, field)
    for k in ("center", "half_size"):
        if k not in p:
            _err(f"{field}.{k}", "required")
    center = _vec(p["center"], f"{field}.center", d)
    half = _vec(p["half_size"], f"{field}.half_size", d, positive=True)
    sticky = p.get("sticky", True)
    if not isinstance(sticky, bool):
        _err(f"{field}.sticky", f"expected true or false, got {sticky!r}")
    grip = p.get("grip", "nodes")
    if grip not in PLATE_GRIPS:
        _err(f"{field}.grip", f"expected one of {list(PLATE_GRIPS)}, got {grip!r}")
    motion = p.get("motion", {"type": "none"})
    if not isinstance(motion, dict) or motion.get("type") not in MOTION_KEYS:
        _err(f"{field}.motion.type", f"expected one of {sorted(MOTION_KEYS)}, got "
             f"{motion.get('type') if isinstance(motion, dict) else motion!r}")
    mtype = motion["type"]
    _keys(motion, MOTION_KEYS[mtype], f"{field}.motion")
    axis = np.zeros(d)
    amp = freq = phase = ramp = 0.0
    times = np.zeros(1)
    positions = center[None, :]
    if mtype == "sinusoid":
        axis = _vec(motion.get("axis", [1.0] + [0.0] * (d - 1)), f"{field}.motion.axis", d)
        norm = np.linalg.norm(axis)
        if norm == 0:
            _err(f"{field}.motion.axis", "must be a non-zero vector")
        axis = axis / norm
        amp = _num(motion.get("amplitude", 0.0), f"{field}.motion.amplitude", lo=0.0)
        freq = _num(motion.get("frequency", 0.0), f"{field}.motion.frequency", lo=0.0)
        phase = _num(motion.get("phase", 0.0), f"{field}.motion.phase")
        ramp = _num(motion.get("ramp_time", 0.0), f"{field}.motion.ramp_time", lo=0.0)
    elif mtype == "samples":
        for k in ("times", "positions"):
            if k not in motion:
                _err(f"{field}.motion.{k}", "required for motion type 'samples'")
        times = np.asarray(motion["times"], float)
        positions = np.asarray(motion["positions"], float)
        if times.ndim != 1 or len(times) < 1:
            _err(f"{field}.motion.times", "expected a non-empty list of times")
        if positions.shape != (len(times), d):
            _err(f"{field}.motion.positions", f"expected {len(times)} positions of {d} numbers")
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(positions))):
            _err(f"{field}.motion", "times and positions must be finite")
        if np.any(np.diff(times) <= 0):
            _err(f"{field}.motion.times", "must be strictly increasing")
    a = lambda v: jnp.asarray(v, dtype)
    return Plate(center=a(center), half_size=a(half), axis=a(axis), amplitude=a(amp), frequency=a(freq),
                 phase=a(phase), ramp_time=a(ramp), sample_times=a(times), sample_positions=a(positions),
                 motion=mtype, sticky=sticky, grip=grip)


def load_scene(scene: str | os.PathLike | dict, dtype=jnp.float64) -> Scene:
    """Parse and validate a scene description (a dict, a JSON string, or a path to a JSON file).

    Accepted keys: kind (hanging_plate | drop | squeeze), dim (2 | 3), gravity (d numbers, m/s^2,
    default [0, -9.81(, 0)]), density (kg/m^3 > 0), kappa (Pa > 0), domain {min, max} (m), floor
    {y (m), friction (>= 0 or "sticky"), contact ("grid" | "particle", default "grid")} (optional),
    plate (one plate) or plates (a list), each {center, half_size (m), motion, sticky (default true),
    grip ("nodes" | "face", default "nodes"; `Plate`)},
    initial_shape (first_mask | box | ellipse), initial_velocity (d numbers, m/s, optional),
    name, notes (free text). A hanging_plate scene needs exactly one plate, a squeeze scene at least one.
    Raises SceneError (a ValueError) naming the offending field.
    """
    if isinstance(scene, dict):
        spec = scene
    else:
        spec = _read_spec(scene)
    _keys(spec, SCENE_KEYS, "scene")
    for k in REQUIRED_KEYS:
        if k not in spec:
            _err(k, "required")
    kind = spec["kind"]
    if kind not in KINDS:
        _err("kind", f"unknown kind {kind!r}; expected one of {list(KINDS)}")
    d = spec["dim"]
    if not isinstance(d, int) or isinstance(d, bool) or d not in (2, 3):
        _err("dim", f"must be the integer 2 or 3, got {d!r}")
    gravity = _vec(spec.get("gravity", [0.0, -9.81] + [0.0] * (d - 2)), "gravity", d)
    density = _num(spec["density"], "density", lo=0.0, lo_open=True)
    kappa = _num(spec["kappa"], "kappa", lo=0.0, lo_open=True)
    dom = spec["domain"]
    _keys(dom, {"min", "max"}, "domain")
    if "min" not in dom or "max" not in dom:
        _err("domain", "needs 'min' and 'max'")
    dmin = _vec(dom["min"], "domain.min", d)
    dmax = _vec(dom["max"], "domain.max", d)
    if np.any(dmax <= dmin):
        _err("domain", f"max must exceed min on every axis, got min {dmin.tolist()} max {dmax.tolist()}")
    floor_y, sticky, friction, contact = None, False, 0.0, "grid"
    if "floor" in spec:
        fl = spec["floor"]
        _keys(fl, FLOOR_KEYS, "floor")
        contact = fl.get("contact", "grid")
        if contact not in FLOOR_CONTACTS:
            _err("floor.contact", f"expected one of {FLOOR_CONTACTS}, got {contact!r}")
        floor_y = _num(fl.get("y", float(dmin[1])), "floor.y")
        fr = fl.get("friction", 0.0)
        if fr == "sticky":
            sticky = True
        else:
            friction = _num(fr, "floor.friction", lo=0.0)
    if "plate" in spec and "plates" in spec:
        _err("plates", "give either 'plate' or 'plates', not both")
    raw_plates = [spec["plate"]] if "plate" in spec else spec.get("plates", [])
    if not isinstance(raw_plates, list):
        _err("plates", "expected a list of plates")
    plates = tuple(_parse_plate(p, "plate" if "plate" in spec else f"plates[{i}]", d, dtype)
                   for i, p in enumerate(raw_plates))
    if kind == "hanging_plate" and len(plates) != 1:
        _err("plate", f"a hanging_plate scene needs exactly one plate, got {len(plates)}")
    if kind == "squeeze" and len(plates) < 1:
        _err("plates", "a squeeze scene needs at least one moving plate")
    shape = spec["initial_shape"]
    if not isinstance(shape, dict) or shape.get("type") not in SHAPE_KEYS:
        _err("initial_shape.type", f"expected one of {sorted(SHAPE_KEYS)}, got "
             f"{shape.get('type') if isinstance(shape, dict) else shape!r}")
    _keys(shape, SHAPE_KEYS[shape["type"]], "initial_shape")
    if shape["type"] == "box":
        lo = _vec(shape.get("min"), "initial_shape.min", d)
        hi = _vec(shape.get("max"), "initial_shape.max", d)
        if np.any(hi <= lo):
            _err("initial_shape", "box max must exceed min on every axis")
    elif shape["type"] == "ellipse":
        _vec(shape.get("center"), "initial_shape.center", d)
        _vec(shape.get("radii"), "initial_shape.radii", d, positive=True)
    v0 = tuple(_vec(spec.get("initial_velocity", [0.0] * d), "initial_velocity", d).tolist())
    for k in ("name", "notes"):
        if k in spec and not isinstance(spec[k], str):
            _err(k, "expected a string")
    _check_geometry(spec, dmin, dmax, floor_y, plates, "plate" if "plate" in spec else "plates")
    return Scene(
        gravity=jnp.asarray(gravity, dtype), plates=plates, floor_friction=jnp.asarray(friction, dtype),
        kind=kind, dim=d, density=density, kappa=kappa, domain_min=tuple(dmin.tolist()),
        domain_max=tuple(dmax.tolist()), floor_y=floor_y, floor_sticky=sticky, floor_contact=contact,
        initial_velocity=v0,
        source=json.dumps(spec, sort_keys=True))


def _read_spec(scene) -> dict:
    """The JSON object of a scene file or text: a path object or the name of an existing file is read
    as a file; any other string must be JSON text (no guess from its first character)."""
    text = os.fspath(scene) if isinstance(scene, os.PathLike) else scene
    if not isinstance(text, str):
        raise SceneError(f"scene: expected a dict, JSON text or a file path, got {type(scene).__name__}")
    if isinstance(scene, os.PathLike) or os.path.exists(text):
        try:
            with open(text, encoding="utf-8") as fh:
                body = fh.read()
        except UnicodeDecodeError as exc:
            raise SceneError(f"scene file {text!r}: must be UTF-8 text (byte {exc.object[exc.start:exc.start + 1]!r} "
                             f"at position {exc.start} is not UTF-8); save it as UTF-8 JSON") from exc
        except OSError as exc:
            raise SceneError(f"scene: cannot read file {text!r}: {exc}") from exc
        try:
            return json.loads(body)
        except json.JSONDecodeError as exc:
            raise SceneError(f"scene file {text!r}: not valid JSON ({exc})") from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        if text.lstrip().startswith(("{", "[")):
            raise SceneError(f"scene: not valid JSON ({exc})") from exc
        raise SceneError(f"scene: cannot read file {text!r}: no such file (and the text is not JSON either)") from exc


def _plate_range(plate: Plate) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (d,) m: the box every position of the plate's motion stays in."""
    c = np.asarray(plate.center, float)
    h = np.asarray(plate.half_size, float)
    if plate.motion == "sinusoid":
        reach = np.abs(np.asarray(plate.axis, float)) * float(plate.amplitude)
        return c - h - reach, c + h + reach
    if plate.motion == "samples":
        pos = np.asarray(plate.sample_positions, float)
        return pos.min(axis=0) - h, pos.max(axis=0) + h
    return c - h, c + h


def _check_geometry(spec, dmin, dmax, floor_y, plates, plate_field):
    """The floor, the initial shape and the plates against the domain: errors for what cannot be simulated
    as written, a PlausibilityWarning for a plate whose whole motion stays clear of the initial shape."""
    d = len(dmin)
    tol = GEOMETRY_TOL * max(1.0, float(np.max(np.abs(np.concatenate([dmin, dmax])))))
    axes = "xyz"
    if floor_y is not None and not (dmin[1] - tol <= floor_y < dmax[1]):
        _err("floor.y", f"must lie in the domain's y range [{dmin[1]:g}, {dmax[1]:g}) m, got {floor_y:g}")
    shape = spec["initial_shape"]
    box = None
    if shape["type"] == "box":
        box = (np.asarray(shape["min"], float), np.asarray(shape["max"], float))
    elif shape["type"] == "ellipse":
        c, r = np.asarray(shape["center"], float), np.asarray(shape["radii"], float)
        box = (c - r, c + r)
    if box is not None:
        lo, hi = box
        for a in range(d):
            if hi[a] <= dmin[a] + tol or lo[a] >= dmax[a] - tol:
                _err("initial_shape", f"{shape['type']} spans {axes[a]} in [{lo[a]:g}, {hi[a]:g}] m, entirely "
                     f"outside the domain's [{dmin[a]:g}, {dmax[a]:g}] m")
            if lo[a] < dmin[a] - tol or hi[a] > dmax[a] + tol:
                warnings.warn(f"scene field 'initial_shape': {shape['type']} spans {axes[a]} in [{lo[a]:g}, "
                              f"{hi[a]:g}] m, beyond the domain's [{dmin[a]:g}, {dmax[a]:g}] m: the part outside "
                              f"is not simulated", PlausibilityWarning, stacklevel=3)
        # Material the domain keeps below the floor would start inside it.
        if floor_y is not None and max(lo[1], dmin[1]) < floor_y - tol:
            _err("initial_shape", f"{shape['type']} reaches down to y = {max(lo[1], dmin[1]):g} m, below the floor "
                 f"(floor.y = {floor_y:g} m): material must start on or above the floor")
    for i, plate in enumerate(plates):
        field = "plate" if plate_field == "plate" else f"plates[{i}]"
        plo, phi = _plate_range(plate)
        if np.any(phi <= dmin) or np.any(plo >= dmax):
            _err(field, f"lies outside the domain along its whole motion (it spans {plo.round(6).tolist()} to "
                 f"{phi.round(6).tolist()} m, the domain {dmin.tolist()} to {dmax.tolist()} m): check its "
                 "center and half_size (m)")
        if box is not None and (np.any(phi < box[0] - tol) or np.any(plo > box[1] + tol)):
            warnings.warn(f"scene field '{field}': the plate never touches the initial material (its motion "
                          f"spans {plo.round(6).tolist()} to {phi.round(6).tolist()} m, the initial shape "
                          f"{box[0].round(6).tolist()} to {box[1].round(6).tolist()} m)",
                          PlausibilityWarning, stacklevel=3)


# ----------------------------------------------------------------------------------------------
# Initial particles
# ----------------------------------------------------------------------------------------------

def _inside_mask(points2, mask, pixel_size, origin):
    """Whether 2D world points (n, 2) fall on a foam pixel of `mask` (row 0 = top)."""
    H, W = mask.shape
    j = np.floor((points2[:, 0] - origin[0]) / pixel_size).astype(int)
    i = H - 1 - np.floor((points2[:, 1] - origin[1]) / pixel_size).astype(int)
    ok = (i >= 0) & (i < H) & (j >= 0) & (j < W)
    out = np.zeros(len(points2), bool)
    out[ok] = mask[i[ok], j[ok]] > 0
    return out


def inside_initial_shape(scene: Scene, points: np.ndarray, first_mask=None) -> np.ndarray:
    """Whether points (n, d) lie in the scene's initial shape.

    first_mask: (mask (H, W) uint8, camera dict with pixel_size and origin) for shape 'first_mask'.
    In 3D the mask is revolved about the vertical axis through its centroid (x) and the domain's
    mid-depth (z).
    """
    shape = scene.initial_shape
    kind = shape["type"]
    if kind == "box":
        lo, hi = np.asarray(shape["min"]), np.asarray(shape["max"])
        return np.all((points >= lo) & (points <= hi), axis=1)
    if kind == "ellipse":
        c, r = np.asarray(shape["center"]), np.asarray(shape["radii"])
        return np.sum(((points - c) / r) ** 2, axis=1) <= 1.0
    if first_mask is None:
        raise SceneError("initial_shape 'first_mask' needs the first mask and camera (pass first_mask=(mask, camera))")
    mask, camera = first_mask
    mask = np.asarray(mask)
    p, origin = float(camera["pixel_size"]), np.asarray(camera["origin"], float)
    if scene.dim == 2:
        return _inside_mask(points, mask, p, origin)
    H, W = mask.shape
    cols = np.nonzero(mask)[1]
    if len(cols) == 0:
        raise SceneError("initial_shape 'first_mask': the first mask holds no foam pixel")
    cx = origin[0] + (cols.mean() + 0.5) * p
    cz = 0.5 * (scene.domain_min[2] + scene.domain_max[2])
    r = np.hypot(points[:, 0] - cx, points[:, 2] - cz)
    return _inside_mask(np.stack([cx + r, points[:, 1]], 1), mask, p, origin) | \
        _inside_mask(np.stack([cx - r, points[:, 1]], 1), mask, p, origin)


def continued_into_plates(scene: Scene, pts: np.ndarray, inside: np.ndarray, spacing: float) -> np.ndarray:
    """(n,) bool: sample points (n, d) that continue a hanging primitive shape into the sticky plate it meets.

    A sticky plate holds only material that reaches its nodes; a shape that ends at a plate's bottom or
    side face (within half a particle `spacing`, m) grips it by less than a cell, by an amount that
    changes with dx: a box ending at the face of the data format's example board hung until 0.4 s at
    dx = 1 cm and had fallen by then at 5 and 2.5 mm. So where a shape that does not rest on the floor
    (its lowest point more than a spacing above it, or above the domain's bottom without one) meets
    such a face from outside, the plate's sample points in line with it (across that face) are added:
    the foam is taken to continue into the plate, as the scenes that overlap their plates model it. A
    plate the shape already enters anywhere (the scene models its glue itself), foam resting on the
    floor (a squeeze under a plate) and plates' top faces are left alone.
    """
    out = np.zeros(len(pts), bool)
    sticky = [pl for pl in scene.plates if pl.sticky]
    if not sticky or not inside.any():
        return out
    d = scene.dim
    floor = scene.floor_y if scene.floor_y is not None else scene.domain_min[1]
    if pts[inside, 1].min() <= floor + spacing:
        return out
    delta = 0.5 * spacing
    for plate in sticky:
        c = np.asarray(plate.position(0.0), float)[:d]
        h = np.asarray(plate.half_size, float)[:d]
        in_plate = np.all(np.abs(pts - c) <= h, axis=1)
        if np.any(in_plate & inside):  # the scene already puts material in this plate: its glue as modelled
            continue
        cand = np.nonzero(in_plate)[0]
        if len(cand) == 0:
            continue
        hit = np.zeros(len(cand), bool)
        # the bottom face (axis 1, below) and the side faces (every other axis, both sides)
        for a, sgn in [(1, -1.0)] + [(a, s) for a in range(d) if a != 1 for s in (-1.0, 1.0)]:
            face = c[a] + sgn * h[a]
            outside, within = pts[cand].copy(), pts[cand].copy()
            outside[:, a] = face + sgn * delta
            within[:, a] = face - sgn * delta
            hit |= inside_initial_shape(scene, outside) & ~inside_initial_shape(scene, within)
        out[cand[hit]] = True
    return out


def sample_particles(scene: Scene, dx: float, ppc: int | None = None, seed: int = 0, first_mask=None):
    """Jittered-grid sampling of the initial shape: returns (positions (n, d) m, volume per particle m^d).

    Cells of side dx cover the domain; each holds ppc points (stratified k^d sub-cells with a jitter
    when ppc = k^d, uniform otherwise); points inside the shape are kept.
    """
    d = scene.dim
    ppc = DEFAULT_PPC[d] if ppc is None else int(ppc)
    if ppc < 1:
        raise ValueError(f"ppc (particles per cell) must be >= 1, got {ppc}")
    if not (dx > 0 and math.isfinite(dx)):
        raise ValueError(f"dx must be a positive length in m, got {dx}")
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(scene.domain_min), np.asarray(scene.domain_max)
    ncell = np.ceil((hi - lo) / dx).astype(int)
    if np.prod(ncell) * ppc > MAX_CANDIDATES:
        raise ValueError(f"dx = {dx:g} m and ppc = {ppc} give {int(np.prod(ncell)):,} cells x {ppc} = "
                         f"{int(np.prod(ncell)) * ppc:,} sample points over the domain, more than {MAX_CANDIDATES:,}: "
                         f"use a coarser dx or fewer particles per cell")
    cells = np.stack(np.meshgrid(*[np.arange(n) for n in ncell], indexing="ij"), -1).reshape(-1, d)
    k = round(ppc ** (1.0 / d))
    if k ** d == ppc:
        sub = np.stack(np.meshgrid(*[np.arange(k)] * d, indexing="ij"), -1).reshape(-1, d)
        local = (sub[None, :, :] + rng.uniform(0.2, 0.8, (len(cells), ppc, d))) / k
    else:
        local = rng.uniform(0.0, 1.0, (len(cells), ppc, d))
    pts = (lo + (cells[:, None, :] + local) * dx).reshape(-1, d)
    pts = pts[np.all(pts < hi, axis=1)]
    keep = inside_initial_shape(scene, pts, first_mask)
    if first_mask is None:  # a first mask is continued into its plates on the image (io.glue_under_plates)
        keep |= continued_into_plates(scene, pts, keep, dx / ppc ** (1.0 / d))
    pts = pts[keep]
    if len(pts) == 0:
        raise SceneError("initial_shape: no particle falls inside the shape at this dx")
    return pts, dx ** d / ppc


def init_state(scene: Scene, dx: float, ppc: int | None = None, *, rho: float | None = None, seed: int = 0,
               first_mask=None, capacity: int | None = None, dtype=jnp.float64) -> State:
    """Sample the scene's initial shape into a State at rest (or at the scene's initial velocity).

    rho: density used for particle masses, kg/m^3 (default: the scene's).
    """
    pts, vol = sample_particles(scene, dx, ppc, seed, first_mask)
    rho = scene.density if rho is None else rho
    n = len(pts)
    return make_state(pts, np.full(n, vol), np.full(n, vol * rho), v=np.asarray(scene.initial_velocity),
                      capacity=capacity, dtype=dtype)
