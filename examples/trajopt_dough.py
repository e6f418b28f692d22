"""Gradient trajectory optimisation on DoughShape-v1: Adam on the two plates' action sequence through the
differentiable simulator (empm_gym.autograd.simulate), then the plan is executed in the environment. The
gradient is zero until a plate touches the dough, so a short horizon may leave the plan where it started.

Writes loss.png (Chamfer distance per Adam iteration), strip.png and summary.json into ``--out``.

    python examples/trajopt_dough.py --horizon 20 --iterations 50
"""

import json
import os
import time
from dataclasses import dataclass
from typing import Optional

import gymnasium as gym
import numpy as np

import empm_gym  # noqa: F401  (registers the ids)
from empm_gym.envs.script_args import parse_args
from empm_gym.planning import GradientPlanner
from empm_gym.viz import save_rollout_strip


@dataclass
class Args:
    """Gradient trajectory optimisation on EMPM/DoughShape-v1."""

    horizon: int = 20
    """Length of the optimised action sequence [control steps]."""
    iterations: int = 40
    """Adam iterations (the budget)."""
    lr: float = 0.3
    """Adam learning rate on the pre-tanh action parameters."""
    seed: int = 0
    """Seed of the environment (target)."""
    device: Optional[str] = None
    """Warp device ("cpu", "cuda:0"); None picks Warp's default."""
    env_kwargs: str = "{}"
    """JSON dict of extra environment arguments (dx, material, task_options, ...)."""
    out: str = "runs/trajopt_dough"
    """Output directory."""


def plot_loss(path, history, zero_chamfer_m):
    """The planner's Chamfer distance to the target [mm] per Adam iteration, with zero action's as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    ax.plot(np.arange(len(history)), 1e3 * np.asarray(history, float), "-o", color="k", label="planned sequence")
    ax.axhline(1e3 * zero_chamfer_m, color="C1", ls="--", label=f"zero action ({1e3 * zero_chamfer_m:.2f} mm)")
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_xlabel("Adam iteration")
    ax.set_ylabel("Chamfer distance to the target [mm]")
    ax.set_title("EMPM/DoughShape-v1: gradient trajectory optimisation")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None):
    args = parse_args(Args, argv)
    os.makedirs(args.out, exist_ok=True)
    kwargs = json.loads(args.env_kwargs)
    if args.device:
        kwargs["device"] = args.device
    env = gym.make("EMPM/DoughShape-v1", render_mode="rgb_array", **kwargs)
    _, info0 = env.reset(seed=args.seed)
    state = env.unwrapped.get_state()
    A = env.action_space.shape[0]

    def execute(actions):
        env.unwrapped.set_state(state)
        frames, info = [(env.render(), 0, info0["chamfer"])], dict(info0)
        for t, a in enumerate(actions):
            _, _, term, trunc, info = env.step(a)
            frames.append((env.render(), t + 1, info["chamfer"]))
            if term or trunc:
                break
        return frames, info

    zero_frames, zero = execute(np.zeros((args.horizon, A), np.float32))
    planner = GradientPlanner("DoughShape-v1", iterations=args.iterations, lr=args.lr, env_kwargs=kwargs)
    t0 = time.time()
    actions = planner.plan(state, args.horizon)
    wall = time.time() - t0
    frames, info = execute(actions)
    lo, hi = env.unwrapped.view_box()
    save_rollout_strip(os.path.join(args.out, "strip.png"), {"gradient trajectory": frames, "zero action": zero_frames},
                       view_lower=lo, view_upper=hi,
                       title=f"EMPM/DoughShape-v1: gradient trajectory optimisation ({args.iterations} iterations, "
                             f"horizon {args.horizon}) against zero action")
    plot_loss(os.path.join(args.out, "loss.png"), planner.history, zero["chamfer"])
    summary = {"iterations": len(planner.history), "wall_s": wall, "initial_chamfer": info0["chamfer"],
               "optimised_chamfer": info["chamfer"], "optimised_iou": info["iou"],
               "zero_action_chamfer": zero["chamfer"], "loss_history": planner.history}
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    print({k: v for k, v in summary.items() if k != "loss_history"})
    return summary


if __name__ == "__main__":
    main()
