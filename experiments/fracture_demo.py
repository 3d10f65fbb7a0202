"""Fracture demo: a foam thread pulled apart between two plates, at three resolutions, with and
without the fracture stage (`jaxfoam.fracture.FractureConfig`).

A strip of foam (1 cm wide, 2.1 cm long, 2D plane strain, gravity off) is held by a still bottom
plate and a top plate that rises at a constant speed. Measured for each run:
- pinch-off extension: how far the top plate had risen when the material attached to it stopped
  being connected to the material on the bottom plate (connectivity on a raster of dx/2 pixels,
  a pixel filled within 0.75 dx of a point: pieces closer than 1.5 dx count as connected);
- the force-based extension: when the plate's pull on the foam (the grid momentum the plate
  imposes, `collider_force`) falls for good below 5% of its peak;
- weak points at pinch-off (fracture runs).
Two materials: a yield-stress foam (sigma_y 30 Pa, m 0.5) and a viscous, nearly Bingham one
(sigma_y 5 Pa, eta 20 Pa s, m 1). Writes experiments/results/fracture_demo[_quick].png/.md.
Run: `python experiments/fracture_demo.py [--quick]` (quick: the yield-stress foam at the two
coarsest resolutions).
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
from jaxfoam.fracture import FractureConfig, collider_force, density_ratio  # noqa: E402

NAME = "fracture_demo"
MATERIALS = {
    "yield-stress foam": jaxfoam.Params(mu=300.0, kappa=3000.0, sigma_y=30.0, eta=3.0, m=0.5, rho=100.0),
    "viscous (Bingham-like)": jaxfoam.Params(mu=300.0, kappa=3000.0, sigma_y=5.0, eta=20.0, m=1.0, rho=100.0),
}
WIDTH = 0.01          # strip width, m
SPEED = 0.1           # top plate speed, m/s
DURATION = 0.5        # s
FRAMES = 50
DXS = (0.0025, 0.00125, 0.000625)   # strip 4, 8, 16 cells wide
COVER = 0.75          # connectivity: pixels filled within this many dx of a point
FORCE_DROP = 0.05     # force-based pinch-off: the pull stays below this share of its peak


def scene():
    y_top = 0.035
    return jaxfoam.load_scene(dict(
        kind="squeeze", dim=2, gravity=[0.0, 0.0], density=100.0, kappa=3000.0,
        domain=dict(min=[-0.03, 0.0], max=[0.03, y_top + 0.01 + SPEED * DURATION + 0.02]),
        plates=[dict(center=[0.0, 0.01], half_size=[0.02, 0.005]),
                dict(center=[0.0, y_top], half_size=[0.02, 0.005],
                     # the motion runs past the end of the run: no stop (a velocity jump) inside it
                     motion=dict(type="samples", times=[0.0, 2 * DURATION],
                                 positions=[[0.0, y_top], [0.0, y_top + 2 * SPEED * DURATION]]))],
        initial_shape=dict(type="box", min=[-WIDTH / 2, 0.012], max=[WIDTH / 2, 0.033]),
        name="pulled thread"))


def top_region(t):
    """Grid nodes of the top plate at time t (its box, with a small tolerance)."""
    def region(nx):
        yc = 0.035 + SPEED * t
        return (jnp.abs(nx[:, 1] - yc) <= 0.005 + 1e-9) & (jnp.abs(nx[:, 0]) <= 0.02 + 1e-9)
    return region


def run(params, dx, fracture):
    sc = scene()
    times = np.linspace(DURATION / FRAMES, DURATION, FRAMES)
    frac = FractureConfig() if fracture else None
    sim = jaxfoam.Simulator(sc, times, params, dx, fracture=frac)

    def observe(state, prm):
        f = collider_force(state, prm, sc, sim.grid, sim.dt, region=top_region(state.t))
        _, gm = jaxfoam.p2g(state, prm, sim.grid, sim.dt)
        weak = state.active & (density_ratio(state, gm, sim.grid) < FractureConfig().threshold(2))
        return dict(x=state.x, force=f[1], weak=jnp.sum(weak))

    with C.Timer() as tm:
        final, frames, health = sim.rollout(params, observe=observe)
        frames = jax.device_get(frames)
    sim.check(frames, health)
    return dict(frames=frames, times=times, seconds=tm.seconds, sim=sim)


def connected(x, dx, t):
    """Whether the material touching the top plate is connected to the material on the bottom plate."""
    lo, hi = np.array([-0.03, 0.0]), np.array([0.03, 0.035 + SPEED * t + 0.01])
    pixel = dx / 2
    img = C.rasterize(x, np.ones(len(x), bool), lo, hi, pixel, COVER * dx)
    ys = lo[1] + (np.arange(img.shape[0]) + 0.5) * pixel
    top_row = int(np.searchsorted(ys, 0.035 + SPEED * t - 0.005))
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


def pinch_off(out, dx):
    """(extension at disconnection m, extension at force drop m, weak points then)."""
    fr, times = out["frames"], out["times"]
    conn = [connected(fr["x"][k], dx, t) for k, t in enumerate(times)]
    k_sep = next((k for k in range(len(conn)) if not any(conn[k:])), None)
    f = fr["force"]
    peak = np.max(f)
    low = np.abs(f) < FORCE_DROP * peak
    k_f = next((k for k in range(len(f)) if low[k:].all()), None)
    ext = (lambda k: SPEED * times[k] if k is not None else float("nan"))
    return ext(k_sep), ext(k_f), int(fr["weak"][k_sep]) if k_sep is not None else -1, conn


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    mats = list(MATERIALS)[:1] if args.quick else list(MATERIALS)
    dxs = DXS[:2] if args.quick else DXS
    results = {}
    for mat in mats:
        for dx in dxs:
            for fracture in (False, True):
                out = run(MATERIALS[mat], dx, fracture)
                e_sep, e_f, weak, conn = pinch_off(out, dx)
                results[(mat, dx, fracture)] = dict(out=out, e_sep=e_sep, e_force=e_f, weak=weak)
                print(f"{mat}, dx {dx * 1000:g} mm, fracture {fracture}: pinch-off at {1000 * e_sep:.1f} mm "
                      f"(force: {1000 * e_f:.1f} mm), {out['seconds']:.0f} s", flush=True)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(mats), 3, figsize=(13, 4.2 * len(mats)), squeeze=False)
    for r, mat in enumerate(mats):
        ax = axes[r, 0]
        for fracture, mk in ((False, "o-"), (True, "s--")):
            ax.plot([1000 * dx for dx in dxs], [1000 * results[(mat, dx, fracture)]["e_sep"] for dx in dxs], mk,
                    label="with fracture" if fracture else "plain MPM")
        ax.set_xticks([1000 * dx for dx in dxs])
        ax.set_xlabel("dx (mm)")
        ax.set_ylabel("pinch-off extension (mm)")
        ax.set_title(mat, fontsize=10)
        ax.legend()
        ax = axes[r, 1]
        for dx in dxs:
            for fracture, ls in ((False, "-"), (True, "--")):
                o = results[(mat, dx, fracture)]["out"]
                ax.plot(1000 * SPEED * o["times"], o["frames"]["force"], ls, lw=1,
                        label=f"dx {1000 * dx:g} mm{' fracture' if fracture else ''}")
        ax.set_xlabel("top plate travel (mm)")
        ax.set_ylabel("pull on the foam (N/m)")
        ax.legend(fontsize=7)
        ax = axes[r, 2]
        dx = dxs[-1]
        for c, fracture in enumerate((False, True)):
            res = results[(mat, dx, fracture)]
            o = res["out"]
            k = int(np.argmin(np.abs(SPEED * o["times"] - res["e_sep"]))) if np.isfinite(res["e_sep"]) else -1
            k = min(k + 2, len(o["times"]) - 1)
            x = o["frames"]["x"][k]
            ax.scatter(x[:, 0] + (0.025 if fracture else -0.005), x[:, 1], s=0.5, lw=0,
                       c="#d1495b" if fracture else "#4a7ab5")
        ax.set_aspect("equal")
        ax.set_title(f"dx {1000 * dx:g} mm, just after pinch-off\n(left plain, right fracture)", fontsize=9)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    rows = []
    for mat in mats:
        for dx in dxs:
            for fracture in (False, True):
                res = results[(mat, dx, fracture)]
                rows.append([mat, 1000 * dx, "yes" if fracture else "no", 1000 * res["e_sep"], 1000 * res["e_force"],
                             res["weak"], int(res["out"]["sim"].state0.active.sum()), res["out"]["sim"].total_substeps,
                             res["out"]["seconds"]])
    table = C.md_table(["material", "dx (mm)", "fracture", "pinch-off extension (mm)", "force-drop extension (mm)",
                        "weak points then", "points", "substeps", "wall s"], rows)
    pairs = [(results[(mat, dx, False)], results[(mat, dx, True)]) for mat in mats for dx in dxs]
    changed = sum(1 for a, b in pairs if not np.isclose(a["e_sep"], b["e_sep"]))
    max_weak = max(r["weak"] for a, b in pairs for r in (a, b))
    body = (f"Strip {1000 * WIDTH:.0f} mm wide between a still bottom plate and a top plate rising at "
            f"{SPEED} m/s for {DURATION} s (2D plane strain, gravity off, kappa 3000 Pa, rho 100 kg/m^3). "
            f"Materials: " + "; ".join(f"{k}: mu {p.mu} Pa, sigma_y {p.sigma_y} Pa, eta {p.eta} Pa s^m, m {p.m}"
                                       for k, p in MATERIALS.items() if k in mats) + ".\n\n"
            f"![fracture]({NAME}{'_quick' if args.quick else ''}.png)\n\n{table}\n"
            f"- Pinch-off extension: top plate travel at the first frame after which the material on the two "
            f"plates stays disconnected (raster of dx/2 pixels, filled within {COVER} dx of a point). "
            f"Force-drop extension: travel after which the plate's pull stays below {FORCE_DROP:.0%} of its peak "
            f"(nan: never; elastic ringing of the detached piece can keep it above). Frames every "
            f"{1000 * SPEED * DURATION / FRAMES:g} mm of travel.\n"
            f"- Wall times on a shared 2-core CPU, compile included.\n"
            f"- The fracture stage changed the pinch-off extension in {changed} of {len(pairs)} cases; at most "
            f"{max_weak} point(s) were weak at pinch-off: in these pulls plain MLS-MPM necks and separates "
            f"before a single-file chain (the weak configuration) forms.\n")
    C.write_md(NAME, args.quick, "Fracture: a pulled thread at three resolutions", body)


if __name__ == "__main__":
    main()
