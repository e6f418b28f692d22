"""Recording I/O: round trips, the PhysTwin raw layout, validation errors, safe unpickling, read-only reads."""

import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from empm_gym.perception import recording as R
from empm_gym.perception.cameras import intrinsics_matrix, look_at
from empm_gym.perception.recording import Recording, RecordingError, RecordingWriter, write_recording


def _snapshot(root: Path):
    """Every path under root with its size and modification time (ns)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames + filenames:
            p = os.path.join(dirpath, n)
            st = os.stat(p)
            out[os.path.relpath(p, root)] = (st.st_size, st.st_mtime_ns)
    return out


def _read_everything(rec: Recording):
    for c in range(rec.num_cameras):
        for t in range(rec.num_frames):
            rec.color(c, t), rec.depth(c, t), rec.depth_raw(c, t)
            if rec.has_masks:
                rec.mask(c, t), rec.controller_masks(c, t)
        if rec.has_tracks:
            rec.tracks(c)
    if rec.has_controls:
        rec.controls()
    rec.ground_truth()
    _ = rec.cameras


def _toy_arrays(C=2, T=3, W=32, H=24, seed=0):
    rng = np.random.default_rng(seed)
    K = [intrinsics_matrix(30.0 + i, 31.0, 15.5, 11.5) for i in range(C)]
    c2w = [look_at([0.5 * np.cos(a), 0.5 * np.sin(a), 0.4], [0, 0, 0]) for a in np.linspace(0, 2, C)]
    color = [[rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(T)] for _ in range(C)]
    depth = [[rng.integers(0, 2000, (H, W)).astype(np.uint16) for _ in range(T)] for _ in range(C)]
    masks = [[rng.random((H, W)) > 0.5 for _ in range(T)] for _ in range(C)]
    cmasks = [[rng.random((H, W)) > 0.8 for _ in range(T)] for _ in range(C)]
    controls = {"positions": rng.normal(size=(T, 2, 3)), "grip": rng.integers(0, 2, (T, 2)),
                "shape": np.array(["sphere", "box"]), "radius": np.array([0.02, 0.0]),
                "half_extents": np.array([[0.01, 0.01, 0.01], [0.01, 0.03, 0.02]])}
    tracks = [(rng.uniform(0, 20, (T, 7, 2)).astype(np.float32), rng.random((T, 7)) > 0.5) for _ in range(C)]
    return dict(intrinsics=K, c2w=c2w, width=W, height=H, fps=30, color=color, depth_raw=depth, masks=masks,
                controller_masks=cmasks, controls=controls, tracks=tracks, ground_truth={"E": 1.0e5, "seed": 3})


@pytest.mark.parametrize("depth_format", ["npy", "png"])
def test_write_read_round_trip_exact(tmp_path, depth_format):
    a = _toy_arrays()
    # the depth median must be plausible metres for depth(): keep raw units in 100..2000 mm
    a["depth_raw"] = [[np.maximum(d, 100) for d in cam] for cam in a["depth_raw"]]
    write_recording(tmp_path / "r", depth_format=depth_format, **a)
    rec = Recording(tmp_path / "r")
    assert (rec.num_cameras, rec.num_frames, rec.width, rec.height, rec.fps) == (2, 3, 32, 24, 30.0)
    np.testing.assert_array_equal(rec.intrinsics, np.array(a["intrinsics"]))
    np.testing.assert_array_equal(rec.c2w, np.array(a["c2w"]))
    for c in range(2):
        for t in range(3):
            np.testing.assert_array_equal(rec.color(c, t), a["color"][c][t])
            raw = rec.depth_raw(c, t)
            assert raw.dtype == np.uint16
            np.testing.assert_array_equal(raw, a["depth_raw"][c][t])
            np.testing.assert_array_equal(rec.depth(c, t), a["depth_raw"][c][t].astype(np.float32) * np.float32(0.001))
            np.testing.assert_array_equal(rec.mask(c, t), a["masks"][c][t])
            np.testing.assert_array_equal(rec.controller_mask(c, t), a["controller_masks"][c][t])
        tr, vis = rec.tracks(c)
        np.testing.assert_array_equal(tr, a["tracks"][c][0])
        np.testing.assert_array_equal(vis, a["tracks"][c][1])
    ctl = rec.controls()
    np.testing.assert_array_equal(ctl["positions"], a["controls"]["positions"])
    np.testing.assert_array_equal(ctl["grip"], a["controls"]["grip"])
    assert ctl["shape"].tolist() == ["sphere", "box"]
    np.testing.assert_array_equal(ctl["half_extents"], a["controls"]["half_extents"])
    assert rec.ground_truth() == {"E": 1.0e5, "seed": 3}
    assert rec.mask_form == "phystwin" and rec.has_controller_masks


def test_simple_mask_layout_round_trip(tmp_path):
    a = _toy_arrays(C=1, T=2)
    a.pop("controller_masks")
    write_recording(tmp_path / "r", mask_layout="simple", **a)
    rec = Recording(tmp_path / "r")
    assert rec.mask_form == "simple" and not rec.has_controller_masks
    assert (tmp_path / "r" / "mask" / "0" / "1.png").is_file()
    np.testing.assert_array_equal(rec.mask(0, 1), a["masks"][0][1])
    assert rec.controller_mask(0, 1) is None


def test_synthetic_recording_reads_back_what_was_written(tmp_path, monkeypatch):
    """Capture what synthesize hands to the writer and compare with what Recording reads."""
    from empm_gym.perception import synth

    captured = {}

    class Capturing(RecordingWriter):
        def write_frame(self, cam, t, **kw):
            captured[(cam, t)] = {k: (v if isinstance(v, list) else np.array(v)) for k, v in kw.items()}
            super().write_frame(cam, t, **kw)

        def write_controls(self, **arrays):
            captured["controls"] = arrays
            super().write_controls(**arrays)

        def write_tracks(self, cam, tracks, visibility, folder="tracks"):
            captured[("tracks", cam)] = (np.array(tracks), np.array(visibility))
            super().write_tracks(cam, tracks, visibility, folder)

    monkeypatch.setattr(synth, "RecordingWriter", Capturing)
    out = synth.synthesize(tmp_path / "s", "dough", frames=2, cameras=2, width=96, height=64, progress=False)
    rec = Recording(out)
    assert rec.num_frames == 2 and rec.num_cameras == 2 and rec.has_controls and rec.has_tracks
    for c in range(2):
        for t in range(2):
            w = captured[(c, t)]
            np.testing.assert_array_equal(rec.color(c, t), w["color"])
            units = np.where(w["depth_m"] > 0, np.round(w["depth_m"] / 0.001), 0).astype(np.uint16)
            np.testing.assert_array_equal(rec.depth_raw(c, t), units)
            np.testing.assert_array_equal(rec.mask(c, t), w["mask"])
            ms = rec.controller_masks(c, t)
            assert len(ms) == len(w["controller_mask"]) == 2
            for got, want in zip(ms, w["controller_mask"]):
                np.testing.assert_array_equal(got, want)
        tr, vis = rec.tracks(c)
        np.testing.assert_array_equal(tr, captured[("tracks", c)][0])
        np.testing.assert_array_equal(vis, captured[("tracks", c)][1])
    ctl = rec.controls()
    np.testing.assert_array_equal(ctl["positions"], captured["controls"]["positions"])
    np.testing.assert_array_equal(ctl["grip"], captured["controls"]["grip"])
    gt = rec.ground_truth()
    assert gt["object"] == "dough" and gt["material"]["yield_stress"] == 2.0e3


def test_phystwin_fixture_loads(phystwin_dir):
    rec = Recording(phystwin_dir)
    assert (rec.num_cameras, rec.num_frames, rec.width, rec.height) == (2, 3, 64, 48)
    assert rec.depth_scale == 0.001 and rec.serial_numbers == ["cam_a", "cam_b"]
    assert not (phystwin_dir / "calibrate.json").exists()  # calibration came from the pickle
    assert rec.c2w.shape == (2, 4, 4)
    np.testing.assert_allclose(rec.c2w[0][:3, 3], [0.35, -0.1, 0.3])
    raw = rec.depth_raw(0, 0)
    assert raw.dtype == np.uint16
    d = rec.depth(0, 0)
    np.testing.assert_allclose(d, raw * np.float32(0.001))
    assert 0.2 < np.median(d[d > 0]) < 1.5  # millimetres became metres
    assert rec.color(1, 2).shape == (48, 64, 3)
    m = rec.mask(0, 1)
    assert m.dtype == bool and 10 < m.sum() < 64 * 48 / 2
    hands = rec.controller_masks(1, 2)
    assert len(hands) == 1 and hands[0].any() and not np.any(hands[0] & rec.mask(1, 2))
    tr, vis = rec.tracks(0)  # from cotracker/0.npz
    assert tr.shape == (3, 5, 2) and vis.shape == (3, 5) and vis.dtype == bool
    assert not rec.has_controls


def test_zero_padded_frame_names(phystwin_copy):
    for kind in ("color", "depth"):
        for c in ("0", "1"):
            for f in (phystwin_copy / kind / c).iterdir():
                f.rename(f.with_name(f"{int(f.stem):06d}{f.suffix}"))
    rec = Recording(phystwin_copy)
    ref = Recording(Path(__file__).parent / "data" / "phystwin_tiny")
    np.testing.assert_array_equal(rec.depth_raw(1, 2), ref.depth_raw(1, 2))
    np.testing.assert_array_equal(rec.color(0, 1), ref.color(0, 1))


def test_reading_never_writes(phystwin_dir, dough_rec):
    for path in (phystwin_dir, dough_rec):
        before = _snapshot(path)
        rec = Recording(path)
        _read_everything(rec)
        from empm_gym.perception.fusion import estimate_table_plane, fuse_frame, load_controls

        fuse_frame(rec, 0)
        estimate_table_plane(rec)
        load_controls(rec, nb_neighbors=5)
        assert _snapshot(path) == before


# -- corrupt and inconsistent recordings ---------------------------------------------------------

def _edit_metadata(path, **changes):
    md = json.loads((path / "metadata.json").read_text())
    md.update(changes)
    (path / "metadata.json").write_text(json.dumps(md))


def test_missing_frame_names_camera_and_frame(phystwin_copy):
    (phystwin_copy / "depth" / "1" / "2.npy").unlink()
    with pytest.raises(RecordingError, match=r"depth/1/2\.npy.*missing depth frame 2 of camera 1"):
        Recording(phystwin_copy)


def test_missing_mask_frame(phystwin_copy):
    (phystwin_copy / "mask" / "0" / "1" / "0.png").unlink()
    with pytest.raises(RecordingError, match=r"mask/0/1/0\.png.*missing mask frame 0 of camera 0"):
        Recording(phystwin_copy)


def test_camera_count_mismatch_calibration(phystwin_copy):
    with open(phystwin_copy / "calibrate.pkl", "rb") as f:
        c2w = pickle.load(f)
    with open(phystwin_copy / "calibrate.pkl", "wb") as f:
        pickle.dump(c2w[:1], f)
    with pytest.raises(RecordingError, match=r"calibrate\.pkl.*camera count mismatch: 1 camera poses.*2 intrinsics"):
        Recording(phystwin_copy)


def test_camera_count_mismatch_folders(phystwin_copy):
    shutil.copytree(phystwin_copy / "color" / "1", phystwin_copy / "color" / "2")
    with pytest.raises(RecordingError, match=r"color.*camera count mismatch.*found folders \['0', '1', '2'\]"):
        Recording(phystwin_copy)


def test_camera_count_mismatch_serials(phystwin_copy):
    _edit_metadata(phystwin_copy, serial_numbers=["a", "b", "c"])
    with pytest.raises(RecordingError, match=r"metadata\.json.*camera count mismatch"):
        Recording(phystwin_copy)


@pytest.mark.parametrize("K, pattern", [
    ([[[0.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]]] * 2, r"focal lengths fx=0\.0.*must be > 0"),
    ([[[50.0, 0, 31.5], [0, -5, 23.5], [0, 0, 1]]] * 2, r"fy=-5\.0 must be > 0"),
    ([[[50.0, 0, 31.5], [0, 50, 23.5]]] * 2, r"'intrinsics' must have shape \[cameras, 3, 3\], got \[2, 2, 3\]"),
    ([[[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 2]]] * 2, r"must be \[\[fx, s, cx\]"),
    ([[[50.0, 0, 900], [0, 50, 23.5], [0, 0, 1]]] * 2, r"principal point.*outside"),
    ([[[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]]] * 3, r"camera count mismatch"),
])
def test_bad_intrinsics(phystwin_copy, K, pattern):
    _edit_metadata(phystwin_copy, intrinsics=K)
    with pytest.raises(RecordingError, match=r"metadata\.json.*" + pattern):
        Recording(phystwin_copy)


@pytest.mark.parametrize("changes, pattern", [
    ({"WH": [64]}, r"'WH' must be \[width, height\]"),
    ({"fps": 0}, r"'fps' must be a positive"),
    ({"frame_num": 0}, r"'frame_num' must be a positive integer"),
    ({"depth_scale": -1}, r"'depth_scale'.*must lie in \(0, 1\]"),
    ({"frame_num": 4}, r"3\.png.*missing color frame 3 of camera 0"),
])
def test_bad_metadata(phystwin_copy, changes, pattern):
    _edit_metadata(phystwin_copy, **changes)
    with pytest.raises(RecordingError, match=pattern):
        Recording(phystwin_copy)


def test_missing_metadata_and_calibration(phystwin_copy):
    (phystwin_copy / "calibrate.pkl").unlink()
    with pytest.raises(RecordingError, match=r"no camera calibration: expected calibrate\.json or calibrate\.pkl"):
        Recording(phystwin_copy)
    (phystwin_copy / "metadata.json").unlink()
    with pytest.raises(RecordingError, match=r"metadata\.json: file missing"):
        Recording(phystwin_copy)


def test_bad_calibration_json(phystwin_copy):
    c2w = np.eye(4)
    c2w[:3, :3] *= 2.0  # scaled, not a rotation
    (phystwin_copy / "calibrate.json").write_text(json.dumps({"c2w": [np.eye(4).tolist(), c2w.tolist()]}))
    with pytest.raises(RecordingError, match=r"calibrate\.json: camera 1: the rotation part"):
        Recording(phystwin_copy)


def test_depth_units_wrong(phystwin_copy):
    # depth stored in metres (floats) while metadata says millimetres
    p = phystwin_copy / "depth" / "0" / "1.npy"
    np.save(p, np.load(p).astype(np.float32) / 1000.0)
    rec = Recording(phystwin_copy)
    rec.depth(0, 0)
    with pytest.raises(RecordingError, match=r"depth/0/1\.npy: median depth 0\.000\d+ m.*depth units"):
        rec.depth(0, 1)


def test_depth_wrong_size_and_negative(phystwin_copy):
    np.save(phystwin_copy / "depth" / "1" / "0.npy", np.zeros((10, 10), np.uint16))
    np.save(phystwin_copy / "depth" / "1" / "1.npy", -np.ones((48, 64), np.float32))
    rec = Recording(phystwin_copy)
    with pytest.raises(RecordingError, match=r"depth/1/0\.npy: depth image has size 10x10.*WH=\[64, 48\]"):
        rec.depth(1, 0)
    with pytest.raises(RecordingError, match=r"depth/1/1\.npy: depth holds negative values"):
        rec.depth(1, 1)


def test_pickled_object_depth_refused(phystwin_copy):
    np.save(phystwin_copy / "depth" / "0" / "2.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    rec = Recording(phystwin_copy)
    with pytest.raises(RecordingError, match=r"depth/0/2\.npy: cannot read \.npy"):
        rec.depth(0, 2)


@pytest.mark.parametrize("controls, pattern", [
    ({"positions": np.full((3, 1, 3), np.nan)}, r"'positions' holds non-finite values \(first at frame 0"),
    ({"positions": np.zeros((2, 1, 3))}, r"'positions' has 2 frames but metadata\.json says frame_num=3"),
    ({"positions": np.zeros((3, 1, 2))}, r"'positions' must have shape \[T, K, 3\]"),
    ({"positions": np.zeros((3, 1, 3)), "grip": np.full((3, 1), 0.5)}, r"'grip' must hold only 0"),
    ({"positions": np.zeros((3, 1, 3)), "radius": np.array([np.inf])}, r"'radius' holds non-finite"),
    ({"positions": np.zeros((3, 1, 3)), "shape": np.array(["cone"])}, r"'shape' entries must be one of"),
    ({"positions": np.zeros((3, 1, 3)), "shape": np.array(["box"]), "half_extents": np.zeros((1, 3))},
     r"end-effector 0 \(box\) needs half_extents > 0"),
    ({"grip": np.zeros((3, 1))}, r"missing array 'positions'"),
])
def test_bad_controls(phystwin_copy, controls, pattern):
    np.savez(phystwin_copy / "controls.npz", **controls)
    with pytest.raises(RecordingError, match=r"controls\.npz: " + pattern):
        Recording(phystwin_copy)


def test_bad_tracks(phystwin_copy):
    np.savez(phystwin_copy / "cotracker" / "1.npz", tracks=np.zeros((3, 4, 3)), visibility=np.ones((3, 4), bool))
    rec = Recording(phystwin_copy)
    rec.tracks(0)
    with pytest.raises(RecordingError, match=r"cotracker/1\.npz: 'tracks' must have shape \[T, N, 2\]"):
        rec.tracks(1)
    np.savez(phystwin_copy / "cotracker" / "1.npz", tracks=np.zeros((3, 4, 2)), visibility=np.ones((3, 5), bool))
    with pytest.raises(RecordingError, match=r"'visibility' must have shape \[3, 4\]"):
        rec.tracks(1)


# -- calibrate.pkl safety -------------------------------------------------------------------------

class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _EvilEval:
    def __reduce__(self):
        return (eval, ("__import__('pathlib').Path('/tmp/never').touch()",))


def test_malicious_calibration_pickle_is_refused(phystwin_copy, tmp_path):
    marker = tmp_path / "pwned"
    with open(phystwin_copy / "calibrate.pkl", "wb") as f:
        pickle.dump([np.eye(4), _Evil(marker)], f)
    with pytest.raises(RecordingError, match=r"calibrate\.pkl: refused to unpickle: it references (posix|os)\.system"):
        Recording(phystwin_copy)
    assert not marker.exists()
    with open(phystwin_copy / "calibrate.pkl", "wb") as f:
        pickle.dump([_EvilEval()], f)
    with pytest.raises(RecordingError, match=r"refused to unpickle: it references builtins\.eval"):
        R.load_calibration_pickle(phystwin_copy / "calibrate.pkl")


def test_safe_unpickler_reads_numpy1_and_protocol0_pickles(tmp_path):
    mats = [np.eye(4), look_at([0.3, 0.1, 0.5], [0, 0, 0])]
    for proto in (0, 2, 4, 5):
        data = pickle.dumps(mats, protocol=proto)
        if proto == 0:  # as written by numpy 1.x, whose module is numpy.core
            data = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
        p = tmp_path / f"c{proto}.pkl"
        p.write_bytes(data)
        np.testing.assert_array_equal(R.load_calibration_pickle(p), np.array(mats))
    p.write_bytes(b"not a pickle")
    with pytest.raises(RecordingError, match=r"c5\.pkl: not a readable pickle"):
        R.load_calibration_pickle(p)


# -- writer safety --------------------------------------------------------------------------------

def test_writer_refuses_non_empty_and_keeps_user_files(tmp_path):
    a = _toy_arrays(C=1, T=3)
    out = tmp_path / "r"
    write_recording(out, **a)
    (out / "notes.txt").write_text("mine")
    (out / "color" / "0" / "notes.txt").write_text("mine too")
    with pytest.raises(RecordingError, match=r"not empty; pass overwrite=True"):
        write_recording(out, **a)
    b = _toy_arrays(C=1, T=2, seed=1)
    write_recording(out, overwrite=True, **b)
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "color" / "0" / "notes.txt").read_text() == "mine too"
    assert not (out / "color" / "0" / "2.png").exists()  # stale frame of the old recording removed
    rec = Recording(out)
    assert rec.num_frames == 2
    np.testing.assert_array_equal(rec.color(0, 1), b["color"][0][1])
    other = tmp_path / "docs"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    with pytest.raises(RecordingError, match=r"not a recording \(no metadata\.json\)"):
        write_recording(other, overwrite=True, **a)
    assert (other / "thesis.tex").read_text() == "x"


def test_controls_to_end_effectors_and_velocities():
    T = 4
    pos = np.zeros((T, 2, 3))
    pos[:, 1, 0] = np.arange(T) * 0.01
    cfgs, p, g = R.controls_to_end_effectors({"positions": pos, "shape": np.array(["sphere", "box"]),
                                              "radius": np.array([0.015, 0.0]),
                                              "half_extents": np.array([[0.0, 0, 0], [0.01, 0.02, 0.03]])})
    assert [c.shape for c in cfgs] == ["sphere", "box"]
    assert cfgs[0].radius == 0.015 and cfgs[1].half_extents == (0.01, 0.02, 0.03)
    assert g.shape == (T, 2) and np.all(g == 1)  # default: closed
    v = R.end_effector_velocities(p, 30.0)
    assert v.shape == (T - 1, 2, 3)
    np.testing.assert_allclose(v[:, 1, 0], 0.3)
    np.testing.assert_allclose(p[0] + v.sum(0) / 30.0, p[-1])
