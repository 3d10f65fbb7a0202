"""The `jaxfoam fit` command line: option parsers, settings from arguments, signal handling."""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import signal
import sys
import threading
from pathlib import Path
from typing import Mapping

import fitting

from .._guards import check_output, missing_modules
from .._params import FIT_FIELDS
from ..fracture import FractureConfig
from ..resample import ResampleConfig
from ..io import read_silhouettes
from .settings import (CalibrationError, DEFAULT_BOUNDS, DEFAULT_DX_REFIT, DEFAULT_MAX_ITER, DEFAULT_STARTS, FIT_CELLS,
                       FIT_DTYPE, FIT_PPC, FitSettings, KNOWN_INPUTS, OPTIMIZERS)
from .problem import build_problem
from .driver import calibrate, default_log_path
from .plots import plot_loss, plot_overlay


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


def parse_start(text: str | None, fixed: Mapping | None = None) -> dict | None:
    """The first start's guess from `--start`: 'mu=150,sigma_y=30' -> {'mu': 150.0, 'sigma_y': 30.0}, or the
    path of a fit.json whose fitted parameters are taken (those held fixed in this fit are left out), e.g.
    a fit of the same data on a coarser grid. None when not given."""
    if not text:
        return None
    path = Path(text)
    if "=" not in text and path.suffix == ".json":
        try:
            params = json.loads(path.read_text(encoding="utf-8"))["params"]
            out = {k: float(v) for k, v in params.items() if k in FIT_FIELDS and k not in (fixed or {})}
        except FileNotFoundError:
            raise CalibrationError(f"--start: no such fit result {text!r}") from None
        except (ValueError, KeyError, TypeError, AttributeError, OSError) as exc:  # JSON, UTF-8, a directory
            raise CalibrationError(f"--start: {text!r} is not a fit result (a fit.json with 'params'): {exc}") from None
        if not all(math.isfinite(v) for v in out.values()):
            raise CalibrationError(f"--start: {text!r} holds non-finite parameters {out}")
        if not out:
            raise CalibrationError(f"--start: {text!r} holds none of the fitted parameters {FIT_FIELDS}")
        return out
    return _parse_numbers(text, "start", FIT_FIELDS)


def parse_bounds(text: str | None) -> dict:
    """'mu=50:400,m=0.3:1' -> {'mu': (50.0, 400.0), 'm': (0.3, 1.0)}."""
    if not text:
        return {}
    out = {}
    for k, v in _parse_assignments(text, "bounds").items():
        if k not in FIT_FIELDS:
            raise CalibrationError(f"--bounds: unknown parameter {k!r}; expected one of {FIT_FIELDS}")
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
    from ..cli import _add_budget_options, int_at_least, positive_float

    ap.add_argument("data", help="silhouette file (.h5)")
    ap.add_argument("--out", required=True, help="result file (.json)")
    ap.add_argument("--dx", type=positive_float, default=None,
                    help=f"grid spacing of the fit, m (default: the largest domain extent / {FIT_CELLS[2]} in 2D, "
                         f"/ {FIT_CELLS[3]} in 3D)")
    ap.add_argument("--ppc", type=int_at_least(1), default=None,
                    help=f"particles per cell (default {FIT_PPC[2]} in 2D, {FIT_PPC[3]} in 3D)")
    ap.add_argument("--optimizer", choices=OPTIMIZERS, default="lm", help="default lm (Levenberg-Marquardt)")
    ap.add_argument("--fix", default=None,
                    help="hold parameters fixed, e.g. m=0.5,eta=10; kappa=.. or rho=.. override the scene's values")
    ap.add_argument("--bounds", default=None, help="bounds lo:hi, e.g. mu=20:1000,m=0.3:1.2 (defaults: "
                    + ", ".join(f"{k}={lo:g}:{hi:g}" for k, (lo, hi) in DEFAULT_BOUNDS.items()) + ")")
    ap.add_argument("--starts", type=int_at_least(1), default=DEFAULT_STARTS, help=f"multi-start guesses (default {DEFAULT_STARTS})")
    ap.add_argument("--start", default=None, metavar="NAME=VALUE,...|FIT.json",
                    help="the first start's guess, e.g. mu=150,sigma_y=30, or a fit.json to continue from (e.g. a "
                         "fit of the same data on a coarser --dx); default: the centre of the start ranges")
    ap.add_argument("--max-iter", type=int_at_least(0), default=None,
                    help="iterations per start (default " + ", ".join(f"{k} {v}" for k, v in DEFAULT_MAX_ITER.items())
                    + ")")
    ap.add_argument("--time-window", default=None, metavar="T_LO:T_HI",
                    help="fit only the frames with times in [T_LO, T_HI] s, e.g. 0:0.8 (default: all)")
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
    ap.add_argument("--no-plots", action="store_true", help="skip the pictures")
    _add_budget_options(ap)
    ap.set_defaults(func=run_fit)
    return ap


def settings_from_args(args) -> FitSettings:
    """The validated `FitSettings` of parsed `fit` arguments."""
    fixed = parse_fixed(args.fix)
    return FitSettings(dx=args.dx, ppc=args.ppc, optimizer=args.optimizer, fixed=fixed,
                       bounds=parse_bounds(args.bounds), starts=args.starts,
                       initial=parse_start(getattr(args, "start", None), fixed), max_iter=args.max_iter,
                       time_budget=parse_duration(getattr(args, "time_budget", None)),
                       time_window=parse_window(getattr(args, "time_window", None)), seed=args.seed,
                       pixel_level=args.pixel_level, dtype=args.dtype,
                       dx_check=not args.no_dx_check, dx_refit=args.dx_refit,
                       resample=parse_feature(getattr(args, "resample", None), ResampleConfig, "resample"),
                       fracture=parse_feature(getattr(args, "fracture", None), FractureConfig, "fracture"),
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


def run_fit(args) -> int:
    """Run the `fit` subcommand from parsed arguments; returns the exit status."""
    settings = settings_from_args(args)
    out = Path(args.out)
    log = Path(args.log) if args.log else default_log_path(out)
    check_output(out, "--out", {"the data": args.data})
    check_output(log, "--log", {"the data": args.data, "--out": out})
    data = read_silhouettes(args.data)
    if args.resume and log.exists():
        fitting.FitLog(log, mode="r").close()  # a file that is not a fit log is refused before any work
    plots = not args.no_plots
    if plots and missing_modules("matplotlib"):
        print("jaxfoam fit: note: matplotlib is not installed, so the pictures are skipped (install the viz "
              "extra: pip install 'jaxfoam[viz]')", flush=True)
        plots = False
    problem = build_problem(data, settings, max_particles=args.max_particles, max_substeps=args.max_substeps)
    if not args.resume and log.exists():
        log.unlink()  # a fresh fit: an old log of this name is replaced

    def say(msg):
        print(msg, flush=True)

    try:
        with _terminate_as_interrupt():
            result = calibrate(data, settings, log=log, resume=args.resume, progress=say, problem=problem)
    except KeyboardInterrupt as exc:
        sys.stderr.write(f"\njaxfoam fit: {'terminated' if isinstance(exc, _Terminated) else 'interrupted'}; the fit "
                         f"log {log} keeps every finished iteration: run the same command with --resume to "
                         f"continue\n")
        return 143 if isinstance(exc, _Terminated) else 130
    result.write(out)
    print(result.report())
    print(f"wrote {out} (fit log {log})")
    if plots:
        loss_png = out.with_name(out.stem + "_loss.png")
        overlay_png = out.with_name(out.stem + "_overlay.png")
        plot_loss(result, loss_png)
        plot_overlay(problem, result, overlay_png)
        print(f"wrote {loss_png} and {overlay_png}")
    return 0
