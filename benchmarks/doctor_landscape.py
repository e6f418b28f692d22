"""The fitting loss of doctor candidates over a lattice of (E, effect parameter), set up as the doctor's candidates
pass sets it up: its body, its shared clock, its window of E around the base fit's E, its fitting frames.

    python benchmarks/doctor_landscape.py PROBLEM.pkl[.gz] --E-base 9686.25 --candidates plasticity,fracture \
        --device cuda:0 [--json OUT.json]

PROBLEM is a problem of ``bench_doctor.py --make`` (the scene and observations the doctor reads; the script reads
nothing else of it). ``--E-base`` is the base fit's E, from a diagnosis of it (``doctor.json``: the middle of a
candidate's ``E_window`` in log E). E runs over 7 points spread in log E across the window (the probe lattice's
four among them, doctor/core.py ``_probe_points``); a yield stress over yield strains 0.01 to 1 of each E (9 values)
and the first generation's three absolute values; any other one-parameter effect over 9 values of its box. Every
point of a candidate is a world of one batched simulation. Prints a table per candidate (rows: E; columns: the
parameter's values) and, with ``--json``, writes every point and loss.

Session 71 (benchmarks/RESULTS.md) ran it on the ropes squeezed into a ring of seeds 20 and 21, with a hidden
plasticity and without an effect, to see where the plasticity candidate's search had missed its optimum.
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np


def lattice(name: str, bounds: dict, window) -> tuple:
    """(the points, the column labels, the E values) of candidate ``name``'s lattice in its box ``bounds``."""
    from empm_gym.identification.doctor import core as C

    (p,) = [k for k in bounds if k != "E"]
    lo, hi = bounds[p]
    Es = np.geomspace(window[0] * 1.01, window[1] / 1.01, 7)
    if p == "yield_stress":
        cols = [("strain", s) for s in np.geomspace(0.01, 1.0, 9)] + [("Pa", v) for v in np.geomspace(lo, hi, 5)[1:-1]]
    elif C.PARAMETERS[p].transform == "log" and lo > 0:
        cols = [("", v) for v in np.geomspace(lo, hi, 9)]
    else:
        cols = [("", v) for v in np.linspace(lo, hi, 9)]
    pts = [{"E": float(E), p: float(np.clip(v * E if kind == "strain" else v, lo, hi))} for E in Es for kind, v in cols]
    labels = [f"{v:.3g}{' strain' if kind == 'strain' else ''}" for kind, v in cols]
    return pts, labels, Es


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("problem", help="a problem of bench_doctor.py --make (.pkl or .pkl.gz)")
    ap.add_argument("--E-base", type=float, required=True, help="the base fit's E [Pa] (a diagnosis's doctor.json)")
    ap.add_argument("--candidates", default="plasticity", help="comma-separated one-parameter candidates")
    ap.add_argument("--device", default=None)
    ap.add_argument("--json", default=None, help="write every point and its loss here")
    args = ap.parse_args(argv)

    from empm_gym.identification.doctor import core as C
    from empm_gym.identification.doctor.core import DoctorConfig
    from empm_gym.identification.offline import fit_losses
    from empm_gym.sim import MaterialConfig

    path = Path(args.problem)
    if not path.is_file():
        raise SystemExit(f"{path}: no such problem file (bench_doctor.py --make writes them)")
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rb") as f:
        prob = pickle.load(f)
    scene, obs = prob["scene"], prob["obs"]
    if args.device:
        scene = dataclasses.replace(scene, device=args.device)
    cfg = DoctorConfig()
    if not args.E_base > 0:
        raise SystemExit(f"--E-base must be a positive E in Pa, got {args.E_base}")
    base = MaterialConfig(E=args.E_base, nu=0.3, density=1000.0)  # the doctor's base model (diagnose's default)
    window = (max(cfg.E_bounds[0], args.E_base / cfg.E_refit_factor), min(cfg.E_bounds[1], args.E_base * cfg.E_refit_factor))
    F = int(round(cfg.train_fraction * obs.num_frames))
    sc = dataclasses.replace(scene, dt_materials=C._clock(list(C.EFFECTS), base, window, scene.dx, cfg.viscosity_cap))
    out = {"problem": path.name, "E_base": args.E_base, "window": list(window), "fitting_frames": F}
    for name in [c.strip() for c in args.candidates.split(",") if c.strip()]:
        if name not in C.EFFECTS or len(C.candidate_params(name)) != 1:
            raise SystemExit(f"{name}: not a one-parameter candidate of the catalogue "
                             f"({', '.join(e for e in C.EFFECTS if len(C.candidate_params(e)) == 1)})")
        _, fsc, _, (_, bounds, _, _) = C._candidate_spec(name, sc, base, window, F, cfg)
        pts, labels, Es = lattice(name, bounds, window)
        t0 = time.perf_counter()
        losses = fit_losses(obs, fsc, pts, frames=F, l_trk=cfg.l_trk, max_points=cfg.max_points, seed=cfg.seed)
        wall = time.perf_counter() - t0
        L = np.asarray(losses, np.float64).reshape(len(Es), len(labels))
        print(f"\n{name} on {path.name}: fitting loss, {len(pts)} worlds in {wall:.1f} s "
              f"(E window {window[0]:.4g} to {window[1]:.4g} Pa around the base fit's {args.E_base:.4g})")
        print(f"{'E [Pa]':>10s} " + " ".join(f"{c:>13s}" for c in labels))
        for E, row in zip(Es, L):
            print(f"{E:10.4g} " + " ".join(f"{v:13.5f}" for v in row))
        i = int(np.nanargmin(L))
        print(f"lowest {L.flat[i]:.6f} at {pts[i]}")
        out[name] = {"points": pts, "losses": [float(v) for v in losses], "wall_s": wall}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    sys.exit(main())
