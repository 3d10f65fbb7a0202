"""Levenberg-Marquardt with Broyden-updated Jacobians (`broyden_steps`): the secant condition, the same
optimum as exact Jacobians with fewer of them, an exact Jacobian wherever one is reported, resumption."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting.optim as F
from fitting import FitSettings
from fitting.settings import CalibrationError
from fitting.optim._base import state_arrays, state_from_arrays
from fitting.optim._lm import _broyden
from helpers import counted

# Two exponentials with noise: a curved valley (the decay rates trade off), 4 parameters like a material fit.
T = jnp.linspace(0.0, 4.0, 400)
_Y = np.asarray(2.0 * jnp.exp(-1.3 * T) + 0.5 * jnp.exp(-0.2 * T)) + 0.002 * np.random.default_rng(3).standard_normal(400)


def _r(x):
    return x[0] * jnp.exp(-x[1] * T) + x[2] * jnp.exp(-x[3] * T) - _Y


R = jax.jit(_r)
RJ = jax.jit(lambda x: (_r(x), jax.jacfwd(_r)(x)))
X0 = np.array([1.0, 1.0, 1.0, 0.1])


def solve(k, rj=RJ, r=R, **kw):
    return F.least_squares(rj, X0, F.LevenbergMarquardt(broyden_steps=k), with_jac=True, residual=r,
                           max_iterations=200, ftol=1e-14, xtol=1e-12, **kw)


def test_broyden_update_satisfies_the_secant_condition_and_keeps_orthogonal_directions():
    """J_new h = r_new - r exactly, and J_new v = J v for v orthogonal to h (the least change)."""
    rng = np.random.default_rng(0)
    J, r, r_new = rng.standard_normal((7, 3)), rng.standard_normal(7), rng.standard_normal(7)
    h = rng.standard_normal(3)
    v = np.cross(h, rng.standard_normal(3))
    J_new = np.asarray(_broyden(J, r, r_new, h))
    np.testing.assert_allclose(J_new @ h, r_new - r, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J_new @ v, J @ v, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("k", [2, 4, 1000])
def test_same_optimum_as_exact_jacobians_with_fewer_of_them(k):
    """The Broyden path ends at exact LM's minimum (x to 1e-6 relative, loss to 1e-9) and evaluates fewer
    (r, J) pairs; its residual-only trials make up the rest of its evaluations."""
    exact_rj, exact_calls = counted(RJ)
    exact = solve(0, rj=exact_rj)
    rj, j_calls = counted(RJ)
    r, r_calls = counted(R)
    sol = solve(k, rj=rj, r=r)
    assert exact.reason.value.startswith("converged") and sol.reason.value.startswith("converged")
    np.testing.assert_allclose(sol.x, exact.x, rtol=1e-6)
    assert abs(sol.loss - exact.loss) <= 1e-9 * exact.loss
    assert j_calls[0] < exact_calls[0]
    assert r_calls[0] > 0 and sol.evaluations == j_calls[0] + r_calls[0]


def test_a_reported_jacobian_is_exact():
    """A Solution's jacobian is the exact one at x, or None when the last accepted step updated it by
    Broyden's rule; the exact run (k = 0) always reports it."""
    stopped = F.least_squares(RJ, X0, F.LevenbergMarquardt(broyden_steps=1000), with_jac=True, residual=R,
                              max_iterations=3)
    assert stopped.reason == F.Reason.MAX_ITERATIONS and stopped.state.age == 3 and stopped.jacobian is None
    np.testing.assert_array_equal(stopped.residual, np.asarray(R(jnp.asarray(stopped.x))))
    converged = solve(1000)  # the predicted decrease ends the run only with J evaluated exactly
    assert converged.state.age == 0
    for sol in (converged, solve(0)):
        np.testing.assert_array_equal(sol.jacobian, np.asarray(RJ(jnp.asarray(sol.x))[1]))


def test_without_a_residual_oracle_the_jacobians_stay_exact():
    """An objective that cannot evaluate residuals alone gets plain LM: the same path bit for bit."""
    plain = F.least_squares(RJ, X0, F.LevenbergMarquardt(), with_jac=True, max_iterations=50)
    given = F.least_squares(RJ, X0, F.LevenbergMarquardt(broyden_steps=3), with_jac=True, max_iterations=50)
    np.testing.assert_array_equal(plain.history.x, given.history.x)
    assert plain.evaluations == given.evaluations


class Interrupt(Exception):
    pass


def test_interrupted_broyden_fit_resumes_bit_identically(tmp_path):
    """Killed after iteration 5, resumed from the log: the same iterates, loss and (approximate) J as an
    uninterrupted run, with no evaluation repeated (the state's age and J travel in the log)."""
    reference = solve(3)
    assert reference.iterations >= 8
    path = tmp_path / "broyden.h5"

    def stop(info):
        if info.iteration == 5:
            raise Interrupt

    with pytest.raises(Interrupt):
        solve(3, log=path, callback=stop)
    rj, j_calls = counted(RJ)
    r, r_calls = counted(R)
    resumed = solve(3, rj=rj, r=r, log=path, resume=True)
    np.testing.assert_array_equal(resumed.history.x, reference.history.x)
    np.testing.assert_array_equal(resumed.state.jacobian, reference.state.jacobian)
    assert resumed.state.age == reference.state.age
    assert j_calls[0] + r_calls[0] == reference.evaluations - reference.history.evaluations[5]


def test_logs_from_before_the_option_resume_with_exact_jacobians():
    """A state written without `age` reads back as exact (age 0), and LM's config without Broyden
    updates is the one earlier logs recorded (no broyden_steps key)."""
    sol = solve(0)
    arrays = state_arrays(sol.state)
    del arrays["age"]
    assert int(state_from_arrays(F.LMState, arrays).age) == 0
    assert "broyden_steps" not in F.LevenbergMarquardt().config()
    assert F.LevenbergMarquardt(broyden_steps=3).config()["broyden_steps"] == 3


def test_bad_broyden_steps_are_refused_naming_the_field():
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="broyden_steps"):
            F.LevenbergMarquardt(broyden_steps=bad)
        with pytest.raises(CalibrationError, match="broyden_steps"):
            FitSettings(broyden_steps=bad).validate()


@pytest.mark.slow
def test_slump_fit_with_broyden_jacobians_reaches_the_exact_fits_optimum():
    """`calibrate` with broyden_steps 30 on a slump (mu and sigma_y fitted, data made at half the fit's
    dx): the exact-Jacobian fit's optimum to 1e-3 relative and its intervals to 1e-2, with fewer (r, J)
    rollouts; the intervals come from the exact Jacobian at the optimum."""
    from fitting import build_problem, calibrate, synthesize
    from helpers import scene as zoo_scene

    scene = zoo_scene("slump", initial_shape={"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.1]})
    data = synthesize(scene, {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}, dx=0.005, frames=6,
                      duration=0.3, noise=0.02, seed=1)
    results, jacobians = {}, {}
    for k in (0, 30):
        settings = FitSettings(dx=0.01, fixed={"eta": 5.0, "m": 0.6}, starts=1, max_iter=12, dx_check=False,
                               broyden_steps=k).validate()
        problem = build_problem(data, settings)
        problem.residual_and_jacobian, calls = counted(problem.residual_and_jacobian)
        results[k], jacobians[k] = calibrate(data, settings, problem=problem), calls
    exact, broyden = results[0], results[30]
    assert exact.reason.startswith("converged") and broyden.reason.startswith("converged")
    for n in ("mu", "sigma_y"):
        assert abs(broyden.params[n] / exact.params[n] - 1) < 1e-3, (n, broyden.params[n], exact.params[n])
        np.testing.assert_allclose(broyden.interval[n], exact.interval[n], rtol=1e-2)
    assert abs(broyden.loss / exact.loss - 1) < 1e-6
    assert jacobians[30][0] < jacobians[0][0]
