"""Each example runs end to end with a tiny budget (CI) and writes its outputs."""

import importlib.util
import json
import pathlib

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


def test_args_reject_unknown_flag():
    with pytest.raises(SystemExit):
        _load("train_ppo").main(["--total-step", "5", "--out", "/nonexistent"])


def test_mpc_rope(tmp_path):
    s = _load("mpc_rope").main(["--samples", "8", "--iterations", "2", "--horizon", "3", "--steps", "3",
                                "--device", "cpu", "--env-kwargs", ROPE, "--out", str(tmp_path)])
    assert (tmp_path / "strip.png").exists() and s["steps"] == 3
    assert s["chamfer"] < s["zero_action_chamfer"]


def test_trajopt_dough(tmp_path):
    s = _load("trajopt_dough").main(["--horizon", "3", "--iterations", "3", "--grip", "true", "--device", "cpu",
                                     "--env-kwargs", DOUGH, "--out", str(tmp_path)])
    assert (tmp_path / "loss.png").exists() and (tmp_path / "strip.png").exists()
    assert s["iterations"] == 3 and min(s["loss_history"]) <= s["loss_history"][0]


def test_rollout_strip_refuses_an_empty_row(tmp_path):
    from empm_gym.viz import save_rollout_strip

    with pytest.raises(ValueError, match="at least one frame"):
        save_rollout_strip(str(tmp_path / "s.png"), {"MPC": []}, view_lower=(0, 0, 0), view_upper=(1, 1, 1), title="t")
