"""Slump of a yield-stress column (2D plane strain and 3D) against Pashias et al. (1996) and Roussel & Coussot (2005).

Setup: a column of height H = 0.1 m and half-width (2D) or radius (3D) R0 = 0.05 m (H/D = 1, the
slump-cone geometry of Pashias) stands on the floor and is released at t = 0 under gravity. The
whole column is simulated: the domain's slip walls are not usable as symmetry planes (a half column
against a slip wall at x = 0 collapsed to 0.43 H at tau' = 0.3 where the whole column stands at 0.97 H;
material next to a slip wall yields spuriously). It is run until the kinetic energy has died out; the
final height is the drop of the highest particle near the axis (the same particle-based surface
estimate before and after).

Dimensionless yield stress tau' = tau_y / (rho g H) with the simple-shear yield stress of this von Mises
model, tau_y = sigma_y / sqrt(3).

Pashias et al. (1996), the cylindrical slump (after Murata's cone analysis): the weight above a depth z
loads a horizontal slice in uniaxial compression; slices below h0 = 2 tau_y / (rho g) yield and spread
until their stress is back at the yield stress, which gives the dimensionless slump
    s' = 1 - 2 tau' (1 - ln(2 tau')),      valid for 0 < 2 tau' <= 1.
The derivation uses the Tresca yield condition (compressive stress 2 tau_y). For this von Mises model the
compressive yield stress is 2 tau_y in plane strain (s = (p/2, -p/2, 0), ||s|| = p/sqrt(2) = sqrt(2/3)
sigma_y gives p = 2 sigma_y / sqrt(3) = 2 tau_y), so the formula holds as written in 2D; in 3D uniaxial
compression it is sigma_y = sqrt(3) tau_y, so the von Mises version replaces 2 tau' by sqrt(3) tau'
(both curves are drawn). The 1D analysis ignores shear at the base and the bulging of the column, so
it is meant for slumps that stay columns: final height of the order of the final radius or more
(flagged in the table by h_f / R_f >= 0.5).

Roussel & Coussot (2005), the spread (lubrication) regime: a thin heap at rest on a no-slip floor has
h dh/dr = tau_y / (rho g), i.e. h(r)^2 = 2 tau_y (R - r) / (rho g); its volume Omega gives
    3D:  tau_y = 225 rho g Omega^2 / (128 pi^2 R^5),
    2D (plane strain, per unit depth, area A of the whole heap): A = (4/3) sqrt(2 tau_y / (rho g)) L^(3/2),
with R (or L) the final spread radius (half-length). Valid when the heap is thin, h_f << R_f
(flagged by h_f / R_f <= 0.2), and the flow slow enough for inertia to be negligible.

Floors: the Pashias analysis assumes no shear stress at the base, so it is compared with runs on a
frictionless floor; the lubrication heap of Roussel & Coussot assumes no slip, so it is compared with
runs on a sticky floor (small tau' only, where the heap is thin).

Error: final height h_f / H against the formula at each tau' (and, in the spread regime, spread radius
against R&C), at 3 resolutions H/dx, with the self-convergence of h_f between resolutions.

Usage: python -m experiments slump [--quick]. Writes experiments/results/slump[_quick].png/.md.
"""
from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C
from jaxfoam._scene import PlausibilityWarning

NAME = "slump"
HEIGHT = 0.1            # initial column height H, m
RADIUS = 0.05           # initial half-width (2D) / radius (3D), m
RHO = 80.0              # kg/m^3 (foam)
G = 9.81                # m/s^2
# Stiff enough that the elastic compression under the column's own weight (rho g H / mu ~ 8%, half of it
# on average) stays small against the slump; eta and m only set how fast it stops (Bingham, m = 1; eta
# large enough that the collapse is not inertial: eta / (rho g H) = 0.13 s ~ sqrt(H / g)).
BASE = jaxfoam.Params(mu=1000.0, kappa=5000.0, sigma_y=1.0, eta=10.0, m=1.0, rho=RHO)  # eta: FLOOR_SETTINGS
# Per floor: (eta Pa s, run time s). Frictionless: eta / (rho g H) = 0.13 s ~ sqrt(H/g) keeps the collapse
# from being inertial and it stops within ~1 s. Sticky (thin heaps): a thin layer creeps slowly, so a
# smaller eta and a longer run (the final / peak kinetic energy is reported).
FLOOR_SETTINGS = {"slip": (10.0, 1.5), "sticky": (2.0, 3.0)}
FRAMES = 24
CFL = 0.3               # jaxfoam.CFL
DOMAIN = {2: 0.3, 3: 0.2}    # half-extent of the floor, m: holds the widest spreads (2D tau' = 0.02: 0.24 m)


def pashias(tau_p, factor=2.0):
    """Dimensionless slump s' = 1 - f tau' (1 - ln(f tau')) for f tau' <= 1 (else 0); f = 2 (Tresca)
    or sqrt(3) (von Mises, uniaxial compression)."""
    a = np.minimum(factor * np.asarray(tau_p, float), 1.0)
    return 1.0 - a * (1.0 - np.log(a))


def rc_spread(tau_y, dim):
    """Roussel & Coussot final spread radius (3D) or half-length (2D), m, for the simulated volume."""
    if dim == 3:
        omega = math.pi * RADIUS ** 2 * HEIGHT
        return (225.0 * RHO * G * omega ** 2 / (128.0 * math.pi ** 2 * tau_y)) ** 0.2
    area = 2.0 * RADIUS * HEIGHT
    return (3.0 * area / (4.0 * math.sqrt(2.0 * tau_y / (RHO * G)))) ** (2.0 / 3.0)


def slump_scene(dim: int, floor: str = "slip"):
    ext = DOMAIN[dim]
    lo = [-ext, 0.0] + ([-ext] if dim == 3 else [])
    hi = [ext, 1.2 * HEIGHT] + ([ext] if dim == 3 else [])
    if dim == 2:
        shape = {"type": "box", "min": [-RADIUS, 0.0], "max": [RADIUS, HEIGHT]}
    else:  # a cylinder: the ellipse primitive cut by the floor; its height is clipped by a box test below
        shape = {"type": "ellipse", "center": [0.0, HEIGHT / 2, 0.0], "radii": [RADIUS, 1e3, RADIUS]}
    spec = {"kind": "drop", "dim": dim, "gravity": [0.0, -G] + [0.0] * (dim - 2), "density": RHO,
            "kappa": float(BASE.kappa), "domain": {"min": lo, "max": hi},
            "floor": {"y": 0.0, "friction": "sticky" if floor == "sticky" else 0.0}, "initial_shape": shape,
            "notes": "slump of a yield-stress column"}
    with warnings.catch_warnings():  # the 3D cylinder is an ellipse the domain clips on purpose
        warnings.simplefilter("ignore", PlausibilityWarning)
        return jaxfoam.load_scene(spec)


def initial_state(scene, dx):
    """Particles of the column (the 3D cylinder is the ellipse shape cut at y = H)."""
    pts, vol = jaxfoam.sample_particles(scene, dx, None, seed=0)
    pts = pts[pts[:, 1] <= HEIGHT]
    n = len(pts)
    return jaxfoam.make_state(pts, np.full(n, vol), np.full(n, vol * RHO), dtype=jnp.float64)


def run(dim: int, res: int, tau_ps, floor: str = "slip"):
    """All tau' at H/dx = res on a "slip" (frictionless) or "sticky" floor, in one vmapped rollout.

    Returns dict(dim, res, tau_p (k,), h (k,) final height / H, spread (k,) m, ke (k,) final / peak kinetic
    energy, series of heights (k, frames), ...).
    """
    scene = slump_scene(dim, floor)
    dx = HEIGHT / res
    grid = jaxfoam.make_grid(scene, dx)
    st = initial_state(scene, dx)
    tau_ps = np.asarray(tau_ps, float)
    sigma_y = math.sqrt(3.0) * tau_ps * RHO * G * HEIGHT
    eta, run_time = FLOOR_SETTINGS[floor]
    params = C.stack_trees([BASE.replace(sigma_y=float(s), eta=eta) for s in sigma_y])
    c = jaxfoam.wave_speed(BASE)
    vmax = math.sqrt(2.0 * G * HEIGHT)
    frame_dt = run_time / FRAMES
    substeps = int(math.ceil(frame_dt / (CFL * dx / (c + vmax))))
    dt = frame_dt / substeps
    axis_band = 0.25 * RADIUS

    def observe(s, p):
        r = jnp.abs(s.x[:, 0]) if dim == 2 else jnp.sqrt(s.x[:, 0] ** 2 + s.x[:, 2] ** 2)
        near = (r < axis_band) & s.active
        top = jnp.max(jnp.where(near, s.x[:, 1], -jnp.inf))
        spread = jnp.max(jnp.where(s.active, r, 0.0))
        ke = 0.5 * jnp.sum(jnp.where(s.active, s.mass * jnp.sum(s.v * s.v, axis=1), 0.0))
        return dict(top=top, spread=spread, ke=ke)

    def one(p):
        return C.rollout(st, p, scene, dt, grid=grid, n_frames=FRAMES, substeps=substeps, observe=observe)[1]

    with C.Timer() as tm:
        fr = jax.device_get(jax.jit(jax.vmap(one))(params))
    r0 = np.abs(np.asarray(st.x[:, 0])) if dim == 2 else np.hypot(np.asarray(st.x[:, 0]), np.asarray(st.x[:, 2]))
    top0 = float(np.max(np.asarray(st.x[:, 1])[r0 < axis_band]))
    spread0 = float(np.max(r0))
    h = 1.0 - (top0 - fr["top"][:, -1]) / HEIGHT
    # The outermost particle moved by (final - initial); the edge of the heap moved by the same amount.
    return dict(dim=dim, res=res, floor=floor, dx=dx, tau_p=tau_ps, h=h, h_series=1.0 - (top0 - fr["top"]) / HEIGHT,
                spread=fr["spread"][:, -1] - spread0 + RADIUS,
                ke=fr["ke"][:, -1] / np.max(fr["ke"], axis=1), particles=len(st.x), steps=substeps * FRAMES,
                seconds=tm.seconds)


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    if args.quick:
        plan = [(2, (8,), (0.05, 0.15, 0.3), "slip"), (2, (8,), (0.02,), "sticky"), (3, (6,), (0.15,), "slip")]
    else:
        plan = [(2, (8, 16, 24), (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4), "slip"),
                (2, (8, 16, 24), (0.01, 0.02), "sticky"),
                (3, (4, 6, 8), (0.05, 0.1, 0.2, 0.3), "slip"),
                (3, (4, 6), (0.01, 0.02), "sticky")]
    runs = []
    for dim, resolutions, tau_ps, floor in plan:
        for res in resolutions:
            r = run(dim, res, tau_ps, floor)
            print(f"{dim}D {floor} H/dx={res}: h_f/H {np.round(r['h'], 4).tolist()} spread "
                  f"{np.round(r['spread'], 4).tolist()} KE end/peak {np.round(r['ke'], 5).tolist()} "
                  f"({r['seconds']:.0f} s)", flush=True)
            runs.append(r)
    chart(runs, args.quick)
    table(runs, args.quick)


def chart(runs, quick):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.4))
    tp = np.linspace(0.005, 0.55, 300)
    for col, dim in enumerate((2, 3)):
        ax = axes[0, col]
        ax.plot(tp, 1.0 - pashias(tp, 2.0), "k-", label="Pashias 1996 (compressive yield 2 tau_y)")
        if dim == 3:
            ax.plot(tp, 1.0 - pashias(tp, math.sqrt(3.0)), "k--", label="Pashias, von Mises uniaxial yield sqrt(3) tau_y")
        for k, r in enumerate([r for r in runs if r["dim"] == dim and r["floor"] == "slip"]):
            ax.plot(r["tau_p"], r["h"], "osD^"[k % 4], color=f"C{k}", label=f"MPM, frictionless floor, H/dx={r['res']}")
        ax.set_xlabel("tau' = tau_y / (rho g H),  tau_y = sigma_y / sqrt(3)")
        ax.set_ylabel("final height / H = 1 - s'")
        ax.set_title(f"{dim}D {'plane-strain block' if dim == 2 else 'cylinder'}: slump height")
        ax.set_ylim(0, 1.05)
        ax.legend(fontsize=7)
        ax = axes[1, col]
        rc_tp = np.linspace(0.005, 0.06, 100)
        ax.plot(rc_tp, [rc_spread(t * RHO * G * HEIGHT, dim) for t in rc_tp], "k:",
                label="Roussel & Coussot 2005 thin heap (no-slip floor)")
        for k, r in enumerate([r for r in runs if r["dim"] == dim and r["floor"] == "sticky"]):
            ax.plot(r["tau_p"], r["spread"], "osD^"[k % 4], color=f"C{k}", label=f"MPM, sticky floor, H/dx={r['res']}")
        ax.set_xlabel("tau'")
        ax.set_ylabel("final spread radius (3D) / half-length (2D), m")
        ax.set_title(f"{dim}D spread of thin heaps")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return C.save_fig(fig, NAME, quick)


def table(runs, quick):
    parts = [f"Column H = {HEIGHT} m, R0 = {RADIUS} m, rho = {RHO} kg/m^3, mu = {float(BASE.mu):g} Pa, "
             f"kappa = {float(BASE.kappa):g} Pa, m = 1, CFL {CFL}; (eta Pa s, run time s) per floor: {FLOOR_SETTINGS}. "
             "'Pashias' is 1 - s' with 2 tau' (3D also with the von Mises sqrt(3) tau'); 'R&C' is the thin-heap "
             "spread; h_f/R_f is the measured aspect ratio (Pashias needs a column, h_f/R_f >~ 0.5; R&C a thin "
             "heap, h_f/R_f <~ 0.2). KE ratio: final / peak kinetic energy (small when the heap has stopped).\n\n"]
    for dim in (2, 3):
        for floor in ("slip", "sticky"):
            rr = [r for r in runs if r["dim"] == dim and r["floor"] == floor]
            if not rr:
                continue
            rows = []
            for r in rr:
                for k, t in enumerate(r["tau_p"]):
                    rc = rc_spread(t * RHO * G * HEIGHT, dim)
                    pv = float(1.0 - pashias(t, 2.0))
                    pvm = float(1.0 - pashias(t, math.sqrt(3.0))) if dim == 3 else float("nan")
                    rows.append([r["res"], float(t), float(r["h"][k]), pv, float(r["h"][k]) - pv, pvm,
                                 float(r["spread"][k]), rc, float(r["spread"][k] / rc - 1.0),
                                 float(r["h"][k] * HEIGHT / r["spread"][k]), float(r["ke"][k])])
            floor_name = "frictionless floor (Pashias)" if floor == "slip" else "sticky floor (Roussel & Coussot)"
            parts.append(f"## {dim}D, {floor_name}\n\n" + C.md_table(
                ["H/dx", "tau'", "h_f/H MPM", "Pashias", "MPM - Pashias", "Pashias (von Mises)", "spread m",
                 "R&C spread m", "spread rel. error", "h_f/R_f", "KE ratio"], rows))
            if len(rr) >= 3:
                dh = [float(np.max(np.abs(rr[i + 1]["h"] - rr[i]["h"]))) for i in range(len(rr) - 1)]
                ds = [float(np.max(np.abs(rr[i + 1]["spread"] / rr[i]["spread"] - 1))) for i in range(len(rr) - 1)]
                parts.append(f"\nSelf-convergence (max over tau'): h_f/H changes by {dh[0]:.4g} from H/dx={rr[0]['res']} "
                             f"to {rr[1]['res']} and {dh[1]:.4g} from {rr[1]['res']} to {rr[2]['res']}; the spread by "
                             f"{ds[0]:.3g} and {ds[1]:.3g} (relative).\n")
            parts.append("\n" + C.md_table(["H/dx", "particles", "steps", "wall s (all tau')"],
                                           [[r["res"], r["particles"], r["steps"], r["seconds"]] for r in rr]) + "\n")
    return C.write_md(NAME, quick, "Slump of a yield-stress column", "".join(parts))


if __name__ == "__main__":
    main()
