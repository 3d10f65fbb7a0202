"""Gravity-driven (Poiseuille) channel flow of the Herschel-Bulkley foam against the analytic plug-flow profile.

Setup (2D plane strain): a column of foam fills the gap of width W between two sticky vertical plates at
x = -W/2 and x = +W/2; gravity g points along -y; the column (COLUMN_LENGTH gaps long) has free surfaces
at its top and bottom, so the body force rho g drives the flow alone. (The domain's walls only slip, so
a periodic channel is not available; a long free column is the same fully developed flow far from its
ends.) The particles start in the analytic steady state (velocity and elastic shear strain) and are
run for RUN_TIME (> 20 relaxation times); the middle section (one gap long, tracked by particle) is
compared with the analytic profile.

Analytic profile. Fully developed flow is simple shear in the x-y plane with velocity u(x) e_(-y);
momentum balance gives |tau_xy| = G |x| with G = rho g (N/m^3). In simple shear this model's flow curve
is tau_xy = T(gdot) (experiments/rheometer.py, `jaxfoam.hb_steady_shear_stress`); with small elastic
strain T(gdot) = tau_y + K gdot^m with
    tau_y = sigma_y / sqrt(3)   (the von Mises yield surface ||s|| = sqrt(2/3) sigma_y with ||s|| = sqrt(2) tau_xy),
    K = eta 2^(-(m+1)/2)         (the plastic rate gamma = gdot / sqrt(2) and tau_xy = ||s|| / sqrt(2)).
The plug is |x| <= x_p = tau_y / G, and for |x| >= x_p
    u(x) = m / ((m + 1) G K^(1/m)) [(G W/2 - tau_y)^(1 + 1/m) - (G |x| - tau_y)^(1 + 1/m)],
u = u(x_p) in the plug. The reference used for errors integrates the exact finite-strain flow curve
(gdot(tau) by inverting `jaxfoam.hb_steady_shear_stress` on a fine table), u(x) = int_|x|^{W/2} gdot(G xi) dxi;
the closed form above differs from it by the finite-strain terms (table).

Error: RMS over the particles of the middle section of (v_particle - u(x_particle)) / u_max, averaged
over the last half of the frames, at 3 resolutions W/dx; observed order of convergence. The effective
driving G_eff (slope of the particles' tau_xy(x) in the section) is reported with the error against
u(x; G_eff), which separates a momentum-balance error from a constitutive one.

Usage: python -m experiments poiseuille [--quick]. Writes experiments/results/poiseuille[_quick].png/.md.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C

NAME = "poiseuille"
# Foam parameters (SI): plug half-width x_p = 0.3 W/2, wall shear rate ~2 1/s, wall stress / mu = 0.04.
PARAMS = jaxfoam.Params(mu=500.0, kappa=2000.0, sigma_y=10.0, eta=16.0, m=0.5, rho=80.0)
WIDTH = 0.1                 # channel gap W, m
PLUG_FRACTION = 0.3         # x_p / (W/2): sets the driving G = tau_y / (0.3 W/2)
COLUMN_LENGTH = 10.0        # column length / W: the middle section is 4.5 W from the free ends
FALL_ROOM = 0.05            # m of empty channel below the column (it falls ~1.5 cm in the run)
RUN_TIME = 0.3              # s: > 10 elastic-viscous times eta_eff/mu (0.02 s), 4 momentum times (0.08 s)
FRAMES = 20                 # frames recorded; the last half is averaged
CFL = 0.3                   # jaxfoam.CFL
PPC = 4


def driving():
    """Body force G = rho g, N/m^3, and gravity g, m/s^2."""
    tau_y = float(PARAMS.sigma_y) / math.sqrt(3.0)
    G = tau_y / (PLUG_FRACTION * WIDTH / 2)
    return G, G / float(PARAMS.rho)


def profile_rigid(x, G=None):
    """Closed-form HB plug-flow speed (m/s, downward positive) at x (m), small-elastic-strain flow curve.

    G: driving stress gradient, N/m^3 (default rho g of the setup).
    """
    G = driving()[0] if G is None else G
    m, eta = float(PARAMS.m), float(PARAMS.eta)
    tau_y = float(PARAMS.sigma_y) / math.sqrt(3.0)
    K = eta * 2.0 ** (-(m + 1.0) / 2.0)
    ax = np.maximum(np.abs(x), tau_y / G)
    e = 1.0 + 1.0 / m
    return m / ((m + 1.0) * G * K ** (1.0 / m)) * ((G * WIDTH / 2 - tau_y) ** e - (G * ax - tau_y) ** e)


def profile_exact(x, G=None):
    """Plug-flow speed (m/s, downward positive) at x (m) from the exact finite-strain flow curve,
    u(x) = int_|x|^{W/2} gdot(G xi) dxi, integrated numerically. G: N/m^3 (default rho g)."""
    G = driving()[0] if G is None else float(G)
    rates, taus, tau_y0 = _flow_curve()
    xi = np.linspace(0.0, WIDTH / 2, 20001)
    tau = G * xi
    gdot = np.where(tau > tau_y0, np.exp(np.interp(tau, taus, np.log(rates))), 0.0)
    seg = 0.5 * (gdot[1:] + gdot[:-1]) * np.diff(xi)   # trapezoid, accumulated from the wall inwards
    u = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
    return np.interp(np.abs(x), xi, u)


@functools.lru_cache(maxsize=1)
def _flow_curve():
    """The exact flow curve tabulated once: (rates (n,) 1/s, tau_xy (n,) Pa, yield limit Pa)."""
    rates = np.logspace(-12, 3, 4000)
    return rates, jaxfoam.hb_steady_shear_stress(rates, PARAMS), float(jaxfoam.hb_steady_shear_stress(0.0, PARAMS))


def channel_scene(res: int):
    """Scene at resolution res = W/dx. Returns (scene, dx m, (y0, y1) of the initial column m)."""
    dx = WIDTH / res
    tp = 3 * dx
    lift = 1e-6 * dx
    _, g = driving()
    y0 = FALL_ROOM
    y1 = y0 + COLUMN_LENGTH * WIDTH
    top = y1 + 0.02
    half = WIDTH / 2

    def wall(sign):
        return {"center": [sign * (half + tp), top / 2], "half_size": [tp + lift, top], "sticky": True}

    spec = {"kind": "squeeze", "dim": 2, "gravity": [0.0, -g], "density": float(PARAMS.rho),
            "kappa": float(PARAMS.kappa), "domain": {"min": [-half - 2 * tp, 0.0], "max": [half + 2 * tp, top]},
            "plates": [wall(-1.0), wall(1.0)],
            "initial_shape": {"type": "box", "min": [-half, y0], "max": [half, y1]},
            "notes": "gravity-driven channel flow between two sticky walls"}
    return jaxfoam.load_scene(spec), dx, (y0, y1)


def initial_state(scene, dx):
    """Particles of the column carrying the analytic steady state: velocity u(x) downward and the
    small-strain elastic shear bbar_xy = G x / mu (renormalized to det 1), so the run starts near steady."""
    st = jaxfoam.init_state(scene, dx, PPC, rho=float(PARAMS.rho))
    G, _ = driving()
    x = np.asarray(st.x[:, 0])
    v = np.zeros((len(x), 2))
    v[:, 1] = -profile_exact(x)
    b = np.tile(np.eye(3), (len(x), 1, 1))
    b[:, 0, 1] = b[:, 1, 0] = G * x / float(PARAMS.mu)
    b /= np.linalg.det(b)[:, None, None] ** (1.0 / 3.0)
    active = np.asarray(st.active)
    return st.replace(v=jnp.asarray(np.where(active[:, None], v, 0.0)),
                      bbar_e=jnp.asarray(np.where(active[:, None, None], b, np.eye(3)[None])))


def run(res: int, cfl: float = CFL):
    """One resolution W/dx and CFL number (dt = cfl dx / (c + 2 u_max)).

    Returns dict(res, cfl, dx, error series, errors against u(x; G) and u(x; G_eff), plug speed, ...)."""
    scene, dx, (y0, y1) = channel_scene(res)
    grid = jaxfoam.make_grid(scene, dx)
    st = initial_state(scene, dx)
    G, _ = driving()
    u_ref = float(profile_exact(0.0))
    c = jaxfoam.wave_speed(PARAMS)
    substeps = int(math.ceil(RUN_TIME / FRAMES / (cfl * dx / (c + 2 * u_ref))))
    dt = RUN_TIME / FRAMES / substeps
    ymid = 0.5 * (y0 + y1)
    section = np.asarray(st.active) & (np.abs(np.asarray(st.x[:, 1]) - ymid) < WIDTH / 2)

    def observe(s, p):
        return dict(x=s.x[:, 0], v=-s.v[:, 1], txy=p.mu * jaxfoam.dev(s.bbar_e)[:, 0, 1])

    f = jax.jit(functools.partial(C.rollout, grid=grid, n_frames=FRAMES, substeps=substeps, observe=observe))
    with C.Timer() as tm:
        _, frames = f(st, PARAMS, scene, dt)
        frames = jax.device_get(frames)
    x, v, txy = frames["x"][:, section], frames["v"][:, section], frames["txy"][:, section]
    err = np.sqrt(np.mean((v - profile_exact(x)) ** 2, axis=1)) / u_ref
    last = slice(FRAMES - FRAMES // 2, FRAMES)
    # Effective driving of the section: slope of tau_xy(x) (equals G in a fully developed flow).
    g_eff = float(np.mean([np.polyfit(x[k], txy[k], 1)[0] for k in range(FRAMES)[last]]))
    err_eff = np.sqrt(np.mean((v[last] - profile_exact(x[last], g_eff)) ** 2, axis=1)) / u_ref
    plug = np.abs(x[last]) < 0.5 * PLUG_FRACTION * WIDTH / 2
    return dict(res=res, cfl=cfl, dx=dx, err_series=err, err=float(err[last].mean()), err_eff=float(err_eff.mean()),
                g_eff=g_eff / G, x=x[-1], v=v[last].mean(axis=0), plug=float(np.mean(v[last][plug])),
                plug_eff=float(profile_exact(0.0, g_eff)),
                particles=int(st.active.sum()), steps=substeps * FRAMES, seconds=tm.seconds)


def _plug_ratio(r) -> float | str:
    """Plug speed over the analytic one at G_eff; "-" when G_eff is below the yield limit (no flow predicted)."""
    return r["plug"] / r["plug_eff"] if r["plug_eff"] > 0 else "- (G_eff below yield)"


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    if args.quick:
        plan = [(8, 0.3), (16, 0.3), (8, 0.1)]
    else:
        plan = [(8, 0.3), (16, 0.3), (32, 0.3), (8, 0.05), (8, 0.1), (8, 0.2), (8, 0.5), (16, 0.1), (16, 0.05)]
    runs = []
    for res, cfl in plan:
        r = run(res, cfl)
        print(f"W/dx={res} CFL={cfl}: rms error {r['err']:.4g} (G), {r['err_eff']:.4g} (G_eff = {r['g_eff']:.4f} G) "
              f"of u_max, plug {r['plug']:.5g} m/s ({r['seconds']:.0f} s)", flush=True)
        runs.append(r)
    u_max = float(profile_exact(0.0))
    default = [r for r in runs if r["cfl"] == CFL]

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.4))
    ax = axes[0]
    xs = np.linspace(-WIDTH / 2, WIDTH / 2, 401)
    ax.plot(xs * 100, profile_exact(xs) * 100, "k-", lw=2, label="analytic HB plug flow (finite-strain flow curve)")
    ax.plot(xs * 100, profile_rigid(xs) * 100, "k:", label="closed form, small elastic strain")
    for k, r in enumerate(runs):
        if r["cfl"] == CFL or r is runs[-1]:
            o = np.argsort(r["x"])
            ax.plot(r["x"][o] * 100, r["v"][o] * 100, ".", ms=2, color=f"C{k}",
                    label=f"MPM particles, W/dx={r['res']}, CFL={r['cfl']}")
    ax.axvspan(-PLUG_FRACTION * WIDTH / 2 * 100, PLUG_FRACTION * WIDTH / 2 * 100, color="0.9", label="plug")
    ax.set_xlabel("x (cm)")
    ax.set_ylabel("downward speed (cm/s)")
    ax.set_title("Steady channel flow profile (middle section)")
    ax.legend(fontsize=7)
    ax = axes[1]
    for k, res in enumerate(sorted({r["res"] for r in runs})):
        rr = sorted([r for r in runs if r["res"] == res], key=lambda r: r["cfl"])
        ax.plot([r["cfl"] for r in rr], [r["plug"] / u_max for r in rr], "-o", color=f"C{k}", label=f"W/dx={res}")
    ax.axhline(1.0, color="k", lw=1)
    ax.set_xlabel("CFL number (dt = CFL dx / (c + 2 u_max))")
    ax.set_ylabel("MPM plug speed / analytic")
    ax.set_title("Plug speed against time step")
    ax.legend(fontsize=8)
    fig.tight_layout()
    C.save_fig(fig, NAME, args.quick)

    G, g = driving()
    ords = C.orders([r["dx"] for r in default], [r["err"] for r in default])
    ords_eff = C.orders([r["dx"] for r in default], [r["err_eff"] for r in default])
    order_of = {id(r): (o, oe) for r, o, oe in zip(default, ords, ords_eff)}
    body = (f"Gap W = {WIDTH} m, G = rho g = {G:.4g} N/m^3 (g = {g:.4g} m/s^2), tau_y = sigma_y/sqrt(3) = "
            f"{float(PARAMS.sigma_y) / math.sqrt(3):.4g} Pa, plug half-width x_p = {PLUG_FRACTION} W/2; "
            f"mu = {float(PARAMS.mu):g} Pa, kappa = {float(PARAMS.kappa):g} Pa, eta = {float(PARAMS.eta):g} Pa s^m, "
            f"m = {float(PARAMS.m):g}; column {COLUMN_LENGTH:g} W long, run {RUN_TIME:g} s from the analytic state. "
            f"Analytic centre-line speed u_max = {u_max:.5g} m/s (closed form, small strain: "
            f"{float(profile_rigid(0.0)):.5g} m/s).\n\n"
            "Errors are RMS(v - u)/u_max over the middle section, averaged over the last half of the frames: "
            "against u(x; G = rho g), and against u(x; G_eff) with G_eff the measured slope of tau_xy(x) in the "
            "section. Orders are between successive resolutions at the default CFL = 0.3.\n\n"
            + C.md_table(["W/dx", "CFL", "dx m", "particles", "steps", "error vs u(G)", "order", "G_eff/G",
                          "error vs u(G_eff)", "order", "plug / u_max(G)", "plug / u_max(G_eff)", "wall s"],
                         [[r["res"], r["cfl"], r["dx"], r["particles"], r["steps"], r["err"],
                           order_of.get(id(r), ("", ""))[0], r["g_eff"], r["err_eff"], order_of.get(id(r), ("", ""))[1],
                           r["plug"] / u_max, _plug_ratio(r), r["seconds"]] for r in runs]))
    C.write_md(NAME, args.quick, "Poiseuille (gravity-driven channel) flow of the HB foam", body)


if __name__ == "__main__":
    main()
