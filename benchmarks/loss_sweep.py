"""The identification loss of a synthetic recording swept over one parameter (a diagnostic for biases).

    python benchmarks/loss_sweep.py REC_DIR --param E --factors 0.5,0.87,1,1.15,2
    python benchmarks/loss_sweep.py REC_DIR --param yield_stress --body both --particles-per-cell 8

Loads the recording as identification does (``load_recording``; the other parameters at their true
values from ``ground_truth.json``), simulates the fitted frames once per factor (all factors as batched
worlds) and prints, per factor x truth, the total loss and its two terms (Chamfer over frames, tracking).
``--body true`` replaces the loaded frame-0 body by the synthesiser's own particles (the debug file
``ground_truth_particles.npz``): where the minimum moves between the two bodies, the loaded body is the
cause; where it sits off the truth for both, the loss is.

``--clocks 2,6,20`` sweeps again at each of those clocks: the substeps per frame that the material with
``--param`` at that multiple of the truth needs (``Scene.dt_materials``); by default the batch's own clock, that
of its largest factor. MPM's transfers damp once per substep, so where the lowest factor moves with the clock,
a fit whose substeps follow the material it evaluates (``identify``) measures the clock as well.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rec_dir")
    p.add_argument("--param", default="E", choices=("E", "nu", "density", "yield_stress"))
    p.add_argument("--factors", default="0.5,0.75,0.87,1,1.15,1.33,2", help="multiples of the true value")
    p.add_argument("--train-fraction", type=float, default=0.7)
    p.add_argument("--dx", type=float, default=0.01)
    p.add_argument("--particles-per-cell", type=float, default=27)
    p.add_argument("--body", choices=("loaded", "true", "both"), default="both")
    p.add_argument("--device", default=None)
    p.add_argument("--clocks", default="", help="multiples of the true value whose substeps every sweep steps with "
                                                "(one sweep each; default: the largest factor's)")
    args = p.parse_args(argv)

    from empm_gym.identification.data import load_recording
    from empm_gym.identification.offline import Objective
    from empm_gym.identification.problem import simulate_frames, substeps_for
    from empm_gym.sim import MaterialConfig

    rec = Path(args.rec_dir)
    gt = json.loads((rec / "ground_truth.json").read_text())
    m = gt["material"]
    if m.get(args.param) is None:
        print(f"{rec}: the recording has no {args.param} (elastic); choose another --param", file=sys.stderr)
        return 2
    true = MaterialConfig(E=m["E"], nu=m["nu"], density=m["density"], yield_stress=m["yield_stress"])
    scene, obs, _ = load_recording(rec, dx=args.dx, particles_per_cell=args.particles_per_cell, material=true,
                                   table_friction=gt["table_friction"], device=args.device, progress=False)
    F = max(2, int(round(args.train_fraction * obs.num_frames)))
    factors = [float(f) for f in args.factors.split(",")]
    mats = [dataclasses.replace(true, **{args.param: getattr(true, args.param) * f}) for f in factors]
    bodies = []
    if args.body in ("loaded", "both"):
        bodies.append(("loaded", scene))
    if args.body in ("true", "both"):
        G = np.load(rec / "ground_truth_particles.npz")
        bodies.append(("true", dataclasses.replace(scene, particles=G["positions"][0].astype(np.float64),
                                                    volumes=G["volumes"].astype(np.float64))))
    clocks = [None] + [float(c) for c in args.clocks.split(",") if c.strip()]
    print(f"{rec}: {args.param} true {getattr(true, args.param):g}, frames 0-{F - 1}, loss x 1e3")
    print(f"{'body':7s} {'clock':>6s} {'substeps':>8s} {'factor':>6s} {'total':>8s} {'chamfer':>8s} {'tracks':>8s}")
    for name, body in bodies:
        for clock in clocks:
            sc = body if clock is None else dataclasses.replace(
                body, dt_materials=(dataclasses.replace(true, **{args.param: getattr(true, args.param) * clock}),))
            t0 = time.perf_counter()
            sub, _ = substeps_for(sc, mats, float(np.max(np.linalg.norm(sc.ee_velocities(F), axis=-1), initial=0.0)))
            X = simulate_frames(sc, mats, frames=F)
            full, cd = Objective(sc, obs, F), Objective(sc, obs, F, l_trk=0.0)
            rows = [(f, full.numpy(X[:, w]), cd.numpy(X[:, w])) for w, f in enumerate(factors)]
            best = min(rows, key=lambda r: r[1])[0]
            label = "batch" if clock is None else f"{clock:g}"
            for f, a, b in rows:
                mark = "  <- lowest" if f == best else ""
                print(f"{name:7s} {label:>6s} {sub:8d} {f:6.3g} {a * 1e3:8.4f} {b * 1e3:8.4f} {(a - b) * 1e3:8.4f}{mark}")
            print(f"        ({len(sc.particles)} particles, {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
