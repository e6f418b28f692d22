"""The doctor end to end on the CPU, continued (see test_doctor.py, HIDDEN_2: a file of its own so that the CI's
two workers share these runs)."""

import pytest

from .test_doctor import HIDDEN_2, doctor_names_the_hidden_effect


@pytest.mark.slow
@pytest.mark.parametrize("effect,script", HIDDEN_2, ids=[f"{e}-{s}" for e, s in HIDDEN_2])
def test_doctor_names_the_hidden_effect_too(tmp_path, effect, script):
    doctor_names_the_hidden_effect(tmp_path, effect, script)
