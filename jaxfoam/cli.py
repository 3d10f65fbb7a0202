"""Command line: `jaxfoam simulate`, `jaxfoam render`, `jaxfoam demo`.

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
    """A user error reported as `jaxfoam: error: ...` with exit code 2."""


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
                   seed=0, cfl=None, frames_per_block=1, progress=True, creator=None) -> dict:
    """Simulate a scene file and write its trajectory (HDF5) to `out`; returns a summary dict.

    Records the initial state at t = 0 and `frames` frames evenly spaced over (0, duration] s. The rollout
    runs `frames_per_block` frames per call to `Simulator.rollout`, each block starting from the previous
    block's final state with the same grid, substep count and dt, and appends each block to the file as it
    finishes (a run that fails part-way leaves a file marked incomplete). Raises SimulationError if the
    state turns non-finite.
    """
    import jax
    import jax.numpy as jnp

    from ._params import Params
    from ._scene import load_scene
    from ._model import CFL
    from ._rollout import observe_default
    from ._rollout import rollout
    from ._simulate import Simulator
    from .adjoint import Autodiff
    from ._trajectory import TrajectoryWriter

    jdtype = _dtype(dtype)
    scene = load_scene(scene_path, dtype=jdtype)
    if not (isinstance(frames, int) and frames >= 1):
        raise CLIError(f"--frames must be an integer >= 1, got {frames!r}")
    if not (duration > 0 and math.isfinite(duration)):
        raise CLIError(f"--duration must be a positive time in s, got {duration!r}")
    if not (isinstance(frames_per_block, int) and frames_per_block >= 1):
        raise CLIError(f"frames_per_block must be an integer >= 1, got {frames_per_block!r}")
    dx = default_dx(scene) if dx is None else float(dx)
    params = Params(mu=float(mu), kappa=scene.kappa, sigma_y=float(sigma_y), eta=float(eta), m=float(m),
                    rho=scene.density).validate()
    times = duration * np.arange(1, frames + 1) / frames
    sim = Simulator(scene, times, params, dx, ppc, dtype=jdtype, seed=seed, cfl=CFL if cfl is None else cfl)
    n_active = int(sim.state0.active.sum())
    d = scene.dim
    ppc_used = int(ppc) if ppc is not None else {2: 4, 3: 8}[d]
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
    p.add_argument("--dx", type=float, default=dx,
                   help="grid spacing, m (default: the largest domain extent / 64 in 2D, / 32 in 3D)"
                   if dx is None else f"grid spacing, m (default {dx})")
    p.add_argument("--ppc", type=int, default=None, help="particles per cell (default 4 in 2D, 8 in 3D)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision (default float64)")
    p.add_argument("--frames", type=int, default=frames, help=f"frames recorded after t = 0 (default {frames})")
    p.add_argument("--duration", type=float, default=duration, help=f"simulated time, s (default {duration})")
    p.add_argument("--mu", type=float, default=DEFAULT_MU, help=f"shear modulus, Pa (default {DEFAULT_MU})")
    p.add_argument("--sigma-y", dest="sigma_y", type=float, default=DEFAULT_SIGMA_Y,
                   help=f"yield stress, Pa (default {DEFAULT_SIGMA_Y})")
    p.add_argument("--eta", type=float, default=DEFAULT_ETA,
                   help=f"Herschel-Bulkley consistency, Pa s^m (default {DEFAULT_ETA})")
    p.add_argument("--m", type=float, default=DEFAULT_M, help=f"Herschel-Bulkley exponent (default {DEFAULT_M})")
    p.add_argument("--seed", type=int, default=0, help="particle sampling seed (default 0)")
    p.add_argument("--cfl", type=float, default=None, help="CFL number of the time step (default jaxfoam.CFL)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def cmd_simulate(args) -> int:
    info = run_simulation(args.scene, args.out, dx=args.dx, ppc=args.ppc, dtype=args.dtype, frames=args.frames,
                          duration=args.duration, mu=args.mu, sigma_y=args.sigma_y, eta=args.eta, m=args.m,
                          seed=args.seed, cfl=args.cfl, progress=not args.quiet)
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
    p.add_argument("--panels", type=int, default=8, help="frames on the contact sheet (default 8)")
    p.add_argument("--fps", type=float, default=20.0, help="video frames per second (default 20)")
    p.set_defaults(func=cmd_render)


def cmd_render(args) -> int:
    from .render import render_contact_sheet, render_video

    render_contact_sheet(args.trajectory, args.out, n_frames=args.panels, color=args.color)
    print(f"wrote {args.out}")
    if args.mp4:
        render_video(args.trajectory, args.mp4, fps=args.fps, color=args.color)
        print(f"wrote {args.mp4}")
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
    from .render import render_contact_sheet, render_video

    scene = args.scene or find_scene(DEMO_SCENE)
    out = Path(args.out)
    h5 = out.with_suffix(".h5")
    info = run_simulation(scene, h5, dx=args.dx, ppc=args.ppc, dtype=args.dtype, frames=args.frames,
                          duration=args.duration, mu=args.mu, sigma_y=args.sigma_y, eta=args.eta, m=args.m,
                          seed=args.seed, cfl=args.cfl, progress=not args.quiet)
    print(f"wrote {h5}: {info['frames']} frames, {info['particles']} particles, {info['wall_s']:.1f} s wall")
    render_contact_sheet(h5, out, n_frames=DEMO_PANELS, color=args.color)
    print(f"wrote {out}")
    if args.mp4:
        render_video(h5, args.mp4, color=args.color)
        print(f"wrote {args.mp4}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(prog="jaxfoam", description="Herschel-Bulkley foam on the Material Point "
                                     "Method: simulate scenes, draw trajectories.")
    parser.add_argument("--version", action="version", version=f"jaxfoam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_simulate_parser(sub)
    add_render_parser(sub)
    add_demo_parser(sub)
    from .calibrate import add_fit_parser
    from .synth import add_synth_parser
    from .track import add_track_parser
    add_synth_parser(sub)
    add_track_parser(sub)
    add_fit_parser(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the `jaxfoam` command; returns the exit code (0 ok, 1 simulation failed, 2 bad input)."""
    import jax

    from ._simulate import SimulationError

    if os.environ.get("JAXFOAM_X64", "1") != "0":
        # The command line is an application: float64 for --dtype float64 and fits (JAXFOAM_X64=0: off).
        jax.config.update("jax_enable_x64", True)
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except SimulationError as exc:
        sys.stderr.write(f"\njaxfoam: simulation failed: {exc}\n")
        return 1
    except (CLIError, ValueError, FileNotFoundError, ImportError) as exc:
        sys.stderr.write(f"jaxfoam: error: {exc}\n")
        return 2


if __name__ == "__main__":
    sys.exit(main())
