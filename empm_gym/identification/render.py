"""Point splatting into pinhole cameras: binary masks, soft (differentiable) masks, depth and colour images.

Cameras follow :mod:`empm_gym.perception.cameras` (OpenCV axes, pixel (row, col), pixel centres at
integer coordinates); anything with ``K`` [3, 3], ``c2w`` [4, 4], ``width`` and ``height`` works.
Every function takes a ``downsample`` factor s: the image is rendered at (H // s, W // s) with the
intrinsics scaled accordingly, so masks and losses can be computed cheaply on large images.
"""

from __future__ import annotations

from typing import Tuple

import numpy as np
import torch

__all__ = [
    "camera_size",
    "scaled_intrinsics",
    "project",
    "project_torch",
    "splat_mask",
    "splat_depth",
    "render_colors",
    "soft_mask",
    "downsample_mask",
]


def camera_size(camera, downsample: int = 1) -> Tuple[int, int]:
    """(height, width) of the camera's image rendered at ``downsample``."""
    s = _check_ds(downsample)
    return int(camera.height) // s, int(camera.width) // s


def _check_ds(downsample) -> int:
    s = int(downsample)
    if s < 1 or s != downsample:
        raise ValueError(f"downsample must be a positive integer, got {downsample!r}")
    return s


def scaled_intrinsics(K: np.ndarray, downsample: int) -> np.ndarray:
    """Intrinsics of the image downsampled by an integer factor (pixel centres stay at integers)."""
    s = _check_ds(downsample)
    K = np.asarray(K, np.float64).copy()
    K[0, 0] /= s
    K[1, 1] /= s
    K[0, 2] = (K[0, 2] + 0.5) / s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / s - 0.5
    return K


def project(points: np.ndarray, camera, downsample: int = 1) -> Tuple[np.ndarray, np.ndarray, float]:
    """(row, col) [N, 2] and depth z [N] (m) of world points, plus the focal length (pixels) at ``downsample``."""
    K = scaled_intrinsics(camera.K, downsample)
    w2c = np.linalg.inv(np.asarray(camera.c2w, np.float64))
    pc = np.asarray(points, np.float64).reshape(-1, 3) @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        col = K[0, 0] * pc[:, 0] / z + K[0, 2]
        row = K[1, 1] * pc[:, 1] / z + K[1, 2]
    return np.stack([row, col], 1), z, float(0.5 * (K[0, 0] + K[1, 1]))


def project_torch(points: torch.Tensor, camera, downsample: int = 1):
    """Differentiable version of :func:`project` for a torch tensor of world points [N, 3]."""
    K = scaled_intrinsics(camera.K, downsample)
    w2c = torch.as_tensor(np.linalg.inv(np.asarray(camera.c2w, np.float64)), dtype=points.dtype, device=points.device)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    zs = torch.clamp(z, min=1e-6)
    col = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    row = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    return torch.stack([row, col], 1), z, float(0.5 * (K[0, 0] + K[1, 1]))


def _disk_offsets(rmax: int):
    r = np.arange(-rmax, rmax + 1)
    dr, dc = np.meshgrid(r, r, indexing="ij")
    return dr.reshape(-1), dc.reshape(-1)


def _splat_pixels(points, camera, radius, downsample, max_radius_px=12):
    """Pixels covered by the disk of each point: (point index, row, col) arrays and the depths."""
    rc, z, f = project(points, camera, downsample)
    H, W = camera_size(camera, downsample)
    ok = np.isfinite(z) & (z > 1e-6) & np.all(np.isfinite(rc), axis=1)
    idx = np.nonzero(ok)[0]
    rc, z = rc[ok], z[ok]
    r_px = np.clip(f * float(radius) / z, 0.5, max_radius_px)
    ctr = np.rint(rc).astype(np.int64)
    rmax = int(np.ceil(r_px.max())) if len(r_px) else 0
    dr, dc = _disk_offsets(rmax)
    # exact disk test against the sub-pixel projected centre
    rows = ctr[:, None, 0] + dr[None, :]
    cols = ctr[:, None, 1] + dc[None, :]
    d2 = (rows - rc[:, None, 0]) ** 2 + (cols - rc[:, None, 1]) ** 2
    inside = (d2 <= r_px[:, None] ** 2) & (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
    pi = np.broadcast_to(np.arange(len(idx))[:, None], rows.shape)[inside]
    return idx[pi], rows[inside], cols[inside], z[pi]


def splat_mask(points: np.ndarray, camera, radius: float, downsample: int = 1) -> np.ndarray:
    """Binary silhouette [H/s, W/s] of world points drawn as disks of world ``radius`` (m)."""
    if radius <= 0:
        raise ValueError(f"splat_mask: radius must be > 0 m, got {radius!r}")
    H, W = camera_size(camera, downsample)
    out = np.zeros((H, W), bool)
    if len(points):
        _, r, c, _ = _splat_pixels(points, camera, radius, downsample)
        out[r, c] = True
    return out


def splat_depth(points: np.ndarray, camera, radius: float, downsample: int = 1) -> Tuple[np.ndarray, np.ndarray]:
    """Z-buffer of disks: (depth [H/s, W/s] in m, inf where empty; index of the nearest point, -1 where empty)."""
    H, W = camera_size(camera, downsample)
    depth = np.full(H * W, np.inf)
    owner = np.full(H * W, -1, np.int64)
    if len(points):
        pi, r, c, z = _splat_pixels(points, camera, radius, downsample)
        lin = r * W + c
        np.minimum.at(depth, lin, z)
        win = z <= depth[lin]
        owner[lin[win]] = pi[win]
    return depth.reshape(H, W), owner.reshape(H, W)


def render_colors(points: np.ndarray, colors: np.ndarray, camera, radius: float, background: np.ndarray,
                  downsample: int = 1) -> Tuple[np.ndarray, np.ndarray]:
    """Render coloured points (colours [N, 3] in [0, 1]) over ``background`` [H/s, W/s, 3] with a z-buffer.

    Returns (image [H/s, W/s, 3], coverage mask [H/s, W/s])."""
    colors = np.asarray(colors, np.float64).reshape(-1, 3)
    if len(colors) != len(points):
        raise ValueError(f"render_colors: {len(colors)} colours for {len(points)} points")
    H, W = camera_size(camera, downsample)
    bg = np.asarray(background, np.float64)
    if bg.shape != (H, W, 3):
        raise ValueError(f"render_colors: background has shape {bg.shape}, expected {(H, W, 3)}")
    _, owner = splat_depth(points, camera, radius, downsample)
    img = bg.copy()
    cov = owner >= 0
    img[cov] = colors[owner[cov]]
    return img, cov


def downsample_mask(mask: np.ndarray, downsample: int) -> np.ndarray:
    """Box-downsample a mask [H, W] to [H//s, W//s]: a pixel is set when at least half its block is."""
    s = _check_ds(downsample)
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ValueError(f"downsample_mask: mask must be 2-D [H, W], got shape {m.shape}")
    m = m.astype(np.float32)
    if m.max(initial=0) > 1:
        m = m / 255.0
    if s == 1:
        return m > 0.5
    H, W = m.shape[0] // s, m.shape[1] // s
    return m[: H * s, : W * s].reshape(H, s, W, s).mean(axis=(1, 3)) >= 0.5


def soft_mask(points: torch.Tensor, camera, radius: float, downsample: int = 1, *, sharpness: float = 3.0,
              max_radius_px: int = 8) -> torch.Tensor:
    """Differentiable silhouette [H/s, W/s] in [0, 1] of world points [N, 3] (torch).

    Each point adds a Gaussian of standard deviation r_px / 2 (r_px its projected ``radius``) to a
    density field rho; the occupancy is 1 - exp(-sharpness * rho). Gradients flow to the positions.
    """
    if radius <= 0:
        raise ValueError(f"soft_mask: radius must be > 0 m, got {radius!r}")
    H, W = camera_size(camera, downsample)
    rc, z, f = project_torch(points, camera, downsample)
    ok = (z > 1e-6) & torch.isfinite(rc).all(1)
    rc, z = rc[ok], z[ok]
    with torch.no_grad():
        r_px = torch.clamp(f * radius / z, 0.5, float(max_radius_px))
        rmax = int(np.ceil(2.0 * float(r_px.max()))) if len(r_px) else 0
        ctr = torch.round(rc).long()
    sigma = torch.clamp(f * radius / z, 0.5, float(max_radius_px)) * 0.5
    off = torch.arange(-rmax, rmax + 1, device=points.device)
    dr, dc = torch.meshgrid(off, off, indexing="ij")
    rows = ctr[:, None, 0] + dr.reshape(1, -1)
    cols = ctr[:, None, 1] + dc.reshape(1, -1)
    d2 = (rows.to(rc.dtype) - rc[:, None, 0]) ** 2 + (cols.to(rc.dtype) - rc[:, None, 1]) ** 2
    w = torch.exp(-0.5 * d2 / sigma[:, None] ** 2)
    valid = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
    lin = (rows * W + cols)[valid]
    rho = torch.zeros(H * W, dtype=points.dtype, device=points.device).index_add(0, lin, w[valid])
    return (1.0 - torch.exp(-sharpness * rho)).reshape(H, W)
