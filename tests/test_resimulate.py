"""benchmarks/resimulate.py: re-simulating given materials on a problem the way the doctor scores them."""

import pickle
import re

import pytest

from tests import load_benchmark
from tests.identification import scenes


@pytest.fixture(scope="module")
def resimulate():
    return load_benchmark("resimulate")


def test_the_true_material_scores_best_and_bad_input_is_named(resimulate, tmp_path, capsys):
    """On a rope lifted by its middle, simulated at E = 50 kPa, the true E scores lower than E 4x off on both the
    fitting and the held-out frames; a missing body or a material without E is refused by name."""
    p = scenes.rope_lift(E=5e4, frames=10, lift_frames=6)
    path = tmp_path / "rope.pkl"
    with open(path, "wb") as f:
        pickle.dump({"scene": p.scene, "obs": p.obs, "truth": "none"}, f)
    assert resimulate.main([str(path), "--E-window", "2e4,2e5", "--material", "E=5e4", "--material", "E=2e5"]) == 0
    out = capsys.readouterr().out
    scores = {float(m.group(1)): (float(m.group(2)), float(m.group(3))) for m in
              re.finditer(r"\{'E': ([0-9.e+]+)\}: fitting ([0-9.]+), held out ([0-9.]+)", out)}
    assert set(scores) == {5e4, 2e5}, out
    assert scores[5e4][0] < scores[2e5][0] and scores[5e4][1] < scores[2e5][1], scores
    with pytest.raises(SystemExit, match="no body 'without camera 0'"):
        resimulate.main([str(path), "--E-window", "2e4,2e5", "--material", "E=5e4", "--body", "without camera 0"])
    with pytest.raises(SystemExit):
        resimulate.main([str(path), "--E-window", "2e4,2e5", "--material", "viscosity=3"])
    assert "--material needs E" in capsys.readouterr().err
