"""Streaming environment rollouts to rerun (``render_mode="rerun"``).

One :class:`RerunLogger` per environment owns its own ``rerun.RecordingStream`` (never the global
one): it saves to an ``.rrd`` file when given a path, keeps the recording in memory otherwise, or
spawns / connects to a viewer when asked. Entities: ``world/object`` (particles), ``world/target``,
``world/ee/<k>`` (end-effector centres, sized by their radius) and scalars under ``metrics/``.
"""

from __future__ import annotations

from typing import Mapping, Optional, Sequence

import numpy as np

__all__ = ["RerunLogger"]


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

    def log(self, particles: np.ndarray, target: np.ndarray, ee_pos: np.ndarray, ee_radius: Sequence[float],
            grip: Sequence[int], metrics: Optional[Mapping[str, float]] = None, *, step: Optional[int] = None):
        """Log one frame: positions in metres, ``metrics`` as scalars."""
        rr, rec = self.rr, self.rec
        rec.set_time("step", sequence=self.frame if step is None else int(step))
        p = np.nan_to_num(np.asarray(particles, np.float32)).reshape(-1, 3)
        h = (p[:, 2] - p[:, 2].min()) / max(float(np.ptp(p[:, 2])), 1e-6) if len(p) else np.zeros(0)
        cols = ((1 - h)[:, None] * np.array([90, 140, 230]) + h[:, None] * np.array([10, 30, 120])).astype(np.uint8)
        rec.log("world/object", rr.Points3D(p, colors=cols, radii=0.002))
        rec.log("world/target", rr.Points3D(np.asarray(target, np.float32).reshape(-1, 3), colors=[245, 160, 160],
                                             radii=0.0015))
        for k, (pos, r) in enumerate(zip(np.asarray(ee_pos, np.float32).reshape(-1, 3), ee_radius)):
            col = [40, 170, 60] if (k < len(grip) and grip[k]) else [240, 150, 30]
            rec.log(f"world/ee/{k}", rr.Points3D(pos[None], colors=[col], radii=float(r)))
        for name, value in (metrics or {}).items():
            rec.log(f"metrics/{name}", rr.Scalars(float(value)))
        self.frame += 1

    def close(self):
        self.rec.flush()
