"""The default fit on the reference simulator's data: does `jaxfoam fit` recover what another code made?

Every silhouette file of `experiments/reference/data/` (an independent MPM at 2-4x finer dx, its own
contact, return map, sampling and rasterizer; the truth in /truth) is fitted with every fitter default
(`fitting.calibrate(data, FitSettings())`, the same as `jaxfoam fit data.h5 --out fit.json`). Per fit the
table gives the truth, the fit and its 95% interval, the error, whether the truth lies in the interval,
the identifiability verdict, the loss at the truth on the fit's grid over the fitted loss (the best
single number for "the model can represent the data": 1 or less when it can), and the wall time.

Each fit writes experiments/results/reference_fits/<file>.json, and its fit log to out/reference_fits/;
a rerun skips finished fits and resumes a killed one from its log. `--report` rebuilds the table from the records only.

Usage: python -m experiments reference_fits [--only TEXT] [--report]
Writes experiments/results/reference_fits.md. SI units.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax

from experiments import _common as C
from fitting import DEFAULT_BOUNDS, FIT_FIELDS, FitSettings, build_problem, calibrate, read_silhouettes

DATA = Path(__file__).resolve().parent / "reference" / "data"
NAME = "reference_fits"
RECORDS = C.RESULTS / NAME
LOGS = Path(__file__).resolve().parents[1] / "out" / NAME  # fit logs (tens of MB each): kept out of git
GOAL_RATIO = 1.2  # issue goal: loss at truth / fitted loss on the default grid


def fit_one(path: Path, settings: FitSettings) -> dict:
    """Fit one reference file with `settings` (resuming its log); the record of the result."""
    RECORDS.mkdir(parents=True, exist_ok=True)
    LOGS.mkdir(parents=True, exist_ok=True)
    log = LOGS / f"{path.stem}.fitlog.h5"
    data = read_silhouettes(path)
    t0 = time.perf_counter()
    res = calibrate(data, settings, log=log, resume=log.exists())
    wall = time.perf_counter() - t0
    problem = build_problem(data, settings)
    truth = {n: float(data.truth[n]) for n in problem.transform.names}
    loss_truth = problem.loss(problem.transform.to_unconstrained(truth))
    return dict(file=path.name, truth=truth, params={n: float(res.params[n]) for n in res.fitted},
                interval={n: list(map(float, res.interval[n])) for n in res.fitted},
                identifiable={n: bool(res.identifiable[n]) for n in res.fitted}, loss=float(res.loss),
                loss_truth=float(loss_truth), dx=float(problem.dx), wall=float(res.wall_time), run_wall=wall,
                reproduces=bool(res.reproduces_data), notes=list(res.notes),
                date=time.strftime("%Y-%m-%d"))


def write_record(path: Path, record: dict) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    os.replace(tmp, path)


def report(records: list[dict]) -> str:
    head = ["file", "dx (mm)", "param", "truth", "fit", "95% interval", "error", "truth inside",
            "identifiable", "loss truth / fit", "wall (min)"]
    rows, inside, ident_wrong, within, at_bounds = [], 0, 0, {"mu": [0, 0], "sigma_y": [0, 0]}, 0
    ratios = []
    for r in records:
        ratio = r["loss_truth"] / r["loss"] if r["loss"] > 0 else float("inf")
        ratios.append((r["file"], ratio))
        for i, n in enumerate(n for n in FIT_FIELDS if n in r["params"]):
            t, f = r["truth"][n], r["params"][n]
            lo, hi = r["interval"][n]
            ok = lo <= t <= hi
            inside += ok
            at_bounds += (lo, hi) == tuple(DEFAULT_BOUNDS[n])
            ident_wrong += r["identifiable"][n] and not ok
            if n in within and "_2d_" in r["file"]:
                within[n][0] += abs(f / t - 1) <= 0.1
                within[n][1] += 1
            rows.append([r["file"] if i == 0 else "", f"{r['dx'] * 1e3:.2f}" if i == 0 else "", n, f"{t:.4g}",
                         f"{f:.4g}", f"[{lo:.4g}, {hi:.4g}]", f"{100 * (f / t - 1):+.0f}%", "yes" if ok else "NO",
                         "yes" if r["identifiable"][n] else "no", f"{ratio:.2f}" if i == 0 else "",
                         f"{r['wall'] / 60:.1f}" if i == 0 else ""])
    n_cases = sum(len(r["params"]) for r in records)
    two_d = [x for f, x in ratios if "_2d_" in f]
    lines = [
        f"Fits: {len(records)} ({len(two_d)} in 2D). Truth inside the reported interval: {inside} of {n_cases} "
        f"parameter-cases (goal: at least 90%), {at_bounds} of them with the interval equal to the default bounds "
        f"(the fit then says nothing); reported identifiable with the truth outside: {ident_wrong} (goal: 0).",
        f"2D: mu within 10% in {within['mu'][0]} of {within['mu'][1]} (goal: 7 of 9), sigma_y in "
        f"{within['sigma_y'][0]} of {within['sigma_y'][1]} (goal: 6 of 9); loss at truth / fitted loss at most "
        f"{GOAL_RATIO} in {sum(x <= GOAL_RATIO for x in two_d)} of {len(two_d)} (goal: 8 of 9).", "",
        C.md_table(head, rows)]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="fit only the files whose name contains TEXT")
    ap.add_argument("--report", action="store_true", help="only rebuild the table from the records")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    jax.config.update("jax_enable_x64", True)
    files = sorted(DATA.glob("*.h5"))
    if args.only:
        files = [p for p in files if args.only in p.name]
    settings = FitSettings()
    for path in files if not args.report else []:
        out = RECORDS / f"{path.stem}.json"
        if out.exists():
            continue
        print(f"fitting {path.name} with the default settings", flush=True)
        record = fit_one(path, settings)
        write_record(out, record)
        print(f"  {record['params']} in {record['wall'] / 60:.1f} min; loss at truth / fit "
              f"{record['loss_truth'] / record['loss']:.2f}", flush=True)
    records = [json.loads(p.read_text()) for p in sorted(RECORDS.glob("*.json"))] if RECORDS.exists() else []
    body = ("The fitter's defaults (`jaxfoam fit data.h5 --out fit.json`) on every file of "
            "experiments/reference/data (the independent reference simulator's silhouettes; "
            "experiments/reference/data/README.md gives each file's truth and resolution).\n\n" + report(records))
    C.write_md(NAME, False, "Default fits on the reference simulator's data", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
