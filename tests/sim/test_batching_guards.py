"""Batched worlds, determinism, input validation and the solver's guards."""

import numpy as np
import pytest

from empm_gym.sim import (EndEffectorConfig, GridConfig, MaterialConfig, ModelBuilder, SimulationDiverged, SolverMPM,
                          TableConfig, UnstableTimeStep, sample_box, sample_cylinder, sample_mesh, sample_points,
                          sample_sphere)

from .conftest import DEVICE, block_model, run

GRIPPER = (EndEffectorConfig(shape="capsule", radius=0.012, half_height=0.02), (0.0, 0.0, 0.02))
MATERIALS = [
    MaterialConfig(E=2e4, nu=0.3, density=1000.0),
    MaterialConfig(E=6e4, nu=0.2, density=1200.0, yield_stress=2e3),
    MaterialConfig(E=1e4, nu=0.45, density=900.0),
]
VELOCITIES = np.array([[0.1, 0.0, 0.2], [-0.2, 0.1, 0.0], [0.0, 0.0, 0.3]], np.float32)


def _batched_run(worlds, steps=40, dt=4e-4):
    m = block_model(worlds=len(worlds), materials=[MATERIALS[i] for i in worlds], end_effectors=[GRIPPER])
    c = m.control()
    c.set(velocity=VELOCITIES[list(worlds)][:, None, :], grip=np.ones((len(worlds), 1)))
    s, _ = run(m, steps, dt, control=c)
    return m, s


def test_batched_worlds_equal_separate_runs():
    m, s = _batched_run([0, 1, 2])
    x = s.particle_x.numpy()
    for i in range(3):
        _, si = _batched_run([i])
        np.testing.assert_allclose(x[m.world_slice(i)], si.particle_x.numpy(), rtol=0, atol=1e-6)
        np.testing.assert_allclose(s.ee_pos.numpy()[i], si.ee_pos.numpy()[0], atol=1e-7)
    # the worlds really differ (different materials and actions)
    assert np.abs(x[m.world_slice(0)] - x[m.world_slice(1)]).max() > 1e-3


def test_packed_p2g_materials_follow_every_material_change():
    """Model.particle_p2g, which the sorted CUDA P2G reads instead of the per-particle arrays, is (mu V,
    lambda V, eta V, rho V) of each particle after set_materials and after a direct write of the world arrays
    followed by update_particle_materials (the documented contract), heterogeneous stiffness included."""
    m = block_model(worlds=3, materials=MATERIALS)

    def check():
        E, nu = m.particle_E.numpy(), m.particle_nu.numpy()
        vol, rho, eta = m.particle_vol.numpy(), m.particle_density.numpy(), m.particle_viscosity.numpy()
        mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
        np.testing.assert_allclose(m.particle_p2g.numpy(), np.stack([mu * vol, lam * vol, eta * vol, rho * vol], 1),
                                   rtol=1e-5)

    check()
    m.set_materials([MATERIALS[2].replace(viscosity=1.5, stiffness_slope_1=0.4), MATERIALS[0], MATERIALS[1]])
    assert np.ptp(m.particle_E.numpy()[m.world_slice(0)]) > 0  # the stiffness field varies over world 0
    check()
    m.world_E.assign(np.array([5e4, 7e4, 9e4], np.float32))
    m.update_particle_materials()
    check()
    assert np.isclose(m.particle_E.numpy()[m.world_slice(1)].mean(), 7e4, rtol=1e-6)


def test_same_inputs_give_bit_identical_trajectories():
    _, a = _batched_run([0, 1])
    _, b = _batched_run([0, 1])
    for k, v in a.to_numpy().items():
        assert np.array_equal(v, b.to_numpy()[k]), k


def test_state_numpy_round_trip_is_exact():
    m, s = _batched_run([1], steps=10)
    d = s.to_numpy()
    s2 = m.state().from_numpy(d)
    for k, v in s2.to_numpy().items():
        assert np.array_equal(v, d[k])


@pytest.mark.parametrize(
    "kwargs,field",
    [
        (dict(E=0.0), "E"),
        (dict(E=-5.0), "E"),
        (dict(nu=0.5), "nu"),
        (dict(nu=-1.0), "nu"),
        (dict(density=0.0), "density"),
        (dict(yield_stress=-1.0), "yield_stress"),
        (dict(viscosity=-1.0), "viscosity"),
        (dict(E=float("nan")), "E"),
    ],
)
def test_material_config_names_bad_field_and_value(kwargs, field):
    with pytest.raises(ValueError, match=field) as e:
        MaterialConfig(**kwargs)
    assert repr(list(kwargs.values())[0]) in str(e.value) or "finite" in str(e.value)


def test_other_configs_validate():
    with pytest.raises(ValueError, match="friction"):
        TableConfig(friction=-0.1)
    with pytest.raises(ValueError, match="shape"):
        EndEffectorConfig(shape="cone")
    with pytest.raises(ValueError, match="radius"):
        EndEffectorConfig(shape="sphere", radius=0.0)
    with pytest.raises(ValueError, match="dx"):
        GridConfig(dx=-1.0)


def test_time_step_above_cfl_limit_is_refused_with_largest_safe_value():
    m = block_model(material=MaterialConfig(E=1e6, nu=0.3, density=1000.0))
    solver = SolverMPM(m)
    limit = solver.max_stable_dt()
    c = np.sqrt((m.materials[0].lame[1] + 2 * m.materials[0].lame[0]) / 1000.0)
    assert limit == pytest.approx(0.4 * m.dx / c, rel=1e-6)
    with pytest.raises(UnstableTimeStep) as e:
        solver.step(m.state(), m.state(), m.control(), 2 * limit)
    assert e.value.max_dt == pytest.approx(limit)
    assert f"{limit:.3g}" in str(e.value)
    solver.step(m.state(), m.state(), m.control(), limit)  # the limit itself is accepted


def test_fast_end_effector_lowers_the_safe_time_step():
    m = block_model(end_effectors=[GRIPPER])
    solver = SolverMPM(m)
    c = m.control().set(velocity=[[[5.0, 0.0, 0.0]]])
    dt = solver.max_stable_dt()
    with pytest.raises(UnstableTimeStep):
        solver.step(m.state(), m.state(), c, dt)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_control_raises_before_any_kernel(bad):
    m = block_model(end_effectors=[GRIPPER])
    with pytest.raises(ValueError, match="non-finite"):
        m.control().set(velocity=[[[bad, 0.0, 0.0]]])
    with pytest.raises(ValueError, match="shape"):
        m.control().set(velocity=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="grip"):
        m.control().set(grip=[[0.5]])


def test_a_control_sequence_sets_each_step_as_set_does_and_is_checked_alike():
    """Control.sequence uploads T steps' commands once; set_step(t) leaves the control's arrays (and its host
    max_speed) exactly as set() with step t's arrays does; bad steps are refused as set() refuses them."""
    m = block_model(worlds=2, materials=MATERIALS[:2], end_effectors=[GRIPPER])
    rng = np.random.default_rng(3)
    vel, om = rng.normal(size=(4, 2, 1, 3)), rng.normal(size=(4, 2, 1, 3))
    grip = rng.integers(0, 2, size=(4, 2, 1))
    seq_ctrl, one = m.control(), m.control()
    seq = seq_ctrl.sequence(vel, om, grip)
    for t in range(4):
        seq_ctrl.set_step(seq, t)
        one.set(velocity=vel[t], omega=om[t], grip=grip[t])
        for name in ("ee_vel", "ee_omega", "ee_grip"):
            np.testing.assert_array_equal(getattr(seq_ctrl, name).numpy(), getattr(one, name).numpy())
        assert seq_ctrl.max_speed == one.max_speed
    with pytest.raises(IndexError, match="step 4 of a sequence of 4"):
        seq_ctrl.set_step(seq, 4)
    bad = vel.copy()
    bad[2, 1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        m.control().sequence(bad, om, grip)
    with pytest.raises(ValueError, match="grip"):
        m.control().sequence(vel, om, grip * 0.5)


def test_non_finite_state_raises_simulation_diverged_with_step_and_world():
    m = block_model(worlds=2)
    s = m.state()
    v = np.zeros((m.particle_count, 3), np.float32)
    v[m.world_slice(1).start + 3] = np.nan
    s.particle_v.assign(v)
    solver = SolverMPM(m)
    with pytest.raises(SimulationDiverged) as e:
        run(m, 3, 2e-4, state=s, solver=solver)
    assert e.value.worlds == [1]
    assert e.value.step == 1
    assert "world(s) [1]" in str(e.value)


def test_particles_never_leave_the_grid():
    # a block thrown hard at the corner of a tiny grid with no table: clamped, never out of range
    m = block_model(table=None, gravity=(0, 0, 0), grid_lower=(-0.06, -0.06, -0.04), grid_upper=(0.06, 0.06, 0.08),
                    lower=(-0.01, -0.01, 0.0), upper=(0.01, 0.01, 0.02))
    s = m.state()
    s.particle_v.assign(np.tile(np.array([[3.0, 3.0, -3.0]], np.float32), (m.particle_count, 1)))
    out, _ = run(m, 200, 2e-4, state=s)
    x = out.particle_x.numpy()
    lo = np.array(m.grid_origin) + m.dx
    hi = np.array(m.grid_origin) + (np.array(m.grid_res) - 2) * m.dx
    assert np.all(x >= lo - 1e-6) and np.all(x <= hi + 1e-6)
    assert np.all(np.isfinite(x))


def test_particles_outside_grid_are_rejected_at_build_time():
    b = ModelBuilder(GridConfig(lower=(0, 0, 0), upper=(0.2, 0.2, 0.2), dx=0.02))
    w = b.add_world(MaterialConfig())
    with pytest.raises(ValueError, match="outside the usable grid"):
        b.add_particles(w, [[0.5, 0.1, 0.1]], [1e-6])


def test_samplers_fill_the_right_volume():
    dx = 0.01
    x, v = sample_box((0, 0, 0), (0.04, 0.03, 0.02), dx, 8)
    assert v.sum() == pytest.approx(0.04 * 0.03 * 0.02, rel=1e-9)
    assert len(x) == pytest.approx(8 * 4 * 3 * 2, rel=0.15)
    x, v = sample_cylinder((0, 0, 0), (0.3, 0, 0), 0.01, dx, 8)
    assert v.sum() == pytest.approx(np.pi * 0.01**2 * 0.3, rel=1e-9)
    assert np.all(np.hypot(x[:, 1], x[:, 2]) <= 0.01 + 1e-9) and x[:, 0].min() >= 0 and x[:, 0].max() <= 0.3
    x, v = sample_sphere((0, 0, 0), 0.03, dx, 8)
    assert np.all(np.linalg.norm(x, axis=1) <= 0.03 + 1e-9)
    assert len(x) * (dx / 2) ** 3 == pytest.approx(4 / 3 * np.pi * 0.03**3, rel=0.15)


def test_sample_points_fills_interior_of_a_surface_scan():
    # only the surface of a 4 cm cube is given; the sampled body must be solid
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.02, 0.02, (20000, 3))
    axis = rng.integers(0, 3, len(pts))
    pts[np.arange(len(pts)), axis] = np.sign(rng.normal(size=len(pts))) * 0.02
    x, v = sample_points(pts, 0.01, 8)
    centre = np.abs(x).max(1) < 0.01
    assert centre.sum() >= 0.7 * 8 * 8  # the inner 2 cm cube (8 cells of 1 cm) is filled
    assert v.sum() == pytest.approx(0.04**3, rel=0.08)  # surface through the boundary voxel centres


def _box_surface_scan(lo, hi, n=30000, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pts = rng.uniform(lo, hi, (n, 3))
    axis = rng.integers(0, 3, n)
    side = rng.integers(0, 2, n).astype(bool)
    pts[np.arange(n), axis] = np.where(side, hi[axis], lo[axis])
    return pts


def test_an_aligned_lattice_puts_its_outer_rows_half_a_step_inside_the_body():
    """Bars 2.0-2.8 cm wide scanned on their surface: with align_lattice the outer rows across each sit half a
    (stretched) step inside both faces, as each particle stands for the volume around it; the free lattice,
    laid over the padded voxel box, leaves its outer rows most of a step inside (2.5-3.2 mm at 3.3 mm
    steps): a thin body loses a row of material (what biased a 2.4 cm rope's fitted E by up to 8 %)."""
    dx, ppc, h = 0.01, 27, 0.0025
    gaps = {True: [], False: []}
    for w in np.linspace(0.020, 0.028, 5):
        lo, hi = np.array([-0.05, -0.5 * w, 0.0]), np.array([0.05, 0.5 * w, 0.024])
        for align in (True, False):
            x, v = sample_points(_box_surface_scan(lo, hi), dx, ppc, align_lattice=align)
            ys = np.unique(np.round(x[:, 1], 6))
            step = np.diff(ys).mean()
            gaps[align].append((ys[0] - lo[1]) / step)
            if align:  # the box between the outermost voxel centres lies within half a voxel of the faces
                assert ys[0] - lo[1] == pytest.approx(0.5 * step, abs=0.5 * h + 1e-6)
                assert hi[1] - ys[-1] == pytest.approx(0.5 * step, abs=0.5 * h + 1e-6)
            # each face is placed to half a 2.5 mm voxel: up to 10 % per thin axis of a bar this thin
            assert v.sum() == pytest.approx(0.1 * w * 0.024, rel=0.2)
    assert np.mean(gaps[False]) > np.mean(gaps[True]) + 0.2, gaps


def test_an_open_scan_raises_instead_of_becoming_a_sheet_of_particles():
    """A surface seen from one side only (the top of a box, never closed) encloses nothing: whatever the
    lattice, it raises rather than fill a one-row sheet."""
    rng = np.random.default_rng(1)
    top = np.c_[rng.uniform(-0.03, 0.03, (20000, 2)), 0.04 + rng.normal(0, 3e-4, 20000)]
    for align in (True, False):
        with pytest.raises(ValueError, match="open surface"):
            sample_points(top, 0.01, 8, align_lattice=align)


def test_sample_mesh_fills_a_closed_tetrahedron():
    verts = np.array([[0, 0, 0], [0.06, 0, 0], [0, 0.06, 0], [0, 0, 0.06]], np.float32)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    x, v = sample_mesh(verts, faces, 0.005, 8)
    assert np.all(x.sum(1) <= 0.06 + 1e-6) and np.all(x >= -1e-6)
    assert v.sum() == pytest.approx(0.06**3 / 6, rel=0.2)


def test_in_place_grid_clearing_equals_explicit_clearing():
    # the solver's own grid is cleared inside the grid kernel; an explicit scratch grid is cleared by
    # memsets: both must give the same trajectory
    from empm_gym.sim import GridScratch

    m = block_model(end_effectors=[GRIPPER], material=MATERIALS[1])
    c = m.control().set(velocity=[[[0.1, 0.0, 0.2]]], grip=[[1]])
    fused, _ = run(m, 30, 4e-4, control=c)
    solver, scratch = SolverMPM(m), GridScratch(m)
    a, b = m.state(), m.state()
    for _ in range(30):
        solver.step(a, b, c, 4e-4, scratch)
        a, b = b, a
    assert np.array_equal(fused.particle_x.numpy(), a.particle_x.numpy())
    assert not scratch.clean and solver.scratch.clean



def test_blocks_of_states_and_grids_step_like_separate_ones_and_zero_their_gradients_together():
    # a rollout's states and grids are rows of one array per field: stepping through them must give the
    # trajectory that separate arrays give (no row overlaps another), and zero_grad must clear every row
    from empm_gym.sim import GridScratch
    from empm_gym.sim.model import StateBlock
    from empm_gym.sim.solver import GridScratchBlock

    m = block_model(end_effectors=[GRIPPER], material=MATERIALS[1])
    c = m.control().set(velocity=[[[0.1, 0.0, 0.2]]], grip=[[1]])
    steps = 6
    states, grids = StateBlock(m, steps + 1, requires_grad=True), GridScratchBlock(m, steps, requires_grad=True)
    solver, scratch = SolverMPM(m), GridScratch(m)
    states.states[0].assign(m.state())
    for t in range(steps):  # leaves every grid holding a step's values
        solver.step(states.states[t], states.states[t + 1], c, 4e-4, grids.grids[t])
    grids.clear()  # the second pass's steps skip their own clearing
    a, b = m.state(), m.state()
    for t in range(steps):
        solver.step(states.states[t], states.states[t + 1], c, 4e-4, grids.grids[t])
        solver.step(a, b, c, 4e-4, scratch)
        a, b = b, a
        assert np.array_equal(states.states[t + 1].particle_x.numpy(), a.particle_x.numpy())
        assert np.array_equal(grids.grids[t].v.numpy(), scratch.v.numpy())
    # the first state still holds the initial one: no later step wrote into it
    assert np.array_equal(states.states[0].particle_x.numpy(), m.state().particle_x.numpy())
    for s in states.states:
        s.particle_F.grad.fill_(1.0)
    grids.grids[-1].v.grad.fill_(1.0)
    states.zero_grad()
    grids.zero_grad()
    assert all(not s.particle_F.grad.numpy().any() for s in states.states)
    assert not any(g.v.grad.numpy().any() for g in grids.grids)
    with pytest.raises(ValueError, match="count"):
        StateBlock(m, 0)

def test_solver_config_rejects_bad_values():
    from empm_gym.sim import SolverConfig

    for kw, what in (({"cfl": 0.0}, "cfl"), ({"cfl": 1.5}, "cfl"), ({"check_every": -1}, "check_every"),
                     ({"sort_every": -2}, "sort_every")):
        with pytest.raises(ValueError, match=what):
            SolverConfig(**kw)
    assert SolverConfig(sort_every=0).sort_every == 0  # 0 is allowed: never sort
