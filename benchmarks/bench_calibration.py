"""A rig's calibration and depth errors, what the loader measures of them and what its correction leaves.

For each object, script, error size and seed, ``empm synth`` writes a two-frame recording whose cameras' poses are
off by ``--calibration-error M DEG`` and whose depths are scaled by ``1 +- FRAC`` (random directions and signs per
camera), with the synthesiser's particles kept for scoring only. The loader's checks run on it as a user's
recording would be read (:func:`empm_gym.identification.data.open_recording`): the cameras against each other
(:func:`empm_gym.perception.fusion.camera_agreement`) and the rig against the controls
(:func:`empm_gym.perception.fusion.end_effector_agreement`), then the in-memory correction
(:func:`empm_gym.perception.fusion.refine_calibration`). Scored against the truth: how far the frame-0 object points
of all cameras lie from the true body's surface (median absolute and 90th percentile of the distance, m), with the
recorded poses and with the corrected ones. Prints one row per recording and a summary per error size:

    python benchmarks/bench_calibration.py --objects dough,rope,lump --scripts press-release,squeeze-lift,drag \\
        --errors 0,0,0 0.001,0.1,0.003 0.003,0.3,0.01 0.005,0.5,0.02 --seeds 2 --jsonl out.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def surface_distance(points: np.ndarray, true_x: np.ndarray) -> np.ndarray:
    """Unsigned distance [m] of each point to the true particle body's surface (its boundary particles half a
    spacing outward, :func:`empm_gym.identification.offline.body_surface`), along that surface's normal."""
    from scipy.spatial import cKDTree

    from empm_gym.identification.offline import body_surface

    S, n = body_surface(true_x, normals=True)
    _, i = cKDTree(S).query(points)
    return np.abs(np.einsum("ij,ij->i", points - S[i], n[i]))


def measure(rec_dir: Path) -> dict:
    from empm_gym.identification.data import open_recording
    from empm_gym.perception.fusion import frame_points, voxel_downsample
    from empm_gym.perception.recording import Recording

    true_x = np.load(rec_dir / "ground_truth_particles.npz")["positions"][0]
    recorded = Recording(rec_dir)
    d0 = surface_distance(voxel_downsample(frame_points(recorded, 0), 0.002), true_x)
    info = {}
    t0 = time.perf_counter()
    rec = open_recording(rec_dir, info=info)
    wall = time.perf_counter() - t0
    d1 = surface_distance(voxel_downsample(frame_points(rec, 0), 0.002), true_x)
    cal = info["calibration"]
    ee, ee_after = cal["end_effectors"], cal["end_effectors_after"]
    return {"cameras_before_m": cal["before"]["largest_offset_m"],
            "cameras_after_m": (cal["after"] or cal["before"])["largest_offset_m"],
            "tolerance_m": cal["before"]["tolerance_m"],
            "rig_before_m": ee["offset_norm_m"] if ee else None,
            "rig_trusted": bool(ee and ee["trusted"]),
            "rig_after_m": (ee_after or ee or {}).get("offset_norm_m"),
            "applied": cal["applied"], "rig_shifted": cal["rig_shift_m"] is not None,
            "surface_median_before_m": float(np.median(d0)), "surface_p90_before_m": float(np.percentile(d0, 90)),
            "surface_median_after_m": float(np.median(d1)), "surface_p90_after_m": float(np.percentile(d1, 90)),
            "check_wall_s": wall}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--objects", default="dough,rope,lump")
    p.add_argument("--scripts", default="press-release,squeeze-lift,drag")
    p.add_argument("--errors", nargs="+", default=["0,0,0", "0.001,0.1,0.003", "0.003,0.3,0.01", "0.005,0.5,0.02"],
                   help="error sizes, each M,DEG,FRAC: translation (m), rotation (deg), depth bias")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--first-seed", type=int, default=3)
    p.add_argument("--width", type=int, default=848)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--jsonl", default=None, help="append one JSON row per recording here")
    args = p.parse_args(argv)
    from empm_gym.perception.synth import synthesize

    errors = [tuple(float(v) for v in e.split(",")) for e in args.errors]
    if any(len(e) != 3 for e in errors):
        raise SystemExit("--errors: each size is M,DEG,FRAC")
    rows = []
    print(f"{'recording':44s} {'cameras mm':>12s} {'rig mm':>12s} {'corrected':>10s} "
          f"{'surface median mm':>18s} {'surface p90 mm':>15s}")
    with tempfile.TemporaryDirectory() as tmp:
        for obj in args.objects.split(","):
            for script in args.scripts.split(","):
                for err in errors:
                    for seed in range(args.first_seed, args.first_seed + args.seeds):
                        name = f"{obj}-{script}-{seed}-cal{1e3 * err[0]:g}mm{err[1]:g}deg-bias{100 * err[2]:g}pc"
                        rec = synthesize(Path(tmp) / name, obj, script=script, effect="none", frames=2, cameras=3,
                                         width=args.width, height=args.height, seed=seed, progress=False,
                                         overwrite=True, debug_particles=True, calibration_error=err[:2],
                                         depth_bias=err[2])
                        r = {"recording": name, "object": obj, "script": script, "seed": seed,
                             "calibration_error": list(err[:2]), "depth_bias": err[2], **measure(rec)}
                        rows.append(r)
                        mm = lambda v: "   -" if v is None else f"{1e3 * v:4.2f}"  # noqa: E731
                        print(f"{name:44s} {mm(r['cameras_before_m']):>5s} -> {mm(r['cameras_after_m']):>4s} "
                              f"{mm(r['rig_before_m']):>5s} -> {mm(r['rig_after_m']):>4s} "
                              f"{('yes' if r['applied'] else 'no'):>10s} "
                              f"{mm(r['surface_median_before_m']):>9s} -> {mm(r['surface_median_after_m']):>4s} "
                              f"{mm(r['surface_p90_before_m']):>6s} -> {mm(r['surface_p90_after_m']):>4s}", flush=True)
                        if args.jsonl:
                            with open(args.jsonl, "a") as f:
                                f.write(json.dumps(r) + "\n")
    print("\nby error size (medians over recordings): corrected / surface median and p90 before -> after [mm]")
    for err in errors:
        sel = [r for r in rows if tuple(r["calibration_error"]) + (r["depth_bias"],) == err]
        med = lambda k: 1e3 * float(np.median([r[k] for r in sel]))  # noqa: E731
        print(f"  {1e3 * err[0]:g} mm, {err[1]:g} deg, depth {100 * err[2]:g} %: corrected "
              f"{sum(r['applied'] for r in sel)} of {len(sel)}; surface median {med('surface_median_before_m'):.2f} -> "
              f"{med('surface_median_after_m'):.2f}, p90 {med('surface_p90_before_m'):.2f} -> "
              f"{med('surface_p90_after_m'):.2f}; check {np.median([r['check_wall_s'] for r in sel]):.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
