"""Uncertainty and the discretization check: Gauss-Newton intervals widened by the grid's error."""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax.numpy as jnp
import numpy as np

from . import optim

from .silhouette import BSPLINE_SUPPORT
from .settings import (CORRELATION_WINDOW_SUPPORTS, DEFAULT_LEVEL, DX_CHECK_ORDER, DX_CHECK_RATIO, FTOL, GCI_SAFETY, XTOL,
                       FitSettings)
from .result import _format_params
from .problem import CalibrationProblem, build_problem
from .track import label_components


def correlation_area(images: np.ndarray, window: int) -> float:
    """Effective area, in pixels, over which residual pixels are correlated.

    The residual images (F, H, W) are pooled into one autocovariance C(lag) (zero-padded FFT); the
    area is the sum of the positive part of C(lag) / C(0) over lags |lag_x|, |lag_y| <= window (the
    reach of the rendering kernel: a soft silhouette cannot vary on shorter scales, so pixels within
    it share their errors). At least 1 (independent pixels). 1 for an all-zero residual.
    """
    imgs = np.asarray(images, np.float64)
    F, H, W = imgs.shape
    shape = (2 * H, 2 * W)
    spec = np.fft.rfft2(imgs, s=shape)
    acov = np.fft.irfft2(np.sum(np.abs(spec) ** 2, axis=0), s=shape)
    c0 = acov[0, 0]
    if not c0 > 0:
        return 1.0
    w = int(max(0, window))
    rows = np.r_[0:min(w + 1, H), shape[0] - np.arange(1, min(w, H - 1) + 1)]
    cols = np.r_[0:min(w + 1, W), shape[1] - np.arange(1, min(w, W - 1) + 1)]
    block = acov[np.ix_(rows, cols)] / c0
    return max(1.0, float(np.sum(np.maximum(block, 0.0))))


def fit_uncertainty(problem: CalibrationProblem, z, r=None, J=None, level: float = DEFAULT_LEVEL):
    """Gauss-Newton uncertainty at fitted coordinates z: (`fitting.optim.Uncertainty`, n_eff).

    Rows whose residual and Jacobian are exactly zero (pixels no simulated particle reaches and the data
    leave empty) are dropped; the remaining n residuals count as n / A independent ones, A the
    `correlation_area` of the pixel residuals.
    """
    if r is None or J is None:
        r, J = problem.residual_and_jacobian(z)
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return None, float("nan")
    keep = (r != 0) | np.any(J != 0, axis=1)
    n = int(keep.sum())
    p = J.shape[1]
    window = int(math.ceil(BSPLINE_SUPPORT * problem.cfg.kernel_width / problem.cfg.pixel_size *
                           CORRELATION_WINDOW_SUPPORTS))
    area = correlation_area(problem.pixel_images(r), window)
    n_eff = min(float(n), max(n / area, p + 1.0))
    if n <= p:
        return None, float("nan")
    unc = optim.gauss_newton_uncertainty(r[keep], J[keep], np.asarray(z, np.float64), problem.transform,
                                           n_eff=n_eff, level=level)
    return unc, n_eff


def discretization_error(problem: CalibrationProblem, z, J, ratio: float = DX_CHECK_RATIO, details=None, r=None,
                         refit: int = 0, progress: Callable[[str], None] | None = None):
    """The numerical error of an estimate z due to the fit's grid: (error_z (p,) >= 0, shift_z (p,)).

    The residual and its Jacobian at z are evaluated once more with grid spacing `ratio` dx (same
    observations, pixel level and seed). How far the estimate moves from dx to ratio dx is estimated to
    first order in two ways (`DX_CHECK_JACOBIAN`):
      * with the fit grid's Jacobian: -(Jp^T Jp)^+ Jp^T (rp_other - rp) over the pixel rows (the rows both
        grids share; Jp the pixel rows of J at dx);
      * with each grid's own: the difference of the two grids' Gauss-Newton steps from z,
        d = -(J^T J)^+ J^T r over all rows of that grid's residual, d_other - d.
    They agree where the residual is linear over the move; where they do not, the linearization is not
    to be trusted, and the check takes, per parameter, the larger move (shift_z: that one, with its sign).
    With refit > 0 a third, measured, move enters: that of `refit` Levenberg-Marquardt iterations on the
    finer grid from z (the fit's tolerances; the first reuses the residual and Jacobian computed there for
    the estimates). It includes what the fit had left to gain on its own grid, so it errs on the wide side.
    With theta(h) = theta_0 + C h^q (q = DX_CHECK_ORDER) the estimate at dx is off the continuum one by
    |shift| / |ratio^q - 1|; error_z is that times GCI_SAFETY. Returns infinite errors when the other
    grid's residual or Jacobian is not finite. r: the residual at z on the fit's grid, if at hand.
    details: a dict that receives "frame_change" (F,), the norm of each used frame's pixel-residual change
    between the two grids, and "shift_fit_jacobian", "shift_own_jacobians" (p,), the two estimates; with
    refit also "shift_refit" (p,), "refit_iterations", "refit_reason" and "refit_loss" (start, end).
    progress: callable(str) receiving one line per refit iteration, or None.
    """
    other = build_problem(problem.data, finer_settings(problem, problem.settings, ratio))
    p = np.shape(J)[1]
    at_z = {}
    with_fit, with_own, frame_change = predicted_move(problem, other, z, J, r, other_at_z=at_z)
    if details is not None:
        details["frame_change"] = frame_change
    if with_fit is None:
        return np.full(p, np.inf), np.full(p, np.nan)
    if details is not None:
        details["shift_fit_jacobian"], details["shift_own_jacobians"] = with_fit, with_own
    moves = [with_fit, with_own]
    if refit:
        measured = refit_move(other, z, int(refit), at_z=(at_z["r"], at_z["J"]), progress=progress)
        if details is not None:
            details.update(shift_refit=measured["move"], refit_iterations=measured["iterations"],
                           refit_reason=measured["reason"], refit_loss=measured["loss"])
        if not np.all(np.isfinite(measured["move"])):
            return np.full(p, np.inf), np.full(p, np.nan)
        moves.append(measured["move"])
    return check_error(moves, ratio)


def finer_settings(problem: CalibrationProblem, settings: FitSettings, ratio: float = DX_CHECK_RATIO) -> FitSettings:
    """`settings` on the grid check's finer grid for `problem`: dx `ratio` times problem's, same pixel level."""
    return dataclasses.replace(settings, dx=problem.dx * ratio, pixel_level=problem.pixel_level)


def check_error(moves, ratio: float = DX_CHECK_RATIO):
    """The discretization check's (error_z (p,), shift_z (p,)) from its moves between dx and ratio dx (k, p),
    fitted coordinates: per parameter the largest move (with its sign), extrapolated to the continuum at
    order DX_CHECK_ORDER and times GCI_SAFETY."""
    moves = np.asarray(moves, np.float64)
    shift = moves[np.argmax(np.abs(moves), axis=0), np.arange(moves.shape[1])]
    return GCI_SAFETY * np.abs(shift) / abs(ratio ** DX_CHECK_ORDER - 1.0), shift


def numerical_half_width(transform: optim.ParameterTransform, z, error_z) -> np.ndarray:
    """The numerical error error_z (half-widths in fitted coordinates around z) as half-widths in physical
    units, (p,): half the distance between theta(z - error_z) and theta(z + error_z) (the maps are not linear)."""
    z, e = np.asarray(z, np.float64), np.asarray(error_z, np.float64)
    up = np.asarray(transform.to_physical(jnp.asarray(z + e)))
    down = np.asarray(transform.to_physical(jnp.asarray(z - e)))
    return 0.5 * np.abs(up - down)


def refit_move(other: CalibrationProblem, z, iterations: int, at_z=None,
               progress: Callable[[str], None] | None = None) -> dict:
    """How far `iterations` Levenberg-Marquardt iterations on `other` (another discretization of the same
    data) move the estimate from z (fitted coordinates): dict(move (p,), iterations, reason, loss (start,
    end)). at_z: (r, J) of `other` at z if already computed (spares the first evaluation)."""
    z = np.asarray(z, np.float64)
    start = None if at_z is None else tuple(np.asarray(a) for a in at_z)

    def evaluate(x):
        if start is not None and np.array_equal(np.asarray(x, np.float64), z):
            return start
        return other.residual_and_jacobian(x)

    def said(info: optim.IterationInfo):
        if progress is not None:
            progress(f"[dx check refit] iter {info.iteration:>3}  loss {info.loss:.6g}  "
                     f"{_format_params(other.params_of(info.x), other.transform.names)}  ({info.time:.1f} s)")

    sol = optim.least_squares(evaluate, z, optim.LevenbergMarquardt(), with_jac=True, max_iterations=iterations,
                                ftol=FTOL, xtol=XTOL, callback=said)
    losses = np.asarray(sol.history.loss, np.float64)
    return dict(move=np.asarray(sol.x, np.float64) - z, iterations=int(sol.iterations), reason=sol.reason.value,
                loss=(float(losses[0]) if len(losses) else math.nan, float(sol.loss)))


def predicted_move(problem: CalibrationProblem, other: CalibrationProblem, z, J, r=None, other_at_z=None):
    """First-order estimates of how far the estimate z moves from `problem`'s discretization to `other`'s
    (the same observations and pixel level; another grid): (with the fit grid's Jacobian, with each grid's
    own, per-frame norm of the pixel-residual change (F,)), the first two (p,) in fitted coordinates, or
    None where a residual or Jacobian is not finite (`discretization_error` has the two formulas). J, r:
    the Jacobian and residual at z on `problem`'s grid (r computed if None). other_at_z: a dict that
    receives "r" and "J", `other`'s residual and Jacobian at z."""
    F = len(problem.frames)
    npix = problem.cfg.height * problem.cfg.width
    J = np.asarray(J, np.float64)
    p = J.shape[1]
    r = np.asarray(problem.residual(z) if r is None else r, np.float64)
    ro, Jo = (np.asarray(a, np.float64) for a in other.residual_and_jacobian(z))
    if other_at_z is not None:
        other_at_z.update(r=ro, J=Jo)
    rp, rc = r.reshape(F, -1)[:, :npix], ro.reshape(F, -1)[:, :npix]
    frame_change = np.sqrt(np.sum(np.square(rc - rp), axis=1))
    if not all(np.all(np.isfinite(a)) for a in (ro, Jo, r, J)):
        return None, None, frame_change
    Jp = J.reshape(F, -1, p)[:, :npix].reshape(-1, p)
    with_fit = np.linalg.lstsq(Jp, -(rc - rp).ravel(), rcond=None)[0]
    with_own = np.linalg.lstsq(Jo, -ro, rcond=None)[0] - np.linalg.lstsq(J, -r, rcond=None)[0]
    return with_fit, with_own, frame_change


# A frame whose pixel residual changes between the two grids by more than this times the median frame's
# is named in a note (docs/calibrate.md, "The defaults and why"); it changes no result.
UNEVEN_FRAME_RATIO = 1.5


def uneven_frames_note(times, change, dx: float) -> str | None:
    """A note naming the frames (times s) whose residual change between the two grids of the
    discretization check (`change`, per frame) exceeds UNEVEN_FRAME_RATIO times the median frame's, with a
    suggested --time-window when they are the last frames; None when no frame does."""
    change = np.asarray(change, np.float64)
    if change.size < 3 or not np.all(np.isfinite(change)):
        return None
    med = float(np.median(change))
    if not med > 0:
        return None
    ratio = change / med
    bad = np.nonzero(ratio > UNEVEN_FRAME_RATIO)[0]
    if len(bad) == 0:
        return None
    at = ", ".join(f"{times[i]:.3g}" for i in bad)
    note = (f"The dx = {dx:.3g} m grid resolves some frames worse than the rest: between dx and "
            f"{DX_CHECK_RATIO:.3g} dx the residual of the frames at t = {at} s changes {ratio[bad].min():.2g}-"
            f"{ratio[bad].max():.2g}x as much as the median frame's. If the foam stretches, tears or spreads over a "
            f"rough floor there, the grid biases the parameters through them")
    first = int(bad[0])
    if first > 0 and list(bad) == list(range(first, len(change))):
        note += f"; a fit without them (--time-window 0:{times[first - 1]:.4g}) is less biased by it"
    return note + " (docs/calibrate.md)."


# A piece of an observed silhouette counts when it holds at least this fraction of the frame's foam
# pixels (and 4 pixels): tracking speckle and plate-edge slivers do not split the foam.
PIECE_FRACTION = 0.02


def count_pieces(mask) -> int:
    """Number of 4-connected pieces of a boolean image (H, W) holding at least PIECE_FRACTION of its pixels."""
    mask = np.asarray(mask, bool)
    total = int(mask.sum())
    if total == 0:
        return 0
    _, sizes = label_components(mask, connectivity=4)
    return int(np.sum(sizes >= max(4, PIECE_FRACTION * total)))


def separation_note(times, masks, weights) -> str | None:
    """A note when the observed foam splits into more pieces than it starts with (a tear, a pinch-off),
    naming the first such frame and the --time-window that ends before it; None when it never splits.

    times (F,) s, masks and weights (F, H, W) of the frames fitted. A neck that thins to a few cells
    separates when the grid decides, so the frames after it bias the parameters."""
    obs = (np.asarray(masks, np.float64) >= 0.5) & (np.asarray(weights) > 0)
    counts = [count_pieces(m) for m in obs]
    if len(counts) < 2 or counts[0] == 0:
        return None
    split = next((k for k in range(1, len(counts)) if counts[k] > counts[0]), None)
    if split is None:
        return None
    note = (f"The observed foam splits at t = {times[split]:.3g} s ({counts[0]} piece(s) before, {counts[split]} "
            f"then). An MPM grid decides when a thinning neck separates, so the time of the split, and every frame "
            f"after it, changes with dx")
    if split >= 2:
        note += f"; a fit of the frames before it (--time-window 0:{times[split - 1]:.4g}) is less biased by it"
    return note + " (docs/calibrate.md)."


def combine_intervals(unc: optim.Uncertainty, error_z, transform: optim.ParameterTransform) -> np.ndarray:
    """(p, 2) physical intervals whose half-width in fitted coordinates is the statistical half-width
    and the numerical error combined in quadrature."""
    z = np.asarray(unc.z, np.float64)
    half_stat = 0.5 * (unc.interval_z[:, 1] - unc.interval_z[:, 0])
    half = np.sqrt(np.square(half_stat) + np.square(np.asarray(error_z, np.float64)))
    with np.errstate(invalid="ignore"):
        ends = np.stack([np.asarray(transform.to_physical(z - half)), np.asarray(transform.to_physical(z + half))], 1)
    return np.sort(ends, axis=1)


# Beyond this factor on the fit's time a finer grid is not suggested (hours become days).
MAX_SUGGESTED_COST = 1000.0


def grid_limit_note(names, error_z, half_stat_z, dx: float, dim: int, fit_seconds: float) -> str | None:
    """The note that says when the grid, not the data, limits the answer, and what to do.

    error_z, half_stat_z: per parameter the numerical error and the statistical half-width, in fitted
    coordinates. For the parameters whose error exceeds their half-width, the dx at which a first-order
    error falls to the half-width (dx / worst ratio) and its cost, the ratio^(d+1) (particles ~ dx^-d,
    substeps ~ dx^-1) times `fit_seconds` (s). None when the data limit every parameter.
    """
    ratios = {n: float(e) / float(h) for n, e, h in zip(names, error_z, half_stat_z)
              if np.isfinite(e) and np.isfinite(h) and h > 0 and e > h}
    if not ratios:
        return None
    worst = max(ratios.values())
    listed = ", ".join(f"{n} ({r:.2g}x)" for n, r in ratios.items())
    cost = worst ** (dim + 1)
    text = (f"The grid, not the data, limits {', '.join(ratios)}: the dx = {dx:.3g} m grid's numerical error exceeds "
            f"the statistical half-width ({listed}). ")
    if cost <= MAX_SUGGESTED_COST:
        text += (f"At first order, --dx {dx / worst:.3g} would bring it to the data's level, at about {cost:.3g}x this "
                 f"fit's time (about {cost * fit_seconds / 60:.3g} min); a recording that constrains these parameters "
                 f"more does not need a finer grid.")
    else:
        text += (f"A grid fine enough (--dx {dx / worst:.3g} at first order) would cost over {MAX_SUGGESTED_COST:g}x "
                 f"this fit's time; fit a recording that constrains these parameters more instead.")
    return text

