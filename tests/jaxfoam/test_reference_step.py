"""The plain reference step: MLS-MPM with the Herschel-Bulkley return map (model.md eq. 11-16), written
as directly as possible (3^d scatter-adds, full (N, d, d) arrays, a bisection for the plastic rate, no
buffers, layouts or custom derivative rules), as the oracle for `jaxfoam.step` under every `Tuning`
variant, both sides of every switch, in 2D and 3D, float64 and float32, with a sticky shaken plate, a
Coulomb floor and slip walls."""
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam as jf
from jaxfoam._xla_cpu import BUFFERS, PLAIN, XLA_CPU

SQRT_2_3 = math.sqrt(2.0 / 3.0)


def _weights(x, grid):
    """Quadratic B-spline stencil: base node (N, d) int and per-axis weights [3 x (N, d)]."""
    xg = (x - jnp.asarray(grid.origin, x.dtype)[None, :]) / grid.dx
    base = jnp.floor(xg - 0.5).astype(jnp.int32)
    fx = xg - base.astype(xg.dtype)
    return base, fx, [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]


def _rate(a, b, eta, m):
    """gamma > 0 with eta gamma^m + a gamma = b (b > 0), by bisection on ln gamma."""
    lo = jnp.full_like(b, -80.0)
    hi = jnp.log(b / a) + 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        g = jnp.exp(mid)
        over = eta * g ** m + a * g > b
        lo, hi = jnp.where(over, lo, mid), jnp.where(over, mid, hi)
    return jnp.exp(0.5 * (lo + hi))


def _return_map(b, f, p, dt):
    """bbar_e (N, 3, 3), f (N, 3, 3) -> (bbar_e new, plastic rate): elastic predictor and HB return."""
    fbar = f * jnp.linalg.det(f)[:, None, None] ** (-1.0 / 3.0)
    pre = fbar @ b @ jnp.swapaxes(fbar, 1, 2)
    tr3 = jnp.trace(pre, axis1=1, axis2=2) / 3.0
    dev = pre - tr3[:, None, None] * jnp.eye(3, dtype=b.dtype)[None]
    s_pre = p.mu * jnp.sqrt(jnp.sum(dev * dev, axis=(1, 2)))
    excess = s_pre - SQRT_2_3 * p.sigma_y
    yielding = excess > 0
    a = 2.0 * p.mu * tr3 * dt
    gamma = jnp.where(yielding, _rate(a, jnp.where(yielding, excess, 1.0), p.eta, p.m), 0.0)
    ratio = jnp.where(yielding, (s_pre - a * gamma) / jnp.where(yielding, s_pre, 1.0), 1.0)
    ret = dev * ratio[:, None, None] + tr3[:, None, None] * jnp.eye(3, dtype=b.dtype)[None]
    ret = ret / jnp.linalg.det(ret)[:, None, None] ** (1.0 / 3.0)
    return jnp.where(yielding[:, None, None], ret, pre), gamma


def _boundaries(v, node_x, scene, t):
    """Sticky plates, the floor (Coulomb friction on approaching nodes), slip walls; v (G, d) m/s."""
    for plate in scene.plates:
        inside = jnp.all(jnp.abs(node_x - plate.position(t)[None, :]) <= plate.half_size[None, :], axis=1)
        v = jnp.where(inside[:, None], plate.velocity(t)[None, :], v)
    if scene.floor_y is not None:
        vn = v[:, 1]
        tang = jnp.concatenate([v[:, :1], v[:, 2:]], axis=1)
        speed = jnp.sqrt(jnp.sum(tang ** 2, axis=1))
        scale = jnp.maximum(speed + scene.floor_friction * vn, 0.0) / jnp.where(speed > 0, speed, 1.0)
        ruled = jnp.concatenate([tang[:, :1] * scale[:, None], jnp.zeros_like(vn)[:, None],
                                 tang[:, 1:] * scale[:, None]], axis=1)
        hit = (node_x[:, 1] <= scene.floor_y) & (vn < 0)
        v = jnp.where(hit[:, None], ruled, v)
    lo, hi = jnp.asarray(scene.domain_min, v.dtype)[None, :], jnp.asarray(scene.domain_max, v.dtype)[None, :]
    v = jnp.where(node_x <= lo, jnp.maximum(v, 0.0), v)
    return jnp.where(node_x >= hi, jnp.minimum(v, 0.0), v)


def reference_step(state, p, scene, grid, dt):
    """One MLS-MPM substep of dt s (particles in (N, d, d) form; inactive slots carry no mass)."""
    x, d = state.x, state.dim
    base, fx, w = _weights(x, grid)
    strides = np.cumprod((grid.shape[1:] + (1,))[::-1])[::-1]
    J = jnp.linalg.det(state.F)
    b = state.bbar_e
    dev = (b - jnp.trace(b, axis1=1, axis2=2)[:, None, None] / 3.0 * jnp.eye(3, dtype=b.dtype)[None])[:, :d, :d]
    tau = p.mu * dev + 0.5 * p.kappa * (J * J - 1.0)[:, None, None] * jnp.eye(d, dtype=x.dtype)[None]
    mass = jnp.where(state.active, state.mass, 0.0)
    vol = jnp.where(state.active, state.vol0, 0.0)
    affine = -dt * 4.0 / grid.dx ** 2 * vol[:, None, None] * tau + mass[:, None, None] * state.C
    nodes = []
    for off in itertools.product(range(3), repeat=d):
        wt = math.prod(w[off[k]][:, k] for k in range(d))
        idx = jnp.sum((base + jnp.asarray(off, jnp.int32)[None, :]) * jnp.asarray(strides, jnp.int32)[None, :], axis=1)
        r = (jnp.asarray(off, x.dtype)[None, :] - fx) * grid.dx  # x_i - x_p, m
        nodes.append((wt, idx, r))
    gm = jnp.zeros(grid.num_nodes, x.dtype)
    gmv = jnp.zeros((grid.num_nodes, d), x.dtype)
    for wt, idx, r in nodes:
        gm = gm.at[idx].add(wt * mass)
        gmv = gmv.at[idx].add(wt[:, None] * (mass[:, None] * state.v + jnp.einsum("nij,nj->ni", affine, r)))
    gv = jnp.where(gm[:, None] > 0, gmv / jnp.where(gm > 0, gm, 1.0)[:, None] + dt * scene.gravity[None, :], 0.0)
    gv = _boundaries(gv, grid.node_positions(x.dtype), scene, state.t + dt)
    v = jnp.zeros_like(state.v)
    C = jnp.zeros_like(state.C)
    for wt, idx, r in nodes:
        v = v + wt[:, None] * gv[idx]
        C = C + 4.0 / grid.dx ** 2 * wt[:, None, None] * gv[idx][:, :, None] * r[:, None, :]
    f = jnp.eye(d, dtype=x.dtype)[None] + dt * C
    f3 = jnp.zeros((x.shape[0], 3, 3), x.dtype).at[:, :d, :d].set(f)
    f3 = f3.at[:, 2, 2].set(1.0) if d == 2 else f3
    bnew, gamma = _return_map(b, f3, p, dt)
    keep = state.active
    return state.replace(x=jnp.where(keep[:, None], x + dt * v, x), v=jnp.where(keep[:, None], v, 0.0),
                         C=jnp.where(keep[:, None, None], C, 0.0),
                         F=jnp.where(keep[:, None, None], f @ state.F, state.F),
                         bbar_e=jnp.where(keep[:, None, None], bnew, b), gamma_dot=jnp.where(keep, gamma, 0.0),
                         t=state.t + dt)


def _scene(dim, dtype):
    """A yielding block under a shaken sticky plate, above a Coulomb floor, inside slip walls (SI)."""
    z = [0.0] * (dim - 2)
    return jf.load_scene({
        "kind": "hanging_plate", "dim": dim, "gravity": [0.0, -9.81] + z, "density": 80.0, "kappa": 2000.0,
        "domain": {"min": [-0.06, 0.0] + [-0.03] * (dim - 2), "max": [0.06, 0.11] + [0.03] * (dim - 2)},
        "floor": {"y": 0.0, "friction": 0.5},
        "plate": {"center": [0.0, 0.095] + z, "half_size": [0.04, 0.008] + [0.02] * (dim - 2),
                  "motion": {"type": "sinusoid", "axis": [1.0, 0.0] + z, "amplitude": 0.004, "frequency": 8.0},
                  "sticky": True},
        "initial_shape": {"type": "box", "min": [-0.03, 0.005] + [-0.015] * (dim - 2),
                          "max": [0.03, 0.088] + [0.015] * (dim - 2)}}, dtype=dtype)


PARAMS = jf.Params(mu=300.0, kappa=2000.0, sigma_y=15.0, eta=4.0, m=0.6, rho=80.0)
STEPS = 12
# Every buffer point off one at a time, every switch flipped, and the two ends, in 2D float64; the ends
# in 3D; the ends and the float32-only switch (the g2p loop) in 2D float32.
VARIANTS = ([("xla_cpu", XLA_CPU), ("plain", PLAIN)]
            + [(f"no_{b}", XLA_CPU.replace(buffers=XLA_CPU.buffers - {b})) for b in sorted(BUFFERS)]
            + [(f"flip_{k}", XLA_CPU.replace(**{k: not getattr(XLA_CPU, k)}))
               for k in ("g2p_loop_2d_float32", "halley_low_precision", "sort_by_cell")])
CASES = ([("2d-f64", 2, jnp.float64, v) for v in VARIANTS]
         + [("3d-f64", 3, jnp.float64, v) for v in VARIANTS[:2]]
         + [("2d-f32", 2, jnp.float32, v) for v in VARIANTS[:2] + [VARIANTS[-3]]])


def _model(dim, dtype, tuning=None):
    """The model and its sampled initial state (a jittered sample, seed 1)."""
    model = jf.make_model(_scene(dim, dtype), 0.01 if dim == 2 else 0.015, params_ref=PARAMS, dtype=dtype,
                          tuning=tuning)
    return model, model.sample(seed=1)


def _steps(fn, s0):
    return jax.jit(lambda s: jax.lax.fori_loop(0, STEPS, lambda i, s: fn(s), s))(s0)


_REFERENCE = {}


def _reference(dim, dtype):
    if (dim, dtype) not in _REFERENCE:
        model, s0 = _model(dim, dtype)
        p = PARAMS.astype(dtype)
        ref = _steps(lambda s: reference_step(s, p, model.scene, model.grid, model.dt), s0)
        assert float(jnp.max(ref.gamma_dot)) > 0, "no particle yields: the return map is not exercised"
        assert float(jnp.max(jnp.abs(ref.x - s0.x))) > 1e-4, "nothing moved"
        _REFERENCE[dim, dtype] = ref
    return _REFERENCE[dim, dtype]


# The fast tier runs the default tuning in 2D float64; the other variants are in the slow tier.
@pytest.mark.parametrize("case,dim,dtype,variant", [
    pytest.param(*c, id=f"{c[0]}-{c[3][0]}", marks=() if c[:2] == ("2d-f64", 2) and c[3][0] == "xla_cpu"
                 else pytest.mark.slow) for c in CASES])
def test_step_equals_the_reference_step_under_every_tuning(case, dim, dtype, variant):
    """jaxfoam.step (12 substeps) equals the plain reference step: positions to 1e-12 m and the stress
    state to 1e-10 in float64 (1e-6 m and 1e-4 in float32, where sums run in another order). A sorted
    step (sort_by_cell acts per rollout frame) is the same step: sorting is checked in test_sort.py."""
    ref = _reference(dim, dtype)
    model, s0 = _model(dim, dtype, variant[1])
    p = PARAMS.astype(dtype)
    out = _steps(lambda s: jf.step(model, s, p), s0)
    f64 = dtype == jnp.float64
    np.testing.assert_allclose(out.x, ref.x, rtol=0, atol=1e-12 if f64 else 1e-6)
    np.testing.assert_allclose(out.v, ref.v, rtol=0, atol=1e-9 if f64 else 2e-4)
    np.testing.assert_allclose(out.F, ref.F, rtol=0, atol=1e-10 if f64 else 1e-4)
    np.testing.assert_allclose(out.bbar_e, ref.bbar_e, rtol=0, atol=1e-10 if f64 else 1e-4)
    np.testing.assert_allclose(out.gamma_dot, ref.gamma_dot, rtol=1e-7 if f64 else 2e-2,
                               atol=1e-9 * float(jnp.max(ref.gamma_dot)) if f64 else 1e-3)


@pytest.mark.slow
def test_reference_step_detects_a_wrong_step():
    """The oracle would catch a real bug: a 1% error in the yield stress moves the result well past
    the tolerances above."""
    model, s0 = _model(2, jnp.float64)
    out = _steps(lambda s: jf.step(model, s, PARAMS), s0)
    p = PARAMS.replace(sigma_y=PARAMS.sigma_y * 1.01)
    ref = _steps(lambda s: reference_step(s, p, model.scene, model.grid, model.dt), s0)
    assert float(jnp.max(jnp.abs(out.bbar_e - ref.bbar_e))) > 1e-8
