"""Gradients of a rollout observable: autodiff against finite differences, every AD route agreeing.

Scene: a small 2D hanging plate (192 particles, dx = 5 mm, 4 frames of 50 substeps = 200 substeps,
float64): a 4 x 3 cm block of foam whose top 2.5 mm sits inside a sticky plate that oscillates
sideways; with sigma_y = 8 Pa most of the block yields under its weight and the shaking. The observable
is the mean height of the foam at the last frame (m).

Why central differences are clean here (the model has discrete switches; this setup keeps each of
them either smooth or constant over an FD step):
  - the time step is fixed when the Simulator is built, so perturbed runs take the same substeps;
  - the yield switch: with m = 0.5 < 1 the plastic rate grows like (s - s_Y)^(1/m) = (s - s_Y)^2
    past yield, so the return map is C1 across the yield surface (no kink for FD to straddle);
  - B-spline weights: particles crossing cell boundaries change the quadratic weights C1-smoothly;
  - collider membership of grid nodes is discrete, but the plate moves along x only, its y-extent
    is fixed (its lower face lies between two node rows), and its x-edges stay > 2 cells away from
    the foam, so no node that carries mass ever changes membership; the floor and walls are never
    reached. Amplitude and frequency therefore act through the plate velocity, which is smooth.
  - The FD estimates at steps h and h/2 agree (checked), which would fail across a discontinuity.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam as jf

from helpers import central_difference

SCENE = {
    "kind": "hanging_plate", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 2000.0,
    "domain": {"min": [-0.06, 0.0], "max": [0.06, 0.12]}, "floor": {"y": 0.0, "friction": 0.5},
    "plate": {"center": [0.0, 0.1025], "half_size": [0.045, 0.005],
              "motion": {"type": "sinusoid", "axis": [1.0, 0.0], "amplitude": 0.003, "frequency": 5.0,
                         "phase": 0.0, "ramp_time": 0.0},
              "sticky": True},
    "initial_shape": {"type": "box", "min": [-0.02, 0.07], "max": [0.02, 0.1]},
}
PARAMS = jf.Params(mu=200.0, kappa=2000.0, sigma_y=8.0, eta=5.0, m=0.5, rho=80.0)
DX = 0.005          # m
FRAMES = 4
SUBSTEPS = 50       # per frame: 200 substeps of 0.2 ms
FRAME_DT = 0.01     # s
WRT = ("mu", "sigma_y", "eta", "m", "plate0.amplitude", "plate0.frequency")
FD_REL_STEP = 1e-4  # central-difference step relative to the input's value
RTOL_FD = 1e-4
RTOL_MODES = 1e-8


def mean_height(frames):
    """Mean height of the active particles at the last frame, m."""
    w = frames["active"][-1].astype(frames["x"].dtype)
    return jnp.sum(frames["x"][-1, :, 1] * w) / jnp.sum(w)


def _sim(frames):
    scene = jf.load_scene(SCENE)
    return jf.Simulator(scene, [FRAME_DT * (k + 1) for k in range(frames)], PARAMS, dx=DX, ppc=4,
                        substeps=SUBSTEPS)


@pytest.fixture(scope="module")
def sim():
    s = _sim(FRAMES)
    assert s.state0.x.shape[0] < 300 and s.total_substeps == 200
    return s


@pytest.fixture(scope="module")
def rev(sim):
    """Value and gradient by reverse mode through the per-frame checkpoints."""
    return jf.observable_jacobian(sim, PARAMS, mean_height, WRT, jf.HandWritten())


@pytest.fixture(scope="module")
def forward(sim):
    """The plain rollout, compiled once (inputs perturbed through arguments): (mean height m,
    fraction of particles yielding at the last frame, health)."""
    def run(p, sc):
        _, frames, health = sim.rollout(p, scene=sc)
        active = frames["active"][-1]
        frac = jnp.sum((frames["gamma_dot"][-1] > 0) & active) / jnp.sum(active)
        return mean_height(frames), frac, health
    return jax.jit(run, compiler_options=dict(sim.model.tuning.compiler_options) or None)


def _perturbed(sim, name, value):
    """(params, scene) with input `name` set to `value`."""
    if name.startswith("plate0."):
        # float64, not weakly typed: the same compiled forward serves every perturbation
        plate = dataclasses.replace(sim.scene.plates[0], **{name[7:]: jnp.asarray(value, jnp.float64)})
        return PARAMS, dataclasses.replace(sim.scene, plates=(plate,))
    return PARAMS.replace(**{name: value}), sim.scene


def _base_value(sim, name):
    if name.startswith("plate0."):
        return float(getattr(sim.scene.plates[0], name[7:]))
    return float(getattr(PARAMS, name))


@pytest.mark.slow
def test_rollout_yields_and_stays_finite(sim, forward, rev):
    """The setup exercises plasticity (otherwise sigma_y, eta, m would have no effect)."""
    h, frac, health = forward(PARAMS, sim.scene)
    sim.check({}, health)
    assert float(frac) > 0.3
    assert float(h) == pytest.approx(float(rev.value), rel=1e-13)
    assert all(bool(jnp.all(jnp.isfinite(j))) for j in rev.jacobian.values())


@pytest.mark.slow
@pytest.mark.parametrize("name", WRT)
def test_gradient_matches_central_differences(sim, rev, forward, name):
    """d(mean height)/d(input) by reverse mode equals the central difference to 1e-4 relative
    (reverse mode equals forward mode: see the long-rollout test)."""
    x0 = _base_value(sim, name)

    def central(h):
        return float(central_difference(lambda x: forward(*_perturbed(sim, name, x))[0], x0, h=h))

    h = FD_REL_STEP * abs(x0)
    fd, fd_half = central(h), central(0.5 * h)
    ad = float(rev.jacobian[name])
    # the observable is smooth over the step: halving it changes the estimate by O(h^2) only
    assert abs(fd - fd_half) <= 0.1 * RTOL_FD * abs(fd), f"{name}: FD not converged ({fd} vs {fd_half})"
    assert abs(ad - fd) <= RTOL_FD * abs(fd), f"{name}: autodiff {ad} vs central difference {fd}"
    # and it is not trivially small: a 1% change of the input moves the foam by > 1 micrometre
    assert abs(ad * x0) * 0.01 > 1e-6


# The other inputs the derivative promises: the bulk modulus, the density (through the particle
# masses rho * vol0), gravity and the initial state. Each as (direction in its input's space,
# central-difference step, a typical change), the step and the change in the input's unit. A sideways
# shift of the initial positions is not among them: by the scene's symmetry it barely moves the mean
# height (d/dx 2.5e-4), and central differences of it scatter by 1e-5 relative.
OTHER_DIRECTIONS = {
    "kappa": (1.0, 0.2, 20.0),                          # Pa: step 1e-4 of kappa, change 1%
    "rho": (1.0, 0.008, 0.8),                           # kg/m^3
    "gravity": (np.array([0.0, 1.0]), 1e-3, 0.1),       # m/s^2, along y
    "state0.v": (np.array([0.0, 1.0]), 1e-5, 0.1),      # m/s: every particle's initial velocity along +y
    "state0.x": (np.array([0.0, 1.0]), 1e-6, 1e-3),     # m: every particle shifted along +y
}


@pytest.fixture(scope="module")
def forward_inputs(sim):
    """The plain rollout's mean height as a function of (params, state0, scene), compiled once."""
    def run(p, s0, sc):
        return mean_height(sim.rollout(p, state0=s0, scene=sc)[1])
    return jax.jit(run, compiler_options=dict(sim.model.tuning.compiler_options) or None)


def _along(sim, name, h):
    """(params, state0, scene) with input `name` moved by h along its OTHER_DIRECTIONS direction."""
    direction = OTHER_DIRECTIONS[name][0]
    s0, sc = sim.state0, sim.scene
    if name == "kappa":
        return PARAMS.replace(kappa=PARAMS.kappa + h), s0, sc
    if name == "rho":
        return PARAMS, s0.replace(mass=s0.vol0 * (PARAMS.rho + h)), sc
    if name == "gravity":
        return PARAMS, s0, dataclasses.replace(sc, gravity=jnp.asarray(sc.gravity) + h * direction)
    field = name[7:]  # every particle moved by h along the direction
    return PARAMS, s0.replace(**{field: getattr(s0, field) + h * direction[None, :]}), sc


def _directional(name, jac, sim):
    """The derivative along OTHER_DIRECTIONS[name] from the Jacobian entry `jac`."""
    direction = OTHER_DIRECTIONS[name][0]
    jac = np.asarray(jac)
    if name.startswith("state0."):  # every active particle moved along the direction
        jac = jac * np.asarray(sim.state0.active)[:, None]
    return float(np.sum(jac * direction))


@pytest.mark.slow
def test_kappa_density_gravity_and_initial_state_gradients_match_central_differences(sim, forward_inputs):
    """d(mean height) along the bulk modulus, the density (masses rho * vol0), gravity's y component,
    a uniform initial upward velocity and a uniform upward shift of the initial positions: reverse
    mode equals the central difference to 1e-4 relative, as for the fitted parameters; forward mode
    agrees with reverse mode to 1e-8."""
    names = tuple(OTHER_DIRECTIONS)
    rev = jf.observable_jacobian(sim, PARAMS, mean_height, names, jf.HandWritten())
    fwd = jf.observable_jacobian(sim, PARAMS, mean_height, ("kappa", "rho", "gravity"), jf.ForwardMode())
    for name in names:
        _, step, change = OTHER_DIRECTIONS[name]

        def central(h):
            return float(central_difference(lambda t: forward_inputs(*_along(sim, name, t)), 0.0, h=h))

        fd, fd_half = central(step), central(0.5 * step)
        ad = _directional(name, rev.jacobian[name], sim)
        assert np.all(np.isfinite(np.asarray(rev.jacobian[name])))
        assert abs(fd - fd_half) <= 0.1 * RTOL_FD * abs(fd), f"{name}: FD not converged ({fd} vs {fd_half})"
        assert abs(ad - fd) <= RTOL_FD * abs(fd), f"{name}: autodiff {ad} vs central difference {fd}"
        # not trivially small: a typical change of the input moves the mean height by > 1 micrometre
        assert abs(ad * change) > 1e-6, f"{name}: derivative {ad} too small to test"
        if name in ("kappa", "rho", "gravity"):
            a = _directional(name, fwd.jacobian[name], sim)
            assert abs(a - ad) <= RTOL_MODES * abs(ad), f"{name}: forward {a} vs reverse {ad}"


@pytest.mark.slow
def test_checkpointed_and_plain_reverse_agree(sim, rev):
    """Per-frame rematerialization recomputes the same operations: same gradient to round-off."""
    plain = jf.observable_jacobian(sim, PARAMS, mean_height, WRT, jf.Autodiff())
    for name in WRT:
        a, b = float(rev.jacobian[name]), float(plain.jacobian[name])
        assert abs(a - b) <= 1e-10 * abs(a), f"{name}: checkpointed {a} vs plain tape {b}"


@pytest.mark.slow
def test_long_rollout_gradient_through_checkpoints():
    """2000 substeps (40 frames): reverse mode through per-frame checkpoints is finite and equals
    forward mode (jacfwd, no tape) to 1e-8 relative, for the material parameters and the plate motion.
    The plain-scan tape of this rollout would hold every substep's residuals; with a checkpoint per
    frame and a rematerialized checkpoint per substep inside it (saving only the named values of
    REMAT_SAVED), only the 40 frame states, one frame's 50 substep states and one substep's residuals
    are alive at once. The compiled programs' planned buffers (temp + arguments + outputs; about
    322 MB for the plain tape against 4.9 MB checkpointed) must differ by more than 20x; the memory on
    a grid where the plain tape needs gigabytes is in docs/performance.md."""
    long_sim = _sim(40)
    assert long_sim.total_substeps == 2000
    planned, rev_fns = {}, {}
    for ck in (True, False):
        rev_fns[ck] = jf.make_observable_jacobian(long_sim, mean_height, WRT, jf.HandWritten() if ck else jf.Autodiff())
        mem = rev_fns[ck].lower(PARAMS).compile().memory_analysis()
        planned[ck] = mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes
    assert planned[False] > 20 * planned[True], planned
    r = rev_fns[True](PARAMS)  # compiled above: served from the compilation cache
    f = jf.observable_jacobian(long_sim, PARAMS, mean_height, WRT, jf.ForwardMode())
    long_sim.check({}, r.health)
    assert float(f.value) == pytest.approx(float(r.value), rel=1e-13)
    for name in WRT:
        a, b = float(f.jacobian[name]), float(r.jacobian[name])
        assert np.isfinite(a) and np.isfinite(b) and a != 0.0
        assert abs(a - b) <= RTOL_MODES * abs(a), f"{name}: fwd {a} vs rev {b}"


# float32 derivatives of this rollout differ from float64 by up to 3e-5 relative (d/d mu, the smallest
# relative to its inputs' scale); 3e-4 leaves a 10x margin for other machines' summation orders.
RTOL_FLOAT32 = 3e-4


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["fwd", "rev"])
def test_float32_derivatives_match_float64(sim, rev, mode):
    """The same rollout in float32, from the same particles (the float64 sample rounded) and with the same
    time step: forward-mode and reverse-mode derivatives of the last frame's mean height equal float64's
    to RTOL_FLOAT32 relative for every input. The float32 guards (safe_div's quotient rule, the rate's
    underflow rule) keep them finite; this checks they are also accurate over 200 substeps."""
    scene32 = jf.load_scene(SCENE, dtype=jnp.float32)
    sim32 = jf.Simulator(scene32, [FRAME_DT * (k + 1) for k in range(FRAMES)], PARAMS, dx=DX, ppc=4,
                         substeps=SUBSTEPS, dtype=jnp.float32)
    assert sim32.dt == sim.dt
    state0 = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, sim.state0)
    adjoint = jf.ForwardMode() if mode == "fwd" else jf.HandWritten()
    r32 = jf.observable_jacobian(sim32, PARAMS, mean_height, WRT, adjoint, state0=state0)
    assert float(r32.value) == pytest.approx(float(rev.value), rel=1e-6)
    for name in WRT:
        a, b = float(rev.jacobian[name]), float(r32.jacobian[name])
        assert r32.jacobian[name].dtype == jnp.float32
        assert abs(b - a) <= RTOL_FLOAT32 * abs(a), f"{name}: float32 {b} vs float64 {a}"


@pytest.mark.slow
def test_forward_mode_tangent_routes_agree(sim):
    """Forward mode by one jvp rollout per scalar input (tangents="map", the default, in two threads) gives
    the same per-frame Jacobian as jacfwd's batched tangents (tangents="vmap"), for scalar
    inputs and a vector one (gravity, whose columns must land in the right input slots)."""
    obs = lambda fr: jnp.mean(fr["x"][:, :, 1], axis=1)  # (T,) m
    wrt = ("mu", "plate0.amplitude", "gravity")
    a = jf.observable_jacobian(sim, PARAMS, obs, wrt, jf.ForwardMode("vmap"))
    b = jf.observable_jacobian(sim, PARAMS, obs, wrt, jf.ForwardMode("map", threads=2))
    np.testing.assert_array_equal(np.asarray(a.value), np.asarray(b.value))
    for name in wrt:
        ja, jb = np.asarray(a.jacobian[name]), np.asarray(b.jacobian[name])
        assert ja.shape == jb.shape == (FRAMES,) + np.shape(np.asarray(sim.scene.gravity) if name == "gravity" else 0.0)
        np.testing.assert_allclose(jb, ja, rtol=1e-12, atol=1e-12 * np.max(np.abs(ja)))
    assert np.any(np.asarray(a.jacobian["gravity"])[:, 1] != 0.0)  # the vertical column is non-trivial


@pytest.mark.slow
def test_forward_mode_route_default_is_one_for_every_dimension(sim):
    """One Jacobian default (jaxfoam.adjoint.DEFAULT_JACOBIAN) for 2D and 3D, the fitter's too: one jvp
    rollout per input, in the CPU tuning's two threads; a reverse-mode adjoint runs in one program."""
    from jaxfoam._jacobian import make_observable_jacobian
    from jaxfoam.adjoint import DEFAULT_JACOBIAN
    assert DEFAULT_JACOBIAN == jf.ForwardMode("map")
    f2 = make_observable_jacobian(sim, mean_height)
    assert f2.adjoint == DEFAULT_JACOBIAN and f2.threads == (2 if jax.default_backend() == "cpu" else 1)
    spec = dict(SCENE, dim=3, gravity=[0.0, -9.81, 0.0],
                domain={"min": [-0.06, 0.0, -0.03], "max": [0.06, 0.12, 0.03]},
                plate=dict(SCENE["plate"], center=[0.0, 0.1025, 0.0], half_size=[0.045, 0.005, 0.02],
                           motion=dict(SCENE["plate"]["motion"], axis=[1.0, 0.0, 0.0])),
                initial_shape={"type": "box", "min": [-0.02, 0.07, -0.01], "max": [0.02, 0.1, 0.01]})
    sim3 = jf.Simulator(jf.load_scene(spec), [FRAME_DT], PARAMS, dx=0.01)
    f3 = make_observable_jacobian(sim3, mean_height)
    assert f3.adjoint == DEFAULT_JACOBIAN and f3.threads == f2.threads
    assert make_observable_jacobian(sim3, mean_height, adjoint=jf.HandWritten()).threads == 1


@pytest.mark.slow
def test_simulate_is_differentiable(sim, rev):
    """jaxfoam.simulate under jax.grad (outside jit) returns the derivative of the same discrete map as
    Simulator.rollout: the time step comes from the parameters' values and is held fixed, and the
    masses are rho * vol0, so d/d rho flows through them. jax.jvp agrees; under jit it raises a
    ValueError saying why."""
    scene = jf.load_scene(SCENE)
    times = [FRAME_DT * (k + 1) for k in range(FRAMES)]

    def h(p):
        return mean_height(jf.simulate(scene, p, times, DX, ppc=4, substeps=SUBSTEPS).frames)

    g = jax.grad(h)(PARAMS)
    for name in ("mu", "sigma_y", "eta", "m"):
        a, b = float(rev.jacobian[name]), float(getattr(g, name))
        assert abs(b - a) <= 1e-10 * abs(a), f"{name}: simulate grad {b} vs rollout {a}"
    other = jf.observable_jacobian(sim, PARAMS, mean_height, ("kappa", "rho"), jf.ForwardMode())
    for name in ("kappa", "rho"):
        a, b = float(other.jacobian[name]), float(getattr(g, name))
        assert a != 0.0 and abs(b - a) <= 1e-10 * abs(a), f"{name}: simulate grad {b} vs rollout {a}"
    direction = jax.tree_util.tree_map(lambda v: 0.0 * v, PARAMS).replace(sigma_y=1.0)
    _, t = jax.jvp(h, (PARAMS,), (direction,))
    assert float(t) == pytest.approx(float(g.sigma_y), rel=1e-10)
    assert isinstance(jf.simulate(scene, PARAMS, times[:1], DX, ppc=4, substeps=SUBSTEPS).frames["x"], np.ndarray)
    with pytest.raises(ValueError, match="jit"):
        jax.jit(h)(PARAMS)


@pytest.mark.slow
def test_wrt_validation(sim):
    with pytest.raises(ValueError, match="plate1"):
        jf.observable_jacobian(sim, PARAMS, mean_height, ("plate1.amplitude",))
    with pytest.raises(ValueError, match="unknown"):
        jf.observable_jacobian(sim, PARAMS, mean_height, ("viscosity",))
    with pytest.raises(ValueError, match="adjoint"):
        jf.observable_jacobian(sim, PARAMS, mean_height, ("mu",), adjoint="central")
    with pytest.raises(ValueError, match="tangents"):
        jf.observable_jacobian(sim, PARAMS, mean_height, ("mu",), jf.ForwardMode(tangents="batched"))
