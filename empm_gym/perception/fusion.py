"""From a recording's depth images to world-frame point sets, a table plane, frame-0 particles and controls.

Typical use by identification::

    rec = Recording(path)
    plane = estimate_table_plane(rec)                     # or (normal, offset) when the table is known
    obs = [fuse_frame(rec, t) for t in range(rec.num_frames)]  # [N_t, 3] m each, object only
    x0, vol = initial_particles(obs[0], dx=0.01, table_plane=plane)   # solid body, interior filled
    controls = load_controls(rec)                          # controls.npz, or from the "hand" masks

A plane is ``(normal [3], offset)`` with ``normal . x + offset = 0`` on the plane (m) and the
normal pointing up, away from the table into the half-space holding the object.
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

import numpy as np

from .cameras import Camera
from .recording import Recording, RecordingError, validate_controls

__all__ = [
    "fuse_views",
    "frame_points",
    "fuse_frame",
    "voxel_downsample",
    "remove_statistical_outliers",
    "fit_table_plane",
    "estimate_table_plane",
    "close_against_table",
    "smooth_points",
    "initial_particles",
    "carve_with_depth",
    "outside_surface",
    "complete_occluded",
    "view_gap_deg",
    "complete_by_symmetry",
    "half_turn_axis",
    "complete_unseen_side",
    "hidden_by_end_effectors",
    "inside_end_effectors",
    "within_footprint",
    "inside_open_end_effectors",
    "end_effector_sdf",
    "controls_from_masks",
    "load_controls",
    "camera_agreement",
    "camera_shifts",
    "refine_calibration",
    "end_effector_agreement",
    "calibration_tolerance",
    "surface_consistency",
    "temporal_depth_noise",
    "object_mask",
    "drop_table_rim",
    "table_rim_band",
]


def _o3d():
    try:
        import open3d as o3d
    except OSError as exc:  # missing system library, typically libusb-1.0
        raise ImportError(f"open3d failed to import ({exc}); on Debian/Ubuntu install libusb-1.0-0 "
                          f"(apt-get install libusb-1.0-0)") from exc
    return o3d


def _pcd(points: np.ndarray):
    o3d = _o3d()
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64).reshape(-1, 3))
    return pc


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Points [N, 3] (m) averaged per voxel of edge ``voxel_m`` (m) with Open3D; voxel_m <= 0 returns a copy."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if voxel_m is None or voxel_m <= 0 or len(pts) == 0:
        return pts.copy()
    return np.asarray(_pcd(pts).voxel_down_sample(float(voxel_m)).points)


def remove_statistical_outliers(points: np.ndarray, nb_neighbors: int = 20, std_ratio: float = 2.0):
    """Drop points whose mean distance to their ``nb_neighbors`` nearest neighbours exceeds the global
    mean by ``std_ratio`` standard deviations (Open3D). Returns ``(kept points [M, 3], kept indices [M])``."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) <= nb_neighbors:
        return pts.copy(), np.arange(len(pts))
    _, ind = _pcd(pts).remove_statistical_outlier(nb_neighbors=int(nb_neighbors), std_ratio=float(std_ratio))
    ind = np.asarray(ind, dtype=np.int64)
    return pts[ind], ind


def fuse_views(depths: Sequence[np.ndarray], cameras: Sequence[Camera], masks: Optional[Sequence] = None, *,
               erode_px: int = 1, min_depth_m: float = 0.1, max_depth_m: float = 5.0) -> np.ndarray:
    """Back-project several metric depth images [H, W] (m) with their cameras into one world point set [N, 3] (m).

    With ``masks`` (bool [H, W] per view, None for "all pixels") only masked pixels are used; the masks
    are first eroded by ``erode_px`` pixels, since depth at a silhouette mixes object and background.
    """
    from scipy import ndimage

    if len(depths) != len(cameras) or (masks is not None and len(masks) != len(cameras)):
        raise ValueError(f"fuse_views: {len(depths)} depth images, {len(cameras)} cameras"
                         + ("" if masks is None else f", {len(masks)} masks") + " must agree")
    out = []
    for i, (d, cam) in enumerate(zip(depths, cameras)):
        m = None if masks is None else masks[i]
        if m is not None and erode_px > 0:
            m = ndimage.binary_erosion(np.asarray(m, bool), iterations=int(erode_px))
        out.append(cam.backproject(np.asarray(d), m, min_depth_m=min_depth_m, max_depth_m=max_depth_m))
    return np.concatenate(out, axis=0) if out else np.zeros((0, 3))


def object_mask(rec: Recording, cam: int, t: int) -> np.ndarray:
    """The pixels [H, W] bool that measure the object in camera ``cam`` at frame ``t``: its mask less every pixel
    that an end-effector's mask claims too. A segmenter's masks overlap where the object meets a gripper or a hand
    (a mask that bleeds a few pixels onto it), and the depth there is as often the end-effector's surface."""
    m = np.asarray(rec.mask(cam, t), bool)
    ctl = rec.controller_mask(cam, t) if rec.has_controller_masks else None
    return m if ctl is None else m & ~np.asarray(ctl, bool)


def frame_points(rec: Recording, t: int, *, cams: Optional[Sequence[int]] = None, use_mask: bool = True,
                 erode_px: int = 1, min_depth_m: float = 0.1, max_depth_m: float = 5.0) -> np.ndarray:
    """Raw fused object points [N, 3] (m, world) of frame ``t`` from the given cameras (default all)."""
    cams = list(range(rec.num_cameras)) if cams is None else list(cams)
    if use_mask and not rec.has_masks:
        raise RecordingError(f"{rec.path / 'mask'}: object masks are needed to separate the object "
                             f"(or pass use_mask=False)")
    allc = rec.cameras
    depths = [rec.depth(c, t) for c in cams]
    masks = [object_mask(rec, c, t) for c in cams] if use_mask else None
    return fuse_views(depths, [allc[c] for c in cams], masks, erode_px=erode_px, min_depth_m=min_depth_m,
                      max_depth_m=max_depth_m)


def fuse_frame(rec: Recording, t: int, *, voxel_m: float = 0.002, nb_neighbors: int = 20, std_ratio: float = 2.0,
               table_plane: Optional[Tuple[np.ndarray, float]] = None, min_height_m: float = 0.0,
               rim_band_m: Optional[float] = None, stats: Optional[dict] = None, **kw) -> np.ndarray:
    """Object points [N, 3] (m, world) of frame ``t``: all views fused, voxel-downsampled at ``voxel_m`` (m),
    statistical outliers removed (``nb_neighbors``, ``std_ratio``); with ``table_plane`` also points less
    than ``min_height_m`` (m) above the table are dropped, and with ``rim_band_m`` the table's points a mask
    took in around the object's base (:func:`drop_table_rim`, reaching ``2 * voxel_m`` or 4 mm; ``stats``, a
    dict, receives ``points`` and ``rim_dropped``). Extra keywords go to :func:`frame_points`."""
    pts = frame_points(rec, t, **kw)
    if table_plane is not None and len(pts):
        n, off = table_plane
        pts = pts[pts @ np.asarray(n, float) + off >= min_height_m]
    pts = voxel_downsample(pts, voxel_m)
    dropped = 0
    if table_plane is not None and rim_band_m is not None and len(pts):
        reach = max(2.0 * voxel_m, 0.004)
        pts, dropped = drop_table_rim(pts, table_plane, rim_band_m, reach_m=reach,
                                      end_effectors=lambda: _end_effector_points(rec, t, kw.get("cams"), voxel_m),
                                      near_m=2.0 * reach)
    if stats is not None:
        stats.update(points=len(pts) + dropped, rim_dropped=dropped)
    if nb_neighbors and nb_neighbors > 0:
        pts, _ = remove_statistical_outliers(pts, nb_neighbors, std_ratio)
    return pts


#: the table's band, in depth-noise standard deviations: a point of the table seen through a mask that bleeds
#: onto it lies this close above the table's plane (2.5 sigma holds 99 % of them), :func:`table_rim_band`
TABLE_RIM_SIGMAS = 2.5


def table_rim_band(rec: Recording, voxel_m: float, *, frames: int = 30,
                   sigma_m: Optional[float] = None) -> Optional[float]:
    """The height [m] above the table under which a point of the object's masks may be the table's own
    (:func:`drop_table_rim`): :data:`TABLE_RIM_SIGMAS` times the depth's noise ``sigma_m`` (m; default measured on
    the first ``frames`` frames, :func:`temporal_depth_noise`), at least half of ``voxel_m``. None when the noise
    cannot be measured (fewer than 3 frames in a row that see the object, no masks): then no point is taken for
    the table's."""
    sigma = temporal_depth_noise(rec, frames) if sigma_m is None else float(sigma_m)
    return max(0.5 * float(voxel_m), TABLE_RIM_SIGMAS * sigma) if np.isfinite(sigma) else None


def _end_effector_points(rec: Recording, t: int, cams: Optional[Sequence[int]], voxel_m: float) -> Optional[np.ndarray]:
    """The end-effectors' points [N, 3] (m) of frame ``t`` (their masks' depth, voxel-downsampled), or None when the
    recording has no controller masks."""
    if not rec.has_controller_masks:
        return None
    cams = list(range(rec.num_cameras)) if cams is None else list(cams)
    masks = [rec.controller_mask(c, t) for c in cams]
    if all(m is None for m in masks):
        return None
    masks = [np.zeros((rec.height, rec.width), bool) if m is None else m for m in masks]
    pts = fuse_views([rec.depth(c, t) for c in cams], [rec.cameras[c] for c in cams], masks, erode_px=0)
    return voxel_downsample(pts, voxel_m)


#: a low point with this many points one band higher within reach is the foot of a side (:func:`drop_table_rim`):
#: the table's own noise puts a stray point over the band, not several together
SIDE_POINTS = 3


def table_heights(points: np.ndarray, table_plane: Tuple[np.ndarray, float]) -> Tuple[np.ndarray, np.ndarray]:
    """``(heights [N] m, unit normal [3])``: how far ``points`` [N, 3] (m) lie above the table ``(normal, offset)``
    (the normal scaled to unit length, the offset as given)."""
    n = np.asarray(table_plane[0], np.float64)
    n = n / np.linalg.norm(n)
    return np.asarray(points, np.float64).reshape(-1, 3) @ n + float(table_plane[1]), n


def lies_flat(heights: np.ndarray, band_m: float, max_low_share: float = 0.5) -> bool:
    """Whether an object whose points stand ``heights`` [N] (m) above the table lies too flat for the depth to tell
    its points from the table's within ``band_m`` of it: more than ``max_low_share`` of them that low, or none
    reaching ``3 * band_m`` (:func:`drop_table_rim`)."""
    h = np.asarray(heights, np.float64)
    return bool(len(h) and ((h < band_m).mean() > max_low_share or h.max() < 3.0 * band_m))


def drop_table_rim(points: np.ndarray, table_plane: Tuple[np.ndarray, float], band_m: float, *,
                   reach_m: float = 0.004, max_low_share: float = 0.5, end_effectors=None,
                   near_m: float = 0.008) -> Tuple[np.ndarray, int]:
    """``(points [M, 3], dropped)``: ``points`` [N, 3] (m) less the table's points that a segmenter's mask took in
    around the object's base. A mask that bleeds a few pixels past the object's silhouette where it stands on the
    table (or past its top, onto the table behind it) puts a rim of table points, within the depth's noise of the
    plane, around the body. The object's own points that low are the foot of a side that rises from the table:
    a point less than ``band_m`` above the table is kept only where a point ``band_m`` to ``2 * band_m`` high lies
    within ``reach_m`` of it across the table, itself with a point ``2 * band_m`` to ``3 * band_m`` high within
    ``reach_m`` (the side rising above it: the table's own noise reaches past one band on a few points, not two),
    where :data:`SIDE_POINTS` such points one band higher do (a foot whose side above is hidden), or within
    ``near_m`` of a point of ``end_effectors`` [K, 3] (m, or a function returning them or None, called only when a
    point would go; a gripper's plate hides the side above the object's foot below it). Nothing is dropped when more than ``max_low_share`` of the points lie that low or none
    reaches ``3 * band_m`` (a flat object the depth cannot tell from the table)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    h, n = table_heights(pts, table_plane)
    low = h < band_m
    if not low.any() or lies_flat(h, band_m, max_low_share):
        return pts, 0
    from scipy.spatial import cKDTree

    foot = pts - h[:, None] * n  # on the table: distances across it

    def near(a, b, k=1):
        """Of the points ``a`` (a mask), those with ``k`` points of ``b`` (a mask) within reach across the table."""
        out = np.zeros(len(pts), bool)
        if a.sum() and b.sum() >= k:
            d = cKDTree(foot[b]).query(foot[a], k=[k], distance_upper_bound=reach_m)[0][:, 0]
            out[np.flatnonzero(a)] = np.isfinite(d)
        return out

    first = (h >= band_m) & (h < 2.0 * band_m)
    side = near(first, (h >= 2.0 * band_m) & (h < 3.0 * band_m))
    keep = ~low | near(low, side) | near(low, first, SIDE_POINTS)
    if end_effectors is not None and not keep.all():
        ee = end_effectors() if callable(end_effectors) else end_effectors
        if ee is not None and len(ee):
            by_ee = cKDTree(np.asarray(ee, np.float64).reshape(-1, 3)).query(pts[~keep], distance_upper_bound=near_m)[0]
            keep[np.flatnonzero(~keep)[np.isfinite(by_ee)]] = True
    return pts[keep], int((~keep).sum())


#: a second difference's residual from the median of 8 neighbours' has 1 + pi / 16 times its variance
NEIGHBOUR_MEDIAN_INFLATION = math.sqrt(1.0 + math.pi / 16.0)


def temporal_depth_noise(rec: Recording, frames: Optional[int] = None, *, erode_px: int = 2,
                         min_pixels: int = 200) -> float:
    """Robust standard deviation [m] of a depth pixel on the object from frame to frame, along its ray.

    Over every camera's object pixels (masks eroded by ``erode_px``: no silhouette edge) whose depth is valid in
    three consecutive frames, the second difference d[t+1] - 2 d[t] + d[t-1] holds six times the variance of the
    depth's noise and the surface's acceleration along the ray. The acceleration is the same a few millimetres
    away: the median of eight pixels' about 7 mm off (a ring of ``5 * width / 848`` pixels, beyond the few pixels a
    depth camera's noise is correlated over) is taken off, leaving the noise (:data:`NEIGHBOUR_MEDIAN_INFLATION`).
    Scaled from depth to the distance along the pixel's ray. It is what a tracked point lifted with its depth
    scatters by, frame to frame, when the tracker itself is exact
    (:func:`~empm_gym.identification.data.track_noise`). NaN with fewer than ``min_pixels`` such pixels (no masks,
    fewer than 3 frames)."""
    from scipy import ndimage

    T = rec.num_frames if frames is None else min(int(frames), rec.num_frames)
    if T < 3 or not rec.has_masks:
        return float("nan")
    ring = max(2, int(round(5.0 * rec.width / 848.0)))
    offsets = [(dr, dc) for dr in (-ring, 0, ring) for dc in (-ring, 0, ring) if dr or dc]
    vals = []
    for c, cam in enumerate(rec.cameras):
        rr, cc = np.mgrid[0:rec.height, 0:rec.width]
        stretch = np.sqrt(1.0 + ((cc - cam.K[0, 2]) / cam.K[0, 0]) ** 2 + ((rr - cam.K[1, 2]) / cam.K[1, 1]) ** 2)
        win = []
        for t in range(T):
            m = ndimage.binary_erosion(object_mask(rec, c, t), iterations=int(erode_px))
            win.append(np.where(m, rec.depth(c, t), 0.0))
            if len(win) < 3:
                continue
            a, b, d = win
            win.pop(0)
            ok = (a > 0) & (b > 0) & (d > 0)
            if ok.sum() < 9:
                continue
            acc = np.where(ok, (d - 2.0 * b + a) * stretch, np.nan)
            pad = np.pad(acc, ring, constant_values=np.nan)
            nb = np.stack([pad[ring + dr:ring + dr + rec.height, ring + dc:ring + dc + rec.width]
                           for dr, dc in offsets])
            enough = ok & (np.isfinite(nb).sum(0) >= 4)
            if enough.any():
                vals.append(acc[enough] - np.nanmedian(nb[:, enough], axis=0))
    v = np.concatenate(vals) if vals else np.zeros(0)
    if len(v) < min_pixels:
        return float("nan")
    return float(np.median(np.abs(v)) / 0.6745 / np.sqrt(6.0) / NEIGHBOUR_MEDIAN_INFLATION)


def fit_table_plane(points: np.ndarray, *, distance_threshold_m: float = 0.004, iterations: int = 1000,
                    up_hint: Sequence[float] = (0.0, 0.0, 1.0), seed: int = 0) -> Tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane of a point set by RANSAC, then a least-squares refit to its inliers.

    Returns ``(normal [3], offset, inlier indices)`` with ``normal . x + offset = 0`` on the plane and
    the normal oriented to have a positive component along ``up_hint`` (e.g. towards the cameras).

    Deterministic for a given ``seed``, whatever the machine's load: every one of ``iterations`` samples
    is scored (most inliers, then the smallest inlier RMS; ties go to the earlier sample). Open3D's
    ``segment_plane`` stops early in whichever thread gets there first, so under load it returned
    different planes for the same points, and a fit could not be resumed in another process.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) < 3:
        raise ValueError(f"fit_table_plane: need at least 3 points, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("fit_table_plane: the points hold NaN or infinite coordinates")
    thr = float(distance_threshold_m)
    if not thr > 0.0:
        raise ValueError(f"fit_table_plane: distance_threshold_m must be positive, got {distance_threshold_m}")
    rng = np.random.default_rng(int(seed))
    samples = rng.integers(0, len(pts), (max(1, int(iterations)), 3))  # repeated points give no plane: skipped
    centred = pts - pts.mean(0)  # better conditioned offsets
    best = (-1, np.inf, None)
    chunk = max(1, min(len(samples), (1 << 22) // len(pts)))
    for i in range(0, len(samples), chunk):
        s = samples[i:i + chunk]
        a, b, c = centred[s[:, 0]], centred[s[:, 1]], centred[s[:, 2]]
        nrm = np.cross(b - a, c - a)
        norm = np.linalg.norm(nrm, axis=1)
        ok = norm > 1e-12
        nrm = nrm[ok] / norm[ok, None]
        if not len(nrm):
            continue
        dist = np.abs(centred @ nrm.T - np.sum(nrm * a[ok], axis=1))
        inl = dist < thr
        count = inl.sum(0)
        rms = np.sqrt(np.where(inl, dist * dist, 0.0).sum(0) / np.maximum(count, 1))
        k = np.lexsort((rms, -count))[0]  # most inliers, then smallest RMS; stable: the earliest on ties
        if count[k] > best[0] or (count[k] == best[0] and rms[k] < best[1]):
            best = (int(count[k]), float(rms[k]), (nrm[k], float(-nrm[k] @ a[ok][k])))
    if best[2] is None:
        raise ValueError("fit_table_plane: the points are collinear; no plane through them")
    n, d, inliers = _refine_plane(centred, *best[2], thr)
    d = float(d - n @ pts.mean(0))  # back to the original coordinates
    if n @ np.asarray(up_hint, float) < 0:
        n, d = -n, -d
    return n, d, inliers.astype(np.int64)


def _refine_plane(centred: np.ndarray, n: np.ndarray, d: float, thr: float):
    """Least-squares refits of the plane ``n . x + d = 0`` to the points of ``centred`` (coordinates about their
    mean) within ``thr`` of it (the smallest principal direction) until the inliers settle: ``(n, d, inliers)``."""
    inliers = np.flatnonzero(np.abs(centred @ n + d) < thr)
    for _ in range(10):
        q = centred[inliers]
        mean = q.mean(0)
        n_new = np.linalg.svd(q - mean, full_matrices=False)[2][-1]
        n = n_new if n_new @ n >= 0 else -n_new
        d = float(-n @ mean)
        new = np.flatnonzero(np.abs(centred @ n + d) < thr)
        if len(new) < 3 or np.array_equal(new, inliers):
            break
        inliers = new
    return n, d, inliers


#: A direction that fewer than this many pairs of a camera's points with the others' face along (their normal
#: within 60 deg of it; with 2 mm voxels, 4 cm^2 of shared surface) is reported as unmeasured by
#: :func:`camera_agreement` and left out by :func:`camera_shifts`. A count, not a share of the pairs: the table
#: around the object, as large as the 12 cm reach makes it, would otherwise decide. Calibrated synthetic rigs
#: (848 x 480): 0-55 such pairs along a direction the surfaces leave free (a box's faces between plates, a rope's
#: axis), 195 and more along the others, but 81 on one rope camera (session 83).
_SHARED_PAIRS = 100

#: Point-to-plane solves of :func:`camera_agreement` (each with its nearest neighbours found again).
_SHIFT_ITERATIONS = 12
#: The first solves pair points this far apart (m), shrinking by :data:`_REACH_SHRINK` a solve down to the pairs'
#: own limit: a camera 5 mm and 0.5 deg off (10-20 mm at the object with a 2 % depth scale) has few true partners
#: within 1 cm to start from.
_FIRST_REACH_M = 0.03
_REACH_SHRINK = 0.7


def _reach(it: int, floor_m: float) -> float:
    """How far apart [m] the pairs of solve ``it`` may lie (:data:`_FIRST_REACH_M` shrinking to ``floor_m``)."""
    return max(float(floor_m), _FIRST_REACH_M * _REACH_SHRINK ** it)

#: A camera whose points must shift by more than this (m) to lie on the others' surface is reported by
#: :func:`camera_agreement` (and corrected by :func:`refine_calibration`), as is a rig whose end-effectors lie that
#: far from where the controls put them; or by more than :data:`CALIBRATION_TOLERANCE_PX` pixels at the object's
#: depth where that is more (:func:`calibration_tolerance`). Calibrated synthetic rigs at 848 x 480 read 0.1-0.4 mm
#: between cameras and 0.02-0.24 mm against the controls; at 320 x 180 (3.5 mm pixels) up to 1.45 mm between
#: cameras (a rounded lump beside a pusher) (benchmarks/RESULTS.md, session 83).
CALIBRATION_TOLERANCE_M = 1.5e-3
#: The same in pixels of the coarsest camera at the object's depth: a shift of a fraction of a pixel is the
#: sampling's, not the calibration's.
CALIBRATION_TOLERANCE_PX = 0.6


def calibration_tolerance(rec: Recording, t: int = 0) -> float:
    """The disagreement [m] a calibrated rig may show (:data:`CALIBRATION_TOLERANCE_M`, or
    :data:`CALIBRATION_TOLERANCE_PX` pixels of the coarsest camera at the object's median depth where more)."""
    pixel = 0.0
    for c, cam in enumerate(rec.cameras):
        d = rec.depth(c, t)
        m = rec.mask(c, t) if rec.has_masks else d > 0
        z = d[m & (d > 0)]
        if len(z):
            pixel = max(pixel, float(np.median(z)) / float(min(cam.K[0, 0], cam.K[1, 1])))
    return max(CALIBRATION_TOLERANCE_M, CALIBRATION_TOLERANCE_PX * pixel)


def _camera_clouds(rec: Recording, t: int, radius_m: float, voxel_m: float):
    """Per camera: its frame-``t`` depth points within ``radius_m`` of the object's centre, averaged per ``voxel_m``
    voxel, and their normals turned towards it; None without object points."""
    o3d = _o3d()
    obj = frame_points(rec, t, use_mask=rec.has_masks)
    if len(obj) == 0:
        return None
    centre = np.median(obj, axis=0)
    clouds, facing = [], []
    for c, cam in enumerate(rec.cameras):
        p = cam.backproject(rec.depth(c, t), None)
        pc = _pcd(voxel_downsample(p[np.linalg.norm(p - centre, axis=1) < radius_m], voxel_m))
        if len(pc.points) >= 20:
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=20))
            pc.orient_normals_towards_camera_location(cam.position)
        clouds.append(np.asarray(pc.points))
        facing.append(np.asarray(pc.normals) if pc.has_normals() else np.zeros((len(pc.points), 3)))
    return clouds, facing


def _surface_pairs(src: np.ndarray, src_n: np.ndarray, dst: np.ndarray, dst_n: np.ndarray, tree, max_pair_m: float):
    """Pairs of ``src`` points with their nearest ``dst`` points within ``max_pair_m`` on the same side of the same
    surface: the two normals, each turned towards the camera that saw it, agree (not a face one camera sees against
    an edge or the table beside it, nor against the far face of a thin plate, that the others see). Returns the
    pairs' ``(source indices, target indices, target normals, point-to-plane residuals [m])``."""
    d, j = tree.query(src, distance_upper_bound=max_pair_m)
    i = np.nonzero(np.isfinite(d))[0]
    i = i[np.einsum("ij,ij->i", dst_n[j[i]], src_n[i]) > 0.95]
    n = dst_n[j[i]]
    return i, j[i], n, np.einsum("ij,ij->i", n, src[i] - dst[j[i]])


def _unmeasured(n: np.ndarray, A: np.ndarray) -> List[np.ndarray]:
    """Directions (unit [3], the eigenvectors of ``A``) that fewer than :data:`_SHARED_PAIRS` of the pairs'
    normals ``n`` face along (within 60 deg): a table's noisy normals add up to a weight along every direction of
    ``A`` but tell nothing of a shift along the table."""
    _, vec = np.linalg.eigh(A)
    return [vec[:, i] for i in range(3) if np.sum(np.abs(n @ vec[:, i]) > 0.5) < _SHARED_PAIRS]


def camera_agreement(rec: Recording, t: int = 0, *, radius_m: float = 0.12, voxel_m: float = 0.002,
                     max_pair_m: float = 0.01, tolerance_m: Optional[float] = None) -> dict:
    """Whether the cameras' calibrations agree: how far each camera's frame-``t`` points must move to lie on the
    surface the other cameras measure.

    All depth pixels within ``radius_m`` of the object's centre (the object, the table around it, the
    end-effectors: everything rigid at frame 0) are back-projected per camera and averaged per ``voxel_m`` voxel.
    Each camera's points are then moved by the one translation that best puts them on the others' surface
    (point-to-plane least squares over :func:`_surface_pairs`, Huber-weighted, nearest neighbours found again
    :data:`_SHIFT_ITERATIONS` times, pairs within 3 cm at first and ``max_pair_m`` at last, :func:`_reach`). A translation, not a rigid motion: near the object a
    pose's small rotation acts as a shift (0.3 deg at 0.55 m: 2.9 mm), and a rotation's fit drifts along a table
    plane's free directions. A calibrated rig needs no shift beyond what the noise leaves; a camera whose pose or
    depth scale is off needs one.

    Returns ``cameras`` (per camera: ``offset_m`` [3] and ``offset_norm_m``, the shift; ``rms_before_m`` and
    ``rms_after_m``, the point-to-plane distances' RMS before and after it; ``pairs``; ``unmeasured_directions``,
    unit vectors along which the surfaces it shares with the others hardly constrain a shift (:func:`_unmeasured`), so that a
    calibration error along them goes unseen: plates hiding a box's faces; the shift reported has no part along
    them), ``largest_offset_m`` and ``note``: None, or a sentence naming the cameras off by more than
    ``tolerance_m`` (the fused points of such a rig are thicker than the depth noise, and every fit's floor rises
    with them; default :func:`calibration_tolerance`). With one camera there is nothing to compare: ``cameras`` is
    empty."""
    from scipy.spatial import cKDTree

    C = rec.num_cameras
    tolerance_m = calibration_tolerance(rec, t) if tolerance_m is None else float(tolerance_m)
    out = {"frame": int(t), "cameras": [], "largest_offset_m": None, "note": None, "tolerance_m": float(tolerance_m)}
    got = _camera_clouds(rec, t, radius_m, voxel_m) if C >= 2 else None
    if got is None:
        return out
    clouds, facing = got
    delta = 1.5 * voxel_m  # Huber's threshold [m]
    for c in range(C):
        src, src_n = clouds[c], facing[c]
        dst = np.concatenate([clouds[k] for k in range(C) if k != c])
        if len(src) < 100 or len(dst) < 100:
            continue
        normals = np.concatenate([facing[k] for k in range(C) if k != c])
        tree = cKDTree(dst)
        shift = np.zeros(3)
        rms = []
        for it in range(_SHIFT_ITERATIONS + 1):
            _, _, n, r = _surface_pairs(src + shift, src_n, dst, normals, tree, _reach(it, max_pair_m))
            rms.append(float(np.sqrt(np.mean(r ** 2))) if len(r) else float("nan"))
            if it == _SHIFT_ITERATIONS or len(r) < 50:
                break
            w = np.minimum(1.0, delta / np.maximum(np.abs(r), 1e-12))
            A = (n * w[:, None]).T @ n
            shift = shift - np.linalg.solve(A + 1e-3 * np.trace(A) / 3.0 * np.eye(3), (n * w[:, None]).T @ r)
        if len(r) < 50:
            continue
        free = _unmeasured(n, A)
        for u in free:  # what is reported is the shift the shared surfaces measure
            shift = shift - (shift @ u) * u
        out["cameras"].append({"camera": c, "name": rec.camera_names[c], "offset_m": [float(v) for v in shift],
                               "offset_norm_m": float(np.linalg.norm(shift)), "rms_before_m": rms[0],
                               "rms_after_m": rms[-1], "pairs": int(len(r)),
                               "unmeasured_directions": [[float(v) for v in u] for u in free]})
    if out["cameras"]:
        out["largest_offset_m"] = max(r["offset_norm_m"] for r in out["cameras"])
        off = [r for r in out["cameras"] if r["offset_norm_m"] > tolerance_m]
        if off:
            each = ", ".join(f"camera {r['camera']} by {1e3 * r['offset_norm_m']:.1f} mm"
                             for r in sorted(off, key=lambda r: -r["offset_norm_m"]))
            out["note"] = (f"the cameras disagree at frame {t}: to lie on the other cameras' surface, {each} must be "
                           f"shifted, beyond the {1e3 * tolerance_m:.1f} mm a calibrated rig shows here. The fused points "
                           f"are then thicker than the depth noise and every fit's floor rises with them: check the "
                           f"extrinsics (c2w) and the depth scale")
    return out


def camera_shifts(rec: Recording, t: int = 0, *, radius_m: float = 0.12, voxel_m: float = 0.002,
                  max_pair_m: float = 0.01) -> np.ndarray:
    """Translations [C, 3] (m) that, added to the cameras' positions (``c2w[:, :3, 3]``), bring all cameras'
    frame-``t`` points onto one surface: :func:`camera_agreement`'s point-to-plane pairs of every camera with every
    other, solved for all shifts at once (Huber-weighted least squares, nearest neighbours found again
    :data:`_SHIFT_ITERATIONS` times), their mean held at zero (the pairs tell how the cameras sit relative to each
    other, not where the rig sits). A camera's shift then loses its part along a direction its pairs do not measure
    (:func:`_unmeasured`; the mean along it is then no longer zero). Zeros for fewer than two cameras or no object
    points."""
    from scipy.spatial import cKDTree

    C = rec.num_cameras
    S = np.zeros((C, 3))
    got = _camera_clouds(rec, t, radius_m, voxel_m) if C >= 2 else None
    if got is None:
        return S
    clouds, facing = got
    trees = [cKDTree(p) if len(p) else None for p in clouds]
    delta = 1.5 * voxel_m
    for it in range(_SHIFT_ITERATIONS):
        H = np.zeros((3 * C, 3 * C))
        g = np.zeros(3 * C)
        seen = [[] for _ in range(C)]
        for c in range(C):
            for k in range(C):
                if k == c or trees[k] is None or len(clouds[c]) < 100:
                    continue
                # c's point p, shifted by S[c], against k's surface shifted by S[k]: r = n . (p + S[c] - q - S[k])
                _, _, n, r = _surface_pairs(clouds[c] + S[c] - S[k], facing[c], clouds[k], facing[k], trees[k],
                                            _reach(it, max_pair_m))
                if len(r) < 50:
                    continue
                w = np.minimum(1.0, delta / np.maximum(np.abs(r), 1e-12))
                A, b = (n * w[:, None]).T @ n, (n * w[:, None]).T @ r
                a, e = slice(3 * c, 3 * c + 3), slice(3 * k, 3 * k + 3)
                H[a, a] += A
                H[e, e] += A
                H[a, e] -= A
                H[e, a] -= A
                g[a] += b
                g[e] -= b
                seen[c].append(n)
                seen[k].append(n)
        scale = np.trace(H) / max(3 * C, 1)
        if scale <= 0:
            return S
        gauge = np.kron(np.ones((C, C)), np.eye(3))  # the mean shift's own term: holds it at zero
        step = np.linalg.solve(H + scale * (1e-3 * np.eye(3 * C) + gauge / C), -g)
        S = S + step.reshape(C, 3)
    for c in range(C):
        if seen[c]:
            n = np.concatenate(seen[c])
            for u in _unmeasured(n, n.T @ n):
                S[c] = S[c] - (S[c] @ u) * u
        else:
            S[c] = 0.0
    return S


#: :func:`end_effector_agreement` trusts its shift only where the observed end-effector points lie this close (RMS,
#: m) to the modelled shapes once shifted: a hand or a tool its controls model only roughly reads more.
END_EFFECTOR_FIT_M = 2.5e-3


def end_effector_agreement(rec: Recording, t: int = 0, *, band_m: float = 0.01, min_points: int = 200) -> dict:
    """Whether the cameras and the controls agree on where the end-effectors are: the translation that moves the
    observed end-effector points of frame ``t`` (the controller masks, back-projected) onto the shapes the controls
    place there (:func:`end_effector_sdf`, points within 3 cm of a shape at first and ``band_m`` at last,
    :func:`_reach`; Huber-weighted Gauss-Newton on the signed distance, ten steps).

    Returns ``offset_m`` [3] (to add to every camera's position; None where it cannot be measured),
    ``offset_norm_m``, ``rms_before_m`` / ``rms_after_m`` (the points' distances to the shapes), ``points``,
    ``unmeasured_directions`` (the shift along them is left out) and ``trusted``: at least ``min_points`` points,
    and within :data:`END_EFFECTOR_FIT_M` of the shapes once shifted (grippers whose shapes the controls describe;
    not a hand modelled as a sphere). ``why`` says why not. Needs per-end-effector controller masks and
    ``controls.npz``."""
    out = {"offset_m": None, "offset_norm_m": None, "rms_before_m": None, "rms_after_m": None, "points": 0,
           "unmeasured_directions": [], "trusted": False, "why": None}
    if not rec.has_controls or not rec.has_controller_masks:
        out["why"] = "the recording has no controls.npz or no per-end-effector masks"
        return out
    from scipy import ndimage

    from .recording import controls_to_end_effectors

    controls = rec.controls()
    cfgs, pos, _ = controls_to_end_effectors(controls)
    quat = controls.get("orientations")
    seen = []  # (end-effector, its observed points)
    for c, cam in enumerate(rec.cameras):
        masks = rec.controller_masks(c, t)
        if len(masks) != len(cfgs):
            out["why"] = f"camera {c} has {len(masks)} controller masks for {len(cfgs)} end-effectors"
            return out
        for k, m in enumerate(masks):
            p = cam.backproject(rec.depth(c, t), ndimage.binary_erosion(m, iterations=1))
            if len(p):
                seen.append((k, p))
    g = np.zeros(3)
    h = 1e-4
    r = np.zeros(0)
    rms = []
    for it in range(11):
        J, r = [], []
        for k, p in seen:
            q = None if quat is None else quat[t, k]
            x = p + g
            d = end_effector_sdf(x, cfgs[k], pos[t, k], q)
            ok = np.abs(d) < _reach(it, band_m)
            J.append(np.stack([(end_effector_sdf(x[ok] + h * e, cfgs[k], pos[t, k], q)
                                - end_effector_sdf(x[ok] - h * e, cfgs[k], pos[t, k], q)) / (2 * h)
                               for e in np.eye(3)], 1))
            r.append(d[ok])
        J, r = (np.concatenate(J), np.concatenate(r)) if J else (np.zeros((0, 3)), np.zeros(0))
        if len(r) < min_points:
            out.update(points=int(len(r)), why=f"{len(r)} observed end-effector points near the modelled shapes, "
                                                 f"fewer than {min_points}")
            return out
        rms.append(float(np.sqrt(np.mean(r ** 2))))
        if it == 10:
            break
        w = np.minimum(1.0, 3e-3 / np.maximum(np.abs(r), 1e-12))
        A = (J * w[:, None]).T @ J
        g = g - np.linalg.solve(A + 1e-3 * np.trace(A) / 3.0 * np.eye(3), (J * w[:, None]).T @ r)
    free = _unmeasured(J, A)
    for u in free:
        g = g - (g @ u) * u
    out.update(offset_m=[float(v) for v in g], offset_norm_m=float(np.linalg.norm(g)), rms_before_m=rms[0],
               rms_after_m=rms[-1], points=int(len(r)), unmeasured_directions=[[float(v) for v in u] for u in free])
    if rms[-1] > END_EFFECTOR_FIT_M:
        out["why"] = (f"the observed end-effectors lie {1e3 * rms[-1]:.1f} mm (RMS) from the shapes the controls "
                      f"give, over {1e3 * END_EFFECTOR_FIT_M:.1f} mm: their shapes are not what the controls model")
    else:
        out["trusted"] = True
    return out


def surface_consistency(rec: Recording, t: int = 0, *, radius_m: float = 0.12, voxel_m: float = 0.002,
                        max_pair_m: float = 0.01, within_m: float = 2e-3) -> float:
    """Share of the cameras' frame-``t`` points (:func:`camera_agreement`'s, all cameras) that lie within ``within_m``
    of another camera's surface, on its same side (:func:`_surface_pairs`): 0-1, higher where the cameras agree.
    What :func:`refine_calibration` must raise to keep a correction."""
    from scipy.spatial import cKDTree

    got = _camera_clouds(rec, t, radius_m, voxel_m) if rec.num_cameras >= 2 else None
    if got is None:
        return 0.0
    clouds, facing = got
    close = total = 0
    for c in range(len(clouds)):
        others = [k for k in range(len(clouds)) if k != c and len(clouds[k])]
        if not others or not len(clouds[c]):
            continue
        dst = np.concatenate([clouds[k] for k in others])
        _, _, _, r = _surface_pairs(clouds[c], facing[c], dst, np.concatenate([facing[k] for k in others]),
                                    cKDTree(dst), max_pair_m)
        close += int(np.sum(np.abs(r) < within_m))
        total += len(clouds[c])
    return close / max(total, 1)


def refine_calibration(rec: Recording, t: int = 0, *, tolerance_m: Optional[float] = None) -> dict:
    """Correct, in memory, the camera positions of a recording whose cameras disagree with each other
    (:func:`camera_agreement` beyond ``tolerance_m``; corrected by :func:`camera_shifts`) or, as a rig, with the
    controls (:func:`end_effector_agreement` beyond ``tolerance_m`` and trusted; every camera moved by its shift).
    The recording's files are not touched. Returns ``applied`` (whether ``rec.c2w`` was changed), ``shifts_m``
    [C][3] (the cameras' relative shifts), ``rig_shift_m`` (the whole rig's, or None), ``before`` / ``after`` (the
    cameras' agreement), ``end_effectors`` / ``end_effectors_after`` (the rig's against the controls) and ``note``:
    None, or what was done and what is left. A calibrated rig is left as it is (so its results stay bit-for-bit
    those without this step). ``tolerance_m``: default :func:`calibration_tolerance`."""
    tolerance_m = calibration_tolerance(rec, t) if tolerance_m is None else float(tolerance_m)
    before = camera_agreement(rec, t, tolerance_m=tolerance_m)
    out = {"applied": False, "shifts_m": [[0.0, 0.0, 0.0]] * rec.num_cameras, "rig_shift_m": None, "before": before,
           "after": None, "end_effectors": None, "end_effectors_after": None, "note": None}
    said = []
    c2w = np.array(rec.c2w, np.float64)
    if before["note"] is not None:
        S = camera_shifts(rec, t)
        recorded = rec.c2w
        agree0 = surface_consistency(rec, t)
        c2w[:, :3, 3] += S
        rec.c2w = c2w.copy()
        agree1 = surface_consistency(rec, t)
        if agree1 <= agree0:  # the shifts do not bring the cameras' points together: keep the recorded poses
            rec.c2w = recorded
            c2w = np.array(recorded, np.float64)
            out["consistency"] = [agree0, agree1]
            said.append(f"the cameras disagree at frame {t} by up to {1e3 * before['largest_offset_m']:.1f} mm, and "
                        f"no shift of theirs brings their points together ({100 * agree0:.0f} % of them on the "
                        f"others' surface, {100 * agree1:.0f} % shifted): not corrected")
        else:
            after = camera_agreement(rec, t, tolerance_m=tolerance_m)
            out.update(applied=True, shifts_m=[[float(v) for v in s] for s in S], after=after,
                       consistency=[agree0, agree1])
            moved = ", ".join(f"camera {c} by {1e3 * np.linalg.norm(s):.1f} mm" for c, s in enumerate(S))
            left = (f"they now agree within {1e3 * after['largest_offset_m']:.1f} mm" if after["note"] is None else
                    f"they still disagree by up to {1e3 * after['largest_offset_m']:.1f} mm (a rotation or a depth "
                    f"scale a shift cannot take up)")
            said.append(f"the cameras disagreed at frame {t} by up to {1e3 * before['largest_offset_m']:.1f} mm: "
                        f"their positions were shifted onto one surface ({moved}; {100 * agree0:.0f} -> "
                        f"{100 * agree1:.0f} % of their points on the others' surface); {left}")
    ee = end_effector_agreement(rec, t)
    out["end_effectors"] = ee
    if ee["offset_norm_m"] is not None and ee["offset_norm_m"] > tolerance_m:
        off = f"{1e3 * ee['offset_norm_m']:.1f} mm"
        if ee["trusted"] and ee["rms_after_m"] < ee["rms_before_m"]:
            c2w[:, :3, 3] += np.asarray(ee["offset_m"])
            rec.c2w = c2w.copy()
            out.update(applied=True, rig_shift_m=ee["offset_m"], end_effectors_after=end_effector_agreement(rec, t))
            said.append(f"the end-effectors the cameras see lay {off} from where the controls put them (RMS "
                        f"{1e3 * ee['rms_before_m']:.1f} -> {1e3 * ee['rms_after_m']:.1f} mm once shifted): the "
                        f"whole rig was shifted by that")
        else:
            said.append(f"the end-effectors the cameras see lie {off} from where the controls put them, not "
                        f"corrected: {ee['why'] or 'the shift does not bring them closer to their shapes'}")
    if said:
        out["note"] = ("; ".join(said) + ". Corrected in memory only (the recording's files are unchanged) and before "
                       "anything was fused: check the extrinsics (c2w), the depth scale and the controls' frame")
    return out


def estimate_table_plane(rec: Recording, t: int = 0, *, voxel_m: float = 0.005, distance_threshold_m: float = 0.004,
                         max_depth_m: float = 2.0, seed: int = 0) -> Tuple[np.ndarray, float]:
    """Table plane ``(normal, offset)`` of a recording by RANSAC on the background pixels of frame ``t``.

    Background means outside the object and controller masks (all pixels when there are no masks).
    The normal is oriented towards the cameras. RANSAC searches the points averaged per ``voxel_m`` voxel; the
    plane is then fitted by least squares to every background point within ``distance_threshold_m`` of it. A fit
    to the voxel averages alone is biased: a voxel that the table's noisy points barely reach weighs as much as
    one they fill, and with 5-mm voxels the table came out 0.8-0.9 mm low on a synthetic recording (0.008 mm with
    2-mm voxels, benchmarks/RESULTS.md, session 56).
    """
    from scipy import ndimage

    pts = []
    for c, cam in enumerate(rec.cameras):
        fg = np.zeros((rec.height, rec.width), bool)
        if rec.has_masks:
            fg |= rec.mask(c, t)
            cm = rec.controller_mask(c, t)
            if cm is not None:
                fg |= cm
            fg = ndimage.binary_dilation(fg, iterations=3)
        pts.append(cam.backproject(rec.depth(c, t), ~fg, max_depth_m=max_depth_m))
    full = np.concatenate(pts)
    pts = voxel_downsample(full, voxel_m)
    if len(pts) < 100:
        raise RecordingError(f"{rec.path}: too few background depth points ({len(pts)}) in frame {t} to find the "
                             f"table plane; pass table_plane explicitly")
    cam_centre = np.mean(rec.c2w[:, :3, 3], axis=0)
    n, d, _ = fit_table_plane(pts, distance_threshold_m=distance_threshold_m, seed=seed,
                              up_hint=cam_centre - pts.mean(0))
    mean = full.mean(0)
    n2, d2, inliers = _refine_plane(full - mean, n, float(d + n @ mean), float(distance_threshold_m))
    if len(inliers) >= 3:  # _refine_plane keeps the normal's side: still towards the cameras
        n, d = n2, float(d2 - n2 @ mean)
    return n, d


def close_against_table(points: np.ndarray, table_plane: Tuple[np.ndarray, float], spacing_m: float) -> np.ndarray:
    """Add, below every point, samples down to the table plane every ``spacing_m`` (m).

    A surface seen from above and the sides has no bottom; filling each column between the visible
    surface and the table makes it a closed solid (an upper bound of the unseen underside). Points
    under the table are dropped.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    h, n = table_heights(pts, table_plane)
    pts, h = pts[h >= 0], h[h >= 0]
    if len(pts) == 0:
        return pts
    steps = np.floor(h / spacing_m).astype(np.int64)
    rep = np.repeat(np.arange(len(pts)), steps + 1)
    k = np.arange(len(rep)) - np.repeat(np.cumsum(steps + 1) - (steps + 1), steps + 1)
    down = np.minimum(k * spacing_m, h[rep])
    extra = pts[rep] - down[:, None] * n
    # the projection onto the table of every point closes the bottom exactly at the plane
    foot = pts - h[:, None] * n
    return np.concatenate([pts, extra, foot], axis=0)


def smooth_points(points: np.ndarray, radius_m: float) -> np.ndarray:
    """Each point replaced by the mean of the points within ``radius_m`` (m): reduces depth noise normal
    to the surface by about the square root of the neighbour count."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if radius_m is None or radius_m <= 0 or len(pts) == 0:
        return pts.copy()
    tree = cKDTree(pts)
    pairs = tree.query_pairs(float(radius_m), output_type="ndarray")
    acc = pts.copy()
    cnt = np.ones(len(pts))
    if len(pairs):
        np.add.at(acc, pairs[:, 0], pts[pairs[:, 1]])
        np.add.at(acc, pairs[:, 1], pts[pairs[:, 0]])
        np.add.at(cnt, pairs[:, 0], 1)
        np.add.at(cnt, pairs[:, 1], 1)
    return acc / cnt[:, None]


def initial_particles(points: np.ndarray, *, dx: float, particles_per_cell: float = 8,
                      table_plane: Optional[Tuple[np.ndarray, float]] = None, voxel_m: Optional[float] = None,
                      smooth_radius_m: Optional[float] = None, seed: int = 0, jitter: float = 0.0,
                      fill_layers: bool = False, open_thin: bool = False,
                      align_lattice: bool = False) -> Tuple[np.ndarray, np.ndarray]:
    """Frame-0 simulation particles filling the object's interior (not only its visible surface).

    ``points`` [N, 3] (m) is the fused object surface. It is first smoothed over ``smooth_radius_m`` (m,
    default dx / 2; 0 disables), since depth noise would otherwise thicken the voxelised shell. With
    ``table_plane`` the surface is closed against the table (:func:`close_against_table`); then
    :func:`empm_gym.sim.sample_points` voxelises it at ``voxel_m`` (m, default dx / 4), fills enclosed
    cavities (with ``fill_layers`` also the holes of every horizontal layer: for a body completed around its
    sides from one view, :func:`complete_by_symmetry`; with ``open_thin`` sheets thinner than three voxels
    are removed) and samples ``particles_per_cell`` particles per grid cell of ``dx`` (m). Returns
    ``(positions [n, 3] m, volumes [n] m^3)``; with a table, no particle lies below it.

    ``align_lattice`` puts the lattice's outer rows half a step inside the body's bounding box (see
    :func:`empm_gym.sim.sample_points`); without it the lattice is laid over the padded voxel box and a thin
    body's outer rows fall most of a step inside its faces. Aligned, five 3-camera `empm synth` ropes (2.4
    cells thick) fit E -0.6 to -2.2 % instead of +1.9 to +8.2 % (benchmarks/RESULTS.md, session 24);
    :func:`empm_gym.identification.data.frame0_body` aligns every body it rebuilds (session 25: the doctor's
    false table friction on a dragged rope that had kept it for views from one side was the drag script's and
    the doctor's, not the lattice's).
    """
    from empm_gym.sim import sample_points

    pts = smooth_points(points, dx / 2.0 if smooth_radius_m is None else smooth_radius_m)
    h = voxel_m or dx / 4.0
    if table_plane is not None:
        pts = close_against_table(pts, table_plane, spacing_m=h / 2.0)
    x, vol = sample_points(pts, dx, particles_per_cell, voxel=h, fill_interior=True, fill_layers=fill_layers,
                           open_thin=open_thin, align_lattice=align_lattice, seed=seed, jitter=jitter)
    if table_plane is not None:
        keep = table_heights(x, table_plane)[0] >= 0.0
        x, vol = x[keep], vol[keep]
    return x, vol


def outside_surface(x: np.ndarray, points: np.ndarray, *, k: int = 12, reach: float = 2.0) -> np.ndarray:
    """Mask of the particles x [N, 3] (m) whose centres lie outside the surface sampled by ``points`` [M, 3] (m):
    the median, over the ``k`` nearest points, of the particle's offset along each point's outward normal is
    positive, and the nearest point lies within ``reach`` particle spacings (elsewhere, on surface no camera saw,
    nothing is decided).

    A body filled from a voxelised scan reaches to the outer envelope of the scan's depth noise, not to its
    middle: the voxels of the outermost noisy points are occupied, and the fill's outer rows follow them. On
    ``empm synth``'s dough (three cameras, 5 mm grid) some faces of the frame-0 body lay a whole lattice row (2.5 mm)
    beyond the observed points' mean surface. Each point stands for the plane fitted through its ``k`` nearest
    points (their centroid and smallest principal axis: the offset from the noisy point itself would be biased,
    as the points nearest to a particle are those whose noise moved them towards it), its normal turned away
    from the particles nearest to it; the median over ``k`` planes takes the rest of the noise out of the
    decision (a correct outer row lies half a spacing inside, an extra one half a spacing outside). Inward is
    towards the centroid of the ``8 k`` particles nearest to a point: an extra row straddles the surface with the
    body's outer row, but the rows inside outnumber it."""
    from scipy.spatial import cKDTree

    x = np.asarray(x, np.float64).reshape(-1, 3)
    P = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(x), bool)
    if len(x) < 2 or len(P) < 3:
        return out
    k = int(min(k, len(P)))
    tp = cKDTree(P)
    _, nb = tp.query(P, k=k)
    Q = P[nb] - P[nb].mean(1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q))[1][:, :, 0]  # smallest spread: the normal
    # each point's plane passes through the centroid of the neighbours on the same face (normals within 25 deg):
    # one taken over an edge would lie inside it and make the body's edge rows look outside
    same = np.abs(np.einsum("ni,nki->nk", normals, normals[nb])) > 0.9
    C = (P[nb] * same[..., None]).sum(1) / same.sum(1)[:, None]
    tx = cKDTree(x)
    _, near_x = tx.query(P, k=int(min(8 * k, len(x))))
    inward = x[near_x].reshape(len(P), -1, 3).mean(1) - P
    normals = np.where((np.einsum("ni,ni->n", normals, inward) > 0)[:, None], -normals, normals)
    s = float(np.median(tx.query(x, k=2)[0][:, 1]))
    d, idx = tp.query(x, k=k)
    offset = np.median(np.einsum("nki,nki->nk", x[:, None, :] - C[idx], normals[idx]), axis=1)
    return (d[:, 0] <= reach * s) & (offset > 0.0)


def carve_with_depth(x: np.ndarray, vol: np.ndarray, rec: Recording, t: int = 0, *,
                     tol_m: float = 0.004) -> Tuple[np.ndarray, np.ndarray]:
    """Remove particles that some camera sees through (visual-hull carving with depth).

    A particle at depth z along a camera's pixel is free space when that pixel's measured depth lies
    beyond z + ``tol_m`` (m): the camera saw something behind it (typically the table under an
    overhang that a column fill to the table had filled). Pixels without depth, outside the image, or
    in front of the particle keep it. Volumes of the kept particles are unchanged.
    """
    x = np.asarray(x, float)
    keep, _ = _carve(x, rec, t, tol_m)
    if not keep.any():
        raise RecordingError(f"{rec.path}: depth carving removed every particle of frame {t}; check the calibration")
    return x[keep], np.asarray(vol)[keep]


def controls_from_masks(rec: Recording, *, radius_m: float = 0.02, erode_px: int = 1,
                        nb_neighbors: int = 20, std_ratio: float = 2.0, sphere_centre: bool = True) -> dict:
    """End-effector controls estimated from the controller ("hand") masks, as sphere end-effectors.

    K (the number of end-effectors) is the largest number of controller ids of any camera. Per frame,
    the hand pixels of all cameras are back-projected and fused, outliers removed, and split into K
    clusters (nearest previous centre; farthest-point start at the first frame with hands, numbered in
    order of increasing x there); each cluster's centroid is an end-effector position. Frames without hand pixels hold the nearest known position.
    grip is 1 where the hand was seen, else 0. With ``sphere_centre`` every hand point is first moved
    2/3 ``radius_m`` (m) along its camera ray, so that a sphere of that radius gets its centre (not
    the centroid of its visible cap, which lies towards the cameras).
    """
    if not rec.has_controller_masks:
        raise RecordingError(f"{rec.path}: neither controls.npz nor controller masks (mask_info_<cam>.json with a "
                             f"'hand' label) to derive end-effector controls from")
    K = max(len(ctl) for _, ctl in rec._mask_ids)
    T = rec.num_frames
    cams = rec.cameras
    pos = np.full((T, K, 3), np.nan)
    prev = None
    from scipy import ndimage

    for t in range(T):
        pts, rays = [], []
        for c in range(rec.num_cameras):
            m = rec.controller_mask(c, t)
            if m is None or not m.any():
                continue
            if erode_px > 0:
                m = ndimage.binary_erosion(m, iterations=int(erode_px))
            p = cams[c].backproject(rec.depth(c, t), m, min_depth_m=0.1)
            r = p - cams[c].position
            pts.append(p)
            rays.append(r / (np.linalg.norm(r, axis=1, keepdims=True) + 1e-12))
        pts = np.concatenate(pts) if pts else np.zeros((0, 3))
        rays = np.concatenate(rays) if rays else np.zeros((0, 3))
        if len(pts) > nb_neighbors:
            pts, keep = remove_statistical_outliers(pts, nb_neighbors, std_ratio)
            rays = rays[keep]
        if sphere_centre:
            # a visible spherical cap seen uniformly in image area has its centroid 2/3 r towards the camera
            pts = pts + (2.0 / 3.0) * float(radius_m) * rays
        if len(pts) < max(K, 3):
            continue
        if prev is None:  # farthest-point initialisation, then ordered by x, y
            centres = [pts.mean(0)]
            for _ in range(1, K):
                dist = np.min(np.linalg.norm(pts[:, None] - np.array(centres)[None], axis=2), axis=1)
                centres.append(pts[np.argmax(dist)])
            centres = np.array(centres)
            centres = centres[np.lexsort((centres[:, 1], centres[:, 0]))]
        else:
            centres = prev.copy()
        for _ in range(5):
            lab = np.argmin(np.linalg.norm(pts[:, None] - centres[None], axis=2), axis=1)
            for k in range(K):
                if np.any(lab == k):
                    centres[k] = pts[lab == k].mean(0)
        pos[t] = centres
        prev = centres
    seen = np.all(np.isfinite(pos[:, :, 0]), axis=1)
    if not np.any(seen):
        raise RecordingError(f"{rec.path}: the controller masks are empty in every frame")
    idx = np.arange(T)
    known = idx[seen]
    nearest = known[np.argmin(np.abs(idx[:, None] - known[None]), axis=1)]
    pos = pos[nearest]
    grip = np.repeat(seen[:, None], K, axis=1).astype(np.int32)
    return validate_controls({"positions": pos, "grip": grip, "shape": np.array(["sphere"] * K),
                              "radius": np.full(K, float(radius_m))}, T, f"{rec.path} (controller masks)")


def load_controls(rec: Recording, **kw) -> dict:
    """The recording's controls: ``controls.npz`` when present, else :func:`controls_from_masks` (keywords)."""
    return rec.controls() if rec.has_controls else controls_from_masks(rec, **kw)


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def end_effector_sdf(points: np.ndarray, cfg, centre, quat=None) -> np.ndarray:
    """Signed distance (m, negative inside) of world points [N, 3] to an end-effector (sphere, capsule
    along its local z, or box) of config ``cfg`` at ``centre`` (m) with orientation ``quat`` (x, y, z, w)."""
    R = np.eye(3) if quat is None else _quat_matrix(quat)
    p = (np.asarray(points, float) - np.asarray(centre, float)) @ R  # local frame
    if cfg.shape == "sphere":
        return np.linalg.norm(p, axis=1) - cfg.radius
    if cfg.shape == "capsule":
        q = p.copy()
        q[:, 2] = np.clip(q[:, 2], -cfg.half_height, cfg.half_height)
        return np.linalg.norm(p - q, axis=1) - cfg.radius
    he = np.asarray(cfg.half_extents, float)
    d = np.abs(p) - he
    return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(1), 0.0)


def complete_occluded(points: np.ndarray, rec: Recording, t: int, ee_configs, ee_positions, *,
                      grip=None, ee_orientations=None, table_plane: Tuple[np.ndarray, float],
                      spacing_m: float = 0.0025, margin_m: float = 0.01, reach_m: float = 0.02,
                      end_effectors_only: bool = False, connected: bool = True,
                      clamp_reach: float = 1.0) -> np.ndarray:
    """Solid samples [M, 3] (m) of the object's parts that the end-effectors hide from every camera.

    A gripper or pusher in front of the object hides the part it holds or touches, so a fill of the
    visible surface alone stops short of it (a rope's ends under two grippers; a block's faces behind
    two plates). Around each end-effector at frame ``t`` (its bounding box grown by ``margin_m``, from
    the table up to the 95th percentile height of the visible object within ``reach_m`` of that box),
    lattice points every ``spacing_m`` (m) are kept when every camera that measures depth there saw a
    surface in front of them (the end-effector or the object: hidden), they lie outside the end-effector unless it is closed
    (a closed gripper carries the material inside it) and they connect to the visible object. With
    ``grip`` [K] (1 = closed) and ``ee_orientations`` [K, 4] (x, y, z, w) for the same frame.
    With ``end_effectors_only`` a point must moreover be hidden by an end-effector from at least one camera
    (:func:`hidden_by_end_effectors`), not by the object itself from all: for views from one side, whose
    object-hidden far side is left to :func:`complete_by_symmetry`. (From one camera: hidden by an
    end-effector. From two on opposite sides of a body between two plates, each plate hides the face behind
    it from the camera on its side while the body hides that face from the other: with "every camera" both
    faces were left out, and the body came out 17 % small.) ``connected=False`` keeps the hidden points that do not
    connect to the visible object too. ``clamp_reach`` is how far into a closed box gripper the object is taken to
    reach, as a share of the way from its entry face to its middle (:func:`_within_entry_half`).
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    if not 0.0 < clamp_reach <= 1.0:
        raise ValueError(f"clamp_reach must lie in (0, 1] (a share of the way from a gripper's entry face to its "
                         f"middle), got {clamp_reach!r}")
    pts = np.asarray(points, float).reshape(-1, 3)
    n = np.asarray(table_plane[0], float)
    n = n / np.linalg.norm(n)
    off = float(table_plane[1])
    if len(pts) == 0 or len(ee_configs) == 0:
        return np.zeros((0, 3))
    pos = np.asarray(ee_positions, float).reshape(-1, 3)
    grip = np.zeros(len(ee_configs), int) if grip is None else np.asarray(grip).reshape(-1)
    tree = cKDTree(pts)
    out = []
    for k, cfg in enumerate(ee_configs):
        q = None if ee_orientations is None else np.asarray(ee_orientations).reshape(-1, 4)[k]
        R = np.eye(3) if q is None else _quat_matrix(q)
        if cfg.shape == "box":
            half = np.abs(R) @ np.asarray(cfg.half_extents, float)
        elif cfg.shape == "capsule":
            half = np.abs(R[:, 2]) * cfg.half_height + cfg.radius
        else:
            half = np.full(3, cfg.radius)
        lo, hi = pos[k] - half - margin_m, pos[k] + half + margin_m
        near = pts[np.all((pts[:, :2] >= lo[:2] - reach_m) & (pts[:, :2] <= hi[:2] + reach_m), axis=1)]
        if len(near) < 10:
            continue  # the end-effector is not at the object
        cap = float(np.percentile(near @ n + off, 95))
        axes = [np.arange(lo[i] + 0.5 * spacing_m, hi[i], spacing_m) for i in range(2)]
        # heights above the table from half a spacing up to the cap (the table plane is horizontal here)
        zs = np.arange(0.5 * spacing_m, cap, spacing_m)
        if len(zs) == 0 or any(len(a) == 0 for a in axes):
            continue
        G = np.stack(np.meshgrid(axes[0], axes[1], np.arange(len(zs)), indexing="ij"), -1).reshape(-1, 3)
        cand = np.column_stack([G[:, 0], G[:, 1], np.zeros(len(G))])
        # lift each column point to height zs above the plane (z solved on the plane n . x + off = h)
        h = zs[G[:, 2].astype(int)]
        cand[:, 2] = (h - off - cand[:, :2] @ n[:2]) / n[2]
        ok = np.ones(len(cand), bool)
        if not grip[k]:
            ok &= end_effector_sdf(cand, cfg, pos[k], q) > 0.0
        cand = cand[ok]
        if len(cand) == 0:
            continue
        cand = cand[_hidden(cand, rec, t, front_m=0.5 * spacing_m)]
        if grip[k] and cfg.shape == "box" and len(cand):
            cand = cand[_within_entry_half(cand, pts, pos[k], R, np.asarray(cfg.half_extents, float), spacing_m,
                                           reach_m, clamp_reach)]
        if end_effectors_only and len(cand):
            cand = cand[hidden_by_end_effectors(cand, rec.cameras, ee_configs, pos, ee_orientations)]
        if len(cand) == 0:
            continue
        if not connected:
            out.append(cand)
            continue
        # keep the components of the kept lattice that touch the visible object
        idx = np.rint((cand - cand.min(0)) / spacing_m).astype(int)
        occ = np.zeros(idx.max(0) + 1, bool)
        occ[tuple(idx.T)] = True
        lab, nl = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
        lab_pts = lab[tuple(idx.T)]
        touching = np.unique(lab_pts[tree.query(cand)[0] <= 1.5 * spacing_m])
        out.append(cand[np.isin(lab_pts, touching[touching > 0])])
    return np.concatenate(out) if out else np.zeros((0, 3))


def _within_entry_half(cand: np.ndarray, pts: np.ndarray, centre: np.ndarray, R: np.ndarray, hx: np.ndarray,
                       spacing_m: float, reach_m: float, clamp_reach: float = 1.0) -> np.ndarray:
    """Mask of the hidden candidates [M, 3] that a closed box gripper (centre, rotation R, half extents ``hx`` in
    its own frame) is taken to hold: those on the body's side of its centre plane across the horizontal box axis along
    which the visible body ``pts`` enters it, and within the visible body's width across that axis (half a
    spacing around the visible points next to the box).

    The cameras see the gripper's walls, not what they enclose, so how far the body reaches inside is not in the
    data. The prior: a gripper holds what lies between its entry face and its middle, at the width the body
    has where it enters (a box grown around an object's end would otherwise be filled to its far walls: a
    dough held at both ends was 55 % phantom material before this). A body whose top falls towards the gripper
    (:func:`entry_taper`) is rounded there: its top, and each side that narrows, go on narrowing inside at the rate
    they do outside. ``clamp_reach`` < 1 takes the body to end that share of the way from the entry face to the
    middle instead (the body trimmed to the measured surface, which errs small, takes half:
    :data:`CLAMP_REACH_TRIMMED`). Where no visible point lies next to the box, every candidate is kept."""
    rel = pts - centre
    loc = rel @ R                                  # visible points in the box's frame
    outside = np.any(np.abs(loc) > hx + 0.5 * spacing_m, axis=1)
    nearby = outside & np.all(np.abs(loc) <= hx + reach_m, axis=1)
    if nearby.sum() < 10:
        return np.ones(len(cand), bool)
    d = loc[nearby].mean(0)
    d[2] = 0.0                                     # the entry is through a side wall (horizontal axis)
    ax = int(np.argmax(np.abs(d) / np.maximum(hx, 1e-9)))
    if ax == 2 or abs(d[ax]) < 1e-9:
        return np.ones(len(cand), bool)
    sign = np.sign(d[ax])
    lc = (cand - centre) @ R
    # on the body's side of the centre plane (or of the plane clamp_reach of the way in from the entry face)
    keep = sign * lc[:, ax] >= (1.0 - clamp_reach) * hx[ax] - 0.5 * spacing_m
    across = 1 - ax                                # the other horizontal axis of the box
    entering = loc[nearby & (sign * loc[:, ax] > hx[ax])]
    if len(entering) >= 10:
        lo, hi = entering[:, across].min(), entering[:, across].max()
        keep &= (lc[:, across] >= lo - 0.5 * spacing_m) & (lc[:, across] <= hi + 0.5 * spacing_m)
        # a body whose top falls towards the gripper (a rounded lump's end) is taken to go on falling inside it,
        # and its sides to go on narrowing where they narrow; a body whose top does not (a box's end, one side of
        # it seeming to narrow where the gripper hides it from a camera) is continued at its entering cross-section
        depth = np.maximum(hx[ax] - sign * lc[:, ax], 0.0)  # from the entry face inwards
        u = sign * entering[:, ax] - hx[ax]                 # the visible points' distance outside the face
        top = entry_taper(u, entering[:, 2], reach_m)
        if top is not None:
            sides = [(s * lc[:, across], entry_taper(u, s * entering[:, across], reach_m)) for s in (1.0, -1.0)]
            for coord, taper in [(lc[:, 2], top)] + sides:
                if taper is not None:
                    keep &= coord <= taper[0] + taper[1] * depth + 0.5 * spacing_m
    return keep


#: How far into a closed box gripper the body trimmed to the measured surface is taken to reach, as a share of the
#: way from the entry face to the middle (:func:`_within_entry_half`; the doctor's own body reaches the middle). No
#: camera sees where a body ends inside a gripper that encloses it; the doctor's body takes the middle, the trimmed
#: body, which errs small elsewhere too, half of that, so that a named effect must hold on both sides of the prior
#: (``empm synth``'s dough between two clamps ends 6.2 mm short of their middles: 151.4 cm^3 rebuilt from four
#: cameras, 112.5 true; benchmarks/RESULTS.md, session 79).
CLAMP_REACH_TRIMMED = 0.5


#: Least fall of a body's visible top or side over the band it is measured on (m, next to a closed gripper's entry
#: face) that :func:`entry_taper` continues into the gripper, and the most its slices may scatter about their line
#: (RMS, m): a box's or a rope's top, flat within its depth noise (within 0.5 mm over the band on ``empm synth``'s
#: dough and block), is continued at its entering height; a side whose extent is where the cameras' view of it ends
#: (the grippers hide the sides behind them: one side of ``empm synth``'s block jumped by 7 mm between slices)
#: scatters and is not continued.
MIN_TAPER_M = 0.003
MAX_TAPER_SCATTER_M = 0.001


def entry_taper(u: np.ndarray, q: np.ndarray, reach_m: float, *, bins: int = 4, min_taper_m: float = MIN_TAPER_M,
                max_scatter_m: float = MAX_TAPER_SCATTER_M):
    """How a body's outer extent along one direction falls as it enters a closed gripper, from its visible points
    next to the entry face: ``u`` (m) their distance outside the face (0 .. ``reach_m``) and ``q`` (m) their
    coordinate along the direction (height for the top; across the face, or its negative, for a side). Returns
    ``(q0, dq)``: the extent continued linearly from the face into the gripper (``q0 + dq * d`` at depth d past
    the face, ``dq`` < 0), or None where it falls towards the face by less than ``min_taper_m`` over the band, or
    its slices scatter about their line by more than ``max_scatter_m`` (continued as before: at the entering
    extent). Where the slice next to the face lies short of the line through the slices beyond it by more than that
    scatter (the gripper hides part of it from the cameras: a four-camera lump's sides), the line is read from the
    slices beyond it.

    The band is cut into ``bins`` slices by distance from the face; each slice's extent is the 95th percentile of
    its ``q`` (robust to the depth noise and to a few stray points) and a least-squares line through them gives the
    trend. A rounded lump enters its grippers tapering (its true part inside each gripper 11 cm^3, the entering
    cross-section carried to the gripper's middle 37: benchmarks/RESULTS.md, session 77); the line is a prior that
    stops short of a rounded end's faster fall."""
    u = np.asarray(u, float)
    q = np.asarray(q, float)
    edges = np.linspace(0.0, float(reach_m), bins + 1)
    mid, ext = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (u > a) & (u <= b)
        if sel.sum() >= 5:
            mid.append(0.5 * (a + b))
            ext.append(np.percentile(q[sel], 95))
    if len(mid) < 3:
        return None
    mid, ext = np.asarray(mid), np.asarray(ext)
    line = _straight_fall(mid, ext, float(reach_m), min_taper_m, max_scatter_m)
    if line is None and len(mid) > 3:
        # the slice next to the face may lie short of the others because the gripper hides part of it from the
        # cameras: the line through the slices beyond it, where that slice lies below it by more than the scatter
        slope, q0 = np.polyfit(mid[1:], ext[1:], 1)
        if ext[0] < q0 + slope * mid[0] - max_scatter_m:
            line = _straight_fall(mid[1:], ext[1:], float(reach_m), min_taper_m, max_scatter_m)
    return line


def _straight_fall(mid: np.ndarray, ext: np.ndarray, reach_m: float, min_taper_m: float, max_scatter_m: float):
    """:func:`entry_taper`'s line ``(q0, dq)`` through slices at distances ``mid`` (m) with extents ``ext`` (m), or
    None where it falls by less than ``min_taper_m`` over ``reach_m`` or the slices scatter about it by more than
    ``max_scatter_m`` (RMS)."""
    slope, q0 = np.polyfit(mid, ext, 1)
    scatter = float(np.sqrt(np.mean((ext - (q0 + slope * mid)) ** 2)))
    if slope * reach_m < min_taper_m or scatter > max_scatter_m:
        return None
    return float(q0), -float(slope)


def view_gap_deg(cameras: Sequence[Camera], centre, up: Sequence[float] = (0.0, 0.0, 1.0)) -> float:
    """The widest range of azimuths (degrees) about the vertical line through ``centre`` (m) that holds no camera.

    Each camera is placed by the direction from ``centre`` to its optical centre, projected on the plane
    normal to ``up`` (the table normal); cameras within 1 mm of the vertical line (straight above) have no
    azimuth and are skipped. One camera gives 360 and three spaced evenly around the object 120; above
    180 every camera lies on one side of a vertical plane through the object, and the far side of the
    object is seen by none (:func:`complete_by_symmetry` then completes it).
    """
    u = np.asarray(up, float)
    u = u / np.linalg.norm(u)
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    az = []
    for cam in cameras:
        d = cam.position - np.asarray(centre, float)
        a, b = d @ e1, d @ e2
        if np.hypot(a, b) > 1e-3:
            az.append(np.degrees(np.arctan2(b, a)) % 360.0)
    if len(az) < 2:
        return 360.0
    az = np.sort(az)
    return float(np.max(np.diff(np.concatenate([az, az[:1] + 360.0]))))


def _ee_frames(ee_configs, ee_positions, ee_orientations):
    pos = np.asarray(ee_positions, float).reshape(-1, 3)
    quats = [None] * len(ee_configs) if ee_orientations is None else list(np.asarray(ee_orientations).reshape(-1, 4))
    return pos, quats


def _bounding_radius(cfg) -> float:
    if cfg.shape == "sphere":
        return float(cfg.radius)
    if cfg.shape == "capsule":
        return float(cfg.half_height + cfg.radius)
    return float(np.linalg.norm(np.asarray(cfg.half_extents, float)))


def inside_end_effectors(x: np.ndarray, ee_configs, ee_positions, ee_orientations=None, *,
                         select=None) -> np.ndarray:
    """True for world points [N, 3] (m) inside one of the end-effectors (all, or those where the bool [K]
    ``select`` is True) at ``ee_positions`` [K, 3] (m) with orientations [K, 4] (x, y, z, w)."""
    x = np.asarray(x, float).reshape(-1, 3)
    out = np.zeros(len(x), bool)
    if len(ee_configs) == 0:
        return out
    pos, quats = _ee_frames(ee_configs, ee_positions, ee_orientations)
    select = np.ones(len(ee_configs), bool) if select is None else np.asarray(select, bool).reshape(-1)
    for k, cfg in enumerate(ee_configs):
        if select[k]:
            out |= end_effector_sdf(x, cfg, pos[k], quats[k]) < 0.0
    return out


def inside_open_end_effectors(x: np.ndarray, ee_configs, ee_positions, grip=None, ee_orientations=None) -> np.ndarray:
    """True for world points [N, 3] (m) inside an open end-effector (grip 0: a pusher, an open gripper), where
    no material can be; a closed gripper (grip 1) carries the material inside it, so its inside is allowed."""
    grip = np.zeros(len(ee_configs), int) if grip is None else np.asarray(grip).reshape(-1)
    return inside_end_effectors(x, ee_configs, ee_positions, ee_orientations, select=grip == 0)


def hidden_by_end_effectors(x: np.ndarray, cameras: Sequence[Camera], ee_configs, ee_positions,
                            ee_orientations=None, *, samples: int = 24) -> np.ndarray:
    """True for world points [N, 3] (m) that an end-effector hides from at least one camera whose image they
    fall in: the segment from the point to that camera's optical centre passes through an end-effector (tested
    at ``samples`` points along the part of the segment within the end-effector's bounding sphere). Points
    that no camera images are False."""
    x = np.asarray(x, float).reshape(-1, 3)
    if len(ee_configs) == 0 or len(x) == 0:
        return np.zeros(len(x), bool)
    pos, quats = _ee_frames(ee_configs, ee_positions, ee_orientations)
    out = np.zeros(len(x), bool)
    s = (np.arange(samples) + 0.5) / samples
    for cam in cameras:
        rc, z = cam.project(x)
        inside = (z > 0) & (rc[:, 0] >= -0.5) & (rc[:, 0] < cam.height - 0.5) & (rc[:, 1] >= -0.5) & \
            (rc[:, 1] < cam.width - 0.5)
        seg = cam.position - x
        length = np.linalg.norm(seg, axis=1)
        u = seg / np.maximum(length, 1e-12)[:, None]
        hid = np.zeros(len(x), bool)
        for k, cfg in enumerate(ee_configs):
            rb = _bounding_radius(cfg)
            tc = np.clip(np.einsum("ij,ij->i", pos[k] - x, u), 0.0, length)
            dist = np.linalg.norm(x + tc[:, None] * u - pos[k], axis=1)
            near = np.nonzero(dist < rb)[0]
            if len(near) == 0:
                continue
            half = np.sqrt(rb**2 - dist[near] ** 2)
            t0 = np.maximum(tc[near] - half, 0.0)
            t1 = np.minimum(tc[near] + half, length[near])
            t = t0[:, None] + (t1 - t0)[:, None] * s[None]                      # [n, samples]
            q = x[near, None, :] + t[..., None] * u[near, None, :]
            sd = end_effector_sdf(q.reshape(-1, 3), cfg, pos[k], quats[k]).reshape(len(near), samples)
            hid[near] |= (sd < 0.0).any(1)
        out |= hid & inside
    return out


def within_footprint(x: np.ndarray, points: np.ndarray, cell_m: float, margin_m: float) -> np.ndarray:
    """True for points [N, 3] (m) whose horizontal position lies within ``margin_m`` (m) of the footprint of
    ``points`` [M, 3] (m): the cells of ``cell_m`` (m) in x, y that hold a point, holes filled."""
    from scipy import ndimage

    x = np.asarray(x, float).reshape(-1, 3)
    p = np.asarray(points, float).reshape(-1, 3)
    if len(p) == 0 or len(x) == 0:
        return np.zeros(len(x), bool)
    pad = int(np.ceil(margin_m / cell_m)) + 2
    lo = p[:, :2].min(0) - pad * cell_m
    ij = np.floor((p[:, :2] - lo) / cell_m).astype(int)
    grid = np.zeros(ij.max(0) + pad + 1, bool)
    grid[ij[:, 0], ij[:, 1]] = True
    grid = ndimage.binary_fill_holes(ndimage.binary_closing(grid, iterations=1))
    near = ndimage.distance_transform_edt(~grid) * cell_m <= margin_m
    q = np.floor((x[:, :2] - lo) / cell_m).astype(int)
    ok = np.all((q >= 0) & (q < grid.shape), axis=1)
    out = np.zeros(len(x), bool)
    out[ok] = near[q[ok, 0], q[ok, 1]]
    return out


class _DepthViews:
    """Depth images (and silhouettes) of one frame of every camera, for repeated free-space tests of many points.

    With masks, the silhouette of a camera is its object and controller masks grown by the pixels that
    ``tol_m`` spans at the object's depth, and a missing depth is unknown; without masks, a missing depth
    takes the largest valid depth within 2 pixels (depth drops out mostly at silhouettes, where a nearer
    and a farther surface meet: assume the farther). Off the object's mask (grown by a pixel), what the
    camera saw is not the object: there a point must lie behind the measured surface, not within
    ``tol_m`` in front of it (material hugging an end-effector's face would have been seen).
    """

    def __init__(self, rec: Recording, t: int, tol_m: float):
        from scipy import ndimage

        self.cameras = rec.cameras
        self.tol_m = float(tol_m)
        self.depths, self.silhouettes, self.objects = [], [], []
        pix = []
        for c, cam in enumerate(self.cameras):
            depth = np.asarray(rec.depth(c, t), float)
            sil = obj = None
            if not rec.has_masks:
                depth = np.where(depth > 0, depth, ndimage.maximum_filter(depth, size=5))
            else:
                obj = rec.mask(c, t)
                sil = obj.copy()
                ctl = rec.controller_mask(c, t)
                if ctl is not None:
                    sil |= ctl
                z = depth[obj & (depth > 0)]
                if len(z):
                    pix.append(np.median(z) / cam.K[0, 0])
                px = 1 if len(z) == 0 else int(np.ceil(self.tol_m * cam.K[0, 0] / np.median(z)))
                sil = ndimage.binary_dilation(sil, iterations=max(px, 1))
                obj = ndimage.binary_dilation(obj, iterations=1)
            self.depths.append(depth)
            self.silhouettes.append(sil)
            self.objects.append(obj)
        #: the size (m) of a pixel at the object's depth (median over cameras; 2 mm without masks)
        self.pixel_m = float(np.median(pix)) if pix else 0.002

    def in_front(self, x: np.ndarray) -> np.ndarray:
        """How far (m) the points lie in front of what the cameras saw: the largest over cameras of measured
        depth minus the point's depth (0 where no camera measured a depth behind the point; ``tol_m`` more
        off the object's mask), and infinity where no camera images the point or it falls outside a
        silhouette (on the background)."""
        front = np.zeros(len(x))
        imaged = np.zeros(len(x), bool)
        for cam, depth, sil, obj in zip(self.cameras, self.depths, self.silhouettes, self.objects):
            rc, z = cam.project(x)
            r = np.rint(rc[:, 0]).astype(np.int64)
            col = np.rint(rc[:, 1]).astype(np.int64)
            ok = (z > 0) & (r >= 0) & (r < depth.shape[0]) & (col >= 0) & (col < depth.shape[1])
            imaged |= ok
            d = np.zeros(len(x))
            d[ok] = depth[r[ok], col[ok]]
            e = np.where(d > 0, d - z, 0.0)
            if obj is not None:
                other = np.zeros(len(x), bool)
                other[ok] = ~obj[r[ok], col[ok]]
                e[other & (d > 0)] += self.tol_m
            front = np.maximum(front, e)
            if sil is not None:
                off = np.zeros(len(x), bool)
                off[ok] = ~sil[r[ok], col[ok]]
                front[off] = np.inf
        front[~imaged] = np.inf
        return front

    def contradicted(self, x: np.ndarray) -> np.ndarray:
        """True where no camera images the point, or one sees through it: its measured depth lies more than
        ``tol_m`` beyond the point, or the point falls outside its silhouette (on the background)."""
        return self.in_front(x) > self.tol_m


def _half_turn(points: np.ndarray, axis) -> np.ndarray:
    """``points`` [N, 3] (m) turned half a turn (180 degrees) about the vertical line through ``axis`` (x, y in m)."""
    out = np.array(points, float).reshape(-1, 3)
    out[:, :2] = 2.0 * np.asarray(axis, float).reshape(2) - out[:, :2]
    return out


def complete_by_symmetry(points: np.ndarray, rec: Recording, t: int = 0, *, ee_configs=(), ee_positions=None,
                         grip=None, ee_orientations=None, axis: Optional[Sequence[float]] = None,
                         contact: Optional[np.ndarray] = None, tol_m: float = 0.004, cap_m: float = 0.01,
                         max_contradicted: float = 0.2, near_min: float = 0.01, smooth_m: float = 0.004,
                         max_points: int = 2000, seed: int = 0) -> Tuple[np.ndarray, dict]:
    """The far side of a body that the cameras see from one side only, by a stated symmetry prior.

    **Prior**: the body is unchanged when turned by half a turn (180 degrees) about a vertical axis (two-fold
    rotational symmetry): a box resting on a face, a cylinder or rope lying in any direction, an ellipsoid,
    a lump of two-fold symmetry. Its unseen far side is then its seen near side turned about that axis.
    No orientation is assumed: unlike a mirror plane, a half turn maps a rope lying at any angle onto
    itself. Measured against the fill of the visible surface down to the table alone (a ray-cast cylinder
    lying at 40 degrees to the view: 0.46 of its volume, completed 0.92; a box: 0.66, completed 0.79; the
    one-camera dough of ``empm synth``, whose pushers hide most of it: 0.83 with a blob behind a pusher,
    completed 1.03-1.08 with 96 % of it inside the true body).

    **Axis**: candidate axes on a grid over the visible footprint (grown by half its size) turn the visible
    ``points`` [N, 3] (m, world, object only; smoothed over ``smooth_m`` for the search). A turned point
    that lies in front of what a camera measured is penalised by (its distance in front / ``cap_m``)^2,
    capped at 1, which it gets as well where it falls outside a camera's silhouette (object and controller
    masks grown by ``tol_m``: a solid point there would have been seen), inside an open end-effector, or
    in no camera's image. The candidates within ``near_min`` of the least mean penalty (the connected set
    around the best) are what the views allow; the axis is their mean, then, along each principal
    direction of that set that spans at most three pixels at the object's depth, moved to the set's edge
    away from the cameras: the fused surface stops a pixel or two short of the silhouette, so the turned
    far edge falls short of the near edge and the views bound the axis sharply only on the far side
    (without the move, the axis of a ray-cast box lies 2.5 mm towards the camera). Longer directions are
    genuine ambiguity (a rope's length; a side hidden by an end-effector) and keep the middle.
    ``contact`` [M, 3] (m): material taken to touch open end-effectors (see
    :func:`empm_gym.identification.data.load_recording`); turned, it is penalised for entering an
    end-effector, which fixes the axis along directions that pushers hide. Coarse grid, then one four times
    finer. With ``axis`` (x, y in m) there is no search and no refutation test (used to turn further points
    about the axis found from the visible ones).

    Returns ``(turned points [M, 3] that are not contradicted, info)``; a turned point is contradicted
    where it lies more than ``tol_m`` (m) in front of a measured surface or is penalised in full. ``info``:
    ``axis_m`` (x, y), ``axis_spread_m`` (the extent in x and y of the allowed axes: large where one view
    leaves the body's extent open), ``contradicted`` (the fraction of turned points contradicted), ``kept``
    (bool [N]: the points whose turned copy is not contradicted), ``used`` (False, and no points, when more
    than ``max_contradicted`` are: the views refute the prior, and the body is left to the column fill),
    ``away_from_cameras`` (unit x, y: horizontally away from the cameras, None when they look straight down),
    ``pixel_m`` (a pixel's footprint at the object's depth) and ``note`` (one line saying what was assumed).
    """
    from scipy import ndimage

    pts = np.asarray(points, float).reshape(-1, 3)
    if len(pts) < 10:
        raise ValueError(f"complete_by_symmetry: need at least 10 visible points, got {len(pts)}")
    rng = np.random.default_rng(seed)
    sm = smooth_points(pts, smooth_m)
    sub = sm if len(sm) <= max_points else sm[rng.choice(len(sm), max_points, replace=False)]
    coarse_pts = sub if len(sub) <= 600 else sub[rng.choice(len(sub), 600, replace=False)]
    touch = None
    if contact is not None and len(contact):
        touch = np.asarray(contact, float).reshape(-1, 3)
        touch = touch if len(touch) <= 600 else touch[rng.choice(len(touch), 600, replace=False)]
    views = _DepthViews(rec, t, tol_m)

    def in_front(x):
        e = views.in_front(x)
        if len(ee_configs):
            e[inside_open_end_effectors(x, ee_configs, ee_positions, grip, ee_orientations)] = np.inf
        return e

    def contradicted(x):
        return in_front(x) > tol_m

    def costs(P, centres):
        out = np.zeros(len(centres))
        for S in (P,) if touch is None else (P, touch):
            chunk = max(1, 400000 // len(S))
            for i in range(0, len(centres), chunk):
                c = centres[i:i + chunk]
                X = np.repeat(S[None], len(c), axis=0)
                X[..., :2] = 2.0 * c[:, None, :] - X[..., :2]
                if S is P:
                    e = in_front(X.reshape(-1, 3)).reshape(len(c), len(S))
                    out[i:i + chunk] += np.mean(np.minimum(e / cap_m, 1.0) ** 2, axis=1)
                else:  # contact material: turned, it must not enter an end-effector
                    inside = inside_end_effectors(X.reshape(-1, 3), ee_configs, ee_positions, ee_orientations)
                    out[i:i + chunk] += inside.reshape(len(c), len(S)).mean(1)
        return out

    def best(P, xs, ys, smooth):
        cx, cy = np.meshgrid(xs, ys, indexing="ij")
        C = costs(P, np.stack([cx.ravel(), cy.ravel()], 1)).reshape(cx.shape)
        if smooth:  # the coarse grid's noise; on the fine grid this would blur the sharp far-side wall
            C = ndimage.uniform_filter(C, size=3, mode="nearest")
        i = np.unravel_index(np.argmin(C), C.shape)
        region, _ = ndimage.label(C <= C[i] + near_min)
        sel = region == region[i]
        spread = (np.ptp(cx[sel]), np.ptp(cy[sel]))
        Q = np.stack([cx[sel], cy[sel]], 1)
        c = Q.mean(0)
        if away is not None and len(Q) >= 3:
            # along each principal direction of the region that is short (a few pixels: the softness that
            # the eroded silhouette leaves on the cameras' side), from its middle away from the cameras
            h = min(xs[1] - xs[0], ys[1] - ys[0]) / 2.0
            _, vecs = np.linalg.eigh(np.cov((Q - c).T))
            for e in vecs.T:
                a = float(e @ away)
                if np.ptp(Q @ e) > short_m or abs(a) < 0.3:
                    continue
                e = e * np.sign(a)
                for _ in range(int(short_m / h) + 2):
                    q = c + h * e
                    j = (int(round((q[0] - xs[0]) / (xs[1] - xs[0]))),
                         int(round((q[1] - ys[0]) / (ys[1] - ys[0]))))
                    if not (0 <= j[0] < len(xs) and 0 <= j[1] < len(ys)) or not sel[j]:
                        break
                    c = q
        return c, float(C[i]), spread

    cams = np.array([cam.position[:2] for cam in rec.cameras]) - pts[:, :2].mean(0)
    cams = cams[np.linalg.norm(cams, axis=1) > 1e-3]
    away = None
    if len(cams):
        u = np.sum(cams / np.linalg.norm(cams, axis=1, keepdims=True), axis=0)
        away = -u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-6 else None
    short_m = 3.0 * views.pixel_m + 0.001
    if axis is None:
        lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
        size = hi - lo
        grow = 0.5 * size.max() + 0.01
        step = max(size.max() / 60.0, 0.002)
        axes = [np.arange(lo[i] - grow, hi[i] + grow + 0.5 * step, step) for i in range(2)]
        c, _, _ = best(coarse_pts, *axes, True)
        fine = step / 4.0
        axes = [c[i] + np.arange(-3 * step, 3 * step + 0.5 * fine, fine) for i in range(2)]
        c, _, spread = best(sub, *axes, False)
    else:
        c, spread = np.asarray(axis, float).reshape(2), (0.0, 0.0)
    turned = _half_turn(pts, c)
    bad = contradicted(turned)
    frac = float(bad.mean())
    info = {"axis_m": [float(c[0]), float(c[1])], "contradicted": frac, "axis_spread_m": [float(v) for v in spread],
            "used": axis is not None or frac <= max_contradicted, "kept": ~bad,
            "away_from_cameras": None if away is None else [float(away[0]), float(away[1])],
            "pixel_m": float(views.pixel_m)}
    if not info["used"]:
        info["note"] = (f"half-turn symmetry about a vertical axis refuted by the depth images ({100 * frac:.0f} % of "
                        f"the turned surface lies in seen free space); the hidden side is only the column fill "
                        f"down to the table")
        return np.zeros((0, 3)), info
    info["note"] = (f"hidden side = visible side turned 180 deg about the vertical axis at "
                    f"({c[0]:.3f}, {c[1]:.3f}) m ({100 * frac:.0f} % of the turned surface contradicted by depth)")
    if max(spread) > short_m:
        info["note"] += (f"; the views leave the axis open over {1000 * spread[0]:.0f} x {1000 * spread[1]:.0f} mm "
                         f"(x, y): the body's extent along that is the prior's, not measured")
    return turned[~bad], info


def half_turn_axis(points: np.ndarray, *, cap_m: float = 0.01, coarse_m: float = 0.002,
                   fine_m: float = 0.0005) -> Tuple[np.ndarray, float]:
    """The vertical axis (x, y in m) about which half a turn maps the surface ``points`` [N, 3] (m) best onto
    itself, and that fit's cost (m): the mean distance from each turned point to the nearest point, capped at
    ``cap_m`` so that a side seen on one half only (whose turned copy lands where nothing was seen) counts as a
    fixed penalty, not by how far it lands. Searched on a grid of ``coarse_m`` over the middle half of the points'
    footprint, then of ``fine_m`` around the best. (Unlike :func:`complete_by_symmetry`'s search, which asks only
    that the turned copy not be seen through, this needs surfaces seen on both halves: views from all sides.)"""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, float).reshape(-1, 3)
    tree = cKDTree(pts)

    def cost(c):
        d = tree.query(_half_turn(pts, c), distance_upper_bound=cap_m)[0]
        return float(np.mean(np.minimum(d, cap_m)))

    lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
    centre, span = 0.5 * (lo + hi), 0.25 * (hi - lo)
    best = (np.inf, centre)
    for step in (coarse_m, fine_m):
        grids = [np.arange(centre[i] - span[i], centre[i] + span[i] + 0.5 * step, step) for i in range(2)]
        for ax in grids[0]:
            for ay in grids[1]:
                c = np.array([ax, ay])
                e = cost(c)
                if e < best[0]:
                    best = (e, c)
        centre, span = best[1], np.full(2, 3.0 * coarse_m)
    return best[1], best[0]


#: Least share of the turned surface that :func:`complete_unseen_side` must place in an unseen hole before it adds
#: any: a few turned points land in a shadow by chance (3-4 % of them on ``empm synth``'s box dough in two clamps and
#: the lump under a plate), a side that no camera saw lands many (37 % on the lump between two clamps).
MIN_UNSEEN_SIDE_SHARE = 0.1


def complete_unseen_side(points: np.ndarray, rec: Recording, t: int, ee_configs, ee_positions, *,
                         ee_orientations=None, solid: Optional[np.ndarray] = None, gap_m: float = 0.0025,
                         front_m: float = 0.00125, min_share: float = MIN_UNSEEN_SIDE_SHARE) -> Tuple[np.ndarray, dict]:
    """Surface samples [M, 3] (m) of a side of the body that cameras all around it do not see because an
    end-effector stands in the way, by the half-turn prior of :func:`complete_by_symmetry`.

    From cameras around an object every side is seen by some camera, unless end-effectors block it: a rounded
    lump between two tall clamps shows its middle's far slope to no camera (the cameras on that side look at it
    past the clamps, the others see only its crest). Neither the fill of the measured surface nor the clamps'
    prior (:func:`complete_occluded`, which fills next to each end-effector) reaches it, and the body has a bite
    there (``empm synth``'s lump in two clamps: 12 % of its volume missing, benchmarks/RESULTS.md, session 76).

    **Prior**: the body is unchanged by half a turn about a vertical axis (:func:`half_turn_axis`, fitted to the
    seen surface). The seen surface ``points`` [N, 3] (m, frame ``t``, object only) is turned, and a turned point is
    kept where every camera saw a surface at least ``front_m`` (m) in front of it (hidden from all), an end-effector
    (``ee_configs`` at ``ee_positions`` [K, 3], orientations [K, 4]) blocks it from at least one camera, it lies
    inside none, and it is more than ``gap_m`` (m) from every point of ``solid`` [S, 3] (m: the body as filled from
    the seen surface, its particles; default ``points``): inside the body, everything is hidden. Only
    when at least ``min_share`` of the turned points are kept is a side missing (else none are returned: a few
    turned points land in a shadow by chance). Returns ``(points [M, 3], info)`` with ``axis_m``, ``fit_m`` (the
    axis fit's cost), ``share`` (kept / turned) and ``note`` (None when nothing was added)."""
    pts = np.asarray(points, float).reshape(-1, 3)
    info = {"axis_m": None, "fit_m": None, "share": 0.0, "note": None}
    if len(pts) < 10 or len(ee_configs) == 0:
        return np.zeros((0, 3)), info
    from scipy.spatial import cKDTree

    axis, fit = half_turn_axis(pts)
    turned = _half_turn(pts, axis)
    keep = cKDTree(pts if solid is None else np.asarray(solid, float).reshape(-1, 3)).query(turned)[0] > gap_m
    if keep.any():
        keep[keep] &= ~inside_end_effectors(turned[keep], ee_configs, ee_positions, ee_orientations)
    if keep.any():
        keep[keep] &= _hidden(turned[keep], rec, t, front_m)
    if keep.any():
        keep[keep] &= hidden_by_end_effectors(turned[keep], rec.cameras, ee_configs, ee_positions, ee_orientations)
    share = float(keep.mean())
    info.update(axis_m=[float(axis[0]), float(axis[1])], fit_m=fit, share=share)
    if share < min_share:
        return np.zeros((0, 3)), info
    info["note"] = (f"{100 * share:.0f} % of the seen surface, turned half a turn about the vertical axis at "
                    f"({axis[0]:.3f}, {axis[1]:.3f}) m, lands where no camera sees past the end-effectors: that side "
                    f"of the body is the turned seen side (a half-turn symmetry prior), not measured")
    return turned[keep], info


def _measured_depths(x: np.ndarray, rec: Recording, t: int, *, fill_silhouettes: bool = False):
    """Per camera: (measured depth [m] at each point's pixel, 0 where none; the point's own depth z [m]).

    With ``fill_silhouettes`` a missing depth takes the largest valid depth within 2 pixels: depth is
    missing mostly at silhouettes, where a nearer and a farther surface meet, so assume the farther one.
    """
    from scipy import ndimage

    for c, cam in enumerate(rec.cameras):
        depth = np.asarray(rec.depth(c, t), float)
        if fill_silhouettes:
            depth = np.where(depth > 0, depth, ndimage.maximum_filter(depth, size=5))
        rc, z = cam.project(x)
        r = np.rint(rc[:, 0]).astype(int)
        col = np.rint(rc[:, 1]).astype(int)
        ok = (z > 0) & (r >= 0) & (r < depth.shape[0]) & (col >= 0) & (col < depth.shape[1])
        d = np.zeros(len(x))
        d[ok] = depth[r[ok], col[ok]]
        yield d, z


def _carve(x: np.ndarray, rec: Recording, t: int, tol_m: float):
    keep = np.ones(len(x), bool)
    for d, z in _measured_depths(x, rec, t):
        keep &= ~((d > 0) & (d > z + tol_m))
    return keep, None


def _hidden(x: np.ndarray, rec: Recording, t: int, front_m: float) -> np.ndarray:
    """True where every camera that measures a depth at the point's pixel saw a surface at least
    ``front_m`` (m) in front of the point (so no camera sees the point itself or beyond it)."""
    keep = np.ones(len(x), bool)
    for d, z in _measured_depths(x, rec, t, fill_silhouettes=True):
        keep &= ~((d > 0) & (d > z - front_m))
    return keep
