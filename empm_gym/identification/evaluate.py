"""Evaluation of a fitted material on held-out frames.

The scene is simulated from frame 0 with the given material through every frame, and the frames
``eval_frames`` (default: the last 30 %, PhysTwin's split) are compared with the measurements:

- ``chamfer``: symmetric Chamfer distance (m) between particles and observed points, and
  ``chamfer_obs``: mean distance from each observed point to the nearest particle (m);
- ``track``: mean distance (m) between tracked points and their associated particles (visible only);
- ``iou``: 2D mask IoU, particles splatted into each camera (at ``downsample``) vs the object mask, leaving out
  the particles an end-effector hides from that camera (the mask shows only what the camera sees);
- ``psnr`` / ``ssim``: a coloured point rendering vs the observed colour image, over the bounding box of
  the union of both silhouettes (dilated by 4 pixels). Particle colours are sampled from the frame-0
  images where the particle is visible; the background is the observed image with the observed object
  region filled by the median colour of its surroundings.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from . import render as R
from .losses import chamfer_numpy, mask_iou, psnr, ssim, tracking_error
from .problem import Observations, Scene, Views, simulate_frames

__all__ = ["evaluate", "particle_colors", "held_out_frames", "mask_iou_frames"]


def held_out_frames(num_frames: int, train_fraction: float = 0.7) -> list:
    """Frames after the first ``train_fraction`` of the recording (at least one)."""
    if not (0.0 < train_fraction < 1.0):
        raise ValueError(f"train_fraction must lie in (0, 1), got {train_fraction!r}")
    start = min(max(1, int(round(train_fraction * num_frames))), num_frames - 1)
    return list(range(start, num_frames))


def _end_effectors_at(scene: Scene, t: int):
    """(configs, positions [K, 3], orientations [K, 4] or None) of the scene's end-effectors at frame t, or None."""
    if not len(scene.ee_configs) or scene.ee_positions is None or t >= len(scene.ee_positions):
        return None
    return (scene.ee_configs, scene.ee_positions[t],
            None if scene.ee_orientations is None else scene.ee_orientations[t])


def _camera_ious(x: np.ndarray, masks, cameras, radius: float, downsample: int, end_effectors=None) -> list:
    """Mask IoU of particles x [N, 3] (m) splatted into each camera at ``downsample`` against that camera's object
    mask, given already downsampled (:func:`~.render.downsample_mask`). With
    ``end_effectors`` (:func:`_end_effectors_at`), particles an end-effector hides from a camera are not
    splatted into it: the recorded mask shows only what the camera sees of the object (a gripper in front of it
    is not object), and a simulation that holds the object where it really is must not lose IoU for that."""
    from empm_gym.perception.fusion import hidden_by_end_effectors

    out = []
    for m, cam in zip(masks, cameras):
        seen = x if end_effectors is None else x[~hidden_by_end_effectors(x, [cam], *end_effectors)]
        out.append(mask_iou(R.splat_mask(seen, cam, radius, downsample), m))
    return out


def mask_iou_frames(X: np.ndarray, views: Views, frames: Sequence[int], radius: float, downsample: int = 2,
                    scene: Optional[Scene] = None) -> np.ndarray:
    """2D mask IoU per frame (mean over cameras) of simulated particles X [T, N, 3] (m), splatted with
    ``radius`` (m) at ``downsample``, against the views' object masks; NaN where X is not finite. With ``scene``,
    what its end-effectors hide from a camera is left out of that camera's splat (:func:`_camera_ious`)."""
    if views is None or views.masks is None:
        raise ValueError("mask_iou_frames: the views hold no object masks")
    out = np.full(len(frames), np.nan)
    for i, t in enumerate(frames):
        if np.all(np.isfinite(X[t])):
            ee = None if scene is None else _end_effectors_at(scene, t)
            masks = [R.downsample_mask(m, downsample) for m in views.masks[t]]
            out[i] = float(np.mean(_camera_ious(X[t], masks, views.cameras, radius, downsample, ee)))
    return out


def _image(img) -> np.ndarray:
    a = np.asarray(img)
    return a.astype(np.float64) / 255.0 if a.dtype == np.uint8 else a.astype(np.float64)


def _down_image(img: np.ndarray, ds: int) -> np.ndarray:
    if ds == 1:
        return img
    H, W = img.shape[0] // ds, img.shape[1] // ds
    return img[: H * ds, : W * ds].reshape(H, ds, W, ds, -1).mean(axis=(1, 3))


def particle_colors(x0: np.ndarray, views: Views, radius: float, downsample: int = 2) -> np.ndarray:
    """Colours [N, 3] in [0, 1] of particles from the frame-0 images (mean over cameras where visible;
    unseen particles take the colour of the nearest seen one)."""
    from scipy.spatial import cKDTree

    N = len(x0)
    acc, cnt = np.zeros((N, 3)), np.zeros(N)
    imgs = views.images[0]
    for cam, img in zip(views.cameras, imgs):
        im = _down_image(_image(img), downsample)
        _, owner = R.splat_depth(x0, cam, radius, downsample)
        hit = owner >= 0
        np.add.at(acc, owner[hit], im[hit])
        np.add.at(cnt, owner[hit], 1)
    seen = cnt > 0
    if not seen.any():
        return np.full((N, 3), 0.5)
    col = np.zeros((N, 3))
    col[seen] = acc[seen] / cnt[seen, None]
    if (~seen).any():
        _, j = cKDTree(x0[seen]).query(x0[~seen])
        col[~seen] = col[seen][j]
    return col


def _background(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    bg = img.copy()
    if mask.any():
        ring = ndimage.binary_dilation(mask, iterations=4) & ~mask
        fill = np.median(img[ring], axis=0) if ring.any() else np.median(img[~mask], axis=0)
        bg[mask] = fill
    return bg


def _crop(a: np.ndarray, b: np.ndarray, pad: int = 4):
    u = a | b
    if not u.any():
        return None
    r, c = np.nonzero(u)
    return (slice(max(r.min() - pad, 0), r.max() + pad + 1), slice(max(c.min() - pad, 0), c.max() + pad + 1))


def evaluate(scene: Scene, material, friction: Optional[float], obs: Observations, views: Optional[Views] = None, *,
             eval_frames: Optional[Sequence[int]] = None, train_fraction: float = 0.7, downsample: int = 2,
             out_dir=None, progress: bool = True, name: str = "evaluation",
             positions: Optional[np.ndarray] = None) -> dict:
    """Metrics of ``material`` (a MaterialConfig) with table ``friction`` on held-out frames.

    ``positions`` [T', N, 3] (m): the scene's particles as another model family simulated them (the spring-mass
    model, :func:`.springmass.evaluate_spring_mass`); the MPM simulation is then skipped and ``material`` may be
    a dict of that model's parameters (reported as given).

    Returns {"frames": [...], "per_frame": {metric: [...]}, "summary": {metric: mean}, "unscored_frames": [...]}
    (frames where the object is wholly hidden: NaN in every metric, left out of the means); with ``out_dir``
    also writes ``<name>.json``, ``<name>_metrics.png`` and ``<name>.rrd`` there.
    """
    import json

    from tqdm.auto import tqdm

    T = obs.num_frames if scene.num_frames is None else min(obs.num_frames, scene.num_frames)
    frames = list(eval_frames) if eval_frames is not None else held_out_frames(T, train_fraction)
    if not frames or min(frames) < 0 or max(frames) >= T:
        raise ValueError(f"eval_frames must be a non-empty list of frames in [0, {T - 1}], got {frames}")
    mu = scene.table_friction if friction is None else float(friction)
    if positions is None:
        X = simulate_frames(scene, [material], [mu], frames=max(frames) + 1)[:, 0]
    else:
        X = np.asarray(positions)
        if X.ndim != 3 or X.shape[1:] != scene.particles.shape or len(X) <= max(frames):
            raise ValueError(f"positions must have shape [>{max(frames)}, {len(scene.particles)}, 3], got {X.shape}")
        X = X[: max(frames) + 1]
    radius = scene.particle_radius
    track_idx = None
    if obs.tracks is not None and obs.visibility[0].any():
        from scipy.spatial import cKDTree

        keep = np.nonzero(obs.visibility[0])[0]
        _, track_idx = cKDTree(scene.particles).query(obs.tracks[0, keep])
    cols = None
    if views is not None and views.images is not None:
        cols = particle_colors(X[0], views, radius, downsample)
    per = {k: [] for k in ("chamfer", "chamfer_obs", "track", "iou", "psnr", "ssim")}
    for t in tqdm(frames, desc="evaluate", disable=not progress, leave=False):
        x = X[t]
        if not np.all(np.isfinite(x)) or len(obs.points[t]) == 0:  # diverged, or the object wholly hidden: unscored
            for k in per:
                per[k].append(float("nan"))
            continue
        per["chamfer"].append(chamfer_numpy(x, obs.points[t]))
        per["chamfer_obs"].append(chamfer_numpy(x, obs.points[t], direction="obs_to_pred"))
        if track_idx is not None:
            per["track"].append(tracking_error(x[track_idx], obs.tracks[t, keep], obs.visibility[t, keep]))
        if views is None or views.masks is None:
            continue
        ps, ss = [], []
        masks = [R.downsample_mask(m, downsample) for m in views.masks[t]]
        imgs = views.images[t] if views.images is not None else None
        ious = _camera_ious(x, masks, views.cameras, radius, downsample, _end_effectors_at(scene, t))
        for c, cam in enumerate(views.cameras):
            om = masks[c]
            if imgs is not None and cols is not None:
                im = _down_image(_image(imgs[c]), downsample)
                rend, cov = R.render_colors(x, cols, cam, radius, _background(im, om), downsample)
                box = _crop(cov, om)
                if box is not None and im[box].shape[0] > 7 and im[box].shape[1] > 7:
                    ps.append(psnr(rend[box], im[box]))
                    ss.append(ssim(rend[box], im[box]))
        per["iou"].append(float(np.mean(ious)))
        if ps:
            per["psnr"].append(float(np.mean(ps)))
            per["ssim"].append(float(np.mean(ss)))
    per = {k: v for k, v in per.items() if len(v)}
    summary = {k: float(np.nanmean(v)) for k, v in per.items()}
    if isinstance(material, dict):
        mat_out = {**material, "friction": mu}
    else:
        mat_out = {"E": material.E, "nu": material.nu, "density": material.density,
                   "yield_stress": material.yield_stress, "friction": mu}
    out = {"frames": frames, "per_frame": per, "summary": summary, "material": mat_out,
           "unscored_frames": [t for t in frames if len(obs.points[t]) == 0]}
    if out_dir is not None:
        from .report import plot_metrics, save_rrd

        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        with open(d / f"{name}.json", "w", encoding="utf-8") as f:
            json.dump(out, f, indent=2)
        plot_metrics(per, frames, d / f"{name}_metrics.png", title=name)
        full = {k: [None] * len(X) for k in per}
        for k, v in per.items():
            for t, val in zip(frames, v):
                full[k][t] = val
        save_rrd(d / f"{name}.rrd", X, obs.points[: len(X)], obs.fps, ee_positions=scene.ee_positions,
                 ee_configs=scene.ee_configs, ee_orientations=scene.ee_orientations,
                 particle_radius=radius, scalars=full,
                 particle_colors=cols)
        out["files"] = [str(d / f"{name}.json"), str(d / f"{name}_metrics.png"), str(d / f"{name}.rrd")]
    return out
