"""Linear elasticity limit: a block far below yield vibrates at the frequency elasticity predicts.

Setting: plane strain (2D), no gravity, no floor, no plates; a free bar of length L = 0.2 m along x and
thickness h = 0.04 m along y, far from the domain walls. With sigma_y huge the return map never acts
and the model is the hyperelastic solid of eq. 1-2, whose small-strain limit is linear elasticity with
bulk modulus K = kappa and shear modulus G = mu (bbar_e ~ I + 2 dev(eps), so mu dev(bbar_e) = 2 G dev(eps)).

Expected period. A thin bar (h << L) in plane strain has sigma_yy = 0 (free faces) and eps_zz = 0, so its
axial stress is sigma_xx = E' eps_xx with the plane-strain bar modulus
    E' = M - lambda^2 / M = 4 G (K + G/3) / (K + 4G/3),   M = K + 4G/3,  lambda = K - 2G/3,
and axial waves travel at c_bar = sqrt(E' / rho). The fundamental free-free mode is
u(x, t) = U cos(pi (x - x0) / L) sin(omega t) with omega = pi c_bar / L, i.e. period T = 2 L / c_bar.
Starting from the mode's velocity field v_x = V cos(pi (x - x0) / L), the modal velocity
q(t) = sum m v_x phi / sum m phi^2 (phi the mode shape) follows V cos(omega t): it crosses zero at
T/4, 3T/4, 5T/4. Lateral inertia (Rayleigh) lowers the frequency by a relative
~ (nu' pi r / L)^2 / 2 with r = h / sqrt(12) the radius of gyration: 0.3% here; the MPM discretization
(4 cells across the bar) is the dominant error, hence the 10% tolerance.
"""
import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxfoam import Params, Simulator, init_state, load_scene

KAPPA, MU, RHO = 2000.0, 1000.0, 100.0  # bulk modulus Pa, shear modulus Pa, density kg/m^3
# Yield stress far above any stress reached (|s| ~ E' strain ~ 30 Pa): purely elastic, Pa.
SIGMA_Y_ELASTIC = 1e9
LENGTH, THICKNESS = 0.2, 0.04  # bar length and thickness, m
X0, Y0 = 0.1, 0.08  # bar's lower-left corner, m (domain 0.4 m x 0.2 m: 0.08 m clearance to every wall)
DX = 0.01  # grid spacing, m
V_MODE = 0.05  # modal velocity amplitude, m/s: peak strain V / c_bar ~ 1%, linear regime


def bar_modulus_plane_strain(K, G):
    """E' = 4 G (K + G/3) / (K + 4G/3), Pa: axial modulus of a plane-strain bar with free faces."""
    return 4.0 * G * (K + G / 3.0) / (K + 4.0 * G / 3.0)


def _modal_velocity(state, params):
    """Per-frame record: q = sum m v_x phi / sum m phi^2 (m/s), phi = cos(pi (x - X0) / L); and the
    largest plastic rate (1/s), which must stay 0."""
    phi = jnp.cos(jnp.pi * (state.x[:, 0] - X0) / LENGTH)
    m = jnp.where(state.active, state.mass, 0.0)
    return dict(q=jnp.sum(m * state.v[:, 0] * phi) / jnp.sum(m * phi * phi),
                gamma_max=jnp.max(state.gamma_dot))


def _zero_crossings(t, q):
    """Times (s) where q changes sign, by linear interpolation between frames."""
    s = np.sign(q)
    k = np.nonzero(s[:-1] * s[1:] < 0)[0]
    return t[k] - q[k] * (t[k + 1] - t[k]) / (q[k + 1] - q[k])


@pytest.mark.slow
@pytest.mark.parametrize("dim", [2])
def test_elastic_bar_period(dim):
    """The fundamental axial mode of a free elastic bar has period 2 L / c_bar within 10%.

    3D is left out: its first compile alone takes longer than this whole test (the same
    constitutive code runs in 3D in test_conservation and test_plane_strain)."""
    params = Params(mu=MU, kappa=KAPPA, sigma_y=SIGMA_Y_ELASTIC, eta=1.0, m=1.0, rho=RHO)
    c_bar = math.sqrt(bar_modulus_plane_strain(KAPPA, MU) / RHO)
    period = 2.0 * LENGTH / c_bar
    scene = load_scene({"kind": "drop", "dim": dim, "gravity": [0.0] * dim, "density": RHO, "kappa": KAPPA,
                        "domain": {"min": [0.0, 0.0], "max": [0.4, 0.2]},
                        "initial_shape": {"type": "box", "min": [X0, Y0], "max": [X0 + LENGTH, Y0 + THICKNESS]}})
    state0 = init_state(scene, DX)
    vx = V_MODE * jnp.cos(jnp.pi * (state0.x[:, 0] - X0) / LENGTH)
    state0 = state0.replace(v=jnp.stack([vx, jnp.zeros_like(vx)], axis=1))
    # Frames every T/24 up to 1.35 T: three zero crossings of q, each bracketed to T/24.
    frame_times = period / 24.0 * np.arange(1, 33)
    sim = Simulator(scene, frame_times, params, DX, state0=state0, max_speed=2 * V_MODE)
    _, rec, health = sim.rollout(params, observe=_modal_velocity)
    sim.check(rec, health)
    q = np.concatenate([[V_MODE], np.asarray(rec["q"])])
    t = np.concatenate([[0.0], frame_times])
    crossings = _zero_crossings(t, q)
    assert len(crossings) >= 3, f"expected 3 zero crossings of the modal velocity, got {crossings}"
    measured = crossings[2] - crossings[0]  # one full period: from T/4 to 5T/4
    print(f"period: measured {measured:.5f} s, linear elasticity {period:.5f} s "
          f"({measured / period - 1:+.1%}); {sim.total_substeps} substeps of {sim.dt:.3g} s")
    assert abs(measured / period - 1.0) <= 0.10
    assert float(np.max(rec["gamma_max"])) == 0.0, "the bar yielded: not an elastic test"
    # The first crossing is a quarter period in (a wrong stiffness shifts it too).
    assert abs(crossings[0] / (period / 4) - 1.0) <= 0.15
