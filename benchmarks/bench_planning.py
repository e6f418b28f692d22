"""Closed-loop planners against zero and random actions in every registered environment.

    python benchmarks/bench_planning.py --device cuda:0 --seeds 5 --steps 40 --samples 64 --horizon 6
    python benchmarks/bench_planning.py --env-ids EMPM/RopeReshape-v1 --planners mppi --samples 256 --horizon 20 --noise-beta 2

For each environment id and seed (the seed draws the target), one episode per policy: zero action, uniform
random actions, and MPC with each planner of ``--planners`` (re-planned every step, warm-started from the
previous plan shifted by one step). Prints a table per environment: Chamfer to the target at the start and
the end [mm], the end over the start, the success rate (Chamfer below the task's threshold at any step, the
environment's own ``success``), the episode return and the wall time per episode. With ``--jsonl`` every
episode is also written as one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def episode(env, policy, steps: int, seed: int) -> dict:
    """One episode of ``policy(env) -> action`` from ``env.reset(seed=seed)``; its metrics."""
    _, info = env.reset(seed=seed)
    cd0, ret, success = float(info["chamfer"]), 0.0, False
    t0 = time.perf_counter()
    for _ in range(steps):
        _, r, term, trunc, info = env.step(policy(env))
        ret += float(r)
        success |= bool(info.get("success", False))
        if term or trunc:
            break
    return {"chamfer_start_m": cd0, "chamfer_end_m": float(info["chamfer"]), "ratio": float(info["chamfer"]) / cd0,
            "success": success, "return": ret, "wall_s": time.perf_counter() - t0}


def mpc_policy(planner, horizon: int):
    """Re-plan every step from the environment's state, warm-started from the last plan shifted by a step."""
    plan = [None]

    def act(env):
        init = None if plan[0] is None else np.concatenate([plan[0][1:], np.zeros_like(plan[0][-1:])])
        plan[0] = planner.plan(env.unwrapped.get_state(), horizon, init=init)
        return plan[0][0].astype(np.float32)

    def reset():
        plan[0] = None

    act.reset = reset
    return act


def main(argv=None):
    import gymnasium as gym
    from tqdm.auto import tqdm

    import empm_gym  # noqa: F401  (registers the ids)
    from empm_gym.envs import ENV_IDS
    from empm_gym.planning import CEMPlanner, MPPIPlanner

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument("--env-ids", default=",".join(ENV_IDS), help="comma-separated environment ids")
    p.add_argument("--planners", default="mppi,cem", help="comma-separated: mppi, cem")
    p.add_argument("--seeds", type=int, default=3, help="episodes (targets) per policy")
    p.add_argument("--first-seed", type=int, default=0, help="seed of the first episode (seeds first-seed ... first-seed + seeds - 1)")
    p.add_argument("--steps", type=int, default=30, help="control steps per episode")
    p.add_argument("--samples", type=int, default=32, help="planner samples (batched worlds)")
    p.add_argument("--iterations", type=int, default=3, help="planner iterations per control step")
    p.add_argument("--horizon", type=int, default=5, help="planning horizon [control steps]")
    p.add_argument("--noise", type=float, default=0.5, help="std of the action perturbations (action units)")
    p.add_argument("--noise-beta", type=float, default=0.0,
                   help="colour of the perturbations along the horizon: 0 white, 2 brown (smooth sweeps)")
    p.add_argument("--device", default=None, help='Warp device ("cpu", "cuda:0")')
    p.add_argument("--dx", type=float, default=None, help="grid cell [m] (default: the task's)")
    p.add_argument("--ppc", type=float, default=8, help="particles per cell")
    p.add_argument("--task-options", default="{}", help="JSON dict of task overrides")
    p.add_argument("--jsonl", default=None, help="append every episode's metrics to this file")
    args = p.parse_args(argv)

    kwargs = {"particles_per_cell": args.ppc, "task_options": json.loads(args.task_options) or None}
    if args.dx:
        kwargs["dx"] = args.dx
    if args.device:
        kwargs["device"] = args.device
    planners = {"mppi": MPPIPlanner, "cem": CEMPlanner}
    for env_id in args.env_ids.split(","):
        env = gym.make(env_id, **kwargs)
        A = env.action_space.shape[0]
        rng = np.random.default_rng(0)
        policies = {"zero action": lambda e: np.zeros(A, np.float32),
                    "random": lambda e: rng.uniform(-1, 1, A).astype(np.float32)}
        for name in args.planners.split(","):
            planner = planners[name](env_id, samples=args.samples, iterations=args.iterations, noise=args.noise,
                                     env_kwargs=kwargs, seed=0, noise_beta=args.noise_beta)
            policies[f"MPC {name.upper()}"] = mpc_policy(planner, args.horizon)
        rows = {}
        for pname, pol in policies.items():
            res = []
            for seed in tqdm(range(args.first_seed, args.first_seed + args.seeds), desc=f"{env_id}: {pname}", leave=False):
                if hasattr(pol, "reset"):
                    pol.reset()
                r = episode(env, pol, args.steps, seed)
                res.append(r)
                if args.jsonl:
                    with open(args.jsonl, "a") as f:
                        f.write(json.dumps({"env": env_id, "policy": pname, "seed": seed, "noise_beta": args.noise_beta,
                                            "samples": args.samples, "horizon": args.horizon,
                                            "iterations": args.iterations, **r}) + "\n")
            rows[pname] = res
        print(f"\n{env_id}: {args.seeds} targets, {args.steps} steps; MPC with {args.samples} samples, "
              f"{args.iterations} iterations, horizon {args.horizon}, noise {args.noise} (beta {args.noise_beta})")
        print("| policy | Chamfer start [mm] | Chamfer end [mm] | end / start | success | return | s / episode |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for pname, res in rows.items():
            m = lambda k: float(np.mean([r[k] for r in res]))
            print(f"| {pname} | {1e3 * m('chamfer_start_m'):.2f} | {1e3 * m('chamfer_end_m'):.2f} | {m('ratio'):.3f} "
                  f"| {100 * m('success'):.0f} % | {m('return'):.3f} | {m('wall_s'):.1f} |", flush=True)
        env.close()


if __name__ == "__main__":
    main()
