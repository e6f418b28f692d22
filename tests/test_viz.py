"""End-effectors drawn in rerun as the shapes the simulator uses, turned as they turn."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from empm_gym.identification.doctor.phases import surface_gap
from empm_gym.sim import EndEffectorConfig
from empm_gym.viz.rerun_log import end_effector_shapes, log_end_effectors


def _box_corners(centre, half_sizes, quat):
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return centre + Rotation.from_quat(quat).apply(signs * half_sizes)


def test_a_turned_box_and_capsule_are_drawn_where_the_simulation_has_them():
    """A box rolled 60 degrees about x is drawn with corners on the surface the doctor measures it by (its own
    axes), not on the unturned box's; a capsule turned 90 degrees about y is drawn from one end of its axis,
    now along world x, to the other (rerun draws a capsule from its start along its own +z; ours is centred)."""
    box = EndEffectorConfig(shape="box", half_extents=(0.03, 0.01, 0.02))
    cap = EndEffectorConfig(shape="capsule", radius=0.01, half_height=0.04)
    sph = EndEffectorConfig(shape="sphere", radius=0.015)
    pos = np.array([[0.1, 0.2, 0.3], [-0.1, 0.0, 0.05], [0.0, 0.0, 0.1]])
    q_box = Rotation.from_euler("x", 60, degrees=True).as_quat()
    q_cap = Rotation.from_euler("y", 90, degrees=True).as_quat()
    shapes = end_effector_shapes([box, cap, sph], pos, np.stack([q_box, q_cap, [0, 0, 0, 1]]))
    b, c, s = shapes
    assert b["shape"] == "box" and np.allclose(b["half_sizes"], box.half_extents)
    corners = _box_corners(b["centre"], b["half_sizes"], b["quaternion"])
    rot = Rotation.from_quat(q_box).as_matrix()
    assert np.abs(surface_gap(corners, pos[0], np.array(box.half_extents), rot)).max() < 1e-12
    # the same corners are no corners of the unturned box: the turn is drawn
    assert np.abs(surface_gap(corners, pos[0], np.array(box.half_extents))).max() > 5e-3
    assert c["shape"] == "capsule" and c["length"] == pytest.approx(0.08) and c["radius"] == pytest.approx(0.01)
    end = c["start"] + Rotation.from_quat(c["quaternion"]).apply([0, 0, c["length"]])
    assert np.allclose(c["start"], pos[1] - [0.04, 0, 0]) and np.allclose(end, pos[1] + [0.04, 0, 0])
    assert s == {"shape": "sphere", "centre": pytest.approx(pos[2]), "radius": 0.015}
    # unturned when no orientations are given
    assert np.allclose(end_effector_shapes([box], pos[:1])[0]["quaternion"], [0, 0, 0, 1])


def test_end_effector_drawing_refuses_mismatched_or_degenerate_input():
    box = EndEffectorConfig(shape="box")
    with pytest.raises(ValueError, match="2 end-effectors but 1 positions"):
        end_effector_shapes([box, box], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite non-zero quaternions"):
        end_effector_shapes([box], np.zeros((1, 3)), np.zeros((1, 4)))


def test_every_shape_is_logged_to_a_rerun_file(tmp_path):
    import rerun as rr

    rec = rr.RecordingStream("empm_test_viz")
    path = tmp_path / "ee.rrd"
    rec.save(str(path))
    cfgs = [EndEffectorConfig(shape=s) for s in ("sphere", "capsule", "box")]
    for t in range(3):
        rec.set_time("frame", sequence=t)
        q = Rotation.from_euler("z", 20 * t, degrees=True).as_quat()
        log_end_effectors(rec, "world/ee", cfgs, np.eye(3) * 0.1 * t, np.tile(q, (3, 1)))
    rec.flush()
    rec.disconnect()
    assert path.stat().st_size > 1000
