"""Simulate given materials on one of ``bench_doctor.py``'s problems, with a diagnosis's clock, and print their
fitting and held-out losses as the doctor scores them (per held-out frame: Chamfer and median tracking error, mm).

What a row of ``doctor.json`` says a fit scored can be checked here: the same body (the doctor's, or one of the
bodies rebuilt without a camera), the same substeps per frame (the clock: the corners of every candidate's box for
an E window), the same score. Session 36 used it to find that a stiffness field's held-out score on a rope pulled
apart changes fourfold between 547 and 627 substeps a frame (benchmarks/RESULTS.md).

    python benchmarks/resimulate.py PROBLEM.pkl --E-window 21337,192036 \\
        --material E=43103,stiffness_slope_1=0.9055 --material E=62424 [--body "without camera 0"] [--device cuda:0]
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import time

import numpy as np


def _material(text: str) -> dict:
    out = {}
    for item in text.split(","):
        k, sep, v = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"--material wants KEY=VALUE[,KEY=VALUE...], got {text!r}")
        out[k.strip()] = float(v)
    if "E" not in out:
        raise argparse.ArgumentTypeError(f"--material needs E (Pa), got {text!r}")
    return out


def main(argv=None) -> int:
    from empm_gym.identification.doctor import DoctorConfig
    from empm_gym.identification.doctor.core import _Fit, _clock, _per_frame_losses, _simulate_fits, heldout_objective
    from empm_gym.sim import MaterialConfig
    from empm_gym.sim.effects import BASE_TABLE_FRICTION, EFFECTS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("problem", help="a problem pickle of bench_doctor.py --make")
    p.add_argument("--E-window", dest="window", required=True,
                   help="LO,HI: the diagnosis's E window (Pa), which sets its clock (doctor.json: base.E_window)")
    p.add_argument("--material", type=_material, action="append", required=True,
                   help="KEY=VALUE,...: a material to simulate (E and effect parameters, SI); repeatable")
    p.add_argument("--body", default=None, help="a body rebuilt without a camera (its label), else the doctor's")
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    lo, hi = (float(v) for v in args.window.split(","))

    with open(args.problem, "rb") as f:
        prob = pickle.load(f)
    cfg = DoctorConfig()
    obs = prob["obs"]
    scene = dataclasses.replace(prob["scene"], device=args.device, motion_margin=cfg.motion_margin)
    if args.body is not None:
        bodies = dict(prob.get("view_bodies", ()))
        if bodies.get(args.body) is None:
            raise SystemExit(f"no body {args.body!r} in {args.problem}; it holds {sorted(bodies)}")
        scene = dataclasses.replace(bodies[args.body], device=args.device, motion_margin=scene.motion_margin)
    base = MaterialConfig(E=(lo * hi) ** 0.5, nu=0.3, density=1000.0, params={"friction": BASE_TABLE_FRICTION})
    clock = _clock(list(EFFECTS), base, (lo, hi), scene.dx)
    scene = dataclasses.replace(scene.with_material(base, table_friction=BASE_TABLE_FRICTION), dt_materials=clock)
    T = obs.num_frames if scene.num_frames is None else min(obs.num_frames, scene.num_frames)
    F = int(round(cfg.train_fraction * T))
    fits = [_Fit(name=str(m), params=m, material=base.replace(**m), friction=BASE_TABLE_FRICTION, fit_loss=0.0,
                 wall_s=0.0, scene=scene) for m in args.material]
    t0 = time.perf_counter()
    X = _simulate_fits(fits, T)
    objective = heldout_objective(scene, obs, T, cfg)
    print(f"{args.body or 'the doctor’s body'}: {len(scene.particles)} particles, {T} frames (fitting 0-{F - 1}), "
          f"E window {lo:.6g}-{hi:.6g} Pa")
    for f, w in zip(fits, range(len(fits))):
        pf = _per_frame_losses(objective, X[:, w])
        print(f"{f.name}: fitting {np.mean(pf['loss'][:F]):.5f}, held out {np.mean(pf['loss'][F:]):.5f}; held-out "
              f"Chamfer {np.round(pf['chamfer'][F:] * 1e3, 1)} mm, tracks {np.round(pf['track_median'][F:] * 1e3, 1)} mm")
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
