"""empm-gym: differentiable MPM (NVIDIA Warp) for deformable objects and Gymnasium environments on top.

Importing the package registers the ``EMPM/...`` environment ids with Gymnasium (when Gymnasium is
installed); nothing heavier is imported here.
"""

try:
    from .envs import registration as _registration  # noqa: F401  (registers the ids)
except ImportError:  # the simulator alone works without gymnasium
    pass
