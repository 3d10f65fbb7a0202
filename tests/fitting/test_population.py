"""Batched evaluation and the population multi-start.

Contracts: a batch of rollouts (vmapped, with the batch-folding transfers, optionally sharded over
devices) gives each row what the single rollout gives, to round-off; a population of starts follows
each start's sequential path exactly (same iterates, losses and evaluation counts), costs one batched
call per round, resumes from its log, and stops as a whole when one start fails.
"""
import os
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import numpy as np
import pytest

from fitting import FitSettings, build_problem, calibrate, optim, synthesize
from helpers import scene as zoo_scene

# Rosenbrock as residuals, with a second, shallower valley: starts end in different places.
def _residuals(x):
    return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0], 0.3 * np.sin(3.0 * x[0])])


def _jacobian(x):
    return np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0], [0.9 * np.cos(3.0 * x[0]), 0.0]])


def _evaluate(x):
    x = np.asarray(x, np.float64)
    return _residuals(x), _jacobian(x)


def _evaluate_batch(X):
    rows = [_evaluate(x) for x in np.asarray(X)]
    return np.stack([r for r, _ in rows]), np.stack([j for _, j in rows])


STARTS = np.array([[-1.2, 1.0], [0.5, -0.5], [2.0, 2.5], [-0.3, 0.8]])


def _solve(evaluate):
    return lambda x0, **kw: optim.least_squares(evaluate, x0, optim.LevenbergMarquardt(), with_jac=True,
                                                max_iterations=60, **kw)


def test_population_follows_every_start_sequential_path(tmp_path):
    """Same iterates, losses, evaluation counts and stop reasons as the sequential multi-start, with one
    batched call per round (at most the longest start's evaluations), each padded to the full size."""
    seq = optim.multistart(_solve(_evaluate), STARTS, log=tmp_path / "seq.h5")
    calls = []

    def batch(X):
        calls.append(len(X))
        return _evaluate_batch(X)

    oracle = optim.BatchOracle(batch, len(STARTS), sizes=(1, len(STARTS)))
    pop = optim.multistart(_solve(oracle), STARTS, log=tmp_path / "pop.h5", population=oracle)
    for a, b in zip(seq.solutions, pop.solutions):
        np.testing.assert_array_equal(a.history.x, b.history.x)
        np.testing.assert_array_equal(a.history.loss, b.history.loss)
        assert (a.evaluations, a.reason) == (b.evaluations, b.reason)
    evals = [s.evaluations for s in seq.solutions]
    assert len(calls) == max(evals) and oracle.calls == len(calls)
    assert oracle.rows == sum(evals)
    assert set(calls) <= {1, len(STARTS)}
    assert pop.best_index == seq.best_index


def test_batch_rows_come_in_start_order():
    """Whatever order the starts ask in, a batch holds their points in start order (a batch split over
    several processes is only consistent so)."""
    import random
    import threading
    import time
    seen = []

    def batch(X):
        seen.append(np.asarray(X)[:, 0].tolist())
        return (np.asarray(X),)

    oracle = optim.BatchOracle(batch, 5)
    rng = random.Random(3)
    delays = [[rng.random() * 0.02 for _ in range(3)] for _ in range(5)]

    def work(i):
        oracle.bind(i)
        try:
            for d in delays[i]:
                time.sleep(d)
                assert oracle(np.array([float(i)]))[0][0] == i
        finally:
            oracle.leave()

    threads = [threading.Thread(target=work, args=(i,)) for i in range(5)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen == [[0.0, 1.0, 2.0, 3.0, 4.0]] * 3


def test_population_resumes_from_its_log(tmp_path):
    """A population stopped by a callback after 3 iterations of start 2 resumes from the log to the
    uninterrupted result, iterate for iterate."""
    log = tmp_path / "fit.h5"
    full = optim.multistart(_solve(_evaluate), STARTS)

    def stop(info):
        if info.run == 2 and info.iteration == 3:
            raise KeyboardInterrupt

    oracle = optim.BatchOracle(_evaluate_batch, len(STARTS))
    solve = lambda x0, **kw: optim.least_squares(oracle, x0, optim.LevenbergMarquardt(), with_jac=True,
                                                 max_iterations=60, callback=stop, **kw)
    with pytest.raises(KeyboardInterrupt):
        optim.multistart(solve, STARTS, log=log, population=oracle)
    oracle = optim.BatchOracle(_evaluate_batch, len(STARTS))
    resumed = optim.multistart(_solve(oracle), STARTS, log=log, resume=True, population=oracle)
    for a, b in zip(full.solutions, resumed.solutions):
        np.testing.assert_array_equal(a.history.x, b.history.x)
        assert a.reason == b.reason


def test_population_stops_when_the_batched_evaluation_fails():
    """An exception in the batched function reaches the caller (not a hang), as the original error."""

    def broken(X):
        raise FloatingPointError("bad batch")

    oracle = optim.BatchOracle(broken, 3)
    with pytest.raises(optim.PopulationStopped) as info:
        optim.multistart(_solve(oracle), STARTS[:3], population=oracle)
    assert isinstance(info.value.__cause__, FloatingPointError)


SLUMP = zoo_scene("slump", initial_shape={"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.1]})
TRUTH = {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}


@pytest.fixture(scope="module")
def slump_problem():
    data = synthesize(SLUMP, TRUTH, dx=0.01, frames=4, duration=0.12, noise=0.0, seed=1)
    settings = FitSettings(dx=0.01, fixed={"eta": 5.0}, starts=3, max_iter=3, dx_check=False)
    return data, settings, build_problem(data, settings)


@pytest.mark.slow
def test_batched_jacobian_equals_single_rollouts(slump_problem):
    """residual_batch and residual_and_jacobian_batch (3 points x 3 jvp rollouts, folded transfers) equal
    the single-point residual and forward-mode Jacobian to 1e-12 relative."""
    _, _, pb = slump_problem
    Z = jnp.stack([pb.transform.to_unconstrained({"mu": mu, "sigma_y": 20.0, "m": 0.6}) for mu in (90.0, 150.0, 260.0)])
    R = np.asarray(pb.residual_batch(Z))
    RB, JB = (np.asarray(a) for a in pb.residual_and_jacobian_batch(Z))
    for b in range(3):
        r, J = (np.asarray(a) for a in pb.residual_and_jacobian(Z[b]))
        scale = np.max(np.abs(r))
        assert np.max(np.abs(R[b] - r)) <= 1e-12 * scale
        assert np.max(np.abs(RB[b] - r)) <= 1e-12 * scale
        assert np.max(np.abs(JB[b] - J)) <= 1e-12 * np.max(np.abs(J))
        assert np.max(np.abs(J)) > 0


@pytest.mark.slow
def test_population_fit_equals_sequential_fit(slump_problem):
    """`calibrate` with population=True returns the sequential fit's parameters, losses and runs."""
    data, settings, pb = slump_problem
    seq = calibrate(data, settings, problem=pb)
    pop = calibrate(data, FitSettings(**{**settings.__dict__, "population": True}), problem=pb)
    for n in seq.fitted:
        assert pop.params[n] == pytest.approx(seq.params[n], rel=1e-10)
    assert [r["iterations"] for r in pop.runs] == [r["iterations"] for r in seq.runs]
    assert [r["loss"] for r in pop.runs] == pytest.approx([r["loss"] for r in seq.runs], rel=1e-10)


SHARDED = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, "tests")
    from fitting import FitSettings, calibrate, synthesize
    from helpers import scene
    spec = scene("slump", initial_shape={"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.1]})
    data = synthesize(spec, {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}, dx=0.01, frames=4,
                      duration=0.12, noise=0.0, seed=1)
    out = {}
    for devices in (1, 2):
        s = FitSettings(dx=0.01, fixed={"eta": 5.0}, starts=3, max_iter=3, dx_check=False, population=True,
                        devices=devices)
        fit = calibrate(data, s)
        out[devices] = dict(params=fit.params, losses=[r["loss"] for r in fit.runs], devices=len(jax.devices()))
    print(json.dumps(out))
""")


@pytest.mark.slow
def test_sharded_population_fit_equals_single_device_fit():
    """With two host CPU devices, the population's batch split over both gives the one-device fit to 1e-10."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    proc = subprocess.run([sys.executable, "-c", SHARDED], cwd=root, env=env, capture_output=True, text=True,
                          timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    import json
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    one, two = out["1"], out["2"]
    assert two["devices"] == 2
    for n, v in one["params"].items():
        assert two["params"][n] == pytest.approx(v, rel=1e-10, abs=1e-12)
    assert two["losses"] == pytest.approx(one["losses"], rel=1e-10)


def _free_port() -> int:
    import socket
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_process_fit_equals_single_process_fit(tmp_path):
    """`jaxfoam fit --coordinator` over two processes on one machine (one CPU device each, collectives
    over gloo) writes the single-process population fit's parameters to 1e-10; process 1 writes no result."""
    import json
    data = synthesize(SLUMP, TRUTH, dx=0.01, frames=4, duration=0.12, noise=0.0, seed=1)
    path = tmp_path / "slump.h5"
    data.write(path)
    common = [sys.executable, "-m", "jaxfoam", "fit", str(path), "--dx", "0.01", "--fix", "eta=5", "--starts", "3",
              "--max-iter", "3", "--no-dx-check", "--no-plots", "--population", "on"]
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    single = subprocess.run(common + ["--out", str(tmp_path / "one.json")], cwd=root, env=env, capture_output=True,
                            text=True, timeout=1200)
    assert single.returncode == 0, single.stderr[-3000:]
    port = _free_port()
    procs = [subprocess.Popen(common + ["--out", str(tmp_path / f"two{i}.json"), "--coordinator", f"localhost:{port}",
                                        "--num-processes", "2", "--process-id", str(i)], cwd=root, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=1200) for p in procs]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    assert "2 device(s)" in outs[0][0]
    assert not (tmp_path / "two1.json").exists() and (tmp_path / "two1.fitlog.p1.h5").exists()
    one = json.loads((tmp_path / "one.json").read_text())
    two = json.loads((tmp_path / "two0.json").read_text())
    for n in one["fitted"]:
        assert two["params"][n] == pytest.approx(one["params"][n], rel=1e-10)
