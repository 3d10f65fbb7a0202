"""Shaded pictures of a frame's surface, in numpy: a z-buffered triangle rasterizer for 3D, an
embossed fill of the outline for 2D; the floor, the plates and any SDF colliders drawn with the foam.

3D: an orthographic camera at (azimuth, elevation) looks at the region the foam and the plates occupy;
the foam mesh (jaxfoam._surface), the floor (a checkered plane, for depth), the plates (boxes) and the
colliders (marching cubes of their phi over the view's box) are rasterized at SUPERSAMPLE times the resolution with a depth buffer, shaded with Lambert's law plus
an ambient term, with shadows from a second depth buffer seen from the light, then averaged down.
2D: the volume fraction's ISO_LEVEL line bounds the fill (anti-aliased over one pixel); the fill is
lit as a relief whose height is the volume fraction, so its rim is shaded like a rounded edge.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import _surface

# Rendered at this many samples per pixel and axis, then averaged: smooth silhouette edges.
SUPERSAMPLE = 2
# Lambert shading: colour = base (AMBIENT + DIFFUSE max(n.l, 0) lit); the ambient keeps shadows readable.
AMBIENT = 0.32
DIFFUSE = 0.75
# The light, in the camera's frame (right, up, towards the viewer): from the upper left, in front;
# a weak unshadowed fill light from the right keeps faces turned from the light readable.
LIGHT_IN_CAMERA = (-0.5, 0.7, 0.6)
FILL_IN_CAMERA = (0.8, 0.1, 0.6)
FILL = 0.2
# 2D: the light (x right, y up, out of the page), more frontal so the flat interior reads white.
LIGHT_2D = (-0.45, 0.55, 0.7)
FOAM_RGB = (0.96, 0.95, 0.91)  # shaving cream: warm white
FLOOR_RGB = ((0.60, 0.61, 0.63), (0.68, 0.69, 0.71))  # checker squares
PLATE_RGB = (0.36, 0.27, 0.21)  # the particle view's PLATE_COLOR
COLLIDER_RGB = (0.62, 0.55, 0.47)  # SDF colliders (a face, crackers): lighter than the plates
# Marching-cubes cells along the view box's longest side for an SDF collider's surface.
COLLIDER_CELLS = 96
SKY_RGB = ((0.93, 0.95, 0.97), (0.80, 0.84, 0.88))  # background, top to bottom
# The view spans the foam and the plates over the shown frames plus this fraction on each side.
VIEW_MARGIN = 0.12
# Floor squares: about this many across the view, rounded to 1, 2 or 5 x 10^k m.
FLOOR_SQUARES = 10
# Shadow map resolution along its longer side, samples; its depth bias in shadow-map samples.
SHADOW_SIZE = 1024
SHADOW_BIAS = 2.0
# 2D relief: the rim rounds over this many mean particle spacings (and rises by twice that).
RELIEF = 1.5
# Picture height / width: the view's own, within this range.
ASPECT_RANGE = (0.45, 1.2)
# Rasterizer windows are rounded up to this many pixels per side (fewer batches, little waste).
WINDOW_STEP = 4
# Triangle-pixel tests per rasterizer batch (bounds the work arrays to ~100 MB).
BATCH = 2_000_000


@dataclasses.dataclass(frozen=True)
class Camera:
    """An orthographic camera: azimuth (deg) about the vertical y axis, from +z towards +x; elevation
    (deg) above the horizontal plane. (0, 0) looks along -z like the silhouette camera."""

    azimuth: float = 30.0
    elevation: float = 25.0

    def basis(self) -> np.ndarray:
        """Rows: right, up, towards the viewer (3, 3), unit vectors in world coordinates."""
        a, e = math.radians(self.azimuth), math.radians(self.elevation)
        w = np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
        r = np.cross([0.0, 1.0, 0.0], w)
        r /= np.linalg.norm(r)
        return np.stack([r, np.cross(w, r), w])


def nice_length(span: float) -> float:
    """The 1, 2 or 5 x 10^k m length nearest below span."""
    k = 10.0 ** math.floor(math.log10(span))
    return max(m * k for m in (1.0, 2.0, 5.0) if m * k <= span)


def rasterize(xy: np.ndarray, depth: np.ndarray, width: int, height: int):
    """Nearest triangle per pixel: xy (f, 3, 2) pixel coordinates (x right, y down), depth (f, 3) larger
    nearer. Returns triangle ids (height, width) int (-1: none) and depth (height, width)."""
    ids = np.full(width * height, -1, np.int64)
    zbuf = np.full(width * height, -np.inf)
    lo = np.clip(np.floor(xy.min(1)).astype(np.int64), 0, [width, height])
    hi = np.clip(np.ceil(xy.max(1)).astype(np.int64), 0, [width, height])
    size = hi - lo  # (f, 2) bounding boxes, pixels
    e1, e2 = xy[:, 1] - xy[:, 0], xy[:, 2] - xy[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = (size.min(1) > 0) & (np.abs(det) > 1e-12)
    # Triangles are tested in batches of one window size; windows round up to WINDOW_STEP pixels.
    window = np.where(ok[:, None], -(-size // WINDOW_STEP) * WINDOW_STEP, 0)
    for kx, ky in np.unique(window[ok], axis=0):
        tris = np.nonzero(ok & (window[:, 0] == kx) & (window[:, 1] == ky))[0]
        oy, ox = np.divmod(np.arange(kx * ky), kx)
        per = max(1, BATCH // (kx * ky))
        for start in range(0, len(tris), per):
            t = tris[start:start + per]
            px = lo[t, 0, None] + ox[None]
            py = lo[t, 1, None] + oy[None]
            dx = px + 0.5 - xy[t, 0, 0, None]
            dy = py + 0.5 - xy[t, 0, 1, None]
            l1 = (dx * e2[t, 1, None] - dy * e2[t, 0, None]) / det[t, None]
            l2 = (dy * e1[t, 0, None] - dx * e1[t, 1, None]) / det[t, None]
            inside = (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1) & (px < hi[t, 0, None]) & (py < hi[t, 1, None])
            z = depth[t, 0, None] + l1 * (depth[t, 1] - depth[t, 0])[:, None] + l2 * (depth[t, 2] - depth[t, 0])[:, None]
            pix, z, tri = (py * width + px)[inside], z[inside], np.broadcast_to(t[:, None], inside.shape)[inside]
            np.maximum.at(zbuf, pix, z)
            won = z >= zbuf[pix]  # this batch holds the nearest fragment of these pixels so far
            ids[pix[won]] = tri[won]
    return ids.reshape(height, width), zbuf.reshape(height, width)


def barycentric(xy: np.ndarray, tri: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Barycentric weights (n, 3) of pixel centres (px + 1/2, py + 1/2) in triangles xy[tri]."""
    a, b, c = xy[tri, 0], xy[tri, 1], xy[tri, 2]
    e1, e2 = b - a, c - a
    d = np.stack([px + 0.5, py + 0.5], 1) - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    l1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
    l2 = (d[:, 1] * e1[:, 0] - d[:, 0] * e1[:, 1]) / det
    return np.stack([1.0 - l1 - l2, l1, l2], 1)


def _box_triangles(center, half) -> np.ndarray:
    """The 12 triangles (12, 3, 3) of an axis-aligned box, m."""
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    p = np.asarray(center, float) + corners * np.asarray(half, float)
    quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    return np.array([[p[q[0]], p[q[i]], p[q[i + 1]]] for q in quads for i in (1, 2)])


class View:
    """The region a picture shows and its pixel mapping, fixed for every frame of one sheet or video."""

    def __init__(self, traj, indices, width: int, height: int | None = None, camera: Camera | None = None,
                 multiple: int = 1, colliders=()):
        """width px; height px (default: the view's aspect, within ASPECT_RANGE); both rounded up to
        `multiple` (a video encoder's block size); colliders: objects with `phi(x, t)` (m, s ->
        m; `jaxfoam.sdf.SDFCollider`) drawn where phi < 0 inside the view."""
        self.traj, self.scene, self.dim = traj, traj.scene, traj.dim
        self.colliders = tuple(colliders)
        self.camera = camera or Camera()
        act = np.asarray(traj.frames["active"][indices], bool)
        pts = [np.asarray(traj.frames["x"][indices], np.float64)[act]]
        for plate in self.scene.plates:
            for k in indices:
                c = np.asarray(plate.position(float(traj.times[k])), float)
                pts.append(np.stack([c - np.asarray(plate.half_size), c + np.asarray(plate.half_size)]))
        pts = np.concatenate(pts)
        lo, hi = pts.min(0), pts.max(0)
        floor = self.scene.floor_y
        if floor is not None:
            lo[1] = min(lo[1], floor)
        pad = VIEW_MARGIN * float(np.max(hi - lo))
        dmin, dmax = np.asarray(self.scene.domain_min, float), np.asarray(self.scene.domain_max, float)
        self.lo = np.maximum(lo - pad, dmin - pad)
        self.hi = np.minimum(hi + pad, dmax + pad)
        if floor is not None:
            self.lo[1] = floor - (pad if self.dim == 2 else 0.0)
        self.basis = self.camera.basis() if self.dim == 3 else np.eye(2)
        corners = np.array([[self.lo[i] if (j >> i) & 1 == 0 else self.hi[i] for i in range(self.dim)]
                            for j in range(2 ** self.dim)])
        screen = corners @ self.basis[:2].T if self.dim == 3 else corners
        self.s_lo, s_hi = screen.min(0), screen.max(0)
        span = s_hi - self.s_lo
        if height is None:
            height = width * float(np.clip(span[1] / span[0], *ASPECT_RANGE))
        up = lambda n: int(math.ceil(round(n) / multiple) * multiple)
        self.width, self.height = up(width), up(height)
        self.scale = min(self.width / span[0], self.height / span[1])  # px/m
        self.offset = 0.5 * (np.array([self.width, self.height]) - span * self.scale)

    def to_pixels(self, p: np.ndarray, factor: int = 1):
        """World points (..., d) m -> (pixel xy (..., 2), depth (...) m) at `factor` x resolution."""
        if self.dim == 3:
            s, depth = p @ self.basis[:2].T, p @ self.basis[2]
        else:
            s, depth = p, np.zeros(p.shape[:-1])
        px = (s - self.s_lo) * self.scale + self.offset
        px = np.stack([px[..., 0], self.height - px[..., 1]], -1) * factor
        return px, depth

    def scale_bar(self) -> float:
        """A scale bar's length, m (about a quarter of the view's width)."""
        return nice_length(0.25 * self.width / self.scale)

    def _sky(self, factor: int) -> np.ndarray:
        h, w = self.height * factor, self.width * factor
        t = np.linspace(0.0, 1.0, h)[:, None, None]
        top, bottom = np.asarray(SKY_RGB[0]), np.asarray(SKY_RGB[1])
        return np.broadcast_to(top + t * (bottom - top), (h, w, 3)).copy()

    def frame(self, k: int):
        """Frame k as (rgb (height, width, 3) uint8, foam coverage (height, width) in [0, 1])."""
        rgb, foam = (self._frame_3d if self.dim == 3 else self._frame_2d)(k)
        f = SUPERSAMPLE
        down = lambda a: a.reshape(self.height, f, self.width, f, *a.shape[2:]).mean(axis=(1, 3))
        return np.clip(np.round(down(rgb) * 255.0), 0, 255).astype(np.uint8), down(foam)

    def _geometry_3d(self, k: int):
        """Triangles (f, 3, 3) m, per-triangle material (0 foam, 1 floor, 2 plate, 3 collider), vertex
        normals (f, 3, 3)."""
        verts, faces, normals = _surface.frame_surface(self.traj, k)
        tris, kinds, vn = [verts[faces]], [np.zeros(len(faces), int)], [normals[faces]]
        extra = []
        floor = self.scene.floor_y
        if floor is not None:
            (x0, _, z0), (x1, _, z1) = self.lo, self.hi
            q = np.array([[x0, floor, z0], [x1, floor, z0], [x1, floor, z1], [x0, floor, z1]])
            extra.append((np.array([q[[0, 1, 2]], q[[0, 2, 3]]]), 1))
        t = float(self.traj.times[k])
        for plate in self.scene.plates:
            extra.append((_box_triangles(np.asarray(plate.position(t), float), plate.half_size), 2))
        for c in self.colliders:
            tri = self._collider_triangles(c, t)
            if len(tri):
                extra.append((tri, 3))
        for tri, kind in extra:
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            tris.append(tri)
            kinds.append(np.full(len(tri), kind))
            vn.append(np.repeat(n[:, None], 3, 1))
        return np.concatenate(tris), np.concatenate(kinds), np.concatenate(vn)

    def _collider_phi(self, c, pts: np.ndarray, t: float) -> np.ndarray:
        import jax.numpy as jnp

        x = jnp.asarray(pts.reshape(-1, self.dim))
        return np.array(c.phi(x, jnp.asarray(t, x.dtype)), np.float64).reshape(pts.shape[:-1])

    def _collider_triangles(self, c, t: float) -> np.ndarray:
        """The collider's zero level set inside the view box at time t, (f, 3, 3) m (marching cubes)."""
        from skimage.measure import marching_cubes

        h = float(np.max(self.hi - self.lo)) / COLLIDER_CELLS
        axes = [np.arange(self.lo[i] - h, self.hi[i] + 2 * h, h) for i in range(3)]
        phi = self._collider_phi(c, np.stack(np.meshgrid(*axes, indexing="ij"), -1), t)
        # Outside the view box the shape is cut off: the box's faces close it.
        phi[[0, -1]], phi[:, [0, -1]], phi[:, :, [0, -1]] = h, h, h
        if phi.min() >= 0.0:
            return np.zeros((0, 3, 3))
        verts, faces, _, _ = marching_cubes(phi, 0.0, spacing=(h, h, h))
        return (verts + np.array([a[0] for a in axes]))[faces]

    def _frame_3d(self, k: int):
        f = SUPERSAMPLE
        W, H = self.width * f, self.height * f
        tris, kinds, vn = self._geometry_3d(k)
        xy, depth = self.to_pixels(tris, f)
        ids, _ = rasterize(xy, depth, W, H)
        rgb = self._sky(f)
        foam = np.zeros((H, W))
        py, px = np.nonzero(ids >= 0)
        tri = ids[py, px]
        lam = barycentric(xy, tri, px, py)
        p = np.einsum("nk,nkd->nd", lam, tris[tri])  # world points, m
        n = np.einsum("nk,nkd->nd", lam, vn[tri])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        w = self.basis[2]
        n *= np.where(n @ w < 0, -1.0, 1.0)[:, None]  # the visible side faces the camera
        light = np.asarray(LIGHT_IN_CAMERA) @ self.basis
        light /= np.linalg.norm(light)
        lit = self._lit(tris, p, n, light)
        kind = kinds[tri]
        base = np.empty((len(tri), 3))
        base[kind == 0] = FOAM_RGB
        base[kind == 2] = PLATE_RGB
        base[kind == 3] = COLLIDER_RGB
        on_floor = kind == 1
        square = nice_length(float(np.max(self.hi - self.lo)) / FLOOR_SQUARES)
        check = (np.floor(p[on_floor, 0] / square) + np.floor(p[on_floor, 2] / square)).astype(int) % 2
        base[on_floor] = np.asarray(FLOOR_RGB)[check]
        fill = np.asarray(FILL_IN_CAMERA) @ self.basis
        fill /= np.linalg.norm(fill)
        shade = AMBIENT + DIFFUSE * np.clip(n @ light, 0.0, None) * lit + FILL * np.clip(n @ fill, 0.0, None)
        rgb[py, px] = base * shade[:, None]
        foam[py, px] = kind == 0
        return rgb, foam

    def _lit(self, tris, p, normals, light) -> np.ndarray:
        """1 where the points p (n, 3) m with unit normals (n, 3) see the light, 0 in a shadow (a depth
        buffer seen from the light, looked up SHADOW_BIAS samples out along the normal: no self-shadow)."""
        r = np.cross([0.0, 0.0, 1.0] if abs(light[1]) > 0.99 else [0.0, 1.0, 0.0], light)
        r /= np.linalg.norm(r)
        basis = np.stack([r, np.cross(light, r), light])
        ls = tris.reshape(-1, 3) @ basis.T
        s_lo, s_hi = ls[:, :2].min(0), ls[:, :2].max(0)
        scale = SHADOW_SIZE / float(np.max(s_hi - s_lo))
        size = np.maximum(np.ceil((s_hi - s_lo) * scale).astype(int), 1) + 1
        txy = ((tris @ basis[:2].T) - s_lo) * scale
        _, zmap = rasterize(txy, tris @ basis[2], int(size[0]), int(size[1]))
        q = (p + normals * (SHADOW_BIAS / scale)) @ basis.T
        ix = np.clip(((q[:, :2] - s_lo) * scale).astype(int), 0, size - 1)
        return (q[:, 2] >= zmap[ix[:, 1], ix[:, 0]] - 0.5 * SHADOW_BIAS / scale).astype(float)

    def _frame_2d(self, k: int):
        f = SUPERSAMPLE
        W, H = self.width * f, self.height * f
        rgb = self._sky(f)
        # Pixel centres in world coordinates (x right, y up).
        xs = self.s_lo[0] + ((np.arange(W) + 0.5) / f - self.offset[0]) / self.scale
        ys = self.s_lo[1] + ((self.height - (np.arange(H) + 0.5) / f) - self.offset[1]) / self.scale
        foam = np.zeros((H, W))
        x, vol, spacing = _surface.frame_particles(self.traj, k)
        if len(x):
            field = _surface.volume_field(x, vol, spacing)
            phi = _interpolate(field, xs, ys)  # (H, W)
            gy, gx = np.gradient(phi, -1.0 / (self.scale * f), 1.0 / (self.scale * f))
            grad = np.hypot(gx, gy)
            px_m = 1.0 / (self.scale * f)
            foam = np.clip((phi - _surface.ISO_LEVEL) / np.maximum(grad * px_m, 1e-12) + 0.5, 0.0, 1.0)
            foam[phi <= 0.0] = 0.0
            # The relief: the coverage blurred over RELIEF spacings, RELIEF spacings high (a rounded rim).
            sigma = RELIEF * spacing * self.scale * f  # pixels
            height = _blur(foam, sigma) * 2.0 * sigma
            hy, hx = np.gradient(height)
            n = np.stack([-hx, hy, np.ones_like(phi)], -1)  # rows run down: d/dy = -d/drow
            n /= np.linalg.norm(n, axis=-1, keepdims=True)
            light = np.asarray(LIGHT_2D) / np.linalg.norm(LIGHT_2D)
            shade = AMBIENT + DIFFUSE * np.clip(n @ light, 0.0, None)
            color = np.asarray(FOAM_RGB) * shade[..., None]
            rgb = rgb * (1.0 - foam[..., None]) + color * foam[..., None]
        floor = self.scene.floor_y
        if floor is not None:
            below = ys < floor
            rgb[below] = np.asarray(FLOOR_RGB[0]) * (AMBIENT + DIFFUSE * 0.6)
            edge = np.abs(ys - floor) < 1.0 / self.scale
            rgb[edge] = 0.2
        t = float(self.traj.times[k])
        for plate in self.scene.plates:
            c, h = np.asarray(plate.position(t), float), np.asarray(plate.half_size, float)
            inx = (xs >= c[0] - h[0]) & (xs <= c[0] + h[0])
            iny = (ys >= c[1] - h[1]) & (ys <= c[1] + h[1])
            box = iny[:, None] & inx[None, :]
            rgb[box] = np.asarray(PLATE_RGB) * (AMBIENT + DIFFUSE * 0.8)
            foam[box] = 0.0
        if self.colliders:
            pts = np.stack(np.meshgrid(xs, ys, indexing="xy"), -1)  # (H, W, 2)
            for c in self.colliders:
                inside = self._collider_phi(c, pts, t) < 0.0
                rgb[inside] = np.asarray(COLLIDER_RGB) * (AMBIENT + DIFFUSE * 0.8)
                foam[inside] = 0.0
        return rgb, foam


def _interpolate(field, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a 2D field at the grid xs (W,) x ys (H,) m; (H, W), 0 outside."""
    v = np.pad(field.values, 1)
    u = (xs - field.origin[0]) / field.cell + 1.0
    w = (ys - field.origin[1]) / field.cell + 1.0
    i = np.clip(np.floor(u).astype(int), 0, v.shape[0] - 2)
    j = np.clip(np.floor(w).astype(int), 0, v.shape[1] - 2)
    fu = np.clip(u - i, 0.0, 1.0)[None, :]
    fw = np.clip(w - j, 0.0, 1.0)[:, None]
    a, b = v[i][:, j].T, v[i + 1][:, j].T  # (H, W)
    c, d = v[i][:, j + 1].T, v[i + 1][:, j + 1].T
    out = (a * (1 - fu) + b * fu) * (1 - fw) + (c * (1 - fu) + d * fu) * fw
    outside = ((u < 0) | (u > v.shape[0] - 1))[None, :] | ((w < 0) | (w > v.shape[1] - 1))[:, None]
    return np.where(outside, 0.0, out)


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """A Gaussian blur of an image (H, W) with standard deviation sigma pixels (FFT, zero-padded)."""
    pad = math.ceil(3.0 * sigma)
    b = np.pad(a, pad)
    fy, fx = np.fft.fftfreq(b.shape[0]), np.fft.rfftfreq(b.shape[1])
    g = np.exp(-2.0 * (math.pi * sigma) ** 2 * (fy[:, None] ** 2 + fx[None, :] ** 2))
    return np.fft.irfft2(np.fft.rfft2(b) * g, s=b.shape)[pad:pad + a.shape[0], pad:pad + a.shape[1]]
