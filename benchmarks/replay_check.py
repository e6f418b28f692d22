"""Replay consistency of a synthetic recording: does the loaded Scene, simulated at the TRUE parameters,
reproduce the recording?

    python benchmarks/replay_check.py REC_DIR [--dx 0.01]

Reads ``ground_truth.json`` and the debug file ``ground_truth_particles.npz`` that ``empm synth`` writes
(neither is ever read by identification) and prints per frame:

- ``o2p true``: obs -> pred Chamfer (m) of the synthesiser's own particles: the floor set by the
  observation model (surface vs particle centres, depth noise);
- ``o2p loaded``: the same for the loaded scene simulated at the true parameters;
- ``drift``: mean distance (m) between the synthesiser's particles and the same particles replayed
  through the loaded scene (its controls, table, grid, end-effectors): 0 when the replay is exact;
- the volumes of the true and of the loaded (filled) body.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rec_dir")
    p.add_argument("--dx", type=float, default=0.01)
    p.add_argument("--every", type=int, default=3, help="print every n-th frame")
    args = p.parse_args(argv)

    from empm_gym.identification.data import load_recording
    from empm_gym.identification.losses import chamfer_numpy
    from empm_gym.identification.problem import simulate_frames
    from empm_gym.sim import MaterialConfig

    rec = Path(args.rec_dir)
    gt = json.loads((rec / "ground_truth.json").read_text())
    m = gt["material"]
    true = MaterialConfig(E=m["E"], nu=m["nu"], density=m["density"], yield_stress=m["yield_stress"])
    scene, obs, _ = load_recording(rec, dx=args.dx, material=true, table_friction=gt["table_friction"],
                                   progress=False)
    G = np.load(rec / "ground_truth_particles.npz")
    Xt = G["positions"]
    replay = dataclasses.replace(scene, particles=Xt[0].astype(np.float64), volumes=G["volumes"].astype(np.float64))
    Xl = simulate_frames(scene, [true])[:, 0]
    Xr = simulate_frames(replay, [true])[:, 0]
    print(f"{rec}: table at {scene.table.height * 1000:.2f} mm (true 0), body volume loaded "
          f"{scene.volumes.sum() * 1e6:.1f} cm^3, true {G['volumes'].sum() * 1e6:.1f} cm^3; "
          f"particles loaded {len(scene.particles)}, true {Xt.shape[1]}")
    print(f"{'frame':>5s} {'o2p true':>9s} {'o2p loaded':>10s} {'drift':>8s}")
    for t in range(0, obs.num_frames, max(1, args.every)):
        o = obs.points[t]
        print(f"{t:5d} {chamfer_numpy(Xt[t], o, direction='obs_to_pred'):9.4f} "
              f"{chamfer_numpy(Xl[t], o, direction='obs_to_pred'):10.4f} "
              f"{np.linalg.norm(Xr[t] - Xt[t], axis=1).mean():8.5f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
