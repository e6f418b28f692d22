"""Adam fits of E and their intervals with the scan across the box (``uncertainty.SCAN_POINTS``), on the
doctor's benchmark problems (``bench_doctor.py --make``'s pickles, ``.pkl`` or ``.pkl.gz``).

    python benchmarks/bench_scan.py --problems DIR [--device cuda:0] [--iters 30] [--start 1e5] [--jsonl ROWS]

Each problem's base model (E alone, elastic; the table's friction and density as the doctor assumes them) is
fitted by Adam on the first 70 % of frames from ``--start`` Pa (``empm identify``'s default start, 1e5 Pa),
then :func:`~empm_gym.identification.uncertainty.assess_fit` gives its interval with the problem's bodies rebuilt
without each camera and trimmed, once without the scan and once with it. Only problems without an effect
(``truth`` "none") are fitted: for them the elastic model is the true one, and the truth (``base_params``,
read here for scoring only, at the doctor's density) is what the interval should hold. Prints a table: the fit,
the interval and whether it is determined without and with the scan, what the scan found, the truth, and the
seconds each took.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _load(path: Path) -> dict:
    with (gzip.open(path, "rb") if path.suffix == ".gz" else open(path, "rb")) as f:
        return pickle.load(f)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--problems", required=True, help="folder of bench_doctor.py --make problems")
    p.add_argument("--device", default="cpu")
    p.add_argument("--iters", type=int, default=30, help="Adam steps (identify's default: 30)")
    p.add_argument("--start", type=float, default=1e5, help="starting E [Pa] (identify's default: 1e5)")
    p.add_argument("--jsonl", default=None, help="append one row per problem here")
    args = p.parse_args(argv)

    import empm_gym.identification.uncertainty as U
    from bench_doctor import DOCTOR_DENSITY, problem_object
    from empm_gym.perception.synth import effect_material
    from empm_gym.identification.offline import identify

    paths = sorted(q for q in Path(args.problems).iterdir() if q.name.endswith((".pkl", ".pkl.gz")))
    if not paths:
        raise SystemExit(f"{args.problems}: no .pkl or .pkl.gz problems")
    print(f"{'problem':58s} {'fit E':>9s} {'interval, no scan':>22s} {'det':>4s} {'interval, scan':>22s} "
          f"{'det':>4s} {'rivals':>6s} {'truth':>9s} {'fit s':>6s} {'int s':>11s}")
    for path in paths:
        prob = _load(path)
        if prob.get("truth") != "none":
            continue
        dev = args.device
        scene = dataclasses.replace(prob["scene"], device=dev)
        others = [(label, None if sc is None else dataclasses.replace(sc, device=dev))
                  for label, sc in prob.get("view_bodies", ())]
        if prob.get("trimmed_body"):
            label, sc = prob["trimmed_body"]
            others.append((label, None if sc is None else dataclasses.replace(sc, device=dev)))
        obs = prob["obs"]
        F = max(2, int(round(0.7 * obs.num_frames)))
        t0 = time.perf_counter()
        r = identify(obs, scene, params=("E",), method="adam", init={"E": args.start}, iters=args.iters, frames=F,
                     progress=False)
        t_fit = time.perf_counter() - t0
        out, secs = {}, []
        for n in (0, U.SCAN_POINTS):
            keep = U.SCAN_POINTS
            U.SCAN_POINTS = n
            t0 = time.perf_counter()
            try:
                out[n] = U.assess_fit(r, scene, obs, other_bodies=others)
            finally:
                U.SCAN_POINTS = keep
            secs.append(time.perf_counter() - t0)
        obj = problem_object(path, prob)
        mat = effect_material(obj, "none", None, **(prob.get("base_params") or {}))[0] if obj else None
        truth = float(mat.E) * DOCTOR_DENSITY / float(mat.density) if mat is not None else float("nan")
        u0, u1 = out[0]["uncertainty"]["E"], out[U.SCAN_POINTS]["uncertainty"]["E"]
        rivals = [w for w in out[U.SCAN_POINTS]["identifiability"]["warnings"] if "a scan across the search box" in w]
        fmt = lambda iv: f"{iv[0]:.4g}-{iv[1]:.4g}"
        print(f"{path.name[:58]:58s} {r.params['E']:9.4g} {fmt(u0['interval']):>22s} {str(u0['determined'])[0]:>4s} "
              f"{fmt(u1['interval']):>22s} {str(u1['determined'])[0]:>4s} {len(rivals):6d} {truth:9.4g} "
              f"{t_fit:6.1f} {secs[0]:5.1f}/{secs[1]:5.1f}")
        for w in rivals:
            print(f"    {w}")
        if args.jsonl:
            with open(args.jsonl, "a") as f:
                f.write(json.dumps({"problem": path.name, "device": dev, "iters": args.iters, "start": args.start,
                                    "fit_E": r.params["E"], "fit_loss": r.loss, "truth_E": truth,
                                    "no_scan": u0, "scan": u1, "scan_rivals": rivals,
                                    "method": out[U.SCAN_POINTS]["identifiability"]["method"],
                                    "fit_s": t_fit, "intervals_s": secs[0], "intervals_with_scan_s": secs[1]}) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
