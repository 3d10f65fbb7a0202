"""Trajectory files: a simulation's frames, times, parameters and scene in one HDF5 file.

Layout (format "jaxfoam-trajectory", version 1; SI units everywhere):

```
/                 attrs: format = "jaxfoam-trajectory", format_version = 1, jaxfoam_version,
                         dim, dtype ("float32" | "float64"), dx (m), dt (s, substep), substeps (per frame),
                         ppc (particles per cell, -1 if unknown), complete (bool: all frames written),
                         created (ISO 8601 UTC), creator (free text, e.g. the command line),
                         jax_version, python_version, host
/times            float64 [T]            frame times, s (strictly increasing)
/frames/x         dtype   [T, N, d]      positions, m
/frames/v         dtype   [T, N, d]      velocities, m/s
/frames/gamma_dot dtype   [T, N]         Herschel-Bulkley plastic rate of the last substep, 1/s
/frames/s         dtype   [T, N]         deviatoric Kirchhoff stress magnitude ||mu dev(bbar_e)||, Pa
/frames/J         dtype   [T, N]         volume ratio det F
/frames/active    bool    [T, N]         slot holds a material point
/params           attrs: mu (Pa), kappa (Pa), sigma_y (Pa), eta (Pa s^m), m (1), rho (kg/m^3)
/scene            attrs: json (the scene description of shared/specs/silhouettes.md)
```

Each frame dataset carries a `units` attribute. Extra per-frame arrays (any (T, N, ...) entry of
the frames dict) are stored under /frames as well. Frames are appended one block at a time to a
temporary file beside the output, renamed into place when the writer closes: a run that fails part-way
(an exception) leaves a readable file with `complete = False`; a killed one leaves the output path as it
was (and its temporary `.NAME.partial-PID-*.h5`, marked incomplete); concurrent writers each publish
a whole file.
"""
from __future__ import annotations

import dataclasses
import datetime
import json
import os
import platform
import socket
import sys
from typing import Any, Mapping

import h5py
import jax
import numpy as np

from ._errors import JaxfoamError
from .guards import publish, temporary_path
from ._params import Params

FORMAT = "jaxfoam-trajectory"
FORMAT_VERSION = 1
PARAM_FIELDS = ("mu", "kappa", "sigma_y", "eta", "m", "rho")
PARAM_UNITS = {"mu": "Pa", "kappa": "Pa", "sigma_y": "Pa", "eta": "Pa s^m", "m": "1", "rho": "kg/m^3"}
FRAME_UNITS = {"x": "m", "v": "m/s", "gamma_dot": "1/s", "s": "Pa", "J": "1", "active": "bool"}
# Frames that every trajectory must hold (the renderer and the trackers read them).
REQUIRED_FRAMES = ("x", "active")
# gzip level 4: lossless, about as fast as level 1 on float data and within a few % of level 9's size.
GZIP_LEVEL = 4


class TrajectoryError(JaxfoamError, ValueError):
    """A file that is not a readable jaxfoam trajectory; the message names the file and the field."""


@dataclasses.dataclass(frozen=True)
class SavedTrajectory:
    """A trajectory read back from (or ready to be written to) a file.

    Attributes:
      frames: dict name -> array (T, N, ...): x (m), v (m/s), gamma_dot (1/s), s (Pa), J (1), active (bool).
      times: (T,) frame times, s.
      params: Params (Python floats).
      scene_json: the scene description, JSON text.
      dx: grid spacing, m.  dt: substep, s.  substeps: substeps per frame.
      ppc: particles per cell (None if unknown).  dtype: "float32" or "float64".
      version: jaxfoam version that wrote it.  complete: False if the run stopped early.
      created: dict of creation information (created, creator, jax_version, python_version, host).
    """

    frames: dict
    times: np.ndarray
    params: Params
    scene_json: str
    dx: float
    dt: float
    substeps: int
    ppc: int | None = None
    dtype: str = "float64"
    version: str = ""
    complete: bool = True
    created: dict = dataclasses.field(default_factory=dict)

    @property
    def scene(self):
        """The parsed Scene (`load_scene` of scene_json, in this trajectory's dtype)."""
        from ._scene import load_scene

        return load_scene(self.scene_json, dtype=np.dtype(self.dtype))

    @property
    def x(self) -> np.ndarray:
        """Positions (T, N, d), m."""
        return self.frames["x"]

    @property
    def dim(self) -> int:
        return int(self.frames["x"].shape[-1])

    @property
    def num_frames(self) -> int:
        return int(len(self.times))

    @property
    def num_particles(self) -> int:
        """Particle slots N (active or not)."""
        return int(self.frames["x"].shape[1])


def _now_utc() -> str:
    return datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0).isoformat()


def creation_info(creator: str | None = None) -> dict:
    """Creation metadata: time (ISO 8601 UTC), creator text (default: the command line), versions, host."""
    return dict(created=_now_utc(), creator=" ".join(sys.argv) if creator is None else str(creator),
                jax_version=jax.__version__, python_version=platform.python_version(),
                host=socket.gethostname())


def _params_dict(params: Params) -> dict:
    out = {}
    for k in PARAM_FIELDS:
        v = np.asarray(jax.device_get(getattr(params, k)))
        if v.size != 1:
            raise ValueError(f"save_trajectory: Params.{k} must be a scalar to be stored, got shape {v.shape}")
        out[k] = float(v.reshape(()))
    return out


def _scene_json(scene) -> str:
    if isinstance(scene, str):
        json.loads(scene)  # must parse
        return scene
    if isinstance(scene, Mapping):
        return json.dumps(scene)
    source = getattr(scene, "source", None)
    if isinstance(source, str):
        return source
    raise ValueError(f"save_trajectory: scene must be a Scene, a dict or JSON text, got {type(scene).__name__}")


def _as_parts(traj: Any) -> dict:
    """Normalize a Trajectory (from `simulate`), a SavedTrajectory or a mapping into a dict of parts."""
    if isinstance(traj, SavedTrajectory):
        return dict(frames=traj.frames, times=traj.times, params=traj.params, scene=traj.scene_json,
                    dx=traj.dx, dt=traj.dt, substeps=traj.substeps, ppc=traj.ppc, complete=traj.complete)
    if isinstance(traj, Mapping):
        missing = [k for k in ("frames", "times", "params", "scene", "dx", "dt", "substeps") if k not in traj]
        if missing:
            raise ValueError(f"save_trajectory: parts {missing} missing; a dict needs frames, times, params, "
                             "scene, dx (m), dt (s), substeps (and optionally ppc)")
        return dict(traj)
    # jaxfoam.Trajectory (duck-typed to avoid an import cycle with _simulate).
    try:
        return dict(frames=traj.frames, times=traj.times, params=traj.params, scene=traj.scene, dx=traj.dx,
                    dt=traj.dt, substeps=traj.substeps, ppc=getattr(traj, "ppc", None))
    except AttributeError as exc:
        raise ValueError(f"save_trajectory: expected a jaxfoam Trajectory, a SavedTrajectory or a dict of "
                         f"parts, got {type(traj).__name__}") from exc


class TrajectoryWriter:
    """Writes a trajectory file frame block by frame block (the CLI appends as the rollout proceeds).

    Usage: `with TrajectoryWriter(path, params, scene, dx, dt, substeps, dtype) as w: w.append(frames, times)`;
    the file is marked complete when the block exits without an exception (or `close(complete=True)`).
    """

    def __init__(self, path, params: Params, scene, dx: float, dt: float, substeps: int, dtype="float64",
                 ppc: int | None = None, creator: str | None = None, compression: str | None = "gzip"):
        dtype = np.dtype(dtype)
        if dtype not in (np.float32, np.float64):
            raise ValueError(f"save_trajectory: dtype must be float32 or float64, got {dtype}")
        for name, value in (("dx", dx), ("dt", dt)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"save_trajectory: {name} must be a positive finite number, got {value}")
        if int(substeps) < 1:
            raise ValueError(f"save_trajectory: substeps must be >= 1, got {substeps}")
        self.dtype = dtype
        self.path = os.fspath(path)
        self.compression = compression
        if os.path.isdir(self.path):
            raise ValueError(f"save_trajectory: {self.path!r} is a directory; give a file path")
        self._tmp = temporary_path(self.path)
        # Each writer has its own file, so HDF5's lock never blocks a concurrent run on the same output.
        self._file = h5py.File(self._tmp, "w")
        f = self._file
        f.attrs.update(dict(format=FORMAT, format_version=FORMAT_VERSION, jaxfoam_version=_version(),
                            dtype=dtype.name, dx=float(dx), dt=float(dt), substeps=int(substeps),
                            ppc=-1 if ppc is None else int(ppc), complete=False))
        f.attrs.update(creation_info(creator))
        pg = f.create_group("params")
        pg.attrs.update(_params_dict(params))
        pg.attrs["units"] = json.dumps(PARAM_UNITS)
        f.create_group("scene").attrs["json"] = _scene_json(scene)
        f.create_dataset("times", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(256,))
        f["times"].attrs["units"] = "s"
        f.create_group("frames")
        self._count = 0

    @property
    def num_frames(self) -> int:
        return self._count

    def append(self, frames: Mapping, times) -> None:
        """Append frames (dict of (k, N, ...) arrays) recorded at times (k,) s."""
        times = np.asarray(times, np.float64).reshape(-1)
        k = len(times)
        fg = self._file["frames"]
        frames = {name: np.asarray(jax.device_get(a)) for name, a in frames.items()}
        for name, a in frames.items():
            if a.ndim < 2 or a.shape[0] != k:
                raise ValueError(f"save_trajectory: frames['{name}'] must have shape (T={k}, N, ...), got {a.shape}")
        if self._count == 0:
            if "x" not in frames:
                raise ValueError("save_trajectory: frames must contain 'x' (positions, m)")
            frames.setdefault("active", np.ones(frames["x"].shape[:2], bool))
            self._file.attrs["dim"] = int(frames["x"].shape[-1])
            for name, a in frames.items():
                # Each field keeps its own dtype, so values read back identical.
                ds = fg.create_dataset(name, shape=(0,) + a.shape[1:], maxshape=(None,) + a.shape[1:],
                                       dtype=a.dtype, chunks=(1,) + a.shape[1:], compression=self.compression,
                                       compression_opts=GZIP_LEVEL if self.compression == "gzip" else None)
                ds.attrs["units"] = FRAME_UNITS.get(name, "")
        else:
            if "active" not in frames and "x" in frames:
                frames["active"] = np.ones(frames["x"].shape[:2], bool)
            if set(frames) != set(fg):
                raise ValueError(f"save_trajectory: every block must hold the same fields {sorted(fg)}, "
                                 f"got {sorted(frames)}")
        prev = self._file["times"]
        if k and (np.any(np.diff(times) <= 0) or (self._count and times[0] <= prev[self._count - 1])):
            raise ValueError("save_trajectory: frame times must be strictly increasing")
        if not np.all(np.isfinite(times)):
            raise ValueError("save_trajectory: frame times must be finite")
        for name, a in frames.items():
            ds = fg[name]
            if a.shape[1:] != ds.shape[1:]:
                raise ValueError(f"save_trajectory: frames['{name}'] has per-frame shape {a.shape[1:]}, "
                                 f"the file holds {ds.shape[1:]}")
            ds.resize(self._count + k, axis=0)
            ds[self._count:] = a
        prev.resize(self._count + k, axis=0)
        prev[self._count:] = times
        self._count += k
        self._file.flush()

    def close(self, complete: bool = True) -> None:
        if self._file.id.valid:
            self._file.attrs["complete"] = bool(complete and self._count > 0)
            self._file.close()
            publish(self._tmp, self.path)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close(complete=exc_type is None)
        return False


def _version() -> str:
    from . import __version__

    return __version__


def save_trajectory(path, traj_or_parts, *, creator: str | None = None, compression: str | None = "gzip") -> str:
    """Write a trajectory to an HDF5 file (layout in this module's docstring); returns the path.

    Args:
      path: output file (overwritten).
      traj_or_parts: a `jaxfoam.Trajectory` (from `jaxfoam.simulate`), a `SavedTrajectory`, or a dict with
        frames (dict of (T, N, ...) arrays, at least x (m)), times ((T,) s), params (Params),
        scene (Scene, dict or JSON text), dx (m), dt (s), substeps, and optionally ppc.
      creator: free text stored as `creator` (default: the command line).
      compression: "gzip" (lossless) or None.
    Values are stored in the frames' float dtype (float32 or float64) and read back identical.
    """
    parts = _as_parts(traj_or_parts)
    frames = {k: np.asarray(jax.device_get(v)) for k, v in dict(parts["frames"]).items()}
    if "x" not in frames:
        raise ValueError("save_trajectory: frames must contain 'x' (positions, m)")
    dtype = frames["x"].dtype if frames["x"].dtype in (np.float32, np.float64) else np.float64
    writer = TrajectoryWriter(path, parts["params"], parts["scene"], parts["dx"], parts["dt"], parts["substeps"],
                              dtype=dtype, ppc=parts.get("ppc"), creator=creator, compression=compression)
    try:
        writer.append(frames, parts["times"])
    except BaseException:
        writer.close(complete=False)
        raise
    writer.close(complete=bool(parts.get("complete", True)))
    return os.fspath(path)


def load_trajectory(path) -> SavedTrajectory:
    """Read a trajectory file written by `save_trajectory` (or `jaxfoam simulate`).

    Raises FileNotFoundError for a missing file and TrajectoryError (a ValueError) naming the field for a
    file that is not HDF5, not a jaxfoam trajectory, of an unsupported format version, or inconsistent.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"trajectory file {path!r} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise TrajectoryError(f"{path!r} is not an HDF5 file (not a jaxfoam trajectory): {exc}") from exc

    def bad(msg):
        raise TrajectoryError(f"{path!r}: {msg}")

    with f:
        fmt = f.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        if fmt != FORMAT:
            bad(f"not a jaxfoam trajectory (root attribute 'format' is {fmt!r}, expected {FORMAT!r})")
        ver = int(f.attrs.get("format_version", -1))
        if ver != FORMAT_VERSION:
            bad(f"unsupported format_version {ver} (this jaxfoam reads version {FORMAT_VERSION})")
        for name in ("times", "frames", "params", "scene"):
            if name not in f:
                bad(f"missing '/{name}'")
        attrs = {k: f.attrs[k] for k in f.attrs}
        for k in ("dx", "dt", "substeps", "dtype"):
            if k not in attrs:
                bad(f"missing root attribute '{k}'")
        try:
            times = np.asarray(f["times"][()], np.float64)
            frames = {name: ds[()] for name, ds in f["frames"].items()}
        except (OSError, KeyError) as exc:
            bad(f"a dataset cannot be read (the file is damaged or truncated): {exc}")
        for name in REQUIRED_FRAMES:
            if name not in frames:
                bad(f"missing '/frames/{name}'")
        for name, a in frames.items():
            if a.ndim < 2 or a.shape[0] != len(times) or a.shape[1] != frames["x"].shape[1]:
                bad(f"'/frames/{name}' has shape {a.shape}, expected (T={len(times)}, N={frames['x'].shape[1]}, ...)")
        if frames["x"].ndim != 3 or frames["x"].shape[-1] not in (2, 3):
            bad(f"'/frames/x' must have shape (T, N, 2 or 3), got {frames['x'].shape}")
        active = np.asarray(frames["active"], bool)
        nonfinite = ~np.all(np.isfinite(frames["x"]), axis=-1) & (active if active.shape == frames["x"].shape[:2] else True)
        if nonfinite.any():
            t, i = np.argwhere(nonfinite)[0]
            bad(f"'/frames/x' holds non-finite positions ({int(nonfinite.sum())} values; first at frame {t}, "
                f"particle {i}): the positions must be finite numbers in m")
        if len(times) and (not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0)):
            bad("'/times' must be finite and strictly increasing")
        missing = [k for k in PARAM_FIELDS if k not in f["params"].attrs]
        if missing:
            bad(f"'/params' lacks attributes {missing}")
        params = Params(**{k: float(f["params"].attrs[k]) for k in PARAM_FIELDS})
        scene_json = f["scene"].attrs.get("json")
        if scene_json is None:
            bad("'/scene' lacks attribute 'json'")
        scene_json = scene_json.decode() if isinstance(scene_json, bytes) else str(scene_json)
        try:
            json.loads(scene_json)
        except json.JSONDecodeError as exc:
            bad(f"'/scene' json does not parse: {exc}")
        text = lambda k: (lambda v: v.decode() if isinstance(v, bytes) else str(v))(attrs.get(k, ""))
        ppc = int(attrs.get("ppc", -1))
        return SavedTrajectory(
            frames=frames, times=times, params=params, scene_json=scene_json, dx=float(attrs["dx"]),
            dt=float(attrs["dt"]), substeps=int(attrs["substeps"]), ppc=None if ppc < 1 else ppc,
            dtype=text("dtype"), version=text("jaxfoam_version"), complete=bool(attrs.get("complete", True)),
            created={k: text(k) for k in ("created", "creator", "jax_version", "python_version", "host")})


def as_saved_trajectory(traj) -> SavedTrajectory:
    """A SavedTrajectory from a path (read with `load_trajectory`), a SavedTrajectory (returned as is),
    a `jaxfoam.Trajectory` from `simulate`, or a dict of parts (see `save_trajectory`)."""
    if isinstance(traj, SavedTrajectory):
        return traj
    if isinstance(traj, (str, os.PathLike)):
        return load_trajectory(traj)
    parts = _as_parts(traj)
    frames = {k: np.asarray(jax.device_get(v)) for k, v in dict(parts["frames"]).items()}
    if "x" not in frames:
        raise ValueError("trajectory frames must contain 'x' (positions, m)")
    frames.setdefault("active", np.ones(frames["x"].shape[:2], bool))
    params = Params(**_params_dict(parts["params"]))
    return SavedTrajectory(frames=frames, times=np.asarray(parts["times"], np.float64), params=params,
                           scene_json=_scene_json(parts["scene"]), dx=float(parts["dx"]), dt=float(parts["dt"]),
                           substeps=int(parts["substeps"]), ppc=parts.get("ppc"), dtype=frames["x"].dtype.name,
                           version=_version(), complete=bool(parts.get("complete", True)))
