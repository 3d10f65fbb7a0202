"""Helpers shared by the test files: a scene-edit helper, one central-difference helper and a zoo of
small scenes."""
import copy

import numpy as np


def edited(spec: dict, path, value=None, delete: bool = False) -> dict:
    """A deep copy of the scene description `spec` with the entry at `path` (keys / indices) set to
    `value`, or deleted."""
    spec = copy.deepcopy(spec)
    node = spec
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return spec


def central_difference(f, x, direction=None, h=1e-6, order=2):
    """The central-difference derivative of f at x along `direction` (along x itself, elementwise,
    when None), as a numpy value of f's shape:
    order 2: (f(x + h d) - f(x - h d)) / (2 h);
    order 4: (-f(x + 2 h d) + 8 f(x + h d) - 8 f(x - h d) + f(x - 2 h d)) / (12 h).
    x: a scalar or an array; h: a scalar, or without a direction an array broadcasting with x (one
    step per component); f: returns a scalar or an array (jax or numpy)."""
    step = h if direction is None else h * direction
    at = lambda s: np.asarray(f(x + s))
    if order == 2:
        return (at(step) - at(-step)) / (2 * h)
    if order == 4:
        return (-at(2 * step) + 8 * at(step) - 8 * at(-step) + at(-2 * step)) / (12 * h)
    raise ValueError(f"order must be 2 or 4, got {order!r}")


# The zoo: small scenes, SI units (hundreds of particles at dx = 0.01 m in 2D and 0.02 m in 3D, default
# ppc). Those named after tests are the dicts the tests defined inline, so the tests keep their numbers;
# the 3D hanging plate and slump add a z extent to the 2D cross-section.
_ZOO = {
    # a 10 x 9.5 cm box under a 1 cm sticky board that oscillates sideways (test_validation, test_io)
    ("hanging_plate", 2): {
        "kind": "hanging_plate", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 2000.0,
        "domain": {"min": [-0.15, 0.0], "max": [0.15, 0.35]},
        "floor": {"y": 0.0, "friction": 0.5},
        "plate": {"center": [0.0, 0.30], "half_size": [0.08, 0.005],
                  "motion": {"type": "sinusoid", "axis": [1.0, 0.0], "amplitude": 0.01, "frequency": 3.0,
                             "phase": 0.0, "ramp_time": 0.3},
                  "sticky": True},
        "initial_shape": {"type": "box", "min": [-0.05, 0.2], "max": [0.05, 0.295]},
    },
    ("hanging_plate", 3): {
        "kind": "hanging_plate", "dim": 3, "gravity": [0.0, -9.81, 0.0], "density": 80.0, "kappa": 2000.0,
        "domain": {"min": [-0.15, 0.0, -0.08], "max": [0.15, 0.35, 0.08]},
        "floor": {"y": 0.0, "friction": 0.5},
        "plate": {"center": [0.0, 0.30, 0.0], "half_size": [0.08, 0.005, 0.05],
                  "motion": {"type": "sinusoid", "axis": [1.0, 0.0, 0.0], "amplitude": 0.01, "frequency": 3.0,
                             "phase": 0.0, "ramp_time": 0.3},
                  "sticky": True},
        "initial_shape": {"type": "box", "min": [-0.05, 0.2, -0.03], "max": [0.05, 0.295, 0.03]},
    },
    # a 10 cm cube of foam 10 cm above a Coulomb floor (test_collider_selects, test_floor_contact)
    ("drop", 2): {
        "kind": "drop", "dim": 2, "density": 80.0, "kappa": 2000.0, "gravity": [0.0, -9.81],
        "domain": {"min": [0.0, 0.0], "max": [0.3, 0.3]},
        "floor": {"y": 0.0, "friction": 0.5},
        "initial_shape": {"type": "box", "min": [0.1, 0.1], "max": [0.2, 0.2]},
    },
    ("drop", 3): {
        "kind": "drop", "dim": 3, "density": 80.0, "kappa": 2000.0, "gravity": [0.0, -9.81, 0.0],
        "domain": {"min": [0.0, 0.0, 0.0], "max": [0.3, 0.3, 0.3]},
        "floor": {"y": 0.0, "friction": 0.5},
        "initial_shape": {"type": "box", "min": [0.1, 0.1, 0.1], "max": [0.2, 0.2, 0.2]},
    },
    # an 8 x 6.2 cm block on a sticky floor squeezed by a sticky plate, held, pulled up
    # (experiments/scenes/squeeze_2d.json and squeeze_3d.json)
    ("squeeze", 2): {
        "kind": "squeeze", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 3000.0,
        "domain": {"min": [-0.15, 0.0], "max": [0.15, 0.2]},
        "floor": {"y": 0.0, "friction": "sticky"},
        "plates": [{"center": [0.0, 0.075], "half_size": [0.1, 0.0125],
                    "motion": {"type": "samples", "times": [0.0, 0.5, 0.8, 1.4],
                               "positions": [[0.0, 0.075], [0.0, 0.044], [0.0, 0.044], [0.0, 0.15]]},
                    "sticky": True}],
        "initial_shape": {"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.062]},
    },
    ("squeeze", 3): {
        "kind": "squeeze", "dim": 3, "gravity": [0.0, -9.81, 0.0], "density": 80.0, "kappa": 3000.0,
        "domain": {"min": [-0.12, 0.0, -0.12], "max": [0.12, 0.2, 0.12]},
        "floor": {"y": 0.0, "friction": "sticky"},
        "plates": [{"center": [0.0, 0.075, 0.0], "half_size": [0.1, 0.0125, 0.1],
                    "motion": {"type": "samples", "times": [0.0, 0.5, 0.8, 1.4],
                               "positions": [[0.0, 0.075, 0.0], [0.0, 0.044, 0.0], [0.0, 0.044, 0.0],
                                             [0.0, 0.15, 0.0]]},
                    "sticky": True}],
        "initial_shape": {"type": "box", "min": [-0.04, 0.0, -0.04], "max": [0.04, 0.062, 0.04]},
    },
    # an 8 x 6 cm block slumping on a Coulomb floor (test_fit_features, test_model_choice)
    ("slump", 2): {
        "kind": "drop", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 3000.0,
        "domain": {"min": [-0.12, 0.0], "max": [0.12, 0.12]}, "floor": {"y": 0.0, "friction": 0.5},
        "initial_shape": {"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.06]},
    },
    ("slump", 3): {
        "kind": "drop", "dim": 3, "gravity": [0.0, -9.81, 0.0], "density": 80.0, "kappa": 3000.0,
        "domain": {"min": [-0.12, 0.0, -0.12], "max": [0.12, 0.12, 0.12]}, "floor": {"y": 0.0, "friction": 0.5},
        "initial_shape": {"type": "box", "min": [-0.04, 0.0, -0.04], "max": [0.04, 0.06, 0.04]},
    },
}
ZOO_NAMES = ("hanging_plate", "drop", "squeeze", "slump")


def scene(name: str, dim: int = 2, **overrides) -> dict:
    """A fresh copy of the zoo's scene dict `name` (one of ZOO_NAMES) in `dim` = 2 or 3 dimensions,
    with the top-level entries in `overrides` replaced (e.g. floor={...}, initial_shape={...})."""
    if (name, dim) not in _ZOO:
        raise KeyError(f"no zoo scene {name!r} in {dim}D; there are {ZOO_NAMES} in 2D and 3D")
    spec = copy.deepcopy(_ZOO[name, dim])
    spec.update(copy.deepcopy(overrides))
    return spec


def counted(fn):
    """fn wrapped to count its calls: (wrapped, calls), calls[0] the count so far."""
    calls = [0]

    def wrapped(x):
        calls[0] += 1
        return fn(x)

    return wrapped, calls
