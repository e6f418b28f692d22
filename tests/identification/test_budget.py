"""A fit's time, measured and said before it starts, and the cheaper plan a time budget chooses (issue 11:
identification usable without a GPU)."""

import dataclasses
import json

import numpy as np
import pytest

from empm_gym.cli import main
from empm_gym.identification.budget import SCAN_COST, estimate_s, plan_fit
from empm_gym.sim import sample_box, sample_cylinder

from . import scenes


@pytest.fixture(scope="module")
def rope():
    p = scenes.rope_lift(E=5e4, frames=24, seed=0)
    lo, hi = p.scene.particles.min(0), p.scene.particles.max(0)
    # a scene as load_recording makes it: the grid from the observed motion, not a fixed box
    return dataclasses.replace(p.scene, grid=None, motion_bounds=(lo, hi + [0, 0, 0.1]))


def _thin_body(scene, ppc):
    x, v = sample_cylinder((-0.12, 0, 0.02), (0.12, 0, 0.02), 0.02, 0.02, ppc)
    return dataclasses.replace(scene, particles=x, volumes=v)


def test_estimate_scales_with_frames_iterations_and_probes():
    assert estimate_s(1.0, 21, 10, 0) == pytest.approx(2 * estimate_s(1.0, 11, 10, 0))
    assert estimate_s(1.0, 21, 10, 0) == pytest.approx(2 * estimate_s(1.0, 21, 5, 0))
    assert estimate_s(1.0, 21, 10, 4) > estimate_s(1.0, 21, 10, 1) > estimate_s(1.0, 21, 10, 0)


def test_plan_changes_only_what_the_user_left_open(rope, monkeypatch):
    m = rope.material
    free = dict(particles_per_cell=False, iters=False, lr=False, frames=False)
    plan, sc = plan_fit(rope, m, fit_frames=24, iters=30, particles_per_cell=27, budget_s=None, fixed=free, views=2,
                        rebuild_body=_thin_body)
    assert sc is rope and not plan.steps and plan.estimate_s == plan.default_estimate_s > 0
    # the intervals scan each fitted value across its box: two values cost one scan more than one (one forward
    # frame's measured seconds held fixed, so that the estimates compare)
    import empm_gym.identification.budget as B

    monkeypatch.setattr(B, "frame_seconds", lambda *a: 0.01)
    plan, _ = plan_fit(rope, m, fit_frames=24, iters=30, particles_per_cell=27, budget_s=None, fixed=free, views=2,
                       rebuild_body=_thin_body)
    two, _ = plan_fit(rope, m, fit_frames=24, iters=30, particles_per_cell=27, budget_s=None, fixed=free, views=2,
                      rebuild_body=_thin_body, fitted=2)
    none, _ = plan_fit(rope, m, fit_frames=24, iters=30, particles_per_cell=27, budget_s=None, fixed=free, views=2,
                       rebuild_body=_thin_body, uncertainty=False, fitted=2)
    # the intervals: the fitted body, 2 lattices, 2 views and the scan; one more value, one more scan
    per_body = (plan.estimate_s - none.estimate_s) / (1 + 2 + 2 + SCAN_COST)
    assert per_body > 0 and two.estimate_s - plan.estimate_s == pytest.approx(SCAN_COST * per_body)
    monkeypatch.undo()
    # a 4 cm rope at dx = 2 cm is under 2 cells thick (body_thickness: 1.7): its fill is kept, the rest reduced
    plan, sc = plan_fit(rope, m, fit_frames=24, iters=30, particles_per_cell=27, budget_s=1e-3, fixed=free, views=2,
                        rebuild_body=_thin_body)
    assert (plan.particles_per_cell, plan.iters, plan.lr, plan.resample_bodies) == (27, 8, 0.3, 0)
    assert plan.fit_frames == 16 and plan.motion_margin == 0.0 and sc.motion_margin == 0.0
    assert sc.particles is rope.particles and plan.estimate_s < plan.default_estimate_s
    assert "27 particles per cell kept: the body is 1.7 cells thick" in plan.describe()
    assert np.prod(np.subtract(sc.grid_config().upper, sc.grid_config().lower)) < \
        np.prod(np.subtract(rope.grid_config().upper, rope.grid_config().lower))
    assert "still over the budget" in plan.describe() and "--budget-min 0" in plan.describe()
    # a 12 cm block is 6 cells thick: 8 particles per cell
    x, v = sample_box((-0.06, -0.06, 0.0), (0.06, 0.06, 0.12), 0.02, 27)
    block = dataclasses.replace(rope, particles=x, volumes=v)
    plan, sc = plan_fit(block, m, fit_frames=24, iters=30, particles_per_cell=27, budget_s=1e-3, fixed=free, views=2,
                        rebuild_body=_thin_body)
    assert plan.particles_per_cell == 8.0 and len(sc.particles) == len(_thin_body(rope, 8).particles)
    fixed = dict(particles_per_cell=True, iters=True, lr=True, frames=True)
    plan, sc = plan_fit(block, m, fit_frames=24, iters=30, particles_per_cell=27, budget_s=1e-3, fixed=fixed, views=2,
                        rebuild_body=_thin_body, lr=0.2)
    assert (plan.particles_per_cell, plan.iters, plan.lr, plan.fit_frames) == (27, 30, 0.2, 24)
    assert sc.particles is block.particles


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    from empm_gym.perception.synth import synthesize

    return synthesize(tmp_path_factory.mktemp("rec") / "rope", "rope", frames=12, width=212, height=120,
                      progress=False)


def test_cli_says_the_estimate_and_records_the_plan(rec, tmp_path, capsys):
    out = tmp_path / "m.json"
    assert main(["identify", str(rec), "--out", str(out), "--dx", "0.02", "--iters", "2", "--no-rrd", "--quiet",
                 "--no-uncertainty"]) == 0
    err = capsys.readouterr().err
    assert "empm identify: estimated about" in err and "budget 9.0 min" in err
    fit = json.loads(out.read_text())["fit"]
    assert fit["plan"]["steps"] == [] and fit["particles_per_cell"] == 27
    # a budget the defaults miss: the options not given are reduced, the given one (--iters) kept
    assert main(["identify", str(rec), "--out", str(out), "--dx", "0.02", "--iters", "2", "--no-rrd", "--quiet",
                 "--no-uncertainty", "--budget-min", "0.001"]) == 0
    err = capsys.readouterr().err
    assert "over the budget of 0 s (--budget-min); planned instead:" in err and "particles per cell kept" in err
    assert "12 Adam iterations" not in err
    fit = json.loads(out.read_text())["fit"]
    assert fit["plan"]["particles_per_cell"] == 27 and fit["particles_per_cell"] == 27
    assert fit["plan"]["motion_margin"] == 0.0 and fit["iterations_done"] == 2


def test_cli_refuses_a_negative_budget(rec, tmp_path, capsys):
    out = tmp_path / "m.json"
    assert main(["identify", str(rec), "--out", str(out), "--budget-min", "-1"]) == 2
    assert "--budget-min must be 0 (no budget) or a positive number of minutes, got -1.0" in capsys.readouterr().err
    assert not out.exists()


def test_cli_fits_past_frames_where_no_camera_sees_the_object(rec, tmp_path, capsys):
    """A recording whose object masks are empty in one frame (a hand over the object) is identified on the other
    frames: the command says which frame is not scored and the material file's fit section records it."""
    import shutil

    import imageio.v3 as iio

    hidden = tmp_path / "hidden"
    shutil.copytree(rec, hidden)
    for path in sorted(hidden.glob("mask/*/0/3.png")):
        iio.imwrite(path, np.zeros_like(iio.imread(path)))
    out = tmp_path / "m.json"
    assert main(["identify", str(hidden), "--out", str(out), "--dx", "0.02", "--iters", "2", "--no-rrd", "--quiet",
                 "--no-uncertainty"]) == 0
    assert "frames 3 not scored: no camera sees the object there" in capsys.readouterr().err
    assert json.loads(out.read_text())["fit"]["hidden_frames"] == [3]
