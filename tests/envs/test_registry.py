"""Tests run over every registered EMPM id (a new id is tested the moment it is registered)."""

import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

from empm_gym.envs import ENV_IDS
from empm_gym.envs.env import EMPMEnv, EMPMVectorEnv



def test_registry_lists_every_empm_id():
    ids = {k for k in gym.registry if k.startswith("EMPM/")}
    assert ids == set(ENV_IDS)
    assert {"EMPM/RopeReshape-v0", "EMPM/RopeReshape-v1", "EMPM/DoughFlatten-v1", "EMPM/DoughShape-v1"} <= ids
    for i in ids:
        spec = gym.spec(i)
        assert spec.max_episode_steps and spec.vector_entry_point


@pytest.mark.parametrize("env_id", ["EMPM/DoughFlatten-v0", "EMPM/DoughShape-v0"])
def test_withdrawn_versions_name_their_successor(env_id):
    """A withdrawn version is not registered: gym.make says it is deprecated and names the version to use."""
    from empm_gym.envs.registration import WITHDRAWN

    assert env_id in WITHDRAWN and env_id not in gym.registry
    with pytest.raises(gym.error.DeprecatedEnv, match=env_id.replace("-v0", "-v1")):
        gym.make(env_id)


def _obs_equal(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    else:
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("obs_mode", ["state", "points"])
def test_gymnasium_check_env(env_id, obs_mode, small_kwargs):
    from gymnasium.utils.env_checker import check_env

    env = gym.make(env_id, obs_mode=obs_mode, **small_kwargs(env_id))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=True)
    msgs = [str(w.message) for w in caught]
    assert not msgs, msgs


def test_sb3_check_env(env_id, small_kwargs):
    from stable_baselines3.common.env_checker import check_env

    env = gym.make(env_id, **small_kwargs(env_id)).unwrapped
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, warn=True)
    msgs = [str(w.message) for w in caught]
    assert not msgs, msgs


def test_depth_observation(env_id, small_kwargs):
    env = gym.make(env_id, obs_mode="depth", **small_kwargs(env_id))
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    d = obs["depth"][..., 0]
    # the object is closer than the table somewhere, and the table is visible somewhere
    assert d.min() < 255 and d.max() == 255


def _rollout(small_kwargs, env_id, seed, steps, actions_seed=1, **extra):
    env = gym.make(env_id, **small_kwargs(env_id), **extra)
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(actions_seed)
    out = [obs]
    rewards = []
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        out.append(obs)
        rewards.append(r)
        if term or trunc:
            obs, _ = env.reset()
            out.append(obs)
    return np.array(out), np.array(rewards), env


def test_seeded_determinism_50_steps(env_id, small_kwargs):
    a, ra, _ = _rollout(small_kwargs, env_id, seed=3, steps=50)
    b, rb, _ = _rollout(small_kwargs, env_id, seed=3, steps=50)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ra, rb)
    c, _, _ = _rollout(small_kwargs, env_id, seed=4, steps=1)
    assert not np.array_equal(a[0], c[0]), "a different seed must draw a different target"


def test_reset_after_stepping_equals_fresh_reset(env_id, small_kwargs):
    env = gym.make(env_id, **small_kwargs(env_id))
    fresh, _ = env.reset(seed=11)
    env.reset(seed=5)
    for _ in range(5):
        env.step(env.action_space.sample())
    again, info = env.reset(seed=11)
    np.testing.assert_array_equal(fresh, again)
    env2 = gym.make(env_id, **small_kwargs(env_id))
    other, _ = env2.reset(seed=11)
    np.testing.assert_array_equal(fresh, other)
    # and the sequel is identical too
    a = np.full(env.action_space.shape, 0.7, np.float32)
    np.testing.assert_array_equal(env.step(a)[0], env2.step(a)[0])


def test_out_of_bound_actions_behave_as_clipped(env_id, small_kwargs):
    e1 = gym.make(env_id, **small_kwargs(env_id))
    e2 = gym.make(env_id, **small_kwargs(env_id))
    e1.reset(seed=2)
    e2.reset(seed=2)
    rng = np.random.default_rng(0)
    for _ in range(5):
        big = rng.uniform(-5, 5, e1.action_space.shape).astype(np.float32)
        o1, r1, *_ = e1.step(big)
        o2, r2, *_ = e2.step(np.clip(big, -1, 1))
        np.testing.assert_array_equal(o1, o2)
        assert r1 == r2


def test_bad_actions_raise_value_error(env_id, small_kwargs):
    env = gym.make(env_id, **small_kwargs(env_id))
    env.reset(seed=0)
    A = env.action_space.shape[0]
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(A + 1, np.float32))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((1, A), np.float32))
    bad = np.zeros(A, np.float32)
    bad[0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        env.step(bad)
    bad[0] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        env.step(bad)
    env.step(np.zeros(A, np.float32))  # still usable


def test_vector_env_equals_single_envs(env_id, small_kwargs):
    N, steps = 3, 8
    venv = gym.make_vec(env_id, num_envs=N, max_episode_steps=5, **small_kwargs(env_id))
    assert isinstance(venv, EMPMVectorEnv) and venv.core.num_envs == N  # one batched simulation
    singles = [gym.make(env_id, max_episode_steps=5, **small_kwargs(env_id)) for _ in range(N)]
    vobs, _ = venv.reset(seed=7)
    sobs = np.stack([e.reset(seed=7 + i)[0] for i, e in enumerate(singles)])
    np.testing.assert_allclose(vobs, sobs, rtol=1e-6, atol=1e-7)
    rng = np.random.default_rng(0)
    saw_reset = False
    for _ in range(steps):
        acts = rng.uniform(-1, 1, venv.action_space.shape).astype(np.float32)
        vobs, vr, vterm, vtrunc, vinfo = venv.step(acts)
        for i, e in enumerate(singles):
            o, r, term, trunc, info = e.step(acts[i])
            assert (term, trunc) == (bool(vterm[i]), bool(vtrunc[i]))
            np.testing.assert_allclose(r, vr[i], rtol=1e-6, atol=1e-9)
            np.testing.assert_allclose(info["chamfer"], vinfo["chamfer"][i], rtol=1e-6)
            if term or trunc:
                saw_reset = True
                np.testing.assert_allclose(vinfo["final_obs"][i], o, rtol=1e-6, atol=1e-7)
                o, _ = e.reset()
            np.testing.assert_allclose(vobs[i], o, rtol=1e-6, atol=1e-7)
    assert saw_reset, "the test must cover the same-step autoreset"


def test_state_observation_is_the_current_particles(env_id, small_kwargs):
    """After a few steps, each world's "state" observation holds, in order: positions of that world's particles
    as they are now (each at zero distance from one of them, none stale), the end-effectors' positions and
    grips, and its target points."""
    N = 2
    venv = gym.make_vec(env_id, num_envs=N, **small_kwargs(env_id))
    venv.reset(seed=3)
    rng = np.random.default_rng(1)
    for _ in range(3):
        obs, *_ = venv.step(rng.uniform(-1, 1, venv.action_space.shape).astype(np.float32))
    core = venv.core
    n, K = core.obs_particles, core.K
    x = core.state.particle_x.numpy().reshape(N, core.P, 3)
    for w in range(N):
        pts = obs[w, : 3 * n].reshape(n, 3)
        d = np.linalg.norm(pts[:, None] - x[w][None], axis=-1)
        assert d.min(1).max() < 1e-6, d.min(1).max()
    ee = core.state.ee_pos.numpy()[: N * K].reshape(N, K * 3)
    np.testing.assert_allclose(obs[:, 3 * n: 3 * n + 3 * K], ee, atol=1e-6)
    np.testing.assert_array_equal(obs[:, 3 * n + 3 * K: 3 * n + 4 * K], core.grip)
    np.testing.assert_array_equal(obs[:, 3 * n + 4 * K:], core._target_obs.reshape(N, -1))


def test_get_set_state_round_trip(env_id, small_kwargs):
    env = gym.make(env_id, **small_kwargs(env_id))
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(3):
        env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
    st = env.unwrapped.get_state()
    acts = rng.uniform(-1, 1, (5, *env.action_space.shape)).astype(np.float32)
    first = [env.step(a) for a in acts]
    env.unwrapped.set_state(st)
    st2 = env.unwrapped.get_state()
    for k in st["sim"]:
        np.testing.assert_array_equal(st["sim"][k], st2["sim"][k])
    np.testing.assert_array_equal(st["target"], st2["target"])
    second = [env.step(a) for a in acts]
    for (o1, r1, t1, u1, i1), (o2, r2, t2, u2, i2) in zip(first, second):
        np.testing.assert_array_equal(o1, o2)
        assert (r1, t1, u1) == (r2, t2, u2) and i1 == i2
    # a state moves between environments, and the next reset continues the same random stream
    other = gym.make(env_id, **small_kwargs(env_id))
    other.reset(seed=99)
    other.unwrapped.set_state(st)
    env.unwrapped.set_state(st)
    np.testing.assert_array_equal(other.step(acts[0])[0], env.step(acts[0])[0])
    np.testing.assert_array_equal(other.reset()[0], env.reset()[0])


def test_forced_divergence_ends_episode_cleanly(env_id, small_kwargs):
    env = gym.make(env_id, **small_kwargs(env_id))
    env.reset(seed=0)
    st = env.unwrapped.get_state()
    st["sim"]["particle_v"][:] = np.nan
    env.unwrapped.set_state(st)
    obs, r, term, trunc, info = env.step(np.zeros(env.action_space.shape, np.float32))
    assert term and info["diverged"] and r == 0.0
    assert env.observation_space.contains(obs)
    obs, _ = env.reset(seed=0)
    obs, r, term, trunc, info = env.step(np.zeros(env.action_space.shape, np.float32))
    assert not info["diverged"] and np.all(np.isfinite(obs))
    # a non-finite deformation gradient in one world of a vector env ends (and resets) only that world
    venv = gym.make_vec(env_id, num_envs=2, **small_kwargs(env_id))
    venv.reset(seed=0)
    st = venv.get_state(1)
    st["sim"]["particle_F"][:5] = np.nan
    venv.set_state(st, 1)
    _, r, term, trunc, info = venv.step(np.zeros(venv.action_space.shape, np.float32))
    assert info["diverged"].tolist() == [False, True] and term[1] and info["_final_obs"][1]
    assert np.all(np.isfinite(venv.core.state.particle_x.numpy()))


def test_reward_terms_sum_and_scale(env_id, small_kwargs):
    env = gym.make(env_id, **small_kwargs(env_id))
    _, info0 = env.reset(seed=4)
    total, last = 0.0, None
    rng = np.random.default_rng(3)
    for _ in range(6):
        _, r, term, trunc, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        assert r == pytest.approx(info["reward_chamfer"] + info["reward_iou"], abs=1e-12)
        assert info["success"] == (info["chamfer"] < env.unwrapped.core.task.success_chamfer)
        total += r
        last = info
    # the documented scale: the return telescopes to 0.5 (1 - cd_T / cd0) + 0.5 (iou_T - iou_0)
    expect = 0.5 * (1 - last["chamfer"] / info0["chamfer"]) + 0.5 * (last["iou"] - info0["iou"])
    assert total == pytest.approx(expect, abs=1e-9)


def test_material_file_and_randomize(env_id, tmp_path, small_kwargs):
    import json

    base = small_kwargs(env_id)
    mat = dict(base.pop("material"), E=6.5e3, friction=0.25, fit={"loss": 0.1})
    path = tmp_path / "material.json"
    path.write_text(json.dumps(mat))
    env = gym.make(env_id, material=str(path), **base)
    env.reset(seed=0)
    core = env.unwrapped.core
    assert core.model.materials[0].E == pytest.approx(6.5e3)
    assert core.model.world_table_friction.numpy()[0] == pytest.approx(0.25)
    venv = gym.make_vec(env_id, num_envs=3, material=str(path), randomize={"E": (0.5, 1.5), "friction": (0.5, 1.0)}, **base)
    venv.reset(seed=0)
    Es = [m.E for m in venv.core.model.materials]
    assert len(set(Es)) == 3 and all(3.25e3 <= E <= 9.75e3 for E in Es)
    dt_nominal = gym.make(env_id, material=str(path), **base).unwrapped.core.dt
    assert venv.core.dt <= dt_nominal, "the substep must be stable for the stiffest material drawn"
    with pytest.raises(ValueError, match="randomize key"):
        gym.make(env_id, randomize={"stiffness": (1, 2)}, **base)
    with pytest.raises(ValueError, match="does not exist"):
        gym.make(env_id, material=str(tmp_path / "missing.json"), **base)
    with pytest.raises(ValueError, match="nu"):
        gym.make(env_id, material={"nu": 0.7}, **base)


def test_render_rgb_array_shows_object_tools_target(env_id, small_kwargs):
    env = gym.make(env_id, render_mode="rgb_array", **small_kwargs(env_id))
    env.reset(seed=0)
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    colours = {tuple(c) for c in img.reshape(-1, 3)[:: 7]}
    target = any(c == (245, 160, 160) for c in colours)
    # a closed (green) or open (orange) tool; boxes are drawn at 60 % opacity, over the background (250 grey)
    # an open box is (244, 190, 118)
    tool = any(abs(c[0] - 40) < 30 and c[1] > 140 and c[2] < 110 for c in colours) or \
        any(c[0] > 200 and 120 < c[1] < 180 and c[2] < 90 for c in colours) or \
        any(c[0] > 235 and 180 <= c[1] <= 200 and 105 <= c[2] <= 130 for c in colours)
    obj = any(c[2] > 110 and c[0] < 100 for c in colours)
    assert target and tool and obj


def test_render_rerun_saves_recording(env_id, tmp_path, small_kwargs):
    path = tmp_path / "run.rrd"
    env = gym.make(env_id, render_mode="rerun", rerun_path=str(path), **small_kwargs(env_id))
    env.reset(seed=0)
    env.step(env.action_space.sample())
    env.close()
    assert path.exists() and path.stat().st_size > 1000


def test_make_with_module_prefix_without_import():
    code = ("import gymnasium as gym; e = gym.make('empm_gym:EMPM/RopeReshape-v0', device='cpu', dx=0.025, "
            "particles_per_cell=2, material={'E': 5e3}); o, _ = e.reset(seed=0); print(o.shape)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]


@pytest.mark.parametrize("obs_mode", ["state", "points", "depth"])
def test_a_partial_autoreset_observes_only_the_reset_worlds(obs_mode, small_kwargs):
    """Worlds that end at different steps: the reset worlds' metrics and observation rows are computed for them
    alone; every row must equal a full recomputation, and the finished worlds' final observations must not be
    overwritten by the reset."""
    env_id = "EMPM/RopeReshape-v0"
    N = 4
    venv = gym.make_vec(env_id, num_envs=N, max_episode_steps=3, obs_mode=obs_mode, **small_kwargs(env_id))
    core = venv.unwrapped.core
    venv.reset(seed=3)
    rng = np.random.default_rng(1)
    step = lambda: venv.step(rng.uniform(-1, 1, venv.action_space.shape).astype(np.float32))
    step()
    core.reset(worlds=[1, 3])  # worlds 1 and 3 now end one step after 0 and 2
    full_cd, full_iou = core.metrics()
    cd, iou = core.metrics([3, 1])
    np.testing.assert_allclose(cd, full_cd[[3, 1]], rtol=1e-6)
    np.testing.assert_allclose(iou, full_iou[[3, 1]])
    for _ in range(2):
        obs, _, term, trunc, info = step()
    done = term | trunc
    assert done.tolist() == [True, False, True, False]
    flat = (lambda o: np.concatenate([np.asarray(v, np.float64).ravel() for v in o.values()])) \
        if isinstance(obs, dict) else (lambda o: np.asarray(o, np.float64).ravel())
    fresh = core.observe()
    for i in range(N):
        np.testing.assert_allclose(flat(_index_obs(obs, i)), flat(_index_obs(fresh, i)), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(core.cd_prev, core.metrics()[0], rtol=1e-6)
    for i in (0, 2):  # the final observation is the state before the reset, not the reset world's new row
        assert not np.allclose(flat(info["final_obs"][i]), flat(_index_obs(obs, i)))


def _index_obs(obs, i):
    return {k: v[i] for k, v in obs.items()} if isinstance(obs, dict) else obs[i]
