"""Visualisation: rgb_array rendering (numpy rasteriser), rerun logging, image strips."""

from .render import image_strip, render_scene

__all__ = ["image_strip", "render_scene", "RerunLogger"]


def __getattr__(name):
    if name == "RerunLogger":  # rerun is imported only when asked for
        from .rerun_log import RerunLogger

        return RerunLogger
    raise AttributeError(name)
