"""What a camera records of a reference run: the run sampled at a video's own frame times, each frame
drawn as a lit, shaded picture of the foam, encoded as H.264. SI units (m, s); intensities in [0, 1].

A frame (`render_frame`) is drawn on a fine grid (SUPERSAMPLE sub-pixels per video pixel per axis)
and averaged over each video pixel, as a sensor integrates the light on its area:

1. the foam's fine mask (silhouettes.render_mask: the same disk union as the silhouette files);
2. a height field from the distance to the mask's edge, a rounded rim of radius `rim` m (a
   cylinder-like edge profile), and its normals;
3. wrap-lit Lambert shading (a subsurface-like term: light reaches past the terminator) under one
   directional light, softened by a Gaussian blur inside the foam (light diffusing in the bubbles);
4. a textured background (seeded multi-octave value noise in world coordinates, the same in every
   frame) darkened by a soft drop shadow: the foam and plates' silhouette shifted away from the light
   and blurred;
5. the plates (where the scene has them) drawn as shaded boards over everything;
6. box averaging to video pixels, a slight lens blur, Gaussian sensor noise (seeded per frame), 8 bits.

`write_video` encodes H.264 (libx264, yuv420p) through imageio-ffmpeg. `record` runs a reference case
(the same seeded run as its silhouette file) and keeps the particle positions at arbitrary times.
"""
from __future__ import annotations

import dataclasses
import math
import os
import tempfile

import numpy as np

from .silhouettes import Camera, plate_pixels, render_mask

# Sub-pixels per video pixel per axis: enough that the shading and the box average resolve the rim.
SUPERSAMPLE = 3
# H.264 constant rate factor: 23 is x264's default; 25 is a little more compressed, as a phone's.
CRF = 25
# Gaussian sensor noise, fraction of full scale per channel: a well-lit phone sensor at base ISO.
NOISE_SIGMA = 0.015


@dataclasses.dataclass(frozen=True)
class Look:
    """How the scene looks: light direction (towards the light, camera frame: x right, y up, z to the
    camera), rim radius m, colours (RGB in [0, 1]), shadow offset (m, world x y), blur and strength,
    background texture scale m and contrast, lens blur (video pixels) and sensor noise."""

    light: tuple = (-0.45, 0.55, 0.70)
    rim: float = 0.0025              # m: how far in from the edge the foam surface turns to face the camera
    ambient: float = 0.45            # fraction of the light reaching every surface (room light)
    wrap: float = 0.8                # wrap lighting: n.l is remapped to (n.l + wrap) / (1 + wrap)
    soften: float = 0.0012           # m: Gaussian blur of the foam's shading (subsurface-like)
    foam_rgb: tuple = (0.97, 0.96, 0.93)
    plate_rgb: tuple = (0.50, 0.34, 0.20)
    background_rgb: tuple = (0.36, 0.42, 0.50)
    texture_scale: float = 0.02      # m: the coarsest octave of the background texture
    texture_contrast: float = 0.10   # peak-to-peak change of the background's intensity, fraction
    shadow_offset: tuple = (0.006, -0.005)  # m, away from the light
    shadow_blur: float = 0.004       # m, Gaussian sigma of the shadow's edge
    shadow_strength: float = 0.35    # fraction of the background's light the shadow removes at most
    lens_blur: float = 0.5           # video pixels, Gaussian sigma of the optics
    noise: float = NOISE_SIGMA
    seed: int = 0                    # background texture and sensor noise


def video_times(duration, fps):
    """Frame times k / fps (s) on [0, duration] s."""
    n = math.floor(duration * fps + 1e-9) + 1
    return np.arange(n) / float(fps)


def video_camera(scene_lo, scene_hi, pixel_size):
    """The camera of the video: the scene's domain (x, y) at `pixel_size` m, its width and height rounded
    up to even pixel counts (H.264 in yuv420p needs them); the origin stays at the domain's bottom-left."""
    cam = Camera.covering(scene_lo, scene_hi, pixel_size)
    H, W = cam.shape
    return Camera(pixel_size, cam.origin, (H + H % 2, W + W % 2))


def record(case_name, set_index, times, refine=None, progress=print):
    """Run a reference case (the run of its silhouette file: the same seed, grid offset and sampling)
    and keep the particle positions at `times` (s). Returns dict(times, x (T, N, d) m, spacing m, dx m,
    scene (RefScene), params, steps, wall_s)."""
    import time

    from .generate import CASES, parameter_sets, setup_case

    case = CASES[case_name]
    params = parameter_sets(case)[set_index]
    scene, sim, dx, spacing, _ = setup_case(case, params, seed=set_index, refine=refine)
    times = np.asarray(times, float)
    if not np.all(np.diff(times) > 0) or times[0] < 0:
        raise ValueError("record: times must be >= 0 and strictly increasing")
    xs = np.zeros((len(times),) + sim.p.x.shape)
    t0 = time.perf_counter()
    for k, t in enumerate(times):
        sim.advance_to(t)
        xs[k] = sim.p.x
        progress(f"  {case_name} t = {t:.4f} s: {sim.steps} steps, {time.perf_counter() - t0:.0f} s")
    return dict(times=times, x=xs, spacing=spacing, dx=dx, scene=scene, params=params, steps=sim.steps,
                wall_s=time.perf_counter() - t0)


def exact_masks(x, times, spacing, camera, scene):
    """The silhouettes of positions x (T, N, d) m at `times` s on `camera`, as the silhouette files make
    them (plate pixels mask 0, weight 0): (masks (T, H, W) uint8, weights (T, H, W) float32)."""
    masks = np.zeros((len(times),) + camera.shape, np.uint8)
    weights = np.ones(masks.shape, np.float32)
    for k, t in enumerate(times):
        masks[k] = render_mask(x[k], spacing, camera)
        hidden = plate_pixels(camera, _plate_boxes(scene, t))
        masks[k][hidden] = 0
        weights[k][hidden] = 0.0
    return masks, weights


def _plate_boxes(scene, t):
    lo, hi, _, _ = scene.boundaries.plate_arrays(float(t))
    return [(lo[q, :2], hi[q, :2]) for q in range(len(lo))]


# ----------------------------------------------------------------------------------------------
# Image operations (numpy; scipy.ndimage for the distance transform and blurs)
# ----------------------------------------------------------------------------------------------

def _blur(img, sigma_px):
    from scipy.ndimage import gaussian_filter

    if sigma_px <= 0:
        return img
    axes = (0, 1)
    return gaussian_filter(img, sigma=[sigma_px if a in axes else 0.0 for a in range(img.ndim)], mode="nearest")


def _shift(img, dj, di):
    """img (rows, cols) shifted by di rows down and dj columns right (whole sub-pixels), zeros enter."""
    out = np.zeros_like(img)
    H, W = img.shape
    di, dj = round(di), round(dj)
    src = img[max(0, -di):H - max(0, di), max(0, -dj):W - max(0, dj)]
    out[max(0, di):max(0, di) + src.shape[0], max(0, dj):max(0, dj) + src.shape[1]] = src
    return out


def _box_down(img, f):
    H, W = img.shape[:2]
    return img.reshape(H // f, f, W // f, f, *img.shape[2:]).mean(axis=(1, 3))


def background_texture(camera, look, supersample=SUPERSAMPLE):
    """The background (rows, cols, 3) on the fine grid: a seeded sum of value-noise octaves (bicubic
    upsampling of random lattices at scales texture_scale, /2, /4, /8 m, amplitudes halving), plus a
    faint fine grain; the same for every frame of a video of one seed."""
    from scipy.ndimage import map_coordinates

    H, W = camera.shape[0] * supersample, camera.shape[1] * supersample
    h = camera.pixel_size / supersample
    rng = np.random.default_rng([look.seed, 1])
    ys, xs = np.mgrid[0:H, 0:W].astype(float) * h  # from the image's top-left corner, m
    tex = np.zeros((H, W))
    amp, total = 1.0, 0.0
    for octave in range(4):
        scale = look.texture_scale / 2 ** octave
        lattice = rng.random((int(H * h / scale) + 4, int(W * h / scale) + 4))
        tex += amp * map_coordinates(lattice, [ys / scale + 1, xs / scale + 1], order=3, mode="nearest")
        total += amp
        amp *= 0.5
    tex = tex / total - 0.5
    tint = 1.0 + look.texture_contrast * tex / max(np.ptp(tex), 1e-9) * 2
    rgb = np.asarray(look.background_rgb)[None, None, :] * tint[:, :, None]
    # A second, greener-bluer field at the coarsest scale so the texture is not grey only.
    hue = map_coordinates(rng.random((int(H * h / look.texture_scale) + 4, int(W * h / look.texture_scale) + 4)),
                          [ys / look.texture_scale + 1, xs / look.texture_scale + 1], order=3, mode="nearest")
    rgb[:, :, 1] *= 1.0 + 0.06 * (hue - 0.5)
    return np.clip(rgb, 0.0, 1.0)


def _shading(mask, h, look):
    """Wrap-lit Lambert intensity (rows, cols) of the foam of fine mask `mask` (sub-pixel h m)."""
    from scipy.ndimage import distance_transform_edt

    d = distance_transform_edt(mask) * h
    s = np.clip(d / look.rim, 0.0, 1.0)
    height = look.rim * np.sqrt(1.0 - (1.0 - s) ** 2)  # quarter circle: vertical at the edge, flat inside
    height = _blur(height, 0.75)  # removes the distance transform's sub-pixel staircase
    gy, gx = np.gradient(height, h)  # rows go down the image: world dh/dy = -gy
    n = np.stack([-gx, gy, np.ones_like(gx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    light = np.asarray(look.light, float)
    light /= np.linalg.norm(light)
    ndl = n @ light
    lit = look.ambient + (1.0 - look.ambient) * np.clip((ndl + look.wrap) / (1.0 + look.wrap), 0.0, 1.0)
    # Subsurface-like softening: a blur of the shading normalised by the blurred mask (no dark halo).
    sig = look.soften / h
    m = mask.astype(float)
    return np.where(mask, _blur(lit * m, sig) / np.maximum(_blur(m, sig), 1e-6), 0.0)


def render_frame(x, t, spacing, camera, scene, look, background=None, frame_index=0,
                 supersample=SUPERSAMPLE):
    """One video frame (H, W, 3) uint8 of particles at x (N, d) m at time t (s); see the module docstring.

    x None draws the empty scene (the background photo a user takes). background: the fine texture of
    `background_texture` (computed once per video). frame_index seeds the sensor noise.
    """
    ss = int(supersample)
    H, W = camera.shape
    fine = Camera(camera.pixel_size / ss, camera.origin, (H * ss, W * ss))
    h = fine.pixel_size
    bg = background_texture(camera, look, ss) if background is None else background
    foam = render_mask(x, spacing, fine).astype(bool) if x is not None else np.zeros(fine.shape, bool)
    plates = plate_pixels(fine, _plate_boxes(scene, t))
    caster = (foam | plates).astype(float)
    shadow = _blur(_shift(caster, look.shadow_offset[0] / h, -look.shadow_offset[1] / h), look.shadow_blur / h)
    img = bg * (1.0 - look.shadow_strength * shadow)[:, :, None]
    if foam.any():
        shade = _shading(foam, h, look)
        img = np.where(foam[:, :, None], shade[:, :, None] * np.asarray(look.foam_rgb), img)
    if plates.any():
        img = np.where(plates[:, :, None], _plate_shading(plates, h) [:, :, None] * np.asarray(look.plate_rgb), img)
    img = _blur(_box_down(img, ss), look.lens_blur)
    rng = np.random.default_rng([look.seed, 2, int(frame_index)])
    img = img + rng.normal(0.0, look.noise, img.shape)
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def _plate_shading(plates, h):
    """A board lit from above: brighter towards its top face, a darker bevel of 1 mm at its edges."""
    from scipy.ndimage import distance_transform_edt

    d = distance_transform_edt(plates) * h
    rows = np.arange(plates.shape[0], dtype=float)[:, None] / plates.shape[0]
    return np.where(d < 0.001, 0.7, 1.0) * (1.05 - 0.2 * rows)


def render_video(x, times, spacing, camera, scene, look):
    """Frames (T, H, W, 3) uint8 of positions x (T, N, d) m at times (T,) s, and the empty-scene photo
    (H, W, 3) uint8 (plates at t = 0, its own noise)."""
    bg = background_texture(camera, look)
    frames = np.stack([render_frame(x[k], t, spacing, camera, scene, look, bg, k) for k, t in enumerate(times)])
    empty = render_frame(None, 0.0, spacing, camera, scene, look, bg, frame_index=len(times) + 1)
    return frames, empty


def write_video(path, frames, fps, crf=CRF):
    """Encode frames (T, H, W, 3) uint8 as H.264 (libx264, yuv420p, constant rate factor crf) at fps
    frames/s; written to a temporary file beside `path` and renamed into place."""
    import imageio.v2 as iio2

    from jaxfoam.video import ffmpeg_subprocess

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[1] % 2 or frames.shape[2] % 2:
        raise ValueError(f"write_video: frames must be (T, H, W, 3) with H, W even, got {frames.shape}")
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".video.partial-", suffix=".mp4", dir=folder)
    os.close(fd)
    try:
        with ffmpeg_subprocess():
            w = iio2.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=None,
                                pixelformat="yuv420p", macro_block_size=1, ffmpeg_log_level="error",
                                output_params=["-crf", str(int(crf))])
            for f in frames:
                w.append_data(f)
            w.close()
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_png(path, image):
    """Write an image (H, W, 3) uint8 as PNG (lossless) atomically."""
    import imageio.v3 as iio

    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".image.partial-", suffix=".png", dir=folder)
    os.close(fd)
    iio.imwrite(tmp, np.asarray(image, np.uint8))
    os.replace(tmp, path)
    return path
