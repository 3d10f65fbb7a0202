"""Virtual rheometer: steady simple shear of the Herschel-Bulkley model against its analytic flow curve.

Part 1, one material point. `jaxfoam.return_map` is driven with the plane-strain increment
f = I + dt [[0, gdot], [0, 0]] every step (strain increment dg = gdot dt) at shear rates 1e-2..1e3 1/s
until the stress is steady; the steady shear stress tau_xy = mu dev(bbar_e)_xy (Kirchhoff, Pa) is
compared with the flow curve of the model.

The flow curve (derived in `jaxfoam.hb_steady_shear_stress`). In the continuous limit the return map
integrates d bbar/dt = L bbar + bbar L^T - 2/3 tr(bbar) gamma n + lam bbar (eq. 4 plus the det = 1
renormalization of eq. 16), L = gdot e_x e_y^T, n = dev(bbar)/||dev(bbar)||. With small elastic strain
(tr bbar = 3, ||dev bbar|| = sqrt(2) bbar_xy) the xy component gives gdot = 2 gamma n_xy = sqrt(2) gamma,
the HB rule (eq. 5) gives ||s|| = sqrt(2/3) sigma_y + eta gamma^m, and tau_xy = ||s|| / sqrt(2):
    tau_xy = sigma_y / sqrt(3) + eta (gdot / sqrt 2)^m / sqrt(2)          (rigid-elastic limit)
i.e. a Herschel-Bulkley law with yield stress sigma_y/sqrt(3) and consistency eta 2^(-(m+1)/2). At
finite elastic strain the normal components bbar_xx != bbar_yy = bbar_zz enter: the exact steady state
(bbar_yy = bbar_zz = a, bbar_xx = a + delta, bbar_xy = q, t = tr/3, D = ||dev bbar||) solves
    delta (a t - 2/3 q^2) = 2 q^2 a,   a ((a + delta) a - q^2) = 1,   gdot = 2 t q gamma / (D (a - 2 q^2 / (3 t))),
with s = mu D; `jaxfoam.hb_steady_shear_stress` inverts it by bisection (this experiment found the
rigid-elastic formula, the library's original one, 21% high at s/mu = 0.7 and fixed it).
The return map is first order in dg, so the error at 3 strain increments gives the order.

Part 2, full MPM. A 2D box of foam between two sticky plates moving at -V/2 and +V/2 along x (gap H,
gdot = V/H nominal, gravity 0), as wide as BOX_ASPECT gaps, closed by the domain's slip walls. The shear
rate is measured as the slope of v_x(y) and the stress as the mean tau_xy of the particles in the
central window (one gap wide, the middle 60% of the gap), averaged over the last quarter of the run;
the error is tau_measured / flow_curve(gdot_measured) - 1. Density is scaled with the rate
(rho = RE_SCALE / (gdot^2 H^2), a Reynolds number rho gdot H^2 / (tau/gdot) <= 0.5) so that inertia stays
negligible and every rate needs the same number of steps; the steady shear stress does not depend on rho.
The full run repeats H/dx = 8 at CFL 0.1 (a third of the default step): the shear rate reached in the
window depends on the time step through the sticky plates (see experiments/README.md).

Usage: python -m experiments rheometer [--quick]. Writes experiments/results/rheometer[_quick].png/.md.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C

NAME = "rheometer"
# A shaving-cream-like foam (Yue et al. 2015 used mu ~ 1e2 Pa, sigma_y ~ 1e1 Pa, m < 1; SI units).
FOAM = jaxfoam.Params(mu=200.0, kappa=1000.0, sigma_y=20.0, eta=5.0, m=0.5, rho=80.0)
# A soft shear-thickening material whose elastic strain s/mu reaches ~1.8 at 1e3 1/s: the finite-strain
# terms dominate there (the rigid-elastic formula is then off by orders of magnitude).
THICKENING = jaxfoam.Params(mu=50.0, kappa=1000.0, sigma_y=20.0, eta=50.0, m=1.5, rho=80.0)
RATES = np.logspace(-2, 3, 11)                # shear rates of the material-point runs, 1/s
STRAIN_STEPS = (4e-3, 2e-3, 1e-3)              # strain increments gdot dt per step (the resolutions)
TOTAL_STRAIN = {"foam": 20.0, "thickening": 40.0}  # shear strain driven: >= 10 relaxation strains
STEADY_FRACTION = 0.9                          # steadiness: stress change over the last 10% of the strain

GAP = 0.02                 # plate gap H, m
BOX_ASPECT = 10            # box width / gap: the ends stay >= 3.5 gaps from the window over the run
BOX_STRAIN = 3.0           # shear strain of the MPM run (steady from ~1.5, end effects grow after ~4)
RE_SCALE = 6.0             # rho gdot^2 H^2, Pa: Reynolds number rho gdot H^2/(tau/gdot) = 6/tau <= 0.5
BOX_CFL = 0.3              # CFL number of the MPM runs (jaxfoam.CFL)
BOX_FRAMES = 30            # frames recorded (the last quarter is averaged)
BOX_PPC = 4


def point_steady_stress(params, rates, dg, total_strain):
    """Steady shear stress of one material point driven in simple shear.

    Args: params (Pa), rates (n,) 1/s, dg strain increment per step, total_strain dimensionless.
    Returns (tau_xy at the end (n,) Pa, relative change of tau_xy over the last 10% of the strain (n,)).
    """
    n = int(round(total_strain / dg))
    f = jnp.asarray([[1.0, dg], [0.0, 1.0]])

    def one(gdot):
        dt = dg / gdot

        def body(b, _):
            b2, _ = jaxfoam.return_map(b, f, params, dt)
            return b2, params.mu * jaxfoam.dev(b2)[0, 1]

        _, hist = jax.lax.scan(body, jnp.eye(3), None, length=n)
        return hist[-1], hist[int(STEADY_FRACTION * n)]

    tau, tau_before = jax.jit(jax.vmap(one))(jnp.asarray(rates))
    tau, tau_before = np.asarray(tau), np.asarray(tau_before)
    return tau, np.abs(tau - tau_before) / tau


def point_study(quick: bool):
    """Material-point flow curves of both materials at every strain increment (cheap: seconds)."""
    out = {}
    for label, params in (("foam", FOAM), ("thickening", THICKENING)):
        exact = jaxfoam.hb_steady_shear_stress(RATES, params)
        rigid = jaxfoam.hb_steady_shear_stress(RATES, params, rigid_limit=True)
        runs = []
        for dg in STRAIN_STEPS:
            with C.Timer() as tm:
                tau, drift = point_steady_stress(params, RATES, dg, TOTAL_STRAIN[label])
            runs.append(dict(dg=dg, tau=tau, err=tau / exact - 1.0, drift=drift, seconds=tm.seconds))
        out[label] = dict(params=params, exact=exact, rigid=rigid, runs=runs)
    return out


def box_scene(res: int):
    """The sheared box at resolution res = H/dx; plate motion is set per rate by `retime`.

    Returns (scene, dx m, y of the lower plate face m, domain width m).
    """
    dx = GAP / res
    tp = 3 * dx                      # plate thickness inside the domain
    lift = 1e-6 * dx                 # plate faces reach just past the nodes on them (round-off safe)
    width = BOX_ASPECT * GAP
    big = width + BOX_STRAIN * GAP + 1.0   # plates cover the domain over the whole run

    def plate(cy, sign):
        return {"center": [width / 2, cy], "half_size": [big, tp + lift], "sticky": True,
                "motion": {"type": "samples", "times": [0.0, 1.0],
                           "positions": [[width / 2, cy], [width / 2 + sign * 0.5 * BOX_STRAIN * GAP, cy]]}}

    spec = {"kind": "squeeze", "dim": 2, "gravity": [0.0, 0.0], "density": 1.0, "kappa": FOAM.kappa,
            "domain": {"min": [0.0, 0.0], "max": [width, 2 * tp + GAP]},
            "plates": [plate(0.0, -1.0), plate(2 * tp + GAP, 1.0)],
            "initial_shape": {"type": "box", "min": [0.0, tp], "max": [width, tp + GAP]},
            "notes": "virtual rheometer: simple shear between two sticky plates"}
    return jaxfoam.load_scene(spec), dx, tp, width


def retime(scene, gdot):
    """The plates reach their end positions (BOX_STRAIN gaps apart) at t = BOX_STRAIN / gdot s."""
    t_end = BOX_STRAIN / gdot
    return dataclasses.replace(scene, plates=tuple(
        dataclasses.replace(p, sample_times=jnp.asarray([0.0, t_end], p.sample_times.dtype)) for p in scene.plates))


def box_study(res: int, rates, cfl: float = BOX_CFL):
    """MPM sheared box at one resolution and CFL number, all rates in one vmapped rollout.

    Returns dict(gdot (n,) 1/s measured, tau (n,) Pa measured, err (n,), series of window tau (n, frames),
    particles, steps, seconds).
    """
    scene, dx, tp, width = box_scene(res)
    grid = jaxfoam.make_grid(scene, dx)
    st = jaxfoam.init_state(scene, dx, BOX_PPC, rho=1.0)
    rates = np.asarray(rates, float)
    rho = RE_SCALE / (rates ** 2 * GAP ** 2)
    c = np.sqrt((FOAM.kappa + 4.0 / 3.0 * FOAM.mu) / rho)   # P-wave speed, m/s (proportional to gdot)
    t_run = BOX_STRAIN / rates
    substeps = int(math.ceil(t_run[0] / BOX_FRAMES / (cfl * dx / c[0])))
    dts = t_run / BOX_FRAMES / substeps
    states = C.stack_trees([st.replace(mass=st.mass * r) for r in rho])
    params = C.stack_trees([FOAM.replace(rho=float(r)) for r in rho])
    scenes = C.stack_trees([retime(scene, g) for g in rates])
    xc, y0, y1 = width / 2, tp, tp + GAP

    def observe(s, p):
        win = ((jnp.abs(s.x[:, 0] - xc) < 0.5 * GAP) & (s.x[:, 1] > y0 + 0.2 * GAP)
               & (s.x[:, 1] < y1 - 0.2 * GAP) & s.active)
        w = win.astype(s.x.dtype)
        n = jnp.sum(w)
        y, vx = s.x[:, 1], s.v[:, 0]
        ym, vm = jnp.sum(w * y) / n, jnp.sum(w * vx) / n
        slope = jnp.sum(w * (y - ym) * (vx - vm)) / jnp.sum(w * (y - ym) ** 2)
        txy = p.mu * jaxfoam.dev(s.bbar_e)[:, 0, 1]
        return dict(gdot=slope, tau=jnp.sum(w * txy) / n)

    run = jax.jit(jax.vmap(functools.partial(C.rollout, grid=grid, n_frames=BOX_FRAMES, substeps=substeps,
                                             observe=observe)))
    with C.Timer() as tm:
        _, frames = run(states, params, scenes, jnp.asarray(dts))
        frames = jax.device_get(frames)
    last = BOX_FRAMES - BOX_FRAMES // 4
    gdot = frames["gdot"][:, last:].mean(axis=1)
    tau = frames["tau"][:, last:].mean(axis=1)
    exact = jaxfoam.hb_steady_shear_stress(gdot, FOAM)
    return dict(res=res, cfl=cfl, dx=dx, rates=rates, gdot=gdot, tau=tau, err=tau / exact - 1.0, series=frames["tau"],
                particles=int(st.active.sum()), steps=substeps * BOX_FRAMES, seconds=tm.seconds)


def chart(point, boxes, quick):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    ax = axes[0]
    fine = np.logspace(-2, 3, 200)
    for label, color in (("foam", "C0"), ("thickening", "C3")):
        p = point[label]["params"]
        ax.loglog(fine, jaxfoam.hb_steady_shear_stress(fine, p), "-", color=color,
                  label=f"{label}: exact flow curve (m={float(p.m)}, mu={float(p.mu):g} Pa)")
        ax.loglog(fine, jaxfoam.hb_steady_shear_stress(fine, p, rigid_limit=True), ":", color=color,
                  label=f"{label}: rigid-elastic HB formula")
        ax.loglog(RATES, point[label]["runs"][-1]["tau"], "o", color=color, mfc="none",
                  label=f"{label}: material point, dg={STRAIN_STEPS[-1]:g}")
    for k, b in enumerate(boxes):
        ax.loglog(b["gdot"], b["tau"], "s^vD"[k % 4], color="k", ms=5,
                  label=f"foam: MPM box, H/dx={b['res']}, CFL {b['cfl']}")
    ax.set_ylim(5, 500)
    ax.set_xlabel("shear rate (1/s)")
    ax.set_ylabel("steady shear stress tau_xy (Pa)")
    ax.set_title("Flow curve: model vs analytic")
    ax.legend(fontsize=7)
    ax = axes[1]
    for label, mk in (("foam", "o"), ("thickening", "x")):
        for r in point[label]["runs"]:
            ax.loglog(RATES, np.maximum(np.abs(r["err"]), 1e-12), mk + "-", lw=0.8,
                      label=f"point {label}, dg={r['dg']:g}")
    for k, b in enumerate(boxes):
        ax.loglog(b["gdot"], np.maximum(np.abs(b["err"]), 1e-12), "s^vD"[k % 4] + "--k", lw=1,
                  label=f"MPM box H/dx={b['res']}, CFL {b['cfl']}")
    ax.set_xlabel("shear rate (1/s)")
    ax.set_ylabel("|tau / exact - 1|")
    ax.set_title("Relative error against the exact (finite-strain) law")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return C.save_fig(fig, NAME, quick)


def table(point, boxes, quick):
    body = ["## 1. One material point (return map), steady simple shear\n\n",
            f"Rates: {len(RATES)} values from 1e-2 to 1e3 1/s. Error: max over rates of |tau/exact - 1|, "
            "exact = finite-strain flow curve. 'rigid formula' is the small-strain HB law "
            "sigma_y/sqrt(3) + eta (gdot/sqrt 2)^m / sqrt 2 against the same exact curve.\n\n"]
    rows = []
    for label, d in point.items():
        errs = [float(np.max(np.abs(r["err"]))) for r in d["runs"]]
        ords = C.orders([r["dg"] for r in d["runs"]], errs)
        rigid_err = float(np.max(np.abs(d["rigid"] / d["exact"] - 1)))
        for r, e, o in zip(d["runs"], errs, ords):
            rows.append([label, r["dg"], e, o, float(np.max(r["drift"])), rigid_err, r["seconds"]])
    body.append(C.md_table(["material", "strain step dg", "max rel. error", "order", "steadiness (last 10%)",
                            "rigid formula max rel. error", "wall s"], rows))
    body.append("\nFlow curve of the foam (mu = 200 Pa, sigma_y = 20 Pa, eta = 5 Pa s^0.5, m = 0.5):\n\n")
    f = point["foam"]
    body.append(C.md_table(["gdot 1/s", "exact tau_xy Pa", "rigid formula Pa", "point dg=1e-3 Pa", "rel. error"],
                           [[float(g), float(e), float(r), float(t), float(er)] for g, e, r, t, er in
                            zip(RATES, f["exact"], f["rigid"], f["runs"][-1]["tau"], f["runs"][-1]["err"])]))
    if boxes:
        body.append("\n## 2. Full MPM: sheared box between sticky plates (foam)\n\n")
        body.append("Error: tau_xy measured in the central window against the exact flow curve at the shear rate "
                    "measured there (slope of v_x(y)).\n\n")
        rows = []
        for b in boxes:
            for g, gm, t, e in zip(b["rates"], b["gdot"], b["tau"], b["err"]):
                rows.append([b["res"], b["cfl"], float(g), float(gm), float(gm / g), float(t), float(e)])
        body.append(C.md_table(["H/dx", "CFL", "nominal gdot 1/s", "measured gdot 1/s", "measured / nominal",
                                "tau_xy Pa", "rel. error"], rows))
        default = [b for b in boxes if b["cfl"] == BOX_CFL]
        errs = [float(np.max(np.abs(b["err"]))) for b in default]
        ords = C.orders([b["dx"] for b in default], errs) + [float("nan")] * (len(boxes) - len(default))
        errs += [float(np.max(np.abs(b["err"]))) for b in boxes if b["cfl"] != BOX_CFL]
        body.append("\n" + C.md_table(
            ["H/dx", "CFL", "dx m", "particles", "steps", "max rel. error", "order (default CFL)", "wall s (all rates)"],
            [[b["res"], b["cfl"], b["dx"], b["particles"], b["steps"], e, o, b["seconds"]]
             for b, e, o in zip(default + [b for b in boxes if b["cfl"] != BOX_CFL], errs, ords)]))
    return C.write_md(NAME, quick, "Virtual rheometer", "".join(body))


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    point = point_study(args.quick)
    for label, d in point.items():
        print(label, "max rel. error per dg:", [float(np.max(np.abs(r["err"]))) for r in d["runs"]])
    box_res = (4, 8) if args.quick else (4, 8, 16)
    box_rates = (1e-2, 1.0, 1e2) if args.quick else (1e-2, 1e-1, 1.0, 1e1, 1e2, 1e3)
    # The last entry checks the time step: the same box at a third of the default CFL.
    box_plan = [(r, BOX_CFL) for r in box_res] + ([] if args.quick else [(8, 0.1)])
    boxes = []
    for res, cfl in box_plan:
        b = box_study(res, box_rates, cfl)
        print(f"box H/dx={res} CFL={cfl}: rel. errors {np.round(b['err'], 5).tolist()} ({b['seconds']:.0f} s)", flush=True)
        boxes.append(b)
    chart(point, boxes, args.quick)
    table(point, boxes, args.quick)


if __name__ == "__main__":
    main()
