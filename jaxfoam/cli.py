"""Command line: `jaxfoam simulate`, `jaxfoam render`, `jaxfoam demo`, `jaxfoam export`, and the calibration package's
`jaxfoam synth`, `jaxfoam track` and `jaxfoam fit` (parsers in `fitting.cli`, imported only when needed).

Each subcommand is one `add_<name>_parser(subparsers)` function that registers its arguments and one
`cmd_<name>(args) -> exit code` function; `main` dispatches on `args.func`. A new subcommand adds its
pair and one line in `build_parser`.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from ._errors import JaxfoamError
from .guards import DEFAULT_MAX_PARTICLES, DEFAULT_MAX_SUBSTEPS

# Shaving-cream-like defaults (order of magnitude of Gillette foam rheometry, Durian 1990 / Ovarlez 2010):
# shear modulus ~ 100-300 Pa, yield stress ~ 20-60 Pa, Herschel-Bulkley consistency ~ 5-30 Pa s^m with
# a shear-thinning exponent ~ 0.4-0.6. kappa and rho come from the scene.
DEFAULT_MU = 200.0        # Pa
DEFAULT_SIGMA_Y = 40.0    # Pa
DEFAULT_ETA = 10.0        # Pa s^m
DEFAULT_M = 0.5           # dimensionless
DEFAULT_FRAMES = 24
DEFAULT_DURATION = 1.0    # s
# Default grid: this many cells across the largest domain extent (2D, 3D): coarse enough for a laptop.
DEFAULT_CELLS = {2: 64, 3: 32}
# The progress bar redraws at most this often, s (and a non-terminal stderr gets a line this often).
PROGRESS_INTERVAL = {True: 0.2, False: 5.0}
BAR_WIDTH = 28

# The demo: the 2D hanging-plate scene, coarse enough to finish in about a minute on two CPU cores.
DEMO_SCENE = "hanging_plate_2d.json"
DEMO_DX = 0.006           # m
DEMO_DURATION = 1.5       # s
DEMO_FRAMES = 30
DEMO_PANELS = 8


class CLIError(JaxfoamError):
    """A user error reported as `jaxfoam <command>: error: ...` with exit code 2."""


# argparse value types: a bad value is reported as "argument --NAME: must be ..., got 'VALUE'" (exit 2).

def int_at_least(lo: int):
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {text!r}") from None
        if value < lo:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {text!r}")
        return value
    parse.__name__ = f"integer >= {lo}"
    return parse


def float_in(lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False, hi_open: bool = False,
             unit: str = ""):
    """A finite float in the interval (lo, hi) with the given open ends."""
    left = "(" if lo_open else "["
    right = ")" if hi_open else "]"
    if hi == math.inf:
        rng = f"{'>' if lo_open else '>='} {lo:g}"
    else:
        rng = f"in {left}{lo:g}, {hi:g}{right}"
    rng += f" {unit}" if unit else ""

    def parse(text):
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number {rng}, got {text!r}") from None
        ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"must be a finite number {rng}, got {text!r}")
        return value
    parse.__name__ = f"number {rng}"
    return parse


positive_float = float_in(0.0, lo_open=True)


def _dtype(name: str):
    import jax.numpy as jnp

    return {"float32": jnp.float32, "float64": jnp.float64}[name]


class Progress:
    """A progress bar on stderr: simulated time, frames, substeps per second and particle-steps per second.

    On a terminal it redraws one line; otherwise it prints a line every PROGRESS_INTERVAL[False] s.
    The rates exclude the first block of frames, which includes the compilation.
    """

    def __init__(self, t_end: float, total_frames: int, particles: int, stream=None, enabled: bool = True):
        self.stream = sys.stderr if stream is None else stream
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t_end, self.total, self.particles, self.enabled = t_end, total_frames, particles, enabled
        self.start = time.perf_counter()
        self.rate_start = None  # (wall time, substeps) after the first block
        self.last_draw = -math.inf

    def update(self, t: float, frames_done: int, substeps_done: int, force: bool = False):
        if not self.enabled:
            return
        now = time.perf_counter()
        rate = None
        if self.rate_start is None:
            if frames_done > 0:  # the first block (compilation included) has just finished
                self.rate_start = (now, substeps_done)
        else:
            dt_wall = now - self.rate_start[0]
            rate = (substeps_done - self.rate_start[1]) / dt_wall if dt_wall > 0 else None
        if not force and now - self.last_draw < PROGRESS_INTERVAL[self.tty]:
            return
        self.last_draw = now
        frac = min(1.0, frames_done / max(self.total, 1))
        filled = int(round(frac * BAR_WIDTH))
        bar = "#" * filled + "." * (BAR_WIDTH - filled)
        if rate:
            left = (self.total - frames_done) * (substeps_done / frames_done) / rate
            speed = (f"{rate:,.0f} substeps/s, {rate * self.particles / 1e6:.2f} M particle-steps/s, "
                     f"~{left:.0f} s left")
        else:
            speed = "compiling + first frame" if frames_done == 0 else "measuring speed"
        line = (f"[{bar}] t = {t:.3f}/{self.t_end:.3f} s  frame {frames_done}/{self.total}  {speed}  "
                f"({now - self.start:.0f} s)")
        if self.tty:
            self.stream.write("\r" + line + "\033[K")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self):
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()


def default_dx(scene) -> float:
    """Grid spacing giving DEFAULT_CELLS cells across the largest domain extent, m."""
    extent = float(np.max(np.asarray(scene.domain_max) - np.asarray(scene.domain_min)))
    return extent / DEFAULT_CELLS[scene.dim]


def run_simulation(scene_path, out, *, dx=None, ppc=None, dtype="float64", frames=DEFAULT_FRAMES,
                   duration=DEFAULT_DURATION, mu=DEFAULT_MU, sigma_y=DEFAULT_SIGMA_Y, eta=DEFAULT_ETA, m=DEFAULT_M,
                   seed=0, cfl=None, frames_per_block=1, progress=True, creator=None,
                   max_particles=DEFAULT_MAX_PARTICLES, max_substeps=DEFAULT_MAX_SUBSTEPS) -> dict:
    """Simulate a scene file and write its trajectory (HDF5) to `out`; returns a summary dict.

    Records the initial state at t = 0 and `frames` frames evenly spaced over (0, duration] s. The rollout
    runs `frames_per_block` frames per call to `Simulator.rollout`, each block starting from the previous
    block's final state with the same grid, substep count and dt, and appends each block to the file as it
    finishes (a run that fails part-way leaves a file marked incomplete; the file appears at `out` when
    the run ends). Every option is checked before any work: a run over `max_particles` particles or
    `max_substeps` substeps is refused (BudgetError). Raises SimulationError if the state turns non-finite.
    """
    import jax
    import jax.numpy as jnp

    from .guards import check_dtype_range, check_output, check_particles, check_substeps, estimate_particles
    from .guards import substeps_per_frame
    from ._params import Params
    from ._model import CFL
    from ._rollout import observe_default, rollout
    from ._scene import DEFAULT_PPC, load_scene
    from ._simulate import Simulator
    from .adjoint import Autodiff
    from ._trajectory import TrajectoryWriter

    if dtype not in ("float32", "float64"):
        raise CLIError(f"--dtype must be float32 or float64, got {dtype!r}")
    jdtype = _dtype(dtype)
    scene = load_scene(scene_path, dtype=jdtype)
    out = check_output(out, "--out", {"the scene": scene_path})
    if not (isinstance(frames, int) and frames >= 1):
        raise CLIError(f"--frames must be an integer >= 1, got {frames!r}")
    if not (duration > 0 and math.isfinite(duration)):
        raise CLIError(f"--duration must be a positive time in s, got {duration!r}")
    if not (isinstance(frames_per_block, int) and frames_per_block >= 1):
        raise CLIError(f"frames_per_block must be an integer >= 1, got {frames_per_block!r}")
    if not (isinstance(seed, int) and seed >= 0):
        raise CLIError(f"--seed must be an integer >= 0, got {seed!r}")
    if ppc is not None and not (isinstance(ppc, int) and ppc >= 1):
        raise CLIError(f"--ppc must be an integer >= 1, got {ppc!r}")
    if dx is not None and not (dx > 0 and math.isfinite(dx)):
        raise CLIError(f"--dx must be a positive grid spacing in m, got {dx!r}")
    cfl = CFL if cfl is None else cfl
    if not (0 < cfl <= 1):
        raise CLIError(f"--cfl must be in (0, 1], got {cfl!r}")
    dx = default_dx(scene) if dx is None else float(dx)
    params = Params(mu=float(mu), kappa=scene.kappa, sigma_y=float(sigma_y), eta=float(eta), m=float(m),
                    rho=scene.density).validate()
    check_dtype_range(dict(mu=mu, sigma_y=sigma_y, eta=eta, m=m), dtype, lambda k: "--" + k.replace("_", "-"))
    check_dtype_range(dict(kappa=scene.kappa, density=scene.density), dtype, lambda k: f"scene field '{k}'")
    times = duration * np.arange(1, frames + 1) / frames
    d = scene.dim
    ppc_used = int(ppc) if ppc is not None else DEFAULT_PPC[d]
    itemsize = np.dtype(dtype).itemsize
    # The budgets are checked before sampling: a too-fine grid or a stiff material is refused at once.
    estimate = estimate_particles(scene, dx, ppc_used)
    if estimate is not None:
        check_particles(estimate, d, itemsize, max_particles, dx=dx, ppc=ppc_used)
    per_frame = substeps_per_frame(scene, params, dx, cfl, times)
    check_substeps(per_frame, frames, max_substeps, span=duration, dt=float(times[0]) / per_frame)
    sim = Simulator(scene, times, params, dx, ppc, dtype=jdtype, seed=seed, cfl=cfl)
    n_active = int(sim.state0.active.sum())
    check_particles(n_active, d, itemsize, max_particles, dx=dx, ppc=ppc_used)
    p_run = params.astype(sim.dtype)
    bar = Progress(duration, frames, n_active, enabled=progress)
    info = dict(particles=n_active, substeps_per_frame=sim.substeps, dt=sim.dt, dx=dx, grid=sim.grid.shape,
                frames=frames + 1, out=os.fspath(out))
    if progress:
        sys.stderr.write(f"jaxfoam simulate: {scene.kind} {d}D, {n_active} particles, grid {sim.grid.shape} "
                         f"(dx = {dx:.4g} m), dt = {sim.dt:.3g} s, {sim.substeps} substeps/frame, "
                         f"{frames} frames to t = {duration:g} s, {jnp.dtype(jdtype).name}\n")
    wall0 = time.perf_counter()
    state = sim.state0
    with TrajectoryWriter(out, params, scene, dx, sim.dt, sim.substeps, dtype=jnp.dtype(jdtype).name, ppc=ppc_used,
                          creator=creator) as writer:
        first = jax.device_get(observe_default(state, p_run))
        writer.append({k: np.asarray(v)[None] for k, v in first.items()}, [0.0])
        done = 0
        bar.update(0.0, 0, 0, force=True)
        while done < frames:
            block = times[done:done + frames_per_block]
            # The same model (substeps per frame, frame spacing) for every block: one compiled rollout.
            state, fr, health = rollout(sim.model, state, p_run, block, adjoint=Autodiff())
            fr = jax.device_get(fr)
            sim.check(fr, health, frame_times=block)
            writer.append(fr, block)
            done += len(block)
            bar.update(float(block[-1]), done, done * sim.substeps, force=done == frames)
        bar.close()
    info["wall_s"] = time.perf_counter() - wall0
    info["substeps_per_s"] = frames * sim.substeps / info["wall_s"]
    return info


def add_simulate_parser(sub):
    p = sub.add_parser("simulate", help="simulate a scene file and write an HDF5 trajectory",
                       description="Simulate a scene (JSON, shared/specs/silhouettes.md) and write the trajectory "
                                   "(HDF5: positions, velocities, plastic rate, stress, J per frame). SI units.")
    p.add_argument("scene", help="scene description, JSON file")
    p.add_argument("--out", required=True, help="output trajectory file (.h5)")
    _add_run_options(p)
    p.set_defaults(func=cmd_simulate)


def _add_run_options(p, dx=None, frames=DEFAULT_FRAMES, duration=DEFAULT_DURATION):
    p.add_argument("--dx", type=positive_float, default=dx,
                   help="grid spacing, m (default: the largest domain extent / 64 in 2D, / 32 in 3D)"
                   if dx is None else f"grid spacing, m (default {dx})")
    p.add_argument("--ppc", type=int_at_least(1), default=None, help="particles per cell (default 4 in 2D, 8 in 3D)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision (default float64)")
    p.add_argument("--frames", type=int_at_least(1), default=frames,
                   help=f"frames recorded after t = 0 (default {frames})")
    p.add_argument("--duration", type=positive_float, default=duration, help=f"simulated time, s (default {duration})")
    p.add_argument("--mu", type=float_in(0.0, lo_open=True, unit="Pa"), default=DEFAULT_MU,
                   help=f"shear modulus, Pa (default {DEFAULT_MU})")
    p.add_argument("--sigma-y", dest="sigma_y", type=float_in(0.0, unit="Pa"), default=DEFAULT_SIGMA_Y,
                   help=f"yield stress, Pa (default {DEFAULT_SIGMA_Y})")
    p.add_argument("--eta", type=float_in(0.0, unit="Pa s^m"), default=DEFAULT_ETA,
                   help=f"Herschel-Bulkley consistency, Pa s^m (default {DEFAULT_ETA})")
    p.add_argument("--m", type=float_in(0.0, 5.0, lo_open=True), default=DEFAULT_M,
                   help=f"Herschel-Bulkley exponent, in (0, 5] (default {DEFAULT_M})")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="particle sampling seed (default 0)")
    p.add_argument("--cfl", type=float_in(0.0, 1.0, lo_open=True), default=None,
                   help="CFL number of the time step, in (0, 1] (default jaxfoam.CFL)")
    add_budget_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_budget_options(p):
    """Add --max-particles and --max-substeps (the run's size budget) to the parser p."""
    p.add_argument("--max-particles", type=int_at_least(1), default=DEFAULT_MAX_PARTICLES,
                   help=f"refuse a run of more particles than this (default {DEFAULT_MAX_PARTICLES:,})")
    p.add_argument("--max-substeps", type=int_at_least(1), default=DEFAULT_MAX_SUBSTEPS,
                   help=f"refuse a rollout of more substeps than this, all frames together "
                        f"(default {DEFAULT_MAX_SUBSTEPS:,})")


def cmd_simulate(args) -> int:
    info = run_simulation(args.scene, args.out, dx=args.dx, ppc=args.ppc, dtype=args.dtype, frames=args.frames,
                          duration=args.duration, mu=args.mu, sigma_y=args.sigma_y, eta=args.eta, m=args.m,
                          seed=args.seed, cfl=args.cfl, progress=not args.quiet,
                          max_particles=args.max_particles, max_substeps=args.max_substeps)
    print(f"wrote {info['out']}: {info['frames']} frames, {info['particles']} particles, "
          f"{info['substeps_per_frame']} substeps/frame of {info['dt']:.3g} s, {info['wall_s']:.1f} s wall "
          f"({info['substeps_per_s']:,.0f} substeps/s including compilation)")
    return 0


def add_render_parser(sub):
    p = sub.add_parser("render", help="draw a contact sheet (PNG) and optionally a video (MP4) of a trajectory")
    p.add_argument("trajectory", help="trajectory file (.h5) from `jaxfoam simulate`")
    p.add_argument("--out", required=True, help="output contact sheet (.png)")
    p.add_argument("--mp4", default=None, help="also write a video of every frame (needs the viz extra)")
    p.add_argument("--color", choices=("gamma_dot", "s"), default="gamma_dot",
                   help="colour by plastic strain rate (1/s, log) or deviatoric stress (Pa)")
    p.add_argument("--panels", type=int_at_least(1), default=8, help="frames on the contact sheet (default 8)")
    p.add_argument("--fps", type=positive_float, default=20.0, help="video frames per second (default 20)")
    p.add_argument("--surface", action="store_true",
                   help="shaded surface renders instead of particles (3D: lit mesh, floor, plates; 2D: lit "
                        "outline fill); needs the export extra")
    p.add_argument("--camera", type=camera_angles, default=None,
                   help="3D --surface camera: AZIMUTH,ELEVATION in degrees (default 30,25; 0,0 looks along -z)")
    p.set_defaults(func=cmd_render)


def camera_angles(text):
    """AZIMUTH,ELEVATION (deg): azimuth any finite angle, elevation in [-90, 90]."""
    parts = text.split(",")
    try:
        az, el = (float(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be AZIMUTH,ELEVATION in degrees (e.g. 30,25), got {text!r}") from None
    if not (math.isfinite(az) and math.isfinite(el) and -90.0 <= el <= 90.0):
        raise argparse.ArgumentTypeError(f"must be a finite azimuth and an elevation in [-90, 90] deg, got {text!r}")
    return (az, el)


# Picture and video formats the renderer writes (matplotlib's and ffmpeg's, chosen by the suffix).
PICTURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi")


def _check_suffix(path, option, allowed):
    suffix = Path(os.fspath(path)).suffix.lower()
    if suffix not in allowed:
        raise CLIError(f"{option} {os.fspath(path)!r} must end in one of {', '.join(allowed)} (the format is "
                       f"chosen by the suffix), got {suffix or 'no suffix'!r}")


def cmd_render(args) -> int:
    from .guards import EXPORT_HINT, check_output, require_extra
    from ._trajectory import load_trajectory
    from .render import render_contact_sheet, render_surface_sheet, render_surface_video, render_video

    require_extra("jaxfoam render", "matplotlib", *(("imageio", "imageio_ffmpeg") if args.mp4 else ()))
    if args.surface:
        require_extra("jaxfoam render --surface", "skimage", hint=EXPORT_HINT)
    elif args.camera is not None:
        raise CLIError("--camera sets the view of --surface renders; add --surface")
    traj = load_trajectory(args.trajectory)
    check_output(args.out, "--out", {"the trajectory": args.trajectory, "--mp4": args.mp4})
    _check_suffix(args.out, "--out", PICTURE_SUFFIXES)
    if args.mp4:
        check_output(args.mp4, "--mp4", {"the trajectory": args.trajectory})
        _check_suffix(args.mp4, "--mp4", VIDEO_SUFFIXES)
    if args.surface:
        render_surface_sheet(traj, args.out, n_frames=args.panels, camera=args.camera)
    else:
        render_contact_sheet(traj, args.out, n_frames=args.panels, color=args.color)
    print(f"wrote {args.out}")
    if args.mp4:
        if args.surface:
            render_surface_video(traj, args.mp4, fps=args.fps, camera=args.camera)
        else:
            render_video(traj, args.mp4, fps=args.fps, color=args.color)
        print(f"wrote {args.mp4}")
    return 0


def add_export_parser(sub):
    from .export import FORMATS

    p = sub.add_parser("export", help="write frames as particle clouds (PLY) and surfaces (meshes, outlines)",
                       description="Per frame: the particles with their fields as PLY, and the material's surface "
                                   "(3D: a closed mesh, PLY or OBJ; 2D: closed outline loops, PLY, OBJ, SVG or "
                                   "CSV), plus export.json listing the files. Needs the export extra.")
    p.add_argument("trajectory", help="trajectory file (.h5) from `jaxfoam simulate`")
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--format", default="ply", help=f"surface format: {', '.join(FORMATS)} (svg and csv: 2D only; "
                                                   "default ply); particle clouds are always PLY")
    p.add_argument("--frames", default="all", help="frames to export: all (default), or indices and ranges, "
                                                   "e.g. 0,5,-1 or 0:24:4")
    p.add_argument("--no-particles", dest="particles", action="store_false", help="do not write particle clouds")
    p.add_argument("--no-surface", dest="surface", action="store_false", help="do not write surfaces")
    p.set_defaults(func=cmd_export)


def cmd_export(args) -> int:
    from .export import check_folder, check_format, export_trajectory, parse_frames
    from .guards import EXPORT_HINT, require_extra
    from ._trajectory import load_trajectory

    if not (args.particles or args.surface):
        raise CLIError("--no-particles with --no-surface leaves nothing to export")
    needs = (("skimage",) if args.surface else ()) + (("plyfile",) if args.particles or args.format == "ply" else ())
    require_extra("jaxfoam export", *needs, hint=EXPORT_HINT)
    traj = load_trajectory(args.trajectory)
    check_format(args.format, traj.dim, "--format")
    parse_frames(args.frames, traj.num_frames, "--frames")
    check_folder(args.out, "--out")
    manifest = export_trajectory(traj, args.out, fmt=args.format, frames=args.frames, particles=args.particles,
                                 surface=args.surface)
    print(f"wrote {len(manifest['frames'])} frames to {args.out} (listed in {args.out}/export.json)")
    return 0


def find_scene(name: str) -> Path:
    """An example scene file: experiments/scenes/<name> in the source tree or the working directory."""
    candidates = [Path(__file__).resolve().parent.parent / "experiments" / "scenes" / name,
                  Path.cwd() / "experiments" / "scenes" / name]
    for c in candidates:
        if c.is_file():
            return c
    raise CLIError(f"example scene {name!r} not found (looked in {', '.join(str(c.parent) for c in candidates)}); "
                   "run from a source checkout or pass --scene")


def add_demo_parser(sub):
    p = sub.add_parser("demo", help="simulate the 2D hanging-plate example and draw a contact sheet",
                       description="Simulates experiments/scenes/hanging_plate_2d.json at a coarse resolution "
                                   "(about a minute on two CPU cores), writes the trajectory beside the picture "
                                   "(demo.png -> demo.h5) and the contact sheet.")
    p.add_argument("--out", default="demo.png", help="contact sheet (.png); the trajectory goes beside it (.h5)")
    p.add_argument("--scene", default=None, help="another scene file (default: the 2D hanging-plate example)")
    p.add_argument("--mp4", default=None, help="also write a video (needs the viz extra)")
    p.add_argument("--color", choices=("gamma_dot", "s"), default="gamma_dot")
    _add_run_options(p, dx=DEMO_DX, frames=DEMO_FRAMES, duration=DEMO_DURATION)
    p.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    from .guards import check_output, require_extra
    from .render import render_contact_sheet, render_video

    require_extra("jaxfoam demo", "matplotlib", *(("imageio", "imageio_ffmpeg") if args.mp4 else ()))
    scene = args.scene or find_scene(DEMO_SCENE)
    _check_suffix(args.out, "--out", PICTURE_SUFFIXES)
    if args.mp4:
        _check_suffix(args.mp4, "--mp4", VIDEO_SUFFIXES)
    out = Path(check_output(args.out, "--out", {"--scene": scene}))
    h5 = out.with_suffix(".h5")
    check_output(h5, "the trajectory beside --out", {"--scene": scene})
    if args.mp4:
        check_output(args.mp4, "--mp4", {"--scene": scene, "--out": out, "the trajectory": h5})
    info = run_simulation(scene, h5, dx=args.dx, ppc=args.ppc, dtype=args.dtype, frames=args.frames,
                          duration=args.duration, mu=args.mu, sigma_y=args.sigma_y, eta=args.eta, m=args.m,
                          seed=args.seed, cfl=args.cfl, progress=not args.quiet,
                          max_particles=args.max_particles, max_substeps=args.max_substeps)
    print(f"wrote {h5}: {info['frames']} frames, {info['particles']} particles, {info['wall_s']:.1f} s wall")
    render_contact_sheet(h5, out, n_frames=DEMO_PANELS, color=args.color)
    print(f"wrote {out}")
    if args.mp4:
        render_video(h5, args.mp4, color=args.color)
        print(f"wrote {args.mp4}")
    return 0


SIMULATOR_COMMANDS = ("simulate", "render", "demo", "export")


def build_parser(argv=None) -> argparse.ArgumentParser:
    """The `jaxfoam` parser. The `fitting` package's subcommands are added unless argv names a simulator
    command (so `jaxfoam simulate` never imports the calibration package)."""
    from . import __version__

    parser = argparse.ArgumentParser(prog="jaxfoam", description="Herschel-Bulkley foam on the Material Point "
                                     "Method: simulate scenes, draw trajectories.")
    parser.add_argument("--version", action="version", version=f"jaxfoam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_simulate_parser(sub)
    add_render_parser(sub)
    add_demo_parser(sub)
    add_export_parser(sub)
    command = next((a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")), None)
    if command in SIMULATOR_COMMANDS:
        return parser
    from fitting.cli import add_design_parser, add_fit_parser, add_synth_parser, add_track_parser
    add_synth_parser(sub)
    add_track_parser(sub)
    add_fit_parser(sub)
    add_design_parser(sub)
    return parser


def _show_warning(command):
    """Plausibility warnings as one line `jaxfoam <command>: warning: ...` (others as Python prints them)."""
    import warnings

    from ._scene import PlausibilityWarning

    default = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, PlausibilityWarning):
            sys.stderr.write(f"jaxfoam {command}: warning: {message}\n")
        else:
            default(message, category, filename, lineno, file, line)
    return show


def main(argv=None) -> int:
    """Entry point of the `jaxfoam` command; returns the exit code (0 ok, 1 simulation failed, 2 bad input).

    Bad input, a missing optional dependency or an unusable file ends with one line
    `jaxfoam <command>: error: ...` and exit code 2, never a traceback.
    """
    import warnings

    import jax

    from ._simulate import SimulationError

    if os.environ.get("JAXFOAM_X64", "1") != "0":
        # The command line is an application: float64 for --dtype float64 and fits (JAXFOAM_X64=0: off).
        jax.config.update("jax_enable_x64", True)
    parser = build_parser(argv)
    as_command = argv is None
    args = parser.parse_args(argv)
    prog = f"jaxfoam {args.command}"
    previous = warnings.showwarning
    warnings.showwarning = _show_warning(args.command)
    try:
        code = int(args.func(args) or 0)
        if as_command and code == 143:
            # A SIGTERM that interrupted a compilation leaves JAX in a state whose interpreter teardown
            # can crash (exit -11): the fit log is closed by now, so end the process at once.
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(143)
        return code
    except SimulationError as exc:
        sys.stderr.write(f"\n{prog}: simulation failed: {exc}\n")
        return 1
    except (CLIError, ValueError, ImportError) as exc:
        sys.stderr.write(f"{prog}: error: {exc}\n")
        return 2
    except OSError as exc:  # a file that cannot be read or written (permissions, a full disk)
        name = f" {exc.filename!r}" if getattr(exc, "filename", None) else ""
        sys.stderr.write(f"{prog}: error: file{name}: {exc.strerror or exc}\n")
        return 2
    except MemoryError:
        sys.stderr.write(f"{prog}: error: out of memory; use a coarser grid, fewer frames or a smaller image\n")
        return 2
    finally:
        warnings.showwarning = previous


if __name__ == "__main__":
    sys.exit(main())
