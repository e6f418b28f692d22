"""Plots for the examples: learning curves against baselines (matplotlib, Agg backend)."""

from __future__ import annotations

from typing import Mapping, Optional, Sequence

import numpy as np

__all__ = ["plot_learning_curve"]


def plot_learning_curve(path: str, steps: Sequence[float], returns: Sequence[float], *,
                        baselines: Optional[Mapping[str, float]] = None, title: str = "") -> None:
    """Episode return against environment steps, smoothed, with horizontal baseline lines; saved to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    if len(returns):
        ax.plot(steps, returns, ".", alpha=0.15, color="C0", markersize=3, label="episodes")
        # mean return per bin of environment steps: batched envs finish many episodes at once, so a
        # running mean over episodes would mostly trace single batches
        edges = np.linspace(steps.min(), steps.max() + 1e-9, min(25, max(2, len(np.unique(steps)))) + 1)
        idx = np.clip(np.digitize(steps, edges) - 1, 0, len(edges) - 2)
        have = np.array([np.any(idx == b) for b in range(len(edges) - 1)])
        means = np.array([returns[idx == b].mean() if have[b] else np.nan for b in range(len(edges) - 1)])
        centres = 0.5 * (edges[:-1] + edges[1:])
        ax.plot(centres[have], means[have], "-o", color="C0", lw=2.5, markersize=4, label="mean per step bin")
    for i, (name, value) in enumerate((baselines or {}).items()):
        ax.axhline(value, color=f"C{i + 1}", ls="--", label=f"{name} ({value:.3f})")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
