"""The Herschel-Bulkley return map (model.md, Yue et al. 2015 eq. 12-16) checked against its equations.

The reference quantities (elastic predictor, s_pre, mubar, eq. 15, eq. 16) are recomputed here in numpy,
independently of jaxfoam. Stresses in Pa, times in s, eta in Pa s^m.

`return_map` returns s_new = mu ||dev(bbar_new)|| of the renormalized tensor (det 1). Eq. 16 keeps the
direction of dev(bbar_pre) and the trace part tr(bbar_pre)/3 and only the renormalization multiplies both
by the same factor c, so the eq. 14 stress is recovered exactly as
    s = s_new * tr(bbar_pre) / tr(bbar_new).
"""
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam
import jaxfoam._constitutive as constitutive
from jaxfoam import Params, return_map

from helpers import central_difference

SQRT_2_3 = math.sqrt(2.0 / 3.0)
EPS = np.finfo(np.float64).eps
MU = 500.0  # shear modulus of the test material, Pa (shaving-cream order of magnitude)
KAPPA = 2000.0  # bulk modulus, Pa (enters no plastic quantity; needed by Params)
RHO = 80.0  # density, kg/m^3 (idem)

# Yield excess ratios s_pre / s_Y: from just past the yield surface to 1000x yield.
YIELD_RATIOS = (1.0 + 1e-10, 1.0 + 1e-6, 1.01, 2.0, 30.0, 1000.0)
# Shear strain of the step (the size of f - I): small, moderate, large.
STRAINS = (1e-3, 0.1, 1.0)
DTS = (1e-5, 1e-3)
M_VALUES = (0.1, 0.2, 0.5, 2.0, 3.0)
ETA_VALUES = (0.1, 1.0, 1e2, 1e4)


# ------------------------------------------------------------------------------------------------
# Independent numpy reference of the predictor and of eq. 15-16.
# ------------------------------------------------------------------------------------------------

def _embed3(f):
    d = f.shape[-1]
    out = np.broadcast_to(np.eye(3), f.shape[:-2] + (3, 3)).copy()
    out[..., :d, :d] = f
    return out


def _predictor(bbar, f):
    """Elastic predictor (model.md step 2-3): bbar_pre, dev(bbar_pre), tr(bbar_pre)/3, ||dev||."""
    f3 = _embed3(f)
    fbar = f3 * np.linalg.det(f3)[..., None, None] ** (-1.0 / 3.0)
    bpre = fbar @ bbar @ np.swapaxes(fbar, -1, -2)
    tr3 = np.trace(bpre, axis1=-2, axis2=-1) / 3.0
    dev = bpre - tr3[..., None, None] * np.eye(3)
    return bpre, dev, tr3, np.sqrt(np.sum(dev * dev, axis=(-2, -1)))


def _deformations(dim, strain, n, seed):
    """n incremental deformation gradients (n, dim, dim) with det > 0 and |f - I| ~ strain, and
    n elastic states bbar_e (n, 3, 3) (SPD, det 1) left by earlier elastic steps."""
    rng = np.random.default_rng(seed)
    e = rng.normal(size=(n, dim))
    e -= 0.3 * e.mean(axis=1, keepdims=True)  # some volume change, mostly isochoric
    stretch = np.exp(0.3 * strain * e)[:, :, None] * np.eye(dim)[None]
    shear = np.eye(dim)[None] + strain * np.triu(rng.normal(size=(n, dim, dim)), 1)
    theta = rng.uniform(-np.pi, np.pi, n)
    rot = np.broadcast_to(np.eye(dim), (n, dim, dim)).copy()
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = (np.cos(theta), -np.sin(theta),
                                                              np.sin(theta), np.cos(theta))
    f = rot @ stretch @ shear
    a = np.eye(3)[None] + 0.05 * rng.normal(size=(n, 3, 3))
    b0 = a @ np.swapaxes(a, -1, -2)
    b0 = b0 / np.linalg.det(b0)[:, None, None] ** (1.0 / 3.0)
    return f, b0


def _cases(dim, m_values, eta_values, seed=0):
    """A batch over (m, eta, dt, yield ratio, strain) with sigma_y chosen so that s_pre / s_Y is the
    requested ratio. Returns f, bbar, params (batched leaves), dt (n,) and the numpy predictor."""
    combos = list(itertools.product(m_values, eta_values, DTS, YIELD_RATIOS, STRAINS))
    m, eta, dt, ratio, strain = (np.array(c, float) for c in zip(*combos))
    n = len(combos)
    f = np.zeros((n, dim, dim))
    bbar = np.zeros((n, 3, 3))
    for k, g in enumerate(STRAINS):
        sel = strain == g
        f[sel], bbar[sel] = _deformations(dim, g, int(sel.sum()), seed + k)
    bpre, dev, tr3, ndev = _predictor(bbar, f)
    s_pre = MU * ndev
    sigma_y = s_pre / (ratio * SQRT_2_3)
    params = Params(mu=jnp.full(n, MU), kappa=jnp.full(n, KAPPA), sigma_y=jnp.asarray(sigma_y),
                    eta=jnp.asarray(eta), m=jnp.asarray(m), rho=jnp.full(n, RHO))
    ref = dict(bpre=bpre, dev=dev, tr3=tr3, s_pre=s_pre, s_y=SQRT_2_3 * sigma_y, mubar=MU * tr3,
               m=m, eta=eta, dt=dt, ratio=ratio)
    return jnp.asarray(f), jnp.asarray(bbar), params, jnp.asarray(dt), ref


_return_map_jit = jax.jit(return_map)
# Derivatives of gamma (1/s) with respect to (a, b, eta, m), per material point.
_grad_rate = jax.jit(jax.vmap(jax.grad(jaxfoam.hb_rate, argnums=(0, 1, 2, 3))))
# d(sum of s_new)/d(params), Pa per unit of each parameter.
_grad_sum_s = jax.jit(jax.grad(lambda params, bbar, f, dt: jnp.sum(return_map(bbar, f, params, dt)[1])))


def _run(f, bbar, params, dt):
    bnew, s_new = _return_map_jit(bbar, f, params, dt)
    bnew, s_new = np.asarray(bnew), np.asarray(s_new)
    s_rec = s_new * 3.0 / np.trace(bnew, axis1=-2, axis2=-1)  # times tr3 below
    return bnew, s_new, s_rec


# ------------------------------------------------------------------------------------------------
# m = 1 and eta = 0: the closed form eq. 15.
# ------------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
def test_m1_matches_closed_form_eq15(dim):
    """For m = 1 (Bingham) and eta = 0 (rate-independent) the stress after the return is eq. 15,
    s = s_pre - (s_pre - s_Y) / (1 + eta / (2 mubar dt)), to 1e-12 relative (1e-13 where s > 1 Pa),
    and bbar_new is eq. 16 renormalized, to 1e-12 relative."""
    f, bbar, params, dt, ref = _cases(dim, (1.0,), (0.0, 0.1, 1.0, 1e2, 1e4))
    bnew, s_new, s_rec = _run(f, bbar, params, dt)
    s_rec = s_rec * ref["tr3"]
    s_pre, s_y, mubar = ref["s_pre"], ref["s_y"], ref["mubar"]
    # eq. 15 with e = eta / (2 mubar dt), written without cancellation: s = (e s_pre + s_Y) / (1 + e).
    e = ref["eta"] / (2.0 * mubar * ref["dt"])
    s15 = (e * s_pre + s_y) / (1.0 + e)
    # 1e-12 relative, except where s << mu: there the floor eps mu |bbar| of a stress carried by
    # bbar_new (see `_attainable`) exceeds it (measured: 9.5e-13 relative at s = 0.04 Pa, mu = 500 Pa).
    tol = np.maximum(1e-12 * s15, 8.0 * _attainable(s15, bnew))
    rel = np.abs(s_rec - s15) / s15
    assert np.all(np.abs(s_rec - s15) <= tol), f"eq. 15 mismatch: max relative error {rel.max():.3e}"
    assert rel[s15 > 1.0].max() <= 1e-13
    # eq. 16 then det-1 renormalization, elementwise.
    b16 = (s15 / s_pre)[:, None, None] * ref["dev"] + ref["tr3"][:, None, None] * np.eye(3)
    b16 = b16 / np.linalg.det(b16)[:, None, None] ** (1.0 / 3.0)
    err_b = np.max(np.abs(bnew - b16), axis=(-2, -1)) / np.max(np.abs(b16), axis=(-2, -1))
    assert err_b.max() <= 1e-12, f"eq. 16 mismatch: max relative error {err_b.max():.3e}"
    s16 = MU * np.sqrt(np.sum((b16 - np.trace(b16, axis1=-2, axis2=-1)[:, None, None] / 3 * np.eye(3)) ** 2,
                              axis=(-2, -1)))
    assert np.all(np.abs(s_new - s16) <= np.maximum(1e-12 * s16, 8.0 * _attainable(s16, bnew)))
    # eta = 0 returns to the yield surface.
    eta0 = ref["eta"] == 0
    assert np.all(np.abs(s_rec[eta0] - s_y[eta0]) <= tol[eta0])


# ------------------------------------------------------------------------------------------------
# m != 1: the returned stress solves eq. 14.
# ------------------------------------------------------------------------------------------------

def _attainable(s, bnew):
    """Round-off floor of a stress (Pa) carried by bbar_new: eps (s + mu |bbar_new|_max). The deviator
    mu dev(bbar_new) is taken from a tensor with entries ~ tr(bbar)/3 >= 1, so for s << mu its
    relative precision is eps mu |bbar| / s, not eps."""
    return EPS * (s + MU * np.max(np.abs(bnew), axis=(-2, -1)))


def _eq14_root(s_pre, s_y, mubar, dt, eta, m, iters=200):
    """The root of eq. 14, r(s) = eta^(1/m) (s - s_pre) + 2 mubar dt (s - s_Y)^(1/m) = 0 on [s_Y, s_pre]
    (r increases from r(s_Y) <= 0 to r(s_pre) >= 0), by bisection in extended precision (Pa)."""
    L = np.longdouble
    s_pre, s_y, mubar, dt, eta, m = (np.asarray(v, L) for v in (s_pre, s_y, mubar, dt, eta, m))
    a = 2 * mubar * dt
    e = eta ** (1 / m)
    lo, hi = s_y.copy(), s_pre.copy()
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        r = e * (mid - s_pre) + a * (mid - s_y) ** (1 / m)
        lo, hi = np.where(r < 0, mid, lo), np.where(r < 0, hi, mid)
    return 0.5 * (lo + hi)


@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
def test_general_m_solves_eq14_to_roundoff(dim):
    """For m in {0.1, 0.2, 0.5, 2, 3}, eta in {0, 0.1 .. 1e4} Pa s^m, dt in {1e-5, 1e-3} s and
    s_pre / s_Y from 1 + 1e-10 to 1000, the returned s satisfies eq. 14 to round-off, lies in
    [s_Y, s_pre], keeps the direction of dev(bbar_pre) (eq. 16) and has det(bbar_new) = 1.
    eta = 0 is rate-independent plasticity: eq. 14 reduces to (s - s_Y)^(1/m) = 0, s = s_Y for any m."""
    f, bbar, params, dt, ref = _cases(dim, M_VALUES, (0.0,) + ETA_VALUES, seed=10 + dim)
    bnew, s_new, s_rec = _run(f, bbar, params, dt)
    s_rec = s_rec * ref["tr3"]
    s_pre, s_y = ref["s_pre"], ref["s_y"]
    assert np.all(np.isfinite(bnew)) and np.all(np.isfinite(s_new))
    # Distance to the exact root of eq. 14 (extended-precision bisection), in units of the attainable
    # accuracy (see `_attainable`). Measured: <= 2.1.
    root = _eq14_root(s_pre, s_y, ref["mubar"], ref["dt"], ref["eta"], ref["m"]).astype(float)
    err = np.abs(s_rec - root) / _attainable(root, bnew)
    assert err.max() <= 8.0, f"eq. 14 not solved to round-off: max error {err.max():.2f} x attainable"
    eta0 = ref["eta"] == 0
    assert np.all(np.abs(s_rec[eta0] - s_y[eta0]) <= 8.0 * _attainable(s_y[eta0], bnew[eta0]))
    slack = 8.0 * _attainable(s_rec, bnew)
    assert np.all(s_rec >= s_y - slack) and np.all(s_rec <= s_pre + slack)
    # eq. 16: only the magnitude of the deviator changes.
    dev_new = bnew - np.trace(bnew, axis1=-2, axis2=-1)[:, None, None] / 3 * np.eye(3)
    n_new = np.sqrt(np.sum(dev_new ** 2, axis=(-2, -1)))
    n_pre = s_pre / MU
    direction_err = np.max(np.abs(dev_new / n_new[:, None, None] - ref["dev"] / n_pre[:, None, None]), axis=(1, 2))
    assert np.all(direction_err <= 8.0 * _attainable(s_new, bnew) / s_new)
    # det(bbar_new) = 1 up to the round-off of a 3x3 determinant of entries of size |bbar|.
    size = np.max(np.abs(bnew), axis=(-2, -1))
    det_err = np.abs(np.linalg.det(bnew) - 1.0) / size ** 3
    assert det_err.max() <= 20 * EPS, f"det(bbar_new) - 1 up to {det_err.max():.3e} |bbar|^3"


# ------------------------------------------------------------------------------------------------
# The scalar solve: residual, iteration budget, no NaN at the yield surface.
# ------------------------------------------------------------------------------------------------

def _rate_grid():
    """(a, b, eta, m) over a log grid: a = 2 mubar dt in [1e-8, 1e4] Pa s, b = s_pre - s_Y in
    [1e-12, 1e8] Pa, eta in {0} U [1e-6, 1e4] Pa s^m, m in [0.1, 3]."""
    ms = np.array([0.1, 0.12, 0.2, 0.3, 0.5, 0.7, 0.9, 0.99, 1.0, 1.01, 1.5, 2.0, 2.5, 3.0])
    etas = np.concatenate([[0.0], np.logspace(-6, 4, 11)])
    a_s = np.logspace(-8, 4, 13)
    b_s = np.logspace(-12, 8, 21)
    return [np.ravel(v) for v in np.meshgrid(a_s, b_s, etas, ms, indexing="ij")]


def test_rate_equation_residual_roundoff():
    """gamma from `hb_rate` solves h(gamma) = eta gamma^m + a gamma - b = 0 (the gamma form of eq. 14)
    with |h| / b at float64 round-off over 11 decades of a, 20 of b, eta in {0} U [1e-6, 1e4], m in [0.1, 3].

    The solve iterates on ln(gamma), so gamma carries a relative error of ~|ln gamma| ulps (measured:
    |h|/b <= 1e-14 at |ln gamma| ~ 16); the bound 1e-13 allows that and nothing more."""
    a, b, eta, m = _rate_grid()
    gamma = np.asarray(jax.jit(jaxfoam.hb_rate)(jnp.asarray(a), jnp.asarray(b), jnp.asarray(eta), jnp.asarray(m)))
    assert np.all(np.isfinite(gamma)) and np.all(gamma > 0)
    rel = _rate_residual(gamma, a, b, eta, m)
    assert rel.max() <= 1e-13, f"max |h|/b = {rel.max():.3e} at {np.argmax(rel)}"


def _rate_residual(gamma, a, b, eta, m):
    """|h(gamma)| / b in extended precision, h = eta gamma^m + a gamma - b."""
    L = np.longdouble
    g = np.asarray(gamma, L)
    h = np.asarray(eta, L) * g ** np.asarray(m, L) + np.asarray(a, L) * g - np.asarray(b, L)
    return np.abs(h / np.asarray(b, L)).astype(float)


def test_newton_iteration_budget(monkeypatch):
    """RETURN_MAP_NEWTON_ITERS suffices, with one iteration to spare: over the grid of
    `test_rate_equation_residual_roundoff`, RETURN_MAP_NEWTON_ITERS - 1 iterations already leave the
    residual |h|/b at round-off (<= 1e-13 and <= twice that of 40 iterations).

    Measured on this grid (Halley steps, cubic convergence): 3 iterations reach round-off, |h|/b <= 7.1e-15
    as after 40 (2 leave 8.7e-6), and 4 reach the 40-iteration value bit for bit (3 differ by <= 3.8e-15
    relative)."""
    args = _rate_grid()
    budget = constitutive.RETURN_MAP_NEWTON_ITERS

    def residual(iters):
        monkeypatch.setattr(constitutive, "RETURN_MAP_NEWTON_ITERS", iters)
        gamma = jax.jit(lambda *x: constitutive.hb_rate(*x))(*(jnp.asarray(v) for v in args))
        return _rate_residual(np.asarray(gamma), *args).max()

    floor = residual(40)
    spare = residual(budget - 1)
    print(f"|h|/b: {floor:.2e} after 40 iterations, {spare:.2e} after {budget - 1}")
    assert spare <= min(1e-13, 2 * floor), f"{budget} Newton iterations leave no spare iteration"


@pytest.mark.slow
@pytest.mark.parametrize("m", [0.1, 0.3, 0.9])
def test_no_nan_just_past_yield_shear_thinning(m):
    """m < 1 at s -> s_Y+ (gamma -> 0+, where gamma^(m-1) is singular): finite gamma, stress and
    derivatives, from b = s_pre - s_Y at the smallest subnormal up to 1e-6 Pa; b = 0 is elastic."""
    b = jnp.asarray([0.0, 5e-324, 1e-310, 1e-300, 1e-200, 1e-30, 1e-15, 1e-6])
    a, eta = jnp.full_like(b, 1e-3), jnp.full_like(b, 10.0)
    mm = jnp.full_like(b, m)
    gamma = jaxfoam.hb_rate(a, b, eta, mm)
    assert np.all(np.isfinite(gamma)) and gamma[0] == 0.0 and np.all(gamma[1:] >= 0)
    grads = _grad_rate(a, b, eta, mm)
    assert all(np.all(np.isfinite(g)) for g in grads)

    # Through the full return map: sigma_y a hair below the predictor stress.
    f, bbar, params, dt, ref = _cases(3, (m,), (10.0,), seed=5)
    for rel_gap in (1e-15, 1e-13, 0.0):
        sigma_y = ref["s_pre"] * (1 - rel_gap) / SQRT_2_3
        p = params.replace(sigma_y=jnp.asarray(sigma_y))
        bnew, s_new = _return_map_jit(bbar, f, p, dt)
        assert np.all(np.isfinite(bnew)) and np.all(np.isfinite(s_new))
        grad_s = _grad_sum_s(p, bbar, f, dt)
        assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grad_s))


# ------------------------------------------------------------------------------------------------
# Elastic states.
# ------------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
def test_elastic_states_unchanged(dim):
    """Phi(s_pre) <= 0 accepts the elastic predictor: with f = I an elastic bbar_e comes back
    bit-identical and s_new is its stress; with a general f the result is the predictor fbar bbar fbar^T
    (to round-off of the independent numpy product) and s_new = s_pre; the gradient of s is that of
    mu ||dev(bbar_pre)||."""
    f, bbar, params, dt, _ = _cases(dim, (0.4,), (3.0,), seed=7)  # the batch shape of the other tests
    f, bbar = np.asarray(f), np.asarray(bbar)
    bpre, _, _, ndev = _predictor(bbar, f)
    identity = np.broadcast_to(np.eye(dim), f.shape)
    _, _, _, ndev0 = _predictor(bbar, identity)
    # sigma_y just above the stress, for both f: elastic.
    params = params.replace(sigma_y=jnp.asarray(1.001 * MU * np.maximum(ndev, ndev0) / SQRT_2_3))
    b_same, s_same = _return_map_jit(jnp.asarray(bbar), jnp.asarray(identity), params, dt)
    assert np.array_equal(np.asarray(b_same), bbar), "an elastic state with f = I must come back bit for bit"
    np.testing.assert_allclose(np.asarray(s_same), MU * ndev0, rtol=1e-14)

    b_el, s_el = _return_map_jit(jnp.asarray(bbar), jnp.asarray(f), params, dt)
    np.testing.assert_allclose(np.asarray(b_el), bpre, rtol=0, atol=1e-14 * np.abs(bpre).max())
    np.testing.assert_allclose(np.asarray(s_el), MU * ndev, rtol=1e-13)
    # Elastic gradients: s = mu ||dev(bbar_pre)|| depends on mu alone (the plastic branch, unused,
    # must not leak NaN into reverse mode).
    grad = _grad_sum_s(params, jnp.asarray(bbar), jnp.asarray(f), dt)
    np.testing.assert_allclose(np.asarray(grad.mu), ndev, rtol=1e-12)
    for name in ("sigma_y", "eta", "m", "kappa", "rho"):
        assert np.all(np.asarray(getattr(grad, name)) == 0.0), name


@pytest.mark.slow
def test_scalar_and_batched_agree():
    """Leading axes broadcast: a single material point (no batch axis) gives the batched answer."""
    f, bbar, params, dt, _ = _cases(3, (0.5,), (1.0,), seed=9)
    bnew, s_new = _return_map_jit(bbar, f, params, dt)
    k = 17
    one = jax.tree_util.tree_map(lambda v: v[k], params)
    b1, s1 = _return_map_jit(bbar[k], f[k], one, dt[k])
    assert b1.shape == (3, 3) and s1.shape == ()
    np.testing.assert_allclose(np.asarray(b1), np.asarray(bnew[k]), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(float(s1), float(s_new[k]), rtol=1e-14)


def test_inverse_cube_root_matches_the_power_to_round_off_and_has_its_derivative():
    """The return map's x^(-1/3) (isochoric part of f, renormalization to det 1; eq. 12, 16), computed as
    exp(-ln(x) / 3): over det values from 1e-300 to 1e300 in float64 (extreme strains give determinants
    far from 1) within 2 (1 + |ln x| / 3) ulp of numpy's 1 / cbrt (exp amplifies the rounding of its
    argument -ln(x) / 3), and its derivative -x^(-4/3) / 3 against the analytic one and a central
    difference to 1e-8 relative."""
    x = np.geomspace(1e-300, 1e300, 6001)
    y = np.asarray(constitutive._inv_cbrt(jnp.asarray(x)))
    ref = 1.0 / np.cbrt(x)  # within 1.5 ulp (x ** (-1/3) is itself off by up to ~60 ulp here)
    ulp = np.abs(y - ref) / (EPS * ref)
    # measured: at most 0.98 (1 + |ln x| / 3) ulp, 5.3 ulp on 1e-6..1e6.
    assert np.max(ulp / (1.0 + np.abs(np.log(x)) / 3.0)) <= 2.0
    x0 = np.array([0.5, 0.97, 1.0, 1.03, 2.0])
    g = np.asarray(jax.vmap(jax.grad(constitutive._inv_cbrt))(jnp.asarray(x0)))
    h = 1e-6 * x0
    fd = central_difference(lambda x: constitutive._inv_cbrt(jnp.asarray(x)), x0, h=h)
    np.testing.assert_allclose(g, -x0 ** (-4.0 / 3.0) / 3.0, rtol=1e-12)
    np.testing.assert_allclose(g, fd, rtol=1e-8)


def test_return_map_renormalizes_to_det_one_at_extreme_strain():
    """Eq. 16 at shear strains of 1e8 and 1e12 in one step: bbar_new has det 1 to round-off (the
    renormalization's cube root of a determinant far outside float32's range stays exact)."""
    params = Params(mu=MU, kappa=KAPPA, sigma_y=20.0, eta=5.0, m=0.5, rho=RHO)
    for g in (1e8, 1e12):
        bnew, s_new = return_map(jnp.eye(3), jnp.array([[1.0, g], [0.0, 1.0]]), params, 1e-3)
        assert abs(float(jnp.linalg.det(bnew)) - 1.0) <= 1e-12 and np.isfinite(float(s_new))


@pytest.mark.slow
def test_float32_rate_with_its_shorter_iteration_budget_is_as_accurate_as_float32_allows(monkeypatch):
    """In float32 the solve runs RETURN_MAP_NEWTON_ITERS_F32 (= 3) Halley steps: over the shaving-cream
    and beyond ranges (m in [0.1, 3], eta in [0, 1e4] Pa s^m, a in [1e-6, 1e3] Pa s, b in [1e-6, 1e4] Pa)
    its rate is within 2e-5 relative of the float64 root wherever that root is a normal float32, and
    no worse than 40 float32 steps give (float32's exp of the log-rate sets the floor: 1.1e-5 measured).
    Catches a budget too short for float32: 2 steps reach 3.4e-5."""
    rng = np.random.default_rng(0)
    n = 200000
    m = 10 ** rng.uniform(-1.0, math.log10(3.0), n)
    eta = np.where(rng.random(n) < 0.1, 0.0, 10 ** rng.uniform(-3, 4, n))
    a = 10 ** rng.uniform(-6, 3, n)
    b = 10 ** rng.uniform(-6, 4, n)
    ref = np.asarray(constitutive.hb_rate(*(jnp.asarray(v) for v in (a, b, eta, m))))
    ok = (ref > 1e-30) & (ref < 1e30)
    assert ok.mean() > 0.9

    def rel_err():
        g = jax.jit(constitutive.hb_rate)(*(jnp.asarray(v, jnp.float32) for v in (a, b, eta, m)))
        return (np.abs(np.asarray(g, np.float64) - ref) / ref)[ok].max()

    err = rel_err()
    monkeypatch.setattr(constitutive, "RETURN_MAP_NEWTON_ITERS_F32", 40)
    jax.clear_caches()  # the budget is read at trace time
    floor = rel_err()
    jax.clear_caches()
    print(f"float32 rate: max relative error {err:.2e} ({floor:.2e} after 40 steps)")
    assert err <= 2e-5 and err <= 1.5 * floor
