"""Pinhole cameras: projection of world points and back-projection of depth images to world points.

Conventions (OpenCV): camera x right, y down, z forward (along the optical axis); pixel (row, col)
with col = fx * x / z + cx and row = fy * y / z + cy, pixel centres at integer coordinates. A camera
pose is a 4x4 camera-to-world matrix ``c2w`` (metres). Depths are metric z (distance along the
optical axis, not along the ray), 0 or non-finite meaning "no measurement".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

__all__ = [
    "Camera",
    "intrinsics_matrix",
    "look_at",
    "project_points",
    "backproject_depth",
    "pixel_rays",
]


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 pinhole intrinsics from focal lengths and principal point, all in pixels."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world matrix (OpenCV axes) of a camera at ``eye`` (m) looking at ``target`` (m).

    The image "up" (-y of the camera) is as close to the world direction ``up`` as possible.
    """
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise ValueError(f"look_at: eye {eye.tolist()} and target {target.tolist()} coincide")
    z /= n
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"look_at: viewing direction {z.tolist()} is parallel to up {up.tolist()}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def project_points(points: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Project world points [N, 3] (m) into a camera.

    Returns ``(rc [N, 2] pixel (row, col), z [N] depth in m)``; points behind the camera get
    z <= 0 and meaningless pixel coordinates.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    w2c = np.linalg.inv(np.asarray(c2w, np.float64))
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        col = K[0, 0] * pc[:, 0] / z + K[0, 2]
        row = K[1, 1] * pc[:, 1] / z + K[1, 2]
    return np.stack([row, col], axis=1), z


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame directions [H, W, 3] with z = 1 through every pixel centre."""
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x = (cols - K[0, 2]) / K[0, 0]
    y = (rows - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def backproject_depth(depth_m: np.ndarray, K: np.ndarray, c2w: np.ndarray, mask: Optional[np.ndarray] = None,
                      *, min_depth_m: float = 1e-6, max_depth_m: float = np.inf,
                      return_pixels: bool = False):
    """World points [N, 3] (m) of the valid pixels of a metric depth image [H, W] (m).

    A pixel is used when its depth is finite and in [min_depth_m, max_depth_m] and, if given,
    ``mask`` [H, W] (bool) is true there. With ``return_pixels`` also returns the (row, col)
    indices [N, 2] of the used pixels.
    """
    d = np.asarray(depth_m)
    if d.ndim != 2:
        raise ValueError(f"backproject_depth: depth must be a 2-D image [H, W], got shape {d.shape}")
    K = np.asarray(K, np.float64)
    valid = np.isfinite(d) & (d >= min_depth_m) & (d <= max_depth_m)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != d.shape:
            raise ValueError(f"backproject_depth: mask shape {m.shape} differs from depth shape {d.shape}")
        valid &= m
    rows, cols = np.nonzero(valid)
    z = d[rows, cols].astype(np.float64)
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    pc = np.stack([x, y, z], axis=1)
    c2w = np.asarray(c2w, np.float64)
    pw = pc @ c2w[:3, :3].T + c2w[:3, 3]
    if return_pixels:
        return pw, np.stack([rows, cols], axis=1)
    return pw


@dataclass
class Camera:
    """One calibrated pinhole camera: intrinsics K [3, 3] (pixels), pose c2w [4, 4] (m), image size (pixels)."""

    K: np.ndarray
    c2w: np.ndarray
    width: int
    height: int
    name: str = ""

    def __post_init__(self):
        self.K = np.asarray(self.K, np.float64)
        self.c2w = np.asarray(self.c2w, np.float64)

    @property
    def w2c(self) -> np.ndarray:
        """World-to-camera 4x4 matrix."""
        return np.linalg.inv(self.c2w)

    @property
    def position(self) -> np.ndarray:
        """Optical centre in world coordinates (m)."""
        return self.c2w[:3, 3].copy()

    def project(self, points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """(row, col) pixel coordinates [N, 2] and depth z [N] (m) of world points [N, 3] (m)."""
        return project_points(points, self.K, self.c2w)

    def backproject(self, depth_m: np.ndarray, mask: Optional[np.ndarray] = None, **kw) -> np.ndarray:
        """World points (m) of a metric depth image of this camera; see :func:`backproject_depth`."""
        if depth_m.shape != (self.height, self.width):
            raise ValueError(f"Camera {self.name!r}: depth shape {depth_m.shape} differs from "
                             f"(height, width) = {(self.height, self.width)}")
        return backproject_depth(depth_m, self.K, self.c2w, mask, **kw)

    def world_rays(self) -> Tuple[np.ndarray, np.ndarray]:
        """Ray origin [3] and world-frame directions [H, W, 3] (z-component in camera = 1) of every pixel."""
        d = pixel_rays(self.K, self.width, self.height) @ self.c2w[:3, :3].T
        return self.position, d
