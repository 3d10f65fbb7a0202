"""Gradients against rollout length: where autodiff and finite differences disagree.

For the hanging-plate and drop scenes (experiments/scenes/<scene>_2d.json, the foam of experiments/pareto.py:
mu = 200 Pa, sigma_y = 40 Pa, eta = 10 Pa s^0.5, m = 0.5; a coarse grid of CELLS cells across the width,
4 particles per cell, CFL 0.3, float64) the observable is the mean height of the foam (m) at each of
FRAMES frames. Its derivative with respect to ln mu, ln sigma_y, ln eta and m is computed at every frame
(rollout length t) by forward-mode autodiff (one jvp rollout per parameter) and by central differences
with steps H_COARSE and H_FINE in those coordinates (the time step is fixed, so every run takes the same
substeps). Reported per frame and parameter:

- AD-FD disagreement = |AD - FD(H_FINE)| / max(|AD|, |FD(H_FINE)|, FLOOR);
- FD self-disagreement = |FD(H_COARSE) - FD(H_FINE)| / max(|FD(H_COARSE)|, |FD(H_FINE)|, FLOOR): where it
  is large the observable is not smooth on the scale of the step (contact events, topology changes,
  chaotic amplification), and neither number is a trustworthy derivative for a fit.

FLOOR (m) keeps derivatives that are zero to round-off (before the foam moves) from counting as errors.

Usage: python -m experiments grad_horizon [--quick]. Writes experiments/results/grad_horizon[_quick].png/.md.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C
from experiments import pareto

NAME = "grad_horizon"
CELLS = 32                       # cells across the domain width (coarse: 4 + 16 rollouts per scene)
CFL = 0.3
FRAMES, FRAMES_QUICK = 20, 10
DURATION = {"hanging_plate": 1.0, "drop": 0.5}   # s (half in --quick)
WRT = ("ln mu", "ln sigma_y", "ln eta", "m")
WRT_QUICK = ("ln mu", "ln sigma_y")
H_COARSE, H_FINE = 1e-3, 1e-5    # central-difference steps in the fitted coordinates
FLOOR = 1e-6                     # m per unit coordinate: derivatives below this count as zero
DIM = 2


def params_of(z, scene):
    """Params from z = (ln mu, ln sigma_y, ln eta, m); kappa and rho from the scene."""
    return jaxfoam.Params(mu=jnp.exp(z[0]), kappa=jnp.asarray(scene.kappa, z.dtype), sigma_y=jnp.exp(z[1]),
                          eta=jnp.exp(z[2]), m=z[3], rho=jnp.asarray(scene.density, z.dtype))


def study(name: str, quick: bool):
    _, scene = pareto.load(name, DIM)
    width = scene.domain_max[0] - scene.domain_min[0]
    dx = width / CELLS
    frames = FRAMES_QUICK if quick else FRAMES
    duration = DURATION[name] * (0.5 if quick else 1.0)
    times = np.linspace(duration / frames, duration, frames)
    p0 = jaxfoam.Params(kappa=scene.kappa, rho=scene.density, **pareto.FOAM)
    sim = jaxfoam.Simulator(scene, times, p0, dx, None, dtype=jnp.float64, cfl=CFL)
    z0 = jnp.asarray([np.log(p0.mu), np.log(p0.sigma_y), np.log(p0.eta), p0.m], jnp.float64)

    def observe(s, p):
        w = s.active.astype(s.x.dtype)
        return jnp.sum(s.x[:, 1] * w) / jnp.sum(w)

    roll = functools.partial(C.rollout, grid=sim.grid, n_frames=frames, substeps=sim.substeps, observe=observe)
    dt = jnp.asarray(sim.dt, jnp.float64)

    def heights(z):
        return roll(sim.state0, params_of(z, scene), scene, dt)[1]

    fwd = jax.jit(heights)
    jvp = jax.jit(lambda z, e: jax.jvp(heights, (z,), (e,))[1])
    wrt = WRT_QUICK if quick else WRT
    with C.Timer() as t_compile:
        fwd.lower(z0).compile()
        jvp.lower(z0, z0).compile()
    out = dict(times=times, wrt=wrt, ad={}, fd_coarse={}, fd_fine={}, steps=sim.total_substeps,
               particles=int(np.asarray(sim.state0.active).sum()), dx=dx, compile=t_compile.seconds)
    t_ad = t_fd = 0.0
    for i, label in enumerate(wrt):
        e = jnp.zeros(4, jnp.float64).at[i].set(1.0)
        with C.Timer() as tm:
            out["ad"][label] = np.asarray(jax.block_until_ready(jvp(z0, e)))
        t_ad += tm.seconds
        with C.Timer() as tm:
            for key, h in (("fd_coarse", H_COARSE), ("fd_fine", H_FINE)):
                out[key][label] = (np.asarray(fwd(z0 + h * e)) - np.asarray(fwd(z0 - h * e))) / (2.0 * h)
        t_fd += tm.seconds
        print(f"{name} d/d{label}: AD {out['ad'][label][-1]:.4g}, FD {out['fd_fine'][label][-1]:.4g} at "
              f"t = {times[-1]:g} s", flush=True)
    out["t_ad"], out["t_fd"] = t_ad, t_fd
    return out


def disagreement(a, b):
    return np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), FLOOR)


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    results = {name: study(name, args.quick) for name in ("hanging_plate", "drop")}

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, (name, res) in zip(axes, results.items()):
        for i, label in enumerate(res["wrt"]):
            ad, fc, ff = res["ad"][label], res["fd_coarse"][label], res["fd_fine"][label]
            ax.semilogy(res["times"], np.maximum(disagreement(ad, ff), 1e-16), "o-", color=f"C{i}",
                        label=f"AD vs FD, d/d {label}")
            ax.semilogy(res["times"], np.maximum(disagreement(fc, ff), 1e-16), "x:", color=f"C{i}",
                        label=f"FD {H_COARSE:g} vs {H_FINE:g}, d/d {label}")
        ax.axhline(1e-4, color="k", lw=0.8, ls="--")
        ax.set_xlabel("rollout length (s)")
        ax.set_ylabel("relative disagreement")
        ax.set_title(f"{name}: gradient of the mean height, AD vs central differences", fontsize=9)
        ax.legend(fontsize=6)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    parts = [f"Foam {pareto.FOAM}, kappa and rho from the scene; 2D, {CELLS} cells across the width, ppc 4, CFL {CFL}, "
             f"float64. Observable: mean height of the foam (m) per frame. AD = forward-mode jvp; FD = central "
             f"differences with steps {H_COARSE:g} (coarse) and {H_FINE:g} (fine) in (ln mu, ln sigma_y, ln eta, m). "
             f"Entries: relative disagreement (floor {FLOOR:g} m). Wall times on the shared 2-core machine.\n\n"]
    for name, res in results.items():
        parts.append(f"## {name}\n\ndx = {res['dx']:.4g} m, {res['particles']} particles, {res['steps']} substeps; "
                     f"compile {res['compile']:.0f} s, AD columns {res['t_ad']:.1f} s, FD rollouts {res['t_fd']:.1f} s."
                     f"\n\n")
        header = ["t s"]
        for label in res["wrt"]:
            header += [f"d/d {label} (AD)", "AD vs FD", "FD vs FD"]
        rows = []
        for k, t in enumerate(res["times"]):
            row = [float(t)]
            for label in res["wrt"]:
                ad, fc, ff = res["ad"][label][k], res["fd_coarse"][label][k], res["fd_fine"][label][k]
                row += [float(ad), float(disagreement(ad, ff)), float(disagreement(fc, ff))]
            rows.append(row)
        parts.append(C.md_table(header, rows) + "\n")
        first = {}
        for label in res["wrt"]:
            bad = np.nonzero(disagreement(res["ad"][label], res["fd_fine"][label]) > 1e-4)[0]
            first[label] = f"{res['times'][bad[0]]:g} s" if len(bad) else "never"
        parts.append("First rollout length where AD and FD disagree by more than 1e-4: "
                     + ", ".join(f"d/d {k}: {v}" for k, v in first.items()) + ".\n\n")
    C.write_md(NAME, args.quick, "Gradients against rollout length", "".join(parts))


if __name__ == "__main__":
    main()
