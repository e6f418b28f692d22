"""A small numpy rasteriser for ``render_mode="rgb_array"``: top and side views of object, tools, target.

No display and no OpenGL: points are splatted as small squares, end-effectors drawn as filled discs
(spheres, capsules) or rectangles (boxes). Left panel: top view (x right, y up); right panel: side view
(x right, z up). Colours: target light red, object blue (darker = higher), closed grippers green, open
ones orange, table grey.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["render_scene"]

_BG = np.array([250, 250, 250], np.uint8)
_TABLE = np.array([200, 200, 200], np.uint8)
_TARGET = np.array([245, 160, 160], np.uint8)
_CLOSED = np.array([40, 170, 60], np.uint8)
_OPEN = np.array([240, 150, 30], np.uint8)


def _to_px(xy, lo, hi, size):
    u = (xy[:, 0] - lo[0]) / (hi[0] - lo[0]) * (size - 1)
    v = (1.0 - (xy[:, 1] - lo[1]) / (hi[1] - lo[1])) * (size - 1)
    return np.stack([v, u], 1)


def _splat(img, px, colors, r):
    H, W = img.shape[:2]
    px = np.round(px).astype(int)
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            i = np.clip(px[:, 0] + di, 0, H - 1)
            j = np.clip(px[:, 1] + dj, 0, W - 1)
            img[i, j] = colors


def _disc(img, centre, radius_px, color, alpha=0.8):
    H, W = img.shape[:2]
    ii, jj = np.mgrid[0:H, 0:W]
    m = (ii - centre[0]) ** 2 + (jj - centre[1]) ** 2 <= max(radius_px, 1.5) ** 2
    img[m] = (alpha * color + (1 - alpha) * img[m]).astype(np.uint8)


def _rect(img, c0, c1, color, alpha=0.6):
    H, W = img.shape[:2]
    i0, i1 = sorted((int(round(c0[0])), int(round(c1[0]))))
    j0, j1 = sorted((int(round(c0[1])), int(round(c1[1]))))
    i0, j0 = max(i0, 0), max(j0, 0)
    i1, j1 = min(i1, H - 1), min(j1, W - 1)
    if i1 >= i0 and j1 >= j0:
        sub = img[i0:i1 + 1, j0:j1 + 1]
        img[i0:i1 + 1, j0:j1 + 1] = (alpha * color + (1 - alpha) * sub).astype(np.uint8)


def _panel(axes, particles, target, ee_pos, ee_cfgs, grip, lo, hi, size):
    a, b = axes
    lo2, hi2 = np.array([lo[a], lo[b]]), np.array([hi[a], hi[b]])
    img = np.empty((size, size, 3), np.uint8)
    img[:] = _BG
    if b == 2:  # side view: the table below z = 0
        z0 = _to_px(np.array([[lo[a], 0.0]]), lo2, hi2, size)[0, 0]
        img[int(max(z0, 0)):] = _TABLE
    scale = (size - 1) / max(hi2 - lo2)
    r = max(1, size // 160)
    if len(target):
        _splat(img, _to_px(target[:, [a, b]], lo2, hi2, size), _TARGET, r)
    if len(particles):
        order = np.argsort(particles[:, 2]) if b != 2 else np.argsort(-particles[:, 1])
        p = particles[order]
        h = np.clip((p[:, 2] - lo[2]) / max(hi[2] - lo[2], 1e-9), 0, 1)[:, None]
        cols = ((1 - h) * np.array([90, 140, 230]) + h * np.array([10, 30, 120])).astype(np.uint8)
        _splat(img, _to_px(p[:, [a, b]], lo2, hi2, size), cols, r)
    for k, cfg in enumerate(ee_cfgs):
        c = _to_px(ee_pos[k][None, [a, b]], lo2, hi2, size)[0]
        col = _CLOSED if (k < len(grip) and grip[k]) else _OPEN
        if cfg.shape == "box":
            he = np.array([cfg.half_extents[a], cfg.half_extents[b]]) * scale
            _rect(img, c - he[::-1], c + he[::-1], col)
        else:
            _disc(img, c, cfg.radius * scale, col)
    return img


def render_scene(particles: np.ndarray, target: np.ndarray, ee_pos: np.ndarray, ee_cfgs: Sequence, grip,
                 lower, upper, size: int = 256) -> np.ndarray:
    """An RGB image [size, 2 * size + 4, 3] uint8: top view | side view of one world.

    particles [P, 3], target [T, 3], ee_pos [K, 3] in metres; ``ee_cfgs`` the end-effectors'
    :class:`~empm_gym.sim.EndEffectorConfig`; ``grip`` [K] flags; lower/upper the view box [m].
    """
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    particles = np.nan_to_num(np.asarray(particles, float)).reshape(-1, 3)
    target = np.asarray(target, float).reshape(-1, 3)
    ee_pos = np.asarray(ee_pos, float).reshape(-1, 3)
    top = _panel((0, 1), particles, target, ee_pos, ee_cfgs, grip, lo, hi, size)
    # the side view zooms on z: same x range, z from the table to the top of the box
    side = _panel((0, 2), particles, target, ee_pos, ee_cfgs, grip, lo, hi, size)
    sep = np.full((size, 4, 3), 60, np.uint8)
    return np.concatenate([top, sep, side], 1)
