"""Fusion boundaries (jaxfoam._xla_cpu.fusion): identities on values and derivatives, kept by XLA."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfoam._xla_cpu.fusion import hoist, materialize_linearization, materialize_tangent


def _grid_fn(x, t):
    # a scalar function of the time broadcast over a grid-sized array, as a plate's motion is
    c = hoist(jnp.stack([jnp.sin(3.0 * t), jnp.cos(2.0 * t)]), t)
    return jnp.sum(jnp.where(x[:, :1] > 0.5, c[None, :], x) ** 2)


def _plain_grid_fn(x, t):
    c = jnp.stack([jnp.sin(3.0 * t), jnp.cos(2.0 * t)])
    return jnp.sum(jnp.where(x[:, :1] > 0.5, c[None, :], x) ** 2)


@pytest.mark.slow
def test_hoist_is_the_identity_on_values_and_gradients():
    x = jnp.asarray(np.random.default_rng(0).random((64, 2)))
    t = jnp.float64(0.37)
    np.testing.assert_allclose(_grid_fn(x, t), _plain_grid_fn(x, t), rtol=1e-15)
    g = jax.grad(_grid_fn, argnums=(0, 1))(x, t)
    g0 = jax.grad(_plain_grid_fn, argnums=(0, 1))(x, t)
    np.testing.assert_allclose(g[0], g0[0], rtol=1e-14)
    np.testing.assert_allclose(g[1], g0[1], rtol=1e-14)
    # a non-finite time gives NaN, as sin(t) would, and integer leaves (grid indices) stay valid: 0
    assert np.isnan(_grid_fn(x, jnp.float64(np.inf)))
    idx = hoist(jnp.arange(5, dtype=jnp.int32) + 7, jnp.float64(np.nan))
    np.testing.assert_array_equal(idx, np.zeros(5, np.int32))
    np.testing.assert_array_equal(hoist(jnp.arange(5, dtype=jnp.int32), jnp.float64(0.0)), np.arange(5))


@pytest.mark.parametrize("boundary", [materialize_tangent, materialize_linearization])
def test_materializing_is_the_identity_in_forward_and_reverse_mode(boundary):
    a = jnp.asarray(np.random.default_rng(1).random((50, 3)))
    ta = jnp.asarray(np.random.default_rng(2).random((50, 3)))
    out, tout = jax.jvp(lambda a: boundary(a, 1e-3), (a,), (ta,))
    np.testing.assert_array_equal(out, a)
    np.testing.assert_array_equal(tout, ta)
    _, vjp = jax.vjp(lambda a: boundary(a, 1e-3), a)
    np.testing.assert_array_equal(vjp(ta)[0], ta)


def test_materialize_linearization_passes_the_primal_through_the_cond():
    a = jnp.asarray(np.random.default_rng(3).random((50, 3)))
    ta = jnp.asarray(np.random.default_rng(4).random((50, 3)))
    # the primal value comes out of the cond in a jvp program (NaN for a non-finite dt, as a time
    # step would give), and the tangent is 0 there
    out, tout = jax.jvp(lambda a: materialize_linearization(a, np.inf), (a,), (ta,))
    assert np.all(np.isnan(out)) and np.all(np.asarray(tout) == 0.0)
    # the primal program alone is the identity, whatever dt
    np.testing.assert_array_equal(materialize_linearization(a, np.inf), a)
    # kept by XLA in the compiled forward-mode program, absent from the primal one
    w, dt = jnp.ones((4, 3)), jnp.float64(1e-3)

    def f(w, dt):
        return jnp.sum(jnp.sin(materialize_linearization(w * 2.0, dt)))
    assert "conditional(" in jax.jit(jax.jacfwd(f)).lower(w, dt).compile().as_text()
    assert "conditional(" not in jax.jit(f).lower(w, dt).compile().as_text()


def test_the_boundary_survives_xla_in_derivative_programs_only():
    """XLA:CPU drops optimization_barrier before fusion; the cond must remain in the compiled
    reverse-mode program (that is the whole point) and the primal program must not pay for it."""
    idx = jnp.asarray([1, 4, 4, 7])

    def f(w, dt):
        grid = jnp.zeros((10, 3)).at[idx].add(w)
        grid = materialize_tangent(grid, dt)
        return jnp.sum(jnp.sin(grid)[idx] * 2.0)

    w = jnp.ones((4, 3))
    dt = jnp.float64(1e-3)
    grad_hlo = jax.jit(jax.grad(f)).lower(w, dt).compile().as_text()
    fwd_hlo = jax.jit(f).lower(w, dt).compile().as_text()
    assert "conditional(" in grad_hlo
    assert "conditional(" not in fwd_hlo


@pytest.mark.slow
def test_a_rollout_vmapped_over_parameters_keeps_its_fusion_boundaries():
    """An ensemble (jax.vmap of a rollout over mu) gives each member's own rollout to round-off, and
    keeps every cond of the substep: their predicates test the time, which the ensemble shares, so
    none turns into a select that computes both branches (a predicate on a particle's position did)."""
    import pathlib

    import jaxfoam as jf

    scenes = pathlib.Path(__file__).parents[2] / "experiments" / "scenes"
    scene = jf.load_scene(str(scenes / "hanging_plate_2d.json"))
    params = jf.Params(kappa=scene.kappa, rho=scene.density, mu=200.0, sigma_y=20.0, eta=5.0, m=0.5)
    sim = jf.Simulator(scene, [0.004], params, dx=0.01)
    mus = jnp.asarray([120.0, 300.0])

    def height(mu):
        fr = sim.rollout(params.replace(mu=mu))[1]
        return (jnp.sum(jnp.where(fr["active"], fr["x"][:, :, 1], 0.0), axis=1)
                / jnp.sum(fr["active"], axis=1).astype(fr["x"].dtype))

    ens = jax.jit(jax.vmap(height))
    out = ens(mus)
    for k in range(2):
        np.testing.assert_allclose(out[k], jax.jit(height)(mus[k]), rtol=1e-12)
    n_member = jax.jit(height).lower(mus[0]).compile().as_text().count("conditional(")
    n_ensemble = ens.lower(mus).compile().as_text().count("conditional(")
    assert n_member >= 3 and n_ensemble == n_member, (n_member, n_ensemble)
