"""The planner interface: from an environment state and a horizon, an action sequence.

Every planner is built for one task and one set of environment keyword arguments (those given to
``gym.make``) and answers ``plan(state, horizon)`` with an array [horizon, action_dim] in [-1, 1],
where ``state`` comes from ``env.get_state()`` (or ``env.unwrapped.get_state()``).
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

from ..envs.core import BatchedCore

__all__ = ["Planner", "task_of"]


def task_of(env_or_id) -> str:
    """The task name of an environment, an env id ("EMPM/RopeReshape-v0") or a task name.

    v0 ids map to the bare name ("RopeReshape"); later versions keep theirs ("DoughFlatten-v1"), as
    :data:`empm_gym.envs.tasks.TASKS` names them.
    """
    if isinstance(env_or_id, str):
        name = env_or_id.split("/")[-1]
        return name[: -len("-v0")] if name.endswith("-v0") else name
    core = getattr(getattr(env_or_id, "unwrapped", env_or_id), "core", None)
    if core is None:
        raise ValueError(f"cannot tell the task of {env_or_id!r}: pass an EMPM environment, an id or a task name")
    return core.task.name


class Planner:
    """Base class. Subclasses implement :meth:`plan`.

    Args:
        task: a task name, an env id or an EMPM environment (then its construction kwargs are not known:
            pass ``env_kwargs`` too).
        env_kwargs: the keyword arguments the environment was made with (dx, material, ...), so that the
            planner's internal simulation is the environment's.
        seed: seed of the planner's own random numbers.
    """

    def __init__(self, task, *, env_kwargs: Optional[Mapping[str, Any]] = None, seed: Optional[int] = 0):
        self.task = task_of(task)
        kw = dict(env_kwargs or {})
        for k in ("render_mode", "rerun_path", "render_size", "max_episode_steps"):
            kw.pop(k, None)
        kw["obs_mode"] = "state"
        self.env_kwargs = kw
        self.rng = np.random.default_rng(seed)

    def _core(self, num_envs: int) -> BatchedCore:
        return BatchedCore(self.task, num_envs, **self.env_kwargs)

    def plan(self, state: dict, horizon: int, init: Optional[np.ndarray] = None) -> np.ndarray:
        """An action sequence [horizon, action_dim] in [-1, 1] from ``state``; ``init`` warm-starts it."""
        raise NotImplementedError(f"{type(self).__name__}.plan: abstract, implemented by CEM, MPPI and gradient planners")

    @staticmethod
    def _check_horizon(horizon) -> int:
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
        return int(horizon)

    def _init(self, init, horizon, action_dim) -> np.ndarray:
        if init is None:
            return np.zeros((horizon, action_dim))
        init = np.asarray(init, float)
        if init.shape != (horizon, action_dim):
            raise ValueError(f"init must have shape {(horizon, action_dim)}, got {init.shape}")
        return np.clip(init, -1.0, 1.0)
