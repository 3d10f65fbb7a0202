"""Scoring a recovery fit against the truth it was made from (the study reads /truth; the fitter never
does): errors and goals, and the diagnostics that explain a miss (loss and per-frame fit at the truth,
the truth's shear rates, the fit's goodness of fit). Each diagnostic is cached beside the records."""
from __future__ import annotations

import json
import math

import numpy as np

from experiments.recovery.cases import (
    CASES,
    SCENES,
    WORK,
    SceneCase,
    case_id,
    data_path,
    truth_sets,
    write_cache,
)
from fitting import FitSettings
from fitting import read_silhouettes

# Goals of the issue: relative error for mu, sigma_y, eta; absolute for m.
GOALS = {"mu": ("rel", 0.10), "sigma_y": ("rel", 0.10), "eta": ("rel", 0.25), "m": ("abs", 0.1)}
# Plastic shear rates below this (1/s) count as not yielding (the elastic creep of the return map).
YIELD_RATE = 1e-3
SHEAR_FRAMES = 20  # frames of the truth rollout sampled for the shear-rate range


def shear_rates(c: SceneCase, k: int, quick: bool) -> dict:
    """The plastic shear rates the truth produces in a case (rolled out at dx_fit, SHEAR_FRAMES frames):
    the fraction of particle-frames that yield and the 10th/50th/90th percentiles of their rate (1/s).
    eta and m can only be separated when these span a wide range (stress sigma_y + eta gamma_dot^m).
    Cached in CASES/<case>_shear.json."""
    path = CASES / f"{case_id(c, k, quick)}_shear.json"
    if path.exists():
        return json.loads(path.read_text())
    from jaxfoam import Params, load_scene, simulate

    scene = load_scene(json.loads((SCENES / f"{c.name}.json").read_text()))
    t = truth_sets()[k]
    p = Params(mu=t["mu"], kappa=scene.kappa, sigma_y=t["sigma_y"], eta=t["eta"], m=t["m"], rho=scene.density)
    times = np.linspace(c.duration / SHEAR_FRAMES, c.duration, SHEAR_FRAMES)
    g = np.asarray(simulate(scene, p, times, c.dx_fit).frames["gamma_dot"]).ravel()
    y = g[g > YIELD_RATE]
    out = {"yielding": float(y.size / g.size),
           **{f"p{q}": float(np.percentile(y, q)) if y.size else 0.0 for q in (10, 50, 90)}}
    write_cache(path, out)
    return out


def _fit_problem(c: SceneCase, k: int, quick: bool):
    """(data, the fit's `CalibrationProblem`) of a case: its grid, time window and seed, LM settings."""
    from fitting import build_problem

    data = read_silhouettes(data_path(c, k, quick))
    return data, build_problem(data, FitSettings(dx=c.dx_fit, optimizer="lm", seed=0, time_window=c.window,
                                                 dtype=c.fit_dtype))


def truth_loss(c: SceneCase, k: int, quick: bool) -> float:
    """The fit's loss 0.5 |r|^2 at the true parameters (one rollout at dx_fit): below the fitted loss, the
    optimizer stopped short of the truth's basin; above it, the fit grid's bias (or the data's
    ambiguity) moved the optimum away from the truth. Cached in CASES/<case>_truthloss.json."""
    path = CASES / f"{case_id(c, k, quick)}_truthloss.json"
    if path.exists():
        return float(json.loads(path.read_text())["loss"])
    data, problem = _fit_problem(c, k, quick)
    theta = np.array([data.truth[n] for n in problem.transform.names])
    loss = problem.loss(problem.transform.to_unconstrained(theta))
    write_cache(path, {"loss": loss})
    return loss


def truth_frames(c: SceneCase, k: int, quick: bool) -> dict:
    """Per used frame, how far the fit grid's silhouette at the true parameters lies from the data: the
    fitter's goodness-of-fit measure (`fitting.silhouette_mismatch`, mean boundary distance, in
    particle spacings) and the frame times, s. Shows in which phase of a scene the fit grid and the data
    grid differ. One rollout at dx_fit; cached in CASES/<case>_truthframes.json."""
    path = CASES / f"{case_id(c, k, quick)}_truthframes.json"
    if path.exists():
        return json.loads(path.read_text())
    from fitting import silhouette_mismatch
    from fitting.settings import FIT_PPC
    from fitting.silhouette import particle_spacing

    data, problem = _fit_problem(c, k, quick)
    occ = problem.render({n: data.truth[n] for n in problem.transform.names})
    _, boundary = silhouette_mismatch(occ, problem.masks, problem.weights, problem.cfg.pixel_size)
    s = particle_spacing(problem.dx, FIT_PPC[problem.scene.dim], problem.scene.dim)
    out = {"times": [float(data.times[i]) for i in problem.frames], "boundary": [float(b / s) for b in boundary]}
    write_cache(path, out)
    return out


def goodness(r: dict) -> tuple[float, float]:
    """(smallest per-frame IoU, largest per-frame mean boundary distance in particle spacings) of a fit
    against its data: the fitter's goodness-of-fit check (`FitResult.frame_iou`, `.frame_boundary_error`,
    `.frame_boundary_limit`). Fits recorded before the check existed get it from one rollout at the
    fitted parameters, cached in CASES/<case>_<optimizer>_gof.json. NaNs if it cannot be computed."""
    from fitting.settings import FIT_PPC
    from fitting.silhouette import particle_spacing

    fit = r["fit"]
    dim = 3 if r["scene"].endswith("3d") else 2
    spacing = particle_spacing(r["dx_fit"], fit["settings"].get("ppc") or FIT_PPC[dim], dim)
    if fit.get("frame_boundary_error"):
        return float(min(fit["frame_iou"])), float(max(fit["frame_boundary_error"])) / spacing
    path = CASES / f"{r['case']}_{r['optimizer']}_gof.json"
    if not path.exists():
        try:
            from fitting import build_problem, silhouette_mismatch

            data = read_silhouettes(WORK / f"{r['case']}_data.h5")
            problem = build_problem(data, FitSettings(dx=r["dx_fit"], optimizer="lm", seed=0))
            theta = np.array([fit["params"][n] for n in problem.transform.names])
            iou, boundary = silhouette_mismatch(problem.render(theta), problem.masks, problem.weights,
                                                problem.cfg.pixel_size)
        except Exception:  # noqa: BLE001  (the table must not fail over a diagnostic)
            return float("nan"), float("nan")
        write_cache(path, {"frame_iou": [float(v) for v in iou],
                           "frame_boundary_error": [float(v) for v in boundary]})
    g = json.loads(path.read_text())
    return float(min(g["frame_iou"])), float(max(g["frame_boundary_error"])) / spacing


def param_error(value: float, truth: float, kind: str) -> float:
    """Relative (kind "rel") or absolute error of a fitted value."""
    return (value - truth) / truth if kind == "rel" else value - truth


def _ends(interval) -> tuple[float, float]:
    """An interval's ends as floats (a record writes an infinite end as "inf" / "-inf")."""
    return tuple(float(x) if not isinstance(x, str) else (math.inf if x == "inf" else -math.inf)
                 for x in interval)


def evaluate(fit: dict, truth: dict) -> dict:
    """Errors, goal flags and interval coverage of one fit against the truth."""
    out = {}
    for n, (kind, tol) in GOALS.items():
        v, t = fit["params"][n], truth[n]
        err = param_error(v, t, kind)
        lo, hi = _ends(fit["interval"][n])
        slo, shi = _ends(fit["interval_statistical"][n])
        inside = lo <= t <= hi
        ident = bool(fit["identifiable"][n])
        out[n] = {"value": v, "truth": t, "error": err, "kind": kind, "within_goal": abs(err) <= tol,
                  "inside": inside, "inside_statistical": slo <= t <= shi, "identifiable": ident,
                  "goal_met": (abs(err) <= tol) or ((not ident) and inside), "interval": [lo, hi]}
    return out
