"""Plots (PNG, matplotlib Agg) and rerun recordings (.rrd) of fits and evaluations."""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np

__all__ = ["plot_fit", "plot_metrics", "plot_online", "save_rrd"]


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path) -> Path:
    """Lay out, write (creating folders) and close a figure; returns the path."""
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def _with_unit(name: str) -> str:
    """``name [unit]`` of a base or effect parameter (the registry's SI unit), ``name`` for any other."""
    from empm_gym.sim.effects import parameter

    try:
        return f"{name} [{parameter(name).unit}]"
    except ValueError:
        return name


def plot_fit(result, path) -> Path:
    """Loss curve and parameter trajectories of a :class:`~.offline.FitResult` (one panel per parameter)."""
    from .uncertainty import uncertainty_bound

    plt = _plt()
    names = list(result.params)
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(4.2 * (1 + len(names)), 3.4), squeeze=False)
    ax = axes[0, 0]
    it = np.arange(len(result.loss_history))
    ax.semilogy(it, result.loss_history, "o-", ms=3)
    ax.set_xlabel("generation" if result.method == "cmaes" else "iteration")
    ax.set_ylabel("loss")
    ax.set_title(f"{result.method}: loss ({result.wall_time_s:.1f} s)")
    ax.grid(alpha=0.3)
    for i, n in enumerate(names):
        a = axes[0, i + 1]
        vals = [p[n] for p in result.param_history]
        a.plot(it, vals, "o-", ms=3, label="evaluated")
        if result.method == "cmaes" and "mean_history" in result.extra:
            a.plot(it, [p[n] for p in result.extra["mean_history"]], "--", label="CMA-ES mean")
        a.axhline(result.params[n], color="k", lw=0.8, ls=":", label=f"fit {result.params[n]:.4g}")
        u = (result.extra.get("uncertainty") or {}).get(n)
        title = n
        if u is not None:
            lo, hi = u["interval"]
            ylo, yhi = a.get_ylim()
            a.axhspan(max(lo, min(ylo, result.params[n]) * 0.5 if n != "nu" else -1.0),
                      min(hi, max(yhi, result.params[n]) * 2.0 if n != "nu" else 0.5), color="tab:green",
                      alpha=0.2, label=f"{100 * u['level']:.0f} % interval [{lo:.3g}, {hi:.3g}]")
            if not u["determined"]:
                bound = uncertainty_bound(u, ".3g")
                title += f"\n(NOT DETERMINED: {bound})" if bound else " (NOT DETERMINED: see fit.identifiability)"
        if n in ("E", "yield_stress", "density"):
            a.set_yscale("log")
        a.set_title(title, fontsize=8 if "\n" in title else 9)
        a.set_ylabel(_with_unit(n))
        a.set_xlabel("iteration")
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    return _save(plt, fig, path)


def plot_metrics(per_frame: Dict[str, Sequence[float]], frames: Sequence[int], path, title: str = "") -> Path:
    """One panel per metric over time (frames)."""
    plt = _plt()
    keys = [k for k in per_frame if len(per_frame[k])]
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 3.0), squeeze=False)
    for a, k in zip(axes[0], keys):
        a.plot(frames, per_frame[k], "o-", ms=3)
        a.set_title(k)
        a.set_xlabel("frame")
        a.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    return _save(plt, fig, path)


def plot_online(result: dict, path) -> Path:
    """Chamfer and mask loss per frame with and without online updates, and the parameter trajectory."""
    plt = _plt()
    w, wo = result["with_updates"], result["without_updates"]
    keys = [k for k in ("chamfer", "mask_loss") if k in w[0]]
    names = list(result["params"])
    fig, axes = plt.subplots(1, len(keys) + len(names), figsize=(4 * (len(keys) + len(names)), 3.2), squeeze=False)
    fr = [r["frame"] for r in w]
    upd = [r["frame"] for r in w if r["updated"]]
    for a, k in zip(axes[0], keys):
        a.plot(fr, [r[k] for r in w], label="with updates")
        a.plot(fr, [r[k] for r in wo], label="without updates")
        for u in upd:
            a.axvline(u, color="g", alpha=0.2)
        a.set_title(k)
        a.set_xlabel("frame")
        a.legend(fontsize=7)
        a.grid(alpha=0.3)
    for a, n in zip(axes[0][len(keys):], names):
        a.plot(fr, [r[n] for r in w], "o-", ms=2)
        a.set_title(n)
        a.set_xlabel("frame")
        a.grid(alpha=0.3)
    return _save(plt, fig, path)


def save_rrd(path, sim_positions: np.ndarray, obs_points: Sequence[np.ndarray], fps: float, *,
             ee_positions: Optional[np.ndarray] = None, ee_configs: Optional[Sequence] = None,
             ee_orientations: Optional[np.ndarray] = None, particle_radius: float = 0.003,
             scalars: Optional[Dict[str, Sequence[float]]] = None,
             app_id: str = "empm_identification", particle_colors: Optional[np.ndarray] = None,
             second_sim: Optional[np.ndarray] = None, second_name: str = "simulated_2") -> Path:
    """Write a rerun recording: simulated particles ``sim`` [T, N, 3] over measured points per frame.

    Entities: ``world/simulated``, ``world/measured``, ``world/ee`` (the end-effectors at ``ee_positions``
    [T, K, 3]: each drawn as its shape from ``ee_configs``, turned by ``ee_orientations`` [T, K, 4] (x, y, z, w);
    as 1 cm points without configs), ``world/<second_name>`` (a second
    simulation [T, N, 3] to compare, e.g. the model with an added effect) and scalars ``metrics/<name>``;
    the timeline ``frame`` (sequence) and ``time`` (seconds).
    """
    import rerun as rr

    from ..viz.rerun_log import log_end_effectors

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(app_id)
    rec.save(str(p))
    T = min(len(sim_positions), len(obs_points))
    cols = None
    if particle_colors is not None:
        cols = (np.clip(particle_colors, 0, 1) * 255).astype(np.uint8)
    for t in range(T):
        rec.set_time("frame", sequence=t)
        rec.set_time("time", duration=t / fps)
        x = np.asarray(sim_positions[t], np.float32)
        if np.all(np.isfinite(x)):
            rec.log("world/simulated", rr.Points3D(x, radii=particle_radius,
                                                   colors=cols if cols is not None else [70, 130, 230]))
        if second_sim is not None and t < len(second_sim) and np.all(np.isfinite(second_sim[t])):
            rec.log(f"world/{second_name}", rr.Points3D(np.asarray(second_sim[t], np.float32), radii=particle_radius,
                                                        colors=[200, 70, 200]))
        rec.log("world/measured", rr.Points3D(np.asarray(obs_points[t], np.float32), radii=particle_radius * 0.5,
                                              colors=[235, 120, 40]))
        if ee_positions is not None and t < len(ee_positions) and len(ee_positions[t]):
            if ee_configs is not None:
                log_end_effectors(rec, "world/ee", ee_configs, ee_positions[t],
                                  None if ee_orientations is None else ee_orientations[t])
            else:
                rec.log("world/ee", rr.Points3D(np.asarray(ee_positions[t], np.float32), radii=0.01,
                                                colors=[90, 200, 90]))
        for k, v in (scalars or {}).items():
            if t < len(v) and v[t] is not None and np.isfinite(v[t]):
                rec.log(f"metrics/{k}", rr.Scalars(float(v[t])))
    rec.flush()
    try:
        rec.disconnect()
    except Exception:  # pragma: no cover - older rerun
        pass
    return p
