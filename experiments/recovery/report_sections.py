"""The recovery report's probe and check sections: data made differently, float32 fits, the default grid,
and the discretization check against refits, grid shifts, its measured move and its earlier Jacobian."""
from __future__ import annotations

from experiments import _common as C
from experiments.recovery.cases import case_of
from experiments.recovery.checks import (
    PREVIOUS_DX_REFIT,
    REFIT_ITERATIONS,
    measured_check,
    refit_check,
    shift_check,
    with_measured_move,
)
from experiments.recovery.report_tables import (
    error_range,
    probe_table,
    rel_move,
    same_step_base,
    tally,
    truth_frames_table,
    varied_table,
    wall_span,
)
from experiments.recovery.scoring import evaluate
from fitting.settings import DEFAULT_DX_REFIT, DEFAULT_STARTS, FIT_CELLS


def shift_section(lm: list[dict]) -> str:
    """The `shift_check` of the main table's LM fits (cached ones only), for mu and sigma_y."""
    rows, n, covered, larger = [], 0, 0, 0
    for r in lm:
        sc = shift_check(r, compute=False)
        if sc is None:
            continue
        fr = sc["fractions"]
        for i, name in enumerate(sc["names"]):
            if name not in ("mu", "sigma_y"):
                continue
            biggest = max(max(abs(m["fit_jacobian"][i]), abs(m["own_jacobians"][i])) for m in sc["moves"].values())
            e, refine = sc["error_z"][i], abs(sc["shift_z"][i])
            n += 1
            covered += biggest <= e
            larger += biggest > refine
            rows.append([r["scene"], r["set"], name]
                        + [rel_move(r, name, sc['moves'][str(f)][k][i]) for f in sc["fractions"]
                           for k in ("fit_jacobian", "own_jacobians")]
                        + [rel_move(r, name, sc['shift_z'][i]), error_range(r, name, e),
                           "yes" if biggest <= e else "**no**", f"{r['evaluation'][name]['error'] * 100:+.0f}%"])
    if not rows:
        return ""
    heads = [f"{f:g} cell: {k}" for f in fr for k in ("fit grid's J", "own J")]
    return (f"\n## Discretization check against grid shifts (LM, main table)\n\n"
            f"At each fit's optimum, the move of mu and sigma_y that the discretization check's two first-order "
            f"estimates (with the fit grid's Jacobian; with each grid's own) predict when the grid of the same "
            f"spacing is shifted against the scene by {' and '.join(f'{f:g}' for f in fr)} of a cell along every "
            f"axis (the scene's domain moved, geometry and camera kept), beside the check's own predicted move "
            f"between dx and dx / sqrt(2) (`refinement`, the larger of its two estimates) and the numerical error "
            f"it reports (the range it spans around the estimate). `error vs truth` is the fit's actual error. "
            f"Moves are computed in the fit's coordinates (logit-log for these bounded parameters) and shown as the "
            f"relative change of the parameter they make (before 2026-11-25 this section showed the coordinate "
            f"moves as if they were log moves, about 0.6-0.75x the true relative changes at these values); "
            f"`covers` compares them in those coordinates. `python -m experiments.recovery --shift-check` computes "
            f"them.\n\n"
            + C.md_table(["scene", "set", "param"] + heads + ["refinement", "numerical error", "covers the shifts",
                                                               "error vs truth"], rows)
            + f"\nShift checks cached for {len(rows) // 2} of the {len(lm)} fits. The largest predicted shift move "
              f"exceeds the refinement move the check is built on in {larger}/{n} parameter-cases; the reported "
              f"numerical error covers every predicted shift move in {covered}/{n}.\n")


def refit_section(lm: list[dict]) -> str:
    """The `refit_check` of the main table's LM fits (cached ones only): per fit and parameter, the move of
    the estimate in REFIT_ITERATIONS LM iterations on the finer grid against the check's two predictions."""
    rows, covered, n, closer = [], 0, 0, {"fit": 0, "own": 0}
    for r in lm:
        rc = refit_check(r, compute=False)
        if rc is None:
            continue
        for i, name in enumerate(rc["names"]):
            if name not in ("mu", "sigma_y"):
                continue
            mv, a, b, e = rc["moved_z"][i], rc["shift_z_fit_jacobian"][i], rc["shift_z_own_jacobians"][i], rc["error_z"][i]
            n += 1
            covered += abs(mv) <= e
            closer["fit" if abs(a - mv) <= abs(b - mv) else "own"] += 1
            left = rc['left_on_fit_grid_z'][i]
            rows.append([r["scene"], r["set"], name, rel_move(r, name, mv, left), rel_move(r, name, a),
                         rel_move(r, name, b), error_range(r, name, e), "yes" if abs(mv) <= e else "**no**",
                         rel_move(r, name, left),
                         f"{rc['fit_grid_iterations']}; {rc['finer_grid_iterations']}"])
    if not rows:
        return ""
    return (f"\n## Discretization check against refits on its finer grid (LM, main table)\n\n"
            f"Each fit continued for at most {REFIT_ITERATIONS} LM iterations from its optimum on its own grid and on "
            f"the check's grid (dx / sqrt(2), the same pixels): how far mu and sigma_y (moves in the fit's logit-log "
            f"coordinates, shown as the relative changes of the parameters they make) the finer grid's end point lies from the fit grid's (`moved`; `left on fit grid`: how "
            f"far the fit grid's own continuation went, which the difference removes), against the check's two "
            f"first-order predictions of that move (with the fit "
            f"grid's Jacobian; with each grid's own; the check uses the larger) and the numerical error it "
            f"reports (the range around the estimate: extrapolated to the continuum and times the safety factor; "
            f"`covers` compares in the fit's coordinates). "
            f"No truth enters. `python -m experiments.recovery --refit-check` computes the refits.\n\n"
            + C.md_table(["scene", "set", "param", "moved", "predicted: fit grid's J", "predicted: own J",
                          "numerical error", "covers the move", "left on fit grid", "iterations (fit grid; finer)"],
                         rows)
            + f"\nRefits cached for {len(rows) // 2} of the {len(lm)} fits"
              + (" (the others not run)" if len(rows) // 2 < len(lm) else "")
              + f". The numerical error covers the refit's move in {covered}/{n}; the prediction closer to the move is "
              f"the fit grid's Jacobian's in {closer['fit']}/{n} and the own Jacobians' in {closer['own']}/{n}.\n")


def _count(evs: list[dict], key: str, names) -> int:
    """How many parameter-cases of evaluations `evs` have flag `key`."""
    return sum(ev[n][key] for ev in evs for n in names)


def _seconds(v) -> str:
    return f"{min(v):.0f}-{max(v):.0f} s"


def _share(v, base) -> str:
    """The range of v over base, in percent."""
    return f"{100 * min(e / b for e, b in zip(v, base)):.0f}-{100 * max(e / b for e, b in zip(v, base)):.0f}%"


def _interval(e: dict) -> str:
    """An evaluated parameter's interval, flagged `n.i.` and `out`."""
    return (f"[{e['interval'][0]:.4g}, {e['interval'][1]:.4g}]"
            f"{'' if e['identifiable'] else ' n.i.'}{'' if e['inside'] else ' out'}")


def measured_move_section(groups: list[tuple[str, list[dict]]], names) -> str:
    """Coverage and goal of fit groups with the check's first-order estimates only (as the fits were first
    reported), with the measured move of the fitter's DEFAULT_DX_REFIT iterations for the scene's dimension
    (as reported now), and with the PREVIOUS_DX_REFIT iterations the fitter ran before (where cached)."""
    rows, changed = [], []
    for label, recs in groups:
        recs = [r for r in recs if "estimates_only" in r]
        if not recs:
            continue
        before = [r["estimates_only"]["evaluation"] for r in recs]
        now = [r["evaluation"] for r in recs]
        previous, previous_wall = [], []
        for r in recs:
            mp = measured_check(r, compute=False, iterations=PREVIOUS_DX_REFIT)
            if mp is not None:
                previous.append(evaluate(with_measured_move(dict(r, fit=r["estimates_only"]["fit"]), mp["move_z"],
                                                            PREVIOUS_DX_REFIT), r["truth"]))
                previous_wall.append(float(mp["wall"]))
        whole = len(previous) == len(recs)
        extra = [r["fit"]["wall_time"] - r["estimates_only"]["fit"]["wall_time"] for r in recs]
        base = [r["estimates_only"]["fit"]["wall_time"] for r in recs]
        rows.append([label, len(recs), len(names) * len(recs)]
                    + [f"{_count(before, key, names)} -> {_count(now, key, names)}"
                       + (f" ({_count(previous, key, names)})" if whole else "")
                       for key in ("inside", "goal_met", "identifiable")]
                    + [_seconds(extra) + (f" ({_seconds(previous_wall)})" if whole else ""),
                       _share(extra, base) + (f" ({_share(previous_wall, base)})" if whole else "")])
        for r, a, b in zip(recs, before, now):
            for n in names:
                if (a[n]["inside"], a[n]["goal_met"], a[n]["identifiable"]) != (b[n]["inside"], b[n]["goal_met"],
                                                                                 b[n]["identifiable"]):
                    changed.append([label, r["scene"], r["set"], r["case"].split("_set")[0].split(r["scene"])[0].rstrip("_")
                                    or "-", n, f"{r['truth'][n]:.4g}", f"{a[n]['value']:.4g}",
                                    f"{a[n]['error'] * (100 if a[n]['kind'] == 'rel' else 1):+.3g}"
                                    + ("%" if a[n]["kind"] == "rel" else ""), _interval(a[n]), _interval(b[n]),
                                    f"{'yes' if a[n]['goal_met'] else 'no'} -> {'yes' if b[n]['goal_met'] else 'no'}"])
    if not rows:
        return ""
    return (f"\n## Discretization check with a measured move (LM)\n\n"
            f"Since 2026-11-25 the fitter's discretization check also measures the move it estimates: "
            f"`FitSettings.dx_refit` LM iterations on its finer grid from the optimum (`jaxfoam fit --dx-refit N`, "
            f"0 to skip; by default {DEFAULT_DX_REFIT[2]} in 2D and {DEFAULT_DX_REFIT[3]} in 3D, "
            f"{PREVIOUS_DX_REFIT} in both until 2026-11-25, later), the largest of that and the two first-order "
            f"estimates counting. The fits above ran before; each is re-reported from a cached run of those "
            f"iterations (`measured_check`: the same start, grid and tolerances as the fitter's; same optimum and "
            f"statistical interval), its wall time with their time added. Parameter-cases with the truth inside "
            f"the combined interval, with the goal met, and reported identifiable: estimates only -> with the "
            f"fitter's default iterations (in brackets: {PREVIOUS_DX_REFIT} iterations everywhere), and the time "
            f"the iterations added (in brackets: {PREVIOUS_DX_REFIT}; each measured alone, on the shared "
            f"machine):\n\n"
            + C.md_table(["group", "fits", "parameter-cases", "inside", "goal met", "identifiable",
                          "time added", "of the fit's wall time"], rows)
            + ("\nThe parameter-cases whose verdict changed:\n\n"
               + C.md_table(["group", "scene", "set", "variant", "param", "truth", "fit", "error", "estimates only",
                             "with the measured move", "goal met"], changed) if changed else
               "\nNo parameter-case changed its verdict.\n"))


def data_section(varied: list[dict], lm: list[dict], names) -> str:
    """The DATA probe: each variant's fits beside the main table's fit of the same set, and per variant the
    coverage and goal counts."""
    out = [(f"\n## Data made differently (hanging plate and drop; squeeze with `mask`; 1 cm, LM, {DEFAULT_STARTS} "
            "starts)\n\n"
            "The main table's truths and fit settings, with data made otherwise, one change at a time (none "
           "chosen from these results): `fine4` data on a grid 4x finer than the fit instead of 2x; `noisy` "
           "boundary flips 0.2 and 30% of frames dropped (0.05, 10%); `pix` 1.25 mm camera pixels (2.5 mm), "
           "which the fitter coarsens; `mask` the file's scene starts from its first, noisy, mask, as a tracked "
           "video's does, not from the exact primitive; `fat` every mask grown by one pixel (2.5 mm), as a renderer "
           "or tracker that draws the boundary a pixel further out would; `numerics` the data simulated with "
           "another simulator's numerics: 9 particles per cell, CFL 0.5 and float32 (the fit: 4, 0.3, float64). "
           "Beside each, the main table's fit of the same set.\n\n"),
           varied_table(varied, lm, names), "\n"]
    base = {(r["scene"], r["set"]) for r in varied}
    same = [r for r in lm if (r["scene"], r["set"]) in base]
    n0, inside0, goals0, within0 = tally(same, names)
    for tag in dict.fromkeys(case_of(r).tag for r in varied):
        rs = [r for r in varied if case_of(r).tag == tag]
        n, inside_v, goals_v, within_v = tally(rs, names)
        out.append(f"- `{tag}`: truth inside the combined interval in {inside_v}/{n} parameter-cases, goal met in "
                   f"{goals_v}/{n}; within the error goal: " + ", ".join(f"{p} {within_v[p]}/{len(rs)}" for p in names)
                   + f"; wall time {wall_span(rs)}.\n")
    out.append(f"- the main table's fits of the same sets: inside {inside0}/{n0}, goal met {goals0}/{n0}; within the "
               "error goal: " + ", ".join(f"{p} {within0[p]}/{len(same)}" for p in names) + ".\n")
    return "".join(out)


def precision_section(f32: list[dict], base: list[dict], names) -> str:
    """The PRECISION probe: each float32 fit beside the float64 fit of the same data, and per grid the
    coverage, goal counts and the wall time against float64's."""
    out = [(f"\n## Fits in float32 (main table's 2D fits and the default grid's squeeze; LM, {DEFAULT_STARTS} "
            "starts)\n\n"
            "The same data files, grids and budget as the float64 fits beside them, with the fit's rollouts, "
           "Jacobians and renderer in float32 (`jaxfoam fit --dtype float32`). The wall-time ratio is float64's "
           "over float32's, per fit.\n\n"),
           probe_table(f32, base, names, base_scene=lambda r: r["scene"],
                        base_of=lambda r, same: same_step_base(r, same)), "\n"]
    for dx in sorted({r["dx_fit"] for r in f32}, reverse=True):
        rs = [r for r in f32 if r["dx_fit"] == dx]
        pairs = [(r, same_step_base(r, base)) for r in rs]
        n, inside_v, goals_v, within_v = tally(rs, names)
        n0, inside0, goals0, within0 = tally([b for _, b in pairs], names)
        speed = [b["fit"]["wall_time"] / r["fit"]["wall_time"] for r, b in pairs]
        out.append(f"- dx {dx * 1e3:.2f} mm, float32: truth inside the combined interval in {inside_v}/{n} "
                   f"parameter-cases, goal met in {goals_v}/{n} (float64: {inside0}/{n0}, {goals0}/{n0}); within the "
                   "error goal: " + ", ".join(f"{p} {within_v[p]}/{len(rs)} ({within0[p]})" for p in names)
                   + f"; wall time {wall_span(rs)}, "
                     f"{min(speed):.2f}-{max(speed):.2f}x faster than float64.\n")
    return "".join(out)


def default_grid_section(dflt: list[dict], lm: list[dict], names) -> str:
    """The DEFAULT_GRID probe: its fits beside the study's 1 cm fits of the same sets, and its coverage and
    goal counts (the same measures as the main table's summary)."""
    n, inside, goals, within = tally(dflt, names)
    same = [b for b in lm if any(b["scene"] == r["scene"] and b["set"] == r["set"] for r in dflt)]
    lm3d = [b for b in lm if b["scene"].endswith("3d")]
    n3d, in3d, g3d, _ = tally(lm3d, names)
    grid = [r["dx_fit"] * 1e3 for r in dflt]
    coarse = f"{same[0]['dx_fit'] * 1e3:g} mm" if same else "dx_fit"
    return (f"\n## The fitter's default grid (2D, LM, {DEFAULT_STARTS} starts)\n\n"
            f"`jaxfoam fit` without `--dx` fits on the largest domain extent / {FIT_CELLS[2]} ({min(grid):.1f}-"
            f"{max(grid):.1f} mm for these scenes). The same truths, noise and budget, fitted on that grid to data "
            f"made at half its spacing; beside each, the same set at the study's {coarse}.\n\n"
            + probe_table(dflt, lm, names, base_scene=lambda r: r["scene"])
            + f"\nOn the default grid: truth inside the combined interval in {inside}/{n} parameter-cases, goal met in "
            f"{goals}/{n}; within the error goal: " + ", ".join(f"{p} {within[p]}/{len(dflt)}" for p in names)
            + f" (at {coarse}, the same sets: " + ", ".join(
                f"{p} {sum(b['evaluation'][p]['within_goal'] for b in same)}/{len(same)}" for p in names)
            + f"). Wall time {wall_span(dflt)} (goal < 15 min)."
            + (f" With the 3D fits of the main table (dx {lm3d[0]['dx_fit'] * 1e3:g} mm) the truth is inside {inside + in3d}/{n + n3d} intervals "
               f"and the goal is met in {goals + g3d}/{n + n3d}." if n3d else "") + "\n"
            + "\nWhere the default grid differs from the data: at the true parameters, the mean distance between "
              "the fit grid's silhouette and the data's boundary in each used frame (time: particle spacings; "
              "the fitter's goodness-of-fit measure, limit 1):\n\n" + truth_frames_table(dflt))


def check_change_section(groups: list[tuple[str, list[dict]]], names) -> str:
    """How the discretization check's larger estimate (DX_CHECK_JACOBIAN "both", re-reported from the fit
    logs at the same optima) changed coverage and goals against the fit grid's Jacobian alone, per group of
    fits; empty when no record keeps its earlier evaluation."""
    rows = []
    for label, recs in groups:
        was = [r for r in recs if (r.get("rereported") or {}).get("previous_jacobian") == "fit"
               and "previous_evaluation" in r["rereported"]]
        if not was:
            continue
        n = len(names) * len(was)
        old = [r["rereported"]["previous_evaluation"] for r in was]
        new = [r["evaluation"] for r in was]

        def count(evs, key):
            return sum(e[p][key] for e in evs for p in names)

        rows.append([label, len(was), f"{count(old, 'inside')}/{n}", f"{count(new, 'inside')}/{n}",
                     f"{count(old, 'goal_met')}/{n}", f"{count(new, 'goal_met')}/{n}",
                     f"{count(old, 'identifiable')}/{n}", f"{count(new, 'identifiable')}/{n}"])
    if not rows:
        return ""
    return ("\n## Discretization check: the fit grid's Jacobian against both grids' (LM)\n\n"
            "The same optima, re-reported from their fit logs after the check changed (2026-11-24) from one "
            "estimate of the move between dx and dx / sqrt(2), with the fit grid's Jacobian, to the larger of that "
            "and the estimate with each grid's own Jacobian (`fitting.settings.DX_CHECK_JACOBIAN`, "
            "docs/calibrate.md). Parameter-cases with the truth inside the reported interval, with the goal met "
            "(within tolerance, or not identifiable with the truth inside), and reported identifiable:\n\n"
            + C.md_table(["fits", "n", "inside: fit grid's J", "inside: both", "goal met: fit grid's J",
                          "goal met: both", "identifiable: fit grid's J", "identifiable: both"], rows))
