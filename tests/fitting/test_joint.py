"""Joint fits of one material to several recordings (`fitting.joint`, `jaxfoam fit a.h5 b.h5`).

Contracts: the joint residual is the recordings' residuals stacked (each over its noise scale) and its
Jacobian puts each recording's columns under the shared material and its own nuisance coordinates; the
information shares sum to 1 per parameter; densities must agree; a joint fit of a slump and a drop of
the same foam recovers the fitted parameter, writes its report, and resumes to the same result.
"""
import dataclasses
import json

import numpy as np
import pytest

from fitting import FitSettings, CalibrationError, synthesize
from fitting.joint import build_joint, calibrate_joint, joint_grid_error
from helpers import edited, scene as zoo_scene
from jaxfoam.cli import main

TRUTH = {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}
SLUMP = zoo_scene("slump", initial_shape={"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.1]})
DROP = edited(zoo_scene("drop"), ("kappa",), 3000.0)
SETTINGS = FitSettings(dx=0.01, fixed={"mu": 150.0, "eta": 5.0, "m": 0.6}, starts=1, max_iter=6, dx_check=False)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("joint")
    paths = []
    for name, spec, duration in (("slump", SLUMP, 0.2), ("drop", DROP, 0.3)):
        data = synthesize(spec, TRUTH, dx=0.005, frames=4, duration=duration, noise=0.01, seed=2)
        path = d / f"{name}.h5"
        data.write(path)
        paths.append(path)
    return paths


@pytest.mark.slow
def test_joint_residual_stacks_the_recordings(recordings):
    """r and J of the joint problem are the per-recording ones, stacked, over their scales, in the columns
    of the shared parameter and of each recording's own friction."""
    settings = FitSettings(dx=0.01, fixed={"mu": 150.0, "eta": 5.0, "m": 0.6}, fit_also=("friction",),
                           starts=1, dx_check=False)
    joint = build_joint(recordings, settings)
    assert joint.names == ("sigma_y", "friction[0]", "friction[1]")
    joint.set_scales([2.0, 0.5])
    z = np.asarray(joint.transform.to_unconstrained({"sigma_y": 20.0, "friction[0]": 0.4, "friction[1]": 0.6}))
    r, J = joint.residual_and_jacobian(z)
    (r0, J0), (r1, J1) = joint.parts(z)
    n0 = r0.shape[0]
    np.testing.assert_allclose(r[:n0], r0 / 2.0, rtol=0, atol=0)
    np.testing.assert_allclose(r[n0:], r1 / 0.5, rtol=0, atol=0)
    np.testing.assert_allclose(J[:n0, [0, 1]], J0 / 2.0, rtol=0, atol=0)
    np.testing.assert_allclose(J[n0:, [0, 2]], J1 / 0.5, rtol=0, atol=0)
    assert np.all(J[:n0, 2] == 0) and np.all(J[n0:, 1] == 0)
    assert np.max(np.abs(J0[:, 1])) > 0 and np.max(np.abs(J1[:, 1])) > 0
    # the residual alone (Broyden-updated LM's trials) is the stacked, scaled r, to round-off
    np.testing.assert_allclose(joint.residual(z), r, rtol=1e-9, atol=1e-13)  # another compiled program


@pytest.mark.slow
def test_joint_fit_with_broyden_jacobians_reaches_the_exact_joint_optimum(recordings):
    """calibrate_joint with broyden_steps 30: the exact-Jacobian joint fit's sigma_y to 1e-3 and its
    interval to 1e-2 (both stages run their trials on residuals alone)."""
    exact = calibrate_joint(recordings, dataclasses.replace(SETTINGS, max_iter=12))
    broyden = calibrate_joint(recordings, dataclasses.replace(SETTINGS, max_iter=12, broyden_steps=30))
    assert abs(broyden.params["sigma_y"] / exact.params["sigma_y"] - 1) < 1e-3
    np.testing.assert_allclose(broyden.interval["sigma_y"], exact.interval["sigma_y"], rtol=1e-2)


def test_joint_refuses_recordings_of_different_density(tmp_path):
    """Two densities are two materials: refused before any simulator is built, naming both values."""
    paths = []
    for rho in (80.0, 120.0):
        path = tmp_path / f"drop{rho:g}.h5"
        synthesize(edited(DROP, ("density",), rho), TRUTH, dx=0.02, frames=2, duration=0.05, seed=0).write(path)
        paths.append(path)
    with pytest.raises(CalibrationError, match=r"density: .*\[80.0, 120.0\]"):
        build_joint(paths, SETTINGS)


@pytest.mark.slow
def test_joint_fit_recovers_yield_stress_and_resumes(recordings, tmp_path):
    """`jaxfoam fit slump.h5 drop.h5` fits sigma_y within 15% of the truth (each 1 cm grid's bias is
    about 11%), with shares of the information summing to 1, per-recording scales and goodness of fit;
    a fit stopped after its first start resumes to the same numbers."""
    out = tmp_path / "joint.json"
    args = ["fit", *map(str, recordings), "--out", str(out), "--dx", "0.01", "--fix", "mu=150,eta=5,m=0.6",
            "--starts", "1", "--max-iter", "6", "--no-dx-check", "--no-plots"]
    assert main(args) == 0
    fit = json.loads(out.read_text())
    assert fit["format"] == "jaxfoam-joint-fit"
    assert fit["params"]["sigma_y"] == pytest.approx(25.0, rel=0.15)
    lo, hi = fit["interval"]["sigma_y"]
    assert lo < fit["params"]["sigma_y"] < hi
    assert sum(fit["information_share"]["sigma_y"]) == pytest.approx(1.0, abs=1e-12)
    assert all(0 < s < 1 for s in fit["information_share"]["sigma_y"])
    assert len(fit["recordings"]) == 2 and all(r["scale"] > 0 for r in fit["recordings"])
    assert np.prod([r["scale"] for r in fit["recordings"]]) == pytest.approx(1.0, rel=1e-9)
    # A resumed finished log reads every run back: the same result.
    log = tmp_path / "joint.fitlog.h5"
    again = tmp_path / "again.json"
    assert main(args + ["--resume"]) == 0 and log.exists()
    assert main(["fit", *map(str, recordings), "--out", str(again), "--log", str(log), "--resume", *args[5:]]) == 0
    resumed = json.loads(again.read_text())
    assert resumed["params"]["sigma_y"] == pytest.approx(fit["params"]["sigma_y"], rel=1e-12)


@pytest.mark.slow
def test_joint_population_equals_joint_in_turn(recordings):
    """The joint fit's starts as a population (each recording's batch one program) give the in-turn fit."""
    settings = FitSettings(dx=0.01, fixed={"mu": 150.0, "eta": 5.0}, starts=2, max_iter=2, dx_check=False)
    joint = build_joint(recordings, settings)
    seq = calibrate_joint(None, settings, joint=joint)
    pop = calibrate_joint(None, FitSettings(**{**settings.__dict__, "population": True}), joint=joint)
    for n in seq.fitted:
        assert pop.params[n] == pytest.approx(seq.params[n], rel=1e-10)
    assert [r["iterations"] for r in pop.runs] == [r["iterations"] for r in seq.runs]


def _joint_of(index, scales, names):
    """A stand-in JointProblem with only what `joint_grid_error` reads (its stack, index and scales)."""
    from types import SimpleNamespace
    from fitting.joint import JointProblem
    ns = SimpleNamespace(names=tuple(names), index=[np.asarray(i, int) for i in index],
                         scales=np.asarray(scales, np.float64))
    ns.stack = lambda parts: JointProblem.stack(ns, parts)
    return ns


def test_joint_grid_error_of_one_recording_is_the_single_fits():
    """A joint of one recording holding every parameter has the single fit's numerical error
    (check_error of its grid shift), whatever its noise scale."""
    from fitting.check import check_error
    rng = np.random.default_rng(0)
    J = rng.normal(size=(40, 3))
    shift = np.array([0.3, -0.05, 0.01])
    joint = _joint_of([[0, 1, 2]], [3.0], ["mu", "sigma_y", "eta"])
    err = joint_grid_error(joint, [(rng.normal(size=40), J)], [shift])
    np.testing.assert_allclose(err, check_error([shift])[0], rtol=1e-12)


def test_joint_grid_error_weights_shifts_by_information():
    """Two recordings sharing one parameter: its joint move is their shifts averaged with the weights of
    their noise-scaled Fisher information, |J_i|^2 / s_i^2, then extrapolated as a single fit's."""
    from fitting.check import check_error
    J0, J1 = np.full((10, 1), 2.0), np.full((30, 1), 0.5)
    scales = [1.0, 0.5]
    f0, f1 = np.sum(J0 ** 2) / 1.0, np.sum(J1 ** 2) / 0.25
    joint = _joint_of([[0], [0]], scales, ["sigma_y"])
    err = joint_grid_error(joint, [(np.zeros(10), J0), (np.zeros(30), J1)], [np.array([0.2]), np.array([-0.1])])
    move = (f0 * 0.2 + f1 * -0.1) / (f0 + f1)
    np.testing.assert_allclose(err, check_error([[move]])[0], rtol=1e-12)
