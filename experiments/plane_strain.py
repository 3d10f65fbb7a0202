"""2D plane strain against 3D: how deep a block of foam must be before the 2D model reproduces its silhouette.

A 2D simulation is an infinitely deep slab (plane strain). A real foam sample has a finite depth D along
the camera axis, with free front and back faces. This study extrudes the cross-section of each 2D scene
(`scenes/drop_2d.json`, `scenes/hanging_plate_2d.json`, the current 2 cm grip) along z and simulates:

- "slab": the cross-section filling a domain only SLAB_CELLS cells deep, whose front and back walls are
  slip walls: plane strain, discretized in 3D (model.md, "Plane strain (2D)"; tests/jaxfoam/test_plane_strain.py);
- "block D/W = r": a block of depth D = r W (W the foam's width along x) centred in a domain with MARGIN of
  free space in front and behind, so its front and back faces are free (the hanging plate's board covers the
  block's depth plus the margin);
- "2D": the 2D scene at the same dx, and "2D, dx/2" at half the spacing.

All at one grid spacing DX and particle spacing (4 per cell in 2D, 8 in 3D: the same spacing), CFL 0.3,
float32 (float32 and float64 agree to 3-4 digits in results/pareto.md; it halves the 3D cost). Errors:

- silhouette error = 1 - IoU of occupancy images (pixel PIXEL m, a pixel is occupied when a particle lies
  within 0.75 particle spacings), averaged over FRAMES frames; 3D runs are projected along z (the camera of
  shared/specs/silhouettes.md);
- mid-plane error: the same, using only the particles within one particle spacing of the block's mid-plane
  z = 0 (is the middle of the block in plane strain, whatever its ends do?).

The plane-strain modelling error of depth D is the block's silhouette error against the slab (both 3D at the
same dx, so the discretization is the same). It is compared with the grid error of the 2D model at this dx
(2D against 2D at dx/2): plane strain is adequate once the depth error falls below the grid error, i.e. when
the 2D answer's error is dominated by the grid rather than the missing depth.

Usage: python -m experiments plane_strain [--quick] [--scene drop|hanging_plate]. Writes
experiments/results/plane_strain[_quick].png/.md (with --scene: plane_strain_<scene>[_quick]).
"""
from __future__ import annotations

import copy
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C

NAME = "plane_strain"
SCENES = Path(__file__).resolve().parent / "scenes"
FOAM = dict(mu=200.0, sigma_y=40.0, eta=10.0, m=0.5)   # the CLI default foam (Pa, Pa, Pa s^m, -)
DURATION = {"drop": 0.5, "hanging_plate": 1.0}          # simulated time, s (as in pareto.py)
FRAMES = 10
DX = 0.0075            # grid spacing, m: the 3D fitter grid (32 cells across 0.24 m), affordable in 3D here
DX_QUICK = 0.015       # quick runs, m
RATIOS = {"drop": (0.5, 1.0, 2.0, 4.0), "hanging_plate": (0.5, 1.0, 2.0, 4.0)}  # block depth / foam width
RATIOS_QUICK = (0.5, 1.0, 2.0)
SLAB_CELLS = 4         # depth of the slip-wall slab, cells (>= 2 so that the stencil sees interior nodes)
MARGIN = {"drop": 0.06, "hanging_plate": 0.05}  # free space in front of and behind a block, m (the spread seen)
PIXEL = 0.002          # silhouette pixel, m
SPREAD = 0.75          # occupancy radius in particle spacings
CFL = 0.3              # the fitter's CFL number (MODEL_CHOICE.md section 2)
PPC = {2: 4, 3: 8}     # the defaults: the same particle spacing dx/2 in 2D and 3D


def _spec2(name):
    return json.loads((SCENES / f"{name}_2d.json").read_text())


def _extrude(spec2: dict, z_lo: float, z_hi: float, zd_lo: float, zd_hi: float, plate_half_z: float) -> dict:
    """The 3D scene of a 2D spec: material from z_lo to z_hi (m), domain from zd_lo to zd_hi (m).

    The 2D shape's cross-section is kept: a box stays a box; an ellipse becomes the bounding box here and
    is cut to the elliptic cylinder by `_elliptic_cylinder` (the scene format has no cylinder)."""
    s = copy.deepcopy(spec2)
    s["name"] = s["name"].replace("_2d", "_3d_extruded")
    s["dim"] = 3
    s["gravity"] = list(s["gravity"]) + [0.0]
    s["domain"] = {"min": list(s["domain"]["min"]) + [zd_lo], "max": list(s["domain"]["max"]) + [zd_hi]}
    shape = s["initial_shape"]
    if shape["type"] == "box":
        s["initial_shape"] = {"type": "box", "min": list(shape["min"]) + [z_lo], "max": list(shape["max"]) + [z_hi]}
    else:
        c, r = np.asarray(shape["center"]), np.asarray(shape["radii"])
        s["initial_shape"] = {"type": "box", "min": list(c - r) + [z_lo], "max": list(c + r) + [z_hi]}
    if "initial_velocity" in s:
        s["initial_velocity"] = list(s["initial_velocity"]) + [0.0]
    if "plate" in s:
        p = s["plate"]
        p["center"] = list(p["center"]) + [0.5 * (zd_lo + zd_hi)]
        p["half_size"] = list(p["half_size"]) + [plate_half_z]
        if p.get("motion", {}).get("type") == "sinusoid":
            p["motion"]["axis"] = list(p["motion"]["axis"]) + [0.0]
    return s


def _state0(spec2: dict, scene, dx: float, dtype):
    """Initial particles: the scene's sampling, cut to the 2D cross-section (ellipse) when it is one."""
    ppc = PPC[scene.dim]
    pts, vol = jaxfoam.sample_particles(scene, dx, ppc)
    shape = spec2["initial_shape"]
    if shape["type"] == "ellipse" and scene.dim == 3:
        c, r = np.asarray(shape["center"]), np.asarray(shape["radii"])
        keep = np.sum(((pts[:, :2] - c) / r) ** 2, axis=1) <= 1.0
        pts = pts[keep]
    n = len(pts)
    return jaxfoam.make_state(pts, np.full(n, vol), np.full(n, vol * scene.density),
                              v=np.asarray(scene.initial_velocity), dtype=dtype)


def _observe(s, p):
    return dict(x=s.x, active=s.active)


def run(spec: dict, spec2: dict, dx: float, duration: float):
    """One rollout: dict(x (T, N, d) m, active, seconds, particles, substeps)."""
    dtype = jnp.float32
    scene = jaxfoam.load_scene(spec, dtype=dtype)
    params = jaxfoam.Params(kappa=scene.kappa, rho=scene.density, **FOAM)
    times = np.linspace(duration / FRAMES, duration, FRAMES)
    state0 = _state0(spec2, scene, dx, dtype)
    sim = jaxfoam.Simulator(scene, times, params, dx, dtype=dtype, cfl=CFL, state0=state0)
    sim.rollout(params, observe=_observe, adjoint=jaxfoam.Autodiff())  # compile (excluded from the time)
    with C.Timer() as tm:
        _, fr, health = sim.rollout(params, observe=_observe, adjoint=jaxfoam.Autodiff())
        fr = jax.block_until_ready(fr)
    sim.check(fr, health)
    fr = jax.device_get(fr)
    return dict(x=np.asarray(fr["x"], np.float64), active=np.asarray(fr["active"]), seconds=tm.seconds,
                particles=int(np.asarray(state0.active).sum()), substeps=sim.total_substeps,
                spacing=dx / PPC[scene.dim] ** (1.0 / scene.dim))


def images(r, lo, hi, mid: bool = False):
    out = []
    for k in range(FRAMES):
        a = r["active"][k]
        if mid:
            a = a & (np.abs(r["x"][k][:, 2]) <= r["spacing"])
        out.append(C.rasterize(r["x"][k][:, :2], a, lo, hi, PIXEL, SPREAD * r["spacing"]))
    return out


def error(imgs, ref_imgs) -> float:
    return 1.0 - float(np.mean([C.iou(a, b) for a, b in zip(imgs, ref_imgs)]))


def study(name: str, quick: bool):
    spec2 = _spec2(name)
    dx = DX_QUICK if quick else DX
    duration = DURATION[name] * (0.5 if quick else 1.0)
    lo, hi = np.asarray(spec2["domain"]["min"]), np.asarray(spec2["domain"]["max"])
    shape = spec2["initial_shape"]
    width = (shape["max"][0] - shape["min"][0]) if shape["type"] == "box" else 2 * shape["radii"][0]
    plate_margin = 0.02  # the hanging plate's board overhangs the block front and back by this, m
    rows, runs = [], {}

    def record(label, r, kind, depth):
        runs[label] = r
        rows.append(dict(label=label, kind=kind, depth=depth, particles=r["particles"], substeps=r["substeps"],
                         seconds=r["seconds"]))
        print(f"  {name} {label}: {r['particles']} particles, {r['substeps']} substeps, {r['seconds']:.1f} s",
              flush=True)

    record("2D", run(spec2, spec2, dx, duration), "2d", None)
    record("2D, dx/2", run(spec2, spec2, dx / 2, duration), "2d", None)
    slab_d = SLAB_CELLS * dx
    slab = _extrude(spec2, -slab_d / 2, slab_d / 2, -slab_d / 2, slab_d / 2, slab_d / 2 + plate_margin)
    record("3D slab, slip walls", run(slab, spec2, dx, duration), "slab", slab_d)
    for ratio in (RATIOS_QUICK if quick else RATIOS[name]):
        d = ratio * width
        half = d / 2 + MARGIN[name]
        half = dx * np.ceil(half / dx)  # whole cells
        spec = _extrude(spec2, -d / 2, d / 2, -half, half, d / 2 + plate_margin)
        record(f"3D block D/W = {ratio:g}", run(spec, spec2, dx, duration), "block", d)

    img = {k: images(r, lo, hi) for k, r in runs.items()}
    mid = {k: images(r, lo, hi, mid=True) for k, r in runs.items() if k.startswith("3D")}
    grid_error = error(img["2D"], img["2D, dx/2"])
    for row in rows:
        row["vs_slab"] = error(img[row["label"]], img["3D slab, slip walls"])
        row["vs_2d"] = error(img[row["label"]], img["2D"])
        row["mid_vs_slab"] = error(mid[row["label"]], mid["3D slab, slip walls"]) if row["label"] in mid else None
    return dict(rows=rows, grid_error=grid_error, dx=dx, width=width, duration=duration,
                slab_vs_2d=error(img["3D slab, slip walls"], img["2D"]))


def adequate_ratio(res):
    """Smallest measured D/W from which every deeper block's depth error is below the 2D grid error."""
    blocks = [r for r in res["rows"] if r["kind"] == "block"]
    ok = None
    for r in reversed(blocks):
        if r["vs_slab"] <= res["grid_error"]:
            ok = r["depth"] / res["width"]
        else:
            break
    return ok


def main(argv=None):
    import argparse
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced version (coarse grid, shorter runs)")
    parser.add_argument("--scene", action="append", choices=tuple(DURATION), help="only this scene (repeatable)")
    args = parser.parse_args(argv)
    scenes = tuple(args.scene) if args.scene else tuple(DURATION)
    name_out = NAME if scenes == tuple(DURATION) else "_".join([NAME, *scenes])
    results = {name: study(name, args.quick) for name in scenes}

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(results), figsize=(6.0 * len(results), 4.5), squeeze=False)
    for ax, (name, res) in zip(axes[0], results.items()):
        blocks = [r for r in res["rows"] if r["kind"] == "block"]
        ratios = [r["depth"] / res["width"] for r in blocks]
        ax.semilogx(ratios, [r["vs_slab"] for r in blocks], "o-", label="block vs 3D slab (depth error)")
        ax.semilogx(ratios, [r["mid_vs_slab"] for r in blocks], "s--", label="block mid-plane vs slab mid-plane")
        ax.semilogx(ratios, [r["vs_2d"] for r in blocks], "^:", label="block vs 2D (depth + dimension)")
        ax.axhline(res["grid_error"], color="k", lw=0.8, label="2D grid error (dx vs dx/2)")
        ax.axhline(res["slab_vs_2d"], color="C3", lw=0.8, ls="--", label="3D slab vs 2D")
        ax.set_xlabel("block depth / foam width D/W")
        ax.set_ylabel("silhouette error 1 - IoU (mean over frames)")
        ax.set_title(f"{name}: dx {res['dx'] * 1e3:g} mm, W {res['width'] * 100:g} cm", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    C.save_fig(fig, name_out, args.quick)

    parts = [f"Foam {FOAM} (kappa, rho from the scene), float32, CFL {CFL}, {FRAMES} frames; particle spacing dx/2 "
             f"(4 per cell in 2D, 8 in 3D); slab {SLAB_CELLS} cells deep between slip walls; blocks with "
             f"{MARGIN} m of free space front and back.\n\n"]
    for name, res in results.items():
        ok = adequate_ratio(res)
        parts.append(f"## {name}\n\ndx {res['dx']} m, foam width W = {res['width']} m, {res['duration']} s simulated. "
                     f"Grid error of 2D at this dx (2D vs 2D at dx/2): **{res['grid_error']:.4f}**; 3D slab vs 2D: "
                     f"{res['slab_vs_2d']:.4f}. Plane strain adequate (depth error below the grid error for this "
                     f"and every deeper block measured) from D/W = "
                     f"{'not reached' if ok is None else f'{ok:g}'}.\n\n")
        parts.append(C.md_table(
            ["run", "depth (m)", "particles", "substeps", "wall s", "vs 3D slab", "mid-plane vs slab", "vs 2D"],
            [[r["label"], "-" if r["depth"] is None else r["depth"], r["particles"], r["substeps"], r["seconds"],
              r["vs_slab"], "-" if r["mid_vs_slab"] is None else r["mid_vs_slab"], r["vs_2d"]]
             for r in res["rows"]]) + "\n")
    flags = "".join(f" --scene {n}" for n in scenes)
    C.write_md(name_out, args.quick, "2D plane strain against 3D blocks of finite depth", "".join(parts),
               command=None if name_out == NAME else NAME + flags)


if __name__ == "__main__":
    main()
