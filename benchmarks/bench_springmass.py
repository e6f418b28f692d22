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

Three stages, for fitting on a GPU machine without Open3D (which loading a recording needs) that receives
little data per call (run from the repository root):

    # 0. the recordings of issue 12: an elastic rope, an elastoplastic dough, each hidden effect of the catalogue
    #    (the latter: seed 0 of `PYTHONPATH=. python benchmarks/bench_doctor.py --make /tmp/docbench --only-make`)
    PYTHONPATH=. python -m empm_gym.cli synth /tmp/sm_dough --object dough --frames 45 --width 424 --height 240
    # 1. CPU, with Open3D: load each recording, pickle its scene and observations (no images) to DIR/<name>.pkl
    PYTHONPATH=. python benchmarks/bench_springmass.py --make-problems .smproblems /tmp/prof_rope_45_424 \
        /tmp/sm_dough /tmp/docbench/dough-press-release-0-{none,plasticity,viscosity} \
        /tmp/docbench/dough-push-slide-0-table_friction \
        /tmp/docbench/dough-squeeze-lift-0-{gripper_slip,heterogeneous_stiffness,fracture,none}
    # 2. GPU, no Open3D needed: fit both families on each pickle from the same start, simulate every frame
    #    with each fit, write OUT/<name>.npz (one at a time, as each problem finishes)
    PYTHONPATH=. python benchmarks/bench_springmass.py --problems .smproblems --fit-out $OUT --device cuda:0 \
        --iters 30
    #    split over calls with --shard 0/2, then --shard 1/2 (every N-th problem from the K-th)
    # 3. CPU: score the npz files against the recordings (views read again from each recording's stored
    #    path, scene and observations from the pickles), print a markdown table, write results.json
    PYTHONPATH=. python benchmarks/bench_springmass.py --score OUT --problems .smproblems --out-dir OUTDIR

Stage 1 takes the loading options (``--dx``, ``--start-E``, ``--density``) and stores, besides the scene and the
observations, the recording's folder name and absolute path. Stage 2 takes the fitting options (``--iters``,
``--mpm-params``, e.g. ``E,yield_stress`` for a plastic start with ``--start-yield``, ``--start-damping``,
``--train-fraction``); before the first timed fit it runs one untimed iteration of each family on two frames,
so that Warp's kernel compilation is not counted in the first fit time. Each npz holds, per family, the
positions at frame 0 and at the held-out frames (``--store-frames all``: every frame) quantised to int16 over
the stored positions' box (a step of about 15 um per metre of box; frame 0 also exactly, since the particle
colours that PSNR and SSIM use are splatted from it), the spring-mass network's particles, the
fitted parameters, loss histories, iteration counts and wall times, and the error of a family whose fit or
simulation failed (the other is kept; a problem that fails as a whole is written with its error and the run
goes on). Stage 3 finds each problem's pickle in ``--problems`` (default: the path stage 2 read it from) and
writes ``results.json`` to ``--out-dir`` (default OUT where writable, else ``bench_springmass_out``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

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
    out_dir = Path(args.out_dir or "bench_springmass_out") / rec.name

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


# --------------------------------------------------------------------------------------------------------------
# three stages: --make-problems (CPU, Open3D), --problems --fit-out (GPU), --score (CPU)

FAMILIES = ("mpm", "spring_mass")
_QMAX = 32767  # int16 codes -32767..32767; -32768 marks a non-finite coordinate


def _quantise(X: np.ndarray):
    """int16 codes, offset [3] and step (m) of positions X [..., 3] over their finite box."""
    X = np.asarray(X, np.float64)
    ok = np.isfinite(X)
    if not ok.any():
        return np.full(X.shape, -_QMAX - 1, np.int16), np.zeros(3), 1.0
    Xf = np.where(ok, X, np.nan)
    lo, hi = np.nanmin(Xf.reshape(-1, 3), 0), np.nanmax(Xf.reshape(-1, 3), 0)
    mid = 0.5 * (lo + hi)
    step = max(float((hi - lo).max()) / (2 * _QMAX), 1e-9)
    q = np.where(ok, np.round((np.where(ok, X, 0.0) - mid) / step), -_QMAX - 1)
    return q.astype(np.int16), mid, step


def _dequantise(q: np.ndarray, mid, step) -> np.ndarray:
    X = q.astype(np.float64) * step + np.asarray(mid, np.float64)
    X[q == -_QMAX - 1] = np.nan
    return X


def make_problems(recs, args) -> Path:
    """Stage 1: load each recording and pickle its scene and observations (no views) to DIR/<name>.pkl."""
    from empm_gym.identification.data import load_recording
    from empm_gym.sim import MaterialConfig

    out = Path(args.make_problems)
    out.mkdir(parents=True, exist_ok=True)
    for rec in recs:
        rec = Path(rec).resolve()
        t0 = time.perf_counter()
        scene, obs, _ = load_recording(rec, dx=args.dx, material=MaterialConfig(E=args.start_E, nu=0.3,
                                                                                 density=args.density),
                                       progress=not args.quiet)
        path = out / f"{rec.name}.pkl"
        with open(path, "wb") as f:
            pickle.dump({"scene": scene, "obs": obs, "name": rec.name, "recording": str(rec),
                         "load": {"dx": args.dx, "start_E": args.start_E, "density": args.density,
                                  "load_s": time.perf_counter() - t0}}, f, protocol=pickle.HIGHEST_PROTOCOL)
        print(f"{rec.name}: {len(scene.particles)} particles, {obs.num_frames} frames, "
              f"{sum(len(p) for p in obs.points) / obs.num_frames:.0f} points per frame -> {path} "
              f"({path.stat().st_size / 1e6:.1f} MB, {time.perf_counter() - t0:.1f} s)", flush=True)
    return out


def _fit_summary(res) -> dict:
    return {"params": dict(res.params), "init": dict(res.init), "loss": res.loss, "fit_s": res.wall_time_s,
            "iterations_done": int(res.iterations_done), "iterations_requested": int(res.iterations_requested),
            "complete": bool(res.complete), "loss_history": list(res.loss_history),
            "param_history": list(res.param_history),
            "extra": {k: v for k, v in res.extra.items() if k != "resume"}}


def _printer(name: str, family: str, every: int):
    t0 = time.perf_counter()

    def cb(it, loss, vals):
        if every > 0 and (it % every == 0):
            ps = ", ".join(f"{k}={v:.4g}" for k, v in vals.items() if v is not None)
            print(f"  {name} {family} iter {it}: loss {loss:.6g} ({ps}) {time.perf_counter() - t0:.1f} s", flush=True)
    return cb


def fit_problem(prob: dict, args, warmup: bool = False) -> dict:
    """Stage 2 on one problem: both fits from the same start, then every frame simulated with each fit.
    Returns the npz's arrays (and ``meta``, a JSON string)."""
    from empm_gym.identification.evaluate import held_out_frames
    from empm_gym.identification.offline import identify
    from empm_gym.identification.problem import simulate_frames
    from empm_gym.identification.springmass import (identify_spring_mass, simulate_frames_spring_mass,
                                                    spring_mass_scene, spring_mass_sim)

    scene = dataclasses.replace(prob["scene"], device=args.device)
    obs = prob["obs"]
    name = prob["name"]
    T = obs.num_frames if scene.num_frames is None else min(obs.num_frames, scene.num_frames)
    F = max(2, int(round(args.train_fraction * T)))
    frames = held_out_frames(T, args.train_fraction)
    iters, fit_frames = (1, 2) if warmup else (args.iters, F)
    keep = list(range(T)) if args.store_frames == "all" else [0, *frames]
    mpm_params = tuple(args.mpm_params.split(","))
    mpm_init = {"E": args.start_E}
    if "yield_stress" in mpm_params and args.start_yield is not None:
        mpm_init["yield_stress"] = args.start_yield
    meta = {"name": name, "recording": prob.get("recording"), "problem": prob.get("problem"),
            "frames": T, "frames_fitted": F, "eval_frames": frames, "stored_frames": keep,
            "train_fraction": args.train_fraction, "iters": args.iters, "device": str(args.device),
            "particles": {"mpm": int(len(scene.particles))}, "fits": {}, "errors": {}, "sim_s": {}}
    arrays = {}
    every = 0 if warmup else args.print_every
    for fam in FAMILIES:
        try:
            if fam == "mpm":
                res = identify(obs, scene, params=mpm_params, init=mpm_init, iters=iters, frames=fit_frames,
                               progress=False, callback=_printer(name, fam, every))
                if warmup:
                    continue
                t0 = time.perf_counter()
                mu = scene.table_friction if res.friction is None else float(res.friction)
                X = simulate_frames(scene, [res.material], [mu], frames=T)[:, 0]
                fitted = {"model": "mpm", **res.material.to_dict(), "friction": mu}
            else:
                res = identify_spring_mass(obs, scene, init={"stiffness": args.start_E, "damping": args.start_damping},
                                           iters=iters, frames=fit_frames, progress=False,
                                           callback=_printer(name, fam, every))
                if warmup:
                    continue
                t0 = time.perf_counter()
                sim = spring_mass_sim(scene, res.config)
                X = simulate_frames_spring_mass(scene, res.config, frames=T, sim=sim)
                sm_scene = spring_mass_scene(scene, sim)
                arrays["x0_spring_mass"] = np.asarray(sm_scene.particles, np.float64)
                arrays["vol_spring_mass"] = np.asarray(sm_scene.volumes, np.float32)
                meta["particles"]["spring_mass"] = int(len(sm_scene.particles))
                fitted = {"model": "spring-mass", "stiffness": res.config.stiffness, "damping": res.config.damping,
                          "density": scene.material.density, "friction": scene.table_friction}
            meta["sim_s"][fam] = time.perf_counter() - t0
            X = np.asarray(X)
            q, mid, step = _quantise(X[keep])
            arrays[f"frame0_{fam}"] = X[0].astype(np.float64)  # exact: the colours' splat is sensitive to ties
            arrays[f"pos_{fam}"], arrays[f"mid_{fam}"], arrays[f"step_{fam}"] = q, mid, np.float64(step)
            meta["fits"][fam] = {**_fit_summary(res), "fitted": fitted}
            print(f"  {name} {fam}: fitted {', '.join(f'{k}={v:.4g}' for k, v in res.params.items())} "
                  f"loss {res.loss:.6g} in {res.wall_time_s:.1f} s ({res.iterations_done} iterations), "
                  f"simulated {T} frames in {meta['sim_s'][fam]:.1f} s", flush=True)
        except Exception as exc:  # noqa: BLE001 - recorded, the other family and problems go on
            if warmup:
                print(f"  warm-up {fam} on {name} failed: {type(exc).__name__}: {exc}", flush=True)
                continue
            import traceback

            meta["errors"][fam] = f"{type(exc).__name__}: {exc}"
            meta.setdefault("tracebacks", {})[fam] = traceback.format_exc()[-4000:]
            print(f"  {name} {fam}: FAILED {meta['errors'][fam]}", flush=True)
    arrays["meta"] = np.array(json.dumps(meta, default=_json_default))
    return arrays


def _json_default(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    return repr(v)


def fit_problems(args) -> Path:
    """Stage 2: fit both families on every (sharded) pickle in --problems, write --fit-out/<name>.npz."""
    k, n = (int(v) for v in args.shard.split("/"))
    if not (n >= 1 and 0 <= k < n):
        raise SystemExit(f"--shard must be K/N with 0 <= K < N, got {args.shard}")
    paths = sorted(Path(args.problems).glob("*.pkl"))[k::n]
    if not paths:
        raise SystemExit(f"no *.pkl problems in {args.problems} (shard {args.shard})")
    out = Path(args.fit_out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{len(paths)} problems (shard {args.shard}) on {args.device}: {', '.join(p.stem for p in paths)}",
          flush=True)
    t_all = time.perf_counter()
    for i, path in enumerate(paths):
        t0 = time.perf_counter()
        print(f"[{i + 1}/{len(paths)}] {path.stem}", flush=True)
        try:
            with open(path, "rb") as f:
                prob = pickle.load(f)
            prob.setdefault("name", path.stem)
            prob["problem"] = str(path)
            if i == 0 and args.warmup:
                tw = time.perf_counter()
                fit_problem(prob, args, warmup=True)
                print(f"  warm-up (untimed kernels compile) {time.perf_counter() - tw:.1f} s", flush=True)
            arrays = fit_problem(prob, args)
        except Exception as exc:  # noqa: BLE001 - recorded, the next problem goes on
            import traceback

            meta = {"name": path.stem, "problem": str(path), "errors": {"problem": f"{type(exc).__name__}: {exc}"},
                    "tracebacks": {"problem": traceback.format_exc()[-4000:]}, "fits": {}}
            arrays = {"meta": np.array(json.dumps(meta, default=_json_default))}
            print(f"  {path.stem}: FAILED {meta['errors']['problem']}", flush=True)
        dst = out / f"{path.stem}.npz"
        np.savez_compressed(dst, **arrays)
        print(f"  wrote {dst} ({dst.stat().st_size / 1e6:.2f} MB) in {time.perf_counter() - t0:.1f} s; "
              f"{time.perf_counter() - t_all:.1f} s so far", flush=True)
    return out


def _load_problem(meta: dict, npz: Path, args) -> dict:
    cands = []
    if args.problems:
        cands.append(Path(args.problems) / f"{meta['name']}.pkl")
    if meta.get("problem"):
        cands += [Path(meta["problem"]), npz.parent / Path(meta["problem"])]
    for c in cands:
        if c.is_file():
            with open(c, "rb") as f:
                return pickle.load(f)
    raise FileNotFoundError(f"{npz}: problem pickle of {meta['name']} not found (tried "
                            f"{', '.join(map(str, cands)) or 'nothing'}); give --problems DIR")


def score(args) -> list:
    """Stage 3: held-out metrics of every npz in OUT, a markdown table and results.json."""
    from empm_gym.identification.data import load_views
    from empm_gym.identification.evaluate import evaluate

    src = Path(args.score)
    files = sorted(src.glob("*.npz"))
    if not files:
        raise SystemExit(f"no *.npz files in {src}")
    rows = []
    for npz in files:
        with np.load(npz) as z:
            arr = {k: z[k] for k in z.files}
        meta = json.loads(str(arr["meta"]))
        name = meta["name"]
        base = {"recording": name, "frames": meta.get("frames"), "frames_fitted": meta.get("frames_fitted"),
                "iters": meta.get("iters"), "device": meta.get("device")}
        if "problem" in meta.get("errors", {}):
            for fam in FAMILIES:
                rows.append({**base, "model": fam.replace("_", "-"), "error": meta["errors"]["problem"],
                             **{k: float("nan") for k in METRICS}})
            print(f"{name}: failed on the device: {meta['errors']['problem']}", flush=True)
            continue
        prob = _load_problem(meta, npz, args)
        scene, obs = prob["scene"], prob["obs"]
        rec = meta.get("recording") or prob.get("recording")
        views = load_views(rec, frames=meta["frames"])
        frames, keep = meta["eval_frames"], meta["stored_frames"]
        for fam in FAMILIES:
            row = {**base, "model": fam.replace("_", "-")}
            fit = meta["fits"].get(fam)
            if fit is None:
                row.update(error=meta["errors"].get(fam, "missing"), **{k: float("nan") for k in METRICS})
                rows.append(row)
                print(f"{name} {fam}: {row['error']}", flush=True)
                continue
            Xs = _dequantise(arr[f"pos_{fam}"], arr[f"mid_{fam}"], float(arr[f"step_{fam}"]))
            X = np.full((max(keep) + 1,) + Xs.shape[1:], np.nan)
            X[keep] = Xs
            sc = scene
            if fam == "spring_mass":
                sc = dataclasses.replace(scene, particles=arr["x0_spring_mass"],
                                         volumes=arr["vol_spring_mass"].astype(np.float64))
            if f"frame0_{fam}" in arr:  # frame 0 as simulated, exactly (the colours' splat is sensitive to ties)
                X[0] = arr[f"frame0_{fam}"]
            t0 = time.perf_counter()
            fitted = fit["fitted"]
            ev = evaluate(sc, fitted, fitted.get("friction"), obs, views, eval_frames=frames,
                          downsample=args.downsample, progress=False, positions=X)
            row.update(params=fit["params"], fit_s=fit["fit_s"], iterations=fit["iterations_done"],
                       particles=len(sc.particles), loss=fit["loss"], fitted=fitted,
                       **{k: ev["summary"].get(k, float("nan")) for k in METRICS})
            rows.append(row)
            print(f"{name} {fam}: scored in {time.perf_counter() - t0:.1f} s", flush=True)
    out = Path(args.out_dir) if args.out_dir else (src if os.access(src, os.W_OK) else Path("bench_springmass_out"))
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(rows, indent=2, default=_json_default))
    print()
    print(markdown_table(rows))
    print(f"\nwrote {out / 'results.json'}")
    return rows


def _fmt(v, f):
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, f)


def markdown_table(rows) -> str:
    """One row per recording x model family: held-out metrics, fit time, iterations and fitted parameters."""
    lines = ["| recording | model | Chamfer (m) | track (m) | IoU | PSNR (dB) | SSIM | fit (s) | iters | particles "
             "| fitted |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        if r.get("error"):
            fitted = "failed: " + r["error"].replace("|", "/").replace("\n", " ")[:120]
        else:
            fitted = ", ".join(f"{k}={v:.4g}" for k, v in r.get("params", {}).items())
        lines.append(f"| {r['recording']} | {r['model']} | {_fmt(r['chamfer'], '.4f')} | {_fmt(r['track'], '.4f')} "
                     f"| {_fmt(r['iou'], '.3f')} | {_fmt(r['psnr'], '.2f')} | {_fmt(r['ssim'], '.3f')} "
                     f"| {_fmt(r.get('fit_s'), '.1f')} | {r.get('iterations', '')} | {r.get('particles', '')} "
                     f"| {fitted} |")
    return "\n".join(lines)


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
    p.add_argument("--out-dir", default=None, help="results.json (and --synth recordings) go here (default "
                   "bench_springmass_out; with --score, OUT where writable)")
    p.add_argument("--quiet", action="store_true")
    g = p.add_argument_group("stages (see above)")
    g.add_argument("--make-problems", metavar="DIR", default=None,
                   help="stage 1: load the recordings, pickle scene and observations to DIR/<name>.pkl, stop")
    g.add_argument("--problems", metavar="DIR", default=None,
                   help="stage 2: the pickled problems to fit (with --fit-out); stage 3: where their pickles are")
    g.add_argument("--fit-out", metavar="OUT", default=None,
                   help="stage 2: fit both families on each problem, write OUT/<name>.npz")
    g.add_argument("--score", metavar="OUT", default=None,
                   help="stage 3: score the npz files in OUT, print a markdown table, write results.json")
    g.add_argument("--shard", default="0/1", help="stage 2: K/N fits every N-th problem from the K-th")
    g.add_argument("--store-frames", choices=("heldout", "all"), default="heldout",
                   help="stage 2: positions stored: frame 0 and the held-out frames (what scoring reads), or all")
    g.add_argument("--start-yield", type=float, default=None,
                   help="stage 2: start of the MPM yield stress (Pa) when --mpm-params has yield_stress "
                        "(default the effect registry's start)")
    g.add_argument("--print-every", type=int, default=5, help="stage 2: print the loss every this many iterations")
    g.add_argument("--no-warmup", dest="warmup", action="store_false",
                   help="stage 2: no untimed one-iteration warm-up of each family before the first fit")
    args = p.parse_args(argv)
    if args.score:
        score(args)
        return 0
    if args.fit_out:
        if not args.problems:
            p.error("--fit-out needs --problems DIR")
        fit_problems(args)
        return 0
    if args.problems:
        p.error("--problems needs --fit-out OUT (stage 2) or --score OUT (stage 3)")
    if args.small:
        args.synth = args.synth or "rope"
        args.frames, args.width, args.height, args.dx, args.iters = 16, 212, 120, 0.02, 3
        args.downsample = 1
    out = Path(args.out_dir or "bench_springmass_out")
    out.mkdir(parents=True, exist_ok=True)
    recs = [Path(r) for r in args.recordings]
    for obj in filter(None, (args.synth or "").split(",")):
        recs.append(synth(obj.strip(), out, args))
    if not recs:
        p.error("give recording directories, --synth OBJECTS or --small")
    if args.make_problems:
        make_problems(recs, args)
        return 0
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
