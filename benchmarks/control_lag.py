"""The doctor's control-lag check (:func:`empm_gym.identification.doctor.features.control_lag`) on recordings as
they are and with their controls moved in time: does it read a lag that is there, and none that is not?

    python benchmarks/control_lag.py REC_DIR [REC_DIR ...] [--shifts -1,-0.5,0.5,1] [--out rows.jsonl]

For each recording (those whose grippers never close on the object read "undetermined") the lag is estimated
from the recording as it is, then with the controls' positions read ``shift`` frames later
(:func:`~empm_gym.identification.data.delayed_positions` and ``delayed_orientations`` by ``-shift``): the images then show the gripper's
effect ``shift`` frames after the controls say it happened, a lag of ``shift`` to recover. Reads only what the
doctor reads (images, depth, masks, tracks, controls); the table prints the estimate, its 95 % interval, and
whether the doctor would report it (:func:`~empm_gym.identification.doctor.core.lag_note`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    from tqdm import tqdm

    from empm_gym.identification.data import delayed_orientations, delayed_positions, load_recording
    from empm_gym.identification.doctor.core import CONTACT_GAP_M, _ee_orientations, _ee_sizes, lag_note
    from empm_gym.identification.doctor.features import control_lag

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recordings", nargs="+")
    ap.add_argument("--shifts", default="-1,-0.5,0.5,1", help="control shifts [frames] to add (comma-separated)")
    ap.add_argument("--out", default=None, help="write one JSON line per recording and shift")
    ap.add_argument("--world-axes", action="store_true",
                    help="ignore the controls' orientations (as before session 51): a turning gripper's material "
                         "is then taken in the world's axes")
    args = ap.parse_args(argv)
    shifts = [0.0] + [float(s) for s in args.shifts.split(",") if s.strip()]
    rows = []
    print(f"| recording | shift [frames] | lag read [frames] | 95 % interval | slip share | samples | reported |")
    print("|---|---:|---:|---|---:|---:|---|")
    for rec in tqdm(args.recordings, desc="recordings", leave=False):
        t0 = time.perf_counter()
        scene, obs, _ = load_recording(rec, dx=0.01, progress=False, warn=False)
        if obs.tracks is None or scene.ee_positions is None:
            print(f"| {Path(rec).name} | | no tracks or controls | | | | |")
            continue
        T = len(obs.points)
        for s in shifts:
            ee = delayed_positions(scene.ee_positions[:T], -s)  # read s frames later
            q = _ee_orientations(scene, T)
            q = None if q is None or args.world_axes else delayed_orientations(q, -s)
            r = control_lag(obs.tracks, obs.visibility, ee, scene.ee_grip[:T], _ee_sizes(scene), obs.points[:T],
                            contact_dist_m=CONTACT_GAP_M, ee_orientations=q)
            note = lag_note(r, obs.fps)
            rows.append({"recording": Path(rec).name, "shift_frames": s, **r, "reported": note is not None,
                         "load_s": time.perf_counter() - t0})
            if not r["samples"] or not np.isfinite(r["lag_frames"]):
                print(f"| {Path(rec).name} | {s:+.1f} | undetermined ({r['followers']} of {r['points']} points "
                      f"move with their gripper) | | {r['slip_share']:+.3f} | {r['samples']} | no |")
                continue
            print(f"| {Path(rec).name} | {s:+.1f} | {r['lag_frames']:+.2f} | {r['lower']:+.2f} to {r['upper']:+.2f} "
                  f"| {r['slip_share']:+.3f} | {r['samples']} | {'yes' if note else 'no'} |")
    if args.out:
        with open(args.out, "w") as fh:
            for row in rows:
                fh.write(json.dumps(row) + "\n")
    done = [r for r in rows if r["samples"] and np.isfinite(r["lag_frames"])]
    for s in shifts:
        sel = [r for r in done if r["shift_frames"] == s]
        if sel:
            err = np.array([r["lag_frames"] - s for r in sel])
            print(f"shift {s:+.1f}: {len(sel)} recordings, lag read minus shift: median {np.median(err):+.2f}, "
                  f"max |.| {np.abs(err).max():.2f} frames; reported on {sum(r['reported'] for r in sel)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
