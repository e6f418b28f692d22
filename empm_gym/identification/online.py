"""Online identification while streaming (the paper's quasi-static update).

:class:`OnlineIdentifier` takes frames one by one (:class:`OnlineFrame`: fused object points, object masks
per camera, end-effector positions and grip flags), keeps a simulated twin that follows the streamed
end-effector motion (velocity over the last frame interval = position difference * fps), and detects
quasi-static moments: every end-effector slower than ``speed_threshold`` (m/s) and the observed points
moved less than ``motion_threshold`` (m, Chamfer distance between consecutive frames). At such a moment,
at most once every ``k`` frames, it runs the update: simulate ``H`` frame intervals from the twin's
current state with the end-effectors held still; at equilibrium the body should stay where it is
observed, so the loss is

    Chamfer(X_H, X_obs_t)  +  mask_weight * (1 - soft IoU of X_H's silhouette with the segmented masks)

(averaged over cameras; each camera splats only the particles that the streamed end-effectors do not hide
from it, as its recorded mask holds only what it sees of the object), and one Adam step on the parameters
in :class:`~.problem.ParamSpace` follows. The twin continues with the updated parameters. :func:`replay` runs
a recording through an updating and a non-updating identifier side by side and reports both losses.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np
import torch

from empm_gym.sim import Rollout, SimulationDiverged, SolverConfig, SolverMPM
from empm_gym.sim.config import end_effector_speed

from . import render as R
from .evaluate import _camera_ious
from .losses import chamfer_distance, chamfer_numpy, soft_mask_loss
from .offline import _initial_values, _sim_kwargs, default_bounds
from .problem import ParamSpace, Scene, quat_angular_velocity, substeps_for

__all__ = ["OnlineFrame", "OnlineIdentifier", "replay"]


@dataclass
class OnlineFrame:
    """One streamed frame: observed object points [n, 3] (m), end-effector centres [K, 3] (m), grip [K]
    (0/1), optional orientations [K, 4] (x, y, z, w) and object masks (one [H, W] bool per camera)."""

    points: np.ndarray
    ee_positions: Optional[np.ndarray] = None
    ee_grip: Optional[np.ndarray] = None
    masks: Optional[Sequence[np.ndarray]] = None
    ee_orientations: Optional[np.ndarray] = None


class OnlineIdentifier:
    """Streaming identification of ``params`` on a twin of ``scene`` (its frame-0 particles, end-effector
    shapes, fps, table and base material; the scene's recorded controls are not used, only streamed ones).

    ``cameras`` are needed for the mask term. ``update=False`` gives the baseline (a twin with fixed
    parameters) with the same loss reporting.
    """

    def __init__(self, scene: Scene, *, params: Sequence[str] = ("E",), init: Optional[Dict[str, float]] = None,
                 cameras: Optional[Sequence] = None, H: int = 10, k: int = 5, lr: float = 0.1,
                 update: bool = True, speed_threshold: float = 0.01, motion_threshold: float = 0.003,
                 mask_weight: float = 0.02, mask_downsample: int = 4, chamfer: str = "both",
                 max_points: int = 2000, bounds: Optional[Dict[str, Tuple[float, float]]] = None, seed: int = 0):
        if H < 1 or k < 1:
            raise ValueError(f"H and k must be >= 1 frames, got H={H}, k={k}")
        self.scene = scene
        self.params = tuple(params)
        init_vals = _initial_values(scene, self.params, init)
        self.space = ParamSpace(self.params, {**default_bounds(init_vals), **(bounds or {})})
        self.base = self.space.material(init_vals, scene.material, scene.table_friction)[0]
        if "yield_stress" in self.params and scene.material.yield_stress is None:
            from empm_gym.sim import MaterialConfig

            m = scene.material
            self.base = MaterialConfig(E=m.E, nu=m.nu, density=m.density, yield_stress=init_vals["yield_stress"])
        self.z = torch.tensor(self.space.to_z(init_vals), dtype=torch.float64, requires_grad=True)
        self.opt = torch.optim.Adam([self.z], lr=lr)
        self.cameras = list(cameras) if cameras is not None else None
        self.H, self.k, self.update_enabled = int(H), int(k), bool(update)
        self.speed_threshold, self.motion_threshold = float(speed_threshold), float(motion_threshold)
        self.mask_weight, self.ds, self.direction = float(mask_weight), int(mask_downsample), chamfer
        self.max_points = int(max_points)
        self.rng = np.random.default_rng(seed)
        self.radius = scene.particle_radius
        mat, mu = self._material()
        self.model = scene.builder([mat], [mu]).finalize(scene.device, requires_grad=False)
        self.solver = SolverMPM(self.model, SolverConfig(cfl=scene.cfl, check_every=0,
                                                         deterministic=scene.deterministic))
        self.state, self._tmp = self.model.state(), self.model.state()
        self.ctrl = self.model.control()
        self._grad = None  # (model, solver, {substeps: (rollout, controls)}) built on the first update
        self.t = -1
        self.prev: Optional[OnlineFrame] = None
        self.seen_last: Optional[OnlineFrame] = None  # the last frame with observed points
        self.since_update = 10**9
        self.history: List[dict] = []
        self.update_time_s = 0.0

    # -- parameters ---------------------------------------------------------------------------
    @property
    def values(self) -> Dict[str, float]:
        return self.space.from_z(self.z.detach().numpy())

    def _material(self):
        return self.space.material(self.values, self.base, self.scene.table_friction)

    def _apply(self):
        mat, mu = self._material()
        self.model.set_materials([mat])
        self.model.world_table_friction.assign(np.array([mu], np.float32))

    # -- streaming ------------------------------------------------------------------------------
    def _check_frame(self, f: OnlineFrame) -> OnlineFrame:
        K = self.model.ee_count
        pts = np.asarray(f.points, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or (len(pts) == 0 and self.prev is None):
            raise ValueError(f"OnlineFrame.points must be an [n, 3] array, non-empty on the first frame (it places "
                             f"the twin), got shape {pts.shape}")
        pos = np.zeros((0, 3)) if f.ee_positions is None else np.asarray(f.ee_positions, np.float64).reshape(-1, 3)
        if len(pos) != K:
            raise ValueError(f"OnlineFrame.ee_positions must have shape [{K}, 3] (the scene's end-effectors), "
                             f"got {len(pos)} rows")
        grip = np.ones(K, np.int32) if f.ee_grip is None else np.asarray(f.ee_grip).reshape(-1).astype(np.int32)
        if grip.shape != (K,) or not np.all((grip == 0) | (grip == 1)):
            raise ValueError(f"OnlineFrame.ee_grip must hold {K} values 0/1, got {grip.tolist()}")
        if f.masks is not None and self.cameras is not None and len(f.masks) != len(self.cameras):
            raise ValueError(f"OnlineFrame.masks has {len(f.masks)} masks for {len(self.cameras)} cameras")
        if len(pts) > self.max_points:
            pts = pts[self.rng.choice(len(pts), self.max_points, replace=False)]
        masks = None
        if f.masks is not None and self.cameras is not None:
            masks = [R.downsample_mask(m, self.ds) for m in f.masks]
        return OnlineFrame(pts, pos, grip, masks, f.ee_orientations)

    def step(self, frame: OnlineFrame) -> dict:
        """Consume the next frame; returns this frame's record (losses, quasi-static flag, update, parameters)."""
        f = self._check_frame(frame)
        self.t += 1
        K = self.model.ee_count
        speed = 0.0
        if self.t > 0:
            vel = (f.ee_positions - self.prev.ee_positions) * self.scene.fps
            omega = np.zeros_like(vel)
            if K and f.ee_orientations is not None and self.prev.ee_orientations is not None:
                omega = quat_angular_velocity(np.stack([self.prev.ee_orientations, f.ee_orientations]),
                                              self.scene.fps)[0]
            # the surface's speed, a turn's included: a gripper turning in place is no quasi-static moment
            speed = end_effector_speed(vel, omega, self.scene.ee_configs) if K else 0.0
            self._advance(vel, omega, speed, self.prev.ee_grip)
        x = self.state.particle_x.numpy()
        if not len(f.points):  # the object wholly hidden (a hand over it): the twin moves on, nothing is scored
            rec = {"frame": self.t, "ee_speed": speed, "obs_motion": float("nan"), "chamfer": float("nan"),
                   "hidden": True, "quasi_static": False, "updated": False}
            self.since_update += 1
            rec.update(self.values)
            self.history.append(rec)
            self.prev = f
            return rec
        # against the last frame that saw the object
        motion = chamfer_numpy(f.points, self.seen_last.points) if self.seen_last is not None else float("inf")
        self.seen_last = f
        rec = {"frame": self.t, "ee_speed": speed, "obs_motion": motion,
               "chamfer": chamfer_numpy(x, f.points, direction=self.direction)}
        if f.masks is not None:
            with torch.no_grad():
                rec["mask_loss"] = float(self._mask_loss(torch.as_tensor(x, dtype=torch.float64), f))
            rec["mask_iou"] = float(np.mean(_camera_ious(x, f.masks, self.cameras, self.radius, self.ds,
                                                         self._end_effectors(f))))
        quasi = self.t > 0 and speed < self.speed_threshold and motion < self.motion_threshold
        rec["quasi_static"] = bool(quasi)
        self.since_update += 1
        rec["updated"] = False
        if self.update_enabled and quasi and self.since_update >= self.k:
            rec["update_loss"] = self._update(f)
            rec["updated"] = True
            self.since_update = 0
        rec.update(self.values)
        self.history.append(rec)
        self.prev = f
        return rec

    def _end_effectors(self, f: OnlineFrame):
        """The frame's end-effectors as :func:`~.evaluate._camera_ious` takes them, or None without any."""
        if not self.model.ee_count:
            return None
        return self.scene.ee_configs, f.ee_positions, f.ee_orientations

    def _mask_loss(self, x: torch.Tensor, f: OnlineFrame) -> torch.Tensor:
        """Mean over cameras of 1 - soft IoU of particles x [N, 3] against the frame's masks, each camera splatting
        only the particles that the frame's end-effectors do not hide from it: a recorded mask holds what the
        camera sees of the object, and a gripper in front of it would otherwise pull the twin's silhouette (and
        the parameters) towards the hole it leaves."""
        from empm_gym.perception.fusion import hidden_by_end_effectors

        ee = self._end_effectors(f)
        xn = x.detach().cpu().numpy()
        terms = []
        for cam, m in zip(self.cameras, f.masks):
            seen = np.ones(len(xn), bool) if ee is None else ~hidden_by_end_effectors(xn, [cam], *ee)
            # (a camera that sees none of the particles scores them all: its mask cannot say where they went)
            pts = x if seen.all() or not seen.any() else x[torch.as_tensor(np.nonzero(seen)[0], device=x.device)]
            terms.append(soft_mask_loss(pts, [cam], [m], self.radius, self.ds))
        return torch.stack(terms).mean()

    def _advance(self, vel, omega, speed, grip):
        """Advance the twin by one frame interval under the streamed end-effector velocity and turn (``speed``:
        the fastest end-effector surface's, m/s)."""
        self._apply()
        K = self.model.ee_count
        sub, dt = substeps_for(self.scene, self.model.materials, speed)
        if K:
            self.ctrl.set(velocity=vel[None], omega=omega[None], grip=grip[None])
        a, b = self.state, self._tmp
        for _ in range(sub):
            self.solver.step(a, b, self.ctrl, dt, guards=False)
            a, b = b, a
        self.solver.check_state(a, step=self.t)
        self.state, self._tmp = a, b

    def _update(self, f: OnlineFrame) -> float:
        """One gradient step on the parameters from an H-frame look-ahead at a quasi-static moment."""
        from empm_gym.autograd import simulate

        t0 = time.perf_counter()
        mat, mu = self._material()
        if self._grad is None:
            gm = self.scene.builder([mat], [mu]).finalize(self.scene.device, requires_grad=True)
            self._grad = (gm, SolverMPM(gm, SolverConfig(cfl=self.scene.cfl, check_every=0,
                                                         deterministic=self.scene.deterministic)), {})
        gm, gs, cache = self._grad
        gm.set_materials([mat])
        gm.world_table_friction.assign(np.array([mu], np.float32))
        sub, dt = substeps_for(self.scene, [mat], 0.0)
        if sub not in cache:
            cache.clear()
            ro = Rollout(gm, gs, steps=self.H * sub, dt=dt, substeps_per_control=sub, record_every=self.H * sub)
            cache[sub] = (ro, ro.make_controls())
        ro, ctrls = cache[sub]
        K = gm.ee_count
        for c in ctrls:
            if K:
                c.set(velocity=np.zeros((1, K, 3)), omega=np.zeros((1, K, 3)), grip=f.ee_grip[None])
        s0 = gm.state(requires_grad=True).from_numpy(self.state.to_numpy())
        self.opt.zero_grad()
        try:
            X = simulate(ro, s0, ctrls, **_sim_kwargs(self.space, self.z))
        except SimulationDiverged:
            self.update_time_s += time.perf_counter() - t0
            return float("nan")
        xh = X[-1]
        loss = chamfer_distance(xh, f.points, direction=self.direction)
        if f.masks is not None and self.cameras is not None and self.mask_weight > 0:
            loss = loss + self.mask_weight * self._mask_loss(xh.to(torch.float64), f).to(loss.dtype)
        loss.backward()
        if torch.isfinite(self.z.grad).all():
            self.opt.step()
            with torch.no_grad():
                self.z.copy_(torch.as_tensor(self.space.clamp(self.z.numpy())))
        self.update_time_s += time.perf_counter() - t0
        return float(loss.detach())


def replay(scene: Scene, frames: Iterable[OnlineFrame], *, progress: bool = True, **kw) -> dict:
    """Stream ``frames`` through an updating identifier and a fixed-parameter baseline (same options ``kw``).

    Returns {"with_updates": records, "without_updates": records, "summary": {...}, "params": final values}.
    """
    from tqdm.auto import tqdm

    kw = dict(kw)
    kw.pop("update", None)
    upd = OnlineIdentifier(scene, update=True, **kw)
    base = OnlineIdentifier(scene, update=False, **kw)
    t0 = time.perf_counter()
    for f in tqdm(frames, desc="online identification", disable=not progress, leave=False):
        upd.step(f)
        base.step(f)
    wall = time.perf_counter() - t0

    def mean(recs, key, first=0):
        v = [r[key] for r in recs[first:] if key in r and np.isfinite(r[key])]
        return float(np.mean(v)) if v else float("nan")

    first_upd = next((r["frame"] for r in upd.history if r["updated"]), None)
    after = first_upd + 1 if first_upd is not None else len(upd.history)
    summary = {
        "frames": len(upd.history),
        "updates": int(sum(r["updated"] for r in upd.history)),
        "quasi_static_frames": int(sum(r["quasi_static"] for r in upd.history)),
        "first_update_frame": first_upd,
        "wall_time_s": wall,
        "update_time_s": upd.update_time_s,
    }
    for key in ("chamfer", "mask_loss", "mask_iou"):
        summary[f"{key}_with_updates"] = mean(upd.history, key, after)
        summary[f"{key}_without_updates"] = mean(base.history, key, after)
    return {"with_updates": upd.history, "without_updates": base.history, "summary": summary,
            "params": upd.values, "initial_params": base.values}
