"""Track a foam silhouette in an ordinary video and write it in the silhouette format.

Pipeline (numpy only; frames come from imageio):

1. read the frames (a video or GIF file, or a directory of images) and the frame rate;
2. optional average-pool downsampling (a phone video's 1080p is more than a fit needs);
3. foreground: the colour difference to a static background (the per-pixel median of the frames,
   the first frame, or a photo of the empty scene; `polarity` 'brighter' counts only pixels brighter
   than the background, so a shadow the foam casts is not foam), or, with background 'none', the
   brightness (foam is white; `invert` for dark foam); thresholded at a given value or by Otsu's method;
4. optionally, edges at half contrast (`edges` 'half'): a global threshold puts the edge where the
   difference crosses it, too far in where the foam's rim is shaded darker than its middle and too far
   out where it is brighter. Within EDGE_BAND pixels of the thresholded edge, a pixel is foam when its
   difference is at least halfway from the local background level to the local foam level (means over
   EDGE_WINDOW pixels around it): a pixel is foam when more than half of it is;
5. clean-up: a morphological opening (removes specks) then closing (bridges cracks), disk-shaped;
6. the largest 8-connected component, with its holes filled (foam is opaque);
7. pixels under a plate of the scene (its footprint at each frame's time, dilated by a margin) get
   weight 0 and mask 0: a moving plate shows up in a background difference and must be ignored.

Times are t0 + k / fps. The camera is orthographic: the user gives the pixel size (m) and the world
position (m) of the image's bottom-left corner, e.g. from a ruler or the plate's known width.
"""
from __future__ import annotations

import json
import os

import numpy as np

from jaxfoam import load_scene
from .io import Camera, Silhouettes, plate_footprint, validate
from .video import read_frames

BACKGROUNDS = ("median", "first", "none")
POLARITIES = ("any", "brighter", "darker")
EDGES = ("half", "threshold")
# Half-contrast edges: the band (pixels each side of the thresholded edge) that is re-decided, and the
# half-width of the window of the local foam and background means; 3 reaches past a shaded rim.
EDGE_BAND = 2
EDGE_WINDOW = 3
# Frames used for the median background at most (evenly spread): the median of 64 frames is as
# good as that of all when the foam covers each pixel less than half the time, at bounded memory.
MEDIAN_FRAMES = 64
# Otsu's histogram resolution on differences in [0, 1].
OTSU_BINS = 256
# Default clean-up radii, pixels: opening 1 removes isolated specks of compression noise; closing 2
# bridges cracks from specular highlights without merging separate bodies a few pixels apart.
OPEN_RADIUS = 1
CLOSE_RADIUS = 2
# Plate footprint dilation, pixels: the scene's plate position is known to about a pixel or two.
PLATE_MARGIN = 2


# ----------------------------------------------------------------------------------------------
# Morphology and connected components (binary images, numpy)
# ----------------------------------------------------------------------------------------------

def _disk(radius: int) -> list[tuple[int, int]]:
    r = int(radius)
    return [(di, dj) for di in range(-r, r + 1) for dj in range(-r, r + 1) if di * di + dj * dj <= r * r]


def _shift_reduce(mask: np.ndarray, radius: int, reduce_and: bool) -> np.ndarray:
    r = int(radius)
    if r <= 0:
        return mask.copy()
    H, W = mask.shape
    # Edge replication: the image border neither erodes the foam nor grows it.
    padded = np.pad(mask, r, mode="edge")
    out = np.ones_like(mask) if reduce_and else np.zeros_like(mask)
    for di, dj in _disk(r):
        view = padded[r + di:r + di + H, r + dj:r + dj + W]
        if reduce_and:
            out &= view
        else:
            out |= view
    return out


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary erosion by a disk of `radius` pixels (bool (H, W))."""
    return _shift_reduce(np.asarray(mask, bool), radius, True)


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation by a disk of `radius` pixels (bool (H, W))."""
    return _shift_reduce(np.asarray(mask, bool), radius, False)


def opening(mask: np.ndarray, radius: int) -> np.ndarray:
    """Erosion then dilation: removes features thinner than the disk."""
    return dilate(erode(mask, radius), radius)


def closing(mask: np.ndarray, radius: int) -> np.ndarray:
    """Dilation then erosion: fills gaps and notches narrower than the disk."""
    return erode(dilate(mask, radius), radius)


def label_components(mask: np.ndarray, connectivity: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of a binary image: (labels (H, W) int, 0 = background, 1..n; sizes (n,) pixels).

    Run-length labeling: the foreground runs of each row are merged with the overlapping runs of the
    row above (union-find), so the Python work grows with the number of runs, not of pixels.
    connectivity: 4 or 8.
    """
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity}")
    m = np.asarray(mask, bool)
    H, W = m.shape
    padded = np.zeros((H, W + 2), np.int8)
    padded[:, 1:-1] = m
    step = np.diff(padded, axis=1)
    rows, starts = np.nonzero(step == 1)
    _, ends = np.nonzero(step == -1)  # exclusive; same row-major order as the starts
    n = len(rows)
    if n == 0:
        return np.zeros((H, W), np.int64), np.zeros(0, np.int64)
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    row_ptr = np.searchsorted(rows, np.arange(H + 1)).tolist()
    s_list, e_list = starts.tolist(), ends.tolist()
    k = 1 if connectivity == 8 else 0  # diagonal neighbours touch when runs are one column apart
    for r in range(1, H):
        i, i_end = row_ptr[r - 1], row_ptr[r]
        j, j_end = row_ptr[r], row_ptr[r + 1]
        while i < i_end and j < j_end:
            if s_list[i] < e_list[j] + k and s_list[j] < e_list[i] + k:
                a, b = find(i), find(j)
                if a != b:
                    parent[max(a, b)] = min(a, b)
            if e_list[i] < e_list[j]:
                i += 1
            else:
                j += 1
    roots = np.array([find(a) for a in range(n)])
    _, run_label = np.unique(roots, return_inverse=True)
    run_label = run_label + 1
    sizes = np.bincount(run_label, weights=ends - starts)[1:].astype(np.int64)
    acc = np.zeros((H, W + 1), np.int64)
    np.add.at(acc, (rows, starts), run_label)
    np.add.at(acc, (rows, ends), -run_label)
    return np.cumsum(acc, axis=1)[:, :W], sizes


def largest_component(mask: np.ndarray, connectivity: int = 8) -> np.ndarray:
    """The largest connected component of a binary image (bool (H, W); all False if empty)."""
    labels, sizes = label_components(mask, connectivity)
    if len(sizes) == 0:
        return np.zeros(labels.shape, bool)
    return labels == (int(np.argmax(sizes)) + 1)


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill background regions that do not reach the image border (4-connected background)."""
    m = np.asarray(mask, bool)
    labels, sizes = label_components(~m, connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    hole = (labels > 0) & ~np.isin(labels, border)
    return m | hole


def otsu_threshold(values: np.ndarray, bins: int = OTSU_BINS) -> float:
    """Otsu's threshold of values in [0, 1]: the cut maximising the between-class variance."""
    v = np.clip(np.asarray(values, float).ravel(), 0.0, 1.0)
    hist, edges = np.histogram(v, bins=bins, range=(0.0, 1.0))
    p = hist / max(hist.sum(), 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(p)
    mu_cum = np.cumsum(p * centres)
    mu_t = mu_cum[-1]
    w1 = 1.0 - w0
    valid = (w0 > 0) & (w1 > 0)
    between = np.where(valid, (mu_t * w0 - mu_cum) ** 2 / np.where(valid, w0 * w1, 1.0), -1.0)
    return float(edges[int(np.argmax(between)) + 1])


# ----------------------------------------------------------------------------------------------
# Frames
# ----------------------------------------------------------------------------------------------

def foreground(frames: np.ndarray, background: str | np.ndarray = "median", threshold: float | None = None,
               invert: bool = False, polarity: str = "any", edges: str = "threshold") -> tuple[np.ndarray, float]:
    """Raw foreground masks (T, H, W) bool and the threshold used.

    frames: (T, H, W, C) in [0, 1]. background: 'median' (per-pixel median of up to MEDIAN_FRAMES
    frames), 'first', an image (H, W, C) in [0, 1] of the empty scene, or 'none' (threshold the
    brightness: foam brighter than the threshold, or darker with `invert`). threshold: None for Otsu.
    polarity (with a background): 'any' (the largest absolute channel difference), 'brighter' or
    'darker' (the largest signed one, 0 for the other sign). edges: 'half' (see `half_contrast_edges`)
    or 'threshold' (the thresholded score as it is).
    """
    if polarity not in POLARITIES:
        raise ValueError(f"polarity must be one of {POLARITIES}, got {polarity!r}")
    if edges not in EDGES:
        raise ValueError(f"edges must be one of {EDGES}, got {edges!r}")
    score = _score(frames, background, invert, polarity)
    if threshold is None:
        threshold = otsu_threshold(score)
    elif not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must lie in (0, 1) (a fraction of full intensity), got {threshold}")
    raw = score > threshold
    if edges == "half":
        raw = np.stack([half_contrast_edges(score[t], raw[t]) for t in range(len(raw))])
    return raw, float(threshold)


def _signed(diff: np.ndarray, polarity: str) -> np.ndarray:
    if polarity == "any":
        return np.abs(diff).max(axis=-1)
    return np.clip(diff if polarity == "brighter" else -diff, 0.0, None).max(axis=-1)


def _score(frames, background, invert, polarity):
    """The foreground score (T, H, W) in [0, 1] of `foreground`."""
    if isinstance(background, str):
        if background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {BACKGROUNDS} or an image, got {background!r}")
        if background == "none":
            score = frames.mean(axis=-1)
            if invert:
                score = 1.0 - score
        else:
            if background == "first":
                bg = frames[0]
            else:
                pick = np.unique(np.round(np.linspace(0, len(frames) - 1, min(len(frames), MEDIAN_FRAMES))).astype(int))
                bg = np.median(frames[pick], axis=0)
            score = _signed(frames - bg[None], polarity)
    else:
        bg = np.asarray(background, np.float32)
        if bg.ndim == 2:
            bg = bg[:, :, None]
        if bg.shape[:2] != frames.shape[1:3]:
            raise ValueError(f"background image has shape {bg.shape[:2]}, the frames {frames.shape[1:3]}")
        score = _signed(frames - bg[None], polarity)
    return score


def _box_sum(img: np.ndarray, r: int) -> np.ndarray:
    """Sum over the (2r+1)^2 window about each pixel (zeros beyond the image), by cumulative sums."""
    H, W = img.shape
    c = np.zeros((H + 2 * r + 1, W + 2 * r + 1))
    c[1:, 1:] = np.cumsum(np.cumsum(np.pad(img.astype(float), r), axis=0), axis=1)
    k = 2 * r + 1
    return c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]


def half_contrast_edges(score: np.ndarray, mask: np.ndarray, band: int = EDGE_BAND,
                        window: int = EDGE_WINDOW) -> np.ndarray:
    """Re-decide the pixels within `band` pixels of the edge of `mask` (bool (H, W), the thresholded
    `score` (H, W)): foam where the score is at least the mean of the local foam level (score over the
    mask eroded by `band`, in a window of half-width `window` + `band`) and the local background level
    (score outside the mask grown by `band`). A pixel with no level of either kind nearby keeps its value."""
    m = np.asarray(mask, bool)
    if not m.any() or m.all():
        return m.copy()
    inner, outer = erode(m, band), ~dilate(m, band)
    r = int(window) + int(band)
    n_in, n_out = _box_sum(inner, r), _box_sum(outer, r)
    level_in = _box_sum(np.where(inner, score, 0.0), r) / np.maximum(n_in, 1)
    level_out = _box_sum(np.where(outer, score, 0.0), r) / np.maximum(n_out, 1)
    decide = ~inner & ~outer & (n_in > 0) & (n_out > 0)
    out = m.copy()
    out[decide] = score[decide] >= 0.5 * (level_in[decide] + level_out[decide])
    return out


def clean_mask(mask: np.ndarray, open_radius: int = OPEN_RADIUS, close_radius: int = CLOSE_RADIUS,
               holes: bool = True) -> np.ndarray:
    """Opening, closing, largest 8-connected component, hole filling: bool (H, W)."""
    m = closing(opening(mask, open_radius), close_radius)
    m = largest_component(m)
    return fill_holes(m) if holes else m


def track_video(video: str | os.PathLike, pixel_size: float, origin, scene, *, background: str | np.ndarray = "median",
                threshold: float | None = None, invert: bool = False, polarity: str = "any", edges: str = "threshold",
                fps: float | None = None, t0: float = 0.0,
                every: int = 1, downsample: int = 1, max_frames: int | None = None, open_radius: int = OPEN_RADIUS,
                close_radius: int = CLOSE_RADIUS, holes: bool = True, plate_margin: int | None = PLATE_MARGIN,
                progress=None) -> Silhouettes:
    """Track the foam in a video: returns validated `Silhouettes` (write with `.write(path)`).

    Args:
      video: video/GIF file or image directory.  pixel_size: m per pixel of the source video.
      origin: (x0, y0), m: world position of the source image's bottom-left corner.
      scene: the scene description (path, JSON text or dict) stored with the data.
      background, threshold, invert, polarity, edges: see `foreground`.  fps: frame rate override.
      t0: time of the
      first frame since the start of the scene, s.  every, downsample, max_frames: see `read_frames`.
      open_radius, close_radius, holes: see `clean_mask`.  plate_margin: dilation of the plates'
      footprint, pixels (None: do not mask plates).
    """
    say = progress or (lambda msg: None)
    parsed = load_scene(scene if isinstance(scene, dict) else os.fspath(scene) if isinstance(scene, os.PathLike) else scene)
    frames, fps = read_frames(video, fps=fps, every=every, downsample=downsample, max_frames=max_frames)
    T, H, W = frames.shape[:3]
    say(f"read {T} frames of {H}x{W} pixels at {fps:g} fps")
    raw, thr = foreground(frames, background, threshold, invert, polarity, edges)
    say(f"foreground threshold {thr:.3f}")
    masks = np.stack([clean_mask(raw[t], open_radius, close_radius, holes) for t in range(T)]).astype(np.uint8)
    camera = Camera(pixel_size=float(pixel_size) * downsample, origin=tuple(float(v) for v in origin))
    times = float(t0) + np.arange(T) * every / fps
    weights = np.ones((T, H, W), np.float32)
    if plate_margin is not None and parsed.plates:
        for t in range(T):
            fp = dilate(plate_footprint(parsed, float(times[t]), camera, (H, W)), int(plate_margin))
            masks[t][fp] = 0
            weights[t][fp] = 0.0
    source = json.dumps(dict(generator="jaxfoam track", video=os.path.basename(os.fspath(video)), fps=fps,
                             every=every, downsample=downsample, threshold=thr,
                             background=background if isinstance(background, str) else "image",
                             invert=invert, polarity=polarity, edges=edges, open_radius=open_radius,
                             close_radius=close_radius, holes=holes,
                             plate_margin=plate_margin))
    empty = [t for t in range(T) if not masks[t].any()]
    if 0 in empty and parsed.initial_shape.get("type") == "first_mask":
        hint = (" (background 'first' takes the first frame as the empty scene: use 'median' or an image of "
                "the empty scene)" if isinstance(background, str) and background == "first" else "")
        raise ValueError(f"track: no foam found in the first frame, which the scene's initial_shape "
                         f"'first_mask' needs{hint}; threshold used {thr:.3f}")
    if empty:
        say(f"warning: no foam found in {len(empty)} frame(s), first at t = {times[empty[0]]:.3f} s")
    return validate(masks, times, camera, parsed.spec, weights=weights, source=source)
