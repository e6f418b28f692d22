"""MPM against the spring-mass model family (PhysTwin-style) on the same recordings: held-out metrics and fit time.

    python benchmarks/bench_springmass.py REC_DIR [REC_DIR ...] --device cuda:0      # your recordings
    python benchmarks/bench_springmass.py --synth rope,dough --device cuda:0           # makes `empm synth` ones
    python benchmarks/bench_springmass.py --small                                     # CPU smoke run, minutes

Each recording is loaded once (:func:`empm_gym.identification.data.load_recording`), then both families are
fitted on its first ``--train-fraction`` of frames with Adam through the tape, from the same start
(``--start-E``: the MPM's E and the spring-mass stiffness, both in Pa; spring-mass damping ``--start-damping``
Pa s), for ``--iters`` steps each:

- MPM: :func:`empm_gym.identification.offline.identify` of ``--mpm-params`` (default E);
- spring-mass: :func:`empm_gym.identification.springmass.identify_spring_mass` of stiffness and damping.

Both are scored on the held-out frames by the same code (:func:`empm_gym.identification.evaluate.evaluate`):
Chamfer (m), tracking error (m), mask IoU, PSNR (dB), SSIM; fit time is the optimisation's wall time alone.
Prints a table and writes ``results.json`` under ``--out-dir``. ``ground_truth.json`` is never read.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

METRICS = ("chamfer", "track", "iou", "psnr", "ssim")


def synth(obj: str, out: Path, args) -> Path:
    """An ``empm synth`` recording of ``obj`` (rope: elastic; dough: elastoplastic) in ``out`` (reused if present)."""
    rec = out / f"synth_{obj}"
    if (rec / "metadata.json").is_file():
        return rec
    cmd = [sys.executable, "-m", "empm_gym.cli", "synth", str(rec), "--object", obj, "--frames", str(args.frames),
           "--width", str(args.width), "--height", str(args.height), "--cameras", "3", "--overwrite", "--quiet"]
    if args.device:
        cmd += ["--device", args.device]
    subprocess.run(cmd, check=True)
    return rec


def fit_both(rec: Path, args) -> list:
    from empm_gym.identification.data import load_recording
    from empm_gym.identification.evaluate import evaluate, held_out_frames
    from empm_gym.identification.offline import identify
    from empm_gym.identification.springmass import evaluate_spring_mass, identify_spring_mass
    from empm_gym.sim import MaterialConfig

    t0 = time.perf_counter()
    scene, obs, views = load_recording(rec, dx=args.dx, material=MaterialConfig(E=args.start_E, nu=0.3,
                                                                                density=args.density),
                                       device=args.device, progress=not args.quiet)
    t_load = time.perf_counter() - t0
    T = obs.num_frames
    F = max(2, int(round(args.train_fraction * T)))
    frames = held_out_frames(T, args.train_fraction)
    rows = []
    out_dir = Path(args.out_dir) / rec.name

    mpm = identify(obs, scene, params=tuple(args.mpm_params.split(",")), iters=args.iters, frames=F,
                   progress=not args.quiet)
    mpm.save(out_dir / "mpm.json")
    ev = evaluate(scene, mpm.material, mpm.friction, obs, views, eval_frames=frames, downsample=args.downsample,
                  progress=False)
    rows.append({"recording": rec.name, "model": "mpm", "params": mpm.params, "fit_s": mpm.wall_time_s,
                 "particles": len(scene.particles), **{k: ev["summary"].get(k, float("nan")) for k in METRICS}})

    sm = identify_spring_mass(obs, scene, init={"stiffness": args.start_E, "damping": args.start_damping},
                              iters=args.iters, frames=F, progress=not args.quiet)
    sm.save(out_dir / "spring_mass.json")
    ev = evaluate_spring_mass(scene, sm.config, obs, views, eval_frames=frames, downsample=args.downsample,
                              progress=False)
    rows.append({"recording": rec.name, "model": "spring-mass", "params": sm.params, "fit_s": sm.wall_time_s,
                 "particles": sm.extra["particles"], **{k: ev["summary"].get(k, float("nan")) for k in METRICS}})
    for r in rows:
        r.update(load_s=t_load, frames=T, frames_fitted=F, iters=args.iters, device=str(args.device or "default"))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recordings", nargs="*", help="recording directories")
    p.add_argument("--synth", default=None, help="also make and use `empm synth` recordings of these objects "
                   "(comma-separated: rope,dough)")
    p.add_argument("--small", action="store_true", help="CPU smoke run: --synth rope, 16 frames at 212x120, "
                   "dx 0.02 m, 3 iterations")
    p.add_argument("--device", default=None, help='Warp device ("cpu", "cuda:0")')
    p.add_argument("--frames", type=int, default=60, help="frames of synthesised recordings")
    p.add_argument("--width", type=int, default=848)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--dx", type=float, default=0.01, help="MPM grid cell (m); the spring spacing is dx / 2")
    p.add_argument("--iters", type=int, default=30, help="Adam steps per fit")
    p.add_argument("--mpm-params", default="E", help="MPM parameters fitted (comma-separated)")
    p.add_argument("--start-E", type=float, default=1.0e5, help="start of E and of the spring stiffness (Pa)")
    p.add_argument("--start-damping", type=float, default=1.0, help="start of the spring damping (Pa s)")
    p.add_argument("--density", type=float, default=1000.0, help="assumed density (kg/m^3)")
    p.add_argument("--train-fraction", type=float, default=0.7)
    p.add_argument("--downsample", type=int, default=2, help="image downsampling for IoU / PSNR / SSIM")
    p.add_argument("--out-dir", default="bench_springmass_out")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    if args.small:
        args.synth = args.synth or "rope"
        args.frames, args.width, args.height, args.dx, args.iters = 16, 212, 120, 0.02, 3
        args.downsample = 1
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    recs = [Path(r) for r in args.recordings]
    for obj in filter(None, (args.synth or "").split(",")):
        recs.append(synth(obj.strip(), out, args))
    if not recs:
        p.error("give recording directories, --synth OBJECTS or --small")
    rows = []
    for rec in recs:
        rows += fit_both(rec, args)
    (out / "results.json").write_text(json.dumps(rows, indent=2, default=float))
    head = f"{'recording':18s} {'model':12s} {'chamfer m':>10s} {'track m':>9s} {'IoU':>6s} {'PSNR dB':>8s} " \
           f"{'SSIM':>6s} {'fit s':>7s} {'particles':>9s}  params"
    print(head)
    print("-" * len(head))
    for r in rows:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in r["params"].items())
        print(f"{r['recording']:18s} {r['model']:12s} {r['chamfer']:10.4f} {r['track']:9.4f} {r['iou']:6.3f} "
              f"{r['psnr']:8.2f} {r['ssim']:6.3f} {r['fit_s']:7.1f} {r['particles']:9d}  {ps}")
    print(f"wrote {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
