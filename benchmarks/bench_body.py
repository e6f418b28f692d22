"""How far the frame-0 body the loader builds lies from the synthesiser's: volume, extra and missing material.

Reads the problems of ``bench_doctor.py --make`` (pickled or gzipped: the doctor's scene and observations) and, for
scoring only, runs the synthesiser's own first frame for each (``ground_truth``'s object, script, seed and grid, as
``bench_doctor.py --oracle`` does). Prints one row per recording and writes them with ``--jsonl``:

    python benchmarks/bench_body.py .dd20/*.pkl.gz --object dough

Columns: particles and volume of the doctor's body against the synthesiser's; "extra", the share of the doctor's
particles over 1.5 spacings from every true particle, and of those the share within 3 cm of an end-effector (the
completion of what the end-effectors hide); "missing", the share of true particles over 1.5 spacings from every
doctor particle; "surface", the median distance of the doctor's body surface (its boundary particles half a
spacing outward, :func:`empm_gym.identification.offline.body_surface`) from the true body's (outside positive);
"observed", that of the frame-0 observed points (the synthesiser's rendering and the depth noise: what the loader
is given).
"""

from __future__ import annotations

import argparse
import gzip
import json
import pickle
import sys
from pathlib import Path
from typing import Optional

import numpy as np


def _load(path: Path) -> dict:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rb") as f:
        return pickle.load(f)


def _surface_offset(points: np.ndarray, true_x: np.ndarray) -> float:
    """Median signed distance (m, outside positive) of ``points`` from the surface of the true particle body: the
    distance to the nearest true boundary particle moved half a spacing outward, signed by the side of its normal."""
    from scipy.spatial import cKDTree

    from empm_gym.identification.offline import body_surface

    S, n = body_surface(true_x, normals=True)
    _, i = cKDTree(S).query(points)
    return float(np.median(np.einsum("ij,ij->i", points - S[i], n[i])))


def measure(path: Path, obj: str, device: str = "cpu", synth_dx: Optional[float] = None) -> dict:
    from scipy.spatial import cKDTree

    from empm_gym.identification.offline import body_surface
    from empm_gym.perception.synth import simulate
    from empm_gym.sim import MaterialConfig

    prob = _load(path)
    sc = prob["scene"]
    x = np.asarray(sc.particles, np.float64)
    vol = np.asarray(sc.volumes, np.float64) * np.ones(len(x))
    synth_dx = prob.get("synth_dx", synth_dx)
    if synth_dx is None:
        raise SystemExit(f"{path.name} does not say which grid its recording was made on (problems made before "
                         f"session 38): give it as --synth-dx")
    r = simulate(obj, MaterialConfig(), script=prob["script"], frames=2, dx=synth_dx, seed=prob["seed"],
                 device=device)
    X = r["particles"][0].astype(np.float64)
    VX = float(r["model"].particle_vol.numpy().sum())
    d0 = float(np.median(cKDTree(X).query(np.asarray(prob["obs"].points[0]))[0]))
    if d0 > synth_dx:
        raise SystemExit(f"{path.name}: the synthesiser's frame-0 body lies {1e3 * d0:.1f} mm (median) from the "
                         f"recording's frame-0 points: not this recording's object (--object {obj}?)")
    s = float(np.median(cKDTree(x).query(x, k=2)[0][:, 1]))
    extra = cKDTree(X).query(x)[0] > 1.5 * s
    missing = cKDTree(x).query(X)[0] > 1.5 * s
    near_ee = np.zeros(len(x), bool)
    pos0 = np.asarray(sc.ee_positions[0]) if sc.ee_positions is not None and len(sc.ee_configs) else np.zeros((0, 3))
    if len(pos0):
        near_ee = np.min(np.linalg.norm(x[:, None, :] - pos0[None], axis=-1), axis=1) < 0.03
    return {"recording": path.name.split(".pkl")[0], "particles": len(x), "true_particles": len(X),
            "volume_m3": float(vol.sum()), "true_volume_m3": VX, "extra": float(extra.mean()),
            "extra_near_end_effectors": float(near_ee[extra].mean()) if extra.any() else 0.0,
            "missing": float(missing.mean()),
            "observed_offset_m": _surface_offset(np.asarray(prob["obs"].points[0], np.float64), X),
            "surface_offset_m": _surface_offset(body_surface(x), X),
            "trimmed": bool(prob.get("trim_to_surface", False))}


def main(argv=None) -> int:
    from empm_gym.perception.synth import OBJECT_DEFAULTS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("problems", nargs="+", help="bench_doctor.py --make problems (.pkl or .pkl.gz)")
    p.add_argument("--object", required=True, choices=sorted(OBJECT_DEFAULTS))
    p.add_argument("--device", default="cpu")
    p.add_argument("--synth-dx", type=float, default=None,
                   help="the synthesiser's grid (m) for problems that do not record it (made before session 38)")
    p.add_argument("--jsonl", default=None, help="append one JSON line per recording to this file")
    args = p.parse_args(argv)
    print(f"{'recording':48s} {'particles':>13s} {'volume cm^3':>15s} {'extra':>6s} {'near EE':>7s} {'missing':>7s} "
          f"{'surface':>9s} {'observed':>9s}")
    for f in args.problems:
        row = measure(Path(f), args.object, args.device, args.synth_dx)
        print(f"{row['recording']:48s} {row['particles']:6d}/{row['true_particles']:6d} "
              f"{1e6 * row['volume_m3']:7.1f}/{1e6 * row['true_volume_m3']:6.1f} {100 * row['extra']:5.1f}% "
              f"{100 * row['extra_near_end_effectors']:6.0f}% {100 * row['missing']:6.1f}% "
              f"{1e3 * row['surface_offset_m']:+7.2f}mm {1e3 * row['observed_offset_m']:+7.2f}mm", flush=True)
        if args.jsonl:
            with open(args.jsonl, "a") as fh:
                fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
