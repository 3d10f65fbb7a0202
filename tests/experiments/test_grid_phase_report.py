"""The floor-phase refinement summary counts what it says: the observed order of the mean boundary
distance between the default dx and dx / 2, and the files where phase 0.5 has the lower loss on every grid."""
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments.grid_phase import REFINEMENTS, refined_section  # noqa: E402


def _file(name, boundary0, boundary5, loss0, loss5):
    rows = []
    for ph, b, losses in ((0.0, boundary0, loss0), (0.5, boundary5, loss5)):
        for k, bk, lk in zip(REFINEMENTS, b, losses):
            rows.append(dict(floor_phase=ph, refine=k, dx=0.005 / k, loss=lk, iou_min=0.8, boundary_mean=bk, wall=1.0))
    return dict(file=name, rows=rows)


def test_order_and_wins():
    first = [0.004, 0.004 / math.sqrt(2.0), 0.002]  # first order: halved at dx / 2
    flat = [0.002, 0.002, 0.002]                     # order 0
    a = _file("drop_2d_set0.h5", first, flat, loss0=[3.0, 2.0, 1.0], loss5=[1.0, 1.0, 0.5])   # 0.5 lower on all
    b = _file("drop_2d_set1.h5", first, flat, loss0=[3.0, 2.0, 1.0], loss5=[1.0, 3.0, 0.5])   # not on dx / sqrt 2
    text = refined_section([a, b])
    assert "drop, floor phase 0: mean boundary distance 4.00, 2.83, 2.00 mm at the three grids (observed order 1.00" in text
    assert "drop, floor phase 0.5: mean boundary distance 2.00, 2.00, 2.00 mm at the three grids (observed order 0.00" in text
    assert "floor phase 0.5 has the lower loss at the truth on all three grids in 1 of 2 files" in text
