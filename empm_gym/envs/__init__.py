"""Gymnasium environments (single and natively batched) for rope and dough tasks with geometry targets.

``import empm_gym`` registers the ids (``EMPM/RopeReshape-v0``, ``EMPM/RopeReshape-v1``,
``EMPM/DoughFlatten-v1``, ``EMPM/DoughShape-v1``; ``DoughFlatten-v0`` and ``DoughShape-v0`` are withdrawn,
see :data:`~.registration.WITHDRAWN`); the classes are importable from here without loading Warp kernels.
"""

from .registration import ENV_IDS

__all__ = ["ENV_IDS", "BatchedCore", "EMPMEnv", "EMPMVectorEnv", "RopeReshapeEnv", "RopeReshapeV1Env",
           "DoughFlattenEnv", "DoughFlattenV1Env", "DoughShapeEnv", "DoughShapeV1Env", "RopeReshapeVectorEnv",
           "RopeReshapeV1VectorEnv", "DoughFlattenVectorEnv", "DoughFlattenV1VectorEnv", "DoughShapeVectorEnv",
           "DoughShapeV1VectorEnv"]


def __getattr__(name):
    if name == "BatchedCore":
        from .core import BatchedCore

        return BatchedCore
    if name in __all__:
        from . import env

        return getattr(env, name)
    raise AttributeError(f"module 'empm_gym.envs' has no attribute {name!r}")
