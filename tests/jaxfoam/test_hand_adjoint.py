"""The hand-written reverse-mode derivatives of particle-to-grid and grid-to-particle
(`jaxfoam._xla_cpu.transfers._p2g_transfer`, `_g2p_transfer`), and particle-to-grid's hand-written
forward-mode rule (`jaxfoam._xla_cpu.transfers._p2g_impl`).

Contract: the vector-Jacobian product of each transfer equals the transpose of the transfer's
automatic derivative (to round-off), and central finite differences of the transfer (float64); a
rollout differentiated in reverse mode with `adjoint=HandWritten()` gives the gradient that plain
autodiff gives; forward mode through it is refused (a custom VJP has no JVP). The forward-mode rule
of particle-to-grid equals autodiff's JVP of the same scatter, and its transpose autodiff's VJP.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam as jf
from jaxfoam._grid import Grid, _flat_index, _stencil
from jaxfoam._xla_cpu import XLA_CPU
from jaxfoam._xla_cpu.transfers import _g2p_impl, _g2p_transfer, _p2g_impl, _p2g_scatter, _p2g_transfer
from jaxfoam.adjoint import HandWritten, checkpoint_blocks

from helpers import central_difference

# The tuning the transfers run with (its buffer points on, as on the CPU backend).
TUNING = XLA_CPU

# The substep's start time the transfers' conds test (s); any finite value.
T0 = 0.25

RTOL_AD = 1e-12   # hand-written VJP vs autodiff's transpose: round-off only
RTOL_FD = 1e-7    # vs central differences (h = 1e-6 of the grid spacing or of the value)


def _setup(d, n=40, seed=0):
    """A 10^d-node grid of spacing 0.1 m and n particles well inside it, with random payloads."""
    rng = np.random.default_rng(seed)
    grid = Grid(origin=(0.0,) * d, dx=0.1, shape=(10,) * d)
    x = jnp.asarray(rng.uniform(0.25, 0.7, (n, d)))
    mvA = jnp.asarray(rng.normal(size=(n, d)))            # momentum, kg m/s
    A = jnp.asarray(rng.normal(size=(n, d, d)))           # affine payload, kg/s
    mass = jnp.asarray(rng.uniform(0.5, 2.0, n))          # kg
    grid_v = jnp.asarray(rng.normal(size=(grid.num_nodes, d)))  # m/s
    return rng, grid, x, mvA, A, mass, grid_v


def _idx0(x, grid):
    return _flat_index(_stencil(x, grid)[0], (0,) * x.shape[1], grid)


def _joined(out):
    """(momentum (G, d), mass (G,)) as one (G, d + 1) table."""
    return jnp.concatenate([out[0], out[1][:, None]], axis=1)


def _p2g_plain(grid, idx0):
    """Particle to grid with no custom derivative rule anywhere (autodiff's reference)."""
    def f(x, mvA, A, mass):
        _, fx, w = _stencil(x, grid)
        return _p2g_scatter(grid, fx, w, idx0, mvA, A, mass)
    return f


def _g2p_plain(grid, idx0):
    return lambda x, grid_v: _g2p_impl(x, grid_v, grid, idx0, T0, TUNING)


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.slow
@pytest.mark.parametrize("d", [2, 3])
def test_p2g_adjoint_equals_autodiff_transpose(d):
    """d<ct, grid>/d(x, mv, A, mass): hand-written = autodiff, to round-off (2D and 3D)."""
    rng, grid, x, mvA, A, mass, _ = _setup(d)
    idx0 = _idx0(x, grid)
    ct = jnp.asarray(rng.normal(size=(grid.num_nodes, d + 1)))
    _, vjp_ad = jax.vjp(_p2g_plain(grid, idx0), x, mvA, A, mass)
    out, vjp_hand = jax.vjp(lambda *a: _joined(_p2g_transfer(grid, TUNING, a[0], idx0, *a[1:], T0)), x, mvA, A, mass)
    np.testing.assert_allclose(out, _p2g_plain(grid, idx0)(x, mvA, A, mass), rtol=0, atol=0)
    for name, a, b in zip(("x", "mv", "A", "mass"), vjp_hand(ct), vjp_ad(ct)):
        assert _rel(a, b) <= RTOL_AD, f"{name}: relative difference {_rel(a, b):.2e}"


@pytest.mark.slow
@pytest.mark.parametrize("d", [2, 3])
def test_p2g_forward_rule_equals_autodiff_jvp_and_transposes(d):
    """Tangent of the grid along (dx, dmv, dA, dmass): the hand-written rule
    W (dmv - A dx + dA r) + (grad W . dx)(mv + A r) equals autodiff's JVP to round-off (2D and 3D), and
    reverse mode through the rule (its transpose) equals autodiff's VJP."""
    rng, grid, x, mvA, A, mass, _ = _setup(d, seed=2)
    idx0 = _idx0(x, grid)
    args = (x, mvA, A, mass)
    tangents = tuple(jnp.asarray(rng.normal(size=a.shape)) for a in args)
    ruled = lambda *a: _joined(_p2g_impl(grid, False, a[0], idx0, *a[1:]))
    out, t_rule = jax.jvp(ruled, args, tangents)
    out_ad, t_ad = jax.jvp(_p2g_plain(grid, idx0), args, tangents)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(out_ad))
    assert _rel(t_rule, t_ad) <= RTOL_AD, f"tangent: relative difference {_rel(t_rule, t_ad):.2e}"
    # each input alone (a wrong term in one of them cannot hide behind the others)
    for k, name in enumerate(("x", "mv", "A", "mass")):
        only = tuple(t if i == k else jnp.zeros_like(t) for i, t in enumerate(tangents))
        a, b = jax.jvp(ruled, args, only)[1], jax.jvp(_p2g_plain(grid, idx0), args, only)[1]
        assert _rel(a, b) <= RTOL_AD, f"{name}: relative difference {_rel(a, b):.2e}"
    ct = jnp.asarray(rng.normal(size=out.shape))
    for name, a, b in zip(("x", "mv", "A", "mass"), jax.vjp(ruled, *args)[1](ct),
                          jax.vjp(_p2g_plain(grid, idx0), *args)[1](ct)):
        assert _rel(a, b) <= RTOL_AD, f"vjp {name}: relative difference {_rel(a, b):.2e}"


@pytest.mark.slow
@pytest.mark.parametrize("d", [2, 3])
def test_g2p_adjoint_equals_autodiff_transpose(d):
    """d<(cv, cC), (v, C)>/d(x, grid_v): hand-written = autodiff, to round-off (2D and 3D)."""
    rng, grid, x, _, _, _, grid_v = _setup(d)
    idx0 = _idx0(x, grid)
    n = x.shape[0]
    ct = (jnp.asarray(rng.normal(size=(n, d))),
          tuple(tuple(jnp.asarray(rng.normal(size=n)) for _ in range(d)) for _ in range(d)))
    _, vjp_ad = jax.vjp(_g2p_plain(grid, idx0), x, grid_v)
    _, vjp_hand = jax.vjp(lambda x_, g_: _g2p_transfer(grid, TUNING, x_, g_, idx0, T0), x, grid_v)
    for name, a, b in zip(("x", "grid_v"), vjp_hand(ct), vjp_ad(ct)):
        assert _rel(a, b) <= RTOL_AD, f"{name}: relative difference {_rel(a, b):.2e}"


def _of_arg(f, args, k):
    """f as a function of its k-th argument, the others held at args."""
    return lambda a: f(*args[:k], a, *args[k + 1:])


@pytest.mark.slow
@pytest.mark.parametrize("d", [2, 3])
def test_transfer_adjoints_match_central_differences(d):
    """Directional derivatives <hand VJP, e> equal central differences of <ct, transfer(. + h e)>,
    for random directions e in each input (positions move by 1e-6 of a cell: no stencil change)."""
    rng, grid, x, mvA, A, mass, grid_v = _setup(d, n=12, seed=1)
    idx0 = _idx0(x, grid)
    ct_grid = jnp.asarray(rng.normal(size=(grid.num_nodes, d + 1)))
    p2g_scalar = lambda *a: jnp.vdot(ct_grid, _joined(_p2g_transfer(grid, TUNING, a[0], idx0, *a[1:], T0)))
    args = (x, mvA, A, mass)
    grads = jax.grad(p2g_scalar, argnums=(0, 1, 2, 3))(*args)
    for k, name in enumerate(("x", "mv", "A", "mass")):
        e = jnp.asarray(rng.normal(size=args[k].shape))
        h = 1e-6 * (grid.dx if k == 0 else 1.0)
        fd = float(central_difference(_of_arg(p2g_scalar, args, k), args[k], e, h=h))
        ad = float(jnp.vdot(grads[k], e))
        assert abs(fd - ad) <= RTOL_FD * abs(ad), f"p2g {name}: FD {fd} vs hand {ad}"

    n = x.shape[0]
    cv = jnp.asarray(rng.normal(size=(n, d)))
    cC = jnp.asarray(rng.normal(size=(n, d, d)))

    def g2p_scalar(x_, g_):
        v, C = _g2p_transfer(grid, TUNING, x_, g_, idx0, T0)
        return jnp.vdot(cv, v) + sum(jnp.vdot(cC[:, i, j], C[i][j]) for i in range(d) for j in range(d))

    g_args = (x, grid_v)
    gx, gg = jax.grad(g2p_scalar, argnums=(0, 1))(*g_args)
    for k, (name, g) in enumerate((("x", gx), ("grid_v", gg))):
        e = jnp.asarray(rng.normal(size=g.shape))
        h = 1e-6 * (grid.dx if k == 0 else 1.0)
        fd = float(central_difference(_of_arg(g2p_scalar, g_args, k), g_args[k], e, h=h))
        ad = float(jnp.vdot(g, e))
        assert abs(fd - ad) <= RTOL_FD * abs(ad), f"g2p {name}: FD {fd} vs hand {ad}"


SCENE_2D = {
    "kind": "hanging_plate", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 2000.0,
    "domain": {"min": [-0.08, 0.0], "max": [0.08, 0.14]}, "floor": {"y": 0.0, "friction": 0.5},
    "plate": {"center": [0.0, 0.1225], "half_size": [0.06, 0.01],
              "motion": {"type": "sinusoid", "axis": [1.0, 0.0], "amplitude": 0.003, "frequency": 5.0,
                         "phase": 0.0, "ramp_time": 0.0},
              "sticky": True},
    "initial_shape": {"type": "box", "min": [-0.03, 0.07], "max": [0.03, 0.12]},
}
PARAMS = jf.Params(mu=200.0, kappa=2000.0, sigma_y=8.0, eta=5.0, m=0.5, rho=80.0)


@pytest.mark.slow
def test_rollout_gradient_same_with_hand_adjoint():
    """Reverse mode through a 2D rollout (yielding foam under a shaken sticky plate, 2 frames of 10
    substeps): the gradient w.r.t. the material parameters, the plate amplitude and the initial
    positions is the same with the hand-written transfer adjoints as with autodiff's (relative 1e-10).
    (3D: the transfers are checked above; a 3D rollout pair compiles for ~35 s, too long for CI.)"""
    sim = jf.Simulator(jf.load_scene(SCENE_2D), [0.01, 0.02], PARAMS, dx=0.01, substeps=10)

    def loss(params, x0, amplitude, hand):
        plate = dataclasses.replace(sim.scene.plates[0], amplitude=amplitude)
        scene_ = dataclasses.replace(sim.scene, plates=(plate,))
        adjoint = HandWritten() if hand else jf.Checkpointed()
        fr = sim.rollout(params, state0=sim.state0.replace(x=x0), scene=scene_, adjoint=adjoint)[1]
        w = fr["active"].astype(fr["x"].dtype)
        return jnp.sum(jnp.sin(40.0 * fr["x"]) * w[..., None]) + jnp.sum(fr["s"] * w) * 1e-3

    amp = jnp.asarray(sim.scene.plates[0].amplitude)
    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3,
                   compiler_options=dict(sim.model.tuning.compiler_options) or None)
    grads = {hand: grad(PARAMS, sim.state0.x, amp, hand) for hand in (False, True)}
    ref, got = grads[False], grads[True]
    for name in ("mu", "sigma_y", "eta", "m", "kappa"):
        a, b = float(getattr(got[0], name)), float(getattr(ref[0], name))
        assert b != 0.0 and abs(a - b) <= 1e-10 * abs(b), f"{name}: hand {a} vs autodiff {b}"
    assert _rel(got[1], ref[1]) <= 1e-10
    assert float(ref[2]) != 0.0 and abs(float(got[2]) - float(ref[2])) <= 1e-10 * abs(float(ref[2]))


@pytest.mark.slow
def test_forward_mode_refused_with_hand_adjoint():
    """The hand-written adjoints are reverse-mode only: jvp through such a rollout raises a TypeError
    (and the default rollout stays forward-differentiable)."""
    sim = jf.Simulator(jf.load_scene(SCENE_2D), [0.005], PARAMS, dx=0.02, substeps=2)
    f = lambda mu, hand: jnp.sum(sim.rollout(PARAMS.replace(mu=mu), adjoint=HandWritten() if hand
                                             else jf.Checkpointed())[0].x)
    _, t = jax.jvp(lambda mu: f(mu, False), (200.0,), (1.0,))
    assert np.isfinite(float(t))
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jvp(lambda mu: f(mu, True), (200.0,), (1.0,))


@pytest.mark.slow
def test_reverse_jacobian_of_vector_observable():
    """observable_jacobian(adjoint=HandWritten()) of a per-frame observable (T,): each row equals forward mode's
    (relative 1e-9), and a Jacobian w.r.t. the initial positions has shape (T, N, d) whose last row is
    the gradient of the last frame's value alone."""
    sim = jf.Simulator(jf.load_scene(SCENE_2D), [0.01, 0.02], PARAMS, dx=0.02, substeps=10)

    def heights(fr):
        w = fr["active"].astype(fr["x"].dtype)
        return jnp.sum(fr["x"][:, :, 1] * w, axis=1) / jnp.sum(w, axis=1)

    wrt = ("mu", "sigma_y", "plate0.amplitude")
    rev = jf.observable_jacobian(sim, PARAMS, heights, wrt, HandWritten())
    fwd = jf.observable_jacobian(sim, PARAMS, heights, wrt, jf.ForwardMode())
    for name in wrt:
        assert rev.jacobian[name].shape == (2,)
        np.testing.assert_allclose(rev.jacobian[name], fwd.jacobian[name], rtol=1e-9, err_msg=name)
    jx = jf.observable_jacobian(sim, PARAMS, heights, ("state0.x",), HandWritten()).jacobian["state0.x"]
    assert jx.shape == (2,) + sim.state0.x.shape
    last = jf.observable_jacobian(sim, PARAMS, lambda fr: heights(fr)[-1], ("state0.x",), HandWritten())
    assert last.jacobian["state0.x"].shape == sim.state0.x.shape
    assert _rel(jx[-1], last.jacobian["state0.x"]) <= 1e-12


@pytest.mark.slow
def test_frame_checkpoint_blocks_same_gradient_less_memory():
    """A frame store above `frame_tape_bytes` splits each frame's substeps into checkpointed blocks
    (here 10 substeps -> 4 blocks of 3, 3, 3 and 1): the reverse-mode gradient is the same to 1e-12
    and the compiled program's working memory is smaller; the block count follows the budget."""
    scene = jf.load_scene(SCENE_2D)
    big = jf.Simulator(scene, [0.01, 0.02], PARAMS, dx=0.01, substeps=10)
    assert (checkpoint_blocks(big.state0, big.grid, 10, 2.0 ** 40), checkpoint_blocks(big.state0, big.grid, 10, 1.0)) == (1, 4)
    # A budget far below the store: the cap ceil(sqrt(substeps)); a store that fits: one level.
    assert checkpoint_blocks(big.state0, big.grid, 100, 10.0) == 10
    assert checkpoint_blocks(big.state0, big.grid, 10, 2.0 ** 40) == 1

    def loss(fr):
        w = fr["active"].astype(fr["x"].dtype)
        return jnp.sum(fr["x"][:, :, 1] * w) / jnp.sum(w)

    fns = {k: jf.make_observable_jacobian(big, loss, ("mu", "sigma_y", "eta", "m"), HandWritten(frame_tape_bytes=k))
           for k in (2.0 ** 40, 1.0)}
    out = {k: f(PARAMS) for k, f in fns.items()}
    for name in ("mu", "sigma_y", "eta", "m"):
        a, b = float(out[1.0].jacobian[name]), float(out[2.0 ** 40].jacobian[name])
        assert abs(a - b) <= 1e-12 * abs(b), name
    temp = {k: f.lower(PARAMS).compile().memory_analysis().temp_size_in_bytes for k, f in fns.items()}
    assert temp[1.0] < 0.8 * temp[2.0 ** 40], temp
    with pytest.raises(ValueError, match="frame_tape_bytes"):
        HandWritten(frame_tape_bytes=0)
