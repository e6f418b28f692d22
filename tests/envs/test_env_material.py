"""gym.make(id, material=path) simulates every effect in the material file, exactly as the solver does."""

import gymnasium as gym
import numpy as np
import pytest

import empm_gym  # noqa: F401
from empm_gym.sim import MaterialConfig, ModelBuilder, SolverConfig, SolverMPM, TableConfig, write_material

ENV = "EMPM/RopeReshape-v0"
KW = dict(device="cpu", dx=0.025, particles_per_cell=2)


@pytest.fixture
def material():
    return MaterialConfig(E=5.0e3, nu=0.3, density=1000.0, viscosity=4.0,
                          params=dict(friction=0.3, grip_friction=8.0, stiffness_slope_1=0.4, stiffness_slope_2=-0.2,
                                      stiffness_slope_3=0.1, fracture_strain=0.15, fracture_softening=0.03))


def test_env_made_with_material_file_simulates_every_effect(tmp_path, material):
    path = write_material(tmp_path / "material.json", material, fit={"method": "cmaes"})
    env = gym.make(ENV, material=str(path), **KW)
    env.reset(seed=3)
    core = env.unwrapped.core
    m = core.model
    assert m.materials[0] == material
    assert m.world_viscosity.numpy()[0] == pytest.approx(4.0)
    assert m.world_table_friction.numpy()[0] == pytest.approx(0.3)
    assert m.world_grip_friction.numpy()[0] == pytest.approx(8.0)
    np.testing.assert_allclose(m.world_stiffness_slope.numpy()[0], [0.4, -0.2, 0.1], rtol=1e-6)
    assert m.world_fracture_strain.numpy()[0] == pytest.approx(0.15)
    assert m.world_fracture_softening.numpy()[0] == pytest.approx(0.03)

    # the same scene built directly with the solver
    task = core.task
    b = ModelBuilder(task.grid(core.dx), table=TableConfig(height=0.0, friction=0.5))
    x, vol = task.object_particles(core.dx, 2)
    w = b.add_world(material)
    b.add_particles(w, x, vol)
    for cfg, pos in task.end_effectors():
        b.add_end_effector(w, cfg, pos)
    model = b.finalize("cpu", requires_grad=False)
    assert model.world_table_friction.numpy()[0] == pytest.approx(0.3)
    solver = SolverMPM(model, SolverConfig(cfl=0.4, check_every=0))
    # the env's substep is stable for this material (stiffness field and viscosity included)
    assert core.dt <= solver.max_stable_dt(core.max_speed * np.sqrt(3.0)) * (1 + 1e-6)
    a, nxt = model.state(), model.state()
    ctrl = model.control()
    np.testing.assert_array_equal(a.particle_x.numpy(), core.state.particle_x.numpy())

    # lift both ends and pull them apart: stretches the rope, the grip can slip, the rope can tear
    act = np.array([-0.5, 0.0, 1.0, 0.5, 0.0, 1.0], np.float32)
    for _ in range(5):
        vel, grip = core.controls_from_actions(act[None])  # the env's action -> control map (workspace clip)
        env.step(act)
        ctrl.set(velocity=vel, grip=grip)
        for _ in range(core.substeps):
            solver.step(a, nxt, ctrl, core.dt, guards=False)
            a, nxt = nxt, a
    got, want = core.state.particle_x.numpy(), a.particle_x.numpy()
    assert np.all(np.isfinite(want))
    assert np.abs(want - x).max() > 5e-3, "the rope moved"
    np.testing.assert_allclose(got, want, atol=1e-6, rtol=0)

    # a material without the effects moves differently (the effects are really on)
    plain = gym.make(ENV, material={"E": 5.0e3, "friction": 0.3}, **KW)
    plain.reset(seed=3)
    for _ in range(5):
        plain.step(act)
    assert np.abs(plain.unwrapped.core.state.particle_x.numpy() - want).max() > 1e-4


def test_env_state_round_trip_keeps_effects(tmp_path, material):
    path = write_material(tmp_path / "material.json", material)
    env = gym.make(ENV, material=path, **KW)
    env.reset(seed=0)
    st = env.unwrapped.get_state()
    assert MaterialConfig.from_dict(st["material"]) == material
    other = gym.make(ENV, **KW)
    other.reset(seed=1)
    other.unwrapped.set_state(st)
    assert other.unwrapped.core.model.materials[0] == material
    assert other.unwrapped.core.materials[0] == st["material"]


def test_env_material_unknown_keys_raise(tmp_path):
    p = tmp_path / "m.json"
    p.write_text('{"schema": 2, "E": 5e3, "nu": 0.3, "density": 1000, "effects": {"viscosity": {"viscosty": 2}}}')
    with pytest.raises(ValueError, match=f"{p}.*unknown key 'viscosty' in effect 'viscosity'"):
        gym.make(ENV, material=str(p), **KW)
    with pytest.raises(ValueError, match="unknown key 'stiffness'"):
        gym.make(ENV, material={"stiffness": 2.0}, **KW)
