"""Coarse-to-fine continuation and Richardson extrapolation of the optimum, on the reference simulator's data.

Each committed default fit of `reference_fits` (the fit grid dx, every fitter default) is continued
with Levenberg-Marquardt on a grid of spacing dx / sqrt(2) from its optimum (up to --iterations
accepted iterations, the fit's tolerances, log-file resume). Per file and parameter the table compares
four estimates with the truth:
  * fit: the default fit on dx;
  * continued: the continuation's end on dx / sqrt(2) (what a fit that finishes on the finer grid gives);
  * Richardson: the two extrapolated to dx -> 0 at first order in fitted (log) coordinates,
    z_0 = z_fine + (z_fine - z_coarse) r / (1 - r), r = 1 / sqrt(2);
  * the fine grid's loss at the truth over its continued loss (the "model can represent the data"
    ratio on that grid), and the statistical 95% interval at the continued point.

Usage: python -m experiments coarse_to_fine [--only TEXT] [--iterations K] [--report]
Writes experiments/results/coarse_to_fine.md and coarse_to_fine/<file>.json (one record per file; a
rerun skips finished files). SI units.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np

from experiments import _common as C
from fitting import FitSettings, build_problem, read_silhouettes
from fitting import optim
from fitting.check import fit_uncertainty
from fitting.design import TOLERANCE
from fitting.settings import FTOL, XTOL
from jaxfoam.guards import atomic_output

DATA = Path(__file__).resolve().parent / "reference" / "data"
FITS = C.RESULTS / "reference_fits"
NAME = "coarse_to_fine"
RECORDS = C.RESULTS / NAME
LOGS = Path(__file__).resolve().parents[1] / "out" / NAME
RATIO = 1.0 / math.sqrt(2.0)   # fine dx / fit dx: the discretization check's finer grid
ITERATIONS = 8                 # continuation's LM iterations: past the check's 4, where its moves had not settled


def richardson(z_coarse, z_fine, ratio: float = RATIO, order: float = 1.0):
    """Two grids' estimates (fitted coordinates) extrapolated to dx -> 0: theta(h) = theta_0 + C h^order."""
    z_coarse, z_fine = np.asarray(z_coarse, np.float64), np.asarray(z_fine, np.float64)
    rq = ratio ** order
    return z_fine + (z_fine - z_coarse) * rq / (1.0 - rq)


def continue_one(path: Path, fit: dict, iterations: int) -> dict:
    """Continue the default fit `fit` (a reference_fits record) of `path` on the finer grid: the record."""
    data = read_silhouettes(path)
    fine = build_problem(data, FitSettings(dx=fit["dx"] * RATIO, dx_check=False))
    tr = fine.transform
    settings = FitSettings()
    start = {}
    for n in tr.names:  # a fit that ended on a bound starts just inside it (the transform is open there)
        lo, hi = settings.bounds_of(n)
        start[n] = min(max(fit["params"][n], lo + 1e-9 * (hi - lo)), hi - 1e-9 * (hi - lo))
    z0 = np.asarray(tr.to_unconstrained(start), np.float64)
    LOGS.mkdir(parents=True, exist_ok=True)
    log = LOGS / f"{path.stem}.fitlog.h5"
    t0 = time.perf_counter()

    def said(info):
        print(f"  iter {info.iteration:>2} loss {info.loss:.6g} ({info.time:.0f} s)", flush=True)

    sol = optim.least_squares(fine.residual_and_jacobian, z0, optim.LevenbergMarquardt(), with_jac=True,
                              max_iterations=iterations, ftol=FTOL, xtol=XTOL, callback=said, log=log,
                              resume=log.exists())
    wall = time.perf_counter() - t0
    z1 = np.asarray(sol.x, np.float64)
    unc, _ = fit_uncertainty(fine, z1, sol.residual, sol.jacobian) if sol.jacobian is not None else (None, None)
    truth = {n: float(data.truth[n]) for n in tr.names}
    z_truth = tr.to_unconstrained(truth)
    zr = richardson(z0, z1)
    return dict(file=path.name, truth=truth, dx_fit=fit["dx"], dx_fine=float(fine.dx),
                fit=fit["params"], continued=fine.params_of(z1), richardson=fine.params_of(zr),
                interval_continued=None if unc is None else
                {n: [float(v) for v in unc.interval[i]] for i, n in enumerate(tr.names)},
                loss_start=float(sol.history.loss[0]), loss=float(sol.loss), loss_truth=float(fine.loss(z_truth)),
                loss_fit_grid=fit["loss"], loss_truth_fit_grid=fit["loss_truth"], iterations=int(sol.iterations),
                reason=sol.reason.value, wall=wall, date=time.strftime("%Y-%m-%d"))


def within(name: str, value: float, truth: float) -> bool:
    err = abs(value - truth) if name == "m" else abs(value / truth - 1.0)
    return err <= TOLERANCE[name]


def error_text(name: str, value: float, truth: float) -> str:
    return f"{value - truth:+.2f}" if name == "m" else f"{100 * (value / truth - 1):+.0f}%"


def report(records: list[dict]) -> str:
    head = ["file", "param", "truth", "fit (dx)", "error", "continued (dx/sqrt2)", "error", "95% interval (stat.)",
            "Richardson", "error"]
    rows = []
    counts = {k: {n: 0 for n in ("mu", "sigma_y", "eta", "m")} for k in ("fit", "continued", "richardson")}
    for r in records:
        for i, n in enumerate(r["truth"]):
            t = r["truth"][n]
            iv = r["interval_continued"][n] if r["interval_continued"] else [math.nan, math.nan]
            for k in counts:
                counts[k][n] += within(n, r[k][n], t)
            rows.append([r["file"] if i == 0 else "", n, f"{t:.4g}", f"{r['fit'][n]:.4g}", error_text(n, r["fit"][n], t),
                         f"{r['continued'][n]:.4g}", error_text(n, r["continued"][n], t),
                         f"[{iv[0]:.4g}, {iv[1]:.4g}]", f"{r['richardson'][n]:.4g}",
                         error_text(n, r["richardson"][n], t)])
    loss_rows = [[r["file"], f"{r['dx_fit'] * 1e3:.2f}", f"{r['loss_truth_fit_grid'] / r['loss_fit_grid']:.2f}",
                  f"{r['dx_fine'] * 1e3:.2f}", f"{r['loss_truth'] / r['loss']:.2f}", f"{r['loss_start']:.4g}",
                  f"{r['loss']:.4g}", str(r["iterations"]), r["reason"], f"{r['wall'] / 60:.1f}"] for r in records]
    n = len(records)
    tally = "; ".join(f"{k}: " + ", ".join(f"{p} {c}" for p, c in v.items()) for k, v in counts.items())
    return "\n".join([
        f"Files: {n}. Within tolerance (mu, sigma_y 10%, eta 25%, m 0.1), of {n}: {tally}.", "",
        C.md_table(head, rows), "",
        "## Loss at the truth over the fitted loss, per grid", "",
        C.md_table(["file", "fit dx (mm)", "ratio on dx", "fine dx (mm)", "ratio on dx/sqrt2",
                    "continuation start loss", "end loss", "iterations", "reason", "wall (min)"], loss_rows)])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="only the files whose name contains TEXT")
    ap.add_argument("--iterations", type=int, default=ITERATIONS, help="LM iterations on the finer grid")
    ap.add_argument("--report", action="store_true", help="only rebuild the page from the records")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    jax.config.update("jax_enable_x64", True)
    RECORDS.mkdir(parents=True, exist_ok=True)
    fits = sorted(FITS.glob("*_2d_*.json"))
    if args.only:
        fits = [p for p in fits if args.only in p.name]
    for fit_path in fits if not args.report else []:
        out = RECORDS / fit_path.name
        if out.exists():
            continue
        fit = json.loads(fit_path.read_text())
        print(f"continuing {fit['file']} on dx / sqrt(2)", flush=True)
        record = continue_one(DATA / fit["file"], fit, args.iterations)
        with atomic_output(out) as tmp:
            Path(tmp).write_text(json.dumps(record, indent=1) + "\n")
        print(f"  {record['continued']} ({record['wall'] / 60:.1f} min)", flush=True)
    records = [json.loads(p.read_text()) for p in sorted(RECORDS.glob("*.json"))]
    body = ("The default fits of `reference_fits.md` (reference simulator's data, fit grid dx) continued by "
            f"Levenberg-Marquardt on dx / sqrt(2) (up to {args.iterations} iterations) from their optimum, and "
            "the two grids' optima extrapolated to dx -> 0 at first order (Richardson, fitted coordinates).\n\n"
            + report(records))
    C.write_md(NAME, False, "Coarse-to-fine continuation and Richardson extrapolation of the optimum", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
