"""Differentiable Material Point Method on NVIDIA Warp (imports neither gymnasium nor torch).

Newton-style split: a :class:`ModelBuilder` collects worlds, particles and end-effectors and
``finalize()`` makes a :class:`Model` (static); ``model.state()`` gives a :class:`State`
(time-varying), ``model.control()`` a :class:`Control` (one step's action); ``SolverMPM.step``
advances every world by one substep. :class:`Rollout` makes multi-step runs differentiable.
"""

import warp as wp

# keep Warp's per-module load notices out of users' logs (set wp.config.log_level back to see them)
if getattr(wp.config, "log_level", None) == getattr(wp, "LOG_INFO", None):
    wp.config.log_level = wp.LOG_WARNING
wp.config.quiet = True

from .config import EndEffectorConfig, GridConfig, MaterialConfig, SolverConfig, TableConfig, stable_dt
from .material_file import MaterialFile, read_material, write_material
from .model import Control, Model, ModelBuilder, State
from .rollout import Rollout
from .sampling import sample_box, sample_cylinder, sample_mesh, sample_points, sample_sphere
from .solver import GridScratch, SimulationDiverged, SolverMPM, UnstableTimeStep


__all__ = [
    "Control", "EndEffectorConfig", "GridConfig", "GridScratch", "MaterialConfig", "MaterialFile", "Model", "ModelBuilder",
    "Rollout", "SimulationDiverged", "SolverConfig", "SolverMPM", "State", "TableConfig", "UnstableTimeStep",
    "sample_box", "sample_cylinder", "stable_dt", "sample_mesh", "sample_points", "sample_sphere",
    "read_material", "write_material",
]
