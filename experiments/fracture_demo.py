"""Fracture demo: a foam strip pulled apart between two plates, at three resolutions, plain MPM against
the fracture stage with a critical neck thickness (`FractureConfig(neck_thickness=H_C)`).

A strip of foam (1 cm wide, 2.1 cm long, 2D plane strain, gravity off) is held by a still bottom
plate and a top plate that rises at 0.1 m/s. Two materials: a yield-stress foam (sigma_y 30 Pa,
m 0.5) and a viscous, nearly Bingham one (sigma_y 5 Pa, eta 20 Pa s, m 1). Each runs at dx 2.5,
1.25 and 0.625 mm, plain and with fracture, with particle resampling (`jaxfoam.resample`, every
RESAMPLE_EVERY substeps: the paper's setting, which keeps stretched material sampled) and without.
Measured for each run (frames every 1 mm of plate travel):
- load pinch-off: the plate travel at which the pull on the top plate (`collider_force`) first falls
  below FORCE_DROP of its peak: the thread stops carrying load;
- geometric pinch-off: travel after which the material on the two plates stays disconnected
  (raster of dx/2 pixels, a pixel filled within 0.75 dx of a point);
- load-path pinch-off: the same connectivity through the points that still carry elastic strain
  (the points the fracture stage releases excluded; plain runs: the geometric one);
- the neck thickness (`neck_thickness` with h_c = H_C, the thinnest point between the plates) over
  the run, to compare the necking itself across resolutions.
A bulk-flow check runs a 2D slump (experiments/slump.py, tau' = 0.15) plain and with fracture
(h_c = 3 dx) and counts the points the criterion marks. Writes experiments/results/fracture_demo[_quick].png/.md.
Run: `python -m experiments fracture_demo [--quick]` (quick: the viscous strip without resampling at
the two coarsest resolutions, plain and with fracture).
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import jaxfoam  # noqa: E402
from experiments import _common as C  # noqa: E402
from jaxfoam.fracture import FractureConfig, collider_force, neck_thickness  # noqa: E402
from jaxfoam.resample import ResampleConfig  # noqa: E402

NAME = "fracture_demo"
FOAM = jaxfoam.Params(mu=300.0, kappa=3000.0, sigma_y=30.0, eta=3.0, m=0.5, rho=100.0)
VISCOUS = jaxfoam.Params(mu=300.0, kappa=3000.0, sigma_y=5.0, eta=20.0, m=1.0, rho=100.0)
WIDTH = 0.01          # strip width, m
SPEED = 0.1           # top plate speed, m/s
DURATION = 0.5        # s
FRAMES = 50           # one frame per mm of plate travel
DXS = (0.0025, 0.00125, 0.000625)   # strip 4, 8, 16 cells wide
# Critical neck thickness, m: 40% of the strip's width; 6.4 and 3.2 cells on the two finer grids (the
# thinnest neck they represent with several points across), 1.6 cells on the coarsest, which is
# therefore not expected to agree. A real foam's h_c (a few bubbles, ~0.1-0.3 mm) is below all three.
H_C = 0.004
# Resampling pass every this many substeps: the plate moves 0.6 mm (dx 2.5 mm) to 0.16 mm (dx 0.625 mm)
# in between, well under a cell.
RESAMPLE_EVERY = 50
COVER = 0.75          # connectivity: pixels filled within this many dx of a point
FORCE_DROP = 0.1      # load pinch-off: the pull falls below this share of its peak
Y_TOP = 0.035         # initial centre of the top plate, m
SLUMP_TAUS = (0.15, 0.05)   # bulk-flow check: dimensionless yield stresses of the slump (a column; a heap)
SLUMP_RES = 16        # bulk-flow check: column height / dx
SLUMP_HC = 3          # bulk-flow check: h_c in cells (the smallest h_c the docstring of FractureConfig advises)


@dataclasses.dataclass(frozen=True)
class Case:
    """One pulled-strip setting: material, plate speed (m/s), duration (s), strip width (m), points per
    cell and sampling seed."""

    params: jaxfoam.Params
    speed: float = SPEED
    duration: float = DURATION
    width: float = WIDTH
    ppc: int = 4
    seed: int = 0


CASES = {"yield-stress foam": Case(FOAM), "viscous (Bingham-like)": Case(VISCOUS)}


def scene(case: Case):
    s, dur = case.speed, case.duration
    return jaxfoam.load_scene(dict(
        kind="squeeze", dim=2, gravity=[0.0, 0.0], density=float(case.params.rho),
        kappa=float(case.params.kappa),
        domain=dict(min=[-0.03, 0.0], max=[0.03, Y_TOP + 0.01 + s * dur + 0.02]),
        plates=[dict(center=[0.0, 0.01], half_size=[0.02, 0.005]),
                dict(center=[0.0, Y_TOP], half_size=[0.02, 0.005],
                     # the motion runs past the end of the run: no stop (a velocity jump) inside it
                     motion=dict(type="samples", times=[0.0, 2 * dur],
                                 positions=[[0.0, Y_TOP], [0.0, Y_TOP + 2 * s * dur]]))],
        initial_shape=dict(type="box", min=[-case.width / 2, 0.012], max=[case.width / 2, 0.033]),
        name="pulled thread"))


def top_region(case: Case, t):
    """Grid nodes of the top plate at time t (its box, with a small tolerance)."""
    def region(nx):
        yc = Y_TOP + case.speed * t
        return (jnp.abs(nx[:, 1] - yc) <= 0.005 + 1e-9) & (jnp.abs(nx[:, 0]) <= 0.02 + 1e-9)
    return region


def run(case: Case, dx, fracture: bool, resample: bool):
    sc = scene(case)
    params = case.params
    times = np.linspace(case.duration / FRAMES, case.duration, FRAMES)
    cfg = FractureConfig(neck_thickness=H_C)
    sim = jaxfoam.Simulator(sc, times, params, dx, ppc=case.ppc, fracture=cfg if fracture else None,
                            resample=ResampleConfig(every=RESAMPLE_EVERY) if resample else None, seed=case.seed)

    def observe(state, prm):
        f = collider_force(state, prm, sc, sim.grid, sim.dt, region=top_region(case, state.t))
        _, gm = jaxfoam.p2g(state, prm, sim.grid, sim.dt)
        weak = cfg.weak(state, gm, sim.grid)
        h = neck_thickness(state, sim.grid, H_C)
        between = state.active & (state.x[:, 1] > 0.017) & (state.x[:, 1] < Y_TOP + case.speed * state.t - 0.007)
        return dict(x=state.x, active=state.active, force=f[1], weak=weak,
                    hmin=jnp.min(jnp.where(between, h, jnp.inf)))

    with C.Timer() as tm:
        final, frames, health = sim.rollout(params, observe=observe)
        frames = jax.device_get(frames)
    sim.check(frames, health)
    return dict(frames=frames, times=times, seconds=tm.seconds, sim=sim, points=int(sim.state0.active.sum()),
                final_points=int(np.sum(frames["active"][-1])))


def connected(x, mask, dx, y_plate):
    """Whether the material (points where `mask`) touching the top plate (centre at y_plate, m) is
    connected to the material on the bottom plate."""
    lo, hi = np.array([-0.03, 0.0]), np.array([0.03, y_plate + 0.01])
    pixel = dx / 2
    img = C.rasterize(x, mask, lo, hi, pixel, COVER * dx)
    ys = lo[1] + (np.arange(img.shape[0]) + 0.5) * pixel
    top_row = int(np.searchsorted(ys, y_plate - 0.005))
    bottom_row = int(np.searchsorted(ys, 0.015))
    reach = np.zeros_like(img)
    reach[top_row:] = img[top_row:]
    while True:
        grown = reach.copy()
        grown[1:] |= reach[:-1]
        grown[:-1] |= reach[1:]
        grown[:, 1:] |= reach[:, :-1]
        grown[:, :-1] |= reach[:, 1:]
        grown &= img
        if grown[:bottom_row + 1].any():
            return True
        if (grown == reach).all():
            return False
        reach = grown


def pinch_off(out, dx, case: Case, fracture: bool):
    """Pinch-off measures of a run, m of plate travel (nan: not within the run): e_load (the pull first
    below FORCE_DROP of its peak, after the peak), e_geom (geometric disconnection for good), e_path
    (disconnection through the points not released by the fracture stage), and the neck thickness
    series (m)."""
    fr, times = out["frames"], out["times"]
    ext = lambda k: case.speed * times[k] if k is not None else float("nan")
    f = fr["force"]
    k_peak = int(np.argmax(f))
    k_load = next((k for k in range(k_peak, len(f)) if f[k] < FORCE_DROP * f[k_peak]), None)

    def for_good(flags):
        return next((k for k in range(len(flags)) if not any(flags[k:])), None)

    y = lambda t: Y_TOP + case.speed * t
    geom = [connected(fr["x"][k], fr["active"][k], dx, y(t)) for k, t in enumerate(times)]
    path = ([connected(fr["x"][k], fr["active"][k] & ~fr["weak"][k], dx, y(t)) for k, t in enumerate(times)]
            if fracture else geom)
    return dict(e_load=ext(k_load), e_geom=ext(for_good(geom)), e_path=ext(for_good(path)), hmin=fr["hmin"],
                peak=float(f[k_peak]), weak=fr["weak"].sum(axis=1))


def slump_check(fracture: bool, tau_p: float):
    """The 2D slump of experiments/slump.py (tau' = tau_p, frictionless floor, H/dx = SLUMP_RES),
    plain or with fracture (h_c = SLUMP_HC dx): final height / H, spread (m), most points the criterion
    marks in a frame, wall s."""
    import math
    from experiments import slump as S
    sc = S.slump_scene(2, "slip")
    dx = S.HEIGHT / SLUMP_RES
    st = S.initial_state(sc, dx)
    eta, run_time = S.FLOOR_SETTINGS["slip"]
    params = S.BASE.replace(sigma_y=math.sqrt(3.0) * tau_p * S.RHO * S.G * S.HEIGHT, eta=eta)
    cfg = FractureConfig(neck_thickness=SLUMP_HC * dx)
    times = np.linspace(run_time / S.FRAMES, run_time, S.FRAMES)
    sim = jaxfoam.Simulator(sc, times, params, dx, state0=st, fracture=cfg if fracture else None)

    def observe(s, p):
        _, gm = jaxfoam.p2g(s, p, sim.grid, sim.dt)
        near = (jnp.abs(s.x[:, 0]) < 0.25 * S.RADIUS) & s.active
        return dict(top=jnp.max(jnp.where(near, s.x[:, 1], -jnp.inf)),
                    spread=jnp.max(jnp.where(s.active, jnp.abs(s.x[:, 0]), 0.0)),
                    weak=jnp.sum(cfg.weak(s, gm, sim.grid)))

    with C.Timer() as tm:
        _, fr, health = sim.rollout(params, observe=observe)
        fr = jax.device_get(fr)
    sim.check(fr, health)
    x0 = np.asarray(st.x)
    top0 = float(np.max(x0[np.abs(x0[:, 0]) < 0.25 * S.RADIUS, 1]))
    return dict(h=1.0 - (top0 - fr["top"][-1]) / S.HEIGHT, spread=float(fr["spread"][-1]),
                weak=int(np.max(fr["weak"])), seconds=tm.seconds, dx=dx, h_c=SLUMP_HC * dx)


def S_points():
    from experiments import slump as S
    sc = S.slump_scene(2, "slip")
    return len(S.initial_state(sc, S.HEIGHT / SLUMP_RES).x)


def slots_full(out):
    """Plate travel (m) at the first frame where every particle slot is in use (nan: never)."""
    act = out["frames"]["active"]
    full = act.sum(axis=1) >= act.shape[1]
    k = int(np.argmax(full)) if full.any() else None
    return float("nan") if k is None else SPEED * out["times"][k]


def mm(v):
    return 1000 * v if np.isfinite(v) else float("nan")


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    if args.quick:
        plan = [("viscous (Bingham-like)", False)]
        dxs = DXS[:2]
    else:
        plan = [(m, rs) for m in CASES for rs in (True, False)]
        dxs = DXS
    slump = {} if args.quick else {(t, f): slump_check(f, t) for t in SLUMP_TAUS for f in (False, True)}
    for (t, f), r in slump.items():
        print(f"slump tau' {t}, fracture {f}: height {r['h']:.3f} H, spread {1000 * r['spread']:.1f} mm, weak {r['weak']}, "
              f"{r['seconds']:.0f} s", flush=True)
    results = {}
    for mat, rs in plan:
        for dx in dxs:
            for fracture in (False, True):
                out = run(CASES[mat], dx, fracture, rs)
                res = dict(out=out, **pinch_off(out, dx, CASES[mat], fracture))
                results[(mat, rs, dx, fracture)] = res
                print(f"{mat}, resampling {rs}, dx {dx * 1000:g} mm, fracture {fracture}: load pinch-off "
                      f"{mm(res['e_load']):.0f} mm, geometric {mm(res['e_geom']):.0f} mm, load path "
                      f"{mm(res['e_path']):.0f} mm, {out['seconds']:.0f} s", flush=True)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(plan), 4, figsize=(17, 4.2 * len(plan)), squeeze=False)
    for r, (mat, rs) in enumerate(plan):
        case = CASES[mat]
        label = f"{mat}, {'with' if rs else 'no'} resampling"
        ax = axes[r, 0]
        for fracture, mk in ((False, "o-"), (True, "s--")):
            ax.plot([1000 * dx for dx in dxs], [mm(results[(mat, rs, dx, fracture)]["e_load"]) for dx in dxs], mk,
                    label=f"with fracture (h_c {1000 * H_C:g} mm)" if fracture else "plain MPM")
        ax.set_xticks([1000 * dx for dx in dxs])
        ax.set_xlabel("dx (mm)")
        ax.set_ylabel(f"load pinch-off (mm of travel)\n(missing: pull never below {FORCE_DROP:.0%} of peak)")
        ax.set_title(label, fontsize=10)
        ax.legend(fontsize=8)
        ax = axes[r, 1]
        for dx in dxs:
            for fracture, ls in ((False, "-"), (True, "--")):
                o = results[(mat, rs, dx, fracture)]["out"]
                ax.plot(1000 * case.speed * o["times"], o["frames"]["force"], ls, lw=1,
                        label=f"dx {1000 * dx:g} mm{' fracture' if fracture else ''}")
        ax.set_xlabel("top plate travel (mm)")
        ax.set_ylabel("pull on the foam (N/m)")
        ax.legend(fontsize=7)
        ax = axes[r, 2]
        for dx in dxs:
            res = results[(mat, rs, dx, False)]
            h = np.where(np.isfinite(res["hmin"]), res["hmin"], np.nan)
            ax.plot(1000 * case.speed * res["out"]["times"], 1000 * h, lw=1, label=f"plain, dx {1000 * dx:g} mm")
        ax.axhline(1000 * H_C, color="k", lw=0.8, ls=":", label="h_c")
        ax.set_xlabel("top plate travel (mm)")
        ax.set_ylabel("neck thickness estimate (mm)")
        ax.legend(fontsize=7)
        ax = axes[r, 3]
        dx = dxs[-1]
        for fracture in (False, True):
            res = results[(mat, rs, dx, fracture)]
            o = res["out"]
            e = res["e_load"] if np.isfinite(res["e_load"]) else case.speed * o["times"][-1]
            k = min(int(np.argmin(np.abs(case.speed * o["times"] - e))) + 5, len(o["times"]) - 1)
            act = o["frames"]["active"][k]
            x = o["frames"]["x"][k][act]
            weak = o["frames"]["weak"][k][act] if fracture else np.zeros(len(x), bool)
            off = 0.025 if fracture else -0.005
            ax.scatter(x[~weak, 0] + off, x[~weak, 1], s=0.5 if dx < 0.002 else 2, lw=0,
                       c="#d1495b" if fracture else "#4a7ab5")
            ax.scatter(x[weak, 0] + off, x[weak, 1], s=0.5 if dx < 0.002 else 2, lw=0, c="#999999")
            ax.text(off, 0.005, f"{1000 * case.speed * o['times'][k]:.0f} mm", ha="center", fontsize=7)
        ax.set_aspect("equal")
        ax.set_title(f"dx {1000 * dx:g} mm, 5 mm after the load pinch-off\n(left plain, right fracture; "
                     f"grey: released points)", fontsize=9)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    rows = []
    for mat, rs in plan:
        for dx in dxs:
            for fracture in (False, True):
                res = results[(mat, rs, dx, fracture)]
                o = res["out"]
                rows.append([mat, "yes" if rs else "no", 1000 * dx, "yes" if fracture else "no", mm(res["e_load"]),
                             mm(res["e_geom"]), mm(res["e_path"]), res["peak"], o["points"], o["final_points"],
                             mm(slots_full(o)) if rs else float("nan"), o["sim"].total_substeps, o["seconds"]])
    table = C.md_table(["case", "resampling", "dx (mm)", "fracture", "load pinch-off (mm)",
                        "geometric pinch-off (mm)", "load-path pinch-off (mm)", "peak pull (N/m)",
                        "points at start", "points at end", "slots all used at (mm)", "substeps", "wall s"], rows)
    crow = []
    for mat, rs in plan:
        for fracture in (False, True):
            e = [mm(results[(mat, rs, dx, fracture)]["e_load"]) for dx in dxs]
            steps = [e[i + 1] - e[i] for i in range(len(e) - 1)]
            crow.append([mat, "yes" if rs else "no", "yes" if fracture else "no", ", ".join(f"{v:.0f}" for v in e),
                         ", ".join(f"{v:+.0f}" for v in steps)])
    ctable = C.md_table(["case", "resampling", "fracture", "load pinch-off at dx " +
                         ", ".join(f"{1000 * dx:g}" for dx in dxs) + " mm", "change as dx halves (mm)"], crow)
    # neck thickness at a fixed travel, plain runs, to show that the necking itself converges
    hrow = []
    for mat, rs in plan:
        for travel in (0.01, 0.02):
            vals = []
            for dx in dxs:
                res = results[(mat, rs, dx, False)]
                k = int(np.argmin(np.abs(CASES[mat].speed * res["out"]["times"] - travel)))
                vals.append(mm(float(res["hmin"][k])))
            hrow.append([mat, "yes" if rs else "no", 1000 * travel, ", ".join(f"{v:.2f}" for v in vals)])
    htable = C.md_table(["case", "resampling", "travel (mm)", "plain: neck thickness estimate at dx " +
                         ", ".join(f"{1000 * dx:g}" for dx in dxs) + " mm (mm)"], hrow)
    describe = lambda p: f"mu {p.mu} Pa, kappa {p.kappa} Pa, sigma_y {p.sigma_y} Pa, eta {p.eta} Pa s^m, m {p.m}"
    body = (f"Strip between a still bottom plate and a rising top plate (2D plane strain, rho 100 kg/m^3), "
            f"{1000 * WIDTH:.0f} mm wide, {SPEED} m/s for {DURATION} s, gravity off, 4 points per cell. "
            f"Yield-stress foam: {describe(FOAM)}; viscous (Bingham-like): {describe(VISCOUS)}. Fracture: "
            f"`FractureConfig(neck_thickness={H_C})` (h_c = {1000 * H_C:g} mm, 40% of the strip width; the "
            f"default density-ratio criterion stays on). Resampling: `ResampleConfig(every={RESAMPLE_EVERY})`.\n\n"
            f"![fracture]({NAME}{'_quick' if args.quick else ''}.png)\n\n{table}\n"
            f"### Load pinch-off against resolution\n\n{ctable}\n"
            f"### Necking before the break (plain runs)\n\n{htable}\n")
    if slump:
        srow = [[t, "plain" if not f else f"fracture, h_c {1000 * s['h_c']:.2f} mm ({SLUMP_HC} dx)", 1000 * s["dx"],
                 s["h"], 1000 * s["spread"], s["weak"], s["seconds"]] for (t, f), s in slump.items()]
        npts = int(S_points())
        body += (f"### Bulk flow: a slump\n\n2D slump of experiments/slump.py (column 10 cm x 10 cm, {npts} points, "
                 f"frictionless floor, H/dx = {SLUMP_RES}); the plain runs count the points the criterion would "
                 f"mark.\n\n"
                 + C.md_table(["tau'", "run", "dx (mm)", "final height / H", "half spread (mm)",
                               "most points marked weak in a frame", "wall s"], srow) + "\n")
    notes = [
        f"- Load pinch-off: plate travel at the first frame (one per mm) after the pull's peak where the pull "
        f"is below {FORCE_DROP:.0%} of the peak (nan: not within {1000 * SPEED * DURATION:.0f} mm). Geometric "
        f"pinch-off: travel after which the material on the two plates stays disconnected (raster of dx/2 "
        f"pixels filled within {COVER} dx of a point). Load-path pinch-off: the same through the points the "
        f"fracture stage does not release (equal to the geometric one for plain runs).",
        f"- Neck thickness estimate: `jaxfoam.fracture.neck_thickness` with h_c = {1000 * H_C:g} mm at the "
        f"thinnest point more than 5 mm from the bottom plate and 2 mm from the top one; it reads a slab's "
        f"width below h_c and saturates at about 1.4-2.4 h_c for wide material.",
        "- The fracture stage releases the points of a neck thinner than h_c (grey in the figure): the pull drops "
        "(load pinch-off) while those points still lie between the pieces. Without resampling they drift apart and "
        "the geometric pinch-off follows within a few mm. With resampling, the resampler leaves the cells of such "
        "a neck unfilled (`FractureConfig.holds`), so the released thread thins and parts, but later than the load "
        "drops and not at a travel that converges with dx: it carries no stress, nothing (this model has no "
        "surface tension) draws it back into the pieces, and the flow stretches it until its points lie more than "
        f"{2 * COVER:g} dx apart.",
        "- Wall times on a shared 2-core CPU, compile included. Slots: a resampled run has twice the initial "
        "points' slots (`capacity_factor` 2); 'slots all used at': the travel from which the resampler can insert "
        "no more points (nan: never).",
    ]
    lp = lambda mat, rs, f: ", ".join(f"{mm(results[(mat, rs, dx, f)]['e_load']):.0f}" for dx in dxs)
    dl = ", ".join(f"{1000 * dx:g}" for dx in dxs)
    for mat in dict.fromkeys(m for m, _ in plan):
        for rs in (True, False):
            if (mat, rs) in plan:
                notes.append(f"- {mat}, {'with' if rs else 'without'} resampling: load pinch-off at dx {dl} mm: "
                             f"plain {lp(mat, rs, False)} mm, fracture {lp(mat, rs, True)} mm.")
    body += "\n" + "\n".join(notes) + "\n"
    C.write_md(NAME, args.quick, "Fracture: a pulled thread at three resolutions", body)


if __name__ == "__main__":
    main()
