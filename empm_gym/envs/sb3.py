"""A stable-baselines3 ``VecEnv`` over an EMPM vector environment (all worlds in one simulation).

SB3 expects its own vector API (``step_async`` / ``step_wait``, a list of info dicts, the last
observation of a finished episode in ``info["terminal_observation"]``, ``"TimeLimit.truncated"``
flags and Monitor-style ``info["episode"]`` statistics); this adapter supplies them from the
same-step-autoreset :class:`~empm_gym.envs.env.EMPMVectorEnv`, without copying any world.
"""

from __future__ import annotations

from typing import Any, List, Optional

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

__all__ = ["SB3VecEnv", "make_sb3_vec_env", "evaluate_policy", "train_and_report"]


class SB3VecEnv(VecEnv):
    """Wrap ``gym.make_vec(id, num_envs=N)`` (an :class:`EMPMVectorEnv`) as an SB3 VecEnv."""

    def __init__(self, venv):
        self.venv = venv.unwrapped if hasattr(venv, "unwrapped") else venv
        super().__init__(self.venv.num_envs, self.venv.single_observation_space, self.venv.single_action_space)
        self._actions = None
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, np.int64)
        self.render_mode = self.venv.render_mode

    def reset(self):
        seeds = self._seeds if any(s is not None for s in self._seeds) else None
        obs, _ = self.venv.reset(seed=seeds)
        self._reset_seeds()
        self._reset_options()
        self._returns[:] = 0
        self._lengths[:] = 0
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, np.float32).reshape(self.num_envs, -1)

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.venv.step(np.clip(self._actions, -1.0, 1.0))
        done = terminated | truncated
        self._returns += reward
        self._lengths += 1
        infos: List[dict] = []
        for i in range(self.num_envs):
            d = {k: (v[i].item() if hasattr(v[i], "item") else v[i]) for k, v in info.items()
                 if isinstance(v, np.ndarray) and v.dtype != object and not k.startswith("_")}
            if done[i]:
                d["terminal_observation"] = info["final_obs"][i]
                d["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                d["is_success"] = bool(info["final_info"]["success"][i])
                d["episode"] = {"r": float(self._returns[i]), "l": int(self._lengths[i])}
                self._returns[i], self._lengths[i] = 0.0, 0
            infos.append(d)
        return obs, reward.astype(np.float32), done, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices=None) -> List[Any]:
        return [getattr(self.venv, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *args, indices=None, **kwargs) -> List[Any]:
        return [getattr(self.venv, method_name)(*args, **kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> List[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self):
        return list(self.venv.render() or [])


def make_sb3_vec_env(env_id: str, num_envs: int, seed: Optional[int] = None, **kwargs) -> SB3VecEnv:
    """``gym.make_vec(env_id, num_envs, **kwargs)`` (batched worlds) wrapped for stable-baselines3."""
    import empm_gym  # noqa: F401  (registers the ids)

    venv = SB3VecEnv(gym.make_vec(env_id, num_envs=num_envs, **kwargs))
    if seed is not None:
        venv.seed(seed)
    return venv


def evaluate_policy(venv: SB3VecEnv, policy, episodes: int, seed: int = 0):
    """(returns, success flags) of ``episodes`` episodes of ``policy(obs) -> actions`` on ``venv`` (a success:
    the task's Chamfer threshold reached during the episode).

    The episodes are the first one of each world, in world order, over as many rounds of ``num_envs`` as
    needed. Taking the first episodes to finish instead would favour the short ones, and episodes end early
    on success: with 1024 rope worlds that counted 100 % where one episode per world gives far less.
    """
    venv.seed(seed)
    obs = venv.reset()
    N = venv.num_envs
    returns: List[float] = []
    success: List[bool] = []
    while len(returns) < episodes:
        r_round, ok_round = np.full(N, np.nan), np.zeros(N, bool)
        while np.isnan(r_round).any():
            obs, _, done, infos = venv.step(policy(obs))
            for i in np.flatnonzero(done & np.isnan(r_round)):
                r_round[i] = infos[i]["episode"]["r"]
                ok_round[i] = bool(infos[i]["is_success"])
        returns += r_round.tolist()
        success += ok_round.tolist()
    return np.asarray(returns[:episodes]), np.asarray(success[:episodes])


def _last_fraction_rate(steps, success, fraction: float = 0.1) -> Optional[float]:
    """Success rate of the training episodes that ended in the last ``fraction`` of the environment steps."""
    if not steps:
        return None
    steps = np.asarray(steps)
    keep = steps >= steps.max() - fraction * steps.max()
    return float(np.asarray(success, float)[keep].mean())


def train_and_report(args, make_model, *, algo_name: str) -> dict:
    """The body shared by examples/train_ppo.py and train_sac.py.

    ``args`` needs: env_id, num_envs, total_steps, seed, device, env_kwargs (JSON str), out,
    baseline_episodes, strip_frames. ``make_model(venv)`` builds the SB3 model. Writes ``model.zip``,
    ``learning_curve.png`` (episode returns and success rates against the zero-action and random-action
    baselines), ``curve.npz`` (every training episode's end step, return and success), ``strip.png`` (a
    rollout of the trained policy) and ``summary.json`` into ``args.out``.
    """
    import json
    import os
    import time

    from stable_baselines3.common.callbacks import BaseCallback

    from ..viz.plots import plot_learning_curve, save_rollout_strip

    max_wall = getattr(args, "max_wall_s", None)
    if max_wall is not None and not max_wall > 0:  # checked before the environments and the model are built
        raise ValueError(f"max_wall_s must be a positive number of seconds, got {max_wall!r}")
    os.makedirs(args.out, exist_ok=True)
    kwargs = json.loads(args.env_kwargs) if isinstance(args.env_kwargs, str) else dict(args.env_kwargs)
    if args.device:
        kwargs["device"] = args.device
    venv = make_sb3_vec_env(args.env_id, args.num_envs, seed=args.seed, **kwargs)

    class Curve(BaseCallback):
        def __init__(self):
            super().__init__()
            self.steps, self.returns, self.success = [], [], []

        def _on_step(self):
            if max_wall is not None and time.time() - t0 > max_wall:
                return False  # SB3 stops learning; the report covers the steps done
            for info in self.locals.get("infos", []):
                if "episode" in info:
                    self.steps.append(self.num_timesteps)
                    self.returns.append(info["episode"]["r"])
                    self.success.append(bool(info["is_success"]))
            return True

    model = make_model(venv)
    from stable_baselines3.common.logger import configure


    # SB3's training statistics go next to the other outputs (its default is a new folder in /tmp per run)
    model.set_logger(configure(os.path.join(args.out, "sb3_log"), ["csv"]))
    curve = Curve()
    t0 = time.time()
    model.learn(total_timesteps=args.total_steps, callback=curve)
    wall = time.time() - t0
    steps_done = int(model.num_timesteps)
    model.save(os.path.join(args.out, "model"))

    A = venv.action_space.shape[0]
    rng = np.random.default_rng(args.seed)
    baselines, success_rates = {}, {}
    if args.baseline_episodes > 0:
        policies = {
            "zero action": lambda o: np.zeros((venv.num_envs, A), np.float32),
            "random action": lambda o: rng.uniform(-1, 1, (venv.num_envs, A)).astype(np.float32),
            "trained (eval)": lambda o: model.predict(o, deterministic=True)[0],
        }
        for name, policy in policies.items():
            r, ok = evaluate_policy(venv, policy, args.baseline_episodes, args.seed)
            baselines[name], success_rates[name] = float(r.mean()), float(ok.mean())
    plot_learning_curve(os.path.join(args.out, "learning_curve.png"), curve.steps, curve.returns,
                        baselines=baselines, successes=curve.success, baseline_success=success_rates,
                        title=f"{algo_name} on {args.env_id} ({args.num_envs} envs)")
    np.savez(os.path.join(args.out, "curve.npz"), steps=np.asarray(curve.steps, np.int64),
             returns=np.asarray(curve.returns), success=np.asarray(curve.success, bool))

    env = gym.make(args.env_id, render_mode="rgb_array", **kwargs)
    obs, info = env.reset(seed=args.seed)
    frames = [(env.render(), 0, info["chamfer"])]
    for t in range(env.spec.max_episode_steps or 100):
        obs, _, term, trunc, info = env.step(model.predict(obs, deterministic=True)[0])
        frames.append((env.render(), t + 1, info["chamfer"]))
        if term or trunc:
            break
    lo, hi = env.unwrapped.view_box()
    save_rollout_strip(os.path.join(args.out, "strip.png"), {f"trained {algo_name} policy": frames}, view_lower=lo,
                       view_upper=hi, max_frames=args.strip_frames,
                       title=f"{algo_name} on {args.env_id}: one episode of the trained policy (seed {args.seed})")
    summary = {"algo": algo_name, "env_id": args.env_id, "num_envs": args.num_envs, "total_steps": args.total_steps,
               "steps_done": steps_done, "stopped_by_wall_time": steps_done < args.total_steps,
               "wall_s": wall, "steps_per_s": steps_done / max(wall, 1e-9), "episodes": len(curve.returns),
               "final_mean_return": float(np.mean(curve.returns[-20:])) if curve.returns else None,
               "final_success_rate": _last_fraction_rate(curve.steps, curve.success),
               "baselines": baselines, "success_rates": success_rates}
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    venv.close()
    return summary
