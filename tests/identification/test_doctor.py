"""The discrepancy doctor: bad input, the noise test, and hidden-effect recordings named end to end."""

import dataclasses
import json
import logging
import math

import numpy as np
import pytest

from empm_gym.identification.doctor import DoctorConfig, DoctorError, candidate_params, diagnose
from empm_gym.identification.doctor.core import SIGNATURE_FEATURES
from empm_gym.identification.problem import Observations, Scene
from empm_gym.identification.uncertainty import measurement_noise, paired_gain_test
from empm_gym.sim import EndEffectorConfig, sample_box
from empm_gym.sim.effects import EFFECTS


def _still_scene(T=20, with_ee=True, motion=0.0, seed=0):
    rng = np.random.default_rng(seed)
    x, vol = sample_box((-0.02, -0.02, 0.0), (0.02, 0.02, 0.04), 0.01, 8, seed=1)
    ee = [EndEffectorConfig(shape="sphere", radius=0.01)] if with_ee else []
    pos = np.tile([[[0.0, 0.0, 0.06]]], (T, 1, 1)) if with_ee else None
    scene = Scene(x, vol, fps=30.0, ee_configs=ee, ee_positions=pos, ee_grip=np.zeros((T, 1)) if with_ee else None)
    pts = [x + rng.normal(0, 5e-4, x.shape) + [motion * t / T, 0, 0] for t in range(T)]
    return scene, Observations(30.0, pts, surface=True)


def test_controls_are_delayed_whole_and_checked():
    from empm_gym.identification.data import delayed_controls

    scene, _ = _still_scene(T=10)
    pos = np.asarray(scene.ee_positions).copy()
    pos[:, 0, 2] += 0.01 * np.arange(10)
    grip = np.zeros((10, 1))
    grip[4:] = 1
    scene = dataclasses.replace(scene, ee_positions=pos, ee_grip=grip)
    d = delayed_controls(scene, 2.0)
    assert np.allclose(d.ee_positions[2:], pos[:-2]) and np.allclose(d.ee_positions[:2], pos[0])
    assert d.ee_grip[:, 0].tolist() == [0] * 6 + [1] * 4  # the grip closes two frames later too
    assert np.array_equal(scene.ee_positions, pos)  # the scene given is not changed
    assert delayed_controls(scene, 0.0) is scene
    for bad in (float("nan"), 9.0, -12.0):
        with pytest.raises(ValueError, match="control delay"):
            delayed_controls(scene, bad)


def test_a_turn_is_delayed_with_the_positions():
    """A gripper turning at a constant rate, delayed by 1.5 frames, is where it was 1.5 frames earlier: its angle
    interpolated at that rate (not the nearest frame's), held at the first frame."""
    from scipy.spatial.transform import Rotation

    from empm_gym.identification.data import delayed_controls
    from empm_gym.perception.scripts import axis_angle_quaternions

    scene, _ = _still_scene(T=10)
    q = axis_angle_quaternions((0, 0, 1), 0.1 * np.arange(10))[:, None, :]
    d = delayed_controls(dataclasses.replace(scene, ee_orientations=q), 1.5)
    angle = Rotation.from_quat(d.ee_orientations[:, 0]).as_rotvec()[:, 2]
    np.testing.assert_allclose(angle, 0.1 * np.clip(np.arange(10) - 1.5, 0, None), atol=1e-9)


def test_too_short_recording_is_refused():
    scene, obs = _still_scene(T=8)
    with pytest.raises(DoctorError, match="too few"):
        diagnose(scene, obs, progress=False)


def test_recording_without_controls_is_refused():
    scene, obs = _still_scene(with_ee=False)
    with pytest.raises(DoctorError, match="no end-effector controls"):
        diagnose(scene, obs, progress=False)


def test_the_doctor_says_when_its_grid_is_too_coarse_for_the_body():
    """doctor.json gives the body's thickness in cells of the grid, with a note when that is marginal (under
    3 cells: a fitted stiffness biased by up to tens of per cent) or too coarse (under 1.5); a block 4 cells thick
    gets no note."""
    T = 20
    for height, cells, says in ((0.04, 4.0, None), (0.024, 2.4, "stiffness may be biased"),
                                (0.012, 1.2, "too coarse for the body")):
        x, vol = sample_box((-0.03, -0.03, 0.0), (0.03, 0.03, height), 0.01, 8, seed=1)
        scene = Scene(x, vol, fps=30.0, dx=0.01, ee_configs=[EndEffectorConfig(shape="sphere", radius=0.01)],
                      ee_positions=np.tile([[[0.0, 0.0, 0.08]]], (T, 1, 1)), ee_grip=np.zeros((T, 1)))
        res = diagnose(scene, Observations(30.0, [x] * T, surface=True), progress=False)
        assert res["grid"]["dx_m"] == 0.01 and res["grid"]["cells_across"] == pytest.approx(cells, rel=0.15)
        notes = [n for n in res["notes"] if n.startswith("the doctor's body")]
        assert (notes == []) if says is None else (len(notes) == 1 and says in notes[0]), notes


def test_recording_without_motion_gets_no_verdict(tmp_path):
    scene, obs = _still_scene()
    res = diagnose(scene, obs, progress=False, out_dir=tmp_path)
    assert res["effect"] == "none" and res["decidable"] is False
    assert "hardly moves" in res["reason"]
    assert json.loads((tmp_path / "doctor.json").read_text())["decidable"] is False


def test_motion_that_end_effectors_drive_counts_without_centroid_motion():
    """A body pulled apart symmetrically or pressed in one place keeps its centroid still, yet the controls act on
    it: the doctor counts how far an end-effector travels while it touches the observed points (the gate of
    ``test_recording_without_motion_gets_no_verdict`` once refused every rope recording of pull-apart,
    press-release and squeeze-lift as "hardly moves"). An end-effector moving clear of the body drives nothing."""
    import dataclasses

    from empm_gym.identification.doctor.core import _driven_m, _motion_m

    T = 20
    scene, obs = _still_scene(T=T)
    assert _motion_m(obs) < 2e-3 and _driven_m(scene, obs, T) == 0.0  # touching but still
    pos = scene.ee_positions.copy()
    pos[:, 0, 2] = 0.045  # the sphere dips 5 mm into the top and slides 3 cm along x
    pos[:, 0, 0] = np.linspace(0.0, 0.03, T)
    assert _driven_m(dataclasses.replace(scene, ee_positions=pos), obs, T) == pytest.approx(0.03, abs=2e-3)
    pos[:, 0, 2] = 0.1  # the same slide 6 cm above the body
    assert _driven_m(dataclasses.replace(scene, ee_positions=pos), obs, T) == 0.0


def test_measurement_noise_recovers_the_depth_noise():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.05, 0.05, (6000, 2))
    for sigma in (5e-4, 1e-3):  # points 1.3 mm apart
        pts = np.c_[xy, rng.normal(0.0, sigma, len(xy))]
        est = measurement_noise([pts])
        assert 0.85 * sigma < est < 1.15 * sigma, (sigma, est)


def test_paired_gain_test_separates_a_real_gain_from_noise():
    rng = np.random.default_rng(1)
    base = 1.0 + 0.1 * rng.standard_normal(30)
    same = base + 0.02 * rng.standard_normal(30)
    better = 0.6 * base
    assert not paired_gain_test(base, same)["significant"]
    t = paired_gain_test(base, better, added_params=1)
    assert t["significant"] and t["lower"] > 0.3 and abs(t["gain"] - 0.4) < 1e-9
    # the same 4 % gain pays for one parameter but not for three
    slight = 0.95 * base
    assert paired_gain_test(base, slight, added_params=1, penalty_per_param=0.04)["significant"]
    assert not paired_gain_test(base, slight, added_params=3, penalty_per_param=0.04)["significant"]
    # a 5 % gain on average whose interval reaches below the 4 % penalty does not pay for the parameter
    wobbly = base * (0.95 + 0.06 * np.random.default_rng(0).standard_normal(30))
    t = paired_gain_test(base, wobbly, added_params=1, penalty_per_param=0.04)
    assert t["gain"] > 0.04 and 0.0 < t["lower"] < 0.04 and not t["significant"], t


def test_a_fit_at_the_edge_of_its_window_is_widened_to_the_optimum():
    """A candidate refits E within E_refit_factor of the base fit; an effect can move the stiffness that explains
    a recording far from that (a torn rope's elastic fit ends at the softest E of its box while the material is
    25 times stiffer). A fit that ends at an edge of its window inside the box is fitted again with the window
    stretched to the box on that side, and reaches the optimum beyond the old edge; a fit inside its window,
    or at the box's own bound, stays as it is. Several fits are widened together (one batched simulation where
    they share a body): each comes out as it does alone."""
    from empm_gym.identification.doctor.core import _fit_candidate, _widened, _window_edge
    from empm_gym.sim import MaterialConfig

    from .test_effect_params import _observe, _scene

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)
    start = truth.replace(E=600.0)
    scene, obs = _scene(start), _observe(truth)
    cfg = DoctorConfig(candidate_iters=4, popsize=6, seed=1)
    narrow = _fit_candidate("base", scene, obs, start, (300.0, 1000.0), 7, cfg, False)
    assert narrow.params["E"] > 1000.0 / 1.05 and _window_edge(narrow, (100.0, 3e4)) == 1
    assert _window_edge(narrow, (100.0, 1000.0)) == 0  # the window's edge is the box's bound: nothing beyond
    wide, = _widened([(narrow, scene, start)], obs, (100.0, 3e4), 7, cfg, False)
    assert wide.bounds["E"] == (300.0, 3e4)
    assert wide.params["E"] == pytest.approx(3.0e3, rel=0.1) and wide.fit_loss < 0.5 * narrow.fit_loss
    assert _window_edge(wide, (100.0, 3e4)) == 0
    # widened beside a fit that stays and another that widens: the same refit as alone, to the bit (CPU)
    stiff = truth.replace(E=1e4)
    low = _fit_candidate("base", scene, obs, stiff, (5e3, 2e4), 7, cfg, False)
    assert _window_edge(low, (100.0, 3e4)) == -1
    kept, wide2, low2 = _widened([(wide, scene, start), (narrow, scene, start), (low, scene, stiff)], obs,
                                 (100.0, 3e4), 7, cfg, False)
    assert kept is wide and wide2.params == wide.params and wide2.fit_loss == wide.fit_loss
    assert low2.bounds["E"] == (100.0, 2e4) and low2.params["E"] == pytest.approx(3.0e3, rel=0.1)


def test_a_fit_near_the_edge_of_its_window_is_widened_with_fresh_effect_starts(monkeypatch):
    """Where the base model's E measures nothing (``loose``), a short CMA-ES run whose optimum lies beyond its
    window's edge stops short of it: E in the window's outer quarter (log E), with the box reaching further,
    counts as at that edge; elsewhere only E within 5 % of it. The widened refit starts from the fit, from E
    spread to the box's edge with the fitted effect parameters, and from the same E with the effect's
    registry starts (a fracture strain fitted beside a wrong E is no start at another E)."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig

    def fit(E, name="fracture", window=(2e3, 6.4e3), strain=0.58):
        return core._Fit(name, {"E": E, "fracture_strain": strain}, MaterialConfig(E=E), 0.5, 1.0, 0.0,
                         bounds={"E": window, "fracture_strain": (0.02, 1.5)})

    box = (2e3, 5e5)
    assert core._window_edge(fit(5.4e3), box, loose=True) == 1  # 86 % of the way up in log E
    assert core._window_edge(fit(5.4e3), box) == 0
    assert core._window_edge(fit(6.2e3), box) == 1  # within 5 %
    assert core._window_edge(fit(3.6e3), box, loose=True) == 0  # 51 %
    assert core._window_edge(fit(2.1e3), box, loose=True) == 0  # near the lower edge, but that is the box's bound
    assert core._window_edge(fit(2.9e3, window=(2.4e3, 6.4e3)), (1e3, 5e5), loose=True) == -1
    assert core._window_edge(fit(6.3e3, window=(2e3, 5e5 / 1.01)), box, loose=True) == 0  # nearly the box's bound

    seen = {}

    def spec(name, scene, base_material, window, F, cfg, starts=()):
        seen.update(window=window, starts=list(starts))
        return window

    def fake(specs, obs, progress, desc):
        return [dataclasses.replace(fit(5.0e4, window=window, strain=0.2), fit_loss=0.2) for window in specs]

    monkeypatch.setattr(core, "_candidate_spec", spec)
    monkeypatch.setattr(core, "_fit_candidates", fake)

    def widened(f, loose=False, cfg=DoctorConfig(popsize=8)):
        return core._widened([(f, None, MaterialConfig(E=2e3))], None, box, 7, cfg, False, loose)[0]

    g = widened(fit(5.4e3), loose=True)
    assert seen["window"] == (2e3, 5e5) and g.params["E"] == 5.0e4
    starts = seen["starts"]
    assert len(starts) == 6 and starts[0] == {"E": 5.4e3, "fracture_strain": 0.58}
    assert {st["fracture_strain"] for st in starts[1:]} == {0.58, core.PARAMETERS["fracture_strain"].start}
    assert all(6.4e3 < st["E"] <= 5e5 for st in starts[1:])
    widened(fit(6.2e3))
    assert len(seen["starts"]) == 4 and {st["fracture_strain"] for st in seen["starts"]} == {0.58}
    assert widened(fit(5.4e3), cfg=DoctorConfig()).params["E"] == 5.4e3


def _pushed_block(truth):
    """test_effect_params' block pushed by a sphere, 13 frames (its last 3 repeated): 4 held out."""
    from .test_effect_params import _observe, _scene

    scene, obs = _scene(truth), _observe(truth)
    obs = Observations(obs.fps, obs.points + obs.points[-3:], tracks=np.concatenate([obs.tracks, obs.tracks[-3:]]),
                       visibility=np.concatenate([obs.visibility, obs.visibility[-3:]]))
    scene = dataclasses.replace(scene, ee_positions=np.concatenate([scene.ee_positions, scene.ee_positions[-3:]]),
                                ee_grip=np.concatenate([scene.ee_grip, scene.ee_grip[-3:]]))
    return scene, obs


def test_a_candidate_whose_search_stayed_at_the_base_model_is_searched_again_from_a_better_point_of_its_box():
    """A plastic block (E 20 kPa, yield 1 kPa) fits an elastic E 5 times softer; its plasticity candidate, searched
    around that E, can stay at the base model (the rope of seed 20, session 70). A lattice over the candidate's
    box (E across its window, the yield at strains spread over 0.01 to 1 of each E) finds a point that fits better, and
    the candidate is searched again from there: its fitting loss falls to under a third. A fit that is already
    better than every point of its lattice is left as it is, and so is the base model's refit. doctor.json says
    what the lattice found."""
    from empm_gym.identification.doctor import core
    from empm_gym.identification.offline import fit_losses
    from empm_gym.sim import MaterialConfig

    truth = MaterialConfig(E=2.0e4, nu=0.3, density=1000.0, yield_stress=1.0e3)
    scene, obs = _swinging_block(truth)
    base = truth.replace(yield_stress=None, E=4.0e3)
    cfg, window, F = DoctorConfig(candidate_iters=3, popsize=6, seed=1), (4.0e3 / 3, 1.2e4), 12
    sc = dataclasses.replace(scene, dt_materials=core._clock(["plasticity"], base, window, scene.dx))
    stuck = []
    for name, params in (("base", {"E": 4.0e3}), ("plasticity", {"E": 4.0e3, "yield_stress": 1.0e6})):
        _, fsc, _, (ps, bounds, start_mat, csc) = core._candidate_spec(name, sc, base, window, F, cfg)
        loss, = fit_losses(obs, fsc, [params], frames=F, l_trk=cfg.l_trk, max_points=cfg.max_points, seed=cfg.seed)
        stuck.append(core._Fit(name, params, start_mat, 0.5, loss, 0.0, added=len(ps), scene=csc, bounds=bounds,
                               start_material=start_mat))
    # the lattice: four E across the window, the yield at strains 0.01 to 1 of each (clipped to its box, once)
    pts = core._probe_points(stuck[1], cfg.popsize)
    Es = np.geomspace(window[0] * 1.01, window[1] / 1.01, 7)[[0, 2, 4, 6]]
    assert sorted({p["E"] for p in pts}) == pytest.approx(Es)
    want = {(E, float(np.clip(E * r, *stuck[1].bounds["yield_stress"]))) for E in Es for r in np.geomspace(0.01, 1, 9)}
    assert len(pts) == len(want) < 36 and {(p["E"], p["yield_stress"]) for p in pts} == want
    # a candidate with a dimensionless parameter takes its first generation's scan at each E
    visc = dataclasses.replace(stuck[1], name="fracture", params={"E": 4.0e3, "fracture_strain": 1.5},
                               bounds={"E": window, "fracture_strain": (0.02, 1.5)})
    scan = [st["fracture_strain"] for st in core._effect_starts(visc.bounds, 4.0e3, cfg.popsize)[1:]]
    assert [p["fracture_strain"] for p in core._probe_points(visc, cfg.popsize)] == scan * 4
    # one with more parameters keeps its fitted values at each E; a window too narrow to spread E has no lattice
    field = dataclasses.replace(stuck[1], name="heterogeneous_stiffness",
                                params={"E": 4.0e3, "stiffness_slope_1": 0.3, "stiffness_slope_2": -0.2},
                                bounds={"E": window, "stiffness_slope_1": (-1.2, 1.2), "stiffness_slope_2": (-1.2, 1.2)})
    assert [(p["stiffness_slope_1"], p["stiffness_slope_2"]) for p in core._probe_points(field, 8)] == [(0.3, -0.2)] * 4
    assert core._probe_points(dataclasses.replace(visc, bounds={**visc.bounds, "E": (4.0e3, 4.1e3)}), 8) == []
    kept, found = core._probed(stuck, sc, obs, base, F, cfg, False)
    assert kept is stuck[0] and kept.probe is None
    assert found.probe["searched_again"] and found.probe["best_loss"] < stuck[1].fit_loss * (1 - core.PROBE_MARGIN)
    assert found.fit_loss <= found.probe["best_loss"] and found.fit_loss < stuck[1].fit_loss / 3
    assert 0.3 * truth.E < found.params["E"] and found.params["yield_stress"] < 5.0 * truth.yield_stress
    assert core._fit_dict(found, DoctorConfig())["probe"]["fit_loss_before"] == stuck[1].fit_loss
    # found, the fit is better than its whole lattice: nothing to search again
    params, loss = dict(found.params), found.fit_loss
    _, again = core._probed([stuck[0], found], sc, obs, base, F, cfg, False)
    assert again is found and not again.probe["searched_again"] and (again.params, again.fit_loss) == (params, loss)


def test_a_refit_on_a_variant_at_the_edge_of_its_window_is_widened():
    """A refit on a variant searches E in its fit's window on the doctor's body; a variant can move the optimum
    beyond it (dough lifted at both ends: the base model's 8.4 kPa went to the window's edge, 21.5 kPa, on a
    shifted grid, where a stiffness field then gained 24 % by the clamp). With the base model's box, the
    variant's base model ending at its window's edge is refitted with the window widened and reaches the
    optimum beyond it; without the box (the old check) it stays at the edge."""
    from empm_gym.identification.doctor.core import _check_variants, _fit_candidate
    from empm_gym.sim import MaterialConfig

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)
    start = truth.replace(E=600.0)
    scene, obs = _pushed_block(truth)
    T, F = 13, 9
    cfg = DoctorConfig(candidate_iters=4, variant_iters=2, popsize=6, seed=1, variants=1)
    base, visc = (_fit_candidate(name, scene, obs, start, (300.0, 1000.0), F, cfg, False)
                  for name in ("base", "viscosity"))
    assert base.params["E"] > 1000.0 / 1.05  # held at the window's edge on the doctor's body too
    runs = {box: _check_variants([visc], scene, obs, base, F, T, list(range(F, T)), cfg, False, box=box)
            for box in (None, (100.0, 3.0e4))}
    assert all(run["base_E"] == base.params["E"] for run in runs.values())
    clamped, widened = (runs[box]["base"][0] for box in runs)
    assert clamped["params"]["E"] <= 1000.0
    assert widened["params"]["E"] == pytest.approx(3.0e3, rel=0.15)
    assert widened["heldout_loss"] < clamped["heldout_loss"]


def test_a_candidate_gains_nothing_on_a_variant_by_an_E_the_base_models_refit_missed(monkeypatch):
    """On a variant the base model's refit and each candidate's are short searches; a candidate that ends there
    with its effect absent but a better E must not gain by that E (session 45: on rope pulled apart the base
    model's refits on the variants stayed at the box's floor, 2 kPa, where 9-12 kPa fits better). The variant's
    base model is the better, on the fitting frames, of its refit and the base model at the candidate's E. The
    refits are replaced here by fixed results (a base refit at 3x the truth's E, a viscosity refit at the
    truth's E with no viscosity); their losses are simulated."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)
    scene, obs = _pushed_block(truth)
    # the diagnosis's one clock (as diagnose sets it): the base model and the candidate step alike
    scene = dataclasses.replace(scene, dt_materials=core._clock(["viscosity"], truth, (1.0e3, 9.0e3), scene.dx))
    T, F = 13, 9
    cfg = DoctorConfig(candidate_iters=1, variant_iters=1, popsize=4, seed=1, variants=1)
    base, visc = (core._fit_candidate(name, scene, obs, truth, (1.0e3, 9.0e3), F, cfg, False)
                  for name in ("base", "viscosity"))

    def fixed(specs, obs, progress, desc):
        out = []
        for name, _, kw, (ps, bounds, start_mat, sc) in specs:
            params = {"E": 9.0e3} if name == "base" else {"E": 3.0e3, "viscosity": 0.0}
            out.append(core._Fit(name, params, start_mat.replace(**params), 0.5, 0.0, 0.0, added=len(ps), scene=sc,
                                 bounds=bounds, start_material=start_mat))
        return out

    monkeypatch.setattr(core, "_fit_candidates", fixed)
    out = core._check_variants([visc], scene, obs, base, F, T, list(range(F, T)), cfg, False)
    (vbase,), (test,) = out["base"], out["candidates"]["viscosity"]["tests"]
    assert vbase["params"]["E"] == 3.0e3 and vbase["refit_params"]["E"] == 9.0e3 and vbase["E_from"] == "viscosity"
    assert test["gain"] == pytest.approx(0.0, abs=1e-6) and not test["holds"]
    # the base model's refit at the better E is kept as it is
    assert core._base_alternatives([base, dataclasses.replace(visc, params={**visc.params, "E": base.params["E"]})]) == []


def test_a_refit_that_parts_a_body_its_model_cannot_tear_is_scored_at_the_doctors_optimum(monkeypatch):
    """A candidate whose model has no tear of its own (a stiffness field) but whose refit on a variant parts the
    simulated body into more pieces than the variant's base model does has torn numerically (session 46: rope
    pulled apart, the field's refit at the slope's cap parted the rope on one rebuilt body and lost 20 % held
    out, where the field's optimum on the doctor's body kept it whole and gained 62 %). Its test on that variant
    scores the candidate at its optimum on the doctor's body and says so. The refits are replaced by fixed
    results (the field's at E = 300 Pa and slope -4, which parts the block the gripper lifts: real simulations)."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)
    scene, obs = _pushed_block(truth)
    field_name = "heterogeneous_stiffness"
    scene = dataclasses.replace(scene, dt_materials=core._clock([field_name], truth, (1.0e3, 9.0e3), scene.dx))
    T, F = 13, 9
    heldout = list(range(F, T))
    cfg = DoctorConfig(candidate_iters=1, variant_iters=1, popsize=4, seed=1, variants=1)
    base, field = (core._fit_candidate(name, scene, obs, truth, (1.0e3, 9.0e3), F, cfg, False)
                   for name in ("base", field_name))
    torn = {"E": 300.0, "stiffness_slope_1": -4.0}
    seen = []  # (candidate, the variant's scene it was refitted on)

    def fixed(specs, obs, progress, desc):
        out = []
        for name, _, kw, (ps, bounds, start_mat, sc) in specs:
            seen.append((name, sc))
            params = {"E": 3.0e3} if name == "base" else torn
            out.append(core._Fit(name, params, start_mat.replace(**params), 0.5, 0.0, 0.0, added=len(ps), scene=sc,
                                 bounds=bounds, start_material=start_mat))
        return out

    monkeypatch.setattr(core, "_fit_candidates", fixed)
    out = core._check_variants([field], scene, obs, base, F, T, heldout, cfg, False)
    (test,) = out["candidates"][field_name]["tests"]
    assert test["refit_params"] == torn and test["params"] == field.params
    assert test["refit_pieces"] == 2 and test["base_pieces"] == 1 and test["params_from"] == "the doctor's body"
    # scored as the doctor's optimum simulated on that variant (the scene its refit ran on), not as the torn refit
    (vscene,) = [sc for name, sc in seen if name == field_name]
    as_doctor = dataclasses.replace(field, scene=vscene)
    as_refit = dataclasses.replace(as_doctor, params=torn, material=field.material.replace(**torn))
    X = core._simulate_fits([as_doctor, as_refit], T)
    obj = core.heldout_objective(as_doctor.scene, obs, T, cfg)
    kept, parted = (float(np.mean(core._per_frame_losses(obj, X[:, w])["loss"][heldout])) for w in (0, 1))
    assert test["heldout_loss"] == pytest.approx(kept, rel=1e-5) and parted > kept


def test_a_refit_on_a_later_variant_starts_from_the_optima_found_on_earlier_ones(monkeypatch):
    """Each candidate's refit on a variant after the first gets, among its starts, that candidate's optimum on the
    first variant (dough pulled apart: the fracture found on one shifted grid is a start on the next); the first
    variant is refitted before the others, which are refitted together."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0, viscosity=20.0)
    scene, obs = _pushed_block(truth)
    T, F = 13, 9
    cfg = DoctorConfig(candidate_iters=2, variant_iters=1, popsize=5, seed=1, variants=2)
    start = truth.replace(viscosity=0.0)
    base, visc = (core._fit_candidate(name, scene, obs, start, (1.0e3, 9.0e3), F, cfg, False)
                  for name in ("base", "viscosity"))
    calls = []

    def spy(like, base_fit, variant_base, found=()):
        calls.append((like.name, [dict(f) for f in found]))
        return real(like, base_fit, variant_base, found)

    real = core._variant_starts
    monkeypatch.setattr(core, "_variant_starts", spy)
    out = core._check_variants([visc], scene, obs, base, F, T, list(range(F, T)), cfg, False)
    tests = out["candidates"]["viscosity"]["tests"]
    assert [c[0] for c in calls] == ["viscosity", "viscosity"] and len(tests) == 2
    assert calls[0][1] == [] and calls[1][1] == [tests[0]["params"]]
    # the stage's clock: each step's seconds, the refits of the first variant apart from the others'
    clock = out["wall_s"]
    assert {"base models", "refits, first variant", "refits, the other variants", "held-out simulations",
            "parted refits scored"} <= set(clock) and all(v >= 0.0 for v in clock.values()), clock
    assert clock["refits, first variant"] > 0.0 and clock["refits, the other variants"] > 0.0


def test_a_winner_that_other_discretisations_rank_second_is_no_confident_verdict():
    """Two candidates that both hold can trade places from one discretisation to the next (dough pushed across
    the table with 200 Pa s of hidden viscosity, session 29: plasticity first on the doctor's body and the three
    rebuilt bodies, viscosity on both shifted grids). ``_first_on`` gives the winner's share of first places
    over the discretisations where both were refitted (non-finite gains left out) and the candidates that come
    first elsewhere; a lone passing candidate comes first everywhere."""
    from empm_gym.identification.doctor.core import _first_on

    labels = ["grid (1)", "grid (2)", "without camera 0", "without camera 1", "without camera 2"]

    def tests(gains):
        return {"tests": [{"variant": v, "gain": g} for v, g in zip(labels, gains)]}

    variants = {"variants": labels, "candidates": {
        "plasticity": tests([0.201, 0.213, 0.173, 0.188, 0.193]),
        "viscosity": tests([0.250, 0.289, 0.128, 0.158, None]),
        "fracture": tests([0.1, 0.1, 0.1, 0.1, 0.1])}}
    body = {"plasticity": 0.186, "viscosity": 0.161, "fracture": 0.05}
    share, others, n = _first_on("plasticity", ["plasticity", "viscosity"], body, variants)
    assert (share, others, n) == (pytest.approx(3 / 5), ["viscosity"], 5)  # the last variant: viscosity not finite
    assert _first_on("plasticity", ["plasticity", "fracture"], body, variants) == (1.0, [], 6)
    assert _first_on("plasticity", ["plasticity"], body, variants) == (1.0, [], 0)


def test_a_variant_where_a_rival_holds_only_a_lower_bound_does_not_count_towards_the_first_places():
    """Rope pulled apart with a stiffness field (seed 21, session 82, one H200): the field's refits on the bodies
    rebuilt without cameras 0 and 2 parted the rope, so there it was scored at its optimum on the doctor's body
    (``params_from``): a lower bound of what it gains there. Plasticity's refits beat those bounds; counted, the
    field came first on 3 of 6 and the verdict was split. Those two variants cannot say who is first: the field
    is first on 3 of the 4 others, and the verdict stands. Where the bounded candidate is itself first, the
    variant counts."""
    from empm_gym.identification.doctor.core import (_first_on, first_places, first_places_not_counted,
                                                     first_places_text, split_verdict)

    labels = ["grid (1)", "grid (2)", "without camera 0", "without camera 1", "without camera 2"]

    def tests(gains, bounded=()):
        return {"tests": [{"variant": v, "gain": g, "threshold": 0.04, "kind": "body" if "camera" in v
                           else "discretisation", **({"params_from": "the doctor's body"} if v in bounded else {})}
                          for v, g in zip(labels, gains)]}

    parted = ("without camera 0", "without camera 1", "without camera 2")
    variants = {"variants": labels, "candidates": {
        "heterogeneous_stiffness": tests([0.350, 0.364, 0.321, 0.308, 0.310], bounded=parted),
        "plasticity": tests([0.218, 0.368, 0.367, 0.205, 0.339])}}
    body = {"heterogeneous_stiffness": 0.565, "plasticity": 0.282}
    share, others, n = _first_on("heterogeneous_stiffness", ["heterogeneous_stiffness", "plasticity"], body, variants)
    assert (share, others, n) == (pytest.approx(3 / 4), ["plasticity"], 4)
    assert not split_verdict(share, n)
    # the same gains, none of them a bound: plasticity first on 3 of 6, and the verdict split (as before)
    plain = {"variants": labels, "candidates": {
        "heterogeneous_stiffness": tests([0.350, 0.364, 0.321, 0.308, 0.310]),
        "plasticity": tests([0.218, 0.368, 0.367, 0.205, 0.339])}}
    share, _, n = _first_on("heterogeneous_stiffness", ["heterogeneous_stiffness", "plasticity"], body, plain)
    assert (share, n) == (pytest.approx(3 / 6), 6) and split_verdict(share, n)
    # through the verdict's own path: both candidates significant, plasticity refuted (its trimmed-body refit
    # ends where it vanishes), the field named
    cands = [_gain_candidate("heterogeneous_stiffness", 0.565, 0.0185, 0.03),
             _gain_candidate("plasticity", 0.282, 0.0305, 0.01)]
    variants["candidates"]["plasticity"]["robust"] = False
    assert first_places(cands, variants, "heterogeneous_stiffness")[:3] == (pytest.approx(3 / 4), ["plasticity"], 4)
    # which two were left out, and the report's line says so
    left = first_places_not_counted(cands, variants, "heterogeneous_stiffness")
    assert left == ["without camera 0", "without camera 2"]
    assert first_places_not_counted(cands, plain, "heterogeneous_stiffness") == []
    line = first_places_text({"effect": "heterogeneous_stiffness", "first_on": "3 of 4", "split": None,
                              "first_elsewhere": ["plasticity"], "first_not_counted": left})
    assert "not counted: without camera 0, without camera 2" in line and "lower bound" in line


#: Two shifted grids and two bodies rebuilt without a camera: the variants of the verdict tests below.
_FOUR_VARIANTS = ["grid (1)", "grid (2)", "without camera 0", "without camera 1"]


def _variant_tests(gains):
    """A candidate's refits on :data:`_FOUR_VARIANTS` with held-out ``gains`` (penalty 4 %)."""
    return {"tests": [{"variant": v, "gain": g, "threshold": 0.04, "kind": "discretisation" if v.startswith("grid")
                       else "body"} for v, g in zip(_FOUR_VARIANTS, gains)]}


def _gain_candidate(name, gain, loss, half):
    """A candidate of ``doctor.json`` with held-out ``gain`` (interval +- ``half``) and held-out ``loss``."""
    return {"effect": name, "heldout": {"loss": loss}, "equivalent_to_base": False,
            "gain": {"gain": gain, "lower": gain - half, "upper": gain + half, "threshold": 0.04}}


def test_a_stronger_candidate_that_fails_on_one_grid_lowers_the_verdicts_confidence():
    """Block pulled apart with a hidden fracture (session 33, one H200): fracture gained 43.9 % held out and more
    than the stiffness field on both rebuilt bodies, but its refit on one shifted grid stayed at the base model;
    the field held everywhere and was named with confidence 1.00. The verdict stays the field (what holds on
    every variant) in the ranking; its first places are counted against fracture too: 2 of 5, no majority of the
    discretisations, so since session 72 the verdict is split and none is named (``split_verdict``)."""
    from empm_gym.identification.doctor.core import _contenders, _first_on, first_places, select_verdict, split_verdict

    labels, tests = _FOUR_VARIANTS, _variant_tests

    def cand(name, gain, loss):
        return _gain_candidate(name, gain, loss, 0.05)

    cands = [cand("fracture", 0.439, 0.0030), cand("heterogeneous_stiffness", 0.188, 0.0042),
             cand("table_friction", 0.002, 0.0050)]
    variants = {"variants": labels, "base_E": 4.6e5, "base": [], "candidates": {
        "fracture": tests([0.177, -0.001, 0.514, 0.497]),
        "heterogeneous_stiffness": tests([0.212, 0.223, 0.160, 0.155])}}
    win, before, passing = select_verdict(cands, variants)
    assert (win, before, passing) == ("heterogeneous_stiffness", "fracture", ["heterogeneous_stiffness"])
    contenders = _contenders(cands, variants)
    assert contenders == ["fracture", "heterogeneous_stiffness"]  # table friction: not significant
    body = {c["effect"]: c["gain"]["gain"] for c in cands}
    assert _first_on(win, contenders, body, variants) == (pytest.approx(2 / 5), ["fracture"], 5)
    assert _first_on(win, passing, body, variants) == (1.0, [], 0)  # the old count: no rival at all
    share, others, n, yielded = first_places(cands, variants, win)
    assert (share, others, n, yielded) == (pytest.approx(2 / 5), ["fracture"], 5, [])
    assert split_verdict(share, n)


def test_a_verdict_first_on_no_more_than_half_of_the_discretisations_is_split_and_not_named():
    """Seed 23's dough lifted by one end without any effect (session 71, one H200): gripper slip held on every
    variant and was ranked first; the stiffness field gained more on the doctor's body and on 3 of the 4 variants
    but failed on one shifted grid, so gripper slip came first on 1 of 5 discretisations and was named (confidence
    0.05). A verdict first on at most half of its discretisations is split (``split_verdict``): the diagnosis and
    the benchmark's rescore call it none. Where the slip comes first on 3 of 5 it is named; half of an even count
    is no majority; a verdict compared nowhere (no rival refitted on the variants) is not split."""
    from empm_gym.identification.doctor.core import first_places, select_verdict, split_reason, split_verdict

    labels, tests = _FOUR_VARIANTS, _variant_tests

    def cand(name, gain, loss):
        return _gain_candidate(name, gain, loss, 0.1)

    cands = [cand("heterogeneous_stiffness", 0.434, 0.00347), cand("gripper_slip", 0.319, 0.00418),
             cand("fracture", 0.034, 0.00593)]
    slip = tests([0.065, 0.139, 0.443, 0.365])

    def verdict(field_gains):
        variants = {"variants": labels, "base_E": 1.5e4, "base": [], "candidates": {
            "heterogeneous_stiffness": tests(field_gains), "gripper_slip": slip}}
        win, before, _ = select_verdict(cands, variants)
        share, others, n, _ = first_places(cands, variants, win)
        return win, before, round(share * n), n, others, split_verdict(share, n)

    # the field fails on the first grid: the slip ranks first, but first on 1 of 5 discretisations
    assert verdict([-0.01, 0.175, 0.470, 0.421]) == (
        "gripper_slip", "heterogeneous_stiffness", 1, 5, ["heterogeneous_stiffness"], True)
    assert verdict([-0.01, 0.100, 0.470, 0.421])[2:] == (2, 5, ["heterogeneous_stiffness"], True)
    assert verdict([-0.01, 0.100, 0.400, 0.421])[2:] == (3, 5, ["heterogeneous_stiffness"], False)
    assert split_verdict(0.5, 6) and not split_verdict(4 / 6, 6) and not split_verdict(1.0, 0)
    assert first_places(cands, None, "gripper_slip")[:3] == (1.0, [], 0)
    # the none's reason names both, and says which one fails on a variant
    assert split_reason("gripper_slip", 0.319, "1 of 5", ["heterogeneous_stiffness"], ["gripper_slip"]).startswith(
        "gripper_slip lowers the held-out loss by 31.9 % and holds on the variants, but comes first on only 1 of 5 "
        "discretisations of the body, heterogeneous_stiffness (which fails on some variant) on the others")



def test_the_report_says_on_how_many_discretisations_the_verdict_comes_first():
    """report.md's "first places" line, from doctor.json's first_on, first_elsewhere and split: a named verdict
    with its share and the others first elsewhere, a split one with the candidate that led and why it is not named,
    nothing where no count was made (no variants, no rival) or nothing led."""
    from empm_gym.identification.doctor.core import first_places_text

    named = {"effect": "gripper_slip", "first_on": "4 of 5", "first_elsewhere": ["fracture"], "split": None}
    assert first_places_text(named) == ("gripper_slip is first among the significant candidates on 4 of 5 "
                                        "discretisations of the body; fracture on the others")
    assert first_places_text({**named, "first_on": "5 of 5", "first_elsewhere": []}).endswith("of the body")
    split = {"effect": "none", "first_on": "1 of 5", "first_elsewhere": ["heterogeneous_stiffness", "fracture"],
             "split": "gripper_slip"}
    assert first_places_text(split) == (
        "gripper_slip is first among the significant candidates on 1 of 5 discretisations of the body; "
        "heterogeneous_stiffness and fracture on the others: no majority puts gripper_slip first, so it is not named "
        "(split)")
    assert first_places_text({**named, "first_on": ""}) is None
    assert first_places_text({"effect": "none", "first_on": "", "first_elsewhere": [], "split": None}) is None


def test_a_verdict_fitted_outside_the_plausible_range_says_so_in_its_reason():
    """Seed 22's dough pulled apart with a fracture was named gripper slip at a grip friction of 308 (confidence 0.25,
    session 66): the doubt stood in a note only, and the reason read like a plain fit. The reason now ends on the
    value, its range and what it may stand for; within the range it says nothing more."""
    from empm_gym.identification.doctor.core import implausible_clause, implausible_text

    assert implausible_text({"E": 4.6e5, "grip_friction": 308.34}, {"grip_friction": (0.0, 15.0)}) == (
        "grip_friction = 308, outside the 0 to 15 that real objects and contacts usually show")
    assert implausible_clause({"E": 4.6e5, "grip_friction": 308.34}) == (
        "; but its fit has grip_friction = 308, outside the 0 to 15 that real objects and contacts usually show: it "
        "may stand in for something the catalogue lacks (read the notes and the runner-up candidates)")
    assert implausible_clause({"E": 4.6e5, "friction": 2.6}).startswith("; but its fit has friction = 2.6, outside "
                                                                         "the 0 to 1.5")
    for ok in ({"E": 4.6e5, "grip_friction": 11.2}, {"E": 2e4, "viscosity": 500.0}, {"E": 2e4, "friction": 1.5}):
        assert implausible_clause(ok) == "", ok

def test_a_first_candidate_fitted_outside_the_plausible_range_yields_to_a_plausible_one_about_as_good():
    """Seed 19's dough pulled apart with a hidden fracture on a moved grid (session 57, one H200): fracture gained
    74.5 % held out (strain 0.24) and gripper slip 73.3 % with a grip friction of 162, far outside the 0 to 15 that
    real grasps show; slip gained more on 4 of the 5 discretisations and was named. Its fit stands in for the tear:
    fracture, fitted within its range and about as good (the intervals meet), is named. A plausible candidate that
    explains clearly less does not take the verdict (a spring-mass dough dragged: table friction 1.62 gained 17.7 %,
    a stiffness field 5.2 %), nor does an implausible one that is not first."""
    from empm_gym.identification.doctor.core import _yields_to, select_verdict, yield_note

    labels = ["grid (1)", "grid (2)", "without camera 0", "without camera 1"]

    def cand(name, gain, lower, upper, loss, **params):
        return {"effect": name, "heldout": {"loss": loss}, "equivalent_to_base": False, "params": {"E": 4e5, **params},
                "gain": {"gain": gain, "lower": lower, "upper": upper, "threshold": 0.04}}

    def tests(gains):
        return {"tests": [{"variant": v, "gain": g, "threshold": 0.04, "kind": "discretisation" if v.startswith("grid")
                           else "body"} for v, g in zip(labels, gains)]}

    def torn(grip_friction):
        return [cand("fracture", 0.745, 0.742, 0.752, 0.0040, fracture_strain=0.24),
                cand("gripper_slip", 0.733, 0.724, 0.741, 0.0042, grip_friction=grip_friction),
                cand("heterogeneous_stiffness", 0.717, 0.712, 0.726, 0.0044, stiffness_slope_1=-1.2)]

    variants = {"variants": labels, "base_E": 4.98e5, "base": [], "candidates": {
        "fracture": tests([0.687, 0.612, 0.807, 0.722]), "gripper_slip": tests([0.752, 0.70, 0.83, 0.75]),
        "heterogeneous_stiffness": tests([0.70, 0.69, 0.78, 0.71])}}
    # a grip friction that real grasps show: slip, first on most discretisations, stays the verdict
    assert select_verdict(torn(4.0), variants)[0] == "gripper_slip"
    win, before, passing = select_verdict(torn(162.0), variants)
    assert (win, before) == ("fracture", "fracture") and passing[:2] == ["fracture", "gripper_slip"]
    assert _yields_to(torn(162.0)[1], torn(162.0)[0]) and not _yields_to(torn(162.0)[1], torn(162.0)[1])
    # doctor.json's notes say why
    note = yield_note(*torn(162.0)[:2])
    assert note.startswith("gripper_slip passes too and its held-out gain (73.3 %) is not clearly above "
                           "fracture's (74.5 %)") and "grip_friction = 162, outside the 0 to 15" in note, note
    assert yield_note(*torn(4.0)[:2]) is None and yield_note(*torn(162.0)[::-1][1:]) is None
    # without fracture the stiffness field, whose interval (71.2-72.6 %) reaches slip's (72.4-74.1 %), takes it;
    # set clearly behind, it does not
    assert select_verdict(torn(162.0)[1:], variants)[0] == "heterogeneous_stiffness"
    behind = torn(162.0)[1:]
    behind[1]["gain"].update(gain=0.70, lower=0.69, upper=0.71)
    assert select_verdict(behind, variants)[0] == "gripper_slip"
    dragged = [cand("table_friction", 0.177, 0.173, 0.180, 0.0050, friction=1.62),
               cand("heterogeneous_stiffness", 0.052, 0.049, 0.054, 0.0058, stiffness_slope_1=0.65)]
    assert select_verdict(dragged, None)[0] == "table_friction"
    dragged[1]["gain"]["upper"] = 0.175  # the frames no longer clearly prefer the implausible friction
    assert select_verdict(dragged, None)[0] == "heterogeneous_stiffness"
    # a later round after a gripper slip named at grip friction 162: every candidate carries that friction as the
    # base model's; it is no fit of theirs, and only their own parameters are judged (fracture's 0.24 plausible)
    later = [{**c, "params": {**c["params"], "grip_friction": 162.0}, "carried": ["grip_friction"]}
             for c in (torn(4.0)[0], torn(4.0)[2])]
    later[1]["gain"].update(gain=0.74, lower=0.735, upper=0.745)  # about as good: would take an implausible first's
    assert select_verdict(later, None)[0] == "fracture"
    assert yield_note(later[1], later[0]) is None and _yields_to(later[0], later[1])


def test_a_first_candidate_doubted_by_its_own_signature_yields_to_an_undoubted_one_about_as_good():
    """Varied seed 22's dough lifted by one end with a hidden fracture (session 60, two H200s): gripper slip gained
    42.3 % held out (39.1-44.0), fracture 41.9 % (37.6-44.7), a stiffness field 38.6 % (33.9-41.7); slip gained
    more on most discretisations and was named, while the tracked points near the closed gripper moved with it
    (0.25 mm from the base model, depth noise 1.46 mm) and the slip's fit moved them 0.76 mm off. Fracture, about
    as good and not doubted, is named, and the notes say why. A doubted first that explains clearly more stays
    first (a dough pulled apart with gripper slip shows no slip either), and a doubted runner-up takes nothing."""
    from empm_gym.identification.doctor.core import select_verdict, yield_note

    labels = ["grid (1)", "grid (2)", "without camera 0", "without camera 1"]

    def cand(name, gain, lower, upper, doubted, **params):
        sig = None if doubted is None else {
            "feature": "track_slip_m", "unsupported": doubted, "doubted": doubted, "trusted": True}
        return {"effect": name, "heldout": {"loss": 0.01 * (1 - gain)}, "equivalent_to_base": False,
                "params": {"E": 3e5, **params}, "signature_check": sig,
                "gain": {"gain": gain, "lower": lower, "upper": upper, "threshold": 0.04}}

    def tests(gains):
        return {"tests": [{"variant": v, "gain": g, "threshold": 0.04, "kind": "discretisation" if v.startswith("grid")
                           else "body"} for v, g in zip(labels, gains)]}

    def lifted(slip_doubted=True, fracture_gain=(0.419, 0.376, 0.447)):
        return [cand("gripper_slip", 0.423, 0.391, 0.440, slip_doubted, grip_friction=4.1),
                cand("fracture", *fracture_gain, None, fracture_strain=0.27),
                cand("heterogeneous_stiffness", 0.386, 0.339, 0.417, None, stiffness_slope_1=-0.89)]

    variants = {"variants": labels, "base_E": 4.6e5, "base": [], "candidates": {
        "gripper_slip": tests([0.745, 0.774, 0.435, 0.453]), "fracture": tests([0.742, 0.757, 0.304, 0.413])}}
    assert select_verdict(lifted(slip_doubted=False), variants)[0] == "gripper_slip"
    win, before, passing = select_verdict(lifted(), variants)
    assert (win, before) == ("fracture", "gripper_slip") and passing == ["fracture", "gripper_slip"], passing
    # the order before the yield (what the diagnosis halves the confidence for, and says was set behind)
    assert select_verdict(lifted(), variants, yield_rules=False)[2] == ["gripper_slip", "fracture"]
    note = yield_note(lifted()[1], lifted()[0])
    assert note.startswith("gripper_slip passes too and its held-out gain (42.3 %) is not clearly above fracture's "
                           "(41.9 %)") and "shows nothing in its signature (track_slip_m)" in note, note
    assert yield_note(lifted()[1], lifted(slip_doubted=False)[0]) is None
    # fracture clearly behind (its interval below slip's): slip stays first, doubted
    assert select_verdict(lifted(fracture_gain=(0.30, 0.27, 0.33)), variants)[0] == "gripper_slip"
    # without variants the same; a doubted runner-up does not take the verdict from a doubted first
    assert select_verdict(lifted(), None)[0] == "fracture"
    both = lifted()
    both[1]["signature_check"] = {"feature": "pieces_observed_max", "doubted": True, "unsupported": False}
    assert select_verdict(both[:2], None)[0] == "gripper_slip"


def test_a_viscosity_at_the_top_of_its_capped_box_says_the_cap_is_the_solvers():
    """A named viscosity at the top of a box the explicit step cut (a soft rope at dx = 5 mm: 0.5-22.7 Pa s, the
    registry's box reaching 500; the truth 44.8 Pa s, session 57) says the bound is the solver's, with the cap's
    value; a viscosity at the registry's own top, the box's bottom, or another parameter at its bound does not."""
    from empm_gym.identification.doctor.core import _search_box, at_bound_note
    from empm_gym.sim import MaterialConfig

    box = _search_box("viscosity", MaterialConfig(E=41374.0, nu=0.3, density=1000.0), 0.005)
    assert box[0] == 0.5 and 22.0 < box[1] < 23.5  # rho dx c / 3 x exp(0.6): 22.7 Pa s
    bounds = {"E": (4597.0, 41374.0), "viscosity": box}
    note = at_bound_note("viscosity", {"E": 30000.0, "viscosity": box[1] * 0.99}, bounds, ["viscosity"])
    assert note.startswith("viscosity's fit ends at the bound of its search box in viscosity = 22.")
    assert f"box ends at {box[1]:.3g} Pa s because the doctor steps explicitly" in note, note
    for params, bnds in (({"E": 3e4, "viscosity": 495.0}, {**bounds, "viscosity": (0.5, 500.0)}),  # the registry's
                         ({"E": 3e4, "viscosity": 0.5}, bounds)):                                 # its bottom
        other = at_bound_note("viscosity", params, bnds, ["viscosity"])
        assert "no measurement" in other and "steps explicitly" not in other
    assert "steps explicitly" not in at_bound_note("plasticity", {"E": 3e4, "yield_stress": 99.0},
                                                   {"E": (1e3, 1e5), "yield_stress": (10.0, 100.0)}, ["yield_stress"])


def test_the_viscosity_box_is_raised_only_for_a_fit_at_its_capped_top_that_gains():
    """The second pass (``DoctorConfig.viscosity_raise``, off by default) is asked for by a viscosity fit in the top tenth (log) of
    a box the explicit step capped, with a held-out gain over its penalty (the rope squeezed in the ring, seed 18:
    18.1 Pa s in a box to 23.2, gain 12.4 %); not by a fit lower in the box, one that gains less than its
    penalty, one at the top of the registry's own box, another effect, or with the raise switched off."""
    from empm_gym.identification.doctor.core import _Fit, viscosity_raise_reason
    from empm_gym.sim import MaterialConfig

    def visc(v, gain, box=(0.5, 23.2), name="viscosity"):
        f = _Fit(name, {"E": 1.4e4, "viscosity": v}, MaterialConfig(E=1.4e4, nu=0.3, density=1000.0), 0.5, 0.0, 0.0,
                 added=1, bounds={"E": (5e3, 4e4), "viscosity": box})
        f.test = {"gain": gain, "threshold": 0.04, "lower": gain - 0.1, "upper": gain + 0.1}
        return f

    cfg = DoctorConfig(viscosity_raise=3.0)
    why = viscosity_raise_reason([visc(18.1, 0.124)], cfg)
    assert why.startswith("the viscosity candidate's fit ended at 18.1 Pa s, at the top of its box (0.5 to 23.2 Pa s")
    assert "gained 12.4 % held out against its 4 % penalty" in why
    # 18.1 lies at 0.94 of the box in log viscosity, 15 at 0.89
    for fits in ([visc(15.0, 0.124)], [visc(18.1, 0.039)], [visc(480.0, 0.3, box=(0.5, 500.0))],
                 [visc(18.1, 0.124, name="plasticity")], [visc(float("nan"), 0.2)], []):
        assert viscosity_raise_reason(fits, cfg) is None
    assert viscosity_raise_reason([visc(18.1, 0.124)], DoctorConfig()) is None  # off by default
    for bad in (float("nan"), float("inf"), 0.0, -3.0, "3", True):
        with pytest.raises(ValueError, match="DoctorConfig.viscosity_raise must be a positive, finite number"):
            DoctorConfig(viscosity_raise=bad)
    with pytest.raises(ValueError, match="DoctorConfig.viscosity_cap"):
        DoctorConfig(viscosity_cap=float("nan"))


def _swinging_block(material, T=18, move=9):
    """test_effect_params' block lifted and pulled by a closed sphere for ``move`` frames, then held still
    while it swings (``T`` frames at 30 fps): the held-out frames see its swing decay."""
    from empm_gym.identification.problem import simulate_frames
    from empm_gym.sim import TableConfig

    x, v = sample_box((-0.06, -0.03, 0.0), (0.06, 0.03, 0.04), 0.02, 8)
    p0, vel = np.array([0.05, 0.0, 0.02]), np.array([0.25, 0.0, 0.35])
    ee = np.stack([p0 + vel * min(t, move) / 30.0 for t in range(T)])[:, None]
    scene = Scene(x, v, 30.0, ee_configs=[EndEffectorConfig(shape="sphere", radius=0.025, friction=0.8)],
                  ee_positions=ee, ee_grip=np.ones((T, 1)), material=material, table=TableConfig(), dx=0.02,
                  device="cpu")
    X = simulate_frames(scene, [material])[:, 0]
    return scene, Observations(30.0, list(X), tracks=X, visibility=np.ones(X.shape[:2], bool))


def test_the_doctor_reports_how_much_its_shared_clock_damps_the_base_model():
    """The candidates' boxes set one clock for every fit; a viscosity's box needs more substeps than the base
    model alone. On a block swinging with 100 Pa s of viscosity the doctor reports both substep counts and the
    base model's held-out loss on each clock (on its own, coarser clock the base model is damped less and misses
    the viscous swing by 11 % more), and says so in a note since that exceeds the 4 % penalty. The loss on the
    base model's own clock is that of the fitted material simulated on that clock. With plasticity alone as the
    candidate the clock is the base model's own: no change, no note."""
    from empm_gym.identification.doctor import core
    from empm_gym.identification.problem import simulate_frames
    from empm_gym.sim import MaterialConfig

    scene, obs = _swinging_block(MaterialConfig(E=3.0e3, nu=0.3, density=1000.0, viscosity=100.0))
    cfg = DoctorConfig(base_iters=2, candidate_iters=2, popsize=6, variants=0, base_E=3e3, E_bounds=(1e3, 9e3))
    res = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    ck = res["clock"]
    assert ck["substeps_per_frame"] > ck["base_model_alone"] >= 1
    assert ck["base_heldout_loss"] == res["base"]["heldout"]["loss"]
    # the fitted base material on the substeps its own E window needs, scored as the doctor scores
    T, heldout = 18, list(range(res["heldout_frames"][0], 18))
    window = res["base"]["E_window"]
    own = dataclasses.replace(scene, dt_materials=(MaterialConfig(E=window[0], nu=0.3, density=1000.0),
                                                   MaterialConfig(E=window[1], nu=0.3, density=1000.0)),
                              motion_margin=DoctorConfig().motion_margin)
    base_mat = MaterialConfig(E=res["base"]["params"]["E"], nu=0.3, density=1000.0)
    assert core._substeps(own, base_mat, T) == ck["base_model_alone"]
    X = simulate_frames(own.with_material(base_mat), [base_mat])[:, 0]
    loss = np.mean(core._per_frame_losses(core.heldout_objective(own, obs, T, cfg), X)["loss"][heldout])
    assert ck["base_heldout_loss_on_its_own_clock"] == pytest.approx(loss, rel=1e-4)
    assert ck["change"] == pytest.approx((loss - ck["base_heldout_loss"]) / ck["base_heldout_loss"], rel=1e-3)
    assert ck["change"] > cfg.penalty_per_param
    notes = [n for n in res["notes"] if "substeps a frame" in n]
    assert len(notes) == 1 and f"{ck['base_model_alone']} the base model alone would" in notes[0]
    assert f"scores {100 * ck['change']:.1f} % worse held out" in notes[0]
    plastic = diagnose(scene, obs, effects=["plasticity"], config=cfg, progress=False)
    assert plastic["clock"]["substeps_per_frame"] == plastic["clock"]["base_model_alone"]
    assert plastic["clock"]["change"] == 0.0 and not any("substeps a frame" in n for n in plastic["notes"])
    for change in (0.039, -0.039, float("nan")):
        assert core.clock_note({**ck, "change": change}, 0.04) is None
    assert "better held out" in core.clock_note({**ck, "change": -0.05}, 0.04)


def test_a_viscosity_fit_at_its_capped_top_fits_every_candidate_again_on_a_raised_clock(monkeypatch):
    """A block swinging with 100 Pa s of viscosity, where the first pass caps the viscosity at 42 Pa s: its fit
    ends at the top of that box and gains held out, so every candidate (the base model's refit too) is fitted
    and scored again with the box raised 3x, all on one clock with more substeps than the first pass's; the
    notes and ``viscosity_box_raised`` say so, and each candidate's searched box is in doctor.json. Without the
    raise the same first pass is the diagnosis."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig, stable_dt

    scene, obs = _swinging_block(MaterialConfig(E=3.0e3, nu=0.3, density=1000.0, viscosity=100.0))
    dts = {}  # the stable step of every fit of each pass, by the pass's progress label
    starts = {}  # the raised pass's first generations, by candidate
    fit_candidates = core._fit_candidates

    def spy(specs, obs, progress, desc):
        dts.setdefault(desc, []).extend(stable_dt(list(sc.dt_materials), sc.dx, sc.cfl) for _, sc, _, _ in specs)
        if desc.endswith("raised"):
            starts.update({name: kw["extra_starts"] for name, _, kw, _ in specs})
        return fit_candidates(specs, obs, progress, desc)

    monkeypatch.setattr(core, "_fit_candidates", spy)
    runs = {}
    for raise_ in (1.0, 3.0):
        cfg = DoctorConfig(base_iters=3, candidate_iters=8, popsize=8, variants=0, base_E=3e3, E_bounds=(1e3, 9e3),
                           viscosity_raise=raise_)
        runs[raise_] = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    once, twice = runs[1.0], runs[3.0]
    (v1,), (v3,) = once["candidates"], twice["candidates"]
    top = v1["search_box"]["viscosity"][1]
    assert once["viscosity_box_raised"] is None and not any("raised" in n for n in once["notes"])
    assert v1["params"]["viscosity"] > top / 1.45 and v1["gain"]["gain"] > v1["gain"]["threshold"]
    assert twice["viscosity_box_raised"] == 3.0
    assert v3["search_box"]["viscosity"][1] == pytest.approx(3.0 * top, rel=1e-6)
    assert any(n.startswith(f"the viscosity candidate's fit ended at {v1['params']['viscosity']:.3g} Pa s")
               and "box raised 3 times" in n for n in twice["notes"])
    # the unraised run's one pass, then the raised run's two
    first, second = dts["doctor: candidates"][2:], dts["doctor: candidates, viscosity box raised"]
    assert dts["doctor: candidates"][:2] == first
    assert len(first) == len(second) == 2  # the base model's refit and the viscosity candidate, each pass
    assert len(set(first)) == 1 and len(set(second)) == 1 and second[0] < first[0] / 1.5
    # each raised fit starts from its first pass's optimum as well (the same first pass as the run without raise)
    assert v1["params"] in starts["viscosity"] and once["base"]["params"] in starts["base"]
    # the base model too was refitted on the raised clock: it is scored with the candidate's substeps
    assert twice["base"]["heldout"]["loss"] != once["base"]["heldout"]["loss"]
    assert sum(twice["stage_wall_s"].values()) == pytest.approx(twice["wall_time_s"], abs=0.06)


def test_candidates_search_the_whole_box_when_the_base_fit_ends_at_its_bound():
    """The base fit's E at a bound of its box measures nothing (the block is softer than the box allows): the
    candidates then refit E over the whole box, not within E_refit_factor of that bound; inside the box they
    keep the window."""
    from empm_gym.sim import MaterialConfig

    scene, obs = _pushed_block(MaterialConfig(E=3.0e3, nu=0.3, density=1000.0))
    for box, at_bound in (((6.0e3, 6.0e4), True), ((3.0e2, 6.0e4), False)):
        cfg = DoctorConfig(base_iters=6, candidate_iters=1, popsize=5, variants=0, E_bounds=box, base_E=1.2e4)
        res = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
        window = res["candidates"][0]["E_window"]
        assert res["base"]["E_window"] == window
        if at_bound:  # (the base fit on the box ended at 6 kPa; the null candidate's refit is reported)
            assert window == pytest.approx(list(box))
        else:
            assert window[0] > box[0] and window[1] < box[1] and window[0] < 3.0e3 < window[1]


def test_a_base_fit_that_stopped_short_of_a_bound_its_loss_falls_toward_is_at_that_bound():
    """The base fit's E near a bound, its candidates' window reaching past it: the base model is simulated at the
    bound and at the fitted E. The block (3 kPa) in a box from 6 kPa, fitted for one generation, ends well above
    the floor; the floor fits better, so the candidates search the whole box and a note says why. In a box from
    1.5 kPa the floor fits worse than the fit: the window is kept. Far from any bound nothing is simulated."""
    from empm_gym.sim import MaterialConfig

    scene, obs = _pushed_block(MaterialConfig(E=3.0e3, nu=0.3, density=1000.0))
    for box, at_bound in (((6.0e3, 6.0e4), True), ((1.5e3, 6.0e4), False), ((3.0e2, 6.0e4), None)):
        cfg = DoctorConfig(base_iters=1 if at_bound else 2, candidate_iters=1, popsize=5, variants=0, E_bounds=box,
                           base_E=1.2e4)
        res = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
        check, window = res["base_bound_check"], res["candidates"][0]["E_window"]
        if at_bound is None:
            assert check is None and window[0] > box[0]
            continue
        assert check["bound"] == box[0] and check["E"] > box[0] * 1.05  # not at the bound by _at_bound's measure
        assert check["at_bound"] is at_bound
        assert (check["loss_at_bound"] <= check["loss_at_fit"]) is at_bound
        said = [n for n in res["notes"] if "fits the fitting frames at least as well at the bound" in n]
        if at_bound:
            assert window == pytest.approx(list(box)) and len(said) == 1
        else:
            assert window[0] == box[0] and window[1] < box[1] and not said


def test_a_none_names_the_candidates_its_frames_can_neither_show_nor_exclude():
    """A candidate whose gain is not significant but whose interval reaches above its penalty is not ruled out: a
    ``none`` names it (seed 17's rope squeezed with a hidden viscosity: 5.0 %, interval -2.3 to 9.0 %, penalty
    4 %, ``none`` at confidence 0.38). A gain wholly under the penalty, a significant one, the verdict itself, the
    base model's table and a fit contradicted by its own signature are not listed; these are exactly what keeps
    a ``none``'s confidence under 1."""
    from empm_gym.identification.doctor.core import _confidence, not_ruled_out, not_ruled_out_text

    rng = np.random.default_rng(1)
    base = 1.0 + 0.1 * rng.standard_normal(30)
    same = base + 0.02 * rng.standard_normal(30)  # gains nothing: interval about 0
    wobbly = base * (0.95 + 0.06 * np.random.default_rng(0).standard_normal(30))  # 5 %, interval across 4 %
    better = 0.6 * base  # 40 %: significant
    tests = {name: paired_gain_test(base, x, added_params=1, penalty_per_param=0.04)
             for name, x in [("plasticity", same), ("viscosity", wobbly), ("fracture", better)]}
    assert tests["viscosity"]["upper"] > 0.04 > tests["viscosity"]["lower"] and tests["plasticity"]["upper"] < 0.04
    cands = [{"effect": n, "gain": t, "equivalent_to_base": False, "contradicted_by_signature": False}
             for n, t in tests.items()]
    cands += [{"effect": "table_friction", "gain": tests["viscosity"], "equivalent_to_base": True},
              {"effect": "gripper_slip", "gain": tests["viscosity"], "contradicted_by_signature": True},
              {"effect": "heterogeneous_stiffness", "gain": None}]
    got = not_ruled_out(cands)
    assert [e["effect"] for e in got] == ["viscosity"], got
    e = got[0]
    assert (e["gain"], e["lower"], e["upper"], e["threshold"]) == tuple(
        tests["viscosity"][k] for k in ("gain", "lower", "upper", "threshold"))
    assert e["signature"].startswith("motion decays")
    assert not_ruled_out(cands, verdict="viscosity") == []  # the verdict is no rival of itself
    text = not_ruled_out_text(got)
    assert "not ruled out: viscosity" in text and f"{100 * e['upper']:.1f} %" in text and "neither show nor exclude it" in text
    assert not_ruled_out_text([]) == ""
    # what keeps a none from full confidence: the candidate not ruled out clears its penalty on some resamples
    cfg = DoctorConfig(penalty_per_param=0.04)
    assert _confidence(base, [same], [1], cfg, None) == 1.0
    assert 0.0 < _confidence(base, [same, wobbly], [1, 1], cfg, None) < 0.9


def test_a_candidate_refuted_by_the_variants_is_no_rival_in_the_confidence():
    """The confidence is the share of resampled held-out frames on which the verdict stays: a candidate whose
    gain failed on the variants is out of the verdict on every resample, so its larger gain does not count
    against the winner (dough push-slide-0: viscosity named with confidence 0.01 beside a refuted plasticity)."""
    from empm_gym.identification.doctor.core import _beats, _confidence, select_verdict

    rng = np.random.default_rng(0)
    base = 1.0 + 0.02 * rng.standard_normal(12)
    winner = 0.90 * base + 0.005 * rng.standard_normal(12)  # gains 10 %
    refuted = 0.85 * base + 0.005 * rng.standard_normal(12)  # gains 15 %, but not on the variants
    cfg = DoctorConfig()
    assert _confidence(base, [winner, refuted], [1, 1], cfg, 0) < 0.05
    assert _confidence(base, [winner, refuted], [1, 1], cfg, 0, refuted=[1]) > 0.95
    assert _confidence(base, [winner, refuted], [1, 1], cfg, None, refuted=[0, 1]) == 1.0  # none: nothing left


def test_a_candidate_the_variants_did_not_check_competes_by_its_gain_on_the_resampled_frames():
    """Only the ``variant_top`` best significant candidates are refitted on the variants. One they did not check
    competes with the winner in the confidence by the two gains on the resampled held-out frames, not by its gain
    there against the winner's median over the variants (which are lower): so compared, gripper slip's 29.8 %
    took every resample from a fracture named at 45.1 % (16-26 % on its variants; block pulled apart, the CPU
    tests' one checked candidate, confidence 0.00). A rival level with the winner on those frames still takes a
    share of them; a refuted one (``no_rivals``) none."""
    from empm_gym.identification.doctor.core import _confidence, no_rivals

    rng = np.random.default_rng(0)
    base = 1.0 + 0.02 * rng.standard_normal(12)
    fracture = 0.55 * base + 0.004 * rng.standard_normal(12)    # gains 45 %
    slip = 0.70 * base + 0.004 * rng.standard_normal(12)        # 30 %, not refitted on the variants
    level = fracture * (1 + 0.02 * np.tile([1.0, -1.0], 6))     # 45 % too, ahead on some frames, behind on others
    cfg = DoctorConfig()
    vg = [[0.16, 0.26, 0.25], []]
    assert _confidence(base, [fracture, slip], [2, 1], cfg, 0, variant_gains=vg) > 0.95
    assert 0.1 < _confidence(base, [fracture, level], [2, 1], cfg, 0, variant_gains=vg) < 0.9
    assert _confidence(base, [fracture, level], [2, 1], cfg, 0, variant_gains=vg, refuted=[1]) > 0.95
    # both refitted on the variants: their medians over them compare (slip holds better there)
    assert _confidence(base, [fracture, slip], [2, 1], cfg, 0, variant_gains=[[0.16, 0.26, 0.25], [0.29] * 3]) < 0.05

    def cand(name, gain, equivalent=False):
        return {"effect": name, "heldout": {"loss": 1 - gain}, "equivalent_to_base": equivalent,
                "gain": {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04}}

    cands = [cand("fracture", 0.451), cand("gripper_slip", 0.298), cand("table_friction", 0.2, equivalent=True)]
    variants = {"variants": ["v0"], "candidates": {"fracture": {"tests": [], "robust": True}}}
    assert no_rivals(cands, variants) == ["table_friction"]              # unchecked: not refuted
    variants["candidates"]["gripper_slip"] = {"tests": [], "robust": False}
    assert no_rivals(cands, variants) == ["gripper_slip", "table_friction"]
    assert no_rivals(cands, None) == ["table_friction"]


def test_a_gain_holds_on_the_variants_with_at_most_one_miss_in_five_and_most_rebuilt_bodies():
    """The variants' rule (:func:`_robust`): a true effect's gain, each variant tested at the doctor's level after a
    short refit, may fail on one variant in five (dough pushed with a viscosity, seed 16: 4.8, 0.4, 11.3, 9.3 and
    13.2 % against a threshold of 4 %), not on two, and must hold on more than half of the rebuilt bodies; with
    fewer than five variants it must hold on all of them."""
    from empm_gym.identification.doctor.core import _robust

    def tests(disc, body):
        return ([{"variant": f"grid shifted and particles resampled ({i + 1})", "kind": "discretisation",
                  "gain": g, "threshold": 0.04} for i, g in enumerate(disc)]
                + [{"variant": f"without camera {i}", "kind": "body", "gain": g, "threshold": 0.04}
                   for i, g in enumerate(body)])

    seed16 = _robust(tests([0.048, 0.004], [0.113, 0.093, 0.132]))
    assert seed16["robust"] and seed16["holds_on"] == "4 of 5 variants" and seed16["why"] == ""
    assert "resampled (2)' it gains 0.4 % against a threshold of 4 %" in seed16["missed"]  # the verdict says so
    assert _robust(tests([0.048, 0.05], [0.113, 0.01, 0.132]))["robust"]          # one body misses
    two = _robust(tests([0.048, 0.004], [0.113, 0.01, 0.132]))                    # a grid and a body miss
    assert not two["robust"] and "grid shifted and particles resampled (2)" in two["why"] and "0.4 %" in two["why"]
    assert two["missed"] == "" and _robust(tests([0.048, 0.05], [0.113, 0.09, 0.132]))["missed"] == ""
    assert not _robust(tests([0.01, 0.004], [0.113, 0.09, 0.132]))["robust"]       # both grids miss
    assert not _robust(tests([0.048, 0.004], []))["robust"]                       # 2 variants: both must hold
    assert not _robust(tests([0.048, 0.05, 0.06], [0.113, float("nan")]))["robust"]  # 5, but half the bodies fail
    nan_body = _robust(tests([0.048, 0.05], [0.113, 0.09, float("nan")]))             # a refit not finite: a miss
    assert nan_body["robust"] and nan_body["holds_on"] == "4 of 5 variants"
    # a refit that ends where its effect vanishes does not hold, whatever its gain (rope lifted by one end without
    # any effect, seed 17, session 47: fracture held on 4 of 5, two of them refits at strains of 1.497 and 1.5, the
    # box's top)
    vanishing = tests([0.31, 0.29], [0.2, 0.25, 0.22])
    for t in vanishing[1:3]:
        t["toward_absence"] = ["fracture_strain"]
    got = _robust(vanishing)
    assert not got["robust"] and got["holds_on"] == "3 of 5 variants"
    assert "29.0 % against a threshold of 4 %, its refit there ending where the effect vanishes (fracture_strain at " \
           "its bound)" in got["why"], got["why"]



def test_a_gain_must_also_hold_on_the_body_trimmed_to_the_measured_surface():
    """The trimmed body (:func:`~empm_gym.identification.data.trimmed_body`) is a check of its own: a gain that holds
    on every variant but not there is refused and the verdict says where (the rebuilt bodies all lean larger than
    the object, the trimmed one smaller); it is not counted among the one-in-five misses, and
    ``robust_without_trimmed`` keeps the verdict of the variants alone; a select_verdict on stored variants applies
    it too."""
    from empm_gym.identification.data import TRIMMED_BODY
    from empm_gym.identification.doctor.core import _robust, select_verdict

    variants = ([{"variant": f"grid shifted and particles resampled ({i + 1})", "kind": "discretisation", "gain": g,
                  "threshold": 0.04} for i, g in enumerate([0.06, 0.07])]
                + [{"variant": f"without camera {i}", "kind": "body", "gain": g, "threshold": 0.04}
                   for i, g in enumerate([0.05, 0.08, 0.09])])
    trimmed = {"variant": TRIMMED_BODY, "kind": "trimmed", "gain": -0.038, "threshold": 0.04}
    got = _robust(variants, trimmed)
    assert not got["robust"] and got["robust_without_trimmed"] and got["holds_on"] == "5 of 5 variants"
    assert f"on the {TRIMMED_BODY} it gains -3.8 % against a threshold of 4 %" in got["why"], got["why"]
    assert _robust(variants, {**trimmed, "gain": 0.05})["robust"]                   # it holds there too
    assert _robust(variants)["robust"]                                              # no trimmed body: as before
    vanished = _robust(variants, {**trimmed, "gain": 0.2, "toward_absence": ["viscosity"]})
    assert not vanished["robust"] and "where the effect vanishes (viscosity at its bound)" in vanished["why"]
    one_miss = _robust([{**variants[0], "gain": 0.01}] + variants[1:], {**trimmed, "gain": 0.05})
    assert one_miss["robust"] and one_miss["holds_on"] == "4 of 5 variants"          # the trimmed body is not a variant
    # the verdict on stored variants: viscosity, refuted by the trimmed body, leaves plasticity, which holds there
    cands = [{"effect": e, "params": {}, "heldout": {"loss": loss}, "added": 1,
              "gain": {"gain": g, "lower": g - 0.02, "upper": g + 0.02, "threshold": 0.04, "significant": True}}
             for e, loss, g in (("viscosity", 0.0044, 0.20), ("plasticity", 0.0046, 0.15))]
    stored = {"variants": [v["variant"] for v in variants] + [TRIMMED_BODY],
              "candidates": {"viscosity": {"tests": variants, "trimmed": trimmed},
                             "plasticity": {"tests": variants, "trimmed": {**trimmed, "gain": 0.06}}}}
    assert select_verdict(cands, stored)[0] == "plasticity"
    stored["candidates"]["plasticity"]["trimmed"]["gain"] = 0.0
    assert select_verdict(cands, stored)[0] is None
    del stored["candidates"]["viscosity"]["trimmed"]
    assert select_verdict(cands, stored)[0] == "viscosity"

def test_a_gain_failing_on_a_rebuilt_body_the_doctors_body_fits_significantly_better_is_not_counted():
    """A rebuilt body (without a camera, or trimmed) whose base model the doctor's body beats held out by the
    doctor's own test (``body_unlike``) cannot refute a gain: a failure there is not counted and the rule counts the
    rest; a gain that holds there still counts, a failing body that fits as well still refutes, and stored tests
    without the field count as before (varied seed 22's rope squeezed in a ring, session 69)."""
    from empm_gym.identification.data import TRIMMED_BODY
    from empm_gym.identification.doctor.core import _robust, select_verdict

    def tests(disc, body, unlike):
        return ([{"variant": f"grid shifted and particles resampled ({i + 1})", "kind": "discretisation",
                  "gain": g, "threshold": 0.04} for i, g in enumerate(disc)]
                + [{"variant": f"without camera {i}", "kind": "body", "gain": g, "threshold": 0.04, "body_unlike": u}
                   for i, (g, u) in enumerate(zip(body, unlike))])

    seed22 = tests([0.396, 0.408], [0.059, 0.114, 0.005], [True, True, True])
    for t in seed22[2:]:  # its refits there ended at the bottom of the viscosity's box
        t["toward_absence"] = ["viscosity"]
    assert not _robust([{k: v for k, v in t.items() if k != "body_unlike"} for t in seed22])["robust"]  # as stored
    got = _robust(seed22)
    assert got["robust"] and got["not_counted"] == ["without camera 0", "without camera 1", "without camera 2"]
    assert got["holds_on"].startswith("2 of 2 variants ('without camera 0', 'without camera 1', 'without camera 2' "
                                      "not counted: the doctor's body fits"), got["holds_on"]
    # one failing body that fits as well as the doctor's still refutes the gain (with a grid's miss: two in five)
    assert not _robust(tests([0.396, 0.01], [0.01, 0.114, 0.2], [False, True, True]))["robust"]
    assert not _robust(tests([0.396, 0.408], [0.01, 0.01, 0.2], [False, False, True]))["robust"]  # 2 in five
    # with it not counted, the rest must still hold: one grid and one body failing of four counted
    assert not _robust(tests([0.396, 0.01], [0.01, 0.01, 0.2], [False, True, False]))["robust"]
    # an unlike body the gain holds on is counted: it does not thin the evidence for the gain
    kept = _robust(tests([0.396, 0.408], [0.3, 0.01, 0.2], [True, False, True]))
    assert kept["robust"] and kept["not_counted"] == [] and kept["holds_on"] == "4 of 5 variants"
    # the trimmed body alike: refuting where it fits as well, not counted where the doctor's body fits better
    trimmed = {"variant": TRIMMED_BODY, "kind": "trimmed", "gain": -0.02, "threshold": 0.04}
    fine = tests([0.396, 0.408], [0.3, 0.25, 0.2], [False, False, False])
    assert not _robust(fine, trimmed)["robust"]
    aside = _robust(fine, {**trimmed, "body_unlike": True})
    assert aside["robust"] and aside["not_counted"] == [TRIMMED_BODY]
    # the verdict on stored variants follows
    cands = [{"effect": "viscosity", "params": {}, "heldout": {"loss": 0.005}, "added": 1,
              "gain": {"gain": 0.46, "lower": 0.40, "upper": 0.48, "threshold": 0.04, "significant": True}}]
    assert select_verdict(cands, {"variants": ["v"], "candidates": {"viscosity": {"tests": seed22}}})[0] == "viscosity"
    seed22[2]["body_unlike"] = False
    assert select_verdict(cands, {"variants": ["v"], "candidates": {"viscosity": {"tests": seed22}}})[0] is None


def _block_with_fixed_refits(monkeypatch, variants: int, viscosity: float):
    """The pushed block (true E 3 kPa) with its base model and viscosity candidate fitted briefly, and every later
    refit (``core._fit_candidates``, monkeypatched) fixed at the true E, the viscosity candidate's at ``viscosity``:
    ``(scene, obs, T, F, heldout frames, DoctorConfig with `variants` discretisation variants, base fit, viscosity
    fit)``."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)
    scene, obs = _pushed_block(truth)
    scene = dataclasses.replace(scene, dt_materials=core._clock(["viscosity"], truth, (1.0e3, 9.0e3), scene.dx))
    T, F = 13, 9
    cfg = DoctorConfig(candidate_iters=1, variant_iters=1, popsize=4, seed=1, variants=variants)
    base, visc = (core._fit_candidate(name, scene, obs, truth, (1.0e3, 9.0e3), F, cfg, False)
                  for name in ("base", "viscosity"))

    def fixed(specs, obs, progress, desc):
        return [core._Fit(name, {"E": 3.0e3, **({} if name == "base" else {"viscosity": viscosity})},
                          start_mat.replace(E=3.0e3), 0.5, 0.0, 0.0, added=len(ps), scene=sc, bounds=bounds,
                          start_material=start_mat)
                for name, _, kw, (ps, bounds, start_mat, sc) in specs]

    monkeypatch.setattr(core, "_fit_candidates", fixed)
    return scene, obs, T, F, list(range(F, T)), cfg, base, visc


def test_the_variants_check_compares_each_rebuilt_body_with_the_doctors_held_out(monkeypatch):
    """Each rebuilt body's base model is compared with the doctor's body's on the held-out frames by the doctor's
    paired test (simulated here): a body displaced by 1.5 cm from the measured block fits significantly worse and
    its tests say ``body_unlike``; the doctor's own body given again as a rebuilt one does not. The refits are
    fixed (the true E, a viscosity at 0 that gains nothing), so the gain fails on both bodies: not counted on the
    displaced one only."""
    from empm_gym.identification.doctor import core

    scene, obs, T, F, heldout, cfg, base, visc = _block_with_fixed_refits(monkeypatch, variants=0, viscosity=0.0)
    doctors = dataclasses.replace(base, params={"E": 3.0e3}, material=base.material.replace(E=3.0e3))
    X = core._simulate_fits([doctors], T)
    base_heldout = core._per_frame_losses(core.heldout_objective(scene, obs, T, cfg), X[:, 0])["loss"][heldout]
    moved = dataclasses.replace(scene, particles=scene.particles + np.array([0.015, 0.0, 0.0]))
    out = core._check_variants([visc], scene, obs, base, F, T, heldout, cfg, False,
                               other_bodies=[("the same body", scene), ("a displaced body", moved)],
                               base_heldout=base_heldout)
    same, far = out["base"]
    assert same["doctors_body_gain"]["gain"] == pytest.approx(0.0, abs=1e-6)
    assert not same["doctors_body_gain"]["significant"]
    assert far["doctors_body_gain"]["significant"] and far["doctors_body_gain"]["lower"] > 0.04
    tests = out["candidates"]["viscosity"]["tests"]
    assert [t["body_unlike"] for t in tests] == [False, True] and not any(t["holds"] for t in tests)
    rec = out["candidates"]["viscosity"]
    assert rec["not_counted"] == ["a displaced body"] and not rec["robust"]  # the same body's failure refutes it
    assert rec["holds_on"].startswith("0 of 1 variants")


def test_fitted_values_at_their_search_bound_are_flagged():
    """A fit's parameter at a bound of its box (log-scaled: within 5 %; linear: within 2.5 % of the width) is
    listed, a value inside is not, whatever the sign of a linear parameter."""
    from empm_gym.identification.doctor.core import _Fit, _params_at_bound
    from empm_gym.sim import MaterialConfig

    def fit(**params):
        bounds = {"E": (1e3, 1e5), "friction": (0.0, 1.0), "stiffness_slope_1": (-1.2, 1.2), "yield_stress": (1e2, 1e5)}
        return _Fit("x", params, MaterialConfig(E=params["E"]), 0.5, 0.0, 0.0, bounds={k: bounds[k] for k in params})

    assert _params_at_bound(fit(E=1.04e3, friction=0.5)) == ["E"]
    assert _params_at_bound(fit(E=9.7e4, friction=0.02)) == ["E", "friction"]
    assert _params_at_bound(fit(E=5e3, friction=0.1, stiffness_slope_1=-1.19)) == ["stiffness_slope_1"]
    assert _params_at_bound(fit(E=5e3, stiffness_slope_1=0.0, yield_stress=9.6e4)) == ["yield_stress"]
    assert _params_at_bound(fit(E=1.1e3, friction=0.04, yield_stress=1.1e2)) == []


def test_a_fitted_value_real_contacts_do_not_show_is_flagged():
    """A table friction beyond 1.5 (a spring-mass rope pulled apart, whose grasp gives, gained 18.5 % with 2.6,
    session 49) or a grip friction beyond 15 is flagged with its range, so that the verdict is doubted; the
    frictions the benchmark's true recordings fit (table 0.04-0.07, grip 0.1-11.2) and the assumed 0.5 are not,
    nor is any parameter without a range."""
    from empm_gym.identification.doctor.core import implausible_params
    from empm_gym.sim.effects import PARAMETERS

    assert implausible_params({"E": 4.6e3, "friction": 2.6}) == {"friction": (0.0, 1.5)}
    assert implausible_params({"E": 4.6e3, "friction": 1.62}) == {"friction": (0.0, 1.5)}
    for f in (0.013, 0.05, 0.5, 1.5):
        assert implausible_params({"E": 2e4, "friction": f}) == {}, f
    # a grip friction far above any pad's (a dough torn at the clamps fitted 148, session 54) is flagged; the
    # benchmark's true slips fitted 0.1 to 11.2 and are not
    assert implausible_params({"E": 2e4, "grip_friction": 148.0}) == {"grip_friction": (0.0, 15.0)}
    for g in (0.1, 1.0, 11.2, 15.0):
        assert implausible_params({"E": 2e4, "grip_friction": g}) == {}, g
    # only the frictions carry a range so far: the others' fits on true recordings span their boxes
    assert [k for k, p in PARAMETERS.items() if p.plausible is not None] == ["friction", "grip_friction"]
    assert implausible_params({"E": 2e4, "yield_stress": 1e6, "viscosity": 500.0, "stiffness_slope_1": 1.5}) == {}
    assert implausible_params({"E": 2e4, "friction": float("nan")}) == {}


def test_every_effect_is_a_candidate():
    for name in EFFECTS:
        assert candidate_params(name), name
    with pytest.raises(ValueError, match="unknown effect"):
        candidate_params("magic")


# ------------------------------------------------------------------------------------------ end to end
# Hidden-effect recordings named end to end on the CPU, each on the script where its effect's signature is
# clearest (docs/EFFECTS.md), plus one the base model explains. Reduced resolution for the CPU: 24 frames at
# 30 fps, 3 cameras at 320 x 180, the doctor's body at dx 1.25 cm with 4 particles per cell, short CMA-ES
# runs. At this scale viscosity is not named (seed 3, 2026-11-25: on squeeze-ring, its clearest script, `none`
# with a viscous gain of 1.5 %; on push-slide plasticity, wrongly, with confidence 1.00, the viscous refit
# ending worse than the base model inside an E window that leaves out the true E); it is measured at full
# resolution by benchmarks/bench_doctor.py (benchmarks/RESULTS.md). The stiffness field is named on pull-apart,
# its natural script (HIDDEN_2), not on squeeze-ring. The CI time (the whole suite within 45 minutes) leaves
# room for seven doctor runs.
HIDDEN = [
    ("plasticity", "press-release"),
    ("gripper_slip", "squeeze-lift"),
    ("none", "press-release"),
]
#: run from test_doctor_e2e.py, a file of its own, so that the two CI workers (pytest-xdist, --dist loadfile)
#: share the doctor's end-to-end runs
HIDDEN_2 = [
    # on the rounded lump, a shape none of the doctor's rules was chosen on (session 76; the box dough's slide was
    # the case before): 85.5 % held out, the slide's signature brought from +141 mm to -35 mm, 384 s beside the suite
    ("table_friction", "push-slide", "lump"),
    # the block pulled apart tears (the fracture's natural script, docs/EFFECTS.md): fracture gains 45.1 % held
    # out, gripper slip 29.8 %, the stiffness field 24.3 %; it holds on its variants (16-26 %). Session 43, with the
    # depth drawn on the true surface: the case before, a rope lifted by one end (1.4 cells across, the grid too
    # coarse), went to the stiffness field (82.3 % against the fracture's 81.0 %; with the flat discs' depth the
    # two were level at 83.2 % and fracture was named). The dough lifted by one end, the case before session 39,
    # is the doctor's weakest fracture: the piece torn off stays hidden in the gripper, and gripper slip, which
    # also lets the body fall back, fits the later frames as well or better (seeds 13-15 at 5 mm). Pulled apart at
    # this scale, the dough's fracture is called none and the rope's (at 1 cm) gripper slip; 75.2 % against slip's
    # 73.7 % at 1.25 cm (session 43).
    ("fracture", "pull-apart", "block"),
    # at this scale the viscous candidate gains 10.8 % here on the elastic dough (the bootstrap over frames calls
    # it significant), but loses on the body rebuilt without camera 0 or 1: only the variants check says none
    ("none", "squeeze-ring"),
    # a stiffness rising along the long axis (its natural script): the field gains 28.4 % held out (bootstrap
    # 26.2-30.8 %), fracture 3.5 % and plasticity 2.4 %, neither significant: named with confidence 1.00 in 132 s
    # (2026-11-25, beside other jobs)
    ("heterogeneous_stiffness", "pull-apart"),
]

def test_a_search_smaller_than_the_measured_one_is_said():
    """The doctor's accuracy was measured with 6 generations of 8 worlds and 2 variants: the notes say when a
    run searched less (a base fit short of its optimum would let any added parameter gain)."""
    from empm_gym.identification.doctor.core import MEASURED_SEARCH, _search_note

    assert _search_note(DoctorConfig()) is None  # the defaults search at least as much
    m = MEASURED_SEARCH
    assert _search_note(DoctorConfig(base_iters=m["iters"], candidate_iters=m["iters"], popsize=m["popsize"],
                                     variants=m["variants"])) is None
    for less in ({"base_iters": 1}, {"candidate_iters": m["iters"] - 1}, {"popsize": 3}, {"variants": 0}):
        note = _search_note(dataclasses.replace(DoctorConfig(), **less))
        assert note and note.startswith("search:") and f"{list(less.values())[0]}" in note, (less, note)


_CPU = DoctorConfig(base_iters=3, candidate_iters=3, popsize=5, E_refit_factor=2.0, motion_margin=0.015, variants=1,
                   variant_iters=2, variant_top=1)


@pytest.mark.slow
@pytest.mark.parametrize("effect,script", HIDDEN, ids=[f"{e}-{s}" for e, s in HIDDEN])
def test_doctor_names_the_hidden_effect(tmp_path, effect, script):
    doctor_names_the_hidden_effect(tmp_path, effect, script)


def doctor_names_the_hidden_effect(tmp_path, effect, script, obj="dough"):
    from empm_gym.identification.doctor import diagnose_recording
    from empm_gym.perception.synth import synthesize

    rec = synthesize(tmp_path / "rec", obj, script=script, effect=effect, frames=24, cameras=3, width=320,
                     height=180, seed=3, progress=False)
    (rec / "ground_truth.json").unlink()  # the doctor must not need it (and never reads it)
    # the slipping dough in a second round as well: with the slip in its base model (the grip friction fitted again
    # in every fit) no other effect gains (the largest 0.4 %, session 74), and none may be named
    rounds = 2 if effect == "gripper_slip" else 1
    res = diagnose_recording(rec, out_dir=tmp_path / "doctor", config=dataclasses.replace(_CPU, rounds=rounds),
                             dx=0.0125, particles_per_cell=4, progress=False)
    if rounds > 1:
        (second,) = res["rounds"]
        assert second["effect"] == "none" and res["effects"] == [effect], second["reason"]
        assert second["base_effects"] == [effect] and (tmp_path / "doctor" / "round2" / "report.md").exists()
        assert {c["effect"] for c in second["result"]["candidates"]} == set(EFFECTS) - {effect}
    table = {c["effect"]: (round(1e3 * c["heldout"]["chamfer_m"], 2), round(c["gain"]["gain"], 3),
                           c["gain"]["significant"]) for c in res["candidates"]}
    print(f"{effect} on {script}: verdict {res['effect']} ({res['confidence']:.2f}); base held-out "
          f"{1e3 * res['base']['heldout']['chamfer_m']:.2f} mm; {table}")
    assert res["effect"] == effect, res["reason"]
    # two clamps hide most of a compact body from every camera (squeeze-lift, lift-end, pull-apart): the notes say how
    # much of the body the loader's completion supplied; pressed or pushed, nothing is said
    hidden = [n for n in res["notes"] if "completed by a prior" in n]
    assert len(hidden) == (obj in ("dough", "block") and script in ("squeeze-lift", "lift-end", "pull-apart")), \
        res["notes"]
    # the controls and the images share one clock here: no lag is reported (doctor.json holds what was read)
    assert not any("out of step" in n for n in res["notes"]), res["control_lag"]
    assert set(res["control_lag"]) >= {"lag_frames", "lower", "upper", "slip_share", "followers", "points"}
    # the CPU's small search is said (3 generations of 5, 1 variant: less than the doctor was measured with)
    assert sum(n.startswith("search: the fits ran 3 (base model)") for n in res["notes"]) == 1, res["notes"]
    if effect != "none":
        best = next(c for c in res["candidates"] if c["effect"] == effect)
        assert best["heldout"]["loss"] < res["base"]["heldout"]["loss"]
        assert (tmp_path / "doctor" / "material.json").exists()
        # the true effect's fit moves its own signature toward the measurement (or has none to move)
        sig = res["evidence"]["signature_check"]
        print(f"signature {sig['feature']}: {sig['base']} -> {sig['with_effect']} ({sig['explained']})")
        assert sig["feature"] == SIGNATURE_FEATURES[effect][0] and not sig["doubted"], sig
        assert sig["explained"] is not False or not SIGNATURE_FEATURES[effect][2], sig
        assert "signature check" in (tmp_path / "doctor" / "report.md").read_text()
        assert res["evidence"]["features_with_effect"][sig["feature"]] == sig["with_effect"]
    # every significant candidate with a signature feature carries its own check (not one set aside as ending where
    # its effect vanishes); none named is contradicted or set aside
    for c in res["candidates"]:
        checked = (c["effect"] in SIGNATURE_FEATURES and c["gain"]["significant"] and not c["equivalent_to_base"]
                   and not c["toward_absence"])
        assert (c["signature_check"] is not None) == checked, c
        assert c["contradicted_by_signature"] == bool(checked and c["signature_check"]["trusted"]
                                                      and c["signature_check"]["explained"] is False), c
        if c["effect"] == res["effect"]:
            assert c["signature_check"] == res["evidence"]["signature_check"] and not c["contradicted_by_signature"]
            assert not c["toward_absence"], c
    # what a none could not exclude: every candidate whose interval reaches above its penalty without being
    # significant, each named in a none's reason
    from empm_gym.identification.doctor.core import not_ruled_out

    assert res["not_ruled_out"] == not_ruled_out(res["candidates"], res["effect"]), res["not_ruled_out"]
    for c in res["candidates"]:
        listed = c["effect"] in [e["effect"] for e in res["not_ruled_out"]]
        assert listed == (c["effect"] != res["effect"] and not c["gain"]["significant"] and not c["equivalent_to_base"]
                          and not c["contradicted_by_signature"] and not c["toward_absence"]
                          and c["gain"]["upper"] > c["gain"]["threshold"]), c
        assert (f"not ruled out: {c['effect']}" in res["reason"] or f"; {c['effect']} (held-out gain" in res["reason"]) \
            == (listed and res["effect"] == "none"), res["reason"]
    # the held-out gap before and after, as the candidates' table and the verdict score it, with the mask IoU
    gap = res["gap"]
    assert gap["frames"] == list(range(res["heldout_frames"][0], res["heldout_frames"][1] + 1))
    shown = [("base", res["base"])] + ([("effect", best)] if effect != "none" else [])
    assert sorted(gap["total"]) == sorted(k for k, _ in shown) and gap["effect"] == (None if effect == "none" else effect)
    for key, fit in shown:
        assert gap["total"][key]["chamfer_m"] == pytest.approx(fit["heldout"]["chamfer_m"], rel=1e-9)
        # no overlap at all is a measurement too: the base model's lump stays where the slippery table let the
        # pushed one slide 10 cm away (IoU 0.00, the table friction's 0.36)
        assert 0.0 <= gap["total"][key]["mask_iou"] <= 1.0
        assert len(gap["per_frame"][key]["mask_iou"]) == len(gap["frames"])
    assert max(gap["total"][key]["mask_iou"] for key, _ in shown) > 0.0
    assert "The held-out gap" in (tmp_path / "doctor" / "report.md").read_text()
    assert (tmp_path / "doctor" / "heldout_gap.png").stat().st_size > 5000
    assert (tmp_path / "doctor" / "report.md").exists() and (tmp_path / "doctor" / "doctor.rrd").exists()
    # each candidate's E window: the report's table and doctor.json agree
    lo, hi = res["candidates"][0]["E_window"]
    assert "E searched [Pa]" in (tmp_path / "doctor" / "report.md").read_text()
    assert f"{lo:.3g} to {hi:.3g}" in (tmp_path / "doctor" / "report.md").read_text()


def test_doctor_cli_reports_bad_input(tmp_path, capsys):
    from empm_gym.cli import main

    assert main(["doctor", str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 2
    assert "empm doctor: error" in capsys.readouterr().err
    assert main(["effects"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in EFFECTS)


def test_doctor_cli_marks_fits_at_their_search_bound(tmp_path, capsys, monkeypatch):
    """The CLI's summary gives every fit's parameters and says which lie at their search bound (the demo's
    base model sat at its lowest E and the summary printed it as a plain number)."""
    import empm_gym.identification.doctor as doctor
    from empm_gym.cli import main

    fit = {"heldout": {"chamfer_m": 0.02, "loss": 0.05}, "gain": None}
    res = {"effect": "gripper_slip", "confidence": 1.0, "reason": "it lowers the held-out loss", "notes": [],
           "base": {**fit, "params": {"E": 2000.0}, "at_search_bound": ["E"]},
           "candidates": [{**fit, "effect": "gripper_slip", "params": {"E": 29936.1, "grip_friction": 0.8967},
                           "at_search_bound": [], "gain": {"gain": 0.85, "significant": True}},
                          {**fit, "effect": "fracture", "params": {"E": 2003.0, "fracture_strain": 0.02},
                           "at_search_bound": ["E", "fracture_strain"], "gain": {"gain": -0.12, "significant": False}},
                          {**fit, "effect": "viscosity", "params": {"E": 2100.0, "viscosity": 3.0}, "at_search_bound": [],
                           "gain": {"gain": 0.05, "lower": -0.023, "upper": 0.09, "threshold": 0.04,
                                    "significant": False}},
                          {**fit, "effect": "plasticity", "params": {"E": 2.3e4, "yield_stress": 9.9e5},
                           "at_search_bound": ["yield_stress"], "toward_absence": ["yield_stress"],
                           "gain": {"gain": 0.06, "significant": True}}],
           "not_ruled_out": [{"effect": "viscosity"}],
           "uncertainty": {"E": {"interval": [2.1e4, 3.9e4], "level": 0.95, "determined": True, "bounded_only": None},
                           "grip_friction": {"interval": [0.0, 1.2], "level": 0.95, "determined": False,
                                             "bounded_only": "upper"}},
           "identifiability": {"warnings": ["grip_friction: the loss is flat within the frame-to-frame noise below "
                                            "the fit"],
                               "combinations": {"grip_friction*E": {
                                   "value": 2.684e4, "interval": [2.5e4, 2.9e4], "level": 0.95, "unit": "Pa",
                                   "of": ["E", "grip_friction"], "exponent": 1.0, "determined": True, "note": "..."}}}}
    seen = {}
    monkeypatch.setattr(doctor, "diagnose_recording", lambda *a, **k: seen.update(k) or res)
    assert main(["doctor", str(tmp_path), "--out", str(tmp_path / "out"), "--control-delay", "1.5",
                 "--viscosity-raise", "3"]) == 0
    assert seen["control_delay"] == 1.5  # handed on to delay the controls (delayed_controls checks the value)
    assert seen["config"].viscosity_raise == 3.0 and seen["config"].intervals
    out = capsys.readouterr().out
    # the named fit's values with their intervals; one the frames do not fix says so, and why
    assert "gripper_slip E = 2.994e+04 (95 % interval 2.1e+04 to 3.9e+04)\n" in out
    assert ("gripper_slip grip_friction = 0.8967 (95 %: at most 1.2): not determined (the loss is flat within the "
            "frame-to-frame noise below the fit)\n") in out
    assert "gripper_slip grip_friction*E = 2.684e+04 Pa (95 % interval 2.5e+04 to 2.9e+04)\n" in out  # what they fix
    assert "base model: E=2000 (at bound)" in out
    assert "(significant); fitted E=2.994e+04, grip_friction=0.8967\n" in out
    assert "fitted E=2003 (at bound), fracture_strain=0.02 (at bound)" in out
    # each gain with its interval and penalty; a candidate the frames cannot exclude says so
    assert "loss gain +5.0 % (95 % interval -2.3 to 9.0 %, penalty 4 %) (not ruled out); fitted E=2100" in out
    assert "loss gain -12.0 % ; fitted E=2003" in out  # no interval stored: none printed
    # a fit at the bound where its effect vanishes says that it is not named
    assert "fitted E=2.3e+04, yield_stress=9.9e+05 (at bound, where the effect vanishes: not named)" in out
    # one round that named an effect points to the rounds, for a recording that lacks two
    assert "to look for a second missing effect on top of gripper_slip: the same command with --rounds 2" in out
    assert main(["doctor", str(tmp_path), "--out", str(tmp_path / "out"), "--no-intervals", "--quiet"]) == 0
    assert not seen["config"].intervals


def test_variants_are_the_same_body_on_another_discretisation():
    """The doctor's variants (a named effect must hold its gain on them): the grid moved sideways by part of a
    cell, still covering the original box and keeping the node layer on the table; the particles moved by at
    most half their spacing, same volumes, above the table; each variant different."""
    from empm_gym.identification.doctor.core import _variant_scene

    scene, _ = _still_scene()
    g0 = scene.grid_config()
    h = float(np.cbrt(np.median(scene.volumes)))
    shifts = []
    for k in range(3):
        v = _variant_scene(scene, k)
        g = v.grid_config()
        assert g.dx == g0.dx and g.lower[2] == g0.lower[2]  # the table's node layer stays
        assert np.all(np.asarray(g.lower) <= np.asarray(g0.lower) + 1e-12)
        assert np.all(np.asarray(g.upper) >= np.asarray(g0.upper) - 1e-12)
        frac = ((np.asarray(g0.lower[:2]) - np.asarray(g.lower[:2])) / g0.dx) % 1.0
        assert np.any((frac > 0.1) & (frac < 0.9)), frac  # a new lattice of nodes, not a whole-cell move
        shifts.append(tuple(np.round(frac, 3)))
        d = np.abs(v.particles - scene.particles)
        assert d.max() <= 0.5 * h + 1e-12 and d.max() > 0.05 * h
        np.testing.assert_array_equal(v.volumes, scene.volumes)
        assert v.particles[:, 2].min() >= scene.table.height
    assert len(set(shifts)) == 3


def test_each_fit_is_scored_with_its_own_substeps():
    """A base model scored beside a viscous candidate (which needs 4x the substeps) moves exactly as it does
    alone: the substep count comes from each fit's scene (Scene.dt_materials: the diagnosis's clock and the
    fit's box), not from the batch."""
    import dataclasses

    from empm_gym.identification.doctor.core import _box_corners, _Fit, _simulate_fits
    from empm_gym.identification.problem import _ForwardSim, substeps_for
    from empm_gym.sim import MaterialConfig

    T = 4
    scene, _ = _still_scene(T=T)
    pos = scene.ee_positions.copy()
    pos[:, 0, 2] = np.linspace(0.06, 0.035, T)  # the sphere presses on the block
    scene = dataclasses.replace(scene, ee_positions=pos)
    base = MaterialConfig(E=2e4, nu=0.3, density=1000.0)
    visc = base.replace(viscosity=200.0)
    sc_base = dataclasses.replace(scene.with_material(base), dt_materials=_box_corners(base, {"E": (1e4, 4e4)}))
    sc_visc = dataclasses.replace(scene.with_material(visc),
                                  dt_materials=_box_corners(visc, {"E": (1e4, 4e4), "viscosity": (10.0, 500.0)}))
    n_base, _ = substeps_for(sc_base, [base], 0.0)
    n_visc, _ = substeps_for(sc_visc, [visc], 0.0)
    assert n_visc > 2 * n_base  # the viscous box needs far smaller steps
    fits = [_Fit("base", {"E": 2e4}, base, 0.5, 0.0, 0.0, scene=sc_base),
            _Fit("viscosity", {"E": 2e4, "viscosity": 200.0}, visc, 0.5, 0.0, 0.0, scene=sc_visc)]
    X = _simulate_fits(fits, T)
    alone, _, _ = _ForwardSim(sc_base, [base], [0.5]).run(T)
    np.testing.assert_array_equal(X[:, 0], alone[:, 0])
    batched, _, _ = _ForwardSim(sc_visc, [base, visc], [0.5, 0.5]).run(T)
    np.testing.assert_array_equal(X[:, 1], batched[:, 1])
    assert np.abs(batched[:, 0] - alone[:, 0]).max() > 0  # the bug this guards against: dt from the batch


def test_variant_refits_also_start_from_the_base_model_inside_each_candidate():
    """A candidate's refit on a variant also starts where its effect vanishes (at the variant's base E), from
    its own optimum with E moved as the base model's E moved, from its optima on the variants refitted before
    (each once, clipped to its box) and from its own optimum as it is (an effect that stands in for part of the
    stiffness: session 45's viscosity); every start lies in the candidate's box."""
    from empm_gym.identification.doctor.core import _ABSENT, _Fit, _search_box, _variant_starts
    from empm_gym.sim import MaterialConfig

    stiff = MaterialConfig(E=1e5, nu=0.3, density=1000.0)
    base = _Fit("base", {"E": 2e4}, stiff, 0.5, 1.0, 0.0)
    vbase = _Fit("base", {"E": 5e4}, stiff, 0.5, 1.0, 0.0)
    vanish = {"yield_stress": 1, "viscosity": 0, "grip_friction": 1, "fracture_strain": 1}  # box end: 0 low, 1 high
    for effect in EFFECTS:
        ps = candidate_params(effect)
        assert set(ps) <= set(_ABSENT), effect
        bounds = {"E": (1e4, 6e4), **{p: _search_box(p, stiff, 0.01) for p in ps}}
        params = {"E": 1.5e4, **{p: float(np.mean(bounds[p])) for p in ps}}
        like = _Fit(effect, params, stiff, 0.5, 1.0, 0.0, bounds=bounds)
        absent, moved, unscaled = _variant_starts(like, base, vbase)
        assert absent["E"] == 5e4 and moved["E"] == pytest.approx(1.5e4 * 2.5) and unscaled == params
        elsewhere = {"E": 5.5e4, **{p: float(bounds[p][0]) for p in ps}}  # found on a variant before
        beyond = {"E": 9e4, **{p: float(bounds[p][1]) for p in ps}}  # E outside this fit's window
        starts = _variant_starts(like, base, vbase, [elsewhere, beyond, dict(elsewhere)])
        assert starts[:3] == [absent, moved, elsewhere] and starts[4] == unscaled
        assert starts[3] == {**beyond, "E": 6e4} and len(starts) == 5  # clipped; the repeat left out
        # the optimum unscaled where the base model's E did not move is the moved start, not a second one
        assert _variant_starts(like, base, base) == [{**absent, "E": 2e4}, params]
        assert all(bounds[k][0] <= v <= bounds[k][1] for st in starts for k, v in st.items())
        for p in ps:
            lo, hi = bounds[p]
            want = 0.5 if p == "friction" else 0.0 if p.startswith("stiffness_slope") else (lo, hi)[vanish[p]]
            assert absent[p] == pytest.approx(want), (effect, p)
            assert moved[p] == params[p]
        assert all(bounds[k][0] <= v <= bounds[k][1] for st in (absent, moved) for k, v in st.items())


def test_each_candidate_at_its_absent_start_moves_as_the_base_model():
    """Every candidate holds the base model at the start where its effect vanishes (:data:`_ABSENT`, clipped to
    its search box): a stiff body (the top of the doctor's E box), gripped at both ends and pulled apart, moves
    as the elastic base model does. The grip friction's box once ended at 30, where a gripper holding a stiff
    body slips: the gripper-slip candidate could not reproduce the rigid grip it is meant to relax."""
    import dataclasses

    from empm_gym.identification.doctor.core import _ABSENT, _search_box
    from empm_gym.identification.problem import _ForwardSim
    from empm_gym.perception.scripts import ObjectGeometry, run_script
    from empm_gym.sim import MaterialConfig, sample_box

    T, dx = 8, 0.01
    size = (0.06, 0.04, 0.03)
    s = run_script("pull-apart", T, ObjectGeometry(size))
    # the body pulled to its full stretch within these frames
    x, vol = sample_box((-size[0] / 2, -size[1] / 2, 0.0), (size[0] / 2, size[1] / 2, size[2]), dx, 8, seed=1)
    pos = s.positions.copy()
    pos[:, 0, 0] = np.linspace(pos[0, 0, 0], pos[-1, 0, 0], T)
    pos[:, 1, 0] = np.linspace(pos[0, 1, 0], pos[-1, 1, 0], T)
    lo, hi = s.reach
    scene = Scene(x, vol, fps=30.0, ee_configs=[EndEffectorConfig(**e) for e in s.end_effectors], ee_positions=pos,
                  ee_grip=s.grip, dx=dx, motion_bounds=(lo, hi))
    E = DoctorConfig().E_bounds[1]
    base = MaterialConfig(E=E, nu=0.3, density=1000.0)
    mats = [base]
    for effect in EFFECTS:
        vals = {}
        for p in candidate_params(effect):
            lo_p, hi_p = _search_box(p, base, dx)
            vals[p] = float(np.clip(_ABSENT[p], lo_p, hi_p))
        mats.append(base.replace(**{k: v for k, v in vals.items() if k != "friction"}))
    sc = dataclasses.replace(scene.with_material(base), dt_materials=tuple(mats))
    X, _, _ = _ForwardSim(sc, mats, [0.5] * len(mats)).run(T)
    stretch = np.ptp(X[-1, 0, :, 0]) - np.ptp(X[0, 0, :, 0])
    assert stretch > 0.01  # the base model is pulled apart by the rigid grips
    for k, effect in enumerate(EFFECTS, start=1):
        gap = np.abs(X[:, k] - X[:, 0]).max()
        assert gap < 1e-4, f"{effect} at its absent start moves {1e3 * gap:.3f} mm away from the base model"


def test_the_gap_table_says_which_way_each_metric_moved():
    """report.md's held-out gap: per metric the base model, the named effect and the change, where a lower
    distance and a higher IoU are better; without masks the IoU row is left out; with no effect, one column; the
    terminal's one line says the same."""
    from empm_gym.identification.doctor.report import gap_rows, gap_summary

    gap = {"effect": "plasticity", "total": {
        "base": {"chamfer_m": 0.004, "track_median_m": 0.002, "track_rmse_m": 0.003, "mask_iou": 0.5},
        "effect": {"chamfer_m": 0.002, "track_median_m": 0.0025, "track_rmse_m": 0.003, "mask_iou": 0.6}}}
    rows = {r["metric"]: r for r in gap_rows(gap)}
    assert rows["Chamfer (mm)"]["base model"] == pytest.approx(4.0) and rows["Chamfer (mm)"]["with plasticity"] == pytest.approx(2.0)
    assert rows["Chamfer (mm)"]["change [%]"] == pytest.approx(-50.0) and rows["Chamfer (mm)"]["better"]
    assert rows["median tracking error (mm)"]["change [%]"] == pytest.approx(25.0)
    assert not rows["median tracking error (mm)"]["better"] and not rows["RMS tracking error (mm)"]["better"]
    assert rows["mask IoU (-)"]["change [%]"] == pytest.approx(20.0) and rows["mask IoU (-)"]["better"]
    no_masks = {"effect": None, "total": {"base": {k: v for k, v in gap["total"]["base"].items() if k != "mask_iou"}}}
    rows = gap_rows(no_masks)
    assert [r["metric"] for r in rows] == ["Chamfer (mm)", "median tracking error (mm)", "RMS tracking error (mm)"]
    assert all(set(r) == {"metric", "base model"} for r in rows)
    # the terminal's line (empm doctor, make demo)
    assert gap_summary(gap) == ("held-out frames, base model -> with plasticity: Chamfer 4.0 -> 2.0 mm, median tracking "
                                "error 2.0 -> 2.5 mm, RMS tracking error 3.0 -> 3.0 mm, mask IoU 0.50 -> 0.60")
    assert gap_summary(no_masks).startswith("held-out frames, base model: Chamfer 4.0 mm") and gap_summary(None) == ""


def test_the_verdict_is_taken_again_from_doctor_json_with_non_finite_gains():
    """``select_verdict`` reads ``doctor.json`` (``bench_doctor.py --rescore`` does), where a non-finite gain, a
    candidate or a variant whose simulation diverged, is written as null: it counts as not holding, as in the
    doctor itself, instead of raising."""
    from empm_gym.identification.doctor.core import _jsonable, select_verdict

    def test(gain):
        return {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04}

    cands = [{"effect": "fracture", "heldout": {"loss": 1.0}, "gain": test(0.5)},
             {"effect": "plasticity", "heldout": {"loss": 1.1}, "gain": test(0.45)},
             {"effect": "viscosity", "heldout": {"loss": 2.0}, "gain": test(float("nan"))}]
    labels = [("grid shifted (1)", "discretisation"), ("grid shifted (2)", "discretisation"),
              ("without camera 0", "body")]

    def tests(gains):
        return {"tests": [{"variant": v, "kind": k, **test(g)} for (v, k), g in zip(labels, gains)]}

    variants = {"variants": [v for v, _ in labels],
                "candidates": {"fracture": tests([0.5, float("nan"), 0.5]), "plasticity": tests([0.4, 0.4, 0.4])}}
    live = select_verdict(cands, variants)
    stored = json.loads(json.dumps(_jsonable({"c": cands, "v": variants})))
    assert stored["v"]["candidates"]["fracture"]["tests"][1]["gain"] is None
    assert select_verdict(stored["c"], stored["v"]) == live == ("plasticity", "fracture", ["plasticity"])


def test_a_table_friction_near_the_assumed_one_is_not_named():
    """A table friction fitted within ``friction_equivalence`` of the base model's is the base's table: on rope
    drag recordings without any hidden effect, E and friction fitted together gained 4.5-5.9 % held out at
    friction 0.54-0.60 (session 25). Such a candidate is not named, the next one is, and a slippery table
    (friction 0.05, the benchmark's) still is."""
    from empm_gym.identification.doctor.core import _friction_equivalent, select_verdict

    assert _friction_equivalent(0.544, 0.5, 1.5) and _friction_equivalent(0.34, 0.5, 1.5)
    assert not _friction_equivalent(0.05, 0.5, 1.5) and not _friction_equivalent(0.8, 0.5, 1.5)
    assert not _friction_equivalent(0.544, 0.5, 1.0)          # the rule off
    assert not _friction_equivalent(None, 0.5, 1.5)           # no friction fitted
    assert _friction_equivalent(0.25, 0.2, 1.5)               # around the base material's own friction
    # a later round, after the table friction was named: every candidate refits the base model's friction, which
    # says nothing of its own effect (every candidate was set aside as the base's table, session 74's pushed rope)
    from empm_gym.identification.doctor.core import base_table_fit
    carried = DoctorConfig(carried=("friction",))
    assert not base_table_fit({"E": 2e4, "yield_stress": 300.0, "friction": 0.051}, 0.048, carried)
    assert base_table_fit({"E": 2e4, "friction": 0.544}, 0.5, DoctorConfig())  # round 1's table friction
    assert not base_table_fit({"E": 2e4, "yield_stress": 300.0}, 0.5, DoctorConfig())

    def test(gain):
        return {"gain": gain, "lower": gain - 0.005, "upper": gain + 0.005, "threshold": 0.04}

    def cands(friction):
        return [{"effect": "table_friction", "heldout": {"loss": 0.94}, "gain": test(0.06),
                 "equivalent_to_base": _friction_equivalent(friction, 0.5, 1.5)},
                {"effect": "plasticity", "heldout": {"loss": 0.95}, "gain": test(0.05)}]

    assert select_verdict(cands(0.544), None) == ("plasticity", "plasticity", ["plasticity"])
    assert select_verdict(cands(0.05), None) == ("table_friction", "table_friction", ["table_friction", "plasticity"])
    scene, obs = _still_scene()
    with pytest.raises(DoctorError, match="friction_equivalence"):
        diagnose(scene, obs, config=DoctorConfig(friction_equivalence=0.5), progress=False)


def test_a_fit_that_ends_where_its_effect_vanishes_is_not_named():
    """A candidate's effect parameter at the bound of its box on the side where the effect vanishes (a fracture
    strain or a grip at the top, a viscosity at the bottom) is the least of the effect the box allows; its optimum
    lies toward the base model. On dough lifted by one end without any effect (seed 11, benchmarks/RESULTS.md,
    session 53) fracture gained 6.1 % held out at a strain of 1.50, the top of its box, and was named at
    confidence 0.59. Such a fit is not named, is no rival of the verdict and is not listed as not ruled out; the
    same effect at its strong end (a viscosity at its cap, a grip at its slipperiest) and parameters whose effect
    vanishes inside the box (a stiffness slope, the table's friction) are never set aside."""
    from empm_gym.identification.doctor.core import no_rivals, not_ruled_out, select_verdict, toward_absence

    box = {"E": (2e3, 5e5), "fracture_strain": (0.02, 1.5), "viscosity": (0.5, 8.8), "grip_friction": (0.1, 1e4),
           "yield_stress": (50.0, 1e6), "stiffness_slope_1": (-1.2, 1.2), "friction": (0.01, 3.0)}
    assert toward_absence({"E": 2e3, "fracture_strain": 1.5}, box) == ["fracture_strain"]  # E at its bound: not this
    assert toward_absence({"E": 2.7e4, "fracture_strain": 1.45}, box) == ["fracture_strain"]  # within 5 % (log)
    assert toward_absence({"E": 2.7e4, "fracture_strain": 1.3}, box) == []
    assert toward_absence({"E": 2.7e4, "fracture_strain": 0.02}, box) == []  # the strongest fracture the box holds
    assert toward_absence({"viscosity": 0.519}, box) == ["viscosity"]
    assert toward_absence({"viscosity": 8.7}, box) == []  # at its cap: as much viscosity as the box allows
    assert toward_absence({"grip_friction": 9.9e3}, box) == ["grip_friction"]  # a grip that does not slip
    # within 2.5 % of a log box's width in log space (five decades: from 7,499 up), as a linear box's bound: the
    # refit at 8,912 on a trimmed body of session 80 held gripper slip on a recording without an effect
    assert toward_absence({"grip_friction": 8912.0}, box) == ["grip_friction"]
    assert toward_absence({"grip_friction": 7000.0}, box) == []
    assert toward_absence({"E": 2.7e4, "fracture_strain": 1.34}, box) == []  # 1.875 decades: 1.35 up
    assert toward_absence({"grip_friction": 0.1}, box) == []
    assert toward_absence({"yield_stress": 9.8e5}, box) == ["yield_stress"]
    assert toward_absence({"stiffness_slope_1": 0.0}, box) == [] and toward_absence({"friction": 0.5}, box) == []
    assert toward_absence({"stiffness_slope_1": 1.2, "friction": 3.0}, box) == []
    assert toward_absence({"fracture_strain": 0.2, "fracture_softening": 0.005},
                          {**box, "fracture_softening": (0.005, 0.5)}) == []  # abrupt damage is no absent fracture

    def test(gain, width=0.005):
        return {"gain": gain, "lower": gain - width, "upper": gain + width, "threshold": 0.04}

    def cands(absent):
        return [{"effect": "fracture", "heldout": {"loss": 0.939}, "gain": test(0.061),
                 "toward_absence": ["fracture_strain"] if absent else []},
                {"effect": "heterogeneous_stiffness", "heldout": {"loss": 0.95}, "gain": test(0.05)},
                {"effect": "viscosity", "heldout": {"loss": 0.99}, "gain": test(0.01, 0.04),
                 "toward_absence": ["viscosity"] if absent else []}]

    assert select_verdict(cands(False), None)[0] == "fracture"
    assert select_verdict(cands(True), None) == ("heterogeneous_stiffness", "heterogeneous_stiffness",
                                                 ["heterogeneous_stiffness"])
    assert no_rivals(cands(True), None) == ["fracture", "viscosity"] and no_rivals(cands(False), None) == []
    assert [e["effect"] for e in not_ruled_out(cands(False), "fracture")] == ["viscosity"]
    assert not_ruled_out(cands(True), "heterogeneous_stiffness") == []


def test_a_diagnosis_sets_aside_a_fit_that_ends_where_its_effect_vanishes(monkeypatch):
    """End to end on a block pushed by a sphere with a low yield stress: plasticity gains nearly all the held-out
    loss and is named, its fit inside its box (``toward_absence`` empty). Were its yield stress at the top of the
    box (the rule's answer replaced, the fits and scores real), it is not named: the verdict is ``none``, the
    candidate says why in ``doctor.json``, a note and the reason, and its signature is not checked."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig

    scene, obs = _pushed_block(MaterialConfig(E=3.0e4, nu=0.3, density=1000.0, yield_stress=300.0))
    cfg = DoctorConfig(base_iters=4, candidate_iters=3, popsize=6, variants=0, base_E=1.5e4)
    res = diagnose(scene, obs, effects=["plasticity"], config=cfg, progress=False)
    (cand,) = res["candidates"]
    assert res["effect"] == "plasticity" and cand["gain"]["significant"] and cand["toward_absence"] == []
    assert cand["params"]["yield_stress"] < 1e3

    seen = []

    def at_top(params, bounds):
        seen.append(bounds["yield_stress"])
        return ["yield_stress"]

    monkeypatch.setattr(core, "toward_absence", at_top)
    res = diagnose(scene, obs, effects=["plasticity"], config=cfg, progress=False)
    (cand,) = res["candidates"]
    assert seen and all(b == core._search_box("yield_stress", scene.material, scene.dx) for b in seen)
    assert cand["gain"]["significant"] and cand["toward_absence"] == ["yield_stress"]
    assert res["effect"] == "none" and cand["signature_check"] is None and res["not_ruled_out"] == []
    assert "ends where its effect vanishes (yield_stress at its bound)" in res["reason"], res["reason"]
    assert any("where the effect vanishes (yield_stress = " in n for n in res["notes"]), res["notes"]


def test_two_effects_that_both_hold_are_ranked_over_every_discretisation():
    """Fracture and plasticity both explain a torn rope almost equally well; which of them a short CMA-ES run
    puts ahead on the doctor's own discretisation varied between two runs of the same recording (rope lift-end-0
    fracture, session 26), while fracture gained more on all five variants in both. The verdict ranks the
    candidates that pass by their median gain over the discretisation and the variants, and the confidence
    compares them the same way; without variants the held-out loss ranks them as before."""
    from empm_gym.identification.doctor.core import _confidence, select_verdict

    def test(gain):
        return {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04}

    cands = [{"effect": "plasticity", "heldout": {"loss": 0.221}, "gain": test(0.779)},
             {"effect": "fracture", "heldout": {"loss": 0.236}, "gain": test(0.764)}]
    labels = [("grid shifted (1)", "discretisation"), ("grid shifted (2)", "discretisation"),
              ("without camera 0", "body"), ("without camera 1", "body"), ("without camera 2", "body")]

    def tests(gains):
        return {"tests": [{"variant": v, "kind": k, **test(g)} for (v, k), g in zip(labels, gains)]}

    plast, frac = [0.860, 0.853, 0.798, 0.798, 0.802], [0.876, 0.870, 0.816, 0.819, 0.834]
    variants = {"variants": [v for v, _ in labels],
                "candidates": {"plasticity": tests(plast), "fracture": tests(frac)}}
    assert select_verdict(cands, variants) == ("fracture", "plasticity", ["fracture", "plasticity"])
    assert select_verdict(cands, None) == ("plasticity", "plasticity", ["plasticity", "fracture"])
    # one variant in five where fracture fails to gain: it still passes, and its median gain over the doctor's
    # discretisation and the variants (0.818) still beats plasticity's (0.800)
    variants["candidates"]["fracture"] = tests([0.876, 0.01, 0.816, 0.819, 0.834])
    assert select_verdict(cands, variants) == ("fracture", "plasticity", ["fracture", "plasticity"])
    # two (a shifted grid and a rebuilt body): it no longer passes, plasticity is named
    variants["candidates"]["fracture"] = tests([0.876, 0.01, 0.816, 0.01, 0.834])
    assert select_verdict(cands, variants) == ("plasticity", "plasticity", ["plasticity"])

    rng = np.random.default_rng(0)
    base = 1.0 + 0.02 * rng.standard_normal(12)
    p = (1 - 0.779) * base + 0.002 * rng.standard_normal(12)
    f = (1 - 0.764) * base + 0.002 * rng.standard_normal(12)
    cfg = DoctorConfig()
    assert _confidence(base, [p, f], [1, 1], cfg, 1) < 0.05  # on the held-out frames alone plasticity is ahead
    assert _confidence(base, [p, f], [1, 1], cfg, 1, variant_gains=[plast, frac]) > 0.95
    assert _confidence(base, [p, f], [1, 1], cfg, 0, variant_gains=[plast, frac]) < 0.05


def test_a_candidate_whose_fit_moves_its_own_signature_away_from_the_measurement_is_not_named():
    """Seed 15's dough pulled apart with a hidden fracture (benchmarks/RESULTS.md, session 41): gripper slip gained
    11.7 % held out and was named, but its fit took the tracks' slip relative to the gripper from 5.81 mm away from
    the measurement to 6.99 mm (depth noise 1.41 mm); fracture gained about as much. A candidate its own trusted
    signature contradicts is out of the verdict and of the confidence's rivals; one whose signature shows
    nothing beyond the noise stays (its verdict's confidence is halved, as before)."""
    from empm_gym.identification.doctor.core import no_rivals, select_verdict, signature_check

    slip = signature_check("gripper_slip", {"track_slip_m": 5.81e-3}, {"track_slip_m": 6.99e-3}, noise_m=1.41e-3)
    assert slip["explained"] is False and not slip["unsupported"] and slip["trusted"]
    quiet = signature_check("gripper_slip", {"track_slip_m": 1.2e-4}, {"track_slip_m": 2.2e-4}, noise_m=1.34e-3)
    assert quiet["explained"] is None and quiet["unsupported"]

    def test(gain):
        return {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04}

    def cands(contradicted):
        return [{"effect": "gripper_slip", "heldout": {"loss": 0.0041}, "gain": test(0.117),
                 "contradicted_by_signature": contradicted},
                {"effect": "fracture", "heldout": {"loss": 0.0042}, "gain": test(0.10)},
                {"effect": "viscosity", "heldout": {"loss": 0.0046}, "gain": test(0.003)}]

    assert select_verdict(cands(False), None) == ("gripper_slip", "gripper_slip", ["gripper_slip", "fracture"])
    assert select_verdict(cands(True), None) == ("fracture", "fracture", ["fracture"])
    assert no_rivals(cands(True), None) == ["gripper_slip"] and no_rivals(cands(False), None) == []
    # the only significant candidate contradicted: none, and the benchmark's rescore agrees
    only = [c for c in cands(True) if c["effect"] != "fracture"]
    assert select_verdict(only, None) == (None, None, [])
    assert DoctorConfig().signature_veto
    from empm_gym.identification.doctor.core import signature_contradicts, signature_overshot

    assert signature_contradicts(slip) and not signature_overshot(slip) and not signature_contradicts(quiet)
    # across the measurement and no further than the base model's discrepancy plus the noise: an overshoot, doubted
    # and not vetoed (varied seed 23's stiff rope dragged over a slippery table, session 61: the base model's rope
    # slid 6.92 mm less than the observed one, the table-friction fit 7.39 mm more, noise 2.41 mm; 80.8 % held out)
    dragged = signature_check("table_friction", {"table_slide_m": 6.92e-3}, {"table_slide_m": -7.39e-3},
                              noise_m=2.41e-3)
    assert dragged["explained"] is False and dragged["overshot"] and dragged["doubted"]
    assert not signature_contradicts(dragged)
    # further across than that (a slip of 12.7 mm predicted where 1.7 mm was measured, noise 1.49 mm), or on the
    # same side, stays a contradiction; so does any overshoot of a feature that is no signed length
    for base, fit in ((1.7e-3, -12.68e-3), (-6.92e-3, -7.39e-3)):
        c = signature_check("table_friction", {"table_slide_m": base}, {"table_slide_m": fit}, noise_m=1.49e-3)
        assert not c["overshot"] and signature_contradicts(c), (base, fit)
    key = "residual_after_release_vs_contact"
    assert not signature_contradicts(None)
    # a residual ratio (once free over in contact) that a fit raises contradicts it where the ratio is or ends over
    # 1: an excess once free made worse (a plasticity fitted to the dough pushed with a hidden viscosity, varied
    # seed 20: 1.733 -> 1.805) or made (0.48 -> 1.3); under 1 with both fits neither model shows an excess once
    # free, and the fit is doubted, not vetoed (the rounded lump pressed with a hidden plasticity, seed 41, session
    # 79: 0.295 -> 0.311, a held-out gain of 23.0 % on every variant, called `none` at 1.00 by the veto)
    from empm_gym.identification.doctor.core import signature_no_excess

    for base, fit in ((1.733, 1.805), (0.48, 1.3)):
        c = signature_check("plasticity", {key: base}, {key: fit})
        assert c["explained"] is False and not c["no_excess"] and signature_contradicts(c), (base, fit)
    for base, fit in ((0.295, 0.311), (0.48, 0.83)):
        c = signature_check("plasticity", {key: base}, {key: fit})
        assert c["explained"] is False and c["no_excess"] and c["doubted"] and not signature_contradicts(c)
        # a check stored before the flag existed is judged the same
        assert not signature_contradicts({k: v for k, v in c.items() if k != "no_excess"})
    assert not signature_no_excess(signature_check("plasticity", {key: 0.48}, {key: 0.30}))  # lowered: explained
    assert not signature_no_excess(signature_check("gripper_slip", {"track_slip_m": 1e-4}, {"track_slip_m": 5e-4}))


def test_candidates_that_pass_rank_by_the_discretisations_each_comes_first_on_before_their_median_gain():
    """Seed 16's dough lifted by one end with a hidden fracture (benchmarks/RESULTS.md, session 44; the gains as
    stored): fracture gains more than gripper slip on the doctor's body and on 3 of the 4 variants, by 0.2-3.8
    points, and slip 0.3 points more on one, which puts slip's median over the five 0.3 points higher. The gains
    of one discretisation are paired (one body, one grid, one base model refitted on it): fracture is named,
    and the confidence's resamples rank the two the same way."""
    from empm_gym.identification.doctor.core import _beats, _confidence, select_verdict

    labels = [("grid shifted and particles resampled (1)", "discretisation"),
              ("grid shifted and particles resampled (2)", "discretisation"),
              ("without camera 0", "body"), ("without camera 1", "body")]
    gains = {"fracture": (0.1753, [0.6825, 0.7626, 0.5861, 0.1195]),
             "gripper_slip": (0.1370, [0.6786, 0.7607, 0.5887, 0.1168])}

    def test(g):
        return {"gain": g, "lower": g - 0.015, "upper": g + 0.03, "threshold": 0.04}

    cands = [{"effect": "fracture", "heldout": {"loss": 0.003385}, "gain": test(gains["fracture"][0])},
             {"effect": "gripper_slip", "heldout": {"loss": 0.003543}, "gain": test(gains["gripper_slip"][0])}]
    variants = {"variants": [lb for lb, _ in labels], "base_E": 5e5, "candidates": {
        n: {"tests": [{"variant": lb, "kind": kind, **test(g), "holds": True}
                      for (lb, kind), g in zip(labels, vg)]} for n, (_, vg) in gains.items()}}
    for n in gains:
        variants["candidates"][n].update(robust=True, why="")
    assert float(np.median([gains["gripper_slip"][0], *gains["gripper_slip"][1]])) > \
        float(np.median([gains["fracture"][0], *gains["fracture"][1]]))
    assert select_verdict(cands, variants) == ("fracture", "fracture", ["fracture", "gripper_slip"])
    # two variants more on slip's side: slip first on 3 of the 5, named
    variants["candidates"]["gripper_slip"]["tests"][0]["gain"] = 0.70
    variants["candidates"]["gripper_slip"]["tests"][1]["gain"] = 0.77
    assert select_verdict(cands, variants)[0] == "gripper_slip"
    # as many first places each (a refit whose gain is not finite is no discretisation): the higher median
    cols = [{"a": 0.2, "b": 0.1}, {"a": 0.3, "b": 0.4}, {"b": 0.5}]
    assert _beats("b", "a", cols, {"a": 0.25, "b": 0.4}) and not _beats("a", "b", cols, {"a": 0.25, "b": 0.4})
    # the confidence: frames on which both gain about what they gain on the body, fracture a little more
    rng = np.random.default_rng(0)
    base = 0.0041 + 1e-4 * rng.standard_normal(12)
    frac, slip = base * (1 - 0.1753), base * (1 - 0.1370)
    cfg = DoctorConfig()
    vg = [gains["fracture"][1], gains["gripper_slip"][1]]
    assert _confidence(base, [frac, slip], [1, 1], cfg, 0, variant_gains=vg) > 0.95
    assert _confidence(base, [frac, slip], [1, 1], cfg, 1, variant_gains=vg) < 0.05


def test_the_signature_check_asks_whether_the_effect_moves_its_own_feature_toward_the_measurement():
    """Values from the benchmark's recordings (session 31, the fits' features recomputed on the CPU): on pressed
    dough the plastic fit lowers the residual after release against that in contact (0.83 -> 0.48; the ratio
    stays under 1 either way, so it is no "agrees at 1" ratio); on dough lifted by one end with a hidden
    fracture, called gripper slip, the slip fit moves the tracks' slip relative to the gripper away from the
    measurement (0.21 -> 0.37 mm), and the doctor says so; a torn dough still in one piece leaves the fracture's
    count of pieces nothing to explain; a rate ratio agrees at 1 from either side."""
    from empm_gym.identification.doctor.core import SIGNATURE_FEATURES, signature_check, signature_discrepancy
    from empm_gym.sim.effects import EFFECTS

    assert set(SIGNATURE_FEATURES) == set(EFFECTS)
    key = "residual_after_release_vs_contact"
    c = signature_check("plasticity", {key: 0.8332}, {key: 0.4801})
    assert c["explained"] is True and c["feature"] == key and c["base"] == 0.8332 and c["with_effect"] == 0.4801
    assert c["trusted"] and not c["doubted"]
    assert c["discrepancy_with_effect"] < c["discrepancy_base"] and c["unit"] == "-" and c["meaning"]
    assert signature_check("plasticity", {key: 0.48}, {key: 0.83})["explained"] is False
    c = signature_check("gripper_slip", {"track_slip_m": 2.071e-4}, {"track_slip_m": 3.654e-4})
    assert c["explained"] is False and c["discrepancy_base"] == pytest.approx(2.071e-4)
    assert c["trusted"] and c["doubted"]
    # a feature the doctor does not trust for its effect is shown, never doubted: the rope's stiffness field
    # gains 77 % held out and moves the residual asymmetry from 0.024 to -0.068
    c = signature_check("heterogeneous_stiffness", {"residual_asymmetry": 0.024}, {"residual_asymmetry": -0.068})
    assert c["explained"] is False and not c["trusted"] and not c["doubted"]
    assert signature_check("gripper_slip", {"track_slip_m": -5.5e-3}, {"track_slip_m": 1.3e-3})["explained"] is True
    # a discrepancy in metres under the depth noise is none to explain: seed 14's dough lifted by one end with a
    # fracture, called gripper slip (0.83): the base model's tracks 0.44 mm from the measured slip, noise 1.36 mm
    c = signature_check("gripper_slip", {"track_slip_m": -4.4e-4}, {"track_slip_m": 2.6e-4}, noise_m=1.36e-3)
    assert c["explained"] is None and c["unsupported"] and c["doubted"] and c["noise_m"] == 1.36e-3
    c = signature_check("gripper_slip", {"track_slip_m": -4.4e-4}, {"track_slip_m": 2.6e-4})
    assert c["explained"] is True and not c["unsupported"] and not c["doubted"]  # no noise given: judged as before
    # a slip the grippers show beyond the noise (rope pushed and lifted, seed 10: 3.13 mm, noise 2.47 mm) is judged
    c = signature_check("gripper_slip", {"track_slip_m": 3.13e-3}, {"track_slip_m": 2.1e-4}, noise_m=2.47e-3)
    assert c["explained"] is True and not c["unsupported"] and not c["doubted"]
    # closer, but by less than the depth noise, is doubted and not vetoed: seed 18's dough lifted by one end with a
    # fracture, called gripper slip at 0.80, moved the tracks' slip from 4.25 to 3.36 mm off (noise 1.49 mm)
    c = signature_check("gripper_slip", {"track_slip_m": -4.25e-3}, {"track_slip_m": 3.36e-3}, noise_m=1.49e-3)
    assert c["explained"] is True and c["marginal"] and c["doubted"] and not c["unsupported"]
    c = signature_check("gripper_slip", {"track_slip_m": 3.13e-3}, {"track_slip_m": 2.1e-4}, noise_m=2.47e-3)
    assert not c["marginal"] and not c["doubted"]  # 2.92 mm closer: beyond the noise
    assert not signature_check("gripper_slip", {"track_slip_m": -4.25e-3}, {"track_slip_m": 3.36e-3})["marginal"]
    # a feature that is no length is not measured against the depth noise
    c = signature_check("plasticity", {key: 0.0008}, {key: 0.0009}, noise_m=1.36e-3)
    assert c["explained"] is False and not c["unsupported"] and c["noise_m"] is None
    # nothing to explain, or no feature: no judgement either way
    one = {"pieces_observed_max": 1.0, "pieces_simulated_max": 1.0}
    assert signature_check("fracture", one, dict(one))["explained"] is None
    assert signature_check("fracture", {"pieces_observed_max": 2.0, "pieces_simulated_max": 1.0},
                           {"pieces_observed_max": 2.0, "pieces_simulated_max": 2.0})["explained"] is True
    c = signature_check("gripper_slip", {"track_slip_m": None}, {"track_slip_m": 1e-3})
    assert c["explained"] is None and c["discrepancy_base"] is None and not c["doubted"]
    assert signature_check("viscosity", {"oscillation_decay": float("nan")}, {"oscillation_decay": 1.0})["explained"] is None
    assert signature_discrepancy("viscosity", {"oscillation_decay": 2.0}) == pytest.approx(math.log(2.0))
    assert signature_discrepancy("viscosity", {"oscillation_decay": 0.5}) == pytest.approx(math.log(2.0))
    assert signature_check("viscosity", {"oscillation_decay": 0.5}, {"oscillation_decay": 1.1})["explained"] is True
    assert signature_check("table_friction", {"table_slide_m": 0.02}, {"table_slide_m": -0.001})["explained"] is True
    assert signature_check("heterogeneous_stiffness", {"residual_asymmetry": 0.40},
                           {"residual_asymmetry": 0.39})["explained"] is True


def test_a_stiffness_field_within_the_discretisations_spread_is_not_named():
    """A stiffness field must vary the stiffness across the body by more than an equally valid discretisation
    moves the elastic fit's E: dough held at both ends and lifted, with no effect, gained 4-25 % with a field of
    contrast 1.8 on 4 of 5 variants while the base model's E moved by 1.9-2.6x between shifted grids (session
    27: the one effect invented on `none`). The same gains with a contrast of 9 name the field; the rule
    touches no other effect; the verdict taken again from doctor.json agrees."""
    from empm_gym.identification.doctor.core import FIELD_CONTRAST_FLOOR, _within_discretisation, select_verdict

    def test(gain):
        return {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04}

    labels = [("grid shifted (1)", "discretisation"), ("grid shifted (2)", "discretisation"),
              ("without camera 0", "body"), ("without camera 1", "body")]
    gains = [0.069, 0.255, 0.050, 0.044]

    def case(slope, effect="heterogeneous_stiffness", base_Es=(16001.0, 21456.0, 10424.0, 9567.0)):
        key = "stiffness_slope_1" if effect == "heterogeneous_stiffness" else "yield_stress"
        cands = [{"effect": effect, "params": {"E": 4004.0, key: slope}, "heldout": {"loss": 0.0048},
                  "gain": test(0.063)}]
        variants = {"variants": [v for v, _ in labels], "base_E": 8371.0,
                    "base": [{"variant": v, "kind": k, "params": {"E": E}} for (v, k), E in zip(labels, base_Es)],
                    "candidates": {effect: {"tests": [{"variant": v, "kind": k, "params": {"E": 5e3, key: slope},
                                                       **test(g)} for (v, k), g in zip(labels, gains)]}}}
        return cands, variants

    cands, variants = case(0.30)  # contrast exp(0.6) = 1.82 against 21456 / 8371 = 2.56
    why = _within_discretisation("heterogeneous_stiffness", cands[0]["params"], variants)
    assert "1.82x" in why and "2.56x" in why
    assert select_verdict(cands, variants) == (None, "heterogeneous_stiffness", [])
    # the spread counts the discretisations only: a body rebuilt from fewer views may fail on its own
    cands, variants = case(0.30, base_Es=(9000.0, 10000.0, 4e5, 2e3))
    assert select_verdict(cands, variants)[0] == "heterogeneous_stiffness"
    cands, variants = case(1.10)  # contrast 9.0
    assert not _within_discretisation("heterogeneous_stiffness", cands[0]["params"], variants)
    assert select_verdict(cands, variants)[0] == "heterogeneous_stiffness"
    cands, variants = case(1.10)  # the smallest contrast over the discretisations counts
    variants["candidates"]["heterogeneous_stiffness"]["tests"][1]["params"]["stiffness_slope_1"] = -0.2
    assert select_verdict(cands, variants)[0] is None
    cands, variants = case(500.0, effect="plasticity")
    assert not _within_discretisation("plasticity", cands[0]["params"], variants)
    assert select_verdict(cands, variants)[0] == "plasticity"
    # a spread the short refits did not measure (the shifted grids' refits ended where they started) does not
    # let a field under FIELD_CONTRAST_FLOOR through: a rope squeezed in a ring without an effect was named a field
    # of contrast 1.19 (session 60)
    flat = (8371.0, 8371.0 * 1.002, 8000.0, 12000.0)
    cands, variants = case(0.088, base_Es=flat)
    why = _within_discretisation("heterogeneous_stiffness", cands[0]["params"], variants)
    assert "1.19x" in why and f"under {FIELD_CONTRAST_FLOOR:g}x" in why
    assert select_verdict(cands, variants) == (None, "heterogeneous_stiffness", [])
    cands, variants = case(0.25, base_Es=flat)  # contrast 1.65: above the floor, and the spread is 1.00
    assert not _within_discretisation("heterogeneous_stiffness", cands[0]["params"], variants)
    assert select_verdict(cands, variants)[0] == "heterogeneous_stiffness"


def test_a_stiffness_field_that_rises_the_other_way_on_a_variant_is_not_named():
    """A material's stiffness rises towards the same end of the body on every discretisation: the rounded lump
    pushed across the table with a hidden viscosity (seed 40, session 76) was named a stiffness field at 1.00
    whose slope was +0.60 on the doctor's body, +1.10 on both shifted grids and -1.09 on the body rebuilt without
    camera 0, where its gain held too. Such a field is not named and the reason says where it reversed; the same
    field rising the same way everywhere is; a reversal where its gain fails, or on a body not counted, does not
    count; the rule touches no other effect."""
    from empm_gym.identification.doctor.core import field_not_material, select_verdict

    def test(gain):
        return {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04}

    labels = [("grid shifted (1)", "discretisation"), ("grid shifted (2)", "discretisation"),
              ("without camera 0", "body"), ("without camera 1", "body"), ("without camera 2", "body")]
    base_Es = (101566.0, 64792.0, 10027.0, 63967.0, 51942.0)

    def case(slopes, gains=(0.12, 0.069, 0.248, -0.002, 0.004), effect="heterogeneous_stiffness",
             unlike=("without camera 1", "without camera 2")):  # as measured: significantly worse bodies
        key = "stiffness_slope_1" if effect == "heterogeneous_stiffness" else "yield_stress"
        cands = [{"effect": effect, "params": {"E": 67356.0, key: slopes[0]}, "heldout": {"loss": 0.00375},
                  "gain": test(0.067)}]
        tests = [{"variant": v, "kind": k, "params": {"E": 5e4, key: s}, **test(g)}
                 for (v, k), s, g in zip(labels, slopes[1:], gains)]
        for t in tests[2:]:
            t["body_unlike"] = bool(unlike and t["variant"] in unlike)
        variants = {"variants": [v for v, _ in labels], "base_E": 67356.0,
                    "base": [{"variant": v, "kind": k, "params": {"E": E}} for (v, k), E in zip(labels, base_Es)],
                    "candidates": {effect: {"tests": tests}}}
        return cands, variants

    lump = (0.60, 1.10, 1.10, -1.085, 0.292, -0.118)
    cands, variants = case(lump)
    why = field_not_material("heterogeneous_stiffness", cands[0]["params"], variants)
    assert "+0.60 on the doctor's body" in why and "-1.08 on 'without camera 0'" in why
    assert "camera 2" not in why  # its gain fails there: its direction is no evidence
    assert select_verdict(cands, variants) == (None, "heterogeneous_stiffness", [])
    cands, variants = case((0.60, 1.10, 1.10, 1.085, 0.292, -0.118))  # rising the same way wherever it holds
    assert not field_not_material("heterogeneous_stiffness", cands[0]["params"], variants)
    assert select_verdict(cands, variants)[0] == "heterogeneous_stiffness"
    # a reversed field on a failing body the doctor's body fits significantly better is not counted either way
    cands, variants = case((0.60, 1.10, 1.10, 1.085, -0.9, 0.8), gains=(0.12, 0.069, 0.248, -0.05, 0.05))
    assert select_verdict(cands, variants)[0] == "heterogeneous_stiffness"
    cands, variants = case((0.60, 1.10, 1.10, 1.085, -0.9, 0.8), gains=(0.12, 0.069, 0.248, 0.05, 0.05))
    assert "-0.90 on 'without camera 1'" in field_not_material("heterogeneous_stiffness", cands[0]["params"],
                                                                variants)  # where it holds, it counts
    cands, variants = case((500.0, 400.0, 450.0, -300.0, 420.0, 410.0), effect="plasticity")
    assert not field_not_material("plasticity", cands[0]["params"], variants)


def test_a_candidate_as_good_as_the_winner_that_the_variants_never_checked_is_named_as_its_rival():
    """Only the best ``variant_top`` candidates are refitted on the variants; a third that gains as much as the
    named one held out (at or above the lower end of its interval) has never been tested against it: the rounded
    lump lifted by one end with a hidden fracture (seed 40, session 76) was called gripper slip at 1.00 (81.9 %,
    interval 80.4-82.7 %) with the fracture third at 80.8 %, unchecked. Such a candidate is found and named in the
    note; one below the interval, one set aside, one not significant or one the variants checked is not; without
    variants there is nothing to miss."""
    from empm_gym.identification.doctor.core import unchecked_rivals, unchecked_rivals_note

    def cand(name, gain, lower, **flags):
        return {"effect": name, "params": {"E": 1e4}, "gain": {"gain": gain, "lower": lower, "upper": gain + 0.01,
                                                               "threshold": 0.04}, **flags}

    cands = [cand("gripper_slip", 0.819, 0.804), cand("heterogeneous_stiffness", 0.814, 0.803),
             cand("fracture", 0.808, 0.791), cand("plasticity", 0.731, 0.724),
             cand("table_friction", 0.81, 0.80, equivalent_to_base=True), cand("viscosity", 0.807, 0.02)]
    variants = {"variants": ["grid (1)"], "candidates": {"gripper_slip": {"tests": []},
                                                         "heterogeneous_stiffness": {"tests": []}}}
    assert unchecked_rivals(cands, variants, "gripper_slip") == ["fracture"]
    note = unchecked_rivals_note("gripper_slip", ["fracture"], cands, 2)
    assert "fracture (80.8 %)" in note and "gripper_slip (81.9 %)" in note and "only the best 2" in note
    variants["candidates"]["fracture"] = {"tests": []}  # checked: its variants decided
    assert unchecked_rivals(cands, variants, "gripper_slip") == []
    assert unchecked_rivals(cands, None, "gripper_slip") == [] and unchecked_rivals(cands, variants, None) == []


def test_the_base_fit_scans_its_box():
    """The base fit's first generation holds E spread evenly in log E inside the box, its bounds left out."""
    from empm_gym.identification.doctor.core import _scan_starts

    s = _scan_starts((2.0e3, 5.0e5), 6)
    assert len(s) == 6 and 2.0e3 < s[0] and s[-1] < 5.0e5
    assert np.allclose(np.diff(np.log(s)), np.log(250.0) / 7)
    assert _scan_starts((2.0e3, 5.0e5), 0) == [] and _scan_starts((2.0e3, 5.0e5), -1) == []


def test_each_candidate_starts_from_the_base_model_and_scans_its_effect():
    """A candidate's first generation holds the base model inside it (the base fit's E, each effect parameter
    where its effect vanishes) and its one effect parameter spread over its box, in log for a positive one,
    leaving half the generation sampled. So a candidate never fits worse than the base model it contains: on an
    elastic block the viscosity candidate, one generation long, from the registry's 10 Pa s, fits no worse than
    the base model (before, its first generation sampled only around 10 Pa s)."""
    from empm_gym.identification.doctor.core import _ABSENT, _candidate_box, _effect_starts, _search_box
    from empm_gym.sim import MaterialConfig

    base = MaterialConfig(E=2e4, nu=0.3, density=1000.0)
    for effect in EFFECTS:
        ps = candidate_params(effect)
        st = _effect_starts(_candidate_box(effect, base, (1e4, 4e4), 0.01)[1], 2e4, 8)
        boxes = {p: _search_box(p, base.replace(E=4e4), 0.01) for p in ps}
        assert st[0] == {"E": 2e4, **{p: float(np.clip(_ABSENT[p], *boxes[p])) for p in ps}}, effect
        assert len(st) == (4 if len(ps) == 1 else 1) and all(s["E"] == 2e4 for s in st)
        for p in ps if len(ps) == 1 else ():
            vals = np.array([s[p] for s in st[1:]])
            lo, hi = boxes[p]
            assert np.all((lo < vals) & (vals < hi)), effect
            steps = np.diff(np.log(vals)) if PARAMETERS_LOG(p) else np.diff(vals)
            assert np.allclose(steps, steps[0]), effect
    assert _effect_starts({"E": (1e4, 4e4)}, 5e4, 8) == [{"E": 4e4}]  # the base model, in its window

    scene, obs = _pushed_block(MaterialConfig(E=3.0e4, nu=0.3, density=1000.0))
    cfg = DoctorConfig(base_iters=6, candidate_iters=1, popsize=6, variants=0, base_E=1.5e4)
    res = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    (cand,) = res["candidates"]
    assert cand["fit_loss"] <= res["base"]["fit_loss"] * 1.01, (cand["fit_loss"], res["base"]["fit_loss"])


def test_every_candidate_starts_inside_its_box_on_a_fine_grid():
    """The viscosity's box shrinks with the grid cell (its explicit step limit): on a soft body at dx = 5 mm it
    ends below the registry's start of 10 Pa s, and a rope diagnosed there failed with "init viscosity=10.0
    lies outside its bounds (0.5, 8.85)" (session 34). Every candidate's start lies in its box, the material it
    starts from holds that start, and a one-generation fit of the viscosity runs there."""
    from empm_gym.identification.doctor.core import _candidate_box
    from empm_gym.sim import MaterialConfig
    from empm_gym.sim.effects import PARAMETERS

    soft = MaterialConfig(E=2e3, nu=0.3, density=1000.0)
    _, box, _ = _candidate_box("viscosity", soft, (2e3, 6e3), 0.005)
    assert box["viscosity"][1] < PARAMETERS["viscosity"].start  # the case: the registry's start lies outside
    for effect in EFFECTS:
        init, bounds, start = _candidate_box(effect, soft, (2e3, 6e3), 0.005)
        for p, v in init.items():
            assert bounds[p][0] <= v <= bounds[p][1], (effect, p, v, bounds[p])
            assert p == "E" or start.get(p) == v, (effect, p)

    scene, obs = _pushed_block(MaterialConfig(E=3.0e3, nu=0.3, density=1000.0))
    scene = dataclasses.replace(scene, dx=0.005, grid=None)
    cfg = DoctorConfig(base_iters=1, candidate_iters=1, popsize=4, variants=0, base_E=3e3, E_bounds=(2e3, 6e3))
    res = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    (cand,) = res["candidates"]
    assert cand["params"]["viscosity"] < PARAMETERS["viscosity"].start  # fitted inside the fine grid's box


def PARAMETERS_LOG(name):
    from empm_gym.sim.effects import PARAMETERS

    return PARAMETERS[name].transform == "log" and PARAMETERS[name].search[0] > 0


def test_every_candidate_steps_with_the_same_substeps():
    """The diagnosis's clock (:func:`_clock`) holds every candidate's box corners: each candidate's scene (the
    clock and its own box) then has the clock's stable step, whatever its effect. The viscosity's box needs no
    smaller step than the stiffness field's. And the transfers' damping, which the clock holds fixed, is real:
    the same elastic block dropped on the table rings less with 4x the substeps."""
    import dataclasses

    from empm_gym.identification.doctor.core import _box_corners, _candidate_box, _clock
    from empm_gym.identification.problem import _ForwardSim
    from empm_gym.sim import MaterialConfig, stable_dt

    base = MaterialConfig(E=1e4, nu=0.3, density=1000.0)
    window, dx = (3.3e3, 3e4), 0.01
    clock = _clock(list(EFFECTS), base, window, dx)
    dt = stable_dt(list(clock), dx, 0.4)
    own = {}
    for name in ["base", *EFFECTS]:
        _, bounds, start = _candidate_box(name, base, window, dx)
        own[name] = stable_dt(list(_box_corners(start, bounds)), dx, 0.4)
        assert stable_dt(list(clock) + list(_box_corners(start, bounds)), dx, 0.4) == dt
    assert dt == min(own.values()) and own["viscosity"] == pytest.approx(own["heterogeneous_stiffness"], rel=1e-6)
    assert own["base"] > 1.5 * dt  # without the clock, the base model took larger steps than the slope's box

    from .test_effect_params import _scene

    sc = _scene(base)
    T = sc.ee_positions.shape[0]
    sc = dataclasses.replace(sc, particles=sc.particles + [0.0, 0.0, 0.03], ee_grip=np.zeros_like(sc.ee_grip),
                             ee_positions=np.full_like(sc.ee_positions, 0.5))  # no end-effector near it
    ring = []
    for top in (base, base.replace(E=16 * base.E)):  # 4x the substeps
        X, _, _ = _ForwardSim(dataclasses.replace(sc, dt_materials=(top,)), [base], [0.5]).run(T)
        ring.append(np.abs(np.diff(X[3:, 0, :, 2].max(1))).sum())  # the top's motion once it has landed
    assert ring[1] < 0.8 * ring[0], ring


def test_the_doctor_chooses_a_grid_that_resolves_the_body(tmp_path, caplog):
    """Without a cell given, the doctor loads a 2.4 cm rope (under 4 cells across at 1 cm) on the 1 cm grid halved,
    the body filled again there, and says so; a cell given is kept. On ropes recorded by a 5 mm simulation with
    no effect, the doctor at 1 cm named an effect on 3 of 6, at 5 mm on none (benchmarks/RESULTS.md, session 34).
    Images too coarse to fill the finer lattice (the same rope at 212 x 120 pixels: 117 cm^3 there against 163
    on the coarser one) leave the grid as it was, and the note says why. A finer fill that gains volume is no
    such sign: a rope in two clamps at 848 x 480 fills the 1 cm grid to 162 cm^3 and the 5 mm one to 182 (the
    clamps' prior resolved), and is refined (session 35: a 10 % tolerance both ways kept every clamp rope at
    1 cm). The dough (3.4 cells at 1 cm, under DOCTOR_CELLS_ACROSS) is refined too: at 1 cm the doctor named a
    fracture on a dough lifted by one end with no effect, on both seeds recorded at 5 mm; at 5 mm on none."""
    from empm_gym.identification.doctor import DEFAULT_DX, DOCTOR_CELLS_ACROSS, load_for_doctor
    from empm_gym.identification.uncertainty import grid_resolution
    from empm_gym.perception.synth import synthesize

    for obj, script, width, height, refined in (("rope", "press-release", 424, 240, True),
                                                ("rope", "press-release", 212, 120, False),
                                                ("rope", "squeeze-lift", 848, 480, True),
                                                ("dough", "lift-end", 424, 240, True)):
        rec = synthesize(tmp_path / f"{obj}{script}{width}", obj, script=script, effect="none",
                         frames=6 if script == "press-release" else 3, width=width, height=height, seed=0,
                         progress=False)
        coarse, obs, _, _, notes = load_for_doctor(rec, dx=DEFAULT_DX, progress=False)
        assert coarse.dx == DEFAULT_DX and not any(n.startswith("grid:") for n in notes)
        res = grid_resolution(coarse)[0]
        assert res["cells_across"] < DOCTOR_CELLS_ACROSS
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="empm_gym.identification"):
            scene, obs2, _, _, notes = load_for_doctor(rec, device="cpu", progress=False)
        note, *further = [n for n in notes if n.startswith("grid:")]
        # said before any fit starts, with what the finer grid costs on the CPU and how to avoid it
        said = [r.getMessage() for r in caplog.records if note in r.getMessage()]
        assert len(said) == (1 if refined else 0), (said, note)
        assert not refined or "On the CPU this costs up to 16x" in said[0] and "--dx 0.01" in said[0]
        assert f"{res['cells_across']:.1f} cells across" in note and obs2.num_frames == obs.num_frames
        if not refined:
            assert scene.dx == DEFAULT_DX and "was not used" in note, note
            assert np.array_equal(scene.particles, coarse.particles)
            continue
        assert scene.dx == pytest.approx(DEFAULT_DX / 2) and scene.grid_config().dx == pytest.approx(DEFAULT_DX / 2)
        assert "chosen for the body" in note
        # the chosen grid resolves the body, or a second note says why it was not refined further: with the table
        # fitted to every background point (session 57) the 424 x 240 rope reads 3.9 cells across at 5 mm, and
        # its views fill the 2.5 mm lattice to about half the 1 cm fill (images too coarse for it)
        if grid_resolution(scene)[0]["cells_across"] >= DOCTOR_CELLS_ACROSS:
            assert not further, further
        else:
            (why,) = further
            assert why.startswith("grid: not refined further; the finer grid (0.0025 m) was not used"), why
            assert f"against {1e6 * coarse.volumes.sum():.0f} cm^3" in why, why  # the fill at 1 cm
        # the same body, filled more finely: no volume lost beyond a tenth, several times the particles
        grown = scene.volumes.sum() / coarse.volumes.sum()
        assert grown > 0.9 and len(scene.particles) > 5 * len(coarse.particles)
        # (a recording this short cannot measure its tracks' scatter nor look for the table's rim: notes of their
        # own, left out here)
        hidden = [n for n in notes if not n.startswith(("grid:", "the tracks'", "the table's rim"))]
        if obj == "dough":  # the clamps hide most of it: the note quotes the body simulated, not the 1 cm fill
            (hidden,) = hidden
            assert f"of {1e6 * scene.volumes.sum():.0f} cm^3)" in hidden, hidden
            assert f"of {1e6 * coarse.volumes.sum():.0f} cm^3)" not in hidden
            # and so does the warning logged while loading, once (it once quoted the 1 cm fill first)
            logged = [r.getMessage() for r in caplog.records if "hide it from every camera" in r.getMessage()]
            assert len(logged) == 1 and hidden in logged[0], logged
        if script == "squeeze-lift":
            assert grown > 1.1  # what the tolerance must not refuse
        elif obj == "rope":
            assert grown < 1.1


def test_a_model_that_leaves_several_times_the_noise_held_out_says_the_verdict_is_not_the_whole_story():
    """The chosen model's held-out Chamfer over 4x the depth noise: a note (the rope lifted by one end without an
    effect left 11.9 mm against 1.4 mm of noise, and was called none at 0.90 in session 39); at the level a perfect
    model leaves (about 1.3x) or a good fit (under 3x), none; nothing from numbers that are not finite."""
    from empm_gym.identification.doctor.core import UNEXPLAINED_NOISE_MULTIPLE, unexplained_note

    note = unexplained_note(0.0119, 0.0014, "the base model")
    assert note.startswith("the base model still leaves a held-out Chamfer of 11.90 mm, 8.5x the depth noise (1.40 mm)")
    assert "tears or jams" in note
    assert unexplained_note(UNEXPLAINED_NOISE_MULTIPLE * 0.0014 * 1.01, 0.0014, "fracture").startswith("fracture")
    for chamfer, noise in ((0.0018, 0.0014), (0.0042, 0.0014), (UNEXPLAINED_NOISE_MULTIPLE * 0.0014, 0.0014),
                           (float("nan"), 0.0014), (0.01, float("nan")), (0.01, 0.0)):
        assert unexplained_note(chamfer, noise, "m") is None


def test_frames_where_the_object_is_wholly_hidden_are_neither_fitted_nor_scored(tmp_path):
    """A recording whose object is wholly hidden in some frames (a hand over it) is diagnosed on the others: the
    hidden frames are named in the notes and in ``hidden_frames``, and are not among the held-out frames scored;
    too few held-out frames that see the object is refused by name."""
    from empm_gym.sim import MaterialConfig

    scene, obs = _pushed_block(MaterialConfig(E=3.0e3, nu=0.3, density=1000.0))
    cfg = DoctorConfig(base_iters=2, candidate_iters=1, popsize=4, variants=0, base_E=3e3, E_bounds=(1e3, 9e3))

    def hide(frames):
        return Observations(obs.fps, [np.zeros((0, 3)) if t in frames else p for t, p in enumerate(obs.points)],
                            tracks=obs.tracks, visibility=obs.visibility)

    res = diagnose(scene, hide({5}), effects=["viscosity"], config=cfg, progress=False, out_dir=tmp_path)
    assert (tmp_path / "report.md").exists() and json.loads((tmp_path / "doctor.json").read_text())["hidden_frames"] == [5]
    assert res["hidden_frames"] == [5] and any("wholly hidden in frames 5 " in n for n in res["notes"])
    # where the time went: the stages add up to the diagnosis's wall time, and the report says it
    assert list(res["stage_wall_s"]) == ["base fit", "candidates", "signatures", "variants", "intervals",
                                         "verdict and localisation"]
    assert sum(res["stage_wall_s"].values()) == pytest.approx(res["wall_time_s"], abs=0.06)
    assert f"wall time [s]: {res['wall_time_s']:.1f} (base fit" in (tmp_path / "report.md").read_text()
    assert res["heldout_per_frame"]["frames"] == [9, 10, 11, 12] and res["gap"]["frames"] == [9, 10, 11, 12]
    assert np.isfinite(res["base"]["heldout"]["chamfer_m"])
    with pytest.raises(DoctorError, match=r"wholly hidden in frames 10.*3 of the held-out frames 9-12 see it"):
        diagnose(scene, hide({10}), effects=["viscosity"], config=cfg, progress=False)


def test_the_base_model_is_taken_at_a_candidates_E_that_fits_the_fitting_frames_better(monkeypatch):
    """Every candidate searches E too. Where a candidate's fit ends at an E at which the elastic model alone fits
    the fitting frames better than the base model's refit, the base model is taken there (session 59: a dough
    lifted by one end without any effect, its refit at 55 kPa, a plasticity that never yields at 66.5 kPa named by
    what that E gained held out). The candidates' fits are replaced by fixed results on a swinging block (3 kPa): the
    refit at 2x the truth's E, the viscosity's at the truth's E with 2 Pa s. Taken as it is, the refit lets the
    viscosity gain by its E and be named; with the base model at the viscosity's E (which the note and doctor.json
    say) the viscosity gains about nothing and the verdict is none. A move of E within 1 % is made without a note; a
    candidate's E that fits worse is not taken."""
    from empm_gym.identification.doctor import core
    from empm_gym.sim import MaterialConfig

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)
    scene, obs = _swinging_block(truth)
    cfg = DoctorConfig(base_iters=2, popsize=5, variants=0, base_E=3e3, E_bounds=(1e3, 3e4))
    found = {"base": {"E": 6.0e3}, "viscosity": {"E": 3.0e3, "viscosity": 2.0}}

    def fixed(specs, obs, progress, desc):
        return [core._Fit(name, found[name], start_mat.replace(**found[name]), 0.5, 0.0, 0.0, added=len(ps),
                          scene=sc, bounds=bounds, start_material=start_mat)
                for name, _, kw, (ps, bounds, start_mat, sc) in specs]

    monkeypatch.setattr(core, "_fit_candidates", fixed)
    res = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    assert res["base"]["params"]["E"] == 3.0e3 and res["base"]["E_from"] == "viscosity"
    (visc,) = res["candidates"]
    assert abs(visc["gain"]["gain"]) < 0.02 and res["effect"] == "none"
    (note,) = [n for n in res["notes"] if "the base model's refit ended at E = 6000 Pa" in n]
    assert "better at E = 3000 Pa, where the viscosity fit put it" in note
    # the refit as it was: the viscosity gains by the E its fit found, and is named
    monkeypatch.setattr(core, "_best_base", lambda fits, obs, F, cfg: (fits[0], float("nan")))
    kept = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    assert kept["base"]["params"]["E"] == 6.0e3 and "E_from" not in kept["base"]
    assert kept["candidates"][0]["gain"]["gain"] > 0.2 and kept["effect"] == "viscosity"
    # a move of E within 1 % is made, and not noted
    monkeypatch.undo()
    monkeypatch.setattr(core, "_fit_candidates", fixed)
    found["base"] = {"E": 3.0e3 * 1.005}
    near = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    assert near["base"]["params"]["E"] == 3.0e3 and near["base"]["E_from"] == "viscosity"
    assert not any("the base model's refit ended at" in n for n in near["notes"])
    # a candidate's E that fits the fitting frames worse leaves the refit as it is
    monkeypatch.undo()
    sc = dataclasses.replace(scene, dt_materials=core._clock(["viscosity"], truth, (1.0e3, 9.0e3), scene.dx))
    fits = fixed([core._candidate_spec(n, sc, truth, (1.0e3, 9.0e3), 13, cfg) for n in ("base", "viscosity")], obs,
                 False, "")
    fits[0].params, fits[1].params = {"E": 3.0e3}, {"E": 9.0e3, "viscosity": 2.0}
    base, loss = core._best_base(fits, obs, 13, cfg)
    assert base is fits[0] and np.isfinite(loss)


def test_a_deterministic_diagnosis_simulates_every_fit_variant_and_rebuilt_body_deterministically(monkeypatch):
    """``DoctorConfig(deterministic=True)`` reaches every simulation: the fits and scores on the doctor's body,
    the variants' discretisations and a body given from outside (which arrives without the flag)."""
    from empm_gym.identification.doctor.core import _check_variants, _fit_candidate
    from empm_gym.sim import MaterialConfig, SolverMPM

    made = []
    init = SolverMPM.__init__

    def recording_init(self, model, config=None):
        init(self, model, config)
        made.append((model.particle_count, self.config.deterministic, self._fixed is not None))

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0)
    scene, obs = _pushed_block(truth)  # its observations simulated before the recorder below
    monkeypatch.setattr(SolverMPM, "__init__", recording_init)
    cfg = DoctorConfig(base_iters=1, candidate_iters=1, popsize=4, variants=0, base_E=3.0e3, deterministic=True)
    res = diagnose(scene, obs, effects=["viscosity"], config=cfg, progress=False)
    assert res["candidates"] and made and all(d and fixed for _, d, fixed in made), made
    assert res["deterministic"] is True
    # the variants' check, on a scene the diagnosis made deterministic, with a body rebuilt elsewhere
    made.clear()
    det = dataclasses.replace(scene, deterministic=True)
    other = dataclasses.replace(scene, particles=scene.particles[::2], volumes=scene.volumes[::2] * 2.0)
    assert not other.deterministic
    T, F = 13, 9
    cfg = dataclasses.replace(cfg, variants=1, variant_iters=1)
    base, visc = (_fit_candidate(name, det, obs, truth, (1e3, 1e4), F, cfg, False) for name in ("base", "viscosity"))
    out = _check_variants([visc], det, obs, base, F, T, list(range(F, T)), cfg, False,
                          other_bodies=[("half the particles", other)])
    assert len(out["base"]) == 2 and out["candidates"]["viscosity"]["tests"]
    counts = {n for n, _, _ in made}
    assert len(other.particles) in counts and len(counts) >= 2  # the other body was simulated
    assert all(d and fixed for _, d, fixed in made), made


# ------------------------------------------------------------------------------------------ rounds


def test_a_second_round_adds_the_named_effect_to_the_base_model_and_names_another(tmp_path):
    """A block that both slips in its gripper and yields (grip friction 0.5, yield stress 150 Pa, E 3 kPa), lifted
    and swung (its observations simulated, 18 frames): the first round names the gripper slip, which explains
    most of the held-out miss; the second fits the base model with the slip, E and the grip friction fitted
    together, and names the plasticity, which brings the held-out Chamfer down again with both parameters near
    the truth. The table's friction, written into the first round's material at the assumed 0.5, stays a
    candidate. doctor.json keeps each later round's summary, its whole result in its own folder, which holds the
    material with both effects; report.md shows the rounds. (With the grip friction frozen at the first round's
    1.6, a plasticity gained 17 % here. With the previous round's model in the base fit's first generation, the
    plasticity's search missed its basin, and its lattice, which took the grip friction beside the yield stress for a
    second parameter of its own and scanned neither, did not find it: a table friction of 0.17 was named. The
    lattice scans the added effect's parameter, the base model's own at their fitted values.)"""
    from empm_gym.identification.doctor.core import candidate_params
    from empm_gym.sim import MaterialConfig
    from empm_gym.sim.material_file import read_material

    truth = MaterialConfig(E=3.0e3, nu=0.3, density=1000.0, yield_stress=150.0, params={"grip_friction": 0.5})
    scene, obs = _swinging_block(truth)
    effects = ["plasticity", "viscosity", "gripper_slip", "table_friction"]
    cfg = DoctorConfig(base_iters=3, candidate_iters=8, popsize=8, variants=0, base_E=3e3, E_bounds=(1e3, 9e3),
                       rounds=2)
    res = diagnose(scene, obs, effects=effects, config=cfg, progress=False, out_dir=tmp_path / "doc")
    (second,) = res["rounds"]
    r2 = second["result"]
    print("rounds:", res["effect"], res["confidence"], "|", r2["effect"], r2["confidence"], r2["reason"][:200])
    assert res["effect"] == "gripper_slip" and r2["effect"] == "plasticity", (res["reason"], r2["reason"])
    assert res["effects"] == ["gripper_slip", "plasticity"] and second["base_effects"] == ["gripper_slip"]
    # the second round's candidates: the catalogue's others, the table's friction among them
    assert [c["effect"] for c in r2["candidates"]] != [] and {c["effect"] for c in r2["candidates"]} == \
        {"plasticity", "viscosity", "table_friction"}
    # every fit of the second round fits the grip friction again with E; the penalty counts the added effect alone
    for c in [r2["base"], *r2["candidates"]]:
        assert set(c["params"]) == {"E", "grip_friction", *(() if c["effect"] == "base" else
                                                            candidate_params(c["effect"]))}, c["params"]
        assert c["added_params"] == (0 if c["effect"] == "base" else len(candidate_params(c["effect"])))
    # the held-out Chamfer falls round by round, and the summary says so
    slip = next(c for c in res["candidates"] if c["effect"] == "gripper_slip")
    plast = next(c for c in r2["candidates"] if c["effect"] == "plasticity")
    assert res["base"]["heldout"]["chamfer_m"] > 10 * slip["heldout"]["chamfer_m"]
    assert plast["heldout"]["chamfer_m"] < 0.5 * r2["base"]["heldout"]["chamfer_m"]
    assert second["base_heldout_chamfer_m"] == r2["base"]["heldout"]["chamfer_m"]
    assert second["notes"] == [n for n in r2["notes"] if n not in res["notes"]]
    assert second["effect_heldout_chamfer_m"] == plast["heldout"]["chamfer_m"]
    # the yield stress recovered, and the grip friction, fitted again beside it, moved from the first round's
    # toward the truth (0.5): the first round's slip had stood in for part of the yielding
    assert plast["params"]["yield_stress"] == pytest.approx(150.0, rel=0.3)
    assert 0.5 < plast["params"]["grip_friction"] < 0.8 * slip["params"]["grip_friction"]
    # the files: the summary in doctor.json (the whole result in round2/), the material with both effects
    d = tmp_path / "doc"
    stored = json.loads((d / "doctor.json").read_text())
    assert stored["effects"] == res["effects"] and "result" not in stored["rounds"][0]
    assert stored["rounds"][0]["dir"] == str(d / "round2")
    assert json.loads((d / "round2" / "doctor.json").read_text())["effect"] == "plasticity"
    final = read_material(d / "round2" / "material.json").material
    assert set(final.effects()) >= {"gripper_slip", "plasticity"}
    assert final.yield_stress == pytest.approx(plast["params"]["yield_stress"])
    report = (d / "report.md").read_text()
    assert "## Further rounds" in report and "**Effects named: gripper_slip, plasticity**" in report
    assert "round2/report.md" in report and (d / "rounds_gap.png").stat().st_size > 5000


def test_rounds_and_the_refitted_base_effects_are_checked():
    """``rounds`` is a whole number from 1; ``carried`` names effect parameters, which the base material must
    hold (a base model cannot fit again an effect it does not have)."""
    from empm_gym.sim import MaterialConfig

    for bad in (0, 1.5, True, "2"):
        with pytest.raises(ValueError, match="rounds must be a whole number"):
            DoctorConfig(rounds=bad)
    with pytest.raises(ValueError, match="unknown effect parameters"):
        DoctorConfig(carried=("yield",))
    scene, obs = _swinging_block(MaterialConfig(E=3.0e3, nu=0.3, density=1000.0), T=12, move=6)
    with pytest.raises(DoctorError, match="not parameters of the base material's effects"):
        diagnose(scene, obs, base=MaterialConfig(E=3.0e3, nu=0.3, density=1000.0), progress=False,
                 config=DoctorConfig(carried=("yield_stress",), base_iters=1, popsize=4, variants=0))


def test_doctor_cli_prints_each_round_and_where_the_material_with_every_effect_is(tmp_path, capsys, monkeypatch):
    """``empm doctor --rounds 2``: the rounds are handed to the doctor, and the summary gives each later round's
    verdict, its held-out Chamfer before and after, its report, and the material that holds every effect named."""
    import empm_gym.identification.doctor as doctor
    from empm_gym.cli import main

    fit = {"heldout": {"chamfer_m": 0.02, "loss": 0.05}, "gain": None, "at_search_bound": []}
    res = {"effect": "gripper_slip", "confidence": 1.0, "reason": "it lowers the held-out loss", "notes": [],
           "base": {**fit, "params": {"E": 2000.0}},
           "candidates": [{**fit, "effect": "gripper_slip", "params": {"E": 2.0e3, "grip_friction": 0.9},
                           "gain": {"gain": 0.85, "significant": True}}],
           "effects": ["gripper_slip", "plasticity"],
           "rounds": [{"round": 2, "base_effects": ["gripper_slip"], "effect": "plasticity", "confidence": 0.9,
                       "reason": "plasticity lowers the held-out loss by 60 %", "base_heldout_chamfer_m": 0.003,
                       "effect_heldout_chamfer_m": 0.0012, "dir": str(tmp_path / "out" / "round2"),
                       "notes": ["yield_stress = 50 Pa lies at its search bound"]}],
           "files": {"doctor": str(tmp_path / "out" / "doctor.json")}}
    seen = {}
    monkeypatch.setattr(doctor, "diagnose_recording", lambda *a, **k: seen.update(k) or res)
    assert main(["doctor", str(tmp_path), "--out", str(tmp_path / "out"), "--rounds", "2", "--quiet"]) == 0
    assert seen["config"].rounds == 2
    out = capsys.readouterr().out
    assert "round 2 (the base model with gripper_slip): plasticity  (confidence 0.90)" in out
    assert "held-out Chamfer 3.00 mm -> 1.20 mm with plasticity\n  note: yield_stress = 50 Pa lies at its search " \
           "bound" in out  # a later round's own notes (a value at its bound, ...) are said as well
    assert f"its report: {tmp_path / 'out' / 'round2'}/report.md" in out
    assert f"effects named: gripper_slip, plasticity; the material with all of them: " \
           f"{tmp_path / 'out' / 'round2'}/material.json" in out
    assert "to look for a second missing effect" not in out  # it ran in rounds
    assert main(["doctor", str(tmp_path), "--out", str(tmp_path / "o"), "--rounds", "0"]) == 2
    assert "rounds must be a whole number" in capsys.readouterr().err


def test_the_doctor_says_when_a_side_of_the_body_is_the_turned_seen_side(tmp_path):
    """A rounded lump held in two clamps shows the far slope of its middle to no camera (the clamps stand in the
    way); the loader completes it by turning the seen side half a turn. The doctor's notes say so, also after it
    fills the body again on a finer cell (the note of the coarser fill would otherwise stand for a body not
    simulated)."""
    from empm_gym.identification.doctor import DEFAULT_DX, load_for_doctor
    from empm_gym.perception.synth import synthesize

    rec = synthesize(tmp_path / "lump", "lump", script="squeeze-lift", effect="none", frames=3, seed=3,
                     progress=False)
    scene, _, _, info, notes = load_for_doctor(rec, progress=False)
    assert scene.dx < DEFAULT_DX  # refilled on a finer cell
    said = [n for n in notes if n.startswith("frame-0 body:")]
    assert len(said) == 1 and "turned half a turn" in said[0], notes
    assert info["unseen_side"]["share"] >= 0.1 and "turned half a turn" in info["body_completion"]
    # what is said is the finer fill's (36 % of the seen surface turned into the hole at 1 cm, 39 % at 5 mm)
    fine = load_for_doctor(rec, dx=scene.dx, progress=False)[3]
    assert info["unseen_side"] == fine["unseen_side"] and info["body_completion"] == fine["body_completion"]


def test_a_gain_that_no_other_discretisation_keeps_a_fifth_of_is_not_named():
    """The rounded lump pulled apart without any effect on four cameras (seed 40, session 81): gripper slip gained
    60.0 % held out on the doctor's body and 6.9 and 6.1 % on the two shifted grids, over its 4 % penalty on both and
    on the rebuilt bodies, and was named. No other discretisation keeps a fifth of that gain: it is not named, and
    the reason says by how much it shrank. The same candidate keeping 15 % on one shifted grid (a quarter) is named,
    as is one whose other grid fails outright (the variants' rule allows one miss in five)."""
    from empm_gym.identification.doctor.core import gain_not_reproduced, select_verdict

    def test(gain):
        return {"gain": gain, "lower": gain - 0.01, "upper": gain + 0.01, "threshold": 0.04}

    labels = [("grid shifted (1)", "discretisation"), ("grid shifted (2)", "discretisation"),
              ("without camera 1", "body"), ("without camera 2", "body"), ("without camera 3", "body")]

    def case(disc):
        cands = [{"effect": "gripper_slip", "params": {"E": 3619.0, "grip_friction": 17.6},
                  "heldout": {"loss": 0.00714}, "gain": test(0.600)}]
        tests = [{"variant": v, "kind": k, "params": {"E": 4e3, "grip_friction": 17.0}, **test(g)}
                 for (v, k), g in zip(labels, (*disc, 0.53, 0.375, 0.597))]
        variants = {"variants": [v for v, _ in labels], "base_E": 6202.0,
                    "base": [{"variant": v, "kind": k, "params": {"E": 6e3}} for v, k in labels],
                    "candidates": {"gripper_slip": {"tests": tests, "trimmed": {"variant": "trimmed", **test(0.677)}}}}
        return cands, variants

    cands, variants = case((0.069, 0.061))
    why = gain_not_reproduced(0.600, variants["candidates"]["gripper_slip"]["tests"])
    assert "60.0 %" in why and "6.9 %" in why, why
    assert select_verdict(cands, variants)[0] is None
    cands, variants = case((0.150, 0.061))
    assert not gain_not_reproduced(0.600, variants["candidates"]["gripper_slip"]["tests"])
    assert select_verdict(cands, variants)[0] == "gripper_slip"
    cands, variants = case((0.55, -0.3))
    assert select_verdict(cands, variants)[0] == "gripper_slip"
    assert not gain_not_reproduced(None, variants["candidates"]["gripper_slip"]["tests"])  # no gain to compare


def test_the_variants_check_refutes_a_gain_that_no_other_discretisation_keeps_a_fifth_of(monkeypatch):
    """The variants check itself (not only the verdict from stored tests): a candidate gaining 60 % on the doctor's
    body whose refits on the two shifted grids gain 6.9 and 6.1 % (each over its 4 % penalty, as the four-camera lump
    pulled apart without an effect did, session 81) holds on every variant and is still not robust, the reason saying
    how far its gain shrank; gaining 15 % on one of them, it is robust. The refits are fixed and the variants' gain
    tests given, in the order the check makes them."""
    from empm_gym.identification.doctor import core

    scene, obs, T, F, heldout, cfg, base, visc = _block_with_fixed_refits(monkeypatch, variants=2, viscosity=1.0)
    visc.test = {"gain": 0.600}
    for gains, robust in (((0.069, 0.061), False), ((0.150, 0.061), True)):
        given = iter(gains)

        def gain_test(*a, **kw):
            g = next(given)
            return {"gain": g, "lower": g - 0.01, "upper": g + 0.01, "threshold": 0.04, "significant": True}

        monkeypatch.setattr(core, "paired_gain_test", gain_test)
        rec = core._check_variants([visc], scene, obs, base, F, T, heldout, cfg, False)["candidates"]["viscosity"]
        assert all(t["holds"] for t in rec["tests"]) and rec["robust"] is robust, rec
        if not robust:
            assert rec["not_reproduced"] and "60.0 %" in rec["why"] and "6.9 %" in rec["why"], rec["why"]


def test_a_value_the_frames_do_not_fix_is_said_so_with_its_bound_and_why():
    """The chosen model's intervals in words (report, CLI, notes): a two-sided interval, a bound where the
    resamples' minima ran off one way, "unbounded" where they ran off both ways; the note names only the values
    not determined, each with the reason assess_fit gave it, and there is none when every value is determined."""
    from empm_gym.identification.doctor.core import interval_words, undetermined_note

    u = {"interval": [2.1e4, 3.9e4], "level": 0.95, "determined": True, "bounded_only": None}
    assert interval_words(u) == "95 % interval 2.1e+04 to 3.9e+04"
    assert interval_words({**u, "interval": [0.0, 6.02e4], "bounded_only": "upper"}) == "95 %: at most 6.02e+04"
    assert interval_words({**u, "interval": [4e3, None], "bounded_only": "lower"}) == "95 %: at least 4000"
    assert interval_words({**u, "interval": [0.0, math.inf]}) == "95 %: unbounded either way"
    intervals = {"uncertainty": {"E": u, "yield_stress": {**u, "interval": [0.0, math.inf], "determined": False}},
                 "identifiability": {"warnings": ["yield_stress: correlated with E (r = +1.00)", "grid: coarse"]}}
    note = undetermined_note("plasticity", {"E": 3e4, "yield_stress": 1087.0}, intervals)
    assert note.startswith("plasticity's fitted yield_stress = 1087 (95 %: unbounded either way) is not determined "
                           "by these frames (yield_stress: correlated with E (r = +1.00))"), note
    assert "E = " not in note and "grid" not in note
    assert undetermined_note("plasticity", {"E": 3e4}, {"uncertainty": {"E": u}}) is None


def test_the_combination_the_frames_fix_is_named_where_its_values_are_not():
    """Two correlated values (E and the yield stress, r = 0.99) are each not determined; the combination the
    frames fix (yield_stress/E, a yield strain) is named in the note with its interval and gets its own row of the
    report's table; one that is not determined either gets a row that says why, and no mention in the note; a
    ratio to an assumed density (no verdict of its own) gets neither."""
    from empm_gym.identification.doctor.core import interval_rows, undetermined_note

    u = {"interval": [1e3, 1e6], "level": 0.95, "determined": False, "bounded_only": None}
    ys_e = {"value": 0.0151, "interval": [0.0142, 0.0160], "level": 0.95, "unit": "-", "of": ["E", "yield_stress"],
            "exponent": -1.0, "correlation": 0.99, "determined": True, "note": "..."}
    res = {"effect": "plasticity",
           "candidates": [{"effect": "plasticity", "params": {"E": 2.0e4, "yield_stress": 302.0}}],
           "uncertainty": {"E": u, "yield_stress": {**u, "interval": [50.0, 1e4]}},
           "identifiability": {"warnings": ["E: correlated with yield_stress (r = +0.99): only the combination "
                                            "yield_stress/E = 0.0151 is determined (see the combinations)"],
                               "combinations": {"yield_stress/E": ys_e,
                                                "E/density": {"value": 20.0, "unit": "m^2/s^2", "note": "..."}}}}
    note = undetermined_note("plasticity", res["candidates"][0]["params"], res)
    assert note.endswith("; what the frames do fix is yield_stress/E = 0.0151 (95 % interval 0.0142 to 0.016)"), note
    rows = interval_rows(res)
    assert [r["parameter"] for r in rows] == ["E", "yield_stress", "yield_stress/E"], rows
    assert rows[2]["value"] == "0.0151" and rows[2]["determined"] == "yes" and rows[2]["why not"] == ""
    res["identifiability"]["combinations"]["yield_stress/E"] = {**ys_e, "determined": False, "note": "too wide"}
    assert "what the frames do fix" not in undetermined_note("plasticity", res["candidates"][0]["params"], res)
    assert interval_rows(res)[2]["why not"] == "too wide"
