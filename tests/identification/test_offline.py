"""Recovery of material parameters from simulator-made observations with depth-like noise, from 3x off."""

import json

import numpy as np
import pytest

from empm_gym.identification.offline import FitResult, identify, load_material
from empm_gym.identification.problem import Observations, ParamSpace, Scene, quat_angular_velocity

from . import scenes

ROPE_E = 5.0e4
DOUGH_YIELD = 1500.0


@pytest.fixture(scope="module")
def rope():
    return scenes.rope_lift(E=ROPE_E)


@pytest.fixture(scope="module")
def rope_adam(rope):
    return identify(rope.obs, rope.scene, params=("E",), method="adam", init={"E": ROPE_E / 3}, iters=14,
                    progress=False)


@pytest.mark.slow
def test_adam_recovers_rope_E_within_10_percent(rope, rope_adam):
    r = rope_adam
    assert abs(r.params["E"] / ROPE_E - 1) < 0.10, r.params
    assert r.material.E == pytest.approx(r.params["E"])
    assert r.loss_history[0] > 3 * r.loss  # started far off
    assert r.loss == min(r.loss_history)
    assert r.frames_used == rope.obs.num_frames


@pytest.mark.slow
def test_cmaes_recovers_rope_E_and_agrees_with_adam(rope, rope_adam):
    r = identify(rope.obs, rope.scene, params=("E",), method="cmaes", init={"E": ROPE_E / 3}, iters=12,
                 popsize=4, progress=False)
    assert abs(r.params["E"] / ROPE_E - 1) < 0.10, r.params
    # both minimise the same loss: they agree to within their tolerances (10 % each)
    assert abs(np.log(r.params["E"] / rope_adam.params["E"])) < np.log(1.10)
    assert r.extra["evaluations"] == 12 * 4
    assert len(r.loss_history) == 12


@pytest.mark.slow
def test_adam_recovers_dough_yield_stress_within_15_percent():
    d = scenes.dough_squeeze(yield_stress=DOUGH_YIELD, E=1.5e4, fill_from_observation=False)
    r = identify(d.obs, d.scene, params=("yield_stress",), method="adam", init={"yield_stress": 3 * DOUGH_YIELD},
                 iters=14, progress=False)
    assert abs(r.params["yield_stress"] / DOUGH_YIELD - 1) < 0.15, r.params
    assert r.material.plastic and r.material.yield_stress == pytest.approx(r.params["yield_stress"])
    assert r.material.E == 1.5e4  # not identified: kept


def test_material_json_round_trip(tmp_path, rope_adam):
    from empm_gym.sim import read_material

    p = rope_adam.save(tmp_path / "m" / "material.json")
    d = json.loads(p.read_text())
    assert set(d) == {"schema", "E", "nu", "density", "effects", "fit"} and d["schema"] == 2
    assert d["effects"] == {"table_friction": {"friction": pytest.approx(0.5)}}  # elastic: no plasticity
    assert d["fit"]["method"] == "adam" and len(d["fit"]["loss_history"]) == 14
    assert d["fit"]["wall_time_s"] > 0 and d["fit"]["frames_used"] == 24
    assert d == json.loads(json.dumps(rope_adam.to_dict()))
    mf = read_material(p)
    assert mf.material.E == pytest.approx(rope_adam.params["E"]) and mf.table_friction == pytest.approx(0.5)
    assert mf.fit["method"] == "adam"
    mat, mu = load_material(p)  # the compatibility wrapper
    assert mat == mf.material and mu == pytest.approx(0.5)
    (tmp_path / "bad.json").write_text('{"E": -3, "nu": 0.3, "density": 1000}')
    with pytest.raises(ValueError, match="bad.json.*E must lie in"):
        load_material(tmp_path / "bad.json")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_material(tmp_path / "none.json")


def test_report_plot_and_rrd(tmp_path, rope, rope_adam):
    from empm_gym.identification.problem import simulate_frames
    from empm_gym.identification.report import plot_fit, save_rrd

    png = plot_fit(rope_adam, tmp_path / "fit.png")
    assert png.stat().st_size > 10_000
    X = simulate_frames(rope.scene, [rope_adam.material], frames=4)[:, 0]
    rrd = save_rrd(tmp_path / "sim.rrd", X, rope.obs.points, 30.0, ee_positions=rope.scene.ee_positions,
                   scalars={"loss": [1.0, 2.0, None, 3.0]})
    assert rrd.stat().st_size > 1000


def test_param_space_maps_and_bounds():
    sp = ParamSpace(("E", "nu", "yield_stress", "friction", "density"),
                    {"E": (1e3, 1e7), "nu": (-0.5, 0.45), "yield_stress": (10, 1e5), "friction": (0.01, 2),
                     "density": (100, 1e4)})
    vals = {"E": 2.5e5, "nu": 0.3, "yield_stress": 700.0, "friction": 0.4, "density": 1100.0}
    z = sp.to_z(vals)
    assert z[0] == pytest.approx(np.log(0.25))  # E / 1e6 in log space
    back = sp.from_z(z)
    for k in vals:
        assert back[k] == pytest.approx(vals[k])
    assert sp.from_z(sp.clamp(np.full(5, 50.0)))["nu"] == pytest.approx(0.45)
    assert sp.from_z(sp.clamp(np.full(5, -50.0)))["E"] == pytest.approx(1e3)
    with pytest.raises(ValueError, match="unknown parameter 'G'"):
        ParamSpace(("G",), {})
    with pytest.raises(ValueError, match="bounds for 'nu'"):
        ParamSpace(("nu",), {"nu": (-0.5, 0.6)})


def test_identify_rejects_bad_arguments(rope):
    with pytest.raises(ValueError, match="method must be one of"):
        identify(rope.obs, rope.scene, method="sgd")
    with pytest.raises(ValueError, match="unknown parameter 'yeild_stress'"):
        identify(rope.obs, rope.scene, params=("yeild_stress",))
    with pytest.raises(ValueError, match="outside its bounds"):
        identify(rope.obs, rope.scene, init={"E": 1e4}, bounds={"E": (2e4, 1e5)})
    obs2 = Observations(15.0, rope.obs.points)
    with pytest.raises(ValueError, match="15.0 fps"):
        identify(obs2, rope.scene)
    with pytest.raises(ValueError, match="exceeds"):
        identify(rope.obs, rope.scene, frames=100)


def test_observations_and_scene_validation():
    with pytest.raises(ValueError, match=r"none of frames 1..1 holds an observed point"):
        Observations(30.0, [np.zeros((3, 3)), np.zeros((0, 3))])
    with pytest.raises(ValueError, match="tracks must have shape"):
        Observations(30.0, [np.zeros((3, 3))] * 2, tracks=np.zeros((3, 4, 3)), visibility=np.zeros((3, 4), bool))
    with pytest.raises(ValueError, match="ee_positions must have shape"):
        from empm_gym.sim import EndEffectorConfig

        Scene(np.zeros((4, 3)), 1e-6, fps=30.0, ee_configs=[EndEffectorConfig()], ee_positions=np.zeros((5, 2, 3)))


def test_quaternion_angular_velocity():
    ang = 0.3  # rad about z per frame
    q = np.array([[[0, 0, np.sin(a / 2), np.cos(a / 2)]] for a in (0.0, ang, 2 * ang)])
    w = quat_angular_velocity(q, 30.0)
    assert np.allclose(w[:, 0], [[0, 0, ang * 30]] * 2)


def test_adam_skips_a_non_finite_gradient_without_corrupting_the_parameters(rope, monkeypatch):
    # a NaN gradient (as a float atomic gone wrong would give) must be counted and skipped, not stepped on
    import torch

    from empm_gym.identification import offline

    class NanGrad(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.clone()

        @staticmethod
        def backward(ctx, g):
            return g * float("nan")

    calls = {"n": 0}
    real = offline.Objective.torch

    def poisoned(self, X):
        calls["n"] += 1
        loss = real(self, X)
        return NanGrad.apply(loss) if calls["n"] == 2 else loss

    monkeypatch.setattr(offline.Objective, "torch", poisoned)
    r = identify(rope.obs, rope.scene, params=("E",), method="adam", init={"E": ROPE_E / 3}, iters=3,
                 progress=False)
    assert calls["n"] >= 3
    assert r.extra["skipped_steps"] == 1
    assert all(np.isfinite(p["E"]) for p in r.param_history) and np.isfinite(r.params["E"])


def test_substep_rungs_hold_every_count_within_a_quarter():
    """The GPU fit rounds the substep count up to a rung, so that small changes of E reuse one rollout and its
    CUDA graphs: every count maps to a rung at least as large and at most 25 % larger, rungs map to
    themselves, the map never decreases, and there are few rungs (about four per doubling)."""
    from empm_gym.identification.offline import substep_rung

    r = [substep_rung(n) for n in range(1, 4097)]
    assert all(n <= v <= 1.25 * n for n, v in zip(range(1, 4097), r))
    assert all(substep_rung(v) == v for v in r)
    assert all(a <= b for a, b in zip(r, r[1:]))
    assert len(set(r)) <= 8 + 4 * 9


def test_adam_converged_needs_no_progress_and_small_steps():
    from empm_gym.identification.offline import CONVERGED_PATIENCE, CONVERGED_STEP, adam_converged

    k = CONVERGED_PATIENCE
    flat = [1.0, 0.5] + [0.5 * (1 - 1e-6)] * k
    small = [[0.0], [-0.5]] + [[-0.5 + 0.3 * CONVERGED_STEP * (i % 2)] for i in range(k)]
    assert adam_converged(flat, small, tol=1e-4)
    assert not adam_converged(flat, small, tol=0.0)  # tol 0: never
    assert not adam_converged(flat[:k], small[:k], tol=1e-4)  # too few iterations to judge
    improving = [1.0, 0.5] + [0.5 * (1 - 1e-3 * (i + 1)) for i in range(k)]
    assert not adam_converged(improving, small, tol=1e-4)
    moving = [[0.0], [-0.5]] + [[-0.5 + 2 * CONVERGED_STEP * (i % 2)] for i in range(k)]
    assert not adam_converged(flat, moving, tol=1e-4)  # the loss is flat but a step is still large
    assert not adam_converged(flat[:-1] + [float("nan")], small, tol=1e-4)


@pytest.mark.slow
def test_adam_stops_once_converged_and_the_fit_is_complete(rope):
    # started 0.5 % from the truth: Adam's first step overshoots, it halves its step until it stops moving
    r = identify(rope.obs, rope.scene, params=("E",), method="adam", init={"E": 1.005 * ROPE_E}, iters=20,
                 progress=False)
    k = r.extra["converged_at"]
    assert k is not None and r.iterations_done == k + 1 < 20 and len(r.loss_history) == k + 1
    assert r.complete and "resume" not in r.extra
    assert abs(r.params["E"] / ROPE_E - 1) < 0.05 and r.loss == min(r.loss_history)
    with pytest.raises(ValueError, match="tol must be"):
        identify(rope.obs, rope.scene, params=("E",), method="adam", iters=2, tol=-1.0, progress=False)


def test_lockstep_fits_are_the_fits_one_by_one(monkeypatch):
    """identify_lockstep steps several CMA-ES fits in turn, their worlds one batched simulation: on the CPU the
    results are those of identify alone to the last bit (each search draws its own random numbers; the scene's
    dt_materials fix the substeps, as the doctor's clock does). A fit whose box is not covered by them runs
    alone (its substeps follow its own candidates) and is also unchanged."""
    import dataclasses

    from empm_gym.identification.offline import identify_lockstep
    from empm_gym.sim import MaterialConfig

    p = scenes.rope_lift(E=ROPE_E, frames=8, lift_frames=6)
    clock = (MaterialConfig(E=2e5, nu=0.3, density=1000.0, viscosity=5.0),)
    sc = dataclasses.replace(p.scene, dt_materials=clock)
    common = dict(method="cmaes", iters=3, popsize=3, seed=4, max_points=300)
    fits = [(sc, dict(params=("E",), init={"E": ROPE_E / 3}, bounds={"E": (1e4, 2e5)}, **common)),
            (sc, dict(params=("E", "viscosity"), init={"E": ROPE_E, "viscosity": 1.0},
                      bounds={"E": (1e4, 2e5), "viscosity": (0.1, 5.0)}, extra_starts=[{"E": 3e4, "viscosity": 0.1}],
                      **common)),
            (p.scene, dict(params=("E",), init={"E": ROPE_E * 2}, bounds={"E": (1e4, 4e5)}, **{**common, "popsize": 4}))]
    from empm_gym.identification import offline

    worlds = []

    class Counted(offline._ForwardSim):
        def __init__(self, scene, materials, frictions):
            worlds.append(len(materials))
            super().__init__(scene, materials, frictions)

    monkeypatch.setattr(offline, "_ForwardSim", Counted)
    together = identify_lockstep(p.obs, fits, progress=False)
    assert worlds == [3 + 3, 4]  # the first two share one simulation of 6 worlds; the third runs alone
    monkeypatch.undo()
    for (scene, kw), r in zip(fits, together):
        alone = identify(p.obs, scene, progress=False, **kw)
        assert r.params == alone.params and r.loss_history == alone.loss_history, (kw["params"], r.params, alone.params)
        assert r.param_history == alone.param_history and r.extra["evaluations"] == alone.extra["evaluations"]
    assert together[1].params["viscosity"] != 1.0  # the viscosity was searched, not left at its start
    with pytest.raises(ValueError, match="CMA-ES fits only"):
        identify_lockstep(p.obs, [(sc, dict(params=("E",), method="adam"))], progress=False)


def test_rollouts_advanced_in_turn_are_the_rollouts_one_by_one():
    """run_together advances several simulations (different scenes: separate models) a frame each in turn, as the
    doctor's variants are simulated; each ends as run() alone ends (on the CPU to the bit), and a world whose
    check fails is NaN from that frame on in either."""
    import dataclasses

    from empm_gym.identification.problem import _ForwardSim, run_together
    from empm_gym.sim import MaterialConfig

    scs = [scenes.rope_lift(E=ROPE_E, frames=6, lift_frames=4).scene,
           dataclasses.replace(scenes.rope_lift(E=ROPE_E, frames=6, lift_frames=3).scene, table_friction=0.2)]
    mats = [MaterialConfig(E=E, nu=0.3, density=1000.0) for E in (3e4, 9e4)]
    alone = [_ForwardSim(sc, mats, [0.5, 0.3]).run(6) for sc in scs]
    together = run_together([_ForwardSim(sc, mats, [0.5, 0.3]).steps(6, queued=True) for sc in scs])
    for (xa, bad_a, _), (xt, bad_t, _) in zip(alone, together):
        np.testing.assert_array_equal(xt, xa)
        assert bad_a == bad_t == []
    assert np.ptp(together[0][0][:, 0, :, 2]) > 0.02  # the rope was lifted
    sim = _ForwardSim(scs[0], mats, [0.5, 0.3])
    sim.solver.config.max_speed = 1e-9  # every moving particle "too fast": both worlds diverge at frame 1
    (x, bad, _), = run_together([sim.steps(6, queued=True)])
    assert bad == [0, 1] and not np.isnan(x[0]).any() and np.isnan(x[1:]).all()


def test_rollouts_reusing_their_states_are_fresh_rollouts():
    """A simulation run from rest with ``reuse`` keeps its states and control (and on CUDA its frames' graphs)
    from one rollout to the next, set back to rest at the start: after a rollout that tore and yielded the
    body (damage, plastic F, velocities left in the kept states) and a change of materials, it gives what a
    new simulation gives, to the bit on the CPU, queued or not; a rollout from a given state is not affected."""
    from empm_gym.identification.problem import _ForwardSim, run_together
    from empm_gym.sim import MaterialConfig

    import dataclasses

    # the clock fixed as the doctor fixes it (a change of substeps starts new states and graphs)
    sc = dataclasses.replace(scenes.rope_lift(E=ROPE_E, frames=6, lift_frames=4).scene,
                             dt_materials=(MaterialConfig(E=2e5, nu=0.3, density=1000.0, viscosity=5.0),))
    torn = [MaterialConfig(E=3e4, nu=0.3, density=1000.0, yield_stress=500.0,
                           params={"fracture_strain": 0.01, "fracture_softening": 0.05}),
            MaterialConfig(E=9e4, nu=0.3, density=1000.0, viscosity=2.0)]
    plain = [MaterialConfig(E=E, nu=0.3, density=1000.0) for E in (5e4, 2e4)]
    sim = _ForwardSim(sc, torn, [0.5, 0.3])
    x_torn, _, end = sim.run(6, reuse=True)
    assert float(np.max(end.particle_damage.numpy())) > 0  # the kept state holds what the next must not see
    kept = sim._kept["a"]
    sim.set(plain, [0.2, 0.5])
    x_reused, bad, _ = sim.run(6, reuse=True)
    assert sim._kept["a"] is kept  # the same states, set back to rest
    x_fresh, bad_fresh, _ = _ForwardSim(sc, plain, [0.2, 0.5]).run(6)
    np.testing.assert_array_equal(x_reused, x_fresh)
    assert bad == bad_fresh == []
    (x_queued, _, _), = run_together([sim.steps(6, queued=True, reuse=True)])
    np.testing.assert_array_equal(x_queued, x_fresh)
    sim.set(torn, [0.5, 0.3])
    np.testing.assert_array_equal(sim.run(6, reuse=True)[0], x_torn)
    assert not np.array_equal(x_torn, x_fresh)

def test_frame_chunks_cover_a_frame_with_even_chunks_and_the_rest():
    from empm_gym.identification.problem import frame_chunks

    assert frame_chunks(879, 64) == (64,) * 13 + (47,)
    assert frame_chunks(128, 64) == (64, 64)
    assert frame_chunks(5, 64) == (5,)
    for bad in [(0, 64), (10, 3), (10, 0)]:
        with pytest.raises(ValueError, match="frame_chunks"):
            frame_chunks(*bad)


@pytest.mark.parametrize("chunk", [2, 4])
def test_a_frame_simulated_in_chunks_is_the_frame_simulated_whole(monkeypatch, chunk):
    """A frame's substeps run as chunks (the CUDA graphs' unit, :func:`frame_chunks`), an odd rest among them,
    give the positions the whole frame's substeps give, to the bit on the CPU, from rest and reused."""
    import dataclasses

    from empm_gym.identification import problem
    from empm_gym.identification.problem import _ForwardSim, substeps_for
    from empm_gym.sim import MaterialConfig

    sc = dataclasses.replace(scenes.rope_lift(E=ROPE_E, frames=4, lift_frames=3).scene,
                             dt_materials=(MaterialConfig(E=2e5, nu=0.3, density=1000.0),))
    mats = [MaterialConfig(E=E, nu=0.3, density=1000.0) for E in (5e4, 2e4)]
    sub = substeps_for(sc, mats, sc.ee_max_speed(4))[0]
    assert sub % chunk, "the test needs a frame that ends in a partial chunk"
    monkeypatch.setattr(problem, "GRAPH_CHUNK", 10 ** 6)
    whole = _ForwardSim(sc, mats, [0.5, 0.5]).run(4)[0]
    monkeypatch.setattr(problem, "GRAPH_CHUNK", chunk)
    sim = _ForwardSim(sc, mats, [0.5, 0.5])
    np.testing.assert_array_equal(sim.run(4)[0], whole)
    np.testing.assert_array_equal(sim.run(4, reuse=True)[0], whole)
    np.testing.assert_array_equal(sim.run(4, reuse=True)[0], whole)


@pytest.mark.skipif(not __import__("warp").is_cuda_available(), reason="needs a CUDA device")
def test_a_frame_replayed_from_chunked_cuda_graphs_is_the_frame_launched_kernel_by_kernel(monkeypatch):
    """On CUDA, a frame replayed from its chunks' graphs (two start states, whole chunks and an odd rest, each
    captured once) follows the same substeps as kernel-by-kernel launches: the same positions but for the order
    of atomic sums."""
    import dataclasses

    from empm_gym.identification import problem
    from empm_gym.identification.problem import _ForwardSim, run_together
    from empm_gym.sim import MaterialConfig

    sc = dataclasses.replace(scenes.rope_lift(E=ROPE_E, frames=5, lift_frames=4).scene, device="cuda:0",
                             dt_materials=(MaterialConfig(E=2e5, nu=0.3, density=1000.0),))
    mats = [MaterialConfig(E=E, nu=0.3, density=1000.0) for E in (5e4, 2e4)]
    monkeypatch.setattr(problem, "GRAPH_CHUNK", 4)
    plain = _ForwardSim(sc, mats, [0.5, 0.5])
    plain.graph = False
    ref = plain.run(5)[0]
    sim = _ForwardSim(sc, mats, [0.5, 0.5])
    for _ in range(2):  # captured, then replayed
        (x, bad, _), = run_together([sim.steps(5, queued=True, reuse=True)])
        assert bad == []
        np.testing.assert_allclose(x, ref, atol=1e-5)
    assert len(sim._kept["graphs"]) == 4  # (each start state) x (a whole chunk, the rest)
    assert float(np.max(np.abs(ref[-1] - ref[0]))) > 1e-3  # the rope moved


def _box_lattice(n=(10, 8, 6), s=0.004):
    g = np.stack(np.meshgrid(*[np.arange(k) * s for k in n], indexing="ij"), -1).reshape(-1, 3)
    return g, s


def test_body_surface_is_half_a_spacing_outside_the_boundary_particles():
    from empm_gym.identification.offline import body_surface

    x, s = _box_lattice()
    hi = x.max(0)
    pts = body_surface(x)
    assert len(pts) == 10 * 8 * 6 - 8 * 6 * 4  # every particle of the outer layer, no inner one
    # each lies outside the particle box by half a spacing along some axis (a face's outward normal; edges and
    # corners diagonally), and none inside it
    outside = np.maximum(np.maximum(-pts, pts - hi), 0.0)
    reach = np.linalg.norm(outside, axis=1)
    assert np.all(reach > 0.25 * s) and np.all(reach < 0.55 * s)
    faces = (np.abs(outside) > 1e-9).sum(1) == 1
    np.testing.assert_allclose(reach[faces], 0.5 * s, atol=1e-9)
    with pytest.raises(ValueError, match="no surface"):
        body_surface(x[:1])


def test_unseen_surface_matches_observed_points_on_a_side_frame_0_did_not_see():
    """A box seen only from above at frame 0 and lifted: at frame 1 the cameras see its underside. The carried
    frame-0 points (the top) cannot stand for it; with ``unseen_surface`` the observed-to-simulated half reaches
    the simulated body's own surface, and the simulated-to-observed half, numpy and torch agree."""
    import torch

    from empm_gym.identification.offline import Objective

    x, s = _box_lattice()
    hi = x.max(0)
    top = x[x[:, 2] == hi[2]] + [0.0, 0.0, 0.5 * s]
    bottom = x[x[:, 2] == 0.0] - [0.0, 0.0, 0.5 * s]
    lift = np.array([0.0, 0.0, 0.02])
    X = np.stack([x, x + lift])
    obs = Observations(30.0, [top, np.concatenate([top, bottom]) + lift], surface=True)
    scene = Scene(x, s ** 3, fps=30.0)
    plain = Objective(scene, obs, 2, l_trk=0.0)
    full = Objective(scene, obs, 2, l_trk=0.0, unseen_surface=True)
    P = plain.predicted_points(X)
    np.testing.assert_allclose(P[1], top + lift, atol=1e-6)
    # without it, the underside's points are the box's height from the nearest carried point
    height = hi[2] + s
    assert plain.chamfer(P, direction="obs_to_pred", first=1)[0] == pytest.approx(0.5 * height, rel=0.02)
    U = full.unseen_points(X)
    reach = full.chamfer(P, direction="obs_to_pred", first=1, unseen=U)[0]
    assert reach < 0.1 * s  # the bottom face's points; along its edges they lie diagonally out of the corners
    # the other half is the carried points' alone
    assert full.chamfer(P, direction="pred_to_obs", first=1, unseen=U)[0] == pytest.approx(
        plain.chamfer(P, direction="pred_to_obs", first=1)[0], abs=1e-12)
    assert full.numpy(X) == pytest.approx(0.5 * (plain.chamfer(P, direction="pred_to_obs", first=1)[0] + reach),
                                          abs=1e-12)
    # (the differentiable distances are sqrt(d^2 + 1e-12): 1e-6 m on points that match exactly)
    assert full.torch(torch.as_tensor(X)).item() == pytest.approx(full.numpy(X), abs=1.5e-6)
    assert plain.torch(torch.as_tensor(X)).item() == pytest.approx(plain.numpy(X), abs=1.5e-6)
    with pytest.raises(ValueError, match="unseen_surface needs"):
        Objective(scene, obs, 2, l_trk=0.0, observation="particles", unseen_surface=True)


def test_carried_points_are_the_weighted_sums_of_their_particles_in_numpy_and_torch():
    """The carried surface points (a sparse product a frame in numpy, a gather in torch) are sum_j a_sj x_j of
    the embedding's particles on a body deformed unevenly, frame by frame, float32 input included."""
    import torch

    from empm_gym.identification.offline import Objective

    x, s = _box_lattice()
    rng = np.random.default_rng(3)
    X = np.stack([x, x + 0.01 * np.sin(40.0 * x[:, [1, 2, 0]]), x * 1.1 + rng.normal(0, 1e-3, x.shape)])
    top = x[x[:, 2] == x[:, 2].max()] + [0.0, 0.0, 0.5 * s]
    obs = Observations(30.0, [top, top, top], surface=True)
    ob = Objective(Scene(x, s ** 3, fps=30.0), obs, 3, l_trk=0.0, unseen_surface=True)
    for emb in (ob.surf, ob.unseen):
        idx, a = emb
        want = np.einsum("tskd,sk->tsd", X[:, idx], a)
        np.testing.assert_allclose(ob._carry(X, emb), want, rtol=0, atol=1e-14)
        X32 = X.astype(np.float32)  # summed in float64
        np.testing.assert_allclose(ob._carry(X32, emb), np.einsum("tskd,sk->tsd", X32.astype(np.float64)[:, idx], a),
                                   rtol=0, atol=1e-14)
        np.testing.assert_allclose(ob._carry(torch.as_tensor(X), emb).numpy(), want, rtol=0, atol=1e-14)
    np.testing.assert_allclose(ob.predicted_points(X)[0], top, atol=1e-7)  # frame 0 reproduces the points


def test_a_frame_where_the_object_is_wholly_hidden_is_left_out_of_the_loss():
    """A frame with no observed points (a hand over the object) is not scored: the loss, its per-frame terms and
    its gradient are those of the recording with that frame cut out, tracks included (a track marked visible on
    the hidden frame counts as occluded there), on the CPU's KD-trees and on the GPU's padded all-pairs path
    (run here on torch's CPU device)."""
    import torch

    from empm_gym.identification.losses import PaddedFrames
    from empm_gym.identification.offline import Objective

    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 0.05, (300, 3))
    T, hidden = 6, 3
    X = np.stack([x + [0.004 * t, 0.0, 0.001 * t * t] for t in range(T)])
    pts = [X[t, :150] + rng.normal(0.0, 5e-4, (150, 3)) + [0.0, 0.002 * t, 0.0] for t in range(T)]
    tracks = np.stack([X[t, 200:210] + [0.0, 0.0, 0.003 * t] for t in range(T)])
    vis = np.ones((T, 10), bool)
    scene = Scene(x, np.full(300, 1e-7), fps=30.0)
    shown = [p if t != hidden else np.zeros((0, 3)) for t, p in enumerate(pts)]
    obs = Observations(30.0, shown, tracks=tracks, visibility=vis, surface=True)
    keep = [t for t in range(T) if t != hidden]
    cut = Observations(30.0, [pts[t] for t in keep], tracks=tracks[keep], visibility=vis[keep], surface=True)
    assert obs.seen.tolist() == [t != hidden for t in range(T)]
    a, b = Objective(scene, obs, T, l_trk=50.0), Objective(scene, cut, T - 1, l_trk=50.0)
    per = a.per_frame(X)
    assert np.isnan(per[hidden - 1]) and np.isfinite(np.delete(per, hidden - 1)).all()
    np.testing.assert_allclose(np.delete(per, hidden - 1), b.per_frame(X[keep]), rtol=1e-12)
    assert a.numpy(X) == pytest.approx(b.numpy(X[keep]), rel=1e-12)
    for objective in (a, b):  # the GPU's path: the seen frames padded, indexed by their rank
        objective._padded = PaddedFrames([p for p in objective.points if len(p)], torch.device("cpu"))
    assert a.numpy(X) == pytest.approx(b.numpy(X[keep]), rel=1e-12)
    ta, tb = torch.tensor(X, requires_grad=True), torch.tensor(X[keep], requires_grad=True)
    la, lb = a.torch(ta), b.torch(tb)
    la.backward()
    lb.backward()
    assert la.item() == pytest.approx(lb.item(), rel=1e-12) and la.item() == pytest.approx(a.numpy(X), abs=1e-5)
    assert torch.all(ta.grad[hidden] == 0) and torch.allclose(ta.grad[keep], tb.grad, rtol=1e-10, atol=0)
    diverged = X.copy()
    diverged[4, 0, 0] = np.nan
    assert np.isnan(a.per_frame(diverged)[hidden - 1]) and a.numpy(diverged) > 100.0
    with pytest.raises(ValueError, match=r"points\[0\] is empty"):
        Observations(30.0, [np.zeros((0, 3)), pts[1]])
    with pytest.raises(ValueError, match="none of frames 1..2 holds"):
        Observations(30.0, [pts[0], np.zeros((0, 3)), np.zeros((0, 3))])


def test_fit_losses_are_the_fits_own_losses_where_it_sampled():
    """fit_losses gives the loss identify minimises (the same frames, weights, observed points and seed) at any
    values: at the members a CMA-ES fit sampled it gives their recorded losses to the last bit on the CPU (the
    scene's dt_materials fix the substeps), the fit's best among them; bad values are refused."""
    import dataclasses

    from empm_gym.identification.offline import fit_losses
    from empm_gym.sim import MaterialConfig

    p = scenes.rope_lift(E=ROPE_E, frames=8, lift_frames=6)
    sc = dataclasses.replace(p.scene, dt_materials=(MaterialConfig(E=2e5, nu=0.3, density=1000.0),))
    kw = dict(iters=2, popsize=3, seed=4, max_points=300, l_trk=50.0, frames=7)
    r = identify(p.obs, sc, params=("E",), method="cmaes", init={"E": ROPE_E / 3}, bounds={"E": (1e4, 2e5)},
                 progress=False, **kw)
    got = fit_losses(p.obs, sc, [r.param_history[0], r.params, {"E": 2e5}], **kw)
    assert got[:2] == [r.loss_history[0], r.loss]
    assert got[2] > r.loss  # a far stiffer rope fits worse
    # another weight of the tracking term is another loss
    assert fit_losses(p.obs, sc, [r.params], **{**kw, "l_trk": 500.0})[0] != r.loss
    with pytest.raises(ValueError, match="same parameters"):
        fit_losses(p.obs, sc, [{"E": 3e4}, {"E": 3e4, "viscosity": 1.0}])
    with pytest.raises(ValueError, match="same parameters"):
        fit_losses(p.obs, sc, [])
