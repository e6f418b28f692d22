"""The batched environment core: N worlds of one task simulated together in one Warp model.

:class:`BatchedCore` owns the model, the solver and the per-world bookkeeping (targets, materials,
random generators, reward state). The single environment, the Gymnasium vector environment, the
stable-baselines3 adapter and the sampling planners are all thin layers over it, so they cannot
disagree: a single environment is a core with ``num_envs=1``.

Reward (every task, same scale): with ``cd`` the symmetric Chamfer distance [m] between a fixed
subsample of the object's particles and the target cloud, ``cd0`` its value at reset and ``iou`` the
occupancy IoU of all particles against the target on a voxel grid,

    reward_chamfer = 0.5 * (cd_{t-1} - cd_t) / cd0
    reward_iou     = 0.5 * (iou_t - iou_{t-1})
    reward         = reward_chamfer + reward_iou

so the return of an episode is 0.5 * (1 - cd_T / cd0) + 0.5 * (iou_T - iou_0): dimensionless, 1 at
best, 0 for doing nothing, whatever the task.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
from typing import Dict, List, Mapping, Optional, Sequence, Union

import numpy as np
import warp as wp

from ..sim import (MaterialConfig, ModelBuilder, SimulationDiverged, SolverConfig, SolverMPM, TableConfig,
                   read_material, stable_dt)
from . import kernels as EK
from .tasks import TASKS, Task

__all__ = ["BatchedCore", "OBS_MODES", "load_material", "RANDOMIZE_KEYS"]

OBS_MODES = ("state", "points", "depth")
RANDOMIZE_KEYS = ("E", "nu", "density", "yield_stress", "friction")
REWARD_WEIGHT_CHAMFER = 0.5
REWARD_WEIGHT_IOU = 0.5


def load_material(material: Union[None, str, os.PathLike, Mapping], default: Mapping) -> Dict:
    """The flat material dict (:meth:`MaterialConfig.to_dict`) of ``material`` over ``default``.

    ``material`` is a material file path or mapping read by :func:`empm_gym.sim.read_material` (every effect
    in it is simulated; unknown keys raise): a schema 2 file gives the whole material (E, nu, density
    default to ``default``'s), a flat dict (E [Pa], nu, density [kg/m^3], yield_stress [Pa] (None =
    elastic), viscosity [Pa s], friction (table Coulomb coefficient), any effect parameter) overrides
    ``default`` key by key.
    """
    base = MaterialConfig.from_dict(default)
    if material is None:
        mat = base
    elif isinstance(material, (str, os.PathLike, Mapping)):
        try:
            mat = read_material(material, base=base).material
        except FileNotFoundError as exc:
            raise ValueError(f"material file {str(material)!r} does not exist") from exc
    else:
        raise ValueError(f"material must be None, a dict or a JSON file path, got {type(material).__name__}")
    TableConfig(friction=mat.get("friction") if mat.get("friction") is not None else 0.5)
    return mat.to_dict()


def _check_randomize(randomize, material) -> Dict[str, tuple]:
    if randomize is None:
        return {}
    if not isinstance(randomize, Mapping):
        raise ValueError(f"randomize must be a dict {{key: (low_factor, high_factor)}}, got {type(randomize).__name__}")
    out = {}
    for k, v in randomize.items():
        if k not in RANDOMIZE_KEYS:
            raise ValueError(f"randomize key {k!r} is not one of {RANDOMIZE_KEYS}")
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise ValueError(f"randomize[{k!r}] must be a pair (low_factor, high_factor), got {v!r}") from None
        if not (0 < lo <= hi) or not math.isfinite(hi):
            raise ValueError(f"randomize[{k!r}] must satisfy 0 < low <= high (finite), got {v!r}")
        if k == "yield_stress" and material.get("yield_stress") is None:
            raise ValueError("randomize['yield_stress'] needs a plastic material (yield_stress is None)")
        if k == "nu" and material["nu"] * hi >= 0.5:
            raise ValueError(f"randomize['nu'] high factor {hi} takes nu={material['nu']} to >= 0.5")
        out[k] = (lo, hi)
    return out


def voxelize(points: np.ndarray, origin: np.ndarray, voxel: float, res: Sequence[int]) -> np.ndarray:
    """Occupancy [res] (int32) of the voxels holding at least one of ``points`` [n, 3]."""
    occ = np.zeros(tuple(res), np.int32)
    q = np.floor((points - origin) / voxel).astype(int)
    ok = np.all((q >= 0) & (q < np.asarray(res)), axis=1)
    q = q[ok]
    occ[q[:, 0], q[:, 1], q[:, 2]] = 1
    return occ


class BatchedCore:
    """``num_envs`` worlds of one task in one simulation (see the module docstring).

    Args:
        task: a task name ("RopeReshape", "DoughFlatten", "DoughShape") or a :class:`Task`.
        num_envs: number of worlds.
        obs_mode: "state", "points" or "depth".
        material: material file path or dict (see :func:`load_material`; every effect in it is simulated).
        randomize: {key: (low_factor, high_factor)} multiplicative ranges drawn per world at reset.
        task_options: overrides of the task's fields (e.g. ``{"shapes": ("arc",)}``).
        dx: grid cell size [m] (default: the task's).
        particles_per_cell: particle sampling density.
        control_dt: control period [s] (default: the task's).
        max_episode_steps: truncation horizon of each world, or None for none.
        obs_particles: particles in the "state" observation; points_count: in the "points" one.
        obs_target_points: target points in observations; chamfer_points: points used for the reward
            (default: the task's ``chamfer_points``).
        depth_resolution: side [px] of the depth image.
        device: Warp device ("cpu", "cuda:0", None = Warp's default).
    """

    def __init__(
        self,
        task: Union[str, Task] = "RopeReshape",
        num_envs: int = 1,
        *,
        obs_mode: str = "state",
        material=None,
        randomize=None,
        task_options: Optional[Mapping] = None,
        dx: Optional[float] = None,
        particles_per_cell: float = 8,
        control_dt: Optional[float] = None,
        max_episode_steps: Optional[int] = None,
        obs_particles: int = 64,
        points_count: int = 256,
        obs_target_points: int = 64,
        chamfer_points: Optional[int] = None,
        depth_resolution: int = 64,
        cfl: float = 0.4,
        device=None,
    ):
        if isinstance(task, str):
            if task not in TASKS:
                raise ValueError(f"task must be one of {sorted(TASKS)}, got {task!r}")
            task = TASKS[task]()
        if task_options:
            known = set(task.__dataclass_fields__)
            bad = [k for k in task_options if k not in known]
            if bad:
                raise ValueError(f"task_options {bad} are not fields of {type(task).__name__}; known: {sorted(known)}")
            task = dataclasses.replace(task, **task_options)
        self.task = task
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.num_envs = W = int(num_envs)
        if obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")
        self.obs_mode = obs_mode
        self.material = load_material(material, task.material)
        self.randomize = _check_randomize(randomize, self.material)
        self.dx = float(dx if dx is not None else task.dx)
        self.control_dt = float(control_dt if control_dt is not None else task.control_dt)
        if not (self.control_dt > 0 and math.isfinite(self.control_dt)):
            raise ValueError(f"control_dt must be a positive number of seconds, got {control_dt!r}")
        if max_episode_steps is not None and int(max_episode_steps) < 1:
            raise ValueError(f"max_episode_steps must be >= 1 or None, got {max_episode_steps!r}")
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.max_speed = float(task.max_speed)
        self.ee_lower = np.asarray(task.ee_lower, np.float32)
        self.ee_upper = np.asarray(task.ee_upper, np.float32)

        # -- the model: W identical worlds ----------------------------------------------------------
        grid = task.grid(self.dx)
        b = ModelBuilder(grid, table=TableConfig(height=0.0, friction=float(self.material.get("friction", 0.5))))
        x, vol = task.object_particles(self.dx, particles_per_cell)
        ees = task.end_effectors()
        nominal = MaterialConfig.from_dict(self.material)
        for _ in range(W):
            w = b.add_world(nominal)
            b.add_particles(w, x, vol)
            for cfg, pos in ees:
                b.add_end_effector(w, cfg, pos)
        self.model = model = b.finalize(device, requires_grad=False)
        self.device = model.device
        self.K = model.ee_count
        self.P = model.world_slice(0).stop
        self.action_dim = task.action_dim
        self.solver = SolverMPM(model, SolverConfig(cfl=cfl, check_every=0))

        # substep: stable for the stiffest / lightest material randomisation can draw, at full speed
        extreme = self._extreme_material()
        self.max_wave_speed = extreme.max_wave_speed
        dt_max = stable_dt([extreme], self.dx, cfl, self.max_speed * math.sqrt(3.0))
        n = max(2, int(math.ceil(self.control_dt / dt_max - 1e-9)))
        self.substeps = n + (n % 2)  # even, so the result always ends in self.state
        self.dt = self.control_dt / self.substeps

        self.state = model.state()
        self._next = model.state()
        self._rest = model.state()
        self.control = model.control()
        self._graph = None

        # -- observation / reward subsets -----------------------------------------------------------
        self.obs_particles = min(int(obs_particles), self.P)
        self.points_count = min(int(points_count), self.P)
        self.chamfer_points = min(int(task.chamfer_points if chamfer_points is None else chamfer_points), self.P)
        self.obs_target_points = min(int(obs_target_points), task.target_points)
        self.chamfer_target_points = min(self.chamfer_points, task.target_points)
        G = max(self.chamfer_points, self.obs_particles, self.points_count if obs_mode == "points" else 0)
        self.gather_count = G
        perm = np.random.default_rng(12345).permutation(self.P)[:G]
        key = task.observed_particle_key(x)
        if key is not None:  # the observed particles in the task's order (a set, not its order, enters the reward)
            head = perm[: self.obs_particles]
            perm[: self.obs_particles] = head[np.argsort(np.asarray(key)[head], kind="stable")]
        idx = np.stack([model.world_particle_start[w] + perm for w in range(W)]).astype(np.int32)
        self._gather_idx = wp.array(idx, dtype=int, device=self.device)
        self._gathered = wp.zeros((W, G), dtype=wp.vec3, device=self.device)
        # the observed particles alone (the first of the gathered ones): observe() reads back only these, not the
        # Chamfer sample (reading back all G per step took 6.5 of 27 ms per vector step at 1024 rope worlds)
        self._obs_count = {"state": self.obs_particles, "points": self.points_count}.get(obs_mode, 0)
        self._obs_gathered = wp.zeros((W, max(self._obs_count, 1)), dtype=wp.vec3, device=self.device)
        self._target_dev = wp.zeros((W, self.chamfer_target_points), dtype=wp.vec3, device=self.device)
        self._cd_a = wp.zeros(W, dtype=float, device=self.device)
        self._cd_b = wp.zeros(W, dtype=float, device=self.device)

        lo = np.asarray(grid.lower, np.float32)
        hi = lo + (np.asarray(model.grid_res) - 1) * self.dx
        self.space_lower, self.space_upper = lo, hi.astype(np.float32)
        vox = float(task.occupancy_voxel)
        self.occ_origin = lo.copy()
        self.occ_voxel = vox
        self.occ_res = tuple(int(math.ceil((hi[i] - lo[i]) / vox)) for i in range(3))
        self._occ = wp.zeros((W, *self.occ_res), dtype=int, device=self.device)
        self._occ_target = wp.zeros((W, *self.occ_res), dtype=int, device=self.device)
        self._inter = wp.zeros(W, dtype=int, device=self.device)
        self._union = wp.zeros(W, dtype=int, device=self.device)
        self.depth_resolution = int(depth_resolution)

        # -- per-world bookkeeping ------------------------------------------------------------------
        self.rngs: List[np.random.Generator] = [np.random.default_rng() for _ in range(W)]
        self.targets = np.zeros((W, task.target_points, 3), np.float32)
        self._target_obs = np.zeros((W, self.obs_target_points, 3), np.float32)
        self.materials: List[Dict] = [dict(self.material) for _ in range(W)]
        self.grip = np.tile(np.asarray(task.default_grip or (0,) * self.K, np.int32), (W, 1))
        self.cd0 = np.ones(W, np.float64)
        self.cd_prev = np.zeros(W, np.float64)
        self.iou_prev = np.zeros(W, np.float64)
        self.elapsed = np.zeros(W, np.int64)
        self._mask = wp.zeros(W, dtype=int, device=self.device)
        self._all_worlds = wp.array(np.arange(W, dtype=np.int32), dtype=int, device=self.device)
        self._all_mask = wp.array(np.ones(W, np.int32), dtype=int, device=self.device)

    # ------------------------------------------------------------------------------------ helpers
    def _extreme_material(self) -> MaterialConfig:
        """The stiffest, lightest material randomisation can draw (it sets the stable substep)."""
        m = dict(self.material)
        r = self.randomize
        m["E"] = m["E"] * r.get("E", (1, 1))[1]
        m["density"] = m["density"] * r.get("density", (1, 1))[0]
        m["nu"] = m["nu"] * (r.get("nu", (1, 1))[1] if m["nu"] > 0 else r.get("nu", (1, 1))[0])
        return MaterialConfig.from_dict(m)

    def _sample_material(self, rng: np.random.Generator) -> Dict:
        m = dict(self.material)
        for k in RANDOMIZE_KEYS:  # fixed order, so the draw sequence is reproducible
            if k in self.randomize:
                lo, hi = self.randomize[k]
                base = m[k] if k != "friction" else m.get("friction", 0.5)
                m[k] = float(base * rng.uniform(lo, hi))
        return m

    def _apply_materials(self):
        self.model.set_materials([MaterialConfig.from_dict(m) for m in self.materials])
        self.model.world_table_friction.assign(
            np.array([m.get("friction", 0.5) for m in self.materials], np.float32))

    # ------------------------------------------------------------------------------------ metrics
    def _world_arrays(self, worlds: Optional[Sequence[int]]):
        """(number of worlds, device array of their indices, device mask [W]) for ``worlds`` (None: all)."""
        if worlds is None:
            return self.num_envs, self._all_worlds, self._all_mask
        ws = np.asarray(worlds, np.int32)
        mask = np.zeros(self.num_envs, np.int32)
        mask[ws] = 1
        return len(ws), wp.array(ws, dtype=int, device=self.device), wp.array(mask, dtype=int, device=self.device)

    def metrics(self, worlds: Optional[Sequence[int]] = None):
        """(chamfer [n] m, iou [n]) of the given worlds' current state (default all) against their targets.

        A reset computes them for the reset worlds alone: at 1024 worlds the full computation is about 1 ms."""
        n, ws, mask = self._world_arrays(worlds)
        wp.launch(EK.gather_kernel, dim=(n, self.gather_count),
                  inputs=[self.state.particle_x, self._gather_idx, ws], outputs=[self._gathered], device=self.device)
        a = self._gathered[:, : self.chamfer_points] if self.chamfer_points < self.gather_count else self._gathered
        self._cd_a.zero_()
        self._cd_b.zero_()
        wp.launch(EK.nearest_mean_kernel, dim=(n, self.chamfer_points),
                  inputs=[a, self._target_dev, ws, 0.5 / self.chamfer_points], outputs=[self._cd_a],
                  device=self.device)
        wp.launch(EK.nearest_mean_kernel, dim=(n, self.chamfer_target_points),
                  inputs=[self._target_dev, a, ws, 0.5 / self.chamfer_target_points], outputs=[self._cd_b],
                  device=self.device)
        self._occ.zero_()
        self._inter.zero_()
        self._union.zero_()
        wp.launch(EK.occupancy_kernel, dim=self.model.particle_count,
                  inputs=[self.state.particle_x, self.model.particle_world, mask, wp.vec3(*self.occ_origin),
                          1.0 / self.occ_voxel, wp.vec3i(*self.occ_res)], outputs=[self._occ], device=self.device)
        wp.launch(EK.iou_counts_kernel, dim=(n, *self.occ_res), inputs=[self._occ, self._occ_target, ws],
                  outputs=[self._inter, self._union], device=self.device)
        cd = self._cd_a.numpy().astype(np.float64) + self._cd_b.numpy().astype(np.float64)
        inter, union = self._inter.numpy(), self._union.numpy()
        iou = inter / np.maximum(union, 1)
        if worlds is None:
            return cd, iou
        sel = np.asarray(worlds, np.int64)
        return cd[sel], iou[sel]

    # ------------------------------------------------------------------------------------ reset
    def _set_targets(self, worlds: Sequence[int], targets: Sequence[np.ndarray]):
        """The target point clouds [m] of the given worlds, with everything derived from them (device copies,
        voxels, observation), uploaded in one batch: one copy per array and a scatter kernel, not two blocking
        copies per world."""
        ws = np.asarray(worlds, np.int32)
        self.targets[ws] = np.stack([np.asarray(t, np.float32) for t in targets])
        occ = np.stack([voxelize(self.targets[w], self.occ_origin, self.occ_voxel, self.occ_res) for w in ws])
        ws_dev = wp.array(ws, dtype=int, device=self.device)
        sub = self.targets[ws][:, self.task.target_subset_indices(self.chamfer_target_points)]
        wp.launch(EK.scatter_rows_vec3_kernel, dim=(len(ws), self.chamfer_target_points),
                  inputs=[ws_dev, wp.array(np.ascontiguousarray(sub), dtype=wp.vec3, device=self.device)],
                  outputs=[self._target_dev], device=self.device)
        wp.launch(EK.scatter_rows_int_kernel, dim=(len(ws), occ[0].size),
                  inputs=[ws_dev, wp.array(occ.reshape(len(ws), -1).astype(np.int32), dtype=int, device=self.device)],
                  outputs=[self._occ_target.reshape((self.num_envs, -1))], device=self.device)
        # the target part of the observation changes only here, so it is clipped once, not every step
        self._target_obs[ws] = self._clip_points(self.targets[ws][:, self.task.target_subset_indices(self.obs_target_points)])

    def target_subset(self, w: int, count: int) -> np.ndarray:
        """The ``count`` points of world w's target that the reward (Chamfer) or the observation uses."""
        return self.targets[w, self.task.target_subset_indices(count)]

    def reset(self, worlds: Optional[Sequence[int]] = None, seeds: Optional[Sequence[Optional[int]]] = None):
        """Reset the given worlds (default all); ``seeds[i]`` (None keeps the world's generator) reseeds them."""
        W = self.num_envs
        worlds = list(range(W)) if worlds is None else [int(w) for w in worlds]
        if not worlds:
            return
        if seeds is not None and len(seeds) != len(worlds):
            raise ValueError(f"reset: got {len(seeds)} seeds for {len(worlds)} worlds")
        mask = np.zeros(W, np.int32)
        materials_changed = False
        targets = []
        for i, w in enumerate(worlds):
            if seeds is not None and seeds[i] is not None:
                self.rngs[w] = np.random.default_rng(int(seeds[i]))
            rng = self.rngs[w]
            material = self._sample_material(rng)
            materials_changed |= material != self.materials[w]
            self.materials[w] = material
            targets.append(self.task.sample_target(rng))
            mask[w] = 1
        self._set_targets(worlds, targets)
        if materials_changed:  # without randomisation nothing changes: skip rewriting every world's material
            self._apply_materials()
        self._mask.assign(mask)
        s, r = self.state, self._rest
        wp.launch(EK.reset_worlds_kernel, dim=self.model.particle_count,
                  inputs=[self._mask, self.model.particle_world, r.particle_x],
                  outputs=[s.particle_x, s.particle_v, s.particle_C, s.particle_F], device=self.device)
        wp.launch(EK.reset_ee_kernel, dim=W * self.K, inputs=[self._mask, self.K, r.ee_pos, r.ee_rot],
                  outputs=[s.ee_pos, s.ee_rot], device=self.device)
        cd, iou = self.metrics(worlds)
        sel = np.asarray(worlds)
        self.cd0[sel] = np.maximum(cd, 1e-6)
        self.cd_prev[sel] = cd
        self.iou_prev[sel] = iou
        self.elapsed[sel] = 0
        self.grip[sel] = np.asarray(self.task.default_grip or (0,) * self.K, np.int32)

    # ------------------------------------------------------------------------------------ step
    def check_action(self, action, shape) -> np.ndarray:
        """Validate (shape, finiteness) and clip an action batch to [-1, 1]."""
        try:
            a = np.asarray(action, dtype=np.float32)
        except (TypeError, ValueError):
            raise ValueError(f"action must be a numeric array of shape {shape}, got {type(action).__name__}") from None
        if a.shape != tuple(shape):
            raise ValueError(f"action must have shape {tuple(shape)}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action holds non-finite values (NaN or inf): {a.reshape(-1)[~np.isfinite(a.reshape(-1))][:4]}")
        return np.clip(a, -1.0, 1.0)

    def controls_from_actions(self, actions: np.ndarray):
        """End-effector velocities [W, K, 3] (m/s, kept inside the workspace box) and grips [W, K]."""
        W, K = self.num_envs, self.K
        vel = actions[:, : 3 * K].reshape(W, K, 3).astype(np.float64) * self.max_speed
        pos = self.state.ee_pos.numpy()[: W * K].reshape(W, K, 3)
        T = self.control_dt
        vel = np.minimum(np.maximum(vel, (self.ee_lower - pos) / T), (self.ee_upper - pos) / T)
        vel = np.clip(vel, -self.max_speed, self.max_speed)
        if self.task.grip_control:
            grip = (actions[:, 3 * K:] > 0).astype(np.int32)
        else:
            grip = self.grip
        return vel.astype(np.float32), grip

    def _advance(self):
        if self.device.is_cuda and self._graph is None:
            try:
                with wp.ScopedCapture(device=self.device) as cap:
                    self._substeps()
                self._graph = cap.graph  # capture records the launches without running them
            except Exception:
                self._graph = False
        if self._graph:
            wp.capture_launch(self._graph)
        else:
            self._substeps()

    def _substeps(self):
        a, b = self.state, self._next
        for i in range(self.substeps):
            # the graph replays these substeps: re-sort P2G's particle order once per replay
            self.solver.step(a, b, self.control, self.dt, guards=False, sort=i == 0)
            a, b = b, a

    def step(self, actions: np.ndarray):
        """Advance every world by one control period; returns (reward, terminated, truncated, info) arrays.

        ``actions`` [W, action_dim] must already be checked by :meth:`check_action`.
        """
        W = self.num_envs
        vel, grip = self.controls_from_actions(actions)
        self.grip = grip.copy()
        self.control.set(velocity=vel, grip=grip)
        self._advance()
        diverged = np.zeros(W, bool)
        try:
            self.solver.check_state(self.state)
        except SimulationDiverged as e:
            diverged[e.worlds] = True
        cd, iou = self.metrics()
        cd = np.where(diverged | ~np.isfinite(cd), self.cd_prev, cd)
        iou = np.where(diverged, self.iou_prev, iou)
        r_cd = REWARD_WEIGHT_CHAMFER * (self.cd_prev - cd) / self.cd0
        r_iou = REWARD_WEIGHT_IOU * (iou - self.iou_prev)
        self.cd_prev, self.iou_prev = cd.copy(), iou.copy()  # reset() edits these in place
        self.elapsed += 1
        success = (cd < self.task.success_chamfer) & ~diverged
        terminated = success | diverged
        truncated = np.zeros(W, bool) if self.max_episode_steps is None else (self.elapsed >= self.max_episode_steps) & ~terminated
        reward = r_cd + r_iou
        info = {"reward_chamfer": r_cd, "reward_iou": r_iou, "chamfer": cd, "iou": iou,
                "success": success, "diverged": diverged}
        return reward, terminated, truncated, info

    # ------------------------------------------------------------------------------------ observations
    def observation_bounds(self):
        return self.space_lower, self.space_upper

    def _ee_obs(self, sel) -> np.ndarray:
        pos = self.state.ee_pos.numpy()[: self.num_envs * self.K].reshape(self.num_envs, self.K * 3)[sel]
        pos = np.clip(np.where(np.isnan(pos), 0.0, pos), np.tile(self.space_lower, self.K),
                      np.tile(self.space_upper, self.K))
        return np.concatenate([pos, self.grip[sel].astype(np.float32)], 1).astype(np.float32)

    def _clip_points(self, p):
        """Points [..., 3] with NaN read as 0, clamped to the observation box (as observe_points_kernel does)."""
        p = np.asarray(p, np.float32)
        return np.clip(np.where(np.isnan(p), np.float32(0.0), p), self.space_lower, self.space_upper)

    def observe(self, worlds: Optional[Sequence[int]] = None):
        """Observations of the given worlds (default all): an array [n, ...] ("state") or a dict of arrays.

        After an autoreset only the reset worlds are observed again: their rows replace those of the step's
        observation (a full second observation cost about 1.5 ms per vector step at 1024 worlds)."""
        sel = slice(None) if worlds is None else np.asarray(worlds, np.int64)
        ee = self._ee_obs(sel)
        target = self._target_obs[sel].copy()
        if self.obs_mode == "depth":
            return {"depth": self.depth_images(worlds), "ee": ee, "target": target}
        n, ws, _ = self._world_arrays(worlds)
        wp.launch(EK.observe_points_kernel, dim=(n, self._obs_count),
                  inputs=[self.state.particle_x, self._gather_idx, ws, wp.vec3(*self.space_lower),
                          wp.vec3(*self.space_upper)], outputs=[self._obs_gathered], device=self.device)
        p = self._obs_gathered[:n].numpy()
        if not self.device.is_cuda:  # a CPU array's numpy() is a view of it, which the next call overwrites
            p = p.copy()
        if self.obs_mode == "state":
            return np.concatenate([p.reshape(n, -1), ee, target.reshape(n, -1)], 1)
        return {"points": p, "ee": ee, "target": target}

    def depth_images(self, worlds: Optional[Sequence[int]] = None) -> np.ndarray:
        """Top-down orthographic depth of the given worlds' particles (default all), [n, R, R, 1] uint8:
        255 * (camera_height - z) / camera_height (clipped), i.e. 255 is the table (or farther), smaller is closer
        to the camera."""
        W, R = self.num_envs, self.depth_resolution
        x = np.nan_to_num(self.state.particle_x.numpy()).reshape(W, self.P, 3)
        if worlds is not None:
            x = x[np.asarray(worlds, np.int64)]
            W = len(x)
        lo, hi = self.space_lower, self.space_upper
        ij = np.floor((x[..., :2] - lo[:2]) / (hi[:2] - lo[:2]) * R).astype(np.int64)
        ij = np.clip(ij, 0, R - 1)
        H = float(self.task.camera_height)
        depth = np.clip(H - x[..., 2], 0.0, H)
        img = np.full(W * R * R, H, np.float64)
        flat = (np.arange(W)[:, None] * R * R + ij[..., 1] * R + ij[..., 0]).reshape(-1)
        np.minimum.at(img, flat, depth.reshape(-1))
        img = np.round(255.0 * img / H).astype(np.uint8)
        return img.reshape(W, R, R, 1)

    # ------------------------------------------------------------------------------------ state
    def get_world_states(self, worlds: Sequence[int]) -> List[dict]:
        """Exact copies of the given worlds' simulation state and bookkeeping."""
        sim = self.state.to_numpy()
        out = []
        for w in worlds:
            sl = self.model.world_slice(w)
            es = slice(w * self.K, (w + 1) * self.K)
            d = {k: sim[k][sl].copy() for k in ("particle_x", "particle_v", "particle_C", "particle_F")}
            d.update({"ee_pos": sim["ee_pos"][es].copy(), "ee_rot": sim["ee_rot"][es].copy()})
            out.append({
                "sim": d, "material": dict(self.materials[w]), "target": self.targets[w].copy(),
                "cd0": float(self.cd0[w]), "cd_prev": float(self.cd_prev[w]), "iou_prev": float(self.iou_prev[w]),
                "elapsed": int(self.elapsed[w]), "grip": self.grip[w].copy(),
                "rng": copy.deepcopy(self.rngs[w].bit_generator.state),
            })
        return out

    def set_world_states(self, worlds: Sequence[int], states: Sequence[dict]):
        """Restore worlds from :meth:`get_world_states` dicts (any world's state fits any world)."""
        if len(worlds) != len(states):
            raise ValueError(f"set_world_states: {len(worlds)} worlds but {len(states)} states")
        sim = self.state.to_numpy()
        for w, st in zip(worlds, states):
            if not isinstance(st, Mapping) or "sim" not in st:
                raise ValueError("set_state: expected a dict from get_state() with a 'sim' entry")
            sl = self.model.world_slice(w)
            es = slice(w * self.K, (w + 1) * self.K)
            for k in ("particle_x", "particle_v", "particle_C", "particle_F"):
                v = np.asarray(st["sim"][k], np.float32)
                if v.shape != sim[k][sl].shape:
                    raise ValueError(f"set_state: sim[{k!r}] has shape {v.shape}, expected {sim[k][sl].shape}")
                sim[k][sl] = v
            for k in ("ee_pos", "ee_rot"):
                sim[k][es] = np.asarray(st["sim"][k], np.float32).reshape(sim[k][es].shape)
            self.materials[w] = load_material(st["material"], self.task.material)
            self._set_targets([w], [st["target"]])
            self.cd0[w], self.cd_prev[w], self.iou_prev[w] = st["cd0"], st["cd_prev"], st["iou_prev"]
            self.elapsed[w] = st["elapsed"]
            self.grip[w] = np.asarray(st["grip"], np.int32)
            rng = np.random.default_rng()
            rng.bit_generator.state = copy.deepcopy(st["rng"])
            self.rngs[w] = rng
        self.state.from_numpy(sim)
        self._apply_materials()
