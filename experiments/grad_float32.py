"""Gradients in float32: how far they are from float64, and how they compare with float32 differences.

The scenes and foam are those of experiments/grad_horizon.py: the hanging plate and the drop, 2D,
CELLS cells across the width, 4 particles per cell, CFL 0.3, mu = 200 Pa, sigma_y = 40 Pa, eta = 10 Pa
s^0.5 and m = 0.5. Both precisions start from the same particles (the float64 sample cast to float32).
They take the same time step and substeps. The observable is the mean height of the foam (m) at each of
FRAMES frames.

Its derivative with respect to ln mu, ln sigma_y, ln eta and m is computed four ways:
- forward-mode AD (one jvp rollout per parameter) in float32 and in float64;
- central differences in float32 with steps H32 (each in those coordinates);
- reverse-mode AD (jax.grad through the checkpointed rollout) of the last frame's height, in both
  precisions.

Reported per frame and parameter, against float64 AD. That is the reference: experiments/grad_horizon.py
finds it within 7.9e-8 of float64 central differences on the hanging plate (2.0e-6 for d/dm); on the drop
after floor contact the differences themselves disagree between step sizes, so they cannot check it there.
  error = |value - AD64| / max(|AD64|, FLOOR).
Also reported: the float32 drift of the height itself, |h32 - h64| (m), and the wall time of the jvp
columns in each precision.

Usage: python -m experiments grad_float32 [--quick]. Writes experiments/results/grad_float32[_quick].png/.md.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C
from experiments import grad_horizon as GH
from experiments import pareto

NAME = "grad_float32"
CELLS = GH.CELLS
CFL = GH.CFL
FRAMES, FRAMES_QUICK = 20, 10
DURATION = GH.DURATION           # s (half in --quick)
WRT = GH.WRT
H32 = (1e-2, 1e-3)               # float32 central-difference steps in the fitted coordinates
FLOOR = GH.FLOOR                 # m per unit coordinate: derivatives below this count as zero
DIM = 2


def _cast_state(state, dtype):
    return jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, state)


def study(name: str, quick: bool):
    spec, scene64 = pareto.load(name, DIM)
    scene32 = jaxfoam.load_scene(spec, dtype=jnp.float32)
    width = scene64.domain_max[0] - scene64.domain_min[0]
    dx = width / CELLS
    frames = FRAMES_QUICK if quick else FRAMES
    duration = DURATION[name] * (0.5 if quick else 1.0)
    times = np.linspace(duration / frames, duration, frames)
    p0 = jaxfoam.Params(kappa=scene64.kappa, rho=scene64.density, **pareto.FOAM)
    sims = {"float64": jaxfoam.Simulator(scene64, times, p0, dx, None, dtype=jnp.float64, cfl=CFL),
            "float32": jaxfoam.Simulator(scene32, times, p0, dx, None, dtype=jnp.float32, cfl=CFL)}
    if sims["float32"].substeps != sims["float64"].substeps or sims["float32"].dt != sims["float64"].dt:
        raise RuntimeError("the two precisions chose different time steps")
    state0 = {"float64": sims["float64"].state0, "float32": _cast_state(sims["float64"].state0, jnp.float32)}
    z64 = np.array([np.log(p0.mu), np.log(p0.sigma_y), np.log(p0.eta), p0.m])

    def heights_fn(prec):
        sim, s0, scene = sims[prec], state0[prec], (scene64 if prec == "float64" else scene32)

        def heights(z):
            _, fr, _ = sim.rollout(GH.params_of(z, scene), state0=s0)
            w = fr["active"].astype(fr["x"].dtype)
            return jnp.sum(fr["x"][:, :, 1] * w, axis=1) / jnp.sum(w, axis=1)
        return heights

    out = dict(times=times, wrt=WRT, dx=dx, steps=sims["float64"].total_substeps,
               particles=int(np.asarray(sims["float64"].state0.active).sum()), ad={}, fd={}, rev={}, h={},
               t_jvp={})
    for prec, dt in (("float64", jnp.float64), ("float32", jnp.float32)):
        heights = heights_fn(prec)
        z0 = jnp.asarray(z64, dt)
        fwd = jax.jit(heights)
        jvp = jax.jit(lambda z, e: jax.jvp(heights, (z,), (e,))[1])
        rev = jax.jit(jax.grad(lambda z: heights(z)[-1]))
        out["h"][prec] = np.asarray(fwd(z0), np.float64)
        jvp(z0, z0).block_until_ready()
        out["ad"][prec] = {}
        with C.Timer() as tm:
            for i, label in enumerate(WRT):
                e = jnp.zeros(4, dt).at[i].set(1.0)
                out["ad"][prec][label] = np.asarray(jax.block_until_ready(jvp(z0, e)), np.float64)
        out["t_jvp"][prec] = tm.seconds
        out["rev"][prec] = np.asarray(rev(z0), np.float64)
        if prec == "float32":
            for h in H32:
                out["fd"][h] = {}
                for i, label in enumerate(WRT):
                    e = jnp.zeros(4, dt).at[i].set(h)
                    out["fd"][h][label] = (np.asarray(fwd(z0 + e), np.float64) - np.asarray(fwd(z0 - e), np.float64)) / (2.0 * h)
        print(f"{name} {prec}: jvp columns {out['t_jvp'][prec]:.1f} s", flush=True)
    return out


def error(value, ref):
    return np.abs(value - ref) / np.maximum(np.abs(ref), FLOOR)


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    results = {name: study(name, args.quick) for name in ("hanging_plate", "drop")}

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, (name, res) in zip(axes, results.items()):
        for i, label in enumerate(res["wrt"]):
            ref = res["ad"]["float64"][label]
            ax.semilogy(res["times"], np.maximum(error(res["ad"]["float32"][label], ref), 1e-16), "o-",
                        color=f"C{i}", label=f"AD float32, d/d {label}")
            ax.semilogy(res["times"], np.maximum(error(res["fd"][H32[0]][label], ref), 1e-16), "x:",
                        color=f"C{i}", label=f"FD float32 (step {H32[0]:g}), d/d {label}")
        ax.set_xlabel("rollout length (s)")
        ax.set_ylabel("relative error against float64 AD")
        ax.set_title(f"{name}: gradient of the mean height in float32", fontsize=9)
        ax.legend(fontsize=6)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    parts = [f"Foam {pareto.FOAM}, kappa and rho from the scene; 2D, {CELLS} cells across the width, ppc 4, "
             f"CFL {CFL}; both precisions from the same particles, same time step. Observable: mean height of "
             f"the foam (m) per frame. Error = |value - AD64| / max(|AD64|, {FLOOR:g} m), AD64 = forward-mode AD "
             f"in float64. AD32 = forward-mode AD in float32; FD32(h) = float32 central differences with step h "
             f"in (ln mu, ln sigma_y, ln eta, m). Wall times on the shared 2-core machine.\n\n"]
    for name, res in results.items():
        parts.append(f"## {name}\n\ndx = {res['dx']:.4g} m, {res['particles']} particles, {res['steps']} "
                     f"substeps. Four jvp columns: {res['t_jvp']['float64']:.1f} s in float64, "
                     f"{res['t_jvp']['float32']:.1f} s in float32.\n\n")
        header = ["t s", "h64 m", "abs(h32 - h64) m"]
        for label in res["wrt"]:
            header += [f"d/d {label} (AD64)", "AD32 err", f"FD32({H32[0]:g}) err", f"FD32({H32[1]:g}) err"]
        rows = []
        for k, t in enumerate(res["times"]):
            row = [float(t), float(res["h"]["float64"][k]), float(abs(res["h"]["float32"][k] - res["h"]["float64"][k]))]
            for label in res["wrt"]:
                ref = res["ad"]["float64"][label][k]
                row += [float(ref), float(error(res["ad"]["float32"][label][k], ref)),
                        float(error(res["fd"][H32[0]][label][k], ref)), float(error(res["fd"][H32[1]][label][k], ref))]
            rows.append(row)
        parts.append(C.md_table(header, rows) + "\n")
        worst = {label: float(np.max(error(res["ad"]["float32"][label], res["ad"]["float64"][label])))
                 for label in res["wrt"]}
        worst_fd = {label: float(min(np.max(error(res["fd"][h][label], res["ad"]["float64"][label])) for h in H32))
                    for label in res["wrt"]}
        parts.append("Largest AD32 error over the frames: " + ", ".join(f"d/d {k}: {v:.2g}" for k, v in worst.items())
                     + ". Largest FD32 error over the frames, better of the two steps: "
                     + ", ".join(f"d/d {k}: {v:.2g}" for k, v in worst_fd.items()) + ".\n\n")
        rref = res["rev"]["float64"]
        fref = np.array([res["ad"]["float64"][label][-1] for label in res["wrt"]])
        rows = [[label, float(rref[i]), float(error(rref[i], fref[i])), float(error(res["rev"]["float32"][i], rref[i]))]
                for i, label in enumerate(res["wrt"])]
        parts.append("Reverse mode, last frame:\n\n" + C.md_table(
            ["d h_T / d", "reverse float64", "error of reverse64 against AD64 (forward)", "reverse float32 error"],
            rows) + "\n")
    C.write_md(NAME, args.quick, "Gradients in float32", "".join(parts))


if __name__ == "__main__":
    main()
