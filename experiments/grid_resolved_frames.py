"""Which frames the fit grid resolves: the grid's own refinement against the misfit to the reference data.

For every 2D file of `experiments/reference/data/` (the independent reference simulator's silhouettes), at
the file's true parameters, per observed frame: the mean boundary displacement (`fitting.silhouette_mismatch`,
in particle spacings of the fit grid) between the fit grid's silhouette and that of the discretization
check's grid (dx / sqrt(2), as `FitSettings.dx_check` uses; `fitting.horizon.grid_displacement`), beside the displacement between the fit grid's
silhouette and the data. Where the first exceeds FRAME_BOUNDARY_SPACINGS the grid does not resolve the frame
(at these parameters), and the table gives the first such frame, the misfit before and from it, and the
share of the loss at the truth that the frames from it hold. No data enter the grid-to-grid column: it is
what a fit can compute by itself.

Usage: python -m experiments grid_resolved_frames [--quick]   (quick: the hanging-plate files only)
Writes experiments/results/grid_resolved_frames[_quick].md and .json. SI units.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import jax
import numpy as np

from experiments import _common as C
from fitting import FitSettings, build_problem, read_silhouettes, silhouette_mismatch
from fitting.check import finer_settings
from fitting.horizon import grid_displacement, resolved_count
from fitting.settings import FIT_PPC, FRAME_BOUNDARY_SPACINGS
from fitting.silhouette import particle_spacing
from jaxfoam.guards import atomic_output

DATA = Path(__file__).resolve().parent / "reference" / "data"
NAME = "grid_resolved_frames"


def frame_rows(path: Path) -> dict:
    """Per-frame grid-to-grid and grid-to-data boundary displacements (particle spacings) and frame losses at the truth."""
    data = read_silhouettes(path)
    settings = FitSettings(starts=1, dx_check=False)
    coarse = build_problem(data, settings)
    fine = build_problem(data, finer_settings(coarse, settings))
    truth = {n: float(data.truth[n]) for n in coarse.transform.names}
    spacing = particle_spacing(coarse.dx, FIT_PPC[coarse.scene.dim], coarse.scene.dim)
    grid = grid_displacement(coarse, fine, truth)
    _, misfit = silhouette_mismatch(np.asarray(coarse.render(truth)), coarse.masks, coarse.weights,
                                    coarse.cfg.pixel_size)
    r = np.asarray(coarse.residual(coarse.transform.to_unconstrained(truth)))
    loss = 0.5 * np.sum(r.reshape(len(coarse.observed), -1) ** 2, axis=1)
    return dict(file=path.name, dx=float(coarse.dx), spacing=float(spacing),
                times=[float(data.times[i]) for i in coarse.frames],
                grid=grid.tolist(), misfit=(misfit / spacing).tolist(), loss=loss.tolist())


def summary_row(rec: dict) -> list:
    grid, misfit, loss = (np.asarray(rec[k]) for k in ("grid", "misfit", "loss"))
    first = resolved_count(grid, min_frames=0)
    before = float(np.mean(misfit[:first])) if first else float("nan")
    after = float(np.mean(misfit[first:])) if first < len(grid) else float("nan")
    share = float(np.sum(loss[first:]) / np.sum(loss))
    corr = float(np.corrcoef(grid, misfit)[0, 1])
    t_first = f"{rec['times'][first]:.3g}" if first < len(grid) else "none"
    return [rec["file"], rec["dx"] * 1e3, len(grid), f"{first} ({t_first})", before, after, share, corr]


def page(rows: list[dict], quick: bool) -> None:
    head = ["file", "dx (mm)", "frames", "first unresolved frame (t s)", "misfit before (spacings)",
            "misfit from it (spacings)", "share of the loss at the truth from it", "corr(grid, misfit)"]
    body = (f"At the true parameters, on the fit's default grid; a frame is unresolved when its silhouette and the "
            f"dx / sqrt(2) grid's are more than {FRAME_BOUNDARY_SPACINGS:g} particle spacing apart (mean boundary "
            f"displacement). Misfit: the same displacement between the fit grid's silhouette and the data.\n\n"
            + C.md_table(head, [summary_row(r) for r in rows])
            + "\n## Per frame (particle spacings): grid to grid / grid to data\n\n")
    for r in rows:
        cells = [f"{g:.2f} / {m:.2f}" for g, m in zip(r["grid"], r["misfit"])]
        body += f"- {r['file']}: " + ", ".join(cells) + "\n"
    C.write_md(NAME, quick, "Which frames the fit grid resolves, at the truth", body)


def main(argv=None) -> int:
    args = C.parse_args(__doc__, sys.argv[1:] if argv is None else argv)
    jax.config.update("jax_enable_x64", True)
    files = sorted(p for p in DATA.glob("*_2d_*.h5") if not args.quick or "hanging_plate" in p.name)
    rows = []
    for path in files:
        print(f"{path.name} ...", flush=True)
        rows.append(frame_rows(path))
    with atomic_output(C.out_path(NAME, "json", args.quick)) as tmp:
        Path(tmp).write_text(json.dumps(dict(rows=rows, machine=C.machine_line()), indent=1))
    page(rows, args.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
