"""`calibrate`: multi-start optimization with a resumable fit log, then uncertainty and the report."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from . import optim
from .optim.uncertainty import DEFAULT_MAX_RELATIVE_WIDTH

from .io import Silhouettes, read_silhouettes
from .silhouette import particle_spacing
from .settings import (ADAM_DECAY, ADAM_LEARNING_RATE, BOUND_SPAN_FRACTION, CalibrationError, DEFAULT_DX_REFIT,
                       DX_CHECK_JACOBIAN, DX_CHECK_ORDER, DX_CHECK_RATIO, FIT_PPC, FRAME_BOUNDARY_SPACINGS, FTOL,
                       FitSettings, GCI_SAFETY, OPTIMIZERS, XTOL)
from .result import FitResult, _format_params
from .problem import CalibrationProblem, _data_fingerprint, build_problem, fitted_occupancy
from .check import (combine_intervals, discretization_error, fit_uncertainty, grid_limit_note, numerical_half_width,
                    separation_note, uneven_frames_note)


def judge_reported_intervals(interval: dict, params: dict, transform, identifiable: dict):
    """Identifiability judged again on the reported intervals (statistical and numerical combined).

    A parameter is not identifiable when its interval is wider than DEFAULT_MAX_RELATIVE_WIDTH times
    its value, covers at least BOUND_SPAN_FRACTION of its bounds, or is unbounded. Args: interval
    name -> (lo, hi) and params name -> value in physical units; transform the fit's
    `fitting.optim.ParameterTransform` (its names and bounds); identifiable name -> bool from the
    statistical check. Returns (updated identifiable dict, list of notes for the changed ones).
    """
    out, notes = dict(identifiable), []
    for i, n in enumerate(transform.names):
        lo, hi = interval[n]
        value = float(params[n])
        span = float(transform.upper[i]) - float(transform.lower[i])
        wide = (hi - lo) > DEFAULT_MAX_RELATIVE_WIDTH * max(abs(value), np.finfo(np.float64).tiny)
        fills = math.isfinite(span) and (hi - lo) >= BOUND_SPAN_FRACTION * span
        if out.get(n, False) and (wide or fills or not (math.isfinite(lo) and math.isfinite(hi))):
            out[n] = False
            why = (f"covers {100 * (hi - lo) / span:.0f}% of its bounds [{transform.lower[i]:.4g}, "
                   f"{transform.upper[i]:.4g}]" if fills
                   else f"is wider than {DEFAULT_MAX_RELATIVE_WIDTH:g} times its value {value:.4g}")
            notes.append(f"{n} is not identifiable from these data: its reported interval [{lo:.4g}, {hi:.4g}] "
                         f"(statistical and numerical error combined) {why}.")
    return out, notes


def use_population(settings: FitSettings, problem) -> bool:
    """Whether a fit runs its starts as a population (`FitSettings.population`; None: when the backend is
    not the CPU or the fit spans several processes). Sets the devices of `problem` (a `CalibrationProblem`
    or a joint problem)."""
    auto = jax.default_backend() != "cpu" or jax.process_count() > 1
    if settings.population is False or (settings.population is None and not auto):
        return False
    problem.use_devices(settings.devices)
    return True


def make_optimizer(name: str, broyden_steps: int = 0):
    """The `fitting` optimizer for "lm", "lbfgs" or "adam" (`broyden_steps`: LM's, see FitSettings)."""
    if name == "lm":
        return optim.LevenbergMarquardt(broyden_steps=int(broyden_steps))
    if name == "lbfgs":
        return optim.LBFGS()
    if name == "adam":
        return optim.Adam(learning_rate=ADAM_LEARNING_RATE, decay_steps=ADAM_DECAY)
    raise CalibrationError(f"optimizer must be one of {OPTIMIZERS}, got {name!r}")


def just_inside(value, lo: float, hi: float) -> float:
    """`value` moved inside [lo, hi] by 1e-9 of its span where it lies on or beyond a finite bound (the
    parameter transforms are open there)."""
    pad = 1e-9 * (hi - lo) if math.isfinite(hi - lo) else 0.0
    return min(max(float(value), lo + pad), hi - pad)


def make_starts(transform: optim.ParameterTransform, settings: FitSettings):
    """Initial guesses (S, p) in fitted coordinates and their unit-cube design (S, p): the centre of the
    starting ranges (log-centre for log parameters), with `settings.initial`'s values in place of the
    centre's, then S - 1 seeded Latin-hypercube points. The unit design of the first start is 0.5, and NaN
    (not drawn from the design) for a parameter set by `initial`."""
    ranges = {n: settings.start_range_of(n) for n in transform.names}
    first = np.array(transform.from_unit(np.full((1, transform.size), 0.5), ranges)[0], np.float64)
    unit0 = np.full(transform.size, 0.5)
    for i, n in enumerate(transform.names):
        if settings.initial and n in settings.initial:
            # a value on a bound (a fit that ended there) starts just inside it: the transform is open there
            first[i] = just_inside(settings.initial[n], *settings.bounds_of(n))
            unit0[i] = math.nan
    z = [np.asarray(transform.to_unconstrained(first))]
    unit = [unit0]
    if settings.starts > 1:
        zl, ul = optim.lhs_starts(transform, settings.starts - 1, settings.seed, sample_bounds=ranges)
        z.extend(list(zl))
        unit.extend(list(ul))
    return np.stack(z), np.stack(unit)


def default_log_path(out) -> Path:
    """The fit log beside a fit.json: fit.json -> fit.fitlog.h5."""
    out = Path(out)
    return out.with_name(out.stem + ".fitlog.h5")


def _path_settings(settings: FitSettings) -> dict:
    """The settings the optimizer's path depends on (not the uncertainty options, nor the iteration
    and time budgets, which a resumed fit may extend), as JSON values."""
    return json.loads(json.dumps({k: v for k, v in settings.to_dict().items()
                                  if k not in ("dx_check", "dx_refit", "level", "max_iter", "time_budget",
                                               "population", "devices")}))


# What a path setting was in logs written before it existed, where today's default differs.
_LEGACY_SETTINGS = {"broyden_steps": 0}


def _same_fit(logged: dict, fingerprint: dict) -> bool:
    """Whether a fit log's fingerprint (data, path settings, dx, floor phase) is this fit's. A setting that
    did not exist when the log was written matches when this fit gives it the behaviour the log's version
    had: its default (e.g. `resample` and `fracture`, off), or `_LEGACY_SETTINGS`'s value (exact
    Jacobians, `broyden_steps` 0); a log without a floor phase
    had the domain's rows, which the default `floor_phase` gives."""
    current = json.loads(json.dumps(fingerprint))
    logged = dict(logged)
    if "floor_phase" not in logged and "floor_phase" in current:
        logged["floor_phase"] = current["floor_phase"]  # the settings then match only at floor_phase None
    before = {**_path_settings(FitSettings()), **_LEGACY_SETTINGS}
    settings = dict(logged.get("settings", {}))
    for key, value in current["settings"].items():
        if key not in settings and value == before.get(key, object()):
            settings[key] = value
    return dict(logged, settings=settings) == current


def calibrate(data, settings: FitSettings | None = None, *, log=None, resume: bool = False,
              progress: Callable[[str], None] | None = None,
              callback: Callable[[optim.IterationInfo, dict], None] | None = None,
              problem: CalibrationProblem | None = None, start_z=None) -> FitResult:
    """Fit mu, sigma_y, eta and m (those not fixed) to silhouette data.

    Args:
      data: a `Silhouettes` or the path of a silhouette file; a list of several: a joint fit of one material
        to all of them (`fitting.joint.calibrate_joint`, which returns a `JointFitResult`).
      settings: `FitSettings` (default: Levenberg-Marquardt, DEFAULT_STARTS starts, defaults for the rest).
      log: path of the HDF5 fit log (every iteration of every start); None for no log.
      resume: continue the fit recorded in `log` (same data and settings required): finished starts are
        read back, the interrupted one continues from its last iteration, later ones run.
      progress: callable(str) receiving one line per iteration (iteration, loss, parameters), or None.
      callback: callable(IterationInfo, params dict) after every iteration; an exception it raises stops
        the fit (the log stays resumable).
      problem: a prebuilt `build_problem(data, settings)` (reuses its simulator; not used with
        `settings.resolved_frames`, whose rounds build their own, `fitting.horizon`).
      start_z: the first start in fitted coordinates (p,), e.g. an earlier fit's `FitResult.z`, in place of
        the one `settings.initial` gives (which rounds a parameter on a bound to just inside it).
    Returns a `FitResult`.
    """
    if isinstance(data, (list, tuple)):
        if len(data) > 1:
            from .joint import calibrate_joint
            return calibrate_joint(data, settings, log=log, resume=resume, progress=progress)
        data = data[0]
    wall0 = time.perf_counter()
    if not isinstance(data, Silhouettes):
        data = read_silhouettes(data)
    settings = (settings or FitSettings()).validate()
    if start_z is not None:
        start_z = np.asarray(start_z, np.float64)
        if start_z.shape != (len(settings.fitted),) or not np.all(np.isfinite(start_z)):
            raise CalibrationError(f"start_z must be {len(settings.fitted)} finite fitted coordinates "
                                   f"({', '.join(settings.fitted)}), got {start_z.tolist()}")
    if settings.resolved_frames:
        from .horizon import calibrate_resolved
        return calibrate_resolved(data, settings, log=log, resume=resume, progress=progress, callback=callback)
    say = progress or (lambda msg: None)
    if problem is None:
        problem = build_problem(data, settings)
    tr = problem.transform
    names = tr.names
    sim = problem.sim
    say(f"fit: {problem.scene.kind} {problem.scene.dim}D, dx = {problem.dx:.4g} m, "
        f"{int(np.sum(sim.state0.active))} particles, {len(problem.frames)} frames "
        f"(t = {problem.data.times[problem.frames[0]]:.4g}..{problem.data.times[problem.frames[-1]]:.4g} s"
        + (f"; {len(sim.frame_times)} simulated, gaps filled" if len(sim.frame_times) > len(problem.frames)
           else "") + f"), {sim.substeps} substeps/frame "
        f"of dt = {sim.dt:.3g} s, images {problem.cfg.height}x{problem.cfg.width} px at level "
        f"{problem.pixel_level} ({problem.cfg.pixel_size:.3g} m/px); fitting {', '.join(names)} with "
        f"{settings.optimizer}, {settings.starts} start(s)"
        + (f" within {settings.time_budget:.4g} s" if settings.time_budget is not None else "")
        + (f"; resampling every {sim.resample.every} substeps ({sim.state0.capacity} slots)" if sim.resample else "")
        + ("; fracture on" if sim.fracture else ""))

    starts, unit = make_starts(tr, settings)
    if start_z is not None:
        starts[0] = start_z
    optimizer = make_optimizer(settings.optimizer, settings.broyden_steps)
    n_starts = len(starts)
    population = None
    if n_starts > 1 and use_population(settings, problem):
        # A lone start left runs unpadded; two or more run in the population's full batch.
        population = optim.BatchOracle(problem.residual_and_jacobian_batch, n_starts, sizes=(1, n_starts))
        say(f"population: {n_starts} starts together, {n_starts * len(names)} jvp rollouts per batch on "
            f"{problem.devices} device(s)")

    def evaluate(z):
        return problem.residual_and_jacobian(z) if population is None else population(z)

    def on_iteration(info: optim.IterationInfo):
        theta = problem.params_of(info.x)
        say(f"[start {info.run + 1}/{n_starts}] iter {info.iteration:>3}  loss {info.loss:.6g}  "
            f"{_format_params(theta, names)}  ({info.time:.1f} s)")
        if callback is not None:
            callback(info, theta)

    def solve(x0, **kw):
        return optim.least_squares(evaluate, x0, optimizer, with_jac=True, max_iterations=settings.iterations,
                                     residual=problem.residual if population is None else None,
                                     ftol=FTOL, xtol=XTOL, callback=on_iteration, **kw)

    # What the optimizer's path depends on (not the uncertainty options, nor the iteration budget, which a
    # resumed fit may extend): a log is resumed only with these.
    fit_settings = _path_settings(settings)
    fingerprint = dict(data=_data_fingerprint(data), settings=fit_settings, dx=problem.dx,
                       floor_phase=problem.floor_phase)
    fitlog = None
    if log is not None:
        fitlog = optim.FitLog(log)
        logged = fitlog.file.attrs.get("calibration")
        if resume and logged is not None and not _same_fit(json.loads(logged), fingerprint):
            fitlog.close()
            raise CalibrationError(f"{log}: cannot resume: the log was written for other data or settings "
                                   f"(start afresh without --resume, or use another log)")
        fitlog.file.attrs["calibration"] = json.dumps(fingerprint)
        fitlog.flush()
    before = time.perf_counter() - wall0
    try:
        ms = optim.multistart(solve, starts, log=fitlog, resume=resume, seed=settings.seed, unit=unit,
                              max_time=settings.time_budget, population=population)
    except OSError as exc:  # h5py's error for a log damaged on disk
        raise CalibrationError(f"{log}: the fit log cannot be read or written ({exc}); start afresh without "
                               f"--resume, or use another log") from exc
    finally:
        if fitlog is not None:
            fitlog.close()
    after0 = time.perf_counter()
    # A population's starts share the wall clock; sequential starts add up.
    walls = [float(s.wall_time) for s in ms.solutions]
    optimization_wall = max(walls) if population is not None else sum(walls)

    # The lowest loss of any iterate of any start: Adam accepts every finite step, so its last
    # iterate need not be its best one (LM and L-BFGS only accept decreases).
    # (A start the time budget left unrun has no iterate; the first start always has one.)
    lows = [float(np.min(s.history.loss)) if len(s.history.loss) else math.inf for s in ms.solutions]
    best_index = int(np.argmin(lows))
    best = ms.solutions[best_index]
    k_best = int(np.argmin(best.history.loss))
    if k_best == len(best.history.loss) - 1:
        z_best, loss_best = np.asarray(best.x), float(best.loss)
        r, J = best.residual, best.jacobian
    else:
        z_best, loss_best = np.asarray(best.history.x[k_best]), float(best.history.loss[k_best])
        r = J = None
        say(f"best iterate: start {best_index + 1}, iteration {k_best} (loss {loss_best:.6g}), not the last one")
    if r is None or J is None or not np.all(np.isfinite(np.asarray(r))):
        r, J = problem.residual_and_jacobian(z_best)
    unc, n_eff = fit_uncertainty(problem, z_best, r, J, level=settings.level)
    params = problem.params_of(z_best)
    p = len(names)
    numerical = {n: 0.0 for n in names}
    dx_check = None
    dx_refit = DEFAULT_DX_REFIT[problem.scene.dim] if settings.dx_refit is None else int(settings.dx_refit)
    if unc is not None:
        stat = {n: tuple(float(v) for v in unc.interval[i]) for i, n in enumerate(names)}
        interval = dict(stat)
        stderr = {n: float(unc.stderr_theta[i]) for i, n in enumerate(names)}
        corr = np.asarray(unc.correlation)
        identifiable = {n: n not in unc.non_identifiable for n in names}
        notes = list(unc.messages)
        if settings.dx_check:
            say(f"discretization check: the residual and Jacobian at the optimum with dx = {problem.dx * DX_CHECK_RATIO:.4g} m"
                + (f", then up to {dx_refit} LM iterations there" if dx_refit else ""))
            details = {}
            err_z, shift_z = discretization_error(problem, z_best, J, details=details, r=r, refit=dx_refit,
                                                  progress=say)
            change = details.get("frame_change")
            both = combine_intervals(unc, err_z, tr)
            half_stat = 0.5 * (unc.interval_z[:, 1] - unc.interval_z[:, 0])
            half_num = numerical_half_width(tr, z_best, err_z)
            for i, n in enumerate(names):
                numerical[n] = float(half_num[i])
                interval[n] = tuple(float(v) for v in both[i])
            dx_check = dict(ratio=DX_CHECK_RATIO, order=DX_CHECK_ORDER, safety=GCI_SAFETY,
                            jacobian=DX_CHECK_JACOBIAN,
                            shift_z_fit_jacobian=[float(v) for v in details.get("shift_fit_jacobian", [math.nan] * p)],
                            shift_z_own_jacobians=[float(v) for v in details.get("shift_own_jacobians", [math.nan] * p)],
                            shift_z=[float(v) for v in shift_z], error_z=[float(v) for v in err_z],
                            refit=dx_refit,
                            shift_z_refit=([float(v) for v in details["shift_refit"]] if "shift_refit" in details
                                           else None),
                            refit_iterations=details.get("refit_iterations"), refit_reason=details.get("refit_reason"),
                            refit_loss=list(details["refit_loss"]) if "refit_loss" in details else None,
                            frame_change=None if change is None else [float(v) for v in change])
            limit = grid_limit_note(names, err_z, half_stat, problem.dx, problem.scene.dim,
                                    optimization_wall)
            if limit:
                notes.append(limit)
            uneven = None if change is None else uneven_frames_note(
                [float(data.times[i]) for i in problem.frames], change, problem.dx)
            if uneven:
                notes.append(uneven)
        if best.reason == optim.Reason.MAX_ITERATIONS:
            more = iteration_budget_note(best.history.loss, [tr.to_physical(x) for x in best.history.x], tr,
                                         best_index + 1, settings.iterations)
            if more:
                notes.append(more)
        split = separation_note([float(data.times[i]) for i in problem.frames], problem.masks, problem.weights)
        if split:
            notes.append(split)
        identifiable, more = judge_reported_intervals(interval, params, tr, identifiable)
        notes.extend(more)
        notes = tuple(notes)
    else:
        stat = interval = {n: (-math.inf, math.inf) for n in names}
        stderr = {n: math.nan for n in names}
        corr = np.full((p, p), np.nan)
        identifiable = {n: False for n in names}
        notes = ("The residual or its Jacobian is not finite at the optimum: no uncertainty could be computed.",)
    runs = []
    for i, s in enumerate(ms.solutions):
        runs.append(dict(start=problem.params_of(starts[i]), end=problem.params_of(s.x), loss=float(s.loss),
                         reason=s.reason.value, iterations=int(s.iterations), evaluations=int(s.evaluations),
                         wall_time=float(s.wall_time)))
    stopped = [i + 1 for i, s in enumerate(ms.solutions) if s.reason == optim.Reason.MAX_TIME and len(s.history.loss)]
    unstarted = [i + 1 for i, s in enumerate(ms.solutions) if s.reason == optim.Reason.MAX_TIME
                 and not len(s.history.loss)]
    if stopped or unstarted:
        said = []
        if stopped:
            said.append(f"stopped start(s) {', '.join(map(str, stopped))} before convergence")
        if unstarted:
            said.append(f"left start(s) {', '.join(map(str, unstarted))} unrun")
        notes = tuple(notes) + (f"The time budget ({settings.time_budget:.4g} s) {' and '.join(said)}: the result is "
                                f"the best point found so far. Continue with --resume (the fit log keeps every "
                                f"iteration) and a new or no budget.",)
    settings_out = dict(settings.to_dict(), dx=problem.dx, floor_phase=problem.floor_phase, ppc=FIT_PPC[problem.scene.dim]
                        if settings.ppc is None else int(settings.ppc),
                        dx_refit=dx_refit,
                        pixel_level=problem.pixel_level, pixel_size_fit=problem.cfg.pixel_size,
                        substeps_per_frame=sim.substeps, dt=sim.dt, fitted=list(names),
                        transforms=dict(zip(names, tr.kinds)), log=None if log is None else os.fspath(log),
                        dx_check=dx_check,
                        # the configs as the rollouts used them (resample's ppc resolved to the fit's)
                        resample=None if sim.resample is None else dataclasses.asdict(sim.resample),
                        fracture=None if sim.fracture is None else dataclasses.asdict(sim.fracture),
                        capacity=int(sim.state0.capacity))
    T, H, W = data.shape
    data_out = dict(frames=T, height=H, width=W, pixel_size=data.camera.pixel_size,
                    times=[float(t) for t in data.times], frames_used=[int(i) for i in problem.frames],
                    scene_kind=problem.scene.kind, dim=problem.scene.dim, source=data.source)
    result = FitResult(params=params, fitted=names, interval=interval, interval_statistical=stat,
                     numerical_error=numerical, stderr=stderr, correlation=corr,
                     identifiable=identifiable, notes=notes, loss=loss_best,
                     loss_history=np.asarray(best.history.loss), time_history=np.asarray(best.history.time),
                     runs=runs, best_run=best_index, best_iteration=k_best, reason=best.reason.value,
                     iterations=int(best.iterations), evaluations=int(best.evaluations), settings=settings_out,
                     data=data_out, n_effective=float(n_eff),
                     wall_time=before + optimization_wall + time.perf_counter() - after0,
                     uncertainty=unc, residual=np.asarray(r), z=np.asarray(z_best, np.float64))
    return _with_goodness_of_fit(problem, result)


# The unconverged-start note looks at the best start's last UNCONVERGED_TAIL iterations; a parameter whose
# position in its bounds (log span for log parameters) fell monotonically there to below NEAR_BOUND is
# named as heading for that bound.
UNCONVERGED_TAIL = 5
NEAR_BOUND = 0.1


def _bound_position(kind: str, lo: float, hi: float, values) -> np.ndarray | None:
    """Positions (0 at lo, 1 at hi) of physical `values` between two finite bounds, in log for log kinds;
    None for a kind without two bounds."""
    v = np.asarray(values, np.float64)
    if kind == "bounded":
        return (v - lo) / (hi - lo)
    if kind == "log_bounded":
        return np.log(v / lo) / math.log(hi / lo)
    return None


def iteration_budget_note(history_loss, history_theta, transform, start: int, budget: int) -> str | None:
    """A note for a best start that stopped at its iteration budget (`budget` iterations): how much its loss
    fell over its last UNCONVERGED_TAIL iterations and which parameters were heading for a bound there.
    history_loss: (K,) losses of its iterations; history_theta: (K, p) physical values of the fitted
    parameters (`transform` order); start: its 1-based number. None when the history is too short."""
    loss = np.asarray(history_loss, np.float64)
    theta = np.asarray(history_theta, np.float64)
    k = min(UNCONVERGED_TAIL, len(loss) - 1)
    if k < 1:
        return None
    drop = (loss[-k - 1] - loss[-1]) / loss[-k - 1] if loss[-k - 1] > 0 else 0.0
    heading = []
    for i, (name, kind, lo, hi) in enumerate(zip(transform.names, transform.kinds, transform.lower, transform.upper)):
        u = _bound_position(kind, float(lo), float(hi), theta[-k - 1:, i])
        if u is None:
            continue
        steps = np.diff(u)
        if np.all(steps < 0) and u[-1] < NEAR_BOUND:
            heading.append(f"{name} ({theta[-1, i]:.4g}) towards its lower bound {float(lo):g}")
        elif np.all(steps > 0) and u[-1] > 1.0 - NEAR_BOUND:
            heading.append(f"{name} ({theta[-1, i]:.4g}) towards its upper bound {float(hi):g}")
    note = (f"The best start ({start}) stopped at its iteration budget ({budget}) before converging: its loss fell "
            f"{100 * drop:.2g}% over its last {k} iterations")
    note += (", with " + " and ".join(heading) + "; the optimum lies further that way, where the data do not "
             "bound those parameters" if heading else "")
    return note + (". More iterations continue the fit from its log: the same command with --max-iter "
                   f"{2 * budget} --resume.")


def silhouette_mismatch(occupancy, masks, weights, pixel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, how far a simulated silhouette is from an observed one, over pixels of weight > 0.

    Args: occupancy (F, H, W) soft occupancy (inside where >= 1/2; NaN counts as outside), masks
    (F, H, W) observed (inside where >= 1/2), weights (F, H, W), pixel_size m.
    Returns (iou (F,), boundary (F,) m): the intersection over union (1 when both are empty), and the
    mean boundary displacement, the area of the symmetric difference over the observed perimeter (a
    band of width b along the boundary has area b x perimeter); the perimeter counts observed pixels
    with a 4-neighbour outside the mask, times pixel_size (that of the simulated silhouette when nothing
    is observed; 0 when both are empty).
    """
    occ = np.nan_to_num(np.asarray(occupancy, np.float64), nan=0.0)
    w = np.asarray(weights) > 0
    sim = (occ >= 0.5) & w
    obs = (np.asarray(masks, np.float64) >= 0.5) & w
    inter = np.sum(sim & obs, axis=(1, 2))
    union = np.sum(sim | obs, axis=(1, 2))
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)

    def perimeter(a):
        p = np.pad(a, ((0, 0), (1, 1), (1, 1)))
        inner = p[:, :-2, 1:-1] & p[:, 2:, 1:-1] & p[:, 1:-1, :-2] & p[:, 1:-1, 2:]
        return np.sum(a & ~inner, axis=(1, 2))

    per = np.where(obs.any(axis=(1, 2)), perimeter(obs), perimeter(sim)) * pixel_size
    diff = np.sum(sim ^ obs, axis=(1, 2)) * pixel_size ** 2
    boundary = np.where(diff > 0, diff / np.maximum(per, pixel_size), 0.0)
    return iou, boundary


def _with_goodness_of_fit(problem: CalibrationProblem, result: FitResult) -> FitResult:
    """The result with its per-frame silhouette IoU (read back from the stored residual, no rollout)
    and, when a frame is not reproduced, a note saying so and what to try."""
    iou, boundary = silhouette_mismatch(fitted_occupancy(problem, result), problem.masks, problem.weights,
                                        problem.cfg.pixel_size)
    notes = list(result.notes)
    ppc = FIT_PPC[problem.scene.dim] if problem.settings.ppc is None else int(problem.settings.ppc)
    limit = FRAME_BOUNDARY_SPACINGS * particle_spacing(problem.dx, ppc, problem.scene.dim)
    bad = np.nonzero(boundary > limit)[0]
    interval, identifiable = dict(result.interval), dict(result.identifiable)
    if len(bad):
        times = np.asarray(problem.data.times)[np.asarray(problem.frames)]
        k = int(np.argmax(boundary))
        tr = problem.transform
        interval = {n: (float(tr.lower[i]), float(tr.upper[i])) for i, n in enumerate(tr.names)}
        identifiable = {n: False for n in identifiable}
        notes.append(f"the fitted simulation does not reproduce {len(bad)} of {len(iou)} frames (silhouette boundaries "
                     f"more than {FRAME_BOUNDARY_SPACINGS:g} particle spacing = {limit:.3g} m apart on average; worst "
                     f"{boundary[k]:.3g} m, IoU {iou[k]:.2f}, at t = {times[k]:.4g} s). The intervals computed at this "
                     f"optimum assume a fit that reproduces the data, so each reported interval is the parameter's "
                     f"bounds and no parameter is reported identifiable (the interval at the optimum is kept as "
                     f"interval_local). Likely a local minimum (more --starts, another --optimizer) or an event such "
                     f"as a tear-off or a contact that the dx = {problem.dx:.3g} m grid places differently from the "
                     f"data (finer --dx).")
    return dataclasses.replace(result, frame_iou=tuple(float(v) for v in iou),
                               frame_boundary_error=tuple(float(v) for v in boundary), frame_boundary_limit=limit,
                               notes=tuple(notes), interval=interval, identifiable=identifiable,
                               interval_local=dict(result.interval))
