"""End to end on an `empm synth` dough recording: synth -> load_recording -> identify the yield stress (a
file of its own so that a parallel test run fits the rope and the dough at the same time).

ground_truth.json is read here only to check the result; identification never reads it.
"""

import numpy as np
import pytest

from .test_synth_recovery import _fit, _recovery_problem, _recovery_recording


@pytest.fixture(scope="module")
def dough_recording(tmp_path_factory):
    return _recovery_recording(tmp_path_factory, "dough")


@pytest.fixture(scope="module")
def dough_problem(tmp_path_factory, dough_recording):
    return _recovery_problem(tmp_path_factory, "dough", dough_recording)


@pytest.fixture(scope="module")
def dough_adam(dough_problem):
    return _fit(dough_problem, "yield_stress", "adam", iters=10)


#: How far the fitted yield stress may lie from the truth. The squeeze determines it loosely: on the demo's
#: recording of the same script `empm identify` gives 2416 Pa with a 95 % interval of [1441, 2916] Pa (true
#: 2000). Here Adam fits 1.27x and CMA-ES 1.25x (2026-11-26). Within 15 % they had fitted while the frame-0 body
#: held a sheet of table under the open grippers (84 particles reaching 9 mm past the block's faces,
#: benchmarks/RESULTS.md, session 27): over the yield stress its loss was flat from 1500 to 2500 Pa. On the body
#: without the sheet (still 5 % over the true volume, 3 mm past the block in y and z) the fitting and the
#: held-out frames alike have their minimum near 2500 Pa.
YIELD_TOLERANCE = 0.3


@pytest.mark.slow
def test_adam_recovers_the_dough_yield_stress_from_a_synthetic_recording(dough_adam):
    ratio, res = dough_adam
    assert abs(ratio - 1.0) < YIELD_TOLERANCE, (ratio, res.param_history)
    assert res.material.plastic and res.material.E == pytest.approx(2.0e4)  # E is not identified: kept


@pytest.mark.slow
def test_cmaes_recovers_the_dough_yield_stress_and_agrees_with_adam(dough_problem, dough_adam):
    ratio, res = _fit(dough_problem, "yield_stress", "cmaes", iters=8, popsize=6)
    assert abs(ratio - 1.0) < YIELD_TOLERANCE, (ratio, res.param_history)
    assert abs(np.log(ratio / dough_adam[0])) < np.log(1.15)


@pytest.mark.slow
def test_real2sim2real_the_fitted_dough_plans_no_worse_and_predicts_the_real_outcome(dough_recording, dough_adam,
                                                                                      tmp_path):
    """examples/real2sim2real.py on a tiny budget, with the yield stress fitted above: the press planned with the
    fitted material ends on the real dough no farther from the target than the one planned with a yield stress
    5x too high, and its model predicts the real outcome far better (the wrong model expects more spring-back).

    Measured (2-core machine, target 0, CEM 8 samples x 2 iterations): fitted 3.17 mm, predicted to 0.03 mm;
    5x 3.34 mm, predicted 4.5 mm.
    """
    import importlib.util
    import json
    import pathlib

    _, res = dough_adam
    mat = res.save(tmp_path / "material.json")
    path = pathlib.Path(__file__).resolve().parents[2] / "examples" / "real2sim2real.py"
    spec = importlib.util.spec_from_file_location("real2sim2real", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "out"
    s = mod.main(["--recording", str(dough_recording), "--material", str(mat), "--seeds", "0", "--samples", "8",
                  "--iterations", "2", "--device", "cpu", "--out", str(out)])
    for f in ("summary.json", "transfer.png", "strip.png"):
        assert (out / f).stat().st_size > 0, f
    assert json.loads((out / "summary.json").read_text())["rows"]
    fitted, wrong = (s["summary"][k] for k in s["models"])
    assert "fitted" in next(iter(s["models"])) and "5x" in list(s["models"])[1]
    assert fitted["mean_chamfer_real_m"] <= wrong["mean_chamfer_real_m"] + 1e-4, s["summary"]
    assert fitted["mean_prediction_error_m"] < 0.5 * wrong["mean_prediction_error_m"], s["summary"]
    assert fitted["mean_chamfer_real_m"] < 0.8 * s["rows"][0]["chamfer_start_m"]  # it pressed
