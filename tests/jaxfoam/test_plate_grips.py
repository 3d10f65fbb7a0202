"""How a sticky plate grips (scene "plate": {"grip": "nodes" | "face"}).

With "nodes" the grid nodes inside the plate take its velocity, so the no-slip wall the foam sees sits
near the lowest node row inside the face: 0 to 1 cell in, depending on where the face falls between
node rows. With "face" each node within a cell outside the plate also takes the velocity interpolated
linearly between the plate's at the face and the next node's further out (only pushing along the
face normal), so the velocity profile meets the plate at its face whatever the phase. Measured in
plane Couette flow (experiments/results/plate_grip.md): walls within 0.18 cells of the face at dx 10
and 5 mm with "face", from 0.74 cells inside to 0.2 cells below it with "nodes"."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam as jf
from jaxfoam import JaxfoamError

from helpers import central_difference


def plate_scene(grip="face", face=0.043, motion=None, dim=2):
    """A 2D domain with a sticky plate whose lower face is at y = `face` m."""
    centre = [0.0, face + 0.02]
    plate = {"center": centre, "half_size": [0.1, 0.02], "grip": grip}
    if motion is not None:
        plate["motion"] = motion
    return {"kind": "hanging_plate", "dim": dim, "gravity": [0.0, 0.0], "density": 80.0, "kappa": 3000.0,
            "domain": {"min": [-0.2, 0.0], "max": [0.2, 0.12]}, "floor": {"y": 0.0, "friction": "sticky"},
            "plate": plate, "initial_shape": {"type": "box", "min": [-0.05, 0.0], "max": [0.05, face + 0.01]}}


def test_face_grip_sets_band_nodes_to_the_linear_profile_through_the_face():
    """One grid update's plate rule, against the formula node by node: inside the plate v = v_plate; a node
    d = 0.3 dx below the face takes v_p + (v_below - v_p) d / (d + dx) (tangential part), its normal part
    only where that pushes away from the plate; nodes a cell or more outside keep their velocity."""
    dx = 0.01
    scene = jf.load_scene(plate_scene(face=0.043))
    grid = jf.make_grid(scene, dx)
    x = np.asarray(grid.node_positions(jnp.float64, xp=np))
    rng = np.random.default_rng(0)
    v = rng.normal(size=x.shape)
    vp = np.zeros(2)                                   # a plate at rest
    out = np.asarray(jf.apply_colliders(jnp.asarray(v), jnp.asarray(x), scene, 0.0, grid=grid))
    shape = tuple(grid.shape)
    V, X, O = (a.reshape(shape + (2,)) for a in (v, x, out))
    i = int(np.argmin(np.abs(X[:, 0, 0])))             # the column through the plate's centre
    col_y = X[i, :, 1]
    inside = col_y >= 0.043 - 1e-12
    np.testing.assert_allclose(O[i, inside & (col_y <= 0.083)], 0.0, atol=1e-15)
    j = int(np.nonzero(inside)[0][0]) - 1              # the node just below the face
    d = 0.043 - col_y[j]
    assert 0 < d < dx
    frac = d / (d + dx)
    target = vp + frac * (V[i, j - 1] - vp)
    assert O[i, j, 0] == pytest.approx(target[0], abs=1e-14)
    # normal (-y out of the plate): only a push down is imposed, a pull up leaves the node's own v_y
    assert O[i, j, 1] == pytest.approx(min(target[1], V[i, j, 1]), abs=1e-14)
    np.testing.assert_array_equal(O[i, : j - 1][col_y[: j - 1] > dx], V[i, : j - 1][col_y[: j - 1] > dx])


def test_nodes_grip_leaves_nodes_outside_the_plate_alone():
    dx = 0.01
    scene = jf.load_scene(plate_scene(grip="nodes", face=0.043))
    grid = jf.make_grid(scene, dx)
    x = np.asarray(grid.node_positions(jnp.float64, xp=np))
    v = np.random.default_rng(1).normal(size=x.shape)
    out = np.asarray(jf.apply_colliders(jnp.asarray(v), jnp.asarray(x), scene, 0.0, grid=grid))
    outside = ~np.all(np.abs(x - np.array([0.0, 0.063])) <= np.array([0.1, 0.02]) + 1e-12, axis=1)
    inside_floor = x[:, 1] <= 0.0
    keep = outside & ~inside_floor & (x[:, 1] < 0.11) & (np.abs(x[:, 0]) < 0.19)
    np.testing.assert_array_equal(out[keep], v[keep])
    np.testing.assert_allclose(out[~outside], 0.0, atol=1e-15)


def test_grip_is_validated():
    with pytest.raises(JaxfoamError, match=r"plate\.grip.*'nodes', 'face'.*'glue'"):
        jf.load_scene(plate_scene(grip="glue"))
    assert jf.load_scene(plate_scene(grip="face")).plates[0].grip == "face"
    spec = plate_scene()
    del spec["plate"]["grip"]
    assert jf.load_scene(spec).plates[0].grip == "nodes"


def _couette_wall(grip: str, dx: float, phase: float) -> float:
    """Cells between the plate's face and where the steady Couette profile reaches the plate's speed
    (> 0: below the face, in the foam; < 0: inside the plate)."""
    face, speed, duration = 0.04 + phase * dx, 0.02, 0.4
    centre = [0.0, face + 0.02]
    spec = plate_scene(grip=grip, face=face, motion={"type": "samples", "times": [0.0, 10.0],
                                                      "positions": [centre, [speed * 10.0, centre[1]]]})
    spec["plate"]["half_size"] = [0.19, 0.02]
    spec["initial_shape"] = {"type": "box", "min": [-0.15, 0.0], "max": [0.15, face + 0.01]}
    material = jf.Params(mu=2000.0, kappa=3000.0, sigma_y=0.0, eta=2.0, m=1.0, rho=80.0)
    tr = jf.simulate(jf.load_scene(spec), material, np.array([duration]), dx)
    x, v = np.asarray(tr.frames["x"])[-1], np.asarray(tr.frames["v"])[-1]
    sel = (np.abs(x[:, 0] - speed * duration) < 0.05) & (x[:, 1] > 0.25 * face) & (x[:, 1] < 0.75 * face)
    slope, icpt = np.polyfit(x[sel, 1], v[sel, 0], 1)
    return (face - (speed - icpt) / slope) / dx


@pytest.mark.slow
def test_face_grip_puts_the_couette_wall_at_the_face_at_every_phase():
    """Plane Couette flow between a sticky floor and a sticky plate moving at 2 cm/s, dx 1 cm, faces a
    quarter and three quarters of a cell past a node row: with "face" the wall lies within 0.25 cell of the
    face at both; with "nodes" it sits near the lowest node row inside (0.75 cell in at phase 0.25)."""
    for phase in (0.25, 0.75):
        assert abs(_couette_wall("face", 0.01, phase)) <= 0.25, phase
    assert _couette_wall("nodes", 0.01, 0.25) < -0.4


@pytest.mark.slow
def test_face_grip_rollout_gradient_matches_central_differences():
    """d(mean x velocity of the foam at 0.05 s) / d(mu, the plate's sinusoid amplitude) with grip "face":
    reverse mode against central differences in float64, relative error <= 1e-4."""
    motion = {"type": "sinusoid", "axis": [1.0, 0.0], "amplitude": 0.004, "frequency": 5.0, "ramp_time": 0.0}
    scene = jf.load_scene(plate_scene(grip="face", face=0.0435, motion=motion))
    material = jf.Params(mu=300.0, kappa=3000.0, sigma_y=40.0, eta=3.0, m=0.6, rho=80.0)
    sim = jf.Simulator(scene, np.array([0.025, 0.05]), material, 0.01)

    def mean_vx(frames):
        return jnp.mean(frames["v"][-1, :, 0])

    rev = jf.observable_jacobian(sim, material, mean_vx, ("mu",))
    fd = central_difference(lambda d: float(mean_vx(sim.rollout(material.replace(mu=material.mu + d))[1])),
                            0.0, h=1e-2)
    assert abs(float(rev.jacobian["mu"]) - fd) <= 1e-4 * abs(fd), (float(rev.jacobian["mu"]), fd)

    def with_amplitude(a):
        plate = dataclasses.replace(scene.plates[0], amplitude=a)
        return mean_vx(sim.rollout(material, scene=dataclasses.replace(scene, plates=(plate,)))[1])

    g = float(jax.grad(with_amplitude)(scene.plates[0].amplitude))
    fd = central_difference(lambda d: float(with_amplitude(scene.plates[0].amplitude + d)), 0.0, h=1e-6)
    assert np.isfinite(g) and abs(g - fd) <= 1e-4 * abs(fd), (g, fd)
