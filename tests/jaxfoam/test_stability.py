"""Explicit time stepping: stable at the CFL bound, and a clear error when it is not.

The step is dt = C dx / (c + v_max), C = jaxfoam.CFL, with the P-wave speed c = sqrt((kappa + 4/3 mu) / rho)
(model.md, "Stable explicit step"). Units: SI.
"""
import re

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam
from jaxfoam import Params, SimulationError, Simulator, load_scene, wave_speed

DX = 0.02  # grid spacing, m
# A stiff foam (c = 39 m/s, ~7x the foams of the other tests) thrown fast at a frictional floor.
STIFF = Params(mu=1e4, kappa=1e5, sigma_y=200.0, eta=20.0, m=0.5, rho=75.0)
THROW = [2.0, -4.0]  # initial velocity, m/s
STABLE_FRAMES = np.linspace(0.004, 0.04, 10)  # s
# The CFL bound with the true largest speed (initial speed + free fall over the run), not the
# Simulator's conservative default (a 1.5x margin and a fall over the domain height), m/s.
V_BOUND = float(np.hypot(*THROW)) + 9.81 * STABLE_FRAMES[-1]


def _scene():
    """A blob 2 cm above a Coulomb floor, moving at 4.5 m/s: it hits the floor after ~5 ms."""
    return load_scene({"kind": "drop", "dim": 2, "density": 75.0, "kappa": 1e5,
                       "domain": {"min": [-0.2, 0.0], "max": [0.2, 0.2]}, "floor": {"y": 0.0, "friction": 0.5},
                       "initial_shape": {"type": "ellipse", "center": [-0.05, 0.08], "radii": [0.05, 0.04]},
                       "initial_velocity": THROW})


def _record(state, params):
    """Per-frame record: positions (m), total energy (J per metre of depth: kinetic + gravitational
    about y = 0 + stored elastic), largest speed (m/s), lowest particle (m), extreme volume ratios J."""
    J = jaxfoam.det(state.F)
    m = jnp.where(state.active, state.mass, 0.0)
    kinetic = 0.5 * jnp.sum(m * jnp.sum(state.v * state.v, axis=1))
    potential = 9.81 * jnp.sum(m * state.x[:, 1])
    stored = jnp.sum(jnp.where(state.active, state.vol0, 0.0) * jaxfoam.energy_density(state.F, state.bbar_e, params))
    return dict(x=state.x, energy=kinetic + potential + stored,
                speed=jnp.max(jnp.sqrt(jnp.sum(state.v * state.v, axis=1))), y_min=jnp.min(state.x[:, 1]),
                J_min=jnp.min(J), J_max=jnp.max(J))


@pytest.mark.slow
def test_stiff_fast_impact_at_cfl_bound_stays_finite():
    """At the CFL bound the stiff, fast blob hits the floor and spreads: everything stays finite and
    uninverted, the total energy (kinetic + gravitational + elastic) never grows (an unstable explicit
    step makes energy; friction, plasticity and the transfers only remove it) and J stays within 30% of 1
    (kappa = 1e5 Pa against an impact pressure ~ rho c v ~ 1.3e4 Pa: measured J >= 0.84)."""
    scene = _scene()
    frames, v_bound = STABLE_FRAMES, V_BOUND
    sim = Simulator(scene, frames, STIFF, DX, max_speed=v_bound)
    c = wave_speed(STIFF)
    assert sim.dt == pytest.approx(jaxfoam.CFL * DX / (c + v_bound), rel=0.1)
    _, rec, health = sim.rollout(STIFF, observe=_record)
    sim.check(rec, health)  # raises SimulationError on any non-finite or inverted state
    speed = np.asarray(rec["speed"])
    print(f"c = {c:.1f} m/s, dt = {sim.dt:.3g} s ({sim.total_substeps} substeps), speeds {np.round(speed, 2)} m/s, "
          f"J in [{float(np.min(rec['J_min'])):.4f}, {float(np.max(rec['J_max'])):.4f}]")
    assert np.all(np.isfinite(speed))
    assert float(np.min(rec["y_min"])) < 0.01, "the blob never reached the floor"
    state0 = sim.state0
    energy0 = float(0.5 * jnp.sum(state0.mass * jnp.sum(state0.v ** 2, axis=1))
                    + 9.81 * jnp.sum(state0.mass * state0.x[:, 1]))
    energy = np.asarray(rec["energy"])
    print(f"energy / initial: {np.round(energy / energy0, 4)}")
    assert energy.max() <= energy0 * (1 + 1e-3)
    assert speed.max() <= 1.5 * v_bound  # local splash speeds may exceed the bulk speed, not by 50%
    assert 0.7 < float(np.min(rec["J_min"])) and float(np.max(rec["J_max"])) < 1.3


@pytest.mark.slow
@pytest.mark.parametrize("stretch", [4.0, 25.0])
def test_unstable_step_raises_simulation_error(stretch):
    """The same scene, frame count and substep count as the stable run (the compiled rollout is
    reused), with frames `stretch` times further apart: c dt / dx = 1.04 (just past the limit: measured
    stable at 0.78) or 6.5 (far past it). The rollout blows up and `check` (what `simulate` calls)
    raises SimulationError naming the frame, its time and the first bad quantity, and the position
    of the bad particle in the previous frame when there is one."""
    scene = _scene()
    stable = Simulator(scene, STABLE_FRAMES, STIFF, DX, max_speed=V_BOUND)
    frames = stretch * STABLE_FRAMES
    sim = Simulator(scene, frames, STIFF, DX, substeps=stable.substeps)
    assert wave_speed(STIFF) * sim.dt / DX > 1.0
    _, rec, health = sim.rollout(STIFF, observe=_record)
    with pytest.raises(SimulationError) as info:
        sim.check(rec, health)
    msg = str(info.value)
    print(msg)
    k = re.search(r"frame (\d+)", msg)
    assert k is not None, msg
    t = re.search(r"t = ([0-9.e+-]+) s", msg)
    assert t is not None and float(t.group(1)) == pytest.approx(frames[int(k.group(1))], rel=1e-5), msg
    assert re.search(r"quantity '(x|v|C|F|bbar_e|J <= 0 \(inverted\))'", msg), msg
    if int(k.group(1)) > 0:
        pos = re.search(r"at position \[([^\]]+)\] m \(previous frame\)", msg)
        assert pos is not None and np.all(np.isfinite([float(v) for v in pos.group(1).split(",")])), msg


@pytest.mark.slow
def test_unstable_step_raises_under_grad_too():
    """`jaxfoam.simulate` differentiated (jax.grad outside jit) still checks the rollout on the host: the
    far-unstable case above raises SimulationError instead of returning a NaN gradient."""
    import jax

    scene = _scene()
    stable = Simulator(scene, STABLE_FRAMES, STIFF, DX, max_speed=V_BOUND)

    def height(p):
        tr = jaxfoam.simulate(scene, p, 25.0 * STABLE_FRAMES, DX, substeps=stable.substeps)
        return jnp.mean(tr.frames["x"][-1, :, 1])

    with pytest.raises(SimulationError, match="frame"):
        jax.grad(height)(STIFF)
