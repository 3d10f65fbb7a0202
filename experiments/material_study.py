"""One foam in three recordings, on the reference simulator's data: single, joint and designed fits.

For each shared material K of experiments/reference (`generate.materials()`; files
experiments/reference/data/materials/<scene>_mat<K>.h5, made by the independent reference MPM at 4x
finer dx than jaxfoam's fit default):
  (i)   the hanging plate, drop and squeeze recordings, each fitted alone;
  (ii)  the three fitted jointly (`fitting.joint.calibrate_joint`);
  (iii) `jaxfoam design` of the hanging plate's motion (AMPLITUDES x FREQUENCIES, 1 s at 15 fps, the
        reference camera's pixels) with the drop and squeeze as recordings already made, from the joint
        fit (ii) as the guess (what a user has in hand; a value on a bound moved 2% of the span inside),
        worst over 3 parameter points, ranked on the renderer's misfit (--misfit render); the best-ranked
        motion filmed by the reference simulator at material K; drop + squeeze + that recording fitted
        jointly. The best candidate is predicted once more at the truth, and once with the made
        recordings' misfit (--misfit with), so predicted half-widths can be set against the achieved
        statistical ones.
Every fit: dx FIT_DX, 2 starts of up to 15 LM iterations, the discretization check on (the reported
intervals combine it with the statistical ones; both are recorded). Each step's record is kept in
experiments/results/material_study/ and a rerun resumes after the last finished step.

Usage: python -m experiments material_study [--material K ...] [--stop-after STEP] [--grid 1cm|default]
                                            [--design-grid 1cm|default] [--report]
Writes experiments/results/material_study.md (--grid default: material_study_default.md, the fitter's
default grid, records *_default). With --design-grid G (another grid) step (iii) fits, on --grid, the
recording that G's design chose (records *_designed_joint<tag>_design<G>; page <page>_design<G>.md);
G = 1cm_check is the 1 cm design ranked with `design(dx_check=True)`. SI units.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from experiments import _common as C  # noqa: E402
from experiments.reference import generate as G  # noqa: E402
from fitting import FitSettings, calibrate, read_silhouettes  # noqa: E402
from fitting.design import TOLERANCE, Variable, design, half_widths  # noqa: E402
from fitting.joint import calibrate_joint  # noqa: E402
from fitting.settings import BOUND_SPAN_FRACTION  # noqa: E402
from jaxfoam.guards import atomic_output  # noqa: E402

NAME = "material_study"
RECORDS = C.RESULTS / NAME
KINDS = ("hanging_plate_2d", "drop_2d", "squeeze_2d")
NAMES = ("mu", "sigma_y", "eta", "m")
FIT_DX = 0.01        # m: fits of three recordings and a 20-candidate design per material fit the session
SETTINGS = FitSettings(dx=FIT_DX, starts=2, max_iter=15)


@dataclasses.dataclass(frozen=True)
class Grid:
    """A fit grid of the study: its records' suffix, the fits' settings and the page's name."""

    tag: str
    settings: FitSettings
    page: str
    design_from: str | None = None  # another grid's name whose design (and designed recording) to fit
    design_check: bool = False      # rank the design with the fit's discretization check predicted
    guess_tag: str | None = None    # the tag of the joint fit whose values are the design's guess (None: own)

    @property
    def design(self) -> "Grid":
        """The grid whose design records and designed recording this grid's designed joint fit uses."""
        return self if self.design_from is None else GRIDS[self.design_from]

    @property
    def designed_tag(self) -> str:
        """The designed joint fit's record suffix."""
        return self.tag + ("" if self.design_from is None else f"_design{self.design_from}")


GRIDS = {"1cm": Grid("", SETTINGS, NAME),
         "default": Grid("_default", dataclasses.replace(SETTINGS, dx=None), NAME + "_default"),
         # a design source only (--design-grid): the 1 cm design from the 1 cm joint fit, ranked with dx_check
         "1cm_check": Grid("_check", SETTINGS, NAME + "_check", design_check=True, guess_tag=""),
         # every fit on the frames its grid resolves (a window per recording in the joint fits)
         "1cm_resolved": Grid("_resolved", dataclasses.replace(SETTINGS, resolved_frames=True), NAME + "_resolved"),
         "default_resolved": Grid("_default_resolved", dataclasses.replace(SETTINGS, dx=None, resolved_frames=True),
                                  NAME + "_default_resolved")}
AMPLITUDES = (0.005, 0.01, 0.02, 0.03)   # m
FREQUENCIES = (1.0, 2.0, 3.0, 5.0, 8.0)  # Hz
DESIGN_DURATION, DESIGN_FPS, DESIGN_POINTS = 1.0, 15.0, 3
STEPS = ("single", "joint", "design", "designed_joint")  # design includes design_misfit


def data_path(kind: str, k: int, designed: bool = False, tag: str = "") -> Path:
    return G.MATERIALS_DIR / f"{kind}_mat{k}{'_designed' + tag if designed else ''}.h5"


def record_path(k: int, step: str, kind: str | None = None, grid: Grid = GRIDS["1cm"]) -> Path:
    return RECORDS / f"mat{k}_{step}{'_' + kind if kind else ''}{grid.tag}.json"


def _save(path: Path, rec: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(rec, indent=1, allow_nan=True, default=float))


def _load(path: Path):
    return json.loads(path.read_text()) if path.exists() else None


def _fit_record(res, wall: float, files) -> dict:
    return dict(files=[str(Path(f).name) for f in files], params=res.params, interval=dict(res.interval),
                interval_statistical=dict(res.interval_statistical), identifiable=res.identifiable,
                notes=list(res.notes), loss=res.loss, wall=wall, measured=C.machine_line(),
                **({"resolved_frames": res.settings["resolved"]["frames"], "of": res.settings["resolved"]["of"]}
                   if res.settings.get("resolved") else {}),
                **({"information_share": res.information_share,
                    "recordings": [{q: r[q] for q in ("name", "scale", "loss", "reproduced")} for r in res.recordings]}
                   if hasattr(res, "information_share") else {}))


def _design_inputs(k: int, grid: Grid, misfit: str):
    """The hanging plate's scene (dict) and the design's keyword arguments: the drop and squeeze of
    material k as recordings made, the reference camera's pixels, the given misfit."""
    return (read_silhouettes(data_path(KINDS[0], k)).scene_dict,
            dict(settings=grid.settings, duration=DESIGN_DURATION, fps=DESIGN_FPS, pixel_size=G.PIXEL_SIZE,
                 with_data=[read_silhouettes(data_path(kind, k)) for kind in KINDS[1:]], misfit=misfit))


def run_material(k: int, stop_after: str, grid: Grid = GRIDS["1cm"], say=print) -> None:
    truth = G.materials()[k]
    for kind in KINDS:
        out = record_path(k, "single", kind, grid=grid)
        if out.exists():
            continue
        t = time.perf_counter()
        res = calibrate(read_silhouettes(data_path(kind, k)), grid.settings)
        _save(out, _fit_record(res, time.perf_counter() - t, [data_path(kind, k)]))
        say(f"mat{k} {kind} alone: {_short(res.params)} in {time.perf_counter() - t:.0f} s")
    if stop_after == "single":
        return
    out = record_path(k, "joint", grid=grid)
    if not out.exists():
        files = [data_path(kind, k) for kind in KINDS]
        t = time.perf_counter()
        res = calibrate_joint([read_silhouettes(f) for f in files], grid.settings)
        _save(out, _fit_record(res, time.perf_counter() - t, files))
        say(f"mat{k} joint: {_short(res.params)} in {time.perf_counter() - t:.0f} s")
    if stop_after == "joint":
        return
    dg = grid.design
    out = record_path(k, "design", grid=dg)
    scene_file = RECORDS / f"mat{k}_designed_scene{dg.tag}.json"
    if not out.exists():
        source = RECORDS / f"mat{k}_joint{dg.tag if dg.guess_tag is None else dg.guess_tag}.json"
        if not source.exists():
            raise SystemExit(f"material {k}: the design's guess needs the joint fit {source.name}; run its grid's "
                             f"study first")
        guess = inside_bounds({n: _load(source)["params"][n] for n in NAMES})
        variables = [Variable("plate.motion.amplitude", AMPLITUDES), Variable("plate.motion.frequency", FREQUENCIES)]
        scene, kw = _design_inputs(k, dg, "render")
        t = time.perf_counter()
        res = design(scene, guess, variables, points=DESIGN_POINTS, dx_check=dg.design_check, **kw)
        wall = time.perf_counter() - t
        best = res.best
        at_truth = design(scene, truth, [Variable(n, (v,)) for n, v in best["values"].items()],
                          points=1, dx_check=dg.design_check, **kw).best
        res.write_scene(scene_file)
        _save(out, dict(guess=guess, wall=wall, candidates=len(res.candidates), values=best["values"],
                        recording=best["recording"], predicted_guess=half_widths(best["predicted"][0], guess),
                        predicted_worst=best["half_width"],
                        predicted_truth=half_widths(at_truth["predicted"][0], truth),
                        **({"predicted_reported_truth": half_widths(at_truth["predicted_reported"][0], truth),
                            "numerical_error_z": best["numerical_error_z"]} if dg.design_check else {}),
                        with_only=res.with_only, advice=res.advice,
                        ranking=[dict(values=c["values"], half_width=c["half_width"], within=c["within"])
                                 for c in res.candidates], measured=C.machine_line()))
        say(f"mat{k} design: best {best['values']} of {len(res.candidates)} in {wall:.0f} s")
    out_m = record_path(k, "design_misfit", grid=dg)
    if not out_m.exists():  # the best candidate predicted once more with the made recordings' misfit
        rec = _load(out)
        scene, kw = _design_inputs(k, dg, "with")
        one = [Variable(n, (v,)) for n, v in rec["values"].items()]
        t = time.perf_counter()
        best = design(scene, rec["guess"], one, points=DESIGN_POINTS, dx_check=dg.design_check, **kw).best
        _save(out_m, dict(predicted_guess=half_widths(best["predicted"][0], rec["guess"]),
                          predicted_worst=best["half_width"], wall=time.perf_counter() - t, measured=C.machine_line()))
        say(f"mat{k} design with the made recordings' misfit: {_short(best['half_width'])}")
    if stop_after == "design":
        return
    designed = data_path(KINDS[0], k, designed=True, tag=dg.tag)
    if not designed.exists():
        rec = _load(out)["recording"]
        case = G.Case(KINDS[0], float(rec["duration"]), int(rec["frames"]), 4.0, 1, 0, path=str(scene_file))
        G.generate(KINDS[0], 0, G.MATERIALS_DIR, material=k, case=case, name=designed.stem,
                   progress=lambda m: None)
        (G.MATERIALS_DIR / "README.md").write_text(G.MATERIALS_README_HEAD + G.index_table(G.MATERIALS_DIR))
        say(f"mat{k}: made {designed.name}")
    out = RECORDS / f"mat{k}_designed_joint{grid.designed_tag}.json"
    if not out.exists():
        files = [designed] + [data_path(kind, k) for kind in KINDS[1:]]
        t = time.perf_counter()
        res = calibrate_joint([read_silhouettes(f) for f in files], grid.settings)
        _save(out, _fit_record(res, time.perf_counter() - t, files))
        say(f"mat{k} designed joint: {_short(res.params)} in {time.perf_counter() - t:.0f} s")


GUESS_MARGIN = 0.02  # of a bound's span (log span for positive parameters): a fit's value on a bound, moved inside


def inside_bounds(params: dict) -> dict:
    """The joint fit's values as a design guess: a value on (or past) a bound moved GUESS_MARGIN inside it."""
    out = {}
    for n, v in params.items():
        lo, hi = SETTINGS.bounds_of(n)
        if n == "m":
            a, b, x = lo, hi, v
        else:
            a, b, x = math.log(lo), math.log(hi), math.log(v)
        y = min(max(x, a + GUESS_MARGIN * (b - a)), b - GUESS_MARGIN * (b - a))
        out[n] = v if y == x else (y if n == "m" else math.exp(y))
    return out


def _short(p: dict) -> dict:
    return {n: round(float(p[n]), 4) for n in NAMES}


def error(name: str, value: float, truth: float) -> float:
    """Signed error: absolute for m, relative otherwise (the design's TOLERANCE convention)."""
    return value - truth if name == "m" else value / truth - 1.0


def within(name: str, value: float, truth: float) -> bool:
    return abs(error(name, value, truth)) <= TOLERANCE[name]


def half_width(name: str, interval, value: float) -> float:
    """`fitting.design.half_widths` of one parameter: relative to the value, absolute for m."""
    return half_widths({name: interval}, {name: value})[name]


def log_width(name: str, interval) -> float:
    """An interval's width in the fit's own coordinates: log(hi / lo) for mu, sigma_y, eta; hi - lo for m."""
    lo, hi = interval
    return hi - lo if name == "m" else math.log(hi / lo)


def covers_bounds(name: str, interval, settings: FitSettings) -> bool:
    """Whether an interval spans at least BOUND_SPAN_FRACTION of the parameter's bounds (log span for
    positive parameters): the data then inform it no more than the bounds do."""
    lo, hi = settings.bounds_of(name)
    return log_width(name, interval) >= BOUND_SPAN_FRACTION * log_width(name, (lo, hi))


def _fmt_err(n, e):
    return f"{e:+.2f}" if n == "m" else f"{100 * e:+.0f}%"


def _fmt_hw(n, v):
    return "inf" if not math.isfinite(v) else (f"{v:.3g}" if n == "m" else f"{100 * v:.3g}%")


def report(materials, grid: Grid = GRIDS["1cm"]) -> Path:
    """Rebuild material_study.md from the records (finished steps only)."""
    st = grid.settings
    body = [f"Fit settings: dx {f'{st.dx} m' if st.dx else 'the fitter default (64 cells across the domain)'}, "
            f"{st.starts} starts of up to {st.max_iter} LM iterations, "
            f"the discretization check on"
            + (", every fit on the frames its grid resolves (`--resolved-frames`; a window per recording in the "
               "joint fits)" if st.resolved_frames else "")
            + f". Tolerance (design's): {TOLERANCE} (relative; m absolute).\n"]
    goals = {"joint2x": [], "designed": [], "pred": [], "pred_misfit": []}
    for k in materials:
        truth = G.materials()[k]
        singles = {kind: _load(record_path(k, "single", kind, grid=grid)) for kind in KINDS}
        joint, des = (_load(record_path(k, s, grid=g)) for s, g in (("joint", grid), ("design", grid.design)))
        dj = _load(RECORDS / f"mat{k}_designed_joint{grid.designed_tag}.json")
        body.append(f"## Material {k}: mu {truth['mu']:g} Pa, sigma_y {truth['sigma_y']:g} Pa, "
                    f"eta {truth['eta']:g} Pa s^m, m {truth['m']:g}\n")
        cols = [(kind.replace('_2d', '') + " alone", singles[kind]) for kind in KINDS] + [
            ("joint (h + d + s)", joint), ("designed joint", dj)]
        cols = [(lab, r) for lab, r in cols if r is not None]
        if not cols:
            body.append("No step finished.\n")
            continue
        rows = []
        for n in NAMES:
            row = [n, f"{truth[n]:g}"]
            for _, r in cols:
                v, (lo, hi) = r["params"][n], r["interval"][n]
                flag = (("" if lo <= truth[n] <= hi else " OUT") + (" ok" if within(n, v, truth[n]) else "")
                        + (" id" if r.get("identifiable", {}).get(n) else ""))
                row.append(f"{v:.4g} ({_fmt_err(n, error(n, v, truth[n]))}) [{lo:.3g}, {hi:.3g}]{flag}")
            rows.append(row)
        body.append("Value (error) [reported 95% interval]; OUT: truth outside it; ok: within tolerance; "
                    "id: reported identifiable.\n")
        body.append(C.md_table(["param", "truth"] + [lab for lab, _ in cols], rows) + "\n")
        rows = []
        for n in NAMES:
            row = [n]
            for _, r in cols:
                row.append(f"{_fmt_hw(n, half_width(n, r['interval'][n], r['params'][n]))} / "
                           f"{_fmt_hw(n, half_width(n, r['interval_statistical'][n], r['params'][n]))}")
            rows.append(row)
        body.append("Half-widths, reported / statistical (relative; m absolute):\n")
        body.append(C.md_table(["param"] + [lab for lab, _ in cols], rows) + "\n")
        if joint and all(singles.values()):
            ratios = {}
            for n in ("sigma_y", "eta"):
                for which in ("interval", "interval_statistical"):
                    best = min(log_width(n, s[which][n]) for s in singles.values())
                    ratios[(n, which)] = best / log_width(n, joint[which][n])
            goals["joint2x"].append((k, ratios))
            body.append("Narrowing, the best single recording's interval width over the joint one's (log width): " + "; ".join(
                f"{n} {ratios[(n, 'interval')]:.2f} (statistical {ratios[(n, 'interval_statistical')]:.2f})"
                for n in ("sigma_y", "eta")) + ". Joint information shares (h / d / s): " + "; ".join(
                f"{n} " + " / ".join(f"{100 * v:.0f}%" for v in joint["information_share"][n]) for n in NAMES)
                + ". Noise scales " + ", ".join(f"{r['scale']:.3g}" for r in joint["recordings"]) + ".\n")
        if des:
            where = ("" if grid.design_from is None else
                     f" on the {grid.design_from} grid (its joint fit's values, its fits' predictions)")
            body.append(f"Design from the joint fit's values{where}: {des['candidates']} candidates in "
                        f"{des['wall']:.0f} s; best {des['values']}. {des['advice']}\n")
        if dj and des:
            ok = all(within(n, dj["params"][n], truth[n]) and dj["interval"][n][0] <= truth[n] <= dj["interval"][n][1]
                     for n in NAMES)
            goals["designed"].append((k, ok))
            rows = []
            for n in NAMES:
                ach = half_width(n, dj["interval_statistical"][n], dj["params"][n])
                pt = des["predicted_truth"][n]
                informative = not covers_bounds(n, dj["interval_statistical"][n], st)
                if informative:
                    goals["pred"].append(ach / pt if pt > 0 and math.isfinite(pt) else math.inf)
                dm = _load(record_path(k, "design_misfit", grid=grid.design))
                mis = [_fmt_hw(n, dm["predicted_guess"][n]), _fmt_hw(n, dm["predicted_worst"][n]),
                       f"{ach / dm['predicted_worst'][n]:.2f}"] if dm else ["-", "-", "-"]
                if dm and informative:
                    goals["pred_misfit"].append(ach / dm["predicted_worst"][n])
                rows.append([n, _fmt_hw(n, des["predicted_guess"][n]), _fmt_hw(n, des["predicted_worst"][n]),
                             _fmt_hw(n, pt), _fmt_hw(n, ach) + ("" if informative else " (bounds)"),
                             f"{ach / pt:.2f}" if pt > 0 else "-"] + mis)
            if "predicted_reported_truth" in des:
                rep_rows = []
                for n in NAMES:
                    ach = half_width(n, dj["interval"][n], dj["params"][n])
                    pr = des["predicted_reported_truth"][n]
                    goals.setdefault("pred_reported", []).append(ach / pr if pr > 0 else math.inf)
                    rep_rows.append([n, _fmt_hw(n, pr), _fmt_hw(n, ach), f"{ach / pr:.2f}" if pr > 0 else "-"])
                body.append("Designed joint fit: reported half-widths (statistical and numerical) predicted by the "
                            "design's dx_check at the truth on its own grid, against those the fit reported:\n")
                body.append(C.md_table(["param", "predicted reported (truth)", "achieved reported",
                                        "achieved / predicted"], rep_rows) + "\n")
            body.append("Designed joint fit: predicted statistical half-widths against achieved"
                        + (" (the 'worst point' and misfit columns include the dx_check's numerical error)"
                           if "predicted_reported_truth" in des else "") + ":\n")
            body.append(C.md_table(["param", "predicted (guess)", "predicted (worst point)", "predicted (truth)",
                                    "achieved", "achieved / predicted (truth)", "misfit 'with': predicted (guess)",
                                    "(worst point)", "achieved / predicted (worst)"], rows) + "\n")
        if st.resolved_frames:
            body.append("Frames fitted (resolved of observed): " + "; ".join(
                f"{lab} {r['resolved_frames']} of {r['of']}" for lab, r in cols if "resolved_frames" in r) + ".\n")
        walls = [f"{lab} {r['wall'] / 60:.1f} min" for lab, r in cols]
        body.append("Wall times: " + ", ".join(walls) + ".\n")
    summary = ["## Goals (issue: joint fits and experiment design)\n"]
    if goals["joint2x"]:
        met = [k for k, r in goals["joint2x"] if r[("sigma_y", "interval")] >= 2 and r[("eta", "interval")] >= 2]
        summary.append(f"- Joint fit of the three default recordings, sigma_y and eta reported intervals at least 2x "
                       f"narrower than the best single recording's: {len(met)} of {len(goals['joint2x'])} materials "
                       f"(goal: every material).")
    if goals["designed"]:
        summary.append(f"- Designed recordings, all four parameters within tolerance with the truth inside: "
                       f"{sum(ok for _, ok in goals['designed'])} of {len(goals['designed'])} materials (goal: 2 of 3).")
    if goals["pred"]:
        inside = sum(0.5 <= r <= 2.0 for r in goals["pred"])
        summary.append(f"- Achieved statistical half-widths within 2x of the predicted (at the truth): {inside} of "
                       f"{len(goals['pred'])} parameter-cases whose achieved interval is narrower than "
                       f"{BOUND_SPAN_FRACTION:.0%} of the bounds (goal: within 2x).")
    if goals["pred_misfit"]:
        inside = sum(0.5 <= r <= 2.0 for r in goals["pred_misfit"])
        summary.append(f"- The same with the design's misfit 'with' (the made recordings' misfit; worst point): "
                       f"{inside} of {len(goals['pred_misfit'])}.")
    if goals.get("pred_reported"):
        inside = sum(0.5 <= r <= 2.0 for r in goals["pred_reported"])
        summary.append(f"- Reported half-widths within 2x of those the design's dx_check predicted at the truth: "
                       f"{inside} of {len(goals['pred_reported'])} parameter-cases.")
    text = "\n".join(summary) + "\n\n" + "\n".join(body)
    return C.write_md(grid.page, False, "One foam in three recordings: single, joint and designed fits on reference data",
                      text, command=NAME + ("" if grid.tag == "" else " --grid " + next(n for n, g in GRIDS.items() if g.tag == grid.tag))
                      + ("" if grid.design_from is None else f" --design-grid {grid.design_from}"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", type=int, action="append", help="material index (repeatable; default all)")
    ap.add_argument("--stop-after", choices=STEPS, default=STEPS[-1])
    ap.add_argument("--grid", choices=sorted(GRIDS), default="1cm",
                    help="the fits' grid: dx 1 cm, or the fitter's default (records *_default, page material_study_default.md)")
    ap.add_argument("--design-grid", choices=sorted(GRIDS), default=None,
                    help="fit the designed recording of this grid's design (default: design on --grid itself)")
    ap.add_argument("--report", action="store_true", help="rebuild the page from the records, no fits")
    args = ap.parse_args(argv)
    grid = GRIDS[args.grid]
    if args.design_grid is not None and args.design_grid != args.grid:
        grid = dataclasses.replace(grid, design_from=args.design_grid, page=f"{grid.page}_design{args.design_grid}")
    mats = args.material if args.material is not None else list(range(G.N_MATERIALS))
    for k in mats:
        if not 0 <= k < G.N_MATERIALS:
            ap.error(f"--material: {k} is not in [0, {G.N_MATERIALS - 1}]")
    if not args.report:
        for k in mats:
            missing = [str(data_path(kind, k)) for kind in KINDS if not data_path(kind, k).exists()]
            if missing:
                ap.error(f"material {k}: missing {missing}; make them with "
                         f"python -m experiments.reference generate --material {k}")
            run_material(k, args.stop_after, grid, say=lambda m: print(m, flush=True))
    print(report(range(G.N_MATERIALS), grid))
    return 0


if __name__ == "__main__":
    sys.exit(main())
