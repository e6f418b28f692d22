"""How far to trust a fit or a comparison of fits, from the data alone (one place for the noise estimates).

- :func:`measurement_noise`: the depth noise of a recording, as the robust spread of observed points
  about their local surface (a plane through their nearest neighbours). It is the floor below which no
  model can bring a point-to-surface residual.
- :func:`paired_gain_test`: does model B predict held-out frames better than model A by more than the
  frame-to-frame noise explains? A moving-block bootstrap over frames of the paired per-frame
  differences (frames of a recording are correlated, so whole blocks are resampled), with a penalty
  per added parameter. The doctor's "explains more than noise" test is this function.

Assumptions, stated: the per-frame errors of a recording form a stationary, weakly dependent sequence
over the held-out frames (blocks of ``block`` frames capture the dependence), and the frames held out
were never used to fit either model.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np

__all__ = ["measurement_noise", "paired_gain_test", "block_bootstrap_indices"]


def measurement_noise(points: Sequence[np.ndarray], *, k: int = 60, max_points: int = 3000, seed: int = 0) -> float:
    """Robust standard deviation [m] of observed points about their local surface, over all frames given.

    For each (subsampled) point, a plane is fitted to its ``k`` nearest neighbours; the distance of the
    point to that plane is its residual. The median absolute residual / 0.6745 estimates the noise's
    standard deviation. The plane fit absorbs part of the noise when it is comparable with the point spacing
(neighbours are chosen in 3-D): 0.92-1.0x the true sigma for noise up to 0.8x the spacing, 0.82x at 1.5x.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    res = []
    for p in points:
        p = np.asarray(p, np.float64)
        if len(p) <= k:
            continue
        q = p if len(p) <= max_points else p[rng.choice(len(p), max_points, replace=False)]
        _, idx = cKDTree(p).query(q, k=k + 1)
        nb = p[idx[:, 1:]]
        c = nb.mean(1, keepdims=True)
        cov = np.einsum("ski,skj->sij", nb - c, nb - c)
        _, v = np.linalg.eigh(cov)
        n = v[:, :, 0]
        res.append(np.abs(np.einsum("si,si->s", q - c[:, 0], n)))
    if not res:
        raise ValueError("measurement_noise: no frame has enough observed points to estimate the noise")
    return float(np.median(np.concatenate(res)) / 0.6745)


def block_bootstrap_indices(n: int, block: int, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """``[n_boot, n]`` frame indices of a moving-block bootstrap (blocks of ``block`` consecutive frames)."""
    block = int(max(1, min(block, n)))
    starts = rng.integers(0, n - block + 1, size=(n_boot, -(-n // block)))
    idx = (starts[:, :, None] + np.arange(block)[None, None, :]).reshape(n_boot, -1)[:, :n]
    return idx


def paired_gain_test(base: Sequence[float], candidate: Sequence[float], *, added_params: int = 1,
                     penalty_per_param: float = 0.05, block: Optional[int] = None, n_boot: int = 2000,
                     level: float = 0.95, seed: int = 0) -> Dict[str, float]:
    """Held-out gain of ``candidate`` over ``base`` (per-frame errors of the same frames, lower is better).

    Returns ``gain`` (relative: 1 - mean(candidate) / mean(base)), ``gain_abs`` (mean difference, error
    units), ``lower`` / ``upper`` (bootstrap ``level`` interval of the relative gain), ``threshold``
    (``penalty_per_param * added_params``, the relative gain an added parameter must pay for) and
    ``significant``: the interval's lower end lies above 0 and the gain above the threshold.
    """
    a = np.asarray(base, np.float64)
    b = np.asarray(candidate, np.float64)
    if a.shape != b.shape or a.ndim != 1 or len(a) < 2:
        raise ValueError(f"paired_gain_test: need two equal-length per-frame error series of >= 2 frames, got "
                         f"{a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return {"gain": float("nan"), "gain_abs": float("nan"), "lower": float("nan"), "upper": float("nan"),
                "threshold": penalty_per_param * added_params, "significant": False}
    n = len(a)
    block = int(block or max(2, round(n ** (1.0 / 3.0) * 1.5)))
    idx = block_bootstrap_indices(n, block, n_boot, np.random.default_rng(seed))
    ma, mb = a[idx].mean(1), b[idx].mean(1)
    rel = 1.0 - mb / np.maximum(ma, 1e-300)
    lo, hi = np.quantile(rel, [(1.0 - level) / 2.0, 1.0 - (1.0 - level) / 2.0])
    gain = float(1.0 - b.mean() / max(a.mean(), 1e-300))
    thr = float(penalty_per_param * added_params)
    return {"gain": gain, "gain_abs": float(a.mean() - b.mean()), "lower": float(lo), "upper": float(hi),
            "threshold": thr, "significant": bool(lo > 0.0 and gain > thr)}
