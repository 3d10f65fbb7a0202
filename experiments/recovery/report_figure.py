"""The recovery report's chart: LM errors with their intervals against the goals, fit against truth, and
the optimizers' loss against wall time on the same data."""
from __future__ import annotations

from experiments import _common as C
from experiments.recovery.cases import COMPARE, NAME
from experiments.recovery.scoring import GOALS


def save_chart(lm: list[dict], comp: list[dict], names, quick: bool) -> None:
    """Write results/recovery[_quick].png from the main table's LM fits and the optimizer comparison."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    ax = axes[0]
    for j, n in enumerate(names):
        for i, r in enumerate(lm):
            e = r["evaluation"][n]
            t = e["truth"]
            lo, hi = e["interval"]
            if e["kind"] == "rel":
                y, ylo, yhi = e["error"], lo / t - 1, hi / t - 1
            else:
                y, ylo, yhi = e["error"], lo - t, hi - t
            ylo, yhi = max(ylo, -2.0), min(yhi, 2.0)
            x = j + (i - (len(lm) - 1) / 2) * 0.8 / max(len(lm), 1)
            ax.errorbar([x], [y], yerr=[[max(y - ylo, 0.0)], [max(yhi - y, 0.0)]], fmt="o" if e["identifiable"] else "s",
                        color="C0" if e["inside"] else "C3", ms=4, capsize=2, lw=1)
        _, tol = GOALS[n]
        ax.fill_between([j - 0.45, j + 0.45], -tol, tol, color="0.85", zorder=0)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels([f"{n}\n({'rel' if GOALS[n][0] == 'rel' else 'abs'})" for n in names])
    ax.set_ylim(-1.5, 1.5)
    ax.set_ylabel("error (relative, or absolute for m) with 95% interval")
    ax.set_title("LM recovery: blue = truth inside, red = outside; grey = goal")
    ax = axes[1]
    for r in lm:
        for n in names:
            e = r["evaluation"][n]
            ax.scatter(e["truth"], e["value"], color=f"C{names.index(n)}", s=14)
    lim = [1e-1, 1e3]
    ax.plot(lim, lim, "k-", lw=0.6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("truth")
    ax.set_ylabel("fit")
    ax.set_title("fit vs truth (" + ", ".join(f"C{i}: {n}" for i, n in enumerate(names)) + ")", fontsize=9)
    ax = axes[2]
    styles = {"lm": "-", "lbfgs": "--", "adam": ":"}
    for r in comp:  # each optimizer's first start: the common initial guess
        h = r["histories"]["0"]
        colour = f"C{COMPARE[quick].index((r['scene'], r['set']))}"
        ax.semilogy(h["time"], h["loss"], styles[r["optimizer"]], color=colour,
                    label=f"{r['scene']} {r['set']} {r['optimizer']}")
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel("loss 0.5 |r|^2")
    ax.set_title("optimizers on the same data")
    if comp:
        ax.legend(fontsize=7)
    fig.tight_layout()
    C.save_fig(fig, NAME, quick)
    plt.close(fig)
