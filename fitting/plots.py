"""Pictures of a fit: the loss curve and observed against simulated silhouettes."""
from __future__ import annotations

import os

import numpy as np

from . import optim

from .result import FitResult
from .problem import CalibrationProblem, fitted_occupancy


def plot_loss(result: FitResult, path) -> None:
    """Loss against iteration for every start (the best one bold), log scale; PNG at `path`."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=110)
    log = result.settings.get("log")
    histories = {}
    if log and os.path.exists(log):
        for i, run in optim.read_fitlog(log)["runs"].items():
            histories[i] = np.asarray(run["loss"])
    if not histories:
        histories = {result.best_run: result.loss_history}
    for i, h in sorted(histories.items()):
        best = i == result.best_run
        ax.semilogy(np.arange(len(h)), np.maximum(h, 1e-300), "-o" if best else "-", lw=2 if best else 1,
                    ms=3, alpha=1 if best else 0.6, label=f"start {i + 1}" + (" (best)" if best else ""))
    ax.set_xlabel("iteration")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_ylabel("loss 0.5 |r|^2")
    ax.set_title(f"{result.settings['optimizer']} fit: loss per iteration")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_overlay(problem: CalibrationProblem, result: FitResult, path, n_panels: int = 4) -> None:
    """Observed masks (grey) with the simulated silhouette at the fitted parameters (red contour at
    occupancy 1/2) for up to `n_panels` frames spread over the fit; weight-0 pixels hatched blue."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    occ = fitted_occupancy(problem, result)
    F = occ.shape[0]
    picks = np.unique(np.round(np.linspace(0, F - 1, min(n_panels, F))).astype(int))
    H, W = problem.cfg.shape
    extent = problem.camera.extent((H, W))
    fig, axes = plt.subplots(1, len(picks), figsize=(3.0 * len(picks), 3.2), dpi=110, squeeze=False)
    xc, yc = problem.camera.pixel_centers((H, W))
    for ax, k in zip(axes[0], picks):
        ax.imshow(problem.masks[k], cmap="Greys", vmin=0, vmax=1.6, extent=extent, origin="upper",
                  interpolation="nearest")
        hidden = np.ma.masked_where(problem.weights[k] > 0, np.ones((H, W)))
        ax.imshow(hidden, cmap="Blues", vmin=0, vmax=2, alpha=0.5, extent=extent, origin="upper",
                  interpolation="nearest")
        ax.contour(xc, yc, occ[k], levels=[0.5], colors="red", linewidths=1.2)
        t = problem.data.times[problem.frames[k]]
        ax.set_title(f"t = {t:.3f} s", fontsize=9)
        ax.set_xlabel("x (m)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("y (m)", fontsize=8)
    fig.suptitle("observed (grey) vs simulated at the fit (red); blue: weight 0", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_design(result, path) -> None:
    """Predicted 95% half-widths over the tolerance (`fitting.design.TOLERANCE`) per parameter for every
    candidate of a `DesignResult`, best first (log scale; 1 is the tolerance); PNG at `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .design import TOLERANCE

    cands = result.candidates
    names = list(result.guess_names)
    k = len(cands)
    fig, ax = plt.subplots(figsize=(max(5.5, 0.45 * k * len(names) / 2 + 2), 3.8), dpi=110)
    width = 0.8 / len(names)
    x = np.arange(k)
    for j, n in enumerate(names):
        ratio = np.array([c["half_width"][n] / TOLERANCE[n] for c in cands], float)
        ratio = np.where(np.isfinite(ratio), ratio, np.nan)
        ax.bar(x + (j - (len(names) - 1) / 2) * width, ratio, width, label=n)
    ax.axhline(1.0, color="k", lw=1, ls="--", label="tolerance")
    ax.set_yscale("log")
    ax.set_xticks(x)
    ax.set_xticklabels([f"{i + 1}" for i in range(k)])
    ax.set_xlabel("candidate (rank; values in the design's JSON)")
    ax.set_ylabel("predicted half-width / tolerance")
    ax.set_title(f"jaxfoam design: {result.robust} over {len(result.points)} parameter points", fontsize=9)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=len(names) + 1)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    from jaxfoam.guards import atomic_output

    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
