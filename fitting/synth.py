"""Synthetic silhouette data: simulate a scene and render it the way a tracked video looks.

`synthesize` runs `jaxfoam.simulate` at a given dx, then for every frame:

1. renders a hard silhouette: particles are splatted with a fine kernel (width 1.5 particle spacings)
   on a supersampled pixel grid, the coverage is thresholded at 1/2, and a pixel is foam when at
   least half of its sub-pixels are (what a tracker that thresholds a sharp image reports);
2. hides the plates: pixels under a plate's footprint at that time (`Plate.position(t)`) get mask 0
   and weight 0 (occluded: a fitter must ignore them);
3. adds boundary noise: each pixel on either side of the foam boundary flips with probability `noise`;
4. drops frames: a fraction of the frames after the first is removed at random (times with gaps).

The parameters that made the data are written to /truth (for recovery studies; fitters never read
it). The command line is `jaxfoam synth SCENE.json --params mu=..,sigma_y=..,eta=..,m=.. --out data.h5`.
"""
from __future__ import annotations

import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxfoam import CFL, DEFAULT_PPC, FIT_FIELDS, Params, Scene, Simulator, load_scene
from jaxfoam.guards import (DEFAULT_MAX_PARTICLES, DEFAULT_MAX_SUBSTEPS, check_dtype_range, check_particles,
                            check_substeps, estimate_particles, substeps_per_frame)
from .io import Camera, Silhouettes, camera_covering, plate_footprint, validate
from .silhouette import HALF_DENSITY, make_render_config, particle_spacing, splat_density

# Sub-pixels per particle spacing of the supersampled rendering: 2 resolves the kernel's edge well
# enough that the pixel coverage is accurate to ~1/4 pixel.
SUBPIXELS_PER_SPACING = 2.0
# Largest supersampling factor per axis (memory: (H ss) x (W ss) per frame).
MAX_SUPERSAMPLE = 8
# Kernel width of the "true" silhouette, particle spacings: the smallest width that closes the gaps
# between jittered particles (see KERNEL_SPACINGS in silhouette.py).
FINE_KERNEL_SPACINGS = 1.5
_splat = jax.jit(splat_density, static_argnames=("cfg",))
# Largest image (pixels per frame) synth renders: a 4096 x 4096 image of the domain is far finer than a
# fit uses; more is a pixel size given in the wrong unit.
MAX_IMAGE_PIXELS = 4096 * 4096



def parse_params(text: str) -> dict:
    """Parse 'mu=100,sigma_y=30,eta=5,m=0.6' into a dict of floats (all four required)."""
    out = {}
    for item in filter(None, (s.strip() for s in str(text).split(","))):
        if "=" not in item:
            raise ValueError(f"--params: expected name=value pairs separated by commas, got {item!r}")
        k, v = (s.strip() for s in item.split("=", 1))
        if k in ("kappa", "rho", "density"):
            raise ValueError(f"--params: {k} is a known input of the scene (density, kappa), not a parameter here")
        if k not in FIT_FIELDS:
            raise ValueError(f"--params: unknown parameter {k!r}; expected {list(FIT_FIELDS)}")
        try:
            out[k] = float(v)
        except ValueError as exc:
            raise ValueError(f"--params: {k} must be a number, got {v!r}") from exc
    missing = [k for k in FIT_FIELDS if k not in out]
    if missing:
        raise ValueError(f"--params: missing {missing} (give all of {list(FIT_FIELDS)})")
    return out


def hard_masks(xs, active, camera: Camera, shape, dx: float, ppc: int, dim: int) -> np.ndarray:
    """Binary silhouettes (T, H, W) uint8 of particle frames xs (T, N, d) m, active (T, N) bool.

    The coverage of a fine kernel (FINE_KERNEL_SPACINGS particle spacings) is thresholded at 1/2 on
    a supersampled grid; a pixel is foam when at least half of its sub-pixels are.
    """
    H, W = shape
    s = particle_spacing(dx, ppc, dim)
    ss = int(min(MAX_SUPERSAMPLE, max(1, math.ceil(camera.pixel_size * SUBPIXELS_PER_SPACING / s))))
    fine = Camera(pixel_size=camera.pixel_size / ss, origin=camera.origin)
    cfg = make_render_config(fine, (H * ss, W * ss), dx, ppc, dim, kernel_spacings=FINE_KERNEL_SPACINGS,
                             kernel_pixels=1.0)
    out = np.zeros((len(xs), H, W), np.uint8)
    for t in range(len(xs)):
        dens = np.asarray(_splat(jnp.asarray(xs[t]), jnp.asarray(active[t]), cfg))
        cover = (dens >= HALF_DENSITY).reshape(H, ss, W, ss).mean(axis=(1, 3))
        out[t] = cover >= 0.5
    return out


def boundary_pixels(mask: np.ndarray) -> np.ndarray:
    """Pixels with a 4-neighbour of the other class (both sides of the boundary): bool (H, W)."""
    m = np.asarray(mask, bool)
    diff = np.zeros_like(m)
    diff[1:, :] |= m[1:, :] != m[:-1, :]
    diff[:-1, :] |= m[1:, :] != m[:-1, :]
    diff[:, 1:] |= m[:, 1:] != m[:, :-1]
    diff[:, :-1] |= m[:, 1:] != m[:, :-1]
    return diff


def synthesize(scene: Scene | dict | str, params: dict, dx: float | None = None, ppc: int | None = None,
               frames: int = 16, duration: float = 1.0, pixel_size: float | None = None, noise: float = 0.05,
               drop_frames: float = 0.0, seed: int = 0, dtype=jnp.float64, first_mask: bool = False,
               cfl: float = CFL, progress=None, max_particles: int = DEFAULT_MAX_PARTICLES,
               max_substeps: int = DEFAULT_MAX_SUBSTEPS) -> Silhouettes:
    """Simulate a scene and render it as tracked-video silhouettes.

    Args:
      scene: the scene (parsed, dict, JSON text or path); its initial_shape must be box or ellipse.
      params: {mu (Pa), sigma_y (Pa), eta (Pa s^m), m}; kappa and density come from the scene.
      dx: simulation grid spacing, m (default: `jaxfoam simulate`'s, the domain's largest extent / 64
        in 2D, / 32 in 3D).
      ppc: particles per cell (default 4 in 2D, 8 in 3D).
      frames: number of frames before dropping, evenly spaced on [0, duration] s (frame 0 is t = 0).
      pixel_size: m per pixel (default dx / 2); the camera covers the domain's (x, y) extent.
      noise: probability in [0, 1] that a pixel on either side of the boundary flips.
      drop_frames: fraction in [0, 1) of the frames after the first removed at random.
      seed: seed of particle sampling, noise and dropped frames.
      first_mask: record the scene with initial_shape 'first_mask' (a fit then starts from the first,
        noisy, mask as it would with real data) instead of the primitive used to simulate.
      cfl: CFL number of the simulation's time step (default the simulator's, 0.3); data made with
        another time step than the fit's emulate another simulator's numerics.
      progress: optional callable(str) for status lines.
      max_particles, max_substeps: the run's budgets (BudgetError, checked before any work).
    Returns the validated `Silhouettes` (write it with `.write(path)`).
    """
    say = progress or (lambda msg: None)
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    if scene.initial_shape["type"] == "first_mask":
        raise ValueError("scene.initial_shape: synth needs an explicit shape ('box' or 'ellipse'), not 'first_mask'")
    if isinstance(params, str):
        params = parse_params(params)
    p = Params(mu=params["mu"], kappa=scene.kappa, sigma_y=params["sigma_y"], eta=params["eta"], m=params["m"],
               rho=scene.density).validate()
    d = scene.dim
    ppc = DEFAULT_PPC[d] if ppc is None else int(ppc)
    if dx is None:
        from jaxfoam.cli import default_dx

        dx = default_dx(scene)
    dx = float(dx)
    pixel_size = dx / 2 if pixel_size is None else float(pixel_size)
    if not (isinstance(frames, int) and frames >= 2):
        raise ValueError(f"frames must be an integer >= 2, got {frames!r}")
    if not (duration > 0 and math.isfinite(duration)):
        raise ValueError(f"duration must be > 0 s, got {duration!r}")
    if not 0.0 <= noise <= 1.0:
        raise ValueError(f"noise must be a probability in [0, 1], got {noise}")
    if not 0.0 <= drop_frames < 1.0:
        raise ValueError(f"drop_frames must be a fraction in [0, 1), got {drop_frames}")
    if not (isinstance(seed, int) and seed >= 0):
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    if ppc < 1:
        raise ValueError(f"ppc must be an integer >= 1, got {ppc!r}")
    if not (dx > 0 and math.isfinite(dx)):
        raise ValueError(f"dx must be a positive grid spacing in m, got {dx!r}")
    if not (0 < cfl <= 1):
        raise ValueError(f"cfl must be in (0, 1], got {cfl!r}")
    times = np.linspace(0.0, float(duration), frames)
    dtype_name = jnp.dtype(dtype).name
    check_dtype_range(dict(params), dtype_name)
    estimate = estimate_particles(scene, dx, ppc)
    if estimate is not None:
        check_particles(estimate, d, jnp.dtype(dtype).itemsize, max_particles, dx=dx, ppc=ppc)
    camera, shape = camera_covering(scene, pixel_size)
    if shape[0] * shape[1] > MAX_IMAGE_PIXELS:
        raise ValueError(f"pixel_size {pixel_size:g} m makes {shape[0]}x{shape[1]} pixel images of the domain, over "
                         f"{MAX_IMAGE_PIXELS:,} pixels: the pixel size is in m (not mm or um)")
    per_frame = substeps_per_frame(scene, p, dx, cfl, times[1:])
    check_substeps(per_frame, frames - 1, max_substeps, span=float(duration), dt=float(times[1]) / per_frame)

    t0 = time.perf_counter()
    sim = Simulator(scene, times[1:], p, dx, ppc, dtype=dtype, cfl=cfl, seed=seed)
    _, traj, health = sim.rollout(p)
    sim.check(traj, health)
    say(f"simulated {frames - 1} frames to t = {duration:g} s: {int(np.sum(sim.state0.active))} particles, "
        f"{sim.substeps} substeps/frame of dt = {sim.dt:.3g} s, {time.perf_counter() - t0:.1f} s wall")
    # Frame 0 (t = 0) is the initial state itself.
    xs = np.concatenate([np.asarray(sim.state0.x)[None], np.asarray(traj["x"])], axis=0)
    act = np.concatenate([np.asarray(sim.state0.active)[None], np.asarray(traj["active"])], axis=0)

    masks = hard_masks(xs, act, camera, shape, dx, ppc, d)
    # Separate streams: the frames dropped do not depend on the noise level.
    rng_noise = np.random.default_rng([seed, 1])
    rng_drop = np.random.default_rng([seed, 2])
    weights = np.ones(masks.shape, np.float32)
    for t in range(frames):
        if noise > 0:
            flip = boundary_pixels(masks[t]) & (rng_noise.random(shape) < noise)
            masks[t] ^= flip.astype(np.uint8)
        plate = plate_footprint(scene, float(times[t]), camera, shape)
        masks[t][plate] = 0
        weights[t][plate] = 0.0
    keep = np.ones(frames, bool)
    n_drop = int(round(drop_frames * (frames - 1)))
    if n_drop:
        keep[1 + rng_drop.choice(frames - 1, size=n_drop, replace=False)] = False

    spec = scene.spec
    if first_mask:
        spec = dict(spec, initial_shape={"type": "first_mask"})
    source = json.dumps(dict(generator="jaxfoam synth", dx=dx, ppc=ppc, pixel_size=pixel_size, noise=noise,
                             drop_frames=drop_frames, frames=frames, duration=duration, seed=seed,
                             dt=sim.dt, substeps=sim.substeps, cfl=cfl, dtype=str(jnp.dtype(dtype)),
                             simulated_initial_shape=scene.initial_shape))
    truth = dict(params, kappa=scene.kappa, rho=scene.density)
    return validate(masks[keep], times[keep], camera, spec, weights=weights[keep], source=source, truth=truth)
