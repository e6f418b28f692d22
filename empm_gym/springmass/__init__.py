"""Spring-mass model family (PhysTwin-style) on NVIDIA Warp, differentiable through ``wp.Tape``.

A body is a network of particles joined by springs to their neighbours within a radius; stiffness and
damping are normalised by geometry so that they read as a modulus [Pa] and a viscosity [Pa s] independent
of the particle spacing (:mod:`.model`). :class:`SpringMassSim` replays end-effector motion: closed grippers
hold the particles they touch through control springs, everything else meets the end-effectors and the table
through Coulomb contact (:mod:`.simulator`). Imports neither torch nor gymnasium; fitting to recordings lives in
:mod:`empm_gym.identification.springmass`.
"""

from .model import SpringMassConfig, SpringMassModel, build_network, downsample, model_from_body
from .simulator import SpringMassSim

__all__ = ["SpringMassConfig", "SpringMassModel", "SpringMassSim", "build_network",
           "downsample", "model_from_body"]
