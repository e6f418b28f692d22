"""Wall time and parameter error of offline identification on synthetic recordings (``empm synth``).

    python benchmarks/bench_identify.py                          # CPU, 3 cameras, 60 frames (slow on CPU)
    python benchmarks/bench_identify.py --device cuda:0 --methods adam,cmaes
    python benchmarks/bench_identify.py --frames 12 --width 212 --height 120 --dx 0.02 --iters 3   # smoke test
    python benchmarks/bench_identify.py --cameras 1,2,3 --objects rope     # intervals against the camera count
    python benchmarks/bench_identify.py --objects rope --truth-body        # on the synthesiser's own body

For each object (rope: elastic, E identified; dough: elastoplastic, yield stress identified with E known)
a recording is synthesised with known parameters, loaded through the perception layer (fusion, interior
fill, controls, lifted tracks) and fitted on its first ``--train-fraction`` of frames from a start
``--start-factor`` times off the truth. The harness reads ``ground_truth.json`` only to choose the known
parameters, the start and to score the result; identification never sees it. Prints a table (wall time
of the fit alone, parameter error, final loss, the 95 % interval of :func:`assess_fit` (its width, whether
it covers the truth, whether the parameter is reported determined, the seconds it took), held-out Chamfer /
IoU) and writes ``results.json``.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np


OBJECTS = {
    "rope": {"params": ("E",)},
    "dough": {"params": ("yield_stress",)},
    # the dough squeezed well below its yield stress: its E is what the squeeze and release show
    "dough-elastic": {"params": ("E",), "synth": {"object": "dough", "yield_stress": 3.0e4}},
}


def load_problem(rec, args):
    """(scene, observations, views, ground truth, load seconds, bodies) of a synthetic recording; ``bodies`` are
    what :func:`assess_fit` needs for the body's shape: ``{"other_bodies", "body_note"}`` (the frame-0 body
    rebuilt without each camera in turn, as ``empm identify`` does)."""
    from empm_gym.identification.data import load_recording, view_jackknife_bodies
    from empm_gym.sim import MaterialConfig

    gt = json.loads((rec / "ground_truth.json").read_text())
    m = gt["material"]
    known = MaterialConfig(E=m["E"], nu=m["nu"], density=m["density"], yield_stress=m["yield_stress"])
    t0 = time.perf_counter()
    info = {}
    scene, obs, views = load_recording(rec, dx=args.dx, particles_per_cell=args.particles_per_cell, material=known,
                                       table_friction=gt["table_friction"], device=args.device,
                                       progress=not args.quiet, info=info)
    t_load = time.perf_counter() - t0
    if args.truth_body:
        scene = truth_body_scene(rec, scene)
    bodies = {"other_bodies": view_jackknife_bodies(rec, scene, particles_per_cell=args.particles_per_cell,
                                                         symmetry=info.get("symmetry")),
              "body_note": info.get("body_completion")}
    return scene, obs, views, gt, t_load, bodies


def truth_body_scene(rec, scene):
    """``scene`` with its frame-0 body replaced by the synthesiser's own particles (``ground_truth_particles.npz``,
    benchmark side only): a fit on it has no share of the body's reconstruction in its error, so the difference
    between a fit on the rebuilt body and one on this tells how much of the error the body carries."""
    from dataclasses import replace

    from empm_gym.identification.data import attach_grippers

    path = Path(rec) / "ground_truth_particles.npz"
    if not path.exists():
        raise SystemExit(f"--truth-body: {path} is missing (empm synth writes it for recordings without an effect, "
                         f"or with --debug-particles)")
    gt = np.load(path)
    x0 = np.ascontiguousarray(gt["positions"][0], dtype=np.float64)
    vol = np.ascontiguousarray(gt["volumes"], dtype=np.float64)
    grown, _ = attach_grippers(scene.ee_configs, scene.ee_positions, scene.ee_grip, x0, scene.dx)
    return replace(scene, particles=x0, volumes=vol, ee_configs=grown)


def run_one(obj, method, args, problem, cameras):
    from empm_gym.identification.evaluate import evaluate, held_out_frames
    from empm_gym.identification.offline import identify
    from empm_gym.identification.uncertainty import assess_fit

    scene, obs, views, gt, t_load, bodies = problem
    if args.device:
        for sc in [scene] + [b for _, b in bodies["other_bodies"] if b is not None]:
            sc.device = args.device
    m = gt["material"]
    params = tuple(args.params.split(",")) if args.params else OBJECTS[obj]["params"]
    init = {p: (m[p] if p != "friction" else gt["table_friction"]) * args.start_factor for p in params}
    F = max(2, int(round(args.train_fraction * obs.num_frames)))
    kw = dict(params=params, method=method, init=init, iters=args.iters, frames=F, progress=not args.quiet,
              popsize=args.popsize)
    if args.lr:
        kw["lr"] = args.lr
    res = identify(obs, scene, **kw)
    t0 = time.perf_counter()
    res.extra.update(assess_fit(res, scene, obs, **bodies))
    t_assess = time.perf_counter() - t0
    blind = assess_fit(res, scene, obs)["uncertainty"]  # without the shape's share, for comparison
    out_dir = Path(args.out_dir) / f"{obj}_c{cameras}_{method}"
    res.extra["dx"] = scene.dx
    res.save(out_dir / "material.json")
    nan = {"summary": {"chamfer": float("nan"), "iou": float("nan")}}
    ev = nan if views is None else evaluate(scene, res.material, res.friction, obs, views,
                                            eval_frames=held_out_frames(obs.num_frames, args.train_fraction),
                                            downsample=4, progress=False)
    rows = []
    for p in params:
        true = m[p] if p != "friction" else gt["table_friction"]
        u = res.extra["uncertainty"][p]
        lo, hi = u["interval"]
        blo, bhi = blind[p]["interval"]
        rows.append({"object": obj, "cameras": cameras, "method": method, "param": p, "true": true, "init": init[p],
                     "interval": [lo, hi], "width_pct": 100.0 * (hi - lo) / true, "covered": bool(lo <= true <= hi),
                     "interval_shape_blind": [blo, bhi], "covered_shape_blind": bool(blo <= true <= bhi),
                     "body_minima": res.extra["identifiability"].get("body_minima"),
                     "determined": bool(u["determined"]), "assess_s": t_assess,
                     "warnings": res.extra["identifiability"]["warnings"],
                     "fitted": res.params[p], "error_pct": 100.0 * (res.params[p] / true - 1.0),
                     "fit_wall_s": res.wall_time_s, "load_s": t_load, "iters": len(res.loss_history),
                     "particles": len(scene.particles), "dx": scene.dx, "frames_fitted": F, "loss": res.loss,
                     "heldout_chamfer_m": ev["summary"].get("chamfer"), "heldout_iou": ev["summary"].get("iou"),
                     "device": str(args.device or "default")})
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument("--device", default=None, help='Warp device for synthesis and identification ("cpu", "cuda:0")')
    p.add_argument("--objects", default="rope,dough", help="comma-separated: " + ",".join(OBJECTS))
    p.add_argument("--methods", default="adam", help="comma-separated: adam,cmaes")
    p.add_argument("--params", default=None, help="override the identified parameters, e.g. E,yield_stress")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--cameras", default="3", help="comma-separated camera counts, e.g. 1,2,3")
    p.add_argument("--width", type=int, default=848)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--dx", type=float, default=0.01, help="identification grid cell (m)")
    p.add_argument("--synth-dx", type=float, default=0.01,
                   help="the synthesiser's grid cell (m): the truth's own discretisation (a 1 cm rope is 2.4 cells thick)")
    p.add_argument("--truth-body", action="store_true",
                   help="fit on the synthesiser's own frame-0 particles instead of the body rebuilt from the views "
                        "(benchmark side: separates the body's share of the error from the fit's)")
    p.add_argument("--particles-per-cell", type=float, default=27, help="frame-0 fill (default 27, as identify)")
    p.add_argument("--iters", type=int, default=20, help="Adam steps / CMA-ES generations")
    p.add_argument("--lr", type=float, default=None, help="Adam step in log space (default: identify's)")
    p.add_argument("--popsize", type=int, default=8)
    p.add_argument("--start-factor", type=float, default=3.0, help="start = truth x this factor")
    p.add_argument("--train-fraction", type=float, default=0.7)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out-dir", default="bench_identify_out")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--save-problems", default=None,
                   help="synthesise and load (fusion needs open3d), pickle each problem into this folder, stop")
    p.add_argument("--problems", default=None,
                   help="fit pickled problems from this folder (a machine without open3d); no held-out images")
    args = p.parse_args(argv)

    from empm_gym.perception.synth import synthesize

    rows = []
    for obj in args.objects.split(","):
        if obj not in OBJECTS:
            print(f"unknown object {obj!r}; choose from {sorted(OBJECTS)}", file=sys.stderr)
            return 2
        for C in (int(c) for c in str(args.cameras).split(",")):
            key = f"{obj}_c{C}"
            if args.problems:
                with open(Path(args.problems) / f"{key}.pkl", "rb") as f:
                    scene, obs, gt, t_load, bodies = pickle.load(f)
                problem = (scene, obs, None, gt, t_load, bodies)
            else:
                t0 = time.perf_counter()
                spec = OBJECTS[obj].get("synth", {"object": obj})
                rec = synthesize(Path(args.out_dir) / f"rec_{key}", seed=args.seed, frames=args.frames, **spec,
                                 dx=args.synth_dx,
                                 cameras=C, width=args.width, height=args.height, overwrite=True,
                                 progress=not args.quiet, device=args.device or "cpu")
                print(f"synthesised {obj}: {args.frames} frames x {C} cameras in "
                      f"{time.perf_counter() - t0:.1f} s", flush=True)
                problem = load_problem(rec, args)
                if args.save_problems:
                    Path(args.save_problems).mkdir(parents=True, exist_ok=True)
                    scene, obs, _, gt, t_load, bodies = problem
                    with open(Path(args.save_problems) / f"{key}.pkl", "wb") as f:
                        pickle.dump((scene, obs, gt, t_load, bodies), f)
                    print(f"saved the {key} problem to {args.save_problems}")
                    continue
            for method in args.methods.split(","):
                rows.extend(run_one(obj, method, args, problem, C))
    if args.save_problems:
        return 0
    hdr = f"{'object':6s} {'cams':>4s} {'method':6s} {'param':12s} {'true':>10s} {'init':>10s} {'fitted':>10s} " \
          f"{'err %':>7s} {'95 % interval':>21s} {'width %':>7s} {'covers':>6s} {'shape-blind interval':>21s} " \
          f"{'covers':>6s} {'determ.':>7s} {'fit s':>7s} " \
          f"{'int. s':>6s} {'iters':>5s} {'N':>6s} {'dx mm':>5s} {'loss':>9s} {'CD held':>8s} {'IoU held':>8s}"
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        iv = f"[{r['interval'][0]:.3g}, {r['interval'][1]:.3g}]"
        bv = f"[{r['interval_shape_blind'][0]:.3g}, {r['interval_shape_blind'][1]:.3g}]"
        print(f"{r['object']:6s} {r['cameras']:4d} {r['method']:6s} {r['param']:12s} {r['true']:10.4g} {r['init']:10.4g} "
              f"{r['fitted']:10.4g} {r['error_pct']:7.2f} {iv:>21s} {r['width_pct']:7.1f} {'yes' if r['covered'] else 'no':>6s} "
              f"{bv:>21s} {'yes' if r['covered_shape_blind'] else 'no':>6s} {'yes' if r['determined'] else 'no':>7s} {r['fit_wall_s']:7.1f} {r['assess_s']:6.1f} {r['iters']:5d} "
              f"{r['particles']:6d} {1e3 * r['dx']:5.2f} {r['loss']:9.3g} {r['heldout_chamfer_m']:8.4f} {r['heldout_iou']:8.3f}")
    for r in rows:
        if r.get("body_minima"):
            print(f"  {r['object']} {r['cameras']} cameras: minimum per body: "
                  + ", ".join(f"{k} {'none' if v is None else f'{v:.4g}'}" for k, v in r["body_minima"].items()))
        for w in r["warnings"]:
            print(f"  {r['object']} {r['cameras']} cameras: {w}")
    out = Path(args.out_dir) / "results.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": vars(args), "rows": rows}, indent=2, default=float))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
