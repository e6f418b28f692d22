"""Gymnasium environments over :class:`~empm_gym.envs.core.BatchedCore`: single (N = 1) and vector (N worlds).

:class:`EMPMEnv` is a ``gymnasium.Env`` holding a core with one world; :class:`EMPMVectorEnv` is a
``gymnasium.vector.VectorEnv`` holding a core with ``num_envs`` worlds that advance in one Warp
launch per kernel and substep (same-step autoreset). Both share every line of physics, reward and
observation code, so a vector environment equals N single environments given the same seeds and
actions.
"""

from __future__ import annotations

from typing import Any, Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from .core import BatchedCore

__all__ = [
    "EMPMEnv", "EMPMVectorEnv", "RopeReshapeEnv", "RopeReshapeVectorEnv", "RopeReshapeV1Env", "RopeReshapeV1VectorEnv",
    "DoughFlattenEnv",
    "DoughFlattenVectorEnv", "DoughFlattenV1Env", "DoughFlattenV1VectorEnv", "DoughShapeEnv", "DoughShapeVectorEnv",
    "DoughShapeV1Env", "DoughShapeV1VectorEnv",
    "make_spaces",
]


def make_spaces(core: BatchedCore):
    """(single observation space, single action space) of a core."""
    lo, hi = core.observation_bounds()
    K = core.K
    ee_lo = np.concatenate([np.tile(lo, K), np.zeros(K)]).astype(np.float32)
    ee_hi = np.concatenate([np.tile(hi, K), np.ones(K)]).astype(np.float32)
    tgt = spaces.Box(np.tile(lo, (core.obs_target_points, 1)), np.tile(hi, (core.obs_target_points, 1)), dtype=np.float32)
    ee = spaces.Box(ee_lo, ee_hi, dtype=np.float32)
    if core.obs_mode == "state":
        p_lo = np.tile(lo, core.obs_particles)
        p_hi = np.tile(hi, core.obs_particles)
        obs = spaces.Box(np.concatenate([p_lo, ee_lo, tgt.low.reshape(-1)]),
                         np.concatenate([p_hi, ee_hi, tgt.high.reshape(-1)]), dtype=np.float32)
    elif core.obs_mode == "points":
        pts = spaces.Box(np.tile(lo, (core.points_count, 1)), np.tile(hi, (core.points_count, 1)), dtype=np.float32)
        obs = spaces.Dict({"points": pts, "ee": ee, "target": tgt})
    else:
        R = core.depth_resolution
        obs = spaces.Dict({"depth": spaces.Box(0, 255, (R, R, 1), dtype=np.uint8), "ee": ee, "target": tgt})
    act = spaces.Box(-1.0, 1.0, (core.action_dim,), dtype=np.float32)
    return obs, act


def _index(obs, i, copy: bool = False):
    """World i's observation (views into the batch, or copies)."""
    if isinstance(obs, dict):
        return {k: (v[i].copy() if copy else v[i]) for k, v in obs.items()}
    return obs[i].copy() if copy else obs[i]


class EMPMEnv(gym.Env):
    """Base class of the single environments; subclasses set ``TASK`` and document the task."""

    TASK = ""
    metadata = {"render_modes": ["rgb_array", "rerun"], "render_fps": 20}

    def __init__(self, render_mode: Optional[str] = None, *, rerun_path: Optional[str] = None,
                 render_size: int = 256, **kwargs: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.core = BatchedCore(self.TASK, 1, **kwargs)
        self.observation_space, self.action_space = make_spaces(self.core)
        self.render_mode = render_mode
        self.render_size = int(render_size)
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.core.control_dt))}
        self._rerun = None
        if render_mode == "rerun":
            from ..viz.rerun_log import RerunLogger

            self._rerun = RerunLogger(f"empm_gym/{self.TASK}", path=rerun_path)

    # -- gymnasium API ---------------------------------------------------------------------------
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        self.core.reset([0], [seed])
        info = {"chamfer": float(self.core.cd_prev[0]), "iou": float(self.core.iou_prev[0])}
        self._log_rerun(info)
        return _index(self.core.observe(), 0), info

    def step(self, action):
        a = self.core.check_action(action, self.action_space.shape)
        reward, terminated, truncated, info = self.core.step(a[None])
        obs = _index(self.core.observe(), 0)
        info = {k: (bool(v[0]) if v.dtype == bool else float(v[0])) for k, v in info.items()}
        self._log_rerun(info)
        return obs, float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        if self.render_mode == "rgb_array":
            return self.core_render(0)
        return None

    def close(self):
        if self._rerun is not None:
            self._rerun.close()

    # -- extras ----------------------------------------------------------------------------------
    def core_render(self, world: int) -> np.ndarray:
        from ..viz.render import render_scene

        c = self.core
        sl = c.model.world_slice(world)
        x = c.state.particle_x.numpy()[sl]
        ee = c.state.ee_pos.numpy()[world * c.K:(world + 1) * c.K]
        lo, hi = self.view_box()
        return render_scene(x, c.targets[world], ee, c.model.ee_configs[world], c.grip[world], lo, hi,
                            size=self.render_size)

    def view_box(self):
        """(lower, upper) [m] of what ``render()`` shows: its top view spans x and y, its side view x and z
        (see :func:`empm_gym.viz.save_rollout_strip`, which labels the axes with it)."""
        t = self.core.task
        lo = np.array([t.grid_lower[0], t.grid_lower[1], -0.01])
        hi = np.array([t.grid_upper[0], t.grid_upper[1], t.grid_upper[0] - t.grid_lower[0] - 0.01])
        return lo, hi

    def _log_rerun(self, info):
        if self._rerun is None:
            return
        c = self.core
        self._rerun.log(c.state.particle_x.numpy()[c.model.world_slice(0)], c.targets[0],
                        c.state.ee_pos.numpy()[: c.K], c.model.ee_configs[0], c.grip[0],
                        {k: float(v) for k, v in info.items()}, step=int(c.elapsed[0]),
                        ee_rot=c.state.ee_rot.numpy()[: c.K])

    def get_state(self) -> dict:
        """An exact copy of the simulation state and episode bookkeeping (for planners)."""
        return self.core.get_world_states([0])[0]

    def set_state(self, state: dict):
        """Restore a state from :meth:`get_state`; the next step continues exactly from it."""
        self.core.set_world_states([0], [state])


class EMPMVectorEnv(gym.vector.VectorEnv):
    """Base class of the natively batched vector environments (same-step autoreset).

    ``num_envs`` worlds live in one simulation. ``reset(seed=s)`` seeds world i with ``s + i``,
    exactly as ``gym.make`` environments seeded ``s + i`` would be. Finished worlds are reset within
    the same ``step``; their last observation and info are in ``info["final_obs"]`` and
    ``info["final_info"]`` (masks ``info["_final_obs"]``, ``info["_final_info"]``).
    """

    TASK = ""
    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.SAME_STEP, "render_fps": 20}

    def __init__(self, num_envs: int = 1, render_mode: Optional[str] = None, *,
                 max_episode_steps: Optional[int] = None, render_size: int = 256, **kwargs: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.core = BatchedCore(self.TASK, num_envs, max_episode_steps=max_episode_steps, **kwargs)
        self.num_envs = self.core.num_envs
        self.single_observation_space, self.single_action_space = make_spaces(self.core)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.render_mode = render_mode
        self.render_size = int(render_size)

    def reset(self, *, seed=None, options: Optional[dict] = None):
        N = self.num_envs
        super().reset(seed=seed if (seed is None or isinstance(seed, (int, np.integer))) else None)
        if seed is None:
            seeds = [None] * N
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(N)]
        else:
            seeds = list(seed)
            if len(seeds) != N:
                raise ValueError(f"reset: seed must be None, an int or a list of {N} seeds, got {len(seeds)}")
        self.core.reset(seeds=seeds)
        info = {"chamfer": self.core.cd_prev.copy(), "iou": self.core.iou_prev.copy()}
        return self.core.observe(), info

    def step(self, actions):
        a = self.core.check_action(actions, self.action_space.shape)
        reward, terminated, truncated, info = self.core.step(a)
        obs = self.core.observe()
        done = terminated | truncated
        if np.any(done):
            idx = np.nonzero(done)[0]
            final_obs = np.full(self.num_envs, None, dtype=object)
            for i in idx:  # copies: the reset worlds' rows of obs are overwritten below
                final_obs[i] = _index(obs, i, copy=True)
            info["final_obs"], info["_final_obs"] = final_obs, done.copy()
            info["final_info"] = {k: v.copy() for k, v in info.items() if not k.startswith(("final", "_final"))}
            info["_final_info"] = done.copy()
            self.core.reset(worlds=idx.tolist())
            fresh = self.core.observe(idx)  # the other worlds' rows are still current
            if isinstance(obs, dict):
                for k, v in fresh.items():
                    obs[k][idx] = v
            else:
                obs[idx] = fresh
        return obs, reward.astype(np.float64), terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return tuple(EMPMEnv.core_render(self, w) for w in range(self.num_envs))

    def get_state(self, world: int = 0) -> dict:
        return self.core.get_world_states([world])[0]

    def set_state(self, state: dict, world: int = 0):
        self.core.set_world_states([world], [state])


_COMMON_ARGS = """
    | Argument | Default | Meaning |
    |---|---|---|
    | `obs_mode` | `"state"` | `"state"`, `"points"` or `"depth"` (see Observation Space) |
    | `material` | task default | a material file (identification's or the doctor's output, read by `empm_gym.sim.read_material`) or a flat dict of `E` [Pa], `nu`, `density` [kg/m^3] and any effect parameter of `empm_gym.sim.effects` (`yield_stress` [Pa], `viscosity` [Pa s], `friction` (table), `grip_friction`, `stiffness_slope_1..3`, `fracture_strain`, `fracture_softening`); every effect in it is simulated; unknown keys raise |
    | `randomize` | `None` | `{key: (low, high)}` multiplicative ranges of `E`, `nu`, `density`, `yield_stress`, `friction`, drawn per episode |
    | `task_options` | `None` | overrides of the task's fields (e.g. `{"shapes": ("arc",)}`) |
    | `dx` | task default | grid cell size [m] |
    | `particles_per_cell` | 8 | particle sampling density |
    | `control_dt` | 0.05 | control period [s] |
    | `obs_particles`, `points_count`, `obs_target_points` | 64, 256, 64 | points in observations |
    | `chamfer_points` | task's (128; DoughFlatten-v1, DoughShape-v1: 1024) | particle / target points of the reward's Chamfer distance |
    | `depth_resolution` | 64 | side of the depth image [px] |
    | `device` | Warp default | `"cpu"`, `"cuda:0"`, ... |
    | `render_mode` | `None` | `"rgb_array"` (top and side views) or `"rerun"` (streams every step; `rerun_path=` saves an .rrd, else kept in memory) |
"""

_COMMON_REWARD = """
    With `cd` the symmetric Chamfer distance [m] between 128 fixed particles and the target cloud
    (each direction's mean nearest-neighbour distance, averaged), `cd0` its value at reset and `iou` the
    occupancy IoU of all particles against the target on a voxel grid:
    `reward_chamfer = 0.5 * (cd_prev - cd) / cd0`, `reward_iou = 0.5 * (iou - iou_prev)`,
    `reward = reward_chamfer + reward_iou`. Both terms, `chamfer`, `iou`, `success` and `diverged` are in
    `info`. Scale: an episode's return is `0.5 (1 - cd_T / cd0) + 0.5 (iou_T - iou_0)`, dimensionless,
    0 for doing nothing and at most 1, for every task.
"""

_COMMON_OBS = """
    - `"state"` (default): flat float32 Box: 64 subsampled particle positions [m] (x, y, z each), then
      per end-effector its centre [m], then one grip flag per end-effector (1 = closed), then 64 target
      points [m]. Bounded by the simulation grid.
    - `"points"`: Dict `points` (256, 3) particle positions, `ee` (4 K,), `target` (64, 3).
    - `"depth"`: Dict `depth` (64, 64, 1) uint8 top-down orthographic depth of the particles over the
      grid's xy box, `255 (h - z) / h` with camera height h = 0.3 m (255 = table), plus `ee`, `target`.
"""

_COMMON_END = """
    Terminated when `chamfer` falls below the task's success threshold (`info["success"]`) or the
    simulation diverges (`info["diverged"] = True`, reward 0; call `reset`). Truncated by the
    registered `max_episode_steps`.
"""


class RopeReshapeEnv(EMPMEnv):
    __doc__ = f"""Reshape an elastic rope lying on a table with two grippers holding it near its ends.

    ## Description
    A 0.30 m elastic rope (radius 1.2 cm; E = 30 kPa, nu = 0.3, 1000 kg/m^3 unless `material=` says
    otherwise) lies straight along x on a table (friction 0.4). Two closed spherical grippers (radius
    2 cm) hold it 1.4 cm from each end and carry the grid nodes they cover (Dirichlet). At reset a
    target curve of the rope's length is drawn from the family straight / arc / U / S, rotated by up to
    30 degrees and shifted by up to 2 cm, within reach of the grippers. The simulation grid spans
    0.5 x 0.5 m with dx = 1.5 cm (about 360 particles per world).

    ## Action Space
    `Box(-1, 1, (6,), float32)`: the velocity of each gripper (x, y, z), times 0.25 m/s. Values outside
    [-1, 1] are clipped; a wrong shape or a non-finite value raises `ValueError`. Gripper centres are
    kept inside x, y in [-0.19, 0.19] m, z in [0.012, 0.06] m (the velocity is limited at the walls).
    Control period 0.05 s (20 Hz), split into an even number of MPM substeps chosen from the CFL limit
    of the stiffest material `randomize` can draw at the largest gripper speed (58 at the defaults).

    ## Observation Space
    {_COMMON_OBS}
    ## Rewards
    {_COMMON_REWARD}
    Success: `chamfer < 0.012` m.

    ## Episode End
    {_COMMON_END}
    ## Arguments
    {_COMMON_ARGS}
    ## Version History
    - v0: initial release.
    - v1 (:class:`RopeReshapeV1Env`): ordered observations (rope particles from end to end, target points
      along the target curve).
    """
    TASK = "RopeReshape"


class RopeReshapeV1Env(EMPMEnv):
    __doc__ = f"""Reshape an elastic rope with two grippers, observing rope and target in order (RopeReshape-v1).

    ## Description
    v0's rope, grippers, targets, reward and success (see :class:`RopeReshapeEnv`). What changes is the
    "state" and "points" observations' order: the observed rope particles run from the rope's end at
    x < 0 (at rest) to the other, and the observed target points run along the target curve, evenly
    strided in arc length, from the end on the first gripper's side. v0 observes both in random order;
    a policy then has to match two unordered clouds.

    ## Action Space
    `Box(-1, 1, (6,), float32)`: as v0.

    ## Observation Space
    {_COMMON_OBS}
    ## Rewards
    {_COMMON_REWARD}
    The reward's Chamfer uses target points evenly strided along the curve (v0: a random sample).
    Success: `chamfer < 0.012` m.

    ## Episode End
    {_COMMON_END}
    ## Arguments
    {_COMMON_ARGS}
    ## Version History
    - v1: observations in order along the rope and along the target curve.
    """
    TASK = "RopeReshape-v1"


class DoughFlattenEnv(EMPMEnv):
    __doc__ = f"""Flatten an elastoplastic dough lump with a flat pressing tool to a target height and footprint.

    ## Description
    A 6 x 6 x 4 cm dough lump (von Mises: E = 30 kPa, nu = 0.3, 1000 kg/m^3, yield stress 1 kPa;
    table friction 0.6) sits on a table under a flat box tool (10 x 10 x 1.6 cm, friction 0.3). At
    reset a target is drawn: a flat slab of the dough's volume, height in [1.2, 2.2] cm, with a disc or
    square footprint, shifted by up to 1 cm. dx = 1 cm (1152 particles per world).

    ## Action Space
    `Box(-1, 1, (3,), float32)`: the tool's velocity (x, y, z) times 0.1 m/s; clipped, validated as in
    every EMPM environment. The tool centre stays inside x, y in [-0.03, 0.03] m, z in [0, 0.07] m.
    Control period 0.05 s, about 82 substeps at the defaults.

    ## Observation Space
    {_COMMON_OBS}
    ## Rewards
    {_COMMON_REWARD}
    Success: `chamfer < 0.005` m.

    ## Episode End
    {_COMMON_END}
    ## Arguments
    {_COMMON_ARGS}
    ## Version History
    - v0: initial release.
    - v1 (:class:`DoughFlattenV1Env`): a 4 cm thick tool and targets centred on the lump; v0's 1.6 cm tool
      lets pressed dough flow into it at dx = 1 cm, and its shifted targets are out of a press's reach.
    """
    TASK = "DoughFlatten"


class DoughFlattenV1Env(EMPMEnv):
    __doc__ = f"""Press an elastoplastic dough lump to a target thickness with a flat tool (DoughFlatten-v1).

    ## Description
    A 6 x 6 x 4 cm dough lump (von Mises: E = 30 kPa, nu = 0.3, 1000 kg/m^3, yield stress 1 kPa;
    table friction 0.6) sits on a table under a flat box tool (10 x 10 x 4 cm, friction 0.3). At reset
    a target is drawn: a slab of the dough's volume, height in [1.4, 2.4] cm, with a disc or square
    footprint, centred on the lump. The dough springs back when the tool lifts, by an amount set by
    its yield stress: a plan that ends with the tool lifted has to know the material. dx = 1 cm.

    ## Action Space
    `Box(-1, 1, (3,), float32)`: the tool's velocity (x, y, z) times 0.1 m/s. The tool centre stays
    inside x, y in [-0.03, 0.03] m, z in [0.024, 0.09] m (its bottom at least 4 mm above the table).
    Control period 0.05 s.

    ## Observation Space
    {_COMMON_OBS}
    ## Rewards
    {_COMMON_REWARD}
    Success: `chamfer < 0.004` m on 1024 points (two samples of one slab are about 3 mm apart; the lump at
    rest starts 5.5-8 mm from its target).

    ## Episode End
    {_COMMON_END}
    ## Arguments
    {_COMMON_ARGS}
    ## Version History
    - v1: replaces v0's 1.6 cm tool (dough flowed into it) and its shifted targets (out of reach); the
      reward's Chamfer on 1024 points (v0's 128 cannot tell 5 mm); 30 steps.
    """
    TASK = "DoughFlatten-v1"


class DoughShapeEnv(EMPMEnv):
    __doc__ = f"""Shape an elastoplastic dough lump into a goal point cloud with two grippers / pushers.

    ## Description
    The DoughFlatten lump (6 x 6 x 4 cm, von Mises) with two spherical end-effectors (radius 1.5 cm)
    beside it. Open, they push (Coulomb contact, friction 0.5); closed, they carry the dough they
    enclose. At reset a goal point cloud of the dough's volume is drawn: an elongated bar, an L or a
    ring (height 2.5-3 cm), rotated about z and shifted by up to 1 cm.

    ## Action Space
    `Box(-1, 1, (8,), float32)`: the velocities (x, y, z) of both end-effectors times 0.15 m/s, then one
    grip command per end-effector (> 0 closes it). Centres stay inside x, y in [-0.1, 0.1] m, z in
    [0.008, 0.07] m. Control period 0.05 s, about 84 substeps at the defaults.

    ## Observation Space
    {_COMMON_OBS}
    ## Rewards
    {_COMMON_REWARD}
    Success: `chamfer < 0.006` m.

    ## Episode End
    {_COMMON_END}
    ## Arguments
    {_COMMON_ARGS}
    ## Version History
    - v0: initial release.
    - v1 (:class:`DoughShapeV1Env`): two plates squeeze the lump into a bar; v0's spheres cannot shape it
      into its targets.
    """
    TASK = "DoughShape"


class DoughShapeV1Env(EMPMEnv):
    __doc__ = f"""Squeeze an elastoplastic dough lump between two plates into a bar (DoughShape-v1).

    ## Description
    The DoughFlatten lump (6 x 6 x 4 cm, von Mises: E = 30 kPa, nu = 0.3, 1000 kg/m^3, yield stress
    1 kPa; table friction 0.6) stands between two vertical plates (3 cm thick, 10 cm long along y, 6 cm
    tall, friction 0.3), 5 mm from its sides along x. At reset a target is drawn: a bar along y of the
    dough's volume, 3.4-4.0 cm wide, its height the one a squeeze to that width leaves (5.0-4.8 cm), its
    centre line shifted by up to 1 cm in x. How far to squeeze, and how the dough bulges and springs
    back, depend on the material. dx = 1 cm.

    ## Action Space
    `Box(-1, 1, (6,), float32)`: the velocities (x, y, z) of both plates times 0.1 m/s. Plate centres
    stay inside x in [-0.1, 0.1] m, y in [-0.02, 0.02] m, z = 0.025 m (the plates stand on the table; z
    commands have no effect). Control period 0.05 s.

    ## Observation Space
    {_COMMON_OBS}
    ## Rewards
    {_COMMON_REWARD}
    Success: `chamfer < 0.0035` m on 1024 points (a scripted squeeze to the right gap ends 2.8-3.0 mm
    from its target; the lump at rest starts 4.3-6.0 mm away).

    ## Episode End
    {_COMMON_END}
    ## Arguments
    {_COMMON_ARGS}
    ## Version History
    - v1: replaces v0's two spheres and its bar / L / ring targets of any orientation (out of reach of
      spheres, which only push holes into the dough) by two plates and bar targets of a width and
      position a squeeze can reach; the reward's Chamfer on 1024 points (v0: 128, floor about 6 mm);
      30 steps.
    """
    TASK = "DoughShape-v1"


class RopeReshapeVectorEnv(EMPMVectorEnv):
    __doc__ = "RopeReshape with ``num_envs`` worlds in one simulation; see :class:`RopeReshapeEnv`.\n\n" + EMPMVectorEnv.__doc__
    TASK = "RopeReshape"


class DoughFlattenVectorEnv(EMPMVectorEnv):
    __doc__ = "DoughFlatten with ``num_envs`` worlds in one simulation; see :class:`DoughFlattenEnv`.\n\n" + EMPMVectorEnv.__doc__
    TASK = "DoughFlatten"


class DoughFlattenV1VectorEnv(EMPMVectorEnv):
    __doc__ = "DoughFlatten-v1 with ``num_envs`` worlds in one simulation; see :class:`DoughFlattenV1Env`.\n\n" + EMPMVectorEnv.__doc__
    TASK = "DoughFlatten-v1"


class RopeReshapeV1VectorEnv(EMPMVectorEnv):
    __doc__ = "RopeReshape-v1 with ``num_envs`` worlds in one simulation; see :class:`RopeReshapeV1Env`.\n\n" + EMPMVectorEnv.__doc__
    TASK = "RopeReshape-v1"


class DoughShapeV1VectorEnv(EMPMVectorEnv):
    __doc__ = "DoughShape-v1 with ``num_envs`` worlds in one simulation; see :class:`DoughShapeV1Env`.\n\n" + EMPMVectorEnv.__doc__
    TASK = "DoughShape-v1"


class DoughShapeVectorEnv(EMPMVectorEnv):
    __doc__ = "DoughShape with ``num_envs`` worlds in one simulation; see :class:`DoughShapeEnv`.\n\n" + EMPMVectorEnv.__doc__
    TASK = "DoughShape"
