"""How well jaxfoam's grids can represent data made by the independent reference simulator.

For every 2D silhouette file of `experiments/reference/data/` (made at 4x finer dx than the fitter's
default, by code that shares nothing with jaxfoam), the true parameters in its /truth are put through
the fitter's own problem (`fitting.build_problem`, all four parameters fitted, every other setting at
its default) on three grids (the default dx, dx / sqrt(2), dx / 2) and with each floor contact model
(`"floor": {"contact": "grid" | "particle"}`). Per run it records the fitter's loss at the truth, the
silhouettes' IoU and mean boundary distance to the data (`fitting.silhouette_mismatch`), per frame
worst, and the rollout's wall time. The loss at the truth is the discretization's share of the misfit:
a fit on that grid can only do better than the truth by moving away from it.

Usage: python -m experiments reference_bias [--quick]   (quick: the default dx only)
Writes experiments/results/reference_bias[_quick].md. SI units.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np

from experiments import _common as C
from fitting import FitSettings, build_problem, read_silhouettes, silhouette_mismatch

DATA = Path(__file__).resolve().parent / "reference" / "data"
CONTACTS = ("grid", "particle")
REFINEMENTS = (1.0, math.sqrt(2.0), 2.0)  # default dx / dx
NAME = "reference_bias"


def with_contact(data, contact: str):
    """The data with its scene's floor contact model replaced (data without a floor are returned as is)."""
    spec = json.loads(data.scene_json)
    if "floor" not in spec:
        return data
    spec["floor"] = dict(spec["floor"], contact=contact)
    return dataclasses.replace(data, scene_json=json.dumps(spec))


def at_truth(data, contact: str, refine: float) -> dict:
    """The fitter's loss and silhouette mismatch at the data's true parameters on the grid default dx / refine."""
    data = with_contact(data, contact)
    default_dx = build_problem(data, FitSettings(starts=1, dx_check=False)).dx
    problem = build_problem(data, FitSettings(dx=default_dx / refine, starts=1, dx_check=False))
    truth = {n: float(data.truth[n]) for n in problem.transform.names}
    z = problem.transform.to_unconstrained(truth)
    t0 = time.perf_counter()
    r = np.asarray(problem.residual(z))
    wall = time.perf_counter() - t0
    H, W = problem.cfg.shape
    N = problem.sim.state0.x.shape[0]
    per = r.reshape(len(problem.observed), -1)
    parts = {k: 0.5 * float(np.sum(per[:, sl] ** 2)) for k, sl in
             (("pixel", slice(0, H * W)), ("distance", slice(H * W, H * W + N)), ("chamfer", slice(H * W + N, None)))}
    iou, boundary = silhouette_mismatch(problem.render(truth), problem.masks, problem.weights,
                                        problem.cfg.pixel_size)
    return dict(dx=problem.dx, particles=int(np.sum(np.asarray(problem.sim.state0.active))), loss=0.5 * float(r @ r),
                **parts,
                iou_min=float(np.min(iou)), boundary_max=float(np.max(boundary)),
                boundary_mean=float(np.mean(boundary)), wall=wall)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    quick = "--quick" in argv
    jax.config.update("jax_enable_x64", True)
    files = sorted(p for p in DATA.glob("*_2d_set*.h5"))
    refinements = REFINEMENTS[:1] if quick else REFINEMENTS
    rows = []
    for path in files:
        data = read_silhouettes(path)
        for contact in CONTACTS:
            for refine in refinements:
                r = at_truth(data, contact, refine)
                rows.append(dict(file=path.name, contact=contact, refine=refine, **r))
                print(f"{path.name} {contact} dx {r['dx'] * 1e3:.2f} mm: loss {r['loss']:.4g} (pixel {r['pixel']:.3g}, "
                      f"distance {r['distance']:.3g}, chamfer {r['chamfer']:.3g}), IoU min "
                      f"{r['iou_min']:.3f}, boundary max {r['boundary_max'] * 1e3:.2f} mm", flush=True)
    head = ["file", "contact", "dx (mm)", "particles", "loss at truth", "pixel", "distance", "chamfer", "IoU min", "boundary mean (mm)",
            "boundary max (mm)", "rollout (s)"]
    table = [[r["file"], r["contact"], f"{r['dx'] * 1e3:.2f}", r["particles"], f"{r['loss']:.4g}",
              f"{r['pixel']:.3g}", f"{r['distance']:.3g}", f"{r['chamfer']:.3g}", f"{r['iou_min']:.3f}", f"{r['boundary_mean'] * 1e3:.2f}", f"{r['boundary_max'] * 1e3:.2f}",
              f"{r['wall']:.1f}"] for r in rows]
    body = ("Every 2D file of experiments/reference/data (independent MPM at 4x finer dx), the fitter's problem "
            "with all four parameters fitted and every other setting at its default, evaluated at the file's "
            "/truth. Boundary: mean displacement between the silhouettes (area of the symmetric difference over "
            "the observed perimeter), per frame; its mean and worst over the frames.\n\n" + C.md_table(head, table))
    C.write_md(NAME, quick, "jaxfoam's grids against the reference simulator's data, at the true parameters", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
