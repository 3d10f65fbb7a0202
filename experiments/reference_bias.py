"""How well jaxfoam's grids can represent data made by the independent reference simulator.

For every 2D silhouette file of `experiments/reference/data/` (made at 4x finer dx than the fitter's
default, by code that shares nothing with jaxfoam), the true parameters in its /truth are put through
the fitter's own problem (`fitting.build_problem`, all four parameters fitted, every other setting at
its default) on three grids (the default dx, dx / sqrt(2), dx / 2) and with each floor contact model
(`"floor": {"contact": "grid" | "particle"}`). Per run it records the fitter's loss at the truth, the
silhouettes' IoU and mean boundary distance to the data (`fitting.silhouette_mismatch`), per frame
worst, and the rollout's wall time. The loss at the truth is the discretization's share of the misfit:
a fit on that grid can only do better than the truth by moving away from it.

With --friction (files with a Coulomb floor the foam lands on: the drops; default dx only): the floor's Coulomb coefficient fitted alone
(`fit_also=("friction",)`, the material held at the truth) for each contact model, so that the
discretization's share of the misfit is measured with the one scene parameter a user does not know
profiled out, and the grid and particle contacts are compared at their own best friction.

Usage: python -m experiments reference_bias [--quick] [--friction] [--report] [--only TEXT] [--contact C]
  (quick: the default dx only; report: rebuild the page from the committed JSON record, no runs;
  only / contact: rerun just the files whose name contains TEXT / that contact, replacing their rows)
Writes experiments/results/reference_bias[_quick].md and .json (the rows). SI units.
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
from fitting import (
    FitSettings,
    build_problem,
    calibrate,
    read_silhouettes,
    silhouette_mismatch,
)
from jaxfoam.guards import atomic_output

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


def record_path(quick: bool) -> Path:
    return C.out_path(NAME, "json", quick)


def friction_fit(data, contact: str) -> dict:
    """The floor's friction fitted alone (material at the truth) on the default grid with `contact`."""
    data = with_contact(data, contact)
    truth = {n: float(data.truth[n]) for n in ("mu", "sigma_y", "eta", "m")}
    settings = FitSettings(fixed=truth, fit_also=("friction",), starts=1, dx_check=False)
    problem = build_problem(data, settings)
    t0 = time.perf_counter()
    res = calibrate(data, settings, problem=problem)
    wall = time.perf_counter() - t0
    params = dict(res.params)
    iou, boundary = silhouette_mismatch(problem.render(params), problem.masks, problem.weights, problem.cfg.pixel_size)
    lo, hi = res.interval["friction"]
    return dict(file=None, contact=contact, dx=problem.dx, friction=float(params["friction"]), friction_lo=float(lo),
                friction_hi=float(hi), loss=float(res.loss), iou_min=float(np.min(iou)),
                boundary_mean=float(np.mean(boundary)), wall=wall)


def family(name: str) -> str:
    return name.split("_2d")[0]


def summary(rows: list[dict]) -> str:
    """Per scene family and contact: the mean boundary distance and loss at the truth on each grid, and
    how the contacts compare at the default dx (numbers from the rows)."""
    out = ["## Summary", ""]
    refines = sorted({r["refine"] for r in rows})
    for fam in sorted({family(r["file"]) for r in rows}):
        for contact in CONTACTS:
            sel = [r for r in rows if family(r["file"]) == fam and r["contact"] == contact]
            if not sel:
                continue
            b = [np.mean([r["boundary_mean"] for r in sel if r["refine"] == k]) * 1e3 for k in refines]
            iou = [np.mean([r["iou_min"] for r in sel if r["refine"] == k]) for k in refines]
            dxs = [np.mean([r["dx"] for r in sel if r["refine"] == k]) * 1e3 for k in refines]
            line = (f"- {fam}, {contact} contact: mean boundary distance " + ", ".join(f"{v:.2f}" for v in b)
                    + " mm and mean worst-frame IoU " + ", ".join(f"{v:.3f}" for v in iou) + " at dx "
                    + ", ".join(f"{v:.2f}" for v in dxs) + " mm")
            if len(b) > 1 and b[-1] > 0 and b[0] > 0:
                line += f" (observed order {math.log(b[0] / b[-1]) / math.log(refines[-1] / refines[0]):.2f} in dx)"
            out.append(line + ".")
    base = {(r["file"], r["contact"]): r for r in rows if r["refine"] == refines[0]}
    floor_files = sorted({f for f, _ in base if not f.startswith("hanging")})
    if floor_files:
        closer = [f for f in floor_files if base[(f, "particle")]["boundary_mean"] < base[(f, "grid")]["boundary_mean"]]
        lower = [f for f in floor_files if base[(f, "particle")]["loss"] < base[(f, "grid")]["loss"]]
        out.append(f"- Floor contact at the default dx, drop and squeeze files: particle contact's silhouettes are "
                   f"closer to the data (boundary distance) in {len(closer)} of {len(floor_files)}, its loss at the "
                   f"truth is lower in {len(lower)} of {len(floor_files)}.")
    return "\n".join(out) + "\n"


def friction_table(frows: list[dict], rows: list[dict]) -> str:
    base = {(r["file"], r["contact"]): r for r in rows if r["refine"] == 1.0}
    head = ["file", "contact", "dx (mm)", "friction fitted", "95% interval", "loss at truth (friction 0.5)",
            "loss, friction fitted", "IoU min", "boundary mean (mm)", "fit wall (s)"]
    table = [[r["file"], r["contact"], f"{r['dx'] * 1e3:.2f}", f"{r['friction']:.3g}",
              f"[{r['friction_lo']:.3g}, {r['friction_hi']:.3g}]",
              f"{base[(r['file'], r['contact'])]['loss']:.4g}" if (r["file"], r["contact"]) in base else "",
              f"{r['loss']:.4g}", f"{r['iou_min']:.3f}", f"{r['boundary_mean'] * 1e3:.2f}", f"{r['wall']:.0f}"]
             for r in frows]
    return ("\n## The floor's friction profiled out\n\nThe floor's Coulomb coefficient fitted alone (the data's is 0.5), "
            "the material held at the truth, on the default grid (one start, no discretization check).\n\n"
            + C.md_table(head, table))


def page(rec: dict, quick: bool) -> None:
    rows = rec["rows"]
    head = ["file", "contact", "dx (mm)", "particles", "loss at truth", "pixel", "distance", "chamfer", "IoU min", "boundary mean (mm)",
            "boundary max (mm)", "rollout (s)"]
    table = [[r["file"], r["contact"], f"{r['dx'] * 1e3:.2f}", r["particles"], f"{r['loss']:.4g}",
              f"{r['pixel']:.3g}", f"{r['distance']:.3g}", f"{r['chamfer']:.3g}", f"{r['iou_min']:.3f}", f"{r['boundary_mean'] * 1e3:.2f}", f"{r['boundary_max'] * 1e3:.2f}",
              f"{r['wall']:.1f}"] for r in rows]
    body = ("Every 2D file of experiments/reference/data (independent MPM at 4x finer dx), the fitter's problem "
            "with all four parameters fitted and every other setting at its default, evaluated at the file's "
            "/truth. Boundary: mean displacement between the silhouettes (area of the symmetric difference over "
            "the observed perimeter), per frame; its mean and worst over the frames.\n\n" + C.md_table(head, table)
            + "\n" + summary(rows))
    if rec.get("friction"):
        body += friction_table(rec["friction"], rows)
    C.write_md(NAME, quick, "jaxfoam's grids against the reference simulator's data, at the true parameters", body,
               stamp=rec.get("stamp"))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    quick = "--quick" in argv
    path = record_path(quick)
    if "--report" in argv:
        page(json.loads(path.read_text()), quick)
        return 0
    jax.config.update("jax_enable_x64", True)
    files = sorted(p for p in DATA.glob("*_2d_set*.h5"))
    rec = json.loads(path.read_text()) if path.exists() else {}
    only = argv[argv.index("--only") + 1] if "--only" in argv else ""
    contacts = (argv[argv.index("--contact") + 1],) if "--contact" in argv else CONTACTS
    files = [p for p in files if only in p.name]

    def merged(old: list, new: list) -> list:
        """old rows with those of the rerun (file, contact[, refine]) replaced, in the old order."""
        key = lambda r: (r["file"], r["contact"], r.get("refine"))
        fresh = {key(r): r for r in new}
        out = [fresh.pop(key(r), r) for r in old]
        return out + list(fresh.values())

    if "--friction" in argv:
        frows = []
        for p in files:
            data = read_silhouettes(p)
            floor = json.loads(data.scene_json).get("floor", {})
            if p.name.startswith("hanging") or floor.get("friction") in (None, "sticky"):
                continue  # the floor barely matters (hanging) or has no friction to fit (sticky)
            for contact in contacts:
                r = friction_fit(data, contact)
                r["file"] = p.name
                frows.append(r)
                print(f"{p.name} {contact}: friction {r['friction']:.3g}, loss {r['loss']:.4g}, IoU min "
                      f"{r['iou_min']:.3f}, {r['wall']:.0f} s", flush=True)
        rec["friction"] = merged(rec.get("friction", []), frows)
    else:
        refinements = REFINEMENTS[:1] if quick else REFINEMENTS
        rows = []
        for p in files:
            data = read_silhouettes(p)
            for contact in contacts:
                for refine in refinements:
                    r = at_truth(data, contact, refine)
                    rows.append(dict(file=p.name, contact=contact, refine=refine, **r))
                    print(f"{p.name} {contact} dx {r['dx'] * 1e3:.2f} mm: loss {r['loss']:.4g} (pixel {r['pixel']:.3g}, "
                          f"distance {r['distance']:.3g}, chamfer {r['chamfer']:.3g}), IoU min "
                          f"{r['iou_min']:.3f}, boundary max {r['boundary_max'] * 1e3:.2f} mm", flush=True)
        rec["rows"] = merged(rec.get("rows", []), rows)
        rec["stamp"] = C.machine_line()
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(rec, indent=1))
    page(rec, quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
