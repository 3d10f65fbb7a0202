"""The note on a best start that stopped at its iteration budget (`fitting.driver.iteration_budget_note`).

Contract: it gives the loss's relative fall over the last UNCONVERGED_TAIL iterations, names a parameter
whose position in its bounds (log span for log parameters) fell (rose) in each of those iterations to
within NEAR_BOUND of the lower (upper) bound, names no other, and tells how to continue; a fit that stops
at its budget carries it, a converged one does not.
"""
import dataclasses

import numpy as np
import pytest

from fitting import FitSettings, calibrate, synthesize
from fitting.driver import NEAR_BOUND, UNCONVERGED_TAIL, iteration_budget_note
from fitting.optim import ParameterTransform

from helpers import scene as zoo_scene

TR = ParameterTransform.create(["mu", "eta", "m"], positive=["mu", "eta"],
                               bounds={"mu": (5.0, 2000.0), "eta": (0.05, 500.0), "m": (0.2, 1.5)})


def test_note_gives_the_loss_fall_and_the_parameters_heading_for_a_bound():
    k = UNCONVERGED_TAIL
    loss = np.array([2.0] + [1.0 * 0.99 ** i for i in range(k + 1)])
    eta = 0.05 * np.exp(np.linspace(1.0, 0.1, k + 2))   # log position 0.109 -> 0.011: falls, ends near lo
    m = np.linspace(1.2, 1.49, k + 2)                   # rises to 0.992 of the span: near hi
    mu = np.array([100.0, 101, 99, 102, 100, 101, 100.5])  # wanders in the middle
    note = iteration_budget_note(loss, np.stack([mu, eta, m], axis=1), TR, 2, 30)
    assert note.startswith("The best start (2) stopped at its iteration budget (30) before converging")
    assert f"its loss fell {100 * (1 - 0.99 ** k):.2g}% over its last {k} iterations" in note
    assert f"eta ({eta[-1]:.4g}) towards its lower bound 0.05" in note
    assert f"m ({m[-1]:.4g}) towards its upper bound 1.5" in note and "mu (" not in note
    assert note.endswith("--max-iter 60 --resume.")


def test_note_names_no_bound_when_the_parameters_stay_inside_or_turn_back():
    k = UNCONVERGED_TAIL
    loss = np.linspace(1.0, 0.9, k + 1)
    lo_pos = 0.05 * np.exp(np.log(500 / 0.05) * np.array([0.3, 0.25, 0.2, 0.15, 0.12, 0.11]))  # ends above NEAR_BOUND
    assert 0.11 > NEAR_BOUND
    back = np.array([0.25, 0.24, 0.23, 0.215, 0.22, 0.21])  # m's position turns back once
    note = iteration_budget_note(loss, np.stack([np.full(k + 1, 100.0), lo_pos, back], axis=1), TR, 1, 10)
    assert "towards" not in note and "fell 10% over its last 5 iterations." in note
    # a start with no iteration after its start point gets no note
    assert iteration_budget_note([1.0], [[100.0, 1.0, 0.5]], TR, 1, 0) is None


@pytest.mark.slow
def test_a_fit_stopped_by_its_budget_says_so_and_a_converged_one_does_not(tmp_path):
    slump = zoo_scene("slump", initial_shape={"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.1]})
    data = synthesize(slump, {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}, dx=0.005, frames=6,
                      duration=0.3, noise=0.02, seed=1)
    settings = FitSettings(dx=0.01, fixed={"mu": 150.0, "eta": 5.0, "m": 0.6}, starts=1, max_iter=1, dx_check=False)
    short = calibrate(data, settings)
    assert short.reason == "max_iterations"
    assert any(n.startswith("The best start (1) stopped at its iteration budget (1)") for n in short.notes)
    full = calibrate(data, dataclasses.replace(settings, max_iter=30))
    assert full.reason.startswith("converged") and not any("iteration budget" in n for n in full.notes)
