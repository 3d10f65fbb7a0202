"""Guards shared by the commands: run budgets, output paths, atomic writes, optional dependencies.

A run is refused before any work when its particle count or its substep count exceeds a stated budget
(`--max-particles`, `--max-substeps`), with the numbers and the option that overrides it; a legal but
suspicious value gives a `PlausibilityWarning`. Outputs are written to a temporary file in the
destination's directory and renamed into place, so a killed or concurrent run never leaves a truncated
file where a good one was; an output path that names an input, or a directory, is refused.
"""
from __future__ import annotations

import contextlib
import importlib.util
import math
import os
import tempfile
import warnings

import numpy as np

from ._scene import PlausibilityWarning, Scene

# Default budgets: far above the example scenes at their default grids, far below what fills a laptop's
# memory or runs for hours.
DEFAULT_MAX_PARTICLES = 1_000_000
DEFAULT_MAX_SUBSTEPS = 1_000_000  # substeps of one rollout (all frames)
# Above this many substeps per frame a time step is suspicious (a units slip in kappa or mu).
WARN_SUBSTEPS_PER_FRAME = 100_000
# Simulated spans above this are suspicious for a foam experiment (times in ms instead of s).
WARN_SPAN_S = 60.0
VIZ_HINT = "install the viz extra: pip install 'jaxfoam[viz]' (matplotlib, imageio, imageio-ffmpeg)"
EXPORT_HINT = ("install the export extra: pip install -e '.[export]' (or pip install 'jaxfoam[export]': "
               "scikit-image, plyfile)")


class BudgetError(ValueError):
    """A run over its particle or substep budget; the message gives the numbers and the override."""


def state_floats(d: int) -> int:
    """Floats per particle of the simulation state (x, v, C, F, bbar_e, vol0, mass, gamma_dot, active)."""
    return 2 * d + 2 * d * d + 9 + 4


def shape_volume(scene: Scene) -> float | None:
    """Volume (m^d) of the scene's primitive initial shape, None for 'first_mask'."""
    shape = scene.initial_shape
    if shape["type"] == "box":
        return float(np.prod(np.asarray(shape["max"], float) - np.asarray(shape["min"], float)))
    if shape["type"] == "ellipse":
        r = np.asarray(shape["radii"], float)
        return float((math.pi if scene.dim == 2 else 4.0 / 3.0 * math.pi) * np.prod(r))
    return None


def estimate_particles(scene: Scene, dx: float, ppc: int) -> int | None:
    """About how many particles sampling the initial shape at dx (m) with ppc per cell gives."""
    vol = shape_volume(scene)
    return None if vol is None else int(math.ceil(vol / dx ** scene.dim * ppc))


def _mib(nbytes: float) -> str:
    return f"{nbytes / 2 ** 30:.1f} GiB" if nbytes >= 2 ** 30 else f"{nbytes / 2 ** 20:.0f} MiB"


def check_particles(n: int, d: int, itemsize: int, max_particles: int, *, dx: float, ppc: int,
                    dx_option: str = "--dx", ppc_option: str = "--ppc", override: str = "--max-particles"):
    """Raise BudgetError when n particles exceed max_particles."""
    if n <= max_particles:
        return
    raise BudgetError(f"{dx_option} {dx:g} m with {ppc_option} {ppc} means about {n:,} particles (the particle state "
                      f"alone about {_mib(n * state_floats(d) * itemsize)}, the rollout several times that), over the "
                      f"budget of {max_particles:,}: use a coarser {dx_option} or fewer {ppc_option}, or pass "
                      f"{override} {n} to run it anyway")


def substeps_per_frame(scene: Scene, params, dx: float, cfl: float, frame_times, t0: float = 0.0) -> int:
    """Substeps per frame the simulator will take (its CFL rule, `jaxfoam._simulate.stable_dt`)."""
    from ._model import speed_bound, stable_dt

    times = np.asarray(frame_times, float).ravel()
    widest = float(np.max(np.diff(np.concatenate([[t0], times]))))
    dt = stable_dt(params, dx, speed_bound(scene), cfl)
    return max(1, int(math.ceil(widest / dt - 1e-9)))


def check_substeps(per_frame: int, frames: int, max_substeps: int, *, span: float, dt: float,
                   override: str = "--max-substeps", times_option: str = "--duration"):
    """Raise BudgetError when a rollout of `frames` frames of `per_frame` substeps exceeds the budget;
    warn when one frame takes more than WARN_SUBSTEPS_PER_FRAME substeps or the span looks like ms."""
    total = per_frame * frames
    hint = ""
    if span > WARN_SPAN_S:
        hint = (f"; {times_option} gives {span:g} s of simulated time: times are seconds (a time in "
                f"milliseconds must be divided by 1000)")
    if total > max_substeps:
        raise BudgetError(f"the run needs {total:,} substeps ({frames} frames x {per_frame:,} substeps of dt = "
                          f"{dt:.3g} s, the CFL time step of these parameters), over the budget of "
                          f"{max_substeps:,}{hint}; check kappa, mu and rho for a units slip (Pa, kg/m^3), or pass "
                          f"{override} {total} to run it anyway")
    if per_frame > WARN_SUBSTEPS_PER_FRAME:
        warnings.warn(f"{per_frame:,} substeps per frame (dt = {dt:.3g} s): a stiff material (kappa, mu in Pa?) "
                      f"makes a very short time step", PlausibilityWarning, stacklevel=2)
    elif hint:
        warnings.warn(hint[2:], PlausibilityWarning, stacklevel=2)


def check_dtype_range(values: dict, dtype_name: str, option_of=lambda k: k):
    """Raise ValueError when a value overflows (or a non-zero one vanishes) in the run's float dtype."""
    info = np.finfo(np.dtype(dtype_name))
    for k, v in values.items():
        v = float(v)
        if math.isfinite(v) and (abs(v) > float(info.max) or (v != 0 and abs(v) < float(info.tiny))):
            raise ValueError(f"{option_of(k)} = {v:g} is outside the range of {dtype_name} "
                             f"(magnitudes {info.tiny:.3g} to {info.max:.3g}); use --dtype float64 or check the units")


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_output(path, option: str = "--out", inputs: dict | None = None) -> str:
    """Validate an output path before any work; returns it as a str.

    Refuses a directory and a path that names one of `inputs` (option -> path); the parent directory is
    created when missing (the same rule for every command)."""
    out = os.fspath(path)
    if not out:
        raise ValueError(f"{option} must be a file path, got an empty string")
    if os.path.isdir(out):
        raise ValueError(f"{option} {out!r} is a directory; give a file path")
    for name, other in (inputs or {}).items():
        if other is not None and _same_file(out, os.fspath(other)):
            raise ValueError(f"{option} {out!r} is the same file as {name} {os.fspath(other)!r}: writing it would "
                             f"destroy the input; choose another output path")
    parent = os.path.dirname(os.path.abspath(out))
    try:
        os.makedirs(parent, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{option} {out!r}: cannot create its directory {parent!r} ({exc.strerror})") from exc
    if not os.access(parent, os.W_OK):
        raise ValueError(f"{option} {out!r}: directory {parent!r} is not writable")
    return out


def temporary_path(path) -> str:
    """A new, unique temporary file beside `path` (same directory, same suffix)."""
    out = os.fspath(path)
    folder, name = os.path.split(os.path.abspath(out))
    stem, suffix = os.path.splitext(name)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{stem}.partial-{os.getpid()}-", suffix=suffix, dir=folder)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would otherwise become the output's mode
    return tmp


def publish(tmp: str, path) -> None:
    """Move a finished temporary file into place (atomic on one file system)."""
    os.replace(tmp, os.fspath(path))


def discard(tmp: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(tmp)


@contextlib.contextmanager
def atomic_output(path):
    """`with atomic_output(out) as tmp: write(tmp)`: the file appears at `out` only when the block succeeds."""
    tmp = temporary_path(path)
    try:
        yield tmp
    except BaseException:
        discard(tmp)
        raise
    publish(tmp, path)


def missing_modules(*modules: str) -> list[str]:
    return [m for m in modules if importlib.util.find_spec(m) is None]


def require_extra(what: str, *modules: str, hint: str = VIZ_HINT) -> None:
    """Raise ImportError naming the extra (`hint`: VIZ_HINT or EXPORT_HINT) when any of `modules` is
    not installed."""
    missing = missing_modules(*modules)
    if missing:
        raise ImportError(f"{what} needs {', '.join(missing)}: {hint}")
