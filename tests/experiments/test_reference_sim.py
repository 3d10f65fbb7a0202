"""The reference simulator (experiments/reference): its laws on tiny problems, and one short validation case."""
from __future__ import annotations


import numpy as np
import pytest

from experiments.reference import material as M
from experiments.reference import mpm
from experiments.reference.scene import Plate, RefScene, sample
from experiments.reference.silhouettes import Camera, plate_pixels, read_back, render_mask, write


def _dev_norm(a):
    return float(np.linalg.norm(a - np.trace(a) / 3.0 * np.eye(3)))


@pytest.mark.parametrize("m", [0.3, 0.6, 1.0, 1.5])
def test_return_map_satisfies_hb_relation(m):
    rng = np.random.default_rng(int(10 * m))
    mu, sigma_y, eta, dt = 150.0, 30.0, 8.0, 1e-3
    for _ in range(20):
        f = np.eye(3)
        f[:2, :2] += 0.3 * rng.standard_normal((2, 2))  # plane strain: a big in-plane increment
        b = np.eye(3)
        c2 = np.linalg.det(f) ** (-2.0 / 3.0)
        pre = c2 * f @ f.T
        s_pre, mubar = mu * _dev_norm(pre), mu * np.trace(pre) / 3.0
        gamma = M.return_map(b, f, mu, sigma_y, eta, m, dt, np.zeros((3, 3)))
        assert abs(np.linalg.det(b) - 1.0) < 1e-12
        if s_pre <= M.SQRT_2_3 * sigma_y:
            assert gamma == 0.0
            continue
        excess = s_pre - M.SQRT_2_3 * sigma_y
        assert abs(M.hb_residual(gamma, s_pre, mubar, sigma_y, eta, m, dt)) <= 1e-8 * excess
        # The deviatoric part keeps its direction and shrinks to s = s_pre - 2 mubar dt gamma (before det -> 1).
        unnorm = b * np.linalg.det(b) ** 0  # b is renormalized; undo by matching the trace of the predictor
        dev_new = unnorm - np.trace(unnorm) / 3.0 * np.eye(3)
        dev_pre = pre - np.trace(pre) / 3.0 * np.eye(3)
        cos = np.sum(dev_new * dev_pre) / (np.linalg.norm(dev_new) * np.linalg.norm(dev_pre))
        assert cos > 1.0 - 1e-12


def test_plastic_rate_limits():
    assert M.plastic_rate(0.0, 1.0, 5.0, 0.5) == 0.0
    assert M.plastic_rate(3.0, 2.0, 0.0, 0.5) == 1.5  # eta = 0: the rate-independent limit
    g = M.plastic_rate(3.0, 2.0, 1.0, 1.0)  # Bingham: closed form (eq. 15)
    assert abs(g - 1.0) < 1e-14


def _cloud(n=200, d=2, seed=0):
    rng = np.random.default_rng(seed)
    return 0.05 + 0.03 * rng.random((n, d))


@pytest.mark.parametrize("d", [2, 3])
def test_transfers_reproduce_affine_motion_and_conserve_momentum(d):
    """P2G then G2P of a rigid motion (translation + rotation) with zero stress returns it exactly."""
    x = _cloud(120 if d == 3 else 200, d)
    p = mpm.Particles(x, 1e-7, 80.0)
    w = np.zeros((d, d))
    w[0, 1], w[1, 0] = -2.0, 2.0  # rotation at 2 rad/s about the cloud's centre in the x-y plane
    centre = x.mean(axis=0)
    vt = np.array([0.3, -0.1, 0.2][:d])
    p.v[:] = vt + (x - centre) @ w.T
    p.C[:] = w
    g = mpm.Grid.covering(np.zeros(d), np.full(d, 0.1), 0.01, shift=np.full(d, 0.3))
    gm, gp = np.zeros(g.size), np.zeros((g.size, d))
    mpm.p2g(p.x, p.v, p.C, p.J, p.b, p.vol0, p.mass, 100.0, 1000.0, 1e-4, g.origin, g.dx, g.shape, False, gm, gp)
    assert abs(gm.sum() - p.mass.sum()) < 1e-12 * p.mass.sum()
    np.testing.assert_allclose(gp.sum(axis=0), (p.mass[:, None] * p.v).sum(axis=0), rtol=0, atol=1e-13)
    nodes = g.node_positions()
    ang_grid = np.sum(gp[:, 1] * nodes[:, 0] - gp[:, 0] * nodes[:, 1])
    # APIC: the particles' angular momentum includes the affine part m (C^T : ...) = sum m (x v) + m D C terms;
    # for a rigid rotation the grid's equals that of the affine field sampled at the nodes.
    v_nodes = np.where(gm[:, None] > 0, gp / np.where(gm > 0, gm, 1.0)[:, None], 0.0)
    ang_field = np.sum(gm * ((vt + (nodes - centre) @ w.T)[:, 1] * nodes[:, 0] - (vt + (nodes - centre) @ w.T)[:, 0] * nodes[:, 1]))
    assert abs(ang_grid - ang_field) < 1e-12 * abs(ang_field) + 1e-15
    p.v[:] = 0.0
    p.C[:] = 0.0
    x_before = p.x.copy()
    mpm.g2p(p.x, p.v, p.C, p.J, p.b, v_nodes, p.gamma, 100.0, 1e9, 0.0, 1.0, 0.0, g.origin, g.dx, g.shape, False,
            np.full(d, -1.0), np.full(d, 1.0))
    np.testing.assert_allclose(p.v, vt + (x_before - centre) @ w.T, atol=1e-12)
    np.testing.assert_allclose(p.C, np.broadcast_to(w, p.C.shape), atol=1e-10)


def test_plate_velocity_is_the_derivative_of_its_position():
    sin = Plate({"center": [0.0, 0.3], "half_size": [0.08, 0.02], "motion": {
        "type": "sinusoid", "axis": [1.0, 0.0], "amplitude": 0.01, "frequency": 3.0, "phase": 0.4, "ramp_time": 0.3}}, 2)
    smp = Plate({"center": [0.0, 0.07], "half_size": [0.1, 0.01], "motion": {
        "type": "samples", "times": [0.0, 0.5, 1.4], "positions": [[0.0, 0.07], [0.0, 0.04], [0.0, 0.15]]}}, 2)
    h = 1e-6
    for plate in (sin, smp):
        for t in (0.1, 0.2, 0.45, 0.7, 1.2):
            fd = (plate.position(t + h) - plate.position(t - h)) / (2 * h)
            np.testing.assert_allclose(plate.velocity(t), fd, atol=1e-6)
        assert max(np.linalg.norm(plate.velocity(t)) for t in np.linspace(0, 1.5, 301)) <= plate.max_speed() + 1e-12


def test_coulomb_floor_and_sticky_plate_on_grid_nodes():
    g = mpm.Grid(np.array([-0.02, -0.02]), 0.01, np.array([5, 5]))
    gm = np.ones(g.size)
    gp = np.tile([1.0, -1.0], (g.size, 1))
    gv = np.zeros_like(gp)
    lo, hi = np.array([[0.005, 0.005]]), np.array([[0.03, 0.03]])
    # The bottom wall lies on the floor's plane (as in the scenes): it must not take the floor's normal velocity first.
    mpm.grid_update(gm, gp, gv, 0.0, np.zeros(2), g.origin, g.dx, g.shape, False, np.array([-1.0, 0.0]), np.full(2, 1.0),
                    0.0, mpm.FLOOR_COULOMB, 0.4, lo, hi, np.array([[0.5, 0.0]]), np.array([True]))
    x = g.node_positions()
    floor = x[:, 1] <= 0.0
    np.testing.assert_allclose(gv[floor], np.tile([0.6, 0.0], (floor.sum(), 1)))  # |v_t| reduced by 0.4 |v_n|
    in_plate = np.all((x >= lo[0]) & (x <= hi[0]), axis=1)
    np.testing.assert_allclose(gv[in_plate], np.tile([0.5, 0.0], (in_plate.sum(), 1)))
    free = ~floor & ~in_plate
    np.testing.assert_allclose(gv[free], np.tile([1.0, -1.0], (free.sum(), 1)))


def test_written_file_passes_jaxfoams_reader(tmp_path):
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 3000.0,
            "domain": {"min": [-0.05, 0.0], "max": [0.05, 0.08]}, "floor": {"y": 0.0, "friction": 0.5},
            "plate": {"center": [0.0, 0.035], "half_size": [0.02, 0.005]},
            "initial_shape": {"type": "box", "min": [-0.02, 0.0], "max": [0.02, 0.03]}}
    scene = RefScene(spec)
    dx = 0.002
    parts = sample(scene, dx, 4, seed=3)
    cam = Camera.covering(scene.lo, scene.hi, 0.0025)
    mask = render_mask(parts.x, dx / 2, cam)
    assert abs(mask.sum() * 0.0025 ** 2 / (0.04 * 0.03) - 1.0) < 0.05
    hidden = plate_pixels(cam, [(np.array([-0.02, 0.03]), np.array([0.02, 0.04]))])
    masks = np.stack([mask, mask])
    weights = np.ones(masks.shape, np.float32)
    weights[:, hidden] = 0.0
    path = tmp_path / "ref.h5"
    write(path, masks, [0.0, 0.1], cam, spec, weights, {"generator": "test"}, {"mu": 100.0, "sigma_y": 20.0,
                                                                            "eta": 3.0, "m": 0.5, "kappa": 3000.0})
    data = read_back(path)
    assert data.masks.shape == masks.shape and data.truth["mu"] == 100.0
    np.testing.assert_array_equal(data.masks, masks)
    assert data.camera.pixel_size == 0.0025


def test_free_fall_keeps_shape_and_follows_gravity():
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 3000.0,
            "domain": {"min": [-0.05, 0.0], "max": [0.05, 0.2]},
            "initial_shape": {"type": "ellipse", "center": [0.0, 0.15], "radii": [0.02, 0.02]},
            "initial_velocity": [0.2, 0.0]}
    scene = RefScene(spec)
    parts = sample(scene, 0.005, 4, seed=0)
    x0 = parts.x.copy()
    sim = mpm.Simulation(parts, mpm.Grid.covering(scene.lo, scene.hi, 0.005), dict(
        mu=100.0, kappa=3000.0, sigma_y=20.0, eta=2.0, m=0.5, rho=80.0), scene.boundaries, scene.gravity)
    sim.advance_to(0.05)
    moved = parts.x - x0
    np.testing.assert_allclose(moved, np.broadcast_to(moved[0], x0.shape), atol=1e-12)  # rigid: no deformation
    dt = 0.05 / sim.steps
    # Symplectic Euler: x moves by v_{n+1} dt, so the fall exceeds g t^2 / 2 by g t dt / 2.
    np.testing.assert_allclose(moved[0], [0.2 * 0.05, -0.5 * 9.81 * 0.05 * (0.05 + dt)], rtol=1e-4)
    np.testing.assert_allclose(parts.J, 1.0, atol=1e-12)


@pytest.mark.slow
def test_elastic_column_period_matches_linear_elasticity():
    from experiments.reference.validate import column_period

    T, T0, _ = column_period(8, periods=2.0)
    assert abs(T / T0 - 1.0) < 0.05
