"""PGND episodes (kywind/pgnd) load through Recording: cameras, depth, masks, controls; corrupt episodes raise
RecordingError naming the file. The fixture ``data/pgnd_tiny`` is made by ``data/make_pgnd_fixture.py``."""

import importlib.util
import logging
import os
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from empm_gym.perception.recording import Recording, RecordingError

DATA = Path(__file__).parent / "data"
FLIP = np.diag([1.0, -1.0, -1.0])  # PGND's z-down board frame -> our z-up world (180 deg about x)


def _load_generator():
    spec = importlib.util.spec_from_file_location("make_pgnd_fixture", DATA / "make_pgnd_fixture.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


G = _load_generator()


@pytest.fixture(scope="module")
def pgnd_dir() -> Path:
    return DATA / "pgnd_tiny"


@pytest.fixture
def pgnd_copy(tmp_path, pgnd_dir) -> Path:
    dst = tmp_path / "episode_0000"
    shutil.copytree(pgnd_dir, dst)
    return dst


def _pgnd_project(p_world, i, ep):
    """Pixel (row, col) and z-depth of PGND-world points as PGND does it: x_cam = Rodrigues(rvec) x + tvec[:, 0]."""
    rvec = np.load(ep / "calibration" / "rvecs.npy")[i]
    tvec = np.load(ep / "calibration" / "tvecs.npy")[i, :, 0]
    K = np.load(ep / "calibration" / "intrinsics.npy")[i]
    R = Rotation.from_rotvec(rvec[:, 0]).as_matrix()  # = cv2.Rodrigues(rvec)[0]
    pc = np.asarray(p_world) @ R.T + tvec
    uv = pc @ K.T
    return np.stack([uv[:, 1] / uv[:, 2], uv[:, 0] / uv[:, 2]], 1), pc[:, 2]


def test_fixture_is_small(pgnd_dir):
    size = sum(f.stat().st_size for f in pgnd_dir.rglob("*") if f.is_file())
    assert size < 500_000


def test_pgnd_episode_loads(pgnd_dir):
    rec = Recording(pgnd_dir)
    assert rec.layout == "pgnd"
    assert (rec.num_cameras, rec.num_frames, rec.width, rec.height) == (2, 4, G.W, G.H)
    assert rec.fps == pytest.approx(30.0)  # from timestamps.txt
    assert rec.metadata["fps_source"].startswith("1 / median interval")
    assert rec.depth_scale == 0.001
    assert rec.serial_numbers == ["camera_0", "camera_1"]
    assert rec.has_masks and rec.mask_form == "simple" and not rec.has_controller_masks
    assert rec.has_controls and not rec.has_tracks
    np.testing.assert_allclose(rec.intrinsics, np.stack([G.K] * 2))


def test_cameras_follow_pgnd_convention(pgnd_dir):
    """A PGND-world point projected by PGND's convention lands where our Camera projects the same point in our
    z-up world; the cameras sit above the table (z > 0)."""
    rec = Recording(pgnd_dir)
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform([-0.1, -0.1, -0.15], [0.1, 0.1, 0.0], (50, 3)),
                          np.array([[0.04, 0.03, -0.04], [-0.04, -0.03, 0.0], [0.04, -0.03, 0.0]])])
    for i, cam in enumerate(rec.cameras):
        rc_pgnd, z_pgnd = _pgnd_project(pts, i, pgnd_dir)
        rc, z = cam.project(pts @ FLIP.T)
        np.testing.assert_allclose(rc, rc_pgnd, atol=1e-6)
        np.testing.assert_allclose(z, z_pgnd, atol=1e-9)
        np.testing.assert_allclose(cam.position, FLIP @ G.EYES[i], atol=1e-9)
        assert cam.position[2] > 0.2
    assert rec.metadata["world"].startswith("PGND calibration frame turned 180 deg")


def test_depth_in_metres_and_masks(pgnd_dir):
    rec = Recording(pgnd_dir)
    top = np.array([[0.0, 0.0, -0.04]])  # centre of the box's top face, PGND world
    for i, cam in enumerate(rec.cameras):
        (r, c), = np.round(_pgnd_project(top, i, pgnd_dir)[0]).astype(int)
        d = rec.depth(i, 0)
        assert d.dtype == np.float32 and d.shape == (G.H, G.W)
        # the exact z-depth at that pixel's centre, within the 1 mm quantisation and the sub-pixel offset
        assert abs(d[r, c] - _pgnd_project(top, i, pgnd_dir)[1][0]) < 0.006
        m = rec.mask(i, 0)
        assert m.dtype == bool and m[r, c] and 100 < m.sum() < 2000
        # every masked pixel back-projects onto the box, in our z-up world
        p = cam.backproject(d, m)
        assert np.all(p[:, 2] > -0.002) and np.all(p[:, 2] < 0.042)
        assert np.all(np.abs(p[:, 0]) < 0.042) and np.all(np.abs(p[:, 1]) < 0.032)
        assert rec.color(i, 0).shape == (G.H, G.W, 3) and rec.color(i, 0).dtype == np.uint8
        # the table (z = 0) elsewhere: the image's bottom row lies on the table near the camera
        pt = cam.backproject(d, np.zeros_like(m) | (np.arange(G.H)[:, None] == G.H - 1))
        np.testing.assert_allclose(pt[:, 2], 0.0, atol=0.003)


def test_controls_grip_and_pose(pgnd_dir):
    c = Recording(pgnd_dir).controls()
    assert c["positions"].shape == (4, 2, 3)
    np.testing.assert_allclose(c["positions"], G.ARM_POS @ FLIP.T, atol=1e-6)
    np.testing.assert_array_equal(c["grip"], G.GRIP_EXPECTED)  # 401 of 800 open, 399 closed
    R = Rotation.from_quat(c["orientations"].reshape(-1, 4)).as_matrix().reshape(4, 2, 3, 3)
    np.testing.assert_allclose(R, FLIP @ G.ARM_ROT, atol=1e-5)  # the gripper's axes, in our world
    assert list(c["shape"]) == ["sphere", "sphere"]
    np.testing.assert_allclose(c["radius"], [0.04, 0.04])


def test_assumptions_are_logged(pgnd_copy, caplog):
    (pgnd_copy / "timestamps.txt").unlink()
    with caplog.at_level(logging.INFO, logger="empm_gym.perception"):
        rec = Recording(pgnd_copy)
    assert rec.fps == 30.0 and rec.metadata["fps_source"].startswith("assumed")
    text = "\n".join(r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING)
    assert "30 fps assumed" in text
    assert "sphere(s) of radius 0.04 m" in text and "< 0.5" in text
    assert any("turned 180 deg about x" in r.getMessage() for r in caplog.records)


def test_one_arm_and_position_only(pgnd_copy, caplog):
    for t in range(G.T):
        rows = [G.ARM_POS[t, 0], *G.ARM_ROT[t, 0].T, [G.GRIPPER[t, 0], 0.0, 0.0]]
        np.savetxt(pgnd_copy / "robot" / f"{t:06d}.txt", np.array(rows), fmt="%.6f")
    c = Recording(pgnd_copy).controls()
    assert c["positions"].shape == (4, 1, 3)
    np.testing.assert_array_equal(c["grip"][:, 0], G.GRIP_EXPECTED[:, 0])
    for t in range(G.T):  # PGND's readers accept a single row: a position only
        np.savetxt(pgnd_copy / "robot" / f"{t:06d}.txt", G.ARM_POS[t, :1], fmt="%.6f")
    with caplog.at_level(logging.WARNING, logger="empm_gym.perception"):
        c = Recording(pgnd_copy).controls()
    np.testing.assert_allclose(c["positions"][:, 0], G.ARM_POS[:, 0] @ FLIP.T, atol=1e-6)
    np.testing.assert_array_equal(c["grip"], 1)  # openness 0, as PGND reads it
    assert any("positions only" in r.getMessage() for r in caplog.records)


def test_load_recording_body_volume(pgnd_dir):
    from empm_gym.identification.data import load_recording

    scene, obs, views = load_recording(pgnd_dir, single_view=False, progress=False)
    assert scene.fps == pytest.approx(30.0)
    assert abs(scene.table.height) < 0.003
    vol = float(np.sum(scene.volumes))
    assert 0.7 * G.BOX_VOLUME_M3 < vol < 1.15 * G.BOX_VOLUME_M3
    lo, hi = scene.particles.min(0), scene.particles.max(0)
    assert np.all(lo > [-0.05, -0.04, -0.005]) and np.all(hi < [0.05, 0.04, 0.045])
    np.testing.assert_allclose(scene.ee_positions, G.ARM_POS @ FLIP.T, atol=1e-6)
    np.testing.assert_array_equal(scene.ee_grip, G.GRIP_EXPECTED)
    assert obs.fps == pytest.approx(30.0) and len(obs.points) == G.T
    for p in obs.points:  # the fused object points lie on the box (z up, table at 0)
        assert np.all(p[:, 2] > -0.004) and np.all(p[:, 2] < 0.044)


def _snapshot(root: Path):
    return {os.path.relpath(os.path.join(d, n), root): os.stat(os.path.join(d, n)).st_mtime_ns
            for d, dirs, files in os.walk(root) for n in dirs + files}


def test_reading_never_writes(pgnd_copy):
    before = _snapshot(pgnd_copy)
    rec = Recording(pgnd_copy)
    for c in range(rec.num_cameras):
        for t in range(rec.num_frames):
            rec.color(c, t), rec.depth(c, t), rec.mask(c, t)
    rec.controls()
    assert _snapshot(pgnd_copy) == before


# -- corrupt variants: each raises RecordingError naming the file ------------------------------------------


def _save(path, a):
    np.save(path, a)


CORRUPT = {
    "depth frame deleted": (lambda p: (p / "camera_1/depth/000002.png").unlink(),
                            r"camera_1/depth/000002\.png: missing depth frame 2 of camera 1"),
    "rgb frame deleted": (lambda p: (p / "camera_0/rgb/000003.jpg").unlink(),
                          r"camera_0/rgb/000003\.jpg: missing rgb frame 3 of camera 0"),
    "mask frame deleted": (lambda p: (p / "camera_0/mask/000001.png").unlink(),
                           r"camera_0/mask/000001\.png: missing mask frame 1"),
    "extra mask frame": (lambda p: shutil.copy(p / "camera_1/mask/000003.png", p / "camera_1/mask/000004.png"),
                         r"camera_1/mask/000004\.png: mismatched frame counts"),
    "camera folder gap": (lambda p: (p / "camera_1").rename(p / "camera_2"), r"camera_1: folder missing"),
    "intrinsics wrong shape": (lambda p: _save(p / "calibration/intrinsics.npy", np.zeros((2, 3, 4))),
                               r"calibration/intrinsics\.npy: intrinsics must have shape \[cameras, 3, 3\]"),
    "intrinsics one matrix": (lambda p: _save(p / "calibration/intrinsics.npy", G.K),
                              r"calibration/intrinsics\.npy: intrinsics must have shape"),
    "intrinsics count": (lambda p: _save(p / "calibration/intrinsics.npy", np.stack([G.K] * 3)),
                         r"calibration/intrinsics\.npy: camera count mismatch: 3 intrinsics but .* 2 camera"),
    "intrinsics zero focal": (lambda p: _save(p / "calibration/intrinsics.npy", np.stack([G.K * [[0], [1], [1]]] * 2)),
                              r"calibration/intrinsics\.npy: intrinsics of camera 0: focal lengths"),
    "rvecs wrong shape": (lambda p: _save(p / "calibration/rvecs.npy", np.zeros((2, 4, 1))),
                          r"calibration/rvecs\.npy: must have shape \[cameras, 3, 1\]"),
    "tvecs count": (lambda p: _save(p / "calibration/tvecs.npy", np.zeros((3, 3, 1))),
                    r"calibration/tvecs\.npy: camera count mismatch"),
    "tvecs missing": (lambda p: (p / "calibration/tvecs.npy").unlink(), r"calibration/tvecs\.npy: file missing"),
    "rvecs not npy": (lambda p: (p / "calibration/rvecs.npy").write_bytes(b"not numpy"),
                      r"calibration/rvecs\.npy: cannot read \.npy"),
    "robot txt unreadable": (lambda p: (p / "robot/000001.txt").write_text("0.1 0.2 zero\n1 0 0\n"),
                             r"robot/000001\.txt: cannot read robot telemetry"),
    "robot txt empty": (lambda p: (p / "robot/000001.txt").write_text(""),
                        r"robot/000001\.txt: robot telemetry must be rows of 3 numbers"),
    "robot txt 4 rows": (lambda p: np.savetxt(p / "robot/000002.txt", np.zeros((4, 3))),
                         r"robot/000002\.txt: robot telemetry must be rows of 3 numbers: 5 rows for one arm"),
    "robot not a rotation": (lambda p: np.savetxt(p / "robot/000002.txt", np.full((9, 3), 0.5)),
                             r"robot/000002\.txt: arm 0: rows 2-4 are not a rotation"),
    "robot arms differ": (lambda p: np.savetxt(p / "robot/000003.txt", np.vstack([G.ARM_POS[3, 0], np.eye(3),
                                                                                [0.0, 0, 0]])),
                          r"robot/000003\.txt: 1 arm\(s\) but 000000\.txt has 2"),
    "robot frame deleted": (lambda p: (p / "robot/000003.txt").unlink(),
                            r"robot/000003\.txt: missing robot frame 3; the camera images have 4 frames"),
    "extra robot frame": (lambda p: shutil.copy(p / "robot/000003.txt", p / "robot/000004.txt"),
                          r"robot/000004\.txt: mismatched frame counts: robot/ has 5 frames but the camera images "
                          r"have 4"),
    "raw capture robot names": (lambda p: [f.rename(f.with_name(f"17000000{f.stem[-2:]}.123.txt"))
                                           for f in sorted((p / "robot").iterdir())],
                                r"robot/000000\.txt: file missing: .*raw PGND capture named by timestamps"),
    "timestamps unreadable": (lambda p: (p / "timestamps.txt").write_text("a b\nc d\n"),
                              r"timestamps\.txt: cannot read frame timestamps"),
    "timestamps columns": (lambda p: (p / "timestamps.txt").write_text("1 2 3\n4 5 6\n"),
                           r"timestamps\.txt: expected 2 columns"),
    "first rgb unreadable": (lambda p: (p / "camera_0/rgb/000000.jpg").write_bytes(b"\xff\xd8 broken"),
                             r"camera_0/rgb/000000\.jpg: cannot read image"),
}


@pytest.mark.parametrize("name", list(CORRUPT))
def test_corrupt_episode_names_the_file(pgnd_copy, name):
    corrupt, pattern = CORRUPT[name]
    corrupt(pgnd_copy)
    with pytest.raises(RecordingError, match=pattern):
        Recording(pgnd_copy)


LAZY = {
    "rgb unreadable": (lambda p: (p / "camera_1/rgb/000002.jpg").write_bytes(b"garbage"),
                       lambda r: r.color(1, 2), r"camera_1/rgb/000002\.jpg: cannot read image"),
    "depth 8-bit": (lambda p: iio.imwrite(p / "camera_0/depth/000001.png", np.zeros((G.H, G.W), np.uint8)),
                    lambda r: r.depth(0, 1), r"camera_0/depth/000001\.png: a depth PNG must be 16-bit"),
    "depth wrong size": (lambda p: iio.imwrite(p / "camera_0/depth/000001.png", np.zeros((10, 12), np.uint16)),
                         lambda r: r.depth(0, 1), r"camera_0/depth/000001\.png: depth image has size 12x10"),
    "depth in metres": (lambda p: iio.imwrite(p / "camera_1/depth/000000.png", np.ones((G.H, G.W), np.uint16)),
                        lambda r: r.depth(1, 0), r"camera_1/depth/000000\.png: median depth 0\.001 m"),
    "mask wrong size": (lambda p: iio.imwrite(p / "camera_1/mask/000003.png", np.zeros((5, 5), np.uint8)),
                        lambda r: r.mask(1, 3), r"camera_1/mask/000003\.png: mask has size 5x5"),
}


@pytest.mark.parametrize("name", list(LAZY))
def test_corrupt_image_names_the_file_when_read(pgnd_copy, name):
    corrupt, read, pattern = LAZY[name]
    corrupt(pgnd_copy)
    rec = Recording(pgnd_copy)  # images are read lazily
    with pytest.raises(RecordingError, match=pattern):
        read(rec)


def test_dataset_root_points_to_its_episodes(tmp_path, pgnd_dir):
    shutil.copytree(pgnd_dir, tmp_path / "rope" / "episode_0000")
    with pytest.raises(RecordingError, match=r"metadata\.json: file missing.*holds PGND episodes.*episode_0000"):
        Recording(tmp_path / "rope")


def test_metadata_json_wins(pgnd_copy, phystwin_dir):
    """A folder with metadata.json is read as our layout even if it has camera_<i>/ folders."""
    for f in phystwin_dir.iterdir():
        (shutil.copytree if f.is_dir() else shutil.copy)(f, pgnd_copy / f.name)
    assert Recording(pgnd_copy).layout == "phystwin"
