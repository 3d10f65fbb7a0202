"""Diagnostics of the fitter's discretization check on finished fits (no truth enters): refits on its finer
grid, its estimates on shifted grids, and its measured move for fits recorded before the fitter ran it,
with which such records are re-reported as the fitter reports them now. Each is cached beside the records."""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from experiments.recovery.cases import (
    CASES,
    SceneCase,
    case_of,
    data_path,
    fitter_refit,
    make_data,
    write_cache,
)
from experiments.recovery.scoring import evaluate
from fitting import FitSettings, calibrate
from fitting import read_silhouettes

# Refit diagnostic of the discretization check: LM iterations on the check's finer grid, from the fit's optimum.
REFIT_ITERATIONS = 4
# The fitter's dx_refit before DEFAULT_DX_REFIT was per dimension: the report shows both.
PREVIOUS_DX_REFIT = 2


def _cached_check(r: dict, kind: str) -> tuple[Path, dict | None]:
    """The cache file CASES/<case>_<kind>.json of a check on finished fit r, and its content (None if absent)."""
    path = CASES / f"{r['case']}_{kind}.json"
    return path, (json.loads(path.read_text()) if path.exists() else None)


def fit_and_data(r: dict):
    """(SceneCase, fit dict, Silhouettes) of finished fit record r."""
    c = case_of(r)
    return c, r["fit"], read_silhouettes(data_path(c, r["set"], r["case"].startswith("q_")))


def _settings_at_optimum(c: SceneCase, fit: dict, **kw) -> FitSettings:
    """One LM start from fit dict `fit`'s optimum with its pixel level, case c's time window and seed 0."""
    return FitSettings(optimizer="lm", seed=0, time_window=c.window, starts=1,
                       initial={n: fit["params"][n] for n in fit["fitted"]},
                       pixel_level=fit["settings"]["pixel_level"], **kw)


def refit_check(r: dict, compute: bool = True) -> dict | None:
    """How far the estimate of a finished LM fit moves between its grid and the discretization check's finer
    one (dx * DX_CHECK_RATIO; the fit's pixel level, time window and seed): the fit is continued for at most
    REFIT_ITERATIONS LM iterations from its optimum on both grids, and the difference of the two end points
    (so that what the fit itself had left to gain on its own grid does not count as the grid's effect) is
    set against the check's predicted move (both of its estimates) and its numerical error, in fitted
    coordinates. Uses no truth: it tests the check itself. Cached in CASES/<case>_refit.json; None when not
    cached and `compute` is False."""
    if r["optimizer"] != "lm":  # the cache is keyed by case: it holds the LM fit's refit
        raise ValueError(f"refit_check: {r['case']} is an {r['optimizer']} fit; the refit check is of LM fits")
    path, cached = _cached_check(r, "refit")
    if cached is not None or not compute:
        return cached
    from fitting import fit_transform, make_starts
    from fitting.settings import DX_CHECK_RATIO

    c, fit, data = fit_and_data(r)
    same = _settings_at_optimum(c, fit, dx=c.dx_fit, max_iter=REFIT_ITERATIONS, dx_check=False)
    t0 = time.perf_counter()
    tr = fit_transform(same)
    ends = {}
    for label, dx in (("fit_grid", c.dx_fit), ("finer_grid", c.dx_fit * DX_CHECK_RATIO)):
        res = calibrate(data, dataclasses.replace(same, dx=dx))
        ends[label] = {"z": np.asarray(res.uncertainty.z if res.uncertainty is not None else
                                        tr.to_unconstrained(np.array([res.params[n] for n in tr.names]))),
                           "iterations": int(res.iterations), "reason": res.reason, "loss": float(res.loss),
                           "loss_start": float(res.loss_history[0])}
    z0 = make_starts(tr, same)[0][0]
    check = fit["settings"]["dx_check"]
    out = dict(names=list(tr.names), moved_z=[float(v) for v in ends["finer_grid"]["z"] - ends["fit_grid"]["z"]],
               left_on_fit_grid_z=[float(v) for v in ends["fit_grid"]["z"] - z0], shift_z=check["shift_z"],
               shift_z_fit_jacobian=check["shift_z_fit_jacobian"], shift_z_own_jacobians=check["shift_z_own_jacobians"],
               error_z=check["error_z"], wall=time.perf_counter() - t0,
               **{f"{k}_{q}": v[q] for k, v in ends.items() for q in ("iterations", "reason", "loss", "loss_start")})
    write_cache(path, out)
    return out


# Grid shifts (fractions of dx along every axis; geometry and camera stay): half a cell is the largest
# misalignment, a quarter an intermediate one (a whole cell is the same lattice again).
SHIFT_FRACTIONS = (0.25, 0.5)


def shift_check(r: dict, compute: bool = True) -> dict | None:
    """How far the estimate of a finished LM fit would move on the same grid spacing with the grid shifted
    against the scene (SHIFT_FRACTIONS of a cell along every axis): the discretization check's two first-order
    estimates (the fit grid's Jacobian; each grid's own), applied to the shifted grid instead of the finer one,
    at the fit's optimum, set against the numerical error the check reported (fitted coordinates). The
    refinement check samples one grid per spacing; where the result depends on how the node lattice falls on
    the geometry (a sticky face, a floor, the initial shape), a shift shows it. Uses no truth. Cached in
    CASES/<case>_shift.json; None when not cached and `compute` is False."""
    path, cached = _cached_check(r, "shift")
    if cached is not None or not compute:
        return cached
    from fitting import build_problem, make_starts
    from fitting.check import predicted_move

    c, fit, data = fit_and_data(r)
    settings = _settings_at_optimum(c, fit, dx=c.dx_fit, dx_check=False)
    t0 = time.perf_counter()
    base = build_problem(data, settings)
    tr = base.transform
    # the optimum as a start (a parameter that ended on a bound is taken just inside it)
    z = make_starts(tr, settings)[0][0]
    r0, J0 = (np.asarray(a, np.float64) for a in base.residual_and_jacobian(z))
    moves = {}
    for frac in SHIFT_FRACTIONS:
        scene = json.loads(data.scene_json)
        h = frac * c.dx_fit
        scene["domain"] = {k: [v - h for v in scene["domain"][k]] for k in ("min", "max")}
        other = build_problem(dataclasses.replace(data, scene_json=json.dumps(scene)), settings)
        with_fit, with_own, _ = predicted_move(base, other, z, J0, r0)
        moves[str(frac)] = {"fit_jacobian": [float(v) for v in with_fit], "own_jacobians": [float(v) for v in with_own]}
    out = {"names": list(tr.names), "fractions": list(SHIFT_FRACTIONS), "moves": moves,
               "error_z": fit["settings"]["dx_check"]["error_z"], "shift_z": fit["settings"]["dx_check"]["shift_z"],
               "wall": time.perf_counter() - t0}
    write_cache(path, out)
    return out


def record_optimum(r: dict):
    """(transform, theta (p,), z (p,)) of finished fit r: the fitter's transform for its bounds and fixed
    parameters, and its optimum in physical and fitted coordinates (a value on a bound taken just inside it,
    as `make_starts` does)."""
    from fitting import fit_transform, make_starts

    st = r["fit"]["settings"]
    settings = FitSettings(bounds={n: tuple(b) for n, b in st["bounds"].items()}, fixed=dict(st["fixed"]),
                           initial={n: r["fit"]["params"][n] for n in r["fit"]["fitted"]}, starts=1)
    tr = fit_transform(settings)
    z = np.asarray(make_starts(tr, settings)[0][0], np.float64)
    return tr, np.asarray(tr.to_physical(z), np.float64), z


def with_measured_move(r: dict, measured_z, iterations: int) -> dict:
    """Fit record r's fit dict (reported with the discretization check's two first-order estimates only) as
    the fitter reports it with `FitSettings.dx_refit` = iterations: the check's move per parameter the
    largest of the two estimates and `measured_z`, the move of that many LM iterations on the check's grid
    from the optimum (fitted coordinates); the numerical error and the combined interval recomputed from it
    and the statistical interval, identifiability judged again. A fit that does not reproduce its data
    keeps its bounds. Uses no truth."""
    from types import SimpleNamespace

    from fitting import combine_intervals, judge_reported_intervals
    from fitting.check import check_error, numerical_half_width

    fit = json.loads(json.dumps(r["fit"]))
    check = fit["settings"]["dx_check"]
    tr, theta, z = record_optimum(r)
    names = list(tr.names)
    measured = np.asarray(measured_z, np.float64)
    err, shift = check_error([check["shift_z_fit_jacobian"], check["shift_z_own_jacobians"], measured])

    def coord(i, v):  # a physical interval end in fitted coordinates (an end on a bound just inside it)
        w = theta.copy()
        w[i] = min(max(float(v), tr.lower[i] + 1e-12 * (tr.upper[i] - tr.lower[i])),
                   tr.upper[i] - 1e-12 * (tr.upper[i] - tr.lower[i]))
        return float(np.asarray(tr.to_unconstrained(w))[i])

    stat_z = np.array([[coord(i, v) for v in fit["interval_statistical"][n]] for i, n in enumerate(names)])
    both = combine_intervals(SimpleNamespace(z=z, interval_z=stat_z), err, tr)
    interval = {n: [float(v) for v in both[i]] for i, n in enumerate(names)}
    fit["numerical_error"].update(zip(names, (float(v) for v in numerical_half_width(tr, z, err))))
    check.update(refit=int(iterations), shift_z_refit=[float(v) for v in measured], shift_z=[float(v) for v in shift],
                 error_z=[float(v) for v in err])
    if fit.get("reproduces_data", True):
        ident = {n: bool(fit["identifiable"][n]) for n in names}
        # the statistical verdict (before the interval rules) is not stored: a parameter the current check
        # reports identifiable passed it, one it reports not identifiable keeps that verdict
        ident, _ = judge_reported_intervals(interval, fit["params"], tr, ident)
        fit["interval"], fit["identifiable"] = {**fit["interval"], **interval}, {**fit["identifiable"], **ident}
    return fit


def measured_check(r: dict, compute: bool = True, iterations: int | None = None) -> dict | None:
    """The move that the fitter's discretization check now measures (`FitSettings.dx_refit` = `iterations`,
    None: the fitter's default for the scene's dimension, LM iterations on its finer grid, dx *
    DX_CHECK_RATIO, from the optimum; the fit's
    pixel level, precision, time window and seed) for a finished fit recorded before the check measured it,
    so that the record can be reported as the fitter reports it now (`with_measured_move`). `wall` is the
    time of those iterations alone, what the fitter adds to a fit (the finer grid's first residual and
    Jacobian, which the check computed already, are timed apart as `wall_first`). Uses no truth. Cached in
    CASES/<case>_<optimizer>_measured<iterations>.json; None
    when not cached and `compute` is False."""
    from fitting import build_problem, make_starts
    from fitting.check import refit_move
    from fitting.settings import DX_CHECK_RATIO

    iterations = fitter_refit(r) if iterations is None else int(iterations)
    path = CASES / f"{r['case']}_{r['optimizer']}_measured{iterations}.json"
    if path.exists() or not compute:
        return json.loads(path.read_text()) if path.exists() else None
    c = case_of(r)
    make_data(c, r["set"], r["case"].startswith("q_"))
    _, fit, data = fit_and_data(r)
    settings = _settings_at_optimum(c, fit, dx=c.dx_fit * DX_CHECK_RATIO, dtype=c.fit_dtype)
    other = build_problem(data, settings)
    z = make_starts(other.transform, settings)[0][0]
    t0 = time.perf_counter()
    at_z = tuple(np.asarray(a) for a in other.residual_and_jacobian(z))
    t1 = time.perf_counter()
    m = refit_move(other, z, int(iterations), at_z=at_z)
    out = {"names": list(other.transform.names), "refit": int(iterations), "move_z": [float(v) for v in m["move"]],
               "iterations": m["iterations"], "reason": m["reason"], "loss": list(m["loss"]),
               "wall": time.perf_counter() - t1, "wall_first": t1 - t0, "date": time.strftime("%Y-%m-%d")}
    write_cache(path, out)
    return out


def with_current_check(r: dict) -> dict:
    """Record r as the fitter reports it now: a fit whose check ran without the measured move is re-reported
    with its cached `measured_check` (fit and evaluation replaced, the earlier ones kept under
    `estimates_only`; the refit's time added to the fit's wall time); unchanged when the check measured the
    move already, or when no measured check is cached (then `check_measured` is False)."""
    check = r["fit"]["settings"].get("dx_check") or {}
    if "refit" in check or not check:
        return dict(r, check_measured=bool(check))
    mc = measured_check(r, compute=False)
    if mc is None:
        return dict(r, check_measured=False)
    fit = with_measured_move(r, mc["move_z"], mc["refit"])
    fit["wall_time"] = float(r["fit"]["wall_time"]) + float(mc["wall"])
    fit["settings"]["dx_check"].update(refit_iterations=mc["iterations"], refit_reason=mc["reason"],
                                       refit_loss=mc["loss"], rereported_from_cache=True)
    return dict(r, fit=fit, evaluation=evaluate(fit, r["truth"]), check_measured=True,
                estimates_only={"fit": r["fit"], "evaluation": r["evaluation"]})
