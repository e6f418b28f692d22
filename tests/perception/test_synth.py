"""Synthetic recordings: embedded surface, depth noise model, scripted physics, tracks and the CLI."""

import numpy as np
import pytest

from empm_gym.perception import synth as S
from empm_gym.perception.fusion import fuse_frame
from empm_gym.perception.recording import Recording


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


@pytest.fixture
def embedding():
    rng = np.random.default_rng(0)
    particles = rng.uniform(-0.02, 0.02, (400, 3))
    sp, sn, _ = S._box_surface((0.04, 0.04, 0.04), 0.004)
    sp = sp - [0, 0, 0.02]
    return S.SurfaceEmbedding(sp, sn, particles), particles, sp, sn


def test_embedding_is_identity_at_rest(embedding):
    emb, x0, sp, sn = embedding
    p, n = emb.deform(x0)
    np.testing.assert_allclose(p, sp, atol=1e-7)
    np.testing.assert_allclose(n, sn, atol=1e-7)


def test_embedding_follows_rigid_and_affine_motion(embedding):
    emb, x0, sp, sn = embedding
    R = _rot([1, 2, 0.5], 0.7)
    t = np.array([0.1, -0.05, 0.2])
    p, n = emb.deform(x0 @ R.T + t)
    np.testing.assert_allclose(p, sp @ R.T + t, atol=1e-7)
    np.testing.assert_allclose(n, sn @ R.T, atol=1e-7)
    A = np.diag([1.3, 0.8, 1.0]) + 0.1 * np.eye(3)[::-1]
    p, n = emb.deform(x0 @ A.T)
    np.testing.assert_allclose(p, sp @ A.T, atol=1e-7)
    n_ref = sn @ np.linalg.inv(A)
    np.testing.assert_allclose(n, n_ref / np.linalg.norm(n_ref, axis=1, keepdims=True), atol=1e-7)


def test_depth_noise_grows_with_depth_squared():
    rng = np.random.default_rng(0)
    stds = []
    for z in (0.5, 1.0):
        d = np.full((200, 200), z)
        out = S.add_depth_noise(d, np.ones_like(d), rng, random_drop=0.0)
        assert np.all(out > 0)
        stds.append(np.std(out - z))
    assert stds[0] == pytest.approx(1.5e-3, rel=0.05)
    assert stds[1] / stds[0] == pytest.approx(4.0, rel=0.08)


def test_depth_noise_drops_edges_grazing_and_out_of_range():
    rng = np.random.default_rng(1)
    d = np.full((100, 100), 0.6)
    d[:, 50:] = 0.8                       # a depth edge at column 50
    d[:10] = np.inf                       # nothing there
    d[90:] = 2.0                          # beyond the range
    cos = np.ones_like(d)
    cos[40:50, :20] = 0.05                # grazing
    out = S.add_depth_noise(d, cos, rng)
    assert np.all(out[:10] == 0) and np.all(out[90:] == 0)
    assert np.all(out[40:50, :20] == 0)
    edge = out[10:90, 49:51]
    interior = out[15:38, 10:40]
    assert np.mean(edge == 0) > 0.4 and np.mean(interior == 0) < 0.02


def _box_sdf(P, lo, hi):
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(P - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)


def _rope_sdf(P):
    L, r = S._ROPE_LENGTH_M, S._ROPE_RADIUS_M
    radial, ax = np.hypot(P[:, 1], P[:, 2] - r) - r, np.abs(P[:, 0]) - L / 2
    return np.where(ax < 0, np.maximum(radial, ax), np.hypot(np.maximum(radial, 0), ax))


def _lump_sdf(P):
    """Signed distance (first order, exact on the surface) to the lump: its ellipsoid above the table."""
    c, ax = np.array([0.0, 0.0, S._LUMP_CENTRE_Z_M]), np.array(S._LUMP_SEMI_AXES_M)
    q = (P - c) / ax
    g = np.linalg.norm(2.0 * q / ax, axis=1)
    return np.maximum((np.einsum("ij,ij->i", q, q) - 1.0) / np.maximum(g, 1e-12), -P[:, 2])


@pytest.mark.parametrize("obj", ["dough", "rope", "lump"])
def test_tangent_splats_put_the_rendered_depth_on_the_true_surface_from_every_camera(obj):
    """With ``tangent`` the noise-free depth of the rendered object, back-projected, lies on the object's true
    surface: each surface point's disc is drawn in its tangent plane, and the silhouette has no holes. Flat
    discs (``tangent=False``), drawn at their centre's depth over their whole footprint, put every face inclined
    to a camera 0.3-0.8 mm too near (median), a bias no real depth camera has and that every rebuilt body
    carried until tangent discs became the default."""
    from scipy.ndimage import binary_fill_holes

    if obj == "dough":
        size = np.array(S._DOUGH_SIZE_M)
        sp, sn, _ = S._box_surface(size, 0.0015)
        lo, hi = np.array([-size[0] / 2, -size[1] / 2, 0.0]), np.array([size[0] / 2, size[1] / 2, size[2]])
        sdf, tol = (lambda P: _box_sdf(P, lo, hi)), 1e-5           # flat faces: exact
    elif obj == "lump":
        sp, sn, _ = S._lump_surface(0.0015)
        sdf, tol = _lump_sdf, 1e-4                                 # curvature radii of 3 cm and more
    else:
        sp, sn, _ = S._rope_surface(0.0015)
        sdf, tol = _rope_sdf, 1e-4                                 # a tangent plane on a 12 mm radius: 0.05 mm
    for cam in S.camera_ring(3, target=(0.0, 0.0, 0.03)):
        for tangent in (True, False):
            depth, _, label, cosv = S.render_view(S._StaticView(cam), sp, sn, np.full((len(sp), 3), 0.5), 0.0015,
                                                  [], tangent=tangent)
            seen = label == 1
            assert seen.sum() > 1000 and not (binary_fill_holes(seen) & ~seen).any()
            d = sdf(cam.backproject(np.where(seen & (cosv > 0.25), depth, 0.0)))
            if tangent:
                assert abs(np.median(d)) < tol and np.percentile(np.abs(d), 90) < 2 * tol, (cam.name, np.median(d))
            else:
                assert 3e-4 < np.median(d) < 1e-3, (cam.name, np.median(d))


def test_the_lump_is_the_part_of_its_ellipsoid_above_the_table():
    """The lump's particles fill the ellipsoid's cap above the table to its analytic volume, (a b / c^2) pi h^2
    (3 c - h) / 3 with h the cap's height; its surface points lie on the ellipsoid or on the footprint (z = 0),
    about the asked spacing apart, with outward normals; the scripts take its bounding box."""
    from scipy.spatial import cKDTree

    a, b, c = S._LUMP_SEMI_AXES_M
    h = c + S._LUMP_CENTRE_Z_M
    exact = a * b / c**2 * np.pi * h**2 * (3 * c - h) / 3
    m, _ = S.effect_material("lump", "none")
    sim = S.simulate("lump", m, script="press-release", frames=2, dx=0.005)
    x0 = sim["particles"][0]
    assert abs(sim["volumes"].sum() / exact - 1.0) < 0.03
    assert S.inside_lump(x0).all() and x0[:, 2].min() > 0.0
    sx, sy, sz = S._GEOMETRY["lump"].size
    assert np.isclose(sz, h) and np.ptp(x0[:, 0]) < sx and np.ptp(x0[:, 1]) < sy and x0[:, 2].max() < sz
    p, n, _ = S._lump_surface(0.0015)
    assert np.abs(_lump_sdf(p)).max() < 1e-9
    assert np.all(np.einsum("ij,ij->i", p - [0.0, 0.0, 0.3 * h], n) > 0)
    spacing = np.median(cKDTree(p).query(p, k=2)[0][:, 1])
    assert 0.0012 < spacing < 0.0018, spacing


def test_a_tangent_disc_narrower_than_a_pixel_still_draws_the_pixel_under_its_centre():
    """A 4 cm block at 64 x 48 px: a pixel is 17 mm wide there and a surface point's disc 1.5 mm, so almost every
    ray misses every disc; each disc still draws the pixel under its centre (as flat discs do), at the depth where
    that pixel's ray meets the disc's plane. Without it the block's mask was empty and no recording of it could
    be loaded. Where a pixel holds an edge its depth is the plane's, and the nearest plane wins, but the depths
    lie far nearer the true surface than the flat discs' (which draw every covered pixel at a disc centre's
    depth); a face's pixel on the table's side of its bottom edge stays the table's."""
    size = np.array(S._BLOCK_SIZE_M)
    sp, sn, _ = S._box_surface(size, 0.0015)
    lo, hi = np.array([-size[0] / 2, -size[1] / 2, 0.0]), np.array([size[0] / 2, size[1] / 2, size[2]])
    f = 420.0 * 64 / 848
    for cam in S.camera_ring(3, width=64, height=48, fx=f, fy=f, target=(0.0, 0.0, 0.03)):
        err = []
        for tangent in (True, False):
            depth, _, label, _ = S.render_view(S._StaticView(cam), sp, sn, np.full((len(sp), 3), 0.5), 0.0015,
                                               [], tangent=tangent)
            seen = label == 1
            err.append(np.abs(_box_sdf(cam.backproject(np.where(seen, depth, 0.0)), lo, hi)))
            if tangent:
                n_tangent = seen.sum()
        assert n_tangent >= 0.75 * len(err[1]) and np.sum(err[0] < 1e-6) >= 3, (cam.name, n_tangent)
        assert np.median(err[0]) < 0.7 * np.median(err[1]), (cam.name, np.median(err[0]), np.median(err[1]))


def test_rope_recording_physics_and_metadata(rope_rec):
    rec = Recording(rope_rec)
    gt = rec.ground_truth()
    assert gt["material"] == {"E": 5.0e4, "nu": 0.3, "density": 1100.0, "yield_stress": None}
    assert gt["seed"] == 1 and gt["object"] == "rope"
    # the render is much denser than the simulation particles identification would sample
    assert gt["render"]["surface_points"] > 4 * gt["scene"]["particle_count"]
    ctl = rec.controls()
    assert ctl["positions"].shape == (10, 2, 3) and ctl["shape"].tolist() == ["sphere", "sphere"]
    assert ctl["grip"][0].tolist() == [1, 1] and ctl["grip"][-1].tolist() == [0, 0]
    # CFL-chosen substeps: dt below the limit of the true material
    from empm_gym.sim import MaterialConfig

    c = MaterialConfig(**gt["material"]).wave_speed
    assert gt["scene"]["dt_s"] <= 0.4 * gt["scene"]["grid"]["dx"] / c
    z = [np.percentile(fuse_frame(rec, t)[:, 2], 99) for t in range(rec.num_frames)]
    assert z[0] < 0.03                         # lying on the table
    assert z[4] > 0.08                         # lifted by 8 cm while gripped
    assert min(z[7:]) < z[5] - 0.03            # put back down and released
    # depth is quantised to whole millimetres
    raw = rec.depth_raw(0, 0)
    assert raw.dtype == np.uint16 and rec.depth_scale == 0.001
    # some object pixels are missing (silhouette edges, grazing angles), most are not
    m = rec.mask(0, 4)
    missing = np.mean(rec.depth(0, 4)[m] == 0)
    assert 0.01 < missing < 0.5


def test_tracks_visible_where_the_object_is(rope_rec):
    rec = Recording(rope_rec)
    for c in range(rec.num_cameras):
        tr, vis = rec.tracks(c)
        assert tr.shape[:2] == vis.shape == (10, 128)
        assert 0.15 < vis.mean() < 0.9
        for t in (0, 4, 9):
            m = rec.mask(c, t)
            rc = np.round(tr[t][vis[t]]).astype(int)
            assert np.mean(m[rc[:, 0], rc[:, 1]]) > 0.95
    # tracks of a material point move with the object: lifted frames are higher in the image
    tr, vis = rec.tracks(0)
    both = vis[0] & vis[4]
    assert both.sum() > 10 and np.median(tr[4, both, 0] - tr[0, both, 0]) < -5  # rows decrease upwards


def test_synthesize_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="object must be one of"):
        S.synthesize(tmp_path / "a", "cloth")
    with pytest.raises(ValueError, match="MaterialConfig.E must be > 0"):
        S.synthesize(tmp_path / "b", "rope", E=-1.0)
    with pytest.raises(ValueError, match="frames must be >= 2"):
        S.synthesize(tmp_path / "c", "rope", frames=1)


def test_cli_synth(tmp_path, capsys):
    from empm_gym.cli import main

    out = tmp_path / "d"
    args = ["synth", str(out), "--object", "dough", "--frames", "2", "--cameras", "1", "--width", "64",
            "--height", "48", "--E", "8e4", "--yield-stress", "2500", "--seed", "4", "--quiet"]
    assert main(args) == 0
    assert "wrote" in capsys.readouterr().out
    gt = Recording(out).ground_truth()
    assert gt["material"]["E"] == 8e4 and gt["material"]["yield_stress"] == 2500 and gt["seed"] == 4
    assert main(args) == 2
    assert "not empty; pass overwrite=True" in capsys.readouterr().err
    assert main(args + ["--overwrite"]) == 0
    npy = Recording(out).depth(0, 1)
    # the same recording with 16-bit PNG depth: same millimetres, read back through the same reader
    png_out = tmp_path / "p"
    assert main([png_out.as_posix() if a == str(out) else a for a in args] + ["--depth-format", "png"]) == 0
    assert (png_out / "depth" / "0" / "1.png").is_file() and not (png_out / "depth" / "0" / "1.npy").exists()
    np.testing.assert_array_equal(Recording(png_out).depth(0, 1), npy)
    assert gt["render"]["tangent_splats"] is True
    # --flat-splats: the same scene drawn as flat discs, whose footprints overdraw the silhouette (at 64 x 48 px
    # the depths are mostly edge noise; test_tangent_splats_put_the_rendered_depth_on_the_true_surface_...)
    f_out = tmp_path / "f"
    assert main([f_out.as_posix() if a == str(out) else a for a in args] + ["--flat-splats"]) == 0
    assert Recording(f_out).ground_truth()["render"]["tangent_splats"] is False
    assert Recording(f_out).mask(0, 1).sum() > Recording(out).mask(0, 1).sum() > 0


def test_controls_replay_recipe_reaches_recorded_positions(dough_rec):
    """The docstring's recipe: add end-effectors at positions[0], command finite-difference velocities."""
    import math

    from empm_gym.perception.recording import controls_to_end_effectors, end_effector_velocities
    from empm_gym.sim import GridConfig, MaterialConfig, ModelBuilder, SolverMPM, TableConfig, sample_box

    rec = Recording(dough_rec)
    cfgs, pos, grip = controls_to_end_effectors(rec.controls())
    assert [c.shape for c in cfgs] == ["box", "box"]
    b = ModelBuilder(GridConfig(lower=(-0.12, -0.09, -0.04), upper=(0.12, 0.09, 0.12), dx=0.01),
                     table=TableConfig())
    w = b.add_world(MaterialConfig(E=1e5, nu=0.3, density=1200.0, yield_stress=3e3))
    x, v = sample_box((-0.025, -0.025, 0.0), (0.025, 0.025, 0.045), 0.01, 1)
    b.add_particles(w, x, v)
    for k, c in enumerate(cfgs):
        b.add_end_effector(w, c, pos[0, k])
    model = b.finalize("cpu")
    solver = SolverMPM(model)
    vel = end_effector_velocities(pos, rec.fps)
    n = int(math.ceil((1 / rec.fps) / (0.9 * solver.max_stable_dt(np.abs(vel).max()))))
    s0, s1, ctrl = model.state(), model.state(), model.control()
    for t in range(rec.num_frames - 1):
        ctrl.set(velocity=vel[t][None], grip=grip[t][None])
        for _ in range(n):
            solver.step(s0, s1, ctrl, 1.0 / (rec.fps * n))
            s0, s1 = s1, s0
        np.testing.assert_allclose(s0.ee_pos.numpy(), pos[t + 1], atol=2e-5)


def test_a_body_the_script_tears_without_a_fracture_is_flagged(tmp_path):
    """The synthesiser's MPM tears a rope whose end is lifted faster than the grid holds it together (lift-end in
    6 frames at dx = 1 cm, its end raised by half the rope's length within two frame intervals, parts it at
    frame 5): the recording, labelled `none`, shows a tear, so ground_truth.json says where the body parted and a
    warning says why. The same rope pulled apart stays whole (parted: null). body_parts counts the pieces of
    particle sets built to part or not."""
    kw = dict(object="rope", effect="none", frames=6, cameras=1, width=48, height=32, dx=0.01, progress=False)
    with pytest.warns(UserWarning, match=r"parts into 2 pieces from frame \d+ on without a fracture"):
        torn = S.synthesize(tmp_path / "torn", script="lift-end", **kw)
    parted = Recording(torn).ground_truth()["parted"]
    assert parted["pieces"] == 2 and 0 < parted["from_frame"] < 6 and parted["link_m"] == pytest.approx(0.02)
    whole = S.synthesize(tmp_path / "whole", script="pull-apart", **kw)
    assert Recording(whole).ground_truth()["parted"] is None
    # a bar of particles 5 mm apart, cut by a 3 cm gap from frame 2 on: 2 pieces at dx = 1 cm (link 2 cm),
    # none at dx = 2 cm (link 4 cm bridges the gap)
    bar = np.stack([np.arange(40) * 0.005, np.zeros(40), np.zeros(40)], 1)
    cut = bar + (np.arange(40) >= 20)[:, None] * [0.025, 0, 0]
    X = np.stack([bar, bar, cut, cut])
    assert S.body_parts(X, 0.01) == {"pieces": 2, "from_frame": 2, "link_m": 0.02}
    assert S.body_parts(X, 0.02) is None


def test_a_rig_with_calibration_and_depth_errors_writes_poses_and_depths_off_by_exactly_them(tmp_path):
    """``calibration_error`` and ``depth_bias``: the images are rendered with the true poses, the recording holds
    poses moved by the asked translation and rotation (about each optical centre) and depths scaled by 1 +- the
    bias; the noise and everything else are those of the same recording without errors, and only
    ground_truth.json says what was done."""
    from scipy.spatial.transform import Rotation

    kw = dict(frames=2, cameras=3, width=96, height=64, seed=5, progress=False, effect="none")
    clean = Recording(S.synthesize(tmp_path / "clean", "dough", **kw))
    off = Recording(S.synthesize(tmp_path / "off", "dough", calibration_error=(0.004, 0.5), depth_bias=0.02, **kw))
    rec = off.ground_truth()["sensor_errors"]
    assert "sensor_errors" in clean.ground_truth()
    for c in range(3):
        A, B = clean.c2w[c], off.c2w[c]
        dR = B[:3, :3] @ A[:3, :3].T
        assert np.linalg.norm(B[:3, 3] - A[:3, 3]) == pytest.approx(0.004, rel=1e-6)
        assert np.degrees(Rotation.from_matrix(dR).magnitude()) == pytest.approx(0.5, rel=1e-5)
        np.testing.assert_allclose(B[:3, 3] - A[:3, 3], rec["calibration_translation_m"][c], atol=1e-9)
        assert rec["calibration_rotation_deg"][c] == pytest.approx(0.5)
        s = rec["depth_scale"][c]
        assert s in (pytest.approx(1.02), pytest.approx(0.98))
        d0, d1 = clean.depth(c, 1), off.depth(c, 1)
        np.testing.assert_array_equal(d0 > 0, d1 > 0)  # the same pixels measured, the same noise drawn
        assert np.abs(d1[d0 > 0] - s * d0[d0 > 0]).max() <= 1.01e-3  # within one depth unit (1 mm) of the scale
        np.testing.assert_array_equal(clean.color(c, 1), off.color(c, 1))
        np.testing.assert_array_equal(clean.mask(c, 1), off.mask(c, 1))
    # another seed draws other directions and signs
    other = S.sensor_errors(clean.cameras, (0.004, 0.5), 0.02, seed=6)["record"]
    assert other["calibration_translation_m"] != rec["calibration_translation_m"]
    with pytest.raises(ValueError, match="calibration_error must be"):
        S.synthesize(tmp_path / "bad", "dough", calibration_error=(0.001,), **kw)
    with pytest.raises(ValueError, match="depth_bias must be a finite value >= 0"):
        S.sensor_errors(clean.cameras, (0.0, 0.0), -0.01)
    with pytest.raises(ValueError, match="a broken calibration"):
        S.sensor_errors(clean.cameras, (0.2, 0.0), 0.0)


def test_a_tracker_and_a_segmenter_with_errors_change_only_the_tracks_and_masks_by_what_was_asked(tmp_path):
    """``track_error`` (jitter, drift, outliers) and ``mask_error_px``: the tracks move off the exact ones by the
    asked amounts (frame 0's query points exact, the jumps 4-20 px), the masks grow or shrink by exactly that many
    pixels, and the depth, colours and controls are those of the same recording without errors."""
    from scipy import ndimage

    kw = dict(frames=12, cameras=2, width=96, height=64, seed=5, progress=False, effect="none", n_tracks=64)
    clean = Recording(S.synthesize(tmp_path / "clean", "dough", **kw))
    off = Recording(S.synthesize(tmp_path / "off", "dough", track_error=(0.0, 0.0, 0.25), mask_error_px=2, **kw))
    grown = ndimage.generate_binary_structure(2, 1)
    for c in range(2):
        (t0, v0), (t1, v1) = clean.tracks(c), off.tracks(c)
        np.testing.assert_array_equal(v0, v1)
        np.testing.assert_array_equal(t0[0], t1[0])  # the query points
        d = np.linalg.norm(t1 - t0, axis=-1)
        moved = d > 1e-4
        assert (moved <= v0).all()  # only visible entries jump
        assert 0.15 < moved[1:][v0[1:]].mean() < 0.35
        inside = (t1[..., 0] > 0) & (t1[..., 0] < 63) & (t1[..., 1] > 0) & (t1[..., 1] < 95)
        assert (d[moved & inside] > 4 - 1e-3).all() and (d[moved] < 20 + 1e-3).all()
        for t in (0, 11):
            np.testing.assert_array_equal(off.mask(c, t), ndimage.binary_dilation(clean.mask(c, t), grown, 2))
            np.testing.assert_array_equal(clean.depth(c, t), off.depth(c, t))
            np.testing.assert_array_equal(clean.color(c, t), off.color(c, t))
    gt = off.ground_truth()["sensor_errors"]
    assert gt["mask_error_px"] == 2 and gt["track_outlier_fraction"] == 0.25 and gt["track_outliers"] > 0
    # jitter and drift: the error's spread grows with the frame as a random walk's does, on top of the jitter
    tr = np.zeros((1, 400, 500, 2)) + 30.0
    noisy, _ = S.tracker_errors(tr, np.ones((1, 400, 500), bool), (1.0, 0.2, 0.0), width=96, height=64, seed=1)
    sd = (noisy - tr).std(axis=2).mean(-1)[0]
    assert sd[0] == 0.0
    assert sd[1] == pytest.approx(np.hypot(1.0, 0.2), rel=0.1)
    assert sd[100] == pytest.approx(np.hypot(1.0, 0.2 * 10), rel=0.1)
    with pytest.raises(ValueError, match="track_error must be"):
        S.synthesize(tmp_path / "bad", "dough", track_error=(1.0, 0.1), **kw)
    with pytest.raises(ValueError, match="a lost tracker"):
        S.synthesize(tmp_path / "bad", "dough", track_error=(1.0, 0.1, 0.9), **kw)
    with pytest.raises(ValueError, match="mask_error_px must be a whole number"):
        S.synthesize(tmp_path / "bad", "dough", mask_error_px=1.5, **kw)
