"""The optimizer protocol shared by Adam, L-BFGS and Levenberg-Marquardt.

An optimizer is a small frozen configuration object with three methods:

* ``init(fn, x0) -> state``: evaluates the oracle once at x0 and builds the state pytree;
* ``step(fn, x, state) -> (x, state)``: one accepted iteration (it may evaluate several trial points;
  a trial whose value is not finite is rejected and the step shrunk, never accepted);
* ``terminate(state) -> (done, reason)``: method-specific stops (a failed search, no finite trial).

The oracle ``fn`` is supplied by the driver (`fitting.optim.minimize`, `fitting.optim.least_squares`):

* ``kind == "minimize"``: ``fn(x) -> (loss, grad)``, a scalar and a (p,) array;
* ``kind == "least_squares"``: ``fn(x) -> (r, J)``, residuals (n,) and their Jacobian (n, p).

The driver guarantees that a non-finite evaluation comes back as ``loss = +inf`` (or ``r`` filled with
+inf), so every comparison an optimizer makes treats it as worse than any finite point.

Every state is a frozen dataclass registered as a pytree whose fields are arrays, including ``loss``
(scalar), ``grad`` ((p,), gradient of the loss at the current x) and ``status`` (an integer
`fitting.optim.Reason` code), so the driver can apply the common tolerances and a fit log can store it.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from ._solution import Reason, reason_code, reason_from_code

RUNNING = reason_code(Reason.RUNNING)


class AbstractOptimizer:
    """Base class: subclasses set `kind`, `State` and implement `init` and `step`."""

    kind: str = "minimize"
    State: type = None

    def init(self, fn, x0):
        raise NotImplementedError

    def step(self, fn, x, state):
        raise NotImplementedError

    def terminate(self, state):
        """(done, reason): done when the state's status is anything but RUNNING."""
        reason = reason_from_code(state.status)
        return reason != Reason.RUNNING, (None if reason == Reason.RUNNING else reason)

    def config(self) -> dict:
        """The hyper-parameters, as a JSON-able dict (a fit log checks them on resume)."""
        return {"name": type(self).__name__, **dataclasses.asdict(self)}


def state_arrays(state) -> dict:
    """The state's fields as a dict of numpy arrays (field name -> array)."""
    return {f.name: np.asarray(getattr(state, f.name)) for f in dataclasses.fields(state)}


def state_from_arrays(state_type, arrays: dict):
    """Rebuild a state of `state_type` from `state_arrays` output (numpy arrays, dtypes kept)."""
    fields = dataclasses.fields(state_type)
    # a field added with a default since the log was written takes its default
    names = [f.name for f in fields if f.name in arrays or f.default_factory is dataclasses.MISSING]
    missing = set(names) - set(arrays)
    if missing:
        raise ValueError(f"cannot rebuild {state_type.__name__}: fields {sorted(missing)} are missing")
    return state_type(**{n: np.asarray(arrays[n]) for n in names})


def as_array(v):
    """v as an array (jax arrays and numpy arrays pass through unchanged)."""
    return v if isinstance(v, (jax.Array, np.ndarray)) else np.asarray(v)


def host(v, dtype=None):
    """A numpy array: host-side values (counters, step lengths, trial points) stay on the host, where
    building them costs no XLA dispatch; jitted functions accept them like jax arrays."""
    return np.asarray(v, dtype=dtype)


def scalar(x) -> float:
    """A host float from a scalar array."""
    return float(np.asarray(x))


def is_finite_number(v: float) -> bool:
    return math.isfinite(v)


def check_positive(name: str, value, strict: bool = True):
    """Raise ValueError naming a hyper-parameter that must be positive (or >= 0 when not strict)."""
    if not (value > 0 if strict else value >= 0) or not math.isfinite(value):
        raise ValueError(f"{name} must be {'> 0' if strict else '>= 0'} and finite, got {value!r}")


def check_unit_interval(name: str, value, closed_left=True):
    ok = (0.0 <= value < 1.0) if closed_left else (0.0 < value < 1.0)
    if not ok:
        raise ValueError(f"{name} must be in {'[0, 1)' if closed_left else '(0, 1)'}, got {value!r}")
