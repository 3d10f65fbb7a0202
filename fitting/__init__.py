"""Calibration: fit mu, sigma_y, eta and m of a scene to tracked silhouettes.

The calibration package of jaxfoam. It joins the silhouette data (`fitting.io`, `fitting.track`,
`fitting.synth`), the simulator (`jaxfoam`'s public API only), the differentiable renderer and
losses (`fitting.silhouette`) and the generic optimizers (`fitting.optim`):

1. `build_problem(data, settings)`: the scene comes from the data file; density and kappa are known
   inputs of the scene (never fitted; `fixed` may override them). A `Simulator` is bound once at the
   fit's dx, at the data's frame times, from the scene's initial shape (`first_mask`: the first mask
   and camera, and the simulation starts at the first frame's time). Its time step is the CFL step
   of the stiffest material the bounds allow (the largest mu), with a fixed number of substeps per
   frame, so the objective is a smooth function of the parameters.
2. The residual z -> r: fitted coordinates z (log / bounded maps of `fitting.optim.ParameterTransform`)
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

5. `fitting.joint`: one material fitted to several recordings (`calibrate([a, b, ...])`);
   `fitting.design`: candidate recordings ranked by the intervals a fit of them would give (`design`);
   `fitting.horizon`: a fit of only the frames the grid resolves (`FitSettings(resolved_frames=True)`).

The command lines are `jaxfoam fit data.h5 --out fit.json` (see `add_fit_parser`) and `jaxfoam design`.
A fitter never reads the data's /truth: nothing here touches `Silhouettes.truth`.
Units: SI throughout (m, s, kg, Pa); fitted coordinates are dimensionless.
"""
from __future__ import annotations

from jaxfoam import FIT_FIELDS as FIT_FIELDS

from . import io as io, optim as optim, silhouette as silhouette, synth as synth, track as track
from . import design as design, horizon as horizon
from .check import (combine_intervals as combine_intervals, correlation_area as correlation_area,
                    discretization_error as discretization_error, fit_uncertainty as fit_uncertainty)
from .design import DesignResult as DesignResult
from .driver import (calibrate as calibrate, default_log_path as default_log_path,
                     judge_reported_intervals as judge_reported_intervals, make_starts as make_starts,
                     silhouette_mismatch as silhouette_mismatch)
from .io import (Camera as Camera, SilhouetteFormatError as SilhouetteFormatError, Silhouettes as Silhouettes,
                 read_silhouettes as read_silhouettes, write_silhouettes as write_silhouettes)
from .plots import plot_loss as plot_loss, plot_overlay as plot_overlay
from .problem import (CalibrationProblem as CalibrationProblem, build_problem as build_problem,
                      fit_transform as fit_transform, fitted_occupancy as fitted_occupancy)
from .result import FitResult as FitResult
from .settings import (DEFAULT_BOUNDS as DEFAULT_BOUNDS, NUISANCE_FIELDS as NUISANCE_FIELDS,
                       CalibrationError as CalibrationError, FitSettings as FitSettings)
from .synth import synthesize as synthesize
from .track import track_video as track_video

__all__ = [
    "Camera", "CalibrationError", "CalibrationProblem", "DEFAULT_BOUNDS", "DesignResult", "FIT_FIELDS", "FitResult", "FitSettings", "NUISANCE_FIELDS",
    "SilhouetteFormatError", "Silhouettes", "build_problem", "calibrate", "combine_intervals", "correlation_area",
    "default_log_path", "design", "horizon", "discretization_error", "fit_transform", "fit_uncertainty", "fitted_occupancy", "io",
    "judge_reported_intervals", "make_starts", "optim", "plot_loss", "plot_overlay", "read_silhouettes",
    "silhouette", "silhouette_mismatch", "synth", "synthesize", "track", "track_video", "write_silhouettes",
]


def __getattr__(name):
    # The optimizers lived at the package's top level before `fitting.optim`; kept for one release.
    if name in optim.__all__:
        import warnings
        warnings.warn(f"fitting.{name} is deprecated: use fitting.optim.{name}", DeprecationWarning, stacklevel=2)
        return getattr(optim, name)
    raise AttributeError(f"module 'fitting' has no attribute {name!r}")
