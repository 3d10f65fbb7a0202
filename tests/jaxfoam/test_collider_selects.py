"""Colliders written with selects (jaxfoam._boundary._pos_part, _neg_part, _clamp): the same values as
jnp.maximum / jnp.minimum / jnp.clip, NaN passed through (so a blow-up is still reported), and
derivatives that are 0 or 1 (no tie splitting)."""
import jax
import pytest
import jax.numpy as jnp
import numpy as np

import jaxfoam as jf
from jaxfoam._boundary import _clamp, _neg_part, _pos_part

from helpers import scene as zoo_scene

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


def _box_scene(dim, sticky, floor_y):
    return jf.load_scene(zoo_scene("drop", dim, floor={"y": floor_y, "friction": "sticky" if sticky else 0.7}))


@pytest.mark.slow
def test_floor_on_its_node_layers_equals_the_masked_floor():
    """grid_update applies the floor to its static node layers (a slice) and the mask form to every
    node: the same velocities, bit for bit, in 2D and 3D, float64 and float32, sticky and with Coulomb
    friction, for a floor on a node layer and between layers, with NaN velocities kept; and the same
    derivatives."""
    rng = np.random.default_rng(3)
    for dim in (2, 3):
        for sticky in (False, True):
            for floor_y in (0.0, 0.0371):
                scene = _box_scene(dim, sticky, floor_y)
                grid = jf.make_grid(scene, 0.02)
                node_x = grid.node_positions(jnp.float64)
                v = jnp.asarray(rng.normal(size=(grid.num_nodes, dim)))
                v = v.at[::97].set(jnp.nan)
                masked = jf.apply_colliders(v, node_x, scene, 0.0)
                sliced = jf.apply_colliders(v, node_x, scene, 0.0, grid=grid)
                np.testing.assert_array_equal(np.asarray(sliced), np.asarray(masked))
                # float32 (the scene's leaves cast as a float32 rollout casts them): the layer count comes
                # from the same float32 node positions
                v32, x32 = v.astype(jnp.float32), grid.node_positions(jnp.float32)
                s32 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), scene)
                out32 = jf.apply_colliders(v32, x32, s32, 0.0, grid=grid)
                assert out32.dtype == jnp.float32
                np.testing.assert_array_equal(np.asarray(out32), np.asarray(jf.apply_colliders(v32, x32, s32, 0.0)))
                below = np.asarray(node_x[:, 1] <= floor_y)
                assert below.sum() >= grid.shape[0], "the floor holds at least one node layer"
                v = jnp.nan_to_num(v)
                ct = jnp.asarray(rng.normal(size=v.shape))
                g_mask = jax.grad(lambda u: jnp.sum(ct * jf.apply_colliders(u, node_x, scene, 0.0)))(v)
                g_grid = jax.grad(lambda u: jnp.sum(ct * jf.apply_colliders(u, node_x, scene, 0.0, grid=grid)))(v)
                np.testing.assert_array_equal(np.asarray(g_grid), np.asarray(g_mask))
                # friction: approaching floor nodes lose tangential speed; sticky ones stop
                out = np.asarray(jf.apply_colliders(v, node_x, scene, 0.0, grid=grid))
                approaching = below & (np.asarray(v[:, 1]) < 0)
                tang = [k for k in range(dim) if k != 1]  # away from the side walls, which act on these components
                interior = approaching & np.all((np.asarray(node_x)[:, tang] > 0.0) & (np.asarray(node_x)[:, tang] < 0.3), axis=1)
                assert interior.any()
                np.testing.assert_array_equal(out[interior, 1], 0.0)
                if sticky:
                    np.testing.assert_array_equal(out[below & interior], 0.0)
                else:
                    vt = np.asarray(v)[interior][:, tang]
                    speed = np.linalg.norm(vt, axis=1)
                    new = np.linalg.norm(out[interior][:, tang], axis=1)
                    np.testing.assert_allclose(new, np.maximum(speed + 0.7 * np.asarray(v)[interior, 1], 0.0),
                                               rtol=1e-12, atol=1e-15)
