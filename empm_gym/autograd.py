"""Torch bridge: run a differentiable :class:`empm_gym.sim.Rollout` inside torch autograd.

``simulate(rollout, state0, controls, E=..., ee_velocity=...)`` writes the given torch tensors into
the model and controls, runs the rollout and returns the recorded particle positions as a tensor
[records, N, 3]; ``loss.backward()`` then fills the gradients of every tensor passed in, so torch
optimisers (Adam, AdamW, ...) can drive material parameters, initial positions and action sequences.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
import warp as wp

from .sim import Control, Rollout, State

__all__ = ["simulate", "PARAMETERS"]

def _parameters():
    from .sim.effects import PARAMETERS as EFFECT_PARAMS

    out = {"E": ("world_E", None), "nu": ("world_nu", None), "density": ("world_density", None),
           "table_friction": ("world_table_friction", None), "stiffness": ("particle_stiffness", None)}
    for p in EFFECT_PARAMS.values():
        if p.name != "friction":
            out[p.name] = (p.array, p.component)
    return out


#: Material / contact parameters that ``simulate`` accepts: name -> (model array, vector component or None).
#: Every effect parameter of :mod:`empm_gym.sim.effects` is one (the table's ``friction`` is ``table_friction``).
PARAMETERS = _parameters()


def _check(name, t: torch.Tensor, shape):
    if tuple(t.shape) != tuple(shape):
        raise ValueError(f"simulate: {name} must have shape {tuple(shape)}, got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"simulate: {name} holds non-finite values")


def _to_wp(t: torch.Tensor, dtype, device):
    return wp.array(t.detach().to("cpu", torch.float32).numpy(), dtype=dtype, device=device)


def _to_torch(a: wp.array, like: torch.Tensor):
    return torch.from_numpy(a.numpy().copy()).to(device=like.device, dtype=like.dtype)


class _Simulate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rollout: Rollout, state0: State, controls, names, *tensors):
        model = rollout.model
        for name, t in zip(names, tensors):
            if name in PARAMETERS:
                arr_name, comp = PARAMETERS[name]
                arr = getattr(model, arr_name)
                _check(name, t, arr.shape)
                if comp is None:
                    arr.assign(_to_wp(t, float, model.device))
                else:
                    host = arr.numpy().copy()
                    host[:, comp] = t.detach().to("cpu", torch.float32).numpy()
                    arr.assign(host)
            elif name == "ee_velocity":
                _check(name, t, (len(controls), model.world_count, model.ee_count, 3))
                for c, tc in zip(controls, t):
                    c.set(velocity=tc.detach().cpu().numpy())
            elif name == "x0":
                _check(name, t, (model.particle_count, 3))
                state0.particle_x.assign(_to_wp(t, wp.vec3, model.device))
            elif name == "v0":
                _check(name, t, (model.particle_count, 3))
                state0.particle_v.assign(_to_wp(t, wp.vec3, model.device))
            else:
                raise ValueError(f"simulate: unknown input {name!r}; known: {sorted(PARAMETERS) + ['ee_velocity', 'x0', 'v0']}")
        if any(n in PARAMETERS and n not in ("table_friction",) for n in names):
            model.sync_materials_from_device()
        records = rollout.forward(state0, controls)
        ctx.rollout, ctx.state0, ctx.controls, ctx.names = rollout, state0, controls, names
        ctx.save_for_backward(*tensors)
        out = np.stack([r.numpy() for r in records])
        like = tensors[0] if tensors else torch.zeros(())
        return torch.from_numpy(out).to(device=like.device, dtype=torch.float32)

    @staticmethod
    def backward(ctx, grad_out):
        rollout, model = ctx.rollout, ctx.rollout.model
        tensors = ctx.saved_tensors
        rollout.zero_grad(ctx.controls)
        g = grad_out.detach().to("cpu", torch.float32).numpy()
        rollout.backward([g[i] for i in range(g.shape[0])])
        grads = []
        for name, t in zip(ctx.names, tensors):
            if name in PARAMETERS:
                arr_name, comp = PARAMETERS[name]
                g = getattr(model, arr_name).grad
                if comp is None:
                    grads.append(_to_torch(g, t))
                else:
                    grads.append(torch.from_numpy(g.numpy()[:, comp].copy()).to(device=t.device, dtype=t.dtype))
            elif name == "ee_velocity":
                grads.append(torch.stack([_to_torch(c.ee_vel.grad, t).reshape(t.shape[1:]) for c in ctx.controls]))
            elif name == "x0":
                grads.append(_to_torch(rollout.initial_grad["particle_x"], t))
            elif name == "v0":
                grads.append(_to_torch(rollout.initial_grad["particle_v"], t))
        return (None, None, None, None, *grads)


def simulate(rollout: Rollout, state0: State, controls: Optional[Sequence[Control]] = None, **inputs: torch.Tensor):
    """Differentiable rollout; returns recorded positions [records, N, 3] (m) as a torch tensor.

    Keyword inputs (torch tensors, any of): ``E``, ``nu``, ``density``, ``table_friction`` and every effect
    parameter of :mod:`empm_gym.sim.effects` (``yield_stress``, ``viscosity``, ``grip_friction``,
    ``stiffness_slope_1..3``, ``fracture_strain``, ``fracture_softening``; each [worlds]), ``stiffness`` ([N] multiplier), ``ee_velocity``
    ([controls, worlds, ee_count, 3] m/s), ``x0``, ``v0`` ([N, 3] initial positions / velocities).
    """
    controls = list(controls) if controls is not None else rollout.make_controls()
    names = tuple(inputs)
    return _Simulate.apply(rollout, state0, controls, names, *inputs.values())
