"""Where a spring-mass body moves unlike our MPM base model at the same material (benchmark side: it runs both
simulators with the true material, which the doctor never sees).

    PYTHONPATH=. python benchmarks/simulator_gap.py --object dough            # every script, the object's defaults
    PYTHONPATH=. python benchmarks/simulator_gap.py --object rope --E 1e5 --jsonl gap.jsonl

For each script of :data:`empm_gym.perception.scripts.SCRIPTS` the object (elastic, table friction 0.5, rigid
grip) is simulated by :func:`empm_gym.perception.synth.simulate` with ``simulator="mpm"`` and ``"springmass"`` on
the same grid (``--dx``, the spring-mass network at half a cell) and prints, per script:

- ``gap``: the mean Chamfer distance [mm] between the two particle sets over the held-out frames (the last 30 %),
  what a recording of the spring-mass body shows that the base model at the true E does not;
- the change of the body's height (99th percentile of z) from frame 0 to the last frame [mm]: a body that stays
  pressed shows a permanent set here;
- the travel of the body's centroid on the table [mm]: a pushed or dragged body that slides or rolls farther;
- the grip's lag [mm]: how far the material within 1 cm of a closed gripper's centre when it closes has moved
  relative to the gripper by the time it opens (the largest over grippers). The MPM's closed gripper carries the
  grid nodes it covers; the spring-mass one pulls the particles it touched through control springs.

These are the differences a doctor's verdict on a spring-mass recording can describe in the MPM's terms (a
permanent set as plasticity, a compliant grip as gripper slip, a longer slide as a lower table friction):
benchmarks/RESULTS.md, session 49.
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def gaps(obj: str, E=None, *, frames: int = 30, dx: float = 0.005, seed: int = 0, scripts=None, held_out: float = 0.3):
    """One dict per script (see the module docstring)."""
    from empm_gym.identification.losses import chamfer_numpy
    from empm_gym.perception.scripts import SCRIPTS
    from empm_gym.perception.synth import effect_material, simulate

    mat = effect_material(obj, "none", E=E)[0]
    first = min(frames - 1, int(round((1.0 - held_out) * frames)))
    for script in scripts or SCRIPTS:
        runs = {s: simulate(obj, mat, script=script, frames=frames, dx=dx, seed=seed, simulator=s)
                for s in ("mpm", "springmass")}
        A, B = runs["mpm"]["particles"], runs["springmass"]["particles"]
        grip, pos = runs["mpm"]["grip"], runs["mpm"]["positions"]
        row = {"object": obj, "script": script, "E": mat.E, "dx": dx,
               "heldout_gap_mm": 1e3 * float(np.mean([chamfer_numpy(A[t], B[t]) for t in range(first, frames)]))}
        for s, X in (("mpm", A), ("springmass", B)):
            row[f"{s}_height_change_mm"] = 1e3 * float(np.percentile(X[-1, :, 2], 99) - np.percentile(X[0, :, 2], 99))
            row[f"{s}_travel_mm"] = 1e3 * float(np.linalg.norm(X[-1].mean(0)[:2] - X[0].mean(0)[:2]))
            lags = []
            for k in range(pos.shape[1]):
                closed = np.nonzero(grip[:, k] > 0)[0]
                if len(closed) < 2:
                    continue
                t0, t1 = closed[0], closed[-1]
                near = np.linalg.norm(X[t0] - pos[t0, k], axis=1) < 0.01
                if near.sum() >= 3:
                    d = (X[t1, near].mean(0) - X[t0, near].mean(0)) - (pos[t1, k] - pos[t0, k])
                    lags.append(1e3 * float(np.linalg.norm(d)))
            row[f"{s}_grip_lag_mm"] = max(lags) if lags else None
        yield row


def _mm(v):
    return "-" if v is None else f"{v:.2f}"


def main(argv=None):
    from empm_gym.perception.synth import OBJECT_DEFAULTS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--object", default="dough", choices=sorted(OBJECT_DEFAULTS))
    p.add_argument("--E", type=float, default=None, help="Young's modulus [Pa] (default: the object's)")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--dx", type=float, default=0.005, help="the MPM grid [m] (the benchmark's synthesiser: 5 mm)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scripts", default=None, help="comma-separated scripts (default: all)")
    p.add_argument("--jsonl", default=None, help="append one JSON line per script to this file")
    args = p.parse_args(argv)
    print("| object | script | held-out gap [mm] | height change MPM / spring-mass [mm] | travel MPM / spring-mass "
          "[mm] | grip lag MPM / spring-mass [mm] |\n|---|---|---:|---:|---:|---:|")
    for r in gaps(args.object, args.E, frames=args.frames, dx=args.dx, seed=args.seed,
                  scripts=args.scripts.split(",") if args.scripts else None):
        print(f"| {r['object']} | {r['script']} | {r['heldout_gap_mm']:.2f} | {r['mpm_height_change_mm']:.2f} / "
              f"{r['springmass_height_change_mm']:.2f} | {r['mpm_travel_mm']:.1f} / {r['springmass_travel_mm']:.1f} | "
              f"{_mm(r['mpm_grip_lag_mm'])} / {_mm(r['springmass_grip_lag_mm'])} |", flush=True)
        if args.jsonl:
            with open(args.jsonl, "a") as f:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
