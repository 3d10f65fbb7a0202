"""Resampling (jaxfoam.resample): conservation of mass, volume and momentum; insertion only inside the
material's SDF (cavities and the outside stay empty); merging leaves no pair closer than its radius."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam
from jaxfoam import resample as R

from helpers import central_difference

DX = 1.0 / 32
CENTER = 0.5
R_OUT, R_IN = 0.25, 0.12     # annulus radii before stretching, m
STRETCH = 1.8                # x is stretched by this factor: spacing 0.9 dx along x, sparse cells


def _scene(dim):
    lo, hi = [0.0] * dim, [1.0] * dim
    return jaxfoam.load_scene(dict(kind="drop", dim=dim, density=100.0, kappa=1000.0,
                                   domain=dict(min=lo, max=hi),
                                   initial_shape=dict(type="ellipse", center=[CENTER] * dim, radii=[R_OUT] * dim)))


def _stretched_annulus(dim, dx, seed=0):
    """An annulus (a spherical shell in 3D) sampled at 2^d points per cell, then stretched along x by
    STRETCH, with random velocities, masses and velocity gradients (so conservation is not trivial)."""
    scene = _scene(dim)
    st = jaxfoam.init_state(scene, dx, 2 ** dim, rho=100.0, seed=seed)
    x = np.asarray(st.x)[np.asarray(st.active)]
    x = x[np.linalg.norm(x - CENTER, axis=1) > R_IN]
    n = len(x)
    x[:, 0] = CENTER + STRETCH * (x[:, 0] - CENTER)
    rng = np.random.default_rng(seed)
    mass = 100.0 * dx ** dim / 2 ** dim * rng.uniform(0.5, 1.5, n)
    state = jaxfoam.make_state(x, mass / 100.0, mass, v=rng.normal(size=(n, dim)), capacity=2 * n)
    C = jnp.where(state.active[:, None, None], jnp.asarray(rng.normal(size=(2 * n, dim, dim))), 0.0)
    return scene, state.replace(C=C)


def _totals(s):
    m = jnp.where(s.active, s.mass, 0.0)
    return float(jnp.sum(m)), float(jnp.sum(jnp.where(s.active, s.vol0, 0.0))), np.asarray(jnp.sum(m[:, None] * s.v, 0))


def _unstretch(x):
    x = np.array(x)
    x[:, 0] = CENTER + (x[:, 0] - CENTER) / STRETCH
    return x


@pytest.mark.slow
def test_insert_conserves_mass_volume_momentum_and_respects_sdf_2d():
    """Insertion moves mass and momentum from neighbours to new points: totals unchanged to round-off;
    every new point lies where the material SDF is negative, inside the stretched annulus, and none in
    its cavity (a hole of 7.7 dx diameter) or outside."""
    scene, st = _stretched_annulus(2, DX)
    grid = jaxfoam.make_grid(scene, DX)
    cfg = R.ResampleConfig()
    out, stats = jax.jit(lambda s, k: R.resample_with_stats(s, grid, cfg, k))(st, jax.random.PRNGKey(3))
    new = np.asarray(out.active & ~st.active)
    assert int(stats["inserted"]) == new.sum() >= 20, "the stretched annulus has sparse cells to fill"
    m0, v0, p0 = _totals(st)
    m1, v1, p1 = _totals(out)
    assert abs(m1 - m0) <= 1e-13 * m0
    assert abs(v1 - v0) <= 1e-13 * v0
    assert np.max(np.abs(p1 - p0)) <= 1e-12 * np.sum(np.abs(np.asarray(st.mass)[:, None] * np.asarray(st.v)))
    xn = np.asarray(out.x)[new]
    assert np.all(np.asarray(stats["sdf"](jnp.asarray(xn))) < 0)
    r = np.linalg.norm(_unstretch(xn) - CENTER, axis=1)
    spacing = DX / 2
    assert r.min() > R_IN - spacing and r.max() < R_OUT + spacing, (r.min(), r.max())
    # Material points stay admissible: masses positive, bbar_e unimodular, det F > 0.
    act = np.asarray(out.active)
    assert np.all(np.asarray(out.mass)[act] > 0)
    assert np.allclose(np.asarray(jaxfoam.det(out.bbar_e))[act], 1.0, atol=1e-12)
    assert np.all(np.asarray(jaxfoam.det(out.F))[act] > 0)
    # New points take a share comparable to their neighbours' (not a sliver, not a lump).
    mn = np.asarray(out.mass)[new]
    mo = np.asarray(out.mass)[act & ~new]
    assert 0.2 * np.median(mo) < np.median(mn) < 2.0 * np.median(mo)
    # A whole pass (merge, then insertion) leaves no pair closer than the merge distance: insertion
    # keeps insert_radius (> merge_radius) from every point.
    xa = np.asarray(out.x)[act]
    D = np.linalg.norm(xa[:, None] - xa[None], axis=-1)
    np.fill_diagonal(D, np.inf)
    assert D.min() >= cfg.merge_radius * cfg.spacing(DX, 2), (D.min(), cfg.merge_radius * cfg.spacing(DX, 2))


@pytest.mark.slow
def test_material_sdf_fills_gaps_but_keeps_wide_cavities():
    """The closing of two rows of points 1.5 dx apart (a gap narrower than 2 R = 2 dx) is material
    between the rows; the inside of a ring 8 dx across is not, nor is the outside."""
    from jaxfoam.sdf import material_sdf
    t = np.linspace(0.2, 0.8, 40)
    rows = np.concatenate([np.stack([t, np.full_like(t, 0.30)], 1),
                           np.stack([t, np.full_like(t, 0.30 + 1.5 * DX)], 1)])
    ang = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    ring = np.concatenate([np.stack([0.5 + rr * np.cos(ang), 0.7 + rr * np.sin(ang)], 1)
                           for rr in (4 * DX, 4.5 * DX, 5 * DX)])
    x = jnp.asarray(np.concatenate([rows, ring]))
    sdf = material_sdf(x, jnp.ones(len(x), bool), (0.0, 0.0), (32, 32), DX, closing_radius=1.0, refine=2)
    phi = np.asarray(sdf(jnp.asarray([[0.5, 0.30 + 0.75 * DX],      # between the rows
                                      [0.5, 0.7],                   # centre of the ring's cavity
                                      [0.5, 0.30 - 1.0 * DX],       # outside, below the rows
                                      [0.5, 0.7 + 4.5 * DX]])))     # inside the ring's wall
    assert phi[0] < 0 and phi[3] < 0
    assert phi[1] > 0 and phi[2] > 0


def test_merge_removes_every_close_pair_and_conserves():
    """Merging 1,512 random points (many pairs closer than the radius, plus a clump of 12 within
    0.3 radius) leaves no pair closer than the radius; mass, momentum and centre of mass are kept."""
    scene = _scene(2)
    grid = jaxfoam.make_grid(scene, DX)
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(0.3, 0.7, (1500, 2)), 0.5 + rng.normal(scale=0.002, size=(12, 2))])
    n = len(x)
    m = rng.uniform(0.5, 1.5, n)
    v = rng.normal(size=(n, 2))
    st = jaxfoam.make_state(x, m / 100, m, v=v, capacity=n + 8)
    radius = R.ResampleConfig().merge_radius * DX / 2
    out, removed = jax.jit(lambda s: R.merge(s, grid, radius, R.ResampleConfig().merge_rounds))(st)
    xa = np.asarray(out.x)[np.asarray(out.active)]
    D = np.linalg.norm(xa[:, None] - xa[None], axis=-1)
    np.fill_diagonal(D, np.inf)
    assert D.min() >= radius
    assert int(removed) == n - len(xa) > 300
    mo = np.asarray(jnp.where(out.active, out.mass, 0.0))
    assert abs(mo.sum() - m.sum()) <= 1e-13 * m.sum()
    np.testing.assert_allclose(np.sum(mo[:, None] * np.asarray(out.v), 0), np.sum(m[:, None] * v, 0),
                               rtol=0, atol=1e-12 * np.abs(m[:, None] * v).sum())
    np.testing.assert_allclose(np.sum(mo[:, None] * np.asarray(out.x), 0) / mo.sum(),
                               np.sum(m[:, None] * x, 0) / m.sum(), rtol=0, atol=1e-14)


@pytest.mark.slow
def test_resample_3d_conserves_and_stays_inside():
    """The same contract in 3D (one implementation for both dimensions)."""
    dx = 1.0 / 16  # the cavity is 3.8 dx across in y and z: wider than the closing's 2 dx
    scene, st = _stretched_annulus(3, dx, seed=2)
    grid = jaxfoam.make_grid(scene, dx)
    cfg = R.ResampleConfig(sdf_refine=1)
    out, stats = jax.jit(lambda s, k: R.resample_with_stats(s, grid, cfg, k))(st, jax.random.PRNGKey(0))
    new = np.asarray(out.active & ~st.active)
    assert new.sum() >= 5
    m0, v0, p0 = _totals(st)
    m1, v1, p1 = _totals(out)
    assert abs(m1 - m0) <= 1e-13 * m0 and abs(v1 - v0) <= 1e-13 * v0
    assert np.max(np.abs(p1 - p0)) <= 1e-12 * np.sum(np.abs(np.asarray(st.mass)[:, None] * np.asarray(st.v)))
    xn = np.asarray(out.x)[new]
    assert np.all(np.asarray(stats["sdf"](jnp.asarray(xn))) < 0)
    r = np.linalg.norm(_unstretch(xn) - CENTER, axis=1)
    assert r.min() > R_IN - dx / 2 and r.max() < R_OUT + dx / 2


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="merge_radius"):
        R.ResampleConfig(merge_radius=0.6, insert_radius=0.5).validate(2)
    with pytest.raises(ValueError, match="ppc"):
        R.ResampleConfig(ppc=5).validate(2)
    with pytest.raises(ValueError, match="every"):
        R.ResampleConfig(every=0).validate(3)


@pytest.mark.slow
def test_gradient_with_resampling_and_fracture_matches_finite_differences():
    """jax.grad of a rollout observable (the mass-weighted mean height after 20 substeps of a hanging
    block whose lower part is stretched, plus two stray points) with respect to mu, with resampling
    every 10 substeps and fracture on, agrees with central differences to 1e-5 and is finite.

    Approximation: resampling and fracture decisions (which points merge, which candidates are
    accepted, which points are weak) are made on stop-gradient values and are piecewise constant in
    mu; the derivative flows through the mass-weighted transfers and the strain release. Finite
    differences see the same decisions while the step in mu is small enough not to flip one.
    """
    from jaxfoam.fracture import FractureConfig
    dx = 0.01
    scene = jaxfoam.load_scene(dict(
        kind="hanging_plate", dim=2, density=100.0, kappa=2000.0, domain=dict(min=[-0.1, 0.0], max=[0.1, 0.2]),
        plate=dict(center=[0.0, 0.18], half_size=[0.05, 0.005],
                   motion=dict(type="sinusoid", amplitude=0.005, frequency=5.0)),
        initial_shape=dict(type="box", min=[-0.04, 0.12], max=[0.04, 0.178])))
    params = jaxfoam.Params(mu=200.0, kappa=2000.0, sigma_y=20.0, eta=2.0, m=0.6, rho=100.0)
    x = np.asarray(jaxfoam.init_state(scene, dx, rho=100.0).x)
    y = np.where(x[:, 1] < 0.16, 0.16 - 1.7 * (0.16 - x[:, 1]), x[:, 1])   # stretched: sparse cells
    x = np.concatenate([np.stack([x[:, 0], y], 1), [[0.07, 0.05], [-0.07, 0.06]]])  # + weak strays
    vol = np.full(len(x), dx * dx / 4)
    st0 = jaxfoam.make_state(x, vol, 100.0 * vol, capacity=2 * len(x))
    sim = jaxfoam.Simulator(scene, [0.002, 0.004], params, dx, state0=st0, substeps=10,
                            resample=R.ResampleConfig(every=10), fracture=FractureConfig())

    def observable(mu):
        final, _, health = sim.rollout(params.replace(mu=mu), adjoint=jaxfoam.Autodiff())
        m = jnp.where(final.active, final.mass, 0.0)
        return jnp.sum(m * final.x[:, 1]) / jnp.sum(m), (jnp.sum(final.active), health[0])

    vg = jax.jit(jax.value_and_grad(observable, has_aux=True))
    (value, (n_active, ok)), grad = vg(200.0)
    assert bool(np.all(np.asarray(ok))) and np.isfinite(float(grad)) and float(grad) != 0.0
    assert int(n_active) > int(np.sum(np.asarray(st0.active))), "resampling inserted points"
    eps = 1e-3  # Pa: 5e-6 relative
    fd = central_difference(lambda mu: vg(mu)[0][0], 200.0, h=eps)
    assert abs(float(fd) - float(grad)) <= 1e-5 * abs(float(grad)), (float(fd), float(grad))
