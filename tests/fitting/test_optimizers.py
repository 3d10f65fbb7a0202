"""Optimizers, driver, transforms, Latin hypercube and Gauss-Newton uncertainty (package `fitting`).

Iteration bounds below were measured (float64, CPU) and given ~30% headroom: L-BFGS 2D 41 iterations /
54 evaluations, 4D 37 / 49; Adam(lr=0.1) 2D 1685, 4D 2505; LM 2D 17 / 21, 4D from (-0.5, 0.5, 0.5, 0.5) 25.
"""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting.optim as F
from helpers import counted

ONES_TOL = 1e-5  # |x - 1| at convergence; gtol 1e-6 leaves Adam ~3e-6 away, the others far closer


def rosenbrock(x):
    """Chained Rosenbrock function, minimum 0 at (1, ..., 1)."""
    return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)


def rosenbrock_residuals(x):
    """Residuals whose half squared norm is rosenbrock / 2."""
    return jnp.concatenate([10.0 * (x[1:] - x[:-1] ** 2), 1.0 - x[:-1]])


ROSEN_VG = jax.jit(jax.value_and_grad(rosenbrock))
ROSEN_RJ = jax.jit(F.value_and_jacfwd(rosenbrock_residuals))


# ---------------------------------------------------------------- Rosenbrock


@pytest.mark.parametrize("name, x0, max_iter", [
    ("lbfgs", [-1.2, 1.0], 55), ("adam", [-1.2, 1.0], 2200), ("lm", [-1.2, 1.0], 25),
    ("lbfgs", [-1.2, 1.0, -1.2, 1.0], 50), ("adam", [-1.2, 1.0, -1.2, 1.0], 3300),
    ("lm", [-0.5, 0.5, 0.5, 0.5], 33),
])
def test_rosenbrock_converges_to_ones(name, x0, max_iter):
    """Each optimizer reaches the Rosenbrock minimum (1, ..., 1) within its measured iteration budget,
    and the driver calls the objective exactly `evaluations` times."""
    x0 = jnp.asarray(x0)
    if name == "lm":
        fn, calls = counted(ROSEN_RJ)
        sol = F.least_squares(fn, x0, F.LevenbergMarquardt(), with_jac=True, gtol=1e-12, max_iterations=max_iter)
    else:
        fn, calls = counted(ROSEN_VG)
        opt = F.LBFGS() if name == "lbfgs" else F.Adam(learning_rate=0.1)
        sol = F.minimize(fn, x0, opt, with_grad=True, gtol=1e-6 if name == "adam" else 1e-8,
                         max_iterations=max_iter)
    assert sol.reason == F.Reason.CONVERGED_GTOL, sol.reason
    assert np.max(np.abs(sol.x - 1.0)) < ONES_TOL
    assert sol.evaluations == calls[0]
    assert sol.history.loss.shape == (sol.iterations + 1,)
    if name == "adam":  # one gradient per iteration, nothing else
        assert sol.evaluations == sol.iterations + 1
    if name != "adam":  # monotone methods: every accepted iteration lowers the loss
        assert np.all(np.diff(sol.history.loss) < 0)


def test_lm_stops_at_known_local_minimum_of_4d_rosenbrock():
    """From (-1.2, 1, -1.2, 1) Gauss-Newton descends into the known non-global stationary point of the 4D
    chained Rosenbrock function near (-0.7757, 0.6131, 0.3820, 0.1459): the optimizer must report
    convergence there (gradient ~ 0), not wander; multi-start is the remedy (next test)."""
    sol = F.least_squares(ROSEN_RJ, jnp.array([-1.2, 1.0, -1.2, 1.0]), with_jac=True, gtol=1e-9, ftol=None, xtol=None)
    assert sol.converged
    np.testing.assert_allclose(sol.x, [-0.7757, 0.6131, 0.3820, 0.1459], atol=2e-4)
    assert np.max(np.abs(sol.grad)) < 1e-6


def test_multistart_finds_global_minimum_and_reports_every_start():
    """LM from 6 Latin-hypercube starts in [-2, 2]^4 keeps the best (the global minimum at ones) and
    returns every run."""
    tr = F.ParameterTransform.create([f"x{i}" for i in range(4)])
    starts, unit = F.lhs_starts(tr, 6, seed=3, sample_bounds={f"x{i}": (-2.0, 2.0) for i in range(4)})
    res = F.multistart(lambda x0, **kw: F.least_squares(ROSEN_RJ, x0, with_jac=True, gtol=1e-12, **kw),
                       starts, seed=3, unit=unit)
    assert len(res.solutions) == 6
    assert res.best.loss == min(s.loss for s in res.solutions)
    assert np.max(np.abs(res.best.x - 1.0)) < 1e-8
    assert res.solutions[res.best_index] is res.best
    assert "run" in res.table() and len(res.table().splitlines()) == 7


def test_two_loop_recursion_equals_dense_bfgs_inverse():
    """The L-BFGS two-loop recursion applies the same inverse Hessian as the dense BFGS update
    H <- (I - rho s y^T) H (I - rho y s^T) + rho s s^T from H0 = (s.y / y.y) I of the newest pair, with
    unused history rows ignored (Nocedal & Wright 2006, Alg. 7.4)."""
    from fitting.optim._lbfgs import _two_loop

    rng = np.random.default_rng(2)
    n, pairs, memory = 4, 3, 6
    a = rng.standard_normal((n, n))
    a = a @ a.T + n * np.eye(n)  # SPD Hessian: every pair has s.y > 0
    s = rng.standard_normal((pairs, n))
    y = s @ a
    h = np.eye(n) * (s[-1] @ y[-1]) / (y[-1] @ y[-1])
    for si, yi in zip(s, y):
        rho = 1.0 / (si @ yi)
        v = np.eye(n) - rho * np.outer(yi, si)
        h = v.T @ h @ v + rho * np.outer(si, si)
    g = rng.standard_normal(n)
    pad = np.zeros((memory - pairs, n))
    d = _two_loop(g, np.concatenate([pad, s]), np.concatenate([pad, y]), np.asarray(pairs, np.int32))
    np.testing.assert_allclose(np.asarray(d), -h @ g, rtol=1e-12)


# ---------------------------------------------------------------- least squares with a known answer

T_DECAY = jnp.linspace(0.0, 4.0, 40)  # sample times, s
DECAY_TRUTH = np.array([2.0, 1.3, 0.5])  # amplitude (signal units), rate (1/s), offset (signal units)
DECAY_TR = F.ParameterTransform.create(["A", "k", "c"], positive=["A", "k"])


def decay_residual(z, y):
    """Model A exp(-k t) + c minus data, in fitted coordinates z = (log A, log k, c)."""
    a, k, c = DECAY_TR.to_physical(z)
    return a * jnp.exp(-k * T_DECAY) + c - y


DECAY_RJ = jax.jit(lambda z, y: F.value_and_jacfwd(lambda zz: decay_residual(zz, y))(z))
DECAY_EXACT = np.asarray(decay_residual(DECAY_TR.to_unconstrained(DECAY_TRUTH), 0.0))
DECAY_Z0 = DECAY_TR.to_unconstrained([1.0, 0.5, 0.0])


def test_lm_recovers_exponential_decay_from_exact_data():
    """Exact data: LM recovers (A, k, c) to 1e-8 relative, through a user-supplied (r, J) function and
    through the driver's own forward-mode Jacobian alike."""
    sol = F.least_squares(lambda z: DECAY_RJ(z, DECAY_EXACT), DECAY_Z0, with_jac=True, gtol=1e-13)
    assert sol.converged and sol.iterations <= 12
    theta = np.asarray(DECAY_TR.to_physical(sol.x))
    np.testing.assert_allclose(theta, DECAY_TRUTH, rtol=1e-8)
    auto = F.least_squares(jax.jit(lambda z: decay_residual(z, DECAY_EXACT)), DECAY_Z0, gtol=1e-13)
    np.testing.assert_allclose(np.asarray(DECAY_TR.to_physical(auto.x)), DECAY_TRUTH, rtol=1e-8)
    assert auto.residual.shape == (40,) and auto.jacobian.shape == (40, 3)


def test_gradient_optimizers_run_on_residuals_and_keep_r_and_j():
    """least_squares with L-BFGS minimizes 0.5 |r|^2 with gradient J^T r and returns the (r, J) of the
    accepted point without an extra evaluation."""
    fn, calls = counted(lambda z: DECAY_RJ(z, DECAY_EXACT))
    sol = F.least_squares(fn, DECAY_Z0, F.LBFGS(), with_jac=True, gtol=1e-10, max_iterations=200)
    assert sol.converged
    np.testing.assert_allclose(np.asarray(DECAY_TR.to_physical(sol.x)), DECAY_TRUTH, rtol=1e-6)
    r, jac = DECAY_RJ(jnp.asarray(sol.x), DECAY_EXACT)
    np.testing.assert_array_equal(sol.residual, np.asarray(r))
    np.testing.assert_array_equal(sol.jacobian, np.asarray(jac))
    assert calls[0] == sol.evaluations


def test_interval_coverage_of_noisy_exponential_fits():
    """95% intervals from s^2 (J^T J)^-1 with the Student-t quantile contain the true parameters in
    90%-99% of 200 seeded noisy repetitions (nominal 95%; binomial sd 1.5%): too narrow or too wide an
    interval fails."""
    rng = np.random.default_rng(20240)
    noise = 0.05
    covered = np.zeros(3)
    for _ in range(200):
        y = DECAY_EXACT + noise * rng.standard_normal(DECAY_EXACT.shape[0])
        sol = F.least_squares(lambda z: DECAY_RJ(z, y), DECAY_Z0, with_jac=True, gtol=1e-10)
        assert sol.converged
        unc = F.solution_uncertainty(sol, DECAY_TR)
        covered += unc.contains(DECAY_TRUTH)
    coverage = covered / 200
    assert np.all(coverage >= 0.90) and np.all(coverage <= 0.99), coverage
    assert np.all(unc.interval[:2, 0] > 0)  # positive parameters get positive intervals


def test_student_t_quantile_matches_tables():
    """Two-sided 95% quantiles: t(1) = 12.7062, t(10) = 2.2281, t(inf) -> 1.95996."""
    assert F.student_t_quantile(0.975, 1.0) == pytest.approx(12.706204736174, rel=1e-10)
    assert F.student_t_quantile(0.975, 10.0) == pytest.approx(2.228138851986, rel=1e-10)
    assert F.student_t_quantile(0.975, 1e8) == pytest.approx(1.959963984540, rel=1e-7)


def test_effective_sample_size_inflates_covariance():
    """n_eff = n / 4 (four residuals per independent observation) multiplies the covariance by 4 and
    uses n_eff - p degrees of freedom."""
    rng = np.random.default_rng(1)
    y = DECAY_EXACT + 0.05 * rng.standard_normal(40)
    sol = F.least_squares(lambda z: DECAY_RJ(z, y), DECAY_Z0, with_jac=True, gtol=1e-10)
    full = F.solution_uncertainty(sol, DECAY_TR)
    quarter = F.solution_uncertainty(sol, DECAY_TR, n_eff=10)
    np.testing.assert_allclose(quarter.cov_z, 4.0 * full.cov_z, rtol=1e-12)
    assert quarter.quantile == pytest.approx(F.student_t_quantile(0.975, 7.0))
    # delta method: cov_theta = D cov_z D with D = d theta / d z = (A, k, 1) for (log, log, identity)
    d = np.array([*np.asarray(DECAY_TR.to_physical(sol.x))[:2], 1.0])
    np.testing.assert_allclose(full.cov_theta, full.cov_z * np.outer(d, d), rtol=1e-12)
    with pytest.raises(ValueError, match="n_eff"):
        F.solution_uncertainty(sol, DECAY_TR, n_eff=3)


# ---------------------------------------------------------------- identifiability

HB_TR = F.ParameterTransform.create(["eta", "m"], positive=["eta"], bounds={"m": (0.1, 2.0)})
HB_TRUTH = np.array([5.0, 0.5])  # consistency Pa s^m, exponent


def _hb_fit(rates, seed, noise=0.01):
    """Fit viscous stress eta * rate^m (Pa) to data with relative noise `noise` at the given rates (1/s)."""
    rates = jnp.asarray(rates)
    rng = np.random.default_rng(seed)
    clean = HB_TRUTH[0] * np.asarray(rates) ** HB_TRUTH[1]
    data = clean * (1 + noise * rng.standard_normal(clean.shape[0]))

    def resid(z):
        eta, m = HB_TR.to_physical(z)
        return (eta * rates**m - data) / data

    sol = F.least_squares(jax.jit(resid), HB_TR.to_unconstrained([3.0, 0.8]), gtol=1e-12)
    assert sol.converged
    return F.solution_uncertainty(sol, HB_TR)


def test_eta_and_m_trade_off_when_shear_rates_are_narrow():
    """Stress eta * rate^m seen only at rates 9.5-10.5 1/s with 5% noise: log eta and m move together
    along log(stress) = log eta + m log(10), so the report names eta and m as trading off and as not
    identifiable, while the truth stays inside both (wide) intervals."""
    unc = _hb_fit(np.linspace(9.5, 10.5, 30), seed=0, noise=0.05)
    text = " ".join(unc.messages)
    assert "eta and m trade off" in text
    assert set(unc.non_identifiable) == {"eta", "m"}
    assert unc.correlation[0, 1] < -0.999
    assert np.all(unc.contains(HB_TRUTH))
    assert "trade off" in unc.report()


def test_wide_shear_rates_identify_eta_and_m():
    """The same law seen over rates 0.1-100 1/s determines both: no trade-off, narrow intervals."""
    unc = _hb_fit(np.geomspace(0.1, 100.0, 30), seed=0)
    assert unc.non_identifiable == ()
    assert "identifiable" in unc.messages[0] and "trade off" not in " ".join(unc.messages)
    assert np.all((unc.interval[:, 1] - unc.interval[:, 0]) / HB_TRUTH < 0.05)


def test_exactly_singular_direction_gives_unbounded_intervals():
    """Data depending on a*b only: J^T J is singular, both intervals are (0, inf) and the report says
    raising one while lowering the other leaves the fit unchanged."""
    tr = F.ParameterTransform.create(["a", "b"], positive=["a", "b"])
    t = jnp.linspace(0.0, 1.0, 20)
    y = 6.0 * jnp.exp(-t) + 0.01 * jnp.asarray(np.random.default_rng(0).standard_normal(20))
    z = tr.to_unconstrained([2.0, 3.0])
    r, jac = F.value_and_jacfwd(lambda zz: jnp.prod(tr.to_physical(zz)) * jnp.exp(-t) - y)(z)
    unc = F.gauss_newton_uncertainty(r, jac, z, tr)
    assert set(unc.non_identifiable) == {"a", "b"}
    assert np.all(unc.interval[:, 0] == 0.0) and np.all(np.isinf(unc.interval[:, 1]))
    assert any("raising a while lowering b" in m for m in unc.messages)


# ---------------------------------------------------------------- transforms


def test_transform_round_trip_bounds_and_jacobian():
    """z -> theta -> z is the identity for every kind, bounded kinds stay inside [lo, hi] even for
    saturated z, and `jacobian` equals the diagonal of jax.jacfwd(to_physical)."""
    tr = F.ParameterTransform(names=("a", "b", "c", "d", "e", "f"),
                              kinds=("identity", "log", "bounded", "log_bounded", "lower", "upper"),
                              lower=(-math.inf, 0.0, 0.2, 10.0, 1.0, -math.inf),
                              upper=(math.inf, math.inf, 1.2, 1000.0, math.inf, 3.0))
    rng = np.random.default_rng(5)
    jacfwd = jax.jit(jax.jacfwd(tr.to_physical))
    for _ in range(20):
        z = jnp.asarray(rng.uniform(-4, 4, 6))
        np.testing.assert_allclose(tr.to_unconstrained(tr.to_physical(z)), z, rtol=1e-10, atol=1e-10)
        jac = jacfwd(z)
        np.testing.assert_allclose(tr.jacobian(z), jnp.diagonal(jac), rtol=1e-12)
        np.testing.assert_allclose(jac - jnp.diag(jnp.diagonal(jac)), 0.0, atol=0)
    theta = {"a": -3.0, "b": 2e-3, "c": 0.7, "d": 40.0, "e": 1.5, "f": -2.0}
    np.testing.assert_allclose(tr.to_physical(tr.to_unconstrained(theta)), tr.vector(theta), rtol=1e-12)
    for zz in (-1e3, -40.0, 40.0, 1e3):
        th = np.asarray(tr.to_physical(jnp.full(6, zz)))
        assert 0.2 <= th[2] <= 1.2 and 10.0 <= th[3] <= 1000.0 and th[1] >= 0 and th[4] >= 1.0 and th[5] <= 3.0
    assert tr.coordinate_names()[:3] == ["a", "log(b)", "logit(c)"]


def test_transform_create_and_errors():
    """create() picks log for positive, log_bounded for positive with bounds, bounded for a bounded m;
    out-of-domain values and bad bounds raise ValueError naming the parameter."""
    tr = F.ParameterTransform.create(["mu", "sigma_y", "eta", "m"], positive=["mu", "sigma_y", "eta"],
                                     bounds={"mu": (10.0, 1000.0), "m": (0.2, 1.2)})
    assert tr.kinds == ("log_bounded", "log", "log", "bounded")
    with pytest.raises(ValueError, match="m=1.5"):
        tr.to_unconstrained({"mu": 100.0, "sigma_y": 20.0, "eta": 3.0, "m": 1.5})
    with pytest.raises(ValueError, match="sigma_y"):
        tr.to_unconstrained([100.0, -1.0, 3.0, 0.5])
    with pytest.raises(ValueError, match="mu"):
        F.ParameterTransform.create(["mu"], positive=["mu"], bounds={"mu": (5.0, 1.0)})
    with pytest.raises(ValueError, match="unknown"):
        F.ParameterTransform.create(["mu"], positive=["nu"])


# ---------------------------------------------------------------- Latin hypercube


def test_latin_hypercube_stratification_and_seed():
    """Every axis has exactly one point in each of the n strata [k/n, (k+1)/n); the same seed gives the
    same design, another seed another."""
    n, p = 9, 4
    u = F.latin_hypercube(n, p, seed=11)
    assert u.shape == (n, p) and np.all((u >= 0) & (u < 1))
    for j in range(p):
        np.testing.assert_array_equal(np.sort(np.floor(u[:, j] * n)), np.arange(n))
    np.testing.assert_array_equal(u, F.latin_hypercube(n, p, seed=11))
    assert not np.allclose(u, F.latin_hypercube(n, p, seed=12))


def test_lhs_starts_within_bounds_log_stratified():
    """Starts respect the bounds (less the margin) and a log parameter is stratified in log."""
    tr = F.ParameterTransform.create(["mu", "m"], positive=["mu"], bounds={"mu": (10.0, 1000.0), "m": (0.2, 1.2)})
    z, unit = F.lhs_starts(tr, 8, seed=0, margin=0.05)
    theta = np.stack([np.asarray(tr.to_physical(zz)) for zz in z])
    assert np.all((theta[:, 0] > 10.0) & (theta[:, 0] < 1000.0))
    assert np.all((theta[:, 1] > 0.2) & (theta[:, 1] < 1.2))
    u_mu = (np.log(theta[:, 0]) - np.log(10.0)) / (np.log(1000.0) - np.log(10.0))
    np.testing.assert_allclose(u_mu, 0.05 + 0.9 * unit[:, 0], rtol=1e-9)
    with pytest.raises(ValueError, match="sample_bounds"):
        F.lhs_starts(F.ParameterTransform.create(["x"]), 4, seed=0)


# ---------------------------------------------------------------- non-finite objectives and budgets


def _nan_region(x):
    """Outside the region around the path to (1, 1) where the objective is defined."""
    return (x[0] > 1.5) | (x[1] < -2.0) | (x[1] > 1.45)


NAN_VG = jax.jit(jax.value_and_grad(lambda x: jnp.where(_nan_region(x), jnp.nan, rosenbrock(x))))
NAN_RJ = jax.jit(F.value_and_jacfwd(lambda x: jnp.where(_nan_region(x), jnp.nan, rosenbrock_residuals(x))))


@pytest.mark.parametrize("name", ["lbfgs", "adam", "lm"])
def test_nonfinite_trials_are_rejected_and_fit_converges(name):
    """The objective is NaN in a region the first trial steps enter (a long first L-BFGS step, Adam's
    first step of 0.5, an undamped Gauss-Newton jump): those trials are counted, never accepted, and the
    fit still reaches (1, 1)."""
    x0 = jnp.array([-1.2, 1.0])
    if name == "lm":
        sol = F.least_squares(NAN_RJ, x0, F.LevenbergMarquardt(initial_damping=1e-8), with_jac=True, gtol=1e-12)
    else:
        opt = F.LBFGS(initial_step=5.0) if name == "lbfgs" else F.Adam(learning_rate=0.5)
        sol = F.minimize(NAN_VG, x0, opt, with_grad=True, gtol=1e-8 if name == "lbfgs" else 1e-6,
                         max_iterations=3000)
    assert sol.nonfinite_evaluations > 0
    assert np.all(np.isfinite(sol.history.loss))
    assert not np.any([_nan_region(x) for x in sol.history.x])
    assert sol.converged and np.max(np.abs(sol.x - 1.0)) < ONES_TOL


def test_nonfinite_start_and_minimum_beyond_the_edge():
    """A NaN at x0 ends the fit at once with reason nonfinite. When the loss keeps falling into the NaN
    region ((x - 1)^2, NaN for x > 0), Adam's shrunk steps creep up to the edge and stop there, finite."""
    sol = F.minimize(NAN_VG, jnp.array([2.0, 0.0]), F.LBFGS(), with_grad=True)
    assert sol.reason == F.Reason.NONFINITE and sol.iterations == 0 and sol.evaluations == 1
    edge = jax.jit(jax.value_and_grad(lambda x: jnp.where(x[0] > 0.0, jnp.nan, (x[0] - 1.0) ** 2)))
    sol = F.minimize(edge, jnp.array([-1.0]), F.Adam(learning_rate=0.3), with_grad=True, max_iterations=1000)
    assert sol.converged and sol.nonfinite_evaluations > 0
    assert -1e-3 < float(sol.x[0]) <= 0.0 and np.all(np.isfinite(sol.history.loss))
    assert float(sol.state.lr_scale) < 1e-3


def test_evaluation_and_iteration_budgets():
    """max_evaluations is never exceeded (reason max_evaluations); max_iterations stops at exactly that
    many iterations."""
    fn, calls = counted(ROSEN_VG)
    sol = F.minimize(fn, jnp.array([-1.2, 1.0]), F.LBFGS(), with_grad=True, max_evaluations=17)
    assert sol.reason == F.Reason.MAX_EVALUATIONS and sol.evaluations == calls[0] <= 17
    sol = F.minimize(ROSEN_VG, jnp.array([-1.2, 1.0]), F.Adam(), with_grad=True, max_iterations=12)
    assert sol.reason == F.Reason.MAX_ITERATIONS and sol.iterations == 12


def test_tolerance_reasons():
    """ftol and xtol stop on the quantities they name."""
    x0 = jnp.array([-1.2, 1.0])
    sol = F.minimize(ROSEN_VG, x0, F.LBFGS(), with_grad=True, ftol=1e-3, xtol=None, gtol=None)
    h = sol.history.loss
    assert sol.reason == F.Reason.CONVERGED_FTOL and abs(h[-2] - h[-1]) <= 1e-3 * max(abs(h[-2]), abs(h[-1]))
    sol = F.minimize(ROSEN_VG, x0, F.LBFGS(), with_grad=True, ftol=None, xtol=1e-3, gtol=None)
    dx = np.max(np.abs(sol.history.x[-1] - sol.history.x[-2]))
    assert sol.reason == F.Reason.CONVERGED_XTOL and dx <= 1e-3 * (1e-3 + np.max(np.abs(sol.x)))


def test_driver_input_errors():
    with pytest.raises(ValueError, match="least_squares"):
        F.minimize(ROSEN_VG, jnp.array([0.0, 0.0]), F.LevenbergMarquardt(), with_grad=True)
    with pytest.raises(ValueError, match="1-D"):
        F.minimize(ROSEN_VG, jnp.zeros((2, 2)), F.LBFGS(), with_grad=True)
    with pytest.raises(ValueError, match="gtol"):
        F.minimize(ROSEN_VG, jnp.zeros(2), F.LBFGS(), with_grad=True, gtol=-1.0)
    with pytest.raises(ValueError, match="c1 < c2"):
        F.LBFGS(c1=0.9, c2=0.5)
    with pytest.raises(ValueError, match="learning_rate"):
        F.Adam(learning_rate=0.0)
