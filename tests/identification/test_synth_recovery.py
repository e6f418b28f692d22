"""End to end on `empm synth` recordings: synth -> load_recording -> replay / identify.

ground_truth.json and ground_truth_particles.npz are read here only to check the result; identification
never reads them.
"""

import dataclasses
import json

import numpy as np
import pytest

from empm_gym.identification.data import load_recording
from empm_gym.identification.problem import simulate_frames
from empm_gym.sim import MaterialConfig

FRAMES = 24


def _synth(tmp_path_factory, obj, frames=FRAMES, width=212, height=120):
    from empm_gym.perception.synth import synthesize

    return synthesize(tmp_path_factory.mktemp("synth") / obj, obj, frames=frames, width=width, height=height,
                      cameras=3, progress=False)


@pytest.fixture(scope="module")
def dough_rec(tmp_path_factory):
    return _synth(tmp_path_factory, "dough")


@pytest.fixture(scope="module")
def rope_rec(tmp_path_factory):
    return _synth(tmp_path_factory, "rope")


def _truth(rec):
    gt = json.loads((rec / "ground_truth.json").read_text())
    m = gt["material"]
    return gt, MaterialConfig(E=m["E"], nu=m["nu"], density=m["density"], yield_stress=m["yield_stress"])


@pytest.mark.slow
def test_replaying_the_synthesised_body_reproduces_the_recording(dough_rec):
    """The loaded scene (controls, estimated table, grid, end-effectors) replays the synthesiser's own
    particles at the true parameters exactly; a table node layer one cell off drifts by millimetres."""
    gt, true = _truth(dough_rec)
    scene, obs, _ = load_recording(dough_rec, material=true, table_friction=gt["table_friction"], progress=False)
    assert abs(scene.table.height) < 1e-3
    G = np.load(dough_rec / "ground_truth_particles.npz")
    Xt = G["positions"]
    replay = dataclasses.replace(scene, particles=Xt[0].astype(np.float64), volumes=G["volumes"].astype(np.float64))
    X = simulate_frames(replay, [true])[:, 0]
    drift = np.linalg.norm(X - Xt, axis=2).mean(1)
    assert drift.max() < 2e-4, np.round(drift * 1000, 3)
    assert np.abs(X[:, :, 2].min() - Xt[:, :, 2].min()) < 5e-4  # nothing sinks into the table


def test_hidden_rope_ends_are_filled_and_grippers_keep_their_size(rope_rec):
    gt, true = _truth(rope_rec)
    scene, _, _ = load_recording(rope_rec, material=true, table_friction=gt["table_friction"], progress=False)
    length = gt["scene"]["object_geometry"]["length_m"]
    x = scene.particles[:, 0]
    # the grippers hide the last ~3.5 cm of each end; the body still reaches (within a cell) the true ends
    assert x.min() < -length / 2 + 0.01 and x.max() > length / 2 - 0.01
    assert [c.radius for c in scene.ee_configs] == [e["radius"] for e in gt["scene"]["end_effectors"]]
    true_vol = np.pi * gt["scene"]["object_geometry"]["radius_m"] ** 2 * length
    assert abs(scene.volumes.sum() / true_vol - 1) < 0.3


def test_closed_clamps_hold_no_phantom_material(tmp_path):
    """Two closed box clamps enclose the dough's ends (squeeze-lift) and hide them from every camera: the
    body fills each clamp only on the dough's side of its middle, at the dough's width (before: out to the
    clamps' far walls, 2.4x the dough's volume)."""
    from empm_gym.perception.synth import synthesize

    rec = synthesize(tmp_path / "rec", "dough", script="squeeze-lift", effect="none", frames=4, cameras=3,
                     width=320, height=180, progress=False)
    gt = json.loads((rec / "ground_truth.json").read_text())
    size = np.asarray(gt["scene"]["object_geometry"]["size_m"])
    info = {}
    scene, _, _ = load_recording(rec, progress=False, info=info)
    assert abs(scene.volumes.sum() / np.prod(size) - 1.0) < 0.25
    assert np.abs(scene.particles[:, 0]).max() < size[0] / 2 + 0.01   # within a cell of the true ends
    # the clamps hide most of the dough: the loader says how much of the body its completion supplied
    assert 0.5 < info["hidden_share"] < 0.9, info["hidden_share"]
    assert f"{100 * info['hidden_share']:.0f} % of the frame-0 body" in info["hidden_note"]
    # no camera sees where the dough ends inside a clamp: the doctor's body reaches each clamp's middle, the body
    # trimmed to the measured surface (the one that errs small, which a named effect must hold on too) half as far
    from empm_gym.identification.data import trimmed_body
    from empm_gym.perception.fusion import CLAMP_REACH_TRIMMED, load_controls
    from empm_gym.perception.recording import Recording, controls_to_end_effectors

    label, trim = trimmed_body(rec, scene, particles_per_cell=27)
    assert trim is not None, label
    cfgs, pos, _ = controls_to_end_effectors(load_controls(Recording(rec)))
    reach = []
    for k, cfg in enumerate(cfgs):
        c, hx = pos[0][k][0], cfg.half_extents[0]
        side = np.sign(c)
        entry = abs(c) - hx
        for body in (scene, trim):
            inside = body.particles[side * body.particles[:, 0] > entry]
            reach.append((side * inside[:, 0]).max() - entry)
    spacing = scene.dx / 3.0
    for (full_in, trim_in) in (reach[:2], reach[2:]):
        assert abs(full_in - hx) < spacing, (full_in, hx)                        # to the middle
        # half as far (the lattice's outer row half a spacing inside, and the trim takes up to one more)
        assert -1.5 * spacing < trim_in - CLAMP_REACH_TRIMMED * hx < spacing, (trim_in, hx)
    less = 1.0 - trim.volumes.sum() / scene.volumes.sum()
    assert 0.15 < less < 0.4 and f"{100 * less:.1f} % of the volume; the closed grippers holding it 0.5 of the way" \
        in label, (less, label)


def test_the_doctors_body_and_the_trimmed_body_lie_on_either_side_of_a_clamped_dough_seen_by_four_cameras(tmp_path):
    """Where a body ends inside a closed clamp no camera sees; the doctor's body continues to each clamp's middle and
    the body trimmed to the measured surface halfway there, so that a named effect must hold on a body on each side
    of the prior. Four cameras (PGND's rig) see the sides next to the clamps that three miss, and the doctor's body
    is the largest there (seed 0, 5 mm: 150.7 cm^3 against 112.5 true; the trimmed body 98.3; before session 80 the
    trimmed body kept the clamps' parts and was 148 on seed 24, and a false gripper slip held on both)."""
    from empm_gym.identification.data import trimmed_body
    from empm_gym.perception.synth import synthesize

    rec = synthesize(tmp_path / "rec", "dough", script="squeeze-lift", effect="none", frames=2, cameras=4,
                     debug_particles=True, progress=False)
    true_vol = np.load(rec / "ground_truth_particles.npz")["volumes"].sum()
    scene, _, _ = load_recording(rec, dx=0.005, particles_per_cell=8, progress=False, warn=False)
    _, trim = trimmed_body(rec, scene, particles_per_cell=8)
    assert trim is not None
    assert trim.volumes.sum() < 0.95 * true_vol and scene.volumes.sum() > 1.1 * true_vol, (
        trim.volumes.sum(), true_vol, scene.volumes.sum())


def test_a_body_the_cameras_see_whole_carries_no_completion_note(tmp_path):
    """Pressed from above (press-release), nothing of the dough is hidden from every camera at frame 0: the share
    completed by the hidden-part prior is small (the pusher over it hides a little of its top) and no note is given
    (the clamps' case is above)."""
    from empm_gym.identification.data import HIDDEN_NOTE_SHARE
    from empm_gym.perception.synth import synthesize

    rec = synthesize(tmp_path / "rec", "dough", script="press-release", effect="none", frames=4, cameras=3,
                     width=320, height=180, progress=False)
    info = {}
    load_recording(rec, progress=False, info=info)
    assert info["hidden_share"] < HIDDEN_NOTE_SHARE and info["hidden_note"] is None


def test_trimming_to_the_measured_surface_takes_only_outer_rows_and_brings_the_volume_to_the_truth(tmp_path):
    """The voxel fill of a noisy scan reaches the noise's outer envelope; ``trim_to_surface`` removes the particles
    outside the measured surface. Only outer particles go, and the body's volume comes closer to the true one on
    a scan biased outward: this 320 x 180 recording at 5 mm drawn with flat discs, which put the observed faces
    0.5-1 mm outside the true ones (126 -> 119 cm^3, the dough 112.5). On depth measured on the true surface (the
    synthesiser's default since session 43) the untrimmed body is 109.9 cm^3 and the trim takes it to 104.1,
    farther from the truth: one more reason the trim is off by default (benchmarks/RESULTS.md, sessions 40-41)."""
    from scipy.spatial import cKDTree

    from empm_gym.identification.offline import body_surface
    from empm_gym.perception.synth import synthesize

    rec = synthesize(tmp_path / "rec", "dough", script="press-release", effect="none", frames=4, cameras=3,
                     width=320, height=180, progress=False, tangent_splats=False)
    true_vol = np.prod(json.loads((rec / "ground_truth.json").read_text())["scene"]["object_geometry"]["size_m"])
    info = {}
    full, _, _ = load_recording(rec, dx=0.005, particles_per_cell=8, progress=False, warn=False)
    trim, _, _ = load_recording(rec, dx=0.005, particles_per_cell=8, progress=False, warn=False, info=info,
                                trim_to_surface=True)
    x, y = full.particles, trim.particles
    assert cKDTree(x).query(y)[0].max() < 1e-9                 # a subset of the untrimmed body
    removed = x[cKDTree(y).query(x)[0] > 1e-9]
    assert len(removed) == len(x) - len(y) and 0.01 < info["trimmed_share"] < 0.25
    assert info["trimmed_share"] == pytest.approx(len(removed) / len(x))
    # the removed particles lie on the untrimmed body's boundary (within half a spacing of a surface point), but
    # for a few in the second row: with the table fitted to every background point (session 56), one of 472 lies
    # 1.2 spacings in, beside a stray outer column of the fill that the trim kept
    s = np.median(cKDTree(x).query(x, k=2)[0][:, 1])
    depth = cKDTree(body_surface(x)).query(removed)[0]
    assert np.mean(depth < 0.6 * s) > 0.99 and depth.max() < 1.3 * s, (np.sort(depth)[-5:] / s)
    assert abs(trim.volumes.sum() - true_vol) < abs(full.volumes.sum() - true_vol) - 0.03 * true_vol



def test_the_trimmed_body_is_the_loaders_trim_of_the_same_scene_and_says_when_it_is_not_built(tmp_path, monkeypatch):
    """:func:`~empm_gym.identification.data.trimmed_body` (the body the doctor's named effect must also hold on) is
    the loader's ``trim_to_surface`` body, particle for particle, in the untrimmed scene's setting; where the trim
    removes too little to be a body of its own, no scene, and the label says why."""
    import empm_gym.identification.data as data
    from empm_gym.perception.synth import synthesize

    rec = synthesize(tmp_path / "rec", "dough", script="press-release", effect="none", frames=4, cameras=3,
                     width=320, height=180, progress=False)
    full, _, _ = load_recording(rec, dx=0.005, particles_per_cell=8, progress=False, warn=False)
    info = {}
    trim, _, _ = load_recording(rec, dx=0.005, particles_per_cell=8, progress=False, warn=False, info=info,
                                trim_to_surface=True)
    label, sc = data.trimmed_body(rec, full, particles_per_cell=8)
    share = 100 * info["trimmed_share"]
    less = 100 * (1.0 - trim.volumes.sum() / full.volumes.sum())
    assert sc is not None and label == (f"{data.TRIMMED_BODY} ({share:.1f} % of the particles removed, {less:.1f} % "
                                        f"of the volume)"), label
    assert np.array_equal(sc.particles, trim.particles) and np.array_equal(sc.volumes, trim.volumes)
    assert len(sc.particles) < len(full.particles) and sc.dx == full.dx and sc.table == full.table
    monkeypatch.setattr(data, "MIN_TRIMMED_SHARE", 0.5)
    label, sc = data.trimmed_body(rec, full, particles_per_cell=8)
    assert sc is None and "under 50 %: the doctor's body already is that body" in label, label

# -- recovery through the whole pipeline ---------------------------------------------------------------
#
# `empm synth` recordings (3 cameras, rendered surface, depth noise, tracks) -> perception -> identify, from
# 3x off. 45 frames at 424 x 240 keep the CPU cost down; the script (lift + stretch, hold, put down,
# release) is the one the 60-frame benchmark recordings use. The fit uses the first 70 % of the frames.

RECOVERY_FRAMES = 45


def _recovery_recording(tmp_path_factory, obj):
    return _synth(tmp_path_factory, obj, frames=RECOVERY_FRAMES, width=424, height=240)


def _recovery_problem(tmp_path_factory, obj, rec=None):
    rec = _recovery_recording(tmp_path_factory, obj) if rec is None else rec
    gt, true = _truth(rec)
    scene, obs, views = load_recording(rec, material=true, table_friction=gt["table_friction"], progress=False)
    return gt, scene, obs, int(round(0.7 * obs.num_frames)), views


@pytest.fixture(scope="module")
def rope_problem(tmp_path_factory):
    return _recovery_problem(tmp_path_factory, "rope")


def _fit(problem, param, method, **kw):
    from empm_gym.identification.offline import identify

    gt, scene, obs, F, _ = problem
    true = gt["material"][param]
    res = identify(obs, scene, params=(param,), method=method, init={param: 3.0 * true}, frames=F, progress=False,
                   **kw)
    return res.params[param] / true, res


@pytest.fixture(scope="module")
def rope_adam(rope_problem):
    # lr 0.25 (default 0.15): from 3x off in 8 steps (measured: 3.0, 2.34, 1.82, 1.44, 1.13, 0.88, 1.08, 1.004 x
    # the true E; 590 s on one core), where 12 steps at 0.15 took 1090 s for the same answer
    return _fit(rope_problem, "E", "adam", iters=8, lr=0.25)


@pytest.mark.slow
def test_adam_recovers_the_rope_E_from_a_synthetic_recording(rope_adam):
    ratio, res = rope_adam
    assert abs(ratio - 1.0) < 0.10, (ratio, res.param_history)
    assert res.loss_history[0] > 2.0 * res.loss  # it started far off


@pytest.mark.slow
def test_cmaes_recovers_the_rope_E_and_agrees_with_adam(rope_problem, rope_adam):
    ratio, res = _fit(rope_problem, "E", "cmaes", iters=6, popsize=4, sigma0=0.3)
    assert abs(ratio - 1.0) < 0.10, (ratio, res.param_history)
    assert abs(np.log(ratio / rope_adam[0])) < np.log(1.10)


@pytest.mark.slow
def test_the_online_twin_loses_no_mask_iou_to_what_the_grippers_hide(rope_problem):
    """The recorded masks show what each camera sees of the rope, without what the closed grippers hide. The
    twin at the true E (no updates) must be scored the same way: while the grippers hold the rope its mask IoU
    stays within 9 % of its IoU after they open. Measured (45 frames, 424 x 240): 0.746 held, 0.803 after
    release (0.93x; with the flat discs that drew the recordings before session 43, 0.750 and 0.783);
    splatting every particle, as before, gave 0.668 held (0.87x)."""
    from empm_gym.identification.online import OnlineFrame, OnlineIdentifier

    gt, scene, obs, _, views = rope_problem
    twin = OnlineIdentifier(scene, update=False, init={"E": gt["material"]["E"]}, cameras=views.cameras)
    iou = np.array([twin.step(OnlineFrame(obs.points[t], scene.ee_positions[t], scene.ee_grip[t], views.masks[t]))
                    ["mask_iou"] for t in range(obs.num_frames)])
    held = scene.ee_grip[: obs.num_frames].all(axis=1)
    assert held[:5].all() and not held[-5:].any()
    assert iou[held].mean() > 0.91 * iou[-5:].mean(), (iou[held].mean(), iou[-5:].mean())


@pytest.mark.slow
def test_online_updates_on_a_synthetic_recording_beat_no_updates(rope_problem):
    """The recording streamed frame by frame from E 3x too low: the twin that updates E at quasi-static
    moments matches the segmented masks and the fused points better than one that keeps the starting E.

    Measured (45 frames, 424 x 240, what the grippers hide left out of the twin's silhouettes): mask loss
    0.387 against 0.404, mask IoU 0.636 against 0.611, Chamfer 9.7 mm against 10.5 mm. The update at rest
    before the lift raises E (16.7 -> 22.4 kPa); the later ones, while the lifted rope still sways, lower it
    again a little (to 16.3 kPa at the end): the update assumes a body at rest.
    """
    from empm_gym.identification.online import OnlineFrame, replay

    gt, scene, obs, _, views = rope_problem
    E = gt["material"]["E"]
    frames = [OnlineFrame(obs.points[t], scene.ee_positions[t], scene.ee_grip[t], views.masks[t])
              for t in range(obs.num_frames)]
    out = replay(scene, frames, params=("E",), init={"E": E / 3}, cameras=views.cameras, H=10, k=3, lr=0.3,
                 progress=False)
    s = out["summary"]
    assert s["updates"] >= 4
    assert s["mask_loss_with_updates"] < 0.99 * s["mask_loss_without_updates"]
    assert s["mask_iou_with_updates"] > s["mask_iou_without_updates"]
    assert s["chamfer_with_updates"] < 0.97 * s["chamfer_without_updates"]
