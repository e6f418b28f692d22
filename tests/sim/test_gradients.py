"""Tape gradients of rollouts, and the Kirchhoff stress's adjoint, against central finite differences (as
warp.autograd.gradcheck does)."""

import numpy as np
import pytest
import warp as wp

from empm_gym.sim import EndEffectorConfig, MaterialConfig, Rollout, SolverMPM, TableConfig
from empm_gym.sim import kernels as K

from .conftest import DEVICE, block_model

DT = 5e-4


def _loss_and_grads(model, steps, *, spc=5, checkpoint_every=None, setup=None, W=None, record_every=None):
    """Loss = sum_t sum_p W_tp . x_tp over recorded frames; returns (loss, rollout, controls)."""
    solver = SolverMPM(model)
    ro = Rollout(model, solver, steps=steps, dt=DT, substeps_per_control=spc,
                 record_every=record_every or steps, checkpoint_every=checkpoint_every)
    ctrls = ro.make_controls()
    s0 = model.state(requires_grad=True)
    if setup:
        setup(s0, ctrls)
    recs = ro.forward(s0, ctrls)
    if record_every is None:  # W weighs the final frame only
        W = [None] * (len(recs) - 1) + [W[0]]
    loss = float(sum((W[i] * r.numpy()).sum() for i, r in enumerate(recs) if W[i] is not None))
    ro.zero_grad(ctrls)
    ro.backward(list(W), state0=s0)
    return loss, ro, ctrls, s0


def _weights(model, records, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(records, model.particle_count, 3)).astype(np.float32)


def _fd(model, steps, set_value, values, *, setup=None, W=None, spc=5):
    out = []
    for v in values:
        set_value(v)
        out.append(_loss_and_grads(model, steps, setup=setup, W=W, spc=spc)[0])
    return out


def _set_world(model, name):
    arr = getattr(model, name)

    def setter(v):
        a = arr.numpy()
        a[0] = v
        arr.assign(a)
        model.sync_materials_from_device()

    return setter


def _check(analytic, numeric, rtol, what):
    print(f"{what}: tape {analytic:.6g}, finite difference {numeric:.6g}")
    assert np.isfinite(analytic), f"{what}: non-finite gradient"
    assert abs(numeric) > 0, f"{what}: the loss does not depend on the parameter; the test would prove nothing"
    assert abs(analytic - numeric) <= rtol * abs(numeric), f"{what}: tape {analytic:.6g} vs finite difference {numeric:.6g}"


def _squeeze_scene(material, **kw):
    # a block dropped onto the table with a downward initial velocity: it compresses and rebounds
    return block_model(material=material, requires_grad=True, jitter=0.4, **kw)


def _initial_velocity(s0, ctrls):
    v = np.zeros((s0.particle_v.shape[0], 3), np.float32)
    v[:, 2] = -0.4
    v[:, 0] = 0.1
    s0.particle_v.assign(v)


@pytest.mark.parametrize("param,value,rel", [("world_E", 2e4, 0.02), ("world_nu", 0.3, 0.03),
                                             ("world_viscosity", 5.0, 0.05), ("world_density", 1000.0, 0.02)])
def test_material_gradient_matches_finite_difference(param, value, rel):
    model = _squeeze_scene(MaterialConfig(E=2e4, nu=0.3, density=1000.0, viscosity=5.0))
    steps = 40
    W = _weights(model, 1)
    _, _, _, _ = _loss_and_grads(model, steps, setup=_initial_velocity, W=W)
    set_v = _set_world(model, param)
    set_v(value)
    _, ro, _, _ = _loss_and_grads(model, steps, setup=_initial_velocity, W=W)
    analytic = float(getattr(model, param).grad.numpy()[0])
    h = rel * value
    lp, lm = _fd(model, steps, set_v, [value + h, value - h], setup=_initial_velocity, W=W)
    set_v(value)
    _check(analytic, (lp - lm) / (2 * h), 0.05, f"d loss / d {param}")


def test_yield_stress_gradient_matches_finite_difference():
    ys = 1.5e3
    press = (EndEffectorConfig(shape="box", half_extents=(0.05, 0.05, 0.01)), (0.0, 0.0, 0.05))

    def setup(s0, ctrls):
        for c in ctrls:
            c.set(velocity=[[[0.0, 0.0, -0.4]]], grip=[[1]])

    model = block_model(material=MaterialConfig(E=3e4, nu=0.3, density=1000.0, yield_stress=ys),
                        end_effectors=[press], requires_grad=True)
    steps = 40
    W = _weights(model, 1, seed=3)
    _loss_and_grads(model, steps, setup=setup, W=W)
    analytic = float(model.world_yield.grad.numpy()[0])
    set_v = _set_world(model, "world_yield")
    h = 0.03 * ys
    lp, lm = _fd(model, steps, set_v, [ys + h, ys - h], setup=setup, W=W)
    set_v(ys)
    _check(analytic, (lp - lm) / (2 * h), 0.05, "d loss / d yield_stress")


def test_table_friction_gradient_matches_finite_difference():
    mu = 0.3

    def setup(s0, ctrls):
        v = np.zeros((s0.particle_v.shape[0], 3), np.float32)
        v[:, 0] = 0.5  # sliding along the table
        s0.particle_v.assign(v)

    model = block_model(material=MaterialConfig(E=2e4, nu=0.3, density=1000.0), table=TableConfig(friction=mu),
                        lower=(-0.03, -0.03, 0.0), upper=(0.0, 0.03, 0.03), requires_grad=True)
    steps = 60
    W = np.zeros((1, model.particle_count, 3), np.float32)
    W[..., 0] = 1.0  # loss = sum of x: how far the block slid
    _loss_and_grads(model, steps, setup=setup, W=W)
    analytic = float(model.world_table_friction.grad.numpy()[0])
    set_v = _set_world(model, "world_table_friction")
    h = 0.02
    lp, lm = _fd(model, steps, set_v, [mu + h, mu - h], setup=setup, W=W)
    set_v(mu)
    numeric = (lp - lm) / (2 * h)
    assert numeric < 0  # more friction, less sliding
    _check(analytic, numeric, 0.05, "d loss / d table friction")


def _gripper_model():
    grip = (EndEffectorConfig(shape="sphere", radius=0.018), (0.0, 0.0, 0.02))
    return block_model(material=MaterialConfig(E=2e4, nu=0.3, density=1000.0), end_effectors=[grip],
                       requires_grad=True)


def test_action_gradient_several_steps_before_loss_matches_finite_difference():
    # a closed gripper inside the block drags it; the loss sees only the final frame, 3 control
    # periods (15 substeps) after the perturbed action.
    model = _gripper_model()
    steps, spc = 30, 5
    vel = np.zeros((steps // spc, 1, 1, 3), np.float32)
    vel[:, 0, 0] = (0.2, 0.0, 0.3)
    W = _weights(model, 1, seed=5)

    def setup_with(v):
        def setup(s0, ctrls):
            for c, vc in zip(ctrls, v):
                c.set(velocity=vc, grip=[[1]])
        return setup

    _, ro, ctrls, _ = _loss_and_grads(model, steps, spc=spc, setup=setup_with(vel), W=W)
    k, axis = 2, 0
    analytic = float(ctrls[k].ee_vel.grad.numpy()[0, axis])
    h = 2e-3
    vals = []
    for sgn in (1, -1):
        v = vel.copy()
        v[k, 0, 0, axis] += sgn * h
        vals.append(_loss_and_grads(model, steps, spc=spc, setup=setup_with(v), W=W)[0])
    _check(analytic, (vals[0] - vals[1]) / (2 * h), 0.05, "d loss / d action")


def test_checkpointed_gradients_equal_full_tape():
    model = _gripper_model()
    steps, spc = 30, 5
    W = _weights(model, 4, seed=7)

    def setup(s0, ctrls):
        _initial_velocity(s0, ctrls)
        for c in ctrls:
            c.set(velocity=[[[0.1, 0.0, 0.2]]], grip=[[1]])

    def grads(ckpt):
        loss, ro, ctrls, s0 = _loss_and_grads(model, steps, spc=spc, setup=setup, W=W, record_every=10,
                                              checkpoint_every=ckpt)
        return [np.array([loss]), model.world_E.grad.numpy().copy(), model.world_nu.grad.numpy().copy(),
                np.stack([c.ee_vel.grad.numpy() for c in ctrls]), ro.initial_grad["particle_x"].numpy(),
                ro.initial_grad["particle_v"].numpy()], ro

    full, ro_full = grads(None)
    # segments that do not divide the horizon nor align with records (each re-taped), and segments that do
    # (one segment's code for all: replayed from two CUDA graphs on a GPU, its control slots refilled)
    for every, aligned in ((7, False), (10, True)):
        ckpt, ro_ckpt = grads(every)
        assert ro_ckpt.aligned == aligned
        for a, b in zip(full, ckpt):
            assert np.all(np.isfinite(a)) and np.abs(a).max() > 0
            np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6 * np.abs(a).max())
        assert ro_ckpt.memory_bytes() < ro_full.memory_bytes() / 2


def test_gradients_stay_finite_over_long_horizon():
    model = _squeeze_scene(MaterialConfig(E=2e4, nu=0.3, density=1000.0, yield_stress=2e3))
    steps = 800  # 0.4 s: fall, impact, plastic flattening, rest
    W = _weights(model, 1, seed=11)
    _, ro, _, _ = _loss_and_grads(model, steps, setup=_initial_velocity, W=W, checkpoint_every=100)
    for name in ("world_E", "world_nu", "world_yield", "world_density", "world_table_friction"):
        g = getattr(model, name).grad.numpy()
        assert np.all(np.isfinite(g)), f"{name} gradient is not finite after {steps} steps"
    assert abs(model.world_E.grad.numpy()[0]) > 0
    for name, g in ro.initial_grad.items():
        assert np.all(np.isfinite(g.numpy())), f"initial {name} gradient is not finite"


def test_grid_update_thread_count_and_packed_atomics_change_nothing():
    # the grid update's threads stride over the active nodes; results and gradients must not depend on
    # how many there are (one, a few that do not divide the work, more than there are nodes), nor on P2G's
    # native 16-byte node atomic (its CPU branch runs here)
    model = _gripper_model()
    W = _weights(model, 1, seed=11)

    def setup(s0, ctrls):
        _initial_velocity(s0, ctrls)
        for c in ctrls:
            c.set(velocity=[[[0.1, 0.0, 0.2]]], grip=[[1]])

    out = []
    for threads in (None, 7, 100000, "packed"):
        solver = SolverMPM(model)
        if threads == "packed":
            solver._packed = 1
        elif threads:
            solver._grid_threads = threads
        ro = Rollout(model, solver, steps=20, dt=DT, substeps_per_control=5, record_every=20)
        ctrls = ro.make_controls()
        s0 = model.state(requires_grad=True)
        setup(s0, ctrls)
        recs = ro.forward(s0, ctrls)
        ro.zero_grad(ctrls)
        ro.backward([None] * (len(recs) - 1) + [W[0]], state0=s0)
        out.append((recs[-1].numpy().copy(), model.world_E.grad.numpy().copy(),
                    np.stack([c.ee_vel.grad.numpy() for c in ctrls])))
    assert np.abs(out[0][1]).max() > 0 and np.abs(out[0][2]).max() > 0
    for x, gE, gv in out[1:]:
        np.testing.assert_array_equal(x, out[0][0])
        np.testing.assert_allclose(gE, out[0][1], rtol=1e-6)
        np.testing.assert_allclose(gv, out[0][2], rtol=1e-6, atol=1e-9)


# -- the Kirchhoff stress's hand-written adjoint (wp.func_grad) against central differences of a float64
# reference: tau = 2 mu k (F - R) F^T + lam J (J - 1) I (times k when J > 1), k = 1 - damage, R the rotation
# of F's signed SVD (U and V rotations, the last singular value negative when det F < 0, as wp.svd3 does).


@wp.kernel
def _kirchhoff_kernel(F: wp.array(dtype=wp.mat33), mu: wp.array(dtype=float), lam: wp.array(dtype=float),
                      damage: wp.array(dtype=float), tau: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    tau[i] = K.damaged_kirchhoff(F[i], mu[i], lam[i], damage[i])


def _kirchhoff_reference(F, mu, lam, damage):
    u, _, vt = np.linalg.svd(F)
    R = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    J = np.linalg.det(F)
    k = 1.0 - damage
    return 2.0 * mu * k * (F - R) @ F.T + lam * J * (J - 1.0) * (k if J > 1.0 else 1.0) * np.eye(3)


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.sign(np.linalg.det(q))


def _kirchhoff_cases(rng):
    """(name, F, damage): at rest and rotated (repeated singular values, where the polar rotation's adjoint
    differs most from svd3's), near them, stretched (J > 1), compressed (J < 1), mixed, inverted."""
    def turned(s):
        return _rotation(rng) @ np.diag(s) @ _rotation(rng)
    cases = [("identity", np.eye(3), 0.0), ("rotation", _rotation(rng), 0.0)]  # J = 1: the damage kink
    for d in (0.0, 0.5):
        cases += [("near identity", np.eye(3) + 0.02 * rng.normal(size=(3, 3)), d),
                  ("near rotation", _rotation(rng) @ (np.eye(3) + 0.02 * rng.normal(size=(3, 3))), d),
                  ("stretched", turned([1.3, 1.15, 1.05]), d),
                  ("compressed", turned([0.8, 0.9, 0.7]), d),
                  ("two equal stretches", turned([1.2, 1.2, 0.8]), d),
                  ("mixed", np.eye(3) + 0.3 * rng.normal(size=(3, 3)), d),
                  ("inverted", turned([1.1, 0.9, -0.4]), d)]
    return cases


def test_kirchhoff_adjoint_matches_finite_difference():
    rng = np.random.default_rng(2)
    cases = _kirchhoff_cases(rng)
    n = len(cases)
    F = np.array([c[1] for c in cases], np.float32)
    damage = np.array([c[2] for c in cases], np.float32)
    mu = rng.uniform(5e3, 1e4, n).astype(np.float32)
    lam = rng.uniform(5e3, 2e4, n).astype(np.float32)
    G = rng.normal(size=(n, 3, 3)).astype(np.float32)  # dL/dtau, not symmetric (as P2G's is not)
    inputs = [wp.array(F, dtype=wp.mat33, device=DEVICE, requires_grad=True)]
    inputs += [wp.array(a, dtype=float, device=DEVICE, requires_grad=True) for a in (mu, lam, damage)]
    tau = wp.zeros(n, dtype=wp.mat33, device=DEVICE, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(_kirchhoff_kernel, dim=n, inputs=inputs, outputs=[tau], device=DEVICE)
    tape.backward(grads={tau: wp.array(G, dtype=wp.mat33, device=DEVICE)})
    grads = [a.grad.numpy() for a in inputs]
    h = 1e-6
    for i, (name, _, _) in enumerate(cases):
        x = [F[i].astype(np.float64), float(mu[i]), float(lam[i]), float(damage[i])]
        np.testing.assert_allclose(tau.numpy()[i], _kirchhoff_reference(*x), rtol=1e-4, atol=1e-5 * lam.max())

        def loss(j, delta):
            y = list(x)
            y[j] = y[j] + delta
            return float(np.sum(G[i] * _kirchhoff_reference(*y)))

        dF = np.zeros((3, 3))
        for a in range(3):
            for b in range(3):
                e = np.zeros((3, 3))
                e[a, b] = h
                dF[a, b] = (loss(0, e) - loss(0, -e)) / (2 * h)
        what = f"{name} (det F {np.linalg.det(x[0]):.3f}, damage {x[3]})"
        np.testing.assert_allclose(grads[0][i], dF, rtol=1e-3, atol=1e-6 * np.abs(dF).max(), err_msg=f"dL/dF, {what}")
        # float32 round-off of tau's two parts: |G| |F|^2 per unit modulus, times the modulus for damage
        unit = np.abs(G[i]).sum()
        for j, param, scale in ((1, "mu", unit), (2, "lambda", unit), (3, "damage", unit * max(mu[i], lam[i]))):
            numeric = (loss(j, h) - loss(j, -h)) / (2 * h)
            assert abs(grads[j][i] - numeric) <= 1e-3 * abs(numeric) + 1e-5 * scale, \
                f"dL/d{param}, {what}: adjoint {grads[j][i]:.6g}, finite difference {numeric:.6g}"


def test_kirchhoff_adjoint_stays_finite_where_the_rotation_is_undefined():
    # F = 0, rank one, two singular values that cancel (s_2 = -s_3: flattened, or inverted by a reflection)
    F = np.array([np.zeros((3, 3)), np.outer([1.0, 2.0, 3.0], [0.3, -0.2, 0.1]), np.diag([1.0, 1e-8, -1e-8]),
                  np.diag([1.0, 0.5, -0.5]), np.diag([-1.0, -1.0, -1.0])], np.float32)
    n = len(F)
    inputs = [wp.array(F, dtype=wp.mat33, device=DEVICE, requires_grad=True)]
    inputs += [wp.array(np.full(n, v, np.float32), dtype=float, device=DEVICE, requires_grad=True)
               for v in (7e3, 1e4, 0.3)]
    tau = wp.zeros(n, dtype=wp.mat33, device=DEVICE, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(_kirchhoff_kernel, dim=n, inputs=inputs, outputs=[tau], device=DEVICE)
    G = np.random.default_rng(4).normal(size=(n, 3, 3)).astype(np.float32)
    tape.backward(grads={tau: wp.array(G, dtype=wp.mat33, device=DEVICE)})
    for a in inputs:
        assert np.all(np.isfinite(a.grad.numpy()))
