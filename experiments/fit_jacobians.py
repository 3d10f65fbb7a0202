"""Default fits with exact Jacobians at every Levenberg-Marquardt trial against Broyden-updated ones.

Each (file, broyden_steps) pair is one `fitting.calibrate(data, FitSettings(broyden_steps=K))` in a fresh
process (its compilation included), on files of the reference simulator's data; the residual-only and
(r, J) evaluations of the fit's own grid are counted and timed. Records: experiments/results/fit_jacobians/
<file>_k<K>.json (a pair already recorded is not rerun); the page compares each K with K = 0.
Usage: python -m experiments fit_jacobians [--quick] [--files a.h5,b.h5] [--steps 0,30] [--starts S]
       [--max-iter N] [--no-dx-check]   (settings other than the defaults are named in the record's name)
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from experiments._common import RESULTS, machine_line, md_table, write_md

DATA = Path(__file__).parent / "reference" / "data"
FILES = ("drop_2d_set0.h5", "hanging_plate_2d_set0.h5")
# The quick run: one start of 6 iterations at dx 1 cm, enough for trials to be rejected and J refreshed.
QUICK = dict(dx=0.01, starts=1, max_iter=6)


def _options(args) -> dict:
    """The FitSettings fields the command line sets besides broyden_steps."""
    opts = dict(QUICK) if args.quick else {}
    if args.starts is not None:
        opts["starts"] = args.starts
    if args.max_iter is not None:
        opts["max_iter"] = args.max_iter
    if args.no_dx_check:
        opts["dx_check"] = False
    return opts


def _suffix(opts: dict) -> str:
    """The record name's tail for settings other than the defaults ("" for the defaults)."""
    return "".join(f"_{key}{int(value)}" for key, value in sorted(opts.items()) if key != "dx")


def _one(path: str, k: int, out: str, opts: dict) -> None:
    """One fit in this process, its record written atomically to `out`."""
    import jax
    jax.config.update("jax_enable_x64", True)
    from fitting import FitSettings, build_problem, calibrate, read_silhouettes
    from jaxfoam.guards import atomic_output

    t0 = time.perf_counter()
    settings = FitSettings(broyden_steps=k, **opts).validate()
    data = read_silhouettes(path)
    problem = build_problem(data, settings)
    count = {"residual": [], "jacobian": []}  # seconds per call, the first one with its compilation
    residual, both = problem.residual, problem.residual_and_jacobian

    def timed(fn, key):
        def call(z):
            a = time.perf_counter()
            value = jax.block_until_ready(fn(z))
            count[key].append(time.perf_counter() - a)
            return value
        return call

    problem.residual, problem.residual_and_jacobian = timed(residual, "residual"), timed(both, "jacobian")
    res = calibrate(data, settings, problem=problem, progress=lambda m: print(m, flush=True))
    record = dict(file=os.path.basename(path), broyden_steps=k, options=opts, wall=time.perf_counter() - t0,
                  fit_wall=res.wall_time, params={n: float(res.params[n]) for n in res.fitted},
                  interval={n: [float(v) for v in res.interval[n]] for n in res.fitted},
                  identifiable={n: bool(res.identifiable[n]) for n in res.fitted}, loss=float(res.loss),
                  evaluations=count, best_run=int(res.best_run),
                  best_history=dict(loss=[float(v) for v in res.loss_history],
                                    time=[float(v) for v in res.time_history]),
                  runs=[dict(iterations=int(r["iterations"]), loss=float(r["loss"]), reason=r["reason"],
                             wall=float(r["wall_time"])) for r in res.runs],
                  machine=machine_line())
    with atomic_output(out) as tmp:
        Path(tmp).write_text(json.dumps(record, indent=1))


def _rel(a, b):
    return abs(a - b) / abs(b) if b else math.inf


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help=f"each fit with {QUICK} (records under _quick)")
    ap.add_argument("--files", default=",".join(FILES), help="files of experiments/reference/data, comma-separated")
    ap.add_argument("--steps", default="0,30", help="broyden_steps values, comma-separated; 0 is the baseline")
    ap.add_argument("--starts", type=int, default=None, help="starts per fit (default: the fitter's)")
    ap.add_argument("--max-iter", type=int, default=None, help="LM iterations per start (default: the fitter's)")
    ap.add_argument("--no-dx-check", action="store_true", help="skip the discretization check")
    ap.add_argument("--one", nargs=3, metavar=("FILE", "K", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    opts = _options(args)
    if args.one:
        _one(args.one[0], int(args.one[1]), args.one[2], opts)
        return
    steps = [int(v) for v in args.steps.split(",")]
    folder = RESULTS / ("fit_jacobians_quick" if args.quick else "fit_jacobians")
    folder.mkdir(parents=True, exist_ok=True)
    for name in args.files.split(","):
        for k in steps:
            out = folder / f"{Path(name).stem}_k{k}{_suffix(opts)}.json"
            if not out.exists():
                print(f"== {name}, broyden_steps {k}, {opts or 'defaults'}", flush=True)
                cmd = [sys.executable, "-m", "experiments", "fit_jacobians", "--one", str(DATA / name), str(k), str(out)]
                cmd += (["--quick"] if args.quick else []) + (["--starts", str(args.starts)] if args.starts else [])
                cmd += (["--max-iter", str(args.max_iter)] if args.max_iter is not None else [])
                subprocess.run(cmd + (["--no-dx-check"] if args.no_dx_check else []), check=True)
    # The page shows every record of the folder, each against K = 0 with the same settings (or, for a
    # K > 0 record whose settings were not run with K = 0, against K = 0 with the defaults).
    records = {}
    for path in sorted(folder.glob("*.json")):
        rec = json.loads(path.read_text())
        records[rec["file"], rec["broyden_steps"], _suffix(rec["options"])] = rec

    rows = []
    for (name, k, tail), rec in sorted(records.items(), key=lambda kv: (kv[0][0], kv[0][2], kv[0][1])):
        base = records.get((name, 0, tail)) or records.get((name, 0, _suffix(QUICK if args.quick else {})))
        ev = rec["evaluations"]
        med = {key: statistics.median(v[1:]) if len(v) > 1 else math.nan for key, v in ev.items()}
        moved = ends = same_time = "n/a"  # no K = 0 run of this file recorded here
        if base is not None:
            moved = f"{max(_rel(rec['params'][n], base['params'][n]) for n in rec['params']):.2g}"
            ends = f"{max(_rel(rec['interval'][n][i], base['interval'][n][i]) for n in rec['params'] for i in (0, 1)):.2g}"
        if base is not None and "best_history" in rec and "best_history" in base and k:
            # K = 0's best start at the moment this run's best start ended (iterations finished by then)
            t_end = rec["best_history"]["time"][-1]
            done = [v for v, t in zip(base["best_history"]["loss"], base["best_history"]["time"]) if t <= t_end]
            same_time = f"{min(done):.4g}" if done else "n/a"
        rows.append([name, k, ", ".join(f"{a}={b}" for a, b in rec["options"].items()) or "defaults",
                     "none" if base is None else "same settings" if _suffix(base["options"]) == tail else "defaults",
                     rec["wall"], rec["fit_wall"], sum(r["wall"] for r in rec["runs"]),
                     " / ".join(str(r["iterations"]) for r in rec["runs"]), len(ev["jacobian"]), len(ev["residual"]),
                     med["jacobian"], med["residual"], sum(ev["jacobian"]) + sum(ev["residual"]),
                     rec["loss"], same_time, moved, ends,
                     "n/a" if base is None else "same" if rec["identifiable"] == base["identifiable"] else "differs"])
    header = ["file", "broyden_steps", "settings", "against K = 0 with", "command wall (s)", "fit wall (s)", "starts (s)", "iterations per start",
              "(r, J) calls", "r calls", "s per (r, J)", "s per r", "calls (s)", "loss", "K = 0's best start by then", "params moved (rel, max)",
              "interval ends moved (rel, max)", "identifiable"]
    stamps = sorted({rec["machine"] for rec in records.values()})
    body = ("Fits (`FitSettings(broyden_steps=K)` with the settings named, everything else at its default) "
            "of the reference simulator's files, each in a fresh "
            "process. (r, J) and r calls are the fit grid's (the starts, the uncertainty; the discretization "
            "check's finer grid is not counted); s per call: the median after the first (compiling) call; calls (s): "
            "all of them; K = 0's best start by then: its lowest loss among the iterations it had finished when "
            "this run's best start ended (both best starts timed from their own start); moves are relative to "
            "K = 0. " + "; ".join(st.rstrip(".") for st in stamps) + ".\n\n" + md_table(header, rows) + "\n")
    write_md("fit_jacobians", args.quick, "Exact against Broyden-updated Jacobians in the default fit", body)


if __name__ == "__main__":
    main()
