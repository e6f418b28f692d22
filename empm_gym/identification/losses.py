"""Losses and metrics of identification and evaluation.

- :func:`chamfer_distance`: nearest-neighbour distances between point sets, differentiable (torch)
  with respect to either set. Nearest neighbours are selected with a KD-tree (scipy ``cKDTree``,
  no gradient through the selection) and the distances of the selected pairs are recomputed in torch,
  so the cost is O(N log M) and memory O(N + M) rather than O(N M).
- :func:`tracking_loss` / :func:`tracking_error`: tracked points, visible ones only.
- :func:`mask_iou`, :func:`soft_mask_loss`: 2D silhouettes (see :mod:`.render`).
- :func:`psnr`, :func:`ssim`: image metrics (SSIM with Gaussian windows, Wang et al. 2004).

Units: distances in metres; images as floats in [0, ``data_range``].
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from .render import soft_mask

__all__ = [
    "nearest_neighbors",
    "chamfer_distance",
    "chamfer_numpy",
    "chamfer_frames",
    "chamfer_frames_torch",
    "pad_frames",
    "tracking_loss",
    "tracking_error",
    "mask_iou",
    "soft_iou",
    "soft_mask_loss",
    "psnr",
    "ssim",
]

_DIRECTIONS = ("both", "obs_to_pred", "pred_to_obs")


def _as_points(name, p):
    if isinstance(p, torch.Tensor):
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"{name} must have shape [N, 3], got {tuple(p.shape)}")
        return p
    a = np.asarray(p, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape [N, 3], got {a.shape}")
    return a


def nearest_neighbors(queries: np.ndarray, points: np.ndarray):
    """(distance [N], index [N]) of the nearest of ``points`` [M, 3] to each of ``queries`` [N, 3]."""
    q = np.asarray(queries, np.float64).reshape(-1, 3)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) == 0:
        raise ValueError("nearest_neighbors: the point set is empty")
    d, i = cKDTree(p).query(q, k=1)
    return d, i


def _np(t):
    return t.detach().cpu().numpy().astype(np.float64) if isinstance(t, torch.Tensor) else t


def chamfer_distance(pred, obs, *, direction: str = "both", squared: bool = False, eps: float = 1e-12):
    """Chamfer distance between point sets ``pred`` [N, 3] and ``obs`` [M, 3] (m).

    ``direction="both"``: 0.5 * (mean over pred of the distance to the nearest obs point + mean over obs
    of the distance to the nearest pred point); ``"obs_to_pred"`` / ``"pred_to_obs"``: one of the two
    means alone (a partial, surface-only observation is best compared with ``"obs_to_pred"``).
    ``squared=True`` uses squared distances (m^2). Returns a torch scalar, differentiable with respect to
    whichever argument is a tensor that requires grad; numpy inputs are converted.
    """
    if direction not in _DIRECTIONS:
        raise ValueError(f"chamfer_distance: direction must be one of {_DIRECTIONS}, got {direction!r}")
    pred = _as_points("chamfer_distance: pred", pred)
    obs = _as_points("chamfer_distance: obs", obs)
    if len(pred) == 0 or len(obs) == 0:
        raise ValueError(f"chamfer_distance: empty point set (pred {len(pred)}, obs {len(obs)} points)")
    like = pred if isinstance(pred, torch.Tensor) else (obs if isinstance(obs, torch.Tensor) else None)
    dtype = like.dtype if like is not None else torch.float64
    device = like.device if like is not None else "cpu"
    P = pred if isinstance(pred, torch.Tensor) else torch.as_tensor(pred, dtype=dtype, device=device)
    O = obs if isinstance(obs, torch.Tensor) else torch.as_tensor(obs, dtype=dtype, device=device)
    pn, on = _np(pred), _np(obs)
    total = []
    if direction in ("both", "pred_to_obs"):
        _, i = cKDTree(on).query(pn, k=1)
        d2 = ((P - O[torch.as_tensor(i, device=device)]) ** 2).sum(1)
        total.append(d2.mean() if squared else torch.sqrt(d2 + eps).mean())
    if direction in ("both", "obs_to_pred"):
        _, j = cKDTree(pn).query(on, k=1)
        d2 = ((O - P[torch.as_tensor(j, device=device)]) ** 2).sum(1)
        total.append(d2.mean() if squared else torch.sqrt(d2 + eps).mean())
    return total[0] if len(total) == 1 else 0.5 * (total[0] + total[1])


def chamfer_numpy(pred: np.ndarray, obs: np.ndarray, *, direction: str = "both", squared: bool = False) -> float:
    """:func:`chamfer_distance` on numpy arrays, returning a float (no gradients)."""
    if direction not in _DIRECTIONS:
        raise ValueError(f"chamfer_numpy: direction must be one of {_DIRECTIONS}, got {direction!r}")
    pred = _as_points("chamfer_numpy: pred", pred)
    obs = _as_points("chamfer_numpy: obs", obs)
    if len(pred) == 0 or len(obs) == 0:
        raise ValueError(f"chamfer_numpy: empty point set (pred {len(pred)}, obs {len(obs)} points)")
    parts = []
    if direction in ("both", "pred_to_obs"):
        d, _ = cKDTree(obs).query(pred, k=1)
        parts.append(np.mean(d**2 if squared else d))
    if direction in ("both", "obs_to_pred"):
        d, _ = cKDTree(pred).query(obs, k=1)
        parts.append(np.mean(d**2 if squared else d))
    return float(parts[0] if len(parts) == 1 else 0.5 * (parts[0] + parts[1]))


def _cuda_device(device) -> Optional[torch.device]:
    """The torch CUDA device for a Warp/torch device name, or None (a CPU device, or torch without CUDA)."""
    if device is None or not str(device).startswith("cuda") or not torch.cuda.is_available():
        return None
    return torch.device(str(device))


class PaddedFrames:
    """Point sets of several frames ([M_t, 3] each) padded into one tensor on a torch device, for
    :func:`chamfer_frames`: ``points`` [T, M, 3] float64, ``valid`` [T, M] (False on padding)."""

    def __init__(self, frames, device):
        sets = [np.asarray(p, np.float64).reshape(-1, 3) for p in frames]
        if any(len(p) == 0 for p in sets):
            raise ValueError(f"chamfer_frames: empty observed point set in frame "
                             f"{next(t for t, p in enumerate(sets) if len(p) == 0)}")
        M = max(len(p) for p in sets)
        pts = np.zeros((len(sets), M, 3))
        valid = np.zeros((len(sets), M), bool)
        for t, p in enumerate(sets):
            pts[t, :len(p)], valid[t, :len(p)] = p, True
        self.points = torch.as_tensor(pts, device=device)
        self.valid = torch.as_tensor(valid, device=device)
        self.count = self.valid.sum(1).to(torch.float64)

    def __len__(self) -> int:
        return int(self.points.shape[0])


def pad_frames(frames, device) -> Optional[PaddedFrames]:
    """:class:`PaddedFrames` of ``frames`` on ``device`` when it is a CUDA device torch can use, else None."""
    dev = _cuda_device(device)
    return None if dev is None else PaddedFrames(frames, dev)


def chamfer_frames(pred, obs, *, direction: str = "both", device=None, first: int = 0,
                   max_pairs: int = 2 ** 27) -> np.ndarray:
    """:func:`chamfer_numpy` of every frame t >= ``first``: ``pred[t - first]`` against ``obs[t]`` -> floats (m).

    ``pred`` is [T, S, 3] (one point count for all frames), ``obs`` a list of T [M_t, 3] arrays or their
    :func:`pad_frames`. On a CUDA ``device`` (or with ``obs`` padded on one) every pairwise distance is
    computed on the GPU in float64 (torch's matrix-product form, exact to ~1e-9 m at these coordinates),
    as many frames at a time as ``max_pairs`` distances allow: the KD-trees' value without their host
    cost, which was most of a CMA-ES generation on the GPU. Elsewhere it is :func:`chamfer_numpy` frame
    by frame.
    """
    if direction not in _DIRECTIONS:
        raise ValueError(f"chamfer_frames: direction must be one of {_DIRECTIONS}, got {direction!r}")
    if not isinstance(obs, PaddedFrames):
        padded = pad_frames(obs, device)
        if padded is None:
            return np.array([chamfer_numpy(p, o, direction=direction) for p, o in zip(pred, obs[first:])])
        obs = padded
    P = torch.as_tensor(np.asarray(pred, np.float64), device=obs.points.device) \
        if not isinstance(pred, torch.Tensor) else pred.detach().to(obs.points.device, torch.float64)
    return _padded_chamfer(P, obs, direction, first, max_pairs, eps=None).cpu().numpy()


def chamfer_frames_torch(pred: torch.Tensor, obs: PaddedFrames, *, direction: str = "both", first: int = 0,
                         eps: float = 1e-12, max_pairs: int = 2 ** 27) -> torch.Tensor:
    """:func:`chamfer_distance` of every frame t >= ``first`` (``pred[t - first]`` [T, S, 3], a tensor that may
    require grad, against the padded ``obs[t]``) -> [T] on ``pred``'s device, differentiable with respect to
    ``pred``. The nearest neighbours come from all pairs on ``obs``' device (no KD-trees, no host copies of
    the points); the distances to them carry the gradient, as in :func:`chamfer_distance`."""
    if direction not in _DIRECTIONS:
        raise ValueError(f"chamfer_frames_torch: direction must be one of {_DIRECTIONS}, got {direction!r}")
    return _padded_chamfer(pred.to(obs.points.device, torch.float64), obs, direction, first, max_pairs,
                           eps=eps).to(pred.device, pred.dtype)


def _padded_chamfer(P: torch.Tensor, obs: PaddedFrames, direction: str, first: int, max_pairs: int,
                    eps: Optional[float]) -> torch.Tensor:
    """Per-frame Chamfer of P [T, S, 3] (float64, on obs' device) against ``obs`` frames ``first`` ...: the
    nearest distances (``eps`` None), or sqrt(squared distance to the nearest point + eps), differentiable."""
    T = len(obs) - first
    if P.ndim != 3 or P.shape[0] != T or P.shape[2] != 3 or P.shape[1] == 0:
        raise ValueError(f"chamfer_frames: pred must be [{T}, S > 0, 3], got {tuple(P.shape)}")
    out = []
    step = max(1, int(max_pairs // max(1, P.shape[1] * obs.points.shape[1])))
    for a in range(0, T, step):
        b = min(T, a + step)
        p, o = P[a:b], obs.points[first + a:first + b]
        valid, count = obs.valid[first + a:first + b], obs.count[first + a:first + b]
        with torch.no_grad():
            d = torch.cdist(p.detach(), o, compute_mode="use_mm_for_euclid_dist")  # [c, S, M]
        parts = []
        if direction in ("both", "pred_to_obs"):
            d_po = d.masked_fill(~valid[:, None, :], float("inf")).min(2)
            if eps is None:
                parts.append(d_po.values.mean(1))
            else:
                near = torch.gather(o, 1, d_po.indices[..., None].expand(-1, -1, 3))
                parts.append(torch.sqrt(((p - near) ** 2).sum(-1) + eps).mean(1))
        if direction in ("both", "obs_to_pred"):
            d_op = d.min(1)
            if eps is None:
                dist = d_op.values
            else:
                near = torch.gather(p, 1, d_op.indices[..., None].expand(-1, -1, 3))
                dist = torch.sqrt(((o - near) ** 2).sum(-1) + eps)
            parts.append((dist * valid).sum(1) / count)
        out.append(parts[0] if len(parts) == 1 else 0.5 * (parts[0] + parts[1]))
    return torch.cat(out)


def _track_args(pred, target, visible):
    if tuple(pred.shape) != tuple(np.shape(target)) or pred.shape[-1] != 3:
        raise ValueError(f"tracking: pred {tuple(pred.shape)} and target {tuple(np.shape(target))} must both be [..., M, 3]")
    vis = torch.as_tensor(np.asarray(visible, bool)) if not isinstance(visible, torch.Tensor) else visible.bool()
    if tuple(vis.shape) != tuple(pred.shape[:-1]):
        raise ValueError(f"tracking: visibility has shape {tuple(vis.shape)}, expected {tuple(pred.shape[:-1])}")
    tgt = target if isinstance(target, torch.Tensor) else torch.as_tensor(np.asarray(target), dtype=pred.dtype)
    return tgt.to(pred.dtype), vis.to(pred.device)


def tracking_loss(pred: torch.Tensor, target, visible) -> torch.Tensor:
    """Mean squared distance (m^2) between predicted and tracked points over visible entries only.

    ``pred`` and ``target`` are [..., M, 3], ``visible`` [..., M] (bool). Occluded entries contribute
    neither to the value nor to the gradient; with nothing visible the loss is 0.
    """
    tgt, vis = _track_args(pred, target, visible)
    d2 = ((pred - tgt) ** 2).sum(-1)
    n = vis.sum()
    if int(n) == 0:
        return pred.sum() * 0.0
    return (d2 * vis).sum() / n


def tracking_error(pred, target, visible) -> float:
    """Mean Euclidean distance (m) between predicted and tracked points over visible entries (nan if none)."""
    p = np.asarray(_np(pred), np.float64)
    t = np.asarray(_np(target), np.float64)
    v = np.asarray(_np(visible), bool)
    if p.shape != t.shape or v.shape != p.shape[:-1]:
        raise ValueError(f"tracking_error: shapes pred {p.shape}, target {t.shape}, visible {v.shape} disagree")
    if not v.any():
        return float("nan")
    return float(np.linalg.norm(p - t, axis=-1)[v].mean())


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two binary masks of equal shape (1.0 when both are empty)."""
    a = np.asarray(a, bool)
    b = np.asarray(b, bool)
    if a.shape != b.shape:
        raise ValueError(f"mask_iou: mask shapes differ: {a.shape} vs {b.shape}")
    union = np.logical_or(a, b).sum()
    if union == 0:
        return 1.0
    return float(np.logical_and(a, b).sum() / union)


def soft_iou(pred: torch.Tensor, target) -> torch.Tensor:
    """Soft IoU sum(p t) / sum(p + t - p t) of an occupancy image in [0, 1] and a target mask."""
    t = torch.as_tensor(np.asarray(target, np.float32) if not isinstance(target, torch.Tensor) else target,
                        dtype=pred.dtype, device=pred.device)
    if t.shape != pred.shape:
        raise ValueError(f"soft_iou: target shape {tuple(t.shape)} differs from prediction {tuple(pred.shape)}")
    inter = (pred * t).sum()
    union = (pred + t - pred * t).sum()
    return inter / torch.clamp(union, min=1e-9)


def soft_mask_loss(points: torch.Tensor, cameras, masks, radius: float, downsample: int = 4) -> torch.Tensor:
    """Mean over cameras of 1 - soft IoU between the points' soft silhouette and the observed mask.

    ``masks``: one boolean mask per camera, already at the ``downsample`` resolution
    (see :func:`empm_gym.identification.render.downsample_mask`).
    """
    if len(cameras) != len(masks):
        raise ValueError(f"soft_mask_loss: {len(cameras)} cameras but {len(masks)} masks")
    if len(cameras) == 0:
        raise ValueError("soft_mask_loss: need at least one camera")
    losses = [1.0 - soft_iou(soft_mask(points, cam, radius, downsample), m) for cam, m in zip(cameras, masks)]
    return torch.stack(losses).mean()


def psnr(a: np.ndarray, b: np.ndarray, *, data_range: float = 1.0, mask: Optional[np.ndarray] = None) -> float:
    """Peak signal-to-noise ratio (dB) of two images of equal shape, over ``mask`` pixels if given."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"psnr: image shapes differ: {a.shape} vs {b.shape}")
    err = (a - b) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != a.shape[:2]:
            raise ValueError(f"psnr: mask shape {m.shape} differs from image size {a.shape[:2]}")
        err = err[m]
    if err.size == 0:
        return float("nan")
    mse = float(err.mean())
    if mse == 0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / mse))


def ssim(a: np.ndarray, b: np.ndarray, *, data_range: float = 1.0, sigma: float = 1.5) -> float:
    """Mean structural similarity of two images (grey [H, W] or colour [H, W, C], channels averaged).

    Gaussian-weighted local statistics (standard deviation ``sigma`` pixels, truncated at 3.5 sigma),
    constants K1 = 0.01, K2 = 0.03, sample covariances, as in Wang et al. (2004).
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"ssim: image shapes differ: {a.shape} vs {b.shape}")
    if a.ndim == 3:
        return float(np.mean([ssim(a[..., c], b[..., c], data_range=data_range, sigma=sigma) for c in range(a.shape[2])]))
    if a.ndim != 2:
        raise ValueError(f"ssim: images must be [H, W] or [H, W, C], got shape {a.shape}")
    C1, C2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    filt = lambda x: ndimage.gaussian_filter(x, sigma, truncate=3.5, mode="reflect")  # noqa: E731
    truncate_r = int(3.5 * sigma + 0.5)
    npix = (2 * truncate_r + 1) ** 2
    cov_norm = npix / (npix - 1.0) if npix > 1 else 1.0
    mu_a, mu_b = filt(a), filt(b)
    va = cov_norm * (filt(a * a) - mu_a**2)
    vb = cov_norm * (filt(b * b) - mu_b**2)
    vab = cov_norm * (filt(a * b) - mu_a * mu_b)
    s = ((2 * mu_a * mu_b + C1) * (2 * vab + C2)) / ((mu_a**2 + mu_b**2 + C1) * (va + vb + C2))
    pad = truncate_r
    if s.shape[0] > 2 * pad and s.shape[1] > 2 * pad:
        s = s[pad:-pad, pad:-pad]
    return float(s.mean())
