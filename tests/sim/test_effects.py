"""The effects catalogue in the simulator: registry, behaviour against statics / linear elasticity, and
tape gradients of every new effect parameter against central finite differences."""

import numpy as np
import pytest
import warp as wp
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from empm_gym.sim import kernels as K
from empm_gym.sim import (EndEffectorConfig, GridConfig, MaterialConfig, ModelBuilder, SolverMPM, sample_box)
from empm_gym.sim.effects import EFFECTS, PARAMETERS
from empm_gym.sim.model import principal_coords

from .conftest import block_model, run
from .test_gradients import _check, _loss_and_grads, _weights

DX = 0.01


# ------------------------------------------------------------------------------------------ registry
def test_registry_parameters_reach_the_model():
    """Every parameter of every effect has a per-world array, and a material with it sets that array."""
    values = {"yield_stress": 1500.0, "viscosity": 3.0, "friction": 0.2, "grip_friction": 0.7,
              "stiffness_slope_1": 0.4, "stiffness_slope_2": -0.3, "stiffness_slope_3": 0.1,
              "fracture_strain": 0.25, "fracture_softening": 0.08}
    assert set(values) == set(PARAMETERS), "a registry parameter is missing from this test"
    mat = MaterialConfig(E=2e4).replace(**values)
    assert set(mat.effects()) == set(EFFECTS)
    model = block_model(material=mat)
    for name, p in PARAMETERS.items():
        arr = getattr(model, p.array).numpy()
        got = arr[0] if p.component is None else arr[0, p.component]
        assert got == pytest.approx(values[name], rel=1e-6), name
    # and the host copy made back from the device arrays is the same material
    model.sync_materials_from_device()
    for name in values:
        assert model.materials[0].get(name) == pytest.approx(values[name], rel=1e-6), name


def test_unknown_or_bad_effect_parameter_raises():
    with pytest.raises(ValueError, match="grip_frixion"):
        MaterialConfig(params={"grip_frixion": 1.0})
    with pytest.raises(ValueError, match="fracture_strain"):
        MaterialConfig(params={"fracture_strain": -0.1})
    with pytest.raises(ValueError, match="stiffness_slope_1"):
        MaterialConfig(params={"stiffness_slope_1": float("nan")})


def test_principal_coordinates_follow_the_body():
    rng = np.random.default_rng(0)
    x = rng.uniform([-0.1, -0.02, 0.0], [0.1, 0.02, 0.03], (2000, 3))
    u = principal_coords(x)
    assert np.allclose(np.abs(u).max(0), 1.0)
    assert np.corrcoef(u[:, 0], x[:, 0])[0, 1] > 0.99  # axis 1 = the long x axis, pointing along +x
    assert np.corrcoef(u[:, 1], x[:, 1])[0, 1] > 0.99
    # similar extents leave the axes to sampling noise: a lump takes the world axes, a square slab's pair
    # takes x then y, whatever the sample
    for seed in range(5):
        r = np.random.default_rng(seed)
        for size in ((0.05, 0.05, 0.045), (0.1, 0.1, 0.02)):
            x = r.uniform([-size[0] / 2, -size[1] / 2, 0.0], [size[0] / 2, size[1] / 2, size[2]], (900, 3))
            u = principal_coords(x)
            for i in range(3):
                assert np.corrcoef(u[:, i], x[:, i])[0, 1] > 0.99, (seed, size, i)


# ------------------------------------------------------------------------------------------ gripper slip
_GRIP = EndEffectorConfig(shape="box", half_extents=(0.03, 0.03, 0.0075))
_GRIP_POS = (0.0, 0.0, 0.04 - 0.0075 + 0.001)


def _hanging_block(grip_friction=None, requires_grad=False):
    """A 4 cm elastic cube held at its top by one closed box gripper, no table, gravity on."""
    mat = MaterialConfig(E=4e4, nu=0.3, density=1000.0,
                         params=None if grip_friction is None else {"grip_friction": grip_friction})
    return block_model(material=mat, lower=(-0.02, -0.02, 0.0), upper=(0.02, 0.02, 0.04), table=None,
                       end_effectors=[(_GRIP, _GRIP_POS)], grid_lower=(-0.08, -0.08, -0.2),
                       grid_upper=(0.08, 0.08, 0.08), requires_grad=requires_grad)


def _grid_mass_inside_box(model, centre, half):
    """Mass [kg] that P2G puts on the grid nodes strictly inside a box (quadratic B-splines, as the solver)."""
    x = model.state().particle_x.numpy().astype(np.float64)
    mass = model.particle_mass().astype(np.float64)
    o = np.asarray(model.grid_origin)
    xl = (x - o) / model.dx
    base = np.floor(xl - 0.5).astype(int)
    fx = xl - base
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    total = 0.0
    for i in range(3):
        for j in range(3):
            for k in range(3):
                node = o + (base + [i, j, k]) * model.dx
                inside = np.all(np.abs(node - centre) < half, axis=1)
                total += float((w[i][:, 0] * w[j][:, 1] * w[k][:, 2] * mass * inside).sum())
    return total, float(mass.sum())


def _drop_after(model, seconds=0.25):
    solver = SolverMPM(model)
    dt = solver.max_stable_dt()
    ctrl = model.control().set(grip=[[1]])
    state, _ = run(model, int(seconds / dt), dt, control=ctrl, solver=solver)
    return float((state.particle_x.numpy()[:, 2] - model.state().particle_x.numpy()[:, 2]).mean()), state


def test_gripper_slip_threshold_matches_statics():
    """Held while grip_friction * (grasped grid mass) >= the block's mass: slides out 15 % below that, stays
    15 % above it (the per-node friction limit is grip_friction * 9.81 m/s^2 * dt)."""
    inside, total = _grid_mass_inside_box(_hanging_block(), np.array(_GRIP_POS), np.array(_GRIP.half_extents))
    mu_crit = total / inside
    assert 1.5 < mu_crit < 5.0, f"the scene should grasp part of the block (mu_crit {mu_crit:.3g})"
    held, _ = _drop_after(_hanging_block(1.15 * mu_crit))
    slid, _ = _drop_after(_hanging_block(0.85 * mu_crit))
    print(f"mu_crit {mu_crit:.3f}: mean drop {held * 1e3:.2f} mm at 1.15x, {slid * 1e3:.2f} mm at 0.85x")
    assert held > -1.0e-3, f"block should stay in a gripper 15 % above the statics threshold, dropped {held:.4f} m"
    assert slid < -5.0e-3, f"block should slide out 15 % below the statics threshold, dropped only {slid:.4f} m"


def test_gripper_slip_with_huge_coefficient_is_the_rigid_grip():
    rigid, s_rigid = _drop_after(_hanging_block(None), 0.1)
    huge, s_huge = _drop_after(_hanging_block(1e6), 0.1)
    np.testing.assert_array_equal(s_rigid.particle_x.numpy(), s_huge.particle_x.numpy())


# ------------------------------------------------------------------------------------------ bars
_L, _H = 0.12, 0.02
_PAD = EndEffectorConfig(shape="box", half_extents=(0.0125, 0.02, 0.02))


def _bar(material, *, notch=False, requires_grad=False):
    """A 12 x 2 x 2 cm bar along x held at both ends by closed box pads (no gravity, no table); ``notch``
    removes the upper half of the section over the middle 1.2 cm."""
    b = ModelBuilder(GridConfig(lower=(-0.16, -0.05, -0.05), upper=(0.16, 0.05, 0.05), dx=DX), gravity=(0, 0, 0),
                     table=None)
    w = b.add_world(material)
    x, vol = sample_box((-_L / 2, -_H / 2, -_H / 2), (_L / 2, _H / 2, _H / 2), DX, 8, seed=1, jitter=0.0)
    if notch:
        keep = ~((np.abs(x[:, 0]) < 0.006) & (x[:, 2] > 0.0))
        x = x[keep]
        vol = vol[keep] if np.ndim(vol) else vol
    b.add_particles(w, x, vol)
    b.add_end_effector(w, _PAD, (-_L / 2 + 0.0075, 0, 0))
    b.add_end_effector(w, _PAD, (_L / 2 - 0.0075, 0, 0))
    return b.finalize("cpu", requires_grad=requires_grad)


_FREE = _L - 2 * 0.02  # length between the pads [m]


def _pull(model, nominal_strain, *, speed=0.02, hold=0.1, every=None):
    """Pull the pads apart by nominal_strain of the free length at `speed` m/s each, then hold still."""
    solver = SolverMPM(model)
    dt = solver.max_stable_dt(speed)
    ctrl = model.control().set(velocity=[[[-speed, 0, 0], [speed, 0, 0]]], grip=[[1, 1]])
    state, _ = run(model, int(nominal_strain * _FREE / (2 * speed) / dt), dt, control=ctrl, solver=solver)
    ctrl.set(velocity=np.zeros((1, 2, 3)))
    return run(model, int(hold / dt), dt, state=state, control=ctrl, solver=solver, every=every)


def _pieces(x, link, min_fraction=0.05):
    pairs = cKDTree(x).query_pairs(link, output_type="ndarray")
    A = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(x), len(x)))
    _, lab = connected_components(A, directed=False)
    return int((np.bincount(lab) >= min_fraction * len(x)).sum())


_FRACTURE = MaterialConfig(E=2e4, nu=0.3, density=1000.0, params={"fracture_strain": 0.2, "fracture_softening": 0.05})


def test_fracture_threshold():
    """A bar pulled to 80 % of the fracture strain keeps zero damage and one piece; pulled to 150 % it tears."""
    below, _ = _pull(_bar(_FRACTURE), 0.8 * 0.2)
    above, _ = _pull(_bar(_FRACTURE), 1.5 * 0.2, speed=0.05)
    d_below, d_above = below.particle_damage.numpy(), above.particle_damage.numpy()
    print(f"max damage {d_below.max():.3f} below, {d_above.max():.3f} above")
    assert d_below.max() == 0.0
    assert _pieces(below.particle_x.numpy(), 0.75 * DX) == 1
    assert d_above.max() == 1.0
    assert _pieces(above.particle_x.numpy(), 0.75 * DX) >= 2


def test_fracture_notched_bar_breaks_in_two_at_the_notch():
    state, _ = _pull(_bar(_FRACTURE, notch=True), 0.3, speed=0.05)
    d = state.particle_damage.numpy()
    x0 = state.particle_x.numpy()
    assert _pieces(x0, 0.75 * DX) == 2
    broken_x = _bar(_FRACTURE, notch=True).state().particle_x.numpy()[d > 0.5, 0]
    assert np.all(np.abs(broken_x) < 0.015), f"damage away from the notch at x = {np.unique(broken_x.round(3))}"


def test_torn_bar_pulled_far_keeps_a_bounded_deformation_gradient():
    """Past full damage nothing resists stretching, so F would grow without bound and, in a torn rope that
    kept being lifted, reach principal stretches of thousands and then NaN. A fully broken particle keeps
    F = J^(1/3) I with J <= 1 instead (kernels.broken_deformation), and the bar stays finite."""
    state, _ = _pull(_bar(_FRACTURE, notch=True), 1.0, speed=0.1, hold=0.05)
    d = state.particle_damage.numpy()
    F = state.particle_F.numpy()
    assert np.all(np.isfinite(F)) and np.all(np.isfinite(state.particle_x.numpy()))
    broken = d >= 1.0
    assert broken.sum() > 10, "the bar should tear"
    J = np.linalg.det(F[broken])
    np.testing.assert_allclose(F[broken], J[:, None, None] ** (1 / 3) * np.eye(3), atol=1e-5)
    assert J.max() <= 1.0 + 1e-6
    # what damage < 1 leaves alone: those particles' stretch is below full damage
    stretch = np.linalg.svd(F[~broken], compute_uv=False).max(1)
    assert stretch.max() < 1.0 + 0.2 + 0.05 + 1e-3


@wp.kernel
def _broken_kernel(F: wp.array(dtype=wp.mat33), mu: float, lam: float, tau: wp.array(dtype=wp.mat33),
                   tau_reset: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    tau[i] = K.damaged_kirchhoff(F[i], mu, lam, 1.0)
    tau_reset[i] = K.damaged_kirchhoff(K.broken_deformation(F[i], 1.0e-3), mu, lam, 1.0)


def test_reset_of_a_broken_particle_keeps_its_stress():
    """A fully broken particle's stress depends on J alone (compression only): the reset to J^(1/3) I leaves
    it unchanged, compressed or stretched, sheared or not."""
    rng = np.random.default_rng(3)
    F = np.eye(3) + 0.4 * rng.normal(size=(64, 3, 3))
    F[:8] = np.eye(3) * 0.9  # pure compression
    F = F[np.linalg.det(F) > 0.05].astype(np.float32)
    Fw = wp.array(F, dtype=wp.mat33, device="cpu")
    tau, tau_reset = (wp.zeros(len(F), dtype=wp.mat33, device="cpu") for _ in range(2))
    wp.launch(_broken_kernel, dim=len(F), inputs=[Fw, 3.0e4, 5.0e4], outputs=[tau, tau_reset], device="cpu")
    a, b = tau.numpy(), tau_reset.numpy()
    assert np.abs(a).max() > 1e3, "some cases should be compressed (a nonzero stress)"
    np.testing.assert_allclose(b, a, atol=1e-3 * np.abs(a).max())


def test_no_fracture_leaves_damage_zero():
    state, _ = _pull(_bar(MaterialConfig(E=2e4, nu=0.3, density=1000.0)), 0.4, speed=0.05, hold=0.02)
    assert state.particle_damage.numpy().max() == 0.0


# ------------------------------------------------------------------------------------------ stiffness field
def _extensions(model, strain=0.06):
    """(left, right) extension [m] of the two halves of the free part of a pulled bar, settled."""
    x0 = model.state().particle_x.numpy()
    _, xs = _pull(model, strain, hold=0.15, every=10)
    x = np.mean(xs[-20:], axis=0)

    def disp(a):
        m = np.abs(x0[:, 0] - a) < 0.003
        return float((x[m, 0] - x0[m, 0]).mean())

    a = 0.035
    return disp(0.0) - disp(-a), disp(a) - disp(0.0)


def test_heterogeneous_stiffness_gradient_strains_as_linear_elasticity_predicts():
    """E(x) = E exp(a u), u = x / h: in series, extensions go as the integral of 1/E, so
    left / right = exp(a * 0.035 / h) for the halves [-0.035, 0] and [0, 0.035] m."""
    slope = 1.0
    model = _bar(MaterialConfig(E=2e4, nu=0.0, density=1000.0, viscosity=2.0, params={"stiffness_slope_1": slope}))
    h = float(np.abs(model.state().particle_x.numpy()[:, 0]).max())
    left, right = _extensions(model)
    predicted = np.exp(slope * 0.035 / h)
    print(f"left {left * 1e3:.3f} mm, right {right * 1e3:.3f} mm, ratio {left / right:.3f}, predicted {predicted:.3f}")
    assert left / right == pytest.approx(predicted, rel=0.05)


def test_soft_and_stiff_halves_strain_in_the_ratio_of_their_moduli():
    """Two halves in series, E and 3E: the soft half stretches 3x as much (7 % tolerance: the step in E is
    smeared over one grid cell)."""
    model = _bar(MaterialConfig(E=2e4, nu=0.0, density=1000.0, viscosity=2.0))
    x0 = model.state().particle_x.numpy()
    model.particle_stiffness.assign(np.where(x0[:, 0] > 0, 3.0, 1.0).astype(np.float32))
    model.update_particle_materials()
    left, right = _extensions(model)
    assert left / right == pytest.approx(3.0, rel=0.1)


# ------------------------------------------------------------------------------------------ gradients
def _set_param(model, name):
    p = PARAMETERS[name]
    arr = getattr(model, p.array)

    def setter(v):
        a = arr.numpy().copy()
        if p.component is None:
            a[0] = v
        else:
            a[0, p.component] = v
        arr.assign(a)
        model.sync_materials_from_device()

    return setter


def _grad_of(model, name):
    p = PARAMETERS[name]
    g = getattr(model, p.array).grad.numpy()
    return float(g[0] if p.component is None else g[0, p.component])


def _pull_setup(speed):
    def setup(s0, ctrls):
        for c in ctrls:
            c.set(velocity=[[[-speed, 0, 0], [speed, 0, 0]]], grip=[[1, 1]])
    return setup


def _stretched_bar_state(model, strain):
    """A state of the bar pulled to a nominal strain (the starting point of the fracture gradient checks)."""
    state, _ = _pull(model, strain, speed=0.05, hold=0.0)
    return state.to_numpy()


# Tearing is a softening instability: the loss bends sharply with fracture_strain once the bar starts to
# tear, so its check uses a shorter horizon and a smaller step (the difference quotient converges to the
# tape value as h shrinks: 2.32, 0.71, 0.498 at h = 2, 0.5, 0.1 % against 0.486 at 40 substeps).
@pytest.mark.parametrize("name,value,rel,steps", [
    ("grip_friction", 2.0, 0.02, 40),
    ("stiffness_slope_1", 0.5, 0.04, 40),
    ("fracture_strain", 0.2, 0.005, 20),
    ("fracture_softening", 0.1, 0.02, 40),
])
def test_effect_parameter_gradient_matches_finite_difference(name, value, rel, steps):
    spc = 5
    if name == "grip_friction":
        model = _hanging_block(value, requires_grad=True)

        def setup(s0, ctrls):
            for c in ctrls:
                c.set(grip=[[1]])
    else:
        mat = MaterialConfig(E=2e4, nu=0.3, density=1000.0)
        if name.startswith("fracture"):
            mat = mat.replace(fracture_strain=0.2, fracture_softening=0.1)
        mat = mat.replace(**{name: value})
        model = _bar(mat, requires_grad=True)
        start = _stretched_bar_state(_bar(mat), 0.21) if name.startswith("fracture") else None
        pull = _pull_setup(0.1)

        def setup(s0, ctrls):
            if start is not None:
                s0.from_numpy(start)
            pull(s0, ctrls)
    W = _weights(model, 1, seed=5)
    _loss_and_grads(model, steps, setup=setup, W=W, spc=spc)
    analytic = _grad_of(model, name)
    set_v = _set_param(model, name)
    h = rel * abs(value)
    losses = []
    for v in (value + h, value - h):
        set_v(v)
        losses.append(_loss_and_grads(model, steps, setup=setup, W=W, spc=spc)[0])
    set_v(value)
    _check(analytic, (losses[0] - losses[1]) / (2 * h), 0.05, f"d loss / d {name}")
