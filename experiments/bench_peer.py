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

`--peer warp` runs the same toy written in Warp kernels on Warp's CPU device instead (Warp ships no MPM
example). Neither is a jaxfoam dependency: `pip install taichi==1.7.4` or `pip install warp-lang`. Usage:
python experiments/bench_peer.py [--peer taichi|warp] [--rounds N]. Writes experiments/bench_peer.md or
experiments/bench_peer_warp.md.
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


def make_warp_toy():
    """The same toy in Warp kernels on Warp's CPU device (which runs a launch on one thread)."""
    import warp as wp
    wp.config.quiet = True
    wp.init()
    N, G, DT, E = N_PARTICLES, CELLS, TOY_DT, TOY_E
    dx = 1.0 / G
    p_vol = (0.5 * dx) ** 2
    p_mass = p_vol * 1.0

    @wp.kernel
    def clear(gv: wp.array2d(dtype=wp.vec2), gm: wp.array2d(dtype=float)):
        i, j = wp.tid()
        gv[i, j] = wp.vec2(0.0, 0.0)
        gm[i, j] = 0.0

    @wp.func
    def weights(fx: float):
        return wp.vec3(0.5 * (1.5 - fx) * (1.5 - fx), 0.75 - (fx - 1.0) * (fx - 1.0), 0.5 * (fx - 0.5) * (fx - 0.5))

    @wp.kernel
    def p2g(x: wp.array(dtype=wp.vec2), v: wp.array(dtype=wp.vec2), C: wp.array(dtype=wp.mat22), J: wp.array(dtype=float),
            gv: wp.array2d(dtype=wp.vec2), gm: wp.array2d(dtype=float), dx: float, dt: float, e: float, vol: float, mass: float):
        p = wp.tid()
        X = x[p] / dx
        bx = int(X[0] - 0.5)
        by = int(X[1] - 0.5)
        fx = X[0] - float(bx)
        fy = X[1] - float(by)
        wx = weights(fx)
        wy = weights(fy)
        stress = -dt * 4.0 * e * vol * (J[p] - 1.0) / (dx * dx)
        affine = wp.mat22(stress, 0.0, 0.0, stress) + mass * C[p]
        for i in range(3):
            for j in range(3):
                dpos = wp.vec2((float(i) - fx) * dx, (float(j) - fy) * dx)
                wt = wx[i] * wy[j]
                wp.atomic_add(gv, bx + i, by + j, wt * (mass * v[p] + affine * dpos))
                wp.atomic_add(gm, bx + i, by + j, wt * mass)

    @wp.kernel
    def grid_op(gv: wp.array2d(dtype=wp.vec2), gm: wp.array2d(dtype=float), dt: float, g: int):
        i, j = wp.tid()
        m = gm[i, j]
        u = gv[i, j]
        if m > 0.0:
            u = u / m
        u = wp.vec2(u[0], u[1] - dt * 9.8)
        ux = u[0]
        uy = u[1]
        if i < 3 and ux < 0.0:
            ux = 0.0
        if i > g - 3 and ux > 0.0:
            ux = 0.0
        if j < 3 and uy < 0.0:
            uy = 0.0
        if j > g - 3 and uy > 0.0:
            uy = 0.0
        gv[i, j] = wp.vec2(ux, uy)

    @wp.kernel
    def g2p(x: wp.array(dtype=wp.vec2), v: wp.array(dtype=wp.vec2), C: wp.array(dtype=wp.mat22), J: wp.array(dtype=float),
            gv: wp.array2d(dtype=wp.vec2), dx: float, dt: float):
        p = wp.tid()
        X = x[p] / dx
        bx = int(X[0] - 0.5)
        by = int(X[1] - 0.5)
        fx = X[0] - float(bx)
        fy = X[1] - float(by)
        wx = weights(fx)
        wy = weights(fy)
        nv = wp.vec2(0.0, 0.0)
        nC = wp.mat22(0.0, 0.0, 0.0, 0.0)
        for i in range(3):
            for j in range(3):
                dpos = wp.vec2((float(i) - fx) * dx, (float(j) - fy) * dx)
                wt = wx[i] * wy[j]
                gvn = gv[bx + i, by + j]
                nv = nv + wt * gvn
                nC = nC + 4.0 * wt * wp.outer(gvn, dpos) / (dx * dx)
        v[p] = nv
        x[p] = x[p] + dt * nv
        J[p] = J[p] * (1.0 + dt * (nC[0, 0] + nC[1, 1]))
        C[p] = nC

    dev = "cpu"
    rng = np.random.default_rng(0)
    arrays = {}

    def reset():
        arrays["x"] = wp.array((rng.random((N, 2)) * 0.4 + 0.2).astype(np.float32), dtype=wp.vec2, device=dev)
        arrays["v"] = wp.array(np.tile([0.0, -1.0], (N, 1)).astype(np.float32), dtype=wp.vec2, device=dev)
        arrays["C"] = wp.zeros(N, dtype=wp.mat22, device=dev)
        arrays["J"] = wp.array(np.ones(N, np.float32), dtype=float, device=dev)
        arrays["gv"] = wp.zeros((G, G), dtype=wp.vec2, device=dev)
        arrays["gm"] = wp.zeros((G, G), dtype=float, device=dev)
        wp.synchronize()

    def run(steps):
        a = arrays
        for _ in range(steps):
            wp.launch(clear, (G, G), [a["gv"], a["gm"]], device=dev)
            wp.launch(p2g, N, [a["x"], a["v"], a["C"], a["J"], a["gv"], a["gm"], dx, DT, E, p_vol, p_mass], device=dev)
            wp.launch(grid_op, (G, G), [a["gv"], a["gm"], DT, G], device=dev)
            wp.launch(g2p, N, [a["x"], a["v"], a["C"], a["J"], a["gv"], dx, DT], device=dev)
        wp.synchronize()
        return float(np.isfinite(a["x"].numpy()).all())

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
    ap.add_argument("--peer", choices=("taichi", "warp"), default="taichi",
                    help="the toy's runtime: Taichi 1.7.4 on 2 CPU threads, or Warp's CPU device (default taichi)")
    ap.add_argument("--out", default=None, help="default experiments/bench_peer.md (taichi), bench_peer_warp.md (warp)")
    args = ap.parse_args(argv)
    here = os.path.dirname(__file__)
    out = args.out or os.path.join(here, "bench_peer.md" if args.peer == "taichi" else "bench_peer_warp.md")
    toy, toy_reset = make_taichi_toy() if args.peer == "taichi" else make_warp_toy()
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
    if args.peer == "taichi":
        peer, runtime, install = "Taichi", "Taichi 1.7.4 on 2 CPU threads", "`pip install taichi==1.7.4`"
    else:
        import warp as wp
        peer, runtime, install = "Warp", f"Warp {wp.__version__} on its CPU device (one thread)", "`pip install warp-lang`"
    lines = [f"# Same-run peer comparison: jaxfoam HB step vs {peer} toy MLS-MPM (2D, float32)", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores; JAX {jax.__version__} (2 cores); {runtime}; "
             f"{args.rounds} interleaved rounds of {TOY_STEPS} toy and {HB_STEPS} jaxfoam substeps "
             f"on {N_PARTICLES} particles, {CELLS}^2 grid; load average during the rounds "
             f"{min(loads):.1f}-{max(loads):.1f}. Regenerate: `python experiments/bench_peer.py --peer {args.peer}` "
             f"(needs {install}).", "",
             "| | M particle-steps/s (median) | min | max |", "|---|---|---|---|",
             f"| {peer} toy (fluid, E = 400 Pa) | {med(r_toy) / 1e6:.2f} | {min(r_toy) / 1e6:.2f} | {max(r_toy) / 1e6:.2f} |",
             f"| jaxfoam full HB step | {med(r_hb) / 1e6:.2f} | {min(r_hb) / 1e6:.2f} | {max(r_hb) / 1e6:.2f} |",
             f"| ratio jaxfoam / {peer}, per round | {med(ratios):.2f} | {min(ratios):.2f} | {max(ratios):.2f} |", ""]
    if args.peer == "taichi":
        lines.append(f"Issue goal (2D HB step at least as fast as Taichi's toy step): median same-round ratio "
                     f"{med(ratios):.2f} ({'met' if med(ratios) >= 1.0 else 'missed'}).")
    else:
        lines.append(f"Per core (jaxfoam on 2 cores, Warp's CPU launches on 1): {med(ratios) / 2:.2f}. Warp 1.19 ships "
                     f"no MPM example, so the toy is the Taichi toy's kernels written in Warp.")
    with open(out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
