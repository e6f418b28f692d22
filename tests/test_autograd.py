"""The torch bridge: gradients equal finite differences, and torch optimisers recover parameters."""

import numpy as np
import pytest
import torch

from empm_gym.autograd import simulate
from empm_gym.sim import (EndEffectorConfig, GridConfig, MaterialConfig, ModelBuilder, Rollout, SolverMPM,
                          TableConfig, sample_box)


def _model(E=2e4):
    b = ModelBuilder(GridConfig(lower=(-0.08, -0.08, -0.03), upper=(0.08, 0.08, 0.12), dx=0.01),
                     table=TableConfig(friction=0.5))
    w = b.add_world(MaterialConfig(E=E, nu=0.3, density=1000.0))
    x, v = sample_box((-0.025, -0.025, 0.0), (0.025, 0.025, 0.05), 0.01, 8, jitter=0.4)
    b.add_particles(w, x, v)
    b.add_end_effector(w, EndEffectorConfig(shape="box", half_extents=(0.04, 0.04, 0.01)), (0.0, 0.0, 0.06))
    return b.finalize("cpu", requires_grad=True)


def _rollout(model, steps=60):
    return Rollout(model, SolverMPM(model), steps=steps, dt=5e-4, substeps_per_control=10, record_every=20)


def _press(n):
    v = torch.zeros(n, 1, 1, 3)
    v[..., 2] = -0.15  # a plate pressing the block down
    return v


def test_bridge_gradients_match_finite_differences():
    model = _model()
    ro = _rollout(model)
    ctrls = ro.make_controls()
    for c in ctrls:
        c.set(grip=[[1]])
    W = torch.randn(len(ro.record_steps), model.particle_count, 3, generator=torch.Generator().manual_seed(0))

    def loss(E, vel):
        return (simulate(ro, model.state(), ctrls, E=E, ee_velocity=vel) * W).sum()

    E = torch.tensor([2e4], requires_grad=True)
    vel = _press(len(ctrls)).requires_grad_(True)
    loss(E, vel).backward()
    assert vel.grad.shape == vel.shape
    h = 400.0
    fd_E = (loss(torch.tensor([2e4 + h]), vel.detach()) - loss(torch.tensor([2e4 - h]), vel.detach())) / (2 * h)
    assert E.grad.item() == pytest.approx(fd_E.item(), rel=0.05)
    hv = 2e-3
    k = 1
    vp, vm = vel.detach().clone(), vel.detach().clone()
    vp[k, 0, 0, 2] += hv
    vm[k, 0, 0, 2] -= hv
    fd_v = (loss(E.detach(), vp) - loss(E.detach(), vm)) / (2 * hv)
    assert vel.grad[k, 0, 0, 2].item() == pytest.approx(fd_v.item(), rel=0.05)


def test_bridge_rejects_bad_inputs():
    model = _model()
    ro = _rollout(model, steps=10)
    with pytest.raises(ValueError, match="shape"):
        simulate(ro, model.state(), E=torch.tensor([1e4, 2e4]))
    with pytest.raises(ValueError, match="non-finite"):
        simulate(ro, model.state(), E=torch.tensor([float("nan")]))
    with pytest.raises(ValueError, match="unknown input"):
        simulate(ro, model.state(), stiffnesss=torch.tensor([1.0]))


def test_adam_recovers_youngs_modulus_from_a_trajectory():
    E_true = 3e4
    model = _model(E_true)
    ro = _rollout(model, steps=80)
    ctrls = ro.make_controls()
    for c in ctrls:
        c.set(velocity=[[[0.0, 0.0, -0.15]]], grip=[[1]])
    with torch.no_grad():
        target = simulate(ro, model.state(), ctrls, E=torch.tensor([E_true]))
    # optimise log(E / 1e4) from 3x too soft
    theta = torch.tensor([np.log(1.0)], requires_grad=True)
    opt = torch.optim.Adam([theta], lr=0.15)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.9)
    for _ in range(30):
        opt.zero_grad()
        X = simulate(ro, model.state(), ctrls, E=1e4 * torch.exp(theta))
        loss = ((X - target) ** 2).sum(-1).mean()
        loss.backward()
        opt.step()
        sched.step()
    E_fit = 1e4 * float(torch.exp(theta.detach()))
    assert abs(E_fit - E_true) / E_true < 0.03, E_fit
