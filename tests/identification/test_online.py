"""Online identification: quasi-static detection and updates that lower the mask loss."""

import numpy as np
import pytest

from empm_gym.identification.online import OnlineFrame, OnlineIdentifier, replay

from . import scenes


@pytest.fixture(scope="module")
def rope():
    return scenes.rope_lift(E=5e4, frames=40)


def _frames(p):
    return [OnlineFrame(p.obs.points[t], p.scene.ee_positions[t], p.scene.ee_grip[t], p.views.masks[t])
            for t in range(p.obs.num_frames)]


def test_online_updates_lower_mask_loss(rope):
    out = replay(rope.scene, _frames(rope), params=("E",), init={"E": 5e4 / 3}, cameras=rope.views.cameras,
                 mask_downsample=2, H=10, k=5, progress=False)
    s = out["summary"]
    w, wo = out["with_updates"], out["without_updates"]
    # no update while the gripper is lifting (frames 1-12), updates at most every k = 5 frames afterwards
    upd = [r["frame"] for r in w if r["updated"]]
    assert len(upd) >= 3 and min(upd) > 12
    assert np.all(np.diff(upd) >= 5)
    assert all(r["quasi_static"] for r in w if r["updated"])
    assert not any(r["quasi_static"] for r in w[:13])
    # the stiffness moves towards the truth and the twin then matches the masks better
    assert out["params"]["E"] > 1.3 * (5e4 / 3)
    assert all(r["E"] == pytest.approx(5e4 / 3) for r in wo)
    assert s["mask_loss_with_updates"] < 0.95 * s["mask_loss_without_updates"]
    assert s["mask_iou_with_updates"] > s["mask_iou_without_updates"]
    # before the first update both twins are identical
    first = s["first_update_frame"]
    assert w[first]["mask_loss"] == pytest.approx(wo[first]["mask_loss"])


def test_online_rejects_bad_frames(rope):
    ident = OnlineIdentifier(rope.scene, cameras=rope.views.cameras)
    with pytest.raises(ValueError, match=r"ee_positions must have shape \[1, 3\]"):
        ident.step(OnlineFrame(rope.obs.points[0], np.zeros((2, 3))))
    with pytest.raises(ValueError, match="3 cameras"):
        ident.step(OnlineFrame(rope.obs.points[0], np.zeros((1, 3)), masks=[np.zeros((120, 160), bool)]))
    with pytest.raises(ValueError, match="H and k"):
        OnlineIdentifier(rope.scene, H=0)


def test_a_frame_where_the_object_is_wholly_hidden_moves_the_twin_and_scores_nothing(rope):
    """A streamed frame with no observed points (a hand over the object) still moves the twin with its controls;
    its record says hidden, scores nothing (NaN) and updates nothing, and the frames after it are scored as if it
    had been seen. The first frame, which places the twin, must see the object."""
    frames = _frames(rope)[:8]
    seen = OnlineIdentifier(rope.scene, cameras=rope.views.cameras, update=False)
    blind = OnlineIdentifier(rope.scene, cameras=rope.views.cameras, update=False)
    for t, f in enumerate(frames):
        a = seen.step(f)
        b = blind.step(OnlineFrame(np.zeros((0, 3)), f.ee_positions, f.ee_grip, None) if t in (3, 4) else f)
        if t in (3, 4):
            assert b["hidden"] and np.isnan(b["chamfer"]) and not b["updated"] and not b["quasi_static"]
        else:
            assert b["chamfer"] == a["chamfer"] and b["mask_iou"] == a["mask_iou"]
    np.testing.assert_array_equal(blind.state.particle_x.numpy(), seen.state.particle_x.numpy())
    with pytest.raises(ValueError, match="non-empty on the first frame"):
        OnlineIdentifier(rope.scene).step(OnlineFrame(np.zeros((0, 3)), frames[0].ee_positions))


def test_the_twin_turns_its_grippers_with_the_streamed_orientations(rope):
    """A gripper that turns while it holds (the streamed frames' ``ee_orientations``) turns the twin's grip as
    the offline simulation of the same controls does; ignoring the turn leaves the twin centimetres off."""
    import dataclasses

    from empm_gym.identification.problem import simulate_frames
    from empm_gym.perception.scripts import axis_angle_quaternions

    T = 20
    q = axis_angle_quaternions((0.0, 1.0, 0.0), np.linspace(0.0, np.pi / 3, T))[:, None, :]
    turned = dataclasses.replace(rope.scene, ee_orientations=q, ee_positions=rope.scene.ee_positions[:T],
                                 ee_grip=rope.scene.ee_grip[:T])
    ident = OnlineIdentifier(turned, update=False)
    for t in range(T):
        ident.step(OnlineFrame(rope.obs.points[t], turned.ee_positions[t], turned.ee_grip[t], None, q[t]))
    online = ident.state.particle_x.numpy()
    offline = simulate_frames(turned, [ident._material()[0]])[-1, 0]
    plain = simulate_frames(dataclasses.replace(turned, ee_orientations=None), [ident._material()[0]])[-1, 0]
    off = np.linalg.norm(online - offline, axis=1).mean()
    assert off < 1e-3, off
    assert np.linalg.norm(plain - offline, axis=1).mean() > 10 * max(off, 1e-4)
