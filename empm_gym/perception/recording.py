"""Multi-view RGB-D recordings on disk: read (lazily, validated, never writing) and write.

The layout is PhysTwin's raw layout plus a few files of ours (see ``ARCHITECTURE.md``,
"Recordings")::

    <recording>/
      metadata.json        {"intrinsics": [C][3][3], "WH": [W, H], "fps": 30, "frame_num": T,
                            "serial_numbers": [...], "depth_scale": 0.001}  (depth units -> metres)
      calibrate.json       {"c2w": [C][4][4]}            (preferred)
      calibrate.pkl        list of 4x4 camera-to-world matrices (PhysTwin; numpy-only unpickler)
      color/<cam>/<frame>.png
      depth/<cam>/<frame>.npy | .png      depth_scale units (uint16 or float)
      mask/<cam>/<frame>.png              object mask 0/255 ("simple" form), or
      mask/mask_info_<cam>.json + mask/<cam>/<id>/<frame>.png   (PhysTwin; label "hand" = controller)
      controls.npz         positions [T, K, 3] m, grip [T, K], shape [K], radius [K] m,
                           half_height [K] m, half_extents [K, 3] m, orientations [T, K, 4] (x, y, z, w)
      tracks/<cam>.npz     tracks [T, N, 2] pixel (row, col), visibility [T, N] (or cotracker/<cam>.npz)
      ground_truth.json    synthetic recordings only

Cameras are the folders ``color/0 .. color/C-1``; frame files are ``0.png`` or zero-padded
``000000.png``. :class:`Recording` checks the structure when opened and each image when it is read,
raising :class:`RecordingError` that names the file and the problem.

PGND's episodes (kywind/pgnd: ``camera_<i>/{rgb,depth,mask}``, ``calibration/``, ``robot/``) are read by
the same class, detected by their files; :mod:`empm_gym.perception.pgnd` says what is mapped how.

``metadata.json`` without ``depth_scale`` means millimetres (0.001), as in PhysTwin.
``controls.npz`` without ``grip`` means closed grippers (1) throughout; without ``shape``, spheres;
without ``radius``, 0.02 m.
"""

from __future__ import annotations

import io
import json
import math
import os
import pickle
import re
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .cameras import Camera

__all__ = [
    "RecordingError",
    "Recording",
    "RecordingWriter",
    "write_recording",
    "load_calibration_pickle",
    "validate_controls",
    "controls_to_end_effectors",
    "end_effector_velocities",
    "quat_angular_velocity",
    "CONTROLLER_LABEL",
]

#: PhysTwin's mask label of the controller (hand or gripper).
CONTROLLER_LABEL = "hand"
_SHAPES = ("sphere", "capsule", "box")
_FRAME_RE = re.compile(r"^(\d+)\.(png|npy)$")
_DEPTH_MEDIAN_RANGE_M = (0.02, 20.0)


def _frame_name(t: int, ext: str, layout: str = "phystwin") -> str:
    """The file name of frame ``t`` as the layout writes it (PhysTwin ``0.png``, PGND ``000000.png``)."""
    return f"{t:06d}.{ext}" if layout == "pgnd" else f"{t}.{ext}"


class RecordingError(ValueError):
    """A recording on disk is missing a file, inconsistent or malformed; the message names the file."""


# ----------------------------------------------------------------------------------------------
# calibrate.pkl: a restricted unpickler
# ----------------------------------------------------------------------------------------------


def _numpy_globals() -> Dict[Tuple[str, str], object]:
    try:
        from numpy._core import multiarray as ma  # numpy >= 2
        from numpy._core import numeric as nm
    except ImportError:  # numpy 1.x
        from numpy.core import multiarray as ma  # type: ignore
        from numpy.core import numeric as nm  # type: ignore
    import codecs

    allowed = {}
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed[(mod, "_reconstruct")] = ma._reconstruct
        allowed[(mod, "scalar")] = ma.scalar
    for mod in ("numpy.core.numeric", "numpy._core.numeric"):
        allowed[(mod, "_frombuffer")] = nm._frombuffer
    allowed[("numpy", "ndarray")] = np.ndarray
    allowed[("numpy", "dtype")] = np.dtype
    # protocol-2 pickles written by Python 2 encode byte strings through _codecs.encode
    allowed[("_codecs", "encode")] = codecs.encode
    for name, obj in (("list", list), ("tuple", tuple), ("dict", dict), ("set", set), ("frozenset", frozenset),
                      ("complex", complex), ("bytearray", bytearray)):
        allowed[("builtins", name)] = obj
        allowed[("__builtin__", name)] = obj
    return allowed


class _Refused(pickle.UnpicklingError):
    pass


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that reconstructs numpy arrays and plain containers and refuses every other global."""

    _allowed = None

    def find_class(self, module, name):
        if _NumpyOnlyUnpickler._allowed is None:
            _NumpyOnlyUnpickler._allowed = _numpy_globals()
        obj = self._allowed.get((module, name))
        if obj is None:
            raise _Refused(f"{module}.{name}")
        return obj

    def persistent_load(self, pid):
        raise _Refused(f"persistent id {pid!r}")


def load_calibration_pickle(path) -> np.ndarray:
    """Camera-to-world matrices [C, 4, 4] from a PhysTwin ``calibrate.pkl``, without executing code.

    Only numpy arrays, numpy dtypes and plain containers may appear in the pickle; anything else
    (a class, a function such as ``os.system``) raises :class:`RecordingError` before it is called.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read the calibration pickle ({exc})") from None
    try:
        obj = _NumpyOnlyUnpickler(io.BytesIO(data), encoding="latin1").load()
    except _Refused as exc:
        raise RecordingError(
            f"{path}: refused to unpickle: it references {exc}, but calibrate.pkl may only hold numpy "
            f"arrays and lists (a list of 4x4 camera-to-world matrices); convert it to calibrate.json "
            f"if it comes from a trusted source"
        ) from None
    except Exception as exc:  # truncated or not a pickle at all
        raise RecordingError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from None
    return _check_c2w(obj, path)


def _check_c2w(obj, path) -> np.ndarray:
    try:
        c2w = np.asarray(obj, dtype=np.float64)
    except (TypeError, ValueError):
        raise RecordingError(f"{path}: camera-to-world matrices must be a list of 4x4 numeric arrays") from None
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or c2w.shape[0] < 1:
        raise RecordingError(f"{path}: camera-to-world matrices must have shape [cameras, 4, 4], got {c2w.shape}")
    if not np.all(np.isfinite(c2w)):
        raise RecordingError(f"{path}: camera-to-world matrices hold non-finite values")
    for i, m in enumerate(c2w):
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise RecordingError(f"{path}: camera {i}: last row of c2w must be [0, 0, 0, 1], got {m[3].tolist()}")
        R = m[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=2e-3) or np.linalg.det(R) < 0:
            raise RecordingError(f"{path}: camera {i}: the rotation part of c2w is not a proper rotation "
                                 f"(R^T R != I or det < 0); is it a scaled or mirrored matrix?")
    return c2w


# ----------------------------------------------------------------------------------------------
# controls
# ----------------------------------------------------------------------------------------------


def validate_controls(data, frame_num: Optional[int] = None, source: str = "controls.npz") -> dict:
    """Check and complete a controls mapping (see the module docstring); returns a new dict of arrays.

    Raises :class:`RecordingError` naming ``source`` on a missing ``positions``, wrong shapes,
    non-finite values, grip values other than 0/1, unknown shapes or non-positive sizes.
    """
    d = {k: np.asarray(data[k]) for k in data.keys()}
    if "positions" not in d:
        raise RecordingError(f"{source}: missing array 'positions' [T, K, 3] (end-effector centres, m)")
    pos = d["positions"]
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 1:
        raise RecordingError(f"{source}: 'positions' must have shape [T, K, 3], got {pos.shape}")
    if not np.issubdtype(pos.dtype, np.number):
        raise RecordingError(f"{source}: 'positions' must be numeric, got dtype {pos.dtype}")
    T, K = pos.shape[:2]
    if frame_num is not None and T != frame_num:
        raise RecordingError(f"{source}: 'positions' has {T} frames but metadata.json says frame_num={frame_num}")
    out = {"positions": pos.astype(np.float64)}
    if not np.all(np.isfinite(out["positions"])):
        bad = np.argwhere(~np.isfinite(out["positions"]))[0]
        raise RecordingError(f"{source}: 'positions' holds non-finite values (first at frame {bad[0]}, "
                             f"end-effector {bad[1]})")

    def numeric(name, shape, default):
        if name not in d:
            return np.broadcast_to(np.asarray(default, np.float64), shape).copy()
        a = d[name]
        if not np.issubdtype(a.dtype, np.number) and a.dtype != bool:
            raise RecordingError(f"{source}: '{name}' must be numeric, got dtype {a.dtype}")
        if a.shape != shape:
            raise RecordingError(f"{source}: '{name}' must have shape {list(shape)}, got {list(a.shape)}")
        a = a.astype(np.float64)
        if not np.all(np.isfinite(a)):
            raise RecordingError(f"{source}: '{name}' holds non-finite values")
        return a

    grip = numeric("grip", (T, K), 1.0)
    if not np.all((grip == 0) | (grip == 1)):
        raise RecordingError(f"{source}: 'grip' must hold only 0 (open) or 1 (closed), got {np.unique(grip)[:6]}")
    out["grip"] = grip.astype(np.int32)
    if "shape" in d:
        shp = d["shape"]
        if shp.shape != (K,) or shp.dtype.kind not in "US":
            raise RecordingError(f"{source}: 'shape' must be {K} strings, got dtype {shp.dtype} shape {shp.shape}")
        shp = np.array([s.decode() if isinstance(s, bytes) else str(s) for s in shp.tolist()])
        bad = [s for s in shp if s not in _SHAPES]
        if bad:
            raise RecordingError(f"{source}: 'shape' entries must be one of {list(_SHAPES)}, got {bad[0]!r}")
    else:
        shp = np.array(["sphere"] * K)
    out["shape"] = shp.astype("<U7")
    out["radius"] = numeric("radius", (K,), 0.02)
    out["half_height"] = numeric("half_height", (K,), 0.02)
    out["half_extents"] = numeric("half_extents", (K, 3), 0.02)
    for k in range(K):
        s = out["shape"][k]
        if s in ("sphere", "capsule") and out["radius"][k] <= 0:
            raise RecordingError(f"{source}: end-effector {k} ({s}) needs radius > 0 m, got {out['radius'][k]}")
        if s == "capsule" and out["half_height"][k] < 0:
            raise RecordingError(f"{source}: end-effector {k} needs half_height >= 0 m, got {out['half_height'][k]}")
        if s == "box" and np.any(out["half_extents"][k] <= 0):
            raise RecordingError(f"{source}: end-effector {k} (box) needs half_extents > 0 m, "
                                 f"got {out['half_extents'][k].tolist()}")
    q = numeric("orientations", (T, K, 4), [0.0, 0.0, 0.0, 1.0])
    n = np.linalg.norm(q, axis=-1)
    if np.any(n < 1e-6):
        raise RecordingError(f"{source}: 'orientations' holds zero quaternions (x, y, z, w)")
    out["orientations"] = q / n[..., None]
    return out


def controls_to_end_effectors(controls: dict, friction: float = 0.8):
    """Simulator end-effectors from a controls mapping (``controls.npz`` or :func:`validate_controls`).

    Returns ``(configs, positions [T, K, 3] m, grip [T, K] int)`` where ``configs`` is one
    :class:`empm_gym.sim.EndEffectorConfig` per end-effector (``friction`` [-] for all; a ``gripper`` where its
    grip closes in some frame, a tool otherwise). To replay the
    recording, add end-effector k at ``positions[0, k]`` and command during frame interval t -> t+1
    the velocity ``end_effector_velocities(positions, fps)[t]`` (m/s) and the grip ``grip[t]``.
    """
    from empm_gym.sim import EndEffectorConfig

    c = validate_controls(controls)
    configs = []
    for k in range(c["positions"].shape[1]):
        configs.append(EndEffectorConfig(
            shape=str(c["shape"][k]), radius=float(c["radius"][k]),
            half_height=float(c["half_height"][k]), half_extents=tuple(float(v) for v in c["half_extents"][k]),
            friction=friction, gripper=bool(np.any(c["grip"][:, k]))))
    return configs, c["positions"], c["grip"]


def end_effector_velocities(positions: np.ndarray, fps: float) -> np.ndarray:
    """Per-interval end-effector velocities [T-1, K, 3] (m/s): (positions[t+1] - positions[t]) * fps.

    Integrating these over the frame interval 1/fps s (any number of substeps) lands exactly on the
    next recorded position.
    """
    p = np.asarray(positions, np.float64)
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"positions must have shape [T, K, 3], got {p.shape}")
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be a positive frame rate in 1/s, got {fps!r}")
    return np.diff(p, axis=0) * float(fps)


def quat_angular_velocity(q: np.ndarray, fps: float) -> np.ndarray:
    """Angular velocities [T-1, K, 3] (rad/s, world frame) taking quaternions (x, y, z, w) q[t] to q[t+1] in 1/fps s."""
    q = np.asarray(q, np.float64)
    a, b = q[:-1], q[1:]
    # relative rotation r = b * conj(a)
    ax, ay, az, aw = -a[..., 0], -a[..., 1], -a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    rw = bw * aw - bx * ax - by * ay - bz * az
    rx = bw * ax + bx * aw + by * az - bz * ay
    ry = bw * ay - bx * az + by * aw + bz * ax
    rz = bw * az + bx * ay - by * ax + bz * aw
    v = np.stack([rx, ry, rz], -1)
    sign = np.where(rw < 0, -1.0, 1.0)[..., None]
    v, rw = v * sign, np.abs(rw)
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, rw)
    axis = np.where(s[..., None] > 1e-12, v / np.maximum(s, 1e-12)[..., None], 0.0)
    return axis * angle[..., None] * float(fps)


# ----------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------


def _read_json(path: Path):
    try:
        with open(path, "r", encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise RecordingError(f"{path}: file missing") from None
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: not valid JSON ({exc})") from None


def _index_frames(folder: Path, exts: Sequence[str]) -> Dict[int, Dict[str, str]]:
    """{frame number: {extension: file name}} of the frame files ``<digits>.<ext>`` in a folder (empty if missing)."""
    out: Dict[int, Dict[str, str]] = {}
    if not folder.is_dir():
        return out
    pattern = re.compile(r"^(\d+)\.(" + "|".join(re.escape(e) for e in exts) + r")$")
    for name in os.listdir(folder):
        m = pattern.match(name)
        if not m:
            continue
        t, ext = int(m.group(1)), m.group(2)
        prev = out.setdefault(t, {}).get(ext)
        if prev is not None:
            raise RecordingError(f"{folder}: frame {t} appears twice ({prev} and {name}); keep one naming scheme")
        out[t][ext] = name
    return out


def _read_png(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    try:
        return np.asarray(iio.imread(path))
    except FileNotFoundError:
        raise RecordingError(f"{path}: file missing") from None
    except Exception as exc:
        raise RecordingError(f"{path}: cannot read image ({type(exc).__name__}: {exc})") from None


def _read_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise RecordingError(f"{path}: file missing") from None
    except Exception as exc:
        raise RecordingError(f"{path}: cannot read .npy ({type(exc).__name__}: {exc}); object arrays are refused")


def _read_npz(path: Path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise RecordingError(f"{path}: file missing") from None
    except Exception as exc:
        raise RecordingError(f"{path}: cannot read .npz ({type(exc).__name__}: {exc}); object arrays are refused")


def _check_intrinsics(K, width: int, height: int, src, what: str = "intrinsics") -> np.ndarray:
    """Per-camera pinhole intrinsics [C, 3, 3] (pixels), checked; ``src`` names the file in errors."""
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise RecordingError(f"{src}: {what} must be a [cameras][3][3] array of numbers") from None
    if K.ndim != 3 or K.shape[1:] != (3, 3) or K.shape[0] < 1:
        raise RecordingError(f"{src}: {what} must have shape [cameras, 3, 3], got {list(K.shape)}")
    for i, k in enumerate(K):
        if not np.all(np.isfinite(k)):
            raise RecordingError(f"{src}: intrinsics of camera {i} hold non-finite values")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise RecordingError(f"{src}: intrinsics of camera {i}: focal lengths fx={k[0, 0]}, fy={k[1, 1]} "
                                 f"must be > 0 pixels")
        if not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0:
            raise RecordingError(f"{src}: intrinsics of camera {i}: must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], "
                                 f"got {k.tolist()}")
        if not (0 <= k[0, 2] <= width and 0 <= k[1, 2] <= height):
            raise RecordingError(f"{src}: intrinsics of camera {i}: principal point (cx, cy) = "
                                 f"({k[0, 2]}, {k[1, 2]}) lies outside the {width}x{height} image")
    return K


class Recording:
    """A recording directory opened for reading (frames load lazily, one image per call).

    Opening checks metadata, calibration, camera count and that every camera has every frame of
    colour, depth and (when present) masks; it raises :class:`RecordingError` otherwise. Nothing is
    ever written into the directory.

    Two layouts are read, told apart by their files (no option): ours / PhysTwin's (``metadata.json``;
    ``layout == "phystwin"``) and PGND's episodes (``camera_<i>/``, ``calibration/``, ``robot/`` and no
    ``metadata.json``; ``layout == "pgnd"``), which :mod:`empm_gym.perception.pgnd` maps onto the same
    attributes: cameras in a z-up world, depth in metres, object masks, and controls from the robot
    telemetry (see that module for what is mapped how, and the defaults it assumes and logs).
    """

    def __init__(self, path):
        from . import pgnd

        self.path = Path(path)
        if not self.path.is_dir():
            raise RecordingError(f"{self.path}: recording directory does not exist")
        self._controls = None
        self._mask_form = None
        self._mask_ids: List[Tuple[List[str], List[str]]] = []
        self._mask_dirs: List[Path] = []
        self._color: List[Dict[int, Dict[str, str]]] = []  # per camera: {frame: {extension: file name}}
        self._depth: List[Dict[int, Dict[str, str]]] = []
        if not (self.path / "metadata.json").is_file():
            if pgnd.is_pgnd_episode(self.path):
                self._open_pgnd(pgnd.read_pgnd_episode(self.path))
                return
            raise RecordingError(pgnd.not_a_recording_message(self.path))
        self.layout = "phystwin"
        self.metadata = _read_json(self.path / "metadata.json")
        self._parse_metadata()
        self._frame_count_source = f"metadata.json says frame_num={self.num_frames}"
        self.c2w = self._read_calibration()
        self._check_camera_folders()
        self._color_dirs = [self.path / "color" / c for c in self.camera_names]
        self._depth_dirs = [self.path / "depth" / c for c in self.camera_names]
        self._color_exts = ("png",)
        self._index()
        if (self.path / "controls.npz").is_file():
            self._controls = validate_controls(_read_npz(self.path / "controls.npz"), self.num_frames,
                                               str(self.path / "controls.npz"))

    def _open_pgnd(self, ep):
        """Take over a PGND episode read and checked by :func:`empm_gym.perception.pgnd.read_pgnd_episode`."""
        self.layout = "pgnd"
        self.metadata = ep.metadata
        self.width, self.height = ep.width, ep.height
        self.intrinsics, self.c2w = ep.intrinsics, ep.c2w
        self.fps, self.num_frames, self.depth_scale = ep.fps, ep.num_frames, ep.depth_scale
        self.num_cameras = len(ep.camera_dirs)
        self.camera_names = [str(i) for i in range(self.num_cameras)]
        self.serial_numbers = [d.name for d in ep.camera_dirs]
        self._frame_count_source = ep.frame_count_source
        self._color_dirs = [d / "rgb" for d in ep.camera_dirs]
        self._depth_dirs = [d / "depth" for d in ep.camera_dirs]
        self._color_exts = ep.color_exts
        for i, c in enumerate(self.camera_names):
            for kind, folder, exts, store in (("rgb", self._color_dirs[i], self._color_exts, self._color),
                                              ("depth", self._depth_dirs[i], ("png",), self._depth)):
                if not folder.is_dir():
                    raise RecordingError(f"{folder}: folder missing for camera {c}")
                idx = _index_frames(folder, exts)
                self._check_complete(idx, folder, c, kind, exts[0], exact=True)
                store.append(idx)
        masks = [d / "mask" for d in ep.camera_dirs]
        if any(m.is_dir() for m in masks):
            self._mask_form, self._mask_dirs = "simple", masks
            for c, folder in zip(self.camera_names, masks):
                self._check_complete(_index_frames(folder, ("png",)), folder, c, "mask", "png", exact=True)
        if ep.controls is not None:
            self._controls = validate_controls(ep.controls, self.num_frames, str(ep.controls_source))

    # -- structure -------------------------------------------------------------------------
    def _parse_metadata(self):
        md, src = self.metadata, self.path / "metadata.json"
        if not isinstance(md, dict):
            raise RecordingError(f"{src}: must hold a JSON object")
        for key in ("intrinsics", "WH", "fps", "frame_num"):
            if key not in md:
                raise RecordingError(f"{src}: missing key {key!r}")
        wh = md["WH"]
        if (not isinstance(wh, (list, tuple)) or len(wh) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in wh)):
            raise RecordingError(f"{src}: 'WH' must be [width, height] positive integers (pixels), got {wh!r}")
        self.width, self.height = int(wh[0]), int(wh[1])
        K = _check_intrinsics(md["intrinsics"], self.width, self.height, src, "'intrinsics'")
        self.intrinsics = K
        fps = md["fps"]
        if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not math.isfinite(fps) or fps <= 0:
            raise RecordingError(f"{src}: 'fps' must be a positive number of frames per second, got {fps!r}")
        self.fps = float(fps)
        T = md["frame_num"]
        if not isinstance(T, int) or isinstance(T, bool) or T < 1:
            raise RecordingError(f"{src}: 'frame_num' must be a positive integer, got {T!r}")
        self.num_frames = T
        ds = md.get("depth_scale", 0.001)
        if not isinstance(ds, (int, float)) or isinstance(ds, bool) or not math.isfinite(ds) or not (0 < ds <= 1):
            raise RecordingError(f"{src}: 'depth_scale' (metres per depth unit) must lie in (0, 1], e.g. 0.001 "
                                 f"for millimetres, got {ds!r}")
        self.depth_scale = float(ds)
        self.num_cameras = K.shape[0]
        sn = md.get("serial_numbers")
        if sn is not None and (not isinstance(sn, list) or len(sn) != self.num_cameras):
            raise RecordingError(f"{src}: camera count mismatch: {len(K)} intrinsics but "
                                 f"{len(sn) if isinstance(sn, list) else sn!r} serial_numbers")
        self.serial_numbers = list(sn) if sn is not None else [str(i) for i in range(self.num_cameras)]

    def _read_calibration(self) -> np.ndarray:
        pj, pp = self.path / "calibrate.json", self.path / "calibrate.pkl"
        if pj.is_file():
            d = _read_json(pj)
            if not isinstance(d, dict) or "c2w" not in d:
                raise RecordingError(f"{pj}: must be a JSON object with key 'c2w' ([cameras][4][4])")
            c2w, src = _check_c2w(d["c2w"], pj), pj
        elif pp.is_file():
            c2w, src = load_calibration_pickle(pp), pp
        else:
            raise RecordingError(f"{self.path}: no camera calibration: expected calibrate.json or calibrate.pkl")
        if len(c2w) != self.num_cameras:
            raise RecordingError(f"{src}: camera count mismatch: {len(c2w)} camera poses but metadata.json has "
                                 f"{self.num_cameras} intrinsics")
        return c2w

    def _check_camera_folders(self):
        color = self.path / "color"
        if not color.is_dir():
            raise RecordingError(f"{color}: folder missing (expected color/<cam>/<frame>.png)")
        cams = sorted(n for n in os.listdir(color) if (color / n).is_dir())
        expected = [str(i) for i in range(self.num_cameras)]
        if sorted(cams, key=lambda s: (len(s), s)) != expected:
            raise RecordingError(f"{color}: camera count mismatch: metadata.json and calibration describe "
                                 f"{self.num_cameras} cameras (folders {expected}), found folders {cams}")
        self.camera_names = expected

    def _index(self):
        for i, c in enumerate(self.camera_names):
            for kind, folder, exts, store in (("color", self._color_dirs[i], self._color_exts, self._color),
                                              ("depth", self._depth_dirs[i], ("npy", "png"), self._depth)):
                if not folder.is_dir():
                    raise RecordingError(f"{folder}: folder missing for camera {c}")
                idx = _index_frames(folder, exts)
                self._check_complete(idx, folder, c, kind, exts[0])
                store.append(idx)
        # masks: PhysTwin form if mask_info_<cam>.json exists, else the simple form
        mdir = self.path / "mask"
        if mdir.is_dir():
            infos = [mdir / f"mask_info_{c}.json" for c in self.camera_names]
            if any(p.is_file() for p in infos):
                self._mask_form = "phystwin"
                for c, p in zip(self.camera_names, infos):
                    info = _read_json(p)
                    if not isinstance(info, dict) or not info:
                        raise RecordingError(f"{p}: must map mask ids to labels, e.g. {{\"0\": \"rope\", \"1\": \"hand\"}}")
                    obj = sorted((str(k) for k, v in info.items() if v != CONTROLLER_LABEL), key=lambda s: (len(s), s))
                    ctl = sorted((str(k) for k, v in info.items() if v == CONTROLLER_LABEL), key=lambda s: (len(s), s))
                    if not obj:
                        raise RecordingError(f"{p}: no object label (every id is labelled {CONTROLLER_LABEL!r})")
                    for i in obj + ctl:
                        folder = mdir / c / i
                        self._check_complete(_index_frames(folder, ("png",)), folder, c, "mask", "png")
                    self._mask_ids.append((obj, ctl))
            elif any((mdir / c).is_dir() for c in self.camera_names):
                self._mask_form = "simple"
                self._mask_dirs = [mdir / c for c in self.camera_names]
                for c, folder in zip(self.camera_names, self._mask_dirs):
                    self._check_complete(_index_frames(folder, ("png",)), folder, c, "mask", "png")

    def _check_complete(self, idx, folder: Path, cam: str, kind: str, ext: str, exact: bool = False):
        """Every frame 0..T-1 present in ``idx`` (and, with ``exact``, none beyond), else :class:`RecordingError`."""
        missing = [t for t in range(self.num_frames) if t not in idx]
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise RecordingError(f"{folder / _frame_name(missing[0], ext, self.layout)}: missing {kind} frame "
                                 f"{missing[0]} of camera {cam}{more}; {self._frame_count_source}")
        extra = sorted(t for t in idx if t >= self.num_frames)
        if exact and extra:
            name = next(iter(idx[extra[0]].values()))
            raise RecordingError(f"{folder / name}: mismatched frame counts: {kind} of camera {cam} has "
                                 f"{len(idx)} frames but {self._frame_count_source}")

    # -- properties ----------------------------------------------------------------------------
    @property
    def cameras(self) -> List[Camera]:
        """One :class:`Camera` per camera, in folder order."""
        return [Camera(self.intrinsics[i], self.c2w[i], self.width, self.height, name=c)
                for i, c in enumerate(self.camera_names)]

    @property
    def has_masks(self) -> bool:
        return self._mask_form is not None

    @property
    def mask_form(self) -> Optional[str]:
        """"phystwin", "simple" or None (no masks)."""
        return self._mask_form

    @property
    def has_controls(self) -> bool:
        return self._controls is not None

    @property
    def has_controller_masks(self) -> bool:
        return self._mask_form == "phystwin" and any(ctl for _, ctl in self._mask_ids)

    def with_cameras(self, cameras: Sequence[int]) -> "Recording":
        """The same recording seen by the cameras ``cameras`` only (indices into this one's, in that order):
        every per-camera attribute is narrowed, the files are the same. Used to rebuild the frame-0 body from
        fewer views (how much its shape depends on each view)."""
        import copy

        idx = [self._cam(c) for c in cameras]
        if not idx or len(set(idx)) != len(idx):
            raise ValueError(f"with_cameras: need distinct camera indices, at least one, got {list(cameras)}")
        sub = copy.copy(self)
        sub.intrinsics, sub.c2w = np.asarray(self.intrinsics)[idx], np.asarray(self.c2w)[idx]
        sub.num_cameras = len(idx)
        for name in ("camera_names", "serial_numbers", "_color_dirs", "_depth_dirs", "_color", "_depth",
                     "_mask_ids", "_mask_dirs"):
            full = getattr(self, name)
            setattr(sub, name, [full[i] for i in idx] if len(full) else full)
        return sub

    def __repr__(self):
        return (f"Recording({str(self.path)!r}, cameras={self.num_cameras}, frames={self.num_frames}, "
                f"{self.width}x{self.height} @ {self.fps:g} fps)")

    # -- frames --------------------------------------------------------------------------------
    def _cam(self, cam) -> int:
        i = int(cam)
        if not (0 <= i < self.num_cameras):
            raise IndexError(f"camera {cam!r} out of range: the recording has {self.num_cameras} cameras")
        return i

    def _frame(self, t) -> int:
        t = int(t)
        if not (0 <= t < self.num_frames):
            raise IndexError(f"frame {t} out of range: the recording has {self.num_frames} frames")
        return t

    def _check_hw(self, img: np.ndarray, path: Path, what: str):
        if img.shape[:2] != (self.height, self.width):
            raise RecordingError(f"{path}: {what} has size {img.shape[1]}x{img.shape[0]} (WxH) but metadata.json "
                                 f"says WH=[{self.width}, {self.height}]")

    def color(self, cam, t) -> np.ndarray:
        """Colour image [H, W, 3] uint8 (RGB) of camera ``cam`` at frame ``t``."""
        i, t = self._cam(cam), self._frame(t)
        files = self._color[i][t]
        p = self._color_dirs[i] / next(files[e] for e in self._color_exts if e in files)
        img = _read_png(p)
        self._check_hw(img, p, "colour image")
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.ndim != 3 or img.shape[2] not in (3, 4):
            raise RecordingError(f"{p}: colour image must be RGB or RGBA, got shape {img.shape}")
        if img.dtype != np.uint8:
            raise RecordingError(f"{p}: colour image must be 8-bit, got dtype {img.dtype}")
        return img[..., :3]

    def depth_path(self, cam, t) -> Path:
        i, t = self._cam(cam), self._frame(t)
        files = self._depth[i][t]
        return self._depth_dirs[i] / (files.get("npy") or files["png"])

    def depth_raw(self, cam, t) -> np.ndarray:
        """Depth image [H, W] as stored (depth_scale units; .npy preferred over .png)."""
        p = self.depth_path(cam, t)
        d = _read_npy(p) if p.suffix == ".npy" else _read_png(p)
        if d.ndim == 3 and d.shape[2] == 1:
            d = d[..., 0]
        if d.ndim != 2:
            raise RecordingError(f"{p}: depth must be a single-channel image, got shape {d.shape}")
        self._check_hw(d, p, "depth image")
        if not (np.issubdtype(d.dtype, np.integer) or np.issubdtype(d.dtype, np.floating)) or d.dtype == bool:
            raise RecordingError(f"{p}: depth must be integer or float depth units, got dtype {d.dtype}")
        if p.suffix == ".png" and d.dtype != np.uint16:
            raise RecordingError(f"{p}: a depth PNG must be 16-bit (uint16), got {d.dtype}")
        return d

    def depth(self, cam, t) -> np.ndarray:
        """Metric depth [H, W] float32 (m) of camera ``cam`` at frame ``t``; 0 where there is no measurement.

        Raises :class:`RecordingError` for negative depths or when the median measured depth is
        implausible (outside 0.02-20 m), which means the depth units or ``depth_scale`` are wrong.
        """
        p = self.depth_path(cam, t)
        raw = self.depth_raw(cam, t)
        d = raw.astype(np.float32) * np.float32(self.depth_scale)
        d[~np.isfinite(d)] = 0.0
        if np.any(d < 0):
            raise RecordingError(f"{p}: depth holds negative values (min {float(d.min())} m)")
        valid = d > 0
        if np.any(valid):
            med = float(np.median(d[valid]))
            lo, hi = _DEPTH_MEDIAN_RANGE_M
            if not (lo <= med <= hi):
                raise RecordingError(
                    f"{p}: median depth {med:.4g} m (stored units x depth_scale {self.depth_scale}) is outside "
                    f"{lo}-{hi} m: the depth units do not match metadata.json's depth_scale (PhysTwin stores "
                    f"millimetres: depth_scale 0.001)")
        return d

    def _mask_png(self, p: Path) -> np.ndarray:
        m = _read_png(p)
        self._check_hw(m, p, "mask")
        if m.ndim == 3:
            m = m[..., :3].max(axis=2)
        return m > 0

    def mask(self, cam, t) -> np.ndarray:
        """Object mask [H, W] bool (union of every non-controller id in PhysTwin's form)."""
        i, t = self._cam(cam), self._frame(t)
        c = self.camera_names[i]
        if self._mask_form is None:
            raise RecordingError(f"{self.path / 'mask'}: the recording has no object masks")
        if self._mask_form == "simple":
            return self._mask_png(self._frame_file(self._mask_dirs[i], t))
        out = np.zeros((self.height, self.width), bool)
        for oid in self._mask_ids[i][0]:
            out |= self._mask_png(self._frame_file(self.path / "mask" / c / oid, t))
        return out

    def controller_masks(self, cam, t) -> List[np.ndarray]:
        """One mask [H, W] bool per controller id (label "hand") of camera ``cam`` at frame ``t``."""
        i, t = self._cam(cam), self._frame(t)
        if self._mask_form != "phystwin":
            return []
        c = self.camera_names[i]
        return [self._mask_png(self._frame_file(self.path / "mask" / c / cid, t))
                for cid in self._mask_ids[i][1]]

    def controller_mask(self, cam, t) -> Optional[np.ndarray]:
        """Union of the controller masks [H, W] bool, or None when the recording has none."""
        ms = self.controller_masks(cam, t)
        if not ms:
            return None
        return np.logical_or.reduce(ms)

    def _frame_file(self, folder: Path, t) -> Path:
        # masks are indexed on demand (cheap listing, cached per folder)
        cache = self.__dict__.setdefault("_mask_index", {})
        if folder not in cache:
            cache[folder] = _index_frames(folder, ("png",))
        return folder / cache[folder][t]["png"]

    # -- other files ---------------------------------------------------------------------------
    def controls(self) -> dict:
        """Validated controls (copies): positions [T, K, 3] m, grip [T, K], shape [K], radius [K] m, ..."""
        if self._controls is None:
            if self.layout == "pgnd":
                raise RecordingError(f"{self.path / 'robot'}: no robot telemetry (robot/<frame>.txt) in this PGND "
                                     f"episode, so no end-effector controls")
            raise RecordingError(f"{self.path / 'controls.npz'}: file missing (derive controls from the hand "
                                 f"masks with empm_gym.perception.fusion.controls_from_masks)")
        return {k: v.copy() for k, v in self._controls.items()}

    def tracks_path(self, cam) -> Optional[Path]:
        c = self.camera_names[self._cam(cam)]
        for folder in ("tracks", "cotracker"):
            p = self.path / folder / f"{c}.npz"
            if p.is_file():
                return p
        return None

    @property
    def has_tracks(self) -> bool:
        return all(self.tracks_path(i) is not None for i in range(self.num_cameras))

    def tracks(self, cam) -> Tuple[np.ndarray, np.ndarray]:
        """2-D tracks of camera ``cam``: (tracks [T, N, 2] float pixel (row, col), visibility [T, N] bool)."""
        p = self.tracks_path(cam)
        if p is None:
            raise RecordingError(f"{self.path / 'tracks' / (self.camera_names[self._cam(cam)] + '.npz')}: file missing "
                                 f"(nor cotracker/<cam>.npz)")
        d = _read_npz(p)
        if "tracks" not in d or "visibility" not in d:
            raise RecordingError(f"{p}: must hold arrays 'tracks' [T, N, 2] and 'visibility' [T, N], has {sorted(d)}")
        tr, vis = d["tracks"], d["visibility"]
        if tr.ndim != 3 or tr.shape[2] != 2:
            raise RecordingError(f"{p}: 'tracks' must have shape [T, N, 2] (row, col), got {list(tr.shape)}")
        if vis.ndim == 3 and vis.shape[2] == 1:
            vis = vis[..., 0]
        if vis.shape != tr.shape[:2]:
            raise RecordingError(f"{p}: 'visibility' must have shape {list(tr.shape[:2])}, got {list(vis.shape)}")
        if tr.shape[0] != self.num_frames:
            raise RecordingError(f"{p}: 'tracks' has {tr.shape[0]} frames but {self._frame_count_source}")
        if not np.issubdtype(tr.dtype, np.number):
            raise RecordingError(f"{p}: 'tracks' must be numeric, got dtype {tr.dtype}")
        vis = vis > 0.5 if vis.dtype != bool else vis
        if not np.all(np.isfinite(tr[vis])):
            raise RecordingError(f"{p}: 'tracks' holds non-finite pixel positions where visible")
        return tr, vis

    def ground_truth(self) -> Optional[dict]:
        """The synthetic recording's ground truth (true parameters, seed, scene), or None for real data."""
        p = self.path / "ground_truth.json"
        return _read_json(p) if p.is_file() else None


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------

_LAYOUT_FILES = ("metadata.json", "calibrate.json", "calibrate.pkl", "controls.npz", "ground_truth.json",
                 "ground_truth_particles.npz")
_LAYOUT_DIRS = ("color", "depth", "mask", "tracks", "cotracker")


def _remove_recording_files(path: Path):
    """Delete only files of the recording layout (frame images, known JSON/npz); keep anything else."""
    for name in _LAYOUT_FILES:
        (path / name).unlink(missing_ok=True)
    for top in _LAYOUT_DIRS:
        root = path / top
        if not root.is_dir():
            continue
        for dirpath, dirnames, filenames in os.walk(root, topdown=False):
            rel = Path(dirpath).relative_to(root).parts
            for f in filenames:
                layout = (
                    (rel and all(p.isdigit() for p in rel) and len(rel) <= 2 and _FRAME_RE.match(f))
                    or (top in ("tracks", "cotracker") and not rel and re.match(r"^\d+\.npz$", f))
                    or (top == "mask" and not rel and re.match(r"^mask_info_\d+\.json$", f))
                )
                if layout:
                    os.unlink(os.path.join(dirpath, f))
            try:
                os.rmdir(dirpath)  # only succeeds when empty
            except OSError:
                pass


class RecordingWriter:
    """Writes a recording frame by frame in the layout :class:`Recording` reads.

    Refuses a non-empty directory unless ``overwrite=True``; then the directory must already be a
    recording (hold metadata.json) and only the layout's files are replaced, never other files.
    ``mask_layout="phystwin"`` writes object masks as id 0 and controller masks as ids 1.. ("hand"),
    ``"simple"`` writes ``mask/<cam>/<frame>.png`` (object only).
    """

    def __init__(self, path, *, intrinsics, c2w, width: int, height: int, fps: float, frame_num: int,
                 depth_scale: float = 0.001, serial_numbers: Optional[Sequence[str]] = None,
                 depth_format: str = "npy", mask_layout: str = "phystwin", object_label: str = "object",
                 calibrate_pickle: bool = False, overwrite: bool = False, extra_metadata: Optional[dict] = None):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise RecordingError(f"{self.path}: exists and is not a directory")
        if self.path.is_dir() and any(self.path.iterdir()):
            if not overwrite:
                raise RecordingError(f"{self.path}: directory is not empty; pass overwrite=True (empm synth "
                                     f"--overwrite) to replace the recording in it")
            if not (self.path / "metadata.json").is_file():
                raise RecordingError(f"{self.path}: not empty and not a recording (no metadata.json); refusing to "
                                     f"write into it even with overwrite=True")
            _remove_recording_files(self.path)
        if depth_format not in ("npy", "png"):
            raise ValueError(f"depth_format must be 'npy' or 'png', got {depth_format!r}")
        if mask_layout not in ("phystwin", "simple"):
            raise ValueError(f"mask_layout must be 'phystwin' or 'simple', got {mask_layout!r}")
        K = np.asarray(intrinsics, np.float64)
        C = K.shape[0]
        c2w = _check_c2w(c2w, "c2w")
        if len(c2w) != C:
            raise ValueError(f"{C} intrinsics but {len(c2w)} camera poses")
        self.num_cameras, self.num_frames = C, int(frame_num)
        self.width, self.height = int(width), int(height)
        self.depth_scale = float(depth_scale)
        self.depth_format, self.mask_layout, self.object_label = depth_format, mask_layout, object_label
        md = {"intrinsics": K.tolist(), "WH": [self.width, self.height], "fps": fps, "frame_num": self.num_frames,
              "serial_numbers": list(serial_numbers) if serial_numbers is not None else [str(i) for i in range(C)],
              "depth_scale": self.depth_scale}
        md.update(extra_metadata or {})
        self.path.mkdir(parents=True, exist_ok=True)
        with open(self.path / "metadata.json", "w") as f:
            json.dump(md, f, indent=1)
        with open(self.path / "calibrate.json", "w") as f:
            json.dump({"c2w": c2w.tolist()}, f, indent=1)
        if calibrate_pickle:
            with open(self.path / "calibrate.pkl", "wb") as f:
                pickle.dump([m for m in c2w], f, protocol=4)
        self._mask_info: Dict[int, Dict[str, str]] = {}

    def _file(self, kind: str, cam: int, t: int, ext: str, sub: Optional[str] = None) -> Path:
        if not (0 <= cam < self.num_cameras):
            raise IndexError(f"camera {cam} out of range (0..{self.num_cameras - 1})")
        if not (0 <= t < self.num_frames):
            raise IndexError(f"frame {t} out of range (0..{self.num_frames - 1})")
        folder = self.path / kind / str(cam)
        if sub is not None:
            folder = folder / sub
        folder.mkdir(parents=True, exist_ok=True)
        return folder / f"{t}.{ext}"

    def _check_hw(self, a: np.ndarray, what: str):
        if a.shape[:2] != (self.height, self.width):
            raise ValueError(f"{what} has shape {a.shape}, expected (height, width) = {(self.height, self.width)}")

    def depth_units(self, depth_m: np.ndarray) -> np.ndarray:
        """Metric depth (m, 0 = missing) -> uint16 depth units (rounded; out-of-range -> 0)."""
        d = np.asarray(depth_m, np.float64)
        u = np.where(np.isfinite(d) & (d > 0), np.round(d / self.depth_scale), 0.0)
        u[u > 65535] = 0
        return u.astype(np.uint16)

    def write_frame(self, cam: int, t: int, *, color=None, depth_m=None, depth_raw=None, mask=None,
                    controller_mask=None):
        """Write one camera's images for frame ``t``: colour uint8 [H, W, 3], depth in metres (quantised to
        depth units) or ``depth_raw`` in depth units as is, object mask (bool [H, W]) and controller mask
        (bool [H, W], or a list of them, one per controller: PhysTwin ids 1, 2, ... labelled "hand")."""
        import imageio.v3 as iio

        if color is not None:
            c = np.asarray(color)
            self._check_hw(c, "color")
            if c.dtype != np.uint8 or c.ndim != 3 or c.shape[2] != 3:
                raise ValueError(f"color must be uint8 [H, W, 3], got {c.dtype} {c.shape}")
            iio.imwrite(self._file("color", cam, t, "png"), c, compress_level=1)
        if depth_m is not None and depth_raw is not None:
            raise ValueError("give depth_m or depth_raw, not both")
        if depth_m is not None:
            depth_raw = self.depth_units(depth_m)
        if depth_raw is not None:
            d = np.asarray(depth_raw)
            self._check_hw(d, "depth")
            if self.depth_format == "npy":
                np.save(self._file("depth", cam, t, "npy"), d, allow_pickle=False)
            else:
                if d.dtype != np.uint16:
                    raise ValueError(f"a depth PNG needs uint16 depth units, got {d.dtype}")
                iio.imwrite(self._file("depth", cam, t, "png"), d, compress_level=1)
        if self.mask_layout == "simple":
            if controller_mask is not None:
                raise ValueError("mask_layout='simple' cannot store controller masks; use mask_layout='phystwin'")
            if mask is not None:
                self._check_hw(np.asarray(mask), "mask")
                iio.imwrite(self._file("mask", cam, t, "png"), (np.asarray(mask, bool) * 255).astype(np.uint8))
            return
        items = [("0", mask)]
        if controller_mask is not None:
            cms = controller_mask if isinstance(controller_mask, (list, tuple)) else [controller_mask]
            items += [(str(k + 1), m) for k, m in enumerate(cms)]
        for sub, m in items:
            if m is None:
                continue
            self._check_hw(np.asarray(m), "mask")
            iio.imwrite(self._file("mask", cam, t, "png", sub), (np.asarray(m, bool) * 255).astype(np.uint8))
            info = self._mask_info.setdefault(cam, {})
            if sub not in info:
                info[sub] = self.object_label if sub == "0" else CONTROLLER_LABEL
                (self.path / "mask" / f"mask_info_{cam}.json").write_text(json.dumps(info))

    def write_controls(self, **arrays):
        """Write ``controls.npz`` (validated first; see :func:`validate_controls` for the keys)."""
        validate_controls(arrays, self.num_frames, "controls")
        np.savez(self.path / "controls.npz", **{k: np.asarray(v) for k, v in arrays.items()})

    def write_tracks(self, cam: int, tracks, visibility, folder: str = "tracks"):
        """Write ``tracks/<cam>.npz``: tracks [T, N, 2] pixel (row, col), visibility [T, N] bool."""
        tr, vis = np.asarray(tracks), np.asarray(visibility, bool)
        if tr.ndim != 3 or tr.shape[0] != self.num_frames or tr.shape[2] != 2 or vis.shape != tr.shape[:2]:
            raise ValueError(f"tracks must be [T={self.num_frames}, N, 2] with visibility [T, N], got "
                             f"{tr.shape} and {vis.shape}")
        (self.path / folder).mkdir(exist_ok=True)
        np.savez(self.path / folder / f"{cam}.npz", tracks=tr, visibility=vis)

    def write_ground_truth(self, data: dict):
        with open(self.path / "ground_truth.json", "w") as f:
            json.dump(data, f, indent=1)


def write_recording(path, *, intrinsics, c2w, width: int, height: int, fps: float, color, depth_m=None,
                    depth_raw=None, masks=None, controller_masks=None, controls: Optional[dict] = None,
                    tracks: Optional[Sequence[Tuple[np.ndarray, np.ndarray]]] = None,
                    ground_truth: Optional[dict] = None, overwrite: bool = False, **writer_kw) -> Path:
    """Write a whole recording from arrays indexed ``[cam][frame]`` (colour uint8 [H, W, 3]; depth in metres
    or raw depth units [H, W]; masks bool [H, W]); returns the path. See :class:`RecordingWriter`."""
    C, T = len(color), len(color[0])
    w = RecordingWriter(path, intrinsics=intrinsics, c2w=c2w, width=width, height=height, fps=fps, frame_num=T,
                        overwrite=overwrite, **writer_kw)
    for c in range(C):
        for t in range(T):
            w.write_frame(c, t, color=color[c][t],
                          depth_m=None if depth_m is None else depth_m[c][t],
                          depth_raw=None if depth_raw is None else depth_raw[c][t],
                          mask=None if masks is None else masks[c][t],
                          controller_mask=None if controller_masks is None else controller_masks[c][t])
    if controls is not None:
        w.write_controls(**controls)
    for c, tr in enumerate(tracks or []):
        w.write_tracks(c, *tr)
    if ground_truth is not None:
        w.write_ground_truth(ground_truth)
    return Path(path)
