"""The differentiable silhouette renderer and its losses: coverage of known particle blocks, IoU
against masks, exact distance transform, and loss gradients against finite differences (float64)."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam
from fitting import Camera, Silhouettes
from fitting.silhouette import (BSPLINE_SUPPORT, distance_transform, loss_terms, make_render_config, make_target,
                                occupancy, pyramid, render, render_frames, residuals, silhouette_loss, splat_density)

from helpers import central_difference

DX, PPC = 0.01, 4
S = DX / 2  # particle spacing in 2D at 4 particles per cell

# Jitted once per configuration: eager op-by-op dispatch would compile every primitive separately.
_render = jax.jit(render, static_argnames=("cfg",))
_splat = jax.jit(splat_density, static_argnames=("cfg",))
_terms = jax.jit(loss_terms, static_argnames=("cfg",))


def _lattice_block(lo, hi, s=S, dim=2):
    """Particles at the centres of an s-lattice filling the box [lo, hi] (every cell fully inside)."""
    axes = [np.arange(a + s / 2, b, s) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim)


def _pixel_grid(cam, shape):
    xc, yc = cam.pixel_centers(shape)
    return np.meshgrid(xc, yc)


def test_block_occupancy_covers_exactly_its_pixels():
    """A 2D block [0.05, 0.15] x [0.04, 0.12] on 2 mm pixels: every pixel whose centre is inside is
    occupied (> 1/2), every pixel whose centre is outside is not (corners, rounded by the kernel,
    excepted), deep inside O ~ 1, beyond the kernel's reach exactly 0."""
    cam = Camera(0.002, (0.0, 0.0))
    shape = (80, 100)
    pts = _lattice_block((0.05, 0.04), (0.15, 0.12))
    cfg = make_render_config(cam, shape, DX, PPC, 2)
    occ = np.asarray(_render(jnp.asarray(pts), jnp.ones(len(pts), bool), cfg))
    X, Y = _pixel_grid(cam, shape)
    inside = (X > 0.05) & (X < 0.15) & (Y > 0.04) & (Y < 0.12)
    h = cfg.kernel_width
    corner = np.min([np.hypot(X - cx, Y - cy) for cx in (0.05, 0.15) for cy in (0.04, 0.12)], axis=0)
    away = corner > h
    np.testing.assert_array_equal((occ > 0.5)[away], inside[away])
    assert np.sum((occ > 0.5) != inside) <= 4 * 3  # a few pixels per rounded corner
    deep = (X > 0.05 + 2 * h) & (X < 0.15 - 2 * h) & (Y > 0.04 + 2 * h) & (Y < 0.12 - 2 * h)
    assert occ[deep].min() > 0.98
    reach = BSPLINE_SUPPORT * h
    far = (X < 0.05 - reach) | (X > 0.15 + reach) | (Y < 0.04 - reach) | (Y > 0.12 + reach)
    assert np.all(occ[far] == 0.0)
    assert np.all((occ >= 0) & (occ < 1))


def test_straight_edge_half_level_lies_on_the_material_boundary():
    """Coverage of a half-plane of particles is 1/2 on its edge (symmetric kernel): the soft
    silhouette is not biased outward. The edge found along every column lies within 5% of a
    particle spacing of the material boundary, and within 3% on average."""
    cam = Camera(0.001, (0.0, 0.0))
    pts = _lattice_block((0.0, 0.0), (0.2, 0.1))
    cfg = make_render_config(cam, (200, 200), DX, PPC, 2)
    dens = np.asarray(_splat(jnp.asarray(pts), jnp.ones(len(pts), bool), cfg))
    xc, yc = cam.pixel_centers((200, 200))
    y = yc[::-1]
    edges = []
    for j in range(40, 160):
        col = dens[::-1, j]  # bottom to top
        k = int(np.nonzero((col[:-1] >= 0.5) & (col[1:] < 0.5))[0][0])
        edges.append(y[k] + (0.5 - col[k]) / (col[k + 1] - col[k]) * (y[k + 1] - y[k]))
    edges = np.array(edges)
    assert np.abs(edges - 0.1).max() < 0.05 * S
    assert abs(edges.mean() - 0.1) < 0.03 * S
    interior = dens[::-1][(y > 0.03) & (y < 0.07)][:, 40:160]
    assert np.all(np.abs(interior - 1.0) < 0.04)


def test_splat_conserves_total_coverage_and_ignores_inactive():
    """sum(D) p^2 = (number of active particles) s^2 whenever kernels stay inside the image."""
    rng = np.random.default_rng(1)
    cam = Camera(0.003, (0.0, 0.0))
    pts = rng.uniform(0.03, 0.12, (50, 2))
    active = np.arange(50) < 37
    cfg = make_render_config(cam, (50, 50), DX, PPC, 2)
    dens = np.asarray(_splat(jnp.asarray(pts), jnp.asarray(active), cfg))
    assert dens.sum() * cam.pixel_size ** 2 == pytest.approx(37 * cfg.particle_area, rel=1e-12)
    edge = pts.copy()
    edge[0] = [0.001, 0.07]  # half of its kernel falls off the image: only that half is lost
    dens_e = np.asarray(_splat(jnp.asarray(edge), jnp.asarray(active), cfg))
    assert 36.2 * cfg.particle_area < dens_e.sum() * cam.pixel_size ** 2 < 36.8 * cfg.particle_area
    moved = pts.copy()
    moved[~active] += 0.01  # inactive particles do not show, wherever they are
    dens2 = np.asarray(_splat(jnp.asarray(moved), jnp.asarray(active), cfg))
    np.testing.assert_allclose(dens2, dens, atol=1e-15)


@pytest.mark.slow
def test_3d_silhouette_is_the_projection_whatever_the_depth():
    """3D blocks 8 and 20 layers deep seen along -z: depth-normalized coverage ~ 1 inside, and the
    silhouette is the (x, y) block (a plain layer count would dilate it by ~1 kernel width);
    a jittered ellipsoid's silhouette is its projected ellipse (IoU > 0.95)."""
    s = DX / 2  # 8 particles per cell in 3D
    cam = Camera(0.002, (0.0, 0.0))
    shape = (80, 100)
    cfg = make_render_config(cam, shape, DX, 8, 3)
    X, Y = _pixel_grid(cam, shape)
    h = cfg.kernel_width
    inside = (X > 0.05) & (X < 0.15) & (Y > 0.04) & (Y < 0.12)
    deep = (X > 0.05 + 2 * h) & (X < 0.15 - 2 * h) & (Y > 0.04 + 2 * h) & (Y < 0.12 - 2 * h)
    corner = np.min([np.hypot(X - cx, Y - cy) for cx in (0.05, 0.15) for cy in (0.04, 0.12)], axis=0)
    for depth in (0.04, 0.1):
        pts = _lattice_block((0.05, 0.04, 0.0), (0.15, 0.12, depth), s=s, dim=3)
        dens = np.asarray(_splat(jnp.asarray(pts), jnp.ones(len(pts), bool), cfg))
        assert np.abs(dens[deep] - 1).max() < 0.04
        hard = np.asarray(occupancy(jnp.asarray(dens), cfg)) > 0.5
        np.testing.assert_array_equal(hard[corner > h], inside[corner > h])
    scene = jaxfoam.load_scene({"kind": "drop", "dim": 3, "density": 80.0, "kappa": 2000.0,
                                "domain": {"min": [0.0, 0.0, 0.0], "max": [0.2, 0.16, 0.2]},
                                "initial_shape": {"type": "ellipse", "center": [0.1, 0.08, 0.1],
                                                  "radii": [0.06, 0.04, 0.05]}})
    pts, _ = jaxfoam.sample_particles(scene, DX, 8, seed=0)
    occ = np.asarray(_render(jnp.asarray(pts), jnp.ones(len(pts), bool), cfg))
    truth = ((X - 0.1) / 0.06) ** 2 + ((Y - 0.08) / 0.04) ** 2 <= 1
    hard = occ > 0.5
    assert (hard & truth).sum() / (hard | truth).sum() > 0.95


def test_rendering_of_sampled_ellipse_matches_its_mask():
    """Jittered particles sampled in an ellipse (the simulator's sampler) render to the ellipse's
    pixel mask with IoU > 0.95 at pixels finer than the particles and at pixels coarser."""
    scene = jaxfoam.load_scene({"kind": "drop", "dim": 2, "density": 80.0, "kappa": 2000.0,
                                "domain": {"min": [0.0, 0.0], "max": [0.2, 0.2]},
                                "initial_shape": {"type": "ellipse", "center": [0.1, 0.09], "radii": [0.06, 0.04]}})
    pts, _ = jaxfoam.sample_particles(scene, DX, PPC, seed=3)
    for p in (0.002, 0.008):
        n = int(round(0.2 / p))
        cam = Camera(p, (0.0, 0.0))
        cfg = make_render_config(cam, (n, n), DX, PPC, 2)
        occ = np.asarray(_render(jnp.asarray(pts), jnp.ones(len(pts), bool), cfg))
        X, Y = _pixel_grid(cam, (n, n))
        truth = ((X - 0.1) / 0.06) ** 2 + ((Y - 0.09) / 0.04) ** 2 <= 1
        hard = occ > 0.5
        iou = (hard & truth).sum() / (hard | truth).sum()
        assert iou > 0.95, (p, iou)
        soft = 1 - float(_terms(jnp.asarray(pts)[None], jnp.ones((1, len(pts)), bool),
                                    make_target(truth[None], np.ones((1, n, n)), cam), cfg)["iou"])
        assert soft > 0.9, (p, soft)


def test_distance_transform_is_exact():
    """Brute force over all foam pixels on random masks (and the empty mask gives inf)."""
    rng = np.random.default_rng(0)
    for shape in ((23, 31), (31, 17)):
        b = rng.random(shape) < 0.05
        d = distance_transform(b)
        ii, jj = np.nonzero(b)
        I, J = np.indices(shape)
        ref = np.sqrt(np.min((I[..., None] - ii) ** 2 + (J[..., None] - jj) ** 2, axis=-1))
        np.testing.assert_allclose(d, ref, atol=1e-12)
    assert np.all(np.isinf(distance_transform(np.zeros((4, 5), bool))))


def _scene_pair(rng, T=2, n=100):
    cam = Camera(0.004, (0.0, 0.0))
    H, W = 30, 40
    X, Y = _pixel_grid(cam, (H, W))
    masks = np.stack([((X - 0.09) / 0.03) ** 2 + ((Y - 0.06) / 0.025) ** 2 <= 1,
                      ((X - 0.10) / 0.03) ** 2 + ((Y - 0.055) / 0.025) ** 2 <= 1]).astype(np.uint8)
    weights = np.ones((T, H, W))
    weights[:, :3, :] = 0.0  # an occluded strip
    weights[:, 10:12, :] = 0.5
    target = make_target(masks, weights, cam)
    x = np.stack([rng.uniform(0.05, 0.12, (T, n)), rng.uniform(0.03, 0.09, (T, n))], -1)
    active = np.ones((T, n), bool)
    active[:, -5:] = False
    cfg = make_render_config(cam, (H, W), DX, PPC, 2)
    return x, active, target, cfg


TERMS = ("iou", "cross_entropy", "pixel", "distance", "chamfer")


def test_loss_gradients_match_central_differences():
    """d(each loss term) / d positions (reverse mode) against central differences along random
    directions, float64, eps = 1e-7 m (the kernel is C1: the FD error is O(eps) relative to the
    pixel size, ~1e-8 here); inactive particles get exactly zero gradient."""
    rng = np.random.default_rng(7)
    x, active, target, cfg = _scene_pair(rng)

    def terms(x):
        t = loss_terms(x, jnp.asarray(active), target, cfg)
        return jnp.stack([t[k] for k in TERMS])

    f = jax.jit(terms)
    jac = np.asarray(jax.jit(jax.jacrev(terms))(jnp.asarray(x)))  # (5, T, N, 2)
    assert np.all(np.isfinite(jac))
    assert np.all(jac[:, :, -5:] == 0.0)  # inactive particles have no say
    jvp = jax.jit(lambda x, v: jax.jvp(terms, (x,), (v,))[1])  # forward mode, as Gauss-Newton uses
    eps = 1e-7
    for _ in range(2):
        v = rng.normal(size=x.shape)
        fd = central_difference(f, x, v, h=eps)
        an = np.tensordot(jac, v, axes=3)
        assert np.all(np.abs(an) > 1e-3), dict(zip(TERMS, an))
        np.testing.assert_allclose(fd, an, rtol=1e-6, err_msg=str(TERMS))
        np.testing.assert_allclose(np.asarray(jvp(jnp.asarray(x), jnp.asarray(v))), an, rtol=1e-10)


def test_disjoint_shapes_still_get_a_useful_gradient():
    """A blob far from the observed mask: the pixel losses are flat (zero gradient) but the
    distance-field terms point the blob towards the mask, and gradient descent on a rigid shift
    closes the gap."""
    cam = Camera(0.004, (0.0, 0.0))
    H, W = 40, 60
    X, Y = _pixel_grid(cam, (H, W))
    mask = (((X - 0.18) / 0.03) ** 2 + ((Y - 0.08) / 0.03) ** 2 <= 1)[None].astype(np.uint8)
    target = make_target(mask, np.ones((1, H, W)), cam)
    cfg = make_render_config(cam, (H, W), DX, PPC, 2)
    blob = _lattice_block((0.03, 0.05), (0.09, 0.11))
    active = jnp.ones((1, len(blob)), bool)

    def loss_of_shift(shift, **kw):
        return silhouette_loss(jnp.asarray(blob)[None] + shift[None, None, :], active, target, cfg, **kw)

    g_pix = jax.jit(jax.grad(lambda s: loss_of_shift(s, distance=0.0, chamfer_weight=0.0)))(jnp.zeros(2))
    assert float(jnp.linalg.norm(g_pix)) == 0.0
    step = jax.jit(jax.grad(loss_of_shift))
    g = np.asarray(step(jnp.zeros(2)))
    towards = np.array([0.18 - 0.06, 0.0])
    cos = -g @ towards / (np.linalg.norm(g) * np.linalg.norm(towards))
    assert cos > 0.95
    shift = jnp.zeros(2)
    for _ in range(60):  # plain gradient descent, step 2e-5 m^2 per unit loss
        shift = shift - 2e-5 * step(shift)
    assert abs(float(shift[0]) - 0.12) < 0.01 and abs(float(shift[1])) < 0.01


def test_residuals_sum_of_squares_is_the_least_squares_loss():
    """The Gauss-Newton residual vector: one entry per pixel, particle and boundary point per frame,
    and its sum of squares is the least-squares loss (pixel + weighted distance terms)."""
    rng = np.random.default_rng(9)
    x, active, target, cfg = _scene_pair(rng)
    r = jax.jit(residuals, static_argnames=("cfg", "distance", "chamfer_weight"))(
        jnp.asarray(x), jnp.asarray(active), target, cfg, distance=0.7, chamfer_weight=0.3)
    T, H, W = target.masks.shape
    assert r.shape == (T * (H * W + x.shape[1] + target.points.shape[1]),)
    ls = jax.jit(lambda x: silhouette_loss(x, jnp.asarray(active), target, cfg, iou=0.0, pixel=1.0, distance=0.7,
                                           chamfer_weight=0.3))(jnp.asarray(x))
    assert float(jnp.sum(r ** 2)) == pytest.approx(float(ls), rel=1e-12)


def test_losses_are_minimal_at_the_true_position():
    """Particles filling exactly the observed block: the distance terms vanish (inside their dead
    zone), and shifting the particles by 1 or 2 pixels along x or y raises the IoU, cross-entropy
    and squared-error losses: the minimum sits at the true position."""
    cam = Camera(0.002, (0.0, 0.0))
    shape = (60, 80)
    pts = jnp.asarray(_lattice_block((0.05, 0.03), (0.13, 0.09)))[None]
    X, Y = _pixel_grid(cam, shape)
    mask = ((X > 0.05) & (X < 0.13) & (Y > 0.03) & (Y < 0.09))[None].astype(np.uint8)
    cfg = make_render_config(cam, shape, DX, PPC, 2)
    target = make_target(mask, np.ones((1,) + shape), cam)
    active = jnp.ones(pts.shape[:2], bool)
    terms = jax.jit(lambda d: loss_terms(pts + d[None, None, :], active, target, cfg))
    t0 = terms(jnp.zeros(2))
    assert float(t0["distance"]) == 0.0 and float(t0["chamfer"]) == 0.0
    for k in range(2):
        for step in (-2, -1, 1, 2):
            t = terms(jnp.zeros(2).at[k].set(step * cam.pixel_size))
            for name in ("iou", "cross_entropy", "pixel"):
                assert float(t[name]) > float(t0[name]), (name, k, step)


def test_pyramid_levels_keep_the_geometry():
    """Downsampled levels: soft coverage averages the fine mask, the camera keeps world positions
    (foam centroid equal at every level), and rendering vmapped over frames works at each level."""
    cam = Camera(0.002, (-0.1, 0.0))
    T, H, W = 2, 45, 50  # not divisible by 2 or 4: exercises the padding
    X, Y = _pixel_grid(cam, (H, W))
    masks = np.stack([((X + 0.05) / 0.02) ** 2 + ((Y - 0.05) / 0.015) ** 2 <= 1] * T).astype(np.uint8)
    data = Silhouettes(masks=masks, times=np.array([0.0, 0.1]), weights=np.ones((T, H, W), np.float32),
                       camera=cam, scene_json="{}")
    levels = pyramid(data, 3)
    for f, (soft, w, c) in zip((1, 2, 4), levels):
        assert soft.shape[1:] == (math.ceil(H / f), math.ceil(W / f))
        assert c.pixel_size == pytest.approx(0.002 * f)
        assert soft.sum() * f * f == pytest.approx(masks.sum())
        Xc, Yc = _pixel_grid(c, soft.shape[1:])
        cx = (soft[0] * Xc).sum() / soft[0].sum()
        cy = (soft[0] * Yc).sum() / soft[0].sum()
        assert cx == pytest.approx(-0.05, abs=1e-3) and cy == pytest.approx(0.05, abs=1e-3)
        assert np.all(w[:, -1, :] <= 1.0)
    cfg = make_render_config(levels[1][2], levels[1][0].shape[1:], DX, PPC, 2)
    xs = jnp.asarray(np.stack([_lattice_block((-0.07, 0.035), (-0.03, 0.065))] * T))
    occ = jax.jit(render_frames, static_argnames=("cfg",))(xs, jnp.ones(xs.shape[1], bool), cfg)
    assert occ.shape == (T,) + levels[1][0].shape[1:]
