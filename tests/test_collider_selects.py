"""Colliders written with selects (jaxfoam._mpm._pos_part, _neg_part, _clamp): the same values as
jnp.maximum / jnp.minimum / jnp.clip, NaN passed through (so a blow-up is still reported), and
derivatives that are 0 or 1 (no tie splitting)."""
import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam as jf
from jaxfoam._mpm import _clamp, _neg_part, _pos_part

VALUES = jnp.asarray([-np.inf, -3.5, -1e-300, -0.0, 0.0, 1e-300, 2.25, np.inf, np.nan])


def test_selects_equal_max_min_clip_and_pass_nan():
    np.testing.assert_array_equal(_pos_part(VALUES), jnp.maximum(VALUES, 0.0))
    np.testing.assert_array_equal(_neg_part(VALUES), jnp.minimum(VALUES, 0.0))
    np.testing.assert_array_equal(_clamp(VALUES, -1.0, 2.0), jnp.clip(VALUES, -1.0, 2.0))
    assert np.isnan(_pos_part(VALUES)[-1]) and np.isnan(_neg_part(VALUES)[-1]) and np.isnan(_clamp(VALUES, -1.0, 2.0)[-1])


def test_select_derivatives_are_zero_or_one_also_at_the_kink():
    # jnp.maximum(x, 0) has derivative 0.5 at x = 0; the select takes the branch that keeps x there
    x = jnp.asarray([-1.0, 0.0, 1.0])
    np.testing.assert_array_equal(jax.vmap(jax.grad(_pos_part))(x), [0.0, 1.0, 1.0])
    np.testing.assert_array_equal(jax.vmap(jax.grad(_neg_part))(x), [1.0, 1.0, 0.0])
    np.testing.assert_array_equal(jax.vmap(jax.grad(lambda v: _clamp(v, -1.0, 1.0)))(jnp.asarray([-2.0, -1.0, 0.5, 1.0, 3.0])),
                                  [0.0, 1.0, 1.0, 1.0, 0.0])


def test_walls_and_floor_keep_nan_velocities_visible():
    """A non-finite grid velocity on a wall or floor node stays non-finite: the rollout's health check
    must see a blow-up, which a select that mapped NaN to 0 would hide."""
    scene = jf.load_scene({"kind": "drop", "dim": 2, "density": 80.0, "kappa": 2000.0, "gravity": [0.0, -9.81],
                           "domain": {"min": [0.0, 0.0], "max": [1.0, 1.0]}, "floor": {"y": 0.0, "friction": 0.5},
                           "initial_shape": {"type": "box", "min": [0.3, 0.3], "max": [0.7, 0.7]}})
    node_x = jnp.asarray([[0.0, 0.5], [1.0, 0.5], [0.5, 0.0], [0.5, 0.5]])  # left wall, right wall, floor, inside
    v = jnp.full((4, 2), jnp.nan)
    out = jf.apply_colliders(v, node_x, scene, 0.0)
    assert bool(jnp.all(jnp.isnan(out)))
    # finite velocities: walls remove the outward normal component, the floor applies Coulomb friction
    v = jnp.asarray([[-1.0, 0.3], [1.0, -0.2], [0.4, -1.0], [0.4, -1.0]])
    out = np.asarray(jf.apply_colliders(v, node_x, scene, 0.0))
    np.testing.assert_allclose(out[0], [0.0, 0.3])
    np.testing.assert_allclose(out[1], [0.0, -0.2])
    np.testing.assert_allclose(out[2], [0.0, 0.0])  # |v_t| 0.4 - 0.5 * 1.0 < 0: sticks
    np.testing.assert_allclose(out[3], [0.4, -1.0])
