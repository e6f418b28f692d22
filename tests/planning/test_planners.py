"""Planners on a small CPU RopeReshape instance: each must end closer to the target than doing nothing."""

import gymnasium as gym
import numpy as np
import pytest

import empm_gym  # noqa: F401
from empm_gym.planning import CEMPlanner, GradientPlanner, MPPIPlanner

ENV_ID = "EMPM/RopeReshape-v0"
KW = dict(device="cpu", dx=0.025, particles_per_cell=2, material={"E": 5e3}, task_options={"shapes": ("arc",)})
H = 6
#: a plan must close at least this fraction of the Chamfer distance left by zero actions
MARGIN = 0.05


def _execute(env, state, actions):
    env.unwrapped.set_state(state)
    total = 0.0
    for a in actions:
        _, r, term, trunc, info = env.step(a)
        total += r
    return info["chamfer"], total


@pytest.fixture(scope="module")
def start():
    env = gym.make(ENV_ID, **KW)
    env.reset(seed=0)
    state = env.unwrapped.get_state()
    zero_cd, _ = _execute(env, state, np.zeros((H, 6), np.float32))
    return env, state, zero_cd


@pytest.mark.parametrize("make", [
    lambda: CEMPlanner(ENV_ID, samples=16, iterations=3, env_kwargs=KW, seed=0),
    lambda: MPPIPlanner(ENV_ID, samples=16, iterations=3, env_kwargs=KW, seed=0),
    lambda: GradientPlanner(ENV_ID, iterations=8, lr=0.3, env_kwargs=KW),
], ids=["cem", "mppi", "gradient"])
def test_planner_beats_doing_nothing(start, make):
    env, state, zero_cd = start
    planner = make()
    actions = planner.plan(state, H)
    assert actions.shape == (H, env.action_space.shape[0]) and actions.dtype == np.float32
    assert np.all(np.abs(actions) <= 1.0)
    cd, _ = _execute(env, state, actions)
    assert cd < (1.0 - MARGIN) * zero_cd, f"planned chamfer {cd:.4f} m vs zero-action {zero_cd:.4f} m"


def test_batched_evaluation_matches_sequential_env(start):
    """Every sample of the one batched rollout scores what the environment gives step by step."""
    env, state, _ = start
    planner = MPPIPlanner(ENV_ID, samples=4, iterations=1, env_kwargs=KW)
    acts = np.random.default_rng(1).uniform(-1, 1, (4, 3, 6))
    R = planner.evaluate(state, acts)
    for i in range(4):
        _, total = _execute(env, state, acts[i].astype(np.float32))
        assert R[i] == pytest.approx(total, rel=1e-6, abs=1e-9)


def test_planner_input_validation(start):
    _, state, _ = start
    p = CEMPlanner(ENV_ID, samples=4, iterations=1, env_kwargs=KW)
    with pytest.raises(ValueError, match="horizon"):
        p.plan(state, 0)
    with pytest.raises(ValueError, match="init"):
        p.plan(state, 3, init=np.zeros((2, 6)))
    with pytest.raises(ValueError, match="samples"):
        MPPIPlanner(ENV_ID, samples=1, env_kwargs=KW)
