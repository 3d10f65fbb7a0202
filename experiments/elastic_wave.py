"""Elastic column: oscillation period and P-wave speed against linear elasticity, 2D and 3D, 3 resolutions.

Setup: an elastic column (sigma_y far above any stress, so the model is a compressible neo-Hookean
solid with the volumetric energy of eq. 1) of height H and width H/4 stands on a sticky floor, free on
its sides and top, away from the domain walls. At t = 0 gravity is switched on (the column starts at
rest, unstressed). The bulk modulus is kappa = 2/3 mu, i.e. Poisson's ratio 0 (Lame lambda = 0): an
axial strain then causes no lateral stress or strain, so the free column deforms in exact uniaxial
strain and the 1D solution below holds in 2D plane strain and in 3D alike. (Lateral confinement by the
domain's slip walls was tried first: material next to a slip wall is spuriously soft in this MPM, see
slump.py, and the period came out 19% long at H/dx = 8.)

Linear solution: u_y(y, t) with the P-wave modulus M = kappa + 4/3 mu = 2 mu (the model linearizes to
Kirchhoff tau = kappa tr(eps) I + 2 mu dev(eps)); wave equation rho u_tt = M u_yy - rho g, u(0) = 0
(sticky floor), u_y(H) = 0 (free top). The suddenly loaded response is a sum of the modes
sin((2n+1) pi y / (2H)) with angular frequencies (2n+1) pi c / (2H), c = sqrt(M / rho), so every
quantity, e.g. the centre of mass, is periodic with period
    T = 4 H / c.
Gravity is small (static strain rho g H / M = 4e-5), keeping finite-strain corrections negligible.

Measured: the centre-of-mass height y_cm(t) over PERIODS periods; its period is the mean spacing of the
up-crossings of y_cm - mean (linear interpolation between frames), and the wave speed is c_meas = 4 H / T.
Also reported: the amplitude decay per period (numerical dissipation of the explicit MLS-MPM).

Usage: python -m experiments elastic_wave [--quick]. Writes experiments/results/elastic_wave[_quick].png/.md.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C

NAME = "elastic_wave"
# An elastic foam-like solid: sigma_y = 1e9 Pa never yields (the yield test is s > sqrt(2/3) sigma_y).
# kappa = 2/3 mu: Poisson's ratio 0 (see the docstring).
PARAMS = jaxfoam.Params(mu=1000.0, kappa=2000.0 / 3.0, sigma_y=1e9, eta=0.0, m=1.0, rho=80.0)
HEIGHT = 0.1            # column height H, m
WIDTH = 0.025           # column width (and depth in 3D), m; the 1D solution holds for any width (nu = 0)
GRAVITY = 1.0           # m/s^2: static strain rho g H / M = 4e-5
PERIODS = 6             # periods simulated
FRAMES_PER_PERIOD = 40  # samples of y_cm per period
CFL = 0.3               # jaxfoam.CFL


def wave_speed() -> float:
    """Linear P-wave speed sqrt((kappa + 4/3 mu) / rho), m/s."""
    return math.sqrt((float(PARAMS.kappa) + 4.0 / 3.0 * float(PARAMS.mu)) / float(PARAMS.rho))


def column_scene(dim: int):
    d = dim
    lo = [-WIDTH / 2, 0.0] + ([-WIDTH / 2] if d == 3 else [])
    hi = [WIDTH / 2, HEIGHT] + ([WIDTH / 2] if d == 3 else [])
    room = [2 * WIDTH, 1.5 * HEIGHT] + ([2 * WIDTH] if d == 3 else [])
    spec = {"kind": "drop", "dim": d, "gravity": [0.0, -GRAVITY] + [0.0] * (d - 2), "density": float(PARAMS.rho),
            "kappa": float(PARAMS.kappa), "domain": {"min": [-room[0], 0.0] + [-r for r in room[2:]], "max": room},
            "floor": {"y": 0.0, "friction": "sticky"},
            "initial_shape": {"type": "box", "min": lo, "max": hi},
            "notes": "free elastic column (Poisson ratio 0) on a sticky floor, gravity switched on at t = 0"}
    return jaxfoam.load_scene(spec)


def crossing_period(t, y):
    """Mean period (s) from the up-crossings of y - mean(y), linearly interpolated; NaN if < 2 crossings."""
    z = y - np.mean(y)
    idx = np.nonzero((z[:-1] < 0) & (z[1:] >= 0))[0]
    tc = t[idx] - z[idx] * (t[idx + 1] - t[idx]) / (z[idx + 1] - z[idx])
    return float(np.mean(np.diff(tc))) if len(tc) >= 2 else float("nan")


def run(dim: int, res: int):
    """One column at H/dx = res. Returns dict(dim, res, dx, period, speed, errors, decay, series, ...)."""
    scene = column_scene(dim)
    dx = HEIGHT / res
    grid = jaxfoam.make_grid(scene, dx)
    st = jaxfoam.init_state(scene, dx, None, rho=float(PARAMS.rho))
    c = wave_speed()
    T = 4.0 * HEIGHT / c
    frame_dt = T / FRAMES_PER_PERIOD
    substeps = int(math.ceil(frame_dt / (CFL * dx / c)))
    dt = frame_dt / substeps
    n_frames = PERIODS * FRAMES_PER_PERIOD

    def observe(s, p):
        w = s.mass * s.active
        return jnp.sum(w * s.x[:, 1]) / jnp.sum(w)

    f = jax.jit(functools.partial(C.rollout, grid=grid, n_frames=n_frames, substeps=substeps, observe=observe))
    with C.Timer() as tm:
        _, ycm = f(st, PARAMS, scene, dt)
        ycm = np.asarray(ycm)
    t = frame_dt * np.arange(1, n_frames + 1)
    period = crossing_period(t, ycm)
    amp = [np.ptp(ycm[k * FRAMES_PER_PERIOD:(k + 1) * FRAMES_PER_PERIOD]) for k in range(PERIODS)]
    decay = float((amp[-1] / amp[0]) ** (1.0 / (PERIODS - 1)))
    return dict(dim=dim, res=res, dx=dx, period=period, period_exact=T, err=period / T - 1.0,
                speed=4.0 * HEIGHT / period, decay=decay, t=t, ycm=ycm, particles=int(st.active.sum()),
                steps=substeps * n_frames, seconds=tm.seconds)


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    resolutions = (8, 16) if args.quick else (8, 16, 32)
    runs = []
    for dim in (2, 3):
        for res in resolutions:
            r = run(dim, res)
            print(f"{dim}D H/dx={res}: period {r['period']:.6g} s (exact {r['period_exact']:.6g}), "
                  f"rel. error {r['err']:.3e}, amplitude ratio per period {r['decay']:.4f} ({r['seconds']:.0f} s)",
                  flush=True)
            runs.append(r)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    ax = axes[0]
    T = runs[0]["period_exact"]
    for k, r in enumerate(runs):
        if r["dim"] == 2:
            ax.plot(r["t"] / T, (r["ycm"] - HEIGHT / 2) * 1e6, "-", lw=1, color=f"C{k}", label=f"2D H/dx={r['res']}")
    ax.set_xlabel("t / (4 H / c)")
    ax.set_ylabel("centre-of-mass height - H/2 (micrometre)")
    ax.set_title("Confined elastic column under suddenly applied gravity")
    ax.legend(fontsize=8)
    ax = axes[1]
    for dim, mk in ((2, "o-"), (3, "s--")):
        rr = [r for r in runs if r["dim"] == dim]
        ax.loglog([r["dx"] for r in rr], [abs(r["err"]) for r in rr], mk, label=f"{dim}D |period error|")
    ax.set_xlabel("dx (m)")
    ax.set_ylabel("|T_MPM / (4H/c) - 1|")
    ax.set_title("Period (and P-wave speed) error against dx")
    ax.legend(fontsize=8)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    rows = []
    for dim in (2, 3):
        rr = [r for r in runs if r["dim"] == dim]
        ords = C.orders([r["dx"] for r in rr], [abs(r["err"]) for r in rr])
        for r, o in zip(rr, ords):
            rows.append([f"{dim}D", r["res"], r["dx"], r["particles"], r["steps"], r["period"], r["period_exact"],
                         r["err"], o, r["speed"], r["decay"], r["seconds"]])
    body = (f"Column H = {HEIGHT} m, mu = {float(PARAMS.mu):g} Pa, kappa = {float(PARAMS.kappa):g} Pa, "
            f"rho = {float(PARAMS.rho):g} kg/m^3: c = sqrt((kappa + 4/3 mu)/rho) = {wave_speed():.5g} m/s, "
            f"T = 4H/c = {4 * HEIGHT / wave_speed():.5g} s; CFL {CFL}, {PERIODS} periods.\n\n"
            + C.md_table(["dim", "H/dx", "dx m", "particles", "steps", "period s", "exact s", "rel. error", "order",
                          "wave speed m/s", "amplitude ratio per period", "wall s"], rows))
    C.write_md(NAME, args.quick, "Elastic column: period and wave speed", body)


if __name__ == "__main__":
    main()
