"""Parameter uncertainty from the Gauss-Newton Hessian at a least-squares optimum.

Model and assumptions (state them with any number this produces):

* residuals r_i = (model_i(z) - data_i) / w_i are independent, zero-mean, with a common variance
  sigma^2, and the model is close to linear in z over the uncertainty region;
* sigma^2 is estimated as s^2 = |r|^2 / (n - p) (n residuals, p parameters);
* the covariance of the fitted coordinates z is Cov_z = c * s^2 (J^T J)^-1, J = dr/dz (n, p), with
  c = n / n_eff. Silhouette pixels are not independent (neighbouring pixels share the same boundary
  error), so an image carries fewer independent observations than pixels: pass n_eff, the effective
  number of independent residuals (e.g. n / (pixels per correlation area)), to inflate the covariance;
  n_eff = n (the default) assumes independence and gives the narrowest intervals;
* intervals are z_j +- t_q sigma_zj with t_q the Student-t quantile at n_eff - p degrees of freedom,
  mapped to physical units through each parameter's monotone map, so a log parameter's interval is
  positive and a bounded one stays inside its bounds (the interval is not symmetric in physical units);
* the physical covariance is the delta method, Cov_theta = D Cov_z D with D = diag(d theta / d z).

A direction in which J^T J is (nearly) singular is one the data do not determine: the parameters that
make it up trade off. The report names them in plain words.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from .transforms import ParameterTransform

# Defaults of the report (all dimensionless).
DEFAULT_LEVEL = 0.95
# A parameter whose interval is wider than this multiple of its value is reported as not identifiable
# (1.0: the interval spans more than the value itself, e.g. [0.3, 1.4] around 0.7).
DEFAULT_MAX_RELATIVE_WIDTH = 1.0
# Directions of the diagonally scaled J^T J with eigenvalue below this fraction of the largest are called
# near-singular (for two parameters this is |correlation| > ~0.998).
DEFAULT_SINGULAR_RATIO = 1e-3
# Pairs at least this correlated are reported as trading off.
DEFAULT_CORRELATION_THRESHOLD = 0.95
# Eigenvalues below this fraction of the largest are treated as exactly zero (infinite variance).
DEFAULT_RCOND = 1e-12
# A component of a near-singular eigenvector at least this large (unit vector) names its parameter.
_COMPONENT_MIN = 0.3


def _betainc(a: float, b: float, x: float) -> float:
    """Regularized incomplete beta I_x(a, b) by its continued fraction (DLMF 8.17.22), modified Lentz."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    if x > (a + 1.0) / (a + b + 2.0):  # the fraction converges fast below the mean; use the symmetry
        return 1.0 - _betainc(b, a, 1.0 - x)
    log_front = a * math.log(x) + b * math.log1p(-x) - math.log(a) - (
        math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b))
    # K = 1 / (1 + d1 / (1 + d2 / (1 + ...))) as b0 + a1/(b1 + a2/(b2 + ...)) with b0 = 0, b_j = 1,
    # a_1 = 1, a_j = d_{j-1}:  d_{2m} = m (b - m) x / ((a + 2m - 1)(a + 2m)),
    # d_{2m+1} = -(a + m)(a + b + m) x / ((a + 2m)(a + 2m + 1)).
    tiny, tol = 1e-300, 1e-15
    f, c, d = tiny, tiny, 0.0
    for j in range(1, 4000):
        k = j - 1
        if k == 0:
            num = 1.0
        elif k % 2 == 0:
            m = k // 2
            num = m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m))
        else:
            m = (k - 1) // 2
            num = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))
        d = 1.0 + num * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + num / c
        c = c if abs(c) > tiny else tiny
        f *= c * d
        if abs(c * d - 1.0) < tol:
            break
    return math.exp(log_front) * f


@functools.lru_cache(maxsize=256)
def student_t_quantile(prob: float, dof: float) -> float:
    """Quantile t with P(T <= t) = prob for Student's t with `dof` degrees of freedom (prob in (0.5, 1)).

    Bisection, to relative 1e-12, on the CDF 1 - 0.5 I_{dof/(dof+t^2)}(dof/2, 1/2).
    """
    if not 0.5 < prob < 1.0:
        raise ValueError(f"prob must be in (0.5, 1), got {prob!r}")
    if not dof > 0:
        raise ValueError(f"degrees of freedom must be > 0, got {dof!r}")

    def cdf(t):
        return 1.0 - 0.5 * _betainc(dof / 2.0, 0.5, dof / (dof + t * t))

    lo, hi = 0.0, 1.0
    while cdf(hi) < prob:
        lo, hi = hi, 2.0 * hi
    while hi - lo > 1e-12 * hi:
        mid = 0.5 * (lo + hi)
        if cdf(mid) < prob:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@dataclasses.dataclass(frozen=True)
class Uncertainty:
    """Covariance, intervals and identifiability of a least-squares fit (p parameters).

    Attributes:
      names: parameter names.  coordinates: how each fitted coordinate is written ("log(mu)").
      z: (p,) fitted coordinates at the optimum.  theta: (p,) physical values.
      cov_z: (p, p) covariance of z.  cov_theta: (p, p) delta-method covariance in physical units.
      stderr_theta: (p,) sqrt(diag(cov_theta)), physical units (local, symmetric).
      interval: (p, 2) physical `level` interval (mapped from z; asymmetric for log/bounded parameters).
      interval_z: (p, 2) the interval in fitted coordinates.
      correlation: (p, p) correlation matrix (the same in z and theta: the maps are diagonal).
      level: confidence level.  quantile: the Student-t quantile used.
      s2: residual variance estimate |r|^2 / (n - p).  n: residuals.  n_eff: effective independent ones.
      eigenvalues: (p,) ascending eigenvalues of the diagonally scaled J^T J (largest = 1 after scaling by it).
      eigenvectors: (p, p) matching unit eigenvectors (columns), in scaled fitted coordinates.
      non_identifiable: names of parameters the data do not determine.
      messages: plain-language findings.
    """

    names: tuple
    coordinates: tuple
    z: np.ndarray
    theta: np.ndarray
    cov_z: np.ndarray
    cov_theta: np.ndarray
    stderr_theta: np.ndarray
    interval: np.ndarray
    interval_z: np.ndarray
    correlation: np.ndarray
    level: float
    quantile: float
    s2: float
    n: int
    n_eff: float
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    non_identifiable: tuple
    messages: tuple

    def contains(self, theta_true) -> np.ndarray:
        """(p,) bool: whether each true value lies inside its interval."""
        t = np.asarray(theta_true, np.float64)
        return (self.interval[:, 0] <= t) & (t <= self.interval[:, 1])

    def to_dict(self) -> dict:
        """JSON-able summary (infinite values as strings "inf"/"-inf", nan as None)."""

        def clean(a):
            a = np.asarray(a, np.float64)
            if a.ndim == 0:
                v = float(a)
                return None if math.isnan(v) else (v if math.isfinite(v) else ("inf" if v > 0 else "-inf"))
            return [clean(b) for b in a]

        return {
            "parameters": {n: {"value": clean(self.theta[i]), "stderr": clean(self.stderr_theta[i]),
                               "interval": clean(self.interval[i]), "identifiable": n not in self.non_identifiable}
                           for i, n in enumerate(self.names)},
            "level": self.level, "correlation": clean(self.correlation), "names": list(self.names),
            "covariance": clean(self.cov_theta), "residual_variance": self.s2, "n_residuals": self.n,
            "n_effective": self.n_eff, "messages": list(self.messages),
        }

    def report(self) -> str:
        """Multi-line plain-text report: values, intervals, correlations, findings."""
        pct = f"{100 * self.level:g}%"
        lines = [f"{'parameter':<12} {'value':>12} {pct + ' interval':>30} {'stderr':>11}"]
        for i, n in enumerate(self.names):
            lo, hi = self.interval[i]
            lines.append(f"{n:<12} {self.theta[i]:>12.5g} {'[' + f'{lo:.4g}, {hi:.4g}' + ']':>30} "
                         f"{self.stderr_theta[i]:>11.3g}")
        lines.append("correlation:")
        lines.append(" " * 12 + "".join(f"{n:>10}" for n in self.names))
        for i, n in enumerate(self.names):
            lines.append(f"{n:<12}" + "".join(f"{c:>10.3f}" for c in self.correlation[i]))
        lines.append(f"residual variance s^2 = {self.s2:.4g} from n = {self.n} residuals "
                     f"(n_eff = {self.n_eff:g} independent)")
        if len(self.names) > 1:
            v = self.eigenvectors[:, 0]
            combo = " ".join(f"{v[j]:+.2f}*{c}" for j, c in enumerate(self.coordinates))
            lines.append(f"weakest direction of the scaled J^T J: eigenvalue ratio {self.eigenvalues[0]:.3g} "
                         f"along {combo}")
        lines.extend(self.messages)
        return "\n".join(lines)


def _join(names):
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def gauss_newton_uncertainty(residual, jacobian, z, transform: ParameterTransform | None = None, *,
                             n_eff: float | None = None, level: float = DEFAULT_LEVEL,
                             max_relative_width: float = DEFAULT_MAX_RELATIVE_WIDTH,
                             singular_ratio: float = DEFAULT_SINGULAR_RATIO,
                             correlation_threshold: float = DEFAULT_CORRELATION_THRESHOLD,
                             rcond: float = DEFAULT_RCOND) -> Uncertainty:
    """Covariance, `level` intervals and an identifiability report at a least-squares optimum.

    Args:
      residual: (n,) residuals r at the optimum (dimensionless: data misfit over its scale).
      jacobian: (n, p) dr/dz at the optimum, z the fitted coordinates.
      z: (p,) fitted coordinates at the optimum.
      transform: the maps z -> theta (None: identity, names x0, x1, ...).
      n_eff: effective number of independent residuals, p < n_eff <= n (default n; see module docs).
      level: confidence level in (0, 1).
      max_relative_width: interval width / |value| above which a parameter is not identifiable.
      singular_ratio: eigenvalue ratio of the scaled J^T J below which a direction is near-singular.
      correlation_threshold: |correlation| above which a pair is reported as trading off.
      rcond: eigenvalue ratio treated as exactly singular (that direction's variance is infinite).
    """
    r = np.asarray(residual, np.float64).ravel()
    J = np.asarray(jacobian, np.float64)
    z = np.asarray(z, np.float64)
    n, p = r.shape[0], z.shape[0]
    if J.shape != (n, p):
        raise ValueError(f"jacobian must be (n={n}, p={p}), got {J.shape}")
    if n <= p:
        raise ValueError(f"need more residuals than parameters to estimate the noise, got n={n}, p={p}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise ValueError("residual and jacobian must be finite")
    n_eff = float(n) if n_eff is None else float(n_eff)
    if not p < n_eff <= n:
        raise ValueError(f"n_eff must be in (p={p}, n={n}], got {n_eff}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    if transform is None:
        transform = ParameterTransform.create([f"x{i}" for i in range(p)])
    if transform.size != p:
        raise ValueError(f"transform has {transform.size} parameters, the fit has {p}")
    names = tuple(transform.names)

    s2 = float(r @ r) / (n - p)
    inflation = n / n_eff
    H = J.T @ J
    d = np.sqrt(np.diag(H))
    dead = d <= 0.0  # parameters the residuals do not depend on at all
    ds = np.where(dead, 1.0, d)
    Hs = H / np.outer(ds, ds)
    Hs[dead, :] = 0.0
    Hs[:, dead] = 0.0
    w, V = np.linalg.eigh(Hs)
    w_max = max(float(w[-1]), np.finfo(np.float64).tiny)
    singular = w <= rcond * w_max
    inv_w = np.where(singular, 0.0, 1.0 / np.where(singular, 1.0, w))
    cov_s = (V * inv_w[None, :]) @ V.T
    cov_z = s2 * inflation * cov_s / np.outer(ds, ds)
    unbounded = (np.sum(V[:, singular] ** 2, axis=1) > _COMPONENT_MIN ** 2 / 100) | dead
    var_z = np.where(unbounded, np.inf, np.diag(cov_z))
    cov_z = np.where(unbounded[:, None] | unbounded[None, :], np.nan, cov_z)
    cov_z[np.diag_indices(p)] = var_z
    sd_z = np.sqrt(var_z)

    dof = n_eff - p
    q = student_t_quantile(0.5 + 0.5 * level, dof)
    interval_z = np.stack([z - q * sd_z, z + q * sd_z], axis=1)
    with np.errstate(invalid="ignore"):
        ends = np.stack([np.asarray(transform.to_physical(interval_z[:, 0])),
                         np.asarray(transform.to_physical(interval_z[:, 1]))], axis=1)
    interval = np.sort(ends, axis=1)
    theta = np.asarray(transform.to_physical(z))
    D = np.asarray(transform.jacobian(z))
    with np.errstate(invalid="ignore"):
        cov_theta = cov_z * np.outer(D, D)
        corr = cov_z / np.outer(sd_z, sd_z)
    corr = np.where(unbounded[:, None] | unbounded[None, :], np.nan, corr)
    corr[np.diag_indices(p)] = 1.0
    stderr_theta = np.sqrt(np.diag(cov_theta))

    messages, non_ident = [], []
    pct = f"{100 * level:g}%"
    for i, name in enumerate(names):
        lo, hi = interval[i]
        scale = max(abs(theta[i]), np.finfo(np.float64).tiny)
        if dead[i]:
            non_ident.append(name)
            messages.append(f"{name} is not identifiable: the residuals do not change when it changes.")
        elif unbounded[i] or (hi - lo) / scale > max_relative_width:
            non_ident.append(name)
            messages.append(f"{name} is not identifiable from these data: its {pct} interval [{lo:.4g}, {hi:.4g}] "
                            f"is wider than {max_relative_width:g} times its value {theta[i]:.4g}.")
    coords = transform.coordinate_names()
    reported_pairs = set()
    for k in range(p):
        if not (w[k] < singular_ratio * w_max) or dead.all():
            continue
        v = V[:, k]
        members = [j for j in range(p) if abs(v[j]) >= _COMPONENT_MIN and not dead[j]]
        if len(members) < 2:
            continue
        j0 = members[0]
        together = [names[j] for j in members if np.sign(v[j]) == np.sign(v[j0])]
        opposite = [names[j] for j in members if np.sign(v[j]) != np.sign(v[j0])]
        combo = " ".join(f"{v[j]:+.2f}*{coords[j]}" for j in members)
        if opposite:
            how = f"raising {_join(together)} while lowering {_join(opposite)}"
        else:
            how = f"raising {_join(together)} together"
        messages.append(f"{_join([names[j] for j in members])} trade off: {how} leaves the fit almost unchanged "
                        f"(J^T J is near-singular, eigenvalue ratio {w[k] / w_max:.2g}, direction {combo}); the "
                        f"data determine a combination of them, not each one.")
        reported_pairs.update((a, b) for a in members for b in members if a < b)
    for a in range(p):
        for b in range(a + 1, p):
            c = corr[a, b]
            if (a, b) in reported_pairs or not np.isfinite(c) or abs(c) < correlation_threshold:
                continue
            # positively correlated estimates: the flat valley of the loss runs along (+, +)
            sense = "raising both together" if c > 0 else "raising one while lowering the other"
            messages.append(f"{names[a]} and {names[b]} trade off (correlation {c:+.3f}): errors in one are "
                            f"compensated by the other ({sense} mostly fits the data equally well); "
                            f"quote them together.")
    if not messages:
        messages.append(f"All parameters are identifiable: every {pct} interval is narrower than "
                        f"{max_relative_width:g} times its value and no pair is correlated beyond "
                        f"{correlation_threshold:g}.")
    return Uncertainty(names=names, coordinates=tuple(coords), z=z, theta=theta, cov_z=cov_z, cov_theta=cov_theta,
                       stderr_theta=stderr_theta, interval=interval, interval_z=interval_z, correlation=corr,
                       level=level, quantile=q, s2=s2, n=n, n_eff=n_eff, eigenvalues=w / w_max, eigenvectors=V,
                       non_identifiable=tuple(non_ident), messages=tuple(messages))


def solution_uncertainty(solution, transform: ParameterTransform | None = None, **kwargs) -> Uncertainty:
    """`gauss_newton_uncertainty` at a `Solution` of `least_squares` (uses its residual and jacobian)."""
    if solution.residual is None or solution.jacobian is None:
        raise ValueError("this Solution carries no residual/jacobian (not a least-squares fit, or resumed from "
                         "a finished log with a gradient optimizer); evaluate (r, J) at solution.x and call "
                         "gauss_newton_uncertainty")
    return gauss_newton_uncertainty(solution.residual, solution.jacobian, solution.x, transform, **kwargs)
