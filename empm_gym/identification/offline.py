"""Offline identification: fit material parameters so that the simulated scene reproduces the observations.

Loss (the paper's, averaged over the frames used instead of summed, which only rescales it):

    L = l_dist * mean_t Chamfer(X_hat_t, X_obs_t) + l_trk * mean_t mean_{j visible} |X_hat_{t,a(j)} - X_trk_{t,j}|^2

over frames t = 1 .. F-1 (frame 0 is the initial state), where a(j) is the frame-0 particle nearest to
tracked point j (tracks not visible at frame 0 are not used). Two methods:

- ``method="adam"``: gradients through the differentiable simulator (:func:`empm_gym.autograd.simulate`)
  and torch AdamW in the unconstrained space of :class:`ParamSpace` (log space for positive
  parameters, E normalised by 1e6; a sigmoid for nu). When a step made the loss worse, the optimiser
  returns to the best point so far, drops Adam's momentum and halves the step (regrown by 25 % per
  improving step, up to ``lr``), so it settles into the minimum instead of orbiting it.
- ``method="cmaes"``: CMA-ES (the ``cma`` package) on the forward simulator; each generation's whole
  population is simulated as batched worlds in one simulation.

The result is the evaluated parameter vector with the lowest loss.

Interruption and resumption: ``identify(..., stop=...)`` checks the stop request (a
:class:`~empm_gym.identification.interrupt.StopRequest`, ``threading.Event`` or callable) before every
iteration and returns early with ``FitResult.complete`` False; its ``extra["resume"]`` (saved in the
material file's ``fit`` section) holds what ``identify(..., resume=fit_section)`` needs to continue to the
same answer as an uninterrupted fit: Adam's point, moments, step scale and best iterate; for CMA-ES every
generation's population losses, from which the strategy (and numpy's global random state that pycma
draws from) is rebuilt by replaying ask/tell without simulating. The settings and a digest of the
observations and scene are stored beside it, and resuming with others raises :class:`ResumeError`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from empm_gym.sim import MaterialConfig, Rollout, SimulationDiverged, SolverConfig, SolverMPM, read_material, write_material
from empm_gym.sim.effects import PARAMETERS, parameter
from empm_gym.sim.material_file import material_dict

from .losses import chamfer_distance, chamfer_frames, chamfer_frames_torch, pad_frames, tracking_loss
from .problem import PARAM_NAMES, Observations, ParamSpace, Scene, _ForwardSim, run_together, substeps_for

__all__ = ["identify", "FitResult", "Objective", "ResumeError", "read_resume_state", "default_bounds",
           "surface_embedding", "body_surface", "METHODS", "OBSERVATION_MODELS"]

METHODS = ("adam", "cmaes")
_DIVERGED_LOSS = 1.0e3
_RESUME_FORMAT = 1


class ResumeError(ValueError):
    """A fit cannot be resumed from the given state; the message says why."""


def default_bounds(init: Dict[str, float]) -> Dict[str, Tuple[float, float]]:
    """Search box around the starting values, from the registry (:mod:`empm_gym.sim.effects`).

    E, density, yield_stress: a factor 10 either way; friction likewise (at least 1e-3 to 0.05); nu
    (-0.9, 0.49); the other positive ("log") effect parameters the registry's search box intersected with a
    factor 10 either way, always holding the start; "linear" ones (stiffness slopes) the registry's search
    box widened to hold the start.
    """
    out = {}
    for n, v in init.items():
        p = parameter(n)
        if n == "nu":
            out[n] = (-0.9, 0.49)
        elif n == "friction":
            out[n] = (max(v / 10.0, 1e-3), max(v * 10.0, 0.05))
        elif n in ("E", "density", "yield_stress"):
            out[n] = (v / 10.0, v * 10.0)
        elif p.transform == "log":
            lo, hi = p.search
            lo, hi = min(v, max(v / 10.0, lo)), max(v, min(v * 10.0, hi))
            if lo >= hi:
                lo, hi = v / 10.0, v * 10.0
            out[n] = (max(lo, p.valid[0]) if p.valid[0] > 0 else lo, min(hi, p.valid[1]))
        else:
            lo, hi = p.search
            out[n] = (max(min(lo, v), p.valid[0]), min(max(hi, v), p.valid[1]))
    return out


OBSERVATION_MODELS = ("surface", "particles")


def surface_embedding(points0: np.ndarray, particles0: np.ndarray, k: int = 12) -> Tuple[np.ndarray, np.ndarray]:
    """Carry points observed at frame 0 with the simulated body: ``(index [S, k], weight [S, k])`` such that
    ``sum_j weight[s, j] * X[index[s, j]]`` is point s on the deformed body X [N, 3].

    Each point p0 is tied to its ``k`` nearest frame-0 particles x_j with Gaussian weights w_j (width
    twice the median nearest-particle distance); its position follows the weighted least-squares affine
    map of those particles from frame 0 to now, c + A (p0 - c0), which is linear in the particle
    positions. At frame 0 it reproduces p0 exactly, also when p0 lies outside the particles (the
    observed surface is about half a particle spacing outside the outermost particle centres).
    """
    from scipy.spatial import cKDTree

    p0 = np.asarray(points0, np.float64).reshape(-1, 3)
    x0 = np.asarray(particles0, np.float64).reshape(-1, 3)
    k = int(min(k, len(x0)))
    dist, idx = cKDTree(x0).query(p0, k=k)
    dist, idx = dist.reshape(len(p0), k), idx.reshape(len(p0), k)
    h = 2.0 * float(np.median(dist[:, 0])) + 1e-9
    w = np.exp(-(dist / h) ** 2)
    w /= w.sum(1, keepdims=True)
    nb = x0[idx]
    c0 = np.einsum("sk,skd->sd", w, nb)
    r0 = nb - c0[:, None]
    M = np.einsum("sk,ski,skj->sij", w, r0, r0)
    tr = np.trace(M, axis1=1, axis2=2)[:, None, None]
    Minv = np.linalg.inv(M + 1e-6 * tr * np.eye(3) + 1e-18 * np.eye(3))
    # p = c + sum_j w_j (x_j - c) (r0_j . Minv off0) = sum_j (w_j (1 - G) + g_j) x_j, g_j = w_j r0_j . Minv off0
    g = w * np.einsum("ski,sij,sj->sk", r0, Minv, p0 - c0)
    a = w * (1.0 - g.sum(1, keepdims=True)) + g
    return idx.astype(np.int64), a


def body_surface(particles0: np.ndarray, radius: float = 1.8, shift: float = 0.25, normals: bool = False):
    """Points on the surface of a body of particles [N, 3] (m): each boundary particle moved half the median
    particle spacing s outward, where the observed surface of a body lies (:func:`surface_embedding`).

    A particle is on the boundary when the centroid of its neighbours within ``radius`` s (the nearest 32; a
    cubic or body-centred lattice holds 26 within 1.8 spacings) lies more than ``shift`` s from it (inside a body
    the neighbours surround it and their centroid is the particle itself; on a face of a lattice it lies half a
    spacing inward); outward is away from that centroid. Thin bodies, whose particles are mostly on the
    boundary, need no count of what a full neighbourhood holds. With ``normals``, ``(points, outward unit
    normals)``."""
    from scipy.spatial import cKDTree

    x = np.asarray(particles0, np.float64).reshape(-1, 3)
    if len(x) < 2:
        raise ValueError(f"body_surface: a body of {len(x)} particles has no surface to find")
    tree = cKDTree(x)
    s = float(np.median(tree.query(x, k=2)[0][:, 1]))
    dist, idx = tree.query(x, k=min(len(x), 32), distance_upper_bound=radius * s)
    near = np.isfinite(dist)
    centre = (x[np.where(near, idx, 0)] * near[..., None]).sum(1) / near.sum(1)[:, None]
    out = x - centre
    norm = np.linalg.norm(out, axis=1)
    edge = norm > shift * s
    n = out[edge] / norm[edge, None]
    return (x[edge] + 0.5 * s * n, n) if normals else x[edge] + 0.5 * s * n


class Objective:
    """The identification loss of a scene against observations on the first ``frames`` frames.

    ``observation="surface"`` compares the observations with the frame-0 observed surface
    carried by the simulated body (:func:`surface_embedding`): the cameras see the object's surface, which
    lies outside the particle centres, so comparing observed points with particle centres directly
    (``observation="particles"``) favours bodies that bulge out towards the surface (a softer material).
    Tracked points are carried the same way from their frame-0 position.

    ``unseen_surface=True`` (with ``observation="surface"``): an observed point may also lie on surface the
    cameras did not see at frame 0 (the underside of a body lifted later, a side turned towards a camera), which
    no carried frame-0 point stands for. The distance from the observed points to the simulation is then taken
    to the nearer of the carried points and the simulated body's own surface (:func:`body_surface` at frame 0,
    carried the same way); the simulated-to-observed half stays with the carried points, as the rest of the
    body's surface may be hidden from the cameras.

    A frame that holds no observed points (:attr:`~.problem.Observations.seen`: the object wholly hidden) is not
    scored: its Chamfer term is left out of the loss's mean (NaN in :meth:`per_frame` and :meth:`chamfer`) and
    its tracks count as occluded.
    """

    def __init__(self, scene: Scene, obs: Observations, frames: int, *, l_dist: float = 1.0, l_trk: float = 100.0,
                 chamfer: str = "both", max_points: int = 2000, seed: int = 0, observation: str = "surface",
                 unseen_surface: bool = False):
        if frames < 2:
            raise ValueError(f"frames must be >= 2 (frame 0 is the initial state), got {frames}")
        if frames > obs.num_frames:
            raise ValueError(f"frames={frames} exceeds the {obs.num_frames} observed frames")
        if observation not in OBSERVATION_MODELS:
            raise ValueError(f"observation must be one of {OBSERVATION_MODELS}, got {observation!r}")
        self.frames, self.l_dist, self.l_trk, self.direction = frames, float(l_dist), float(l_trk), chamfer
        # a tracker's own error lowers the tracks' weight (Observations.track_weight, 1 for tracks of the depth alone):
        # the tracking term's factor in the loss is l_trk * track_weight
        self.track_weight = float(obs.track_weight)
        self.track_term = self.l_trk * self.track_weight
        self._carry_mats = {}  # (id(embedding index), particles) -> (that index, its sparse matrix): :meth:`_carry`
        self.observation = observation
        rng = np.random.default_rng(seed)
        self.points = []
        for p in obs.points[:frames]:
            if len(p) > max_points:
                p = p[rng.choice(len(p), max_points, replace=False)]
            self.points.append(np.ascontiguousarray(p))
        self.seen = np.array([len(p) > 0 for p in self.points], bool)  # frames with observed points
        if not self.seen[1:].any():
            raise ValueError(f"none of frames 1..{frames - 1} holds an observed point: nothing to score")
        # the observed points on the GPU (None on a CPU); of the frames that hold points only
        self._padded = pad_frames([p for p in self.points if len(p)], scene.device)
        self._rank = np.cumsum(self.seen) - 1  # frame t's place among those frames
        if unseen_surface and observation != "surface":
            raise ValueError("unseen_surface needs observation='surface' (the particles themselves are the body)")
        self.surf = self.unseen = None
        if observation == "surface":
            self.surf = surface_embedding(self.points[0], scene.particles)
        if unseen_surface:
            self.unseen = surface_embedding(body_surface(scene.particles), scene.particles)
        self.track_index = self.track_emb = None
        if obs.tracks is not None and l_trk > 0:
            vis0 = obs.visibility[0]
            if vis0.any():
                from scipy.spatial import cKDTree

                keep = np.nonzero(vis0)[0]
                if observation == "surface":
                    self.track_emb = surface_embedding(obs.tracks[0, keep], scene.particles)
                    self.track_index = self.track_emb[0]
                else:
                    _, idx = cKDTree(scene.particles).query(obs.tracks[0, keep])
                    self.track_emb = None
                    self.track_index = np.asarray(idx, np.int64)
                self.track_keep = keep
                self.tracks = obs.tracks[:frames, keep]
                self.visible = obs.visibility[:frames, keep] & self.seen[:, None]

    def _carry(self, X, emb):
        """Embedded points [frames, S, 3] of positions X [frames, N, 3] (torch or numpy)."""
        idx, a = emb
        if isinstance(X, torch.Tensor):
            return torch.einsum("tskd,sk->tsd", X[:, torch.as_tensor(idx)], torch.as_tensor(a, dtype=X.dtype))
        # numpy (a fit scores every member of every generation so): the embedding as a sparse matrix [S, N], one
        # product a frame; 3-4x faster than gathering the k particles of every point (the same sums, in another order)
        key = (id(idx), X.shape[1])
        if key not in self._carry_mats or self._carry_mats[key][0] is not idx:  # an id can return with another array
            import scipy.sparse

            S, k = idx.shape
            self._carry_mats[key] = (idx, scipy.sparse.csr_matrix(
                (np.asarray(a, np.float64).ravel(), (np.repeat(np.arange(S), k), idx.ravel())), shape=(S, X.shape[1])))
        W = self._carry_mats[key][1]
        return np.stack([W @ np.asarray(x, np.float64) for x in X])

    def predicted_points(self, X):
        """What the loss compares with the observed points: [frames, S, 3] carried surface points, or X itself."""
        return X if self.surf is None else self._carry(X[: self.frames], self.surf)

    def unseen_points(self, X):
        """The simulated body's surface carried with X ([frames, K, 3], see ``unseen_surface``), or None."""
        return None if self.unseen is None else self._carry(X[: self.frames], self.unseen)

    def _predicted_tracks(self, X):
        if self.track_emb is None:
            return X[1:self.frames, torch.as_tensor(self.track_index) if isinstance(X, torch.Tensor) else self.track_index]
        return self._carry(X[1:self.frames], self.track_emb)

    def torch(self, X: torch.Tensor) -> torch.Tensor:
        """Loss of simulated positions X [frames, N, 3] (torch), differentiable."""
        P, U = self.predicted_points(X), self.unseen_points(X)
        idx = self._scored(1)
        if self._padded is not None:  # all pairs on the GPU
            at = torch.as_tensor(idx, device=P.device)
            terms = self._halves(P[at], None if U is None else U[at], self.direction,
                                 lambda p, d: chamfer_frames_torch(p, self._padded, direction=d,
                                                                   first=int(self._rank[idx[0]])))
        else:
            terms = torch.stack([self._halves(P[t], None if U is None else U[t], self.direction,
                                              lambda p, d: chamfer_distance(p, self.points[t], direction=d))
                                 for t in idx])
        loss = self.l_dist * terms.mean()
        if self.track_index is not None:
            pred = self._predicted_tracks(X)
            loss = loss + self.track_term * tracking_loss(pred, self.tracks[1:], self.visible[1:])
        return loss

    @staticmethod
    def _halves(P, U, direction: str, chamfer):
        """``chamfer(points, direction)`` of the predicted points P, where the observed-to-simulated half
        also reaches the unseen surface U (None: P alone)."""
        if U is None:
            return chamfer(P, direction)
        cat = torch.cat if isinstance(P, torch.Tensor) else np.concatenate
        axis = P.ndim - 2
        if direction == "obs_to_pred":
            return chamfer(cat([P, U], axis), direction)
        if direction == "pred_to_obs":
            return chamfer(P, direction)
        return 0.5 * (chamfer(P, "pred_to_obs") + chamfer(cat([P, U], axis), "obs_to_pred"))

    def _scored(self, first: int) -> np.ndarray:
        """The frames ``first`` .. frames - 1 that hold observed points."""
        return np.nonzero(self.seen[first:self.frames])[0] + first

    def chamfer(self, P: np.ndarray, direction: Optional[str] = None, first: int = 0,
                unseen: Optional[np.ndarray] = None) -> np.ndarray:
        """Chamfer distance (m) of predicted points P [frames, S, 3] (:meth:`predicted_points`) against the
        observed points of frames ``first`` .. frames - 1 (:func:`~.losses.chamfer_frames`: on the GPU for a
        CUDA scene); NaN on a frame without observed points. ``unseen`` [frames, K, 3] (:meth:`unseen_points`)
        joins P in the observed-to-simulated half."""
        idx = self._scored(first)
        out = np.full(self.frames - first, np.nan)
        if len(idx):
            obs = self._padded if self._padded is not None else [self.points[t] for t in idx]
            at = int(self._rank[idx[0]]) if self._padded is not None else 0
            out[idx - first] = self._halves(P[idx], None if unseen is None else unseen[idx], direction or self.direction,
                                            lambda p, d: chamfer_frames(p, obs, direction=d, first=at))
        return out

    def numpy(self, X: np.ndarray) -> float:
        """Loss of simulated positions X [frames, N, 3] (numpy); non-finite input gives a large finite value."""
        return float(np.nanmean(self.per_frame(X)))

    def per_frame(self, X: np.ndarray) -> np.ndarray:
        """Per-frame terms [frames - 1] of the loss (frames 1 .. F-1) whose mean is :meth:`numpy`.

        Frame t's term is l_dist * Chamfer_t + l_trk * w * (squared tracking error summed over the tracks
        visible at t) / (mean number of visible tracks per frame), w the tracks' weight (:attr:`track_weight`), so
        that the mean over frames weighs every visible track entry equally, as :meth:`torch` does (the mean over the
        frames that hold observed points: a frame without them is NaN). Non-finite input gives large finite terms.
        """
        depth, tracks = self.per_frame_terms(X)
        return depth if tracks is None else depth + tracks

    def per_frame_terms(self, X: np.ndarray) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """:meth:`per_frame`'s two terms apart: (the depth's, l_dist * Chamfer_t; the tracks', None where there are
        no tracks or none is visible in frames 1 .. F-1). Non-finite input gives large finite depth terms and no
        track terms."""
        n = int(self.seen[1:self.frames].sum())
        if not np.all(np.isfinite(X[: self.frames])):
            return np.where(self.seen[1:self.frames], _DIVERGED_LOSS, np.nan), None
        Xf = np.asarray(X[: self.frames], np.float64)
        depth = self.l_dist * self.chamfer(self.predicted_points(Xf), first=1, unseen=self.unseen_points(Xf))
        if self.track_index is None or not self.visible[1:].any():
            return depth, None
        vis = self.visible[1:]
        pred = self._predicted_tracks(np.asarray(X, np.float64))
        sq = np.where(vis, np.sum((pred - self.tracks[1:]) ** 2, -1), 0.0)
        return depth, self.track_term * sq.sum(1) / (vis.sum() / n)


@dataclass
class FitResult:
    """Fitted parameters (SI) and the history of a fit."""

    method: str
    params: Dict[str, float]
    material: MaterialConfig
    friction: float
    loss: float
    loss_history: List[float]
    param_history: List[Dict[str, float]]
    wall_time_s: float
    frames_used: int
    fps: float
    init: Dict[str, float]
    extra: Dict = field(default_factory=dict)
    complete: bool = True
    """False when the fit was stopped early; ``extra["resume"]`` then holds its resumable state."""
    iterations_done: Optional[int] = None
    """Iterations (Adam steps or CMA-ES generations) done, those of a resumed fit included."""
    iterations_requested: Optional[int] = None
    """The ``iters`` the fit was asked for."""

    def __post_init__(self):
        if self.iterations_done is None:
            self.iterations_done = len(self.loss_history)
        if self.iterations_requested is None:
            self.iterations_requested = self.iterations_done

    def fit_section(self) -> dict:
        """The ``fit`` section of the material file."""
        return {
            "method": self.method,
            "params": list(self.params),
            "init": self.init,
            "complete": bool(self.complete),
            "iterations_done": int(self.iterations_done),
            "iterations_requested": int(self.iterations_requested),
            "loss": self.loss if math.isfinite(self.loss) else None,
            "loss_history": self.loss_history,
            "param_history": self.param_history,
            "wall_time_s": self.wall_time_s,
            "frames_used": self.frames_used,
            "frames_used_range": [0, self.frames_used - 1],
            "fps": self.fps,
            **self.extra,
        }

    def file_material(self) -> MaterialConfig:
        """The fitted material with the table friction the fit used (what the material file holds)."""
        return self.material if self.friction is None else self.material.replace(friction=float(self.friction))

    def to_dict(self) -> dict:
        """The material file's JSON object (schema 2, see :mod:`empm_gym.sim.material_file`)."""
        return material_dict(self.file_material(), self.fit_section())

    def save(self, path) -> Path:
        """Write the material file (schema 2: base parameters, effects, and the ``fit`` section), atomically."""
        return write_material(path, self.file_material(), self.fit_section())


def load_material(path) -> Tuple[MaterialConfig, Optional[float]]:
    """(MaterialConfig, table friction or None) of a material file; a thin wrapper of
    :func:`empm_gym.sim.read_material` (which reads it)."""
    mf = read_material(path)
    return mf.material, mf.table_friction


def _initial_values(scene: Scene, params: Sequence[str], init: Optional[Dict[str, float]]) -> Dict[str, float]:
    """Starting values: ``init``, else the scene's material (and table friction), else the registry's start
    value of an effect the scene's material does not simulate."""
    init = dict(init or {})
    unknown = set(init) - set(PARAM_NAMES)
    if unknown:
        raise ValueError(f"init names unknown parameters {sorted(unknown)}; allowed: {', '.join(PARAM_NAMES)}")
    m = scene.material
    out = {}
    for n in params:
        if n not in PARAM_NAMES:
            raise ValueError(f"unknown parameter {n!r}; allowed: {', '.join(PARAM_NAMES)}")
        if n in init:
            v = init[n]
        elif n in ("E", "nu", "density"):
            v = getattr(m, n)
        elif n == "friction":
            v = scene.table_friction
        else:
            p = PARAMETERS[n]
            v = m.get(n)
            if v is None or (p.off is not None and v == p.off and p.transform == "log"):
                v = p.start  # the scene's material lacks the effect: the registry's starting value
        out[n] = parameter(n).check(v, "init: ")
    ParamSpace(params, default_bounds(out))  # validates names
    return out


def identify(observations: Observations, scene: Scene, *, params: Sequence[str] = ("E",), method: str = "adam",
             init: Optional[Dict[str, float]] = None, iters: int = 30, frames: Optional[int] = None,
             lr: float = 0.15, betas: Tuple[float, float] = (0.8, 0.95), popsize: int = 6, sigma0: float = 0.5, l_dist: float = 1.0, l_trk: float = 100.0,
             chamfer: str = "both", max_points: int = 2000, observation: str = "auto",
             bounds: Optional[Dict[str, Tuple[float, float]]] = None, seed: int = 0, progress: bool = True,
             checkpoint_every: Union[str, int, None] = "auto", memory_budget_bytes: Optional[float] = None,
             callback: Optional[Callable[[int, float, Dict[str, float]], None]] = None,
             stop: Any = None, resume: Union[Mapping, "FitResult", None] = None,
             extra_starts: Sequence[Dict[str, float]] = (), tol: float = 1e-4) -> FitResult:
    """Identify ``params`` (any of :data:`~.problem.PARAM_NAMES`: E, nu, density and every effect parameter) of
    ``scene`` from ``observations``.

    ``init`` gives starting values (SI; default the scene's material and table friction, else the effect's
    registry start value), ``frames`` the
    number of leading frames fitted (default all observed frames the controls cover), ``iters`` Adam steps
    or CMA-ES generations, ``lr`` Adam's learning rate in the unconstrained space, ``popsize`` /
    ``sigma0`` CMA-ES's population (= simulated worlds) and initial step, ``bounds`` SI search boxes
    (default :func:`default_bounds`), ``observation`` the observation model of :class:`Objective`
    ("surface": the frame-0 observed surface carried by the body; "particles": particle centres; "auto":
    "surface" when ``observations.surface`` says the points are a measured surface, as from a recording). ``callback(iteration, loss, params)`` is called every iteration.

    Adam stops before ``iters`` once it has converged (:func:`adam_converged`: over its last
    :data:`CONVERGED_PATIENCE` steps the best loss improved by less than ``tol`` relative and no step moved a
    parameter by more than :data:`CONVERGED_STEP` in the search space, 1 % for a log-space parameter);
    ``extra["converged_at"]`` then gives the iteration and the fit is complete. ``tol=0`` runs all ``iters``.

    ``stop`` (an object with ``is_set()``, such as :class:`~.interrupt.StopRequest` or ``threading.Event``,
    or a callable returning a bool) is checked before every iteration: once set, the fit returns what it
    has with ``complete=False`` and its resumable state in ``extra["resume"]`` (no iteration done: the
    starting values with loss NaN). ``resume`` (the ``fit`` section of such a result's material file, or
    the result) continues that fit up to ``iters`` iterations in all; the other arguments, the observations
    and the scene must be those it was started with (else :class:`ResumeError`).

    ``extra_starts`` (CMA-ES only): further starting points (SI values of ``params``, clipped to the box),
    each simulated as one member of the first generation in place of a random sample: the search keeps the
    best of them if nothing it samples does better.

    ``checkpoint_every`` ("auto": on CUDA, one segment per frame; on the CPU, only when the taped rollout would
    exceed ``memory_budget_bytes``; None: never; an int: every so many substeps) trades memory for recomputation
    in Adam's backward pass. On CUDA a rollout of one-frame segments replays two CUDA graphs of one frame's
    substeps for every frame (:class:`~empm_gym.sim.Rollout`): capturing graphs of the whole horizon instead
    cost more, in launches from Python, than the fit's GPU work, and the forward pass that each segment's
    adjoint recomputes costs less. ``memory_budget_bytes`` (None: 1 GB) is what the CPU's "auto" compares the taped
    rollout with.
    """
    prep = _prepare_fit(observations, scene, params=params, method=method, init=init, iters=iters, frames=frames,
                        lr=lr, betas=betas, popsize=popsize, sigma0=sigma0, l_dist=l_dist, l_trk=l_trk,
                        chamfer=chamfer, max_points=max_points, observation=observation, bounds=bounds, seed=seed,
                        extra_starts=extra_starts, tol=tol)
    prior = None if resume is None else _check_resume(resume, prep.settings, prep.digest, iters)
    t0 = time.perf_counter()
    if method == "adam":
        hist_l, hist_p, extra, state = _fit_adam(scene, prep.objective, prep.space, prep.init_vals, prep.base_mat,
                                                 iters, lr, tuple(betas), progress, checkpoint_every,
                                                 memory_budget_bytes, callback, stop, prior, tol)
    else:
        hist_l, hist_p, extra, state = _fit_cmaes(scene, prep.objective, prep.space, prep.init_vals, prep.base_mat,
                                                  iters, popsize, sigma0, seed, progress, callback, stop, prior,
                                                  prep.starts)
    wall = time.perf_counter() - t0 + (float(prior["wall_time_s"]) if prior else 0.0)
    return _fit_result(prep, hist_l, hist_p, extra, state, wall)


@dataclass
class _PreparedFit:
    """One fit's checked inputs (:func:`_prepare_fit`): what :func:`identify` and :func:`identify_lockstep` run."""

    scene: Scene
    method: str
    params: Tuple[str, ...]
    init_vals: Dict[str, float]
    space: ParamSpace
    F: int
    observation: str
    objective: "Objective"
    base_mat: MaterialConfig
    starts: List[Dict[str, float]]
    settings: dict
    digest: str
    iters: int
    popsize: int
    sigma0: float
    seed: int


def _prepare_fit(observations: Observations, scene: Scene, *, params, method, init, iters, frames, lr, betas, popsize,
                 sigma0, l_dist, l_trk, chamfer, max_points, observation, bounds, seed, extra_starts, tol
                 ) -> _PreparedFit:
    """Check :func:`identify`'s arguments (a clear error naming what and why) and build the fit's search space,
    objective and starting material."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0, got {tol}")
    if abs(observations.fps - scene.fps) > 1e-6 * scene.fps:
        raise ValueError(f"observations at {observations.fps} fps but the scene's controls at {scene.fps} fps")
    params = tuple(params)
    if extra_starts and method != "cmaes":
        raise ValueError("extra_starts are CMA-ES starting points; method='adam' has one start (init)")
    init_vals = _initial_values(scene, params, init)
    space = ParamSpace(params, {**default_bounds(init_vals), **(bounds or {})})
    for n, v in init_vals.items():
        lo, hi = space.bounds[n]
        if not (lo <= v <= hi):
            raise ValueError(f"init {n}={v} lies outside its bounds ({lo}, {hi})")
    F = frames or min(observations.num_frames, scene.num_frames or observations.num_frames)
    if scene.num_frames is not None and F > scene.num_frames:
        raise ValueError(f"frames={F} exceeds the {scene.num_frames} frames of end-effector controls")
    if observation == "auto":
        observation = "surface" if observations.surface else "particles"
    objective = Objective(scene, observations, F, l_dist=l_dist, l_trk=l_trk, chamfer=chamfer,
                          max_points=max_points, seed=seed, observation=observation)
    # the fitted effects are simulated from the start (their flags and arrays on), at the starting values
    base_mat = _base_material(scene.material, init_vals)
    starts = [{n: float(np.clip(st[n], *space.bounds[n])) for n in params} for st in extra_starts]
    if len(starts) >= popsize:
        raise ValueError(f"{len(starts)} extra_starts leave no sampled member in a population of {popsize}")
    settings = _fit_settings(method, params, init_vals, space, F, observation, l_dist, l_trk, chamfer, max_points,
                             seed, lr, betas, popsize, sigma0)
    if starts:
        settings["extra_starts"] = starts
    return _PreparedFit(scene=scene, method=method, params=params, init_vals=init_vals, space=space, F=F,
                        observation=observation, objective=objective, base_mat=base_mat, starts=starts,
                        settings=settings, digest=_problem_digest(scene, objective, base_mat), iters=int(iters),
                        popsize=int(popsize), sigma0=float(sigma0), seed=int(seed))


def _fit_result(prep: _PreparedFit, hist_l, hist_p, extra: dict, state: dict, wall: float) -> "FitResult":
    """The :class:`FitResult` of a fit run from ``prep``: its best iterate, history and resumable state."""
    done = len(hist_l)
    complete = done >= prep.iters or extra.get("converged_at") is not None
    # what assess_fit needs to rebuild the objective and the search box
    extra["bounds"], extra["observation"] = prep.settings["bounds"], prep.observation
    s = prep.settings
    extra["objective"] = {k: s[k] for k in ("l_dist", "l_trk", "chamfer", "max_points", "seed")}
    if not complete:
        extra["resume"] = {"format": _RESUME_FORMAT, "settings": prep.settings, "data_sha256": prep.digest,
                           "state": state}
    if done:
        best = int(np.argmin(hist_l))
        best_p, best_l = hist_p[best], float(hist_l[best])
    else:  # stopped before the first iteration
        best_p, best_l = dict(prep.init_vals), float("nan")
    mat, mu = prep.space.material(best_p, prep.base_mat, prep.scene.table_friction)
    return FitResult(method=prep.method, params=dict(best_p), material=mat, friction=mu, loss=best_l,
                     loss_history=[float(v) for v in hist_l], param_history=hist_p, wall_time_s=wall,
                     frames_used=prep.F, fps=prep.scene.fps, init=prep.init_vals, extra=extra, complete=complete,
                     iterations_done=done, iterations_requested=prep.iters)


def _fit_settings(method, params, init_vals, space, F, observation, l_dist, l_trk, chamfer, max_points, seed, lr,
                  betas, popsize, sigma0) -> dict:
    """Everything besides the data that decides a fit's course (``iters`` excepted), as JSON would hold it."""
    s = {"method": method, "params": list(params), "frames": int(F), "init": dict(init_vals),
         "bounds": {n: list(space.bounds[n]) for n in params}, "observation": observation, "l_dist": l_dist,
         "l_trk": l_trk, "chamfer": chamfer, "max_points": max_points, "seed": seed}
    if method == "adam":
        s.update(lr=lr, betas=list(betas))
    else:
        s.update(popsize=popsize, sigma0=sigma0)
    return json.loads(json.dumps(s, default=float))


def _problem_digest(scene: Scene, objective: Objective, base_mat: MaterialConfig) -> str:
    """SHA-256 of what the fit sees: the observations it compares with, the frame-0 body, the controls of the
    fitted frames and the scene's settings (another recording, --frames, --dx ... change it)."""
    h = hashlib.sha256()

    def arr(a):
        if a is None:
            h.update(b"None;")
            return
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype}{a.shape};".encode())
        h.update(a.tobytes())

    F = objective.frames
    for p in objective.points:
        arr(p)
    if objective.track_index is not None:
        for a in (objective.tracks, objective.visible, objective.track_index):
            arr(a)
    arr(scene.particles)
    arr(scene.volumes)
    for a in (scene.ee_positions, scene.ee_grip, scene.ee_orientations):
        arr(None if a is None else a[:F])
    h.update(repr((scene.fps, scene.ee_configs, scene.table, scene.table_friction, scene.dx, scene.grid,
                   scene.gravity, scene.cfl, scene.motion_bounds, scene.motion_margin)).encode())
    h.update(json.dumps(material_dict(base_mat), sort_keys=True).encode())
    return h.hexdigest()


def read_resume_state(path) -> dict:
    """The ``fit`` section of the material file ``path`` if it holds an interrupted fit that
    ``identify(..., resume=...)`` can continue; :class:`ResumeError` naming the file and the reason if not."""
    try:
        mf = read_material(path)
    except (ValueError, OSError) as exc:
        raise ResumeError(f"cannot resume from {path}: {exc}") from None
    try:
        _resumable(mf.fit)
    except ResumeError as exc:
        raise ResumeError(f"cannot resume from {path}: {exc}") from None
    return mf.fit


def _resumable(fit) -> dict:
    """``fit``'s resume section, or ResumeError saying why there is none."""
    if not isinstance(fit, Mapping):
        raise ResumeError("it holds no fit section (it was not written by an interrupted fit)")
    if fit.get("complete") is True:
        raise ResumeError(f"it holds a complete fit ({fit.get('iterations_done')} iterations); there is nothing "
                          f"to resume (fit again without resuming to overwrite it)")
    res = fit.get("resume")
    if not isinstance(res, Mapping) or not isinstance(res.get("state"), Mapping):
        raise ResumeError(f"its fit section (method {fit.get('method')!r}) holds no resumable state (only an "
                          f"interrupted offline fit of this version writes one)")
    if res.get("format") != _RESUME_FORMAT:
        raise ResumeError(f"its resumable state has format {res.get('format')!r}; this version reads "
                          f"format {_RESUME_FORMAT}")
    return res


def _check_resume(resume, settings: dict, digest: str, iters: int) -> dict:
    """What the fit loops need to continue ``resume`` (a fit section or FitResult), after checking that it was
    made by the same fit: {"state", "loss_history", "param_history", "iterations_done", "wall_time_s"}."""
    fit = resume.fit_section() if isinstance(resume, FitResult) else resume
    if not isinstance(fit, Mapping):
        raise TypeError(f"resume must be a material file's fit section (a dict) or a FitResult, "
                        f"got {type(resume).__name__}")
    res = _resumable(fit)
    old = res.get("settings") or {}
    diff = [f"{k}: {old.get(k)!r} then, {settings.get(k)!r} now" for k in sorted(set(old) | set(settings))
            if old.get(k) != settings.get(k)]
    if diff:
        raise ResumeError("it was fitted with other settings (" + "; ".join(diff) + ")")
    if res.get("data_sha256") != digest:
        raise ResumeError("it was fitted to other data: the observations or the simulated scene differ (another "
                          "recording, or another frame count, grid cell or particle fill)")
    done = int(fit.get("iterations_done", -1))
    hist_l, hist_p = list(fit.get("loss_history") or []), list(fit.get("param_history") or [])
    if done < 0 or len(hist_l) != done or len(hist_p) != done:
        raise ResumeError(f"its iteration count ({fit.get('iterations_done')!r}) does not match its histories "
                          f"({len(hist_l)} losses, {len(hist_p)} parameter sets)")
    if iters <= done:
        raise ResumeError(f"it already holds {done} iterations; ask for more than {done} in all (--iters) to "
                          f"continue")
    return {"state": res["state"], "loss_history": [float(v) for v in hist_l],
            "param_history": [{k: float(v) for k, v in p.items()} for p in hist_p], "iterations_done": done,
            "wall_time_s": float(fit.get("wall_time_s") or 0.0)}


def _stop_requested(stop) -> bool:
    if stop is None:
        return False
    is_set = getattr(stop, "is_set", None)
    return bool(is_set() if is_set is not None else stop())


def _iterations(start: int, iters: int, stop) -> Iterator[int]:
    """Iteration indices ``start .. iters-1``, ending early once ``stop`` is set (checked before each)."""
    for it in range(start, iters):
        if _stop_requested(stop):
            return
        yield it


def _base_material(material: MaterialConfig, init_vals: Dict[str, float]) -> MaterialConfig:
    """``material`` with every fitted effect parameter set to its starting value (table friction excluded:
    the scene carries it)."""
    try:
        return material.replace(**{n: v for n, v in init_vals.items() if n in PARAMETERS and n != "friction"})
    except ValueError as exc:
        raise ValueError(f"cannot fit {', '.join(init_vals)} on this material: {exc}") from None


def _bar(iters, desc, progress, initial=0):
    from tqdm.auto import tqdm

    return tqdm(total=iters, initial=initial, desc=desc, disable=not progress, leave=False, dynamic_ncols=True)


def _sim_kwargs(space: ParamSpace, z: torch.Tensor) -> Dict[str, torch.Tensor]:
    out = {}
    for i, n in enumerate(space.names):
        key = "table_friction" if n == "friction" else n
        out[key] = space.from_z1(n, z[i]).reshape(1).to(torch.float32)
    return out


def _tensor_to_json(v):
    if torch.is_tensor(v):
        return {"dtype": str(v.dtype).replace("torch.", ""), "data": v.detach().cpu().tolist()}
    return v


def _tensor_from_json(v):
    if isinstance(v, Mapping) and set(v) == {"dtype", "data"}:
        return torch.tensor(v["data"], dtype=getattr(torch, v["dtype"]))
    return v


#: On CUDA, Adam keeps its rollout while it takes at most this many times the substeps the current E needs
#: (from 3x above the truth, a 42-frame rope fit built its rollout and graphs about six times otherwise).
REUSE_SUBSTEPS = 1.5


def substep_rung(n: int) -> int:
    """``n`` substeps per frame rounded up to a coarse ladder (exact to 8, then multiples of a quarter of the
    power of two below: 10, 12, 14, 16, 20, 24, 28, 32, 40, ...; at most 25 % more): Adam moves E by a few per
    cent per step, and each change of the substep count builds a new rollout and captures its CUDA graphs
    again (about 8 s for a 42-frame rope on an H100, against under a second to replay them)."""
    n = int(n)
    if n <= 8:
        return max(1, n)
    q = 1 << (n.bit_length() - 3)  # a quarter of the power of two below n
    return -(-n // q) * q


CONVERGED_PATIENCE = 3
"""Adam's steps over which :func:`adam_converged` looks for progress."""
CONVERGED_STEP = 0.01
"""The largest step in the search space (log space: 1 %) that :func:`adam_converged` counts as no move."""


def adam_converged(losses: Sequence[float], z_history: Sequence[Sequence[float]], tol: float) -> bool:
    """Whether a descent has converged: over its last :data:`CONVERGED_PATIENCE` iterations (``losses`` and the
    search-space points ``z_history`` they were evaluated at, one per iteration) the best loss improved on the
    best before them by less than ``tol`` relative, and no step between those points moved a coordinate by more
    than :data:`CONVERGED_STEP`. ``tol`` 0 never converges."""
    k = CONVERGED_PATIENCE
    if tol <= 0 or len(losses) <= k:
        return False
    if not np.all(np.isfinite(losses[-k:])):
        return False
    before, recent = np.nanmin(losses[:-k]), min(losses[-k:])
    if not np.isfinite(before) or before - recent > tol * abs(before):
        return False
    z = np.asarray(z_history[-k - 1:], dtype=float)
    return bool(np.max(np.abs(np.diff(z, axis=0))) < CONVERGED_STEP)


def _fit_adam(scene, objective, space, init_vals, base_mat, iters, lr, betas, progress, checkpoint_every, budget,
              callback, stop=None, prior=None, tol=0.0):
    from empm_gym.autograd import simulate

    F = objective.frames
    model = scene.builder([base_mat], [scene.table_friction]).finalize(scene.device, requires_grad=True)
    solver = SolverMPM(model, SolverConfig(cfl=scene.cfl, check_every=0, deterministic=scene.deterministic))
    vel, om = scene.ee_velocities(F), scene.ee_omegas(F)
    grip = scene.ee_grip[: F - 1] if model.ee_count else None
    vmax = scene.ee_max_speed(F)
    z = torch.tensor(space.to_z(init_vals), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.AdamW([z], lr=lr, betas=betas, weight_decay=0.0)
    scale = 1.0  # step multiplier: halved when the loss went up, regrown by 25 % per improvement
    best = None  # (loss, z, gradient) of the best iterate
    cache = {}
    per_node = 2 * 4 * 7 * int(np.prod(model.grid_res)) * model.world_count
    per_particle = 2 * 4 * 24 * model.particle_count
    if budget is None:
        budget = 1.0e9
    hist_l, hist_p = [], []
    skipped = 0
    converged_at = None
    kept_sub = None  # substeps per frame of the rollout kept (CUDA)
    if prior is not None:  # continue an interrupted fit where it stopped
        st = prior["state"]
        try:
            with torch.no_grad():
                z.copy_(torch.tensor(st["z"], dtype=torch.float64))
            if st["optimizer"]:
                opt.state[z] = {k: _tensor_from_json(v) for k, v in st["optimizer"].items()}
            scale = float(st["scale"])
            if st["best"] is not None:
                bl, bz, bg = st["best"]
                best = (float(bl), torch.tensor(bz, dtype=torch.float64), torch.tensor(bg, dtype=torch.float64))
            skipped = int(st["skipped_steps"])
            kept_sub = st.get("substeps")  # the rollout's substeps when it stopped (CUDA), so it resumes on them
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise ResumeError(f"its Adam state is incomplete or malformed ({type(exc).__name__}: {exc})") from None
        hist_l, hist_p = list(prior["loss_history"]), list(prior["param_history"])
    bar = _bar(iters, "identify (adam)", progress, initial=len(hist_l))
    for it in _iterations(len(hist_l), iters, stop):
        vals = space.from_z(z.detach().numpy())
        mat, mu = space.material(vals, base_mat, scene.table_friction)
        sub, dt = substeps_for(scene, [mat], vmax)
        if model.device.is_cuda:  # a rollout (and its CUDA graphs) serves every E of its rung, and smaller E
            # while it takes at most REUSE_SUBSTEPS times the substeps they need (a smaller dt is as stable)
            sub = kept_sub if kept_sub and sub <= kept_sub <= REUSE_SUBSTEPS * sub else substep_rung(sub)
            kept_sub, dt = sub, 1.0 / (scene.fps * sub)
        if sub not in cache:
            cache.clear()  # keep one rollout's memory at a time
            steps = (F - 1) * sub
            if checkpoint_every == "auto" and model.device.is_cuda:
                ck = sub if steps > sub else None
            elif checkpoint_every == "auto":
                per_step = per_node + per_particle
                ck = None if steps * per_step <= budget else max(sub, int(budget // per_step) // sub * sub)
            else:
                ck = checkpoint_every
            ro = Rollout(model, solver, steps=steps, dt=dt, substeps_per_control=sub, record_every=sub,
                         checkpoint_every=ck)
            ctrls = ro.make_controls()
            for t, c in enumerate(ctrls):
                if model.ee_count:
                    c.set(velocity=vel[t][None], omega=om[t][None], grip=grip[t][None])
            cache[sub] = (ro, ctrls)
        ro, ctrls = cache[sub]
        opt.zero_grad()
        try:
            X = simulate(ro, model.state(), ctrls, **_sim_kwargs(space, z))
        except SimulationDiverged:
            hist_l.append(_DIVERGED_LOSS)
            hist_p.append(vals)
            with torch.no_grad():  # step back towards the start
                z.mul_(0.5).add_(0.5 * torch.tensor(space.to_z(init_vals)))
            bar.update(1)
            continue
        loss = objective.torch(X)
        loss.backward()
        L = float(loss.detach())
        hist_l.append(L)
        hist_p.append(vals)
        if callback is not None:
            callback(it, L, vals)
        g = z.grad.detach().clone()
        if not torch.isfinite(g).all():
            skipped += 1
            g = torch.zeros_like(g)
            z.grad = g.clone()  # the optimiser steps on z.grad: a NaN there would make the parameters NaN
        if best is None or L < best[0]:
            best = (L, z.detach().clone(), g)
            scale = min(1.0, scale * 1.25)
        else:
            # the loss went up: go back to the best point, forget the momentum and halve the step
            scale *= 0.5
            with torch.no_grad():
                z.copy_(best[1])
            z.grad = best[2].clone()
            for st in opt.state.values():
                if "exp_avg" in st:
                    st["exp_avg"].zero_()
        for group in opt.param_groups:
            group["lr"] = lr * scale
        opt.step()
        with torch.no_grad():
            z.copy_(torch.as_tensor(space.clamp(z.numpy())))
        bar.set_postfix(loss=f"{L:.5f}", **{k: f"{v:.4g}" for k, v in vals.items()})
        bar.update(1)
        if adam_converged(hist_l, [space.to_z(v) for v in hist_p], tol):
            converged_at = it
            break
    bar.close()
    state = {"z": z.detach().tolist(), "optimizer": {k: _tensor_to_json(v) for k, v in opt.state.get(z, {}).items()},
             "scale": scale, "best": None if best is None else [best[0], best[1].tolist(), best[2].tolist()],
             "skipped_steps": skipped, "substeps": kept_sub}
    return hist_l, hist_p, {"lr": lr, "betas": list(betas), "skipped_steps": skipped, "converged_at": converged_at}, state


class _CMAES:
    """One CMA-ES search in a fit's space (pycma): ``ask`` the next generation's candidates (SI values),
    ``tell`` their losses; the history of the best member per generation.

    pycma draws its samples from numpy's global generator, which its constructor seeds: each search keeps
    that generator's state as its own and restores it around every draw, so that several searches stepped in
    turn (:func:`identify_lockstep`) draw what each would draw alone."""

    def __init__(self, space: ParamSpace, init_vals: Dict[str, float], popsize: int, sigma0: float, seed: int,
                 starts: Sequence[Dict[str, float]] = ()):
        import warnings

        import cma

        if popsize < 2:
            raise ValueError(f"popsize must be >= 2 for CMA-ES, got {popsize}")
        self.space, self.n = space, len(space.names)
        z0 = space.to_z(init_vals)
        lo, hi = list(space.z_lo), list(space.z_hi)
        # pycma does not support 1-D problems (its issues #86, #302): add a dummy coordinate the loss ignores
        self.dummy = len(z0) == 1
        if self.dummy:
            z0, lo, hi = np.append(z0, 0.0), lo + [-1.0], hi + [1.0]
        opts = {"popsize": int(popsize), "seed": int(seed) + 1, "verbose": -9, "bounds": [lo, hi],
                "maxstd": float("inf"), "tolfun": 0.0, "tolx": 1e-6}
        outside = np.random.get_state()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.es = cma.CMAEvolutionStrategy(list(z0), float(sigma0), opts)  # seeds numpy's global generator
        if starts:  # members of the first generation (pycma's inject: they replace its first samples)
            self.es.inject([list(space.to_z(st)) + ([0.0] if self.dummy else []) for st in starts], force=True)
        self._rng = np.random.get_state()
        np.random.set_state(outside)
        self.hist_l: List[float] = []
        self.hist_p: List[Dict[str, float]] = []
        self.gen_mean: List[Dict[str, float]] = []
        self.pop_losses: List[List[float]] = []
        self.population: List[List[Dict[str, float]]] = []  # every generation's members (SI), as told
        self._Z = None

    def _own_rng(self, fn, *a):
        import warnings

        outside = np.random.get_state()
        np.random.set_state(self._rng)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return fn(*a)
        finally:
            self._rng = np.random.get_state()
            np.random.set_state(outside)

    def ask(self) -> List[Dict[str, float]]:
        self._Z = self._own_rng(self.es.ask)
        return [self.space.from_z(z[:self.n]) for z in self._Z]

    def tell(self, cand: List[Dict[str, float]], losses: Sequence[float]) -> int:
        """Record the generation ``cand`` (from :meth:`ask`) scored ``losses``; the index of its best member."""
        losses = [float(v) for v in losses]
        self._own_rng(self.es.tell, self._Z, losses)
        i = int(np.argmin(losses))
        self.hist_l.append(losses[i])
        self.hist_p.append(cand[i])
        self.gen_mean.append(self.space.from_z(self.es.mean[:self.n]))
        self.pop_losses.append(losses)
        self.population.append([{k: float(v) for k, v in c.items()} for c in cand])
        return i

    def generation(self, losses_of) -> Tuple[List[Dict[str, float]], int]:
        """ask, evaluate (``losses_of(candidates) -> losses``), tell: the candidates and the best one's index."""
        cand = self.ask()
        return cand, self.tell(cand, losses_of(cand))

    def extra(self, popsize: int, sigma0: float) -> dict:
        # the members this search evaluated and their losses: where else the loss is as low (assess_fit's basins)
        return {"popsize": popsize, "sigma0": sigma0, "evaluations": popsize * len(self.hist_l),
                "mean_history": self.gen_mean, "population": self.population,
                "population_losses": [[float(v) for v in g] for g in self.pop_losses[-len(self.population):]]
                if self.population else []}


def _losses_of(sim: "_ForwardSim", space: ParamSpace, base_mat: MaterialConfig, scene: Scene, objective: "Objective",
               F: int, cand: Sequence[Dict[str, float]]) -> List[float]:
    """``objective``'s loss of each of ``cand`` (values of ``space``'s parameters, SI), simulated for ``F`` frames
    as the worlds of ``sim`` (one per candidate); a diverged world's loss is NaN."""
    mats = [space.material(v, base_mat, scene.table_friction) for v in cand]
    sim.set([m for m, _ in mats], [mu for _, mu in mats])
    X, _, _ = sim.run(F, reuse=True, queued=True)  # read back once, after the last frame (CUDA)
    return [objective.numpy(X[:, w]) for w in range(len(cand))]


def fit_losses(observations: Observations, scene: Scene, values: Sequence[Dict[str, float]], **kw) -> List[float]:
    """The loss that ``identify(observations, scene, params=..., **kw)`` minimises (its frames, weights, observed
    points and seed: ``kw`` as given to it; its search settings, such as ``bounds`` or ``iters``, play no part), at
    each of ``values`` ({parameter: SI value}, the same parameters in each), simulated as the worlds of one batch
    (a diverged world's loss is NaN): a fit's loss where its search did not sample (the doctor asks whether a bound
    of the box fits at least as well as a fit that stopped short of it)."""
    values = [dict(v) for v in values]
    if not values or any(set(v) != set(values[0]) for v in values):
        raise ValueError(f"fit_losses needs one or more values of the same parameters, got {values}")
    params = tuple(values[0])
    # the box only has to hold the values (it shapes no search here)
    box = {p: (min([lo] + [v[p] for v in values]), max([hi] + [v[p] for v in values]))
           for p, (lo, hi) in default_bounds(values[0]).items() if p in params}
    kw = {k: v for k, v in kw.items() if k not in ("params", "init", "bounds", "iters", "popsize", "extra_starts",
                                                    "method")}
    prep = _prepare_fit(observations, scene, **{**_IDENTIFY_DEFAULTS, **kw, "params": params, "method": "cmaes",
                                                "init": values[0], "bounds": box, "iters": 1,
                                                "popsize": len(values) + 1, "extra_starts": ()})
    sim = _ForwardSim(scene, [prep.base_mat] * len(values), [scene.table_friction] * len(values))
    return _losses_of(sim, prep.space, prep.base_mat, scene, prep.objective, prep.F, values)


def _fit_cmaes(scene, objective, space, init_vals, base_mat, iters, popsize, sigma0, seed, progress, callback,
               stop=None, prior=None, starts=()):
    F = objective.frames
    cm = _CMAES(space, init_vals, popsize, sigma0, seed, starts)
    hist_l, hist_p = cm.hist_l, cm.hist_p
    generation = cm.generation

    if prior is not None:
        # rebuild the strategy (and numpy's global random state, which pycma draws from) by replaying the
        # recorded generations: the same seed and the same losses give the same candidates, without simulating
        try:
            recorded = [[float(v) for v in gen] for gen in prior["state"]["population_losses"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise ResumeError(f"its CMA-ES state is incomplete or malformed ({type(exc).__name__}: {exc})") from None
        if len(recorded) != prior["iterations_done"] or any(len(g) != popsize for g in recorded):
            raise ResumeError(f"its CMA-ES state holds {len(recorded)} generations of "
                              f"{sorted(set(len(g) for g in recorded))} losses, not {prior['iterations_done']} of "
                              f"{popsize}")
        for g, want in zip(recorded, prior["param_history"]):
            generation(lambda cand: g)
            got = hist_p[-1]
            if any(not math.isclose(got[k], want.get(k, math.nan), rel_tol=1e-9, abs_tol=1e-12) for k in got):
                raise ResumeError(f"replaying its CMA-ES generations gave candidate {got} at generation "
                                  f"{len(hist_p) - 1} where the fit had {want} (another cma or numpy version?)")
    sim = _ForwardSim(scene, [base_mat] * popsize, [scene.table_friction] * popsize)

    def simulated(cand):
        return _losses_of(sim, space, base_mat, scene, objective, F, cand)

    bar = _bar(iters, "identify (cmaes)", progress, initial=len(hist_l))
    for gen in _iterations(len(hist_l), iters, stop):
        cand, i = generation(simulated)
        if callback is not None:
            callback(gen, hist_l[-1], cand[i])
        bar.set_postfix(loss=f"{hist_l[-1]:.5f}", **{k: f"{v:.4g}" for k, v in cand[i].items()})
        bar.update(1)
    bar.close()
    return hist_l, hist_p, cm.extra(popsize, sigma0), {"population_losses": cm.pop_losses}


#: identify's defaults of what :func:`_prepare_fit` takes (one place: identify's signature)
_IDENTIFY_DEFAULTS = {k: v.default for k, v in inspect.signature(identify).parameters.items()
                      if k in inspect.signature(_prepare_fit).parameters and v.default is not inspect.Parameter.empty}


def identify_lockstep(observations: Observations, fits: Sequence[Tuple[Scene, dict]], *, progress: bool = True,
                      desc: str = "identify (cmaes, lockstep)") -> List["FitResult"]:
    """Several CMA-ES fits (``fits``: ``(scene, keyword arguments of identify)`` each, ``method`` "cmaes") run
    generation by generation in turn, the members of every fit that share a simulation simulated as the worlds
    of one batched model: the results are those of :func:`identify` called on each alone, on the CPU to the
    last bit (each search draws its own random numbers, each world its own material), at a fraction of the
    launches.

    Fits share a simulation when their scenes hold the same body (particles), grid, controls and substep count
    per frame (their ``dt_materials`` and the end-effectors' speed), and they fit as many frames for as many
    generations. A diagnosis fits the base model and every effect on one body with one clock (the doctor's
    candidates): on a GPU, one generation of 8 worlds of a few thousand particles costs about as much as one of
    56. ``stop``, ``resume``, ``callback`` and ``method="adam"`` are not supported here (use :func:`identify`).
    Each result's ``wall_time_s`` is its share of the whole run (the run's wall time over the number of fits)."""
    t0 = time.perf_counter()
    preps: List[_PreparedFit] = []
    for scene, kw in fits:
        kw = dict(kw)
        bad = sorted(set(kw) & {"stop", "resume", "callback", "checkpoint_every", "memory_budget_bytes", "progress"})
        if bad or kw.get("method", "cmaes") != "cmaes":
            raise ValueError(f"identify_lockstep runs CMA-ES fits only, without {bad or 'method=' + kw['method']}: "
                             f"use identify for those")
        kw["method"] = "cmaes"
        preps.append(_prepare_fit(observations, scene, **{**_IDENTIFY_DEFAULTS, **kw}))

    def key(i: int, p: _PreparedFit) -> tuple:
        # the substeps a simulation takes follow the stiffest material it holds; a fit shares its worlds only
        # where its scene's dt_materials fix them for every point of its box (the box's corners bound the
        # wave speed), else the others' materials would change its substeps: it then runs alone
        sc = p.scene
        speed = sc.ee_max_speed(p.F)
        names = [n for n in p.params if n != "friction"]
        corners = [p.space.material({**p.init_vals, **{n: p.space.bounds[n][(k >> j) & 1] for j, n in enumerate(names)}},
                                    p.base_mat, sc.table_friction)[0] for k in range(2 ** len(names))]
        fixed = substeps_for(sc, [], speed)[0] if sc.dt_materials else None
        if fixed is None or substeps_for(sc, corners, speed)[0] != fixed:
            return ("alone", i)
        return (id(sc.particles), repr(sc.grid_config()), str(sc.device), p.F, p.iters, fixed)

    groups: Dict[tuple, List[int]] = {}
    for i, p in enumerate(preps):
        groups.setdefault(key(i, p), []).append(i)
    searches = [_CMAES(p.space, p.init_vals, p.popsize, p.sigma0, p.seed, p.starts) for p in preps]
    total = sum(p.iters for p in (preps[g[0]] for g in groups.values()))
    bar = _bar(total, desc, progress)
    sims = []
    for idx in groups.values():
        dt_materials = []
        for i in idx:
            dt_materials += [m for m in preps[i].scene.dt_materials if m not in dt_materials]
        sc = dataclasses.replace(preps[idx[0]].scene, dt_materials=tuple(dt_materials))
        mats0 = [m for i in idx for m in [preps[i].base_mat] * preps[i].popsize]
        sims.append((idx, _ForwardSim(sc, mats0, [preps[i].scene.table_friction for i in idx
                                                  for _ in range(preps[i].popsize)])))
    # generation by generation; the groups' simulations (different bodies or clocks: separate models) advance a
    # frame each in turn, side by side on a GPU (problem.run_together)
    for gen in range(max(preps[idx[0]].iters for idx, _ in sims)):
        live = [(idx, sim) for idx, sim in sims if gen < preps[idx[0]].iters]
        asked = []
        for idx, sim in live:
            cands = [searches[i].ask() for i in idx]
            mats = [preps[i].space.material(v, preps[i].base_mat, preps[i].scene.table_friction)
                    for i, cand in zip(idx, cands) for v in cand]
            sim.set([m for m, _ in mats], [mu for _, mu in mats])
            asked.append(cands)
        runs = run_together([sim.steps(preps[idx[0]].F, queued=True, reuse=True) for idx, sim in live])
        for (idx, _), cands, (X, _, _) in zip(live, asked, runs):
            w = 0
            for i, cand in zip(idx, cands):
                searches[i].tell(cand, [preps[i].objective.numpy(X[:, w + k]) for k in range(len(cand))])
                w += len(cand)
            bar.update(1)
    bar.close()
    wall = (time.perf_counter() - t0) / max(1, len(preps))
    return [_fit_result(p, cm.hist_l, cm.hist_p, cm.extra(p.popsize, p.sigma0), {"population_losses": cm.pop_losses},
                        wall) for p, cm in zip(preps, searches)]
