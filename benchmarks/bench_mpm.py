"""Throughput and memory of the MPM step: particle-steps per second, forward and forward+backward.

Prints a table. Cases: one world at growing particle counts, and batches of many small worlds.
Forward: a loop of ``SolverMPM.step`` (captured in a CUDA graph on GPUs). Forward+backward: a
``Rollout`` of ``--grad-steps`` substeps taped, then back-propagated, with and without segment
checkpointing; memory is what the rollout holds after its backward pass (CUDA mempool use on GPUs,
the rollout's array bytes on CPU).

    python benchmarks/bench_mpm.py                      # CPU, small sizes
    python benchmarks/bench_mpm.py --device cuda:0 --sizes 1e3,1e4,1e5,1e6,2e6 --batches 1024x2000,4096x2000
    python benchmarks/bench_mpm.py --effects --sizes 1e6 --batches 1024x2000 --device cuda:0   # one row per effect

``--effects`` times every case once per effect of the catalogue (``none`` first), each with a closed box
gripper pressing on the block so that the gripper-slip path runs, and prints the speed relative to ``none``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

from empm_gym.sim import (EndEffectorConfig, GridConfig, MaterialConfig, ModelBuilder, Rollout, SolverConfig,
                          SolverMPM, TableConfig, sample_box)
from empm_gym.sim.effects import EFFECTS

#: Parameter values that switch each effect on in the benchmark (typical magnitudes; the step's cost does
#: not depend on them, except that fracture's damage update runs only where the effect is on).
EFFECT_VALUES = {
    "none": {},
    "plasticity": {"yield_stress": 5e3},
    "viscosity": {"viscosity": 1.0},
    "table_friction": {"friction": 0.2},
    "gripper_slip": {"grip_friction": 2.0},
    "heterogeneous_stiffness": {"stiffness_slope_1": 0.5, "stiffness_slope_2": -0.3},
    "fracture": {"fracture_strain": 0.3, "fracture_softening": 0.05},
}
assert set(EFFECT_VALUES) == {"none", *EFFECTS}, "bench_mpm: give every registered effect a benchmark value"


def build(worlds: int, particles: int, device: str, requires_grad: bool = False, plastic: bool = False,
          effect: str = None):
    """`worlds` worlds, each a block of about `particles` particles (8 per cell) resting on a table; with
    ``effect`` (a key of EFFECT_VALUES) that effect is on and a closed box gripper presses on the block."""
    ppc = 8
    dx = 0.01
    cells = particles / ppc
    side = cells ** (1.0 / 3.0)
    n = max(int(round(side)), 2)
    h = max(int(round(cells / (n * n))), 1)
    size = np.array([n, n, h]) * dx
    margin = 4 * dx
    lower = (-size[0] / 2 - margin, -size[1] / 2 - margin, -margin)
    upper = (size[0] / 2 + margin, size[1] / 2 + margin, size[2] + 2 * margin)
    b = ModelBuilder(GridConfig(lower=lower, upper=upper, dx=dx), table=TableConfig(friction=0.5))
    x, vol = sample_box((-size[0] / 2, -size[1] / 2, 0.0), (size[0] / 2, size[1] / 2, size[2]), dx, ppc, jitter=0.5)
    mat = MaterialConfig(E=1e5, nu=0.3, density=1000.0, yield_stress=5e3 if plastic else None)
    if effect is not None:
        mat = mat.replace(**EFFECT_VALUES[effect])
    for _ in range(worlds):
        w = b.add_world(mat)
        b.add_particles(w, x, vol)
        if effect is not None:
            pad = EndEffectorConfig(shape="box", half_extents=(size[0] / 4, size[1] / 4, dx))
            b.add_end_effector(w, pad, (0.0, 0.0, size[2] + 0.5 * dx))
    return b.finalize(device, requires_grad=requires_grad)


def time_forward(model, steps: int, graph: bool, config: SolverConfig = None):
    solver = SolverMPM(model, config)
    dt = 0.5 * solver.max_stable_dt()
    a, b = model.state(), model.state()
    c = model.control()
    if model.ee_count:
        c.set(grip=np.ones((model.world_count, model.ee_count)))

    def loop(n):
        nonlocal a, b
        for _ in range(n):
            solver.step(a, b, c, dt, guards=False)
            a, b = b, a

    loop(2)  # compile / warm up
    wp.synchronize_device(model.device)
    if graph and model.device.is_cuda:
        steps += steps % 2  # an even count keeps the ping-pong buffers in place across replays
        with wp.ScopedCapture(device=model.device) as cap:
            loop(steps)
        wp.capture_launch(cap.graph)
        wp.synchronize_device(model.device)
        t0 = time.perf_counter()
        wp.capture_launch(cap.graph)
        wp.synchronize_device(model.device)
    else:
        t0 = time.perf_counter()
        loop(steps)
        wp.synchronize_device(model.device)
    elapsed = time.perf_counter() - t0
    solver.check_state(a)  # the benchmark must not time a diverged run
    return model.particle_count * steps / elapsed


def time_grad(model, steps: int, checkpoint_every):
    solver = SolverMPM(model)
    dt = 0.5 * solver.max_stable_dt()
    cuda = model.device.is_cuda
    if cuda:
        wp.synchronize_device(model.device)
        base = wp.get_mempool_used_mem_current(model.device)
    ro = Rollout(model, solver, steps=steps, dt=dt, record_every=steps, checkpoint_every=checkpoint_every)
    ctrls = ro.make_controls()
    if model.ee_count:
        for c in ctrls:
            c.set(grip=np.ones((model.world_count, model.ee_count)))
    s0 = model.state()
    seed = [None, np.ones((model.particle_count, 3), np.float32)]
    ro.forward(s0, ctrls)  # warm up (compiles adjoint kernels on backward)
    ro.backward(seed)
    wp.synchronize_device(model.device)
    t0 = time.perf_counter()
    ro.forward(s0, ctrls)
    wp.synchronize_device(model.device)
    t1 = time.perf_counter()
    ro.zero_grad(ctrls)
    ro.backward(seed)
    wp.synchronize_device(model.device)
    t2 = time.perf_counter()
    # everything the backward pass needs is allocated by now (states, grids, adjoints, checkpoints)
    peak = wp.get_mempool_used_mem_current(model.device) - base if cuda else ro.memory_bytes()
    g = model.world_E.grad.numpy()
    assert np.all(np.isfinite(g)), "non-finite gradient in benchmark"
    n = model.particle_count * steps
    return n / (t1 - t0), n / (t2 - t0), (t2 - t1) / (t1 - t0), peak / 2**20


def profile(particles: int, device: str, steps: int, plastic: bool):
    """Per-kernel GPU time of one taped rollout's forward and backward pass (CUDA activity timing)."""
    model = build(1, particles, device, requires_grad=True, plastic=plastic)
    solver = SolverMPM(model)
    ro = Rollout(model, solver, steps=steps, dt=0.5 * solver.max_stable_dt(), record_every=steps)
    ctrls = ro.make_controls()
    seed = [None, np.ones((model.particle_count, 3), np.float32)]
    ro.forward(model.state(), ctrls)
    ro.backward(seed)
    wp.synchronize_device(model.device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    ro.forward(model.state(), ctrls)
    ro.zero_grad(ctrls)
    ro.backward(seed)
    wp.synchronize_device(model.device)
    results = wp.timing_end()
    totals = {}
    for r in results:
        totals[r.name] = totals.get(r.name, 0.0) + r.elapsed
    print(f"per-kernel GPU time over {steps} substeps of {model.particle_count} particles (ms):")
    for name, ms in sorted(totals.items(), key=lambda kv: -kv[1]):
        print(f"  {ms:9.3f}  {name}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--sizes", default="1e3,1e4,1e5", help="particle counts of the single-world cases")
    p.add_argument("--batches", default="64x2000", help="WORLDSxPARTICLES batched cases, comma separated")
    p.add_argument("--steps", type=int, default=0, help="forward substeps to time (0: by size)")
    p.add_argument("--grad-steps", type=int, default=20, help="substeps of the differentiable rollout")
    p.add_argument("--grad-max", type=float, default=2e6, help="skip forward+backward above this many particles")
    p.add_argument("--plastic", action="store_true", help="von Mises dough instead of an elastic block (a second SVD)")
    p.add_argument("--profile", type=int, default=0,
                   help="CUDA only: per-kernel forward/adjoint GPU times for one world of this many particles")
    p.add_argument("--no-graph", action="store_true", help="do not capture the forward loop in a CUDA graph")
    p.add_argument("--effects", action="store_true", help="one row per effect of the catalogue (none first)")
    p.add_argument("--sort-every", type=int, default=None,
                   help="SolverConfig.sort_every of the forward column (CUDA; default: the solver's default)")
    p.add_argument("--deterministic", action="store_true",
                   help="the forward column with SolverConfig(deterministic=True) (64-bit fixed-point P2G); the "
                        "unsorted column is then left out (the process's kernels are in Warp's deterministic "
                        "mode from there on): run the default in a process of its own to compare")
    args = p.parse_args(argv)
    wp.init()
    dev = wp.get_device(args.device)
    cases = [(1, int(float(s))) for s in args.sizes.split(",") if s]
    cases += [tuple(int(v) for v in b.split("x")) for b in args.batches.split(",") if b]
    if args.profile:
        profile(args.profile, args.device, args.grad_steps, args.plastic)
        return
    if args.effects:
        effects_table(cases, args, dev)
        return
    print(f"device: {dev.name} ({dev.alias}), warp {wp.__version__}, material: "
          f"{'elastoplastic (von Mises)' if args.plastic else 'elastic (fixed corotated)'}")
    head = (f"{'worlds':>7} {'particles':>10} {'fwd p-steps/s':>14} {'unsorted':>10} "
            f"{'fwd+bwd p-steps/s':>18} {'bwd/fwd':>8} {'peak MB full':>13} {'peak MB ckpt':>13}")
    print(head)
    print("-" * len(head))
    for worlds, per_world in cases:
        model = build(worlds, per_world, args.device, plastic=args.plastic)
        total = model.particle_count
        steps = args.steps or int(np.clip(2e7 / total if dev.is_cuda else 2e6 / total, 4, 2000))
        kw = {} if args.sort_every is None else {"sort_every": args.sort_every}
        fwd = time_forward(model, steps, graph=not args.no_graph,
                           config=SolverConfig(deterministic=True, **kw) if args.deterministic
                           else SolverConfig(**kw) if kw else None)
        # the same step without the cell sort and warp sums (CUDA, sort_every=0); the plain reference step to
        # compare with is ../shared/tools/ref_mpm.py, run in the same job
        plain = time_forward(model, steps, graph=not args.no_graph, config=SolverConfig(sort_every=0)) \
            if dev.is_cuda and not args.deterministic else float("nan")
        row = f"{worlds:>7} {total:>10} {fwd:>14.3e} {plain:>10.3e}"
        if total <= args.grad_max:
            gm = build(worlds, per_world, args.device, requires_grad=True, plastic=args.plastic)
            _, fb, ratio, peak_full = time_grad(gm, args.grad_steps, None)
            _, _, _, peak_ckpt = time_grad(gm, args.grad_steps, max(args.grad_steps // 4, 1))
            row += f" {fb:>18.3e} {ratio:>8.2f} {peak_full:>13.1f} {peak_ckpt:>13.1f}"
        print(row, flush=True)


def effects_table(cases, args, dev):
    """Forward and forward+backward throughput with each effect on, relative to no effect."""
    print(f"device: {dev.name} ({dev.alias}), warp {wp.__version__}; each case with one closed box gripper")
    head = (f"{'effect':>24} {'worlds':>7} {'particles':>10} {'fwd p-steps/s':>14} {'vs none':>8} "
            f"{'fwd+bwd p-steps/s':>18} {'vs none':>8}")
    print(head)
    print("-" * len(head))
    for worlds, per_world in cases:
        ref = None
        for effect in EFFECT_VALUES:
            model = build(worlds, per_world, args.device, effect=effect)
            total = model.particle_count
            steps = args.steps or int(np.clip(2e7 / total if dev.is_cuda else 2e6 / total, 4, 2000))
            fwd = time_forward(model, steps, graph=not args.no_graph)
            fb = float("nan")
            if total <= args.grad_max:
                gm = build(worlds, per_world, args.device, requires_grad=True, effect=effect)
                _, fb, _, _ = time_grad(gm, args.grad_steps, max(args.grad_steps // 4, 1))
            ref = ref or (fwd, fb)
            print(f"{effect:>24} {worlds:>7} {total:>10} {fwd:>14.3e} {fwd / ref[0]:>8.2f} {fb:>18.3e} "
                  f"{fb / ref[1]:>8.2f}", flush=True)


if __name__ == "__main__":
    main()
