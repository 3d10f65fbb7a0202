"""Experiment design: which recording to make so that a fit pins the material's parameters (`design`).

Candidate recordings of one scene (its plate motion, initial shape, duration, frame rate and pixel
size set from a grid of design variables) are ranked by the 95% intervals a fit of each would report.
For every candidate and every parameter point (the guess and `points - 1` others around it, so a wrong
guess does not decide the ranking), the candidate is simulated on the design's grid at that point,
rendered as a tracked video would be (hard masks with boundary noise, `fitting.synth`), and the fit's
residual and Jacobian are evaluated there. The predicted interval is the Gauss-Newton interval of a
joint fit (`fitting.joint`) of that recording with the recordings already made (`with_data`: their
residual at the guess sets their noise scale, their Jacobian is taken at the point). It is what the
fitter reports when its optimum is the truth and the model represents the data; discretization and
model error, which widen intervals of real data, enter through `misfit="with"` (the default with
recordings already made: the candidate misfits as they do) and, with `dx_check=True`, through the fit's
discretization check predicted for every recording (the grid's numerical error, added as the fit adds it).

Candidates that differ only in the scene's differentiable data (plate amplitude, frequency, phase,
ramp time, sample times and positions, floor friction) share one compiled rollout.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
import math
import time
from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from jaxfoam import FIT_FIELDS, init_state, load_scene
from jaxfoam.guards import atomic_output

from .io import Silhouettes, camera_covering, plate_footprint, read_silhouettes, validate
from .check import check_error, combine_intervals, finer_settings, predicted_move
from .joint import JointProblem, information_shares, joint_grid_error, joint_uncertainty, noise_scales
from .problem import _data_fingerprint, build_problem, fit_grid
from .settings import CalibrationError, DX_CHECK_RATIO, FitSettings, NUISANCE_FIELDS
from .synth import boundary_pixels, hard_masks

# What a calibrated foam is quoted to (relative for mu, sigma_y, eta; absolute for m, dimensionless):
# a rheometer's flow-curve accuracy, and the targets of the design evidence (experiments/design_study.py).
TOLERANCE = {"mu": 0.10, "sigma_y": 0.10, "eta": 0.25, "m": 0.1}
ABSOLUTE = ("m",)
# Values per ranged design variable (lo:hi): 3 levels of 2 variables stay under a dozen candidates.
DEFAULT_LEVELS = 3
# Parameter points per candidate: the guess and two on either side of the sigma_y-eta trade-off.
DEFAULT_POINTS = 3
# The robustness points lie a factor DEFAULT_SPREAD above or below the guess for the positive
# parameters and M_SPREAD (dimensionless) from it for m: a guess within 1.5x is what a user has.
DEFAULT_SPREAD = 1.5
M_SPREAD = 0.15
ROBUST = ("worst", "mean")
# Whose particles make the predicted recording: the fit's own ("same": the noise is the renderer's and the
# boundary flips'), or a second sampling ("other": the misfit of another discretization of the material too).
SAMPLINGS = ("same", "other")
# The predicted recording's misfit: the renderer's noise ("render"), or at least the recordings already made
# have at the guess ("with": model error like theirs, which real data carry); "auto": "with" given recordings.
MISFITS = ("auto", "render", "with")
# Boundary-pixel flip probability of the predicted recordings: synth's default, about the tracking
# error measured on rendered videos (docs/data.md).
DESIGN_NOISE = 0.05
# A recording's length (s) and frame rate (1/s) unless varied: synth's 16 frames over 1 s.
DEFAULT_DURATION = 1.0
DEFAULT_FPS = 15.0
# Samples per period of an amplitude sweep written as plate samples: linear interpolation of a sine
# at 32 samples per period is within 0.5% of its amplitude.
SWEEP_SAMPLES_PER_PERIOD = 32
# Design variables that are not paths into the scene JSON, with their units.
RECORDING_VARIABLES = {"duration": "s", "fps": "1/s", "pixel_size": "m"}
DERIVED_VARIABLES = {
    "plate.motion.sweep": "m, the plate amplitude at the end of the recording (a linear sweep from "
                          "plate.motion.amplitude; the motion becomes plate samples)",
    "shape.height": "m, height of the initial shape's centre above the floor (the domain bottom without one)",
    "shape.size": "m, the initial shape's largest half-extent (scaled about its centre)",
    "squeeze.speed": "m/s, the first plate's press speed",
    "squeeze.depth": "m, how far the first plate moves down",
    "squeeze.hold": "s, how long the first plate holds at depth",
}
# Signs of the robustness points' moves of (mu, sigma_y, eta, m), in order: along the sigma_y-eta
# trade-off first (sigma_y up with eta down and the reverse), then the other sign patterns.
_POINT_SIGNS = ((1, -1, 1, -1), (-1, 1, -1, 1), (1, 1, -1, -1), (-1, -1, 1, 1), (1, -1, -1, 1), (-1, 1, 1, -1))


@dataclasses.dataclass(frozen=True)
class Variable:
    """A design variable: its name (`RECORDING_VARIABLES`, `DERIVED_VARIABLES` or a path to a number in
    the scene JSON, e.g. plate.motion.frequency) and the values the candidates take."""

    name: str
    values: tuple


def parse_vary(text: str, levels: int = DEFAULT_LEVELS) -> Variable:
    """Parse 'NAME=LO:HI' (`levels` values, evenly spaced), 'NAME=LO:HI:N' or 'NAME=V1,V2,...'."""
    if "=" not in str(text):
        raise CalibrationError(f"--vary: expected NAME=LO:HI, NAME=LO:HI:N or NAME=V1,V2,..., got {text!r}")
    name, spec = (s.strip() for s in str(text).split("=", 1))
    try:
        parts = [float(v) for v in spec.split(":" if ":" in spec else ",")]
    except ValueError:
        parts = None
    if parts is None or (":" in spec and len(parts) not in (2, 3)):
        raise CalibrationError(f"--vary {name}: values must be numbers as LO:HI, LO:HI:N or V1,V2,..., got {spec!r}")
    if ":" in spec:
        lo, hi = parts[:2]
        n = levels if len(parts) == 2 else parts[2]
        if not (n == int(n) and n >= 2):
            raise CalibrationError(f"--vary {name}: the number of values must be an integer >= 2, got {n:g}")
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise CalibrationError(f"--vary {name}: needs finite LO < HI, got {lo:g}:{hi:g}")
        values = tuple(float(v) for v in np.linspace(lo, hi, int(n)))
    else:
        values = tuple(parts)
    if not values or not all(math.isfinite(v) for v in values) or len(set(values)) != len(values):
        raise CalibrationError(f"--vary {name}: needs distinct finite values, got {spec!r}")
    if name in RECORDING_VARIABLES and min(values) <= 0:
        raise CalibrationError(f"--vary {name}: must be > 0 {RECORDING_VARIABLES[name]}, got {min(values):g}")
    return Variable(name, values)


def _path(spec: dict, name: str) -> tuple[object, object]:
    """(container, key) of the number that a dotted path (list items by index) names in the scene."""
    keys = name.split(".")
    if keys[0] == "plate" and "plate" not in spec and len(spec.get("plates", ())) >= 1:
        keys = ["plates", "0"] + keys[1:]
    node = spec
    for i, k in enumerate(keys):
        where = ".".join(keys[:i]) or "the scene"
        if isinstance(node, list):
            if not (k.isdigit() and int(k) < len(node)):
                raise CalibrationError(f"--vary {name}: {where} is a list of {len(node)}; {k!r} is not an index of it")
            k = int(k)
        elif not (isinstance(node, dict) and k in node):
            have = sorted(node) if isinstance(node, dict) else []
            raise CalibrationError(f"--vary {name}: {where} has no {k!r} (it has {have}); design variables are "
                                   f"{sorted(RECORDING_VARIABLES) + sorted(DERIVED_VARIABLES)} or a path to a number "
                                   f"in the scene")
        if i == len(keys) - 1:
            if isinstance(node[k], bool) or not isinstance(node[k], (int, float)):
                raise CalibrationError(f"--vary {name}: the scene's value there is {node[k]!r}, not a number")
            return node, k
        node = node[k]


def _plate_spec(spec: dict, name: str) -> dict:
    plates = [spec["plate"]] if "plate" in spec else list(spec.get("plates", ()))
    if not plates:
        raise CalibrationError(f"--vary {name}: the scene has no plate")
    return plates[0]


def _shape_frame(spec: dict):
    shape = spec["initial_shape"]
    if shape.get("type") == "ellipse":
        return np.asarray(shape["center"], float), np.asarray(shape["radii"], float)
    if shape.get("type") == "box":
        lo, hi = np.asarray(shape["min"], float), np.asarray(shape["max"], float)
        return 0.5 * (lo + hi), 0.5 * (hi - lo)
    raise CalibrationError(f"shape.height, shape.size: need an initial_shape 'box' or 'ellipse', not {shape.get('type')!r}")


def _set_shape(spec: dict, center, half) -> None:
    shape = spec["initial_shape"]
    if shape["type"] == "ellipse":
        shape["center"], shape["radii"] = [float(v) for v in center], [float(v) for v in half]
    else:
        shape["min"], shape["max"] = [float(v) for v in center - half], [float(v) for v in center + half]


def _squeeze(spec: dict, speed=None, depth=None, hold=None) -> None:
    """Press the first plate `depth` m at `speed` m/s, hold `hold` s, pull up at its own speed (4 samples)."""
    motion = _plate_spec(spec, "squeeze.*").get("motion", {})
    t = np.asarray(motion.get("times", ()), float)
    x = np.asarray(motion.get("positions", ()), float)
    if motion.get("type") != "samples" or len(t) != 4 or not np.allclose(x[1], x[2]):
        raise CalibrationError("squeeze.*: need a first plate with 'samples' motion of 4 samples (start, pressed, "
                               "held at the same position, pulled up)")
    down = x[1] - x[0]
    depth0 = float(np.linalg.norm(down))
    u = down / depth0
    d = depth0 if depth is None else float(depth)
    v = depth0 / (t[1] - t[0]) if speed is None else float(speed)
    h = t[2] - t[1] if hold is None else float(hold)
    for label, val in (("squeeze.depth", d), ("squeeze.speed", v)):
        if not val > 0:
            raise CalibrationError(f"--vary {label}: must be > 0, got {val:g}")
    if h < 0:
        raise CalibrationError(f"--vary squeeze.hold: must be >= 0 s, got {h:g}")
    up = float(np.linalg.norm(x[3] - x[2])) / (t[3] - t[2])
    x1 = x[0] + u * d
    t1 = t[0] + d / v
    t2 = t1 + max(h, 1e-6 * t1)  # strictly increasing sample times
    t3 = t2 + float(np.linalg.norm(x[3] - x1)) / up
    motion["times"] = [float(t[0]), float(t1), float(t2), float(t3)]
    motion["positions"] = [x[0].tolist(), x1.tolist(), x1.tolist(), x[3].tolist()]


def _sweep(spec: dict, end_amplitude: float, duration: float) -> None:
    """The first plate's sinusoid with its amplitude going linearly to `end_amplitude` m at `duration` s,
    written as samples (SWEEP_SAMPLES_PER_PERIOD per period)."""
    plate = _plate_spec(spec, "plate.motion.sweep")
    m = plate.get("motion", {})
    if m.get("type") != "sinusoid":
        raise CalibrationError("plate.motion.sweep: needs a plate with 'sinusoid' motion")
    a0, f, phase, ramp = (float(m.get(k, 0.0)) for k in ("amplitude", "frequency", "phase", "ramp_time"))
    axis = np.asarray(m["axis"], float)
    c = np.asarray(plate["center"], float)
    n = int(math.ceil(duration * f * SWEEP_SAMPLES_PER_PERIOD)) + 1
    t = np.linspace(0.0, duration, n)
    r = np.minimum(1.0, t / ramp) if ramp > 0 else np.ones_like(t)
    amp = a0 + (float(end_amplitude) - a0) * t / duration
    pos = c[None, :] + axis[None, :] * (amp * r * np.sin(2 * math.pi * f * t + phase))[:, None]
    plate["motion"] = {"type": "samples", "times": t.tolist(), "positions": pos.tolist()}


def candidate_scene(spec: dict, values: dict, duration: float = DEFAULT_DURATION, fps: float = DEFAULT_FPS,
                    pixel_size: float | None = None) -> tuple[dict, dict]:
    """The scene JSON (dict) and recording (duration s, fps 1/s, pixel_size m or None, frames) of one
    candidate: the design variables `values` (name -> value) applied to `spec`."""
    spec = copy.deepcopy(spec)
    rec = dict(duration=float(duration), fps=float(fps), pixel_size=pixel_size)
    squeeze = {}
    for name, v in values.items():
        if name in RECORDING_VARIABLES:
            rec[name] = float(v)
        elif name.startswith("squeeze."):
            squeeze[name.split(".", 1)[1]] = float(v)
        elif name in ("shape.height", "shape.size"):
            center, half = _shape_frame(spec)
            if name == "shape.height":
                floor = spec["floor"]["y"] if "floor" in spec else spec["domain"]["min"][1]
                center[1] = float(floor) + float(v)
            else:
                half = half * (float(v) / float(np.max(half)))
            _set_shape(spec, center, half)
        elif name != "plate.motion.sweep":
            node, key = _path(spec, name)
            node[key] = float(v)
    if squeeze:
        _squeeze(spec, **squeeze)
    if "plate.motion.sweep" in values:
        _sweep(spec, values["plate.motion.sweep"], rec["duration"])
    rec["frames"] = int(round(rec["fps"] * rec["duration"])) + 1
    return spec, rec


def _structure(spec: dict, rec: dict) -> str:
    """A key equal for candidates that differ only in the scene's differentiable data."""
    s = copy.deepcopy(spec)
    s.pop("name", None), s.pop("notes", None)
    plates = [s["plate"]] if "plate" in s else list(s.get("plates", ()))
    for p in plates:
        m = p.get("motion", {})
        for k in ("amplitude", "frequency", "phase", "ramp_time"):
            if k in m:
                m[k] = None
        for k in ("times", "positions"):
            if k in m:
                m[k] = len(m[k])
    if isinstance(s.get("floor", {}).get("friction"), (int, float)):
        s["floor"]["friction"] = None
    return json.dumps([s, rec], sort_keys=True)


def parameter_points(guess: dict, names, count: int = DEFAULT_POINTS, spread: float = DEFAULT_SPREAD,
                     bounds: dict | None = None) -> list[dict]:
    """The guess and count - 1 points around it (positive parameters times spread^(+-1), m +- M_SPREAD,
    `_POINT_SIGNS`), each kept strictly inside `bounds` (one past a bound lies halfway between the guess
    and it: geometrically for positive parameters)."""
    if not 1 <= count <= len(_POINT_SIGNS) + 1:
        raise CalibrationError(f"points must be in [1, {len(_POINT_SIGNS) + 1}], got {count}")
    if not spread > 1.0:
        raise CalibrationError(f"spread must be > 1 (a factor), got {spread:g}")
    out = [dict(guess)]
    for signs in _POINT_SIGNS[:count - 1]:
        p = dict(guess)
        for n, sgn in zip(FIT_FIELDS, signs):
            if n not in names:
                continue
            v = guess[n] + sgn * M_SPREAD if n in ABSOLUTE else guess[n] * spread ** sgn
            if bounds and n in bounds:  # a point past a bound goes halfway to it: the transforms are open there
                lo, hi = bounds[n]
                g = guess[n]
                if not lo < v < hi:
                    b = hi if v >= hi else lo
                    v = 0.5 * (g + b) if n in ABSOLUTE else math.sqrt(g * b)
            p[n] = float(v)
        out.append(p)
    return out


def _rms(r, n_eff: float) -> float:
    """A residual's RMS per effective independent residual."""
    return math.sqrt(float(np.dot(r, r)) / max(float(n_eff), 1.0))


def half_widths(interval: dict, theta: dict) -> dict:
    """Half-widths of intervals: relative to the value for mu, sigma_y, eta; absolute for m."""
    out = {}
    for n, (lo, hi) in interval.items():
        hw = 0.5 * (hi - lo)
        out[n] = hw if n in ABSOLUTE else hw / abs(theta[n])
    return out


def _tolerance_ratio(hw: dict) -> dict:
    return {n: (v / TOLERANCE[n] if n in TOLERANCE else math.nan) for n, v in hw.items()}


def _render(problem, theta: dict, spec: dict, ppc: int, rec_seed) -> Silhouettes:
    """The recording a camera would give of `problem`'s rollout at parameters theta: hard masks of every
    frame with boundary noise (`DESIGN_NOISE`) and the plates' pixels at weight 0, as `fitting.synth`
    renders them."""
    data = problem.data
    x, active = problem.simulate({n: theta[n] for n in problem.transform.names})
    # Frames before the simulation's start (t = 0) show the initial state.
    s0 = problem.sim.state0
    xs = np.repeat(np.asarray(s0.x)[None], data.shape[0], axis=0)
    act = np.repeat(np.asarray(s0.active)[None], data.shape[0], axis=0)
    xs[problem.frames], act[problem.frames] = x, active
    masks = hard_masks(xs, act, data.camera, data.image_shape, problem.dx, ppc, problem.scene.dim)
    rng = np.random.default_rng(rec_seed)
    weights = np.ones(masks.shape, np.float32)
    for t in range(masks.shape[0]):
        flip = boundary_pixels(masks[t]) & (rng.random(data.image_shape) < DESIGN_NOISE)
        masks[t] ^= flip.astype(np.uint8)
        plate = plate_footprint(problem.scene, float(data.times[t]), data.camera, data.image_shape)
        masks[t][plate] = 0
        weights[t][plate] = 0.0
    return validate(masks, data.times, data.camera, spec, weights=weights, source="jaxfoam design (predicted)")


def _layout(spec: dict, rec: dict, settings: FitSettings, dtype) -> Silhouettes:
    """Data with a candidate's frame times and camera whose every frame shows the initial shape: what
    `build_problem` needs to bind the simulator before the candidate's own recording is rendered."""
    scene = load_scene(spec, dtype=dtype)
    d = scene.dim
    dx, ppc = fit_grid(scene, settings)
    pixel = dx / 2 if rec["pixel_size"] is None else float(rec["pixel_size"])
    camera, shape = camera_covering(scene, pixel)
    s0 = init_state(scene, dx, ppc, rho=scene.density, seed=settings.seed, dtype=dtype)
    m0 = hard_masks(np.asarray(s0.x)[None], np.asarray(s0.active)[None], camera, shape, dx, ppc, d)[0]
    times = np.linspace(0.0, rec["duration"], rec["frames"])
    return validate(np.repeat(m0[None], len(times), axis=0), times, camera, spec, source="jaxfoam design (layout)")


@dataclasses.dataclass(frozen=True)
class DesignResult:
    """A ranking of candidate recordings (`design`); written as JSON (format "jaxfoam-design").

    Attributes:
      guess: the parameter guess (Pa, Pa, Pa s^m, -).  points: the parameter points every candidate was
        evaluated at (the guess first).  variables: name -> values.  robust: "worst" or "mean" over the points.
      candidates: per candidate (in rank order): values, scene (JSON dict), recording (duration s, fps 1/s,
        pixel_size m, frames), predicted (per point: parameter -> [lo, hi] 95% interval), half_width
        (parameter -> the robust half-width: relative for mu, sigma_y, eta, absolute for m), within
        (parameters within TOLERANCE), score (geometric mean of half-width / tolerance), information_share
        (at the guess: parameter -> [this candidate, each recording already made]), wall_time s.
      with_only: the intervals of the recordings already made alone, at the guess (None without them).
      advice: the plain-language recommendation.  wall_time: s.  settings: the design's settings.
    """

    guess: dict
    points: list
    variables: dict
    robust: str
    candidates: list
    with_only: dict | None
    advice: str
    wall_time: float
    settings: dict

    @property
    def best(self) -> dict:
        return self.candidates[0]

    def as_dict(self) -> dict:
        return dict(format="jaxfoam-design", version=1, **dataclasses.asdict(self))

    def write(self, path) -> None:
        with atomic_output(path) as tmp:
            Path(tmp).write_text(json.dumps(self.as_dict(), indent=1, allow_nan=True))

    def write_scene(self, path) -> None:
        """The best candidate's scene JSON (for `jaxfoam synth` and for filming; its recording in "notes")."""
        best = self.best
        spec = dict(best["scene"])
        rec = best["recording"]
        spec["notes"] = (f"{spec.get('notes', '')} Recommended by jaxfoam design: record {rec['duration']:g} s at "
                         f"{rec['fps']:g} fps ({rec['frames']} frames)"
                         + (f", {rec['pixel_size']:g} m per pixel" if rec.get("pixel_size") else "")
                         + "; " + ", ".join(f"{k} = {v:g}" for k, v in best["values"].items()) + ".").strip()
        with atomic_output(path) as tmp:
            Path(tmp).write_text(json.dumps(spec, indent=2))

    def report(self) -> str:
        names = list(self.guess_names)
        head = f"{'rank':>4}  " + "  ".join(f"{n:>9}" for n in names) + "  within  " + ", ".join(self.variables)
        rel = [n for n in names if n not in ABSOLUTE]
        kinds = ([f"relative for {', '.join(rel)}"] if rel else []) + (
            [f"absolute for {', '.join(n for n in names if n in ABSOLUTE)}"] if len(rel) < len(names) else [])
        lines = [f"predicted 95% half-widths ({self.robust} over {len(self.points)} parameter points; "
                 f"{', '.join(kinds)})", head]
        for k, c in enumerate(self.candidates):
            hw = "  ".join(f"{_fmt_hw(n, c['half_width'][n]):>9}" for n in names)
            vals = ", ".join(f"{v:g}" for v in c["values"].values())
            lines.append(f"{k + 1:>4}  {hw}  {len(c['within']):>3}/{len(names)}  {vals}")
        lines += ["", self.advice]
        return "\n".join(lines)

    @property
    def guess_names(self):
        return tuple(self.candidates[0]["half_width"]) if self.candidates else ()


def _fmt_hw(name: str, v: float) -> str:
    if not math.isfinite(v):
        return "inf"
    return f"{v:.3g}" if name in ABSOLUTE else f"{100 * v:.3g}%"


def _advice(best: dict, names, with_only_hw: dict | None, with_labels) -> str:
    rec = best["recording"]
    what = ", ".join(f"{k} {v:g}" for k, v in best["values"].items() if k not in RECORDING_VARIABLES)
    film = f"Film {rec['duration']:g} s at {rec['fps']:g} fps"
    if rec.get("pixel_size"):
        film += f" ({1e3 * rec['pixel_size']:.3g} mm per pixel)"
    if what:
        film += f" with {what}"
    pinned = [n for n in names if with_only_hw and with_only_hw[n] <= TOLERANCE[n]]
    newly = [n for n in best["within"] if n not in pinned]
    wide = [n for n in names if n not in best["within"]]
    parts = [film + ":"]
    if newly:
        parts.append(", ".join(f"{n} (+-{_fmt_hw(n, best['half_width'][n])})" for n in newly)
                     + (" becomes" if len(newly) == 1 else " become") + " identifiable to the tolerance")
    if pinned:
        parts.append(("; " if newly else "") + ", ".join(pinned) + (" is" if len(pinned) == 1 else " are")
                     + f" already pinned by {', '.join(with_labels)}")
    if wide:
        parts.append(("; " if newly or pinned else "") + ", ".join(
            f"{n} stays at +-{_fmt_hw(n, best['half_width'][n])} (tolerance {_fmt_hw(n, TOLERANCE[n])})" for n in wide)
                     + ": add a recording that informs " + ("it" if len(wide) == 1 else "them")
                     + " (vary other design variables) or widen the design's ranges")
    return " ".join(parts[:1]) + " " + "".join(parts[1:]) + "."


def design(scene, guess: dict, variables, *, with_data=(), settings: FitSettings | None = None,
           points: int = DEFAULT_POINTS, spread: float = DEFAULT_SPREAD, robust: str = "worst",
           duration: float = DEFAULT_DURATION, fps: float = DEFAULT_FPS, pixel_size: float | None = None,
           progress: Callable[[str], None] | None = None, log=None, resume: bool = False,
           sampling: str = "same", misfit: str = "auto", dx_check: bool = False) -> DesignResult:
    """Rank the candidate recordings of `scene` by their predicted 95% intervals (module docs).

    Args:
      scene: scene JSON path or dict (initial shape 'box' or 'ellipse').
      guess: mu (Pa), sigma_y (Pa), eta (Pa s^m), m (-): the expected material.
      variables: `Variable`s (or 'NAME=LO:HI' strings); candidates are every combination of their values.
      with_data: recordings already made of the same material (`Silhouettes` or paths).
      settings: `FitSettings` of the fits predicted (grid dx, ppc, fixed parameters, level, seed).
      points, spread: the parameter points (`parameter_points`); robust: "worst" or "mean" over them.
      duration (s), fps (1/s), pixel_size (m, default dx / 2): each candidate's recording unless varied.
      progress: optional callable(str) for status lines.
      sampling: "same" or "other" (`SAMPLINGS`): the predicted recording is rendered from the fit's own
        particle sampling, or from a second one (seed + 1).
      misfit: "auto", "render" or "with" (`MISFITS`): the predicted recording's residual as rendered, or
        raised to the median RMS per effective residual of the `with_data` recordings at the guess (needs
        with_data; the guess should then be their fit). "auto": "with" when with_data is given.
      dx_check: predict the intervals a fit reports, not only their statistical part: at the guess, each
        recording's residual and Jacobian once more on a grid DX_CHECK_RATIO finer give the first-order
        move of the estimate between the grids (`fitting.check.predicted_move`, as the fit's discretization
        check without its refit), combined over the recordings by their Fisher information as the joint
        fit combines them, extrapolated like the fit's check (GCI_SAFETY, DX_CHECK_ORDER) and added in
        quadrature to every point's statistical half-width. A candidate whose silhouettes the grid resolves
        poorly (a tear-off, a splash) then ranks below one the fit grid can represent. Costs about one more
        Jacobian on the finer grid per candidate.
      log: a JSON file that receives each candidate's prediction as it finishes (written atomically);
        resume: take the candidates found there instead of evaluating them again (the log must be of the
        same design: CalibrationError otherwise).
    Returns a `DesignResult`, candidates best first: most parameters within TOLERANCE, then the lowest
    geometric mean of half-width over tolerance. Raises CalibrationError for bad input before any simulation.
    """
    wall0 = time.perf_counter()
    say = progress or (lambda msg: None)
    settings = (settings or FitSettings()).validate()
    if any(n in NUISANCE_FIELDS for n in settings.fitted):
        raise CalibrationError("fit_also: a design predicts the material's intervals; it does not fit nuisance "
                               "parameters")
    names = tuple(settings.fitted)
    missing = [n for n in names if n not in guess]
    if missing:
        raise CalibrationError(f"guess: needs {', '.join(missing)} (the fitted parameters {list(names)})")
    for n in names:
        lo, hi = settings.bounds_of(n)
        if not lo < float(guess[n]) < hi:
            raise CalibrationError(f"guess: {n} = {guess[n]:g} lies outside its bounds ({lo:g}, {hi:g})")
    if sampling not in SAMPLINGS:
        raise CalibrationError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    if robust not in ROBUST:
        raise CalibrationError(f"robust must be one of {ROBUST}, got {robust!r}")
    if misfit not in MISFITS:
        raise CalibrationError(f"misfit must be one of {MISFITS}, got {misfit!r}")
    if misfit == "auto":
        misfit = "with" if with_data else "render"
    if misfit == "with" and not with_data:
        raise CalibrationError("misfit 'with' takes the misfit of the recordings already made: give them (--with)")
    guess = {n: float(guess[n]) for n in names}
    spec = json.loads(Path(scene).read_text()) if not isinstance(scene, dict) else copy.deepcopy(scene)
    variables = [v if isinstance(v, Variable) else parse_vary(v) for v in variables]
    if not variables:
        raise CalibrationError("variables: a design needs at least one --vary")
    if len({v.name for v in variables}) != len(variables):
        raise CalibrationError("variables: each design variable may be varied once")
    dtype = jnp.float64 if settings.dtype == "float64" else jnp.float32
    fixed = dict(settings.fixed)
    pts = parameter_points(guess, names, points, spread, {n: settings.bounds_of(n) for n in names})
    full = [dict({n: float(fixed.get(n, guess.get(n, math.nan))) for n in FIT_FIELDS}, **p) for p in pts]
    # Every candidate is checked (scene geometry, variables) before any simulation.
    combos = list(itertools.product(*[v.values for v in variables]))
    candidates = []
    for combo in combos:
        values = dict(zip([v.name for v in variables], combo))
        c_spec, rec = candidate_scene(spec, values, duration, fps, pixel_size)
        try:
            load_scene(c_spec, dtype=dtype)
        except ValueError as exc:
            raise CalibrationError(f"candidate {values}: {exc}") from exc
        candidates.append(dict(values=values, scene=c_spec, recording=rec))
    labels = [f"recording {i}" if isinstance(d, Silhouettes) else str(d) for i, d in enumerate(with_data)]
    with_data = [d if isinstance(d, Silhouettes) else read_silhouettes(d) for d in with_data]
    rho = [float(fixed.get("rho", load_scene(spec).density))] + [
        float(fixed.get("rho", d.load_scene().density)) for d in with_data]
    if max(rho) - min(rho) > 1e-6 * max(rho):
        raise CalibrationError(f"density: the scene and the recordings give {rho} kg/m^3; one material has one "
                               f"density (set it with fix rho=...)")
    say(f"{len(candidates)} candidates x {len(pts)} parameter points")
    fingerprint = hashlib.sha256(json.dumps(
        [spec, guess, [[v.name, list(v.values)] for v in variables], pts, robust, duration, fps, pixel_size,
         settings.to_dict(), DESIGN_NOISE, sampling, misfit, [_data_fingerprint(d) for d in with_data]]
        + ([True] if dx_check else []),
        sort_keys=True, default=str).encode()).hexdigest()[:16]
    done = _read_log(log, fingerprint) if (log is not None and resume) else {}
    if done:
        say(f"resuming: {len(done)} of {len(candidates)} candidates from {log}")

    # Recordings already made: their noise from their residual at the guess, their Jacobian at each point.
    made = []
    for i, d in enumerate(with_data):
        pb = build_problem(d, settings)
        zg = pb.transform.to_unconstrained({n: guess[n] for n in pb.transform.names})
        r0 = np.asarray(pb.residual(zg), np.float64)
        jac = [np.asarray(pb.residual_and_jacobian(pb.transform.to_unconstrained(
            {n: p[n] for n in pb.transform.names}))[1], np.float64) for p in pts]
        made.append((pb, r0, jac))
        say(f"{labels[i]}: residual and {len(pts)} Jacobians at dx = {pb.dx:.4g} m")
    made_shift = []
    if dx_check:
        for i, (pb, r0, jac) in enumerate(made):
            zg = pb.transform.to_unconstrained({n: guess[n] for n in pb.transform.names})
            made_shift.append(_grid_shift(pb, build_problem(with_data[i], finer_settings(pb, settings)), zg, jac[0], r0))
            say(f"{labels[i]}: grid check at dx = {pb.dx * DX_CHECK_RATIO:.4g} m")
    with_only = None
    if made:
        tr = made[0][0].transform
        z0 = np.asarray(tr.to_unconstrained({n: guess[n] for n in tr.names}), np.float64)
        joint = JointProblem([pb for pb, _, _ in made], settings)
        parts = [(r0, jac[0]) for _, r0, jac in made]
        joint.set_scales(noise_scales(joint, parts))
        unc = joint_uncertainty(joint, parts, z0, settings.level)
        with_only = {n: [float(v) for v in unc.interval[k]] for k, n in enumerate(joint.names)}
        made_rms = float(np.median([_rms(r0, joint.n_effective(i, r0)) for i, (r0, _) in enumerate(parts)]))

    groups: dict[str, list] = {}
    for c in candidates:
        groups.setdefault(_structure(c["scene"], c["recording"]), []).append(c)
    for gi, members in enumerate(groups.values()):
        for c in members:
            c.update(done.get(_key(c), {}))
        if all("score" in c for c in members):
            continue
        template = max(members, key=lambda c: load_scene(c["scene"]).max_plate_speed())
        base = build_problem(_layout(template["scene"], template["recording"], settings, dtype), settings)
        if sampling == "other":
            other = dataclasses.replace(settings, seed=settings.seed + 1)
            source = build_problem(_layout(template["scene"], template["recording"], other, dtype), other)
        else:
            source = base
        fine = None
        if dx_check:
            same_pixels = dict(template["recording"], pixel_size=float(base.data.camera.pixel_size))
            fine = build_problem(_layout(template["scene"], same_pixels, finer_settings(base, settings), dtype),
                                 finer_settings(base, settings))
        say(f"group {gi + 1}/{len(groups)}: {len(members)} candidate(s) on one compiled rollout (dx = {base.dx:.4g} m, "
            f"{int(np.sum(base.sim.state0.active))} particles, {len(base.frames)} frames)")
        for c in members:
            if "score" in c:
                continue
            t0 = time.perf_counter()
            scene_c = load_scene(c["scene"], dtype=dtype)
            pb_c = base.with_scene(scene_c)
            src_c = pb_c if source is base else source.with_scene(scene_c)
            per_point, reported, share, err_z = [], [], None, None
            for k, (p, pf) in enumerate(zip(pts, full)):
                data = _render(src_c, pf, c["scene"], fit_grid(scene_c, settings)[1], [settings.seed, gi, candidates.index(c), k])
                pb = pb_c.with_observations(data)
                z = pb.transform.to_unconstrained({n: p[n] for n in pb.transform.names})
                r, J = (np.asarray(a, np.float64) for a in pb.residual_and_jacobian(z))
                if fine is not None and k == 0:
                    shift_c = _grid_shift(pb, fine.with_scene(scene_c).with_observations(data), z, J, r)
                joint = JointProblem([pb] + [m[0] for m in made], settings)
                if misfit == "with":
                    own = _rms(r, joint.n_effective(0, r))
                    r = r * (made_rms / own) if 0.0 < own < made_rms else r
                parts = [(r, J)] + [(r0, jac[k]) for _, r0, jac in made]
                joint.set_scales(noise_scales(joint, parts))
                unc = joint_uncertainty(joint, parts, np.asarray(z, np.float64), settings.level)
                per_point.append({n: [float(v) for v in unc.interval[j]] for j, n in enumerate(joint.names)})
                if fine is not None:
                    if k == 0:
                        err_z = joint_grid_error(joint, parts, [shift_c] + made_shift)
                    reported.append(_intervals(unc, err_z, joint.transform, joint.names))
                if k == 0:
                    sh = information_shares(joint, parts)
                    share = {n: [float(v) for v in sh[:, j]] for j, n in enumerate(joint.names)}
            hws = [half_widths(iv, p) for iv, p in zip(reported or per_point, pts)]
            agg = {n: float(np.max([h[n] for h in hws]) if robust == "worst" else np.mean([h[n] for h in hws]))
                   for n in names}
            ratio = _tolerance_ratio(agg)
            if fine is not None:
                c.update(predicted_reported=reported,
                         numerical_error_z={n: float(v) for n, v in zip(names, err_z)})
            c.update(predicted=per_point, half_width=agg, within=[n for n in names if ratio[n] <= 1.0],
                     score=float(np.exp(np.mean(np.log(np.maximum([ratio[n] for n in names], 1e-300))))),
                     information_share=share, wall_time=time.perf_counter() - t0)
            if log is not None:
                done[_key(c)] = {k: c[k] for k in _RESULT_KEYS + (_CHECK_KEYS if fine is not None else ())}
                _write_log(log, fingerprint, done)
            say(f"  {c['values']}: " + ", ".join(f"{n} +-{_fmt_hw(n, agg[n])}" for n in names)
                + f" ({c['wall_time']:.1f} s)")
    candidates.sort(key=lambda c: (-len(c["within"]), c["score"] if math.isfinite(c["score"]) else math.inf))
    with_hw = None if with_only is None else half_widths(with_only, guess)
    advice = _advice(candidates[0], names, with_hw, labels)
    out_settings = dict(settings.to_dict(), points=points, spread=spread, duration=duration, fps=fps,
                        pixel_size=pixel_size, noise=DESIGN_NOISE, sampling=sampling, misfit=misfit, with_data=labels,
                        dx_check=bool(dx_check))
    return DesignResult(guess=guess, points=pts, variables={v.name: list(v.values) for v in variables}, robust=robust,
                        candidates=candidates, with_only=with_only, advice=advice,
                        wall_time=time.perf_counter() - wall0, settings=out_settings)


_RESULT_KEYS = ("predicted", "half_width", "within", "score", "information_share", "wall_time")
_CHECK_KEYS = ("predicted_reported", "numerical_error_z")


def _grid_shift(problem, other, z, J, r) -> np.ndarray:
    """The first-order move (p,) of the estimate z from problem's grid to other's (the larger of
    `predicted_move`'s two estimates per parameter, with its sign; inf where not finite)."""
    with_fit, with_own, _ = predicted_move(problem, other, np.asarray(z, np.float64), J, r)
    if with_fit is None:
        return np.full(np.shape(J)[1], np.inf)
    return check_error([with_fit, with_own], DX_CHECK_RATIO)[1]


def _intervals(unc, err_z, transform, names) -> dict:
    """name -> [lo, hi]: the statistical interval and err_z combined as the fit reports them."""
    return {n: [float(v) for v in row] for n, row in zip(names, combine_intervals(unc, err_z, transform))}


def _key(candidate: dict) -> str:
    return json.dumps(candidate["values"], sort_keys=True)


def _read_log(path, fingerprint: str) -> dict:
    """The candidates' results in a design log (empty when there is none)."""
    path = Path(path)
    if not path.exists():
        return {}
    try:
        log = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise CalibrationError(f"design log {str(path)!r}: not readable as JSON ({exc})") from exc
    if log.get("format") != "jaxfoam-design-log" or log.get("fingerprint") != fingerprint:
        raise CalibrationError(f"design log {str(path)!r} was written by another design (scene, guess, variables, "
                               f"settings or recordings differ); remove it or run without resume")
    return dict(log["candidates"])


def _write_log(path, fingerprint: str, done: dict) -> None:
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(dict(format="jaxfoam-design-log", fingerprint=fingerprint, candidates=done),
                                        allow_nan=True))


