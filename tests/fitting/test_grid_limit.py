"""The fitter says when the grid, not the data, limits an answer, and what a finer grid would cost."""
import math

import numpy as np

from fitting.check import MAX_SUGGESTED_COST, grid_limit_note


def test_no_note_when_the_data_limit_every_parameter():
    assert grid_limit_note(("mu", "sigma_y"), [0.01, 0.02], [0.05, 0.05], 0.005, 2, 300.0) is None
    assert grid_limit_note(("mu",), [np.nan], [0.05], 0.005, 2, 300.0) is None


def test_note_names_the_grid_limited_parameters_the_dx_and_its_cost():
    """mu's error is 2x its half-width (sigma_y's is within it): at first order dx / 2 reaches the data's
    level, at 2^(d+1) = 8x the fit's time in 2D (16x in 3D)."""
    note = grid_limit_note(("mu", "sigma_y"), [0.10, 0.01], [0.05, 0.05], 0.006, 2, 300.0)
    assert note.startswith("The grid, not the data, limits mu: the dx = 0.006 m grid's numerical error")
    assert "mu (2x)" in note and "sigma_y" not in note
    assert "--dx 0.003 " in note and "about 8x this fit's time (about 40 min)" in note
    note3 = grid_limit_note(("mu",), [0.10], [0.05], 0.01, 3, 600.0)
    assert "about 16x this fit's time (about 160 min)" in note3


def test_out_of_reach_grid_points_to_a_better_recording():
    ratio = 1.01 * MAX_SUGGESTED_COST ** (1 / 3)  # cost just above the cap in 2D
    note = grid_limit_note(("eta",), [0.05 * ratio], [0.05], 0.005, 2, 60.0)
    assert f"over {MAX_SUGGESTED_COST:g}x this fit's time" in note
    assert "fit a recording that constrains these parameters more instead" in note
    assert f"--dx {0.005 / ratio:.3g}" in note and math.isclose(ratio ** 3, 1.0303 * MAX_SUGGESTED_COST, rel_tol=1e-3)
