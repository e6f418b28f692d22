"""CUDA-only checks (skipped on machines without a GPU): CPU/GPU agreement and deterministic mode."""

import numpy as np
import pytest
import warp as wp

from empm_gym.sim import MaterialConfig, SolverConfig, SolverMPM

from .conftest import block_model

cuda = pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device")


def _run(device, config=None, steps=60):
    m = block_model(material=MaterialConfig(E=3e4, nu=0.3, density=1000.0, yield_stress=2e3), worlds=3, device=device)
    s = m.state()
    v = np.zeros((m.particle_count, 3), np.float32)
    v[:, 2] = -0.5
    s.particle_v.assign(v)
    solver = SolverMPM(m, config)
    a, b = s, m.state()
    for _ in range(steps):
        solver.step(a, b, m.control(), 4e-4)
        a, b = b, a
    return a.particle_x.numpy()


@cuda
def test_cuda_matches_cpu():
    np.testing.assert_allclose(_run("cuda:0"), _run("cpu"), atol=2e-5)


@cuda
def test_cuda_deterministic_mode_is_bit_identical():
    cfg = SolverConfig(deterministic=True)
    assert np.array_equal(_run("cuda:0", cfg), _run("cuda:0", cfg))
