"""The Continuum Foam material law (Yue et al. 2015, eqs. 1-16), written independently of jaxfoam.

State of a material point: J = det F (volume ratio) and the isochoric elastic left Cauchy-Green tensor
bbar_e (3x3, det 1). Plastic flow is isochoric, so J_e = J.

- Kirchhoff stress tau = kappa/2 (J^2 - 1) I + mu dev(bbar_e), Pa (eq. 2).
- Yield: ||s|| > sqrt(2/3) sigma_y with s = mu dev(bbar_e) (von Mises).
- Herschel-Bulkley plastic rate gamma(s) = ((||s|| - sqrt(2/3) sigma_y) / eta)^(1/m), 1/s (eq. 5).
- Return map (eq. 14-16): the plastic rate of a step solves
      h(gamma) = eta gamma^m + 2 mubar dt gamma - (s_pre - s_Y) = 0,   mubar = mu tr(bbar_pre) / 3,
  by a bracketed Newton iteration with bisection fallback (`plastic_rate`), then
      s = s_pre - 2 mubar dt gamma,   bbar = (s / s_pre) dev(bbar_pre) + tr(bbar_pre)/3 I,  det -> 1.

All functions are numba kernels (see `_jit`): scalars and small numpy arrays only.
"""
from __future__ import annotations

import math

import numpy as np

from ._jit import kernel

SQRT_2_3 = math.sqrt(2.0 / 3.0)
# The Newton/bisection iteration on h stops when the bracket is this small relative to its upper end.
RATE_RTOL = 1e-15
RATE_MAX_ITER = 200


@kernel
def plastic_rate(excess, a, eta, m):
    """Root gamma >= 0 (1/s) of eta gamma^m + a gamma = excess, for excess >= 0 (Pa), a = 2 mubar dt > 0 (Pa s).

    h is strictly increasing on [0, excess / a] with h(0) <= 0 <= h(excess / a), so the root is bracketed.
    Newton steps are taken from the current point and replaced by the bracket's midpoint whenever they
    leave the bracket; the bracket shrinks every iteration. eta = 0 is the rate-independent limit.
    """
    if excess <= 0.0:
        return 0.0
    hi = excess / a
    if eta <= 0.0:
        return hi
    lo = 0.0
    # Start at the Bingham (m = 1) root, inside the bracket.
    g = excess / (a + eta * hi ** (m - 1.0)) if m != 1.0 else excess / (a + eta)
    for _ in range(RATE_MAX_ITER):
        h = eta * g ** m + a * g - excess
        if h > 0.0:
            hi = g
        else:
            lo = g
        if h == 0.0 or hi - lo <= RATE_RTOL * hi:
            return g
        step = h / (m * eta * g ** (m - 1.0) + a) if g > 0.0 else hi
        g_new = g - step
        if not (lo < g_new < hi):
            g_new = 0.5 * (lo + hi)
        elif abs(step) <= RATE_RTOL * g_new:
            return g_new
        g = g_new
    return g


@kernel
def det3(a):
    """Determinant of a 3x3 array."""
    return (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
            - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
            + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))


@kernel
def return_map(b, f, mu, sigma_y, eta, m, dt, pre):
    """One step of bbar_e, in place. b: (3, 3) bbar_e at step n (det 1); f: (3, 3) increment I + dt grad v
    (plane strain: f[2, 2] = 1, f[:2, 2] = f[2, :2] = 0). mu, sigma_y (Pa), eta (Pa s^m), m, dt (s);
    pre: a (3, 3) work array (it receives the elastic predictor).

    Returns the plastic rate gamma of the step (1/s; 0 when elastic).
    """
    c2 = det3(f) ** (-2.0 / 3.0)
    for i in range(3):  # pre <- f b
        for j in range(3):
            pre[i, j] = f[i, 0] * b[0, j] + f[i, 1] * b[1, j] + f[i, 2] * b[2, j]
    for i in range(3):  # b <- det(f)^(-2/3) (f b) f^T, the predictor; pre <- the same
        r0, r1, r2 = pre[i, 0], pre[i, 1], pre[i, 2]
        for j in range(3):
            b[i, j] = c2 * (r0 * f[j, 0] + r1 * f[j, 1] + r2 * f[j, 2])
    for i in range(3):
        for j in range(3):
            pre[i, j] = b[i, j]
    tr3 = (pre[0, 0] + pre[1, 1] + pre[2, 2]) / 3.0
    dev_norm2 = 0.0
    for i in range(3):
        for j in range(3):
            dij = pre[i, j] - (tr3 if i == j else 0.0)
            dev_norm2 += dij * dij
    s_pre = mu * math.sqrt(dev_norm2)
    s_y = SQRT_2_3 * sigma_y
    gamma = 0.0
    scale = 1.0
    if s_pre > s_y:
        a = 2.0 * mu * tr3 * dt
        gamma = plastic_rate(s_pre - s_y, a, eta, m)
        scale = max(s_pre - a * gamma, s_y) / s_pre
    for i in range(3):
        for j in range(3):
            b[i, j] = scale * (pre[i, j] - (tr3 if i == j else 0.0)) + (tr3 if i == j else 0.0)
    renorm = det3(b) ** (-1.0 / 3.0)
    for i in range(3):
        for j in range(3):
            b[i, j] *= renorm
    return gamma


@kernel
def kirchhoff(b, J, mu, kappa, d, out):
    """Kirchhoff stress, Pa, of (bbar_e b (3, 3), J) into out (d, d): the in-plane block in 2D (plane strain)."""
    tr3 = (b[0, 0] + b[1, 1] + b[2, 2]) / 3.0
    vol = 0.5 * kappa * (J * J - 1.0)
    for i in range(d):
        for j in range(d):
            out[i, j] = mu * b[i, j] + ((vol - mu * tr3) if i == j else 0.0)


def hb_residual(gamma, s_pre, mubar, sigma_y, eta, m, dt):
    """Residual of eq. 14 written for the rate: eta gamma^m + 2 mubar dt gamma - (s_pre - sqrt(2/3) sigma_y), Pa."""
    return eta * gamma ** m + 2.0 * mubar * dt * gamma - (s_pre - SQRT_2_3 * sigma_y)


def drive_simple_shear(mu, sigma_y, eta, m, rate, strain, steps_per_unit_strain=2000):
    """Drive one material point in plane-strain simple shear (grad v = rate e_x e_y^T, 1/s) to a shear strain.

    Returns the history of the shear stress tau_xy = mu bbar_xy (Pa; Kirchhoff, J = 1) per step.
    """
    n = int(round(strain * steps_per_unit_strain))
    dt = 1.0 / (steps_per_unit_strain * rate)
    f = np.eye(3)
    f[0, 1] = rate * dt
    b = np.eye(3)
    work = np.zeros((3, 3))
    out = np.empty(n)
    for k in range(n):
        return_map(b, f, mu, sigma_y, eta, m, dt, work)
        out[k] = mu * b[0, 1]
    return out
