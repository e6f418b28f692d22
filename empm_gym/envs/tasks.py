"""Task definitions: the scene (object, end-effectors, grid), the action mapping and the target family.

A :class:`Task` is plain geometry and numbers; :class:`empm_gym.envs.core.BatchedCore` turns one into a
batch of simulated worlds. Units: metres, seconds, Pascals; z up, table at z = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence, Tuple

import numpy as np

from ..sim import EndEffectorConfig, GridConfig, sample_box, sample_cylinder

__all__ = ["Task", "RopeReshapeTask", "RopeReshapeV1Task", "DoughFlattenTask", "DoughFlattenV1Task", "DoughShapeTask",
           "DoughShapeV1Task", "TASKS"]


def _exact_count(rng: np.random.Generator, lower, upper, inside, count: int) -> np.ndarray:
    """``count`` points uniformly distributed in the region ``inside(points) -> bool`` of a bounding box."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    out = []
    have = 0
    while have < count:
        cand = rng.uniform(lower, upper, size=(4 * count, 3))
        cand = cand[inside(cand)]
        out.append(cand)
        have += len(cand)
    return np.concatenate(out)[:count]


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Task:
    """Base class: the fields every task sets and the methods it implements."""

    name: str = ""
    dx: float = 0.015
    """Default grid cell size [m]."""
    grid_lower: Tuple[float, float, float] = (-0.2, -0.2, -0.05)
    """Lower corner of the simulation grid [m]."""
    grid_upper: Tuple[float, float, float] = (0.2, 0.2, 0.1)
    """Upper corner of the simulation grid [m]."""
    ee_lower: Tuple[float, float, float] = (-0.15, -0.15, 0.0)
    """Lower corner of the box the end-effector centres are kept in [m]."""
    ee_upper: Tuple[float, float, float] = (0.15, 0.15, 0.08)
    """Upper corner of the box the end-effector centres are kept in [m]."""
    max_speed: float = 0.2
    """End-effector speed [m/s] per axis that an action of 1 commands."""
    grip_control: bool = False
    """Whether the action carries one grip command per end-effector."""
    default_grip: Tuple[int, ...] = ()
    """Grip flags (1 = closed) when the action carries none, and at reset."""
    control_dt: float = 0.05
    """Control period [s]: one env step."""
    max_episode_steps: int = 100
    material: Dict = field(default_factory=dict)
    """Default material (keys of MaterialConfig plus "friction", the table's Coulomb coefficient)."""
    success_chamfer: float = 0.01
    """Chamfer distance [m] below which the episode counts as solved."""
    occupancy_voxel: float = 0.02
    """Voxel size [m] of the occupancy IoU."""
    target_points: int = 1024
    """Number of points in the dense target point cloud (IoU and obs/chamfer subsets)."""
    chamfer_points: int = 128
    """Object and target points of the reward's Chamfer distance. Two random samples of one shape are
    apart by about half their mean spacing: for a 144 cm^3 slab 5.8 mm at 128 points, 3.1 mm at 1024."""
    camera_height: float = 0.3
    """Height [m] of the top-down depth camera."""

    def end_effectors(self) -> Sequence[Tuple[EndEffectorConfig, Tuple[float, float, float]]]:
        """(config, initial position [m]) of every end-effector."""
        raise NotImplementedError(f"{type(self).__name__}.end_effectors: abstract, each task defines it")

    def object_particles(self, dx: float, particles_per_cell: float):
        """(positions [n, 3] m, rest volumes [n] m^3) of the object at rest."""
        raise NotImplementedError(f"{type(self).__name__}.object_particles: abstract, each task defines it")

    def sample_target(self, rng: np.random.Generator) -> np.ndarray:
        """A target point cloud [target_points, 3] drawn from the task's family."""
        raise NotImplementedError(f"{type(self).__name__}.sample_target: abstract, each task defines it")

    def grid(self, dx: float) -> GridConfig:
        """The grid for cell size dx [m]: three cell layers below the table (z = 0) whatever dx is."""
        lower = (self.grid_lower[0], self.grid_lower[1], -3.0 * dx)
        upper = (self.grid_upper[0], self.grid_upper[1], max(self.grid_upper[2], 9.0 * dx))
        return GridConfig(lower=lower, upper=upper, dx=dx)

    def target_subset_indices(self, count: int) -> np.ndarray:
        """Indices of the ``count`` target points the reward's Chamfer distance and the observation use: the
        first ``count`` (targets are i.i.d. samples of the shape unless a task orders them)."""
        return np.arange(min(int(count), self.target_points))

    def observed_particle_key(self, rest_positions: np.ndarray) -> Optional[np.ndarray]:
        """A sort key [n] of the object's particles at rest that orders the "state" observation's particles, or
        None (a fixed random order)."""
        return None

    @property
    def ee_count(self) -> int:
        return len(self.end_effectors())

    @property
    def action_dim(self) -> int:
        return 3 * self.ee_count + (self.ee_count if self.grip_control else 0)


# ---------------------------------------------------------------------------- rope
ROPE_SHAPES = ("straight", "arc", "U", "S")


@dataclass
class RopeReshapeTask(Task):
    name: str = "RopeReshape"
    dx: float = 0.015
    grid_lower: Tuple[float, float, float] = (-0.25, -0.25, -0.045)
    grid_upper: Tuple[float, float, float] = (0.25, 0.25, 0.105)
    ee_lower: Tuple[float, float, float] = (-0.19, -0.19, 0.012)
    ee_upper: Tuple[float, float, float] = (0.19, 0.19, 0.06)
    max_speed: float = 0.25
    grip_control: bool = False
    default_grip: Tuple[int, ...] = (1, 1)
    max_episode_steps: int = 100
    material: Dict = field(default_factory=lambda: {"E": 3.0e4, "nu": 0.3, "density": 1000.0,
                                                   "yield_stress": None, "friction": 0.4})
    success_chamfer: float = 0.012
    occupancy_voxel: float = 0.02
    length: float = 0.30
    """Rope length [m]."""
    radius: float = 0.012
    """Rope radius [m]."""
    gripper_radius: float = 0.02
    """Radius [m] of the two spherical grippers."""
    shapes: Tuple[str, ...] = ROPE_SHAPES
    """Target family drawn from at reset."""
    ordered_targets: bool = False
    """Store the target's points in the order of arc length along its curve (v1); v0's are in random order."""

    def end_effectors(self):
        cfg = EndEffectorConfig(shape="sphere", radius=self.gripper_radius, friction=0.8)
        x = 0.5 * self.length - 0.8 * self.gripper_radius
        return [(cfg, (-x, 0.0, self.radius)), (cfg, (x, 0.0, self.radius))]

    def object_particles(self, dx, ppc):
        h = 0.5 * self.length
        return sample_cylinder((-h, 0.0, self.radius), (h, 0.0, self.radius), self.radius, dx, ppc)

    def curve(self, kind: str, rng: np.random.Generator, n: int = 400) -> np.ndarray:
        """Centre line [n, 2] (xy, m) of a target of the given kind, of the rope's length, centred."""
        L = self.length
        s = np.linspace(0.0, 1.0, n)
        if kind == "straight":
            pts = np.stack([(s - 0.5) * L, np.zeros(n)], 1)
        elif kind == "arc":
            phi = rng.uniform(math.pi / 3, math.pi)
            R = L / phi
            a = (s - 0.5) * phi
            pts = np.stack([R * np.sin(a), R * (1 - np.cos(a))], 1)
        elif kind == "U":
            R = rng.uniform(0.03, 0.045)
            leg = 0.5 * (L - math.pi * R)
            t = s * L
            pts = np.zeros((n, 2))
            m1 = t < leg
            m2 = (t >= leg) & (t <= leg + math.pi * R)
            m3 = t > leg + math.pi * R
            pts[m1] = np.stack([-R * np.ones(m1.sum()), leg - t[m1]], 1)
            a = (t[m2] - leg) / R
            pts[m2] = np.stack([-R * np.cos(a), -R * np.sin(a)], 1)
            pts[m3] = np.stack([R * np.ones(m3.sum()), t[m3] - leg - math.pi * R], 1)
        elif kind == "S":
            phi = rng.uniform(math.pi / 2, math.pi)
            R = 0.5 * L / phi
            t = s * 2 * phi
            pts = np.zeros((n, 2))
            m1 = t <= phi
            a = t[m1]
            pts[m1] = np.stack([R * np.sin(a), R * (1 - np.cos(a))], 1)
            end = np.array([R * math.sin(phi), R * (1 - math.cos(phi))])
            tang = np.array([math.cos(phi), math.sin(phi)])
            nrm = np.array([-tang[1], tang[0]])  # left normal at the joint; the second arc turns right
            a = t[~m1] - phi
            centre = end - R * nrm
            ang0 = math.atan2(nrm[1], nrm[0])
            pts[~m1] = centre + R * np.stack([np.cos(ang0 - a), np.sin(ang0 - a)], 1)
        else:
            raise ValueError(f"rope target shape must be one of {ROPE_SHAPES}, got {kind!r}")
        return pts - pts.mean(0)

    def sample_target(self, rng):
        kind = self.shapes[int(rng.integers(len(self.shapes)))]
        c = self.curve(kind, rng)
        ang = rng.uniform(-math.pi / 6, math.pi / 6)
        c = c @ _rot_z(ang)[:2, :2].T + rng.uniform(-0.02, 0.02, size=2)
        seg = np.diff(c, axis=0)
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
        u = rng.uniform(0.0, cum[-1], self.target_points)
        if self.ordered_targets:
            u = np.sort(u)
        k = np.clip(np.searchsorted(cum, u) - 1, 0, len(seg) - 1)
        f = ((u - cum[k]) / np.maximum(cum[k + 1] - cum[k], 1e-12))[:, None]
        centre = c[k] + f * seg[k]
        tang = seg[k] / np.maximum(np.linalg.norm(seg[k], axis=1, keepdims=True), 1e-12)
        nrm = np.stack([-tang[:, 1], tang[:, 0]], 1)
        r = self.radius * np.sqrt(rng.uniform(0, 1, self.target_points))
        a = rng.uniform(0, 2 * math.pi, self.target_points)
        xy = centre + (r * np.cos(a))[:, None] * nrm
        z = self.radius + r * np.sin(a)
        return np.concatenate([xy, z[:, None]], 1)


@dataclass
class RopeReshapeV1Task(RopeReshapeTask):
    """RopeReshape, version 1: the same rope, grippers, targets and reward, with ordered observations.

    v0 observes 64 rope particles in a fixed random order and 64 target points drawn at random along the
    target curve, in random order: a policy has to compare two unordered clouds, and PPO stayed at 22 %
    success after 3 M steps (benchmarks/RESULTS.md). Here the observed particles run from one end of the
    rope to the other (sorted by their position along the rope at rest), and the target points are
    stored in the order of arc length along the target curve, so that the observed target points (and the
    reward's Chamfer subset) are evenly strided along it, from the end nearest the first gripper's side
    (x < 0 before the rotation) to the other. The shapes the task asks for and how success is scored are
    v0's.
    """

    name: str = "RopeReshape-v1"

    ordered_targets: bool = True

    def target_subset_indices(self, count: int) -> np.ndarray:
        n = min(int(count), self.target_points)
        return np.unique(np.linspace(0, self.target_points - 1, n).round().astype(int)) if n > 1 else np.arange(n)

    def observed_particle_key(self, rest_positions):
        return np.asarray(rest_positions)[:, 0]


# ---------------------------------------------------------------------------- dough
@dataclass
class _DoughTask(Task):
    dx: float = 0.01
    grid_lower: Tuple[float, float, float] = (-0.13, -0.13, -0.03)
    grid_upper: Tuple[float, float, float] = (0.13, 0.13, 0.1)
    material: Dict = field(default_factory=lambda: {"E": 3.0e4, "nu": 0.3, "density": 1000.0,
                                                   "yield_stress": 1.0e3, "friction": 0.6})
    occupancy_voxel: float = 0.015
    size: Tuple[float, float, float] = (0.06, 0.06, 0.04)
    """Size [m] of the dough lump (a box on the table, centred at the origin)."""

    @property
    def volume(self) -> float:
        return float(np.prod(self.size))

    def object_particles(self, dx, ppc):
        sx, sy, sz = self.size
        return sample_box((-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz), dx, ppc)


@dataclass
class DoughFlattenTask(_DoughTask):
    name: str = "DoughFlatten"
    ee_lower: Tuple[float, float, float] = (-0.03, -0.03, 0.0)
    ee_upper: Tuple[float, float, float] = (0.03, 0.03, 0.07)
    max_speed: float = 0.1
    max_episode_steps: int = 50
    success_chamfer: float = 0.005
    tool_half_extents: Tuple[float, float, float] = (0.05, 0.05, 0.008)
    """Half sizes [m] of the flat pressing tool (a box)."""
    heights: Tuple[float, float] = (0.012, 0.022)
    """Range [m] of the target height."""
    target_shift: float = 0.01
    """Largest xy shift [m] of the target."""

    def end_effectors(self):
        cfg = EndEffectorConfig(shape="box", half_extents=self.tool_half_extents, friction=0.3)
        return [(cfg, (0.0, 0.0, self.size[2] + self.tool_half_extents[2] + 0.01))]

    def sample_target(self, rng):
        h = rng.uniform(*self.heights)
        area = self.volume / h
        shift = np.append(rng.uniform(-self.target_shift, self.target_shift, 2), 0.0)
        if rng.uniform() < 0.5:  # disc footprint
            r = math.sqrt(area / math.pi)
            inside = lambda p: (p[:, 0] ** 2 + p[:, 1] ** 2) <= r * r
            lo, hi = (-r, -r, 0.0), (r, r, h)
        else:  # square footprint
            a = 0.5 * math.sqrt(area)
            inside = lambda p: np.ones(len(p), bool)
            lo, hi = (-a, -a, 0.0), (a, a, h)
        return _exact_count(rng, lo, hi, inside, self.target_points) + shift


@dataclass
class DoughFlattenV1Task(DoughFlattenTask):
    """DoughFlatten, version 1: a tool thick enough to press with, and targets the press can reach.

    Two things made v0 unsolvable. Its tool is 1.6 cm thick, under two cells at dx = 1 cm: grid nodes in
    its upper half take the top face's normal, so dough pressed into the tool flows through it and is
    then carried up when the tool lifts. And its targets are shifted by up to 1 cm, which a flat press
    cannot do (it moves dough sideways only by friction). Here the tool is 4 cm thick, its bottom stays
    4 mm above the table, and the target slab (height 1.4-2.4 cm, disc or square footprint aligned with
    the lump, the dough's volume) sits where the lump is. The reward's Chamfer uses 1024 points (v0:
    128, whose sampling floor of about 6 mm lies above v0's success threshold of 5 mm). A vertical
    press to the right depth, then lifting the tool, leaves the dough 2.8-3.5 mm (Chamfer) from the
    target, near the 3.1 mm floor of two 1024-point samples of one slab; success is below 4 mm, the
    lump at rest starts 5.5-8 mm away. How deep is right depends on the yield stress (spring-back):
    with the default dough, planning with a yield stress 5x too high presses too deep (measured at
    dx 1 cm: 4.6-5.8 mm instead of 2.9-3.2 mm).
    """

    name: str = "DoughFlatten-v1"
    chamfer_points: int = 1024
    ee_lower: Tuple[float, float, float] = (-0.03, -0.03, 0.024)
    ee_upper: Tuple[float, float, float] = (0.03, 0.03, 0.09)
    max_episode_steps: int = 30
    tool_half_extents: Tuple[float, float, float] = (0.05, 0.05, 0.02)
    heights: Tuple[float, float] = (0.014, 0.024)
    success_chamfer: float = 0.004
    target_shift: float = 0.0
    """Largest xy shift [m] of the target (v0: 0.01)."""


DOUGH_SHAPES = ("bar", "L", "ring")


@dataclass
class DoughShapeTask(_DoughTask):
    name: str = "DoughShape"
    ee_lower: Tuple[float, float, float] = (-0.1, -0.1, 0.008)
    ee_upper: Tuple[float, float, float] = (0.1, 0.1, 0.07)
    max_speed: float = 0.15
    grip_control: bool = True
    default_grip: Tuple[int, ...] = (0, 0)
    max_episode_steps: int = 100
    success_chamfer: float = 0.006
    gripper_radius: float = 0.015
    """Radius [m] of the two spherical grippers / pushers."""
    shapes: Tuple[str, ...] = DOUGH_SHAPES
    """Target family drawn from at reset."""

    def end_effectors(self):
        cfg = EndEffectorConfig(shape="sphere", radius=self.gripper_radius, friction=0.5)
        x = 0.5 * self.size[0] + self.gripper_radius + 0.005
        return [(cfg, (-x, 0.0, 0.02)), (cfg, (x, 0.0, 0.02))]

    def sample_target(self, rng):
        kind = self.shapes[int(rng.integers(len(self.shapes)))]
        V = self.volume
        h = rng.uniform(0.025, 0.03)
        if kind == "bar":
            w = rng.uniform(0.035, 0.045)
            L = V / (h * w)
            lo, hi = (-L / 2, -w / 2, 0.0), (L / 2, w / 2, h)
            inside = lambda p: np.ones(len(p), bool)
        elif kind == "L":
            w = rng.uniform(0.03, 0.035)
            arm = 0.5 * (V / (h * w) + w)  # two arms of length arm overlapping in a w x w corner
            lo, hi = (-arm / 2, -arm / 2, 0.0), (arm / 2, arm / 2, h)
            inside = lambda p: (p[:, 0] <= -arm / 2 + w) | (p[:, 1] <= -arm / 2 + w)
        elif kind == "ring":
            t = rng.uniform(0.02, 0.025)
            # pi (ro^2 - ri^2) h = V with ro - ri = t  ->  ro + ri = V / (pi h t)
            s = V / (math.pi * h * t)
            ro, ri = 0.5 * (s + t), 0.5 * (s - t)
            lo, hi = (-ro, -ro, 0.0), (ro, ro, h)
            inside = lambda p: (p[:, 0] ** 2 + p[:, 1] ** 2 <= ro * ro) & (p[:, 0] ** 2 + p[:, 1] ** 2 >= ri * ri)
        else:
            raise ValueError(f"dough target shape must be one of {DOUGH_SHAPES}, got {kind!r}")
        pts = _exact_count(rng, lo, hi, inside, self.target_points)
        pts -= np.append(pts[:, :2].mean(0), 0.0)
        ang = rng.uniform(-math.pi, math.pi)
        return pts @ _rot_z(ang).T + np.append(rng.uniform(-0.01, 0.01, 2), 0.0)


@dataclass
class DoughShapeV1Task(_DoughTask):
    """DoughShape, version 1: squeeze the lump between two plates into a bar of a given width and position.

    Why v0 was unsolvable: its two spheres (3 cm across) push a hole into the dough where they touch and
    the dough flows around them, so no sequence of pushes turns the lump into v0's bars, Ls and rings of
    any orientation (MPC closed 10-35 % of the distance, never reaching its 6 mm threshold, and 128
    Chamfer points have a sampling floor of about 6 mm for this volume). Here two vertical plates (3 cm
    thick, 10 cm long, 6 cm tall, touching the table) stand on either side of the lump along x and move
    in x and y. A squeeze to a gap g leaves a bar along y whose sides bulge and whose top rises; the target
    is the box that a squeeze to g leaves (fitted to the squeezed dough at dx 1 cm with the default
    material: width w = g + 1.0-1.4 cm, height 5.0 cm at w = 3.4 cm falling to 4.8 cm at w = 4.0 cm,
    the length from the volume), with w in [3.4, 4.0] cm (gaps of about 2-3 cm) and its centre line
    shifted by up to 1 cm in x, which a squeeze that moves both plates the same way can reach.

    The plates reach 5 mm below the table plane so that they also push the grid's table layer: with a
    bottom above it, the lowest half-cell of dough stays stuck to the table (friction 0.6) and spreads
    under the plates. Measured at dx 1 cm with the default dough: a scripted squeeze and release ends
    2.8-3.0 mm (Chamfer, 1024 points) from the box fitted to it; the lump at rest starts 4.3-6.0 mm from
    the targets. Success is below 3.5 mm.
    """

    name: str = "DoughShape-v1"
    chamfer_points: int = 1024
    ee_lower: Tuple[float, float, float] = (-0.1, -0.02, 0.025)
    ee_upper: Tuple[float, float, float] = (0.1, 0.02, 0.025)
    max_speed: float = 0.1
    grip_control: bool = False
    default_grip: Tuple[int, ...] = (0, 0)
    max_episode_steps: int = 30
    success_chamfer: float = 0.0035
    plate_half_extents: Tuple[float, float, float] = (0.015, 0.05, 0.03)
    """Half sizes [m] of the two plates (x: thickness, y: length, z: height)."""
    widths: Tuple[float, float] = (0.034, 0.040)
    """Range [m] of the target bar's width (along x)."""
    height_at_widths: Tuple[float, float] = (0.050, 0.048)
    """Target height [m] at the two ends of ``widths`` (linear in between)."""
    target_shift: float = 0.01
    """Largest x shift [m] of the target's centre line."""

    def end_effectors(self):
        hx, _, hz = self.plate_half_extents
        cfg = EndEffectorConfig(shape="box", half_extents=self.plate_half_extents, friction=0.3)
        x = 0.5 * self.size[0] + hx + 0.005
        z = hz - 0.005  # the bottom 5 mm below the table: the plates push the table's node layer too
        return [(cfg, (-x, 0.0, z)), (cfg, (x, 0.0, z))]

    def sample_target(self, rng):
        (w0, w1), (h0, h1) = self.widths, self.height_at_widths
        w = rng.uniform(w0, w1)
        h = h0 + (h1 - h0) * (w - w0) / (w1 - w0) if w1 > w0 else h0
        L = self.volume / (w * h)
        c = rng.uniform(-self.target_shift, self.target_shift)
        return _exact_count(rng, (c - w / 2, -L / 2, 0.0), (c + w / 2, L / 2, h), lambda p: np.ones(len(p), bool),
                            self.target_points)


#: task name -> class. A version after v0 is part of the name ("DoughFlatten-v1"), as in the env id.
TASKS = {"RopeReshape": RopeReshapeTask, "RopeReshape-v1": RopeReshapeV1Task, "DoughFlatten": DoughFlattenTask,
         "DoughFlatten-v1": DoughFlattenV1Task, "DoughShape": DoughShapeTask, "DoughShape-v1": DoughShapeV1Task}
