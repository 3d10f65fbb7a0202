"""Scenes for the reference simulator: the spec's JSON (shared/specs/silhouettes.md) read into its own
boundary description and particle sampling. SI units.

Accepted: kind hanging_plate | drop | squeeze, dim 2 | 3, gravity, density, kappa, domain, floor
{y, friction (number or "sticky")}, plate or plates {center, half_size, motion (none | sinusoid |
samples), sticky}, initial_shape box | ellipse, initial_velocity; name and notes are ignored.
"""
from __future__ import annotations

import json
import math

import numpy as np

from .mpm import FLOOR_COULOMB, FLOOR_NONE, FLOOR_STICKY, Particles

SCENES_DIR = __import__("pathlib").Path(__file__).resolve().parents[1] / "scenes"
KNOWN_KEYS = {"kind", "dim", "gravity", "density", "kappa", "domain", "floor", "plate", "plates",
              "initial_shape", "initial_velocity", "name", "notes"}


class Plate:
    """A rigid box: centre (d,) m, half_size (d,) m, motion dict of the spec, sticky flag."""

    def __init__(self, spec, d):
        self.center = np.asarray(spec["center"], float)
        self.half = np.asarray(spec["half_size"], float)
        self.motion = dict(spec.get("motion", {"type": "none"}))
        self.sticky = bool(spec.get("sticky", True))
        self.kind = self.motion.get("type", "none")
        if self.kind == "samples":
            self.ts = np.asarray(self.motion["times"], float)
            self.xs = np.asarray(self.motion["positions"], float).reshape(len(self.ts), d)
        elif self.kind == "sinusoid":
            mo = self.motion
            self.axis = np.asarray(mo.get("axis", [1.0] + [0.0] * (d - 1)), float)
            self.amp, self.freq = float(mo.get("amplitude", 0.0)), float(mo.get("frequency", 0.0))
            self.phase, self.ramp = float(mo.get("phase", 0.0)), float(mo.get("ramp_time", 0.0))

    def position(self, t):
        """Centre at time t (s), m."""
        if self.kind == "samples":
            return np.array([np.interp(t, self.ts, self.xs[:, k]) for k in range(self.xs.shape[1])])
        if self.kind == "sinusoid":
            r = min(1.0, t / self.ramp) if self.ramp > 0 else 1.0
            return self.center + self.axis * self.amp * r * math.sin(2 * math.pi * self.freq * t + self.phase)
        return self.center.copy()

    def velocity(self, t):
        """Velocity at time t (s), m/s: the derivative of `position` (one-sided at sample knots)."""
        if self.kind == "samples":
            k = int(np.searchsorted(self.ts, t, side="right")) - 1
            if k < 0 or k >= len(self.ts) - 1:
                return np.zeros(self.xs.shape[1])
            return (self.xs[k + 1] - self.xs[k]) / (self.ts[k + 1] - self.ts[k])
        if self.kind == "sinusoid":
            w = 2 * math.pi * self.freq
            ramping = self.ramp > 0 and t < self.ramp
            r = t / self.ramp if ramping else 1.0
            dr = 1.0 / self.ramp if ramping else 0.0
            arg = w * t + self.phase
            return self.axis * self.amp * (dr * math.sin(arg) + r * w * math.cos(arg))
        return np.zeros_like(self.center)

    def max_speed(self):
        """An upper bound of the speed over all times, m/s."""
        if self.kind == "samples" and len(self.ts) > 1:
            return float(np.max(np.linalg.norm(np.diff(self.xs, axis=0), axis=1) / np.diff(self.ts)))
        if self.kind == "sinusoid":
            return abs(self.amp) * (2 * math.pi * abs(self.freq) + (1.0 / self.ramp if self.ramp > 0 else 0.0))
        return 0.0


class Boundaries:
    """Walls (slip, at the domain box), floor (y m, FLOOR_* mode, Coulomb coefficient) and plates."""

    def __init__(self, lo, hi, floor_y=None, friction=0.0, plates=()):
        self.wall_lo = np.asarray(lo, float)
        self.wall_hi = np.asarray(hi, float)
        self.plates = list(plates)
        if floor_y is None:
            self.floor_mode, self.floor_y, self.friction = FLOOR_NONE, -1e30, 0.0
        elif friction == "sticky":
            self.floor_mode, self.floor_y, self.friction = FLOOR_STICKY, float(floor_y), 0.0
        else:
            self.floor_mode, self.floor_y, self.friction = FLOOR_COULOMB, float(floor_y), float(friction)
        self.clamp_lo = self.wall_lo.copy()
        if floor_y is not None:
            self.clamp_lo[1] = max(self.clamp_lo[1], self.floor_y)
        self.clamp_hi = self.wall_hi.copy()
        self._speed = max([p.max_speed() for p in self.plates], default=0.0)

    def max_plate_speed(self, t):
        return self._speed

    def plate_arrays(self, t):
        """(lo (P, d), hi (P, d), velocity (P, d), sticky (P,)) of the plates at time t (s)."""
        d = len(self.wall_lo)
        if not self.plates:
            z = np.zeros((0, d))
            return z, z, z, np.zeros(0, np.bool_)
        c = np.array([p.position(t) for p in self.plates])
        h = np.array([p.half for p in self.plates])
        vel = np.array([p.velocity(t) for p in self.plates])
        return c - h, c + h, vel, np.array([p.sticky for p in self.plates], np.bool_)


class RefScene:
    """A parsed scene: spec (the JSON dict), dim, gravity, density, kappa, domain lo/hi, boundaries."""

    def __init__(self, spec):
        if isinstance(spec, str):
            spec = json.loads(open(spec).read()) if spec.endswith(".json") else json.loads(spec)
        unknown = set(spec) - KNOWN_KEYS
        if unknown:
            raise ValueError(f"scene: unknown key(s) {sorted(unknown)}")
        self.spec = spec
        self.kind = spec["kind"]
        self.dim = d = int(spec["dim"])
        self.gravity = np.asarray(spec.get("gravity", [0.0, -9.81] + [0.0] * (d - 2)), float)
        self.density = float(spec["density"])
        self.kappa = float(spec["kappa"])
        self.lo = np.asarray(spec["domain"]["min"], float)
        self.hi = np.asarray(spec["domain"]["max"], float)
        plates = [spec["plate"]] if "plate" in spec else list(spec.get("plates", []))
        self.plates = [Plate(p, d) for p in plates]
        floor = spec.get("floor")
        self.boundaries = Boundaries(self.lo, self.hi, None if floor is None else floor["y"],
                                     0.0 if floor is None else floor.get("friction", 0.0), self.plates)
        self.v0 = np.asarray(spec.get("initial_velocity", [0.0] * d), float)

    def inside(self, pts):
        """Whether points (N, d) m lie in the initial shape (and the domain, above the floor): bool (N,)."""
        sh = self.spec["initial_shape"]
        if sh["type"] == "box":
            keep = np.all((pts >= np.asarray(sh["min"])) & (pts <= np.asarray(sh["max"])), axis=1)
        elif sh["type"] == "ellipse":
            keep = np.sum(((pts - np.asarray(sh["center"])) / np.asarray(sh["radii"])) ** 2, axis=1) <= 1.0
        else:
            raise ValueError(f"scene.initial_shape: the reference simulator needs box or ellipse, got {sh['type']!r}")
        keep &= np.all((pts >= self.lo) & (pts <= self.hi), axis=1)
        if self.boundaries.floor_mode != FLOOR_NONE:
            keep &= pts[:, 1] >= self.boundaries.floor_y
        return keep

    def shape_bounds(self):
        sh = self.spec["initial_shape"]
        if sh["type"] == "box":
            lo, hi = np.asarray(sh["min"], float), np.asarray(sh["max"], float)
        else:
            c, r = np.asarray(sh["center"], float), np.asarray(sh["radii"], float)
            lo, hi = c - r, c + r
        return np.maximum(lo, self.lo), np.minimum(hi, self.hi)


def particle_spacing(dx, ppc, d):
    """Mean particle spacing, m, of ppc particles per cell of side dx (m) in d dimensions."""
    return dx / ppc ** (1.0 / d)


def sample(scene, dx, ppc, seed=0):
    """Stratified jittered sampling of the initial shape: one uniform random point in each cube of side
    `particle_spacing(dx, ppc, d)` of a lattice with a random offset; each particle carries the cube's
    volume (m^3; m^2 per unit depth in 2D). Returns `Particles` at the scene's initial velocity."""
    d = scene.dim
    s = particle_spacing(dx, ppc, d)
    rng = np.random.default_rng(seed)
    lo, hi = scene.shape_bounds()
    start = lo - s * rng.random(d)
    counts = np.ceil((hi - start) / s).astype(int) + 1
    axes = [start[k] + s * np.arange(counts[k]) for k in range(d)]
    cells = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    pts = cells + s * rng.random(cells.shape)
    pts = pts[scene.inside(pts)]
    return Particles(pts, s ** d, scene.density, scene.v0)
