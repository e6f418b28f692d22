"""Synthetic multi-view RGB-D recordings with known material parameters (``empm synth``).

:func:`synthesize` builds a scene with the simulator, runs a scripted manipulation and renders it from
N cameras around the table into the recording layout of :mod:`empm_gym.perception.recording`:

* ``rope``: an elastic cylinder (0.3 m long, radius 1.2 cm) lying on the table along x, held at both
  ends by two closed sphere grippers (radius 1.8 cm, centred 2 mm above the rope's top, so that they
  carry its upper part and lift off cleanly when opened); script: hold (grasp), lift by 8 cm while
  stretching by 1.5 cm per side, hold, put it back down, release (grippers open and move up), settle.
* ``dough``: an elastoplastic block (5 x 5 x 4.5 cm) between two box plates (pushers, grip open =
  frictional contact); script: hold, squeeze by 1 cm per side, hold, release (plates back out), settle.
* ``block``: an elastic 4 cm cube (E 60 kPa); default script press-release.
* ``lump``: the dough's material as a rounded lump, the part of an ellipsoid (semi-axes 4.2 x 3.4 x 4.0 cm)
  above the table (8.4 x 6.8 x 3.8 cm, 111 cm^3): no face, edge or corner of the boxes the other objects are,
  a shape the doctor's rules were not tuned on; default script press-release.

These are the ``default`` scripts; ``script=`` picks one of :data:`empm_gym.perception.scripts.SCRIPTS`
(press-release, push-slide, squeeze-lift, pull-apart, squeeze-ring), each of which runs on every object.

Hidden effects (``empm synth --effect NAME [--effect-param KEY=VALUE ...] --script SCRIPT``): with an
effect the object is the base model (elastic, also the dough; table friction 0.5; rigid closed grippers)
plus that one effect of :data:`empm_gym.sim.effects.EFFECTS` at :func:`default_effect_params` (or the
given values); ``--effect none`` is the base model alone. Only ``ground_truth.json`` names the effect:
file names, metadata, calibration, controls and timing are the same for every effect (the debug file
``ground_truth_particles.npz`` is written only on request). docs/EFFECTS.md lists which script shows
which effect and by how much.

Rendering does not reuse the simulation particles as the observed surface: a dense set of surface
sample points (spacing ``surface_spacing_m``, about 1.5 mm, much finer than the particles) is
embedded at frame 0 in its nearest particles by a weighted least-squares affine fit, moved with
them, and z-buffered as discs of their world size. Depth gets a RealSense-like noise model: Gaussian
error with sigma = ``noise_sigma_m`` * (z / 0.5 m)^2, 1 mm quantisation (uint16 millimetres), pixels
dropped at silhouette edges (depth jumps > 1 cm), at grazing angles (|cos| < 0.25 between surface
normal and ray) and at random (0.3 %), and nothing outside 0.2-1.5 m.

Replaying the recorded end-effector motion (for identification)
----------------------------------------------------------------
``controls.npz`` holds per frame t = 0..T-1 the end-effector centres ``positions[t, k]`` (m) and
``grip[t, k]``; ``shape``, ``radius``, ``half_extents`` (m) give the geometry. With
``configs, pos, grip = recording.controls_to_end_effectors(controls)``:

1. add end-effector k to every world with ``builder.add_end_effector(w, configs[k], pos[0, k])``;
2. during frame interval t -> t+1 command the constant velocity
   ``v[t] = (pos[t+1] - pos[t]) * fps`` (m/s; :func:`recording.end_effector_velocities`) and the grip
   ``grip[t]`` for all substeps of that interval (``control.set(velocity=v[t][None], grip=grip[t][None])``);
3. substeps: the synthesiser used ``n = ceil((1/fps) / (0.9 * solver.max_stable_dt(max |v|)))``
   substeps of ``dt = 1 / (fps n)`` per frame (also stored in ``ground_truth.json``, which
   identification must not read); any stable dt whose substeps tile 1/fps reproduces the motion.

Frame t of the images shows the state after t frame intervals (frame 0 is the rest state).
"""

from __future__ import annotations

import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .cameras import Camera, intrinsics_matrix, look_at
from .recording import RecordingError, RecordingWriter, end_effector_velocities, quat_angular_velocity
from .scripts import SCRIPTS, ObjectGeometry, _phases, _smooth, run_script

__all__ = ["synthesize", "simulate", "effect_signature", "heldout_difference", "effect_material",
           "default_effect_params", "register", "OBJECT_DEFAULTS", "DEFAULT_SCRIPT", "render_view", "add_depth_noise",
           "camera_ring", "SurfaceEmbedding"]

#: Default material parameters per object (SI: Pa, -, kg/m^3, Pa). They are chosen so that the
#: scripted motion shows them: a soft rubber rope (E / density sets how far the lifted, stretched rope
#: sags and how it sways) and a soft modelling dough whose yield strain (yield_stress / E = 10 %) sets
#: how far it springs back after the squeeze. A stiffer rope only stretches (its sag changes by a
#: fraction of a millimetre with E), and a dough with a yield strain of 1-3 % springs back too little
#: for any camera to tell its yield stress.
OBJECT_DEFAULTS: Dict[str, dict] = {
    "rope": {"E": 5.0e4, "nu": 0.3, "density": 1100.0, "yield_stress": None},
    "dough": {"E": 2.0e4, "nu": 0.3, "density": 1200.0, "yield_stress": 2.0e3},
    "block": {"E": 6.0e4, "nu": 0.3, "density": 1000.0, "yield_stress": None},
    "lump": {"E": 2.0e4, "nu": 0.3, "density": 1200.0, "yield_stress": 2.0e3},
}

_ROPE_LENGTH_M, _ROPE_RADIUS_M, _ROPE_GRIPPER_RADIUS_M = 0.30, 0.012, 0.018
_DOUGH_SIZE_M = (0.05, 0.05, 0.045)
_BLOCK_SIZE_M = (0.04, 0.04, 0.04)
_PLATE_HALF_M = (0.006, 0.035, 0.028)
#: The lump: the part above the table (z >= 0) of the ellipsoid of these semi-axes centred this far below it.
#: (8.4 x 6.8 x 3.8 cm, 111 cm^3, the dough's volume; a flatter lump, 3.0 cm high, measured 3.6 cells across
#: its tapered rim at 5 mm, and the doctor refined its grid to 2.5 mm, 8x the particles.)
_LUMP_SEMI_AXES_M = (0.042, 0.034, 0.040)
_LUMP_CENTRE_Z_M = -0.002
_TABLE_HALF_M = 0.6


# ----------------------------------------------------------------------------------------------
# scene and script
# ----------------------------------------------------------------------------------------------


def _rope_script(T: int):
    """End-effector positions [T, 2, 3] m and grip [T, 2] for the rope: hold, lift + stretch, hold (the
    taut rope sways and sags by an amount set by E / density), lower back to the table and slacken,
    release (grippers open and lift away), settle.

    The rope is put down before it is released: a rope dropped from the air bounces chaotically on
    the table, and a fit would then chase that chaos instead of the material.
    """
    L, r = _ROPE_LENGTH_M, _ROPE_RADIUS_M
    # sphere centres above the rope's top: a closed sphere carries the upper 2/3 of the rope's ends,
    # and on release it lifts away from the rope without dragging it
    x0, zc = L / 2 - 0.015, 2 * r + 0.002
    start = np.array([[-x0, 0.0, zc], [x0, 0.0, zc]])
    _, g0, g1, g2, g3, g4, _ = _phases(T, [0.07, 0.28, 0.25, 0.2, 0.07, 0.13])
    t = np.arange(T, dtype=np.float64)
    up = _smooth((t - g0) / max(g1 - g0, 1)) - _smooth((t - g2) / max(g3 - g2, 1))
    lift = 0.08 * up
    stretch = 0.015 * up
    away = 0.04 * _smooth((t - g3) / max(g4 - g3, 1))
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 0] -= stretch
    pos[:, 1, 0] += stretch
    pos[:, :, 2] += (lift + away)[:, None]
    grip = np.ones((T, 2), np.int32)
    grip[g3:] = 0
    return pos, grip


def _dough_script(T: int):
    """Plate positions [T, 2, 3] m and grip [T, 2] (always open: pushing) for the dough squeeze."""
    sx = _DOUGH_SIZE_M[0] / 2 + _PLATE_HALF_M[0] + 0.002
    start = np.array([[-sx, 0.0, _PLATE_HALF_M[2] + 0.003], [sx, 0.0, _PLATE_HALF_M[2] + 0.003]])
    _, g0, g1, g2, g3, _ = _phases(T, [0.1, 0.35, 0.1, 0.15, 0.3])
    t = np.arange(T, dtype=np.float64)
    squeeze = 0.012 * _smooth((t - g0) / max(g1 - g0, 1)) - 0.03 * _smooth((t - g2) / max(g3 - g2, 1))
    pos = np.repeat(start[None], T, axis=0)
    pos[:, 0, 0] += squeeze
    pos[:, 1, 0] -= squeeze
    return pos, np.zeros((T, 2), np.int32)


def _lump_base_semi_axes() -> Tuple[float, float]:
    """Semi-axes (m) along x and y of the lump's footprint, where its ellipsoid meets the table."""
    a, b, c = _LUMP_SEMI_AXES_M
    s = math.sqrt(1.0 - (_LUMP_CENTRE_Z_M / c) ** 2)
    return a * s, b * s


def _lump_size() -> Tuple[float, float, float]:
    bx, by = _lump_base_semi_axes()
    return (2 * bx, 2 * by, _LUMP_SEMI_AXES_M[2] + _LUMP_CENTRE_Z_M)


def inside_lump(x: np.ndarray) -> np.ndarray:
    """Whether points ``x`` [N, 3] (m) lie in the lump (inside its ellipsoid and not below the table)."""
    x = np.asarray(x, np.float64)
    q = (x - [0.0, 0.0, _LUMP_CENTRE_Z_M]) / np.asarray(_LUMP_SEMI_AXES_M)
    return (np.einsum("ij,ij->i", q, q) <= 1.0) & (x[:, 2] >= 0.0)


_GEOMETRY = {"rope": ObjectGeometry((_ROPE_LENGTH_M, 2 * _ROPE_RADIUS_M, 2 * _ROPE_RADIUS_M)),
             "dough": ObjectGeometry(_DOUGH_SIZE_M), "block": ObjectGeometry(_BLOCK_SIZE_M),
             "lump": ObjectGeometry(_lump_size())}

#: Script used when none is named (``--script default``): the historic rope / dough scripts.
DEFAULT_SCRIPT = {"rope": "default", "dough": "default", "block": "press-release", "lump": "press-release"}


def _script(obj: str, script: str, T: int, dx: float = 0.01):
    """(positions [T, K, 3], grip [T, K], end-effector kwargs, grid (lower, upper), orientations [T, K, 4] (x, y, z,
    w): the identity where the end-effectors never turn)."""
    if script == "default" and obj in ("rope", "dough"):
        if obj == "rope":
            pos, grip = _rope_script(T)
            ees = [{"shape": "sphere", "radius": _ROPE_GRIPPER_RADIUS_M}] * 2
            return pos, grip, ees, ((-0.25, -0.08, -0.04), (0.25, 0.08, 0.17)), _identity_quats(pos)
        pos, grip = _dough_script(T)
        ees = [{"shape": "box", "half_extents": _PLATE_HALF_M}] * 2
        return pos, grip, ees, ((-0.12, -0.09, -0.04), (0.12, 0.09, 0.12)), _identity_quats(pos)
    name = DEFAULT_SCRIPT[obj] if script == "default" else script
    r = run_script(name, T, _GEOMETRY[obj])
    lo, hi = np.array(r.reach[0], float), np.array(r.reach[1], float)
    for k, e in enumerate(r.end_effectors):
        ext = np.full(3, e["radius"]) if e["shape"] == "sphere" else np.asarray(e["half_extents"], float)
        if r.orientations is not None and e["shape"] != "sphere":    # a turning box reaches its corners' sphere
            ext = np.full(3, float(np.linalg.norm(ext)))
        lo = np.minimum(lo, r.positions[:, k].min(0) - ext)
        hi = np.maximum(hi, r.positions[:, k].max(0) + ext)
    m = max(0.03, 3.5 * dx)                            # the grid's boundary cells are not usable
    lo, hi = lo - m, hi + m
    c, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 4 * dx)
    lo, hi = c - half, c + half
    lo[2] = min(-0.04, -2 * dx)
    lo = np.round(lo, 4)
    lo[:2] -= grid_shift_off_faces(lo, r.positions, r.end_effectors, dx)
    return (r.positions, r.grip, r.end_effectors, (tuple(np.round(lo, 4)), tuple(np.round(hi, 4))),
            r.quaternions())


def _identity_quats(pos) -> np.ndarray:
    return np.tile([0.0, 0.0, 0.0, 1.0], (*np.shape(pos)[:2], 1))




#: A box end-effector face within this fraction of a cell of a grid node plane lies "on" it (see
#: :func:`grid_shift_off_faces`); one that does so in more than :data:`_ON_NODE_SHARE` of the frames is moved off.
_ON_NODE_CELLS = 0.02
_ON_NODE_SHARE = 0.1


def grid_shift_off_faces(lower, positions, end_effectors, dx: float, axes=(0, 1)) -> np.ndarray:
    """Shift [len(axes)] (m, each 0 or a fraction of ``dx``) to subtract from the grid's ``lower`` corner along
    ``axes`` so that no face of a box end-effector (``end_effectors``: script kwargs, axis-aligned, centres
    ``positions`` [T, K, 3] m) lies on a plane of grid nodes in more than a tenth of the frames.

    Which nodes a box carries is decided by the sign of their distance to it; a node on a face is inside or
    outside by the rounding of its float32 coordinates, which changes with the grid's origin. A synthetic
    recording made on such a knife-edge shows a whole layer of nodes held or free by accident: the block's box
    clamps (inner faces at +-1 cm, on the 1 cm grid's nodes) gave a lifted block whose middle sat 3.5 mm higher
    on the synthesiser's grid than on the same grid moved by one whole cell, which the doctor fitted as a
    stiffness field on a recording with no effect (benchmarks/RESULTS.md, session 33). The shift is the first of
    a quarter, a half, three quarters of a cell (then the eighths) that leaves every face off the nodes in at
    least 90 % of the frames (else the one that leaves the fewest on them); the table's axis (z) is left alone,
    its node layer being aligned with the table on purpose."""
    lower = np.asarray(lower, float)
    pos = np.asarray(positions, float)
    faces = [[] for _ in axes]
    for k, e in enumerate(end_effectors):
        if e.get("shape") != "box":
            continue
        h = np.asarray(e["half_extents"], float)
        for i, a in enumerate(axes):
            faces[i] += [pos[:, k, a] - h[a], pos[:, k, a] + h[a]]
    out = np.zeros(len(axes))
    for i, a in enumerate(axes):
        if not faces[i]:
            continue
        F = np.stack(faces[i])                              # [faces, T]

        def worst(s):
            u = (F - (lower[a] - s * dx)) / dx
            return float(np.max(np.mean(np.abs(u - np.rint(u)) < _ON_NODE_CELLS, axis=1)))

        if worst(0.0) <= _ON_NODE_SHARE:
            continue
        shifts = (0.25, 0.5, 0.75, 0.125, 0.375, 0.625, 0.875)
        ok = [s for s in shifts if worst(s) <= _ON_NODE_SHARE]
        out[i] = dx * (ok[0] if ok else min(shifts, key=worst))
    return out


def _build(obj: str, material, *, dx: float, ppc: float, table_friction: float, ee_friction: float, seed: int,
           device, controls_pos, ee_kwargs, grid_box, controls_quat=None, grid_offset=(0.0, 0.0, 0.0),
           jitter: float = 0.0):
    from empm_gym.sim import (EndEffectorConfig, GridConfig, ModelBuilder, TableConfig, sample_box,
                              sample_cylinder)

    grid = GridConfig(lower=grid_box[0], upper=grid_box[1], dx=dx).shifted(grid_offset)
    if not (math.isfinite(jitter) and 0.0 <= jitter <= 1.0):
        raise ValueError(f"jitter must lie in [0, 1] (a fraction of the particle spacing), got {jitter!r}")
    if obj == "rope":
        L, r = _ROPE_LENGTH_M, _ROPE_RADIUS_M
        x, vol = sample_cylinder((-L / 2, 0, r), (L / 2, 0, r), r, dx, ppc, seed=seed, jitter=jitter)
    elif obj == "lump":  # the lattice over its bounding box, the points inside kept (each its lattice cell's volume)
        sx, sy, sz = _GEOMETRY[obj].size
        x, vol = sample_box((-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz), dx, ppc, seed=seed, jitter=jitter)
        keep = inside_lump(x)
        x, vol = x[keep], vol[keep]
    else:
        sx, sy, sz = _GEOMETRY[obj].size
        x, vol = sample_box((-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz), dx, ppc, seed=seed, jitter=jitter)
    ee = [EndEffectorConfig(friction=ee_friction, **kw) for kw in ee_kwargs]
    b = ModelBuilder(grid, gravity=(0, 0, -9.81), table=TableConfig(height=0.0, friction=table_friction))
    w = b.add_world(material)
    b.add_particles(w, x, vol)
    for k, cfg in enumerate(ee):
        b.add_end_effector(w, cfg, controls_pos[0, k], (0, 0, 0, 1) if controls_quat is None else controls_quat[0, k])
    return b.finalize(device), ee, grid


def default_effect_params(effect: str, material) -> Dict[str, float]:
    """Parameters of ``effect`` when ``--effect NAME`` is given without ``--effect-param`` (SI), chosen so
    that its signature is clear on its natural script (see docs/EFFECTS.md): a yield stress of 5 % of E
    (press-release leaves a dent), eta = 50 Pa s (squeeze-ring), table friction 0.05 (push-slide),
    grip friction 1 (squeeze-lift: slips unless it grasps the whole weight), a stiffness slope of 1 along
    the long axis (pull-apart), fracture from 20 % stretch (pull-apart pulls to 80 %)."""
    from empm_gym.sim.effects import EFFECTS

    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; known: none, {', '.join(EFFECTS)}")
    return {
        "plasticity": {"yield_stress": 0.05 * material.E},
        "viscosity": {"viscosity": 50.0},
        "table_friction": {"friction": 0.05},
        "gripper_slip": {"grip_friction": 1.0},
        "heterogeneous_stiffness": {"stiffness_slope_1": 1.0},
        "fracture": {"fracture_strain": 0.2, "fracture_softening": 0.05},
    }[effect]


def effect_material(object: str, effect: str, effect_params: Optional[Dict[str, float]] = None, *,
                    base=None, E: Optional[float] = None, nu: Optional[float] = None,
                    density: Optional[float] = None):
    """(MaterialConfig, effects list for ground_truth.json): the base model of ``object`` (elastic, table
    friction 0.5, rigid grip; ``base`` replaces it) with ``effect`` ("none" or a name of
    :data:`empm_gym.sim.effects.EFFECTS`) as its only effect, its parameters being the defaults of
    :func:`default_effect_params` updated by ``effect_params`` (validated against the registry)."""
    from empm_gym.sim import MaterialConfig
    from empm_gym.sim.effects import BASE_TABLE_FRICTION, EFFECTS

    if object not in OBJECT_DEFAULTS:
        raise ValueError(f"object must be one of {sorted(OBJECT_DEFAULTS)}, got {object!r}")
    if base is None:
        d = {k: v for k, v in OBJECT_DEFAULTS[object].items() if k != "yield_stress"}
        base = MaterialConfig(**d, params={"friction": BASE_TABLE_FRICTION})
    kw = {k: float(v) for k, v in (("E", E), ("nu", nu), ("density", density)) if v is not None}
    if kw:
        base = base.replace(**kw)
    effect_params = dict(effect_params or {})
    if effect in (None, "none"):
        if effect_params:
            raise ValueError(f"--effect none takes no effect parameters, got {', '.join(effect_params)}")
        return base, []
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; known: none, {', '.join(EFFECTS)}")
    eff = EFFECTS[effect]
    params = default_effect_params(effect, base)
    for k, v in effect_params.items():
        if k not in eff.param_names:
            raise ValueError(f"effect {effect!r} has no parameter {k!r}; its parameters: "
                             f"{', '.join(eff.param_names)}")
        params[k] = next(p for p in eff.params if p.name == k).check(v, f"effect {effect}: ")
    for p in eff.params:                               # name every parameter of the effect
        if p.name not in params and p.off is not None:
            params[p.name] = float(p.off)
    params = {p.name: params[p.name] for p in eff.params if p.name in params}
    material = base.replace(**params)
    return material, [{"name": effect, "params": {k: float(v) for k, v in params.items()}}]


def _effect_param_names(effect: str):
    from empm_gym.sim.effects import EFFECTS

    return EFFECTS[effect].param_names


def _effects_of(material) -> List[dict]:
    """ground_truth.json's effects list of a material (table friction only where it differs from 0.5)."""
    out = []
    for n in material.added_effects():
        params = {p: material.get(p) for p in _effect_param_names(n)}
        out.append({"name": n, "params": {k: float(v) for k, v in params.items() if v is not None}})
    return out


def _check_scene_args(object: str, script: str, frames) -> None:
    if object not in OBJECT_DEFAULTS:
        raise ValueError(f"object must be one of {sorted(OBJECT_DEFAULTS)}, got {object!r}")
    if script != "default" and script not in SCRIPTS:
        raise ValueError(f"unknown script {script!r}; known: default, {', '.join(SCRIPTS)}")
    if int(frames) < 2:
        raise ValueError(f"frames must be >= 2, got {frames!r}")


#: The simulators a recording can be made with: our MPM, or the spring-mass family of PhysTwin
#: (:mod:`empm_gym.springmass`), which the doctor's base model is not, as another simulator's output would be.
SIMULATORS = ("mpm", "springmass")
#: Effects the spring-mass simulator can carry (its springs have no yield, rate term beyond their dashpots,
#: damage or gripper slip): the table's friction and a stiffness field (per-spring multipliers).
SPRINGMASS_EFFECTS = ("table_friction", "heterogeneous_stiffness")


#: Particles closer than this many grid cells belong to one piece of the simulated body (:func:`body_parts`):
#: a gap of two cells with no particle in it is one that no MPM interaction bridges and that the cameras see.
PARTED_LINK_CELLS = 2.0


def body_parts(particles: np.ndarray, dx: float, min_frac: float = 0.02) -> Optional[dict]:
    """Whether a simulated body ``particles`` [T, N, 3] (m) comes apart: ``{"pieces": n, "from_frame": t,
    "link_m": l}``, the most connected pieces it is in at any frame (particles closer than
    :data:`PARTED_LINK_CELLS` cells ``dx`` linked; a piece of under ``min_frac`` of the particles is not
    counted) and the first frame in that many, when that is more than at frame 0; None when it never parts.

    The synthesiser's MPM tears a body that a script stretches faster or further than its grid holds together,
    with no fracture in the material: the rope lifted by one end and drawn out (``lift-end`` before session 52,
    dx = 5 mm, 30 frames) parted at its lifted gripper from frame 17 on, on each of seeds 10-18
    (benchmarks/RESULTS.md, session 52). Such a recording shows a tear that its ground truth does not name."""
    from empm_gym.identification.doctor.features import count_pieces

    X = np.asarray(particles, np.float64)
    link = PARTED_LINK_CELLS * float(dx)
    counts = [count_pieces(x, link_m=link, min_frac=min_frac) for x in X]
    most = max(counts)
    if most <= counts[0]:
        return None
    return {"pieces": int(most), "from_frame": int(counts.index(most)), "link_m": link}


def simulate(object: str, material, *, script: str = "default", frames: int = 60, fps: float = 30.0,
             dx: float = 0.01, particles_per_cell: float = 8, table_friction: float = 0.5,
             gripper_friction: float = 0.8, seed: int = 0, device: str = "cpu", progress: bool = False,
             simulator: str = "mpm", springmass_damping: float = 1.0, grid_offset=(0.0, 0.0, 0.0),
             jitter: float = 0.0) -> dict:
    """Run ``script`` on ``object`` of ``material`` without rendering. Returns a dict: ``particles`` [T, N, 3]
    (m, frame t = after t intervals), ``positions`` [T, K, 3], ``grip`` [T, K], ``end_effectors``
    (EndEffectorConfig list), ``grid``, ``model``, ``substeps``, ``dt``, ``volumes`` [N] (m^3). The table
    friction is ``material.params['friction']`` where set, else ``table_friction``.

    ``simulator`` "springmass" runs the body as a spring-mass network instead (see :func:`_simulate_springmass`):
    the MPM's frame-0 particles voxel-downsampled to half a cell, springs of stiffness ``material.E`` (the
    network's Young's modulus, Pa), dashpots of ``springmass_damping`` (Pa s), the same table, friction and
    end-effector motion, a closed gripper holding the particles it touches.

    ``grid_offset`` moves the script's grid by fractions of a cell (:meth:`~empm_gym.sim.GridConfig.shifted`);
    ``jitter`` (in [0, 1]) displaces each particle of the body's lattice uniformly within +-jitter/2 of the
    lattice spacing along each axis (seeded by ``seed``). Both default to the lattice and grid every seed shares;
    with them, seeds differ in the discretisation as real objects do (benchmarks/RESULTS.md, session 56)."""
    from tqdm.auto import tqdm

    from empm_gym.sim import SolverMPM
    from empm_gym.sim.config import end_effector_speed

    _check_scene_args(object, script, frames)
    if simulator not in SIMULATORS:
        raise ValueError(f"simulator must be one of {', '.join(SIMULATORS)}, got {simulator!r}")
    T = int(frames)
    pos, grip, ee_kw, grid_box, quat = _script(object, script, T, dx)
    model, ee_cfgs, grid = _build(object, material, dx=dx, ppc=particles_per_cell, table_friction=table_friction,
                                  ee_friction=gripper_friction, seed=seed, device=device, controls_pos=pos,
                                  ee_kwargs=[dict(kw, gripper=bool(np.any(grip[:, k]))) for k, kw in enumerate(ee_kw)],
                                  grid_box=grid_box, controls_quat=quat, grid_offset=grid_offset, jitter=jitter)
    if simulator == "springmass":
        out = _simulate_springmass(model, material, pos, grip, ee_cfgs, grid, fps=fps, damping=springmass_damping,
                                   table_friction=table_friction, device=device, progress=progress, quat=quat)
        return {**out, "orientations": quat}
    solver = SolverMPM(model)
    vel = end_effector_velocities(pos, fps)
    omega = quat_angular_velocity(quat, fps)
    vmax = end_effector_speed(vel, omega, ee_cfgs)
    n_sub = int(math.ceil((1.0 / fps) / (0.9 * solver.max_stable_dt(vmax))))
    dt = 1.0 / (fps * n_sub)
    s0, s1 = model.state(), model.state()
    ctrl = model.control()
    X = np.zeros((T, model.particle_count, 3), np.float32)
    X[0] = s0.particle_x.numpy()
    for t in tqdm(range(T - 1), desc=f"simulate {object} ({model.particle_count} particles, {n_sub} substeps/frame)",
                  disable=not progress, leave=False):
        ctrl.set(velocity=vel[t][None], omega=omega[t][None], grip=grip[t][None])
        for _ in range(n_sub):
            solver.step(s0, s1, ctrl, dt)
            s0, s1 = s1, s0
        X[t + 1] = s0.particle_x.numpy()
    return {"particles": X, "positions": pos, "orientations": quat, "grip": grip, "end_effectors": ee_cfgs,
            "grid": grid, "model": model, "substeps": n_sub, "dt": dt, "volumes": model.particle_vol.numpy()}


def _simulate_springmass(mpm_model, material, pos, grip, ee_cfgs, grid, *, fps: float, damping: float,
                         table_friction: float, device, progress: bool, quat=None) -> dict:
    """:func:`simulate`'s spring-mass run: the MPM model's frame-0 particles and volumes become a network at half
    a grid cell (:func:`empm_gym.springmass.model.model_from_body`), stiffness E, dashpots ``damping``; the
    table friction is the material's where set; a stiffness field E exp(a . u) (u: the body's principal
    coordinates, :func:`empm_gym.sim.model.principal_coords`) multiplies each spring by its value at the
    spring's midpoint. Any other effect raises ValueError: the spring-mass family has no such term."""
    from tqdm.auto import tqdm

    from empm_gym.sim.model import principal_coords
    from empm_gym.springmass import SpringMassConfig, SpringMassSim, model_from_body

    other = [e for e in material.effects() if e not in SPRINGMASS_EFFECTS]
    if other:
        raise ValueError(f"the spring-mass simulator cannot carry {', '.join(other)} (only "
                         f"{', '.join(SPRINGMASS_EFFECTS)}); make that recording with simulator='mpm'")
    if material.get("friction") is not None:
        table_friction = float(material.get("friction"))
    spacing = 0.5 * grid.dx
    cfg = SpringMassConfig(stiffness=float(material.E), damping=float(damping), spacing=spacing)
    sm = model_from_body(mpm_model.state().particle_x.numpy(), mpm_model.particle_vol.numpy(),
                         density=float(material.density), config=cfg, spacing=spacing, device=device)
    slope = np.array([material.get(f"stiffness_slope_{i}") or 0.0 for i in (1, 2, 3)], np.float64)
    log_scale = None
    if np.any(slope != 0.0):
        u = principal_coords(sm.x0)
        i, j = sm.springs_np[:, 0], sm.springs_np[:, 1]
        log_scale = 0.5 * (u[i] + u[j]) @ slope
        sm.set_params(float(material.E), float(damping), log_scale)
    sim = SpringMassSim(sm, fps=fps, ee_configs=ee_cfgs, ee_positions=pos, ee_orientations=quat, ee_grip=grip,
                        table_height=0.0, table_friction=table_friction)
    T = len(pos)
    n_sub, dt = sim.substeps(float(material.E), float(damping), T,
                             log_scale_max=0.0 if log_scale is None else float(log_scale.max()))
    bar = tqdm(total=T - 1, desc=f"simulate spring-mass ({sm.particle_count} particles, {sm.spring_count} springs, "
               f"{n_sub} substeps/frame)", disable=not progress, leave=False)
    try:
        X = sim.run(T, substeps=n_sub, progress=lambda t: bar.update(1))
    finally:
        bar.close()
    return {"particles": X.astype(np.float32), "positions": pos, "grip": grip, "end_effectors": ee_cfgs,
            "grid": grid, "model": sm, "substeps": n_sub, "dt": dt, "volumes": sm.mass / float(material.density)}


# ----------------------------------------------------------------------------------------------
# dense surface embedded in the particles
# ----------------------------------------------------------------------------------------------


def effect_signature(object: str, script: str, effect: str, *, frames: int = 30, held_out: float = 0.3,
                     effect_params: Optional[Dict[str, float]] = None,
                     base_params: Optional[Dict[str, float]] = None, material=None, **kwargs) -> float:
    """How much a recording can show of ``effect``: the mean Chamfer distance [m], over the last ``held_out``
    of the frames (what a fit holds out), between the particles of ``object`` run through ``script`` with the
    effect (its defaults, updated by ``effect_params``) and without it (``simulate`` kwargs pass on). Below the
    depth noise (about 1 mm) the effect is practically not in the recording. ``base_params`` (E, nu, density)
    replace the object's base material, as :func:`synthesize`'s arguments of those names do; ``material`` (a
    MaterialConfig, with another effect, say) is the base the effect is added to, as :func:`synthesize`'s is. For
    benchmarks and tests: it needs the true material."""
    if effect in (None, "none"):
        return 0.0
    a, b = [simulate(object, effect_material(object, e, p, base=material, **(base_params or {}))[0], script=script,
                     frames=frames, **kwargs)["particles"]
            for e, p in (("none", None), (effect, effect_params))]
    return heldout_difference(a, b, held_out)


def heldout_difference(a: np.ndarray, b: np.ndarray, held_out: float = 0.3) -> float:
    """The mean Chamfer distance [m] between two simulations' particles ``a``, ``b`` [T, N, 3] over the last
    ``held_out`` of the frames (what a fit holds out): :func:`effect_signature`'s measure."""
    from empm_gym.identification.losses import chamfer_numpy

    frames = min(len(a), len(b))
    first = min(frames - 1, int(round((1.0 - held_out) * frames)))
    return float(np.mean([chamfer_numpy(a[t], b[t]) for t in range(first, frames)]))


def _rope_surface(spacing: float):
    L, r = _ROPE_LENGTH_M, _ROPE_RADIUS_M
    nc = max(8, int(math.ceil(2 * math.pi * r / spacing)))
    nl = max(2, int(math.ceil(L / spacing)))
    th = (np.arange(nc) + 0.5) * 2 * np.pi / nc
    xs = -L / 2 + (np.arange(nl) + 0.5) * L / nl
    X, TH = np.meshgrid(xs, th, indexing="ij")
    side_n = np.stack([np.zeros_like(X), np.cos(TH), np.sin(TH)], -1).reshape(-1, 3)
    side_p = np.stack([X, r * np.cos(TH), r + r * np.sin(TH)], -1).reshape(-1, 3)
    caps_p, caps_n = [], []
    for sgn in (-1.0, 1.0):
        for rr in np.arange(spacing / 2, r, spacing):
            m = max(6, int(math.ceil(2 * math.pi * rr / spacing)))
            a = (np.arange(m) + 0.5) * 2 * np.pi / m
            caps_p.append(np.stack([np.full(m, sgn * L / 2), rr * np.cos(a), r + rr * np.sin(a)], -1))
            caps_n.append(np.tile([sgn, 0.0, 0.0], (m, 1)))
    p = np.concatenate([side_p] + caps_p)
    n = np.concatenate([side_n] + caps_n)
    # texture coordinate along the rope for coloured stripes
    u = (p[:, 0] + L / 2) / L
    return p, n, u


def _box_surface(size, spacing: float):
    sx, sy, sz = size
    lo, hi = np.array([-sx / 2, -sy / 2, 0.0]), np.array([sx / 2, sy / 2, sz])
    P, N = [], []
    for ax in range(3):
        o = [a for a in range(3) if a != ax]
        n1 = max(2, int(math.ceil((hi[o[0]] - lo[o[0]]) / spacing)))
        n2 = max(2, int(math.ceil((hi[o[1]] - lo[o[1]]) / spacing)))
        a = lo[o[0]] + (np.arange(n1) + 0.5) * (hi[o[0]] - lo[o[0]]) / n1
        b = lo[o[1]] + (np.arange(n2) + 0.5) * (hi[o[1]] - lo[o[1]]) / n2
        A, B = np.meshgrid(a, b, indexing="ij")
        for side, val in ((-1.0, lo[ax]), (1.0, hi[ax])):
            p = np.zeros((A.size, 3))
            p[:, o[0]], p[:, o[1]], p[:, ax] = A.ravel(), B.ravel(), val
            n = np.zeros_like(p)
            n[:, ax] = side
            P.append(p)
            N.append(n)
    p = np.concatenate(P)
    return p, np.concatenate(N), None


def _lump_surface(spacing: float):
    """Points [S, 3] (m) about ``spacing`` apart on the lump's surface, with outward unit normals: its
    ellipsoid above the table (a Fibonacci lattice on the unit sphere, stretched) and its flat footprint."""
    a, b, c = _LUMP_SEMI_AXES_M
    p = 1.6075  # Knud Thomsen's approximation of an ellipsoid's area (within about 1 %)
    area = 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3.0) ** (1.0 / p)
    n = int(math.ceil(area / spacing ** 2))
    i = np.arange(n) + 0.5
    w = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - w ** 2)
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    u = np.stack([r * np.cos(phi), r * np.sin(phi), w], -1)
    pts = u * [a, b, c] + [0.0, 0.0, _LUMP_CENTRE_Z_M]
    nrm = u / [a, b, c]
    keep = pts[:, 2] >= 0.0
    pts, nrm = pts[keep], nrm[keep]
    bx, by = _lump_base_semi_axes()
    gx = np.arange(-bx + spacing / 2, bx, spacing)
    gy = np.arange(-by + spacing / 2, by, spacing)
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    inside = (X / bx) ** 2 + (Y / by) ** 2 <= 1.0
    base = np.stack([X[inside], Y[inside], np.zeros(int(inside.sum()))], -1)
    pts = np.concatenate([pts, base])
    nrm = np.concatenate([nrm, np.tile([0.0, 0.0, -1.0], (len(base), 1))])
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True), None


class SurfaceEmbedding:
    """Dense surface points carried by simulation particles through a local weighted affine fit.

    For each surface point p0 (frame 0) with neighbour particles x_i0 and Gaussian weights w_i, the
    current position is c + A (p0 - c0) where c0, c are the weighted neighbour centroids and A the
    weighted least-squares map of the neighbour offsets from rest to now; normals follow A^-T.
    """

    def __init__(self, surface0: np.ndarray, normals0: np.ndarray, particles0: np.ndarray, *, k: int = 12,
                 h: Optional[float] = None):
        from scipy.spatial import cKDTree

        self.p0 = np.asarray(surface0, np.float64)
        self.n0 = np.asarray(normals0, np.float64)
        x0 = np.asarray(particles0, np.float64)
        dist, idx = cKDTree(x0).query(self.p0, k=k)
        h = h or float(np.median(dist[:, 0])) * 2.0 + 1e-9
        w = np.exp(-(dist / h) ** 2)
        self.w = w / w.sum(1, keepdims=True)
        self.idx = idx
        nb = x0[idx]                                     # [S, k, 3]
        self.c0 = np.einsum("sk,skd->sd", self.w, nb)
        r0 = nb - self.c0[:, None]
        M = np.einsum("sk,ski,skj->sij", self.w, r0, r0)
        tr = np.trace(M, axis1=1, axis2=2)[:, None, None]
        self.Minv = np.linalg.inv(M + 1e-10 * tr * np.eye(3))
        self.r0 = r0
        self.off0 = self.p0 - self.c0

    def deform(self, particles: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Surface points [S, 3] (m) and unit normals [S, 3] for the current particle positions [N, 3] (m)."""
        nb = np.asarray(particles, np.float64)[self.idx]
        c = np.einsum("sk,skd->sd", self.w, nb)
        B = np.einsum("sk,ski,skj->sij", self.w, nb - c[:, None], self.r0)
        A = B @ self.Minv
        p = c + np.einsum("sij,sj->si", A, self.off0)
        det = np.linalg.det(A)
        ok = np.abs(det) > 1e-6
        n = self.n0.copy()
        if np.any(ok):
            Ainv_T = np.linalg.inv(A[ok]).transpose(0, 2, 1)
            n[ok] = np.einsum("sij,sj->si", Ainv_T, self.n0[ok])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        return p, n


# ----------------------------------------------------------------------------------------------
# rendering
# ----------------------------------------------------------------------------------------------

_LIGHT = np.array([0.3, -0.4, 1.0]) / np.linalg.norm([0.3, -0.4, 1.0])


def _shade(albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    lam = np.clip(normal @ _LIGHT, 0.0, 1.0)
    return albedo * (0.35 + 0.65 * lam)[..., None]


def camera_ring(n: int, *, width: int = 848, height: int = 480, fx: float = 420.0, fy: float = 420.0,
                distance_m: float = 0.55, elevation_deg: float = 40.0, target=(0.0, 0.0, 0.03),
                azimuth0_deg: float = 30.0) -> List[Camera]:
    """``n`` cameras evenly spaced in azimuth around ``target`` (m) at ``distance_m`` and ``elevation_deg``."""
    K = intrinsics_matrix(fx, fy, (width - 1) / 2.0, (height - 1) / 2.0)
    cams = []
    el = math.radians(elevation_deg)
    for i in range(n):
        az = math.radians(azimuth0_deg + 360.0 * i / n)
        eye = np.asarray(target) + distance_m * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                          math.sin(el)])
        cams.append(Camera(K, look_at(eye, target), width, height, name=str(i)))
    return cams


class _StaticView:
    """Per-camera quantities that do not change over frames: rays, table depth, colour and incidence."""

    def __init__(self, cam: Camera):
        self.cam = cam
        self.o, d = cam.world_rays()                      # d: world direction with camera z = 1
        self.d = d
        self.dn = d / np.linalg.norm(d, axis=-1, keepdims=True)
        H, W = cam.height, cam.width
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -self.o[2] / d[..., 2]                     # depth z along the optical axis to the plane z = 0
        hit = (s > 0) & np.isfinite(s)
        P = self.o + s[..., None] * d
        hit &= (np.abs(P[..., 0]) < _TABLE_HALF_M) & (np.abs(P[..., 1]) < _TABLE_HALF_M)
        self.table_depth = np.where(hit, s, np.inf)
        self.table_cos = np.abs(self.dn[..., 2])
        checker = ((np.floor(P[..., 0] / 0.05) + np.floor(P[..., 1] / 0.05)) % 2 == 0)
        albedo = np.where(checker[..., None], [0.62, 0.52, 0.40], [0.55, 0.45, 0.34])
        self.table_color = np.where(hit[..., None], _shade(albedo, np.array([0.0, 0.0, 1.0])), [0.18, 0.18, 0.2])
        self.H, self.W = H, W


def _ee_hits(view: _StaticView, shape: str, centre, rot: np.ndarray, radius: float, half_extents):
    """Depth (inf = miss) and world normals of one end-effector over the pixels of its projected bounding box."""
    cam = view.cam
    ext = radius if shape == "sphere" else float(np.linalg.norm(half_extents))
    corners = np.asarray(centre) + ext * np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
    rc, z = cam.project(corners)
    if np.all(z <= 0):
        return None
    if np.any(z <= 0):
        r0, r1, c0, c1 = 0, view.H, 0, view.W
    else:
        r0 = int(max(0, np.floor(rc[:, 0].min()) - 1))
        r1 = int(min(view.H, np.ceil(rc[:, 0].max()) + 2))
        c0 = int(max(0, np.floor(rc[:, 1].min()) - 1))
        c1 = int(min(view.W, np.ceil(rc[:, 1].max()) + 2))
    if r0 >= r1 or c0 >= c1:
        return None
    d = view.d[r0:r1, c0:c1]
    o = view.o
    if shape == "sphere":
        oc = o - centre
        a = np.einsum("ijk,ijk->ij", d, d)
        b = 2 * d @ oc
        c = oc @ oc - radius**2
        disc = b * b - 4 * a * c
        s = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        s = np.where(s > 0, s, np.inf)
        n = o + np.where(np.isfinite(s), s, 0.0)[..., None] * d - centre
        n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    else:  # box (and capsule rendered as its bounding box is not needed here)
        he = np.asarray(half_extents, float)
        ol = rot.T @ (o - centre)
        dl = d @ rot
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-he - ol) / dl
            t2 = (he - ol) / dl
        tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
        tmin = np.where(np.isnan(tmin), -np.inf, tmin)
        tmax = np.where(np.isnan(tmax), np.inf, tmax)
        enter = tmin.max(-1)
        ax = tmin.argmax(-1)
        exit_ = tmax.min(-1)
        s = np.where((enter <= exit_) & (enter > 0), enter, np.inf)
        nl = np.zeros(d.shape)
        sign = -np.sign(np.take_along_axis(dl, ax[..., None], -1))[..., 0]
        np.put_along_axis(nl, ax[..., None], sign[..., None], -1)
        n = nl @ rot.T
    return (r0, r1, c0, c1), s, n


def _quat_to_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


#: How far from its disc's centre (in pixel widths at the centre's depth) the ray through the pixel under the
#: centre may meet the disc's tangent plane and still be drawn (:func:`render_view` with ``tangent``): the ray
#: passes within 0.71 pixel of the centre, farther along a plane inclined to it (2 allows 69 degrees).
_CENTRE_REACH_PX = 2.0


def render_view(view: _StaticView, surf_p: np.ndarray, surf_n: np.ndarray, surf_albedo: np.ndarray,
                splat_radius_m: float, ees: List[dict], tangent: bool = False):
    """Noise-free render of one camera: depth [H, W] m (inf = nothing), colour [H, W, 3] in [0, 1],
    label [H, W] (-1 background, 0 table, 1 object, 2 + k end-effector k), |cos| of the incidence angle.

    The object's surface points are drawn as z-buffered discs of radius ``splat_radius_m``. By default each
    disc covers a circle of pixels at its centre's depth (at least the pixel under its centre): the nearest disc
    wins, so every face inclined to the camera comes out 0.3-0.8 mm too near and the silhouette a fraction of a
    pixel too wide. ``tangent`` draws each disc in the point's tangent plane instead: a pixel's depth is where
    its ray meets the disc, and a pixel whose ray misses every disc is not the object's (faces on their true
    depth; benchmarks/RESULTS.md, session 41). Where a disc is narrower than a pixel (a small object seen from
    afar) the ray through the pixel under its centre may pass beside it: that pixel is drawn where the ray meets
    the disc's plane, within :data:`_CENTRE_REACH_PX` pixels' width of the centre, so that, as with flat
    discs, every disc covers at least that pixel (a 4 cm block at 64 x 48 px vanished without it)."""
    cam = view.cam
    depth = view.table_depth.copy()
    color = view.table_color.copy()
    label = np.where(np.isfinite(depth), 0, -1).astype(np.int16)
    cosv = view.table_cos.copy()
    for k, e in enumerate(ees):
        hit = _ee_hits(view, e["shape"], e["pos"], e["rot"], e.get("radius", 0.0), e.get("half_extents"))
        if hit is None:
            continue
        (r0, r1, c0, c1), s, n = hit
        win = (slice(r0, r1), slice(c0, c1))
        closer = s < depth[win]
        depth[win] = np.where(closer, s, depth[win])
        col = _shade(np.array([0.55, 0.57, 0.62]), n)
        color[win] = np.where(closer[..., None], col, color[win])
        label[win] = np.where(closer, 2 + k, label[win])
        cosv[win] = np.where(closer, np.abs(np.einsum("ijk,ijk->ij", n, view.dn[win])), cosv[win])
    # object: z-buffered discs
    rc, z = cam.project(surf_p)
    view_dir = surf_p - cam.position
    front = np.einsum("ij,ij->i", surf_n, view_dir) < 0
    ok = front & (z > 0.05)
    rc, z, idx = rc[ok], z[ok], np.nonzero(ok)[0]
    if tangent:
        p_ok, n_ok = surf_p[ok], surf_n[ok]
        n_dot_po = np.einsum("ij,ij->i", n_ok, p_ok - cam.position)   # < 0: the camera is on the normal's side
    rpx = np.maximum(cam.K[0, 0] * splat_radius_m / z, 0.75)
    R = int(np.ceil(rpx.max())) if len(rpx) else 0
    rows_c = np.round(rc[:, 0]).astype(np.int64)
    cols_c = np.round(rc[:, 1]).astype(np.int64)
    pix, zz, ii = [], [], []
    for dr in range(-R, R + 1):
        for dc in range(-R, R + 1):
            rr, cc = rows_c + dr, cols_c + dc
            m = (rr >= 0) & (rr < view.H) & (cc >= 0) & (cc < view.W)
            if tangent:  # where the pixel's ray meets the disc (camera z = 1: s is the pixel's depth)
                k = np.nonzero(m)[0]
                d = view.d[rr[k], cc[k]]
                den = np.einsum("ij,ij->i", n_ok[k], d)
                with np.errstate(divide="ignore", invalid="ignore"):
                    s = n_dot_po[k] / den
                q = cam.position + s[:, None] * d - p_ok[k]
                reach2 = splat_radius_m**2
                if dr == 0 and dc == 0:  # the pixel under the centre: its ray may pass beside a disc narrower
                    reach2 = np.maximum(reach2, (_CENTRE_REACH_PX * z[k] / cam.K[0, 0]) ** 2)  # than a pixel
                hit = (den < 0) & (s > 0.05) & (np.einsum("ij,ij->i", q, q) <= reach2)
                k, s = k[hit], s[hit]
            else:
                k = np.nonzero(m & ((rr - rc[:, 0]) ** 2 + (cc - rc[:, 1]) ** 2 <= rpx**2))[0]
                s = z[k]
            pix.append(rr[k] * view.W + cc[k])
            zz.append(s)
            ii.append(idx[k])
    if pix:
        pix, zz, ii = np.concatenate(pix), np.concatenate(zz), np.concatenate(ii)
        order = np.lexsort((zz, pix))
        pix, zz, ii = pix[order], zz[order], ii[order]
        first = np.ones(len(pix), bool)
        first[1:] = pix[1:] != pix[:-1]
        pix, zz, ii = pix[first], zz[first], ii[first]
        flat_d = depth.reshape(-1)
        closer = zz < flat_d[pix]
        pix, zz, ii = pix[closer], zz[closer], ii[closer]
        flat_d[pix] = zz
        color.reshape(-1, 3)[pix] = _shade(surf_albedo[ii], surf_n[ii])
        label.reshape(-1)[pix] = 1
        cosv.reshape(-1)[pix] = np.abs(np.einsum("ij,ij->i", surf_n[ii], view.dn.reshape(-1, 3)[pix]))
    return depth, color, label, cosv


def add_depth_noise(depth: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator, *,
                    sigma_m: float = 1.5e-3, ref_depth_m: float = 0.5, edge_jump_m: float = 0.01,
                    edge_drop: float = 0.6, grazing_cos: float = 0.25, random_drop: float = 0.003,
                    min_depth_m: float = 0.2, max_depth_m: float = 1.5) -> np.ndarray:
    """Sensor-like depth (m, 0 = missing) from a clean depth [H, W] (m, inf = nothing).

    Gaussian noise with std ``sigma_m * (z / ref_depth_m)^2``; dropped with probability ``edge_drop``
    where a 4-neighbour's depth differs by more than ``edge_jump_m``; dropped with probability rising
    to 1 as |cos| of the incidence falls from ``grazing_cos`` to 0.4 of it; ``random_drop`` elsewhere;
    nothing outside [min_depth_m, max_depth_m]. Quantisation happens when written (depth units).
    """
    z = np.where(np.isfinite(depth), depth, 0.0)
    zf = np.where(np.isfinite(depth), depth, 1e3)
    jump = np.zeros(z.shape, bool)
    for ax in (0, 1):
        dz = np.abs(np.diff(zf, axis=ax)) > edge_jump_m
        if ax == 0:
            jump[1:] |= dz
            jump[:-1] |= dz
        else:
            jump[:, 1:] |= dz
            jump[:, :-1] |= dz
    u = rng.random(z.shape)
    p_graze = np.clip((grazing_cos - cos_incidence) / (0.6 * grazing_cos), 0.0, 1.0)
    drop = (jump & (u < edge_drop)) | (rng.random(z.shape) < p_graze) | (rng.random(z.shape) < random_drop)
    noisy = z + rng.standard_normal(z.shape) * sigma_m * (z / ref_depth_m) ** 2
    valid = (z > 0) & ~drop & (noisy >= min_depth_m) & (noisy <= max_depth_m)
    return np.where(valid, noisy, 0.0)


def _finite_nonnegative(named_values) -> None:
    """ValueError naming the first of ``(name, value)`` that is not a finite value >= 0."""
    for name, v in named_values:
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"{name} must be a finite value >= 0, got {v!r}")


def sensor_errors(cameras: Sequence[Camera], calibration_error: Sequence[float] = (0.0, 0.0),
                  depth_bias: float = 0.0, *, seed: int = 0) -> dict:
    """Errors of a real rig's calibration and depth, drawn per camera for a synthetic recording.

    ``calibration_error`` ``(translation_m, rotation_deg)``: the pose written for each camera is its true pose
    moved by a translation of that length in a random direction and turned by that angle about a random axis
    through its optical centre (a multi-camera calibration leaves a few millimetres and a few tenths of a degree
    between the cameras' point clouds). ``depth_bias``: each camera's depth is scaled by ``1 +- depth_bias``, the
    sign drawn at random (a depth camera's absolute error is of 0.5-2 % of the distance). The images are rendered
    with the true poses; the recording holds the written ones, so its views disagree where a real rig's would.

    Returns ``c2w`` (the poses to write, [C, 4, 4]), ``depth_scale`` [C] and ``record`` (for ground_truth.json).
    Draws from a generator of its own (``seed``), so that a recording without errors is the same as before."""
    from scipy.spatial.transform import Rotation

    t_m, r_deg = (float(v) for v in calibration_error)
    bias = float(depth_bias)
    _finite_nonnegative((("calibration_error translation (m)", t_m), ("calibration_error rotation (deg)", r_deg),
                         ("depth_bias", bias)))
    if t_m > 0.05 or r_deg > 5.0 or bias > 0.1:
        raise ValueError(f"sensor errors this large ({t_m:g} m, {r_deg:g} deg, depth bias {bias:g}) are a broken "
                         f"calibration, not a calibrated rig's error: at most 0.05 m, 5 deg and 0.1")
    rng = np.random.default_rng([int(seed), 0x5E05])
    C = len(cameras)
    c2w, trans, rotvec, scale = [], [], [], []
    for cam in cameras:
        d = rng.standard_normal(3)
        t = t_m * d / np.linalg.norm(d)
        a = rng.standard_normal(3)
        rv = math.radians(r_deg) * a / np.linalg.norm(a)
        s = 1.0 + bias * (1.0 if rng.random() < 0.5 else -1.0)
        m = np.array(cam.c2w, np.float64)
        m[:3, :3] = Rotation.from_rotvec(rv).as_matrix() @ m[:3, :3]  # about the optical centre
        m[:3, 3] = m[:3, 3] + t
        c2w.append(m)
        trans.append(t)
        rotvec.append(rv)
        scale.append(s)
    record = {"calibration_translation_m": [list(map(float, t)) for t in trans],
              "calibration_rotation_deg": [float(np.degrees(np.linalg.norm(r))) for r in rotvec],
              "calibration_rotation_axis": [list(map(float, r / max(np.linalg.norm(r), 1e-300))) for r in rotvec],
              "depth_scale": [float(s) for s in scale]}
    return {"c2w": np.stack(c2w) if C else np.zeros((0, 4, 4)), "depth_scale": np.array(scale), "record": record}


def _check_tracker_errors(track_error: Sequence[float], mask_error_px: int) -> Tuple[float, float, float, int]:
    if len(tuple(track_error)) != 3:
        raise ValueError(f"track_error must be (jitter px, drift px per frame, outlier fraction), got {track_error!r}")
    jit, drift, frac = (float(v) for v in track_error)
    _finite_nonnegative((("track_error jitter (px)", jit), ("track_error drift (px per frame)", drift),
                         ("track_error outlier fraction", frac)))
    if jit > 20.0 or drift > 5.0 or frac > 0.5:
        raise ValueError(f"tracker errors this large (jitter {jit:g} px, drift {drift:g} px a frame, outliers "
                         f"{frac:g}) are a lost tracker, not a tracker's error: at most 20 px, 5 px and 0.5")
    if isinstance(mask_error_px, bool) or int(mask_error_px) != mask_error_px or abs(int(mask_error_px)) > 10:
        raise ValueError(f"mask_error_px must be a whole number of pixels in [-10, 10], got {mask_error_px!r}")
    return jit, drift, frac, int(mask_error_px)


def tracker_errors(tracks: np.ndarray, visible: np.ndarray, track_error: Sequence[float] = (0.0, 0.0, 0.0), *,
                   width: int, height: int, seed: int = 0) -> Tuple[np.ndarray, dict]:
    """A 2D point tracker's errors on exact tracks [C, T, M, 2] (row, col pixels) of a synthetic recording.

    ``track_error`` ``(jitter_px, drift_px, outlier_frac)``: every visible entry moves by Gaussian noise of
    ``jitter_px`` per axis, drawn anew each frame; each track also wanders by a random walk of ``drift_px`` per axis
    and frame from frame 0 on (a tracker loses its point slowly on a textureless surface); and a fraction
    ``outlier_frac`` of the visible entries after frame 0 jump 4-20 pixels in a random direction (onto another
    feature), still marked visible. A learned tracker (CoTracker, TAPIR) on real video is about 1-3 pixels off on
    textured objects, more where texture is weak. Frame 0's query points stay exact; positions stay in the image.

    Returns (tracks, record for ground_truth.json). Draws from a generator of its own (``seed``), so that a
    recording without errors is the same as before."""
    jit, drift, frac, _ = _check_tracker_errors(track_error, 0)
    out = np.array(tracks, np.float64, copy=True)
    record = {"track_jitter_px": jit, "track_drift_px_per_frame": drift, "track_outlier_fraction": frac}
    if not (jit or drift or frac) or out.size == 0:
        return out.astype(np.float32), record
    rng = np.random.default_rng([int(seed), 0x7AC4])
    C, T, M, _ = out.shape
    err = rng.standard_normal((C, T, M, 2)) * jit
    walk = np.cumsum(rng.standard_normal((C, T, M, 2)) * drift, axis=1)
    err += walk - walk[:, :1]
    jump = (rng.random((C, T, M)) < frac) & np.asarray(visible, bool)
    jump[:, 0] = False
    ang = rng.random((C, T, M)) * 2 * np.pi
    r = 4.0 + 16.0 * rng.random((C, T, M))
    err += np.where(jump[..., None], np.stack([r * np.sin(ang), r * np.cos(ang)], -1), 0.0)
    err[:, 0] = 0.0
    out += err
    out[..., 0] = np.clip(out[..., 0], 0.0, height - 1.0)
    out[..., 1] = np.clip(out[..., 1], 0.0, width - 1.0)
    record["track_outliers"] = int(jump.sum())
    return out.astype(np.float32), record


def mask_error(mask: np.ndarray, mask_error_px: int) -> np.ndarray:
    """A segmenter's boundary error on an exact object mask: grown by ``mask_error_px`` pixels (positive: onto the
    table, the background and the end-effectors beside it, as a mask that bleeds does) or shrunk (negative)."""
    from scipy import ndimage

    k = int(mask_error_px)
    if k > 0:
        return ndimage.binary_dilation(mask, iterations=k)
    if k < 0:
        return ndimage.binary_erosion(mask, iterations=-k)
    return mask


# ----------------------------------------------------------------------------------------------
# main entry
# ----------------------------------------------------------------------------------------------


def synthesize(out_dir, object: str = "rope", *, seed: int = 0, E: Optional[float] = None,
               nu: Optional[float] = None, density: Optional[float] = None, yield_stress: Optional[float] = None,
               frames: int = 60, cameras: int = 3, width: int = 848, height: int = 480, fx: Optional[float] = None,
               fy: Optional[float] = None, fps: float = 30.0, dx: float = 0.01, particles_per_cell: float = 8,
               table_friction: float = 0.5, gripper_friction: float = 0.8, surface_spacing_m: float = 0.0015,
               noise_sigma_m: float = 1.5e-3, n_tracks: int = 128, depth_format: str = "npy",
               overwrite: bool = False, progress: bool = True, device: str = "cpu", script: str = "default",
               effect: Optional[str] = None, effect_params: Optional[Dict[str, float]] = None,
               material=None, debug_particles: Optional[bool] = None, tangent_splats: bool = True,
               simulator: str = "mpm", springmass_damping: float = 1.0, grid_offset=(0.0, 0.0, 0.0),
               jitter: float = 0.0, calibration_error: Sequence[float] = (0.0, 0.0), depth_bias: float = 0.0,
               track_error: Sequence[float] = (0.0, 0.0, 0.0), mask_error_px: int = 0) -> Path:
    """Simulate a scripted manipulation and write a synthetic recording with known parameters to ``out_dir``.

    ``object`` is "rope", "dough", "block" or "lump"; ``script`` "default" (rope lift-and-stretch, dough squeeze,
    block press-release) or a name of :data:`empm_gym.perception.scripts.SCRIPTS`.

    Materials: without ``effect`` (and ``material``) the object takes :data:`OBJECT_DEFAULTS` (the dough is
    elastoplastic), overridden by ``E``, ``nu``, ``density``, ``yield_stress`` (Pa, -, kg/m^3, Pa), on a
    table of friction ``table_friction``. With ``effect`` ("none" or an effect of
    :data:`empm_gym.sim.effects.EFFECTS`) the object is the base model (elastic, whatever the object, table
    friction 0.5, rigid closed grippers) plus that one effect with :func:`default_effect_params` updated
    by ``effect_params``; ``material`` (a MaterialConfig, e.g. from a material file) replaces the base
    model, or without ``effect`` is used as it is. Only ``ground_truth.json`` names the effects: every
    other file is the same for every effect given the object, script, frames, cameras and seed (the debug
    particle file ``ground_truth_particles.npz`` is written only when ``debug_particles``, which defaults to
    True for the historic calls without ``effect`` / ``material`` and to False otherwise).

    The scene is rendered from ``cameras`` cameras (``width`` x ``height`` pixels, focal ``fx``, ``fy``
    pixels) at ``fps`` for ``frames`` frames (focal lengths default to 420 px scaled by width / 848);
    ``tangent_splats`` (the default) draws the surface's discs in their tangent planes, so that the depth lies on
    the true surface as a depth camera measures it (:func:`render_view`); False draws flat discs at their
    centres' depth, which put inclined faces 0.3-0.8 mm too near and widen the silhouette (the recordings of
    benchmark seeds up to 14 were made so).
    ``simulator`` "springmass" moves the body as a spring-mass network (PhysTwin's family; only table friction
    and a stiffness field can be its effects, dashpots ``springmass_damping`` Pa s) instead of our MPM, so that
    the doctor and identification can be tried on another simulator's output (:func:`simulate`); the
    rendering is the same. ``grid_offset`` and ``jitter`` vary the discretisation (:func:`simulate`); the
    ground truth's ``scene`` records both. ``calibration_error`` ``(m, deg)`` and ``depth_bias`` give the rig a
    real one's errors (:func:`sensor_errors`): the recording's camera poses and depths are off by them;
    ``track_error`` ``(jitter px, drift px a frame, outlier fraction)`` gives the tracks a real tracker's
    (:func:`tracker_errors`) and ``mask_error_px`` the object masks a segmenter's (:func:`mask_error`); only
    ground_truth.json's ``sensor_errors`` says by how much.
    Returns the recording path. See the module docstring for the scene, the noise model and how
    ``controls.npz`` replays.
    """
    from tqdm.auto import tqdm

    from empm_gym.sim import MaterialConfig

    _check_scene_args(object, script, frames)
    if int(cameras) < 1:
        raise ValueError(f"cameras must be >= 1, got {cameras!r}")
    if len(tuple(calibration_error)) != 2:
        raise ValueError(f"calibration_error must be (translation m, rotation deg), got {calibration_error!r}")
    sensor_errors([], calibration_error, depth_bias, seed=seed)  # its values checked before the simulation runs
    _check_tracker_errors(track_error, mask_error_px)
    T, C = int(frames), int(cameras)
    fx = 420.0 * width / 848.0 if fx is None else float(fx)
    fy = fx if fy is None else float(fy)
    legacy = effect is None and material is None
    if debug_particles is None:
        debug_particles = legacy
    if effect is not None:
        if yield_stress is not None:
            raise ValueError("yield_stress is an effect parameter: use effect='plasticity' with "
                             "effect_params={'yield_stress': ...}")
        with_file = material is not None
        material, effects = effect_material(object, effect, effect_params, base=material, E=E, nu=nu,
                                            density=density)
        if with_file:  # the material file's own effects stay
            effects = _effects_of(material)
    elif material is not None:
        if effect_params:
            raise ValueError("effect_params needs an effect")
        kw = {k: float(v) for k, v in (("E", E), ("nu", nu), ("density", density), ("yield_stress", yield_stress))
              if v is not None}
        material = material.replace(**kw) if kw else material
        effects = _effects_of(material)
    else:
        if effect_params:
            raise ValueError("effect_params needs an effect")
        d = dict(OBJECT_DEFAULTS[object])
        for k, v in (("E", E), ("nu", nu), ("density", density), ("yield_stress", yield_stress)):
            if v is not None:
                d[k] = float(v)
        material = MaterialConfig(**d)
        effects = _effects_of(material)  # the default dough yields (yield_stress 2 kPa): ground truth says so
    if material.get("friction") is not None:
        table_friction = float(material.get("friction"))
    rng = np.random.default_rng(seed)
    t_start = time.perf_counter()

    # -- simulate -------------------------------------------------------------------------------
    sim = simulate(object, material, script=script, frames=T, fps=fps, dx=dx, particles_per_cell=particles_per_cell,
                   table_friction=table_friction, gripper_friction=gripper_friction, seed=seed, device=device,
                   progress=progress, simulator=simulator, springmass_damping=springmass_damping,
                   grid_offset=grid_offset, jitter=jitter)
    X, pos, grip, ee_cfgs, grid, model = (sim["particles"], sim["positions"], sim["grip"], sim["end_effectors"],
                                          sim["grid"], sim["model"])
    quat = sim["orientations"]
    n_sub, dt = sim["substeps"], sim["dt"]
    t_sim = time.perf_counter() - t_start
    parted = body_parts(X, dx)
    if parted is not None and not any(e["name"] == "fracture" for e in effects):
        warnings.warn(f"synthesize: the simulated {object} parts into {parted['pieces']} pieces from frame "
                      f"{parted['from_frame']} on without a fracture in its material: script {script!r} stretches "
                      f"it further or faster than a grid of dx = {dx:g} m holds together. The recording shows a "
                      f"tear that its ground truth does not name (ground_truth.json: parted); a finer dx or more "
                      f"frames may keep the body whole", stacklevel=2)

    cams = camera_ring(C, width=width, height=height, fx=fx, fy=fy,
                       target=(0.0, 0.0, 0.03 if object == "rope" else 0.02))
    errors = sensor_errors(cams, calibration_error, depth_bias, seed=seed)
    out = Path(out_dir)
    writer = RecordingWriter(out, intrinsics=[c.K for c in cams], c2w=list(errors["c2w"]), width=width,
                             height=height, fps=fps, frame_num=T, depth_scale=0.001, depth_format=depth_format,
                             serial_numbers=[f"synth-{i}" for i in range(C)], object_label=object,
                             overwrite=overwrite)
    if not debug_particles:
        (out / "ground_truth_particles.npz").unlink(missing_ok=True)

    # -- dense surface ------------------------------------------------------------------------------
    if object == "rope":
        sp, sn, u = _rope_surface(surface_spacing_m)
        stripes = 0.5 + 0.5 * np.cos(2 * np.pi * u * 12)
        albedo = np.stack([0.75 - 0.25 * stripes, 0.18 + 0.3 * stripes, 0.12 + 0.1 * stripes], -1)
    elif object in ("dough", "lump"):
        sp, sn, _ = (_box_surface(_DOUGH_SIZE_M, surface_spacing_m) if object == "dough" else
                     _lump_surface(surface_spacing_m))
        albedo = np.clip(np.array([0.85, 0.72, 0.45]) + rng.normal(0, 0.04, (len(sp), 1)), 0, 1)
    else:
        sp, sn, _ = _box_surface(_BLOCK_SIZE_M, surface_spacing_m)
        speckle = rng.normal(0, 0.05, (len(sp), 1))
        albedo = np.clip(np.array([0.25, 0.45, 0.75]) + speckle, 0, 1)
    emb = SurfaceEmbedding(sp, sn, X[0])
    n_tr = min(int(n_tracks), len(sp))
    track_idx = np.sort(rng.choice(len(sp), n_tr, replace=False)) if n_tr else np.zeros(0, int)
    tracks = np.zeros((C, T, n_tr, 2), np.float32)
    vis = np.zeros((C, T, n_tr), bool)

    views = [_StaticView(c) for c in cams]
    splat_r = 1.0 * surface_spacing_m
    for t in tqdm(range(T), desc=f"render {C} cameras", disable=not progress, leave=False):
        P, N = emb.deform(X[t])
        ees = []
        for k, cfg in enumerate(ee_cfgs):
            ees.append({"shape": cfg.shape, "pos": pos[t, k], "rot": _quat_to_matrix(quat[t, k]), "radius": cfg.radius,
                        "half_extents": cfg.half_extents})
        for c, view in enumerate(views):
            depth, color, label, cosv = render_view(view, P, N, albedo, splat_r, ees, tangent=tangent_splats)
            noisy = add_depth_noise(depth, cosv, rng, sigma_m=noise_sigma_m) * errors["depth_scale"][c]
            rgb = np.clip(color + rng.normal(0, 0.008, color.shape), 0, 1)
            writer.write_frame(c, t, color=(rgb * 255 + 0.5).astype(np.uint8), depth_m=noisy,
                               mask=mask_error(label == 1, mask_error_px),
                               controller_mask=[label == 2 + k for k in range(len(ee_cfgs))])
            if n_tr:
                rc, z = view.cam.project(P[track_idx])
                tracks[c, t] = rc
                ri, ci = np.round(rc[:, 0]).astype(int), np.round(rc[:, 1]).astype(int)
                inside = (ri >= 0) & (ri < height) & (ci >= 0) & (ci < width) & (z > 0)
                zb = np.full(n_tr, -np.inf)
                zb[inside] = depth[ri[inside], ci[inside]]
                lab = np.full(n_tr, -1)
                lab[inside] = label[ri[inside], ci[inside]]
                vis[c, t] = inside & (lab == 1) & (z <= zb + max(0.003, 2 * surface_spacing_m))

    shapes = np.array([c.shape for c in ee_cfgs])
    writer.write_controls(positions=pos, grip=grip, shape=shapes,
                          radius=np.array([c.radius for c in ee_cfgs]),
                          half_height=np.array([c.half_height for c in ee_cfgs]),
                          half_extents=np.array([c.half_extents for c in ee_cfgs]),
                          orientations=quat)
    tracks, track_record = tracker_errors(tracks, vis, track_error, width=width, height=height, seed=seed)
    for c in range(C):
        writer.write_tracks(c, tracks[c], vis[c])
    # debug only (never read by identification): the simulated particle trajectories [T, N, 3] (m) and
    # the end-effector centres per frame, to check that a replay of the recording reproduces them
    if debug_particles:
        np.savez_compressed(out / "ground_truth_particles.npz", positions=X, volumes=sim["volumes"],
                            ee_positions=pos.astype(np.float32), ee_orientations=quat.astype(np.float32), grip=grip)
    writer.write_ground_truth({
        "synthetic": True,
        "object": object,
        "script": script if script != "default" else f"default ({DEFAULT_SCRIPT[object]})",
        "seed": int(seed),
        "material": {"E": material.E, "nu": material.nu, "density": material.density,
                     "yield_stress": material.yield_stress},
        "material_parameters": material.to_dict(),
        "table_friction": float(table_friction),
        "gripper_friction": float(gripper_friction),
        "grip": ("rigid" if material.get("grip_friction") is None else
                 f"friction {material.get('grip_friction'):g}"),
        "effects": effects,
        # the simulated body came apart (body_parts; None: it stayed whole), fracture or not
        "parted": parted,
        "simulator": ({"name": "mpm"} if simulator == "mpm" else
                      {"name": "springmass", "stiffness_Pa": float(material.E), "damping_Pa_s": float(springmass_damping),
                       "spacing_m": float(model.spacing), "springs": int(model.spring_count)}),
        "scene": {
            "grid": {"lower": list(grid.lower), "upper": list(grid.upper), "dx": grid.dx},
            "grid_offset_cells": [float(v) for v in grid_offset],
            "particle_jitter": float(jitter),
            "particles_per_cell": float(particles_per_cell),
            "particle_count": int(X.shape[1]),
            "substeps_per_frame": n_sub,
            "dt_s": dt,
            "gravity": [0.0, 0.0, -9.81],
            "table_height_m": 0.0,
            "object_geometry": ({"type": "cylinder", "length_m": _ROPE_LENGTH_M, "radius_m": _ROPE_RADIUS_M,
                                 "axis": "x", "centre": [0.0, 0.0, _ROPE_RADIUS_M]} if object == "rope" else
                                {"type": "ellipsoid above the table", "semi_axes_m": list(_LUMP_SEMI_AXES_M),
                                 "centre": [0.0, 0.0, _LUMP_CENTRE_Z_M]} if object == "lump" else
                                {"type": "box", "size_m": list(_GEOMETRY[object].size),
                                 "lower": [-_GEOMETRY[object].size[0] / 2, -_GEOMETRY[object].size[1] / 2, 0.0]}),
            "end_effectors": [{"shape": c.shape, "radius": c.radius, "half_extents": list(c.half_extents)}
                              for c in ee_cfgs],
        },
        "sensor_errors": {**errors["record"], **track_record, "mask_error_px": int(mask_error_px)},
        "render": {"surface_points": int(len(sp)), "surface_spacing_m": surface_spacing_m,
                   "splat_radius_m": splat_r, "tangent_splats": bool(tangent_splats),
                   "depth_noise_sigma_m_at_0.5m": noise_sigma_m,
                   "track_surface_indices": track_idx.tolist()},
        "timing_s": {"simulate": round(t_sim, 3), "total": round(time.perf_counter() - t_start, 3)},
    })
    return out


# ----------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------


def _parse_effect_params(items) -> Dict[str, float]:
    out = {}
    for it in items or []:
        key, sep, val = it.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--effect-param expects KEY=VALUE, got {it!r}")
        try:
            out[key.strip()] = float(val)
        except ValueError:
            raise ValueError(f"--effect-param {key.strip()}: {val!r} is not a number") from None
    return out


def _cli(args) -> int:
    try:
        material = None
        if getattr(args, "material", None):
            from empm_gym.sim.material_file import read_material

            material = read_material(args.material).material
        effect = args.effect
        params = _parse_effect_params(args.effect_param)
        if params and effect is None:
            raise ValueError("--effect-param needs --effect NAME")
        path = synthesize(args.out_dir, object=args.object, seed=args.seed, E=args.E, nu=args.nu,
                          density=args.density, yield_stress=args.yield_stress, frames=args.frames,
                          cameras=args.cameras, width=args.width, height=args.height, overwrite=args.overwrite,
                          depth_format=args.depth_format, progress=not args.quiet, device=args.device,
                          script=args.script, effect=effect, effect_params=params, material=material,
                          debug_particles=True if args.debug_particles else None,
                          tangent_splats=args.tangent_splats, simulator=args.simulator,
                          springmass_damping=args.springmass_damping, grid_offset=args.grid_offset,
                          jitter=args.jitter, calibration_error=args.calibration_error, depth_bias=args.depth_bias,
                          track_error=args.track_error, mask_error_px=args.mask_error)
    except (RecordingError, ValueError, OSError) as exc:
        print(f"empm synth: error: {exc}", file=sys.stderr)
        return 2
    gt = json.loads((path / "ground_truth.json").read_text())
    m = gt["material"]
    eff = ", ".join(f"{e['name']} " + " ".join(f"{k}={v:g}" for k, v in e["params"].items())
                    for e in gt["effects"]) or "none"
    print(f"wrote {path}: {args.object}, script {gt['script']}, {args.frames} frames x {args.cameras} cameras; "
          f"E={m['E']:g} Pa, nu={m['nu']:g}, density={m['density']:g} kg/m^3, yield_stress={m['yield_stress']} Pa; "
          f"effects: {eff}; simulator {gt['simulator']['name']} ({gt['timing_s']['total']:.1f} s)")
    return 0


def register(subparsers) -> None:
    """Add the ``empm synth`` sub-command."""
    p = subparsers.add_parser(
        "synth", help="write a synthetic multi-view RGB-D recording with known material parameters",
        description="Simulate a scripted manipulation of a rope, a dough lump or a block, optionally with one "
                    "hidden effect, and render it from N RGB-D cameras into the recording layout (see "
                    "ARCHITECTURE.md, Recordings, and docs/EFFECTS.md).")
    p.add_argument("out_dir", help="output recording directory (must be empty unless --overwrite)")
    p.add_argument("--object", choices=sorted(OBJECT_DEFAULTS), default="rope")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--E", type=float, default=None, help="Young's modulus, Pa (rope 5e4, dough 2e4)")
    p.add_argument("--nu", type=float, default=None, help="Poisson's ratio (default 0.3)")
    p.add_argument("--density", type=float, default=None, help="kg/m^3 (rope 1100, dough 1200)")
    p.add_argument("--yield-stress", dest="yield_stress", type=float, default=None,
                   help="von Mises yield stress, Pa (dough 2e3; rope elastic unless given)")
    p.add_argument("--script", choices=["default", *SCRIPTS], default="default",
                   help="scripted manipulation (default: rope lift-and-stretch, dough squeeze, block "
                        "press-release); see docs/EFFECTS.md")
    p.add_argument("--effect", default=None, metavar="NAME",
                   help="record the base model (elastic body, table friction 0.5, rigid grip) plus effect NAME "
                        "(none, plasticity, viscosity, table_friction, gripper_slip, heterogeneous_stiffness, "
                        "fracture); only ground_truth.json names it. Without --effect or --material the "
                        "object's defaults are recorded: the dough is then plastic (yield_stress 2 kPa)")
    p.add_argument("--effect-param", dest="effect_param", action="append", default=[], metavar="KEY=VALUE",
                   help="a parameter of --effect (SI units; repeatable), e.g. yield_stress=1500")
    p.add_argument("--material", default=None, metavar="FILE",
                   help="material file (empm_gym.sim.material_file): the base material and its effects "
                        "(with --effect: the base that the effect is added to)")
    p.add_argument("--debug-particles", dest="debug_particles", action="store_true",
                   help="also write ground_truth_particles.npz (the simulated particles; written anyway "
                        "without --effect / --material, as before)")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--cameras", type=int, default=3)
    p.add_argument("--width", type=int, default=848)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--depth-format", choices=("npy", "png"), default="npy",
                   help="depth files: PhysTwin's .npy (default) or 16-bit PNG in millimetres (PGND-style, "
                        "about 8x smaller)")
    p.add_argument("--device", default="cpu", help="Warp device for the simulation (cpu, cuda:0)")
    p.add_argument("--tangent-splats", dest="tangent_splats", action="store_true", default=True,
                   help="draw the surface in its tangent planes: depth on the true surface (the default)")
    p.add_argument("--flat-splats", dest="tangent_splats", action="store_false",
                   help="draw the surface as flat discs at their centres' depth, as recordings made before "
                        "2026-11-28 were: inclined faces 0.3-0.8 mm too near, the silhouette a little wide")
    p.add_argument("--simulator", choices=SIMULATORS, default="mpm",
                   help="move the body with our MPM (default) or a spring-mass network (PhysTwin's family: "
                        "springs of stiffness E, only table_friction and heterogeneous_stiffness as effects), "
                        "to try the doctor and identification on another simulator's output")
    p.add_argument("--springmass-damping", dest="springmass_damping", type=float, default=1.0,
                   help="the spring-mass dashpots, Pa s (with --simulator springmass)")
    p.add_argument("--grid-offset", dest="grid_offset", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("X", "Y", "Z"),
                   help="move the simulation grid's nodes down by these fractions of a cell, each in [0, 1); a z "
                        "offset moves the node layer the table acts on below the table (the body rests in it)")
    p.add_argument("--jitter", type=float, default=0.0,
                   help="displace the body's particles by up to +-jitter/2 of their spacing (0 to 1, seeded)")
    p.add_argument("--calibration-error", dest="calibration_error", type=float, nargs=2, default=(0.0, 0.0),
                   metavar=("M", "DEG"), help="each camera's written pose is off its true one by a translation of M "
                   "metres and a rotation of DEG degrees (random directions; a real rig's calibration error)")
    p.add_argument("--depth-bias", dest="depth_bias", type=float, default=0.0, metavar="FRAC",
                   help="each camera's depth is scaled by 1 +- FRAC (random sign; a depth camera's absolute error)")
    p.add_argument("--track-error", dest="track_error", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("JITTER", "DRIFT", "OUTLIERS"), help="the tracks get a real tracker's errors: Gaussian "
                   "jitter of JITTER px a frame, a random walk of DRIFT px a frame, and a fraction OUTLIERS of the "
                   "visible entries jumping 4-20 px (still marked visible)")
    p.add_argument("--mask-error", dest="mask_error", type=int, default=0, metavar="PX",
                   help="the object masks grown by PX pixels (onto the background and the end-effectors, as a "
                        "segmenter's mask that bleeds) or shrunk (negative PX)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing recording in out_dir")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cli)
