"""Silhouette rendering and the HDF5 writer of the spec (shared/specs/silhouettes.md, version 1).

Rendering: the material of a frame is the union of disks of radius DISK_SPACINGS particle spacings
about the particles (projected along -z in 3D: the projection of a union of balls is the union of their
disks), eroded by ERODE_SPACINGS spacings: a morphological closing that fills the gaps between jittered
or stretched particles yet puts the boundary half a spacing outside the outermost particles, where a
particle's own volume ends. It is drawn on a fine occupancy grid (sub-pixels at most half a particle
spacing), and a camera pixel is foam when at least half of its sub-pixels are (box downsampling).
Pixels under a plate's footprint get mask 0 and weight 0 (the plate hides the foam).
"""
from __future__ import annotations

import json
import math

import numpy as np

from ._jit import kernel

FORMAT, VERSION = "jaxfoam-silhouettes", 1
# Disk radius and erosion, in particle spacings: disks of 1.2 spacings close gaps up to ~2.4 spacings
# (stratified jitter puts neighbours up to ~2 apart); eroding by 0.7 leaves the edge 0.5 beyond them.
DISK_SPACINGS = 1.2
ERODE_SPACINGS = 0.7
# Sub-pixels per particle spacing (at least), and the largest supersampling per axis.
SUB_PER_SPACING = 2.0
MAX_SUPERSAMPLE = 16


class Camera:
    """Orthographic camera along -z: pixel_size m, origin (x0, y0) m (image bottom-left), shape (H, W)."""

    def __init__(self, pixel_size, origin, shape):
        self.pixel_size = float(pixel_size)
        self.origin = (float(origin[0]), float(origin[1]))
        self.shape = (int(shape[0]), int(shape[1]))

    @classmethod
    def covering(cls, lo, hi, pixel_size):
        """A camera whose image covers the box lo..hi (x, y), m."""
        W, H = (int(math.ceil((hi[k] - lo[k]) / pixel_size - 1e-9)) for k in range(2))
        return cls(pixel_size, (lo[0], lo[1]), (H, W))


@kernel
def _splat_disks(xy, radius, x0, y0, h, occ):
    """Set occ (rows from the bottom, columns) to 1 where a sub-pixel centre lies within radius (m) of a point xy (N, 2)."""
    ny, nx = occ.shape
    r2 = radius * radius
    for p in range(xy.shape[0]):
        cx, cy = xy[p, 0], xy[p, 1]
        j0 = max(int(math.floor((cx - radius - x0) / h)), 0)
        j1 = min(int(math.ceil((cx + radius - x0) / h)), nx - 1)
        i0 = max(int(math.floor((cy - radius - y0) / h)), 0)
        i1 = min(int(math.ceil((cy + radius - y0) / h)), ny - 1)
        for i in range(i0, i1 + 1):
            dy = y0 + (i + 0.5) * h - cy
            for j in range(j0, j1 + 1):
                dxp = x0 + (j + 0.5) * h - cx
                if dxp * dxp + dy * dy <= r2:
                    occ[i, j] = 1


@kernel
def _erode(occ, radius_cells, out):
    """out <- the cells of occ whose every cell within radius_cells (a disk) is set (cells beyond the edge count as set)."""
    ny, nx = occ.shape
    r = int(math.floor(radius_cells))
    r2 = radius_cells * radius_cells
    for i in range(ny):
        for j in range(nx):
            if occ[i, j] == 0:
                out[i, j] = 0
                continue
            keep = 1
            for a in range(-r, r + 1):
                ii = i + a
                if ii < 0 or ii >= ny:
                    continue
                for c in range(-r, r + 1):
                    jj = j + c
                    if a * a + c * c <= r2 and 0 <= jj < nx and occ[ii, jj] == 0:
                        keep = 0
                        break
                if keep == 0:
                    break
            out[i, j] = keep


def render_mask(x, spacing, camera):
    """Binary mask (H, W) uint8, row 0 at the top, of particles at x (N, d) m with mean spacing `spacing` m."""
    return (coverage(x, spacing, camera) >= 0.5).astype(np.uint8)


def coverage(x, spacing, camera):
    """Fraction (H, W) of each pixel covered by the material (row 0 at the top); see the module docstring."""
    H, W = camera.shape
    ss = int(min(MAX_SUPERSAMPLE, max(1, math.ceil(camera.pixel_size * SUB_PER_SPACING / spacing))))
    h = camera.pixel_size / ss
    occ = np.zeros((H * ss, W * ss), np.uint8)
    _splat_disks(np.ascontiguousarray(x[:, :2], float), DISK_SPACINGS * spacing, camera.origin[0],
                 camera.origin[1], h, occ)
    closed = np.empty_like(occ)
    _erode(occ, ERODE_SPACINGS * spacing / h, closed)
    return closed.reshape(H, ss, W, ss).mean(axis=(1, 3))[::-1]


def plate_pixels(camera, boxes):
    """Pixels (H, W) bool overlapping, even partly, any rectangle (lo (2,), hi (2,)) m; row 0 at the top."""
    H, W = camera.shape
    p = camera.pixel_size
    x0, y0 = camera.origin
    out = np.zeros((H, W), bool)
    for lo, hi in boxes:
        j0 = max(int(math.floor((lo[0] - x0) / p + 1e-9)), 0)
        j1 = min(int(math.ceil((hi[0] - x0) / p - 1e-9)), W)
        r_lo = max(int(math.floor((lo[1] - y0) / p + 1e-9)), 0)  # rows counted from the bottom
        r_hi = min(int(math.ceil((hi[1] - y0) / p - 1e-9)), H)
        if j1 > j0 and r_hi > r_lo:
            out[H - r_hi:H - r_lo, j0:j1] = True
    return out


def write(path, masks, times, camera, scene_spec, weights, source, truth):
    """Write a silhouette file: masks (T, H, W) uint8, times (T,) s, camera, the scene dict, weights
    (T, H, W) in [0, 1], source (dict, stored as JSON text) and truth (dict of parameters)."""
    import h5py

    masks = np.asarray(masks, np.uint8)
    times = np.asarray(times, np.float64)
    if masks.shape[0] != times.shape[0] or masks.shape[1:] != camera.shape:
        raise ValueError(f"masks {masks.shape} disagree with times {times.shape} / camera {camera.shape}")
    if not np.all(np.diff(times) > 0):
        raise ValueError("times must be strictly increasing")
    with h5py.File(path, "w") as fh:
        fh.attrs["format"] = FORMAT
        fh.attrs["version"] = VERSION
        fh.attrs["source"] = json.dumps(source)
        fh.create_dataset("masks", data=masks, compression="gzip", compression_opts=9, chunks=(1,) + masks.shape[1:])
        fh.create_dataset("times", data=times)
        fh.create_dataset("weights", data=np.asarray(weights, np.float32), compression="gzip",
                          compression_opts=9, chunks=(1,) + masks.shape[1:])
        cam = fh.create_group("camera")
        cam.attrs["model"] = "orthographic"
        cam.attrs["pixel_size"] = camera.pixel_size
        cam.attrs["origin"] = np.asarray(camera.origin, np.float64)
        cam.attrs["axis"] = "z"
        fh.create_group("scene").attrs["json"] = json.dumps(scene_spec)
        tr = fh.create_group("truth")
        for k, v in truth.items():
            tr.attrs[k] = float(v)


def read_back(path):
    """Read a file with the calibration package's reader, which validates it against the spec."""
    from fitting.io import read_silhouettes
    return read_silhouettes(path)
