"""Registers every EMPM environment id with Gymnasium (imported by ``import empm_gym``).

Each id has a single-environment ``entry_point``, a ``vector_entry_point`` that simulates all copies
as batched worlds of one Warp model (the default of ``gym.make_vec``), and ``max_episode_steps``.
A registered id never changes meaning: a change of task bumps the version.
"""

from gymnasium.envs.registration import register, registry

__all__ = ["ENV_IDS", "register_envs"]

#: id -> (task / class prefix, max_episode_steps)
_SPECS = {
    "EMPM/RopeReshape-v0": ("RopeReshape", 100),
    "EMPM/RopeReshape-v1": ("RopeReshapeV1", 100),
    "EMPM/DoughFlatten-v0": ("DoughFlatten", 50),
    "EMPM/DoughFlatten-v1": ("DoughFlattenV1", 30),
    "EMPM/DoughShape-v0": ("DoughShape", 100),
    "EMPM/DoughShape-v1": ("DoughShapeV1", 30),
}
ENV_IDS = tuple(_SPECS)


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
