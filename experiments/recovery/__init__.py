"""Parameter recovery: fit synthetic silhouettes made at a 2x finer grid and compare with the truth.

For each scene (hanging_plate, drop, squeeze in 2D; hanging_plate in 3D; experiments/scenes/*.json)
and each of three parameter sets in shaving-cream ranges (a seeded Latin hypercube over mu 50-400 Pa,
sigma_y 15-80 Pa, eta 1-30 Pa s^m log-uniform, m 0.3-1.0 uniform):

1. `fitting.synthesize` renders the scene at dx_data = dx_fit / 2 into tracked-video-like
   silhouettes (boundary pixel noise, dropped frames, plate pixels of weight 0, pixel size dx_data / 2);
2. `fitting.calibrate` fits mu, sigma_y, eta and m at dx_fit from the default starts and
   bounds (nothing here is tuned to these data: the fitter's defaults are used as a user would);
3. the study (never the fitter) reads the file's /truth and reports each parameter's error, whether
   the truth lies inside the 95% interval (the combined one, and the Gauss-Newton part alone),
   iterations, evaluations and wall time; two diagnostics explain a miss: the fit's loss at the true
   parameters (optimizer stuck in another basin, or the fit grid's optimum away from the truth) and
   the plastic shear-rate range the truth produces (eta and m separate only over a wide range).

The three optimizers (Levenberg-Marquardt, L-BFGS, Adam) are compared on the same data (loss against
wall time). The full study also refits the drop at dx_fit / sqrt(2) against data made at half that
(FINE), to see whether a finer fit grid brings the parameters closer to the truth, and the drop on a
frictionless floor (SLIP), to see how much of the drop's bias the floor's friction causes, the drop with
particle floor contact (CONTACT), to see how much of it the grid-contact gap under the landed foam causes,
the squeeze's data fitted over the squeeze and the hold only (WINDOW), to see how much of its bias the
lift causes, and fits the 2D scenes on the fitter's default grid (DEFAULT_GRID, 64 cells across, data at
half its spacing), what a user who keeps the default gets. The hanging plate and the drop are also
fitted to data made otherwise, one change at a time (DATA): on a grid 4x finer than the fit, with 4x the
boundary noise and 3x the dropped frames, through a camera with finer pixels, from a scene that starts
at the first mask as a tracked video's does, with masks grown by a pixel, and simulated with other
numerics (9 particles per cell, CFL 0.5, float32) as another simulator's would be. The main table's 2D
fits and the default grid's squeeze are repeated in float32 (PRECISION) on the same data. Goals (issue 4): mu and sigma_y within 10%,
m within 0.1, eta within 25% (or reported not identifiable with an interval containing the truth);
truth inside the interval in >= 90% of cases; a 2D fit under 15 minutes on 2 CPU cores.

Modules: cases (scenes, probes, truths, plan, datasets), runs (the fits, resumable), scoring (against the
truth), checks (diagnostics of the discretization check), report, report_sections, report_tables and
report_figure (the table and chart), __main__ (the command line).
"""
from experiments.recovery.cases import (
    BUDGET,
    CASES,
    COMPARE,
    CONTACT,
    DATA,
    DEFAULT_GRID,
    DROP_FRAMES,
    FINE,
    FULL,
    N_SETS,
    NAME,
    NOISE,
    PRECISION,
    PROBES,
    QUICK,
    ROOT,
    SCENES,
    SLIP,
    TRUTH_RANGES,
    TRUTH_SEED,
    WINDOW,
    WORK,
    SceneCase,
    case_id,
    case_of,
    data_path,
    default_fit_dx,
    fitter_refit,
    make_data,
    plan,
    starts_for,
    truth_sets,
)
from experiments.recovery.checks import (
    PREVIOUS_DX_REFIT,
    REFIT_ITERATIONS,
    SHIFT_FRACTIONS,
    measured_check,
    refit_check,
    shift_check,
    with_current_check,
    with_measured_move,
)
from experiments.recovery.report import report
from experiments.recovery.report_tables import halved_step
from experiments.recovery.runs import (
    load_records,
    reported_with_current_rules,
    run_job,
    run_study,
)
from experiments.recovery.scoring import (
    GOALS,
    evaluate,
    goodness,
    shear_rates,
    truth_frames,
    truth_loss,
)


def main(argv=None) -> None:
    """The command line (`python -m experiments recovery ...` calls this; see __main__)."""
    from experiments.recovery.__main__ import main as cli

    cli(argv)


__all__ = ["BUDGET", "CASES", "COMPARE", "CONTACT", "DATA", "DEFAULT_GRID", "DROP_FRAMES", "FINE", "FULL", "GOALS",
           "NAME", "NOISE", "N_SETS", "PRECISION", "PREVIOUS_DX_REFIT", "PROBES", "QUICK", "REFIT_ITERATIONS", "ROOT",
           "SCENES", "SHIFT_FRACTIONS", "SLIP", "TRUTH_RANGES", "TRUTH_SEED", "WINDOW", "WORK", "SceneCase", "case_id",
           "case_of", "data_path", "default_fit_dx", "evaluate", "fitter_refit", "goodness", "halved_step",
           "load_records", "main", "make_data", "measured_check", "plan", "refit_check", "report",
           "reported_with_current_rules", "run_job", "run_study", "shear_rates", "shift_check", "starts_for",
           "truth_frames", "truth_loss", "truth_sets", "with_current_check", "with_measured_move"]
