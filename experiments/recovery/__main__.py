"""Parameter recovery: fit synthetic silhouettes made at a 2x finer grid and compare with the truth.

Every case is saved as it finishes (its record in experiments/results/recovery_cases/<case>.json,
committed; its data and fit log in out/recovery/; a killed study resumes where it stopped), and the
table and chart are rebuilt from the finished cases (`--report` needs only the committed records).
Usage: python -m experiments.recovery [--quick] [--sets N] [--only TEXT] [--report]
                                      [--refit-check] [--shift-check] [--measured-check]
(--report: only rebuild table and chart; re-running skips finished fits and resumes a killed one from its log.
The checks are diagnostics of the discretization check, cached beside the records: --refit-check continues
the main table's and the default grid's LM fits on both grids, --shift-check evaluates the check's estimates on
shifted grids, --measured-check runs the check's measured move for fits recorded before the fitter had it, so
that the report shows every fit as the fitter reports it now.)
Writes experiments/results/recovery[_quick].md and .png. SI units.
"""
from __future__ import annotations

import argparse

from experiments.recovery.cases import (
    DEFAULT_GRID,
    FULL,
    N_SETS,
    QUICK,
    case_of,
    fitter_refit,
)
from experiments.recovery.checks import measured_check, refit_check, shift_check
from experiments.recovery.report import report
from experiments.recovery.runs import load_records, run_study
from fitting.settings import DEFAULT_DX_REFIT


def main(argv=None) -> None:
    """Run (or resume) the study, or a check, then rebuild the report; --report only rebuilds it."""
    ap = argparse.ArgumentParser(prog="python -m experiments.recovery", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one parameter set per scene, coarser fits, one start")
    ap.add_argument("--report", action="store_true", help="only rebuild the table and chart from finished cases")
    ap.add_argument("--only", default=None, help="run only jobs whose scene name contains this text")
    ap.add_argument("--refit-check", action="store_true",
                    help="refit the main table's LM fits on the discretization check's finer grid (cached), then report")
    ap.add_argument("--measured-check", type=int, nargs="?", const=0, default=None, metavar="N",
                    help="for every finished fit reported before the discretization check measured its move, run "
                         f"those LM iterations (alone: the fitter's, {DEFAULT_DX_REFIT[2]} in 2D and "
                         f"{DEFAULT_DX_REFIT[3]} in 3D; N: another budget, shown beside) on the check's grid (cached) "
                         "so the report shows it as the fitter reports it now, then report")
    ap.add_argument("--shift-check", action="store_true",
                    help="the discretization check's estimate on half- and quarter-cell shifted grids for the main table's LM fits (cached), then report")
    ap.add_argument("--sets", type=int, default=None,
                    help=f"parameter sets per scene (default 1 with --quick, {N_SETS} without)")
    args = ap.parse_args(argv)
    for wanted, label, check, cases in ((args.refit_check, "refit", refit_check, FULL + DEFAULT_GRID),
                                        (args.shift_check, "shift", shift_check, FULL)):
        if not wanted:
            continue
        for r in load_records(args.quick):
            if r["optimizer"] == "lm" and case_of(r) in (QUICK if args.quick else cases):
                print(f"== {label} check {r['case']}", flush=True)
                check(r)
        args.report = True
    if args.measured_check is not None:
        for r in load_records(args.quick):
            if "refit" not in (r["fit"]["settings"].get("dx_check") or {"refit": None}):
                n = args.measured_check or fitter_refit(r)
                print(f"== measured check ({n}) {r['case']} {r['optimizer']}", flush=True)
                measured_check(r, iterations=n)
        args.report = True
    if not args.report:
        run_study(args.quick, args.sets, args.only, after_each=lambda: report(args.quick, args.sets))
    report(args.quick, args.sets)


if __name__ == "__main__":
    main()
