"""A differentiable silhouette renderer and the losses that compare it with observed masks.

Rendering (pure JAX, static shapes, jit/vmap/grad friendly):

1. `project`: orthographic camera along -z (shared/specs/silhouettes.md): a particle's image position
   is its (x, y); in 3D z is dropped.
2. `splat_density`: every active particle spreads its projected area a = s^2 (s = dx / ppc^(1/d), the
   particle spacing) over the pixel grid with a separable quadratic B-spline kernel of width h,
   renormalized over the pixels it touches (a scatter-add onto a static stencil), so the image
   holds exactly N a / p^2 in total. The result D is a dimensionless coverage: about 1 inside a
   body, 1/2 on a straight edge (the kernel is symmetric), 0 beyond the kernel's reach.
   In 3D a column of material holds L / s particle layers; summing them would blow the kernel's
   tails up by that factor and dilate the silhouette by up to 1.5 h. The 3D coverage is therefore
   depth-normalized: the first three z-moments of the splat give the column's thickness
   L = sqrt(12 var(z) + s^2) (exact for a uniform column) and D = s sum(a K) / L.
3. `occupancy`: O = 1 - exp(-ln 2 (D / D_half)^k) in [0, 1): O = 1/2 exactly at D = D_half = 1/2,
   so the soft silhouette's half-level lies on the material boundary (no outward bias).

Losses against observed masks (row 0 = top), with per-pixel weights in [0, 1]:

- `soft_iou_loss`, `cross_entropy_loss`, `pixel_loss` (weighted squared error), and `pixel_residuals`
  for Gauss-Newton (their sum of squares is `pixel_loss`).
- Distance-field terms, so that shapes that do not overlap still get a gradient: `particle_distance`
  samples the exact Euclidean distance transform of the observed mask (computed once in numpy,
  `distance_transform`) at each particle (particles outside the mask are pulled in), and `chamfer`
  measures from each observed boundary pixel to the nearest particle (the mask pulls particles out).
  Both have a dead zone (`margin` pixels; the chamfer's one particle spacing more) so they vanish
  when the shapes agree to within a pixel.
- `pyramid`: the observed masks downsampled by 2, 4, ... (soft coverage targets) for coarse-to-fine fits.
- `make_target` bundles one observation level (masks, weights, distance fields, boundary points) and
  `silhouette_loss` / `residuals` combine the terms over frames.

Units: positions and lengths in m; images, losses and occupancy are dimensionless.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from .io import Camera, Silhouettes

# Kernel width h in particle spacings: a quadratic B-spline of spacing s is a partition of unity
# on a lattice of spacing s, so a block of particles renders D = 1 inside; 1.5 s keeps D within
# ~10% of 1 for jittered sampling and moderate stretch (measured in tests/fitting/test_silhouette.py).
KERNEL_SPACINGS = 1.5
# Kernel width h in pixels, at least: every particle then reaches >= 3 pixel centres per axis, so
# the image is a smooth function of its position at any zoom (no particle falls between pixels).
KERNEL_PIXELS = 1.0
# Coverage at which the occupancy is 1/2: the value of D on the straight edge of a uniformly
# covered half-plane under a symmetric kernel.
HALF_DENSITY = 0.5
# Coverage below which a pixel counts as empty in the 3D depth normalization (round-off level).
DENSITY_FLOOR = 1e-12
# Exponent k of the occupancy map: D = 1 gives O = 1 - 2^-8 (0.996), D = 0.25 gives 0.08.
OCC_POWER = 3.0
# Probability clip of the cross-entropy: caps a single wrong pixel's loss at -log(1e-4) ~ 9.2.
BCE_EPS = 1e-4
# Quadratic B-spline support half-width, in units of the kernel width h.
BSPLINE_SUPPORT = 1.5
# Dead zone of the distance terms, pixels: the observed boundary is uncertain by about a pixel
# (thresholding, boundary noise), so deviations within it are left to the pixel terms.
DISTANCE_MARGIN = 1.0
# Cap of observed boundary points per frame used by the chamfer term (memory: points x particles).
MAX_BOUNDARY_POINTS = 512
# Relative weights of the distance terms against the pixel term (all dimensionless: distances are
# measured in kernel widths h); they vanish when the shapes agree within the margin.
DISTANCE_WEIGHT = 1.0
CHAMFER_WEIGHT = 1.0


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Static rendering configuration (hashable: pass it as a static argument).

    Attributes:
      height, width: image shape H, W, pixels.
      pixel_size: m per pixel.  origin: (x0, y0), m, the image's bottom-left corner.
      kernel_width: B-spline width h, m (support +-1.5 h).
      spacing: particle spacing s = dx / ppc^(1/d), m.  dim: 2 or 3 (3: depth-normalized coverage).
      half_density: coverage D at which occupancy is 1/2.  power: occupancy exponent k.
    """

    height: int
    width: int
    pixel_size: float
    origin: tuple
    kernel_width: float
    spacing: float
    dim: int = 2
    half_density: float = HALF_DENSITY
    power: float = OCC_POWER

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def particle_area(self) -> float:
        """Projected area per particle a = s^2, m^2."""
        return self.spacing * self.spacing

    @property
    def stencil(self) -> int:
        """Pixels per axis a particle may touch (static): enough to cover the kernel's support."""
        reach = BSPLINE_SUPPORT * self.kernel_width / self.pixel_size
        return int(math.floor(2.0 * reach)) + 2

    @property
    def camera(self) -> Camera:
        return Camera(pixel_size=self.pixel_size, origin=tuple(self.origin))


def particle_spacing(dx: float, ppc: int, dim: int) -> float:
    """Mean particle spacing s = dx / ppc^(1/d), m."""
    return float(dx) / float(ppc) ** (1.0 / dim)


def make_render_config(camera: Camera | dict, shape, dx: float, ppc: int, dim: int,
                       kernel_spacings: float = KERNEL_SPACINGS, kernel_pixels: float = KERNEL_PIXELS
                       ) -> RenderConfig:
    """The renderer for a camera, an image shape (H, W) and a particle discretization.

    Args:
      camera: `Camera` (or dict with pixel_size, origin).  shape: (H, W).
      dx: simulation grid spacing, m.  ppc: particles per cell.  dim: 2 or 3.
      kernel_spacings, kernel_pixels: kernel width h = max(kernel_spacings s, kernel_pixels p);
        h must be at least half a pixel (so every particle reaches a pixel centre).
    """
    if isinstance(camera, dict):
        camera = Camera(pixel_size=float(camera["pixel_size"]), origin=tuple(map(float, camera["origin"])))
    H, W = (int(v) for v in shape)
    if H < 1 or W < 1:
        raise ValueError(f"image shape must be positive (H, W), got {shape}")
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    if not (dx > 0 and ppc >= 1):
        raise ValueError(f"dx must be > 0 m and ppc >= 1, got dx={dx}, ppc={ppc}")
    s = particle_spacing(dx, ppc, dim)
    h = max(kernel_spacings * s, kernel_pixels * camera.pixel_size)
    if not h >= 0.5 * camera.pixel_size:
        raise ValueError(f"kernel width {h:.3g} m must be >= half a pixel ({camera.pixel_size / 2:.3g} m): "
                         f"raise kernel_spacings or kernel_pixels")
    return RenderConfig(height=H, width=W, pixel_size=float(camera.pixel_size),
                        origin=(float(camera.origin[0]), float(camera.origin[1])), kernel_width=float(h),
                        spacing=s, dim=int(dim))


# ----------------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------------

def project(x: jax.Array) -> jax.Array:
    """Orthographic projection along -z: (N, d) positions, m -> (N, 2) image-plane (x, y), m."""
    return x[:, :2]


def _bspline2(r):
    """Quadratic B-spline N(r) (support |r| < 1.5, integral 1, C1)."""
    a = jnp.abs(r)
    inner = 0.75 - a * a
    outer = 0.5 * jnp.square(jnp.maximum(BSPLINE_SUPPORT - a, 0.0))
    return jnp.where(a < 0.5, inner, outer)


def _axis_weights(u, n_pix, cfg: RenderConfig):
    """Kernel weights along one axis: u (N,) particle coordinate in pixels from the image edge.

    Returns (index (N, K) int, weight (N, K) in 1/m summing to 1/p over the stencil, valid (N, K)
    bool: inside the image) for the K stencil pixels.
    """
    reach = BSPLINE_SUPPORT * cfg.kernel_width / cfg.pixel_size
    base = jnp.floor(u - 0.5 - reach).astype(jnp.int32) + 1
    idx = base[:, None] + jnp.arange(cfg.stencil, dtype=jnp.int32)[None, :]
    centre = idx.astype(u.dtype) + 0.5
    r = (centre - u[:, None]) * (cfg.pixel_size / cfg.kernel_width)
    w = _bspline2(r)
    # Renormalized over the stencil: the sampled B-spline is a partition of unity only when p = h.
    w = w / (jnp.sum(w, axis=1, keepdims=True) * cfg.pixel_size)
    return idx, w, (idx >= 0) & (idx < n_pix)


def splat(x: jax.Array, values: jax.Array, cfg: RenderConfig) -> jax.Array:
    """Scatter-add per-particle values (N, C) with the kernel onto the image: (H, W, C), in units of
    values per m^2 (row 0 = top). x: (N, d) m (projected along z)."""
    xy = project(x)
    H, W = cfg.shape
    u = (xy[:, 0] - cfg.origin[0]) / cfg.pixel_size  # columns from the left edge
    v = (xy[:, 1] - cfg.origin[1]) / cfg.pixel_size  # rows from the bottom edge
    ju, wu, oku = _axis_weights(u, W, cfg)
    rv, wv, okv = _axis_weights(v, H, cfg)
    w = wv[:, :, None] * wu[:, None, :]
    row = (H - 1) - rv  # image rows count from the top
    flat = row[:, :, None] * W + ju[:, None, :]
    ok = okv[:, :, None] & oku[:, None, :]
    # Out-of-image stencil pixels go to one spare slot that is cut off afterwards.
    flat = jnp.where(ok, flat, H * W)
    C = values.shape[1]
    contrib = w[:, :, :, None] * values[:, None, None, :]
    img = jnp.zeros((H * W + 1, C), values.dtype).at[flat.reshape(-1)].add(contrib.reshape(-1, C))
    return img[: H * W].reshape(H, W, C)


def splat_density(x: jax.Array, active: jax.Array, cfg: RenderConfig) -> jax.Array:
    """Projected coverage D (H, W) of the particles (dimensionless; row 0 = top of the image).

    2D: D(pixel) = sum over active particles of a K_h(c - x_p), c the pixel centre, a = s^2 the
    particle's area, K_h the (renormalized) separable quadratic B-spline of width h.
    3D: the same sum times s / L, L = sqrt(12 var(z) + s^2) the local thickness along the camera axis
    (var(z) from the kernel-weighted z-moments), so that D ~ 1 inside whatever the depth.
    x: (N, d) m.  active: (N,) bool.
    """
    on = jnp.where(active, 1.0, 0.0).astype(x.dtype)
    amount = cfg.particle_area * on
    if cfg.dim == 2 or x.shape[1] == 2:
        return splat(x, amount[:, None], cfg)[:, :, 0]
    # z relative to the particles' mean depth: the moments then do not cancel in floating point.
    zc = jax.lax.stop_gradient(jnp.sum(on * x[:, 2]) / jnp.maximum(jnp.sum(on), 1.0))
    z = x[:, 2] - zc
    m = splat(x, jnp.stack([amount, amount * z, amount * z * z], axis=1), cfg)
    total = m[:, :, 0]
    # Below this coverage a pixel is empty to round-off: its moments are not formed (no 0/0).
    occupied = total > DENSITY_FLOOR
    safe = jnp.where(occupied, total, 1.0)
    mean = m[:, :, 1] / safe
    var = jnp.maximum(m[:, :, 2] / safe - mean * mean, 0.0)
    thickness = jnp.sqrt(12.0 * var + cfg.spacing ** 2)
    return jnp.where(occupied, total * (cfg.spacing / thickness), 0.0)


def occupancy(density: jax.Array, cfg: RenderConfig) -> jax.Array:
    """Soft occupancy O = 1 - exp(-ln 2 (D / D_half)^k) in [0, 1) of a coverage image D."""
    z = math.log(2.0) * jnp.power(jnp.maximum(density, 0.0) / cfg.half_density, cfg.power)
    return -jnp.expm1(-z)


def render(x: jax.Array, active: jax.Array, cfg: RenderConfig) -> jax.Array:
    """Soft silhouette (H, W) in [0, 1) of one frame: x (N, d) m, active (N,) bool."""
    return occupancy(splat_density(x, active, cfg), cfg)


def render_frames(xs: jax.Array, active: jax.Array, cfg: RenderConfig) -> jax.Array:
    """Soft silhouettes (T, H, W) of frames xs (T, N, d) m with active (T, N) or (N,) bool."""
    if active.ndim == 1:
        active = jnp.broadcast_to(active[None, :], xs.shape[:2])
    return jax.vmap(render, in_axes=(0, 0, None))(xs, active, cfg)


# ----------------------------------------------------------------------------------------------
# Pixel losses
# ----------------------------------------------------------------------------------------------

def _wsum(a):
    return jnp.sum(a, axis=(-2, -1))


def soft_iou_loss(occ, mask, weights) -> jax.Array:
    """1 - soft IoU, per frame: 1 - sum(w O M) / sum(w (O + M - O M)). occ, mask, weights (..., H, W);
    returns (...,) in [0, 1] (0 for identical images)."""
    inter = _wsum(weights * occ * mask)
    union = _wsum(weights * (occ + mask - occ * mask))
    return 1.0 - inter / jnp.maximum(union, 1e-12)


def cross_entropy_loss(occ, mask, weights) -> jax.Array:
    """Weighted mean binary cross-entropy per frame, (...,); mask may be soft (coverage in [0, 1])."""
    o = jnp.clip(occ, BCE_EPS, 1.0 - BCE_EPS)
    ce = -(mask * jnp.log(o) + (1.0 - mask) * jnp.log1p(-o))
    return _wsum(weights * ce) / jnp.maximum(_wsum(weights), 1e-12)


def pixel_loss(occ, mask, weights) -> jax.Array:
    """Weighted mean squared difference per frame, (...,): sum(w (O - M)^2) / sum(w)."""
    return _wsum(weights * jnp.square(occ - mask)) / jnp.maximum(_wsum(weights), 1e-12)


def pixel_residuals(occ, mask, weights) -> jax.Array:
    """Residual images sqrt(w / sum w) (O - M), flattened per frame: (..., H*W).

    The sum of squares of one frame's residuals equals its `pixel_loss`.
    """
    scale = jnp.sqrt(weights / jnp.maximum(_wsum(weights), 1e-12)[..., None, None])
    r = scale * (occ - mask)
    return r.reshape(r.shape[:-2] + (-1,))


# ----------------------------------------------------------------------------------------------
# Distance fields (numpy, computed once per observation)
# ----------------------------------------------------------------------------------------------

def distance_transform(binary: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance transform, in pixels: distance from each pixel centre to the nearest
    True pixel centre (0 on True pixels; inf everywhere if there is none). binary (H, W).

    Separable (Saito-Toriwaki): the column-wise distance g by two sweeps, then
    d^2(i, j) = min_j' (j - j')^2 + g(i, j')^2, evaluated in row blocks (O(H W^2) work).
    """
    b = np.asarray(binary, bool)
    if b.ndim != 2:
        raise ValueError(f"distance_transform expects a 2D image, got shape {b.shape}")
    if not b.any():
        return np.full(b.shape, np.inf)
    if b.shape[1] > b.shape[0]:
        return distance_transform(b.T).T  # the quadratic pass runs along the shorter axis
    H, W = b.shape
    big = float(H + W)
    g = np.where(b, 0.0, big)
    for i in range(1, H):
        np.minimum(g[i], g[i - 1] + 1.0, out=g[i])
    for i in range(H - 2, -1, -1):
        np.minimum(g[i], g[i + 1] + 1.0, out=g[i])
    g2 = np.square(g)
    cols = np.arange(W, dtype=float)
    dj2 = np.square(cols[:, None] - cols[None, :])  # (W, W)
    out = np.empty((H, W))
    block = max(1, int(4_000_000 // (W * W)))
    for i0 in range(0, H, block):
        blk = g2[i0:i0 + block]  # (B, W') with j' on the last axis
        out[i0:i0 + block] = np.min(dj2[None, :, :] + blk[:, None, :], axis=2)
    return np.sqrt(out)


def outside_distance(mask: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Distance, in pixels, from each pixel to the region where foam may be: observed foam or
    pixels of weight 0 (unknown). (H, W); zeros where nothing may be foam (the term is then off)."""
    allowed = np.asarray(mask) > 0.5
    if weights is not None:
        allowed |= np.asarray(weights) <= 0
    if not allowed.any():
        return np.zeros(allowed.shape)
    return distance_transform(allowed)


def boundary_points(mask: np.ndarray, weights: np.ndarray, camera: Camera, max_points: int = MAX_BOUNDARY_POINTS):
    """Observed foam boundary pixels of one frame: (points (M, 2) m, count).

    A boundary pixel is a foam pixel of weight > 0 with a 4-neighbour that is background of
    weight > 0 (the image border and weight-0 pixels are unknown, not background). At most
    `max_points` evenly spread along the row-major order are returned.
    """
    m = np.asarray(mask) > 0.5
    known = np.asarray(weights) > 0
    bg = ~m & known
    nb = np.zeros_like(m)
    nb[1:, :] |= bg[:-1, :]
    nb[:-1, :] |= bg[1:, :]
    nb[:, 1:] |= bg[:, :-1]
    nb[:, :-1] |= bg[:, 1:]
    ii, jj = np.nonzero(m & known & nb)
    if len(ii) > max_points:
        pick = np.round(np.linspace(0, len(ii) - 1, max_points)).astype(int)
        ii, jj = ii[pick], jj[pick]
    xc, yc = camera.pixel_centers(m.shape)
    return np.stack([xc[jj], yc[ii]], axis=1), len(ii)


def sample_field(field: jax.Array, xy: jax.Array, cfg: RenderConfig) -> jax.Array:
    """Bilinear interpolation of a pixel field (H, W) (values at pixel centres) at image-plane
    points xy (N, 2) m; outside the image the value at the nearest edge point plus the Euclidean
    distance to it, in pixels (so a distance field keeps growing off-image)."""
    H, W = cfg.shape
    u = (xy[:, 0] - cfg.origin[0]) / cfg.pixel_size - 0.5  # column-centre coordinate
    r = (H - 1) - ((xy[:, 1] - cfg.origin[1]) / cfg.pixel_size - 0.5)  # row-centre coordinate
    uc = jnp.clip(u, 0.0, W - 1.0)
    rc = jnp.clip(r, 0.0, H - 1.0)
    excess = jnp.sqrt(jnp.square(u - uc) + jnp.square(r - rc) + 1e-30) - 1e-15
    j0 = jnp.clip(jnp.floor(uc).astype(jnp.int32), 0, max(W - 2, 0))
    i0 = jnp.clip(jnp.floor(rc).astype(jnp.int32), 0, max(H - 2, 0))
    j1 = jnp.minimum(j0 + 1, W - 1)
    i1 = jnp.minimum(i0 + 1, H - 1)
    fu = uc - j0.astype(uc.dtype)
    fr = rc - i0.astype(rc.dtype)
    f00, f01 = field[i0, j0], field[i0, j1]
    f10, f11 = field[i1, j0], field[i1, j1]
    val = (1 - fr) * ((1 - fu) * f00 + fu * f01) + fr * ((1 - fu) * f10 + fu * f11)
    return val + excess


def _dead_zone(d, margin):
    return jnp.maximum(d - margin, 0.0)


def particle_distance(x, active, dist_field, cfg: RenderConfig, margin: float = DISTANCE_MARGIN) -> jax.Array:
    """Per-particle distance outside the observed foam, in kernel widths h, (N,) (0 for inactive).

    dist_field: `outside_distance` of the observed mask, pixels (H, W). Distances within `margin`
    pixels of the foam count as 0.
    """
    d = _dead_zone(sample_field(dist_field, project(x), cfg), margin)
    return jnp.where(active, d * (cfg.pixel_size / cfg.kernel_width), 0.0)


def chamfer(x, active, points, point_weights, cfg: RenderConfig, margin: float = DISTANCE_MARGIN) -> jax.Array:
    """Per-point distance from observed boundary points (M, 2) m to the nearest active particle,
    in kernel widths h, minus a dead zone of `margin` pixels plus one particle spacing (material
    reaches about half a spacing beyond its outermost particles, more where jittered or stretched);
    (M,) (0 where point_weights is 0)."""
    xy = project(x)
    d2 = jnp.sum(jnp.square(points[:, None, :] - xy[None, :, :]), axis=-1)
    far = jnp.asarray(1e30, d2.dtype)
    d2 = jnp.where(active[None, :], d2, far)
    dmin2 = jnp.min(d2, axis=1)
    # sqrt with a floor: its derivative stays finite when a particle sits exactly on a point.
    dist = jnp.sqrt(jnp.maximum(dmin2, (1e-9 * cfg.pixel_size) ** 2)) / cfg.pixel_size
    d = _dead_zone(dist, margin + cfg.spacing / cfg.pixel_size) * (cfg.pixel_size / cfg.kernel_width)
    return jnp.where(point_weights > 0, d, 0.0)


# ----------------------------------------------------------------------------------------------
# Observations, pyramid, combined losses
# ----------------------------------------------------------------------------------------------

@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SilhouetteTarget:
    """One level of observations prepared for the losses (arrays; a pytree).

    Attributes:
      masks: (T, H, W) float in [0, 1] (soft on coarse pyramid levels).
      weights: (T, H, W) float in [0, 1].
      dist: (T, H, W) `outside_distance`, pixels.
      points: (T, M, 2) observed boundary points, m (padding rows are zero).
      point_weights: (T, M) 1 for real points, 0 for padding.
    """

    masks: jax.Array
    weights: jax.Array
    dist: jax.Array
    points: jax.Array
    point_weights: jax.Array


def make_target(masks, weights, camera: Camera, max_points: int = MAX_BOUNDARY_POINTS,
                dtype=jnp.float64, pad: bool = False) -> SilhouetteTarget:
    """Prepare observed masks (T, H, W) (0/1 or soft coverage) and weights (T, H, W) for the losses.
    pad: boundary points padded to max_points per frame, so targets of other data have the same shapes
    (one compiled residual; padding rows add zeros)."""
    masks = np.asarray(masks, float)
    weights = np.broadcast_to(np.asarray(weights, float), masks.shape)
    T = masks.shape[0]
    dist = np.stack([outside_distance(masks[t], weights[t]) for t in range(T)])
    pts = [boundary_points(masks[t], weights[t], camera, max_points) for t in range(T)]
    M = max_points if pad else max(1, max(n for _, n in pts))
    points = np.zeros((T, M, 2))
    pw = np.zeros((T, M))
    for t, (p, n) in enumerate(pts):
        points[t, :n] = p
        pw[t, :n] = 1.0
    a = lambda v: jnp.asarray(v, dtype)
    return SilhouetteTarget(masks=a(masks), weights=a(weights), dist=a(dist), points=a(points), point_weights=a(pw))


def downsample(masks, weights, factor: int):
    """Average-pool masks (T, H, W) and weights by an integer factor: (soft masks, weights).

    The coarse mask is the weighted foam fraction of each block (a soft target); the coarse weight
    the mean weight. Images are padded at the right and bottom with weight-0 pixels; the camera
    origin (bottom-left) therefore moves down by the padded rows: see `pyramid`.
    """
    masks = np.asarray(masks, float)
    weights = np.broadcast_to(np.asarray(weights, float), masks.shape)
    T, H, W = masks.shape
    Hc, Wc = -(-H // factor), -(-W // factor)
    pm = np.zeros((T, Hc * factor, Wc * factor))
    pw = np.zeros_like(pm)
    pm[:, :H, :W] = masks * weights
    pw[:, :H, :W] = weights
    sm = pm.reshape(T, Hc, factor, Wc, factor).sum(axis=(2, 4))
    sw = pw.reshape(T, Hc, factor, Wc, factor).sum(axis=(2, 4))
    soft = np.where(sw > 0, sm / np.maximum(sw, 1e-12), 0.0)
    return soft, sw / factor ** 2


def pyramid(data: Silhouettes, levels: int) -> list[tuple[np.ndarray, np.ndarray, Camera]]:
    """Coarse-to-fine observations: [(masks, weights, camera)] for factors 1, 2, 4, ... 2^(levels-1).

    Level 0 is the data itself; level l has pixels 2^l times larger and soft coverage masks.
    """
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    out = []
    H = data.masks.shape[1]
    for lvl in range(levels):
        f = 2 ** lvl
        soft, w = downsample(data.masks, data.weights, f)
        pad_rows = soft.shape[1] * f - H  # padding sits at the bottom: the origin moves down
        cam = Camera(pixel_size=data.camera.pixel_size * f,
                     origin=(data.camera.origin[0], data.camera.origin[1] - pad_rows * data.camera.pixel_size))
        out.append((soft, w, cam))
    return out


def loss_terms(xs, active, target: SilhouetteTarget, cfg: RenderConfig, margin: float = DISTANCE_MARGIN) -> dict:
    """Every loss term, averaged over frames: dict of scalars.

    xs: (T, N, d) particle positions, m, at the observed times; active (T, N) or (N,) bool.
    Terms: iou (1 - soft IoU), cross_entropy, pixel (weighted squared error), distance (mean
    squared `particle_distance` of active particles), chamfer (weighted mean squared `chamfer`).
    """
    if active.ndim == 1:
        active = jnp.broadcast_to(active[None, :], xs.shape[:2])
    occ = render_frames(xs, active, cfg)
    m, w = target.masks, target.weights
    dist = jax.vmap(particle_distance, in_axes=(0, 0, 0, None, None))(xs, active, target.dist, cfg, margin)
    n_act = jnp.maximum(jnp.sum(active, axis=1), 1).astype(xs.dtype)
    ch = jax.vmap(chamfer, in_axes=(0, 0, 0, 0, None, None))(xs, active, target.points, target.point_weights,
                                                             cfg, margin)
    pw = target.point_weights
    return dict(
        iou=jnp.mean(soft_iou_loss(occ, m, w)),
        cross_entropy=jnp.mean(cross_entropy_loss(occ, m, w)),
        pixel=jnp.mean(pixel_loss(occ, m, w)),
        distance=jnp.mean(jnp.sum(jnp.square(dist), axis=1) / n_act),
        chamfer=jnp.mean(jnp.sum(pw * jnp.square(ch), axis=1) / jnp.maximum(jnp.sum(pw, axis=1), 1.0)),
    )


def silhouette_loss(xs, active, target: SilhouetteTarget, cfg: RenderConfig, iou: float = 1.0,
                    cross_entropy: float = 0.0, pixel: float = 0.0, distance: float = DISTANCE_WEIGHT,
                    chamfer_weight: float = CHAMFER_WEIGHT, margin: float = DISTANCE_MARGIN) -> jax.Array:
    """A weighted sum of `loss_terms` (dimensionless scalar); the keyword arguments are the weights."""
    t = loss_terms(xs, active, target, cfg, margin)
    return (iou * t["iou"] + cross_entropy * t["cross_entropy"] + pixel * t["pixel"]
            + distance * t["distance"] + chamfer_weight * t["chamfer"])


def residuals(xs, active, target: SilhouetteTarget, cfg: RenderConfig, distance: float = DISTANCE_WEIGHT,
              chamfer_weight: float = CHAMFER_WEIGHT, margin: float = DISTANCE_MARGIN) -> jax.Array:
    """The residual vector for Gauss-Newton: (T (H W + N + M),).

    Its sum of squares equals `silhouette_loss(..., iou=0, pixel=1, distance=distance,
    chamfer_weight=chamfer_weight)`: per frame, the weighted pixel residual images, sqrt(distance /
    N_active) times the particle distances, and sqrt(chamfer / M) times the boundary-point distances,
    all divided by sqrt(T).
    """
    if active.ndim == 1:
        active = jnp.broadcast_to(active[None, :], xs.shape[:2])
    T = xs.shape[0]
    occ = render_frames(xs, active, cfg)
    r_pix = pixel_residuals(occ, target.masks, target.weights)
    d = jax.vmap(particle_distance, in_axes=(0, 0, 0, None, None))(xs, active, target.dist, cfg, margin)
    n_act = jnp.maximum(jnp.sum(active, axis=1), 1).astype(xs.dtype)
    r_d = jnp.sqrt(distance / n_act)[:, None] * d
    c = jax.vmap(chamfer, in_axes=(0, 0, 0, 0, None, None))(xs, active, target.points, target.point_weights,
                                                            cfg, margin)
    pw = target.point_weights
    r_c = jnp.sqrt(chamfer_weight * pw / jnp.maximum(jnp.sum(pw, axis=1), 1.0)[:, None]) * c
    return jnp.concatenate([r_pix, r_d, r_c], axis=1).reshape(-1) / math.sqrt(T)
