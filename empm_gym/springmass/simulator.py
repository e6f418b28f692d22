"""Rollouts of a spring-mass model under recorded end-effector motion, forward or on ``wp.Tape``.

The end-effectors follow their per-frame poses: within a frame interval the position moves at constant
velocity and the orientation turns at constant angular velocity (as in the MPM scene). A gripper that is
closed at frame t holds, through control springs (:func:`~.kernels.control_force_kernel`), the particles
that touched it when it closed; they are released when it opens. Other particles meet every end-effector
and the table through Coulomb contact (relative approaching velocity removed, friction on the tangential
part) and are pushed out of the shapes. Attachment is decided on the positions at the closing frame and is
not differentiated (the gradient treats the anchors as constants).

``run`` records the positions at every frame; with ``requires_grad`` it keeps one state per substep on a
tape, and ``backward`` takes the gradient of a loss with respect to the recorded positions to the model's
``stiffness``, ``damping`` and ``spring_log_scale``.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import warp as wp

from empm_gym.sim.config import SHAPE_IDS
from empm_gym.sim.solver import SimulationDiverged

from . import kernels as K
from .model import SpringMassModel

__all__ = ["SpringMassSim"]


class SpringMassSim:
    """A spring-mass model driven by end-effector poses per frame (see the module docstring).

    ``ee_positions`` [T, K, 3] (m), ``ee_orientations`` [T, K, 4] (x, y, z, w) or None, ``ee_grip`` [T, K]
    (1 = closed) at ``fps`` frames per second; ``table_height`` (m, None: no table) with Coulomb
    ``table_friction``; ``contact_radius`` (m, default half the particle spacing) is the particles' radius
    in contacts; ``max_speed`` (m/s) above which the state counts as diverged.
    """

    def __init__(self, model: SpringMassModel, *, fps: float, ee_configs: Sequence = (),
                 ee_positions: Optional[np.ndarray] = None, ee_orientations: Optional[np.ndarray] = None,
                 ee_grip: Optional[np.ndarray] = None, table_height: Optional[float] = None,
                 table_friction: float = 0.5, contact_radius: Optional[float] = None, max_speed: float = 100.0):
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"fps must be a positive frame rate (1/s), got {fps!r}")
        self.model, self.fps = model, float(fps)
        self.ee_configs = list(ee_configs)
        Kn = len(self.ee_configs)
        self.ee_count = Kn
        if Kn:
            p = np.asarray(ee_positions, np.float64)
            if p.ndim != 3 or p.shape[1:] != (Kn, 3) or not np.all(np.isfinite(p)):
                raise ValueError(f"ee_positions must be finite with shape [T, {Kn}, 3], got {p.shape}")
            self.ee_positions = p
            q = np.tile([0.0, 0.0, 0.0, 1.0], (len(p), Kn, 1)) if ee_orientations is None else \
                np.asarray(ee_orientations, np.float64)
            if q.shape != (len(p), Kn, 4):
                raise ValueError(f"ee_orientations must have shape [{len(p)}, {Kn}, 4], got {q.shape}")
            self.ee_orientations = q / np.linalg.norm(q, axis=-1, keepdims=True)
            g = np.zeros((len(p), Kn)) if ee_grip is None else np.asarray(ee_grip)
            if g.shape != (len(p), Kn) or not np.all((g == 0) | (g == 1)):
                raise ValueError(f"ee_grip must have shape [{len(p)}, {Kn}] with values 0/1")
            self.ee_grip = g.astype(np.int32)
        else:
            self.ee_positions = self.ee_orientations = self.ee_grip = None
        r = 0.5 * model.spacing if contact_radius is None else float(contact_radius)
        if not (r >= 0 and math.isfinite(r)):
            raise ValueError(f"contact_radius must be >= 0 m, got {contact_radius!r}")
        self.contact_radius = r
        self.has_table = table_height is not None
        if self.has_table:
            mu = float(table_friction)
            if not (mu >= 0 and math.isfinite(mu)):
                raise ValueError(f"table_friction must be finite and >= 0, got {table_friction!r}")
            # particles start at least their radius above the table, else the table's contact radius shrinks to
            # their height (no jolt at the first step)
            rt = float(np.clip(model.x0[:, 2].min() - float(table_height), 0.0, r))
            self.table_z = float(table_height) + rt - r
        else:
            self.table_z, mu = 0.0, 0.0
        self.table_friction = mu
        self.max_speed = float(max_speed)
        d = model.device
        cfg = self.ee_configs
        self._shape = wp.array([SHAPE_IDS[c.shape] for c in cfg] or [0], dtype=int, device=d)
        self._radius = wp.array([c.radius for c in cfg] or [0.0], dtype=float, device=d)
        self._half_height = wp.array([c.half_height for c in cfg] or [0.0], dtype=float, device=d)
        self._half_extents = wp.array([c.half_extents for c in cfg] or [(0.0, 0.0, 0.0)], dtype=wp.vec3, device=d)
        self._friction = wp.array([c.friction for c in cfg] or [0.0], dtype=float, device=d)
        self._buffers: Dict = {}
        self._attach_cache: Dict = {}
        self.tape: Optional[wp.Tape] = None
        self.records: List[wp.array] = []

    # -- controls ------------------------------------------------------------------------
    @property
    def num_frames(self) -> Optional[int]:
        return None if self.ee_positions is None else len(self.ee_positions)

    def grips_closed(self, frames: int) -> bool:
        return bool(self.ee_count and np.any(self.ee_grip[: max(frames - 1, 1)] == 1))

    def substeps(self, stiffness: float, damping: float, frames: int, *, log_scale_max: float = 0.0) -> Tuple[int, float]:
        """(substeps per frame, dt [s]) stable for these parameters (and the control springs if a gripper closes)."""
        dt_max = self.model.stable_dt(stiffness, damping, control=self.grips_closed(frames), log_scale_max=log_scale_max)
        n = max(1, int(math.ceil((1.0 / self.fps) / dt_max)))
        return n, 1.0 / (self.fps * n)

    def _ee_steps(self, frames: int, sub: int):
        """Per-substep poses [(steps + 1) K] and velocities [steps K] of the end-effectors, as Warp arrays."""
        from scipy.spatial.transform import Rotation

        Kn, d = self.ee_count, self.model.device
        steps = (frames - 1) * sub
        if not Kn:
            z = wp.zeros(1, dtype=wp.vec3, device=d)
            return z, wp.array([wp.quat_identity()], dtype=wp.quat, device=d), z, z
        if self.num_frames is not None and frames > self.num_frames:
            raise ValueError(f"asked for {frames} frames but the end-effector controls hold {self.num_frames}")
        p = self.ee_positions[:frames]
        R = Rotation.from_quat(self.ee_orientations[:frames].reshape(-1, 4))
        rel = (R[Kn:] * R[:-Kn].inv()).as_rotvec().reshape(frames - 1, Kn, 3) if frames > 1 else np.zeros((0, Kn, 3))
        pos = np.empty((steps + 1, Kn, 3))
        rot = np.empty((steps + 1, Kn, 4))
        vel = np.empty((max(steps, 1), Kn, 3))
        om = np.zeros((max(steps, 1), Kn, 3))
        for t in range(frames - 1):
            s = np.arange(sub)[:, None, None] / sub
            pos[t * sub:(t + 1) * sub] = p[t] + s * (p[t + 1] - p[t])
            vel[t * sub:(t + 1) * sub] = (p[t + 1] - p[t]) * self.fps
            om[t * sub:(t + 1) * sub] = rel[t] * self.fps
            R0 = R[t * Kn:(t + 1) * Kn]
            for i in range(sub):
                rot[t * sub + i] = (Rotation.from_rotvec(rel[t] * (i / sub)) * R0).as_quat()
        pos[steps] = p[frames - 1]
        rot[steps] = self.ee_orientations[frames - 1]
        if steps == 0:
            vel[:] = 0.0
        f32 = np.float32
        return (wp.array(pos.reshape(-1, 3).astype(f32), dtype=wp.vec3, device=d),
                wp.array(rot.reshape(-1, 4).astype(f32), dtype=wp.quat, device=d),
                wp.array(vel.reshape(-1, 3).astype(f32), dtype=wp.vec3, device=d),
                wp.array(om.reshape(-1, 3).astype(f32), dtype=wp.vec3, device=d))

    def _sdf(self, x: np.ndarray, k: int, t: int) -> np.ndarray:
        c = self.ee_configs[k]
        d = self.model.device
        out = wp.zeros(len(x), dtype=float, device=d)
        q = self.ee_orientations[t, k]
        wp.launch(K.sdf_kernel, dim=len(x),
                  inputs=[wp.array(x.astype(np.float32), dtype=wp.vec3, device=d), SHAPE_IDS[c.shape],
                          wp.vec3(*self.ee_positions[t, k]), wp.quat(*q), float(c.radius), float(c.half_height),
                          wp.vec3(*c.half_extents)], outputs=[out], device=d, record_tape=False)
        return out.numpy()

    def _attachments(self, x: np.ndarray, t: int, phases: dict):
        """Attachment arrays for the grippers closed at frame t; new closing phases are attached from ``x``."""
        from scipy.spatial.transform import Rotation

        Kn, N = self.ee_count, self.model.particle_count
        key = []
        for k in range(Kn):
            if self.ee_grip[t, k] != 1:
                phases.pop(k, None)
                continue
            if k not in phases:  # the gripper closes now: hold what touches it
                sd = self._sdf(x, k, t)
                held = np.nonzero(sd < self.contact_radius + 0.5 * self.model.spacing)[0]
                R = Rotation.from_quat(self.ee_orientations[t, k])
                local = R.inv().apply(x[held] - self.ee_positions[t, k])
                phases[k] = (t, held, local)
            key.append((k, phases[k][0]))
        key = tuple(key)
        if key not in self._attach_cache:
            owner = np.full(N, -1, np.int32)
            parts, ees, locs = [], [], []
            for k, _ in key:
                _, held, local = phases[k]
                free = owner[held] < 0  # a particle touching two grippers is held by the first
                owner[held[free]] = k
                parts.append(held[free])
                ees.append(np.full(int(free.sum()), k))
                locs.append(local[free])
            d = self.model.device
            p = np.concatenate(parts) if parts else np.zeros(0, np.int64)
            self._attach_cache[key] = (
                wp.array(owner, dtype=int, device=d),
                wp.array(p.astype(np.int32), dtype=int, device=d),
                wp.array((np.concatenate(ees) if ees else np.zeros(0)).astype(np.int32), dtype=int, device=d),
                wp.array((np.concatenate(locs) if locs else np.zeros((0, 3))).astype(np.float32), dtype=wp.vec3,
                         device=d),
            )
        return self._attach_cache[key]

    # -- rollout -------------------------------------------------------------------------
    def _alloc(self, steps: int, requires_grad: bool):
        key = (steps, requires_grad)
        if key not in self._buffers:
            self._buffers.clear()  # one rollout's memory at a time
            d, N = self.model.device, self.model.particle_count
            n_states = steps + 1 if requires_grad else 2
            xs = [wp.zeros(N, dtype=wp.vec3, device=d, requires_grad=requires_grad) for _ in range(n_states)]
            vs = [wp.zeros(N, dtype=wp.vec3, device=d, requires_grad=requires_grad) for _ in range(n_states)]
            fs = [wp.zeros(N, dtype=wp.vec3, device=d, requires_grad=requires_grad)
                  for _ in range(steps if requires_grad else 1)]
            self._buffers[key] = (xs, vs, fs)
        return self._buffers[key]

    def run(self, frames: int, *, substeps: Optional[int] = None, requires_grad: bool = False,
            x0: Optional[np.ndarray] = None, v0: Optional[np.ndarray] = None, progress=None) -> np.ndarray:
        """Simulate frames 0 .. frames-1 from the model's frame-0 body (or ``x0``, ``v0`` [N, 3]); returns the
        positions [frames, N, 3] (m) (the velocities [frames, N, 3] (m/s) are left in ``self.velocities``). ``substeps`` per frame default to the stable count of the model's current
        parameters. Raises :class:`~empm_gym.sim.SimulationDiverged` when the state turns non-finite or faster
        than ``max_speed``."""
        m = self.model
        frames = int(frames)
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        Y, eta = float(m.stiffness.numpy()[0]), float(m.damping.numpy()[0])
        if substeps is None:
            smax = float(m.spring_log_scale.numpy().max()) if m.spring_count else 0.0
            substeps, _ = self.substeps(Y, eta, frames, log_scale_max=smax)
        sub = int(substeps)
        if sub < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        dt = 1.0 / (self.fps * sub)
        steps = (frames - 1) * sub
        xs, vs, fs = self._alloc(max(steps, 1), requires_grad)
        N = m.particle_count
        x_init = m.x0 if x0 is None else np.asarray(x0, np.float64)
        v_init = np.zeros((N, 3)) if v0 is None else np.asarray(v0, np.float64)
        for name, a in (("x0", x_init), ("v0", v_init)):
            if a.shape != (N, 3) or not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite with shape [{N}, 3], got {a.shape}")
        xs[0].assign(x_init.astype(np.float32))
        vs[0].assign(v_init.astype(np.float32))
        ee_pos, ee_rot, ee_vel, ee_om = self._ee_steps(frames, sub)
        out = np.empty((frames, N, 3), np.float32)
        out[0] = x_init
        vel = np.empty((frames, N, 3), np.float32)
        vel[0] = v_init
        self.velocities = vel
        self.records = [xs[0]]
        self.tape = wp.Tape() if requires_grad else None
        g = wp.vec3(*m.gravity)
        integrate = K.integrate_kernel(self.ee_count)
        phases: dict = {}
        no_attach = None
        d = m.device
        try:
            if self.tape is not None:
                self.tape.__enter__()
            for t in range(frames - 1):
                if self.ee_count:
                    owner, ap, ae, al = self._attachments(out[t].astype(np.float64), t, phases)
                else:
                    if no_attach is None:
                        no_attach = (wp.full(N, -1, dtype=int, device=d), wp.zeros(0, dtype=int, device=d))
                    owner, ap, ae, al = no_attach[0], no_attach[1], no_attach[1], None
                for i in range(sub):
                    s = t * sub + i
                    a, b = (s, s + 1) if requires_grad else (s % 2, (s + 1) % 2)
                    f = fs[s] if requires_grad else fs[0]
                    f.zero_()
                    if m.spring_count:
                        wp.launch(K.spring_force_kernel, dim=m.spring_count,
                                  inputs=[xs[a], vs[a], m.spring_indices, m.spring_rest, m.spring_weight,
                                          m.spring_log_scale, m.stiffness, m.damping], outputs=[f], device=d)
                    if ap.shape[0]:
                        wp.launch(K.control_force_kernel, dim=ap.shape[0],
                                  inputs=[xs[a], vs[a], m.particle_mass, ap, ae, al, ee_pos, ee_rot, ee_vel, ee_om,
                                          self.ee_count, s, float(m.config.control_omega)], outputs=[f], device=d)
                    wp.launch(integrate, dim=N,
                              inputs=[xs[a], vs[a], f, m.particle_inv_mass, owner, g, dt, float(m.config.drag),
                                      int(self.has_table), self.table_z, self.table_friction, self.contact_radius,
                                      self._shape, self._radius, self._half_height, self._half_extents,
                                      self._friction, ee_pos, ee_rot, ee_vel, ee_om, s],
                              outputs=[xs[b], vs[b]], device=d)
                b = (t + 1) * sub if requires_grad else ((t + 1) * sub) % 2
                out[t + 1] = xs[b].numpy()
                self.records.append(xs[b])
                vel[t + 1] = vs[b].numpy()
                vmax = float(np.max(np.linalg.norm(vel[t + 1], axis=1)))
                if not np.all(np.isfinite(out[t + 1])) or not math.isfinite(vmax) or vmax > self.max_speed:
                    why = "non-finite positions or velocities" if not math.isfinite(vmax) or \
                        not np.all(np.isfinite(out[t + 1])) else f"a particle speed of {vmax:.3g} m/s > {self.max_speed} m/s"
                    raise SimulationDiverged(
                        f"spring-mass simulation diverged at frame {t + 1} ({why}) with stiffness {Y:.4g} Pa, damping "
                        f"{eta:.4g} Pa s, {sub} substeps per frame (dt {dt:.3g} s); use more substeps or check the "
                        f"parameters and end-effector speeds", step=t + 1, worlds=[0])
                if progress is not None:
                    progress(t + 1)
        finally:
            if self.tape is not None:
                self.tape.__exit__(None, None, None)
        return out

    def backward(self, grad_positions: np.ndarray) -> Dict[str, np.ndarray]:
        """Gradients of a loss with respect to ``stiffness`` [1/Pa units of the loss], ``damping`` and
        ``spring_log_scale`` given its gradient with respect to the positions [frames, N, 3] that ``run``
        (with ``requires_grad``) returned."""
        if self.tape is None:
            raise RuntimeError("backward needs a rollout run with requires_grad=True first")
        g = np.asarray(grad_positions, np.float32)
        if g.shape != (len(self.records), self.model.particle_count, 3):
            raise ValueError(f"grad_positions must have shape {(len(self.records), self.model.particle_count, 3)}, "
                             f"got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError("grad_positions holds non-finite values")
        m = self.model
        # the state buffers are reused between rollouts and a fresh tape's zero() does not know them: clear every
        # adjoint by hand, else the previous backward pass leaks into this one
        for bufs in self._buffers.values():
            for arr in (a for group in bufs for a in group):
                if arr.grad is not None:
                    arr.grad.zero_()
        for a in (m.stiffness, m.damping, m.spring_log_scale):
            a.grad.zero_()
        grads = {}
        for t, rec in enumerate(self.records):
            if t == 0:
                continue  # frame 0 is the given initial state
            grads[rec] = wp.array(g[t], dtype=wp.vec3, device=m.device)
        self.tape.backward(grads=grads)
        out = {"stiffness": m.stiffness.grad.numpy().copy(), "damping": m.damping.grad.numpy().copy(),
               "spring_log_scale": m.spring_log_scale.grad.numpy().copy()}
        for k, v in out.items():
            if not np.all(np.isfinite(v)):
                raise SimulationDiverged(f"spring-mass gradient of {k} is not finite", step=len(self.records) - 1,
                                         worlds=[0])
        return out
