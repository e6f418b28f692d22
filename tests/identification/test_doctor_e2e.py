"""The doctor end to end on the CPU, continued (see test_doctor.py, HIDDEN_2: a file of its own so that the CI's
two workers share these runs)."""

import pytest

from .test_doctor import HIDDEN_2, doctor_names_the_hidden_effect


@pytest.mark.slow
@pytest.mark.parametrize("case", HIDDEN_2, ids=["-".join(c[:2]) + ("-" + c[2] if len(c) > 2 else "") for c in HIDDEN_2])
def test_doctor_names_the_hidden_effect_too(tmp_path, case):
    doctor_names_the_hidden_effect(tmp_path, *case)
