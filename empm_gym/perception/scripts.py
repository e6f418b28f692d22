"""Scripted manipulations for synthetic recordings (``empm synth --script``).

A script is a function of the frame count T and the object's rest geometry (an axis-aligned box on the
table, ``lower = (-sx/2, -sy/2, 0)``, ``upper = (sx/2, sy/2, sz)``) that returns the end-effector centres
``positions[T, K, 3]`` (m), the grip ``grip[T, K]`` (1 = closed) and the end-effector shapes. Scripts
place their end-effectors from the geometry alone, so every script runs on every object (rope, dough,
block), and they never depend on the material or on any effect: the controls of two recordings of the
same object, script and frame count are identical whatever the physics.

Scripts (phases as fractions of the recording; "long axis" = x, the object's longest side):

* ``press-release``: a flat pusher above the centre presses down by 45 % of the height, holds, lifts
  away; the body is left to settle (plasticity: a permanent dent).
* ``push-slide``: a vertical plate behind the object (-y side) pushes it 4 cm along +y in a quick stroke
  and withdraws at once; the object slides on by itself (table friction: how far it slides).
* ``squeeze-lift``: two closed grippers (spheres over the ends of an elongated object, side pads pressed
  6 mm into a compact one) take it, lift it by 6 cm, hold, put it back down and open (gripper slip: the
  object sags / slides down relative to the grippers).
* ``pull-apart``: two closed grippers at the ends of the long axis pull them apart by 40 % of the length
  each, hold, open and move away (fracture: it tears; heterogeneous stiffness: one side stretches more).
* ``squeeze-ring``: two plates squeeze the object across its shortest horizontal side by 30 %, hold, then
  jump away within one frame interval, so the body springs back and rings (viscosity: damped ringing).

``default`` is the object's historic script (:func:`default_script`: rope lift-and-stretch, dough
squeeze), used when no script is named.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Tuple

import numpy as np

__all__ = ["ObjectGeometry", "ScriptResult", "SCRIPTS", "run_script"]


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


def _sphere(r):
    return {"shape": "sphere", "radius": float(r)}


def _box(h):
    return {"shape": "box", "half_extents": tuple(float(v) for v in h)}


def _press_release(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    hz = 0.006
    hx = min(0.25 * sx, 0.02) if g.elongated else 0.3 * sx
    hy = 0.5 * sy + 0.01
    start = np.array([[0.0, 0.0, sz + hz + 0.002]])
    _, a, b, c, d, _ = _phases(T, [0.08, 0.3, 0.12, 0.15, 0.35])
    t = np.arange(T, dtype=np.float64)
    depth = 0.45 * sz + 0.002
    z = -depth * _ramp(t, a, b) + (depth + 0.04) * _ramp(t, c, d)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 2] += z
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz)
    return ScriptResult(pos, np.zeros((T, 1), np.int32), [_box((hx, hy, hz))], (lo, hi))


def _push_slide(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    hy = 0.006
    hx = 0.5 * sx + 0.01
    hz = 0.5 * min(sz, 0.03)
    start = np.array([[0.0, -sy / 2 - hy - 0.002, hz + 0.002]])
    _, a, b, c, _ = _phases(T, [0.1, 0.22, 0.08, 0.6])
    t = np.arange(T, dtype=np.float64)
    push = 0.04
    y = push * _ramp(t, a, b)
    # withdraw quickly backwards and up, so the object slides on freely
    back = (push + 0.03) * _ramp(t, b, c)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 1] += y - back
    pos[:, 0, 2] += 0.03 * _ramp(t, b, c)
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2 + 0.2, sz)
    return ScriptResult(pos, np.zeros((T, 1), np.int32), [_box((hx, hy, hz))], (lo, hi))


def _end_grippers(g: ObjectGeometry, press: float):
    """Start centres [2, 3] and shapes of two grippers at the ends of the long axis (x)."""
    sx, sy, sz = g.size
    if g.elongated:
        r = 0.75 * max(sy, sz) + 1e-9
        x0, zc = sx / 2 - 0.015, sz + 0.002
        return np.array([[-x0, 0.0, zc], [x0, 0.0, zc]]), [_sphere(r)] * 2, 0.0
    hx, hy, hz = 0.012, 0.5 * sy + 0.008, 0.4 * sz
    x0 = sx / 2 + hx + 0.002
    start = np.array([[-x0, 0.0, hz + 0.003], [x0, 0.0, hz + 0.003]])
    return start, [_box((hx, hy, hz))] * 2, press + 0.002


def _squeeze_lift(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    start, ees, press = _end_grippers(g, 0.006)
    _, a, b, c, d, e, f, _ = _phases(T, [0.05, 0.1, 0.22, 0.25, 0.15, 0.05, 0.18])
    t = np.arange(T, dtype=np.float64)
    inward = press * _ramp(t, a, b) - (press + 0.01) * _ramp(t, e, f)
    lift = 0.06 * (_ramp(t, b, c) - _ramp(t, d, e)) + 0.03 * _ramp(t, e, f)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 0] += inward
    pos[:, 1, 0] -= inward
    pos[:, :, 2] += lift[:, None]
    grip = np.zeros((T, 2), np.int32)
    grip[b:e] = 1
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz + 0.07)
    return ScriptResult(pos, grip, ees, (lo, hi))


def _pull_apart(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    start, ees, press = _end_grippers(g, 0.006)
    _, a, b, c, d, e, _ = _phases(T, [0.05, 0.1, 0.35, 0.2, 0.08, 0.22])
    t = np.arange(T, dtype=np.float64)
    pull = 0.4 * sx
    inward = press * _ramp(t, a, b)
    out = pull * _ramp(t, b, c)
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 0] += inward - out
    pos[:, 1, 0] -= inward - out
    pos[:, :, 2] += 0.03 * _ramp(t, d, e)[:, None]
    grip = np.zeros((T, 2), np.int32)
    grip[b:d] = 1
    lo, hi = (-sx / 2 - pull - 0.01, -sy / 2, 0.0), (sx / 2 + pull + 0.01, sy / 2, sz)
    return ScriptResult(pos, grip, ees, (lo, hi))


def _squeeze_ring(T: int, g: ObjectGeometry) -> ScriptResult:
    sx, sy, sz = g.size
    ax = 1 if g.elongated else 0                       # squeeze across the shortest horizontal side
    other = 1 - ax
    w = g.size[ax]
    th = 0.006
    h = [0.0, 0.0, 0.4 * sz if not g.elongated else 0.45 * sz]
    h[ax] = th
    h[other] = 0.5 * g.size[other] + 0.008
    c0 = w / 2 + th + 0.002
    start = np.zeros((2, 3))
    start[0, ax], start[1, ax] = -c0, c0
    start[:, 2] = h[2] + 0.002
    _, a, b, c, _ = _phases(T, [0.08, 0.3, 0.1, 0.52])
    t = np.arange(T, dtype=np.float64)
    sq = (0.15 * w + 0.002) * _ramp(t, a, b)
    jump = np.where(t >= c + 1, 0.15 * w + 0.002 + 0.04, 0.0)   # away within one frame interval
    d = sq - jump
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, ax] += d
    pos[:, 1, ax] -= d
    lo, hi = (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz + 0.02)
    return ScriptResult(pos, np.zeros((T, 2), np.int32), [_box(h)] * 2, (lo, hi))


SCRIPTS: Dict[str, Callable[[int, ObjectGeometry], ScriptResult]] = {
    "press-release": _press_release,
    "push-slide": _push_slide,
    "squeeze-lift": _squeeze_lift,
    "pull-apart": _pull_apart,
    "squeeze-ring": _squeeze_ring,
}


def run_script(name: str, T: int, geometry: ObjectGeometry) -> ScriptResult:
    """The script ``name`` (a key of :data:`SCRIPTS`) for ``T`` frames on an object of ``geometry``."""
    if name not in SCRIPTS:
        raise ValueError(f"unknown script {name!r}; known: default, {', '.join(SCRIPTS)}")
    if int(T) < 2:
        raise ValueError(f"frames must be >= 2, got {T!r}")
    return SCRIPTS[name](int(T), geometry)
