"""Joint fits: one material's parameters fitted to several recordings at once (`calibrate_joint`).

Each recording keeps its own scene, camera, frame times, grid (`build_problem` with the shared
settings) and nuisance parameters (its floor friction, when fitted). The fitted coordinates are the
material's, shared, followed by each recording's nuisance ones. The residual is the recordings'
residuals stacked, each divided by its noise scale s_i, the RMS of its own residual at the first
stage's optimum over its effective number of independent residuals (so a noisy recording does not
drown a clean one): stage 1 fits with s_i = 1 from the multi-start, stage 2 continues from its best
point with the scales. Intervals come from the stacked, weighted Jacobian; the discretization check
runs on every recording and moves the joint estimate by each one's information-weighted share.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from jaxfoam.guards import atomic_output

from . import optim
from .check import (check_error, combine_intervals, correlation_area, discretization_error, numerical_half_width)
from .driver import (_data_fingerprint, _path_settings, judge_reported_intervals, make_optimizer, make_starts,
                     silhouette_mismatch, use_population)
from .io import Silhouettes, read_silhouettes
from .problem import CalibrationProblem, build_problem, fit_transform
from .result import _format_params
from .settings import (CORRELATION_WINDOW_SUPPORTS, DEFAULT_DX_REFIT, DX_CHECK_RATIO, FIT_PPC,
                       FRAME_BOUNDARY_SPACINGS, FTOL, NUISANCE_FIELDS, XTOL, CalibrationError,
                       FitSettings)
from .silhouette import BSPLINE_SUPPORT, particle_spacing

# Relative difference of two recordings' densities (kg/m^3) that still counts as one material: the
# silhouettes fix stresses only relative to density.
DENSITY_TOLERANCE = 1e-6
# Stage-2 iterations (noise-scaled residuals) from the stage-1 optimum: the scales change the optimum
# little where the recordings agree, so a few LM steps suffice.
REWEIGHT_ITERATIONS = 10


def _nuisance_name(name: str, i: int) -> str:
    return f"{name}[{i}]"


class JointProblem:
    """Recordings bound to their simulators (one `CalibrationProblem` each) with shared material parameters.

    Attributes:
      problems: the per-recording problems.  names: the joint fitted names (material first, then
        "friction[i]" for recording i's nuisance).  transform: their `ParameterTransform`.
      index: per recording, the positions in the joint coordinates of its own fitted names (in its
        problem's transform order).  scales: per-recording noise scales s_i (1 until `set_scales`).
    """

    def __init__(self, problems: list, settings: FitSettings, labels=None):
        self.problems = list(problems)
        self.labels = [f"recording {i}" for i in range(len(problems))] if labels is None else [str(v) for v in labels]
        self.settings = settings
        material = tuple(n for n in settings.fitted if n not in NUISANCE_FIELDS)
        nuisance = tuple(n for n in settings.fitted if n in NUISANCE_FIELDS)
        names = list(material) + [_nuisance_name(n, i) for i in range(len(problems)) for n in nuisance]
        bounds = {n: settings.bounds_of(n) for n in material}
        bounds.update({_nuisance_name(n, i): settings.bounds_of(n) for i in range(len(problems)) for n in nuisance})
        self.names = tuple(names)
        self.material, self.nuisance = material, nuisance
        self.transform = optim.ParameterTransform.create(self.names, positive=[n for n in self.names if n != "m"],
                                                         bounds=bounds)
        self.index = []
        for i, pb in enumerate(self.problems):
            own = [self.names.index(n if n in material else _nuisance_name(n, i)) for n in pb.transform.names]
            self.index.append(np.asarray(own, int))
        self.scales = np.ones(len(self.problems))

    def split(self, z) -> list:
        """Each recording's fitted coordinates from the joint ones."""
        z = np.asarray(z, np.float64)
        return [z[idx] for idx in self.index]

    def set_scales(self, scales) -> None:
        self.scales = np.asarray(scales, np.float64)

    def parts(self, z):
        """Per recording (r_i (n_i,), J_i (n_i, p_i)), unscaled, at joint coordinates z."""
        out = []
        for pb, zi in zip(self.problems, self.split(z)):
            r, J = pb.residual_and_jacobian(jnp.asarray(zi, pb.sim.dtype))
            out.append((np.asarray(r, np.float64), np.asarray(J, np.float64)))
        return out

    def stack(self, parts):
        """The stacked residual (n,) and joint Jacobian (n, P) of per-recording parts, noise-scaled."""
        P = len(self.names)
        rows = [r / s for (r, _), s in zip(parts, self.scales)]
        blocks = []
        for (r, J), idx, s in zip(parts, self.index, self.scales):
            B = np.zeros((r.shape[0], P))
            B[:, idx] = J / s
            blocks.append(B)
        return np.concatenate(rows), np.concatenate(blocks)

    def residual_and_jacobian(self, z):
        return self.stack(self.parts(z))

    def residual(self, z):
        """The stacked, noise-scaled residual (n,) alone (as `residual_and_jacobian`'s first part)."""
        return np.concatenate([np.asarray(pb.residual(jnp.asarray(zi, pb.sim.dtype)), np.float64) / s
                               for pb, zi, s in zip(self.problems, self.split(z), self.scales)])

    def residual_and_jacobian_batch(self, Z):
        """(R (B, n), J (B, n, P)) at B joint points: each recording's batch as one batched program
        (`CalibrationProblem.residual_and_jacobian_batch`), stacked per point."""
        Z = np.asarray(Z, np.float64)
        per = [tuple(np.asarray(a, np.float64) for a in pb.residual_and_jacobian_batch(jnp.asarray(Z[:, idx], pb.sim.dtype)))
               for pb, idx in zip(self.problems, self.index)]
        rows = [self.stack([(R[b], J[b]) for R, J in per]) for b in range(Z.shape[0])]
        return np.stack([r for r, _ in rows]), np.stack([j for _, j in rows])

    def use_devices(self, devices) -> "JointProblem":
        for pb in self.problems:
            pb.use_devices(devices)
        return self

    def n_effective(self, i: int, r) -> float:
        """Recording i's effective number of independent residuals at its residual r (`fit_uncertainty`'s rule)."""
        pb = self.problems[i]
        keep = np.asarray(r) != 0
        window = int(math.ceil(BSPLINE_SUPPORT * pb.cfg.kernel_width / pb.cfg.pixel_size * CORRELATION_WINDOW_SUPPORTS))
        area = correlation_area(pb.pixel_images(r), window)
        return max(float(keep.sum()) / area, 1.0)

    def params_of(self, z) -> dict:
        theta = np.asarray(self.transform.to_physical(jnp.asarray(z)))
        out = {n: float(getattr(self.problems[0].base, n)) for n in ("mu", "sigma_y", "eta", "m")}
        out.update({n: float(theta[k]) for k, n in enumerate(self.names)})
        return out


def noise_scales(joint: JointProblem, parts) -> np.ndarray:
    """Per-recording noise scales s_i (geometric mean 1, so the loss keeps its size): the RMS of each
    recording's residual r_i over its effective number of independent residuals; parts: (r_i, J_i)."""
    scales = [math.sqrt(float(r @ r) / joint.n_effective(i, r)) if np.any(r) else 1.0
              for i, (r, _) in enumerate(parts)]
    return np.asarray(scales) / np.exp(np.mean(np.log(scales)))


def joint_uncertainty(joint: JointProblem, parts, z, level: float):
    """The Gauss-Newton `fitting.optim.Uncertainty` of the noise-scaled stacked residual at joint
    coordinates z, with the recordings' effective residual counts summed; parts: (r_i, J_i)."""
    r, J = joint.stack(parts)
    keep = (r != 0) | np.any(J != 0, axis=1)
    n_eff = sum(joint.n_effective(i, ri) for i, (ri, _) in enumerate(parts))
    n_eff = min(float(keep.sum()), max(n_eff, len(joint.names) + 1.0))
    return optim.gauss_newton_uncertainty(r[keep], J[keep], np.asarray(z, np.float64), joint.transform,
                                          n_eff=n_eff, level=level)


def information_shares(joint: JointProblem, parts) -> np.ndarray:
    """(recordings, parameters): each recording's share of the diagonal of the Fisher information
    J^T W J (columns sum to 1); parts: (r_i, J_i)."""
    info = np.stack([np.sum(np.square(J_i / s), axis=0) for (_, J_i), s in zip(parts, joint.scales)])
    full = np.zeros((len(parts), len(joint.names)))
    for i, idx in enumerate(joint.index):
        full[i, idx] = info[i]
    return full / np.maximum(full.sum(axis=0, keepdims=True), np.finfo(float).tiny)


def build_joint(datas, settings: FitSettings | None = None, windows=None) -> JointProblem:
    """Bind every recording to its simulator with the shared settings; the densities must agree.

    windows: per recording the time_window (s) of the frames it fits (None in the list: settings'), for
    instance the windows `fitting.horizon.calibrate_joint_resolved` measures; None: settings' for all.
    """
    settings = (settings or FitSettings()).validate()
    if settings.resolved_frames:
        raise CalibrationError("resolved_frames=True: the windows are measured by calibrate_joint (through "
                               "fitting.horizon.calibrate_joint_resolved), not fixed by build_joint; pass "
                               "resolved_frames=False with windows=[...] to bind measured windows")
    labels = [f"recording {i}" if isinstance(d, Silhouettes) else str(d) for i, d in enumerate(datas)]
    datas = [d if isinstance(d, Silhouettes) else read_silhouettes(d) for d in datas]
    if len(datas) < 2:
        raise CalibrationError(f"a joint fit needs at least 2 recordings, got {len(datas)}")
    rho = [float(settings.fixed.get("rho", d.load_scene().density)) for d in datas]
    if max(rho) - min(rho) > DENSITY_TOLERANCE * max(rho):
        raise CalibrationError(f"density: the recordings' scenes give {rho} kg/m^3; one material has one density "
                               f"(set it with --fix rho=..., or fit the recordings separately)")
    if windows is None:
        windows = [None] * len(datas)
    if len(windows) != len(datas):
        raise CalibrationError(f"windows: one time window per recording ({len(datas)}), got {len(windows)}")
    own = [settings if w is None else dataclasses.replace(settings, time_window=tuple(float(v) for v in w)).validate()
           for w in windows]
    return JointProblem([build_problem(d, s) for d, s in zip(datas, own)], settings, labels)


@dataclasses.dataclass(frozen=True)
class JointFitResult:
    """A joint fit's result. params/interval/identifiable as in `FitResult` over the joint names;
    information_share: name -> per-recording share of the diagonal of J^T W J (sums to 1); recordings: per
    recording its file/source, scale, loss, frame IoU and boundary error, whether it is reproduced."""

    params: dict
    fitted: tuple
    interval: dict
    interval_statistical: dict
    numerical_error: dict
    identifiable: dict
    notes: tuple
    loss: float
    information_share: dict
    recordings: list
    runs: list
    correlation: list
    wall_time: float
    settings: dict
    z: tuple = ()  # the optimum in the joint fitted coordinates (a later fit's start_z)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["format"], d["version"] = "jaxfoam-joint-fit", 1
        d["z"] = [float(v) for v in self.z]
        d["fitted"] = list(self.fitted)
        d["notes"] = list(self.notes)
        d["interval"] = {k: list(v) for k, v in self.interval.items()}
        d["interval_statistical"] = {k: list(v) for k, v in self.interval_statistical.items()}
        return d

    def write(self, path) -> None:
        with atomic_output(path) as tmp:
            Path(tmp).write_text(json.dumps(self.as_dict(), indent=1, allow_nan=True))

    def report(self) -> str:
        lines = [f"{'parameter':<12} {'value':>10}   {'95% interval':<24} " + "  ".join(
            f"share rec {i}" for i in range(len(self.recordings)))]
        for n in self.fitted:
            lo, hi = self.interval[n]
            share = "  ".join(f"{100 * s:10.1f}%" for s in self.information_share[n])
            flag = "" if self.identifiable[n] else "  (not identifiable)"
            lines.append(f"{n:<12} {self.params[n]:>10.5g}   [{lo:.4g}, {hi:.4g}]".ljust(50) + share + flag)
        for i, rec in enumerate(self.recordings):
            label = f"recording {i}" + ("" if rec["name"] == f"recording {i}" else f" ({rec['name']})")
            lines.append(f"{label}: loss {rec['loss']:.5g}, noise scale {rec['scale']:.3g}, "
                         f"IoU min {min(rec['frame_iou']):.3f}, " + ("reproduced" if rec["reproduced"]
                                                                     else "NOT reproduced"))
        lines.extend(self.notes)
        lines.append(f"joint loss {self.loss:.6g}; {self.wall_time:.1f} s wall")
        return "\n".join(lines)


def joint_grid_error(joint: JointProblem, parts, shifts) -> np.ndarray:
    """The numerical error (p,) of a joint estimate, fitted coordinates, from each recording's grid shift
    (`discretization_error`'s shift_z, that recording's coordinates): the shifts weighted by the
    recordings' noise-scaled Fisher information, extrapolated like a single fit's check (`check_error`)."""
    _, Jw = joint.stack(parts)
    moved = np.zeros(Jw.shape[1])
    for i, ((_, Ji), shift, idx) in enumerate(zip(parts, shifts, joint.index)):
        Ji = Ji / joint.scales[i]
        moved[idx] += Ji.T @ (Ji @ np.asarray(shift, np.float64))
    return check_error([np.linalg.lstsq(Jw.T @ Jw, moved, rcond=None)[0]])[0]


def joint_starts(joint: JointProblem, settings: FitSettings):
    """The multi-start's starting points in joint fitted coordinates and their unit-cube design, (S, P) each:
    the material's from `make_starts`; nuisance coordinates at each range's centre (or `initial`), the same
    for every recording (their design entries NaN)."""
    names, tr = joint.names, joint.transform
    joint_settings = dataclasses.replace(settings, fit_also=())
    base_starts, unit = make_starts(fit_transform(joint_settings), joint_settings)
    starts = []
    for zs in base_starts:
        full = np.zeros(len(names))
        full[:len(joint.material)] = zs[:len(joint.material)]
        for k, n in enumerate(names[len(joint.material):], start=len(joint.material)):
            base = n.split("[")[0]
            lo, hi = settings.start_range_of(base)
            value = float((settings.initial or {}).get(base, math.sqrt(lo * hi)))
            full[k] = float(tr.to_unconstrained({**{m: 1.0 for m in names}, n: value})[k])
        starts.append(full)
    starts = np.stack(starts)
    unit = np.concatenate([unit, np.full((len(starts), len(names) - unit.shape[1]), np.nan)], axis=1)
    return starts, unit


def calibrate_joint(datas, settings: FitSettings | None = None, *, log=None, resume: bool = False,
                    progress: Callable[[str], None] | None = None, joint: JointProblem | None = None,
                    start_z=None) -> JointFitResult:
    """Fit one material's parameters to several recordings (see the module docstring).

    Args as `calibrate`; datas: `Silhouettes` or paths (at least 2). The fit log holds the multi-start's
    runs (0 .. S-1) and the noise-scaled stage (run S), so a killed fit resumes. joint: a prebuilt
    `build_joint` (datas then unused). start_z: the first start in joint fitted coordinates (an earlier
    result's `z`). With `settings.resolved_frames` each recording fits the frames its grid resolves
    (`fitting.horizon.calibrate_joint_resolved`). max_iter=0 evaluates the start point only (the noise-scaled
    stage then runs no iterations either).
    """
    settings = (settings or FitSettings()).validate()
    if settings.resolved_frames:
        if joint is not None:
            raise CalibrationError("resolved_frames=True measures each recording's window and builds its own "
                                   "joint problems: pass the recordings, not a prebuilt joint")
        from .horizon import calibrate_joint_resolved
        return calibrate_joint_resolved(datas, settings, log=log, resume=resume, progress=progress)
    wall0 = time.perf_counter()
    say = progress or (lambda msg: None)
    if joint is None:
        joint = build_joint(datas, settings)
    if start_z is not None:
        start_z = np.asarray(start_z, np.float64)
        if start_z.shape != (len(joint.names),) or not np.all(np.isfinite(start_z)):
            raise CalibrationError(f"start_z must be {len(joint.names)} finite joint fitted coordinates "
                                   f"({', '.join(joint.names)}), got {start_z.tolist()}")
    tr, names = joint.transform, joint.names
    joint.set_scales(np.ones(len(joint.problems)))  # stage 1 weighs every recording alike
    for i, pb in enumerate(joint.problems):
        say(f"recording {i}: {pb.scene.kind} {pb.scene.dim}D, dx = {pb.dx:.4g} m, "
            f"{int(np.sum(pb.sim.state0.active))} particles, {len(pb.frames)} frames")
    say(f"joint fit of {', '.join(names)} with {settings.optimizer}, {settings.starts} start(s)")
    starts, unit = joint_starts(joint, settings)
    if start_z is not None:
        starts[0] = start_z
    optimizer = make_optimizer(settings.optimizer, settings.broyden_steps)
    population = None
    if len(starts) > 1 and use_population(settings, joint):
        population = optim.BatchOracle(joint.residual_and_jacobian_batch, len(starts), sizes=(1, len(starts)))
        say(f"population: {len(starts)} starts together on {joint.problems[0].devices} device(s)")

    def evaluate(z):
        return joint.residual_and_jacobian(z) if population is None else population(z)

    def on_iteration(stage):
        def cb(info):
            say(f"[{stage} {info.run + 1}] iter {info.iteration:>3}  loss {info.loss:.6g}  "
                f"{_format_params(joint.params_of(info.x), names)}  ({info.time:.1f} s)")
        return cb

    def solve(x0, **kw):
        return optim.least_squares(evaluate, x0, optimizer, with_jac=True,
                                   residual=joint.residual if population is None else None,
                                   max_iterations=settings.iterations, ftol=FTOL, xtol=XTOL,
                                   callback=on_iteration("start"), **kw)

    fingerprint = dict(data=[_data_fingerprint(pb.data) for pb in joint.problems], settings=_path_settings(settings),
                       dx=[pb.dx for pb in joint.problems], floor_phase=[pb.floor_phase for pb in joint.problems])
    fitlog = None
    if log is not None:
        fitlog = optim.FitLog(log)
        logged = fitlog.file.attrs.get("calibration")
        if resume and logged is not None and json.loads(logged) != json.loads(json.dumps(fingerprint)):
            fitlog.close()
            raise CalibrationError(f"{log}: cannot resume: the log was written for other recordings or settings")
        fitlog.file.attrs["calibration"] = json.dumps(fingerprint)
        fitlog.flush()
    try:
        ms = optim.multistart(solve, starts, log=fitlog, resume=resume, seed=settings.seed, unit=unit,
                              max_time=settings.time_budget, population=population)
        lows = [float(np.min(s.history.loss)) if len(s.history.loss) else math.inf for s in ms.solutions]
        best = ms.solutions[int(np.argmin(lows))]
        z1 = np.asarray(best.history.x[int(np.argmin(best.history.loss))])
        scales = noise_scales(joint, joint.parts(z1))
        joint.set_scales(scales)
        say("noise scales per recording: " + ", ".join(f"{s:.3g}" for s in scales))
        spent = time.perf_counter() - wall0
        budget = {} if settings.time_budget is None else {"max_time": max(1e-9, settings.time_budget - spent)}
        stage2 = optim.least_squares(joint.residual_and_jacobian, z1, optimizer, with_jac=True,
                                     residual=joint.residual,
                                     max_iterations=REWEIGHT_ITERATIONS if settings.iterations else 0, ftol=FTOL, xtol=XTOL,
                                     callback=on_iteration("scaled"), log=fitlog, run=len(starts), resume=resume,
                                     seed=settings.seed, **budget)
    finally:
        if fitlog is not None:
            fitlog.close()
    z = np.asarray(stage2.x)
    parts = joint.parts(z)
    unc = joint_uncertainty(joint, parts, z, settings.level)
    params = joint.params_of(z)
    stat = {n: tuple(float(v) for v in unc.interval[k]) for k, n in enumerate(names)}
    interval = dict(stat)
    numerical = {n: 0.0 for n in names}
    notes = list(unc.messages)
    share = information_shares(joint, parts)
    if settings.dx_check:
        refit = DEFAULT_DX_REFIT[joint.problems[0].scene.dim] if settings.dx_refit is None else int(settings.dx_refit)
        shifts = []
        for i, (pb, zi, (ri, Ji)) in enumerate(zip(joint.problems, joint.split(z), parts)):
            say(f"discretization check, recording {i}: dx = {pb.dx * DX_CHECK_RATIO:.4g} m")
            shifts.append(discretization_error(pb, zi, Ji, r=ri, refit=refit, progress=say)[1])
        err_z = joint_grid_error(joint, parts, shifts)
        both = combine_intervals(unc, err_z, tr)
        half = numerical_half_width(tr, z, err_z)
        for k, n in enumerate(names):
            numerical[n] = float(half[k])
            interval[n] = tuple(float(v) for v in both[k])
    identifiable = {n: n not in unc.non_identifiable for n in names}
    identifiable, more = judge_reported_intervals(interval, params, tr, identifiable)
    notes.extend(more)
    recordings = []
    for i, (pb, (ri, _)) in enumerate(zip(joint.problems, parts)):
        occ = _occupancy(pb, ri)
        iou, boundary = silhouette_mismatch(occ, pb.masks, pb.weights, pb.cfg.pixel_size)
        ppc = FIT_PPC[pb.scene.dim] if settings.ppc is None else int(settings.ppc)
        limit = FRAME_BOUNDARY_SPACINGS * particle_spacing(pb.dx, ppc, pb.scene.dim)
        reproduced = bool(np.all(boundary <= limit))
        if not reproduced:
            notes.append(f"recording {i}: the joint fit does not reproduce {int(np.sum(boundary > limit))} of "
                         f"{len(iou)} frames (mean boundary distance up to {float(np.max(boundary)):.3g} m, limit "
                         f"{limit:.3g} m); its share of the information may pull the others' parameters")
        recordings.append(dict(name=joint.labels[i], scale=float(joint.scales[i]), loss=0.5 * float(ri @ ri),
                               dx=pb.dx, frame_iou=[float(v) for v in iou],
                               frame_boundary_error=[float(v) for v in boundary], reproduced=reproduced,
                               kind=pb.scene.kind))
    runs = [dict(start=joint.params_of(starts[k]), end=joint.params_of(s.x), loss=float(s.loss), reason=s.reason.value,
                 iterations=int(s.iterations), wall_time=float(s.wall_time)) for k, s in enumerate(ms.solutions)]
    runs.append(dict(start=joint.params_of(z1), end=params, loss=float(stage2.loss), reason=stage2.reason.value,
                     iterations=int(stage2.iterations), wall_time=float(stage2.wall_time), stage="noise-scaled"))
    settings_out = dict(settings.to_dict(), dx=[pb.dx for pb in joint.problems], log=None if log is None else str(log))
    return JointFitResult(params=dict(params, rho=float(joint.problems[0].base.rho)),
                          fitted=names, interval=interval, interval_statistical=stat, numerical_error=numerical,
                          identifiable=identifiable, notes=tuple(notes), loss=float(stage2.loss),
                          information_share={n: [float(v) for v in share[:, k]] for k, n in enumerate(names)},
                          recordings=recordings, runs=runs, correlation=np.asarray(unc.correlation).tolist(),
                          wall_time=time.perf_counter() - wall0, settings=settings_out,
                          z=tuple(float(v) for v in z))


def _occupancy(pb: CalibrationProblem, r) -> np.ndarray:
    """The simulated soft silhouettes read back from recording pb's (unscaled) residual r (`fitted_occupancy`)."""
    F = len(pb.frames)
    w = np.asarray(pb.weights, np.float64)
    scale = np.sqrt(w / np.maximum(w.sum(axis=(1, 2), keepdims=True), 1e-12)) / math.sqrt(F)
    img = pb.pixel_images(r)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(w > 0, pb.masks + img / np.where(w > 0, scale, 1.0), np.nan)
