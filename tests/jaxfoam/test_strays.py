"""Stray points (debris with no neighbour within a cell): the fracture stage keeps them finite.

A point shed by a thinning neck has no neighbours; the fracture stage releases its shear every
substep, so nothing resists its affine velocity C, and before the release made F isotropic its F
integrated f = I + dt C into singular values that part exponentially until det F lost all precision
(a lone shaving-cream point dropped on the floor at 1.2 m/s: condition number 8e15 at 0.21 s,
non-finite at 0.23 s in float32). These tests check the contract of `jaxfoam.fracture.release` and
that lone point's fate. Units: SI.
"""
import jax
import pytest
import jax.numpy as jnp
import numpy as np

import jaxfoam
from jaxfoam.fracture import FractureConfig, release

# Shaving-cream foam (docs/materials.md) and a stray point lighter than a sampled one (1e-5 kg at
# dx 10 mm, 8 per cell): the debris of the showcase scene weighed 1.9e-6 to 8.2e-6 kg.
PARAMS = jaxfoam.Params(mu=120.0, kappa=3000.0, sigma_y=90.0, eta=30.0, m=0.4, rho=80.0)
DX = 0.01          # m
MASS = 2e-6        # kg
V_DROP = (0.3, -1.2, 0.1)   # m/s: the landing speed of the stray that failed first, plus sliding


@pytest.mark.slow
def test_release_makes_weak_F_isotropic_and_keeps_the_stress():
    """Weak points: F = min(J, 1)^(1/d) I and bbar_e = I, so the Kirchhoff stress equals
    kappa/2 (min(J,1)^2 - 1) I (compression kept, stretch released) whatever F's shape was;
    strong points are untouched. 2D and 3D."""
    rng = np.random.default_rng(1)
    for d in (2, 3):
        n = 6
        F = np.eye(d)[None] + 0.4 * rng.normal(size=(n, d, d))
        F[:, 0, 0] *= 5.0       # strongly anisotropic
        F[1] *= 0.7             # compressed ...
        F[2] *= 1.3             # ... and stretched weak points
        J = np.linalg.det(F)
        assert np.all(J > 0)
        st = jaxfoam.make_state(rng.normal(size=(n, d)), np.full(n, 1e-6), np.full(n, 1e-4))
        bbar = np.eye(3)[None] + 0.1 * rng.normal(size=(n, 3, 3))
        st = st.replace(F=jnp.asarray(F), bbar_e=jnp.asarray(bbar))
        weak = jnp.asarray([True, True, True, False, True, False])
        out = release(st, weak)
        Fo, Bo = np.asarray(out.F), np.asarray(out.bbar_e)
        for i in range(n):
            if weak[i]:
                Jr = min(J[i], 1.0)
                np.testing.assert_allclose(Fo[i], Jr ** (1.0 / d) * np.eye(d), rtol=1e-12, atol=1e-15)
                np.testing.assert_allclose(Bo[i], np.eye(3), atol=0)
            else:
                np.testing.assert_array_equal(Fo[i], F[i])
                np.testing.assert_array_equal(Bo[i], bbar[i])
        tau = np.asarray(jaxfoam.kirchhoff_stress(out.F, out.bbar_e, PARAMS))
        for i in np.flatnonzero(np.asarray(weak)):
            Jr = min(J[i], 1.0)
            np.testing.assert_allclose(tau[i][:d, :d], 0.5 * 3000.0 * (Jr ** 2 - 1.0) * np.eye(d),
                                       rtol=1e-10, atol=1e-9)


@pytest.mark.slow
def test_lone_point_dropped_on_the_floor_stays_finite_float32():
    """A lone foam point (2e-6 kg) dropped on the floor at 1.2 m/s with fracture on, float32, 0.4 s
    (1,400 substeps): every frame finite, 0 < J <= 1, F isotropic (condition number 1 to 1e-5),
    mass unchanged; the point lands and stays on the floor (no deeper than 0.5 mm) and slows
    (friction) below 0.15 m/s. Before the fix it turned non-finite at 0.23 s."""
    scene = jaxfoam.load_scene(dict(
        kind="drop", dim=3, gravity=[0.0, -9.81, 0.0], density=80.0, kappa=3000.0,
        domain=dict(min=[-0.03, 0.0, -0.03], max=[0.03, 0.05, 0.03]), floor=dict(y=0.0, friction=0.5),
        initial_shape=dict(type="ellipse", center=[0.0, 0.02, 0.0], radii=[0.01] * 3)))
    st = jaxfoam.make_state(np.array([[0.0013, 0.012, 0.0021]]), np.array([MASS / 80.0]), np.array([MASS]),
                            v=np.array([V_DROP]), dtype=jnp.float32)
    times = 0.02 * np.arange(1, 21)
    sim = jaxfoam.Simulator(scene, times, PARAMS, DX, dtype=jnp.float32, state0=st, fracture=FractureConfig(),
                            substeps=70)

    def obs(s, p):
        sv = jnp.linalg.svd(s.F, compute_uv=False)
        return dict(x=s.x, v=s.v, J=jaxfoam.det(s.F), cond=sv[:, 0] / sv[:, -1], mass=s.mass)

    final, fr, health = sim.rollout(PARAMS, observe=obs, adjoint=jaxfoam.Autodiff())
    fr = jax.device_get(fr)
    sim.check(fr, health)
    assert np.all(np.isfinite(fr["x"])) and np.all(np.isfinite(fr["v"]))
    assert np.all(fr["J"] > 0) and np.all(fr["J"] <= 1.0 + 1e-6), fr["J"].ravel()
    assert np.all(np.abs(fr["cond"] - 1.0) < 1e-5), fr["cond"].ravel()
    np.testing.assert_array_equal(fr["mass"], np.float32(MASS))
    y = fr["x"][:, 0, 1]
    assert y[-1] < 0.002 and y.min() > -0.0005, y       # landed, not sunk into the floor
    speed = np.linalg.norm(fr["v"][:, 0], axis=-1)
    assert speed[-1] < 0.15, speed
