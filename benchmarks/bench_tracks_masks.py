"""A 2D tracker's and a segmenter's errors: what the loader measures of them and what they leave in its points.

For each object, script, error size and seed, ``empm synth`` writes a recording whose tracks carry a tracker's
errors (``--track-error JITTER DRIFT OUTLIERS``: Gaussian jitter in pixels a frame, a random walk in pixels a frame,
a share of visible entries jumping 4-20 pixels) and whose object masks are grown by ``--mask-error PX`` pixels (onto
the background and the end-effectors), with the synthesiser's particles kept for scoring only. The loader reads it
as a user's recording (:func:`empm_gym.identification.data.load_recording`): the depth's own frame-to-frame noise
(:func:`empm_gym.perception.fusion.temporal_depth_noise`), the lifted tracks' scatter along and across their rays
and the weight they keep in the fit (:func:`empm_gym.identification.data.track_noise`). Scored against the truth:
the fused object points' distance to the true body's surface over every frame (median and 90th percentile, m),
with the recorded masks as they are, with :func:`empm_gym.perception.fusion.object_mask` (the end-effectors'
pixels given back) and as the loader gives them (also the table's rim left out,
:func:`empm_gym.perception.fusion.drop_table_rim`; ``rim`` is the share of a frame's points that goes, median);
the visible track entries over 1 cm from the true surface as lifted and as loaded (the tracked points on the table
left out, :func:`empm_gym.identification.data.tracks_on_table`), with how many were left out and how many of those
lay within 5 mm of the surface.
Prints one row per recording and a summary per error size:

    python benchmarks/bench_tracks_masks.py --objects dough,rope,lump --scripts press-release,squeeze-lift \\
        --errors 0,0,0,0 0.5,0.05,0.01,1 1,0.1,0.02,2 2,0.3,0.05,3 --jsonl out.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_calibration import surface_distance  # noqa: E402


def measure(rec_dir: Path, frames: int) -> dict:
    from empm_gym.identification.data import load_recording
    from empm_gym.perception.fusion import (estimate_table_plane, fuse_views, object_mask,
                                            remove_statistical_outliers, voxel_downsample)
    from empm_gym.perception.recording import Recording

    info = {}
    _, obs, _ = load_recording(rec_dir, dx=0.02, particles_per_cell=1, progress=False, warn=False, info=info)
    true_x = np.load(rec_dir / "ground_truth_particles.npz")["positions"]
    rec = Recording(rec_dir)
    n, off = estimate_table_plane(rec)
    out = {k: info["track_noise"][k] for k in ("depth_sigma_m", "along_ray_m", "across_ray_m", "scatter_m", "weight")}
    for label, given_back in (("raw", False), ("object_mask", True)):
        d = []
        for t in range(frames):
            masks = [object_mask(rec, c, t) if given_back else rec.mask(c, t) for c in range(rec.num_cameras)]
            p = fuse_views([rec.depth(c, t) for c in range(rec.num_cameras)], rec.cameras, masks)
            p = p[p @ n + off >= 0.0015]  # as the loader: the table's points left out
            p = remove_statistical_outliers(voxel_downsample(p, 0.003), 20, 2.0)[0]
            d.append(surface_distance(p, true_x[t]))
        d = np.concatenate(d)
        out[f"surface_median_{label}_m"] = float(np.median(d))
        out[f"surface_p90_{label}_m"] = float(np.percentile(d, 90))
    # as loaded: object_mask and the table's rim left out (fusion.drop_table_rim)
    d = np.concatenate([surface_distance(p, true_x[t]) for t, p in enumerate(obs.points[:frames]) if len(p)])
    out["surface_median_loader_m"], out["surface_p90_loader_m"] = float(np.median(d)), float(np.percentile(d, 90))
    rim = info["table_rim"]
    out["rim_share"] = float(np.median(np.array(rim["dropped"]) / np.maximum(1, rim["points"])))
    # the tracks: visible entries over 1 cm from the true surface as lifted and as loaded (the tracked points on the
    # table left out, data.tracks_on_table), and the entries left out that lay on it (under 5 mm)
    if obs.tracks is not None:
        from scipy.spatial import cKDTree

        from empm_gym.identification.data import lift_tracks
        from empm_gym.identification.offline import body_surface

        P, vis = lift_tracks(rec, frames=frames)
        kept = np.asarray(obs.visibility, bool)[:frames]
        off = {"recorded": 0, "loader": 0, "dropped": 0, "dropped_on_surface": 0}
        for t in range(frames):
            d = cKDTree(body_surface(true_x[t])).query(P[t])[0]
            gone = vis[t] & ~kept[t]
            off["recorded"] += int((vis[t] & (d > 0.01)).sum())
            off["loader"] += int((kept[t] & (d > 0.01)).sum())
            off["dropped"] += int(gone.sum())
            off["dropped_on_surface"] += int((gone & (d < 0.005)).sum())
        out.update({f"tracks_off_{k}": v for k, v in off.items()}, tracks_visible=int(vis.sum()))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--objects", default="dough,rope,lump")
    p.add_argument("--scripts", default="press-release,squeeze-lift")
    p.add_argument("--errors", nargs="+", default=["0,0,0,0", "0.5,0.05,0.01,1", "1,0.1,0.02,2", "2,0.3,0.05,3"],
                   help="error sizes, each JITTER,DRIFT,OUTLIERS,MASK_PX (px, px a frame, share, px)")
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--first-seed", type=int, default=3)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--width", type=int, default=848)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--jsonl", default=None, help="append one JSON row per recording here")
    args = p.parse_args(argv)
    from empm_gym.perception.synth import synthesize

    errors = [tuple(float(v) for v in e.split(",")) for e in args.errors]
    if any(len(e) != 4 or e[3] != int(e[3]) for e in errors):
        raise SystemExit("--errors: each size is JITTER,DRIFT,OUTLIERS,MASK_PX (MASK_PX a whole number)")
    rows = []
    print(f"{'recording':46s} {'depth mm':>8s} {'across mm':>9s} {'scatter mm':>10s} {'weight':>6s} "
          f"{'surface median mm':>26s} {'surface p90 mm':>23s} {'rim':>5s} {'tracks > 1 cm off':>18s}")
    with tempfile.TemporaryDirectory() as tmp:
        for obj in args.objects.split(","):
            for script in args.scripts.split(","):
                for err in errors:
                    for seed in range(args.first_seed, args.first_seed + args.seeds):
                        name = f"{obj}-{script}-{seed}-trk{err[0]:g}px{err[1]:g}-{100 * err[2]:g}pc-mask{int(err[3])}"
                        rec = synthesize(Path(tmp) / name, obj, script=script, effect="none", frames=args.frames,
                                         cameras=3, width=args.width, height=args.height, seed=seed, progress=False,
                                         overwrite=True, debug_particles=True, track_error=err[:3],
                                         mask_error_px=int(err[3]))
                        r = {"recording": name, "object": obj, "script": script, "seed": seed,
                             "track_error": list(err[:3]), "mask_error_px": int(err[3]), **measure(rec, args.frames)}
                        rows.append(r)
                        mm = lambda v: f"{1e3 * v:4.2f}"  # noqa: E731
                        print(f"{name:46s} {mm(r['depth_sigma_m']):>8s} {mm(r['across_ray_m']):>9s} "
                              f"{mm(r['scatter_m']):>10s} {r['weight']:6.2f} "
                              f"{mm(r['surface_median_raw_m']):>9s} -> {mm(r['surface_median_object_mask_m']):>4s} -> "
                              f"{mm(r['surface_median_loader_m']):>4s} {mm(r['surface_p90_raw_m']):>6s} -> "
                              f"{mm(r['surface_p90_object_mask_m']):>4s} -> {mm(r['surface_p90_loader_m']):>4s} "
                              f"{100 * r['rim_share']:4.1f}% {_tracks_off(r):>18s}", flush=True)
                        if args.jsonl:
                            with open(args.jsonl, "a") as f:
                                f.write(json.dumps(r) + "\n")
    print("\nby error size (medians over recordings): track weight; surface median and p90, masks as recorded -> "
          "object_mask -> as loaded (the table's rim left out) [mm]; the share of the points the rim took")
    for err in errors:
        sel = [r for r in rows if tuple(r["track_error"]) + (r["mask_error_px"],) == err]
        med = lambda k: float(np.median([r[k] for r in sel]))  # noqa: E731
        print(f"  jitter {err[0]:g} px, drift {err[1]:g} px, outliers {100 * err[2]:g} %, mask +{int(err[3])} px: "
              f"weight {med('weight'):.2f} (min {min(r['weight'] for r in sel):.2f}); surface median "
              f"{1e3 * med('surface_median_raw_m'):.2f} -> {1e3 * med('surface_median_object_mask_m'):.2f} -> "
              f"{1e3 * med('surface_median_loader_m'):.2f}, p90 {1e3 * med('surface_p90_raw_m'):.2f} -> "
              f"{1e3 * med('surface_p90_object_mask_m'):.2f} -> {1e3 * med('surface_p90_loader_m'):.2f}; rim "
              f"{100 * med('rim_share'):.1f} %; tracks > 1 cm off {_tracks_off(sel)}")
    return 0


def _tracks_off(rows) -> str:
    """'recorded -> loaded (left out, of them on the surface)': visible track entries over 1 cm from the true
    surface, summed over ``rows`` (one row or several)."""
    rows = [rows] if isinstance(rows, dict) else rows
    rows = [r for r in rows if "tracks_visible" in r]
    if not rows:
        return "-"
    total = lambda k: sum(r[k] for r in rows)  # noqa: E731
    return (f"{total('tracks_off_recorded')} -> {total('tracks_off_loader')} ({total('tracks_off_dropped')}, "
            f"{total('tracks_off_dropped_on_surface')})")


if __name__ == "__main__":
    sys.exit(main())
