"""Gradient trajectory optimisation: Adam on the action sequence through the differentiable simulator.

The actions are ``tanh(u)`` of free parameters u [H, 3K], so they stay in [-1, 1]; the end-effector
velocities ``max_speed * tanh(u)`` go through :func:`empm_gym.autograd.simulate` on a
:class:`~empm_gym.sim.Rollout` (checkpointed per control period) from the given state. The loss is the
symmetric Chamfer distance [m] between the final particles and the target, plus a penalty on
end-effector centres leaving the task's workspace box (the environment would stop them there). Grip
commands are not differentiable: they are held at the state's current grip.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..autograd import simulate
from ..sim import Rollout, SimulationDiverged
from .base import Planner

__all__ = ["GradientPlanner", "chamfer_torch"]


def chamfer_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Symmetric Chamfer distance [m] of point sets a [n, 3], b [m, 3]: mean of both directions' mean
    nearest-neighbour distances (the environments' reward metric)."""
    d = torch.cdist(a, b)
    return 0.5 * (d.min(1).values.mean() + d.min(0).values.mean())


class GradientPlanner(Planner):
    """Adam on the action sequence (see the module docstring).

    Args:
        iterations: Adam steps.
        lr: Adam learning rate on the pre-tanh parameters.
        bound_weight: weight of the workspace penalty [1/m].
    """

    def __init__(self, task, *, iterations: int = 20, lr: float = 0.3, bound_weight: float = 10.0,
                 env_kwargs=None, seed: Optional[int] = 0):
        super().__init__(task, env_kwargs=env_kwargs, seed=seed)
        if iterations < 1 or not lr > 0:
            raise ValueError(f"iterations must be >= 1 and lr > 0, got iterations={iterations!r}, lr={lr!r}")
        self.iterations, self.lr, self.bound_weight = int(iterations), float(lr), float(bound_weight)
        self.core = self._core(1)
        self.action_dim = self.core.action_dim
        self._rollouts = {}
        self.history = []
        """Loss [m] of each iteration of the last :meth:`plan`."""

    def _rollout(self, H: int) -> Rollout:
        if H not in self._rollouts:
            c = self.core
            self._rollouts[H] = Rollout(c.model, c.solver, steps=H * c.substeps, dt=c.dt,
                                        substeps_per_control=c.substeps, record_every=H * c.substeps,
                                        checkpoint_every=c.substeps)
        return self._rollouts[H]

    def plan(self, state, horizon, init=None):
        H = self._check_horizon(horizon)
        c = self.core
        K = c.K
        c.set_world_states([0], [state])
        ro = self._rollout(H)
        controls = ro.make_controls()
        grip = c.grip[0][None].astype(np.int32)
        for ctl in controls:
            ctl.set(grip=grip)
        init = self._init(init, H, self.action_dim)
        u = torch.tensor(np.arctanh(np.clip(init[:, : 3 * K], -0.95, 0.95)), dtype=torch.float32, requires_grad=True)
        opt = torch.optim.Adam([u], lr=self.lr)
        target = torch.tensor(c.target_subset(0, c.chamfer_target_points), dtype=torch.float32)
        ee0 = torch.tensor(state["sim"]["ee_pos"], dtype=torch.float32)
        lo, hi = torch.tensor(c.ee_lower), torch.tensor(c.ee_upper)
        s0 = c.state
        best_u, best_loss = u.detach().clone(), np.inf
        self.history = []
        for _ in range(self.iterations):
            opt.zero_grad()
            vel = (c.max_speed * torch.tanh(u)).reshape(H, 1, K, 3)
            try:
                X = simulate(ro, s0, controls, ee_velocity=vel)
            except SimulationDiverged:
                break
            loss_cd = chamfer_torch(X[-1], target)
            path = ee0[None] + torch.cumsum(vel[:, 0] * c.control_dt, 0)  # [H, K, 3]
            excess = torch.relu(lo - path) + torch.relu(path - hi)
            loss = loss_cd + self.bound_weight * (excess ** 2).sum()
            if loss_cd.item() < best_loss:
                best_loss, best_u = loss_cd.item(), u.detach().clone()
            self.history.append(loss_cd.item())
            loss.backward()
            if not torch.isfinite(u.grad).all():
                break
            opt.step()
        acts = np.tanh(best_u.numpy())
        if c.task.grip_control:
            acts = np.concatenate([acts, np.tile(np.where(grip[0] > 0, 1.0, -1.0), (H, 1))], 1)
        return acts.astype(np.float32)
