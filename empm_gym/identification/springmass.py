"""Identification with the spring-mass model family (PhysTwin-style, :mod:`empm_gym.springmass`).

The same :class:`~.problem.Scene` as the MPM fits (frame-0 body, end-effector controls, table) becomes a
spring-mass network (:func:`spring_mass_sim`); :func:`simulate_frames_spring_mass` mirrors
:func:`~.problem.simulate_frames`; :func:`identify_spring_mass` fits the log stiffness and log damping with
the offline fit's loss (:class:`~.offline.Objective`: Chamfer to the observed points plus tracking, the
observed frame-0 surface carried by the simulated body) by gradients through ``wp.Tape`` and AdamW with the
offline fit's step control (back to the best point and half the step when the loss rose).

The network's particles are the scene's body voxel-downsampled to ``SpringMassConfig.spacing`` (default half
the MPM grid cell), so its particle set differs from the MPM one: :func:`spring_mass_scene` gives the scene
with the network's particles, which the loss and the evaluation use. Substeps are fixed for a whole fit from
the stiffest, most damped corner of the search box, so the loss is a function of the parameters alone.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
import torch

from empm_gym.sim import SimulationDiverged, write_material
from empm_gym.springmass import SpringMassConfig, SpringMassSim, model_from_body

from .offline import FitResult, Objective
from .problem import Observations, Scene

__all__ = ["SPRING_MASS_PARAMS", "spring_mass_sim", "spring_mass_scene", "simulate_frames_spring_mass",
           "identify_spring_mass", "evaluate_spring_mass", "SpringMassFitResult", "read_spring_mass"]

#: Fitted parameters and their reference scales (the optimiser sees z = log(value / scale)).
SPRING_MASS_PARAMS = {"stiffness": 1.0e5, "damping": 1.0}
_DIVERGED_LOSS = 1.0e3


def _spacing(scene: Scene, config: SpringMassConfig) -> float:
    return float(config.spacing) if config.spacing is not None else 0.5 * float(scene.dx)


def spring_mass_sim(scene: Scene, config: SpringMassConfig = SpringMassConfig(), *,
                    requires_grad: bool = False) -> SpringMassSim:
    """The scene as a spring-mass simulation: its frame-0 body at ``config.spacing`` (default ``scene.dx / 2``),
    masses from ``scene.material.density``, its end-effectors, table and table friction."""
    model = model_from_body(scene.particles, scene.volumes, density=scene.material.density, config=config,
                            spacing=_spacing(scene, config), gravity=scene.gravity, device=scene.device,
                            requires_grad=requires_grad)
    return SpringMassSim(model, fps=scene.fps, ee_configs=scene.ee_configs, ee_positions=scene.ee_positions,
                         ee_orientations=scene.ee_orientations, ee_grip=scene.ee_grip,
                         table_height=None if scene.table is None else scene.table.height,
                         table_friction=scene.table_friction)


def spring_mass_scene(scene: Scene, sim: SpringMassSim) -> Scene:
    """``scene`` with the spring-mass network's particles and volumes (what the loss and evaluation compare)."""
    m = sim.model
    return replace(scene, particles=m.x0, volumes=m.mass / scene.material.density)


def simulate_frames_spring_mass(scene: Scene, config: SpringMassConfig = SpringMassConfig(),
                                frames: Optional[int] = None, *, sim: Optional[SpringMassSim] = None) -> np.ndarray:
    """Positions [frames, N, 3] (m) of the spring-mass network's N particles (see :func:`spring_mass_scene`),
    at every frame; raises :class:`~empm_gym.sim.SimulationDiverged` instead of returning NaNs."""
    frames = frames or scene.num_frames
    if frames is None or frames < 1:
        raise ValueError("simulate_frames_spring_mass: give frames (the scene has no end-effector controls)")
    sim = sim or spring_mass_sim(scene, config)
    sim.model.set_params(config.stiffness, config.damping)
    return sim.run(frames)


class _Rollout(torch.autograd.Function):
    """Taped spring-mass rollout as a torch function of (stiffness [Pa], damping [Pa s], per-spring log scale)."""

    @staticmethod
    def forward(ctx, sim: SpringMassSim, frames: int, substeps: int, Y: torch.Tensor, eta: torch.Tensor,
                log_scale: torch.Tensor):
        sim.model.set_params(float(Y), float(eta), log_scale.detach().cpu().numpy() if log_scale.numel() else None)
        X = sim.run(frames, substeps=substeps, requires_grad=True)
        ctx.sim = sim
        ctx.shapes = (Y, eta, log_scale)
        return torch.from_numpy(X)

    @staticmethod
    def backward(ctx, gX):
        g = ctx.sim.backward(gX.detach().cpu().numpy())
        Y, eta, s = ctx.shapes
        gs = torch.from_numpy(g["spring_log_scale"]).to(s.dtype) if s.numel() else torch.zeros_like(s)
        return (None, None, None, torch.tensor(float(g["stiffness"][0]), dtype=Y.dtype),
                torch.tensor(float(g["damping"][0]), dtype=eta.dtype), gs)


@dataclass
class SpringMassFitResult(FitResult):
    """A spring-mass fit: ``params`` holds stiffness [Pa] and damping [Pa s]; ``config`` the fitted model."""

    config: Optional[SpringMassConfig] = None

    def spring_mass_section(self) -> dict:
        c = self.config
        return {"stiffness": c.stiffness, "damping": c.damping, "drag": c.drag, "spacing": c.spacing,
                "radius_factor": c.radius_factor, "max_neighbors": c.max_neighbors, "control_omega": c.control_omega,
                "cfl": c.cfl}

    def to_dict(self) -> dict:
        from empm_gym.sim.material_file import material_dict

        return material_dict(self.file_material(), self.fit_section(), spring_mass=self.spring_mass_section())

    def save(self, path) -> Path:
        """Write the material file with ``"model": "spring-mass"`` (density, table friction, the model's settings
        and the ``fit`` section), atomically."""
        return write_material(path, self.file_material(), self.fit_section(), spring_mass=self.spring_mass_section())


def read_spring_mass(material_file) -> Tuple[SpringMassConfig, "object"]:
    """(SpringMassConfig, MaterialFile) of a ``"model": "spring-mass"`` file; ValueError naming the file otherwise."""
    from empm_gym.sim import read_material

    mf = read_material(material_file, models=("spring-mass",))
    try:
        cfg = SpringMassConfig(**{k: v for k, v in mf.spring_mass.items()})
    except TypeError as exc:
        raise ValueError(f"{material_file}: spring_mass section: {exc}") from None
    except ValueError as exc:
        raise ValueError(f"{material_file}: {exc}") from None
    return cfg, mf


def _check_value(name: str, v: float) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"init: {name} must be a number, got {v!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"init: {name} must be finite and > 0 ({'Pa' if name == 'stiffness' else 'Pa s'}), got {v!r}")
    return v


def identify_spring_mass(observations: Observations, scene: Scene, *, config: SpringMassConfig = SpringMassConfig(),
                         params: Sequence[str] = ("stiffness", "damping"), init: Optional[Dict[str, float]] = None,
                         bounds: Optional[Dict[str, Tuple[float, float]]] = None, iters: int = 30,
                         frames: Optional[int] = None, lr: float = 0.15, betas: Tuple[float, float] = (0.8, 0.95),
                         l_dist: float = 1.0, l_trk: float = 100.0, chamfer: str = "both", max_points: int = 2000,
                         observation: str = "auto", seed: int = 0, per_spring: bool = False, progress: bool = True,
                         callback: Optional[Callable[[int, float, Dict[str, float]], None]] = None,
                         stop=None) -> SpringMassFitResult:
    """Fit ``params`` (stiffness [Pa], damping [Pa s]) of a spring-mass model of ``scene`` to ``observations``.

    ``init`` starts the fit (default ``config``'s values), ``bounds`` (SI) bound it (default a factor 10 either
    way of the start); the optimiser works on z = log(value / scale) (scales :data:`SPRING_MASS_PARAMS`) with
    AdamW at ``lr``. ``per_spring`` also fits a log stiffness multiplier per spring (PhysTwin's per-spring
    stiffness; within a factor 10 of the global value). The loss is :class:`~.offline.Objective` on the first
    ``frames`` frames (``l_dist``, ``l_trk``, ``chamfer``, ``max_points``, ``observation`` as in
    :func:`~.offline.identify`). ``stop`` (``is_set()`` or a callable) ends the fit early (``complete`` False).
    Returns the best evaluated parameters as a :class:`SpringMassFitResult`.
    """
    params = tuple(params)
    if not params or any(p not in SPRING_MASS_PARAMS for p in params) or len(set(params)) != len(params):
        raise ValueError(f"params must be distinct names among {', '.join(SPRING_MASS_PARAMS)}, got {params}")
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    if abs(observations.fps - scene.fps) > 1e-6 * scene.fps:
        raise ValueError(f"observations at {observations.fps} fps but the scene's controls at {scene.fps} fps")
    init = dict(init or {})
    unknown = set(init) - set(SPRING_MASS_PARAMS)
    if unknown:
        raise ValueError(f"init names unknown parameters {sorted(unknown)}; allowed: {', '.join(SPRING_MASS_PARAMS)}")
    start = {"stiffness": _check_value("stiffness", init.get("stiffness", config.stiffness)),
             "damping": init.get("damping", config.damping)}
    if "damping" in params:
        start["damping"] = _check_value("damping", start["damping"])
    box = {n: (start[n] / 10.0, start[n] * 10.0) for n in params}
    for n, b in (bounds or {}).items():
        if n not in params:
            raise ValueError(f"bounds given for {n!r}, which is not fitted ({', '.join(params)})")
        lo, hi = float(b[0]), float(b[1])
        if not (0 < lo < hi) or not (lo <= start[n] <= hi):
            raise ValueError(f"bounds for {n!r} must satisfy 0 < lo <= start ({start[n]:g}) <= hi, got {b}")
        box[n] = (lo, hi)
    F = frames or min(observations.num_frames, scene.num_frames or observations.num_frames)
    if scene.num_frames is not None and F > scene.num_frames:
        raise ValueError(f"frames={F} exceeds the {scene.num_frames} frames of end-effector controls")
    if observation == "auto":
        observation = "surface" if observations.surface else "particles"
    cfg = config.replace(stiffness=start["stiffness"], damping=start["damping"])
    sim = spring_mass_sim(scene, cfg, requires_grad=True)
    objective = Objective(spring_mass_scene(scene, sim), observations, F, l_dist=l_dist, l_trk=l_trk, chamfer=chamfer,
                          max_points=max_points, seed=seed, observation=observation)
    hi = {n: box[n][1] if n in box else start[n] for n in SPRING_MASS_PARAMS}
    smax = math.log(10.0) if per_spring else 0.0
    sub, dt = sim.substeps(hi["stiffness"], hi["damping"], F, log_scale_max=smax)
    scale = SPRING_MASS_PARAMS
    z = torch.tensor([math.log(start[n] / scale[n]) for n in params], dtype=torch.float64, requires_grad=True)
    z_lo = torch.tensor([math.log(box[n][0] / scale[n]) for n in params], dtype=torch.float64)
    z_hi = torch.tensor([math.log(box[n][1] / scale[n]) for n in params], dtype=torch.float64)
    S = sim.model.spring_count
    s = torch.zeros(S if per_spring else 0, dtype=torch.float64, requires_grad=per_spring)
    leaves = [z, s] if per_spring else [z]
    opt = torch.optim.AdamW(leaves, lr=lr, betas=betas, weight_decay=0.0)
    step_scale, best = 1.0, None
    hist_l, hist_p = [], []
    from tqdm.auto import tqdm

    bar = tqdm(total=iters, desc="identify (spring-mass, adam)", disable=not progress, leave=False, dynamic_ncols=True)
    t0 = time.perf_counter()

    def values(zv):
        v = dict(start)
        v.update({n: float(scale[n] * math.exp(float(zv[i]))) for i, n in enumerate(params)})
        return v

    for it in range(iters):
        if stop is not None and (stop.is_set() if hasattr(stop, "is_set") else stop()):
            break
        vals = values(z.detach())
        for a in leaves:
            a.grad = None
        Y = torch.exp(z[params.index("stiffness")]) * scale["stiffness"] if "stiffness" in params else \
            torch.tensor(start["stiffness"], dtype=torch.float64)
        eta = torch.exp(z[params.index("damping")]) * scale["damping"] if "damping" in params else \
            torch.tensor(start["damping"], dtype=torch.float64)
        try:
            X = _Rollout.apply(sim, F, sub, Y, eta, s)
        except SimulationDiverged:
            hist_l.append(_DIVERGED_LOSS)
            hist_p.append(vals)
            with torch.no_grad():  # step back towards the start
                z.mul_(0.5).add_(0.5 * torch.tensor([math.log(start[n] / scale[n]) for n in params]))
            bar.update(1)
            continue
        loss = objective.torch(X)
        loss.backward()
        L = float(loss.detach())
        hist_l.append(L)
        hist_p.append(vals)
        if callback is not None:
            callback(it, L, vals)
        grads = [a.grad.detach().clone() if a.grad is not None else torch.zeros_like(a) for a in leaves]
        if best is None or L < best[0]:
            best = (L, [a.detach().clone() for a in leaves], grads, vals)
            step_scale = min(1.0, step_scale * 1.25)
        else:  # the loss rose: back to the best point, drop the momentum, halve the step
            step_scale *= 0.5
            with torch.no_grad():
                for a, b in zip(leaves, best[1]):
                    a.copy_(b)
            for a, g in zip(leaves, best[2]):
                a.grad = g.clone()
            for st in opt.state.values():
                if "exp_avg" in st:
                    st["exp_avg"].zero_()
        for group in opt.param_groups:
            group["lr"] = lr * step_scale
        opt.step()
        with torch.no_grad():
            z.copy_(torch.maximum(torch.minimum(z, z_hi), z_lo))
            if per_spring:
                s.clamp_(-math.log(10.0), math.log(10.0))
        bar.set_postfix(loss=f"{L:.5f}", **{k: f"{v:.4g}" for k, v in vals.items()})
        bar.update(1)
    bar.close()
    wall = time.perf_counter() - t0
    if best is not None:
        best_l, best_p = best[0], best[3]
        log_scale = best[1][1].numpy() if per_spring else None
    else:
        best_l, best_p, log_scale = float("nan"), dict(start), None
    fitted = cfg.replace(stiffness=best_p["stiffness"], damping=best_p["damping"])
    extra = {"model": "spring-mass", "lr": lr, "betas": list(betas), "substeps": sub, "dt_s": dt,
             "particles": sim.model.particle_count, "springs": S, "spacing_m": sim.model.spacing,
             "bounds": {n: list(box[n]) for n in params}, "observation": observation, "per_spring": per_spring,
             "objective": {"l_dist": l_dist, "l_trk": l_trk, "chamfer": chamfer, "max_points": max_points, "seed": seed}}
    extra["identifiability"] = bound_warnings({n: best_p[n] for n in params}, box)
    if log_scale is not None:
        extra["spring_log_scale"] = {"mean": float(log_scale.mean()), "std": float(log_scale.std()),
                                     "min": float(log_scale.min()), "max": float(log_scale.max())}
    res = SpringMassFitResult(method="adam", params={n: best_p[n] for n in params}, material=scene.material,
                              friction=scene.table_friction, loss=best_l, loss_history=[float(v) for v in hist_l],
                              param_history=hist_p, wall_time_s=wall, frames_used=F, fps=scene.fps,
                              init={n: start[n] for n in params}, extra=extra, complete=len(hist_l) >= iters,
                              iterations_requested=iters, config=fitted)
    res.spring_log_scale = log_scale
    return res


def bound_warnings(values: Dict[str, float], box: Dict[str, Tuple[float, float]]) -> dict:
    """Which fitted values sit at their search bound (within 2 % of the box's log-width of an end, the rule
    of the MPM fit's :func:`~empm_gym.identification.uncertainty.assess_fit`): ``{"method", "warnings",
    "determined": {param: bool}}``. A value at its bound is what the box allowed, not what the data say.
    Spring-mass fits get this check only, no intervals."""
    warnings, determined = [], {}
    for n, v in values.items():
        lo, hi = (math.log(b) for b in box[n])
        tol = 0.02 * (hi - lo)
        z = math.log(v)
        determined[n] = lo + tol < z < hi - tol
        if not determined[n]:
            side, b = ("lower", box[n][0]) if z <= lo + tol else ("upper", box[n][1])
            warnings.append(f"{n}: at its {side} search bound {b:.4g}: the data ask for a value outside the box "
                            f"searched, or do not determine it (the loss is flat along it)")
    return {"method": "bound check only (no intervals for spring-mass fits)", "warnings": warnings,
            "determined": determined}


def evaluate_spring_mass(scene: Scene, config: SpringMassConfig, obs: Observations, views=None, **kwargs) -> dict:
    """:func:`~.evaluate.evaluate` of a spring-mass model: the same held-out metrics (Chamfer, tracking, IoU,
    PSNR, SSIM), computed on the network's particles simulated with ``config`` (keyword arguments as there)."""
    from .evaluate import evaluate, held_out_frames

    T = obs.num_frames if scene.num_frames is None else min(obs.num_frames, scene.num_frames)
    frames = kwargs.get("eval_frames")
    if frames is None:
        frames = held_out_frames(T, kwargs.get("train_fraction", 0.7))
        kwargs["eval_frames"] = frames
    sim = spring_mass_sim(scene, config)
    X = simulate_frames_spring_mass(scene, config, frames=max(frames) + 1, sim=sim)
    params = {"model": "spring-mass", "stiffness": config.stiffness, "damping": config.damping,
              "density": scene.material.density}
    return evaluate(spring_mass_scene(scene, sim), params, scene.table_friction, obs, views, positions=X, **kwargs)
