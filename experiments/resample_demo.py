"""Resampling demo: a foam sheet with a round cavity, stretched to about 2.5x its length.

Without resampling the points separate along the stretch and cells inside the sheet empty out
(non-physical voids); with `ResampleConfig` the sparse cells are refilled while the cavity, a real
hole, stays empty. Writes experiments/results/resample_demo[_quick].png/.md.

Measures, at every frame, for the plain run and the resampled run:
- void fraction: the share of empty cells among the interior cells of the sheet: strictly between the
  lowest and the highest occupied cell of their column, and more than dx from the cavity;
- the cavity: the empty region around the cavity's centre, found by flood fill on a raster of
  pixels dx/4 wide where a pixel is filled when a point lies within 0.75 dx of it (this bridges the
  stretch voids, which are narrower than 1.5 dx, but not the cavity); its area;
- conservation: total mass, and the momentum change that resampling itself makes (measured on the
  resampling pass alone).
Run: `python experiments/resample_demo.py [--quick]` (quick: dx 3 mm instead of 1.5 mm).
"""
from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import jaxfoam  # noqa: E402
from experiments import _common as C  # noqa: E402
from jaxfoam.resample import ResampleConfig, resample_with_stats, rollout_key  # noqa: E402

NAME = "resample_demo"
# A soft foam (low yield stress) so that the sheet keeps stretching on its own momentum.
PARAMS = jaxfoam.Params(mu=300.0, kappa=3000.0, sigma_y=0.5, eta=0.05, m=0.5, rho=100.0)
SHEET = ((-0.03, 0.02), (0.03, 0.08))     # sheet box (min, max), m
CAVITY = ((0.0, 0.05), (0.010, 0.016))   # cavity centre (m) and radii along x and y (m): elongated
                                          # across the stretch, so it stays wider than 2 dx
COVER = 0.75                              # raster cover radius, units of dx
RATE = 7.0                                # initial extension rate, 1/s: v = (RATE (x - xc), 0)
DURATION = 0.3                            # s
FRAMES = 15


def scene_spec():
    (x0, y0), (x1, y1) = SHEET
    return dict(kind="drop", dim=2, gravity=[0.0, 0.0], density=PARAMS.rho, kappa=PARAMS.kappa,
                domain=dict(min=[-0.16, 0.0], max=[0.16, 0.1]),
                initial_shape=dict(type="box", min=[x0, y0], max=[x1, y1]),
                initial_velocity=[0.0, 0.0], name="stretched sheet with a cavity")


def initial_state(scene, dx):
    """The sheet sampled at 4 points per cell with the cavity cut out, in planar extension."""
    st = jaxfoam.init_state(scene, dx, 4, rho=float(PARAMS.rho))
    x = np.asarray(st.x)[np.asarray(st.active)]
    c, r = np.asarray(CAVITY[0]), np.asarray(CAVITY[1])
    x = x[np.sum(((x - c) / r) ** 2, axis=1) > 1.0]
    vol = np.full(len(x), dx * dx / 4)
    # Extension along x only, v = (RATE (x - xc), 0), with the matching affine velocity gradient C: the
    # contraction along y then comes from the pressure, not from momentum aimed at the cavity.
    v = RATE * (x - c) * np.array([1.0, 0.0])
    st = jaxfoam.make_state(x, vol, float(PARAMS.rho) * vol, v=v)
    return st.replace(C=jnp.broadcast_to(jnp.diag(jnp.asarray([RATE, 0.0])), st.C.shape))


def observe(state, params):
    return dict(x=state.x, active=state.active, mass=state.mass, v=state.v)


def cavity_region(x, dx, lo, hi):
    """Boolean raster (pixels dx/4, rows along y) of the empty region connected to the cavity centre."""
    pixel = dx / 4
    covered = C.rasterize(x, np.ones(len(x), bool), lo, hi, pixel, COVER * dx)
    seed = tuple(np.floor((np.asarray(CAVITY[0]) - lo) / pixel).astype(int)[::-1])
    region = np.zeros_like(covered)
    if covered[seed]:
        return region, pixel
    region[seed] = True
    while True:  # grow by 4-neighbours through uncovered pixels until nothing changes
        grown = region.copy()
        grown[1:] |= region[:-1]
        grown[:-1] |= region[1:]
        grown[:, 1:] |= region[:, :-1]
        grown[:, :-1] |= region[:, 1:]
        grown &= ~covered
        if (grown == region).all():
            return region, pixel
        region = grown


def void_fraction(x, cavity, pixel, dx, lo):
    """Share of empty cells among the interior cells of the sheet.

    Interior: strictly between the lowest and the highest occupied cell of the cell's column, and
    farther than one dx from the cavity (cells cut by a boundary are partly empty for real).
    """
    ij = np.floor((x - lo[None, :]) / dx).astype(int)
    occupied = set(map(tuple, ij))
    near_cavity = cavity.copy()
    r = int(round(dx / pixel))
    for _ in range(r):  # dilate the cavity by dx
        grown = near_cavity.copy()
        grown[1:] |= near_cavity[:-1]
        grown[:-1] |= near_cavity[1:]
        grown[:, 1:] |= near_cavity[:, :-1]
        grown[:, :-1] |= near_cavity[:, 1:]
        near_cavity = grown
    inside = empty = 0
    for i in np.unique(ij[:, 0]):
        col = ij[ij[:, 0] == i, 1]
        for j in range(col.min() + 1, col.max()):
            centre = lo + (np.array([i, j]) + 0.5) * dx
            pi, pj = np.floor((centre - lo) / pixel).astype(int)[::-1]
            if near_cavity[pi, pj]:
                continue
            inside += 1
            empty += (i, j) not in occupied
    return empty / max(inside, 1)


def run(dx, resample):
    scene = jaxfoam.load_scene(scene_spec())
    st0 = initial_state(scene, dx)
    cfg = ResampleConfig(every=10) if resample else None
    st0 = cfg.prepare(st0) if resample else st0
    times = np.linspace(DURATION / FRAMES, DURATION, FRAMES)
    sim = jaxfoam.Simulator(scene, times, PARAMS, dx, state0=st0, resample=cfg)
    with C.Timer() as tm:
        final, frames, health = sim.rollout(PARAMS, observe=observe)
        frames = jax.device_get(frames)
    sim.check(frames, health)
    lo, hi = np.asarray(scene.domain_min), np.asarray(scene.domain_max)
    rows, cavities = [], []
    for k, t in enumerate(times):
        act = frames["active"][k]
        x = frames["x"][k][act]
        cav, pixel = cavity_region(x, dx, lo, hi)
        cavities.append(cav)
        # A cavity region that reaches the raster's border has leaked: the sheet around it broke open
        # (or was too sparse to enclose it); its area and the void fraction are then undefined.
        leaked = bool(cav[0].any() or cav[-1].any() or cav[:, 0].any() or cav[:, -1].any())
        nan = float("nan")
        rows.append(dict(t=float(t), void=nan if leaked else void_fraction(x, cav, pixel, dx, lo),
                         cavity_area=nan if leaked else cav.sum() * pixel ** 2, leaked=leaked,
                         n=int(act.sum()), mass=float(np.sum(frames["mass"][k] * act))))
    return dict(sim=sim, frames=frames, rows=rows, seconds=tm.seconds, st0=st0, cavities=cavities,
                extent=(lo[0], hi[0], lo[1], hi[1]))


def pass_conservation(sim, state):
    """Mass and momentum before/after one resampling pass applied to `state` (relative changes)."""
    cfg = ResampleConfig()
    out, stats = jax.jit(lambda s: resample_with_stats(s, sim.grid, cfg, rollout_key(cfg, 0)))(state)
    m0 = jnp.sum(state.mass * state.active)
    m1 = jnp.sum(out.mass * out.active)
    p0 = jnp.sum((state.mass * state.active)[:, None] * state.v, 0)
    p1 = jnp.sum((out.mass * out.active)[:, None] * out.v, 0)
    pscale = jnp.sum(state.mass * state.active * jnp.linalg.norm(state.v, axis=1))
    return (float(abs(m1 - m0) / m0), float(jnp.max(jnp.abs(p1 - p0)) / pscale),
            int(stats["inserted"]), int(stats["merged"]))


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    dx = 0.003 if args.quick else 0.0015
    plain = run(dx, False)
    res = run(dx, True)
    # One pass applied to the plain run's final (stretched) state, for the conservation check.
    fin = plain["frames"]
    last = jaxfoam.make_state(fin["x"][-1], np.asarray(plain["st0"].vol0), np.asarray(plain["st0"].mass),
                              v=fin["v"][-1], capacity=2 * len(fin["x"][-1]))
    dm, dp, n_ins, n_mrg = pass_conservation(plain["sim"], last)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(12, 7.5))
    gs = fig.add_gridspec(3, 2, height_ratios=[1, 1, 1.3])
    for r, (name, out) in enumerate((("plain MPM", plain), ("with resampling", res))):
        for c, k in enumerate((FRAMES // 2 - 1, FRAMES - 1)):
            ax = fig.add_subplot(gs[r, c])
            fr = out["frames"]
            act = fr["active"][k]
            n0 = int(np.asarray(out["st0"].active).sum())
            new = act & (np.arange(len(act)) >= n0)
            ax.scatter(fr["x"][k][act & ~new, 0], fr["x"][k][act & ~new, 1], s=1.5, c="#4a7ab5", lw=0)
            ax.scatter(fr["x"][k][new, 0], fr["x"][k][new, 1], s=1.5, c="#d1495b", lw=0)
            ax.contour(out["cavities"][k], [0.5], colors="k", linewidths=0.7, origin="lower",
                       extent=out["extent"])
            ax.set_aspect("equal")
            ax.set_xlim(-0.15, 0.15)
            ax.set_ylim(0.015, 0.085)
            ax.set_title(f"{name}, t = {out['rows'][k]['t']:.2f} s (void {out['rows'][k]['void']:.1%})", fontsize=9)
    ax = fig.add_subplot(gs[2, 0])
    t = [r["t"] for r in plain["rows"]]
    ax.plot(t, [100 * r["void"] for r in plain["rows"]], "o-", label="plain MPM")
    ax.plot(t, [100 * r["void"] for r in res["rows"]], "s-", label="with resampling")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("void fraction of the sheet (%)")
    ax.legend()
    ax = fig.add_subplot(gs[2, 1])
    ax.plot(t, [1e6 * r["cavity_area"] for r in plain["rows"]], "o-", label="plain MPM")
    ax.plot(t, [1e6 * r["cavity_area"] for r in res["rows"]], "s-", label="with resampling")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("cavity area (mm$^2$)")
    ax.legend()
    fig.suptitle("Stretched sheet (red: inserted points; black: the cavity's outline)", fontsize=10)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    rows = []
    for a, b in zip(plain["rows"], res["rows"]):
        rows.append([a["t"], 100 * a["void"], 100 * b["void"], 1e6 * a["cavity_area"], 1e6 * b["cavity_area"],
                     a["n"], b["n"]])
    table = C.md_table(["t (s)", "void % plain", "void % resampled", "cavity mm^2 plain",
                        "cavity mm^2 resampled", "points plain", "points resampled"], rows)
    both = [(a["void"], b["void"]) for a, b in zip(plain["rows"], res["rows"])
            if not (a["leaked"] or b["leaked"])]
    leak = {name: next((r["t"] for r in out["rows"] if r["leaked"]), None)
            for name, out in (("plain", plain), ("resampled", res))}
    area = [(a["cavity_area"], b["cavity_area"]) for a, b in zip(plain["rows"], res["rows"])
            if not (a["leaked"] or b["leaked"])]
    summary = (f"- Mean void fraction over the {len(both)} frames where neither cavity leaked: plain "
               f"{100 * np.mean([a for a, _ in both]):.2f}%, resampled {100 * np.mean([b for _, b in both]):.2f}%. "
               f"Cavity leaked to the outside (the sheet around it no longer encloses it at 1.5 dx): plain "
               f"{'at t = %.2f s' % leak['plain'] if leak['plain'] is not None else 'never'}, resampled "
               f"{'at t = %.2f s' % leak['resampled'] if leak['resampled'] is not None else 'never'}. "
               f"Cavity area, resampled / plain, over those frames: "
               f"{min(b / a for a, b in area):.3f} to {max(b / a for a, b in area):.3f}.\n")
    m_plain = plain["rows"][-1]["mass"] / plain["rows"][0]["mass"] - 1
    m_res = res["rows"][-1]["mass"] / plain["rows"][0]["mass"] - 1
    body = (f"Sheet {100 * (SHEET[1][0] - SHEET[0][0]):.0f} x {100 * (SHEET[1][1] - SHEET[0][1]):.0f} cm with an "
            f"elliptic cavity of radii {1000 * CAVITY[1][0]:.0f} x {1000 * CAVITY[1][1]:.0f} mm, set in extension at t = 0 (v = ({RATE} 1/s "
            f"(x - xc), 0)) and left to coast for {DURATION} s; gravity off; "
            f"mu {PARAMS.mu} Pa, sigma_y {PARAMS.sigma_y} Pa, "
            f"eta {PARAMS.eta} Pa s^m, m {PARAMS.m}, kappa {PARAMS.kappa} Pa, rho {PARAMS.rho} kg/m^3; "
            f"dx {1000 * dx:g} mm, 4 points per cell, dt {plain['sim'].dt:.3g} s, "
            f"{plain['sim'].total_substeps} substeps. Resampling every 10 substeps (defaults of ResampleConfig).\n\n"
            f"![resampling]({NAME}{'_quick' if args.quick else ''}.png)\n\n{table}\n"
            f"{summary}"
            f"- Wall time (shared 2-core CPU, compile included): plain {plain['seconds']:.1f} s, "
            f"resampled {res['seconds']:.1f} s.\n"
            f"- Total mass change over the run: plain {m_plain:.2e}, resampled {m_res:.2e} (relative).\n"
            f"- One resampling pass on the plain run's final state: inserted {n_ins}, merged {n_mrg}; "
            f"relative mass change {dm:.1e}, momentum change {dp:.1e} of sum m|v| (round-off).\n"
            f"- Void fraction: the share of empty cells among the interior cells: strictly between the "
            f"lowest and the highest occupied cell of their column and more than dx from the cavity. Cavity: the empty region connected to the cavity's "
            f"centre on a raster of dx/4 pixels, a pixel filled when a point lies within {COVER} dx.\n")
    C.write_md(NAME, args.quick, "Resampling: voids in a stretched sheet", body)


if __name__ == "__main__":
    main()
