"""The fit-fidelity goal table counts what the issue's goals count: truth inside the interval, intervals
that are only the bounds, identifiable-but-wrong, parameters within 10% in 2D, and the loss ratio."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments.reference_fits import report  # noqa: E402


def _record(name, fit, interval, identifiable, loss, loss_truth):
    truth = {"mu": 100.0, "sigma_y": 20.0, "eta": 5.0, "m": 0.5}
    return dict(file=name, truth=truth, params=dict(zip(truth, fit)), interval=dict(zip(truth, interval)),
                identifiable=dict(zip(truth, identifiable)), loss=loss, loss_truth=loss_truth, dx=0.005, wall=60.0)


def test_goal_counts():
    bounds = [[5.0, 2000.0], [0.5, 500.0], [0.05, 500.0], [0.2, 1.5]]
    good = _record("drop_2d_set0.h5", [105.0, 21.0, 4.0, 0.6], [[90, 120], [18, 24], [2, 8], [0.4, 0.7]],
                   [True] * 4, loss=1.0, loss_truth=1.1)
    wrong = _record("squeeze_2d_set0.h5", [150.0, 30.0, 4.0, 0.6], [[140, 160], bounds[1], bounds[2], bounds[3]],
                    [True, False, False, False], loss=1.0, loss_truth=3.0)
    text = report([good, wrong])
    assert "Truth inside the reported interval: 7 of 8 parameter-cases" in text
    assert "3 of them with the interval equal to the default bounds" in text
    assert "reported identifiable with the truth outside: 1 (goal: 0)" in text
    assert "mu within 10% in 1 of 2" in text and "sigma_y in 1 of 2" in text
    assert "at most 1.2 in 1 of 2 (goal: 8 of 9)" in text
