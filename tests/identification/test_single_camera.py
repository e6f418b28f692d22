"""Recordings from one camera: the frame-0 body is completed under the half-turn symmetry prior
(:func:`empm_gym.perception.fusion.complete_by_symmetry`), checked against the true geometry, the
rope's E identified from one camera, and the dough's identified or reported undetermined.

The constructed scenes are ray-cast here (a box and a cylinder on the table, exact geometry, no
end-effectors); the rope and dough recordings come from ``empm synth --cameras 1``. ground_truth.json is
read only to check results (and for the parameters that are not fitted).
"""

import json
import math

import numpy as np
import pytest

from empm_gym.identification.data import AXIS_VARIANT, load_recording, view_jackknife_bodies
from empm_gym.perception.cameras import Camera, intrinsics_matrix, look_at
from empm_gym.perception.fusion import hidden_by_end_effectors, view_gap_deg
from empm_gym.perception.recording import RecordingWriter
from empm_gym.sim import EndEffectorConfig, MaterialConfig

# -- constructed scenes: one camera, exact depth ---------------------------------------------------------


def _yaw(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _box_hits(centre, R, half):
    """Ray caster of a solid box: (origin [3], directions [..., 3]) -> (ray parameter t [...], normals [..., 3])."""
    def hit(o, d):
        ol, dl = (o - centre) @ R, d @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - ol) / dl, (half - ol) / dl
        tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
        face = np.nanargmax(np.minimum(t1, t2), axis=-1)
        n = np.zeros(d.shape)
        np.put_along_axis(n, face[..., None], -np.sign(np.take_along_axis(dl, face[..., None], -1)), -1)
        return np.where((tmin <= tmax) & (tmax > 0), tmin, np.inf), n @ R.T
    return hit


def _cylinder_hits(centre, R, radius, half_len):
    """Ray caster of a solid cylinder along its local x axis (a rope lying on the table)."""
    def hit(o, d):
        ol, dl = (o - centre) @ R, d @ R
        a = dl[..., 1] ** 2 + dl[..., 2] ** 2
        b = 2 * (ol[1] * dl[..., 1] + ol[2] * dl[..., 2])
        disc = b * b - 4 * a * (ol[1] ** 2 + ol[2] ** 2 - radius**2)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / (2 * a)
        p = ol + t[..., None] * dl
        t = np.where((disc >= 0) & (t > 0) & (np.abs(p[..., 0]) <= half_len), t, np.inf)
        n = np.stack([np.zeros_like(t), p[..., 1], p[..., 2]], -1) / radius
        for s in (-1.0, 1.0):
            with np.errstate(invalid="ignore", divide="ignore"):
                tc = (s * half_len - ol[0]) / dl[..., 0]
            pc = ol + tc[..., None] * dl
            cap = (tc > 0) & (pc[..., 1] ** 2 + pc[..., 2] ** 2 <= radius**2) & (tc < t)
            t = np.where(cap, tc, t)
            n = np.where(cap[..., None], np.array([s, 0.0, 0.0]), n)
        return t, n @ R.T
    return hit


def _one_camera_recording(path, hit, *, azimuth_deg=30.0, elevation_deg=40.0, seed=0, frames=2, hidden=()):
    """A recording (2 frames) of a still object on the table z = 0 from one camera 0.55 m away (320 x 240):
    depth with 1 mm noise, none at grazing incidence (|cos| < 0.25, as a depth sensor), exact mask (empty in the
    ``hidden`` frames)."""
    rng = np.random.default_rng(seed)
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    target = np.array([0.0, 0.0, 0.02])
    eye = target + 0.55 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    W, H = 320, 240
    cam = Camera(intrinsics_matrix(300.0, 300.0, (W - 1) / 2, (H - 1) / 2), look_at(eye, target), W, H)
    o, d = cam.world_rays()
    with np.errstate(divide="ignore", invalid="ignore"):
        t_table = np.where(-o[2] / d[..., 2] > 0, -o[2] / d[..., 2], np.inf)
    t_obj, n_obj = hit(o, d)
    obj = t_obj < t_table
    depth = np.where(obj, t_obj, t_table)
    ray = d / np.linalg.norm(d, axis=-1, keepdims=True)
    cos = np.abs(np.where(obj, np.einsum("ijk,ijk->ij", n_obj, ray), ray[..., 2]))
    depth = np.where(np.isfinite(depth) & (cos >= 0.25), depth + rng.normal(0.0, 0.001, depth.shape), 0.0)
    w = RecordingWriter(path, intrinsics=cam.K[None], c2w=cam.c2w[None], width=W, height=H, fps=30.0,
                        frame_num=frames)
    for t in range(frames):
        w.write_frame(0, t, color=np.full((H, W, 3), 128, np.uint8), depth_m=depth,
                      mask=np.zeros_like(obj) if t in hidden else obj)
    np.savez(path / "controls.npz", positions=np.zeros((frames, 0, 3)), grip=np.zeros((frames, 0)))
    return path


CONSTRUCTED = {
    # name: (ray caster, inside test of world points, true volume m^3, true axis x, y m)
    "cylinder": (_cylinder_hits(np.array([0.0, 0.01, 0.015]), _yaw(-40), 0.015, 0.06),
                 lambda q: (np.abs(((q - [0.0, 0.01, 0.015]) @ _yaw(-40))[:, 0]) <= 0.06)
                 & (np.linalg.norm(((q - [0.0, 0.01, 0.015]) @ _yaw(-40))[:, 1:], axis=1) <= 0.015),
                 math.pi * 0.015**2 * 0.12, (0.0, 0.01)),
    "box": (_box_hits(np.array([0.01, -0.005, 0.02]), _yaw(25), np.array([0.03, 0.02, 0.02])),
            lambda q: np.all(np.abs((q - [0.01, -0.005, 0.02]) @ _yaw(25)) <= [0.03, 0.02, 0.02], axis=1),
            0.06 * 0.04 * 0.04, (0.01, -0.005)),
}


@pytest.mark.parametrize("name", sorted(CONSTRUCTED))
def test_one_view_body_is_completed_by_the_half_turn(tmp_path, name):
    """A cylinder lying at an angle and a turned box, seen from one camera: the fill of the visible surface
    alone misses the far side; completed, the body has the true volume within 25 % (the width across the
    camera is measured only at the silhouette, which the fused surface stops a pixel short of), lies inside
    the true body, and the symmetry axis found is the body's own within 3 mm."""
    hit, inside, volume, axis = CONSTRUCTED[name]
    rec = _one_camera_recording(tmp_path / name, hit)
    info = {}
    scene, _, _ = load_recording(rec, frames=2, info=info, progress=False)
    assert info["single_view"] and info["view_gap_deg"] == 360.0
    assert info["symmetry"]["used"] and "turned 180 deg" in info["body_completion"]
    assert np.hypot(*(np.array(info["symmetry"]["axis_m"]) - axis)) < 0.003, info["symmetry"]
    ratio = scene.volumes.sum() / volume
    assert 0.75 < ratio < 1.15, ratio
    assert inside(scene.particles).mean() > 0.9
    plain, _, _ = load_recording(rec, frames=2, single_view=False, progress=False)
    assert plain.volumes.sum() / volume < ratio - 0.1  # what the completion adds
    # the completion's share in the interval: the body completed about the axis moved half a pixel towards the
    # camera is thinner across the view, moved away thicker; nothing else of the scene changes
    bodies = view_jackknife_bodies(rec, scene, particles_per_cell=27, symmetry=info["symmetry"])
    assert [label.split(" mm ")[1] for label, _ in bodies] == ["towards the cameras", "away from the cameras"]
    assert all(label.startswith(AXIS_VARIANT) for label, _ in bodies)
    (_, near), (_, far) = bodies
    v = scene.volumes.sum()
    assert near.volumes.sum() < 0.985 * v and far.volumes.sum() > 1.015 * v, (near.volumes.sum(), v, far.volumes.sum())
    assert near.dx == scene.dx and near.table == scene.table and near.material == scene.material


def test_a_view_that_shows_too_little_says_so(tmp_path):
    """From 12 degrees above the table the box's top is at grazing incidence (no depth): one wall is seen,
    its turned copy is the opposite wall, and nothing closes the body; loading says why instead of
    returning a sliver."""
    hit = CONSTRUCTED["box"][0]
    rec = _one_camera_recording(tmp_path / "low", hit, elevation_deg=12.0)
    with pytest.raises(ValueError, match="cannot be completed from views on one side.*record from higher"):
        load_recording(rec, frames=2, progress=False)


def test_frames_that_do_not_see_the_object_load_and_are_not_scored(tmp_path, caplog):
    """A recording whose object is wholly hidden in some frames (a hand or a plate over it) loads: the hidden
    frames are listed (logged, ``info``) and marked unseen, and the loss leaves them out (the Chamfer of a frame
    with no observed point is undefined, not zero). Only frame 0 seeing the object leaves nothing to compare."""
    import logging

    from empm_gym.identification.evaluate import evaluate
    from empm_gym.identification.offline import Objective

    box = CONSTRUCTED["box"][0]
    rec = _one_camera_recording(tmp_path / "hidden", box, frames=6, hidden=(3, 4))
    info = {}
    with caplog.at_level(logging.WARNING, logger="empm_gym.identification"):
        scene, obs, _ = load_recording(rec, progress=False, info=info)
    assert info["hidden_frames"] == [3, 4] and "wholly hidden in 2 of 6 frames (3-4)" in caplog.text
    assert obs.seen.tolist() == [True, True, True, False, False, True]
    obj = Objective(scene, obs, 6)
    X = np.repeat(scene.particles[None], 6, 0)  # the body at rest: its loss is finite on every seen frame
    per = obj.per_frame(X)
    assert np.isnan(per[[2, 3]]).all() and np.isfinite(per[[0, 1, 4]]).all()
    assert obj.numpy(X) == pytest.approx(np.mean(per[[0, 1, 4]]), rel=1e-12)
    ev = evaluate(scene, scene.material, None, obs, eval_frames=[1, 2, 3, 4, 5], positions=X, progress=False)
    assert ev["unscored_frames"] == [3, 4] and np.isnan(ev["per_frame"]["chamfer"][2:4]).all()
    assert ev["summary"]["chamfer"] == pytest.approx(np.mean(np.array(ev["per_frame"]["chamfer"])[[0, 1, 4]]))
    with pytest.raises(ValueError, match="only frame 0 of 6 holds object points"):
        load_recording(_one_camera_recording(tmp_path / "late", box, frames=6, hidden=(1, 2, 3, 4, 5)), progress=False)


def test_view_gap_and_the_occluder_test():
    def cam_at(az):
        eye = 0.5 * np.array([math.cos(math.radians(az)), math.sin(math.radians(az)), 0.6])
        return Camera(intrinsics_matrix(300, 300, 159.5, 119.5), look_at(eye, [0, 0, 0]), 320, 240)

    assert view_gap_deg([cam_at(30)], [0, 0, 0]) == 360.0
    assert abs(view_gap_deg([cam_at(a) for a in (30, 150, 270)], [0, 0, 0]) - 120.0) < 1e-6
    assert abs(view_gap_deg([cam_at(0), cam_at(60)], [0, 0, 0]) - 300.0) < 1e-6  # both on one side
    cam = cam_at(0)
    sphere = EndEffectorConfig(shape="sphere", radius=0.02)
    between = 0.5 * cam.position  # a sphere half-way to the camera hides the origin, not a point beside it
    hid = hidden_by_end_effectors(np.array([[0, 0, 0], [0, 0.08, 0]]), [cam], [sphere], between[None])
    assert hid.tolist() == [True, False]


# -- one-camera `empm synth` recordings ---------------------------------------------------------------


def _synth_one_camera(tmp_path_factory, obj, frames):
    from empm_gym.cli import main

    out = tmp_path_factory.mktemp("one_camera") / obj
    assert main(["synth", str(out), "--object", obj, "--cameras", "1", "--frames", str(frames),
                 "--width", "424", "--height", "240", "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def dough_one_camera(tmp_path_factory):
    return _synth_one_camera(tmp_path_factory, "dough", 30)


def _inside_box(x, geo, grow=0.0):
    lo = np.array(geo["lower"]) - grow
    return np.all((x >= lo) & (x <= lo + np.array(geo["size_m"]) + 2 * grow), axis=1)


def test_dough_body_from_one_camera(dough_one_camera):
    """The dough between two pushers, seen from one camera that the near pusher blocks for most of the
    dough: the completed body is the dough's box (its volume within 15 %, 90 % of it inside the box, 85 % of
    the box filled), centred on the true axis, and clear of the pushers; the fill of the visible surface
    alone covers far less of it."""
    from scipy.spatial import cKDTree

    from empm_gym.perception.fusion import inside_open_end_effectors

    geo = json.loads((dough_one_camera / "ground_truth.json").read_text())["scene"]["object_geometry"]
    centre = np.array(geo["lower"][:2]) + 0.5 * np.array(geo["size_m"][:2])
    lattice = np.stack(np.meshgrid(*[np.arange(lo + 0.0015, lo + s, 0.003) for lo, s in
                                     zip(geo["lower"], geo["size_m"])], indexing="ij"), -1).reshape(-1, 3)

    def covered(x):
        return float(np.mean(cKDTree(x).query(lattice)[0] < 0.003))

    info = {}
    scene, _, _ = load_recording(dough_one_camera, info=info, progress=False)
    x = scene.particles
    assert info["single_view"] and info["symmetry"]["used"], info
    assert np.hypot(*(np.array(info["symmetry"]["axis_m"]) - centre)) < 0.002, info["symmetry"]
    assert abs(scene.volumes.sum() / np.prod(geo["size_m"]) - 1.0) < 0.15
    assert _inside_box(x, geo).mean() > 0.9 and covered(x) > 0.85
    assert not inside_open_end_effectors(x, scene.ee_configs, scene.ee_positions[0], scene.ee_grip[0]).any()
    plain, _, _ = load_recording(dough_one_camera, single_view=False, progress=False)
    assert covered(plain.particles) < covered(x) - 0.15


@pytest.fixture(scope="module")
def rope_one_camera(tmp_path_factory):
    return _synth_one_camera(tmp_path_factory, "rope", 30)


@pytest.mark.slow
def test_rope_E_from_one_camera(rope_one_camera):
    """E of the rope from one camera within 15 %: 30 frames at 424 x 240 (the first 21 fitted, which hold its
    lift and sway), 8 particles per cell, Adam from 2x below with a larger step; density known. (Measured:
    +1.8 % after 8 steps; after 5, Adam's momentum still carried it 21 % past.)"""
    from empm_gym.identification.offline import identify

    m = json.loads((rope_one_camera / "ground_truth.json").read_text())["material"]
    start = MaterialConfig(E=0.5 * m["E"], nu=m["nu"], density=m["density"], yield_stress=m["yield_stress"])
    info = {}
    scene, obs, _ = load_recording(rope_one_camera, particles_per_cell=8, material=start, info=info, progress=False)
    assert info["single_view"] and info["symmetry"]["used"], info
    res = identify(obs, scene, params=("E",), iters=8, lr=0.3, frames=21, progress=False)
    assert abs(res.params["E"] / m["E"] - 1.0) < 0.15, res.param_history


@pytest.mark.slow
def test_dough_E_from_one_camera_is_found_or_flagged(dough_one_camera):
    """The dough's E from one camera (the default squeeze, yield stress and density known): within 15 %, or
    reported undetermined with the true E inside its interval, never a confident wrong number. (Measured: the
    fit settles at 13.6 kPa against 20 kPa, the loss flat within noise along E: interval [8.9 kPa, open),
    determined false; the plastic squeeze hardly depends on E, and three cameras do no better.)"""
    from empm_gym.identification.offline import identify
    from empm_gym.identification.uncertainty import assess_fit

    m = json.loads((dough_one_camera / "ground_truth.json").read_text())["material"]
    start = MaterialConfig(E=0.5 * m["E"], nu=m["nu"], density=m["density"], yield_stress=m["yield_stress"])
    scene, obs, _ = load_recording(dough_one_camera, particles_per_cell=8, material=start, progress=False)
    res = identify(obs, scene, params=("E",), iters=8, lr=0.3, frames=21, progress=False)
    u = assess_fit(res, scene, obs, n_boot=500)["uncertainty"]["E"]
    lo, hi = u["interval"]
    assert abs(res.params["E"] / m["E"] - 1.0) < 0.15 or (not u["determined"] and lo <= m["E"] <= hi), (res.params, u)


def test_two_opposite_cameras_body_and_both_completions(tmp_path):
    """Two cameras half a turn apart, the dough between two plates that hide its x faces from both (each
    plate from the camera on its side, the dough itself from the other). The body is built by the half-turn
    prior with what the plates hide filled up to them: its volume within 8 % of the true box, its x faces
    within 3 mm (they came out 5 mm short, the body 17 % small, when a point had to be hidden by a plate
    from every camera: the -38 % confident yield stress of issue 14). The views leave the completion open,
    so the shape variants for the interval hold the other completion, the fill of both sides; three cameras
    around the dough leave nothing open and get none."""
    from empm_gym.cli import main
    from empm_gym.identification.data import view_jackknife_bodies

    rec = tmp_path / "dough2"
    assert main(["synth", str(rec), "--object", "dough", "--cameras", "2", "--frames", "3",
                 "--width", "424", "--height", "240", "--quiet"]) == 0
    geo = json.loads((rec / "ground_truth.json").read_text())["scene"]["object_geometry"]
    info = {}
    scene, _, _ = load_recording(rec, particles_per_cell=27, info=info, progress=False)
    assert info["single_view"] and 150.0 <= info["view_gap_deg"] <= 210.0, info
    assert abs(scene.volumes.sum() / np.prod(geo["size_m"]) - 1.0) < 0.08
    spacing = 0.01 / 3.0  # 27 particles per cell: the outer particles lie half a spacing inside the faces
    lo, hi = np.array(geo["lower"]), np.array(geo["lower"]) + np.array(geo["size_m"])
    assert abs(scene.particles[:, 0].min() - (lo[0] + spacing / 2)) < 0.003
    assert abs(scene.particles[:, 0].max() - (hi[0] - spacing / 2)) < 0.003
    bodies = dict(view_jackknife_bodies(rec, scene, particles_per_cell=27))
    assert len(bodies) == 3, list(bodies)  # each camera left out, and the other completion
    other = [sc for label, sc in bodies.items() if "fill of both sides" in label]
    assert len(other) == 1 and other[0] is not None and len(other[0].particles) != len(scene.particles)
    rec3 = tmp_path / "dough3"
    assert main(["synth", str(rec3), "--object", "dough", "--cameras", "3", "--frames", "3",
                 "--width", "424", "--height", "240", "--quiet"]) == 0
    scene3, _, _ = load_recording(rec3, particles_per_cell=27, progress=False)
    labels = [label for label, _ in view_jackknife_bodies(rec3, scene3, particles_per_cell=27)]
    assert len(labels) == 3 and all(label.startswith("without camera") for label in labels), labels


def test_every_camera_left_out_still_closes_the_push_slide_body(tmp_path):
    """Regression: rebuilt without camera 2, the push-slide dough's views (both on one side) leave a handful
    of samples hidden by the pusher; turning fewer than ten samples raised "need at least 10 visible
    points", and the body was lost from the interval and the doctor's variants."""
    from empm_gym.cli import main
    from empm_gym.identification.data import view_jackknife_bodies

    rec = tmp_path / "push"
    assert main(["synth", str(rec), "--object", "dough", "--script", "push-slide", "--frames", "3", "--quiet"]) == 0
    scene, _, _ = load_recording(rec, particles_per_cell=8, progress=False)
    bodies = view_jackknife_bodies(rec, scene, particles_per_cell=8)
    assert len(bodies) == 3 and all(sc is not None for _, sc in bodies), [label for label, _ in bodies]
    for _, sc in bodies:
        assert abs(len(sc.particles) / len(scene.particles) - 1.0) < 0.25


def test_the_table_under_a_hovering_pusher_is_no_material(tmp_path):
    """Regression: seen from three cameras, the push-slide dough's pusher hovers 2 mm over the table beside
    the block. The strip of table beneath it, hidden from every camera and touching the block, was completed
    as material: a sheet one particle thick, 8 % of the body, reaching 4 cm beyond the block under the pusher
    (on the rope pushed across the table, 23 %). Now 2 of 1120 particles (a corner at the pusher's edge) lie
    more than half a cell beyond the true block."""
    import json

    from empm_gym.cli import main
    from empm_gym.perception.fusion import inside_end_effectors

    rec = tmp_path / "push"
    assert main(["synth", str(rec), "--object", "dough", "--script", "push-slide", "--frames", "3", "--quiet"]) == 0
    scene, _, _ = load_recording(rec, particles_per_cell=8, progress=False)
    x, dx = scene.particles, scene.dx
    under = np.zeros(len(x), bool)
    for s in (0.25, 0.5, 0.75, 1.0):
        under |= inside_end_effectors(x + [0.0, 0.0, s * dx], scene.ee_configs, scene.ee_positions[0],
                                      select=scene.ee_grip[0] == 0)
    assert not under.any(), f"{under.sum()} of {len(x)} particles lie under the open pusher"
    geo = json.loads((rec / "ground_truth.json").read_text())["scene"]["object_geometry"]
    lo = np.asarray(geo["lower"]); hi = lo + np.asarray(geo["size_m"])
    out = ~np.all((x > lo - 0.5 * dx) & (x < hi + 0.5 * dx), axis=1)
    assert out.mean() < 0.01, f"{out.sum()} of {len(x)} particles lie beyond the block (was 8 %)"
