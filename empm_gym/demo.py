"""`make demo`: the whole loop on built-in data, on the CPU in a few minutes.

1. the simulator: a dough block squeezed by two grippers and a rope lifted at one end
   (``sim_demo.png``, ``sim_demo.rrd``);
2. ``empm synth``: a synthetic 3-camera RGB-D recording of dough being squeezed, with known parameters
   (``dough_recording/``);
3. ``empm identify``: the dough's yield stress fitted from the recording, starting 3x off
   (``material.json`` and its report: loss / parameter plot, ``.rrd`` of the simulation over the points);
4. ``empm evaluate``: held-out Chamfer, tracking, mask IoU, PSNR / SSIM with plots;
5. ``empm doctor`` on a second recording whose effect is hidden: it names the effect the base model
   misses and shows the held-out gap before and after (``doctor/report.md``, ``doctor/residual_timeline.png``,
   ``doctor/heldout_gap.png``);
6. real-to-sim-to-real: a press in ``EMPM/DoughFlatten-v1`` planned with the fitted material and with a
   yield stress 5x off, both executed on the "real" dough (``real2sim2real/``).

Everything lands in ``demo_out/`` (open ``.rrd`` files with ``rerun FILE``).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from .sim import (EndEffectorConfig, GridConfig, MaterialConfig, ModelBuilder, SolverMPM, TableConfig,
                  sample_box, sample_cylinder)


@dataclass
class Scene:
    name: str
    key: str
    """Entity path in rerun (no spaces)."""
    model: object
    duration: float
    """Simulated time [s]."""
    command: Callable[[float], tuple]
    """t [s] -> (velocities [1, K, 3] m/s, grip [1, K])."""


def dough_squeeze(device="cpu") -> Scene:
    """An elastoplastic 6 cm block squeezed between two box grippers, then released."""
    dx = 0.01
    b = ModelBuilder(GridConfig(lower=(-0.12, -0.08, -0.03), upper=(0.12, 0.08, 0.12), dx=dx),
                     table=TableConfig(friction=0.6))
    w = b.add_world(MaterialConfig(E=6e4, nu=0.35, density=1100.0, yield_stress=2.5e3))
    x, vol = sample_box((-0.03, -0.03, 0.0), (0.03, 0.03, 0.06), dx, 8, jitter=0.5)
    b.add_particles(w, x, vol)
    pad = EndEffectorConfig(shape="box", half_extents=(0.01, 0.04, 0.04), friction=0.8)
    b.add_end_effector(w, pad, (-0.045, 0.0, 0.035))
    b.add_end_effector(w, pad, (0.045, 0.0, 0.035))

    def command(t):
        v = np.zeros((1, 2, 3))
        if t < 0.3:  # squeeze 2.4 cm from each side
            v[0, 0, 0], v[0, 1, 0] = 0.08, -0.08
        elif t < 0.45:  # back off
            v[0, 0, 0], v[0, 1, 0] = -0.15, 0.15
        return v, np.zeros((1, 2))

    return Scene("dough squeezed by two grippers", "dough_squeeze", b.finalize(device), 0.7, command)


def rope_lift(device="cpu") -> Scene:
    """An elastic 30 cm rope on the table lifted at one end by a closed gripper."""
    dx = 0.01
    b = ModelBuilder(GridConfig(lower=(-0.2, -0.06, -0.03), upper=(0.2, 0.06, 0.3), dx=dx),
                     table=TableConfig(friction=0.4))
    w = b.add_world(MaterialConfig(E=2e5, nu=0.3, density=1200.0))
    x, vol = sample_cylinder((-0.15, 0.0, 0.012), (0.15, 0.0, 0.012), 0.012, dx, 8, jitter=0.3)
    b.add_particles(w, x, vol)
    b.add_end_effector(w, EndEffectorConfig(shape="sphere", radius=0.018), (0.14, 0.0, 0.012))

    def command(t):
        v = np.zeros((1, 1, 3))
        if t < 0.6:
            v[0, 0] = (-0.08, 0.0, 0.3)
        return v, np.ones((1, 1))

    return Scene("rope lifted at one end", "rope_lift", b.finalize(device), 1.0, command)


def simulate(scene: Scene, frames: int = 40, progress: bool = True):
    """Run a scene; returns per-frame particle positions [frames + 1, N, 3] and end-effector positions."""
    m = scene.model
    solver = SolverMPM(m)
    a, b = m.state(), m.state()
    ctrl = m.control()
    v, g = scene.command(0.0)
    ctrl.set(velocity=v, grip=g)
    dt = 0.9 * solver.max_stable_dt(max_speed=1.0)
    frame_dt = scene.duration / frames
    sub = int(np.ceil(frame_dt / dt))
    dt = frame_dt / sub
    xs, ees = [a.particle_x.numpy().copy()], [a.ee_pos.numpy().copy()]
    t = 0.0
    for _ in tqdm(range(frames), desc=scene.name, disable=not progress, unit="frame"):
        v, g = scene.command(t)
        ctrl.set(velocity=v, grip=g)
        for _ in range(sub):
            solver.step(a, b, ctrl, dt)
            a, b = b, a
        t += frame_dt
        xs.append(a.particle_x.numpy().copy())
        ees.append(a.ee_pos.numpy().copy())
    return np.stack(xs), np.stack(ees), frame_dt


def log_rerun(path: Path, runs):
    import rerun as rr

    rec = rr.RecordingStream("empm_gym_demo")
    rec.save(str(path))
    from .viz.rerun_log import log_end_effectors

    for name, (xs, ees, frame_dt, model, key) in runs.items():
        for f in range(len(xs)):
            rec.set_time("sim_time", duration=f * frame_dt)
            z = xs[f][:, 2]
            col = np.stack([0.9 * np.ones_like(z), 0.5 + 4 * z.clip(0, 0.1), 0.2 * np.ones_like(z)], 1)
            rec.log(f"{key}/particles", rr.Points3D(xs[f], radii=model.dx * 0.3, colors=col))
            log_end_effectors(rec, f"{key}/end_effectors", model.ee_configs[0], ees[f],
                              colors=[[60, 120, 230]] * len(model.ee_configs[0]))
    rec.flush()


def ee_outline(cfg: EndEffectorConfig, pos, n: int = 200) -> np.ndarray:
    """Points on an end-effector's surface (axis-aligned orientation), for drawing [n, 3] m."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if cfg.shape == "sphere":
        return pos + cfg.radius * d
    if cfg.shape == "capsule":
        z = rng.uniform(-cfg.half_height, cfg.half_height, (n, 1))
        return pos + cfg.radius * d + np.concatenate([np.zeros((n, 2)), z], 1)
    he = np.asarray(cfg.half_extents)
    u = rng.uniform(-1, 1, (n, 3))
    axis = rng.integers(0, 3, n)
    u[np.arange(n), axis] = np.sign(u[np.arange(n), axis])
    return pos + u * he


def plot(path: Path, runs):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 4
    fig = plt.figure(figsize=(4 * cols, 3.6 * len(runs)))
    for r, (name, (xs, ees, frame_dt, model, _)) in enumerate(runs.items()):
        picks = np.linspace(0, len(xs) - 1, cols).round().astype(int)
        lo, hi = xs.reshape(-1, 3).min(0), xs.reshape(-1, 3).max(0)
        span = (hi - lo).max() / 2 + 0.02
        mid = (hi + lo) / 2
        for c, f in enumerate(picks):
            ax = fig.add_subplot(len(runs), cols, r * cols + c + 1, projection="3d")
            x = xs[f]
            ax.scatter(x[:, 0], x[:, 1], x[:, 2], s=1.5, c=x[:, 2], cmap="copper", vmin=lo[2], vmax=hi[2] + 1e-3)
            for cfg, p in zip(model.ee_configs[0], ees[f]):
                o = ee_outline(cfg, p)
                ax.scatter(o[:, 0], o[:, 1], o[:, 2], s=2, c="tab:blue", alpha=0.6)
            ax.set_xlim(mid[0] - span, mid[0] + span)
            ax.set_ylim(mid[1] - span, mid[1] + span)
            ax.set_zlim(0, 2 * span)
            ax.set_title(f"{name}\nt = {f * frame_dt:.2f} s", fontsize=9)
            ax.set_xlabel("x [m]", fontsize=7)
            ax.set_ylabel("y [m]", fontsize=7)
            ax.set_zlabel("z [m]", fontsize=7)
            ax.tick_params(labelsize=6)
            ax.view_init(elev=22, azim=-60)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_sim_demo(out: Path, *, device="cpu", frames=40, progress=True):
    out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for make in (dough_squeeze, rope_lift):
        scene = make(device)
        xs, ees, frame_dt = simulate(scene, frames, progress)
        runs[scene.name] = (xs, ees, frame_dt, scene.model, scene.key)
    log_rerun(out / "sim_demo.rrd", runs)
    plot(out / "sim_demo.png", runs)
    return runs


def run_transfer_demo(out: Path, recording: Path, material: Path, *, device: str = "cpu", seeds=(0,),
                      samples: int = 8, iterations: int = 2) -> dict:
    """Real-to-sim-to-real (:func:`empm_gym.planning.transfer.run_real2sim2real`): CEM plans a press in
    ``EMPM/DoughFlatten-v1`` with the fitted material and with its yield stress 5x too high; both plans
    run open loop on the "real" dough (the recording's ground-truth material, which only this judge
    reads). Writes ``real2sim2real/{summary.json, transfer.png, strip.png}``.

    The default budget suits one CPU core (about 2 minutes). Measured on this 2-core machine
    (2026-11-23, target 0): the fitted plan ends 3.2 mm from the target, as its model predicted (to
    0.03 mm); the 5x plan ends at 3.3 mm where its model predicted 4.5. A larger budget on a GPU is in
    benchmarks/RESULTS.md (``examples/real2sim2real.py``).
    """
    import json

    from .planning.transfer import run_real2sim2real

    gt = json.loads((recording / "ground_truth.json").read_text())
    real = {**gt["material"], "friction": gt["table_friction"]}
    return run_real2sim2real(out / "real2sim2real", real, material, factors=(5.0,), seeds=seeds, samples=samples,
                             iterations=iterations, env_kwargs={"device": device})


def run_loop_demo(out: Path, *, device: str = "cpu", frames: int = 45, iters: int = 5) -> dict:
    """Synthesise a dough recording, identify its yield stress, evaluate, diagnose a second recording with a
    hidden effect, and plan with the fitted material (and a wrong one) to execute on the real dough.

    The recording is the synthesiser's default dough (E 2e4 Pa, density 1200 kg/m^3, yield stress 2000
    Pa); identification knows E and the density (``--init`` fixes the parameters it does not fit) and
    starts the yield stress 3x off. CMA-ES with 4 worlds per generation: on one CPU core each generation
    is one batched simulation of the 31 fitted frames.
    """

    from .cli import main as empm

    rec = out / "dough_recording"
    truth_ys, E, density = 2000.0, 2.0e4, 1200.0
    steps = [
        ("synthesise a 3-camera dough recording",
         ["synth", str(rec), "--object", "dough", "--frames", str(frames), "--width", "424", "--height", "240",
          "--E", str(E), "--density", str(density), "--yield-stress", str(truth_ys), "--device", device,
          "--overwrite"]),
        ("identify the yield stress (start 3x off)",
         ["identify", str(rec), "--out", str(out / "material.json"), "--params", "yield_stress", "--init",
          f"E={E},density={density},yield_stress={3 * truth_ys}", "--method", "cmaes", "--popsize", "4",
          "--iters", str(iters), "--device", device]),
        ("evaluate on held-out frames",
         ["evaluate", str(rec), "--material", str(out / "material.json"), "--out-dir", str(out / "evaluation"),
          "--device", device]),
    ]
    for what, argv in steps:
        t0 = time.time()
        print(f"== {what}: empm {' '.join(argv)}", flush=True)
        rc = empm(argv)
        if rc:
            raise SystemExit(f"demo step failed ({what}): exit code {rc}")
        print(f"   done in {time.time() - t0:.1f} s", flush=True)
    from .sim.material_file import read_material

    fitted = read_material(out / "material.json").material
    print(f"   yield stress: true {truth_ys:.0f} Pa, start {3 * truth_ys:.0f} Pa, fitted {fitted.yield_stress:.0f} Pa")
    doctor = run_doctor_demo(out, device=device)
    print("== real-to-sim-to-real: plan a press in EMPM/DoughFlatten-v1 with the fitted material and with a "
          "yield stress 5x off, execute both on the real dough", flush=True)
    transfer = run_transfer_demo(out, rec, out / "material.json", device=device)
    for label, s in transfer["summary"].items():
        print(f"   planned with {label}: {1000 * s['mean_chamfer_real_m']:.2f} mm from the target on the real dough, "
              f"{s['successes']} / {s['episodes']} below the threshold; its model predicted "
              f"{1000 * s['mean_chamfer_predicted_m']:.2f} mm")
    return {"material": fitted.to_dict(), "real2sim2real": transfer["summary"], "doctor": doctor}


def run_doctor_demo(out: Path, *, device: str = "cpu", effect: str = "gripper_slip",
                    script: str = "squeeze-lift") -> dict:
    """A recording with a hidden effect goes through ``empm doctor``, which names it.

    The recording hides ``effect`` (the synthesiser writes it only into ``ground_truth.json``, which the
    demo moves aside before the doctor runs); the doctor fits the base model, tries every effect of the
    catalogue and writes its report, whose first figure shows the held-out gap before and after.
    Reduced settings for one CPU core: 24 frames at 320 x 180, a 1.25 cm grid, short CMA-ES runs.
    """
    import json

    from .cli import main as empm

    rec = out / "hidden_effect_recording"
    steps = [
        (f"synthesise a dough recording with a hidden effect (script {script})",
         ["synth", str(rec), "--object", "dough", "--script", script, "--effect", effect, "--frames", "24",
          "--width", "320", "--height", "180", "--seed", "3", "--device", device, "--overwrite", "--quiet"]),
        ("diagnose it: empm doctor",
         ["doctor", str(rec), "--out", str(out / "doctor"), "--iters", "4", "--popsize", "5", "--dx", "0.0125",
          "--particles-per-cell", "4", "--variant-iters", "2", "--device", device]),
    ]
    for what, argv in steps:
        t0 = time.time()
        print(f"== {what}: empm {' '.join(argv)}", flush=True)
        if argv[0] == "doctor":  # the doctor must not see the answer
            (rec / "ground_truth.json").replace(out / "hidden_effect_ground_truth.json")
        rc = empm(argv)
        if rc:
            raise SystemExit(f"demo step failed ({what}): exit code {rc}")
        print(f"   done in {time.time() - t0:.1f} s", flush=True)
    res = json.loads((out / "doctor" / "doctor.json").read_text())
    hidden = json.loads((out / "hidden_effect_ground_truth.json").read_text())["effects"]
    print(f"   hidden effect: {hidden[0]['name'] if hidden else 'none'}; the doctor says: {res['effect']} "
          f"(confidence {res['confidence']:.2f}); report in {out / 'doctor' / 'report.md'}, the held-out gap "
          f"before and after in {out / 'doctor' / 'residual_timeline.png'} and {out / 'doctor' / 'heldout_gap.png'}")
    from .identification.doctor.report import gap_summary

    if gap_summary(res.get("gap")):
        print(f"   {gap_summary(res['gap'])}", flush=True)
    from .identification.uncertainty import MARGINAL_CELLS_ACROSS

    grid = res.get("grid") or {}
    if grid.get("cells_across", MARGINAL_CELLS_ACROSS) < MARGINAL_CELLS_ACROSS:  # the doctor's note on its grid
        print(f"   (the demo's {100 * grid['dx_m']:g} cm grid keeps the doctor within minutes on one CPU core; it "
              f"puts {grid['cells_across']:.1f} cells across the body, hence the doctor's note on the grid and the "
              f"--dx it gives for a GPU)", flush=True)
    return {"hidden": hidden, "verdict": res["effect"], "confidence": res["confidence"]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("demo_out"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--frames", type=int, default=40, help="frames of the simulator demo")
    p.add_argument("--sim-only", action="store_true", help="only the simulator demo (step 1)")
    args = p.parse_args(argv)
    t0 = time.time()
    print("== simulator: dough squeezed by two grippers, rope lifted at one end", flush=True)
    run_sim_demo(args.out, device=args.device, frames=args.frames)
    print(f"   wrote {args.out}/sim_demo.png and {args.out}/sim_demo.rrd ({time.time() - t0:.1f} s)", flush=True)
    if not args.sim_only:
        run_loop_demo(args.out, device=args.device)
    print(f"demo finished in {time.time() - t0:.0f} s; results in {args.out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
