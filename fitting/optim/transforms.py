"""Fitted (unconstrained) coordinates z <-> physical parameters theta, one monotone map per parameter.

Kinds (lo, hi are the user's bounds, in the parameter's physical unit):

* ``identity``: theta = z (unbounded).
* ``log``: theta = exp(z), theta > 0 (moduli, yield stress, consistency). A step in z is a relative
  change of theta, so parameters of different magnitudes are comparable.
* ``bounded``: theta = lo + (hi - lo) * sigmoid(z), lo <= theta <= hi (the exponent m).
* ``log_bounded``: log theta = log lo + (log hi - log lo) * sigmoid(z), 0 < lo <= theta <= hi (a positive
  parameter with bounds spanning decades).
* ``lower``: theta = lo + exp(z) > lo.   ``upper``: theta = hi - exp(z) < hi.

The maps are elementwise, so the Jacobian d theta / d z is diagonal; `jacobian` returns that diagonal,
used to carry a covariance from z to theta (delta method). The bounded maps are clipped to [lo, hi], so
even a saturated sigmoid (|z| > ~37 in float64) stays inside the closed interval.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

KINDS = ("identity", "log", "bounded", "log_bounded", "lower", "upper")
# How each kind names its fitted coordinate (for reports).
_COORD_NAMES = {"identity": "{}", "log": "log({})", "bounded": "logit({})", "log_bounded": "logit-log({})",
                "lower": "log({} - lo)", "upper": "log(hi - {})"}


def _forward_one(kind, lo, hi, z):
    """theta(z) for one parameter (traceable)."""
    if kind == "identity":
        return z
    if kind == "log":
        return jnp.exp(z)
    if kind == "bounded":
        return jnp.clip(lo + (hi - lo) * jax.nn.sigmoid(z), lo, hi)
    if kind == "log_bounded":
        llo, lhi = math.log(lo), math.log(hi)
        return jnp.clip(jnp.exp(llo + (lhi - llo) * jax.nn.sigmoid(z)), lo, hi)
    if kind == "lower":
        return lo + jnp.exp(z)
    return hi - jnp.exp(z)  # upper


def _inverse_one(kind, lo, hi, theta):
    """z(theta) for one parameter (theta strictly inside the domain)."""
    if kind == "identity":
        return theta
    if kind == "log":
        return jnp.log(theta)
    if kind == "bounded":
        t = (theta - lo) / (hi - lo)
        return jnp.log(t) - jnp.log1p(-t)
    if kind == "log_bounded":
        llo, lhi = math.log(lo), math.log(hi)
        t = (jnp.log(theta) - llo) / (lhi - llo)
        return jnp.log(t) - jnp.log1p(-t)
    if kind == "lower":
        return jnp.log(theta - lo)
    return jnp.log(hi - theta)  # upper


def _derivative_one(kind, lo, hi, z):
    """d theta / d z for one parameter (traceable)."""
    if kind == "identity":
        return jnp.ones_like(z)
    if kind in ("log", "lower"):
        return jnp.exp(z)
    if kind == "upper":
        return -jnp.exp(z)
    s = jax.nn.sigmoid(z)
    if kind == "bounded":
        return (hi - lo) * s * (1 - s)
    llo, lhi = math.log(lo), math.log(hi)
    return jnp.exp(llo + (lhi - llo) * s) * (lhi - llo) * s * (1 - s)  # log_bounded


def _domain_ok(kind, lo, hi, v):
    if not math.isfinite(v):
        return False
    if kind == "identity":
        return True
    if kind == "log":
        return v > 0
    if kind == "lower":
        return v > lo
    if kind == "upper":
        return v < hi
    return lo < v < hi


@dataclasses.dataclass(frozen=True)
class ParameterTransform:
    """Per-parameter maps between fitted coordinates z (p,) and physical values theta (p,).

    Attributes:
      names: parameter names, in vector order.
      kinds: one of KINDS per parameter.
      lower, upper: bounds per parameter in physical units (-inf / +inf where the kind has none).
    """

    names: tuple
    kinds: tuple
    lower: tuple
    upper: tuple

    def __post_init__(self):
        p = len(self.names)
        if not (len(self.kinds) == len(self.lower) == len(self.upper) == p) or p == 0:
            raise ValueError("ParameterTransform: names, kinds, lower and upper must have the same length >= 1")
        if len(set(self.names)) != p:
            raise ValueError(f"ParameterTransform: duplicate parameter names in {self.names}")
        for name, kind, lo, hi in zip(self.names, self.kinds, self.lower, self.upper):
            if kind not in KINDS:
                raise ValueError(f"transform of {name!r}: kind must be one of {KINDS}, got {kind!r}")
            if kind in ("bounded", "log_bounded"):
                if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                    raise ValueError(f"bounds of {name!r}: need finite lo < hi, got [{lo}, {hi}]")
                if kind == "log_bounded" and not lo > 0:
                    raise ValueError(f"bounds of {name!r}: a positive (log) parameter needs lo > 0, got {lo}")
            if kind == "lower" and not math.isfinite(lo):
                raise ValueError(f"bounds of {name!r}: kind 'lower' needs a finite lo, got {lo}")
            if kind == "upper" and not math.isfinite(hi):
                raise ValueError(f"bounds of {name!r}: kind 'upper' needs a finite hi, got {hi}")

    @classmethod
    def create(cls, names: Sequence[str], *, positive: Sequence[str] = (),
               bounds: Mapping[str, tuple] | None = None, kinds: Mapping[str, str] | None = None):
        """Choose each parameter's map from what is known about it.

        Args:
          names: parameter names in vector order, e.g. ("mu", "sigma_y", "eta", "m").
          positive: names that must stay > 0 (get `log`, or `log_bounded` with bounds lo > 0).
          bounds: name -> (lo, hi) in physical units; None or +-inf for an open side.
          kinds: name -> kind, overriding the automatic choice.

        Automatic choice: two finite bounds -> `log_bounded` if positive and lo > 0, else `bounded`;
        one finite bound -> `lower` / `upper` (`log` if positive with lo <= 0 and no hi); positive with
        no bounds -> `log`; otherwise `identity`.
        """
        names = tuple(names)
        bounds = dict(bounds or {})
        kinds = dict(kinds or {})
        unknown = (set(bounds) | set(kinds) | set(positive)) - set(names)
        if unknown:
            raise ValueError(f"transform: unknown parameter names {sorted(unknown)}; parameters are {names}")
        out_kinds, lows, highs = [], [], []
        for name in names:
            lo, hi = bounds.get(name, (None, None))
            lo = -math.inf if lo is None else float(lo)
            hi = math.inf if hi is None else float(hi)
            if lo >= hi:
                raise ValueError(f"bounds of {name!r}: need lo < hi, got [{lo}, {hi}]")
            pos = name in positive
            if pos and hi <= 0:
                raise ValueError(f"bounds of {name!r}: a positive parameter needs hi > 0, got {hi}")
            if name in kinds:
                kind = kinds[name]
            elif math.isfinite(lo) and math.isfinite(hi):
                kind = "log_bounded" if pos and lo > 0 else "bounded"
            elif pos and (not math.isfinite(lo) or lo <= 0) and not math.isfinite(hi):
                kind, lo = "log", 0.0
            elif math.isfinite(lo):
                kind = "lower"
            elif math.isfinite(hi):
                kind = "upper"
            else:
                kind = "identity"
            if kind == "log":
                lo = 0.0
            out_kinds.append(kind)
            lows.append(lo)
            highs.append(hi)
        return cls(names, tuple(out_kinds), tuple(lows), tuple(highs))

    @property
    def size(self) -> int:
        return len(self.names)

    def coordinate_names(self) -> list[str]:
        """How each fitted coordinate is written (e.g. "log(mu)", "logit(m)")."""
        return [_COORD_NAMES[k].format(n) for n, k in zip(self.names, self.kinds)]

    def vector(self, theta) -> np.ndarray:
        """A (p,) float64 array from a mapping name -> value or a sequence in `names` order."""
        if isinstance(theta, Mapping):
            missing = [n for n in self.names if n not in theta]
            if missing:
                raise ValueError(f"values missing for parameters {missing}")
            theta = [theta[n] for n in self.names]
        theta = np.asarray(theta, np.float64)
        if theta.shape != (self.size,):
            raise ValueError(f"expected {self.size} parameter values {self.names}, got shape {theta.shape}")
        return theta

    def as_dict(self, theta) -> dict:
        """name -> float."""
        return {n: float(v) for n, v in zip(self.names, np.asarray(theta))}

    def to_physical(self, z):
        """theta (p,) from z (p,); traceable, so an objective can call it inside jit."""
        return _to_physical(self, jnp.asarray(z))

    def to_unconstrained(self, theta):
        """z (p,) from theta (p,) or a dict; ValueError naming a value outside the open domain."""
        theta = self.vector(theta)
        for name, kind, lo, hi, v in zip(self.names, self.kinds, self.lower, self.upper, theta):
            if not _domain_ok(kind, lo, hi, float(v)):
                raise ValueError(f"{name}={float(v)!r} is outside the domain of its {kind} transform "
                                 f"(bounds [{lo}, {hi}], open at finite ends)")
        return _to_unconstrained(self, jnp.asarray(theta))

    def jacobian(self, z):
        """Diagonal of d theta / d z at z, (p,) (physical units per unit of z)."""
        return _jacobian(self, jnp.asarray(z))

    def from_unit(self, u, sample_bounds: Mapping[str, tuple] | None = None) -> np.ndarray:
        """Physical values from points u (..., p) of the unit cube (for Latin-hypercube starts).

        Uniform between the bounds for `identity`/`bounded`/`lower`/`upper`, uniform in log for
        `log`/`log_bounded`. `sample_bounds` (name -> (lo, hi)) overrides or supplies the range, and is
        required for a parameter without two finite bounds.
        """
        u = np.asarray(u, np.float64)
        if u.shape[-1] != self.size:
            raise ValueError(f"unit points need last axis {self.size}, got shape {u.shape}")
        if np.any((u < 0) | (u > 1)):
            raise ValueError("unit points must lie in [0, 1]")
        sample_bounds = dict(sample_bounds or {})
        out = np.empty_like(u)
        for i, (name, kind, lo, hi) in enumerate(zip(self.names, self.kinds, self.lower, self.upper)):
            slo, shi = sample_bounds.get(name, (lo, hi))
            slo, shi = float(slo), float(shi)
            if not (math.isfinite(slo) and math.isfinite(shi) and slo < shi):
                raise ValueError(f"starting-point range of {name!r}: need finite lo < hi (give sample_bounds), "
                                 f"got [{slo}, {shi}]")
            if kind in ("log", "log_bounded"):
                if slo <= 0:
                    raise ValueError(f"starting-point range of {name!r}: a log parameter needs lo > 0, got {slo}")
                out[..., i] = np.exp(np.log(slo) + u[..., i] * (np.log(shi) - np.log(slo)))
            else:
                out[..., i] = slo + u[..., i] * (shi - slo)
        return out


# The maps, jitted once per transform (a frozen dataclass of tuples, hence hashable and static).
@functools.partial(jax.jit, static_argnums=0)
def _to_physical(tr: ParameterTransform, z):
    return jnp.stack([_forward_one(k, lo, hi, z[i]) for i, (k, lo, hi) in enumerate(zip(tr.kinds, tr.lower, tr.upper))])


@functools.partial(jax.jit, static_argnums=0)
def _to_unconstrained(tr: ParameterTransform, theta):
    return jnp.stack([_inverse_one(k, lo, hi, theta[i])
                      for i, (k, lo, hi) in enumerate(zip(tr.kinds, tr.lower, tr.upper))])


@functools.partial(jax.jit, static_argnums=0)
def _jacobian(tr: ParameterTransform, z):
    return jnp.stack([_derivative_one(k, lo, hi, z[i]) for i, (k, lo, hi) in enumerate(zip(tr.kinds, tr.lower, tr.upper))])
