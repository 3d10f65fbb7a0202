"""Conservation laws of the MLS-MPM transfers (SI units: kg, m, s).

- Mass: particles carry a constant mass; P2G spreads it with quadratic B-spline weights, a partition of
  unity, so the grid mass equals the particle mass to round-off.
- Momentum: P2G moves m v to the grid unchanged (the affine and stress terms are weighted by
  x_i - x_p, whose B-spline first moment is zero); G2P returns it (sum_p m_p w_ip = m_i); with no
  external force and no boundary touching the material, a rollout conserves total momentum.
- Affine fields: quadratic B-splines reproduce linear fields, so G2P of v_i = A x_i + b gives
  v_p = A x_p + b and C_p = A exactly (sum_i w_ip (x_i - x_p)(x_i - x_p)^T = dx^2/4 I).
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfoam import Params, Simulator, g2p, init_state, load_scene, make_grid, p2g

# A soft foam-like material: shear and bulk modulus Pa, yield stress Pa, consistency Pa s^m, density kg/m^3.
PARAMS = Params(mu=500.0, kappa=2000.0, sigma_y=20.0, eta=5.0, m=0.5, rho=80.0)
DX = 0.01  # grid spacing, m: a block 6-8 cells wide


def _free_scene(dim):
    """A box of material in the middle of a 0.2 m domain: no gravity, no floor, no plates."""
    lo, hi = [0.06, 0.06, 0.08][:dim], [0.14, 0.12, 0.12][:dim]
    return load_scene({"kind": "drop", "dim": dim, "gravity": [0.0] * dim, "density": 80.0, "kappa": 2000.0,
                       "domain": {"min": [0.0] * dim, "max": [0.2] * dim},
                       "initial_shape": {"type": "box", "min": lo, "max": hi}})


def _stirred_state(scene, seed=0, capacity=None):
    """Sampled state with a translation + spin + shear velocity field, a matching affine matrix C, and a
    random elastic deformation (so stresses are non-zero from the start)."""
    state = init_state(scene, DX, capacity=capacity)
    d, n = scene.dim, state.capacity
    rng = np.random.default_rng(seed)
    x = np.asarray(state.x)
    centre = x[np.asarray(state.active)].mean(axis=0)
    grad_v = np.zeros((d, d))
    grad_v[0, 1], grad_v[1, 0] = -5.0 + 3.0, 5.0  # spin 5 rad/s plus a shear rate 3 1/s, 1/s
    if d == 3:
        grad_v[2, 0], grad_v[0, 2] = 2.0, -2.0
    v = np.asarray([0.2, 0.1, -0.15][:d])[None, :] + (x - centre[None, :]) @ grad_v.T
    F = np.eye(d)[None] + 0.02 * rng.normal(size=(n, d, d))
    a = np.eye(3)[None] + 0.03 * rng.normal(size=(n, 3, 3))
    bbar = a @ np.swapaxes(a, 1, 2)
    bbar /= np.linalg.det(bbar)[:, None, None] ** (1.0 / 3.0)
    act = np.asarray(state.active)
    return state.replace(v=jnp.asarray(np.where(act[:, None], v, 0.0)),
                         C=jnp.asarray(np.where(act[:, None, None], grad_v[None], 0.0)),
                         F=jnp.asarray(np.where(act[:, None, None], F, np.eye(d)[None])),
                         bbar_e=jnp.asarray(np.where(act[:, None, None], bbar, np.eye(3)[None])))


@pytest.mark.parametrize("dim", [2])
def test_p2g_conserves_mass_and_momentum(dim):
    """Grid mass = particle mass and grid momentum = particle momentum (relative 1e-13), with stresses,
    affine velocities and inactive slots holding garbage present; inactive slots add nothing.

    2D only: P2G is dimension-generic code, and in 3D its compile alone costs more than this file's
    budget; the 3D rollout below conserves momentum to round-off, which it could not with a P2G that
    does not."""
    scene = _free_scene(dim)
    state = _stirred_state(scene)
    # 37 inactive slots holding garbage (mass, volume, velocity, stress) that must be ignored.
    rng = np.random.default_rng(5)
    k = 37

    def pad(a, junk):
        return jnp.concatenate([a, jnp.asarray(junk, a.dtype)])

    padded = state.replace(
        x=pad(state.x, rng.uniform(0.05, 0.15, (k, dim))), v=pad(state.v, rng.normal(size=(k, dim))),
        C=pad(state.C, rng.normal(size=(k, dim, dim))), F=pad(state.F, 1.5 * np.eye(dim)[None].repeat(k, 0)),
        bbar_e=pad(state.bbar_e, np.eye(3)[None].repeat(k, 0)), vol0=pad(state.vol0, np.ones(k)),
        mass=pad(state.mass, np.ones(k)), gamma_dot=pad(state.gamma_dot, np.zeros(k)),
        active=pad(state.active, np.zeros(k, bool)))
    grid = make_grid(scene, DX)
    act = np.asarray(padded.active)
    mass = np.asarray(padded.mass)[act]
    momentum = (mass[:, None] * np.asarray(padded.v)[act]).sum(axis=0)
    grid_mv, grid_m = jax.jit(p2g, static_argnums=2)(padded, PARAMS, grid, 1e-3)
    assert abs(float(jnp.sum(grid_m)) - mass.sum()) <= 1e-13 * mass.sum()
    scale = float(np.sum(mass * np.linalg.norm(np.asarray(padded.v)[act], axis=1)))
    np.testing.assert_allclose(np.asarray(jnp.sum(grid_mv, axis=0)), momentum, rtol=0, atol=1e-13 * scale)
    assert float(jnp.min(grid_m)) >= 0.0
    # (The 37 inactive slots hold 37 kg: had they contributed, both sums above would be off by far.)


def _totals(state, params):
    """Per-frame record: total mass kg, total momentum kg m/s (d,), sum m|v| kg m/s, least distance of
    the material to the walls of the 0.2 m domain, m."""
    m = jnp.where(state.active, state.mass, 0.0)
    return dict(mass=jnp.sum(m), momentum=jnp.sum(m[:, None] * state.v, axis=0),
                scale=jnp.sum(m * jnp.sqrt(jnp.sum(state.v * state.v, axis=1))),
                wall_gap=jnp.min(jnp.where(state.active[:, None], jnp.minimum(state.x, 0.2 - state.x), 0.1)))


@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
def test_rollout_conserves_mass_and_momentum(dim):
    """With gravity off, no floor, no plates and the material 0.06 m from the walls, a stirred
    elastoplastic block (translation, spin, shear, pre-strain) keeps its total momentum to 1e-12 of
    sum m|v| over ~100-150 substeps, and its total mass exactly."""
    scene = _free_scene(dim)
    state0 = _stirred_state(scene, seed=1)
    frames = (0.01, 0.02, 0.03) if dim == 2 else (0.01, 0.02)
    sim = Simulator(scene, frames, PARAMS, DX, state0=state0, max_speed=1.0)
    final, rec, health = sim.rollout(PARAMS, observe=_totals)
    sim.check(rec, health)
    print(f"dim {dim}: {sim.total_substeps} substeps, dt {sim.dt:.3g} s, {int(state0.active.sum())} particles")
    m0 = float(jnp.sum(state0.mass))
    assert np.all(np.asarray(rec["mass"]) == m0), "total mass changed"
    assert np.array_equal(np.asarray(final.mass), np.asarray(state0.mass))
    p0 = np.asarray(jnp.sum(state0.mass[:, None] * state0.v, axis=0))
    scale = float(np.min(rec["scale"]))
    drift = np.max(np.abs(np.asarray(rec["momentum"]) - p0[None, :])) / scale
    print(f"dim {dim}: momentum drift {drift:.2e} of sum m|v|")
    assert drift <= 1e-12
    # Not trivial: the velocity field changed (stresses acted) while the material stayed off the walls.
    dv = float(jnp.max(jnp.abs(final.v - state0.v)))
    assert dv > 1e-3, f"velocities barely changed ({dv:.1e} m/s): the test would not see a force bug"
    assert float(np.min(rec["wall_gap"])) > 0.04


@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
def test_g2p_reproduces_affine_field(dim):
    """Grid velocities v_i = A x_i + b (m/s) give particle v_p = A x_p + b and C_p = A (1/s) to round-off."""
    scene = _free_scene(dim)
    state = init_state(scene, DX)
    grid = make_grid(scene, DX)
    rng = np.random.default_rng(3)
    A = rng.normal(size=(dim, dim)) * 4.0
    b = rng.normal(size=dim)
    nodes = np.asarray(grid.node_positions(jnp.float64))
    grid_v = jnp.asarray(nodes @ A.T + b[None, :])
    v, C = jax.jit(g2p, static_argnums=2)(state, grid_v, grid)
    x = np.asarray(state.x)
    np.testing.assert_allclose(np.asarray(v), x @ A.T + b[None, :], rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(C), np.broadcast_to(A, C.shape), rtol=0, atol=1e-11)
