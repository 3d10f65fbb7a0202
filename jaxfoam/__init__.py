"""jaxfoam: a differentiable Material Point Method for Herschel-Bulkley foam (Yue et al. 2015), in JAX.

The path through a simulation: `load_scene` -> `make_model` -> `Model.sample` (or `init_state`) ->
`step(model, state, params)` / `rollout(model, state0, params, frame_times, adjoint=...)`. Importing
jaxfoam changes no JAX configuration: enable float64 with `jax.config.update("jax_enable_x64", True)`.
"""
from . import adjoint as adjoint
from ._constitutive import (det as det, dev as dev, deviatoric_stress_norm as deviatoric_stress_norm,
                            energy_density as energy_density, hb_rate as hb_rate,
                            hb_steady_shear_stress as hb_steady_shear_stress, kirchhoff_stress as kirchhoff_stress,
                            return_map as return_map)
from ._boundary import apply_colliders as apply_colliders
from ._errors import JaxfoamError as JaxfoamError
from ._grid import Grid as Grid, make_grid as make_grid
from ._jacobian import (ObservableJacobian as ObservableJacobian, make_observable_jacobian as make_observable_jacobian,
                        observable_jacobian as observable_jacobian)
from ._model import (CFL as CFL, Model as Model, ModelError as ModelError, make_model as make_model,
                     stable_dt as stable_dt, wave_speed as wave_speed)
from ._mpm import g2p as g2p, grid_update as grid_update, p2g as p2g, step as step
from ._params import FIT_FIELDS as FIT_FIELDS, Params as Params
from ._rollout import observe_default as observe_default, rollout as rollout
from ._scene import (DEFAULT_PPC as DEFAULT_PPC, PlausibilityWarning as PlausibilityWarning, Plate as Plate, Scene as Scene, SceneError as SceneError, init_state as init_state,
                     load_scene as load_scene, sample_particles as sample_particles)
from ._simulate import (SimulationError as SimulationError, Simulator as Simulator, Trajectory as Trajectory,
                        simulate as simulate)
from ._state import State as State, make_state as make_state
from ._trajectory import (SavedTrajectory as SavedTrajectory, TrajectoryError as TrajectoryError,
                          load_trajectory as load_trajectory, save_trajectory as save_trajectory)
from .adjoint import (Autodiff as Autodiff, Checkpointed as Checkpointed, ForwardMode as ForwardMode,
                      HandWritten as HandWritten)

__version__ = "0.1.0"

__all__ = [
    "Autodiff", "CFL", "Checkpointed", "DEFAULT_PPC", "FIT_FIELDS", "ForwardMode", "Grid", "HandWritten", "JaxfoamError", "Model", "ModelError",
    "ObservableJacobian", "Params", "PlausibilityWarning", "Plate", "SavedTrajectory", "Scene", "SceneError", "SimulationError", "Simulator",
    "State", "Trajectory", "TrajectoryError", "adjoint", "apply_colliders", "det", "dev", "deviatoric_stress_norm",
    "energy_density", "g2p", "grid_update", "hb_rate", "hb_steady_shear_stress", "init_state", "kirchhoff_stress",
    "load_scene", "load_trajectory", "make_grid", "make_model", "make_observable_jacobian", "make_state",
    "observable_jacobian", "observe_default", "p2g", "return_map", "rollout", "sample_particles", "save_trajectory",
    "simulate", "stable_dt", "step",
]
