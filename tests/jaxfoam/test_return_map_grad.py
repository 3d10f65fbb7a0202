"""Derivatives of the Herschel-Bulkley return map (implicit function theorem) and of the grid division.

Contracts checked:
  - d s_new / d(mu, sigma_y, eta, m) and d bbar_new / d bbar_n equal central finite differences in
    float64 to 1e-6 relative, over m in {0.2, 0.5, 1, 2}, eta in {0 .. 1e3} Pa s^m and trial stresses
    from just past yield to 50x yield. The finite differences use a 5-point stencil (truncation
    O(h^4)) with steps kept well inside the distance to the yield kink; their rounding error,
    FD_NOISE * eps * max|f| / h, is added to the tolerance ("FD noise permitting") and the test also
    checks that this floor is below the 1e-6 relative bound for most comparisons.
  - forward mode (jvp) and reverse mode (vjp) give the same derivatives;
  - values and derivatives are finite exactly at the yield surface (gamma = 0), in the elastic
    regime, at eta = 0 and at m = 1; d s / d m = 0 at eta = 0; the one-sided derivatives at the
    yield surface are the documented limits;
  - the grid velocity division keeps a finite derivative in float32 for tiny node masses.
"""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam as jf
from jaxfoam._mpm import safe_div

from helpers import central_difference

SQRT_2_3 = math.sqrt(2.0 / 3.0)
MU = 200.0        # Pa
SIGMA_Y = 30.0    # Pa
DT = 1e-3         # s
M_VALUES = (0.2, 0.5, 1.0, 2.0)
ETA_VALUES = (0.0, 1e-2, 1.0, 30.0, 1e3)      # Pa s^m
RATIOS = (1.001, 1.1, 3.0, 10.0, 50.0)         # trial stress / yield stress
RTOL = 1e-6
FD_NOISE = 30.0  # rounding of the 5-point stencil is ~1.5 eps max|f| / h; x20 for rounding inside f
EPS = float(np.finfo(np.float64).eps)

# A generic plane-strain increment direction (shear, stretch and volume change) and a pre-stressed
# elastic state (det 1): every term of the predictor and of eq. 16 is exercised.
G_DIR = np.array([[0.3, 1.0], [-0.2, -0.1]])
B_SYM = np.array([[0.05, 0.02, 0.01], [0.02, -0.03, 0.0], [0.01, 0.0, -0.02]])


def _expm_sym(a):
    w, v = np.linalg.eigh(a)
    return (v * np.exp(w)) @ v.T


BBAR_N = _expm_sym(B_SYM)  # traceless exponent: det = 1


def _predictor(t):
    """Elastic predictor of the increment f = I + t G_DIR (numpy): (bpre (3,3), s_pre / mu, fbar)."""
    f3 = np.eye(3)
    f3[:2, :2] += t * G_DIR
    fbar = f3 * np.linalg.det(f3) ** (-1.0 / 3.0)
    bpre = fbar @ BBAR_N @ fbar.T
    dev = bpre - np.trace(bpre) / 3.0 * np.eye(3)
    return bpre, np.linalg.norm(dev), fbar


def _t_for_ratio(r):
    """Increment size t >= 0 whose trial stress is r times the yield stress (bisection)."""
    target = r * SQRT_2_3 * SIGMA_Y / MU
    lo, hi = 0.0, 1.0
    while _predictor(hi)[1] < target:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _predictor(mid)[1] < target else (lo, mid)
    return 0.5 * (lo + hi)


def _cases():
    """Flat arrays over the grid m x eta x ratio: f (B, 2, 2), bbar (B, 3, 3), m, eta, D = s_pre / mu."""
    rows = []
    for m in M_VALUES:
        for eta in ETA_VALUES:
            for r in RATIOS:
                t = _t_for_ratio(r)
                _, D, fbar = _predictor(t)
                rows.append((np.eye(2) + t * G_DIR, BBAR_N, m, eta, D, np.linalg.norm(fbar, 2)))
    f = np.stack([r[0] for r in rows])
    b = np.stack([r[1] for r in rows])
    m, eta, D, fnorm = (np.array([r[k] for r in rows]) for k in (2, 3, 4, 5))
    return f, b, m, eta, D, fnorm


def _s_new(theta, f, bbar):
    """s_new as a function of theta = (mu, sigma_y, eta, m), each (B,)."""
    mu, sy, eta, m = theta
    params = jf.Params(mu=mu, kappa=1000.0, sigma_y=sy, eta=eta, m=m, rho=80.0)
    return jf.return_map(bbar, f, params, DT)[1]


def _bbar_new(bbar, f, theta):
    mu, sy, eta, m = theta
    params = jf.Params(mu=mu, kappa=1000.0, sigma_y=sy, eta=eta, m=m, rho=80.0)
    return jf.return_map(bbar, f, params, DT)[0]


_s_new_jit = jax.jit(_s_new)
_bbar_new_jit = jax.jit(_bbar_new)
_s_new_jvp = jax.jit(lambda th, tan, f, b: jax.jvp(lambda *t: _s_new(t, f, b), th, tan)[1])
_bbar_new_jvp = jax.jit(lambda b, v, f, th: jax.jvp(lambda bb: _bbar_new(bb, f, th), (b,), (v,))[1])


def _fd5_forward(fun, x0, h):
    """One-sided 5-point derivative (for eta = 0, where eta < 0 is outside the model: only here, so
    it stays local; the central ones use helpers.central_difference)."""
    return (-25 * fun(x0) + 48 * fun(x0 + h) - 36 * fun(x0 + 2 * h) + 16 * fun(x0 + 3 * h)
            - 3 * fun(x0 + 4 * h)) / (12 * h)


@pytest.fixture(scope="module")
def grid_cases():
    f, b, m, eta, D, fnorm = _cases()
    B = len(m)
    theta = (np.full(B, MU), np.full(B, SIGMA_Y), eta, m)
    excess = MU * D - SQRT_2_3 * SIGMA_Y
    tr3 = np.array([np.trace(_predictor(_t_for_ratio(r))[0]) / 3.0 for r in RATIOS])
    a = 2.0 * MU * np.tile(tr3, B // len(RATIOS)) * DT
    gamma = np.asarray(jf.hb_rate(jnp.asarray(a), jnp.asarray(excess), jnp.asarray(eta), jnp.asarray(m)))
    # eta at which the viscous term eta gamma^m equals the elastic one a gamma: s varies with eta on
    # the scale eta + eta_c (for m > 1 and fast flow eta_c is tiny: FD steps must be smaller).
    eta_c = a * gamma ** (1.0 - m)
    return dict(f=jnp.asarray(f), b=jnp.asarray(b), theta=tuple(jnp.asarray(x) for x in theta), D=D,
                fnorm=fnorm, excess=excess, eta_scale=eta + eta_c, log_gamma=np.abs(np.log(gamma)))


def test_grid_covers_just_past_yield_to_50x(grid_cases):
    ratio = MU * grid_cases["D"] / (SQRT_2_3 * SIGMA_Y)
    np.testing.assert_allclose(sorted(set(np.round(ratio, 9))), RATIOS, rtol=1e-9)


def test_ds_dparams_matches_finite_differences(grid_cases):
    """Implicit-function derivative of s_new (eq. 14) against central differences, per parameter."""
    f, b, theta, excess, D = (grid_cases[k] for k in ("f", "b", "theta", "excess", "D"))
    B = f.shape[0]
    s0 = np.asarray(_s_new_jit(theta, f, b))
    # Parameter change that would reach the yield kink: mu by excess / D, sigma_y by excess / sqrt(2/3).
    kink = (excess / D, excess / SQRT_2_3, np.full(B, np.inf), np.full(B, np.inf))
    n_checked, n_noisy = 0, 0
    for k, name in enumerate(("mu", "sigma_y", "eta", "m")):
        tangent = tuple(jnp.ones(B) if j == k else jnp.zeros(B) for j in range(4))
        ad = np.asarray(_s_new_jvp(theta, tangent, f, b))
        x0 = np.asarray(theta[k])
        h = np.minimum(1e-3 * np.maximum(np.abs(x0), 1.0), 0.02 * kink[k])
        if name == "eta":
            h = 1e-3 * grid_cases["eta_scale"]
        if name == "m":  # gamma^m changes by a factor exp(h |ln gamma|)
            h = 1e-3 * x0 / np.maximum(1.0, grid_cases["log_gamma"])

        def fun(x):
            th = tuple(jnp.asarray(x) if j == k else theta[j] for j in range(4))
            return np.asarray(_s_new_jit(th, f, b))

        if name == "eta":
            # central where the stencil stays at eta >= 0, else one-sided (eta < 0 is outside the model)
            fd = np.where(x0 - 2 * h > 0, central_difference(fun, x0, h=h, order=4), _fd5_forward(fun, x0, h))
        else:
            fd = central_difference(fun, x0, h=h, order=4)
        noise = FD_NOISE * EPS * np.abs(s0) / h
        err = np.abs(ad - fd)
        bad = err > RTOL * np.abs(fd) + noise
        assert not bad.any(), (
            f"d s_new / d {name}: {bad.sum()} of {B} cases off; worst: m = {np.asarray(theta[3])[bad][:3]}, "
            f"eta = {np.asarray(theta[2])[bad][:3]}, autodiff {ad[bad][:3]}, FD {fd[bad][:3]}")
        assert np.all(np.isfinite(ad))
        n_checked += B
        n_noisy += int(np.sum(noise > RTOL * np.abs(fd)))
    # The rounding floor must leave most comparisons at the full 1e-6 relative bound (cases where the
    # derivative itself is ~0, e.g. d/deta at eta = 1e3 just past yield, are the exceptions).
    assert n_noisy <= 0.2 * n_checked, f"{n_noisy} of {n_checked} comparisons limited by FD rounding"


def test_dbbar_dbbar_n_matches_finite_differences(grid_cases):
    """d bbar_new / d bbar_n along a generic symmetric direction, all 9 components."""
    f, b, theta, excess, fnorm = (grid_cases[k] for k in ("f", "b", "theta", "excess", "fnorm"))
    V = jnp.asarray(np.array([[0.3, -0.7, 0.2], [-0.7, 0.5, 0.4], [0.2, 0.4, -0.6]]))
    V = jnp.broadcast_to(V, b.shape)
    ad = np.asarray(_bbar_new_jvp(b, V, f, theta))
    # |d s_pre / dh| <= mu |fbar|^2 |V|: keep 2 h below 2% of the distance to yield.
    h = np.minimum(1e-4, 0.02 * excess / (MU * fnorm ** 2 * float(jnp.linalg.norm(V[0]))))[:, None, None]
    fun = lambda hh: np.asarray(_bbar_new_jit(b + jnp.asarray(hh) * V, f, theta))
    fd = central_difference(fun, 0.0, h=h, order=4)
    scale = np.max(np.abs(fd), axis=(1, 2))
    err = np.max(np.abs(ad - fd), axis=(1, 2))
    noise = FD_NOISE * EPS * np.max(np.abs(fun(0.0 * h)), axis=(1, 2)) / h[:, 0, 0]
    bad = err > RTOL * scale + noise
    assert not bad.any(), f"d bbar_new / d bbar_n off in {bad.sum()} cases: err {err[bad][:3]}, scale {scale[bad][:3]}"
    assert np.all(noise < RTOL * scale)


@pytest.mark.slow
def test_forward_and_reverse_mode_agree(grid_cases):
    """<u, J v> by jvp equals <J^T u, v> by vjp, for d(bbar_new, s_new) / d(bbar_n, params)."""
    f, b, theta = (grid_cases[k] for k in ("f", "b", "theta"))
    B = f.shape[0]
    rng = np.random.default_rng(0)

    def fun(bb, th):
        mu, sy, eta, m = th
        params = jf.Params(mu=mu, kappa=1000.0, sigma_y=sy, eta=eta, m=m, rho=80.0)
        bn, s = jf.return_map(bb, f, params, DT)
        return bn, s

    vb = jnp.asarray(rng.normal(size=b.shape))
    vth = tuple(jnp.asarray(rng.normal(size=B) * x) for x in (MU * 1e-2, 1.0, 1.0, 0.1))
    # eta = 0 is a boundary: only increase it there, so forward and reverse see the same one-sided rule.
    vth = (vth[0], vth[1], jnp.abs(vth[2]), vth[3])
    ub = jnp.asarray(rng.normal(size=b.shape))
    us = jnp.asarray(rng.normal(size=B))
    @jax.jit
    def both(b, theta, vb, vth, ub, us):
        _, tangent_out = jax.jvp(fun, (b, theta), (vb, vth))
        _, pullback = jax.vjp(fun, b, theta)
        return tangent_out, pullback((ub, us))

    (jb, js), (cb, cth) = both(b, theta, vb, vth, ub, us)
    lhs = np.sum(np.asarray(jb * ub), axis=(1, 2)) + np.asarray(js * us)
    rhs = np.sum(np.asarray(cb * vb), axis=(1, 2)) + sum(np.asarray(c * v) for c, v in zip(cth, vth))
    scale = (np.sum(np.abs(np.asarray(jb * ub)), axis=(1, 2)) + np.abs(np.asarray(js * us)))
    np.testing.assert_array_less(np.abs(lhs - rhs), 1e-12 * scale + 1e-300)
    # and the full Jacobians by jacfwd and jacrev, case by case
    for i in (0, 37, 66, B - 1):
        _, jfw, jrv = _all_derivatives(b[i], f[i], jnp.asarray([t[i] for t in theta]))
        for x, y in zip(jax.tree_util.tree_leaves(jfw), jax.tree_util.tree_leaves(jrv)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-14)


@jax.jit
def _all_derivatives_jit(bb, f, theta):
    def fun(x):
        bb_, th = x
        mu, sy, eta, m = (th[k] for k in range(4))
        params = jf.Params(mu=mu, kappa=1000.0, sigma_y=sy, eta=eta, m=m, rho=80.0)
        return jf.return_map(bb_, f, params, DT)
    x = (bb, theta)
    return fun(x), jax.jacfwd(fun)(x), jax.jacrev(fun)(x)


def _all_derivatives(bb, f, theta):
    """Value and every first derivative of (bbar_new, s_new) w.r.t. (bbar_n, (mu, sigma_y, eta, m)),
    by forward and by reverse mode."""
    return _all_derivatives_jit(jnp.asarray(bb, jnp.float64), jnp.asarray(f, jnp.float64),
                                jnp.asarray(theta, jnp.float64))


def _finite(tree):
    return all(bool(jnp.all(jnp.isfinite(a))) for a in jax.tree_util.tree_leaves(tree))


@pytest.mark.slow
@pytest.mark.parametrize("m", M_VALUES)
@pytest.mark.parametrize("eta", (0.0, 5.0))
def test_finite_exactly_at_yield(m, eta):
    """gamma = 0 at s_pre = s_Y: value and all derivatives finite, for sigma_y within 3 ulps of yield."""
    t = _t_for_ratio(2.0)
    f = jnp.asarray(np.eye(2) + t * G_DIR)
    bb = jnp.asarray(BBAR_N)
    elastic = jf.Params(mu=MU, kappa=1000.0, sigma_y=1e9, eta=eta, m=m, rho=80.0)
    s_pre = float(jf.return_map(bb, f, elastic, DT)[1])
    sy = s_pre / SQRT_2_3
    for k in range(-3, 4):
        sy_k = float(sy)
        for _ in range(abs(k)):
            sy_k = float(np.nextafter(sy_k, np.inf if k > 0 else -np.inf))
        (bn, s), jf_, jr = _all_derivatives(bb, f, (MU, sy_k, eta, m))
        assert _finite((bn, s, jf_, jr)), f"non-finite at sigma_y = yield {k:+d} ulp"
        assert abs(float(s) - s_pre) <= 1e-12 * s_pre  # no plastic flow at the yield surface
        np.testing.assert_allclose(jf_[1][1], jr[1][1], rtol=1e-12, atol=1e-15)


def test_elastic_regime_derivatives_are_exact():
    """Below yield: s = s_pre, so d s/d mu = s_pre / mu and the flow parameters have no effect;
    bbar_new = fbar bbar_n fbar^T is linear in bbar_n."""
    t = _t_for_ratio(0.5)
    f = jnp.asarray(np.eye(2) + t * G_DIR)
    bb = jnp.asarray(BBAR_N)
    (bn, s), jfw, jrv = _all_derivatives(bb, f, (MU, SIGMA_Y, 7.0, 0.4))
    assert _finite((jfw, jrv))
    ds = np.asarray(jfw[1][1])
    np.testing.assert_allclose(ds[0], float(s) / MU, rtol=1e-12)
    np.testing.assert_array_equal(ds[1:], 0.0)
    _, _, fbar = _predictor(t)
    expect = np.einsum("ik,lj->ijkl", fbar, fbar.T)  # d (fbar B fbar^T)_ij / d B_kl
    np.testing.assert_allclose(np.asarray(jfw[0][0]), expect, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(jrv[0][0]), expect, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("m", M_VALUES)
def test_eta_zero_rate_independent_limit(m):
    """eta = 0 (rate-independent plasticity, eq. 15): finite derivatives, d s / d m = 0 exactly, and
    d s / d eta equals its one-sided finite difference (eta < 0 is outside the model)."""
    t = _t_for_ratio(5.0)
    f = jnp.asarray(np.eye(2) + t * G_DIR)
    bb = jnp.asarray(BBAR_N)
    (bn, s), jfw, jrv = _all_derivatives(bb, f, (MU, SIGMA_Y, 0.0, m))
    assert _finite((bn, s, jfw, jrv))
    ds = np.asarray(jfw[1][1])
    assert ds[3] == 0.0 and float(np.asarray(jrv[1][1])[3]) == 0.0
    fun = lambda e: float(_s_new_jit((MU, SIGMA_Y, e, m), f, bb))
    # s varies with eta on the scale eta_c = a gamma^(1-m) (viscous term = elastic term)
    bpre, D, _ = _predictor(t)
    a = 2.0 * MU * np.trace(bpre) / 3.0 * DT
    gamma = (MU * D - SQRT_2_3 * SIGMA_Y) / a  # eta = 0: gamma = b / a (eq. 15)
    h = 1e-3 * a * gamma ** (1.0 - m)
    fd = _fd5_forward(np.vectorize(fun), 0.0, h)
    assert abs(ds[2] - fd) <= RTOL * abs(fd) + FD_NOISE * EPS * abs(float(s)) / h


def test_one_sided_derivative_at_the_yield_surface():
    """d s / d sigma_y just past yield tends to the documented plastic-side limits
    (m < 1: 0, continuous with the elastic side; m = 1: K sqrt(2/3) a / (a + eta); m > 1: K sqrt(2/3),
    with a = 2 mubar dt and K = tr(bpre) tr(bpre^-1) / 9 >= 1 the factor by which the det-1
    renormalization of eq. 16 scales a change of s), while at and above yield the elastic side (0)
    is returned."""
    t = _t_for_ratio(2.0)
    f = jnp.asarray(np.eye(2) + t * G_DIR)
    bb = jnp.asarray(BBAR_N)
    elastic = jf.Params(mu=MU, kappa=1000.0, sigma_y=1e9, eta=1.0, m=1.0, rho=80.0)
    bpre, D, _ = _predictor(t)
    s_pre = float(jf.return_map(bb, f, elastic, DT)[1])
    a = 2.0 * MU * np.trace(bpre) / 3.0 * DT
    eta = 1.0
    K = np.trace(bpre) * np.trace(np.linalg.inv(bpre)) / 9.0
    grad_sy = jax.jit(jax.grad(lambda sy, m: _s_new((MU, sy, eta, m), f, bb)))
    for m, limit in ((0.5, 0.0), (1.0, K * SQRT_2_3 * a / (a + eta)), (2.0, K * SQRT_2_3)):
        sy_plastic = s_pre / SQRT_2_3 * (1.0 - 1e-10)
        assert float(grad_sy(s_pre / SQRT_2_3 * (1.0 + 1e-12), m)) == 0.0
        np.testing.assert_allclose(float(grad_sy(sy_plastic, m)), limit, atol=1e-6 * SQRT_2_3)


@jax.jit
def _hb_rate_derivatives(*args):
    argnums = (0, 1, 2, 3)
    return (jf.hb_rate(*args), jax.jacfwd(jf.hb_rate, argnums=argnums)(*args),
            jax.jacrev(jf.hb_rate, argnums=argnums)(*args))


@pytest.mark.parametrize("m", (0.1, 0.2, 1.0, 2.0))
def test_hb_rate_finite_everywhere(m):
    """The scalar solve's value and derivatives (w.r.t. a, b, eta, m) at b = 0, b < 0, tiny b > 0
    (gamma may underflow), eta = 0 and huge eta, in float64 and float32."""
    for dtype in (jnp.float64, jnp.float32):
        bs = jnp.asarray([0.0, -1.0, 1e-300 if dtype == jnp.float64 else 1e-38, 1e-8, 1.0, 1e3], dtype)
        for eta in (0.0, 1e-3, 1.0, 1e4):
            args = (jnp.full_like(bs, 0.4), bs, jnp.full_like(bs, eta), jnp.full_like(bs, m))
            g, jac_f, jac_r = _hb_rate_derivatives(*args)
            assert _finite((g, jac_f, jac_r)), f"non-finite hb_rate derivative, m = {m}, eta = {eta}, {dtype}"
            assert bool(jnp.all(g[:2] == 0.0))
            for a, b in zip(jac_f, jac_r):
                # atol: both modes agree to underflow level (b = 1e-300 gives derivatives ~1e-300)
                f32 = dtype == jnp.float32
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5 if f32 else 1e-12,
                                           atol=1e-30 if f32 else 1e-250)


# ----------------------------------------------------------------------------------------------
# Grid velocity = momentum / mass in float32.
# ----------------------------------------------------------------------------------------------

# Node masses, kg: a full node (1e-4) down to the smallest a float32 stencil-edge weight can produce
# (quadratic weights >= ~1e-14 per axis in float32, times a particle mass ~1e-4 kg).
TINY_MASSES = (1e-4, 1e-12, 1e-20, 1e-28, 1e-33, 0.0)


@pytest.mark.slow
def test_safe_div_derivative_finite_in_float32_for_tiny_masses():
    """d(mv/m) in float32: the textbook quotient rule squares m (1e-33^2 underflows to 0 -> inf/NaN);
    safe_div's (dmv - q dm)/m stays finite and matches the float64 derivative."""
    den64 = np.asarray(TINY_MASSES)
    num64 = 1.7 * den64  # momentum of a node moving at 1.7 m/s
    weights = np.linspace(0.5, 1.5, den64.size)

    def loss(num, den, div):
        return jnp.sum(jnp.asarray(weights[:num.size], num.dtype) * div(num, den))

    naive = lambda n, d: n / d
    for mode in ("rev", "fwd"):
        diff = jax.grad if mode == "rev" else jax.jacfwd
        g32 = diff(loss, argnums=(0, 1))(jnp.asarray(num64, jnp.float32), jnp.asarray(den64, jnp.float32), safe_div)
        g64 = diff(loss, argnums=(0, 1))(jnp.asarray(num64), jnp.asarray(den64), safe_div)
        assert _finite(g32), f"{mode}: safe_div derivative not finite in float32"
        for a, b in zip(g32, g64):
            np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b), rtol=1e-5)
        # empty node: zero value and zero derivative
        assert float(g32[0][-1]) == 0.0 and float(g32[1][-1]) == 0.0
    # The quotient rule would fail here (this is what the custom derivative fixes).
    g_naive = jax.grad(loss, argnums=1)(jnp.asarray(num64[:-1], jnp.float32),
                                        jnp.asarray(den64[:-1], jnp.float32), naive)
    assert not bool(jnp.all(jnp.isfinite(g_naive)))


@pytest.mark.slow
def test_grid_update_reverse_mode_finite_in_float32():
    """Gravity and colliders after the division: the gradient of grid velocities w.r.t. grid mass and
    momentum stays finite in float32 with tiny stencil-edge masses."""
    scene = jf.load_scene({"kind": "drop", "dim": 2, "density": 80.0, "kappa": 2000.0,
                           "domain": {"min": [0.0, 0.0], "max": [0.1, 0.1]}, "floor": {"y": 0.0, "friction": 0.5},
                           "initial_shape": {"type": "box", "min": [0.03, 0.03], "max": [0.07, 0.07]}},
                          dtype=jnp.float32)
    grid = jf.make_grid(scene, 0.02)
    G = grid.num_nodes
    rng = np.random.default_rng(1)
    mass = jnp.asarray(np.asarray(TINY_MASSES)[rng.integers(0, len(TINY_MASSES), G)], jnp.float32)
    mom = mass[:, None] * jnp.asarray(rng.normal(size=(G, 2)), jnp.float32)

    def loss(mv, m):
        v = jf.grid_update(mv, m, scene, grid, jnp.float32(0.0), jnp.float32(1e-4))
        return jnp.sum(v * v)

    gmv, gm = jax.grad(loss, argnums=(0, 1))(mom, mass)
    assert _finite((gmv, gm))
    assert float(jnp.max(jnp.abs(gm))) > 0.0
