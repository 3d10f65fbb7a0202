"""Where a sticky plate and a sticky floor grip the foam: the no-slip walls of plane Couette flow.

A layer of foam (yield stress 0, Newtonian: m = 1, eta 2 Pa s; mu 2 kPa) lies between a sticky floor
(y = 0, on a node row) and a sticky plate whose face is at y = H + phase dx, moving sideways at U.
Its top centimetre is inside the plate, as in the hanging-plate scene. In steady flow the particles'
velocity is linear in y; the line's zero is the floor's effective wall and the height where it
reaches U is the plate's. Each is reported in cells from the boundary it models, for grid spacings
10, 5 and 2.5 mm and four phases of the face against the node rows. The plate acts on the grid nodes
inside it (jaxfoam's only plate contact), so its wall sits near the lowest node row inside the face,
which lies 0 to 1 cell inside it depending on the phase. The hanging-plate rows of the
reference-simulator comparison (`reference_bias.json`) are listed with the depth of that node row at
each dx, next to their loss at the truth.

Usage: python -m experiments plate_grip [--quick] [--report]   (quick: dx 5 mm only; report: rebuild the
page from the JSON record, no runs)
Writes experiments/results/plate_grip[_quick].md and .json (the Couette rows). SI units; walls in cells.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

import jaxfoam
from experiments import _common as C
from jaxfoam.guards import atomic_output

H = 0.04           # m, the layer's height between floor and plate face
U = 0.02           # m/s, plate speed
DURATION = 0.4     # s: 30 viscous times rho H^2 / eta, and 400 Maxwell times eta / mu
DXS = (0.01, 0.005, 0.0025)
PHASES = (0.0, 0.25, 0.5, 0.75)
GOAL = 0.25        # cells: the fidelity issue's target for the grip edge
MATERIAL = dict(mu=2000.0, kappa=3000.0, sigma_y=0.0, eta=2.0, m=1.0, rho=80.0)


def couette_scene(dx: float, phase: float) -> dict:
    face = H + phase * dx
    centre = [0.0, face + 0.02]
    return {"name": "couette", "kind": "hanging_plate", "dim": 2, "gravity": [0.0, 0.0], "density": 80.0,
            "kappa": 3000.0, "domain": {"min": [-0.2, 0.0], "max": [0.2, 0.12]},
            "floor": {"y": 0.0, "friction": "sticky"},
            "plate": {"center": centre, "half_size": [0.19, 0.02],
                      "motion": {"type": "samples", "times": [0.0, 10.0],
                                 "positions": [centre, [U * 10.0, centre[1]]]}},
            "initial_shape": {"type": "box", "min": [-0.15, 0.0], "max": [0.15, face + 0.01]}}


def walls(dx: float, phase: float) -> dict:
    """The floor's and the plate's effective no-slip walls, cells from the floor and from the face."""
    face = H + phase * dx
    scene = jaxfoam.load_scene(couette_scene(dx, phase))
    t0 = time.perf_counter()
    tr = jaxfoam.simulate(scene, jaxfoam.Params(**MATERIAL), np.array([DURATION]), dx)
    wall = time.perf_counter() - t0
    x = np.asarray(tr.frames["x"])[-1]
    v = np.asarray(tr.frames["v"])[-1]
    act = np.asarray(tr.frames["active"])[-1].astype(bool)
    # the middle of the layer, far from its ends and from both boundary layers of the stencil
    sel = act & (np.abs(x[:, 0] - U * DURATION) < 0.05) & (x[:, 1] > 0.25 * face) & (x[:, 1] < 0.75 * face)
    slope, icpt = np.polyfit(x[sel, 1], v[sel, 0], 1)
    return dict(dx=dx, phase=phase, floor=(-icpt / slope) / dx, plate=((U - icpt) / slope - face) / dx,
                row_depth=row_depth(scene_grid_origin(scene, dx), dx, face), wall=wall)


def scene_grid_origin(scene, dx: float) -> float:
    return float(jaxfoam.make_grid(scene, dx).origin[1])


def row_depth(origin_y: float, dx: float, face: float) -> float:
    """Cells between a plate's lower face and the lowest node row at or above it."""
    k = math.ceil((face - origin_y) / dx - 1e-9)
    return (origin_y + k * dx - face) / dx


def hanging_rows() -> list[list]:
    """The reference comparison's hanging-plate rows (grid floor contact) with their face's row depth."""
    path = C.RESULTS / "reference_bias.json"
    if not path.exists():
        return []
    from experiments.reference_bias import DATA
    from fitting import read_silhouettes
    out = []
    for r in json.loads(path.read_text())["rows"]:
        if not r["file"].startswith("hanging") or r["contact"] != "grid":
            continue
        data = read_silhouettes(DATA / r["file"])
        spec = json.loads(data.scene_json)
        face = spec["plate"]["center"][1] - spec["plate"]["half_size"][1]
        dx = json.loads(data.source)["fit_default_dx"] / r["refine"]  # the record's dx is rounded
        scene = jaxfoam.load_scene(spec)
        out.append([r["file"], f"{dx * 1e3:.2f}", f"{row_depth(scene_grid_origin(scene, dx), dx, face):.2f}",
                    f"{r['loss']:.4g}", f"{r['iou_min']:.3f}", f"{r['boundary_mean'] * 1e3:.2f}"])
    return out


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    report = "--report" in argv
    args = C.parse_args(__doc__, [a for a in argv if a != "--report"])
    path = C.out_path("plate_grip", "json", args.quick)
    if report:
        rec = json.loads(path.read_text())
    else:
        rows = []
        for dx in ((0.005,) if args.quick else DXS):
            for ph in PHASES:
                r = walls(dx, ph)
                rows.append(r)
                print(f"dx {dx * 1e3:g} mm phase {ph}: floor wall {r['floor']:+.3f}, plate wall {r['plate']:+.3f} cells "
                      f"(node row {r['row_depth']:.2f} cells inside), {r['wall']:.0f} s", flush=True)
        rec = dict(rows=rows, stamp=C.machine_line())
        with atomic_output(path) as tmp:
            Path(tmp).write_text(json.dumps(rec, indent=1))
    rows = rec["rows"]
    head = ["dx (mm)", "face phase (cells)", "lowest node row inside the face (cells)", "floor wall (cells above floor)",
            "plate wall (cells below face; < 0: inside)", "rollout (s)"]
    table = [[f"{r['dx'] * 1e3:g}", r["phase"], f"{r['row_depth']:.2f}", f"{r['floor']:+.3f}", f"{-r['plate']:+.3f}",
              f"{r['wall']:.0f}"] for r in rows]
    plate = np.array([r["plate"] for r in rows])
    floor = np.array([r["floor"] for r in rows])
    within = int(np.sum(np.abs(plate) <= GOAL))
    text = (f"Plane Couette flow, layer {H * 1e3:g} mm, plate at {U * 1e3:g} mm/s, {DURATION} s, float64, 4 particles "
            f"per cell. The effective walls are where the particles' steady velocity line reaches 0 and U.\n\n"
            + C.md_table(head, table)
            + f"\n- Floor (on a node row): wall within {np.max(np.abs(floor)):.3f} cells of it in every run.\n"
            f"- Plate: wall from {-plate.max():+.2f} to {-plate.min():+.2f} cells below the face (negative: inside "
            f"it); within the {GOAL} cell goal in {within} of {len(rows)} runs. The wall follows the lowest node row "
            f"inside the face, {np.mean([r['plate'] - r['row_depth'] for r in rows]):+.2f} cells from it on average: "
            "the grip edge moves with the phase of the face against the grid.\n")
    hrows = hanging_rows()
    if hrows:
        text += ("\nThe hanging-plate files of the reference comparison (`reference_bias.md`, grid floor contact, "
                 "true parameters): the face's node row depth at each dx, and the loss at the truth.\n\n"
                 + C.md_table(["file", "dx (mm)", "lowest node row inside the face (cells)", "loss at truth",
                               "IoU min", "boundary mean (mm)"], hrows))
    C.write_md("plate_grip", args.quick, "Where sticky boundaries grip the foam: Couette walls", text,
               stamp=rec["stamp"])


if __name__ == "__main__":
    main()
