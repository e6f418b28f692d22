"""Plots for the examples: learning curves against baselines, labelled rollout strips (matplotlib, Agg backend)."""

from __future__ import annotations

from typing import Mapping, Optional, Sequence, Tuple

import numpy as np

__all__ = ["plot_learning_curve", "save_rollout_strip", "save_transfer_chart"]


def _bin_means(steps: np.ndarray, values: np.ndarray, bins: int = 25):
    """(bin centres, mean of ``values`` per bin) over bins of environment steps that hold an episode."""
    edges = np.linspace(steps.min(), steps.max() + 1e-9, min(bins, max(2, len(np.unique(steps)))) + 1)
    idx = np.clip(np.digitize(steps, edges) - 1, 0, len(edges) - 2)
    have = np.array([np.any(idx == b) for b in range(len(edges) - 1)])
    means = np.array([values[idx == b].mean() if have[b] else np.nan for b in range(len(edges) - 1)])
    return 0.5 * (edges[:-1] + edges[1:])[have], means[have]


def plot_learning_curve(path: str, steps: Sequence[float], returns: Sequence[float], *,
                        baselines: Optional[Mapping[str, float]] = None, title: str = "",
                        successes: Optional[Sequence[bool]] = None,
                        baseline_success: Optional[Mapping[str, float]] = None) -> None:
    """Episode return against environment steps, smoothed, with horizontal baseline lines; saved to ``path``.

    With ``successes`` (one flag per episode) a second panel shows the success rate per bin of environment
    steps, with ``baseline_success`` (name -> rate in [0, 1]) as horizontal lines.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 2 if successes is not None else 1
    fig, axes = plt.subplots(1, panels, figsize=(6 * panels, 4), dpi=100, squeeze=False)
    ax = axes[0, 0]
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    if len(returns):
        # at most 5000 episodes drawn (a long run ends hundreds of thousands), every one in the means
        shown = np.random.default_rng(0).permutation(len(returns))[:5000]
        ax.plot(steps[shown], returns[shown], ".", alpha=0.15, color="C0", markersize=3,
                label="episodes" if len(shown) == len(returns) else f"episodes ({len(shown)} of {len(returns)})")
        # mean return per bin of environment steps: batched envs finish many episodes at once, so a
        # running mean over episodes would mostly trace single batches
        centres, means = _bin_means(steps, returns)
        ax.plot(centres, means, "-o", color="k", lw=2.5, markersize=4, label="mean per step bin")
    for i, (name, value) in enumerate((baselines or {}).items()):
        ax.axhline(value, color=f"C{i + 1}", ls="--", label=f"{name} ({value:.3f})")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(title if panels == 1 else "episode return")
    if ax.get_legend_handles_labels()[0]:  # nothing to list before the first episode ends
        ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    if successes is not None:
        ax = axes[0, 1]
        flags = np.asarray(successes, float)
        if len(flags) != len(steps):
            raise ValueError(f"plot_learning_curve: {len(flags)} success flags for {len(steps)} episodes")
        if len(flags):
            centres, rates = _bin_means(steps, flags)
            ax.plot(centres, 100.0 * rates, "-o", color="k", lw=2.5, markersize=4,
                    label="training episodes, per step bin")
        for i, (name, value) in enumerate((baseline_success or {}).items()):
            ax.axhline(100.0 * value, color=f"C{i + 1}", ls="--", label=f"{name} ({100.0 * value:.0f} %)")
        ax.set_ylim(-3, 103)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("success rate [%]")
        ax.set_title("success rate (Chamfer below the task's threshold)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3)
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def save_rollout_strip(path: str, rows: Mapping[str, Sequence[Tuple[np.ndarray, int, float]]], *, view_lower,
                       view_upper, title: str, max_frames: int = 5, metric: str = "Chamfer to target") -> None:
    """Rollouts side by side, one row each, saved to ``path``: evenly picked frames of ``render()``
    (:func:`empm_gym.viz.render_scene`), each split into its top view (x, y) and side view (x, z) with axes
    in metres, titled with the step and ``metric`` (given in metres, shown in mm), and a legend of the
    colours (object, target, closed and open end-effectors, table).

    ``rows`` maps a label (for instance "MPC (MPPI)", "zero action") to frames ``(image, step, metric_m)``;
    ``view_lower`` / ``view_upper`` are the rendered box (``env.unwrapped.view_box()``).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from .render import _CLOSED, _OPEN, _TABLE, _TARGET

    if not rows or any(len(f) == 0 for f in rows.values()):
        raise ValueError("save_rollout_strip: every row needs at least one frame")
    lo, hi = np.asarray(view_lower, float), np.asarray(view_upper, float)
    picks = {k: np.unique(np.linspace(0, len(f) - 1, min(max_frames, len(f))).round().astype(int))
             for k, f in rows.items()}
    ncol = max(len(v) for v in picks.values())
    fig, axes = plt.subplots(len(rows), 2 * ncol, figsize=(2.3 * 2 * ncol, 2.6 * len(rows) + 0.9), squeeze=False)
    for r, (label, frames) in enumerate(rows.items()):
        for c in range(ncol):
            ax_top, ax_side = axes[r, 2 * c], axes[r, 2 * c + 1]
            if c >= len(picks[label]):
                ax_top.axis("off")
                ax_side.axis("off")
                continue
            img, step, value = frames[picks[label][c]]
            img = np.asarray(img)
            size = img.shape[0]
            ax_top.imshow(img[:, :size], extent=(lo[0], hi[0], lo[1], hi[1]), aspect="equal")
            ax_side.imshow(img[:, -size:], extent=(lo[0], hi[0], lo[2], hi[2]), aspect="equal")
            ax_top.set_title(f"{label}\nstep {step}: {metric} {1e3 * value:.1f} mm" if c == 0
                             else f"step {step}: {1e3 * value:.1f} mm", fontsize=8)
            ax_side.set_title("side view", fontsize=8)
            ax_top.set_xlabel("x [m]", fontsize=7)
            ax_side.set_xlabel("x [m]", fontsize=7)
            ax_top.set_ylabel("y [m]", fontsize=7)
            ax_side.set_ylabel("z [m]", fontsize=7)
            for ax in (ax_top, ax_side):
                ax.tick_params(labelsize=6)
    handles = [Patch(color=np.array([50, 85, 175]) / 255, label="object (darker = higher)"),
               Patch(color=_TARGET / 255, label="target"), Patch(color=_CLOSED / 255, label="closed gripper / tool"),
               Patch(color=_OPEN / 255, label="open gripper / tool"), Patch(color=_TABLE / 255, label="table")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def save_transfer_chart(path: str, result: Mapping) -> None:
    """Bar chart of a real-to-sim-to-real comparison (:func:`empm_gym.planning.transfer.compare_materials`):
    per target, the Chamfer distance at rest and after each model's plan on the real object, in mm, with
    the task's success threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    if not rows:
        raise ValueError("save_transfer_chart: the result has no rows")
    seeds = sorted({r["seed"] for r in rows})
    labels = list(dict.fromkeys(r["model"] for r in rows))
    by = {(r["seed"], r["model"]): r for r in rows}
    width = 0.8 / (len(labels) + 1)
    x = np.arange(len(seeds))
    fig, ax = plt.subplots(figsize=(max(6.5, 1.2 + 0.5 * len(seeds) * (len(labels) + 1)), 4.2))
    start = [by[(s, labels[0])]["chamfer_start_m"] * 1000 for s in seeds]
    ax.bar(x - 0.4 + width / 2, start, width, color="0.8", label="at rest (start)")
    for i, label in enumerate(labels):
        ax.bar(x - 0.4 + width * (i + 1.5), [by[(s, label)]["chamfer_real_m"] * 1000 for s in seeds], width,
               label=f"planned with {label}")
    ax.axhline(result["success_chamfer_m"] * 1000, color="k", ls="--", lw=1, label="success threshold")
    ax.set_xticks(x, [f"target {s}" for s in seeds])
    ax.set_ylabel("Chamfer to target, real object [mm]")
    ax.set_title(f"{result['env']}: open-loop plans executed on the real object", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")  # keeps the title and the legend beside the axes
    plt.close(fig)
