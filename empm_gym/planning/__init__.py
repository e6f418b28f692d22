"""Planners over the EMPM environments behind one interface: ``plan(state, horizon) -> actions [H, A]``.

:class:`CEMPlanner` and :class:`MPPIPlanner` evaluate all their samples as one batched rollout;
:class:`GradientPlanner` runs Adam on the action sequence through the differentiable simulator.
"""

from .base import Planner
from .sampling import CEMPlanner, MPPIPlanner, SamplingPlanner

__all__ = ["Planner", "SamplingPlanner", "CEMPlanner", "MPPIPlanner", "GradientPlanner"]


def __getattr__(name):
    if name == "GradientPlanner":  # imports torch
        from .gradient import GradientPlanner

        return GradientPlanner
    raise AttributeError(name)
