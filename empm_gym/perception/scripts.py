"""Scripted manipulations for synthetic recordings (``empm synth --script``).

A script is a function of the frame count T and the object's rest geometry (an axis-aligned box on the
table, ``lower = (-sx/2, -sy/2, 0)``, ``upper = (sx/2, sy/2, sz)``) that returns the end-effector centres
``positions[T, K, 3]`` (m), the grip ``grip[T, K]`` (1 = closed) and the end-effector shapes. Scripts
place their end-effectors from the geometry alone, so every script runs on every object (rope, dough,
block), and they never depend on the material or on any effect: the controls of two recordings of the
same object, script and frame count are identical whatever the physics.

Scripts (phases as fractions of the recording; "long axis" = x, the object's longest side):

* ``press-release``: a flat pusher (an 8 cm punch across the middle of an elongated object, a plate over
  the whole top of a compact one) presses down by 35 % of the height (45 % on an elongated object),
  holds, lifts away; the body is left to settle (plasticity: a permanent dent).
* ``push-slide``: a vertical plate behind the object (-y side) pushes it 4 cm along +y with constant
  acceleration and at once withdraws back and up; the object slides on by itself (table friction: how
  far it slides).
* ``squeeze-lift``: two closed grippers (spheres over the ends of an elongated object, clamps enclosing
  the outer quarters of a compact one) lift it by 6 cm, hold, put it back down to 4 mm above its start,
  open and move away (gripper slip: the object slides down / drops out of the grip).
* ``pull-apart``: the same grippers pull the ends apart by 20 % of the length each (15 % on an elongated
  object), hold, open and move away (fracture: it tears; heterogeneous stiffness: one side stretches more).
* ``squeeze-ring``: a plate over the whole top squeezes the object against the table by 30 % of its
  height, holds, then snaps 8 cm up within one frame interval, so the body springs back, hops and rings
  (viscosity: the rebound loses energy, a lower hop and damped ringing).
* ``lift-end``: one end gripper holds its end where it lies, the other lifts its end by half the length and
  (a compact object) draws it outwards, held there to the end (fracture: the body tears).
* ``drag``: one closed gripper on the -x end drags the object 4 cm along +x, stops, opens and moves away; the
  object slides on by itself (table friction: how far it slides).
* ``lift-twist``: the end grippers lift the object by 4 cm; then the +x gripper turns by 60 degrees about the
  long axis (a wrist roll, about its own centre) while the other holds still, and both hold to the end (a
  stiffness field: one side twists more; gripper slip: the twisted body turns back in the grip; fracture: it
  tears). The only script whose end-effectors rotate: ``orientations`` is set.

``default`` (resolved in :mod:`empm_gym.perception.synth`) is the object's historic script: rope
lift-and-stretch, dough squeeze, block press-release.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

__all__ = ["ObjectGeometry", "ScriptResult", "SCRIPTS", "axis_angle_quaternions", "run_script"]


def _smooth(s):
    """Cosine ease from 0 to 1 over s in [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * s)


def _phases(T: int, fractions: List[float]) -> List[int]:
    """Frame boundaries of consecutive phases with the given fractions of T (each at least one interval)."""
    b = [0]
    for f in np.cumsum(fractions)[:-1]:
        b.append(max(b[-1] + 1, int(round(f * (T - 1)))))
    b.append(max(b[-1] + 1, T - 1))
    return b


def _ramp(t, a, b):
    return _smooth((t - a) / max(b - a, 1))


@dataclass(frozen=True)
class ObjectGeometry:
    """Rest bounding box of an object lying centred on the table (m)."""

    size: Tuple[float, float, float]

    @property
    def elongated(self) -> bool:
        sx, sy, sz = self.size
        return sx > 3.0 * max(sy, sz)


@dataclass
class ScriptResult:
    positions: np.ndarray
    """End-effector centres [T, K, 3] (m)."""
    grip: np.ndarray
    """[T, K] int32, 1 = closed."""
    end_effectors: List[dict]
    """Per end-effector kwargs of :class:`empm_gym.sim.EndEffectorConfig` (shape, radius, half_extents)."""
    reach: Tuple[Tuple[float, float, float], Tuple[float, float, float]]
    """(lower, upper) corners (m) of the region the object may reach (for sizing the grid)."""
    orientations: Optional[np.ndarray] = None
    """End-effector orientations [T, K, 4], unit quaternions (x, y, z, w); None: they never turn (identity)."""

    def quaternions(self) -> np.ndarray:
        """``orientations``, the identity where the script leaves them unset."""
        if self.orientations is not None:
            return np.asarray(self.orientations, np.float64)
        T, K = self.positions.shape[:2]
        return np.tile([0.0, 0.0, 0.0, 1.0], (T, K, 1))


#: Half thickness of pushers and plates (m): thick against the grid, so that no grid node inside one sees
#: its far face as the nearest (a thin plate lets material tunnel into it and then drags it along).
_THICK = 0.02

#: Gap [m] between a plate over the top and the object at frame 0: the cameras (40 deg elevation) see the
#: top surface under a plate hovering this high; a plate just above the object hides the top from every
#: camera and frame 0, from which the body is rebuilt, would lose it.
_CLEAR = 0.03


def _sphere(r):
    return {"shape": "sphere", "radius": float(r)}


def _box(h):
    return {"shape": "box", "half_extents": tuple(float(v) for v in h)}


def _press_release(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    hz = _THICK
    # an 8 cm punch across the middle of an elongated object, a flat press over all of a compact one (a
    # narrow punch sunk deep into a block grips it by its sides and lifts it on the way out)
    hx = min(0.25 * sx, 0.04) if g.elongated else 0.5 * sx + 0.01
    hy = 0.5 * sy + 0.01
    start = np.array([[0.0, 0.0, sz + hz + _CLEAR]])
    _, a, b, c, d, _ = _phases(T, [0.08, 0.3, 0.12, 0.15, 0.35])
    t = np.arange(T, dtype=np.float64)
    depth = (0.45 if g.elongated else 0.35) * sz + _CLEAR
    z = -depth * _ramp(t, a, b) + (depth + 0.04) * _ramp(t, c, d)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 2] += z
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz)
    return ScriptResult(pos, np.zeros((T, 1), np.int32), [_box((hx, hy, hz))], (lo, hi))


def _push_slide(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    hy = _THICK
    hx = 0.5 * sx + 0.01
    hz = 0.5 * min(sz, 0.03)
    start = np.array([[0.0, -sy / 2 - hy - 0.002, hz + 0.002]])
    _, a, b, _ = _phases(T, [0.1, 0.2, 0.7])
    t = np.arange(T, dtype=np.float64)
    push = 0.04
    s = np.clip((t - a) / max(b - a, 1), 0.0, 1.0)
    y = push * s**2                                    # constant acceleration to 2 push / duration
    # then at once back and up, out of the way: the object slides on by itself
    w = max(2, int(round(0.05 * T)))
    back = _ramp(t, b, b + w)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 1] += y - (push + 0.03) * back
    pos[:, 0, 2] += 0.03 * back
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2 + 0.2, sz)
    return ScriptResult(pos, np.zeros((T, 1), np.int32), [_box((hx, hy, hz))], (lo, hi))


def _end_grippers(g: ObjectGeometry):
    """Start centres [2, 3], shapes and the release direction of two grippers over the ends of the long
    axis (x): spheres just above the ends of an elongated object (they cover its upper part; released
    upwards), clamps enclosing the outer quarter of a compact one (from 4 mm above the table to 2 cm
    above its top, reaching 2.5 cm beyond its end, so that the inner face is the nearest face of every
    point they hold; released outwards along x)."""
    sx, sy, sz = g.size
    if g.elongated:
        r = 0.75 * max(sy, sz)
        x0, zc = sx / 2 - 0.015, sz + 0.002
        return np.array([[-x0, 0.0, zc], [x0, 0.0, zc]]), [_sphere(r)] * 2, np.array([0.0, 0.0, 1.0])
    inner = sx / 2 - 0.25 * sx
    hx, hy, hz = (sx / 2 + 0.025 - inner) / 2, sy / 2 + 0.01, (sz + 0.016) / 2
    x0 = inner + hx
    start = np.array([[-x0, 0.0, 0.004 + hz], [x0, 0.0, 0.004 + hz]])
    return start, [_box((hx, hy, hz))] * 2, np.array([1.0, 0.0, 0.0])


def _release(pos, t, a, b, away):
    """Move the end grippers (the -x one, then the +x one) 3 cm away along ``away`` (mirrored in x for the
    first) between frames a and b."""
    r = 0.03 * _ramp(t, a, b)[:, None]
    for k in range(pos.shape[1]):
        pos[:, k] += r * (away * [(-1.0, 1.0)[k], 1.0, 1.0])


def _squeeze_lift(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    start, ees, away = _end_grippers(g)
    # the lifted hold lasts to 80 % of the recording, so that the last 30 % (what a fit holds out) still
    # shows whether the object stays in the grip
    _, a, b, c, d, e, _ = _phases(T, [0.06, 0.22, 0.52, 0.1, 0.05, 0.05])
    t = np.arange(T, dtype=np.float64)
    # put it back down to 4 mm above where it was: a body pressed into the table by rigid grippers
    # jumps when they let go
    lift = 0.06 * _ramp(t, a, b) - 0.056 * _ramp(t, c, d)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, :, 2] += lift[:, None]
    _release(pos, t, d, e, away)
    grip = np.zeros((T, 2), np.int32)
    grip[:d] = 1
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz + 0.07)
    return ScriptResult(pos, grip, ees, (lo, hi))


def _pull_apart(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    start, ees, away = _end_grippers(g)
    # held apart to the end of the recording: the last 30 % (what a fit holds out) shows the stretched or
    # torn body, not its chaotic spring-back after a release
    _, a, b, _ = _phases(T, [0.06, 0.4, 0.54])
    t = np.arange(T, dtype=np.float64)
    pull = (0.15 if g.elongated else 0.2) * sx
    out = pull * _ramp(t, a, b)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 0] -= out
    pos[:, 1, 0] += out
    grip = np.ones((T, 2), np.int32)
    lo, hi = (-sx / 2 - pull - 0.01, -sy / 2, 0.0), (sx / 2 + pull + 0.01, sy / 2, sz)
    return ScriptResult(pos, grip, ees, (lo, hi))


def _lift_end(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    start, ees, _ = _end_grippers(g)
    # one end held where it lies; the other lifted by half the length and, on a compact object, drawn outwards
    # by a fifth of it, held there to the end: the body stretches and bends over the held end while its
    # underside slides along the table towards the lifted end (as far as the table's friction lets it). A rope
    # is only lifted: drawn out as well, its ends 1.3 lengths apart, it stretched by a third and the
    # synthesiser's grid (dx = 5 mm, 30 frames) tore it at the lifted gripper with no fracture in its material,
    # on every seed (benchmarks/RESULTS.md, session 52); lifted alone it stays whole, and a fracture tears it
    draw = 0.0 if g.elongated else 0.2
    _, a, b, _ = _phases(T, [0.06, 0.4, 0.54])
    t = np.arange(T, dtype=np.float64)
    s = _ramp(t, a, b)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 1, 2] += 0.5 * sx * s
    pos[:, 1, 0] += draw * sx * s
    grip = np.ones((T, 2), np.int32)
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2 + draw * sx + 0.01, sy / 2, sz + 0.5 * sx)
    return ScriptResult(pos, grip, ees, (lo, hi))


def _drag(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    start, ees, away = _end_grippers(g)
    start, ees = start[:1], ees[:1]
    # a closed gripper on the -x end drags the object 4 cm along +x over the table with constant acceleration,
    # stops, opens and moves away (as squeeze-lift's grippers do): the object slides on by itself (as far as
    # the table's friction lets it). An open gripper left where it stopped caught the rope sliding out of it:
    # the sphere sits in the rope's top, and whether the rope's end snagged on it depended on where the grid's
    # nodes fell (the true rope at friction 0.05, simulated on grids shifted by 0.3 mm and half a cell, ended
    # 4 mm and 43 mm away from itself; benchmarks/RESULTS.md, session 25)
    _, a, b, c, _ = _phases(T, [0.06, 0.34, 0.06, 0.54])
    t = np.arange(T, dtype=np.float64)
    drag = 0.04
    u = np.clip((t - a) / max(b - a, 1), 0.0, 1.0)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 0] += drag * u**2
    _release(pos, t, b, c, away)
    grip = np.zeros((T, 1), np.int32)
    grip[:b] = 1
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2 + 0.15, sy / 2, sz)
    return ScriptResult(pos, grip, ees, (lo, hi))


def axis_angle_quaternions(axis, angles) -> np.ndarray:
    """Unit quaternions (x, y, z, w) [len(angles), 4] of turns by ``angles`` (rad) about the unit ``axis``."""
    a = np.asarray(angles, np.float64)[:, None]
    u = np.asarray(axis, np.float64)
    u = u / np.linalg.norm(u)
    return np.concatenate([np.sin(a / 2) * u, np.cos(a / 2)], axis=1)


def _lift_twist(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    start, ees, _ = _end_grippers(g)
    # lifted clear of the table first, so that nothing but the grippers holds the body while one end turns; the
    # turn runs into the held-out 30 % (a fit on the first 70 % must carry its material past what it saw)
    _, a, b, c, d, _ = _phases(T, [0.06, 0.2, 0.06, 0.42, 0.26])
    t = np.arange(T, dtype=np.float64)
    lift = 0.04
    pos = np.repeat(start[None], T, axis=0)
    pos[:, :, 2] += lift * _ramp(t, a, b)[:, None]
    q = np.tile([0.0, 0.0, 0.0, 1.0], (T, 2, 1))
    q[:, 1] = axis_angle_quaternions((1.0, 0.0, 0.0), np.deg2rad(60.0) * _ramp(t, c, d))
    grip = np.ones((T, 2), np.int32)
    # a turned clamp sweeps its corners about its centre: the reach covers the body turned as a whole
    r = float(np.hypot(sy, sz))
    lo, hi = (-sx / 2, -r, 0.0), (sx / 2, r, sz + lift + r)
    return ScriptResult(pos, grip, ees, (lo, hi), q)


def _squeeze_ring(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    hz = _THICK
    hx, hy = 0.5 * sx + 0.01, 0.5 * sy + 0.01          # a flat plate over the whole top
    start = np.array([[0.0, 0.0, sz + hz + _CLEAR]])
    # the snap comes at half the recording: the first 70 % (what a fit uses) hold the whole hop, which pins
    # down E, and the last 30 % the ringing decaying (a later snap lets a softer elastic body mimic the
    # damped hop)
    _, a, b, c, _ = _phases(T, [0.08, 0.3, 0.12, 0.5])
    t = np.arange(T, dtype=np.float64)
    depth = 0.3 * sz + _CLEAR
    z = -depth * _ramp(t, a, b) + np.where(t >= c + 1, depth + 0.08, 0.0)   # snaps up within one frame
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 2] += z
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz + 0.06)
    return ScriptResult(pos, np.zeros((T, 1), np.int32), [_box((hx, hy, hz))], (lo, hi))


SCRIPTS: Dict[str, Callable[[int, ObjectGeometry], ScriptResult]] = {
    "press-release": _press_release,
    "push-slide": _push_slide,
    "squeeze-lift": _squeeze_lift,
    "pull-apart": _pull_apart,
    "squeeze-ring": _squeeze_ring,
    "lift-end": _lift_end,
    "drag": _drag,
    "lift-twist": _lift_twist,
}


def run_script(name: str, T: int, geometry: ObjectGeometry) -> ScriptResult:
    """The script ``name`` (a key of :data:`SCRIPTS`) for ``T`` frames on an object of ``geometry``."""
    if name not in SCRIPTS:
        raise ValueError(f"unknown script {name!r}; known: default, {', '.join(SCRIPTS)}")
    if int(T) < 2:
        raise ValueError(f"frames must be >= 2, got {T!r}")
    return SCRIPTS[name](int(T), geometry)
