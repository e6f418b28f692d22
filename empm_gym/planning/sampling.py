"""Sampling planners, CEM and MPPI, that evaluate all their samples as one batched rollout.

Each iteration copies the given state into every world of a :class:`BatchedCore` with
``num_envs = samples`` and steps all of them at once with their own action sequences; a sequence's
score is its summed environment reward (the progress towards the target, see
:mod:`empm_gym.envs.core`). A diverged sample scores -inf. Both planners keep their current mean
as sample 0, so the returned sequence never scores below the best one evaluated.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .base import Planner

__all__ = ["SamplingPlanner", "CEMPlanner", "MPPIPlanner", "colored_noise"]


def colored_noise(rng: np.random.Generator, shape, beta: float) -> np.ndarray:
    """Gaussian noise of unit variance, coloured along axis -2 (time) of ``shape`` [..., H, A]: its power
    spectrum falls as 1 / f^``beta`` (0: white; 1: pink; 2: brown, a random walk's smoothness). Long, smooth
    sweeps get the exploration that white noise spreads over jitter (iCEM, Pinneri et al. 2020, found
    beta 2-4 best for manipulation). White noise filtered in the frequency domain (the constant component
    weighted as the lowest frequency), scaled so that every time step has unit variance."""
    *lead, H, A = shape
    if beta == 0.0 or H < 2:
        return rng.standard_normal(shape)
    f = np.fft.rfftfreq(H)
    f[0] = f[1]
    amp = f ** (-0.5 * float(beta))
    x = np.fft.irfft(np.fft.rfft(rng.standard_normal(shape), axis=-2) * amp[:, None], n=H, axis=-2)
    # the filter is circular: each step's variance is the mean of the squared gains over the full spectrum
    full = np.concatenate([amp, amp[1:(H + 1) // 2][::-1]])
    return x / np.sqrt(np.mean(full ** 2))


class SamplingPlanner(Planner):
    """Shared machinery: a batched core of ``samples`` worlds and sequence evaluation.

    ``tail`` [k, action_dim] (in [-1, 1]) is a fixed action sequence run after every candidate when it is
    scored, neither optimised nor returned: for instance lifting a pressing tool, so that the score is
    that of the shape the object keeps once released (its spring-back included), which is what an
    open-loop plan executed on the real object ends with.

    ``noise_beta`` colours the perturbations along the horizon (:func:`colored_noise`; 0 is white noise).
    """

    def __init__(self, task, *, samples: int = 32, iterations: int = 5, noise: float = 0.5,
                 env_kwargs=None, seed: Optional[int] = 0, tail: Optional[np.ndarray] = None,
                 noise_beta: float = 0.0):
        super().__init__(task, env_kwargs=env_kwargs, seed=seed)
        if samples < 2:
            raise ValueError(f"samples must be >= 2, got {samples!r}")
        if iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations!r}")
        if not noise > 0:
            raise ValueError(f"noise must be > 0 (std of the action perturbation, action units), got {noise!r}")
        if not (np.isfinite(noise_beta) and 0.0 <= noise_beta <= 6.0):
            raise ValueError(f"noise_beta must lie in [0, 6] (0 white, 2 brown noise), got {noise_beta!r}")
        self.samples, self.iterations, self.noise = int(samples), int(iterations), float(noise)
        self.noise_beta = float(noise_beta)
        self.core = self._core(self.samples)
        self.action_dim = self.core.action_dim
        self.best_return = -np.inf
        self.tail = np.zeros((0, self.action_dim), np.float32)
        if tail is not None:
            t = np.asarray(tail, np.float32)
            if t.ndim != 2 or t.shape[1] != self.action_dim or not np.all(np.isfinite(t)) or np.abs(t).max() > 1:
                raise ValueError(f"tail must be finite actions in [-1, 1] of shape [k, {self.action_dim}], "
                                 f"got shape {t.shape}")
            self.tail = t

    def evaluate(self, state: dict, actions: np.ndarray) -> np.ndarray:
        """Summed reward [samples] of the sequences ``actions`` [samples, H, A], all from ``state``, each
        followed by the planner's ``tail``."""
        S, H, A = actions.shape
        if S != self.samples or A != self.action_dim:
            raise ValueError(f"evaluate: actions must be [{self.samples}, H, {self.action_dim}], got {actions.shape}")
        core = self.core
        core.set_world_states(list(range(S)), [state] * S)
        total = np.zeros(S)
        dead = np.zeros(S, bool)
        tail = np.broadcast_to(self.tail[None], (S, *self.tail.shape))
        seq = np.concatenate([np.clip(actions, -1, 1).astype(np.float32), tail], axis=1)
        for t in range(seq.shape[1]):
            r, term, trunc, info = core.step(seq[:, t])
            total += np.where(dead, 0.0, r)
            dead |= info["diverged"]
        total[dead] = -np.inf
        return total

    def _sample(self, mean, std, S):
        eps = colored_noise(self.rng, (S, *mean.shape), self.noise_beta) * std
        acts = np.clip(mean[None] + eps, -1.0, 1.0)
        acts[0] = mean
        return acts


class CEMPlanner(SamplingPlanner):
    """Cross-entropy method: refit a diagonal Gaussian to the ``elite_frac`` best sequences each iteration."""

    def __init__(self, task, *, samples: int = 32, iterations: int = 5, noise: float = 0.5,
                 elite_frac: float = 0.2, momentum: float = 0.1, env_kwargs=None, seed: Optional[int] = 0,
                 tail: Optional[np.ndarray] = None, noise_beta: float = 0.0):
        super().__init__(task, samples=samples, iterations=iterations, noise=noise, env_kwargs=env_kwargs, seed=seed,
                         tail=tail, noise_beta=noise_beta)
        if not 0 < elite_frac <= 1:
            raise ValueError(f"elite_frac must lie in (0, 1], got {elite_frac!r}")
        self.elites = max(2, int(round(elite_frac * self.samples)))
        self.momentum = float(momentum)

    def plan(self, state, horizon, init=None):
        H = self._check_horizon(horizon)
        mean = self._init(init, H, self.action_dim)
        std = np.full_like(mean, self.noise)
        best, best_r = mean.copy(), -np.inf
        for _ in range(self.iterations):
            acts = self._sample(mean, std, self.samples)
            R = self.evaluate(state, acts)
            i = int(np.argmax(R))
            if R[i] > best_r:
                best, best_r = acts[i].copy(), float(R[i])
            elite = acts[np.argsort(-R)[: self.elites]]
            mean = self.momentum * mean + (1 - self.momentum) * elite.mean(0)
            std = self.momentum * std + (1 - self.momentum) * elite.std(0) + 1e-3
        self.best_return = best_r
        return best.astype(np.float32)


class MPPIPlanner(SamplingPlanner):
    """Model-predictive path integral: the mean moves to the exp(R / temperature)-weighted average.

    ``temperature`` is relative: returns are scaled by their spread before weighting, so it needs no
    tuning across tasks (the EMPM reward scale is the same everywhere anyway).
    """

    def __init__(self, task, *, samples: int = 32, iterations: int = 5, noise: float = 0.5,
                 temperature: float = 0.1, env_kwargs=None, seed: Optional[int] = 0, tail: Optional[np.ndarray] = None,
                 noise_beta: float = 0.0):
        super().__init__(task, samples=samples, iterations=iterations, noise=noise, env_kwargs=env_kwargs, seed=seed,
                         tail=tail, noise_beta=noise_beta)
        if not temperature > 0:
            raise ValueError(f"temperature must be > 0, got {temperature!r}")
        self.temperature = float(temperature)

    def plan(self, state, horizon, init=None):
        H = self._check_horizon(horizon)
        mean = self._init(init, H, self.action_dim)
        best, best_r = mean.copy(), -np.inf
        for _ in range(self.iterations):
            acts = self._sample(mean, self.noise, self.samples)
            R = self.evaluate(state, acts)
            ok = np.isfinite(R)
            if not np.any(ok):
                break
            i = int(np.argmax(np.where(ok, R, -np.inf)))
            if R[i] > best_r:
                best, best_r = acts[i].copy(), float(R[i])
            spread = max(float(np.ptp(R[ok])), 1e-9)
            w = np.where(ok, np.exp((np.where(ok, R, 0.0) - R[i]) / (self.temperature * spread)), 0.0)
            w /= w.sum()
            mean = np.clip(np.tensordot(w, acts, axes=1), -1.0, 1.0)
        self.best_return = best_r
        return best.astype(np.float32)
