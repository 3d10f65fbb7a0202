"""jaxfoam: a differentiable Material Point Method for Herschel-Bulkley foam (Yue et al. 2015), in JAX."""
import os as _os

import jax as _jax

if _os.environ.get("JAXFOAM_X64", "1") != "0":
    # float64 is needed for gradient checks and fits; float32 stays available per simulation.
    _jax.config.update("jax_enable_x64", True)

from ._constitutive import (det, dev, energy_density, hb_rate, hb_steady_shear_stress, kirchhoff_stress,
                            return_map, deviatoric_stress_norm)
from ._jacobian import ObservableJacobian, make_observable_jacobian, observable_jacobian
from ._mpm import (Grid, apply_colliders, from_components, g2p, grid_update, make_grid, make_step, p2g, sort_by_cell,
                   substep, to_components, unsort)
from ._params import Params
from ._scene import Plate, Scene, SceneError, init_state, load_scene, sample_particles
from ._simulate import CFL, SimulationError, Simulator, Trajectory, simulate, stable_dt, wave_speed
from ._state import State, make_state
from ._trajectory import SavedTrajectory, TrajectoryError, load_trajectory, save_trajectory

__version__ = "0.1.0"

__all__ = [
    "Params", "State", "Scene", "Plate", "Grid", "Simulator", "Trajectory", "SceneError", "SimulationError",
    "load_scene", "init_state", "make_state", "sample_particles", "make_grid", "make_step", "substep",
    "p2g", "grid_update", "g2p", "apply_colliders", "return_map", "hb_rate", "kirchhoff_stress",
    "energy_density", "deviatoric_stress_norm", "hb_steady_shear_stress", "det", "dev", "simulate",
    "stable_dt", "wave_speed", "CFL", "save_trajectory", "load_trajectory", "SavedTrajectory", "TrajectoryError",
    "observable_jacobian", "make_observable_jacobian", "ObservableJacobian", "to_components", "from_components",
    "sort_by_cell", "unsort",
]
