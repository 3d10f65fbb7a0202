"""HDF5 fit log: a fit interrupted after k iterations resumes bit-identically and loses no iteration."""
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting.optim as F
from fitting.optim.fitlog import ROW_LEAF_MAX
from helpers import counted


def rosenbrock(x):
    return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)


ROSEN_VG = jax.jit(jax.value_and_grad(rosenbrock))
ROSEN_RJ = jax.jit(F.value_and_jacfwd(lambda x: jnp.concatenate([10.0 * (x[1:] - x[:-1] ** 2), 1.0 - x[:-1]])))
X0 = np.array([-1.2, 1.0])

# Exponential decay sampled at 2000 times: the LM Jacobian (2000 x 3) is larger than ROW_LEAF_MAX, so it
# goes through the double-buffered slots of the log.
T_LONG = jnp.linspace(0.0, 4.0, 2000)
DECAY_TR = F.ParameterTransform.create(["A", "k", "c"], positive=["A", "k"])
_Y = np.asarray(2.0 * jnp.exp(-1.3 * T_LONG) + 0.5) + 0.02 * np.random.default_rng(7).standard_normal(2000)
DECAY_RJ = jax.jit(F.value_and_jacfwd(lambda z: (lambda a, k, c: a * jnp.exp(-k * T_LONG) + c - _Y)(
    *DECAY_TR.to_physical(z))))
DECAY_Z0 = np.asarray(DECAY_TR.to_unconstrained([1.0, 0.5, 0.0]))


class Interrupt(Exception):
    """Raised from a callback to kill a fit after a given iteration."""


def interrupt_after(k):
    def callback(info):
        if info.iteration == k:
            raise Interrupt

    return callback


CASES = {
    "lm": lambda fn, **kw: F.least_squares(fn, DECAY_Z0, F.LevenbergMarquardt(), with_jac=True, gtol=1e-12, **kw),
    "lbfgs": lambda fn, **kw: F.minimize(fn, X0, F.LBFGS(), with_grad=True, gtol=1e-8, **kw),
    "adam": lambda fn, **kw: F.minimize(fn, X0, F.Adam(learning_rate=0.1), with_grad=True, max_iterations=150, **kw),
}
ORACLES = {"lm": DECAY_RJ, "lbfgs": ROSEN_VG, "adam": ROSEN_VG}


def assert_same_solution(a, b):
    np.testing.assert_array_equal(a.x, b.x)
    assert a.loss == b.loss and a.reason == b.reason
    assert a.iterations == b.iterations and a.evaluations == b.evaluations
    np.testing.assert_array_equal(a.grad, b.grad)
    for field in ("loss", "x", "evaluations", "nonfinite"):
        np.testing.assert_array_equal(getattr(a.history, field), getattr(b.history, field))
    for x, y in zip(jax.tree_util.tree_leaves(a.state), jax.tree_util.tree_leaves(b.state)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("name", ["lm", "lbfgs", "adam"])
def test_interrupted_fit_resumes_bit_identically(name, tmp_path):
    """Kill the fit from the callback after iteration 4, resume from the log: the result equals an
    uninterrupted fit bit for bit, the log held all 5 rows (iterations 0-4), and the resumed part made
    exactly the evaluations the uninterrupted fit made after iteration 4 (none repeated)."""
    run, oracle = CASES[name], ORACLES[name]
    reference = run(oracle)
    assert reference.iterations >= 8  # the interruption falls mid-fit (LM takes 9, L-BFGS 41, Adam 150)
    path = tmp_path / f"{name}.h5"
    with pytest.raises(Interrupt):
        run(oracle, log=path, callback=interrupt_after(4))
    logged = F.read_fitlog(path)["runs"][0]
    assert logged["loss"].shape == (5,) and logged["finished"] is None
    np.testing.assert_array_equal(logged["loss"], reference.history.loss[:5])
    fn, calls = counted(oracle)
    resumed = run(fn, log=path, resume=True)
    assert_same_solution(resumed, reference)
    assert calls[0] == reference.evaluations - reference.history.evaluations[4]
    if name == "lm":
        assert reference.jacobian.size > ROW_LEAF_MAX  # exercised the slot path
        np.testing.assert_array_equal(resumed.jacobian, reference.jacobian)


def test_finished_run_is_read_back_without_evaluating(tmp_path):
    """Resuming a finished fit returns its solution from the log with zero objective calls."""
    path = tmp_path / "done.h5"
    first = CASES["lm"](DECAY_RJ, log=path)
    fn, calls = counted(DECAY_RJ)
    again = CASES["lm"](fn, log=path, resume=True)
    assert calls[0] == 0
    assert_same_solution(again, first)
    assert again.wall_time == first.wall_time


def test_uncommitted_partial_row_is_ignored(tmp_path):
    """A kill in the middle of writing a row leaves datasets longer than the committed `rows` count;
    resume uses only committed rows and still reproduces the uninterrupted fit."""
    reference = CASES["lbfgs"](ROSEN_VG)
    path = tmp_path / "torn.h5"
    with pytest.raises(Interrupt):
        CASES["lbfgs"](ROSEN_VG, log=path, callback=interrupt_after(5))
    with h5py.File(path, "a") as f:
        g = f["runs/0000"]
        for name in ("x", "loss", "evaluations"):
            ds = g[name]
            ds.resize(ds.shape[0] + 1, axis=0)
            ds[-1] = np.nan if ds.dtype.kind == "f" else -1
    assert_same_solution(CASES["lbfgs"](ROSEN_VG, log=path, resume=True), reference)


def test_resume_with_a_larger_budget_continues(tmp_path):
    """A fit stopped by max_iterations=8 and resumed with max_iterations=40 equals a fit run with 40."""
    path = tmp_path / "budget.h5"
    short = F.minimize(ROSEN_VG, X0, F.LBFGS(), with_grad=True, gtol=1e-8, max_iterations=8, log=path)
    assert short.reason == F.Reason.MAX_ITERATIONS
    longer = F.minimize(ROSEN_VG, X0, F.LBFGS(), with_grad=True, gtol=1e-8, max_iterations=40, log=path, resume=True)
    direct = F.minimize(ROSEN_VG, X0, F.LBFGS(), with_grad=True, gtol=1e-8, max_iterations=40)
    assert_same_solution(longer, direct)


def test_resume_refuses_a_different_fit(tmp_path):
    """The log checks the starting point and the optimizer settings before resuming."""
    path = tmp_path / "other.h5"
    with pytest.raises(Interrupt):
        F.minimize(ROSEN_VG, X0, F.LBFGS(), with_grad=True, log=path, callback=interrupt_after(2))
    with pytest.raises(F.FitLogError, match="x0"):
        F.minimize(ROSEN_VG, X0 + 0.1, F.LBFGS(), with_grad=True, log=path, resume=True)
    with pytest.raises(F.FitLogError, match="optimizer"):
        F.minimize(ROSEN_VG, X0, F.LBFGS(history=5), with_grad=True, log=path, resume=True)
    with pytest.raises(F.FitLogError, match="format"):
        bad = tmp_path / "not_a_log.h5"
        with h5py.File(bad, "w") as f:
            f.attrs["format"] = "something else"
        F.minimize(ROSEN_VG, X0, F.LBFGS(), with_grad=True, log=bad)


def test_multistart_resumes_mid_run(tmp_path):
    """Three LM starts; the fit is killed in run 1 at iteration 3. Resuming reads run 0 back without
    evaluating, finishes run 1 and runs 2: every solution equals the uninterrupted multi-start."""
    tr = F.ParameterTransform.create(["x", "y"])
    bounds = {"x": (-2.0, 2.0), "y": (-1.0, 3.0)}
    starts, unit = F.lhs_starts(tr, 3, seed=4, sample_bounds=bounds)

    def solver(fn, callback=None):
        def solve(x0, **kw):
            cb = callback if kw["run"] == 1 else None
            return F.least_squares(fn, x0, with_jac=True, gtol=1e-12, callback=cb, **kw)
        return solve

    reference = F.multistart(solver(ROSEN_RJ), starts, seed=4, unit=unit)
    path = tmp_path / "multi.h5"
    with pytest.raises(Interrupt):
        F.multistart(solver(ROSEN_RJ, interrupt_after(3)), starts, log=path, seed=4, unit=unit)
    fn, calls = counted(ROSEN_RJ)
    resumed = F.multistart(solver(fn), starts, log=path, resume=True, seed=4, unit=unit)
    for a, b in zip(resumed.solutions, reference.solutions):
        assert_same_solution(a, b)
    r1 = reference.solutions[1]
    assert calls[0] == (r1.evaluations - r1.history.evaluations[3]) + reference.solutions[2].evaluations
    assert resumed.best_index == reference.best_index
    logged = F.read_fitlog(path)
    np.testing.assert_array_equal(logged["multistart"][0], starts)
    assert logged["multistart"][2] == 4 and sorted(logged["runs"]) == [0, 1, 2]
    with pytest.raises(F.FitLogError, match="seed"):
        F.multistart(solver(ROSEN_RJ), starts, log=path, resume=True, seed=5, unit=unit)


def test_fresh_fit_overwrites_the_log(tmp_path):
    """Without resume, an existing log is started afresh (row count = the new fit's iterations + 1)."""
    path = tmp_path / "fresh.h5"
    F.minimize(ROSEN_VG, X0, F.LBFGS(), with_grad=True, log=path)
    sol = F.minimize(ROSEN_VG, X0, F.Adam(learning_rate=0.1), with_grad=True, max_iterations=5, log=path)
    data = F.read_fitlog(path)["runs"][0]
    assert data["loss"].shape == (sol.iterations + 1,) and data["meta"]["optimizer"]["name"] == "Adam"
    assert set(data["state"]) == {"loss", "grad", "m", "v", "t", "lr_scale", "status"}


def slowed(fn, seconds):
    """The oracle `fn`, taking at least `seconds` per call (a stand-in for an expensive rollout)."""
    import time

    def wrapped(x):
        time.sleep(seconds)
        return fn(x)

    return wrapped


def test_time_budget_stops_a_multistart_and_resume_finishes_it_bit_identically(tmp_path):
    """Three LM starts on Rosenbrock residuals at >= 20 ms per evaluation under a 0.15 s budget (the
    uninterrupted fit makes dozens of evaluations): the first start stops with reason MAX_TIME, a start
    the budget left no time for is not evaluated (loss inf, empty history, nothing logged), and the
    elapsed time overruns the budget by at most about one iteration. Resumed without a budget, every
    start ends exactly as in the uninterrupted multi-start, and no evaluation is repeated."""
    import time

    tr = F.ParameterTransform.create(["x", "y"])
    starts, unit = F.lhs_starts(tr, 3, seed=4, sample_bounds={"x": (-2.0, 2.0), "y": (-1.0, 3.0)})

    def solver(fn):
        return lambda x0, **kw: F.least_squares(fn, x0, with_jac=True, gtol=1e-12, **kw)

    reference = F.multistart(solver(ROSEN_RJ), starts, seed=4, unit=unit)
    assert sum(s.evaluations for s in reference.solutions) >= 20
    path = tmp_path / "budget.h5"
    t0 = time.perf_counter()
    cut = F.multistart(solver(slowed(ROSEN_RJ, 0.02)), starts, log=path, seed=4, unit=unit, max_time=0.15)
    elapsed = time.perf_counter() - t0
    assert cut.solutions[0].reason == F.Reason.MAX_TIME
    assert cut.solutions[0].iterations < reference.solutions[0].iterations
    assert elapsed < 0.15 + 0.5  # one iteration (a few 20 ms evaluations) past the budget, not a whole start
    logged = F.read_fitlog(path)["runs"]
    for i, s in enumerate(cut.solutions):
        if len(s.history.loss) == 0:  # not started: nothing evaluated or logged
            assert s.reason == F.Reason.MAX_TIME and s.loss == np.inf and s.evaluations == 0 and i not in logged
        else:
            np.testing.assert_array_equal(s.history.loss, reference.solutions[i].history.loss[:len(s.history.loss)])
    fn, calls = counted(ROSEN_RJ)
    resumed = F.multistart(solver(fn), starts, log=path, resume=True, seed=4, unit=unit)
    for a, b in zip(resumed.solutions, reference.solutions):
        assert_same_solution(a, b)
    assert calls[0] == sum(r.evaluations for r in reference.solutions) - sum(s.evaluations for s in cut.solutions)


def test_zero_time_budget_evaluates_nothing_and_bad_budgets_are_refused(tmp_path):
    """max_time = 0 evaluates and logs nothing; a multi-start whose budget the first evaluation spends
    leaves its later starts unrun; negative, non-finite and non-numeric budgets are refused."""
    fn, calls = counted(ROSEN_VG)
    sol = F.minimize(fn, X0, F.LBFGS(), with_grad=True, max_time=0.0, log=tmp_path / "none.h5")
    assert calls[0] == 0 and sol.reason == F.Reason.MAX_TIME and sol.loss == np.inf
    assert sol.history.x.shape == (0, 2) and F.read_fitlog(tmp_path / "none.h5")["runs"] == {}
    # A budget spent by the first start's first evaluation (>= 20 ms against 1 ms): that start stops
    # at its starting point, the two after it are not run.
    tr = F.ParameterTransform.create(["x", "y"])
    starts, _ = F.lhs_starts(tr, 3, seed=4, sample_bounds={"x": (-2.0, 2.0), "y": (-1.0, 3.0)})
    fn, calls = counted(slowed(ROSEN_RJ, 0.02))
    ms = F.multistart(lambda x0, **kw: F.least_squares(fn, x0, with_jac=True, **kw), starts, max_time=0.001)
    assert calls[0] == 1 and [s.reason for s in ms.solutions] == [F.Reason.MAX_TIME] * 3
    assert [len(s.history.loss) for s in ms.solutions] == [1, 0, 0] and ms.best_index == 0
    for bad in (-1.0, float("nan"), float("inf"), "10"):
        with pytest.raises(ValueError, match="max_time"):
            F.minimize(ROSEN_VG, X0, F.LBFGS(), with_grad=True, max_time=bad)
    with pytest.raises(ValueError, match="max_time"):
        F.multistart(lambda x0, **kw: None, np.zeros((1, 2)), max_time=-1.0)


# ------------------------------------------------------------------------------------------------
# Damaged logs are refused (FitLogError naming the file), never resumed to another answer
# ------------------------------------------------------------------------------------------------

def _killed_lm_log(path, k=3):
    with pytest.raises(Interrupt):
        CASES["lm"](DECAY_RJ, log=path, callback=interrupt_after(k))
    return path


def _set_x(f, row, value):
    ds = f["runs/0000/x"]
    x = ds[row]
    x[0] = value
    ds[row] = x


DAMAGES = {
    # name: (edit of the file, words of the error)
    "truncated to 60%": (lambda p: p.write_bytes(p.read_bytes()[:int(0.6 * p.stat().st_size)]),
                         ["cannot be read as a fit log"]),
    "a text file": (lambda p: p.write_text("not a log\n"), ["cannot be read as a fit log"]),
    "claims 99 rows": (lambda p: _h5(p, lambda f: f["runs/0000"].attrs.__setitem__("rows", 99)),
                       ["claims 99 committed rows", "holds 4"]),
    "last parameters altered": (lambda p: _h5(p, lambda f: _set_x(f, 3, 0.123)), ["row 3", "checksum"]),
    "last parameters NaN": (lambda p: _h5(p, lambda f: _set_x(f, 3, np.nan)), ["row 3", "checksum"]),
    "checksums removed": (lambda p: _h5(p, lambda f: f["runs/0000"].__delitem__("checksum")), ["checksums"]),
    "Jacobian slot altered": (lambda p: _h5(p, _alter_slot), ["slot", "checksum"]),
}


def _alter_slot(f):
    """Change one element of a large leaf in the slot of the last committed row (row 3: slot 1)."""
    slot = f["runs/0000/slots/1"]
    ds = slot[sorted(slot)[0]]
    a = ds[()]
    a.flat[0] += 1.0
    ds[...] = a


def _h5(path, edit):
    with h5py.File(path, "a") as f:
        edit(f)


@pytest.mark.parametrize("name", sorted(DAMAGES))
def test_damaged_log_is_refused(tmp_path, name):
    edit, words = DAMAGES[name]
    path = _killed_lm_log(tmp_path / "fit.h5")
    edit(path)
    with pytest.raises(F.FitLogError) as info:
        CASES["lm"](DECAY_RJ, log=path, resume=True)
    msg = str(info.value)
    assert str(path) in msg and all(w in msg for w in words), msg
    assert "without --resume" in msg or "another log" in msg


def test_nan_parameters_with_a_matching_checksum_are_refused(tmp_path):
    """Even a row whose checksum was recomputed cannot resume from non-finite parameters."""
    from fitting.optim.fitlog import _digest

    path = _killed_lm_log(tmp_path / "fit.h5")

    def edit(f):
        g = f["runs/0000"]
        _set_x(f, 3, np.nan)
        names = ["iteration", "x", "loss", "evaluations", "nonfinite", "time"] + [f"state/{n}" for n in g["state"]]
        g["checksum"][3] = _digest(sorted((n, g[n][3]) for n in names))

    _h5(path, edit)
    with pytest.raises(F.FitLogError, match=r"row 3 holds non-finite parameters"):
        CASES["lm"](DECAY_RJ, log=path, resume=True)


def test_log_rows_carry_checksums_and_an_intact_log_resumes(tmp_path):
    path = _killed_lm_log(tmp_path / "fit.h5")
    with h5py.File(path, "r") as f:
        assert f.attrs["version"] == 2 and f["runs/0000/checksum"].shape == (4,)
        assert np.all(f["runs/0000/checksum"][()] != 0)
    ref = CASES["lm"](DECAY_RJ)
    assert_same_solution(CASES["lm"](DECAY_RJ, log=path, resume=True), ref)
