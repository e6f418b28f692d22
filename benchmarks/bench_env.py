"""Environment steps per second of ``gym.make_vec`` (all worlds in one batched simulation).

    python benchmarks/bench_env.py --env-id EMPM/RopeReshape-v0 --sizes 1,16,256,1024,4096 --device cuda:0

Prints a table: worlds, particles per world, substeps per env step, vector steps/s, env steps/s and
particle-substeps/s. Actions are random; observations are the default "state" mode.
"""

import argparse
import json
import time

import gymnasium as gym
import numpy as np

import empm_gym  # noqa: F401


def profile(env_id, n, steps, kwargs):
    """Per-kernel GPU time and the host's share over ``steps`` vector steps of ``n`` environments."""
    import warp as wp

    venv = gym.make_vec(env_id, num_envs=n, **kwargs)
    venv.reset(seed=0)
    venv.unwrapped.core._graph = False  # launch kernels one by one, so that each is timed
    acts = np.random.default_rng(0).uniform(-1, 1, (steps + 3, *venv.action_space.shape)).astype(np.float32)
    for t in range(3):
        venv.step(acts[t])
    wp.synchronize()
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET | wp.TIMING_MEMCPY | wp.TIMING_GRAPH)
    t0 = time.perf_counter()
    for t in range(3, steps + 3):
        venv.step(acts[t])
    wp.synchronize()
    wall = time.perf_counter() - t0
    totals = {}
    for r in wp.timing_end():
        totals[r.name] = totals.get(r.name, 0.0) + r.elapsed
    print(f"{env_id}, {n} envs, {steps} vector steps: {wall * 1e3 / steps:.2f} ms wall per vector step; "
          f"GPU time per vector step (ms):")
    for name, ms in sorted(totals.items(), key=lambda kv: -kv[1])[:15]:
        print(f"  {ms / steps:9.3f}  {name}")
    # the same steps as the benchmark runs them (substeps replayed as one graph), the wall time split by phase:
    # each phase ends with a synchronize, so a phase's time is its host work plus the GPU work it waits for
    venv.close()
    venv = gym.make_vec(env_id, num_envs=n, **kwargs)
    venv.reset(seed=0)
    core = venv.unwrapped.core
    phases = {}

    def timed(name, fn):
        def wrapper(*a, **kw):
            wp.synchronize()
            t = time.perf_counter()
            out = fn(*a, **kw)
            wp.synchronize()
            phases[name] = phases.get(name, 0.0) + time.perf_counter() - t
            return out
        return wrapper

    for name in ("controls_from_actions", "_advance", "metrics", "observe", "reset", "check_action"):
        setattr(core, name, timed(name, getattr(core, name)))
    core.solver.check_state = timed("check_state", core.solver.check_state)
    core.control.set = timed("control.set", core.control.set)
    for t in range(3):
        venv.step(acts[t])
    phases.clear()
    wp.synchronize()
    t0 = time.perf_counter()
    for t in range(3, steps + 3):
        venv.step(acts[t])
    wp.synchronize()
    wall = time.perf_counter() - t0
    print(f"with the graph: {wall * 1e3 / steps:.2f} ms wall per vector step, by phase (ms):")
    for name, sec in sorted(phases.items(), key=lambda kv: -kv[1]):
        print(f"  {sec * 1e3 / steps:9.3f}  {name}")
    print(f"  {(wall - sum(phases.values())) * 1e3 / steps:9.3f}  the rest (wrappers, rewards, autoreset)")


def bench(env_id, n, steps, warmup, kwargs):
    venv = gym.make_vec(env_id, num_envs=n, **kwargs)
    venv.reset(seed=0)
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (warmup + steps, *venv.action_space.shape)).astype(np.float32)
    for t in range(warmup):
        venv.step(acts[t])
    t0 = time.perf_counter()
    for t in range(warmup, warmup + steps):
        venv.step(acts[t])
    wall = time.perf_counter() - t0
    core = venv.unwrapped.core
    return {"num_envs": n, "particles_per_world": core.P, "substeps": core.substeps, "vec_steps_per_s": steps / wall,
            "env_steps_per_s": n * steps / wall, "particle_substeps_per_s": n * core.P * core.substeps * steps / wall}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument("--env-id", default="EMPM/RopeReshape-v0", help="registered environment id")
    p.add_argument("--sizes", default="1,4,16,64,256,1024,4096", help="comma-separated numbers of environments")
    p.add_argument("--device", default=None, help='Warp device ("cpu", "cuda:0"); default: Warp\'s default')
    p.add_argument("--steps", type=int, default=20, help="timed vector steps per size")
    p.add_argument("--warmup", type=int, default=3, help="untimed vector steps first (compile, graph capture)")
    p.add_argument("--env-kwargs", default="{}", help="JSON dict of extra environment arguments")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    p.add_argument("--profile", type=int, default=0,
                   help="CUDA: per-kernel GPU time per vector step at this many environments, instead of the table")
    a = p.parse_args(argv)
    kwargs = json.loads(a.env_kwargs)
    if a.device:
        kwargs["device"] = a.device
    if a.profile:
        profile(a.env_id, a.profile, a.steps, kwargs)
        return []
    rows = []
    print(f"{a.env_id} on {a.device or 'default device'}")
    print(f"{'envs':>6} {'P/world':>8} {'substeps':>8} {'vec steps/s':>12} {'env steps/s':>12} {'particle-substeps/s':>20}")
    for n in [int(s) for s in a.sizes.split(",") if s]:
        r = bench(a.env_id, n, a.steps, a.warmup, kwargs)
        rows.append(r)
        print(f"{r['num_envs']:>6} {r['particles_per_world']:>8} {r['substeps']:>8} {r['vec_steps_per_s']:>12.2f} "
              f"{r['env_steps_per_s']:>12.1f} {r['particle_substeps_per_s']:>20.3e}", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
