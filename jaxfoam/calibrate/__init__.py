"""Calibration: fit mu, sigma_y, eta and m of a scene to tracked silhouettes.

The glue between the silhouette data (`jaxfoam.io`), the simulator (`jaxfoam.Simulator`), the
differentiable renderer (`jaxfoam.silhouette`) and the optimizers (`fitting`):

1. `build_problem(data, settings)`: the scene comes from the data file; density and kappa are known
   inputs of the scene (never fitted; `fixed` may override them). A `Simulator` is bound once at the
   fit's dx, at the data's frame times, from the scene's initial shape (`first_mask`: the first mask
   and camera, and the simulation starts at the first frame's time). Its time step is the CFL step
   of the stiffest material the bounds allow (the largest mu), with a fixed number of substeps per
   frame, so the objective is a smooth function of the parameters.
2. The residual z -> r: fitted coordinates z (log / bounded maps of `fitting.ParameterTransform`)
   -> parameters -> rollout -> particle positions at the observed times -> soft silhouettes at the
   data's camera -> weighted residual images plus the distance-field terms (`silhouette.residuals`).
   The observed masks are compared at the pyramid level whose pixels are closest to (not larger than)
   the fit's particle spacing (`pixel_level`), so a fine video does not cost more than the simulation
   can resolve. Frames at or before the simulation's start carry no information on the parameters
   and are left out.
3. The Jacobian dr/dz by forward mode: one jvp rollout per fitted parameter (4 at most), each giving
   r and one column (no tape: memory independent of the number of substeps).
4. `calibrate(data, settings)`: the optimizer (Levenberg-Marquardt by default, or L-BFGS / Adam on
   0.5 |r|^2) from a multi-start (the centre of the starting range, then a seeded Latin hypercube),
   every iteration written to an HDF5 fit log (`resume=True` continues a killed fit), then the
   Gauss-Newton uncertainty at the best optimum (correlations, identifiability notes), widened by
   an estimate of the discretization error of the estimate (`discretization_error`: the residual and
   Jacobian once more on a finer grid), into 95% intervals, returned as a `FitResult`.

The command line is `jaxfoam fit data.h5 --out fit.json` (see `add_fit_parser`).
A fitter never reads the data's /truth: nothing here touches `Silhouettes.truth`.
Units: SI throughout (m, s, kg, Pa); fitted coordinates are dimensionless.
"""
from __future__ import annotations

from .._params import FIT_FIELDS as FIT_FIELDS
from .settings import (ADAM_DECAY as ADAM_DECAY, ADAM_LEARNING_RATE as ADAM_LEARNING_RATE,
                       BOUND_SPAN_FRACTION as BOUND_SPAN_FRACTION,
                       CORRELATION_WINDOW_SUPPORTS as CORRELATION_WINDOW_SUPPORTS, CalibrationError as CalibrationError,
                       DEFAULT_BOUNDS as DEFAULT_BOUNDS, DEFAULT_DX_REFIT as DEFAULT_DX_REFIT,
                       DEFAULT_LEVEL as DEFAULT_LEVEL, DEFAULT_MAX_ITER as DEFAULT_MAX_ITER,
                       DEFAULT_STARTS as DEFAULT_STARTS, DEFAULT_START_RANGES as DEFAULT_START_RANGES,
                       DX_CHECK_JACOBIAN as DX_CHECK_JACOBIAN, DX_CHECK_ORDER as DX_CHECK_ORDER,
                       DX_CHECK_RATIO as DX_CHECK_RATIO, FIT_CELLS as FIT_CELLS, FIT_CFL as FIT_CFL,
                       FIT_DTYPE as FIT_DTYPE, FIT_FRACTURE as FIT_FRACTURE, FIT_PPC as FIT_PPC,
                       FIT_RESAMPLE as FIT_RESAMPLE, FRAME_BOUNDARY_SPACINGS as FRAME_BOUNDARY_SPACINGS, FTOL as FTOL,
                       FitSettings as FitSettings, GCI_SAFETY as GCI_SAFETY, KNOWN_INPUTS as KNOWN_INPUTS,
                       MAX_FRAMES_PER_OBSERVED as MAX_FRAMES_PER_OBSERVED, MIN_DOMAIN_PIXELS as MIN_DOMAIN_PIXELS,
                       MIN_LEVEL_PIXELS as MIN_LEVEL_PIXELS, OPTIMIZERS as OPTIMIZERS, XTOL as XTOL,
                       _as_config as _as_config, _check_config as _check_config)
from .result import FitResult as FitResult, _format_params as _format_params
from .problem import (CalibrationProblem as CalibrationProblem, _Static as _Static,
                      _residual_and_jacfwd as _residual_and_jacfwd,
                      _data_fingerprint as _data_fingerprint, _observed as _observed, _params_from as _params_from,
                      _positions as _positions, _residual as _residual, _residual_and_columns as _residual_and_columns,
                      _residual_and_jacobian as _residual_and_jacobian, _residual_jit as _residual_jit,
                      build_problem as build_problem, check_fit_data as check_fit_data,
                      choose_pixel_level as choose_pixel_level, fit_transform as fit_transform,
                      fitted_occupancy as fitted_occupancy, max_pixel_level as max_pixel_level,
                      observe_positions as observe_positions, simulation_frames as simulation_frames,
                      without_plate_pixels as without_plate_pixels)
from .check import (UNEVEN_FRAME_RATIO as UNEVEN_FRAME_RATIO, check_error as check_error,
                    combine_intervals as combine_intervals, correlation_area as correlation_area,
                    discretization_error as discretization_error, fit_uncertainty as fit_uncertainty,
                    numerical_half_width as numerical_half_width, predicted_move as predicted_move,
                    refit_move as refit_move, uneven_frames_note as uneven_frames_note)
from .driver import (_path_settings as _path_settings, _same_fit as _same_fit,
                     _with_goodness_of_fit as _with_goodness_of_fit, calibrate as calibrate,
                     default_log_path as default_log_path, judge_reported_intervals as judge_reported_intervals,
                     make_optimizer as make_optimizer, make_starts as make_starts,
                     silhouette_mismatch as silhouette_mismatch)
from .plots import plot_loss as plot_loss, plot_overlay as plot_overlay
from .cli import (_DURATION_UNITS as _DURATION_UNITS, _Terminated as _Terminated,
                  _parse_assignments as _parse_assignments, _parse_numbers as _parse_numbers,
                  _terminate_as_interrupt as _terminate_as_interrupt, add_fit_parser as add_fit_parser,
                  parse_bounds as parse_bounds, parse_duration as parse_duration, parse_feature as parse_feature,
                  parse_fixed as parse_fixed, parse_start as parse_start, parse_window as parse_window,
                  run_fit as run_fit, settings_from_args as settings_from_args)
