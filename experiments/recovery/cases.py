"""The recovery study's cases: the scenes and grids, the probes, the truths, the job plan and each case's
synthetic dataset (made once in WORK; a case's id names its files)."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import fitting
from experiments import _common  # noqa: F401  (enables float64)
from fitting.settings import DEFAULT_DX_REFIT, DEFAULT_STARTS
from fitting import synthesize

NAME = "recovery"
ROOT = Path(__file__).resolve().parents[1]  # experiments/
SCENES = ROOT / "scenes"
WORK = ROOT.parent / "out" / "recovery"
# Records and small diagnostics (JSON) are committed so that --report works on a fresh clone; the data
# files and fit logs are large and stay in WORK.
CASES = ROOT / "results" / "recovery_cases"
# The shaving-cream ranges of the truths (SI units); log-uniform except m.
TRUTH_RANGES = {"mu": (50.0, 400.0), "sigma_y": (15.0, 80.0), "eta": (1.0, 30.0), "m": (0.3, 1.0)}
TRUTH_SEED = 2015
N_SETS = 3
# Synthetic-data realism: boundary pixel flips and dropped frames like a tracked video.
NOISE = 0.05
DROP_FRAMES = 0.1


@dataclasses.dataclass(frozen=True)
class SceneCase:
    """A scene of the study: file, fit grid spacing (m), simulated duration (s), frames, and the fit's
    time window (s, `FitSettings.time_window`; None: every frame)."""

    name: str
    dx_fit: float
    duration: float
    frames: int
    window: tuple | None = None
    # How the data differ from the main table's (DATA probe): data grid dx_fit / data_ratio, `synthesize`'s
    # noise, drop_frames, pixel_size (None: its default) and first_mask (start from the first mask).
    tag: str = ""
    data_ratio: float = 2.0
    noise: float = NOISE
    drop_frames: float = DROP_FRAMES
    pixel_size: float | None = None
    first_mask: bool = False
    dilate_px: int = 0  # masks grown by this many pixels where the weight is not 0 (a fatter renderer)
    # The data simulation's own numerics (None: synthesize's defaults, which are the fit's), as another
    # simulator's would differ.
    ppc: int | None = None
    cfl: float | None = None
    data_dtype: str = "float64"
    # The fit's floating-point precision (`FitSettings.dtype`); the data are the same case's in float64.
    fit_dtype: str = "float64"


# Coarse fit grids (a Jacobian costs dx^-3 in 2D, dx^-4 in 3D); durations cover each scene's informative
# phase (stretching under the plate; impact and spreading; squeeze, hold and lift).
FULL = [SceneCase("hanging_plate_2d", 0.01, 0.8, 12), SceneCase("drop_2d", 0.01, 0.4, 12),
        SceneCase("squeeze_2d", 0.01, 1.4, 12), SceneCase("hanging_plate_3d", 0.016, 0.6, 8)]
QUICK = [SceneCase("hanging_plate_2d", 0.01, 0.6, 8), SceneCase("drop_2d", 0.01, 0.4, 8),
         SceneCase("squeeze_2d", 0.01, 1.0, 8), SceneCase("hanging_plate_3d", 0.016, 0.6, 8)]
# Finer-grid probe (full study, LM): the drop at dx_fit / sqrt(2), data at half that: does a finer fit
# grid bring the parameters closer to the truth?
FINE = [SceneCase("drop_2d", 0.01 / math.sqrt(2.0), 0.4, 12)]
# Floor-friction probe (full study, LM): on the rough floor the foam spreads by shearing a layer a few
# cells thick (experiments/floor_contact); does the drop's bias go with the friction?
SLIP = [SceneCase("drop_2d_frictionless", 0.01, 0.4, 12)]
# Floor-contact probe (full study, LM): grid contact leaves the landed foam a fraction of a cell above the
# floor, particle contact does not (experiments/floor_contact); does the drop's bias go with that gap?
CONTACT = [SceneCase("drop_2d_particle_contact", 0.01, 0.4, 12)]


def _domain(name: str) -> dict:
    """Study scene `name`'s domain ({"min": [...], "max": [...]}, m)."""
    return json.loads((SCENES / f"{name}.json").read_text())["domain"]


def default_fit_dx(name: str) -> float:
    """The fitter's default dx (m) for a study scene: its largest domain extent / FIT_CELLS[dim]."""
    from fitting.settings import FIT_CELLS

    dom = _domain(name)
    extent = max(hi - lo for lo, hi in zip(dom["min"], dom["max"]))
    return extent / FIT_CELLS[len(dom["min"])]


def fitter_refit(r: dict) -> int:
    """The fitter's default `dx_refit` (LM iterations of the check's measured move) for finished fit r's scene."""
    return DEFAULT_DX_REFIT[len(_domain(case_of(r).name)["min"])]


# The fitter's default grid (`jaxfoam fit` without --dx; LM, data at half its spacing): what a user who
# keeps the default gets, against the study's coarser grid.
DEFAULT_GRID = [dataclasses.replace(c, dx_fit=default_fit_dx(c.name)) for c in FULL if not c.name.endswith("3d")]
# Time-window probe (LM, the main table's squeeze data): only the squeeze and the hold (to the hold's end),
# which the fit grid reproduces at the truth more closely than the lift.
WINDOW = [SceneCase("squeeze_2d", 0.01, 1.4, 12, window=(0.0, 0.8)),
          SceneCase("squeeze_2d", default_fit_dx("squeeze_2d"), 1.4, 12, window=(0.0, 0.8))]
PROBES = FINE + SLIP + CONTACT + WINDOW + DEFAULT_GRID
# Data-variation probe: the fitter will meet data from other simulators, resolutions and cameras; the main
# table's fits against data made differently, one change at a time (the report's "Data made differently").
DATA = [SceneCase(name, 0.01, dur, 12, **var) for var in (
            {"tag": "fine4", "data_ratio": 4.0}, {"tag": "noisy", "noise": 0.2, "drop_frames": 0.3},
            {"tag": "pix", "pixel_size": 0.00125}, {"tag": "mask", "first_mask": True}, {"tag": "fat", "dilate_px": 1},
            {"tag": "numerics", "ppc": 9, "cfl": 0.5, "data_dtype": "float32"})
        for name, dur in (("hanging_plate_2d", 0.8), ("drop_2d", 0.4))] + [
    # the squeeze starts from its first mask too: its foam rests on the floor with the plate just above it
    SceneCase("squeeze_2d", 0.01, 1.4, 12, tag="mask", first_mask=True)]
# Precision probe: the main table's 2D fits and the default grid's slowest (squeeze) in float32 on the same
# data: does a fit keep its accuracy, and how much of float32's speed (experiments/bench_step.md)?
PRECISION = [dataclasses.replace(c, fit_dtype="float32") for c in FULL if not c.name.endswith("3d")] + [
    dataclasses.replace(c, fit_dtype="float32") for c in DEFAULT_GRID if c.name == "squeeze_2d"]
# Full 2D LM fits take the fitter's default starts, as a user's would; 3D and comparison fits one (cost).
# Start 0 is the same guess for every optimizer, so the comparison reads each fit's first start.
BUDGET = {True: {"starts": {"lm": 1, "lbfgs": 1, "adam": 1}, "iters": {"lm": 12, "lbfgs": 12, "adam": 20}},
          False: {"starts": {"lm": DEFAULT_STARTS, "lbfgs": 1, "adam": 1}, "iters": {"lm": 20, "lbfgs": 20, "adam": 40}}}


def starts_for(c: SceneCase, opt: str, quick: bool) -> int:
    """Multi-start count of a fit in the study (BUDGET; 3D fits always one start)."""
    return 1 if c.name.endswith("3d") else int(BUDGET[quick]["starts"][opt])


# Which (scene, set) pairs get the optimizer comparison (all three optimizers).
COMPARE = {True: [("drop_2d", 0)], False: [("drop_2d", 0), ("squeeze_2d", 0), ("hanging_plate_2d", 1), ("hanging_plate_2d", 2)]}


def write_atomic(path: Path, text: str) -> None:
    """Write `path` whole or not at all (a killed study must not leave a truncated record)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_name(path.name + ".part")
    part.write_text(text)
    os.replace(part, path)


def write_cache(path: Path, obj) -> None:
    """Write a diagnostic's JSON cache file beside the records."""
    write_atomic(path, json.dumps(obj) + "\n")


def truth_sets() -> list[dict]:
    """The N_SETS parameter sets: a seeded Latin hypercube over TRUTH_RANGES (log-uniform except m)."""
    u = fitting.latin_hypercube(N_SETS, 4, TRUTH_SEED)
    out = []
    for row in u:
        t = {}
        for j, (n, (lo, hi)) in enumerate(TRUTH_RANGES.items()):
            t[n] = float(lo + row[j] * (hi - lo)) if n == "m" else float(math.exp(
                math.log(lo) + row[j] * (math.log(hi) - math.log(lo))))
        out.append({k: float(f"{v:.4g}") for k, v in t.items()})
    return out


def plan(quick: bool, n_sets: int | None = None) -> list[tuple]:
    """(priority, scene case, set index, optimizer) in the order they run: LM on the first set of every
    2D scene, then the optimizer comparison, then the remaining 2D sets, then 3D."""
    cases = QUICK if quick else FULL
    sets = list(range((1 if quick else N_SETS) if n_sets is None else min(int(n_sets), N_SETS)))
    jobs = []
    for k in sets:
        for c in cases:
            pri = 10 + k if c.name.endswith("3d") else (0 if k == 0 else 1 + k)
            jobs.append((pri, c, k, "lm"))
    for name, k in COMPARE[quick]:
        c = next(c for c in cases if c.name == name)
        for opt in ("lbfgs", "adam"):
            jobs.append((1, c, k, opt))
    if not quick:
        jobs.extend((20 + k, c, k, "lm") for k in sets for c in FINE + SLIP + CONTACT + WINDOW)
        jobs.extend((25 + k, c, k, "lm") for k in sets for c in DATA)
        jobs.extend((30 + k, c, k, "lm") for k in sets for c in DEFAULT_GRID)
        jobs.extend(((35 if c.dx_fit != 0.01 else 27) + k, c, k, "lm") for k in sets for c in PRECISION)
    return sorted(jobs, key=lambda j: j[0])


def case_id(c: SceneCase, k: int, quick: bool) -> str:
    if c.fit_dtype != "float64":  # a fit setting: the prefix, then that of the same case in float64
        return "f32_" + case_id(dataclasses.replace(c, fit_dtype="float64"), k, quick)
    if c in WINDOW:  # the window's prefix, then that of the same case without it (the data's)
        return "win_" + case_id(dataclasses.replace(c, window=None), k, quick)
    if c.tag:
        return f"{c.tag}_{c.name}_set{k}"
    prefix = 'q_' if quick else 'fine_' if c in FINE else 'dflt_' if c in DEFAULT_GRID else ''
    return f"{prefix}{c.name}_set{k}"


def data_path(c: SceneCase, k: int, quick: bool) -> Path:
    """The synthetic silhouette file of a case; a fit window or the fit's precision changes the fit, not
    the data, so such a case shares the file of the same case without it."""
    return WORK / f"{case_id(dataclasses.replace(c, window=None, fit_dtype='float64'), k, quick)}_data.h5"


def make_data(c: SceneCase, k: int, quick: bool) -> tuple[Path, float]:
    """The synthetic silhouette file of a case (made once): (path, wall seconds spent now)."""
    WORK.mkdir(parents=True, exist_ok=True)
    path = data_path(c, k, quick)
    if path.exists():
        return path, 0.0
    t0 = time.perf_counter()
    scene = json.loads((SCENES / f"{c.name}.json").read_text())
    truth = truth_sets()[k]
    data = synthesize(scene, truth, dx=c.dx_fit / c.data_ratio, frames=c.frames, duration=c.duration,
                      pixel_size=c.pixel_size, noise=c.noise, drop_frames=c.drop_frames, seed=k,
                      first_mask=c.first_mask, progress=lambda m: print("  synth:", m, flush=True),
                      **({} if c.ppc is None else {"ppc": c.ppc}), **({} if c.cfl is None else {"cfl": c.cfl}),
                      dtype=jnp.float32 if c.data_dtype == "float32" else jnp.float64)
    if c.dilate_px:
        from fitting.track import dilate

        grown = np.stack([dilate(m, c.dilate_px) for m in data.masks]) & (data.weights > 0)
        data = dataclasses.replace(data, masks=grown.astype(np.uint8))
    part = path.with_name(path.stem + ".part.h5")  # a killed study must not leave a truncated file
    data.write(part)
    os.replace(part, path)
    return path, time.perf_counter() - t0


def case_of(r: dict) -> SceneCase:
    """The SceneCase of a finished record (quick records from QUICK, the others from FULL or PROBES)."""
    if r["case"].startswith("f32_"):
        return dataclasses.replace(case_of(dict(r, case=r["case"][len("f32_"):])), fit_dtype="float32")
    tagged = [c for c in DATA if r["case"] == case_id(c, r["set"], False)]
    if tagged:
        return tagged[0]
    if r["case"].startswith("q_"):
        cases = QUICK
    elif r["case"].startswith("win_"):
        cases = WINDOW
    else:  # a window case shares its scene and grid with the case it windows
        cases = [c for c in FULL + PROBES if c not in WINDOW]
    return next(c for c in cases if c.name == r["scene"] and c.dx_fit == r["dx_fit"])
