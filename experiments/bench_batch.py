"""Benchmark: batched evaluation of fit-sized rollouts, on one device and sharded over host devices.

In one process, in interleaved rounds (medians reported): the 8,192-particle 2D step of
`bench_step.py` (float64, the reference rate), a fit's residual rollout alone (the default fit of
the reference drop, 794 particles; frames up to 0.15 s), B of them as one batched program
(`CalibrationProblem.residual_batch`) on one device and split over D host devices, and the
Jacobians of three starts: in turn (`residual_and_jacobian`, two column threads) against one
batched program of their 12 jvp rollouts on one and on D devices.
Writes experiments/results/bench_batch[_quick].md and .json.
Usage: python -m experiments bench_batch [--quick] [--devices D] [--batch B] [--name NAME]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import jax

_early = argparse.ArgumentParser(add_help=False)
_early.add_argument("--devices", type=int, default=2)
# Host devices must be requested before JAX's CPU backend starts.
jax.config.update("jax_num_cpu_devices", max(1, _early.parse_known_args()[0].devices))
jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from experiments import bench_step  # noqa: E402
from experiments._common import machine_line, md_table, out_path, write_md  # noqa: E402
from fitting import FitSettings, build_problem, read_silhouettes  # noqa: E402
from jaxfoam.guards import atomic_output  # noqa: E402

DATA = os.path.join(os.path.dirname(__file__), "reference", "data", "drop_2d_set0.h5")
POINT = {"mu": 150.0, "sigma_y": 30.0, "eta": 10.0, "m": 0.6}


def _timed(fn):
    t = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 rounds instead of 5")
    ap.add_argument("--devices", type=int, default=2, help="host devices of the sharded runs (default 2)")
    ap.add_argument("--batch", type=int, default=8, help="rollouts per batched residual program (default 8)")
    ap.add_argument("--name", default="bench_batch", help="record name under experiments/results (default bench_batch)")
    args = ap.parse_args(argv)
    if not args.name.replace("_", "").isalnum():
        ap.error(f"--name {args.name!r}: letters, digits and '_' only (a record name under experiments/results)")
    rounds = 2 if args.quick else 5
    D = min(args.devices, len(jax.devices()))

    scene, state, params, grid, dt = bench_step.make_case(2, 8192, 128, jnp.float64)
    steps = 100
    ref = bench_step.make_rollout(scene, grid, dt, steps, True, jnp.float64)
    data = read_silhouettes(DATA)
    one = build_problem(data, FitSettings(time_window=(0.0, 0.15)))
    many = build_problem(data, FitSettings(time_window=(0.0, 0.15))).use_devices(D)
    n = int(np.sum(one.sim.state0.active))
    substeps = one.sim.substeps * len(one.sim.frame_times)
    z = jnp.asarray(one.transform.to_unconstrained(POINT), jnp.float64)
    Z = z[None] + 0.01 * jnp.arange(args.batch, dtype=z.dtype)[:, None]
    Z3 = Z[:3]
    p = z.shape[0]
    cases = {
        "step, 8,192 particles": (lambda: ref(state, params), 8192 * steps),
        "fit residual, alone": (lambda: one.residual(z), n * substeps),
        f"fit residuals, batch of {args.batch}, 1 device": (lambda: one.residual_batch(Z), args.batch * n * substeps),
        "3 Jacobians in turn (2 column threads)": (lambda: [one.residual_and_jacobian(Z3[i]) for i in range(3)],
                                                   3 * p * n * substeps),
        "3 Jacobians batched, 1 device": (lambda: one.residual_and_jacobian_batch(Z3), 3 * p * n * substeps),
    }
    if D > 1:  # the sharded rows
        cases[f"fit residuals, batch of {args.batch}, {D} devices"] = (lambda: many.residual_batch(Z),
                                                                       args.batch * n * substeps)
        cases[f"3 Jacobians batched, {D} devices"] = (lambda: many.residual_and_jacobian_batch(Z3), 3 * p * n * substeps)
    compile_s = {k: _timed(fn) for k, (fn, _) in cases.items()}
    times = {k: [] for k in cases}
    for r in range(rounds):
        for k, (fn, _) in cases.items():
            times[k].append(_timed(fn))
        print(f"round {r + 1}/{rounds}: " + ", ".join(f"{statistics.median(v):.3g}s" for v in times.values()), flush=True)
    med = {k: statistics.median(v) for k, v in times.items()}
    rate = {k: cases[k][1] / med[k] for k in cases}
    step_rate = rate["step, 8,192 particles"]
    rows = [[k, f"{med[k]:.3f}", f"{rate[k] / 1e6:.2f}", f"{rate[k] / step_rate:.2f}", f"{compile_s[k]:.1f}"]
            for k in cases]
    jac_seq = med["3 Jacobians in turn (2 column threads)"]
    body = (f"The reference drop's default fit problem ({n} particles, {substeps} substeps up to 0.15 s), float64; "
            f"medians of {rounds} interleaved rounds. Rate: particle-steps per second summed over the batch "
            f"(a jvp rollout counts once).\n\n"
            + md_table(["program", "median s", "M particle-steps/s", "vs the 8,192-particle step", "first call s"], rows)
            + "\n\nThe Jacobians of three starts: batched on 1 device "
            f"{jac_seq / med['3 Jacobians batched, 1 device']:.2f}x"
            + (f", on {D} devices {jac_seq / med[f'3 Jacobians batched, {D} devices']:.2f}x" if D > 1 else "")
            + " the speed of computing them in turn.\n")
    write_md(args.name, args.quick, "Batched and sharded evaluation of fit-sized rollouts", body,
             command="bench_batch" + ("" if D == 2 else f" --devices {D}")
             + ("" if args.name == "bench_batch" else f" --name {args.name}"))
    record = dict(machine=machine_line(), devices=D, particles=n, substeps=substeps, rounds=rounds,
                  median_s=med, rate=rate, compile_s=compile_s, times=times)
    with atomic_output(out_path(args.name, "json", args.quick)) as tmp:
        with open(tmp, "w") as fh:
            json.dump(record, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
