"""Benchmark: cost of gradients of a 2D hanging-plate rollout, as ratios to the forward run.

For the 2D hanging plate (experiments/scenes/hanging_plate_2d.json) at two grid spacings, three
jit-compiled calls at the same parameters (shaving cream: mu 200 Pa, sigma_y 20 Pa, eta 5 Pa s^m,
m 0.5) over FRAMES frames (FRAME_DT s apart, CFL substeps in between), float64:
  forward  the rollout and the per-frame mean foam height (T,), m;
  reverse  value and gradient of the mean over frames of that height w.r.t. (mu, sigma_y, eta, m),
           reverse mode through the per-frame checkpoints (`adjoint=HandWritten()`);
  jacfwd   the (T, 4) Jacobian of the per-frame heights, forward mode: in 2D the tangents batched by
           jax.jacfwd (`ForwardMode("vmap")`), in 3D one jvp per parameter in sequence
           (`ForwardMode("map", threads=1)`);
  jacobian the same Jacobian by the default route (`jaxfoam.adjoint.DEFAULT_JACOBIAN`: one jvp per
           parameter, in the tuning's concurrent column groups);
  reverse, no checkpoint (run on the coarse 2D grid only): the same gradient with the plain scan
           tape, as a reference for what checkpointing saves; on the other grids it is compiled but
           not run, and the buffers its program plans (gigabytes on the fine grid) are listed.
Time: a fresh process per grid spacing compiles all calls, then runs `repeats` rounds with the
calls interleaved (so machine load hits them alike); its medians of wall-clock and of process CPU
time give its ratios to the forward run. `runs` such processes run one after another per grid
spacing (3 in the full run): the ratios reported are the medians over them, each run's listed.
Memory: every (grid, call) in its own fresh process: compile, one warm-up call, then the peak
resident set is reset (Linux /proc/self/clear_refs = 5) and the working memory of one more call is
VmHWM - VmRSS(before the call) from /proc/self/status, and the peak VmHWM itself (runtime and
compiled code included) is listed too.

With --one-core every worker process is pinned to one CPU core (sched_setaffinity), so XLA runs one
thread: wall and CPU time then agree and measure the work of each call, without the second core that
some calls use and others do not, and without the thread pool's spin-waiting that CPU time counts.

With --3d the same calls run on the 3D hanging plate (experiments/scenes/hanging_plate_3d.json) at one
grid spacing (FULL_3D), without the plain-tape reference.

Writes experiments/bench_grad.md (bench_grad_quick.md with --quick, bench_grad_1core.md with
--one-core, bench_grad_3d.md with --3d, the suffixes combined) next to this script.
Usage: python experiments/bench_grad.py [--quick] [--one-core] [--3d]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = {2: os.path.join(HERE, "scenes", "hanging_plate_2d.json"),
          3: os.path.join(HERE, "scenes", "hanging_plate_3d.json")}
# Shaving-cream parameters (Pa, Pa, Pa s^m, -): mid-range of the values the fits expect.
PARAMS = dict(mu=200.0, sigma_y=20.0, eta=5.0, m=0.5)
FRAME_DT = 0.005  # s between frames (a 200 fps camera)
# Goals of the gradient issue: reverse <= 4x forward time, jacfwd(4) <= 6x, gradient memory <= 3x.
GOALS = {"reverse": (4.0, 3.0), "jacfwd": (6.0, None)}
# runs: timing processes per grid spacing. One process's ratios move by up to 10% between runs of the
# same code on the shared machine, so the verdict takes the median over runs and lists each run's ratio.
FULL = dict(dxs=(0.005, 0.0025), frames=10, repeats=5, runs=3)
QUICK = dict(dxs=(0.01,), frames=3, repeats=2, runs=1)
# --3d: the 3D hanging plate at one grid (6,798 particles at dx 1 cm), fewer frames: its jacfwd call takes
# about 3 s per frame's worth of substeps on this machine.
FULL_3D = dict(dxs=(0.01,), frames=5, repeats=5, runs=3)
QUICK_3D = dict(dxs=(0.02,), frames=2, repeats=2, runs=1)
MODES = ("forward", "reverse", "jacfwd", "jacobian", "reverse_nockpt")
JACFWD_ROUTE = {2: "the 4 tangents batched, ForwardMode('vmap')",
                3: "one jvp rollout per parameter in sequence, ForwardMode('map', threads=1)"}


def _build(dx, frames, dim=2):
    """Simulator, params and the three jitted calls for one grid spacing (dim: which scene)."""
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)  # float64 (jaxfoam leaves JAX's configuration alone)
    import jaxfoam as jf
    from jaxfoam.adjoint import Autodiff, ForwardMode, HandWritten

    scene = jf.load_scene(SCENES[dim])
    params = jf.Params(kappa=scene.kappa, rho=scene.density, **PARAMS)
    sim = jf.Simulator(scene, [FRAME_DT * (k + 1) for k in range(frames)], params, dx=dx)

    def heights(fr):
        """Mean foam height per frame, m, (T,)."""
        w = fr["active"].astype(fr["x"].dtype)
        return jnp.sum(fr["x"][:, :, 1] * w, axis=1) / jnp.sum(w, axis=1)

    def loss(fr):
        return jnp.mean(heights(fr))

    # The forward run as users run it: compiled with XLA's default options, as `jaxfoam.rollout` and
    # `jaxfoam.simulate` are (the tuning's compiler options serve the differentiated programs).
    fwd = jax.jit(lambda p, s0, sc: heights(sim.rollout(p, state0=s0, scene=sc)[1]))
    forward = lambda p: fwd(p, sim.state0, sim.scene)
    forward.lower = lambda p: fwd.lower(p, sim.state0, sim.scene)
    calls = {
        "forward": forward,
        "reverse": jf.make_observable_jacobian(sim, loss, adjoint=HandWritten()),
        "jacfwd": jf.make_observable_jacobian(
            sim, heights, adjoint=ForwardMode("vmap") if dim == 2 else ForwardMode("map", threads=1)),
        # The default Jacobian route of observable_jacobian and the fitter (DEFAULT_JACOBIAN).
        "jacobian": jf.make_observable_jacobian(sim, heights),
        "reverse_nockpt": jf.make_observable_jacobian(sim, loss, adjoint=Autodiff()),
    }
    return sim, params, calls


def _block(out):
    import jax
    return jax.block_until_ready(out)


def _status_kb(field):
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def worker_time(dx, frames, repeats, modes, dim=2):
    sim, params, calls = _build(dx, frames, dim)
    compile_s = {}
    for m in modes:
        t0 = time.perf_counter()
        _block(calls[m](params))
        compile_s[m] = time.perf_counter() - t0
    times = {m: [] for m in modes}
    cpu = {m: [] for m in modes}
    for _ in range(repeats):
        for m in modes:
            t0, c0 = time.perf_counter(), time.process_time()
            _block(calls[m](params))
            times[m].append(time.perf_counter() - t0)
            cpu[m].append(time.process_time() - c0)
    n = int(sim.state0.active.sum())
    return dict(dx=dx, particles=n, substeps=sim.total_substeps, frames=frames, dt=sim.dt,
                compile_s=compile_s, times=times, cpu=cpu)


def worker_memory(dx, frames, mode, dim=2):
    import gc
    sim, params, calls = _build(dx, frames, dim)
    xla = calls[mode].lower(params).compile().memory_analysis()
    xla_mb = (xla.temp_size_in_bytes + xla.argument_size_in_bytes + xla.output_size_in_bytes) / 2**20
    _block(calls[mode](params))  # compile and warm up
    gc.collect()
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")  # reset VmHWM to the current resident set
    rss0 = _status_kb("VmRSS")
    out = _block(calls[mode](params))
    hwm = _status_kb("VmHWM")
    del out
    return dict(dx=dx, mode=mode, xla_mb=xla_mb, xla_temp_mb=xla.temp_size_in_bytes / 2**20, rss_before_mb=rss0 / 1024, hwm_mb=hwm / 1024, peak_mb=(hwm - rss0) / 1024,
                maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def worker_plan(dx, frames, mode, dim=2):
    """The compiled program's planned buffers only (`memory_analysis()`), without running it: for the
    plain-tape reverse call on grids where running it would hold gigabytes."""
    sim, params, calls = _build(dx, frames, dim)
    xla = calls[mode].lower(params).compile().memory_analysis()
    return dict(dx=dx, mode=mode, plan_only=True, xla_temp_mb=xla.temp_size_in_bytes / 2**20,
                xla_mb=(xla.temp_size_in_bytes + xla.argument_size_in_bytes + xla.output_size_in_bytes) / 2**20)


def _pin_one_core():
    """Pin the calling (child) process to the lowest CPU core it may run on."""
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def _run_worker(args, cache_dir, one_core=False):
    cmd = [sys.executable, os.path.abspath(__file__), "--worker"] + [str(a) for a in args]
    # The timing process compiles first and fills a persistent cache private to this benchmark run;
    # the memory processes load from it instead of compiling again (compile time is not measured there).
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache_dir, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
               JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
               # a fixed mmap threshold: buffers >= 64 kB are mapped and unmapped one by one, so freed
               # buffers of the warm-up call are not kept in malloc's arenas and reused unseen
               MALLOC_MMAP_THRESHOLD_="65536")
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, preexec_fn=_pin_one_core if one_core else None)
    if res.returncode != 0:
        raise RuntimeError(f"worker {args} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _modes_for(dx, dxs, dim=2):
    # The plain-scan tape runs only on the coarse 2D grid: on the fine grid and in 3D it needs gigabytes
    # (elsewhere only its compiled program's planned memory is reported, `worker_plan`).
    return MODES if dx == max(dxs) and dim == 2 else tuple(m for m in MODES if m != "reverse_nockpt")


def _ratios(run, m):
    """(CPU, wall) median time of call m over forward's, within one timing process."""
    return (statistics.median(run["cpu"][m]) / statistics.median(run["cpu"]["forward"]),
            statistics.median(run["times"][m]) / statistics.median(run["times"]["forward"]))


def _table(time_runs, mem_rows):
    """time_runs: per grid spacing, the list of its timing processes' results (`worker_time`)."""
    lines = ["| dx (m) | particles | substeps | call | wall (s) | CPU (s) | CPU / forward | wall / forward | "
             "wall / forward per run | XLA buffers (MB) | / forward | RSS rise in call (MB) | peak RSS in call (MB) | "
             "/ forward | compile (s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    verdicts = []
    for runs in time_runs:
        tr = runs[0]
        dx = tr["dx"]
        mem = {r["mode"]: r for r in mem_rows if r["dx"] == dx}
        for m in tr["times"]:
            per_run = [_ratios(r, m) for r in runs]
            cratio = statistics.median(c for c, _ in per_run)
            wratio = statistics.median(w for _, w in per_run)
            wall = statistics.median(statistics.median(r["times"][m]) for r in runs)
            cpu = statistics.median(statistics.median(r["cpu"][m]) for r in runs)
            wm = mem[m]["xla_mb"] / mem["forward"]["xla_mb"]
            hm = mem[m]["hwm_mb"] / mem["forward"]["hwm_mb"]
            lines.append(f"| {dx:g} | {tr['particles']} | {tr['substeps']} | {m} | {wall:.2f} | {cpu:.2f} | "
                         f"{cratio:.2f} | {wratio:.2f} | {', '.join(f'{w:.2f}' for _, w in per_run)} | "
                         f"{mem[m]['xla_mb']:.1f} | {wm:.1f} | {mem[m]['peak_mb']:.1f} | "
                         f"{mem[m]['hwm_mb']:.0f} | {hm:.2f} | {tr['compile_s'][m]:.1f} |")
            if m in GOALS:
                tg, mg = GOALS[m]
                worst = max(max(c, w) for c, w in per_run)
                text = (f"- dx {dx:g} m, {m}: CPU time {cratio:.2f}x forward, wall {wratio:.2f}x, medians of "
                        f"{len(runs)} run(s) (goal <= {tg:g}x: "
                        f"{'met' if max(cratio, wratio) <= tg else ('met on one measure' if min(cratio, wratio) <= tg else 'missed')}"
                        f"{'' if len(runs) == 1 else '; in every run on both measures' if worst <= tg else f'; the worst run {worst:.2f}x'}"
                        f"; CPU ratio per run {', '.join(f'{c:.2f}' for c, _ in per_run)})")
                if mg is not None:
                    text += (f"; peak RSS in the call {hm:.2f}x forward's, XLA working buffers {wm:.1f}x "
                             f"(goal <= {mg:g}x: {'met' if hm <= mg else 'missed'} on peak RSS, "
                             f"{'met' if wm <= mg else 'missed'} on working buffers)")
                verdicts.append(text)
        for r in mem_rows:
            if r["dx"] == dx and r.get("plan_only"):
                wm = r["xla_mb"] / mem["forward"]["xla_mb"]
                lines.append(f"| {dx:g} | {tr['particles']} | {tr['substeps']} | {r['mode']} (compiled, not run) | "
                             f"- | - | - | - | - | {r['xla_mb']:.1f} | {wm:.1f} | - | - | - | - |")
                verdicts.append(f"- dx {dx:g} m, {r['mode']}: not run; its compiled program plans {r['xla_mb']:.0f} MB "
                                f"of buffers, {r['xla_mb'] / mem['reverse']['xla_mb']:.1f}x the checkpointed "
                                f"reverse call's {mem['reverse']['xla_mb']:.0f} MB")
    return "\n".join(lines) + "\n", "\n".join(verdicts) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one coarse grid, 3 frames, 2 repeats (a fast check)")
    ap.add_argument("--one-core", action="store_true", help="pin every worker to one CPU core (writes bench_grad_1core.md)")
    ap.add_argument("--3d", dest="three_d", action="store_true",
                    help="the 3D hanging plate at one grid instead (writes bench_grad_3d[_1core].md)")
    ap.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        kind, rest = args.worker[0], args.worker[1:]
        if kind == "time":
            out = worker_time(float(rest[0]), int(rest[1]), int(rest[2]), rest[3].split(","), int(rest[4]))
        elif kind == "plan":
            out = worker_plan(float(rest[0]), int(rest[1]), rest[2], int(rest[3]))
        else:
            out = worker_memory(float(rest[0]), int(rest[1]), rest[2], int(rest[3]))
        print(json.dumps(out))
        return 0
    dim = 3 if args.three_d else 2
    cfg = (QUICK_3D if args.quick else FULL_3D) if dim == 3 else (QUICK if args.quick else FULL)
    t_start = time.perf_counter()
    time_runs, mem_rows = [], []
    cache_dir = tempfile.mkdtemp(prefix="bench_grad_cache_")
    for dx in cfg["dxs"]:
        modes = _modes_for(dx, cfg["dxs"], dim)
        runs = []
        for k in range(cfg["runs"]):
            print(f"dx = {dx} m: timing {', '.join(modes)} (run {k + 1} of {cfg['runs']}) ...", flush=True)
            runs.append(_run_worker(["time", dx, cfg["frames"], cfg["repeats"], ",".join(modes), dim], cache_dir,
                                    args.one_core))
        time_runs.append(runs)
        for m in modes:
            print(f"dx = {dx} m: memory of {m} ...", flush=True)
            mem_rows.append(_run_worker(["memory", dx, cfg["frames"], m, dim], cache_dir, args.one_core))
        if "reverse_nockpt" not in modes:
            print(f"dx = {dx} m: planned memory of reverse_nockpt (compile only) ...", flush=True)
            mem_rows.append(_run_worker(["plan", dx, cfg["frames"], "reverse_nockpt", dim], cache_dir, args.one_core))
    shutil.rmtree(cache_dir, ignore_errors=True)
    table, verdicts = _table(time_runs, mem_rows)
    import jax
    from jaxfoam._xla_cpu import tuning_for
    name = f"bench_grad{'_3d' if dim == 3 else ''}{'_quick' if args.quick else ''}{'_1core' if args.one_core else ''}.md"
    flags = (" --3d" if dim == 3 else "") + (" --quick" if args.quick else "") + (" --one-core" if args.one_core else "")
    cores = (f"every worker process pinned to 1 of {os.cpu_count()} CPU cores" if args.one_core
             else f"{os.cpu_count()} CPU cores")
    body = (f"# Gradient cost: {dim}D hanging plate\n\n"
            f"_{'quick' if args.quick else 'full'} run; regenerate with `python experiments/bench_grad.py"
            f"{flags}` ({time.perf_counter() - t_start:.0f} s). "
            f"{platform.machine()}, {cores} shared with other jobs, JAX {jax.__version__}, "
            f"float64, {time.strftime('%Y-%m-%d')}._\n\n"
            f"Scene `experiments/scenes/hanging_plate_{dim}d.json`, parameters {PARAMS}, {cfg['frames']} frames "
            f"{FRAME_DT} s apart, CFL substeps. forward = rollout + per-frame mean height (T,); reverse = "
            f"value and gradient of its mean w.r.t. (mu, sigma_y, eta, m) through per-frame checkpoints; "
            f"jacfwd = the (T, 4) Jacobian in forward mode "
            f"({JACFWD_ROUTE[dim]}); jacobian = the same by the default route (DEFAULT_JACOBIAN: one jvp "
            f"rollout per parameter, in the tuning's 2 concurrent column groups); "
            f"reverse_nockpt = reverse mode with the plain "
            f"scan tape (run on the coarse 2D grid only; elsewhere compiled, and its planned buffers "
            f"listed). The forward call is compiled with XLA's default options, as "
            f"`jaxfoam.simulate` runs it; the gradient calls with the tuning's compiler options "
            f"({dict(tuning_for().compiler_options)}). Times: medians of {cfg['repeats']} interleaved repeats in one "
            f"process, wall clock and process CPU time, in {cfg['runs']} such process(es) per grid (each "
            f"compiles afresh; the ratios and times listed are medians over them, and `per run` lists each "
            f"process's ratio: the machine is shared). Memory, each call in a fresh process: XLA buffers = temp + argument + "
            f"output bytes of the compiled program (`memory_analysis()`, the working memory XLA plans); "
            f"after a warm-up call, peak RSS in call = VmHWM during one more call (reset through "
            f"/proc/self/clear_refs just before it; includes the JAX runtime and compiled code) and RSS "
            f"rise = that peak minus the resident set just before the call (malloc's mmap threshold fixed "
            f"at 64 kB so freed buffers are not silently reused); the RSS rise reproduces the XLA figure."
            f"\n\n{table}\nGoals (reverse <= 4x forward time, jacfwd(4) <= 6x, "
            f"gradient memory <= 3x):\n{verdicts}")
    path = os.path.join(HERE, name)
    with open(path, "w") as fh:
        fh.write(body)
    print(body)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
