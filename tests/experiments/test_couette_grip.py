"""Where sticky boundaries grip: the no-slip walls of plane Couette flow (experiments/plate_grip.py).

A Newtonian layer (yield stress 0) between a sticky floor on a node row and a sticky plate moving
sideways has, in steady flow, a velocity linear in height. The floor's no-slip wall lies on the floor;
the plate's lies at the lowest grid node row inside its face, about 0.12 cells below that row, so it
moves with the face's phase against the grid (the grip edge of grid contact: 0 to 1 cell inside the
face). Numbers: dx 1 cm, two phases."""
import pytest

from experiments.plate_grip import walls


@pytest.mark.slow
def test_couette_walls_floor_on_floor_plate_at_its_lowest_node_row():
    on_row = walls(0.01, 0.0)    # a node row on the face
    half = walls(0.01, 0.5)      # the face half a cell below a node row
    for r in (on_row, half):
        assert abs(r["floor"]) < 0.1, r               # no-slip wall on the floor, to 0.1 cell
        # the plate's wall follows its lowest node row (0 and 0.5 cells inside the face), 0.05-0.25 below it
        assert -0.3 < r["plate"] - r["row_depth"] < 0.0, r
    assert on_row["row_depth"] == pytest.approx(0.0, abs=1e-9) and half["row_depth"] == pytest.approx(0.5, abs=1e-9)
    assert half["plate"] - on_row["plate"] == pytest.approx(0.5, abs=0.1)  # the edge moves with the phase
