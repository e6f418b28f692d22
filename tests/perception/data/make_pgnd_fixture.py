"""Regenerate the tiny PGND-layout episode ``pgnd_tiny/`` (run: python make_pgnd_fixture.py).

Written the way PGND (kywind/pgnd) writes an episode, in PGND's world: its calibration-board frame,
whose z axis points down into the table (table at z = 0, everything above it at z < 0).

Scene (metres): a box object [-0.04, 0.04] x [-0.03, 0.03] x [-0.04, 0] (8 x 6 x 4 cm, 192 cm^3) on the
table, two arms whose end-effector points are drawn as spheres of radius 0.02 m at ARM_POS[t, k], and
two 128x96 cameras on opposite sides looking down at the box. Files:

- camera_<i>/rgb/%06d.jpg, camera_<i>/depth/%06d.png (uint16 mm, exact ray-cast z-depth),
  camera_<i>/mask/%06d.png (box 0/255);
- calibration/intrinsics.npy [C, 3, 3], rvecs.npy and tvecs.npy [C, 3, 1]: world -> camera,
  R = Rodrigues(rvec), x_cam = R x_world + t (OpenCV);
- robot/%06d.txt: 9 rows of 3 (two arms): per arm its point, then the rows of ARM_ROT[t, k].T (the
  gripper's x, y, z axes in the world), then [gripper position arm 0, arm 1, 0] in xArm units
  (0 closed .. 800 open), written with "%.6f" as PGND does;
- timestamps.txt: per frame one timestamp (s) per camera, 30 fps.
"""

import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np

OUT = Path(__file__).parent / "pgnd_tiny"
W, H, T, C = 128, 96, 4, 2
BOX = (np.array([-0.04, -0.03, -0.04]), np.array([0.04, 0.03, 0.0]))
BOX_VOLUME_M3 = 0.08 * 0.06 * 0.04
ARM_R = 0.02
K = np.array([[120.0, 0.0, 63.5], [0.0, 118.0, 47.5], [0.0, 0.0, 1.0]])
EYES = np.array([[0.30, -0.05, -0.32], [-0.30, 0.05, -0.32]])
TARGET = np.array([0.0, 0.0, -0.02])
ARM_POS = np.array([[[0.0, 0.0, -0.20], [0.0, 0.15, -0.18]],
                    [[0.0, 0.0, -0.17], [0.01, 0.15, -0.18]],
                    [[0.0, 0.0, -0.14], [0.02, 0.15, -0.18]],
                    [[0.0, 0.0, -0.11], [0.03, 0.15, -0.18]]])
GRIPPER = np.array([[800.0, 800.0], [800.0, 401.0], [300.0, 399.0], [0.0, 0.0]])  # xArm units
GRIP_EXPECTED = np.array([[0, 0], [0, 0], [1, 1], [1, 1]])  # closed where position / 800 < 0.5
FPS = 30.0


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0], [0, 0, 1]])


# end-effector-to-world rotations (columns: the gripper's axes in PGND's world); not symmetric, so a
# reader that took the rows for columns would be caught
ARM_ROT = np.array([[rot_z(np.radians(30 + 10 * t)) @ rot_x(np.radians(15)),
                     rot_z(np.radians(-20 * t)) @ rot_x(np.radians(170))] for t in range(T)])


def world_to_camera(eye, target):
    """(R, t) with x_cam = R x_world + t, OpenCV axes, image "up" towards -z (PGND's up)."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, -1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    Rc2w = np.stack([x, y, z], 1)
    return Rc2w.T, -Rc2w.T @ eye


def rotvec(R):
    """Rotation vector (axis * angle) of a rotation matrix (angle < pi), as cv2.Rodrigues."""
    th = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    if th < 1e-12:
        return np.zeros(3)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v * th / (2 * np.sin(th))


W2C = [world_to_camera(e, TARGET) for e in EYES]


def render(R, t, arms):
    cols, rows = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    dc = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(cols)], -1)
    d = dc @ R  # world directions of the pixel rays, scaled so that the camera z component is 1
    o = -R.T @ t
    depth = np.full((H, W), np.inf)
    label = np.full((H, W), -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[2] / d[..., 2]
    ok = s > 0
    depth[ok], label[ok] = s[ok], 9  # table z = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (BOX[0] - o) / d, (BOX[1] - o) / d
    tn, tf = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    hit = (tn <= tf) & (tn > 0) & (tn < depth)
    depth[hit], label[hit] = tn[hit], 0
    for c in arms:
        oc = o - c
        a = (d * d).sum(-1)
        b = 2 * d @ oc
        disc = b * b - 4 * a * (oc @ oc - ARM_R**2)
        sh = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        hit = (sh > 0) & (sh < depth)
        depth[hit], label[hit] = sh[hit], 1
    return depth, label


def main():
    shutil.rmtree(OUT, ignore_errors=True)
    (OUT / "calibration").mkdir(parents=True)
    np.save(OUT / "calibration" / "intrinsics.npy", np.stack([K] * C))
    np.save(OUT / "calibration" / "rvecs.npy", np.stack([rotvec(R)[:, None] for R, _ in W2C]))
    np.save(OUT / "calibration" / "tvecs.npy", np.stack([t[:, None] for _, t in W2C]))
    for c, (R, tv) in enumerate(W2C):
        for sub in ("rgb", "depth", "mask"):
            (OUT / f"camera_{c}" / sub).mkdir(parents=True)
        for t in range(T):
            depth, label = render(R, tv, ARM_POS[t])
            mm = np.where(np.isfinite(depth), np.round(depth * 1000), 0).astype(np.uint16)
            color = np.zeros((H, W, 3), np.uint8)
            color[label == 9] = (150, 120, 90)
            color[label == 0] = (200, 60, 40)
            color[label == 1] = (128, 128, 128)
            iio.imwrite(OUT / f"camera_{c}" / "rgb" / f"{t:06d}.jpg", color, quality=85)
            iio.imwrite(OUT / f"camera_{c}" / "depth" / f"{t:06d}.png", mm)
            iio.imwrite(OUT / f"camera_{c}" / "mask" / f"{t:06d}.png", ((label == 0) * 255).astype(np.uint8))
    (OUT / "robot").mkdir()
    for t in range(T):
        rows = []
        for k in range(2):
            rows += [ARM_POS[t, k], *ARM_ROT[t, k].T]
        rows.append([GRIPPER[t, 0], GRIPPER[t, 1], 0.0])
        np.savetxt(OUT / "robot" / f"{t:06d}.txt", np.array(rows), fmt="%.6f")
    with open(OUT / "timestamps.txt", "w") as f:
        for t in range(T):
            f.write(" ".join(str(1700000000.0 + t / FPS + 0.002 * c) for c in range(C)) + "\n")


if __name__ == "__main__":
    main()
