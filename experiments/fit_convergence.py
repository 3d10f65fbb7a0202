"""Fit convergence: how the fitted parameters move with the fit's grid and particles per cell.

One synthetic dataset per scene is made once on a fine grid (the recovery study's data path:
`fitting.synthesize` with its truth set 0, boundary noise and dropped frames), then fitted by
`fitting.calibrate` (Levenberg-Marquardt, the fitter's bounds, discretization check and
intervals) at several fit resolutions: 32, 48 and 64 cells across the domain's largest extent with 4
particles per cell, and 64 cells with 9. Every fit starts at the truth (one start; a start range of
+-0.1% around it), so what changes between fits is where each grid's optimum lies, not which basin
a random start fell into; the iteration budget is modest (FULL_ITERS) to keep the study near half an
hour on a shared 2-core CPU.

Per fit the table gives the fitted (mu Pa, sigma_y Pa, eta Pa s^m, m), the combined 95% interval, the
loss, the wall time, and the change of each parameter from the reference fit (64 cells, 4 per cell)
in units of the reference's interval half-width (combined; and statistical alone).

Resampling and fracture (FitSettings.resample / .fracture) are measured by experiments/fit_features.py,
not here.

Every fit is saved as it finishes (out/fit_convergence/<case>.json) and a re-run skips finished fits.
Usage: python -m experiments fit_convergence [--quick] [--report]
Writes experiments/results/fit_convergence[_quick].md and .png. SI units.
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
from experiments.recovery import DROP_FRAMES, NOISE, SCENES, truth_sets
from fitting import FIT_FIELDS, FitSettings, calibrate
from fitting import read_silhouettes
from fitting import synthesize

NAME = "fit_convergence"
WORK = Path(__file__).resolve().parent.parent / "out" / NAME
TRUTH_SET = 0  # the recovery study's first truth set (mu 233 Pa, sigma_y 49.2 Pa, eta 28.3 Pa s^m, m 0.393)
# Scenes: (name, duration s, frames, data cells across the largest extent). squeeze_2d first: it is the
# scene whose fits identified sigma_y and m (results/recovery.md). The data grid is ~1.6x finer than the
# finest fit grid, so no fit grid coincides with it.
FULL_SCENES = [("squeeze_2d", 1.0, 8, 100), ("drop_2d", 0.4, 8, 100)]
QUICK_SCENES = [("squeeze_2d", 0.5, 4, 40)]
# Fit discretizations (cells across the largest extent, particles per cell); the first is the reference.
FULL_FITS = [(64, 4), (32, 4), (48, 4), (64, 9)]
QUICK_FITS = [(24, 4), (16, 4)]
FULL_ITERS = 10   # LM iterations per fit (from the truth, LM stops on ftol or here)
QUICK_ITERS = 2
PIXEL_SIZE = 0.0025  # m per data pixel: the recovery study's (its data dx 5 mm / 2); no fit here uses coarser
START_HALF_WIDTH = 1e-3  # relative (absolute for m) half-width of the start range around the truth
# Fits started at the reference fit's optimum instead of the truth, with REFINE_ITERS iterations: the
# ppc-9 fit costs 2.25x per iteration, and from the reference optimum it only has to move as far as
# the particle count moves the optimum (the same question, at a third of the cost).
FROM_REFERENCE = {(64, 9)}
REFINE_ITERS = 4


def case_id(scene: str, cells: int, ppc: int, quick: bool) -> str:
    return f"{'q_' if quick else ''}{scene}_c{cells}_p{ppc}"


def make_data(scene: str, duration: float, frames: int, cells: int, quick: bool) -> Path:
    """The scene's synthetic silhouettes at `cells` across its largest extent (made once)."""
    WORK.mkdir(parents=True, exist_ok=True)
    path = WORK / f"{'q_' if quick else ''}{scene}_data_c{cells}.h5"
    if path.exists():
        return path
    spec = json.loads((SCENES / f"{scene}.json").read_text())
    extent = max(b - a for a, b in zip(spec["domain"]["min"], spec["domain"]["max"]))
    t0 = time.perf_counter()
    data = synthesize(spec, truth_sets()[TRUTH_SET], dx=extent / cells, frames=frames, duration=duration,
                      pixel_size=PIXEL_SIZE, noise=NOISE, drop_frames=DROP_FRAMES, seed=TRUTH_SET,
                      progress=lambda m: print("  synth:", m, flush=True))
    data.write(path)
    print(f"  synth {scene}: {time.perf_counter() - t0:.1f} s", flush=True)
    return path


def start_ranges(truth: dict) -> dict:
    out = {}
    for n in FIT_FIELDS:
        v = float(truth[n])
        out[n] = (v - START_HALF_WIDTH, v + START_HALF_WIDTH) if n == "m" else \
            (v * (1 - START_HALF_WIDTH), v * (1 + START_HALF_WIDTH))
    return out


def run_fit(scene: str, data_path: Path, cells: int, ppc: int, quick: bool) -> dict:
    path = WORK / f"{case_id(scene, cells, ppc, quick)}.json"
    if path.exists():
        return json.loads(path.read_text())
    data = read_silhouettes(data_path)
    start, iters = data.truth, (QUICK_ITERS if quick else FULL_ITERS)
    if (cells, ppc) in FROM_REFERENCE:
        ref = WORK / f"{case_id(scene, *(QUICK_FITS if quick else FULL_FITS)[0], quick)}.json"
        start, iters = json.loads(ref.read_text())["params"], REFINE_ITERS
    extent = float(np.max(np.asarray(data.load_scene().domain_max) - np.asarray(data.load_scene().domain_min)))
    settings = FitSettings(dx=extent / cells, ppc=ppc, optimizer="lm", starts=1, seed=0,
                           max_iter=iters, start_ranges=start_ranges(start))
    print(f"== {scene}: {cells} cells, ppc {ppc}", flush=True)
    t0 = time.perf_counter()
    res = calibrate(data, settings, progress=lambda m: print("  " + m, flush=True))
    rec = dict(res.to_dict(), scene=scene, cells=cells, ppc=ppc, truth=dict(data.truth), start=dict(start),
               wall_study=time.perf_counter() - t0)
    rec.pop("loss_history", None)
    rec["loss_start"] = float(res.loss_history[0])
    path.write_text(json.dumps(rec, indent=1) + "\n")
    return rec


def _interval(rec: dict, n: str, key: str = "interval") -> tuple:
    lo, hi = (float(x) if not isinstance(x, str) else (math.inf if x == "inf" else -math.inf)
              for x in rec[key][n])
    return lo, hi


def shifts(rec: dict, ref: dict) -> dict:
    """Per parameter: (relative change from ref, change / ref combined half-width, / statistical half-width)."""
    out = {}
    for n in FIT_FIELDS:
        v, v0 = rec["params"][n], ref["params"][n]
        lo, hi = _interval(ref, n)
        slo, shi = _interval(ref, n, "interval_statistical")
        rel = (v - v0) / v0 if n != "m" else v - v0
        out[n] = (rel, (v - v0) / (0.5 * (hi - lo)), (v - v0) / (0.5 * (shi - slo)))
    return out


def report(quick: bool) -> None:
    scenes = QUICK_SCENES if quick else FULL_SCENES
    fits = QUICK_FITS if quick else FULL_FITS
    recs = {}
    for s, *_ in scenes:
        for c, p in fits:
            path = WORK / f"{case_id(s, c, p, quick)}.json"
            if path.exists():
                recs[(s, c, p)] = json.loads(path.read_text())
    ref_key = fits[0]
    body = [f"Fits of one synthetic dataset per scene at several fit discretizations; the reference is "
            f"{ref_key[0]} cells across the largest extent, {ref_key[1]} particles per cell (the fitter's 2D "
            f"default is 64 / 4). Truth: recovery set {TRUTH_SET} {truth_sets()[TRUTH_SET]}. Data: "
            f"`synthesize` with noise {NOISE}, {int(100 * DROP_FRAMES)}% of frames dropped, {PIXEL_SIZE} m pixels. "
            f"Each fit: Levenberg-Marquardt from the truth (one start, range +-{START_HALF_WIDTH:g} relative), at "
            f"most {QUICK_ITERS if quick else FULL_ITERS} iterations, the fitter's bounds, discretization check "
            f"and 95% intervals (combined = statistical and numerical in quadrature). " + (
                f"Fits {', '.join(f'{c} / {p}' for c, p in sorted(FROM_REFERENCE))} instead start at the "
                f"reference fit's optimum with at most {REFINE_ITERS} iterations (2.25x the particles per "
                f"iteration; from there they only move as far as the particle count moves the optimum). "
                if FROM_REFERENCE & set(fits) else "") + "`loss@start` is the loss of "
            "the start on that grid (the truth, or the reference optimum). All fits ran 2-3 at a time on "
            "the shared 2-core machine (load average about 6), so wall times are inflated and compare only "
            "roughly.\n"]
    for s, dur, frames, dcells in scenes:
        body.append(f"## {s}\n\nData: {dcells} cells across the largest extent, {dur} s, {frames} frames.\n")
        done = [(c, p) for c, p in fits if (s, c, p) in recs]
        if not done:
            body.append("Not run (out of time).\n")
            continue
        rows = []
        for c, p in done:
            r = recs[(s, c, p)]
            rows.append([c, p, r["settings"]["dx"]] + [r["params"][n] for n in FIT_FIELDS] +
                        [r["loss"], r["loss_start"], r["iterations"], r["reason"], r["wall_time"]])
        body.append(C.md_table(["cells", "ppc", "dx m", "mu", "sigma_y", "eta", "m", "loss", "loss@start",
                                "iter", "stop", "wall s"], rows))
        rows = []
        for c, p in done:
            r = recs[(s, c, p)]
            for n in FIT_FIELDS:
                lo, hi = _interval(r, n)
                slo, shi = _interval(r, n, "interval_statistical")
                rows.append([c, p, n, r["params"][n], f"[{lo:.4g}, {hi:.4g}]", f"[{slo:.4g}, {shi:.4g}]",
                             r["numerical_error"][n], "yes" if r["identifiable"][n] else "no"])
        body.append("\n95% intervals (combined, and the Gauss-Newton part alone) and the numerical error the "
                    "fitter's dx check reports:\n\n")
        body.append(C.md_table(["cells", "ppc", "param", "fit", "combined 95%", "statistical 95%",
                                "numerical error", "identifiable"], rows))
        if ref_key in done:
            ref = recs[(s,) + ref_key]
            rows = []
            for c, p in done:
                if (c, p) == ref_key:
                    continue
                sh = shifts(recs[(s, c, p)], ref)
                rows.append([f"{c} / {p}"] + [f"{100 * sh[n][0]:+.1f}%" if n != "m" else f"{sh[n][0]:+.3f}"
                                              for n in FIT_FIELDS] +
                            [f"{sh[n][1]:+.2f} ({sh[n][2]:+.2f})" for n in FIT_FIELDS])
            body.append(f"\nChange from the {ref_key[0]} / {ref_key[1]} fit (relative; absolute for m), and in "
                        f"units of the reference's combined 95% half-width (in brackets: statistical "
                        f"half-width):\n\n")
            body.append(C.md_table(["cells / ppc", "mu", "sigma_y", "eta", "m", "mu (hw)", "sigma_y (hw)",
                                    "eta (hw)", "m (hw)"], rows))
        body.append("\n")
    body.append("## Resampling and fracture\n\nNot run here: fits with `FitSettings(resample=..., fracture=...)` "
                "are compared with plain fits by `experiments/fit_features.py` (results/fit_features.md).\n")
    C.write_md(NAME, quick, "Fit convergence: fitted parameters against the fit's grid and ppc", "\n".join(body))
    plot(recs, scenes, fits, quick)


def plot(recs, scenes, fits, quick) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(scenes), 4, figsize=(13, 3.2 * len(scenes)), squeeze=False)
    for i, (s, *_) in enumerate(scenes):
        for j, n in enumerate(FIT_FIELDS):
            ax = axes[i, j]
            for c, p in fits:
                r = recs.get((s, c, p))
                if r is None:
                    continue
                lo, hi = _interval(r, n)
                slo, shi = _interval(r, n, "interval_statistical")
                v = r["params"][n]
                xpos = c + (2 if p != 4 else 0)
                col = "C1" if p != 4 else "C0"
                ax.errorbar([xpos], [v], yerr=[[v - lo], [hi - v]], fmt="o", color=col, capsize=4, alpha=0.5)
                ax.errorbar([xpos], [v], yerr=[[v - slo], [shi - v]], fmt="o", color=col, capsize=2, lw=2.5)
                ax.annotate(f"ppc {p}", (xpos, v), textcoords="offset points", xytext=(5, 3), fontsize=7)
            t = truth_sets()[TRUTH_SET][n]
            ax.axhline(t, color="k", ls="--", lw=0.8, label="truth")
            if n != "m":
                ax.set_yscale("log")
            ax.set_title(f"{s}: {n}", fontsize=9)
            ax.set_xlabel("fit cells across the largest extent")
            ax.set_xlim(min(c for c, _ in fits) - 6, max(c for c, _ in fits) + 8)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Fitted parameters against fit resolution (thick: statistical 95%, thin: combined 95%)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(C.out_path(NAME, "png", quick), dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced version (minutes on 2 cores)")
    parser.add_argument("--report", action="store_true", help="only rebuild the table and chart")
    parser.add_argument("--only", default=None, help="run only scenes whose name contains this text")
    parser.add_argument("--fits", default=None, help="run only these fits, e.g. '64:9,48:4' (cells:ppc)")
    args = parser.parse_args(argv)
    scenes = QUICK_SCENES if args.quick else FULL_SCENES
    fits = QUICK_FITS if args.quick else FULL_FITS
    if args.fits:
        fits = [f for f in fits if f"{f[0]}:{f[1]}" in args.fits.split(",")]
    if not args.report:
        for s, dur, frames, dcells in scenes:
            if args.only and args.only not in s:
                continue
            data_path = make_data(s, dur, frames, dcells, args.quick)
            for c, p in fits:
                run_fit(s, data_path, c, p, args.quick)
                report(args.quick)
    report(args.quick)


if __name__ == "__main__":
    main()
