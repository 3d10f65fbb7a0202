"""The shared test helpers: the central difference and the scene zoo."""
import numpy as np
import pytest

import jaxfoam
from helpers import ZOO_NAMES, central_difference, scene

PARAMS = jaxfoam.Params(mu=200.0, kappa=2000.0, sigma_y=20.0, eta=5.0, m=0.5, rho=80.0)
DX = {2: 0.01, 3: 0.02}  # m, the spacings the tests use
# Particle counts at DX and the default ppc (measured: 2D 192-420, 3D 384-1000).
COUNT_RANGE = {2: (150, 500), 3: (300, 1100)}


def test_central_difference_of_sin():
    assert abs(central_difference(np.sin, 0.3, h=1e-5) - np.cos(0.3)) < 1e-9
    assert abs(central_difference(np.sin, 0.3, h=1e-3, order=4) - np.cos(0.3)) < 1e-12


def test_central_difference_of_an_array_function_along_a_direction():
    """f(x) = (sum x^2, x0 x1) at x = (1, 2) along d = (0.6, 0.8): J d = (2 x . d, x1 d0 + x0 d1)."""
    f = lambda x: np.array([np.sum(x ** 2), x[0] * x[1]])
    x, d = np.array([1.0, 2.0]), np.array([0.6, 0.8])
    expected = np.array([2 * x @ d, x[1] * d[0] + x[0] * d[1]])
    for order in (2, 4):
        got = central_difference(f, x, d, h=1e-4, order=order)
        assert got.shape == (2,)
        np.testing.assert_allclose(got, expected, rtol=1e-10)
    # without a direction: elementwise, one step per component
    np.testing.assert_allclose(central_difference(np.exp, np.array([0.0, 1.0]), h=np.array([1e-5, 2e-5])),
                               np.exp([0.0, 1.0]), rtol=1e-9)
    with pytest.raises(ValueError, match="order"):
        central_difference(np.sin, 0.3, order=3)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", ZOO_NAMES)
def test_zoo_scene_loads_and_samples(name, dim):
    spec = scene(name, dim)
    assert spec["dim"] == dim
    sc = jaxfoam.load_scene(spec)
    state = jaxfoam.make_model(sc, DX[dim], params_ref=PARAMS).sample()
    n = int(np.sum(np.asarray(state.active)))
    lo, hi = COUNT_RANGE[dim]
    assert lo <= n <= hi, f"{name} {dim}D: {n} particles"


def test_zoo_scene_is_a_fresh_copy_with_overrides():
    a = scene("slump", initial_shape={"type": "first_mask"})
    assert a["initial_shape"] == {"type": "first_mask"}
    a["floor"]["friction"] = 0.0
    assert scene("slump")["floor"]["friction"] == 0.5
    with pytest.raises(KeyError, match="pour"):
        scene("pour")
