"""The result of a fit: values, intervals, correlations, notes, goodness of fit; JSON and report."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from . import optim

from jaxfoam.guards import atomic_output
from jaxfoam import FIT_FIELDS
from .settings import FRAME_BOUNDARY_SPACINGS, KNOWN_INPUTS


@dataclasses.dataclass(frozen=True)
class FitResult:
    """The outcome of `calibrate`.

    Attributes:
      params: every material parameter used, name -> value (mu Pa, sigma_y Pa, eta Pa s^m, m,
        kappa Pa, rho kg/m^3): fitted ones at the optimum, fixed and known ones as given.
      fitted: names of the fitted parameters.
      interval: fitted name -> (lo, hi), the `level` interval (physical units): the statistical
        (Gauss-Newton) half-width and the numerical error combined in quadrature, in fitted coordinates.
      interval_statistical: the Gauss-Newton interval alone (noise-like misfit only).
      numerical_error: fitted name -> estimated error of the estimate from the fit's discretization, as
        a half-width in physical units (GCI_SAFETY times the first-order extrapolated shift, mapped
        through the parameter's transform; 0 without dx_check).
      stderr: fitted name -> local standard error (physical units), statistical.
      correlation: (p, p) correlation matrix of the fitted parameters (order of `fitted`).
      identifiable: fitted name -> whether the data determine it.
      notes: plain-language identifiability findings.
      loss: 0.5 |r|^2 at the optimum (dimensionless): the lowest over every iterate of every start.
      loss_history: (K+1,) loss per iteration of the best start.
      time_history: (K+1,) wall time of each of those iterations, s since its start.
      runs: one dict per start: start and end parameters, loss, reason, iterations, evaluations, wall time.
      best_run: index of the start with the lowest loss.  best_iteration: its iteration with that loss
        (the last one, except for Adam, whose loss may rise again).
      reason: why the best start stopped.  iterations, evaluations: of the best start.
      settings: the `FitSettings` as a dict, plus the resolved dx, pixel level and substeps.
      data: summary of the data (frames, image size, pixel size, frames used).
      wall_time: seconds for the whole calibration: set-up, every start's optimizer time (summed over
        resumes, from the fit log) and the uncertainty.
      n_effective: effective number of independent residuals used for the intervals.
      uncertainty: the `fitting.optim.Uncertainty` (None when the Jacobian was not finite).
      residual: (n,) residual vector at the optimum (not written to JSON; `plot_overlay` uses it).
      frame_iou: per used frame, the IoU of the fitted silhouette (soft occupancy >= 1/2) with the
        observed mask over weighted pixels.  frame_boundary_error: per used frame, the mean distance
        between the two silhouettes' boundaries, m (`silhouette_mismatch`).  frame_boundary_limit: the
        largest admitted, m: FRAME_BOUNDARY_SPACINGS particle spacings. `reproduces_data` is False, and
        a note says so, when a frame exceeds it. The intervals assume a fit that reproduces the data, so
        `interval` is then each parameter's bounds (the data, as fitted, exclude nothing the bounds
        allow) and no parameter is identifiable; the interval computed at the optimum is kept in
        `interval_local`.
      interval_local: the combined interval at the optimum before the goodness-of-fit check (equal to
        `interval` when the fit reproduces the data).
      z: the optimum in fitted coordinates (`fitted` order): exact where a parameter on a bound rounds to the
        bound in `params` (`calibrate(..., start_z=result.z)` continues from it).
    """

    params: dict
    fitted: tuple
    interval: dict
    interval_statistical: dict
    numerical_error: dict
    stderr: dict
    correlation: np.ndarray
    identifiable: dict
    notes: tuple
    loss: float
    loss_history: np.ndarray
    time_history: np.ndarray
    runs: list
    best_run: int
    best_iteration: int
    reason: str
    iterations: int
    evaluations: int
    settings: dict
    data: dict
    wall_time: float
    n_effective: float
    uncertainty: optim.Uncertainty | None = None
    residual: np.ndarray | None = None
    frame_iou: tuple = ()
    frame_boundary_error: tuple = ()
    frame_boundary_limit: float = math.nan
    interval_local: dict | None = None
    z: np.ndarray | None = None

    @property
    def reproduces_data(self) -> bool:
        """Whether every used frame's fitted silhouette boundary lies within frame_boundary_limit of the
        observed one on average."""
        return bool(len(self.frame_boundary_error)) and max(self.frame_boundary_error) <= self.frame_boundary_limit

    def to_dict(self) -> dict:
        """JSON-able dict (infinite interval ends as "inf"/"-inf", undefined values as null)."""

        def clean(v):
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple, np.ndarray)):
                return [clean(x) for x in v]
            if isinstance(v, (np.floating, float)):
                v = float(v)
                return None if math.isnan(v) else (v if math.isfinite(v) else ("inf" if v > 0 else "-inf"))
            if isinstance(v, (np.integer,)):
                return int(v)
            if isinstance(v, np.bool_):
                return bool(v)
            return v

        return clean({
            "format": "jaxfoam-fit", "version": 1,
            "params": self.params, "fitted": list(self.fitted), "level": self.settings.get("level"),
            "interval": self.interval, "interval_statistical": self.interval_statistical,
            "interval_local": self.interval if self.interval_local is None else self.interval_local,
            "numerical_error": self.numerical_error, "stderr": self.stderr, "correlation": self.correlation,
            "identifiable": self.identifiable, "notes": list(self.notes), "loss": self.loss,
            "loss_history": self.loss_history, "time_history": self.time_history, "runs": self.runs,
            "best_run": self.best_run, "best_iteration": self.best_iteration, "reason": self.reason, "iterations": self.iterations,
            "evaluations": self.evaluations, "settings": self.settings, "data": self.data,
            "wall_time": self.wall_time, "n_effective": self.n_effective,
            "frame_iou": list(self.frame_iou), "frame_boundary_error": list(self.frame_boundary_error),
            "frame_boundary_limit": self.frame_boundary_limit, "reproduces_data": self.reproduces_data,
            "z": None if self.z is None else [float(v) for v in self.z],
        })

    def write(self, path) -> None:
        """Write `to_dict()` as JSON to `path`."""
        text = json.dumps(self.to_dict(), indent=2) + "\n"
        with atomic_output(path) as tmp:
            Path(tmp).write_text(text)

    def report(self) -> str:
        """A plain-text summary: values, intervals, correlations, notes."""
        pct = f"{100 * self.settings['level']:g}%"
        lines = [f"{'parameter':<10} {'value':>11}   {pct} interval{'':<14} statistical part    numerical error"]
        for n in FIT_FIELDS + KNOWN_INPUTS + tuple(n for n in self.fitted if n not in FIT_FIELDS):
            v = self.params[n]
            if n in self.fitted:
                lo, hi = self.interval[n]
                slo, shi = self.interval_statistical[n]
                lines.append(f"{n:<10} {v:>11.5g}   {f'[{lo:.4g}, {hi:.4g}]':<26} {f'[{slo:.4g}, {shi:.4g}]':<19} "
                             f"{self.numerical_error[n]:.3g}" + ("" if self.identifiable[n] else
                                                                 "  (not identifiable)"))
            else:
                lines.append(f"{n:<10} {v:>11.5g}   (fixed)" if n in FIT_FIELDS else
                             f"{n:<10} {v:>11.5g}   (known input)")
        if len(self.fitted) > 1:
            lines.append("correlation: " + "  ".join(
                f"{a}-{b} {self.correlation[i, j]:+.2f}" for i, a in enumerate(self.fitted)
                for j, b in enumerate(self.fitted) if i < j))
        lines.extend(self.notes)
        if len(self.frame_boundary_error):
            worst = max(self.frame_boundary_error)
            lines.append(f"goodness of fit per frame: mean boundary distance max {worst:.3g} m (limit "
                         f"{self.frame_boundary_limit:.3g} m = {FRAME_BOUNDARY_SPACINGS:g} particle spacing), silhouette "
                         f"IoU min {min(self.frame_iou):.3f}: the data are "
                         f"{'reproduced' if self.reproduces_data else 'NOT reproduced'}")
        lines.append(f"loss {self.loss:.5g} after {self.iterations} iterations ({self.reason}), best of "
                     f"{len(self.runs)} start(s); {self.wall_time:.1f} s wall")
        return "\n".join(lines)


def _format_params(d: dict, names) -> str:
    return "  ".join(f"{n}={d[n]:.4g}" for n in names)
