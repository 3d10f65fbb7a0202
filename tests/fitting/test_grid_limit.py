"""The fitter says when the grid, not the data, limits an answer, and what a finer grid would cost."""
import math
from pathlib import Path

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


def test_count_pieces_counts_4_connected_pieces_above_the_speckle_fraction():
    """Pieces are 4-connected (diagonal touching does not join), and a piece under PIECE_FRACTION of
    the foam pixels (tracking speckle) is not counted."""
    from fitting.check import PIECE_FRACTION, count_pieces

    m = np.zeros((40, 60), bool)
    assert count_pieces(m) == 0
    m[5:20, 5:25] = True
    assert count_pieces(m) == 1
    m[5:20, 30:50] = True
    assert count_pieces(m) == 2
    m[20, 25] = True  # touches the first block only diagonally
    m[21, 26:30] = True
    assert count_pieces(m) == 2
    m[30, 55] = True  # one-pixel speckle, far under PIECE_FRACTION of ~600 pixels
    assert PIECE_FRACTION * m.sum() > 1 and count_pieces(m) == 2


def test_separation_note_names_the_first_split_frame_and_the_window_before_it():
    """The observed foam of drop_2d set 2 (reference simulator) pinches into two pieces at its sixth
    frame: the note names that time and the --time-window ending one frame earlier; the squeeze's
    set 0, which never splits, gets no note; a split at the second frame gets no window."""
    from fitting.check import count_pieces, separation_note
    from fitting.io import read_silhouettes

    root = Path(__file__).resolve().parents[2] / "experiments" / "reference" / "data"
    drop = read_silhouettes(root / "drop_2d_set2.h5")
    counts = [count_pieces(m) for m in drop.masks >= 0.5]
    k = next(i for i, c in enumerate(counts) if c > counts[0])
    assert counts[0] == 1 and k == 5
    note = separation_note(drop.times, drop.masks, drop.weights)
    assert f"t = {drop.times[k]:.3g} s" in note and f"--time-window 0:{drop.times[k - 1]:.4g}" in note
    squeeze = read_silhouettes(root / "squeeze_2d_set0.h5")
    assert separation_note(squeeze.times, squeeze.masks, squeeze.weights) is None
    two = np.zeros((2, 30, 30))
    two[:, 5:25, 5:12] = 1.0
    two[1, 5:25, 18:25] = 1.0
    note = separation_note([0.1, 0.2], two, np.ones_like(two))
    assert "t = 0.2 s" in note and "--time-window" not in note
