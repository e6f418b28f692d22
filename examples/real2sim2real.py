"""Real-to-sim-to-real: identify a dough's material from a recording, plan with it, execute on the "real" dough.

An ``empm synth`` recording of a dough squeeze plays the real object (its ground-truth material is read
from ``ground_truth.json`` only to build the "real" environment, never by identification):

1. ``empm identify`` fits the dough's yield stress from the recording (E and density given, as a user
   who measured them would; the yield stress starts 3x off);
2. for several targets of ``EMPM/DoughFlatten-v1`` (press the lump to a target thickness), CEM plans an
   open-loop press with (a) the fitted material and (b) materials whose yield stress is off by the
   ``--wrong-factors``; every candidate is scored after lifting the tool, so spring-back counts;
3. each plan is executed on the real dough (the environment made with the ground-truth material), and
   the final Chamfer distance to the target is compared.

Writes ``summary.json`` (one row per target and model: start, predicted and real final Chamfer),
``transfer.png`` (bar chart) and ``strip.png`` (the real dough under each plan) into ``--out``.

    python examples/real2sim2real.py --device cuda:0 --seeds 0,1,2,3,4,5,6,7 --samples 64 --iterations 5
"""

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import empm_gym  # noqa: F401  (registers the ids)
from empm_gym.envs.script_args import parse_args

@dataclass
class Args:
    """Identify a dough's yield stress, plan DoughFlatten-v1 presses with it and with wrong ones, execute them."""

    recording: str = ""
    """An existing ``empm synth`` dough recording (with ground_truth.json); empty: synthesise one into --out."""
    material: str = ""
    """An existing fitted material file for the recording; empty: run ``empm identify``."""
    frames: int = 45
    """Frames of the synthesised recording."""
    width: int = 424
    """Image width [px] of the synthesised recording (height: 240 / 424 of it)."""
    fit_iters: int = 5
    """CMA-ES generations of the yield-stress fit (4 worlds each)."""
    wrong_factors: str = "5"
    """Comma-separated factors applied to the fitted yield stress to make the wrong models."""
    seeds: str = "0,1,2"
    """Comma-separated environment seeds (one target each)."""
    steps: int = 10
    """Planned control steps (0.05 s each) before the 6-step lift."""
    samples: int = 32
    """CEM samples per iteration."""
    iterations: int = 4
    """CEM iterations."""
    noise: float = 0.4
    """Initial std of the CEM actions (action units)."""
    dx: float = 0.01
    """Grid cell [m] of the environments."""
    particles_per_cell: float = 8
    """Particle density of the environments."""
    device: Optional[str] = None
    """Warp device ("cpu", "cuda:0"); None picks Warp's default."""
    out: str = "runs/real2sim2real"
    """Output directory."""


def _csv(text, cast):
    try:
        vals = [cast(x) for x in str(text).split(",") if x.strip()]
    except ValueError as exc:
        raise ValueError(f"expected a comma-separated list, got {text!r}: {exc}") from None
    if not vals:
        raise ValueError(f"expected a non-empty comma-separated list, got {text!r}")
    return vals


def _empm(argv):
    from empm_gym.cli import main as empm

    print("== empm " + " ".join(argv), flush=True)
    rc = empm(argv)
    if rc:
        raise SystemExit(f"empm {argv[0]} failed with exit code {rc}")


def synthesise_and_identify(out: Path, args) -> tuple:
    """(recording dir, fitted material file): made here unless given."""
    device = ["--device", args.device] if args.device else []
    rec = Path(args.recording) if args.recording else out / "dough_recording"
    if not args.recording:
        _empm(["synth", str(rec), "--object", "dough", "--frames", str(args.frames), "--width", str(args.width),
               "--height", str(int(round(args.width * 240 / 424))), "--overwrite", *device])
    if args.material:
        return rec, Path(args.material)
    truth = json.loads((rec / "ground_truth.json").read_text())["material"]
    # E and density as a user who measured them gives them; the yield stress starts 3x off
    mat = out / "material.json"
    _empm(["identify", str(rec), "--out", str(mat), "--params", "yield_stress", "--init",
           f"E={truth['E']},density={truth['density']},yield_stress={3 * truth['yield_stress']}",
           "--method", "cmaes", "--popsize", "4", "--iters", str(args.fit_iters), "--no-rrd", *device])
    return rec, mat


def main(argv=None):
    args = parse_args(Args, argv)
    from empm_gym.planning.transfer import run_real2sim2real

    out = Path(args.out)
    os.makedirs(out, exist_ok=True)
    seeds = _csv(args.seeds, int)
    factors = _csv(args.wrong_factors, float)
    t0 = time.time()
    rec, mat_path = synthesise_and_identify(out, args)
    t_fit = time.time() - t0
    gt = json.loads((rec / "ground_truth.json").read_text())  # the "real" dough: the judge's knowledge only
    real = {**gt["material"], "friction": gt["table_friction"]}
    kw = {"dx": args.dx, "particles_per_cell": args.particles_per_cell}
    if args.device:
        kw["device"] = args.device
    t1 = time.time()
    summary = run_real2sim2real(out, real, mat_path, factors=factors, seeds=seeds, steps=args.steps,
                                samples=args.samples, iterations=args.iterations, noise=args.noise, env_kwargs=kw)
    summary.update({"recording": str(rec), "material_file": str(mat_path), "time_identify_s": t_fit,
                    "time_plan_s": time.time() - t1})
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"\nyield stress: true {summary['real_material']['yield_stress']:.0f} Pa")
    print(f"{'model':<34} {'mean real Chamfer [mm]':>22} {'successes':>10} {'|real - predicted| [mm]':>24}")
    for label, s in summary["summary"].items():
        print(f"{label:<34} {1000 * s['mean_chamfer_real_m']:>22.2f} {s['successes']:>4} / {s['episodes']:<4} "
              f"{1000 * s['mean_prediction_error_m']:>24.2f}")
    return summary


if __name__ == "__main__":
    main()
