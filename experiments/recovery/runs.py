"""Running the recovery study's fits. Each case's record is written once it finishes (atomically), each
fit logs every iteration, and data files are made once, so a killed study resumes losing nothing: re-running
skips finished cases and continues an unfinished fit from its log. Finished fits whose intervals follow
older uncertainty rules are re-reported from their logs at the same optimum."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

import fitting
from experiments.recovery.cases import (
    BUDGET,
    CASES,
    DATA,
    FULL,
    N_SETS,
    PRECISION,
    PROBES,
    QUICK,
    WORK,
    SceneCase,
    case_id,
    fitter_refit,
    make_data,
    plan,
    starts_for,
    write_atomic,
)
from experiments.recovery.scoring import GOALS, evaluate
from fitting import FitSettings, calibrate
from fitting.settings import DX_CHECK_JACOBIAN, GCI_SAFETY
from fitting import read_silhouettes


def reported_with_current_rules(record: dict) -> bool:
    """Whether a finished fit's intervals were computed with the fitter's current uncertainty rules
    (the discretization check's safety factor `fitting.settings.GCI_SAFETY`, its Jacobian,
    `DX_CHECK_JACOBIAN`, records from before the latter was recorded reused the fit grid's, and its measured
    move, `DEFAULT_DX_REFIT` iterations for the scene's dimension). The report applies the measured move to
    older records from a cache instead (`with_current_check`)."""
    check = record["fit"]["settings"].get("dx_check") or {}
    # older records lack interval_local: a misfit then still reported its local interval
    return (check.get("safety") == GCI_SAFETY and check.get("jacobian", "fit") == DX_CHECK_JACOBIAN
            and check.get("refit") == fitter_refit(record) and "interval_local" in record["fit"])


def run_job(c: SceneCase, k: int, opt: str, quick: bool) -> Path:
    """Fit one case (resuming its log), or re-report a finished one whose intervals were computed with
    other uncertainty rules: `calibrate` then reads every iteration back from the fit log, runs no
    optimizer step, and recomputes the uncertainty at the same optimum (the fit's wall time keeps the
    logged optimizer time and adds this set-up and uncertainty)."""
    cid = case_id(c, k, quick)
    res_path = CASES / f"{cid}_{opt}.json"
    log = WORK / f"{cid}_{opt}.fitlog.h5"
    old = json.loads(res_path.read_text()) if res_path.exists() else None
    if old is not None and len(old["fit"]["runs"]) != starts_for(c, opt, quick):
        # a fit with another number of starts: kept aside, and this case fitted afresh
        tag = f".superseded-{len(old['fit']['runs'])}start"
        res_path.rename(res_path.with_name(res_path.name + tag))
        if log.exists():
            log.rename(log.with_name(log.name + tag))
        old = None
    if old is not None and (reported_with_current_rules(old) or not log.exists()):
        return res_path
    print(f"== {cid} {opt}: " + ("re-reporting the logged fit" if old else "data"), flush=True)
    data_path, synth_wall = make_data(c, k, quick)
    data = read_silhouettes(data_path)
    b = BUDGET[quick]
    settings = FitSettings(dx=c.dx_fit, optimizer=opt, starts=starts_for(c, opt, quick), max_iter=b["iters"][opt],
                           seed=0, time_window=c.window, dtype=c.fit_dtype)
    t0 = time.perf_counter()
    res = calibrate(data, settings, log=log, resume=True, progress=lambda m: print("  " + m, flush=True))
    fit = res.to_dict()
    if old is not None and not np.allclose([fit["params"][n] for n in GOALS], [old["fit"]["params"][n] for n in GOALS],
                                           rtol=1e-9, atol=0.0):
        raise RuntimeError(f"{cid} {opt}: re-reporting moved the fitted parameters; the log does not hold this fit")
    record = {"case": cid, "scene": c.name, "set": k, "optimizer": opt, "dx_fit": c.dx_fit, "dx_data": c.dx_fit / c.data_ratio,
                  "data_variant": {"tag": c.tag, "noise": c.noise, "drop_frames": c.drop_frames, "pixel_size": data.camera.pixel_size,
                                    "first_mask": c.first_mask},
                  "duration": c.duration, "frames": c.frames, "truth": data.truth, "fit": fit,
                  "evaluation": evaluate(fit, data.truth),
                  "fit_wall_this_session": old["fit_wall_this_session"] if old else time.perf_counter() - t0,
                  "synth_wall": old["synth_wall"] if old else synth_wall, "histories": _histories(log)}
    if old is not None:
        prev = old["fit"]["settings"].get("dx_check") or {}
        record["rereported"] = {"wall": time.perf_counter() - t0, "date": time.strftime("%Y-%m-%d"),
                                    "previous_safety": prev.get("safety"), "previous_jacobian": prev.get("jacobian", "fit"),
                                    "previous_evaluation": old["evaluation"],
                                    "previous_numerical_error": old["fit"].get("numerical_error")}
    # written whole or not at all: a study killed here re-runs this case from its log
    write_atomic(res_path, json.dumps(record, indent=1) + "\n")
    print(res.report(), flush=True)
    return res_path


def _histories(log: Path) -> dict:
    """Loss and wall-time histories of every start in a fit log."""
    runs = fitting.read_fitlog(log)["runs"]
    return {str(i): {"loss": np.asarray(r["loss"]).tolist(), "time": np.asarray(r["time"]).tolist()} for i, r in runs.items()}


def load_records(quick: bool) -> list[dict]:
    """The finished records of the study (quick or full), in plan order of the cases."""
    recs = []
    for c in (QUICK if quick else FULL + PROBES + DATA + PRECISION):
        for k in range(N_SETS):
            for opt in ("lm", "lbfgs", "adam"):
                p = CASES / f"{case_id(c, k, quick)}_{opt}.json"
                if p.exists():
                    recs.append(json.loads(p.read_text()))
    return recs


def run_study(quick: bool, n_sets: int | None = None, only: str | None = None, after_each=None) -> None:
    """Run the planned jobs in order (`only`: those whose scene name contains it), calling `after_each()`
    after each; finished cases are skipped and a killed fit resumes from its log."""
    for _, c, k, opt in plan(quick, n_sets):
        if only and only not in c.name:
            continue
        try:
            run_job(c, k, opt, quick)
            if after_each is not None:
                after_each()
        except Exception as exc:  # noqa: BLE001  (one failed case must not stop the study; reported as missing)
            print(f"== {case_id(c, k, quick)} {opt} FAILED: {type(exc).__name__}: {exc}", flush=True)
