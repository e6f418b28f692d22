"""Train PPO (stable-baselines3) on a natively batched EMPM environment.

All ``num_envs`` copies run as worlds of one simulation (``gym.make_vec``'s vector entry point) behind
an SB3 VecEnv adapter. Writes model.zip, learning_curve.png (against zero- and random-action
baselines), strip.png (a rollout of the trained policy) and summary.json into ``--out``.

    python examples/train_ppo.py --env-id EMPM/RopeReshape-v1 --num-envs 1024 --n-steps 32 --batch-size 4096 \
        --total-steps 5000000 --device cuda:0 --torch-device cuda

On one H100 this reaches 92 % success on RopeReshape-v1 in 3.2 M steps, and 100 % on DoughFlatten-v1 and
DoughShape-v1 in 1.8 M (benchmarks/RESULTS.md).
"""

from dataclasses import dataclass
from typing import Optional

from stable_baselines3 import PPO

from empm_gym.envs.sb3 import train_and_report
from empm_gym.envs.script_args import parse_args


@dataclass
class Args:
    """PPO on a batched EMPM environment."""

    env_id: str = "EMPM/RopeReshape-v1"
    """Registered environment id."""
    num_envs: int = 16
    """Number of environments (worlds of one batched simulation)."""
    total_steps: int = 100_000
    """Total environment steps of training (the budget)."""
    n_steps: int = 64
    """Rollout length per environment between PPO updates."""
    batch_size: int = 256
    """Minibatch size of the PPO update."""
    n_epochs: int = 5
    """Passes over each rollout."""
    learning_rate: float = 3e-4
    """Adam learning rate."""
    gamma: float = 0.99
    """Discount factor."""
    seed: int = 0
    """Seed of the environments and the agent."""
    device: Optional[str] = None
    """Warp device of the simulation ("cpu", "cuda:0"); None picks Warp's default."""
    torch_device: str = "auto"
    """Torch device of the policy."""
    env_kwargs: str = "{}"
    """JSON dict of extra environment arguments (dx, material, randomize, obs_mode, ...)."""
    out: str = "runs/ppo"
    """Output directory."""
    baseline_episodes: int = 16
    """Episodes for each of the zero-action, random-action and trained evaluations (0 skips them)."""
    strip_frames: int = 5
    """Frames in the rollout image strip."""
    max_wall_s: Optional[float] = None
    """Stop training after this many seconds of wall time (the report then says how many steps ran)."""


def main(argv=None):
    args = parse_args(Args, argv)

    def make_model(venv):
        policy = "MultiInputPolicy" if isinstance(venv.observation_space, dict) or \
            venv.observation_space.__class__.__name__ == "Dict" else "MlpPolicy"
        n_steps = max(2, args.n_steps)
        batch = min(args.batch_size, n_steps * venv.num_envs)
        return PPO(policy, venv, n_steps=n_steps, batch_size=batch, n_epochs=args.n_epochs,
                   learning_rate=args.learning_rate, gamma=args.gamma, seed=args.seed, device=args.torch_device,
                   verbose=0)

    summary = train_and_report(args, make_model, algo_name="PPO")
    print(summary)
    return summary


if __name__ == "__main__":
    main()
