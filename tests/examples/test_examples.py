"""Each example runs end to end with a tiny budget (CI) and writes its outputs."""

import importlib.util
import json
import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2] / "examples"
ROPE = json.dumps({"dx": 0.025, "particles_per_cell": 2, "material": {"E": 5e3}, "max_episode_steps": 4})
DOUGH = json.dumps({"dx": 0.02, "particles_per_cell": 2, "material": {"E": 5e3, "yield_stress": 300},
                    "max_episode_steps": 4})


def _load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("name,extra", [
    ("train_ppo", ["--n-steps", "8", "--batch-size", "8", "--n-epochs", "1"]),
    ("train_sac", ["--learning-starts", "8", "--batch-size", "8", "--gradient-steps", "1", "--buffer-size", "100"]),
])
def test_train_scripts(tmp_path, name, extra):
    out = tmp_path / name
    s = _load(name).main(["--num-envs", "2", "--total-steps", "32", "--device", "cpu", "--torch-device", "cpu",
                          "--env-kwargs", ROPE, "--baseline-episodes", "2", "--out", str(out), *extra])
    for f in ("model.zip", "learning_curve.png", "strip.png", "summary.json"):
        assert (out / f).stat().st_size > 0, f
    assert s["episodes"] >= 2  # 4-step episodes: the curve has points
    assert set(s["baselines"]) == {"zero action", "random action", "trained (eval)"}
    assert set(s["success_rates"]) == set(s["baselines"])
    curve = np.load(out / "curve.npz")
    assert len(curve["steps"]) == len(curve["returns"]) == len(curve["success"]) == s["episodes"]


@pytest.mark.parametrize("threshold,expect", [(1.0, True), (0.0, False)])
def test_success_flags_follow_the_task_threshold(threshold, expect):
    """A Chamfer threshold of 1 m is met at the first step (every episode a success, ended after one step); one
    of 0 m never is (every episode runs to its time limit and fails)."""
    from empm_gym.envs.sb3 import evaluate_policy, make_sb3_vec_env

    kw = json.loads(ROPE)
    venv = make_sb3_vec_env("EMPM/RopeReshape-v1", 2, seed=0, device="cpu", task_options={"success_chamfer": threshold},
                            **kw)
    returns, ok = evaluate_policy(venv, lambda o: np.zeros((2, venv.action_space.shape[0]), np.float32), 3)
    assert len(returns) == 3 and ok.tolist() == [expect] * 3


def test_training_stops_at_its_wall_time_budget(tmp_path):
    s = _load("train_ppo").main(["--num-envs", "2", "--total-steps", "100000", "--device", "cpu", "--torch-device", "cpu",
                                 "--env-kwargs", ROPE, "--baseline-episodes", "0", "--n-steps", "8", "--batch-size", "8",
                                 "--max-wall-s", "1e-6", "--out", str(tmp_path)])
    assert s["stopped_by_wall_time"] and 0 < s["steps_done"] < 100 and s["total_steps"] == 100000


def test_args_reject_unknown_flag():
    with pytest.raises(SystemExit):
        _load("train_ppo").main(["--total-step", "5", "--out", "/nonexistent"])


def test_mpc_rope(tmp_path):
    s = _load("mpc_rope").main(["--samples", "8", "--iterations", "2", "--horizon", "3", "--steps", "3",
                                "--device", "cpu", "--env-kwargs", ROPE, "--out", str(tmp_path)])
    assert (tmp_path / "strip.png").exists() and s["steps"] == 3
    assert s["chamfer"] < s["zero_action_chamfer"]


def test_trajopt_dough(tmp_path):
    s = _load("trajopt_dough").main(["--horizon", "3", "--iterations", "3", "--device", "cpu",
                                     "--env-kwargs", DOUGH, "--out", str(tmp_path)])
    assert (tmp_path / "loss.png").exists() and (tmp_path / "strip.png").exists()
    assert s["iterations"] == 3 and min(s["loss_history"]) <= s["loss_history"][0]


def test_rollout_strip_refuses_an_empty_row(tmp_path):
    from empm_gym.viz import save_rollout_strip

    with pytest.raises(ValueError, match="at least one frame"):
        save_rollout_strip(str(tmp_path / "s.png"), {"MPC": []}, view_lower=(0, 0, 0), view_upper=(1, 1, 1), title="t")
