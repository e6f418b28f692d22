"""Regenerate the tiny PhysTwin-layout fixture ``phystwin_tiny/`` (run: python make_phystwin_fixture.py).

Scene (metres, z up, table z = 0): a box object [-0.04, 0.04] x [-0.03, 0.03] x [0, 0.03] and a
"hand" sphere of radius 0.025 centred at HAND_CENTRES[t]; two 64x48 cameras. Written exactly as
PhysTwin's raw capture: metadata.json without depth_scale, calibrate.pkl (a pickled list of 4x4
numpy arrays), depth/<cam>/<frame>.npy in millimetres (uint16), masks as mask_info_<cam>.json +
mask/<cam>/<id>/<frame>.png, and cotracker/<cam>.npz; no controls.npz, no calibrate.json.
"""

import json
import pickle
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np

OUT = Path(__file__).parent / "phystwin_tiny"
W, H, T = 64, 48, 3
BOX = (np.array([-0.04, -0.03, 0.0]), np.array([0.04, 0.03, 0.03]))
HAND_R = 0.025
HAND_CENTRES = np.array([[0.0, 0.0, 0.08], [0.01, 0.0, 0.085], [0.02, 0.0, 0.09]])
K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])


def look_at(eye, target):
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


C2W = [look_at(np.array([0.35, -0.1, 0.3]), [0, 0, 0.02]), look_at(np.array([-0.3, 0.2, 0.35]), [0, 0, 0.02])]


def render(c2w, hand):
    cols, rows = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    d = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(cols)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    depth = np.full((H, W), np.inf)
    label = np.full((H, W), -1)
    s = -o[2] / d[..., 2]
    ok = s > 0
    depth[ok], label[ok] = s[ok], 9  # table
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (BOX[0] - o) / d, (BOX[1] - o) / d
    tn, tf = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    hit = (tn <= tf) & (tn > 0) & (tn < depth)
    depth[hit], label[hit] = tn[hit], 0
    oc = o - hand
    a = (d * d).sum(-1)
    b = 2 * d @ oc
    disc = b * b - 4 * a * (oc @ oc - HAND_R**2)
    sh = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    hit = (sh > 0) & (sh < depth)
    depth[hit], label[hit] = sh[hit], 1
    return depth, label


def main():
    shutil.rmtree(OUT, ignore_errors=True)
    OUT.mkdir(parents=True)
    json.dump({"intrinsics": [K.tolist()] * 2, "serial_numbers": ["cam_a", "cam_b"], "fps": 30, "WH": [W, H],
               "frame_num": T}, open(OUT / "metadata.json", "w"))
    with open(OUT / "calibrate.pkl", "wb") as f:
        pickle.dump([m.copy() for m in C2W], f)
    rng = np.random.default_rng(0)
    for c in range(2):
        (OUT / "mask").mkdir(exist_ok=True)
        json.dump({"0": "rope", "1": "hand"}, open(OUT / "mask" / f"mask_info_{c}.json", "w"))
        for t in range(T):
            depth, label = render(C2W[c], HAND_CENTRES[t])
            mm = np.where(np.isfinite(depth), np.round(depth * 1000), 0).astype(np.uint16)
            color = np.zeros((H, W, 3), np.uint8)
            color[label == 9] = (150, 120, 90)
            color[label == 0] = (200, 60, 40)
            color[label == 1] = (220, 180, 160)
            (OUT / "color" / str(c)).mkdir(parents=True, exist_ok=True)
            (OUT / "depth" / str(c)).mkdir(parents=True, exist_ok=True)
            iio.imwrite(OUT / "color" / str(c) / f"{t}.png", color)
            np.save(OUT / "depth" / str(c) / f"{t}.npy", mm)
            for oid, lab in (("0", 0), ("1", 1)):
                (OUT / "mask" / str(c) / oid).mkdir(parents=True, exist_ok=True)
                iio.imwrite(OUT / "mask" / str(c) / oid / f"{t}.png", ((label == lab) * 255).astype(np.uint8))
        tr = rng.uniform([0, 0], [H - 1, W - 1], (T, 5, 2)).astype(np.float32)
        vis = rng.random((T, 5)) > 0.3
        (OUT / "cotracker").mkdir(exist_ok=True)
        np.savez(OUT / "cotracker" / f"{c}.npz", tracks=tr, visibility=vis)


if __name__ == "__main__":
    main()
