"""Material parameters: the quantities a fit may differentiate."""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

# Admissible range of the Herschel-Bulkley exponent m: 0 is singular (infinite thinning); above 5 the
# flow rule is so stiff in gamma that nothing measured on foams comes near (foams have m ~ 0.3-1).
M_RANGE = (0.0, 5.0)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Params:
    """Herschel-Bulkley foam parameters (all leaves are scalars or arrays; SI units).

    Attributes:
      mu: shear modulus, Pa (> 0).
      kappa: bulk modulus, Pa (> 0).
      sigma_y: yield stress, Pa (>= 0).
      eta: Herschel-Bulkley consistency, Pa s^m (>= 0; 0 gives rate-independent plasticity).
      m: Herschel-Bulkley exponent, dimensionless, in (0, 5] (< 1 shear thinning).
      rho: density, kg/m^3 (> 0).
    """

    mu: jax.Array | float
    kappa: jax.Array | float
    sigma_y: jax.Array | float
    eta: jax.Array | float
    m: jax.Array | float
    rho: jax.Array | float

    def validate(self) -> "Params":
        """Raise ValueError naming the field and its allowed range; return self when valid.

        Concrete values are checked, and so are the primal values of tracers that have them (jax.grad,
        jax.jvp, jax.jacfwd outside jit); abstract values inside jit or vmap pass through.
        """
        rules = {
            "mu": ("> 0 Pa", lambda v: v > 0),
            "kappa": ("> 0 Pa", lambda v: v > 0),
            "sigma_y": (">= 0 Pa", lambda v: v >= 0),
            "eta": (">= 0 Pa s^m", lambda v: v >= 0),
            "m": ("in (0, 5]", lambda v: M_RANGE[0] < v <= M_RANGE[1]),
            "rho": ("> 0 kg/m^3", lambda v: v > 0),
        }
        for name, (rng, ok) in rules.items():
            value = getattr(self, name)
            if isinstance(value, jax.core.Tracer):
                try:
                    value = np.asarray(jax.lax.stop_gradient(value))
                except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError, TypeError):
                    continue
            try:
                # numpy, not jnp: inside a jit trace jnp would stage even a Python float.
                flat = [float(x) for x in np.ravel(np.asarray(value, dtype=np.float64))]
            except (TypeError, ValueError) as exc:
                raise ValueError(f"Params.{name} must be a real number ({rng}), got {value!r}") from exc
            for x in flat:
                if not math.isfinite(x):
                    raise ValueError(f"Params.{name} must be finite ({rng}), got {x}")
                if not ok(x):
                    raise ValueError(f"Params.{name} must be {rng}, got {x}")
        return self

    def astype(self, dtype) -> "Params":
        """The same parameters as arrays of `dtype`."""
        return jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), self)

    def replace(self, **changes) -> "Params":
        return dataclasses.replace(self, **changes)


FIT_FIELDS = ("mu", "sigma_y", "eta", "m")
