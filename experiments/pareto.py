"""Accuracy against speed for the hanging-plate and drop scenes: dx, particles per cell, CFL, float32/64, 2D/3D.

For each scene (experiments/scenes/<scene>_2d.json, foam mu = 200 Pa, sigma_y = 40 Pa, eta = 10 Pa s^0.5,
m = 0.5, the CLI defaults) every run changes one knob from the base setting (the CLI default: 64 cells
across the domain width, 4 particles per cell, CFL 0.3, float64) and is compared with a reference run at
the finest resolution affordable here (REF_CELLS cells, CFL REF_CFL):

- silhouette error = 1 - IoU of the particle occupancy images, averaged over the frames. A pixel
  (PIXEL m) is occupied when a particle lies within 0.75 particle spacings (dx / ppc^(1/d)) of its
  centre; 3D runs are projected along z (the camera of shared/specs/silhouettes.md);
- stress error = || s - s_ref || / || s_ref || over all frames, with s the deviatoric stress magnitude
  (Pa) averaged per STRESS_CELL square (cells empty in one run count as 0).

Wall time is the rollout alone (compiled ahead of time, compile excluded), on the shared 2-core machine.
The 3D point runs the scene's 3D version (a slab of finite depth) and is compared with the 2D reference:
its error is the plane-strain modelling error for that geometry, not a discretization error. The kappa
points change the model too (bulk modulus 1000 and 10000 Pa instead of the scene's 3000 Pa): their error
is how much the answer depends on compressibility; the volume error max over frames of mean |J - 1| is
listed for every run.

Usage: python -m experiments pareto [--quick] [--scene hanging_plate|drop] [--no-3d | --only-3d]. Writes
experiments/results/pareto[_quick].png/.md; with --scene, --no-3d or --only-3d (a partial study, e.g. a re-run
after a scene file changed) it writes pareto_<scene...>[_2d|_3d][_quick].png/.md instead, never over the full
results.
"""
from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C
from jaxfoam._scene import DEFAULT_PPC

NAME = "pareto"
SCENES = Path(__file__).resolve().parent / "scenes"
# The CLI defaults (jaxfoam/cli.py): shaving-cream-like foam.
FOAM = dict(mu=200.0, sigma_y=40.0, eta=10.0, m=0.5)
DURATION = {"hanging_plate": 1.0, "drop": 0.5}   # simulated time, s (half in --quick)
FRAMES = 10
BASE = dict(cells=64, ppc=None, cfl=0.3, dtype="float64", dim=2, kappa=None)  # the CLI default discretization
REF_CELLS, REF_CFL = 96, 0.15     # reference: the finest resolution affordable on 2 shared cores
PIXEL = 0.002                     # silhouette pixel, m
STRESS_CELL = 0.01                # stress comparison cell, m
SPREAD = 0.75                     # occupancy radius in particle spacings


def load(name: str, dim: int):
    spec = json.loads((SCENES / f"{name}_{dim}d.json").read_text())
    return spec, jaxfoam.load_scene(spec)


def simulate(name: str, cells: int, ppc, cfl: float, dtype: str, dim: int, duration: float, kappa=None):
    """One run (kappa Pa: the bulk modulus, default the scene's).

    Returns dict(x (T, N, 2) projected positions m, s (T, N) Pa, active (T, N), volume error max over frames of
    mean |J - 1|, seconds, particles, steps, dx)."""
    spec, scene = load(name, dim)
    width = scene.domain_max[0] - scene.domain_min[0]
    dx = width / cells
    dt_type = jnp.float64 if dtype == "float64" else jnp.float32
    if dtype == "float32":
        scene = jaxfoam.load_scene(spec, dtype=jnp.float32)
    params = jaxfoam.Params(kappa=scene.kappa if kappa is None else kappa, rho=scene.density, **FOAM)
    times = np.linspace(duration / FRAMES, duration, FRAMES)
    sim = jaxfoam.Simulator(scene, times, params, dx, ppc, dtype=dt_type, cfl=cfl)

    def observe(s, p):
        return dict(x=s.x[:, :2], s=jaxfoam.deviatoric_stress_norm(s.bbar_e, p), active=s.active,
                    dJ=jnp.sum(jnp.where(s.active, jnp.abs(jaxfoam.det(s.F) - 1.0), 0.0)) / jnp.sum(s.active))

    f = jax.jit(functools.partial(C.rollout, grid=sim.grid, n_frames=FRAMES, substeps=sim.substeps, observe=observe))
    args = (sim.state0, params.astype(dt_type), scene, jnp.asarray(sim.dt, dt_type))
    compiled = f.lower(*args).compile()
    with C.Timer() as tm:
        _, fr = compiled(*args)
        fr = jax.block_until_ready(fr)
    fr = jax.device_get(fr)
    n_ppc = DEFAULT_PPC[dim] if ppc is None else ppc
    return dict(x=fr["x"].astype(np.float64), s=fr["s"].astype(np.float64), active=fr["active"], seconds=tm.seconds,
                volume_error=float(np.max(fr["dJ"])),
                particles=int(np.asarray(sim.state0.active).sum()), steps=sim.total_substeps, dx=dx,
                spacing=dx / n_ppc ** (1.0 / dim), scene=scene)


def images(run, lo, hi):
    return [C.rasterize(run["x"][k], run["active"][k], lo, hi, PIXEL, SPREAD * run["spacing"]) for k in range(FRAMES)]


def stress_cells(run, lo, hi):
    """(T, ny, nx) mean deviatoric stress per STRESS_CELL square, Pa (0 where empty)."""
    nx = int(math.ceil((hi[0] - lo[0]) / STRESS_CELL))
    ny = int(math.ceil((hi[1] - lo[1]) / STRESS_CELL))
    out = np.zeros((FRAMES, ny, nx))
    for k in range(FRAMES):
        a = run["active"][k]
        x, s = run["x"][k][a], run["s"][k][a]
        j = np.clip(((x[:, 0] - lo[0]) / STRESS_CELL).astype(int), 0, nx - 1)
        i = np.clip(((x[:, 1] - lo[1]) / STRESS_CELL).astype(int), 0, ny - 1)
        tot = np.zeros((ny, nx))
        cnt = np.zeros((ny, nx))
        np.add.at(tot, (i, j), s)
        np.add.at(cnt, (i, j), 1.0)
        out[k] = np.where(cnt > 0, tot / np.maximum(cnt, 1.0), 0.0)
    return out


def errors(run, ref, lo, hi):
    img, img_ref = images(run, lo, hi), ref["images"]
    sil = 1.0 - float(np.mean([C.iou(a, b) for a, b in zip(img, img_ref)]))
    sc = stress_cells(run, lo, hi)
    stress = float(np.linalg.norm(sc - ref["stress"]) / np.linalg.norm(ref["stress"]))
    return sil, stress


def variants(quick: bool):
    """(label, knobs) for the one-at-a-time sweep around BASE."""
    if quick:  # around a coarser base (32 cells) so that it runs in about a minute per scene
        return [("base (32 cells, ppc 4, CFL 0.3, f64)", dict(cells=32)), ("24 cells", dict(cells=24)),
                ("32 cells, CFL 0.6", dict(cells=32, cfl=0.6)), ("32 cells, float32", dict(cells=32, dtype="float32"))]
    return [("base (64 cells, ppc 4, CFL 0.3, f64)", {}), ("32 cells", dict(cells=32)), ("48 cells", dict(cells=48)),
            ("ppc 1", dict(ppc=1)), ("ppc 9", dict(ppc=9)), ("CFL 0.15", dict(cfl=0.15)), ("CFL 0.6", dict(cfl=0.6)),
            ("CFL 0.9", dict(cfl=0.9)), ("float32", dict(dtype="float32")), ("32 cells, CFL 0.6", dict(cells=32, cfl=0.6)),
            ("kappa 1000 Pa", dict(kappa=1000.0)), ("kappa 10000 Pa", dict(kappa=1e4)),
            ("3D slab, 32 cells", dict(dim=3, cells=32))]


def study(name: str, quick: bool, no_3d: bool = False, only_3d: bool = False):
    ref_cells, ref_cfl = (48, 0.15) if quick else (REF_CELLS, REF_CFL)
    duration = DURATION[name] * (0.5 if quick else 1.0)
    ref = simulate(name, ref_cells, None, ref_cfl, "float64", 2, duration)
    scene = ref["scene"]
    lo, hi = np.asarray(scene.domain_min[:2]), np.asarray(scene.domain_max[:2])
    ref["images"] = images(ref, lo, hi)
    ref["stress"] = stress_cells(ref, lo, hi)
    print(f"{name}: reference {ref_cells} cells CFL {ref_cfl}: {ref['particles']} particles, {ref['steps']} steps, "
          f"{ref['seconds']:.0f} s", flush=True)
    rows = []
    for label, knobs in variants(quick):
        if (no_3d and knobs.get("dim", 2) == 3) or (only_3d and knobs.get("dim", 2) != 3):
            continue
        cfg = dict(BASE, **knobs)
        run = simulate(name, cfg["cells"], cfg["ppc"], cfg["cfl"], cfg["dtype"], cfg["dim"], duration, cfg["kappa"])
        if not np.all(np.isfinite(run["x"][run["active"]])):
            rows.append(dict(label=label, sil=float("nan"), stress=float("nan"), seconds=run["seconds"],
                             particles=run["particles"], steps=run["steps"], dx=run["dx"], volume_error=float("nan")))
            continue
        sil, stress = errors(run, ref, lo, hi)
        print(f"  {label}: silhouette error {sil:.4f}, stress error {stress:.4f}, {run['seconds']:.2f} s", flush=True)
        rows.append(dict(label=label, sil=sil, stress=stress, seconds=run["seconds"], particles=run["particles"],
                         steps=run["steps"], dx=run["dx"], volume_error=run["volume_error"]))
    return dict(ref=dict(cells=ref_cells, cfl=ref_cfl, particles=ref["particles"], steps=ref["steps"],
                         seconds=ref["seconds"], duration=duration, volume_error=ref["volume_error"]), rows=rows)


def pareto_front(rows, key):
    """Labels of the rows no other row beats in both wall time and error."""
    front = []
    for r in rows:
        if not np.isfinite(r[key]):
            continue
        dominated = any(o is not r and np.isfinite(o[key]) and o["seconds"] <= r["seconds"] and o[key] <= r[key]
                        and (o["seconds"] < r["seconds"] or o[key] < r[key]) for o in rows)
        if not dominated:
            front.append(r["label"])
    return front


def main(argv=None):
    import argparse
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced version (minutes on 2 cores)")
    parser.add_argument("--scene", action="append", choices=tuple(DURATION), help="only this scene (repeatable)")
    parser.add_argument("--no-3d", action="store_true", help="leave out the 3D point")
    parser.add_argument("--only-3d", action="store_true", help="only the reference and the 3D point")
    args = parser.parse_args(argv)
    if args.no_3d and args.only_3d:
        parser.error("--no-3d and --only-3d exclude each other")
    scenes = tuple(args.scene) if args.scene else tuple(DURATION)
    name_out = NAME if (scenes == tuple(DURATION) and not args.no_3d and not args.only_3d) else \
        "_".join([NAME, *scenes] + (["2d"] if args.no_3d else []) + (["3d"] if args.only_3d else []))
    results = {name: study(name, args.quick, args.no_3d, args.only_3d) for name in scenes}

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, len(results), figsize=(6.5 * len(results), 9), squeeze=False)
    for col, (name, res) in enumerate(results.items()):
        for row, (key, title) in enumerate((("sil", "silhouette error 1 - IoU"), ("stress", "stress-field error"))):
            ax = axes[row, col]
            pts = [r for r in res["rows"] if np.isfinite(r[key])]
            front = pareto_front(pts, key)
            for r in pts:
                on = r["label"] in front
                ax.loglog(r["seconds"], max(r[key], 1e-4), "o", color="C3" if on else "C0", ms=7 if on else 5)
                ax.annotate(r["label"], (r["seconds"], max(r[key], 1e-4)), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
            ax.set_xlabel("rollout wall time (s, compile excluded)")
            ax.set_ylabel(title)
            ax.set_title(f"{name}: {title} vs time (red: Pareto front)", fontsize=9)
    fig.tight_layout()
    C.save_fig(fig, name_out, args.quick)

    parts = [f"Foam {FOAM} (kappa, rho from the scene), {FRAMES} frames over {DURATION} s (half in quick runs). Base = "
             f"{BASE['cells']} cells across the domain width, default ppc (4 in 2D, 8 in 3D), CFL {BASE['cfl']}, float64. "
             f"Silhouette pixel {PIXEL} m, stress cells {STRESS_CELL} m.\n\n"]
    for name, res in results.items():
        ref = res["ref"]
        parts.append(f"## {name}\n\nReference: {ref['cells']} cells, CFL {ref['cfl']}, {ref['particles']} particles, "
                     f"{ref['steps']} substeps, {ref['seconds']:.1f} s, volume error max mean |J-1| "
                     f"{ref['volume_error']:.3g}.\n\n")
        front_s = pareto_front(res["rows"], "sil")
        front_t = pareto_front(res["rows"], "stress")
        parts.append(C.md_table(
            ["setting", "particles", "substeps", "wall s", "silhouette error", "stress error", "max mean abs(J-1)",
             "Pareto (sil / stress)"],
            [[r["label"], r["particles"], r["steps"], r["seconds"], r["sil"], r["stress"], r["volume_error"],
              ("yes" if r["label"] in front_s else "no") + " / " + ("yes" if r["label"] in front_t else "no")]
             for r in res["rows"]]) + "\n")
    flags = "".join(f" --scene {n}" for n in scenes) + (" --no-3d" if args.no_3d else "") + \
        (" --only-3d" if args.only_3d else "")
    # a partial study names the command that regenerates it, not its output name
    C.write_md(name_out, args.quick, "Accuracy against speed", "".join(parts),
               command=None if name_out == NAME else NAME + flags)


if __name__ == "__main__":
    main()
