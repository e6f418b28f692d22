"""Train SAC (stable-baselines3) on a natively batched EMPM environment.

Same outputs as train_ppo.py: model.zip, learning_curve.png, strip.png, summary.json in ``--out``.

    python examples/train_sac.py --env-id EMPM/DoughFlatten-v1 --num-envs 64 --total-steps 200000 --device cuda:0
"""

from dataclasses import dataclass
from typing import Optional

from stable_baselines3 import SAC

from empm_gym.envs.sb3 import train_and_report
from empm_gym.envs.script_args import parse_args


@dataclass
class Args:
    """SAC on a batched EMPM environment."""

    env_id: str = "EMPM/RopeReshape-v1"
    """Registered environment id."""
    num_envs: int = 16
    """Number of environments (worlds of one batched simulation)."""
    total_steps: int = 50_000
    """Total environment steps of training (the budget)."""
    buffer_size: int = 200_000
    """Replay buffer capacity [transitions]."""
    batch_size: int = 256
    """Minibatch size of each gradient step."""
    learning_starts: int = 1_000
    """Environment steps collected before the first update."""
    gradient_steps: int = 4
    """Gradient steps per vector step (one step of every environment)."""
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
    out: str = "runs/sac"
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
        policy = "MultiInputPolicy" if venv.observation_space.__class__.__name__ == "Dict" else "MlpPolicy"
        return SAC(policy, venv, buffer_size=args.buffer_size, batch_size=args.batch_size,
                   learning_starts=args.learning_starts, gradient_steps=args.gradient_steps, train_freq=1,
                   learning_rate=args.learning_rate, gamma=args.gamma, seed=args.seed, device=args.torch_device,
                   verbose=0)

    summary = train_and_report(args, make_model, algo_name="SAC")
    print(summary)
    return summary


if __name__ == "__main__":
    main()
