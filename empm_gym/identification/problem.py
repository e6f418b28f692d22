"""What identification works on: the simulated :class:`Scene`, the :class:`Observations` it is fitted
to, the camera :class:`Views`, the parameter space (:class:`ParamSpace`) and a batched forward
simulator (:func:`simulate_frames`).

A scene replays a recording: particles sampled at frame 0 (interior filled), end-effectors following
the recorded positions (velocity during frame interval t -> t+1 = (p[t+1] - p[t]) * fps, grip flag of
frame t), a table plane with Coulomb friction. Frames are ``1 / fps`` seconds apart; each frame interval
is split into as many equal substeps as the CFL limit of the stiffest material requires.
"""

from __future__ import annotations

import logging
import math
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import warp as wp

from empm_gym.sim import (EndEffectorConfig, GridConfig, MaterialConfig, ModelBuilder, SimulationDiverged,
                          SolverConfig, SolverMPM, TableConfig, stable_dt)
from empm_gym.sim.config import end_effector_speed
from empm_gym.perception.recording import quat_angular_velocity
from empm_gym.sim.effects import BASE_PARAMETERS, PARAMETERS, parameter

_log = logging.getLogger(__name__)

__all__ = [
    "Scene",
    "Observations",
    "Views",
    "ParamSpace",
    "PARAM_NAMES",
    "simulate_frames",
    "substeps_for",
    "quat_angular_velocity",
]

#: Identifiable parameters: the base model's (E [Pa], nu [-], density [kg/m^3]) and every effect parameter of
#: :mod:`empm_gym.sim.effects` (yield_stress [Pa], viscosity [Pa s], the table's ``friction`` [-], grip_friction,
#: stiffness_slope_1..3, fracture_strain, fracture_softening).
PARAM_NAMES = tuple(BASE_PARAMETERS) + tuple(PARAMETERS)

_NU_LO, _NU_HI = -1.0, 0.5
# a table node layer sits this fraction of a cell below the table height (see Scene.grid_config)
_TABLE_NODE_EPS = 1.0e-4


@dataclass
class Scene:
    """A recording replayed in the simulator (all SI units).

    ``particles`` [N, 3] (m) and ``volumes`` [N] (m^3) are the frame-0 body; ``ee_positions`` [T, K, 3] (m),
    ``ee_grip`` [T, K] (0/1) and optional ``ee_orientations`` [T, K, 4] (x, y, z, w) drive the
    end-effectors described by ``ee_configs``. ``material`` holds the values of the parameters that are
    not identified (and the starting values of those that are, unless ``init`` is given to the fit).
    ``table_friction`` [-] is the table's Coulomb coefficient (``table`` gives its height; None: no table).
    ``dx`` (m) is the grid cell (default: from the particle volumes at 8 particles per cell); ``grid``
    overrides the automatic grid box around the motion. ``motion_bounds`` ((lo, hi), m) is the box that
    the object was seen to occupy over the recording: the automatic grid then spans it and the
    end-effector path with a ``motion_margin`` (m) around them, instead of the generous guess of half the
    body's largest extent around the end-effector path (for a 30 cm rope that guess is a 4.7x larger
    grid, and on the CPU the empty nodes cost as much as the particles). ``dt_materials`` are materials
    whose stable step bounds the substep too, besides those simulated: a fit that passes the stiffest
    corners of its search box gets the same substeps for every evaluation, so that its loss is a function
    of the parameters alone (not of which other candidates share the batch; MPM's result depends on dt by
    about as much as the effects the doctor weighs). ``deterministic``: every simulation of the scene is the
    same to the bit on every run, on a GPU too (``SolverConfig.deterministic``).
    """

    particles: np.ndarray
    volumes: np.ndarray
    fps: float
    ee_configs: Sequence[EndEffectorConfig] = ()
    ee_positions: Optional[np.ndarray] = None
    ee_grip: Optional[np.ndarray] = None
    ee_orientations: Optional[np.ndarray] = None
    material: MaterialConfig = field(default_factory=MaterialConfig)
    table: Optional[TableConfig] = field(default_factory=TableConfig)
    table_friction: Optional[float] = None
    dx: Optional[float] = None
    grid: Optional[GridConfig] = None
    gravity: Tuple[float, float, float] = (0.0, 0.0, -9.81)
    cfl: float = 0.4
    device: Optional[str] = None
    motion_bounds: Optional[Tuple[Sequence[float], Sequence[float]]] = None
    motion_margin: float = 0.03
    dt_materials: Tuple[MaterialConfig, ...] = ()
    deterministic: bool = False

    def __post_init__(self):
        x = np.asarray(self.particles, np.float64)
        if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
            raise ValueError(f"Scene.particles must have shape [N, 3] with N > 0, got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("Scene.particles holds non-finite positions")
        self.particles = x
        vol = np.broadcast_to(np.asarray(self.volumes, np.float64), (len(x),)).copy()
        if np.any(vol <= 0) or not np.all(np.isfinite(vol)):
            raise ValueError("Scene.volumes must be finite and > 0 m^3")
        self.volumes = vol
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise ValueError(f"Scene.fps must be a positive frame rate (1/s), got {self.fps!r}")
        K = len(self.ee_configs)
        self.ee_configs = list(self.ee_configs)
        if K:
            p = np.asarray(self.ee_positions, np.float64)
            if p.ndim != 3 or p.shape[1:] != (K, 3) or len(p) < 1:
                raise ValueError(f"Scene.ee_positions must have shape [T, {K}, 3], got {p.shape}")
            self.ee_positions = p
            g = np.ones((len(p), K)) if self.ee_grip is None else np.asarray(self.ee_grip)
            if g.shape != (len(p), K) or not np.all((g == 0) | (g == 1)):
                raise ValueError(f"Scene.ee_grip must have shape [{len(p)}, {K}] with values 0/1, got {g.shape}")
            self.ee_grip = g.astype(np.int32)
            if self.ee_orientations is not None:
                q = np.asarray(self.ee_orientations, np.float64)
                if q.shape != (len(p), K, 4):
                    raise ValueError(f"Scene.ee_orientations must have shape [{len(p)}, {K}, 4], got {q.shape}")
                self.ee_orientations = q / np.linalg.norm(q, axis=-1, keepdims=True)
        else:
            self.ee_positions = None
            self.ee_grip = None
        if self.table_friction is None:
            self.table_friction = self.table.friction if self.table is not None else 0.0
        if self.dx is None:
            self.dx = float(np.round(np.cbrt(np.median(self.volumes) * 8.0), 5))

    # -- derived --------------------------------------------------------------------------
    @property
    def num_frames(self) -> Optional[int]:
        """Frames of end-effector motion (None without end-effectors: any horizon)."""
        return None if self.ee_positions is None else len(self.ee_positions)

    @property
    def particle_radius(self) -> float:
        """Half the mean particle spacing (m), used to draw particles into images."""
        return 0.5 * float(np.cbrt(np.mean(self.volumes)))

    def ee_velocities(self, frames: int) -> np.ndarray:
        """[frames-1, K, 3] m/s: finite differences of the recorded positions times fps."""
        K = len(self.ee_configs)
        if not K:
            return np.zeros((frames - 1, 0, 3))
        self._check_frames(frames)
        return np.diff(self.ee_positions[:frames], axis=0) * self.fps

    def ee_omegas(self, frames: int) -> np.ndarray:
        K = len(self.ee_configs)
        if not K or self.ee_orientations is None:
            return np.zeros((frames - 1, K, 3))
        self._check_frames(frames)
        return quat_angular_velocity(self.ee_orientations[:frames], self.fps)

    def ee_max_speed(self, frames: int, start_frame: int = 0) -> float:
        """Largest speed [m/s] of an end-effector's surface over the intervals of frames ``start_frame`` to
        ``frames - 1``: its centre's speed plus its turn's (angular speed times its reach), for the time step."""
        if not len(self.ee_configs) or frames - start_frame < 2:
            return 0.0
        return end_effector_speed(self.ee_velocities(frames)[start_frame:], self.ee_omegas(frames)[start_frame:],
                                  self.ee_configs)

    def _check_frames(self, frames):
        if self.num_frames is not None and frames > self.num_frames:
            raise ValueError(f"Scene: asked for {frames} frames but the end-effector controls hold {self.num_frames}")

    def grid_config(self) -> GridConfig:
        """The grid: ``self.grid`` or a box around the particles and the end-effector path."""
        if self.grid is not None:
            return self.grid
        dx = self.dx
        lo, hi = self.particles.min(0), self.particles.max(0)
        ext = float(np.max(hi - lo))
        if self.motion_bounds is not None:
            m = float(self.motion_margin)
            lo = np.minimum(lo, np.asarray(self.motion_bounds[0], float)) - m
            hi = np.maximum(hi, np.asarray(self.motion_bounds[1], float)) + m
            if self.ee_positions is not None:
                p = self.ee_positions.reshape(-1, 3)
                lo, hi = np.minimum(lo, p.min(0) - m), np.maximum(hi, p.max(0) + m)
        elif self.ee_positions is not None:
            p = self.ee_positions.reshape(-1, 3)
            # the object moves with the end-effectors: keep room for it around their whole path
            lo = np.minimum(lo, p.min(0) - 0.5 * ext)
            hi = np.maximum(hi, p.max(0) + 0.5 * ext)
        pad = 4.0 * dx
        lower, upper = lo - pad, hi + pad
        if self.table is not None:
            lower[2] = min(self.particles[:, 2].min(), self.table.height) - 3.0 * dx
        lower = np.floor(lower / dx) * dx
        upper = np.ceil(upper / dx) * dx
        if self.table is not None:
            # The solver applies the table to the grid nodes at or below its height, so the contact
            # plane it simulates is the highest node layer not above the table. Put a node layer on the
            # table (a hair below it, so that float32 rounding of the node position keeps it a table
            # node): otherwise a table measured 0.1 mm low drops the effective contact a whole cell.
            h = float(self.table.height)
            k = math.ceil((h - lower[2]) / dx)
            lower[2] = h - k * dx - _TABLE_NODE_EPS * dx
            upper[2] = lower[2] + math.ceil((upper[2] - lower[2]) / dx - 1e-9) * dx
        return GridConfig(lower=tuple(lower), upper=tuple(upper), dx=dx)

    def builder(self, materials: Sequence[MaterialConfig], frictions: Sequence[float]) -> ModelBuilder:
        """A ModelBuilder with one world per material (all with this scene's particles and end-effectors)."""
        b = ModelBuilder(self.grid_config(), gravity=self.gravity, table=self.table)
        for m, mu in zip(materials, frictions):
            w = b.add_world(m, table_friction=float(mu))
            b.add_particles(w, self.particles, self.volumes)
            for k, cfg in enumerate(self.ee_configs):
                q = (0, 0, 0, 1) if self.ee_orientations is None else self.ee_orientations[0, k]
                b.add_end_effector(w, cfg, self.ee_positions[0, k], q)
        return b

    def with_material(self, material: MaterialConfig, table_friction: Optional[float] = None) -> "Scene":
        return replace(self, material=material,
                       table_friction=self.table_friction if table_friction is None else table_friction)


@dataclass
class Observations:
    """Measurements of a recording in the world frame (m), at ``fps`` frames per second.

    ``points``: one fused object point set [n_t, 3] per frame. Optional ``tracks`` [T, M, 3] tracked
    surface points with ``visibility`` [T, M] (bool; occluded entries are ignored), ``colors``: per-frame
    colours [n_t, 3] in [0, 1] of ``points``. ``surface``: the points sample the object's measured surface
    (depth cameras), not simulation particles; identification then compares them with the frame-0 surface
    carried by the simulated body instead of with particle centres.

    A frame after the first may hold no points: the object wholly hidden there (a hand or a plate over it). Such a
    frame is not scored (:attr:`seen`; the losses and the doctor leave it out, its tracks count as occluded);
    frame 0, which places the body, must see it, and so must one later frame at least.

    ``track_weight`` (0 < w <= 1): the tracks' share of the loss against tracks without a 2D tracker's error
    (:func:`~.data.track_noise`): identification's tracking term is multiplied by it, the doctor's held-out median
    tracking error by its square root.
    """

    fps: float
    points: Sequence[np.ndarray]
    tracks: Optional[np.ndarray] = None
    visibility: Optional[np.ndarray] = None
    colors: Optional[Sequence[np.ndarray]] = None
    surface: bool = False
    track_weight: float = 1.0

    def __post_init__(self):
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise ValueError(f"Observations.fps must be a positive frame rate (1/s), got {self.fps!r}")
        if not (0.0 < self.track_weight <= 1.0):
            raise ValueError(f"Observations.track_weight must lie in (0, 1], got {self.track_weight!r}")
        pts = []
        for t, p in enumerate(self.points):
            a = np.asarray(p, np.float64)
            if a.ndim != 2 or a.shape[1] != 3:
                raise ValueError(f"Observations.points[{t}] must have shape [n, 3], got {a.shape}")
            if len(a) == 0 and t == 0:
                raise ValueError("Observations.points[0] is empty: frame 0 places the body and must see the object")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Observations.points[{t}] holds non-finite values")
            pts.append(a)
        if len(pts) < 2:
            raise ValueError(f"Observations need at least 2 frames, got {len(pts)}")
        self.points = pts
        T = len(pts)
        if sum(len(a) > 0 for a in pts[1:]) == 0:
            raise ValueError(f"Observations: none of frames 1..{T - 1} holds an observed point (the object is hidden "
                             f"after frame 0): nothing to compare a simulation with")
        if (self.tracks is None) != (self.visibility is None):
            raise ValueError("Observations.tracks and Observations.visibility must be given together")
        if self.tracks is not None:
            tr = np.asarray(self.tracks, np.float64)
            vis = np.asarray(self.visibility, bool)
            if tr.ndim != 3 or tr.shape[0] != T or tr.shape[2] != 3:
                raise ValueError(f"Observations.tracks must have shape [{T}, M, 3], got {tr.shape}")
            if vis.shape != tr.shape[:2]:
                raise ValueError(f"Observations.visibility must have shape {tr.shape[:2]}, got {vis.shape}")
            if not np.all(np.isfinite(tr[vis])):
                raise ValueError("Observations.tracks holds non-finite positions where visible")
            self.tracks, self.visibility = tr, vis
        if self.colors is not None:
            cols = [np.asarray(c, np.float64) for c in self.colors]
            if len(cols) != T or any(c.shape != p.shape for c, p in zip(cols, pts)):
                raise ValueError("Observations.colors must give one [n_t, 3] colour array per frame matching points")
            self.colors = cols

    @property
    def num_frames(self) -> int:
        return len(self.points)

    @property
    def seen(self) -> np.ndarray:
        """[T] bool: the frames that hold observed points (the others show the object wholly hidden)."""
        return np.array([len(p) > 0 for p in self.points], bool)


@dataclass
class Views:
    """Calibrated cameras with, per frame, object masks and colour images.

    ``masks[t]`` and ``images[t]`` give one entry per camera ([H, W] bool; [H, W, 3] uint8 or float in
    [0, 1]); any object indexable by frame works (a list, or a lazy reader).
    """

    cameras: Sequence
    masks: Optional[Sequence] = None
    images: Optional[Sequence] = None


class ParamSpace:
    """Map between SI parameters and the unconstrained vector z that optimisers see.

    Each parameter's coordinate follows its registry entry (:func:`empm_gym.sim.effects.parameter`):
    "log" parameters live in log space relative to their reference scale (E / 1e6 Pa as in the paper,
    density / 1e3 kg/m^3, yield_stress / 1e3 Pa, viscosity / 10 Pa s, ...), "linear" ones (the stiffness
    slopes, which may be negative) as value / scale, and nu = -1 + 1.5 * sigmoid(z) stays in (-1, 0.5).
    ``bounds`` (SI, per parameter) are enforced by clamping z.
    """

    def __init__(self, names: Sequence[str], bounds: Dict[str, Tuple[float, float]]):
        names = tuple(names)
        if not names:
            raise ValueError(f"params must name at least one of {', '.join(PARAM_NAMES)}")
        for n in names:
            if n not in PARAM_NAMES:
                raise ValueError(f"unknown parameter {n!r}; allowed: {', '.join(PARAM_NAMES)}")
        if len(set(names)) != len(names):
            raise ValueError(f"params lists a parameter twice: {names}")
        self.names = names
        self.bounds = {}
        for n in names:
            if n not in bounds:
                raise ValueError(f"ParamSpace: missing bounds for {n!r}")
            lo, hi = (float(v) for v in bounds[n])
            t = parameter(n).transform
            if n == "nu":
                ok, allowed = lo < hi and lo > _NU_LO and hi < _NU_HI, "-1 < lo < hi < 0.5"
            elif t == "log":
                ok, allowed = lo < hi and lo > 0, "0 < lo < hi"
            else:
                vlo, vhi = parameter(n).valid
                ok, allowed = vlo <= lo < hi <= vhi, f"{vlo:g} <= lo < hi <= {vhi:g}"
            if not ok:
                raise ValueError(f"bounds for {n!r} must satisfy {allowed}, got ({lo}, {hi})")
            self.bounds[n] = (lo, hi)
        self.z_lo = np.array([self.to_z1(n, self.bounds[n][0]) for n in names])
        self.z_hi = np.array([self.to_z1(n, self.bounds[n][1]) for n in names])

    @staticmethod
    def to_z1(name: str, value: float) -> float:
        if name == "nu":
            s = (value - _NU_LO) / (_NU_HI - _NU_LO)
            return float(np.log(s / (1.0 - s)))
        p = parameter(name)
        if p.transform == "log":
            return float(np.log(value / p.scale))
        return float(value / p.scale)

    @staticmethod
    def from_z1(name: str, z):
        """SI value of one coordinate; works for floats, numpy arrays and torch tensors."""
        p = None if name == "nu" else parameter(name)
        try:
            import torch

            if isinstance(z, torch.Tensor):
                if name == "nu":
                    return _NU_LO + (_NU_HI - _NU_LO) * torch.sigmoid(z)
                return p.scale * torch.exp(z) if p.transform == "log" else p.scale * z
        except ImportError:  # pragma: no cover
            pass
        if name == "nu":
            return _NU_LO + (_NU_HI - _NU_LO) / (1.0 + np.exp(-z))
        return p.scale * np.exp(z) if p.transform == "log" else p.scale * z

    def to_z(self, values: Dict[str, float]) -> np.ndarray:
        return np.array([self.to_z1(n, values[n]) for n in self.names])

    def from_z(self, z) -> Dict[str, float]:
        return {n: float(self.from_z1(n, float(v))) for n, v in zip(self.names, z)}

    def clamp(self, z: np.ndarray) -> np.ndarray:
        return np.clip(z, self.z_lo, self.z_hi)

    def material(self, values: Dict[str, float], base: MaterialConfig, base_friction: float):
        """(MaterialConfig, table friction) with the identified values substituted into ``base`` (a fitted
        table friction is also set in the material's ``friction``)."""
        mat = base.replace(**{n: float(v) for n, v in values.items()})
        return mat, float(values.get("friction", base_friction))


def substeps_for(scene: Scene, materials: Sequence[MaterialConfig], max_ee_speed: float,
                 margin: float = 0.9) -> Tuple[int, float]:
    """(substeps per frame, dt [s]) keeping dt below ``margin`` times the stable limit of the stiffest (and
    most viscous) material, of ``materials`` and of the scene's ``dt_materials``."""
    dt_max = margin * stable_dt(list(materials) + list(scene.dt_materials), scene.dx, scene.cfl, max_ee_speed)
    n = max(1, int(math.ceil((1.0 / scene.fps) / dt_max)))
    return n, 1.0 / (scene.fps * n)


#: Substeps one CUDA graph of :class:`_ForwardSim` holds (even: a chunk ends in the state it started from).
#: A frame's substeps are replayed as chunks of this many and one chunk of the rest, not as one graph of the
#: whole frame: capturing launches every kernel of a graph from Python (about 4 launches a substep), and a
#: frame of a stiff rope at 5 mm takes 879 substeps, captured anew for each simulation a diagnosis builds (a
#: body, a clock); replaying 14 graphs a frame instead of one costs a few microseconds each.
GRAPH_CHUNK = 64


def frame_chunks(substeps: int, chunk: int = GRAPH_CHUNK) -> Tuple[int, ...]:
    """The substeps of each CUDA graph a frame of ``substeps`` replays, in order: whole chunks of ``chunk``
    (an even number), then the rest."""
    if substeps < 1 or chunk < 2 or chunk % 2:
        raise ValueError(f"frame_chunks: substeps must be >= 1 and chunk even and >= 2, got {substeps}, {chunk}")
    whole, rest = divmod(substeps, chunk)
    return (chunk,) * whole + ((rest,) if rest else ())


class _ForwardSim:
    """A batched model of a scene (one world per candidate) for forward-only rollouts."""

    def __init__(self, scene: Scene, materials: Sequence[MaterialConfig], frictions: Sequence[float]):
        self.scene = scene
        #: on CUDA, replay each frame's substeps from CUDA graphs (:func:`frame_chunks`) captured at its first
        #: frames (a few thousand particles are otherwise bound by launching kernels from Python)
        self.graph = True
        self.model = scene.builder(materials, frictions).finalize(scene.device, requires_grad=False)
        self.solver = SolverMPM(self.model, SolverConfig(cfl=scene.cfl, check_every=0,
                                                         deterministic=scene.deterministic))
        self._own_stream = None  # made on the first queued rollout on CUDA (:meth:`steps`)
        self._kept = None  # rollouts from rest with ``reuse``: their states, control, CUDA graphs (:meth:`steps`)

    def set(self, materials, frictions):
        self.model.set_materials(list(materials))
        self.model.world_table_friction.assign(np.asarray(frictions, np.float32))

    def run(self, frames: int, *, state=None, start_frame: int = 0, velocities=None, omegas=None, grips=None,
            on_frame=None, reuse: bool = False, queued: bool = False):
        """Simulate frames start_frame -> start_frame + frames - 1; returns (positions [frames, W, N, 3], diverged worlds, final state).

        ``velocities`` / ``omegas`` [frames-1, K, 3] and ``grips`` [frames-1, K] override the scene's controls;
        ``reuse`` and ``queued`` as :meth:`steps` (queued, ``on_frame`` sees states still being computed).
        """
        steps = self.steps(frames, state=state, start_frame=start_frame, velocities=velocities, omegas=omegas,
                           grips=grips, reuse=reuse, queued=queued)
        while True:
            try:
                t, a = next(steps)
            except StopIteration as done:
                return done.value
            if on_frame is not None:
                on_frame(t, a)

    def steps(self, frames: int, *, state=None, start_frame: int = 0, velocities=None, omegas=None, grips=None,
              queued: bool = False, reuse: bool = False):
        """:meth:`run` a frame at a time: a generator that yields ``(frame, state it ends in)`` after each frame
        and returns :meth:`run`'s result.

        ``queued`` (CUDA): each frame's substeps, the copy of its positions and its divergence check are queued
        on this simulation's own stream and read back once, after the last frame (the states yielded are then
        still being computed). Advanced in turn (:func:`run_together`), the frames of several simulations run
        side by side on one GPU, where each alone, a few thousand particles a world, leaves most of it idle.
        The positions are the same either way; on a CPU, ``queued`` changes nothing.

        ``reuse`` (a rollout from rest, ``state`` None): its states and control are this simulation's own, kept
        from one such rollout to the next on the same substeps (set back to rest at the start), and so are the
        CUDA graphs of their frames' substeps (:func:`frame_chunks`): a fit that simulates the same scene
        generation after generation captures them once instead of once a generation (a capture launches every
        kernel of its substeps from Python: on a rope pulled apart at 5 mm, 400-900 substeps a frame, most of the
        host's time). The positions are the same; the final state returned is overwritten by the next such
        rollout."""
        sc, m = self.scene, self.model
        W, N, K = m.world_count, len(sc.particles), m.ee_count
        end = start_frame + frames
        vel = sc.ee_velocities(end)[start_frame:] if velocities is None else np.asarray(velocities)
        om = sc.ee_omegas(end)[start_frame:] if omegas is None else np.asarray(omegas)
        grip = (sc.ee_grip[start_frame:end - 1] if K else None) if grips is None else np.asarray(grips)
        speed = end_effector_speed(vel, om, sc.ee_configs)
        sub, dt = substeps_for(sc, m.materials, speed)
        graphs = {}  # (id(state a chunk starts from), its substeps) -> (its CUDA graph, a, b after it)
        if reuse and state is None:
            if self._kept is None or self._kept["clock"] != (sub, dt):
                self._kept = {"clock": (sub, dt), "rest": m.state(), "a": m.state(), "b": m.state(),
                              "ctrl": m.control(), "graphs": {}}
            kept = self._kept
            a, b = kept["a"].assign(kept["rest"]), kept["b"].assign(kept["rest"])
            ctrl, graphs = kept["ctrl"], kept["graphs"]
        else:
            a = state if state is not None else m.state()
            b = m.state()
            ctrl = m.control()
        seq = None
        if K and frames > 1:  # every frame's commands on the device at once; each frame copies its own there
            n = frames - 1
            seq = ctrl.sequence(np.broadcast_to(np.asarray(vel[:n], np.float32)[:, None], (n, W, K, 3)),
                                np.broadcast_to(np.asarray(om[:n], np.float32)[:, None], (n, W, K, 3)),
                                np.broadcast_to(np.asarray(grip[:n])[:, None], (n, W, K)))
        out = np.empty((frames, W, N, 3), np.float32)
        out[0] = a.particle_x.numpy().reshape(W, N, 3)
        bad = set()
        stream = self._stream() if queued and m.device.is_cuda else None
        if stream is not None:
            x_dev = wp.empty(frames * W * N, dtype=wp.vec3, device=m.device)
            flags_dev = wp.zeros((frames, W), dtype=int, device=m.device)
            stream.wait_stream(m.device.stream)  # what set() and the states' creation queued comes first

        every = self.solver.config.sort_every

        def substeps(a, b, n):  # n substeps: returns (the state they end in, the other)
            for i in range(n):  # P2G's particle order re-sorted at the same substeps in a graph's every replay
                self.solver.step(a, b, ctrl, dt, guards=False, sort=every > 0 and i % every == 0)
                a, b = b, a
            return a, b

        use_graph = self.graph and m.device.is_cuda
        plan = frame_chunks(sub, GRAPH_CHUNK)
        for t in range(frames - 1):
            with wp.ScopedStream(stream, sync_enter=False) if stream is not None else nullcontext():
                if seq is not None:  # copied into the control's arrays, which the graphs read
                    ctrl.set_step(seq, t)
                for n in plan:
                    key = (id(a), n)
                    if use_graph and key not in graphs:
                        try:
                            with wp.ScopedCapture(device=m.device) as cap:
                                a1, b1 = substeps(a, b, n)
                            graphs[key] = (cap.graph, a1, b1)  # captured, not yet run
                        except Exception as exc:  # a device or driver that cannot capture: kernel by kernel
                            _log.warning("forward simulation: CUDA graph capture failed (%s); launching kernels one "
                                         "by one", exc)
                            use_graph = False
                    if use_graph:
                        g, a1, b1 = graphs[key]
                        wp.capture_launch(g)
                        a, b = a1, b1
                    else:
                        a, b = substeps(a, b, n)
                if stream is not None:
                    wp.copy(x_dev, a.particle_x, dest_offset=(t + 1) * W * N, count=W * N)
                    self.solver.queue_check(a, flags_dev[t + 1])
            if stream is None:
                try:
                    self.solver.check_state(a, step=t + 1)
                except SimulationDiverged as exc:
                    bad.update(exc.worlds)
                    if len(bad) == W:
                        out[t + 1:] = np.nan
                        return out, sorted(bad), a
                out[t + 1] = a.particle_x.numpy().reshape(W, N, 3)
                if bad:
                    out[t + 1, sorted(bad)] = np.nan
            yield t + 1, a
        if stream is not None:
            m.device.stream.wait_stream(stream)  # later work on the model (the next set()) waits for these frames
            wp.synchronize_stream(stream)  # and so does the host, before reading what they wrote
            out[1:] = x_dev.numpy().reshape(frames, W, N, 3)[1:]
            flags = flags_dev.numpy()
            for w in range(W):
                hit = np.nonzero(flags[1:, w])[0]
                if hit.size:  # NaN from the frame the world diverged at, as run() marks it frame by frame
                    bad.add(w)
                    out[1 + hit[0]:, w] = np.nan
        return out, sorted(bad), a

    def _stream(self):
        """This simulation's own CUDA stream (:meth:`steps` with ``queued``)."""
        if self._own_stream is None:
            self._own_stream = wp.Stream(self.model.device)
        return self._own_stream


def run_together(rollouts: Sequence) -> list:
    """Advance several rollouts (:meth:`_ForwardSim.steps` generators, ``queued`` on CUDA) a frame each in
    turn until all are done; returns each one's result, in order. Simulations of different bodies or grids,
    which cannot be worlds of one model, so share one GPU at once."""
    results: list = [None] * len(rollouts)
    live = list(range(len(rollouts)))
    while live:
        for i in list(live):
            try:
                next(rollouts[i])
            except StopIteration as done:
                results[i] = done.value
                live.remove(i)
    return results


def simulate_frames(scene: Scene, materials: Sequence[MaterialConfig], frictions: Optional[Sequence[float]] = None,
                    frames: Optional[int] = None) -> np.ndarray:
    """Particle positions [frames, W, N, 3] (m) of the scene simulated with each material (one world each),
    recorded at every frame; diverged worlds are NaN from the frame where they diverged."""
    materials = list(materials)
    frictions = [scene.table_friction] * len(materials) if frictions is None else list(frictions)
    if len(frictions) != len(materials):
        raise ValueError(f"simulate_frames: {len(materials)} materials but {len(frictions)} frictions")
    frames = frames or scene.num_frames
    if frames is None or frames < 1:
        raise ValueError("simulate_frames: give frames (the scene has no end-effector controls)")
    sim = _ForwardSim(scene, materials, frictions)
    x, _, _ = sim.run(frames)
    return x
