"""Reading video: frames of a video or GIF file, or of a directory of images, as float arrays in [0, 1]."""
from __future__ import annotations

import math
import os

import numpy as np

from jaxfoam.video import ffmpeg_subprocess

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def average_pool(frame: np.ndarray, factor: int) -> np.ndarray:
    """Average-pool (H, W, C) by `factor`, cropping the top rows and right columns that do not fit
    (the image's bottom-left corner, the camera origin, stays put)."""
    if factor == 1:
        return frame.astype(np.float32)
    H, W = frame.shape[:2]
    Hc, Wc = H // factor, W // factor
    f = frame[H - Hc * factor:, :Wc * factor].astype(np.float32)
    return f.reshape(Hc, factor, Wc, factor, -1).mean(axis=(1, 3))


def read_frames(path: str | os.PathLike, fps: float | None = None, every: int = 1, downsample: int = 1,
                max_frames: int | None = None) -> tuple[np.ndarray, float]:
    """Read a video/GIF file or a directory of images: (frames (T, H, W, C) float32 in [0, 1], fps).

    fps: frames per second of the source (needed for an image directory; overrides the file's).
    every: keep one frame in `every`.  downsample: average-pool factor.  max_frames: stop after this many
    kept frames. The returned fps is that of the source (kept frame k is source frame k * every).
    """
    with ffmpeg_subprocess():  # a video file is decoded by an ffmpeg subprocess
        return _read_frames(path, fps, every, downsample, max_frames)


def _read_frames(path, fps, every, downsample, max_frames):
    import imageio.v3 as iio

    path = os.fspath(path)
    if every < 1 or downsample < 1:
        raise ValueError(f"every and downsample must be >= 1, got {every}, {downsample}")
    if os.path.isdir(path):
        names = sorted(f for f in os.listdir(path) if f.lower().endswith(IMAGE_EXTENSIONS))
        if not names:
            raise ValueError(f"video: directory {path!r} holds no image ({', '.join(IMAGE_EXTENSIONS)})")
        if fps is None:
            raise ValueError("fps: an image directory has no frame rate; pass --fps")
        source = (_read_image(iio, os.path.join(path, n)) for n in names)
    else:
        if not os.path.exists(path):
            raise ValueError(f"video: file {path!r} does not exist")
        if os.path.getsize(path) == 0:
            raise ValueError(f"video: file {path!r} is empty (0 bytes)")
        if fps is None:
            try:
                meta = iio.immeta(path)
            except Exception as exc:  # imageio raises many kinds for an unreadable file
                raise ValueError(f"video: cannot read {path!r} as a video or GIF ({type(exc).__name__}: {exc})") from exc
            if meta.get("fps"):
                fps = float(meta["fps"])
            elif meta.get("duration"):  # GIF: milliseconds per frame
                fps = 1000.0 / float(meta["duration"])
            else:
                raise ValueError(f"fps: {path!r} does not say its frame rate; pass --fps")
        source = _frames_of(iio, path)
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be > 0, got {fps}")
    kept = []
    for k, frame in enumerate(source):
        if k % every:
            continue
        f = np.asarray(frame)
        if f.ndim == 2:
            f = f[:, :, None]
        if f.shape[-1] == 4:
            f = f[:, :, :3]  # drop alpha
        scale = 65535.0 if f.dtype == np.uint16 else 255.0 if f.dtype.kind in "ui" else 1.0
        f = average_pool(f, downsample) / scale
        if kept and f.shape != kept[0].shape:
            raise ValueError(f"video: frame {k} has shape {f.shape[:2]}, the first {kept[0].shape[:2]}")
        kept.append(f)
        if max_frames is not None and len(kept) >= max_frames:
            break
    if not kept:
        raise ValueError(f"video: {path!r} holds no frame")
    return np.stack(kept), float(fps)


def _read_image(iio, path):
    try:
        return iio.imread(path)
    except Exception as exc:  # imageio raises many kinds for an unreadable file
        raise ValueError(f"video: cannot read image {path!r} ({type(exc).__name__}: {exc})") from exc


def _frames_of(iio, path):
    """The frames of a video file; a file imageio cannot decode is reported with its name."""
    try:
        yield from iio.imiter(path)
    except ValueError:
        raise
    except Exception as exc:  # imageio and its plugins raise OSError, RuntimeError, IndexError...
        raise ValueError(f"video: cannot read {path!r} as a video or GIF ({type(exc).__name__}: {exc})") from exc
