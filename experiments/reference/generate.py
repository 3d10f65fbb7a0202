"""Reference silhouette data: the spec's scenes simulated by the reference MPM at 4x (2D) finer dx than
jaxfoam's fit default, with its own sampling, grid offset, particles per cell and time step.

Cases: hanging_plate_2d, drop_2d, squeeze_2d (3 parameter sets each) and hanging_plate_3d (2 sets), in
the shaving-cream ranges mu 50-400 Pa, sigma_y 15-80 Pa, eta 1-30 Pa s^m, m 0.3-1.0 (a seeded Latin
hypercube per scene, log-uniform except m). Files: data/<scene>_set<k>.h5, clean masks (no pixel noise,
no dropped frames: a study adds its own), plate pixels of weight 0, the truth in /truth.

python -m experiments.reference generate [--case SCENE] [--set K] [--refine R] [--out DIR]
"""
from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import time

import numpy as np

from ._jit import HAVE_NUMBA
from .mpm import Grid, Simulation
from .scene import SCENES_DIR, RefScene, particle_spacing, sample
from .silhouettes import Camera, plate_pixels, read_back, render_mask, write

DATA_DIR = pathlib.Path(__file__).resolve().parent / "data"
RANGES = {"mu": (50.0, 400.0), "sigma_y": (15.0, 80.0), "eta": (1.0, 30.0), "m": (0.3, 1.0)}
# jaxfoam's fit default: the largest domain extent over this many cells (FIT_CELLS of the fitter).
FIT_CELLS = {2: 64, 3: 32}
PIXEL_SIZE = 0.0025   # m per pixel, the recovery study's camera
CFL = 0.25            # the reference's own step: dt = CFL dx / (c + max speed)
PPC = {2: 5, 3: 4}    # particles per cell (jaxfoam's default is 4 in 2D, 8 in 3D)


@dataclasses.dataclass(frozen=True)
class Case:
    """A scene of the data set: its file in experiments/scenes, duration (s), frames on [0, duration],
    how many times finer than the fit default the reference grid is, and the number of parameter sets."""

    scene: str
    duration: float
    frames: int
    refine: float
    n_sets: int
    seed: int
    path: str | None = None  # a scene JSON file instead of experiments/scenes/<scene>.json


CASES = {c.scene: c for c in (
    Case("hanging_plate_2d", 0.8, 17, 4.0, 3, 101),
    Case("drop_2d", 0.4, 13, 4.0, 3, 102),
    Case("squeeze_2d", 1.4, 15, 4.0, 3, 103),
    # 3D at 2.5x (4.4 mm, ~4e4 particles): 4x (2.7 mm, ~1.7e5 particles, ~6000 steps) was estimated at
    # over 20 min per run on one shared core. The committed set 0 was made at --refine 2 (5.5 mm, 214 s).
    Case("hanging_plate_3d", 0.6, 9, 2.5, 2, 104),
)}


def parameter_sets(case):
    """The case's truths: a Latin hypercube of n_sets points over RANGES (its own seed), 3 significant digits."""
    rng = np.random.default_rng(case.seed)
    out = [dict() for _ in range(case.n_sets)]
    for name, (lo, hi) in RANGES.items():
        u = (rng.permutation(case.n_sets) + rng.random(case.n_sets)) / case.n_sets
        for k in range(case.n_sets):
            val = lo + u[k] * (hi - lo) if name == "m" else math.exp(math.log(lo) + u[k] * math.log(hi / lo))
            out[k][name] = float(f"{val:.3g}")
    return out


# One foam filmed in every 2D scene (the joint-fit and design evidence): its own Latin hypercube over RANGES.
MATERIAL_SEED = 105
N_MATERIALS = 3
MATERIAL_SCENES = ("hanging_plate_2d", "drop_2d", "squeeze_2d")
MATERIALS_DIR = DATA_DIR / "materials"


def materials():
    """The material sets shared by the scenes of MATERIAL_SCENES (mu Pa, sigma_y Pa, eta Pa s^m, m)."""
    return parameter_sets(Case("materials", 0.0, 0, 1.0, N_MATERIALS, MATERIAL_SEED))


def fit_dx(scene):
    """jaxfoam's default fit grid spacing for the scene, m."""
    return float(np.max(scene.hi - scene.lo)) / FIT_CELLS[scene.dim]


def setup_case(case, params, seed=0, refine=None):
    """The run of one case before its first step: (scene, Simulation, dx m, particle spacing m, grid shift
    (d,) cells). The seed fixes the grid offset and the sampling, so a case's run is the same each time."""
    scene = RefScene(case.path or str(SCENES_DIR / f"{case.scene}.json"))
    d = scene.dim
    dx = fit_dx(scene) / (case.refine if refine is None else float(refine))
    rng = np.random.default_rng([case.seed, seed])
    shift = rng.random(d)  # node lattice offset, cells
    grid = Grid.covering(scene.lo, scene.hi, dx, shift=shift)
    parts = sample(scene, dx, PPC[d], seed=int(rng.integers(1 << 31)))
    mat = dict(params, kappa=scene.kappa, rho=scene.density)
    sim = Simulation(parts, grid, mat, scene.boundaries, scene.gravity, cfl=CFL)
    return scene, sim, dx, particle_spacing(dx, PPC[d], d), shift


def simulate_case(case, params, seed=0, refine=None, progress=print):
    """Run one case; returns (masks (T, H, W), times (T,), weights, camera, scene, source dict)."""
    scene, sim, dx, spacing, shift = setup_case(case, params, seed, refine)
    parts, ppc = sim.p, PPC[scene.dim]
    camera = Camera.covering(scene.lo, scene.hi, PIXEL_SIZE)
    times = np.linspace(0.0, case.duration, case.frames)
    masks = np.zeros((len(times),) + camera.shape, np.uint8)
    weights = np.ones(masks.shape, np.float32)
    t0 = time.perf_counter()
    for k, t in enumerate(times):
        sim.advance_to(t)
        masks[k] = render_mask(parts.x, spacing, camera)
        lo, hi, _, _ = scene.boundaries.plate_arrays(t)
        hidden = plate_pixels(camera, [(lo[q, :2], hi[q, :2]) for q in range(len(lo))])
        masks[k][hidden] = 0
        weights[k][hidden] = 0.0
        progress(f"  {case.scene} t = {t:.3f} s: {sim.steps} steps, {int(masks[k].sum())} foam pixels, "
                 f"{time.perf_counter() - t0:.0f} s")
    wall = time.perf_counter() - t0
    source = dict(generator="experiments.reference (independent numpy/numba MLS-MPM)", dx=dx,
                  fit_default_dx=fit_dx(scene), refine=fit_dx(scene) / dx, ppc=ppc, particles=len(parts.x),
                  sampling="stratified jitter", grid_shift_cells=[float(s) for s in shift], cfl=CFL,
                  steps=sim.steps, wall_s=round(wall, 1), numba=HAVE_NUMBA, pixel_size=PIXEL_SIZE,
                  render="disk union r = 1.2 spacings eroded by 0.7, box downsampled", noise=0.0, seed=seed)
    return masks, times, weights, camera, scene, source


def generate(case_name, set_index, out_dir=DATA_DIR, refine=None, progress=print, material=None, case=None,
             name=None):
    """Simulate one parameter set of one case, write data/<scene>_set<k>.h5 and check it with jaxfoam's reader.

    material: index into `materials()`: that foam instead of the case's own set (file <scene>_mat<k>.h5).
    case: a `Case` to run instead of CASES[case_name] (a scene file of its own); name: the file's stem."""
    case = CASES[case_name] if case is None else case
    params = parameter_sets(case)[set_index] if material is None else materials()[material]
    tag = f"set{set_index}" if material is None else f"mat{material}"
    progress(f"{case.scene} {tag}: {params}")
    seed = set_index if material is None else MATERIAL_SEED + material
    masks, times, weights, camera, scene, source = simulate_case(case, params, seed=seed, refine=refine,
                                                                 progress=progress)
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name or f'{case.scene}_{tag}'}.h5"
    truth = dict(params, kappa=scene.kappa, rho=scene.density)
    write(path, masks, times, camera, scene.spec, weights, source, truth)
    read_back(path)
    progress(f"wrote {path} ({path.stat().st_size / 1024:.0f} kB), dx {source['dx'] * 1e3:.3g} mm, "
             f"{source['particles']} particles, {source['steps']} steps, {source['wall_s']:.0f} s")
    return path, source


def index_table(out_dir=DATA_DIR):
    """A markdown table of the files in out_dir: truth, dx, particles, steps, wall time, size."""
    rows = ["| file | mu Pa | sigma_y Pa | eta Pa s^m | m | dx mm (fit default / dx) | particles | steps | wall s | kB |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    import h5py

    for path in sorted(pathlib.Path(out_dir).glob("*.h5")):
        with h5py.File(path, "r") as fh:
            src = json.loads(fh.attrs["source"])
            tr = dict(fh["truth"].attrs)
        rows.append(f"| {path.name} | {tr['mu']:g} | {tr['sigma_y']:g} | {tr['eta']:g} | {tr['m']:g} | "
                    f"{src['dx'] * 1e3:.3g} ({src['refine']:.2g}x) | {src['particles']} | {src['steps']} | "
                    f"{src['wall_s']:.0f} | {path.stat().st_size / 1024:.0f} |")
    return "\n".join(rows) + "\n"


README_HEAD = """# Reference silhouette data

Made by `python -m experiments.reference generate` (experiments/reference/generate.py): the independent
reference MPM (no jaxfoam code), clean masks at 2.5 mm pixels, plate pixels of weight 0, truth in /truth.
Each file's /source attribute (JSON) holds its dx, particles, sampling, grid offset, time steps and wall time.
Wall times: one shared core of a 2-core machine, numba-compiled kernels.

"""

MATERIALS_README_HEAD = """# Reference silhouette data: one foam in several scenes

Made by `python -m experiments.reference generate --material K` (experiments/reference/generate.py): the
three foams of `materials()` (seed 105), each filmed by the independent reference MPM in the hanging plate,
drop and squeeze (2D, 4x finer dx than jaxfoam's fit default), the files `<scene>_mat<K>.h5`.
`hanging_plate_2d_mat<K>_designed.h5`: the plate motion `jaxfoam design` recommends for material K
(experiments/material_study.py; the motion is in the file's scene notes). Clean masks at 2.5 mm pixels,
plate pixels of weight 0, truth in /truth, dx, sampling, steps and wall time in /source.
Wall times: one shared core of a 2-core machine, numba-compiled kernels.

"""
