"""Fit features: do particle resampling and fracture change the fitted parameters?

For each 2D fit scene (hanging plate, drop, squeeze) one synthetic dataset is made once on a grid finer
than the fit's (`fitting.synthesize`, plain MPM, the recovery study's truth set 0, boundary noise
and dropped frames; the same data files as experiments/fit_convergence.py), then fitted four ways by
`fitting.calibrate`: plain, with resampling only (`FitSettings.resample`, the default
`ResampleConfig`: a pass every 20 substeps, target ppc = the fit's), with fracture only
(`FitSettings.fracture`, the default `FractureConfig`) and with both. Everything else is the fitter's
default (4 particles per cell, CFL 0.3, float64, Levenberg-Marquardt, discretization check, 95% intervals)
except the grid: STUDY_CELLS = 32 cells across the largest extent, half the fitter's 64, because at 64
cells a rollout with both features cost 9x the plain one (measured on the drop: 37.7 s against 4.2 s per
forward rollout, 288 s against 38.7 s per 4-column Jacobian, at load ~7) and the twelve fits would take
several hours on the shared 2-core machine; at 32 cells they took 2.2 hours of fit wall time summed
(about one hour elapsed, 2-4 fits at a time, load average 8-11). All four fits of a scene start from the same point, the truth (one
start; a start range of +-0.1% around it), with the same modest iteration budget, so a difference between
them comes from the model, not from the optimizer's path from different starts.

Per fit the table gives the fitted (mu Pa, sigma_y Pa, eta Pa s^m, m), the loss, the loss at the start,
the wall time; and per parameter the change from the plain fit, relative and in units of the plain fit's
95% half-width (combined statistical + numerical; in brackets the statistical part alone).

Every fit is saved as it finishes (out/fit_features/<case>.json) and a re-run skips finished fits.
Usage: python -m experiments fit_features [--quick] [--report] [--only TEXT] [--variants plain,both]
Writes experiments/results/fit_features[_quick].md and .png. SI units.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

import jaxfoam  # noqa: F401  (float64)
from experiments import _common as C
from experiments.fit_convergence import START_HALF_WIDTH, TRUTH_SET, make_data, start_ranges
from experiments.recovery import DROP_FRAMES, NOISE, truth_sets
from fitting import FIT_FIELDS, FitSettings, calibrate
from fitting.settings import FIT_CELLS, FIT_PPC
from jaxfoam.fracture import FractureConfig
from fitting import read_silhouettes
from jaxfoam.resample import ResampleConfig

NAME = "fit_features"
WORK = Path(__file__).resolve().parent.parent / "out" / NAME
# Scenes: (name, duration s, frames, data cells across the largest extent). The data grid (100 cells) is
# 1.6x finer than the fit's default 64, as in fit_convergence (whose drop and squeeze data files are
# shared). The hanging plate runs first: it is the scene that necks and tears, where resampling and
# fracture could matter most; the squeeze is the costliest (1252 substeps per frame at 64 cells).
FULL_SCENES = [("hanging_plate_2d", 0.8, 8, 100), ("drop_2d", 0.4, 8, 100), ("squeeze_2d", 1.0, 8, 100)]
QUICK_SCENES = [("drop_2d", 0.3, 4, 40)]
# Fit grids (cells across the largest extent): half the fitter's default for cost (see the docstring).
STUDY_CELLS = FIT_CELLS[2] // 2
QUICK_CELLS = 16
# The four model variants: name -> (resample, fracture) settings of FitSettings (configs at their defaults).
VARIANTS = {"plain": (None, None), "resample": (ResampleConfig(), None), "fracture": (None, FractureConfig()),
            "both": (ResampleConfig(), FractureConfig())}
FULL_ITERS = 4    # LM iterations per fit from the truth (fit_convergence: most of the move is in the first 3-4)
QUICK_ITERS = 1
# The quick version runs the two extremes only (each variant compiles its own rollouts: minutes on 2 cores).
QUICK_VARIANTS = ("plain", "both")


def case_id(scene: str, variant: str, quick: bool) -> str:
    return f"{'q_' if quick else ''}{scene}_{variant}"


def run_fit(scene: str, data_path: Path, variant: str, quick: bool) -> dict:
    WORK.mkdir(parents=True, exist_ok=True)
    path = WORK / f"{case_id(scene, variant, quick)}.json"
    if path.exists():
        return json.loads(path.read_text())
    data = read_silhouettes(data_path)
    truth = dict(data.truth)
    resample, fracture = VARIANTS[variant]
    dom = data.load_scene()
    extent = float(np.max(np.asarray(dom.domain_max) - np.asarray(dom.domain_min)))
    settings = FitSettings(dx=extent / (QUICK_CELLS if quick else STUDY_CELLS), optimizer="lm", starts=1, seed=0,
                           max_iter=QUICK_ITERS if quick else FULL_ITERS, start_ranges=start_ranges(truth),
                           dx_check=not quick, resample=resample, fracture=fracture)
    print(f"== {scene}: {variant}", flush=True)
    t0 = time.perf_counter()
    res = calibrate(data, settings, progress=lambda m: print("  " + m, flush=True))
    rec = dict(res.to_dict(), scene=scene, variant=variant, truth=truth, wall_study=time.perf_counter() - t0)
    rec.pop("loss_history", None)
    rec["loss_start"] = float(res.loss_history[0])
    path.write_text(json.dumps(rec, indent=1) + "\n")
    return rec


def _interval(rec: dict, n: str, key: str = "interval") -> tuple:
    return tuple(float(x) if not isinstance(x, str) else (math.inf if x == "inf" else -math.inf)
                 for x in rec[key][n])


def shifts(rec: dict, ref: dict) -> dict:
    """Per parameter: (change from ref: relative, absolute for m; change / ref combined 95% half-width;
    change / ref statistical 95% half-width)."""
    out = {}
    for n in FIT_FIELDS:
        v, v0 = rec["params"][n], ref["params"][n]
        lo, hi = _interval(ref, n)
        slo, shi = _interval(ref, n, "interval_statistical")
        rel = v - v0 if n == "m" else (v - v0) / v0
        out[n] = (rel, (v - v0) / (0.5 * (hi - lo)), (v - v0) / (0.5 * (shi - slo)))
    return out


def load(quick: bool) -> dict:
    recs = {}
    for s, *_ in (QUICK_SCENES if quick else FULL_SCENES):
        for v in VARIANTS:
            path = WORK / f"{case_id(s, v, quick)}.json"
            if path.exists():
                recs[(s, v)] = json.loads(path.read_text())
    return recs


def report(quick: bool) -> None:
    scenes = QUICK_SCENES if quick else FULL_SCENES
    recs = load(quick)
    cells = QUICK_CELLS if quick else STUDY_CELLS
    iters = QUICK_ITERS if quick else FULL_ITERS
    body = [f"Fits of one synthetic dataset per 2D scene with and without particle resampling and fracture. "
            f"Truth: recovery set {TRUTH_SET} {truth_sets()[TRUTH_SET]}. Data: plain MPM (`synthesize`) on a finer "
            f"grid (cells below), noise {NOISE}, {int(100 * DROP_FRAMES)}% of frames dropped. Fits: {cells} cells "
            f"across the largest extent (the fitter's default is {FIT_CELLS[2]}), {FIT_PPC[2]} particles per cell, Levenberg-Marquardt from the truth (one "
            f"start, range +-{START_HALF_WIDTH:g} relative) for at most {iters} iterations, the fitter's bounds"
            + ("" if quick else ", discretization check") + " and 95% intervals. Variants: `plain`; `resample`: "
            f"`ResampleConfig()` defaults (a pass every {ResampleConfig().every} substeps, target ppc = the fit's, "
            f"{ResampleConfig().capacity_factor:g}x particle slots); `fracture`: `FractureConfig()` defaults "
            f"(weak below a neighbourhood density ratio of 0.2 in 2D); `both`. The derivatives treat the "
            f"resampling and fracture decisions as fixed (see `FitSettings`). Wall times were measured with other "
            f"jobs on the shared 2-core machine (load average 8-11, 2-4 of these fits at a time), so they compare "
            f"only roughly; `wall s` includes compilation.\n"]
    for s, dur, frames, dcells in scenes:
        body.append(f"## {s}\n\nData: {dcells} cells across the largest extent, {dur} s, {frames} frames.\n")
        done = [v for v in VARIANTS if (s, v) in recs]
        if not done:
            body.append("Not run (out of time).\n")
            continue
        missing = [v for v in (QUICK_VARIANTS if quick else VARIANTS) if v not in done]
        if missing:
            body.append(f"Not run (out of time): {', '.join(missing)}.\n")
        rows = []
        for v in done:
            r = recs[(s, v)]
            rows.append([v] + [r["params"][n] for n in FIT_FIELDS] +
                        [r["loss"], r["loss_start"], r["iterations"], r["reason"], r["wall_time"],
                         r["settings"].get("capacity", "")])
        body.append(C.md_table(["variant", "mu", "sigma_y", "eta", "m", "loss", "loss@start", "iter", "stop",
                                "wall s", "slots"], rows))
        rows = []
        for v in done:
            r = recs[(s, v)]
            for n in FIT_FIELDS:
                lo, hi = _interval(r, n)
                slo, shi = _interval(r, n, "interval_statistical")
                rows.append([v, n, r["params"][n], f"[{lo:.4g}, {hi:.4g}]", f"[{slo:.4g}, {shi:.4g}]",
                             "yes" if r["identifiable"][n] else "no"])
        body.append("\n95% intervals (combined, and the Gauss-Newton part alone):\n\n")
        body.append(C.md_table(["variant", "param", "fit", "combined 95%", "statistical 95%", "identifiable"], rows))
        if "plain" in done and len(done) > 1:
            ref = recs[(s, "plain")]
            rows = []
            for v in done:
                if v == "plain":
                    continue
                sh = shifts(recs[(s, v)], ref)
                rows.append([v] + [f"{100 * sh[n][0]:+.2f}%" if n != "m" else f"{sh[n][0]:+.4f}" for n in FIT_FIELDS]
                            + [f"{sh[n][1]:+.2f} ({sh[n][2]:+.2f})" for n in FIT_FIELDS]
                            + [f"{recs[(s, v)]['wall_time'] / ref['wall_time']:.2f}x"])
            body.append("\nChange from the plain fit (relative; absolute for m), and in units of the plain fit's "
                        "combined 95% half-width (in brackets: its statistical half-width); wall time against "
                        "the plain fit's:\n\n")
            body.append(C.md_table(["variant", "mu", "sigma_y", "eta", "m", "mu (hw)", "sigma_y (hw)", "eta (hw)",
                                    "m (hw)", "wall"], rows))
        body.append("\n")
    body.append(summary(recs, scenes))
    C.write_md(NAME, quick, "Fit features: fitted parameters with and without resampling and fracture",
               "\n".join(body))
    plot(recs, scenes, quick)


def _max_rel_diff(a: dict, b: dict) -> float:
    """Largest relative difference of the fitted parameters and the loss of two fits."""
    pairs = [(a["params"][n], b["params"][n]) for n in FIT_FIELDS] + [(a["loss"], b["loss"])]
    return max(abs(x - y) / max(abs(y), 1e-300) for x, y in pairs)


def summary(recs: dict, scenes) -> str:
    """Findings computed from the tables: which variants gave the same fit, and the largest changes."""
    lines = ["## Summary (computed from the tables above)\n"]
    for s, *_ in scenes:
        if (s, "plain") not in recs:
            continue
        ref = recs[(s, "plain")]
        parts = []
        for v, base in (("fracture", "plain"), ("both", "resample")):
            if (s, v) in recs and (s, base) in recs:
                d = _max_rel_diff(recs[(s, v)], recs[(s, base)])
                parts.append(f"`{v}` against `{base}`: largest relative difference of the fitted parameters and "
                             f"loss {d:.2g}" + (" (the fracture stage changed nothing)" if d < 1e-9 else ""))
        other = "resample" if (s, "resample") in recs else "both"
        if (s, other) in recs:
            sh = shifts(recs[(s, other)], ref)
            n_c = max(FIT_FIELDS, key=lambda n: abs(sh[n][1]))
            n_s = max(FIT_FIELDS, key=lambda n: abs(sh[n][2]))
            parts.append(f"`{other}` against `plain`: largest change {sh[n_c][1]:+.2f} combined half-widths "
                         f"({n_c}), {sh[n_s][2]:+.2f} statistical half-widths ({n_s}); wall time "
                         f"{recs[(s, other)]['wall_time'] / ref['wall_time']:.2f}x")
        lines.append(f"- {s}: " + "; ".join(parts) + ".")
    return "\n".join(lines) + "\n"


def plot(recs, scenes, quick) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(scenes), 5, figsize=(15, 3.0 * len(scenes)), squeeze=False)
    names = list(VARIANTS)
    for i, (s, *_) in enumerate(scenes):
        for j, n in enumerate(FIT_FIELDS):
            ax = axes[i, j]
            for k, v in enumerate(names):
                r = recs.get((s, v))
                if r is None:
                    continue
                val = r["params"][n]
                lo, hi = _interval(r, n)
                slo, shi = _interval(r, n, "interval_statistical")
                col = f"C{k}"
                ax.errorbar([k], [val], yerr=[[max(val - lo, 0)], [max(hi - val, 0)]], fmt="o", color=col,
                            capsize=4, alpha=0.45)
                ax.errorbar([k], [val], yerr=[[max(val - slo, 0)], [max(shi - val, 0)]], fmt="o", color=col,
                            capsize=2, lw=2.5)
            ax.axhline(truth_sets()[TRUTH_SET][n], color="k", ls="--", lw=0.8, label="truth")
            if n != "m":
                ax.set_yscale("log")
            ax.set_xticks(range(len(names)))
            ax.set_xticklabels(names, fontsize=7)
            ax.set_title(f"{s}: {n}", fontsize=9)
        ax = axes[i, 4]
        walls = [recs[(s, v)]["wall_time"] if (s, v) in recs else 0.0 for v in names]
        ax.bar(range(len(names)), walls, color=[f"C{k}" for k in range(len(names))])
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels(names, fontsize=7)
        ax.set_ylabel("fit wall time (s)", fontsize=8)
        ax.set_title(f"{s}: cost", fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Fitted parameters with resampling / fracture off and on (thick: statistical 95%, thin: "
                 "combined 95%)", fontsize=10)
    fig.tight_layout()
    C.save_fig(fig, NAME, quick)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced version (minutes on 2 cores)")
    parser.add_argument("--report", action="store_true", help="only rebuild the table and chart")
    parser.add_argument("--only", default=None, help="run only scenes whose name contains this text")
    parser.add_argument("--variants", default=None, help="run only these variants, e.g. 'plain,both'")
    args = parser.parse_args(argv)
    variants = list(QUICK_VARIANTS if args.quick else VARIANTS)
    if args.variants:
        variants = [v for v in VARIANTS if v in args.variants.split(",")]
    if not args.report:
        for s, dur, frames, dcells in (QUICK_SCENES if args.quick else FULL_SCENES):
            if args.only and args.only not in s:
                continue
            data_path = make_data(s, dur, frames, dcells, args.quick)
            for v in variants:
                run_fit(s, data_path, v, args.quick)
                report(args.quick)
    report(args.quick)


if __name__ == "__main__":
    main()
