"""Visualisation: rgb_array rendering (numpy rasteriser), rerun logging, labelled rollout strips."""

from .plots import plot_learning_curve, save_rollout_strip, save_transfer_chart
from .render import render_scene

__all__ = ["render_scene", "save_rollout_strip", "save_transfer_chart", "plot_learning_curve", "RerunLogger"]


def __getattr__(name):
    if name == "RerunLogger":  # rerun is imported only when asked for
        from .rerun_log import RerunLogger

        return RerunLogger
    raise AttributeError(name)
