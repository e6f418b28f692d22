"""PGND episodes (kywind/pgnd) read as recordings; used by :class:`~empm_gym.perception.recording.Recording`.

A PGND episode (what PGND's ``experiments/real_world/postprocess.py`` writes, ``episode_<n>/``)::

    <episode>/
      camera_<i>/rgb/%06d.jpg        colour (RealSense bgr8 written by OpenCV: an ordinary RGB JPEG)
      camera_<i>/depth/%06d.png      uint16 depth in millimetres, aligned to the colour image
      camera_<i>/mask/%06d.png       object mask 0/255 (written by PGND's SAM2 step; optional)
      calibration/intrinsics.npy     [C, 3, 3] pinhole intrinsics (pixels)
      calibration/rvecs.npy          [C, 3, 1] Rodrigues vectors, world -> camera (OpenCV)
      calibration/tvecs.npy          [C, 3, 1] translations (m), world -> camera
      robot/%06d.txt                 rows of 3 numbers: per arm its position and its 3x3 orientation, then
                                     one row of gripper positions (see below)
      timestamps.txt                 per frame one timestamp (s) per camera (optional here)

:class:`Recording` detects it by its files (``camera_0/`` or ``calibration/`` and no ``metadata.json``)
and maps it as follows, so that everything that reads recordings (``load_recording``, ``empm identify``,
``evaluate``, ``doctor``) takes it unchanged:

- Cameras: ``x_cam = R x_world + t`` with ``R = Rodrigues(rvec)`` (PGND's ``load_camera`` and ``get_camera``
  build this world-to-camera matrix and back-project depth with its inverse). PGND's world is its
  calibration board's frame, whose z axis points down into the table (its workspace box spans
  z in [-0.65, 0.05] m and its simulator takes -z as up). Our world is z up with the table at z = 0, so
  when the cameras lie at negative z (they look down on the table from above) the world is turned by
  180 degrees about its x axis: ``(x, y, z) -> (x, -y, -z)``, a proper rotation that keeps the table
  at z = 0 and every distance. Cameras already at positive z are taken as they are. Either way the
  choice is logged (logger ``empm_gym.perception``).
- Depth: millimetres (depth scale 0.001 m per unit, as every PGND reader divides by 1000).
- Masks: ``camera_<i>/mask/`` is the object mask (our "simple" form). PGND has no controller masks.
- Robot: ``robot/%06d.txt`` holds 5 rows (one arm) or 9 rows (two arms): for each arm one row with the
  end-effector point in the world (m; PGND's point 0.175 m along the gripper's z axis from the flange,
  between the fingertips) and three rows that are the gripper's x, y and z axes in the world (PGND writes
  ``(R_base2world R_eef2base I).T``, so the end-effector-to-world rotation is that block transposed);
  then one row of raw xArm gripper positions (first entry per arm, the rest 0). A file of one row is a
  position only (PGND's readers accept it too). Positions become ``controls["positions"]`` [T, K, 3]
  and rotations ``controls["orientations"]`` [T, K, 4] (x, y, z, w), both in our z-up world.
- Grip: openness = clip(gripper position / 800, 0, 1) (800 is PGND's ``GRIPPER_OPEN_MAX``, 0 its
  ``GRIPPER_OPEN_MIN``, in ``experiments/real_world/modules_planning/common/xarm.py``; 1 = open). A
  gripper is closed (grip 1) where openness < 0.5, i.e. a position below 400. This is PGND's own rule:
  its simulator moves the grid nodes within the gripper radius with the gripper where ``gripper_open
  < 0.5`` (``pgnd/sim/model.py``) and its planner uses ``< 0.5`` for closed; so a grip means the same
  here as there. Half the range also separates a gripper closed on an object, which stops at the
  object's width (a thin rope: near 0; a thicker body: up to a few hundred), from an open one (800).
  A position-only file has no openness; PGND's readers then use openness 0, i.e. a closed gripper, and
  so does this reader (with a logged warning).

What PGND episodes do not record, and what is assumed instead (each logged as a warning when an
episode is opened):

- The end-effector geometry: spheres of radius 0.04 m (:data:`DEFAULT_EE_RADIUS_M`, PGND's default
  ``model.gripper_radius`` in ``experiments/cfg/model/pgnd.yaml``, the radius within which its simulator
  moves material with a closed gripper). PGND's per-dataset end-effector offsets (``model.eef_t``) live in
  its training configuration, not in the episode, and are not applied.
- The frame rate: from ``timestamps.txt`` (one over the median interval of the first camera's
  timestamps, to 0.001 fps) when present, else 30 fps (:data:`DEFAULT_FPS`; PGND records at 30 fps, ``teleop.py``
  ``record_fps=30``, and its dataset code asserts a frame interval of 1/30 s).

Files are checked as for our layout: a missing, unreadable or inconsistent file raises
:class:`RecordingError` naming it (missing frames, frames beyond the others, wrong shapes, counts
that disagree, rotations that are not rotations). Nothing is ever written into the episode.
"""

from __future__ import annotations

import logging
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from .recording import RecordingError, _check_c2w, _check_intrinsics, _index_frames, _read_npy, _read_png

__all__ = ["is_pgnd_episode", "read_pgnd_episode", "PGNDEpisode", "GRIPPER_OPEN_MAX", "GRIP_CLOSED_BELOW",
           "DEFAULT_EE_RADIUS_M", "DEFAULT_FPS", "DEPTH_SCALE"]

_log = logging.getLogger("empm_gym.perception")

#: xArm gripper position of a fully open gripper (PGND's GRIPPER_OPEN_MAX; 0 = fully closed).
GRIPPER_OPEN_MAX = 800.0
#: openness (0 closed .. 1 open) below which a gripper counts as closed (grip = 1); PGND's own threshold.
GRIP_CLOSED_BELOW = 0.5
#: end-effector sphere radius (m) assumed for PGND episodes (PGND's default model.gripper_radius).
DEFAULT_EE_RADIUS_M = 0.04
#: frame rate (1/s) assumed when an episode has no usable timestamps.txt (PGND records at 30 fps).
DEFAULT_FPS = 30.0
#: metres per depth unit of PGND's depth PNGs (millimetres).
DEPTH_SCALE = 0.001
#: colour frame extensions, in order of preference.
COLOR_EXTS = ("jpg", "jpeg", "png")

_CAMERA_RE = re.compile(r"^camera_(\d+)$")
_FLIP = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x: PGND's z-down board frame -> z up


@dataclass
class PGNDEpisode:
    """What :class:`Recording` takes over from a PGND episode (cameras in our z-up world)."""

    camera_dirs: List[Path]
    intrinsics: np.ndarray  # [C, 3, 3] pixels
    c2w: np.ndarray  # [C, 4, 4] camera-to-world, our world (z up), m
    width: int
    height: int
    fps: float
    num_frames: int
    frame_count_source: str
    controls: Optional[dict]  # positions, orientations, grip, shape, radius (unvalidated)
    controls_source: Optional[Path]
    flipped: bool  # True: world turned 180 deg about x (PGND's z-down board frame)
    depth_scale: float = DEPTH_SCALE
    color_exts: Tuple[str, ...] = COLOR_EXTS
    metadata: dict = field(default_factory=dict)


def is_pgnd_episode(path) -> bool:
    """True if ``path`` looks like a PGND episode (``camera_0/`` or ``calibration/``); metadata.json is checked
    by the caller (a folder with metadata.json is read as our layout)."""
    path = Path(path)
    return (path / "camera_0").is_dir() or (path / "calibration").is_dir()


def not_a_recording_message(path) -> str:
    """The error for a folder that is neither layout (names metadata.json, and PGND episodes inside if any)."""
    path = Path(path)
    msg = (f"{path / 'metadata.json'}: file missing; {path} is neither a recording in our (PhysTwin's) layout "
           f"nor a PGND episode (camera_<i>/, calibration/, robot/)")
    try:
        eps = sorted(n for n in os.listdir(path) if n.startswith("episode_") and is_pgnd_episode(path / n))
    except OSError:
        eps = []
    if eps:
        msg += f"; it holds PGND episodes: open one of them, e.g. {path / eps[0]}"
    return msg


def _rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle, rad), as OpenCV's cv2.Rodrigues."""
    r = np.asarray(rvec, np.float64).reshape(3)
    th = float(np.linalg.norm(r))
    if th < 1e-12:
        return np.eye(3)
    k = r / th
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * Kx + (1.0 - np.cos(th)) * (Kx @ Kx)


def _vectors(path: Path, C: int) -> np.ndarray:
    """rvecs.npy / tvecs.npy as [C, 3] (PGND saves [C, 3, 1]; [C, 3] and [C, 1, 3] are accepted too)."""
    a = _read_npy(path)
    if not (np.issubdtype(a.dtype, np.number) and a.dtype != bool):
        raise RecordingError(f"{path}: must be numeric, got dtype {a.dtype}")
    if a.ndim == 3 and a.shape[1:] in ((3, 1), (1, 3)):
        a = a.reshape(a.shape[0], 3)
    if a.ndim != 2 or a.shape[1] != 3:
        raise RecordingError(f"{path}: must have shape [cameras, 3, 1] (one 3-vector per camera), got {list(a.shape)}")
    if len(a) != C:
        raise RecordingError(f"{path}: camera count mismatch: {len(a)} vectors but the episode has {C} camera "
                             f"folders (camera_0 .. camera_{C - 1}) and calibration/intrinsics.npy {C} matrices")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise RecordingError(f"{path}: holds non-finite values")
    return a


def _camera_dirs(path: Path) -> List[Path]:
    found = {}
    for n in os.listdir(path):
        m = _CAMERA_RE.match(n)
        if m and (path / n).is_dir():
            found[int(m.group(1))] = path / n
    if not found:
        raise RecordingError(f"{path / 'camera_0'}: folder missing (a PGND episode has camera_<i>/rgb, depth, mask)")
    expected = list(range(len(found)))
    if sorted(found) != expected:
        gap = next(i for i in expected if i not in found)
        raise RecordingError(f"{path / f'camera_{gap}'}: folder missing: found camera folders "
                             f"{[found[i].name for i in sorted(found)]}, expected camera_0 .. camera_{len(found) - 1}")
    return [found[i] for i in expected]


def _read_robot_file(p: Path) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """(positions [K, 3] m, end-effector-to-world rotations [K, 3, 3], gripper positions [K] or None) in
    PGND's world, from one ``robot/%06d.txt``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns on an empty file; the shape check below reports it
            a = np.loadtxt(p, ndmin=2, dtype=np.float64)
    except FileNotFoundError:
        raise RecordingError(f"{p}: file missing") from None
    except Exception as exc:
        raise RecordingError(f"{p}: cannot read robot telemetry as rows of numbers ({type(exc).__name__}: "
                             f"{str(exc)[:120]})") from None
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] not in (1, 5, 9):
        raise RecordingError(f"{p}: robot telemetry must be rows of 3 numbers: 5 rows for one arm (position, 3x3 "
                             f"orientation, gripper), 9 for two arms, or 1 (a position only); "
                             f"got shape {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise RecordingError(f"{p}: robot telemetry holds non-finite values")
    if a.shape[0] == 1:
        return a[:1].copy(), np.eye(3)[None], None
    K = (a.shape[0] - 1) // 4
    arms = a[:-1].reshape(K, 4, 3)
    rot = np.transpose(arms[:, 1:], (0, 2, 1))  # rows are the gripper's axes in the world -> columns
    for k in range(K):
        R = rot[k]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-2) or np.linalg.det(R) <= 0:
            raise RecordingError(f"{p}: arm {k}: rows {4 * k + 2}-{4 * k + 4} are not a rotation matrix (the gripper's "
                                 f"x, y, z axes in the world); got {np.round(arms[k, 1:], 4).tolist()}")
        u, _, vt = np.linalg.svd(R)
        rot[k] = u @ vt  # nearest rotation (the file holds 6 decimals)
    return arms[:, 0].copy(), rot, a[-1, :K].copy()


def _quaternions(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w) of rotation matrices [..., 3, 3]."""
    from scipy.spatial.transform import Rotation

    shp = R.shape[:-2]
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(shp + (4,))


def _read_controls(path: Path, T: int, flip: np.ndarray, notes: List[str]) -> Tuple[Optional[dict], Optional[Path]]:
    rdir = path / "robot"
    if not rdir.is_dir():
        notes.append("no robot/ folder: no end-effector controls")
        return None, None
    idx = _index_frames(rdir, ("txt",))
    if not idx:
        others = sorted(n for n in os.listdir(rdir) if n.endswith(".txt"))
        hint = (f" (it holds {others[0]} ...: a raw PGND capture named by timestamps; PGND's postprocess.py "
                f"match_timestamps turns it into an episode)") if others else ""
        raise RecordingError(f"{rdir / '000000.txt'}: file missing: no robot/%06d.txt frames{hint}")
    missing = [t for t in range(T) if t not in idx]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise RecordingError(f"{rdir / f'{missing[0]:06d}.txt'}: missing robot frame {missing[0]}{more}; the "
                             f"camera images have {T} frames")
    extra = sorted(t for t in idx if t >= T)
    if extra:
        raise RecordingError(f"{rdir / idx[extra[0]]['txt']}: mismatched frame counts: robot/ has {len(idx)} frames "
                             f"but the camera images have {T}")
    pos, rot, grip_raw, first = [], [], [], None
    for t in range(T):
        p = rdir / idx[t]["txt"]
        x, R, g = _read_robot_file(p)
        if first is None:
            first = (p, len(x), g is None)
        elif (len(x), g is None) != first[1:]:
            raise RecordingError(f"{p}: {len(x)} arm(s){' (position only)' if g is None else ''} but {first[0].name} "
                                 f"has {first[1]}{' (position only)' if first[2] else ''}; every frame must describe "
                                 f"the same arms")
        pos.append(x)
        rot.append(R)
        grip_raw.append(np.zeros(len(x)) if g is None else g)
    pos = np.einsum("ij,tkj->tki", flip, np.array(pos))
    rot = np.einsum("ij,tkjl->tkil", flip, np.array(rot))
    K = pos.shape[1]
    if first[2]:
        quat = np.tile([0.0, 0.0, 0.0, 1.0], (T, K, 1))
        notes.append("robot/ holds positions only (no orientation, no gripper): orientation identity, and the "
                     "end-effector is a closed gripper (grip 1) throughout, as PGND's readers take openness 0")
    else:
        quat = _quaternions(rot)
    openness = np.clip(np.array(grip_raw) / GRIPPER_OPEN_MAX, 0.0, 1.0)
    grip = (openness < GRIP_CLOSED_BELOW).astype(np.int32)
    notes.append(f"end-effectors: {K} sphere(s) of radius {DEFAULT_EE_RADIUS_M} m at the recorded end-effector "
                 f"points (PGND records no geometry; its default model.gripper_radius; its per-dataset eef_t "
                 f"offsets are not applied); closed where gripper position / {GRIPPER_OPEN_MAX:g} < "
                 f"{GRIP_CLOSED_BELOW} (PGND's rule)")
    controls = {"positions": pos, "orientations": quat, "grip": grip, "shape": np.array(["sphere"] * K),
                "radius": np.full(K, DEFAULT_EE_RADIUS_M)}
    return controls, rdir


def _read_fps(path: Path, C: int, notes: List[str]) -> Tuple[float, str]:
    p = path / "timestamps.txt"
    if not p.is_file():
        notes.append(f"no timestamps.txt: {DEFAULT_FPS:g} fps assumed (PGND records at 30 fps)")
        return DEFAULT_FPS, "assumed (no timestamps.txt)"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            a = np.loadtxt(p, ndmin=2, dtype=np.float64)
    except Exception as exc:
        raise RecordingError(f"{p}: cannot read frame timestamps as rows of numbers ({type(exc).__name__}: "
                             f"{str(exc)[:120]})") from None
    if a.shape[0] < 2:
        notes.append(f"{p.name} has fewer than 2 rows: {DEFAULT_FPS:g} fps assumed (PGND records at 30 fps)")
        return DEFAULT_FPS, f"assumed ({p.name} too short)"
    if a.shape[1] == C:  # an episode's timestamps.txt: one timestamp (s) per camera
        ts = a[:, 0]
    elif a.shape[1] == 3 * C:  # the recorder's: step indices, relative times, absolute times
        ts = a[:, 2 * C]
    else:
        raise RecordingError(f"{p}: expected {C} columns (one timestamp in s per camera) or {3 * C}, got {a.shape[1]}")
    dt = float(np.median(np.diff(ts)))
    if not (np.isfinite(dt) and dt > 0):
        raise RecordingError(f"{p}: the timestamps of camera 0 do not increase (median interval {dt} s)")
    fps = round(1.0 / dt, 3)  # timestamps of ~1.7e9 s carry float noise of ~1e-7 s
    if not (0.5 <= fps <= 1000.0):
        raise RecordingError(f"{p}: the median frame interval {dt:.6g} s gives {fps:.4g} fps, outside 0.5-1000; are "
                             f"the timestamps in seconds?")
    return fps, f"1 / median interval of {p.name}"


def read_pgnd_episode(path) -> PGNDEpisode:
    """Read and check a PGND episode's structure (calibration, frame counts, robot telemetry); images are read
    lazily by :class:`Recording`. Logs the assumptions it makes (see the module docstring)."""
    path = Path(path)
    cams = _camera_dirs(path)
    C = len(cams)
    cal = path / "calibration"
    ip, rp, tp = cal / "intrinsics.npy", cal / "rvecs.npy", cal / "tvecs.npy"
    K = _read_npy(ip)
    if K.ndim != 3 or K.shape[1:] != (3, 3):
        raise RecordingError(f"{ip}: intrinsics must have shape [cameras, 3, 3], got {list(K.shape)}")
    if len(K) != C:
        raise RecordingError(f"{ip}: camera count mismatch: {len(K)} intrinsics but the episode has {C} camera "
                             f"folders (camera_0 .. camera_{C - 1})")
    rvecs, tvecs = _vectors(rp, C), _vectors(tp, C)

    # frame count and image size: the colour and depth images of every camera define the episode
    T, first = 0, None
    for d in cams:
        for sub, exts in (("rgb", COLOR_EXTS), ("depth", ("png",))):
            folder = d / sub
            if not folder.is_dir():
                raise RecordingError(f"{folder}: folder missing for camera {d.name}")
            idx = _index_frames(folder, exts)
            if idx:
                T = max(T, max(idx) + 1)
                if first is None and sub == "rgb":
                    t0 = min(idx)
                    first = folder / next(idx[t0][e] for e in exts if e in idx[t0])
    if first is None:
        raise RecordingError(f"{cams[0] / 'rgb' / '000000.jpg'}: file missing: no colour frames in any camera")
    img = _read_png(first)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise RecordingError(f"{first}: colour image must be RGB, got shape {list(img.shape)}")
    H, W = int(img.shape[0]), int(img.shape[1])
    K = _check_intrinsics(K, W, H, ip)

    # cameras: PGND's w2c = [Rodrigues(rvec) | tvec]; our c2w in a z-up world
    c2w = np.zeros((C, 4, 4))
    for i in range(C):
        R = _rodrigues(rvecs[i])
        c2w[i, :3, :3] = R.T
        c2w[i, :3, 3] = -R.T @ tvecs[i]
        c2w[i, 3, 3] = 1.0
    notes: List[str] = []
    flipped = bool(np.median(c2w[:, 2, 3]) < 0)
    flip = _FLIP if flipped else np.eye(3)
    if flipped:
        F4 = np.eye(4)
        F4[:3, :3] = _FLIP
        c2w = F4 @ c2w
        _log.info("%s: PGND episode: the calibration frame's z points down (cameras at z < 0); world turned 180 deg "
                  "about x, (x, y, z) -> (x, -y, -z), so that z is up", path)
    else:
        _log.info("%s: PGND episode: cameras at z > 0 in the calibration frame; taken as a z-up world as is", path)
    c2w = _check_c2w(c2w, rp)

    controls, csrc = _read_controls(path, T, flip, notes)
    fps, fps_source = _read_fps(path, C, notes)
    for n in notes:
        _log.warning("%s: PGND episode: %s", path, n)
    source = f"the episode's camera images run to frame {T - 1} ({T} frames)"
    md = {"layout": "pgnd", "intrinsics": K.tolist(), "WH": [W, H], "fps": fps, "frame_num": T,
          "serial_numbers": [d.name for d in cams], "depth_scale": DEPTH_SCALE, "fps_source": fps_source,
          "world": ("PGND calibration frame turned 180 deg about x (z up)" if flipped
                    else "PGND calibration frame (z up)"),
          "assumptions": notes}
    return PGNDEpisode(camera_dirs=cams, intrinsics=K, c2w=c2w, width=W, height=H, fps=fps, num_frames=T,
                       frame_count_source=source, controls=controls, controls_source=csrc, flipped=flipped,
                       metadata=md)
