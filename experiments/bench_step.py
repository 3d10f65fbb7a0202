"""Benchmark: particle-steps per second of the full Herschel-Bulkley MLS-MPM step.

Cases (the classic mpm88 sizes of shared/perf/anchors.md):
  2D: 8,192 particles, 128^2 cells;  3D: 32,768 particles, 64^3 cells; float32 and float64.
Each case: compile time of a jitted lax.scan of STEPS substeps, then the median of REPEATS timed runs.
A timed run is one frame of `jaxfoam.rollout` (as `jaxfoam.simulate` runs it): particles sorted by grid
cell, the substeps, the original order restored (sort included in the time); the same without sorting
(the tuning's sort_by_cell off) is reported beside it.
Writes experiments/bench_step.md next to this script. Usage: python experiments/bench_step.py [--quick]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
jax.config.update("jax_enable_x64", True)  # float64 cases and fits; jaxfoam leaves the config alone
import jax.numpy as jnp
import numpy as np

import jaxfoam as jf

# Peer figures on the same 2-core machine (shared/perf/anchors.md), particle-steps/s.
ANCHORS = {"taichi_2d_f32": 5.3e6, "jax_toy_2d_f32": 4.8e6, "jax_toy_2d_f64": 4.0e6,
           "taichi_3d_f64": 1.4e6, "jax_toy_3d": 0.9e6}
CASES = [(2, 8192, 128), (3, 32768, 64)]


def make_case(dim, n, cells, dtype):
    """A yielding foam block in a unit box, particles at random in its lower-middle part."""
    spec = {"kind": "drop", "dim": dim, "density": 80.0, "kappa": 2000.0,
            "gravity": [0.0, -9.81] + [0.0] * (dim - 2),
            "domain": {"min": [0.0] * dim, "max": [1.0] * dim}, "floor": {"y": 0.0, "friction": 0.5},
            "initial_shape": {"type": "box", "min": [0.3] * dim, "max": [0.7] * dim}}
    scene = jf.load_scene(spec, dtype=dtype)
    rng = np.random.default_rng(0)
    x = 0.3 + 0.4 * rng.random((n, dim))
    vol = 0.4 ** dim / n
    state = jf.make_state(x, np.full(n, vol), np.full(n, 80.0 * vol), dtype=dtype)
    params = jf.Params(mu=200.0, kappa=2000.0, sigma_y=20.0, eta=10.0, m=0.5, rho=80.0).astype(dtype)
    dx = 1.0 / cells
    grid = jf.make_grid(scene, dx)
    dt = jf.stable_dt(params, dx, 5.0)
    return scene, state, params, grid, dt


def _observe_x(state, params):
    return state.x


def make_rollout(scene, grid, dt, steps, sort, dtype, tuning=None):
    """One frame of `steps` substeps of dt s through `jaxfoam.rollout` (forward only), jit-compiled; with
    the backend's tuning and `sort` as its sort_by_cell, or `tuning` as given."""
    model = jf.Model(scene=scene, dt=dt, dt_cfl=dt, grid=grid, substeps=steps, dtype=jnp.dtype(dtype).name)
    model = model.replace(tuning=tuning or model.tuning.replace(sort_by_cell=sort))
    times = np.asarray([steps * dt])

    @jax.jit
    def rollout(state, params):
        final, _, _ = jf.rollout(model, state, params, times, observe=_observe_x, adjoint=jf.Autodiff())
        return final
    return rollout


def time_runs(rollout, state, params, repeats):
    t0 = time.perf_counter()
    out = rollout(state, params)
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(rollout(state, params))
        times.append(time.perf_counter() - t0)
    return out, compile_s, times


def run_case(dim, n, cells, dtype, steps, repeats):
    scene, state, params, grid, dt = make_case(dim, n, cells, dtype)
    out, compile_s, times = time_runs(make_rollout(scene, grid, dt, steps, True, dtype), state, params, repeats)
    _, _, times_unsorted = time_runs(make_rollout(scene, grid, dt, steps, False, dtype), state, params, repeats)

    if not bool(jnp.all(jnp.isfinite(out.x))):
        raise RuntimeError(f"benchmark case {dim}D went non-finite")
    med = statistics.median(times)
    return dict(dim=dim, n=n, cells=cells, dtype=jnp.dtype(dtype).name, steps=steps, compile_s=compile_s,
                median_s=med, rate=n * steps / med, best_rate=n * steps / min(times),
                rate_unsorted=n * steps / statistics.median(times_unsorted))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "bench_step.md"))
    args = ap.parse_args(argv)
    # The machine is shared and noisy (+-30% between runs): the full run takes 7 repeats and reports the
    # median and the best.
    steps, repeats = (20, 2) if args.quick else (100, 7)
    rows = []
    for dim, n, cells in CASES:
        for dtype in (jnp.float32, jnp.float64):
            r = run_case(dim, n, cells, dtype, steps if dim == 2 else max(steps // 4, 5), repeats)
            rows.append(r)
            print(f"{dim}D {r['dtype']}: {r['rate'] / 1e6:.2f} M particle-steps/s "
                  f"(compile {r['compile_s']:.1f} s)", flush=True)
    load = os.getloadavg()[0]
    lines = ["# Full HB MLS-MPM step: particle-steps per second", "",
             f"Load average when measured: {load:.1f} on {os.cpu_count()} cores (peers in shared/perf/anchors.md "
             "were measured on an idle machine; compare only runs at similar load).", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores; JAX {jax.__version__}; "
             f"steps per timed run: 2D {steps}, 3D {max(steps // 4, 5)}; median and best of {repeats} runs "
             "(ratios use the median).", "",
             "| case | particles | grid | dtype | M particle-steps/s (median) | best | unsorted (median) | vs Taichi toy 2D f32 (5.3 M) | vs JAX toy (same dim) | vs Taichi 3D f64 (1.4 M) | compile s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        toy = ANCHORS["jax_toy_2d_f32" if r["dtype"] == "float32" else "jax_toy_2d_f64"] if r["dim"] == 2 else ANCHORS["jax_toy_3d"]
        lines.append(f"| {r['dim']}D | {r['n']} | {r['cells']}^{r['dim']} | {r['dtype']} | {r['rate'] / 1e6:.2f} | {r['best_rate'] / 1e6:.2f} | {r['rate_unsorted'] / 1e6:.2f} | "
                     f"{r['rate'] / ANCHORS['taichi_2d_f32']:.2f} | {r['rate'] / toy:.2f} | "
                     f"{r['rate'] / ANCHORS['taichi_3d_f64']:.2f} | {r['compile_s']:.1f} |")
    by = {(r["dim"], r["dtype"]): r["rate"] for r in rows}
    lines += ["", "Goals (issue: 2D HB step at least as fast as Taichi's toy step, 5.3 M in float32; 3D at least 1 M):",
              f"- 2D float32: {by[(2, 'float32')] / 1e6:.2f} M = {by[(2, 'float32')] / ANCHORS['taichi_2d_f32']:.2f}x "
              f"Taichi's toy step ({'met' if by[(2, 'float32')] >= ANCHORS['taichi_2d_f32'] else 'missed'})",
              f"- 3D float32: {by[(3, 'float32')] / 1e6:.2f} M, float64: {by[(3, 'float64')] / 1e6:.2f} M "
              f"(goal 1 M: {'met' if by[(3, 'float32')] >= 1e6 else 'missed'} in float32, "
              f"{'met' if by[(3, 'float64')] >= 1e6 else 'missed'} in float64)"]
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
