"""Small synthetic identification problems made directly with the simulator (CPU, a few hundred particles).

The "truth" is simulated with its own jittered particle set; identification gets different particles
(a regular lattice, or the perception layer's interior fill of the noisy frame-0 points) and
observations that are only what cameras would see: the visible surface (z-buffer from three cameras
above the table), displaced along the viewing ray by depth-like noise growing with depth squared,
quantised to 1 mm and subsampled; tracked points are visible surface particles with noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List

import numpy as np

from empm_gym.identification import render as R
from empm_gym.identification.problem import Observations, Scene, Views, simulate_frames
from empm_gym.perception.cameras import Camera, intrinsics_matrix, look_at
from empm_gym.sim import EndEffectorConfig, GridConfig, MaterialConfig, TableConfig, sample_box, sample_cylinder

FPS = 30.0


def cameras(width=160, height=120, target=(0.0, 0.0, 0.04)) -> List[Camera]:
    K = intrinsics_matrix(140.0 * width / 160, 140.0 * width / 160, width / 2 - 0.5, height / 2 - 0.5)
    out = []
    for i, az in enumerate((0.3, 2.4, 4.4)):
        eye = (0.55 * np.cos(az), 0.55 * np.sin(az), 0.45)
        out.append(Camera(K, look_at(eye, target), width, height, name=f"cam{i}"))
    return out


@dataclass
class Problem:
    truth: Scene              # scene with the true particles and material
    scene: Scene              # what identification gets (other particles, material to be fitted)
    true_positions: np.ndarray  # [T, N_true, 3]
    obs: Observations
    views: Views


def observe(x: np.ndarray, cams, radius: float, *, rng, noise_per_m2=0.002, max_points=1500, n_tracks=30,
            colors=None, image_ds=1):
    """Observations (and masks / images) of true particle positions x [T, N, 3] seen by ``cams``."""
    T, N, _ = x.shape
    pts, cols, vis_all, masks, images = [], [], [], [], []
    for t in range(T):
        seen = np.zeros(N, bool)
        out, oc, fm, fi = [], [], [], []
        for cam in cams:
            depth, owner = R.splat_depth(x[t], cam, radius, 1)
            ids = np.unique(owner[owner >= 0])
            seen[ids] = True
            p = x[t, ids]
            ray = p - cam.position
            dist = np.linalg.norm(ray, axis=1, keepdims=True)
            ray /= dist
            sigma = noise_per_m2 * dist**2
            # the visible surface of a particle's disk lies one radius towards the camera
            d_noisy = np.round((dist - radius + rng.normal(size=dist.shape) * sigma) * 1000.0) / 1000.0
            out.append(cam.position + ray * d_noisy)
            if colors is not None:
                oc.append(colors[ids])
            fm.append(R.splat_mask(x[t], cam, radius, image_ds))
            if colors is not None:
                bg = np.broadcast_to(np.array([0.55, 0.5, 0.45]), (*R.camera_size(cam, image_ds), 3))
                fi.append(R.render_colors(x[t], colors, cam, radius, bg, image_ds)[0])
        p = np.concatenate(out)
        c = np.concatenate(oc) if colors is not None else None
        if len(p) > max_points:
            keep = rng.choice(len(p), max_points, replace=False)
            p = p[keep]
            c = c[keep] if c is not None else None
        pts.append(p)
        cols.append(c)
        vis_all.append(seen)
        masks.append(fm)
        images.append(fi if colors is not None else None)
    vis = np.stack(vis_all)
    cand = np.nonzero(vis[0])[0]
    tid = rng.choice(cand, min(n_tracks, len(cand)), replace=False)
    tracks = x[:, tid] + rng.normal(size=(T, len(tid), 3)) * 0.001
    obs = Observations(FPS, pts, tracks=tracks, visibility=vis[:, tid],
                       colors=cols if colors is not None else None)
    return obs, Views(cams, masks, images if colors is not None else None)


def rope_lift(E=5e4, *, frames=24, lift_frames=12, speed=0.3, seed=0, dx=0.02, colors=False,
              fit_jitter=0.0, same_body=False) -> Problem:
    """A rope (0.24 m long, 2 cm radius) lying on the table, gripped at its middle and lifted 12 cm.

    Its two halves bend under gravity by an amount and with an oscillation that depend on E / density.
    Identification gets a regular lattice of particles, or with ``fit_jitter`` > 0 another jittered sample
    of the same cylinder (then it and the truth are two draws of the same sampling); with ``same_body`` the
    truth's own particles (the model is then exact up to the observation noise)."""
    mat = MaterialConfig(E=E, nu=0.3, density=1000.0)
    grid = GridConfig(lower=(-0.2, -0.1, -0.06), upper=(0.2, 0.1, 0.3), dx=dx)
    ee = [EndEffectorConfig(shape="sphere", radius=0.03, friction=0.8)]
    pos = np.zeros((frames, 1, 3))
    pos[:, 0, 2] = 0.02 + speed / FPS * np.minimum(np.arange(frames), lift_frames)
    grip = np.ones((frames, 1), np.int32)
    xt, vt = sample_cylinder((-0.12, 0, 0.02), (0.12, 0, 0.02), 0.02, dx, 8, seed=seed + 1, jitter=0.5)
    common = dict(fps=FPS, ee_configs=ee, ee_positions=pos, ee_grip=grip, table=TableConfig(friction=0.5), grid=grid)
    truth = Scene(xt, vt, material=mat, **common)
    xi, vi = sample_cylinder((-0.12, 0, 0.02), (0.12, 0, 0.02), 0.02, dx, 8, seed=seed + 2, jitter=fit_jitter)
    if same_body:
        xi, vi = xt, vt
    scene = Scene(xi, vi, material=mat, **common)
    return _finish(truth, scene, frames, seed, colors)


def dough_squeeze(yield_stress=1500.0, E=3e4, *, frames=31, seed=0, dx=0.02, colors=False,
                  fill_from_observation=True) -> Problem:
    """A dough block (10 x 6 x 6 cm) squeezed between two box pushers well beyond yield, then released.

    It flows sideways while squeezed and keeps a residual deformation after release; both depend on
    the yield stress (and on gravity for a soft dough)."""
    mat = MaterialConfig(E=E, nu=0.3, density=1000.0, yield_stress=yield_stress)
    grid = GridConfig(lower=(-0.14, -0.1, -0.06), upper=(0.14, 0.1, 0.16), dx=dx)
    box = EndEffectorConfig(shape="box", half_extents=(0.03, 0.06, 0.05), friction=0.3)
    t = np.arange(frames)
    # inwards at 0.1 m/s for 10 frames, hold 3, back out for 10, rest
    travel = 0.1 / FPS * (np.clip(t, 0, 10) - np.clip(t - 13, 0, 10))
    pos = np.zeros((frames, 2, 3))
    pos[:, 0] = np.stack([-0.082 + travel, 0 * t, 0.05 + 0 * t], 1)
    pos[:, 1] = np.stack([0.082 - travel, 0 * t, 0.05 + 0 * t], 1)
    grip = np.zeros((frames, 2), np.int32)
    xt, vt = sample_box((-0.05, -0.03, 0.0), (0.05, 0.03, 0.06), dx, 8, seed=seed + 1, jitter=0.5)
    common = dict(fps=FPS, ee_configs=[box, box], ee_positions=pos, ee_grip=grip, table=TableConfig(friction=0.5),
                  grid=grid)
    truth = Scene(xt, vt, material=mat, **common)
    prob = _finish(truth, None, frames, seed, colors)
    if fill_from_observation:
        from empm_gym.perception.fusion import initial_particles

        xi, vi = initial_particles(prob.obs.points[0], dx=dx, table_plane=(np.array([0, 0, 1.0]), 0.0))
    else:
        xi, vi = sample_box((-0.05, -0.03, 0.0), (0.05, 0.03, 0.06), dx, 8)
    prob.scene = Scene(xi, vi, material=mat, **common)
    return prob


def _finish(truth, scene, frames, seed, colors):
    x = simulate_frames(truth, [truth.material], frames=frames)[:, 0]
    rng = np.random.default_rng(seed + 100)
    col = None
    if colors:
        x0 = truth.particles
        u = (x0 - x0.min(0)) / np.maximum(np.ptp(x0, 0), 1e-9)
        col = np.clip(np.stack([0.2 + 0.7 * u[:, 0], 0.3 + 0.5 * u[:, 1], 0.8 - 0.6 * u[:, 2]], 1), 0, 1)
    obs, views = observe(x, cameras(), truth.particle_radius, rng=rng, colors=col)
    return Problem(truth, scene, x, obs, views)
