"""Where the methods fail: explicit time step, return-map solvers, float32.

1. Time step. A free 2D block (no gravity, no walls touching) starts with a smooth velocity field of
   amplitude V0 = 1% of the P-wave speed c = sqrt((kappa + 4/3 mu)/rho) and is run for a fixed number of
   substeps at dt = CFL dx / (c + V0). Over stiffness (mu 1e1..1e5 Pa, kappa/mu 3..100) and CFL 0.1..2, a
   run fails when a value turns non-finite or the total energy (kinetic + stored, `jaxfoam.energy_density`
   times the initial volumes) rises above 1.05 of its initial value (the model only dissipates). The
   theoretical line is the classical explicit bound dt = dx / c (CFL = 1) of the P wave.

2. Return map. The scalar HB equation h(gamma) = eta gamma^m + a gamma - b = 0 (a = 2 mubar dt,
   b = s_pre - sqrt(2/3) sigma_y) over m in [0.1, 3], eta in {0} U [1e-4, 1e4] Pa s^m and extreme strains
   (b / mu from 1e-10 to 1e4, dt from 1e-7 to 1e-2 s), solved by
     - the default solver (`jaxfoam.hb_rate`: Halley steps in log-rate space from the upper bracket),
     - plain bisection on eq. 14 in s, eta^(1/m) (s - s_pre) + a (s - s_Y)^(1/m) = 0 on [s_Y, s_pre]
       (BISECTION_ITERS halvings), gamma = (s_pre - s)/a,
     - plain Newton on h(gamma) from gamma0 = b/a (NEWTON_ITERS steps, no safeguard),
   against a reference (bisection in z = ln gamma on ln(eta e^(m z) + a e^z) = ln b, 200 halvings, all in
   log space so nothing overflows). Failure: non-finite, or relative error of gamma above 1e-8.

3. Float32. A foam block resting on a sticky floor under gravity, run long in float32 and float64 from
   the same state; drift = RMS particle distance between the two runs / dx, and the volume ratio J error,
   against the number of substeps, for small and large kappa and dx.

4. Domain walls as symmetry planes. The 2D slump column of experiments/slump.py (sticky floor,
   tau' = 0.3, Bingham eta = 10 Pa s) simulated whole, and as its right half against the domain's slip
   wall at x = 0 (a symmetry plane in the continuum): final height / H of both.

Usage: python -m experiments stability [--quick]. Writes experiments/results/stability[_quick].png/.md.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

import jaxfoam
from experiments import _common as C

NAME = "stability"

# --- 1. time step ---------------------------------------------------------------------------------
BLOCK = 0.1                  # block side, m
DX = 0.01                    # grid spacing, m (10 cells across the block)
V0_FRACTION = 0.01           # initial speed amplitude / c: 1% strain waves
ENERGY_TOLERANCE = 1.05      # total energy may not exceed its initial value by more than 5%
PLASTIC_YIELD = 0.005        # sigma_y / mu of the plastic runs: ||s|| reaches sqrt(2/3) sigma_y at ~0.4% strain
TS_STEPS = 400               # substeps per run: instabilities at CFL > 1 grow within tens of steps
RHO = 80.0


def block_scene():
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, 0.0], "density": RHO, "kappa": 1000.0,
            "domain": {"min": [-0.15, -0.15], "max": [0.15, 0.15]},
            "initial_shape": {"type": "box", "min": [-BLOCK / 2, -BLOCK / 2], "max": [BLOCK / 2, BLOCK / 2]},
            "notes": "free block with an initial velocity field, no gravity"}
    return jaxfoam.load_scene(spec)


def total_energy(s, p):
    """Kinetic + stored elastic energy, J per metre of depth (2D)."""
    act = s.active
    ke = 0.5 * jnp.sum(jnp.where(act, s.mass * jnp.sum(s.v * s.v, axis=1), 0.0))
    w = jaxfoam.energy_density(s.F, s.bbar_e, p)
    pe = jnp.sum(jnp.where(act, s.vol0 * w, 0.0))
    return ke + pe


def timestep_map(mus, ratios, cfls, plastic: bool):
    """Outcome codes (len(ratios), len(mus), len(cfls)): 0 stable, 1 energy grew, 2 non-finite."""
    scene = block_scene()
    grid = jaxfoam.make_grid(scene, DX)
    st = jaxfoam.init_state(scene, DX, 4, rho=RHO)
    x = np.asarray(st.x)
    shape = np.stack([np.sin(math.pi * x[:, 1] / BLOCK), np.sin(math.pi * x[:, 0] / BLOCK)], axis=1)
    cases, params, states, dts = [], [], [], []  # one vmapped batch
    for i, ratio in enumerate(ratios):
        for j, mu in enumerate(mus):
            kappa = ratio * mu
            c = math.sqrt((kappa + 4.0 / 3.0 * mu) / RHO)
            v0 = V0_FRACTION * c
            # Plastic: yield at a deviatoric strain of ~0.4%, below the 1% waves, so the runs do flow.
            p = jaxfoam.Params(mu=mu, kappa=kappa, sigma_y=(PLASTIC_YIELD * mu if plastic else 1e12),
                               eta=(0.01 * mu if plastic else 0.0), m=(0.5 if plastic else 1.0), rho=RHO)
            for k, cfl in enumerate(cfls):
                cases.append((i, j, k))
                params.append(p)
                states.append(st.replace(v=jnp.asarray(v0 * shape)))
                dts.append(cfl * DX / (c + v0))

    def one(state, p, dt):
        model = jaxfoam.Model(scene=scene, dt=dt, dt_cfl=dt, grid=grid)

        def sub(s, _):
            return jaxfoam.step(model, s, p), None
        e0 = total_energy(state, p)
        fin, _ = jax.lax.scan(sub, state, None, length=TS_STEPS)
        e1 = total_energy(fin, p)
        finite = jnp.all(jnp.isfinite(fin.x)) & jnp.all(jnp.isfinite(fin.F)) & jnp.isfinite(e1)
        return finite, e1 / e0

    run = jax.jit(jax.vmap(one))
    finite, growth = jax.device_get(run(C.stack_trees(states), C.stack_trees(params), jnp.asarray(dts)))
    out = np.zeros((len(ratios), len(mus), len(cfls)), int)
    gmap = np.full(out.shape, np.nan)
    for (i, j, k), ok, g in zip(cases, finite, growth):
        out[i, j, k] = 0 if (ok and g <= ENERGY_TOLERANCE) else (1 if ok else 2)
        gmap[i, j, k] = g if ok else np.nan
    return out, gmap, len(st.x)


# --- 2. return map solvers ------------------------------------------------------------------------
BISECTION_ITERS = 60         # float64 halvings of [s_Y, s_pre]: 2^-60 ~ 1e-18 of the bracket
NEWTON_ITERS = 50            # plain Newton steps (quadratic convergence needs < 10 when it converges)
REF_ITERS = 200              # reference bisection in ln(gamma)
ERROR_TOLERANCE = 1e-8
MU = 100.0                   # Pa; mubar = mu (tr bbar / 3 = 1) for the map
SIGMA_Y = 10.0               # Pa


def reference_rate(a, b, eta, m):
    """gamma solving eta gamma^m + a gamma = b by bisection in z = ln(gamma), overflow-free (log space)."""
    la, lb = jnp.log(a), jnp.log(b)
    le = jnp.log(jnp.where(eta > 0, eta, 1.0))
    hi = jnp.minimum(lb - la, jnp.where(eta > 0, (lb - le) / m, jnp.inf))  # g(hi) >= 0
    lo = hi - 400.0                                                        # g(lo) < 0 for every case here

    def g(z):
        return jnp.logaddexp(jnp.where(eta > 0, le + m * z, -jnp.inf), la + z) - lb

    def body(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        neg = g(mid) < 0
        return jnp.where(neg, mid, lo), jnp.where(neg, hi, mid)

    lo, hi = jax.lax.fori_loop(0, REF_ITERS, body, (lo, hi))
    return jnp.exp(0.5 * (lo + hi))


def bisection_eq14(a, b, eta, m):
    """Plain bisection on eq. 14 in s over [s_Y, s_pre]; returns gamma = (s_pre - s)/a."""
    s_y = math.sqrt(2.0 / 3.0) * SIGMA_Y
    s_pre = s_y + b
    e1m = eta ** (1.0 / m)

    def f(s):
        return e1m * (s - s_pre) + a * (s - s_y) ** (1.0 / m)

    def body(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        neg = f(mid) < 0
        return jnp.where(neg, mid, lo), jnp.where(neg, hi, mid)

    lo, hi = jax.lax.fori_loop(0, BISECTION_ITERS, body, (jnp.full_like(b, s_y), s_pre))
    return (s_pre - 0.5 * (lo + hi)) / a


def newton_plain(a, b, eta, m):
    """Plain Newton on h(gamma) from the upper bound b/a, no safeguard. Returns (gamma, converged)."""
    def body(_, g):
        h = eta * g ** m + a * g - b
        dh = m * eta * g ** (m - 1.0) + a
        return g - h / dh

    g = jax.lax.fori_loop(0, NEWTON_ITERS, body, b / a)
    res = jnp.abs(eta * g ** m + a * g - b) / b
    return g, res < 1e-10


def solver_map(ms, etas, strains, dts):
    """Fraction of the (strain, dt) cases each solver fails at every (eta, m): dict name -> (len(etas), len(ms))."""
    M, E, S, D = np.meshgrid(ms, etas, strains, dts, indexing="ij")
    m = jnp.asarray(M.ravel())
    eta = jnp.asarray(E.ravel())
    b = jnp.asarray(S.ravel() * MU)
    a = jnp.asarray(2.0 * MU * D.ravel())
    ref = jax.jit(reference_rate)(a, b, eta, m)

    def failed(g, extra_ok=None):
        bad = ~jnp.isfinite(g) | (jnp.abs(g / ref - 1.0) > ERROR_TOLERANCE)
        if extra_ok is not None:
            bad = bad | ~extra_ok
        return np.asarray(bad).reshape(M.shape).mean(axis=(2, 3)).T   # (etas, ms)

    out = {}
    with C.Timer() as t_default:
        g_default = jax.block_until_ready(jax.jit(jaxfoam.hb_rate)(a, b, eta, m))
    out["default (Halley in ln gamma)"] = failed(g_default)
    with C.Timer() as t_bis:
        g_bis = jax.block_until_ready(jax.jit(bisection_eq14)(a, b, eta, m))
    out[f"bisection on eq. 14 ({BISECTION_ITERS} halvings)"] = failed(g_bis)
    with C.Timer() as t_newton:
        g_newton, conv = jax.block_until_ready(jax.jit(newton_plain)(a, b, eta, m))
    out[f"plain Newton on h (<= {NEWTON_ITERS} steps)"] = failed(g_newton, conv)
    worst = float(np.nanmax(np.abs(np.asarray(g_default) / np.asarray(ref) - 1.0)))
    return out, worst, int(m.size), (t_default.seconds, t_bis.seconds, t_newton.seconds)


# --- 3. float32 drift -----------------------------------------------------------------------------
FOAM = jaxfoam.Params(mu=200.0, kappa=3000.0, sigma_y=20.0, eta=5.0, m=0.5, rho=RHO)


def drift_scene():
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -9.81], "density": RHO, "kappa": 3000.0,
            "domain": {"min": [-0.1, 0.0], "max": [0.1, 0.1]}, "floor": {"y": 0.0, "friction": "sticky"},
            "initial_shape": {"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.04]},
            "notes": "foam block settling on a sticky floor"}
    return jaxfoam.load_scene(spec)


def drift(kappa: float, dx: float, n_frames: int, steps_per_frame: int):
    """float32 vs float64 over n_frames x steps_per_frame substeps at CFL 0.3.

    Returns dict(steps (n_frames,), drift RMS |x32 - x64| / dx, J error max |J32 - J64|, dt s, particles).
    """
    scene = drift_scene()
    grid = jaxfoam.make_grid(scene, dx)
    p = FOAM.replace(kappa=kappa)
    dt = jaxfoam.stable_dt(p, dx, 1.0)
    st64 = jaxfoam.init_state(scene, dx, 4, rho=RHO, dtype=jnp.float64)
    st32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, st64)
    scene32 = jaxfoam.load_scene(scene.spec, dtype=jnp.float32)

    def observe(s, p):
        return dict(x=s.x, J=jaxfoam.det(s.F))

    res = {}
    for name, st, sc, dtype in (("64", st64, scene, jnp.float64), ("32", st32, scene32, jnp.float32)):
        f = jax.jit(functools.partial(C.rollout, grid=grid, n_frames=n_frames, substeps=steps_per_frame,
                                      observe=observe))
        _, fr = f(st, p.astype(dtype), sc, jnp.asarray(dt, dtype))
        res[name] = jax.device_get(fr)
    diff = res["32"]["x"].astype(np.float64) - res["64"]["x"]
    return dict(steps=steps_per_frame * np.arange(1, n_frames + 1), drift=np.sqrt(np.mean(np.sum(diff ** 2, -1), -1)) / dx,
                jerr=np.max(np.abs(res["32"]["J"].astype(np.float64) - res["64"]["J"]), axis=-1), dt=dt,
                kappa=kappa, dx=dx, particles=len(st64.x))


def symmetry_wall_check(res: int):
    """Final height / H of the 2D slump column (tau' = 0.3, sticky floor): (whole column, half column
    against the slip wall at x = 0)."""
    from experiments import slump
    H, R = slump.HEIGHT, slump.RADIUS
    tau_p = 0.3
    p = slump.BASE.replace(sigma_y=math.sqrt(3.0) * tau_p * slump.RHO * slump.G * H, eta=10.0)
    out = []
    for x_lo, box_lo in ((-0.3, -R), (0.0, 0.0)):
        spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -slump.G], "density": slump.RHO, "kappa": float(p.kappa),
                "domain": {"min": [x_lo, 0.0], "max": [0.3, 1.2 * H]}, "floor": {"y": 0.0, "friction": "sticky"},
                "initial_shape": {"type": "box", "min": [box_lo, 0.0], "max": [R, H]}}
        scene = jaxfoam.load_scene(spec)
        dx = H / res
        grid = jaxfoam.make_grid(scene, dx)
        st = jaxfoam.init_state(scene, dx, 4, rho=slump.RHO)
        t_end, frames = 1.2, 4
        substeps = int(math.ceil(t_end / frames / jaxfoam.stable_dt(p, dx, math.sqrt(2 * slump.G * H))))
        dt = t_end / frames / substeps

        def observe(s, p_):
            near = (jnp.abs(s.x[:, 0]) < 0.25 * R) & s.active
            return jnp.max(jnp.where(near, s.x[:, 1], -jnp.inf))

        f = jax.jit(functools.partial(C.rollout, grid=grid, n_frames=frames, substeps=substeps, observe=observe))
        _, top = f(st, p, scene, dt)
        x0 = np.asarray(st.x)
        top0 = float(np.max(x0[np.abs(x0[:, 0]) < 0.25 * R, 1]))
        out.append(1.0 - (top0 - float(top[-1])) / H)
    return out


def main(argv=None):
    args = C.parse_args(__doc__, argv)
    q = args.quick
    # 1
    mus = np.logspace(1, 5, 3 if q else 5)
    ratios = (10.0,) if q else (3.0, 10.0, 100.0)
    cfls = np.array([0.3, 0.7, 1.0, 1.4] if q else [0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 1.0, 1.2, 1.4, 2.0])
    with C.Timer() as t1:
        ts_elastic, growth_elastic, n_particles = timestep_map(mus, ratios, cfls, plastic=False)
        ts_plastic, growth_plastic, _ = timestep_map(mus, ratios, cfls, plastic=True)
    print(f"time-step maps done ({t1.seconds:.0f} s)", flush=True)
    # 2
    ms = np.linspace(0.1, 3.0, 8 if q else 30)
    etas = np.concatenate([[0.0], np.logspace(-4, 4, 8 if q else 25)])
    strains = np.logspace(-10, 4, 8 if q else 15)
    dts = np.array([1e-7, 1e-4, 1e-2])
    solvers, worst_default, n_cases, solver_seconds = solver_map(ms, etas, strains, dts)
    print("return-map failure fractions:", {k: float(v.mean()) for k, v in solvers.items()}, flush=True)
    # 3
    if q:
        drift_cases = [(3000.0, 0.01), (3e5, 0.01)]
        n_frames, spf = 10, 100
    else:
        drift_cases = [(3000.0, 0.01), (3000.0, 0.0025), (3e5, 0.01), (3e5, 0.0025)]
        n_frames, spf = 40, 500
    drifts = []
    for kappa, dx in drift_cases:
        d = drift(kappa, dx, n_frames, spf)
        print(f"float32 drift kappa={kappa:g} dx={dx:g}: final {d['drift'][-1]:.3g} dx, J error {d['jerr'][-1]:.3g}",
              flush=True)
        drifts.append(d)
    # 4
    wall_res = 8 if q else 16
    whole, half = symmetry_wall_check(wall_res)
    print(f"symmetry wall: whole column {whole:.4f} H, half column against the slip wall {half:.4f} H", flush=True)
    chart(mus, ratios, cfls, ts_elastic, ts_plastic, ms, etas, solvers, drifts, q)
    table(mus, ratios, cfls, ts_elastic, ts_plastic, growth_elastic, growth_plastic, solvers, worst_default,
          n_cases, solver_seconds, strains, dts, drifts, n_particles, q, (wall_res, whole, half))


def _first_failure(codes, cfls):
    """Smallest CFL that failed, per row (NaN if none)."""
    out = []
    for row in codes:
        bad = np.nonzero(row > 0)[0]
        out.append(float(cfls[bad[0]]) if len(bad) else float("nan"))
    return out


def chart(mus, ratios, cfls, ts_elastic, ts_plastic, ms, etas, solvers, drifts, quick):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    fig = plt.figure(figsize=(15, 10))
    # time step: wave speed on x, dt on y, the line dt = dx / c.
    ax = fig.add_subplot(2, 3, 1)
    colors = {0: "tab:green", 1: "tab:orange", 2: "tab:red"}
    labels = {0: "stable, energy bounded", 1: "finite, energy grew > 5%", 2: "non-finite"}
    seen = set()
    for codes_all, mk, tag in ((ts_elastic, "o", "elastic"), (ts_plastic, "^", "HB plastic")):
        for i, ratio in enumerate(ratios):
            for j, mu in enumerate(mus):
                c = math.sqrt((ratio * mu + 4.0 / 3.0 * mu) / RHO)
                for k, cfl in enumerate(cfls):
                    code = int(codes_all[i, j, k])
                    dt = cfl * DX / (c * (1 + V0_FRACTION))
                    lab = f"{labels[code]} ({tag})" if (code, tag) not in seen else None
                    seen.add((code, tag))
                    ax.loglog(c * (1.0 + 0.03 * (mk == "^")), dt, mk, color=colors[code], ms=5, mfc="none" if mk == "^" else None,
                              label=lab)
    cs = np.logspace(np.log10(0.3), np.log10(300), 50)
    ax.loglog(cs, DX / cs, "k-", label="theory dt = dx / c (CFL 1)")
    ax.loglog(cs, 0.3 * DX / cs, "k:", label="default CFL 0.3")
    ax.set_xlabel("P-wave speed c (m/s)")
    ax.set_ylabel("dt (s)")
    ax.set_title(f"Time-step stability, dx = {DX} m")
    ax.legend(fontsize=6)
    # return-map solver maps
    cmap = ListedColormap(["#e8f5e9", "#ffcc80", "#e53935"])
    for n, (name, frac) in enumerate(solvers.items()):
        ax = fig.add_subplot(2, 3, 2 + n)
        shown = np.where(frac == 0, 0, np.where(frac < 0.25, 1, 2))
        ax.pcolormesh(ms, np.arange(len(etas)), shown, cmap=cmap, vmin=0, vmax=2, shading="nearest")
        ax.set_yticks(np.arange(len(etas))[::3])
        ax.set_yticklabels([f"{e:.0e}" if e > 0 else "0" for e in etas[::3]], fontsize=7)
        ax.set_xlabel("m")
        ax.set_ylabel("eta (Pa s^m)")
        ax.set_title(f"{name}\nfailed cases: {100 * frac.mean():.1f}% (green none, orange <25%, red more)", fontsize=8)
    # float32 drift
    ax = fig.add_subplot(2, 3, 5)
    for k, d in enumerate(drifts):
        ax.loglog(d["steps"], np.maximum(d["drift"], 1e-12), "-o", ms=3, color=f"C{k}",
                  label=f"kappa={d['kappa']:g} Pa, dx={d['dx']:g} m")
    ax.set_xlabel("substeps")
    ax.set_ylabel("RMS |x_f32 - x_f64| / dx")
    ax.set_title("float32 drift from float64 (settling foam block)")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(2, 3, 6)
    for k, d in enumerate(drifts):
        ax.loglog(d["steps"], np.maximum(d["jerr"], 1e-12), "-o", ms=3, color=f"C{k}",
                  label=f"kappa={d['kappa']:g} Pa, dx={d['dx']:g} m")
    ax.set_xlabel("substeps")
    ax.set_ylabel("max |J_f32 - J_f64|")
    ax.set_title("float32 volume-ratio error")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return C.save_fig(fig, NAME, quick)


def table(mus, ratios, cfls, ts_elastic, ts_plastic, growth_elastic, growth_plastic, solvers, worst_default,
          n_cases, solver_seconds, strains, dts, drifts, n_particles, quick, wall):
    parts = ["## 1. Time step\n\n",
             f"Free block {BLOCK} m, dx = {DX} m, {n_particles} particles, {TS_STEPS} substeps, initial speed "
             f"{V0_FRACTION} c; dt = CFL dx / (c + V0). Entry: smallest CFL that failed (non-finite or energy > "
             f"{ENERGY_TOLERANCE} x initial); '-' = none failed up to CFL {cfls[-1]:g}. Plastic: sigma_y = {PLASTIC_YIELD} mu, "
             "eta = 0.01 mu Pa s^0.5, m = 0.5.\n\n"]
    rows = []
    for i, ratio in enumerate(ratios):
        fe = _first_failure(ts_elastic[i], cfls)
        fp = _first_failure(ts_plastic[i], cfls)
        for j, mu in enumerate(mus):
            c = math.sqrt((ratio * mu + 4.0 / 3.0 * mu) / RHO)
            fmt = lambda v: "-" if math.isnan(v) else f"{v:g}"
            stable = ts_elastic[i, j] == 0
            rows.append([f"{mu:g}", f"{ratio:g}", c, fmt(fe[j]), fmt(fp[j]),
                         float(np.max(growth_elastic[i, j][stable])) if stable.any() else float("nan")])
    parts.append(C.md_table(["mu Pa", "kappa/mu", "c m/s", "first failing CFL (elastic)",
                             "first failing CFL (HB plastic)", "max energy ratio of the stable elastic runs"], rows))
    parts.append("\n## 2. Return-map solvers\n\n"
                 f"{n_cases} cases: m in [0.1, 3], eta in {{0}} U [1e-4, 1e4], b/mu in [{strains[0]:.0e}, {strains[-1]:.0e}] "
                 f"({len(strains)} values), dt in {[float(d) for d in dts]} s, mu = {MU} Pa, sigma_y = {SIGMA_Y} Pa, float64. "
                 f"Failure: non-finite or |gamma/gamma_ref - 1| > {ERROR_TOLERANCE:g}.\n\n")
    parts.append(C.md_table(["solver", "failed cases", "wall s (all cases, incl. compile)"],
                            [[name, f"{100 * frac.mean():.2f}%", sec] for (name, frac), sec in
                             zip(solvers.items(), solver_seconds)]))
    parts.append(f"\nLargest relative error of the default solver over all cases: {worst_default:.3g}.\n")
    parts.append("\n## 3. float32 drift\n\nFoam block (mu 200 Pa, sigma_y 20 Pa, eta 5 Pa s^0.5, m 0.5) settling on "
                 "a sticky floor, CFL 0.3; the same initial state in both precisions.\n\n")
    rows = []
    for d in drifts:
        k10 = min(len(d["steps"]) - 1, max(0, len(d["steps"]) // 10 - 1))
        rows.append([f"{d['kappa']:g}", d["dx"], d["dt"], d["particles"], int(d["steps"][k10]), float(d["drift"][k10]),
                     int(d["steps"][-1]), float(d["drift"][-1]), float(d["jerr"][-1])])
    parts.append(C.md_table(["kappa Pa", "dx m", "dt s", "particles", "steps", "drift / dx", "steps", "drift / dx",
                             "max J error"], rows))
    wall_res, whole, half = wall
    parts.append("\n## 4. Domain slip wall as a symmetry plane\n\n"
                 f"2D slump column (experiments/slump.py geometry, tau' = 0.3, sticky floor, eta = 10 Pa s, m = 1), "
                 f"H/dx = {wall_res}, 1.2 s:\n\n"
                 + C.md_table(["configuration", "final height / H"],
                              [["whole column", whole], ["right half against the slip wall at x = 0", half]]))
    return C.write_md(NAME, quick, "Stability: where methods fail", "".join(parts))


if __name__ == "__main__":
    main()
