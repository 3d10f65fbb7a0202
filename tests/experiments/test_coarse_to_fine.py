"""Richardson extrapolation of two grids' optima: exact for an estimate that is linear (or of the stated
order) in dx, and the continuation study's tolerance rule is the issue's (mu, sigma_y 10%, eta 25%, m 0.1)."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments.coarse_to_fine import RATIO, richardson, within  # noqa: E402


@pytest.mark.parametrize("order", [1.0, 2.0])
def test_richardson_recovers_the_limit_of_a_power_law_in_dx(order):
    z0, c, h = np.array([4.6, 3.0, 1.5, -0.7]), np.array([2.0, -1.0, 30.0, 0.4]), 0.005
    coarse, fine = z0 + c * h ** order, z0 + c * (RATIO * h) ** order
    np.testing.assert_allclose(richardson(coarse, fine, order=order), z0, rtol=0, atol=1e-12)
    # at first order with r = 1/sqrt(2) the fine estimate moves 2.414 times the two grids' difference
    if order == 1.0:
        np.testing.assert_allclose((richardson(coarse, fine) - fine) / (fine - coarse), 1 / (math.sqrt(2) - 1))


def test_tolerances_are_relative_except_m():
    assert within("mu", 109.0, 100.0) and not within("mu", 111.0, 100.0)
    assert within("eta", 12.4, 10.0) and not within("eta", 12.6, 10.0)
    assert within("m", 0.69, 0.6) and not within("m", 0.71, 0.6)
