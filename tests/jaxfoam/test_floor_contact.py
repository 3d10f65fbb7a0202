"""Floor contact models (scene "floor": {"contact": "grid" | "particle"}).

With grid contact the floor's rule acts on the grid nodes at or below it, so a particle is held by the
floor as soon as its B-spline stencil reaches those nodes: foam that lands comes to rest with its
lowest particles 0.66-0.81 cells above the floor (measured, 2D, dx 2.3-4.7 mm; experiments/results/
floor_contact.md), a gap that scales with dx. With particle contact (`jaxfoam._boundary.particle_floor`) each
particle's extent, half its sampling spacing, is kept from crossing the floor, and the grid's rule only
acts half a cell below it: landed foam rests with that extent on the floor at any dx. Both models apply
Coulomb's law, and a block sliding on a floor decelerates at friction x g (measured 0.99-1.004x with
either model, 2D and 3D, dx 2.5-5 mm)."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam as jf
from jaxfoam._boundary import particle_floor

from helpers import central_difference, scene as zoo_scene

G = 9.81
ELASTIC = jf.Params(mu=2000.0, sigma_y=1e4, eta=1.0, m=1.0, kappa=3000.0, rho=80.0)  # never yields here
FOAM = jf.Params(mu=233.3, sigma_y=49.24, eta=28.31, m=0.3931, kappa=3000.0, rho=80.0)


def block_scene(contact, friction, dim=2, lift=0.0, v0=0.0):
    """A 4 x 2 (x 4) cm block on (or `lift` m above) a floor at y = 0, moving at v0 m/s along x."""
    z = [0.0] * (dim - 2)
    return jf.load_scene({
        "kind": "drop", "dim": dim, "gravity": [0.0, -G] + z, "density": 80.0, "kappa": 3000.0,
        "domain": {"min": [-0.1, 0.0] + [-0.06] * (dim - 2), "max": [0.2, 0.15] + [0.06] * (dim - 2)},
        "floor": {"y": 0.0, "friction": friction, "contact": contact},
        "initial_shape": {"type": "box", "min": [-0.04, lift] + [-0.02] * (dim - 2),
                          "max": [0.0, lift + 0.02] + [0.02] * (dim - 2)},
        "initial_velocity": [v0, 0.0] + z})


@pytest.mark.slow
def test_particle_floor_rule_on_single_particles():
    """One substep's contact: a particle falling at 1 m/s with a 1 mm gap under its extent (dt 10 ms)
    is slowed to land exactly (v_y = -0.1 m/s); the 0.9 m/s removed costs friction 0.5 x 0.9 of its
    1 m/s tangential speed (0.55 left), or all of it on a sticky floor. A particle clear of the floor,
    or moving up, keeps its velocity; a touching one on a sticky floor is held."""
    dt, r = 0.01, 0.001                      # vol0 = (2 r)^2 in 2D
    x = jnp.array([[0.0, 0.002], [0.0, 0.05], [0.0, 0.001], [0.0, 0.001]])
    v = jnp.array([[1.0, -1.0], [1.0, -1.0], [1.0, 0.5], [-0.3, 0.0]])
    vol0 = jnp.full(4, (2 * r) ** 2)
    out = np.asarray(particle_floor(x, v, vol0, block_scene("particle", 0.5), dt))
    np.testing.assert_allclose(out, [[0.55, -0.1], [1.0, -1.0], [1.0, 0.5], [-0.3, 0.0]], atol=1e-12)
    stuck = np.asarray(particle_floor(x, v, vol0, block_scene("particle", "sticky"), dt))
    np.testing.assert_allclose(stuck, [[0.0, -0.1], [1.0, -1.0], [0.0, 0.0], [0.0, 0.0]], atol=1e-12)
    # An empty slot (vol0 = 0) gives finite values and derivatives.
    g = jax.grad(lambda vv: jnp.sum(particle_floor(x, v, vv, block_scene("particle", 0.5), dt)))(vol0.at[0].set(0.0))
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.slow
@pytest.mark.parametrize("friction", [0.5, "sticky"])
def test_landed_foam_rests_on_the_floor_with_particle_contact_and_a_cell_above_it_with_grid_contact(friction):
    """Foam dropped from 5 cm, at rest after 0.6 s: with particle contact its lowest particles lie at
    their half-extent above the floor (s/2 = dx/4 at 4 per cell) to round-off at dx 5 and 2.5 mm; with
    grid contact they float more than half a cell above it."""
    for dx in (0.005, 0.0025):
        lowest = {}
        for contact in ("particle", "grid"):
            tr = jf.simulate(block_scene(contact, friction, lift=0.05), FOAM, np.array([0.6]), dx)
            lowest[contact] = float(np.min(np.asarray(tr.frames["x"])[0, :, 1]))
        assert abs(lowest["particle"] - dx / 4) < 1e-9, (dx, lowest)
        assert lowest["grid"] > 0.5 * dx, (dx, lowest)


@pytest.mark.slow
@pytest.mark.parametrize("contact,dim,dx", [("grid", 2, 0.005), ("particle", 2, 0.005), ("particle", 3, 0.01)])
def test_sliding_block_decelerates_at_friction_times_g(contact, dim, dx):
    """Coulomb's law: an elastic block launched at 0.5 m/s along a floor with friction 0.3 slows at
    0.3 g = 2.94 m/s^2 (the slope of its mean velocity over 0.02-0.12 s) within 3%."""
    times = np.linspace(0.02, 0.12, 6)
    tr = jf.simulate(block_scene(contact, 0.3, dim=dim, v0=0.5), ELASTIC, times, dx)
    vx = np.asarray(tr.frames["v"])[:, :, 0].mean(axis=1)
    decel = -np.polyfit(times, vx, 1)[0]
    assert abs(decel / (0.3 * G) - 1.0) < 0.03, (decel, vx)


@pytest.mark.slow
def test_particle_contact_rollout_gradient_matches_central_differences():
    """d(mean x of the sliding block at 0.1 s) / d(floor friction, mu) through a rollout with particle
    contact: reverse mode against central differences in float64 (every bottom particle stays in
    sliding contact, so the loss is smooth there), relative error <= 1e-4."""
    scene = block_scene("particle", 0.3, v0=0.5)
    sim = jf.Simulator(scene, np.array([0.05, 0.1]), ELASTIC, 0.01)

    def mean_x(frames):
        return jnp.mean(frames["x"][-1, :, 0])

    wrt = ("floor_friction", "mu")
    rev = jf.observable_jacobian(sim, ELASTIC, mean_x, wrt, jf.HandWritten())
    for name, h in (("floor_friction", 1e-4), ("mu", 1e-1)):
        def at(delta):
            if name == "mu":
                return float(mean_x(sim.rollout(ELASTIC.replace(mu=ELASTIC.mu + delta))[1]))
            sc = dataclasses.replace(scene, floor_friction=scene.floor_friction + delta)
            return float(mean_x(sim.rollout(ELASTIC, scene=sc)[1]))

        fd = central_difference(at, 0.0, h=h)
        got = float(rev.jacobian[name])
        assert abs(got - fd) <= 1e-4 * abs(fd), (name, got, fd)
    assert float(rev.jacobian["floor_friction"]) < 0  # more friction, shorter slide


def test_floor_contact_is_validated_and_recorded():
    with pytest.raises(jf.SceneError, match="floor.contact"):
        block_scene("nodes", 0.5)
    assert block_scene("particle", 0.5).floor_contact == "particle"
    assert jf.load_scene({**block_scene("grid", 0.5).spec, "floor": {"y": 0.0}}).floor_contact == "grid"


@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("friction", [0.7, "sticky"])
def test_particle_contact_grid_rule_acts_only_on_touched_floor_nodes(dim, friction):
    """apply_colliders with particle contact: the floor's rule changes only the floor-row nodes that
    `touch` marks (an untouched node approaching the floor keeps its velocity); the bottom wall acts half
    a cell below the floor, not on it; the layer-slice form equals the mask form bit for bit; and
    `touch` is required."""
    rng = np.random.default_rng(5)
    dx = 0.02
    scene = jf.load_scene(zoo_scene("drop", dim, floor={"y": 0.0, "friction": friction, "contact": "particle"}))
    grid = jf.make_grid(scene, dx)
    node_x = np.asarray(grid.node_positions(jnp.float64))
    v = jnp.asarray(rng.normal(size=(grid.num_nodes, dim)))
    touch = jnp.asarray(rng.random(grid.num_nodes) < 0.5)
    masked = np.asarray(jf.apply_colliders(v, jnp.asarray(node_x), scene, 0.0, dx=dx, touch=touch))
    sliced = np.asarray(jf.apply_colliders(v, jnp.asarray(node_x), scene, 0.0, grid=grid, touch=touch))
    np.testing.assert_array_equal(sliced, masked)
    vn, t = np.asarray(v), np.asarray(touch)
    tang = [k for k in range(dim) if k != 1]
    interior = np.all((node_x[:, tang] > 0.0) & (node_x[:, tang] < 0.3), axis=1)
    on_floor = interior & (np.abs(node_x[:, 1]) < 1e-12) & (vn[:, 1] < 0)
    np.testing.assert_array_equal(sliced[on_floor & ~t], vn[on_floor & ~t])   # untouched: free
    np.testing.assert_array_equal(sliced[on_floor & t, 1], 0.0)               # touched: held
    wall = interior & (node_x[:, 1] < -0.4 * dx) & ~t
    np.testing.assert_array_equal(sliced[wall, 1], np.maximum(vn[wall, 1], 0.0))
    with pytest.raises(ValueError, match="touch"):
        jf.apply_colliders(v, jnp.asarray(node_x), scene, 0.0, grid=grid)
