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
        ax.plot(steps, returns, ".", alpha=0.3, color="C0", label="episodes")
        k = max(1, len(returns) // 20)
        smooth = np.convolve(returns, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, color="C0", label=f"mean of {k}")
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
