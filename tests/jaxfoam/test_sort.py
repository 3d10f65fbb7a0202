"""Reordering particles by grid cell (jaxfoam._xla_cpu.layout.sort_by_cell, Tuning.sort_by_cell) is a pure permutation of the slots.

The MPM sums are order-independent up to floating-point association, so a rollout that sorts the
particles at the start of every frame and restores their order at its end must give the same
particles, in the same slots, as one that never sorts (to round-off), and the same derivatives.
"""
import jax
import pytest
import jax.numpy as jnp
import numpy as np

from jaxfoam import Params, Simulator, load_scene, make_grid, step
from jaxfoam._grid import _flat_index, _stencil
from jaxfoam._xla_cpu.layout import sort_by_cell, to_components, unsort

# Shear and bulk modulus Pa, yield stress Pa, consistency Pa s^m, flow index, density kg/m^3.
PARAMS = Params(mu=300.0, kappa=3000.0, sigma_y=20.0, eta=5.0, m=0.6, rho=80.0)
DX = 0.01  # grid spacing, m


def _scene():
    """A 2D foam column 0.12 m tall slumping on a frictional floor: rho g h = 94 Pa exceeds the
    20 Pa yield stress, so it yields from the first substeps (gravity m/s^2, lengths m)."""
    return load_scene({"kind": "drop", "dim": 2, "density": 80.0, "kappa": 3000.0,
                       "gravity": [0.0, -9.81], "domain": {"min": [0.0, 0.0], "max": [0.2, 0.2]},
                       "floor": {"y": 0.0, "friction": 0.4},
                       "initial_shape": {"type": "box", "min": [0.05, 0.0], "max": [0.15, 0.12]}})


def _shuffled_sim(sort, frames=(0.01, 0.02, 0.03)):
    """A simulator whose particles start in random slot order, with 10% inactive slots at random."""
    scene = _scene()
    base = Simulator(scene, (0.02,), PARAMS, DX, capacity=None)
    s0 = base.state0
    n = s0.capacity
    rng = np.random.default_rng(3)
    perm = rng.permutation(n)
    s0 = jax.tree_util.tree_map(lambda a: a[perm] if jnp.ndim(a) >= 1 else a, s0)
    drop = rng.random(n) < 0.1
    s0 = s0.replace(active=s0.active & ~drop, mass=jnp.where(drop, 0.0, s0.mass),
                    vol0=jnp.where(drop, 0.0, s0.vol0))
    return Simulator(scene, frames, PARAMS, DX, state0=s0, sort=sort)


@pytest.mark.slow
def test_sort_by_cell_orders_cells_and_puts_inactive_last():
    """sorted = original[perm]: cell indices of active particles are nondecreasing, inactive slots
    come after every active one, and unsort restores every slot bit for bit."""
    sim = _shuffled_sim(True)
    grid = make_grid(sim.scene, DX)
    s = to_components(sim.state0)
    ss, perm = sort_by_cell(s, grid)
    assert sorted(np.asarray(perm).tolist()) == list(range(s.capacity)), "perm is not a permutation"
    act = np.asarray(ss.active)
    n_act = int(act.sum())
    assert act[:n_act].all() and not act[n_act:].any(), "inactive slots are not last"
    key = np.asarray(_flat_index(_stencil(ss.x, grid)[0], (0, 0), grid))[:n_act]
    assert np.all(np.diff(key) >= 0), "active particles are not in cell order"
    back = unsort(ss, perm)
    for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(s)):
        assert np.array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
def test_sorted_rollout_matches_unsorted_slot_by_slot():
    """Sorting during each frame changes the result only by floating-point association (positions agree
    to 1e-11 m over 3 frames of a slumping, yielding column) and keeps particle i in slot i."""
    outs = []
    for sort in (False, True):
        sim = _shuffled_sim(sort)
        final, frames, health = sim.rollout(PARAMS)
        sim.check(frames, health)
        outs.append((final, frames))
    (f0, r0), (f1, r1) = outs
    moved = float(jnp.max(jnp.abs(f0.x - _shuffled_sim(False).state0.x)))
    assert moved > 1e-3, "the block barely moved: the comparison would be vacuous"
    assert float(jnp.max(jnp.abs(f1.x - f0.x))) < 1e-11
    assert float(jnp.max(jnp.abs(jnp.asarray(r1["x"]) - jnp.asarray(r0["x"])))) < 1e-11
    assert np.array_equal(np.asarray(f1.active), np.asarray(f0.active))
    assert float(jnp.max(jnp.abs(f1.bbar_e - f0.bbar_e))) < 1e-9


@pytest.mark.slow
def test_sorted_substeps_have_same_gradient():
    """d(slot-weighted height after 40 substeps)/d(mu, sigma_y) by reverse mode is the same with the particles
    sorted by cell before the substeps and put back after them as without (relative 1e-8), on the
    yielding column: the permutation is treated as data and gradients pass through the reordering
    (a gather forward, a scatter in the transpose)."""
    sim = _shuffled_sim(True, frames=(0.01,))
    grid = make_grid(sim.scene, DX)

    def height(p, sort):
        params = PARAMS.replace(mu=p[0], sigma_y=p[1])
        s = to_components(sim.state0)
        if sort:
            s, perm = sort_by_cell(s, grid)
        s = jax.lax.scan(lambda c, _: (step(sim.model, c, params), None), s, None, length=40)[0]
        if sort:
            s = unsort(s, perm)
        # Slot-dependent weights: a wrong restore of the order changes value and gradient.
        return jnp.sum(jnp.where(s.active, slot_weight, 0.0) * s.x[:, 1])

    slot_weight = jnp.asarray(np.random.default_rng(7).random(sim.state0.capacity))
    p0 = jnp.array([300.0, 20.0])
    grads = [np.asarray(jax.jit(jax.grad(height), static_argnums=1)(p0, sort)) for sort in (False, True)]
    assert np.all(np.isfinite(grads[1])) and np.all(np.abs(grads[0]) > 0), grads
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-8)
