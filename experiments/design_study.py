"""Experiment design on the 2D hanging plate: rank 20 recordings, then fit the best and the default one.

1. `jaxfoam design` (`fitting.design.design`) ranks the plate motions amplitude x frequency (AMPLITUDES x
   FREQUENCIES, 1 s at 15 fps) of experiments/scenes/hanging_plate_2d.json at the fitter's default grid
   from a guess (GUESS) about 1.3x off the material (MATERIAL), robust over 3 parameter points: the wall
   time of the ranking, and every candidate's predicted 95% half-widths.
2. The best-ranked recording and the scene's own (amplitude 1 cm, 3 Hz) are made by `jaxfoam synth` at
   MATERIAL (the same dx, its own particle sampling and renderer, 5% boundary noise) and fitted with the
   fitter's defaults except 2 starts of up to 15 LM iterations and no discretization check (statistical
   intervals, which the prediction is of). Reported: the fit, its 95% interval, the error, whether it is
   within the design's tolerance and the truth inside, and the achieved half-width against the predicted
   one (at the guess, the worst over the points, and at the truth: the design run once more there).
The data are jaxfoam's own (model-consistent); the reference simulator's are not used here.
Writes experiments/results/design_study[_quick].md and .json. Usage: python -m experiments design_study [--quick]
"""
from __future__ import annotations

import json
import math
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)


from experiments._common import machine_line, md_table, out_path, parse_args, write_md  # noqa: E402
from fitting import FitSettings, calibrate, synthesize  # noqa: E402
from fitting.design import TOLERANCE, Variable, design, half_widths  # noqa: E402
from jaxfoam.guards import atomic_output  # noqa: E402

SCENE = os.path.join(os.path.dirname(__file__), "scenes", "hanging_plate_2d.json")
MATERIAL = {"mu": 150.0, "sigma_y": 30.0, "eta": 8.0, "m": 0.6}
GUESS = {"mu": 200.0, "sigma_y": 22.0, "eta": 11.0, "m": 0.5}
AMPLITUDES = (0.005, 0.01, 0.02, 0.03)
FREQUENCIES = (1.0, 2.0, 3.0, 5.0, 8.0)
DEFAULT_MOTION = {"plate.motion.amplitude": 0.01, "plate.motion.frequency": 3.0}
NOISE, DATA_SEED = 0.05, 7
NAMES = ("mu", "sigma_y", "eta", "m")


def within(name, value, truth) -> bool:
    err = abs(value - truth) if name == "m" else abs(value / truth - 1.0)
    return err <= TOLERANCE[name]


def main(argv=None):
    args = parse_args(__doc__, argv)
    quick = args.quick
    amps, freqs = ((0.01, 0.02), (3.0, 5.0)) if quick else (AMPLITUDES, FREQUENCIES)
    settings = FitSettings(dx=0.0109375 if quick else None)
    points = 2 if quick else 3
    duration = 0.5 if quick else 1.0
    variables = [Variable("plate.motion.amplitude", amps), Variable("plate.motion.frequency", freqs)]
    t0 = time.perf_counter()
    res = design(SCENE, GUESS, variables, settings=settings, points=points, duration=duration,
                 progress=lambda m: print(m, flush=True))
    rank_wall = time.perf_counter() - t0
    record = dict(material=MATERIAL, guess=GUESS, ranking_wall=rank_wall, candidates=len(res.candidates),
                  design=res.as_dict(), fits={})
    rows = []
    for k, c in enumerate(res.candidates):
        rows.append([k + 1, f"{c['values']['plate.motion.amplitude']:g}", f"{c['values']['plate.motion.frequency']:g}"]
                    + [("inf" if not math.isfinite(c["half_width"][n]) else
                        f"{c['half_width'][n]:.3g}" if n == "m" else f"{100 * c['half_width'][n]:.3g}%") for n in NAMES]
                    + [f"{len(c['within'])}/4", f"{c['wall_time']:.0f}"])

    default = next(c for c in res.candidates if c["values"] == DEFAULT_MOTION) if not quick else res.candidates[-1]
    fit_rows = []
    for label, c in (("best-ranked", res.best), ("scene default" if not quick else "worst-ranked", default)):
        rec = c["recording"]
        data = synthesize(c["scene"], MATERIAL, dx=res.settings["dx"] or None, frames=rec["frames"],
                          duration=rec["duration"], noise=NOISE, seed=DATA_SEED)
        t = time.perf_counter()
        fit = calibrate(data, FitSettings(dx=settings.dx, starts=2, max_iter=15, dx_check=False), progress=None)
        wall = time.perf_counter() - t
        achieved = half_widths(fit.interval_statistical, fit.params)
        at_guess = half_widths(c["predicted"][0], GUESS)
        at_truth = design(SCENE, MATERIAL, [Variable(k, (v,)) for k, v in c["values"].items()], settings=settings,
                          points=1, duration=duration).best["half_width"]
        record["fits"][label] = dict(values=c["values"], params=fit.params, interval=fit.interval_statistical,
                                     achieved_half_width=achieved, predicted_at_guess=at_guess, predicted_at_truth=at_truth,
                                     predicted_worst=c["half_width"], wall=wall)
        print(f"{label} {c['values']}: {({n: round(fit.params[n], 4) for n in NAMES})} in {wall:.0f} s", flush=True)
        for n in NAMES:
            lo, hi = fit.interval_statistical[n]
            inside = lo <= MATERIAL[n] <= hi
            fmt = (lambda v: f"{v:.3g}") if n == "m" else (lambda v: f"{100 * v:.3g}%")
            err = fit.params[n] - MATERIAL[n] if n == "m" else fit.params[n] / MATERIAL[n] - 1.0
            fit_rows.append([label if n == "mu" else "", n, f"{MATERIAL[n]:g}", f"{fit.params[n]:.4g}",
                             f"[{lo:.4g}, {hi:.4g}]", f"{err:+.3g}" if n == "m" else f"{100 * err:+.1f}%",
                             "yes" if within(n, fit.params[n], MATERIAL[n]) else "no", "yes" if inside else "no",
                             fmt(at_guess[n]), fmt(c["half_width"][n]), fmt(at_truth[n]), fmt(achieved[n]),
                             f"{achieved[n] / at_truth[n]:.2f}" if at_truth[n] > 0 else "-"])
    dx_used = res.settings["dx"]
    body = (f"Scene experiments/scenes/hanging_plate_2d.json; material {MATERIAL}; guess {GUESS}; tolerance "
            f"{TOLERANCE} (relative, m absolute). Design at dx {dx_used if dx_used else 'the fit default'}, "
            f"{duration:g} s at 15 fps, {points} parameter points (worst), {len(res.candidates)} candidates.\n\n"
            f"Ranking wall time: {rank_wall:.0f} s ({rank_wall / len(res.candidates):.1f} s per candidate).\n\n"
            + md_table(["rank", "amplitude m", "frequency Hz"] + [f"{n} half-width" for n in NAMES]
                       + ["within tolerance", "wall s"], rows)
            + "\n\nFits of synthesized recordings (same dx, own particle sampling, "
            f"{NOISE:.0%} boundary noise; 2 starts, up to 15 LM iterations, statistical intervals):\n\n"
            + md_table(["recording", "parameter", "truth", "fit", "95% interval", "error", "within tolerance",
                        "truth inside", "predicted half-width (guess)", "predicted (worst)", "predicted (truth)",
                        "achieved", "achieved / predicted (truth)"], fit_rows)
            + "\n\nFit wall times: " + ", ".join(f"{k} {v['wall']:.0f} s" for k, v in record["fits"].items()) + ".\n\n"
            + "Advice: " + res.advice + "\n")
    write_md("design_study", quick, "Experiment design on the 2D hanging plate", body)
    with atomic_output(out_path("design_study", "json", quick)) as tmp:
        with open(tmp, "w") as fh:
            json.dump(record, fh, indent=1, default=float)
    print(machine_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
