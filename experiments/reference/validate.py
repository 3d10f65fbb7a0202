"""Validation of the reference simulator against analytic solutions; writes validation.md (measured numbers).

1. Elastic column (the case of experiments/elastic_wave.py): a free column of height H = 0.1 m, width
   H/4, Poisson ratio 0 (kappa = 2/3 mu), on a sticky floor, gravity (1 m/s^2) switched on at t = 0. Its
   centre of mass oscillates with period T = 4 H / c, c = sqrt((kappa + 4/3 mu) / rho). Tolerance 2% at
   the finest H/dx.
2. Steady simple shear, against the exact finite-strain flow curve of the model
   (`jaxfoam.hb_steady_shear_stress`, the analytic relation; no jaxfoam simulation code is used):
   (a) one material point driven by the reference return map, tolerance 1e-3 relative;
   (b) the reference MPM: a layer of gap H between two sticky plates moving at -V/2 and +V/2, periodic
       along x, no gravity, density scaled so inertia is negligible (Reynolds number 0.5); the shear rate
       is the slope of v_x(y) over the middle 60% of the gap and the stress the mean Kirchhoff tau_xy there
       over the last quarter of the run. Tolerance 3%.
3. Slump (experiments/slump.py): a 2D column H = 0.1 m, half-width 0.05 m on a frictionless floor; final
   height h_f / H against Pashias et al. (1996), h_f / H = 2 tau' (1 - ln 2 tau'), tau' = tau_y / (rho g H),
   tau_y = sigma_y / sqrt(3). Tolerance 0.05 for tau' >= 0.3 (the 1D analysis is meant for slumps that stay
   columns; tau' = 0.2 is reported without a tolerance).
4. Renderer: the covered area (sum of pixel coverages before the 1/2 threshold) of each 2D scene's first
   frame against the exact shape's area, tolerance 1% (the thresholded mask's area also depends on where
   the shape's edges fall within pixels).
5. Coulomb floor: a stiff elastic block (4 x 2 cm) sliding at v0 = 1 m/s on a floor of friction 0.5, with
   the domain's bottom wall on the floor's plane (as in the scenes), at three offsets of the node lattice;
   it stops after v0^2 / (2 mu_f g). Tolerance 3%.
"""
from __future__ import annotations

import math
import pathlib
import platform
import time

import numpy as np

from .material import drive_simple_shear
from .mpm import Grid, Particles, Simulation
from .scene import Boundaries, Plate, RefScene, particle_spacing, sample
from .silhouettes import Camera, coverage

OUT = pathlib.Path(__file__).resolve().parent / "validation.md"
# Written under table 2b: a static note whose numbers are those of the last full run on the 2-core host.
NOTE_SHEAR = ("The MPM layer's measured rate is 8-32% below V/H (the sticky plate nodes do not pin the material's "
              "edge to the plate speed) and its stress is 2.6-4.3% below the flow curve at the measured rate, "
              "growing with the rate; the same return map alone is within 2.5e-4 (2a), so the gap is the MPM's (not"
              " yet explained; jaxfoam's sheared box, experiments/rheometer.md, is 1.2-6.3% off).")
RHO, G = 80.0, 9.81


# ---------------------------------------------------------------- 1. elastic column
def column_period(res, periods=4.0, frames_per_period=40, ppc=4, cfl=0.25):
    """Measured and exact period (s) of the elastic column at H/dx = res."""
    H, W, g = 0.1, 0.025, 1.0
    mat = dict(mu=1000.0, kappa=2000.0 / 3.0, sigma_y=1e9, eta=0.0, m=1.0, rho=RHO)
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -g], "density": RHO, "kappa": mat["kappa"],
            "domain": {"min": [-2 * W, 0.0], "max": [2 * W, 1.5 * H]}, "floor": {"y": 0.0, "friction": "sticky"},
            "initial_shape": {"type": "box", "min": [-W / 2, 0.0], "max": [W / 2, H]}}
    scene = RefScene(spec)
    dx = H / res
    parts = sample(scene, dx, ppc, seed=res)
    sim = Simulation(parts, Grid.covering(scene.lo, scene.hi, dx), mat, scene.boundaries, scene.gravity, cfl)
    T = 4.0 * H / sim.wave_speed
    ts = np.linspace(0.0, periods * T, int(periods * frames_per_period) + 1)
    ycm = []
    for t in ts:
        sim.advance_to(t)
        ycm.append(np.average(parts.x[:, 1], weights=parts.mass))
    z = np.asarray(ycm) - np.mean(ycm)
    i = np.nonzero((z[:-1] < 0) & (z[1:] >= 0))[0]
    tc = ts[i] - z[i] * (ts[i + 1] - ts[i]) / (z[i + 1] - z[i])
    return float(np.mean(np.diff(tc))), T, sim.steps


# ---------------------------------------------------------------- 2. simple shear
FOAM = dict(mu=200.0, kappa=1000.0, sigma_y=20.0, eta=5.0, m=0.5)


def flow_curve(rate, mat=FOAM):
    """The model's exact steady shear stress tau_xy (Pa) at a shear rate (1/s)."""
    import jaxfoam

    p = jaxfoam.Params(mu=mat["mu"], kappa=mat["kappa"], sigma_y=mat["sigma_y"], eta=mat["eta"], m=mat["m"], rho=RHO)
    return float(jaxfoam.hb_steady_shear_stress(rate, p))


def point_shear(rate, strain=20.0):
    """Steady tau_xy (Pa) of one material point driven at `rate` (1/s) by the reference return map."""
    return float(drive_simple_shear(FOAM["mu"], FOAM["sigma_y"], FOAM["eta"], FOAM["m"], rate, strain)[-1])


def mpm_shear(rate, res=16, strain=4.0, width_cells=4, ppc=4, cfl=0.25, reynolds=0.5):
    """(measured shear rate 1/s, mean tau_xy Pa) of the periodic MPM shear layer at H/dx = res."""
    H = 0.02
    dx = H / res
    rho = reynolds / (rate ** 2 * H ** 2)
    V = rate * H
    Wx = width_cells * dx
    grid = Grid(np.array([0.0, -4 * dx]), dx, np.array([width_cells, res + 9]), periodic=True)
    big = 1e3
    t_end = strain / rate
    span = 2.0 * t_end  # the plates move at +-V/2 over [0, span], longer than the run

    def plate(y_centre, speed):
        return Plate({"center": [0.0, y_centre], "half_size": [big, 2 * dx],
                      "motion": {"type": "samples", "times": [0.0, span],
                                 "positions": [[0.0, y_centre], [speed * span, y_centre]]}}, 2)

    bnd = Boundaries([-big, -big], [big, big], None, 0.0, [plate(-2 * dx, -V / 2), plate(H + 2 * dx, V / 2)])
    s = particle_spacing(dx, ppc, 2)
    nx, ny = int(round(Wx / s)), int(round(H / s))
    sx, sy = Wx / nx, H / ny
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) * sx, (np.arange(ny) + 0.5) * sy, indexing="ij")
    jitter = (np.random.default_rng(res).random((nx * ny, 2)) - 0.5) * 0.5 * np.array([sx, sy])
    parts = Particles(np.stack([gx.ravel(), gy.ravel()], 1) + jitter, sx * sy, rho)
    parts.v[:, 0] = rate * (parts.x[:, 1] - H / 2)  # start in the steady velocity profile
    sim = Simulation(parts, grid, dict(FOAM, rho=rho), bnd, np.zeros(2), cfl)
    samples = []
    for t in np.linspace(0.75 * t_end, t_end, 9):
        sim.advance_to(t)
        mid = np.abs(parts.x[:, 1] - H / 2) < 0.3 * H
        slope = np.polyfit(parts.x[mid, 1], parts.v[mid, 0], 1)[0]
        samples.append((slope, float(np.mean(FOAM["mu"] * parts.b[mid, 0, 1]))))
    return tuple(np.mean(samples, axis=0))


# ---------------------------------------------------------------- 3. slump
def pashias_height(tau_p):
    """Pashias et al. final height h_f / H = 2 tau' (1 - ln 2 tau') (1 for 2 tau' >= 1)."""
    a = min(2.0 * tau_p, 1.0)
    return a * (1.0 - math.log(a))


def slump_height(tau_p, res=24, duration=1.5, ppc=5, cfl=0.25):
    """(h_f / H, final / peak kinetic energy) of the 2D slump at H/dx = res."""
    H, R = 0.1, 0.05
    mat = dict(mu=1000.0, kappa=5000.0, sigma_y=math.sqrt(3.0) * tau_p * RHO * G * H, eta=10.0, m=1.0, rho=RHO)
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -G], "density": RHO, "kappa": mat["kappa"],
            "domain": {"min": [-0.3, 0.0], "max": [0.3, 1.2 * H]}, "floor": {"y": 0.0, "friction": 0.0},
            "initial_shape": {"type": "box", "min": [-R, 0.0], "max": [R, H]}}
    scene = RefScene(spec)
    dx = H / res
    parts = sample(scene, dx, ppc, seed=res)
    sim = Simulation(parts, Grid.covering(scene.lo, scene.hi, dx, shift=[0.5, 0.0]), mat, scene.boundaries,
                     scene.gravity, cfl)
    axis = np.abs(parts.x[:, 0]) < 0.1 * R

    def top():
        return float(np.max(parts.x[axis, 1]))

    h0, ke = top(), []
    for t in np.linspace(duration / 30, duration, 30):
        sim.advance_to(t)
        ke.append(0.5 * float(np.sum(parts.mass * np.sum(parts.v ** 2, axis=1))))
    return top() / h0, ke[-1] / max(ke)


# ---------------------------------------------------------------- 4. renderer
def render_area_errors(res_ratio=4.0):
    """Per 2D scene: (foam pixels of the first frame, exact area in pixels, relative error)."""
    from .generate import PIXEL_SIZE, PPC, fit_dx
    from .scene import SCENES_DIR

    out = {}
    for name in ("hanging_plate_2d", "drop_2d", "squeeze_2d"):
        scene = RefScene(str(SCENES_DIR / f"{name}.json"))
        dx = fit_dx(scene) / res_ratio
        parts = sample(scene, dx, PPC[2], seed=1)
        cam = Camera.covering(scene.lo, scene.hi, PIXEL_SIZE)
        px = float(coverage(parts.x, particle_spacing(dx, PPC[2], 2), cam).sum())
        sh = scene.spec["initial_shape"]
        if sh["type"] == "box":
            exact = float(np.prod(np.asarray(sh["max"]) - np.asarray(sh["min"])))
        else:
            exact = math.pi * float(np.prod(sh["radii"]))
        exact /= PIXEL_SIZE ** 2
        out[name] = (px, exact, px / exact - 1.0)
    return out


# ---------------------------------------------------------------- 5. sliding block
def sliding_distance(shift, dx=0.0025, friction=0.5, v0=1.0):
    """Distance (m) a stiff block sliding at v0 (m/s) travels on a Coulomb floor, node lattice offset `shift` cells."""
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -G], "density": RHO, "kappa": 3000.0,
            "domain": {"min": [-0.1, 0.0], "max": [0.2, 0.05]}, "floor": {"y": 0.0, "friction": friction},
            "initial_shape": {"type": "box", "min": [-0.08, 0.0], "max": [-0.04, 0.02]}, "initial_velocity": [v0, 0.0]}
    scene = RefScene(spec)
    parts = sample(scene, dx, 4, seed=0)
    mat = dict(mu=1000.0, kappa=3000.0, sigma_y=1e6, eta=0.0, m=1.0, rho=RHO)
    sim = Simulation(parts, Grid.covering(scene.lo, scene.hi, dx, shift=[0.3, shift]), mat, scene.boundaries,
                     scene.gravity)
    x0 = np.average(parts.x[:, 0], weights=parts.mass)
    sim.advance_to(1.5 * v0 / (friction * G))
    return float(np.average(parts.x[:, 0], weights=parts.mass) - x0)


def _row(cells):
    return "| " + " | ".join(str(c) for c in cells) + " |"


def main(quick=False):
    t_all = time.perf_counter()
    lines = ["# Reference simulator: validation", "",
             "Regenerate: `python -m experiments.reference validate` (experiments/reference/validate.py; its docstring "
             f"defines each case). Machine: {platform.machine()}, shared 2-core host, one core; numba kernels.", ""]
    ok_all = True

    def verdict(ok):
        nonlocal ok_all
        ok_all &= bool(ok)
        return "pass" if ok else "FAIL"

    lines += ["## 1. Elastic column period (T = 4H/c)", "",
              _row(["H/dx", "period s", "exact s", "rel. error", "steps", "wall s", "tolerance", "result"]),
              _row(["---"] * 8)]
    resolutions = (8, 16) if quick else (8, 16, 32)
    for res in resolutions:
        t0 = time.perf_counter()
        T, T0, steps = column_period(res)
        err = T / T0 - 1.0
        last = res == resolutions[-1]
        lines.append(_row([res, f"{T:.5g}", f"{T0:.5g}", f"{err:+.2%}", steps, f"{time.perf_counter() - t0:.0f}",
                           "2% (finest)" if last else "-", verdict(abs(err) < 0.02) if last else "-"]))
        print(lines[-1], flush=True)

    lines += ["", "## 2a. Steady simple shear, one material point (return map; strain step 5e-4, strain 20)", "",
              _row(["shear rate 1/s", "tau_xy Pa", "exact Pa", "rel. error", "tolerance", "result"]), _row(["---"] * 6)]
    for rate in (1e-2, 1e-1, 1.0, 10.0, 100.0, 1e3):
        tau, exact = point_shear(rate), flow_curve(rate)
        err = tau / exact - 1.0
        lines.append(_row([f"{rate:g}", f"{tau:.5g}", f"{exact:.5g}", f"{err:+.2e}", "1e-3", verdict(abs(err) < 1e-3)]))
    print("\n".join(lines[-6:]), flush=True)

    res = 8 if quick else 16
    lines += ["", f"## 2b. Steady simple shear, MPM layer between sticky plates (periodic in x, H/dx = {res})", "",
              _row(["nominal rate 1/s", "measured rate 1/s", "tau_xy Pa", "exact at measured rate Pa", "rel. error",
                    "wall s", "tolerance", "result"]), _row(["---"] * 8)]
    for rate in (0.1, 1.0, 10.0, 100.0):
        t0 = time.perf_counter()
        gd, tau = mpm_shear(rate, res=res)
        exact = flow_curve(gd)
        err = tau / exact - 1.0
        lines.append(_row([f"{rate:g}", f"{gd:.4g}", f"{tau:.4g}", f"{exact:.4g}", f"{err:+.2%}",
                           f"{time.perf_counter() - t0:.0f}", "3%", verdict(abs(err) < 0.03)]))
        print(lines[-1], flush=True)

    lines += ["", NOTE_SHEAR]
    res = 16 if quick else 24
    lines += ["", f"## 3. Slump, frictionless floor, H/dx = {res}, 1.5 s", "",
              _row(["tau'", "sigma_y Pa", "h_f/H", "Pashias", "difference", "final/peak KE", "wall s", "tolerance",
                    "result"]), _row(["---"] * 9)]
    for tau_p in (0.2, 0.3, 0.35, 0.4):
        t0 = time.perf_counter()
        h, ke = slump_height(tau_p, res=res)
        ref = pashias_height(tau_p)
        judged = tau_p >= 0.3
        lines.append(_row([tau_p, f"{math.sqrt(3) * tau_p * RHO * G * 0.1:.3g}", f"{h:.4f}", f"{ref:.4f}",
                           f"{h - ref:+.4f}", f"{ke:.2g}", f"{time.perf_counter() - t0:.0f}",
                           "0.05" if judged else "-", verdict(abs(h - ref) <= 0.05) if judged else "-"]))
        print(lines[-1], flush=True)

    lines += ["", "## 4. Renderer: first-frame covered area against the exact shape area (2.5 mm pixels, 4x grid)", "",
              _row(["scene", "covered area px", "exact area px", "rel. error", "tolerance", "result"]), _row(["---"] * 6)]
    for name, (px, exact, err) in render_area_errors().items():
        lines.append(_row([name, f"{px:.1f}", f"{exact:.1f}", f"{err:+.2%}", "1%", verdict(abs(err) < 0.01)]))
    exact = 1.0 / (2 * 0.5 * G)
    lines += ["", "## 5. Coulomb floor: sliding distance of a stiff block (v0 = 1 m/s, friction 0.5, dx 2.5 mm)", "",
              _row(["lattice offset (cells)", "distance m", "exact m", "rel. error", "tolerance", "result"]),
              _row(["---"] * 6)]
    for shift in (0.0, 0.5, 0.79):
        dist = sliding_distance(shift)
        err = dist / exact - 1.0
        lines.append(_row([shift, f"{dist:.4f}", f"{exact:.4f}", f"{err:+.2%}", "3%", verdict(abs(err) < 0.03)]))
    lines += ["", f"All checks {'pass' if ok_all else 'DO NOT all pass'}; total wall time "
              f"{time.perf_counter() - t_all:.0f} s.", ""]
    text = "\n".join(lines)
    print(text)
    if not quick:
        OUT.write_text(text)
    return 0 if ok_all else 1
