"""How large the bulk modulus kappa must be before volume error stops mattering, and what dt a smaller kappa buys.

The foam is nearly incompressible; the model makes it compressible with bulk modulus kappa (Pa), and the
explicit time step is bounded by the dilatational wave speed c = sqrt((kappa + 4/3 mu) / rho). A smaller
kappa allows a larger dt but lets the volume change (J = det F != 1). For the hanging-plate and drop scenes
(experiments/scenes/<scene>_2d.json, the foam of experiments/pareto.py: mu = 200 Pa, sigma_y = 40 Pa,
eta = 10 Pa s^0.5, m = 0.5) each run changes kappa alone, at the fitter's default discretization (64 cells
across the domain width, 4 particles per cell, CFL 0.3, float64), and is compared with the stiffest kappa
(the near-incompressible reference) on:

- volume error: max over frames of the mean |J - 1| over the particles, and max over frames and particles
  of |J - 1|;
- silhouette change: 1 - IoU of the particle occupancy images against the stiffest run, averaged over the
  frames (the same raster as experiments/pareto.py);
- stress change: || s - s_ref || / || s_ref || of the deviatoric stress per cell (as in pareto.py);
- the time step dt and substep count of the run (CFL 0.3 with this mu), the dt the fitter would use
  (its time step is set by the stiffest admissible shear modulus, mu = 2000 Pa, see
  jaxfoam/calibrate/problem.py `build_problem`), and the rollout wall time (compile excluded).

Usage: python -m experiments kappa_study [--quick]. Writes experiments/results/kappa_study[_quick].png/.md.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C
from experiments import pareto
from jaxfoam._scene import DEFAULT_PPC

NAME = "kappa_study"
KAPPAS = (300.0, 1000.0, 3000.0, 10000.0, 30000.0)   # Pa; the scenes use 3000 Pa; the last is the reference
KAPPAS_QUICK = (1000.0, 3000.0, 10000.0)
CELLS, CELLS_QUICK = 64, 32          # cells across the domain width (the fitter's default / a coarse quick grid)
CFL = 0.3                            # the simulator's default CFL number
FIT_MU_MAX = 2000.0                  # Pa: the fitter's upper bound of mu, which sets its time step
DIM = 2


def simulate(name: str, kappa: float, cells: int, duration: float):
    """One 2D run with bulk modulus kappa (Pa). Returns the frames and scalars of the run (SI units)."""
    _, scene = pareto.load(name, DIM)
    width = scene.domain_max[0] - scene.domain_min[0]
    dx = width / cells
    params = jaxfoam.Params(kappa=kappa, rho=scene.density, **pareto.FOAM)
    times = np.linspace(duration / pareto.FRAMES, duration, pareto.FRAMES)
    sim = jaxfoam.Simulator(scene, times, params, dx, None, dtype=jnp.float64, cfl=CFL)
    fit_sim = jaxfoam.Simulator(scene, times, params.replace(mu=FIT_MU_MAX), dx, None, dtype=jnp.float64, cfl=CFL,
                                state0=sim.state0)

    def observe(s, p):
        dj = jnp.where(s.active, jnp.abs(jaxfoam.det(s.F) - 1.0), 0.0)
        return dict(x=s.x[:, :2], s=jaxfoam.deviatoric_stress_norm(s.bbar_e, p), active=s.active,
                    dJ_mean=jnp.sum(dj) / jnp.sum(s.active), dJ_max=jnp.max(dj))

    f = jax.jit(functools.partial(C.rollout, grid=sim.grid, n_frames=pareto.FRAMES, substeps=sim.substeps,
                                  observe=observe))
    args = (sim.state0, params, scene, jnp.asarray(sim.dt, jnp.float64))
    compiled = f.lower(*args).compile()
    with C.Timer() as tm:
        _, fr = compiled(*args)
        fr = jax.block_until_ready(fr)
    fr = jax.device_get(fr)
    return dict(x=np.asarray(fr["x"]), s=np.asarray(fr["s"]), active=np.asarray(fr["active"]),
                dJ_mean=float(np.max(fr["dJ_mean"])), dJ_max=float(np.max(fr["dJ_max"])),
                finite=bool(np.all(np.isfinite(fr["x"][fr["active"]]))), seconds=tm.seconds,
                dt=float(sim.dt), steps=int(sim.total_substeps), fit_dt=float(fit_sim.dt),
                particles=int(np.asarray(sim.state0.active).sum()),
                spacing=dx / DEFAULT_PPC[DIM] ** (1.0 / DIM), scene=scene, dx=dx)


def study(name: str, quick: bool):
    kappas = KAPPAS_QUICK if quick else KAPPAS
    cells = CELLS_QUICK if quick else CELLS
    duration = pareto.DURATION[name] * (0.5 if quick else 1.0)
    runs = {k: simulate(name, k, cells, duration) for k in kappas}
    ref = runs[kappas[-1]]
    scene = ref["scene"]
    lo, hi = np.asarray(scene.domain_min[:2]), np.asarray(scene.domain_max[:2])
    ref["images"] = pareto.images(ref, lo, hi)
    ref["stress"] = pareto.stress_cells(ref, lo, hi)
    rows = []
    for k in kappas:
        r = runs[k]
        sil, stress = pareto.errors(r, ref, lo, hi) if r["finite"] else (float("nan"), float("nan"))
        rows.append(dict(kappa=k, ratio=k / pareto.FOAM["mu"], dJ_mean=r["dJ_mean"], dJ_max=r["dJ_max"], sil=sil,
                         stress=stress, dt=r["dt"], steps=r["steps"], fit_dt=r["fit_dt"], seconds=r["seconds"],
                         particles=r["particles"]))
        print(f"{name} kappa {k:g} Pa: mean|J-1| {r['dJ_mean']:.4f}, max|J-1| {r['dJ_max']:.3f}, "
              f"silhouette change {sil:.4f}, stress change {stress:.4f}, dt {r['dt']:.3g} s, {r['seconds']:.1f} s",
              flush=True)
    return dict(cells=cells, dx=ref["dx"], duration=duration, rows=rows)


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    results = {name: study(name, args.quick) for name in ("hanging_plate", "drop")}

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, res in results.items():
        rows = res["rows"]
        k = [r["kappa"] for r in rows]
        axes[0].loglog(k, [r["dJ_mean"] for r in rows], "o-", label=f"{name}: max mean |J-1|")
        axes[0].loglog(k, [r["dJ_max"] for r in rows], "s--", label=f"{name}: max |J-1|")
        sub = [r for r in rows[:-1] if np.isfinite(r["sil"])]
        axes[1].loglog([r["kappa"] for r in sub], [max(r["sil"], 1e-4) for r in sub], "o-",
                       label=f"{name}: silhouette 1 - IoU")
        axes[1].loglog([r["kappa"] for r in sub], [max(r["stress"], 1e-4) for r in sub], "s--",
                       label=f"{name}: stress change")
        for r in rows:
            axes[1].annotate(f"dt {r['dt'] * 1e3:.2g} ms", (r["kappa"], max(r["sil"], 1e-4) if np.isfinite(r["sil"])
                                                            else 1e-4), fontsize=7, xytext=(3, 3),
                             textcoords="offset points")
    axes[0].set_xlabel("bulk modulus kappa (Pa)")
    axes[0].set_ylabel("volume error")
    axes[0].set_title("volume error against kappa (mu = 200 Pa)", fontsize=9)
    axes[1].set_xlabel("bulk modulus kappa (Pa)")
    axes[1].set_ylabel(f"change against kappa = {KAPPAS_QUICK[-1] if args.quick else KAPPAS[-1]:g} Pa")
    axes[1].set_title("answer change against the stiffest kappa (labels: dt of the run)", fontsize=9)
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    kap = KAPPAS_QUICK if args.quick else KAPPAS
    parts = [f"Foam {pareto.FOAM}, rho from the scene (80 kg/m^3); kappa in {list(kap)} Pa, the last the reference. "
             f"2D, default ppc ({DEFAULT_PPC[DIM]}), CFL {CFL}, float64, {pareto.FRAMES} frames. 'fit dt' is the time "
             f"step the fitter would use at this kappa (mu = {FIT_MU_MAX:g} Pa, its upper bound, same dx and CFL). "
             f"Wall time: rollout only, compile excluded, shared 2-core machine.\n\n"]
    for name, res in results.items():
        parts.append(f"## {name}\n\n{res['cells']} cells across the width (dx = {res['dx']:.4g} m), "
                     f"{res['duration']} s simulated.\n\n")
        parts.append(C.md_table(
            ["kappa Pa", "kappa/mu", "max mean abs(J-1)", "max abs(J-1)", "silhouette change (1-IoU)",
             "stress change", "dt s", "substeps", "fit dt s", "particles", "wall s"],
            [[r["kappa"], r["ratio"], r["dJ_mean"], r["dJ_max"], r["sil"], r["stress"], r["dt"], r["steps"],
              r["fit_dt"], r["particles"], r["seconds"]] for r in res["rows"]]) + "\n")
    C.write_md(NAME, args.quick, "Bulk modulus: volume error against time step", "".join(parts))


if __name__ == "__main__":
    main()
