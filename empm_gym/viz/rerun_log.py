"""Streaming environment rollouts to rerun (``render_mode="rerun"``).

One :class:`RerunLogger` per environment owns its own ``rerun.RecordingStream`` (never the global
one): it saves to an ``.rrd`` file when given a path, keeps the recording in memory otherwise, or
spawns / connects to a viewer when asked. Entities: ``world/object`` (particles), ``world/target``,
``world/ee/<k>`` (each end-effector drawn as its shape: a sphere, a capsule or a box, turned by its
orientation; :func:`log_end_effectors`) and scalars under ``metrics/``.
"""

from __future__ import annotations

from typing import Mapping, Optional, Sequence

import numpy as np

__all__ = ["RerunLogger", "end_effector_shapes", "log_end_effectors"]


def end_effector_shapes(configs: Sequence, positions: np.ndarray,
                        orientations: Optional[np.ndarray] = None) -> list:
    """How to draw end-effectors ``configs`` (:class:`~empm_gym.sim.EndEffectorConfig`) at ``positions``
    ``[K, 3]`` (m, their centres) turned by ``orientations`` ``[K, 4]`` (x, y, z, w; None: unturned), one dict per
    end-effector in rerun's terms: ``{"shape": "sphere", "centre", "radius"}``, ``{"shape": "box", "centre",
    "half_sizes", "quaternion"}`` or ``{"shape": "capsule", "start", "length", "radius", "quaternion"}`` (rerun
    draws a capsule from ``start`` along its own +z; ours is centred on its position, its axis the local z)."""
    from scipy.spatial.transform import Rotation

    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    if len(pos) != len(configs):
        raise ValueError(f"end_effector_shapes: {len(configs)} end-effectors but {len(pos)} positions")
    q = (np.tile([0.0, 0.0, 0.0, 1.0], (len(pos), 1)) if orientations is None
         else np.asarray(orientations, np.float64).reshape(-1, 4))
    if q.shape != (len(pos), 4) or not np.all(np.isfinite(q)) or np.any(np.linalg.norm(q, axis=1) == 0):
        raise ValueError(f"end_effector_shapes: orientations must be {len(pos)} finite non-zero quaternions "
                         f"(x, y, z, w), got shape {q.shape}")
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    out = []
    for cfg, c, qk in zip(configs, pos, q):
        if cfg.shape == "sphere":
            out.append({"shape": "sphere", "centre": c, "radius": float(cfg.radius)})
        elif cfg.shape == "box":
            out.append({"shape": "box", "centre": c, "half_sizes": np.asarray(cfg.half_extents, float),
                        "quaternion": qk})
        else:
            axis = Rotation.from_quat(qk).apply([0.0, 0.0, 1.0])
            out.append({"shape": "capsule", "start": c - cfg.half_height * axis, "length": 2 * float(cfg.half_height),
                        "radius": float(cfg.radius), "quaternion": qk})
    return out


def log_end_effectors(rec, entity: str, configs: Sequence, positions: np.ndarray,
                      orientations: Optional[np.ndarray] = None, colors: Optional[Sequence] = None):
    """Log end-effectors to the rerun ``RecordingStream`` ``rec`` as their shapes (:func:`end_effector_shapes`),
    the k-th under ``<entity>/<k>``, in ``colors[k]`` (RGB, 0-255; default green)."""
    import rerun as rr

    for k, sh in enumerate(end_effector_shapes(configs, positions, orientations)):
        col = [list(colors[k]) if colors is not None else [90, 200, 90]]
        if sh["shape"] == "sphere":
            arch = rr.Ellipsoids3D(centers=[sh["centre"]], half_sizes=[[sh["radius"]] * 3], colors=col,
                                   fill_mode="solid")
        elif sh["shape"] == "box":
            arch = rr.Boxes3D(centers=[sh["centre"]], half_sizes=[sh["half_sizes"]],
                              quaternions=[rr.Quaternion(xyzw=sh["quaternion"])], colors=col, fill_mode="solid")
        else:
            arch = rr.Capsules3D(translations=[sh["start"]], lengths=[sh["length"]], radii=[sh["radius"]],
                                 quaternions=[rr.Quaternion(xyzw=sh["quaternion"])], colors=col, fill_mode="solid")
        rec.log(f"{entity}/{k}", arch)


class RerunLogger:
    """Log frames of one world to rerun.

    Args:
        app_id: the rerun application id.
        path: an ``.rrd`` file to save to; None keeps the recording in memory (``self.memory``).
        spawn: start a viewer and stream to it instead.
    """

    def __init__(self, app_id: str = "empm_gym", *, path: Optional[str] = None, spawn: bool = False):
        try:
            import rerun as rr
        except ImportError as e:  # pragma: no cover - rerun-sdk is a dependency
            raise ImportError("render_mode='rerun' needs the rerun-sdk package (pip install rerun-sdk)") from e
        self.rr = rr
        self.rec = rr.RecordingStream(app_id)
        self.memory = None
        self.path = path
        if spawn:
            self.rec.spawn()
        elif path is not None:
            self.rec.save(path)
        else:
            self.memory = self.rec.memory_recording()
        self.frame = 0

    def log(self, particles: np.ndarray, target: np.ndarray, ee_pos: np.ndarray, ee_configs: Sequence,
            grip: Sequence[int], metrics: Optional[Mapping[str, float]] = None, *, step: Optional[int] = None,
            ee_rot: Optional[np.ndarray] = None):
        """Log one frame: positions in metres, end-effectors ``ee_configs`` at ``ee_pos`` turned by ``ee_rot``
        ([K, 4], x, y, z, w), closed grippers green and the rest orange, ``metrics`` as scalars."""
        rr, rec = self.rr, self.rec
        rec.set_time("step", sequence=self.frame if step is None else int(step))
        p = np.nan_to_num(np.asarray(particles, np.float32)).reshape(-1, 3)
        h = (p[:, 2] - p[:, 2].min()) / max(float(np.ptp(p[:, 2])), 1e-6) if len(p) else np.zeros(0)
        cols = ((1 - h)[:, None] * np.array([90, 140, 230]) + h[:, None] * np.array([10, 30, 120])).astype(np.uint8)
        rec.log("world/object", rr.Points3D(p, colors=cols, radii=0.002))
        rec.log("world/target", rr.Points3D(np.asarray(target, np.float32).reshape(-1, 3), colors=[245, 160, 160],
                                             radii=0.0015))
        log_end_effectors(rec, "world/ee", ee_configs, ee_pos, ee_rot,
                          colors=[[40, 170, 60] if (k < len(grip) and grip[k]) else [240, 150, 30]
                                  for k in range(len(ee_configs))])
        for name, value in (metrics or {}).items():
            rec.log(f"metrics/{name}", rr.Scalars(float(value)))
        self.frame += 1

    def close(self):
        self.rec.flush()
