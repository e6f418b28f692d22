"""Registers every EMPM environment id with Gymnasium (imported by ``import empm_gym``).

Each id has a single-environment ``entry_point``, a ``vector_entry_point`` that simulates all copies
as batched worlds of one Warp model (the default of ``gym.make_vec``), and ``max_episode_steps``.
A registered id never changes meaning: a change of task bumps the version. A version that cannot be
solved is withdrawn (:data:`WITHDRAWN`): ``gym.make`` then raises Gymnasium's ``DeprecatedEnv`` naming the
newer version, as Gymnasium does for its own withdrawn versions; the task classes stay in
:mod:`empm_gym.envs.tasks` for the benchmarks recorded with them.
"""

from gymnasium.envs.registration import register, registry

__all__ = ["ENV_IDS", "WITHDRAWN", "register_envs"]

#: id -> (task / class prefix, max_episode_steps)
_SPECS = {
    "EMPM/RopeReshape-v0": ("RopeReshape", 100),
    "EMPM/RopeReshape-v1": ("RopeReshapeV1", 100),
    "EMPM/DoughFlatten-v1": ("DoughFlattenV1", 30),
    "EMPM/DoughShape-v1": ("DoughShapeV1", 30),
}
ENV_IDS = tuple(_SPECS)

#: withdrawn id -> why (benchmarks/RESULTS.md, "Planners against zero and random actions"): no planner's budget
#: reached their success thresholds, because of the tasks, not the planners
WITHDRAWN = {
    "EMPM/DoughFlatten-v0": "its 1.6 cm tool lets the pressed dough flow into it at dx = 1 cm and its shifted targets "
                            "lie out of a press's reach (MPC ended at 6.3 mm against 5 mm); use EMPM/DoughFlatten-v1",
    "EMPM/DoughShape-v0": "its spheres push holes into the dough, which flows around them (MPC closed 30 % of the "
                          "distance, 0 of 4 targets); use EMPM/DoughShape-v1, whose plates squeeze the lump",
}


def register_envs():
    for env_id, (name, steps) in _SPECS.items():
        if env_id in registry:
            continue
        register(
            id=env_id,
            entry_point=f"empm_gym.envs.env:{name}Env",
            vector_entry_point=f"empm_gym.envs.env:{name}VectorEnv",
            max_episode_steps=steps,
        )


register_envs()
