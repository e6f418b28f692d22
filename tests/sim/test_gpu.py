"""CUDA-only checks (skipped on machines without a GPU): CPU/GPU agreement and deterministic mode."""

import numpy as np
import pytest
import warp as wp

from empm_gym.sim import MaterialConfig, SolverConfig, SolverMPM

from .conftest import block_model

cuda = pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device")


def _run(device, config=None, steps=60):
    m = block_model(material=MaterialConfig(E=3e4, nu=0.3, density=1000.0, yield_stress=2e3), worlds=3, device=device)
    s = m.state()
    v = np.zeros((m.particle_count, 3), np.float32)
    v[:, 2] = -0.5
    s.particle_v.assign(v)
    solver = SolverMPM(m, config)
    a, b = s, m.state()
    for _ in range(steps):
        solver.step(a, b, m.control(), 4e-4)
        a, b = b, a
    return a.particle_x.numpy()


@cuda
def test_cuda_matches_cpu():
    np.testing.assert_allclose(_run("cuda:0"), _run("cpu"), atol=2e-5)


@cuda
def test_cuda_deterministic_mode_is_bit_identical():
    cfg = SolverConfig(deterministic=True)
    assert np.array_equal(_run("cuda:0", cfg), _run("cuda:0", cfg))


@cuda
def test_cell_sorted_p2g_matches_per_particle_atomics():
    # warp-summed atomics over cell-sorted particles (the CUDA default) against one atomic per particle
    # and component (sort_every=0), with the particle arrays in a shuffled order so that sorting matters
    m = block_model(material=MaterialConfig(E=3e4, nu=0.3, density=1000.0), worlds=3, device="cuda:0")
    perm = np.random.default_rng(0).permutation(m.particle_count // 3)
    x = m.state().particle_x.numpy().reshape(3, -1, 3)[:, perm].reshape(-1, 3)
    out = []
    for cfg in (SolverConfig(), SolverConfig(sort_every=0)):
        solver = SolverMPM(m, cfg)
        assert (solver._order is None) == (cfg.sort_every == 0)
        a, b = m.state(), m.state()
        a.particle_x.assign(x)
        solver.step(a, b, m.control(), 4e-4, guards=False, sort=True if cfg.sort_every else None)
        out.append(solver.scratch.v.numpy())
        for _ in range(40):
            solver.step(a, b, m.control(), 4e-4)
            a, b = b, a
        out.append(a.particle_x.numpy())
    np.testing.assert_allclose(out[0], out[2], atol=1e-6)  # grid velocity after one step
    np.testing.assert_allclose(out[1], out[3], atol=2e-5)


@cuda
def test_sorted_p2g_reads_materials_set_after_the_solver_was_made():
    # the sorted P2G reads a packed copy of the materials (Model.particle_p2g): a change of material after
    # the solvers exist must reach it as it reaches the per-particle arrays that the unsorted P2G reads
    m = block_model(material=MaterialConfig(E=3e4, nu=0.3, density=1000.0), worlds=3, device="cuda:0")
    solvers = [SolverMPM(m, SolverConfig()), SolverMPM(m, SolverConfig(sort_every=0))]
    m.set_materials([MaterialConfig(E=1e4, nu=0.2, density=800.0), MaterialConfig(E=8e4, nu=0.4, density=1200.0),
                     MaterialConfig(E=3e4, nu=0.3, density=1000.0, viscosity=2.0)])
    out = []
    for solver in solvers:
        a, b = m.state(), m.state()
        v = np.zeros((m.particle_count, 3), np.float32)
        v[:, 2] = -0.5
        a.particle_v.assign(v)
        for _ in range(40):
            solver.step(a, b, m.control(), 2e-4)
            a, b = b, a
        out.append(a.particle_x.numpy())
    np.testing.assert_allclose(out[0], out[1], atol=2e-5)


@cuda
def test_cuda_material_gradient_matches_cpu():
    from empm_gym.sim import Rollout

    W = None
    grads = []
    for device in ("cpu", "cuda:0"):
        m = block_model(material=MaterialConfig(E=2e4, nu=0.3, density=1000.0), worlds=2, requires_grad=True,
                        device=device)
        ro = Rollout(m, SolverMPM(m), steps=30, dt=5e-4, record_every=30)
        ctrls = ro.make_controls()
        s0 = m.state(requires_grad=True)
        v = np.zeros((m.particle_count, 3), np.float32)
        v[:, 0] = 0.3
        s0.particle_v.assign(v)
        recs = ro.forward(s0, ctrls)
        if W is None:
            W = np.random.default_rng(3).normal(size=(m.particle_count, 3)).astype(np.float32)
        ro.zero_grad(ctrls)
        ro.backward([None] * (len(recs) - 1) + [W], state0=s0)
        grads.append(np.concatenate([m.world_E.grad.numpy(), m.world_nu.grad.numpy()]))
    assert np.all(np.isfinite(grads[1])) and np.abs(grads[0]).max() > 0
    np.testing.assert_allclose(grads[1], grads[0], rtol=2e-3, atol=1e-3 * np.abs(grads[0]).max())


@cuda
def test_graph_rollout_matches_launches_over_repeated_fits():
    """A rollout replayed from its CUDA graphs (forward and adjoint) gives the records and gradients of the
    same rollout launched kernel by kernel, on its first run and on later runs with another material, other
    controls and other seed gradients written into the same arrays (what an Adam fit does); so does a rollout
    of aligned segments, whose two graphs (one segment) replay once per segment."""
    from empm_gym.sim import Rollout

    out = {}
    for graph, every in ((False, None), (True, None), (True, 10)):
        m = block_model(material=MaterialConfig(E=2e4, nu=0.3, density=1000.0), worlds=2, requires_grad=True,
                        device="cuda:0")
        ro = Rollout(m, SolverMPM(m, SolverConfig(check_every=0)), steps=40, dt=5e-4, substeps_per_control=10,
                     record_every=10, graph=graph, checkpoint_every=every)
        assert ro.graph == graph and ro.aligned == (every is not None)
        ctrls = ro.make_controls()
        rng = np.random.default_rng(5)
        runs = []
        for E in (2e4, 3.5e4, 2.5e4):
            m.world_E.assign(np.full(m.world_count, E, np.float32))
            m.sync_materials_from_device()
            s0 = m.state(requires_grad=True)
            v = np.zeros((m.particle_count, 3), np.float32)
            v[:, 0] = 0.3
            s0.particle_v.assign(v)
            recs = ro.forward(s0, ctrls)
            seeds = [rng.normal(size=(m.particle_count, 3)).astype(np.float32) for _ in recs]
            seeds[1] = None
            ro.zero_grad(ctrls)
            ro.backward(seeds, state0=s0)
            runs.append((np.stack([r.numpy() for r in recs]),
                         np.concatenate([m.world_E.grad.numpy(), m.world_nu.grad.numpy()]),
                         ro.initial_grad["particle_v"].numpy()))
        out[graph, every] = runs
    for (x0, g0, v0), (x1, g1, v1) in [pair for key in ((True, None), (True, 10))
                                       for pair in zip(out[False, None], out[key])]:
        np.testing.assert_allclose(x1, x0, atol=1e-5)
        assert np.all(np.isfinite(g1)) and np.abs(g0).max() > 0
        np.testing.assert_allclose(g1, g0, rtol=1e-3, atol=1e-4 * np.abs(g0).max())
        # per-particle initial-velocity gradients carry the atomics' summation order (measured: 0.8 % of the largest)
        np.testing.assert_allclose(v1, v0, rtol=1e-3, atol=2e-2 * np.abs(v0).max())


@cuda
def test_forward_frames_from_graphs_match_launches():
    """The identification's forward simulation (probes, CMA-ES) replays each frame's substeps from a CUDA graph:
    three worlds of the lifted rope, each with its own material, end where the same run launched kernel by
    kernel ends (the end-effector's velocity changes every frame, through the control's arrays)."""
    from dataclasses import replace

    from empm_gym.identification.problem import _ForwardSim
    from ..identification.scenes import rope_lift

    scene = replace(rope_lift(frames=12).scene, device="cuda:0")
    mats = [MaterialConfig(E=E, nu=0.3, density=1000.0) for E in (3e4, 5e4, 8e4)]
    out = {}
    for graph in (False, True):
        sim = _ForwardSim(scene, mats, [0.5] * 3)
        sim.graph = graph
        X, bad, _ = sim.run(12)
        assert not bad
        out[graph] = X
    assert np.ptp(out[False][:, 0, :, 2]) > 0.05  # the rope was lifted
    np.testing.assert_allclose(out[True], out[False], atol=2e-5)


@cuda
def test_chamfer_frames_on_the_gpu_matches_kd_trees():
    """The objective's Chamfer on a CUDA scene (all pairs on the GPU) equals the CPU's KD-tree value."""
    import torch

    from empm_gym.identification.losses import chamfer_frames, chamfer_numpy, pad_frames

    if not torch.cuda.is_available():
        pytest.skip("torch without CUDA: the objective keeps its KD-trees")
    rng = np.random.default_rng(0)
    pred = rng.normal(size=(9, 700, 3)) * 0.05
    obs = [rng.normal(size=(n, 3)) * 0.05 for n in rng.integers(100, 1500, 9)]
    want = [chamfer_numpy(p, o) for p, o in zip(pred, obs)]
    np.testing.assert_allclose(chamfer_frames(pred, pad_frames(obs, "cuda:0"), max_pairs=2 ** 21), want, rtol=1e-10)
    # Adam's differentiable loss: the value and the gradient of the KD-tree chamfer_distance, frame by frame
    from empm_gym.identification.losses import chamfer_distance, chamfer_frames_torch

    ref = torch.tensor(pred, requires_grad=True)
    torch.stack([chamfer_distance(ref[t], obs[t + 1]) for t in range(8)]).sum().backward()
    got = torch.tensor(pred[:8], requires_grad=True)
    val = chamfer_frames_torch(got, pad_frames(obs, "cuda:0"), first=1, max_pairs=2 ** 21)
    assert val.device == got.device and val.shape == (8,)
    val.sum().backward()
    np.testing.assert_allclose(val.detach().numpy(), [chamfer_numpy(p, o) for p, o in zip(pred, obs[1:])], rtol=1e-8)
    np.testing.assert_allclose(got.grad.numpy(), ref.grad.numpy()[:8], rtol=1e-8, atol=1e-12)


@cuda
def test_queued_rollouts_side_by_side_are_the_rollouts_one_by_one():
    """Rollouts queued on their simulations' own streams and advanced a frame each in turn (``run_together``:
    the doctor's variants, different bodies on one GPU) end where each run alone ends, and a world flagged as
    diverged is NaN from the same frame as when the check is read frame by frame."""
    from dataclasses import replace

    from empm_gym.identification.problem import _ForwardSim, run_together
    from ..identification.scenes import rope_lift

    scenes = [replace(rope_lift(frames=10).scene, device="cuda:0"),
              replace(rope_lift(E=8e4, frames=10, lift_frames=4).scene, device="cuda:0")]
    mats = [MaterialConfig(E=E, nu=0.3, density=1000.0) for E in (3e4, 6e4)]
    alone = [_ForwardSim(sc, mats, [0.5, 0.5]).run(10) for sc in scenes]
    sims = [_ForwardSim(sc, mats, [0.5, 0.5]) for sc in scenes]
    together = run_together([s.steps(10, queued=True) for s in sims])
    for (xa, bad_a, _), (xt, bad_t, _) in zip(alone, together):
        assert not bad_a and not bad_t
        np.testing.assert_allclose(xt, xa, atol=2e-5)
    flagged = []
    for queued in (False, True):  # every particle "too fast": both worlds diverge at the first frame
        s = _ForwardSim(scenes[0], mats, [0.5, 0.5])
        s.solver.config.max_speed = 1e-9
        (x, bad, _), = run_together([s.steps(10, queued=queued)])
        flagged.append((bad, np.isnan(x).all(axis=(2, 3))))
    assert flagged[0][0] == flagged[1][0] == [0, 1]
    np.testing.assert_array_equal(flagged[1][1], flagged[0][1])
    assert not flagged[1][1][0].any() and flagged[1][1][1:].all()


@cuda
def test_deterministic_forward_frames_from_graphs_are_bit_identical_and_follow_the_default():
    """``Scene(deterministic=True)`` (the doctor's ``--deterministic``): the identification's forward simulation,
    each frame replayed from CUDA graphs, sums P2G in 64-bit fixed point; three runs of three worlds of the
    lifted rope end to the bit where the first did, and where the default float sums end to their rounding."""
    from dataclasses import replace

    from empm_gym.identification.problem import _ForwardSim
    from ..identification.scenes import rope_lift

    scene = replace(rope_lift(frames=12).scene, device="cuda:0")
    mats = [MaterialConfig(E=E, nu=0.3, density=1000.0) for E in (3e4, 5e4, 8e4)]
    runs = []
    for det in (True, True, True, False):
        sim = _ForwardSim(replace(scene, deterministic=det), mats, [0.5] * 3)
        assert (sim.solver._fixed is not None) == det
        X, bad, _ = sim.run(12)
        assert not bad
        runs.append(X)
    assert np.ptp(runs[0][:, 0, :, 2]) > 0.05  # the rope was lifted
    assert np.array_equal(runs[1], runs[0]) and np.array_equal(runs[2], runs[0])
    np.testing.assert_allclose(runs[0], runs[3], atol=2e-5)
