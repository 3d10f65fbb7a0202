"""The silhouette dataset format (shared/specs/silhouettes.md, version 1): read, validate, write.

One experiment is one HDF5 file::

    /          attrs format = "jaxfoam-silhouettes", version = 1, source (free text)
    /masks     uint8 (T, H, W), 1 = foam seen; row 0 is the TOP of the image
    /times     float64 (T,), s since the start of the scene, strictly increasing (gaps allowed)
    /weights   optional float32 (T, H, W) or (H, W), per-pixel confidence in [0, 1] (0 = ignore)
    /camera    attrs model = "orthographic", pixel_size (m), origin [x0, y0] (m, the image's
               bottom-left corner in the world), axis = "z" (looks along -z: right = +x, up = +y)
    /scene     attrs json = the scene description (parsed by `jaxfoam.load_scene`)
    /truth     optional attrs: parameters that generated synthetic data (recovery studies only)

Every check of the spec is made on read and on write, so a file this module wrote is one it reads.
Each failure is a `SilhouetteFormatError` (a ValueError) naming the file and the field.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from typing import Any, Mapping

import numpy as np

from jaxfoam import JaxfoamError, Scene, load_scene
from jaxfoam.guards import discard, publish, temporary_path

FORMAT = "jaxfoam-silhouettes"
VERSION = 1
CAMERA_MODEL = "orthographic"
CAMERA_AXIS = "z"
# gzip level 4: masks are long runs of 0 and 1 and compress ~50x; higher levels gain little and cost time.
GZIP_LEVEL = 4
# Round-off allowance, in pixels, when a box edge falls on a pixel boundary.
EDGE_TOL = 1e-9


class SilhouetteFormatError(JaxfoamError, ValueError):
    """A silhouette file or array set that does not follow the format; the message names the field."""


def _fail(where: str, field: str, msg: str):
    raise SilhouetteFormatError(f"{where}: field '{field}': {msg}")


@dataclasses.dataclass(frozen=True)
class Camera:
    """The orthographic camera of the format.

    Attributes:
      pixel_size: metres per pixel (square pixels), > 0.
      origin: (x0, y0), m: world position of the image's bottom-left corner.
      axis: "z" (the camera looks along -z; image right = world +x, image up = world +y).
      model: "orthographic".
    Pixel (row i, column j) of an image with H rows covers x in [x0 + j p, x0 + (j + 1) p] and
    y in [y0 + (H - 1 - i) p, y0 + (H - i) p].
    """

    pixel_size: float
    origin: tuple
    axis: str = CAMERA_AXIS
    model: str = CAMERA_MODEL

    def as_dict(self) -> dict:
        """The camera as the plain dict `jaxfoam.init_state(first_mask=(mask, camera))` expects."""
        return dict(model=self.model, pixel_size=self.pixel_size, origin=list(self.origin), axis=self.axis)

    def pixel_centers(self, shape) -> tuple[np.ndarray, np.ndarray]:
        """World coordinates of pixel centres for an image of shape (H, W): x (W,) m, y (H,) m (row order)."""
        H, W = shape
        p = self.pixel_size
        x = self.origin[0] + (np.arange(W) + 0.5) * p
        y = self.origin[1] + (H - 1 - np.arange(H) + 0.5) * p
        return x, y

    def extent(self, shape) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max), m, of an image of shape (H, W) (matplotlib's `extent` order)."""
        H, W = shape
        x0, y0 = self.origin
        return x0, x0 + W * self.pixel_size, y0, y0 + H * self.pixel_size

    def scaled(self, factor: int) -> "Camera":
        """The camera of the same image downsampled by an integer `factor` (pixels factor times larger)."""
        return dataclasses.replace(self, pixel_size=self.pixel_size * factor)


def camera_covering(scene: Scene, pixel_size: float) -> tuple[Camera, tuple[int, int]]:
    """A camera whose image covers the scene domain's (x, y) extent: (camera, (H, W)).

    The origin is the domain's lower-left corner; H, W are rounded up so the image reaches the
    domain's upper and right edges.
    """
    if not (pixel_size > 0 and math.isfinite(pixel_size)):
        raise ValueError(f"pixel_size must be a positive length in m, got {pixel_size!r}")
    lo = np.asarray(scene.domain_min[:2], float)
    hi = np.asarray(scene.domain_max[:2], float)
    # EDGE_TOL keeps an exact multiple of the pixel size from gaining an empty extra row or column.
    W, H = (int(math.ceil((hi[k] - lo[k]) / pixel_size - EDGE_TOL)) for k in range(2))
    return Camera(pixel_size=float(pixel_size), origin=(float(lo[0]), float(lo[1]))), (H, W)


def plate_footprint(scene: Scene, t: float, camera: Camera, shape) -> np.ndarray:
    """Pixels covered, even partly, by any plate of the scene at time t (s): bool (H, W).

    The plate box (centre `Plate.position(t)`, half_size) is projected along the camera axis
    (z dropped in 3D); a pixel counts when its square overlaps the projected rectangle.
    """
    out = np.zeros(tuple(shape), bool)
    for plate in scene.plates:
        box = _plate_box_pixels(plate, t, camera, shape)
        if box is not None:
            r0, r1, c0, c1 = box
            out[r0:r1, c0:c1] = True
    return out


def _plate_box_pixels(plate, t: float, camera: Camera, shape) -> tuple[int, int, int, int] | None:
    """(top row, bottom row exclusive, first column, last column exclusive) of the pixels a plate covers at
    time t (s), clipped to the image (row 0 at the top); None when it covers none."""
    H, W = shape
    p = camera.pixel_size
    x0, y0 = camera.origin
    c = np.asarray(plate.position(t), float)[:2]
    h = np.asarray(plate.half_size, float)[:2]
    # EDGE_TOL: an edge on a pixel boundary (up to round-off) does not claim the next pixel.
    j_lo = max(int(math.floor((c[0] - h[0] - x0) / p + EDGE_TOL)), 0)
    j_hi = min(int(math.ceil((c[0] + h[0] - x0) / p - EDGE_TOL)), W)  # exclusive
    r_lo = max(int(math.floor((c[1] - h[1] - y0) / p + EDGE_TOL)), 0)  # rows counted from the bottom
    r_hi = min(int(math.ceil((c[1] + h[1] - y0) / p - EDGE_TOL)), H)
    if j_lo < j_hi and r_lo < r_hi:
        return H - r_hi, H - r_lo, j_lo, j_hi
    return None


def glue_under_plates(scene: Scene, mask: np.ndarray, camera: Camera, t: float,
                      weights: np.ndarray | None = None) -> np.ndarray:
    """The first mask with the foam a sticky plate holds, and hides, filled in: uint8 (H, W).

    A camera cannot see foam where a plate covers it (those pixels are 0 in a mask, weight 0), yet a
    sticky plate only holds material that reaches its nodes: foam seeded from the visible pixels alone
    ends at the plate's face and grips it by less than a cell, by an amount that changes with dx (the
    grip, and the moment hanging foam tears off, then follow the grid, not the foam). Foam that nothing
    below supports at the start (a connected piece of the mask that does not reach the floor, or the
    domain's bottom without one) hangs from the plates it meets. So, for each sticky plate at time t (s),
    and each such unsupported piece, every pixel column of the plate whose first foam pixel below the
    plate's bottom face belongs to that piece is continued up through the plate's covered rows, and every
    row of the plate whose first foam pixel beside a side face does, through its covered columns. Between
    the face and that pixel there may only be ignored pixels (weight 0: `jaxfoam track` blanks a margin of
    PLATE_MARGIN pixels around each plate), which are filled too; with no weights given, the foam must
    touch the face. Foam resting on the floor (say, under a plate about to squeeze it) or on a plate's
    top face is left as it is, as are non-sticky plates.
    """
    from .track import label_components  # the tracker's labeling (track imports this module)

    m = np.asarray(mask).astype(bool)
    out = m.copy()
    H, W = m.shape
    ignored = np.zeros((H, W), bool) if weights is None else (np.asarray(weights) <= 0) & ~m
    sticky = [pl for pl in scene.plates if pl.sticky]
    if not sticky or not m.any():
        return out.astype(np.uint8)
    labels, sizes = label_components(m, 8)
    # each piece's lowest row (rows run downwards), and the y (m) of that row's lower edge: a piece
    # reaching within a pixel of the floor rests on it
    lowest = np.zeros(len(sizes) + 1, np.int64)
    np.maximum.at(lowest, labels[m], np.nonzero(m)[0])
    p, y0 = camera.pixel_size, camera.origin[1]
    floor = scene.floor_y if scene.floor_y is not None else scene.domain_min[1]
    hangs = y0 + (H - 1 - lowest) * p > floor + p
    hangs[0] = False  # background
    hanging = hangs[labels]

    def reach(line_mask, line_ignored):
        """Index of the first pixel along a line (from the face outwards) past ignored pixels, and whether
        it holds hanging foam."""
        k = 0
        while k < len(line_mask) and line_ignored[k]:
            k += 1
        return k, k < len(line_mask) and bool(line_mask[k])

    for plate in sticky:
        box = _plate_box_pixels(plate, t, camera, (H, W))
        if box is None:
            continue
        r0, r1, c0, c1 = box
        for c in range(c0, c1):  # below the bottom face (rows run downwards)
            k, hit = reach(hanging[r1:, c], ignored[r1:, c])
            if hit:
                out[r0:r1 + k, c] = True
        for r in range(r0, r1):  # beside the side faces
            k, hit = reach(hanging[r, c0 - 1::-1] if c0 > 0 else hanging[r, :0],
                           ignored[r, c0 - 1::-1] if c0 > 0 else ignored[r, :0])
            if hit:
                out[r, c0 - k:c1] = True
            k, hit = reach(hanging[r, c1:], ignored[r, c1:])
            if hit:
                out[r, c0:c1 + k] = True
    return out.astype(np.uint8)


@dataclasses.dataclass(frozen=True)
class Silhouettes:
    """A silhouette dataset in memory (validated).

    Attributes:
      masks: uint8 (T, H, W), 1 where foam is seen; row 0 is the top of the image.
      times: float64 (T,), s since the start of the scene, strictly increasing.
      weights: float32 (T, H, W) in [0, 1] (a stored (H, W) array is broadcast; ones when absent).
      camera: the `Camera`.
      scene_json: the scene description, JSON text.
      source: free text saying where the data came from.
      truth: dict of the parameters that generated synthetic data (mu, sigma_y, eta, m, kappa, ...),
        or None. For recovery studies only: a fitter never reads it.
    """

    masks: np.ndarray
    times: np.ndarray
    weights: np.ndarray
    camera: Camera
    scene_json: str
    source: str = ""
    truth: dict | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """(T, H, W)."""
        return tuple(self.masks.shape)

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W)."""
        return tuple(self.masks.shape[1:])

    @property
    def scene_dict(self) -> dict:
        """The scene description as a dict."""
        return json.loads(self.scene_json)

    def load_scene(self, **kwargs) -> Scene:
        """The parsed scene (`jaxfoam.load_scene`)."""
        return load_scene(self.scene_json, **kwargs)

    @property
    def first_mask(self) -> tuple[np.ndarray, dict]:
        """(mask, camera dict): the `first_mask` argument of `jaxfoam.init_state` / `Simulator`, the first
        frame's mask with the foam that hangs from its sticky plates filled in where they hide it
        (`glue_under_plates`, at the first frame's time, with its weights)."""
        mask = glue_under_plates(self.load_scene(), self.masks[0], self.camera, float(self.times[0]),
                                 self.weights[0])
        return mask, self.camera.as_dict()

    def write(self, path: str | os.PathLike) -> None:
        """Write this dataset to `path` (see `write_silhouettes`)."""
        write_silhouettes(path, self.masks, self.times, self.camera, self.scene_json, weights=self.weights,
                          source=self.source, truth=self.truth)


# ----------------------------------------------------------------------------------------------
# Validation (shared by reader and writer)
# ----------------------------------------------------------------------------------------------

def _check_camera(camera: Any, where: str) -> Camera:
    if isinstance(camera, Camera):
        camera = camera.as_dict()
    if not isinstance(camera, Mapping):
        _fail(where, "camera", f"expected a Camera or a dict of attributes, got {type(camera).__name__}")
    for key in ("model", "pixel_size", "origin", "axis"):
        if key not in camera:
            _fail(where, f"camera.{key}", "required attribute missing")
    model = _as_str(camera["model"])
    if model != CAMERA_MODEL:
        _fail(where, "camera.model", f"must be '{CAMERA_MODEL}', got {model!r}")
    axis = _as_str(camera["axis"])
    if axis != CAMERA_AXIS:
        _fail(where, "camera.axis", f"must be '{CAMERA_AXIS}' (the camera looks along -z), got {axis!r}")
    try:
        p = float(np.asarray(camera["pixel_size"], float).reshape(()))
    except (TypeError, ValueError):
        _fail(where, "camera.pixel_size", f"expected one number (m per pixel), got {camera['pixel_size']!r}")
    if not math.isfinite(p) or p <= 0:
        _fail(where, "camera.pixel_size", f"must be a finite length > 0 m, got {p}")
    try:
        origin = np.asarray(camera["origin"], float)
    except (TypeError, ValueError):
        _fail(where, "camera.origin", f"expected 2 numbers [x0, y0] in m, got {camera['origin']!r}")
    if origin.shape != (2,):
        _fail(where, "camera.origin", f"expected 2 numbers [x0, y0] in m, got shape {origin.shape}")
    if not np.all(np.isfinite(origin)):
        _fail(where, "camera.origin", f"values must be finite, got {origin.tolist()}")
    return Camera(pixel_size=p, origin=(float(origin[0]), float(origin[1])))


def _as_str(v) -> str:
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray) and v.shape == ():
        return _as_str(v.item())
    return v if isinstance(v, str) else repr(v)


def _check_scene(scene: Any, where: str) -> tuple[str, Scene]:
    if isinstance(scene, Scene):
        text = scene.source
    elif isinstance(scene, Mapping):
        text = json.dumps(scene)
    elif isinstance(scene, (str, bytes)):
        text = _as_str(scene)
    else:
        _fail(where, "scene.json", f"expected JSON text or a dict, got {type(scene).__name__}")
    try:
        spec = json.loads(text)
    except json.JSONDecodeError as exc:
        _fail(where, "scene.json", f"not valid JSON ({exc})")
    if not isinstance(spec, dict):
        _fail(where, "scene.json", f"expected a JSON object (the scene description), got {type(spec).__name__}")
    try:
        parsed = load_scene(spec)
    except ValueError as exc:
        _fail(where, "scene.json", str(exc))
    return text, parsed


def _check_arrays(masks, times, weights, where: str):
    masks = np.asarray(masks)
    if masks.ndim != 3:
        _fail(where, "masks", f"expected a (T, H, W) array, got shape {masks.shape}")
    T, H, W = masks.shape
    if T < 1 or H < 1 or W < 1:
        _fail(where, "masks", f"needs at least one frame of at least 1x1 pixels, got shape {masks.shape}")
    if masks.dtype.kind == "f":
        if not np.all(np.isfinite(masks)):
            _fail(where, "masks", "values must be finite (and 0 or 1)")
    elif masks.dtype.kind not in "biu":
        _fail(where, "masks", f"expected uint8 values 0 or 1, got dtype {masks.dtype}")
    bad = (masks != 0) & (masks != 1)
    if bad.any():
        t, i, j = np.argwhere(bad)[0]
        _fail(where, "masks", f"values must be 0 or 1 (uint8); frame {t} pixel ({i}, {j}) holds {masks[t, i, j].item()!r}")
    masks = masks.astype(np.uint8)

    times = np.asarray(times)
    if times.dtype.kind not in "biuf":
        _fail(where, "times", f"expected numbers in s, got dtype {times.dtype}")
    times = times.astype(np.float64)
    if times.ndim != 1 or times.shape[0] != T:
        _fail(where, "times", f"expected shape ({T},) to match masks (T, H, W) = {masks.shape}, got {times.shape}")
    if not np.all(np.isfinite(times)):
        _fail(where, "times", f"values must be finite, got {times[~np.isfinite(times)][:3].tolist()}")
    if times[0] < 0:
        _fail(where, "times", f"are seconds since the start of the scene and must be >= 0, got {times[0]}")
    steps = np.diff(times)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        _fail(where, "times", f"must be strictly increasing; times[{k}] = {times[k]} s, "
                              f"times[{k + 1}] = {times[k + 1]} s")

    if weights is None:
        weights = np.ones((T, H, W), np.float32)
    else:
        weights = np.asarray(weights)
        if weights.dtype.kind not in "biuf":
            _fail(where, "weights", f"expected numbers in [0, 1], got dtype {weights.dtype}")
        if weights.shape not in ((T, H, W), (H, W)):
            _fail(where, "weights", f"expected shape (T, H, W) = {(T, H, W)} or (H, W) = {(H, W)} to match "
                                    f"masks, got {weights.shape}")
        weights = weights.astype(np.float32)
        if not np.all(np.isfinite(weights)):
            _fail(where, "weights", "values must be finite")
        if weights.min() < 0 or weights.max() > 1:
            _fail(where, "weights", f"values must lie in [0, 1], got range [{weights.min()}, {weights.max()}]")
        weights = np.broadcast_to(weights, (T, H, W)).copy()
    return masks, times, weights


def _check_truth(truth: Any, where: str) -> dict | None:
    if truth is None:
        return None
    if not isinstance(truth, Mapping):
        _fail(where, "truth", f"expected a dict of parameter values, got {type(truth).__name__}")
    out = {}
    for k, v in truth.items():
        arr = np.asarray(v)
        if arr.dtype.kind in "SUO":
            out[str(k)] = _as_str(v)
            continue
        if arr.dtype.kind not in "biuf" or arr.size != 1 or not np.isfinite(arr.astype(float)).all():
            _fail(where, f"truth.{k}", f"expected one finite number, got {v!r}")
        out[str(k)] = float(arr.reshape(()))
    return out


def validate(masks, times, camera, scene, weights=None, source: str = "", truth=None,
             where: str = "silhouettes") -> Silhouettes:
    """Check arrays and metadata against the format and return a `Silhouettes`.

    Checks: masks (T, H, W) of 0/1 values; times (T,) finite, >= 0, strictly increasing; weights
    (T, H, W) or (H, W), finite, in [0, 1]; camera model 'orthographic', axis 'z', pixel_size > 0,
    origin two finite numbers; the camera's image overlaps the scene domain in (x, y); the scene
    JSON parses and passes `jaxfoam.load_scene` (unknown kind or key is an error); truth values are
    finite numbers. Raises SilhouetteFormatError naming the field.
    """
    masks, times, weights = _check_arrays(masks, times, weights, where)
    cam = _check_camera(camera, where)
    text, parsed = _check_scene(scene, where)
    x_lo, x_hi, y_lo, y_hi = cam.extent(masks.shape[1:])
    dmin, dmax = parsed.domain_min, parsed.domain_max
    if x_hi <= dmin[0] or x_lo >= dmax[0] or y_hi <= dmin[1] or y_lo >= dmax[1]:
        _fail(where, "camera", f"the image covers x in [{x_lo:.4g}, {x_hi:.4g}] m, y in [{y_lo:.4g}, {y_hi:.4g}] m, "
                               f"which misses the scene domain x in [{dmin[0]:.4g}, {dmax[0]:.4g}], "
                               f"y in [{dmin[1]:.4g}, {dmax[1]:.4g}] m: check camera.origin and "
                               f"camera.pixel_size (metres, not pixels or mm)")
    if parsed.initial_shape.get("type") == "first_mask" and not masks[0].any():
        _fail(where, "masks", "the scene's initial_shape is 'first_mask' but the first mask holds no foam pixel")
    if not isinstance(source, (str, bytes)):
        _fail(where, "source", f"expected free text, got {type(source).__name__}")
    return Silhouettes(masks=masks, times=times, weights=weights, camera=cam, scene_json=text,
                       source=_as_str(source), truth=_check_truth(truth, where))


# ----------------------------------------------------------------------------------------------
# HDF5
# ----------------------------------------------------------------------------------------------

def read_silhouettes(path: str | os.PathLike) -> Silhouettes:
    """Read and validate a silhouette file.

    Returns a `Silhouettes` (weights broadcast to (T, H, W); ones when the file has none). The
    `truth` group, if present, is returned as a dict for recovery studies; fitters must not read it.
    Raises SilhouetteFormatError (a ValueError) naming the file and the offending field.
    """
    import h5py

    where = os.fspath(path)
    try:
        fh = h5py.File(where, "r")
    except OSError as exc:
        raise SilhouetteFormatError(f"{where}: cannot open as HDF5 ({exc})") from exc
    with fh:
        fmt = _as_str(fh.attrs.get("format", "<missing>"))
        if fmt != FORMAT:
            _fail(where, "format", f"root attribute must be '{FORMAT}', got {fmt!r}")
        version = fh.attrs.get("version", None)
        if version is None:
            _fail(where, "version", "root attribute missing")
        try:
            version_ok = int(np.asarray(version).reshape(())) == VERSION
        except (TypeError, ValueError):
            version_ok = False
        if not version_ok:
            _fail(where, "version", f"this reader understands version {VERSION}, got "
                                    f"{version.item() if isinstance(version, np.generic) else version!r}")
        for name in ("masks", "times"):
            if name not in fh or not isinstance(fh[name], h5py.Dataset):
                _fail(where, name, "required dataset missing")
        def read(name):
            try:
                return fh[name][()]
            except (OSError, ValueError) as exc:  # a chunk that fails to decompress: h5py's OSError
                _fail(where, name, f"cannot be read: the file is damaged or truncated ({exc})")

        masks = read("masks")
        times = read("times")
        weights = None
        if "weights" in fh:
            if not isinstance(fh["weights"], h5py.Dataset):
                _fail(where, "weights", "expected a dataset")
            weights = read("weights")
        if "camera" not in fh:
            _fail(where, "camera", "required group missing")
        camera = {k: fh["camera"].attrs[k] for k in fh["camera"].attrs}
        if "scene" not in fh or "json" not in fh["scene"].attrs:
            _fail(where, "scene.json", "required attribute missing (group /scene, attribute json)")
        scene_json = _as_str(fh["scene"].attrs["json"])
        source = _as_str(fh.attrs.get("source", ""))
        truth = {k: fh["truth"].attrs[k] for k in fh["truth"].attrs} if "truth" in fh else None
    if not isinstance(scene_json, str) or not scene_json.strip():
        _fail(where, "scene.json", "expected a non-empty JSON string")
    return validate(masks, times, camera, scene_json, weights=weights, source=source, truth=truth, where=where)


def write_silhouettes(path: str | os.PathLike, masks, times, camera, scene, *, weights=None, source: str = "",
                      truth: Mapping | None = None) -> Silhouettes:
    """Validate and write a silhouette file; returns the validated `Silhouettes`.

    Args:
      path: output .h5 file (overwritten).
      masks: (T, H, W) 0/1 values (stored as uint8), row 0 = top of the image.
      times: (T,) s since the start of the scene, strictly increasing.
      camera: a `Camera` or a dict with model, pixel_size (m), origin [x0, y0] (m), axis.
      scene: the scene description (JSON text, dict, or a parsed `Scene`).
      weights: None (not stored: all pixels count fully), (H, W) or (T, H, W) in [0, 1]. An array
        equal in every frame is stored once as (H, W).
      source: free text (how the data was made).
      truth: parameters that generated synthetic data (mu, sigma_y, eta, m, kappa, ...), or None.
    """

    where = os.fspath(path)
    given_weights = weights
    data = validate(masks, times, camera, scene, weights=weights, source=source, truth=truth, where=where)
    if os.path.isdir(where):
        raise SilhouetteFormatError(f"{where}: is a directory; give a file path")
    tmp = temporary_path(where)  # written beside the output, then renamed: never half a file at `path`
    try:
        _write_h5(tmp, data, given_weights)
    except BaseException:
        discard(tmp)
        raise
    publish(tmp, where)
    return data


def _write_h5(where, data: Silhouettes, given_weights) -> None:
    import h5py

    with h5py.File(where, "w") as fh:
        fh.attrs["format"] = FORMAT
        fh.attrs["version"] = VERSION
        fh.attrs["source"] = data.source
        fh.create_dataset("masks", data=data.masks, compression="gzip", compression_opts=GZIP_LEVEL)
        fh.create_dataset("times", data=data.times)
        if given_weights is not None:
            w = data.weights
            if np.all(w == w[:1]):
                w = w[0]
            fh.create_dataset("weights", data=w, compression="gzip", compression_opts=GZIP_LEVEL)
        cam = fh.create_group("camera")
        cam.attrs["model"] = data.camera.model
        cam.attrs["pixel_size"] = data.camera.pixel_size
        cam.attrs["origin"] = np.asarray(data.camera.origin, np.float64)
        cam.attrs["axis"] = data.camera.axis
        fh.create_group("scene").attrs["json"] = data.scene_json
        if data.truth is not None:
            tr = fh.create_group("truth")
            for k, v in data.truth.items():
                tr.attrs[k] = v
