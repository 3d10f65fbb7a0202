"""MLS-MPM (Hu et al. 2018) with quadratic B-splines and APIC affine velocities: transfers, grid
boundary conditions and the time loop of the reference simulator. SI units (m, s, kg, Pa).

One step of length dt (s):
1. P2G: each particle p scatters mass m_p and momentum m_p v_p + (m_p C_p - dt V0_p (4 / dx^2) tau_p)(x_i - x_p)
   to the 3^d nodes i of its stencil, weighted by w_ip (tau_p: Kirchhoff stress, so V0 tau = V sigma).
2. Grid: v_i = p_i / m_i + dt g, then the boundary rules (`grid_update`): domain walls (slip), the floor
   (Coulomb friction or sticky), plates (sticky: the node takes the plate's velocity).
3. G2P: v_p = sum_i w_ip v_i, C_p = (4 / dx^2) sum_i w_ip v_i (x_i - x_p)^T, x_p += dt v_p, then
   f = I + dt C_p (3x3, plane strain in 2D), J_p *= det f, and the return map updates bbar_e (`material`).

The grid is flattened (last axis fastest). It may be periodic along x (validation runs only).
"""
from __future__ import annotations

import math

import numpy as np

from ._jit import kernel
from .material import det3, kirchhoff, return_map

FLOOR_NONE, FLOOR_STICKY, FLOOR_COULOMB = 0, 1, 2


@kernel
def _stencil(xp, origin, inv_dx, base, fx, w):
    """Quadratic B-spline stencil of a particle at xp (d,), m: base node (d,), offset fx in [0.5, 1.5), weights (d, 3)."""
    for k in range(xp.shape[0]):
        r = (xp[k] - origin[k]) * inv_dx
        base[k] = int(math.floor(r - 0.5))
        t = r - base[k]
        fx[k] = t
        w[k, 0] = 0.5 * (1.5 - t) ** 2
        w[k, 1] = 0.75 - (t - 1.0) ** 2
        w[k, 2] = 0.5 * (t - 0.5) ** 2


@kernel
def _node(c, base, fx, w, dx, shape, periodic, dpos):
    """Flat index and weight of the c-th node (0 <= c < 3^d) of a stencil; dpos (d,) <- x_i - x_p, m."""
    d = base.shape[0]
    idx = 0
    wt = 1.0
    rest = c
    for k in range(d):
        o = rest % 3
        rest //= 3
        ik = base[k] + o
        if periodic and k == 0:
            ik = ik % shape[0]
        idx = idx * shape[k] + ik
        wt *= w[k, o]
        dpos[k] = (o - fx[k]) * dx
    return idx, wt


@kernel
def p2g(x, v, C, J, b, vol0, mass, mu, kappa, dt, origin, dx, shape, periodic, gm, gp):
    """Scatter particles to the grid: gm (G,) kg and gp (G, d) kg m/s are accumulated (zero them first)."""
    n, d = x.shape
    inv = 1.0 / dx
    tau = np.zeros((d, d))
    aff = np.zeros((d, d))
    base = np.zeros(d, np.int64)
    fx = np.zeros(d)
    w = np.zeros((d, 3))
    dpos = np.zeros(d)
    for p in range(n):
        kirchhoff(b[p], J[p], mu, kappa, d, tau)
        for i in range(d):
            for j in range(d):
                aff[i, j] = mass[p] * C[p, i, j] - dt * vol0[p] * 4.0 * inv * inv * tau[i, j]
        _stencil(x[p], origin, inv, base, fx, w)
        for c in range(3 ** d):
            idx, wt = _node(c, base, fx, w, dx, shape, periodic, dpos)
            gm[idx] += wt * mass[p]
            for i in range(d):
                acc = mass[p] * v[p, i]
                for j in range(d):
                    acc += aff[i, j] * dpos[j]
                gp[idx, i] += wt * acc


@kernel
def grid_update(gm, gp, gv, dt, gravity, origin, dx, shape, periodic, wall_lo, wall_hi,
                floor_y, floor_mode, friction, plate_lo, plate_hi, plate_vel, plate_sticky):
    """Node velocities gv (G, d), m/s, from momentum, gravity (d,) m/s^2 and the boundary rules.

    Walls: at nodes on or beyond wall_lo / wall_hi (d,) the outward velocity component is removed (slip;
    none along x when periodic). Floor (nodes with y <= floor_y): FLOOR_STICKY sets v = 0 (no slip, glued);
    FLOOR_COULOMB removes the approaching normal velocity and reduces the tangential speed by friction
    times it (to zero at most). Plates (boxes plate_lo..plate_hi (P, d) m moving at
    plate_vel (P, d) m/s): a node inside a sticky plate takes its velocity; inside a non-sticky one, the
    velocity component toward the nearest face's inside, relative to the plate, is removed.
    """
    G, d = gp.shape
    xi = np.zeros(d)
    vi = np.zeros(d)
    for i in range(G):
        if gm[i] <= 0.0:
            for k in range(d):
                gv[i, k] = 0.0
            continue
        rem = i
        for k in range(d - 1, -1, -1):
            xi[k] = origin[k] + (rem % shape[k]) * dx
            rem //= shape[k]
        for k in range(d):
            vi[k] = gp[i, k] / gm[i] + dt * gravity[k]
        if floor_mode != FLOOR_NONE and xi[1] <= floor_y:
            if floor_mode == FLOOR_STICKY:
                for k in range(d):
                    vi[k] = 0.0
            elif vi[1] < 0.0:
                vn = -vi[1]
                vi[1] = 0.0
                vt = 0.0
                for k in range(d):
                    vt += vi[k] * vi[k]
                vt = math.sqrt(vt)
                keep = max(0.0, 1.0 - friction * vn / vt) if vt > 0.0 else 0.0
                for k in range(d):
                    vi[k] *= keep
        # Walls after the floor: a wall on the floor's plane must not take the approaching velocity
        # that the floor's friction is proportional to.
        for k in range(d):
            if periodic and k == 0:
                continue
            if xi[k] <= wall_lo[k] and vi[k] < 0.0:
                vi[k] = 0.0
            if xi[k] >= wall_hi[k] and vi[k] > 0.0:
                vi[k] = 0.0
        for q in range(plate_lo.shape[0]):
            inside = True
            for k in range(d):
                if xi[k] < plate_lo[q, k] or xi[k] > plate_hi[q, k]:
                    inside = False
            if not inside:
                continue
            if plate_sticky[q]:
                for k in range(d):
                    vi[k] = plate_vel[q, k]
                continue
            best, axis, sign = 1e300, 0, 1.0
            for k in range(d):
                for sgn in (-1.0, 1.0):
                    gap = (plate_hi[q, k] - xi[k]) if sgn > 0 else (xi[k] - plate_lo[q, k])
                    if gap < best:
                        best, axis, sign = gap, k, sgn
            rel = vi[axis] - plate_vel[q, axis]
            if rel * sign < 0.0:  # moving into the plate through its nearest face
                vi[axis] = plate_vel[q, axis]
        for k in range(d):
            gv[i, k] = vi[k]


@kernel
def g2p(x, v, C, J, b, gv, gamma, mu, sigma_y, eta, m, dt, origin, dx, shape, periodic, lo, hi):
    """Gather grid velocities to the particles, move them, update J and bbar_e (return map), in place.

    Positions are kept in [lo, hi] (d,) m (wrapped along x when periodic). gamma (N,) <- plastic rate, 1/s.
    """
    n, d = x.shape
    inv = 1.0 / dx
    base = np.zeros(d, np.int64)
    fx = np.zeros(d)
    w = np.zeros((d, 3))
    dpos = np.zeros(d)
    f = np.zeros((3, 3))
    work = np.zeros((3, 3))
    for p in range(n):
        _stencil(x[p], origin, inv, base, fx, w)
        for i in range(d):
            v[p, i] = 0.0
            for j in range(d):
                C[p, i, j] = 0.0
        for c in range(3 ** d):
            idx, wt = _node(c, base, fx, w, dx, shape, periodic, dpos)
            for i in range(d):
                v[p, i] += wt * gv[idx, i]
                for j in range(d):
                    C[p, i, j] += 4.0 * inv * inv * wt * gv[idx, i] * dpos[j]
        for k in range(d):
            xk = x[p, k] + dt * v[p, k]
            if periodic and k == 0:
                span = shape[0] * dx
                xk = origin[0] + (xk - origin[0]) % span
            else:
                xk = min(max(xk, lo[k]), hi[k])
            x[p, k] = xk
        for i in range(3):
            for j in range(3):
                f[i, j] = (1.0 if i == j else 0.0) + (dt * C[p, i, j] if (i < d and j < d) else 0.0)
        J[p] *= det3(f)
        gamma[p] = return_map(b[p], f, mu, sigma_y, eta, m, dt, work)


class Grid:
    """A regular background grid: origin (d,) m (node 0), spacing dx m, shape (d,) nodes; periodic along x or not."""

    def __init__(self, origin, dx, shape, periodic=False):
        self.origin = np.asarray(origin, float)
        self.dx = float(dx)
        self.shape = np.asarray(shape, np.int64)
        self.periodic = bool(periodic)
        self.size = int(np.prod(self.shape))

    @classmethod
    def covering(cls, lo, hi, dx, pad=3, shift=None):
        """A grid over the box [lo, hi] (m) with `pad` cells beyond it on every side; shift (d,) in cells
        moves the node lattice (the reference grid need not align with the domain's round numbers)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        sh = np.zeros(len(lo)) if shift is None else np.asarray(shift, float)
        origin = lo - (pad - sh) * dx
        shape = np.ceil((hi - origin) / dx).astype(np.int64) + pad + 1
        return cls(origin, dx, shape)

    def node_positions(self):
        """Positions of all nodes (G, d), m, in the flat order of the kernels."""
        axes = [self.origin[k] + self.dx * np.arange(self.shape[k]) for k in range(len(self.shape))]
        return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)


class Particles:
    """Material points: x (N, d) m, v (N, d) m/s, C (N, d, d) 1/s, J (N,), b = bbar_e (N, 3, 3),
    vol0 (N,) m^3 (m^2 in 2D: per unit depth), mass (N,) kg, gamma (N,) 1/s (last plastic rate)."""

    def __init__(self, x, vol0, rho, v0=None):
        n, d = x.shape
        self.x = np.ascontiguousarray(x, float)
        self.v = np.zeros((n, d)) if v0 is None else np.ascontiguousarray(np.broadcast_to(v0, (n, d)), float)
        self.C = np.zeros((n, d, d))
        self.J = np.ones(n)
        self.b = np.ascontiguousarray(np.broadcast_to(np.eye(3), (n, 3, 3)))
        self.vol0 = np.ascontiguousarray(np.broadcast_to(vol0, (n,)), float)
        self.mass = self.vol0 * float(rho)
        self.gamma = np.zeros(n)


class Simulation:
    """The time loop: particles, a grid, material parameters and boundaries (`scene.Boundaries`).

    material: dict of mu, kappa (Pa), sigma_y (Pa), eta (Pa s^m), m, rho (kg/m^3). The step is
    dt = cfl dx / (c + max speed) with c = sqrt((kappa + 4/3 mu) / rho) the elastic wave speed, cut to
    land on the requested times exactly.
    """

    def __init__(self, particles, grid, material, boundaries, gravity, cfl=0.3):
        self.p = particles
        self.grid = grid
        self.mat = {k: float(v) for k, v in material.items()}
        self.bnd = boundaries
        self.gravity = np.asarray(gravity, float)
        self.cfl = float(cfl)
        self.t = 0.0
        self.steps = 0
        self.gm = np.zeros(grid.size)
        self.gp = np.zeros((grid.size, len(self.gravity)))
        self.gv = np.zeros_like(self.gp)
        self.wave_speed = math.sqrt((self.mat["kappa"] + 4.0 / 3.0 * self.mat["mu"]) / self.mat["rho"])

    def stable_dt(self):
        """The step for the current state, s."""
        vmax = float(np.sqrt(np.max(np.sum(self.p.v ** 2, axis=1)))) if len(self.p.x) else 0.0
        vmax = max(vmax, self.bnd.max_plate_speed(self.t))
        return self.cfl * self.grid.dx / (self.wave_speed + vmax)

    def step(self, dt):
        """Advance by dt (s)."""
        p, g, mt, bd = self.p, self.grid, self.mat, self.bnd
        self.gm[:] = 0.0
        self.gp[:] = 0.0
        p2g(p.x, p.v, p.C, p.J, p.b, p.vol0, p.mass, mt["mu"], mt["kappa"], dt, g.origin, g.dx, g.shape,
            g.periodic, self.gm, self.gp)
        lo, hi, vel, sticky = bd.plate_arrays(self.t + dt)
        grid_update(self.gm, self.gp, self.gv, dt, self.gravity, g.origin, g.dx, g.shape, g.periodic,
                    bd.wall_lo, bd.wall_hi, bd.floor_y, bd.floor_mode, bd.friction, lo, hi, vel, sticky)
        g2p(p.x, p.v, p.C, p.J, p.b, self.gv, p.gamma, mt["mu"], mt["sigma_y"], mt["eta"], mt["m"], dt,
            g.origin, g.dx, g.shape, g.periodic, bd.clamp_lo, bd.clamp_hi)
        self.t += dt
        self.steps += 1

    def advance_to(self, t_end):
        """Step until time t_end (s), the last step shortened to land on it."""
        while self.t < t_end - 1e-12:
            dt = min(self.stable_dt(), t_end - self.t)
            self.step(dt)
            if not np.all(np.isfinite(self.p.x)):
                raise FloatingPointError(f"reference simulation blew up at t = {self.t:.4g} s")
