"""The recovery report: results/recovery[_quick].md and .png rebuilt from the finished records (`--report`
needs only the committed ones). The probe and check sections are in report_sections, the cells in
report_tables, the chart in report_figure."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments import _common as C
from experiments.recovery.cases import (
    BUDGET,
    COMPARE,
    CONTACT,
    DEFAULT_GRID,
    DROP_FRAMES,
    FINE,
    FULL,
    NAME,
    NOISE,
    QUICK,
    SLIP,
    WINDOW,
    case_id,
    case_of,
    plan,
    truth_sets,
)
from experiments.recovery.checks import with_current_check
from experiments.recovery.report_figure import save_chart
from experiments.recovery.report_sections import (
    check_change_section,
    data_section,
    default_grid_section,
    measured_move_section,
    precision_section,
    refit_section,
    shift_section,
)
from experiments.recovery.report_tables import (
    fmt_err,
    fmt_gof,
    fmt_shear,
    halved_step,
    probe_table,
    tally,
    truth_loss_of,
    wall_min,
    wall_span,
)
from experiments.recovery.runs import load_records
from experiments.recovery.scoring import GOALS, goodness, param_error
from fitting.settings import DEFAULT_STARTS, FRAME_BOUNDARY_SPACINGS

# The study's conclusions, written from its tables (appended to the full report only).
VERDICT = Path(__file__).resolve().parent / "verdict.md"


def _run_summary(quick: bool, jobs: list[tuple], recs: list[dict]) -> str:
    """What was run: the scenes, truths, budgets and data noise, and which planned fits are finished."""
    done = {(r["case"], r["optimizer"]) for r in recs}
    missing = [f"{c.name}{' at dx ' + format(c.dx_fit, '.4g') + ' m' if c in FINE + DEFAULT_GRID else ''} set {k} ({opt})"
               for _, c, k, opt in jobs if (case_id(c, k, quick), opt) not in done]
    body = []
    body.append("## What was run\n\n")
    b = BUDGET[quick]
    scenes = ", ".join(f"{c.name} (fit dx {c.dx_fit} m, data dx {c.dx_fit / 2} m, {c.duration} s, {c.frames} frames)"
                       for c in (QUICK if quick else FULL))
    body.append(
        f"{'Quick' if quick else 'Full'} study: scenes {scenes}; "
        f"parameter sets {sorted({k for _, _, k, _ in jobs})} of {truth_sets()}; "
        f"starts per fit {b['starts']} (3D fits: 1), iteration budgets per start {b['iters']}; data noise {NOISE} "
        f"(boundary pixel flips), "
        f"{DROP_FRAMES:.0%} of frames dropped, plate pixels weight 0. All four parameters are fitted with the "
        f"fitter's default bounds, starts and discretization check; density and kappa are the scene's.\n\n")
    body.append(f"Finished: {len(recs)} of {len(jobs)} planned fits."
                + (f" **Not run (out of time on the shared 2-core machine):** {', '.join(missing)}." if missing else "")
                + "\n\n")
    stale = [r for r in load_records(quick) if halved_step(r) > 1.0]
    if stale:
        body.append(
            f"**Time step of fits with a dropped frame (2026-11-24).** Every frame of a rollout runs the same "
            f"number of substeps, sized for its widest frame interval, so until the fitter filled gaps in the "
            f"data with unobserved frames (`fitting.problem.simulation_frames`), a frame dropped inside the "
            f"fitted span made every frame run at half (or a third of) the fit's CFL time step, for 2-3x the "
            f"cost: the datasets of sets 1 and 2 have such a gap in every scene. The main table's LM fits, the "
            f"optimizer comparison's and the default grid's squeeze fits were re-run with the gaps filled (the "
            f"earlier records are kept as `<case>_<optimizer>.json.halved-dt`); {len(stale)} records below still ran "
            f"at the narrower step and are marked † at their wall time (the probes' and the float32 fits', the "
            f"last compared with the float64 fits made at the same step); their `loss at truth` is evaluated "
            f"with the gaps filled, as every other's.\n\n")
    return "".join(body)


def _main_section(lm: list[dict], names) -> str:
    """The main table (LM): errors, losses, goodness of fit, cost and shear rates; intervals; coverage."""
    if not lm:
        return ""
    rows = []
    for r in lm:
        ev, fit = r["evaluation"], r["fit"]
        rows.append([r["scene"], r["set"], ", ".join(f"{n}={r['truth'][n]:.3g}" for n in names),
                     ", ".join(f"{fit['params'][n]:.3g}" for n in names)]
                    + [fmt_err(ev[n]) for n in names]
                    + [f"{fit['loss']:.3g}", f"{truth_loss_of(r):.3g}", fmt_gof(r),
                       fit["iterations"], fit["evaluations"], fit["reason"], wall_min(r),
                       fmt_shear(r)])
    n_par = sum(len(names) for _ in lm)
    inside = sum(r["evaluation"][n]["inside"] for r in lm for n in names)
    inside_stat = sum(r["evaluation"][n]["inside_statistical"] for r in lm for n in names)
    goals = sum(r["evaluation"][n]["goal_met"] for r in lm for n in names)
    per_param = {n: (sum(r["evaluation"][n]["goal_met"] for r in lm), sum(r["evaluation"][n]["inside"] for r in lm))
                 for n in names}
    fits_2d = [r["fit"]["wall_time"] for r in lm if not r["scene"].endswith("3d")]
    body = []
    body.append("## Recovery (Levenberg-Marquardt)\n\n")
    body.append("Errors: relative for mu, sigma_y, eta, absolute for m; `out` = truth outside the 95% interval, "
                "`n.i.` = reported not identifiable. `loss at truth`: the fit's loss evaluated at the true "
                "parameters on the fit grid (below `loss`: the optimizer stopped in another basin; above it: "
                "the fit grid's own optimum lies away from the truth). The shear-rate column gives the "
                "fraction of particle-frames that yield and the 10th-90th percentile of their plastic rate "
                "in a rollout of the truth at the fit dx: eta and m are only separable when it spans "
                "decades. `min IoU; max boundary`: the fitter's goodness-of-fit check, the smallest per-frame IoU "
                "of the fitted silhouette with the data and the largest per-frame mean distance between their "
                "boundaries in particle spacings (dx / 2 here); above FRAME_BOUNDARY_SPACINGS (1) the fitter "
                "reports that it did not reproduce the data (**no**) and reports each parameter's bounds as its "
                "interval, not identifiable (the interval at its optimum kept as `interval_local`).\n\n")
    body.append(C.md_table(["scene", "set", "truth (mu, sigma_y, eta, m)", "fit"] + [f"err {n}" for n in names]
                           + ["loss", "loss at truth", "min IoU; max boundary (spacings)", "iter", "evals", "stop", "wall min",
                              "yielding; shear rate p10-p90 (1/s)"], rows))
    body.append("\nTrue value, fit and combined 95% interval of every parameter (LM):\n\n")
    irows = [[r["scene"], r["set"], n, f"{r['truth'][n]:.4g}", f"{r['fit']['params'][n]:.4g}",
              "[" + ", ".join(f"{v:.4g}" for v in r["evaluation"][n]["interval"]) + "]",
              "yes" if r["evaluation"][n]["inside"] else "**no**",
              "yes" if r["evaluation"][n]["identifiable"] else "no"] for r in lm for n in names]
    body.append(C.md_table(["scene", "set", "param", "truth", "fit", "95% interval", "truth inside",
                            "identifiable"], irows))
    body.append(f"\nTruth inside the combined 95% interval: {inside}/{n_par} parameter-cases "
                f"({100 * inside / max(n_par, 1):.1f}%; goal >= 90%: "
                f"{'met' if inside >= 0.9 * n_par else 'missed'}); inside the Gauss-Newton interval alone: "
                f"{inside_stat}/{n_par}. Goal met (within tolerance, or not identifiable with the truth inside): "
                f"{goals}/{n_par}; per parameter (goal met, inside interval) of {len(lm)}: "
                + ", ".join(f"{n} {g}/{i}" for n, (g, i) in per_param.items()) + ". ")
    good = [r for r in lm if goodness(r)[1] <= FRAME_BOUNDARY_SPACINGS]
    body.append(f"Fits that reproduce their data (boundaries within {FRAME_BOUNDARY_SPACINGS:g} particle spacing): {len(good)}/{len(lm)}; among them the truth is "
                f"inside the combined interval in {sum(r['evaluation'][n]['inside'] for r in good for n in names)}"
                f"/{len(names) * len(good)} parameter-cases and the goal is met in "
                f"{sum(r['evaluation'][n]['goal_met'] for r in good for n in names)}/{len(names) * len(good)}. ")
    if fits_2d:
        body.append(f"2D fit wall time: {min(fits_2d) / 60:.1f}-{max(fits_2d) / 60:.1f} min (goal < 15 min), "
                    f"on a shared 2-core machine.\n")
    notes = [(r["scene"], r["set"], note) for r in lm for note in r["fit"]["notes"]]
    if notes:
        body.append("\nIdentifiability notes of the fits:\n\n" + "".join(f"- {s} set {k}: {n}\n" for s, k, n in notes))
    return "".join(body)


def _optimizer_section(comp: list[dict], names) -> str:
    """The optimizers compared on the same data (each fit's first start)."""
    if not comp:
        return ""
    body = []
    body.append("\n## Optimizers on the same data\n\n")
    body.append("Each optimizer's first start (the same initial guess, the centre of the start ranges); "
                "`wall min` is that start's optimizer time. For a multi-start LM fit whose best start is "
                "another one, the goodness-of-fit column is `-` and the errors carry no interval flags "
                "(intervals are computed at the best start only).\n\n")
    crow = []
    for r in comp:
        run, best = r["fit"]["runs"][0], r["fit"]["best_run"] == 0
        errs = [fmt_err(r["evaluation"][n]) if best else
                fmt_err({"kind": GOALS[n][0], "inside": True, "identifiable": True,
                         "error": param_error(run["end"][n], r["truth"][n], GOALS[n][0])}) for n in names]
        label = r["optimizer"] + (f" (start 1 of {len(r['fit']['runs'])})" if len(r["fit"]["runs"]) > 1 else "")
        # the lowest loss of the start (the fitter reports the best iterate: Adam's last need not be it)
        loss = r["fit"]["loss"] if best else min(r["histories"]["0"]["loss"])
        crow.append([r["scene"], r["set"], label, loss, truth_loss_of(r), fmt_gof(r) if best else "-",
                     run["iterations"], run["evaluations"], run["reason"], wall_min(r, run["wall_time"])] + errs)
    body.append(C.md_table(["scene", "set", "optimizer", "final loss", "loss at truth",
                            "min IoU; max boundary (spacings)", "iter", "evals", "stop", "wall min"]
                           + [f"err {n}" for n in names], crow))
    return "".join(body)


def _scene_section(lm: list[dict], names) -> str:
    """Per scene: how often each parameter was identifiable, and the median error."""
    if not lm:
        return ""
    body = []
    body.append("\n## Which scene constrains which parameter (LM fits)\n\n"
                "Per scene: in how many fits the parameter was identifiable, and the median error "
                "(relative; absolute for m) over the fits.\n\n")
    srows = []
    for scene in dict.fromkeys(r["scene"] for r in lm):
        rs = [r for r in lm if r["scene"] == scene]
        row = [scene, len(rs)]
        for n in names:
            ident = sum(r["evaluation"][n]["identifiable"] for r in rs)
            med = float(np.median([abs(r["evaluation"][n]["error"]) for r in rs]))
            row.append(f"{ident}/{len(rs)}, {100 * med:.0f}%" if GOALS[n][0] == "rel" else f"{ident}/{len(rs)}, {med:.2f}")
        srows.append(row)
    body.append(C.md_table(["scene", "fits"] + [f"{n}: identifiable, median err" for n in names], srows))
    return "".join(body)


def _probe_sections(fine, slip, contact, win, lm, dflt, names) -> str:
    """The finer grid, the frictionless floor, particle floor contact and the time window, each beside the
    main table's fits."""
    body = []
    if fine:
        body.append(f"\n## Finer fit grid (LM, {DEFAULT_STARTS} starts)\n\n"
                    "The same truths, noise and budget, fitted at dx_fit / sqrt(2) to data made at half that "
                    "(FINE); beside each, the same set at the study's dx_fit.\n\n")
        body.append(probe_table(fine, lm, names, base_scene=lambda r: r["scene"]))
    if slip:
        body.append(f"\n## Frictionless floor (drop, LM, {DEFAULT_STARTS} starts)\n\n"
                    "The drop's truths, noise and budget on the same scene with floor friction 0 (data made on "
                    "that scene); beside each, the same set on the scene's floor (friction 0.5). "
                    "`experiments/results/floor_contact.md` measures the two floors across grid spacings.\n\n")
        body.append(probe_table(slip, lm, names, base_scene=lambda r: "drop_2d"))
    if contact:
        body.append(f"\n## Particle floor contact (drop, LM, {DEFAULT_STARTS} starts)\n\n"
                    "The drop's truths, noise and budget on the same scene with particle floor contact (data made "
                    "on that scene): the landed foam rests on the floor on every grid instead of about 0.7 cells "
                    "above it; beside each, the same set with the default grid contact. "
                    "`experiments/results/floor_contact.md` compares the two contacts across grid spacings.\n\n")
        body.append(probe_table(contact, lm, names, base_scene=lambda r: "drop_2d"))
    if win:
        w = WINDOW[0].window
        body.append(f"\n## Time window (squeeze, LM, {DEFAULT_STARTS} starts)\n\n"
                    f"The squeeze's data of the main table (the same files), fitted over t = {w[0]:g}-{w[1]:g} s "
                    "only: the squeeze and the hold, without the lift, in which the foam stuck to the rising plate "
                    "stretches (`FitSettings.time_window`, `jaxfoam fit --time-window`); beside each, the main "
                    "table's fit of all frames. `loss at truth` is over the window's frames.\n\n")
        body.append(probe_table(win, lm + dflt, names, base_scene=lambda r: r["scene"]))
        for dx in sorted({r["dx_fit"] for r in win}, reverse=True):
            rs = [r for r in win if r["dx_fit"] == dx]
            n, inside_w, goals_w, within_w = tally(rs, names)
            body.append(f"\nIn the window at dx {dx * 1e3:.2f} mm: truth inside the combined interval in "
                        f"{inside_w}/{n} parameter-cases, goal met in {goals_w}/{n}; within the error goal: "
                        + ", ".join(f"{p} {within_w[p]}/{len(rs)}" for p in names)
                        + f"; wall time {wall_span(rs)}.\n")
    return "".join(body)


def report(quick: bool, n_sets: int | None = None) -> None:
    """Rebuild results/recovery[_quick].md and .png from the finished records (no fit runs; diagnostics
    not cached are computed when their data are at hand, else left out)."""
    recs = [with_current_check(r) for r in load_records(quick)]
    jobs = plan(quick, n_sets)
    load_all = list(recs)
    fine = [r for r in recs if r["case"].startswith("fine_")]
    dflt = [r for r in recs if r["case"].startswith("dflt_")]
    slip = [r for r in recs if any(r["scene"] == c.name for c in SLIP)]
    contact = [r for r in recs if any(r["scene"] == c.name for c in CONTACT)]
    win = [r for r in recs if r["case"].startswith("win_")]
    f32 = [r for r in recs if r["case"].startswith("f32_")]
    varied = [r for r in recs if case_of(r).tag]
    recs = [r for r in recs if not r["case"].startswith(("fine_", "dflt_", "win_", "f32_")) and r not in slip
            and r not in contact and r not in varied]
    lm = [r for r in recs if r["optimizer"] == "lm"]
    names = list(GOALS)

    body = [_run_summary(quick, jobs, load_all), _main_section(lm, names)]
    comp = [r for r in recs if (r["scene"], r["set"]) in {(s, k) for s, k in COMPARE[quick]}]
    body.append(_optimizer_section(comp, names))
    body.append(_scene_section(lm, names))
    body.append(_probe_sections(fine, slip, contact, win, lm, dflt, names))
    if dflt:
        body.append(default_grid_section(dflt, lm, names))
    if varied:
        body.append(data_section(varied, lm, names))
    if f32:
        body.append(precision_section(f32, lm + dflt, names))
    body.append(refit_section(lm))
    body.append(measured_move_section([("main table", lm), ("default grid", [r for r in dflt if r["optimizer"] == "lm"]),
                                        ("probes and others", [r for r in load_all if r["optimizer"] == "lm"
                                                               and r not in lm and r not in dflt])], names))
    body.append(shift_section(lm))
    body.append(check_change_section([("main table, 1 cm (3D: 16 mm)", lm), ("default grid", dflt),
                                       ("probes: finer grid, floor, contact, window", fine + slip + contact + win)],
                                      names))
    if not quick:
        body.append("\n## Verdict\n\n" + VERDICT.read_text().strip() + "\n")
    save_chart(lm, comp, names, quick)
    C.write_md(NAME, quick, "Parameter recovery from synthetic silhouettes", "".join(body))
