"""The command lines of `jaxfoam fit`, `jaxfoam design`, `jaxfoam track` and `jaxfoam synth`: option parsers, settings from
arguments, signal handling. `jaxfoam.cli` adds these subcommands when it builds its parser."""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Mapping

import jax.numpy as jnp
import numpy as np

from jaxfoam import CFL, FIT_FIELDS, load_scene
from jaxfoam.fracture import FractureConfig
from jaxfoam.guards import check_output, missing_modules
from jaxfoam.resample import ResampleConfig

from . import optim
from .io import read_silhouettes
from .settings import (CalibrationError, DEFAULT_BOUNDS, DEFAULT_BROYDEN_STEPS, DEFAULT_DX_REFIT, DEFAULT_MAX_ITER,
                       DEFAULT_STARTS, FIT_CELLS,
                       FIT_DTYPE, FIT_PPC, FitSettings, KNOWN_INPUTS, NUISANCE_FIELDS, OPTIMIZERS)
from .problem import build_problem
from .driver import calibrate, default_log_path
from .plots import plot_loss, plot_overlay
from .synth import parse_params, synthesize
from .track import BACKGROUNDS, CLOSE_RADIUS, EDGES, OPEN_RADIUS, PLATE_MARGIN, POLARITIES, track_video
from .video import IMAGE_EXTENSIONS, average_pool


def _parse_assignments(text: str, label: str) -> dict:
    out = {}
    for item in filter(None, (s.strip() for s in str(text).split(","))):
        if "=" not in item:
            raise CalibrationError(f"--{label}: expected name=value pairs separated by commas, got {item!r}")
        k, v = (s.strip() for s in item.split("=", 1))
        if k == "density":
            k = "rho"
        out[k] = v
    return out


def parse_fixed(text: str | None) -> dict:
    """'kappa=3000,m=0.5' -> {'kappa': 3000.0, 'm': 0.5} (names from FIT_FIELDS, kappa, rho/density)."""
    if not text:
        return {}
    return _parse_numbers(text, "fix", FIT_FIELDS + KNOWN_INPUTS)


def _parse_numbers(text: str, label: str, allowed) -> dict:
    """'a=1,b=2' -> {'a': 1.0, 'b': 2.0} for names in `allowed`; errors name the option --label."""
    out = {}
    for k, v in _parse_assignments(text, label).items():
        if k not in allowed:
            raise CalibrationError(f"--{label}: unknown parameter {k!r}; expected one of {tuple(allowed)}")
        try:
            out[k] = float(v)
        except ValueError as exc:
            raise CalibrationError(f"--{label}: {k} must be a number, got {v!r}") from exc
    return out


_DURATION_UNITS = {"": 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}


def parse_duration(text: str | None) -> float | None:
    """The --time-budget option: '900', '900s', '15m', '15min' or '1.5h' -> seconds (None when absent)."""
    if text is None:
        return None
    t = str(text).strip().lower()
    number = t.rstrip("abcdefghijklmnopqrstuvwxyz")
    unit = t[len(number):]
    try:
        seconds = float(number) * _DURATION_UNITS[unit]
    except (ValueError, KeyError):
        raise CalibrationError(f"--time-budget: expected a duration such as 900, 900s, 15m or 1.5h, "
                               f"got {text!r}") from None
    if not (math.isfinite(seconds) and seconds > 0):
        raise CalibrationError(f"--time-budget: must be a positive duration, got {text!r}")
    return seconds


def parse_window(text: str | None) -> tuple | None:
    """The --time-window option: 'T_LO:T_HI' in s -> (T_LO, T_HI) (None when absent)."""
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in str(text).split(":"))
    except ValueError:
        raise CalibrationError(f"--time-window: expected T_LO:T_HI in s, e.g. 0:0.8, got {text!r}") from None
    return (lo, hi)


def parse_fit_also(text: str | None) -> tuple:
    """'friction' -> ('friction',): the scene parameters `--fit-also` fits beside the material."""
    if not text:
        return ()
    names = tuple(n.strip() for n in str(text).split(",") if n.strip())
    for n in names:
        if n not in NUISANCE_FIELDS:
            raise CalibrationError(f"--fit-also: unknown parameter {n!r}; expected some of {NUISANCE_FIELDS}")
    return names


def parse_start(text: str | None, fixed: Mapping | None = None, fit_also: tuple = ()) -> dict | None:
    """The first start's guess from `--start`: 'mu=150,sigma_y=30' -> {'mu': 150.0, 'sigma_y': 30.0}, or the
    path of a fit.json whose fitted parameters are taken (those held fixed in this fit are left out), e.g.
    a fit of the same data on a coarser grid. None when not given."""
    if not text:
        return None
    names = FIT_FIELDS + tuple(fit_also)
    path = Path(text)
    if "=" not in text and path.suffix == ".json":
        try:
            params = json.loads(path.read_text(encoding="utf-8"))["params"]
            out = {k: float(v) for k, v in params.items() if k in names and k not in (fixed or {})}
        except FileNotFoundError:
            raise CalibrationError(f"--start: no such fit result {text!r}") from None
        except (ValueError, KeyError, TypeError, AttributeError, OSError) as exc:  # JSON, UTF-8, a directory
            raise CalibrationError(f"--start: {text!r} is not a fit result (a fit.json with 'params'): {exc}") from None
        if not all(math.isfinite(v) for v in out.values()):
            raise CalibrationError(f"--start: {text!r} holds non-finite parameters {out}")
        if not out:
            raise CalibrationError(f"--start: {text!r} holds none of the fitted parameters {names}")
        return out
    return _parse_numbers(text, "start", names)


def parse_bounds(text: str | None) -> dict:
    """'mu=50:400,m=0.3:1' -> {'mu': (50.0, 400.0), 'm': (0.3, 1.0)}."""
    if not text:
        return {}
    out = {}
    for k, v in _parse_assignments(text, "bounds").items():
        if k not in FIT_FIELDS + NUISANCE_FIELDS:
            raise CalibrationError(f"--bounds: unknown parameter {k!r}; expected one of {FIT_FIELDS + NUISANCE_FIELDS}")
        try:
            lo, hi = (float(s) for s in v.split(":"))
        except ValueError as exc:
            raise CalibrationError(f"--bounds: {k} needs lo:hi, got {v!r}") from exc
        out[k] = (lo, hi)
    return out


def parse_feature(text: str | None, kind, label: str):
    """The --resample / --fracture option: None (flag absent) -> None; '' (flag alone) -> kind() with its
    defaults; 'every=10,sparse_fraction=0.4' -> kind(every=10, sparse_fraction=0.4) (integer fields parsed
    as int, the rest as float, 'none' as None)."""
    if text is None:
        return None
    types = {f.name: str(f.type) for f in dataclasses.fields(kind)}
    out = {}
    for k, v in _parse_assignments(text, label).items():
        if k not in types:
            raise CalibrationError(f"--{label}: unknown field {k!r}; expected some of {sorted(types)}")
        try:
            out[k] = None if v.lower() == "none" else (int(v) if types[k].startswith("int") else float(v))
        except ValueError as exc:
            raise CalibrationError(f"--{label}: {k} must be a {types[k].split()[0]}, got {v!r}") from exc
    return kind(**out)


def add_fit_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `fit` subcommand to an argparse subparsers object (runs via args.func(args))."""
    ap = subparsers.add_parser(
        "fit", help="calibrate mu, sigma_y, eta, m from silhouette data",
        description="Fit the Herschel-Bulkley parameters (mu Pa, sigma_y Pa, eta Pa s^m, m) of the scene in a "
                    "silhouette file. Density and kappa are known inputs from the scene. Writes fit.json, a loss "
                    "curve (<out>_loss.png), observed vs simulated silhouettes (<out>_overlay.png) and an HDF5 fit "
                    "log of every iteration (<out>.fitlog.h5) that --resume continues.")
    from jaxfoam.cli import add_budget_options, float_in, int_at_least, positive_float

    ap.add_argument("data", nargs="+", help="silhouette file (.h5); several files of one material: a joint fit")
    ap.add_argument("--out", required=True, help="result file (.json)")
    ap.add_argument("--dx", type=positive_float, default=None,
                    help=f"grid spacing of the fit, m (default: the largest domain extent / {FIT_CELLS[2]} in 2D, "
                         f"/ {FIT_CELLS[3]} in 3D)")
    ap.add_argument("--ppc", type=int_at_least(1), default=None,
                    help=f"particles per cell (default {FIT_PPC[2]} in 2D, {FIT_PPC[3]} in 3D)")
    ap.add_argument("--floor-phase", type=float_in(0.0, 1.0, hi_open=True, unit="cells"), default=None,
                    help="cells from the node row below the floor up to the floor on the fit's grid (default: rows "
                         "at the domain's lower bound + k dx, so a floor there lies on a row)")
    ap.add_argument("--optimizer", choices=OPTIMIZERS, default="lm", help="default lm (Levenberg-Marquardt)")
    ap.add_argument("--fix", default=None,
                    help="hold parameters fixed, e.g. m=0.5,eta=10; kappa=.. or rho=.. override the scene's values")
    ap.add_argument("--bounds", default=None, help="bounds lo:hi, e.g. mu=20:1000,m=0.3:1.2 (defaults: "
                    + ", ".join(f"{k}={lo:g}:{hi:g}" for k, (lo, hi) in DEFAULT_BOUNDS.items()) + ")")
    ap.add_argument("--fit-also", default=None, metavar="NAME,...",
                    help="scene parameters to fit beside the material, with their own intervals: friction (the "
                         "floor's Coulomb coefficient; default: the scene's value, known)")
    ap.add_argument("--starts", type=int_at_least(1), default=DEFAULT_STARTS, help=f"multi-start guesses (default {DEFAULT_STARTS})")
    ap.add_argument("--start", default=None, metavar="NAME=VALUE,...|FIT.json",
                    help="the first start's guess, e.g. mu=150,sigma_y=30, or a fit.json to continue from (e.g. a "
                         "fit of the same data on a coarser --dx); default: the centre of the start ranges")
    ap.add_argument("--max-iter", type=int_at_least(0), default=None,
                    help="iterations per start (default " + ", ".join(f"{k} {v}" for k, v in DEFAULT_MAX_ITER.items())
                    + ")")
    ap.add_argument("--broyden-steps", type=int_at_least(0), default=None, metavar="K",
                    help="lm: trials evaluate the residuals alone and the Jacobian is updated by Broyden's rule, "
                         "evaluated exactly every K accepted steps, after a rejected trial and before stopping; "
                         f"0: the exact Jacobian at every trial (default {DEFAULT_BROYDEN_STEPS}; starts in turn only)")
    ap.add_argument("--time-window", default=None, metavar="T_LO:T_HI",
                    help="fit only the frames with times in [T_LO, T_HI] s, e.g. 0:0.8 (default: all)")
    ap.add_argument("--resolved-frames", action="store_true",
                    help="fit only the frames before the first one the grid does not resolve (its silhouette "
                         "moves more than a particle spacing at dx / sqrt 2), found at the start and at each "
                         "optimum and refitted until the window stays put")
    ap.add_argument("--time-budget", default=None, metavar="DURATION",
                    help="wall-time budget of the optimization, all starts together: 900 (s), 15m or 1.5h "
                         "(default: none). The best point found is reported when it runs out; --resume continues")
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="seed of the starts and particle sampling (default 0)")
    ap.add_argument("--pixel-level", type=int_at_least(0), default=None,
                    help="compare at 2^level larger pixels (default: the coarsest not larger than the particle spacing)")
    ap.add_argument("--dtype", choices=("float32", "float64"), default=FIT_DTYPE,
                    help=f"precision (default {FIT_DTYPE})")
    ap.add_argument("--log", default=None, help="fit log path (default <out>.fitlog.h5 beside the result)")
    ap.add_argument("--resume", action="store_true", help="continue the fit recorded in the fit log")
    ap.add_argument("--no-dx-check", action="store_true",
                    help="skip the discretization check (intervals then hold the statistical part only)")
    ap.add_argument("--dx-refit", type=int_at_least(0), default=None, metavar="N",
                    help=f"LM iterations the discretization check runs on its finer grid from the optimum; the move "
                         f"they measure counts beside its first-order estimates (default {DEFAULT_DX_REFIT[2]} in 2D, "
                         f"{DEFAULT_DX_REFIT[3]} in 3D; 0: the estimates only; each iteration costs one or two "
                         f"Jacobians on that grid)")
    ap.add_argument("--resample", nargs="?", const="", default=None, metavar="FIELD=VALUE,...",
                    help="particle resampling in every rollout of the fit (default off); alone it uses the "
                         "ResampleConfig defaults (every=20 substeps, target ppc = the fit's ppc, ...), or "
                         "override fields, e.g. --resample every=10,sparse_fraction=0.4")
    ap.add_argument("--fracture", nargs="?", const="", default=None, metavar="FIELD=VALUE,...",
                    help="the fracture stage in every substep of the fit (default off); alone it uses the "
                         "FractureConfig defaults (density_ratio 0.2 in 2D, 0.12 in 3D), or e.g. "
                         "--fracture density_ratio=0.15")
    ap.add_argument("--population", choices=("auto", "on", "off"), default="auto",
                    help="run the starts together, each step of all of them one batched evaluation of their "
                         "Jacobians (same results as in turn); auto: on when the backend is not the CPU or "
                         "the fit spans several processes (default auto)")
    ap.add_argument("--devices", type=int_at_least(1), default=None, metavar="N",
                    help="devices the population's batch is split over (default: all; on the CPU, N > 1 "
                         "makes N host devices that share the cores)")
    ap.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                    help="a fit over several processes (hosts): process 0's address; every process runs the same "
                         "command with its --process-id, and the population's batch is split over all their "
                         "devices (docs/calibrate.md)")
    ap.add_argument("--num-processes", type=int_at_least(1), default=None, metavar="N",
                    help="processes of a --coordinator fit")
    ap.add_argument("--process-id", type=int_at_least(0), default=None, metavar="I",
                    help="this process's index in a --coordinator fit (0 writes the results; each keeps its own log)")
    ap.add_argument("--no-plots", action="store_true", help="skip the pictures")
    add_budget_options(ap)
    ap.set_defaults(func=run_fit)
    return ap


def settings_from_args(args) -> FitSettings:
    """The validated `FitSettings` of parsed `fit` arguments."""
    fixed = parse_fixed(args.fix)
    fit_also = parse_fit_also(getattr(args, "fit_also", None))
    return FitSettings(dx=args.dx, ppc=args.ppc, floor_phase=args.floor_phase, optimizer=args.optimizer, fixed=fixed,
                       bounds=parse_bounds(args.bounds), starts=args.starts, fit_also=fit_also,
                       initial=parse_start(getattr(args, "start", None), fixed, fit_also), max_iter=args.max_iter,
                       broyden_steps=(DEFAULT_BROYDEN_STEPS if getattr(args, "broyden_steps", None) is None
                                      else args.broyden_steps),
                       time_budget=parse_duration(getattr(args, "time_budget", None)),
                       time_window=parse_window(getattr(args, "time_window", None)),
                       resolved_frames=bool(getattr(args, "resolved_frames", False)), seed=args.seed,
                       pixel_level=args.pixel_level, dtype=args.dtype,
                       dx_check=not args.no_dx_check, dx_refit=args.dx_refit,
                       resample=parse_feature(getattr(args, "resample", None), ResampleConfig, "resample"),
                       fracture=parse_feature(getattr(args, "fracture", None), FractureConfig, "fracture"),
                       population={"auto": None, "on": True, "off": False}[getattr(args, "population", "auto")],
                       devices=getattr(args, "devices", None),
                       ).validate()


class _Terminated(KeyboardInterrupt):
    """SIGTERM (a job scheduler's or `timeout`'s stop) delivered to a running fit."""


@contextlib.contextmanager
def _terminate_as_interrupt():
    """Within the block, SIGTERM raises `_Terminated` like Ctrl-C raises KeyboardInterrupt, so a stopped
    fit ends with a message on how to resume instead of silently (main thread only; a no-op elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise _Terminated

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def request_devices(n: int | None) -> None:
    """Make `n` local devices available to this process: on the CPU backend, n host devices (JAX's
    jax_num_cpu_devices, which must be set before the backend starts). Raises CalibrationError when
    fewer than n exist afterwards."""
    if n is None or n <= 1:
        return
    import jax
    try:
        jax.config.update("jax_num_cpu_devices", int(n))
    except RuntimeError:  # the backend already started (a notebook); the count is what it is
        pass
    have = len(jax.devices())
    if have < n:
        raise CalibrationError(f"--devices {n}: this process has {have} {jax.default_backend()} device(s); on the "
                               f"CPU start Python with XLA_FLAGS=--xla_force_host_platform_device_count={n}")


def start_processes(args) -> int:
    """Join a multi-process fit (`jax.distributed.initialize`) when --coordinator is given; returns this
    process's index (0 without one). Raises CalibrationError for an incomplete or inconsistent set."""
    coordinator = getattr(args, "coordinator", None)
    n, i = getattr(args, "num_processes", None), getattr(args, "process_id", None)
    if coordinator is None:
        if n is not None or i is not None:
            raise CalibrationError("--num-processes and --process-id need --coordinator HOST:PORT")
        return 0
    if n is None or i is None:
        raise CalibrationError("--coordinator needs --num-processes N and --process-id I (0 .. N-1)")
    if not 0 <= i < n:
        raise CalibrationError(f"--process-id must be in [0, {n - 1}] for --num-processes {n}, got {i}")
    import jax
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=n, process_id=i)
    return i


def run_fit(args) -> int:
    """Run the `fit` subcommand from parsed arguments; returns the exit status."""
    settings = settings_from_args(args)
    paths = list(args.data) if isinstance(args.data, (list, tuple)) else [args.data]
    if len(paths) > 1:
        return run_joint_fit(args, settings, paths)
    args.data = paths[0]
    rank, out, log = _fit_outputs(args, settings)
    check_output(out, "--out", {"the data": args.data})
    check_output(log, "--log", {"the data": args.data, "--out": out})
    data = read_silhouettes(args.data)
    if args.resume and log.exists():
        optim.FitLog(log, mode="r").close()  # a file that is not a fit log is refused before any work
    plots = not args.no_plots
    if plots and missing_modules("matplotlib"):
        print("jaxfoam fit: note: matplotlib is not installed, so the pictures are skipped (install the viz "
              "extra: pip install 'jaxfoam[viz]')", flush=True)
        plots = False
    problem = build_problem(data, settings, max_particles=args.max_particles, max_substeps=args.max_substeps)
    if not args.resume:
        from .horizon import RESOLVED_MAX_ROUNDS, round_log
        for old in [log] + [round_log(log, k) for k in range(RESOLVED_MAX_ROUNDS)]:
            if old.exists():
                old.unlink()  # a fresh fit: old logs of this name are replaced

    status, result = _run_logged_fit(
        lambda say: calibrate(data, settings, log=log, resume=args.resume, progress=say, problem=problem), log, out, rank)
    if result is None:
        return status
    if plots:
        loss_png = out.with_name(out.stem + "_loss.png")
        overlay_png = out.with_name(out.stem + "_overlay.png")
        plot_loss(result, loss_png)
        if settings.resolved_frames:  # the overlay shows the frames fitted
            window = result.settings["time_window"]
            problem = build_problem(data, dataclasses.replace(settings, resolved_frames=False, time_window=None
                                    if window is None else tuple(window)), max_particles=args.max_particles,
                                    max_substeps=args.max_substeps)
        plot_overlay(problem, result, overlay_png)
        print(f"wrote {loss_png} and {overlay_png}")
    return 0


def run_joint_fit(args, settings: FitSettings, paths) -> int:
    """`jaxfoam fit a.h5 b.h5 ...`: one material fitted to every recording (`fitting.joint`)."""
    from .joint import build_joint, calibrate_joint
    rank, out, log = _fit_outputs(args, settings)
    for path in paths:
        check_output(out, "--out", {"the data": path})
        check_output(log, "--log", {"the data": path, "--out": out})
    from .horizon import RESOLVED_MAX_ROUNDS, round_log
    # with --resolved-frames the rounds build their own joint problems (a window per recording)
    joint = None if settings.resolved_frames else build_joint(paths, settings)
    if not args.resume:
        for old in [log] + [round_log(log, k) for k in range(RESOLVED_MAX_ROUNDS)]:
            if old.exists():
                old.unlink()  # a fresh fit: old logs of this name are replaced
    return _run_logged_fit(lambda say: calibrate_joint(paths, settings, log=log, resume=args.resume, progress=say,
                                                       joint=joint), log, out, rank)[0]


def _fit_outputs(args, settings: FitSettings):
    """Join the processes and devices a fit asks for; (this process's index, the result path, its log path:
    process i > 0 keeps `<log stem>.p<i>.h5`)."""
    rank = start_processes(args)
    request_devices(settings.devices)
    out = Path(args.out)
    log = Path(args.log) if args.log else default_log_path(out)
    if rank:
        log = log.with_name(f"{log.stem}.p{rank}{log.suffix}")
    return rank, out, log


def _run_logged_fit(run, log: Path, out: Path, rank: int):
    """Run `run(say)`, a fit that keeps its log at `log`, with Ctrl-C and SIGTERM turned into a stop that says
    how to resume; on process 0 write its result to `out` and print its report. Returns (exit status,
    the result, or None when it was stopped or this is not process 0)."""
    lock = threading.Lock()

    def say(msg):
        with lock:  # a population's starts report from their own threads
            print(msg, flush=True)

    try:
        with _terminate_as_interrupt():
            result = run(say)
    except KeyboardInterrupt as exc:
        sys.stderr.write(f"\njaxfoam fit: {'terminated' if isinstance(exc, _Terminated) else 'interrupted'}; the fit "
                         f"log {log} keeps every finished iteration: run the same command with --resume to "
                         f"continue\n")
        return (143 if isinstance(exc, _Terminated) else 130), None
    if rank:
        print(f"process {rank}: the fit ended (process 0 writes {out}; this process's log is {log})")
        return 0, None
    result.write(out)
    print(result.report())
    print(f"wrote {out} (fit log {log})")
    return 0, result


# ----------------------------------------------------------------------------------------------
# jaxfoam design
# ----------------------------------------------------------------------------------------------

def add_design_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `design` subcommand to an argparse subparsers object (runs via args.func(args))."""
    from jaxfoam.cli import float_in, int_at_least, positive_float
    from .design import (DEFAULT_DURATION, DEFAULT_FPS, DEFAULT_LEVELS, DEFAULT_POINTS, DEFAULT_SPREAD,
                         DERIVED_VARIABLES, RECORDING_VARIABLES, MISFITS, ROBUST, SAMPLINGS)

    named = "; ".join([f"{k} ({u})" for k, u in RECORDING_VARIABLES.items()]
                      + [f"{k} ({u.split(',')[0]})" for k, u in DERIVED_VARIABLES.items()])
    ap = subparsers.add_parser(
        "design", help="rank candidate recordings by the intervals a fit of them would give",
        description="Predict, for every combination of the --vary values, the 95%% intervals a fit of that "
                    "recording (with the --with recordings already made) would report, at the guess and at "
                    "parameter points around it; write the ranking, the best candidate's scene and a chart. "
                    "See docs/calibrate.md, 'Designing the next recording'.")
    ap.add_argument("scene", help="scene JSON file (initial_shape box or ellipse)")
    ap.add_argument("--guess", required=True, help="mu=..,sigma_y=..,eta=..,m=.. (Pa, Pa, Pa s^m, -): the expected material")
    ap.add_argument("--vary", action="append", required=True, metavar="NAME=LO:HI[:N]|NAME=V1,V2,...",
                    help=f"a design variable and its values (repeat for more): {named}; or a path to a number in "
                         f"the scene, e.g. plate.motion.frequency")
    ap.add_argument("--with", dest="with_data", nargs="+", default=[], metavar="DATA.h5",
                    help="recordings already made of the same material (joint with every candidate)")
    ap.add_argument("--out", required=True, help="result file (.json); the best scene goes to <out>.scene.json")
    ap.add_argument("--levels", type=int_at_least(2), default=DEFAULT_LEVELS,
                    help=f"values of a LO:HI range (default {DEFAULT_LEVELS})")
    ap.add_argument("--points", type=int_at_least(1), default=DEFAULT_POINTS,
                    help=f"parameter points per candidate, the guess first (default {DEFAULT_POINTS})")
    ap.add_argument("--spread", type=float_in(1.0, lo_open=True), default=DEFAULT_SPREAD,
                    help=f"the points' factor from the guess (m: +-0.15) (default {DEFAULT_SPREAD})")
    ap.add_argument("--robust", choices=ROBUST, default="worst", help="over the points (default worst)")
    ap.add_argument("--sampling", choices=SAMPLINGS, default="same",
                    help="render the predicted recording from the fit's own particle sampling or from another "
                         "(default same)")
    ap.add_argument("--misfit", choices=MISFITS, default="auto",
                    help="the predicted recording's misfit: the renderer's noise, or at least that of the --with "
                         "recordings at the guess (model error like theirs); auto: with when --with is given "
                         "(default auto)")
    ap.add_argument("--dx-check", action="store_true",
                    help="predict the intervals a fit reports: add the discretization check's numerical error, "
                         "predicted at the guess from one more Jacobian per recording on a grid 0.71x finer")
    ap.add_argument("--duration", type=positive_float, default=DEFAULT_DURATION,
                    help=f"recorded time, s, unless varied (default {DEFAULT_DURATION:g})")
    ap.add_argument("--fps", type=positive_float, default=DEFAULT_FPS,
                    help=f"frame rate, 1/s, unless varied (default {DEFAULT_FPS:g})")
    ap.add_argument("--pixel-size", type=positive_float, default=None, help="m per pixel unless varied (default dx / 2)")
    ap.add_argument("--dx", type=positive_float, default=None, help="grid spacing of the predicted fits, m (default: the fit's)")
    ap.add_argument("--ppc", type=int_at_least(1), default=None, help="particles per cell (default: the fit's)")
    ap.add_argument("--floor-phase", type=float_in(0.0, 1.0, hi_open=True, unit="cells"), default=None,
                    help="the predicted fits' --floor-phase (default: as the fit's)")
    ap.add_argument("--fix", default=None, help="known values, e.g. m=1 (that parameter is not predicted)")
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="seed of particle sampling and pixel noise")
    ap.add_argument("--dtype", choices=("float32", "float64"), default=FIT_DTYPE)
    ap.add_argument("--resume", action="store_true",
                    help="take the candidates already evaluated from the design log <out>.designlog.json")
    ap.add_argument("--no-plots", action="store_true", help="skip the chart")
    ap.set_defaults(func=run_design)
    return ap


def run_design(args) -> int:
    """Run the `design` subcommand from parsed arguments; returns the exit status."""
    from .design import design, parse_vary
    from .plots import plot_design

    out = Path(args.out)
    if out.suffix != ".json":
        raise CalibrationError(f"--out must name a .json file, got {args.out!r}")
    scene_out = out.with_name(out.stem + ".scene.json")
    chart = out.with_name(out.stem + ".png")
    log = out.with_name(out.stem + ".designlog.json")
    inputs = {"the scene": args.scene, **{f"--with {p}": p for p in args.with_data}}
    for path, option in ((out, "--out"), (scene_out, "--out (its scene)"), (chart, "--out (its chart)"),
                         (log, "--out (its log)")):
        check_output(path, option, inputs)
    guess = parse_params(args.guess)
    variables = [parse_vary(v, args.levels) for v in args.vary]
    settings = FitSettings(dx=args.dx, ppc=args.ppc, floor_phase=args.floor_phase, fixed=parse_fixed(args.fix),
                           seed=args.seed, dtype=args.dtype, dx_check=False).validate()
    plots = not args.no_plots
    if plots and missing_modules("matplotlib"):
        print("jaxfoam design: note: matplotlib is not installed, so the chart is skipped (install the viz "
              "extra: pip install 'jaxfoam[viz]')", flush=True)
        plots = False
    if not args.resume and log.exists():
        log.unlink()  # a fresh design: an old log of this name is replaced
    try:
        with _terminate_as_interrupt():
            result = design(args.scene, guess, variables, with_data=args.with_data, settings=settings,
                            points=args.points, spread=args.spread, robust=args.robust, duration=args.duration,
                            fps=args.fps, pixel_size=args.pixel_size, progress=lambda m: print(m, flush=True),
                            log=log, resume=args.resume, sampling=args.sampling,
                            misfit=args.misfit, dx_check=args.dx_check)
    except KeyboardInterrupt as exc:
        sys.stderr.write(f"\njaxfoam design: {'terminated' if isinstance(exc, _Terminated) else 'interrupted'}; "
                         f"the design log {log} keeps every finished candidate: run the same command with "
                         f"--resume to continue\n")
        return 143 if isinstance(exc, _Terminated) else 130
    result.write(out)
    result.write_scene(scene_out)
    print(result.report())
    rec = result.best["recording"]
    synth = (f"jaxfoam synth {scene_out} --params {args.guess} --frames {rec['frames']} --duration {rec['duration']:g}"
             + (f" --pixel-size {rec['pixel_size']:g}" if rec.get("pixel_size") else "") + " --out predicted.h5")
    print(f"wrote {out} and {scene_out} ({result.wall_time:.0f} s); to simulate the recommended recording: {synth}")
    if plots:
        plot_design(result, chart)
        print(f"wrote {chart}")
    return 0


# ----------------------------------------------------------------------------------------------
# jaxfoam track
# ----------------------------------------------------------------------------------------------

def add_track_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `track` subcommand to an argparse subparsers object (runs via args.func(args))."""
    ap = subparsers.add_parser(
        "track", help="track the foam silhouette in a video and write silhouette data",
        description="Turn a video (or GIF, or a directory of images) of foam in front of a static background "
                    "into the silhouette format: background difference or brightness threshold, "
                    "morphological clean-up, largest component, plate pixels ignored.")
    from jaxfoam.cli import float_in, int_at_least, positive_float

    ap.add_argument("video", help="video or GIF file, or a directory of images (then --fps)")
    ap.add_argument("--out", required=True, help="output silhouette file (.h5)")
    ap.add_argument("--scene", required=True, help="scene JSON file describing the experiment")
    ap.add_argument("--pixel-size", type=positive_float, required=True, help="metres per pixel of the video")
    ap.add_argument("--origin", type=float_in(), nargs=2, required=True, metavar=("X0", "Y0"),
                    help="world position (m) of the image's bottom-left corner")
    ap.add_argument("--background", default="median",
                    help="median | first | none (brightness threshold) | PATH of an image of the empty scene")
    ap.add_argument("--threshold", type=float_in(0.0, 1.0, lo_open=True, hi_open=True), default=None,
                    help="foreground threshold in (0, 1) of full intensity (default: Otsu's method)")
    ap.add_argument("--invert", action="store_true", help="with --background none: foam darker than the background")
    ap.add_argument("--polarity", choices=POLARITIES, default="any",
                    help="with a background: any difference (default), or only pixels brighter (white foam: "
                         "its shadow is not foam) or darker than the background")
    ap.add_argument("--edges", choices=EDGES, default="threshold",
                    help="threshold (default): the thresholded difference as it is; half: edge pixels are foam "
                         "when at least halfway from the local background to the local foam level")
    ap.add_argument("--fps", type=positive_float, default=None, help="frame rate (default: from the file)")
    ap.add_argument("--t0", type=float_in(0.0), default=0.0, help="time of the first frame since the scene's start, s")
    ap.add_argument("--every", type=int_at_least(1), default=1, help="keep one frame in EVERY")
    ap.add_argument("--downsample", type=int_at_least(1), default=1, help="average-pool factor (pixel size grows by it)")
    ap.add_argument("--max-frames", type=int_at_least(1), default=None, help="stop after this many kept frames")
    ap.add_argument("--open", type=int_at_least(0), default=OPEN_RADIUS,
                    help=f"opening radius, pixels (default {OPEN_RADIUS})")
    ap.add_argument("--close", type=int_at_least(0), default=CLOSE_RADIUS,
                    help=f"closing radius, pixels (default {CLOSE_RADIUS})")
    ap.add_argument("--keep-holes", action="store_true", help="do not fill holes in the silhouette")
    ap.add_argument("--plate-margin", type=int_at_least(-1), default=PLATE_MARGIN,
                    help=f"dilation of the plates' footprint (weight 0), pixels (default {PLATE_MARGIN}); "
                         "-1 keeps plate pixels")
    ap.set_defaults(func=run_track)
    return ap


def run_track(args) -> int:
    """Run the `track` subcommand from parsed arguments; returns the exit status."""
    from jaxfoam.guards import check_output, require_extra

    video = os.fspath(args.video)
    image_input = os.path.isdir(video) or video.lower().endswith(IMAGE_EXTENSIONS + (".gif",))
    require_extra("jaxfoam track", "imageio", *(() if image_input else ("imageio_ffmpeg",)))
    load_scene(args.scene)
    if not os.path.exists(video):
        raise ValueError(f"video: file {video!r} does not exist")
    check_output(args.out, "--out", {"the video": video, "--scene": args.scene,
                                     "--background": None if args.background in BACKGROUNDS else args.background})
    background = args.background
    if background not in BACKGROUNDS:
        if not os.path.exists(background):
            raise ValueError(f"--background must be one of {BACKGROUNDS} or an image file, got {background!r}")
        import imageio.v3 as iio

        try:
            img = np.asarray(iio.imread(background))
        except Exception as exc:  # imageio raises many kinds for an unreadable file
            raise ValueError(f"--background: cannot read {background!r} as an image ({type(exc).__name__}: {exc})") from exc
        img = img[:, :, None] if img.ndim == 2 else img[:, :, :3]
        scale = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype.kind in "ui" else 1.0
        background = average_pool(img, args.downsample) / scale
    data = track_video(args.video, args.pixel_size, args.origin, args.scene, background=background,
                       threshold=args.threshold, invert=args.invert, polarity=args.polarity, edges=args.edges,
                       fps=args.fps, t0=args.t0, every=args.every,
                       downsample=args.downsample, max_frames=args.max_frames, open_radius=args.open,
                       close_radius=args.close, holes=not args.keep_holes,
                       plate_margin=None if args.plate_margin < 0 else args.plate_margin, progress=print)
    data.write(args.out)
    T, H, W = data.shape
    print(f"wrote {args.out}: {T} frames of {H}x{W} pixels ({data.camera.pixel_size:g} m/pixel), "
          f"times {data.times[0]:g}..{data.times[-1]:g} s")
    return 0


# ----------------------------------------------------------------------------------------------
# jaxfoam synth
# ----------------------------------------------------------------------------------------------

def add_synth_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `synth` subcommand to an argparse subparsers object (runs via args.func(args))."""
    from jaxfoam.cli import add_budget_options, float_in, int_at_least, positive_float

    ap = subparsers.add_parser(
        "synth", help="simulate a scene and write synthetic silhouette data (with /truth)",
        description="Simulate SCENE.json with the given parameters and render it as tracked-video silhouettes "
                    "(hard masks, boundary pixel noise, dropped frames, plate pixels with weight 0).")
    ap.add_argument("scene", help="scene JSON file (initial_shape box or ellipse)")
    ap.add_argument("--params", required=True, help="mu=..,sigma_y=..,eta=..,m=.. (Pa, Pa, Pa s^m, -)")
    ap.add_argument("--out", required=True, help="output silhouette file (.h5)")
    ap.add_argument("--dx", type=positive_float, default=None,
                    help="grid spacing, m (default: the largest domain extent / 64 in 2D, / 32 in 3D)")
    ap.add_argument("--ppc", type=int_at_least(1), default=None, help="particles per cell (default 4 in 2D, 8 in 3D)")
    ap.add_argument("--frames", type=int_at_least(2), default=16,
                    help="frames on [0, duration], before dropping (default 16)")
    ap.add_argument("--duration", type=positive_float, default=1.0, help="simulated time, s (default 1)")
    ap.add_argument("--pixel-size", type=positive_float, default=None, help="m per pixel (default dx / 2)")
    ap.add_argument("--noise", type=float_in(0.0, 1.0), default=0.05,
                    help="flip probability of pixels next to the foam boundary, in [0, 1] (default 0.05)")
    ap.add_argument("--drop-frames", type=float_in(0.0, 1.0, hi_open=True), default=0.0,
                    help="fraction of frames after the first removed at random, in [0, 1) (default 0)")
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="seed of sampling, noise and dropped frames")
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    ap.add_argument("--cfl", type=float_in(0.0, 1.0, lo_open=True), default=CFL,
                    help=f"CFL number of the simulation's time step, in (0, 1] (default {CFL})")
    ap.add_argument("--first-mask", action="store_true",
                    help="record initial_shape 'first_mask' in the file's scene (fits start from the first mask)")
    add_budget_options(ap)
    ap.set_defaults(func=run_synth)
    return ap


def run_synth(args) -> int:
    """Run the `synth` subcommand from parsed arguments; returns the exit status."""
    scene = load_scene(args.scene)
    params = parse_params(args.params)
    check_output(args.out, "--out", {"the scene": args.scene})
    data = synthesize(scene, params, dx=args.dx, ppc=args.ppc, frames=args.frames,
                      duration=args.duration, pixel_size=args.pixel_size, noise=args.noise,
                      drop_frames=args.drop_frames, seed=args.seed,
                      dtype=jnp.float32 if args.dtype == "float32" else jnp.float64,
                      first_mask=args.first_mask, cfl=args.cfl, progress=print,
                      max_particles=args.max_particles, max_substeps=args.max_substeps)
    data.write(args.out)
    T, H, W = data.shape
    print(f"wrote {args.out}: {T} frames of {H}x{W} pixels ({data.camera.pixel_size:g} m/pixel), "
          f"times {data.times[0]:g}..{data.times[-1]:g} s")
    return 0
