"""Localisation pieces of the discrepancy doctor on constructed data (pure numpy, fast)."""

import numpy as np
import pytest

from empm_gym.identification.doctor.features import (
    count_pieces,
    frame_residuals,
    localise,
    point_residuals,
    regions,
    summary_features,
    track_errors,
)
from empm_gym.identification.doctor.phases import PHASES, phase_of_frames, segment_phases

FPS = 30.0


def _block(nx=20, ny=6, nz=4, size=(0.2, 0.06, 0.04), z0=0.0):
    g = np.stack(np.meshgrid(*[np.linspace(-s / 2, s / 2, n) for s, n in zip(size, (nx, ny, nz))],
                             indexing="ij"), -1).reshape(-1, 3)
    g[:, 2] += size[2] / 2 + z0
    return g


def _scenario(rng=None, noise=0.0):
    """One gripper: approach 0-9, contact 10-11, holding 12-19, lift 20-34, release+fall 35-44, rest 45-59."""
    T = 60
    block = _block()
    top = block[:, 2].max()
    r = 0.01
    ee = np.zeros((T, 1, 3))
    grip = np.zeros((T, 1))
    c = np.zeros((T, 3))  # object offset
    hover = top + r  # ee centre when touching the top surface
    for t in range(T):
        if t < 10:
            ee[t, 0] = (0, 0, hover + 0.1 - 0.1 * t / 9.5)  # reaches contact distance at t = 10
        elif t < 20:
            ee[t, 0] = (0, 0, hover)
        elif t < 35:
            ee[t, 0] = (0, 0, hover + 0.005 * (t - 19))
            c[t] = (0, 0, 0.005 * (t - 19))
        else:
            ee[t, 0] = (0, 0, hover + 0.3)
        grip[t] = 1.0 if 12 <= t < 35 else 0.0
    ee[9, 0, 2] = hover + 0.03  # still outside contact at frame 9
    h = c[34, 2]
    for t in range(35, 45):  # falls to the table, reaching it at frame 44
        c[t, 2] = h * (1 - ((t - 34) / 10) ** 2)
    c[45:, 2] = 0.0
    obs = []
    rng = rng or np.random.default_rng(0)
    for t in range(T):
        p = block + c[t]
        if noise:
            p = p + rng.normal(0, noise, p.shape)
        obs.append(p)
    return ee, grip, obs, np.array([r]), block, c


def test_known_phases_found():
    ee, grip, obs, r, _, _ = _scenario(noise=0.0005)
    phases = segment_phases(ee, grip, FPS, obs, r)
    assert phases[0].start == 0 and phases[-1].stop == 60
    assert all(a.stop == b.start for a, b in zip(phases, phases[1:]))
    assert all(p.name in PHASES for p in phases)
    expect = {"approach": (0, 10), "contact": (10, 12), "holding": (12, 20), "moving": (20, 35),
              "after_release": (35, 45), "at_rest": (45, 60)}
    got = {p.name: (p.start, p.stop) for p in phases}
    assert [p.name for p in phases] == list(expect)
    for name, (s, e) in expect.items():
        assert abs(got[name][0] - s) <= 1 and abs(got[name][1] - e) <= 1, (name, got[name])
    lab = phase_of_frames(phases, 60)
    assert lab[15] == "holding" and lab[25] == "moving" and lab[55] == "at_rest"
    # the object wholly hidden while it is held and lifted (a hand over it): the contact it was last seen in holds
    hidden = [p if not 14 <= t < 30 else np.zeros((0, 3)) for t, p in enumerate(obs)]
    assert [(p.name, p.start, p.stop) for p in segment_phases(ee, grip, FPS, hidden, r)] == \
        [(p.name, p.start, p.stop) for p in phases]


def test_no_contact_is_rest():
    ee, grip, obs, r, block, _ = _scenario()
    ee = ee + np.array([0, 0, 1.0])  # far away
    obs = [block] * 60
    phases = segment_phases(ee, grip, FPS, obs, r)
    assert [p.name for p in phases] == ["at_rest"]


def test_residual_helpers():
    a = np.zeros((3, 3))
    b = np.array([[0, 0, 0.01]])
    np.testing.assert_allclose(point_residuals(a, b), 0.01)
    fr = frame_residuals([a, np.zeros((0, 3))], np.stack([b, b]))
    assert fr[0] == pytest.approx(0.01) and np.isnan(fr[1])
    tr = np.zeros((2, 2, 3))
    st = tr + np.array([0.003, 0.004, 0])
    e = track_errors(tr, np.array([[1, 0], [1, 1]]), st)
    assert e[0, 0] == pytest.approx(0.005) and np.isnan(e[0, 1])


def test_regions():
    pts = np.array([[0, 0, 0.1], [0.5, 0, 0.002], [0.5, 0, 0.1], [1.0, 0, 0.1]])
    ee = np.array([[0, 0, 0.12], [1.0, 0, 0.13]])
    lab = regions(pts, ee, [0.01, 0.01])
    assert list(lab) == ["near_ee_0", "on_table", "free", "near_ee_1"]


def test_drifting_region_localised():
    """Observed points of the +x end (near gripper 0) drift sideways; the simulation stays put."""
    T = 30
    block = _block()
    sim = np.repeat(block[None], T, 0)

    def observe(sel):
        out = []
        for t in range(T):
            p = block.copy()
            p[sel, 1] += 0.0002 * t  # stays below half the grid spacing: monotone residual
            out.append(p + np.random.default_rng(t).normal(0, 0.0003, p.shape))
        return out

    ee = np.zeros((T, 2, 3))
    ee[:, 0] = (0.11, 0, 0.02)   # end-effector at the +x end
    ee[:, 1] = (-0.11, 0, 0.02)  # and at the -x end
    grip = np.ones((T, 2))
    r = np.array([0.01, 0.01])
    obs = observe(block[:, 0] > 0.05)
    phases = segment_phases(ee, grip, FPS, obs, r)
    assert [p.name for p in phases] == ["holding"]
    loc = localise(phases, obs, sim, ee, r, near_m=0.05, table_band_m=-1.0)
    assert loc["worst_region"] == "near_ee_0"
    assert loc["worst_cell"] == ("holding", "near_ee_0")
    assert loc["halves"]["positive"] > 3 * loc["halves"]["negative"]
    assert min(loc["worst_frames"]) >= T - 5
    f = summary_features(phases, obs, sim, ee, grip, r, FPS, near_m=0.05)
    assert f["residual_asymmetry"] > 0.5
    assert f["residual_near_ee_vs_free"] > 2.0
    # mirrored: the -x end drifts -> negative asymmetry, near_ee_1 worst
    obs2 = observe(block[:, 0] < -0.05)
    loc2 = localise(phases, obs2, sim, ee, r, near_m=0.05, table_band_m=-1.0)
    f2 = summary_features(phases, obs2, sim, ee, grip, r, FPS, near_m=0.05)
    assert loc2["worst_region"] == "near_ee_1" and f2["residual_asymmetry"] < -0.5


def test_pieces():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 0.01, (400, 3))
    b = rng.normal(0, 0.01, (300, 3)) + [0.2, 0, 0]
    stray = np.array([[1.0, 1.0, 1.0]])
    assert count_pieces(np.concatenate([a, b, stray])) == 2
    assert count_pieces(a) == 1
    assert count_pieces(np.zeros((0, 3))) == 0


def test_pieces_parted_only_by_an_end_effector_that_hides_the_gap_are_one():
    """A rope seen as two stretches with a 6 cm gap: one piece where a plate (a box turned by 30 degrees about z)
    covers the gap and each stretch reaches its surface, as a pressing plate hides what it presses; two where
    the plate sits beside the gap or is too small to reach both stretches; two without end-effectors."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    x = np.concatenate([rng.uniform(-0.15, -0.03, 600), rng.uniform(0.03, 0.15, 600)])
    rope = np.stack([x, rng.normal(0, 0.004, len(x)), 0.01 + rng.normal(0, 0.004, len(x))], 1)
    rot = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    plate = (np.array([0.0, 0.0, 0.03]), np.array([0.04, 0.02, 0.01]), rot)
    assert count_pieces(rope) == 2
    assert count_pieces(rope, occluders=[plate]) == 1
    assert count_pieces(rope, occluders=[(plate[0] + [0, 0.2, 0], plate[1], rot)]) == 2   # beside the gap
    assert count_pieces(rope, occluders=[(plate[0], np.array([0.01, 0.01, 0.005]), rot)]) == 2  # too small
    # a sphere hides it as well (size (r, r, -1)); with a contact gap large enough to reach the stretches
    sphere = (np.array([0.0, 0.0, 0.05]), np.array([0.02, 0.02, -1.0]), None)
    assert count_pieces(rope, occluders=[sphere]) == 2
    assert count_pieces(rope, occluders=[sphere], occluder_gap_m=0.045) == 1


def test_features_on_scenario_and_slip():
    ee, grip, obs, r, block, c = _scenario(noise=0.0005)
    T = len(obs)
    phases = segment_phases(ee, grip, FPS, obs, r)
    sim = np.stack([block + c[t] for t in range(T)])
    # tracks: points on the top near the gripper; observed ones slide down 1 mm per frame while lifted
    top = np.flatnonzero((block[:, 2] >= block[:, 2].max() - 1e-9) & (np.abs(block[:, 0]) < 0.02))
    st = sim[:, top]
    tr = st.copy()
    for t in range(20, 35):
        tr[t, :, 2] -= 0.001 * (t - 19)
    tr[35:] = tr[34]
    vis = np.ones(tr.shape[:2])
    vis[:, 0] = 0  # one track never visible
    f = summary_features(phases, obs, sim, ee, grip, r, FPS, tracks=tr, visible=vis, sim_tracks=st)
    assert f["track_slip_m"] == pytest.approx(0.015, abs=0.002)
    assert f["pieces_observed"] == 1 and f["pieces_simulated"] == 1
    assert abs(f["rest_drift_m"]) < 0.003
    assert abs(f["table_slide_m"]) < 0.003
    for k, v in f.items():
        assert isinstance(v, float), k
    # without tracks, or with no release: NaN, no crash
    f0 = summary_features(phases[:3], obs[:20], sim[:20], ee[:20], grip[:20], r, FPS)
    assert np.isnan(f0["track_slip_m"]) and np.isnan(f0["residual_after_release_vs_contact"])
    assert np.isnan(f0["oscillation_decay"])


def test_rest_drift_and_table_slide_detected():
    ee, grip, obs, r, block, c = _scenario()
    T = len(obs)
    phases = segment_phases(ee, grip, FPS, obs, r)
    sim = np.stack([block + c[t] for t in range(T)])
    obs2 = [p + [0.0005 * max(0, t - 45), 0, 0] for t, p in enumerate(obs)]  # slow slide while at rest
    f = summary_features(phases, obs2, sim, ee, grip, r, FPS)
    assert f["table_slide_m"] > 0.005
    assert f["rest_drift_m"] > 0.005


def test_figures_and_report_written(tmp_path):
    from empm_gym.identification.doctor.features import FEATURE_INFO
    from empm_gym.identification.doctor.report import (
        plot_candidate_gains,
        plot_residual_heatmap,
        plot_residual_timeline,
        write_report_md,
    )

    ee, grip, obs, r, block, c = _scenario(noise=0.0005)
    T = len(obs)
    phases = segment_phases(ee, grip, FPS, obs, r)
    sim = np.stack([block + c[t] * 0.9 for t in range(T)])
    fr = frame_residuals(obs, sim)
    fr[20:22] = np.nan  # the object wholly hidden there: no residual, the frames hatched
    f1 = plot_residual_timeline(fr, fr * 0.5, phases, 40, tmp_path / "fig" / "timeline.png", "rope", fps=FPS,
                                hidden=[20, 21])
    res = point_residuals(obs[30], sim[30])
    f2 = plot_residual_heatmap({"frame 30, base": (obs[30], res), "frame 30, refit": (obs[30], res * 0.3)},
                               tmp_path / "fig" / "heat.png", "worst frame")
    f3 = plot_candidate_gains(["plasticity", "viscosity", "gripper_slip"], 0.004, [0.0035, 0.0039, 0.002], 0.0003,
                              tmp_path / "fig" / "gains.png")
    for f in (f1, f2, f3):
        assert f.exists() and f.stat().st_size > 1000
    loc = localise(phases, obs, sim, ee, r)
    md = write_report_md(
        tmp_path / "report.md",
        {"headline": "gripper_slip explains the gap", "heldout_gain_mm": 2.0},
        {"Residual over time": "fig/timeline.png", "Residual on the object": "fig/heat.png"},
        {"Where the disagreement is": loc["table"],
         "Candidates": [{"effect": "plasticity", "gain_mm": 0.5}, {"effect": "gripper_slip", "gain_mm": 2.0}]},
        features=summary_features(phases, obs, sim, ee, grip, r, FPS), feature_info=FEATURE_INFO)
    text = md.read_text()
    assert text.index("gripper_slip explains the gap") < text.index("Where the disagreement is")
    assert "![Residual over time](fig/timeline.png)" in text and "| effect | gain_mm |" in text


def _held_block(lag=0.0, slip=0.0, seed=0, T=30, M=40, noise=1.5e-3):
    """A box gripper closed on a block, at rest, lifted 8 cm over frames 6-14, held still, lowered over 20-25;
    ``M`` tracked points on the block beside the jaws follow the gripper ``lag`` frames late and fall behind by
    ``slip`` of its travel, with depth-like noise. Returns (tracks, visible, ee [T, 1, 3], grip, size, points)."""
    rng = np.random.default_rng(seed)
    z = np.interp(np.arange(T), [0, 6, 14, 20, 25, T - 1], [0.03, 0.03, 0.11, 0.11, 0.05, 0.05])
    ee = np.zeros((T, 1, 3))
    ee[:, 0, 2] = z
    size = np.array([[0.02, 0.03, 0.02]])
    offs = np.column_stack([rng.uniform(0.021, 0.03, M) * rng.choice([-1, 1], M), rng.uniform(-0.03, 0.03, M),
                            rng.uniform(-0.02, 0.02, M)])
    late = np.interp(np.arange(T) - lag, np.arange(T), z)  # the gripper's height lag frames earlier
    tz = late - slip * (late - z[0])
    tracks = offs[None] + np.column_stack([np.zeros(T), np.zeros(T), tz])[:, None, :]
    tracks = tracks + rng.normal(0, noise, tracks.shape)
    points = [tracks[t] for t in range(T)]
    return tracks, np.ones((T, M), bool), ee, np.ones((T, 1)), size, points


@pytest.mark.parametrize("lag", [0.0, 1.0, -0.5, 2.0])
def test_a_lag_between_controls_and_images_is_read_from_the_held_material(lag):
    from empm_gym.identification.doctor.core import lag_note
    from empm_gym.identification.doctor.features import control_lag

    tracks, vis, ee, grip, size, pts = _held_block(lag=lag)
    r = control_lag(tracks, vis, ee, grip, [size[0]], pts, contact_dist_m=0.015)
    # first order in the lag: within 0.1 frame up to a frame; a 2-frame lag across the lift's corners reads 1.85
    assert abs(r["lag_frames"] - lag) < (0.1 if abs(lag) <= 1 else 0.2), r
    assert abs(r["slip_share"]) < (0.05 if abs(lag) <= 1 else 0.12) and r["followers"] == 40, r
    note = lag_note(r, 30.0)
    if lag == 0.0:
        assert note is None
    else:
        assert note is not None and f"{abs(r['lag_frames']):.2f} frames" in note
        assert ("after" if lag > 0 else "before") in note
        assert ("reads low" in note) == (abs(r["lag_frames"]) > 1.0)  # a 2-frame lag reads 1.85: said so


def test_material_sliding_in_the_grip_is_no_measure_of_a_lag():
    from empm_gym.identification.doctor.core import lag_note
    from empm_gym.identification.doctor.features import control_lag

    # the points fall behind by half the gripper's travel (and a frame): they move by the slip, not by the
    # controls' clock, and no lag is read from them
    tracks, vis, ee, grip, size, pts = _held_block(lag=1.0, slip=0.5)
    r = control_lag(tracks, vis, ee, grip, [size[0]], pts, contact_dist_m=0.015)
    assert np.isnan(r["lag_frames"]) and r["followers"] == 0 and r["points"] == 40, r
    assert abs(r["slip_share"] - 0.5) < 0.05, r
    assert lag_note(r, 30.0) is None
    # a gripper at one steady speed throughout: a lag is an offset there, and is not read
    tracks, vis, ee, grip, size, pts = _held_block(lag=1.0)
    ee[:, 0, 2] = 0.03 + 0.002 * np.arange(len(ee))
    r = control_lag(tracks, vis, ee, grip, [size[0]], pts, contact_dist_m=0.015)
    assert np.isnan(r["lag_frames"])
    # no tracks at all
    assert control_lag(None, None, ee, grip, [size[0]], pts)["samples"] == 0


def test_controls_delayed_to_the_images_clock_read_no_lag():
    from empm_gym.identification.data import delayed_positions
    from empm_gym.identification.doctor.features import control_lag

    tracks, vis, ee, grip, size, pts = _held_block(lag=1.0)
    r = control_lag(tracks, vis, delayed_positions(ee, 1.0), grip, [size[0]], pts, contact_dist_m=0.015)
    assert abs(r["lag_frames"]) < 0.1, r
    # exact: a whole frame is the previous row, half a frame the midpoint, the first row held
    assert np.array_equal(delayed_positions(ee, 1.0)[1:], ee[:-1]) and np.array_equal(delayed_positions(ee, 1.0)[0], ee[0])
    assert np.allclose(delayed_positions(ee, 0.5)[1:], 0.5 * (ee[1:] + ee[:-1]))
    assert np.array_equal(delayed_positions(ee, -2.0)[:-2], ee[2:])


def _turned_block(lag=0.0, seed=0, T=40, M=40, noise=1.5e-3):
    """:func:`_held_block`'s gripper that, once it has lifted the block, turns it by 90 degrees about x (a wrist
    roll about its own centre, frames 16-30) and holds it there; the tracked points are carried rigidly,
    ``lag`` frames late. Returns (tracks, visible, ee [T, 1, 3], grip, size, points, quaternions [T, 1, 4])."""
    from empm_gym.perception.scripts import axis_angle_quaternions

    rng = np.random.default_rng(seed)
    frames = np.arange(T, dtype=float)
    z_of = lambda t: np.interp(t, [0, 6, 14, T - 1], [0.03, 0.03, 0.11, 0.11])
    th_of = lambda t: np.interp(t, [0, 16, 30, T - 1], [0.0, 0.0, np.pi / 2, np.pi / 2])
    ee = np.zeros((T, 1, 3))
    ee[:, 0, 2] = z_of(frames)
    q = axis_angle_quaternions((1.0, 0.0, 0.0), th_of(frames))[:, None, :]
    size = np.array([[0.02, 0.03, 0.02]])
    offs = np.column_stack([rng.uniform(0.021, 0.03, M) * rng.choice([-1, 1], M), rng.uniform(-0.03, 0.03, M),
                            rng.uniform(-0.02, 0.02, M)])
    late = frames - lag
    c, s = np.cos(th_of(late)), np.sin(th_of(late))
    tracks = np.empty((T, M, 3))
    tracks[:, :, 0] = offs[:, 0]
    tracks[:, :, 1] = c[:, None] * offs[:, 1] - s[:, None] * offs[:, 2]
    tracks[:, :, 2] = s[:, None] * offs[:, 1] + c[:, None] * offs[:, 2] + z_of(late)[:, None]
    tracks = tracks + rng.normal(0, noise, tracks.shape)
    return tracks, np.ones((T, M), bool), ee, np.ones((T, 1)), size, [tracks[t] for t in range(T)], q


@pytest.mark.parametrize("lag", [0.0, 1.0])
def test_the_lag_is_read_in_a_turning_grippers_own_frame(lag):
    """Material a gripper carries round as it turns is still carried: in the gripper's frame it stays put, and a
    lag is its trailing the carried motion. Taken in the world's axes, the turn reads as the material moving on
    its own."""
    from empm_gym.identification.doctor.features import control_lag

    tracks, vis, ee, grip, size, pts, q = _turned_block(lag=lag)
    r = control_lag(tracks, vis, ee, grip, [size[0]], pts, contact_dist_m=0.015, ee_orientations=q)
    assert abs(r["lag_frames"] - lag) < 0.15 and r["followers"] == 40, r
    blind = control_lag(tracks, vis, ee, grip, [size[0]], pts, contact_dist_m=0.015)
    assert not (abs(blind["lag_frames"] - lag) < 0.15 and blind["followers"] == 40), blind


def test_a_turned_box_is_measured_along_its_own_axes():
    from empm_gym.identification.doctor.phases import contact_distances, surface_gap
    from empm_gym.perception.scripts import axis_angle_quaternions

    size = np.array([0.01, 0.05, 0.01])               # a long, thin jaw along y
    p = np.array([[0.0, 0.0, 0.04]])                  # 4 cm above its centre
    assert surface_gap(p, np.zeros(3), size)[0] == pytest.approx(0.03)
    q = axis_angle_quaternions((1, 0, 0), [np.pi / 2])    # turned about x: the jaw now stands along z
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(q).as_matrix()[0]
    assert surface_gap(p, np.zeros(3), size, R)[0] == pytest.approx(-0.01)     # inside it
    d = contact_distances(np.zeros((1, 1, 3)), [tuple(size)], [p], q[None])
    assert d[0, 0] == pytest.approx(-0.01)


def test_a_gripper_turning_in_place_moves_the_object():
    """A closed gripper that turns without travelling drives the object: its frames are ``moving``, not
    ``holding``, once the controls' orientations say so."""
    from empm_gym.identification.doctor.phases import segment_phases

    tracks, vis, ee, grip, size, pts, q = _turned_block()
    ee[:] = ee[14]                                   # lifted already (from frame 14 on), it only turns
    still = segment_phases(ee, grip, FPS, pts, [size[0]], contact_dist_m=0.015)
    turning = segment_phases(ee, grip, FPS, pts, [size[0]], contact_dist_m=0.015, ee_orientations=q)
    lab = lambda ph, t: next(p.name for p in ph if p.start <= t < p.stop)
    assert lab(still, 22) == "holding"
    assert lab(turning, 22) == "moving" and lab(turning, 36) == "holding"
