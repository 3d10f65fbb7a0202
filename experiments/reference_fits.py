"""The default fit on the reference simulator's data: does `jaxfoam fit` recover what another code made?

Every silhouette file of `experiments/reference/data/` (an independent MPM at 2-4x finer dx, its own
contact, return map, sampling and rasterizer; the truth in /truth) is fitted with every fitter default
(`fitting.calibrate(data, FitSettings())`, the same as `jaxfoam fit data.h5 --out fit.json`). Per fit the
table gives the truth, the fit and its 95% interval, the error, whether the truth lies in the interval,
the identifiability verdict, the loss at the truth on the fit's grid over the fitted loss (the best
single number for "the model can represent the data": 1 or less when it can), and the wall time.

Each fit writes experiments/results/reference_fits/<file>.json, and its fit log to out/reference_fits/;
a rerun skips finished fits and resumes a killed one from its log. `--report` rebuilds the table from the records only.
`--from-fit FILE=FIT.json` records a default fit of FILE made by `jaxfoam fit` elsewhere (on a GPU, say):
its settings are checked against the defaults and the loss at the truth is computed here.
`--floor-phase X` fits the files with a Coulomb floor with only that setting changed (`jaxfoam fit
--floor-phase X`), into experiments/results/reference_fits_floor_phase_X/; the page gives their table
below the defaults'. `--resolved-frames` fits every file with `resolved_frames` on, all else default (or also
`--floor-phase X`), into experiments/results/reference_fits_resolved_frames[_floor_phase_X]/, and the page gives
those tables too.

Usage: python -m experiments reference_fits [--only TEXT] [--report] [--from-fit FILE=FIT.json ...]
                                            [--floor-phase X] [--resolved-frames]
Writes experiments/results/reference_fits.md. SI units.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax

from experiments import _common as C
from fitting import DEFAULT_BOUNDS, FIT_FIELDS, FitSettings, build_problem, calibrate, read_silhouettes
from fitting.problem import fit_grid
from fitting.settings import DEFAULT_DX_REFIT, DEFAULT_MAX_ITER

DATA = Path(__file__).resolve().parent / "reference" / "data"
NAME = "reference_fits"
RECORDS = C.RESULTS / NAME
LOGS = Path(__file__).resolve().parents[1] / "out" / NAME  # fit logs (tens of MB each): kept out of git
GOAL_RATIO = 1.2  # issue goal: loss at truth / fitted loss on the default grid


def phase_records(phase: float) -> Path:
    """Where the fits with `--floor-phase phase` are recorded."""
    return C.RESULTS / f"{NAME}_floor_phase_{phase:g}"


def records_of(settings: FitSettings) -> Path:
    """Where the fits with `settings` (the defaults, `--floor-phase` or `--resolved-frames`) are recorded."""
    if settings.resolved_frames:
        return C.RESULTS / (f"{NAME}_resolved_frames" + ("" if settings.floor_phase is None
                                                          else f"_floor_phase_{settings.floor_phase:g}"))
    return RECORDS if settings.floor_phase is None else phase_records(settings.floor_phase)


def fit_one(path: Path, settings: FitSettings) -> dict:
    """Fit one reference file with `settings` (resuming its log); the record of the result."""
    logs = LOGS.with_name(records_of(settings).name)
    logs.mkdir(parents=True, exist_ok=True)
    log = logs / f"{path.stem}.fitlog.h5"
    data = read_silhouettes(path)
    t0 = time.perf_counter()
    # resolved-frames rounds keep their own logs beside `log` and resume each one that exists
    res = calibrate(data, settings, log=log, resume=log.exists() or settings.resolved_frames)
    wall = time.perf_counter() - t0
    window = res.settings["time_window"]
    problem = build_problem(data, dataclasses.replace(settings, resolved_frames=False,
                                                      time_window=None if window is None else tuple(window)))
    truth = {n: float(data.truth[n]) for n in problem.transform.names}
    loss_truth = problem.loss(problem.transform.to_unconstrained(truth))
    return dict(file=path.name, truth=truth, params={n: float(res.params[n]) for n in res.fitted},
                interval={n: list(map(float, res.interval[n])) for n in res.fitted},
                identifiable={n: bool(res.identifiable[n]) for n in res.fitted}, loss=float(res.loss),
                loss_truth=float(loss_truth), dx=float(problem.dx), floor_phase=problem.floor_phase,
                wall=float(res.wall_time), run_wall=wall,
                reproduces=bool(res.reproduces_data), notes=list(res.notes),
                frames_used=len(res.data["frames_used"]), frames=len(data.times) - 1,
                time_window=window, resolved=res.settings.get("resolved"),
                date=time.strftime("%Y-%m-%d"))


# Settings of a fit.json that must equal the defaults for it to count as a default fit (dx and ppc are
# compared with the resolved defaults of the file's problem).
_DEFAULT_FIELDS = ("optimizer", "fixed", "starts", "initial", "time_window", "time_budget", "seed", "level", "dtype",
                   "distance_weight", "chamfer_weight", "fit_also", "resample", "fracture")


def record_from_fit(path: Path, fit_json: Path) -> dict:
    """The record of a default fit of `path` made elsewhere (`jaxfoam fit path --out fit_json`); raises
    ValueError naming the first setting that is not the default. The loss at the truth is computed here."""
    fit = json.loads(fit_json.read_text())
    data = read_silhouettes(path)
    settings = FitSettings()
    problem = build_problem(data, settings)
    got, default = fit["settings"], dataclasses.asdict(settings.validate())
    dim = problem.scene.dim
    checks = [("dx", got["dx"], float(problem.dx)), ("ppc", got["ppc"], fit_grid(problem.scene, settings)[1]),
              ("max_iter", got["max_iter"], DEFAULT_MAX_ITER[settings.optimizer]),
              ("dx_refit", got["dx_refit"], DEFAULT_DX_REFIT[dim]),
              # fits written before floor_phase existed had the domain's rows, as the default has
              ("floor_phase", got.get("floor_phase", problem.floor_phase), problem.floor_phase)]
    checks += [(k, got[k], default[k]) for k in _DEFAULT_FIELDS]
    checks += [("bounds", got["bounds"], {n: list(DEFAULT_BOUNDS[n]) for n in problem.transform.names}),
               ("data.frames_used", len(fit["data"]["frames_used"]), len(data.times) - 1),
               ("data.scene_kind", fit["data"]["scene_kind"], problem.scene.kind)]
    for name, a, b in checks:
        same = (abs(a - b) <= 1e-12 * abs(b)) if isinstance(b, float) and a is not None else _plain(a) == _plain(b)
        if not same:
            raise ValueError(f"{fit_json}: settings.{name} = {a!r} is not the default fit's {b!r}; "
                             "only a default `jaxfoam fit` of the file is a reference fit")
    truth = {n: float(data.truth[n]) for n in problem.transform.names}
    loss_truth = problem.loss(problem.transform.to_unconstrained(truth))
    return dict(file=path.name, truth=truth, params={n: float(fit["params"][n]) for n in fit["fitted"]},
                interval={n: list(map(float, fit["interval"][n])) for n in fit["fitted"]},
                identifiable={n: bool(fit["identifiable"][n]) for n in fit["fitted"]}, loss=float(fit["loss"]),
                loss_truth=float(loss_truth), dx=float(problem.dx), wall=float(fit["wall_time"]),
                reproduces=bool(fit["reproduces_data"]), notes=list(fit["notes"]),
                made_from=str(fit_json), date=time.strftime("%Y-%m-%d"))


def _plain(v):
    """JSON-comparable form (tuples as lists)."""
    return json.loads(json.dumps(v))


def has_coulomb_floor(path: Path) -> bool:
    """Whether the file's scene has a floor with Coulomb friction and grid contact."""
    floor = json.loads(read_silhouettes(path).scene_json).get("floor", {})
    return bool(floor) and floor.get("friction", 0.0) != "sticky" and floor.get("contact", "grid") == "grid"


def compare(default: list[dict], other: list[dict], label: str) -> str:
    """Per file of `other`: each parameter's error with the defaults and with the other settings (`label`),
    the loss ratios and whether the truth lies inside each interval."""
    by_file = {r["file"]: r for r in default}
    head = ["file", "param", "truth", "error, default", f"error, {label}", f"truth inside (default / {label})",
            f"loss truth / fit (default / {label})"]
    rows = []
    for r in other:
        d = by_file.get(r["file"])
        if d is None:
            continue
        for i, n in enumerate(n for n in FIT_FIELDS if n in r["params"]):
            t = r["truth"][n]
            inside = ["yes" if x["interval"][n][0] <= t <= x["interval"][n][1] else "NO" for x in (d, r)]
            rows.append([r["file"] if i == 0 else "", n, f"{t:.4g}", f"{100 * (d['params'][n] / t - 1):+.0f}%",
                         f"{100 * (r['params'][n] / t - 1):+.0f}%", " / ".join(inside),
                         f"{d['loss_truth'] / d['loss']:.2f} / {r['loss_truth'] / r['loss']:.2f}" if i == 0 else ""])
    return C.md_table(head, rows)


def windows(default: list[dict], other: list[dict]) -> str:
    """Per file of `other` (resolved-frames fits): the frames fitted, each round's frames kept, the wall times."""
    by_file = {r["file"]: r for r in default}
    head = ["file", "frames fitted", "window (s)", "frames kept per round", "settled", "wall (min), default / resolved"]
    rows = []
    for r in other:
        res, d = r.get("resolved") or {}, by_file.get(r["file"])
        window = r.get("time_window")
        rows.append([r["file"], f"{r['frames_used']} of {r['frames']}",
                     "all" if window is None else f"{window[0]:.3g}-{window[1]:.3g}",
                     " -> ".join(str(x["resolved"]) for x in res.get("rounds", [])),
                     "yes" if res.get("settled") else "no",
                     f"{d['wall'] / 60:.1f} / {r['wall'] / 60:.1f}" if d else f"- / {r['wall'] / 60:.1f}"])
    return C.md_table(head, rows)


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
    elsewhere = [f"{r['file']} ({r['made_from']})" for r in records if r.get("made_from")]
    if elsewhere:
        lines += ["", "Fits made by `jaxfoam fit` on another machine and recorded with `--from-fit` (their wall "
                  "times are that machine's; the loss at the truth was computed here): " + ", ".join(elsewhere) + "."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="fit only the files whose name contains TEXT")
    ap.add_argument("--report", action="store_true", help="only rebuild the table from the records")
    ap.add_argument("--from-fit", nargs="+", default=[], metavar="FILE=FIT.json",
                    help="record default fits made elsewhere: FILE a name in experiments/reference/data")
    ap.add_argument("--floor-phase", type=float, default=None, metavar="X",
                    help="fit the files with a Coulomb floor with floor_phase X (cells), all else default")
    ap.add_argument("--resolved-frames", action="store_true",
                    help="fit with resolved_frames on (`jaxfoam fit --resolved-frames`), all else default")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    jax.config.update("jax_enable_x64", True)
    for item in args.from_fit:
        name, sep, fit_path = item.partition("=")
        if not sep or not (DATA / name).exists():
            raise SystemExit(f"--from-fit {item!r}: expected FILE=FIT.json with FILE one of "
                             f"{sorted(p.name for p in DATA.glob('*.h5'))}")
        RECORDS.mkdir(parents=True, exist_ok=True)
        write_record(RECORDS / f"{Path(name).stem}.json", record_from_fit(DATA / name, Path(fit_path)))
        print(f"recorded {name} from {fit_path}", flush=True)
    if args.from_fit:
        args.report = True
    files = sorted(DATA.glob("*.h5"))
    if args.only:
        files = [p for p in files if args.only in p.name]
    settings = FitSettings()
    if args.floor_phase is not None:
        settings = FitSettings(floor_phase=args.floor_phase).validate()
        files = [p for p in files if has_coulomb_floor(p)]
    if args.resolved_frames:
        settings = dataclasses.replace(settings, resolved_frames=True).validate()
    where = records_of(settings)
    for path in files if not args.report else []:
        out = where / f"{path.stem}.json"
        if out.exists():
            continue
        where.mkdir(parents=True, exist_ok=True)
        print(f"fitting {path.name} with the default settings" + ("" if settings.floor_phase is None else
              f" but floor_phase {settings.floor_phase:g}") + (" but resolved_frames" if settings.resolved_frames
                                                               else ""), flush=True)
        record = fit_one(path, settings)
        write_record(out, record)
        print(f"  {record['params']} in {record['wall'] / 60:.1f} min; loss at truth / fit "
              f"{record['loss_truth'] / record['loss']:.2f}", flush=True)
    records = [json.loads(p.read_text()) for p in sorted(RECORDS.glob("*.json"))] if RECORDS.exists() else []
    body = ("The fitter's defaults (`jaxfoam fit data.h5 --out fit.json`) on every file of "
            "experiments/reference/data (the independent reference simulator's silhouettes; "
            "experiments/reference/data/README.md gives each file's truth and resolution).\n\n" + report(records))
    for folder in sorted(C.RESULTS.glob(f"{NAME}_floor_phase_*")):
        alt = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
        if alt:
            phase = alt[0]["floor_phase"]
            body += (f"\n\n## The files with a Coulomb floor, `--floor-phase {phase:g}`\n\nThe same fits with the fit "
                     f"grid's node rows placed so that the floor lies {phase:g} cells above the row below it "
                     f"(`jaxfoam fit --floor-phase {phase:g}`), every other setting default; records in "
                     f"experiments/results/{folder.name}/.\n\n" + compare(records, alt, f"floor phase {phase:g}") + "\n\n" + report(alt))
    for folder in sorted(C.RESULTS.glob(f"{NAME}_resolved_frames*")):
        alt = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
        if not alt:
            continue
        phase = alt[0].get("floor_phase")
        flags = "--resolved-frames" + ("" if phase is None else f" --floor-phase {phase:g}")
        body += (f"\n\n## Resolved frames, `{flags}`\n\nThe same fits with `resolved_frames` on (the frames "
                 "before the first one whose silhouette moves more than a particle spacing between dx and "
                 "dx / sqrt(2), chosen in rounds; docs/calibrate.md)"
                 + ("" if phase is None else f" and the floor {phase:g} cells above a node row")
                 + f", every other setting default; records in experiments/results/{folder.name}/. The loss ratio "
                 "is over the frames each fit used. Wall times of a record completed by resuming its round logs "
                 "count the optimizer time of the earlier run from the logs.\n\n"
                 + windows(records, alt) + "\n\n" + compare(records, alt, "resolved frames") + "\n\n" + report(alt))
    C.write_md(NAME, False, "Default fits on the reference simulator's data", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
