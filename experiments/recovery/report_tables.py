"""Row and cell formatting of the recovery report: errors, wall times, moves in the fit's coordinates as
relative changes, and the tables the probe sections share."""
from __future__ import annotations

import json
import math

import numpy as np

from experiments import _common as C
from experiments.recovery.cases import CASES, DATA, case_of
from experiments.recovery.checks import record_optimum
from experiments.recovery.scoring import goodness, shear_rates, truth_frames, truth_loss
from fitting.settings import FRAME_BOUNDARY_SPACINGS


def _theta_of_move(r: dict, name: str, v: float, base: float = 0.0) -> tuple[float, float]:
    """Physical values (before, after) of parameter `name` of finished fit r when its fitted coordinate
    moves by v from the optimum's (plus `base`): the fitter's transform is logit-log for a bounded positive
    parameter, so a move in it is not a relative change (d z / d log theta = 1 / ((log hi - log lo) t (1 - t)),
    t the parameter's place between its bounds in log)."""
    tr, _, z = record_optimum(r)
    i = list(tr.names).index(name)
    z0, z1 = z.copy(), z.copy()
    z0[i] += base
    z1[i] += base + v
    return float(np.asarray(tr.to_physical(z0))[i]), float(np.asarray(tr.to_physical(z1))[i])


def rel_move(r: dict, name: str, v: float, base: float = 0.0) -> str:
    """A move v of `name`'s fitted coordinate (from the optimum plus `base`) as the relative change of the
    parameter it makes."""
    a, b = _theta_of_move(r, name, v, base)
    return _log_change(math.log(b / a)) if a > 0 and b > 0 else "n/a"


def error_range(r: dict, name: str, e: float) -> str:
    """The numerical error e (a half-width in the fitted coordinate) as the relative range around the estimate."""
    return f"{rel_move(r, name, -e)} / {rel_move(r, name, e)}"


def _log_change(v: float) -> str:
    """A move v in log coordinates as a relative change, or as the factor e^v beyond +700% / -99.9% (where
    a percentage says little; e^v written out when it would overflow)."""
    if -7.0 < v < 2.08:
        return f"{100 * math.expm1(v):+.1f}%"
    return f"x{math.exp(v):.3g}" if -700.0 < v < 700.0 else f"x e^{v:.3g}"


def truth_frames_table(recs: list[dict]) -> str:
    """One row per case: the truth's per-frame boundary distance on the fit grid (`truth_frames`)."""
    rows, width = [], 0
    for r in sorted(recs, key=lambda r: (r["scene"], r["set"])):
        try:
            tf = truth_frames(case_of(r), r["set"], r["case"].startswith("q_"))
        except Exception:  # noqa: BLE001, S112  (a diagnostic must not fail the report)
            continue
        cells = [f"{t:.2f} s: {b:.2f}" for t, b in zip(tf["times"], tf["boundary"])]
        width = max(width, len(cells))
        rows.append([r["scene"], r["set"], f"{r['dx_fit'] * 1e3:.2f}"] + cells)
    rows = [row + [""] * (3 + width - len(row)) for row in rows]
    return C.md_table(["scene", "set", "fit dx (mm)"] + [f"frame {i + 1}" for i in range(width)], rows)


def truth_loss_of(r: dict) -> float:
    """`truth_loss` of a finished fit; NaN when it cannot be computed."""
    c = case_of(r)
    try:
        return truth_loss(c, r["set"], r["case"].startswith("q_"))
    except Exception:  # noqa: BLE001  (the table must not fail over a diagnostic)
        return float("nan")


def fmt_gof(r: dict) -> str:
    """`goodness` as "min IoU; max boundary", marked **no** above the fitter's limit."""
    iou, spacings = goodness(r)
    return f"{iou:.2f}; {spacings:.2f}" + (" **no**" if spacings > FRAME_BOUNDARY_SPACINGS else "")


def fmt_shear(r: dict) -> str:
    """`shear_rates` as "yielding%; p10-p90"."""
    c = case_of(r)
    try:
        sh = shear_rates(c, r["set"], r["case"].startswith("q_"))
    except Exception as exc:  # noqa: BLE001  (the table must not fail over a diagnostic)
        return f"({type(exc).__name__})"
    return f"{100 * sh['yielding']:.0f}%; {sh['p10']:.2g}-{sh['p90']:.2g}"


def halved_step(r: dict) -> float:
    """How many times narrower than the fitter's time step a finished fit ran: 1 for a fit made with gap
    filling (`fitting.problem.simulation_frames`) or whose data have no gap, k > 1 for a fit made before
    it whose data have a frame dropped inside the fitted span, so that every frame ran the substeps of
    its widest interval (k = that interval over the narrowest). Computed from the record's times."""
    from fitting.problem import simulation_frames

    d = r["fit"]["data"]
    times = np.asarray(d["times"], float)[d["frames_used"]]
    t0 = float(d["times"][0]) if (r.get("data_variant") or {}).get("first_mask") else 0.0
    widest = float(np.max(np.diff(np.concatenate([[t0], times]))))
    sim_times, _ = simulation_frames(t0, times)
    filled = float(np.max(np.diff(np.concatenate([[t0], sim_times]))))
    n_fill = math.ceil(filled / r["fit"]["settings"]["dt"] - 1e-6)
    return widest / filled if r["fit"]["settings"]["substeps_per_frame"] > n_fill else 1.0


def wall_min(r: dict, seconds: float | None = None) -> str:
    """A fit's wall time in minutes, marked † when it ran at a narrowed time step (`halved_step`)."""
    w = r["fit"]["wall_time"] if seconds is None else seconds
    return f"{w / 60:.1f}" + ("†" if halved_step(r) > 1.0 else "")


def fmt_err(e: dict) -> str:
    """An evaluated parameter's error, flagged `out` (truth outside) and `n.i.` (not identifiable)."""
    s = f"{100 * e['error']:+.0f}%" if e["kind"] == "rel" else f"{e['error']:+.2f}"
    flags = ("" if e["inside"] else " out") + ("" if e["identifiable"] else " n.i.")
    return s + flags


def result_heads(names) -> list[str]:
    """The column heads of `result_cells`."""
    return [f"err {n}" for n in names] + ["loss", "loss at truth", "min IoU; max boundary (spacings)", "wall min"]


def result_cells(x: dict, names) -> list:
    """A probe row's cells of fit x: errors, loss, loss at the truth, goodness of fit, wall time."""
    return ([fmt_err(x["evaluation"][n]) for n in names]
            + [f"{x['fit']['loss']:.3g}", f"{truth_loss_of(x):.3g}", fmt_gof(x), wall_min(x)])


def wall_span(recs: list[dict]) -> str:
    """The range of fits' wall times, "a-b min per fit"."""
    walls = [r["fit"]["wall_time"] / 60 for r in recs]
    return f"{min(walls):.1f}-{max(walls):.1f} min per fit"


def probe_table(probe: list[dict], lm: list[dict], names, base_scene, base_of=None) -> str:
    """A probe's fits (FINE, SLIP, CONTACT), each after the study's LM fit of the same set on `base_scene(record)`:
    grids, errors, loss, loss at the truth, goodness of fit, wall time."""
    rows = []
    for r in sorted(probe, key=lambda r: (r["scene"], r["dx_fit"], r["set"])):
        same = [b for b in lm if b["scene"] == base_scene(r) and b["set"] == r["set"]]
        # the base fit on the probe's grid when there is one, else the study's
        base = next((b for b in same if b["dx_fit"] == r["dx_fit"]), same[0] if same else None)
        if base_of is not None and same:
            base = base_of(r, same)
        for x in ([base] if base else []) + [r]:
            cx = case_of(x)
            w = cx.window
            label = (x["scene"] + (f", t {w[0]:g}-{w[1]:g} s" if w else "")
                     + (f", {cx.fit_dtype}" if cx.fit_dtype != "float64" else ""))
            rows.append([label, x["set"], f"{x['dx_fit'] * 1e3:.2f}", f"{x['dx_data'] * 1e3:.2f}"]
                        + result_cells(x, names))
    return C.md_table(["scene", "set", "fit dx (mm)", "data dx (mm)"] + result_heads(names), rows)


def varied_table(varied: list[dict], lm: list[dict], names) -> str:
    """Per (scene, set): the main table's fit, then each data variant's (DATA order)."""
    order = {t: i for i, t in enumerate(dict.fromkeys(c.tag for c in DATA))}
    rows = []
    for scene, k in sorted({(r["scene"], r["set"]) for r in varied}):
        base = [b for b in lm if b["scene"] == scene and b["set"] == k]
        these = sorted((r for r in varied if r["scene"] == scene and r["set"] == k), key=lambda r: order[case_of(r).tag])
        for x in base + these:
            tag = case_of(x).tag or "main table"
            rows.append([scene, k, tag, f"{x['dx_data'] * 1e3:.2f}", f"{x['fit']['data']['pixel_size'] * 1e3:.2f}"]
                        + result_cells(x, names))
    return C.md_table(["scene", "set", "data", "data dx (mm)", "pixel (mm)"] + result_heads(names), rows)


def same_step_base(r: dict, base: list[dict]) -> dict:
    """The float64 fit of a float32 record's data made with the same time step: the current record, or the
    one it superseded when the gap filling changed its step (kept as <case>_lm.json.halved-dt)."""
    b = next(b for b in base if b["scene"] == r["scene"] and b["set"] == r["set"] and b["dx_fit"] == r["dx_fit"])
    old = CASES / f"{b['case']}_lm.json.halved-dt"
    if b["fit"]["settings"]["substeps_per_frame"] != r["fit"]["settings"]["substeps_per_frame"] and old.exists():
        return json.loads(old.read_text())
    return b


def tally(recs: list[dict], names) -> tuple[int, int, int, dict]:
    """(parameter-cases, truth inside the interval, goal met, name -> within the error goal) of fits."""
    inside = sum(r["evaluation"][p]["inside"] for r in recs for p in names)
    goals = sum(r["evaluation"][p]["goal_met"] for r in recs for p in names)
    within = {p: sum(r["evaluation"][p]["within_goal"] for r in recs) for p in names}
    return len(names) * len(recs), inside, goals, within
