"""Phases of a recording, read from the controls and the observed object points alone.

Every frame gets one of :data:`PHASES`:

``approach``
    no end-effector touches the object yet (frames before the first contact);
``contact``
    an end-effector touches the object but neither holds it still nor moves it (e.g. the gripper
    is closing, or an open finger rests on the object);
``holding``
    a closed gripper touches the object and every touching end-effector is (nearly) still;
``moving``
    an end-effector touches the object (closed or pushing) and at least one touching
    end-effector moves;
``after_release``
    no end-effector touches, contact happened before, and the observed object still moves;
``at_rest``
    no end-effector touches and the observed object is still (after a contact; or the whole
    recording when there is no contact at all).

"Touching" means: the distance from an end-effector's centre to the nearest observed object point,
minus the end-effector's radius, is at most ``contact_dist_m``. "Moving" end-effectors and object are
decided from speeds: an end-effector moves at frame ``t`` when both its backward and forward control
speeds exceed ``still_speed`` (it moves into and out of ``t``: the frame where it arrives on the object
is contact, not motion), the object speed the backward difference of the observed
centroid, median-filtered over ``smooth_frames`` frames (keeps step edges, removes single-frame
noise). Nothing here uses file names, script frame indices or ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np

__all__ = [
    "PHASES",
    "Phase",
    "contact_distances",
    "observed_centroids",
    "object_speed",
    "segment_phases",
    "phase_of_frames",
]

#: Phase names, in their usual order in a recording.
PHASES = ("approach", "contact", "holding", "moving", "after_release", "at_rest")

#: Phases in which some end-effector touches the object.
CONTACT_PHASES = ("contact", "holding", "moving")
#: Phases without contact after a release.
FREE_PHASES = ("after_release", "at_rest")


@dataclass(frozen=True)
class Phase:
    """A run of frames ``start <= t < stop`` (``stop`` exclusive) with one phase ``name``."""

    name: str
    start: int
    stop: int

    @property
    def frames(self) -> range:
        return range(self.start, self.stop)

    def __len__(self) -> int:
        return self.stop - self.start


def ee_sizes(ee_radius, K: int) -> np.ndarray:
    """``[K, 3]`` end-effector sizes: a radius r (sphere) becomes (r, r, -1); a half-extent triple (an
    axis-aligned box, m) stays as it is. ``ee_radius`` is a scalar, ``[K]`` radii or a list mixing both."""
    if np.ndim(ee_radius) == 0:
        return np.tile([float(ee_radius), float(ee_radius), -1.0], (K, 1))
    out = np.zeros((K, 3))
    for k, r in enumerate(list(ee_radius)[:K]):
        out[k] = (float(r), float(r), -1.0) if np.ndim(r) == 0 else np.asarray(r, float).reshape(3)
    return out


def ee_rotations(ee_orientations, T: int, K: int, identity: bool = False) -> Optional[np.ndarray]:
    """``[T, K, 3, 3]`` rotation matrices (the end-effector's axes in world coordinates, as columns) of the
    controls' ``orientations`` ``[T, K, 4]`` (x, y, z, w); when the controls give none (they never turn), None, or
    with ``identity`` the world's axes."""
    if ee_orientations is None:
        return np.broadcast_to(np.eye(3), (T, K, 3, 3)) if identity else None
    from scipy.spatial.transform import Rotation

    q = np.asarray(ee_orientations, dtype=float)[:T].reshape(-1, K, 4)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(len(q), K, 3, 3)


def surface_gap(points: np.ndarray, centre: np.ndarray, size: np.ndarray,
                rot: Optional[np.ndarray] = None) -> np.ndarray:
    """``[n]`` signed distance (m) of points to an end-effector's surface (a sphere of radius size[0] when
    size[2] < 0, else a box of half extents ``size`` along its own axes: the columns of ``rot`` [3, 3], the
    world's where None)."""
    d = np.asarray(points, float).reshape(-1, 3) - np.asarray(centre, float)
    if size[2] < 0:
        return np.linalg.norm(d, axis=1) - size[0]
    if rot is not None:
        d = d @ np.asarray(rot, float)                 # into the box's frame
    q = np.abs(d) - size
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def ee_reach(size: np.ndarray) -> np.ndarray:
    """``[K]`` farthest distance (m) from each end-effector's centre to its surface, from :func:`ee_sizes`."""
    size = np.asarray(size, float).reshape(-1, 3)
    return np.where(size[:, 2] < 0, size[:, 0], np.linalg.norm(np.abs(size), axis=1))


def contact_distances(ee_positions: np.ndarray, ee_radius, obj_points: Sequence[np.ndarray],
                      ee_orientations: Optional[np.ndarray] = None) -> np.ndarray:
    """``[T, K]`` gap (m) between each end-effector's surface and the nearest observed object point.

    ``ee_radius``: per end-effector a radius (sphere) or half extents (a box), see :func:`ee_sizes`;
    ``ee_orientations`` ``[T, K, 4]`` (x, y, z, w) turn the boxes (None: axis-aligned).
    Negative when points lie inside; ``inf`` where a frame has no observed points.
    """
    ee = np.asarray(ee_positions, dtype=float)
    T, K = ee.shape[:2]
    size = ee_sizes(ee_radius, K)
    rot = ee_rotations(ee_orientations, T, K)
    out = np.full((T, K), np.inf)
    for t in range(min(T, len(obj_points))):
        p = np.asarray(obj_points[t], dtype=float).reshape(-1, 3)
        if len(p) == 0:
            continue
        for k in range(K):
            out[t, k] = surface_gap(p, ee[t, k], size[k], None if rot is None else rot[t, k]).min()
    return out


def observed_centroids(obj_points: Sequence[np.ndarray], T: Optional[int] = None) -> np.ndarray:
    """``[T, 3]`` mean of the observed points per frame (NaN where a frame has none)."""
    T = len(obj_points) if T is None else T
    c = np.full((T, 3), np.nan)
    for t in range(min(T, len(obj_points))):
        p = np.asarray(obj_points[t], dtype=float).reshape(-1, 3)
        if len(p):
            c[t] = p.mean(axis=0)
    return c


def _median_filter(x: np.ndarray, w: int) -> np.ndarray:
    if w <= 1 or len(x) == 0:
        return x.copy()
    h = w // 2
    xp = np.concatenate([np.repeat(x[:1], h), x, np.repeat(x[-1:], h)])
    win = np.lib.stride_tricks.sliding_window_view(xp, 2 * h + 1)
    return np.median(win, axis=-1)


def _fill_nan(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float).copy()
    ok = np.isfinite(x)
    if not ok.any():
        return np.zeros_like(x)
    idx = np.arange(len(x))
    x[~ok] = np.interp(idx[~ok], idx[ok], x[ok])
    return x


def backward_speed(positions: np.ndarray, fps: float) -> np.ndarray:
    """Speed (m/s) by backward differences over the first axis; frame 0 copies frame 1."""
    p = np.asarray(positions, dtype=float)
    v = np.zeros(p.shape[:-1])
    if len(p) > 1:
        v[1:] = np.linalg.norm(p[1:] - p[:-1], axis=-1) * fps
        v[0] = v[1]
    return v


def object_speed(centroids: np.ndarray, fps: float, smooth_frames: int = 3) -> np.ndarray:
    """``[T]`` centroid speed (m/s): backward differences, NaN gaps interpolated, median-filtered."""
    return _median_filter(_fill_nan(backward_speed(centroids, fps)), smooth_frames)


def _runs(labels: Sequence[str]) -> List[Phase]:
    out: List[Phase] = []
    start = 0
    for t in range(1, len(labels) + 1):
        if t == len(labels) or labels[t] != labels[start]:
            out.append(Phase(str(labels[start]), start, t))
            start = t
    return out


def _merge_short(phases: List[Phase], min_len: int) -> List[Phase]:
    """Absorb runs shorter than ``min_len`` into the previous run (the first into the next)."""
    if min_len <= 1 or len(phases) <= 1:
        return phases
    labels = []
    for p in phases:
        labels += [p.name] * len(p)
    changed = True
    while changed:
        changed = False
        runs = _runs(labels)
        if len(runs) <= 1:
            break
        for i, r in enumerate(runs):
            if len(r) < min_len:
                new = runs[i - 1].name if i > 0 else runs[i + 1].name
                labels[r.start:r.stop] = [new] * len(r)
                changed = True
                break
    return _runs(labels)


def segment_phases(
    ee_positions: np.ndarray,
    ee_grip: np.ndarray,
    fps: float,
    obj_points: Sequence[np.ndarray],
    ee_radius,
    *,
    contact_dist_m: float = 0.01,
    still_speed: float = 0.01,
    obj_still_speed: float = 0.02,
    smooth_frames: int = 3,
    min_phase_frames: int = 2,
    ee_orientations: Optional[np.ndarray] = None,
) -> List[Phase]:
    """Split frames ``0..T-1`` into consecutive :class:`Phase` runs named from :data:`PHASES`.

    Args:
        ee_positions: ``[T, K, 3]`` end-effector centres from the controls (m).
        ee_grip: ``[T, K]`` gripper state, 1 = closed, 0 = open (pushers: always 0).
        fps: frames per second of the recording.
        obj_points: per frame, the observed object points ``[n_t, 3]`` (m); a frame without any (the object
            wholly hidden, a hand over it) keeps the contact of the frame before it.
        ee_radius: ``[K]`` (or scalar) end-effector radius (m).
        contact_dist_m: an end-effector touches when its surface gap to the nearest observed point
            is at most this (m). Default 1 cm (depth noise plus finger thickness).
        still_speed: an end-effector is still unless both its backward and forward control speeds
            exceed this (m/s).
        obj_still_speed: the object is still below this (median-filtered) observed-centroid
            speed (m/s). Default 2 cm/s: above the centroid jitter of a few-mm depth noise at 30 fps.
        smooth_frames: median-filter window (frames) for the object speed.
        min_phase_frames: runs shorter than this are absorbed into the previous run (1: keep all).
        ee_orientations: ``[T, K, 4]`` (x, y, z, w) from the controls, or None (they never turn): a box's
            faces turn with it, and an end-effector that turns in place moves its surface (by its angular speed
            times its reach), which counts as motion.

    Returns:
        Runs covering ``0..T-1`` in order; ``stop`` is exclusive.
    """
    ee = np.asarray(ee_positions, dtype=float)
    if ee.ndim == 2:
        ee = ee[:, None, :]
    T, K = ee.shape[:2]
    if T == 0:
        return []
    grip = np.asarray(ee_grip, dtype=float).reshape(T, -1) > 0.5
    gap = contact_distances(ee, ee_radius, obj_points, ee_orientations)
    for t in range(1, T):  # a frame where the object is wholly hidden keeps the contact it was last seen in
        if t < len(obj_points) and not len(np.asarray(obj_points[t]).reshape(-1, 3)):
            gap[t] = gap[t - 1]
    touch = gap <= contact_dist_m  # [T, K]
    v_back = backward_speed(ee, fps)  # [T, K]
    if ee_orientations is not None and T > 1:  # the surface of a turning end-effector moves by omega * reach
        from empm_gym.perception.recording import quat_angular_velocity

        w = np.linalg.norm(quat_angular_velocity(np.asarray(ee_orientations, float)[:T].reshape(T, K, 4), fps), axis=-1)
        v_back[1:] += w * ee_reach(ee_sizes(ee_radius, K))
        v_back[0] = v_back[1]
    v_fwd = np.concatenate([v_back[1:], v_back[-1:]], axis=0)
    ee_moving = np.minimum(v_back, v_fwd) > still_speed  # moves into and out of frame t
    obj_moving = object_speed(observed_centroids(obj_points, T), fps, smooth_frames) > obj_still_speed

    any_touch = touch.any(axis=1)
    labels = np.empty(T, dtype=object)
    if any_touch.any():
        first = int(np.argmax(any_touch))
    else:
        first = T  # no contact at all: frames are labelled by the object's motion only
    for t in range(T):
        if any_touch[t]:
            if (ee_moving[t] & touch[t]).any():
                labels[t] = "moving"
            elif (grip[t] & touch[t]).any():
                labels[t] = "holding"
            else:
                labels[t] = "contact"
        elif t < first:
            labels[t] = "approach"
        else:
            labels[t] = "after_release" if obj_moving[t] else "at_rest"
    if first == T:
        labels = np.array(["after_release" if m else "at_rest" for m in obj_moving], dtype=object)
    return _merge_short(_runs(list(labels)), min_phase_frames)


def phase_of_frames(phases: Sequence[Phase], T: int) -> np.ndarray:
    """``[T]`` array of phase names (``""`` for frames no phase covers)."""
    out = np.full(T, "", dtype=object)
    for p in phases:
        out[max(p.start, 0):min(p.stop, T)] = p.name
    return out.astype(str)
