"""Small CPU instances of every registered EMPM environment, so 50-step tests stay cheap."""

import pytest

import empm_gym  # noqa: F401
from empm_gym.envs import ENV_IDS

#: coarse grid, few particles, soft material: a few ms per env step on one CPU core
SMALL = {
    "EMPM/RopeReshape-v0": dict(device="cpu", dx=0.025, particles_per_cell=2, material={"E": 5e3}),
    "EMPM/RopeReshape-v1": dict(device="cpu", dx=0.025, particles_per_cell=2, material={"E": 5e3}),
    "EMPM/DoughFlatten-v1": dict(device="cpu", dx=0.02, particles_per_cell=2, material={"E": 5e3, "yield_stress": 300}),
    "EMPM/DoughShape-v1": dict(device="cpu", dx=0.02, particles_per_cell=2, material={"E": 5e3, "yield_stress": 300}),
}


def _small(env_id):
    assert env_id in SMALL, f"add a small configuration of {env_id} to tests/envs/conftest.py"
    return dict(SMALL[env_id])


@pytest.fixture
def small_kwargs():
    """small_kwargs(env_id) -> a fresh dict of constructor kwargs of a small CPU instance."""
    return _small


@pytest.fixture(params=sorted(ENV_IDS))
def env_id(request):
    return request.param
