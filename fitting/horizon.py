"""Fits on the frames the grid resolves (`FitSettings.resolved_frames`).

A frame whose silhouette moves by more than FRAME_BOUNDARY_SPACINGS particle spacings when the grid is
refined to DX_CHECK_RATIO dx is placed by the grid, not by the material: a fit that uses it is pulled by
the grid's error. `calibrate_resolved` fits only the frames before the first such frame, in rounds: the
window is measured at the start point, fitted (every start), measured again at the optimum and refitted
from it (one start) until the window stays put or RESOLVED_MAX_ROUNDS fits have run; the last window
then gets the uncertainty and the discretization check at its optimum. The measurement is two forward
rollouts over the whole record (the fit grid's and the finer grid's) and needs no data.
`calibrate_joint_resolved` runs the same rounds for a joint fit, with a window per recording.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .check import finer_settings
from .io import Silhouettes, read_silhouettes
from .problem import CalibrationProblem, build_problem
from .settings import FIT_PPC, FRAME_BOUNDARY_SPACINGS, FitSettings
from .silhouette import particle_spacing

# Fits of the round procedure: the first with every start, the others one-start refits from the last
# optimum; a window still moving after three is reported as such rather than chased at more cost.
RESOLVED_MAX_ROUNDS = 3
# The shortest window fitted, in observed frames: fewer show too little of the motion to separate the
# elastic from the flow parameters, so a record unresolved from its first frame keeps these.
RESOLVED_MIN_FRAMES = 3


def grid_displacement(coarse: CalibrationProblem, fine: CalibrationProblem, theta: dict) -> np.ndarray:
    """Per observed frame of `coarse`, the mean boundary displacement between its silhouette at `theta`
    and that of `fine` (the same frames on a finer grid, same pixels), in particle spacings of `coarse`
    (`fitting.silhouette_mismatch`; a non-finite rollout's pixels count as outside)."""
    from .driver import just_inside, silhouette_mismatch

    tr = coarse.transform
    # an optimum on a bound (where the transform is open) is measured just inside it
    theta = dict(theta, **{n: just_inside(theta[n], float(tr.lower[i]), float(tr.upper[i]))
                           for i, n in enumerate(tr.names)})
    ppc = FIT_PPC[coarse.scene.dim] if coarse.settings.ppc is None else int(coarse.settings.ppc)
    spacing = particle_spacing(coarse.dx, ppc, coarse.scene.dim)
    occ = np.nan_to_num(np.asarray(coarse.render(theta), np.float64), nan=0.0)
    occ_fine = np.nan_to_num(np.asarray(fine.render(theta), np.float64), nan=0.0)
    _, boundary = silhouette_mismatch(occ, occ_fine, coarse.weights, coarse.cfg.pixel_size)
    return boundary / spacing


def resolved_count(displacement, limit: float = FRAME_BOUNDARY_SPACINGS,
                   min_frames: int = RESOLVED_MIN_FRAMES) -> int:
    """How many leading frames the grid resolves: the index of the first frame whose `displacement`
    (particle spacings) exceeds `limit`, at least min(min_frames, frames) and all frames when none does."""
    d = np.asarray(displacement, np.float64)
    bad = np.nonzero(~(d <= limit))[0]  # a NaN displacement counts as unresolved
    first = int(bad[0]) if len(bad) else len(d)
    return max(first, min(int(min_frames), len(d)))


def window_of(times, count: int, user_window) -> tuple | None:
    """The time_window (s) that keeps the first `count` of the frames at `times` (s, increasing): it ends
    half-way to the next frame; `user_window` (or None) when every frame is kept."""
    times = np.asarray(times, np.float64)
    if count >= len(times):
        return None if user_window is None else tuple(float(v) for v in user_window)
    lo = 0.0 if user_window is None else float(user_window[0])
    return lo, float(0.5 * (times[count - 1] + times[count]))


def round_log(log, k: int) -> Path | None:
    """The fit log of round k beside the final log `log`: fit.fitlog.h5 -> fit.round0.fitlog.h5."""
    if log is None:
        return None
    log = Path(log)
    name = log.name
    stem, suffix = (name[:-len(".fitlog.h5")], ".fitlog.h5") if name.endswith(".fitlog.h5") else (log.stem, log.suffix)
    return log.with_name(f"{stem}.round{k}{suffix}")


# The notes of the last round that the result keeps: what the round's budgets stopped.
KEPT_ROUND_NOTES = ("The time budget", "The best start")


def _measured(at: str, count: int, times, dx: float, dx_fine: float, who: str = "") -> str:
    """The progress line of one window measurement; who: ", recording i" or ""."""
    return (f"resolved frames{who}: at {at} the dx = {dx:.4g} m and dx = {dx_fine:.4g} m silhouettes are within "
            f"{FRAME_BOUNDARY_SPACINGS:g} particle spacing in the first {count} of {len(times)} frames "
            f"(t <= {times[count - 1]:.4g} s)")


def _time_left(budget, wall0: float):
    """Seconds of the time budget left (None: no budget)."""
    return None if budget is None else budget - (time.perf_counter() - wall0)


def _rules(settings: FitSettings) -> dict:
    """The window rule's settings, as `settings["resolved"]` records them beside the rounds."""
    return dict(user_time_window=None if settings.time_window is None else [float(v) for v in settings.time_window],
                max_rounds=RESOLVED_MAX_ROUNDS, min_frames=RESOLVED_MIN_FRAMES, limit_spacings=FRAME_BOUNDARY_SPACINGS)


def calibrate_resolved(data, settings: FitSettings, *, log=None, resume: bool = False,
                       progress: Callable[[str], None] | None = None, callback=None):
    """`calibrate` on the frames the fit grid resolves (see the module docstring); returns a `FitResult`
    whose `settings["time_window"]` is the window fitted and `settings["resolved"]` records the rounds
    (window, grid displacement per frame at the point measured, loss, optimum, wall time). Round k's fit log is
    `round_log(log, k)`, the final check's is `log`; `resume` continues each from its log, and the result's
    wall_time then counts the optimizer time the earlier runs spent (from the logs), as `calibrate`'s does."""
    from .driver import calibrate, make_starts

    wall0 = time.perf_counter()
    if not isinstance(data, Silhouettes):
        data = read_silhouettes(data)
    settings = settings.validate()
    say = progress or (lambda msg: None)
    plain = dataclasses.replace(settings, resolved_frames=False)
    unchecked = dataclasses.replace(plain, dx_check=False)
    coarse = build_problem(data, unchecked)
    fine = build_problem(data, finer_settings(coarse, unchecked))
    times = np.asarray(data.times, np.float64)[np.asarray(coarse.frames)]
    names = coarse.transform.names
    theta = coarse.params_of(make_starts(coarse.transform, settings)[0][0])
    budget = settings.time_budget
    rounds, fitted_count, last, extra = [], None, None, 0.0
    for k in range(RESOLVED_MAX_ROUNDS + 1):
        shift = grid_displacement(coarse, fine, theta)
        count = resolved_count(shift)
        at = "the start point" if last is None else f"the round {k - 1} optimum"
        say(_measured(at, count, times, coarse.dx, fine.dx))
        rounds.append(dict(measured_at={n: float(theta[n]) for n in names}, displacement=[float(v) for v in shift],
                           resolved=int(count)))
        if count == fitted_count or k == RESOLVED_MAX_ROUNDS:
            break
        left = _time_left(budget, wall0)
        if left is not None and left <= 0 and last is not None:
            rounds[-1]["stopped"] = "time budget"
            break
        window = window_of(times, count, settings.time_window)
        round_settings = dataclasses.replace(
            unchecked, time_window=window, time_budget=None if left is None else max(left, 1e-3),
            **({} if last is None else dict(starts=1, initial={n: float(theta[n]) for n in names})))
        t = time.perf_counter()
        last = calibrate(data, round_settings, log=round_log(log, k), resume=resume and _exists(round_log(log, k)),
                         progress=say, callback=callback, start_z=None if last is None else last.z)
        # a resumed round's wall_time holds the optimizer time of its earlier runs too (from its log)
        extra += last.wall_time - (time.perf_counter() - t)
        fitted_count, theta = count, last.params
        rounds[-1].update(window=None if window is None else list(window), loss=float(last.loss),
                          wall_time=float(last.wall_time), iterations=int(last.iterations),
                          params={n: float(last.params[n]) for n in names}, z=[float(v) for v in last.z])
    window = window_of(times, fitted_count, settings.time_window)
    # The last window's uncertainty and grid check at its optimum (its exact fitted coordinates): no iterations.
    t = time.perf_counter()
    final = calibrate(data, dataclasses.replace(plain, time_window=window, starts=1, max_iter=0, time_budget=None,
                                                initial={n: float(last.params[n]) for n in names}),
                      log=log, resume=resume and _exists(log), progress=say, start_z=last.z)
    extra += final.wall_time - (time.perf_counter() - t)
    return _merged(final, last, rounds, coarse, fine, times, fitted_count, settings,
                   time.perf_counter() - wall0 + extra)


def _window_note(times, count: int, displacement, dx: float, dx_fine: float, who: str = "") -> str:
    """The plain-language account of a window: the first `count` of the frames at `times` fitted, from the
    grid displacement per frame measured at the point that chose it; who: "recording i: " or ""."""
    n = len(times)
    if count < n:
        left = displacement[count:]
        return (f"{who}Fitted the first {count} of {n} frames (t <= {times[count - 1]:.4g} s), those the dx = "
                f"{dx:.4g} m grid resolves: its silhouettes and those of the dx = {dx_fine:.4g} m grid are "
                f"more than {FRAME_BOUNDARY_SPACINGS:g} particle spacing apart on average from t = "
                f"{times[count]:.4g} s on (up to {max(left):.3g} spacings), so what those frames show is placed by "
                f"the grid as much as by the material. A finer --dx resolves more of them.")
    return (f"{who}Every frame is resolved by the dx = {dx:.4g} m grid (its silhouettes and those of dx = "
            f"{dx_fine:.4g} m within {FRAME_BOUNDARY_SPACINGS:g} particle spacing): all {n} were fitted.")


def calibrate_joint_resolved(datas, settings: FitSettings, *, log=None, resume: bool = False,
                             progress: Callable[[str], None] | None = None):
    """`calibrate_joint` with every recording fitted on the frames its own grid resolves: the rounds of
    `calibrate_resolved`, each recording's window measured at the joint point (the material's parameters
    and that recording's nuisance ones); a round refits when any window moved. Returns a `JointFitResult`
    whose `settings["resolved"]` records the rounds (per recording: displacement per frame, frames resolved,
    window) and whose notes say per recording which frames were fitted. Round k's fit log is
    `round_log(log, k)`, the final stage's (the uncertainty and the discretization check at the last
    round's optimum, no iterations) is `log`; `resume` continues each from its log."""
    from .joint import build_joint, calibrate_joint, joint_starts

    wall0 = time.perf_counter()
    settings = settings.validate()
    say = progress or (lambda msg: None)
    datas = list(datas)
    plain = dataclasses.replace(settings, resolved_frames=False)
    unchecked = dataclasses.replace(plain, dx_check=False)
    whole = build_joint(datas, unchecked)  # every recording's whole record (density agreement checked here)
    fine = [build_problem(pb.data, finer_settings(pb, unchecked)) for pb in whole.problems]
    times = [np.asarray(pb.data.times, np.float64)[np.asarray(pb.frames)] for pb in whole.problems]
    z = np.asarray(joint_starts(whole, settings)[0][0])
    budget = settings.time_budget
    rounds, fitted, last = [], None, None
    for k in range(RESOLVED_MAX_ROUNDS + 1):
        per = []
        at = "the start point" if last is None else f"the round {k - 1} optimum"
        for i, (pb, fpb, zi) in enumerate(zip(whole.problems, fine, whole.split(z))):
            shift = grid_displacement(pb, fpb, pb.params_of(zi))
            count = resolved_count(shift)
            per.append(dict(displacement=[float(v) for v in shift], resolved=int(count)))
            say(_measured(at, count, times[i], pb.dx, fpb.dx, who=f", recording {i}"))
        counts = [r["resolved"] for r in per]
        rounds.append(dict(measured_at={n: float(v) for n, v in whole.params_of(z).items() if n in whole.names},
                           recordings=per))
        if counts == fitted or k == RESOLVED_MAX_ROUNDS:
            break
        left = _time_left(budget, wall0)
        if left is not None and left <= 0 and last is not None:
            rounds[-1]["stopped"] = "time budget"
            break
        windows = [window_of(t, c, settings.time_window) for t, c in zip(times, counts)]
        round_settings = dataclasses.replace(unchecked, time_budget=None if left is None else max(left, 1e-3),
                                             **({} if last is None else dict(starts=1)))
        last = calibrate_joint(None, round_settings, log=round_log(log, k), resume=resume and _exists(round_log(log, k)),
                               progress=say, joint=build_joint(datas, round_settings, windows=windows),
                               start_z=None if last is None else last.z)
        fitted, z = counts, np.asarray(last.z)
        rounds[-1].update(windows=[None if w is None else list(w) for w in windows], loss=float(last.loss),
                          wall_time=float(last.wall_time), params={n: float(last.params[n]) for n in whole.names},
                          z=[float(v) for v in last.z])
    windows = [window_of(t, c, settings.time_window) for t, c in zip(times, fitted)]
    final_settings = dataclasses.replace(plain, starts=1, max_iter=0, time_budget=None)
    final = calibrate_joint(None, final_settings, log=log, resume=resume and _exists(log), progress=say,
                            joint=build_joint(datas, final_settings, windows=windows), start_z=last.z)
    settled = [r["resolved"] for r in rounds[-1]["recordings"]] == fitted
    chosen = [r for r in rounds if "loss" in r][-1]
    notes = [_window_note(t, c, rec["displacement"], pb.dx, fpb.dx, who=f"recording {i}: ")
             for i, (t, c, rec, pb, fpb) in enumerate(zip(times, fitted, chosen["recordings"], whole.problems, fine))]
    if settled:
        notes.append("Measured again at the joint optimum, every window stays.")
    else:
        why = ("the time budget ended the rounds" if rounds[-1].get("stopped") else f"after {RESOLVED_MAX_ROUNDS} rounds")
        notes.append(f"The windows had not settled ({why}): at the joint optimum "
                     f"{[r['resolved'] for r in rounds[-1]['recordings']]} frames are resolved; the windows fitted are "
                     f"the last round's.")
    notes += [m for m in last.notes if m.startswith(KEPT_ROUND_NOTES)]
    out_settings = dict(final.settings, resolved_frames=True, max_iter=settings.max_iter, starts=settings.starts,
                        time_budget=settings.time_budget,
                        time_windows=[None if w is None else list(w) for w in windows],
                        resolved=dict(rounds=rounds, frames=fitted, of=[len(t) for t in times], settled=bool(settled),
                                      **_rules(settings), check_dx=[float(f.dx) for f in fine]))
    return dataclasses.replace(final, settings=out_settings, notes=tuple(notes) + tuple(final.notes), runs=last.runs,
                               wall_time=float(time.perf_counter() - wall0))


def _exists(path) -> bool:
    return path is not None and Path(path).exists()


def _merged(final, last, rounds, coarse, fine, times, count, settings, wall):
    """The final stage's result with the optimization history of the last fitting round, the rounds'
    record and a note on the frames left out."""
    n = len(times)
    settled = rounds[-1]["resolved"] == count
    chosen = [r for r in rounds if "loss" in r][-1]  # the measurement that chose the window fitted last
    notes = list(final.notes)
    note = _window_note(times, count, chosen["displacement"], coarse.dx, fine.dx)
    if settled:
        note += " Measured again at the optimum, the window stays."
    else:
        why = ("the time budget ended the rounds" if rounds[-1].get("stopped") else
               f"after {RESOLVED_MAX_ROUNDS} rounds")
        note += (f" The window had not settled ({why}): at the optimum {rounds[-1]['resolved']} frames are "
                 f"resolved; the window fitted is the last round's.")
    notes[:0] = [note] + [m for m in last.notes if m.startswith(KEPT_ROUND_NOTES)]
    out_settings = dict(final.settings, resolved_frames=True, max_iter=settings.max_iter, starts=settings.starts, initial=settings.initial,
                        time_budget=settings.time_budget,
                        resolved=dict(rounds=rounds, frames=count, of=n, settled=bool(settled), **_rules(settings),
                                      check_dx=float(fine.dx)))
    return dataclasses.replace(final, settings=out_settings, notes=tuple(notes), loss_history=last.loss_history,
                               time_history=last.time_history, runs=last.runs, best_run=last.best_run,
                               best_iteration=last.best_iteration, reason=last.reason, iterations=last.iterations,
                               evaluations=last.evaluations, wall_time=float(wall))


__all__ = ["RESOLVED_MAX_ROUNDS", "RESOLVED_MIN_FRAMES", "calibrate_joint_resolved", "calibrate_resolved",
           "grid_displacement", "resolved_count", "round_log", "window_of"]
