"""Real-to-sim-to-real: plan with a model's material, execute the plan on the "real" object.

The claim the project makes is that identification makes manipulation work: a plan made in a
simulator with the fitted material does on the real object what it did in simulation, and a plan made
with a wrong material does not. :func:`compare_materials` measures exactly that. For each target (one
seed of the environment) and each model material it

1. plans an open-loop action sequence with CEM in the environment made with the model's material,
   each candidate scored after a fixed ``tail`` (for DoughFlatten-v1: lifting the tool, so that the
   score is that of the shape the dough keeps once released, its spring-back included);
2. replays the plan and the tail in the model (the prediction) and in the environment made with the
   real material (the outcome), and records the final Chamfer distance to the target of both.

Open loop on purpose: a closed-loop controller sees the real object and corrects part of the model's
error, which hides the material's effect (and spring-back shows only once the tool has left, when no
correction is possible any more). The "real" object here is a simulation with the ground-truth
material, as in ``examples/real2sim2real.py``; give any material dict or file.
"""

from __future__ import annotations

from typing import Dict, Mapping, Optional, Sequence

import numpy as np
from tqdm.auto import tqdm

from .sampling import CEMPlanner

__all__ = ["lift_tail", "plan_open_loop", "execute_plan", "compare_materials", "wrong_yield_models",
           "run_real2sim2real", "ENV_ID"]

#: The task the real-to-sim-to-real comparison plans: pressing a lump to a thickness, where the spring-back
#: after the tool lifts depends on the yield stress.
ENV_ID = "EMPM/DoughFlatten-v1"


def lift_tail(action_dim: int, up_steps: int = 4, rest_steps: int = 2) -> np.ndarray:
    """Actions [up_steps + rest_steps, action_dim]: every end-effector up at full speed, then still."""
    if action_dim % 3:
        raise ValueError(f"lift_tail: action_dim must be 3 per end-effector (no grip commands), got {action_dim}")
    tail = np.zeros((up_steps + rest_steps, action_dim), np.float32)
    tail[:up_steps, 2::3] = 1.0
    return tail


def _env(env_id: str, material, env_kwargs: Mapping, render: bool = False):
    import gymnasium as gym

    from .. import envs  # noqa: F401  (registers the ids)

    kw = {k: v for k, v in dict(env_kwargs).items() if k not in ("material", "max_episode_steps")}
    return gym.make(env_id, material=material, max_episode_steps=None, render_mode="rgb_array" if render else None,
                    **kw).unwrapped


def execute_plan(env_id: str, material, seed: int, actions: np.ndarray, *, env_kwargs: Optional[Mapping] = None,
                 render: bool = False) -> dict:
    """Run ``actions`` [T, A] open loop from the reset state of ``seed`` in ``env_id`` made with ``material``.

    Returns ``{"chamfer_start", "chamfer", "iou", "frames"}`` (Chamfer in metres; ``frames``: (image, step,
    Chamfer) triples when ``render``, else empty). Termination on success does not stop the sequence: the
    plan is what is executed, to its end.
    """
    env = _env(env_id, material, env_kwargs or {}, render)
    _, info = env.reset(seed=int(seed))
    cd0 = float(info["chamfer"])
    frames = [(env.render(), 0, cd0)] if render else []
    actions = np.asarray(actions, np.float32)
    if actions.ndim != 2 or actions.shape[1] != env.action_space.shape[0]:
        raise ValueError(f"execute_plan: actions must be [T, {env.action_space.shape[0]}], got {actions.shape}")
    for t, a in enumerate(actions):
        _, _, _, _, info = env.step(a)
        if info["diverged"]:
            raise RuntimeError(f"execute_plan: the simulation of {env_id} diverged at step {t} (seed {seed})")
        if render:
            frames.append((env.render(), t + 1, float(info["chamfer"])))
    env.close()
    return {"chamfer_start": cd0, "chamfer": float(info["chamfer"]), "iou": float(info["iou"]), "frames": frames}


def plan_open_loop(env_id: str, material, seed: int, *, steps: int, tail: np.ndarray, samples: int = 32,
                   iterations: int = 4, noise: float = 0.4, init: Optional[np.ndarray] = None,
                   env_kwargs: Optional[Mapping] = None, planner_seed: int = 0) -> np.ndarray:
    """A CEM plan [steps, A] for the target of ``seed``, made in ``env_id`` with ``material`` and scored
    after ``tail`` (see :class:`~empm_gym.planning.CEMPlanner`)."""
    kw = dict(env_kwargs or {})
    env = _env(env_id, material, kw)
    env.reset(seed=int(seed))
    state = env.unwrapped.get_state()
    planner = CEMPlanner(env_id, samples=samples, iterations=iterations, noise=noise,
                         env_kwargs={**kw, "material": material}, seed=planner_seed, tail=tail)
    plan = planner.plan(state, steps, init=init)
    env.close()
    return plan


def compare_materials(env_id: str, real_material, models: Mapping[str, object], seeds: Sequence[int], *,
                      steps: int = 10, tail: Optional[np.ndarray] = None, samples: int = 32, iterations: int = 4,
                      noise: float = 0.4, init: Optional[np.ndarray] = None, env_kwargs: Optional[Mapping] = None,
                      render_seed: Optional[int] = None, progress: bool = True) -> dict:
    """Plan with each of ``models`` ({label: material}), execute on ``real_material``; see the module doc.

    Returns ``{"rows": [...], "summary": {label: {...}}, "frames": {...}}``: one row per (seed, label) with
    the start, predicted and real final Chamfer [m] and whether the real one meets the task's success
    threshold; per label the mean and median real Chamfer, the success count and the mean prediction
    error |real - predicted|; ``frames`` holds rendered real rollouts of ``render_seed`` per label.
    """
    seeds = [int(s) for s in seeds]
    if not seeds or not models:
        raise ValueError(f"compare_materials needs at least one seed and one model, got seeds {seeds} and "
                         f"models {list(models)}")
    kw = dict(env_kwargs or {})
    probe = _env(env_id, real_material, kw)
    A = probe.action_space.shape[0]
    threshold = float(probe.core.task.success_chamfer)
    probe.close()
    tail = lift_tail(A) if tail is None else np.asarray(tail, np.float32)
    rows, frames = [], {}
    jobs = [(s, label) for s in seeds for label in models]
    for s, label in tqdm(jobs, desc=f"real-to-sim-to-real in {env_id}", unit="plan", disable=not progress):
        mat = models[label]
        plan = plan_open_loop(env_id, mat, s, steps=steps, tail=tail, samples=samples, iterations=iterations,
                              noise=noise, init=init, env_kwargs=kw, planner_seed=int(s))
        seq = np.concatenate([plan, tail])
        predicted = execute_plan(env_id, mat, s, seq, env_kwargs=kw)
        real = execute_plan(env_id, real_material, s, seq, env_kwargs=kw, render=(s == render_seed))
        if real["frames"]:
            frames[label] = real["frames"]
        rows.append({"seed": int(s), "model": label, "chamfer_start_m": real["chamfer_start"],
                     "chamfer_predicted_m": predicted["chamfer"], "chamfer_real_m": real["chamfer"],
                     "iou_real": real["iou"], "success": bool(real["chamfer"] < threshold),
                     "plan": seq.tolist()})
    summary: Dict[str, dict] = {}
    for label in models:
        r = [x for x in rows if x["model"] == label]
        real = np.array([x["chamfer_real_m"] for x in r])
        pred = np.array([x["chamfer_predicted_m"] for x in r])
        summary[label] = {"mean_chamfer_real_m": float(real.mean()), "median_chamfer_real_m": float(np.median(real)),
                          "mean_chamfer_predicted_m": float(pred.mean()),
                          "successes": int(sum(x["success"] for x in r)), "episodes": len(r),
                          "mean_prediction_error_m": float(np.abs(real - pred).mean())}
    return {"env": env_id, "success_chamfer_m": threshold, "steps": steps, "tail_steps": len(tail),
            "planner": {"method": "CEM", "samples": samples, "iterations": iterations, "noise": noise},
            "rows": rows, "summary": summary, "frames": frames}


def wrong_yield_models(fitted: Mapping, factors: Sequence[float]) -> Dict[str, dict]:
    """{label: material}: the fitted material and copies with its yield stress times each factor."""
    if fitted.get("yield_stress") is None:
        raise ValueError("real-to-sim-to-real on dough needs a plastic material: the fitted one has no yield stress")
    ys = float(fitted["yield_stress"])
    models = {f"fitted (yield {ys:.0f} Pa)": dict(fitted)}
    for f in factors:
        if not f > 0 or f == 1:
            raise ValueError(f"wrong-material factors must be positive and not 1, got {f!r}")
        models[f"{f:g}x yield ({f * ys:.0f} Pa)"] = {**fitted, "yield_stress": f * ys}
    return models


def run_real2sim2real(out, real_material, fitted_material, *, factors: Sequence[float] = (5.0,),
                      seeds: Sequence[int] = (0, 1, 2), steps: int = 10, samples: int = 32, iterations: int = 4,
                      noise: float = 0.4, env_kwargs: Optional[Mapping] = None, progress: bool = True) -> dict:
    """Plan DoughFlatten-v1 presses with the fitted material and with its yield stress off by ``factors``,
    execute them on ``real_material``, and write ``summary.json``, ``transfer.png`` (bar chart) and
    ``strip.png`` (the real dough under each plan, first seed) into ``out``; returns the summary.

    ``real_material`` and ``fitted_material`` are material dicts or files (the fitted one as ``empm
    identify`` writes it). CEM starts from a slow press (0.6 of full speed down) in every case.
    """
    import json
    from pathlib import Path

    import gymnasium as gym

    from ..envs.core import load_material
    from ..envs.tasks import TASKS
    from ..viz import save_rollout_strip, save_transfer_chart

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    default = TASKS["DoughFlatten-v1"]().material
    real = load_material(real_material, default)
    fitted = load_material(str(fitted_material) if not isinstance(fitted_material, Mapping) else fitted_material,
                           default)
    models = wrong_yield_models(fitted, factors)
    init = np.zeros((steps, 3), np.float32)
    init[:, 2] = -0.6
    result = compare_materials(ENV_ID, real, models, list(seeds), steps=steps, samples=samples,
                               iterations=iterations, noise=noise, init=init, env_kwargs=env_kwargs,
                               render_seed=list(seeds)[0], progress=progress)
    frames = result.pop("frames")
    save_transfer_chart(str(out / "transfer.png"), result)
    kw = {k: v for k, v in dict(env_kwargs or {}).items() if k not in ("material", "max_episode_steps")}
    lo, hi = gym.make(ENV_ID, **kw).unwrapped.view_box()
    save_rollout_strip(str(out / "strip.png"), {f"real dough, planned with {k}": v for k, v in frames.items()},
                       view_lower=lo, view_upper=hi,
                       title=f"{ENV_ID}, target {list(seeds)[0]}: open-loop plans (press, then lift) on the real dough")
    summary = {**result, "real_material": real, "models": models}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
