"""Small scenes shared by the simulator tests (CPU, a few hundred particles each)."""

import numpy as np
import pytest
import warp as wp

from empm_gym.sim import (EndEffectorConfig, GridConfig, MaterialConfig, ModelBuilder, Rollout, SolverMPM,
                          TableConfig, sample_box)

DEVICE = "cpu"


def block_model(*, material=MaterialConfig(E=2e4, nu=0.3, density=1000.0), worlds=1, dx=0.01,
                lower=(-0.03, -0.03, 0.0), upper=(0.03, 0.03, 0.04), grid_lower=(-0.1, -0.1, -0.04),
                grid_upper=(0.1, 0.1, 0.14), table=TableConfig(friction=0.5), gravity=(0, 0, -9.81),
                end_effectors=(), requires_grad=False, ppc=8, jitter=0.3, materials=None, device=DEVICE):
    """One or more worlds each holding an axis-aligned block of particles."""
    b = ModelBuilder(GridConfig(lower=grid_lower, upper=grid_upper, dx=dx), gravity=gravity, table=table)
    x, vol = sample_box(lower, upper, dx, ppc, seed=1, jitter=jitter)
    for i in range(worlds):
        w = b.add_world(materials[i] if materials else material)
        b.add_particles(w, x, vol)
        for cfg, pos in end_effectors:
            b.add_end_effector(w, cfg, pos)
    return b.finalize(device, requires_grad=requires_grad)


def run(model, steps, dt, *, state=None, control=None, solver=None, every=None):
    """Advance `steps` substeps; returns (final state, list of particle positions every `every` steps)."""
    solver = solver or SolverMPM(model)
    a = state or model.state()
    b = model.state()
    c = control or model.control()
    xs = []
    for t in range(steps):
        solver.step(a, b, c, dt)
        a, b = b, a
        if every and (t + 1) % every == 0:
            xs.append(a.particle_x.numpy().copy())
    return a, xs


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
