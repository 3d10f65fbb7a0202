"""How much the grid's phase, not its spacing, moves the fit's misfit at the truth, and what averaging
over phases gives.

For the reference simulator's 2D drop, hanging-plate and squeeze files (experiments/reference/data), the fitter's
problem (every default, all four parameters) is evaluated at the file's /truth on the default grid with
its node lattice shifted down by 0, 1/4, 1/2 and 3/4 of a cell along y (the scene's domain extended
below by that much: the floor and the plate's face then lie at other heights against the node rows,
nothing else changes). Per phase: the loss at the truth, the worst-frame IoU and the mean boundary
distance (`fitting.silhouette_mismatch`). Then the silhouettes of the four phases averaged (their soft
occupancies, per pixel) and scored the same way: what a phase-averaged model would reach at 4x the
cost, next to one grid at dx / 2 (8x the cost in 2D; `reference_bias.md`).

With --refine (the full record must exist; it is extended): for the files with a Coulomb floor, the
fitter's `floor_phase` 0 and 0.5 each on the default dx, dx / sqrt(2) and dx / 2: whether the phase that
helps on the default grid keeps helping as the grid is refined, and the silhouettes' observed order.

Usage: python -m experiments grid_phase [--quick] [--report] [--refine]   (quick: set 0 of each scene)
Writes experiments/results/grid_phase[_quick].md and .json. SI units.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np

from experiments import _common as C
from fitting import FitSettings, build_problem, read_silhouettes, silhouette_mismatch
from jaxfoam.guards import atomic_output

DATA = Path(__file__).resolve().parent / "reference" / "data"
PHASES = (0.0, 0.25, 0.5, 0.75)  # cells the node lattice moves down along y
NAME = "grid_phase"


def row_offset(origin: float, y: float, dx: float) -> float:
    """Cells from the highest node row at or below height y up to y (rows at origin + k dx)."""
    k = np.floor((y - origin) / dx + 1e-9)
    return float((y - origin) / dx - k)


def at_truth(data, settings: FitSettings):
    """The fitter's problem for `settings` at the data's /truth: (problem, soft silhouettes, row of loss,
    worst-frame IoU, mean boundary distance and rollout wall time)."""
    problem = build_problem(data, settings)
    truth = {n: float(data.truth[n]) for n in problem.transform.names}
    t0 = time.perf_counter()
    r = np.asarray(problem.residual(problem.transform.to_unconstrained(truth)))
    img = np.asarray(problem.render(truth))
    wall = time.perf_counter() - t0
    iou, boundary = silhouette_mismatch(img, problem.masks, problem.weights, problem.cfg.pixel_size)
    return problem, img, dict(loss=0.5 * float(r @ r), iou_min=float(np.min(iou)),
                              boundary_mean=float(np.mean(boundary)), wall=wall)


def evaluate(path: Path) -> dict:
    data = read_silhouettes(path)
    dx = build_problem(data, FitSettings(starts=1, dx_check=False)).dx
    spec = json.loads(data.scene_json)
    rows, renders, masks = [], [], None
    for ph in PHASES:
        # the lattice moved down by ph cells: the floor (at the domain's lower bound) ph cells above a row
        problem, img, row = at_truth(data, FitSettings(dx=dx, floor_phase=ph, starts=1, dx_check=False))
        renders.append(img)
        masks = (problem.masks, problem.weights, problem.cfg.pixel_size)
        origin = float(problem.sim.model.grid.origin[1])
        floor = spec.get("floor", {}).get("y")
        face = spec["plate"]["center"][1] - spec["plate"]["half_size"][1] if "plate" in spec else None
        rows.append(dict(phase=ph, **row,
                         floor_above_row=None if floor is None else row_offset(origin, floor, dx),
                         face_below_row=None if face is None else (1.0 - row_offset(origin, face, dx)) % 1.0))
        print(f"{path.name} phase {ph}: loss {row['loss']:.4g}, IoU min {row['iou_min']:.3f}, "
              f"boundary {row['boundary_mean'] * 1e3:.2f} mm, {row['wall']:.0f} s", flush=True)
    iou, boundary = silhouette_mismatch(np.mean(renders, axis=0), *masks)
    return dict(file=path.name, dx=dx, phases=rows, averaged=dict(iou_min=float(np.min(iou)),
                                                                    boundary_mean=float(np.mean(boundary))))


REFINE_PHASES = (0.0, 0.5)  # the fitter's default and the half-cell phase of `jaxfoam fit --floor-phase`
REFINEMENTS = (1.0, math.sqrt(2.0), 2.0)  # default dx / dx


def refined(path: Path) -> dict:
    """Loss and mismatch at the truth for each of REFINE_PHASES on each of REFINEMENTS's grids."""
    data = read_silhouettes(path)
    dx0 = build_problem(data, FitSettings(starts=1, dx_check=False)).dx
    rows = []
    for ph in REFINE_PHASES:
        for k in REFINEMENTS:
            problem, _, row = at_truth(data, FitSettings(dx=dx0 / k, floor_phase=ph, starts=1, dx_check=False))
            rows.append(dict(floor_phase=ph, refine=k, dx=problem.dx, **row))
            print(f"{path.name} floor_phase {ph} dx {problem.dx * 1e3:.2f} mm: loss {row['loss']:.4g}, "
                  f"boundary {row['boundary_mean'] * 1e3:.2f} mm, {row['wall']:.0f} s", flush=True)
    return dict(file=path.name, rows=rows)


def refined_section(files: list[dict]) -> str:
    head = ["file", "floor phase (cells)", "dx (mm)", "loss at truth", "IoU min", "boundary mean (mm)", "rollout (s)"]
    table = [[f["file"], f"{r['floor_phase']:g}", f"{r['dx'] * 1e3:.2f}", f"{r['loss']:.4g}", f"{r['iou_min']:.3f}",
              f"{r['boundary_mean'] * 1e3:.2f}", f"{r['wall']:.0f}"] for f in files for r in f["rows"]]
    lines = []
    for fam in sorted({f["file"].split("_2d")[0] for f in files}):
        sel = [f for f in files if f["file"].startswith(fam)]
        for ph in REFINE_PHASES:
            b = [np.mean([r["boundary_mean"] for f in sel for r in f["rows"] if r["floor_phase"] == ph
                          and r["refine"] == k]) * 1e3 for k in REFINEMENTS]
            order = math.log(b[0] / b[-1]) / math.log(REFINEMENTS[-1]) if b[-1] > 0 else float("nan")
            lines.append(f"- {fam}, floor phase {ph:g}: mean boundary distance " + ", ".join(f"{v:.2f}" for v in b)
                         + f" mm at the three grids (observed order {order:.2f} in dx).")
        wins = sum(all(r0["loss"] > r5["loss"] for r0, r5 in zip(
            [r for r in f["rows"] if r["floor_phase"] == 0.0], [r for r in f["rows"] if r["floor_phase"] == 0.5]))
            for f in sel)
        lines.append(f"- {fam}: floor phase 0.5 has the lower loss at the truth on all three grids in {wins} of "
                     f"{len(sel)} files.")
    return ("\n## The floor's phase as the grid is refined\n\nFiles with a Coulomb floor; the fitter's problem "
            "(`FitSettings(floor_phase=...)`, every other setting default) at the truth on the default dx, "
            "dx / sqrt(2) and dx / 2.\n\n" + C.md_table(head, table) + "\n" + "\n".join(lines) + "\n")


def page(rec: dict, quick: bool) -> None:
    head = ["file", "dx (mm)", "lattice shift (cells)", "floor above its node row (cells)",
            "plate face below its node row (cells)", "loss at truth", "IoU min", "boundary mean (mm)", "rollout (s)"]
    table, summary = [], []
    for f in rec["files"]:
        for r in f["phases"]:
            table.append([f["file"], f"{f['dx'] * 1e3:.2f}", r["phase"],
                          "" if r["floor_above_row"] is None else f"{r['floor_above_row']:.2f}",
                          "" if r["face_below_row"] is None else f"{r['face_below_row']:.2f}",
                          f"{r['loss']:.4g}", f"{r['iou_min']:.3f}", f"{r['boundary_mean'] * 1e3:.2f}", f"{r['wall']:.0f}"])
        losses = [r["loss"] for r in f["phases"]]
        b = [r["boundary_mean"] * 1e3 for r in f["phases"]]
        a = f["averaged"]
        table.append([f["file"], f"{f['dx'] * 1e3:.2f}", "mean of the 4", "", "", "", f"{a['iou_min']:.3f}",
                      f"{a['boundary_mean'] * 1e3:.2f}", ""])
        summary.append(f"- {f['file']}: loss at the truth {min(losses):.3g} to {max(losses):.3g} over the phases "
                       f"({max(losses) / min(losses):.1f}x); boundary distance {min(b):.2f}-{max(b):.2f} mm, "
                       f"{a['boundary_mean'] * 1e3:.2f} mm for the phase-averaged silhouettes.")
    body = ("The fitter's problem at each file's /truth on the default grid, its node lattice shifted along y "
            "(the scene's domain extended below). Last row per file: the four phases' soft silhouettes averaged.\n\n"
            + C.md_table(head, table) + "\n" + "\n".join(summary) + "\n")
    if rec.get("refined"):
        body += refined_section(rec["refined"])
    C.write_md(NAME, quick, "The grid's phase against its spacing, at the true parameters", body, stamp=rec["stamp"])


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    quick = "--quick" in argv
    path = C.out_path(NAME, "json", quick)
    if "--report" in argv:
        page(json.loads(path.read_text()), quick)
        return 0
    jax.config.update("jax_enable_x64", True)
    if "--refine" in argv:
        rec = json.loads(path.read_text())
        files = [p for p in sorted(DATA.glob("*_2d_set*.h5")) if p.name.startswith(("drop", "hanging"))]
        rec["refined"] = [refined(p) for p in files]
        with atomic_output(path) as tmp:
            Path(tmp).write_text(json.dumps(rec, indent=1))
        page(rec, quick)
        return 0
    pattern = "*_2d_set0.h5" if quick else "*_2d_set*.h5"
    files = [p for p in sorted(DATA.glob(pattern)) if p.name.startswith(("drop", "hanging", "squeeze"))]
    rec = dict(files=[evaluate(p) for p in files], stamp=C.machine_line())
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(rec, indent=1))
    page(rec, quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
