"""Same-run peer comparison: jaxfoam's full HB step against a Taichi toy MLS-MPM step, interleaved.

shared/perf/anchors.md quotes Taichi 1.7.4 (CPU, 2 threads) on the classic 2D MLS-MPM toy (8,192
particles, 128^2 grid, dt 2e-4 s, a weakly compressible fluid with E = 400) at 5.3 M particle-steps/s,
7.6-7.9 M with both cores idle, and advises comparing ratios measured in one run because the machine is
noisy. This script measures both in one process, alternating timed runs so that load changes hit both:

  taichi_toy: the toy written here in Taichi (fluid pressure only; quadratic B-splines, APIC/MLS
    transfer, slip walls 3 cells thick), 2 CPU threads, float32;
  jaxfoam: the 2D float32 case of experiments/bench_step.py (the full Herschel-Bulkley step with
    the return map; 8,192 particles on 128^2, particles sorted by cell for each timed run).
Every round starts both from their initial states, after SETTLE_S of idle time; the reported ratio is
the median of the per-round ratios.

Taichi is not a jaxfoam dependency: `pip install taichi==1.7.4` to run this script. Usage:
python experiments/bench_peer.py [--rounds N]. Writes experiments/bench_peer.md.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import bench_step

N_PARTICLES = 8192   # the anchors' 2D toy size
CELLS = 128          # grid cells per axis
TOY_DT = 2e-4        # s, the toy's time step
TOY_E = 400.0        # Pa, the toy fluid's bulk stiffness (density 1 kg/m^3, particle volume (dx/2)^2)
TOY_STEPS = 100      # substeps per timed toy run (the toy step is ~0.1-0.2 ms)
HB_STEPS = 100       # substeps per timed jaxfoam run, as bench_step's 2D case
# s of idle time before each timed run, so that neither starts while the other's worker threads are
# still spinning down (both runtimes keep their threads busy-waiting for a while after a run).
SETTLE_S = 0.1


def make_taichi_toy(threads: int = 2):
    import taichi as ti
    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, default_fp=ti.f32, random_seed=0, log_level=ti.WARN)
    n, g = N_PARTICLES, CELLS
    dx = 1.0 / g
    p_vol = (0.5 * dx) ** 2
    p_mass = p_vol * 1.0
    x = ti.Vector.field(2, ti.f32, n)
    v = ti.Vector.field(2, ti.f32, n)
    C = ti.Matrix.field(2, 2, ti.f32, n)
    J = ti.field(ti.f32, n)
    gv = ti.Vector.field(2, ti.f32, (g, g))
    gm = ti.field(ti.f32, (g, g))

    @ti.kernel
    def init():
        for p in x:
            x[p] = [ti.random() * 0.4 + 0.2, ti.random() * 0.4 + 0.2]
            v[p] = [0.0, -1.0]
            J[p] = 1.0
            C[p] = ti.Matrix.zero(ti.f32, 2, 2)

    @ti.kernel
    def substep():
        for i, j in gm:
            gv[i, j] = [0.0, 0.0]
            gm[i, j] = 0.0
        for p in x:
            Xp = x[p] / dx
            base = (Xp - 0.5).cast(int)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            stress = -TOY_DT * 4 * TOY_E * p_vol * (J[p] - 1) / dx ** 2
            affine = ti.Matrix([[stress, 0.0], [0.0, stress]]) + p_mass * C[p]
            for i, j in ti.static(ti.ndrange(3, 3)):
                off = ti.Vector([i, j])
                dpos = (off - fx) * dx
                wt = w[i].x * w[j].y
                gv[base + off] += wt * (p_mass * v[p] + affine @ dpos)
                gm[base + off] += wt * p_mass
        for i, j in gm:
            if gm[i, j] > 0:
                gv[i, j] /= gm[i, j]
            gv[i, j].y -= TOY_DT * 9.8
            if i < 3 and gv[i, j].x < 0:
                gv[i, j].x = 0
            if i > g - 3 and gv[i, j].x > 0:
                gv[i, j].x = 0
            if j < 3 and gv[i, j].y < 0:
                gv[i, j].y = 0
            if j > g - 3 and gv[i, j].y > 0:
                gv[i, j].y = 0
        for p in x:
            Xp = x[p] / dx
            base = (Xp - 0.5).cast(int)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(ti.f32, 2)
            new_C = ti.Matrix.zero(ti.f32, 2, 2)
            for i, j in ti.static(ti.ndrange(3, 3)):
                off = ti.Vector([i, j])
                dpos = (off - fx) * dx
                wt = w[i].x * w[j].y
                new_v += wt * gv[base + off]
                new_C += 4 * wt * gv[base + off].outer_product(dpos) / dx ** 2
            v[p] = new_v
            x[p] += TOY_DT * v[p]
            J[p] *= 1 + TOY_DT * new_C.trace()
            C[p] = new_C

    def reset():
        init()
        ti.sync()

    def run(steps):
        for _ in range(steps):
            substep()
        ti.sync()
        return float(np.isfinite(x.to_numpy()).all())

    reset()
    return run, reset


def make_jaxfoam():
    scene, state, params, grid, dt = bench_step.make_case(2, N_PARTICLES, CELLS, jnp.float32)
    rollout = bench_step.make_rollout(scene, grid, dt, HB_STEPS, True, jnp.float32)

    def run():
        out = rollout(state, params)
        jax.block_until_ready(out)
        return float(jnp.all(jnp.isfinite(out.x)))

    return run


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=31, help="interleaved timed runs of each (default 31)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "bench_peer.md"))
    args = ap.parse_args(argv)
    toy, toy_reset = make_taichi_toy()
    hb = make_jaxfoam()
    toy(TOY_STEPS)  # compile and warm up
    hb()
    t_toy, t_hb, loads = [], [], []
    for _ in range(args.rounds):
        # Both start every round from their initial state (the jaxfoam rollout always does): left to
        # run on, the toy's fluid would pile up on the floor over the rounds and slow down (scatter
        # contention), which would favour jaxfoam more the more rounds are run.
        toy_reset()
        time.sleep(SETTLE_S)
        t0 = time.perf_counter()
        ok_toy = toy(TOY_STEPS)
        t_toy.append(time.perf_counter() - t0)
        time.sleep(SETTLE_S)
        t0 = time.perf_counter()
        ok_hb = hb()
        t_hb.append(time.perf_counter() - t0)
        loads.append(os.getloadavg()[0])
        if not (ok_toy and ok_hb):
            raise RuntimeError("a benchmark run went non-finite")
    r_toy = [N_PARTICLES * TOY_STEPS / t for t in t_toy]
    r_hb = [N_PARTICLES * HB_STEPS / t for t in t_hb]
    ratios = [a / b for a, b in zip(r_hb, r_toy)]
    med = statistics.median
    lines = ["# Same-run peer comparison: jaxfoam HB step vs Taichi toy MLS-MPM (2D, float32)", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores; JAX {jax.__version__}; Taichi 1.7.4 on "
             f"2 CPU threads; {args.rounds} interleaved rounds of {TOY_STEPS} toy and {HB_STEPS} jaxfoam substeps "
             f"on {N_PARTICLES} particles, {CELLS}^2 grid; load average during the rounds "
             f"{min(loads):.1f}-{max(loads):.1f}. Regenerate: `python experiments/bench_peer.py` (needs "
             "`pip install taichi==1.7.4`).", "",
             "| | M particle-steps/s (median) | min | max |", "|---|---|---|---|",
             f"| Taichi toy (fluid, E = 400 Pa) | {med(r_toy) / 1e6:.2f} | {min(r_toy) / 1e6:.2f} | {max(r_toy) / 1e6:.2f} |",
             f"| jaxfoam full HB step | {med(r_hb) / 1e6:.2f} | {min(r_hb) / 1e6:.2f} | {max(r_hb) / 1e6:.2f} |",
             f"| ratio jaxfoam / Taichi, per round | {med(ratios):.2f} | {min(ratios):.2f} | {max(ratios):.2f} |", "",
             f"Issue goal (2D HB step at least as fast as Taichi's toy step): median same-round ratio "
             f"{med(ratios):.2f} ({'met' if med(ratios) >= 1.0 else 'missed'})."]
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
