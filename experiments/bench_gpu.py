"""Benchmark on an accelerator: the step at 8,192 and 1,000,000 particles and bench_grad's calls, one process.

Step cases (the random foam block of `bench_step.py`, particles per occupied cell held at its 8,192-particle
2D and 32,768-particle 3D density): 2D and 3D, 8,192 and 1,000,000 particles, float32 and float64, with the
backend's tuning (`jaxfoam._xla_cpu.tuning_for()`); at 1,000,000 particles also with the particles sorted by
grid cell each frame, and in 2D float32 with the XLA:CPU tuning, to measure those choices on this backend.
Gradient cases: bench_grad.py's hanging plate in float64 (2D dx 5 mm and 2.5 mm, 10 frames; 3D dx 1 cm, 5
frames), the forward call, reverse mode through the checkpoints and the default Jacobian route, each
compiled, then timed interleaved (median of 3 runs).

Every finished case is appended to <out>.json at once (a run cut short keeps what it measured);
<out>.md is the table of them. Usage:
  python -m experiments bench_gpu [--out experiments/results/bench_gpu] [--quick] [--only step|grad]
  python -m experiments bench_gpu --report   (rewrite the table from the json)
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)  # float64 cases; jaxfoam leaves the config alone
import jax.numpy as jnp

from experiments import bench_grad, bench_step

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "results", "bench_gpu")
# (dim, particles, cells across the unit box): bench_step's 2D density (8,192 on 128^2) and 3D density
# (32,768 on 64^3), scaled by the particle count.
STEP_CASES = [(2, 8192, 128), (2, 1_000_000, 1414), (3, 8192, 40), (3, 1_000_000, 203)]
GRAD_CASES = [(2, 0.005, 10), (2, 0.0025, 10), (3, 0.01, 5)]
GRAD_MODES = ("forward", "reverse", "jacobian")
# Goal of the batched-evaluation issue on one GPU: 2D float32 at 1,000,000 particles, particle-steps/s.
GOAL_2D_F32_1M = 100e6


def _append(path, row):
    rows = _load(path)
    rows.append(row)
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(rows, fh, indent=1)
    os.replace(tmp, path)


def _load(path):
    if not os.path.exists(path):
        return []
    with open(path) as fh:
        return json.load(fh)


def _machine():
    dev = jax.devices()[0]
    return dict(backend=jax.default_backend(), device=getattr(dev, "device_kind", str(dev)),
                jax=jax.__version__, host=platform.machine(), cores=os.cpu_count())


def step_case(dim, n, cells, dtype, steps, repeats, variant):
    """One bench_step case; variant: 'backend' (tuning_for()), 'sorted' (that + sort_by_cell), 'xla_cpu'."""
    from jaxfoam._xla_cpu import XLA_CPU, tuning_for
    scene, state, params, grid, dt = bench_step.make_case(dim, n, cells, dtype)
    tuning = {"backend": tuning_for(), "sorted": tuning_for().replace(sort_by_cell=True), "xla_cpu": XLA_CPU}[variant]
    rollout = bench_step.make_rollout(scene, grid, dt, steps, None, dtype, tuning=tuning)
    out, compile_s, runs = bench_step.time_runs(rollout, state, params, repeats)
    finite = bool(jnp.all(jnp.isfinite(out.x)))
    med = statistics.median(runs)
    return dict(kind="step", dim=dim, n=n, cells=cells, dtype=jnp.dtype(dtype).name, variant=variant, steps=steps,
                compile_s=compile_s, median_s=med, rate=n * steps / med, best_rate=n * steps / min(runs),
                finite=finite)


def grad_case(dim, dx, frames, repeats):
    sim, params, calls = bench_grad._build(dx, frames, dim)
    compile_s, times = {}, {m: [] for m in GRAD_MODES}
    for m in GRAD_MODES:
        t0 = time.perf_counter()
        bench_grad._block(calls[m](params))
        compile_s[m] = time.perf_counter() - t0
    for _ in range(repeats):
        for m in GRAD_MODES:
            t0 = time.perf_counter()
            bench_grad._block(calls[m](params))
            times[m].append(time.perf_counter() - t0)
    return dict(kind="grad", dim=dim, dx=dx, frames=frames, particles=int(sim.state0.active.sum()),
                substeps=int(sim.total_substeps), compile_s=compile_s,
                median_s={m: statistics.median(v) for m, v in times.items()})


def report(path):
    rows = _load(path + ".json")
    meta = [r for r in rows if r["kind"] == "machine"]
    m = meta[-1] if meta else {}
    lines = ["# The step and the gradient calls on an accelerator", "",
             f"_Regenerate with `python -m experiments bench_gpu` on the machine. Backend {m.get('backend')}, "
             f"{m.get('device')}, JAX {m.get('jax')}, {m.get('date', '')}._"]
    steps = [r for r in rows if r["kind"] == "step"]
    if steps:
        lines += ["", "## The step (bench_step.py's foam block), M particle-steps/s", "",
                  "| case | particles | grid | dtype | tuning | substeps per run | median | best | compile s |",
                  "|---|---|---|---|---|---|---|---|---|"]
    for r in steps:
        lines.append(f"| {r['dim']}D | {r['n']:,} | {r['cells']}^{r['dim']} | {r['dtype']} | {r['variant']} | {r['steps']} | "
                     f"{r['rate'] / 1e6:.1f} | {r['best_rate'] / 1e6:.1f} | {r['compile_s']:.1f}"
                     + (" |" if r["finite"] else " (NON-FINITE) |"))
    grads = [r for r in rows if r["kind"] == "grad"]
    if grads:
        lines += ["", "## Gradients (bench_grad.py's hanging plate, float64)", "",
                  "| case | particles | substeps | forward s | reverse / forward | jacobian / forward | compile s (fwd, rev, jac) |",
                  "|---|---|---|---|---|---|---|"]
        for r in grads:
            t, c = r["median_s"], r["compile_s"]
            lines.append(f"| {r['dim']}D dx {r['dx'] * 1000:g} mm, {r['frames']} frames | {r['particles']:,} | {r['substeps']} | "
                         f"{t['forward']:.3f} | {t['reverse'] / t['forward']:.2f}x | {t['jacobian'] / t['forward']:.2f}x | "
                         f"{c['forward']:.1f}, {c['reverse']:.1f}, {c['jacobian']:.1f} |")
    goal = [r for r in steps if (r["dim"], r["n"], r["dtype"], r["variant"]) == (2, 1_000_000, "float32", "backend")]
    if goal:
        rate = goal[0]["rate"]
        lines += ["", f"Goal (2D float32 at 1,000,000 particles, at least {GOAL_2D_F32_1M / 1e6:.0f} M particle-steps/s): "
                  f"{rate / 1e6:.1f} M, {'met' if rate >= GOAL_2D_F32_1M else 'missed'}."]
    with open(path + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=OUT, help="path stem of the .json and .md written")
    ap.add_argument("--quick", action="store_true", help="the 8,192-particle cases and 2D dx 5 mm only, 2 repeats")
    ap.add_argument("--only", choices=("step", "grad"), help="run one part")
    ap.add_argument("--report", action="store_true", help="only rewrite <out>.md from <out>.json")
    args = ap.parse_args(argv)
    if args.report:
        report(args.out)
        return 0
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    path = args.out + ".json"
    if os.path.exists(path):
        os.remove(path)
    _append(path, dict(kind="machine", date=time.strftime("%Y-%m-%d"), **_machine()))
    repeats = 2 if args.quick else 3
    if args.only != "grad":
        for dim, n, cells in STEP_CASES:
            if args.quick and n > 8192:
                continue
            variants = ["backend"] + (["sorted"] if n > 8192 else [])
            for dtype in (jnp.float32, jnp.float64):
                extra = ["xla_cpu"] if (n > 8192 and dim == 2 and dtype == jnp.float32) else []
                for variant in variants + extra:
                    r = step_case(dim, n, cells, dtype, 100 if dim == 2 else 25, repeats, variant)
                    _append(path, r)
                    print(f"step {dim}D {n} {r['dtype']} {variant}: {r['rate'] / 1e6:.1f} M particle-steps/s "
                          f"(compile {r['compile_s']:.1f} s)", flush=True)
    if args.only != "step":
        for dim, dx, frames in GRAD_CASES:
            if args.quick and (dim, dx) != (2, 0.005):
                continue
            r = grad_case(dim, dx, frames, repeats)
            _append(path, r)
            t = r["median_s"]
            print(f"grad {dim}D dx {dx}: forward {t['forward']:.3f} s, reverse {t['reverse'] / t['forward']:.2f}x, "
                  f"jacobian {t['jacobian'] / t['forward']:.2f}x (compile {r['compile_s']})", flush=True)
    report(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
