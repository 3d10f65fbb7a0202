"""Shared plumbing of the experiment scripts: command line, output files, timing, rollouts, rasters.

Every experiment writes its chart (PNG) and table (markdown) to experiments/results/<name>.png/.md.
SI units throughout (m, s, kg, Pa).
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # float64 cases and fits; jaxfoam leaves the config alone
import jax.numpy as jnp
import numpy as np

import jaxfoam
from jaxfoam.guards import atomic_output

# JAXFOAM_RESULTS_DIR redirects the charts and tables (the test suite's quick runs keep the committed ones).
RESULTS = Path(os.environ.get("JAXFOAM_RESULTS_DIR") or Path(__file__).resolve().parent / "results")


def parse_args(doc: str, argv=None) -> argparse.Namespace:
    """The common command line: `--quick` selects the reduced version."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced version (minutes on 2 cores)")
    return parser.parse_args(argv)


def out_path(name: str, suffix: str, quick: bool) -> Path:
    """experiments/results/<name>[_quick].<suffix>: quick runs never overwrite the full results."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    return RESULTS / f"{name}{'_quick' if quick else ''}.{suffix}"


def machine_line() -> str:
    """One line naming the machine the numbers were measured on."""
    return (f"Measured on {platform.machine()} with {os.cpu_count()} CPU cores (shared), "
            f"JAX {jax.__version__}, {time.strftime('%Y-%m-%d')}.")


def md_table(header: list[str], rows: list[list]) -> str:
    """A markdown table; floats are written with 4 significant digits."""
    def fmt(v):
        if isinstance(v, (float, np.floating)):
            if not math.isfinite(v):
                return str(v)
            return f"{v:.4g}"
        return str(v)
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def write_md(name: str, quick: bool, title: str, body: str, command: str | None = None,
             stamp: str | None = None) -> Path:
    """Write results/<name>[_quick].md (atomically). command: the experiment and flags that regenerate it,
    when they differ from `name` (a partial study written under its own name). stamp: the measurement's
    `machine_line`, for a page rebuilt from a record (default: now)."""
    path = out_path(name, "md", quick)
    mode = "quick" if quick else "full"
    text = (f"# {title}\n\n_{mode} run; regenerate with `python -m experiments {command or name}"
            f"{' --quick' if quick else ''}`. {stamp or machine_line()}_\n\n{body}")
    with atomic_output(path) as tmp:
        Path(tmp).write_text(text)
    print(f"wrote {path}")
    return path


def save_fig(fig, name: str, quick: bool) -> Path:
    path = out_path(name, "png", quick)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    print(f"wrote {path}")
    return path


def orders(h, err) -> list:
    """Observed orders of convergence log(e_i / e_{i+1}) / log(h_i / h_{i+1}) between successive resolutions."""
    h, err = np.asarray(h, float), np.asarray(err, float)
    out = [float("nan")]
    for i in range(1, len(h)):
        ok = err[i] > 0 and err[i - 1] > 0
        out.append(float(np.log(err[i - 1] / err[i]) / np.log(h[i - 1] / h[i])) if ok else float("nan"))
    return out


class Timer:
    """Context manager measuring wall seconds (attribute `seconds`)."""

    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0


def rollout(state0, params, scene, dt, *, grid, n_frames: int, substeps: int, observe):
    """Explicit MPM rollout with a fixed dt (s): returns (final state, frames pytree (n_frames, ...)).

    A plain scan over frames of `substeps` substeps of `jaxfoam.step`; dt, params, scene and state0
    are data, so the function can be vmapped over them (one compile for a sweep). observe(state, params)
    -> pytree picked every frame.
    """
    model = jaxfoam.Model(scene=scene, dt=dt, dt_cfl=dt, grid=grid)

    def frame(state, _):
        def sub(s, _):
            return jaxfoam.step(model, s, params), None
        state, _ = jax.lax.scan(sub, state, None, length=substeps)
        return state, observe(state, params)

    return jax.lax.scan(frame, state0, None, length=n_frames)


def stack_trees(trees):
    """Stack a list of pytrees of the same structure along a new leading axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *trees)


def rasterize(x, active, lo, hi, pixel, radius):
    """Occupancy image of particles: pixel centres within `radius` (m) of an active particle.

    x: (N, 2) positions, m (projected to the image plane); lo, hi: (2,) image window, m; pixel: size, m.
    Returns a bool array (rows along y from the bottom, columns along x).
    """
    x = np.asarray(x)[np.asarray(active)]
    nx = int(round((hi[0] - lo[0]) / pixel))
    ny = int(round((hi[1] - lo[1]) / pixel))
    img = np.zeros((ny, nx), bool)
    r = int(math.ceil(radius / pixel))
    ij = np.floor((x - np.asarray(lo)[None, :]) / pixel).astype(int)
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            cx = lo[0] + (ij[:, 0] + dj + 0.5) * pixel
            cy = lo[1] + (ij[:, 1] + di + 0.5) * pixel
            near = (cx - x[:, 0]) ** 2 + (cy - x[:, 1]) ** 2 <= radius ** 2
            j, i = ij[:, 0] + dj, ij[:, 1] + di
            ok = near & (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
            img[i[ok], j[ok]] = True
    return img


def iou(a, b) -> float:
    """Intersection over union of two boolean images (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)
