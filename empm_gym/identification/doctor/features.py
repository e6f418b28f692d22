"""Where simulation and measurement disagree: residuals per frame, per point, per region, and
summary features computed from the data alone.

All lengths are metres, times seconds; z is up and the table is the plane ``z = table_z``.
Inputs are plain arrays: observed points per frame (list of ``[n_t, 3]``), simulated particle
positions ``[T, N, 3]`` (same frames), end-effector controls ``[T, K, 3]`` / grip ``[T, K]``,
optionally tracks ``[T, M, 3]`` with visibility ``[T, M]`` and the simulated positions of the same
tracked material points ``[T, M, 3]``. Nothing keys on file names, script frame indices or ground
truth. Every feature returns NaN (never raises) when the phase or data it needs is absent.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .phases import (CONTACT_PHASES, FREE_PHASES, Phase, contact_distances, ee_rotations, ee_sizes,
                     object_speed, phase_of_frames, surface_gap)

__all__ = [
    "FEATURE_INFO",
    "point_residuals",
    "residuals_per_frame",
    "frame_residuals",
    "track_errors",
    "regions",
    "body_halves",
    "particle_residual_map",
    "count_pieces",
    "summary_features",
    "control_lag",
    "localise",
]

#: name -> (unit, meaning) of every key :func:`summary_features` returns.
FEATURE_INFO: Dict[str, Tuple[str, str]] = {
    "residual_after_release_vs_contact": (
        "-", "mean frame Chamfer in after_release/at_rest over that in contact/holding/moving "
        "(>1: the model is worse once the object is free: plasticity, viscosity, table friction)"),
    "rest_drift_m": (
        "m", "sum over still phases (approach, holding, at_rest) of observed centroid displacement minus "
        "simulated (>0: the real object creeps/sags where the model is still: viscosity, plasticity)"),
    "residual_asymmetry": (
        "-", "(r+ - r-)/(r+ + r-): mean observed-point residual on the two halves of the body split along "
        "its principal axis at the first frame (axis oriented so its largest component is positive); "
        "0 = symmetric, +-1 = all on one half (heterogeneous stiffness, one-sided slip)"),
    "pieces_observed": ("count", "connected pieces of the observed points at the last frame (joined through an "
                                 "end-effector that may hide what lies between them)"),
    "pieces_observed_max": ("count", "most connected pieces of the observed points over frames (joined through an "
                                     "end-effector that may hide what lies between them)"),
    "pieces_simulated": ("count", "connected pieces of the simulated particles at the last frame"),
    "pieces_simulated_max": ("count", "most connected pieces of the simulated particles over frames"),
    "track_slip_m": (
        "m", "median motion of tracked points near a closed, touching gripper relative to that gripper "
        "over the closed interval, observed minus simulated (>0: the real object slips in the grip)"),
    "decay_rate_obs_per_s": ("1/s", "decay rate of the observed centroid speed after its post-release peak"),
    "decay_rate_sim_per_s": ("1/s", "same for the simulated centroid"),
    "oscillation_decay": (
        "-", "decay_rate_obs / decay_rate_sim (>1: the real object settles faster: missing damping/viscosity)"),
    "table_slide_m": (
        "m", "sum over contact-free runs of horizontal observed centroid displacement minus simulated "
        "(>0: the real object slides further on the table than modelled: table friction)"),
    "residual_near_ee_vs_free": (
        "-", "mean observed-point residual near an end-effector over that on free parts "
        "(>1: the disagreement sits at the grip: gripper slip, local plasticity)"),
}


# ----------------------------------------------------------------------------- residuals


def _pts(p) -> np.ndarray:
    return np.asarray(p, dtype=float).reshape(-1, 3)


def point_residuals(obs_points: np.ndarray, sim_points: np.ndarray) -> np.ndarray:
    """``[n]`` distance (m) of each observed point to the nearest simulated point (NaN if no sim points)."""
    o, s = _pts(obs_points), _pts(sim_points)
    if len(s) == 0:
        return np.full(len(o), np.nan)
    if len(o) == 0:
        return np.zeros(0)
    d, _ = cKDTree(s).query(o, k=1)
    return d


def residuals_per_frame(obs_list: Sequence[np.ndarray], sim: np.ndarray) -> List[np.ndarray]:
    """Per frame, :func:`point_residuals` of the observed points against ``sim[t]``."""
    sim = np.asarray(sim, dtype=float)
    return [point_residuals(obs_list[t], sim[t]) for t in range(min(len(obs_list), len(sim)))]


def frame_residuals(obs_list: Sequence[np.ndarray], sim: np.ndarray) -> np.ndarray:
    """``[T]`` symmetric Chamfer per frame, ``0.5 (mean d(obs->sim) + mean d(sim->obs))`` (m).

    Same definition as :func:`empm_gym.identification.losses.chamfer_numpy`; NaN where a frame has no
    observed points.
    """
    sim = np.asarray(sim, dtype=float)
    T = min(len(obs_list), len(sim))
    out = np.full(T, np.nan)
    for t in range(T):
        o, s = _pts(obs_list[t]), _pts(sim[t])
        if len(o) == 0 or len(s) == 0:
            continue
        a, _ = cKDTree(s).query(o, k=1)
        b, _ = cKDTree(o).query(s, k=1)
        out[t] = 0.5 * (a.mean() + b.mean())
    return out


def track_errors(tracks: np.ndarray, visible: np.ndarray, sim_tracks: np.ndarray) -> np.ndarray:
    """``[T, M]`` position error (m) of each tracked point; NaN where the track is not visible."""
    tr, st = np.asarray(tracks, dtype=float), np.asarray(sim_tracks, dtype=float)
    err = np.linalg.norm(tr - st, axis=-1)
    err[~(np.asarray(visible) > 0.5)] = np.nan
    return err


# ----------------------------------------------------------------------------- regions


def regions(points: np.ndarray, ee_positions: np.ndarray, ee_radius, table_z: float = 0.0,
            near_m: float = 0.03, table_band_m: float = 0.005, ee_rot: Optional[np.ndarray] = None) -> np.ndarray:
    """``[n]`` region label of each point: ``"near_ee_k"``, ``"on_table"`` or ``"free"``.

    ``near_ee_k``: within ``near_m`` of end-effector ``k``'s surface (centre distance minus radius; the
    nearest end-effector wins); otherwise ``on_table`` when ``z - table_z <= table_band_m``; otherwise
    ``free``. ``ee_rot`` ``[K, 3, 3]``: the end-effectors' axes (:func:`~.phases.ee_rotations` of one frame; None:
    the world's).
    """
    p = _pts(points)
    ee = np.asarray(ee_positions, dtype=float).reshape(-1, 3)
    lab = np.full(len(p), "free", dtype=object)
    lab[p[:, 2] - table_z <= table_band_m] = "on_table"
    if len(ee) and len(p):
        size = ee_sizes(ee_radius, len(ee))
        gap = np.stack([surface_gap(p, ee[k], size[k], None if ee_rot is None else ee_rot[k])
                        for k in range(len(ee))], axis=1)
        k = np.argmin(gap, axis=1)
        near = gap[np.arange(len(p)), k] <= near_m
        lab[near] = np.array([f"near_ee_{i}" for i in k[near]], dtype=object)
    return lab.astype(str)


def body_halves(sim0: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split the simulated particles into two halves along the principal axis of ``sim0`` ``[N, 3]``.

    Returns ``(positive [N] bool, axis [3], centre [3])``; the axis is oriented so that its largest
    component is positive (deterministic sign). Halves follow the particles (material), not space.
    """
    s = _pts(sim0)
    c = s.mean(axis=0)
    _, _, vt = np.linalg.svd(s - c, full_matrices=False)
    axis = vt[0]
    if axis[np.argmax(np.abs(axis))] < 0:
        axis = -axis
    return (s - c) @ axis > 0, axis, c


def particle_residual_map(obs_list: Sequence[np.ndarray], sim: np.ndarray,
                          frames: Optional[Sequence[int]] = None) -> np.ndarray:
    """``[N]`` mean residual (m) attributed to each simulated particle: every observed point's distance
    to the simulation is credited to its nearest particle, averaged over ``frames`` (default all).
    NaN for particles never nearest to an observed point. Shows *where on the body* the model is off.
    """
    sim = np.asarray(sim, dtype=float)
    N = sim.shape[1]
    tot, cnt = np.zeros(N), np.zeros(N)
    frames = range(min(len(obs_list), len(sim))) if frames is None else frames
    for t in frames:
        o = _pts(obs_list[t])
        if len(o) == 0:
            continue
        d, i = cKDTree(sim[t]).query(o, k=1)
        np.add.at(tot, i, d)
        np.add.at(cnt, i, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)


# ----------------------------------------------------------------------------- pieces


def count_pieces(points: np.ndarray, link_m: Optional[float] = None, min_frac: float = 0.05,
                 link_factor: float = 4.0, max_points: int = 4000, seed: int = 0,
                 occluders: Sequence[Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]] = (),
                 occluder_gap_m: float = 0.0) -> int:
    """Connected pieces of a point set: points closer than ``link_m`` are linked (radius graph).

    ``link_m=None``: ``link_factor`` times the median nearest-neighbour spacing of the set.
    Components with fewer than ``min_frac`` of the points are ignored (noise, flying pixels).
    Sets above ``max_points`` are subsampled (fixed seed). 0 for an empty set.

    ``occluders``: end-effectors ``(centre, size, rot)`` as :func:`~.phases.surface_gap` takes them. The points
    within ``max(link_m, occluder_gap_m)`` of one's surface are linked through it, since what lies between
    them may be hidden behind it. Observed points part at a plate that presses a rope, or at a clamp that
    holds a body, where the cameras cannot see (the rope pressed and released, the dough rolled in
    lift-twist: 2 pieces without the end-effectors, 1 with them; benchmarks/RESULTS.md, session 52).
    """
    p = _pts(points)
    if len(p) == 0:
        return 0
    if len(p) == 1:
        return 1
    if len(p) > max_points:
        p = p[np.random.default_rng(seed).choice(len(p), max_points, replace=False)]
    tree = cKDTree(p)
    if link_m is None:
        d, _ = tree.query(p, k=2)
        link_m = link_factor * float(np.median(d[:, 1]))
        if link_m <= 0:
            link_m = 1e-9
    pairs = tree.query_pairs(link_m, output_type="ndarray").reshape(-1, 2)
    n = len(p)
    rows, cols = [pairs[:, 0]], [pairs[:, 1]]
    for k, (centre, size, rot) in enumerate(occluders):  # node n + k: the end-effector
        near = np.flatnonzero(surface_gap(p, centre, size, rot) <= max(link_m, occluder_gap_m))
        rows.append(np.full(len(near), n + k))
        cols.append(near)
    r, c = np.concatenate(rows), np.concatenate(cols)
    m = n + len(occluders)
    _, lab = connected_components(coo_matrix((np.ones(len(r)), (r, c)), shape=(m, m)), directed=False)
    sizes = np.bincount(lab[:n])
    return int(np.sum(sizes >= max(1, min_frac * n)))


# ----------------------------------------------------------------------------- features


def _frames_in(labels: np.ndarray, names: Sequence[str]) -> np.ndarray:
    return np.isin(labels, list(names))


def _segments(mask: np.ndarray) -> List[Tuple[int, int]]:
    out, t, T = [], 0, len(mask)
    while t < T:
        if mask[t]:
            s = t
            while t < T and mask[t]:
                t += 1
            out.append((s, t))
        else:
            t += 1
    return out


def _edge_disp(c: np.ndarray, s: int, e: int, edge: int, dims=slice(0, 3)) -> float:
    """|median(c[last edge frames]) - median(c[first edge frames])| over ``dims`` (NaN-safe)."""
    w = max(1, min(edge, (e - s) // 2 or 1))
    a = np.nanmedian(c[s:s + w, dims], axis=0)
    b = np.nanmedian(c[e - w:e, dims], axis=0)
    return float(np.linalg.norm(b - a))


def _nanratio(a: float, b: float) -> float:
    if not (np.isfinite(a) and np.isfinite(b)) or b <= 0:
        return float("nan")
    return float(a / b)


def _nanmean(x) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else float("nan")


def _decay_rate(v: np.ndarray, fps: float, floor: float, min_frames: int = 3) -> float:
    """-slope of log(max(v, floor)) against time from the peak of ``v`` to its end (1/s)."""
    v = np.asarray(v, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) < min_frames:
        return float("nan")
    v = v[int(np.argmax(v)):]
    if len(v) < min_frames or v[0] <= floor:
        return float("nan")
    t = np.arange(len(v)) / fps
    slope = np.polyfit(t, np.log(np.maximum(v, floor)), 1)[0]
    return float(-slope)


def summary_features(
    phases: Sequence[Phase],
    obs_list: Sequence[np.ndarray],
    sim: np.ndarray,
    ee_positions: np.ndarray,
    ee_grip: np.ndarray,
    ee_radius,
    fps: float,
    *,
    tracks: Optional[np.ndarray] = None,
    visible: Optional[np.ndarray] = None,
    sim_tracks: Optional[np.ndarray] = None,
    table_z: float = 0.0,
    near_m: float = 0.03,
    contact_dist_m: float = 0.01,
    link_m: Optional[float] = None,
    min_piece_frac: float = 0.05,
    piece_stride: int = 1,
    edge_frames: int = 2,
    floor_mps: float = 0.005,
    frame_res: Optional[np.ndarray] = None,
    point_res: Optional[List[np.ndarray]] = None,
    ee_orientations: Optional[np.ndarray] = None,
) -> Dict[str, float]:
    """Named scalar features (see :data:`FEATURE_INFO` for units and meaning) from data alone.

    Args:
        phases: from :func:`~.phases.segment_phases`.
        obs_list: observed object points per frame; ``sim``: ``[T, N, 3]`` simulated particles of the
            model under test (usually the fitted base model).
        ee_positions, ee_grip, ee_radius: controls, as for :func:`~.phases.segment_phases`.
        tracks, visible, sim_tracks: optional point tracks (``track_slip_m`` is NaN without them).
        table_z: table height (m); near_m: "near a gripper" distance (m) for track slip and regions.
        contact_dist_m: gripper-surface gap (m) that counts as touching (track slip).
        link_m, min_piece_frac, piece_stride: :func:`count_pieces` settings; every ``piece_stride``-th
            frame enters the maxima.
        edge_frames: displacements use medians over this many frames at both ends of a run.
        floor_mps: speed noise floor for the decay rates (m/s).
        frame_res, point_res: precomputed :func:`frame_residuals` / :func:`residuals_per_frame`.
        ee_orientations: ``[T, K, 4]`` (x, y, z, w) from the controls, or None (they never turn): boxes turn
            with them, and a tracked point's slip is its motion in its gripper's own frame.
    """
    sim = np.asarray(sim, dtype=float)
    ee = np.asarray(ee_positions, dtype=float)
    if ee.ndim == 2:
        ee = ee[:, None, :]
    T = min(len(obs_list), len(sim), len(ee))
    K = ee.shape[1]
    grip = np.asarray(ee_grip, dtype=float).reshape(len(ee), -1)[:T] > 0.5
    rot = ee_rotations(ee_orientations, T, K, identity=True)
    lab = phase_of_frames(phases, T)
    fr = frame_residuals(obs_list[:T], sim[:T]) if frame_res is None else np.asarray(frame_res)[:T]
    pr = residuals_per_frame(obs_list[:T], sim[:T]) if point_res is None else point_res
    c_obs = np.full((T, 3), np.nan)
    for t in range(T):
        o = _pts(obs_list[t])
        if len(o):
            c_obs[t] = o.mean(axis=0)
    c_sim = sim[:T].mean(axis=1)
    f: Dict[str, float] = {}

    # residual after release vs during contact
    free = _frames_in(lab, FREE_PHASES)
    cont = _frames_in(lab, CONTACT_PHASES)
    f["residual_after_release_vs_contact"] = _nanratio(_nanmean(fr[free]), _nanmean(fr[cont])) \
        if free.any() and cont.any() else float("nan")

    # drift where the object should be still
    still = _frames_in(lab, ("approach", "holding", "at_rest"))
    segs = [(s, e) for s, e in _segments(still) if e - s >= 2]
    if segs:
        f["rest_drift_m"] = float(sum(_edge_disp(c_obs, s, e, edge_frames) - _edge_disp(c_sim, s, e, edge_frames)
                                      for s, e in segs))
    else:
        f["rest_drift_m"] = float("nan")

    # asymmetry across the body (halves follow the particles of frame 0)
    pos, _, _ = body_halves(sim[0]) if T else (None, None, None)
    rp, rn = [], []
    for t in range(T):
        o = _pts(obs_list[t])
        if len(o) == 0:
            continue
        _, i = cKDTree(sim[t]).query(o, k=1)
        r = pr[t]
        rp.append(r[pos[i]])
        rn.append(r[~pos[i]])
    mp = _nanmean(np.concatenate(rp)) if rp else float("nan")
    mn = _nanmean(np.concatenate(rn)) if rn else float("nan")
    f["residual_asymmetry"] = _nanratio(mp - mn, mp + mn) if np.isfinite(mp) and np.isfinite(mn) else float("nan")

    # pieces: the observed points joined through the end-effectors that may hide what lies between them
    size = ee_sizes(ee_radius, K)  # [K, 3], as surface_gap takes them (also for the track slip below)
    shown = [t for t in range(T) if len(_pts(obs_list[t]))]  # a frame where the object is wholly hidden shows none

    def observed_pieces(t: int) -> int:
        return count_pieces(obs_list[t], link_m, min_piece_frac, occluder_gap_m=contact_dist_m,
                            occluders=[(ee[t, k], size[k], rot[t, k]) for k in range(K)])

    if shown:
        last = shown[-1]  # the last frame that sees the object, for both
        f["pieces_observed"] = float(observed_pieces(last))
        f["pieces_simulated"] = float(count_pieces(sim[last], link_m, min_piece_frac))
        idx = shown[::max(1, piece_stride)]
        f["pieces_observed_max"] = float(max(observed_pieces(t) for t in idx))
        f["pieces_simulated_max"] = float(max(count_pieces(sim[t], link_m, min_piece_frac) for t in idx))
    else:
        for k in ("pieces_observed", "pieces_simulated", "pieces_observed_max", "pieces_simulated_max"):
            f[k] = float("nan")

    # slip of tracked points relative to a closed gripper
    f["track_slip_m"] = float("nan")
    if tracks is not None and sim_tracks is not None and T:
        tr = np.asarray(tracks, dtype=float)[:T]
        st = np.asarray(sim_tracks, dtype=float)[:T]
        vis = (np.ones(tr.shape[:2]) if visible is None else np.asarray(visible))[:T] > 0.5
        gap = contact_distances(ee[:T], ee_radius, obs_list[:T], ee_orientations)

        def local(x, t, k):  # a position relative to gripper k at frame t, in the gripper's own frame
            return (x - ee[t, k]) @ rot[t, k]

        so, ss = [], []
        for k in range(K):
            for s, e in _segments(grip[:, k] & (gap[:, k] <= contact_dist_m)):
                if e - s < 2:
                    continue
                near = vis[s] & (surface_gap(tr[s], ee[s, k], size[k], rot[s, k]) <= near_m)
                for m in np.flatnonzero(near):
                    vf = np.flatnonzero(vis[s:e, m])
                    if len(vf) < 2:
                        continue
                    a, b = s + vf[0], s + vf[-1]
                    so.append(np.linalg.norm(local(tr[b, m], b, k) - local(tr[a, m], a, k)))
                    ss.append(np.linalg.norm(local(st[b, m], b, k) - local(st[a, m], a, k)))
        if so:
            f["track_slip_m"] = float(np.median(so) - np.median(ss))

    # decay of the motion after the last contact
    f["decay_rate_obs_per_s"] = f["decay_rate_sim_per_s"] = f["oscillation_decay"] = float("nan")
    if cont.any() and free.any():
        last = int(np.flatnonzero(cont)[-1]) + 1
        if T - last >= 3:
            vo = object_speed(c_obs, fps, 3)[last:]
            vs = object_speed(c_sim, fps, 3)[last:]
            lo, ls = _decay_rate(vo, fps, floor_mps), _decay_rate(vs, fps, floor_mps)
            f["decay_rate_obs_per_s"], f["decay_rate_sim_per_s"] = lo, ls
            f["oscillation_decay"] = _nanratio(lo, ls)

    # sliding on the table without contact
    nocontact = _frames_in(lab, ("approach",) + FREE_PHASES)
    segs = [(s, e) for s, e in _segments(nocontact) if e - s >= 2]
    if segs and (cont.any()):
        f["table_slide_m"] = float(sum(_edge_disp(c_obs, s, e, edge_frames, slice(0, 2))
                                       - _edge_disp(c_sim, s, e, edge_frames, slice(0, 2)) for s, e in segs))
    else:
        f["table_slide_m"] = float("nan")

    # residual near the end-effectors vs on free parts
    near_r, free_r = [], []
    for t in range(T):
        o = _pts(obs_list[t])
        if len(o) == 0:
            continue
        rl = regions(o, ee[t], ee_radius, table_z, near_m, ee_rot=rot[t])
        near_r.append(pr[t][np.char.startswith(rl, "near_ee")])
        free_r.append(pr[t][rl == "free"])
    nm = _nanmean(np.concatenate(near_r)) if near_r else float("nan")
    fm = _nanmean(np.concatenate(free_r)) if free_r else float("nan")
    f["residual_near_ee_vs_free"] = _nanratio(nm, fm)
    return f


# ----------------------------------------------------------------------------- controls against images


#: Fewest (track, frame) samples, and least spread of the gripper's speed over its closed intervals [m/frame],
#: with which :func:`control_lag` estimates a lag: a gripper that moves at one constant speed while closed makes a
#: lag indistinguishable from a constant offset (and from slip, which grows with the gripper's travel).
LAG_MIN_SAMPLES = 30
LAG_MIN_SPEED_SPREAD = 5e-4
#: Largest share of the gripper's travel the material next to it may fall behind by (``slip_share``) for
#: :func:`control_lag` to read a lag: material that stretches or slides away from the gripper moves by its own
#: dynamics, which a lag of the controls cannot be told from (dough lifted by one end: 0.66-0.78 with rigid
#: grips; benchmarks/RESULTS.md, session 50).
LAG_MAX_SLIP_SHARE = 0.25
#: Fewest tracked points that move with their gripper (:data:`LAG_MAX_SLIP_SHARE`) from which a lag is read, and
#: their least share of the points near the grippers: where most of the material there stretches or slides,
#: the few that pass by chance read its dynamics (dough pulled apart with a soft end: 9 of 34 and 17 of 68 pass
#: and read 2.2 and 1.6 frames where there is no lag; benchmarks/RESULTS.md, session 50).
LAG_MIN_TRACKS = 8
LAG_MIN_FOLLOWER_SHARE = 0.5


def control_lag(
    tracks: np.ndarray,
    visible: Optional[np.ndarray],
    ee_positions: np.ndarray,
    ee_grip: np.ndarray,
    ee_radius,
    obs_list: Sequence[np.ndarray],
    *,
    near_m: float = 0.03,
    contact_dist_m: float = 0.01,
    min_frames: int = 4,
    n_boot: int = 400,
    level: float = 0.95,
    seed: int = 0,
    ee_orientations: Optional[np.ndarray] = None,
) -> Dict[str, float]:
    """How many frames the tracked material next to a closed gripper lags behind the gripper's controls,
    from data alone: the controls and the images out of sync.

    Over each interval where a gripper is closed and touching the object (as for ``track_slip_m``), every
    tracked point near it at the interval's start has, relative to the gripper, the position
    ``r(t) = a - beta * D(t) - lag * v(t)``, with ``D`` the gripper's travel since the interval's start, ``v`` its
    velocity per frame (central differences of the controls) and ``a`` the point's own offset: a lag of ``lag``
    frames (the images show the gripper's effect ``lag`` frames after the controls say it happened; negative:
    before) puts the point behind the gripper by ``lag * v``, which vanishes once the gripper stops, while slip
    leaves it behind by a share ``beta`` of the travel, which stays. Each point's own ``beta`` picks the points
    that move with their gripper (:data:`LAG_MAX_SLIP_SHARE`; material that stretches or slides moves by its own
    dynamics); ``beta`` and ``lag`` are then fitted by least squares over those points and their frames, and the
    interval of ``lag`` is a bootstrap over them. With ``ee_orientations`` ``[T, K, 4]`` (x, y, z, w) a gripper
    also turns: ``r``, ``D`` and ``v`` are then taken in the gripper's own frame, and ``v`` is the velocity of
    the material point as the gripper would carry it (its centre's velocity plus its turn about the centre).

    Returns ``lag_frames``, ``lower``, ``upper`` (the ``level`` interval), ``slip_share`` (beta over all points
    near the grippers), ``samples`` (point-frames used), ``followers`` / ``points`` (points that move with their
    gripper / all near it) and ``speed_spread_m`` (the standard deviation of the gripper's speed over the
    samples, m/frame). The lag and its interval are NaN without tracks, without a closed interval of
    ``min_frames`` frames with tracked points near the gripper, where the gripper's speed varies too little to
    tell a lag from an offset (:data:`LAG_MIN_SPEED_SPREAD`), or with fewer than :data:`LAG_MIN_TRACKS` points
    (:data:`LAG_MIN_SAMPLES` point-frames), or under :data:`LAG_MIN_FOLLOWER_SHARE` of those near the grippers,
    that move with their gripper."""
    nan = {"lag_frames": float("nan"), "lower": float("nan"), "upper": float("nan"), "slip_share": float("nan"),
           "samples": 0, "speed_spread_m": float("nan"), "followers": 0, "points": 0}
    if tracks is None:
        return nan
    ee = np.asarray(ee_positions, dtype=float)
    if ee.ndim == 2:
        ee = ee[:, None, :]
    tr = np.asarray(tracks, dtype=float)
    T = min(len(tr), len(ee), len(obs_list))
    if T < min_frames:
        return nan
    tr, ee = tr[:T], ee[:T]
    K = ee.shape[1]
    vis = (np.ones(tr.shape[:2], bool) if visible is None else np.asarray(visible)[:T] > 0.5) & np.all(
        np.isfinite(tr), axis=-1)
    grip = np.asarray(ee_grip, dtype=float).reshape(len(ee_grip), -1)[:T] > 0.5
    gap = contact_distances(ee, ee_radius, obs_list[:T], ee_orientations)
    size = ee_sizes(ee_radius, K)
    R = ee_rotations(ee_orientations, T, K, identity=True)

    def carried(x, ts, k):
        """Velocity [m/frame] in gripper k's frame of points ``x`` [n, 3] at frames ``ts`` were the gripper
        carrying them rigidly: central differences (one-sided at the ends) of where it would put them a frame
        earlier and later (without turns: the gripper's own velocity, np.gradient of its centres)."""
        off = np.einsum("ni,nij->nj", x - ee[ts, k], R[ts, k])          # in the gripper's frame
        a, b = np.maximum(ts - 1, 0), np.minimum(ts + 1, T - 1)
        pa = ee[a, k] + np.einsum("nij,nj->ni", R[a, k], off)
        pb = ee[b, k] + np.einsum("nij,nj->ni", R[b, k], off)
        u = (pb - pa) / np.maximum(b - a, 1)[:, None]
        return np.einsum("ni,nij->nj", u, R[ts, k])
    groups: List[Tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # per tracked point: (r, D, v) demeaned
    speeds = []
    for k in range(K):
        for s, e in _segments(grip[:, k] & (gap[:, k] <= contact_dist_m)):
            if e - s < min_frames:
                continue
            near = vis[s] & (surface_gap(tr[s], ee[s, k], size[k], R[s, k]) <= near_m)
            for m in np.flatnonzero(near):
                ts = s + np.flatnonzero(vis[s:e, m])
                if len(ts) < min_frames:
                    continue
                r = np.einsum("ni,nij->nj", tr[ts, m] - ee[ts, k], R[ts, k])
                D = np.einsum("ni,nij->nj", ee[ts, k] - ee[s, k], R[ts, k])
                v = carried(tr[ts, m], ts, k)
                groups.append((r - r.mean(0), D - D.mean(0), v - v.mean(0)))
                speeds.append(np.linalg.norm(v, axis=-1))
    if not groups:
        return nan
    n = sum(len(g[0]) for g in groups)
    spread = float(np.std(np.concatenate(speeds)))
    if n < LAG_MIN_SAMPLES or not spread >= LAG_MIN_SPEED_SPREAD:
        return {**nan, "samples": int(n), "speed_spread_m": spread, "points": len(groups)}
    # per point, the normal equations' pieces (r = -beta D - lag v, every coordinate a sample)
    A = np.array([[[np.sum(D * D), np.sum(D * v)], [np.sum(D * v), np.sum(v * v)]] for _, D, v in groups])
    b = np.array([[-np.sum(D * r), -np.sum(v * r)] for r, D, v in groups])

    def solve(idx):
        try:
            return np.linalg.solve(A[idx].sum(0), b[idx].sum(0))
        except np.linalg.LinAlgError:
            return np.array([np.nan, np.nan])

    # the points that move with their gripper: each one's own share of the travel it falls behind by is small
    own = np.array([solve([i])[0] if np.linalg.cond(A[i]) < 1e8 else np.nan for i in range(len(groups))])
    keep = np.flatnonzero(np.abs(own) <= LAG_MAX_SLIP_SHARE)
    n_keep = int(sum(len(groups[i][0]) for i in keep))
    beta_all = float(solve(np.arange(len(groups)))[0])
    if len(keep) < max(LAG_MIN_TRACKS, LAG_MIN_FOLLOWER_SHARE * len(groups)) or n_keep < LAG_MIN_SAMPLES:
        return {**nan, "slip_share": beta_all, "samples": int(n), "speed_spread_m": spread, "followers": int(len(keep)),
                "points": len(groups)}
    lag = solve(keep)[1]
    rng = np.random.default_rng(seed)
    boot = np.array([solve(keep[rng.integers(0, len(keep), len(keep))])[1] for _ in range(n_boot)])
    boot = boot[np.isfinite(boot)]
    lo, hi = (np.quantile(boot, [(1 - level) / 2, (1 + level) / 2]) if len(boot) else (np.nan, np.nan))
    return {"lag_frames": float(lag), "lower": float(lo), "upper": float(hi), "slip_share": beta_all,
            "samples": n_keep, "speed_spread_m": spread, "followers": int(len(keep)), "points": len(groups)}


def localise(
    phases: Sequence[Phase],
    obs_list: Sequence[np.ndarray],
    sim: np.ndarray,
    ee_positions: np.ndarray,
    ee_radius,
    *,
    table_z: float = 0.0,
    near_m: float = 0.03,
    table_band_m: float = 0.005,
    top_k: int = 5,
    min_points: int = 20,
    frame_res: Optional[np.ndarray] = None,
    point_res: Optional[List[np.ndarray]] = None,
    ee_orientations: Optional[np.ndarray] = None,
) -> dict:
    """Where the disagreement is: mean observed-point residual per (phase, region), worst cell, worst frames.

    Returns a dict with
      ``table``: ``{phase: {region: mean residual (m)}}``; ``counts``: same layout, number of points;
      ``worst_phase`` / ``worst_region`` / ``worst_cell`` (phase, region): highest mean residual among
      cells with at least ``min_points`` points (falls back to all cells);
      ``by_phase`` / ``by_region``: marginal means (m); ``halves``: ``{"positive", "negative"}`` mean
      residual on the two body halves of :func:`body_halves` plus ``axis``;
      ``frame_residuals``: ``[T]`` list (m); ``worst_frames``: the ``top_k`` frames by frame residual.
    ``ee_orientations`` ``[T, K, 4]`` (x, y, z, w) turn the boxes of the regions (None: axis-aligned).
    """
    sim = np.asarray(sim, dtype=float)
    ee = np.asarray(ee_positions, dtype=float)
    if ee.ndim == 2:
        ee = ee[:, None, :]
    T = min(len(obs_list), len(sim), len(ee))
    lab = phase_of_frames(phases, T)
    rot = ee_rotations(ee_orientations, T, ee.shape[1])
    fr = frame_residuals(obs_list[:T], sim[:T]) if frame_res is None else np.asarray(frame_res)[:T]
    pr = residuals_per_frame(obs_list[:T], sim[:T]) if point_res is None else point_res
    sums: Dict[Tuple[str, str], float] = {}
    cnts: Dict[Tuple[str, str], int] = {}
    pos, axis, _ = body_halves(sim[0])
    hs, hc = np.zeros(2), np.zeros(2)
    for t in range(T):
        o = _pts(obs_list[t])
        if len(o) == 0:
            continue
        r = pr[t]
        rl = regions(o, ee[t], ee_radius, table_z, near_m, table_band_m, None if rot is None else rot[t])
        for reg in np.unique(rl):
            m = rl == reg
            key = (str(lab[t]), str(reg))
            sums[key] = sums.get(key, 0.0) + float(np.nansum(r[m]))
            cnts[key] = cnts.get(key, 0) + int(np.sum(np.isfinite(r[m])))
        _, i = cKDTree(sim[t]).query(o, k=1)
        for h, m in enumerate((pos[i], ~pos[i])):
            hs[h] += np.nansum(r[m])
            hc[h] += np.sum(np.isfinite(r[m]))
    table: Dict[str, Dict[str, float]] = {}
    counts: Dict[str, Dict[str, int]] = {}
    for (ph, reg), s in sums.items():
        table.setdefault(ph, {})[reg] = s / cnts[(ph, reg)] if cnts[(ph, reg)] else float("nan")
        counts.setdefault(ph, {})[reg] = cnts[(ph, reg)]
    cells = [(k, sums[k] / cnts[k]) for k in sums if cnts[k] >= min_points] or \
            [(k, sums[k] / cnts[k]) for k in sums if cnts[k] > 0]
    worst = max(cells, key=lambda kv: kv[1])[0] if cells else (None, None)

    def marginal(idx):
        s, c = {}, {}
        for key in sums:
            s[key[idx]] = s.get(key[idx], 0.0) + sums[key]
            c[key[idx]] = c.get(key[idx], 0) + cnts[key]
        return {k: (s[k] / c[k] if c[k] else float("nan")) for k in s}

    by_phase, by_region = marginal(0), marginal(1)
    ok = np.isfinite(fr)
    order = np.argsort(np.where(ok, -fr, np.inf))
    worst_frames = [int(t) for t in order[:top_k] if ok[t]]
    return {
        "table": table,
        "counts": counts,
        "worst_cell": worst,
        "worst_phase": max(by_phase, key=by_phase.get) if by_phase else None,
        "worst_region": max(by_region, key=by_region.get) if by_region else None,
        "by_phase": by_phase,
        "by_region": by_region,
        "halves": {"positive": float(hs[0] / hc[0]) if hc[0] else float("nan"),
                   "negative": float(hs[1] / hc[1]) if hc[1] else float("nan"),
                   "axis": [float(a) for a in axis]},
        "frame_residuals": [float(x) for x in fr],
        "worst_frames": worst_frames,
    }
