"""The fit problem: a dataset bound to a simulator, a renderer and a parameter transform; the
residual and its forward-mode Jacobian."""
from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import json
import math

import jax
import jax.numpy as jnp
import numpy as np

from . import optim

from jaxfoam.guards import (DEFAULT_MAX_PARTICLES, DEFAULT_MAX_SUBSTEPS, check_dtype_range, check_particles,
                      check_substeps, estimate_particles, substeps_per_frame)
from jaxfoam import FIT_FIELDS, Params, Scene, Simulator, init_state, rollout
from jaxfoam.adjoint import DEFAULT_JACOBIAN, Autodiff, ForwardMode, threaded_columns
from .io import Camera, Silhouettes, plate_footprint
from .silhouette import (RenderConfig, make_render_config, make_target, particle_spacing,
                         pyramid, render_frames, residuals)
from .settings import (CalibrationError, FIT_CELLS, FIT_CFL, FIT_PPC, FitSettings, KNOWN_INPUTS,
                       MAX_FRAMES_PER_OBSERVED, MIN_DOMAIN_PIXELS, MIN_LEVEL_PIXELS)
from .result import FitResult


def observe_positions(state, params) -> dict:
    """Per-frame record of a fit: positions x (N, d) m and the active mask (N,)."""
    return dict(x=state.x, active=state.active)


@dataclasses.dataclass(frozen=True)
class _Static:
    """Hashable configuration of the residual (a static argument of the jitted functions)."""

    transform: optim.ParameterTransform
    cfg: RenderConfig
    distance_weight: float
    chamfer_weight: float
    observed: tuple = ()  # indices of the observed frames among the rollout's (`simulation_frames`)


def simulation_frames(t0: float, times, max_ratio: int = MAX_FRAMES_PER_OBSERVED) -> tuple[np.ndarray, np.ndarray]:
    """The frame times (s) a fit's rollout records, and where the observed `times` are among them.

    Each interval between t0 (s) and the observed times, in order, is split into equal parts no wider
    than h, the narrowest interval (or duration / (max_ratio * len(times)) where that is wider), so the
    substeps per frame, sized for the widest recorded interval, keep the CFL time step instead of
    shrinking it for every frame when the data have gaps. Returns (frame times (S,), indices (F,) of the
    observed times in them); without gaps they are `times` and arange(F)."""
    times = np.asarray(times, float)
    edges = np.concatenate([[float(t0)], times])
    widths = np.diff(edges)
    h = max(float(widths.min()), (edges[-1] - edges[0]) / (max_ratio * len(times)))
    parts = np.maximum(1, np.ceil(widths / h * (1.0 - 1e-9))).astype(int)
    out, idx = [], []
    for a, b, n in zip(edges[:-1], edges[1:], parts):
        out.extend(a + (b - a) * np.arange(1, n) / n)
        out.append(b)
        idx.append(len(out) - 1)
    return np.asarray(out), np.asarray(idx)


def _observed(frames: dict, static) -> tuple:
    """Positions and active flags of a rollout's frames at the observed times (`_Static.observed`)."""
    idx = np.asarray(static.observed)
    return frames["x"][idx], frames["active"][idx]


def _bind(z, static: _Static, base: Params, model):
    """(Params, Model) at fitted coordinates z: the material's parameters into `base`, the fitted scene
    parameters (`FitSettings.fit_also`) into the model's scene."""
    theta = static.transform.to_physical(z)
    values = {n: theta[i] for i, n in enumerate(static.transform.names)}
    params = base.replace(**{n: v for n, v in values.items() if n in FIT_FIELDS})
    if "friction" in values:
        model = model.replace(scene=dataclasses.replace(model.scene, floor_friction=values["friction"]))
    return params, model


def _residual(z, static: _Static, base: Params, model, state0, frame_times, target):
    params, model = _bind(z, static, base, model)
    _, frames, _ = rollout(model, state0, params, frame_times, observe=observe_positions, adjoint=Autodiff())
    x, active = _observed(frames, static)
    return residuals(x, active, target, static.cfg, distance=static.distance_weight,
                     chamfer_weight=static.chamfer_weight)


@functools.partial(jax.jit, static_argnames=("static",))
def _residual_jit(z, static, base, model, state0, frame_times, target):
    return _residual(z, static, base, model, state0, frame_times, target)


@functools.partial(jax.jit, static_argnames=("static",))
def _residual_and_jacobian(z, static, base, model, state0, frame_times, target):
    """(r (n,), dr/dz (n, p)) by forward mode: one jvp rollout per fitted parameter (p <= 4), in
    sequence by `lax.map` (one compiled rollout body; `jaxfoam.adjoint.DEFAULT_JACOBIAN`)."""

    def fn(zz):
        return _residual(zz, static, base, model, state0, frame_times, target)

    rs, cols = jax.lax.map(lambda e: jax.jvp(fn, (z,), (e,)), jnp.eye(z.shape[0], dtype=z.dtype))
    return rs[0], cols.T


@functools.partial(jax.jit, static_argnames=("static",))
def _residual_and_columns(z, basis, static, base, model, state0, frame_times, target):
    """r (n,) and the directional derivatives dr/dz . e (k, n) along the rows e of `basis` (k, p),
    one jvp rollout per row in sequence (`lax.map`); a zero row gives a zero column."""

    def fn(zz):
        return _residual(zz, static, base, model, state0, frame_times, target)

    rs, cols = jax.lax.map(lambda e: jax.jvp(fn, (z,), (e,)), basis)
    return rs[0], cols


@functools.partial(jax.jit, static_argnames=("static",))
def _residual_and_jacfwd(z, static, base, model, state0, frame_times, target):
    """(r (n,), dr/dz (n, p)) with every tangent through one rollout (`jax.jacfwd`, ForwardMode("vmap"))."""

    def fn(zz):
        r = _residual(zz, static, base, model, state0, frame_times, target)
        return r, r

    J, r = jax.jacfwd(fn, has_aux=True)(z)
    return r, J


def _folded(model):
    """The model with the batch-folding transfers (`Tuning.batch_fold`) where its tuning says so
    (`Tuning.fold_batches`: XLA:CPU): a vmapped rollout then scatters and gathers once over the
    batch's grids laid end to end."""
    return model.replace(tuning=model.tuning.replace(batch_fold=model.tuning.fold_batches))


def _batch_program(static, mesh, columns: bool):
    """The jit-compiled batch of residual rollouts (columns=False: Z (K, p) -> R (K, n)) or of jvp
    rollouts (columns=True: (Z, E) (K, p) each -> (R (K, n), dR/dz . E (K, n))), one `jax.vmap` over
    K; with a `jax.sharding.Mesh` of D > 1 devices, K (a multiple of D) is split over them by
    `jax.shard_map`, each device running its part as one vmapped program."""

    def run(*a, base, model, state0, frame_times, target):
        model = _folded(model)

        def fn(z):
            return _residual(z, static, base, model, state0, frame_times, target)

        if columns:
            return jax.vmap(lambda z, e: jax.jvp(fn, (z,), (e,)))(*a)
        return jax.vmap(fn)(*a)

    def program(batch, base, model, state0, frame_times, target):
        body = functools.partial(run, base=base, model=model, state0=state0, frame_times=frame_times, target=target)
        if mesh is None:
            return body(*batch)

        def part(*rows):
            # Every device (and process) gets the whole result: a process reads only what it holds.
            return jax.tree_util.tree_map(lambda a: jax.lax.all_gather(a, "batch", tiled=True), body(*rows))

        spec = jax.sharding.PartitionSpec("batch")
        return jax.shard_map(part, mesh=mesh, in_specs=(spec,) * len(batch), out_specs=jax.sharding.PartitionSpec(),
                             check_vma=False)(*batch)

    return jax.jit(program)


def batch_mesh(devices):
    """A 1-D `jax.sharding.Mesh` named "batch" over `devices` (a count of local devices, a list of
    devices, or None for all of `jax.devices()`); None when that is a single device."""
    if devices is None:
        devs = jax.devices()
    elif isinstance(devices, int):
        avail = jax.devices()
        if not 1 <= devices <= len(avail):
            raise CalibrationError(f"devices must be in [1, {len(avail)}] (the {jax.default_backend()} devices "
                                   f"of this process), got {devices}")
        devs = avail[:devices]
    else:
        devs = list(devices)
    return None if len(devs) <= 1 else jax.sharding.Mesh(np.asarray(devs), ("batch",))


@functools.partial(jax.jit, static_argnames=("static",))
def _positions(z, static, base, model, state0, frame_times):
    params, model = _bind(z, static, base, model)
    _, frames, health = rollout(model, state0, params, frame_times, observe=observe_positions, adjoint=Autodiff())
    return frames["x"], frames["active"], health


def _check_jacobian_adjoint(adjoint) -> None:
    if not isinstance(adjoint, ForwardMode):
        raise CalibrationError(f"adjoint: the fit's Jacobian is taken in forward mode, so it must be a "
                               f"jaxfoam.ForwardMode(tangents='map' | 'vmap', threads=...), got {adjoint!r}")


class CalibrationProblem:
    """A dataset bound to a simulator, a renderer and a parameter transform (built by `build_problem`).

    Attributes:
      data: the `Silhouettes`.  settings: the `FitSettings`.  scene: the parsed scene.
      sim: the `Simulator` at the fit's dx (frame times: the used data times, with unobserved frames
        filling the gaps, `simulation_frames`; `observed` says which are the data's).
      transform: `fitting.optim.ParameterTransform` of the fitted parameters.
      base: `Params` with the fixed and known values (fitted entries are placeholders).
      frames: (F,) indices into the data's frames that enter the residual.
      masks, weights, camera: observations at the chosen pyramid level.  cfg: its `RenderConfig`.
      pixel_level: that level.  dx: the fit's grid spacing, m.
      jacobian_adjoint: the Jacobian's route, a `jaxfoam.ForwardMode` (default DEFAULT_JACOBIAN);
      jacobian_threads: its concurrent column groups ("map" on the CPU backend).
    """

    def __init__(self, data: Silhouettes, settings: FitSettings, sim: Simulator, transform, base: Params,
                 frames: np.ndarray, level: int, masks, weights, camera: Camera, cfg: RenderConfig, target,
                 observed=None, adjoint=DEFAULT_JACOBIAN):
        _check_jacobian_adjoint(adjoint)
        self.data, self.settings, self.sim, self.scene = data, settings, sim, sim.scene
        self.transform, self.base, self.frames = transform, base, frames
        self.observed = np.arange(len(frames)) if observed is None else np.asarray(observed)
        self.pixel_level, self.masks, self.weights, self.camera, self.cfg = level, masks, weights, camera, cfg
        self.target = target
        self.dx = sim.dx
        self.static = _Static(transform=transform, cfg=cfg, distance_weight=float(settings.distance_weight),
                              chamfer_weight=float(settings.chamfer_weight),
                              observed=tuple(int(i) for i in self.observed))
        dt = sim.dtype
        self._times = jnp.asarray(sim.frame_times, dt)
        self._base = base.astype(dt)
        self.jacobian_adjoint = adjoint
        self.jacobian_threads = adjoint.resolve_threads(sim.model.tuning)
        self._columns_compiled = False
        self._batch = {}
        self.mesh = None

    def use_devices(self, devices) -> "CalibrationProblem":
        """Shard the batched evaluations (`residual_batch`, `residual_and_jacobian_batch`) over `devices`
        (a count of local devices, a device list, or None for all); returns self."""
        self.mesh = batch_mesh(devices)
        self._batch = {}
        return self

    @property
    def floor_phase(self) -> float | None:
        """Cells from the grid's node row below the floor up to the floor, in [0, 1); None without a floor."""
        if self.scene.floor_y is None:
            return None
        k = (float(self.scene.floor_y) - float(self.sim.model.grid.origin[1])) / self.dx
        return float(round(k - math.floor(k + 1e-9), 9)) % 1.0

    @property
    def devices(self) -> int:
        """The number of devices the batched evaluations are split over."""
        return 1 if self.mesh is None else int(self.mesh.size)

    def _run_batch(self, columns: bool, *batch):
        # Rows padded to a multiple of the devices by repeating the last one (its results are dropped).
        k = batch[0].shape[0]
        pad = -k % self.devices
        if pad:
            batch = tuple(jnp.concatenate([b, jnp.repeat(b[-1:], pad, axis=0)]) for b in batch)
        if columns not in self._batch:
            self._batch[columns] = _batch_program(self.static, self.mesh, columns)
        args = (batch, *self._args()[1:], self.target)
        if self.mesh is not None:
            # Host values are replicated inputs of a program over devices of several processes.
            args = jax.tree_util.tree_map(np.asarray, args)
        out = self._batch[columns](*args)
        return jax.tree_util.tree_map(lambda a: a[:k], out)

    def residual_batch(self, Z) -> jax.Array:
        """Residuals R (B, n) at B points Z (B, p) of fitted coordinates, as one batched program
        (equal to `residual` row by row, to round-off)."""
        Z = jnp.asarray(Z, self.sim.dtype)
        return self._run_batch(False, Z)

    def residual_and_jacobian_batch(self, Z):
        """(R (B, n), J (B, n, p)) at B points Z (B, p): the B p jvp rollouts (one per point and fitted
        parameter) as one batched program, sharded over `devices` (equal to `residual_and_jacobian`
        point by point, to round-off)."""
        Z = jnp.asarray(Z, self.sim.dtype)
        B, p = Z.shape
        rows = jnp.repeat(Z, p, axis=0)
        basis = jnp.tile(jnp.eye(p, dtype=Z.dtype), (B, 1))
        r, cols = self._run_batch(True, rows, basis)
        n = r.shape[1]
        return r[::p], jnp.swapaxes(cols.reshape(B, p, n), 1, 2)

    def _args(self):
        return (self.static, self._base, self.sim.model, self.sim.state0, self._times)

    def residual(self, z) -> jax.Array:
        """Residual vector r(z), (n,), dimensionless (see `silhouette.residuals`)."""
        return _residual_jit(jnp.asarray(z, self.sim.dtype), *self._args(), self.target)

    def residual_and_jacobian(self, z):
        """(r (n,), dr/dz (n, p)) by forward mode as `jacobian_adjoint` says: "map", one jvp rollout per
        fitted parameter with the columns in `jacobian_threads` concurrent groups
        (`jaxfoam.adjoint.threaded_columns`); "vmap", all tangents through one rollout."""
        z = jnp.asarray(z, self.sim.dtype)
        p = z.shape[0]
        if self.jacobian_adjoint.tangents == "vmap":
            return _residual_and_jacfwd(z, *self._args(), self.target)
        if min(int(self.jacobian_threads), p) <= 1:
            return _residual_and_jacobian(z, *self._args(), self.target)
        run = lambda basis: _residual_and_columns(z, jnp.asarray(basis), *self._args(), self.target)
        r, cols = threaded_columns(run, p, self.jacobian_threads, self.sim.dtype, self._columns_compiled)
        self._columns_compiled = True
        return r, cols.T

    def with_scene(self, scene) -> "CalibrationProblem":
        """A copy whose rollouts use `scene`'s differentiable data (plate motions, gravity, floor friction)
        with this problem's compiled programs, grid, substeps and initial state. `scene` must have this
        scene's structure (same plates, motion types and sample counts); ValueError otherwise."""
        model = self.sim.model
        old = (model.scene.gravity, model.scene.plates, model.scene.floor_friction)
        new = (scene.gravity, scene.plates, scene.floor_friction)
        shapes = lambda tree: jax.tree_util.tree_map(lambda a: (jnp.shape(a), jnp.result_type(a)), tree)
        if (jax.tree_util.tree_structure(old) != jax.tree_util.tree_structure(new)
                or shapes(old) != shapes(new)):
            raise ValueError("scene: its plates, motion types or sample counts differ from the problem's scene; "
                             "build a problem for it instead")
        out = copy.copy(self)
        out.sim = copy.copy(self.sim)
        out.sim.model = model.replace(scene=dataclasses.replace(model.scene, gravity=scene.gravity, plates=scene.plates,
                                                                floor_friction=scene.floor_friction))
        out.sim.scene = out.scene = out.sim.model.scene
        return out

    def with_observations(self, data: Silhouettes) -> "CalibrationProblem":
        """A copy that compares with `data` (same camera, image size and frame times as this problem's
        data) at this problem's pixel level and frames; copies made this way share one compiled residual
        (boundary points padded to `silhouette.MAX_BOUNDARY_POINTS` per frame)."""
        if (data.shape != self.data.shape or not np.array_equal(data.times, self.data.times)
                or data.camera.as_dict() != self.data.camera.as_dict()):
            raise ValueError("data: its camera, image size or frame times differ from the problem's data")
        out = copy.copy(self)
        out.data = data
        masks, weights, _ = pyramid(without_plate_pixels(data, self.scene), self.pixel_level + 1)[self.pixel_level]
        out.masks, out.weights = masks[self.frames], weights[self.frames]
        out.target = make_target(out.masks, out.weights, self.camera, dtype=self.sim.dtype, pad=True)
        return out

    def loss(self, z) -> float:
        r = np.asarray(self.residual(z))
        return 0.5 * float(r @ r)

    def simulate(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Particle positions (F, N, d) m and active flags (F, N) at the residual's frames for physical
        parameter values `theta` (dict or (p,) in `transform.names` order)."""
        z = self.transform.to_unconstrained(theta)
        x, active, health = _positions(jnp.asarray(z, self.sim.dtype), *self._args())
        self.sim.check({"x": x}, health)
        return np.asarray(x)[self.observed], np.asarray(active)[self.observed]

    def render(self, theta) -> np.ndarray:
        """Soft silhouettes (F, H, W) in [0, 1) at the observation level for parameters `theta`."""
        x, active = self.simulate(theta)
        return np.asarray(render_frames(jnp.asarray(x), jnp.asarray(active), self.cfg))

    def params_of(self, z) -> dict:
        """Every material parameter (name -> float) at fitted coordinates z, and the fitted scene parameters."""
        theta = np.asarray(self.transform.to_physical(jnp.asarray(z)))
        out = {n: float(getattr(self.base, n)) for n in FIT_FIELDS + KNOWN_INPUTS}
        out.update({n: float(theta[i]) for i, n in enumerate(self.transform.names)})
        return out

    def pixel_images(self, r) -> np.ndarray:
        """The weighted pixel residual images (F, H, W) inside a residual vector r."""
        F = len(self.frames)
        H, W = self.cfg.shape
        return np.asarray(r).reshape(F, -1)[:, :H * W].reshape(F, H, W)


def _data_fingerprint(data: Silhouettes) -> str:
    """A short hash of what the fit sees (masks, weights, times, camera, scene): a fit log made from
    other data is refused on resume."""
    h = hashlib.sha256()
    for a in (data.masks, data.weights, data.times):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps(data.camera.as_dict(), sort_keys=True).encode())
    h.update(data.scene_json.encode())
    return h.hexdigest()[:16]


def choose_pixel_level(pixel_size: float, spacing: float, image_shape) -> int:
    """The coarsest pyramid level whose pixels (pixel_size 2^l, m) are not larger than the particle
    spacing (m), keeping at least 8 pixels across the image."""
    level = 0
    while (pixel_size * 2 ** (level + 1) <= spacing * (1 + 1e-9)
           and min(image_shape) / 2 ** (level + 1) >= 8):
        level += 1
    return level


def max_pixel_level(image_shape) -> int:
    """The coarsest pyramid level that keeps at least MIN_LEVEL_PIXELS pixels across the image."""
    return max(0, int(math.floor(math.log2(max(1, min(image_shape)) / MIN_LEVEL_PIXELS))))


def check_fit_data(data: Silhouettes, scene: Scene, used) -> None:
    """Refuse data a fit cannot use: a camera whose pixels are larger than the domain (a units slip), masks
    with no foam, or foam in every pixel, in every used frame (pixels of weight > 0)."""
    p = data.camera.pixel_size
    span = min(scene.domain_max[k] - scene.domain_min[k] for k in range(2))
    if span / p < MIN_DOMAIN_PIXELS:
        raise CalibrationError(f"camera.pixel_size = {p:g} m: the scene domain ({span:g} m across) spans "
                               f"{span / p:.3g} pixels, fewer than {MIN_DOMAIN_PIXELS}; the pixel size is in m "
                               f"per pixel (not mm or um)")
    seen = data.weights[used] > 0
    foam = data.masks[used].astype(bool) & seen
    if not foam.any():
        raise CalibrationError(f"masks: no foam pixel (of weight > 0) in any of the {len(used)} used frame(s); "
                               f"nothing to fit (check the tracking threshold or --time-window)")
    if np.array_equal(foam, seen):
        raise CalibrationError("masks: every pixel of weight > 0 is foam in every used frame; the silhouette has "
                               "no boundary to fit (check the tracking threshold or the camera)")


def fit_grid(scene: Scene, settings: FitSettings) -> tuple[float, int]:
    """A fit's grid spacing (m) and particles per cell: the settings', or FIT_CELLS across the scene's
    largest extent and FIT_PPC."""
    extent = float(np.max(np.asarray(scene.domain_max) - np.asarray(scene.domain_min)))
    dx = extent / FIT_CELLS[scene.dim] if settings.dx is None else float(settings.dx)
    return dx, FIT_PPC[scene.dim] if settings.ppc is None else int(settings.ppc)


def phased_scene(scene: Scene, dx: float, phase: float) -> Scene:
    """`scene` with its domain extended below so that on a grid of spacing dx (m) its floor lies `phase`
    cells above a node row (rows at domain min + k dx). Scenes without a floor are returned as is."""
    if scene.floor_y is None:
        return scene
    now = (float(scene.floor_y) - float(scene.domain_min[1])) / dx
    extend = (phase - (now - math.floor(now + 1e-9))) % 1.0
    if extend < 1e-9 or extend > 1.0 - 1e-9:
        return scene
    lo = list(scene.domain_min)
    lo[1] = float(lo[1]) - extend * dx
    return dataclasses.replace(scene, domain_min=tuple(lo))


def build_problem(data: Silhouettes, settings: FitSettings | None = None, *,
                  max_particles: int = DEFAULT_MAX_PARTICLES,
                  max_substeps: int = DEFAULT_MAX_SUBSTEPS, adjoint=DEFAULT_JACOBIAN) -> CalibrationProblem:
    """Bind a dataset to a simulator at the fit's dx, a renderer and a parameter transform.

    Args:
      data: the observations (`fitting.io.read_silhouettes`).
      settings: `FitSettings` (default: all defaults).
      max_particles, max_substeps: budgets of one rollout (BudgetError, checked before it is bound).
      adjoint: the Jacobian's route, a `jaxfoam.ForwardMode` (CalibrationError otherwise, before any work).
    Returns a `CalibrationProblem`. Raises CalibrationError for unusable settings or data (no frame
    after the start of the simulation, an empty first mask, masks without foam or a boundary).
    """
    settings = (settings or FitSettings()).validate()
    _check_jacobian_adjoint(adjoint)
    dtype = jnp.float64 if settings.dtype == "float64" else jnp.float32
    scene: Scene = data.load_scene(dtype=dtype)
    d = scene.dim
    dx, ppc = fit_grid(scene, settings)
    if settings.floor_phase is not None:
        scene = phased_scene(scene, dx, float(settings.floor_phase))
    fixed = dict(settings.fixed)
    kappa = float(fixed.get("kappa", scene.kappa))
    rho = float(fixed.get("rho", scene.density))
    fitted = settings.fitted
    bounds = {n: settings.bounds_of(n) for n in fitted}
    transform = fit_transform(settings)
    if "friction" in fitted and (scene.floor_y is None or scene.floor_sticky):
        raise CalibrationError("fit_also: friction needs a scene whose floor has Coulomb friction; this scene has "
                               + ("no floor" if scene.floor_y is None else "a sticky floor"))

    # The time step is that of the stiffest admissible material (mu at its upper bound, or fixed), so
    # every rollout of the fit is stable with one substep count.
    mu_ref = float(fixed["mu"]) if "mu" in fixed else bounds["mu"][1]
    mid = {n: float(np.sqrt(np.prod(settings.bounds_of(n)))) for n in FIT_FIELDS}
    ref = Params(mu=mu_ref, kappa=kappa, sigma_y=float(fixed.get("sigma_y", mid["sigma_y"])),
                 eta=float(fixed.get("eta", mid["eta"])), m=float(fixed.get("m", 0.5 * sum(settings.bounds_of("m")))),
                 rho=rho).validate()
    base = ref.replace(mu=float(fixed.get("mu", mu_ref)))

    times = np.asarray(data.times, float)
    first_mask = scene.initial_shape["type"] == "first_mask"
    if settings.pixel_level is not None and settings.pixel_level > max_pixel_level(data.image_shape):
        raise CalibrationError(f"pixel_level must be in [0, {max_pixel_level(data.image_shape)}] for "
                               f"{data.image_shape[0]}x{data.image_shape[1]} pixel images (each level halves them; "
                               f"at least {MIN_LEVEL_PIXELS} pixels across), got {settings.pixel_level}")
    check_dtype_range(dict(mu=base.mu, kappa=kappa, sigma_y=base.sigma_y, eta=base.eta, m=base.m, rho=rho),
                      settings.dtype)
    estimate = estimate_particles(scene, dx, ppc)
    if estimate is not None:
        check_particles(estimate, d, jnp.dtype(dtype).itemsize, max_particles, dx=dx, ppc=ppc)
    try:
        state0 = init_state(scene, dx, ppc, rho=rho, seed=settings.seed,
                            first_mask=data.first_mask if first_mask else None, dtype=dtype)
    except ValueError as exc:
        raise CalibrationError(f"initial shape: {exc}") from exc
    # With a first_mask shape the material is known at the first frame's time: start there.
    t0 = float(times[0]) if first_mask else 0.0
    state0 = state0.replace(t=jnp.asarray(t0, dtype))
    used = np.nonzero(times > t0 + 1e-12)[0]
    if len(used) == 0:
        raise CalibrationError(f"times: no frame after the start of the simulation (t0 = {t0} s); the fit needs "
                               f"at least one frame after the initial shape")
    if settings.time_window is not None:
        lo, hi = (float(v) for v in settings.time_window)
        used = used[(times[used] >= lo) & (times[used] <= hi)]
        if len(used) == 0:
            raise CalibrationError(f"time_window: no frame after the start (t0 = {t0} s) lies in [{lo}, {hi}] s; "
                                   f"the data's frames are at {np.round(times, 4).tolist()} s")
    # Resampling needs free slots: the Simulator grows state0 to resample.capacity_factor times its
    # sampled count (inactive slots are neither simulated nor rendered).
    check_fit_data(data, scene, used)
    check_particles(int(np.sum(state0.active)), d, jnp.dtype(dtype).itemsize, max_particles, dx=dx, ppc=ppc)
    resample = settings.resample_for(d, ppc)
    fracture = settings.fracture_for(d)
    sim_times, observed = simulation_frames(t0, times[used])
    per_frame = substeps_per_frame(scene, ref, dx, FIT_CFL, sim_times, t0)
    check_substeps(per_frame, len(sim_times), max_substeps, span=float(sim_times[-1]) - t0,
                   dt=float(np.max(np.diff(np.concatenate([[t0], sim_times])))) / per_frame,
                   times_option="the data's times")
    sim = Simulator(scene, sim_times, ref, dx, ppc, dtype=dtype, state0=state0, cfl=FIT_CFL,
                    resample=resample, fracture=fracture)

    spacing = particle_spacing(dx, ppc, d)
    level = (choose_pixel_level(data.camera.pixel_size, spacing, data.image_shape) if settings.pixel_level is None
             else int(settings.pixel_level))
    masks, weights, camera = pyramid(without_plate_pixels(data, scene), level + 1)[level]
    masks, weights = masks[used], weights[used]
    if not np.any(weights > 0):
        raise CalibrationError("weights: every pixel of the used frames has weight 0; nothing to fit")
    cfg = make_render_config(camera, masks.shape[1:], dx, ppc, d)
    target = make_target(masks, weights, camera, dtype=dtype)
    return CalibrationProblem(data, settings, sim, transform, base, used, level, masks, weights, camera, cfg, target,
                              observed, adjoint)


def without_plate_pixels(data: Silhouettes, scene) -> Silhouettes:
    """The data with weight 0 wherever a plate of the scene covers a pixel at that frame's time.

    A plate is solid in the image plane: foam seen there in a video lies in front of or behind it (3D) or
    is not there at all (2D), while the simulation holds foam inside a sticky plate, the layer it grips
    (and `Silhouettes.first_mask` continues hanging foam into it). The fit compares neither. `jaxfoam
    synth` and `jaxfoam track` already write weight 0 there; files from elsewhere may not.
    """
    if not scene.plates:
        return data
    keep = np.stack([~plate_footprint(scene, float(t), data.camera, data.image_shape) for t in data.times])
    if np.all(data.weights[~keep] == 0):
        return data
    return dataclasses.replace(data, weights=(data.weights * keep).astype(np.float32))


def fit_transform(settings: FitSettings) -> optim.ParameterTransform:
    """The fitted coordinates of a fit: log for the positive parameters, bounded for all, within the
    settings' bounds."""
    fitted = settings.fitted
    return optim.ParameterTransform.create(fitted, positive=[n for n in fitted if n != "m"],
                                             bounds={n: settings.bounds_of(n) for n in fitted})


def fitted_occupancy(problem: CalibrationProblem, result: FitResult) -> np.ndarray:
    """The simulated soft silhouettes (F, H, W) at the optimum, as the loss saw them.

    Read back from the stored residual (pixel residual = sqrt(w / sum w) (O - M) / sqrt(F)), so no
    rollout is needed; NaN where the weight is 0 (not compared). Falls back to a rollout without it.
    """
    if result.residual is None:
        return problem.render({n: result.params[n] for n in problem.transform.names})
    F = len(problem.frames)
    w = np.asarray(problem.weights, np.float64)
    scale = np.sqrt(w / np.maximum(w.sum(axis=(1, 2), keepdims=True), 1e-12)) / math.sqrt(F)
    img = problem.pixel_images(result.residual)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(w > 0, problem.masks + img / np.where(w > 0, scale, 1.0), np.nan)
